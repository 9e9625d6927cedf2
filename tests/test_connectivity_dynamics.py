"""Virtual dynamics M v' = f_B + f_lambda + f (Nestmeyer et al. 2017, eq. 1) and Fact 1:
under bounded external forces the connectivity force keeps the graph
connected and the robots apart from each other and from obstacles."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from connected_helpers import preset_params
from controllers.connectivity.connected_params import FiedlerEstimatorParams
from controllers.connectivity.dynamics import (
    connectivity_layer_force,
    damping_force,
    step_virtual_dynamics,
)
from controllers.connectivity.estimator import FiedlerEstimator
from controllers.connectivity.graph import link_weights
from controllers.connectivity.potential import connectivity_potential
from sim.geometry import Boxes, point_clearance

OFFICE = preset_params("office")
DT = 0.01  # s
# A wall beside a six-robot chain along x (y in [0.6, 1.8], x in [3.9, 4.1]).
SIDE_WALL = Boxes.axis_aligned([[4.0, 1.2, 1.0]], [[0.1, 0.6, 1.0]])


def chain(n: int = 6, spacing: float = 1.5) -> np.ndarray:
    jitter = np.random.default_rng(0).normal(0.0, 0.05, (n, 3))
    return np.array([[i * spacing, 0.0, 1.0] for i in range(n)]) + jitter


def min_pair_distance(positions: np.ndarray) -> float:
    d = np.linalg.norm(positions[:, None] - positions[None], axis=-1)
    return float((d + np.diag(np.full(len(positions), np.inf))).min())


def simulate(positions, external, boxes, params, seconds, estimator=None, warmup=0.0):
    """Integrate q, v under f_B + f_lambda + external; record the worst case."""
    velocities = np.zeros_like(positions)
    worst = dict(lambda2=np.inf, distance=np.inf, clearance=np.inf)
    start = positions.copy()
    for k in range(round(seconds / DT)):
        estimate = None
        if estimator is not None:
            estimate = estimator.step(link_weights(positions, boxes, params).weights, DT)
            if k * DT < warmup:
                estimate = None
        layer = connectivity_layer_force(positions, velocities, boxes, params, estimate)
        positions, velocities = step_virtual_dynamics(
            positions, velocities, layer.connectivity + external(positions), DT, params
        )
        worst["lambda2"] = min(worst["lambda2"], layer.state.lambda2)
        worst["distance"] = min(worst["distance"], min_pair_distance(positions))
        if boxes is not None:
            worst["clearance"] = min(worst["clearance"], point_clearance(boxes, positions).min())
    worst["displacement"] = (positions - start).mean(axis=0)
    worst["final_lambda2"] = layer.state.lambda2
    return worst


# ------------------------------------------------------------------ integrator


def test_damping_alone_decays_velocity_geometrically_towards_exp():
    velocities = np.array([[1.0, -2.0, 0.5], [0.0, 3.0, 0.0]])
    positions = np.zeros_like(velocities)
    q, v = positions, velocities
    steps = 100
    for _ in range(steps):
        q, v = step_virtual_dynamics(q, v, np.zeros_like(v), DT, OFFICE)
    ratio = 1.0 / (1.0 + DT * OFFICE.damping_nspm / OFFICE.virtual_mass_kg)
    np.testing.assert_allclose(v, velocities * ratio**steps, rtol=1e-12)
    exact = velocities * np.exp(-OFFICE.damping_nspm / OFFICE.virtual_mass_kg * steps * DT)
    np.testing.assert_allclose(v, exact, atol=0.02 * np.abs(velocities).max())
    # Position is the sum of the velocities it moved with.
    travelled = DT * velocities * ratio * (1 - ratio**steps) / (1 - ratio)
    np.testing.assert_allclose(q, travelled, rtol=1e-12)
    np.testing.assert_array_equal(damping_force(velocities, OFFICE), -OFFICE.damping_nspm * velocities)


def test_constant_force_reaches_terminal_velocity_f_over_b():
    force = np.array([[3.0, 0.0, -1.0]])
    q, v = np.zeros((1, 3)), np.zeros((1, 3))
    for _ in range(1000):
        q, v = step_virtual_dynamics(q, v, force, DT, OFFICE)
    np.testing.assert_allclose(v, force / OFFICE.damping_nspm, rtol=1e-6)


def test_implicit_damping_never_reverses_velocity():
    heavy = SimpleNamespace(virtual_mass_kg=1.0, damping_nspm=1e4)  # far beyond the keys' bounds
    _, v = step_virtual_dynamics(np.zeros((1, 3)), np.ones((1, 3)), np.zeros((1, 3)), DT, heavy)
    assert np.all((v > 0) & (v < 0.02))


def test_integrator_rejects_bad_shapes_and_steps():
    with pytest.raises(ValueError, match="shape"):
        step_virtual_dynamics(np.zeros((2, 3)), np.zeros((3, 3)), np.zeros((2, 3)), DT, OFFICE)
    with pytest.raises(ValueError, match="dt"):
        step_virtual_dynamics(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 3)), 0.0, OFFICE)


# -------------------------------------------------------------------- Fact 1


def test_constant_pull_drags_the_team_without_breaking_connectivity():
    pull = np.zeros((6, 3))
    pull[-1] = [3.0, 0.5, 0.0]  # N, on the last robot of the chain only
    worst = simulate(chain(), lambda q: pull, SIDE_WALL, OFFICE, seconds=15.0)
    assert worst["lambda2"] > OFFICE.lambda2_min + 0.05
    assert worst["distance"] > OFFICE.min_robot_distance_m
    assert worst["clearance"] > OFFICE.min_obstacle_clearance_m
    # Connectivity made the whole team follow: mean displacement ~ F t / (N B).
    assert worst["displacement"][0] > 0.6 * 3.0 * 12.0 / (6 * OFFICE.damping_nspm)


def test_stronger_pull_is_held_by_a_stiffer_response_not_a_break():
    pull = np.zeros((6, 3))
    pull[-1] = [10.0, 0.0, 0.0]
    worst = simulate(chain(), lambda q: pull, None, OFFICE, seconds=8.0)
    assert worst["lambda2"] > OFFICE.lambda2_min + 0.01
    assert worst["distance"] > OFFICE.min_robot_distance_m


def test_robots_pushed_into_each_other_keep_the_minimum_distance():
    positions = np.array([[0.0, 0.0, 1.0], [1.6, 0.0, 1.0], [0.8, 1.3, 1.0], [0.8, -1.3, 1.0]])
    push = np.zeros((4, 3))
    push[0] = [6.0, 0.0, 0.0]
    push[1] = [-6.0, 0.0, 0.0]
    worst = simulate(positions, lambda q: push, None, OFFICE, seconds=6.0)
    assert worst["distance"] > OFFICE.min_robot_distance_m
    assert worst["lambda2"] > OFFICE.lambda2_min


def test_robot_pushed_into_a_wall_keeps_the_obstacle_clearance():
    wall = Boxes.axis_aligned([[0.0, 2.5, 1.0]], [[3.0, 0.1, 1.0]])  # plane y = 2.4..2.6
    positions = np.array([[-1.0, 0.0, 1.0], [0.5, 0.0, 1.0], [0.0, 1.3, 1.0]])
    push = np.zeros((3, 3))
    push[2] = [0.0, 6.0, 0.0]
    worst = simulate(positions, lambda q: push, wall, OFFICE, seconds=6.0)
    assert worst["clearance"] > OFFICE.min_obstacle_clearance_m
    assert worst["lambda2"] > OFFICE.lambda2_min


def test_free_motion_dissipates_energy():
    """Passivity: with f = 0, kinetic + connectivity energy never increases."""
    wall = Boxes.axis_aligned([[2.0, 0.0, 1.0]], [[0.1, 0.8, 1.0]])
    positions = np.array(
        [[1.0, 0.0, 1.0], [1.0, 1.0, 1.0], [3.0, 1.2, 1.0], [3.0, -0.2, 1.2], [2.0, 1.9, 1.3], [4.0, 0.5, 1.0]]
    )
    velocities = np.random.default_rng(0).normal(0.0, 1.0, positions.shape)
    energy, lambdas = [], []
    for _ in range(500):
        layer = connectivity_layer_force(positions, velocities, wall, OFFICE)
        kinetic = 0.5 * OFFICE.virtual_mass_kg * (velocities**2).sum()
        energy.append(kinetic + float(connectivity_potential(layer.state.lambda2, OFFICE)))
        lambdas.append(layer.state.lambda2)
        positions, velocities = step_virtual_dynamics(positions, velocities, layer.connectivity, DT, OFFICE)
    assert np.all(np.diff(energy) <= 1e-9)
    assert energy[-1] < 0.01 * energy[0]
    # The potential drew the team together, towards lambda2_null where it vanishes.
    assert lambdas[0] < 0.5 * OFFICE.lambda2_null < 0.95 * OFFICE.lambda2_null < lambdas[-1]


def test_layer_force_reports_damping_and_connectivity_parts():
    positions, velocities = chain(), np.random.default_rng(1).normal(size=(6, 3))
    layer = connectivity_layer_force(positions, velocities, SIDE_WALL, OFFICE)
    np.testing.assert_array_equal(layer.damping, -OFFICE.damping_nspm * velocities)
    np.testing.assert_allclose(layer.total, layer.damping + layer.connectivity)
    np.testing.assert_array_equal(layer.lambda2_used, np.full(6, layer.state.lambda2))
    assert np.any(layer.connectivity != 0)  # a stretched chain is below lambda2_null


def test_decentralised_estimates_keep_a_moderately_pulled_team_connected():
    """The same pull with each robot using its own lambda2 / eigenvector
    estimate (after the estimator's warm-up on the oracle's motion)."""
    pull = np.zeros((6, 3))
    pull[-1] = [3.0, 0.5, 0.0]
    estimator = FiedlerEstimator(6, FiedlerEstimatorParams(), np.random.default_rng(1))
    worst = simulate(chain(), lambda q: pull, SIDE_WALL, OFFICE, seconds=10.0, estimator=estimator, warmup=3.0)
    assert worst["lambda2"] > OFFICE.lambda2_min + 0.05
    assert worst["distance"] > OFFICE.min_robot_distance_m
    assert worst["clearance"] > OFFICE.min_obstacle_clearance_m


def test_estimate_with_wrong_shape_is_rejected():
    from controllers.connectivity.estimator import FiedlerEstimate

    with pytest.raises(ValueError, match="estimate"):
        connectivity_layer_force(chain(), np.zeros((6, 3)), None, OFFICE, FiedlerEstimate(np.ones(5), np.ones(5)))
