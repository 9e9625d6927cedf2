"""Planning cost of seed 000's team planner (Algorithm 1) on the paper's task.

For 2-robot teams (rings G_T^1 and the 4-robot ring) and 4-robot teams (T_5
of G_T^2), in the indoor office with the paper's 8 targets and EKF prior,
at the default n_sample, it times ``plan_meeting`` on problems like those the
robots solve in a run: members start at different free points and times
(their previous meetings), and reports

- planning wall time per team meeting (mean, max),
- the share of it spent in the EKF cost evaluation (Algorithm 4),
- the time the robots then take to reach the next meeting (t_f - t_0 at
  0.1 m/s, simulated seconds) and the ratio plan time / travel time: a team
  plans while it is together, so planning must be much shorter than the
  segment it plans (the loop is synchronous; on robots the plan would run
  while they drive their other team's segment).

Also the all_time baseline's formation planner (8 sensors on one point).
Usage: ``python bench/bench_intermittent.py [--plans N] [--n-sample S]``.
"""

from __future__ import annotations

import argparse
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


def bench_team(size, plans, params, boxes, bounds, motion, seed=0, sensor_offsets=None):
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
        result = plan_meeting(problem, params, rng)
        travel = (result.plan.meeting_time - start_times.min()) if result.success else np.nan
        rows.append((result.success, result.wall_time_s, result.cost_time_s, travel, result.n_nodes))
    return rows


def report(name, rows):
    ok = np.array([r[0] for r in rows])
    wall = np.array([r[1] for r in rows])
    cost = np.array([r[2] for r in rows])
    travel = np.array([r[3] for r in rows], dtype=float)
    ratio = wall[ok] / travel[ok]
    print(f"| {name} | {ok.sum()}/{len(rows)} | {wall.mean():.2f} | {wall.max():.2f} | "
          f"{cost.sum() / wall.sum():.0%} | {np.nanmean(travel):.0f} | "
          f"{np.mean(ratio):.3f} (max {np.max(ratio):.3f}) |")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--plans", type=int, default=8, help="plans per team size (default 8)")
    parser.add_argument("--n-sample", type=int, default=IntermittentParams().n_sample)
    args = parser.parse_args()
    scenario, boxes, bounds, motion = workspace()
    strategy = IntermittentParams()
    params = PlannerParams(n_sample=args.n_sample, n_uniform=min(strategy.n_uniform, args.n_sample),
                           u_max=strategy.speed_mps * strategy.step_s, comm_range=0.2 - strategy.link_margin_m,
                           delta=strategy.delta_m2, sensor_height=SENSOR_HEIGHT_M, robot_radius=CLEARANCE_M)
    print(f"indoor office, the paper's 8 targets and prior, n_sample = {args.n_sample}, {args.plans} plans per row")
    print()
    print("| team | plans found | plan time mean (s) | max (s) | in EKF cost | travel to meeting (s) "
          "| plan / travel |")
    print("| --- | --- | --- | --- | --- | --- | --- |")
    start = time.perf_counter()
    for size in (2, 4):
        report(f"{size} robots", bench_team(size, args.plans, params, boxes, bounds, motion, seed=size))
    # all_time: the 8-robot formation of intermittent-8 (0.12 m grid) planned as one point with 8 sensors.
    xy = np.array([s[:2] for _, s in scenario.robot_starts()])
    offsets = xy - xy.mean(axis=0)
    radius = float(np.linalg.norm(offsets, axis=1).max()) + CLEARANCE_M
    formation = PlannerParams(**{**params.__dict__, "robot_radius": radius})
    report("all_time formation (8 sensors)",
           bench_team(1, args.plans, formation, boxes, bounds, motion, seed=8, sensor_offsets=offsets))
    print()
    print(f"total {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
