"""Exploration layer of Nestmeyer et al. 2017: parameters, eqs. (3)-(15), and Algorithms 1-2 end to end.

Robot motion is integrated here as the virtual point of eq. (1) with
M = 1 kg, M v' = -B v + f_lambda + f (a double integrator, no MuJoCo).
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from connected_helpers import preset_params
from controllers.connectivity.connected_params import ConnectedParams
from controllers.connectivity.exploration import ExplorationController
from controllers.connectivity.paths import GridPlanner, SplinePath
from controllers.connectivity.roles import Role
from controllers.connectivity.targets import TargetQueues
from controllers.connectivity.travel import (
    PathReference,
    adaptive_gain,
    anchor_force,
    anchor_potential,
    consensus_step,
    efficiency,
    force_alignment,
    needs_replanning,
    path_reference,
    reference_speed,
    tracking_error,
    travel_force,
    traveling_efficiency,
)
from sim.geometry import Boxes
from sim.scenario import load

unit = st.floats(0.0, 1.0, allow_nan=False)
interior = st.floats(1e-3, 1.0 - 1e-3, allow_nan=False)
sigmas = st.floats(1.0, 20.0, allow_nan=False)


# -- parameters ---------------------------------------------------------------


def test_presets_follow_tables_2_and_3():
    office, outdoor = preset_params("office"), preset_params("outdoor")
    experiment = load("connected-lab").strategy.params  # Table 3: the experiment's scenario
    table_row = lambda p: (p.grid_resolution_m, p.cruise_speed_mps, p.target_radius_m, p.dwell_time_s)  # noqa: E731
    assert table_row(office) == (0.25, 1.0, 1.0, 3.0)
    assert table_row(outdoor) == (0.75, 3.0, 1.8, 3.0)
    assert office.sigma == outdoor.sigma == experiment.sigma == 3.0
    assert (office.efficiency_error_full_mps, office.efficiency_error_zero_mps) == pytest.approx((0.1, 0.6))
    assert (outdoor.efficiency_error_full_mps, outdoor.efficiency_error_zero_mps) == pytest.approx((0.3, 1.8))
    assert (experiment.efficiency_error_full_mps, experiment.efficiency_error_zero_mps) == pytest.approx((0.1, 0.35))
    assert (experiment.grid_resolution_m, experiment.target_radius_m, experiment.consensus_gain) == (0.2, 0.75, 1.0)
    # Thresholds follow an overridden cruise speed, as "(0.1, 0.6) v_cruise" says.
    assert preset_params("office", cruise_speed_mps=2.0).efficiency_error_zero_mps == pytest.approx(1.2)


@pytest.mark.parametrize(
    "override, field",
    [
        (dict(cruise_speed_mps=0.0), "cruise_speed"),
        (dict(sigma=0.5), "sigma"),
        (dict(efficiency_error_full_ratio=0.7), "efficiency_error_full"),
        (dict(position_error_weight=1.5), "position_error_weight"),
        (dict(path_min_clearance_m=2.0), "path_min_clearance"),
        (dict(message_latency_ticks=0), "message_latency_ticks"),
        (dict(target_radius_m=float("inf")), "target_radius"),
        (dict(dwell_time_s=-1.0), "dwell_time"),
    ],
)
def test_invalid_parameters_name_the_field(override, field):
    with pytest.raises(ValueError, match=field):
        preset_params("office", **override)


# -- eqs. (8), (9), (14): Theta, Lambda, rho ----------------------------------


def test_force_alignment_cases_of_eq_8():
    x = np.array([[1.0, 0, 0], [1.0, 0, 0], [1.0, 0, 0], [0.0, 0, 0], [2.0, 2.0, 0]])
    y = np.array([[3.0, 0, 0], [-1.0, 0, 0], [0.0, 5.0, 0], [1.0, 0, 0], [0.0, 1.0, 0]])
    np.testing.assert_allclose(force_alignment(x, y), [1.0, 0.0, 0.5, 1.0, 0.5 * (1 + np.sqrt(0.5))])


def test_efficiency_of_eq_9():
    x_c, x_m = 0.1, 0.6
    x = np.array([0.0, 0.1, 0.35, 0.6, 2.0])
    np.testing.assert_allclose(efficiency(x, x_c, x_m), [1.0, 1.0, 0.5, 0.0, 0.0], atol=1e-15)
    dense = efficiency(np.linspace(0.0, 1.0, 1001), x_c, x_m)
    assert np.all(np.diff(dense) <= 0) and np.all(np.diff(dense[101:600]) < 0)
    with pytest.raises(ValueError):
        efficiency(x, 0.6, 0.6)


@settings(max_examples=200, deadline=None)
@given(x=unit, sigma=sigmas)
def test_rho_is_governed_by_efficiency_at_its_boundaries(x, sigma):
    assert adaptive_gain(x, 1.0, sigma) == pytest.approx(1.0)  # property 1
    assert adaptive_gain(x, 0.0, sigma) == pytest.approx(0.0, abs=1e-15)  # property 2
    assert adaptive_gain(x, 0.3, 1.0) == pytest.approx(0.3)  # property 5


@settings(max_examples=200, deadline=None)
@given(x=unit, y1=unit, y2=unit, sigma=sigmas)
def test_rho_increases_with_efficiency_and_stays_in_unit_interval(x, y1, y2, sigma):
    low, high = sorted((y1, y2))
    rho_low, rho_high = adaptive_gain(x, low, sigma), adaptive_gain(x, high, sigma)
    assert 0.0 <= rho_low <= rho_high + 1e-12 <= 1.0 + 1e-12  # property 3


@settings(max_examples=200, deadline=None)
@given(x1=unit, x2=unit, y=interior, sigma=st.floats(1.01, 20.0))
def test_rho_increases_with_alignment(x1, x2, y, sigma):
    low, high = sorted((x1, x2))
    assert adaptive_gain(low, y, sigma) <= adaptive_gain(high, y, sigma) + 1e-12  # property 4
    if high - low > 1e-6:
        assert adaptive_gain(low, y, sigma) < adaptive_gain(high, y, sigma)


def test_rho_tends_to_alignment_for_large_sigma():
    x = np.linspace(0, 1, 11)
    np.testing.assert_allclose(adaptive_gain(x, 0.5, 200.0), x, atol=1e-12)  # property 6
    with pytest.raises(ValueError):
        adaptive_gain(x, 0.5, 0.9)


# -- eq. (13): consensus -------------------------------------------------------


def test_consensus_converges_to_the_prime_travelers_efficiency():
    n = 6
    chain = np.zeros((n, n), dtype=bool)
    chain[np.arange(n - 1), np.arange(1, n)] = chain[np.arange(1, n), np.arange(n - 1)] = True
    is_prime = np.arange(n) == 2
    estimates = np.zeros(n)
    for _ in range(3000):
        estimates = consensus_step(estimates, chain, is_prime, np.full(n, 0.7), gain=3.0, dt=0.01)
    np.testing.assert_allclose(estimates, 0.7, atol=1e-3)


@settings(max_examples=100, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), dt=st.floats(0.001, 5.0))
def test_consensus_is_saturated_to_unit_interval(seed, dt):
    rng = np.random.default_rng(seed)
    n = 8
    weights = np.triu(rng.random((n, n)) * (rng.random((n, n)) < 0.6), 1)
    weights = weights + weights.T
    estimates = rng.random(n)
    is_prime = rng.random(n) < 0.2
    prime_values = rng.uniform(-0.5, 1.5, n)
    updated = consensus_step(estimates, weights, is_prime, prime_values, gain=3.0, dt=dt)
    assert np.all((updated >= 0.0) & (updated <= 1.0))
    np.testing.assert_allclose(updated[is_prime], np.clip(prime_values[is_prime], 0, 1))
    # Small steps do not leave the hull of the neighbours' values (no overshoot).
    small = consensus_step(estimates, weights, np.zeros(n, bool), prime_values, gain=1.0, dt=1e-3)
    assert small.min() >= estimates.min() - 1e-12 and small.max() <= estimates.max() + 1e-12
    # Only the presence of an edge matters, not its weight.
    unweighted = consensus_step(estimates, weights > 0, np.zeros(n, bool), prime_values, 1.0, 1e-3)
    np.testing.assert_allclose(small, unweighted)


def test_isolated_robot_keeps_its_estimate():
    updated = consensus_step(np.array([0.3, 0.9]), np.zeros((2, 2), bool), np.zeros(2, bool), np.zeros(2), 1.0, 0.5)
    np.testing.assert_allclose(updated, [0.3, 0.9])


# -- eqs. (5)-(7): anchor -------------------------------------------------------


def test_anchor_force_is_the_gradient_of_eq_6():
    rng = np.random.default_rng(1)
    radius, gain = 1.8, 3.0
    target = np.array([[2.0, -1.0, 4.0]])
    directions = rng.normal(size=(20, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    points = target + rng.uniform(0.05, 0.95, (20, 1)) * radius * directions
    force = anchor_force(points, target, radius, gain)
    h = 1e-6
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = h
        potential = lambda p: anchor_potential(np.linalg.norm(p - target, axis=1), radius, gain)  # noqa: E731
        numeric = -(potential(points + step) - potential(points - step)) / (2 * h)
        np.testing.assert_allclose(force[:, axis], numeric, rtol=1e-5, atol=1e-7)


def test_anchor_force_limits():
    target = np.zeros((1, 3))
    np.testing.assert_allclose(anchor_force(target, target, 1.0, 1.0), 0.0)
    assert anchor_potential(0.0, 1.0, 1.0) == 0.0 and anchor_potential(1.0, 1.0, 1.0) == np.inf
    near_rim = anchor_force([[0.0, 0.999, 0.0]], target, 1.0, 1.0)
    outside = anchor_force([[0.0, 0.0, -3.0]], target, 1.0, 1.0, max_force=7.0)
    np.testing.assert_allclose(anchor_force([[0.0, 0.999, 0.0]], target, 1.0, 1.0, max_force=7.0), [[0, -7.0, 0]])
    assert near_rim[0, 1] < -600  # tan grows without bound at R_z
    np.testing.assert_allclose(outside, [[0.0, 0.0, 7.0]])


def test_anchor_keeps_a_disturbed_robot_within_the_target_radius():
    params = preset_params("office")
    rng = np.random.default_rng(2)
    dt, damping = 0.005, 2.0
    target = np.array([[4.0, 4.0, 2.0]])
    q = target + [[0.9 * params.target_radius_m, 0.0, 0.0]]
    v = np.array([[0.5, 0.0, 0.0]])  # drifting outwards on arrival
    worst = 0.0
    for _ in range(4000):
        disturbance = rng.normal(size=(1, 3))
        disturbance *= 2.0 * params.anchor_gain_n / np.linalg.norm(disturbance)  # 2 k_z, N
        force = anchor_force(q, target, params.target_radius_m, params.anchor_gain_n, params.anchor_force_limit_n)
        v = v + dt * (force + disturbance - damping * v)
        q = q + dt * v
        worst = max(worst, float(np.linalg.norm(q - target)))
    assert worst < params.target_radius_m
    # Under a 2 k_z push the equilibrium is at tan(l pi / 2 R_z) = 2.
    assert worst > 0.5 * params.target_radius_m


# -- eqs. (3), (11), (12): travel ----------------------------------------------


def office_planner(walls: Boxes, params: ConnectedParams) -> GridPlanner:
    """Planner for a 10 x 10 x 5 m room with the preset's grid and margins."""
    return GridPlanner.from_params(walls, [0, 0, 0], [10, 10, 5], params)



def test_reference_speed_brakes_linearly_to_rest():
    speed, slope = reference_speed(np.array([10.0, 2.0, 1.0, 0.0]), 3.0, 2.0)
    np.testing.assert_allclose(speed, [3.0, 3.0, 1.5, 0.0])
    np.testing.assert_allclose(slope, [0.0, 0.0, -1.5, -1.5])


def test_path_reference_moves_along_the_tangent():
    path = SplinePath.fit(np.array([[0.0, 0, 1], [4.0, 0, 1], [4.0, 4.0, 1]]), 0.2, 0.3)
    reference = path_reference(path, [[2.0, 0.3, 1.0], [4.2, 3.99, 1.0]], cruise_speed=1.0, braking_distance=1.0)
    _, tangent, curvature = path.derivatives(reference.arc_length)
    np.testing.assert_allclose(reference.velocity[0], tangent[0])  # at cruise speed
    np.testing.assert_allclose(reference.acceleration[0], curvature[0], atol=1e-12)  # v^2 kappa, v = 1
    assert reference.remaining[1] < 0.02 and np.linalg.norm(reference.velocity[1]) < 0.02
    np.testing.assert_allclose(reference.remaining, path.length - reference.arc_length)
    assert needs_replanning(reference, 0.25).tolist() == [True, False]


def test_tracking_error_and_efficiency_of_eqs_11_12():
    reference = PathReference(
        arc_length=np.zeros(2),
        point=np.array([[0.0, 0, 0], [1.0, 0, 0]]),
        velocity=np.array([[1.0, 0, 0], [1.0, 0, 0]]),
        acceleration=np.zeros((2, 3)),
        distance=np.zeros(2),
        remaining=np.ones(2),
    )
    q = np.array([[0.0, 0.3, 0.0], [1.0, 0.0, 0.0]])
    v = np.array([[0.8, 0.0, 0.0], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(tracking_error(q, v, reference, 0.25), [0.75 * 0.2 + 0.25 * 0.3, 0.75])
    np.testing.assert_allclose(traveling_efficiency(q, v, reference, 0.0, 0.2, 0.7), [1.0, 0.0])
    # eq. (3) with the same reference: PD + feedforward.
    reference_ff = PathReference(**{**reference.__dict__, "acceleration": np.ones((2, 3))})
    f = travel_force(q, v, reference_ff, position_gain=4.0, velocity_gain=2.0, mass=2.0)
    np.testing.assert_allclose(f[0], 2.0 * (np.ones(3) + 2.0 * np.array([0.2, 0, 0]) + 4.0 * np.array([0, -0.3, 0])))
    # Capped (the simulator's bounded f_i): the magnitude is limited, the direction kept, and a
    # force below the cap is left as it is.
    limit = 0.5 * np.linalg.norm(f[0])
    capped = travel_force(q, v, reference_ff, position_gain=4.0, velocity_gain=2.0, mass=2.0, max_force=limit)
    np.testing.assert_allclose(np.linalg.norm(capped, axis=1), np.minimum(np.linalg.norm(f, axis=1), limit))
    np.testing.assert_allclose(capped[0], 0.5 * f[0])
    loose = travel_force(q, v, reference_ff, position_gain=4.0, velocity_gain=2.0, mass=2.0, max_force=1e6)
    np.testing.assert_array_equal(loose, f)


@pytest.mark.parametrize("damping, expected_speed_fraction", [(0.0, 1.0), (2.0, 10.0 / 12.0)])
def test_travel_force_drives_a_point_mass_along_the_path_at_cruise_speed(damping, expected_speed_fraction):
    params = preset_params("office")
    walls = Boxes.axis_aligned([[5.0, 2.5, 2.5], [5.0, 8.75, 2.5]], [[0.1, 2.5, 2.5], [0.1, 1.25, 2.5]])
    planner = office_planner(walls, params)
    start, goal = np.array([1.0, 1.0, 1.5]), np.array([9.0, 1.5, 3.0])
    path = planner.plan(start, goal)
    dt = 0.01
    q, v = start[None].copy(), np.zeros((1, 3))
    speeds, lateral, cruising = [], [], []
    # The trip at cruise speed plus the exponential approach of the braking ramp.
    cruise_time = path.length / (expected_speed_fraction * params.cruise_speed_mps)
    duration = cruise_time + 6 * params.braking_distance_m / params.cruise_speed_mps
    for _ in range(int(duration / dt)):
        reference = path_reference(path, q, params.cruise_speed_mps, params.braking_distance_m)
        force = travel_force(q, v, reference, params.position_gain, params.velocity_gain, params.virtual_mass_kg)
        v = v + dt * (force - damping * v) / params.virtual_mass_kg
        q = q + dt * v
        speeds.append(np.linalg.norm(v))
        lateral.append(reference.distance[0])
        cruising.append(2.0 < reference.arc_length[0] < path.length - params.braking_distance_m)
    speeds, lateral, cruising = np.array(speeds), np.array(lateral), np.array(cruising)
    assert np.linalg.norm(q[0] - goal) < 0.05  # it reaches the target and stops
    assert np.linalg.norm(v) < 0.05
    np.testing.assert_allclose(speeds[cruising].mean(), expected_speed_fraction * params.cruise_speed_mps, rtol=0.05)
    assert speeds.max() < 1.1 * params.cruise_speed_mps
    assert lateral.max() < 0.1  # stays on gamma_i
    assert planner.clearance_of(path.sample(0.02)).min() >= params.path_clearance_m - 1e-9


# -- Algorithms 1 and 2 ----------------------------------------------------------


def simulate(controller: ExplorationController, q: np.ndarray, duration: float, dt: float, damping: float = 2.0):
    """Integrate M v' = -B v + f for the virtual points on a complete graph with
    f_lambda = 0; yields every tick's output and positions."""
    n = len(q)
    v = np.zeros_like(q)
    complete = ~np.eye(n, dtype=bool)
    for k in range(int(round(duration / dt))):
        out = controller.step(k * dt, q, v, complete, np.zeros_like(q))
        yield k * dt, out, q.copy()
        if out.finished:
            return
        v = v + dt * (out.forces - damping * v) / controller.params.virtual_mass_kg
        q = q + dt * v


@pytest.fixture(scope="module")
def room_planner() -> GridPlanner:
    params = preset_params("office")
    walls = Boxes.axis_aligned([[5.0, 2.5, 2.5], [5.0, 8.75, 2.5]], [[0.1, 2.5, 2.5], [0.1, 1.25, 2.5]])
    return office_planner(walls, params)


def test_team_visits_all_targets_with_their_dwell_times(room_planner):
    params = preset_params("office", dwell_time_s=1.0)
    start = np.array([[1.0, 1.0, 1.5], [1.5, 2.0, 1.5], [2.0, 1.0, 2.0], [2.0, 2.0, 1.0]])
    targets = [
        np.array([[3.0, 8.0, 2.0], [8.0, 2.0, 2.0]]),  # robot 0: two targets, the second behind the wall
        np.array([[2.0, 4.0, 2.5]]),  # robot 1: the closest first target
        np.array([[4.0, 1.5, 3.0], [1.0, 6.0, 1.5]]),
        np.zeros((0, 3)),  # robot 3: connector throughout
    ]
    dwell = [[1.0, 0.5], [1.0], [1.0, 1.0], []]
    controller = ExplorationController(params, room_planner, TargetQueues.from_lists(targets, dwell))
    dt = 0.02
    primes_at_once, roles_seen, visit_log = 0, [], []
    first = None
    for time, out, q in simulate(controller, start.copy(), 90.0, dt):
        first = first or out
        primes_at_once = max(primes_at_once, int(np.sum(out.roles == Role.PRIME_TRAVELER)))
        roles_seen.append(out.roles)
        anchored = out.roles == Role.ANCHOR
        if np.any(anchored):
            visit_log.append(np.linalg.norm(q[anchored] - out.targets[anchored], axis=1).max())
    assert out.finished
    assert primes_at_once == 1
    # Start-up: everybody with a target waits as secondary traveler with rho = 0.
    assert first.roles.tolist() == [Role.SECONDARY_TRAVELER] * 3 + [Role.CONNECTOR]
    np.testing.assert_allclose(first.forces, 0.0)
    roles_seen = np.array(roles_seen)
    # Robot 1 has the shortest first path: the start-up election makes it prime.
    first_prime = roles_seen[np.argmax((roles_seen == Role.PRIME_TRAVELER).any(axis=1))]
    assert np.flatnonzero(first_prime == Role.PRIME_TRAVELER).tolist() == [1]
    assert np.all(roles_seen[:, 3] == Role.CONNECTOR)
    visits = {(v.target.robot, v.target.index): v for v in out.visits}
    assert sorted(visits) == [(0, 0), (0, 1), (1, 0), (2, 0), (2, 1)]
    for visit in out.visits:
        assert visit.completion_time - visit.arrival_time >= visit.target.dwell_time - 1e-9
    assert visits[(0, 0)].completion_time < visits[(0, 1)].arrival_time  # queue order
    assert max(visit_log) < params.target_radius_m  # anchors stay within R_z
    assert not out.skipped


def test_secondary_traveler_replans_when_dragged_off_its_path(room_planner):
    params = preset_params("office")
    start = np.array([[1.0, 1.0, 1.5], [1.0, 2.5, 1.5]])
    queues = TargetQueues.from_lists([np.array([[3.0, 1.0, 1.5]]), np.array([[3.0, 8.0, 2.0]])], 1.0)
    controller = ExplorationController(params, room_planner, queues)
    complete = ~np.eye(2, dtype=bool)
    zeros = np.zeros((2, 3))
    for tick in range(5):
        out = controller.step(0.01 * tick, start, zeros, complete, zeros)
    assert out.roles.tolist() == [Role.PRIME_TRAVELER, Role.SECONDARY_TRAVELER]
    old_paths = out.paths
    dragged = start.copy()
    dragged[0] = [2.0, 2.8, 1.5]  # both robots farther than R_gamma = 1 m from their paths
    dragged[1] = [2.5, 2.0, 3.0]
    for robot in range(2):
        assert old_paths[robot].project(dragged[robot])[2][0] > params.replan_distance_m
    out = controller.step(0.05, dragged, zeros, complete, zeros)
    assert out.paths[1] is not old_paths[1]
    np.testing.assert_allclose(out.paths[1].start, dragged[1])
    np.testing.assert_allclose(out.paths[1].end, [3.0, 8.0, 2.0])
    # The prime traveler keeps its path (Alg. 1 replans secondary travelers only).
    assert out.paths[0] is old_paths[0]


def test_secondary_force_is_scaled_by_rho_and_prime_efficiency_is_broadcast(room_planner):
    params = preset_params("office", consensus_gain=5.0)
    start = np.array([[1.0, 1.0, 1.5], [1.0, 2.5, 1.5], [1.5, 1.5, 1.5]])
    queues = TargetQueues.from_lists([np.array([[4.0, 1.0, 1.5]]), np.array([[3.0, 8.0, 2.0]]), np.zeros((0, 3))], 1.0)
    controller = ExplorationController(params, room_planner, queues)
    chain = np.array([[0, 0, 1], [0, 0, 1], [1, 1, 0]], dtype=bool)  # 0 - 2 - 1
    pushing_back = np.array([[0, 0, 0], [-5.0, 0, 0], [0, 0, 0]])
    zeros = np.zeros((3, 3))
    outs = [controller.step(0.02 * k, start, zeros, chain, pushing_back) for k in range(200)]
    last = outs[-1]
    assert last.prime == 0
    # Robot 0 stands still: velocity error = v_cruise >= x_M, so Lambda_p = 0 and
    # the estimates of the other robots, relayed by robot 2, stay at 0 too.
    assert last.prime_efficiency == 0.0
    np.testing.assert_allclose(last.efficiency_estimate, 0.0)
    np.testing.assert_allclose(last.forces[1], 0.0)
    assert last.roles[2] == Role.CONNECTOR and np.all(last.forces[2] == 0)
    # Now the prime traveler moves at cruise speed along its path.
    moving = np.zeros((3, 3))
    for k in range(200, 600):
        moving[0] = path_reference(last.paths[0], start[:1], params.cruise_speed_mps,
                                   params.braking_distance_m).velocity[0]
        out = controller.step(0.02 * k, start, moving, chain, pushing_back)
    assert out.prime_efficiency == pytest.approx(1.0)
    np.testing.assert_allclose(out.efficiency_estimate, 1.0, atol=1e-3)
    reference = path_reference(out.paths[1], start[1:2], params.cruise_speed_mps, params.braking_distance_m)
    f_travel = travel_force(start[1:2], moving[1:2], reference, params.position_gain, params.velocity_gain)
    theta = force_alignment(pushing_back[1:2], f_travel)
    rho = adaptive_gain(theta, out.efficiency_estimate[1], params.sigma)
    assert out.alignment[1] == pytest.approx(theta[0]) and out.gain[1] == pytest.approx(rho[0])
    np.testing.assert_allclose(out.forces[1], rho[0] * f_travel[0])


def test_unreachable_target_is_skipped(room_planner):
    params = preset_params("office")
    inside_wall = np.array([5.0, 1.0, 2.0])
    queues = TargetQueues.from_lists([np.array([inside_wall, [2.0, 2.0, 2.0]])], 0.0)
    controller = ExplorationController(params, room_planner, queues)
    out = controller.step(0.0, np.array([[1.0, 1.0, 1.5]]), np.zeros((1, 3)), np.zeros((1, 1), bool), np.zeros((1, 3)))
    assert [t.index for t in out.skipped] == [0]
    np.testing.assert_allclose(out.targets[0], [2.0, 2.0, 2.0])


def test_step_rejects_wrong_shapes(room_planner):
    controller = ExplorationController(preset_params("office"), room_planner, TargetQueues(2))
    with pytest.raises(ValueError, match="velocities"):
        controller.step(0.0, np.zeros((2, 3)), np.zeros((3, 3)), np.zeros((2, 2), bool), np.zeros((2, 3)))
