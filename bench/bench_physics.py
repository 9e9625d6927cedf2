"""Where a bare ``mj_step`` goes as the team grows: MuJoCo's own stage timers.

For ``connected-office`` with N quadrotors (default 10, 20, 35) it steps a
copy of the world's ``MjData`` bare (no tether code) and prints, per N, the
step's CPU time relative to the smallest N's, and the share of the step each
of MuJoCo's timed stages takes (``mjData.timer``), plus the share of
``mj_transmission`` (the actuators' moment arms, timed by calling it alone
on the same state; MuJoCo's timers fold it into the position stage's rest).

Each quadrotor has four thrust motors with a site transmission: MuJoCo
computes each one's moment from the site's dense 3 x nv Jacobians, so the
transmission costs O(actuators x dofs), quadratic in the team size (the
"position stage" cost at 35 robots). Usage:
``python bench/bench_physics.py [--robots 10 20 35] [--steps 400]``.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import sim  # noqa: E402,F401  (GL backend before mujoco)
import mujoco  # noqa: E402

from sim.scenario import load  # noqa: E402
from tether.runner import build_simulation  # noqa: E402

STAGES = ("mjTIMER_POS_KINEMATICS", "mjTIMER_POS_COLLISION", "mjTIMER_POS_MAKE", "mjTIMER_CONSTRAINT",
          "mjTIMER_VELOCITY", "mjTIMER_ACTUATION", "mjTIMER_ADVANCE")


def _cpu_per_call(function, model, data, calls: int) -> float:
    started = time.thread_time()
    for _ in range(calls):
        function(model, data)
    return (time.thread_time() - started) / calls


def measure(robots: int, steps: int) -> dict[str, float]:
    scenario = load("connected-office", [f"robots.0.count={robots}"], duration_s=1.0)
    world = build_simulation(scenario).world
    model, data = world.model, mujoco.MjData(world.model)
    data.qpos[:], data.qvel[:], data.ctrl[:] = world.data.qpos, world.data.qvel, world.data.ctrl
    for _ in range(50):  # past the first steps' warm caches and contacts
        mujoco.mj_step(model, data)
    for timer in data.timer:
        timer.duration, timer.number = 0.0, 0
    step_s = _cpu_per_call(mujoco.mj_step, model, data, steps)
    total = data.timer[mujoco.mjtTimer.mjTIMER_STEP].duration
    shares = {name: data.timer[getattr(mujoco.mjtTimer, name)].duration / total for name in STAGES}
    shares["mj_transmission"] = _cpu_per_call(mujoco.mj_transmission, model, data, steps) / step_s
    return {"step_s": step_s, "nu": model.nu, "nv": model.nv, **shares}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", type=int, nargs="+", default=[10, 20, 35])
    parser.add_argument("--steps", type=int, default=400)
    args = parser.parse_args()
    rows = [(n, measure(n, args.steps)) for n in args.robots]
    first = rows[0][1]["step_s"]
    print("bare mj_step of connected-office N (thread CPU time): step / the first row's, and each stage's share")
    print("| robots | actuators | dofs | step ratio | " + " | ".join(s.removeprefix("mjTIMER_").lower() for s in STAGES)
          + " | of which mj_transmission |")
    print("| --- " * (len(STAGES) + 5) + "|")
    for n, row in rows:
        print(f"| {n} | {row['nu']} | {row['nv']} | {row['step_s'] / first:.2f} | "
              + " | ".join(f"{row[s]:.0%}" for s in STAGES) + f" | {row['mj_transmission']:.0%} |")


if __name__ == "__main__":
    main()
