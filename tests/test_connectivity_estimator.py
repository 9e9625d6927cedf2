"""Decentralised lambda2 / Fiedler-vector estimator (Yang et al. 2010) against
numpy eigh of the same weighted Laplacian."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from connected_helpers import grown_positions, preset_params
from controllers.connectivity.connected_params import ConnectedParams, FiedlerEstimatorParams
from controllers.connectivity.estimator import FiedlerEstimator, SubspaceEstimator, ritz_connectivity_gradient
from controllers.connectivity.graph import fiedler_pair, link_weights, weighted_laplacian
from controllers.connectivity.smooth_spectrum import smooth_lambda2_gradient

GAINS = FiedlerEstimatorParams()
OFFICE = preset_params("office")
DT = 0.01  # s, the simulator's control period


def sensor_graph(seed: int, n: int) -> np.ndarray:
    """Weights of a random connected office team (0.9-2.2 m spacing) whose
    lambda2 lies below the estimator's ceiling and is separated from lambda3."""
    rng = np.random.default_rng(seed)
    while True:
        weights = link_weights(grown_positions(rng, n, OFFICE.min_robot_distance_m), None, OFFICE).weights
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


FIEDLER_STATE = ("eigenvector", "mean", "mean_integral", "square_mean", "square_mean_integral")
SUBSPACE_STATE = ("components", "consensus", "consensus_integral")


def test_updates_use_only_neighbours():
    """Robot i's rates (the continuous-time estimator) depend on its own and
    its neighbours' states only."""
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
    rates_a, rates_b = a.rates(weights), b.rates(weights)
    for name in FIEDLER_STATE:
        assert rates_a[name][robot] == rates_b[name][robot], name
        assert np.any(rates_a[name] != rates_b[name]) or name == "mean_integral", name


def reference_step(estimator, names, weights, dt, consensus_weights=None, substeps=20000):
    """Classical RK4 of ``estimator.rates`` with fine steps (no dither)."""
    state = {name: getattr(estimator, name).copy() for name in names}

    def rate_at(values):
        for name in names:
            setattr(estimator, name, values[name])
        return estimator.rates(weights, consensus_weights)

    h = dt / substeps
    for _ in range(substeps):
        k1 = rate_at(state)
        k2 = rate_at({name: state[name] + 0.5 * h * k1[name] for name in names})
        k3 = rate_at({name: state[name] + 0.5 * h * k2[name] for name in names})
        k4 = rate_at({name: state[name] + h * k3[name] for name in names})
        state = {name: state[name] + h / 6 * (k1[name] + 2 * k2[name] + 2 * k3[name] + k4[name]) for name in names}
    return state


@pytest.mark.parametrize("modes", [0, 2])
def test_a_step_integrates_the_continuous_time_estimator(modes):
    """Over one control period from a state far from convergence, ``step``
    (exact consensus flow, Euler power iteration) follows a fine RK4
    integration of ``rates`` (links as consensus graph, 10x gains)."""
    n = 8
    weights = sensor_graph(4, n)
    links = (weights > 0).astype(float)
    fast = ConnectedParams(lambda2_source="estimator").estimator
    fast = dataclasses.replace(fast, dither=0.0)

    def make():
        if modes == 0:
            return FiedlerEstimator(n, fast, np.random.default_rng(8)), FIEDLER_STATE
        return SubspaceEstimator(n, fast, np.random.default_rng(8), modes), SUBSPACE_STATE

    (estimator, names), (reference, _) = make(), make()
    for _ in range(3):  # a few periods in: the consensus is mid-transient
        estimator.step(weights, DT, links)
        reference.step(weights, DT, links)
    before = {name: getattr(reference, name).copy() for name in names}
    expected = reference_step(reference, names, weights, DT, links, substeps=4000)
    estimator.step(weights, DT, links)
    for name in names:
        moved = np.abs(expected[name] - before[name]).max()
        error = np.abs(expected[name] - getattr(estimator, name)).max()
        assert moved > 1e-3, name  # the period really changed the state
        assert error < 0.04 * moved, (name, error, moved)


def test_reset_with_the_same_seed_repeats_the_run():
    weights = sensor_graph(6, 7)
    estimator = FiedlerEstimator(7, GAINS, np.random.default_rng(9))
    first = run(estimator, weights, 0.5)
    estimator.reset(np.random.default_rng(9))
    second = run(estimator, weights, 0.5)
    np.testing.assert_array_equal(first.lambda2, second.lambda2)
    np.testing.assert_array_equal(first.fiedler, second.fiedler)


def test_substeps_keep_dense_large_teams_stable():
    """With no accuracy cap on the substep, the stability rule alone keeps a
    dense 35-robot graph (Laplacian eigenvalues up to ~26) stable."""
    n = 35
    weights = np.random.default_rng(0).uniform(0.5, 1.0, (n, n))
    weights = np.triu(weights, 1) + np.triu(weights, 1).T
    uncapped = dataclasses.replace(GAINS, max_substep=1.0)
    estimator = FiedlerEstimator(n, uncapped, np.random.default_rng(0))
    assert estimator.substep_count(weights, DT) > 1
    estimate = run(estimator, weights, 2.0)
    assert np.all(np.isfinite(estimate.lambda2)) and np.all(np.abs(estimator.eigenvector) < 10)
    np.testing.assert_allclose(estimate.lambda2, GAINS.lambda2_ceiling, rtol=0.05)


def test_invalid_inputs_are_rejected():
    estimator = FiedlerEstimator(4, GAINS, np.random.default_rng(0))
    with pytest.raises(ValueError, match="weights"):
        estimator.step(np.zeros((3, 3)), DT)
    with pytest.raises(ValueError, match="dt"):
        estimator.step(np.zeros((4, 4)), 0.0)
    with pytest.raises(ValueError, match="num_robots"):
        FiedlerEstimator(1, GAINS, np.random.default_rng(0))


# ---------------------------------------------------------------------------
# SubspaceEstimator: K eigenpairs by decentralised subspace iteration + Rayleigh-Ritz.
# ---------------------------------------------------------------------------


def ritz_vectors(estimator: SubspaceEstimator, estimate, robot: int) -> np.ndarray:
    """(N, K) unit-norm Ritz vectors as robot ``robot`` forms them from the messages X_j."""
    centred = estimate.components - estimator.mean[robot]
    return centred @ estimate.coefficients[robot] / np.sqrt(estimator.num_robots)


def subspace_gap(vectors: np.ndarray, reference: np.ndarray) -> float:
    """Largest sine of the principal angles between the column spans."""
    q, _ = np.linalg.qr(vectors)
    return float(np.linalg.norm(reference - q @ (q.T @ reference), ord=2))


@pytest.mark.parametrize("modes", [2, 3])
@pytest.mark.parametrize("seed, n", [(0, 6), (1, 8), (2, 10), (3, 12)])
def test_subspace_estimator_converges_to_the_lowest_eigenpairs(seed, n, modes):
    weights = sensor_graph(seed, n)
    eigenvalues, eigenvectors = np.linalg.eigh(weighted_laplacian(weights))
    assert eigenvalues[modes] < 0.8 * GAINS.lambda2_ceiling  # every tracked mode below the ceiling
    estimator = SubspaceEstimator(n, GAINS, np.random.default_rng(seed), modes)
    estimate = run(estimator, weights, 8.0)
    assert estimate.valid.all()
    # Every robot's Ritz values are lambda2..lambda_{K+1} within 1 %.
    np.testing.assert_allclose(estimate.values, np.broadcast_to(eigenvalues[1:modes + 1], (n, modes)), rtol=0.01)
    np.testing.assert_allclose(estimate.lambda2, eigenvalues[1], rtol=0.01)
    for robot in (0, n - 1):
        vectors = ritz_vectors(estimator, estimate, robot)
        np.testing.assert_allclose(vectors.T @ vectors, np.eye(modes), atol=0.01)
        for k in range(modes):
            gaps = np.abs(eigenvalues[1:modes + 2] - eigenvalues[k + 1])
            if np.sort(gaps)[1] > 0.05:  # a simple eigenvalue: the vector itself up to sign
                assert abs(vectors[:, k] @ eigenvectors[:, k + 1]) > 0.999
        assert subspace_gap(vectors, eigenvectors[:, 1:modes + 1]) < 0.02
    # Robot i's own component of its first Ritz vector is v2_i up to sign.
    aligned = sign_aligned(estimate.fiedler, eigenvectors[:, 1])
    np.testing.assert_allclose(np.abs(aligned), np.abs(eigenvectors[:, 1]), atol=0.02)


def test_subspace_estimator_resolves_a_degenerate_pair():
    n = 8
    weights = np.zeros((n, n))
    for i in range(n):  # ring: lambda2 = lambda3 = 2 - 2 cos(2 pi / n), lambda4 = 2 above the ceiling
        weights[i, (i + 1) % n] = weights[(i + 1) % n, i] = 1.0
    eigenvalues, eigenvectors = np.linalg.eigh(weighted_laplacian(weights))
    estimator = SubspaceEstimator(n, GAINS, np.random.default_rng(2), 2)
    estimate = run(estimator, weights, 8.0)
    np.testing.assert_allclose(estimate.values, eigenvalues[1], rtol=0.01)
    # Any basis of the eigenspace (eigh's is arbitrary inside it).
    assert subspace_gap(ritz_vectors(estimator, estimate, 3), eigenvectors[:, 1:3]) < 0.02


def test_subspace_estimator_tracks_a_slowly_varying_graph():
    n, modes = 8, 2
    base = sensor_graph(11, n)
    phases = np.random.default_rng(4).uniform(0, 2 * np.pi, (n, n))
    phases = np.triu(phases, 1) + np.triu(phases, 1).T

    def weights_at(t):
        return base * (1.0 + 0.25 * np.sin(0.5 * t + phases))

    estimator = SubspaceEstimator(n, GAINS, np.random.default_rng(0), modes)
    errors, gaps = [], []
    for k in range(round(15.0 / DT)):
        t = k * DT
        estimate = estimator.step(weights_at(t), DT)
        if t > 5.0:
            eigenvalues, eigenvectors = np.linalg.eigh(weighted_laplacian(weights_at(t + DT)))
            errors.append(np.abs(estimate.values - eigenvalues[1:modes + 1]).max() / eigenvalues[1])
            gaps.append(subspace_gap(ritz_vectors(estimator, estimate, 0), eigenvectors[:, 1:modes + 1]))
    assert max(errors) < 0.05
    assert max(gaps) < 0.1


def _star_of_arms(first_arm_weight: float) -> np.ndarray:
    """Robot 0 with three two-robot arms; arm 1 hangs on ``first_arm_weight``, arm 2 on 0.3."""
    weights = np.zeros((7, 7))
    for i, j, w in [(0, 1, first_arm_weight), (1, 2, 1.0), (0, 3, 0.3), (3, 4, 1.0), (0, 5, 1.0), (5, 6, 1.0)]:
        weights[i, j] = weights[j, i] = w
    return weights


def test_subspace_estimator_follows_a_mode_crossing_that_traps_one_vector():
    """A link fading within 0.3 s (a robot passing a wall corner) makes another
    mode the lowest; one power-iteration vector stays on the old mode (its
    estimate overshoots lambda2 several times), the two-vector subspace
    already contains the new one."""
    n = 7
    errors = {}
    for modes in (1, 2):
        estimator = (FiedlerEstimator(n, GAINS, np.random.default_rng(0)) if modes == 1
                     else SubspaceEstimator(n, GAINS, np.random.default_rng(0), modes))
        run(estimator, _star_of_arms(1.0), 5.0)
        for k in range(100):
            weights = _star_of_arms(1.0 - 0.95 * min(k * DT / 0.3, 1.0))
            estimate = estimator.step(weights, DT)
        lambda2 = np.linalg.eigvalsh(weighted_laplacian(weights))[1]
        errors[modes] = np.abs(estimate.lambda2 - lambda2).max() / lambda2
    assert errors[1] > 1.0
    assert errors[2] < 0.05


def test_subspace_estimator_with_one_mode_is_the_single_vector_estimator():
    n = 8
    weights = sensor_graph(1, n)
    single = FiedlerEstimator(n, GAINS, np.random.default_rng(5))
    subspace = SubspaceEstimator(n, GAINS, np.random.default_rng(5), 1)
    for k in range(300):
        weights_now = weights * (1.0 + 0.2 * np.sin(0.01 * k))
        a = single.step(weights_now, DT)
        b = subspace.step(weights_now, DT)
        # Same x, Ave(x), Ave(x^2) trajectories (same equations, same random draws).
        np.testing.assert_allclose(subspace.components[:, 0], single.eigenvector, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(subspace.mean[:, 0], single.mean, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(subspace.gram[:, 0, 0], single.square_mean, rtol=1e-9, atol=1e-12)
    a, b = run(single, weights, 4.0), run(subspace, weights, 4.0)
    # Once converged, its Rayleigh quotient and (k3/k2)(1 - y2) agree, as do the vectors.
    np.testing.assert_allclose(b.lambda2, a.lambda2, rtol=0.02)
    np.testing.assert_allclose(b.fiedler, a.fiedler, atol=0.01)


def test_subspace_updates_use_only_neighbours():
    n = 8
    weights = sensor_graph(2, n)
    robot = 0
    strangers = np.flatnonzero(weights[robot] == 0)
    strangers = strangers[strangers != robot]
    a = SubspaceEstimator(n, GAINS, np.random.default_rng(3), 3)
    b = SubspaceEstimator(n, GAINS, np.random.default_rng(3), 3)
    b.components[strangers] += 5.0
    b.consensus[strangers] -= 0.3
    b.consensus_integral[strangers] += 1.0
    rates_a, rates_b = a.rates(weights), b.rates(weights)
    for name in SUBSPACE_STATE:
        np.testing.assert_array_equal(rates_a[name][robot], rates_b[name][robot])
        assert np.any(rates_a[name] != rates_b[name]), name
    # Robot i's estimate is a function of its own consensus values only.
    for name in ("values", "coefficients"):
        np.testing.assert_array_equal(getattr(a.estimate, name)[robot], getattr(b.estimate, name)[robot])


def test_ritz_gradient_matches_the_exact_smooth_gradient_once_converged():
    rng = np.random.default_rng(7)
    n, modes = 7, 3
    while True:
        positions = np.cumsum(rng.uniform(-1.6, 1.6, (n, 3)) * [1, 1, 0.2], axis=0)
        links = link_weights(positions, None, OFFICE)
        eigenvalues, eigenvectors = np.linalg.eigh(weighted_laplacian(links.weights))
        if 0.05 < eigenvalues[1] and eigenvalues[modes + 1] < 0.8 * GAINS.lambda2_ceiling and np.all(
                np.diff(eigenvalues[1:modes + 2]) > 0.02):
            break
    estimator = SubspaceEstimator(n, GAINS, np.random.default_rng(1), modes)
    estimate = run(estimator, links.weights, 10.0)
    for kappa in (0.0, 0.05):
        smooth, gradient = ritz_connectivity_gradient(links, estimate, kappa)
        # The exact surrogate over the same K + 1 lowest eigenvalues (modes above are not tracked).
        exact_smooth, exact_gradient = smooth_lambda2_gradient(
            links, eigenvalues[:modes + 1], eigenvectors[:, :modes + 1], kappa)
        np.testing.assert_allclose(smooth, exact_smooth, rtol=0.01)
        np.testing.assert_allclose(gradient, exact_gradient, atol=0.02 * np.abs(exact_gradient).max())


def test_subspace_estimator_rejects_invalid_modes():
    with pytest.raises(ValueError, match="modes"):
        SubspaceEstimator(4, GAINS, np.random.default_rng(0), 4)
    with pytest.raises(ValueError, match="modes"):
        SubspaceEstimator(4, GAINS, np.random.default_rng(0), 0)


@pytest.mark.parametrize("estimator_links", ["sensing", "messages"])
def test_strategy_estimates_the_graph_its_messages_travel_on(estimator_links):
    """With a link of G^lambda missing from the bodies' message graph A, the
    robots estimate lambda2(W) ("sensing", the paper's single graph) or
    lambda2(W o A) ("messages"), and their force is that graph's gradient."""
    import dataclasses as dc

    from controllers.connectivity.graph import connectivity_state
    from tether.runner import build_simulation
    from sim.scenario import load

    sim = build_simulation(load("connected-office", ['strategy.lambda2_source="estimator"',
                                               f'strategy.estimator_links="{estimator_links}"']))
    strategy = sim.strategy
    observation = sim.observe()
    state = connectivity_state(strategy.q, strategy.boxes, strategy.params)
    # Cut the message link whose loss lowers lambda2 the most but keeps W o A connected.
    candidates = []
    for i, j in state.edges:
        adjacency = observation.links.adjacency.copy()
        adjacency[i, j] = adjacency[j, i] = False
        cut = np.linalg.eigvalsh(weighted_laplacian(state.weights * adjacency))[1]
        if cut > 0.02:
            candidates.append((cut, adjacency))
    cut_lambda2, adjacency = min(candidates, key=lambda item: item[0])
    assert cut_lambda2 < 0.8 * state.lambda2
    cut_observation = dc.replace(observation, links=dc.replace(observation.links, adjacency=adjacency))
    for _ in range(100):  # the virtual points barely move in 1 s: the graph is nearly static
        commands = strategy.step(cut_observation)
    state = connectivity_state(strategy.q, strategy.boxes, strategy.params)
    restricted = state.links.restricted_to(adjacency)
    expected = state.lambda2 if estimator_links == "sensing" else np.linalg.eigvalsh(
        weighted_laplacian(restricted.weights))[1]
    estimates = commands.decorations.robot_scalars["lambda2_estimate"]
    np.testing.assert_allclose(estimates, expected, rtol=0.05)
    # Its own gradient: with exact Ritz pairs of the estimated graph, ritz_connectivity_gradient equals the
    # smooth gradient computed on that graph's links.
    links = state.links if estimator_links == "sensing" else restricted
    smooth, gradient = ritz_connectivity_gradient(links, strategy.estimator.estimate, strategy.params.spectrum_smoothing)
    values, vectors = np.linalg.eigh(weighted_laplacian(links.weights))
    _, reference = smooth_lambda2_gradient(links, values, vectors, strategy.params.spectrum_smoothing)
    np.testing.assert_allclose(gradient, reference, atol=0.05 * np.abs(reference).max())
