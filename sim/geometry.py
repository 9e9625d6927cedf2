"""Static obstacle geometry as oriented boxes: pure numpy, no MuJoCo.

The world builder extracts every static collision geom of a scene into a
:class:`Boxes` set once; controllers and planners then ask clearance questions
of it without touching the simulator. Distances are in metres, world frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# Round-off below this is contact (a segment grazing or crossing a box).
CONTACT_TOLERANCE_M = 1e-9


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
        # All boxes axis-aligned (the usual scene): frame changes are plain offsets.
        object.__setattr__(self, "aligned", bool(np.array_equal(self.rotations, np.broadcast_to(np.eye(3), (k, 3, 3)))))

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
        if self.aligned:
            return rel
        return np.einsum("pki,kij->pkj", rel, self.rotations)

    def point_distances(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distance (P, K) from each point to each box (0 inside) and the
        closest box point (P, K, 3) in world frame."""
        local = self.to_local(points)
        closest_local = np.clip(local, -self.half_sizes, self.half_sizes)
        dist = np.linalg.norm(local - closest_local, axis=-1)
        if self.aligned:
            closest = closest_local + self.centers
        else:
            closest = np.einsum("kij,pkj->pki", self.rotations, closest_local) + self.centers
        return dist, closest


def point_clearance(boxes: Boxes, points: np.ndarray) -> np.ndarray:
    """Distance (P,) from each point (P, 3) to the nearest box; inf if no boxes."""
    points = np.atleast_2d(points)
    if len(boxes) == 0:
        return np.full(len(points), np.inf)
    # Distance to a box = norm of how far each local coordinate exceeds the half extent
    # (the closest point is not needed here).
    excess = np.abs(boxes.to_local(points)) - boxes.half_sizes
    np.maximum(excess, 0.0, out=excess)
    return np.sqrt(np.einsum("pki,pki->pk", excess, excess).min(axis=1))


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


def bounding_box_gaps(boxes: Boxes, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(S, K) distance between the world-frame bounding boxes of each segment
    [a_s, b_s] and of each box: a cheap lower bound of their clearance."""
    box_half = boxes.half_sizes if boxes.aligned else np.einsum("kij,kj->ki", np.abs(boxes.rotations), boxes.half_sizes)
    low_corner, high_corner = np.minimum(a, b), np.maximum(a, b)
    gap = np.maximum(low_corner[:, None, :] - (boxes.centers + box_half)[None], 0.0)
    gap += np.maximum((boxes.centers - box_half)[None] - high_corner[:, None, :], 0.0)
    return np.sqrt(np.einsum("nki,nki->nk", gap, gap))


def segment_clearance(boxes: Boxes, a: np.ndarray, b: np.ndarray) -> SegmentClearance:
    """Minimum distance from each segment [a_p, b_p] to all boxes.

    Exact (piecewise-quadratic minimisation per box, see
    :func:`_segment_box_distance`), vectorised over all candidate pairs.
    """
    a = np.atleast_2d(np.asarray(a, dtype=float))
    b = np.atleast_2d(np.asarray(b, dtype=float))
    n = len(a)
    if len(boxes) == 0 or n == 0:
        return SegmentClearance(np.full(n, np.inf), np.zeros(n), np.full((n, 3), np.nan))
    k = len(boxes)
    # Prune (segment, box) pairs that cannot hold the minimum: a box whose
    # distance from the segment is certainly above the segment's nearest
    # sampled point's clearance is skipped. Lower bounds: the box's bounding
    # sphere, and the gap between the world-frame bounding boxes of the
    # segment and of the box (tight for axis-aligned walls and slabs).
    upper = point_clearance(boxes, np.concatenate([a, b, 0.5 * (a + b)])).reshape(3, n).min(axis=0)
    radius = np.linalg.norm(boxes.half_sizes, axis=1)
    lower = _point_segment_distance(boxes.centers, a, b) - radius[None, :]
    lower = np.maximum(lower, bounding_box_gaps(boxes, a, b))
    rows, cols = np.nonzero(lower <= upper[:, None] + 1e-12)
    # Work in each candidate box's frame: (C, 3).
    if boxes.aligned:
        la = a[rows] - boxes.centers[cols]
        lb = b[rows] - boxes.centers[cols]
    else:
        rot = boxes.rotations[cols]
        la = np.einsum("ci,cij->cj", a[rows] - boxes.centers[cols], rot)
        lb = np.einsum("ci,cij->cj", b[rows] - boxes.centers[cols], rot)
    half = boxes.half_sizes[cols]

    s_cand, d_cand = _segment_box_distance(la, lb, half)
    d_cand[d_cand < CONTACT_TOLERANCE_M] = 0.0
    dist = np.full((n, k), np.inf)
    s = np.zeros((n, k))
    dist[rows, cols] = d_cand
    s[rows, cols] = s_cand

    best_box = dist.argmin(axis=1)
    segment = np.arange(n)
    s_best = s[segment, best_box]
    d_best = dist[segment, best_box]
    point = a + s_best[:, None] * (b - a)
    # Witness: the closest point of the best box only.
    half = boxes.half_sizes[best_box]
    if boxes.aligned:
        witness = np.clip(point - boxes.centers[best_box], -half, half) + boxes.centers[best_box]
    else:
        rot = boxes.rotations[best_box]
        local = np.clip(np.einsum("ni,nij->nj", point - boxes.centers[best_box], rot), -half, half)
        witness = np.einsum("nij,nj->ni", rot, local) + boxes.centers[best_box]
    return SegmentClearance(d_best, s_best, witness)


def _segment_box_distance(la: np.ndarray, lb: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact distance from segments [la, lb] (C, 3) to centred boxes with half
    extents ``half`` (C, 3), all in box frames; returns (s*, distance), (C,).

    Along p(s) = la + s d each axis is below, inside or above its slab, with
    switches at most at 6 values of s. Between switches the squared distance
    is a convex quadratic sum_i (alpha_i + beta_i s)^2, minimised in closed
    form and clamped to the interval; the best interval wins.
    """
    d = lb - la
    with np.errstate(divide="ignore", invalid="ignore"):
        crossings = np.concatenate([(-half - la) / d, (half - la) / d], axis=1)  # (C, 6)
    crossings = np.where(np.isfinite(crossings), np.clip(crossings, 0.0, 1.0), 0.0)
    knots = np.sort(np.concatenate([np.zeros((len(la), 1)), crossings, np.ones((len(la), 1))], axis=1), axis=1)
    start, end = knots[:, :-1], knots[:, 1:]  # (C, 7) intervals
    mid = 0.5 * (start + end)
    p_mid = la[:, None, :] + mid[..., None] * d[:, None, :]  # (C, 7, 3)
    above = p_mid > half[:, None, :]
    below = p_mid < -half[:, None, :]
    # excess_i(s) = alpha_i + beta_i s on the outside axes, 0 inside.
    alpha = np.where(above, la[:, None, :] - half[:, None, :], np.where(below, -half[:, None, :] - la[:, None, :], 0.0))
    beta = np.where(above, d[:, None, :], np.where(below, -d[:, None, :], 0.0))
    bb = (beta * beta).sum(axis=-1)
    ab = (alpha * beta).sum(axis=-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        s_star = np.where(bb > 0, -ab / bb, mid)
    s_star = np.clip(s_star, start, end)
    # Evaluate the true distance (not the interval's quadratic) at each candidate.
    p = la[:, None, :] + s_star[..., None] * d[:, None, :]
    dist = np.linalg.norm(p - np.clip(p, -half[:, None, :], half[:, None, :]), axis=-1)
    best = dist.argmin(axis=1)
    rows = np.arange(len(la))
    return s_star[rows, best], dist[rows, best]


def _point_segment_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Distance (P, K) from each of K points to each of P segments [a_p, b_p]."""
    ab = b - a
    length2 = np.maximum(np.einsum("pi,pi->p", ab, ab), 1e-300)
    rel = points[None, :, :] - a[:, None, :]
    t = np.clip(np.einsum("pki,pi->pk", rel, ab) / length2[:, None], 0.0, 1.0)
    return np.linalg.norm(rel - t[..., None] * ab[:, None, :], axis=-1)


def segments_free(boxes: Boxes, a: np.ndarray, b: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Boolean (P,): segment keeps more than ``margin`` from every box."""
    return segment_clearance(boxes, a, b).distance > margin
