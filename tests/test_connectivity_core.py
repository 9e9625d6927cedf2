"""Continuous-connectivity core of Nestmeyer et al. 2017 (Appendix A): parameters, link
weights, lambda2 and its gradient, the connectivity potential and force.

References: central finite differences of numpy eigvalsh of the Laplacian
built from W(q); Table 2/3 values; invariances (translation, rotation)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from connected_helpers import grown_positions, preset_params
from controllers.connectivity.connected_params import ConnectedParams, FiedlerEstimatorParams
from controllers.connectivity.graph import (
    connectivity_state,
    generalized_connectivity_force,
    half_cosine_rise,
    link_weights,
    weighted_laplacian,
)
from controllers.connectivity.potential import (
    connectivity_potential,
    connectivity_potential_slope,
    guarded_potential_slope,
)
from sim.geometry import Boxes, segment_clearance
from sim.scenario import load

OFFICE = preset_params("office")
# A wall occupying x in [1.9, 2.1], y in [-0.8, 0.8], z in [0, 2].
WALL = Boxes.axis_aligned([[2.0, 0.0, 1.0]], [[0.1, 0.8, 1.0]])
# Six robots around the wall's edge (office parameters): the link 1-2 grazes
# the edge (clearance ~0.3 m, inside (R_o, R'_o)), robots 0 and 1 are 1.0 m
# apart (inside (R_c, R'_c)), the links 0-2 and 0-3 cross the wall.
AROUND_WALL = np.array(
    [
        [1.0, 0.0, 1.0],
        [1.0, 1.0, 1.0],
        [3.0, 1.2, 1.0],
        [3.0, -0.2, 1.2],
        [2.0, 1.9, 1.3],
        [4.0, 0.5, 1.0],
    ]
)


def lambda2_of(positions: np.ndarray, boxes, params: ConnectedParams) -> float:
    """Reference: numpy eigvalsh of the Laplacian of W(q)."""
    return np.linalg.eigvalsh(weighted_laplacian(link_weights(positions, boxes, params).weights))[1]


def central_difference(function, positions, step=1e-6) -> np.ndarray:
    """d function / d positions (N, 3) by central differences of a scalar function of (N, 3) positions."""
    gradient = np.zeros_like(positions)
    for i in range(len(positions)):
        for axis in range(3):
            plus, minus = positions.copy(), positions.copy()
            plus[i, axis] += step
            minus[i, axis] -= step
            gradient[i, axis] = (function(plus) - function(minus)) / (2 * step)
    return gradient


def central_difference_gradient(positions, boxes, params, step=1e-6) -> np.ndarray:
    return central_difference(lambda q: lambda2_of(q, boxes, params), positions, step)


def jittered_wall_configuration(seed: int) -> np.ndarray:
    return AROUND_WALL + np.random.default_rng(seed).normal(0.0, 0.03, AROUND_WALL.shape)


def grown_configuration(rng: np.random.Generator, n: int, params: ConnectedParams) -> np.ndarray:
    """Random connected team: each robot placed 0.9-2.2 m from an earlier one,
    never closer than 1.05 R_c to any."""
    while True:
        positions = grown_positions(rng, n, params.min_robot_distance_m)
        if lambda2_of(positions, None, params) > 0.02:
            return positions


# ----------------------------------------------------------------- parameters


def test_presets_hold_table_2_and_3_values():
    office, outdoor = preset_params("office"), preset_params("outdoor")
    lab = load("connected-lab")  # Table 3: the experiment's scenario
    experiment = lab.strategy.params.at_range(lab.sensing.comm_range_m)

    def table_row(p):
        return (
            (p.full_weight_range_m, p.sensing_range_m),
            (p.min_obstacle_clearance_m, p.full_weight_obstacle_clearance_m),
            (p.min_robot_distance_m, p.full_weight_robot_distance_m),
            (p.lambda2_min, p.lambda2_null),
        )

    assert table_row(office) == ((1.1, 2.5), (0.25, 0.6), (0.8, 1.1), (0.0, 1.0))
    assert table_row(outdoor) == ((2.5, 6.0), (0.75, 1.75), (1.0, 2.5), (0.0, 1.0))
    assert table_row(experiment) == ((1.4, 2.5), (0.5, 0.75), (1.0, 1.4), (0.0, 1.0))
    assert preset_params("office", damping_nspm=3.0).damping_nspm == 3.0


@pytest.mark.parametrize(
    "overrides, sensing_range, field",
    [
        (dict(), 1.0, "full_weight_range_m"),  # R'_s must be < R_s
        (dict(full_weight_obstacle_clearance_m=0.2), 2.5, "min_obstacle_clearance_m"),
        (dict(full_weight_robot_distance_m=0.7), 2.5, "min_robot_distance_m"),
        (dict(min_robot_distance_m=2.6, full_weight_robot_distance_m=2.7), 2.55, "min_robot_distance_m"),
        (dict(full_weight_robot_distance_m=2.6), 2.5, "full_weight_robot_distance_m"),  # beyond R_s
        (dict(lambda2_min=0.5, lambda2_null=0.5), 2.5, "lambda2_min"),
        (dict(lambda2_min=-0.1), 2.5, "lambda2_min"),
        (dict(lambda2_guard=2.0), 2.5, "lambda2_guard"),
        (dict(virtual_mass_kg=0.0), 2.5, "virtual_mass_kg"),
        (dict(damping_nspm=-1.0), 2.5, "damping_nspm"),
        (dict(potential_gain_j=float("inf")), 2.5, "potential_gain_j"),
    ],
)
def test_invalid_parameters_are_rejected_naming_the_field(overrides, sensing_range, field):
    with pytest.raises(ValueError, match=field):
        ConnectedParams(**overrides).at_range(sensing_range)


@pytest.mark.parametrize("name", [f.name for f in dataclasses.fields(FiedlerEstimatorParams) if f.name != "dither"])
def test_estimator_gains_must_be_positive(name):
    with pytest.raises(ValueError, match=name):
        FiedlerEstimatorParams(**{name: 0.0})


def test_estimator_dither_may_be_zero_but_not_negative():
    assert FiedlerEstimatorParams(dither=0.0).dither == 0.0
    with pytest.raises(ValueError, match="dither"):
        FiedlerEstimatorParams(dither=-1e-3)
    assert FiedlerEstimatorParams().lambda2_ceiling > OFFICE.lambda2_null


def test_parameters_are_frozen():
    with pytest.raises(dataclasses.FrozenInstanceError):
        OFFICE.sensing_range_m = 3.0


# -------------------------------------------------------------- weight factors


def test_half_cosine_rise_is_c1_and_exactly_flat_outside_its_band():
    x = np.linspace(-1.0, 3.0, 4001)
    value, slope = half_cosine_rise(x, 0.5, 2.0)
    assert np.all(value[x <= 0.5] == 0.0) and np.all(value[x >= 2.0] == 1.0)
    assert np.all(slope[(x <= 0.5) | (x >= 2.0)] == 0.0)
    assert np.all(np.diff(value) >= 0)
    # Slope matches finite differences and vanishes continuously at both ends.
    h = 1e-6
    fd = (half_cosine_rise(x + h, 0.5, 2.0)[0] - half_cosine_rise(x - h, 0.5, 2.0)[0]) / (2 * h)
    np.testing.assert_allclose(slope, fd, atol=1e-6)
    near_ends = half_cosine_rise(np.array([0.5 + 1e-4, 2.0 - 1e-4]), 0.5, 2.0)[1]
    assert np.all(near_ends < 1e-3)


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(2, 9),
    spread=st.floats(0.5, 4.0),
)
def test_weights_form_a_valid_weighted_graph(seed, n, spread):
    positions = np.random.default_rng(seed).uniform(-spread, spread, (n, 3))
    links = link_weights(positions, WALL, OFFICE)
    weights = links.weights
    np.testing.assert_array_equal(weights, weights.T)
    assert np.all(np.diag(weights) == 0) and np.all((weights >= 0) & (weights <= 1))
    laplacian = weighted_laplacian(weights)
    np.testing.assert_allclose(laplacian.sum(axis=1), 0.0, atol=1e-12)
    assert np.linalg.eigvalsh(laplacian)[0] > -1e-12
    # Edges are exactly the positive weights, each once with i < j.
    edges = links.edges
    assert np.all(edges[:, 0] < edges[:, 1])
    assert len(edges) == np.count_nonzero(np.triu(weights))
    assert np.all(weights[edges[:, 0], edges[:, 1]] > 0)


def test_range_weight_vanishes_at_sensing_range_and_is_full_inside_fade_start():
    def pair_weight(distance):
        return link_weights(np.array([[0.0, 0.0, 1.0], [distance, 0.0, 1.0]]), None, OFFICE).weights[0, 1]

    assert pair_weight(OFFICE.sensing_range_m) == 0.0
    assert pair_weight(OFFICE.sensing_range_m + 0.5) == 0.0
    assert 0.0 < pair_weight(OFFICE.sensing_range_m - 1e-3) < 1e-5
    assert pair_weight(OFFICE.full_weight_range_m) == 1.0  # R'_c = R'_s in the office preset
    assert 0.0 < pair_weight(0.5 * (OFFICE.full_weight_range_m + OFFICE.sensing_range_m)) < 1.0


def test_line_of_sight_weight_vanishes_at_obstacle_clearance():
    def pair_weight(y):
        # Segment along x at height y above the wall's edge (y = 0.8).
        return link_weights(np.array([[1.0, y, 1.0], [3.0, y, 1.0]]), WALL, OFFICE).weights[0, 1]

    edge = 0.8
    assert pair_weight(edge + OFFICE.min_obstacle_clearance_m) == 0.0
    assert pair_weight(0.0) == 0.0  # through the wall
    assert 0.0 < pair_weight(edge + OFFICE.min_obstacle_clearance_m + 1e-3) < 1e-4
    assert 0.0 < pair_weight(edge + 0.45) < pair_weight(edge + 0.55)
    no_wall = link_weights(np.array([[1.0, 2.0, 1.0], [3.0, 2.0, 1.0]]), None, OFFICE).weights[0, 1]
    assert pair_weight(edge + OFFICE.full_weight_obstacle_clearance_m) == pytest.approx(no_wall, abs=1e-12)


def test_a_third_robot_within_collision_distance_cuts_all_links_of_both():
    positions = np.array([[0.0, 0.0, 1.0], [1.5, 0.0, 1.0], [-1.5, 0.0, 1.0], [0.0, 0.0, 1.0 + 0.79]])
    weights = link_weights(positions, None, OFFICE).weights
    # Robot 3 is 0.79 m (< R_c = 0.8 m) from robot 0: every link of 0 and of 3 is cut.
    assert np.all(weights[0] == 0) and np.all(weights[3] == 0)
    positions[3, 2] = 1.0 + 0.81
    weights = link_weights(positions, None, OFFICE).weights
    assert weights[0, 1] > 0 and weights[0, 2] > 0 and weights[0, 3] > 0
    # Between R_c and R'_c the factor fades every link of robot 0, including
    # the one to robot 1, which robot 3 is not near.
    alone = link_weights(positions[:3], None, OFFICE).weights
    assert weights[0, 1] < alone[0, 1]


# ----------------------------------------------------------- lambda2 gradient


@pytest.mark.parametrize("seed", range(4))
def test_lambda2_gradient_matches_finite_differences_with_obstacles(seed):
    positions = jittered_wall_configuration(seed)
    state = connectivity_state(positions, WALL, OFFICE)
    # Preconditions: the configuration exercises all three weight factors.
    first, second = state.links.pairs.T
    clearance = segment_clearance(WALL, positions[first], positions[second]).distance
    grazing = (clearance > OFFICE.min_obstacle_clearance_m) & (clearance < OFFICE.full_weight_obstacle_clearance_m)
    assert np.any(grazing & (state.weights[first, second] > 0))
    assert np.any(state.links.collision_log_slope != 0)
    assert state.lambda2 > 1e-3
    eigenvalues = np.linalg.eigvalsh(state.laplacian)
    assert eigenvalues[2] - eigenvalues[1] > 1e-3  # simple eigenvalue: differentiable

    reference = central_difference_gradient(positions, WALL, OFFICE)
    np.testing.assert_allclose(state.lambda2_gradient, reference, atol=1e-6 * np.abs(reference).max() + 1e-9)
    assert state.lambda2 == pytest.approx(eigenvalues[1], abs=1e-12)


@pytest.mark.parametrize("seed", range(3))
def test_lambda2_gradient_matches_finite_differences_on_random_teams(seed):
    rng = np.random.default_rng(100 + seed)
    positions = grown_configuration(rng, 8, OFFICE)
    state = connectivity_state(positions, None, OFFICE)
    reference = central_difference_gradient(positions, None, OFFICE)
    np.testing.assert_allclose(state.lambda2_gradient, reference, atol=1e-6 * np.abs(reference).max() + 1e-9)


@pytest.mark.parametrize("seed", range(4))
def test_a_bystander_counts_in_the_collision_factors_and_its_gradient_matches_finite_differences(seed):
    """A robot the team dropped is no vertex of the graph but still a body within R'_c (condition (c)):
    the team's weights are those of the whole group's restricted to the team, and the gradient of the
    team's lambda2 (bystander held still) pushes the robots near it away."""
    positions = jittered_wall_configuration(seed)
    bystander = positions[[1]] + np.array([[0.05, 0.0, 0.85]])  # 0.85 m above robot 1: inside (R_c, R'_c)
    state = connectivity_state(positions, WALL, OFFICE, bystanders=bystander)
    whole = link_weights(np.concatenate([positions, bystander]), WALL, OFFICE)
    np.testing.assert_array_equal(state.weights, whole.weights[:6, :6])
    assert state.weights[1].max() < link_weights(positions, WALL, OFFICE).weights[1].max()
    assert len(state.links.bystander_robot) and np.any(state.links.bystander_log_slope != 0)
    reference = central_difference(
        lambda q: np.linalg.eigvalsh(weighted_laplacian(
            link_weights(np.concatenate([q, bystander]), WALL, OFFICE).weights[:6, :6]))[1], positions)
    np.testing.assert_allclose(state.lambda2_gradient, reference, atol=1e-6 * np.abs(reference).max() + 1e-9)
    # Its gradient on robot 1 points away from the bystander (up, away from it, lowers its fade).
    assert state.lambda2_gradient[1, 2] < 0


def test_no_bystanders_is_the_plain_graph_bit_for_bit():
    positions = jittered_wall_configuration(0)
    plain, empty = connectivity_state(positions, WALL, OFFICE), connectivity_state(positions, WALL, OFFICE,
                                                                                   np.zeros((0, 3)))
    np.testing.assert_array_equal(plain.weights, empty.weights)
    np.testing.assert_array_equal(plain.lambda2_gradient, empty.lambda2_gradient)


@pytest.mark.parametrize("seed", range(3))
def test_gradient_on_the_message_links_matches_finite_differences_of_that_graph(seed):
    """Estimator mode controls lambda2(W o A), A the links that carry messages
    (held fixed): its gradient drops the missing links' terms but keeps every
    robot's collision factor."""
    positions = jittered_wall_configuration(seed)
    links = link_weights(positions, WALL, OFFICE)
    first, second = links.edges.T
    adjacency = np.zeros((len(positions),) * 2, dtype=bool)
    adjacency[first, second] = adjacency[second, first] = True
    # Drop one link that moves with q, and keep a pair in the collision fade band.
    dropped = int(np.argmax(np.abs(links.link_factor_grad_first).sum(axis=1) * (links.weights[links.pairs[:, 0],
                                                                                       links.pairs[:, 1]] > 0)))
    i, j = links.pairs[dropped]
    adjacency[i, j] = adjacency[j, i] = False
    assert np.any(links.collision_log_slope != 0)
    restricted = links.restricted_to(adjacency)

    def restricted_lambda2(q):
        weights = link_weights(q, WALL, OFFICE).weights * adjacency
        return np.linalg.eigvalsh(weighted_laplacian(weights))[1]

    eigenvalues, vectors = np.linalg.eigh(weighted_laplacian(restricted.weights))
    assert eigenvalues[1] > 1e-3 and eigenvalues[2] - eigenvalues[1] > 1e-3
    assert eigenvalues[1] < lambda2_of(positions, WALL, OFFICE)  # the dropped link mattered
    reference = central_difference(restricted_lambda2, positions)
    gradient = restricted.lambda2_gradient(vectors[:, 1])
    np.testing.assert_allclose(gradient, reference, atol=1e-6 * np.abs(reference).max() + 1e-9)
    full = links.lambda2_gradient(vectors[:, 1])
    assert np.abs(full - reference).max() > 1e-3 * np.abs(reference).max()


def test_translating_the_team_changes_lambda2_only_through_obstacles():
    positions = jittered_wall_configuration(7)
    direction = np.array([0.3, -0.8, 0.2])
    step = 1e-6
    with_wall = connectivity_state(positions, WALL, OFFICE).lambda2_gradient.sum(axis=0) @ direction
    plus = lambda2_of(positions + step * direction, WALL, OFFICE)
    minus = lambda2_of(positions - step * direction, WALL, OFFICE)
    fd = (plus - minus) / (2 * step)
    assert with_wall == pytest.approx(fd, rel=1e-5, abs=1e-9)
    assert abs(with_wall) > 1e-2  # the clearance term d_ijo really contributes
    without_wall = connectivity_state(positions, None, OFFICE).lambda2_gradient
    np.testing.assert_allclose(without_wall.sum(axis=0), 0.0, atol=1e-12)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_lambda2_gradient_has_no_net_force_or_torque_in_free_space(seed):
    positions = grown_configuration(np.random.default_rng(seed), 7, OFFICE)
    gradient = connectivity_state(positions, None, OFFICE).lambda2_gradient
    scale = np.abs(gradient).max() + 1e-12
    np.testing.assert_allclose(gradient.sum(axis=0) / scale, 0.0, atol=1e-10)
    centred = positions - positions.mean(axis=0)
    np.testing.assert_allclose(np.cross(centred, gradient).sum(axis=0) / scale, 0.0, atol=1e-9)


def test_eq17_alone_misses_the_terms_of_third_robots_within_fade_distance():
    """Eq. (17), sum_j dW_ij/dq_i (v_i - v_j)^2, ignores that q_i also moves the
    links of a robot within R'_c of it; our gradient adds them (and matches FD)."""
    positions = jittered_wall_configuration(3)
    state = connectivity_state(positions, WALL, OFFICE)
    v = state.fiedler
    step = 1e-6
    eq17 = np.zeros_like(positions)
    for i in range(len(positions)):
        for axis in range(3):
            plus, minus = positions.copy(), positions.copy()
            plus[i, axis] += step
            minus[i, axis] -= step
            d_row = (link_weights(plus, WALL, OFFICE).weights[i] - link_weights(minus, WALL, OFFICE).weights[i]) / (
                2 * step
            )
            eq17[i, axis] = d_row @ (v[i] - v) ** 2
    reference = central_difference_gradient(positions, WALL, OFFICE)
    scale = np.abs(reference).max()
    assert np.abs(eq17 - reference).max() > 1e-2 * scale
    assert np.abs(state.lambda2_gradient - reference).max() < 1e-6 * scale


# ------------------------------------------------------------------ potential


def test_potential_slope_matches_finite_differences():
    lam = np.linspace(0.01, 0.99, 99)
    h = 1e-7
    fd = (connectivity_potential(lam + h, OFFICE) - connectivity_potential(lam - h, OFFICE)) / (2 * h)
    np.testing.assert_allclose(connectivity_potential_slope(lam, OFFICE), fd, rtol=1e-5)


def test_potential_is_null_above_threshold_and_c1_there():
    above = np.array([1.0, 1.5, 10.0])
    assert np.all(connectivity_potential(above, OFFICE) == 0)
    assert np.all(connectivity_potential_slope(above, OFFICE) == 0)
    just_below = OFFICE.lambda2_null - 1e-6
    assert 0 < connectivity_potential(just_below, OFFICE) < 1e-10
    assert -1e-4 < connectivity_potential_slope(just_below, OFFICE) < 0


def test_potential_blows_up_at_lambda2_min():
    params = preset_params("office", lambda2_min=0.1, lambda2_null=0.6)
    gaps = 10.0 ** -np.arange(1, 12)
    values = connectivity_potential(params.lambda2_min + gaps, params)
    slopes = connectivity_potential_slope(params.lambda2_min + gaps, params)
    assert np.all(np.diff(values) > 0) and values[-1] > 20 * params.potential_gain_j
    assert np.all(np.diff(slopes) < 0) and slopes[-1] < -1e10
    assert connectivity_potential(params.lambda2_min, params) == np.inf
    assert connectivity_potential_slope(0.05, params) == -np.inf
    # The guarded slope used by the force stays finite and keeps its sign.
    guarded = guarded_potential_slope(np.array([-1.0, 0.1, 0.1 + params.lambda2_guard]), params)
    assert np.all(np.isfinite(guarded)) and np.all(guarded < 0)
    assert guarded[0] == guarded[1] == guarded[2]


def test_connectivity_force_is_the_negative_gradient_of_the_potential_energy():
    params = preset_params("office", potential_gain_j=2.0)
    positions = jittered_wall_configuration(5)
    state = connectivity_state(positions, WALL, params)
    assert params.lambda2_min < state.lambda2 < params.lambda2_null
    force = generalized_connectivity_force(state.links, state.lambda2, state.fiedler, params)

    def energy(q):
        return float(connectivity_potential(lambda2_of(q, WALL, params), params))

    step = 1e-6
    for i in range(len(positions)):
        for axis in range(3):
            plus, minus = positions.copy(), positions.copy()
            plus[i, axis] += step
            minus[i, axis] -= step
            assert force[i, axis] == pytest.approx(-(energy(plus) - energy(minus)) / (2 * step), rel=1e-5, abs=1e-8)


def test_per_robot_lambda2_estimates_scale_each_robots_force():
    state = connectivity_state(jittered_wall_configuration(1), WALL, OFFICE)
    estimates = np.linspace(0.05, 0.9, len(state.fiedler))
    force = generalized_connectivity_force(state.links, estimates, state.fiedler, OFFICE)
    expected = -connectivity_potential_slope(estimates, OFFICE)[:, None] * state.lambda2_gradient
    np.testing.assert_allclose(force, expected, rtol=1e-12, atol=1e-14)
    with pytest.raises(ValueError, match="vector"):
        state.links.lambda2_gradient(np.ones(3))
