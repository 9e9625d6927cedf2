"""``tether`` command line: a thin layer over :func:`sim.loop.run`.

Exit codes: 0 completed, 1 diverged, 2 bad input (one line on stderr naming
the field and the problem; nothing written), 130 interrupted (Ctrl-C or
SIGTERM: the run stops at the next tick and writes its files, status
"interrupted").
"""

from __future__ import annotations

import argparse
import json
import math
import socket
import sys
import time
from pathlib import Path

from sim.config import ConfigError

EXIT_CODES = {"completed": 0, "diverged": 1, "interrupted": 130}
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130


class _Parser(argparse.ArgumentParser):
    """argparse, with its errors as one line (like every other refusal) and exit 2."""

    def error(self, message: str):
        _fail(f"{message} (see '{self.prog} --help')")
        raise SystemExit(EXIT_BAD_INPUT)


def _parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="tether", description="Robot teams under communication constraints, on MuJoCo.")
    sub = parser.add_subparsers(dest="command", required=True)

    run = sub.add_parser("run", help="run a scenario headless")
    run.add_argument("scenario", help="built-in scenario name (see 'tether scenarios') or a TOML file")
    run.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    run.add_argument("--duration", type=float, default=None, metavar="S", help="simulated seconds")
    run.add_argument("--out", default=None, metavar="DIR", help="output folder (default runs/SCENARIO)")
    run.add_argument("--video", action="store_true", help="write video.mp4 (offscreen EGL)")
    run.add_argument("--rrd", action="store_true", help="write run.rrd (Rerun recording)")
    run.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                     help="override a scenario value, e.g. --set strategy.speed_mps=0.3 (repeatable)")
    run.add_argument("--quiet", action="store_true", help="print only the summary line")
    _video_arguments(run, implies_video=True)
    run.add_argument("--rerun-live", action="store_true",
                     help="also stream to Rerun viewers while running (gRPC server and web viewer on --host; "
                          "writes run.rrd too; keeps serving after the run until Ctrl-C)")
    run.add_argument("--host", default="127.0.0.1",
                     help="address the --rerun-live servers listen on (default 127.0.0.1: this machine only)")
    run.add_argument("--rerun-port", default="9876", metavar="N", help="gRPC port of --rerun-live (0: any free port)")
    run.add_argument("--rerun-web-port", default="9090", metavar="N",
                     help="web viewer port of --rerun-live (0: any free port)")

    tune = sub.add_parser("tune", help="serve a live tuning page for a scenario")
    tune.add_argument("scenario", help="built-in scenario name or a TOML file")
    tune.add_argument("--host", default="127.0.0.1", help="address to listen on (default 127.0.0.1: this machine only)")
    tune.add_argument("--port", default="8765", metavar="N", help="port (default 8765; 0: any free port)")
    tune.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    tune.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                      help="override a scenario value (repeatable)")
    tune.add_argument("--view-fps", default="10", metavar="F", help="live view frames per second (default 10)")
    tune.add_argument("--speed", default="1", metavar="X",
                      help="sim speed as a multiple of real time (default 1; 0: as fast as possible)")
    tune.add_argument("--save", default=None, metavar="FILE",
                      help="where 'save as scenario TOML' writes (default runs/tune/SCENARIO_tuned.toml)")
    _video_arguments(tune, implies_video=False)

    sub.add_parser("scenarios", help="list built-in scenarios")

    compare = sub.add_parser("compare", help="seed 000's Table I: intermittent vs its two baselines over seeds "
                             "(resumable; see sim/compare.py)")
    compare.add_argument("--scenarios", nargs="+", default=["intermittent-4", "intermittent-8"], metavar="NAME",
                         help="scenarios to compare on (default: intermittent-4 intermittent-8)")
    compare.add_argument("--methods", nargs="+", default=["all_time", "random_meeting", "intermittent"],
                         metavar="KIND", help="strategy kinds (default: all_time random_meeting intermittent)")
    compare.add_argument("--seeds", type=int, default=10, help="number of seeds per method (default 10)")
    compare.add_argument("--first-seed", type=int, default=0, help="first seed (default 0)")
    compare.add_argument("--duration", type=float, default=300.0, metavar="S",
                         help="simulated seconds per trial (default 300)")
    compare.add_argument("--jobs", type=int, default=1, help="trials run in parallel processes (default 1)")
    compare.add_argument("--out", default="runs/compare", metavar="DIR",
                         help="folder of trials.jsonl, table.md, table.png (default runs/compare)")
    compare.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                         help="override a scenario value in every trial (repeatable)")
    compare.add_argument("--no-run", action="store_true", help="only print the table of the trials already run")
    return parser


def _video_arguments(parser: argparse.ArgumentParser, implies_video: bool) -> None:
    also = " (implies --video)" if implies_video else ""
    parser.add_argument("--video-fps", default=None, metavar="F", help=f"video frames per second of sim time{also}")
    parser.add_argument("--video-size", default=None, metavar="WxH", help=f"frame size in pixels, e.g. 1280x720{also}")
    parser.add_argument("--video-camera", default=None, metavar="NAME",
                        help=f"top, overview, follow:ROBOT (e.g. follow:quad0), a scene camera, or free{also}")


def _video_overrides(args: argparse.Namespace) -> list[str]:
    """--video-* flags as overrides of the scenario's [video] table (checked there)."""
    out = []
    if args.video_fps is not None:
        out.append(f"video.fps={args.video_fps}")
    if args.video_size is not None:
        width, sep, height = args.video_size.lower().partition("x")
        if not (sep and width.strip().isdigit() and height.strip().isdigit()):
            raise ConfigError("--video-size",
                              f"expected WIDTHxHEIGHT in pixels, e.g. 1280x720, got {args.video_size!r}")
        out += [f"video.width={int(width)}", f"video.height={int(height)}"]
    if args.video_camera is not None:
        out.append(f"video.camera={json.dumps(args.video_camera)}")
    return out


def _number(text: str, flag: str, kind: type = float, minimum: float = 0.0) -> float:
    try:
        value = kind(text)
    except ValueError:
        raise ConfigError(flag, f"must be {'an integer' if kind is int else 'a number'}, got {text!r}") from None
    if not value >= minimum or value != value or value == float("inf"):
        raise ConfigError(flag, f"must be at least {minimum:g}, got {text}")
    return value


def _port(text: str, flag: str, host: str = "127.0.0.1") -> int:
    """A free TCP port: ``text`` itself, or any free one for 0; ConfigError if taken."""
    port = int(_number(text, flag, int))
    if port > 65535:
        raise ConfigError(flag, f"must be at most 65535, got {port}")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        try:
            probe.bind((host, port))
        except OSError as err:
            flag = "--host" if isinstance(err, socket.gaierror) else flag
            raise ConfigError(flag, f"cannot listen on {host}:{port}: {err.strerror}") from None
        return probe.getsockname()[1]


def _fail(message: str) -> int:
    """One line on stderr naming the field and the problem; exit 2."""
    line = " ".join(str(message).split())
    print(f"tether: error: {line}", file=sys.stderr)
    return EXIT_BAD_INPUT


def _progress(fraction: float) -> None:
    print(f"\r  {100 * fraction:5.1f} %", end="", file=sys.stderr, flush=True)


def cmd_run(args: argparse.Namespace) -> int:
    from sim.scenario import load
    from sim.validate import check_output_folder

    try:
        if args.out:
            check_output_folder(args.out)  # first: a folder that cannot be written refuses the run at once
        if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
            raise ConfigError("--duration", f"must be a positive, finite number of seconds, got {args.duration}")
        video_overrides = _video_overrides(args)
        scenario = load(args.scenario, [*args.overrides, *video_overrides], seed=args.seed,
                        duration_s=args.duration)
        out = Path(args.out) if args.out else Path("runs") / scenario.name
        check_output_folder(out)
        if args.rerun_live:
            grpc_port = _port(args.rerun_port, "--rerun-port", host=args.host)
            web_port = _port(args.rerun_web_port, "--rerun-web-port", host=args.host)
    except ConfigError as err:
        return _fail(str(err))

    from sim.loop import run

    live = None
    try:
        if args.rerun_live:
            from viz.recording import LiveViewer

            live = LiveViewer(host=args.host, grpc_port=grpc_port, web_port=web_port)
            print(f"live Rerun web viewer: {live.web_url}", flush=True)
            print(f"live Rerun gRPC stream: {live.grpc_url}  (native viewer: rerun {live.grpc_url})", flush=True)
        result = run(scenario, out, video=args.video or bool(video_overrides), rrd=args.rrd or args.rerun_live,
                     live=live.stream if live else None, progress=None if args.quiet else _progress)
    except ConfigError as err:
        if live:
            live.close()
        return _fail(str(err))
    except KeyboardInterrupt:  # before the run's own handlers were in place: nothing written
        if live:
            live.close()
        print("\ntether: interrupted before the run started; nothing written", file=sys.stderr)
        return EXIT_INTERRUPTED
    if not args.quiet:
        print(file=sys.stderr)
    m = result.metrics
    rate = f"x{m['real_time_factor']:.2f}" if m.get("real_time_factor") is not None else "x-"
    print(f"{m['status']}: {m['scenario']} ({m['strategy']}), seed {m['seed']}, "
          f"{m['sim_time_s']:.1f} s simulated in {m['wall_time_s']:.1f} s ({rate} real time)")
    if m.get("message"):
        print(f"  {m['message']}")
    for name, path in result.files.items():
        print(f"  {name:10s} {path}")
    if "recording" in result.files:
        viewer = Path(sys.executable).parent / "rerun"
        command = str(viewer) if viewer.exists() else "rerun"
        print(f"  open the recording with: {command} {result.files['recording']}")
    if live and result.status != "interrupted":
        print(f"still serving the live stream ({live.web_url}); press Ctrl-C to stop", flush=True)
        try:
            while True:
                time.sleep(3600)
        except KeyboardInterrupt:
            pass
    if live:
        live.close()
    return EXIT_CODES[result.status]


def cmd_tune(args: argparse.Namespace) -> int:
    from sim.scenario import load

    try:
        overrides = [*args.overrides, *_video_overrides(args)]
        scenario = load(args.scenario, overrides, seed=args.seed)
        view_fps = _number(args.view_fps, "--view-fps", minimum=0.1)
        speed = _number(args.speed, "--speed")
        port = int(_number(args.port, "--port", int))
        _port(args.port, "--port", host=args.host)  # the address can be listened on, before anything is built
    except ConfigError as err:
        return _fail(str(err))

    from viz.tuning import serve

    def ready(server) -> None:
        print(f"tuning page: {server.url}  ({scenario.name}, strategy {scenario.strategy.kind}; Ctrl-C to stop)",
              flush=True)

    try:
        serve(scenario, args.host, port, view_fps=view_fps, speed=speed, save_path=args.save, ready=ready)
    except ConfigError as err:
        return _fail(str(err))
    except OSError as err:
        flag = "--host" if isinstance(err, socket.gaierror) else "--port"
        return _fail(f"{flag}: cannot listen on {args.host}:{port}: {err.strerror or err}")
    except KeyboardInterrupt:
        pass
    return 0


def cmd_scenarios(args: argparse.Namespace) -> int:
    from sim.scenario import builtin_scenarios

    scenarios = builtin_scenarios()
    width = max(map(len, scenarios), default=0)
    for name, description in scenarios.items():
        print(f"{name:{width}s}  {description}")
    return 0


def cmd_compare(args: argparse.Namespace) -> int:
    from sim.compare import main as compare_main

    return compare_main(args)


def main(argv: list[str] | None = None) -> int:
    try:
        args = _parser().parse_args(argv)
    except SystemExit as stop:  # --help (0) or a usage error (2, one line already printed)
        return stop.code if isinstance(stop.code, int) else EXIT_BAD_INPUT
    handlers = {"run": cmd_run, "tune": cmd_tune, "scenarios": cmd_scenarios, "compare": cmd_compare}
    try:
        return handlers[args.command](args)
    except KeyboardInterrupt:
        print("\ntether: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED


if __name__ == "__main__":
    sys.exit(main())
