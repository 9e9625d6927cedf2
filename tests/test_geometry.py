"""Pure box geometry against dense sampling, finite differences and mj_ray."""

import mujoco
import numpy as np
from hypothesis import given, settings, strategies as st

from sim.geometry import Boxes, point_clearance, segment_clearance, segments_free
from sim.world import extract_obstacles, obstacle_geomgroup
from sim.scenario import SCENE_DIR


def _random_boxes(rng, k=4):
    from scipy.spatial.transform import Rotation

    centers = rng.uniform(-2, 2, size=(k, 3))
    halves = rng.uniform(0.1, 0.8, size=(k, 3))
    rotations = Rotation.random(k, random_state=rng.integers(1 << 31)).as_matrix()
    return Boxes(centers, halves, rotations)


def _dense_clearance(boxes, a, b, n=4001):
    s = np.linspace(0, 1, n)[:, None]
    return point_clearance(boxes, a + s * (b - a)).min()


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 10_000))
def test_segment_clearance_matches_dense_sampling(seed):
    rng = np.random.default_rng(seed)
    boxes = _random_boxes(rng)
    a, b = rng.uniform(-4, 4, size=(2, 3))
    got = segment_clearance(boxes, a[None], b[None]).distance[0]
    # Dense sampling overestimates by at most the sampling step's reach.
    ref = _dense_clearance(boxes, a, b)
    assert got <= ref + 1e-9
    assert got >= ref - np.linalg.norm(b - a) / 4000 - 1e-9


def test_point_clearance_of_an_axis_aligned_box():
    boxes = Boxes.axis_aligned([[0, 0, 0]], [[1, 2, 3]])
    pts = np.array([[2.0, 0, 0], [0, 0, 0], [2.0, 3.0, 0]])
    np.testing.assert_allclose(point_clearance(boxes, pts), [1.0, 0.0, np.sqrt(2.0)])


def test_segment_clearance_gradient_matches_finite_differences():
    rng = np.random.default_rng(3)
    boxes = _random_boxes(rng, k=3)
    checked = 0
    for _ in range(50):
        a, b = rng.uniform(-4, 4, size=(2, 3))
        c = segment_clearance(boxes, a[None], b[None])
        if c.distance[0] < 0.05:
            continue  # gradient undefined when touching
        ga, gb = c.gradients(a[None], b[None])
        h = 1e-6
        for k in range(3):
            e = np.zeros(3)
            e[k] = h
            fd_a = (segment_clearance(boxes, (a + e)[None], b[None]).distance[0]
                    - segment_clearance(boxes, (a - e)[None], b[None]).distance[0]) / (2 * h)
            fd_b = (segment_clearance(boxes, a[None], (b + e)[None]).distance[0]
                    - segment_clearance(boxes, a[None], (b - e)[None]).distance[0]) / (2 * h)
            np.testing.assert_allclose(ga[0, k], fd_a, atol=2e-4)
            np.testing.assert_allclose(gb[0, k], fd_b, atol=2e-4)
        checked += 1
    assert checked >= 20


def test_numpy_line_of_sight_agrees_with_mj_ray_in_the_indoor_scene():
    model = mujoco.MjModel.from_xml_path(str(SCENE_DIR / "indoor.xml"))
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    boxes = extract_obstacles(model, data)
    rng = np.random.default_rng(0)
    a = rng.uniform([0.2, 0.2, 0.2], [9.8, 9.8, 4.8], size=(400, 3))
    b = rng.uniform([0.2, 0.2, 0.2], [9.8, 9.8, 4.8], size=(400, 3))
    clearance = segment_clearance(boxes, a, b).distance
    geomid = np.zeros(1, dtype=np.int32)
    blocked = np.array([
        0 <= mujoco.mj_ray(model, data, a[i], b[i] - a[i], obstacle_geomgroup(), 1, -1, geomid) < 1
        for i in range(len(a))
    ])
    clear_cut = (clearance > 1e-3) | (clearance < 1e-8)  # skip grazing segments
    assert clear_cut.sum() > 380
    np.testing.assert_array_equal(blocked[clear_cut], clearance[clear_cut] < 1e-8)
    assert blocked.any() and (~blocked).any()
    np.testing.assert_array_equal(segments_free(boxes, a, b), clearance > 0)
