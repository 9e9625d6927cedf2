"""Decentralised estimation of lambda2 and the Fiedler vector (Yang et al. 2010).

Seed 001, Appendix A: "the robots perform a distributed estimation of both
lambda2(t) and nu_2i(t) ... as shown in Yang et al. (2010)". Each robot i
keeps five scalars and updates them from its own values and its neighbours'
through the current weighted adjacency W (W_ij > 0 only for linked robots):

    x_i   its component of a vector driven towards the Fiedler eigenvector by
          a continuous-time power iteration with deflation and normalisation,
              x_i' = -k1 y1_i - k2 sum_j W_ij (x_i - x_j) - k3 (y2_i - 1) x_i
    y1_i, z1_i   PI average-consensus estimate of Ave(x)   (input a_i = x_i)
    y2_i, z2_i   PI average-consensus estimate of Ave(x^2) (input a_i = x_i^2)
              y_i' = gamma (a_i - y_i) - K_P sum_j W_ij (y_i - y_j) + K_I sum_j W_ij (z_i - z_j)
              z_i' = -K_I sum_j W_ij (y_i - y_j)               (Freeman et al. 2006)

At the equilibrium x = +-v2 with Ave(x^2) = 1 - k2 lambda2 / k3, so robot i's
estimates are lambda2_i = (k3 / k2) (1 - y2_i) and, since ||x||^2 = N Ave(x^2),
the unit-norm eigenvector component nu_2i = x_i / sqrt(N y2_i). N is assumed
known to every robot, as in Yang et al.

Discretisation: forward Euler, one substep per neighbour message exchange,
with W held over the control period. The substep is the shorter of
``max_substep`` and half the explicit-Euler stability limit of the
estimator's linear part, which depends on the largest Laplacian eigenvalue;
its Gershgorin bound 2 max_i sum_j W_ij is used.

Use in closed loop
------------------
The connectivity force is sensitive to lag in the eigenvector estimate: in
our simulations a six-robot chain dragged by a 10 N pull (office preset,
k_lambda = 10 J) already goes unstable when the *exact* Fiedler vector
reaches the controller 50 ms late. The default gains converge in about 1-3 s, which holds moderate
pulls (the 3 N test in tests/test_connectivity_dynamics.py) but not strong
ones; faster gains cost proportionally more substeps. The exact oracle
(``connectivity_layer_force`` without an estimate) is the reference.

Deviations from the paper
-------------------------
- The paper (and Yang et al.) state the estimator in continuous time; the
  substep rule above is our discretisation. It stands for a message rate high
  enough for the estimator (the paper's controller ran at 1 kHz).
- The eigenvector estimate is normalised by each robot's own y2_i; before
  convergence y2_i may be near or below zero, so it is floored at a small
  positive value for that division.
- Each robot adds white noise of intensity ``dither`` to x_i (see
  FiedlerEstimatorParams), as quantised messages and sensing noise would in
  a real team; without it the estimator can lock onto the constant vector
  after saturating on a dense, symmetric graph.
- The substep count is taken from the global Gershgorin bound (a simulator
  choice; a real robot would fix its message rate for the densest graph it
  expects).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from controllers.connectivity.params import FiedlerEstimatorParams

# Floor for Ave(x^2) when normalising the eigenvector estimate (unit: x^2).
_MIN_SQUARE_MEAN = 1e-6
# Fraction of the explicit-Euler stability limit used as the substep.
_STABILITY_FRACTION = 0.5


@dataclass(frozen=True)
class FiedlerEstimate:
    """What each robot believes, (N,) arrays.

    lambda2: robot i's estimate of lambda2 (weight units).
    fiedler: robot i's estimate of its own unit-norm Fiedler-vector component.
    """

    lambda2: np.ndarray
    fiedler: np.ndarray


class FiedlerEstimator:
    """Batched state of the N per-robot estimators; ``step`` advances all of them."""

    def __init__(self, num_robots: int, params: FiedlerEstimatorParams, rng: np.random.Generator):
        if num_robots < 2:
            raise ValueError(f"num_robots must be at least 2, got {num_robots}")
        self.num_robots = num_robots
        self.params = params
        self.reset(rng)

    def reset(self, rng: np.random.Generator) -> None:
        """Random eigenvector guess (almost surely not orthogonal to v2); the
        consensus estimates start at each robot's own input."""
        self._rng = rng
        self.eigenvector = rng.standard_normal(self.num_robots)
        self.mean = self.eigenvector.copy()
        self.mean_integral = np.zeros(self.num_robots)
        self.square_mean = self.eigenvector**2
        self.square_mean_integral = np.zeros(self.num_robots)

    @property
    def estimate(self) -> FiedlerEstimate:
        p = self.params
        lambda2 = p.normalisation_gain / p.laplacian_gain * (1.0 - self.square_mean)
        norm = np.sqrt(self.num_robots * np.maximum(self.square_mean, _MIN_SQUARE_MEAN))
        return FiedlerEstimate(lambda2=lambda2, fiedler=self.eigenvector / norm)

    def substep_count(self, weights: np.ndarray, dt: float) -> int:
        """Euler substeps used for a control period ``dt`` (s) under ``weights``."""
        p = self.params
        laplacian_bound = 2.0 * float(weights.sum(axis=1).max())
        damping = p.consensus_input_gain + p.consensus_proportional_gain * laplacian_bound
        # Per Laplacian mode mu the PI block has trace -(gamma + K_P mu) and
        # determinant K_I^2 mu^2; Euler is stable for h < 2 Re(-s) / |s|^2.
        limit = 2.0 / damping
        if laplacian_bound > 0:
            limit = min(limit, damping / (p.consensus_integral_gain * laplacian_bound) ** 2)
        power_rate = p.mean_removal_gain + p.normalisation_gain * max(1.0, float(np.abs(self.square_mean - 1).max()))
        limit = min(limit, 2.0 / (power_rate + p.laplacian_gain * laplacian_bound))
        substep = min(p.max_substep, _STABILITY_FRACTION * limit)
        return max(1, math.ceil(dt / substep))

    def _rate_matrices(self) -> tuple[np.ndarray, np.ndarray]:
        """(5, 5) matrices of the linear part of the rate, columns x, y1, z1, y2, z2:
        rate = state @ local + (L @ state) @ coupling (+ the two products)."""
        p = self.params
        k1, k2, k3 = p.mean_removal_gain, p.laplacian_gain, p.normalisation_gain
        gamma, k_p, k_i = p.consensus_input_gain, p.consensus_proportional_gain, p.consensus_integral_gain
        local = np.zeros((5, 5))
        local[0, 0] = k3  # from -k3 (y2 - 1) x
        local[1, 0] = -k1
        local[0, 1], local[1, 1] = gamma, -gamma
        local[3, 3] = -gamma
        coupling = np.zeros((5, 5))
        coupling[0, 0] = -k2
        coupling[1, 1], coupling[2, 1], coupling[1, 2] = -k_p, k_i, -k_i
        coupling[3, 3], coupling[4, 3], coupling[3, 4] = -k_p, k_i, -k_i
        return local, coupling

    def step(self, weights: np.ndarray, dt: float) -> FiedlerEstimate:
        """Advance all estimators by ``dt`` (s) with the (N, N) weighted adjacency."""
        n = self.num_robots
        weights = np.asarray(weights, dtype=float)
        if weights.shape != (n, n):
            raise ValueError(f"weights must have shape ({n}, {n}), got {weights.shape}")
        if not dt > 0:
            raise ValueError(f"dt must be positive, got {dt}")
        p = self.params
        count = self.substep_count(weights, dt)
        h = dt / count
        laplacian = np.diag(weights.sum(axis=1)) - weights
        k3, gamma = p.normalisation_gain, p.consensus_input_gain
        local, coupling = self._rate_matrices()
        step_local = np.eye(5) + h * local
        step_coupling = h * coupling
        # Columns: x, y1, z1, y2, z2. Row i of laplacian @ state is
        # sum_j W_ij (s_i - s_j): what robot i computes from its neighbours'
        # messages. The rate is laplacian @ state @ coupling + state @ local
        # plus the two products -k3 y2 x and gamma x^2.
        state = np.stack(
            [self.eigenvector, self.mean, self.mean_integral, self.square_mean, self.square_mean_integral], axis=1
        )
        for _ in range(count):
            x, y2 = state[:, 0], state[:, 3]
            product_x = (-h * k3) * x * y2
            product_y2 = (h * gamma) * x * x
            state = state @ step_local + (laplacian @ state) @ step_coupling
            state[:, 0] += product_x
            state[:, 3] += product_y2
        self.eigenvector, self.mean, self.mean_integral, self.square_mean, self.square_mean_integral = (
            np.ascontiguousarray(state.T)
        )
        if p.dither > 0:
            # Each robot's own noise, integrated over the period (Euler-Maruyama).
            self.eigenvector += p.dither * np.sqrt(dt) * self._rng.standard_normal(n)
        return self.estimate
