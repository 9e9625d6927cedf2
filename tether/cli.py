"""``tether`` command line: a thin layer over :func:`tether.runner.run`.

Exit codes: 0 completed or time limit, 1 diverged or failed (a child process
died), 2 bad input (one line on
stderr naming the field and the problem; nothing written), 130 interrupted
(Ctrl-C or SIGTERM: the run stops at the next tick and writes its files,
status "interrupted").
"""

from __future__ import annotations

import argparse
import errno
import json
import os
import math
import socket
import sys
import time
from pathlib import Path

import tether.catalog  # noqa: F401 (registers the built-in strategies and scenarios)
from sim.config import ConfigError
from sim.strategy import Status

EXIT_CODES = {Status.COMPLETED: 0, Status.TIME_LIMIT: 0, Status.DIVERGED: 1, Status.INTERRUPTED: 130,
              Status.FAILED: 1}
EXIT_BAD_INPUT = 2
EXIT_INTERRUPTED = 130
MAX_WORKERS_PER_CORE = 4  # tether sweep --workers: trials are CPU-bound, more processes only take memory


class _Parser(argparse.ArgumentParser):
    """argparse, with its errors as one line (like every other refusal) and exit 2."""

    def parse_args(self, args=None, namespace=None):
        self._argv = list(sys.argv[1:] if args is None else args)
        return super().parse_args(args, namespace)

    def error(self, message: str):
        hint = _set_hint(getattr(self, "_argv", [])) if message.startswith("unrecognized arguments") else ""
        _fail(f"{message}{hint} (see '{self.prog} --help')")
        raise SystemExit(EXIT_BAD_INPUT)


def _set_hint(argv: list[str]) -> str:
    """'--set KEY VALUE' (a space for the '='): the one word --set takes."""
    for flag, key, value in zip(argv, argv[1:], argv[2:]):
        if flag == "--set" and "=" not in key and not value.startswith("-"):
            return f"; --set takes KEY=VALUE as one word: --set {key}={value}"
    return ""


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
    run.add_argument("--quiet", action="store_true", help="print only the summary line (no progress, no file list)")
    _scene_argument(run, "run")
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
    _scene_argument(tune, "tune")
    tune.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                      help="override a scenario value (repeatable)")
    tune.add_argument("--view-fps", default="10", metavar="F", help="live view frames per second (default 10)")
    tune.add_argument("--speed", default="1", metavar="X",
                      help="sim speed as a multiple of real time (default 1; 0: as fast as possible)")
    tune.add_argument("--save", default=None, metavar="FILE",
                      help="where 'save as scenario TOML' writes (default runs/tune/SCENARIO_tuned.toml)")
    _video_arguments(tune, implies_video=False)

    view = sub.add_parser("view", help="watch a scenario run in MuJoCo's interactive viewer (needs a display)")
    view.add_argument("scenario", help="built-in scenario name or a TOML file")
    view.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    _scene_argument(view, "view")
    view.add_argument("--duration", type=float, default=None, metavar="S", help="simulated seconds")
    view.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                      help="override a scenario value (repeatable)")
    view.add_argument("--speed", default="1", metavar="X",
                      help="sim speed as a multiple of real time (default 1; 0: as fast as possible)")

    radiomap = sub.add_parser("radiomap", help="draw the mean received power from one robot over the scene (PNG)")
    radiomap.add_argument("scenario", help="built-in scenario name or a TOML file")
    _scene_argument(radiomap, "map")
    radiomap.add_argument("--from", dest="robot", default=None, metavar="ROBOT",
                          help="the transmitting robot, a name (quad0, ground3) or an index (default 0), at its start")
    radiomap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                          help="override a scenario value, e.g. --set radio.preset=\"wifi\" (repeatable)")
    radiomap.add_argument("--out", default=None, metavar="FILE.png",
                          help="where the PNG goes (default runs/SCENARIO/radiomap.png)")
    radiomap.set_defaults(seed=None)

    sub.add_parser("scenarios", help="list built-in scenarios")

    init = sub.add_parser("init", help="write a scenario as a commented TOML file to start from "
                          "(every key with unit, default and meaning)")
    init.add_argument("scenario", help="built-in scenario name or a TOML file")
    init.add_argument("--scene", default=None, metavar="MJCF",
                      help="place it in this scene (a built-in name or an MJCF file), as 'tether run --scene' does")
    init.add_argument("--seed", type=int, default=None, help="override the scenario's seed")
    init.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                      help="override a scenario value (repeatable)")

    sweep = sub.add_parser("sweep", help="run many headless trials (a built-in sweep or a TOML file), resumable",
                           description="Run a sweep's trials on a local process pool or a Ray cluster; every "
                                       "finished trial is stored at once in DIR/trials/ (see docs/sweeps.md). "
                                       "Rerun the same command to resume.")
    sweep.add_argument("sweep", help="built-in sweep name (see 'tether sweeps') or a TOML file")
    sweep.add_argument("--out", default=None, metavar="DIR", help="results folder (one sweep per folder; required)")
    sweep.add_argument("--workers", default=None, metavar="N",
                       help="processes of the local pool (default: the machine's cores)")
    sweep.add_argument("--ray", default=None, metavar="auto|ADDRESS",
                       help="run the trials as tasks on an existing Ray cluster instead of the local pool")
    sweep.add_argument("--retry-failed", action="store_true",
                       help="also rerun the trials whose latest row failed (diverged or raised)")
    sweep.add_argument("--video", action="append", default=[], metavar="TRIAL",
                       help="also write video.mp4 for this trial (index or id; repeatable)")
    sweep.add_argument("--rrd", action="append", default=[], metavar="TRIAL",
                       help="also write run.rrd for this trial (index or id; repeatable)")
    sweep.add_argument("--list", action="store_true", help="print the trials (index, id, parameters) and exit")
    sweep.add_argument("--no-report", action="store_true", help="do not write the report at the end")

    sub.add_parser("sweeps", help="list built-in sweeps")

    report = sub.add_parser("report", help="figures and tables of a sweep's results (no simulation)",
                            description="Write DIR/report.md from a sweep's results table: the trial counts, the "
                                        "papers' figures the sweep reproduces, every numeric metric's mean +- std "
                                        "and n per grid cell (grid.csv) with the main metrics against the first "
                                        "swept key (grid.png), and with --x KEY --y METRIC [--hue KEY] a plot of "
                                        "any metric against any column (docs/sweeps.md).")
    report.add_argument("dir", metavar="DIR", help="a sweep's results folder (or a results .parquet file)")
    report.add_argument("--x", default=None, metavar="KEY", help="plot a metric against this column (a swept key as the sweep file names it, or a metric); needs --y")
    report.add_argument("--y", default=None, metavar="METRIC", help="the metric on y of the --x plot (a key of metrics.json, e.g. e_g_mean_m)")
    report.add_argument("--hue", default=None, metavar="KEY", help="the --x plot: one line per value of this column (e.g. a second swept key)")
    report.add_argument("--out", default=None, metavar="DIR", help="where the report goes (default: DIR)")
    return parser


def _scene_argument(parser: argparse.ArgumentParser, verb: str) -> None:
    parser.add_argument("--scene", default=None, metavar="MJCF",
                        help=f"{verb} the scenario in this scene (a built-in name or an MJCF file): starts, targets "
                             "and prior are placed in it, each change printed")


def _load(args: argparse.Namespace, overrides: list[str], duration_s: float | None = None):
    """The scenario the command names, placed in ``--scene`` when given; also the placement's notes."""
    from sim.scenario import load

    if args.scene is None:
        return load(args.scenario, overrides, seed=args.seed, duration_s=duration_s), []
    from tether.placement import load_in_scene

    return load_in_scene(args.scenario, args.scene, overrides, seed=args.seed, duration_s=duration_s)


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


def cmd_run(args: argparse.Namespace) -> int:
    # a signal in the set-up that is swallowed comes again (see _resend_swallowed)
    _resend.armed, _resend.thread, _resend.generation = True, None, _resend.generation + 1
    try:
        return _run_command(args)
    finally:
        _resend.armed = False


def _run_command(args: argparse.Namespace) -> int:
    from sim.validate import check_output_folder

    try:
        if args.out is not None:  # first: a folder that may not or cannot be written refuses the run at once
            check_output_folder(args.out)
        if args.duration is not None and not (math.isfinite(args.duration) and args.duration > 0):
            raise ConfigError("--duration", f"must be a positive, finite number of seconds, got {args.duration}")
        video_overrides = _video_overrides(args)
        overrides = [*args.overrides, *video_overrides]
        scenario, placement_notes = _load(args, overrides, args.duration)
        out = Path(args.out) if args.out is not None else Path("runs") / scenario.name
        check_output_folder(out)
        if args.rerun_live:
            grpc_port = _port(args.rerun_port, "--rerun-port", host=args.host)
            web_port = _port(args.rerun_web_port, "--rerun-web-port", host=args.host)
    except ConfigError as err:
        return _fail(str(err))
    for note in placement_notes:
        print(note, flush=True)

    from tether.runner import run

    live = None
    from tether.progress import RunProgress

    progress = None if args.quiet else RunProgress(scenario.duration_s)
    try:
        if args.rerun_live:
            from viz.recording import LiveViewer

            live = LiveViewer(host=args.host, grpc_port=grpc_port, web_port=web_port)
            print(f"live Rerun web viewer: {live.web_url}", flush=True)
            print(f"live Rerun gRPC stream: {live.grpc_url}  (native viewer: rerun {live.grpc_url})", flush=True)
        result = run(scenario, out, video=args.video or bool(video_overrides), rrd=args.rrd or args.rerun_live,
                     live=live.stream if live else None, progress=progress)
    except ConfigError as err:
        if progress:
            progress.close()
        if live:
            live.close()
        return _fail(str(err))
    except BaseException as error:  # noqa: BLE001
        if not _was_interrupted(error):
            raise
        _resend.armed = False
        # before the run's own handlers were in place (a KeyboardInterrupt, or what an import made of one)
        if progress:
            progress.close()
        if live:
            live.close()
        print("\ntether: interrupted before the run started; nothing written", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError:  # a full disk, a vanished folder...: main's barrier says it in one line
        if progress:
            progress.close()
        if live:
            live.close()
        raise
    if progress:
        progress.close(result.metrics)
    m = result.metrics
    rate = f"x{m['real_time_factor']:.2f}" if m.get("real_time_factor") is not None else "x-"
    print(f"{m['status']}: {m['scenario']} ({m['strategy']}), seed {m['seed']}, "
          f"{m['sim_time_s']:.1f} s simulated in {m['wall_time_s']:.1f} s ({rate} real time)")
    if m.get("message") and not args.quiet:  # --quiet: the summary line alone
        print(f"  {m['message']}")
    for name, path in ({} if args.quiet else result.files).items():
        print(f"  {name:10s} {path}")
    if "recording" in result.files and not args.quiet:
        viewer = Path(sys.executable).parent / "rerun"
        command = str(viewer) if viewer.exists() else "rerun"
        print(f"  open the recording with: {command} {result.files['recording']}")
    if live and result.status != Status.INTERRUPTED:
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
    from sim.outputs import check_out_file

    try:
        overrides = [*args.overrides, *_video_overrides(args)]
        scenario, placement_notes = _load(args, overrides)
        save = args.save if args.save is not None else Path("runs") / "tune" / f"{scenario.name}_tuned.toml"
        check_out_file(save, "--save")  # the page's "save as scenario TOML" may replace only a file tether wrote
        view_fps = _number(args.view_fps, "--view-fps", minimum=0.1)
        speed = _number(args.speed, "--speed")
        port = int(_number(args.port, "--port", int))
        _port(args.port, "--port", host=args.host)  # the address can be listened on, before anything is built
    except ConfigError as err:
        return _fail(str(err))

    from tether.runner import build_simulation
    from viz.tuning import serve

    for note in placement_notes:
        print(note, flush=True)

    def ready(server) -> None:
        print(f"tuning page: {server.url}  ({scenario.name}, strategy {scenario.strategy.kind}; Ctrl-C to stop)",
              flush=True)

    try:
        serve(scenario, build_simulation, args.host, port, view_fps=view_fps, speed=speed, save_path=args.save,
              ready=ready)
    except ConfigError as err:
        return _fail(str(err))
    except OSError as err:
        flag = "--host" if isinstance(err, socket.gaierror) else "--port"
        return _fail(f"{flag}: cannot listen on {args.host}:{port}: {err.strerror or err}")
    except KeyboardInterrupt:
        pass
    return 0


def cmd_view(args: argparse.Namespace) -> int:
    if args.duration is not None and args.duration <= 0:
        return _fail(f"--duration: must be positive, got {args.duration}")
    try:
        scenario, placement_notes = _load(args, args.overrides, args.duration)
        speed = _number(args.speed, "--speed")
    except ConfigError as err:
        return _fail(str(err))
    from tether.runner import build_simulation
    from viz.viewer import needs_display, view

    problem = needs_display()
    if problem:
        return _fail(problem)
    for note in placement_notes:
        print(note, flush=True)
    print(f"MuJoCo viewer: {scenario.name} ({scenario.strategy.kind}); Space pauses, Right arrow steps a tick, "
          "close the window to quit", flush=True)
    try:
        status = view(scenario, build_simulation, speed=speed)
    except ConfigError as err:
        return _fail(str(err))
    except KeyboardInterrupt:
        return 0
    return EXIT_CODES.get(status, 0)


def cmd_radiomap(args: argparse.Namespace) -> int:
    from tether.radiomap import check_png_target, scenario_radio_map, write_radio_map_png

    try:
        scenario, placement_notes = _load(args, args.overrides)
        out = Path(args.out) if args.out else Path("runs") / scenario.name / "radiomap.png"
        check_png_target(out)
        radio, robot, obstacles = scenario_radio_map(scenario, args.robot)
    except ConfigError as err:
        return _fail(str(err))
    for note in placement_notes:
        print(note, flush=True)
    preset = scenario.radio.preset
    if scenario.radio.is_ideal:
        print("note: the ideal radio has no powers; the map uses the [radio] table's ieee802154 figures",
              file=sys.stderr)
        preset = "ideal (ieee802154 figures)"
    title = f"Radio map: {scenario.name} in {scenario.scene_path.stem}, {preset}, from {robot}"
    write_radio_map_png(radio, obstacles, out, title, robot)
    print(f"radio map: {out}  (sensitivity {radio.sensitivity_dbm:.1f} dBm at 50 % delivery)")
    return 0


def cmd_scenarios(args: argparse.Namespace) -> int:
    from sim.scenario import builtin_scenarios

    scenarios = builtin_scenarios()
    width = max(map(len, scenarios), default=0)
    for name, description in scenarios.items():
        print(f"{name:{width}s}  {description}")
    return 0


def cmd_init(args: argparse.Namespace) -> int:
    from tether.annotated import annotated_scenario
    from sim.scenario import SCENE_DIR

    try:
        if args.scene is not None:
            from tether.placement import load_in_scene

            scenario, notes = load_in_scene(args.scenario, args.scene, args.overrides, seed=args.seed,
                                            unplaced_ok=True)  # a file to edit even where the team fits nowhere
        else:
            from sim.scenario import load

            scenario, notes = load(args.scenario, args.overrides, seed=args.seed), []
    except ConfigError as err:
        return _fail(str(err))
    placed = f", placed in {args.scene}" if args.scene else ""
    header = [f"tether scenario: {args.scenario}{placed} (written by tether init).",
              "Run it with: tether run FILE. Every key is below, under a comment with its meaning,",
              "[unit; default; accepted range]. Unset optional keys are commented out."]
    if notes:
        header += ["", "Placed in the new scene:"] + [f"  {note}" for note in notes]
    # The scene as the user typed it (relative to where they run tether); a scene
    # file the source scenario named relative to itself is written absolute.
    scene_text = args.scene
    if scene_text is None and scenario.scene_path.parent != SCENE_DIR:
        scene_text = str(scenario.scene_path.resolve())
    sys.stdout.write(annotated_scenario(scenario, scene_text, header))
    for note in notes:
        print(note, file=sys.stderr)
    return 0


def cmd_sweep(args: argparse.Namespace) -> int:
    import os

    from tether.sweep import ProcessPool, RayCluster, RayTimeout, ResultsFolder, load_sweep, run_sweep

    engine = folder = None
    try:
        sweep = load_sweep(args.sweep, video=args.video, rrd=args.rrd)
        if args.list:
            for trial in sweep.trials:
                swept = ", ".join(f"{k}={v}" for k, v in trial.swept)
                print(f"{trial.index:5d}  {trial.trial_id}  seed {trial.seed}  {swept}")
            return 0
        if args.out is None:
            raise ConfigError("--out", "is required: the folder the results go to")
        from sim.outputs import check_out_path

        check_out_path(args.out)  # not "", /, the home folder, nor a name too long
        if args.ray is not None and args.workers is not None:
            raise ConfigError("--workers", "sizes the local pool; with --ray the cluster decides")
        cores = os.cpu_count() or 1
        workers = int(_number(args.workers, "--workers", int, minimum=1)) if args.workers else cores
        if workers > MAX_WORKERS_PER_CORE * cores:  # each worker is a process of ~200 MB
            raise ConfigError("--workers", f"must be at most {MAX_WORKERS_PER_CORE * cores} ({MAX_WORKERS_PER_CORE} "
                                           f"per core of this machine's {cores}), got {workers}")
        folder = ResultsFolder(args.out)
        folder.check(sweep)  # before connecting to anything or creating the folder
        engine = RayCluster(args.ray) if args.ray is not None else ProcessPool(workers)
        folder.claim(sweep)
    except BaseException as err:
        if engine is not None:
            engine.close()
        if folder is not None:
            folder.release()
        if isinstance(err, ConfigError):
            code = _fail(str(err))
            if isinstance(err, RayTimeout):  # ray.init's thread retries for ever and blocks the exit
                sys.stdout.flush()
                sys.stderr.flush()
                os._exit(code)
            return code
        raise
    try:
        outcome = run_sweep(sweep, folder.out, engine, retry_failed=args.retry_failed)
        report_note = ""
        if not args.no_report and outcome.results is not None:
            from tether.report import write_report

            files = write_report(folder.out)
            report_note = f"; report {files[0].parent / 'report.md'}" if files else ""
    finally:
        folder.release()
    where = f"table {outcome.results}" if outcome.results else "no rows yet"
    print(f"{sweep.name}: {outcome.finished} finished, {outcome.failed} failed, {outcome.not_run} not run "
          f"of {outcome.total}; {where}{report_note}")
    if outcome.stopped:
        print(f"stopped: {outcome.stopped}; run the same command again to resume", file=sys.stderr)
        return EXIT_CODES[Status.INTERRUPTED] if outcome.stopped == Status.INTERRUPTED else 1
    return 0 if outcome.failed == 0 else 1


def cmd_sweeps(args: argparse.Namespace) -> int:
    from tether.sweep import builtin_sweeps

    sweeps = builtin_sweeps()
    width = max(map(len, sweeps), default=0)
    for name, description in sweeps.items():
        print(f"{name:{width}s}  {description}")
    return 0


def cmd_report(args: argparse.Namespace) -> int:
    from tether.report import write_report

    given = [flag for flag, value in (("--x", args.x), ("--y", args.y)) if value is None]
    if args.hue is not None and given or len(given) == 1:
        return _fail(f"{given[0]}: the generic plot needs both --x and --y")
    try:
        files = write_report(args.dir, out=args.out, x=args.x, y=args.y, hue=args.hue)
    except ConfigError as err:
        return _fail(str(err))
    for path in files:
        print(path)
    return 0


_interrupted: list[str] = []  # the signals that interrupted the command outside a run's ticks
RESEND_AFTER_S = 2.0  # a run's set-up ends within a second of a signal it took (docs/robustness.md)
RESEND_TRIES = 5


class _Resend:
    """Whether a signal during a run's set-up is sent again when the set-up goes on (``armed``: from
    cmd_run's start until its interrupt is dealt with or the run returns)."""

    armed = False
    thread = None
    generation = 0  # one per cmd_run: a thread left from an earlier command (tests call main) sends nothing


_resend = _Resend()


def _raise_interrupt(signum, _frame) -> None:
    import signal

    _interrupted.append(signal.Signals(signum).name)
    if _resend.armed and _resend.thread is None:
        import threading

        _resend.thread = threading.Thread(target=_resend_swallowed, args=(signum, _resend.generation),
                                          name="resend-signal", daemon=True)
        _resend.thread.start()
    raise KeyboardInterrupt


def _signals_unraisable(default):
    """``sys.unraisablehook`` during a command: the KeyboardInterrupt of a signal this process took
    (``_interrupted``) that Python could not raise, because it landed in a ctypes or compiled callback,
    a ``__del__`` or a weakref callback (numba's LLVM object cache, during a run's set-up), is noted
    already and sent again (``_resend_swallowed``): not printed ("Exception ignored ... Traceback"
    over the command's one line). Anything else goes to ``default``."""

    def hook(unraisable) -> None:
        if isinstance(unraisable.exc_value, KeyboardInterrupt) and _interrupted:
            return
        default(unraisable)

    return hook


def _resend_swallowed(signum: int, generation: int) -> None:
    """The KeyboardInterrupt raised for a signal is lost when it lands in code that swallows
    exceptions: a ``__del__`` or a weakref callback run by the garbage collector, a ctypes or compiled
    callback, a library's broad ``except``. Python then prints "Exception ignored" (or nothing) and
    the set-up goes on. While it does, the signal is sent again; once the run's ticks have taken the
    signals (sim.loop) one more is theirs (the run ends "interrupted"), and no more is sent."""
    import signal

    for _ in range(RESEND_TRIES):
        time.sleep(RESEND_AFTER_S)
        if not _resend.armed or _resend.generation != generation:
            return
        ours = signal.getsignal(signum) is _raise_interrupt
        os.kill(os.getpid(), signum)
        if not ours:
            return


def _was_interrupted(error: BaseException) -> bool:
    """A KeyboardInterrupt, or what an extension module made of one raised in
    its import (scipy's "ImportError: initialization failed")."""
    return isinstance(error, KeyboardInterrupt) or bool(_interrupted)


def main(argv: list[str] | None = None) -> int:
    import signal
    import threading

    try:
        args = _parser().parse_args(argv)
    except SystemExit as stop:  # --help (0) or a usage error (2, one line already printed)
        return stop.code if isinstance(stop.code, int) else EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print("\ntether: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    handlers = {"run": cmd_run, "tune": cmd_tune, "view": cmd_view, "scenarios": cmd_scenarios,
                "init": cmd_init, "radiomap": cmd_radiomap, "sweep": cmd_sweep, "sweeps": cmd_sweeps,
                "report": cmd_report}
    previous = {}
    if threading.current_thread() is threading.main_thread():
        # SIGTERM as Ctrl-C in every command: a run's set-up stops at once, nothing written (its ticks
        # have their own handlers, sim.loop), a sweep's driver stops and writes its table, a listing
        # or the tuning page ends. A SIGINT ignored from the start (a shell's background job) stays so.
        _interrupted.clear()
        signals = [signal.SIGTERM] + [signal.SIGINT] * (signal.getsignal(signal.SIGINT) is not signal.SIG_IGN)
        previous = {sig: signal.signal(sig, _raise_interrupt) for sig in signals}
    unraisable = sys.unraisablehook
    sys.unraisablehook = _signals_unraisable(unraisable)
    try:
        code = handlers[args.command](args)
        sys.stdout.flush()  # here, not at exit: a closed pipe or a full disk is seen by the barrier
        return code
    except KeyboardInterrupt:
        print("\ntether: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except OSError as err:
        if _interrupted:
            print("\ntether: interrupted", file=sys.stderr)
            return EXIT_INTERRUPTED
        return _os_error(err)
    except Exception as error:  # noqa: BLE001
        if not _was_interrupted(error):
            raise
        print("\ntether: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        sys.unraisablehook = unraisable
        for sig, handler in previous.items():
            if handler is not None:
                signal.signal(sig, handler)


# errno values that say the path given is wrong (exit 2); any other OSError is a failure while writing (exit 1)
_BAD_PATH = {errno.ENAMETOOLONG, errno.ENOENT, errno.ENOTDIR, errno.EISDIR, errno.EACCES, errno.EPERM,
             errno.EROFS, errno.EEXIST, errno.ENOTEMPTY, errno.ELOOP, errno.EXDEV}


def _os_error(err: OSError) -> int:
    """The one exception barrier of every command: an OSError becomes one line
    on stderr (exit 2 for a bad path, 1 for a failure while writing), no
    traceback. stdout closed by its reader (``| head -1``) ends quietly, exit 0,
    with stdout pointed at /dev/null so that Python's flush at exit is quiet too
    (https://docs.python.org/3/library/signal.html#note-on-sigpipe)."""
    if err.filename is None:  # stdout (a pipe, /dev/full) or a socket: nothing more to write there
        _silence_stdout()
        if isinstance(err, BrokenPipeError):
            return 0
    code = EXIT_BAD_INPUT if err.errno in _BAD_PATH else 1
    try:
        _fail(f"cannot write {err.filename or 'the output'}: {err.strerror or err}")
    except OSError:
        pass
    return code


def _silence_stdout() -> None:
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError, AttributeError):
        pass


if __name__ == "__main__":
    from tether.entry import end_process

    end_process(main())
