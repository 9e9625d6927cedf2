"""Connectivity potential V(lambda2) of Nestmeyer et al. 2017 (Appendix A, step 3).

The paper asks for a potential that grows unbounded as lambda2 -> lambda2_min
from above, and its Tables 2-3 give a second threshold lambda2_null beyond
which the potential is "null". With x = (lambda2 - lambda2_min) /
(lambda2_null - lambda2_min) we use

    V(lambda2) = k_lambda (x - 1 - ln x)      for 0 < x < 1,
    V(lambda2) = 0                             for x >= 1,
    V(lambda2) = +inf                          for x <= 0,

    dV/dlambda2 = k_lambda (1 - 1/x) / (lambda2_null - lambda2_min)   for 0 < x < 1,

which is positive, strictly decreasing on (lambda2_min, lambda2_null),
unbounded at lambda2_min, and C1 at lambda2_null (value and slope both 0
there), so the connectivity force f = -V'(lambda2) dlambda2/dq is continuous
and vanishes for well-connected groups.

Deviations from the paper
-------------------------
- Neither this paper nor its recap of Robuffo Giordano et al. (2013) gives the
  analytic form of V, only its shape (zero above a threshold, unbounded at
  lambda2_min). We chose the logarithmic barrier above: near lambda2_min the
  force is about k_lambda * dlambda2/dq / (lambda2 - lambda2_min), i.e. the
  gradient of k_lambda ln(lambda2). Since dlambda2/dq itself scales with
  lambda2, the force a link exerts depends on how close *that link* is to
  breaking rather than on the team size (a reciprocal barrier 1/(lambda2 -
  lambda2_min) would instead make forces grow with N on sparse large graphs,
  where lambda2 is small even when nothing is about to break).
- ``guarded_potential_slope`` holds the slope below lambda2_min +
  lambda2_guard (see connected_params.py): sampled-data safety, not part of the paper.
"""

from __future__ import annotations

import numpy as np

from controllers.connectivity.connected_params import ConnectedParams
from sim.compiled import kernel


def _normalised(lambda2, params: ConnectedParams) -> np.ndarray:
    return (np.asarray(lambda2, dtype=float) - params.lambda2_min) / (params.lambda2_null - params.lambda2_min)


def connectivity_potential(lambda2, params: ConnectedParams) -> np.ndarray:
    """V(lambda2), J; +inf at or below lambda2_min, 0 at or above lambda2_null."""
    x = _normalised(lambda2, params)
    inside = (x > 0) & (x < 1)
    safe_x = np.where(inside, x, 1.0)
    value = np.where(inside, params.potential_gain_j * (safe_x - 1.0 - np.log(safe_x)), 0.0)
    return np.where(x <= 0, np.inf, value)


def connectivity_potential_slope(lambda2, params: ConnectedParams) -> np.ndarray:
    """dV/dlambda2, J per unit lambda2; -inf at or below lambda2_min, 0 at or above lambda2_null."""
    return _slopes(lambda2, params, -np.inf)


def guarded_potential_slope(lambda2, params: ConnectedParams) -> np.ndarray:
    """dV/dlambda2 with lambda2 floored at lambda2_min + lambda2_guard: always finite."""
    return _slopes(lambda2, params, params.lambda2_min + params.lambda2_guard)


def _slopes(lambda2, params: ConnectedParams, floor: float) -> np.ndarray:
    """dV/dlambda2 at max(lambda2, floor), element by element (compiled: the control tick asks for one or N)."""
    values = np.asarray(lambda2, dtype=float)
    slope = np.empty(values.shape)
    _slope_kernel(values.ravel(), float(floor), float(params.lambda2_min), float(params.lambda2_null),
                  float(params.potential_gain_j), slope.reshape(-1))
    return slope


@kernel
def _slope_kernel(lambda2, floor, lambda2_min, lambda2_null, gain, out):
    """dV/dlambda2 of each max(lambda2[k], floor) into ``out`` (NaN kept, as np.maximum)."""
    span = lambda2_null - lambda2_min
    for k in range(lambda2.shape[0]):
        value = lambda2[k] if (lambda2[k] != lambda2[k] or lambda2[k] > floor) else floor
        x = (value - lambda2_min) / span
        if x <= 0:
            out[k] = -np.inf
        elif x < 1:
            out[k] = gain * (1.0 - 1.0 / x) / span
        else:
            out[k] = 0.0
