"""Faults (sim.faults, applied by sim.loop): bad tables refused, a failed robot stops and goes silent,
a blackout cuts links inside its window only, position noise has the statistics it claims, runs with
faults end with a status and a message, and the same seed gives the same run."""

from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import tether.catalog  # noqa: F401 (registers the built-in scenarios)
from controllers.lowlevel.actuation import LowLevelControl
from controllers.intermittent.runtime import LAG_HOLD_M, LagHolds
from sim.config import ConfigError
from sim.faults import IDEAL_BLACKOUT_CUT_DB, FaultState, PositionNoise
from sim.loop import Simulation
from sim.radio.bus import Delivery, Message
from sim.radio.protocols import HeartbeatMonitor, _hear_columns_then_quiet_pairs, _quiet_pairs
from sim.scenario import load
from sim.strategy import Strategy, build_strategy
from sim.types import Commands
from tether.cli import main

# The hover scene with quadrotor 1 moved next to quadrotor 0 (1 m, line of sight).
NEAR = 'robots.0.starts=[[1.0, 4.0, 1.0], [2.0, 4.0, 1.0], [8.8, 5.5, 1.0], [5.0, 6.0, 1.2]]'
IEEE = ['radio.preset="ieee802154"', 'radio.fading="none"']


@dataclass(frozen=True)
class BroadcastParams:
    pass


class Broadcaster(Strategy):
    """Holds every robot at its start; every robot broadcasts its index and the tick every tick."""

    def __init__(self, params=BroadcastParams()):
        self.params = params

    def reset(self, world, initial, rng) -> None:
        self.hold = np.array(initial.position)
        self.seen: list = []  # per tick: the observation the strategy read

    def step(self, observation) -> Commands:
        self.seen.append(observation)
        n = len(self.hold)
        zeros = np.zeros((n, 3))
        outbox = tuple(Message("test", robot, None, observation.tick, 20) for robot in range(n))
        return Commands(self.hold, zeros, zeros, np.zeros(n), outbox=outbox)


def broadcast(overrides, ticks=40, seed=0):
    sim = Simulation(load("hover", [NEAR, *overrides], seed=seed, duration_s=2.0), lambda _: Broadcaster(),
                     LowLevelControl)
    frames = [sim.tick()[0] for _ in range(ticks)]
    return sim, frames


@pytest.mark.parametrize("assignment, key, problem", [
    ('faults=[{kind="robot_failure", robot=10, at_s=1.0}]', "faults.0.robot", "robot index below 10"),
    ('faults=[{kind="robot_failure", robot=1, at_s=-1.0}]', "faults.0.at_s", "must be at least 0"),
    ('faults=[{kind="robot_failure", robot=1, at_s=99.0}]', "faults.0.at_s", "within the run"),
    ('faults=[{kind="robot_failure", robot=1, at_s=10.0}]', "faults.0.at_s", "within the run"),
    ('faults=[{kind="radio_blackout", center=[1, 1, 1], radius_m=1.0, extra_loss_db=9.0, from_s=10.0}]',
     "faults.0.from_s", "within the run"),
    ('faults=[{kind="robot_failure", robot=1, at_s=nan}]', "faults.0.at_s", "finite"),
    ('faults=[{kind="robot_failure", robot=1, at_s=1.0, mode="fly"}]', "faults.0.mode", "must be one of"),
    ('faults=[{kind="meteor"}]', "faults.0.kind", "must be one of robot_failure"),
    ('faults=[{robot=1}]', "faults.0.kind", "is required"),
    ('faults=[{kind="radio_blackout", center=[1, 1, 1], radius_m=-1.0, extra_loss_db=10.0}]',
     "faults.0.radius_m", "must be positive"),
    ('faults=[{kind="radio_blackout", center=[1, 1, 1], radius_m=1.0, extra_loss_db=inf}]',
     "faults.0.extra_loss_db", "finite"),
    ('faults=[{kind="radio_blackout", center=[1, 1, 1], radius_m=1.0, extra_loss_db=9.0, from_s=5.0, to_s=4.0}]',
     "faults.0.to_s", "must be after from_s"),
    ('faults=[{kind="position_noise", sigma_m=-0.1}]', "faults.0.sigma_m", "must be in [0, 100] m"),
    ('faults=[{kind="position_noise", sigma_m=0.1, jitter=1}]', "faults.0.jitter", "unknown key"),
])
def test_bad_fault_is_refused_in_one_line(capsys, tmp_path, assignment, key, problem):
    code = main(["run", "connected-office", "--duration", "10", "--set", assignment, "--out", str(tmp_path / "o"),
                 "--quiet"])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1, lines
    assert f"{key}: " in lines[0] and problem in lines[0], lines[0]
    assert not (tmp_path / "o").exists()


def test_faults_are_set_key_by_key_and_read_back():
    scenario = load("connected-office", ["faults.0.kind=robot_failure", "faults.0.robot=3", "faults.0.at_s=5.0",
                                         'faults.1.kind="position_noise"', "faults.1.sigma_m=0.1",
                                         "faults.0.at_s=6.0"])
    failure, noise = scenario.faults
    assert (failure.robot, failure.at_s, failure.mode) == (3, 6.0, "stop")
    assert (noise.sigma_m, noise.bias_m, noise.period_s) == (0.1, 0.0, math.inf)
    # In any order (a sweep sorts its overrides), and the list is made when the scenario has none.
    overrides = sorted(["faults.0.kind=robot_failure", "faults.0.robot=3", "faults.0.at_s=5.0"])
    assert load("connected-office", overrides).faults == (dataclasses.replace(failure, at_s=5.0),)
    with pytest.raises(ConfigError) as err:
        load("connected-office", ["faults.2.kind=robot_failure"])  # not the next index
    assert err.value.field == "faults.2"


@pytest.mark.parametrize("radio", [[], IEEE], ids=["ideal", "ieee802154"])
def test_a_failed_robot_goes_silent(radio):
    fail_tick = 10
    sim, frames = broadcast([*radio, f'faults=[{{kind="robot_failure", robot=0, at_s={fail_tick * 0.01}}}]'])
    seen = sim.strategy.seen
    heard = [{(d.message.sender, receiver) for receiver, row in enumerate(o.inbox) for d in row} for o in seen]
    before, after = set().union(*heard[1:fail_tick + 1]), set().union(*heard[fail_tick + 1:])
    assert {(0, 1), (1, 0)} <= before
    sure = {(i, j) for i, j in before if 0 not in (i, j) and seen[fail_tick].radio.delivery[i, j] == 1.0}
    assert sure, "some other pair talks"
    assert not any(0 in pair for pair in after)  # nothing sent at the failure tick or later, nothing received
    assert sure <= after  # the others still hear each other
    after = seen[fail_tick + 5]
    assert not after.radio.delivery[0].any() and not after.radio.comm_adjacency[0].any()
    assert after.radio.delivery[1, 3] == seen[fail_tick - 5].radio.delivery[1, 3]  # others' links untouched
    assert sim.faults.failed.tolist() == [True] + [False] * 7
    assert sim.fault_summary()["faults"][0]["happened"] is True


def test_a_stopped_robot_stays_put_and_a_drifting_one_keeps_its_last_command():
    # Quadrotor 1 stops and quadrotor 2 drifts at 0.5 s, flying; ground robot 6 stops at 3 s, turning.
    faults = ('faults=[{kind="robot_failure", robot=1, at_s=0.5}, {kind="robot_failure", robot=6, at_s=3.0}, '
              '{kind="robot_failure", robot=2, at_s=0.5, mode="drift"}]')
    free = Simulation(load("hover", [], duration_s=5.0), lambda p: build_strategy("waypoints", p), LowLevelControl)
    sim = Simulation(load("hover", [faults], duration_s=5.0), lambda p: build_strategy("waypoints", p),
                     LowLevelControl)
    drift_actuators = sim._robot_actuators[2]
    states, free_states, ctrl, free_ctrl = [], [], [], []
    for _ in range(450):
        observation = sim.tick()[0].observation
        states.append(np.hstack([observation.position, observation.quaternion]))
        observation = free.tick()[0].observation
        free_states.append(np.hstack([observation.position, observation.quaternion]))
        ctrl.append(np.array(sim.world.data.ctrl[drift_actuators]))
        free_ctrl.append(np.array(free.world.data.ctrl[drift_actuators]))
    states, free_states = np.array(states), np.array(free_states)
    for robot, failed in ((1, 50), (6, 300)):  # still over the last second, where it would have moved
        assert np.ptp(states[350:, robot], axis=0).max() < 0.01, robot
        assert np.ptp(free_states[350:, robot], axis=0).max() > 0.05, robot
        assert np.linalg.norm(states[-1, robot, :3] - states[failed, robot, :3]) < 0.1, robot
    assert all(np.array_equal(c, ctrl[50]) for c in ctrl[50:])  # frozen from the failure on
    assert any(not np.array_equal(c, ctrl[50]) for c in free_ctrl[51:])  # unfailed, the commands would change
    assert np.array_equal(states[:51], free_states[:51])  # nothing changed before the failures


@pytest.mark.parametrize("radio, loss_db, cut", [(IEEE, 100.0, True), ([], IDEAL_BLACKOUT_CUT_DB, True),
                                                 ([], IDEAL_BLACKOUT_CUT_DB - 0.1, False)],
                         ids=["ieee802154", "ideal-cut", "ideal-weak"])
def test_a_blackout_cuts_links_inside_its_window_only(radio, loss_db, cut):
    # Around quadrotor 1 only, from tick 10 to tick 20.
    sim, _ = broadcast([*radio, f'faults=[{{kind="radio_blackout", center=[2.0, 4.0, 1.0], radius_m=0.3, '
                                f'extra_loss_db={loss_db}, from_s=0.1, to_s=0.2}}]'])
    clear, _ = broadcast(radio)
    for tick, (observation, reference) in enumerate(zip(sim.strategy.seen, clear.strategy.seen)):
        inside = 10 <= tick < 20 and cut
        assert observation.radio.delivery[0, 1] == (0.0 if inside else reference.radio.delivery[0, 1]), tick
        assert observation.radio.delivery[0, 3] == reference.radio.delivery[0, 3], tick  # both ends outside
    arrivals = np.array([d.arrival_s for o in sim.strategy.seen for d in o.inbox[1] if d.message.sender == 0])
    in_window = (arrivals >= 0.1 - 1e-9) & (arrivals < 0.2 - 1e-9)
    assert (arrivals < 0.1).any() and (arrivals > 0.2).any()
    assert in_window.any() != cut  # what was on the air within the window was lost
    assert clear.strategy.seen[15].radio.delivery[0, 1] == 1.0


def test_position_noise_has_its_sigma_and_bias():
    n, draws = 5, 4000
    noise = PositionNoise(sigma_m=0.2, bias_m=0.3, period_s=1.0)
    faults = FaultState((noise,), n, rng=np.random.default_rng(7))
    truth = np.arange(3 * n, dtype=float).reshape(n, 3)
    # Within one bias period: the mean error is the bias (length bias_m), the spread sigma per axis.
    errors = np.array([faults.noisy_positions(0.0 + k * 1e-4, truth) - truth for k in range(draws)])
    bias = errors.mean(axis=0)
    assert np.allclose(np.linalg.norm(bias, axis=1), 0.3, atol=0.02)
    assert np.allclose((errors - bias).std(axis=0), 0.2, rtol=0.06)
    # Over many periods the bias averages out and its length stays bias_m.
    biases = []
    for period in range(1, 2001):
        faults.noisy_positions(float(period), truth)
        biases.append(np.array(faults._bias))
    biases = np.array(biases)
    assert np.allclose(np.linalg.norm(biases, axis=2), 0.3)
    assert np.abs(biases.mean(axis=0)).max() < 0.3 * 4 / math.sqrt(3 * 2000)
    assert np.allclose(biases.reshape(-1, 3).std(axis=0), 0.3 / math.sqrt(3), rtol=0.05)


def test_position_noise_reaches_the_strategy_not_the_truth():
    sim, frames = broadcast(['faults=[{kind="position_noise", sigma_m=0.05}]'], ticks=200)
    seen = np.array([o.position for o in sim.strategy.seen])
    truth = np.array([f.observation.position for f in frames])
    assert np.allclose((seen - truth).std(axis=(0, 1)), 0.05, rtol=0.1)
    distance = sim.strategy.seen[-1].links.distance
    assert np.allclose(distance, np.linalg.norm(seen[-1][:, None] - seen[-1][None], axis=-1))
    assert not np.allclose(distance, frames[-1].observation.links.distance)


def test_zero_position_noise_is_the_fault_free_run_bit_for_bit():
    plain, plain_frames = broadcast(IEEE)
    quiet, quiet_frames = broadcast([*IEEE, 'faults=[{kind="position_noise", sigma_m=0.0, bias_m=0.0}]'])
    assert all(np.array_equal(a.observation.position, b.observation.position)
               for a, b in zip(plain_frames, quiet_frames))
    assert plain.radio_summary() == quiet.radio_summary()


def test_same_seed_same_run_with_faults():
    faults = ('faults=[{kind="robot_failure", robot=0, at_s=0.1}, {kind="position_noise", sigma_m=0.05, '
              'bias_m=0.02, period_s=0.1}, {kind="radio_blackout", center=[5.0, 6.0, 1.2], radius_m=1.0, '
              'extra_loss_db=6.0}]')
    runs = [broadcast([*IEEE[:1], "radio.tx_power_dbm=-40.0", faults], seed=3) for _ in range(2)]
    (first, first_frames), (second, second_frames) = runs
    assert all(np.array_equal(a.position, b.position) for a, b in zip(first.strategy.seen, second.strategy.seen))
    assert all(np.array_equal(a.observation.position, b.observation.position)
               for a, b in zip(first_frames, second_frames))
    assert first.radio_summary() == second.radio_summary()


@pytest.mark.parametrize("scenario, radio", [("connected-office", []), ("connected-office", IEEE[:1]),
                                             ("intermittent-8", []), ("intermittent-8", IEEE[:1])])
def test_a_fault_never_crashes_a_run(tmp_path, scenario, radio):
    from tether.runner import run

    faults = ('faults=[{kind="robot_failure", robot=1, at_s=1.0}, {kind="robot_failure", robot=2, at_s=1.5, '
              'mode="drift"}, {kind="position_noise", sigma_m=0.05, bias_m=0.02}, {kind="radio_blackout", '
              'center=[2.0, 2.0, 0.5], radius_m=2.0, extra_loss_db=30.0, from_s=0.5, to_s=2.5}]')
    result = run(load(scenario, [*radio, faults], duration_s=3.0), tmp_path / "out")
    metrics = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert metrics["status"] in ("completed", "time limit", "diverged"), metrics["message"]
    assert [f["kind"] for f in metrics["faults"]] == ["robot_failure", "robot_failure", "position_noise",
                                                      "radio_blackout"]
    happened = [f for f in metrics["faults"] if f["happened"]]
    for fault, named in zip(metrics["faults"][:2], ("robot 1 failed at 1.0 s (stop)", "robot 2 failed at 1.5 s (drift)")):
        assert (named in metrics["message"]) == fault["happened"], metrics["message"]
    if len(happened) < len(metrics["faults"]):  # the connected method's measured graph: the true one may break
        assert metrics["status"] == "diverged" and "position noise" in metrics["message"], metrics["message"]
    assert result.status.value == metrics["status"]


def _deliveries(n, time_s, senders_to_receivers):
    rows = [[] for _ in range(n)]
    for sender, receiver in senders_to_receivers:
        rows[receiver].append(Delivery(Message("beat", sender, None, None, 8, 0, time_s), receiver, time_s))
    return tuple(tuple(row) for row in rows)


def test_heartbeats_declare_a_neighbour_silent_after_the_timeout_and_not_before():
    n, dt, timeout = 3, 0.01, 0.5
    monitor = HeartbeatMonitor(n, timeout)
    declared = {}
    for tick in range(200):
        t = tick * dt
        talking = [s for s in range(n) if not (s == 2 and t >= 0.5)]  # robot 2 falls silent at 0.5 s
        pairs = [(s, r) for s in talking for r in range(n) if r != s and not (r == 2 and t >= 0.5)]
        for receiver, sender in monitor.step(t, _deliveries(n, t, pairs)):
            declared.setdefault((receiver, sender), t)
    last = 0.49  # robot 2's last heartbeat
    assert declared[(0, 2)] == declared[(1, 2)] == pytest.approx(last + timeout + dt)  # the first tick past it
    assert monitor.silence_detected_s[2] == [pytest.approx(last + timeout + dt)]
    assert not any(sender != 2 and receiver != 2 for receiver, sender in declared)  # the others still talk
    monitor.step(2.0, _deliveries(n, 2.0, [(2, 0)]))  # heard again: withdrawn
    assert not monitor.silent[0, 2] and monitor.withdrawn == [(2.0, 0, 2)]


def test_the_connected_method_detects_a_failed_robot_over_the_radio(tmp_path):
    from tether.runner import run

    scenario = load("connected-office", ['radio.preset="ieee802154"', "strategy.heartbeat_timeout_s=0.5",
                                         'faults=[{kind="robot_failure", robot=4, at_s=1.0}]'], duration_s=3.0)
    result = run(scenario, tmp_path / "out")
    fault = result.metrics["faults"][0]
    assert 0.5 <= fault["detected_after_s"] <= 0.5 + 0.1, fault  # the timeout, plus the last message's age
    assert result.metrics["silent_neighbour_detections"] >= 1
    assert "robot 4's silence noticed by a team mate 0.5" in result.metrics["message"], result.metrics["message"]


def test_a_meeting_goes_on_without_a_dead_member_after_the_wait_and_not_before(tmp_path):
    from tether.runner import run

    fault = 'faults=[{kind="robot_failure", robot=2, at_s=20.0}]'
    given_up = {}
    for timeout in (10.0, 20.0):
        out = tmp_path / f"wait{timeout:g}"
        run(load("intermittent-8", [fault, f"strategy.member_timeout_s={timeout}"], duration_s=95.0), out)
        metrics = json.loads((out / "metrics.json").read_text())
        assert metrics["status"] == "completed", metrics["message"]
        assert metrics["meetings_missed"] == 1 and [r for r, _ in metrics["members_given_up"]] == [2]
        assert f"1 meetings held without robot(s) [2] after {timeout:g} s waits" in metrics["message"]
        given_up[timeout] = metrics["members_given_up"][0][1]
        assert metrics["faults"][0]["detected_after_s"] == pytest.approx(given_up[timeout] - 20.0)
        assert metrics["e_g_before_fault_m"] > 0 and metrics["e_g_after_fault_m"] > 0
        assert (f"e_g {metrics['e_g_before_fault_m']:.2f} m before, {metrics['e_g_after_fault_m']:.2f} m after"
                in metrics["message"])
    # The team mates arrived 59 s into the run: the meeting goes on one wait later, never earlier.
    assert given_up[20.0] - given_up[10.0] == pytest.approx(10.0)
    assert given_up[10.0] >= 20.0 + 10.0


@settings(max_examples=60, deadline=None)
@given(st.integers(1, 8).flatmap(lambda n: st.tuples(
    st.lists(st.sampled_from([-np.inf, 0.0, 0.2, 0.45, 0.5, 0.7]), min_size=n * n, max_size=n * n),
    st.lists(st.booleans(), min_size=n * n, max_size=n * n))), st.sampled_from([0.0, 0.45, 0.5, 1.0]))
def test_the_heartbeats_compiled_quiet_pairs_are_numpys(case, before_s):
    """``_quiet_pairs`` lists the pairs heard once, last before the limit and not yet silent, in the order
    ``numpy.nonzero`` gives them (the order the detections are recorded in)."""
    last, silent = case
    n = int(round(len(last) ** 0.5))
    last, silent = np.array(last).reshape(n, n), np.array(silent).reshape(n, n)
    expected = np.nonzero(np.isfinite(last) & (last < before_s) & ~silent)
    got = _quiet_pairs(last, silent, before_s)
    assert got.shape == (2, len(expected[0]))
    assert got[0].tolist() == expected[0].tolist() and got[1].tolist() == expected[1].tolist()
    # the monitor's own pass, reading no columns, writes the same pairs into its scratch
    quiet = np.full((2, n * n), -1, dtype=np.int64)
    empty = np.empty(0, dtype=np.int64)
    heard_again, found = _hear_columns_then_quiet_pairs(empty, empty, np.empty(0), last.copy(), silent.copy(),
                                                        empty, before_s, quiet)
    assert heard_again == 0 and found == len(expected[0])
    assert quiet[0, :found].tolist() == expected[0].tolist() and quiet[1, :found].tolist() == expected[1].tolist()


@pytest.mark.slow
def test_a_dead_member_on_its_meeting_point_is_judged_absent_by_its_silence(tmp_path):
    """random_meeting, intermittent-8: robot 4 reaches team 3's point at 79 s and waits for robot 3 (there at
    128 s, when the fault-free meeting is held). Robot 4 dies on its point at 100 s: it is where it should be,
    but nobody hears it, so robot 3 waits the 60 s default and the meeting goes on without it."""
    from tether.runner import run

    scenario = load("intermittent-8", ['strategy.kind="random_meeting"',
                                       'faults=[{kind="robot_failure", robot=4, at_s=100.0}]'], duration_s=200.0)
    metrics = run(scenario, tmp_path / "out").metrics
    assert metrics["status"] == "completed", metrics["message"]
    given_up = {r: t for r, t in metrics["members_given_up"] if r in (3, 4) and t > 100.0}
    # Neither hears the other: each goes on alone, one member_timeout_s after robot 3 arrived.
    assert given_up == {3: pytest.approx(188.0), 4: pytest.approx(188.0)}
    assert metrics["faults"][0]["detected_after_s"] == pytest.approx(88.0)
    assert metrics["delay_bound_held"] is False
    assert metrics["delay_bound_broken_s"] == min(t for _, t in metrics["members_given_up"])
    assert "delay bound of" in metrics["message"] and "broken at t =" in metrics["message"]


def test_a_member_that_came_early_waits_for_one_that_is_on_time_without_giving_it_up(tmp_path):
    """random_meeting, intermittent-8, seed 0, fault-free, the default 60 s member timeout: robot 1 reaches
    team 7's point at 23 s, robot 7 (busy with team 6's meeting at 47 s) on time for the planned 104 s. The
    wait counts from the planned time, so robot 1 waits 81 s and nobody is given up (counted from robot 1's
    arrival, robot 7 was given up at 83 s, 21 s before the meeting was due)."""
    from tether.runner import run

    metrics = run(load("intermittent-8", ['strategy.kind="random_meeting"'], seed=0, duration_s=120.0),
                  tmp_path / "out").metrics
    assert metrics["status"] == "completed", metrics["message"]
    assert metrics["meetings_missed"] == 0 and metrics["members_given_up"] == [], metrics["members_given_up"]
    assert metrics["max_wait_s"] > metrics["member_timeout_s"]  # longer than the timeout, and not given up
    assert metrics["delay_bound_held"] is True


def test_a_late_member_given_up_finishes_its_planned_path_to_the_point_first():
    """random_meeting, intermittent-8, seed 0, a 0.5 s member timeout: team 6's meeting of epoch 3 is planned
    for 188 s and robot 6 reaches its point 0.66 s later, so it is given up while still on its way. Its next
    path starts at this meeting's point, so it goes on along its own planned path to the point (not
    straight to the next path across the walls) and only then on to its next meeting."""
    late, duration_s = 6, 195.0
    scenario = load("intermittent-8", ['strategy.kind="random_meeting"', "strategy.member_timeout_s=0.5"], seed=0,
                    duration_s=duration_s)
    from tether.runner import build_simulation

    simulation = build_simulation(scenario)
    strategy = simulation.strategy
    held = None
    while simulation.time_s < duration_s:
        frame, _ = simulation.tick(decorations_wanted=False)
        segment = strategy.queues[late][0]
        if held is None and segment.meeting.held_s is not None:
            held = segment  # the meeting went on without the late robot; its head segment is still the one there
            assert late in segment.meeting.absent and (late, segment.meeting.held_s) in strategy.members_given_up
            # given up one timeout after the meeting's planned time, not after its team mate's early arrival
            assert segment.meeting.held_s == pytest.approx(segment.meeting.planned_time_s + 0.5, abs=0.05)
            assert not segment.at_end(simulation.time_s)
        if held is not None and segment is not held:
            # It left the held meeting's segment only at that segment's end, at the meeting's point.
            assert held.at_end(simulation.time_s)
            end = held.timed.path.positions[-1]
            assert np.linalg.norm(frame.observation.position[late, :2] - end) < 0.2  # the body is there too
            assert segment.timed.path.positions[0] == pytest.approx(end)
            break
    else:
        raise AssertionError(f"robot {late} never left the meeting held without it")


def _recorded_plans(strategy) -> list:
    """Wrap the strategy's planner so that each plan records (team, epoch, belief step, members' start steps)."""
    plans = []
    design = strategy.design

    def recording_design(team, epoch, members, starts, belief_step, estimate):
        plans.append((team, epoch, belief_step, [s.time for s in starts]))
        return design(team, epoch, members, starts, belief_step, estimate)

    strategy.design = recording_design
    return plans


@pytest.mark.parametrize("seed, robot, at_s, timeout_s, duration_s", [(0, 0, 60.0, 60.0, 140.0),
                                                                       (1, 5, 60.0, 60.0, 130.0)])
def test_a_member_given_up_starts_its_next_plan_no_earlier_than_the_meeting_it_missed(
        seed, robot, at_s, timeout_s, duration_s):
    """A member given up at a meeting still holds its segment to that meeting, planned to end before the
    meeting went on; its next plans start it no earlier than the belief they are planned on (these cases
    ended in ``belief_time must not exceed min(start_times)``)."""
    from tether.runner import build_simulation

    scenario = load("intermittent-8", [f'faults=[{{kind="robot_failure", robot={robot}, at_s={at_s}}}]',
                                       f"strategy.member_timeout_s={timeout_s}"], seed=seed, duration_s=duration_s)
    simulation = build_simulation(scenario)
    plans = _recorded_plans(simulation.strategy)
    while simulation.time_s < duration_s - 1e-9:
        simulation.tick(decorations_wanted=False)
    given_up = simulation.strategy.members_given_up
    assert any(r == robot for r, _ in given_up), given_up  # the case under test happened
    later = [p for p in plans if p[2] > 0]
    assert later and all(min(starts) >= belief for _, _, belief, starts in later), later


@pytest.mark.parametrize("radio", [[], IEEE], ids=["ideal", "ieee802154"])
def test_the_graph_figures_count_the_survivors_of_a_failure(radio):
    """The connected-office start cluster held in place, robot 4 failing at 0.2 s: its silence cuts it off
    (lambda2 of the whole team 0), yet the nine others still form a connected communication graph, which is
    what the metrics and the study's "comm graph disconnected" judge."""
    from sim.observers import LinkMetrics, link_figures

    scenario = load("connected-office", [*radio, 'faults=[{kind="robot_failure", robot=4, at_s=0.2}]'], duration_s=1.0)
    sim = Simulation(scenario, lambda _: Broadcaster(), LowLevelControl)
    metrics = LinkMetrics()
    frames = []
    for _ in range(40):
        frame = sim.tick()[0]
        metrics.on_tick(frame)
        frames.append(frame)
    before, after = frames[10], frames[-1]
    assert before.failed is None and after.failed.tolist() == [i == 4 for i in range(10)]
    assert link_figures(after.observation).comm_lambda2 == pytest.approx(0.0, abs=1e-9)  # the whole team's
    survivors = link_figures(after.observation, after.failed)
    assert survivors.comm_lambda2 > 0.1 and survivors.sensing_lambda2 > 0.1
    summary = metrics.summary()
    assert summary["comm_lambda2_min"] == pytest.approx(min(survivors.comm_lambda2,
                                                            link_figures(before.observation).comm_lambda2))


def test_a_path_clock_waits_for_a_lagging_body_at_most_its_bound_then_until_the_body_comes_close():
    holds = LagHolds(1, period_s=0.1, max_s=1.0)
    t, waited = 0.0, []
    for _ in range(15):  # 1.5 s lagging by 0.3 m: 10 ticks held (1 s), then the clock goes on
        waited.append(holds.wait(0, True, t, 0.3))
        t += 0.1
    assert waited == [True] * 10 + [False] * 5 and holds.released == 1
    assert holds.longest_s == pytest.approx(1.0)
    # Still not close (within half of LAG_HOLD_M): the clock stays loose, even where it dips below LAG_HOLD_M.
    assert not holds.wait(0, False, t, 0.1) and not holds.wait(0, True, t + 0.1, 0.3)
    # Close again: a new lag is waited for.
    assert not holds.wait(0, False, t + 0.2, 0.5 * LAG_HOLD_M) and holds.wait(0, True, t + 0.3, 0.3)
    # A short lag that ends is no stretch to cut.
    fresh = LagHolds(1, period_s=0.1, max_s=1.0)
    assert all(fresh.wait(0, True, k * 0.1, 0.3) for k in range(5)) and not fresh.wait(0, False, 0.5, 0.0)
    assert all(fresh.wait(0, True, 0.6 + k * 0.1, 0.3) for k in range(10)) and fresh.released == 0


def test_meetings_are_held_when_a_position_bias_keeps_a_robot_off_its_reference(tmp_path):
    """A biased fix (0.3 m, beyond LAG_HOLD_M) makes every body look behind its reference forever; a clock that
    waited for it stopped random_meeting (0 of 8 meetings in 150 s). With the wait bounded, they are held."""
    from tether.runner import run

    noise = 'faults=[{kind="position_noise", bias_m=0.3}]'
    metrics = run(load("intermittent-8", ['strategy.kind="random_meeting"', noise], seed=3, duration_s=150.0),
                  tmp_path / "out").metrics
    assert metrics["path_clock_holds_cut"] > 0
    assert metrics["meetings_held"] >= 6, metrics["message"]


def test_a_blackout_too_weak_for_the_ideal_radio_says_it_does_nothing(tmp_path):
    from tether.runner import run

    weak = ('faults=[{kind="radio_blackout", center=[4.0, 2.0, 1.0], radius_m=2.0, extra_loss_db=9.9, '
            'from_s=1.0}]')
    metrics = run(load("connected-office", [weak], duration_s=2.0), tmp_path / "out").metrics
    assert "(no effect: the ideal radio cuts a link only from 10 dB on)" in metrics["message"], metrics["message"]
