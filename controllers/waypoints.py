"""Waypoint following: each robot loops through its route on minimum-jerk segments.

The foundation's demo strategy (scenario ``hover``). Every segment starts and
ends at rest, so the reference is C2 everywhere (position, velocity and
acceleration continuous) and the low-level controllers get consistent
feed-forward terms. The segment time is chosen so the peak speed equals the
cruise speed: a minimum-jerk profile peaks at 1.875 times its mean speed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.config import require
from sim.types import Commands, Observation, WorldInfo

_MIN_JERK_PEAK_RATIO = 1.875  # peak / mean speed of s(tau) = 10 tau^3 - 15 tau^4 + 6 tau^5
Vec3 = tuple[float, float, float]


@dataclass(frozen=True)
class WaypointParams:
    speed_mps: float = 0.5  # quadrotors' peak speed on each segment, m/s
    ground_speed_mps: float = 0.1  # ground robots' peak speed, m/s (e-puck class: <= 0.15)
    dwell_s: float = 0.5  # rest at each waypoint, s
    routes: tuple[tuple[Vec3, ...], ...] = ()  # one route per robot, robot order; empty = hold start

    def __post_init__(self):
        require(self.speed_mps > 0, "speed_mps", f"must be positive, got {self.speed_mps}")
        require(self.ground_speed_mps > 0, "ground_speed_mps", f"must be positive, got {self.ground_speed_mps}")
        require(self.dwell_s >= 0, "dwell_s", f"must be non-negative, got {self.dwell_s}")


def min_jerk(tau: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """s, ds/dtau, d2s/dtau2 of the minimum-jerk blend for tau in [0, 1]."""
    tau = np.clip(tau, 0.0, 1.0)
    s = tau**3 * (10 - 15 * tau + 6 * tau**2)
    ds = 30 * tau**2 * (1 - tau) ** 2
    dds = 60 * tau * (1 - tau) * (1 - 2 * tau)
    return s, ds, dds


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

    def sample(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if len(self.points) == 1 or self.period == 0:
            return self.points[0], np.zeros(3), np.zeros(3)
        t = t % self.period
        for start, end, duration in zip(self.starts, self.ends, self.durations):
            if t < self.dwell or duration == 0:
                if t < self.dwell + duration:
                    return start, np.zeros(3), np.zeros(3)
                t -= self.dwell + duration
                continue
            t -= self.dwell
            if t < duration:
                s, ds, dds = min_jerk(np.array(t / duration))
                delta = end - start
                return start + s * delta, ds / duration * delta, dds / duration**2 * delta
            t -= duration
        return self.points[0], np.zeros(3), np.zeros(3)


class WaypointStrategy:
    """Loops every robot through [its start, *its route]."""

    def __init__(self, params: WaypointParams):
        self.params = params
        self.routes: list[Route] = []

    def reset(self, world: WorldInfo, initial: Observation, rng: np.random.Generator) -> None:
        n = world.n_robots
        if self.params.routes and len(self.params.routes) != n:
            raise ValueError(f"routes: has {len(self.params.routes)} routes for {n} robots")
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

    def step(self, observation: Observation) -> Commands:
        samples = [route.sample(observation.time_s) for route in self.routes]
        position, velocity, acceleration = (np.array(x) for x in zip(*samples))
        return Commands(position, velocity, acceleration, np.zeros(len(samples)))
