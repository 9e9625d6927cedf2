"""Foundation benchmark: bare physics vs the full loop, as ratios from one run.

Prints steps/s of bare ``mj_step`` on the hover world, then the real-time
factor of ``tether run hover`` without and with video, each as a ratio to the
bare physics' real-time factor. Machines here are shared: compare ratios from
the same run, not absolute numbers across runs.

    make bench            # or: .venv/bin/python bench/bench_foundation.py [--duration S]
"""

from __future__ import annotations

import argparse
import os
import tempfile
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import sim  # noqa: E402,F401  (GL backend before mujoco)
import mujoco  # noqa: E402

from sim.loop import Simulation, run  # noqa: E402
from sim.scenario import load  # noqa: E402


def bare_steps_per_second(duration_s: float) -> float:
    simulation = Simulation(load("hover"))
    model, data = simulation.world.model, simulation.world.data
    steps = int(duration_s / model.opt.timestep)
    start = time.perf_counter()
    for _ in range(steps):
        mujoco.mj_step(model, data)
    return steps / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=10.0, help="simulated seconds per measurement")
    args = parser.parse_args()
    scenario = load("hover", duration_s=args.duration)

    steps = bare_steps_per_second(args.duration)
    bare_rtf = steps * scenario.physics.timestep_s
    plain = run(scenario).metrics["real_time_factor"]
    with tempfile.TemporaryDirectory() as out:
        video = run(scenario, out, video=True).metrics["real_time_factor"]
        recorded = run(scenario, out, rrd=True).metrics["real_time_factor"]

    print(f"hover world: {scenario.robot_starts().__len__()} robots, {len(scenario.targets)} targets, "
          f"{args.duration:.0f} s simulated per row")
    print(f"{'measurement':34s} {'real-time factor':>16s} {'ratio to bare':>14s}")
    print(f"{'bare mj_step (%.0f steps/s)' % steps:34s} {bare_rtf:16.2f} {1.0:14.3f}")
    for name, rtf in (("tether run hover", plain), ("tether run hover --video", video),
                      ("tether run hover --rrd", recorded)):
        print(f"{name:34s} {rtf:16.2f} {rtf / bare_rtf:14.3f}")


if __name__ == "__main__":
    main()
