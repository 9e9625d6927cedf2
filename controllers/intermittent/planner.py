"""Joint-space sampling-based informative path planner of Khodayi-mehr et al. 2019.

When the robots of a team T_i meet, they plan together (Sec. III-B/C) the next
path segment of every member: paths that start where (and when) each robot's
previous segment ends, stay collision free, respect the single-integrator
dynamics p(t + 1) = p(t) + u(t), |u| <= u_max, end at the *same* time in a
*connected* configuration, and minimise the accumulated predicted target
uncertainty, problem (5). The solver is Algorithm 1, an RRT* over the joint
space of the team (stacked plane positions, distance = Euclidean norm of the
stack), with

- Sample: f1 uniform over the free space for the first B samples, then f2 =
  N(mu, (2R)^2 I) with mu = [q; ...; q] around a meeting point q drawn
  uniformly from the free space (Sec. IV);
- Steer: Algorithm 6 with time matching (Appendix A), :func:`steer`;
- CollisionFree: every robot's straight move keeps more than the robot radius
  from every obstacle box at sensor height; dynamics hold by construction of
  the arrival times (:func:`arrival_times`);
- Extend: Algorithm 2, the parent among the near nodes that gives the new
  node the smallest cost;
- Rewire: Algorithm 3, only near nodes that are time synchronised and stay
  synchronised through the new node are rewired; the subtree's arrival times,
  covariances and costs are then recomputed;
- Cost: Algorithm 4 (see :mod:`controllers.intermittent.planner_belief`), the
  sum over discrete steps of unc(t) = lambda_max of the predicted team
  covariance, from t_0 = min_j t_0,j up to the meeting time t_f;
- Goal set (6), with the fifth constraint of (5), t_f > t_0,ij for every
  robot (so the root never counts as a plan): (i) lambda_2 of the Laplacian of the team graph > 0 (links
  for pairs within R with line of sight), (ii) equal arrival times, (iii)
  lambda_max of the a-th 3x3 block of the predicted covariance <= delta, with
  a the most uncertain target of the team's belief at planning time; when no
  node qualifies after n_sample samples, (iii) is re-checked for the next most
  uncertain target, and so on (Sec. IV). The cheapest goal node wins
  (Alg. 1, line 13).

Time. Times are integer discrete steps (the simulator's control step; the
paper's u_max = 0.1 m per step). A node v stores the configuration q_j(v) of
every robot and the step t_j(v) at which robot j is there; the edge from a
parent moves robot j at constant speed |q_j(v) - q_j(par)| / (t_j(v) -
t_j(par)) <= u_max, so positions at every step are linear interpolations and
no step exceeds u_max. Robots start at their own t_0,j (the end of their
previous segment, possibly a later meeting of their other team), so the root
is in general not synchronised; Steer then moves only the lagging robots
(Appendix A) until the delay max_j t_j - min_j t_j is zero.

A node is "settled" up to tau(v) = min_j t_j(v): at every step t <= tau(v)
the position of every robot is fixed by the path from the root. The node
stores the predicted covariance C(tau(v)) and the cost sum_{t_0 < t <=
tau(v)} unc(t); the positions of robots that are ahead, at steps tau(v) < t <=
t_j(v), are kept as the node's tail and fused when a child settles those
steps (the paper's "measurements ... retained for future samples", Sec.
III-E). For the synchronised goal nodes tau = t_f, so the node cost is the
objective of problem (5) exactly.

Between the belief time and t_0,j robot j may still be travelling its previous
segment: pass that committed path in ``PlanningProblem.prefixes`` and its
predicted readings are fused; without it the robot takes no reading before
t_0,j.

Deviations from the paper (where it is silent or continuous-time):

- Integer times: Steer uses Delta t_s = ceil(s / u_max) steps and moves the
  robots at the common speed s / Delta t_s <= u_max (the paper: continuous
  Delta t_s = s / u_max at speed u_max). The lagging robot still moves exactly
  s, the others u Delta t_c,ij, and delay(v_new) = max(0, delay(v_nearest) -
  Delta t_s), so time matching is as in Appendix A; meetings fall on steps.
- Arrival times for a parent other than v_nearest (Extend) and for rewiring,
  which the paper leaves open, follow :func:`arrival_times`, the rule that
  reproduces Algorithm 6's times for v_nearest: the moving robots arrive
  together at the earliest step all of them can make at speed <= u_max,
  robots that stay and are not ahead wait until then, robots that stay and are
  ahead keep their time. A synchronised parent thus always gives a
  synchronised child, and a rewired synchronised node and its subtree shift
  in time together (the paper: "t_ij(v_near) may change").
- The cost adds exactly one unc(t) per step, after the update where readings
  exist (Alg. 4's text; its pseudo-code would add the predicted and the
  updated value at measurement steps), and the settled-time bookkeeping above
  replaces the paper's informal handling of unsynchronised nodes.
- Near radius r = min(gamma (log n / n)^(1/d), eta), d = 2 |T_i|, gamma =
  gamma_scale * 2 (1 + 1/d)^(1/d) (mu / zeta_d)^(1/d) [RRT*, Karaman and
  Frazzoli 2011] with mu = (workspace area)^|T_i| (obstacles ignored, an upper
  bound) and eta = sqrt(|T_i|) * step_size, the longest Steer move.
- f2 draws a fresh meeting point q for every sample; samples outside the free
  space are redrawn (at most max_sample_tries times, then the iteration is
  skipped). The free space keeps the robot radius from boxes and bounds.
- Cost comparison in Extend and Rewire uses the settled cost, so nodes with
  different settled times are compared by the paper's Cost as is.
- Line of sight of predicted readings and of communication links uses an
  exact slab test instead of ``segments_free(..., margin=0)`` (the same
  predicate except for segments passing within segments_free's 1e-9 m contact
  tolerance of a box; much faster); collision checks use ``segments_free``.
  Condition (6)(i) is tested by reachability in the graph (lambda_2 > 0 of an
  unweighted graph); lambda_2 itself is computed only for the returned plan.
- The covariance recursion uses batched 3x3 blocks when the belief has no
  coupling between targets (:mod:`planner_belief`); it equals the reference
  covariance_predict / covariance_update chain (tested), which is used
  otherwise.
- Alg. 1, line 13 says the goal node "with smallest uncertainty"; the text
  says smallest cost, which is used. The goal set is evaluated over the whole
  tree after the last sample (the same set as the incremental X_g updates of
  Algs. 2 and 3, which rewiring can change), and t_f > t_0,ij is required
  strictly (the fifth constraint, "greater than").
- The returned path is re-verified (collisions with margin, speed bound,
  synchronisation, connectivity, uncertainty) before it is returned; a goal
  node that fails is skipped.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from estimation.range_model import SENSING_RANGE_M
from estimation.target_motion import TargetMotion
from sim.geometry import Boxes, segments_free

from controllers.intermittent.planner_belief import PredictedBelief
from controllers.intermittent.planner_kernels import edge_sequences
from controllers.intermittent.planner_geometry import (
    algebraic_connectivity,
    communication_graph,
    edges_free,
    is_connected,
    lift,
    points_free,
)

MOVE_TOL_M = 1e-12  # displacement below which a robot counts as standing still, m
TIME_TOL = 1e-9  # slack in ceil(distance / u_max) against rounding, steps
SPEED_RTOL = 1e-9  # relative slack when verifying |u| <= u_max
CONNECTIVITY_TOL = 1e-9  # lambda_2 above this counts as connected


# ---------------------------------------------------------------------------
# Parameters and inputs
# ---------------------------------------------------------------------------


def _check_int(name: str, value, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"{name} must be an integer >= {minimum}, got {value!r}")


def _check_real(name: str, value, *, positive: bool) -> None:
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, bool)
    ok = ok and math.isfinite(value) and (value > 0 if positive else value >= 0)
    if not ok:
        bound = "> 0" if positive else ">= 0"
        raise ValueError(f"{name} must be a finite number {bound}, got {value!r}")


@dataclass(frozen=True)
class PlannerParams:
    """Parameters of Algorithm 1 (Khodayi-mehr et al. 2019 values where the paper gives them)."""

    n_sample: int = 300  # samples, n_sample of Alg. 1, -
    n_uniform: int = 100  # B: the first B samples come from f1 (uniform), -
    step_size: float = 1.0  # epsilon of Alg. 6: longest Steer move of one robot, m
    u_max: float = 0.1  # largest displacement per discrete step, m/step (paper: 0.1 m)
    comm_range: float = 0.2  # R: communication range, m (paper: 0.2 m)
    delta: float = 0.12**2  # goal threshold on lambda_max of a target block, m^2 (paper)
    sensor_height: float = 0.035  # z_s: sensor/radio height above the floor, m
    robot_radius: float = 0.035  # clearance kept from obstacles and bounds, m
    sensing_range: float = SENSING_RANGE_M  # range sensor limit, m (paper: 5 m)
    measurement_period: int = 1  # Delta t of Alg. 4: readings at steps t % period == 0
    gamma_scale: float = 1.1  # gamma / gamma*_RRT* of the near radius, -
    max_sample_tries: int = 100  # rejection-sampling attempts per sample, -

    def __post_init__(self) -> None:
        _check_int("n_sample", self.n_sample, 1)
        _check_int("n_uniform", self.n_uniform, 0)
        _check_int("measurement_period", self.measurement_period, 1)
        _check_int("max_sample_tries", self.max_sample_tries, 1)
        for name in ("step_size", "u_max", "comm_range", "delta", "sensing_range", "gamma_scale"):
            _check_real(name, getattr(self, name), positive=True)
        for name in ("sensor_height", "robot_radius"):
            _check_real(name, getattr(self, name), positive=False)


@dataclass(frozen=True)
class RobotPath:
    """Timestamped waypoints of one robot; straight lines at constant speed between.

    times: (L,) int, strictly increasing, steps. positions: (L, 2) plane
    positions, m, world frame.
    """

    times: np.ndarray
    positions: np.ndarray

    def __post_init__(self) -> None:
        times = np.asarray(self.times)
        positions = np.asarray(self.positions, dtype=float)
        if times.ndim != 1 or len(times) == 0:
            raise ValueError("times must be a non-empty 1-D array")
        if not np.all(np.asarray(times, dtype=float) == np.round(np.asarray(times, dtype=float))):
            raise ValueError("times must be integer steps")
        times = times.astype(int)
        if np.any(np.diff(times) <= 0):
            raise ValueError("times must be strictly increasing")
        if positions.shape != (len(times), 2) or not np.all(np.isfinite(positions)):
            raise ValueError("positions must be finite with shape (len(times), 2)")
        times.setflags(write=False)
        positions = positions.copy()
        positions.setflags(write=False)
        object.__setattr__(self, "times", times)
        object.__setattr__(self, "positions", positions)

    @property
    def start_time(self) -> int:
        return int(self.times[0])

    @property
    def end_time(self) -> int:
        return int(self.times[-1])

    def position_at(self, t) -> np.ndarray:
        """Plane position(s), m, at time(s) ``t`` (steps, float allowed):
        (2,) for a scalar, (..., 2) for an array. ValueError outside the path."""
        t = np.asarray(t, dtype=float)
        if np.any(t < self.times[0]) or np.any(t > self.times[-1]):
            raise ValueError(f"t outside [{self.times[0]}, {self.times[-1]}]")
        x = np.interp(t, self.times, self.positions[:, 0])
        y = np.interp(t, self.times, self.positions[:, 1])
        return np.stack([x, y], axis=-1)


@dataclass(frozen=True)
class PlanningProblem:
    """What a meeting team knows when it plans (one team, n robots, M targets).

    start_positions: (n, 2) m, where each robot's new segment starts
        (p_ij(t_0,ij): its last meeting position, Sec. III-B).
    start_times: (n,) int steps, t_0,ij.
    estimate: (3M,) m, and covariance: (3M, 3M) m^2, the team's belief at
        ``belief_time`` (steps, <= min start_times).
    motion: the targets' model (A, B u(k), Q), used for the predicted estimate.
    boxes: static obstacles; bounds: (2, 2) [[x_min, y_min], [x_max, y_max]] m.
    prefixes: optional, per robot, the committed path it follows until
        t_0,j (ending at (t_0,j, start position)); None entries (or None) mean
        unknown, and such a robot takes no predicted reading before t_0,j.
    target_priority: optional (M,) tie-break of the goal's target order
        (Sec. IV: the most uncertain target first, then the next): among
        targets of equal uncertainty the lower priority comes first; None is
        the target index. The paper is silent on ties; every unseen target
        ties with the others of the same prior, so teams that plan from one
        prior would all chase target 0 without it.
    sensor_offsets: optional (S, 2) m: every robot carries S range sensors at
        these plane offsets from its planned position (the all-time
        baseline plans a rigid formation's centre as one robot); None is one
        sensor at the robot. Collision checks still use the robot point with
        ``PlannerParams.robot_radius``, so give the formation's radius there.
    """

    start_positions: np.ndarray
    start_times: np.ndarray
    estimate: np.ndarray
    covariance: np.ndarray
    belief_time: int
    motion: TargetMotion
    boxes: Boxes
    bounds: np.ndarray
    prefixes: tuple | None = None
    sensor_offsets: np.ndarray | None = None
    target_priority: np.ndarray | None = None

    def __post_init__(self) -> None:
        q = np.asarray(self.start_positions, dtype=float)
        if q.ndim != 2 or q.shape[1] != 2 or len(q) == 0 or not np.all(np.isfinite(q)):
            raise ValueError("start_positions must be a finite (n, 2) array with n >= 1")
        n = len(q)
        t0 = np.asarray(self.start_times)
        if t0.shape != (n,) or not np.all(np.asarray(t0, float) == np.round(np.asarray(t0, float))):
            raise ValueError("start_times must be (n,) integer steps")
        t0 = t0.astype(int)
        m = self.motion.n_targets
        x = np.asarray(self.estimate, dtype=float)
        c = np.asarray(self.covariance, dtype=float)
        if x.shape != (3 * m,) or not np.all(np.isfinite(x)):
            raise ValueError(f"estimate must be finite with shape ({3 * m},)")
        if c.shape != (3 * m, 3 * m) or not np.all(np.isfinite(c)) or not np.allclose(c, c.T):
            raise ValueError(f"covariance must be a finite symmetric ({3 * m}, {3 * m}) array")
        if isinstance(self.belief_time, bool) or not isinstance(self.belief_time, (int, np.integer)):
            raise ValueError("belief_time must be an integer step")
        if self.belief_time > t0.min():
            raise ValueError("belief_time must not exceed min(start_times)")
        bounds = np.asarray(self.bounds, dtype=float)
        if bounds.shape != (2, 2) or not np.all(bounds[0] < bounds[1]):
            raise ValueError("bounds must be [[x_min, y_min], [x_max, y_max]] with min < max")
        prefixes = self.prefixes
        if prefixes is not None:
            prefixes = tuple(prefixes)
            if len(prefixes) != n:
                raise ValueError("prefixes must have one entry per robot")
            for j, path in enumerate(prefixes):
                if path is None:
                    continue
                if not isinstance(path, RobotPath):
                    raise ValueError("prefixes entries must be RobotPath or None")
                if path.end_time != t0[j] or not np.allclose(path.positions[-1], q[j]):
                    raise ValueError(f"prefixes[{j}] must end at (start_times[{j}], start_positions[{j}])")
        offsets = self.sensor_offsets
        if offsets is not None:
            offsets = np.asarray(offsets, dtype=float)
            if offsets.ndim != 2 or offsets.shape[1] != 2 or len(offsets) == 0 or not np.all(np.isfinite(offsets)):
                raise ValueError("sensor_offsets must be a finite (S, 2) array with S >= 1")
        priority = self.target_priority
        if priority is not None:
            priority = np.asarray(priority)
            if priority.shape != (m,) or not np.all(np.isfinite(priority)):
                raise ValueError(f"target_priority must be a finite ({m},) array")
        for name, value in (("start_positions", q), ("start_times", t0), ("estimate", x),
                            ("covariance", c), ("bounds", bounds), ("prefixes", prefixes),
                            ("sensor_offsets", offsets), ("target_priority", priority)):
            if isinstance(value, np.ndarray):
                value = value.copy()
                value.setflags(write=False)
            object.__setattr__(self, name, value)
        object.__setattr__(self, "belief_time", int(self.belief_time))

    @property
    def n_robots(self) -> int:
        return len(self.start_positions)


# ---------------------------------------------------------------------------
# Outputs
# ---------------------------------------------------------------------------


@dataclass(frozen=True)
class TeamPlan:
    """A feasible plan: every robot's path segment to the next team meeting.

    paths: per robot, waypoints from (t_0,j, start) to (meeting_time, meeting
        position); the robots move straight at constant speed in between.
    meeting_time: t_f, step; meeting_positions: (n, 2) m.
    cost: sum of lambda_max(C(t)) over steps t_0 < t <= t_f, m^2 (predicted).
    target: index of the target whose goal condition (iii) holds;
        target_rank: its rank in the team's uncertainty order (0 = most
        uncertain); target_uncertainty: its block's lambda_max at t_f, m^2.
    meeting_estimate: (3M,) m and meeting_covariance: (3M, 3M) m^2, the
        predicted team belief at t_f; meeting_lambda2: lambda_2 of the team
        communication graph at the meeting.
    """

    paths: tuple[RobotPath, ...]
    meeting_time: int
    meeting_positions: np.ndarray
    cost: float
    target: int
    target_rank: int
    target_uncertainty: float
    meeting_estimate: np.ndarray
    meeting_covariance: np.ndarray
    meeting_lambda2: float

    def positions_at(self, t: float) -> np.ndarray:
        """(n, 2) m at time ``t`` (steps); NaN rows for robots whose segment
        has not started yet (t < t_0,j)."""
        if t > self.meeting_time:
            raise ValueError("t after the meeting time")
        out = np.full((len(self.paths), 2), np.nan)
        for j, path in enumerate(self.paths):
            if path.start_time <= t:
                out[j] = path.position_at(t)
        return out


@dataclass(frozen=True)
class PlanResult:
    """Outcome of :func:`plan_meeting`; ``plan`` is None on failure.

    reason: empty on success, else why no plan was returned.
    n_samples: samples taken; n_nodes: tree size; n_goal_nodes: nodes in the
    goal set of the target finally used (of the most uncertain one on failure).
    wall_time_s: planning wall time, s; cost_time_s: part of it spent in
    covariance / cost evaluation (Alg. 4), s (time.perf_counter diagnostics).
    tree_positions: (n_nodes, n, 2) m, tree_times: (n_nodes, n) steps and
    tree_parents: (n_nodes,) (-1 for the root), for visualisation and checks.
    """

    plan: TeamPlan | None
    reason: str
    n_samples: int
    n_nodes: int
    n_goal_nodes: int
    wall_time_s: float
    cost_time_s: float
    tree_positions: np.ndarray
    tree_times: np.ndarray
    tree_parents: np.ndarray

    @property
    def success(self) -> bool:
        return self.plan is not None

    @property
    def cost_time_share(self) -> float:
        return self.cost_time_s / self.wall_time_s if self.wall_time_s > 0 else 0.0


# ---------------------------------------------------------------------------
# Steering and time matching
# ---------------------------------------------------------------------------


def _steps_for(distance: np.ndarray, u_max: float) -> np.ndarray:
    """Fewest whole steps to cover ``distance`` at <= u_max per step (>= 1)."""
    return np.maximum(np.ceil(np.asarray(distance) / u_max - TIME_TOL), 1).astype(int)


def steer(
    q_nearest: np.ndarray,
    t_nearest: np.ndarray,
    q_rand: np.ndarray,
    step_size: float,
    u_max: float,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Algorithm 6 (Appendix A) with integer times.

    q_nearest, q_rand: (n, 2) m; t_nearest: (n,) int steps. Returns (q_new
    (n, 2) m, t_new (n,) int) or None when some robot's projection d_ij is 0.
    s = min(step_size, min_j |d_ij|); Delta t_s = ceil(s / u_max) steps at the
    common speed s / Delta t_s; Delta t_c,ij = Delta t_s - (t_ij - min t); a
    robot with Delta t_c,ij > 0 moves speed * Delta t_c,ij along d_ij and
    arrives at min t + Delta t_s, the others stay with their times.
    """
    q_nearest = np.asarray(q_nearest, dtype=float)
    t_nearest = np.asarray(t_nearest, dtype=int)
    d = np.asarray(q_rand, dtype=float) - q_nearest  # line 1
    norms = np.linalg.norm(d, axis=1)
    s = min(float(step_size), float(norms.min()))  # line 2
    if s <= MOVE_TOL_M:
        return None
    dt_s = int(_steps_for(s, u_max))  # line 3
    speed = s / dt_s
    t_min = int(t_nearest.min())
    dt_c = dt_s - (t_nearest - t_min)  # line 4
    move = dt_c > 0  # line 5
    q_new = q_nearest.copy()
    q_new[move] += (speed * dt_c[move] / norms[move])[:, None] * d[move]  # line 6
    t_new = np.where(move, t_min + dt_s, t_nearest)  # lines 6-9
    return q_new, t_new.astype(int)


def arrival_times(
    t_parent: np.ndarray, q_parent: np.ndarray, q_child: np.ndarray, u_max: float
) -> np.ndarray | None:
    """Arrival steps (n,) at ``q_child`` (n, 2) from a parent node, or None if
    no robot moves.

    The moving robots arrive together at T = max over them of t_j(parent) +
    ceil(|Delta_j| / u_max); standing robots wait until T unless they are
    already later (then they keep their time, as in Algorithm 6). Every robot's
    speed stays <= u_max. For Steer's own output this returns Steer's times.
    """
    times, valid = arrival_times_many(
        np.asarray(t_parent)[None], np.asarray(q_parent, float)[None], np.asarray(q_child, float)[None], u_max
    )
    return times[0] if valid[0] else None


def arrival_times_many(
    t_parent: np.ndarray, q_parent: np.ndarray, q_child: np.ndarray, u_max: float
) -> tuple[np.ndarray, np.ndarray]:
    """:func:`arrival_times` for P parent/child pairs at once: t_parent (P, n)
    steps, q_parent and q_child (P, n, 2) m (q_child may be one (n, 2)).
    Returns times (P, n) int and valid (P,) bool (False where no robot moves;
    those rows of times are meaningless)."""
    t_parent = np.asarray(t_parent, dtype=int)
    disp = np.linalg.norm(q_child - q_parent, axis=-1)
    moving = disp > MOVE_TOL_M
    t_arrive = np.where(moving, t_parent + _steps_for(disp, u_max), np.iinfo(int).min).max(axis=-1)
    times = np.where(moving | (t_parent < t_arrive[:, None]), t_arrive[:, None], t_parent)
    return times.astype(int), moving.any(axis=-1)


def near_radius(
    n_nodes: int, n_robots: int, area: float, step_size: float, gamma_scale: float
) -> float:
    """RRT* near radius r = min(gamma (log n / n)^(1/d), eta), m (joint space).

    d = 2 n_robots; gamma = gamma_scale * 2 (1 + 1/d)^(1/d) (mu / zeta_d)^(1/d)
    with mu = area^n_robots and zeta_d the unit d-ball volume; eta = sqrt(n_robots)
    * step_size (the longest Steer move in the joint space).
    """
    d = 2 * n_robots
    if n_nodes < 2:
        return 0.0
    zeta = math.pi ** (d / 2) / math.gamma(d / 2 + 1)
    gamma = gamma_scale * 2.0 * (1.0 + 1.0 / d) ** (1.0 / d) * (area**n_robots / zeta) ** (1.0 / d)
    radius = gamma * (math.log(n_nodes) / n_nodes) ** (1.0 / d)
    return min(radius, math.sqrt(n_robots) * step_size)


# ---------------------------------------------------------------------------
# The tree
# ---------------------------------------------------------------------------


class _Tree:
    """Nodes of Algorithm 1 in growable arrays.

    q: (N, n, 2) m; t: (N, n) steps; tau: (N,) settled step min_j t_j;
    cost: (N,) m^2; unc: (N, M) per-target lambda_max at tau, m^2; cov: the
    covariance at tau (PredictedBelief representation); tail: (n, D, 2)
    positions at steps tau + 1 .. tau + D (NaN after t_j); connected: (N,).
    """

    def __init__(self, n_robots: int, n_targets: int, capacity: int):
        self.size = 0
        self.q = np.empty((capacity, n_robots, 2))
        self.flat = self.q.reshape(capacity, 2 * n_robots)
        self.t = np.empty((capacity, n_robots), dtype=int)
        self.tau = np.empty(capacity, dtype=int)
        self.parent = np.full(capacity, -1, dtype=int)
        self.cost = np.empty(capacity)
        self.unc = np.empty((capacity, n_targets))
        self.connected = np.zeros(capacity, dtype=bool)
        self.cov: list[np.ndarray] = []
        self.tail: list[np.ndarray] = []
        self.children: list[list[int]] = []

    def add(self, q, t, parent, cost, unc, cov, tail, connected) -> int:
        i = self.size
        self.q[i], self.t[i], self.tau[i] = q, t, t.min()
        self.parent[i], self.cost[i], self.unc[i] = parent, cost, unc
        self.connected[i] = connected
        self.cov.append(cov)
        self.tail.append(tail)
        self.children.append([])
        if parent >= 0:
            self.children[parent].append(i)
        self.size += 1
        return i

    def set_state(self, i, t, cost, unc, cov, tail) -> None:
        self.t[i], self.tau[i], self.cost[i], self.unc[i] = t, t.min(), cost, unc
        self.cov[i], self.tail[i] = cov, tail

    def reparent(self, i: int, parent: int) -> None:
        self.children[self.parent[i]].remove(i)
        self.parent[i] = parent
        self.children[parent].append(i)

    def synced(self, i: int) -> bool:
        return bool(self.t[i].min() == self.t[i].max())

    def ancestors(self, i: int) -> set[int]:
        out = set()
        while i >= 0:
            out.add(i)
            i = int(self.parent[i])
        return out

    def path(self, i: int) -> list[int]:
        out = []
        while i >= 0:
            out.append(i)
            i = int(self.parent[i])
        return out[::-1]


# ---------------------------------------------------------------------------
# Algorithm 1
# ---------------------------------------------------------------------------


class _Planner:
    def __init__(self, problem: PlanningProblem, params: PlannerParams, rng: np.random.Generator):
        self.problem = problem
        self.params = params
        self.rng = rng
        self.n = problem.n_robots
        self.z = params.sensor_height
        self.margin = params.robot_radius
        self.bounds = problem.bounds
        self.boxes = problem.boxes
        self.belief = PredictedBelief(
            problem.motion,
            problem.estimate,
            problem.covariance,
            problem.belief_time,
            problem.boxes,
            params.sensor_height,
            params.sensing_range,
            params.measurement_period,
            sensor_offsets=problem.sensor_offsets,
        )
        lo, hi = self.bounds[0] + self.margin, self.bounds[1] - self.margin
        self.area = float(np.prod(np.maximum(hi - lo, 0.0)))
        self.tree = _Tree(self.n, problem.motion.n_targets, params.n_sample + 1)
        self.cost_time = 0.0

    # -- sampling (Sec. IV) --------------------------------------------------
    def _uniform_free(self, count: int) -> np.ndarray | None:
        lo, hi = self.bounds[0] + self.margin, self.bounds[1] - self.margin
        found = np.empty((0, 2))
        for _ in range(self.params.max_sample_tries):
            points = self.rng.uniform(lo, hi, size=(count, 2))
            ok = points_free(self.boxes, self.bounds, points, self.z, self.margin)
            found = np.concatenate([found, points[ok]])
            if len(found) >= count:
                return found[:count]
        return None

    def _sample(self, index: int) -> np.ndarray | None:
        if index < self.params.n_uniform:  # f1: uniform over the free joint space
            return self._uniform_free(self.n)
        sigma = 2.0 * self.params.comm_range  # f2 = N([q; ...; q], (2R)^2 I)
        for _ in range(self.params.max_sample_tries):
            q = self._uniform_free(1)
            if q is None:
                return None
            sample = q + self.rng.normal(0.0, sigma, size=(self.n, 2))
            if points_free(self.boxes, self.bounds, sample, self.z, self.margin).all():
                return sample
        return None

    # -- geometry ------------------------------------------------------------
    def _edges_free(self, parents: list[int], q_child: np.ndarray) -> np.ndarray:
        """(P,) CollisionFree(parent_p -> q_child) for all robots."""
        if not parents:
            return np.zeros(0, dtype=bool)
        a = self.tree.q[parents].reshape(-1, 2)
        b = np.broadcast_to(q_child, (len(parents), self.n, 2)).reshape(-1, 2)
        return edges_free(self.boxes, a, b, self.z, self.margin).reshape(len(parents), self.n).all(1)

    def _connected(self, q: np.ndarray) -> bool:
        """Goal condition (6)(i) at configuration q (n, 2)."""
        return is_connected(communication_graph(self.boxes, q, self.z, self.params.comm_range))

    def _lambda2(self, q: np.ndarray) -> float:
        return algebraic_connectivity(communication_graph(self.boxes, q, self.z, self.params.comm_range))

    # -- cost (Alg. 4) -------------------------------------------------------
    def _evaluate(self, parents: list[int], q_children: list[np.ndarray], t_children: list[np.ndarray]):
        """Cost, covariance, per-target unc and tail of each child given its parent."""
        start = time.perf_counter()
        tree = self.tree
        tail_list = [tree.tail[p] for p in parents]
        depth = max(tail.shape[1] for tail in tail_list)
        tails = np.full((len(parents), self.n, depth, 2), np.nan)
        for c, tail in enumerate(tail_list):
            tails[c, :, : tail.shape[1]] = tail
        seqs, n_steps, spans = edge_sequences(
            tree.t[parents], tree.q[parents], tree.tau[parents], tails,
            np.array([tail.shape[1] for tail in tail_list]),
            np.ascontiguousarray(np.broadcast_to(np.asarray(q_children, float), (len(parents), self.n, 2))),
            np.asarray(t_children, dtype=np.int64),
        )
        # A child's tail: the steps after it settles, where some robots are already ahead.
        tails = [seqs[c, :, k:span].copy() for c, (k, span) in enumerate(zip(n_steps, spans))]
        positions = seqs[:, :, : max(n_steps.max(), 0)]
        prop = self.belief.propagate(
            np.stack([tree.cov[p] for p in parents]),
            tree.tau[parents],
            n_steps,
            positions,
        )
        costs = tree.cost[parents] + prop.cost
        self.cost_time += time.perf_counter() - start
        return costs, prop.covariance, prop.target_uncertainty, tails

    # -- root ----------------------------------------------------------------
    def _known_position(self, j: int, t: int) -> np.ndarray:
        """Robot j's position at step t <= t_0,j (start, prefix, or NaN)."""
        problem = self.problem
        if t == problem.start_times[j]:
            return problem.start_positions[j]
        prefix = problem.prefixes[j] if problem.prefixes is not None else None
        if prefix is not None and prefix.start_time <= t <= prefix.end_time:
            return prefix.position_at(t)
        return np.full(2, np.nan)

    def _add_root(self) -> None:
        problem, belief = self.problem, self.belief
        t0 = problem.start_times
        tau = int(t0.min())
        depth = int(t0.max()) - tau
        tail = np.array(
            [[self._known_position(j, tau + 1 + k) if tau + 1 + k <= t0[j] else (np.nan, np.nan)
              for k in range(depth)] for j in range(self.n)]
        ).reshape(self.n, depth, 2)
        lead = tau - problem.belief_time
        positions = np.array(
            [[self._known_position(j, problem.belief_time + 1 + k) for k in range(lead)]
             for j in range(self.n)]
        ).reshape(1, self.n, lead, 2)
        start = time.perf_counter()
        prop = belief.propagate(
            belief.initial_covariance[None], np.array([problem.belief_time]), np.array([lead]), positions
        )
        self.cost_time += time.perf_counter() - start
        connected = self._connected(problem.start_positions)
        self.tree.add(
            problem.start_positions, t0, -1, 0.0, prop.target_uncertainty[0], prop.covariance[0],
            tail, connected,
        )

    # -- rewiring ------------------------------------------------------------
    def _update_subtree(self, root: int) -> None:
        """Recompute times, covariances and costs below a rewired node."""
        tree = self.tree
        frontier = [root]
        while frontier:
            kids = [c for u in frontier for c in tree.children[u]]
            if not kids:
                return
            parents = [int(tree.parent[c]) for c in kids]
            times, _ = arrival_times_many(tree.t[parents], tree.q[parents], tree.q[kids], self.params.u_max)
            costs, covs, uncs, tails = self._evaluate(parents, [tree.q[c] for c in kids], times)
            for k, c in enumerate(kids):
                tree.set_state(c, times[k], costs[k], uncs[k], covs[k], tails[k])
            frontier = kids

    # -- Algorithm 1 ---------------------------------------------------------
    def grow(self) -> int:
        params, tree = self.params, self.tree
        self._add_root()
        if not points_free(self.boxes, self.bounds, self.problem.start_positions, self.z, self.margin).all():
            return 0
        taken = 0
        for index in range(params.n_sample):
            taken += 1
            sample = self._sample(index)  # line 3
            if sample is None:
                continue
            size = tree.size
            nearest = int(np.argmin(((tree.flat[:size] - sample.ravel()) ** 2).sum(axis=1)))  # line 4
            steered = steer(tree.q[nearest], tree.t[nearest], sample, params.step_size, params.u_max)
            if steered is None:  # line 5
                continue
            q_new, _ = steered
            radius = near_radius(size + 1, self.n, self.area, params.step_size, params.gamma_scale)
            dist2 = ((tree.flat[:size] - q_new.ravel()) ** 2).sum(axis=1)
            others = [int(v) for v in np.flatnonzero(dist2 <= radius**2) if v != nearest]
            # CollisionFree of every edge into q_new in one call; v_nearest's decides line 6.
            edge_free = self._edges_free([nearest] + others, q_new)
            if not edge_free[0]:  # line 6
                continue
            near = [int(v) for v in np.flatnonzero(dist2 <= radius**2)]  # line 8
            free = dict(zip(others, edge_free[1:]))
            free[nearest] = True
            # Algorithm 2: Extend.
            order = [v for v in [nearest] + others if free[v]]
            times_all, valid = arrival_times_many(tree.t[order], tree.q[order], q_new, params.u_max)
            candidates = [v for v, ok in zip(order, valid) if ok]
            cand_times = list(times_all[valid])
            if not candidates:
                continue
            costs, covs, uncs, tails = self._evaluate(candidates, [q_new] * len(candidates), cand_times)
            best = int(np.argmin(costs))  # first minimum: v_nearest wins ties (Alg. 2, line 1)
            connected = self._connected(q_new)
            new = tree.add(
                q_new, cand_times[best], candidates[best], costs[best], uncs[best], covs[best],
                tails[best], connected,
            )  # line 7, Alg. 2 lines 8-9
            self._rewire(new, near, free)  # line 10
        return taken

    def _rewire(self, new: int, near: list[int], free: dict) -> None:
        """Algorithm 3."""
        tree, u_max = self.tree, self.params.u_max
        blocked = tree.ancestors(new)
        near = [v for v in near if v not in blocked and free[v] and tree.synced(v)]  # line 2
        if not near:
            return
        times, valid = arrival_times_many(tree.t[new][None], tree.q[new][None], tree.q[near], u_max)
        keep = valid & (times.min(axis=1) == times.max(axis=1))  # synchronised through v_new
        targets = [v for v, ok in zip(near, keep) if ok]
        target_times = list(times[keep])
        if not targets:
            return
        costs, covs, uncs, tails = self._evaluate(  # line 3
            [new] * len(targets), [tree.q[v] for v in targets], target_times
        )
        for k, v in enumerate(targets):
            if costs[k] < tree.cost[v]:  # line 4
                tree.reparent(v, new)  # line 5
                tree.set_state(v, target_times[k], costs[k], uncs[k], covs[k], tails[k])
                self._update_subtree(v)

    # -- goal set (6) and the returned plan -----------------------------------
    def target_order(self) -> np.ndarray:
        """Targets by decreasing lambda_max of their block in the team's belief;
        equal values (to 1e-9 relative: unseen targets from one prior tie
        exactly) by ``problem.target_priority`` (default: target index)."""
        unc = self.belief.target_uncertainty(self.belief.initial_covariance)
        key = np.round(unc / max(float(unc.max()), 1e-300), 9)
        priority = self.problem.target_priority
        if priority is None:
            priority = np.arange(len(unc))
        return np.lexsort((priority, -key))

    def goal_nodes(self, target: int) -> np.ndarray:
        tree = self.tree
        size = tree.size
        synced = tree.t[:size].min(axis=1) == tree.t[:size].max(axis=1)
        after_start = tree.t[:size, 0] > self.problem.start_times.max()  # t_f > t_0,ij
        ok = synced & after_start & tree.connected[:size] & (tree.unc[:size, target] <= self.params.delta)
        return np.flatnonzero(ok)

    def verify(self, nodes: list[int], target: int) -> str:
        """Independent re-check of a root-to-goal node path; '' when valid."""
        tree, params = self.tree, self.params
        for parent, child in zip(nodes[:-1], nodes[1:]):
            dt = tree.t[child] - tree.t[parent]
            disp = np.linalg.norm(tree.q[child] - tree.q[parent], axis=1)
            if np.any(dt < 0) or np.any(disp > params.u_max * dt * (1 + SPEED_RTOL) + MOVE_TOL_M):
                return "speed bound violated"
            a = lift(tree.q[parent], self.z)
            b = lift(tree.q[child], self.z)
            if not segments_free(self.boxes, a, b, self.margin).all():
                return "collision"
        end = nodes[-1]
        if not points_free(self.boxes, self.bounds, tree.q[nodes].reshape(-1, 2), self.z, self.margin).all():
            return "outside the free space"
        if not tree.synced(end):
            return "not synchronised"
        if not tree.t[end, 0] > self.problem.start_times.max():
            return "meeting not after every start"
        if not self._lambda2(tree.q[end]) > CONNECTIVITY_TOL:
            return "not connected"
        if not tree.unc[end, target] <= params.delta:
            return "uncertainty above delta"
        return ""

    def build_plan(self, nodes: list[int], target: int, rank: int) -> TeamPlan:
        tree = self.tree
        paths = []
        for j in range(self.n):
            times, positions = [], []
            for v in nodes:
                t, q = int(tree.t[v, j]), tree.q[v, j]
                if times and t == times[-1]:
                    continue  # robot j did not move and kept its time
                times.append(t)
                positions.append(q.copy())
            paths.append(RobotPath(np.array(times), np.array(positions)))
        end = nodes[-1]
        t_f = int(tree.t[end, 0])
        estimate = self.belief.mean(t_f)
        covariance = self.belief.full_covariance(tree.cov[end])
        lam2 = self._lambda2(tree.q[end])
        meeting = tree.q[end].copy()
        for arr in (meeting, estimate, covariance):
            arr.setflags(write=False)
        return TeamPlan(
            paths=tuple(paths),
            meeting_time=t_f,
            meeting_positions=meeting,
            cost=float(tree.cost[end]),
            target=int(target),
            target_rank=int(rank),
            target_uncertainty=float(tree.unc[end, target]),
            meeting_estimate=estimate,
            meeting_covariance=covariance,
            meeting_lambda2=float(lam2),
        )


def plan_meeting(
    problem: PlanningProblem, params: PlannerParams, rng: np.random.Generator
) -> PlanResult:
    """Plan the team's paths to its next meeting (Algorithm 1 with the
    fallback of Sec. IV). Randomness only from ``rng``.

    Returns a :class:`PlanResult` whose ``plan`` satisfies every constraint of
    problem (5), or is None (with ``reason``) when no goal node exists for any
    target; the caller then replans or falls back.
    """
    if not isinstance(rng, np.random.Generator):
        raise ValueError("rng must be a numpy.random.Generator")
    start = time.perf_counter()
    planner = _Planner(problem, params, rng)
    taken = planner.grow()
    tree = planner.tree
    plan, reason, n_goal = None, "", 0
    if taken == 0:
        reason = "start configuration is not in the free space"
    else:
        for rank, target in enumerate(planner.target_order()):
            goals = planner.goal_nodes(int(target))
            if rank == 0:
                n_goal = len(goals)
            for node in goals[np.argsort(tree.cost[goals], kind="stable")]:
                nodes = tree.path(int(node))
                if planner.verify(nodes, int(target)) == "":
                    plan = planner.build_plan(nodes, int(target), rank)
                    n_goal = len(goals)
                    break
            if plan is not None:
                break
        else:
            reason = f"no goal node for any target after {taken} samples ({tree.size} nodes)"
    size = tree.size
    return PlanResult(
        plan=plan,
        reason=reason,
        n_samples=taken,
        n_nodes=size,
        n_goal_nodes=n_goal,
        wall_time_s=time.perf_counter() - start,
        cost_time_s=planner.cost_time,
        tree_positions=tree.q[:size].copy(),
        tree_times=tree.t[:size].copy(),
        tree_parents=tree.parent[:size].copy(),
    )
