"""Pure pieces of the intermittent-task strategies: geodesics, timed paths, body
separation, team connectivity, parameters, the e_g observer and the
comparison's bookkeeping. No simulation."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from controllers.baselines.geodesic import GeodesicPlanner, timed_waypoints
from controllers.intermittent.params import IntermittentParams
from controllers.intermittent.planner import RobotPath
from controllers.intermittent.runtime import TimedPath, separation_offsets
from controllers.intermittent.strategy import Segment, team_connected
from sim.geometry import Boxes, segments_free

Z = 0.05
BOUNDS = np.array([[0.0, 0.0], [6.0, 6.0]])
# A wall from y = 0 to y = 4 at x = 3: going from (1, 1) to (5, 1) must round its end at (3, 4).
WALL = Boxes.axis_aligned([[3.0, 2.0, 1.0]], [[0.05, 2.0, 1.0]])


@pytest.fixture(scope="module")
def geodesic():
    return GeodesicPlanner(WALL, BOUNDS, Z, margin=0.1)


def test_geodesic_goes_around_the_wall_and_is_nearly_shortest(geodesic):
    start, goal = np.array([1.0, 1.0]), np.array([5.0, 1.0])
    path = geodesic.path(start, goal)
    assert path is not None and np.allclose(path[0], start) and np.allclose(path[-1], goal)
    a = np.c_[path[:-1], np.full(len(path) - 1, Z)]
    b = np.c_[path[1:], np.full(len(path) - 1, Z)]
    assert segments_free(WALL, a, b, 0.1).all()
    # True geodesic: via the wall's end (3, 4) padded by the margin: about 2 * sqrt(2^2 + 3.15^2).
    shortest = 2 * np.hypot(2.0, 3.15)
    assert shortest - 0.05 <= geodesic.length(path) <= shortest * 1.03
    assert len(path) <= 5  # string pulling keeps only the turns


def test_geodesic_straight_when_free_and_none_when_blocked(geodesic):
    straight = geodesic.path(np.array([4.0, 1.0]), np.array([5.5, 5.0]))
    assert straight.shape == (2, 2)
    assert geodesic.path(np.array([3.0, 2.0]), np.array([5.0, 1.0])) is None  # start inside the wall
    assert not geodesic.is_free(np.array([[0.05, 3.0]]))[0]  # within the margin of the bounds


def test_timed_waypoints_respect_the_speed_limit():
    waypoints = np.array([[0.0, 0.0], [0.25, 0.0], [0.25, 0.0], [0.25, 1.0]])
    times, positions = timed_waypoints(waypoints, start_step=7, u_max=0.1)
    assert times[0] == 7 and np.all(np.diff(times) > 0)
    assert len(positions) == 3  # the repeated point is dropped
    speed = np.linalg.norm(np.diff(positions, axis=0), axis=1) / np.diff(times)
    assert np.all(speed <= 0.1 + 1e-12)
    assert times[-1] - times[0] == 3 + 10


def test_timed_path_reference_position_and_velocity():
    path = RobotPath(np.array([2, 4, 9]), np.array([[0.0, 0.0], [0.2, 0.0], [0.2, 0.5]]))
    timed = TimedPath(path, step_s=1.0, offset_s=1.5)
    p, v = timed.reference(0.0)
    assert np.allclose(p, [0, 0]) and np.allclose(v, 0)  # before the start: wait at the first point
    p, v = timed.reference(4.5)  # tau = 3
    assert np.allclose(p, [0.1, 0.0]) and np.allclose(v, [0.1, 0.0])
    p, v = timed.reference(8.5)  # tau = 7
    assert np.allclose(p, [0.2, 0.3]) and np.allclose(v, [0.0, 0.1])
    assert not timed.finished(10.0) and timed.finished(10.5)
    p, v = timed.reference(20.0)
    assert np.allclose(p, [0.2, 0.5]) and np.allclose(v, 0)
    assert np.allclose(timed.remaining(4.5), [[0.1, 0.0], [0.2, 0.0], [0.2, 0.5]])


def test_timed_path_reference_is_the_paths_interpolation_bit_for_bit():
    # reference() interpolates in plain floats; trajectories stay identical only if it equals np.interp exactly.
    rng = np.random.default_rng(4)
    for _ in range(200):
        n = int(rng.integers(2, 6))
        path = RobotPath(np.cumsum(rng.integers(1, 20, n)), rng.uniform(-5.0, 5.0, (n, 2)))
        timed = TimedPath(path, step_s=0.5, offset_s=float(rng.uniform(0.0, 3.0)))
        for t in np.concatenate([rng.uniform(0.0, 0.5 * path.end_time + 3.0, 8), 0.5 * path.times + timed.offset_s]):
            tau = timed.tau(t)
            if path.start_time < tau < path.end_time:
                assert np.array_equal(timed.reference(t)[0], path.position_at(tau))


def test_segment_arrival_step_ignores_the_padded_wait():
    path = RobotPath(np.array([0, 5, 9]), np.array([[0.0, 0.0], [0.5, 0.0], [0.5, 0.0]]))
    segment = Segment.of(meeting=None, path=path, step_s=1.0)
    segment.started = True
    assert segment.arrive_step == 5
    assert not segment.at_end(4.9) and segment.at_end(5.0)


def test_separation_is_zero_apart_and_pushes_close_bodies_apart():
    far = np.array([[0.0, 0.0], [0.5, 0.0]])
    assert np.all(separation_offsets(far) == 0)
    close = np.array([[0.0, 0.0], [0.08, 0.0]])
    offsets = separation_offsets(close)
    assert offsets[0, 0] < 0 < offsets[1, 0]  # away from each other
    assert np.allclose(offsets[0], -offsets[1])


def test_separation_head_on_both_dodge_to_their_right():
    bodies = np.array([[0.0, 0.0], [0.09, 0.0]])
    velocity = np.array([[0.1, 0.0], [-0.1, 0.0]])  # driving at each other along x
    offsets = separation_offsets(bodies, velocity)
    assert offsets[0, 1] < 0  # robot 0 heads +x: its right is -y
    assert offsets[1, 1] > 0  # robot 1 heads -x: its right is +y
    # Side by side on parallel courses: no dodge, only apart.
    side = separation_offsets(np.array([[0.0, 0.0], [0.0, 0.09]]), np.array([[0.1, 0.0], [0.1, 0.0]]))
    assert np.allclose(side[:, 0], 0) and side[0, 1] < 0 < side[1, 1]


def test_team_connected_uses_only_links_inside_the_team():
    adjacency = np.zeros((4, 4), dtype=bool)
    for i, j in ((0, 2), (2, 1)):
        adjacency[i, j] = adjacency[j, i] = True
    assert team_connected(adjacency, (0, 2, 1))
    assert not team_connected(adjacency, (0, 1))  # connected only through robot 2, not a member
    assert team_connected(adjacency, (3,))


def test_params_validation_messages():
    with pytest.raises(ValueError, match=r"^teams: robot 2 belongs to 1 team"):
        IntermittentParams(teams=((0, 1), (0, 2), (1, 3)))
    with pytest.raises(ValueError, match=r"^n_sample: must be an integer >= 1"):
        IntermittentParams(n_sample=0)
    with pytest.raises(ValueError, match=r"^delta_m2: must be positive"):
        IntermittentParams(delta_m2=0.0)
    params = IntermittentParams(teams=((0, 1), (0, 2), (2, 3), (1, 3)))
    assert params.team_structure(4).n_teams == 4
    with pytest.raises(ValueError, match=r"^teams: robot\(s\) \[4\] belong to no team"):
        params.team_structure(5)


def test_estimation_observer_measures_e_g_against_the_truth():
    from sim.estimation_observer import EstimationMetrics
    from sim.observers import EstimationError, Frame, estimation_error
    from sim.types import TargetEstimate

    observer = EstimationMetrics()
    truth = np.array([[1.0, 2.0, 1.0], [3.0, 4.0, 1.0]])
    for step, shift in ((0, 5.0), (1, 0.3), (2, 0.4)):
        estimate = TargetEstimate(step, truth + [shift, 0, 0], np.zeros((2, 3, 3)))
        e_g = estimation_error(estimate, step, truth)
        assert e_g == pytest.approx(shift * np.sqrt(2))
        assert estimation_error(estimate, step + 1, truth) is None  # a reading of another step
        assert estimation_error(estimate, None, truth) is None  # no reading this tick
        frame = Frame(SimpleNamespace(target_step=step, time_s=0.1 * step),
                      SimpleNamespace(estimate=estimate, scalars={"lambda_max_m2": 1.0}), truth,
                      estimation=EstimationError(e_g, step, fresh=True))
        observer.on_tick(frame)
        assert frame.scalars == {"lambda_max_m2": 1.0, "e_g_m": e_g}
    summary = observer.summary()  # step 0 is left out (eq. 13a averages t = 1..t_end)
    assert summary["e_g_mean_m"] == pytest.approx(0.35 * np.sqrt(2))
    assert summary["e_g_std_m"] == pytest.approx(0.05 * np.sqrt(2))
    assert EstimationMetrics().summary() == {}


def test_table1_report_tabulates_the_methods_beside_the_paper(tmp_path):
    """`tether report` on a table1-shaped results table (no simulation)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from tether.report import write_report

    rows = []
    for seed in (0, 1):
        for method, level in (("intermittent", 0.5), ("random_meeting", 1.0), ("all_time", 2.0)):
            rows.append({"trial_id": f"{method}{seed}", "trial_index": len(rows), "attempt": 1, "status": "completed",
                         "error": "", "scenario": "intermittent-8", "strategy.kind": method, "strategy": method,
                         "seed": seed, "n_moving_targets": 8, "e_g_mean_m": level + 0.01 * seed, "e_g_std_m": 0.1,
                         "lambda_bar_mean_m2": level / 4, "lambda_bar_std_m2": 0.01})
    pq.write_table(pa.Table.from_pylist(rows), tmp_path / "results.parquet")
    write_report(tmp_path)
    report = (tmp_path / "report.md").read_text()
    assert "0.505 ± 0.100 (seeds ±0.005, n=2)" in report  # intermittent e_g: mean, time std, seed spread, n
    assert "0.929 ± 0.561" in report  # the paper's intermittent e_g, 8 targets
    assert "Intermittent beats both baselines on both means: yes" in report
    assert "intermittent e_g: lower than all-time in 2/2 seeds, lower than random meeting in 2/2 seeds" in report


def test_mirror_reflection_keeps_every_coplanar_reading_and_maps_the_covariance():
    from estimation.ekf import predicted_ranges, reflect_below

    rng = np.random.default_rng(3)
    mean = np.array([1.0, 2.0, -0.7, 3.0, 1.0, 1.2])  # target 0 below the plane z = 0.05, target 1 above
    a = rng.normal(size=(6, 6))
    cov = a @ a.T
    reflected, cov2 = reflect_below(mean, cov, 0.05)
    assert np.allclose(reflected, [1.0, 2.0, 0.8, 3.0, 1.0, 1.2])
    sensors = np.c_[rng.uniform(0, 4, size=(10, 2)), np.full(10, 0.05)]
    targets = np.repeat([0, 1], 5)
    assert np.allclose(predicted_ranges(mean, sensors, targets), predicted_ranges(reflected, sensors, targets))
    flip = np.diag([1, 1, -1, 1, 1, 1.0])
    assert np.allclose(cov2, flip @ cov @ flip)
    assert np.allclose(np.linalg.eigvalsh(cov2), np.linalg.eigvalsh(cov))


def test_ekf_with_coplanar_sensors_settles_above_the_floor():
    from estimation.ekf import FilterState, RangeReadings, TargetEKF
    from estimation.target_motion import LinearPath, TargetMotion

    truth = np.array([0.0, 0.0, 1.0])
    motion = TargetMotion([LinearPath(tuple(truth), tuple(truth), 0.0)], dt=1.0, noise_std=0.0)
    prior = FilterState(0, np.array([0.4, -0.3, 0.0]), 0.25 * np.eye(3))  # poor prior in the sensor plane

    def final(mirror):
        ekf = TargetEKF(motion, prior, mirror_plane_z=mirror)
        for k in range(60):
            angle = 0.15 * k
            sensor = np.array([[1.5 * np.cos(angle), 1.5 * np.sin(angle), 0.05]])
            ekf.update(RangeReadings(sensor, [0], [np.linalg.norm(truth - sensor[0])]))
            ekf.predict()
        return ekf.state.mean

    plain, resolved = final(None), final(0.05)
    assert plain[2] < -0.8  # the plain EKF settles on the mirror image below the floor
    assert resolved[2] > 0.9 and np.linalg.norm(resolved - truth) < 0.2
