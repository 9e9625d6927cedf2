"""Static obstacle geometry as oriented boxes: pure math (numpy and compiled
kernels), no MuJoCo.

The world builder extracts every static collision geom of a scene into a
:class:`Boxes` set once; controllers and planners then ask clearance questions
of it without touching the simulator. Distances are in metres, world frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.compiled import kernel

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
    points = np.ascontiguousarray(np.atleast_2d(points), dtype=float)
    if len(boxes) == 0:
        return np.full(len(points), np.inf)
    clearance = np.empty(len(points))
    _point_clearance_kernel(points, boxes.centers, boxes.half_sizes, np.ascontiguousarray(boxes.rotations),
                            boxes.aligned, clearance)
    return clearance


@kernel
def _point_clearance_kernel(points, centers, half_sizes, rotations, aligned, out):
    for p in range(points.shape[0]):
        out[p] = clearance_at(points[p, 0], points[p, 1], points[p, 2], centers, half_sizes, rotations, aligned)


@kernel
def clearance_at(x, y, z, centers, half_sizes, rotations, aligned):
    """Distance from the point (x, y, z) to the nearest of the boxes (inf if none); for other kernels."""
    # Distance to a box = norm of how far each local coordinate exceeds the half extent.
    smallest = np.inf
    for k in range(centers.shape[0]):
        dx, dy, dz = x - centers[k, 0], y - centers[k, 1], z - centers[k, 2]
        if aligned:
            local0, local1, local2 = dx, dy, dz
        else:
            local0 = (dx * rotations[k, 0, 0] + dy * rotations[k, 1, 0]) + dz * rotations[k, 2, 0]
            local1 = (dx * rotations[k, 0, 1] + dy * rotations[k, 1, 1]) + dz * rotations[k, 2, 1]
            local2 = (dx * rotations[k, 0, 2] + dy * rotations[k, 1, 2]) + dz * rotations[k, 2, 2]
        excess0 = max(abs(local0) - half_sizes[k, 0], 0.0)
        excess1 = max(abs(local1) - half_sizes[k, 1], 0.0)
        excess2 = max(abs(local2) - half_sizes[k, 2], 0.0)
        # Summed (x^2 + z^2) + y^2, numpy einsum's order: the trajectories' round-off depends on it.
        squared = (excess0 * excess0 + excess2 * excess2) + excess1 * excess1
        smallest = min(smallest, squared)
    return np.sqrt(smallest)


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

    Exact (piecewise-quadratic minimisation per box, see
    :func:`segment_box_distance`), one compiled loop over segments and boxes.
    """
    a = np.ascontiguousarray(np.atleast_2d(np.asarray(a, dtype=float)))
    b = np.ascontiguousarray(np.atleast_2d(np.asarray(b, dtype=float)))
    n = len(a)
    if len(boxes) == 0 or n == 0:
        return SegmentClearance(np.full(n, np.inf), np.zeros(n), np.full((n, 3), np.nan))
    distance, s, witness = np.empty(n), np.empty(n), np.empty((n, 3))
    _segment_clearance_kernel(a, b, boxes.centers, boxes.half_sizes, np.ascontiguousarray(boxes.rotations),
                              world_half_extents(boxes), boxes.aligned, distance, s, witness)
    return SegmentClearance(distance, s, witness)


def world_half_extents(boxes: Boxes) -> np.ndarray:
    """(K, 3) half extents of each box's world-frame bounding box."""
    if boxes.aligned:
        return np.ascontiguousarray(boxes.half_sizes, dtype=float)
    return np.einsum("kij,kj->ki", np.abs(boxes.rotations), boxes.half_sizes)


@kernel
def segment_box_distance(la, lb, half):
    """Exact distance from the segment [la, lb] (3,) to the centred box with
    half extents ``half`` (3,), all in the box frame; returns (s*, distance).

    Along p(s) = la + s d each axis is below, inside or above its slab, with
    switches at most at 6 values of s. Between switches the squared distance
    is a convex quadratic sum_i (alpha_i + beta_i s)^2, minimised in closed
    form and clamped to the interval; the best interval wins (the first one
    on ties).
    """
    return segment_box_distance_into(la, lb, half, np.empty(3), np.empty(8))


@kernel
def segment_box_distance_into(la, lb, half, d, knots):
    """:func:`segment_box_distance` with caller-owned scratch arrays ``d`` (3,)
    and ``knots`` (8,) (no allocation a call; the same values)."""
    for i in range(3):
        d[i] = lb[i] - la[i]
    knots[0], knots[7] = 0.0, 1.0
    for i in range(3):
        below_at, above_at = (-half[i] - la[i]) / d[i], (half[i] - la[i]) / d[i]  # +-inf / NaN if d_i = 0
        knots[1 + i] = min(max(below_at, 0.0), 1.0) if np.isfinite(below_at) else 0.0
        knots[4 + i] = min(max(above_at, 0.0), 1.0) if np.isfinite(above_at) else 0.0
    # knots.sort() as numba sorts 8 floats (an insertion sort; no NaN here), without the
    # partition stack its quicksort allocates each call.
    for m in range(1, 8):
        value = knots[m]
        j = m
        while j > 0 and value < knots[j - 1]:
            knots[j] = knots[j - 1]
            j -= 1
        knots[j] = value
    best_s, best_distance = 0.0, np.inf
    for m in range(7):
        start, end = knots[m], knots[m + 1]
        mid = 0.5 * (start + end)
        bb = 0.0
        ab = 0.0
        for i in range(3):
            # excess_i(s) = alpha_i + beta_i s on the outside axes, 0 inside (at the interval's middle).
            p_mid = la[i] + mid * d[i]
            if p_mid > half[i]:
                alpha, beta = la[i] - half[i], d[i]
            elif p_mid < -half[i]:
                alpha, beta = -half[i] - la[i], -d[i]
            else:
                alpha, beta = 0.0, 0.0
            bb += beta * beta
            ab += alpha * beta
        s_star = -ab / bb if bb > 0 else mid
        s_star = min(max(s_star, start), end)
        # The true distance (not the interval's quadratic) at the candidate.
        squared = 0.0
        for i in range(3):
            p = la[i] + s_star * d[i]
            excess = p - min(max(p, -half[i]), half[i])
            squared += excess * excess
        distance = np.sqrt(squared)
        if distance < best_distance:
            best_s, best_distance = s_star, distance
    return best_s, best_distance


@kernel
def _segment_clearance_kernel(a, b, centers, half_sizes, rotations, world_half, aligned, distance_out, s_out,
                              witness_out):
    n_boxes = centers.shape[0]
    la = np.empty(3)
    lb = np.empty(3)
    point = np.empty(3)
    d, knots = np.empty(3), np.empty(8)  # segment_box_distance_into's scratch
    for p in range(a.shape[0]):
        # Upper bound of the clearance: that of the segment's ends and middle.
        bound = np.inf
        for t in (0.0, 0.5, 1.0):
            for j in range(3):
                point[j] = a[p, j] + t * (b[p, j] - a[p, j])
            for k in range(n_boxes):
                squared = 0.0
                for j in range(3):
                    if aligned:
                        local = point[j] - centers[k, j]
                    else:
                        local = ((point[0] - centers[k, 0]) * rotations[k, 0, j] + (point[1] - centers[k, 1])
                                 * rotations[k, 1, j]) + (point[2] - centers[k, 2]) * rotations[k, 2, j]
                    excess = max(abs(local) - half_sizes[k, j], 0.0)
                    squared += excess * excess
                bound = min(bound, np.sqrt(squared))
        best_distance, best_s, best_box = np.inf, 0.0, 0
        for k in range(n_boxes):
            # Skip a box whose world bounding box is farther than the bound or the best box
            # so far (a lower bound of its distance): it cannot hold the minimum.
            gap = 0.0
            for i in range(3):
                low = min(a[p, i], b[p, i]) - (centers[k, i] + world_half[k, i])
                high = (centers[k, i] - world_half[k, i]) - max(a[p, i], b[p, i])
                excess = max(low, 0.0) + max(high, 0.0)
                gap += excess * excess
            if np.sqrt(gap) > min(bound + 1e-12, best_distance):
                continue
            for j in range(3):
                if aligned:
                    la[j] = a[p, j] - centers[k, j]
                    lb[j] = b[p, j] - centers[k, j]
                else:
                    la[j] = ((a[p, 0] - centers[k, 0]) * rotations[k, 0, j] + (a[p, 1] - centers[k, 1])
                             * rotations[k, 1, j]) + (a[p, 2] - centers[k, 2]) * rotations[k, 2, j]
                    lb[j] = ((b[p, 0] - centers[k, 0]) * rotations[k, 0, j] + (b[p, 1] - centers[k, 1])
                             * rotations[k, 1, j]) + (b[p, 2] - centers[k, 2]) * rotations[k, 2, j]
            s, distance = segment_box_distance_into(la, lb, half_sizes[k], d, knots)
            if distance < CONTACT_TOLERANCE_M:
                distance = 0.0
            if distance < best_distance:
                best_distance, best_s, best_box = distance, s, k
        distance_out[p] = best_distance
        s_out[p] = best_s
        # Witness: the closest point of the best box.
        k = best_box
        for j in range(3):
            la[j] = a[p, j] + best_s * (b[p, j] - a[p, j]) - centers[k, j]  # the segment point, box-centred
        if aligned:
            for j in range(3):
                witness_out[p, j] = min(max(la[j], -half_sizes[k, j]), half_sizes[k, j]) + centers[k, j]
        else:
            for j in range(3):
                local = la[0] * rotations[k, 0, j] + la[1] * rotations[k, 1, j] + la[2] * rotations[k, 2, j]
                lb[j] = min(max(local, -half_sizes[k, j]), half_sizes[k, j])
            for i in range(3):
                witness_out[p, i] = (rotations[k, i, 0] * lb[0] + rotations[k, i, 1] * lb[1]
                                     + rotations[k, i, 2] * lb[2]) + centers[k, i]


def segments_free(boxes: Boxes, a: np.ndarray, b: np.ndarray, margin: float = 0.0) -> np.ndarray:
    """Boolean (P,): segment keeps more than ``margin`` from every box."""
    return segment_clearance(boxes, a, b).distance > margin


def boxes_reaching(boxes: Boxes, height: float) -> Boxes:
    """The boxes whose top lies above ``height`` (m): what a planner working in
    the plane of ground robots' sensors at twice that height must avoid (the
    floor slab and low decorations drop out, or every move would touch them)."""
    # Vertical extent of each oriented box: |R[2, :]| . half_sizes.
    reach = np.einsum("kj,kj->k", np.abs(boxes.rotations[:, 2, :]), boxes.half_sizes)
    keep = boxes.centers[:, 2] + reach > height
    return Boxes(boxes.centers[keep], boxes.half_sizes[keep], boxes.rotations[keep])


def pairwise_min_distance(points: np.ndarray) -> float:
    """Smallest distance between two of ``points`` (N, D), m (inf for N < 2;
    NaN rows are skipped). Per pair sqrt(dx^2 + dy^2 [+ dz^2]) summed in that
    order: the figure numpy's ``norm(diff, axis=-1)`` gives."""
    if len(points) < 2:
        return float("inf")
    return float(_pairwise_min_distance(np.ascontiguousarray(points, dtype=float)))


@kernel
def _pairwise_min_distance(points):
    smallest = np.inf
    for i in range(points.shape[0]):
        for j in range(i + 1, points.shape[0]):
            square = 0.0
            for d in range(points.shape[1]):
                delta = points[i, d] - points[j, d]
                square += delta * delta
            smallest = min(smallest, np.sqrt(square))
    return smallest
