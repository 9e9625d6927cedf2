"""The continuous-connectivity method's own exchanges on the message bus (Nestmeyer et al. 2017 under a
real radio): election broadcasts, the prime-traveler token hand to hand, the efficiency consensus (eq. 13)."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

import tether.catalog  # noqa: F401 (registers the built-in scenarios)
from controllers.connectivity.election import (
    ELECTION_KIND,
    BusFlooding,
    Candidacy,
    FloodingNetwork,
    Reply,
    election_bytes,
    election_window_ticks,
)
from controllers.connectivity.exploration import CONSENSUS_KIND, heard_estimates, split_consensus
from controllers.connectivity.roles import PRIME_CODE, SECONDARY_CODE, Role, RoleMachine
from controllers.connectivity.travel import consensus_step
from sim.radio.bus import BusParameters, Delivery, Message, MessageBus, link_conditions
from sim.radio.presets import IDEAL, PRESETS
from sim.radio.protocols import HeartbeatMonitor
from sim.scenario import load
from test_connectivity_explore_election import random_graph

PERIOD_S = 0.01


def disk_link(adjacency: np.ndarray):
    """The ideal radio's view of a graph, as the loop builds it."""
    return link_conditions(np.where(adjacency, np.inf, -np.inf), adjacency)


class ScriptedBus:
    """A transport whose every (message, receiver) copy is lost or delivered after 1 + delay ticks, from a
    script of fates, within a graph (no link, no copy): losses and delays of any pattern."""

    def __init__(self, fates, n: int):
        self.fates, self.n, self.used, self.sequence = fates, n, 0, 0
        self.in_flight: list[tuple[int, Message, int]] = []
        self.tick = 0

    def send(self, message: Message, time_s: float) -> Message:
        stamped = replace(message, sequence=self.sequence, sent_s=time_s)
        self.sequence += 1
        audience = message.receivers if message.receivers is not None else [
            j for j in range(self.n) if j != message.sender]
        for receiver in audience:
            lost, delay = self.fates[self.used % len(self.fates)]
            self.used += 1
            if not lost:
                self.in_flight.append((self.tick + 1 + delay, stamped, receiver))
        return stamped

    def step(self, tick: int):
        """The deliveries due at ``tick`` (the next tick's inbox)."""
        self.tick = tick
        rows = [[] for _ in range(self.n)]
        for due, message, receiver in self.in_flight:
            if due <= tick:
                rows[receiver].append(Delivery(message, receiver, tick * PERIOD_S))
        self.in_flight = [entry for entry in self.in_flight if entry[0] > tick]
        return tuple(tuple(row) for row in rows)


# --- flooding ------------------------------------------------------------------------------------

@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(2, 9), latency=st.integers(1, 3))
def test_flooding_over_the_ideal_bus_is_the_in_process_flooding(seed, n, latency):
    """Election broadcasts on the ideal bus reach each robot at the very tick the in-process exchange does,
    on changing graphs, with several messages started at different ticks and robots."""
    rng = np.random.default_rng(seed)
    bus = MessageBus(BusParameters.from_preset(PRESETS["ideal"]), None, PERIOD_S, robot_count=n)
    over_bus, in_process = BusFlooding(n, latency), FloodingNetwork(n, latency)
    starts = {int(rng.integers(12)): Candidacy(epoch, int(rng.integers(n))) for epoch in range(3)}
    heard_bus, heard_process = set(), set()
    inbox = ((),) * n
    for tick in range(12 + n * latency + 2):
        adjacency = random_graph(rng, n, 0.25, connected=bool(rng.random() < 0.7))
        over_bus.receive(tick, inbox)
        heard_bus |= {(tick, robot, m) for robot, m in over_bus.delivered(tick)}
        heard_process |= {(tick, robot, m) for robot, m in in_process.delivered(tick)}
        if tick in starts:
            message = starts[tick]
            over_bus.broadcast(message.host, message, tick)
            in_process.broadcast(message.host, message, tick)
        for message in over_bus.outbox(tick):
            bus.send(message, tick * PERIOD_S)
        in_process.exchange(adjacency, tick)
        inbox = tuple(tuple(row) for row in bus.step(tick * PERIOD_S, disk_link(adjacency)))
    assert heard_bus == heard_process and heard_bus


def test_election_broadcast_sizes_and_time_to_live():
    flooding = BusFlooding(3, 1, forward_ticks=2)
    flooding.broadcast(0, Candidacy(4, 0), 0)
    flooding.broadcast(0, Reply(4, 0, 2.5), 0)
    first = flooding.outbox(0)
    assert [(m.kind, m.sender, m.receivers) for m in first] == [(ELECTION_KIND, 0, None)]
    # A tag, an int32 epoch, uint16 robots, a float64 length.
    assert first[0].size_bytes == election_bytes(first[0].payload) == (1 + 4 + 2) + (1 + 4 + 2 + 8)
    assert first[0].latest_only
    assert len(flooding.outbox(1)) == 1 and flooding.outbox(2) == []  # two ticks, then silent


# --- the election and the token over a lossy bus ---------------------------------------------------

def run_over(machine: RoleMachine, transport_step, transport_send, remaining, ticks, start=0, events=None):
    """Tick ``machine`` over a transport; checks at every tick that at most one robot is prime traveler,
    that it holds the token, and that at most one robot acts as the token's holder."""
    n = machine.n_robots
    never = np.zeros(n, dtype=bool)
    inbox = ((),) * n
    history = []
    for tick in range(start, start + ticks):
        got, near, done = events(tick, machine.roles) if events else (never, never, never)
        roles = machine.step(tick, None, got, near, done, remaining, inbox, tick * PERIOD_S).roles
        primes = np.flatnonzero(roles == PRIME_CODE)
        assert len(primes) <= 1, f"tick {tick}: prime travelers {primes}"
        assert all(machine.tokens[p].acts_as_holder for p in primes)
        assert sum(token.acts_as_holder for token in machine.tokens) <= 1
        assert np.array_equal(machine.holds_token, [token.acts_as_holder for token in machine.tokens])
        for message in machine.outbox:
            transport_send(message, tick * PERIOD_S)
        inbox = transport_step(tick)
        history.append(roles.copy())
    return np.array(history)


def lossy_802154_bus(n: int, snr_db: float, seed: int):
    """The 802.15.4 bus between robots that all hear each other at ``snr_db`` (Rayleigh fading: losses)."""
    bus = MessageBus(BusParameters.from_preset(PRESETS["ieee802154"]), np.random.default_rng(seed), PERIOD_S,
                     robot_count=n)
    link = link_conditions(np.full((n, n), snr_db), True)
    return bus, (lambda tick: tuple(tuple(row) for row in bus.step(tick * PERIOD_S, link)))


def test_startup_election_over_a_clean_bus_elects_the_closest_traveler():
    n = 6
    remaining = np.array([4.0, np.inf, 2.0, 1.5, np.inf, 3.0])
    machine = RoleMachine(n, 1, host=0, bus_period_s=PERIOD_S)
    machine.start(np.isfinite(remaining))
    bus, step = lossy_802154_bus(n, 40.0, seed=0)
    window = election_window_ticks(n, 1)
    history = run_over(machine, step, bus.send, remaining, window + 12)
    assert (history[:window] != Role.PRIME_TRAVELER).all()  # nobody before the host decides
    assert machine.prime == 3
    # Offer, ack, confirm: three ticks after the decision.
    assert np.argmax(history[:, 3] == Role.PRIME_TRAVELER) == window + 3
    summary = bus.summary()
    assert summary["radio_election_packets_sent"] > 0 and summary["radio_handover_packets_sent"] == 1
    assert summary["radio_handover_confirm_packets_sent"] == 1 and summary["radio_handover_ack_packets_sent"] == 1


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(4, 8), snr_db=st.floats(1.0, 5.0))
@example(seed=13467, n=4, snr_db=1.0)
def test_election_converges_over_the_lossy_bus(seed, n, snr_db):
    """Frames lost to fading: one prime traveler at most at every tick, and one within a few windows."""
    rng = np.random.default_rng(seed)
    has_target = rng.random(n) < 0.6
    has_target[rng.integers(n)] = True
    remaining = np.where(has_target, rng.uniform(1.0, 5.0, n), np.inf)
    machine = RoleMachine(n, 1, host=int(rng.integers(n)), bus_period_s=PERIOD_S)
    machine.start(has_target)
    bus, step = lossy_802154_bus(n, snr_db, seed)
    # At 1 dB about 43 % of frames arrive and the handover's offer and confirm wait out their retransmission
    # timeouts: over 600 cases the first prime came by 6 windows + 39 ticks, one rarer one (seed 13467, n 4)
    # at + 79; the horizon leaves twice that.
    history = run_over(machine, step, bus.send, remaining, 6 * election_window_ticks(n, 1) + 160)
    assert bus.summary()["radio_delivery_ratio"] < 1.0  # the radio did lose frames
    assert machine.prime >= 0 and has_target[machine.prime]
    assert (history == Role.PRIME_TRAVELER).sum(axis=1).max() <= 1


fates = st.lists(st.tuples(st.booleans(), st.integers(0, 6)), min_size=1, max_size=80)


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(fates=fates, seed=st.integers(0, 2**32 - 1), n=st.integers(2, 6))
def test_token_never_duplicated_over_any_loss_pattern(fates, seed, n):
    """Algorithm 1 with random role events over a channel that loses and delays copies by script: the
    handover is never duplicated (never two prime travelers nor two holders, checked every tick), and the
    token is not lost for good."""
    rng = np.random.default_rng(seed)
    machine = RoleMachine(n, 1, host=0, bus_period_s=PERIOD_S)
    machine.start(rng.random(n) < 0.6)
    channel = ScriptedBus(fates, n)
    remaining = rng.uniform(0.5, 10.0, n)

    def events(tick, roles):
        travelling = np.isin(roles, [Role.PRIME_TRAVELER, Role.SECONDARY_TRAVELER])
        return ((roles == Role.CONNECTOR) & (rng.random(n) < 0.05), travelling & (rng.random(n) < 0.02),
                (roles == Role.ANCHOR) & (rng.random(n) < 0.05))

    run_over(machine, channel.step, channel.send, remaining, 250, events=events)
    # Liveness once the losses stop: a given-up offer returns the token, a given-up confirm is sent again,
    # so the token ends up held by exactly one robot.
    channel.fates, channel.used = [(False, 0)], 0
    run_over(machine, channel.step, channel.send, remaining, 200, start=250)
    assert machine.holds_token.sum() == 1


def test_a_lost_confirm_is_sent_again_until_the_winner_holds_the_token():
    """The winner acks the offer, then every copy of the confirm is lost: the old holder may not take the
    token back (the winner might hold it); it re-sends the confirm, and the winner becomes prime."""
    n = 2
    remaining = np.array([np.inf, 1.0])
    machine = RoleMachine(n, 1, host=0, bus_period_s=PERIOD_S)
    machine.start(np.isfinite(remaining))
    channel = ScriptedBus([(False, 0)], n)
    blocked = {"on": False}

    def send(message, time_s):
        if blocked["on"] and message.kind == "handover_confirm":
            return message  # lost
        return channel.send(message, time_s)

    window = election_window_ticks(n, 1)
    blocked["on"] = True
    history = run_over(machine, channel.step, send, remaining, window + 80)
    assert (history[:, 1] != Role.PRIME_TRAVELER).all() and machine.token_in_flight
    assert machine.token_recoveries >= 1 and not machine.holds_token.any()
    blocked["on"] = False
    history = run_over(machine, channel.step, send, remaining, 80, start=window + 80)
    assert machine.prime == 1 and machine.holds_token.tolist() == [False, True]


def test_an_offer_given_up_leaves_the_token_with_the_host():
    """The winner hears no offer: the host's offer is given up, the host keeps the token (nobody else ever
    acts on that offer) and runs a new round, whose offer goes through once the winner is in reach."""
    n = 3
    remaining = np.array([np.inf, 1.0, 2.0])
    machine = RoleMachine(n, 1, host=0, bus_period_s=PERIOD_S)
    machine.start(np.isfinite(remaining))
    channel = ScriptedBus([(False, 0)], n)
    blocked = {"on": True}

    def send(message, time_s):
        if blocked["on"] and message.kind == "handover" and message.receivers == (1,):
            return message  # lost
        return channel.send(message, time_s)

    window = election_window_ticks(n, 1)
    # Decided at tick `window`; ten copies of the offer five ticks apart, given up 50 ticks after the first.
    history = run_over(machine, channel.step, send, remaining, window + 52)
    assert (history != Role.PRIME_TRAVELER).all()
    assert machine.holds_token.tolist() == [True, False, False] and machine.rounds[0] is not None
    blocked["on"] = False
    run_over(machine, channel.step, send, remaining, 60, start=window + 52)
    assert machine.prime == 1


# --- the efficiency consensus (eq. 13) -------------------------------------------------------------

def test_consensus_uses_only_the_neighbours_whose_message_arrived():
    def consensus(sender, value, receiver):
        return Delivery(Message(CONSENSUS_KIND, sender, None, value, 8, sequence=0, sent_s=0.0), receiver, 0.0)

    inbox = ((consensus(1, 0.2, 0), consensus(2, 0.5, 0), consensus(2, 0.6, 0)), (), (consensus(0, 0.9, 2),))
    heard, arrived = heard_estimates(inbox, 3)
    assert arrived.tolist() == [[False, True, True], [False, False, False], [True, False, False]]
    assert heard[0, 1] == 0.2 and heard[0, 2] == 0.6 and heard[2, 0] == 0.9  # the latest value wins
    estimates = np.array([0.1, 0.4, 0.3])
    gain, dt = 2.0, 0.01
    updated = consensus_step(estimates, arrived, np.zeros(3, dtype=bool), np.zeros(3), gain, dt, heard)
    # Robot 0 hears 1 and 2; robot 1 nobody (keeps its value); robot 2 hears 0 only.
    expected = [0.1 + dt * gain * (0.2 + 0.6 - 2 * 0.1), 0.4, 0.3 + dt * gain * (0.9 - 0.3)]
    np.testing.assert_allclose(updated, expected, rtol=0, atol=1e-15)
    # Without the bus, every neighbour's own estimate.
    in_process = consensus_step(estimates, arrived, np.zeros(3, dtype=bool), np.zeros(3), gain, dt)
    np.testing.assert_allclose(in_process, [0.1 + dt * gain * (0.4 + 0.3 - 0.2), 0.4, 0.3 + dt * gain * (0.1 - 0.3)],
                               rtol=0, atol=1e-15)


# --- in the loop -----------------------------------------------------------------------------------

def test_connected_office_under_ieee802154_talks_over_the_bus(tmp_path):
    from tether.runner import build_simulation, run

    scenario = load("connected-office", ['radio.preset="ieee802154"'], seed=1, duration_s=0.6)
    run(scenario, tmp_path / "run")
    metrics = json.loads((tmp_path / "run" / "metrics.json").read_text())
    n = 10
    offered = metrics["radio_consensus_packets_sent"] + metrics["radio_consensus_packets_superseded"]
    assert 60 * n - n <= offered <= 60 * n  # one a robot a tick (the last may still wait)
    assert metrics["radio_election_packets_sent"] > 0 and metrics["radio_election_delivery_ratio"] > 0.9
    assert metrics["radio_handover_packets_sent"] >= 1 and metrics["radio_handover_confirm_packets_sent"] >= 1
    assert metrics["radio_consensus_latency_mean_s"] < 0.05  # the newest value only: no growing backlog
    assert metrics["prime_elections"] == 1 and metrics["token_recoveries"] == 0

    # Under ideal the method keeps its in-process exchange: nothing on the bus.
    ideal = replace(scenario, radio=load("connected-office", [], seed=1).radio)
    sim = build_simulation(ideal)
    for _ in range(5):
        frame, healthy = sim.tick()
        assert healthy and frame.commands.outbox == ()
    # Two prime travelers would end the run "diverged" with the reason, not crash it.
    strategy = sim.strategy
    strategy.roles = np.array(strategy.roles)
    strategy.roles[[2, 5]] = PRIME_CODE
    assert strategy.violation(frame.commands) == "2 prime travelers at once (quad2, quad5)"


# --- the bus's latest-only messages ----------------------------------------------------------------

def test_a_latest_only_message_replaces_its_waiting_predecessor():
    bus = MessageBus(BusParameters.from_preset(PRESETS["ieee802154"]), np.random.default_rng(0), PERIOD_S,
                     robot_count=3)
    link = link_conditions(np.full((3, 3), 60.0), True)
    for value in (0.1, 0.2, 0.3):
        bus.send(Message(CONSENSUS_KIND, 0, None, value, 8, latest_only=True), 0.0)
    bus.send(Message(CONSENSUS_KIND, 0, None, 0.9, 8), 0.0)  # not latest-only: kept, and it replaces nothing
    bus.send(Message(CONSENSUS_KIND, 0, None, 0.4, 8, latest_only=True), 0.0)
    bus.send(Message("other", 0, None, 1.0, 8, latest_only=True), 0.0)  # another kind: kept
    rows = bus.step(0.0, link)
    assert [(d.message.kind, d.message.payload) for d in rows[1]] == [
        (CONSENSUS_KIND, 0.9), (CONSENSUS_KIND, 0.4), ("other", 1.0)]
    summary = bus.summary()
    assert summary["radio_consensus_packets_superseded"] == 3 and summary["radio_consensus_packets_sent"] == 2
    assert summary["radio_packets_superseded"] == 3 and summary["radio_other_packets_superseded"] == 0


def test_a_latest_only_message_never_cuts_one_already_on_the_air():
    bus = MessageBus(BusParameters.from_preset(PRESETS["ieee802154"]), np.random.default_rng(0), PERIOD_S,
                     robot_count=2)
    link = link_conditions(np.full((2, 2), 60.0), True)
    bus.send(Message(ELECTION_KIND, 0, None, "long", 300, latest_only=True), 0.0)  # three frames, two fit a tick
    assert bus.step(0.0, link)[1] == []
    bus.send(Message(ELECTION_KIND, 0, None, "newer", 20, latest_only=True), PERIOD_S)
    assert [d.message.payload for d in bus.step(PERIOD_S, link)[1]] == ["long", "newer"]
    assert bus.summary()["radio_election_packets_superseded"] == 0


def test_split_consensus_is_heard_estimates_and_the_other_deliveries():
    """The one pass over the inbox gives the per-message loop's heard values and arrivals, and leaves every
    other delivery, in order, to the role machine."""
    def reference(inbox, n):
        heard, arrived = np.full((n, n), np.nan), np.zeros((n, n), dtype=bool)
        for robot, deliveries in enumerate(inbox):
            for delivery in deliveries:
                if delivery.message.kind == CONSENSUS_KIND and delivery.receiver == robot:
                    heard[robot, delivery.message.sender] = delivery.message.payload
                    arrived[robot, delivery.message.sender] = True
        return heard, arrived

    rng = np.random.default_rng(3)
    n = 5
    for _ in range(50):
        inbox = []
        for robot in range(n):
            row = []
            for _ in range(int(rng.integers(0, 9))):
                sender = int(rng.choice([j for j in range(n) if j != robot]))
                kind = CONSENSUS_KIND if rng.random() < 0.7 else "election"
                message = Message(kind, sender, None, float(rng.random()), 8, sequence=0, sent_s=0.0)
                row.append(Delivery(message, robot, 0.0))
            inbox.append(tuple(row))
        heard, arrived, rest = split_consensus(tuple(inbox), n)
        expected_heard, expected_arrived = reference(inbox, n)
        np.testing.assert_array_equal(heard, expected_heard)
        np.testing.assert_array_equal(arrived, expected_arrived)
        assert rest == [[d for d in row if d.message.kind != CONSENSUS_KIND] for row in inbox]


def test_the_consensus_as_columns_is_the_consensus_as_rows():
    """The same messages sent as rows and as_arrays over two ideal buses: the split and the heartbeat
    monitor read the same heard values, arrivals, other deliveries and last-heard times from both."""
    rng = np.random.default_rng(5)
    n = 5
    buses = [MessageBus(BusParameters.from_preset(IDEAL), None, PERIOD_S, robot_count=n) for _ in range(2)]
    monitors = [HeartbeatMonitor(n, 0.05) for _ in range(2)]
    for tick in range(30):
        t = tick * PERIOD_S
        plan = [(int(rng.integers(n)), float(rng.random()), rng.random() < 0.8)
                for _ in range(int(rng.integers(0, 12)))]
        for bus, columns in zip(buses, (False, True)):
            for sender, value, consensus in plan:
                kind = CONSENSUS_KIND if consensus else "election"
                bus.send(Message(kind, sender, None, value, 8, as_arrays=columns and consensus), t)
        rows = [bus.step(t, None) for bus in buses]
        inboxes = [tuple(tuple(row) for row in r) for r in rows]
        plain, columnar = (split_consensus(inbox, n, bus.arrivals) for inbox, bus in zip(inboxes, buses))
        assert not buses[0].arrivals and (CONSENSUS_KIND in buses[1].arrivals) == any(c for *_, c in plan)
        np.testing.assert_array_equal(plain[0], columnar[0])
        np.testing.assert_array_equal(plain[1], columnar[1])
        assert [list(row) for row in plain[2]] == [list(row) for row in columnar[2]]
        declared = [monitor.step(t, inbox, bus.arrivals) for monitor, inbox, bus in zip(monitors, inboxes, buses)]
        assert declared[0] == declared[1]
        np.testing.assert_array_equal(monitors[0].last_heard, monitors[1].last_heard)
        np.testing.assert_array_equal(monitors[0].silent, monitors[1].silent)
    assert buses[0].summary() == buses[1].summary()
    assert sorted(monitors[0].withdrawn) == sorted(monitors[1].withdrawn)
    assert monitors[0].detections and monitors[0].withdrawn  # silences and hearing again both happened
