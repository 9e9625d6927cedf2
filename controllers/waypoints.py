"""Waypoint following: each robot loops through its route on minimum-jerk segments.

The foundation's demo strategy (scenario ``hover``). Every segment starts and
ends at rest, so the reference is C2 everywhere (position, velocity and
acceleration continuous) and the low-level controllers get consistent
feed-forward terms. The segment time is chosen so the peak speed equals the
cruise speed: a minimum-jerk profile peaks at 1.875 times its mean speed.

Speeds and dwell can change while it runs (:meth:`WaypointStrategy.update_params`,
used by the tuning page): every robot keeps its place on its route (same
segment, same fraction of it) and goes on at the new pace, so the reference
position stays continuous. New routes restart the strategy from where the
robots are.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.compiled import kernel
from sim.config import ConfigError, check_params, param
from sim.free_space import candidate_grid, nearest_free, route_is_clear, scale_plan
from sim.strategy import Strategy
from sim.types import Commands, Observation, SceneChange, WorldInfo

_MIN_JERK_PEAK_RATIO = 1.875  # peak / mean speed of s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5
Vec3 = tuple[float, float, float]
# Waypoints (and the straight legs between them) keep this clearance from obstacles, m:
# a quadrotor's rotor disc plus margin; a ground robot's radius plus margin.
ROUTE_CLEARANCE_M = {"quadrotor": 0.35, "ground": 0.08}
# A route that crosses an obstacle is replaced by a back-and-forth to a free point at one of
# these distances (the farthest that works) and bearings around the start.
FALLBACK_LEG_M = (1.5, 1.0, 0.6, 0.3)
FALLBACK_BEARINGS = 12


@dataclass(frozen=True)
class WaypointParams:
    speed_mps: float = param(0.5, unit="m/s", min=0.05, max=3.0)  # quadrotors' peak speed on each segment, m/s
    ground_speed_mps: float = param(0.1, unit="m/s", min=0.01, max=0.15)  # ground robots' peak speed, m/s (e-puck)
    dwell_s: float = param(0.5, unit="s", min=0.0, max=10.0, step=0.1)  # rest at each waypoint, s
    routes: tuple[tuple[Vec3, ...], ...] = ()  # one route per robot, robot order; empty = hold start

    def __post_init__(self):
        check_params(self)


@kernel
def _min_jerk(tau, two, three):
    # Exponents arrive as arguments so that libm's pow is called, as Python's ** does: LLVM turns a
    # constant exponent into multiplications, whose last bit can differ from pow's.
    tau = min(max(tau, 0.0), 1.0)
    s = math.pow(tau, three) * (10 - 15 * tau + 6 * math.pow(tau, two))
    ds = 30 * math.pow(tau, two) * math.pow(1 - tau, two)
    dds = 60 * tau * (1 - tau) * (1 - 2 * tau)
    return s, ds, dds


def min_jerk(tau: float) -> tuple[float, float, float]:
    """s, ds/dtau, d2s/dtau2 of the minimum-jerk blend for tau in [0, 1] (clipped there)."""
    return _min_jerk(float(tau), 2.0, 3.0)


class Route:
    """A closed route through ``points`` (K, 3) with per-segment timing."""

    def __init__(self, points: np.ndarray, speed: float, dwell: float):
        self.points = points
        self.starts = points  # segment k runs starts[k] -> ends[k]
        self.ends = np.roll(points, -1, axis=0)
        lengths = np.linalg.norm(self.ends - self.starts, axis=1)
        self.durations = np.where(lengths > 0, _MIN_JERK_PEAK_RATIO * lengths / speed, 0.0)
        self.dwell = dwell
        self.period = float(np.sum(self.durations + dwell))

    def progress(self, t: float) -> float:
        """Where on the route time ``t`` falls: ``2k + f`` while resting at
        waypoint k (f in [0, 1) of the dwell), ``2k + 1 + f`` on segment k."""
        if self.period == 0:
            return 0.0
        t = t % self.period
        for k, duration in enumerate(self.durations):
            if t < self.dwell:
                return 2 * k + t / self.dwell
            t -= self.dwell
            if t < duration:
                return 2 * k + 1 + t / duration
            t -= duration
        return 0.0

    def time_at(self, progress: float) -> float:
        """Inverse of :meth:`progress` within one period, s."""
        k, rest = divmod(progress, 2.0)
        k = min(int(k), len(self.durations) - 1)
        before = float(np.sum(self.durations[:k]) + k * self.dwell)
        if rest < 1.0:
            return before + rest * self.dwell
        return before + self.dwell + (rest - 1.0) * float(self.durations[k])

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration (3,) at route time ``t``."""
        position, velocity, acceleration = RouteTable([self]).sample(np.array([t], dtype=float))
        return position[0], velocity[0], acceleration[0]


class RouteTable:
    """Routes as padded arrays, sampled for all robots in one compiled call."""

    def __init__(self, routes: list[Route]):
        n = len(routes)
        longest = max((len(route.durations) for route in routes), default=0)
        self.starts = np.zeros((n, longest, 3))
        self.deltas = np.zeros((n, longest, 3))  # end - start of each segment
        self.durations = np.zeros((n, longest))
        self.counts = np.array([len(route.durations) for route in routes], dtype=np.int64)
        self.periods = np.array([route.period for route in routes], dtype=float)
        self.dwell = routes[0].dwell if routes else 0.0
        assert all(route.dwell == self.dwell for route in routes)
        for r, route in enumerate(routes):
            k = len(route.durations)
            self.starts[r, :k] = route.starts
            self.deltas[r, :k] = route.ends - route.starts
            self.durations[r, :k] = route.durations

    def sample(self, times: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity, acceleration (N, 3) of every route at its own route time ``times`` (N,), s."""
        n = len(self.counts)
        position, velocity, acceleration = np.empty((n, 3)), np.empty((n, 3)), np.empty((n, 3))
        _sample_routes(np.ascontiguousarray(times, dtype=float), self.starts, self.deltas, self.durations,
                       self.counts, self.periods, self.dwell, 2.0, 3.0, position, velocity, acceleration)
        return position, velocity, acceleration


@kernel
def _sample_routes(times, starts, deltas, durations, counts, periods, dwell, two, three,
                   position, velocity, acceleration):
    """Per route: rest at each waypoint for ``dwell``, then a minimum-jerk segment to the next."""
    for r in range(times.shape[0]):
        for i in range(3):  # at rest at the first waypoint unless a segment below says otherwise
            position[r, i] = starts[r, 0, i]
            velocity[r, i] = acceleration[r, i] = 0.0
        if counts[r] == 1 or periods[r] == 0:
            continue
        t = times[r] % periods[r]
        for k in range(counts[r]):
            duration = durations[r, k]
            if t < dwell or duration == 0:
                if t < dwell + duration:
                    for i in range(3):
                        position[r, i] = starts[r, k, i]
                    break
                t -= dwell + duration
                continue
            t -= dwell
            if t < duration:
                s, ds, dds = _min_jerk(t / duration, two, three)
                v, a = ds / duration, dds / math.pow(duration, two)
                for i in range(3):
                    position[r, i] = starts[r, k, i] + s * deltas[r, k, i]
                    velocity[r, i] = v * deltas[r, k, i]
                    acceleration[r, i] = a * deltas[r, k, i]
                break
            t -= duration


class WaypointStrategy(Strategy):
    """Loops every robot through [its start, *its route]."""

    def __init__(self, params: WaypointParams):
        self.params = params
        self.routes: list[Route] = []
        self._table = RouteTable([])
        self._offsets = np.zeros(0)  # per-robot route clock = sim time - offset, s
        self._time_s = 0.0

    def reset(self, world: WorldInfo, initial: Observation, rng: np.random.Generator) -> None:
        n = world.n_robots
        if self.params.routes and len(self.params.routes) != n:
            raise ConfigError("strategy.routes", f"lists {len(self.params.routes)} routes for {n} robots (one per "
                              "robot, in robot order); after changing the team give one route per robot, or "
                              "--set strategy.routes=[] to hold every start")
        self.routes = []
        self._ground = np.array([k == "ground" for k in world.robot_kinds])
        for i in range(n):
            start = initial.position[i].copy()
            waypoints = [np.array(p, dtype=float) for p in (self.params.routes[i] if self.params.routes else ())]
            if self._ground[i]:
                for p in waypoints:
                    p[2] = start[2]
            speed = self.params.ground_speed_mps if self._ground[i] else self.params.speed_mps
            self.routes.append(Route(np.array([start, *waypoints]), speed, self.params.dwell_s))
        self._table = RouteTable(self.routes)
        self._offsets = np.full(n, initial.time_s)
        self._time_s = initial.time_s

    @classmethod
    def adapt_to_scene(cls, strategy_table: dict, change: SceneChange, keep: frozenset[str]) -> list[str]:
        """Routes scaled from the old floor plan into the new one, each waypoint moved to the
        nearest free spot; a route that would still cross an obstacle becomes a back-and-forth
        between the robot's start and the farthest free point nearby it reaches in a straight line."""
        routes = strategy_table.get("routes")
        if not routes or "strategy.routes" in keep:
            return []
        strategy_table["routes"], replaced = fit_routes(change, routes)
        crossing = f"; {', '.join(change.robot_names[i] for i in replaced)}: route crossed an obstacle, now a " \
                   "back-and-forth to a free point nearby" if replaced else ""
        return [f"strategy.routes: scaled to {change.scene_name}'s floor plan, waypoints moved to free spots{crossing}"]

    def update_params(self, params: WaypointParams) -> bool:
        """Take new speeds and dwell from the next tick on, each robot keeping
        its place on its route. Returns False (asking for a restart from the
        current state) when the routes themselves change."""
        if params.routes != self.params.routes:
            return False
        for i, old in enumerate(self.routes):
            speed = params.ground_speed_mps if self._ground[i] else params.speed_mps
            new = Route(old.points, speed, params.dwell_s)
            place = old.progress(self._time_s - self._offsets[i])
            self._offsets[i] = self._time_s - new.time_at(place)
            self.routes[i] = new
        self._table = RouteTable(self.routes)
        self.params = params
        return True

    def step(self, observation: Observation) -> Commands:
        self._time_s = observation.time_s
        position, velocity, acceleration = self._table.sample(observation.time_s - self._offsets)
        scalars = {}
        if observation.decorations_wanted:
            speed = np.linalg.norm(velocity, axis=1)
            scalars = {"reference_speed_max_mps": float(speed.max(initial=0.0))}
        return Commands(position, velocity, acceleration, np.zeros(len(position)), scalars)


def fit_routes(change: SceneChange, routes: list) -> tuple[list, list[int]]:
    """Waypoint routes moved into the new scene (see :meth:`WaypointStrategy.adapt_to_scene`);
    also the robots whose route became a back-and-forth."""
    grid = candidate_grid(change)
    lo, hi = change.bounds
    out, replaced = [], []
    for i, (kind, start, route) in enumerate(zip(change.robot_kinds, change.starts, routes)):
        clearance, ground = ROUTE_CLEARANCE_M[kind], kind == "ground"
        points = []
        for point in scale_plan(np.array(route, dtype=float).reshape(-1, 3), change.old_bounds, change.bounds):
            spot = nearest_free(change, grid, point, clearance, ground)
            points.append(point if spot is None else spot)
        if points and route_is_clear(change, np.array([start, *points]), clearance, ground):
            out.append([[round(float(v), 3) for v in p] for p in points])
            continue
        replaced.append(i)
        out.append([])  # hold the start if nothing nearby can be reached
        for leg in FALLBACK_LEG_M:
            for k in range(FALLBACK_BEARINGS):
                angle = 2 * np.pi * k / FALLBACK_BEARINGS
                end = start + leg * np.array([np.cos(angle), np.sin(angle), 0.0])
                if np.all(end[:2] >= lo[:2] + clearance) and np.all(end[:2] <= hi[:2] - clearance) \
                        and route_is_clear(change, np.array([start, end]), clearance, ground):
                    out[-1] = [[round(float(v), 3) for v in end]]
                    break
            if out[-1]:
                break
    return out, replaced
