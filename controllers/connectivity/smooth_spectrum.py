"""A smooth lower bound of lambda2 for the centralised oracle (optional, not in the paper).

lambda2 is not differentiable where it meets lambda3: there the Fiedler
vector turns inside a (nearly) two-dimensional eigenspace from one control
tick to the next, and the gradient of eq. (17) - hence f_lambda - jumps
between the two modes. In our runs that happens whenever two explorers pull
on opposite leaves of a tree-like team (lambda2 ~ lambda3), and the force
chatters by tens of newtons at the control rate.

With ``spectrum_smoothing`` kappa > 0 the exact mode drives V with a smooth
surrogate s of lambda2 instead: the soft minimum of the non-zero Laplacian
eigenvalues lambda_k (k >= 2) at a temperature proportional to itself,

    s = -tau log sum_{k>=2} exp(-lambda_k / tau),   tau = kappa s,

so s is a symmetric, smooth (away from s = 0), degree-one homogeneous
function of the spectrum with

    lambda2 / (1 + kappa ln(N - 1)) <= s <= lambda2,

and ds/dlambda_k = w_k s / lambda_bar, w = softmax(-lambda / tau),
lambda_bar = sum_k w_k lambda_k (implicit differentiation). Its gradient is
sum_k (ds/dlambda_k) dlambda_k/dq with each dlambda_k/dq from eq. (17) with
the k-th eigenvector; on a degenerate eigenspace the weights are equal and
the sum does not depend on the basis eigh returns. Since s <= lambda2, the
barrier V(s) keeps lambda2 > lambda2_min as V(lambda2) does (s > lambda2_min
implies lambda2 > lambda2_min); kappa = 0 is the paper's lambda2.
"""

from __future__ import annotations

import math

import numpy as np

from controllers.connectivity.graph import LinkWeights, _lambda2_gradients_kernel
from sim.compiled import kernel

# Eigenvalue modes whose soft-min weight is below this are left out of the gradient.
_MIN_WEIGHT = 1e-9
_NEWTON_STEPS = 50
_TOLERANCE = 1e-13


@kernel
def _smooth_lambda2_kernel(values, kappa, slope):
    """s of the non-zero eigenvalues ``values`` (M,) ascending; ds/dlambda_k into ``slope`` (M,).
    A safeguarded Newton iteration on g(s) = h(kappa s) - s, h the soft minimum at temperature tau."""
    count = len(values)
    lowest = values[0]
    if kappa <= 0 or count == 1 or lowest <= 0:
        for k in range(count):
            slope[k] = 0.0
        slope[0] = 1.0
        return max(lowest, 0.0) if kappa > 0 and count > 1 else lowest
    # g(s) is decreasing with a single root in [lowest / (1 + kappa ln(N-1)), lowest].
    low = lowest / (1.0 + kappa * math.log(count))
    high = lowest
    s = low
    for _ in range(_NEWTON_STEPS):
        tau = kappa * s
        h, mean = _softmin(values, tau, slope)
        g = h - s
        if g > 0:
            low = s
        else:
            high = s
        derivative = kappa * (h - mean) / tau - 1.0
        step = s - g / derivative
        if g == 0 or abs(step - s) < _TOLERANCE * lowest:
            s = step
            break
        s = step if low < step < high else 0.5 * (low + high)
        if high - low < _TOLERANCE * lowest:
            break
    _, mean = _softmin(values, kappa * s, slope)
    for k in range(count):
        slope[k] = slope[k] * s / mean
    return s


@kernel
def _softmin(values, tau, weights):
    """-tau log sum exp(-values / tau) and the weighted mean of ``values``; the softmax weights into ``weights``."""
    lowest = values[0]
    for k in range(len(values)):
        lowest = min(lowest, values[k])
    total = 0.0
    for k in range(len(values)):
        weights[k] = math.exp(-(values[k] - lowest) / tau)
        total += weights[k]
    mean = 0.0
    for k in range(len(values)):
        weights[k] = weights[k] / total
        mean += weights[k] * values[k]
    return lowest - tau * math.log(total), mean


def smooth_lambda2(eigenvalues: np.ndarray, kappa: float) -> tuple[float, np.ndarray]:
    """s and ds/dlambda_k for k = 2..N (array of N - 1), from all N ascending eigenvalues (compiled)."""
    return smooth_minimum(np.asarray(eigenvalues, dtype=float)[1:], kappa)


def smooth_minimum(values: np.ndarray, kappa: float) -> tuple[float, np.ndarray]:
    """``smooth_lambda2`` from the non-zero eigenvalues lambda_2..lambda_N (M,) alone."""
    values = np.ascontiguousarray(values, dtype=float)
    slope = np.empty(len(values))
    return float(_smooth_lambda2_kernel(values, float(kappa), slope)), slope


def smooth_lambda2_gradient(links: LinkWeights, eigenvalues: np.ndarray, eigenvectors: np.ndarray,
                            kappa: float) -> tuple[float, np.ndarray]:
    """s and ds/dq (N, 3), 1/m, from the Laplacian's eigh (values ascending, vectors as columns)."""
    eigenvalues = np.asarray(eigenvalues, dtype=float)
    values = eigenvalues[1:] if eigenvalues.flags.c_contiguous else np.ascontiguousarray(eigenvalues[1:])
    slope = np.empty(len(values))
    s = float(_smooth_lambda2_kernel(values, float(kappa), slope))
    gradient = np.zeros((links.num_robots, 3))
    # One batched eq. (17) for the modes that weigh (each equal to the single-vector one), summed in
    # mode order: one compiled call.
    _weighted_mode_gradient(slope, _MIN_WEIGHT, eigenvectors, links.pairs, links.collision_factor,
                            links.link_factor, links.link_factor_grad_first, links.link_factor_grad_second,
                            links.collision_log_slope, links.unit, links.bystander_robot, links.bystander_log_slope,
                            links.bystander_unit, gradient)
    return s, gradient


@kernel
def _weighted_mode_gradient(slope, min_weight, eigenvectors, pairs, collision_factor, link_factor, grad_first,
                            grad_second, log_slope, unit, bystander_robot, bystander_log_slope, bystander_unit,
                            gradient):
    """gradient += sum over modes k with slope[k] > min_weight max(slope), in order, of slope[k] times eq. (17)
    with eigenvector k + 1: what np.flatnonzero, LinkWeights.lambda2_gradients and _add_weighted did."""
    top = slope[0]
    for k in range(1, slope.shape[0]):
        if slope[k] > top or slope[k] != slope[k]:  # np.max: the largest, NaN if any
            top = slope[k]
            if top != top:
                break
    threshold = min_weight * top
    count = 0
    for k in range(slope.shape[0]):
        if slope[k] > threshold:
            count += 1
    n = eigenvectors.shape[0]
    vectors = np.empty((n, count))
    weights = np.empty(count)
    m = 0
    for k in range(slope.shape[0]):
        if slope[k] > threshold:
            weights[m] = slope[k]
            for i in range(n):
                vectors[i, m] = eigenvectors[i, k + 1]
            m += 1
    terms = np.empty((count, n, 3))
    _lambda2_gradients_kernel(pairs, vectors, collision_factor, link_factor, grad_first, grad_second, log_slope,
                              unit, bystander_robot, bystander_log_slope, bystander_unit, terms)
    _add_weighted(weights, terms, gradient)


@kernel
def _add_weighted(weights, terms, total):
    """total += weights[m] * terms[m] for each m in order; terms (M, N, 3), total (N, 3)."""
    for m in range(terms.shape[0]):
        for i in range(terms.shape[1]):
            for d in range(3):
                total[i, d] += weights[m] * terms[m, i, d]
