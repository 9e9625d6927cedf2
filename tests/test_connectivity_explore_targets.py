"""Target queues, dwell clocks and random target generation of Nestmeyer et al. 2017 (Secs. 2.1, 4.1)."""

from __future__ import annotations

import numpy as np
import pytest

from controllers.connectivity.paths import GridPlanner
from controllers.connectivity.targets import (
    DwellClock,
    TargetQueues,
    monte_carlo_target_counts,
    random_free_points,
    random_target_lists,
)
from sim.geometry import Boxes, point_clearance


@pytest.fixture(scope="module")
def planner() -> GridPlanner:
    # A sealed box room in the corner: nothing inside it is reachable from outside.
    cage = Boxes.axis_aligned(
        [[8.5, 8.5, 0.05], [8.5, 8.5, 4.95], [6.95, 8.5, 2.5], [8.5, 6.95, 2.5], [3.0, 3.0, 2.5]],
        [[1.5, 1.5, 0.05], [1.5, 1.5, 0.05], [0.05, 1.5, 2.5], [1.5, 0.05, 2.5], [0.5, 0.5, 2.5]],
    )
    return GridPlanner(cage, [0, 0, 0], [10, 10, 5], 0.25, 0.6, 0.25, 0.15)


def test_queues_hand_out_targets_in_order_and_accept_online_targets():
    queues = TargetQueues.from_lists([np.array([[1, 2, 3], [4, 5, 6]]), np.zeros((0, 3))], [[2.0, 0.5], []])
    assert queues.pending().tolist() == [True, False] and len(queues) == 2
    first = queues.pop(0)
    assert (first.robot, first.index, first.dwell_time) == (0, 0, 2.0)
    np.testing.assert_allclose(first.position, [1, 2, 3])
    with pytest.raises(ValueError):
        first.position[0] = 9.0  # targets are immutable records
    late = queues.push(1, [7, 8, 9], 1.0)  # generated online
    assert (late.robot, late.index) == (1, 0)
    assert queues.pop(0).index == 1 and queues.pop(0) is None
    assert queues.pop(1) is late and len(queues) == 0


@pytest.mark.parametrize("position, dwell", [([0, 0, np.nan], 1.0), ([0, 0, 0], -1.0), ([0, 0, 0], np.inf)])
def test_invalid_targets_are_rejected(position, dwell):
    with pytest.raises(ValueError):
        TargetQueues(1).push(0, position, dwell)


def test_dwell_clock_restarts_when_the_robot_leaves():
    clock = DwellClock(2)
    clock.update(0.0, [True, False])
    clock.update(1.0, [True, True])
    np.testing.assert_allclose(clock.elapsed(1.5), [1.5, 0.5])
    clock.update(2.0, [False, True])
    clock.update(2.5, [True, True])
    np.testing.assert_allclose(clock.elapsed(3.0), [0.5, 2.0])


def test_monte_carlo_allocation_of_section_4_1():
    counts = monte_carlo_target_counts(35)
    assert sum(counts) == 25 and counts.count(3) == 5 and counts.count(2) == 5 and counts.count(0) == 25
    with pytest.raises(ValueError):
        monte_carlo_target_counts(9)


def test_random_targets_are_free_reachable_and_reproducible(planner):
    home = np.array([1.0, 1.0, 1.5])
    counts = [3, 3, 2, 0, 1]
    queues = random_target_lists(np.random.default_rng(5), planner, counts, 3.0, reachable_from=home)
    again = random_target_lists(np.random.default_rng(5), planner, counts, 3.0, reachable_from=home)
    other = random_target_lists(np.random.default_rng(6), planner, counts, 3.0, reachable_from=home)
    points, repeat, different = [], [], []
    for robot, count in enumerate(counts):
        for _ in range(count):
            target = queues.pop(robot)
            points.append(target.position)
            repeat.append(again.pop(robot).position)
            different.append(other.pop(robot).position)
            assert target.dwell_time == 3.0
        assert queues.pop(robot) is None
    points = np.array(points)
    np.testing.assert_array_equal(points, repeat)
    assert not np.allclose(points, different)
    assert point_clearance(planner.boxes, points).min() > planner.margins[-1]
    assert np.all((points > planner.lower + planner.margins[-1]) & (points < planner.upper - planner.margins[-1]))
    # Nothing lands in the sealed room, although it is free space.
    inside_cage = np.all((points[:, :2] > 7.0) & (points[:, :2] < 10.0), axis=1)
    assert not inside_cage.any()
    assert planner.is_free([[8.5, 8.5, 2.5]])[0] and not planner.connected(home, [8.5, 8.5, 2.5])
    for point in points:
        planner.plan(home, point)  # the planner reaches every target


def test_too_many_points_in_too_little_space_fail_loudly(planner):
    with pytest.raises(ValueError, match="free points"):
        random_free_points(np.random.default_rng(0), planner, 3, clearance=4.0)
