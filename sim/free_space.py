"""Free space of a floor plan: where a point, a start or a route fits among obstacles.

Used by the application's placement (a scenario moved into another scene) and
by the strategies that adapt their own coordinates to the new scene (waypoint
routes), so it lives below both. A floor plan is anything with ``obstacles``
(:class:`sim.geometry.Boxes`) and ``bounds`` ((2, 3) min, max corner, m).
Nothing here is random: candidates are tried in a fixed order.
"""

from __future__ import annotations

from typing import Protocol, Sequence

import numpy as np

from sim.geometry import Boxes, point_clearance, segment_clearance

# A ground robot's footprint is checked this far above its clearance (so the
# floor itself does not count as an obstacle near it), m.
GROUND_PROBE_LIFT_M = 0.01
# Candidate points lie on a grid this fine (at least), m; coarser in large
# scenes so a search stays within ~40,000 candidates.
CANDIDATE_STEP_M = 0.05
MAX_CANDIDATES_PER_AXIS = 200


class FloorPlan(Protocol):
    obstacles: Boxes
    bounds: np.ndarray  # (2, 3): min, max corner, m


def candidate_grid(plan: FloorPlan) -> np.ndarray:
    """(K, 2) x, y candidates over the floor plan, CANDIDATE_STEP_M apart (coarser in large scenes)."""
    lo, hi = plan.bounds
    step = max(CANDIDATE_STEP_M, float((hi - lo)[:2].max()) / MAX_CANDIDATES_PER_AXIS)
    xs = np.arange(lo[0], hi[0] + 1e-9, step)
    ys = np.arange(lo[1], hi[1] + 1e-9, step)
    return np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)


def scale_plan(points: np.ndarray, old_bounds: np.ndarray, new_bounds: np.ndarray) -> np.ndarray:
    """``points`` with x, y mapped from one floor plan's box onto the other's (z unchanged)."""
    out = np.array(points, dtype=float)
    size = np.maximum(old_bounds[1, :2] - old_bounds[0, :2], 1e-9)
    out[:, :2] = new_bounds[0, :2] + (out[:, :2] - old_bounds[0, :2]) / size * (new_bounds[1, :2] - new_bounds[0, :2])
    return out


def nearest_free(plan: FloorPlan, grid: np.ndarray, point: np.ndarray, clearance: float, lift_ground: bool,
                 away_from: Sequence[np.ndarray] = (), separation: float = 0.0) -> np.ndarray | None:
    """The grid point (at ``point``'s height, kept inside the bounds' height) nearest ``point`` that is
    ``clearance`` from obstacles and the bounds and ``separation`` from every point of ``away_from``."""
    lo, hi = plan.bounds
    z = lo[2] + clearance + GROUND_PROBE_LIFT_M if lift_ground else float(np.clip(point[2], lo[2] + clearance,
                                                                                 hi[2] - clearance))
    inside = np.all((grid >= lo[:2] + clearance) & (grid <= hi[:2] - clearance), axis=1)
    for other in away_from:
        inside &= np.linalg.norm(grid - other[:2], axis=1) >= separation
    candidates = grid[inside]
    if not len(candidates):
        return None
    order = np.lexsort((candidates[:, 1], candidates[:, 0], np.linalg.norm(candidates - point[:2], axis=1).round(9)))
    for start in range(0, len(order), 512):  # nearest first, a block at a time
        block = candidates[order[start:start + 512]]
        probe = np.column_stack([block, np.full(len(block), z)])
        free = np.flatnonzero(point_clearance(plan.obstacles, probe) >= clearance)
        if len(free):
            x, y = block[free[0]]
            return np.array([x, y, point[2] if lift_ground else z])
    return None


def route_is_clear(plan: FloorPlan, loop: np.ndarray, clearance: float, ground: bool) -> bool:
    """Every leg of the closed loop through ``loop`` (K, 3) keeps ``clearance`` from obstacles."""
    probe = np.array(loop, dtype=float)
    if ground:  # the floor is not an obstacle to a ground robot
        probe[:, 2] = plan.bounds[0, 2] + clearance + GROUND_PROBE_LIFT_M
    closed = np.vstack([probe, probe[:1]])
    return bool(np.all(segment_clearance(plan.obstacles, closed[:-1], closed[1:]).distance >= clearance))
