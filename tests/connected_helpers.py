"""Shared by the connected-strategy tests: run a scenario tick by tick and check
the continuous-connectivity paper's invariants on every control tick, independently of the strategy's
own bookkeeping (recomputed from the references the quadrotors received)."""

from __future__ import annotations

import numpy as np

from controllers.connectivity.connected_params import ConnectedParams
from controllers.connectivity.graph import connectivity_state
from controllers.connectivity.roles import Role
from sim.geometry import point_clearance
from sim.loop import Simulation
from tether.runner import build_simulation


# R_s of the presets' built-in scenes (their sensing.comm_range_m).
PRESET_RANGES_M = {"office": 2.5, "outdoor": 6.0, "ground": 0.2}


def preset_params(preset: str = "office", **overrides) -> ConnectedParams:
    """A preset's parameters as a run in its scenes uses them (R_s = its comm range)."""
    return ConnectedParams(preset=preset, **overrides).at_range(PRESET_RANGES_M[preset])


class InvariantLog:
    """Per-tick checks: lambda2 > lambda2_min, virtual points farther than R_c
    apart and than R_o from obstacles, at most one prime traveler."""

    def __init__(self, sim: Simulation):
        self.sim = sim
        self.params = sim.strategy.params
        self.boxes = sim.world.obstacles
        self.ticks = 0
        self.lambda2_min = np.inf
        self.robot_distance_min = np.inf
        self.obstacle_distance_min = np.inf
        self.primes_max = 0

    def check(self, frame) -> None:
        q = frame.commands.position  # the virtual points q_i the quadrotors track
        c = self.params
        lambda2 = connectivity_state(q, self.boxes, c).lambda2
        distance = np.linalg.norm(q[:, None] - q[None], axis=-1)[np.triu_indices(len(q), 1)].min()
        clearance = point_clearance(self.boxes, q).min()
        primes = int(np.sum(frame.commands.decorations.robot_scalars["role"] == Role.PRIME_TRAVELER))
        t = frame.observation.time_s
        assert lambda2 > c.lambda2_min + 1e-9, f"t = {t:.2f} s: lambda2 = {lambda2} <= {c.lambda2_min}"
        assert distance > c.min_robot_distance_m, f"t = {t:.2f} s: virtual points {distance:.3f} m apart"
        assert clearance > c.min_obstacle_clearance_m, \
            f"t = {t:.2f} s: virtual point {clearance:.3f} m from an obstacle"
        assert primes <= 1, f"t = {t:.2f} s: {primes} prime travelers"
        self.ticks += 1
        self.lambda2_min = min(self.lambda2_min, lambda2)
        self.robot_distance_min = min(self.robot_distance_min, distance)
        self.obstacle_distance_min = min(self.obstacle_distance_min, clearance)
        self.primes_max = max(self.primes_max, primes)


def run_checked(scenario, duration_s: float | None = None) -> tuple[Simulation, InvariantLog]:
    """Tick ``scenario`` for ``duration_s`` (default: its own) or until the strategy
    finishes, checking the invariants and that the physics stays healthy."""
    sim = build_simulation(scenario)
    log = InvariantLog(sim)
    ticks = int(round((duration_s or scenario.duration_s) / sim.dt))
    for _ in range(ticks):
        frame, healthy = sim.tick()
        assert healthy, f"physics diverged at t = {sim.time_s:.2f} s"
        log.check(frame)
        if sim.strategy.finished:
            break
    return sim, log


def grown_positions(rng: np.random.Generator, n: int, min_robot_distance: float) -> np.ndarray:
    """(n, 3) random team: each robot placed 0.9-2.2 m from an earlier one,
    never closer than 1.05 R_c to any (connected in the office preset)."""
    positions = [np.zeros(3)]
    while len(positions) < n:
        direction = rng.normal(size=3)
        candidate = positions[rng.integers(len(positions))] + rng.uniform(0.9, 2.2) * direction / np.linalg.norm(
            direction
        )
        if min(np.linalg.norm(candidate - p) for p in positions) > 1.05 * min_robot_distance:
            positions.append(candidate)
    return np.array(positions)
