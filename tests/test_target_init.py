"""A target's first estimate from its readings (estimation/target_init.py) and the beliefs that
use it (estimation/beliefs.py with an initialiser): hand-computed multilateration, hypothesis
properties (exact ranges from non-collinear sensors recover the point; sensors on one line are
refused), readings of a moving target carried to one step, and a belief that fixes its targets
from their readings whatever the order the records arrive in."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from estimation.beliefs import Belief, RangeMeasurement
from estimation.ekf import FilterState
from estimation.range_model import range_sigma
from estimation.target_init import (ACCEPTED_VARIANCE_M2, BASELINE_SHARE, ReadingsInitialiser, carried_sensors,
                                    multilaterate)
from estimation.target_motion import CircularPath, LinearPath, TargetMotion

SENSOR_Z = 0.05


def exact(sensors, point):
    return np.linalg.norm(np.asarray(sensors, float) - point, axis=1)


def test_three_sensors_in_a_plane_hand_computed():
    """Equal ranges 5.2 m from the corners of a right triangle (0,0), (6,0), (0,8): the foot is the
    hypotenuse's midpoint (3, 4), 5 m from each corner; the height sqrt(5.2^2 - 5^2) = 1.428 m, on
    the plane's upper side."""
    sensors = np.array([[0, 0, 0], [6, 0, 0], [0, 8, 0]], float)
    fix = multilaterate(sensors, np.full(3, 5.2), np.full(3, 0.01))
    assert fix is not None
    assert fix.position == pytest.approx([3.0, 4.0, np.sqrt(5.2**2 - 25)], abs=1e-9)
    assert fix.chi2 == pytest.approx(0.0, abs=1e-12)


def test_four_sensors_in_space_hand_computed():
    """The origin and the three unit points; ranges sqrt(3), sqrt(2), sqrt(2), sqrt(2) are those of (1, 1, 1)."""
    sensors = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    ranges = np.sqrt([3.0, 2.0, 2.0, 2.0])
    fix = multilaterate(sensors, ranges, np.full(4, 0.01))
    assert fix is not None and fix.position == pytest.approx([1.0, 1.0, 1.0], abs=1e-9)


def test_the_covariance_is_the_inverse_information():
    """Target straight above the origin sensor: the reading from there constrains only z, so with
    sigma 0.1 m and two side sensors the fix's covariance is (J^T W J)^-1, computed by hand here."""
    sensors = np.array([[0, 0, 0], [4, 0, 0], [0, 4, 0]], float)
    point = np.array([0.0, 0.0, 3.0])
    fix = multilaterate(sensors, exact(sensors, point), np.full(3, 0.1))
    jacobian = np.array([[0, 0, 1], [-0.8, 0, 0.6], [0, -0.8, 0.6]])
    assert fix.covariance == pytest.approx(np.linalg.inv(jacobian.T @ jacobian / 0.01), rel=1e-6)


def test_too_few_readings_and_collinear_sensors_are_refused():
    point = np.array([2.0, 3.0, 1.0])
    two = np.array([[0, 0, SENSOR_Z], [3, 0, SENSOR_Z]])
    assert multilaterate(two, exact(two, point), np.full(2, 0.01)) is None
    line = np.column_stack([np.linspace(0, 4, 6), np.zeros(6), np.full(6, SENSOR_Z)])
    assert multilaterate(line, exact(line, point), np.full(6, 0.01)) is None


def test_sensors_nearly_on_a_line_are_deferred_not_guessed():
    """Millimetres off one line, the point and its image across the line fit the ranges equally."""
    line = np.column_stack([np.linspace(0, 4, 6), [0, 0.002, 0, 0.002, 0, 0.002], np.full(6, SENSOR_Z)])
    point = np.array([2.0, 3.0, 1.0])
    assert multilaterate(line, exact(line, point), np.full(6, 0.1)) is None


def test_readings_of_two_different_points_are_refused():
    sensors = np.array([[0, 0, SENSOR_Z], [5, 0, SENSOR_Z], [0, 5, SENSOR_Z], [5, 5, SENSOR_Z],
                        [2.5, 0, SENSOR_Z], [0, 2.5, SENSOR_Z]])
    ranges = np.concatenate([exact(sensors[:3], [1, 1, 1]), exact(sensors[3:], [4, 4, 1])])
    assert multilaterate(sensors, ranges, np.full(6, 0.01)) is None


def test_a_weak_fix_waits_for_more_readings():
    """Far away from a small cluster of sensors the fix's covariance is above the accepted variance."""
    cluster = np.array([[0, 0, SENSOR_Z], [0.12, 0, SENSOR_Z], [0, 0.12, SENSOR_Z], [0.12, 0.12, SENSOR_Z]])
    point = np.array([4.0, 2.0, 1.2])
    assert multilaterate(cluster, exact(cluster, point), np.full(4, 0.1)) is None
    spread = np.array([[0, 0, SENSOR_Z], [3, 0, SENSOR_Z], [0, 3, SENSOR_Z], [3, 3, SENSOR_Z]])
    fix = multilaterate(spread, exact(spread, point), np.full(4, 0.1))
    assert fix is not None and np.linalg.eigvalsh(fix.covariance)[-1] <= ACCEPTED_VARIANCE_M2


def test_a_height_prior_narrows_the_height():
    """The scene's floor-to-ceiling prior is one more term of the least squares: the fix's height
    variance is below the readings' alone and below the prior's, (2.5 m)^2 / 12."""
    sensors = np.array([[0, 0, SENSOR_Z], [4, 0, SENSOR_Z], [0, 4, SENSOR_Z], [4, 4, SENSOR_Z]])
    point = np.array([2.0, 6.0, 1.3])
    ranges = exact(sensors, point)
    alone = multilaterate(sensors, ranges, range_sigma(ranges))
    tied = multilaterate(sensors, ranges, range_sigma(ranges), height_prior=(1.3, 2.5**2 / 12))
    assert alone is not None and tied is not None
    assert tied.position == pytest.approx(point, abs=1e-6)
    assert tied.covariance[2, 2] < min(alone.covariance[2, 2], 2.5**2 / 12)


@settings(max_examples=60, deadline=None)
@given(st.integers(3, 8), st.integers(0, 2**31 - 1))
def test_exact_ranges_from_non_collinear_sensors_recover_the_point(n, seed):
    rng = np.random.default_rng(seed)
    sensors = np.column_stack([rng.uniform(0, 6, (n, 2)), np.full(n, SENSOR_Z)])
    centred = sensors[:, :2] - sensors[:, :2].mean(axis=0)
    point = np.array([*rng.uniform(0, 6, 2), rng.uniform(0.5, 2.5)])
    baseline = np.linalg.svd(centred, compute_uv=False)[-1] / np.sqrt(n)
    # near a line, or a baseline too short for the ranges: covered by the refusal tests
    assume(baseline >= 0.3 and baseline >= 1.05 * BASELINE_SHARE * exact(sensors, point).mean())
    fix = multilaterate(sensors, exact(sensors, point), np.full(n, 1e-3))
    assert fix is not None
    assert fix.position == pytest.approx(point, abs=1e-6)


@settings(max_examples=40, deadline=None)
@given(st.integers(3, 8), st.integers(0, 2**31 - 1))
def test_sensors_on_one_line_never_give_a_fix(n, seed):
    rng = np.random.default_rng(seed)
    direction = rng.normal(size=2)
    direction /= np.linalg.norm(direction)
    along = rng.uniform(-3, 3, n)
    sensors = np.column_stack([1 + along * direction[0], 2 + along * direction[1], np.full(n, SENSOR_Z)])
    point = np.array([*rng.uniform(0, 6, 2), rng.uniform(0.5, 2.5)])
    assert multilaterate(sensors, exact(sensors, point), np.full(n, 0.01)) is None


def test_readings_of_a_moving_target_carried_to_one_step_keep_their_distances():
    motion = TargetMotion([CircularPath((2.0, 2.0, 1.0), 0.5, 0.05), LinearPath((0, 0, 1), (3, 0, 1), 0.1)],
                          dt=1.0, noise_std=0.0)
    states = [motion.initial_state()]
    for k in range(40):
        states.append(motion.predict(states[-1], k))
    rng = np.random.default_rng(3)
    steps = np.array([0, 5, 17, 33, 40])
    sensors = np.column_stack([rng.uniform(0, 4, (5, 2)), np.full(5, SENSOR_Z)])
    for target in (0, 1):
        ranges = [np.linalg.norm(sensors[i] - states[s][3 * target:3 * target + 3]) for i, s in enumerate(steps)]
        carried = carried_sensors(motion, target, sensors, steps, 40)
        now = states[40][3 * target:3 * target + 3]
        assert np.linalg.norm(carried - now, axis=1) == pytest.approx(ranges, abs=1e-9)


def static_motion(n_targets: int) -> TargetMotion:
    return TargetMotion([LinearPath((1, 1, 1), (1, 1, 1), 0.0)] * n_targets, dt=1.0, noise_std=0.01)


def records_of(truth: np.ndarray, positions_by_step: list[np.ndarray], rng) -> list[RangeMeasurement]:
    out = []
    for step, sensors in enumerate(positions_by_step):
        for robot, sensor in enumerate(sensors):
            for target, point in enumerate(truth):
                distance = float(np.linalg.norm(sensor - point))
                out.append(RangeMeasurement(step, robot, tuple(sensor), target,
                                            max(distance + rng.normal(0, range_sigma(distance)), 0.0)))
    return out


def neutral(n_targets: int) -> FilterState:
    return FilterState(0, np.tile([5.0, 5.0, 1.25], n_targets), 12.5 * np.eye(3 * n_targets))


def test_a_belief_with_an_initialiser_fixes_each_target_from_its_readings_in_any_order():
    """Three robots drive apart from one spot: their first readings do not fix the targets (kept
    out of the EKF, the prior's block predicted), later ones do; from then on the EKF fuses.
    Records delivered in another order and late give the same estimates, bit for bit."""
    truth = np.array([[1.5, 7.5, 1.3], [8.0, 2.0, 0.9]])
    rng = np.random.default_rng(7)
    headings = np.array([[-1.0, 0.0], [0.5, 0.87], [0.5, -0.87]])
    path = [np.column_stack([5 + 0.1 * k * headings, np.full(3, SENSOR_Z)]) for k in range(40)]
    records = records_of(truth, path, rng)
    initialiser = ReadingsInitialiser(height_range=(0.0, 2.5))
    belief = Belief(static_motion(2), neutral(2), SENSOR_Z, initialiser)
    belief.receive(records)
    assert belief.fixed_targets(0) == frozenset()
    assert belief.estimate(0).mean == pytest.approx(neutral(2).mean)
    assert belief.fixed_targets(39) == frozenset({0, 1})
    first_fix = min(k for k in range(40) if belief.fixed_targets(k))
    assert 0 < first_fix
    assert np.linalg.norm(belief.estimate(39).mean.reshape(2, 3) - truth, axis=1).max() < 0.3

    shuffled = list(records)
    np.random.default_rng(1).shuffle(shuffled)
    late = Belief(static_motion(2), neutral(2), SENSOR_Z, initialiser)
    late.receive(shuffled[: len(shuffled) // 2])
    late.estimate(39)  # filtered once on half the records, then refiltered with the rest
    late.receive(shuffled[len(shuffled) // 2:])
    for k in (0, first_fix, 39):
        assert np.array_equal(late.estimate(k).mean, belief.estimate(k).mean)
        assert np.array_equal(late.estimate(k).covariance, belief.estimate(k).covariance)
        assert late.fixed_targets(k) == belief.fixed_targets(k)


def test_a_belief_without_an_initialiser_fuses_every_reading_from_the_prior():
    truth = np.array([[1.5, 7.5, 1.3]])
    records = records_of(truth, [np.array([[5.0, 5.0, SENSOR_Z]])], np.random.default_rng(0))
    belief = Belief(static_motion(1), neutral(1), SENSOR_Z)
    belief.receive(records)
    assert belief.fixed_targets(0) == frozenset({0})
    assert not np.array_equal(belief.estimate(0).mean, neutral(1).mean)


def test_forgetting_keeps_which_targets_are_fixed():
    truth = np.array([[1.5, 7.5, 1.3]])
    headings = np.array([[-1.0, 0.0], [0.5, 0.87], [0.5, -0.87]])
    path = [np.column_stack([5 + 0.1 * k * headings, np.full(3, SENSOR_Z)]) for k in range(40)]
    records = records_of(truth, path, np.random.default_rng(2))
    belief = Belief(static_motion(1), neutral(1), SENSOR_Z, ReadingsInitialiser(height_range=(0.0, 2.5)))
    belief.receive(records)
    reference = belief.estimate(39)
    fixed = belief.fixed_targets(30)
    belief.forget_before(31)
    assert belief.fixed_targets(31) >= fixed
    assert np.array_equal(belief.estimate(39).mean, reference.mean)
