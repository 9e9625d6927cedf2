"""``tether view SCENARIO``: MuJoCo's own interactive viewer on a running simulation.

:func:`view` opens ``mujoco.viewer.launch_passive`` on the world of a
:class:`sim.loop.Simulation` and ticks it, paced to real time (``speed``
times it; 0: as fast as the machine goes). Each tick the viewer's user scene
(``handle.user_scn``) gets the same decorations as the video
(:func:`viz.video.draw_decorations`: links coloured by weight, references,
robot halos in role / team colours, planned paths, meeting points, target
estimates, markers) and a text box with the video's overlay line and the
legend. The viewer only reads the simulation (as the video does), except
that MuJoCo's mouse perturbation (double-click a body, Ctrl + drag) pushes
bodies, as in any MuJoCo viewer.

Keys (besides the viewer's own: mouse to orbit / pan / zoom, Tab and
Shift-Tab for its panels, Escape to release a tracked camera):
  Space         pause / resume the simulation
  Right arrow   one control tick while paused
  F1            the viewer's help
When the run ends (duration reached, mission finished, or diverged) the
window stays open on the last state until it is closed.

MuJoCo's viewer needs a display (GLFW): on a headless machine use
``tether run --video`` or ``tether tune`` instead.
"""

from __future__ import annotations

import os
import sys
import threading
import time
from typing import Callable

import mujoco
import numpy as np

from sim.loop import Simulation, end_of_run
from sim.observers import Frame
from sim.scenario import Scenario
from sim.strategy import Status
from viz.decorations import frame_legend
from viz.video import TOP_MARGIN, add_capsule, add_sphere, draw_decorations, overlay_text

KEY_SPACE = 32  # GLFW key codes, as MuJoCo's viewer hands them to key_callback
KEY_RIGHT = 262
VIEW_PIXELS = 900  # the marker scale assumes the floor spans about this many pixels of the window


class ViewerControl:
    """Pause and single-step from the viewer's keys (called on the viewer's
    thread; the simulation thread reads the flags)."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.paused = False
        self._steps = 0

    def key(self, keycode: int) -> None:
        with self._lock:
            if keycode == KEY_SPACE:
                self.paused = not self.paused
            elif keycode == KEY_RIGHT and self.paused:
                self._steps += 1

    def take_tick(self) -> bool:
        """Whether the simulation may advance one tick now."""
        with self._lock:
            if not self.paused:
                return True
            if self._steps:
                self._steps -= 1
                return True
            return False


class UserScene:
    """The viewer's ``user_scn`` as a canvas for :func:`viz.video.draw_decorations`."""

    def __init__(self, world, scene: mujoco.MjvScene):
        self.world = world
        self.scene = scene
        lo, hi = world.bounds
        self.metres_per_px = TOP_MARGIN * float(max(hi[0] - lo[0], hi[1] - lo[1])) / VIEW_PIXELS

    def at_least(self, size_m: float, pixels: float) -> float:
        return max(size_m, pixels * self.metres_per_px)

    def _add_capsule(self, a, b, width, rgba) -> None:
        add_capsule(self.scene, a, b, width, rgba)

    def _add_sphere(self, p, radius, rgba) -> None:
        add_sphere(self.scene, p, radius, rgba)

    def draw(self, frame: Frame) -> None:
        self.scene.ngeom = 0
        draw_decorations(self, frame)


def _legend_text(frame: Frame) -> str:
    items = frame_legend(frame)
    return "\n".join(f"{label}: {colour_name(rgba)}" for label, rgba in items)


COLOUR_NAMES = {  # the viewer's text is one colour: the legend names each colour instead
    "red": (0.9, 0.2, 0.15), "orange": (1.0, 0.6, 0.1), "yellow": (0.95, 0.8, 0.15), "olive": (0.55, 0.55, 0.2),
    "green": (0.15, 0.7, 0.3), "turquoise": (0.0, 0.9, 0.8), "teal": (0.1, 0.6, 0.65), "blue": (0.2, 0.4, 1.0),
    "purple": (0.6, 0.3, 0.8), "pink": (0.9, 0.4, 0.7), "magenta": (0.95, 0.2, 0.6), "grey": (0.55, 0.55, 0.6),
    "dark grey": (0.2, 0.2, 0.25), "white": (1.0, 1.0, 1.0), "black": (0.0, 0.0, 0.0),
}


def colour_name(rgba) -> str:
    """The nearest of :data:`COLOUR_NAMES` to ``rgba`` (0..1)."""
    rgb = np.asarray(list(rgba)[:3], dtype=float)
    return min(COLOUR_NAMES, key=lambda name: float(np.sum((np.array(COLOUR_NAMES[name]) - rgb) ** 2)))


def _texts(frame: Frame, status: str, control: ViewerControl) -> list:
    state = status or ("paused (Space resumes, Right arrow steps)" if control.paused else "running (Space pauses)")
    texts = [(mujoco.mjtFontScale.mjFONTSCALE_150, mujoco.mjtGridPos.mjGRID_TOPLEFT, overlay_text(frame), state)]
    legend = _legend_text(frame)
    if legend:
        texts.append((mujoco.mjtFontScale.mjFONTSCALE_100, mujoco.mjtGridPos.mjGRID_BOTTOMLEFT, "colours", legend))
    return texts


def needs_display() -> str | None:
    """Why the viewer cannot open here (no display), or None."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return "MuJoCo's viewer needs a display (DISPLAY is not set); use 'tether run --video' or 'tether tune'"
    return _display_unreachable()


def _display_unreachable() -> str | None:
    """Why GLFW (the viewer's window library) cannot open the display named, or None: asked
    here, quietly, so that a display that does not exist is one line, not GLFW's warning,
    MuJoCo's error and its MUJOCO_LOG.TXT."""
    import warnings

    try:
        import glfw
    except ImportError:
        return None  # mujoco.viewer will say it
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            opened = glfw.init()
        except Exception:  # noqa: BLE001  (GLFW raises or warns, depending on its error reporting)
            opened = False
        if opened:
            glfw.terminate()
            return None
    display = os.environ.get("WAYLAND_DISPLAY") or os.environ.get("DISPLAY")
    reason = str(caught[-1].message) if caught else "GLFW could not initialise"
    return (f"MuJoCo's viewer cannot open the display {display!r} ({reason}); use 'tether run --video' "
            "or 'tether tune'")


def view(scenario: Scenario, make_simulation: Callable[[Scenario], Simulation], speed: float = 1.0,
         control: ViewerControl | None = None, on_tick: Callable[[Simulation, Frame], None] | None = None, keep_open: bool = True,
         launch: Callable | None = None) -> str:
    """Run ``scenario`` in MuJoCo's viewer until its duration, the end of its
    mission or the window closes; returns the :class:`sim.strategy.Status`
    (completed or time limit as a run would end, diverged, or stopped: the
    window closed before the run ended). ``on_tick(sim, frame)`` after each
    tick (tests); ``keep_open``: leave the window open on the last state
    until the user closes it."""
    import mujoco.viewer

    sim = make_simulation(scenario)
    control = control or ViewerControl()
    launch = launch or mujoco.viewer.launch_passive
    handle = launch(sim.world.model, sim.world.data, key_callback=control.key,
                    show_left_ui=False, show_right_ui=False)
    n_ticks = int(round(scenario.duration_s / sim.dt))
    status = ""
    try:
        with handle.lock():
            lo, hi = sim.world.bounds
            handle.cam.lookat[:] = (lo + hi) / 2
            handle.cam.distance = 1.2 * float(np.linalg.norm(hi[:2] - lo[:2]))
            handle.cam.elevation, handle.cam.azimuth = -60.0, 90.0
        scene = UserScene(sim.world, handle.user_scn)
        frame = None
        anchor_wall, anchor_sim = time.perf_counter(), sim.time_s
        while handle.is_running() and not status:
            if not control.take_tick():
                anchor_wall, anchor_sim = time.perf_counter(), sim.time_s
                if frame is not None:
                    handle.set_texts(_texts(frame, status, control))
                handle.sync()
                time.sleep(0.02)
                continue
            with handle.lock():
                frame, healthy = sim.tick()
                scene.draw(frame)
            if not healthy:
                status = Status.DIVERGED
            elif sim.strategy.finished or sim.tick_count >= n_ticks:
                status, _ = end_of_run(sim.strategy, sim.strategy.finished, scenario.duration_s, sim.time_s)
            handle.set_texts(_texts(frame, f"{status}: close the window to quit" if status else "", control))
            handle.sync()
            if on_tick is not None:
                on_tick(sim, frame)
            if speed > 0:  # real-time pacing (or `speed` times it)
                ahead = (sim.time_s - anchor_sim) / speed - (time.perf_counter() - anchor_wall)
                if ahead > 0:
                    time.sleep(ahead)
                elif ahead < -0.5:  # too far behind: stop catching up
                    anchor_wall, anchor_sim = time.perf_counter(), sim.time_s
        if status:
            print(f"{status}: {scenario.name}, t = {sim.time_s:.2f} s; close the viewer window to quit", flush=True)
        while keep_open and handle.is_running():
            handle.sync()
            time.sleep(0.05)
    finally:
        handle.close()
    return status or Status.STOPPED
