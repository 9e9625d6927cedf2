"""The intermittent-task methods' exchanges over the message bus under a real radio.

- the meeting methods: each member sends its range records over a ReliableLink; the team belief
  takes only what reached every member (``NetworkBeliefs.meet_over_radio``), a meeting waits for
  its records and ends at ``strategy.exchange_timeout_s`` when they never arrive (real MuJoCo runs
  of the small room, the channel gated between the robots);
- the always-connected methods: readings reach the team belief only as ``"fusion"`` messages
  (``controllers.task.RadioFusion``), checked over scripted loss patterns and in a real run.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from controllers.intermittent.teams import PAPER_DENSE_TEAMS, PAPER_RING_TEAMS, Teams
from controllers.task import FUSION_KIND, RadioFusion
from estimation.beliefs import Belief, NetworkBeliefs
from estimation.ekf import paper_prior
from estimation.metrics import delay_report
from intermittent_helpers import room_scenario
from sim.radio.bus import RANGE_RECORD_BYTES, Delivery, link_conditions
from sim.radio.protocols import RELIABLE_HEADER_BYTES
from sim.scenario import load
from test_beliefs import NetworkRun, paper_motion, random_records
from tether.runner import build_simulation

RADIO = '\n[radio]\npreset = "ieee802154"\n'


# ------------------------------------------------------------------ meet_over_radio


def radio_meet(network: NetworkBeliefs):
    """A meeting whose exchange went through: every member sends ``outgoing`` and hears everyone."""
    def meet(team, epoch):
        members = network.teams.members[team]
        sent = {r: network.outgoing(r, team) for r in members}
        cursors = {r: network.robot_beliefs[r].n_records for r in members}
        return network.meet_over_radio(team, epoch, sent, {r: set(members) for r in members}, cursors)
    return meet


def test_a_complete_exchange_fuses_what_meet_fuses():
    """Every member heard by all: the same team, robot and global record sets and packet deliveries as
    Algorithm 5's meet, epoch after epoch."""
    ideal = NetworkRun(PAPER_DENSE_TEAMS, np.random.default_rng(3))
    radio = NetworkRun(PAPER_DENSE_TEAMS, np.random.default_rng(3))
    radio.network.meet = radio_meet(radio.network)
    for _ in range(8):
        ideal.advance_epoch()
        radio.advance_epoch()
        for a, b in zip(ideal.network.team_beliefs, radio.network.team_beliefs):
            assert set(a._records) == set(b._records)
        for robot in ideal.network.robot_beliefs:
            assert set(ideal.network.robot_beliefs[robot]._records) == set(radio.network.robot_beliefs[robot]._records)
        assert ideal.network.deliveries == radio.network.deliveries
    step = radio.last_measured_step
    for team in range(radio.teams.n_teams):
        np.testing.assert_array_equal(ideal.network.team_estimate(team, step).mean,
                                      radio.network.team_estimate(team, step).mean)


def test_a_partial_exchange_fuses_only_the_records_every_member_got():
    teams = Teams([(0, 1, 2), (0, 3), (1, 4), (2, 3, 4)])
    network = NetworkBeliefs(teams, paper_motion(), paper_prior())
    records = random_records(np.random.default_rng(5), paper_motion(), robots=(0, 1, 2), steps=6)
    for robot in (0, 1, 2):
        network.collect(robot, [r for r in records if r.robot == robot])
    sent = {r: network.outgoing(r, 0) for r in (0, 1, 2)}
    assert all(len(sent[r]) == sum(x.robot == r for x in records) > 0 for r in (0, 1, 2))
    cursors = {r: network.robot_beliefs[r].n_records for r in (0, 1, 2)}
    # 0's records reached 1 only; 1's and 2's reached everyone.
    heard = {0: {1, 2}, 1: {0, 2}, 2: {1}}
    report = network.meet_over_radio(0, 1, sent, heard, cursors)
    team_keys = set(network.team_beliefs[0]._records)
    assert team_keys == {r.key for r in sent[1] + sent[2]}
    assert report.new_to_team == len(sent[1]) + len(sent[2])
    assert {r.key for r in sent[0]} <= set(network.robot_beliefs[1]._records)
    assert not {r.key for r in sent[0]} & set(network.robot_beliefs[2]._records)
    # Robot 0's records go again at the team's next meeting, from 0 and from 1, which heard them;
    # 1's and 2's, which the team holds, do not.
    assert {r.key for r in network.outgoing(0, 0)} == {r.key for r in sent[0]}
    assert {r.key for r in network.outgoing(1, 0)} == {r.key for r in sent[0]}
    assert network.outgoing(2, 0) == []
    # Only 1's and 2's packets reached the team.
    delivered = {packet.robot for packet, by_team in network.deliveries.items() if 0 in by_team}
    assert delivered == {1, 2}


def test_a_packet_held_up_past_the_delay_bound_is_overdue():
    """Proposition III.2's D assumes complete meetings: when team 0's exchanges never get through, the
    packets that must reach it are reported overdue once older than D, and the bound as broken."""
    def run(broken_team):
        run = NetworkRun(PAPER_RING_TEAMS, np.random.default_rng(4))
        complete = radio_meet(run.network)

        def meet(team, epoch):
            if team != broken_team:
                return complete(team, epoch)
            members = run.network.teams.members[team]
            return run.network.meet_over_radio(team, epoch, {r: run.network.outgoing(r, team) for r in members},
                                               {}, {r: 0 for r in members})
        run.network.meet = meet
        for _ in range(run.schedule.delay_bound + 2 * run.schedule.period):
            run.advance_epoch()
        return delay_report(run.network, run.schedule.delay_bound, run.epoch)

    whole = run(broken_team=None)
    assert whole.overdue == 0 and whole.within_bound
    broken = run(broken_team=0)
    assert broken.overdue > 0 and not broken.within_bound


# --------------------------------------------------------- meetings in real runs


def gated_room_run(folder: Path, closed, duration: float = 40.0, kind: str = "intermittent", extra: str = "",
                   after_tick=None):
    """The small room under ieee802154 with the bus's channel shut (every SNR -inf: nothing arrives)
    while ``closed(sim)``; real MuJoCo, planner, EKF and bus; ``after_tick(sim)`` after every tick.
    Returns the simulation and its metrics."""
    scenario = load(str(room_scenario(folder, kind=kind, duration=duration, n_sample=60, extra=extra + RADIO)))
    sim = build_simulation(scenario)
    open_link = sim.bus_link
    n = sim.world.n_robots
    shut = link_conditions(np.full((n, n), -np.inf), True)
    sim.bus_link = lambda observation: shut if closed(sim) else open_link(observation)
    for _ in range(int(round(scenario.duration_s / sim.dt))):
        _, healthy = sim.tick()
        assert healthy
        if after_tick is not None:
            after_tick(sim)
    return sim, {**sim.strategy.summary(), **sim.radio_summary()}


def test_a_meeting_waits_for_every_members_records(tmp_path):
    """The channel shuts for the first second of every exchange: the first copies are lost, the
    ReliableLinks send again, and each meeting is held only once every member's records arrived."""
    def closed(sim):
        t = sim.time_s
        return any(t - m.exchange.started_s < 1.0 for m in sim.strategy.open_exchanges.values())

    sim, metrics = gated_room_run(tmp_path, closed, extra="retransmit_after_s = 0.5\n")
    strategy = sim.strategy
    exchanged = [m for m in strategy.meetings if m.exchange is not None and m.held_s is not None]
    assert len(exchanged) >= 2 and metrics["meetings_held"] == len(exchanged)
    assert metrics["meetings_timed_out"] == 0
    for meeting in exchanged:
        assert not meeting.timed_out and meeting.exchange.complete(meeting.members)
        assert meeting.held_s >= meeting.exchange.started_s + 1.0
        team_keys = set(strategy.beliefs.team_beliefs[meeting.team]._records)
        assert {r.key for records in meeting.exchange.sent.values() for r in records} <= team_keys
    # Bytes on the air: 40 a record plus the reliable header, every copy (retransmissions included).
    assert metrics["radio_range_records_packets_sent"] > 2 * len(exchanged)  # the lost first copies went again
    first_copies = sum(len(recs) * (len(m.members) - 1) for m in exchanged for recs in m.exchange.sent.values())
    assert metrics["range_records_sent"] > first_copies
    assert metrics["radio_packets_queued"] == 0
    assert metrics["radio_range_records_bytes_sent"] == (
        RANGE_RECORD_BYTES * metrics["range_records_sent"] + RELIABLE_HEADER_BYTES * metrics["radio_range_records_packets_sent"])
    assert metrics["meetings_over_radio"] is True


def test_a_meeting_whose_records_never_arrive_ends_at_the_timeout(tmp_path):
    sim, metrics = gated_room_run(tmp_path, lambda sim: True, extra="exchange_timeout_s = 3.0\n")
    strategy = sim.strategy
    ended = [m for m in strategy.meetings if m.held_s is not None]
    assert len(ended) >= 2
    for meeting in ended:
        assert meeting.timed_out
        assert meeting.held_s - meeting.exchange.started_s == pytest.approx(3.0, abs=sim.dt + 1e-9)
        assert all(not heard for heard in meeting.exchange.heard.values())
    assert metrics["meetings_timed_out"] == len(ended) and metrics["meetings_held"] == 0
    # Nothing reached any team: every team belief holds no reading; the global one holds them all.
    assert all(belief.n_records == 0 for belief in strategy.beliefs.team_beliefs)
    assert strategy.beliefs.global_belief.n_records > 0
    # The schedule goes on (the teams planned their next meetings), and the run says what happened.
    assert len(strategy.meetings) > len(ended)
    assert f"{len(ended)} ended at the 3 s exchange timeout" in strategy.progress()
    assert metrics["radio_range_records_packets_delivered"] == 0


def test_a_real_run_puts_40_bytes_a_record_on_the_air(tmp_path):
    """Ungated ieee802154 in the room: the meetings' records and the all-time formation's readings
    go over the bus, 40 bytes a record plus the 4-byte reliable header per message copy."""
    sim, metrics = gated_room_run(tmp_path, lambda sim: False, duration=30.0)
    assert metrics["meetings_held"] >= 1 and metrics["meetings_timed_out"] == 0
    assert metrics["radio_range_records_packets_sent"] > 0 and metrics["radio_packets_queued"] == 0
    assert metrics["radio_range_records_bytes_sent"] == (
        RANGE_RECORD_BYTES * metrics["range_records_sent"] + RELIABLE_HEADER_BYTES * metrics["radio_range_records_packets_sent"])
    assert metrics["radio_range_records_ack_bytes_sent"] == 4 * metrics["radio_range_records_ack_packets_sent"]
    sim, metrics = gated_room_run(tmp_path, lambda sim: False, duration=10.0, kind="all_time")
    assert metrics["radio_fusion_packets_sent"] > 0 and metrics["fusion_records_sent"] > 0
    assert metrics["radio_packets_queued"] == 0
    assert metrics["radio_fusion_bytes_sent"] == (
        RANGE_RECORD_BYTES * metrics["fusion_records_sent"] + RELIABLE_HEADER_BYTES * metrics["radio_fusion_packets_sent"])


def test_under_ideal_meetings_pool_their_logs_at_once(tmp_path):
    """The default radio keeps Algorithm 5's exchange: nothing on the bus, no exchange, no timeout."""
    scenario = load(str(room_scenario(tmp_path, duration=25.0, n_sample=60)))
    sim = build_simulation(scenario)
    for _ in range(int(round(scenario.duration_s / sim.dt))):
        sim.tick()
    metrics = {**sim.strategy.summary(), **sim.radio_summary()}
    assert metrics["meetings_held"] >= 1 and metrics["meetings_over_radio"] is False
    assert all(m.exchange is None for m in sim.strategy.meetings)
    assert metrics["radio_packets_sent"] == 0


# ------------------------------------------------------------------ fusion


def step_records(rng, steps: int, robots: int = 3):
    """Per step, per robot, its readings (real RangeMeasurement records)."""
    records = random_records(rng, paper_motion(), robots=tuple(range(robots)), steps=steps)
    return [[[r for r in records if r.step == k and r.robot == robot] for robot in range(robots)]
            for k in range(steps)]


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data(), fusion_robot=st.integers(0, 2))
def test_fusion_never_uses_a_reading_that_did_not_reach_it(data, fusion_robot):
    """Over any pattern of lost messages and acks (a scripted channel, one tick per hop): the team
    belief holds only the fusion robot's own readings and those whose message reached it; once the
    channel delivers again, every reading arrives (given-up messages go again)."""
    steps, ticks_per_step, dt = 8, 5, 0.02
    per_step = step_records(np.random.default_rng(data.draw(st.integers(0, 2**16), label="seed")), steps)
    motion, prior = paper_motion(), paper_prior()
    global_belief, team = Belief(motion, prior), Belief(motion, prior)
    fusion = RadioFusion(3, fusion_robot, team, global_belief, retransmit_after_s=2 * dt)
    reached: set = set()  # keys that arrived at the fusion robot in a fusion message, or its own
    inbox: tuple = ((), (), ())
    lossy_ticks = steps * ticks_per_step
    for tick in range(lossy_ticks + 40 * ticks_per_step):
        time_s = tick * dt
        records = None
        if tick % ticks_per_step == 0 and tick // ticks_per_step < steps:
            records = per_step[tick // ticks_per_step]
            global_belief.receive([r for robot in records for r in robot])
            reached |= {r.key for r in records[fusion_robot]}
        fusion.exchange(time_s, inbox, records)
        assert set(team._records) <= reached
        rows = [[], [], []]
        for message in fusion.drain():
            arrives = tick >= lossy_ticks or data.draw(st.booleans(), label="delivered")
            if arrives:
                (receiver,) = message.receivers
                stamped = dataclasses.replace(message, sequence=tick, sent_s=time_s)
                rows[receiver].append(Delivery(stamped, receiver, time_s))
                if message.kind == FUSION_KIND and receiver == fusion_robot:
                    reached |= {r.key for r in message.payload.data}
        inbox = tuple(tuple(row) for row in rows)
    assert set(team._records) == set(global_belief._records)
    assert fusion.summary(1.0)["fusion_readings_missing"] == 0


def test_all_time_fusion_lags_while_the_channel_is_shut_and_catches_up(tmp_path):
    """A real all_time run under ieee802154, the channel shut from 8 s to 14 s: the formation's belief
    misses the other robots' readings of those steps while shut (t*(t) falls behind), then gets them
    all; e_g's global belief is unaffected."""
    seen = {}

    def watch(sim):
        strategy = sim.strategy
        if sim.time_s < 14.0:  # the last tick with the channel shut
            seen["t_star_s"] = strategy._scalars["t_star_s"]
            seen["missing"] = strategy.belief.n_records - strategy.plan_belief.n_records

    sim, metrics = gated_room_run(tmp_path, lambda sim: 8.0 <= sim.time_s < 14.0, duration=24.0, kind="all_time",
                                  after_tick=watch)
    strategy = sim.strategy
    assert seen["missing"] > 0 and seen["t_star_s"] < 8.0
    assert metrics["t_star_lag_max_s"] >= 5.0
    assert metrics["fusion_readings_missing"] == 0  # caught up by the end
    assert metrics["radio_fusion_packets_sent"] > 0 and metrics["radio_fusion_delivery_ratio"] < 1.0
    assert math.isfinite(metrics["radio_fusion_latency_mean_s"])
    # The global belief (e_g, lambda-bar) took every reading the tick it was taken.
    assert strategy.belief.n_records == metrics["fusion_readings_fused"]
