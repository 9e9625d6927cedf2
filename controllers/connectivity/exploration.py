"""Decentralised multi-target exploration of Nestmeyer et al. 2017: Algorithms 1 and 2 per control tick.

``ExplorationController.step`` is called once per control tick with the
robots' virtual-point positions and velocities, the current communication
graph and the generalized connectivity force f_lambda (computed elsewhere);
it returns the exploration force f_i of eq. (1) for every robot together
with the roles and the figures of Sec. 4 (Lambda_p, its estimates, Theta,
rho, visits, paths). The first call runs the Start-up procedure.

Per tick, for every robot i (all robots at once, using only robot i's own
state, its neighbours' efficiency estimates and election messages that have
reached it):

Algorithm 1 (planning)
  1. a connector with a non-empty queue extracts its next target z_i and
     plans gamma_i from q_i (line 5-6; unreachable targets are skipped);
  2. a secondary traveler farther than R_gamma from gamma_i replans (17-18);
  3. ``RoleMachine`` switches roles: travelers within R_z, anchors whose
     dwell time elapsed, and the prime traveler election.
Algorithm 2 (motion control)
  - prime traveler:     hat-Lambda_p^i <- Lambda_i (12);   f_i = f_travel (3);
  - secondary traveler: consensus (13); f_i = rho_i f_travel, rho_i from (10), (15);
  - anchor:             consensus (13); f_i = f_anchor (5)-(7);
  - connector:          consensus (13); f_i = 0.

The strategy integrates M v' = -B v + f_lambda + f_i with the returned forces.

Messages: with ``bus_period_s`` unset (the ideal radio) the election and the
consensus (13) are exchanged in-process over the adjacency given to ``step``.
With it set (a real radio) they travel on the message bus: ``step`` reads
``inbox`` (``Observation.inbox``) and returns the tick's messages in
``ExplorationStep.outbox``: the role machine's election broadcasts and token
handover (roles.py), and one ``"consensus"`` broadcast per robot carrying its
estimate hat-Lambda_p^i (8 bytes). A robot's neighbours in (13) are then the
robots whose consensus message reached it since the last tick, at the value
it carried.

Deviations from the paper
-------------------------
See connected_params.py, paths.py, travel.py, election.py, roles.py and
targets.py. Here:
- A target the planner cannot reach is skipped (reported in ``skipped``); a
  failed replanning keeps the previous path. The paper assumes paths exist.
- The exploration layer does not read lambda2: eqs. (3)-(15) depend on it
  only through f_lambda.
- Traveling efficiency (12) over the braking stretch: the tracking error is
  scaled by v_cruise / |v_gamma| (|v_gamma| floored at 10 % of v_cruise), so
  x_c and x_M keep meaning "fraction of the speed the traveler should have".
  Without it a prime traveler stalled just short of its target (reference
  slowed to, say, 40 % of cruise) still reads Lambda_p ~ 0.4, the secondary
  travelers keep pulling (rho > 0) and the team can deadlock - which we saw
  in the town scene; the paper, with no braking, has Lambda_p = 0 there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controllers.connectivity.connected_params import ConnectedParams
from controllers.connectivity.path_batch import PathBatch
from controllers.connectivity.paths import GridPlanner, NoPathError, SplinePath
from controllers.connectivity.roles import ANCHOR_CODE, CONNECTOR_CODE, PRIME_CODE, SECONDARY_CODE, RoleMachine
from controllers.connectivity.targets import DwellClock, Target, TargetQueues, Visit
from controllers.connectivity.travel import (
    PathReference,
    _adaptive_gain_scalar,
    _alignment_row,
    _anchor_force_row,
    _consensus_kernel,
    _efficiency_scalar,
    _norm3,
    _tracking_error_row,
    _travel_force_row,
    batch_path_reference,
    needs_replanning,
    path_reference,
    row_norm,
)
from sim.compiled import kernel
from sim.radio.bus import FLOAT64_BYTES, Broadcasts, Message

# Floor of the reference speed, as a fraction of cruise, when scaling the efficiency error.
_MIN_REFERENCE_FRACTION = 0.1
CONSENSUS_KIND = "consensus"


@dataclass(frozen=True)
class ExplorationStep:
    """Output of one control tick; arrays are (N, ...), NaN where not defined."""

    forces: np.ndarray  # (N, 3) exploration force f_i, N
    roles: np.ndarray  # (N,) Role codes (1 prime, 2 secondary, 3 anchor, 4 connector)
    prime: int  # index of the prime traveler, -1 if none
    prime_efficiency: float  # Lambda_p in [0, 1], NaN without prime traveler
    efficiency: np.ndarray  # (N,) Lambda_i of travelers, eq. (12)
    efficiency_estimate: np.ndarray  # (N,) hat-Lambda_p^i, eq. (13)
    alignment: np.ndarray  # (N,) Theta_i of secondary travelers, eq. (10)
    gain: np.ndarray  # (N,) rho_i of secondary travelers, eq. (15)
    tracking_error: np.ndarray  # (N,) e_i of travelers, eq. (11), m/s
    path_points: np.ndarray  # (N, 3) closest path points q_gamma of travelers, m
    remaining: np.ndarray  # (N,) remaining path length d_gamma of travelers, m
    targets: np.ndarray  # (N, 3) current targets z_i, m
    paths: tuple[SplinePath | None, ...]  # gamma_i of travelers (for drawing)
    visits: tuple[Visit, ...]  # every completed visit so far
    skipped: tuple[Target, ...]  # targets found unreachable
    finished: bool  # every queue empty and every robot a connector
    outbox: tuple[Message, ...] = ()  # the tick's messages for the bus (over the bus only)


class ExplorationController:
    """The exploration layer for N robots sharing one static scene.

    params: ConnectedParams; planner: GridPlanner of the scene; queues:
    TargetQueues (the target generators may keep pushing during the run);
    bus_period_s: None to exchange messages in-process, or the control period,
    s, to send them over the message bus (see the module docstring).
    """

    def __init__(self, params: ConnectedParams, planner: GridPlanner, queues: TargetQueues,
                 bus_period_s: float | None = None) -> None:
        n = queues.n_robots
        if not params.election_host < n:
            raise ValueError(f"election_host ({params.election_host}) must be a robot index below {n}")
        self.params = params
        self.planner = planner
        self.scene_planner = planner  # the scene's own obstacles (``planner`` may add dropped robots)
        self.queues = queues
        self.n_robots = n
        self.role_machine = RoleMachine(n, params.message_latency_ticks, params.election_host, bus_period_s)
        self.over_bus = bus_period_s is not None
        self.targets: list[Target | None] = [None] * n
        self._target_table: tuple[np.ndarray, np.ndarray] | None = None  # built when the targets change
        self.paths: list[SplinePath | None] = [None] * n
        self.estimates = np.zeros(n)  # hat-Lambda_p^i, start-up line 12
        self.dwell = DwellClock(n)
        self.arrival_time = np.full(n, np.nan)
        self.visits: list[Visit] = []
        self.skipped: list[Target] = []
        self.tick = 0
        self.last_time: float | None = None
        self._batch: PathBatch | None = None

    # -- Algorithm 1, geometric parts ---------------------------------------

    def _extract_and_plan(self, robot: int, position: np.ndarray) -> bool:
        """Lines 5-6: next reachable target and its path; False if the queue ran dry."""
        while (target := self.queues.pop(robot)) is not None:
            try:
                self.paths[robot] = self._plan(position, target.position)
            except NoPathError:
                self.skipped.append(target)
                continue
            self.targets[robot] = target
            self._target_table = None
            return True
        return False

    def use_planner(self, planner: GridPlanner, q: np.ndarray, robots) -> None:
        """Plan with ``planner`` from now on (the scene's obstacles changed), and plan again the current path
        of each of ``robots`` that has a target from its position in ``q`` (N, 3), m."""
        self.planner = planner
        for robot in robots:
            if self.paths[robot] is not None and self.targets[robot] is not None:
                self._replan(robot, q[robot])

    def _replan(self, robot: int, position: np.ndarray) -> None:
        try:
            self.paths[robot] = self._plan(position, self.targets[robot].position)
        except NoPathError:
            pass  # keep following the old path; f_lambda keeps the robot safe meanwhile

    def _plan(self, start: np.ndarray, goal: np.ndarray) -> SplinePath:
        """A path from ``start`` to ``goal``, clear of the dropped robots' points where one exists: the points
        kept clear are a preference (a start next to one, a passage one narrows), except for a goal inside
        one, which a dropped robot blocks (NoPathError)."""
        try:
            return self.planner.plan(start, goal)
        except NoPathError:
            if self.planner is self.scene_planner or not self.planner.is_free(np.asarray(goal)[None])[0]:
                raise
        return self.scene_planner.plan(start, goal)

    def retarget(self, robot: int, position, dwell_time: float, robot_position=None) -> Target | None:
        """Online target generators: replace robot ``robot``'s current target
        z_i (same index k) by ``position`` (3,), m, with ``dwell_time``, s.

        A traveler replans from ``robot_position`` (3,), m (its q_i) to the new
        point, keeping the old path if none is found; an anchor keeps its
        place (give it the same position) and only its dwell time changes: a
        dwell time it has already spent ends its visit on the next tick.
        Returns the new target, or None when the robot has none.
        """
        current = self.targets[robot]
        if current is None:
            return None
        point = np.asarray(position, dtype=float).reshape(3).copy()
        if not (np.all(np.isfinite(point)) and np.isfinite(dwell_time) and dwell_time >= 0):
            raise ValueError(f"retarget needs a finite position and dwell time >= 0, got {point}, {dwell_time!r}")
        point.setflags(write=False)
        self.targets[robot] = Target(robot, current.index, point, float(dwell_time))
        self._target_table = None
        if self.paths[robot] is not None and robot_position is not None and not np.array_equal(point, current.position):
            self._replan(robot, np.asarray(robot_position, dtype=float).reshape(3))
        return self.targets[robot]

    def _reference(self, robot: int, position: np.ndarray) -> PathReference:
        p = self.params
        return path_reference(self.paths[robot], position[None], p.cruise_speed_mps, p.braking_distance_m)

    def _references(self, q: np.ndarray) -> tuple[np.ndarray, PathReference | None]:
        """Robots with a path (ascending indices) and their path references, one
        row each: splines batched in one compiled pass, single-point paths alone."""
        p = self.params
        # Python ints and lists here: indexing lists with numpy integers costs more than the work.
        robots = [i for i, path in enumerate(self.paths) if path is not None]
        if not robots:
            return np.zeros(0, dtype=int), None
        batched = [i for i in robots if self.paths[i].spline is not None]
        stacked = None
        if batched:
            paths = [self.paths[i] for i in batched]
            if self._batch is None or len(self._batch) != len(paths) or any(
                a is not b for a, b in zip(self._batch.paths, paths)
            ):
                self._batch = PathBatch(paths)
            stacked = batch_path_reference(self._batch, q[batched], p.cruise_speed_mps, p.braking_distance_m)
            if len(batched) == len(robots):
                return np.array(robots, dtype=int), stacked
        single = {i: self._reference(i, q[i]) for i in robots if self.paths[i].spline is None}
        batch_row = {i: k for k, i in enumerate(batched)}
        rows = [single[i] if i in single else stacked.row(batch_row[i]) for i in robots]
        return np.array(robots, dtype=int), PathReference.stack(rows)

    def _targets_now(self) -> tuple[np.ndarray, np.ndarray]:
        """Each robot's current target point (N, 3; NaN without one) and dwell time (N,; inf)."""
        if self._target_table is None:
            self._target_table = (
                np.array([t.position if t is not None else np.full(3, np.nan) for t in self.targets]),
                np.array([t.dwell_time if t is not None else np.inf for t in self.targets]),
            )
        points, dwell = self._target_table
        return points.copy(), dwell

    @staticmethod
    def _replace_row(references: PathReference, k: int, row: PathReference) -> PathReference:
        """``references`` with row k replaced by the one-row ``row``."""
        fields = {}
        for name in PathReference.__dataclass_fields__:
            values = getattr(references, name).copy()
            values[k] = getattr(row, name)[0]
            fields[name] = values
        return PathReference(**fields)

    # -- one control tick ---------------------------------------------------

    def step(self, time: float, positions, velocities, adjacency, connectivity_force, inbox=(),
             arrivals=None) -> ExplorationStep:
        """Algorithms 1 and 2 for one control tick.

        time: s; positions, velocities: (N, 3) virtual points, m and m/s;
        adjacency: (N, N) current communication graph (bool or weights > 0;
        the in-process exchange's); connectivity_force: (N, 3) f_lambda, N;
        inbox: per robot the bus's deliveries since the last tick (over the bus),
        arrivals: the bus's columns of the messages sent as arrays (the consensus; ``Observation.arrivals``).
        """
        p = self.params
        n = self.n_robots
        q = np.asarray(positions, dtype=float)
        v = np.asarray(velocities, dtype=float)
        f_lambda = np.asarray(connectivity_force, dtype=float)
        adjacency = np.asarray(adjacency)
        for name, array, shape in (
            ("positions", q, (n, 3)),
            ("velocities", v, (n, 3)),
            ("connectivity_force", f_lambda, (n, 3)),
            ("adjacency", adjacency, (n, n)),
        ):
            if array.shape != shape:
                raise ValueError(f"{name} must have shape {shape}, got {array.shape}")
        dt = 0.0 if self.last_time is None else float(time) - self.last_time
        if dt < 0:
            raise ValueError(f"time went backwards: {time} after {self.last_time}")

        got_target = np.zeros(n, dtype=bool)
        if not self.role_machine.started:  # Start-up procedure, lines 1-11
            has_target = np.array([self._extract_and_plan(i, q[i]) for i in range(n)])
            self.role_machine.start(has_target)
        else:
            for i in np.flatnonzero((self.role_machine.roles == CONNECTOR_CODE) & self.queues.pending()):
                got_target[i] = self._extract_and_plan(i, q[i])

        travelers, references = self._references(q)
        if references is not None:
            secondary = self.role_machine.roles[travelers] == SECONDARY_CODE
            for k in np.flatnonzero(secondary & needs_replanning(references, p.replan_distance_m)):  # Alg. 1 line 17
                i = int(travelers[k])
                self._replan(i, q[i])
                references = self._replace_row(references, k, self._reference(i, q[i]))

        target_points, dwell_needed = self._targets_now()
        to_target = row_norm(q - target_points)
        near_target = to_target < p.target_radius_m  # False where there is no target (NaN)
        anchors = self.role_machine.roles == ANCHOR_CODE
        self.dwell.update(float(time), anchors & near_target)
        task_done = anchors & near_target & (self.dwell.elapsed(float(time)) >= dwell_needed)
        remaining = np.full(n, np.inf)
        if references is not None:
            remaining[travelers] = references.remaining

        if self.over_bus:  # the consensus messages here, the rest (election, token) to the role machine
            heard, consensus_links, inbox = split_consensus(inbox, n, arrivals)
        changes = self.role_machine.step(self.tick, adjacency, got_target, near_target, task_done, remaining,
                                         inbox, float(time))
        roles = changes.roles
        for i in np.flatnonzero(changes.became_anchor):
            self.paths[i] = None  # lines 13, 20
            self.arrival_time[i] = float(time)
        if references is not None and changes.became_anchor[travelers].any():
            keep = ~changes.became_anchor[travelers]
            travelers = travelers[keep]
            references = PathReference(*(getattr(references, name)[keep]
                                         for name in PathReference.__dataclass_fields__))
        self.dwell.update(float(time), (roles == ANCHOR_CODE) & near_target)
        for i in np.flatnonzero(changes.became_connector):
            self.visits.append(Visit(self.targets[i], float(self.arrival_time[i]), float(time)))
            self.targets[i] = None
            self._target_table = None
            self.arrival_time[i] = np.nan

        # Algorithm 2, every robot in one compiled pass.
        forces = np.empty((n, 3))
        lam, error, alignment, gain = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
        path_points = np.empty((n, 3))
        estimates = np.empty(n)
        if not self.over_bus:
            heard, consensus_links = np.tile(self.estimates, (n, 1)), adjacency
        if references is None or not len(travelers):
            points = velocities_ref = accelerations = np.zeros((0, 3))
            travelers = np.zeros(0, dtype=np.int64)
        else:
            points, velocities_ref, accelerations = references.point, references.velocity, references.acceleration
        _motion_control(q, v, f_lambda, roles, travelers, points, velocities_ref, accelerations, target_points,
                        consensus_links, heard, self.estimates, dt, p.position_gain, p.velocity_gain, p.virtual_mass_kg,
                        p.travel_force_limit_n, p.position_error_weight, p.cruise_speed_mps,
                        _MIN_REFERENCE_FRACTION * p.cruise_speed_mps, p.efficiency_error_full_mps,
                        p.efficiency_error_zero_mps, p.consensus_gain, p.sigma, p.target_radius_m, p.anchor_gain_n,
                        p.anchor_force_limit_n,
                        forces, lam, error, path_points, estimates, alignment, gain)
        self.estimates = estimates
        outbox = ()
        if self.over_bus:
            # every robot's estimate as one outbox item (the bus takes it without a Message per robot)
            outbox = (*self.role_machine.outbox,
                      Broadcasts.handed_over(CONSENSUS_KIND, estimates, FLOAT64_BYTES, latest_only=True))

        self.tick += 1
        self.last_time = float(time)
        prime = self.role_machine.prime
        finished = len(self.queues) == 0 and bool(np.all(roles == CONNECTOR_CODE))  # (queues first: cheaper)
        target_points, _ = self._targets_now()
        return ExplorationStep(
            forces=forces,
            roles=roles,
            prime=prime,
            prime_efficiency=float(lam[prime]) if prime >= 0 else float("nan"),
            efficiency=lam,
            efficiency_estimate=self.estimates.copy(),
            alignment=alignment,
            gain=gain,
            tracking_error=error,
            path_points=path_points,
            remaining=np.where(np.isfinite(remaining) & (roles <= SECONDARY_CODE), remaining, np.nan),
            targets=target_points,
            paths=tuple(self.paths),
            visits=tuple(self.visits),
            skipped=tuple(self.skipped),
            finished=finished,
            outbox=outbox,
        )


def heard_estimates(inbox, n_robots: int, arrivals=None) -> tuple[np.ndarray, np.ndarray]:
    """Over the bus: heard[i, j], the estimate hat-Lambda_p^j in the latest consensus message that reached
    robot i since the last tick (``inbox``, per robot in order of arrival, or ``arrivals``' consensus
    columns), and which arrived (bool (N, N)); NaN and False elsewhere."""
    heard, arrived, _ = split_consensus(inbox, n_robots, arrivals)
    return heard, arrived


def split_consensus(inbox, n_robots: int, arrivals=None) -> tuple[np.ndarray, np.ndarray, list]:
    """``heard_estimates``' two arrays, and per robot its other deliveries (in order): the consensus's
    columns (``arrivals``, sent as arrays) in one numpy pass, and one pass over the inbox for consensus
    messages delivered as rows, so the role machine's readers never walk them."""
    heard = np.empty((n_robots, n_robots))
    arrived = np.empty((n_robots, n_robots), dtype=bool)
    columns = arrivals.get(CONSENSUS_KIND) if arrivals else None
    if columns is None:
        _heard_cells(_NO_ENTRIES, _NO_ENTRIES, _NO_VALUES, heard, arrived)
    else:
        _heard_cells(columns.receiver, columns.sender, columns.payload, heard, arrived)
    if not any(inbox) or not any(delivery.message.kind == CONSENSUS_KIND for row in inbox if row for delivery in row):
        return heard, arrived, inbox
    rest: list[list] = [[] for _ in range(n_robots)]
    for robot, deliveries in enumerate(inbox):
        others = rest[robot]
        for delivery in deliveries:
            message = delivery.message
            if message.kind != CONSENSUS_KIND:
                others.append(delivery)
            elif delivery.receiver == robot:
                heard[robot, message.sender] = message.payload
                arrived[robot, message.sender] = True
    return heard, arrived, rest


_NO_ENTRIES = np.empty(0, dtype=np.int64)
_NO_VALUES = np.empty(0)


@kernel
def _heard_cells(receiver, sender, payload, heard, arrived):
    """heard = NaN and arrived = False, then heard[r, s] = the payload, arrived[r, s] = True for each entry
    in order (by arrival per receiver, so the latest of a pair wins)."""
    heard[:] = np.nan
    arrived[:] = False
    for d in range(receiver.shape[0]):
        heard[receiver[d], sender[d]] = payload[d]
        arrived[receiver[d], sender[d]] = True


@kernel
def _motion_control(q, v, f_lambda, roles, travelers, points, velocities, accelerations, target_points, adjacency,
                    heard, estimates, dt, position_gain, velocity_gain, mass, travel_force_limit, position_weight,
                    cruise_speed, min_reference_speed, x_full, x_zero, consensus_gain, sigma, target_radius,
                    anchor_gain, anchor_force_limit, forces, lam, error, path_points, estimates_out, alignment, gain):
    """Algorithm 2 for every robot (see the module docstring); outputs NaN where undefined.

    travelers (R,) with their path references' points, velocities and
    accelerations (R, 3); roles (N,) codes; estimates (N,) hat-Lambda_p^i of the
    previous tick, estimates_out the new ones (eq. 13), with neighbours j of i where adjacency[i, j] > 0 at
    the values heard[i, j]."""
    n = q.shape[0]
    for i in range(n):
        lam[i] = error[i] = alignment[i] = gain[i] = np.nan
        for k in range(3):
            forces[i, k] = 0.0
            path_points[i, k] = np.nan
    for r in range(travelers.shape[0]):
        i = travelers[r]
        _travel_force_row(q[i], v[i], points[r], velocities[r], accelerations[r], position_gain, velocity_gain, mass,
                          travel_force_limit, forces[i])
        error[i] = _tracking_error_row(q[i], v[i], points[r], velocities[r], position_weight)
        # Over the braking stretch the reference slows down (travel.py); the error is
        # weighed against the reference's own speed there, so a traveler held back near
        # its target reads as inefficient, as one held back at cruise speed does.
        reference_speed = _norm3(velocities[r, 0], velocities[r, 1], velocities[r, 2])
        scale = cruise_speed / max(reference_speed, min_reference_speed)
        lam[i] = _efficiency_scalar(error[i] * scale, x_full, x_zero)
        for k in range(3):
            path_points[i, k] = points[r, k]
    is_prime = roles == PRIME_CODE
    prime_efficiency = np.where(np.isnan(lam), 0.0, lam)
    _consensus_kernel(estimates, heard, adjacency, is_prime, prime_efficiency, consensus_gain, dt, estimates_out)
    for i in range(n):
        if roles[i] == SECONDARY_CODE:
            alignment[i] = _alignment_row(f_lambda[i], forces[i])
            gain[i] = _adaptive_gain_scalar(alignment[i], estimates_out[i], sigma)
            for k in range(3):
                forces[i, k] *= gain[i]
        elif roles[i] == ANCHOR_CODE:
            _anchor_force_row(q[i], target_points[i], target_radius, anchor_gain, anchor_force_limit, forces[i])
        elif roles[i] == CONNECTOR_CODE:
            for k in range(3):
                forces[i, k] = 0.0
