"""Seed 000's tracking task as every method that runs it sees it.

Shared by the three seed 000 strategies (``intermittent``, ``all_time``,
``random_meeting``) and seed 001's controller on that task
(``connected_tracking``), so all four take the same readings into the same
EKF from the same prior and report the same e_g and lambda-bar:

- :func:`check_time_base` - the target model and one reading per step;
- :func:`prior_state` - x^0 and C(0) of Sec. IV;
- :func:`measurement_records` - an Observation's range readings as
  :class:`estimation.beliefs.RangeMeasurement` records, per robot;
- :class:`EstimateSeries` - lambda_max(C_g(t)) per step and the latest
  :class:`sim.types.TargetEstimate` (``Commands.estimate``).

``params`` is any parameter object with the seed 000 fields used here
(``step_s``, ``prior_mean``, ``prior_variance_m2``):
:class:`controllers.intermittent.params.IntermittentParams` or its extension.
"""

from __future__ import annotations

import math

from dataclasses import dataclass, field

import numpy as np

from estimation.beliefs import RangeMeasurement
from estimation.ekf import PAPER_INITIAL_ESTIMATE, FilterState
from sim.config import ConfigError
from sim.types import Observation, TargetEstimate, WorldInfo


def prior_state(params, n_targets: int) -> FilterState:
    """x^0 and C(0) = prior_variance I (Sec. IV); the paper's x^0 when not given."""
    if params.prior_mean:
        if len(params.prior_mean) != n_targets:
            raise ConfigError("strategy.prior_mean",
                              f"has {len(params.prior_mean)} entries for {n_targets} targets")
        mean = np.array(params.prior_mean, dtype=float)
    else:
        if n_targets > len(PAPER_INITIAL_ESTIMATE):
            raise ConfigError("strategy.prior_mean", f"is required for more than {len(PAPER_INITIAL_ESTIMATE)} targets")
        mean = PAPER_INITIAL_ESTIMATE[:n_targets]
    mean = mean.reshape(-1)
    return FilterState(0, mean, params.prior_variance_m2 * np.eye(mean.size))


def check_time_base(world: WorldInfo, params) -> None:
    """The strategies need the target model and a whole number of control ticks per step."""
    if world.n_targets == 0:
        raise ConfigError("targets", "the seed 000 strategies need at least one target")
    if getattr(world, "target_motion", None) is None:
        raise ConfigError("targets", "the simulator did not provide the target model")
    if abs(world.target_motion.dt - params.step_s) > 1e-9:
        raise ConfigError("strategy.step_s",
                          f"must equal target_motion.step_s ({world.target_motion.dt} s), got {params.step_s}")
    if abs(world.sensing_period_s - params.step_s) > 1e-9:
        raise ConfigError("strategy.step_s",
                          f"must equal sensing.period_s ({world.sensing_period_s} s), got {params.step_s}")
    ratio = params.step_s / world.control_period_s
    if abs(ratio - round(ratio)) > 1e-6:
        raise ConfigError("strategy.step_s", f"must be a whole multiple of physics.control_period_s, got {params.step_s}")
    if any(kind != "ground" for kind in world.robot_kinds):
        raise ConfigError("robots", "the seed 000 strategies drive ground robots only")


def measurement_records(observation: Observation, step: int) -> list[list[RangeMeasurement]]:
    """Per robot, its readings of this step (one record per visible target)."""
    # Python floats from tolist() (the values of float(v)); math.isfinite as np.isfinite.
    ranges = np.asarray(observation.target_ranges, dtype=float).tolist()
    sensors = np.asarray(observation.sensor_position, dtype=float).tolist()
    out: list[list[RangeMeasurement]] = []
    for robot, row in enumerate(ranges):
        sensor = tuple(sensors[robot])
        out.append([RangeMeasurement(step, robot, sensor, a, max(r, 0.0)) for a, r in enumerate(row)
                    if math.isfinite(r)])
    return out


@dataclass
class EstimateSeries:
    """lambda_max of the global covariance per step, and the latest estimate
    (:attr:`estimate`, for ``Commands.estimate``: the same object until the next step)."""

    steps: list[int] = field(default_factory=list)
    lambda_max: list[float] = field(default_factory=list)
    last: FilterState | None = None
    estimate: TargetEstimate | None = None

    def record(self, state: FilterState) -> float:
        value = float(np.linalg.eigvalsh(state.covariance)[-1])
        self.steps.append(state.step)
        self.lambda_max.append(value)
        self.last = state
        m = state.n_targets
        mean = state.mean.reshape(m, 3)
        idx = np.arange(m)
        self.estimate = TargetEstimate(state.step, mean, state.covariance.reshape(m, 3, m, 3)[idx, :, idx, :])
        return value

    def summary(self) -> dict:
        """lambda-bar of eq. (13b): mean and population std over steps >= 1."""
        values = np.array([v for s, v in zip(self.steps, self.lambda_max) if s >= 1])
        if values.size == 0:
            return {"lambda_bar_mean_m2": None, "lambda_bar_std_m2": None}
        return {"lambda_bar_mean_m2": float(values.mean()), "lambda_bar_std_m2": float(values.std())}
