"""Team, robot and global beliefs under intermittent communication (Khodayi-mehr et al. 2019,
Remark III.4, Algorithm 5, Sec. IV-A).

Every range reading is a :class:`RangeMeasurement` record (time step, robot,
sensor position, target, measured range): the Kalman form of Remark III.4
keeps "the time, location, and value of each measurement". A holder's belief
(:class:`Belief`) is the EKF run over every record that reached it: the
posterior at step k fuses all its records with step <= k. Records may arrive
late and out of order; the belief keeps a checkpoint of the posterior at
every step and, when a record of step s arrives, refilters from the
checkpoint at s - 1, so a late packet never costs a refilter from t = 0.
The readings of one step are fused as one batch sorted by (robot, target), so
the result does not depend on arrival order, to the last bit.

:class:`NetworkBeliefs` runs Algorithm 5's information flow: robots log what
they measure; when a team meets (lines 3-4) its members exchange everything
they collected or heard since they last met with this team, and the team
belief (the one the team plans with) fuses it. The fictitious global belief
x_g of Sec. IV-A fuses every record the moment it is taken. t*(t) of eq. (14)
is the last step up to which a team's fused measurement sets equal the
global ones, step by step; up to t*(t) the team estimate equals x_g exactly.

Packets: the records a robot collects between two of its meetings always
travel together, so the delay of Proposition III.2 is tracked per packet
(robot, epoch of the robot's last meeting before collection) and the epoch at
which each team first receives it.

Deviations from the paper:
- A record is identified by (step, robot, target): one reading per robot,
  target and step. A second, different record with the same identity is an
  error; an identical one is ignored (the same packet heard twice).
- Robots keep beliefs too (filtered lazily, only when asked); the paper only
  uses team beliefs for planning.
- ``Belief.forget_before`` drops old checkpoints (Remark III.5: information
  older than D epochs has reached everyone); records are kept so that t*(t)
  stays exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Iterable, KeysView, Mapping, Protocol, Sequence

import numpy as np

from estimation.ekf import FilterState, RangeReadings, TargetEKF
from estimation.metrics import local_error
from estimation.target_init import ReadingsInitialiser
from estimation.target_search import HypothesisMotion, StepLooks, collapse, moments, normalised, update_log_weights
from estimation.target_motion import TargetMotion

MeasurementKey = tuple[int, int, int]  # (step, robot, target)


class TeamStructure(Protocol):
    """What the beliefs need of the teams (``controllers.intermittent.teams.Teams``
    provides it; estimation does not import controllers)."""

    @property
    def members(self) -> Sequence[Sequence[int]]: ...

    @property
    def robots(self) -> Sequence[int]: ...

    @property
    def n_teams(self) -> int: ...


@dataclass(frozen=True)
class RangeMeasurement:
    """One range reading.

    step: discrete time k of the reading; robot: id of the robot that took it;
    sensor_position: (x, y, z) of its sensor, m, world frame; target: index a
    of the target; measured_range: the reading, m.
    """

    step: int
    robot: int
    sensor_position: tuple[float, float, float]
    target: int
    measured_range: float

    def __post_init__(self) -> None:
        position = tuple(float(c) for c in self.sensor_position)
        if len(position) != 3:
            raise ValueError(f"sensor_position: need 3 coordinates, got {len(position)}")
        if not all(math.isfinite(c) for c in position):  # math's test: numpy's costs more than the record
            raise ValueError(f"sensor_position: must be finite, got {position}")
        if int(self.step) < 0:
            raise ValueError(f"step: must be >= 0, got {self.step}")
        if int(self.robot) < 0:
            raise ValueError(f"robot: must be >= 0, got {self.robot}")
        if int(self.target) < 0:
            raise ValueError(f"target: must be >= 0, got {self.target}")
        if not math.isfinite(self.measured_range) or self.measured_range < 0:
            raise ValueError(f"measured_range: must be a finite distance >= 0 m, got {self.measured_range}")
        object.__setattr__(self, "step", int(self.step))
        object.__setattr__(self, "robot", int(self.robot))
        object.__setattr__(self, "target", int(self.target))
        object.__setattr__(self, "sensor_position", position)
        object.__setattr__(self, "measured_range", float(self.measured_range))

    @property
    def key(self) -> MeasurementKey:
        return (self.step, self.robot, self.target)


def readings_from_records(records: Iterable[RangeMeasurement]) -> RangeReadings:
    """Batch of readings in (robot, target) order, the fusion order of a step."""
    ordered = sorted(records, key=lambda r: (r.robot, r.target))
    if not ordered:
        return RangeReadings.empty()
    return RangeReadings(
        np.array([r.sensor_position for r in ordered]),
        np.array([r.target for r in ordered], dtype=int),
        np.array([r.measured_range for r in ordered]),
    )


class Belief:
    """EKF over every record received, checkpointed at every step.

    motion: target model; prior: belief about x(prior.step) before any
    reading. ``estimate(k)`` is the posterior at step k given the records with
    step <= k received so far; it is computed lazily and cached.
    mirror_plane_z: see :class:`estimation.ekf.TargetEKF` (None: plain EKF).

    initialiser: None (default): every target starts from ``prior`` and every
    reading is fused. Given (a run without an informed prior), a target's
    readings are kept out of the EKF until, at some step k, its readings of the
    initialiser's window fix it (:mod:`estimation.target_init`); its block of
    the posterior at k is then that fix (no cross-covariance), and its readings
    of later steps are fused. Until then its block is the prior's, predicted.
    Which targets are fixed is checkpointed with each posterior, so the
    posterior at k still depends only on the records with step <= k.
    With the initialiser's search space (:mod:`estimation.target_search`), the
    block of a target not yet fixed is instead the moments of its hypotheses,
    weighed by every reading and non-reading of steps <= k (checkpointed too:
    :meth:`hypotheses`), and their collapse also fixes it.
    """

    def __init__(self, motion: TargetMotion, prior: FilterState, mirror_plane_z: float | None = None,
                 initialiser: ReadingsInitialiser | None = None):
        self._ekf = TargetEKF(motion, prior, mirror_plane_z)
        self._motion = motion
        self._prior = prior
        self._initialiser = initialiser
        # Per posterior (and for _root), the targets fixed by then; only used with an initialiser.
        self._fixed: list[frozenset[int]] = []
        self._root_fixed: frozenset[int] = frozenset()
        # With a search space: per posterior (and for _root), {target not fixed: its hypotheses' log-weights}.
        self._search = initialiser.search if initialiser is not None else None
        self._hypothesis_motion = HypothesisMotion(motion, prior.step) if self._search is not None else None
        self._weights: list[dict[int, np.ndarray]] = []
        self._root_weights: dict[int, np.ndarray] = {}
        self._records: dict[MeasurementKey, RangeMeasurement] = {}
        self._by_step: dict[int, dict[MeasurementKey, RangeMeasurement]] = {}
        self._arrivals: list[RangeMeasurement] = []
        # _posteriors[i] is the posterior at step _origin + i. Before the
        # first posterior, _root is the posterior at _origin - 1 to predict
        # from, or None when _origin is the prior's step.
        self._origin = prior.step
        self._root: FilterState | None = None
        self._posteriors: list[FilterState] = []
        self.filtered_steps = 0  # diagnostics: filter steps run, refilters included

    @property
    def n_targets(self) -> int:
        return self._prior.n_targets

    @property
    def n_records(self) -> int:
        return len(self._arrivals)

    def records_since(self, index: int) -> list[RangeMeasurement]:
        """Records in arrival order from position ``index`` on."""
        return self._arrivals[index:]

    def has(self, key: MeasurementKey) -> bool:
        return key in self._records

    def keys_at(self, step: int) -> KeysView[MeasurementKey]:
        """Identities of the records of ``step`` received so far."""
        return self._by_step.get(step, {}).keys()

    @property
    def earliest_step(self) -> int:
        """First step whose estimate is still available (see ``forget_before``)."""
        return self._origin

    @property
    def computed_until(self) -> int:
        """Last step with a valid cached posterior (earliest_step - 1 if none)."""
        return self._origin + len(self._posteriors) - 1

    def receive(self, records: Iterable[RangeMeasurement]) -> int:
        """Add records (any order, duplicates ignored); returns how many were new.

        Invalidates the cached posteriors from the earliest new step on.
        """
        earliest_new: int | None = None
        added = 0
        for record in records:
            known = self._records.get(record.key)
            if known is not None:
                if known != record:
                    raise ValueError(
                        f"records: two different readings share (step, robot, target) {record.key}"
                    )
                continue
            if record.target >= self.n_targets:
                raise ValueError(f"records: target {record.target} out of range for {self.n_targets} targets")
            if record.step < self._origin:
                raise ValueError(
                    f"records: step {record.step} is before this belief's earliest step "
                    f"{self._origin} (prior step or forgotten)"
                )
            self._records[record.key] = record
            self._by_step.setdefault(record.step, {})[record.key] = record
            self._arrivals.append(record)
            added += 1
            earliest_new = record.step if earliest_new is None else min(earliest_new, record.step)
        if earliest_new is not None:
            del self._posteriors[max(earliest_new - self._origin, 0) :]
            del self._fixed[max(earliest_new - self._origin, 0) :]
            del self._weights[max(earliest_new - self._origin, 0) :]
        return added

    def estimate(self, step: int) -> FilterState:
        """Posterior about x(step) from all records with step <= ``step``."""
        if step < self._origin:
            raise ValueError(f"step: {step} is before this belief's earliest step {self._origin}")
        while self.computed_until < step:
            if self._initialiser is None:
                self._posteriors.append(self._filter_next())
            else:
                posterior, fixed, weights = self._filter_next_initialising()
                self._posteriors.append(posterior)
                self._fixed.append(fixed)
                self._weights.append(weights)
        return self._posteriors[step - self._origin]

    def hypotheses(self, step: int, target: int) -> tuple[np.ndarray, np.ndarray] | None:
        """Where ``target`` may be at ``step`` by the search (positions (N, 3), m, and weights (N,)
        summing to 1), or None: no search space, or the target is fixed by then."""
        if self._search is None:
            return None
        self.estimate(step)
        log_weights = self._weights[step - self._origin].get(target)
        if log_weights is None:
            return None
        return (self._hypothesis_motion.positions(self._search.points, target, step), normalised(log_weights))

    def fixed_targets(self, step: int) -> frozenset[int]:
        """Targets whose readings the posterior at ``step`` fuses: all without an initialiser,
        else those fixed from their readings by then."""
        if self._initialiser is None:
            return frozenset(range(self.n_targets))
        self.estimate(step)
        return self._fixed[step - self._origin]

    def _filter_next_initialising(self) -> tuple[FilterState, frozenset[int], dict[int, np.ndarray]]:
        """:meth:`_filter_next` for a belief with an initialiser: readings of targets not yet
        fixed wait; each such target with a reading this step is tried for a fix. With a search
        space, the hypotheses of every target not fixed are weighed by this step's readings and
        non-readings; their moments are its block of the posterior, and their collapse fixes it
        when multilateration does not."""
        step = self.computed_until + 1
        if self._posteriors:
            self._ekf.reset(self._posteriors[-1])
            self._ekf.predict()
            fixed = self._fixed[-1]
            weights = self._weights[-1]
        elif self._root is not None:
            self._ekf.reset(self._root)
            self._ekf.predict()
            fixed = self._root_fixed
            weights = self._root_weights
        else:
            self._ekf.reset(self._prior)
            fixed = frozenset()
            weights = ({} if self._search is None else
                       {a: np.zeros(self._search.n_hypotheses) for a in range(self.n_targets)})
        self.filtered_steps += 1
        records = self._by_step.get(step) or {}
        fused = [r for r in records.values() if r.target in fixed]
        state = self._ekf.update(readings_from_records(fused)) if fused else self._ekf.state
        read = {r.target for r in records.values()} - fixed
        if not read and self._search is None:
            return state, fixed, weights
        mean, covariance = np.array(state.mean), np.array(state.covariance)
        newly = []
        if read:
            first = max(step - self._initialiser.window_steps + 1, self._origin)
            windows: dict[int, list[RangeMeasurement]] = {target: [] for target in read}
            for s in range(first, step + 1):
                for key in sorted(self._by_step.get(s, {})):  # (step, robot, target): a fixed order
                    if key[2] in windows:
                        windows[key[2]].append(self._by_step[s][key])
            for target in sorted(read):
                window = windows[target]
                result = self._initialiser.fix(self._motion, target, step, [r.step for r in window],
                                               np.array([r.sensor_position for r in window]),
                                               np.array([r.measured_range for r in window]))
                if result is None:
                    continue
                self._set_block(mean, covariance, target, result.position, result.covariance)
                newly.append(target)
        if self._search is not None:
            weights = self._search_step(step, records, fixed | frozenset(newly), weights, mean, covariance,
                                        newly)
        if not newly and self._search is None:
            return state, fixed, weights
        return FilterState(step, mean, covariance), fixed | frozenset(newly), weights

    @staticmethod
    def _set_block(mean: np.ndarray, covariance: np.ndarray, target: int, position: np.ndarray,
                   block_covariance: np.ndarray) -> None:
        block = slice(3 * target, 3 * target + 3)
        mean[block] = position
        covariance[block, :] = 0.0
        covariance[:, block] = 0.0
        covariance[block, block] = block_covariance

    def _search_step(self, step: int, records: Mapping[MeasurementKey, RangeMeasurement], fixed: frozenset[int],
                     weights: dict[int, np.ndarray], mean: np.ndarray, covariance: np.ndarray,
                     newly: list[int]) -> dict[int, np.ndarray]:
        """Weighs the hypotheses of the targets not ``fixed`` by this step's looks (a robot's records
        of a step travel together, so a robot with a record of this step read every target it saw),
        writes their moments into ``mean`` / ``covariance`` and fixes (appending to ``newly``) those
        that collapse. Returns the log-weights of the targets still not fixed."""
        space = self._search
        looks: dict[int, StepLooks] = {}
        for key in sorted(records):
            record = records[key]
            look = looks.setdefault(record.robot, StepLooks(np.array(record.sensor_position)))
            look.ranges[record.target] = record.measured_range
        ordered = [looks[robot] for robot in sorted(looks)]
        out: dict[int, np.ndarray] = {}
        for target in range(self.n_targets):
            if target in fixed:
                continue
            positions = self._hypothesis_motion.positions(space.points, target, step)
            log_weights = weights[target]
            if ordered:
                drift = float(self._motion.process_noise[3 * target, 3 * target]) * (step - self._prior.step)
                log_weights = update_log_weights(space, positions, log_weights, target, ordered, drift)
                result = collapse(positions, log_weights, space.cell_covariance,
                                  self._initialiser.accepted_variance_m2)
                if result is not None:
                    self._set_block(mean, covariance, target, *result)
                    newly.append(target)
                    continue
            self._set_block(mean, covariance, target, *moments(positions, log_weights, space.cell_covariance))
            out[target] = log_weights
        return out

    def _filter_next(self) -> FilterState:
        step = self.computed_until + 1
        if self._posteriors:
            self._ekf.reset(self._posteriors[-1])
            self._ekf.predict()
        elif self._root is not None:
            self._ekf.reset(self._root)
            self._ekf.predict()
        else:
            self._ekf.reset(self._prior)
        self.filtered_steps += 1
        records = self._by_step.get(step)
        if not records:
            return self._ekf.state
        return self._ekf.update(readings_from_records(records.values()))

    def mean_trajectory(self, start: int, stop: int) -> np.ndarray:
        """(stop - start, 3M) posterior means of steps start..stop-1, m."""
        return np.array([self.estimate(k).mean for k in range(start, stop)]).reshape(
            -1, 3 * self.n_targets
        )

    def forget_before(self, step: int) -> None:
        """Drop the checkpoints of steps < ``step``; later records of those
        steps are then rejected. Records themselves are kept."""
        if step <= self._origin:
            return
        self.estimate(step - 1)
        self._root = self._posteriors[step - 1 - self._origin]
        if self._initialiser is not None:
            self._root_fixed = self._fixed[step - 1 - self._origin]
            self._root_weights = self._weights[step - 1 - self._origin]
            del self._fixed[: step - self._origin]
            del self._weights[: step - self._origin]
        del self._posteriors[: step - self._origin]
        self._origin = step


class AgreementTracker:
    """Tracks the steps at which two beliefs' record sets differ.

    Only steps touched by new records are re-compared, so the cost follows
    the arrivals, not the run length.
    """

    def __init__(self, belief: Belief, reference: Belief):
        self.belief = belief
        self.reference = reference
        self._cursors = [0, 0]
        self._mismatched: set[int] = set()

    def _refresh(self) -> None:
        changed: set[int] = set()
        for side, holder in enumerate((self.belief, self.reference)):
            changed.update(r.step for r in holder.records_since(self._cursors[side]))
            self._cursors[side] = holder.n_records
        for step in changed:
            if self.belief.keys_at(step) == self.reference.keys_at(step):
                self._mismatched.discard(step)
            else:
                self._mismatched.add(step)

    def horizon(self, up_to: int) -> int:
        """Largest s <= ``up_to`` such that the record sets agree at every step
        0..s; -1 if they already differ at step 0."""
        self._refresh()
        differing = [s for s in self._mismatched if s <= up_to]
        return min(differing) - 1 if differing else up_to


@dataclass(frozen=True)
class PacketId:
    """Records ``robot`` collected after its meeting at ``epoch`` (0: before any)."""

    robot: int
    epoch: int


@dataclass(frozen=True)
class MeetingReport:
    """Outcome of one communication event.

    team, epoch: who met and when; new_to_team: records the team belief had
    not fused before; refilter_from: earliest step of those records (None if
    none); new_to_robot: {robot: records it had not heard before}.
    """

    team: int
    epoch: int
    new_to_team: int
    refilter_from: int | None
    new_to_robot: Mapping[int, int]


class NetworkBeliefs:
    """Information flow of Algorithm 5 over teams, plus the global belief.

    teams: the team structure; motion: the target model; prior: the common
    initial belief (Sec. IV: x^0, C(0) = 0.25 I); mirror_plane_z: passed to
    every belief's EKF (see :class:`estimation.ekf.TargetEKF`); initialiser:
    passed to every belief (see :class:`Belief`; None: the prior is informed).
    """

    def __init__(self, teams: TeamStructure, motion: TargetMotion, prior: FilterState,
                 mirror_plane_z: float | None = None, initialiser: ReadingsInitialiser | None = None):
        self.teams = teams
        self.global_belief = Belief(motion, prior, mirror_plane_z, initialiser)
        self.team_beliefs = tuple(Belief(motion, prior, mirror_plane_z, initialiser) for _ in range(teams.n_teams))
        self.robot_beliefs = {robot: Belief(motion, prior, mirror_plane_z, initialiser) for robot in teams.robots}
        # Arrival-list positions at the last meeting of each (robot, team) pair:
        # what the robot had then, and what the team had then.
        self._robot_cursor: dict[tuple[int, int], int] = {}
        self._team_cursor: dict[tuple[int, int], int] = {}
        self._last_epoch_of_robot = {robot: 0 for robot in teams.robots}
        self._last_epoch_of_team = [0] * teams.n_teams
        self._packets_of_robot: dict[int, set[PacketId]] = {robot: set() for robot in teams.robots}
        self._deliveries: dict[PacketId, dict[int, int]] = {}
        self._trackers = tuple(AgreementTracker(b, self.global_belief) for b in self.team_beliefs)

    def collect(self, robot: int, records: Iterable[RangeMeasurement]) -> None:
        """Robot ``robot`` logs its own readings; x_g fuses them at once."""
        if robot not in self.robot_beliefs:
            raise ValueError(f"robot: {robot} is in no team")
        records = list(records)
        strangers = {r.robot for r in records} - {robot}
        if strangers:
            raise ValueError(f"records: robot {robot} cannot collect readings of robot(s) {sorted(strangers)}")
        if not records:
            return
        self.robot_beliefs[robot].receive(records)
        self.global_belief.receive(records)
        packet = PacketId(robot, self._last_epoch_of_robot[robot])
        self._packets_of_robot[robot].add(packet)
        self._deliveries.setdefault(packet, {})

    def meet(self, team: int, epoch: int, present: tuple[int, ...] | None = None) -> MeetingReport:
        """Team ``team`` communicates at ``epoch``: its members (``present``: only those, the
        others being absent) pool what they gathered since they last met with this team,
        and the team belief fuses it."""
        if not 0 <= team < self.teams.n_teams:
            raise ValueError(f"team: {team} out of range for {self.teams.n_teams} teams")
        members = self.teams.members[team] if present is None else present
        for robot in members:
            if epoch <= self._last_epoch_of_robot[robot]:
                raise ValueError(
                    f"epoch: robot {robot} already met at epoch {self._last_epoch_of_robot[robot]}; "
                    f"its meetings must follow its schedule in increasing epochs, got {epoch}"
                )
        team_belief = self.team_beliefs[team]
        pooled: list[RangeMeasurement] = []
        for robot in members:
            pooled.extend(self.robot_beliefs[robot].records_since(self._robot_cursor.get((robot, team), 0)))
        fresh = [r for r in pooled if not team_belief.has(r.key)]
        new_to_team = team_belief.receive(fresh)
        new_to_robot = {}
        for robot in members:
            belief = self.robot_beliefs[robot]
            new_to_robot[robot] = belief.receive(team_belief.records_since(self._team_cursor.get((team, robot), 0)))
            self._team_cursor[(team, robot)] = team_belief.n_records
            self._robot_cursor[(robot, team)] = belief.n_records
            self._last_epoch_of_robot[robot] = epoch
        self._last_epoch_of_team[team] = epoch
        packets = set().union(*(self._packets_of_robot[robot] for robot in members))
        for robot in members:
            self._packets_of_robot[robot] = set(packets)
        for packet in packets:
            self._deliveries[packet].setdefault(team, epoch)
        return MeetingReport(
            team=team,
            epoch=epoch,
            new_to_team=new_to_team,
            refilter_from=min((r.step for r in fresh), default=None),
            new_to_robot=new_to_robot,
        )

    def outgoing(self, robot: int, team: int) -> list[RangeMeasurement]:
        """What ``robot`` has to send at its meeting with ``team``: the records it
        gathered or heard since it last met this team, less those the team
        belief already holds (the robot heard all of them at that meeting)."""
        team_belief = self.team_beliefs[team]
        return [r for r in self.robot_beliefs[robot].records_since(self._robot_cursor.get((robot, team), 0))
                if not team_belief.has(r.key)]

    def meet_over_radio(self, team: int, epoch: int, sent: Mapping[int, Sequence[RangeMeasurement]],
                        heard: Mapping[int, Iterable[int]], cursors: Mapping[int, int]) -> MeetingReport:
        """Team ``team``'s meeting at ``epoch`` when its exchange went over a radio.

        sent: per member, the records it sent (:meth:`outgoing` when it sent);
        heard: per member, the members whose records reached it; cursors: per
        member, its robot belief's ``n_records`` when it sent. Each member's
        belief takes what reached it. The team belief (what the team plans with)
        takes only the records of the members that reached every other member:
        those all members hold. A member whose records did not is not cut off
        at its cursor, so what it sent goes again at its next meeting with the
        team. Every member's epoch advances either way (the meeting is over).
        With every member heard by all, this is :meth:`meet` on what was sent.
        """
        if not 0 <= team < self.teams.n_teams:
            raise ValueError(f"team: {team} out of range for {self.teams.n_teams} teams")
        members = tuple(self.teams.members[team])
        for robot in members:
            if epoch <= self._last_epoch_of_robot[robot]:
                raise ValueError(
                    f"epoch: robot {robot} already met at epoch {self._last_epoch_of_robot[robot]}; "
                    f"its meetings must follow its schedule in increasing epochs, got {epoch}"
                )
        heard_by = {robot: set(heard.get(robot, ())) - {robot} for robot in members}
        shared = [s for s in members if all(s in heard_by[r] for r in members if r != s)]
        team_belief = self.team_beliefs[team]
        pooled = [record for s in shared for record in sent.get(s, ())]
        fresh = [r for r in pooled if not team_belief.has(r.key)]
        new_to_team = team_belief.receive(fresh)
        new_to_robot = {}
        packets_of = {robot: set(self._packets_of_robot[robot]) for robot in members}
        for robot in members:
            belief = self.robot_beliefs[robot]
            new_to_robot[robot] = sum(belief.receive(sent.get(s, ())) for s in sorted(heard_by[robot]))
            for s in heard_by[robot]:
                self._packets_of_robot[robot] |= packets_of[s]
            self._team_cursor[(team, robot)] = team_belief.n_records
            if robot in shared:
                self._robot_cursor[(robot, team)] = int(cursors[robot])
            self._last_epoch_of_robot[robot] = epoch
        self._last_epoch_of_team[team] = epoch
        for s in shared:
            for packet in packets_of[s]:
                self._deliveries[packet].setdefault(team, epoch)
        return MeetingReport(
            team=team,
            epoch=epoch,
            new_to_team=new_to_team,
            refilter_from=min((r.step for r in fresh), default=None),
            new_to_robot=new_to_robot,
        )

    def last_epoch_of_robot(self, robot: int) -> int:
        """Epoch of the robot's last meeting (0 before its first)."""
        return self._last_epoch_of_robot[robot]

    @property
    def deliveries(self) -> dict[PacketId, dict[int, int]]:
        """{packet: {team: epoch the team first received it}} (a copy)."""
        return {packet: dict(teams) for packet, teams in self._deliveries.items()}

    def agreement_horizon(self, team: int, step: int) -> int:
        """t*(t) of eq. (14) at t = ``step``: the last step up to which team
        ``team`` has fused exactly the global record sets (-1: none)."""
        return self._trackers[team].horizon(step)

    def local_error(self, team: int, step: int) -> float:
        """e_i(t) of eq. (14) at t = ``step``, m: mean ||x_g(s) - x_Ti(s)|| over
        s = t*(t)+1..t (0 when t*(t) = t); see ``estimation.metrics``."""
        start = self.agreement_horizon(team, step) + 1
        return local_error(
            self.global_belief.mean_trajectory(start, step + 1),
            self.team_beliefs[team].mean_trajectory(start, step + 1),
        )

    def team_estimate(self, team: int, step: int) -> FilterState:
        return self.team_beliefs[team].estimate(step)

    def global_estimate(self, step: int) -> FilterState:
        return self.global_belief.estimate(step)
