"""Range-only line-of-sight measurement model of Khodayi-mehr et al. 2019 (Sec. IV, eq. 12).

Pure numpy (and a compiled scalar sigma(l)); never imports MuJoCo. The state stacks the 3D positions of all
M targets: x = [x_1; ...; x_M] in R^{3M}, metres, world frame. Robot sensor
positions are (R, 3) arrays in the same frame.
"""

from __future__ import annotations

import numpy as np
from numba import njit

SENSING_RANGE_M = 5.0  # Khodayi-mehr et al. 2019: "limited range of 5m"


@njit(cache=True)
def range_sigma_scalar(distance: float) -> float:
    """Standard deviation sigma(l) of a range reading at ``distance`` m, eq. (12).

    0.01 m below 1 m, linear 0.045 l - 0.035 between 1 and 3 m, 0.1 m from
    3 m to the 5 m sensing limit (the paper's table prints 0.1 there; its text
    and Fig. 4 say the curve is flat at 0.1 m). Compiled, so the planner's
    kernels call it per reading.
    """
    if distance < 1.0:
        return 0.01
    if distance < 3.0:
        return 0.045 * distance - 0.035
    return 0.1


@njit(cache=True)
def _range_sigma_flat(distance: np.ndarray) -> np.ndarray:
    out = np.empty_like(distance)
    for i in range(distance.size):
        out[i] = range_sigma_scalar(distance[i])
    return out


def range_sigma(distance: np.ndarray) -> np.ndarray:
    """sigma(l), m, of :func:`range_sigma_scalar` for every distance (any shape)."""
    distance = np.asarray(distance, dtype=float)
    return _range_sigma_flat(distance.ravel()).reshape(distance.shape)


def target_positions(x: np.ndarray) -> np.ndarray:
    """State (3M,) -> (M, 3) target positions."""
    return np.asarray(x, dtype=float).reshape(-1, 3)


def expected_ranges(x: np.ndarray, sensors: np.ndarray) -> np.ndarray:
    """h(x): (R, M) distances from each sensor to each target, m."""
    targets = target_positions(x)
    return np.linalg.norm(sensors[:, None, :] - targets[None, :, :], axis=-1)


def range_jacobian(x: np.ndarray, sensor: np.ndarray, target: int) -> np.ndarray:
    """d l / d x for one reading of ``target`` from ``sensor``: (3M,) row."""
    targets = target_positions(x)
    diff = targets[target] - sensor
    row = np.zeros(targets.size)
    row[3 * target : 3 * target + 3] = diff / max(np.linalg.norm(diff), 1e-9)
    return row


def covariance_predict(cov: np.ndarray, a: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Prediction step C <- A C A^T + Q (all (3M, 3M))."""
    return a @ cov @ a.T + q


def covariance_update(
    cov: np.ndarray, x: np.ndarray, sensors: np.ndarray, visible: np.ndarray
) -> np.ndarray:
    """Covariance after fusing one range reading per visible (sensor, target).

    cov: (3M, 3M) prior covariance; x: (3M,) linearisation point (the
    estimate); sensors: (R, 3); visible: (R, M) bool, which readings exist.
    Used by the planner to predict uncertainty without measurements: the
    EKF covariance update does not depend on the measured values.
    Information form: C+^{-1} = C^{-1} + sum_k h_k h_k^T / sigma_k^2, done
    as a Joseph-free sequence of rank-one updates (exact for scalar readings).
    """
    cov = np.array(cov, dtype=float, copy=True)
    ranges = expected_ranges(x, sensors)
    for r, a in zip(*np.nonzero(visible)):
        h = range_jacobian(x, sensors[r], a)
        variance = range_sigma(ranges[r, a]) ** 2
        ch = cov @ h
        cov -= np.outer(ch, ch) / (h @ ch + variance)
    return 0.5 * (cov + cov.T)
