"""The bus's compiled scheduling against the plain loop it replaces (``ReferenceMessageBus``): the same
frames at the same instants, the same random draws in the same order, the same deliveries and figures."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sim.radio.bus import (BusParameters, Message, MessageBus, ReferenceMessageBus, _arrivals_of, broadcasts,
                           link_conditions, link_from_pairs)
from sim.radio.presets import IDEAL, IEEE802154, NRF24, WIFI

PRESETS = {"ieee802154": IEEE802154, "nrf24": NRF24, "wifi": WIFI}
# (model, Rician K): every branch of the per-receiver fading draw.
FADINGS = [("none", 0.0), ("rayleigh", 0.0), ("rician", 0.0), ("rician", 3.5), ("rician", math.inf)]


@st.composite
def bus_cases(draw):
    n = draw(st.integers(1, 9))
    preset = draw(st.sampled_from(sorted(PRESETS)))
    fading, k = draw(st.sampled_from(FADINGS))
    period_s = draw(st.sampled_from([0.005, 0.01, 0.02]))
    # SNRs where frames are sure, lost or anything between; -inf: no link; NaN: the diagonal's figure.
    snr = np.array(draw(st.lists(st.sampled_from([-math.inf, -5.0, 0.0, 1.5, 3.0, 6.0, 9.0, 30.0]),
                                 min_size=n * n, max_size=n * n))).reshape(n, n)
    np.fill_diagonal(snr, np.nan)
    sense = np.array(draw(st.lists(st.booleans(), min_size=n * n, max_size=n * n))).reshape(n, n)
    if draw(st.booleans()):
        sense = sense | sense.T
    robot = st.integers(0, n - 1)
    message = st.tuples(robot, st.one_of(st.none(), st.sets(robot, max_size=n)), st.integers(1, 400),
                        st.sampled_from([0.0, 0.0, 0.3, 0.999]))
    ticks = draw(st.lists(st.lists(message, max_size=3 * n), min_size=1, max_size=8))
    return PRESETS[preset], fading, k, period_s, snr, sense, ticks, draw(st.integers(0, 2**32 - 1))


def _frame_fits(params: BusParameters, size: int, period_s: float) -> bool:
    return float(params.airtime_s(np.array(params.frame_payloads(size))).max()) <= period_s


def _same(a, b) -> bool:
    return a == b or (isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b))


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(bus_cases())
def test_the_compiled_bus_is_the_reference_loop(case):
    preset, fading, k, period_s, snr, sense, ticks, seed = case
    params = replace(BusParameters.from_preset(preset), fading_model=fading, rician_k=k)
    n = snr.shape[0]
    link = link_conditions(snr, sense)
    buses = [cls(params, np.random.default_rng(seed), period_s, robot_count=n)
             for cls in (MessageBus, ReferenceMessageBus)]
    extra_ticks = 4  # then a few ticks with nothing new, so that queued frames go out
    for tick in range(len(ticks) + extra_ticks):
        time_s = tick * period_s
        sends = []
        for sender, receivers, size, offset in (ticks[tick] if tick < len(ticks) else []):
            targets = None if receivers is None else tuple(sorted(receivers - {sender}))
            if not _frame_fits(params, size, period_s):
                continue
            # even sizes are periodic state (latest_only): the queue's superseding against the reference's
            # sizes divisible by 5 arrive as columns (as_arrays), the consensus's way
            columns = size % 5 == 0
            sends.append((Message("kind%d" % (size % 3), sender, targets, float(size) if columns else None, size,
                                  latest_only=size % 2 == 0, as_arrays=columns), time_s + offset * period_s))
        # the fast bus takes each run of messages sent at one instant at once (a tick's outbox), the
        # reference one by one
        for sent_at, run in itertools.groupby(sends, key=lambda sent: sent[1]):
            buses[0].send_all([message for message, _ in run], sent_at)
        for message, sent_at in sends:
            buses[1].send(message, sent_at)
        fast, reference = (bus.step(time_s, link) for bus in buses)
        assert [[(d.receiver, d.message.sequence, d.arrival_s) for d in row] for row in fast] == \
               [[(d.receiver, d.message.sequence, d.arrival_s) for d in row] for row in reference]
        assert not any(d.message.as_arrays for row in fast for d in row)
        assert buses[0].arrivals.keys() == buses[1].arrivals.keys()
        for kind, columns in buses[0].arrivals.items():
            expected = buses[1].arrivals[kind]
            assert all(np.array_equal(a, b) for a, b in zip(vars(columns).values(), vars(expected).values()))
        assert buses[0].rng.bit_generator.state == buses[1].rng.bit_generator.state  # the same draws
        assert all(_same(a, b) for a, b in zip(vars(buses[0].last_tick).values(),
                                               vars(buses[1].last_tick).values()))
        assert buses[0].queued() == buses[1].queued()
        assert [buses[0].queued(s) for s in range(n)] == [buses[1].queued(s) for s in range(n)]
    summaries = [bus.summary() for bus in buses]
    assert summaries[0].keys() == summaries[1].keys()
    assert all(_same(summaries[0][key], summaries[1][key]) for key in summaries[0])


def one_medium_both_buses(n: int, snr_db: float, seed: int, period_s: float):
    """The compiled bus and the reference, same seed, over ``n`` robots all in one another's carrier sense
    at ``snr_db``: (buses, link)."""
    snr = np.full((n, n), snr_db)
    np.fill_diagonal(snr, np.nan)
    params = BusParameters.from_preset(IEEE802154)
    buses = [cls(params, np.random.default_rng(seed), period_s, robot_count=n)
             for cls in (MessageBus, ReferenceMessageBus)]
    return buses, link_conditions(snr, True)


def test_a_saturated_medium_matches_the_reference_over_many_ticks():
    """Ten robots in one another's carrier sense, each broadcasting every tick more than the air carries:
    the queues grow and both buses still agree, draw for draw."""
    n, period_s = 10, 0.01
    buses, link = one_medium_both_buses(n, 4.0, 11, period_s)
    for tick in range(120):
        for bus in buses:
            for robot in range(n):
                bus.send(Message("state", robot, None, None, 40), tick * period_s)
            if tick % 25 == 0:
                bus.send(Message("records", tick % n, ((tick + 1) % n,), None, 300), tick * period_s)
        fast, reference = (bus.step(tick * period_s, link) for bus in buses)
        assert [[(d.message.sequence, d.arrival_s) for d in row] for row in fast] == \
               [[(d.message.sequence, d.arrival_s) for d in row] for row in reference]
    assert buses[0].queued() == buses[1].queued() > 500
    summaries = [bus.summary() for bus in buses]
    assert summaries[0] == summaries[1]
    assert 0.0 < summaries[0]["radio_delivery_ratio"] < 1.0


def test_the_802154_curve_is_exactly_zero_from_the_buses_sure_snr():
    """The bus skips the PER of frames above this SNR; the reference's PER there is exactly 0."""
    from sim.radio import bus, channel

    sure = bus._ZERO_BER_SNR_DB["oqpsk_dsss_802154"]
    snr = np.concatenate([np.linspace(sure, sure + 60.0, 20001), [300.0, 1e300, np.finfo(float).max]])
    with np.errstate(over="ignore"):  # 10^(SNR / 10) is inf at the top: the BER is then exactly 0 too
        ber = channel.ber_oqpsk_dsss_802154(snr)
    assert not np.any(ber)
    assert not np.any(channel.packet_error_rate(ber, 8 * 127))
    assert channel.ber_oqpsk_dsss_802154(np.array([sure - 2.0]))[0] > 0.0  # and the margin is not wide


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.integers(0, 6),
                          st.one_of(st.just(set(range(7))), st.sets(st.integers(0, 6), min_size=1)),
                          st.sampled_from([0.001, 0.002, 0.003])), min_size=1, max_size=12))
def test_the_columns_are_the_rows_order(records):
    """``_arrivals_of``'s compiled ordering is numpy's lexsort by (receiver, arrival, sequence), for broadcasts
    that reached every other robot (passed as a count) and the others (their receivers listed)."""
    messages = [(replace(Message("consensus", sender, None, float(k), 8, as_arrays=True), sequence=k, sent_s=0.0),
                 sorted(reached - {sender}) or [(sender + 1) % 7], arrival) for k, (sender, reached, arrival)
                in enumerate(records)]
    columns = _arrivals_of(messages, 7)
    entries = [(r, a, m.sequence, m.sender, m.payload) for m, reached, a in messages for r in reached]
    entries.sort(key=lambda e: (e[0], e[1], e[2]))
    assert list(zip(columns.receiver.tolist(), columns.arrival_s.tolist(), columns.sequence.tolist(),
                    columns.sender.tolist(), columns.payload.tolist())) == entries


def test_broadcasts_are_the_messages_one_by_one():
    made = broadcasts("consensus", np.array([0.5, 0.25, 1.0]), 8, latest_only=True, as_arrays=True)
    assert made == tuple(Message("consensus", i, None, v, 8, latest_only=True, as_arrays=True)
                         for i, v in enumerate([0.5, 0.25, 1.0]))


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 9).flatmap(lambda n: st.tuples(
    st.just(n),
    st.lists(st.sampled_from([-math.inf, math.nan, -120.0, -95.0, -85.0, -85.0 + 1e-12, -40.0, math.inf]),
             min_size=n * (n - 1) // 2, max_size=n * (n - 1) // 2),
    st.lists(st.floats(-50.0, 80.0) | st.sampled_from([-math.inf, math.nan]),
             min_size=n * (n - 1) // 2, max_size=n * (n - 1) // 2))))
def test_the_link_from_pairs_is_the_radio_states_matrices(case):
    """``link_from_pairs``' compiled pass gives the matrices the bus was given before: the radio state's SNR
    (``RadioState._matrix``: both triangles, NaN diagonal) and rx power >= the carrier-sense level."""
    n, rx, snr = case
    first, second = np.triu_indices(n, 1)
    rx, snr = np.array(rx, dtype=float), np.array(snr, dtype=float)
    expected_snr = np.empty((n, n))
    expected_snr[first, second] = snr
    expected_snr[second, first] = snr
    np.fill_diagonal(expected_snr, np.nan)
    expected_rx = np.empty((n, n))
    expected_rx[first, second] = rx
    expected_rx[second, first] = rx
    np.fill_diagonal(expected_rx, np.nan)
    with np.errstate(invalid="ignore"):
        expected_sense = expected_rx >= -85.0
    link = link_from_pairs(n, (first, second), snr, rx, -85.0)
    assert np.array_equal(link.snr_db, expected_snr, equal_nan=True)
    assert link.snr_db.dtype == expected_snr.dtype and not link.snr_db.flags.writeable
    assert np.array_equal(link.carrier_sense, expected_sense) and link.carrier_sense.dtype == bool


def test_the_compiled_802154_per_lies_within_its_bound_of_numpys():
    """``_per_802154``'s PER is numpy's within the bound it gives, so a uniform it decides, numpy's decides
    the same way; the bound is small enough that it decides nearly every draw."""
    from sim.radio.bus import _per_802154
    from sim.radio.channel import packet_error_rate_at_snr

    rng = np.random.default_rng(3)
    snr = np.concatenate([np.linspace(-30.0, 20.0, 2001), rng.uniform(-10.0, 20.0, 2000), [-np.inf, -1e308]])
    bits = rng.integers(1, 1100, len(snr)).astype(float)
    exact = packet_error_rate_at_snr("oqpsk_dsss_802154", snr, math.inf, 250e3, bits)
    for level, length, reference in zip(snr, bits, exact):
        per, bound = _per_802154(level, length)
        assert abs(per - reference) <= bound
        assert bound < 1e-5


def test_a_kernel_draws_from_a_generator_by_its_pointers_as_from_the_generator():
    """``sim.compiled.generator_at``: the Generator rebuilt in a kernel from ``generator_pointers`` draws what
    the Generator passed to a kernel draws, and advances the same state."""
    from sim.compiled import generator_at, generator_pointers, kernel

    @kernel
    def by_pointers(a, b, c, d, e, out):
        rng = generator_at(a, b, c, d, e)
        for k in range(out.shape[0]):
            out[k] = rng.random() + rng.standard_exponential() + rng.integers(0, 5)

    @kernel
    def by_generator(rng, out):
        for k in range(out.shape[0]):
            out[k] = rng.random() + rng.standard_exponential() + rng.integers(0, 5)

    rngs = np.random.default_rng(9), np.random.default_rng(9)
    pointers = generator_pointers(rngs[0])
    for _ in range(3):
        drawn = np.empty(40), np.empty(40)
        by_pointers(*pointers, drawn[0])
        by_generator(rngs[1], drawn[1])
        assert np.array_equal(*drawn)
        assert rngs[0].bit_generator.state == rngs[1].bit_generator.state
        assert rngs[0].random() == rngs[1].random()  # numpy's own draws go on from the same state


def test_latest_only_broadcasts_over_a_saturated_medium_match_the_reference():
    """Every robot's state broadcast each tick, latest_only and as columns (the consensus's way), more than
    the air carries, sent as one outbox per tick: the leftovers superseded each tick as the reference's
    plain filter does, draw for draw."""
    n, period_s = 12, 0.01
    buses, link = one_medium_both_buses(n, 8.0, 5, period_s)
    for tick in range(80):
        outbox = broadcasts("state", np.arange(n) + tick, 8, latest_only=True, as_arrays=True)
        if tick % 7 == 0:
            outbox += (Message("records", tick % n, ((tick + 3) % n,), None, 200, latest_only=True),)
        buses[0].send_all(outbox, tick * period_s)
        for message in outbox:
            buses[1].send(message, tick * period_s)
        rows = [bus.step(tick * period_s, link) for bus in buses]
        assert [[(d.message.sequence, d.arrival_s) for d in row] for row in rows[0]] == \
               [[(d.message.sequence, d.arrival_s) for d in row] for row in rows[1]]
        for kind, columns in buses[0].arrivals.items():
            expected = buses[1].arrivals[kind]
            assert all(np.array_equal(a, b) for a, b in zip(vars(columns).values(), vars(expected).values()))
        assert buses[0].rng.bit_generator.state == buses[1].rng.bit_generator.state
        assert [buses[0].queued(s) for s in range(n)] == [buses[1].queued(s) for s in range(n)]
    summaries = [bus.summary() for bus in buses]
    assert summaries[0]["radio_state_packets_superseded"] > 100
    assert all(_same(summaries[0][key], summaries[1][key]) for key in summaries[0])


def test_retuning_between_ideal_and_real_moves_the_queues_as_the_reference_keeps_them():
    """A retune to 'ideal' and back moves the frame table's queues, in-flight receivers and counters into
    the deques and back (``MessageBus``); the reference keeps deques throughout: the same figures."""
    n, period_s = 6, 0.01
    buses, link = one_medium_both_buses(n, 4.0, 3, period_s)
    ideal = BusParameters.from_preset(IDEAL)
    for tick in range(30):
        if tick in (10, 20):
            for bus in buses:
                real = bus.params
                bus.params = ideal
                bus.params = real
        for bus in buses:
            for robot in range(n):
                bus.send(Message("state", robot, None, float(robot), 40, latest_only=True, as_arrays=True),
                         tick * period_s)
            if tick % 4 == 0:
                bus.send(Message("records", tick % n, ((tick + 1) % n,), None, 300), tick * period_s)
        fast, reference = (bus.step(tick * period_s, link) for bus in buses)
        assert [[(d.message.sequence, d.arrival_s) for d in row] for row in fast] == \
               [[(d.message.sequence, d.arrival_s) for d in row] for row in reference]
        assert buses[0].queued() == buses[1].queued()
    summaries = [bus.summary() for bus in buses]
    assert all(_same(summaries[0][key], summaries[1][key]) for key in summaries[0])
    assert summaries[0].keys() == summaries[1].keys()


@st.composite
def batch_cases(draw):
    """Outboxes mixing ``Broadcasts`` items (all robots or some, latest_only or not) with single messages."""
    n = draw(st.integers(1, 9))
    preset = draw(st.sampled_from(sorted(PRESETS)))
    period_s = draw(st.sampled_from([0.005, 0.01]))
    robot = st.integers(0, n - 1)
    single = st.tuples(st.just("message"), robot, st.integers(1, 300), st.booleans())
    batch = st.tuples(st.just("batch"), st.one_of(st.none(), st.sets(robot, min_size=1)),
                      st.sampled_from([8, 8, 40, 150]), st.booleans())
    ticks = draw(st.lists(st.lists(st.one_of(single, batch), max_size=4), min_size=1, max_size=8))
    snr = draw(st.sampled_from([3.0, 6.0, 30.0]))
    return PRESETS[preset], n, period_s, snr, ticks, draw(st.integers(0, 2**32 - 1))


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(batch_cases())
def test_broadcasts_items_enter_the_table_as_their_messages_into_the_reference(case):
    """A ``Broadcasts`` item in an outbox is its ``messages()`` at its place: the frame table's rows made
    kept per shape (``MessageBus._batch_template``) give the reference's sequences, draws, arrivals and counters."""
    from sim.radio.bus import Broadcasts

    preset, n, period_s, level, ticks, seed = case
    params = BusParameters.from_preset(preset)
    snr = np.full((n, n), level)
    np.fill_diagonal(snr, np.nan)
    link = link_conditions(snr, True)
    buses = [cls(params, np.random.default_rng(seed), period_s, robot_count=n)
             for cls in (MessageBus, ReferenceMessageBus)]
    for tick, items in enumerate(ticks + [[]] * 4):
        outbox = []
        for what, who, size, flag in items:
            if what == "message":
                outbox.append(Message("one", who, None, float(tick), size, latest_only=flag, as_arrays=True))
            else:
                senders = None if who is None else sorted(who)
                count = n if senders is None else len(senders)
                outbox.append(Broadcasts(f"state{size}", np.arange(count) + 0.5 * tick, size, flag, senders))
        for bus in buses:
            bus.send_all(tuple(outbox), tick * period_s)
        for bus in buses:
            bus.step(tick * period_s, link)
        arrivals = [bus.arrivals for bus in buses]
        assert arrivals[0].keys() == arrivals[1].keys()
        for kind, columns in arrivals[0].items():
            assert all(np.array_equal(a, b) for a, b in zip(vars(columns).values(), vars(arrivals[1][kind]).values()))
        assert buses[0].rng.bit_generator.state == buses[1].rng.bit_generator.state
        assert [buses[0].queued(s) for s in range(n)] == [buses[1].queued(s) for s in range(n)]
    summaries = [bus.summary() for bus in buses]
    assert summaries[0].keys() == summaries[1].keys()
    assert all(_same(summaries[0][key], summaries[1][key]) for key in summaries[0])


def test_broadcasts_item_is_its_messages_and_keeps_the_working_senders():
    from sim.radio.bus import Broadcasts, each_message

    batch = Broadcasts("consensus", np.array([0.5, 0.25, 1.0]), 8, latest_only=True)
    assert batch.messages() == broadcasts("consensus", [0.5, 0.25, 1.0], 8, latest_only=True, as_arrays=True)
    kept = batch.kept(np.array([True, False, True]))
    assert [(m.sender, m.payload) for m in kept.messages()] == [(0, 0.5), (2, 1.0)]
    single = Message("election", 1, None, 3, 4)
    assert list(each_message((single, kept))) == [single, *kept.messages()]


def test_the_inbox_is_the_steps_rows_as_tuples():
    """``inbox``, what the loop takes each tick, is ``step``'s rows as tuples, None where they hold nothing
    (a tick of columns only), with the same arrivals, on the compiled bus and on the reference."""
    n, period_s = 6, 0.01
    for cls in (MessageBus, ReferenceMessageBus):
        buses = [cls(BusParameters.from_preset(IEEE802154), np.random.default_rng(3), period_s, robot_count=n)
                 for _ in range(2)]
        snr = np.full((n, n), 12.0)
        np.fill_diagonal(snr, np.nan)
        link = link_conditions(snr, True)
        seen = set()
        for tick in range(40):
            for bus in buses:
                bus.send_all(broadcasts("estimate", np.arange(n) * 0.5 + tick, 8, as_arrays=True), tick * period_s)
                if tick % 7 == 0:
                    bus.send(Message("records", tick % n, ((tick + 2) % n,), tick, 60), tick * period_s)
            rows, inbox = buses[0].step(tick * period_s, link), buses[1].inbox(tick * period_s, link)
            expected = tuple(map(tuple, rows)) if any(rows) else None
            assert (inbox is None) == (expected is None)
            if inbox is not None:
                assert [[(d.receiver, d.message.sequence, d.arrival_s) for d in row] for row in inbox] == \
                       [[(d.receiver, d.message.sequence, d.arrival_s) for d in row] for row in expected]
            assert buses[0].arrivals.keys() == buses[1].arrivals.keys()
            seen.add(inbox is None)
        assert seen == {True, False}  # ticks with rows and ticks of columns only


def test_broadcasts_handed_over_are_the_copied_ones():
    """``Broadcasts.handed_over`` takes the caller's array as it is; the bus sends the same frames, draws
    and arrivals as from the constructor's copy. An array it cannot take as it is gets the constructor."""
    from sim.radio.bus import Broadcasts

    n, period_s = 5, 0.01
    buses = [MessageBus(BusParameters.from_preset(IEEE802154), np.random.default_rng(4), period_s, robot_count=n)
             for _ in range(2)]
    snr = np.full((n, n), 8.0)
    np.fill_diagonal(snr, np.nan)
    link = link_conditions(snr, True)
    for tick in range(30):
        values = np.arange(n) + 0.25 * tick
        buses[0].send_all((Broadcasts("estimate", values, 8, latest_only=True),), tick * period_s)
        handed = Broadcasts.handed_over("estimate", values, 8, latest_only=True)
        assert handed.values is values
        buses[1].send_all((handed,), tick * period_s)
        for bus in buses:
            bus.step(tick * period_s, link)
        assert buses[0].arrivals.keys() == buses[1].arrivals.keys()
        for kind, columns in buses[0].arrivals.items():
            other = vars(buses[1].arrivals[kind]).values()
            assert all(np.array_equal(a, b) for a, b in zip(vars(columns).values(), other))
    assert buses[0].summary() == buses[1].summary()
    strided = np.arange(2.0 * n)[::2]
    assert Broadcasts.handed_over("estimate", strided, 8).values is not strided
    with pytest.raises(ValueError):
        Broadcasts.handed_over("estimate", np.zeros(3), 0)


@st.composite
def exchange_cases(draw):
    n = draw(st.integers(2, 8))
    preset = draw(st.sampled_from(sorted(PRESETS)))
    fading, k = draw(st.sampled_from(FADINGS))
    snr = np.array(draw(st.lists(st.sampled_from([-math.inf, -5.0, 1.5, 3.0, 6.0, 30.0]),
                                 min_size=n * n, max_size=n * n))).reshape(n, n)
    np.fill_diagonal(snr, np.nan)
    sense = np.array(draw(st.lists(st.booleans(), min_size=n * n, max_size=n * n))).reshape(n, n)
    # per tick: nothing, the whole team's batch, a batch of some senders, or a batch after a unicast
    outbox = st.sampled_from(["none", "batch", "batch", "batch", "some", "unicast and batch"])
    ticks = draw(st.lists(outbox, min_size=1, max_size=25))
    matrices = draw(st.booleans())  # the channel's own LinkMatrices, or a plain LinkConditions
    return PRESETS[preset], fading, k, snr, sense, ticks, matrices, draw(st.integers(0, 2**32 - 1))


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(exchange_cases())
def test_exchange_is_send_all_then_inbox(case):
    """``MessageBus.exchange``, the loop's one call a tick (an outbox of one batch entering the table and the
    period in one compiled call), gives what ``send_all`` then ``inbox`` (or an idle ``step``) give: the same
    rows, arrivals, figures, queues and draws, tick after tick."""
    from sim.radio.bus import Broadcasts
    from sim.radio.medium import LinkMatrices

    preset, fading, k, snr, sense, ticks, matrices, seed = case
    n, period_s = snr.shape[0], 0.01
    params = replace(BusParameters.from_preset(preset), fading_model=fading, rician_k=k)
    buses = [MessageBus(params, np.random.default_rng(seed), period_s, robot_count=n) for _ in range(2)]
    plain = link_conditions(snr, sense)
    link = LinkMatrices(plain.snr_db, plain.carrier_sense) if matrices else plain
    for tick, plan in enumerate(ticks):
        time_s = tick * period_s
        values = np.arange(n) * 0.5 + tick
        if plan == "none":
            outbox = ()
        elif plan == "some":
            outbox = (Broadcasts("estimate", values[::2].copy(), 8, latest_only=True, senders=np.arange(0, n, 2)),)
        else:
            outbox = (Broadcasts.handed_over("estimate", values, 8, latest_only=True),)
            if plan == "unicast and batch":
                outbox = (Message("records", tick % n, ((tick + 1) % n,), tick, 120),) + outbox
        got = buses[0].exchange(outbox, time_s, lambda: link)
        if outbox:
            buses[1].send_all(outbox, time_s)
        if buses[1].idle:
            buses[1].step(time_s, None)
            expected = False
        else:
            expected = buses[1].inbox(time_s, link)
        assert (got is False) == (expected is False) and (got is None) == (expected is None)
        if got:
            assert [[(d.receiver, d.message.sequence, d.arrival_s) for d in row] for row in got] == \
                   [[(d.receiver, d.message.sequence, d.arrival_s) for d in row] for row in expected]
        assert buses[0].arrivals.keys() == buses[1].arrivals.keys()
        for kind, columns in buses[0].arrivals.items():
            other = vars(buses[1].arrivals[kind]).values()
            assert all(np.array_equal(a, b) for a, b in zip(vars(columns).values(), other))
        assert buses[0].rng.bit_generator.state == buses[1].rng.bit_generator.state
        assert all(_same(a, b) for a, b in zip(vars(buses[0].last_tick).values(), vars(buses[1].last_tick).values()))
        assert [buses[0].queued(s) for s in range(n)] == [buses[1].queued(s) for s in range(n)]
    summaries = [bus.summary() for bus in buses]
    assert all(_same(summaries[0][key], summaries[1][key]) for key in summaries[0])
