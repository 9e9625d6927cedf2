"""Compiled kernels of the intermittent paper's planner (numba, cached on disk).

The planner evaluates Algorithm 4 on a few candidate edges at a time, tens of
steps each, with 3x3 covariance blocks per target: numpy's per-call overhead
on such tiny arrays, not arithmetic, was the cost (one ``eigvalsh`` call per
step, ~4,200 a plan). These kernels do the same arithmetic in plain loops:

- :func:`segment_hits_box` - the slab test of one segment against the boxes;
  :func:`controllers.intermittent.planner_geometry.segments_blocked` maps it
  over many segments, and the propagation kernel calls it per reading.
- :func:`max_eigenvalue_sym3` - lambda_max of a symmetric 3x3 matrix by
  Jacobi rotations; equals ``eigvalsh`` to a few ulps of the matrix norm
  (tested).
- :func:`propagate_blocks` - Algorithm 4 over P edges in the block-diagonal
  representation of :mod:`controllers.intermittent.planner_belief`: predicted
  readings (range, sensing limit, line of sight), predict (eq. 8b), the
  sequential rank-one fusion of every reading of a step (robots in order, as
  :func:`estimation.range_model.covariance_update`) and the cost sum of
  lambda_max (eq. 8c).

Pure numeric code: no MuJoCo, no I/O. ``cache=True`` stores the machine
code next to this file, so only the first run on a machine compiles.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from estimation.range_model import range_sigma_scalar

MIN_RANGE_M = 1e-9  # floor of a reading's range when normalising its direction, m


@njit(cache=True)
def segment_hits_box(a, b, centers, half_sizes, rotations, aligned) -> bool:
    """True when the segment [a, b] (3,) meets a closed box (K boxes:
    centers (K, 3), half_sizes (K, 3), rotations (K, 3, 3) box -> world, m;
    ``aligned``: every rotation is the identity).

    Slab method in each box frame: the segment parameter interval inside each
    pair of parallel faces, intersected over the three axes and with [0, 1];
    a box is left as soon as the interval is empty (most boxes fail on the
    first axis, which is what makes this cheap).
    """
    for k in range(centers.shape[0]):
        enter = 0.0
        leave = 1.0
        for i in range(3):
            if aligned:
                start = a[i] - centers[k, i]
                d = (b[i] - centers[k, i]) - start
            else:
                start = 0.0
                end = 0.0
                for j in range(3):
                    start += (a[j] - centers[k, j]) * rotations[k, j, i]
                    end += (b[j] - centers[k, j]) * rotations[k, j, i]
                d = end - start
            half = half_sizes[k, i]
            if d == 0.0:
                if abs(start) > half:
                    enter = math.inf  # parallel to this slab and outside it: no hit
                    break
            else:
                t1 = (-half - start) / d
                t2 = (half - start) / d
                enter = max(enter, min(t1, t2))
                leave = min(leave, max(t1, t2))
                if enter > leave:
                    break
        if enter <= leave:
            return True
    return False


@njit(cache=True)
def segments_hit_boxes(a, b, centers, half_sizes, rotations, aligned):
    """(P,) bool: :func:`segment_hits_box` for each segment [a_p, b_p] of (P, 3) arrays."""
    out = np.empty(a.shape[0], dtype=np.bool_)
    for p in range(a.shape[0]):
        out[p] = segment_hits_box(a[p], b[p], centers, half_sizes, rotations, aligned)
    return out


JACOBI_MAX_SWEEPS = 16  # cyclic Jacobi sweeps; 3x3 converges quadratically in 3-5
JACOBI_OFF_RTOL = 1e-36  # stop when sum(off-diagonal^2) <= this times sum(diagonal^2)


@njit(cache=True)
def _jacobi_rotation(a_pp: float, a_qq: float, a_pq: float) -> tuple[float, float, float]:
    """tan, cos and sin of the rotation in the (p, q) plane that zeroes
    a_pq (a_pq != 0), in Numerical Recipes' stable form: the smaller root t."""
    theta = (a_qq - a_pp) / (2.0 * a_pq)
    t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
    if theta < 0.0:
        t = -t
    cs = 1.0 / math.sqrt(t * t + 1.0)
    return t, cs, t * cs


@njit(cache=True)
def max_eigenvalue_sym3(c) -> float:
    """Largest eigenvalue of the symmetric 3x3 matrix ``c`` (upper triangle read).

    Cyclic Jacobi rotations (Numerical Recipes' stable form): backward stable
    like LAPACK's ``eigvalsh``, so the result is within a few ulps of
    ||c|| of it even when the two largest eigenvalues coincide (an unseen
    target's horizontal variances), where the closed-form cubic solution
    loses half the digits.
    """
    a00, a11, a22 = c[0, 0], c[1, 1], c[2, 2]
    a01, a02, a12 = c[0, 1], c[0, 2], c[1, 2]
    for _ in range(JACOBI_MAX_SWEEPS):
        off = a01 * a01 + a02 * a02 + a12 * a12
        if off <= JACOBI_OFF_RTOL * (a00 * a00 + a11 * a11 + a22 * a22):
            break
        # Rotation in the (0, 1) plane zeroes a01; a02, a12 mix.
        if a01 != 0.0:
            t, cs, sn = _jacobi_rotation(a00, a11, a01)
            a00 -= t * a01
            a11 += t * a01
            a01 = 0.0
            a02, a12 = cs * a02 - sn * a12, sn * a02 + cs * a12
        # (0, 2) plane: zeroes a02; a01, a12 mix.
        if a02 != 0.0:
            t, cs, sn = _jacobi_rotation(a00, a22, a02)
            a00 -= t * a02
            a22 += t * a02
            a02 = 0.0
            a01, a12 = cs * a01 - sn * a12, sn * a01 + cs * a12
        # (1, 2) plane: zeroes a12; a01, a02 mix.
        if a12 != 0.0:
            t, cs, sn = _jacobi_rotation(a11, a22, a12)
            a11 -= t * a12
            a22 += t * a12
            a12 = 0.0
            a01, a02 = cs * a01 - sn * a02, sn * a01 + cs * a02
    return max(a00, max(a11, a22))


@njit(cache=True)
def block_max_eigenvalues(blocks):
    """(P, M, 3, 3) symmetric blocks -> (P, M) lambda_max of each."""
    out = np.empty(blocks.shape[:2])
    for p in range(blocks.shape[0]):
        for m in range(blocks.shape[1]):
            out[p, m] = max_eigenvalue_sym3(blocks[p, m])
    return out


@njit(cache=True)
def propagate_blocks(
    cov, transition, process_noise, t0, n_steps, positions, means, belief_time, measurement_period,
    sensor_height, sensing_range, centers, half_sizes, rotations, aligned,
):
    """Algorithm 4 over P edges, block-diagonal covariances.

    cov: (P, M, 3, 3) m^2 at steps t0 (P,) int; n_steps: (P,) steps to
    propagate; positions: (P, S, L, 2) sensor plane positions, m, at steps
    t0 + 1 .. t0 + L (NaN: no reading); means: (T, 3M) predicted estimate at
    steps belief_time + row, m; transition, process_noise: (M, 3, 3) blocks
    of A and Q. Readings happen at steps t with t % measurement_period == 0
    from sensors at ``sensor_height`` m to targets within ``sensing_range`` m
    whose segment meets no box. Returns (covariance (P, M, 3, 3) at t0 +
    n_steps, cost (P,) = sum of lambda_max(C(t)), m^2, per-target lambda_max
    (P, M) at the last step).
    """
    n_edges, n_targets = cov.shape[0], cov.shape[1]
    n_sensors = positions.shape[1]
    out = cov.copy()
    cost = np.zeros(n_edges)
    temp = np.empty((3, 3))
    post = np.empty((n_targets, 3, 3))
    sensor = np.empty(3)
    target = np.empty(3)
    h = np.empty(3)
    ch = np.empty(3)
    for e in range(n_edges):
        c = out[e]
        for step in range(n_steps[e]):
            t = t0[e] + 1 + step
            for m in range(n_targets):  # eq. 8b: C <- A C A^T + Q, per target block
                for i in range(3):
                    for j in range(3):
                        temp[i, j] = transition[m, i, 0] * c[m, 0, j] + transition[m, i, 1] * c[m, 1, j] \
                            + transition[m, i, 2] * c[m, 2, j]
                for i in range(3):
                    for j in range(3):
                        post[m, i, j] = temp[i, 0] * transition[m, j, 0] + temp[i, 1] * transition[m, j, 1] \
                            + temp[i, 2] * transition[m, j, 2] + process_noise[m, i, j]
            if t % measurement_period == 0:
                row = t - belief_time
                for s in range(n_sensors):
                    x = positions[e, s, step, 0]
                    y = positions[e, s, step, 1]
                    if math.isnan(x) or math.isnan(y):
                        continue  # robot position unknown at this step: no reading
                    sensor[0], sensor[1], sensor[2] = x, y, sensor_height
                    for m in range(n_targets):
                        for i in range(3):
                            target[i] = means[row, 3 * m + i]
                            h[i] = target[i] - sensor[i]
                        distance = math.sqrt(h[0] * h[0] + h[1] * h[1] + h[2] * h[2])
                        if not distance <= sensing_range:
                            continue
                        if centers.shape[0] and segment_hits_box(sensor, target, centers, half_sizes, rotations,
                                                                 aligned):
                            continue
                        scale = max(distance, MIN_RANGE_M)
                        for i in range(3):
                            h[i] = h[i] / scale
                        sigma = range_sigma_scalar(distance)
                        # Scalar reading: C -= C h h^T C / (h^T C h + sigma^2).
                        for i in range(3):
                            ch[i] = post[m, i, 0] * h[0] + post[m, i, 1] * h[1] + post[m, i, 2] * h[2]
                        denom = h[0] * ch[0] + h[1] * ch[1] + h[2] * ch[2] + sigma * sigma
                        for i in range(3):
                            for j in range(3):
                                post[m, i, j] = post[m, i, j] - ch[i] * (ch[j] / denom)
            unc = -math.inf
            for m in range(n_targets):
                for i in range(3):
                    for j in range(3):
                        c[m, i, j] = 0.5 * (post[m, i, j] + post[m, j, i])
                unc = max(unc, max_eigenvalue_sym3(c[m]))
            cost[e] += unc
    return out, cost, block_max_eigenvalues(out)


@njit(cache=True)
def edge_sequences(t_parent, q_parent, tau_parent, tails, tail_lengths, q_child, t_child):
    """Robot positions at every step of P tree edges, as Algorithm 4 reads them.

    Edge p runs from a parent settled up to step tau_parent[p] (P,), whose
    robots are at q_parent (P, n, 2) m at steps t_parent (P, n), with
    tails (P, n, D, 2) m: the positions of its ahead robots at steps
    tau + 1 .. tau + tail_lengths[p] (NaN after each robot's t_j), to a child
    at q_child (P, n, 2) m reached at steps t_child (P, n). Returns
    positions (P, n, S, 2) at steps tau + 1 .. tau + S, S = max span
    (the parent's tail, then the straight move at constant speed, then NaN
    after t_child; NaN past each edge's own span), n_steps (P,) = min_j
    t_child - tau (the steps the child settles) and spans (P,) = max_j t_child - tau.
    """
    n_edges, n_robots = q_parent.shape[0], q_parent.shape[1]
    spans = np.empty(n_edges, dtype=np.int64)
    n_steps = np.empty(n_edges, dtype=np.int64)
    for e in range(n_edges):
        spans[e] = t_child[e].max() - tau_parent[e]
        n_steps[e] = t_child[e].min() - tau_parent[e]
    positions = np.full((n_edges, n_robots, max(spans.max(), 0), 2), np.nan)
    for e in range(n_edges):
        for j in range(n_robots):
            duration = max(t_child[e, j] - t_parent[e, j], 1)
            for k in range(spans[e]):
                time = tau_parent[e] + 1 + k
                if time <= t_parent[e, j]:  # still on the parent's tail
                    if k < tail_lengths[e]:
                        positions[e, j, k, 0] = tails[e, j, k, 0]
                        positions[e, j, k, 1] = tails[e, j, k, 1]
                elif time <= t_child[e, j]:
                    frac = min(max((time - t_parent[e, j]) / duration, 0.0), 1.0)
                    for i in range(2):
                        positions[e, j, k, i] = q_parent[e, j, i] + frac * (q_child[e, j, i] - q_parent[e, j, i])
    return positions, n_steps, spans
