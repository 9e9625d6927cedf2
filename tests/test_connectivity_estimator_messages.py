"""The lambda2 estimator fed by messages (controllers/connectivity/estimator_messages.py): pure numpy,
hand-made graphs, messages handed over as the bus would."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from controllers.connectivity.connected_params import ConnectedParams
from controllers.connectivity.estimator_messages import (LAMBDA2_ESTIMATE_KIND, MessageFedEstimator,
                                                         estimator_message_bytes)
from sim.radio.bus import Delivery

DT = 0.01
PARAMS = ConnectedParams().message_estimator  # the gains a run over a real radio uses


def laplacian_lambda2(weights: np.ndarray) -> float:
    return float(np.linalg.eigvalsh(np.diag(weights.sum(axis=1)) - weights)[1])


def path(n: int) -> np.ndarray:
    w = np.zeros((n, n))
    i = np.arange(n - 1)
    w[i, i + 1] = w[i + 1, i] = 1.0
    return w


def ring(n: int) -> np.ndarray:
    w = path(n)
    w[0, n - 1] = w[n - 1, 0] = 1.0
    return w


def random_weights(n: int, seed: int) -> np.ndarray:
    """A connected graph: a path plus random chords, weights in (0.2, 1]."""
    rng = np.random.default_rng(seed)
    w = path(n) * rng.uniform(0.2, 1.0, (n, n))
    chords = np.triu(rng.random((n, n)) < 0.3, 2)
    w[chords] = rng.uniform(0.2, 1.0, int(chords.sum()))
    w = np.triu(w, 1)
    return w + w.T


def inbox_of(estimator: MessageFedEstimator, delivered: np.ndarray, time_s: float) -> list[list[Delivery]]:
    """The bus's deliveries of every robot's broadcast at ``time_s``, ``delivered[sender, receiver]``."""
    rows: list[list[Delivery]] = [[] for _ in range(estimator.num_robots)]
    for sequence, message in enumerate(estimator.messages()):
        stamped = dataclasses.replace(message, sequence=sequence, sent_s=time_s)
        for receiver in np.flatnonzero(delivered[message.sender]):
            if receiver != message.sender:
                rows[receiver].append(Delivery(stamped, int(receiver), time_s + 0.5 * DT))
    return rows


def run(estimator: MessageFedEstimator, weights: np.ndarray, ticks: int, delivered=None):
    """``ticks`` ticks: each robot steps on the previous tick's deliveries, then broadcasts.
    ``delivered(tick)``: (N, N) bool of that tick's deliveries (default: every link)."""
    inbox: list = [() for _ in range(estimator.num_robots)]
    for tick in range(ticks):
        time_s = tick * DT
        estimate = estimator.step(weights, DT, time_s, inbox)
        mask = weights > 0 if delivered is None else delivered(tick) & (weights > 0)
        inbox = inbox_of(estimator, mask, time_s)
    return estimate


@pytest.mark.parametrize("weights", [path(5), ring(6), random_weights(7, 0), random_weights(8, 1)],
                         ids=["path5", "ring6", "random7", "random8"])
def test_converges_to_the_exact_lambda2_with_every_message_delivered(weights):
    exact = laplacian_lambda2(weights)
    assert exact < PARAMS.lambda2_ceiling
    estimator = MessageFedEstimator(len(weights), PARAMS, np.random.default_rng(3), 1, timeout_s=0.2)
    estimate = run(estimator, weights, 4000)
    assert estimator.failure == ""
    np.testing.assert_allclose(estimate.lambda2, exact, rtol=2e-3)
    # The robots' own components form a unit Fiedler vector (any in the ring's two-dimensional eigenspace).
    laplacian = np.diag(weights.sum(axis=1)) - weights
    vector = estimate.fiedler
    assert np.linalg.norm(vector) == pytest.approx(1.0, abs=0.03)
    assert np.linalg.norm(laplacian @ vector - exact * vector) < 0.03 * exact


def test_warm_up_is_the_same_exchange_with_every_message_delivered():
    weights = random_weights(6, 2)
    estimator = MessageFedEstimator(6, PARAMS, np.random.default_rng(0), 1, timeout_s=0.2)
    estimate = estimator.warm_up(weights, DT, 3000)
    np.testing.assert_allclose(estimate.lambda2, laplacian_lambda2(weights), rtol=2e-3)


def test_the_laplacian_covers_only_links_that_delivered():
    # W is a ring of four; nothing ever arrives over the link 0-3, so the robots hear a path.
    weights = ring(4)
    silent = np.ones((4, 4), dtype=bool)
    silent[0, 3] = silent[3, 0] = False
    estimator = MessageFedEstimator(4, PARAMS, np.random.default_rng(1), 1, timeout_s=0.2)
    estimate = run(estimator, weights, 4000, lambda tick: silent)
    used = estimator.used_links(weights, 4000 * DT)
    assert not used[0, 3] and not used[3, 0] and used[0, 1] and used[1, 2] and used[2, 3]
    assert laplacian_lambda2(weights) == pytest.approx(2.0)
    np.testing.assert_allclose(estimate.lambda2, laplacian_lambda2(path(4)), rtol=2e-3)  # 2 - sqrt(2)


def test_a_link_heard_one_way_only_is_in_one_row_only():
    weights = path(3)
    estimator = MessageFedEstimator(3, PARAMS, np.random.default_rng(0), 1, timeout_s=0.05)
    one_way = np.ones((3, 3), dtype=bool)
    one_way[1, 0] = False  # robot 1's messages never reach robot 0
    run(estimator, weights, 20, lambda tick: one_way)
    used = estimator.used_links(weights, 20 * DT)
    assert used[1, 0] and not used[0, 1] and used[1, 2] and used[2, 1]
    # A message older than the timeout no longer counts.
    assert not estimator.used_links(weights, 20 * DT + 0.2)[1, 2]


def test_a_lighter_graph_of_messages_gives_the_lower_lambda2_once_a_link_is_silent():
    weights = random_weights(6, 4)
    full = laplacian_lambda2(weights)
    silent = np.ones((6, 6), dtype=bool)
    silent[2, 3] = silent[3, 2] = False  # a path link: 2-3 silenced
    reduced = weights.copy()
    reduced[2, 3] = reduced[3, 2] = 0.0
    estimator = MessageFedEstimator(6, PARAMS, np.random.default_rng(2), 1, timeout_s=0.2)
    estimate = run(estimator, weights, 4000, lambda tick: silent)
    np.testing.assert_allclose(estimate.lambda2, laplacian_lambda2(reduced), rtol=5e-3)
    assert laplacian_lambda2(reduced) < full


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2**31 - 1), delivery=st.floats(0.2, 1.0), burst=st.integers(1, 30),
       graph=st.sampled_from(["path5", "ring6", "random7"]))
def test_lost_messages_leave_the_estimate_finite_and_bounded(seed, delivery, burst, graph):
    """Over random loss patterns (each link independently lost, and bursts where one robot is not heard at
    all) the state stays finite and bounded, and each robot's lambda2 estimate near [0, lambda_max(L)], where
    every Rayleigh quotient of L lies."""
    weights = {"path5": path(5), "ring6": ring(6), "random7": random_weights(7, 0)}[graph]
    n = len(weights)
    largest = float(np.linalg.eigvalsh(np.diag(weights.sum(axis=1)) - weights)[-1])
    rng = np.random.default_rng(seed)
    deaf = rng.integers(n)

    def delivered(tick):
        mask = rng.random((n, n)) < delivery
        if (tick // burst) % 3 == 0:
            mask[deaf] = False
        return mask

    estimator = MessageFedEstimator(n, PARAMS, np.random.default_rng(seed), 1, timeout_s=0.05)
    estimator.warm_up(weights, DT, 200)
    for block in range(4):
        estimate = run(estimator, weights, 100, delivered)
        assert estimator.failure == ""
        for array in (estimator._core.components, estimator._core.consensus, estimator._core.consensus_integral):
            assert np.isfinite(array).all()
        assert np.all(estimate.lambda2 >= -0.1 * largest) and np.all(estimate.lambda2 <= largest)
        assert np.abs(estimator._core.components).max() < 10
        assert np.abs(estimator._core.consensus_integral).max() < 100


def test_messages_are_broadcasts_of_the_rounded_state():
    estimator = MessageFedEstimator(4, PARAMS, np.random.default_rng(0), 1, timeout_s=0.2)
    messages = estimator.messages()
    assert [m.sender for m in messages] == [0, 1, 2, 3]
    assert all(m.kind == LAMBDA2_ESTIMATE_KIND and m.receivers is None and m.latest_only for m in messages)
    # One component, three consensus channels (Ave x, Ave x^2, Ave x L x) and their integrals, the degree,
    # the Fiedler component: 9 float32 and a uint16 round number.
    assert messages[0].size_bytes == estimator_message_bytes(1) == 38
    assert estimator_message_bytes(2) == 4 * (2 + 2 * 9 + 2) + 2
    state = messages[2].payload
    assert state.components.dtype == np.float32
    assert state.components[0] == np.float32(estimator._core.components[2, 0])
    assert state.fiedler == np.float32(estimator.estimate.fiedler[2])


def test_each_robot_sees_the_fiedler_vector_through_its_messages():
    weights = path(3)
    estimator = MessageFedEstimator(3, PARAMS, np.random.default_rng(0), 1, timeout_s=0.05)
    one_way = np.ones((3, 3), dtype=bool)
    one_way[1, 0] = False  # robot 0 never hears robot 1
    run(estimator, weights, 50, lambda tick: one_way)
    views, own = estimator.fiedler_views(), estimator.estimate.fiedler
    np.testing.assert_array_equal(np.diag(views), own)
    assert views[1, 0] == own[0]  # robot 0 has no value of robot 1: its own (no eq. 17 term)
    assert views[0, 1] == estimator.heard_fiedler[1, 0] and views[2, 1] == estimator.heard_fiedler[1, 2]
    assert views[2, 0] == own[0]  # 0 and 2 are not linked
    assert views[0, 1] != own[0]  # robot 1 holds robot 0's value as sent, float32, a tick old
    assert np.float32(views[0, 1]) == views[0, 1]


def test_gains_too_fast_for_one_exchange_a_tick_are_refused():
    fast = ConnectedParams(estimator_message_speedup=1.0).message_estimator  # K_P dt = 4
    with pytest.raises(ValueError, match="unstable"):
        MessageFedEstimator(3, fast, np.random.default_rng(0), 1, timeout_s=0.2).check_gains(DT)
    MessageFedEstimator(3, PARAMS, np.random.default_rng(0), 1, timeout_s=0.2).check_gains(DT)


def test_a_diverging_state_is_reported_not_raised():
    # Gains far above the stable step: the state blows up, and the estimator says so.
    fast = ConnectedParams(estimator_message_speedup=1.0).message_estimator
    weights = random_weights(6, 0)
    estimator = MessageFedEstimator(6, dataclasses.replace(fast, consensus_proportional_gain=1e5),
                                    np.random.default_rng(0), 1, timeout_s=0.2)
    estimate = run(estimator, weights, 400)
    assert "diverged" in estimator.failure
    assert np.isfinite(estimate.lambda2).all()
