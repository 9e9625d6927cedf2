"""Extended Kalman filter over all targets' 3D positions (Khodayi-mehr et al. 2019, Alg. 4).

The state x in R^{3M} stacks the positions of the M targets (m, world frame).
Prediction uses the stacked LTI target model of eq. (11) from
:class:`estimation.target_motion.TargetMotion`:

    x(k+1) = A x(k) + B u(k) + w(k),   w ~ N(0, Q)           (eq. 8: F = A, L = I)

and the update fuses a batch of range-only readings y = ||p_r - x_a|| + v,
v ~ N(0, sigma(l)^2) (eq. 12), taken at the same time step by robot sensors
at positions p_r (eqs. 9-10 with M = I).

Built on filterpy's ``ExtendedKalmanFilter``: its ``predict(u)`` with F = A,
B = I and u = B u(k) is eq. (8), and ``update(z, HJacobian, Hx, R)`` takes a
per-call R, so a batch of any size is one call. Pure numpy, never imports
MuJoCo; line of sight and the 5 m sensing limit are the caller's business:
the filter fuses exactly the readings it is given.

Time convention: ``FilterState.step`` is the discrete time k the estimate
refers to. A filter starts at step 0 with the prior (x^0, C(0)); readings of
step k are fused into the estimate of x(k); ``predict`` moves k -> k + 1 with
the known input B u(k).

Deviations from the paper:
- R = diag(sigma(l_hat)^2) with sigma of eq. (12) evaluated at the predicted
  range l_hat = ||p_r - x_hat_a|| of the prior estimate: the true distance
  that sets the real noise is unknown to the filter.
- Readings taken at the same time step are fused in one batch update (the
  paper: concurrent measurements "must be fused together"), sorted by the
  caller (see ``RangeReadings``); the order changes nothing mathematically
  and the fixed order makes refiltering bit-reproducible.
- filterpy's Joseph-form covariance update (I-KH) C (I-KH)^T + K R K^T is
  used instead of eq. (10b) (I-KH) C: equal for the optimal gain, and it keeps
  C symmetric positive definite in floating point.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter

from estimation.range_model import range_sigma
from estimation.target_motion import TargetMotion

# Khodayi-mehr et al. 2019, Sec. IV: true initial target positions x0, m (8 targets x 3).
PAPER_INITIAL_TARGET_POSITIONS = np.array(
    [
        (1.0, 2.0, 1.5),
        (1.0, 1.0, 1.3),
        (8.5, 1.5, 0.8),
        (9.2, 9.0, 1.0),
        (7.0, 8.0, 1.1),
        (5.9, 9.0, 1.2),
        (3.0, 9.0, 1.3),
        (1.8, 8.2, 0.9),
    ]
)
PAPER_INITIAL_TARGET_POSITIONS.setflags(write=False)

# Khodayi-mehr et al. 2019, Sec. IV: EKF initialisation x^0, m (8 targets x 3).
PAPER_INITIAL_ESTIMATE = np.array(
    [
        (1.0, 1.0, 1.0),
        (1.0, 1.0, 1.0),
        (9.0, 1.0, 1.0),
        (9.0, 9.5, 1.0),
        (7.0, 9.5, 1.0),
        (4.0, 9.0, 1.0),
        (2.5, 7.0, 1.0),
        (1.0, 9.0, 1.0),
    ]
)
PAPER_INITIAL_ESTIMATE.setflags(write=False)

PAPER_INITIAL_VARIANCE_M2 = 0.25  # Sec. IV: C(0) = 0.25 I, m^2

# Distance below which the range Jacobian direction is undefined; the
# direction is then taken as zero-length-safe (same guard as range_model).
_MIN_RANGE_M = 1e-9


@dataclass(frozen=True)
class FilterState:
    """Gaussian belief about x(step): mean (3M,), m; covariance (3M, 3M), m^2.

    The arrays are copied and made read-only, so a state can be kept as a
    checkpoint and shared.
    """

    step: int
    mean: np.ndarray
    covariance: np.ndarray

    def __post_init__(self) -> None:
        mean = np.array(self.mean, dtype=float).reshape(-1)
        covariance = np.array(self.covariance, dtype=float)
        n = mean.size
        if self.step < 0:
            raise ValueError(f"step: must be >= 0, got {self.step}")
        if n == 0 or n % 3:
            raise ValueError(f"mean: length must be a positive multiple of 3 (3M), got {n}")
        if covariance.shape != (n, n):
            raise ValueError(f"covariance: must be ({n}, {n}), got {covariance.shape}")
        if not np.all(np.isfinite(mean)) or not np.all(np.isfinite(covariance)):
            raise ValueError("mean/covariance: must be finite")
        mean.setflags(write=False)
        covariance.setflags(write=False)
        object.__setattr__(self, "step", int(self.step))
        object.__setattr__(self, "mean", mean)
        object.__setattr__(self, "covariance", covariance)

    @property
    def n_targets(self) -> int:
        return self.mean.size // 3


def paper_prior() -> FilterState:
    """Sec. IV initialisation: x^0 and C(0) = 0.25 I (24 states), step 0."""
    mean = PAPER_INITIAL_ESTIMATE.reshape(-1)
    return FilterState(0, mean, PAPER_INITIAL_VARIANCE_M2 * np.eye(mean.size))


@dataclass(frozen=True)
class RangeReadings:
    """A batch of range readings taken at one time step.

    sensor_positions: (R, 3) sensor position of each reading, m, world frame.
    target_indices: (R,) int, which target each reading measures.
    ranges: (R,) measured distances, m.
    """

    sensor_positions: np.ndarray
    target_indices: np.ndarray
    ranges: np.ndarray

    def __post_init__(self) -> None:
        sensors = np.array(self.sensor_positions, dtype=float).reshape(-1, 3)
        targets = np.array(self.target_indices).reshape(-1)
        ranges = np.array(self.ranges, dtype=float).reshape(-1)
        if targets.size and not np.issubdtype(targets.dtype, np.integer):
            raise ValueError(f"target_indices: must be integers, got dtype {targets.dtype}")
        targets = targets.astype(int)
        if not (len(sensors) == len(targets) == len(ranges)):
            raise ValueError(
                f"sensor_positions/target_indices/ranges: lengths differ "
                f"({len(sensors)}, {len(targets)}, {len(ranges)})"
            )
        if np.any(targets < 0):
            raise ValueError(f"target_indices: must be >= 0, got {targets.min()}")
        if not np.all(np.isfinite(sensors)) or not np.all(np.isfinite(ranges)):
            raise ValueError("sensor_positions/ranges: must be finite")
        if np.any(ranges < 0):
            raise ValueError(f"ranges: distances must be >= 0 m, got {ranges.min()}")
        for name, array in (("sensor_positions", sensors), ("target_indices", targets), ("ranges", ranges)):
            array.setflags(write=False)
            object.__setattr__(self, name, array)

    def __len__(self) -> int:
        return len(self.ranges)

    @staticmethod
    def empty() -> "RangeReadings":
        return RangeReadings(np.zeros((0, 3)), np.zeros(0, dtype=int), np.zeros(0))


def predicted_ranges(x: np.ndarray, sensor_positions: np.ndarray, target_indices: np.ndarray) -> np.ndarray:
    """h(x): (R,) distance from each sensor to its target, m."""
    targets = np.asarray(x, dtype=float).reshape(-1, 3)[target_indices]
    return np.linalg.norm(targets - sensor_positions, axis=1)


def range_jacobian_batch(
    x: np.ndarray, sensor_positions: np.ndarray, target_indices: np.ndarray
) -> np.ndarray:
    """H = dh/dx: (R, 3M). Row r is the unit vector from sensor r to its target
    in the columns of that target, zero elsewhere."""
    x = np.asarray(x, dtype=float).reshape(-1)
    diff = x.reshape(-1, 3)[target_indices] - sensor_positions
    norms = np.maximum(np.linalg.norm(diff, axis=1), _MIN_RANGE_M)
    jacobian = np.zeros((len(target_indices), x.size))
    rows = np.arange(len(target_indices))[:, None]
    columns = 3 * np.asarray(target_indices)[:, None] + np.arange(3)[None, :]
    jacobian[rows, columns] = diff / norms[:, None]
    return jacobian


def measurement_noise(predicted: np.ndarray) -> np.ndarray:
    """R = diag(sigma(l)^2), m^2, with sigma of eq. (12) at the predicted ranges."""
    return np.diag(range_sigma(predicted) ** 2)


def reflect_below(state_mean: np.ndarray, covariance: np.ndarray, plane_z: float) -> tuple[np.ndarray, np.ndarray]:
    """Mirror every target estimate below the horizontal plane z = ``plane_z``
    to its image above it (z -> 2 plane_z - z), and its covariance with it.

    When every sensor lies in that plane (ground robots), each range reading
    is the same for a target and its mirror image, so the likelihood cannot
    tell them apart and an EKF started from a poor prior may settle on the
    image below the floor. Targets are known to be above the floor, and the
    reflection changes no predicted reading: it only picks the physical one of
    the two equally likely answers. The covariance is mapped by the same
    reflection J: C -> J C J (J flips the sign of the target's z).
    """
    mean = np.array(state_mean, dtype=float).reshape(-1)
    cov = np.array(covariance, dtype=float)
    z_index = np.arange(2, mean.size, 3)
    below = z_index[mean[z_index] < plane_z]
    if below.size == 0:
        return mean, cov
    mean[below] = 2.0 * plane_z - mean[below]
    flip = np.ones(mean.size)
    flip[below] = -1.0
    return mean, cov * flip[:, None] * flip[None, :]


class TargetEKF:
    """EKF for the stacked target positions on filterpy's ExtendedKalmanFilter.

    motion: the target model (A, B u(k), Q); initial: the belief to start from.
    ``state`` is the current :class:`FilterState`. ``mirror_plane_z`` (m,
    optional): all sensors lie in the plane z = mirror_plane_z and the
    targets above it; after every update an estimate that fell below is
    reflected back (:func:`reflect_below`). None (default): plain EKF.
    """

    def __init__(self, motion: TargetMotion, initial: FilterState, mirror_plane_z: float | None = None):
        n = 3 * motion.n_targets
        if initial.mean.size != n:
            raise ValueError(
                f"initial: mean has {initial.mean.size} states, the motion model has {n} (3M)"
            )
        self.mirror_plane_z = mirror_plane_z
        self.motion = motion
        self._filter = ExtendedKalmanFilter(dim_x=n, dim_z=1, dim_u=n)
        self._filter.F = motion.transition
        self._filter.B = np.eye(n)  # the model already gives B u(k) as a vector
        self._filter.Q = motion.process_noise
        self.reset(initial)

    def reset(self, state: FilterState) -> None:
        """Continue filtering from ``state`` (e.g. a checkpoint)."""
        if state.mean.size != self._filter.dim_x:
            raise ValueError(f"state: has {state.mean.size} states, filter has {self._filter.dim_x}")
        self._step = state.step
        self._filter.x = np.array(state.mean).reshape(-1, 1)
        self._filter.P = np.array(state.covariance)

    @property
    def state(self) -> FilterState:
        return FilterState(self._step, self._filter.x.reshape(-1), self._filter.P)

    def predict(self) -> FilterState:
        """Eq. (8): x(k+1|k) = A x(k) + B u(k), C(k+1|k) = A C A^T + Q."""
        self._filter.predict(u=self.motion.input(self._step).reshape(-1, 1))
        self._step += 1
        return self.state

    def update(self, readings: RangeReadings) -> FilterState:
        """Eqs. (9)-(10): fuse a batch of readings of the current step."""
        if len(readings) == 0:
            return self.state
        if readings.target_indices.max() >= self.motion.n_targets:
            raise ValueError(
                f"readings: target index {readings.target_indices.max()} out of range for "
                f"{self.motion.n_targets} targets"
            )
        sensors, targets = readings.sensor_positions, readings.target_indices
        prior_mean = self._filter.x.reshape(-1)
        noise = measurement_noise(predicted_ranges(prior_mean, sensors, targets))
        self._filter.update(
            readings.ranges.reshape(-1, 1),
            HJacobian=lambda x: range_jacobian_batch(x, sensors, targets),
            Hx=lambda x: predicted_ranges(x, sensors, targets).reshape(-1, 1),
            R=noise,
        )
        if self.mirror_plane_z is not None:
            mean, cov = reflect_below(self._filter.x, self._filter.P, self.mirror_plane_z)
            self._filter.x = mean.reshape(-1, 1)
            self._filter.P = cov
        return self.state
