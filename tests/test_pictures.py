"""Pictures that explain themselves: the overlay scales with the frame, the
colours have a legend, a scene without cameras gets an orthographic top view
that walls do not hide the floor in, and robots stay visible at any scene size.
Real EGL frames read back; skipped cleanly without OpenGL."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from helpers import write_scenario, write_scene
from tether.runner import build_simulation
from sim.scenario import load
from viz.video import FrameRenderer, burn_overlay, overlay_font_px

BAND_RGB = (20, 20, 28)

# A user's 10 x 10 m room: 5 m walls, a floor of its own colour, no cameras, no tether_bounds.
ROOM = """
<mujoco model="user_room">
  <worldbody>
    <light pos="5 5 8" dir="0 0 -1" directional="true"/>
    <geom name="floor" type="plane" size="5 5 0.05" pos="5 5 0" rgba="0.2 0.5 0.9 1"/>
    <geom name="wall_s" type="box" size="5 0.1 2.5" pos="5 0 2.5" rgba="0.5 0.5 0.5 1"/>
    <geom name="wall_n" type="box" size="5 0.1 2.5" pos="5 10 2.5" rgba="0.5 0.5 0.5 1"/>
    <geom name="wall_w" type="box" size="0.1 5 2.5" pos="0 5 2.5" rgba="0.5 0.5 0.5 1"/>
    <geom name="wall_e" type="box" size="0.1 5 2.5" pos="10 5 2.5" rgba="0.5 0.5 0.5 1"/>
  </worldbody>
</mujoco>
"""
ROOM_SCENARIO = """
scene = "scene.xml"
duration_s = 1.0
[video]
width = {width}
height = {height}
[strategy]
kind = "waypoints"
[[robots]]
kind = "ground"
starts = [[0.5, 0.5, 0.0], [9.5, 9.5, 0.0]]
"""


def _render(scenario, ticks: int = 1):
    sim = build_simulation(scenario)
    for _ in range(ticks):
        frame, healthy = sim.tick()
        assert healthy
    try:
        view = FrameRenderer(sim.world, sim.scenario.video)
    except Exception as err:  # no OpenGL here
        pytest.skip(f"offscreen rendering unavailable: {err}")
    try:
        return frame, view, view.render(frame).astype(int)
    finally:
        view.close()


def _band_rows(image: np.ndarray) -> int:
    """Height of the overlay band: rows from the top whose first pixels are the band colour."""
    is_band = np.all(np.abs(image[:, :3] - BAND_RGB) <= 2, axis=(1, 2))
    return int(np.argmin(is_band)) if not is_band.all() else len(is_band)


def _glyph_rows(image: np.ndarray, band: int) -> int:
    """Rows of the band that hold text pixels (bright), first to last."""
    bright = np.flatnonzero((image[:band].min(axis=2) > 150).any(axis=1))
    return int(bright[-1] - bright[0] + 1)


def test_overlay_glyphs_scale_with_the_frame_and_are_legible_at_720p(tmp_path):
    write_scene(tmp_path, ROOM)
    sizes = {}
    for width, height in ((640, 360), (1280, 720)):
        path = write_scenario(tmp_path, ROOM_SCENARIO.format(width=width, height=height), f"s{height}.toml")
        _, _, image = _render(load(str(path)))
        band = _band_rows(image)
        sizes[height] = (band, _glyph_rows(image, band))
    (band_small, glyph_small), (band_large, glyph_large) = sizes[360], sizes[720]
    # Twice the frame height, twice the band and the glyphs (within rounding of font sizes).
    assert band_large / band_small == pytest.approx(2.0, rel=0.15)
    assert glyph_large / glyph_small == pytest.approx(2.0, rel=0.2)
    # Legible at 1280 x 720: capitals and digits about 2 % of the frame height (14 px and more).
    assert glyph_large >= 14 and overlay_font_px(720) >= 18


def test_a_long_overlay_shrinks_to_fit_and_the_legend_band_names_the_colours():
    image = np.full((240, 320, 3), 200, np.uint8)
    out = burn_overlay(image, "t = 12.0 s   links 9   " + "x" * 80,
                       [("prime traveler", (0.0, 0.95, 0.85, 1.0)), ("anchor", (1.0, 0.6, 0.1, 1.0))])
    top = np.asarray(out[:4], dtype=int)
    assert np.all(np.abs(top[:, :300] - BAND_RGB) <= 2, axis=2).mean() > 0.5  # the band spans the width
    bottom = np.asarray(out[-30:], dtype=int)
    # Both swatches are drawn in their colours at the bottom-left.
    assert np.any(np.all(np.abs(bottom - (0, 242, 217)) <= 3, axis=2))
    assert np.any(np.all(np.abs(bottom - (255, 153, 26)) <= 3, axis=2))


def test_a_scene_without_cameras_gets_an_orthographic_top_view_walls_hide_no_floor(tmp_path):
    write_scene(tmp_path, ROOM)
    path = write_scenario(tmp_path, ROOM_SCENARIO.format(width=480, height=480))
    _, view, image = _render(load(str(path)))
    assert view.camera_name == "top" and view.camera.orthographic
    # The floor (blue) fills the room right up to the walls: sample a ring 0.3 m inside them.
    lo_px, hi_px = 240 - 240 / 1.05, 240 + 240 / 1.05  # the floor spans the view, 5 % margin
    per_m = (hi_px - lo_px) / 10.0
    ring = [(0.3, y) for y in np.linspace(2, 8, 7)] + [(9.7, y) for y in np.linspace(2, 8, 7)] + \
           [(x, 0.3) for x in np.linspace(2, 8, 7)] + [(x, 9.7) for x in np.linspace(2, 8, 7)]
    for x, y in ring:
        col, row = int(lo_px + x * per_m), int(hi_px - y * per_m)
        r, g, b = image[row, col]
        assert b > r + 40, (x, y, image[row, col])  # floor blue, not a wall's grey or shadow


def test_robots_stay_visible_in_a_large_scene():
    scenario = load("connected-town", ["robots.0.count=10"])
    scenario = dataclasses.replace(scenario, video=dataclasses.replace(scenario.video, width=640, height=480))
    frame, view, image = _render(scenario)
    # Each quadrotor covers a disc of at least ~4 px radius in its role colour or halo.
    assert view.at_least(0.12, 5.0) > 0.4  # 50 x 70 m in 480 px: 5 px are ~0.77 m
    scale = view.world.model.camera("top").fovy[0] / 480  # the town's orthographic top camera: m per px
    centre = view.world.model.camera("top").pos[:2]
    colors = np.asarray(frame.commands.decorations.robot_colors)[:, :3] * 255
    for p, rgb in zip(frame.observation.position, colors):
        col = int(round(320 + (p[0] - centre[0]) / scale))
        row = int(round(240 - (p[1] - centre[1]) / scale))
        patch = image[row - 2 : row + 3, col - 2 : col + 3]
        # The robot's own colour (its role) shows around it, shaded by the light.
        assert np.abs(patch - rgb).max(axis=2).min() < 70, (p, rgb, patch[2, 2])


class _Line:
    """A straight planned path from (0, 0, 1) to (10, 0, 1) (duck-types SplinePath.sample)."""

    def sample(self, spacing: float) -> np.ndarray:
        xs = np.arange(0.0, 10.0 + 1e-9, spacing)
        return np.stack([xs, np.zeros_like(xs), np.ones_like(xs)], axis=1)


def test_drawn_paths_start_at_their_robot_and_never_serve_a_stale_path():
    from types import SimpleNamespace

    from controllers.connectivity.strategy import ConnectedStrategy

    strategy = SimpleNamespace(_drawn_paths={}, params=SimpleNamespace(grid_resolution_m=0.25))
    draw = lambda path, q: ConnectedStrategy._path_points(strategy, path, np.asarray(q, float))  # noqa: E731
    path = _Line()
    points = draw(path, (3.1, 0.2, 1.0))
    # Only what lies ahead: from the robot's point to the end, nothing behind it.
    np.testing.assert_allclose(points[0], (3.1, 0.2, 1.0))
    assert points[1:, 0].min() > 3.0 and points[-1, 0] == pytest.approx(10.0)
    # Never backwards along the path (a robot pushed back does not regrow its trail).
    assert draw(path, (1.0, 0.0, 1.0))[1:, 0].min() > 3.0
    # A new path whose id equals a dropped one's gets its own samples, not the old polyline.
    other = _Line()
    strategy._drawn_paths[id(other)] = [object(), np.zeros((2, 3)), 0]
    assert draw(other, (0.0, 0.0, 1.0))[-1, 0] == pytest.approx(10.0)
