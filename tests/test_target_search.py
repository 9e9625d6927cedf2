"""The search for targets not yet fixed (estimation/target_search.py, Belief with a search space):
hand-computed likelihoods, moments and collapse, the hypotheses carried by the target model,
order-free weights, and a belief that finds a target from readings and non-readings."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from estimation.beliefs import Belief, RangeMeasurement
from estimation.ekf import FilterState
from estimation.range_model import range_sigma
from estimation.target_init import ReadingsInitialiser
from estimation.target_motion import CircularPath, LinearPath, TargetMotion
from estimation.target_search import (HypothesisMotion, SearchSpace, StepLooks, collapse, grid_points,
                                      miss_log_likelihood, moments, normalised, reading_log_likelihood,
                                      outside_log_likelihood, update_log_weights, visible, visible_mass)

SENSOR_Z = 0.05


def test_a_reading_weighs_by_the_gaussian_of_the_range_hand_computed():
    positions = np.array([[3.0, 0.0, 0.0], [4.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    sigma = 0.045 * 3.0 - 0.035  # eq. (12) at 3 m: 0.1 m
    assert float(range_sigma(np.array(3.0))) == pytest.approx(sigma)
    out = reading_log_likelihood(positions, np.zeros(3), 3.0, extra_variance=0.0)
    assert out == pytest.approx([0.0, -0.5 * 1.0 / sigma**2, -0.5 * 1.0 / sigma**2])
    widened = reading_log_likelihood(positions, np.zeros(3), 3.0, extra_variance=1.0 - sigma**2)
    assert widened == pytest.approx([0.0, -0.5, -0.5])


def test_a_non_reading_lowers_only_what_the_sensor_would_have_seen():
    positions = np.array([[1.0, 0.0, 0.0], [4.0, 0.0, 0.0], [6.0, 0.0, 0.0], [0.0, 4.5, 0.0], [-2.0, 0.0, 0.0]])

    def wall_at_minus_one(a, b):  # a wall across x = -1 blocks everything behind it
        return ~((np.minimum(a[:, 0], b[:, 0]) < -1.0) & (np.maximum(a[:, 0], b[:, 0]) > -1.0))

    out = miss_log_likelihood(positions, np.zeros(3), 5.0, 0.1, margin_m=0.0, line_of_sight=wall_at_minus_one)
    log_miss = np.log(0.1)
    assert out == pytest.approx([log_miss, log_miss, 0.0, log_miss, 0.0])
    # The margin keeps the range's edge: 4.5 m is within 0.6 m of 5 m.
    edge = miss_log_likelihood(positions, np.zeros(3), 5.0, 0.1, margin_m=0.6)
    assert edge == pytest.approx([log_miss, log_miss, 0.0, 0.0, log_miss])
    only = miss_log_likelihood(positions, np.zeros(3), 5.0, 0.1, consider=np.array([True, False, True, True, True]))
    assert only[1] == 0.0


def test_moments_of_two_points_hand_computed():
    positions = np.array([[0.0, 0.0, 1.0], [2.0, 0.0, 1.0]])
    mean, covariance = moments(positions, np.zeros(2))
    assert mean == pytest.approx([1.0, 0.0, 1.0])
    assert covariance == pytest.approx(np.diag([1.0, 0.0, 0.0]))
    cell = np.diag([0.01, 0.01, 0.04])
    _, widened = moments(positions, np.array([0.0, np.log(3.0)]), cell)  # weights 1/4, 3/4
    assert widened == pytest.approx(np.diag([4 * 0.25 * 0.75, 0.0, 0.0]) + cell)
    assert normalised(np.array([0.0, np.log(3.0)])) == pytest.approx([0.25, 0.75])


def test_two_modes_do_not_collapse_one_tight_mode_does():
    rng = np.random.default_rng(0)
    cluster = rng.normal(0.0, 0.1, (50, 3))
    two = np.vstack([cluster + [2.0, 2.0, 1.0], cluster + [6.0, 2.0, 1.0]])
    assert collapse(two, np.zeros(len(two))) is None
    log_weights = np.where(np.arange(len(two)) < 50, 0.0, -40.0)  # the second mode ruled out
    result = collapse(two, log_weights)
    assert result is not None
    mean, covariance = result
    assert mean == pytest.approx([2.0, 2.0, 1.0], abs=0.05)
    assert np.linalg.eigvalsh(covariance)[-1] < 0.05


def test_grid_points_are_cell_centres_and_only_free_ones():
    points = grid_points(np.zeros(3), np.array([2.0, 1.0, 1.0]), np.array([1.0, 0.5, 1.0]))
    assert len(points) == 2 * 2 * 1
    assert sorted(map(tuple, points)) == [(0.5, 0.25, 0.5), (0.5, 0.75, 0.5), (1.5, 0.25, 0.5), (1.5, 0.75, 0.5)]
    free = grid_points(np.zeros(3), np.array([2.0, 1.0, 1.0]), np.array([1.0, 0.5, 1.0]),
                       free=lambda p: p[:, 0] < 1.0)
    assert len(free) == 2 and np.all(free[:, 0] == 0.5)
    with pytest.raises(ValueError, match="grid"):
        grid_points(np.zeros(3), np.zeros(3), np.ones(3))


def test_hypotheses_move_with_the_target_model():
    motion = TargetMotion([CircularPath((2.0, 2.0, 1.0), 0.5, 0.05), LinearPath((0, 0, 1), (3, 0, 1), 0.1)],
                          dt=1.0, noise_std=0.0)
    carried = HypothesisMotion(motion)
    points = np.random.default_rng(1).uniform(0, 4, (6, 3))
    for target in (0, 1):
        expected = [points]
        states = np.tile(points, (1, 2))
        for k in range(45):
            states = np.array([motion.predict(s, k) for s in states])
            expected.append(states[:, 3 * target:3 * target + 3])
        for k in (0, 1, 17, 45):
            assert carried.positions(points, target, k) == pytest.approx(expected[k], abs=1e-9)


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 10_000))
def test_the_weights_do_not_depend_on_the_order_of_the_looks(seed):
    rng = np.random.default_rng(seed)
    space = SearchSpace(grid_points(np.zeros(3), np.array([6.0, 6.0, 2.0]), np.array([0.5, 0.5, 1.0])),
                        np.array([0.5, 0.5, 1.0]), 3.0)
    truth = rng.uniform([0, 0, 0], [6, 6, 2])
    looks = []
    for _ in range(6):
        sensor = np.append(rng.uniform(0, 6, 2), SENSOR_Z)
        distance = float(np.linalg.norm(truth - sensor))
        looks.append(StepLooks(sensor, {0: distance} if distance < 3.0 else {}))
    forward = update_log_weights(space, space.points, np.zeros(space.n_hypotheses), 0, looks, 0.0)
    backward = np.zeros(space.n_hypotheses)
    for look in reversed(looks):
        backward = update_log_weights(space, space.points, backward, 0, [look], 0.0)
    assert normalised(forward) == pytest.approx(normalised(backward), abs=1e-9)
    # The truth's cell is never ruled out: its weight stays within the grid's widening of the best.
    nearest = int(np.argmin(np.linalg.norm(space.points - truth, axis=1)))
    assert forward[nearest] > -30.0


def static_motion(n_targets: int) -> TargetMotion:
    return TargetMotion([LinearPath((1, 1, 1), (1, 1, 1), 0.0)] * n_targets, dt=1.0, noise_std=0.01)


def room_search(sensing_range: float = 5.0) -> SearchSpace:
    spacing = np.array([0.35, 0.35, 2.5 / 3])
    return SearchSpace(grid_points(np.zeros(3), np.array([10.0, 10.0, 2.5]), spacing), spacing, sensing_range)


def sensed_records(truth: np.ndarray, path: list[np.ndarray], sensing_range: float, rng) -> list[RangeMeasurement]:
    """Readings of every target within range of every sensor (no walls), noisy as eq. (12)."""
    out = []
    for step, sensors in enumerate(path):
        for robot, sensor in enumerate(sensors):
            for target, point in enumerate(truth):
                distance = float(np.linalg.norm(sensor - point))
                if distance < sensing_range:
                    out.append(RangeMeasurement(step, robot, tuple(sensor), target,
                                                max(distance + rng.normal(0, range_sigma(distance)), 0.0)))
    return out


def neutral(n_targets: int) -> FilterState:
    return FilterState(0, np.tile([5.0, 5.0, 1.25], n_targets), 12.5 * np.eye(3 * n_targets))


def test_a_belief_with_a_search_reports_the_hypotheses_moments_and_fixes_from_their_collapse():
    """One robot sees target 0 at once and drives on, east then north (along one line its readings
    fit the target and its mirror image); target 1 is out of its range. Target 1's estimate moves
    away from where the robot looked (its non-readings); target 0's hypotheses collapse to a fix
    near the truth; records in another order give the same estimates."""
    truth = np.array([[3.0, 3.0, 1.2], [8.5, 8.5, 1.0]])
    path = [np.array([[2.0 + 0.1 * min(k, 20), 2.0 + 0.1 * max(k - 20, 0), SENSOR_Z]]) for k in range(40)]
    records = sensed_records(truth, path, 4.0, np.random.default_rng(4))
    assert not any(r.target == 1 for r in records)
    initialiser = ReadingsInitialiser(height_range=(0.0, 2.5), search=room_search(4.0))
    belief = Belief(static_motion(2), neutral(2), SENSOR_Z, initialiser)
    belief.receive(records)
    start = belief.estimate(0)
    assert start.mean[3:5] != pytest.approx([5.0, 5.0])  # moments, not the prior
    assert belief.fixed_targets(39) >= frozenset({0})
    plain = Belief(static_motion(2), neutral(2), SENSOR_Z, ReadingsInitialiser(height_range=(0.0, 2.5)))
    plain.receive(records)
    first = min(k for k in range(40) if 0 in belief.fixed_targets(k))
    assert 0 not in plain.fixed_targets(first)  # the collapse fixed it, before multilateration could
    assert np.linalg.norm(belief.estimate(39).mean[:3] - truth[0]) < 0.5
    assert belief.hypotheses(39, 0) is None  # fixed: the EKF has it
    positions, weights = belief.hypotheses(39, 1)
    assert weights.sum() == pytest.approx(1.0)
    seen = np.linalg.norm(positions[:, :2] - [3.0, 2.0], axis=1) < 2.0
    assert weights[seen].sum() < 1e-3  # looked at from close by, no reading: not there
    assert np.linalg.norm(belief.estimate(39).mean[3:5] - truth[1, :2]) < np.linalg.norm(start.mean[3:5] - truth[1, :2])

    shuffled = list(records)
    np.random.default_rng(1).shuffle(shuffled)
    late = Belief(static_motion(2), neutral(2), SENSOR_Z, initialiser)
    late.receive(shuffled[: len(shuffled) // 2])
    late.estimate(39)
    late.receive(shuffled[len(shuffled) // 2:])
    for k in (0, 10, 39):
        assert np.array_equal(late.estimate(k).mean, belief.estimate(k).mean)
        assert late.fixed_targets(k) == belief.fixed_targets(k)


def test_forgetting_keeps_the_hypotheses():
    truth = np.array([[8.5, 8.5, 1.0]])
    path = [np.array([[2.0 + 0.1 * k, 2.0, SENSOR_Z]]) for k in range(30)]
    records = sensed_records(truth, path, 4.0, np.random.default_rng(2))
    records.append(RangeMeasurement(29, 0, (4.9, 2.0, SENSOR_Z), 0, 7.0))  # one far reading
    belief = Belief(static_motion(1), neutral(1), SENSOR_Z, ReadingsInitialiser(search=room_search(8.0)))
    belief.receive(records)
    reference = belief.hypotheses(29, 0)
    belief.forget_before(20)
    again = belief.hypotheses(29, 0)
    assert np.array_equal(reference[1], again[1])


def test_hypotheses_carried_out_of_the_scene_weigh_as_a_miss_hand_computed():
    bounds = np.array([[0.0, 0.0, 0.0], [10.0, 10.0, 2.5]])
    positions = np.array([[5.0, 5.0, 1.0], [10.2, 5.0, 1.0], [10.4, 5.0, 1.0], [5.0, -1.0, 1.0], [5.0, 5.0, 2.8]])
    out = outside_log_likelihood(positions, bounds, 0.05, margin_m=0.3)
    assert out == pytest.approx([0.0, 0.0, np.log(0.05), np.log(0.05), 0.0])
    # In a step's update: the one look from far away (nothing in range) leaves only the box's factor;
    # the margin there is a cell's half diagonal (0.25 m) plus twice the drift (0 here).
    space = SearchSpace(positions, np.array([0.4, 0.3, 0.0]), 5.0, bounds=bounds)
    looks = [StepLooks(np.array([100.0, 100.0, 0.0]))]
    updated = update_log_weights(space, positions, np.zeros(5), 0, looks, drift_variance=0.0)
    assert updated == pytest.approx([0.0, 0.0, np.log(0.05), np.log(0.05), np.log(0.05)])
    unbounded = SearchSpace(positions, np.array([0.4, 0.3, 0.0]), 5.0)
    assert update_log_weights(unbounded, positions, np.zeros(5), 0, looks, 0.0) == pytest.approx(np.zeros(5))


def test_visible_hypotheses_are_those_in_range_less_a_cell_and_in_sight_hand_computed():
    """Range 5 m, cells 0.4 x 0.3 m (half diagonal 0.25 m: seen closer than 4.75 m); a wall at
    x = 2 hides everything beyond it from a sensor at the origin."""
    positions = np.array([[4.7, 0.0, 0.0], [0.0, 4.8, 0.0], [1.0, 1.0, 0.0], [3.0, 0.0, 0.0]])
    weights = np.array([0.1, 0.2, 0.3, 0.4])
    open_space = SearchSpace(positions, np.array([0.4, 0.3, 0.0]), 5.0)
    assert visible(open_space, np.zeros(3), positions).tolist() == [True, False, True, True]
    assert visible_mass(open_space, np.zeros((1, 3)), positions, weights) == pytest.approx([0.8])

    def wall_at_x_2(a, b):
        return ~((a[:, 0] - 2.0) * (b[:, 0] - 2.0) < 0)  # clear unless the segment crosses x = 2

    walled = SearchSpace(positions, np.array([0.4, 0.3, 0.0]), 5.0, wall_at_x_2)
    assert visible(walled, np.zeros(3), positions).tolist() == [False, False, True, False]
    # From (4, 0, 0): (4.7, 0) and (3, 0) in sight and range, (1, 1) and (0, 4.8) behind the wall.
    assert visible_mass(walled, np.array([[0.0, 0.0, 0.0], [4.0, 0.0, 0.0]]), positions, weights) == \
        pytest.approx([0.3, 0.5])


@pytest.mark.slow
def test_intermittent_in_a_held_out_room_without_a_prior_is_within_1_5_times_the_office():
    """The newcomer's case of issue 22: intermittent-8 moved into a room it was never tuned in
    (10 x 10 m, two L-shaped walls, four pillars), no prior given: over 300 s its e_g is within
    1.5 times what it gets in the built-in office with the paper's informed prior (same seed)."""
    from pathlib import Path

    from sim.scenario import load
    from tether.placement import load_in_scene
    from tether.runner import run

    room = Path(__file__).parent / "data" / "room_l_walls.xml"
    scenario, notes = load_in_scene("intermittent-8", str(room), seed=1, duration_s=300.0)
    assert scenario.strategy.params.init_from_readings
    held_out = run(scenario).metrics["e_g_mean_m"]
    office = run(load("intermittent-8", seed=1, duration_s=300.0)).metrics["e_g_mean_m"]
    assert held_out <= 1.5 * office, (held_out, office)


@pytest.mark.slow
def test_connected_tracking_in_a_held_out_room_without_a_prior_is_within_1_5_times_the_office():
    """Issue 22's bound for connected_tracking: moved into the held-out room with no prior, its
    explorers look for the targets not yet fixed; over 300 s its e_g (mean over seeds 1-3; single
    seeds spread 1.9 to 2.9 m) is within 1.5 times its own in the built-in office."""
    from pathlib import Path

    from sim.scenario import load
    from tether.placement import load_in_scene
    from tether.runner import run

    room = Path(__file__).parent / "data" / "room_l_walls.xml"
    kind = ["strategy.kind=connected_tracking"]
    held_out, office = [], []
    for seed in (1, 2, 3):
        scenario, _ = load_in_scene("intermittent-8", str(room), kind, seed=seed, duration_s=300.0)
        assert scenario.strategy.params.init_from_readings
        metrics = run(scenario).metrics
        assert metrics["search_viewpoints_issued"] > 0
        held_out.append(metrics["e_g_mean_m"])
        office.append(run(load("intermittent-8", kind, seed=seed, duration_s=300.0)).metrics["e_g_mean_m"])
    assert np.mean(held_out) <= 1.5 * np.mean(office), (held_out, office)
