"""Targets of Nestmeyer et al. 2017 (Sec. 2.1): per-robot target queues, dwell times and generators.

Each robot i has a ``targetQueue_i`` filled online by its target generator
with locations z_i^k (m, world frame) and dwell times Delta t_i^k (s). A
target is visited (Problem 1) when the robot stays within R_z of it for
Delta t without interruption; ``DwellClock`` measures that.

Generators: ``TargetQueues.from_lists`` for fixed lists; ``random_target_lists``
for the Monte Carlo trials of Sec. 4.1 (uniform in free space, drawn with the
run's np.random.Generator); ``monte_carlo_target_counts`` gives the paper's
allocation (3 targets for 5 robots, 2 for 5 more, none for the rest).

Deviations from the paper
-------------------------
- The paper does not say how its random targets were drawn. We draw them
  uniformly in the scene bounds, keep those at least ``clearance`` from
  obstacles and bound faces, and (with ``reachable_from``) those the planner
  can reach from that point, so every trial is completable.
- A visit is counted from the moment the robot becomes 'anchor' (the prime
  traveler abdicates only after its election round), and the dwell clock
  restarts if the robot ever leaves the R_z ball.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from controllers.connectivity.paths import GridPlanner
from sim.compiled import kernel

# Uniform draws per batch while rejection-sampling free points.
_SAMPLE_BATCH = 256
# Batches before giving up on finding free, reachable points.
_MAX_BATCHES = 200


@dataclass(frozen=True)
class Target:
    """One target z_i^k of robot ``robot``: position (3,), m; dwell_time, s; index k (0-based)."""

    robot: int
    index: int
    position: np.ndarray
    dwell_time: float


@dataclass(frozen=True)
class Visit:
    """A completed visit: arrival (start of anchoring) and completion times, s."""

    target: Target
    arrival_time: float
    completion_time: float


class TargetQueues:
    """targetQueue_i for every robot; the generator may ``push`` at any time (online targets)."""

    def __init__(self, n_robots: int) -> None:
        self.n_robots = n_robots
        self._queues: list[deque[Target]] = [deque() for _ in range(n_robots)]
        self._issued = np.zeros(n_robots, dtype=int)  # targets ever pushed per robot
        self._sizes = np.zeros(n_robots, dtype=int)  # len of each queue, kept with push and pop (read every tick)

    @staticmethod
    def from_lists(positions: Sequence, dwell_time: float | Sequence = 3.0) -> "TargetQueues":
        """Fixed lists: ``positions[i]`` is an (m_i, 3) array of robot i's targets, m;
        ``dwell_time`` a scalar (s) or per robot a scalar or (m_i,) sequence."""
        queues = TargetQueues(len(positions))
        for robot, points in enumerate(positions):
            points = np.asarray(points, dtype=float).reshape(-1, 3)
            dwell = dwell_time if np.isscalar(dwell_time) else dwell_time[robot]
            dwell = np.broadcast_to(np.asarray(dwell, dtype=float), (len(points),))
            for point, stay in zip(points, dwell):
                queues.push(robot, point, float(stay))
        return queues

    def push(self, robot: int, position, dwell_time: float) -> Target:
        """Append a target to robot ``robot``'s queue; returns it."""
        position = np.asarray(position, dtype=float).reshape(3).copy()
        if not np.all(np.isfinite(position)):
            raise ValueError(f"target position must be finite, got {position}")
        if not (np.isfinite(dwell_time) and dwell_time >= 0):
            raise ValueError(f"dwell_time must be a non-negative finite number of seconds, got {dwell_time!r}")
        position.setflags(write=False)
        target = Target(robot, int(self._issued[robot]), position, float(dwell_time))
        self._issued[robot] += 1
        self._queues[robot].append(target)
        self._sizes[robot] += 1
        return target

    def pop(self, robot: int) -> Target | None:
        """Extract robot ``robot``'s next target (Alg. 1 line 5); None if its queue is empty."""
        if not self._queues[robot]:
            return None
        self._sizes[robot] -= 1
        return self._queues[robot].popleft()

    def pending(self) -> np.ndarray:
        """Boolean (N,): the robot's queue is not empty."""
        return self._sizes > 0

    def __len__(self) -> int:
        return int(self._sizes.sum())


class DwellClock:
    """Continuous time spent within R_z by each robot, s (Problem 1)."""

    def __init__(self, n_robots: int) -> None:
        self._since = np.full(n_robots, np.nan)

    def update(self, time: float, inside) -> None:
        """``inside`` (N,) bool: being timed and within R_z; clocks outside stop and reset."""
        inside = np.asarray(inside, dtype=bool)
        since = np.empty(len(self._since))
        _dwell_update(self._since, inside, float(time), since)
        self._since = since

    def elapsed(self, time: float) -> np.ndarray:
        """Seconds (N,) of the current uninterrupted stay; 0 when not inside."""
        out = np.empty(len(self._since))
        _dwell_elapsed(self._since, float(time), out)
        return out


@kernel
def _dwell_update(since, inside, time, out):
    """DwellClock.update, element by element (one call instead of four numpy ones)."""
    for i in range(since.shape[0]):
        if inside[i]:
            out[i] = time if since[i] != since[i] else since[i]
        else:
            out[i] = np.nan


@kernel
def _dwell_elapsed(since, time, out):
    """DwellClock.elapsed, element by element: time - since where timed, else 0."""
    for i in range(since.shape[0]):
        out[i] = time - since[i] if since[i] == since[i] else 0.0


def monte_carlo_target_counts(n_robots: int) -> list[int]:
    """Targets per robot in the trials of Sec. 4.1: 3 for robots 0-4, 2 for 5-9, 0 after."""
    if n_robots < 10:
        raise ValueError(f"the paper's trials use at least 10 robots, got {n_robots}")
    return [3] * 5 + [2] * 5 + [0] * (n_robots - 10)


def random_free_points(
    rng: np.random.Generator,
    planner: GridPlanner,
    count: int,
    clearance: float | None = None,
    reachable_from=None,
) -> np.ndarray:
    """``count`` points (count, 3), uniform in the scene bounds, farther than
    ``clearance`` (m; default the planner's loosest margin) from obstacles and
    bound faces and, if ``reachable_from`` (3,) is given, joined to it by a path."""
    clearance = planner.margins[-1] if clearance is None else clearance
    chosen: list[np.ndarray] = []
    for _ in range(_MAX_BATCHES):
        if len(chosen) >= count:
            break
        draws = rng.uniform(planner.lower, planner.upper, size=(_SAMPLE_BATCH, 3))
        for point in draws[planner.is_free(draws, clearance)]:
            if reachable_from is None or planner.connected(reachable_from, point):
                chosen.append(point)
                if len(chosen) == count:
                    break
    if len(chosen) < count:
        raise ValueError(f"found only {len(chosen)} of {count} free points with clearance {clearance} m")
    return np.array(chosen).reshape(count, 3)


def random_target_lists(
    rng: np.random.Generator,
    planner: GridPlanner,
    counts: Sequence[int],
    dwell_time: float,
    clearance: float | None = None,
    reachable_from=None,
) -> TargetQueues:
    """Queues with ``counts[i]`` random free targets for robot i (see ``random_free_points``)."""
    points = random_free_points(rng, planner, int(sum(counts)), clearance, reachable_from)
    splits = np.cumsum(counts)[:-1]
    return TargetQueues.from_lists(np.split(points, splits), dwell_time)
