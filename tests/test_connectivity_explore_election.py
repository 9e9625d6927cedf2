"""Flooding and the 'prime traveler' election of Nestmeyer et al. 2017 (Sec. 3.3, Alg. 1, Proposition 1)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.sparse.csgraph import shortest_path

from controllers.connectivity.election import Candidacy, ElectionRound, FloodingNetwork, Handover, election_window_ticks
from controllers.connectivity.roles import Role, RoleMachine


def path_graph(n: int) -> np.ndarray:
    adjacency = np.zeros((n, n), dtype=bool)
    idx = np.arange(n - 1)
    adjacency[idx, idx + 1] = adjacency[idx + 1, idx] = True
    return adjacency


def random_graph(rng: np.random.Generator, n: int, density: float, connected: bool) -> np.ndarray:
    """Symmetric random graph; with ``connected`` a random spanning tree is added."""
    upper = np.triu(rng.random((n, n)) < density, 1)
    if connected:
        order = rng.permutation(n)
        for k in range(1, n):
            a, b = order[k], order[rng.integers(k)]
            upper[min(a, b), max(a, b)] = True
    return upper | upper.T


def hop_distances(adjacency: np.ndarray, source: int) -> np.ndarray:
    return shortest_path(adjacency.astype(float), unweighted=True, indices=source)


@pytest.mark.parametrize("latency", [1, 3])
def test_flooding_arrives_one_hop_per_latency_period(latency):
    rng = np.random.default_rng(latency)
    n = 9
    adjacency = random_graph(rng, n, 0.15, connected=True)
    network = FloodingNetwork(n, latency)
    message = Candidacy(epoch=0, host=4)
    network.broadcast(4, message, tick=0)
    first_heard = np.full(n, -1)
    first_heard[4] = 0
    for tick in range(n * latency + 1):
        for robot, received in network.delivered(tick):
            assert received == message and first_heard[robot] == -1
            first_heard[robot] = tick
        network.exchange(adjacency, tick)
    np.testing.assert_array_equal(first_heard, hop_distances(adjacency, 4) * latency)


def test_flooding_reaches_everyone_within_n_minus_1_hops_on_changing_graphs():
    rng = np.random.default_rng(7)
    n, latency = 12, 2
    for trial in range(20):
        network = FloodingNetwork(n, latency)
        message = Candidacy(epoch=trial, host=0)
        network.broadcast(0, message, tick=0)
        for tick in range((n - 1) * latency + 1):
            network.delivered(tick)
            network.exchange(random_graph(rng, n, 0.05, connected=True), tick)
        assert network.knows(message, (n - 1) * latency).all()


def test_flooding_does_not_cross_a_disconnection():
    n = 6
    adjacency = np.zeros((n, n), dtype=bool)
    adjacency[:3, :3] = True  # two cliques {0, 1, 2}, {3, 4, 5}
    adjacency[3:, 3:] = True
    np.fill_diagonal(adjacency, False)
    network = FloodingNetwork(n, 1)
    message = Candidacy(0, 0)
    network.broadcast(0, message, 0)
    for tick in range(10):
        network.delivered(tick)
        network.exchange(adjacency, tick)
    np.testing.assert_array_equal(network.knows(message, 10), [True, True, True, False, False, False])


def test_retired_messages_stop_travelling():
    network = FloodingNetwork(3, 1)
    network.broadcast(0, Candidacy(0, 0), 0)
    network.broadcast(0, Handover(0, 2, 1), 0)
    network.retire(lambda m: isinstance(m, Candidacy))
    network.exchange(path_graph(3), 0)
    assert network.messages == [Handover(0, 2, 1)]
    assert [m for _, m in network.delivered(1)] == [Handover(0, 2, 1)]


def test_round_picks_shortest_remaining_path_then_lower_index():
    round_ = ElectionRound(epoch=0, host=0, deadline=4)
    assert round_.winner() is None
    round_.enroll(5, 3.0)
    round_.enroll(2, 1.5)
    round_.enroll(7, 1.5)
    assert round_.winner() == 2
    round_.withdraw(2)
    assert round_.winner() == 7


def run_startup(adjacency: np.ndarray, remaining: np.ndarray, has_target: np.ndarray, latency: int, ticks: int):
    n = len(remaining)
    machine = RoleMachine(n, latency, host=0)
    machine.start(has_target)
    history = []
    never = np.zeros(n, dtype=bool)
    for tick in range(ticks):
        changes = machine.step(tick, adjacency, never, never, never, remaining)
        history.append(changes.roles.copy())
    return machine, np.array(history)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(2, 10),
    latency=st.integers(1, 3),
)
def test_startup_elects_exactly_the_closest_traveler(seed, n, latency):
    rng = np.random.default_rng(seed)
    adjacency = random_graph(rng, n, 0.3, connected=True)
    has_target = rng.random(n) < 0.6
    has_target[rng.integers(n)] = True
    remaining = np.where(has_target, rng.integers(1, 4, n).astype(float), np.inf)  # ties are likely
    window = election_window_ticks(n, latency)
    machine, history = run_startup(adjacency, remaining, has_target, latency, window + (n - 1) * latency + 2)
    primes = (history == Role.PRIME_TRAVELER).sum(axis=1)
    assert primes.max() <= 1
    assert primes[:window].sum() == 0  # nobody is prime before the host decides
    expected = min(np.flatnonzero(has_target), key=lambda i: (remaining[i], i))
    assert machine.prime == expected
    assert history[-1][~has_target].tolist() == [Role.CONNECTOR] * int((~has_target).sum())
    # The winner became prime exactly when the handover reached it.
    became = np.argmax(history[:, expected] == Role.PRIME_TRAVELER)
    assert became == window + latency * hop_distances(adjacency, 0)[expected]


def test_prime_abdicates_only_upon_decision_and_successor_waits_for_the_handover():
    n, latency = 5, 2
    adjacency = path_graph(n)
    remaining = np.array([1.0, np.inf, np.inf, 5.0, 3.0])
    has_target = np.isfinite(remaining)
    window = election_window_ticks(n, latency)
    machine = RoleMachine(n, latency, host=0)
    machine.start(has_target)
    never = np.zeros(n, dtype=bool)
    tick = 0
    for tick in range(window + 1):
        machine.step(tick, adjacency, never, never, never, remaining)
    assert machine.prime == 0  # the host itself won: no handover needed
    near = never.copy()
    near[0] = True
    reached_at = tick + 1
    roles_seen = []
    for tick in range(reached_at, reached_at + window + (n - 1) * latency + 2):
        roles_seen.append(machine.step(tick, adjacency, never, near, never, remaining).roles.copy())
    roles_seen = np.array(roles_seen)
    # Robot 0 keeps the role during the whole window, then becomes anchor.
    assert np.all(roles_seen[:window, 0] == Role.PRIME_TRAVELER)
    assert roles_seen[window, 0] == Role.ANCHOR
    # Robot 4 (shortest remaining path) becomes prime 4 hops after the decision.
    assert np.all(roles_seen[: window + 4 * latency, 4] == Role.SECONDARY_TRAVELER)
    assert roles_seen[window + 4 * latency, 4] == Role.PRIME_TRAVELER
    assert (roles_seen == Role.PRIME_TRAVELER).sum(axis=1).max() <= 1
    assert roles_seen[-1, 3] == Role.SECONDARY_TRAVELER


def test_token_holder_with_a_new_target_becomes_prime_directly():
    machine = RoleMachine(3, 1, host=0)
    machine.start(np.zeros(3, dtype=bool))  # nobody has a target: host keeps polling
    never = np.zeros(3, dtype=bool)
    inf = np.full(3, np.inf)
    for tick in range(5):
        machine.step(tick, path_graph(3), never, never, never, inf)
    got = np.array([True, True, False])
    roles = machine.step(5, path_graph(3), got, never, never, inf).roles
    assert roles.tolist() == [Role.PRIME_TRAVELER, Role.SECONDARY_TRAVELER, Role.CONNECTOR]


def test_winner_that_reached_its_target_meanwhile_passes_the_token_on():
    n = 4
    adjacency = path_graph(n)
    remaining = np.array([np.inf, np.inf, 4.0, 1.0])
    machine = RoleMachine(n, 1, host=0)
    machine.start(np.isfinite(remaining))
    never = np.zeros(n, dtype=bool)
    window = election_window_ticks(n, 1)
    for tick in range(window + 1):
        machine.step(tick, adjacency, never, never, never, remaining)
    assert machine.token_in_flight  # handover to robot 3 travels 3 hops
    near = never.copy()
    near[3] = True
    roles = machine.step(window + 1, adjacency, never, near, never, remaining).roles
    assert roles[3] == Role.ANCHOR
    for tick in range(window + 2, 3 * window + 8):
        roles = machine.step(tick, adjacency, never, never, never, remaining).roles
    assert machine.holds_token[2] and roles[2] == Role.PRIME_TRAVELER
    assert roles[3] == Role.ANCHOR


def drive(
    machine: RoleMachine,
    rng: np.random.Generator,
    ticks: int,
    connected: bool,
    start_tick: int = 0,
    events: bool = True,
) -> int:
    """Random Algorithm-1 inputs and graphs; checks the invariants at every tick."""
    n = machine.n_robots
    remaining = rng.uniform(0.5, 10.0, n)
    for tick in range(start_tick, start_tick + ticks):
        roles = machine.roles
        if events:
            got_target = (roles == Role.CONNECTOR) & (rng.random(n) < 0.05)
            near_target = np.isin(roles, [Role.PRIME_TRAVELER, Role.SECONDARY_TRAVELER]) & (rng.random(n) < 0.03)
            task_done = (roles == Role.ANCHOR) & (rng.random(n) < 0.05)
        else:
            got_target = near_target = task_done = np.zeros(n, dtype=bool)
        remaining = np.maximum(remaining - rng.uniform(0, 0.2, n), 0.0)
        adjacency = random_graph(rng, n, rng.uniform(0.0, 0.5), connected)
        roles = machine.step(tick, adjacency, got_target, near_target, task_done, remaining).roles
        primes = np.flatnonzero(roles == Role.PRIME_TRAVELER)
        assert len(primes) <= 1
        assert all(machine.holds_token[p] for p in primes)
        handovers = sum(isinstance(m, Handover) for m in machine.network.messages)
        assert machine.holds_token.sum() + handovers == 1  # the token is never lost nor copied
    return start_tick + ticks


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(1, 9),
    latency=st.integers(1, 3),
    connected=st.booleans(),
)
def test_never_two_prime_travelers_under_random_graph_sequences(seed, n, latency, connected):
    rng = np.random.default_rng(seed)
    machine = RoleMachine(n, latency, host=int(rng.integers(n)))
    machine.start(rng.random(n) < 0.5)
    drive(machine, rng, 150, connected)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 8), latency=st.integers(1, 2))
def test_a_waiting_secondary_traveler_becomes_prime_on_connected_graphs(seed, n, latency):
    """Liveness: once events stop, with secondary travelers left and the graph
    connected at every tick, a prime traveler exists within three election windows."""
    rng = np.random.default_rng(seed)
    machine = RoleMachine(n, latency, host=0)
    machine.start(rng.random(n) < 0.5)
    tick = drive(machine, rng, 60, connected=True)
    secondary_left = np.any(machine.roles == Role.SECONDARY_TRAVELER)
    window = election_window_ticks(n, latency)
    tick = drive(machine, rng, 3 * window + (n - 1) * latency + 3, connected=True, start_tick=tick, events=False)
    if secondary_left:
        assert machine.prime >= 0
