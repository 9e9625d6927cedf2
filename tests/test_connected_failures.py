"""The continuous-connectivity method's reaction to a failed robot (controllers/connectivity/failures.py), on
connected-office for a few seconds with real MuJoCo: the team drops the silent robot (at once under ideal,
after the heartbeat timeout and not before under a real radio), freezes its virtual point, re-issues the token
when the prime traveler fails (one prime traveler afterwards, never two), and hands its targets on."""

from __future__ import annotations

import numpy as np
import pytest

import tether  # noqa: F401 (registers the built-in scenarios)
from controllers.connectivity.roles import PRIME_CODE
from sim.scenario import load
from tether.runner import build_simulation, run

IEEE = ['radio.preset="ieee802154"', "strategy.heartbeat_timeout_s=0.5"]
PRIME_AT_1S = 8  # connected-office's default seed: robot 8 wins the first round and travels until well past 5 s
EXPLORER = 3  # a secondary traveler at 1 s with its current target and 2 more queued


def _failing(robot: int, at_s: float, radio=(), duration_s: float = 4.0):
    scenario = load("connected-office", [*radio, f'faults=[{{kind="robot_failure", robot={robot}, at_s={at_s}}}]'],
                    duration_s=duration_s)
    sim = build_simulation(scenario)
    primes_in_team, points = [], []
    for _ in range(int(round(duration_s / sim.dt))):
        frame, healthy = sim.tick()
        assert healthy and sim.strategy.violation(frame.commands) is None, sim.strategy.violation(frame.commands)
        strategy = sim.strategy
        primes_in_team.append(np.flatnonzero(strategy.roles == PRIME_CODE).tolist())
        points.append(strategy.q[robot].copy())
    return sim, primes_in_team, np.array(points)


@pytest.mark.parametrize("radio", [(), tuple(IEEE)], ids=["ideal", "ieee802154"])
def test_the_team_drops_the_prime_traveler_and_elects_a_new_one(radio):
    at_s = 1.0
    sim, primes, points = _failing(PRIME_AT_1S, at_s, radio)
    strategy = sim.strategy
    (dropped,) = strategy.dropped
    assert dropped.robot == PRIME_AT_1S and dropped.was_prime and dropped.held_token
    if radio:  # the heartbeat timeout after its last message, not before
        assert at_s + 0.5 <= dropped.at_s <= at_s + 0.5 + 0.1, dropped
    else:  # the in-process exchange: no link at all at the failure's tick
        assert dropped.at_s == pytest.approx(at_s)
    assert dropped.token_reissued_to == 0  # the lowest index of the team
    assert not strategy.in_team[PRIME_AT_1S]
    assert max(len(p) for p in primes) == 1  # never two prime travelers
    after = primes[int(round(dropped.at_s / sim.dt)) + 1:]
    assert after[-1] and after[-1][0] != PRIME_AT_1S  # a new prime traveler, elected by the team
    # the dead robot's virtual point stays where it was dropped
    frozen = points[int(round(dropped.at_s / sim.dt)) + 1:]
    assert np.array_equal(frozen, np.broadcast_to(frozen[0], frozen.shape))
    assert len(strategy.explorer.role_machine.holds_token.nonzero()[0]) <= 1


def test_a_failed_explorers_targets_go_to_the_nearest_explorers(tmp_path):
    result = run(load("connected-office", [f'faults=[{{kind="robot_failure", robot={EXPLORER}, at_s=1.0}}]'],
                      duration_s=3.0), tmp_path / "out")
    metrics = result.metrics
    fault = metrics["faults"][0]
    assert fault["targets_reassigned"] == 3 and fault["targets_lost"] == 0, fault
    assert fault["dropped_after_s"] == fault["detected_after_s"] == 0.0
    assert f"robot {EXPLORER} failed at 1.0 s; 3 of its 3 targets reassigned" in metrics["message"], metrics["message"]
    assert metrics["status"] in ("completed", "time limit")


@pytest.mark.parametrize("radio", [(), tuple(IEEE)], ids=["ideal", "ieee802154"])
def test_no_one_is_dropped_without_a_fault(radio):
    sim = build_simulation(load("connected-office", list(radio), duration_s=2.0))
    for _ in range(200):
        sim.tick()
    assert sim.strategy.in_team.all() and sim.strategy.dropped == []


def _virtual_points(overrides, duration_s=1.5):
    sim = build_simulation(load("connected-office", overrides, duration_s=duration_s))
    points, lambda2 = [], []
    for _ in range(int(round(duration_s / sim.dt))):
        frame, _ = sim.tick()
        points.append(frame.commands.position.copy())
        lambda2.append((frame.commands.scalars["lambda2"], frame.commands.position.copy()))
    return np.array(points), lambda2, sim


def test_position_noise_of_zero_is_the_fault_free_run_bit_for_bit_and_noise_moves_the_control():
    from controllers.connectivity.graph import connectivity_state

    clean, _, _ = _virtual_points([])
    zero, _, _ = _virtual_points(['faults=[{kind="position_noise", sigma_m=0.0, bias_m=0.0}]'])
    assert np.array_equal(clean, zero)
    noisy, lambda2, sim = _virtual_points(['faults=[{kind="position_noise", sigma_m=0.1, bias_m=0.05}]'])
    assert not np.array_equal(clean, noisy)  # the weights and the gradient come from the measured points
    # the invariant the run checks is measured on the true virtual points
    reported, points = lambda2[-1]
    assert reported == connectivity_state(points, sim.strategy.boxes, sim.strategy.params).lambda2


def test_in_estimator_mode_position_noise_reaches_the_estimators_weights():
    """The estimator's state follows the measured weights (the force too, once lambda2 is below lambda2_null)."""
    estimator = ['strategy.lambda2_source="estimator"']
    runs = [_virtual_points([*estimator, *noise], duration_s=0.5)[2].strategy.estimator.estimate.lambda2
            for noise in ([], ['faults=[{kind="position_noise", sigma_m=0.0}]'],
                          ['faults=[{kind="position_noise", sigma_m=0.01}]'])]
    assert np.array_equal(runs[0], runs[1]) and not np.array_equal(runs[0], runs[2])


def test_in_estimator_mode_the_dropped_robot_leaves_the_estimators_graph():
    """lambda2_source = "estimator" under ideal: after the drop the estimator is the nine robots' (its state
    carried over, the dead robot's point frozen), its estimate of the live team's lambda2 stays usable and
    the invariant, on the team still alive, holds."""
    robot, at_s = EXPLORER, 1.0
    sim, _, points = _failing(robot, at_s, radio=('strategy.lambda2_source="estimator"',), duration_s=3.0)
    strategy = sim.strategy
    (dropped,) = strategy.dropped
    assert dropped.robot == robot and dropped.at_s == pytest.approx(at_s, abs=sim.dt)
    assert strategy.estimator.num_robots == 9
    assert np.isfinite(strategy.estimator.estimate.lambda2).all()
    after = points[int(round(at_s / sim.dt)) + 1:]
    assert np.ptp(after, axis=0).max() == 0.0  # its virtual point frozen where it was dropped


def test_over_the_radio_the_estimator_drops_the_silent_robot_and_estimates_the_survivors_graph():
    """lambda2_source = "estimator" under ieee802154 (the estimator fed by the message bus): robot 7 (in the
    middle of the start lattice) fails at 0.5 s; its team mates drop it one heartbeat timeout after its last
    message, and from then on the estimator is the nine survivors': nobody uses a message from it, it sends
    none, its row is NaN, the invariant's lambda2 is the survivors' graph's (0.74, the ten robots' 1.37), and
    the survivors' estimates, 1.37 at the drop, reach the survivors' lambda2. A static team (robot 0 dwells at
    its start, the others have no targets, the connectivity force off above lambda2 = 0.3) keeps the graph
    fixed, so the estimate has one value to approach."""
    from controllers.connectivity.graph import connectivity_state
    from controllers.connectivity.estimator_messages import LAMBDA2_ESTIMATE_KIND

    robot, at_s, duration_s = 7, 0.5, 3.5
    scenario = load("connected-office", [*IEEE, 'strategy.lambda2_source="estimator"', 'strategy.targets="fixed"',
                                         "strategy.target_lists=[[[4.15, 0.9, 1.0]]]", "strategy.dwell_time_s=20",
                                         "strategy.lambda2_null=0.3",
                                         f'faults=[{{kind="robot_failure", robot={robot}, at_s={at_s}}}]'],
                    duration_s=duration_s)
    sim = build_simulation(scenario)
    strategy = sim.strategy
    whole = connectivity_state(strategy.q, strategy.boxes, strategy.params).lambda2
    survivors = np.arange(10) != robot
    alive = connectivity_state(strategy.q[survivors], strategy.boxes, strategy.params).lambda2
    assert alive < whole - 0.5 and alive < strategy.params.message_estimator.lambda2_ceiling
    errors, reported, senders = [], [], set()
    for _ in range(int(round(duration_s / sim.dt))):
        frame, healthy = sim.tick()
        assert healthy and strategy.violation(frame.commands) is None, strategy.violation(frame.commands)
        if strategy.dropped:
            estimate = strategy.estimator.estimate.lambda2
            assert np.isnan(estimate[robot]) and np.isfinite(estimate[survivors]).all()
            errors.append(np.abs(estimate[survivors] - alive).max())
            reported.append(frame.commands.scalars["lambda2"])
            senders |= {m.sender for m in frame.commands.outbox if m.kind == LAMBDA2_ESTIMATE_KIND}
    (dropped,) = strategy.dropped
    assert dropped.robot == robot and at_s + 0.5 - 0.02 <= dropped.at_s <= at_s + 0.6, dropped  # the timeout
    assert not strategy.estimator.members[robot] and strategy.estimator.members[survivors].all()
    assert not strategy.estimator.used[:, robot].any() and robot not in senders
    assert np.allclose(reported, alive, atol=1e-6)  # the check is on the survivors' graph, not the ten robots'
    assert errors[0] > 0.4  # at the drop the estimate is still the ten robots'
    assert min(errors) < 0.05, min(errors)  # every survivor's estimate comes to the survivors' lambda2


@pytest.mark.parametrize("radio, loss_db, until_s", [((), 30.0, 1.5), (tuple(IEEE), 150.0, 2.0)],
                         ids=["ideal", "ieee802154"])
def test_a_robot_dropped_behind_a_blackout_is_taken_back_once_heard_again(radio, loss_db, until_s):
    robot, from_s = 3, 0.5  # at (4.15, 2.0, 1.0) in the start cluster
    blackout = (f'faults=[{{kind="radio_blackout", center=[4.15, 2.0, 1.0], radius_m=0.4, '
                f'extra_loss_db={loss_db}, from_s={from_s}, to_s={until_s}}}]')
    sim = build_simulation(load("connected-office", [*radio, blackout], duration_s=until_s + 1.0))
    in_team, primes = [], []
    for _ in range(int(round((until_s + 1.0) / sim.dt))):
        frame, healthy = sim.tick()
        assert healthy and sim.strategy.violation(frame.commands) is None, sim.strategy.violation(frame.commands)
        in_team.append(bool(sim.strategy.in_team[robot]))
        primes.append(int(np.count_nonzero(sim.strategy.roles == PRIME_CODE)))
    (dropped,) = sim.strategy.dropped
    assert dropped.robot == robot
    assert from_s <= dropped.at_s < until_s  # dropped during the blackout ...
    assert dropped.taken_back_at_s is not None and until_s <= dropped.taken_back_at_s <= until_s + 0.5  # ... back after
    assert in_team[-1] and max(primes) == 1
    summary = sim.strategy.summary()["dropped_robots"]
    assert summary[0]["taken_back_at_s"] == pytest.approx(dropped.taken_back_at_s)


def test_the_message_names_a_healthy_robot_dropped_and_taken_back(tmp_path):
    blackout = ('faults=[{kind="radio_blackout", center=[4.15, 2.0, 1.0], radius_m=0.4, extra_loss_db=30.0, '
                'from_s=0.5, to_s=1.5}]')
    metrics = run(load("connected-office", [blackout], duration_s=2.0), tmp_path / "out").metrics
    assert "robot 3 dropped as silent at 0.5 s, taken back at 1.5 s" in metrics["message"], metrics["message"]
    assert metrics["dropped_robots"][0]["taken_back_at_s"] == pytest.approx(1.5)


@pytest.mark.parametrize("radio", [(), tuple(IEEE)], ids=["ideal", "ieee802154"])
def test_the_first_token_holder_failing_at_0_s_leaves_the_token_with_the_team(radio):
    """Robot 0 hosts the start-up round. Failing at 0 s, it is dropped before the start-up under ideal, whose
    token then goes to the next robot; over the radio, one heartbeat timeout after the start (its team mates
    knew it from the start), the token re-issued. Then a prime traveler is elected, never two."""
    sim, primes, _ = _failing(0, 0.0, radio, duration_s=3.0)
    (dropped,) = sim.strategy.dropped
    assert dropped.held_token and dropped.token_reissued_to == 1
    assert dropped.at_s <= (0.5 + 0.1 if radio else 0.0)
    after = primes[int(round(dropped.at_s / sim.dt)) + 1:]
    assert max(len(p) for p in primes) == 1 and any(after)
    assert 0 not in {robot for p in after for robot in p}


def test_a_robot_whose_only_neighbour_failed_is_cut_off_not_silent():
    """connected-office, seed 6: robots 7 and 9 hear only robot 5. When it fails, they are not dropped as
    silent (their one witness is the dead robot itself): the team's graph split, and the run says so, as it
    does over a real radio."""
    sim = build_simulation(load("connected-office", ['faults=[{kind="robot_failure", robot=5, at_s=60.0}]'],
                                seed=6, duration_s=61.0))
    while True:
        frame, healthy = sim.tick()
        broke = sim.strategy.violation(frame.commands)
        if broke or not healthy or frame.observation.time_s >= 60.5:
            break
    assert [d.robot for d in sim.strategy.dropped] == [5]
    assert broke and "graph split" in broke, broke


def test_the_planner_keeps_clear_of_a_dropped_robots_point_and_forgets_it_when_taken_back():
    sim, _, points = _failing(EXPLORER, 1.0, duration_s=1.5)
    strategy = sim.strategy
    frozen = points[-1]
    assert not strategy.planner.is_free(frozen[None])[0]
    assert strategy.explorer.planner is strategy.planner
    # Every path of the team passes the point at R_c or more.
    p = strategy.params
    for path in strategy.explorer.paths:
        if path is not None and path.spline is not None:
            samples = path.sample(0.05)
            assert np.linalg.norm(samples[:, :2] - frozen[:2], axis=1).min() >= p.min_robot_distance_m - 0.05
    # Taken back: the planner of the scene alone again.
    entry = strategy.dropped[0]
    strategy.in_team[EXPLORER] = True
    entry.taken_back_at_s = 1.5
    strategy._plan_around_dropped()
    assert strategy.planner.is_free(frozen[None])[0]


def test_a_robot_failing_at_0_s_in_the_start_cluster_leaves_every_target_reachable():
    """Robot 4, the middle of the start grid, fails at 0 s: the points kept clear round it are a preference
    for the planner, not a wall round its neighbours' starts (before: 10 of 25 targets skipped at t = 0)."""
    sim = build_simulation(load("connected-office", ['faults=[{kind="robot_failure", robot=4, at_s=0.0}]'],
                                seed=5, duration_s=1.0))
    for _ in range(50):
        sim.tick()
    explorer = sim.strategy.explorer
    assert explorer.skipped == []
    assert sum(path is not None for path in explorer.paths) >= 1


def test_a_drop_is_blamed_for_a_split_only_when_the_team_with_it_is_connected():
    sim = build_simulation(load("connected-office", ['faults=[{kind="robot_failure", robot=5, at_s=60.0}]'],
                                seed=6, duration_s=61.0))
    while not sim.strategy.dropped:
        sim.tick()
    sim.tick()
    assert sim.strategy._split_by_drops()  # robot 5 was the only link of robots 7 and 9


def test_a_dropped_robot_is_drawn_white_and_named_in_the_legend_only_while_it_is_out():
    from sim import palette

    sim = build_simulation(load("connected-office", [f'faults=[{{kind="robot_failure", robot={EXPLORER}, at_s=0.2}}]'],
                                duration_s=0.5))
    legends, colors = [], []
    for _ in range(50):
        frame, _ = sim.tick()
        legends.append([label for label, _ in frame.commands.decorations.legend])
        colors.append(frame.commands.decorations.robot_colors[EXPLORER])
    name = "robot dropped from the team (not heard)"
    assert name not in legends[0] and name in legends[-1]
    np.testing.assert_array_equal(colors[-1], palette.DROPPED)
