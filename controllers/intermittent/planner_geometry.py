"""Geometric predicates of the intermittent-connectivity planner (Khodayi-mehr et al. 2019).

Pure numpy (and compiled kernels) over :class:`sim.geometry.Boxes`; no MuJoCo. Ground robots live in
the plane; their sensors and radios sit at a fixed height ``z`` above the
floor, so every 2D robot position is lifted to ``(x, y, z)`` before it is
tested against the 3D obstacle boxes. Distances in metres, world frame.

- :func:`lift` - (..., 2) plane positions -> (..., 3) at height z.
- :func:`points_free` - sample validity: inside the workspace bounds shrunk by
  the robot radius and farther than the radius from every box.
- :func:`edges_free` - CollisionFree of Algorithm 1 for straight robot moves:
  a certificate from the clearances of the endpoints and the midpoint first,
  the exact :func:`sim.geometry.segments_free` for the rest (same answer,
  fewer calls).
- :func:`segments_blocked` - exact line-of-sight test (slab method) used for
  the many predicted range readings; equal to ``~segments_free(..., 0)`` up to
  segments that graze a box face, which both treat as blocked.
- :func:`communication_graph` / :func:`algebraic_connectivity` - the team
  graph of goal condition (6)(i): an edge for every pair within range R whose
  straight link keeps line of sight, and lambda_2 of its Laplacian;
  :func:`is_connected` answers lambda_2 > 0 by reachability.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from sim.compiled import kernel
from sim.geometry import Boxes, clearance_at, segments_free

from controllers.intermittent.planner_kernels import segments_hit_boxes


def lift(points: np.ndarray, z: float) -> np.ndarray:
    """(..., 2) plane positions, m -> (..., 3) with the third coordinate ``z``, m."""
    points = np.asarray(points, dtype=float)
    height = np.full(points.shape[:-1] + (1,), float(z))
    return np.concatenate([points, height], axis=-1)


def points_free(
    boxes: Boxes, bounds: np.ndarray, points: np.ndarray, z: float, margin: float
) -> np.ndarray:
    """Boolean (P,): plane points (P, 2) lie in the workspace and clear of obstacles.

    bounds: (2, 2) [[x_min, y_min], [x_max, y_max]], m. A point must lie at
    least ``margin`` inside the bounds and farther than ``margin`` from every
    box (at height ``z``).
    """
    points = np.ascontiguousarray(np.atleast_2d(points), dtype=np.float64)
    assert points.ndim == 2 and points.shape[1] == 2, points.shape
    lo, hi = bounds[0] + margin, bounds[1] - margin
    free = np.empty(len(points), dtype=bool)
    _points_free_kernel(points, float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1]), float(z), float(margin),
                        boxes.centers, boxes.half_sizes, np.ascontiguousarray(boxes.rotations), boxes.aligned, free)
    return free


@kernel
def _points_free_kernel(points, lo_x, lo_y, hi_x, hi_y, z, margin, centers, half_sizes, rotations, aligned, free):
    for p in range(points.shape[0]):
        x, y = points[p, 0], points[p, 1]
        free[p] = (x >= lo_x and y >= lo_y and x <= hi_x and y <= hi_y
                   and clearance_at(x, y, z, centers, half_sizes, rotations, aligned) > margin)


def edges_free(boxes: Boxes, a: np.ndarray, b: np.ndarray, z: float, margin: float) -> np.ndarray:
    """Boolean (P,): the straight moves a_p -> b_p (plane, (P, 2)) keep more
    than ``margin`` from every box.

    A point closer than c - margin to a point of clearance c keeps more than
    ``margin``: the balls of radius c - margin around the two endpoints and
    the midpoint certify the segment when they cover it (each half covered
    when its two radii sum to more than half the length); the others go to
    the exact :func:`sim.geometry.segments_free` (same answer, fewer calls).
    Workspace bounds are not checked here: they are convex, so endpoints
    inside suffice.
    """
    a = np.ascontiguousarray(np.atleast_2d(a), dtype=np.float64)
    b = np.ascontiguousarray(np.atleast_2d(b), dtype=np.float64)
    n = len(a)
    if len(boxes) == 0 or n == 0:
        return np.ones(n, dtype=bool)
    free = np.empty(n, dtype=bool)
    _edges_certified(a, b, float(z), float(margin), boxes.centers, boxes.half_sizes,
                     np.ascontiguousarray(boxes.rotations), boxes.aligned, free)
    rest = ~free
    if rest.any():
        free[rest] = segments_free(boxes, lift(a[rest], z), lift(b[rest], z), margin)
    return free


@kernel
def _edges_certified(a, b, z, margin, centers, half_sizes, rotations, aligned, free):
    """The ball certificate of :func:`edges_free` per move (False: not certified, test exactly)."""
    for p in range(a.shape[0]):
        ax, ay, bx, by = a[p, 0], a[p, 1], b[p, 0], b[p, 1]
        dx, dy = bx - ax, by - ay
        half = 0.5 * np.sqrt(dx * dx + dy * dy)
        r_a = clearance_at(ax, ay, z, centers, half_sizes, rotations, aligned) - margin
        r_mid = clearance_at(0.5 * (ax + bx), 0.5 * (ay + by), z, centers, half_sizes, rotations, aligned) - margin
        r_b = clearance_at(bx, by, z, centers, half_sizes, rotations, aligned) - margin
        # min(r, r_mid) > 0 written as two tests: a NaN fails them as it fails numpy's minimum.
        free[p] = r_mid > half or (r_a > 0 and r_mid > 0 and r_b > 0
                                   and r_a + r_mid > half and r_b + r_mid > half)


def segments_blocked(boxes: Boxes, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Boolean (P,): the segment [a_p, b_p] (3D, (P, 3)) meets a (closed) box.

    Slab method in every box frame (:func:`planner_kernels.segment_hits_box`):
    the segment parameter interval inside each pair of parallel faces is
    intersected over the three axes and with [0, 1].
    """
    a = np.ascontiguousarray(np.atleast_2d(np.asarray(a, dtype=float)))
    b = np.ascontiguousarray(np.atleast_2d(np.asarray(b, dtype=float)))
    if len(boxes) == 0 or len(a) == 0:
        return np.zeros(len(a), dtype=bool)
    return segments_hit_boxes(a, b, boxes.centers, boxes.half_sizes, boxes.rotations, boxes.aligned)


def communication_graph(
    boxes: Boxes, positions: np.ndarray, z: float, comm_range: float
) -> np.ndarray:
    """Adjacency (n, n) bool of robots at plane ``positions`` (n, 2): a link
    for every pair at most ``comm_range`` apart (m) with line of sight."""
    positions = np.asarray(positions, dtype=float)
    n = len(positions)
    adjacency = np.zeros((n, n), dtype=bool)
    i, j = _pairs(n)
    close = np.linalg.norm(positions[i] - positions[j], axis=1) <= comm_range
    i, j = i[close], j[close]
    if len(i):
        # Line of sight: the exact slab test, equal to segments_free(..., 0.0) (tested) and cheaper.
        sight = ~segments_blocked(boxes, lift(positions[i], z), lift(positions[j], z))
        adjacency[i[sight], j[sight]] = True
        adjacency[j[sight], i[sight]] = True
    return adjacency


@lru_cache(maxsize=None)
def _pairs(n: int) -> tuple[np.ndarray, np.ndarray]:
    """Index pairs i < j of n robots (cached: the planner asks once per node)."""
    return np.triu_indices(n, k=1)


def is_connected(adjacency: np.ndarray) -> bool:
    """True when the graph is connected (a single robot is): the same answer
    as algebraic_connectivity > CONNECTIVITY_TOL for these unweighted graphs,
    whose lambda_2 is either ~0 or >= 4 / n^2, without an eigensolver."""
    n = len(adjacency)
    reached = np.zeros(n, dtype=bool)
    reached[0] = True
    for _ in range(n - 1):
        grown = reached | adjacency[reached].any(axis=0)
        if np.array_equal(grown, reached):
            break
        reached = grown
    return bool(reached.all())


def algebraic_connectivity(adjacency: np.ndarray) -> float:
    """lambda_2 of the graph Laplacian L = D - A; +inf for a single robot
    (a one-node graph is connected), 0 for a disconnected graph."""
    adjacency = np.asarray(adjacency, dtype=float)
    n = len(adjacency)
    if n < 2:
        return float("inf")
    laplacian = np.diag(adjacency.sum(axis=1)) - adjacency
    return float(np.linalg.eigvalsh(laplacian)[1])
