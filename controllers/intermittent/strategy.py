"""Algorithm 5 of Khodayi-mehr et al. 2019 on MuJoCo ground robots: ``strategy.kind = "intermittent"``.

Every robot r_ij follows its communication schedule sched_ij forever
(:mod:`controllers.intermittent.schedules`). It drives along the planned path
segment p^k_ij to its next team meeting while taking a range reading of every
target in sight each step (1 s); when all members of the team have reached
the end of their segments and the team's communication graph, read from the
simulator's links (range and line of sight), is connected, the meeting is
*held*: the members exchange their logs (:meth:`NetworkBeliefs.meet`, Alg. 5
lines 3-4) and plan, from the team belief, the segments to the team's next
meeting T epochs later (line 5, :func:`plan_meeting`). Each robot then sets
off on its already planned segment to its other team's meeting; the new
segment starts where that one ends (Sec. III-B, Fig. 2). The paths to the
first meetings (epochs 1..T) are planned a priori from the prior belief
(footnote 4).

Execution on real bodies. Plans are single-integrator paths at integer steps
with |u| <= u_max; a robot tracks p(t) sampled every control tick
(reference position and velocity, see :class:`TimedPath`) with the
foundation's point-offset wheel controller. Bodies lag their references and
meetings are held only once every member has arrived and the team is
connected, so a robot's next segment starts when the meeting is actually
held: its path is executed from that moment (a time offset), and the next
plan of a team starts each member at the planned end of its committed
segment shifted by that member's offset, rounded up to a whole step.
Whoever arrives first waits (recorded: ``max_wait_s``). If every member has
finished but the team graph is not connected after ``gather_after_s``, the
members close in on the centroid of their meeting points until it is.

Planning time. The simulation loop is synchronous: planning runs inside
``step()`` and takes wall-clock time, not simulated time (the robots do not
move while the team plans). ``plan_time_*`` report the wall time per
meeting; the benchmark compares it with the time the robots take to the
next meeting.

Planner failure. If Algorithm 1 finds no goal node for any target (it
already falls back to less uncertain targets, Sec. IV), it is run again with
fresh samples up to ``max_replans`` times; if that fails too, the team meets
again where it just met (each member returns on its geodesic path), or, for
an a-priori plan, around the start of the member that starts last. The
schedule is never broken: the meeting still takes place at its epoch.

Under a real radio (``radio.preset`` other than ``ideal``) the exchange of
lines 3-4 goes over the message bus: a meeting starts when every member has
arrived and the team's communication graph is connected; each member sends
the others its records (``"range_records"``, over a ``ReliableLink``); the
meeting is held once every member has every other member's records, or ends
at ``exchange_timeout_s`` with the team belief fusing only what every member
received (``NetworkBeliefs.meet_over_radio``; docs/radio.md). Under ``ideal``
the logs are pooled the tick the team is connected, as above.

``random_meeting`` (:mod:`controllers.baselines.random_meeting`) reuses all
of this and only designs the segments differently.
"""

from __future__ import annotations

import dataclasses
import math
import time
from abc import abstractmethod
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from controllers.baselines.geodesic import GeodesicPlanner, timed_waypoints
from controllers.intermittent.params import IntermittentParams
from controllers.intermittent.planner import PlanningProblem, RobotPath, plan_meeting
from controllers.intermittent.planner_geometry import edges_free, points_free
from controllers.intermittent.runtime import (
    EstimateSeries,
    PlanningWorld,
    TimedPath,
    as_config_error,
    check_time_base,
    commands_from_plane,
    lifted,
    measurement_records,
    planner_params,
    LAG_HOLD_M,
    LagHolds,
    prior_state,
    team_samples,
    separated_references,
    shifted,
    team_color,
    team_path_style,
)
from controllers.intermittent.schedules import build_schedule
from controllers.task import SEARCH_PLAN_VARIANCE_M2, neutral_prior, target_initialiser
from estimation.beliefs import NetworkBeliefs
from estimation.ekf import FilterState
from estimation.metrics import delay_report
from sim import palette
from sim.config import ConfigError
from sim.geometry import pairwise_min_distance
from sim.radio.bus import range_records_bytes
from sim.radio.protocols import Outbox, ReliableLink, deliveries_of
from sim.types import Commands, Decorations, Observation, SceneChange, WorldInfo
from sim.strategy import Strategy

RECORDS_KIND = "range_records"  # the bus's message kind of a meeting's exchange

RING_RADIUS_M = 0.06  # members of a geodesic meeting stop on a ring this wide around its point, m
IDLE_COLOR = palette.IDLE


@dataclass
class Exchange:
    """A meeting's exchange of range records over the radio: each member sends
    the others what it has for the team (``NetworkBeliefs.outgoing``)."""

    started_s: float  # sim time the members sent, s
    sent: dict[int, list]  # robot -> the records it sent
    cursors: dict[int, int]  # robot -> its belief's record count when it sent
    heard: dict[int, set[int]]  # robot -> the members whose records reached it

    def complete(self, members: tuple[int, ...]) -> bool:
        return all(self.heard[r] >= set(members) - {r} for r in members)


@dataclass
class Meeting:
    """One communication event (team, epoch) and what happened at it."""

    team: int
    epoch: int
    members: tuple[int, ...]
    planned_time_s: float  # meeting time of the plan, s
    points: np.ndarray  # (n, 2) each member's meeting position, m
    target: int | None = None  # target whose goal condition the plan met (None: not planned informatively)
    fallback: bool = False
    arrivals: dict[int, float] = field(default_factory=dict)  # robot -> sim time it arrived, s
    finished_since: float | None = None
    gathering: bool = False
    held_s: float | None = None
    connected: bool = False
    positions_at_hold: np.ndarray | None = None  # (n, 2) body positions when held, m
    exchange: Exchange | None = None  # under a real radio: the records sent and received
    timed_out: bool = False  # ended at strategy.exchange_timeout_s without every member's records
    absent: tuple[int, ...] = ()  # members not at their point after strategy.member_timeout_s: held without them

    def point_of(self, robot: int) -> np.ndarray:
        return self.points[self.members.index(robot)]


@dataclass
class Segment:
    """A robot's path to one meeting, executed from a sim-time offset."""

    meeting: Meeting
    timed: TimedPath
    started: bool = False
    arrive_step: int = 0  # step from which the path stays at its end point

    @staticmethod
    def of(meeting: Meeting, path: RobotPath, step_s: float) -> "Segment":
        end = path.positions[-1]
        moving = np.flatnonzero(np.linalg.norm(path.positions - end, axis=1) > 1e-9)
        arrive = int(path.times[moving[-1] + 1]) if len(moving) else path.start_time
        return Segment(meeting, TimedPath(path, step_s), False, arrive)

    def at_end(self, t: float) -> bool:
        return self.started and self.timed.tau(t) >= self.arrive_step - 1e-9


@dataclass(frozen=True)
class MemberStart:
    """Where and when a member's new segment starts, and its committed path before."""

    position: np.ndarray  # (2,) m
    time: int  # step
    prefix: RobotPath | None


@dataclass(frozen=True)
class TeamDesign:
    """The segments a team designed for its next meeting."""

    paths: tuple[RobotPath, ...]
    meeting_time: int  # step
    points: np.ndarray  # (n, 2) m
    target: int | None
    plan_time_s: float  # wall time spent designing, s
    cost_time_s: float  # part of it in the EKF cost (Alg. 4), s
    failures: int  # planner runs without a plan
    fallback: bool


def team_connected(adjacency: np.ndarray, members: tuple[int, ...]) -> bool:
    """The team's communication graph (links among its members) is connected (no member: not)."""
    if not members:
        return False
    sub = np.asarray(adjacency)[np.ix_(members, members)]
    seen = {0}
    frontier = [0]
    while frontier:
        i = frontier.pop()
        for j in np.flatnonzero(sub[i]):
            if int(j) not in seen:
                seen.add(int(j))
                frontier.append(int(j))
    return len(seen) == len(members)


def linked_groups(adjacency: np.ndarray, robots: list[int]) -> list[tuple[int, ...]]:
    """The connected components of the graph among ``robots``, largest first (ties: lowest robot first)."""
    adjacency = np.asarray(adjacency)
    left, groups = set(robots), []
    while left:
        start = min(left)
        group, frontier = {start}, [start]
        while frontier:
            i = frontier.pop()
            for j in list(left - group):
                if adjacency[i, j]:
                    group.add(j)
                    frontier.append(j)
        left -= group
        groups.append(tuple(sorted(group)))
    return sorted(groups, key=lambda g: (-len(g), g[0]))


def ring_points(center: np.ndarray, n: int, geodesic: GeodesicPlanner, radius: float = RING_RADIUS_M) -> np.ndarray:
    """n stopping points on a small ring around ``center`` (all free), else all at the centre."""
    if n == 1:
        return center[None].copy()
    for turn in np.linspace(0.0, 2 * np.pi, 8, endpoint=False):
        angles = turn + 2 * np.pi * np.arange(n) / n
        points = center + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1)
        if geodesic.is_free(points).all() and edges_free(
            geodesic.boxes, np.broadcast_to(center, points.shape), points, geodesic.z, geodesic.margin
        ).all():
            return points
    return np.repeat(center[None], n, axis=0)


def _farther_than(point: list[float], x: float, y: float, limit: float) -> bool:
    """Whether np.linalg.norm(point - (x, y)) > limit, decided as numpy would without its arrays.

    The norm's BLAS dot may fuse a multiply-add, so its last bit can differ from this plain sum of
    squares; only within a relative 1e-9 of the limit is that close enough to matter, and there
    numpy decides."""
    dx, dy = point[0] - x, point[1] - y
    squared, bound = dx * dx + dy * dy, limit * limit
    if abs(squared - bound) > 1e-9 * bound:
        return squared > bound
    return float(np.linalg.norm(np.array((dx, dy)))) > limit


class MeetingStrategy(Strategy):
    """Teams, schedules, beliefs and meetings on ground robots; subclasses
    design the segments (:meth:`design`)."""

    kind = "meetings"

    def __init__(self, params: IntermittentParams):
        self.params = params

    @classmethod
    def adapt_to_scene(cls, strategy_table: dict, change: SceneChange, keep: frozenset[str]) -> list[str]:
        """In another scene the EKF prior is made non-informative (:func:`controllers.task.neutral_prior`)."""
        return neutral_prior(strategy_table, change, keep)

    # ------------------------------------------------------------------ set-up
    def reset(self, world: WorldInfo, initial: Observation, rng: np.random.Generator) -> None:
        params = self.params
        self.step_s = check_time_base(world)
        n = world.n_robots
        try:
            self.teams = params.team_structure(n)
        except ValueError as err:
            raise as_config_error(err) from None
        self.world = world
        self.rng = rng
        self.schedule = build_schedule(self.teams)
        self.planning = PlanningWorld.from_world(world, initial)
        self.planner = planner_params(params, world, self.planning)
        self.motion = world.target_motion
        self.prior = prior_state(params, world.n_targets)
        mirror = self.planning.sensor_height if params.resolve_mirror else None
        self.beliefs = NetworkBeliefs(self.teams, self.motion, self.prior, mirror_plane_z=mirror,
                                      initialiser=target_initialiser(params, world))
        self.series = EstimateSeries()
        # Without an informed prior, plans look for the targets not yet fixed (search_estimate); its
        # draws come from a stream of their own, so the informed prior's runs draw as before.
        self.search_rng = rng.spawn(1)[0] if params.init_from_readings else None
        starts = initial.position[:, :2].copy()
        free = points_free(self.planning.boxes, self.planning.bounds, starts, self.planning.sensor_height,
                           params.clearance_m)
        if not free.all():
            robot = int(np.flatnonzero(~free)[0])
            raise ConfigError("robots", f"robot {robot} starts at {tuple(np.round(starts[robot], 3))}, closer than "
                              f"strategy.clearance_m = {params.clearance_m} m to a wall or the scene bounds")
        self.geodesic = GeodesicPlanner(self.planning.boxes, self.planning.bounds, self.planning.sensor_height,
                                        params.clearance_m)
        self.queues: list[deque[Segment]] = [deque() for _ in range(n)]
        self.meetings: list[Meeting] = []
        self.initial_xy = starts
        self.last_step: int | None = None
        self.plan_times: list[float] = []
        self.cost_times: list[float] = []
        self.plan_failures = 0
        self.plan_fallbacks = 0
        self.waits: list[float] = []
        self.lags: list[tuple[int, int, float]] = []  # (step, t*, e_i) of the lag team
        self.events: list[str] = []
        self._scalars: dict[str, float] = {}
        self._visual_dirty = True
        self._visual = Decorations()
        self._time_s = 0.0
        self.held_ticks = 0  # robot-ticks a path clock waited for its lagging body
        self.lag_holds = LagHolds(n, world.control_period_s)
        self.closest_m = math.inf  # closest approach of two robot bodies over the run, m
        # Under the ideal radio a meeting's members pool their logs the tick they meet (Alg. 5), as the
        # paper has it; under a real one the records travel over the bus (docs/radio.md).
        self.over_radio = initial.radio is not None and initial.radio.preset != "ideal"
        self.outbox = Outbox()
        attempts = max(1, math.ceil(params.exchange_timeout_s / params.retransmit_after_s))
        self.links = [ReliableLink(self.outbox, r, timeout_s=params.retransmit_after_s, max_attempts=attempts)
                      for r in range(n)]
        self.exchange_times: list[float] = []  # exchange start to the meeting's end, s
        self.records_sent = 0  # range records handed to the bus, every copy (each member, each retransmission), -
        self.open_exchanges: dict[tuple[int, int], Meeting] = {}  # (team, epoch) -> meeting exchanging
        self.members_given_up: list[tuple[int, float]] = []  # (robot, sim time a meeting went on without it)
        # Footnote 4: the paths to the first meeting of every team, a priori.
        for epoch in range(1, self.schedule.period + 1):
            for team in self.schedule.teams_meeting_at(epoch):
                self._plan(team, epoch, belief_step=0, estimate=self.prior)
        for queue in self.queues:
            queue[0].started = True
            queue[0].timed.offset_s = 0.0
        self._scalars.update({"lambda_max_m2": float(np.linalg.eigvalsh(self.prior.covariance)[-1]),
                              "t_star_s": math.nan, "t_star_lag_s": 0.0, "local_error_m": 0.0, "meetings_held": 0.0,
                              "robots_waiting": 0.0})

    # ------------------------------------------------------------- designing
    @abstractmethod
    def design(self, team: int, epoch: int, members: tuple[int, ...], starts: list[MemberStart],
               belief_step: int, estimate: FilterState) -> TeamDesign:
        """The paths of ``members`` (from ``starts``) to their meeting at ``epoch``,
        planned on the team's belief at ``belief_step`` (``estimate``)."""

    def _member_start(self, robot: int, not_before: int) -> MemberStart:
        """The end of the robot's last committed segment (its start before any), no earlier than step
        ``not_before`` (the plan's belief step): a member given up at a meeting still holds its segment
        to that meeting, which it can now end only late."""
        queue = self.queues[robot]
        if not queue:
            return MemberStart(self.initial_xy[robot].copy(), 0, None)
        last = queue[-1]
        shift = int(math.ceil(max(last.timed.offset_s, 0.0) / self.step_s - 1e-9))
        shift = max(shift, not_before - last.timed.path.end_time)
        path = shifted(last.timed.path, shift)
        return MemberStart(path.positions[-1].copy(), path.end_time, path)

    def _plan(self, team: int, epoch: int, belief_step: int, estimate: FilterState) -> Meeting:
        members = tuple(self.teams.members[team])
        starts = [self._member_start(r, belief_step) for r in members]
        design = self.design(team, epoch, members, starts, belief_step, estimate)
        self.plan_times.append(design.plan_time_s)
        self.cost_times.append(design.cost_time_s)
        self.plan_failures += design.failures
        self.plan_fallbacks += int(design.fallback)
        meeting = Meeting(team, epoch, members, design.meeting_time * self.step_s, np.array(design.points),
                          design.target, design.fallback)
        self.meetings.append(meeting)
        for robot, path in zip(members, design.paths):
            self.queues[robot].append(Segment.of(meeting, path, self.step_s))
        what = "fallback meeting" if design.fallback else (
            f"target {design.target}" if design.target is not None else "random meeting point")
        self.events.append(
            f"team {team} planned epoch {epoch}: meet at t = {meeting.planned_time_s:.0f} s ({what}; "
            f"{design.plan_time_s:.2f} s wall{', %d failed runs' % design.failures if design.failures else ''})"
        )
        self._visual_dirty = True
        return meeting

    def search_estimate(self, team: int, belief_step: int, estimate: FilterState) -> FilterState:
        """The belief a team plans with when it looks for targets it has not fixed: each such
        target's block becomes one of its search hypotheses, drawn by weight (Thompson sampling:
        teams go where a target is likely, and a look that finds nothing there moves the weight
        elsewhere), with :data:`SEARCH_PLAN_VARIANCE_M2` I as its covariance, so the planner's
        goal (the most uncertain target brought below delta) sends the team to look there.
        Unchanged without a search (the informed prior)."""
        if self.search_rng is None:
            return estimate
        belief = self.beliefs.team_beliefs[team]
        mean, covariance = np.array(estimate.mean), np.array(estimate.covariance)
        changed = False
        for target in range(self.world.n_targets):
            hypotheses = belief.hypotheses(belief_step, target)
            if hypotheses is None:
                continue
            positions, weights = hypotheses
            block = slice(3 * target, 3 * target + 3)
            mean[block] = positions[self.search_rng.choice(len(weights), p=weights)]
            covariance[block, :] = 0.0
            covariance[:, block] = 0.0
            covariance[block, block] = SEARCH_PLAN_VARIANCE_M2 * np.eye(3)
            changed = True
        return FilterState(estimate.step, mean, covariance) if changed else estimate

    def geodesic_design(self, members: tuple[int, ...], starts: list[MemberStart], points: np.ndarray) -> TeamDesign | None:
        """Geodesic paths from the starts to ``points`` at full speed; every
        member waits at its point until the last one arrives."""
        u_max = self.params.speed_mps * self.step_s
        timed = []
        for start, goal in zip(starts, points):
            waypoints = self.geodesic.path(start.position, goal)
            if waypoints is None:
                return None
            times, positions = timed_waypoints(waypoints, start.time, u_max)
            if len(times) == 1:  # already there: stay one step
                times, positions = np.array([start.time, start.time + 1]), np.vstack([positions, positions])
            timed.append((times, positions))
        meeting_time = max(int(t[-1]) for t, _ in timed)
        paths = []
        for times, positions in timed:
            if times[-1] < meeting_time:
                times = np.append(times, meeting_time)
                positions = np.vstack([positions, positions[-1]])
            paths.append(RobotPath(times, positions))
        return TeamDesign(tuple(paths), meeting_time, np.array(points), None, 0.0, 0.0, 0, False)

    # ----------------------------------------------------------------- running
    def _take_readings(self, observation: Observation) -> None:
        step = observation.target_step
        if abs(observation.time_s - step * self.step_s) > 1e-6 or (
                self.last_step is not None and step != self.last_step + 1):
            raise ConfigError("sensing.period_s", f"readings must come once per period (reading of step {step} "
                              f"at t = {observation.time_s:.3f} s)")
        for robot, records in enumerate(measurement_records(observation, step)):
            self.beliefs.collect(robot, records)
        self.last_step = step
        lam = self.series.record(self.beliefs.global_estimate(step))
        team = self.params.lag_team
        agreement = self.beliefs.agreement_horizon(team, step)
        local = self.beliefs.local_error(team, step)
        self.lags.append((step, agreement, local))
        self._scalars["lambda_max_m2"] = lam
        # t*(t) of eq. (14), Fig. 7; undefined (NaN: a gap in the plots) until the team agrees on a step.
        self._scalars["t_star_s"] = agreement * self.step_s if agreement >= 0 else math.nan
        self._scalars["t_star_lag_s"] = (step - agreement) * self.step_s
        self._scalars["local_error_m"] = local

    def _adjacency(self, observation: Observation) -> np.ndarray:
        """The graph a meeting needs connected: the disk under the ideal radio, else the communication graph."""
        if self.over_radio:
            return observation.radio.comm_adjacency
        return observation.links.adjacency

    def _start_exchange(self, meeting: Meeting, t: float) -> None:
        """Every member sends each other member its records for the team, reliably."""
        sent, cursors = {}, {}
        for robot in meeting.members:
            records = self.beliefs.outgoing(robot, meeting.team)
            sent[robot] = records
            cursors[robot] = self.beliefs.robot_beliefs[robot].n_records
            for other in meeting.members:
                if other != robot:
                    self.links[robot].send(RECORDS_KIND, other, (meeting.team, meeting.epoch, tuple(records)),
                                           range_records_bytes(len(records)), t)
        meeting.exchange = Exchange(t, sent, cursors, {r: set() for r in meeting.members})
        self.open_exchanges[(meeting.team, meeting.epoch)] = meeting

    def _receive_records(self, observation: Observation) -> None:
        """Poll every robot's link: note whose records reached whom; a copy after its meeting ended
        still goes into the receiver's own belief."""
        t = observation.time_s
        open_exchanges = self.open_exchanges
        inbox = observation.inbox
        for robot, link in enumerate(self.links):
            if not link.pending and not (inbox and inbox[robot]):
                continue  # nothing arrived and nothing to retransmit
            events = link.poll(t, deliveries_of(inbox, robot, RECORDS_KIND))
            for got in events.received:
                team, epoch, records = got.data
                meeting = open_exchanges.get((team, epoch))
                if meeting is not None:
                    meeting.exchange.heard[robot].add(got.sender)
                else:
                    self.beliefs.robot_beliefs[robot].receive(records)

    def _hold(self, meeting: Meeting, observation: Observation, timed_out: bool = False,
              members: tuple[int, ...] | None = None) -> None:
        t = observation.time_s
        present = meeting.members if members is None else members
        meeting.held_s = t
        meeting.timed_out = timed_out
        meeting.connected = team_connected(self._adjacency(observation), present)
        meeting.positions_at_hold = observation.position[list(meeting.members), :2].copy()
        exchange = meeting.exchange
        if exchange is None:
            report = self.beliefs.meet(meeting.team, meeting.epoch, None if members is None else present)
        else:
            report = self.beliefs.meet_over_radio(meeting.team, meeting.epoch, exchange.sent, exchange.heard,
                                                  exchange.cursors)
            self.exchange_times.append(t - exchange.started_s)
            del self.open_exchanges[(meeting.team, meeting.epoch)]
        for robot in present:
            self.waits.append(t - meeting.arrivals.get(robot, t))
            done = self.queues[robot].popleft()
            assert done.meeting is meeting
            if not self.queues[robot]:
                raise RuntimeError(f"robot {robot} has no committed segment after epoch {meeting.epoch}")
            following = self.queues[robot][0]
            following.started = True
            following.timed.offset_s = max(0.0, t - following.timed.path.start_time * self.step_s)
        if timed_out:
            missing = sorted(r for r in meeting.members if exchange.heard[r] < set(meeting.members) - {r})
            self.events.append(
                f"meeting timed out: team {meeting.team} epoch {meeting.epoch} at t = {t:.1f} s, records still "
                f"missing at robot(s) {missing} after {self.params.exchange_timeout_s:g} s; "
                f"{report.new_to_team} readings fused")
        else:
            self.events.append(
                f"meeting held: team {meeting.team} epoch {meeting.epoch} at t = {t:.1f} s "
                f"(planned {meeting.planned_time_s:.0f} s), {report.new_to_team} new readings"
            )
        belief_step = self.last_step if self.last_step is not None else 0
        estimate = self.beliefs.team_estimate(meeting.team, belief_step)
        self._plan(meeting.team, meeting.epoch + self.schedule.period, belief_step, estimate)
        self._scalars["meetings_held"] = float(sum(m.held_s is not None and not m.timed_out for m in self.meetings))

    def _gather_reference(self, meeting: Meeting, robot: int, t: float) -> np.ndarray:
        """Close in on the centroid of the meeting points at full speed."""
        point = meeting.point_of(robot)
        goal = meeting.points.mean(axis=0)
        if not self.geodesic.is_free(goal[None])[0]:
            goal = meeting.points[np.argmin(np.linalg.norm(meeting.points - goal, axis=1))]
        gap = goal - point
        distance = float(np.linalg.norm(gap))
        if distance < 1e-9:
            return point.copy()
        travelled = self.params.speed_mps * (t - meeting.finished_since - self.params.gather_after_s)
        return point + gap * min(1.0, max(travelled, 0.0) / distance)

    def step(self, observation: Observation) -> Commands:
        t = observation.time_s
        self._time_s = t
        if self.over_radio:
            self._receive_records(observation)
        if observation.target_ranges is not None:
            self._take_readings(observation)
        xy = observation.position[:, :2]
        heads: dict[int, Meeting] = {}
        for robot, queue in enumerate(self.queues):
            segment = queue[0]
            if segment.meeting.held_s is not None:  # held without this robot
                if not self._pass_held(robot, t):
                    continue  # still on its way to the point
                segment = queue[0]
            meeting = segment.meeting
            heads[id(meeting)] = meeting
            if robot not in meeting.arrivals and segment.started and (  # Segment.at_end inline
                    (t - segment.timed.offset_s) / segment.timed.step_s >= segment.arrive_step - 1e-9) and (
                    np.linalg.norm(xy[robot] - meeting.point_of(robot)) <= self.params.arrival_tolerance_m):
                meeting.arrivals[robot] = t
        for meeting in sorted(heads.values(), key=lambda m: m.epoch):
            absent = self._absent_members(meeting, t, self._adjacency(observation))
            if absent:
                self._hold_without(meeting, observation, absent)
                continue
            if not self._ready(meeting, t):
                continue
            if meeting.exchange is not None:  # under a real radio: the records are on their way
                if meeting.exchange.complete(meeting.members):
                    self._hold(meeting, observation)
                elif t - meeting.exchange.started_s >= self.params.exchange_timeout_s - 1e-9:
                    self._hold(meeting, observation, timed_out=True)
            elif team_connected(self._adjacency(observation), meeting.members):
                if self.over_radio:
                    self._start_exchange(meeting, t)
                else:
                    self._hold(meeting, observation)
            elif meeting.finished_since is None:
                meeting.finished_since = t
            elif t - meeting.finished_since >= self.params.gather_after_s and not meeting.gathering:
                meeting.gathering = True
                self.events.append(f"team {meeting.team} epoch {meeting.epoch}: not connected "
                                   f"{self.params.gather_after_s:.0f} s after arrival, closing in")
        references = []  # per robot (x, y, vx, vy): Python floats, one array at the end
        body = xy.tolist()
        waiting = 0
        for robot, queue in enumerate(self.queues):
            segment = queue[0]
            timed = segment.timed
            # TimedPath.tau, finished and Segment.at_end inline: the same arithmetic, once per robot
            tau = (t - timed.offset_s) / timed.step_s
            if segment.meeting.gathering:
                x, y = self._gather_reference(segment.meeting, robot, t)
                vx = vy = 0.0
            else:
                (x, y), (vx, vy) = timed.reference_at_tau(tau)
                on_path = segment.started and not tau >= timed.end_step - 1e-9
                lagging = on_path and _farther_than(body[robot], x, y, LAG_HOLD_M)
                holds = self.lag_holds
                if (lagging or holds.engaged(robot)) and holds.wait(
                        robot, lagging, t, math.hypot(body[robot][0] - x, body[robot][1] - y) if on_path else 0.0):
                    # Time scaling: the body lags (a sharp turn, a push); its path clock waits for it.
                    timed.offset_s += self.world.control_period_s
                    self.held_ticks += 1
                    tau = (t - timed.offset_s) / timed.step_s
                    (x, y), _ = timed.reference_at_tau(tau)
                    vx = vy = 0.0
            references.append((x, y, vx, vy))
            if segment.started and tau >= segment.arrive_step - 1e-9:
                waiting += 1
        table = np.array(references, dtype=float).reshape(-1, 4)
        positions, velocities = table[:, :2], table[:, 2:]
        self._scalars["robots_waiting"] = float(waiting)
        closest = pairwise_min_distance(xy)
        positions = separated_references(positions, xy, self.planning, velocities, closest)
        self.closest_m = min(self.closest_m, closest)
        commands = commands_from_plane(observation, positions, velocities)
        if self.over_radio:
            outbox = self.outbox.drain()
            self.records_sent += sum(len(m.payload.data[2]) for m in outbox if m.kind == RECORDS_KIND)
            commands = dataclasses.replace(commands, outbox=outbox)
        if observation.decorations_wanted:
            return dataclasses.replace(commands, scalars=self._scalars, estimate=self.series.estimate,
                                       decorations=self._decorations(t))
        # No observer reads the figures and decorations: only the estimate (sim.types.Observation).
        return dataclasses.replace(commands, estimate=self.series.estimate)

    def _absent_members(self, meeting: Meeting, t: float, adjacency: np.ndarray) -> tuple[int, ...]:
        """The members the meeting goes on without once every member at its point has waited
        ``member_timeout_s`` past the meeting's planned time (empty: keep waiting).

        The wait counts from the later of the last arrival and the planned meeting time: a member that
        came early (random_meeting's geodesics of different lengths, all planned to end at the meeting
        time) waits for the others by design, and a member still on its way before the meeting is due is
        not late. Only a member ``member_timeout_s`` behind the plan is given up.

        Absence is judged by what the members hear, never from the simulator's faults: a member counts
        as present when it is at its point (its current segment leading there) and linked, in the team's
        communication graph (``adjacency``: the one the meeting needs connected), to the others there.
        The largest such group goes on; if several are as large (a pair out of each other's hearing),
        none is the team and every member goes on alone. A dead robot sitting on its point is thus
        absent as much as one that never came."""
        timeout = self.params.member_timeout_s
        if not math.isfinite(timeout) or meeting.held_s is not None or meeting.exchange is not None:
            return ()
        arrived = [r for r in meeting.members if r in meeting.arrivals and self.queues[r][0].meeting is meeting]
        if not arrived or t - max(meeting.planned_time_s, *(meeting.arrivals[r] for r in arrived)) < timeout - 1e-9:
            return ()
        groups = linked_groups(adjacency, arrived)
        largest = max(len(g) for g in groups)
        heard = groups[0] if sum(len(g) == largest for g in groups) == 1 else ()
        if len(heard) == len(meeting.members):
            return ()  # everybody is here and heard: the meeting is held as usual
        return tuple(r for r in meeting.members if r not in heard)

    def _hold_without(self, meeting: Meeting, observation: Observation, absent: tuple[int, ...]) -> None:
        """Hold the meeting with the members that came; an absent member's segment to it is dropped."""
        t = observation.time_s
        meeting.absent = absent
        self.members_given_up.extend((r, t) for r in absent)
        # An absent member keeps its segment: its next one was planned from this meeting's point, so it goes
        # there first (a late one on its collision-free path, not across the walls) and then on (_pass_held).
        present = tuple(r for r in meeting.members if r not in absent)
        self.events.append(f"team {meeting.team} epoch {meeting.epoch}: robot(s) {list(absent)} not heard at the meeting "
                           f"{self.params.member_timeout_s:g} s after the others arrived; held without them")
        self._hold(meeting, observation, members=present)

    def _pass_held(self, robot: int, t: float) -> bool:
        """A member given up at its head segment's meeting, once at the end of that segment: on to its next
        segment (True), as the members that met went on. False while it is still on its way (or has no
        later segment yet: it waits at the point)."""
        queue = self.queues[robot]
        if not queue[0].at_end(t) or len(queue) < 2:
            return False
        queue.popleft()
        following = queue[0]
        following.started = True
        following.timed.offset_s = max(0.0, t - following.timed.path.start_time * self.step_s)
        return True

    def _ready(self, meeting: Meeting, t: float) -> bool:
        """Every member's current segment leads to ``meeting`` and has reached its end."""
        queues = self.queues
        for r in meeting.members:
            segment = queues[r][0]
            if segment.meeting is not meeting or not segment.at_end(t):
                return False
        return True

    # ---------------------------------------------------------------- outputs
    def _refresh_visual(self) -> None:
        colors, paths, styles, points, point_colors = [], [], [], [], []
        for robot, queue in enumerate(self.queues):
            colors.append(team_color(queue[0].meeting.team) if queue else IDLE_COLOR)
            # Only the path to the next meeting: later ones of eight teams crossed the middle in a tangle.
            if queue:
                paths.append((lifted(queue[0].timed.path.positions), team_color(queue[0].meeting.team)))  # opaque: cheaper
                styles.append(team_path_style(queue[0].meeting.team))
        pending = {id(s.meeting): s.meeting for q in self.queues for s in q}
        for meeting in pending.values():
            rgba = team_color(meeting.team).copy()
            rgba[3] = 0.5
            for p in meeting.points:
                points.append(lifted(p))
                point_colors.append(rgba)
        self._visual = Decorations(
            legend=(*((f"team {k} robots, {team_path_style(k)} path", team_color(k))
                      for k in range(len(self.teams.members))),
                    ("robot with no meeting planned", IDLE_COLOR)),
            robot_colors=np.array(colors),
            paths=paths,
            path_styles=tuple(styles),
            meeting_points=np.array(points).reshape(-1, 3),
            meeting_point_colors=np.array(point_colors).reshape(-1, 4),
        )
        self._visual_dirty = False

    def _decorations(self, t: float) -> Decorations:
        if self._visual_dirty:
            self._refresh_visual()
        held = int(self._scalars.get("meetings_held", 0))
        waiting = int(self._scalars["robots_waiting"])
        events, self.events = tuple(self.events), []
        # The plans' objects stay those of _visual until they change (the recording logs them then).
        return dataclasses.replace(self._visual, events=events,
                                   overlay=f"{self.kind}: {held} meetings held, {waiting} robots at their meeting point")

    def progress(self) -> str:
        """Meetings held so far against those scheduled, for the run's status message."""
        scheduled = sum(m.planned_time_s <= self._time_s + 1e-9 for m in self.meetings)
        held = sum(m.held_s is not None and not m.timed_out for m in self.meetings)
        text = f"{held}/{scheduled} scheduled meetings held"
        timed_out = sum(m.timed_out for m in self.meetings)
        if timed_out:
            text += (f", {timed_out} ended at the {self.params.exchange_timeout_s:g} s exchange timeout with "
                     "records undelivered")
        missed = sorted((m for m in self.meetings if m.absent), key=lambda m: m.held_s)
        if missed:
            gone = sorted({r for m in missed for r in m.absent})
            text += (f"; {len(missed)} meetings held without robot(s) {gone} after "
                     f"{self.params.member_timeout_s:g} s waits")
        if missed:
            first = missed[0]
            text += (f"; delay bound of {self.schedule.delay_bound} epochs broken at t = {first.held_s:.1f} s: "
                     f"team {first.team}'s meeting of epoch {first.epoch} went on without robot(s) "
                     f"{list(first.absent)}")
        report = self._delay_report() if self.over_radio else None
        if report is not None and not report.within_bound:
            text += (f"; delay bound of {report.bound} epochs exceeded (worst observed {report.worst}, "
                     f"{report.overdue} packets older than it still on their way)")
        return text

    def _delay_report(self):
        """Packet delays against D; the pending packets measured at the last epoch whose meetings,
        and every earlier one's, have all ended."""
        open_epochs = [m.epoch for m in self.meetings if m.held_s is None]
        through = min(open_epochs) - 1 if open_epochs else max((m.epoch for m in self.meetings), default=0)
        return delay_report(self.beliefs, self.schedule.delay_bound, through)

    def summary(self) -> dict:
        t_end = self._time_s
        scheduled = [m for m in self.meetings if m.planned_time_s <= t_end + 1e-9]
        held = [m for m in self.meetings if m.held_s is not None and not m.timed_out]
        timed_out = [m for m in self.meetings if m.timed_out]
        report = self._delay_report()
        lag_steps = np.array([s - a for s, a, _ in self.lags], dtype=float) * self.step_s
        local = np.array([e for _, _, e in self.lags], dtype=float)
        late = [m.held_s - m.planned_time_s for m in held]
        missed = sorted((m for m in self.meetings if m.absent), key=lambda m: m.held_s)
        out = {
            **self.series.summary(),
            "meetings_scheduled": len(scheduled),
            "meetings_held": len(held),
            "meetings_connected": sum(m.connected for m in held),
            "meetings_pending": len([m for m in scheduled if m.held_s is None]),
            "meetings_timed_out": len(timed_out),
            "max_wait_s": float(max(self.waits, default=0.0)),
            "mean_wait_s": float(np.mean(self.waits)) if self.waits else 0.0,
            "mean_meeting_delay_s": float(np.mean(late)) if late else 0.0,
            "schedule_period_epochs": self.schedule.period,
            "delay_bound_epochs": self.schedule.delay_bound,
            "max_delay_epochs_observed": report.worst,
            "packets_overdue": report.overdue,
            # The schedule's bound counts on every meeting: one missed breaks it (docs/faults.md).
            "delay_bound_held": bool(report.within_bound) and not missed,
            "packet_delay_bound_held": bool(report.within_bound),
            "packets_delivered": int(report.delays.size),
            "plan_time_mean_s": float(np.mean(self.plan_times)) if self.plan_times else 0.0,
            "plan_time_max_s": float(max(self.plan_times, default=0.0)),
            "plan_cost_share": float(sum(self.cost_times) / sum(self.plan_times)) if sum(self.plan_times) > 0 else 0.0,
            "plans": len(self.plan_times),
            "plan_failures": self.plan_failures,
            "plan_fallbacks": self.plan_fallbacks,
            "path_clock_hold_s": self.held_ticks * self.world.control_period_s,
            "path_clock_hold_longest_s": self.lag_holds.longest_s,
            "path_clock_holds_cut": self.lag_holds.released,
            "closest_robots_m": self.closest_m if math.isfinite(self.closest_m) else None,
            "lag_team": self.params.lag_team,
            "t_star_lag_mean_s": float(lag_steps.mean()) if lag_steps.size else 0.0,
            "t_star_lag_max_s": float(lag_steps.max()) if lag_steps.size else 0.0,
            "local_error_mean_m": float(local.mean()) if local.size else 0.0,
            "meetings_over_radio": bool(self.over_radio),
        }
        if math.isfinite(self.params.member_timeout_s):
            out.update({
                "member_timeout_s": self.params.member_timeout_s,
                "meetings_missed": len(missed),
                "delay_bound_broken_s": missed[0].held_s if missed else None,
                "members_given_up": [[r, t] for r, t in self.members_given_up],
            })
        if self.over_radio:
            out.update({
                "exchange_time_mean_s": float(np.mean(self.exchange_times)) if self.exchange_times else None,
                "exchange_time_max_s": float(max(self.exchange_times)) if self.exchange_times else None,
                "range_records_sent": self.records_sent,
            })
        return out


class IntermittentStrategy(MeetingStrategy):
    """The intermittent paper's method: segments from the joint-space informative planner."""

    kind = "intermittent"

    def design(self, team, epoch, members, starts, belief_step, estimate) -> TeamDesign:
        estimate = self.search_estimate(team, belief_step, estimate)
        problem = PlanningProblem(
            start_positions=np.array([s.position for s in starts]),
            start_times=np.array([s.time for s in starts]),
            estimate=estimate.mean,
            covariance=estimate.covariance,
            belief_time=belief_step,
            motion=self.motion,
            boxes=self.planning.boxes,
            bounds=self.planning.bounds,
            prefixes=tuple(s.prefix for s in starts),
            target_priority=self.target_priority(team),
        )
        wall = cost = 0.0
        failures = 0
        planner = dataclasses.replace(self.planner, n_sample=team_samples(self.planner.n_sample, len(members)))
        for _ in range(1 + self.params.max_replans):
            result = plan_meeting(problem, planner, self.rng)
            wall += result.wall_time_s
            cost += result.cost_time_s
            if result.success:
                plan = result.plan
                return TeamDesign(plan.paths, plan.meeting_time, plan.meeting_positions, plan.target, wall, cost,
                                  failures, False)
            failures += 1
            self.events.append(f"team {team} epoch {epoch}: planner found no meeting ({result.reason})")
        start = time.perf_counter()
        design = self._fallback(team, members, starts)
        wall += time.perf_counter() - start
        return TeamDesign(design.paths, design.meeting_time, design.points, None, wall, cost, failures, True)

    def target_priority(self, team: int) -> np.ndarray:
        """Tie-break of equally uncertain targets for ``team``: the target order
        rotated by team (team i starts at target floor(i M / n_teams)), so teams
        planning from one prior spread over the targets (see PlanningProblem)."""
        m = self.world.n_targets
        first = (team * m) // self.teams.n_teams
        return (np.arange(m) - first) % m

    def _fallback(self, team: int, members: tuple[int, ...], starts: list[MemberStart]) -> TeamDesign:
        """Meet again where the team last met; before any meeting, around
        the start of the member that starts last."""
        previous = [m for m in self.meetings if m.team == team and m.held_s is not None]
        candidates = []
        if previous:
            candidates.append(previous[-1].points)
        anchor = starts[int(np.argmax([s.time for s in starts]))].position
        candidates.append(ring_points(anchor, len(members), self.geodesic))
        for points in candidates:
            design = self.geodesic_design(members, starts, points)
            if design is not None:
                return design
        # Everyone to the anchor itself (bodies may touch; they are then in range).
        design = self.geodesic_design(members, starts, np.repeat(anchor[None], len(members), axis=0))
        if design is None:
            raise RuntimeError(f"team {team}: no geodesic path to a fallback meeting point")
        return design
