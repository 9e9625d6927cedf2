"""The intermittent paper's all-time connectivity baseline (Sec. IV-B): ``strategy.kind = "all_time"``.

"The network of N robots maintains a fixed connected configuration
throughout the whole experiment. Then, to design informative paths for this
network, we apply the RRT* algorithm to design paths for the geometric
center of this configuration, so that the uncertainty of the most uncertain
target drops below a threshold delta. Once the connected network travels
along the resulting path, the RRT* algorithm is executed again."

Here the fixed configuration is the robots' start configuration (the
scenarios start every robot in one connected cluster; a start that is not
connected is refused). Its centre is planned as a single robot by the same
Algorithm 1 (:func:`plan_meeting` with n = 1: the time-synchronisation and
connectivity conditions of the goal set (6) hold trivially, so it is RRT*
with the Algorithm 4 cost and the uncertainty goal (iii), falling back to
the next most uncertain target as in Sec. IV); the predicted readings are
those of all N robots of the formation (``PlanningProblem.sensor_offsets``),
and the collision margin is the formation's radius plus ``clearance_m``.
Every robot tracks centre(t) + its fixed offset. All robots are always
connected, so every reading is fused at once into the single belief, which
is the global one: t*(t) = t and no meeting is ever needed. That holds under
the ideal radio; under a real one the readings reach the belief the formation
plans with only as messages to its fusion robot
(:class:`controllers.task.RadioFusion`), so t*(t) may lag t.

If the planner fails ``1 + max_replans`` times, the formation drives the
geodesic path towards the most uncertain target and plans again there.
"""

from __future__ import annotations

import dataclasses
import math
import time

import numpy as np

from controllers.baselines.geodesic import GeodesicPlanner, timed_waypoints
from controllers.intermittent.params import IntermittentParams
from controllers.intermittent.planner import PlanningProblem, RobotPath, plan_meeting
from controllers.intermittent.planner_geometry import points_free
from controllers.intermittent.runtime import (
    EstimateSeries,
    PlanningWorld,
    TimedPath,
    check_time_base,
    commands_from_plane,
    lifted,
    measurement_records,
    planner_params,
    LAG_HOLD_M,
    LagHolds,
    prior_state,
    separated_references,
    team_color,
)
from controllers.intermittent.strategy import team_connected
from controllers.task import RadioFusion, neutral_prior, over_radio, target_initialiser
from estimation.beliefs import Belief
from sim.config import ConfigError
from sim.types import Commands, Decorations, Observation, SceneChange, WorldInfo, readonly
from sim.strategy import Strategy

HOLD_STEPS = 5  # steps to stay put when neither the planner nor the fallback finds a path


class AllTimeStrategy(Strategy):
    kind = "all_time"

    def __init__(self, params: IntermittentParams):
        self.params = params

    @classmethod
    def adapt_to_scene(cls, strategy_table: dict, change: SceneChange, keep: frozenset[str]) -> list[str]:
        """In another scene the EKF prior is made non-informative (:func:`controllers.task.neutral_prior`)."""
        return neutral_prior(strategy_table, change, keep)

    def reset(self, world: WorldInfo, initial: Observation, rng: np.random.Generator) -> None:
        params = self.params
        self.step_s = check_time_base(world)
        self.world = world
        self.rng = rng
        n = world.n_robots
        if not team_connected(initial.links.adjacency, tuple(range(n))):
            raise ConfigError("robots", "all_time keeps the start configuration as its formation: the robots must "
                              f"start connected (links within sensing.comm_range_m = {world.comm_range_m} m, "
                              "in line of sight)")
        self.planning = PlanningWorld.from_world(world, initial)
        xy = initial.position[:, :2]
        self.centre0 = xy.mean(axis=0)
        self.offsets = xy - self.centre0
        self.radius = float(np.linalg.norm(self.offsets, axis=1).max()) + params.clearance_m
        if not points_free(self.planning.boxes, self.planning.bounds, self.centre0[None],
                           self.planning.sensor_height, self.radius)[0]:
            raise ConfigError("robots", f"the start formation (radius {self.radius:.2f} m with clearance) "
                              "touches a wall or the scene bounds")
        self.planner = planner_params(params, world, self.planning, robot_radius=self.radius)
        self.motion = world.target_motion
        self.prior = prior_state(params, world.n_targets)
        mirror = self.planning.sensor_height if params.resolve_mirror else None
        self.belief = Belief(self.motion, self.prior, mirror, target_initialiser(params, world))
        # Under the ideal radio every reading is fused the tick it is taken (the paper's baseline); under a
        # real one the formation plans with the belief its fusion robot (nearest the centre) holds, fed
        # over the bus, and self.belief stays the fictitious global one of e_g and lambda-bar.
        self.fusion: RadioFusion | None = None
        self.plan_belief = self.belief
        if over_radio(initial):
            self.plan_belief = Belief(self.motion, self.prior, mirror, target_initialiser(params, world))
            self.fusion = RadioFusion(n, int(np.argmin(np.linalg.norm(self.offsets, axis=1))), self.plan_belief,
                                      self.belief, params.retransmit_after_s)
        self.series = EstimateSeries()
        self.geodesic = GeodesicPlanner(self.planning.boxes, self.planning.bounds, self.planning.sensor_height,
                                        self.radius)
        self.last_step: int | None = None
        self.plan_times: list[float] = []
        self.cost_times: list[float] = []
        self.plan_failures = 0
        self.plan_fallbacks = 0
        self.targets_reached: list[int] = []
        self.ticks = 0
        self.connected_ticks = 0
        self.held_ticks = 0
        self.lag_holds = LagHolds(1, world.control_period_s)  # the formation's one clock
        self.events: list[str] = []
        self._time_s = 0.0
        self._scalars = {"lambda_max_m2": float(np.linalg.eigvalsh(self.prior.covariance)[-1]),
                         "t_star_s": 0.0, "t_star_lag_s": 0.0, "local_error_m": 0.0}
        self.segment = self._plan(self.centre0, 0.0, belief_step=0)

    # ---------------------------------------------------------------- planning
    def _plan(self, start: np.ndarray, now_s: float, belief_step: int) -> TimedPath:
        params = self.params
        start_step = max(belief_step, int(math.ceil(now_s / self.step_s - 1e-9)))
        estimate = self.plan_belief.estimate(belief_step)
        problem = PlanningProblem(
            start_positions=start[None], start_times=np.array([start_step]), estimate=estimate.mean,
            covariance=estimate.covariance, belief_time=belief_step, motion=self.motion,
            boxes=self.planning.boxes, bounds=self.planning.bounds, sensor_offsets=self.offsets,
        )
        wall = cost = 0.0
        path = None
        for _ in range(1 + params.max_replans):
            result = plan_meeting(problem, self.planner, self.rng)
            wall += result.wall_time_s
            cost += result.cost_time_s
            if result.success:
                path = result.plan.paths[0]
                self.targets_reached.append(result.plan.target)
                self.events.append(f"formation planned to t = {result.plan.meeting_time * self.step_s:.0f} s "
                                   f"(target {result.plan.target}, {result.wall_time_s:.2f} s wall)")
                break
            self.plan_failures += 1
        if path is None:
            clock = time.perf_counter()
            path = self._fallback(start, start_step, estimate)
            wall += time.perf_counter() - clock
            self.plan_fallbacks += 1
            self.events.append("formation planner found no path; driving towards the most uncertain target")
        self.plan_times.append(wall)
        self.cost_times.append(cost)
        # Read-only once, so the decorations keep these objects until the next plan.
        self._paths_visual = ((readonly(lifted(path.positions)), readonly(team_color(0))),)
        self._goal_visual = readonly(lifted(path.positions[-1])[None])
        return TimedPath(path, self.step_s, now_s - start_step * self.step_s)

    def _fallback(self, start: np.ndarray, start_step: int, estimate) -> RobotPath:
        blocks = estimate.covariance.reshape(self.world.n_targets, 3, self.world.n_targets, 3)
        idx = np.arange(self.world.n_targets)
        worst = int(np.argmax(np.linalg.eigvalsh(blocks[idx, :, idx, :])[:, -1]))
        goal_xy = estimate.mean.reshape(-1, 3)[worst, :2]
        free_cells = self.geodesic.cells[self.geodesic.free.ravel()]
        if len(free_cells):
            goal = free_cells[np.argmin(((free_cells - goal_xy) ** 2).sum(axis=1))]
            waypoints = self.geodesic.path(start, goal)
            if waypoints is not None:
                times, positions = timed_waypoints(waypoints, start_step, self.params.speed_mps * self.step_s)
                if len(times) >= 2:
                    return RobotPath(times, positions)
        return RobotPath(np.array([start_step, start_step + HOLD_STEPS]), np.vstack([start, start]))

    # ----------------------------------------------------------------- running
    def step(self, observation: Observation) -> Commands:
        t = observation.time_s
        self._time_s = t
        if observation.target_ranges is not None:
            step = observation.target_step
            if abs(t - step * self.step_s) > 1e-6 or (self.last_step is not None and step != self.last_step + 1):
                raise ConfigError("sensing.period_s", f"readings must come once per period (reading of step {step} "
                                  f"at t = {t:.3f} s)")
            by_robot = measurement_records(observation, step)
            self.belief.receive([r for robot in by_robot for r in robot])
            self.last_step = step
            self._scalars["lambda_max_m2"] = self.series.record(self.belief.estimate(step))
            if self.fusion is None:
                self._scalars["t_star_s"] = step * self.step_s  # always connected: t*(t) = t
            else:
                self._scalars.update(self.fusion.tick(observation.time_s, observation.inbox, by_robot, step,
                                                      self.step_s))
        elif self.fusion is not None:
            self.fusion.tick(observation.time_s, observation.inbox, None, -1, self.step_s)
        self.ticks += 1
        self.connected_ticks += int(team_connected(observation.links.adjacency, tuple(range(len(self.offsets)))))
        if self.segment.finished(t):
            self.segment = self._plan(self.segment.path.positions[-1].copy(), t,
                                      self.last_step if self.last_step is not None else 0)
        xy = observation.position[:, :2]
        centre, velocity = self.segment.reference(t)
        on_path = not self.segment.finished(t)
        lag_m = np.linalg.norm(xy - (centre + self.offsets), axis=1).max() if on_path else 0.0
        if self.lag_holds.wait(0, on_path and lag_m > LAG_HOLD_M, t, lag_m):
            # Time scaling: a body lags, the formation's clock waits for it.
            self.segment.offset_s += self.world.control_period_s
            self.held_ticks += 1
            centre, velocity = self.segment.reference(t)
            velocity = np.zeros(2)
        references = separated_references(centre + self.offsets, xy, self.planning,
                                          np.broadcast_to(velocity, self.offsets.shape))
        commands = commands_from_plane(observation, references,
                                       np.broadcast_to(velocity, self.offsets.shape).copy())
        if self.fusion is not None:
            commands = dataclasses.replace(commands, outbox=self.fusion.drain())
        if not observation.decorations_wanted:  # (sim.types.Observation) events wait for a tick that draws
            return dataclasses.replace(commands, estimate=self.series.estimate)
        events, self.events = tuple(self.events), []
        decorations = Decorations(
            overlay=f"all_time: formation of {len(self.offsets)}, {len(self.plan_times)} paths planned",
            robot_colors=np.broadcast_to(team_color(0), (len(self.offsets), 4)).copy(),
            legend=(("robots in formation, their path", team_color(0)),),
            paths=self._paths_visual,
            meeting_points=self._goal_visual,  # the end of the formation's current path
            meeting_point_colors=(team_color(0) * (1, 1, 1, 0.5))[None],
            events=events,
        )
        return dataclasses.replace(commands, scalars=self._scalars, estimate=self.series.estimate,
                                   decorations=decorations)

    def progress(self) -> str:
        """Under a real radio, how many of the team's readings reached the fusion robot, for the run's message."""
        if self.fusion is None:
            return ""
        return f"{self.fusion.fused}/{self.belief.n_records} readings fused over the radio"

    def summary(self) -> dict:
        return {
            **self.series.summary(),
            "meetings_scheduled": 0,
            "meetings_held": 0,
            "meetings_connected": 0,
            "meetings_pending": 0,
            "max_wait_s": 0.0,
            "mean_wait_s": 0.0,
            "delay_bound_epochs": 0,
            "max_delay_epochs_observed": 0,
            "plan_time_mean_s": float(np.mean(self.plan_times)) if self.plan_times else 0.0,
            "plan_time_max_s": float(max(self.plan_times, default=0.0)),
            "plan_cost_share": float(sum(self.cost_times) / sum(self.plan_times)) if sum(self.plan_times) > 0 else 0.0,
            "plans": len(self.plan_times),
            "plan_failures": self.plan_failures,
            "plan_fallbacks": self.plan_fallbacks,
            "formation_connected_share": self.connected_ticks / self.ticks if self.ticks else 1.0,
            "path_clock_hold_s": self.held_ticks * self.world.control_period_s,
            "path_clock_hold_longest_s": self.lag_holds.longest_s,
            "path_clock_holds_cut": self.lag_holds.released,
            "t_star_lag_mean_s": 0.0,
            "t_star_lag_max_s": 0.0,
            **(self.fusion.summary(self.step_s) if self.fusion is not None else {}),
        }
