"""Static obstacle geometry as oriented boxes: pure numpy, no MuJoCo.

The world builder extracts every static collision geom of a scene into a
:class:`Boxes` set once; controllers and planners then ask clearance questions
of it without touching the simulator. Distances are in metres, world frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Golden-section iterations for the convex 1-D search along a segment; 40 steps
# shrink the bracket by 0.618**40 ~ 4e-9 of the segment length.
_GOLDEN_STEPS = 40
_INV_PHI = (np.sqrt(5.0) - 1.0) / 2.0
# A segment crossing a box has a plateau of zeros that the search may only
# approach to within its bracket; anything closer than this is contact.
CONTACT_TOLERANCE_M = 1e-7


@dataclass(frozen=True)
class Boxes:
    """Oriented boxes.

    centers: (K, 3) box centres, m, world frame.
    half_sizes: (K, 3) half extents along the box axes, m.
    rotations: (K, 3, 3) box-to-world rotation matrices (columns are box axes).
    """

    centers: np.ndarray
    half_sizes: np.ndarray
    rotations: np.ndarray

    def __post_init__(self) -> None:
        k = len(self.centers)
        assert self.centers.shape == (k, 3), self.centers.shape
        assert self.half_sizes.shape == (k, 3), self.half_sizes.shape
        assert self.rotations.shape == (k, 3, 3), self.rotations.shape

    @staticmethod
    def axis_aligned(centers, half_sizes) -> "Boxes":
        centers = np.asarray(centers, dtype=float).reshape(-1, 3)
        half_sizes = np.asarray(half_sizes, dtype=float).reshape(-1, 3)
        rotations = np.broadcast_to(np.eye(3), (len(centers), 3, 3)).copy()
        return Boxes(centers, half_sizes, rotations)

    def __len__(self) -> int:
        return len(self.centers)

    def to_local(self, points: np.ndarray) -> np.ndarray:
        """Points (P, 3) -> (P, K, 3) coordinates in each box frame."""
        rel = points[:, None, :] - self.centers[None, :, :]
        return np.einsum("pki,kij->pkj", rel, self.rotations)

    def point_distances(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance (P, K) from each point to each box (0 inside) and the
        closest box point (P, K, 3) in world frame."""
        local = self.to_local(points)
        closest_local = np.clip(local, -self.half_sizes, self.half_sizes)
        dist = np.linalg.norm(local - closest_local, axis=-1)
        closest = np.einsum("kij,pkj->pki", self.rotations, closest_local) + self.centers
        return dist, closest


def point_clearance(boxes: Boxes, points: np.ndarray) -> np.ndarray:
    """Distance (P,) from each point (P, 3) to the nearest box; inf if no boxes."""
    points = np.atleast_2d(points)
    if len(boxes) == 0:
        return np.full(len(points), np.inf)
    dist, _ = boxes.point_distances(points)
    return dist.min(axis=1)


def inside_any(boxes: Boxes, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Boolean (P,): point lies inside (or within ``margin`` of) some box."""
    return point_clearance(boxes, points) <= margin


@dataclass(frozen=True)
class SegmentClearance:
    """Clearance of segments a + s (b - a), s in [0, 1], from a box set.

    distance: (P,) minimum distance to any box, m (0 if the segment hits one).
    s: (P,) segment parameter of the closest point.
    witness: (P, 3) closest obstacle point, world frame.
    """

    distance: np.ndarray
    s: np.ndarray
    witness: np.ndarray

    def gradients(self, a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """d distance / d a and d distance / d b, each (P, 3).

        Envelope theorem: at the optimum only the explicit dependence of the
        segment point on its endpoints matters. Zero where the distance is 0.
        """
        point = a + self.s[:, None] * (b - a)
        diff = point - self.witness
        with np.errstate(invalid="ignore", divide="ignore"):
            unit = np.where(self.distance[:, None] > 0, diff / self.distance[:, None], 0.0)
        return (1.0 - self.s)[:, None] * unit, self.s[:, None] * unit


def segment_clearance(boxes: Boxes, a: np.ndarray, b: np.ndarray) -> SegmentClearance:
    """Minimum distance from each segment [a_p, b_p] to all boxes.

    The distance from a point to a convex box is convex, so along a segment it
    is a convex function of s; a vectorised golden-section search finds its
    minimum for every (segment, box) pair at once.
    """
    a = np.atleast_2d(np.asarray(a, dtype=float))
    b = np.atleast_2d(np.asarray(b, dtype=float))
    n = len(a)
    if len(boxes) == 0 or n == 0:
        return SegmentClearance(np.full(n, np.inf), np.zeros(n), np.full((n, 3), np.nan))
    k = len(boxes)
    # Work in each box frame: (P, K, 3).
    la = boxes.to_local(a)
    lb = boxes.to_local(b)
    half = boxes.half_sizes[None]

    def dist_at(s: np.ndarray) -> np.ndarray:
        p = la + s[..., None] * (lb - la)
        return np.linalg.norm(p - np.clip(p, -half, half), axis=-1)

    lo = np.zeros((n, k))
    hi = np.ones((n, k))
    x1 = hi - _INV_PHI * (hi - lo)
    x2 = lo + _INV_PHI * (hi - lo)
    f1, f2 = dist_at(x1), dist_at(x2)
    for _ in range(_GOLDEN_STEPS):
        left = f1 <= f2  # minimum lies in [lo, x2]
        hi = np.where(left, x2, hi)
        lo = np.where(left, lo, x1)
        x2n = np.where(left, x1, lo + _INV_PHI * (hi - lo))
        x1n = np.where(left, hi - _INV_PHI * (hi - lo), x2)
        x1, x2 = x1n, x2n
        f_new = dist_at(np.where(left, x1, x2))
        f1, f2 = np.where(left, f_new, f2), np.where(left, f1, f_new)
    s = 0.5 * (lo + hi)
    # The endpoints themselves may be the minimisers (golden section never
    # evaluates exactly there).
    candidates = np.stack([s, np.zeros_like(s), np.ones_like(s)])
    values = dist_at(candidates)
    pick = values.argmin(axis=0)
    s = np.take_along_axis(candidates, pick[None], 0)[0]
    dist = np.take_along_axis(values, pick[None], 0)[0]
    dist[dist < CONTACT_TOLERANCE_M] = 0.0

    best_box = dist.argmin(axis=1)
    rows = np.arange(n)
    s_best = s[rows, best_box]
    d_best = dist[rows, best_box]
    p_local = la[rows, best_box] + s_best[:, None] * (lb[rows, best_box] - la[rows, best_box])
    w_local = np.clip(p_local, -boxes.half_sizes[best_box], boxes.half_sizes[best_box])
    witness = np.einsum("pij,pj->pi", boxes.rotations[best_box], w_local) + boxes.centers[best_box]
    return SegmentClearance(d_best, s_best, witness)


def segments_free(boxes: Boxes, a: np.ndarray, b: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Boolean (P,): segment keeps more than ``margin`` from every box."""
    return segment_clearance(boxes, a, b).distance > margin
