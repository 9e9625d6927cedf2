"""Decentralised estimation of lambda2 and the Fiedler vector (Yang et al. 2010).

Nestmeyer et al. 2017, Appendix A: "the robots perform a distributed estimation of both
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

Discretisation: the estimator is a continuous-time system (as in Yang et al.)
integrated with W held over the control period, in substeps. The PI
consensus part is linear in (y, z) with a constant Laplacian over the
period, so each substep applies its exact flow with the input a_i held at
the mean of its values at the substep's two ends (its matrix exponential,
computed once per change of the message graph);
the power iteration x takes a forward-Euler substep, the shorter of
``max_substep`` and half its explicit-Euler stability limit (Gershgorin
bound 2 max_i sum_j W_ij of the Laplacian). Integrating the stiff consensus
by Euler instead needs substeps of 1 / (K_I lambda_max(L_c)), some 50 times
more (a 10-robot team: ~1,100 per 10 ms tick).

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
  integration above is our discretisation. Robot i's rates depend only on its
  own and its neighbours' states (``rates``; tested), but over a substep the
  exact consensus flow lets information cross more than one hop, as the
  continuous-time system does: the substep is not one message round.
- The eigenvector estimate is normalised by each robot's own y2_i; before
  convergence y2_i may be near or below zero, so it is floored at a small
  positive value for that division.
- Each robot adds white noise of intensity ``dither`` to x_i (see
  FiedlerEstimatorParams), as quantised messages and sensing noise would in
  a real team; without it the estimator can lock onto the constant vector
  after saturating on a dense, symmetric graph.
- The substep count is taken from the global Gershgorin bound (a simulator
  choice).

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

import copy

import numpy as np
import scipy.linalg

from controllers.connectivity.connected_params import FiedlerEstimatorParams
from controllers.connectivity.smooth_spectrum import _smooth_lambda2_kernel
from sim.compiled import kernel

# Floor for Ave(x^2) when normalising the eigenvector estimate (unit: x^2).
_MIN_SQUARE_MEAN = 1e-6
# Fraction of the explicit-Euler stability limit used as the substep.
_STABILITY_FRACTION = 0.5


def _euler_substeps(params: FiedlerEstimatorParams, weights: np.ndarray, dt: float,
                    normalisation_deviation: float) -> int:
    """Substeps for a control period ``dt`` (s): half the explicit-Euler
    stability limit of the power iteration (Gershgorin bound of the
    Laplacian of ``weights``), at most ``max_substep``.
    ``normalisation_deviation`` bounds |Ave(x^2) - 1|."""
    p = params
    laplacian_bound = 2.0 * float(weights.sum(axis=1).max())
    power_rate = p.mean_removal_gain + p.normalisation_gain * max(1.0, normalisation_deviation)
    limit = 2.0 / (power_rate + p.laplacian_gain * laplacian_bound)
    substep = min(p.max_substep, _STABILITY_FRACTION * limit)
    return max(1, math.ceil(dt / substep))


class _ConsensusFlow:
    """Exact flow over one substep h of the PI average consensus of every channel,

        y' = gamma (a - y) - K_P L_c y + K_I L_c z,   z' = -K_I L_c y,

    with L_c and the input a held: [y; z] <- transition [y; z] + inflow a.
    The matrices are the blocks of expm(h [[A, B], [0, 0]]) (A the (2N, 2N)
    system matrix, B = [gamma I; 0]), recomputed only when L_c or h change
    (the message graph changes far less often than every tick)."""

    def __init__(self, params: FiedlerEstimatorParams):
        self.params = params
        self._key: tuple[bytes, float] | None = None

    def matrices(self, consensus_laplacian: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
        key = (consensus_laplacian.tobytes(), h)
        if key != self._key:
            p = self.params
            n = len(consensus_laplacian)
            system = np.zeros((3 * n, 3 * n))
            identity = np.eye(n)
            system[:n, :n] = -p.consensus_input_gain * identity - p.consensus_proportional_gain * consensus_laplacian
            system[:n, n:2 * n] = p.consensus_integral_gain * consensus_laplacian
            system[n:2 * n, :n] = -p.consensus_integral_gain * consensus_laplacian
            system[:n, 2 * n:] = p.consensus_input_gain * identity
            flow = scipy.linalg.expm(h * system)
            self._matrices = (np.ascontiguousarray(flow[:2 * n, :2 * n]), np.ascontiguousarray(flow[:2 * n, 2 * n:]))
            self._key = key
        return self._matrices


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
        self._flow = _ConsensusFlow(params)
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

    def restricted(self, keep: np.ndarray) -> "FiedlerEstimator":
        """The estimator of the robots ``keep`` (bool, N) selects, their states carried over; the PI
        consensus integrals restart at 0, as their sum must (else the averages stay biased)."""
        out = copy.copy(self)
        out.num_robots = int(np.count_nonzero(keep))
        out._flow = _ConsensusFlow(self.params)
        out.eigenvector, out.mean, out.square_mean = (a[keep].copy() for a in (self.eigenvector, self.mean,
                                                                               self.square_mean))
        out.mean_integral, out.square_mean_integral = np.zeros(out.num_robots), np.zeros(out.num_robots)
        return out

    @property
    def estimate(self) -> FiedlerEstimate:
        p = self.params
        lambda2 = p.normalisation_gain / p.laplacian_gain * (1.0 - self.square_mean)
        norm = np.sqrt(self.num_robots * np.maximum(self.square_mean, _MIN_SQUARE_MEAN))
        return FiedlerEstimate(lambda2=lambda2, fiedler=self.eigenvector / norm)

    def substep_count(self, weights: np.ndarray, dt: float) -> int:
        """Substeps used for a control period ``dt`` (s) under ``weights``."""
        return _euler_substeps(self.params, weights, dt, float(np.abs(self.square_mean - 1).max()))

    def rates(self, weights: np.ndarray, consensus_weights: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The continuous-time estimator: time derivatives (N,) of each robot's
        five scalars, named as the attributes. Row i of L @ s is
        sum_j W_ij (s_i - s_j): robot i's own and its neighbours' values only."""
        p = self.params
        _, laplacian, consensus_laplacian, _ = _checked_laplacians(self.num_robots, weights, 1.0, consensus_weights)
        x, y1, z1, y2, z2 = (self.eigenvector, self.mean, self.mean_integral, self.square_mean,
                             self.square_mean_integral)
        gamma, k_p, k_i = p.consensus_input_gain, p.consensus_proportional_gain, p.consensus_integral_gain
        return {
            "eigenvector": -p.mean_removal_gain * y1 - p.laplacian_gain * (laplacian @ x)
            - p.normalisation_gain * (y2 - 1.0) * x,
            "mean": gamma * (x - y1) - k_p * (consensus_laplacian @ y1) + k_i * (consensus_laplacian @ z1),
            "mean_integral": -k_i * (consensus_laplacian @ y1),
            "square_mean": gamma * (x * x - y2) - k_p * (consensus_laplacian @ y2) + k_i * (consensus_laplacian @ z2),
            "square_mean_integral": -k_i * (consensus_laplacian @ y2),
        }

    def step(self, weights: np.ndarray, dt: float, consensus_weights: np.ndarray | None = None) -> FiedlerEstimate:
        """Advance all estimators by ``dt`` (s) with the (N, N) weighted adjacency.

        ``consensus_weights`` (default: ``weights``) are the link weights the
        two average-consensus estimators use. Any connected message graph
        gives the same averages; the power iteration always uses ``weights``
        (whose lambda2 is being estimated)."""
        n = self.num_robots
        weights, laplacian, consensus_laplacian, _ = _checked_laplacians(n, weights, dt, consensus_weights)
        p = self.params
        count = self.substep_count(weights, dt)
        h = dt / count
        k1, k2, k3 = p.mean_removal_gain, p.laplacian_gain, p.normalisation_gain
        transition, inflow = self._flow.matrices(consensus_laplacian, h)
        x = self.eigenvector
        # Consensus state: rows y (N), then z (N); columns: the Ave(x) and Ave(x^2) channels.
        consensus = np.concatenate([np.stack([self.mean, self.square_mean], axis=1),
                                    np.stack([self.mean_integral, self.square_mean_integral], axis=1)])
        inputs = np.stack([x, x * x], axis=1)
        for _ in range(count):
            y1, y2 = consensus[:n, 0], consensus[:n, 1]
            x = x - h * (k1 * y1 + k2 * (laplacian @ x) + k3 * (y2 - 1.0) * x)
            # The consensus input over the substep: mean of its values at both ends (second order).
            next_inputs = np.stack([x, x * x], axis=1)
            consensus = transition @ consensus + inflow @ (0.5 * (inputs + next_inputs))
            inputs = next_inputs
        self.eigenvector = x
        self.mean, self.square_mean = np.ascontiguousarray(consensus[:n].T)
        self.mean_integral, self.square_mean_integral = np.ascontiguousarray(consensus[n:].T)
        if p.dither > 0:
            # Each robot's own noise, integrated over the period (Euler-Maruyama).
            self.eigenvector = self.eigenvector + p.dither * np.sqrt(dt) * self._rng.standard_normal(n)
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
        self._flow = _ConsensusFlow(params)
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

    def restricted(self, keep: np.ndarray) -> "SubspaceEstimator":
        """The estimator of the robots ``keep`` (bool, N) selects (see FiedlerEstimator.restricted)."""
        out = copy.copy(self)
        out.num_robots = int(np.count_nonzero(keep))
        out._flow = _ConsensusFlow(self.params)
        out.components, out.consensus = self.components[keep].copy(), self.consensus[keep].copy()
        out.consensus_integral = np.zeros_like(out.consensus)
        return out

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
        values, valid = np.empty((n, k)), np.empty((n, k), dtype=np.bool_)
        coefficients, fiedler, lambda2 = np.empty((n, k, k)), np.empty(n), np.empty(n)
        components = np.ascontiguousarray(self.components, dtype=float)
        _rayleigh_ritz(np.ascontiguousarray(self.consensus, dtype=float), components, self._gram_index.astype(np.int64),
                       self._projected_slice.start, self.params.lambda2_ceiling, values, valid, coefficients, fiedler,
                       lambda2)
        return SubspaceEstimate(lambda2=lambda2, values=values, valid=valid, coefficients=coefficients,
                                components=components.copy(), fiedler=fiedler)

    def substep_count(self, weights: np.ndarray, dt: float) -> int:
        """Substeps for a control period ``dt`` (s): FiedlerEstimator's rule."""
        deviation = np.abs(self.gram - np.eye(self.modes)[None]).sum(axis=2).max()
        return _euler_substeps(self.params, weights, dt, float(deviation))

    def _power_rate(self, x: np.ndarray, lx: np.ndarray, y: np.ndarray) -> np.ndarray:
        """X_i' = -k1 m_i - k2 (L X)_i - k3 X_i (G_i - I), (N, K)."""
        p = self.params
        n, k = self.num_robots, self.modes
        gram = y[:, self._gram_index].reshape(n, k, k)
        return (p.normalisation_gain * x - p.mean_removal_gain * y[:, :k] - p.laplacian_gain * lx
                - p.normalisation_gain * np.matmul(x[:, None, :], gram)[:, 0, :])

    def rates(self, weights: np.ndarray, consensus_weights: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """The continuous-time estimator: time derivatives of ``components``
        (N, K), ``consensus`` and ``consensus_integral`` (N, D). Row i depends
        only on robot i's own and its neighbours' states."""
        p = self.params
        _, laplacian, consensus_laplacian, _ = _checked_laplacians(self.num_robots, weights, 1.0, consensus_weights)
        x, y, z = self.components, self.consensus, self.consensus_integral
        lx = laplacian @ x
        ly, lz = consensus_laplacian @ y, consensus_laplacian @ z
        return {
            "components": self._power_rate(x, lx, y),
            "consensus": p.consensus_input_gain * (self._inputs(x, lx) - y) - p.consensus_proportional_gain * ly
            + p.consensus_integral_gain * lz,
            "consensus_integral": -p.consensus_integral_gain * ly,
        }

    def step(self, weights: np.ndarray, dt: float, consensus_weights: np.ndarray | None = None) -> SubspaceEstimate:
        """Advance all robots by ``dt`` (s); arguments as FiedlerEstimator.step."""
        n, k = self.num_robots, self.modes
        weights, laplacian, consensus_laplacian, _ = _checked_laplacians(n, weights, dt, consensus_weights)
        p = self.params
        count = self.substep_count(weights, dt)
        h = dt / count
        transition, inflow = self._flow.matrices(consensus_laplacian, h)
        consensus = np.concatenate([self.consensus, self.consensus_integral])  # rows: y (N), then z (N)
        x = _subspace_substeps(np.array(self.components, dtype=float), consensus, laplacian, transition, inflow,
                               h, count, p.normalisation_gain, p.mean_removal_gain, p.laplacian_gain,
                               self._gram_index, self._input_left, self._input_right)
        if p.dither > 0:
            x = x + p.dither * np.sqrt(dt) * self._rng.standard_normal((n, k))
        self.components = x
        self.consensus, self.consensus_integral = consensus[:n].copy(), consensus[n:].copy()
        return self.estimate


@kernel
def _subspace_substeps(x, consensus, laplacian, transition, inflow, h, count, normalisation_gain, mean_removal_gain,
                       laplacian_gain, gram_index, input_left, input_right):
    """SubspaceEstimator's ``count`` Euler substeps of length ``h`` in one compiled pass: x (N, K) and
    consensus (2N, D: rows y, then z) advance in place; returns x. Per substep, with the Laplacian L of
    the weights, the consensus flow (transition (2N, 2N), inflow (2N, N)) and the inputs' columns
    [X, L X, 1] (``input_left`` * ``input_right``):
        X <- X + h (k3 X - k1 m - k2 L X - k3 X G),   y, z <- transition [y; z] + inflow (inputs then + now) / 2.
    Sums run in index order (numpy's BLAS matmul may group them otherwise: round-off differs)."""
    n, k = x.shape
    channels = consensus.shape[1]
    rows = consensus.shape[0]
    lx = np.empty((n, k))
    columns = np.empty((n, 2 * k + 1))
    inputs = np.empty((n, channels))
    mixed = np.empty((n, channels))
    updated = np.empty((rows, channels))
    average = np.empty((n, channels))

    def laplacian_times(x, lx):
        for i in range(n):
            for a in range(k):
                lx[i, a] = 0.0
            for j in range(n):
                factor = laplacian[i, j]
                for a in range(k):
                    lx[i, a] += factor * x[j, a]

    def consensus_inputs(x, lx, out):
        for i in range(n):
            for a in range(k):
                columns[i, a] = x[i, a]
                columns[i, k + a] = lx[i, a]
            columns[i, 2 * k] = 1.0
            for d in range(channels):
                out[i, d] = columns[i, input_left[d]] * columns[i, input_right[d]]

    laplacian_times(x, lx)
    consensus_inputs(x, lx, inputs)
    rate = np.empty((n, k))
    for _ in range(count):
        for i in range(n):
            for a in range(k):
                projected = 0.0
                for b in range(k):
                    projected += x[i, b] * consensus[i, gram_index[b * k + a]]
                rate[i, a] = (normalisation_gain * x[i, a] - mean_removal_gain * consensus[i, a]
                              - laplacian_gain * lx[i, a] - normalisation_gain * projected)
        for i in range(n):
            for a in range(k):
                x[i, a] = x[i, a] + h * rate[i, a]
        laplacian_times(x, lx)
        consensus_inputs(x, lx, mixed)  # the next inputs
        for c in range(n):
            for d in range(channels):
                average[c, d] = 0.5 * (inputs[c, d] + mixed[c, d])
        for r in range(rows):
            for d in range(channels):
                updated[r, d] = 0.0
            for c in range(rows):
                factor = transition[r, c]
                for d in range(channels):
                    updated[r, d] += factor * consensus[c, d]
            for c in range(n):
                factor = inflow[r, c]
                for d in range(channels):
                    updated[r, d] += factor * average[c, d]
        consensus[:, :] = updated
        inputs[:, :] = mixed
    return x


@kernel
def _rayleigh_ritz(consensus, components, gram_index, projected_start, lambda2_ceiling, values_out, valid_out,
                   coefficients_out, fiedler_out, lambda2_out):
    """Each robot's Rayleigh-Ritz from its consensus estimates (SubspaceEstimator.estimate, row by row):
    whiten the centred Gram estimate, drop the directions it does not span, then the Ritz pairs of the
    projected Laplacian in that basis, each Ritz vector's largest coefficient positive."""
    n, k = components.shape
    centred = np.empty((k, k))
    projected = np.empty((k, k))
    whiten = np.empty((k, k))
    reduced = np.empty((k, k))
    keep = np.empty(k, dtype=np.bool_)
    for i in range(n):
        for a in range(k):
            for b in range(k):
                centred[a, b] = consensus[i, gram_index[a * k + b]] - consensus[i, a] * consensus[i, b]
                projected[a, b] = 0.5 * (consensus[i, projected_start + a * k + b]
                                         + consensus[i, projected_start + b * k + a])
        scale, basis = np.linalg.eigh(centred)
        floor = max(_GRAM_RELATIVE_FLOOR * scale[k - 1], _MIN_GRAM)
        for c in range(k):
            keep[c] = scale[c] > floor
            root = np.sqrt(scale[c] if keep[c] else 1.0)
            for a in range(k):
                whiten[a, c] = basis[a, c] / root * (1.0 if keep[c] else 0.0)
        for c in range(k):
            for d in range(k):
                total = 0.0
                for a in range(k):
                    for b in range(k):
                        total += whiten[a, c] * projected[a, b] * whiten[b, d]
                reduced[c, d] = total
        for c in range(k):
            for d in range(c + 1, k):
                reduced[c, d] = reduced[d, c] = 0.5 * (reduced[c, d] + reduced[d, c])
            if not keep[c]:
                reduced[c, c] += _DROPPED_VALUE
        ritz, rotation = np.linalg.eigh(reduced)
        for c in range(k):
            valid_out[i, c] = ritz[c] < 0.5 * _DROPPED_VALUE
            values_out[i, c] = ritz[c] if valid_out[i, c] else _DROPPED_VALUE
            largest, sign = -1.0, 1.0
            for a in range(k):
                total = 0.0
                for b in range(k):
                    total += whiten[a, b] * rotation[b, c]
                coefficients_out[i, a, c] = total
                if abs(total) > largest:
                    largest, sign = abs(total), (1.0 if total > 0 else (-1.0 if total < 0 else 1.0))
            for a in range(k):
                coefficients_out[i, a, c] *= sign
        total = 0.0
        for a in range(k):
            total += (components[i, a] - consensus[i, a]) * coefficients_out[i, a, 0]
        fiedler_out[i] = total / np.sqrt(n)
        lambda2_out[i] = values_out[i, 0] if valid_out[i, 0] else lambda2_ceiling


def ritz_connectivity_gradient(links, estimate: SubspaceEstimate, kappa: float) -> tuple[np.ndarray, np.ndarray]:
    """Each robot's smooth lambda2 s_i and its own row of ds/dq (N,), (N, 3).

    Robot i takes the soft minimum (smooth_spectrum.smooth_lambda2, kappa;
    kappa = 0: the lowest) of its valid Ritz values and sums, with the
    soft-min weights, eq. (17) for its Ritz vectors u_k, whose components at
    itself and its neighbours it forms from their messages X_j and its own
    coefficients (sign-consistent by construction). ``links`` is a
    graph.LinkWeights (only its ``lambda2_gradient`` is used).
    """
    n, k = estimate.components.shape
    smooth = np.empty(n)
    robots = np.empty(n * k, dtype=np.int64)
    slopes = np.empty(n * k)
    vectors = np.empty((n, n * k))
    count = _ritz_terms(np.ascontiguousarray(estimate.values, dtype=float), np.ascontiguousarray(estimate.valid),
                        np.asarray(estimate.lambda2, dtype=float), np.ascontiguousarray(estimate.components, dtype=float),
                        np.ascontiguousarray(estimate.coefficients, dtype=float), float(kappa), 1.0 / math.sqrt(n),
                        smooth, robots, slopes, vectors)
    gradient = np.zeros((n, 3))
    if count:
        # One batched eq. (17) for all the Ritz vectors; robot i keeps its own row.
        rows = links.lambda2_gradients(vectors[:, :count])
        _add_own_rows(robots[:count], slopes[:count], rows, gradient)
    return smooth, gradient


@kernel
def _ritz_terms(values, valid, lambda2, components, coefficients, kappa, scale, smooth, robots, slopes, vectors):
    """Each robot's soft minimum of its valid Ritz values into ``smooth`` (N,), and its gradient terms:
    for term t, robot ``robots[t]``, soft-min slope ``slopes[t]`` and Ritz vector ``vectors[:, t]`` (N,)
    (terms with a slope above 1e-9 of the robot's largest, in robot then mode order). Returns the term count."""
    n, k = components.shape
    own = np.empty(k)
    slope = np.empty(k)
    mode = np.empty(k, dtype=np.int64)
    count = 0
    for i in range(n):
        m = 0
        for a in range(k):
            if valid[i, a]:
                own[m] = values[i, a]
                mode[m] = a
                m += 1
        if m == 0:
            smooth[i] = lambda2[i]
            continue
        smooth[i] = _smooth_lambda2_kernel(own[:m], kappa, slope[:m])
        top = slope[0]
        for c in range(1, m):
            top = max(top, slope[c])
        for c in range(m):
            if not slope[c] > 1e-9 * top:
                continue
            a = mode[c]
            for r in range(n):
                total = 0.0
                for b in range(k):
                    total += components[r, b] * coefficients[i, b, a]
                vectors[r, count] = total * scale
            robots[count] = i
            slopes[count] = slope[c]
            count += 1
    return count


@kernel
def _add_own_rows(robots, slopes, rows, gradient):
    """gradient[i] += slope_t * rows[t, i] for each term t of robot i, in term order."""
    for t in range(robots.shape[0]):
        i = robots[t]
        for d in range(3):
            gradient[i, d] += slopes[t] * rows[t, i, d]
