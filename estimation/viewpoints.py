"""How much a viewpoint would teach the EKF about one target (Khodayi-mehr et al. 2019, eqs. 11-12).

Pure numpy, never imports MuJoCo. Used by the EKF target generator of
``connected_tracking`` (the continuous-connectivity paper's controller on the intermittent paper's task): it picks,
for the most uncertain target, the free point from which the explorer's range
readings shrink that target's covariance most, and holds it there as long as
the readings need.

The targets move independently (block-diagonal A and Q, eq. 11) and a range
reading of target a only touches block a, so one target's 3 x 3 covariance
block evolves on its own: C <- A_a C A_a^T + Q_a per step, then one rank-one
update per reading, C <- C - C h h^T C / (h^T C h + sigma(l)^2), with h the
unit vector from the sensor to the target and sigma(l) of eq. (12). As in the
planner's cost (Alg. 4), the covariance update does not depend on the
measured values, so it can be predicted before the readings exist.

Units: m, m^2; one step = one reading period.
"""

from __future__ import annotations

import numpy as np

from estimation.range_model import range_sigma


def block_lambda_max(covariance: np.ndarray, n_targets: int) -> np.ndarray:
    """lambda_max (M,) of each target's 3 x 3 block of a (3M, 3M) covariance, m^2."""
    blocks = np.asarray(covariance, dtype=float).reshape(n_targets, 3, n_targets, 3)
    idx = np.arange(n_targets)
    return np.linalg.eigvalsh(blocks[idx, :, idx, :])[:, -1]


def predicted_lambda_max(covariance: np.ndarray, transition: np.ndarray, noise: np.ndarray, target: np.ndarray,
                         sensors: np.ndarray, travel_steps: np.ndarray, reading_steps: int) -> np.ndarray:
    """lambda_max of one target's block after travelling, then reading, from each of K viewpoints.

    covariance, transition, noise: (3, 3) the block C, A_a and Q_a; target:
    (3,) its estimate (the linearisation point, held fixed); sensors: (K, 3)
    sensor positions at the viewpoints; travel_steps: (K,) steps without a
    reading of this target before the robot is there (prediction only);
    reading_steps: readings taken there, one per step.

    Returns (K, reading_steps + 1): entry j is lambda_max after the travel and
    j readings.
    """
    sensors = np.atleast_2d(np.asarray(sensors, dtype=float))
    k = len(sensors)
    travel = np.asarray(travel_steps, dtype=int).reshape(k)
    a = np.asarray(transition, dtype=float)
    q = np.asarray(noise, dtype=float)
    cov = np.broadcast_to(np.asarray(covariance, dtype=float), (k, 3, 3)).copy()
    for step in range(int(travel.max(initial=0))):
        moving = travel > step
        cov[moving] = a @ cov[moving] @ a.T + q
    diff = np.asarray(target, dtype=float)[None] - sensors
    distance = np.linalg.norm(diff, axis=1)
    h = diff / np.maximum(distance, 1e-9)[:, None]
    variance = range_sigma(distance) ** 2
    out = np.empty((k, reading_steps + 1))
    out[:, 0] = np.linalg.eigvalsh(cov)[:, -1]
    for j in range(1, reading_steps + 1):
        cov = a @ cov @ a.T + q
        ch = np.einsum("kij,kj->ki", cov, h)
        cov = cov - ch[:, :, None] * ch[:, None, :] / (np.einsum("ki,ki->k", h, ch) + variance)[:, None, None]
        cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
        out[:, j] = np.linalg.eigvalsh(cov)[:, -1]
    return out


def readings_needed(series: np.ndarray, delta: float, stall: float) -> int:
    """Readings a viewpoint needs (its dwell, in steps) from its lambda_max ``series``
    (``predicted_lambda_max`` row, entry 0 = on arrival): the first j at which
    lambda_max < ``delta`` (m^2), or at which one more reading would shrink it
    by less than the fraction ``stall`` (readings from one place stop helping:
    a single direction leaves the perpendicular uncertainty), at most the
    series' last entry; at least 1."""
    series = np.asarray(series, dtype=float)
    last = len(series) - 1
    for j in range(1, last + 1):
        if series[j] < delta:
            return j
        if j < last and series[j] - series[j + 1] < stall * series[j]:
            return j
    return max(last, 1)
