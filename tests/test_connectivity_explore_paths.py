"""Planned paths of Nestmeyer et al. 2017 (Sec. 3.2): obstacle-free with margin, C2, arc-length parametrised."""

from __future__ import annotations

import time

import numpy as np
import pytest
from scipy.interpolate import BSpline

from controllers.connectivity.paths import GridPlanner, NoPathError, SplinePath, planning_resolution
from sim.geometry import Boxes, point_clearance

LOWER, UPPER = np.zeros(3), np.array([10.0, 10.0, 5.0])
CLEARANCE, MIN_CLEARANCE, TOLERANCE, RESOLUTION = 0.6, 0.25, 0.15, 0.25


def room_with_door(door_width: float = 2.5) -> Boxes:
    """10 x 10 x 5 m room split by a wall at x = 5 with a full-height door centred at y = 6,
    plus a pillar in the left half."""
    low_end, high_start = 6.0 - door_width / 2, 6.0 + door_width / 2
    return Boxes.axis_aligned(
        [[5.0, low_end / 2, 2.5], [5.0, (high_start + 10.0) / 2, 2.5], [2.5, 3.0, 2.5]],
        [[0.1, low_end / 2, 2.5], [0.1, (10.0 - high_start) / 2, 2.5], [0.4, 0.4, 2.5]],
    )


@pytest.fixture(scope="module")
def planner() -> GridPlanner:
    return GridPlanner(room_with_door(), LOWER, UPPER, RESOLUTION, CLEARANCE, MIN_CLEARANCE, TOLERANCE)


@pytest.fixture(scope="module")
def door_path(planner) -> SplinePath:
    return planner.plan([1.0, 1.0, 1.5], [9.0, 1.5, 3.0])


def test_path_joins_start_to_target(door_path):
    np.testing.assert_allclose(door_path.start, [1.0, 1.0, 1.5], atol=1e-9)
    np.testing.assert_allclose(door_path.end, [9.0, 1.5, 3.0], atol=1e-9)


def test_path_goes_through_the_door_keeping_the_clearance(planner, door_path):
    points = door_path.sample(0.01)
    # Start and goal are themselves farther than the preferred clearance from everything.
    assert planner.clearance_of(points).min() >= CLEARANCE - 1e-9
    crossing = points[np.argmin(np.abs(points[:, 0] - 5.0))]
    assert 6.0 - 1.25 + CLEARANCE <= crossing[1] <= 6.0 + 1.25 - CLEARANCE
    assert np.all((points >= LOWER + CLEARANCE - 1e-9) & (points <= UPPER - CLEARANCE + 1e-9))


def test_path_is_nearly_as_short_as_the_taut_string():
    """Around the end of a full-height wall (x = 5, y <= 6) from (2, 2) to (8, 2):
    any path keeping clearance c crosses x = 5 at y >= 6 + c, so it is at least
    2 hypot(3, 4 + c) long; the polyline via (4.9, 6.75), (5.1, 6.75) keeps the
    planning margin and bounds the taut string from above."""
    wall = Boxes.axis_aligned([[5.0, 3.0, 2.5]], [[0.1, 3.0, 2.5]])
    planner = GridPlanner(wall, LOWER, UPPER, RESOLUTION, CLEARANCE, MIN_CLEARANCE, TOLERANCE)
    path = planner.plan([2.0, 2.0, 2.5], [8.0, 2.0, 2.5])
    lower_bound = 2 * np.hypot(3.0, 4.0 + CLEARANCE)
    margin = CLEARANCE + TOLERANCE
    upper_bound = 2 * np.hypot(2.9, 4.0 + margin) + 0.2
    assert lower_bound <= path.length <= 1.03 * upper_bound


def test_arc_length_matches_a_dense_polyline(door_path):
    u = np.linspace(door_path.spline.t[0], door_path.spline.t[-1], 200_001)
    dense = door_path.spline(u)
    assert door_path.length == pytest.approx(np.sum(np.linalg.norm(np.diff(dense, axis=0), axis=1)), rel=1e-7)
    # point(s) is the B-spline at the parameter whose arc length is s.
    s = np.linspace(0.0, door_path.length, 37)
    np.testing.assert_allclose(door_path.point(s), door_path.spline(door_path.parameter(s)), atol=1e-12)
    np.testing.assert_allclose(door_path.arc_length(door_path.parameter(s)), s, atol=1e-9)


def test_derivatives_match_finite_differences(door_path):
    s = np.linspace(0.05, door_path.length - 0.05, 301)
    h = 1e-4
    position, tangent, curvature = door_path.derivatives(s)
    np.testing.assert_allclose(np.linalg.norm(tangent, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose((door_path.point(s + h) - door_path.point(s - h)) / (2 * h), tangent, atol=1e-6)
    _, tangent_plus, _ = door_path.derivatives(s + h)
    _, tangent_minus, _ = door_path.derivatives(s - h)
    curvature_scale = 1 + np.abs(curvature).max()
    np.testing.assert_allclose((tangent_plus - tangent_minus) / (2 * h), curvature, atol=1e-4 * curvature_scale)
    np.testing.assert_allclose(np.sum(tangent * curvature, axis=1), 0.0, atol=1e-9)
    np.testing.assert_allclose(position, door_path.point(s), atol=1e-12)


def test_path_is_c2_across_knots(door_path):
    knots = np.unique(door_path.spline.t)[1:-1]
    s_knots = door_path.arc_length(knots)
    eps = 1e-7
    for derivative in range(3):
        before = door_path.derivatives(s_knots - eps)[derivative]
        after = door_path.derivatives(s_knots + eps)[derivative]
        np.testing.assert_allclose(before, after, atol=1e-4)
    # ... while the third derivative does jump somewhere: the path is not one cubic.
    third = door_path.spline.derivative(3)
    assert np.abs(third(knots - 1e-9) - third(knots + 1e-9)).max() > 1e-6


def test_projection_matches_brute_force(door_path):
    rng = np.random.default_rng(3)
    dense_s = np.linspace(0.0, door_path.length, 20_001)
    dense = door_path.point(dense_s)
    along = door_path.point(rng.uniform(0, door_path.length, 40))
    queries = along + rng.normal(scale=0.3, size=along.shape)
    arc, closest, distance = door_path.project(queries)
    brute = np.linalg.norm(queries[:, None] - dense[None], axis=-1)
    assert np.all(distance <= brute.min(axis=1) + 1e-9)
    assert np.all(distance >= brute.min(axis=1) - 1e-3)
    np.testing.assert_allclose(door_path.point(arc), closest, atol=1e-9)


def test_straight_path_when_line_of_sight_is_free(planner):
    path = planner.plan([1.0, 6.0, 2.0], [3.5, 8.0, 3.0])
    assert path.length == pytest.approx(np.linalg.norm([2.5, 2.0, 1.0]), rel=1e-12)
    _, _, curvature = path.derivatives(np.linspace(0, path.length, 11))
    np.testing.assert_allclose(curvature, 0.0, atol=1e-9)


def test_zero_length_path_is_a_point():
    path = SplinePath.fit(np.array([[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]]), 0.1, 0.2)
    assert path.length == 0.0
    position, tangent, curvature = path.derivatives(np.array([0.0]))
    np.testing.assert_allclose(position, [[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(tangent, 0.0)
    assert path.project([[2.0, 2.0, 3.0]])[2][0] == pytest.approx(1.0)


def test_smoothing_fit_stays_within_tolerance_of_a_corner():
    corner = np.array([[0.0, 0.0, 1.0], [4.0, 0.0, 1.0], [4.0, 4.0, 1.0]])
    path = SplinePath.fit(corner, 0.2, 0.3)
    points = path.sample(0.005)
    x, y = points[:, 0], points[:, 1]
    to_first_leg = np.hypot(y, np.maximum(x - 4.0, 0.0) + np.maximum(-x, 0.0))
    to_second_leg = np.hypot(x - 4.0, np.maximum(-y, 0.0) + np.maximum(y - 4.0, 0.0))
    to_legs = np.minimum(to_first_leg, to_second_leg)
    np.testing.assert_allclose(points[:, 2], 1.0, atol=1e-12)
    assert to_legs.max() <= 0.2 + 1e-9
    # Rounding the corner is what smoothing is for: the spline leaves the corner point.
    assert np.linalg.norm(points - [4.0, 0.0, 1.0], axis=1).min() > 0.05
    # A C2 B-spline built from its own coefficients reproduces the piecewise form.
    reference = BSpline(path.spline.t, path.spline.c, 3)
    s = np.linspace(0, path.length, 50)
    np.testing.assert_allclose(path.point(s), reference(path.parameter(s)), atol=1e-12)


def test_narrow_door_falls_back_to_the_minimum_clearance():
    narrow = GridPlanner(room_with_door(1.3), LOWER, UPPER, RESOLUTION, CLEARANCE, MIN_CLEARANCE, TOLERANCE)
    path = narrow.plan([1.0, 1.0, 1.5], [9.0, 1.5, 3.0])
    clearance = narrow.clearance_of(path.sample(0.01)).min()
    assert MIN_CLEARANCE - 1e-9 <= clearance < CLEARANCE


def test_unreachable_target_raises(planner):
    cage = Boxes.axis_aligned(
        [[8, 8, 2.5], [8, 8, 0.05], [8, 8, 4.95], [6.95, 8, 2.5], [9.05, 8, 2.5], [8, 6.95, 2.5], [8, 9.05, 2.5]],
        [[0.05] * 3, [1, 1, 0.05], [1, 1, 0.05], [0.05, 1, 2.5], [0.05, 1, 2.5], [1, 0.05, 2.5], [1, 0.05, 2.5]],
    )
    caged = GridPlanner(cage, LOWER, UPPER, RESOLUTION, CLEARANCE, MIN_CLEARANCE, TOLERANCE)
    with pytest.raises(NoPathError):
        caged.plan([1.0, 1.0, 1.5], [8.5, 8.5, 2.5])
    assert not caged.connected([1.0, 1.0, 1.5], [8.5, 8.5, 2.5])
    assert caged.connected([1.0, 1.0, 1.5], [3.0, 5.0, 2.5])


def test_resolution_is_coarsened_for_huge_scenes():
    assert planning_resolution([0, 0, 0], [10, 10, 5], 0.25) == 0.25
    coarse = planning_resolution([0, 0, 0], [500, 700, 50], 0.75, max_cells=400_000)
    assert coarse > 0.75
    assert np.prod(np.floor(np.array([500, 700, 50]) / coarse) + 1) <= 400_000


def town(rng: np.random.Generator) -> Boxes:
    centres = np.c_[rng.uniform(5, 45, 30), rng.uniform(5, 65, 30), np.full(30, 6.0)]
    halves = np.c_[rng.uniform(1, 4, 30), rng.uniform(1, 4, 30), np.full(30, 6.0)]
    return Boxes.axis_aligned(centres, halves)


def test_outdoor_scene_replans_online():
    """50 x 70 m town at the outdoor R_grid: one (re)planning query well under a second."""
    buildings = town(np.random.default_rng(0))
    outdoor = GridPlanner(buildings, [0, 0, 0], [50, 70, 15], 0.75, 1.75, 0.75, 0.4)
    outdoor.plan([2.0, 2.0, 3.0], [48.0, 68.0, 3.0])  # builds the cached graph
    started = time.perf_counter()
    path = outdoor.plan([2.5, 2.0, 3.0], [48.0, 67.0, 3.5])
    elapsed = time.perf_counter() - started
    assert elapsed < 1.0
    points = path.sample(0.05)
    assert point_clearance(buildings, points).min() >= 0.75
    np.testing.assert_allclose(path.end, [48.0, 67.0, 3.5], atol=1e-9)
