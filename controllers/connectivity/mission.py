"""Set-up and bookkeeping of a continuous-connectivity mission on the simulator.

- :func:`shared_planner`: one :class:`GridPlanner` per scene and planning
  parameters, cached (obstacles are static; building the free-space graph
  costs a fraction of a second).
- :func:`target_queues`: the target generator of Sec. 2.1, fixed lists or
  random free-space targets as in the Monte Carlo trials of Sec. 4.1, drawn
  with the run's generator.
- :func:`check_start`: refuse a starting configuration whose graph G^lambda
  is disconnected (Appendix A: the guarantee needs lambda2(0) > lambda2_min).
- :class:`MissionStatistics`: the seed's figures over a run (Sec. 4.1, Fig. 9
  and Fig. 14) and the invariants (lambda2, distances, prime travelers).

Deviations from the paper
-------------------------
- Random targets: the paper does not say how its targets were drawn. They are
  uniform in the scene bounds within a height band (``target_height_min_m``
  .. ``target_height_max_m``), at least ``target_clearance_m`` from obstacles
  and bound faces, and joined to robot 0's start by a planned path. They are
  drawn before anything else uses the run's generator, so one seed gives the
  same targets whatever the robot count (the paper repeats each target
  configuration for every team size).
- Allocation: the paper gives 3 targets to 5 robots and 2 to 5 more (its
  teams have 10 to 35 robots); here robots 0-4 and 5-9. A team of fewer than
  10 robots gets the first N entries of that pattern.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from controllers.connectivity.connected_params import ConnectedParams
from controllers.connectivity.graph import ConnectivityState
from controllers.connectivity.paths import GridPlanner
from controllers.connectivity.roles import PRIME_CODE
from controllers.connectivity.targets import TargetQueues
from sim.compiled import kernel
from sim.config import ConfigError
from sim.geometry import Boxes, pairwise_min_distance, point_clearance  # noqa: F401  (re-exported)

# lambda2 at or below lambda2_min + this is "disconnected" (eigh round-off is ~1e-16).
LAMBDA2_TOLERANCE = 1e-9
# Paper's allocation for the first ten robots (Sec. 4.1).
PAPER_TARGET_COUNTS = (3, 3, 3, 3, 3, 2, 2, 2, 2, 2)
# Uniform draws per batch and batches before giving up, for random targets.
_SAMPLE_BATCH = 256
_MAX_BATCHES = 400
# Planners kept (one per scene and planning parameters).
_PLANNER_CACHE_SIZE = 4
_planners: dict[tuple, GridPlanner] = {}


def shared_planner(boxes: Boxes, bounds: np.ndarray, params: ConnectedParams) -> GridPlanner:
    """The planner of this scene (boxes, (2, 3) bounds) for these planning parameters."""
    key = (
        boxes.centers.tobytes(), boxes.half_sizes.tobytes(), boxes.rotations.tobytes(),
        np.asarray(bounds, dtype=float).tobytes(),
        params.grid_resolution_m, params.path_clearance_m, params.path_min_clearance_m, params.smoothing_tolerance_m,
    )
    planner = _planners.get(key)
    if planner is None:
        if len(_planners) >= _PLANNER_CACHE_SIZE:
            _planners.pop(next(iter(_planners)))
        planner = GridPlanner.from_params(boxes, bounds[0], bounds[1], params)
        _planners[key] = planner
    return planner


def target_counts(params: ConnectedParams, n_robots: int) -> list[int]:
    """Random targets per robot: ``target_counts`` or the paper's allocation."""
    counts = list(params.target_counts) if params.target_counts else list(PAPER_TARGET_COUNTS[:n_robots])
    if len(counts) > n_robots:
        raise ConfigError("strategy.target_counts", f"lists {len(counts)} robots but the scenario has {n_robots}")
    return counts + [0] * (n_robots - len(counts))


def _random_points(rng: np.random.Generator, planner: GridPlanner, count: int, params: ConnectedParams,
                   reachable_from: np.ndarray) -> np.ndarray:
    lower, upper = planner.lower.copy(), planner.upper.copy()
    lower[2] = max(lower[2], params.target_height_min_m)
    upper[2] = min(upper[2], params.target_height_max_m)
    if np.any(upper < lower):
        raise ConfigError("strategy.target_height_min_m",
                          f"the band [{params.target_height_min_m:g}, {params.target_height_max_m:g}] m misses "
                          f"the scene's heights [{planner.lower[2]:g}, {planner.upper[2]:g}] m")
    chosen: list[np.ndarray] = []
    for _ in range(_MAX_BATCHES):
        if len(chosen) >= count:
            break
        draws = rng.uniform(lower, upper, size=(_SAMPLE_BATCH, 3))
        free = draws[planner.is_free(draws, params.target_clearance_m)]
        chosen.extend(free[planner.connected_to(reachable_from, free)][:count - len(chosen)])
    if len(chosen) < count:
        if planner.coarsened:
            raise ConfigError("scene", f"{planner.coarsening()}: at that spacing only {len(chosen)} of {count} "
                                       "random targets could be joined to robot 0's start; use a smaller scene "
                                       "(its tether_bounds)")
        raise ConfigError("strategy.target_clearance_m",
                          f"found only {len(chosen)} of {count} free targets {params.target_clearance_m:g} m "
                          f"from obstacles in the height band; lower it or the band")
    return np.array(chosen).reshape(count, 3)


def target_queues(params: ConnectedParams, planner: GridPlanner, starts: np.ndarray,
                  rng: np.random.Generator) -> TargetQueues:
    """targetQueue_i of every robot, from the scenario's generator settings."""
    n = len(starts)
    dwell = params.dwell_time_s
    if params.targets == "fixed":
        lists = [np.asarray(route, dtype=float).reshape(-1, 3) for route in params.target_lists]
        if len(lists) > n:
            raise ConfigError("strategy.target_lists", f"lists {len(lists)} robots but the scenario has {n}; give "
                              "one list per robot, or --set strategy.targets=\"random\"")
        lists += [np.zeros((0, 3))] * (n - len(lists))
        # A single-layer grid (ground robots: the sensors' plane) has lower == upper on z: a target is
        # a place in that plane, whatever height the list gives.
        flat = planner.lower == planner.upper
        for robot, points in enumerate(lists):
            points[:, flat] = planner.lower[flat]
            for k, point in enumerate(points):
                inside = np.all((point > planner.lower) | flat) and np.all((point < planner.upper) | flat)
                if not inside or not planner.is_free(point[None], 0.0)[0]:
                    raise ConfigError(f"strategy.target_lists.{robot}.{k}",
                                      f"target {point.tolist()} is inside an obstacle or outside the scene")
                if not planner.connected(starts[robot], point):
                    _refuse_coarse_grid(planner, starts[robot], robot)
                    raise ConfigError(f"strategy.target_lists.{robot}.{k}",
                                      f"target {point.tolist()} cannot be reached from robot {robot}'s start")
        return TargetQueues.from_lists(lists, dwell)
    counts = target_counts(params, n)
    points = _random_points(rng, planner, int(sum(counts)), params, starts[0])
    return TargetQueues.from_lists(np.split(points, np.cumsum(counts)[:-1]), dwell)


def _refuse_coarse_grid(planner: GridPlanner, start: np.ndarray, robot: int) -> None:
    """ConfigError('scene', ...) when a grid coarsened by its cell cap is why ``start`` plans nowhere."""
    if planner.coarsened:
        where = ", ".join(f"{v:g}" for v in np.round(start, 2))
        raise ConfigError("scene", f"{planner.coarsening()}: at that spacing robot {robot}'s start ({where}) is "
                                   "cut off from its targets; use a smaller scene (its tether_bounds)")


def check_start(state: ConnectivityState, positions: np.ndarray, boxes: Boxes, names: tuple[str, ...],
                params: ConnectedParams) -> None:
    """ConfigError('robots', ...) unless lambda2(0) > lambda2_min, naming what breaks the graph."""
    reached = _component(state.weights > 0, 0)
    if state.lambda2 > params.lambda2_min + LAMBDA2_TOLERANCE and reached.all():
        return
    rules = (f"a link needs distance < R_s = {params.sensing_range_m:g} m, line-of-sight clearance > R_o = "
             f"{params.min_obstacle_clearance_m:g} m and no robot within R_c = {params.min_robot_distance_m:g} m "
             f"of either end")
    distance = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    np.fill_diagonal(distance, np.inf)
    i, j = np.unravel_index(np.argmin(distance), distance.shape)
    if distance[i, j] <= params.min_robot_distance_m:
        raise ConfigError("robots", f"the starting graph is disconnected: {names[i]} and {names[j]} start "
                          f"{distance[i, j]:.2f} m apart, within R_c = {params.min_robot_distance_m:g} m ({rules})")
    clearance = point_clearance(boxes, positions)
    k = int(np.argmin(clearance))
    if clearance[k] <= params.min_obstacle_clearance_m:
        raise ConfigError("robots", f"the starting graph is disconnected: {names[k]} starts {clearance[k]:.2f} m "
                          f"from an obstacle, within R_o = {params.min_obstacle_clearance_m:g} m ({rules})")
    cut = [names[r] for r in range(len(names)) if not reached[r]]
    raise ConfigError("robots", f"the starting graph is disconnected (lambda2 = {state.lambda2:.3g} <= lambda2_min "
                      f"= {params.lambda2_min:g}): {', '.join(cut)} cannot reach {names[0]} ({rules})")


def _component(adjacency: np.ndarray, root: int) -> np.ndarray:
    reached = np.zeros(len(adjacency), dtype=bool)
    reached[root] = True
    frontier = reached.copy()
    while frontier.any():
        frontier = adjacency[frontier].any(axis=0) & ~reached
        reached |= frontier
    return reached


@dataclass
class MissionStatistics:
    """The seed's figures and invariants accumulated over the control ticks.

    Positions are the virtual points q_i unless the name says ``body``.
    """

    explorers: np.ndarray  # (E,) indices of robots with at least one target
    targets_total: int
    lambda2_min: float = float("inf")
    lambda2_sum: float = 0.0
    edges_min: int | None = None
    edges_sum: int = 0
    ticks: int = 0
    max_stretch: float = 0.0
    travel: np.ndarray = field(default_factory=lambda: np.zeros(0))
    min_robot_distance: float = float("inf")
    min_obstacle_distance: float = float("inf")
    min_body_distance: float = float("inf")
    min_body_obstacle_distance: float = float("inf")
    prime_max: int = 0
    estimate_error_sum: float = 0.0
    estimate_error_count: int = 0
    elections: int = 0

    def record(self, state: ConnectivityState, q: np.ndarray, q_next: np.ndarray, roles: np.ndarray,
               obstacle_distance: np.ndarray, body: np.ndarray, body_obstacle_distance: np.ndarray,
               robot_distance: float, lambda2_estimate: np.ndarray | None) -> dict[str, float]:
        """Add one tick; returns that tick's values (for the per-tick scalars)."""
        if len(self.travel) != len(q):
            self.travel = np.zeros(len(q))
        edges = int(_link_count(state.links.pairs, state.weights))
        self.ticks += 1
        self.lambda2_min = min(self.lambda2_min, state.lambda2)
        self.lambda2_sum += state.lambda2
        self.edges_min = edges if self.edges_min is None else min(self.edges_min, edges)
        self.edges_sum += edges
        stretch = _stretch_and_travel(q, q_next, self.explorers, self.travel)
        self.max_stretch = max(self.max_stretch, stretch)
        self.min_robot_distance = min(self.min_robot_distance, robot_distance)
        self.min_obstacle_distance = min(self.min_obstacle_distance, float(obstacle_distance.min()))
        self.min_body_distance = min(self.min_body_distance, pairwise_min_distance(body))
        self.min_body_obstacle_distance = min(self.min_body_obstacle_distance, float(body_obstacle_distance.min()))
        primes = int(np.sum(roles == PRIME_CODE))
        self.prime_max = max(self.prime_max, primes)
        tick = {"lambda2": state.lambda2, "edges": float(edges), "stretch_m": stretch, "prime_travelers": float(primes)}
        if lambda2_estimate is not None:
            error = np.abs(lambda2_estimate - state.lambda2)
            error = error[np.isfinite(lambda2_estimate)]  # NaN: a robot dropped from the team has no estimate
            self.estimate_error_sum += float(error.sum())
            self.estimate_error_count += len(error)
            tick["lambda2_estimate_error"] = float(error.mean())
        return tick

    def summary(self) -> dict:
        finite = lambda x: None if not np.isfinite(x) else float(x)  # noqa: E731
        return {
            "lambda2_min": finite(self.lambda2_min),
            "lambda2_mean": self.lambda2_sum / self.ticks if self.ticks else None,
            "edges_min": self.edges_min,
            "edges_mean": self.edges_sum / self.ticks if self.ticks else None,
            "max_stretch_m": self.max_stretch,
            "mean_travel_m": float(self.travel[self.explorers].mean()) if len(self.explorers) and len(self.travel)
            else None,
            "min_robot_distance_m": finite(self.min_robot_distance),
            "min_obstacle_distance_m": finite(self.min_obstacle_distance),
            "min_body_distance_m": finite(self.min_body_distance),
            "min_body_obstacle_distance_m": finite(self.min_body_obstacle_distance),
            "prime_travelers_max": self.prime_max,
            "lambda2_estimate_error_mean": self.estimate_error_sum / self.estimate_error_count
            if self.estimate_error_count else None,
        }


@kernel
def _link_count(pairs, weights):
    """Number of pairs (i, j) in ``pairs`` (P, 2) with W_ij > 0: the edges of G^lambda."""
    count = 0
    for p in range(pairs.shape[0]):
        if weights[pairs[p, 0], pairs[p, 1]] > 0:
            count += 1
    return count


@kernel
def _stretch_and_travel(q, q_next, explorers, travel):
    """The largest distance between two explorers (0 with fewer than two), and each robot's step
    ||q_next - q|| added to ``travel`` (N,); norms summed in np.linalg.norm's order."""
    stretch = 0.0
    if explorers.shape[0] > 1:
        stretch = -np.inf
        for a in range(explorers.shape[0]):
            for b in range(explorers.shape[0]):
                i, j = explorers[a], explorers[b]
                d0, d1, d2 = q[i, 0] - q[j, 0], q[i, 1] - q[j, 1], q[i, 2] - q[j, 2]
                distance = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                if distance > stretch or distance != distance:
                    stretch = distance
    for i in range(q.shape[0]):
        d0, d1, d2 = q_next[i, 0] - q[i, 0], q_next[i, 1] - q[i, 1], q_next[i, 2] - q[i, 2]
        travel[i] += np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    return stretch
