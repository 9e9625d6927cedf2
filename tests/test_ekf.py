"""EKF of Khodayi-mehr et al. 2019 (estimation/ekf.py): Jacobians against finite differences,
prediction and update against independent formulas, paper constants, and
filter consistency (NEES) over a seeded pure-numpy simulation."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import chi2

from estimation.ekf import (
    PAPER_INITIAL_ESTIMATE,
    PAPER_INITIAL_TARGET_POSITIONS,
    FilterState,
    RangeReadings,
    TargetEKF,
    measurement_noise,
    paper_prior,
    predicted_ranges,
    range_jacobian_batch,
)
from estimation.range_model import covariance_predict, covariance_update, range_jacobian, range_sigma
from estimation.target_motion import CircularPath, LinearPath, TargetMotion

# Nine ground sensors on a 3 x 3 grid of the 10 x 10 m floor, 0.1 m up.
GRID_SENSORS = np.array([(x, y, 0.1) for x in (2.0, 5.0, 8.0) for y in (2.0, 5.0, 8.0)])
SENSING_RANGE_M = 5.0


def paper_motion(noise_std: float = 0.01) -> TargetMotion:
    """Eight targets starting at the paper's x0: even ones on 1.1 m segments,
    odd ones on 0.5 m circles, 0.05 m/s, 1 s steps."""
    paths = []
    for a, start in enumerate(PAPER_INITIAL_TARGET_POSITIONS):
        if a % 2 == 0:
            paths.append(LinearPath(tuple(start), tuple(start + (1.0, 0.5, 0.0)), 0.05))
        else:
            paths.append(CircularPath(tuple(start - (0.5, 0.0, 0.0)), 0.5, 0.05))
    return TargetMotion(paths, dt=1.0, noise_std=noise_std)


def simulate_readings(x: np.ndarray, rng: np.random.Generator) -> RangeReadings:
    """Every grid sensor reads every target within 5 m (no obstacles), with
    the eq. (12) noise at the true distance."""
    distances = np.linalg.norm(GRID_SENSORS[:, None, :] - x.reshape(-1, 3)[None], axis=-1)
    sensor, target = np.nonzero(distances < SENSING_RANGE_M)
    true = distances[sensor, target]
    return RangeReadings(GRID_SENSORS[sensor], target, true + rng.normal(size=true.size) * range_sigma(true))


def numerical_jacobian(x, sensors, targets, h=1e-6):
    columns = []
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = h
        columns.append((predicted_ranges(x + dx, sensors, targets) - predicted_ranges(x - dx, sensors, targets)) / (2 * h))
    return np.stack(columns, axis=1)




@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_range_jacobian_matches_central_differences(seed):
    rng = np.random.default_rng(seed)
    n_targets = int(rng.integers(1, 5))
    x = rng.uniform(-5, 5, 3 * n_targets)
    sensors = rng.uniform(-5, 5, (6, 3))
    targets = rng.integers(0, n_targets, 6)
    # Keep sensors away from targets, where the range is not differentiable.
    for r in range(6):
        if np.linalg.norm(x.reshape(-1, 3)[targets[r]] - sensors[r]) < 0.1:
            sensors[r] += 1.0
    analytic = range_jacobian_batch(x, sensors, targets)
    np.testing.assert_allclose(analytic, numerical_jacobian(x, sensors, targets), atol=1e-7)
    # Same rows as the single-reading Jacobian of range_model.
    for r in range(6):
        np.testing.assert_allclose(analytic[r], range_jacobian(x, sensors[r], targets[r]), atol=1e-12)


def test_measurement_noise_is_eq12_at_predicted_range():
    x = np.array([0.0, 0.0, 1.0, 4.0, 0.0, 1.0])
    sensors = np.array([[0.0, 0.5, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    targets = np.array([0, 1, 0])
    predicted = predicted_ranges(x, sensors, targets)
    np.testing.assert_allclose(predicted, [0.5, 4.0, 0.0])
    # sigma = 0.01 below 1 m, flat 0.1 between 3 and 5 m.
    np.testing.assert_allclose(measurement_noise(predicted), np.diag([1e-4, 1e-2, 1e-4]))
    # The middle branch: 0.045 * 2 - 0.035 = 0.055 m at 2 m.
    np.testing.assert_allclose(measurement_noise(np.array([2.0])), [[0.055**2]])


def test_paper_initialisation_constants():
    assert PAPER_INITIAL_TARGET_POSITIONS.shape == (8, 3)
    np.testing.assert_array_equal(PAPER_INITIAL_TARGET_POSITIONS[3], (9.2, 9.0, 1.0))
    np.testing.assert_array_equal(PAPER_INITIAL_ESTIMATE[6], (2.5, 7.0, 1.0))
    prior = paper_prior()
    assert prior.step == 0 and prior.mean.shape == (24,)
    np.testing.assert_array_equal(prior.covariance, 0.25 * np.eye(24))
    with pytest.raises(ValueError):
        prior.mean[0] = 3.0  # checkpoints are immutable


def test_predict_is_eq8_with_target_motion():
    motion = paper_motion()
    rng = np.random.default_rng(3)
    a = rng.normal(size=(24, 24))
    start = FilterState(5, rng.normal(size=24), a @ a.T + np.eye(24))
    ekf = TargetEKF(motion, start)
    predicted = ekf.predict()
    assert predicted.step == 6
    np.testing.assert_allclose(predicted.mean, motion.predict(start.mean, 5), atol=1e-12)
    np.testing.assert_allclose(
        predicted.covariance,
        covariance_predict(start.covariance, motion.transition, motion.process_noise),
        atol=1e-12,
    )


def test_batch_update_matches_textbook_and_information_form():
    motion = paper_motion()
    prior = paper_prior()
    rng = np.random.default_rng(7)
    readings = simulate_readings(PAPER_INITIAL_TARGET_POSITIONS.reshape(-1), rng)
    posterior = TargetEKF(motion, prior).update(readings)

    # Eqs. (9)-(10) written out with numpy.
    h = range_jacobian_batch(prior.mean, readings.sensor_positions, readings.target_indices)
    hx = predicted_ranges(prior.mean, readings.sensor_positions, readings.target_indices)
    r = np.diag(range_sigma(hx) ** 2)
    s = h @ prior.covariance @ h.T + r
    gain = prior.covariance @ h.T @ np.linalg.inv(s)
    np.testing.assert_allclose(posterior.mean, prior.mean + gain @ (readings.ranges - hx), atol=1e-9)
    np.testing.assert_allclose(posterior.covariance, (np.eye(24) - gain @ h) @ prior.covariance, atol=1e-9)

    # The planner's covariance-only update (rank-one information form) agrees
    # when every visible (sensor, target) pair is read once.
    visible = np.zeros((len(GRID_SENSORS), 8), dtype=bool)
    sensor_rows = [int(np.flatnonzero((GRID_SENSORS == p).all(axis=1))[0]) for p in readings.sensor_positions]
    visible[sensor_rows, readings.target_indices] = True
    reference = covariance_update(prior.covariance, prior.mean, GRID_SENSORS, visible)
    np.testing.assert_allclose(posterior.covariance, reference, atol=1e-9)


def test_empty_batch_leaves_the_belief_unchanged():
    ekf = TargetEKF(paper_motion(), paper_prior())
    state = ekf.update(RangeReadings.empty())
    np.testing.assert_array_equal(state.mean, paper_prior().mean)
    np.testing.assert_array_equal(state.covariance, paper_prior().covariance)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(sensor_positions=np.zeros((2, 3)), target_indices=[0], ranges=[1.0, 1.0]), "lengths differ"),
        (dict(sensor_positions=np.zeros((1, 3)), target_indices=[-1], ranges=[1.0]), "target_indices"),
        (dict(sensor_positions=np.zeros((1, 3)), target_indices=[0.5], ranges=[1.0]), "target_indices"),
        (dict(sensor_positions=np.zeros((1, 3)), target_indices=[0], ranges=[-1.0]), "ranges"),
        (dict(sensor_positions=np.full((1, 3), np.nan), target_indices=[0], ranges=[1.0]), "finite"),
    ],
)
def test_readings_validation(kwargs, field):
    with pytest.raises(ValueError, match=field):
        RangeReadings(**kwargs)


def test_state_and_filter_validation():
    with pytest.raises(ValueError, match="covariance"):
        FilterState(0, np.zeros(6), np.eye(5))
    with pytest.raises(ValueError, match="step"):
        FilterState(-1, np.zeros(3), np.eye(3))
    with pytest.raises(ValueError, match="initial"):
        TargetEKF(paper_motion(), FilterState(0, np.zeros(3), np.eye(3)))
    ekf = TargetEKF(paper_motion(), paper_prior())
    with pytest.raises(ValueError, match="target index 8"):
        ekf.update(RangeReadings(np.zeros((1, 3)), [8], [1.0]))


def test_filter_is_consistent_nees_within_chi2_bounds():
    """Average NEES over independent runs follows chi2(3M)/runs at every step.

    The truth is drawn from the filter's prior. The prior variance is 0.01 m^2
    rather than the paper's 0.25 m^2: with 0.5 m initial spread a range-only
    EKF linearises badly on its first updates and is known to turn
    overconfident (NEES ~ 5x), which would test EKF linearisation, not this
    implementation. test_paper_initialisation_converges covers 0.25 m^2.
    """
    motion = paper_motion()
    prior = FilterState(0, PAPER_INITIAL_ESTIMATE.reshape(-1), 0.01 * np.eye(24))
    rng = np.random.default_rng(2024)
    runs, steps, dim = 30, 40, 24
    nees = np.zeros((runs, steps))
    for run in range(runs):
        x = rng.multivariate_normal(prior.mean, prior.covariance)
        ekf = TargetEKF(motion, prior)
        for k in range(steps):
            state = ekf.update(simulate_readings(x, rng))
            error = x - state.mean
            nees[run, k] = error @ np.linalg.solve(state.covariance, error)
            ekf.predict()
            x = motion.step(x, k, rng)
    average = nees.mean(axis=0)
    low, high = chi2.ppf([0.005, 0.995], runs * dim) / runs
    inside = np.mean((average > low) & (average < high))
    assert inside >= 0.9, (inside, average)
    assert low < average.mean() < high


def test_paper_initialisation_converges():
    """From x^0 and C(0) = 0.25 I the error to the paper's x0 shrinks from
    ~2.7 m to a fraction of a metre within 60 steps."""
    motion = paper_motion()
    rng = np.random.default_rng(11)
    x = motion.initial_state()
    np.testing.assert_array_equal(x, PAPER_INITIAL_TARGET_POSITIONS.reshape(-1))
    ekf = TargetEKF(motion, paper_prior())
    initial_error = np.linalg.norm(paper_prior().mean - x)
    for k in range(60):
        state = ekf.update(simulate_readings(x, rng))
        ekf.predict()
        x = motion.step(x, k, rng)
    state = ekf.state
    final_error = np.linalg.norm(state.mean - x)
    assert initial_error > 2.5
    assert final_error < 0.4
    assert np.linalg.eigvalsh(state.covariance)[-1] < 0.05
