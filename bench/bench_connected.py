"""Benchmark of the connected strategy (seed 001): real-time factor of
``connected-office`` with 10, 20 and 35 quadrotors, and where a control tick goes.

For each team size one simulation runs ``--duration`` simulated seconds (after
``--warmup`` seconds that build the planner and plan the first paths), timing
every stage of each control tick:

- sensing: the loop's observation (states, mj_ray line of sight, link table);
- lambda2: link weights W(q) (range, line-of-sight clearance, inter-robot
  factors), Laplacian, eigendecomposition (or the estimator), f_lambda;
- forces: the exploration layer (roles, election, consensus, path
  references, f_travel / f_anchor, replanning) and the virtual dynamics;
- strategy, rest: invariant bookkeeping and the observers' ``info``;
- low-level control: the geometric controllers and mixers of all quadrotors;
- physics: the ``mj_step`` calls of the tick.

Each is printed as a ratio to bare ``mj_step`` of the same world in the same
run (a copy of the world's MjData stepped on its own for the tick's substeps,
timed right before the loop), so numbers from a shared, busy machine still
compare. The aim: the whole control stack costs no more than the physics it
drives (ratio <= 1).

    .venv/bin/python bench/bench_connected.py [--counts 10 20 35] [--duration S] [--estimator]
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import sim  # noqa: E402,F401  (GL backend before mujoco)
import mujoco  # noqa: E402
import numpy as np  # noqa: E402

from sim.loop import Simulation  # noqa: E402
from sim.scenario import load  # noqa: E402

STAGES = ("sensing", "lambda2", "forces", "strategy, rest", "low-level control", "physics")


def bare_tick_seconds(simulation: Simulation, ticks: int, restart_ticks: int = 20) -> float:
    """Wall seconds of one tick's worth of bare mj_step on a copy of the world's data.

    The copy flies open-loop (the last rotor commands held), so it is reset to
    the world's current state every ``restart_ticks`` ticks (not timed) before
    it drifts into the floor, where contacts would make it unrepresentative."""
    model = simulation.world.model
    data = mujoco.MjData(model)
    elapsed = 0.0
    for done in range(0, ticks, restart_ticks):
        mujoco.mj_copyData(data, model, simulation.world.data)
        steps = min(restart_ticks, ticks - done) * simulation.substeps
        start = time.perf_counter()
        for _ in range(steps):
            mujoco.mj_step(model, data)
        elapsed += time.perf_counter() - start
    return elapsed / ticks


def measure(count: int, duration_s: float, warmup_s: float, estimator: bool) -> dict:
    overrides = [f"robots.0.count={count}"]
    if estimator:
        overrides.append('strategy.lambda2_source="estimator"')
    simulation = Simulation(load("connected-office", overrides))
    for _ in range(int(round(warmup_s / simulation.dt))):
        simulation.tick()
    ticks = int(round(duration_s / simulation.dt))
    bare = bare_tick_seconds(simulation, ticks)
    strategy = simulation.strategy
    before = dict(strategy.timings)
    spent = dict.fromkeys(STAGES, 0.0)
    model, data = simulation.world.model, simulation.world.data
    start = time.perf_counter()
    for _ in range(ticks):
        t0 = time.perf_counter()
        observation = simulation.observe()
        t1 = time.perf_counter()
        commands = strategy.step(observation)
        t2 = time.perf_counter()
        simulation.control.apply(observation, commands)
        t3 = time.perf_counter()
        for _ in range(simulation.substeps):
            mujoco.mj_step(model, data)
        t4 = time.perf_counter()
        simulation.tick_count += 1
        simulation.time_s = simulation.tick_count * simulation.dt
        spent["sensing"] += t1 - t0
        spent["strategy, rest"] += t2 - t1
        spent["low-level control"] += t3 - t2
        spent["physics"] += t4 - t3
    wall = time.perf_counter() - start
    for stage in ("lambda2", "forces"):
        spent[stage] = strategy.timings[stage] - before[stage]
        spent["strategy, rest"] -= spent[stage]
    summary = strategy.summary()
    return {
        "count": count,
        "real_time_factor": duration_s / wall,
        "bare_real_time_factor": simulation.dt / bare,
        "ratios": {stage: spent[stage] / ticks / bare for stage in STAGES},
        "control_ratio": sum(spent[s] for s in STAGES if s not in ("physics",)) / ticks / bare,
        "lambda2_min": summary["lambda2_min"],
        "edges_mean": summary["edges_mean"],
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--counts", type=int, nargs="+", default=[10, 20, 35], help="team sizes (10 to 35)")
    parser.add_argument("--duration", type=float, default=5.0, help="simulated seconds measured per team size")
    parser.add_argument("--warmup", type=float, default=1.0, help="simulated seconds run before measuring")
    parser.add_argument("--estimator", action="store_true", help="decentralised lambda2 estimator instead of eigh")
    args = parser.parse_args()

    rows = [measure(n, args.duration, args.warmup, args.estimator) for n in args.counts]
    mode = "estimator" if args.estimator else "exact eigh"
    print(f"connected-office ({mode}), {args.duration:g} s simulated per row after {args.warmup:g} s warm-up; "
          "stage columns: time per control tick / bare mj_step time per tick (same world, same run)")
    header = ["robots", "RTF", "bare RTF", *STAGES, "control stack"]
    print(" | ".join(header))
    print(" | ".join("---" for _ in header))
    for row in rows:
        cells = [str(row["count"]), f"{row['real_time_factor']:.2f}", f"{row['bare_real_time_factor']:.1f}"]
        cells += [f"{row['ratios'][s]:.2f}" for s in STAGES]
        cells.append(f"{row['control_ratio']:.2f}")
        print(" | ".join(cells))


if __name__ == "__main__":
    main()
