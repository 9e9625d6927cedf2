"""Decentralised lambda2 / Fiedler-vector estimator (Yang et al. 2010) against
numpy eigh of the same weighted Laplacian."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.connectivity.estimator import FiedlerEstimator
from controllers.connectivity.graph import fiedler_pair, link_weights, weighted_laplacian
from controllers.connectivity.params import ConnectivityParams, FiedlerEstimatorParams

GAINS = FiedlerEstimatorParams()
OFFICE = ConnectivityParams.office()
DT = 0.01  # s, the simulator's control period


def sensor_graph(seed: int, n: int) -> np.ndarray:
    """Weights of a random connected office team (0.9-2.2 m spacing) whose
    lambda2 lies below the estimator's ceiling and is separated from lambda3."""
    rng = np.random.default_rng(seed)
    while True:
        positions = [np.zeros(3)]
        while len(positions) < n:
            direction = rng.normal(size=3)
            candidate = positions[rng.integers(len(positions))] + rng.uniform(0.9, 2.2) * direction / np.linalg.norm(
                direction
            )
            if min(np.linalg.norm(candidate - p) for p in positions) > 1.05 * OFFICE.min_robot_distance:
                positions.append(candidate)
        weights = link_weights(np.array(positions), None, OFFICE).weights
        eigenvalues = np.linalg.eigvalsh(weighted_laplacian(weights))
        if 0.1 < eigenvalues[1] < 0.8 * GAINS.lambda2_ceiling and eigenvalues[2] - eigenvalues[1] > 0.1:
            return weights


def run(estimator: FiedlerEstimator, weights, seconds: float):
    for _ in range(round(seconds / DT)):
        estimate = estimator.step(weights, DT)
    return estimate


def sign_aligned(estimate: np.ndarray, reference: np.ndarray) -> np.ndarray:
    return estimate if estimate @ reference >= 0 else -estimate


@pytest.mark.parametrize("seed, n", [(0, 6), (1, 8), (2, 10), (3, 12)])
def test_converges_to_exact_lambda2_and_fiedler_vector(seed, n):
    weights = sensor_graph(seed, n)
    lambda2, fiedler = fiedler_pair(weighted_laplacian(weights))
    estimator = FiedlerEstimator(n, GAINS, np.random.default_rng(seed))
    estimate = run(estimator, weights, 8.0)
    # Every robot's own lambda2 estimate is within 2 % of eigh's.
    np.testing.assert_allclose(estimate.lambda2, lambda2, rtol=0.02)
    # The per-robot components form the unit-norm Fiedler vector up to sign.
    aligned = sign_aligned(estimate.fiedler, fiedler)
    assert abs(estimate.fiedler @ fiedler) / np.linalg.norm(estimate.fiedler) > 0.999
    np.testing.assert_allclose(aligned, fiedler, atol=0.02)


def test_tracks_a_slowly_varying_graph():
    n = 8
    base = sensor_graph(11, n)
    phases = np.random.default_rng(4).uniform(0, 2 * np.pi, (n, n))
    phases = np.triu(phases, 1) + np.triu(phases, 1).T

    def weights_at(t):
        # Each link's weight breathes by +-25 % with its own phase, period ~12 s.
        return base * (1.0 + 0.25 * np.sin(0.5 * t + phases))

    estimator = FiedlerEstimator(n, GAINS, np.random.default_rng(0))
    errors, alignments, lambdas = [], [], []
    for k in range(round(15.0 / DT)):
        t = k * DT
        estimate = estimator.step(weights_at(t), DT)
        if t > 5.0:  # after the initial convergence
            lambda2, fiedler = fiedler_pair(weighted_laplacian(weights_at(t + DT)))
            lambdas.append(lambda2)
            errors.append(np.abs(estimate.lambda2 - lambda2).max() / lambda2)
            alignments.append(abs(estimate.fiedler @ fiedler) / np.linalg.norm(estimate.fiedler))
    assert max(lambdas) - min(lambdas) > 0.1 * np.mean(lambdas)  # the graph really varied
    assert max(errors) < 0.05
    assert min(alignments) > 0.995


def test_saturates_at_the_ceiling_on_dense_graphs_and_recovers():
    n = 8
    dense = np.ones((n, n)) - np.eye(n)  # complete graph: lambda2 = n > ceiling
    sparse = sensor_graph(5, n)
    lambda2, _ = fiedler_pair(weighted_laplacian(sparse))
    estimator = FiedlerEstimator(n, GAINS, np.random.default_rng(1))
    estimate = run(estimator, dense, 5.0)
    np.testing.assert_allclose(estimate.lambda2, GAINS.lambda2_ceiling, rtol=0.02)
    assert np.all(np.isfinite(estimator.eigenvector)) and np.linalg.norm(estimator.eigenvector) > 0.5
    estimate = run(estimator, sparse, 8.0)
    np.testing.assert_allclose(estimate.lambda2, lambda2, rtol=0.02)


def test_updates_use_only_neighbours():
    """One message exchange: a robot's new state depends on its own and its
    neighbours' states only."""
    n = 8
    weights = sensor_graph(2, n)
    robot = 0
    strangers = np.flatnonzero(weights[robot] == 0)
    strangers = strangers[strangers != robot]
    assert strangers.size > 0
    a = FiedlerEstimator(n, GAINS, np.random.default_rng(3))
    b = FiedlerEstimator(n, GAINS, np.random.default_rng(3))
    b.eigenvector[strangers] += 5.0
    b.square_mean[strangers] -= 0.3
    b.mean_integral[strangers] += 1.0
    dt = 1e-5  # one substep
    assert a.substep_count(weights, dt) == 1
    a.step(weights, dt)
    b.step(weights, dt)
    for name in ("eigenvector", "mean", "mean_integral", "square_mean", "square_mean_integral"):
        assert getattr(a, name)[robot] == getattr(b, name)[robot], name


def test_reset_with_the_same_seed_repeats_the_run():
    weights = sensor_graph(6, 7)
    estimator = FiedlerEstimator(7, GAINS, np.random.default_rng(9))
    first = run(estimator, weights, 0.5)
    estimator.reset(np.random.default_rng(9))
    second = run(estimator, weights, 0.5)
    np.testing.assert_array_equal(first.lambda2, second.lambda2)
    np.testing.assert_array_equal(first.fiedler, second.fiedler)


def test_substeps_keep_dense_large_teams_stable():
    n = 35
    weights = np.random.default_rng(0).uniform(0.5, 1.0, (n, n))
    weights = np.triu(weights, 1) + np.triu(weights, 1).T
    estimator = FiedlerEstimator(n, GAINS, np.random.default_rng(0))
    assert estimator.substep_count(weights, DT) > DT / GAINS.max_substep
    estimate = run(estimator, weights, 0.5)
    assert np.all(np.isfinite(estimate.lambda2)) and np.all(np.abs(estimator.eigenvector) < 10)


def test_invalid_inputs_are_rejected():
    estimator = FiedlerEstimator(4, GAINS, np.random.default_rng(0))
    with pytest.raises(ValueError, match="weights"):
        estimator.step(np.zeros((3, 3)), DT)
    with pytest.raises(ValueError, match="dt"):
        estimator.step(np.zeros((4, 4)), 0.0)
    with pytest.raises(ValueError, match="num_robots"):
        FiedlerEstimator(1, GAINS, np.random.default_rng(0))
