"""Sensor-based weighted graph, lambda2 and its gradient (Nestmeyer et al. 2017, Appendix A).

All robots at once: positions are (N, 3), m, world frame. Obstacles are a
:class:`sim.geometry.Boxes` set (or None for empty space).

Link weight
-----------
    W_ij = alpha(d_ij) * beta(d_ijo) * c_i * c_j,    c_i = prod_{k != i} delta(d_ik)

- alpha: range factor, 1 up to R'_s, fading to 0 at R_s (condition (a));
- beta:  line-of-sight factor of the clearance d_ijo of the segment q_i -> q_j
         from the obstacles (sim.geometry.segment_clearance), 0 up to R_o,
         rising to 1 at R'_o (condition (b));
- delta: inter-robot factor, 0 up to R_c, rising to 1 at R'_c. Condition (c)
         zeroes W_ij as soon as *any* robot k comes within R_c of i (or of j),
         so c_i, the "collision factor" of robot i, multiplies all its links:
         a robot about to collide drops out of the graph, lambda2 falls to
         lambda2_min and the potential pushes the robots apart.

Each factor is a half-cosine step, 0.5 (1 - cos(pi s)), the shape the paper
uses for its traveling efficiency (eq. 9): C1 (slope zero at both ends) and
exactly 0 / 1 outside its transition band.

Gradient of lambda2
-------------------
For a simple lambda2 with unit eigenvector v, dlambda2 = v^T dL v =
sum_{i<j} dW_ij (v_i - v_j)^2. When W_ij depends on q_i and q_j only this is
eq. (17), dlambda2/dq_i = sum_j dW_ij/dq_i (v_i - v_j)^2. Condition (c) makes
W_jk depend on q_i too (through c_j whenever d_ij < R'_c), which adds

    sum_{m : R_c < d_im < R'_c} (delta'/delta)(d_im) (P_i + P_m) (q_i - q_m) / d_im,
    P_m = sum_j W_mj (v_m - v_j)^2,

where P_m is a scalar robot m computes from its own links and sends to its
neighbours (two-hop information for robot i).

Deviations from the paper
-------------------------
- The paper fixes only the zero sets and smoothness of the weight factors;
  the half-cosine shape and the product form c_i c_j of condition (c) are our
  choice (each inter-robot distance d_ij thus enters W_ij twice, once through
  c_i and once through c_j; this changes only the fade shape).
- The gradient includes the condition-(c) terms above, which eq. (17) omits;
  without them the force is not the gradient of V(lambda2) and the passivity
  argument of Robuffo Giordano et al. (2013) does not apply.
- The collision factor counts every robot within R'_c, whether or not it is in
  line of sight (a robot that close is assumed detectable by proximity sensing).
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass

import numpy as np

try:  # numpy's own LAPACK gufunc behind np.linalg.eigh (a private module: a later numpy may move it)
    from numpy.linalg._umath_linalg import eigh_lo as _eigh_lo
except ImportError:  # then the public function, the same LAPACK routine with its checks
    _eigh_lo = None

from controllers.connectivity.connected_params import ConnectedParams
from controllers.connectivity.potential import guarded_potential_slope
from sim.compiled import kernel
from sim.geometry import CONTACT_TOLERANCE_M, Boxes, segment_box_distance_into, world_half_extents


def half_cosine_rise(x, start: float, end: float) -> tuple[np.ndarray, np.ndarray]:
    """Smooth step from 0 (x <= start) to 1 (x >= end) and its slope d/dx (1 / unit of x)."""
    x = np.asarray(x, dtype=float)
    flat = np.ascontiguousarray(x).reshape(-1)
    value, slope = np.empty(len(flat)), np.empty(len(flat))
    _half_cosine_rise_array(flat, float(start), float(end), value, slope)
    return value.reshape(x.shape), slope.reshape(x.shape)


@kernel
def _half_cosine_rise(x, start, end):
    """half_cosine_rise of one value: (value, slope)."""
    span = end - start
    s = min(max((x - start) / span, 0.0), 1.0)
    value = 0.5 * (1.0 - np.cos(np.pi * s))
    slope = 0.5 * np.pi / span * np.sin(np.pi * s) if 0.0 < s < 1.0 else 0.0
    return value, slope


@kernel
def _half_cosine_rise_array(x, start, end, value, slope):
    for k in range(x.shape[0]):
        value[k], slope[k] = _half_cosine_rise(x[k], start, end)


@dataclass(frozen=True)
class LinkWeights:
    """Weights W(q) and what their derivatives need, over candidate pairs.

    pairs: (P, 2) robot indices i < j with d_ij < R_s (the only pairs whose
        weight or weight derivative can be non-zero).
    weights: (N, N) symmetric W, zero diagonal, in [0, 1].
    link_factor: (P,) alpha(d_ij) beta(d_ijo).
    link_factor_grad_first, link_factor_grad_second: (P, 3) d(alpha beta)/dq_i
        and d(alpha beta)/dq_j, 1/m (beta through d_ijo by the envelope theorem).
    collision_factor: (N,) c_i = prod_{k != i} delta(d_ik).
    collision_log_slope: (P,) delta'(d_ij) / delta(d_ij), 1/m (0 outside (R_c, R'_c)).
    unit: (P, 3) (q_i - q_j) / d_ij.
    bystander_robot, bystander_log_slope, bystander_unit: (B,), (B,), (B, 3): for
        each robot i near a bystander b (a body counted by condition (c) but
        not a vertex of the graph, e.g. a robot the team dropped), i,
        delta'(d_ib) / delta(d_ib) and (q_i - q_b) / d_ib; empty without
        bystanders.
    """

    pairs: np.ndarray
    weights: np.ndarray
    link_factor: np.ndarray
    link_factor_grad_first: np.ndarray
    link_factor_grad_second: np.ndarray
    collision_factor: np.ndarray
    collision_log_slope: np.ndarray
    unit: np.ndarray
    bystander_robot: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    bystander_log_slope: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))
    bystander_unit: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))

    @property
    def num_robots(self) -> int:
        return len(self.weights)

    @property
    def edges(self) -> np.ndarray:
        """(E, 2) pairs i < j with W_ij > 0 (the links of the graph G^lambda)."""
        first, second = self.pairs.T
        return self.pairs[self.weights[first, second] > 0]

    def restricted_to(self, adjacency: np.ndarray) -> "LinkWeights":
        """The same robots with only the links in ``adjacency`` (N, N, bool):
        the weights W o A and their derivative data, A held fixed.

        The collision factors still count every robot within R'_c (condition
        (c) is about proximity, not messages), so lambda2_gradient of the
        result is d lambda2(W o A) / dq.
        """
        adjacency = np.asarray(adjacency, dtype=bool)
        n = self.num_robots
        if adjacency.shape != (n, n):
            raise ValueError(f"adjacency must have shape ({n}, {n}), got {adjacency.shape}")
        first, second = self.pairs.T
        kept = adjacency[first, second] & adjacency[second, first]
        return LinkWeights(
            pairs=self.pairs,
            weights=self.weights * (adjacency & adjacency.T),
            link_factor=self.link_factor * kept,
            link_factor_grad_first=self.link_factor_grad_first * kept[:, None],
            link_factor_grad_second=self.link_factor_grad_second * kept[:, None],
            collision_factor=self.collision_factor,
            collision_log_slope=self.collision_log_slope,
            unit=self.unit,
            bystander_robot=self.bystander_robot,
            bystander_log_slope=self.bystander_log_slope,
            bystander_unit=self.bystander_unit,
        )

    def lambda2_gradient(self, vector: np.ndarray) -> np.ndarray:
        """sum_{i<j} dW_ij/dq (v_i - v_j)^2 for v = ``vector`` (N,): (N, 3), 1/m.

        With the unit-norm Fiedler vector of L(W) this is dlambda2/dq exactly;
        with an estimated vector it is what each robot computes from its
        neighbours' estimates.
        """
        n = self.num_robots
        vector = np.asarray(vector, dtype=float)
        if vector.shape != (n,):
            raise ValueError(f"vector must have shape ({n},), got {vector.shape}")
        return self.lambda2_gradients(vector[:, None])[0]

    def lambda2_gradients(self, vectors: np.ndarray) -> np.ndarray:
        """:meth:`lambda2_gradient` of every column of ``vectors`` (N, M) at
        once: (M, N, 3), each equal to the single-vector result bit for bit."""
        n = self.num_robots
        vectors = np.asarray(vectors, dtype=float)
        if vectors.ndim != 2 or len(vectors) != n:
            raise ValueError(f"vectors must have shape ({n}, M), got {vectors.shape}")
        gradients = np.empty((vectors.shape[1], n, 3))
        _lambda2_gradients_kernel(self.pairs, np.ascontiguousarray(vectors), self.collision_factor, self.link_factor,
                                  self.link_factor_grad_first, self.link_factor_grad_second,
                                  self.collision_log_slope, self.unit, self.bystander_robot,
                                  self.bystander_log_slope, self.bystander_unit, gradients)
        return gradients


@kernel
def _lambda2_gradients_kernel(pairs, vectors, collision_factor, link_factor, grad_first, grad_second, log_slope,
                              unit, bystander_robot, bystander_log_slope, bystander_unit, out):
    """out[m] = sum_{i<j} dW_ij/dq (v_i - v_j)^2 for v = vectors[:, m]; (M, N, 3).

    Each robot's sums run over the pairs in order, the two ends' sums kept
    apart and added at the end, as the numpy scatter-add (np.bincount) did."""
    n_pairs, n_modes, n = pairs.shape[0], vectors.shape[1], vectors.shape[0]
    through_first = np.zeros((n_modes, n, 3))
    through_second = np.zeros((n_modes, n, 3))
    node_first = np.zeros((n_modes, n))
    node_second = np.zeros((n_modes, n))
    for p in range(n_pairs):
        i, j = pairs[p, 0], pairs[p, 1]
        collision_pair = collision_factor[i] * collision_factor[j]
        pair_weight = link_factor[p] * collision_pair
        for m in range(n_modes):
            squared_gap = (vectors[i, m] - vectors[j, m]) ** 2
            # Through alpha and beta: only the two ends of a link move its weight.
            coefficient = squared_gap * collision_pair
            for k in range(3):
                through_first[m, i, k] += coefficient * grad_first[p, k]
                through_second[m, j, k] += coefficient * grad_second[p, k]
            node_first[m, i] += pair_weight * squared_gap
            node_second[m, j] += pair_weight * squared_gap
    # Through the collision factors: robot i moves every link of i and of
    # each robot within R'_c of it.
    push_first = np.zeros((n_modes, n, 3))
    push_second = np.zeros((n_modes, n, 3))
    for p in range(n_pairs):
        i, j = pairs[p, 0], pairs[p, 1]
        for m in range(n_modes):
            node_sum = (node_first[m, i] + node_second[m, i]) + (node_first[m, j] + node_second[m, j])
            push = log_slope[p] * node_sum
            for k in range(3):
                push_first[m, i, k] += push * unit[p, k]
                push_second[m, j, k] += push * unit[p, k]
    # A bystander b moves only c_i of the robots i near it (it has no links of its own).
    for b in range(bystander_robot.shape[0]):
        i = bystander_robot[b]
        for m in range(n_modes):
            push = bystander_log_slope[b] * (node_first[m, i] + node_second[m, i])
            for k in range(3):
                push_first[m, i, k] += push * bystander_unit[b, k]
    for m in range(n_modes):
        for r in range(n):
            for k in range(3):
                out[m, r, k] = (through_first[m, r, k] + through_second[m, r, k]) + (
                    push_first[m, r, k] - push_second[m, r, k])


@kernel
def _line_of_sight(a, b, centers, half_sizes, rotations, box_low, box_high, aligned, r_o, r_o_full, grad_a, grad_b,
                   la, lb, point, seg, knots):
    """beta(d_ijo) of the segment [a, b] (3,) and its gradients (written to grad_a, grad_b).

    Only boxes whose world bounding box is within R'_o of the segment's are
    measured (a cheap lower bound of their distance): beyond it beta = 1.
    la, lb, point, seg (3,) and knots (8,) are scratch (no allocation a call); box_low and
    box_high (K, 3) are centers -/+ the world half extents."""
    a_low0, a_low1, a_low2 = min(a[0], b[0]), min(a[1], b[1]), min(a[2], b[2])
    a_high0, a_high1, a_high2 = max(a[0], b[0]), max(a[1], b[1]), max(a[2], b[2])
    best_distance, best_s, best_box = np.inf, 0.0, -1
    for k in range(centers.shape[0]):
        # (the segment's and the box's world bounding boxes: the same values as computed in place)
        excess = max(a_low0 - box_high[k, 0], 0.0) + max(box_low[k, 0] - a_high0, 0.0)
        gap = 0.0 + excess * excess
        excess = max(a_low1 - box_high[k, 1], 0.0) + max(box_low[k, 1] - a_high1, 0.0)
        gap += excess * excess
        excess = max(a_low2 - box_high[k, 2], 0.0) + max(box_low[k, 2] - a_high2, 0.0)
        gap += excess * excess
        gap = np.sqrt(gap)
        if not gap < r_o_full:
            continue
        if gap > best_distance + 1e-9:
            # The bounding boxes' gap is a lower bound of this box's distance: beyond the best
            # box's (more than rounding), the strict comparison below would not pick it.
            continue
        for j in range(3):
            if aligned:
                la[j] = a[j] - centers[k, j]
                lb[j] = b[j] - centers[k, j]
            else:
                la[j] = ((a[0] - centers[k, 0]) * rotations[k, 0, j] + (a[1] - centers[k, 1]) * rotations[k, 1, j]
                         + (a[2] - centers[k, 2]) * rotations[k, 2, j])
                lb[j] = ((b[0] - centers[k, 0]) * rotations[k, 0, j] + (b[1] - centers[k, 1]) * rotations[k, 1, j]
                         + (b[2] - centers[k, 2]) * rotations[k, 2, j])
        s, distance = segment_box_distance_into(la, lb, half_sizes[k], seg, knots)
        if distance < CONTACT_TOLERANCE_M:
            distance = 0.0
        if distance < best_distance:
            best_distance, best_s, best_box = distance, s, k
    grad_a[:] = 0.0
    grad_b[:] = 0.0
    if best_box < 0:
        return 1.0
    factor, slope = _half_cosine_rise(best_distance, r_o, r_o_full)
    # d clearance / d a = (1 - s) u and / d b = s u, u the unit vector from the witness
    # (closest box point) to the segment point (envelope theorem); zero in contact.
    k = best_box
    for j in range(3):
        point[j] = a[j] + best_s * (b[j] - a[j])
        la[j] = point[j] - centers[k, j]
    for j in range(3):
        if aligned:
            witness = min(max(la[j], -half_sizes[k, j]), half_sizes[k, j]) + centers[k, j]
        else:
            witness = centers[k, j]
            for m in range(3):
                local = la[0] * rotations[k, 0, m] + la[1] * rotations[k, 1, m] + la[2] * rotations[k, 2, m]
                witness += rotations[k, j, m] * min(max(local, -half_sizes[k, m]), half_sizes[k, m])
        unit = (point[j] - witness) / best_distance if best_distance > 0 else 0.0
        grad_a[j] = slope * ((1.0 - best_s) * unit)
        grad_b[j] = slope * (best_s * unit)
    return factor


@kernel
def _link_weights_kernel(positions, r_s_full, r_s, r_c, r_c_full, r_o, r_o_full, centers, half_sizes, rotations,
                         world_half, aligned, pairs, weights, link_factor, grad_first, grad_second,
                         collision_factor, log_slope, unit):
    """Fills the LinkWeights arrays (pairs i < j in row-major order); returns the pair count."""
    n = positions.shape[0]
    distance = np.empty((n, n))
    delta = np.ones((n, n))
    delta_slope = np.zeros((n, n))
    for i in range(n):
        distance[i, i] = 0.0  # the diagonal is not a pair: delta = 1
        for j in range(i + 1, n):
            # (p_j - p_i = -(p_i - p_j) exactly, the same squares: one pass fills both triangles)
            dx = positions[i, 0] - positions[j, 0]
            dy = positions[i, 1] - positions[j, 1]
            dz = positions[i, 2] - positions[j, 2]
            distance[i, j] = distance[j, i] = np.sqrt(dx * dx + dy * dy + dz * dz)
            delta[i, j], delta_slope[i, j] = _half_cosine_rise(distance[i, j], r_c, r_c_full)
            delta[j, i], delta_slope[j, i] = delta[i, j], delta_slope[i, j]
    for i in range(n):
        product = delta[i, 0]
        for j in range(1, n):
            product *= delta[i, j]
        collision_factor[i] = product
    sight_a, sight_b = np.empty(3), np.empty(3)
    la, lb, point, seg, knots = np.empty(3), np.empty(3), np.empty(3), np.empty(3), np.empty(8)
    box_low, box_high = np.empty(centers.shape), np.empty(centers.shape)
    for k in range(centers.shape[0]):
        for m in range(3):
            box_low[k, m] = centers[k, m] - world_half[k, m]
            box_high[k, m] = centers[k, m] + world_half[k, m]
    count = 0
    for i in range(n):
        for j in range(i + 1, n):
            d = distance[i, j]
            if not d < r_s:
                continue
            pairs[count, 0], pairs[count, 1] = i, j
            for m in range(3):
                unit[count, m] = (positions[i, m] - positions[j, m]) / d if d > 0 else 0.0
            rise, rise_slope = _half_cosine_rise(d, r_s_full, r_s)
            range_factor, range_slope = 1.0 - rise, -rise_slope
            if centers.shape[0]:
                sight = _line_of_sight(positions[i], positions[j], centers, half_sizes, rotations, box_low,
                                       box_high, aligned, r_o, r_o_full, sight_a, sight_b, la, lb, point, seg, knots)
            else:
                sight = 1.0
                sight_a[:] = 0.0
                sight_b[:] = 0.0
            link_factor[count] = range_factor * sight
            for m in range(3):
                range_grad = range_slope * unit[count, m]  # d alpha / d q_i; d alpha / d q_j is its negative
                grad_first[count, m] = range_grad * sight + range_factor * sight_a[m]
                grad_second[count, m] = -range_grad * sight + range_factor * sight_b[m]
            # delta' / delta is finite wherever delta > 0; where delta = 0, c_i = 0
            # and delta' = 0, so every term it would multiply vanishes.
            log_slope[count] = delta_slope[i, j] / delta[i, j] if delta[i, j] > 0 else 0.0
            weight = link_factor[count] * collision_factor[i] * collision_factor[j]
            weights[i, j] = weight
            weights[j, i] = weight
            count += 1
    return count


_NO_BOXES = Boxes.axis_aligned(np.zeros((0, 3)), np.zeros((0, 3)))


def link_weights(positions: np.ndarray, boxes: Boxes | None, params: ConnectedParams,
                 bystanders: np.ndarray | None = None) -> LinkWeights:
    """Weights W_ij(q) of Appendix A for all robots, with their derivative data (one compiled pass).

    ``bystanders`` (B, 3), m: bodies that condition (c) counts (a robot within R_c of one drops out of the
    graph, and the gradient pushes it away) but that are not vertices of the graph: robots the team dropped,
    still there to be sensed by proximity."""
    positions = np.ascontiguousarray(positions, dtype=float)
    n = len(positions)
    if positions.shape != (n, 3) or n < 2:
        raise ValueError(f"positions must have shape (N, 3) with N >= 2, got {positions.shape}")
    if bystanders is not None and len(bystanders):
        return _without_bystanders(link_weights(np.concatenate([positions, bystanders]), boxes, params), n)
    boxes = _NO_BOXES if boxes is None else boxes
    most = n * (n - 1) // 2
    pairs = np.empty((most, 2), dtype=np.int64)
    weights = np.zeros((n, n))
    link_factor, log_slope = np.empty(most), np.empty(most)
    grad_first, grad_second, unit = np.empty((most, 3)), np.empty((most, 3)), np.empty((most, 3))
    collision_factor = np.empty(n)
    p = params
    count = _link_weights_kernel(
        positions, p.full_weight_range_m, p.sensing_range_m, p.min_robot_distance_m, p.full_weight_robot_distance_m,
        p.min_obstacle_clearance_m, p.full_weight_obstacle_clearance_m, boxes.centers, boxes.half_sizes,
        np.ascontiguousarray(boxes.rotations), world_half_extents(boxes), boxes.aligned,
        pairs, weights, link_factor, grad_first, grad_second, collision_factor, log_slope, unit,
    )
    return LinkWeights(
        pairs=pairs[:count],
        weights=weights,
        link_factor=link_factor[:count],
        link_factor_grad_first=grad_first[:count],
        link_factor_grad_second=grad_second[:count],
        collision_factor=collision_factor,
        collision_log_slope=log_slope[:count],
        unit=unit[:count],
    )


def _without_bystanders(links: LinkWeights, n: int) -> LinkWeights:
    """The first ``n`` robots' graph from ``links`` over them and the bystanders after them: their links and
    collision factors (which count the bystanders), and each (robot, bystander) pair's collision slope."""
    first, second = links.pairs.T
    team = second < n  # (first < second)
    near = (first < n) & ~team
    return LinkWeights(
        pairs=links.pairs[team],
        weights=np.ascontiguousarray(links.weights[:n, :n]),
        link_factor=links.link_factor[team],
        link_factor_grad_first=links.link_factor_grad_first[team],
        link_factor_grad_second=links.link_factor_grad_second[team],
        collision_factor=links.collision_factor[:n].copy(),
        collision_log_slope=links.collision_log_slope[team],
        unit=links.unit[team],
        bystander_robot=np.ascontiguousarray(first[near]),
        bystander_log_slope=links.collision_log_slope[near],
        bystander_unit=links.unit[near],
    )


def weighted_laplacian(weights: np.ndarray) -> np.ndarray:
    """L = diag(sum_j W_ij) - W."""
    laplacian = np.diag(weights.sum(axis=1))
    np.subtract(laplacian, weights, out=laplacian)  # (one array fewer than ``diag - W``; the same values)
    return laplacian


def _symmetric_eigh(matrix: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """np.linalg.eigh of a real symmetric (N, N) float matrix (its lower triangle), through the same
    LAPACK gufunc without the wrapper's checks and casts; LinAlgError
    when it does not converge (NaN eigenvalues), as np.linalg.eigh raises."""
    if _eigh_lo is None:
        return np.linalg.eigh(matrix)
    eigenvalues, eigenvectors = _eigh_lo(matrix, signature="d->dd")
    if np.isnan(eigenvalues[0]):
        raise np.linalg.LinAlgError("Eigenvalues did not converge")
    return eigenvalues, eigenvectors


def _fiedler_sign(vector: np.ndarray) -> np.ndarray:
    """The eigenvector with its largest-magnitude entry positive."""
    return -vector if vector[np.argmax(np.abs(vector))] < 0 else vector


def fiedler_pair(laplacian: np.ndarray) -> tuple[float, np.ndarray]:
    """lambda2 and its unit eigenvector (sign: largest-magnitude entry positive)."""
    eigenvalues, eigenvectors = np.linalg.eigh(laplacian)
    return float(eigenvalues[1]), _fiedler_sign(eigenvectors[:, 1])


@dataclass(frozen=True)
class ConnectivityState:
    """Exact (centralised) connectivity of the team at one instant.

    links: the weights and their derivative data.
    laplacian: (N, N) weighted Laplacian.
    eigenvalues: (N,) its spectrum, ascending; eigenvectors: (N, N) as columns.
    lambda2: second-smallest eigenvalue of the Laplacian (weight units).
    fiedler: (N,) its unit-norm eigenvector (largest-magnitude entry positive).
    lambda2_gradient: (N, 3) dlambda2/dq_i, 1/m (computed on first use).
    """

    links: LinkWeights
    laplacian: np.ndarray
    eigenvalues: np.ndarray
    eigenvectors: np.ndarray

    @property
    def lambda2(self) -> float:
        return float(self.eigenvalues[1])

    @functools.cached_property
    def fiedler(self) -> np.ndarray:
        return _fiedler_sign(self.eigenvectors[:, 1])

    @functools.cached_property
    def lambda2_gradient(self) -> np.ndarray:
        return self.links.lambda2_gradient(self.fiedler)

    @property
    def weights(self) -> np.ndarray:
        return self.links.weights

    @property
    def edges(self) -> np.ndarray:
        return self.links.edges


def connectivity_state(positions: np.ndarray, boxes: Boxes | None, params: ConnectedParams,
                       bystanders: np.ndarray | None = None) -> ConnectivityState:
    """Weights, Laplacian and its eigendecomposition (one eigh); lambda2, the
    Fiedler vector and dlambda2/dq derive from them when read (``bystanders``: link_weights)."""
    links = link_weights(positions, boxes, params, bystanders)
    laplacian = weighted_laplacian(links.weights)
    eigenvalues, eigenvectors = _symmetric_eigh(laplacian)
    return ConnectivityState(links, laplacian, eigenvalues, eigenvectors)


def generalized_connectivity_force(
    links: LinkWeights, lambda2, fiedler: np.ndarray, params: ConnectedParams
) -> np.ndarray:
    """f_lambda_i = -dV/dlambda2 * dlambda2/dq_i (eq. 16), (N, 3), N.

    ``lambda2`` is a scalar (exact value) or (N,) (each robot's own estimate);
    ``fiedler`` is the (N,) unit-norm eigenvector or its estimate.
    """
    n = links.num_robots
    slope = np.broadcast_to(guarded_potential_slope(lambda2, params), (n,))
    return -slope[:, None] * links.lambda2_gradient(fiedler)
