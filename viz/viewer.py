"""``tether view SCENARIO``: MuJoCo's own interactive viewer on a running simulation.

:func:`view` opens ``mujoco.viewer.launch_passive`` on the world of a
:class:`sim.loop.Simulation` and ticks it, paced to real time (``speed``
times it; 0: as fast as the machine goes). Each tick the viewer's user scene
(``handle.user_scn``) gets the same decorations as the video
(:func:`viz.video.draw_decorations`: links on the palette's ramp by weight
or delivery, references, robot halos in role / team colours, planned
paths, meeting points, target estimates, markers), a band at the top-left
with the video's overlay line, the state and the real-time factor reached,
and the legend at the bottom-right. The default camera looks straight down,
the walls drawn translucent (:func:`see_through_walls`) so none hides a room,
the floor in the window's left part, so the legend sits beside it. With no
window manager (Xvfb) the window is made the screen's size
(:func:`fill_screen_without_window_manager`). The viewer only reads the simulation (as the video does), except
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
from viz.scenery import scenery_legend, top_light_gain
from viz.video import TOP_MARGIN, DecorationCanvas, draw_decorations, overlay_text, side_panel

KEY_SPACE = 32  # GLFW key codes, as MuJoCo's viewer hands them to key_callback
KEY_RIGHT = 262
VIEW_PIXELS = 700  # the marker scale assumes the floor spans about this many pixels of the window
FLOOR_SHARE = 0.62  # the default camera puts the floor in this share of the window's width, the legend beside
VIEW_MARGIN = 1.06  # ... with 6 % around it
SLOW_SHARE = 0.9  # the band says the machine cannot keep up below this share of the asked speed
PACE_WINDOW_S = 2.0  # the real-time factor is measured over this much wall time
DEFAULT_ASPECT = 4 / 3  # the window's aspect when the viewer does not tell it yet
VIEW_FOVY_DEG = 15.0  # the viewer's vertical field of view (MuJoCo's default 45)


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


class UserScene(DecorationCanvas):
    """The viewer's ``user_scn`` as a canvas for :func:`viz.video.draw_decorations`."""

    def __init__(self, world, scene: mujoco.MjvScene):
        self.world = world
        self.scene = scene
        self.light_gain = top_light_gain(world.model)
        lo, hi = world.bounds
        self.metres_per_px = TOP_MARGIN * float(max(hi[0] - lo[0], hi[1] - lo[1])) / VIEW_PIXELS

    def mjv_scene(self) -> mujoco.MjvScene:
        return self.scene

    def draw(self, frame: Frame) -> None:
        self.scene.ngeom = 0
        draw_decorations(self, frame)


LEGEND_HEIGHT_SHARE = 0.8  # the legend panel: the window's right part beside the floor, this share of its height


def legend_panel(frame: Frame, robot_kinds, scenery, viewport) -> tuple | None:
    """(MjrRect, image) of the legend beside the floor, at the window's right below the band: the
    pictures' one legend (:func:`viz.decorations.frame_legend`), a swatch and a label an entry, drawn
    as the video's side panel is; None while the window is too small to hold it."""
    width = int(viewport.width * (1.0 - FLOOR_SHARE))
    height = int(viewport.height * LEGEND_HEIGHT_SHARE)
    if width < 80 or height < 120:
        return None
    image = side_panel(height, width, [], frame_legend(frame, robot_kinds, scenery))
    return mujoco.MjrRect(viewport.left + viewport.width - width, viewport.bottom, width, height), image


def pace_text(real_time_factor: float | None, speed: float) -> str:
    """The band's pace: the real-time factor reached, and whether it falls short of the one asked."""
    if real_time_factor is None:
        return "x? of real time"
    text = f"x{real_time_factor:.2f} of real time"
    if speed > 0 and real_time_factor < SLOW_SHARE * speed:
        text += f" (asked x{speed:g}: this machine cannot keep up)"
    return text


def _texts(frame: Frame, status: str, control: ViewerControl, robot_kinds=(), real_time_factor: float | None = None,
           speed: float = 1.0) -> list:
    state = status or ("paused (Space resumes, Right arrow steps)" if control.paused else
                       f"running at {pace_text(real_time_factor, speed)} (Space pauses)")
    return [(mujoco.mjtFontScale.mjFONTSCALE_150, mujoco.mjtGridPos.mjGRID_TOPLEFT, overlay_text(frame), state)]


def _show_legend(handle, frame: Frame, robot_kinds, scenery, shown):
    """Overlay the legend panel when it or the window's size changed since ``shown`` (its key);
    returns the key now shown."""
    viewport = getattr(handle, "viewport", None)
    if viewport is None or not hasattr(handle, "set_images"):
        return shown
    legend = frame_legend(frame, robot_kinds, scenery)
    key = (viewport.width, viewport.height, tuple(label for label, _ in legend))
    if key != shown:
        panel = legend_panel(frame, robot_kinds, scenery, viewport)
        if panel is None:
            handle.clear_images()
        else:
            handle.set_images(panel)
    return key


def _aspect(handle) -> float:
    viewport = getattr(handle, "viewport", None)
    return viewport.width / viewport.height if viewport is not None and viewport.height else DEFAULT_ASPECT


def _camera_pose(cam) -> tuple:
    return (*np.round(cam.lookat, 6), round(float(cam.distance), 6), float(cam.elevation), float(cam.azimuth))


WALL_ALPHA = 0.3  # the viewer draws tall static boxes (walls) this opaque: the rooms show through them
WALL_MIN_HEIGHT_M = 1.0  # ... boxes of the scene's group 0 at least this tall


def see_through_walls(model: mujoco.MjModel) -> int:
    """Give the scene's walls (group-0 boxes at least ``WALL_MIN_HEIGHT_M`` tall) their own colour
    at ``WALL_ALPHA`` in the viewer's model, so that a wall seen from above leaning over a room
    hides none of it; returns how many. Colour only: physics never reads it, and a ray (the
    sensing's line of sight) skips only geoms of alpha 0, which none becomes."""
    walls = [g for g in range(model.ngeom) if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_BOX
             and model.geom_group[g] == 0 and 2 * model.geom_size[g, 2] >= WALL_MIN_HEIGHT_M]
    for g in walls:
        material = model.geom_matid[g]
        rgba = np.array(model.mat_rgba[material] if material >= 0 else model.geom_rgba[g], dtype=float)
        if rgba[3] <= 0:  # invisible (a ceiling): stays so
            continue
        rgba[3] = min(rgba[3], WALL_ALPHA)
        model.geom_rgba[g] = rgba  # an explicit rgba wins over the material's, which keeps naming the legend's entry
    return len(walls)


def default_camera(cam, bounds, fovy_deg: float, aspect: float) -> None:
    """Look straight down on the floor (walls show their tops and hide no room), the whole floor
    in view at the window's left ``FLOOR_SHARE`` of its width, so the legend at the right sits
    beside the scene, not over it."""
    lo, hi = (np.asarray(b, dtype=float) for b in bounds)
    width, depth = float(hi[0] - lo[0]), float(hi[1] - lo[1])
    tan = np.tan(np.radians(fovy_deg) / 2)
    # Visible floor depth (m) at the floor: the depth, or what makes the width fit FLOOR_SHARE of the view.
    visible_depth = VIEW_MARGIN * max(depth, width / (FLOOR_SHARE * max(aspect, 1e-3)))
    visible_width = visible_depth * aspect
    cam.type = mujoco.mjtCamera.mjCAMERA_FREE
    cam.lookat[:] = (lo[0] + visible_width / 2 - (VIEW_MARGIN - 1) * width / 2, (lo[1] + hi[1]) / 2, lo[2])
    # Framed at the scene's top, not its floor: the tops of the outer walls, nearer the camera, reach
    # farther out in the picture than the floor does (they ran off the window's edges).
    cam.distance = visible_depth / (2 * tan) + max(float(hi[2] - lo[2]), 0.0)
    cam.elevation, cam.azimuth = -90.0, 90.0


def fill_screen_without_window_manager(timeout_s: float = 3.0) -> bool:
    """With no window manager (Xvfb, a bare X server) nobody sizes or places windows, and GLFW
    opens the viewer's at two thirds of the screen in its top-left corner: make this process's
    window (its ``_NET_WM_PID``) the screen's size. Under a window manager the window is the
    user's to size and nothing changes. Returns whether it resized one (X11 through libX11)."""
    import ctypes
    import ctypes.util

    if not os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"):
        return False
    name = ctypes.util.find_library("X11")
    if name is None:
        return False
    x = ctypes.CDLL(name)
    ulong, voidp = ctypes.c_ulong, ctypes.c_void_p
    x.XOpenDisplay.restype, x.XOpenDisplay.argtypes = voidp, [ctypes.c_char_p]
    x.XDefaultRootWindow.restype, x.XDefaultRootWindow.argtypes = ulong, [voidp]
    x.XDefaultScreen.argtypes = [voidp]
    x.XDisplayWidth.argtypes = x.XDisplayHeight.argtypes = [voidp, ctypes.c_int]
    x.XInternAtom.restype, x.XInternAtom.argtypes = ulong, [voidp, ctypes.c_char_p, ctypes.c_int]
    x.XGetWindowProperty.argtypes = [voidp, ulong, ulong, ctypes.c_long, ctypes.c_long, ctypes.c_int, ulong,
                                     ctypes.POINTER(ulong), ctypes.POINTER(ctypes.c_int), ctypes.POINTER(ulong),
                                     ctypes.POINTER(ulong), ctypes.POINTER(voidp)]
    x.XQueryTree.argtypes = [voidp, ulong, ctypes.POINTER(ulong), ctypes.POINTER(ulong),
                             ctypes.POINTER(ctypes.POINTER(ulong)), ctypes.POINTER(ctypes.c_uint)]
    x.XMoveResizeWindow.argtypes = [voidp, ulong, ctypes.c_int, ctypes.c_int, ctypes.c_uint, ctypes.c_uint]
    x.XFree.argtypes, x.XFlush.argtypes, x.XCloseDisplay.argtypes = [voidp], [voidp], [voidp]

    def first_long(display, window, atom, kind) -> int | None:
        """The first 32-bit item of ``window``'s property ``atom`` (of type ``kind``), or None."""
        actual, fmt, count, after, data = ulong(), ctypes.c_int(), ulong(), ulong(), voidp()
        if atom == 0 or x.XGetWindowProperty(display, window, atom, 0, 1, 0, kind, ctypes.byref(actual),
                                             ctypes.byref(fmt), ctypes.byref(count), ctypes.byref(after),
                                             ctypes.byref(data)) != 0:
            return None
        try:
            return int(ctypes.cast(data, ctypes.POINTER(ctypes.c_long))[0]) if count.value and data else None
        finally:
            if data:
                x.XFree(data)

    display = x.XOpenDisplay(None)
    if not display:
        return False
    try:
        root = x.XDefaultRootWindow(display)
        xa_window, xa_cardinal = 33, 6  # the predefined atoms WINDOW and CARDINAL
        if first_long(display, root, x.XInternAtom(display, b"_NET_SUPPORTING_WM_CHECK", 1), xa_window) is not None:
            return False  # a window manager: the window is the user's to size
        pid_atom = x.XInternAtom(display, b"_NET_WM_PID", 1)
        screen = x.XDefaultScreen(display)
        width, height = x.XDisplayWidth(display, screen), x.XDisplayHeight(display, screen)
        deadline = time.monotonic() + timeout_s
        while True:
            root_return, parent, kids, count = ulong(), ulong(), ctypes.POINTER(ulong)(), ctypes.c_uint()
            mine = []
            if x.XQueryTree(display, root, ctypes.byref(root_return), ctypes.byref(parent), ctypes.byref(kids),
                            ctypes.byref(count)):
                mine = [kids[i] for i in range(count.value)
                        if first_long(display, kids[i], pid_atom, xa_cardinal) == os.getpid()]
                if kids:
                    x.XFree(kids)
            if mine or time.monotonic() > deadline:
                break
            time.sleep(0.05)
            pid_atom = pid_atom or x.XInternAtom(display, b"_NET_WM_PID", 1)
        for window in mine:
            x.XMoveResizeWindow(display, window, 0, 0, width, height)
        x.XFlush(display)
        return bool(mine)
    finally:
        x.XCloseDisplay(display)


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
    # A narrow field of view from farther away: full-height walls seen from above lean over the rooms
    # far less (the free camera's fovy is a picture setting; physics, sensing and radio never read it).
    sim.world.model.vis.global_.fovy = VIEW_FOVY_DEG
    see_through_walls(sim.world.model)
    scenery = scenery_legend(sim.world.model)
    control = control or ViewerControl()
    own_window = launch is None
    launch = launch or mujoco.viewer.launch_passive
    handle = launch(sim.world.model, sim.world.data, key_callback=control.key,
                    show_left_ui=False, show_right_ui=False)
    if own_window:
        fill_screen_without_window_manager()
    n_ticks = int(round(scenario.duration_s / sim.dt))
    status = ""
    try:
        fovy = float(sim.world.model.vis.global_.fovy)
        with handle.lock():
            framed = [_aspect(handle), None]  # the aspect framed for, and the camera as set (until the user moves it)
            default_camera(handle.cam, sim.world.bounds, fovy, framed[0])
            framed[1] = _camera_pose(handle.cam)
        kinds = sim.world.robot_kinds
        pace: list[tuple[float, float]] = []  # (wall, sim) samples of the last PACE_WINDOW_S
        rtf = None
        scene = UserScene(sim.world, handle.user_scn)
        frame = None
        shown_legend = None
        anchor_wall, anchor_sim = time.perf_counter(), sim.time_s
        while handle.is_running() and not status:
            if not control.take_tick():
                anchor_wall, anchor_sim = time.perf_counter(), sim.time_s
                if frame is not None:
                    handle.set_texts(_texts(frame, status, control, kinds, None, speed))
                    shown_legend = _show_legend(handle, frame, kinds, scenery, shown_legend)
                pace.clear()
                handle.sync()
                time.sleep(0.02)
                continue
            with handle.lock():
                frame, healthy = sim.tick()
                scene.draw(frame)
                aspect = _aspect(handle)
                # The window's size is known once it is drawn: frame again for it, unless the user moved the camera.
                if abs(aspect - framed[0]) > 0.02 and _camera_pose(handle.cam) == framed[1]:
                    default_camera(handle.cam, sim.world.bounds, fovy, aspect)
                    framed[:] = [aspect, _camera_pose(handle.cam)]
            if not healthy:
                status = Status.DIVERGED
            elif sim.strategy.finished or sim.tick_count >= n_ticks:
                status, _ = end_of_run(sim.strategy, sim.strategy.finished, scenario.duration_s, sim.time_s)
            now = time.perf_counter()
            pace.append((now, sim.time_s))
            while now - pace[0][0] > PACE_WINDOW_S:
                pace.pop(0)
            if now - pace[0][0] > 0.25:
                rtf = (pace[-1][1] - pace[0][1]) / (now - pace[0][0])
            handle.set_texts(_texts(frame, f"{status}: close the window to quit" if status else "", control, kinds,
                                    rtf, speed))
            shown_legend = _show_legend(handle, frame, kinds, scenery, shown_legend)
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
            if frame is not None:  # the window may be resized while it stays open
                shown_legend = _show_legend(handle, frame, kinds, scenery, shown_legend)
            handle.sync()
            time.sleep(0.05)
    finally:
        handle.close()
    return status or Status.STOPPED
