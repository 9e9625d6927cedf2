"""`tether view`: MuJoCo's own viewer on a running simulation, under a real
X server (Debian's Xvfb, started here on a free display; skipped without it).
A few ticks, then the screen is read back: not blank, and the user geometry
(the ground robots' halos in the palette's bluish green) is drawn."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from viz.viewer import KEY_RIGHT, KEY_SPACE, ViewerControl

XVFB = shutil.which("Xvfb")
SCREEN = (1024, 768)


def test_space_pauses_and_right_arrow_steps_one_tick_while_paused():
    control = ViewerControl()
    assert control.take_tick() and control.take_tick()  # running
    control.key(KEY_SPACE)
    assert not control.take_tick()
    control.key(KEY_RIGHT)
    control.key(KEY_RIGHT)
    assert control.take_tick() and control.take_tick() and not control.take_tick()  # two steps, then held
    control.key(KEY_SPACE)
    assert control.take_tick()
    control.key(KEY_RIGHT)  # ignored while running
    control.key(KEY_SPACE)
    assert not control.take_tick()


@pytest.fixture
def display():
    if XVFB is None:
        pytest.skip("Xvfb is not installed (Debian package xvfb: run `make system-deps`)")
    for number in range(90, 140):
        if not Path(f"/tmp/.X11-unix/X{number}").exists() and not Path(f"/tmp/.X{number}-lock").exists():
            break
    else:
        pytest.skip("no free X display number")
    server = subprocess.Popen([XVFB, f":{number}", "-screen", "0", f"{SCREEN[0]}x{SCREEN[1]}x24", "-nolisten", "tcp"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 20
    while not Path(f"/tmp/.X11-unix/X{number}").exists():
        if server.poll() is not None or time.monotonic() > deadline:
            server.kill()
            pytest.skip("Xvfb did not start")
        time.sleep(0.1)
    yield f":{number}"
    server.terminate()
    server.wait(timeout=10)


def _swatches_shown(image) -> bool:
    """The legend's swatches of the hover robots' kinds, in the palette's colours (the panel is not lit)."""
    from sim import palette

    return all((np.abs(image - np.asarray(palette.rgb8(palette.KIND[kind]))).max(axis=2) <= 2).sum() > 50
               for kind in ("quadrotor", "ground"))


def test_tether_view_draws_the_running_simulation_with_its_links(display, tmp_path):
    from PIL import ImageGrab

    env = {**os.environ, "DISPLAY": display, "MUJOCO_GL": "glfw", "OPENBLAS_NUM_THREADS": "1"}
    env.pop("PYOPENGL_PLATFORM", None)
    proc = subprocess.Popen([sys.executable, "-m", "tether.cli", "view", "hover", "--duration", "0.05", "--speed", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
    try:
        lines = []
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline:  # the run's 5 ticks done: the window stays open on the last state
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if line.startswith("completed"):
                break
        stderr = proc.stderr.read() if proc.poll() is not None else ""
        assert any(line.startswith("completed: hover, t = 0.05 s") for line in lines), (lines, stderr)
        # A few more frames of the viewer's render loop: the window takes the screen's size, and the
        # legend is drawn again for it.
        wait_until = time.monotonic() + 15
        while True:
            time.sleep(0.5)
            image = np.asarray(ImageGrab.grab(xdisplay=display).convert("RGB"), dtype=int)
            if _swatches_shown(image[:, int(0.6 * SCREEN[0]):]) or time.monotonic() > wait_until:
                break
        ImageGrab.grab(xdisplay=display).save(tmp_path / "viewer.png")
        assert proc.poll() is None  # still open until the window is closed
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
    assert image.shape[:2] == (SCREEN[1], SCREEN[0])
    assert image.std() > 20  # not blank
    # The ground robots' halos are user geometry in the palette's bluish green (lit: shades of it).
    r, g, b = image[..., 0], image[..., 1], image[..., 2]
    green = (g > 100) & (g > r + 60) & (b > r + 30) & (g > b)
    assert green.sum() > 30
    # ... and the scene itself: the office's walls and floor fill much of the window.
    assert (image.sum(axis=2) > 60).mean() > 0.15
    # With no window manager the window is the screen's size (GLFW opened it at two thirds, top-left):
    # the floor reaches below two thirds of its height, and the legend its right third.
    bottom = image[int(0.8 * SCREEN[1]):int(0.85 * SCREEN[1]), : SCREEN[0] // 2].sum(axis=2)
    assert (bottom > 60).mean() > 0.5
    legend = image[:, int(0.6 * SCREEN[0]):]  # the window right of the floor (FLOOR_SHARE)
    assert (legend.sum(axis=2) > 300).sum() > 200  # the legend's white text
    assert _swatches_shown(legend)  # ... and its swatches


def test_bad_input_and_no_display_exit_2_with_one_line(monkeypatch, capsys):
    from tether.cli import main

    monkeypatch.setenv("DISPLAY", ":0")
    assert main(["view", "hover", "--set", "strategy.speed_mps=99"]) == 2
    assert capsys.readouterr().err.strip().startswith("tether: error: strategy.speed_mps: must be in")
    monkeypatch.delenv("DISPLAY")
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert main(["view", "hover"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "needs a display" in err[0] and "tether run --video" in err[0]


def test_the_default_camera_looks_down_on_the_floor_and_leaves_the_right_to_the_legend():
    from types import SimpleNamespace

    from viz.viewer import FLOOR_SHARE, default_camera, pace_text

    cam = SimpleNamespace(lookat=np.zeros(3), distance=0.0, elevation=0.0, azimuth=0.0, type=None)
    default_camera(cam, ((0, 0, 0), (10, 10, 5)), 45.0, 16 / 9)
    assert cam.elevation == -90.0 and cam.azimuth == 90.0  # straight down: walls hide no room
    visible_depth = 2 * cam.distance * np.tan(np.radians(22.5))
    visible_width = visible_depth * 16 / 9
    left = cam.lookat[0] - visible_width / 2
    assert left <= 0.0 and 10.0 <= left + FLOOR_SHARE * visible_width * 1.07  # the floor in the left share
    assert visible_depth >= 10.0
    assert pace_text(0.04, 1.0).startswith("x0.04 of real time (asked x1")
    assert pace_text(1.0, 1.0) == "x1.00 of real time"


def test_the_text_legends_name_every_role_and_team_colour_distinctly():
    """The recording's legend is text: each colour is named, and no two roles or teams by one name."""
    from controllers.connectivity.strategy import LEGEND
    from controllers.intermittent.runtime import TEAM_COLORS
    from sim.palette import colour_name

    roles = [colour_name(rgba) for _, rgba in LEGEND[:4]]
    assert roles == ["vermillion", "blue", "reddish purple", "sky blue"]
    teams = [colour_name(rgba) for rgba in TEAM_COLORS]
    assert len(set(teams)) == len(teams)


def test_a_display_that_does_not_exist_is_one_line_and_leaves_no_log(tmp_path):
    """DISPLAY names a display nobody serves: one line, exit 2, no GLFW warning, no MUJOCO_LOG.TXT."""
    env = {**os.environ, "DISPLAY": ":97", "PYTHONPATH": str(Path(__file__).resolve().parents[1])}
    env.pop("WAYLAND_DISPLAY", None)
    proc = subprocess.run([sys.executable, "-m", "tether.cli", "view", "hover"], cwd=tmp_path, env=env,
                          capture_output=True, text=True, timeout=120)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1, proc.stderr
    assert "cannot open the display ':97'" in lines[0] and "tether run --video" in lines[0]
    assert not list(tmp_path.iterdir())


def test_the_viewer_s_walls_are_translucent_and_still_block_line_of_sight():
    import mujoco

    from sim.scenario import load
    from tether.runner import build_simulation
    from viz.viewer import WALL_ALPHA, see_through_walls

    sim = build_simulation(load("connected-office", duration_s=0.1))
    model, data = sim.world.model, sim.world.data
    start, across = np.array([2.0, 3.0, 1.0]), np.array([0.0, 1.0, 0.0])  # through wall_mid_west at y = 5
    geomid = np.zeros(1, dtype=np.int32)
    before = mujoco.mj_ray(model, data, start, across, np.array([1, 0, 0, 0, 0, 0], np.uint8), 1, -1, geomid)
    assert see_through_walls(model) >= 4
    wall = model.geom("wall_mid_west").id
    assert model.geom_rgba[wall, 3] == WALL_ALPHA
    from viz.scenery import scenery_legend

    assert [label for label, _ in scenery_legend(model)] == ["wall"]  # the material still names it
    after = mujoco.mj_ray(model, data, start, across, np.array([1, 0, 0, 0, 0, 0], np.uint8), 1, -1, geomid)
    assert after == before and geomid[0] == wall  # the sensing's rays see the same wall
