"""Predicted team belief along planned paths: Algorithm 4 of Khodayi-mehr et al. 2019, batched.

At planning time no measurement values exist, so the estimate only follows the
target model, x_hat(t + 1) = A x_hat(t) + B u(t) (eq. 8a; the predicted reading
equals h(x_hat), the innovation is zero and eq. 10a leaves x_hat unchanged),
and the covariance follows the EKF recursion with the readings the robots
*would* take: predict C <- A C A^T + Q (eq. 8b), then fuse every range reading
(robot sensor within the sensing range of a predicted target position, with
line of sight) of that step (eqs. 9-10b). Every discrete time step adds
unc(t) = lambda_max(C(t)) to the cost (eqs. 8c and line 12 of Alg. 4).

Two interchangeable covariance representations:

- **blocks** (M, 3, 3): when A, Q and the prior covariance have no coupling
  between targets (off-diagonal 3x3 blocks below 1e-12 of the largest entry;
  true for the paper's diagonal C(0), per-target A_a, Q_a = q I and range
  readings, each of which involves one target only), the covariance stays
  block-diagonal and all candidate edges are propagated by one compiled
  kernel (:func:`planner_kernels.propagate_blocks`) with 3x3 block algebra:
  the readings of one step are fused by the same sequential
  rank-one updates as :func:`estimation.range_model.covariance_update`
  (C -= C h h^T C / (h^T C h + sigma^2), robots in order), each touching only
  its target's block; lambda_max(C) is the largest block eigenvalue.
- **full** (3M, 3M): otherwise, the reference functions
  :func:`estimation.range_model.covariance_predict` and
  :func:`estimation.range_model.covariance_update` are applied step by step.

Times are integer discrete steps. Robot positions are plane points (m) lifted
to the sensor height; NaN marks a robot whose position is unknown at that step
(it takes no reading).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimation.range_model import covariance_predict, covariance_update
from estimation.target_motion import TargetMotion
from sim.geometry import Boxes

from controllers.intermittent.planner_geometry import lift, segments_blocked
from controllers.intermittent.planner_kernels import block_max_eigenvalues, propagate_blocks

BLOCK_COUPLING_RTOL = 1e-12  # off-block entries below this share of max |entry| count as 0


def is_block_diagonal(matrix: np.ndarray, n_targets: int, rtol: float = BLOCK_COUPLING_RTOL) -> bool:
    """True when ``matrix`` (3M, 3M) has no coupling between different targets."""
    matrix = np.asarray(matrix, dtype=float)
    mask = np.kron(np.eye(n_targets, dtype=bool), np.ones((3, 3), dtype=bool))
    scale = float(np.abs(matrix).max(initial=0.0))
    return bool(np.abs(matrix[~mask]).max(initial=0.0) <= rtol * scale)


def diagonal_blocks(matrix: np.ndarray) -> np.ndarray:
    """(..., 3M, 3M) -> (..., M, 3, 3) per-target diagonal blocks."""
    m = matrix.shape[-1] // 3
    idx = np.arange(m)
    shaped = matrix.reshape(matrix.shape[:-2] + (m, 3, m, 3))
    return np.moveaxis(shaped[..., idx, :, idx, :], 0, -3)


def block_diagonal(blocks: np.ndarray) -> np.ndarray:
    """(M, 3, 3) -> (3M, 3M) block-diagonal matrix."""
    m = len(blocks)
    out = np.zeros((3 * m, 3 * m))
    for a in range(m):
        out[3 * a : 3 * a + 3, 3 * a : 3 * a + 3] = blocks[a]
    return out


@dataclass(frozen=True)
class Propagation:
    """Result of :meth:`PredictedBelief.propagate` for P candidate edges.

    covariance: (P, M, 3, 3) blocks or (P, 3M, 3M), m^2, at the last step.
    cost: (P,) sum of lambda_max(C(t)) over the propagated steps, m^2.
    target_uncertainty: (P, M) lambda_max of each target's 3x3 block at the
    last step, m^2.
    """

    covariance: np.ndarray
    cost: np.ndarray
    target_uncertainty: np.ndarray


class PredictedBelief:
    """The team belief predicted forward from ``belief_time`` (steps).

    estimate: (3M,) m and covariance: (3M, 3M) m^2 hold the team's belief at
    ``belief_time``. Sensors sit ``sensor_height`` m above the floor, see
    targets up to ``sensing_range`` m with line of sight past ``boxes``, and
    take readings at the steps t with t % measurement_period == 0. ``full``
    forces the (3M, 3M) reference representation even for block-diagonal
    covariances. ``sensor_offsets`` (S, 2), m: every planned robot carries S
    sensors at these plane offsets from its position (a rigid formation
    planned as one point, the all-time baseline); None is one sensor at the
    robot.
    """

    def __init__(
        self,
        motion: TargetMotion,
        estimate: np.ndarray,
        covariance: np.ndarray,
        belief_time: int,
        boxes: Boxes,
        sensor_height: float,
        sensing_range: float,
        measurement_period: int = 1,
        full: bool = False,
        sensor_offsets: np.ndarray | None = None,
    ):
        self.motion = motion
        self.n_targets = motion.n_targets
        self.belief_time = int(belief_time)
        self.boxes = boxes
        self.sensor_height = float(sensor_height)
        self.sensing_range = float(sensing_range)
        self.measurement_period = int(measurement_period)
        self.sensor_offsets = None
        if sensor_offsets is not None:
            offsets = np.asarray(sensor_offsets, dtype=float)
            if offsets.ndim != 2 or offsets.shape[1] != 2 or len(offsets) == 0 or not np.all(np.isfinite(offsets)):
                raise ValueError("sensor_offsets must be a finite (S, 2) array with S >= 1")
            self.sensor_offsets = offsets
        self.transition = np.asarray(motion.transition, dtype=float)
        self.process_noise = np.asarray(motion.process_noise, dtype=float)
        covariance = np.asarray(covariance, dtype=float)
        m = self.n_targets
        self.blocks = not full and all(
            is_block_diagonal(mat, m) for mat in (self.transition, self.process_noise, covariance)
        )
        if self.blocks:
            self._a = np.ascontiguousarray(diagonal_blocks(self.transition))
            self._q = np.ascontiguousarray(diagonal_blocks(self.process_noise))
            self.initial_covariance = np.ascontiguousarray(diagonal_blocks(covariance))
        else:
            self.initial_covariance = covariance.copy()
        self._means = np.empty((64, 3 * m))
        self._means[0] = np.asarray(estimate, dtype=float)
        self._n_means = 1

    # -- predicted estimate -------------------------------------------------
    def _ensure(self, t_max: int) -> None:
        needed = int(t_max) - self.belief_time + 1
        if needed <= self._n_means:
            return
        if needed > len(self._means):
            grown = np.empty((max(needed, 2 * len(self._means)), self._means.shape[1]))
            grown[: self._n_means] = self._means[: self._n_means]
            self._means = grown
        for i in range(self._n_means, needed):
            k = self.belief_time + i - 1
            self._means[i] = self.motion.predict(self._means[i - 1], k)
        self._n_means = needed

    def mean(self, t: int) -> np.ndarray:
        """Predicted estimate x_hat(t), (3M,) m, for integer t >= belief_time."""
        if t < self.belief_time:
            raise ValueError(f"t={t} precedes belief_time={self.belief_time}")
        self._ensure(t)
        return self._means[int(t) - self.belief_time].copy()

    def target_positions(self, times: np.ndarray) -> np.ndarray:
        """Predicted target positions (..., M, 3), m, at integer ``times`` (...)."""
        times = np.asarray(times, dtype=int)
        if times.size == 0:
            return np.zeros(times.shape + (self.n_targets, 3))
        self._ensure(int(times.max()))
        return self._means[times - self.belief_time].reshape(times.shape + (self.n_targets, 3))

    # -- covariance helpers -------------------------------------------------
    def full_covariance(self, covariance: np.ndarray) -> np.ndarray:
        """One covariance in this belief's representation -> (3M, 3M)."""
        return block_diagonal(covariance) if self.blocks else np.array(covariance)

    def target_uncertainty(self, covariance: np.ndarray) -> np.ndarray:
        """lambda_max of each target's block, (..., M), m^2."""
        blocks = np.asarray(covariance if self.blocks else diagonal_blocks(covariance), dtype=float)
        flat = np.ascontiguousarray(blocks.reshape(1, -1, 3, 3))
        return block_max_eigenvalues(flat).reshape(blocks.shape[:-2])

    # -- Algorithm 4 over a batch of edges --------------------------------
    def readings(
        self, t0: np.ndarray, n_steps: np.ndarray, positions: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Predicted readings at steps t0 + 1 .. t0 + n_steps of P edges.

        positions: (P, n, L, 2) plane positions, m (NaN: unknown). Returns
        visible (P, n, L, M) bool, directions (P, n, L, M, 3) unit vectors
        sensor -> target (0 where invisible), ranges (P, n, L, M) m and
        times (P, L) int.
        """
        length = positions.shape[2]
        times = t0[:, None] + 1 + np.arange(length)[None, :]
        active = np.arange(length)[None, :] < n_steps[:, None]
        measuring = active & (times % self.measurement_period == 0)
        targets = self.target_positions(np.where(active, times, t0[:, None] + 1))  # (P, L, M, 3)
        sensors = lift(positions, self.sensor_height)  # (P, n, L, 3)
        diff = targets[:, None, :, :, :] - sensors[:, :, :, None, :]
        ranges = np.linalg.norm(diff, axis=-1)
        with np.errstate(invalid="ignore"):
            visible = (
                measuring[:, None, :, None]
                & np.isfinite(ranges)
                & (ranges <= self.sensing_range)
            )
        if visible.any() and len(self.boxes):
            idx = np.nonzero(visible)
            a = sensors[idx[0], idx[1], idx[2]]
            b = targets[idx[0], idx[2], idx[3]]
            blocked = segments_blocked(self.boxes, a, b)
            visible[tuple(i[blocked] for i in idx)] = False
        safe = np.where(visible, np.maximum(ranges, 1e-9), 1.0)
        directions = np.where(visible[..., None], diff / safe[..., None], 0.0)
        return visible, directions, ranges, times

    def propagate(
        self,
        covariance: np.ndarray,
        t0: np.ndarray,
        n_steps: np.ndarray,
        positions: np.ndarray,
    ) -> Propagation:
        """Run Algorithm 4 over P edges at once.

        covariance: (P, ...) starting covariances at steps ``t0`` (P,) int;
        n_steps: (P,) int >= 0 steps to propagate; positions: (P, n, L, 2)
        robot plane positions at steps t0 + 1 .. t0 + L (L >= max n_steps),
        NaN where a robot is absent.
        """
        t0 = np.asarray(t0, dtype=int)
        n_steps = np.asarray(n_steps, dtype=int)
        covariance = np.array(covariance, dtype=float, copy=True)
        if self.sensor_offsets is not None:  # (P, n, L, 2) -> (P, n * S, L, 2)
            p_count, n, length, _ = positions.shape
            expanded = positions[:, :, None] + self.sensor_offsets[None, None, :, None, :]
            positions = expanded.reshape(p_count, n * len(self.sensor_offsets), length, 2)
        if positions.shape[2] < n_steps.max(initial=0):
            raise ValueError("positions shorter than n_steps")
        if self.blocks:
            if len(t0):
                self._ensure(int((t0 + n_steps).max()))
            boxes = self.boxes
            cov, cost, unc = propagate_blocks(
                covariance, self._a, self._q, t0, n_steps, np.ascontiguousarray(positions, dtype=float),
                self._means, self.belief_time, self.measurement_period, self.sensor_height, self.sensing_range,
                boxes.centers, boxes.half_sizes, boxes.rotations, boxes.aligned,
            )
            return Propagation(cov, cost, unc)
        visible, _, _, times = self.readings(t0, n_steps, positions)
        return self._propagate_full(covariance, n_steps, positions, visible, times)

    def _propagate_full(self, cov, n_steps, positions, visible, times) -> Propagation:
        p_count = len(cov)
        cost = np.zeros(p_count)
        for p in range(p_count):
            c = cov[p]
            for step in range(int(n_steps[p])):
                c = covariance_predict(c, self.transition, self.process_noise)
                rows = visible[p, :, step, :]
                keep = rows.any(axis=1)
                if keep.any():
                    sensors = lift(positions[p, keep, step], self.sensor_height)
                    c = covariance_update(c, self.mean(int(times[p, step])), sensors, rows[keep])
                cost[p] += np.linalg.eigvalsh(c)[-1]
            cov[p] = c
        return Propagation(cov, cost, self.target_uncertainty(cov))
