"""``tether`` command line: a thin layer over :func:`sim.loop.run`.

Exit codes: 0 completed, 1 diverged, 2 bad input (one line on stderr naming
the field and the problem; nothing written).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from sim.config import ConfigError


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tether", description="Robot teams under communication constraints, on MuJoCo.")
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

    sub.add_parser("scenarios", help="list built-in scenarios")
    return parser


def _fail(message: str) -> int:
    print(f"tether: error: {message}", file=sys.stderr)
    return 2


def _progress(fraction: float) -> None:
    print(f"\r  {100 * fraction:5.1f} %", end="", file=sys.stderr, flush=True)


def cmd_run(args: argparse.Namespace) -> int:
    from sim.scenario import load

    if args.duration is not None and args.duration <= 0:
        return _fail(f"--duration: must be positive, got {args.duration}")
    try:
        scenario = load(args.scenario, args.overrides, seed=args.seed, duration_s=args.duration)
    except ConfigError as err:
        return _fail(str(err))
    out = Path(args.out) if args.out else Path("runs") / scenario.name
    if out.exists() and not out.is_dir():
        return _fail(f"--out: {out} exists and is not a folder")

    from sim.loop import run

    try:
        result = run(scenario, out, video=args.video, rrd=args.rrd,
                     progress=None if args.quiet else _progress)
    except ConfigError as err:
        return _fail(str(err))
    if not args.quiet:
        print(file=sys.stderr)
    m = result.metrics
    print(f"{m['status']}: {m['scenario']} ({m['strategy']}), seed {m['seed']}, "
          f"{m['sim_time_s']:.1f} s simulated in {m['wall_time_s']:.1f} s (x{m['real_time_factor']:.2f} real time)")
    if m.get("message"):
        print(f"  {m['message']}")
    for name, path in result.files.items():
        print(f"  {name:10s} {path}")
    if "recording" in result.files:
        viewer = Path(sys.executable).parent / "rerun"
        command = str(viewer) if viewer.exists() else "rerun"
        print(f"  open the recording with: {command} {result.files['recording']}")
    return 0 if result.status == "completed" else 1


def cmd_scenarios(args: argparse.Namespace) -> int:
    from sim.scenario import builtin_scenarios

    scenarios = builtin_scenarios()
    width = max(map(len, scenarios), default=0)
    for name, description in scenarios.items():
        print(f"{name:{width}s}  {description}")
    return 0


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    handlers = {"run": cmd_run, "scenarios": cmd_scenarios}
    return handlers[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
