"""The intermittent paper's tracking task as every method that runs it sees it.

Shared by the three intermittent-task strategies (``intermittent``, ``all_time``,
``random_meeting``) and the continuous-connectivity paper's controller on that task
(``connected_tracking``), so all four take the same readings into the same
EKF from the same prior and report the same e_g and lambda-bar:

- :data:`TASK_PARAMS` - the keys every one of them reads (speed limit, delta,
  the EKF's prior), declared once: each parameter class takes its field from
  :func:`task_param`;
- :func:`check_time_base` - the target model and one reading per step;
- :func:`prior_state` - x^0 and C(0) of Sec. IV;
- :func:`neutral_prior` - the prior made non-informative in another scene;
- :func:`measurement_records` - an Observation's range readings as
  :class:`estimation.beliefs.RangeMeasurement` records, per robot;
- :class:`EstimateSeries` - lambda_max(C_g(t)) per step and the latest
  :class:`sim.types.TargetEstimate` (``Commands.estimate``).

``params`` is any parameter object with the task's keys used here
(``prior_mean``, ``prior_variance_m2``):
:class:`controllers.intermittent.params.IntermittentParams` or
:class:`controllers.tracking.params.ConnectedTrackingParams`.

Time: one discrete step of the paper is ``sensing.period_s`` of simulation
(1 s): range readings and the target model (``target_motion.step_s``, which
must equal it) both tick once per step; the strategies read it from
``WorldInfo.sensing_period_s``. The paper's speed limit |u| <= 0.1 m per step
is ``speed_mps`` = 0.1 m/s.
"""

from __future__ import annotations

import math

from dataclasses import dataclass, field

import numpy as np

from estimation.beliefs import RangeMeasurement
from estimation.ekf import PAPER_INITIAL_ESTIMATE, FilterState
from sim.config import ConfigError, param
from sim.types import Observation, SceneChange, TargetEstimate, WorldInfo

# The task's keys, shared by the four methods that run it (a scenario runs under any of them).
TASK_PARAMS: dict[str, dict] = {
    "speed_mps": dict(default=0.1, unit="m/s", above=0.0),  # paper: 0.1 m per 1 s step
    "delta_m2": dict(default=0.0144, unit="m^2", above=0.0, note="a variance threshold, m^2"),  # paper: 0.12^2
    "prior_mean": dict(default=(), unit="m"),  # empty: the paper's x^0
    "prior_variance_m2": dict(default=0.25, unit="m^2", above=0.0),  # paper: C(0) = 0.25 I
    "resolve_mirror": dict(default=True),
    # Under a real radio (radio.preset other than ideal): a reliable message without an ack this long is sent again
    "retransmit_after_s": dict(default=2.0, unit="s", above=0.0, max=600.0),
}
# strategy.step_s is not a key: one step of the task is the scenario's sensing period.
STEP_KEY_REMOVED = {"step_s": "set sensing.period_s (one discrete step of the paper; target_motion.step_s "
                              "must equal it)"}


def task_param(name: str):
    """The field of the task's key ``name`` (:data:`TASK_PARAMS`), for a parameter class."""
    return param(**TASK_PARAMS[name])


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


def neutral_prior(strategy_table: dict, change: SceneChange, keep: frozenset[str]) -> list[str]:
    """The EKF prior of a scenario moved into another scene (the methods' ``adapt_to_scene``).

    A built-in's prior is a guess about its own scene; in another one every
    target starts at the scene's centre with a variance that spans the scene.
    ``strategy.prior_mean`` or ``strategy.prior_variance_m2`` set by the user
    (in ``keep``) stay.
    """
    if not change.n_targets or "strategy.prior_mean" in keep:
        return []
    centre = [round(float(v), 3) for v in change.center]
    half_diagonal = float(np.linalg.norm((change.bounds[1] - change.bounds[0])[:2])) / 2
    # 2 sigma of the prior reach from the centre to the scene's corners.
    variance = round((half_diagonal / 2) ** 2, 3)
    strategy_table["prior_mean"] = [centre] * change.n_targets
    if "strategy.prior_variance_m2" not in keep:
        strategy_table["prior_variance_m2"] = variance
    return [f"strategy.prior_mean: the built-in's EKF prior describes its own scene; every target's estimate "
            f"now starts at the centre of {change.scene_name}, {tuple(centre)} m, with C(0) = "
            f"{strategy_table['prior_variance_m2']:g} I m^2 (non-informative; if you know roughly where "
            "the targets are, set strategy.prior_mean there: a range-only EKF started far off can settle "
            "on a wrong point)"]


def check_time_base(world: WorldInfo) -> float:
    """One step of the task, s (``sensing.period_s``): the strategies need the target model
    stepping with the readings and a whole number of control ticks per step."""
    if world.n_targets == 0:
        raise ConfigError("targets", "the intermittent-task strategies need at least one target")
    if getattr(world, "target_motion", None) is None:
        raise ConfigError("targets", "the simulator did not provide the target model")
    step_s = world.sensing_period_s
    if abs(world.target_motion.dt - step_s) > 1e-9:
        raise ConfigError("target_motion.step_s",
                          f"must equal sensing.period_s ({step_s} s), got {world.target_motion.dt}")
    ratio = step_s / world.control_period_s
    if abs(ratio - round(ratio)) > 1e-6:
        raise ConfigError("sensing.period_s", f"must be a whole multiple of physics.control_period_s, got {step_s}")
    if any(kind != "ground" for kind in world.robot_kinds):
        raise ConfigError("robots", "the intermittent-task strategies drive ground robots only")
    return step_s


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
