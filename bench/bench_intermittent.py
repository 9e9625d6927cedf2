"""Planning cost of the intermittent paper's team planner (Algorithm 1) on the paper's task.

For 2-robot teams (rings G_T^1 and the 4-robot ring) and 4-robot teams (T_5
of G_T^2), in the indoor office with the paper's 8 targets and EKF prior,
at the strategy's default samples (``team_samples``: n_sample for 2 robots,
n_sample * n / 2 for n > 2), it times ``plan_meeting`` on problems like those
the robots solve in a run: members start at different free points and times
(their previous meetings), and reports

- plans found, and the planning time per team meeting (mean, max), in
  thread CPU seconds (a loaded machine stretches wall time, not CPU time);
  the compiled kernels are loaded before the first timed plan (a one-time
  cost of a process, reported apart);
- the share of it spent in the EKF cost evaluation (Algorithm 4);
- the time the robots then take to reach the next meeting (t_f - t_0 at
  0.1 m/s, simulated seconds) and the ratio plan time / travel time: a team
  plans while it is together, so planning must be much shorter than the
  segment it plans (the loop is synchronous; on robots the plan would run
  while they drive their other team's segment).

Also the all_time baseline's formation planner (8 sensors on one point).
Usage: ``python bench/bench_intermittent.py [--plans N] [--n-sample S]``;
other benchmarks call :func:`plan_times`.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import mujoco  # noqa: E402
import numpy as np  # noqa: E402

import sim  # noqa: E402,F401
from controllers.intermittent.params import IntermittentParams  # noqa: E402
from controllers.intermittent.planner import PlannerParams, PlanningProblem, plan_meeting  # noqa: E402
from controllers.intermittent.planner_geometry import points_free  # noqa: E402
from controllers.intermittent.runtime import team_samples  # noqa: E402
from estimation.ekf import paper_prior  # noqa: E402
from estimation.target_motion import TargetMotion  # noqa: E402
from sim.geometry import Boxes  # noqa: E402
from sim.scenario import load  # noqa: E402
from sim.targets import target_path  # noqa: E402
from sim.world import extract_obstacles, load_scene_spec, scene_bounds  # noqa: E402

SENSOR_HEIGHT_M = 0.0555  # e-puck sensor site above the floor
CLEARANCE_M = IntermittentParams().clearance_m


def workspace():
    scenario = load("intermittent-8")
    spec = load_scene_spec(scenario.scene_path)
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    boxes = extract_obstacles(model, data)
    bounds = scene_bounds(model, boxes)[:, :2]
    reach = np.einsum("kj,kj->k", np.abs(boxes.rotations[:, 2, :]), boxes.half_sizes)
    keep = boxes.centers[:, 2] + reach > 0.5 * SENSOR_HEIGHT_M  # drop the floor slab
    boxes = Boxes(boxes.centers[keep], boxes.half_sizes[keep], boxes.rotations[keep])
    motion = TargetMotion([target_path(t) for t in scenario.targets], scenario.target_motion.step_s,
                          scenario.target_motion.noise_std_m)
    return scenario, boxes, bounds, motion


def random_free(rng, boxes, bounds, count, margin):
    out = []
    while len(out) < count:
        p = rng.uniform(bounds[0], bounds[1], size=(1, 2))
        if points_free(boxes, bounds, p, SENSOR_HEIGHT_M, margin)[0]:
            out.append(p[0])
    return np.array(out)


def planner_setup(n_sample: int | None = None):
    """(scenario, boxes, bounds, motion, PlannerParams) of the benchmark task."""
    scenario, boxes, bounds, motion = workspace()
    strategy = IntermittentParams()
    n_sample = strategy.n_sample if n_sample is None else n_sample
    params = PlannerParams(n_sample=n_sample, n_uniform=min(strategy.n_uniform, n_sample),
                           u_max=strategy.speed_mps * scenario.sensing.period_s,
                           comm_range=0.2 - strategy.link_margin_m,
                           delta=strategy.delta_m2, sensor_height=SENSOR_HEIGHT_M, robot_radius=CLEARANCE_M)
    return scenario, boxes, bounds, motion, params


def warm_up(boxes, bounds, motion, params) -> float:
    """Plan once (unreported) so the compiled kernels are loaded; returns its thread CPU s."""
    start = time.thread_time()
    bench_team(2, 1, dataclasses.replace(params, n_sample=10, n_uniform=10), boxes, bounds, motion, seed=99)
    return time.thread_time() - start


def bench_team(size, plans, params, boxes, bounds, motion, seed=0, sensor_offsets=None):
    """Rows (found, thread CPU s, EKF-cost s, travel steps, nodes) of ``plans`` plans."""
    rng = np.random.default_rng(seed)
    prior = paper_prior()
    rows = []
    for k in range(plans):
        margin = params.robot_radius
        starts = random_free(rng, boxes, bounds, size, margin)
        start_times = np.sort(rng.integers(0, 30, size=size)) if size > 1 else np.zeros(1, int)
        problem = PlanningProblem(starts, start_times, prior.mean, prior.covariance, 0, motion, boxes, bounds,
                                  target_priority=np.roll(np.arange(motion.n_targets), -k),
                                  sensor_offsets=sensor_offsets)
        cpu = time.thread_time()
        result = plan_meeting(problem, params, rng)
        cpu = time.thread_time() - cpu
        travel = (result.plan.meeting_time - start_times.min()) if result.success else np.nan
        cost_cpu = cpu * result.cost_time_share  # Alg. 4's share of the wall time, applied to CPU time
        rows.append((result.success, cpu, cost_cpu, travel, result.n_nodes))
    return rows


def summary(rows) -> dict:
    """Plans found, plan time mean/max (thread CPU s), EKF share, travel and plan/travel of bench_team rows."""
    ok = np.array([r[0] for r in rows])
    cpu = np.array([r[1] for r in rows])
    cost = np.array([r[2] for r in rows])
    travel = np.array([r[3] for r in rows], dtype=float)
    ratio = cpu[ok] / travel[ok]
    return {
        "plans": len(rows), "found": int(ok.sum()), "mean_s": float(cpu.mean()), "max_s": float(cpu.max()),
        "cost_share": float(cost.sum() / cpu.sum()),
        "travel_s": float(np.nanmean(travel)) if ok.any() else float("nan"),
        "plan_over_travel": float(np.mean(ratio)) if ok.any() else float("nan"),
        "plan_over_travel_max": float(np.max(ratio)) if ok.any() else float("nan"),
    }


def plan_times(team_size: int, n_plans: int = 8, n_sample: int | None = None, seed: int | None = None,
               setup=None) -> dict:
    """The intermittent paper's planner on the benchmark task for a team of ``team_size`` robots.

    Plans ``n_plans`` meetings from random free starts (seed: ``seed``,
    default ``team_size``) with ``team_samples(n_sample, team_size)`` samples
    (n_sample default: the strategy's). Returns a dict: plans, found (plans
    found), mean_s and max_s (plan time, thread CPU seconds), cost_share
    (share in Algorithm 4), travel_s (mean steps = s to the meeting),
    plan_over_travel (mean, and _max), n_sample (samples used) and
    warm_up_s (thread CPU s of one untimed first plan that loads the
    compiled kernels). ``setup``: a :func:`planner_setup` result to reuse.
    """
    _, boxes, bounds, motion, params = setup if setup is not None else planner_setup(n_sample)
    params = dataclasses.replace(params, n_sample=team_samples(params.n_sample, team_size))
    warm = warm_up(boxes, bounds, motion, params)
    rows = bench_team(team_size, n_plans, params, boxes, bounds, motion, seed=team_size if seed is None else seed)
    return {**summary(rows), "n_sample": params.n_sample, "warm_up_s": warm}


def report(name, result):
    print(f"| {name} | {result['n_sample']} | {result['found']}/{result['plans']} | {result['mean_s']:.2f} | "
          f"{result['max_s']:.2f} | {result['cost_share']:.0%} | {result['travel_s']:.0f} | "
          f"{result['plan_over_travel']:.3f} (max {result['plan_over_travel_max']:.3f}) |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plans", type=int, default=8, help="plans per team size (default 8)")
    parser.add_argument("--n-sample", type=int, default=IntermittentParams().n_sample,
                        help="samples of a 2-robot plan (larger teams: team_samples)")
    args = parser.parse_args()
    setup = planner_setup(args.n_sample)
    scenario, boxes, bounds, motion, params = setup
    print(f"indoor office, the paper's 8 targets and prior, n_sample = {args.n_sample} per 2 robots, "
          f"{args.plans} plans per row; plan time in thread CPU seconds")
    print()
    print("| team | samples | plans found | plan time mean (s) | max (s) | in EKF cost | travel to meeting (s) "
          "| plan / travel |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    start = time.perf_counter()
    warm = None
    for size in (2, 4):
        result = plan_times(size, args.plans, setup=setup)
        warm = result["warm_up_s"] if warm is None else warm
        report(f"{size} robots", result)
    # all_time: the 8-robot formation of intermittent-8 (0.12 m grid) planned as one point with 8 sensors.
    xy = np.array([s[:2] for _, s in scenario.robot_starts()])
    offsets = xy - xy.mean(axis=0)
    radius = float(np.linalg.norm(offsets, axis=1).max()) + CLEARANCE_M
    formation = dataclasses.replace(params, robot_radius=radius)
    rows = bench_team(1, args.plans, formation, boxes, bounds, motion, seed=8, sensor_offsets=offsets)
    report("all_time formation (8 sensors)", {**summary(rows), "n_sample": formation.n_sample})
    print()
    print(f"first plan of the process (loads the compiled kernels): {warm:.2f} s CPU; "
          f"total {time.perf_counter() - start:.0f} s wall")


if __name__ == "__main__":
    main()
