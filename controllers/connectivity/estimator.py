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

Several eigenpairs (not in the paper)
-------------------------------------
A single power-iteration vector fails at mode crossings: when a link fades
within a few tenths of a second (a robot passing a wall corner) another
eigenmode can drop below the tracked one, the vector needs a time of order
1 / (k2 (lambda3 - lambda2)) to rotate onto it, and meanwhile its Rayleigh
quotient overestimates lambda2 and the connectivity force pushes the wrong
way. :class:`SubspaceEstimator` iterates K vectors at once (the symmetric
subspace form of the same flow, with consensus on their Gram matrix) and each
robot solves the K x K Rayleigh-Ritz problem from consensus estimates of
Ave(X^T X) and Ave(X^T L X): a crossing between modes inside the subspace is
followed at once. K = 1 has FiedlerEstimator's x, y1, y2 dynamics.
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


def _euler_substeps(params: FiedlerEstimatorParams, weights: np.ndarray, consensus_weights: np.ndarray | None,
                    dt: float, normalisation_deviation: float) -> int:
    """Euler substeps for a control period ``dt`` (s): half the stability limit
    of the estimator's linear part (Gershgorin bounds of both Laplacians), at
    most ``max_substep``. ``normalisation_deviation`` bounds |Ave(x^2) - 1|."""
    p = params
    laplacian_bound = 2.0 * float(weights.sum(axis=1).max())
    consensus_bound = laplacian_bound if consensus_weights is None else 2.0 * float(consensus_weights.sum(axis=1).max())
    damping = p.consensus_input_gain + p.consensus_proportional_gain * consensus_bound
    # Per Laplacian mode mu the PI block has trace -(gamma + K_P mu) and
    # determinant K_I^2 mu^2; Euler is stable for h < 2 Re(-s) / |s|^2.
    limit = 2.0 / damping
    if consensus_bound > 0:
        limit = min(limit, damping / (p.consensus_integral_gain * consensus_bound) ** 2)
    power_rate = p.mean_removal_gain + p.normalisation_gain * max(1.0, normalisation_deviation)
    limit = min(limit, 2.0 / (power_rate + p.laplacian_gain * laplacian_bound))
    substep = min(p.max_substep, _STABILITY_FRACTION * limit)
    return max(1, math.ceil(dt / substep))


def _checked_laplacians(n: int, weights, dt: float, consensus_weights) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                                  np.ndarray | None]:
    """Validate a step's inputs; (weights, Laplacian of weights, consensus
    Laplacian, consensus_weights or None) as float arrays."""
    weights = np.asarray(weights, dtype=float)
    if weights.shape != (n, n):
        raise ValueError(f"weights must have shape ({n}, {n}), got {weights.shape}")
    if consensus_weights is not None:
        consensus_weights = np.asarray(consensus_weights, dtype=float)
        if consensus_weights.shape != (n, n):
            raise ValueError(f"consensus_weights must have shape ({n}, {n}), got {consensus_weights.shape}")
    if not dt > 0:
        raise ValueError(f"dt must be positive, got {dt}")
    laplacian = np.diag(weights.sum(axis=1)) - weights
    consensus_laplacian = laplacian if consensus_weights is None else (
        np.diag(consensus_weights.sum(axis=1)) - consensus_weights)
    return weights, laplacian, consensus_laplacian, consensus_weights


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

    def substep_count(self, weights: np.ndarray, dt: float, consensus_weights: np.ndarray | None = None) -> int:
        """Euler substeps used for a control period ``dt`` (s) under ``weights``
        (and ``consensus_weights`` for the averaging, default ``weights``)."""
        return _euler_substeps(self.params, weights, consensus_weights, dt,
                               float(np.abs(self.square_mean - 1).max()))

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

    def step(self, weights: np.ndarray, dt: float, consensus_weights: np.ndarray | None = None) -> FiedlerEstimate:
        """Advance all estimators by ``dt`` (s) with the (N, N) weighted adjacency.

        ``consensus_weights`` (default: ``weights``) are the link weights the
        two average-consensus estimators use. Any connected message graph
        gives the same averages; the power iteration always uses ``weights``
        (whose lambda2 is being estimated)."""
        n = self.num_robots
        weights, laplacian, consensus_laplacian, consensus_weights = _checked_laplacians(
            n, weights, dt, consensus_weights)
        p = self.params
        count = self.substep_count(weights, dt, consensus_weights)
        h = dt / count
        k2, k3, gamma = p.laplacian_gain, p.normalisation_gain, p.consensus_input_gain
        local, coupling = self._rate_matrices()
        coupling[0, 0] = 0.0  # the power iteration's -k2 L x is added separately (it uses W)
        step_local = np.eye(5) + h * local
        step_coupling = h * coupling
        power_step = -h * k2 * laplacian
        # Columns: x, y1, z1, y2, z2. Row i of laplacian @ state is
        # sum_j W_ij (s_i - s_j): what robot i computes from its neighbours'
        # messages. The rate is consensus_laplacian @ state @ coupling +
        # state @ local - k2 laplacian @ x plus the two products -k3 y2 x and
        # gamma x^2.
        state = np.stack(
            [self.eigenvector, self.mean, self.mean_integral, self.square_mean, self.square_mean_integral], axis=1
        )
        for _ in range(count):
            x, y2 = state[:, 0], state[:, 3]
            product_x = (-h * k3) * x * y2 + power_step @ x
            product_y2 = (h * gamma) * x * x
            state = state @ step_local + (consensus_laplacian @ state) @ step_coupling
            state[:, 0] += product_x
            state[:, 3] += product_y2
        self.eigenvector, self.mean, self.mean_integral, self.square_mean, self.square_mean_integral = (
            np.ascontiguousarray(state.T)
        )
        if p.dither > 0:
            # Each robot's own noise, integrated over the period (Euler-Maruyama).
            self.eigenvector += p.dither * np.sqrt(dt) * self._rng.standard_normal(n)
        return self.estimate


# ---------------------------------------------------------------------------
# Several eigenpairs: decentralised subspace iteration with Rayleigh-Ritz.
# ---------------------------------------------------------------------------
# Centred-Gram eigenvalues below this fraction of the largest (or below
# _MIN_GRAM absolutely) are directions the K vectors do not span reliably.
_GRAM_RELATIVE_FLOOR = 1e-2
_MIN_GRAM = 1e-3
# Ritz value reported for a direction that was dropped (weight units): above any
# lambda the soft minimum can weigh.
_DROPPED_VALUE = 1e6


@dataclass(frozen=True)
class SubspaceEstimate:
    """What each robot believes about the K lowest non-trivial eigenpairs.

    lambda2: (N,) robot i's estimate of lambda2 (its lowest Ritz value).
    values: (N, K) robot i's Ritz values, ascending (``_DROPPED_VALUE`` where a
        direction was dropped, see ``valid``).
    valid: (N, K) bool, Ritz value k of robot i is backed by the subspace.
    coefficients: (N, K, K) robot i's Ritz coefficients C_i: its estimate of
        the unit-norm Ritz vector k is u_k = (X - 1 m^T) C_i[:, k] / sqrt(N), so
        u_k,j - u_k,l = (X_j - X_l) C_i[:, k] / sqrt(N) from neighbours' X_j.
    components: (N, K) the iterated vectors X (row i: robot i's, which it sends).
    fiedler: (N,) robot i's own component of its first Ritz vector (sign of
        each robot's Ritz vector fixed by its own coefficients: diagnostics only).
    """

    lambda2: np.ndarray
    values: np.ndarray
    valid: np.ndarray
    coefficients: np.ndarray
    components: np.ndarray
    fiedler: np.ndarray


class SubspaceEstimator:
    """K-vector generalisation of :class:`FiedlerEstimator` (not in the paper).

    Robot i keeps a row X_i of K components, X (N, K), driven by the
    subspace (symmetric Oja) form of Yang et al.'s power iteration,

        X_i' = -k1 m_i - k2 sum_j W_ij (X_i - X_j) - k3 X_i (G_i - I),

    with PI average-consensus estimates (same loop as FiedlerEstimator) of

        m_i ~ Ave(X)             (K channels: deflation of the constant vector)
        G_i ~ Ave(X^T X)         (K(K+1)/2: normalisation and mutual orthogonalisation)
        P_i ~ Ave(X^T L X)       (K^2: input at robot i is X_i^T (L X)_i, local
                                  from neighbours' X_j; symmetrised on use)

    For K = 1 the X, m, G equations are FiedlerEstimator's x, y1, y2. The
    equilibria have L X = X M with M = (k3 / k2)(I - G): X spans an invariant
    subspace, the one of the K lowest non-trivial eigenvalues being the stable
    one (needs k1, k3 > k2 lambda_{K+1}); rotations inside it are neutral.
    Rayleigh-Ritz on the estimates: the centred Gram matrix
    Gc_i = G_i - m_i m_i^T and P_i give robot i the K x K generalized
    eigenproblem P_i c = theta Gc_i c; its theta are the Ritz values (with exact
    averages: upper bounds of lambda_2..lambda_{K+1}, exact when X spans the
    eigenvectors)
    and c the Ritz coefficients. Unlike a single vector, a crossing of
    eigenvalues whose modes are both in the subspace is followed
    instantly (the Ritz values swap); a mode entering from outside still
    needs the subspace to rotate, at rate k2 (lambda_{K+2} - lambda_new).
    Directions of Gc below 1 % of its largest eigenvalue (or 1e-3) are
    dropped before the eigenproblem (a vector that saturated onto the
    constant vector, above the ceiling).

    Discretisation, dither and substeps as FiedlerEstimator; the power-iteration
    stability bound uses max_i ||G_i - I||_inf.
    """

    def __init__(self, num_robots: int, params: FiedlerEstimatorParams, rng: np.random.Generator, modes: int = 2):
        if num_robots < 2:
            raise ValueError(f"num_robots must be at least 2, got {num_robots}")
        if not (isinstance(modes, (int, np.integer)) and 1 <= modes < num_robots):
            raise ValueError(f"modes must be an integer in [1, {num_robots - 1}], got {modes!r}")
        self.num_robots = num_robots
        self.modes = int(modes)
        self.params = params
        k = self.modes
        self._pairs = np.triu_indices(k)  # (a, b), a <= b: the Gram channels
        self._pair_count = len(self._pairs[0])
        self.reset(rng)

    # Consensus channels (columns of ``consensus``, N x D): m (K), G's upper triangle (K(K+1)/2), and the
    # full K x K inputs of P, X_ia (L X)_ib (their averages form a symmetric matrix; symmetrised on use).
    def _layout(self) -> None:
        k = self.modes
        a, b = self._pairs
        self._gram_slice = slice(k, k + self._pair_count)
        self._projected_slice = slice(k + self._pair_count, k + self._pair_count + k * k)
        self.channels = k + self._pair_count + k * k
        # Column of the G channel holding G_ab, for the (K, K) matrix.
        gram_index = np.empty((k, k), dtype=int)
        gram_index[a, b] = k + np.arange(self._pair_count)
        gram_index[b, a] = gram_index[a, b]
        self._gram_index = gram_index.ravel()
        # Inputs as products of columns of [X, L X, 1]: m_a <- X_a * 1, G_ab <- X_a X_b, P_ab <- X_a (L X)_b.
        one = 2 * k
        rows, cols = np.divmod(np.arange(k * k), k)
        self._input_left = np.concatenate([np.arange(k), a, rows])
        self._input_right = np.concatenate([np.full(k, one), b, k + cols])

    def reset(self, rng: np.random.Generator) -> None:
        self._rng = rng
        n, k = self.num_robots, self.modes
        self._layout()
        self.components = rng.standard_normal((n, k))
        x = self.components
        self.consensus = self._inputs(x, np.zeros_like(x))
        self.consensus_integral = np.zeros_like(self.consensus)

    def _inputs(self, x: np.ndarray, lx: np.ndarray) -> np.ndarray:
        """(N, D) robot i's consensus inputs from its X_i and (L X)_i."""
        columns = np.concatenate([x, lx, np.ones((len(x), 1))], axis=1)
        return columns[:, self._input_left] * columns[:, self._input_right]

    @property
    def mean(self) -> np.ndarray:
        """(N, K) robot i's estimate of Ave(X)."""
        return self.consensus[:, : self.modes]

    @property
    def gram(self) -> np.ndarray:
        """(N, K, K) robot i's estimate of Ave(X^T X)."""
        k = self.modes
        return self.consensus[:, self._gram_index].reshape(-1, k, k)

    @property
    def projected(self) -> np.ndarray:
        """(N, K, K) robot i's estimate of Ave(X^T L X) (symmetrised)."""
        k = self.modes
        full = self.consensus[:, self._projected_slice].reshape(-1, k, k)
        return 0.5 * (full + np.swapaxes(full, 1, 2))

    @property
    def estimate(self) -> SubspaceEstimate:
        n, k = self.num_robots, self.modes
        mean = self.mean
        centred_gram = self.gram - mean[:, :, None] * mean[:, None, :]
        projected = self.projected
        scale, basis = np.linalg.eigh(centred_gram)
        keep = scale > np.maximum(_GRAM_RELATIVE_FLOOR * scale[:, -1:], _MIN_GRAM)
        whiten = basis / np.sqrt(np.where(keep, scale, 1.0))[:, None, :] * keep[:, None, :]
        reduced = np.einsum("nak,nab,nbl->nkl", whiten, projected, whiten)
        reduced = 0.5 * (reduced + np.swapaxes(reduced, 1, 2))
        reduced += np.eye(k)[None] * np.where(keep, 0.0, _DROPPED_VALUE)[:, None, :]
        values, rotation = np.linalg.eigh(reduced)
        coefficients = whiten @ rotation
        valid = values < 0.5 * _DROPPED_VALUE
        values = np.where(valid, values, _DROPPED_VALUE)
        # Sign of each Ritz vector: its largest coefficient positive (K = 1: C > 0).
        index = np.abs(coefficients).argmax(axis=1)
        sign = np.sign(np.take_along_axis(coefficients, index[:, None, :], axis=1))
        coefficients = coefficients * np.where(sign == 0, 1.0, sign)
        fiedler = np.einsum("na,na->n", self.components - mean, coefficients[:, :, 0]) / math.sqrt(n)
        lambda2 = np.where(valid[:, 0], values[:, 0], self.params.lambda2_ceiling)
        return SubspaceEstimate(lambda2=lambda2, values=values, valid=valid, coefficients=coefficients,
                                components=self.components.copy(), fiedler=fiedler)

    def substep_count(self, weights: np.ndarray, dt: float, consensus_weights: np.ndarray | None = None) -> int:
        """Euler substeps for a control period ``dt`` (s): FiedlerEstimator's rule."""
        deviation = np.abs(self.gram - np.eye(self.modes)[None]).sum(axis=2).max()
        return _euler_substeps(self.params, weights, consensus_weights, dt, float(deviation))

    def step(self, weights: np.ndarray, dt: float, consensus_weights: np.ndarray | None = None) -> SubspaceEstimate:
        """Advance all robots by ``dt`` (s); arguments as FiedlerEstimator.step."""
        n, k = self.num_robots, self.modes
        weights, laplacian, consensus_laplacian, consensus_weights = _checked_laplacians(
            n, weights, dt, consensus_weights)
        p = self.params
        count = self.substep_count(weights, dt, consensus_weights)
        h = dt / count
        k1, k2, k3 = p.mean_removal_gain, p.laplacian_gain, p.normalisation_gain
        gamma, k_p, k_i = p.consensus_input_gain, p.consensus_proportional_gain, p.consensus_integral_gain
        d = self.channels
        x = self.components
        y, z = self.consensus.copy(), self.consensus_integral.copy()
        ones = np.ones((n, 1))
        left, right, gram_index = self._input_left, self._input_right, self._gram_index
        h_gamma, h_kp, h_ki = h * gamma, h * k_p, h * k_i
        for _ in range(count):
            lx = laplacian @ x  # row i: sum_j W_ij (X_i - X_j), from neighbours' messages
            columns = np.concatenate([x, lx, ones], axis=1)
            inputs = columns[:, left] * columns[:, right]
            gram = y[:, gram_index].reshape(n, k, k)
            # X_i' = -k1 m_i - k2 (L X)_i - k3 X_i (G_i - I)
            x = (1.0 + h * k3) * x - (h * k1) * y[:, :k] - (h * k2) * lx - (h * k3) * np.matmul(
                x[:, None, :], gram)[:, 0, :]
            # PI consensus: y' = gamma (a - y) - K_P L_c y + K_I L_c z,  z' = -K_I L_c y
            ly = consensus_laplacian @ y
            lz = consensus_laplacian @ z
            y += h_gamma * (inputs - y) - h_kp * ly + h_ki * lz
            z -= h_ki * ly
        if p.dither > 0:
            x = x + p.dither * np.sqrt(dt) * self._rng.standard_normal((n, k))
        self.components, self.consensus, self.consensus_integral = x, y, z
        return self.estimate


def ritz_connectivity_gradient(links, estimate: SubspaceEstimate, kappa: float) -> tuple[np.ndarray, np.ndarray]:
    """Each robot's smooth lambda2 s_i and its own row of ds/dq (N,), (N, 3).

    Robot i takes the soft minimum (smooth_spectrum.smooth_lambda2, kappa;
    kappa = 0: the lowest) of its valid Ritz values and sums, with the
    soft-min weights, eq. (17) for its Ritz vectors u_k, whose components at
    itself and its neighbours it forms from their messages X_j and its own
    coefficients (sign-consistent by construction). ``links`` is a
    graph.LinkWeights (only its ``lambda2_gradient`` is used).
    """
    from controllers.connectivity.smooth_spectrum import smooth_lambda2

    n = len(estimate.lambda2)
    smooth = np.zeros(n)
    gradient = np.zeros((n, 3))
    scale = 1.0 / math.sqrt(n)
    for i in range(n):
        valid = estimate.valid[i]
        if not valid.any():
            smooth[i] = estimate.lambda2[i]
            continue
        values = estimate.values[i, valid]
        s, slope = smooth_lambda2(np.concatenate([[0.0], values]), kappa)
        smooth[i] = s
        vectors = estimate.components @ estimate.coefficients[i][:, valid] * scale
        for k in np.flatnonzero(slope > 1e-9 * slope.max()):
            gradient[i] += slope[k] * links.lambda2_gradient(vectors[:, k])[i]
    return smooth, gradient
