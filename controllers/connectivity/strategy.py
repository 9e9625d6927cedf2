"""The ``connected`` strategy: the continuous-connectivity method (Nestmeyer et al. 2017) on MuJoCo quadrotors.

Every robot i owns a virtual point q_i with the second-order dynamics of
eq. (1),

    M v_i' = f_B + f_lambda + f_i,   q_i' = v_i,   f_B = -B v_i,

integrated once per control period (semi-implicit Euler with implicit
damping, :func:`dynamics.step_virtual_dynamics`). The real quadrotor tracks
q_i through the foundation's geometric controller: its reference is
(q_i, v_i, a_i) with a_i the virtual acceleration over the period, so
``tracking_error_mean_m`` in metrics.json is the real body against q_i (the
paper's Fig. 11). Virtual points start at the robots' start positions, at rest.

Per control tick (all robots at once):

1. Connectivity (Appendix A): the weights W_ij(q) of the sensor model (range
   R_s, line-of-sight clearance R_o from the scene's obstacle boxes, inter-robot
   distance R_c), the Laplacian, lambda2 and the Fiedler vector, and
   f_lambda = -V'(lambda2) dlambda2/dq (eq. 16-17 with the inter-robot terms).
   ``lambda2_source = "exact"`` uses one eigendecomposition (the centralised
   oracle); ``"estimator"`` gives each robot its own estimate of lambda2 and
   of its eigenvector component from the decentralised estimator of Yang et
   al. (2010), updated only through links of the current graph. The exact
   value is always computed too, for the invariants and metrics.
2. Exploration (Secs. 3.2-3.7, Algorithms 1-2): roles, the prime traveler
   election by flooding over the simulator's current communication graph
   (links within ``sensing.comm_range_m`` = R_s and in ``mj_ray`` line of
   sight, one hop per ``message_latency_ticks``), consensus on the prime
   traveler's efficiency over the same graph, travel / anchor forces f_i.
   Under a real radio (``radio.preset`` not ``ideal``) the election, the
   token and the consensus are messages on the message bus instead
   (``Observation.inbox`` in, ``Commands.outbox`` out; docs/radio.md).
3. Integrate q, v; send (q, v, a) to the quadrotors.

The run ends early (``finished``) once every target is visited and every
robot is a connector again.

Ground robots (the intermittent paper's e-puck bodies; ``preset = "ground"``): the team is
all ground robots or all quadrotors. On the ground the virtual points live in
the horizontal plane of the range sensors (z = the sensors' mean height at the
start): q_i starts at robot i's sensor, every force's z component is dropped
(planar virtual dynamics), obstacles are the boxes that reach above half that
height (the floor slab drops out), and the planner's grid is one layer in that
plane. The body's point-offset wheel controller tracks (q_i, v_i) in x, y.

Target generator: by default the scenario's (``targets``: random or fixed
lists, Sec. 2.1); a caller may pass ``targets``, a function
(planner, start points (N, 3), rng) -> TargetQueues, and keep pushing to
``self.queues`` during the run (online targets, e.g. the EKF's viewpoints of
``connected_tracking``).

``commands.scalars``: lambda2, edges, roles, Lambda_p and its estimates,
Theta, rho, distances (plots and the recording); ``commands.decorations``
(sim.types.Decorations): ``robot_scalars`` (per robot: role,
hat-Lambda_p^i, Lambda_i, Theta_i, rho_i: the recording), ``link_weights``
(W: link colours in the video), ``robot_colors`` (prime traveler
highlighted), ``paths`` (planned paths gamma_i), ``markers`` and
``marker_colors`` (current targets), ``events`` (role changes and visits),
``overlay`` (one line burned into the video). Built only on ticks whose
observation has ``decorations_wanted`` (an observer reads them); role
changes and visits wait in ``events`` until then.

Deviations from the paper
-------------------------
See connected_params.py, mission.py and the library modules (graph.py,
potential.py, estimator.py, dynamics.py, paths.py, travel.py, roles.py,
election.py, targets.py). Here:
- The paper integrates at 1 kHz; we integrate at the control period (10 ms).
- With ``lambda2_source = "estimator"`` the estimator first runs
  ``estimator_warmup_s`` seconds on the start graph (the robots exchange
  estimator messages on the ground before the mission starts); the paper
  does not discuss start-up of the estimator.
- The estimator's messages travel on the links of G^lambda (W_ij > 0, on the
  virtual points), as the paper assumes one graph for sensing and
  communication; election and efficiency consensus use the simulator's
  body-to-body graph A (range and mj_ray line of sight). The two differ when
  bodies lag their points (0.2-0.3 m at peaks): a link of weight ~0.06 can
  be out of range for the bodies. ``estimator_links = "messages"`` restricts
  the estimator to W o A and makes f_lambda the gradient of lambda2(W o A)
  (A held fixed; lambda2(W) >= lambda2(W o A)); a dropped bridge then
  isolates a robot discontinuously (docs/results.md: seed 1 disconnects).
- Estimator mode: robot i evaluates V' at min(its estimate, N/(N-1) d_i),
  with d_i = sum_j W_ij its own degree (lambda2 <= N/(N-1) min_i d_i,
  Fiedler 1973: a bound every robot knows), and at no less than
  lambda2_min + ``estimator_floor`` (an estimator transient below the true
  lambda2 would otherwise launch the virtual points with the barrier's
  near-singular slope).
- Estimator mode under a radio preset other than "ideal": the estimator's
  state travels as messages on the bus, one exchange a tick, fed to
  estimator_messages.MessageFedEstimator (one vector; gains
  ``estimator_message_speedup``); each robot's eq. (17) uses the Fiedler
  components it received. Under "ideal" it runs in process as before.
- Robots never fail in the paper. A robot the team no longer hears is dropped (failures.py): out of the
  graph, the election, the consensus and the estimator (over the radio MessageFedEstimator.drop), its virtual
  point frozen, a lost token re-issued, its targets handed on; in exact mode it is taken back, as a
  connector, once heard again where that keeps the team connected. Under position noise the
  force comes from the virtual points as measured, each displaced by its robot's fix error
  (``Observation.position_error``); the invariants from the true ones.
- Exact mode with ``spectrum_smoothing`` > 0: V acts on a smooth lower bound
  of lambda2 (smooth_spectrum.py) instead of lambda2 itself.
- Estimator mode with ``estimator_modes`` K >= 2 (not in the paper): the
  robots track the K lowest non-trivial eigenpairs (estimator.SubspaceEstimator)
  and robot i drives V with the soft minimum (``spectrum_smoothing``) of its
  own Ritz values and its gradient from its Ritz vectors
  (estimator.ritz_connectivity_gradient), bounded as above.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from controllers.connectivity.connected_params import ConnectedParams
from controllers.connectivity.dynamics import step_virtual_dynamics_applied
from controllers.connectivity.estimator import FiedlerEstimator, SubspaceEstimator, ritz_connectivity_gradient
from controllers.connectivity.estimator_messages import MessageFedEstimator
from controllers.connectivity.exploration import ExplorationController, ExplorationStep
from controllers.connectivity.failures import (
    TAKE_BACK_MIN_WEIGHT,
    DroppedRobot,
    drop_from_election,
    heard_again,
    newly_silent,
    obstacles_with_dropped,
    reassign_targets,
)
from controllers.connectivity.graph import connectivity_state, generalized_connectivity_force
from controllers.connectivity.mission import (
    MissionStatistics,
    LAMBDA2_TOLERANCE,
    check_start,
    pairwise_min_distance,
    shared_planner,
    target_queues,
)
from controllers.connectivity.potential import guarded_potential_slope
from controllers.connectivity.roles import ANCHOR_CODE, CONNECTOR_CODE, PRIME_CODE, SECONDARY_CODE, Role
from controllers.connectivity.smooth_spectrum import smooth_lambda2_gradient
from sim import palette
from sim.config import ConfigError
from sim.geometry import boxes_reaching, point_clearance
from sim.radio.protocols import HeartbeatMonitor
from sim.types import NO_DECORATIONS, Commands, Decorations, Observation, SceneChange, WorldInfo
from sim.strategy import Strategy

# Colours (RGBA) of the robots by role in the pictures (sim.palette); a traveler's path takes its
# role's colour, so one legend entry names both.
ROLE_COLORS = {
    Role.PRIME_TRAVELER: palette.PRIME_TRAVELER,
    Role.SECONDARY_TRAVELER: palette.SECONDARY_TRAVELER,
    Role.ANCHOR: palette.ANCHOR,
    Role.CONNECTOR: palette.CONNECTOR,
}
ROLE_NAMES = {Role.PRIME_TRAVELER: "prime traveler", Role.SECONDARY_TRAVELER: "secondary traveler",
              Role.ANCHOR: "anchor", Role.CONNECTOR: "connector"}
# Opaque: software GL draws a translucent geom in a second, sorted pass (a frame of connected-office took
# about a quarter longer with its paths at alpha 0.85-0.9), and translucent paths darkened where they crossed.
PRIME_PATH_RGBA = palette.PRIME_TRAVELER
SECONDARY_PATH_RGBA = palette.SECONDARY_TRAVELER
TARGET_RGBA = palette.GOAL
# What the colours mean (``Decorations.legend``: video, tuning page, viewer, recording) and the role
# codes' names (plots).
# Each names a robot (its mark on top) so that a picture reads without the README.
_LEGEND_LABELS = {Role.PRIME_TRAVELER: "robot: prime traveler, its path",
                  Role.SECONDARY_TRAVELER: "robot: secondary traveler, its path",
                  Role.ANCHOR: "robot: anchor", Role.CONNECTOR: "robot: connector"}
LEGEND = Decorations(legend=(*((_LEGEND_LABELS.get(r, ROLE_NAMES[r]), ROLE_COLORS[r]) for r in Role),
                             ("traveler's target point", palette.GOAL))).legend  # read-only once, not every tick
# While the team has dropped a robot, the legend names its colour too (drawn only then).
LEGEND_WITH_DROPPED = (*LEGEND, ("robot dropped from the team (not heard)", palette.DROPPED))
ROLE_LEVELS = {float(r): ROLE_NAMES[r] for r in Role}
# Spacing of the points that draw a planned path, as a fraction of R_grid.
_PATH_DRAW_SPACING = 2.0
# Length of the estimator warm-up steps, s.
_WARMUP_STEP_S = 0.01


# A start placed in another scene keeps this much more than R_o from obstacles, m.
START_LINK_MARGIN_M = 0.05


def _table_or_none(strategy_table: dict) -> ConnectedParams | None:
    """The ``[strategy]`` table's parameters (presets filled), or None where it does not build (the run
    refuses it by name later)."""
    from sim.config import build

    try:
        return build(ConnectedParams, {k: v for k, v in strategy_table.items() if k != "kind"}, "strategy")
    except ValueError:
        return None


class ConnectedStrategy(Strategy):
    """Nestmeyer et al. 2017 for a team of quadrotors (see the module docstring)."""

    mission_can_end = True

    def __init__(self, params: ConnectedParams, targets=None):
        self.table = params  # the scenario's keys; ``params`` adds the scenario's R_s (reset)
        self.params = params
        self._target_generator = targets
        self.timings = {"lambda2": 0.0, "forces": 0.0}  # s of wall time per stage, for benchmarks
        self._finished = False

    # ------------------------------------------------------------------ set-up
    @classmethod
    def start_clearance_m(cls, strategy_table: dict, robot_kind: str) -> float:
        """R_o plus START_LINK_MARGIN_M: a start graph with lambda2 > 0 needs every link's line of
        sight clearer than R_o (0 for a table that does not build: the run refuses it by name)."""
        table = _table_or_none(strategy_table)
        return 0.0 if table is None else float(table.min_obstacle_clearance_m) + START_LINK_MARGIN_M

    @classmethod
    def start_separation_m(cls, strategy_table: dict) -> float:
        """Half way from R_c to R'_c: within R_c a robot cuts the start graph's links, and near R_c
        their weights (rising from R_c to R'_c) leave lambda2 all but 0."""
        table = _table_or_none(strategy_table)
        return 0.0 if table is None else 0.5 * float(table.min_robot_distance_m + table.full_weight_robot_distance_m)

    @classmethod
    def adapt_to_scene(cls, strategy_table: dict, change: SceneChange, keep: frozenset[str]) -> list[str]:
        """Fixed targets (``target_lists``) scaled from the old floor plan into the new one, each
        moved to the nearest spot ``target_clearance_m`` from obstacles and the bounds; random
        targets are drawn in the new scene anyway."""
        from sim.free_space import candidate_grid, nearest_free, scale_plan

        lists = strategy_table.get("target_lists")
        if strategy_table.get("targets") != "fixed" or not lists or "strategy.target_lists" in keep:
            return []
        table = _table_or_none(strategy_table)
        if table is None:
            return []  # the run refuses the table by name
        grid = candidate_grid(change)
        moved = []
        for robot, route in enumerate(lists):
            points = scale_plan(np.array(route, dtype=float).reshape(-1, 3), change.old_bounds, change.bounds)
            placed = []
            for k, point in enumerate(points):
                spot = nearest_free(change, grid, point, table.target_clearance_m, False)
                if spot is None:
                    raise ConfigError(f"strategy.target_lists.{robot}.{k}", f"no free spot in {change.scene_name} "
                                      f"{table.target_clearance_m:g} m from obstacles; set strategy.target_lists "
                                      "by hand, or --set strategy.targets=\"random\"")
                placed.append([round(float(v), 3) for v in spot])
            moved.append(placed)
        strategy_table["target_lists"] = moved
        return [f"strategy.target_lists: scaled to {change.scene_name}'s floor plan, each target moved to the "
                f"nearest free spot {table.target_clearance_m:g} m from obstacles"]

    def reset(self, world: WorldInfo, initial: Observation, rng: np.random.Generator) -> None:
        n = world.n_robots
        if n < 2:
            raise ConfigError("robots", f"the connected strategy needs at least 2 robots, got {n}")
        kinds = set(world.robot_kinds)
        if len(kinds) > 1:
            ground = [name for name, kind in zip(world.robot_names, world.robot_kinds) if kind != "quadrotor"]
            raise ConfigError("robots", f"the connected strategy drives one kind of robot at a time; "
                              f"{', '.join(ground)} are ground robots among quadrotors")
        try:
            self.params = p = self.table.at_range(world.comm_range_m)
        except ValueError as err:
            name, _, problem = str(err).partition(": ")
            raise ConfigError(f"strategy.{name}", problem) from None
        if not 0 <= p.election_host < n:
            raise ConfigError("strategy.election_host", f"must be a robot index below {n}, got {p.election_host}")
        self.world = world
        self.dt = world.control_period_s
        self.names = world.robot_names
        self.planar = kinds == {"ground"}
        bounds = np.array(world.bounds, dtype=float)
        if self.planar:
            # Virtual points in the plane of the range sensors (see the module docstring).
            self.plane_z = float(np.mean(initial.sensor_position[:, 2]))
            self.boxes = boxes_reaching(world.obstacles, 0.5 * self.plane_z)
            bounds[:, 2] = self.plane_z
            self.q = np.array(initial.sensor_position, dtype=float)
            self.q[:, 2] = self.plane_z
        else:
            self.boxes = world.obstacles
            self.q = np.array(initial.position, dtype=float)
        self.v = np.zeros_like(self.q)
        state = connectivity_state(self.q, self.boxes, p)
        check_start(state, self.q, self.boxes, self.names, p)

        self.planner = shared_planner(self.boxes, bounds, p)
        self._bounds = bounds
        # Targets first: they are the first draws of the run's generator.
        if self._target_generator is None:
            self.queues = target_queues(p, self.planner, self.q, rng)
        else:
            self.queues = self._target_generator(self.planner, self.q.copy(), rng)
        self.targets_total = len(self.queues)
        self.explorers = np.flatnonzero(self.queues.pending())
        # Under a real radio the election, the token and the consensus travel on the message bus.
        over_bus = initial.radio is not None and initial.radio.preset != "ideal"
        self.explorer = ExplorationController(p, self.planner, self.queues, self.dt if over_bus else None)
        # Under a real radio each robot watches whom it still hears (every message is a heartbeat).
        self.heartbeats = (HeartbeatMonitor(n, p.heartbeat_timeout_s, initial.links.adjacency, initial.time_s)
                           if over_bus else None)
        self.estimator = None
        # Under a real radio the estimator's state travels as messages (estimator_messages.py); under the
        # ideal one it runs in process, as before the bus.
        self.estimator_over_radio = p.lambda2_source == "estimator" and initial.radio is not None and (
            initial.radio.preset != "ideal")
        if p.lambda2_source == "estimator":
            if p.estimator_modes >= n:
                raise ConfigError("strategy.estimator_modes", f"must be below the team size {n}, "
                                  f"got {p.estimator_modes}")
            weights = self._estimator_links(state, initial.links.adjacency).weights
            warmup_steps = int(round(p.estimator_warmup_s / _WARMUP_STEP_S))
            if self.estimator_over_radio:
                # Yang et al.'s single vector: over slow, lossy consensus a saturated second mode is not
                # recognised and gives a spurious Ritz value (docs/radio.md).
                self.estimator = MessageFedEstimator(n, p.message_estimator, rng, 1, p.estimator_message_timeout_s,
                                                     p.estimator_consensus)
                try:
                    self.estimator.check_gains(max(self.dt, _WARMUP_STEP_S))
                except ValueError as err:
                    raise ConfigError("strategy.estimator_message_speedup", str(err)) from None
                self.estimator.warm_up(weights, _WARMUP_STEP_S, warmup_steps)
                self._weights = weights
            else:
                if p.estimator_modes == 1:
                    self.estimator = FiedlerEstimator(n, p.estimator, rng)
                else:
                    self.estimator = SubspaceEstimator(n, p.estimator, rng, p.estimator_modes)
                consensus = self._consensus_weights(weights)
                for _ in range(warmup_steps):
                    self.estimator.step(weights, _WARMUP_STEP_S, consensus)
        self.stats = MissionStatistics(self.explorers, self.targets_total)
        self.in_team = np.ones(n, dtype=bool)  # robots not dropped as silent (failures.py)
        self.dropped: list[DroppedRobot] = []
        self._measured_noise = False  # this tick's force came from the noisy measured graph
        self.roles = np.full(n, int(Role.CONNECTOR))
        self.completion_time: float | None = None
        self._finished = False
        self._events: list[str] = []
        self._drawn_paths: dict[int, list] = {}  # id(path) -> [path, samples (K, 3), nearest sample so far]
        self._visits_seen = 0
        self._skipped_seen = 0
        self.last: ExplorationStep | None = None

    def update_params(self, params: ConnectedParams) -> bool:
        """Take new gains from the next tick on; False (restart) when a field
        that shapes the set-up (graph ranges, planner, targets, estimator,
        election) changes."""
        for f in dataclasses.fields(params):
            restarts = not f.metadata.get("tunable", True)
            if f.init and restarts and getattr(params, f.name) != getattr(self.table, f.name):
                return False
        if params.message_latency_ticks != self.table.message_latency_ticks:
            return False
        resolved = params.at_range(self.world.comm_range_m)
        # A change that would break the invariants at the current state is refused before it applies.
        distance = pairwise_min_distance(self.q)
        if not distance >= resolved.min_robot_distance_m:
            raise ValueError(f"min_robot_distance_m: two virtual points are {distance:.3f} m apart now, inside "
                             f"R_c = {resolved.min_robot_distance_m:g} m")
        lambda2 = connectivity_state(self.q, self.boxes, resolved).lambda2
        if not lambda2 > resolved.lambda2_min + LAMBDA2_TOLERANCE:
            raise ValueError(f"lambda2_min: must stay below the current lambda2 ({lambda2:.3g}) of the "
                             f"virtual points, got {resolved.lambda2_min:g}")
        self.table, self.params = params, resolved
        self.explorer.params = resolved
        return True

    def _estimator_links(self, state, adjacency: np.ndarray):
        """The graph the estimator's messages travel on, whose lambda2 the robots estimate and control:
        G^lambda itself ("sensing"), or W o A ("messages"). Its force is always the gradient of that
        graph's lambda2, never of links the estimator cannot see."""
        if self.params.estimator_links == "messages":
            return state.links.restricted_to(adjacency)
        return state.links

    def _consensus_weights(self, estimator_weights: np.ndarray) -> np.ndarray | None:
        """The averaging loops' graph: every message link at weight 1 ("links"),
        or W itself (None, "weights")."""
        if self.params.estimator_consensus == "weights":
            return None
        return (estimator_weights > 0).astype(float)

    def violation(self, commands: Commands) -> str | None:
        """The invariant the tick of ``commands`` broke, or None: Nestmeyer et al. 2017
        keeps lambda2 > lambda2_min and no two virtual points within R_c."""
        p = self.params
        if getattr(self.estimator, "failure", ""):
            return self.estimator.failure
        scalars = commands.scalars
        lambda2 = scalars.get("lambda2", np.inf)
        if not lambda2 > p.lambda2_min + LAMBDA2_TOLERANCE:
            lost = f"lambda2 = {lambda2:.3g} fell to lambda2_min = {p.lambda2_min:g} (connectivity lost)"
            if self._measured_noise:
                lost += ("; the robots keep the graph they measure through their position noise connected, "
                         "and the true one lost a link")
            out = [d for d in self.dropped if d.taken_back_at_s is None]
            if out and self._split_by_drops():  # a dropped robot was the only link between parts of the team
                them = "it" if len(out) == 1 else "them"
                lost += (f" after the team dropped the silent {', '.join(self.names[d.robot] for d in out)}"
                         f" (t = {', '.join(f'{d.at_s:.2f}' for d in out)} s): its graph split without {them}")
            if self.estimator_over_radio:
                estimate = self.estimator.estimate.lambda2[self.in_team]  # a dropped robot's row is NaN
                lost += (f"; the robots' estimates over the radio were {estimate.min():.3g} to {estimate.max():.3g}, "
                         f"over {int(self.estimator.used.sum())} of {int(np.count_nonzero(self._weights))} link "
                         "directions heard")
            return lost
        distance = scalars.get("min_robot_distance_m", np.inf)
        if not distance >= p.min_robot_distance_m:
            return (f"two virtual points came {distance:.3f} m apart, inside R_c = "
                    f"{p.min_robot_distance_m:g} m")
        primes = np.flatnonzero(self.roles == PRIME_CODE)
        if len(primes) > 1:  # Proposition 1: the token makes this impossible, whatever the radio loses
            return f"{len(primes)} prime travelers at once ({', '.join(self.names[i] for i in primes)})"
        return None

    # ------------------------------------------------------------------ per tick
    @property
    def finished(self) -> bool:
        """Every target visited and every robot a connector again (the loop may stop)."""
        return self._finished

    def step(self, observation: Observation) -> Commands:
        p = self.params
        t = observation.time_s
        q, v = self.q, self.v

        start = time.perf_counter()
        if self.heartbeats is not None:
            for receiver, sender in self.heartbeats.step(t, observation.inbox, observation.arrivals):
                self._events.append(f"t = {t:.2f} s: {self.names[receiver]} has heard nothing from "
                                    f"{self.names[sender]} for {p.heartbeat_timeout_s:g} s")
        self._drop_silent(t, observation.links)
        if self.estimator is None and not self.in_team.all():
            self._take_back_heard(t, observation.links)
        team = None if self.in_team.all() else self.in_team
        # Condition (c) still counts a dropped robot (no vertex, but a body its team mates keep clear of) at its
        # virtual point, frozen since the drop: where the team last knew it, so no factor jumps at the drop.
        bystanders = None if team is None else q[~team]
        state = connectivity_state(q if team is None else q[team], self.boxes, p, bystanders)
        measured = self._measured_state(observation.position_error, team, bystanders)
        self._measured_noise = measured is not None
        truth, state = state, state if measured is None else measured  # the force from what is measured
        estimate = None
        if self.estimator is not None:
            links = self._estimator_links(state, observation.links.adjacency)
            if self.estimator_over_radio:
                # Its messages are indexed by robot: the team's weights at their robots' places, the team's rows
                # of what it estimates (the dropped robots left it, MessageFedEstimator.drop).
                weights = links.weights if team is None else _scatter_square(links.weights, team)
                estimate = self.estimator.step(weights, self.dt, t, observation.inbox)
                views = self.estimator.fiedler_views()
                if team is not None:
                    estimate, views = _team_rows(estimate, team), views[np.ix_(team, team)]
                self._weights = weights
            else:
                estimate = self.estimator.step(links.weights, self.dt, self._consensus_weights(links.weights))
            # Each robot also knows its own degree d_i = sum_j W_ij, and lambda2 <= N / (N - 1) min_i d_i
            # (Fiedler 1973): it never uses an estimate above its own bound.
            n = len(links.weights)  # the team's size
            bound = n / (n - 1) * links.weights.sum(axis=1)
            floor = p.lambda2_min + p.estimator_floor
            if getattr(self.estimator, "modes", 1) >= 2:  # SubspaceEstimator, or K >= 2 over the radio
                # Soft minimum of each robot's Ritz values and its gradient from its Ritz vectors.
                smooth, gradient = ritz_connectivity_gradient(links, estimate, p.spectrum_smoothing)
                lambda2_used = np.maximum(np.minimum(smooth, bound), floor)
                f_lambda = -guarded_potential_slope(lambda2_used, p)[:, None] * gradient
            else:
                lambda2_used = np.maximum(np.minimum(estimate.lambda2, bound), floor)
                if self.estimator_over_radio:
                    # Robot i's eq. (17) from the neighbours' components it received: its own row of the
                    # gradient for its own view of the vector.
                    gradients = links.lambda2_gradients(views)
                    own = gradients[np.arange(n), np.arange(n)]
                    f_lambda = -guarded_potential_slope(lambda2_used, p)[:, None] * own
                else:
                    f_lambda = generalized_connectivity_force(links, lambda2_used, estimate.fiedler, p)
        elif p.spectrum_smoothing > 0:
            smooth, gradient = smooth_lambda2_gradient(state.links, state.eigenvalues, state.eigenvectors,
                                                       p.spectrum_smoothing)
            f_lambda = -guarded_potential_slope(smooth, p) * gradient
        else:
            f_lambda = generalized_connectivity_force(state.links, state.lambda2, state.fiedler, p)
        adjacency = observation.links.adjacency
        if team is not None:  # the dropped robots feel no force and are no one's neighbour
            f_lambda = _scatter_rows(f_lambda, team)
            adjacency = adjacency & team[:, None] & team[None, :]
        middle = time.perf_counter()
        out = self.explorer.step(t, q, v, adjacency, f_lambda, observation.inbox, observation.arrivals)
        # f_lambda + f (z dropped for planar virtual dynamics), integrated; the acceleration (v' - v) / dt.
        q_next, v_next, acceleration = step_virtual_dynamics_applied(q, v, f_lambda, out.forces, self.planar,
                                                                     self.dt, p)
        if team is not None:  # a dropped robot's virtual point stays where it was dropped, at rest
            q_next[~team], v_next[~team], acceleration[~team] = q[~team], 0.0, 0.0
        self.timings["lambda2"] += middle - start
        self.timings["forces"] += time.perf_counter() - middle

        obstacle_distance = point_clearance(self.boxes, q)
        body = observation.sensor_position if self.planar else observation.position
        body_obstacle_distance = point_clearance(self.boxes, body)
        robot_distance = pairwise_min_distance(q if team is None else q[team])
        state = truth  # the invariants and the figures on the truth
        if estimate is not None and team is not None:  # per robot again: NaN for the dropped ones
            full = np.full(len(q), np.nan)
            full[team] = estimate.lambda2
            estimate = dataclasses.replace(estimate, lambda2=full)
        tick = self.stats.record(state, q, q_next, out.roles, obstacle_distance, body,
                                 body_obstacle_distance, robot_distance,
                                 None if estimate is None else estimate.lambda2)
        self._note_changes(t, out)
        if out.finished and not self._finished:
            self._finished = True
            if not out.skipped and len(out.visits) == self.targets_total:
                self.completion_time = max((visit.completion_time for visit in out.visits), default=t)
        self.last = out
        # The invariant's figures every tick (violation() reads them); the rest only for observers.
        scalars, decorations = {"lambda2": tick["lambda2"], "min_robot_distance_m": robot_distance}, NO_DECORATIONS
        if observation.decorations_wanted:  # figures and decorations only for observers that read them
            scalars, decorations = self._outputs(out, state, estimate, f_lambda, tick, robot_distance,
                                                 obstacle_distance)
        outbox = out.outbox + (self.estimator.messages() if self.estimator_over_radio else ())
        commands = Commands(q.copy(), v.copy(), acceleration, np.zeros(len(q)), scalars, decorations=decorations,
                            outbox=outbox)
        self.q, self.v = q_next, v_next
        return commands

    def _measured_state(self, position_error: np.ndarray | None, team: np.ndarray | None,
                        bystanders: np.ndarray | None):
        """Under position noise, the connectivity the robots measure (its weights feed the force in exact
        mode and the lambda2 estimator in estimator mode): every virtual point q_j seen displaced by robot
        j's position-fix error, as every robot measures j through the same fix (docs/faults.md); None
        without noise."""
        if position_error is None:
            return None
        seen = self.q + position_error
        if self.planar:
            seen[:, 2] = self.plane_z
        if team is None:
            return connectivity_state(seen, self.boxes, self.params)
        return connectivity_state(seen[team], self.boxes, self.params, bystanders + position_error[~team])

    def _drop_silent(self, t: float, links) -> None:
        """Drop from the team every robot its team mates no longer hear (failures.py): out of the graph and
        the election, its token re-issued if it took it along, its targets to the nearest explorer."""
        if self.heartbeats is None:
            if np.array_equal(links.adjacency, links.line_of_sight):
                return  # every pair in sight is linked: nobody is silent (always so without a fault)
        elif not self.heartbeats.silent.any():
            return
        for robot in newly_silent(self.in_team, links, self.heartbeats, self.world.comm_range_m):
            if self.in_team.sum() <= 2:
                return  # a team of one has nobody to drop anybody
            machine = self.explorer.role_machine
            was_prime = bool(machine.roles[robot] == PRIME_CODE)
            if self.estimator_over_radio:
                self.estimator.drop(robot)  # it keeps every robot's index for the messages
            elif self.estimator is not None:
                # In process the estimator is the team's: sized and ordered as the robots still in it.
                self.estimator = self.estimator.restricted(np.flatnonzero(self.in_team) != robot)
            self.in_team[robot] = False
            held, heir = drop_from_election(machine, robot, self.in_team)
            reassigned, lost = reassign_targets(self.explorer, robot, self.in_team, self.explorers, self.q)
            self.v[robot] = 0.0
            self.dropped.append(DroppedRobot(robot, float(t), was_prime, held, reassigned, lost, heir))
            self._events.append(f"t = {t:.2f} s: the team drops the silent {self.names[robot]}"
                                f"{' (prime traveler)' if was_prime else ''}; {reassigned} of its targets "
                                f"reassigned, {lost} lost"
                                + (f"; {self.names[heir]} takes a new token" if heir is not None else ""))
            self._plan_around_dropped()

    def _split_by_drops(self) -> bool:
        """Whether the team's graph is split only because of the robots it dropped: connected with their
        (frozen) points as members, not without them."""
        p = self.params
        return connectivity_state(self.q, self.boxes, p).lambda2 > p.lambda2_min + LAMBDA2_TOLERANCE

    def _take_back_heard(self, t: float, links) -> None:
        """Take back every dropped robot a team mate hears again over a strong link (weight at least
        TAKE_BACK_MIN_WEIGHT), with the team's graph connected and no virtual point within R_c of its frozen
        one (failures.py): a connector again, from rest where it was frozen."""
        p = self.params
        for entry in self.dropped:
            robot = entry.robot
            if entry.taken_back_at_s is not None or self.in_team[robot]:
                continue
            if not heard_again(robot, entry.at_s, self.in_team, links, self.heartbeats):
                continue
            with_it = self.in_team.copy()
            with_it[robot] = True
            if not pairwise_min_distance(self.q[with_it]) >= p.min_robot_distance_m:
                continue
            state = connectivity_state(self.q[with_it], self.boxes, p, self.q[~with_it])
            row = int(np.count_nonzero(with_it[:robot]))  # its row among the team with it
            if not (state.weights[row].max() >= TAKE_BACK_MIN_WEIGHT
                    and state.lambda2 > p.lambda2_min + LAMBDA2_TOLERANCE):
                continue
            self.in_team[robot] = True
            self.v[robot] = 0.0
            entry.taken_back_at_s = float(t)
            self._events.append(f"t = {t:.2f} s: the team takes back {self.names[robot]}, heard again "
                                f"{t - entry.at_s:.2f} s after its drop")
            self._plan_around_dropped()

    def _plan_around_dropped(self) -> None:
        """The path planner of the scene with a box round each dropped robot's frozen point (failures.py), and
        every traveler's path planned again with it (a path that no longer exists keeps the old one)."""
        p = self.params
        boxes = obstacles_with_dropped(self.boxes, self.q[~self.in_team], self._bounds, p)
        self.planner = shared_planner(boxes, self._bounds, p)
        self.explorer.use_planner(self.planner, self.q, np.flatnonzero(self.in_team))

    # ------------------------------------------------------------------ outputs
    def _note_changes(self, t: float, out: ExplorationStep) -> None:
        for i in np.flatnonzero(out.roles != self.roles):
            self._events.append(f"t = {t:.2f} s: {self.names[i]} becomes {ROLE_NAMES[Role(int(out.roles[i]))]}")
            if out.roles[i] == PRIME_CODE:
                self.stats.elections += 1
        for visit in out.visits[self._visits_seen:]:
            self._events.append(f"t = {t:.2f} s: {self.names[visit.target.robot]} visited its target "
                                f"{visit.target.index + 1} (arrived {visit.arrival_time:.2f} s)")
        for target in out.skipped[self._skipped_seen:]:
            self._events.append(f"t = {t:.2f} s: {self.names[target.robot]} skips its unreachable target "
                                f"{target.index + 1} at {np.round(target.position, 2).tolist()}")
        self._visits_seen, self._skipped_seen = len(out.visits), len(out.skipped)
        self.roles = out.roles.copy()

    def _path_points(self, path, position: np.ndarray) -> np.ndarray:
        """The part of ``path`` still ahead of a robot at ``position`` (drawn
        paths do not trail behind the robots): its samples from the one
        nearest the robot on (never backwards along the path)."""
        cached = self._drawn_paths.get(id(path))
        if cached is None or cached[0] is not path:  # (an id is reused once its path is gone)
            cached = [path, path.sample(_PATH_DRAW_SPACING * self.params.grid_resolution_m), 0]
            self._drawn_paths[id(path)] = cached
        _, points, start = cached
        ahead = points[start:]
        start += int(np.argmin(np.linalg.norm(ahead - position, axis=1)))
        cached[2] = start
        return np.vstack([position[None], points[start + 1:]]) if start + 1 < len(points) else points[-2:]

    def _outputs(self, out: ExplorationStep, state, estimate, f_lambda, tick, robot_distance,
                 obstacle_distance) -> tuple[dict[str, float], Decorations]:
        roles = out.roles
        secondary = roles == SECONDARY_CODE
        others = roles != PRIME_CODE
        nan = float("nan")
        scalars = {
            **tick,
            "lambda2_estimate_mean": float(np.nanmean(estimate.lambda2)) if estimate is not None else nan,
            "prime_traveler": float(out.prime) if out.prime >= 0 else nan,  # undefined without a prime: a gap
            "secondary_travelers": float(secondary.sum()),
            "anchors": float(np.sum(roles == ANCHOR_CODE)),
            "connectors": float(np.sum(roles == CONNECTOR_CODE)),
            "prime_efficiency": out.prime_efficiency,
            "prime_efficiency_estimate_mean": float(out.efficiency_estimate[others].mean()) if others.any() else nan,
            "alignment_mean": float(np.nanmean(out.alignment[secondary])) if secondary.any() else nan,
            "gain_mean": float(np.nanmean(out.gain[secondary])) if secondary.any() else nan,
            "targets_visited": float(len(out.visits)),
            "min_robot_distance_m": robot_distance,
            "min_obstacle_distance_m": float(obstacle_distance.min()),
            "connectivity_force_max_n": float(np.linalg.norm(f_lambda, axis=1).max()),
        }
        if estimate is None:
            del scalars["lambda2_estimate_mean"]
        robot_scalars = {
            "role": roles.astype(float),
            "prime_efficiency_estimate": out.efficiency_estimate,
            "efficiency": out.efficiency,
            "alignment": out.alignment,
            "gain": out.gain,
        }
        if estimate is not None:
            robot_scalars["lambda2_estimate"] = np.asarray(estimate.lambda2, dtype=float)
        colors = np.array([ROLE_COLORS[Role(int(r))] for r in roles])
        colors[~self.in_team] = palette.DROPPED
        paths = [(self._path_points(path, self.q[i]), PRIME_PATH_RGBA if i == out.prime else SECONDARY_PATH_RGBA)
                 for i, path in enumerate(out.paths) if path is not None]
        current = {id(path) for path in out.paths if path is not None}
        self._drawn_paths = {key: value for key, value in self._drawn_paths.items() if key in current}
        has_target = ~np.isnan(out.targets[:, 0])
        prime = self.names[out.prime] if out.prime >= 0 else "none"
        events, self._events = tuple(self._events), []
        decorations = Decorations(
            robot_scalars=robot_scalars,
            robot_scalar_levels={"role": ROLE_LEVELS},
            legend=LEGEND if self.in_team.all() else LEGEND_WITH_DROPPED,
            link_weights=state.weights if len(state.weights) == len(roles) else _scatter_square(state.weights,
                                                                                                self.in_team),
            robot_colors=colors,
            paths=paths,
            markers=out.targets[has_target],
            marker_colors=np.broadcast_to(TARGET_RGBA, (int(has_target.sum()), 4)).copy(),
            overlay=f"lambda2 {state.lambda2:.3f}  prime {prime}  targets {len(out.visits)}/{self.targets_total}",
            events=events,
        )
        return scalars, decorations

    def progress(self) -> str:
        """How far the mission got, for the run's status message."""
        visited = len(self.last.visits) if self.last is not None else 0
        skipped = len(self.last.skipped) if self.last is not None else 0
        return f"{visited}/{self.targets_total} targets visited" + (
            f", {skipped} skipped (no path reaches them)" if skipped else "")

    def summary(self) -> dict:
        """The continuous-connectivity paper's figures for metrics.json (docs/connected.md)."""
        last = self.last
        visited = len(last.visits) if last is not None else 0
        return {
            "lambda2_source": self.params.lambda2_source,
            "completion_time_s": self.completion_time,
            "targets_to_visit": self.targets_total,
            "targets_visited": visited,
            "targets_skipped": len(last.skipped) if last is not None else 0,
            "explorers": int(len(self.explorers)),
            "connectors": int(len(self.q) - len(self.explorers)),
            "prime_elections": self.stats.elections,
            "token_recoveries": self.explorer.role_machine.token_recoveries,
            **self.stats.summary(),
            **self._heartbeat_summary(),
            "dropped_robots": [d.summary() for d in self.dropped],
        }

    def _heartbeat_summary(self) -> dict:
        """Under a real radio: how often a robot counted a neighbour as failed, and when each robot's
        silence was first noticed (per robot, the times a first neighbour declared it silent)."""
        monitor = self.heartbeats
        if monitor is None:
            return {}
        return {"silent_neighbour_detections": len(monitor.detections),
                "silent_neighbour_withdrawals": len(monitor.withdrawn),
                "silence_detected_s": [list(times) for times in monitor.silence_detected_s]}


def _scatter_rows(rows: np.ndarray, team: np.ndarray) -> np.ndarray:
    """(M, 3) rows of the team's robots as (N, 3), zero for the dropped ones."""
    out = np.zeros((len(team), rows.shape[1]))
    out[team] = rows
    return out


def _team_rows(estimate, team: np.ndarray):
    """The team's robots' rows of every robot's estimate (a SubspaceEstimate of N rows)."""
    return dataclasses.replace(estimate, **{f.name: getattr(estimate, f.name)[team]
                                            for f in dataclasses.fields(estimate)})


def _scatter_square(weights: np.ndarray, team: np.ndarray) -> np.ndarray:
    """(M, M) weights among the team as (N, N), zero for the dropped robots' links."""
    out = np.zeros((len(team), len(team)))
    out[np.ix_(team, team)] = weights
    return out
