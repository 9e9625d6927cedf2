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
- :func:`target_initialiser` - without an informed prior, each target's EKF
  started from its first readings (:mod:`estimation.target_init`);
- :func:`measurement_records` - an Observation's range readings as
  :class:`estimation.beliefs.RangeMeasurement` records, per robot;
- :class:`EstimateSeries` - lambda_max(C_g(t)) per step and the latest
  :class:`sim.types.TargetEstimate` (``Commands.estimate``);
- :class:`RadioFusion` - under a real radio, the readings of the two
  always-connected methods (``all_time``, ``connected_tracking``) reach the
  team's belief only as ``"fusion"`` messages over the bus.

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
from typing import Any

from dataclasses import dataclass, field

import numpy as np

from estimation.beliefs import AgreementTracker, Belief, RangeMeasurement
from estimation.ekf import PAPER_INITIAL_ESTIMATE, FilterState
from estimation.target_init import ReadingsInitialiser
from estimation.target_search import SearchSpace, grid_points
from estimation.metrics import local_error
from sim.config import ConfigError, param
from sim.radio.bus import range_records_bytes
from sim.radio.protocols import Outbox, ReliableLink, deliveries_of
from sim.types import Observation, SceneChange, TargetEstimate, WorldInfo

from controllers.intermittent.planner_geometry import segments_blocked

# The search's cells: across (m) and heights between the scene's floor and ceiling (a 10 x 10 m
# room: about 7,800 hypotheses per target; a 300 s run of intermittent-8 there takes about 15 s of wall
# time, and the coarser 0.35 m x 3 heights gave e_g 0.84 / 1.09 / 0.91 m on seeds 1-3 against 0.79 / 1.12 / 0.78).
SEARCH_CELL_M = 0.25
SEARCH_LEVELS = 5
# A target not yet fixed is planned for as a Gaussian of this variance at a drawn hypothesis, m^2: the
# largest a fix is accepted with (estimation.target_init), so it comes first in the planners' order
# of uncertain targets while their goal (its variance below delta) stays reachable from one visit.
SEARCH_PLAN_VARIANCE_M2 = 1.0

# The task's keys, shared by the four methods that run it (a scenario runs under any of them).
TASK_PARAMS: dict[str, dict] = {
    "speed_mps": dict(default=0.1, unit="m/s", above=0.0),  # paper: 0.1 m per 1 s step
    "delta_m2": dict(default=0.0144, unit="m^2", above=0.0, note="a variance threshold, m^2"),  # paper: 0.12^2
    "prior_mean": dict(default=(), unit="m"),  # empty: the paper's x^0
    "prior_variance_m2": dict(default=0.25, unit="m^2", above=0.0),  # paper: C(0) = 0.25 I
    "resolve_mirror": dict(default=True),
    # false: the paper's informed prior; true (set by --scene): each target's EKF starts from its readings
    "init_from_readings": dict(default=False),
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
    target starts at the scene's centre with a variance that spans the scene,
    and its EKF fuses its readings only once they fix it
    (``strategy.init_from_readings``, :func:`target_initialiser`).
    ``strategy.prior_mean``, ``strategy.prior_variance_m2`` or
    ``strategy.init_from_readings`` set by the user (in ``keep``) stay: a
    prior_mean of the user's is informed.
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
    if "strategy.init_from_readings" not in keep:
        strategy_table["init_from_readings"] = True
    if strategy_table.get("init_from_readings", False):
        return [f"strategy.prior_mean: the built-in's EKF prior describes its own scene; in {change.scene_name} "
                "each target's estimate starts from its first readings (multilateration once they fix it, or a "
                "search over the scene's free space once what was and was not read narrows it to one place; "
                f"before any reading the scene's centre, {tuple(centre)} m, C(0) = "
                f"{strategy_table['prior_variance_m2']:g} I m^2); if you know roughly where the targets are, "
                "set strategy.prior_mean there"]
    return [f"strategy.prior_mean: the built-in's EKF prior describes its own scene; every target's estimate "
            f"now starts at the centre of {change.scene_name}, {tuple(centre)} m, with C(0) = "
            f"{strategy_table['prior_variance_m2']:g} I m^2 (non-informative; if you know roughly where "
            "the targets are, set strategy.prior_mean there: a range-only EKF started far off can settle "
            "on a wrong point)"]


def target_initialiser(params, world: WorldInfo) -> ReadingsInitialiser | None:
    """The initialiser every belief of the task gets: None with the informed prior (the paper's),
    one that starts each target from its readings with ``strategy.init_from_readings`` (targets
    between the scene's floor and ceiling), searching for it over the scene's free space until
    then (:func:`search_space`)."""
    if not params.init_from_readings:
        return None
    low, high = (float(v) for v in np.asarray(world.bounds, dtype=float)[:, 2])
    return ReadingsInitialiser(height_range=(low, high), search=search_space(world))


def search_space(world: WorldInfo) -> SearchSpace:
    """Hypotheses of a target's position over the scene's free space (cells of
    :data:`SEARCH_CELL_M` across, :data:`SEARCH_LEVELS` heights between floor and ceiling),
    sensed up to the sensors' range with line of sight past the scene's obstacles."""
    bounds = np.asarray(world.bounds, dtype=float)
    boxes = world.obstacles
    height = bounds[1, 2] - bounds[0, 2]
    spacing = np.array([SEARCH_CELL_M, SEARCH_CELL_M, height / SEARCH_LEVELS])

    def free(points: np.ndarray) -> np.ndarray:
        return ~segments_blocked(boxes, points, points)

    def line_of_sight(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return ~segments_blocked(boxes, a, b)

    points = grid_points(bounds[0], bounds[1], spacing, free)
    if not len(points):
        points = grid_points(bounds[0], bounds[1], spacing)
    return SearchSpace(points, spacing, world.target_range_m, line_of_sight, bounds=bounds)


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


FUSION_KIND = "fusion"  # the bus's message kind of a robot's readings on their way to the team belief
FUSION_ATTEMPTS = 3  # copies of one fusion message before its readings wait for the robot's next message


def over_radio(observation: Observation) -> bool:
    """Whether the run's radio is a real one (``radio.preset`` other than ``ideal``)."""
    return observation.radio is not None and observation.radio.preset != "ideal"


class RadioFusion:
    """The team's belief of an always-connected method, fed only by the radio.

    The belief lives at one robot, ``fusion_robot``: it takes its own readings
    at once and every other robot's when they arrive as a ``"fusion"``
    message (its records, ``range_records_bytes`` of them, unicast over a
    :class:`sim.radio.protocols.ReliableLink`, one hop: nothing is relayed).
    A message without an ack after ``FUSION_ATTEMPTS`` copies is not lost: its
    readings go again with the robot's next message. The belief accepts late
    and out-of-order records (:class:`estimation.beliefs.Belief`), so t*(t),
    the last step up to which it holds every reading the fictitious global
    belief holds, may lag t.

    Each tick: :meth:`exchange` with the tick's time and inbox and, on a step
    with readings, every robot's records; :meth:`drain` into ``Commands.outbox``.
    """

    def __init__(self, n_robots: int, fusion_robot: int, belief: Belief, global_belief: Belief,
                 retransmit_after_s: float) -> None:
        self.fusion_robot = int(fusion_robot)
        self.belief = belief
        self.outbox = Outbox()
        self.links = [ReliableLink(self.outbox, r, timeout_s=retransmit_after_s, max_attempts=FUSION_ATTEMPTS)
                      for r in range(n_robots)]
        self.waiting: list[list[RangeMeasurement]] = [[] for _ in range(n_robots)]
        self.in_flight: dict[tuple[int, int], tuple[RangeMeasurement, ...]] = {}
        self.tracker = AgreementTracker(belief, global_belief)
        self.global_belief = global_belief
        self.lags: list[tuple[int, int, float]] = []  # (step, t*, e(t)) per step with readings
        self.fused = 0  # records the belief took, the fusion robot's own included
        self.records_sent = 0  # records handed to the bus, every copy (retransmissions included)

    def exchange(self, time_s: float, inbox: Any, records: list[list[RangeMeasurement]] | None) -> None:
        """Read the tick's fusion messages and acks (``inbox``: ``Observation.inbox``), then send what each
        robot has waiting; ``records``: every robot's readings on a step with readings, else None."""
        t = time_s
        for robot, link in enumerate(self.links):
            if not link.pending and not (inbox and inbox[robot]):
                continue  # nothing arrived and nothing to retransmit
            events = link.poll(t, deliveries_of(inbox, robot, FUSION_KIND))
            for got in events.received:
                if robot == self.fusion_robot:
                    self.fused += self.belief.receive(got.data)
            for transfer in events.acknowledged:
                self.in_flight.pop((robot, transfer), None)
            for transfer in events.gave_up:
                self.waiting[robot].extend(self.in_flight.pop((robot, transfer), ()))
        if records is not None:
            for robot, own in enumerate(records):
                if robot == self.fusion_robot:
                    self.fused += self.belief.receive(own)
                else:
                    self.waiting[robot].extend(own)
        for robot, waiting in enumerate(self.waiting):
            if waiting:
                data = tuple(waiting)
                transfer = self.links[robot].send(FUSION_KIND, self.fusion_robot, data, range_records_bytes(len(data)), t)
                self.in_flight[(robot, transfer)] = data
                waiting.clear()

    def drain(self) -> tuple:
        """This tick's messages, for ``Commands.outbox``."""
        messages = self.outbox.drain()
        self.records_sent += sum(len(m.payload.data) for m in messages if m.kind == FUSION_KIND)
        return messages

    def record_lag(self, step: int) -> tuple[int, float]:
        """t*(t) (steps; -1 before any agreement) and e(t) (m, eq. (14)) at t = ``step`` from what the
        belief holds now, kept for the summary. The strategies read it at the end of step t's period,
        just before the next readings: a reading that took a tick to arrive does not count as a lag."""
        horizon = self.tracker.horizon(step)
        start = horizon + 1
        error = local_error(self.global_belief.mean_trajectory(start, step + 1),
                            self.belief.mean_trajectory(start, step + 1))
        self.lags.append((step, horizon, error))
        return horizon, error

    def tick(self, time_s: float, inbox: Any, records: list[list[RangeMeasurement]] | None, step: int,
             step_s: float) -> dict[str, float]:
        """This tick's exchange (``records``: the readings of a new step ``step``, None between readings)
        and, once a step has ended, its figures: t*(t) (s, nan before any agreement), its lag and e(t)."""
        self.exchange(time_s, inbox, records)
        if records is None or step < 1:
            return {}
        agreement, error = self.record_lag(step - 1)  # the step just ended: what reached the fusion robot
        return {"t_star_s": agreement * step_s if agreement >= 0 else math.nan,
                "t_star_lag_s": (step - 1 - agreement) * step_s, "local_error_m": error}

    def summary(self, step_s: float) -> dict:
        lag = np.array([s - a for s, a, _ in self.lags], dtype=float) * step_s
        error = np.array([e for _, _, e in self.lags], dtype=float)
        return {
            "t_star_lag_mean_s": float(lag.mean()) if lag.size else 0.0,
            "t_star_lag_max_s": float(lag.max()) if lag.size else 0.0,
            "local_error_mean_m": float(error.mean()) if error.size else 0.0,
            "fusion_robot": self.fusion_robot,
            "fusion_readings_fused": self.fused,
            "fusion_readings_missing": self.global_belief.n_records - self.belief.n_records,
            "fusion_records_sent": self.records_sent,
        }
