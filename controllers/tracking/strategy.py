"""``connected_tracking``: the continuous-connectivity paper's continuous connectivity on the intermittent paper's tracking task.

The fourth method for the intermittent paper's task (DESIGN.md, "Both paradigms on one
task"). The robots run the continuous-connectivity paper's controller whole - virtual dynamics
M v' = f_B + f_lambda + f, the sensor-based lambda2 force (range R_s = the
communication range, line-of-sight clearance R_o, inter-robot distance R_c),
roles and the prime-traveler election by flooding, travel and anchor forces -
through :class:`controllers.connectivity.strategy.ConnectedStrategy` on the
ground robots (planar virtual points at the sensors' height, the ``ground``
preset). Only its target generator differs: the team's EKF
(:class:`controllers.tracking.generator.EKFTargetGenerator`), whose
explorers are sent to viewpoints of the most uncertain targets (without an
informed prior, first to look for the targets not yet fixed, over the
search's hypotheses of the planning belief).

Estimation. The team is connected at every tick (lambda2 > lambda2_min is the
controller's invariant), so every reading is fused the tick it is taken into
one network-wide EKF: the belief is the global one, t*(t) = t, no delay (under
the ideal radio; under a real one the readings reach the EKF the generator
uses only as messages to a fusion robot, :class:`controllers.task.RadioFusion`,
so t*(t) may lag t). The
readings, the EKF (:class:`estimation.beliefs.Belief`), the prior and the
e_g / lambda-bar metrics are those of the three intermittent-task methods
(:mod:`controllers.task`).

Explorers and connectors: ``explorers`` robots (default 2 of 8) explore, the
rest connect (docs/paradigms.md says why). The run never finishes early:
tracking lasts the scenario's duration.

Bad input: a communication range at which the start configuration's graph
G^lambda is disconnected is refused (ConfigError naming the robots, exit 2),
as is a range the ground preset cannot use (R_s <= R_c).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from controllers.connectivity.connected_params import ConnectedParams
from controllers.connectivity.strategy import ConnectedStrategy
from controllers.task import (EstimateSeries, RadioFusion, check_time_base, measurement_records, neutral_prior,
                              over_radio, prior_state, target_initialiser)
from controllers.tracking.generator import EKFTargetGenerator, spread_robots
from controllers.tracking.params import ConnectedTrackingParams
from estimation.beliefs import Belief
from sim.config import ConfigError
from sim.strategy import WrappingStrategy
from sim.types import Commands, Observation, SceneChange, WorldInfo


def controller_params(params: ConnectedTrackingParams, comm_range: float) -> ConnectedParams:
    """The controller's parameters on the ground robots: the ``ground`` preset at R_s =
    ``comm_range`` (m) and v_cruise = the task's speed limit."""
    try:
        return ConnectedParams(preset="ground", cruise_speed_mps=params.speed_mps,
                               lambda2_source="exact").at_range(float(comm_range))
    except ValueError as err:
        raise ConfigError("sensing.comm_range_m", f"{comm_range:g} m is unusable for connected_tracking: "
                          f"{str(err).partition(': ')[2] or err}") from None


class ConnectedTrackingStrategy(WrappingStrategy):
    """The connected controller (``inner``) with the team's EKF as its target generator."""

    kind = "connected_tracking"

    def __init__(self, params: ConnectedTrackingParams):
        self.params = params

    @classmethod
    def adapt_to_scene(cls, strategy_table: dict, change: SceneChange, keep: frozenset[str]) -> list[str]:
        """In another scene the EKF prior is made non-informative (:func:`controllers.task.neutral_prior`)."""
        return neutral_prior(strategy_table, change, keep)

    def reset(self, world: WorldInfo, initial: Observation, rng: np.random.Generator) -> None:
        params = self.params
        self.step_s = check_time_base(world)
        n = world.n_robots
        if params.explorers >= n:
            raise ConfigError("strategy.explorers", f"must leave at least one connector: below the team size {n}, "
                              f"got {params.explorers}")
        self.world = world
        self.motion = world.target_motion
        self.prior = prior_state(params, world.n_targets)
        self.plane_z = float(np.mean(initial.sensor_position[:, 2]))
        initialiser = target_initialiser(params, world)
        self.search_space = initialiser.search if initialiser is not None else None
        self.belief = Belief(self.motion, self.prior, self.plane_z if params.resolve_mirror else None, initialiser)
        self.series = EstimateSeries()
        self.last_step: int | None = None
        self.readings_fused = 0
        self.generator: EKFTargetGenerator | None = None
        self.team_belief = self.belief  # the belief the explorers plan with (see below)
        self.core = self.inner = ConnectedStrategy(controller_params(params, world.comm_range_m),
                                                   targets=self._first_targets)
        self.core.reset(world, initial, rng)
        # Under the ideal radio every reading is fused the tick it is taken; under a real one the explorers'
        # viewpoints come from the belief of a fusion robot (the connector nearest the start centroid), fed
        # over the bus, and self.belief stays the fictitious global one of e_g and lambda-bar.
        self.fusion: RadioFusion | None = None
        if over_radio(initial):
            starts = initial.position[:, :2]
            distance = np.linalg.norm(starts - starts.mean(axis=0), axis=1)
            distance[self.generator.explorers] = np.inf  # explorers leave; a connector stays amid the team
            self.team_belief = Belief(self.motion, self.prior, self.plane_z if params.resolve_mirror else None,
                                      target_initialiser(params, world))
            self.fusion = RadioFusion(n, int(np.argmin(distance)), self.team_belief, self.belief,
                                      params.retransmit_after_s)
        self._scalars = {"lambda_max_m2": float(np.linalg.eigvalsh(self.prior.covariance)[-1]), "t_star_s": 0.0,
                         "t_star_lag_s": 0.0}

    def _first_targets(self, planner, starts: np.ndarray, rng: np.random.Generator):
        """The controller's target generator at start-up (its queues)."""
        explorers = spread_robots(starts, self.params.explorers)
        self.generator = EKFTargetGenerator(self.params, planner, self.core.boxes, self.core.plane_z, self.motion,
                                            explorers, self.world.target_range_m, self.core.params.cruise_speed_mps,
                                            self.step_s, self.search_space,
                                            self._hypotheses if self.search_space is not None else None)
        return self.generator.first_targets(len(starts), starts, self.prior)

    def _hypotheses(self, step: int) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """The search's hypotheses at ``step`` of every target the planning belief has not fixed."""
        belief = self.team_belief
        found = {a: belief.hypotheses(step, a) for a in range(self.world.n_targets)} if step >= 0 else {}
        return {a: h for a, h in found.items() if h is not None}

    @property
    def finished(self) -> bool:
        """Never: tracking lasts the scenario's duration, so a run that lasts it is "completed"
        (like the other methods of the intermittent paper's task), not stopped at a "time limit"."""
        return False

    def progress(self) -> str:
        """What the team did so far, for the run's status message."""
        visited = len(self.core.last.visits) if self.core.last is not None else 0
        if self.fusion is not None:
            return (f"{self.fusion.fused}/{self.readings_fused} readings fused over the radio, "
                    f"{visited} viewpoints visited")
        return f"{self.readings_fused} readings fused, {visited} viewpoints visited"

    def step(self, observation: Observation) -> Commands:
        fresh = observation.target_ranges is not None
        if fresh:
            step = observation.target_step
            t = observation.time_s
            if abs(t - step * self.step_s) > 1e-6 or (self.last_step is not None and step != self.last_step + 1):
                raise ConfigError("sensing.period_s", f"readings must come once per period (reading of step {step} "
                                  f"at t = {t:.3f} s)")
            by_robot = measurement_records(observation, step)
            self.readings_fused += self.belief.receive([r for robot in by_robot for r in robot])
            self.last_step = step
            self._scalars["lambda_max_m2"] = self.series.record(self.belief.estimate(step))
            if self.fusion is None:
                self._scalars["t_star_s"] = step * self.step_s  # always connected: t*(t) = t
            else:
                self._scalars.update(self.fusion.tick(observation.time_s, observation.inbox, by_robot, step,
                                                      self.step_s))
        elif self.fusion is not None:
            self.fusion.tick(observation.time_s, observation.inbox, None, -1, self.step_s)
        if self.fusion is None:
            estimate = self.series.last if self.series.last is not None else self.prior
        else:
            estimate = self.team_belief.estimate(self.last_step) if self.last_step is not None else self.prior
        core = self.core
        self.generator.update(estimate, core.q, core.explorer, core.queues, fresh)
        commands = core.step(observation)
        if self.fusion is not None:
            commands = dataclasses.replace(commands, outbox=commands.outbox + self.fusion.drain())
        scalars = {**commands.scalars, **self._scalars} if observation.decorations_wanted else commands.scalars
        return dataclasses.replace(commands, scalars=scalars, estimate=self.series.estimate)

    def summary(self) -> dict:
        core = self.core.summary()
        for key in ("completion_time_s", "targets_total", "targets_visited", "targets_skipped"):
            core.pop(key, None)
        return {
            **self.series.summary(),
            **core,
            "viewpoints_visited": len(self.core.last.visits) if self.core.last is not None else 0,
            "readings_fused": self.fusion.fused if self.fusion is not None else self.readings_fused,
            **self.generator.summary(),
            "t_star_lag_mean_s": 0.0,
            "t_star_lag_max_s": 0.0,
            "comm_range_m": self.world.comm_range_m,
            **(self.fusion.summary(self.step_s) if self.fusion is not None else {}),
        }
