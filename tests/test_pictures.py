"""Pictures that explain themselves: the scene fills the frame's height with a
legend panel beside it (never over it) whose text scales with the frame and
stays at least 1/30 of its height, a scene without cameras gets an
orthographic top view that walls do not hide the floor in, and robots stay
visible at any scene size. Real EGL frames read back; skipped cleanly
without OpenGL."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from helpers import write_scenario, write_scene
from tether.runner import build_simulation
from sim.scenario import load
from viz.video import PANEL_RGB, FrameRenderer, min_font_px, overlay_font_px, side_panel

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


def _text_rows(panel: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) rows of each run of rows holding bright text pixels in the panel."""
    bright = (panel.min(axis=2) > 150).any(axis=1)
    runs, start = [], None
    for row, on in enumerate(list(bright) + [False]):
        if on and start is None:
            start = row
        elif not on and start is not None:
            runs.append((start, row - 1))
            start = None
    return runs


def test_the_scene_fills_the_height_and_the_legend_panel_beside_it_scales_with_the_frame(tmp_path):
    write_scene(tmp_path, ROOM)
    glyphs = {}
    for width, height in ((960, 540), (1920, 1080)):
        path = write_scenario(tmp_path, ROOM_SCENARIO.format(width=width, height=height), f"s{height}.toml")
        frame, view, image = _render(load(str(path)))
        assert image.shape == (height, width, 3)
        # The square room fills the height at the left; the panel takes the rest of the 16:9 frame.
        assert view.scene_width == height
        scene, panel = image[:, : view.scene_width], image[:, view.scene_width:]
        assert np.all(np.abs(panel[:, :, :3] - PANEL_RGB).max(axis=2) <= 2, axis=0).any()  # the panel's colour
        assert not np.all(np.abs(scene - PANEL_RGB).max(axis=2) <= 2, axis=1).any()  # no band over the scene
        # The first line ("t = 0.0 s"): its capitals and digits at least 1/30 of the frame's height less
        # the font's leading (a glyph of a font of size s is about 0.7 s tall).
        first, last = _text_rows(panel)[0]
        glyphs[height] = last - first + 1
        assert overlay_font_px(height) >= min_font_px(height) >= height / 30
        assert glyphs[height] >= 0.65 * height / 30
    assert glyphs[1080] / glyphs[540] == pytest.approx(2.0, rel=0.2)


def test_the_panel_names_every_colour_and_wraps_into_columns_when_long():
    legend = [("prime traveler", (0.84, 0.37, 0.0, 1.0)), ("anchor", (0.8, 0.47, 0.65, 1.0))]
    panel = side_panel(540, 420, ["t = 12.0 s", "links 9", "x" * 80], legend).astype(int)
    assert panel.shape == (540, 420, 3)
    # Both swatches are drawn in their colours.
    assert np.any(np.all(np.abs(panel - (214, 94, 0)) <= 3, axis=2))
    assert np.any(np.all(np.abs(panel - (204, 120, 166)) <= 3, axis=2))
    # Thirty entries do not fit one column at 540 px: two columns, text never below 1/30 of the height.
    many = [(f"team {k}", (k / 30, 0.5, 1 - k / 30, 1.0)) for k in range(30)]
    panel = side_panel(540, 420, ["t = 1.0 s"], many).astype(int)
    swatch_columns = np.flatnonzero(np.any(np.all(np.abs(panel - (0, 127, 255)) <= 3, axis=2), axis=0))
    assert swatch_columns.size and swatch_columns.min() < 40  # team 0's swatch in the first column
    late = np.flatnonzero(np.any(np.all(np.abs(panel - (247, 127, 8)) <= 3, axis=2), axis=0))  # team 29
    assert late.size and late.min() > 180  # in the second


def test_a_scene_without_cameras_gets_an_orthographic_top_view_walls_hide_no_floor(tmp_path):
    write_scene(tmp_path, ROOM)
    path = write_scenario(tmp_path, ROOM_SCENARIO.format(width=800, height=480))
    _, view, image = _render(load(str(path)))
    assert view.camera_name == "top" and view.camera.orthographic and view.scene_width == 480
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
    scenario = dataclasses.replace(scenario, video=dataclasses.replace(scenario.video, width=854, height=480))
    frame, view, image = _render(scenario)
    image = image[:, : view.scene_width]
    # Each quadrotor covers a disc of at least ~4 px radius in its role colour or halo.
    assert view.at_least(0.12, 5.0) > 0.4  # 50 x 70 m in 480 px: 5 px are ~0.77 m
    scale = view.world.model.camera("top").fovy[0] / 480  # the town's orthographic top camera: m per px
    centre = view.world.model.camera("top").pos[:2]
    colors = np.asarray(frame.commands.decorations.robot_colors)[:, :3] * 255
    for p, rgb in zip(frame.observation.position, colors):
        col = int(round(view.scene_width / 2 + (p[0] - centre[0]) / scale))
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


def test_a_user_scene_without_a_light_gets_a_default_light_that_does_not_wash_it_out(tmp_path):
    unlit = ROOM.replace('    <light pos="5 5 8" dir="0 0 -1" directional="true"/>\n', "")
    unlit = unlit.replace('rgba="0.2 0.5 0.9 1"', 'rgba="0.8 0.8 0.8 1"')
    write_scene(tmp_path, unlit)
    path = write_scenario(tmp_path, ROOM_SCENARIO.format(width=800, height=480))
    frame, view, image = _render(load(str(path)))
    model = view.world.model
    assert model.nlight == 1 and model.light(0).name == "tether_default_sun"
    assert np.allclose(model.vis.headlight.ambient, 0.3)
    # The light-grey floor stays grey, not washed out to white; the walls' tops stay darker than it.
    floor = image[200:280, 200:280].reshape(-1, 3)
    assert 120 < np.median(floor) < 235, np.median(floor)
    # A scene with its own light keeps it alone.
    write_scene(tmp_path, ROOM, name="lit.xml")
    lit = write_scenario(tmp_path, ROOM_SCENARIO.replace("scene.xml", "lit.xml").format(width=800, height=480),
                         "lit.toml")
    _, lit_view, _ = _render(load(str(lit)))
    assert lit_view.world.model.nlight == 1 and lit_view.world.model.light(0).name != "tether_default_sun"


def _pixels_near(image: np.ndarray, rgba, delta_e: float = 3.0) -> int:
    """How many pixels of ``image`` (H, W, 3; 0..255) are within ``delta_e`` of ``rgba`` (0..1)."""
    from sim import palette

    colours, counts = np.unique(image.reshape(-1, 3), axis=0, return_counts=True)
    return int(sum(n for c, n in zip(colours, counts) if palette.distance(c / 255.0, rgba) <= delta_e))


@pytest.mark.parametrize("lit", [True, False], ids=["scene's light", "default light"])
def test_the_scene_s_obstacles_are_in_the_legend_in_the_colour_they_are_drawn(tmp_path, lit):
    """The legend's obstacle swatch is the colour the walls' tops show under the scene's lights, and
    the decorations are divided by the same gain: in a user scene under the default light they showed
    about a third darker than their swatches (the gain of the built-in scenes' lights was assumed)."""
    from viz.decorations import frame_legend
    from viz.scenery import scenery_legend, top_light_gain

    scene = ROOM if lit else ROOM.replace('    <light pos="5 5 8" dir="0 0 -1" directional="true"/>\n', "")
    write_scene(tmp_path, scene)
    frame, view, image = _render(load(str(write_scenario(tmp_path, ROOM_SCENARIO.format(width=800, height=480)))))
    model = view.world.model
    # By hand: MuJoCo's default headlight (ambient 0.1, diffuse 0.4) and a light of diffuse 0.7 straight
    # down; tether's default light: headlight 0.3 + 0.3, sun 0.35.
    np.testing.assert_allclose(top_light_gain(model), [1.2] * 3 if lit else [0.95] * 3, atol=1e-6)
    ((label, swatch),) = scenery_legend(model)
    assert label == "obstacle"  # geoms coloured without a material
    # By hand: grey 0.5 lit, plus (scene's light) a geom's default specular 0.5 times the headlight's 0.5 and
    # the light's 0.3 seen straight from above; tether's default light has no specular.
    np.testing.assert_allclose(swatch[:3], min(1.0, 0.5 * 1.2 + 0.5 * 0.8) if lit else 0.5 * 0.95, atol=1e-6)
    # The video's swatch: the highlight as its camera sees it at the centre of the first wall's top (MuJoCo's
    # viewer is local: a highlight fades towards the picture's edges); without a highlight, the same.
    ((_, seen),) = view.scenery
    assert (label, tuple(seen)) in [(name, tuple(c)) for name, c in frame_legend(frame, (), view.scenery)]
    if not lit:
        np.testing.assert_allclose(seen, swatch)
    scene_part = image[:, : view.scene_width]
    # The four walls' tops, 0.2 m wide, all in the swatch's colour without a highlight; with one, around
    # the centre of the first wall's top.
    assert _pixels_near(scene_part, seen, 3.0) > (2000 if not lit else 300)
    # A decoration's colour, divided by the gain and lit, comes back as the palette's.
    from viz.video import _lit

    colour = np.array([0.0, 0.62, 0.45, 1.0])
    np.testing.assert_allclose(np.minimum(1.0, _lit(colour, top_light_gain(model))[:3] * top_light_gain(model)),
                               colour[:3], atol=1e-6)


def test_the_office_s_walls_are_named_and_drawn_in_their_swatch():
    from viz.scenery import scenery_legend

    frame, view, image = _render(load("connected-office", duration_s=0.1))
    ((label, swatch),) = scenery_legend(view.world.model)
    assert label == "wall"
    assert _pixels_near(image[:, : view.scene_width], swatch) > 3000  # the interior walls' and the block's tops


def test_the_panel_drawn_from_its_cached_legend_is_the_panel_drawn_afresh():
    from viz import video

    legend = [("prime traveler", (0.84, 0.37, 0.0, 1.0)), ("anchor", (0.8, 0.47, 0.65, 1.0))]
    side_panel(540, 420, ["t = 1.0 s", "links 9"], legend)  # lays out and keeps the legend
    cached = side_panel(540, 420, ["t = 2.0 s", "links 8"], legend)
    video._PANELS.clear()
    np.testing.assert_array_equal(cached, side_panel(540, 420, ["t = 2.0 s", "links 8"], legend))


def test_a_close_up_is_drawn_while_the_robots_are_too_close_to_tell_apart():
    from viz.video import CLOSEUP_BELOW_PX, CLOSEUP_MIN_HALF_M, closeup_view, emptiest_corner

    # By hand: a 4 x 2 grid 0.12 m apart seen at 0.02 m a pixel is 6 px apart: a close-up of its extent.
    grid = np.array([(x, y) for y in (0.0, 0.12) for x in (0.0, 0.12, 0.24, 0.36)])
    centre, half, spacing = closeup_view(grid, 0.02)
    np.testing.assert_allclose(centre, (0.18, 0.06))
    assert half == pytest.approx(max(1.6 * 0.36 / 2, CLOSEUP_MIN_HALF_M)) and spacing == pytest.approx(0.12)
    assert closeup_view(grid * 2, 0.02) is None  # 12 px apart: told apart, no close-up
    assert closeup_view(grid, 0.12 / CLOSEUP_BELOW_PX) is None  # exactly at the threshold
    assert closeup_view(grid[:1], 0.02) is None
    # The corner holding the fewest points; bottom-right among equals.
    points = np.array([[5, 5], [95, 95], [95, 5], [96, 6]])
    assert emptiest_corner(points, 100, 100, 20) == (80, 0)  # bottom-left: empty
    assert emptiest_corner(np.zeros((0, 2)), 100, 100, 20) == (80, 80)


def test_the_intermittent_start_cluster_gets_a_close_up_and_the_office_s_quadrotors_none():
    from viz.video import CLOSEUP_BORDER_RGB, CLOSEUP_SIDE_SHARE

    for name, expected in (("intermittent-8", True), ("connected-office", False)):
        frame, view, image = _render(load(name, duration_s=0.1))
        assert (view._closeup is not None) == expected, name
        side = int(view.config.height * CLOSEUP_SIDE_SHARE) // 2 * 2
        scene = image[:, : view.scene_width]
        corners = [scene[r:r + side, c:c + side] for r in (0, scene.shape[0] - side)
                   for c in (0, scene.shape[1] - side)]
        # The close-up's light border runs along one corner square's edges.
        bordered = [bool(np.all(corner[:, 0] == CLOSEUP_BORDER_RGB) and np.all(corner[0, :] == CLOSEUP_BORDER_RGB))
                    for corner in corners]
        assert any(bordered) == expected, name
        if expected:  # ... and inside it the robots, large: each one's team colour (its halo, lit) over many pixels
            inset = corners[bordered.index(True)]
            for colour in np.unique(frame.commands.decorations.robot_colors, axis=0):
                assert _pixels_near(inset, colour, 15.0) > 100, colour
