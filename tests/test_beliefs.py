"""Team / robot / global beliefs (estimation/beliefs.py) and the estimation
metrics (estimation/metrics.py) of Khodayi-mehr et al. 2019: out-of-order fusion, checkpointed
refiltering, Algorithm 5's exchanges, t*(t), e_i(t) and packet delays
against the schedule replay of Proposition III.2."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.intermittent.schedules import build_schedule, propagation_epochs
from controllers.intermittent.teams import PAPER_DENSE_TEAMS, PAPER_RING_TEAMS, Teams
from estimation.beliefs import Belief, NetworkBeliefs, RangeMeasurement, readings_from_records
from estimation.ekf import PAPER_INITIAL_TARGET_POSITIONS, TargetEKF, paper_prior
from estimation.metrics import (
    delay_report,
    local_error,
    localization_error,
    localization_error_series,
    max_eigenvalue,
    packet_delays,
    lag_series,
    team_lag,
    time_average,
    uncertainty_series,
)
from estimation.range_model import range_sigma
from estimation.target_motion import CircularPath, LinearPath, TargetMotion

SENSING_RANGE_M = 5.0
ROBOT_STEP_M = 0.1  # Khodayi-mehr et al. 2019: ||u_ij|| <= 0.1 m per step
SENSOR_HEIGHT_M = 0.1


def paper_motion() -> TargetMotion:
    paths = []
    for a, start in enumerate(PAPER_INITIAL_TARGET_POSITIONS):
        if a % 2 == 0:
            paths.append(LinearPath(tuple(start), tuple(start + (1.0, 0.5, 0.0)), 0.05))
        else:
            paths.append(CircularPath(tuple(start - (0.5, 0.0, 0.0)), 0.5, 0.05))
    return TargetMotion(paths, dt=1.0, noise_std=0.01)


def read_targets(step, robot, position, x, rng):
    """Range readings of every target within 5 m of a robot (no obstacles)."""
    sensor = np.array([position[0], position[1], SENSOR_HEIGHT_M])
    distances = np.linalg.norm(x.reshape(-1, 3) - sensor, axis=1)
    return [
        RangeMeasurement(step, robot, tuple(sensor), a, d + rng.normal() * float(range_sigma(d)))
        for a, d in enumerate(distances)
        if d < SENSING_RANGE_M
    ]


def random_records(rng, motion, robots=(1, 2, 3), steps=30):
    """Readings of ``robots`` random-walking over 10 x 10 m for ``steps`` steps."""
    x = motion.initial_state()
    positions = {r: rng.uniform(0, 10, 2) for r in robots}
    records = []
    for k in range(steps):
        for r in robots:
            positions[r] = np.clip(positions[r] + rng.uniform(-ROBOT_STEP_M, ROBOT_STEP_M, 2), 0, 10)
            records += read_targets(k, r, positions[r], x, rng)
        x = motion.step(x, k, rng)
    return records


class NetworkRun:
    """Epoch-level run of Algorithm 5: every robot random-walks and measures
    for ``steps_per_epoch`` steps, then the teams of the epoch meet. Robots
    stop measuring after ``measuring_epochs`` (so logs can settle)."""

    def __init__(self, team_lists, rng, steps_per_epoch=4):
        self.teams = Teams(team_lists)
        self.schedule = build_schedule(self.teams)
        self.motion = paper_motion()
        self.network = NetworkBeliefs(self.teams, self.motion, paper_prior())
        self.rng = rng
        self.steps_per_epoch = steps_per_epoch
        self.x = self.motion.initial_state()
        self.truth = [self.x]
        self.positions = {r: rng.uniform(0, 10, 2) for r in self.teams.robots}
        self.step = 0  # next step to be measured
        self.epoch = 0

    def advance_epoch(self, measure=True, after_meeting=None):
        self.epoch += 1
        for _ in range(self.steps_per_epoch):
            if measure:
                for robot in self.teams.robots:
                    move = self.rng.uniform(-ROBOT_STEP_M, ROBOT_STEP_M, 2)
                    self.positions[robot] = np.clip(self.positions[robot] + move, 0, 10)
                    readings = read_targets(self.step, robot, self.positions[robot], self.x, self.rng)
                    self.network.collect(robot, readings)
            self.x = self.motion.step(self.x, self.step, self.rng)
            self.truth.append(self.x)
            self.step += 1
        for team in self.schedule.teams_meeting_at(self.epoch):
            report = self.network.meet(team, self.epoch)
            if after_meeting is not None:
                after_meeting(report)

    @property
    def last_measured_step(self):
        return self.step - 1


# ------------------------------------------------------------ Belief


def test_out_of_order_arrival_ends_identical_to_in_order():
    rng = np.random.default_rng(5)
    motion = paper_motion()
    records = random_records(rng, motion)
    in_order = Belief(motion, paper_prior())
    for k in range(30):
        in_order.receive(r for r in records if r.step == k)
        in_order.estimate(k)

    shuffled = Belief(motion, paper_prior())
    order = rng.permutation(len(records))
    for chunk in np.array_split(order, 12):
        shuffled.receive(records[i] for i in chunk)
        shuffled.estimate(int(rng.integers(0, 30)))  # checkpoints that later go stale
    for k in range(30):
        a, b = in_order.estimate(k), shuffled.estimate(k)
        np.testing.assert_allclose(b.mean, a.mean, rtol=0, atol=1e-9)
        np.testing.assert_allclose(b.covariance, a.covariance, rtol=0, atol=1e-9)
    assert shuffled.filtered_steps > 30  # it did refilter along the way


def test_belief_equals_plain_ekf_over_the_same_records():
    rng = np.random.default_rng(6)
    motion = paper_motion()
    records = random_records(rng, motion, steps=12)
    belief = Belief(motion, paper_prior())
    belief.receive(reversed(records))
    ekf = TargetEKF(motion, paper_prior())
    for k in range(12):
        if k:
            ekf.predict()
        state = ekf.update(readings_from_records(r for r in records if r.step == k))
        np.testing.assert_allclose(belief.estimate(k).mean, state.mean, rtol=0, atol=1e-12)
        np.testing.assert_allclose(belief.estimate(k).covariance, state.covariance, rtol=0, atol=1e-12)


def test_late_packet_refilters_from_its_step_not_from_zero():
    rng = np.random.default_rng(8)
    motion = paper_motion()
    records = random_records(rng, motion, steps=41)
    late = [r for r in records if r.step == 35 and r.robot == 2]
    belief = Belief(motion, paper_prior())
    belief.receive(r for r in records if r not in late)
    before = belief.estimate(40)
    assert belief.filtered_steps == 41
    assert belief.receive(late) == len(late) > 0
    after = belief.estimate(40)
    assert belief.filtered_steps == 41 + 6  # steps 35..40 only
    assert not np.array_equal(before.mean, after.mean)
    np.testing.assert_array_equal(belief.estimate(34).mean, estimate_without(motion, records, late, 34))


def estimate_without(motion, records, late, step):
    belief = Belief(motion, paper_prior())
    belief.receive(r for r in records if r not in late)
    return belief.estimate(step).mean


def test_duplicates_are_ignored_and_conflicts_rejected():
    motion = paper_motion()
    record = RangeMeasurement(3, 1, (1.0, 2.0, 0.1), 0, 1.5)
    belief = Belief(motion, paper_prior())
    assert belief.receive([record, record]) == 1
    assert belief.receive([RangeMeasurement(3, 1, (1.0, 2.0, 0.1), 0, 1.5)]) == 0
    with pytest.raises(ValueError, match=r"\(3, 1, 0\)"):
        belief.receive([RangeMeasurement(3, 1, (1.0, 2.0, 0.1), 0, 1.6)])
    with pytest.raises(ValueError, match="target 8 out of range"):
        belief.receive([RangeMeasurement(3, 1, (1.0, 2.0, 0.1), 8, 1.6)])


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(step=-1), "step"),
        (dict(robot=-2), "robot"),
        (dict(target=-1), "target"),
        (dict(measured_range=-0.5), "measured_range"),
        (dict(measured_range=float("nan")), "measured_range"),
        (dict(sensor_position=(1.0, 2.0)), "sensor_position"),
    ],
)
def test_measurement_validation(kwargs, field):
    fields = dict(step=0, robot=1, sensor_position=(0.0, 0.0, 0.1), target=0, measured_range=1.0)
    fields.update(kwargs)
    with pytest.raises(ValueError, match=field):
        RangeMeasurement(**fields)


def test_forget_before_keeps_estimates_and_rejects_older_records():
    rng = np.random.default_rng(9)
    motion = paper_motion()
    records = random_records(rng, motion, steps=20)
    reference = Belief(motion, paper_prior())
    reference.receive(records)
    belief = Belief(motion, paper_prior())
    belief.receive(r for r in records if r.step < 15)
    belief.forget_before(10)
    assert belief.earliest_step == 10
    belief.receive(r for r in records if r.step >= 15)
    np.testing.assert_array_equal(belief.estimate(19).mean, reference.estimate(19).mean)
    with pytest.raises(ValueError, match="before this belief's earliest step 10"):
        belief.receive([RangeMeasurement(9, 7, (0.0, 0.0, 0.1), 0, 1.0)])
    with pytest.raises(ValueError, match="step"):
        belief.estimate(9)


# ------------------------------------------------------ NetworkBeliefs


@pytest.mark.parametrize("team_lists", [PAPER_DENSE_TEAMS, PAPER_RING_TEAMS], ids=["G2", "G1"])
def test_after_all_logs_are_exchanged_every_belief_equals_global(team_lists):
    run = NetworkRun(team_lists, np.random.default_rng(10))
    for _ in range(6):
        run.advance_epoch(measure=True)
    # No new readings: within D epochs every packet reaches every team; one
    # more period lets every robot attend a meeting after that.
    for _ in range(run.schedule.delay_bound + run.schedule.period):
        run.advance_epoch(measure=False)
    final = run.step - 1
    reference = run.network.global_estimate(final)
    for team in range(run.teams.n_teams):
        estimate = run.network.team_estimate(team, final)
        np.testing.assert_allclose(estimate.mean, reference.mean, rtol=0, atol=1e-9)
        np.testing.assert_allclose(estimate.covariance, reference.covariance, rtol=0, atol=1e-9)
        assert run.network.agreement_horizon(team, final) == final
    for robot, belief in run.network.robot_beliefs.items():
        np.testing.assert_allclose(belief.estimate(final).mean, reference.mean, rtol=0, atol=1e-9)
    report = delay_report(run.network, run.schedule.delay_bound)
    assert report.pending == 0 and report.within_bound


def test_agreement_horizon_is_exact_and_estimates_match_up_to_it():
    """t*(t): record sets equal at every step <= t*, and different at t* + 1;
    the team's filtered estimates equal x_g there and differ right after."""
    run = NetworkRun(PAPER_DENSE_TEAMS, np.random.default_rng(12), steps_per_epoch=3)
    network = run.network
    checked = []

    def check(report):
        t = run.last_measured_step
        team = report.team
        horizon = network.agreement_horizon(team, t)
        team_belief = network.team_beliefs[team]
        for s in range(horizon + 1):
            assert set(team_belief.keys_at(s)) == set(network.global_belief.keys_at(s))
        if horizon < t:
            assert set(team_belief.keys_at(horizon + 1)) != set(network.global_belief.keys_at(horizon + 1))
            assert not np.array_equal(
                team_belief.estimate(horizon + 1).mean, network.global_estimate(horizon + 1).mean
            )
        if horizon >= 0:
            np.testing.assert_array_equal(
                team_belief.mean_trajectory(0, horizon + 1),
                network.global_belief.mean_trajectory(0, horizon + 1),
            )
        lag = team_lag(network, team, t)
        assert lag.agreement_step == horizon
        if horizon < t:
            window = slice(horizon + 1, t + 1)
            expected = np.mean(
                np.linalg.norm(
                    network.global_belief.mean_trajectory(window.start, window.stop)
                    - team_belief.mean_trajectory(window.start, window.stop),
                    axis=1,
                )
            )
            assert lag.local_error == pytest.approx(expected, rel=1e-12)
            assert lag.local_error > 0
        else:
            assert lag.local_error == 0.0
        checked.append(horizon < t)
        lags.setdefault(team, []).append(lag)

    lags = {}
    for _ in range(9):
        run.advance_epoch(measure=True, after_meeting=check)
    assert any(checked)  # some meetings saw a lag (delays exist)
    for team, recorded in lags.items():
        steps, agreement, errors = lag_series(recorded)
        # Teams only gain records and x_g gains them at their own step, so
        # t*(t) never decreases, and never passes t.
        assert np.all(np.diff(agreement) >= 0) and np.all(agreement <= steps)
        assert np.all((errors > 0) == (agreement < steps))


def test_packet_deliveries_match_the_schedule_replay():
    run = NetworkRun(PAPER_DENSE_TEAMS, np.random.default_rng(13), steps_per_epoch=2)
    for _ in range(7):
        run.advance_epoch(measure=True)
    for _ in range(8):
        run.advance_epoch(measure=False)
    deliveries = run.network.deliveries
    assert len(deliveries) > 8
    for packet, reached in deliveries.items():
        replay = propagation_epochs(run.schedule, packet.robot, packet.epoch)
        assert reached == {t: e for t, e in replay.items() if e <= run.epoch}
    delays, pending = packet_delays(deliveries, run.teams.n_teams)
    assert pending == 0
    assert delays.max() == 5 <= run.schedule.delay_bound  # G2: worst case 5, bound 6


def test_meetings_must_follow_increasing_epochs():
    run = NetworkRun(PAPER_RING_TEAMS, np.random.default_rng(14))
    run.advance_epoch()
    with pytest.raises(ValueError, match="robot 12 already met at epoch 1"):
        run.network.meet(1, 1)
    with pytest.raises(ValueError, match="cannot collect readings of robot"):
        run.network.collect(12, [RangeMeasurement(0, 23, (0.0, 0.0, 0.1), 0, 1.0)])
    with pytest.raises(ValueError, match="team: 9"):
        run.network.meet(9, 5)


# ------------------------------------------------------------- metrics


def test_time_average_is_eq13_over_t1_to_tend():
    series = np.array([100.0, 1.0, 2.0, 3.0, 6.0])  # t = 0 (left out), 1..4
    average = time_average(series)
    assert average.mean == pytest.approx(3.0)
    assert average.std == pytest.approx(np.sqrt((4 + 1 + 0 + 9) / 4))
    assert average.n_steps == 4
    with pytest.raises(ValueError, match="series_from_t0"):
        time_average(np.array([1.0]))


def test_error_and_uncertainty_series_against_direct_formulas():
    rng = np.random.default_rng(15)
    estimates, truths = rng.normal(size=(5, 24)), rng.normal(size=(5, 24))
    errors = localization_error_series(estimates, truths)
    assert errors[2] == pytest.approx(localization_error(estimates[2], truths[2]))
    assert errors[2] == pytest.approx(np.sqrt(np.sum((estimates[2] - truths[2]) ** 2)))
    a = rng.normal(size=(5, 24, 24))
    covariances = a @ a.transpose(0, 2, 1)
    lam = uncertainty_series(covariances)
    assert lam[3] == pytest.approx(max_eigenvalue(covariances[3]))
    assert lam[3] == pytest.approx(np.max(np.abs(np.linalg.eigvals(covariances[3]))))
    assert max_eigenvalue(np.diag([0.25, 0.1, 0.7])) == pytest.approx(0.7)
    with pytest.raises(ValueError, match="shapes differ"):
        localization_error_series(estimates, truths[:3])
    assert local_error(np.zeros((0, 24)), np.zeros((0, 24))) == 0.0
    assert local_error(np.zeros((2, 3)), np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 1.0]])) == pytest.approx(3.0)


def test_a_meeting_without_a_member_pools_only_the_members_present():
    teams = Teams([(0, 1, 2), (0, 3), (1, 2, 3)])
    network = NetworkBeliefs(teams, paper_motion(), paper_prior())
    records = random_records(np.random.default_rng(3), paper_motion(), robots=(0, 1, 2), steps=3)
    for robot in (0, 1, 2):
        network.collect(robot, [r for r in records if r.robot == robot])
    network.meet(0, 1, present=(0, 1))
    pooled = {r.key for r in network.team_beliefs[0].records_since(0)}
    assert pooled == {r.key for r in records if r.robot in (0, 1)}
    assert not any(r.robot == 2 for r in network.robot_beliefs[0].records_since(0))
    network.meet(0, 2)  # robot 2 back: its records reach the team at the next meeting
    assert {r.key for r in network.team_beliefs[0].records_since(0)} == {r.key for r in records}
