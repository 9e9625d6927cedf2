"""The medium's compiled kernels: one period's scheduling (``schedule_frames``) and the frame table that
holds ``sim.radio.bus.MessageBus``'s queues under a real preset, sent into (``enqueue``) and stepped
(``period``, ``book``) with one compiled call each.

Pure numba over numpy arrays; no MuJoCo, no I/O. ``sim.radio.bus.ReferenceMessageBus`` is the plain
Python loop these are held to (tests/test_radio_bus_fast.py).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from sim.compiled import generator_at, kernel, numpy_sum
from sim.radio import channel

# How ``_schedule_frames`` draws each receiver's fading gain: none, Exp(1) (Rayleigh, Rician K = 0), or a
# noncentral chi-square with 2 degrees of freedom over 2 (K + 1) (Rician), as ``channel.fading_gain_db`` does.
_NO_DRAW, _EXPONENTIAL, _NONCENTRAL_CHISQUARE = 0, 1, 2
# SNR (dB) from which a modulation's BER is exactly 0 in floating point, so a frame's PER is 0: for the
# 802.15.4 curve every term exp(20 SINR (1/k - 1)) underflows to 0 once 10 SINR > 746 (the k = 2 term;
# SINR > 18.7 dB); 19.5 dB leaves a margin (tests/test_radio_bus_fast.py checks the curve is 0 from it on).
_ZERO_BER_SNR_DB = {"oqpsk_dsss_802154": 19.5}


# The 802.15.4 curve's terms (channel.ber_oqpsk_dsss_802154): exponent factors 1/k - 1 and signed
# binomials (-1)^k C(16, k), k = 2..16, and the scale 8/15 * 1/16.
_OQPSK_FACTORS = channel._OQPSK_EXPONENT_FACTORS.copy()
_OQPSK_BINOMIALS = channel._SIGNED_BINOMIALS_802154.copy()
_OQPSK_SCALE = float(channel._OQPSK_SCALE)


@kernel
def _per_802154(snr_db, bits):
    """PER of a ``bits``-bit frame at ``snr_db`` on the 802.15.4 curve, and a bound on its distance from
    ``channel.packet_error_rate_at_snr``'s (numpy's exp, log1p and expm1 may round differently from these):
    each term's error within (|exponent| + 10) 1e-13 of it (exp's argument carries the power's relative
    error times the exponent; the sum's rounding over 15 terms is below 1e-14 of the terms' magnitude),
    the BER's then at most the terms' magnitudes' sum times that, and dPER/dBER = L (1 - PER) / (1 - BER)
    <= 2 L for BER <= 0.5; 1e-12 more for the PER's own operations."""
    sinr = 10.0 ** (snr_db / 10.0)
    total = 0.0
    error = 0.0
    for k in range(_OQPSK_FACTORS.shape[0]):
        exponent = 20.0 * sinr * _OQPSK_FACTORS[k]
        term = np.exp(exponent) * _OQPSK_BINOMIALS[k]
        total += term
        error += abs(term) * (abs(exponent) + 10.0) * 1e-13
    ber = min(max(total * _OQPSK_SCALE, 0.0), 0.5)
    error *= _OQPSK_SCALE
    per = min(max(-np.expm1(bits * np.log1p(-ber)), 0.0), 1.0)
    return per, 2.0 * bits * error + 1e-12


@kernel
def _schedule_frames(start_s, end_s, eps, sense, snr, queued, numbers, listed, fading_code,
                     noncentrality, gain_scale, sure_snr_db, decide, rng, popped, sent_frame, sent_finish, sent_draws,
                     draw_receiver, draw_snr, draw_bits, draw_gain, draw_uniform, draw_unsure, draw_alive, tally,
                     work_integers, work_reals):
    """One period of the shared medium (``ReferenceMessageBus._step_medium``'s loop, step for step).

    Sender s offers frames first[s] .. first[s] + count[s] - 1 in order (``queued``'s rows: first, count);
    frame f's send time, airtime, error bits and audience count are ``numbers[4 f:4 f + 4]`` (one flat
    array: quicker to build). Each round, every sender whose next frame is ready starts at max(ready, the
    end of the latest frame of anyone it senses); the earliest go, a tie broken by ``rng.integers``; a
    frame that would end after the period stops its sender. A frame that goes draws, per receiver of its
    audience (its audience count's receivers, listed in ``listed`` after the earlier frames', or every
    other robot when the count is -1), its fading gain and then, for all of them, a uniform: the reference's
    draws in its order. Fills ``popped`` (frames gone per sender), the frames gone in order with their end
    and the range of their draws (each with its receiver, mean SNR as ``numpy.nan_to_num(nan=-inf)`` gives
    it, frame bits, fading gain and uniform), and returns how many went. ``sense`` counts as True on the
    diagonal. ``draw_unsure`` marks the draws whose SNR with fading may lie below ``sure_snr_db``, where
    the PER may differ from 0 (judged here with 0.5 dB to spare, the exact PER is numpy's).

    With ``decide`` (the 802.15.4 curve), each such draw's PER is computed here too, with a bound on how far
    it can lie from numpy's (``_per_802154``): a uniform outside PER +- bound decides the frame
    (``draw_alive``) and the draw is no longer unsure; only a uniform within the bound, which numpy's exact
    PER must decide, stays unsure. Without it every draw is alive here and numpy decides the unsure ones.
    ``tally`` gets (unsure draws, draws lost here). ``work_integers`` (3, >= max(frames, N)) and
    ``work_reals`` (3, >= N) are scratch.
    """
    n = sense.shape[0]
    first, count = queued[0], queued[1]
    frames = numbers.reshape((-1, 4))
    sent_s, airtime_s, error_bits = frames[:, 0], frames[:, 1], frames[:, 2]
    audience_count = work_integers[0]
    audience_start = work_integers[1]  # where each frame's receivers are listed
    at = 0
    for f in range(frames.shape[0]):
        audience_count[f] = int(frames[f, 3])
        audience_start[f] = at
        at += max(audience_count[f], 0)
    largest = 1.7976931348623157e308  # numpy.finfo(float).max, what nan_to_num puts for +inf
    medium_free = work_reals[0, :n]  # per sender: the latest end of a frame of anyone it senses
    medium_free[:] = -np.inf
    ready = work_reals[1, :n]
    ready[:] = np.inf
    start = work_reals[2, :n]
    tied = work_integers[2]
    for s in range(n):
        if count[s] > 0 and sent_s[first[s]] < end_s - eps:
            ready[s] = max(start_s, sent_s[first[s]])
    sent = 0
    draws = 0
    unsure = 0
    lost = 0
    sent_draws[0] = 0
    while True:
        earliest = np.inf
        for s in range(n):
            start[s] = max(ready[s], medium_free[s])
            if start[s] < earliest:
                earliest = start[s]
        if earliest == np.inf:
            tally[0] = unsure
            tally[1] = lost
            return sent
        ties = 0
        for s in range(n):
            if start[s] <= earliest + eps:
                tied[ties] = s
                ties += 1
        sender = tied[rng.integers(0, ties)] if ties > 1 else tied[0]
        frame = first[sender] + popped[sender]
        finish = earliest + airtime_s[frame]
        if finish > end_s + eps:
            ready[sender] = np.inf
            continue
        popped[sender] += 1
        for s in range(n):
            if (s == sender or sense[s, sender]) and finish > medium_free[s]:
                medium_free[s] = finish
        ready[sender] = np.inf
        if popped[sender] < count[sender]:
            following = first[sender] + popped[sender]
            if sent_s[following] < end_s - eps:
                ready[sender] = max(start_s, sent_s[following])
        sent_frame[sent] = frame
        sent_finish[sent] = finish
        size = audience_count[frame]
        first_draw = draws
        if size < 0:
            for receiver in range(n):
                if receiver != sender:
                    draw_receiver[draws] = receiver
                    draws += 1
        else:
            for k in range(size):
                draw_receiver[draws] = listed[audience_start[frame] + k]
                draws += 1
        for d in range(first_draw, draws):
            level = snr[sender, draw_receiver[d]]
            if np.isnan(level):
                level = -np.inf
            elif level == np.inf:
                level = largest
            elif level == -np.inf:
                level = -largest
            draw_snr[d] = level
            draw_bits[d] = error_bits[frame]
            if fading_code == 1:
                gain = rng.standard_exponential()
            elif fading_code == 2:
                gain = rng.noncentral_chisquare(2.0, noncentrality) / gain_scale
            else:
                gain = 1.0
            draw_gain[d] = gain
            if fading_code == 0:  # a gain of 1: 0 dB
                draw_unsure[d] = not level >= sure_snr_db + 0.5
            else:
                draw_unsure[d] = not level + 10.0 * np.log10(max(gain, 1e-300)) >= sure_snr_db + 0.5
        for d in range(first_draw, draws):
            draw_uniform[d] = rng.random()
        for d in range(first_draw, draws):
            draw_alive[d] = True
            if draw_unsure[d] and decide:
                level = draw_snr[d]
                if fading_code != 0:
                    level = level + 10.0 * np.log10(max(draw_gain[d], 2.2250738585072014e-308))
                per, bound = _per_802154(level, draw_bits[d])
                if draw_uniform[d] >= per + bound:
                    draw_unsure[d] = False
                elif draw_uniform[d] < per - bound:
                    draw_unsure[d] = False
                    draw_alive[d] = False
                    lost += 1
            if draw_unsure[d]:
                unsure += 1
        sent += 1
        sent_draws[sent] = draws


# The frame table: every frame queued at a sender, one slot each, as a row of ``ints`` and of ``floats``; a
# sender's frames are a linked list in queue order (``I_NEXT``), and a unicast's receivers a row of ``listed``.
I_SENDER, I_SEQUENCE, I_KIND, I_FLAGS, I_NEXT, I_SIZE, I_PAYLOAD_BYTES = range(7)
F_SENT, F_AIRTIME, F_BITS, F_AUDIENCE, F_VALUE = range(5)  # audience: receivers listed, -1 every other robot
LAST, AS_ARRAYS, LATEST_ONLY = 1, 2, 4  # I_FLAGS: the message's last frame, and its Message flags
# ``queues``' rows, per sender: its first and last slot (-1: none), messages waiting, and the sequence of the
# message whose frames are going out (-1: none; its receivers still holding every frame are ``alive``'s row)
Q_HEAD, Q_TAIL, Q_WAITING, Q_FLYING = range(4)
# ``counts``: free slots (the first entries of ``free``), messages waiting, kinds' counters made, latencies logged
T_FREE, T_WAITING, T_KINDS_MADE, T_LOGGED = range(4)
# ``kinds``' rows, per kind: the summary's counters, and the rank of its counters' making (-1: not made),
# the order the summary adds the kinds in, as ``ReferenceMessageBus`` makes them
K_PACKETS, K_FRAMES, K_BYTES, K_ADDRESSED, K_DELIVERED, K_SUPERSEDED, K_RANK = range(7)


@kernel
def _made(kinds, counts, kind):
    if kinds[kind, K_RANK] < 0:
        kinds[kind, K_RANK] = counts[T_KINDS_MADE]
        counts[T_KINDS_MADE] += 1


@kernel
def _enqueue(ints, floats, listed, queues, free, counts, kinds, message_ints, message_values, message_listed,
             frame_spec, first_sequence, sent_s, dropped):
    """Queue messages sent at ``sent_s`` at their senders, in order, each superseding first when it is
    latest_only (what ``ReferenceMessageBus.send`` does). ``message_ints`` rows: sender, sequence (from
    ``first_sequence``), kind, flags (AS_ARRAYS, LATEST_ONLY), size, frames, audience count (-1: a broadcast);
    ``message_values``: each message's value (as_arrays); ``message_listed``: the receivers of those that list
    theirs, in order; ``frame_spec`` rows, each message's frames in order: payload bytes, airtime, error bits.
    Every argument is one flat array of its rows (quicker to build; a batch's rows are kept and passed again).
    The caller leaves enough free slots. Returns how many superseded messages' sequences it wrote to
    ``dropped``."""
    message_ints = message_ints.reshape((-1, 7))
    frame_spec = frame_spec.reshape((-1, 3))
    spec = 0
    listed_at = 0
    dropped_count = 0
    for m in range(message_ints.shape[0]):
        sender = message_ints[m, 0]
        kind = message_ints[m, 2]
        flags = message_ints[m, 3]
        if flags & LATEST_ONLY:
            # drop the waiting latest_only messages of its kind none of whose frames went out
            stale = 0
            previous = -1
            slot = queues[sender, Q_HEAD]
            flying = queues[sender, Q_FLYING]
            while slot >= 0:
                following = ints[slot, I_NEXT]
                if (ints[slot, I_FLAGS] & LATEST_ONLY) and ints[slot, I_KIND] == kind \
                        and ints[slot, I_SEQUENCE] != flying:
                    if previous < 0:
                        queues[sender, Q_HEAD] = following
                    else:
                        ints[previous, I_NEXT] = following
                    if queues[sender, Q_TAIL] == slot:
                        queues[sender, Q_TAIL] = previous
                    free[counts[T_FREE]] = slot
                    counts[T_FREE] += 1
                    if ints[slot, I_FLAGS] & LAST:
                        stale += 1
                        dropped[dropped_count] = ints[slot, I_SEQUENCE]
                        dropped_count += 1
                else:
                    previous = slot
                slot = following
            if stale:
                queues[sender, Q_WAITING] -= stale
                counts[T_WAITING] -= stale
                _made(kinds, counts, kind)
                kinds[kind, K_SUPERSEDED] += stale
        frames = message_ints[m, 5]
        audience = message_ints[m, 6]
        for k in range(frames):
            counts[T_FREE] -= 1
            slot = free[counts[T_FREE]]
            ints[slot, I_SENDER] = sender
            ints[slot, I_SEQUENCE] = first_sequence + message_ints[m, 1]
            ints[slot, I_KIND] = kind
            ints[slot, I_FLAGS] = flags | LAST if k == frames - 1 else flags
            ints[slot, I_NEXT] = -1
            ints[slot, I_SIZE] = message_ints[m, 4]
            ints[slot, I_PAYLOAD_BYTES] = int(frame_spec[spec, 0])
            floats[slot, F_SENT] = sent_s
            floats[slot, F_AIRTIME] = frame_spec[spec, 1]
            floats[slot, F_BITS] = frame_spec[spec, 2]
            floats[slot, F_AUDIENCE] = audience
            floats[slot, F_VALUE] = message_values[m]
            for r in range(audience):
                listed[slot, r] = message_listed[listed_at + r]
            tail = queues[sender, Q_TAIL]
            if tail < 0:
                queues[sender, Q_HEAD] = slot
            else:
                ints[tail, I_NEXT] = slot
            queues[sender, Q_TAIL] = slot
            spec += 1
        listed_at += max(audience, 0)
        queues[sender, Q_WAITING] += 1
        counts[T_WAITING] += 1
    return dropped_count


@kernel
def _period(start_s, end_s, eps, reach_s, sense, snr, ints, floats, listed, queues, alive, free, counts, kinds,
            airtime, log_latency, log_kind, fading_code, noncentrality, gain_scale, sure_snr_db, decide, rng,
            integers, reals, flags, tally, columns, values, present):
    """One period of the medium over the frame table: gathers the head of each queue that can go out (frames
    while the airtime before them fits, and one more, which cannot: the loop must meet it to stop that sender,
    drawing as it does), schedules them (``_schedule_frames``) and, unless some draw is left for numpy's exact
    PER (``tally[0]``: the caller decides those and calls ``book``), books them (``book``). ``integers``
    (16, W), ``reals`` (9, W) and ``flags`` (2, W) are scratch rows (see ``book``; W >= 4 frames gathered, >= N
    + 1, >= the draws); ``columns``, ``values`` and ``present`` ``book``'s outputs. Returns ``book``'s
    figures, or (-1, the frames sent, 0, ...) when the caller must decide draws first."""
    n = sense.shape[0]
    gathered = integers[0]
    first = integers[4, :n]
    count = integers[5, :n]
    total = 0
    listed_total = 0
    for s in range(n):
        first[s] = total
        before_s = 0.0
        slot = queues[s, Q_HEAD]
        while slot >= 0:
            gathered[total] = slot
            total += 1
            before_s += floats[slot, F_AIRTIME]
            if before_s > reach_s:
                break
            slot = ints[slot, I_NEXT]
        count[s] = total - first[s]
    numbers = reals[0, :4 * total]
    receivers_listed = integers[6]
    for f in range(total):
        slot = gathered[f]
        for c in range(4):
            numbers[4 * f + c] = floats[slot, c]
        for r in range(int(floats[slot, F_AUDIENCE])):
            receivers_listed[listed_total] = listed[slot, r]
            listed_total += 1
    popped = integers[7, :n]
    popped[:] = 0
    queued = integers[4:6, :n]
    sent = _schedule_frames(start_s, end_s, eps, sense, snr, queued, numbers, receivers_listed[:listed_total],
                            fading_code, noncentrality, gain_scale, sure_snr_db, decide, rng, popped, integers[1],
                            reals[1], integers[2], integers[3], reals[2], reals[3], reals[4], reals[5], flags[0],
                            flags[1], tally, integers[8:11], reals[6:9])
    if tally[0] > 0:
        return -1, sent, 0, 0, 0, 0, 0, 0.0
    return book(n, ints, floats, queues, alive, free, counts, kinds, airtime, log_latency, log_kind, integers,
                reals, flags, sent, columns, values, present)


@kernel
def _period_at(state_address, state, next_uint64, next_uint32, next_double, eps, reach_s, ints, floats, listed,
               queues, alive, free, counts, kinds, airtime, log_latency, log_kind, fading_code, noncentrality,
               gain_scale, sure_snr_db, decide, integers, reals, flags, tally, present, start_s, end_s, sense, snr,
               columns, values):
    """``_period`` drawing from the Generator of these ``sim.compiled.generator_pointers`` (numba's unboxing
    of a Generator argument costs about 15 us a call), its arguments in the order the bus keeps them: those
    that last until the table grows first, the period's own last."""
    rng = generator_at(state_address, state, next_uint64, next_uint32, next_double)
    return _period(start_s, end_s, eps, reach_s, sense, snr, ints, floats, listed, queues, alive, free, counts,
                   kinds, airtime, log_latency, log_kind, fading_code, noncentrality, gain_scale, sure_snr_db,
                   decide, rng, integers, reals, flags, tally, columns, values, present)


@kernel
def _enqueue_then_period_at(state_address, state, next_uint64, next_uint32, next_double, eps, reach_s, ints, floats,
                            listed, queues, alive, free, counts, kinds, airtime, log_latency, log_kind, fading_code,
                            noncentrality, gain_scale, sure_snr_db, decide, integers, reals, flags, tally, present,
                            dropped, message_ints, message_values, message_listed, frame_spec, first_sequence, sent_s,
                            start_s, end_s, sense, snr, columns, values):
    """``_enqueue`` of a tick's outbox, then ``_period_at``, in one call (what the bus's ``exchange`` makes of
    a tick whose outbox is one kept batch): (superseded, then ``_period``'s figures)."""
    superseded = _enqueue(ints, floats, listed, queues, free, counts, kinds, message_ints, message_values,
                          message_listed, frame_spec, first_sequence, sent_s, dropped)
    rng = generator_at(state_address, state, next_uint64, next_uint32, next_double)
    return superseded, _period(start_s, end_s, eps, reach_s, sense, snr, ints, floats, listed, queues, alive, free,
                               counts, kinds, airtime, log_latency, log_kind, fading_code, noncentrality, gain_scale,
                               sure_snr_db, decide, rng, integers, reals, flags, tally, columns, values, present)


def _period_with(rng, eps, reach_s, ints, floats, listed, queues, alive, free, counts, kinds, airtime, log_latency,
                 log_kind, fading_code, noncentrality, gain_scale, sure_snr_db, decide, integers, reals, flags, tally,
                 present, start_s, end_s, sense, snr, columns, values):
    """``_period_at``'s call with the Generator itself (where numba's JIT is disabled, or the generator has
    no pointers)."""
    return _period(start_s, end_s, eps, reach_s, sense, snr, ints, floats, listed, queues, alive, free, counts,
                   kinds, airtime, log_latency, log_kind, fading_code, noncentrality, gain_scale, sure_snr_db,
                   decide, rng, integers, reals, flags, tally, columns, values, present)


@kernel
def book(n, ints, floats, queues, alive, free, counts, kinds, airtime, log_latency, log_kind, integers, reals,
         flags, sent, columns, values, present):
    """Book the ``sent`` frames ``_schedule_frames`` put on the air (scratch rows: ``integers`` 0 the gathered
    slots, 1 the frames gone, 2 their draws' bounds, 3 the draws' receivers, 8-15 this kernel's; ``reals[1]``
    their ends, ``reals[6:8]`` this kernel's; ``flags[1]`` each draw's survival), as
    ``ReferenceMessageBus._transmit`` does: pop them, keep the in-flight receivers of a message of several
    frames, add the kinds' counters, airtimes and latencies (logged with their kind, in booking order), and
    make the period's arrivals.

    Returns (frames sent, packets sent, pairs addressed, deliveries, entries, finished, groups present, the
    latencies' sum as ``numpy.add.reduce`` gives it) and writes the arrivals into the caller's arrays (a
    returned array costs its boxing each call): one entry per (message, receiver reached), by group (each
    kind's ``as_arrays`` messages in kind order, then every other message, group len(kinds)), within a
    group in the rows' order (by receiver, then arrival and sequence); ``columns`` (3, >= entries):
    receiver, sender, sequence; ``values`` (3, >= entries): arrival, send time, value; ``present`` (>= 3
    (len(kinds) + 1)) the groups with entries, as (group, first entry, end) triples in group order;
    ``integers[15, :finished]`` the sequences of the messages not sent as_arrays whose last frame went. The
    latencies are every entry's, in the rows' order over all groups."""
    gathered, sent_frame, sent_draws, draw_receiver = integers[0], integers[1], integers[2], integers[3]
    sent_finish = reals[1]
    draw_alive = flags[1]
    message_finish = reals[6]
    message_slot = integers[8]  # the slot of its last frame (its numbers)
    message_first = integers[9]  # where its entries start
    entry_receiver = integers[10]
    finished = integers[15]
    finished_count = 0
    messages = 0
    entries = 0
    packets = addressed = delivered = 0
    logged = counts[T_LOGGED]
    for k in range(sent):
        slot = gathered[sent_frame[k]]
        sender = ints[slot, I_SENDER]
        sequence = ints[slot, I_SEQUENCE]
        kind = ints[slot, I_KIND]
        last = ints[slot, I_FLAGS] & LAST
        following = ints[slot, I_NEXT]  # the head of its queue: a sender's frames go in order
        queues[sender, Q_HEAD] = following
        if following < 0:
            queues[sender, Q_TAIL] = -1
        free[counts[T_FREE]] = slot
        counts[T_FREE] += 1
        if last:
            queues[sender, Q_WAITING] -= 1
            counts[T_WAITING] -= 1
        _made(kinds, counts, kind)
        kinds[kind, K_FRAMES] += 1
        airtime[kind, sender] += floats[slot, F_AIRTIME]
        first_draw, end_draw = sent_draws[k], sent_draws[k + 1]
        if queues[sender, Q_FLYING] != sequence:  # its first frame
            if not last:
                queues[sender, Q_FLYING] = sequence
                for d in range(first_draw, end_draw):
                    alive[sender, d - first_draw] = draw_alive[d]
                continue
            message_first[messages] = entries
            for d in range(first_draw, end_draw):
                if draw_alive[d]:
                    entry_receiver[entries] = draw_receiver[d]
                    entries += 1
        else:
            for d in range(first_draw, end_draw):
                alive[sender, d - first_draw] = alive[sender, d - first_draw] and draw_alive[d]
            if not last:
                continue
            queues[sender, Q_FLYING] = -1
            message_first[messages] = entries
            for d in range(first_draw, end_draw):
                if alive[sender, d - first_draw]:
                    entry_receiver[entries] = draw_receiver[d]
                    entries += 1
        reached = entries - message_first[messages]
        kinds[kind, K_PACKETS] += 1
        kinds[kind, K_BYTES] += ints[slot, I_SIZE]
        kinds[kind, K_ADDRESSED] += end_draw - first_draw
        kinds[kind, K_DELIVERED] += reached
        packets += 1
        addressed += end_draw - first_draw
        delivered += reached
        finish = sent_finish[k]
        latency = finish - floats[slot, F_SENT]
        for _ in range(reached):
            log_latency[logged] = latency
            log_kind[logged] = kind
            logged += 1
        if not ints[slot, I_FLAGS] & AS_ARRAYS:
            finished[finished_count] = sequence
            finished_count += 1
        message_finish[messages] = finish
        message_slot[messages] = slot
        messages += 1
    counts[T_LOGGED] = logged
    message_first[messages] = entries
    # The messages by (arrival, sequence): insertion sort, they come nearly in order of arrival
    order = integers[11]
    for a in range(messages):
        order[a] = a
    for a in range(1, messages):
        m = order[a]
        b = a - 1
        while b >= 0 and (message_finish[order[b]] > message_finish[m] or (
                message_finish[order[b]] == message_finish[m]
                and ints[message_slot[order[b]], I_SEQUENCE] > ints[message_slot[m], I_SEQUENCE])):
            order[b + 1] = order[b]
            b -= 1
        order[b + 1] = m
    # then a stable counting sort by receiver: the rows' order
    robots = n
    for e in range(entries):
        robots = max(robots, entry_receiver[e] + 1)
    at = integers[12, :robots + 1]
    at[:] = 0
    for e in range(entries):
        at[entry_receiver[e] + 1] += 1
    for r in range(robots):
        at[r + 1] += at[r]
    row_receiver = integers[13]
    row_message = integers[14]
    for a in range(messages):
        m = order[a]
        for e in range(message_first[m], message_first[m + 1]):
            row = at[entry_receiver[e]]
            at[entry_receiver[e]] += 1
            row_receiver[row] = entry_receiver[e]
            row_message[row] = m
    groups = kinds.shape[0] + 1
    bounds = np.zeros(groups + 1, dtype=np.int64)
    latencies = reals[7, :entries]
    for row in range(entries):
        slot = message_slot[row_message[row]]
        latencies[row] = message_finish[row_message[row]] - floats[slot, F_SENT]
        group = ints[slot, I_KIND] if ints[slot, I_FLAGS] & AS_ARRAYS else groups - 1
        bounds[group + 1] += 1
    for g in range(groups):
        bounds[g + 1] += bounds[g]
    place = bounds[:groups].copy()
    groups_present = 0
    for g in range(groups):
        if bounds[g + 1] > bounds[g]:
            present[3 * groups_present] = g
            present[3 * groups_present + 1] = bounds[g]
            present[3 * groups_present + 2] = bounds[g + 1]
            groups_present += 1
    for row in range(entries):
        m = row_message[row]
        slot = message_slot[m]
        group = ints[slot, I_KIND] if ints[slot, I_FLAGS] & AS_ARRAYS else groups - 1
        e = place[group]
        place[group] += 1
        columns[0, e] = row_receiver[row]
        columns[1, e] = ints[slot, I_SENDER]
        columns[2, e] = ints[slot, I_SEQUENCE]
        values[0, e] = message_finish[m]
        values[1, e] = floats[slot, F_SENT]
        values[2, e] = floats[slot, F_VALUE]
    return sent, packets, addressed, delivered, entries, finished_count, groups_present, numpy_sum(latencies)


class LinkMatrices(NamedTuple):
    """The medium's view of one tick's channel (a ``sim.radio.bus.LinkState``) as the channel makes it with
    its figures (``write_pair_matrices``): (N, N) C arrays each, float64 and bool, the SNR read-only. The
    bus takes them as they are (any other ``LinkState`` is converted and checked first)."""

    snr_db: np.ndarray  # mean SNR from i to j, dB; NaN on the diagonal
    carrier_sense: np.ndarray  # bool: i and j share the air


@kernel
def write_pair_matrices(first, second, snr_db, rx_power_dbm, carrier_sense_dbm, snr, sense):
    """The medium's (N, N) view of the channel from its pairs' figures, into ``snr`` and ``sense``: the
    SNR in both triangles with NaN on the diagonal, carrier sense where the received power reaches
    ``carrier_sense_dbm`` (False elsewhere)."""
    n = snr.shape[0]
    for i in range(n):
        for j in range(n):
            sense[i, j] = False
        snr[i, i] = np.nan
    for p in range(first.shape[0]):
        i, j = first[p], second[p]
        snr[i, j] = snr_db[p]
        snr[j, i] = snr_db[p]
        heard = rx_power_dbm[p] >= carrier_sense_dbm
        sense[i, j] = heard
        sense[j, i] = heard
