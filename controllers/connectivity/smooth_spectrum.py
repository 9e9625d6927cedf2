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

from controllers.connectivity.graph import LinkWeights

# Eigenvalue modes whose soft-min weight is below this are left out of the gradient.
_MIN_WEIGHT = 1e-9
_NEWTON_STEPS = 50
_TOLERANCE = 1e-13


def _softmin(values: np.ndarray, tau: float) -> tuple[float, np.ndarray]:
    """-tau log sum exp(-values / tau) and the softmax weights."""
    shifted = -(values - values.min()) / tau
    exp = np.exp(shifted)
    total = exp.sum()
    return float(values.min() - tau * math.log(total)), exp / total


def smooth_lambda2(eigenvalues: np.ndarray, kappa: float) -> tuple[float, np.ndarray]:
    """s and ds/dlambda_k for k = 2..N (array of N - 1), from all N ascending eigenvalues."""
    values = np.asarray(eigenvalues, dtype=float)[1:]
    lowest = float(values[0])
    if kappa <= 0 or len(values) == 1:
        slope = np.zeros(len(values))
        slope[0] = 1.0
        return lowest, slope
    if lowest <= 0:
        slope = np.zeros(len(values))
        slope[0] = 1.0
        return max(lowest, 0.0), slope
    # g(s) = h(kappa s) - s is decreasing with a single root in [lowest / (1 + kappa ln(N-1)), lowest].
    low = lowest / (1.0 + kappa * math.log(len(values)))
    high = lowest
    s = low
    for _ in range(_NEWTON_STEPS):
        tau = kappa * s
        h, weights = _softmin(values, tau)
        g = h - s
        if g > 0:
            low = s
        else:
            high = s
        mean = float(weights @ values)
        derivative = kappa * (h - mean) / tau - 1.0
        step = s - g / derivative
        if g == 0 or abs(step - s) < _TOLERANCE * lowest:
            s = step
            break
        s = step if low < step < high else 0.5 * (low + high)
        if high - low < _TOLERANCE * lowest:
            break
    tau = kappa * s
    _, weights = _softmin(values, tau)
    mean = float(weights @ values)
    return s, weights * s / mean


def smooth_lambda2_gradient(links: LinkWeights, eigenvalues: np.ndarray, eigenvectors: np.ndarray,
                            kappa: float) -> tuple[float, np.ndarray]:
    """s and ds/dq (N, 3), 1/m, from the Laplacian's eigh (values ascending, vectors as columns)."""
    s, slope = smooth_lambda2(eigenvalues, kappa)
    modes = np.flatnonzero(slope > _MIN_WEIGHT * slope.max())
    gradient = np.zeros((links.num_robots, 3))
    # One batched eq. (17) for all modes (each bit-identical to the single-vector one), summed in mode order.
    for k, mode_gradient in zip(modes, links.lambda2_gradients(eigenvectors[:, modes + 1])):
        gradient += slope[k] * mode_gradient
    return s, gradient
