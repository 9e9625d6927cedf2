"""Sensor-based weighted graph, lambda2 and its gradient (seed 001, Appendix A).

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

import functools
from dataclasses import dataclass

import numpy as np

from controllers.connectivity.params import ConnectivityParams
from controllers.connectivity.potential import guarded_potential_slope
from sim.geometry import Boxes, bounding_box_gaps, segment_clearance


def half_cosine_rise(x, start: float, end: float) -> tuple[np.ndarray, np.ndarray]:
    """Smooth step from 0 (x <= start) to 1 (x >= end) and its slope d/dx (1 / unit of x)."""
    x = np.asarray(x, dtype=float)
    span = end - start
    s = np.clip((x - start) / span, 0.0, 1.0)
    value = 0.5 * (1.0 - np.cos(np.pi * s))
    slope = np.where((s > 0) & (s < 1), 0.5 * np.pi / span * np.sin(np.pi * s), 0.0)
    return value, slope


def _scatter_add(index: np.ndarray, values: np.ndarray, n: int) -> np.ndarray:
    """Sum rows of values (P, ...) into (n, ...) by index (P,). Each output
    entry is summed in row order (np.bincount), whatever the trailing shape."""
    trailing = values.shape[1:]
    width = int(np.prod(trailing))
    flat = values.reshape(len(index), width)
    bins = (index[:, None] * width + np.arange(width)).ravel()
    return np.bincount(bins, flat.ravel(), minlength=n * width).reshape((n, *trailing))


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
    """

    pairs: np.ndarray
    weights: np.ndarray
    link_factor: np.ndarray
    link_factor_grad_first: np.ndarray
    link_factor_grad_second: np.ndarray
    collision_factor: np.ndarray
    collision_log_slope: np.ndarray
    unit: np.ndarray

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
        first, second = self.pairs.T
        squared_gap = (vectors[first] - vectors[second]) ** 2  # (P, M)
        collision_pair = self.collision_factor[first] * self.collision_factor[second]
        # Through alpha and beta: only the two ends of a link move its weight.
        coefficient = (squared_gap * collision_pair[:, None])[:, :, None]
        gradient = _scatter_add(first, coefficient * self.link_factor_grad_first[:, None, :], n)
        gradient += _scatter_add(second, coefficient * self.link_factor_grad_second[:, None, :], n)
        # Through the collision factors: robot i moves every link of i and of
        # each robot within R'_c of it.
        pair_weight = (self.link_factor * collision_pair)[:, None]
        node_sum = _scatter_add(first, pair_weight * squared_gap, n) + _scatter_add(second, pair_weight * squared_gap, n)
        push = (self.collision_log_slope[:, None] * (node_sum[first] + node_sum[second]))[:, :, None] * self.unit[:, None, :]
        gradient += _scatter_add(first, push, n) - _scatter_add(second, push, n)
        return np.moveaxis(gradient, 1, 0)


def _pairwise(positions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    offsets = positions[:, None, :] - positions[None, :, :]
    return offsets, np.linalg.norm(offsets, axis=-1)


def _boxes_subset(boxes: Boxes, mask: np.ndarray) -> Boxes:
    return Boxes(boxes.centers[mask], boxes.half_sizes[mask], boxes.rotations[mask])


def _line_of_sight_factor(
    boxes: Boxes | None, start: np.ndarray, end: np.ndarray, params: ConnectivityParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """beta(d_ijo) (P,) and its gradients w.r.t. the segment ends (P, 3) each."""
    count = len(start)
    value = np.ones(count)
    grad_start = np.zeros((count, 3))
    grad_end = np.zeros((count, 3))
    if boxes is None or len(boxes) == 0 or count == 0:
        return value, grad_start, grad_end
    # Cheap lower bound on each segment/box distance (gap between their
    # world-frame bounding boxes): a pair whose bound reaches R'_o has
    # beta = 1 and needs no exact clearance query.
    near = bounding_box_gaps(boxes, start, end) < params.full_weight_obstacle_clearance
    near_pairs = near.any(axis=1)
    if not near_pairs.any():
        return value, grad_start, grad_end
    subset = _boxes_subset(boxes, near.any(axis=0))
    a, b = start[near_pairs], end[near_pairs]
    clearance = segment_clearance(subset, a, b)
    factor, slope = half_cosine_rise(
        clearance.distance, params.min_obstacle_clearance, params.full_weight_obstacle_clearance
    )
    d_a, d_b = clearance.gradients(a, b)
    value[near_pairs] = factor
    grad_start[near_pairs] = slope[:, None] * d_a
    grad_end[near_pairs] = slope[:, None] * d_b
    return value, grad_start, grad_end


def link_weights(positions: np.ndarray, boxes: Boxes | None, params: ConnectivityParams) -> LinkWeights:
    """Weights W_ij(q) of Appendix A for all robots, with their derivative data."""
    positions = np.asarray(positions, dtype=float)
    n = len(positions)
    if positions.shape != (n, 3) or n < 2:
        raise ValueError(f"positions must have shape (N, 3) with N >= 2, got {positions.shape}")
    offsets, distances = _pairwise(positions)

    # Inter-robot factor delta(d_ik) for all pairs; the diagonal is not a pair.
    delta, delta_slope = half_cosine_rise(distances, params.min_robot_distance, params.full_weight_robot_distance)
    np.fill_diagonal(delta, 1.0)
    collision_factor = delta.prod(axis=1)

    first, second = np.triu_indices(n, k=1)
    in_range = distances[first, second] < params.sensing_range
    first, second = first[in_range], second[in_range]
    pair_distance = distances[first, second]
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = np.where(pair_distance[:, None] > 0, offsets[first, second] / pair_distance[:, None], 0.0)

    rise, rise_slope = half_cosine_rise(pair_distance, params.full_weight_range, params.sensing_range)
    range_factor, range_slope = 1.0 - rise, -rise_slope
    sight_factor, sight_grad_first, sight_grad_second = _line_of_sight_factor(
        boxes, positions[first], positions[second], params
    )
    link_factor = range_factor * sight_factor
    range_grad = range_slope[:, None] * unit  # d alpha / d q_i; d alpha / d q_j is its negative
    grad_first = range_grad * sight_factor[:, None] + range_factor[:, None] * sight_grad_first
    grad_second = -range_grad * sight_factor[:, None] + range_factor[:, None] * sight_grad_second

    pair_delta = delta[first, second]
    with np.errstate(invalid="ignore", divide="ignore"):
        # delta' / delta is finite wherever delta > 0; where delta = 0, c_i = 0
        # and delta' = 0, so every term it would multiply vanishes.
        log_slope = np.where(pair_delta > 0, delta_slope[first, second] / pair_delta, 0.0)

    weights = np.zeros((n, n))
    pair_weight = link_factor * collision_factor[first] * collision_factor[second]
    weights[first, second] = pair_weight
    weights[second, first] = pair_weight
    return LinkWeights(
        pairs=np.stack([first, second], axis=1),
        weights=weights,
        link_factor=link_factor,
        link_factor_grad_first=grad_first,
        link_factor_grad_second=grad_second,
        collision_factor=collision_factor,
        collision_log_slope=log_slope,
        unit=unit,
    )


def weighted_laplacian(weights: np.ndarray) -> np.ndarray:
    """L = diag(sum_j W_ij) - W."""
    return np.diag(weights.sum(axis=1)) - weights


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


def connectivity_state(positions: np.ndarray, boxes: Boxes | None, params: ConnectivityParams) -> ConnectivityState:
    """Weights, Laplacian and its eigendecomposition (one eigh); lambda2, the
    Fiedler vector and dlambda2/dq derive from them when read."""
    links = link_weights(positions, boxes, params)
    laplacian = weighted_laplacian(links.weights)
    eigenvalues, eigenvectors = np.linalg.eigh(laplacian)
    return ConnectivityState(links, laplacian, eigenvalues, eigenvectors)


def generalized_connectivity_force(
    links: LinkWeights, lambda2, fiedler: np.ndarray, params: ConnectivityParams
) -> np.ndarray:
    """f_lambda_i = -dV/dlambda2 * dlambda2/dq_i (eq. 16), (N, 3), N.

    ``lambda2`` is a scalar (exact value) or (N,) (each robot's own estimate);
    ``fiedler`` is the (N,) unit-norm eigenvector or its estimate.
    """
    n = links.num_robots
    slope = np.broadcast_to(guarded_potential_slope(lambda2, params), (n,))
    return -slope[:, None] * links.lambda2_gradient(fiedler)
