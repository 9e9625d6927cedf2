"""Sensed ranges and links against geometric truth in a scene with one known wall."""

import numpy as np
import pytest

from estimation.range_model import range_sigma
from tether.runner import build_simulation
from sim.scenario import load

from helpers import write_scenario, write_scene

# The wall occupies x in [4.9, 5.1], y in [2, 8], z in [0, 4].
SCENARIO = """
scene = "scene.xml"
duration_s = 1.0
[sensing]
range_noise = {noise}
comm_range_m = 3.0
[strategy]
kind = "waypoints"
[[robots]]
kind = "quadrotor"
starts = [[3.0, 5.0, 1.0], [4.0, 6.0, 1.0], [6.0, 5.0, 1.0]]
[[targets]]
path = "static"
start = [3.0, 7.0, 1.0]      # 2 m from robot 0, in sight
[[targets]]
path = "static"
start = [7.0, 5.0, 1.0]      # behind the wall for robots 0 and 1
[[targets]]
path = "static"
start = [3.0, 1.0, 3.5]      # 4.72 m from robot 0, in sight
[[targets]]
path = "static"
start = [9.5, 9.5, 4.5]      # farther than 5 m from robots 0 and 1
"""


@pytest.fixture
def simulation(tmp_path):
    write_scene(tmp_path)
    return build_simulation(load(str(write_scenario(tmp_path, SCENARIO.format(noise="false")))))


def test_ranges_equal_geometric_distance_when_in_sight(simulation):
    obs = simulation.observe()
    sensors = obs.sensor_position
    targets = simulation.targets.positions(0.0)
    truth = np.linalg.norm(sensors[:, None] - targets[None], axis=-1)
    ranges = obs.target_ranges
    assert ranges is not None
    np.testing.assert_allclose(ranges[0, 0], truth[0, 0], atol=1e-9)
    np.testing.assert_allclose(ranges[0, 2], truth[0, 2], atol=1e-9)
    assert truth[0, 2] < 5.0


def test_occluded_or_out_of_range_targets_give_no_reading(simulation):
    ranges = simulation.observe().target_ranges
    assert np.isnan(ranges[0, 1]) and np.isnan(ranges[1, 1])  # wall in between
    assert not np.isnan(ranges[2, 1])  # robot 2 is on the target's side
    assert np.isnan(ranges[0, 3]) and np.isnan(ranges[1, 3])  # beyond 5 m


def test_links_respect_range_and_line_of_sight(simulation):
    links = simulation.observe().links
    assert links.adjacency[0, 1] and links.adjacency[1, 0]  # 1.41 m, same side
    assert not links.line_of_sight[0, 2] and not links.adjacency[0, 2]  # 3 m apart, but wall
    assert not links.adjacency[1, 2]  # 2.24 m, wall in between
    assert not links.adjacency.diagonal().any()
    # Clearance of the 0-1 segment from the wall face at x = 4.9 is 4.9 - 4.0.
    np.testing.assert_allclose(links.clearance[0, 1], 0.9, atol=1e-6)


def test_range_noise_follows_equation_12(tmp_path):
    write_scene(tmp_path)
    sim = build_simulation(load(str(write_scenario(tmp_path, SCENARIO.format(noise="true")))))
    sensors = sim.sensors.sensor_positions()
    targets = sim.targets.positions(0.0)
    truth = np.linalg.norm(sensors[0] - targets[0])
    rng = np.random.default_rng(7)
    samples = np.array([sim.sensors.target_ranges(sensors, targets, rng)[0, 0] for _ in range(3000)])
    sigma = float(range_sigma(truth))
    assert abs(samples.mean() - truth) < 4 * sigma / np.sqrt(len(samples))
    assert abs(samples.std() / sigma - 1) < 0.06


def test_range_sigma_is_the_papers_piecewise_curve():
    np.testing.assert_allclose(range_sigma([0.5, 1.0, 2.0, 3.0, 4.5]), [0.01, 0.01, 0.055, 0.1, 0.1])
