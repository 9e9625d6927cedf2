"""Offscreen video through MuJoCo's renderer (EGL), streamed to ffmpeg.

An observer: it draws the tick's frame (its MuJoCo state ``frame.state``
and its decorations), never writes to the simulation. Frames are taken at
the video fps in sim time; a renderer process draws them and writes them
one by one to the encoder (an ffmpeg process fed through a pipe; in a long
video helper processes draw a share of the frames), so the
simulation does not wait for rendering or encoding (beyond a bounded
queue's back-pressure) and memory does not grow with the video's length.
The simulation builds its decorations only on ticks with a frame due
(:meth:`VideoRecorder.reads_decorations`); the renderer's planes get a
coarse grid (:func:`coarse_planes`), the panel's lines are pasted from a
cache and the encoder runs at preset superfast (``ENCODER_OPTIONS``): the
same picture for less CPU time on software GL.
Communication links are drawn as capsules between robots; robot references
(virtual points) as small spheres. :class:`FrameRenderer` draws one frame
(scene, decorations, overlay band); the video recorder and the tuning page
both use it.

Cameras (``video.camera``): ``top`` (top-down) and ``overview`` (perspective)
use the scene's cameras of those names when it has them, else views computed
from the scene bounds (``top``: orthographic, straight down, so walls hide
no floor); ``follow:ROBOT`` tracks one robot (``follow:quad0``); any other
camera the scene names; ``free``; ``auto`` is ``top``.

Markers, links and paths have a minimum size in pixels of a view of the
whole floor (:meth:`FrameRenderer.at_least`), so robots stay visible in a
70 m scene. The frame is the scene at the floor's aspect, full height, at the left
and a panel beside it (never over it) with sim time, link count, the
strategy's figures and the legend of every kind of thing drawn
(:func:`viz.decorations.frame_legend`), glyphs at least 1/30 of the frame
height.
"""

from __future__ import annotations

import contextlib
import functools
import pickle
import queue
import time
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Any, Sequence

import mujoco
import numpy as np

from sim.config import ConfigError
from sim.observers import Frame, Observer, PhysicsState
from sim.types import Decorations, TargetEstimate
from sim.scenario import VideoConfig
from sim.world import World
from sim import palette
from viz.scenery import scenery_legend, top_light_gain
from viz.decorations import draw_video_decorations, frame_legend, halo_color, link_values, observation_radio

LINK_RGBA = palette.link_rgba(1.0)  # a link with no weight (and an ideal radio)
REFERENCE_RGBA = palette.REFERENCE
LINK_WIDTH_M = 0.02
GROUND_HALO_RGBA = palette.KIND["ground"] * np.array([1, 1, 1, 0.35], dtype=np.float32)
GROUND_HALO_RADIUS_M = 0.12
REFERENCE_RADIUS_M = 0.03
# Minimum on-screen sizes, px (at the scale of a view of the whole floor): robots stay visible at
# any scene size.
ROBOT_MIN_PX = 5.0  # halo radius
REFERENCE_MIN_PX = 1.5  # reference sphere radius
LINK_MIN_PX = 0.8  # link capsule radius
QUADROTOR_SPAN_M = 0.2  # about a quadrotor's size, m: below QUAD_HALO_FROM_PX px it gets a halo
QUAD_HALO_FROM_PX = 8.0
TOP_MARGIN = 1.05  # the computed top view shows the floor and 5 % around it


MESH_SLICES = 8  # rendering: slices of a sphere / capsule (MuJoCo's default 28)
MESH_STACKS = 4  # rendering: stacks of a sphere / capsule (MuJoCo's default 16)
# Rendering: a plane is drawn as a grid of cells its third size apart (the office's floor: 0.05 m, 200 x 200
# cells, two thirds of a frame's software-GL time). Under directional lights (the scenes', the headlight) a flat
# plane is lit the same at any subdivision and its texture repeats by the material, so a coarser grid
# draws the same picture; a spotlight's pool of light gets coarser vertex lighting.
PLANE_GRID_CELLS = 16  # ... at most this many cells along a plane's longer side


def link_color(weight: float) -> np.ndarray:
    """The palette's link ramp: pale grey (about to break, weight 0) to charcoal (strong, weight 1)."""
    return palette.link_rgba(float(weight))


PRESET_CAMERAS = ("top", "overview")  # computed from the scene bounds when the scene lacks them
FOLLOW_PREFIX = "follow:"
FOLLOW_VIEW = {"quadrotor": (3.0, -25.0), "ground": (1.5, -40.0)}  # kind -> (distance m, elevation deg)


def _robot_names(model: mujoco.MjModel) -> list[str]:
    bases = (model.body(i).name for i in range(model.nbody))
    return [n[: -len("/base")] for n in bases if n.endswith("/base") and not n.startswith("target")]


def resolve_camera(model: mujoco.MjModel, name: str) -> str:
    """The camera a video uses; ConfigError for an unknown camera or robot."""
    names = [model.camera(i).name for i in range(model.ncam)]
    if name == "auto":
        return "top"
    if name.startswith(FOLLOW_PREFIX):
        robot = name[len(FOLLOW_PREFIX):]
        robots = _robot_names(model)
        if robot not in robots:
            raise ConfigError("video.camera", f"no robot {robot!r} to follow (robots: {', '.join(robots)})")
        return name
    choices = list(dict.fromkeys([*PRESET_CAMERAS, *names, "free", "auto"]))
    if name not in choices:
        raise ConfigError("video.camera", f"no camera {name!r} (choose from {', '.join(choices)}, follow:ROBOT)")
    return name


def overlay_lines(frame: Frame) -> list[str]:
    """Sim time, link count and the strategy's own figures (``Decorations.overlay``, one line
    per group of figures it separates by two spaces)."""
    lines = [f"t = {frame.observation.time_s:.1f} s", f"links {len(frame.observation.links.edges)}"]
    extra = frame.commands.decorations.overlay
    if extra:
        lines += [part.strip() for part in str(extra).split("  ") if part.strip()]
    return lines


def overlay_text(frame: Frame) -> str:
    """:func:`overlay_lines` on one line (the viewer's band, the tuning page)."""
    return "   ".join(overlay_lines(frame))


TEXT_SHARE = 1 / 28  # the panel's glyph size (font size, px) as a share of the frame height: 19 px at 540
MIN_TEXT_SHARE = 1 / 30  # ... never below this (a talk's slide must read it), shrunk or not
PANEL_MIN_SHARE = 0.3  # the legend panel takes at least this share of the width
PANEL_RGB = (24, 26, 34)
PANEL_TEXT_RGB = (236, 236, 236)
PANEL_DIM_RGB = (170, 175, 185)


@functools.lru_cache(maxsize=16)
def _font(size_px: int):
    from PIL import ImageFont

    return ImageFont.load_default(size=size_px)  # Pillow's bundled scalable font: the same everywhere


def overlay_font_px(height: int) -> int:
    """Font size of the panel's text for a frame ``height`` px tall."""
    return round(height * TEXT_SHARE)


def min_font_px(height: int) -> int:
    return int(np.ceil(height * MIN_TEXT_SHARE))


def scene_width(bounds, width: int, height: int) -> int:
    """Width (px, even) of the scene's part of a ``width`` x ``height`` frame: the floor's
    aspect at full height, leaving the legend panel at least ``PANEL_MIN_SHARE`` of the width."""
    lo, hi = bounds
    aspect = float(hi[0] - lo[0]) / max(float(hi[1] - lo[1]), 1e-9)
    fit = int(round(height * aspect))
    return max(2, min(fit, int(width * (1.0 - PANEL_MIN_SHARE))) // 2 * 2)


def _wrap(draw, text: str, font, width: float) -> list[str]:
    """``text`` broken at spaces into lines no wider than ``width`` px (a long word stays whole)."""
    lines, line = [], ""
    for word in text.split(" "):
        trial = f"{line} {word}" if line else word
        if line and draw.textlength(trial, font=font) > width:
            lines.append(line)
            line = word
        else:
            line = trial
    return lines + [line]


_PANELS: dict = {}  # (height, width, line lengths, legend) -> (the panel without its lines, font, line slots)
PANEL_CACHE_SIZE = 32


def side_panel(height: int, width: int, lines: Sequence[str], legend: Sequence[tuple[str, Any]]) -> np.ndarray:
    """The (height, width, 3) legend panel beside the scene: the overlay's ``lines`` (time,
    links, the strategy's figures) above the ``legend`` ((label, rgba in 0..1) pairs), each
    entry a swatch and its label. Glyphs are ``TEXT_SHARE`` of the height; when the entries
    do not fit they go into two columns, then the text shrinks, never below ``MIN_TEXT_SHARE``.
    The legend changes rarely and the lines' layout with their lengths: the panel without its
    lines is kept and only the lines are drawn each frame (laying it out cost 20 ms a frame)."""
    from PIL import Image, ImageDraw

    key = (height, width, tuple(len(line) for line in lines),
           tuple((str(label), tuple(np.round(np.asarray(rgba, dtype=float)[:3], 4))) for label, rgba in legend))
    cached = _PANELS.get(key)
    if cached is not None:
        base, font, slots = cached
        canvas = Image.fromarray(base)
        draw = ImageDraw.Draw(canvas)
        parts = [part for text in lines for part in _wrap(draw, text, font, width - 2 * max(4, font.size // 2))]
        if len(parts) == len(slots):
            image = base.copy()
            for xy, part in zip(slots, parts):
                _paste_text(image, base, xy, part, font)
            return image
    canvas = Image.new("RGB", (width, height), PANEL_RGB)
    draw = ImageDraw.Draw(canvas)
    layout = None
    for size in range(overlay_font_px(height), min_font_px(height) - 1, -1):
        for columns in (1, 2):
            layout = _panel_layout(draw, size, width, height, lines, legend, columns)
            if layout is not None:
                break
        if layout is not None:
            break
    if layout is None:  # does not fit even small: cut the legend at the panel's foot
        layout = _panel_layout(draw, min_font_px(height), width, height, lines, legend, 2, clip=True)
    font, items = layout
    for kind, xy, text, rgba in items:
        if kind == "dim":
            draw.text(xy, text, fill=PANEL_DIM_RGB, font=font)
        elif kind == "text":
            draw.text(xy, text, fill=PANEL_TEXT_RGB, font=font)
        elif kind == "swatch":
            draw.rectangle(xy, fill=tuple(int(round(255 * float(c))) for c in np.asarray(rgba, dtype=float)[:3]),
                           outline=(90, 92, 100))
    if len(_PANELS) >= PANEL_CACHE_SIZE:
        _PANELS.clear()
    _PANELS[key] = (np.asarray(canvas).copy(), font, [xy for kind, xy, _, _ in items if kind == "line"])
    for kind, xy, text, _ in items:
        if kind == "line":
            draw.text(xy, text, fill=PANEL_TEXT_RGB, font=font)
    return np.asarray(canvas)


_TEXTS: dict = {}  # (text, font size, (x, y), panel shape) -> (y0, x0, block): one line drawn on the panel's colour
TEXT_CACHE_SIZE = 2048


def _paste_text(image: np.ndarray, base: np.ndarray, xy, text: str, font) -> None:
    """Draw one line of ``text`` at ``xy`` into ``image`` (a copy of the panel ``base``): each
    line is drawn once on the base's pixels and kept, so a frame pastes its few lines (only the
    sim time's changes every frame) instead of rasterising them (a third of the panel's cost)."""
    key = (text, font.size, xy, image.shape)
    block = _TEXTS.get(key)
    if block is None:
        from PIL import Image, ImageDraw

        left, top, right, bottom = ImageDraw.Draw(Image.new("RGB", (1, 1))).textbbox(xy, text, font=font)
        x0, y0 = max(0, int(left)), max(0, int(top))
        x1, y1 = min(image.shape[1], int(np.ceil(right)) + 1), min(image.shape[0], int(np.ceil(bottom)) + 1)
        patch = Image.fromarray(np.ascontiguousarray(base[y0:y1, x0:x1]))
        ImageDraw.Draw(patch).text((xy[0] - x0, xy[1] - y0), text, fill=PANEL_TEXT_RGB, font=font)
        block = (y0, x0, np.asarray(patch))
        if len(_TEXTS) >= TEXT_CACHE_SIZE:
            _TEXTS.clear()
        _TEXTS[key] = block
    y0, x0, pixels = block
    image[y0:y0 + pixels.shape[0], x0:x0 + pixels.shape[1]] = pixels


def _panel_layout(draw, size, width, height, lines, legend, columns, clip=False):
    """(font, [(kind, xy, text, rgba)]) of the panel at font ``size`` in ``columns`` legend
    columns; None when it does not fit (unless ``clip``)."""
    font = _font(size)
    pad = max(4, size // 2)
    line_h = int(size * 1.25)
    items = []
    y = pad
    for text in lines:
        for part in _wrap(draw, text, font, width - 2 * pad):
            items.append(("line", (pad, y), part, None))
            y += line_h
    if legend:
        y += line_h // 2
        items.append(("dim", (pad, y), "colours", None))
        y += line_h
    column_w = (width - pad) // columns
    swatch = size
    text_w = column_w - swatch - 2 * pad
    rows = []
    for label, rgba in legend:
        wrapped = _wrap(draw, str(label), font, text_w)
        rows.append((wrapped, rgba))
    per_column = -(-len(rows) // columns) if rows else 0
    top = y
    bottom = y
    for c in range(columns):
        y = top
        for wrapped, rgba in rows[c * per_column:(c + 1) * per_column]:
            needed = line_h * len(wrapped)
            if y + needed > height - pad // 2 and not clip:
                return None
            if y + needed > height:
                break
            x = pad + c * column_w
            items.append(("swatch", (x, y + (line_h - swatch) // 2, x + swatch, y + (line_h - swatch) // 2 + swatch),
                          "", rgba))
            for k, part in enumerate(wrapped):
                if draw.textlength(part, font=font) > text_w and not clip:
                    return None
                items.append(("text", (x + swatch + pad, y + k * line_h), part, None))
            y += needed + line_h // 4
        bottom = max(bottom, y)
    if bottom > height and not clip:
        return None
    return font, items


def _lit(rgba, gain) -> np.ndarray:
    """``rgba`` with its colour divided by the scene's light ``gain`` (:func:`viz.scenery.top_light_gain`),
    so that, lit, it shows the palette's colour the legend names, not a lighter or darker one."""
    out = np.array(rgba, dtype=np.float32)
    out[:3] /= gain
    return out


@contextlib.contextmanager
def coarse_planes(model: mujoco.MjModel):
    """While a renderer's GL context is made (it builds each plane's grid then, from
    ``geom_size``), planes have at most ``PLANE_GRID_CELLS`` grid cells a side; the model's sizes
    are restored afterwards, so the simulation never sees the change."""
    planes = np.flatnonzero(model.geom_type == mujoco.mjtGeom.mjGEOM_PLANE)
    spacing = model.geom_size[planes, 2].copy()
    coarse = 2.0 * np.max(model.geom_size[planes, :2], axis=1) / PLANE_GRID_CELLS
    model.geom_size[planes, 2] = np.maximum(spacing, coarse)
    try:
        yield
    finally:
        model.geom_size[planes, 2] = spacing


def add_capsule(scene: mujoco.MjvScene, a: np.ndarray, b: np.ndarray, width: float, rgba: np.ndarray,
                gain: np.ndarray) -> None:
    """One capsule from ``a`` to ``b`` appended to ``scene`` (nothing when it is full), in ``rgba``
    as seen under the scene's light ``gain``."""
    if scene.ngeom >= scene.maxgeom:
        return
    geom = scene.geoms[scene.ngeom]
    mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_CAPSULE, np.zeros(3), np.zeros(3), np.zeros(9), _lit(rgba, gain))
    geom.specular = 0.0  # no highlight: lit, the colour is the palette's
    mujoco.mjv_connector(geom, mujoco.mjtGeom.mjGEOM_CAPSULE, width, a, b)
    scene.ngeom += 1


def add_sphere(scene: mujoco.MjvScene, p: np.ndarray, radius: float, rgba: np.ndarray, gain: np.ndarray) -> None:
    """One sphere appended to ``scene`` (nothing when it is full), in ``rgba`` as seen under the
    scene's light ``gain``."""
    if scene.ngeom >= scene.maxgeom:
        return
    geom = scene.geoms[scene.ngeom]
    mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_SPHERE, np.full(3, radius), p, np.eye(3).ravel(), _lit(rgba, gain))
    geom.specular = 0.0
    scene.ngeom += 1


class DecorationCanvas(ABC):
    """What :func:`draw_decorations` draws into: a MuJoCo scene (``mjv_scene``) of the ``world``, at
    ``metres_per_px`` (the scale of the markers' minimum sizes), under the scene's ``light_gain``
    (:func:`viz.scenery.top_light_gain`). The video's frame, its close-up and the viewer's user scene are one."""

    world: World
    metres_per_px: float
    light_gain: np.ndarray

    @abstractmethod
    def mjv_scene(self) -> mujoco.MjvScene:
        """The scene the markers are appended to."""

    def at_least(self, size_m: float, pixels: float) -> float:
        """``size_m``, or ``pixels`` of the view when that is larger: markers stay visible in a 70 m
        scene as in a 10 m one."""
        return max(size_m, pixels * self.metres_per_px)

    def _add_capsule(self, a: np.ndarray, b: np.ndarray, width: float, rgba: np.ndarray) -> None:
        add_capsule(self.mjv_scene(), a, b, width, rgba, self.light_gain)

    def _add_sphere(self, p: np.ndarray, radius: float, rgba: np.ndarray) -> None:
        add_sphere(self.mjv_scene(), p, radius, rgba, self.light_gain)


def offscreen_renderer(model: mujoco.MjModel, height: int, width: int,
                       shadows: bool = False) -> tuple[mujoco.Renderer, mujoco.MjvOption]:
    """A ``height`` x ``width`` offscreen renderer of ``model`` (its planes' grids coarse) and the options
    it draws with: the scene (group 0), robot visuals (2) and targets (3), not the collision shells (1)
    nor sites; no reflection, shadows as asked."""
    with coarse_planes(model):
        renderer = mujoco.Renderer(model, height, width)
    options = mujoco.MjvOption()
    options.geomgroup[:] = (1, 0, 1, 1, 0, 0)
    options.sitegroup[:] = 0
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = int(bool(shadows))
    renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
    return renderer, options


def update_scene(renderer: mujoco.Renderer, data: mujoco.MjData, camera, options: mujoco.MjvOption,
                 ortho_height_m: float | None = None) -> None:
    """``renderer``'s scene from ``data`` through ``camera``; an orthographic free camera reads its view
    height (``ortho_height_m``, m) from the model's free-camera fovy, set for the call and put back."""
    if ortho_height_m is None:
        renderer.update_scene(data, camera, options)
        return
    vis = renderer.model.vis.global_
    fovy, vis.fovy = vis.fovy, ortho_height_m
    try:
        renderer.update_scene(data, camera, options)
    finally:
        vis.fovy = fovy


def draw_decorations(canvas: DecorationCanvas, frame: Frame, halo_radius_m: float = GROUND_HALO_RADIUS_M) -> None:
    """Links coloured by weight, references, robot halos (role / team
    colours) and the strategy's decorations (paths, meeting points, target
    estimates, markers) into ``canvas`` (the video's frame or close-up, MuJoCo's viewer:
    viz.viewer). ``halo_radius_m``: a
    ground robot's halo (a close-up, where the robots are large, draws a smaller one)."""
    positions = frame.observation.position
    link_width = canvas.at_least(LINK_WIDTH_M, LINK_MIN_PX)
    values = link_values(frame)  # delivery (non-ideal radio) or weight; None: every link at full value
    if values is None:
        colors, widths = np.broadcast_to(LINK_RGBA, (len(frame.observation.links.edges), 4)), None
    else:  # weak links fainter and thinner: a start cluster's tangle recedes behind its strong links
        colors, widths = palette.link_rgba(values), link_width * palette.link_width_share(values)
    for k, (i, j) in enumerate(frame.observation.links.edges):
        canvas._add_capsule(positions[i], positions[j], link_width if widths is None else widths[k], colors[k])
    for p in frame.commands.position:
        canvas._add_sphere(p, canvas.at_least(REFERENCE_RADIUS_M, REFERENCE_MIN_PX), REFERENCE_RGBA)
    # Ground robots are 7 cm across: a translucent halo keeps them visible; quadrotors get one too
    # once the scene is so large that their bodies shrink below a few pixels.
    world = canvas.world
    halo = canvas.at_least(halo_radius_m, ROBOT_MIN_PX)
    for i in world.kind_index["ground"]:
        canvas._add_sphere(positions[i], halo, halo_color(frame.commands.decorations, i, GROUND_HALO_RGBA))
    if QUAD_HALO_FROM_PX * canvas.metres_per_px > QUADROTOR_SPAN_M:
        for i in world.kind_index["quadrotor"]:
            canvas._add_sphere(positions[i], halo, halo_color(frame.commands.decorations, i, GROUND_HALO_RGBA))
    draw_video_decorations(canvas, frame)  # paths, meeting points, target estimates, markers


# A start cluster (the intermittent scenarios' robots 0.12 m apart: 6 px in a 540 px view of the office) is a
# blob in a view of the whole floor: while the robots' median nearest-neighbour distance is below
# CLOSEUP_BELOW_PX px of the frame, a close-up of them is drawn into the scene's emptiest corner.
CLOSEUP_BELOW_PX = 10.0
CLOSEUP_SIDE_SHARE = 0.35  # the close-up's side, as a share of the frame's height
CLOSEUP_MARGIN = 1.6  # it shows the robots' extent times this ...
CLOSEUP_MIN_HALF_M = 0.25  # ... and at least this much around their centre
CLOSEUP_BORDER_RGB = (236, 236, 236)
CLOSEUP_HALO_SHARE = 0.45  # a ground robot's halo in the close-up: this share of the nearest spacing


def closeup_view(xy: np.ndarray, metres_per_px: float) -> tuple[np.ndarray, float, float] | None:
    """(centre (2,), half side m, nearest spacing m) of a close-up of the robots at ``xy`` (N, 2), m,
    in a view of ``metres_per_px``; None when they are few or far enough apart to tell apart."""
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    if len(xy) < 2:
        return None
    gaps = np.linalg.norm(xy[:, None, :] - xy[None, :, :], axis=2)
    np.fill_diagonal(gaps, np.inf)
    nearest = gaps.min(axis=1)
    if np.median(nearest) / metres_per_px >= CLOSEUP_BELOW_PX:
        return None
    lo, hi = xy.min(axis=0), xy.max(axis=0)
    half = max(CLOSEUP_MARGIN * float(np.max(hi - lo)) / 2, CLOSEUP_MIN_HALF_M)
    return (lo + hi) / 2, half, float(nearest.min())


def emptiest_corner(points_px: np.ndarray, width: int, height: int, side: int) -> tuple[int, int]:
    """(row, column) of the top-left of the ``side`` px square, in one of the four corners of a
    ``width`` x ``height`` image, that holds the fewest of ``points_px`` (K, 2: column, row);
    bottom-right first among equals."""
    corners = [(height - side, width - side), (height - side, 0), (0, width - side), (0, 0)]
    points = np.asarray(points_px, dtype=float).reshape(-1, 2)

    def count(corner):
        row, column = corner
        inside = ((points[:, 0] >= column) & (points[:, 0] < column + side)
                  & (points[:, 1] >= row) & (points[:, 1] < row + side))
        return int(inside.sum())

    return min(corners, key=count)


class _CloseUp(DecorationCanvas):
    """A second, small renderer looking straight down (orthographic) on a close-up of the
    robots, at its own scale."""

    def __init__(self, world: World, side: int, light_gain: np.ndarray):
        self.world = world
        self.side = side
        self.light_gain = light_gain
        self.renderer, self.options = offscreen_renderer(world.model, side, side)
        self.camera = mujoco.MjvCamera()
        self.camera.orthographic = 1
        self.camera.elevation, self.camera.azimuth = -90.0, 90.0
        self.metres_per_px = 1.0

    def mjv_scene(self) -> mujoco.MjvScene:
        return self.renderer.scene

    def render(self, data: mujoco.MjData, frame: Frame, centre: np.ndarray, half_m: float,
               spacing_m: float) -> np.ndarray:
        lo, hi = (np.asarray(b, dtype=float) for b in self.world.bounds)
        self.metres_per_px = 2.0 * half_m / self.side
        self.camera.lookat[:] = (centre[0], centre[1], lo[2])
        self.camera.distance = 2.0 * float(np.linalg.norm(hi - lo))
        update_scene(self.renderer, data, self.camera, self.options, 2.0 * half_m)
        draw_decorations(self, frame, halo_radius_m=min(GROUND_HALO_RADIUS_M, CLOSEUP_HALO_SHARE * spacing_m))
        return self.renderer.render()

    def close(self) -> None:
        self.renderer.close()


class FrameRenderer(DecorationCanvas):
    """Renders one tick's frame to an (H, W, 3) uint8 image: the scene from
    the configured camera, links, references, ground-robot halos and the
    overlay band. Its GL context belongs to the thread that renders."""

    def __init__(self, world: World, config: VideoConfig):
        self.world = world
        self.config = config
        model = world.model
        self.light_gain = top_light_gain(model)
        self.scenery: list | None = None  # the scene's obstacles for the legend, as the camera sees them (first frame)
        # The scene fills the frame's height at the floor's aspect; the legend panel takes the rest.
        self.scene_width = scene_width(world.bounds, config.width, config.height)
        # The offscreen buffer must be at least the scene's size.
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, self.scene_width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, config.height)
        # Coarser tessellation of spheres and capsules: software GL cost is triangles, and a connected
        # mission draws hundreds of path, link and marker geoms a frame (the coarser mesh shows no difference).
        model.vis.quality.numslices = min(model.vis.quality.numslices, MESH_SLICES)
        model.vis.quality.numstacks = min(model.vis.quality.numstacks, MESH_STACKS)
        self.renderer, self.options = offscreen_renderer(model, config.height, self.scene_width, config.shadows)
        lo, hi = world.bounds
        # Metres per pixel of a view of the whole floor: the scale of the minimum marker sizes.
        self.metres_per_px = TOP_MARGIN * max((hi[0] - lo[0]) / self.scene_width, (hi[1] - lo[1]) / config.height)
        self._ortho_height_m: float | None = None
        self._data: mujoco.MjData | None = None  # frame.state's, drawn (made on first use)
        self._closeup: _CloseUp | None = None  # the close-up's renderer (made on first use)
        self.set_camera(config.camera)

    def set_camera(self, name: str) -> None:
        """Switch camera (ConfigError for an unknown one); see the module docstring."""
        self.camera_name = resolve_camera(self.world.model, name)
        self._ortho_height_m = None
        self.camera = self._camera(self.camera_name)

    def mjv_scene(self) -> mujoco.MjvScene:
        return self.renderer.scene

    def _update_scene(self, data: mujoco.MjData) -> None:
        update_scene(self.renderer, data, self.camera, self.options, self._ortho_height_m)

    def _data_of(self, frame: Frame) -> mujoco.MjData:
        """The MuJoCo state to draw: ``frame.state`` in the renderer's own MjData
        (the live one may be a tick ahead), else ``world.data``."""
        state = getattr(frame, "state", None)
        if state is None:
            return self.world.data
        if self._data is None:
            self._data = mujoco.MjData(self.world.model)
        state.load_into(self._data)
        mujoco.mj_forward(self.world.model, self._data)
        return self._data

    def _camera(self, name: str):
        model = self.world.model
        if name.startswith(FOLLOW_PREFIX):
            robot = self.world.robot_names.index(name[len(FOLLOW_PREFIX):])
            distance, elevation = FOLLOW_VIEW[self.world.robot_kinds[robot]]
            cam = mujoco.MjvCamera()
            cam.type = mujoco.mjtCamera.mjCAMERA_TRACKING
            cam.trackbodyid = int(self.world.body_ids[robot])
            cam.fixedcamid = -1
            cam.lookat[:] = self.world.data.xpos[cam.trackbodyid]
            cam.distance, cam.elevation, cam.azimuth = distance, elevation, 90.0
            return cam
        if name in [model.camera(i).name for i in range(model.ncam)]:
            return model.camera(name).id
        cam = mujoco.MjvCamera()
        lo, hi = self.world.bounds
        cam.lookat[:] = (lo + hi) / 2
        self._ortho_height_m = None
        span = float(np.linalg.norm(hi[:2] - lo[:2]))
        cam.azimuth = 90
        if name == "top":  # straight down, orthographic: walls hide no floor; the whole floor in view
            cam.orthographic = 1
            cam.lookat[2] = lo[2]
            cam.distance = 2.0 * (span + hi[2] - lo[2])  # above everything in the scene
            cam.elevation = -90.0
            aspect = self.config.height / self.scene_width
            self._ortho_height_m = TOP_MARGIN * max(hi[1] - lo[1], (hi[0] - lo[0]) * aspect)
        elif name == "overview":  # perspective from the -y side
            cam.distance = 1.1 * span
            cam.elevation = -45
        else:  # free
            cam.distance = 1.6 * span
            cam.elevation = -60
        return cam

    def render_scene(self, frame: Frame) -> np.ndarray:
        """``frame``'s MuJoCo state (``frame.state``; ``world.data`` for a frame
        without one) with its decorations: (height, scene_width, 3) uint8."""
        data = self._data_of(frame)
        self._update_scene(data)
        draw_decorations(self, frame)
        image = self.renderer.render()
        self._draw_closeup(image, data, frame)
        return image

    def _draw_closeup(self, image: np.ndarray, data: mujoco.MjData, frame: Frame) -> None:
        """A close-up of the robots in the scene's emptiest corner while they are too close to
        tell apart (a view straight down on the whole scene only)."""
        camera = self.renderer.scene.camera[0]
        if not camera.orthographic or camera.forward[2] > -0.999:
            return
        positions = np.asarray(frame.observation.position, dtype=float)
        height = self.config.height
        metres_per_px = float(camera.frustum_top - camera.frustum_bottom) / height
        view = closeup_view(positions[:, :2], metres_per_px)
        if view is None:
            return
        centre, half_m, spacing_m = view
        side = int(height * CLOSEUP_SIDE_SHARE) // 2 * 2
        if self._closeup is None:
            self._closeup = _CloseUp(self.world, side, self.light_gain)
        inset = self._closeup.render(data, frame, centre, half_m, spacing_m)
        right = np.cross(camera.forward, camera.up)
        up = np.asarray(camera.up, dtype=float)
        middle = (camera.frustum_top + camera.frustum_bottom) / 2
        decorations = frame.commands.decorations
        busy = np.concatenate([positions, np.asarray(frame.target_positions, dtype=float).reshape(-1, 3),
                               *(np.asarray(points, dtype=float).reshape(-1, 3) for points, _ in (decorations.paths or ())),
                               np.asarray(decorations.meeting_points if decorations.meeting_points is not None
                                          else (), dtype=float).reshape(-1, 3)])
        offset = busy - np.asarray(camera.pos, dtype=float)  # the view straight down: world -> (column, row)
        points_px = np.stack([image.shape[1] / 2 + offset @ right / metres_per_px,
                              height / 2 - (offset @ up - middle) / metres_per_px], axis=1)
        row, column = emptiest_corner(points_px, image.shape[1], height, side)
        image[row:row + side, column:column + side] = inset
        image[row:row + side, [column, column + side - 1]] = CLOSEUP_BORDER_RGB
        image[[row, row + side - 1], column:column + side] = CLOSEUP_BORDER_RGB
        _label(image, (column + 2, row + 2), f"close-up x{metres_per_px / self._closeup.metres_per_px:.0f}",
               min_font_px(height))

    def render(self, frame: Frame) -> np.ndarray:
        """The full (height, width, 3) frame: the scene at the left, beside it the panel with
        the overlay's lines and the legend of everything drawn (never over the scene)."""
        scene = self.render_scene(frame)
        if self.scenery is None:
            camera = self.renderer.scene.camera[0]
            self.scenery = scenery_legend(self.world.model, np.array(camera.pos, dtype=float),
                                          np.array(camera.forward, dtype=float))
        height, width = self.config.height, self.config.width
        image = np.empty((height, width, 3), dtype=np.uint8)
        image[:, : self.scene_width] = scene
        image[:, self.scene_width:] = side_panel(height, width - self.scene_width, overlay_lines(frame),
                                                 frame_legend(frame, self.world.robot_kinds, self.scenery))
        return image

    def close(self) -> None:
        self.renderer.close()
        if self._closeup is not None:
            self._closeup.close()


def _label(image: np.ndarray, xy, text: str, size: int) -> None:
    """``text`` at ``xy`` (column, row) of ``image`` in the panel's colours, on a band of the panel's background."""
    x, y = xy
    pixels = _label_band(text, max(size, 8))[: image.shape[0] - y, : image.shape[1] - x]
    image[y:y + pixels.shape[0], x:x + pixels.shape[1]] = pixels


@functools.lru_cache(maxsize=16)
def _label_band(text: str, size: int) -> np.ndarray:
    """``text`` drawn once on a band of the panel's background (a close-up's label repeats frame after frame)."""
    from PIL import Image, ImageDraw

    font = _font(size)
    _, _, right, bottom = ImageDraw.Draw(Image.new("RGB", (1, 1))).textbbox((0, 0), text, font=font)
    band = Image.new("RGB", (int(right) + 6, int(bottom) + 4), PANEL_RGB)
    ImageDraw.Draw(band).text((3, 1), text, fill=PANEL_TEXT_RGB, font=font)
    pixels = np.asarray(band)
    pixels.flags.writeable = False
    return pixels


@dataclass(frozen=True)
class _LinksView:
    edges: list  # (i, j) robot index pairs with a link


@dataclass(frozen=True)
class _ObservationView:
    position: np.ndarray  # (N, 3) robot positions, m, world frame
    time_s: float  # sim time, s
    links: _LinksView
    radio: "_RadioView | None" = None  # the link colours' delivery (non-ideal radio only)


@dataclass(frozen=True)
class _RadioView:
    preset: str
    delivery: np.ndarray  # (N, N) delivery probability of each pair


@dataclass(frozen=True)
class _CommandsView:
    position: np.ndarray  # (N, 3) references (virtual points), m
    decorations: Decorations  # the strategy's paths, meeting points, overlay, ...
    estimate: TargetEstimate | None


@dataclass(frozen=True)
class FrameView:
    """What :meth:`FrameRenderer.render` reads of a tick's Frame, picklable."""

    observation: _ObservationView
    commands: _CommandsView
    target_positions: np.ndarray  # (M, 3) true target positions, m (the legend names them when present)
    state: PhysicsState  # MuJoCo's state of the tick, drawn

    @staticmethod
    def of(frame: Frame) -> "FrameView":
        obs, cmd = frame.observation, frame.commands
        return FrameView(
            _ObservationView(np.array(obs.position), float(obs.time_s), _LinksView(list(obs.links.edges)),
                             _radio_view(obs)),
            _CommandsView(np.array(cmd.position), cmd.decorations, cmd.estimate),
            np.array(frame.target_positions),
            frame.state,
        )


def _radio_view(obs) -> _RadioView | None:
    radio = observation_radio(obs)
    return None if radio is None else _RadioView(radio.preset, np.array(radio.delivery))


# H.264 at constant quality 15 (near lossless for flat-shaded frames), preset superfast: about 0.7 of the
# encoder's CPU time at preset veryfast for a file about twice as large (a 20 s video of 1-5 MB) and no
# difference to see (the error against the rendered frames is the 4:2:0 chroma's, the same at any preset).
ENCODER_OPTIONS = ("-preset", "superfast", "-crf", "15")
VIDEO_QUEUE_FRAMES = 32  # states waiting for the renderer process before the simulation waits, -
WORKER_POLL_S = 1.0  # how often a blocked simulation checks that the renderer is still alive, s
INTERRUPTED_CLOSE_S = 0.0  # an interrupted run's renderer stops at its frame (the CPU is the painters'), then finishes the file
RESULT_TIMEOUT_S = 60.0  # closing: a renderer that has not finished the file by then is stopped
STALL_S = 30.0  # a renderer that takes no frame from a full queue for this long is stopped (it hangs)


class VideoRecorder(Observer):
    """Observer writing ``video.mp4`` at ``config.fps`` frames per second of
    sim time: frame k shows the state of the tick at or just before k / fps
    (a tick's image is repeated when the fps exceeds the control rate), so a
    run of T s gives ceil(T * fps) frames and the video lasts as long as the
    run at any fps.

    Rendering (slow on software EGL) and encoding run in a
    renderer process of their own (start method 'spawn': a fresh process
    owns its GL context); past ``HELPERS_AFTER_FRAMES`` frames it shares the
    drawing with helper processes of its own (``renderers`` in all, by
    default one per usable CPU up to ``MAX_RENDERERS``: frames are
    independent given their state), each drawing every n-th frame, and
    writes all of them to the encoder in order. The simulation only copies the state of a tick
    whose frame is due (``frame.state``: qpos, qvel, act, mocap poses, the
    state the frame's observation was read from) and what its decorations
    read (:class:`FrameView`) into a bounded queue of
    ``VIDEO_QUEUE_FRAMES`` states; the renderer recomputes the kinematics
    (``mj_forward``) and draws. Every frame is written: when rendering is
    slower than the simulation, the queue fills and the simulation waits for
    a free slot (back-pressure; memory stays bounded), so a run then goes at
    the renderer's pace, with the simulation's own work done in parallel.
    ``close`` waits until the last frame is encoded; an interrupted run's
    close renders the queue for ``INTERRUPTED_CLOSE_S`` at most (none: the
    frame being drawn, and a first one if none was), and :meth:`abandon` (a
    signal while closing) stops it at the next frame; the file is finished
    either way.

    The renderer is supervised (viz.painter): it ignores the group's SIGINT
    and SIGTERM, every wait on it is bounded and checks that it is alive,
    and one that died (killed, out of memory) or failed (disk full) raises
    :class:`sim.loop.ObserverFailure` naming it and its exit code: the run
    ends "failed" with its files written.
    """

    def __init__(self, world: World, config: VideoConfig, path: str, control_period_s: float,
                 renderers: int | None = None):
        import multiprocessing

        from viz.painter import group_signals_deferred, supervise

        resolve_camera(world.model, config.camera)  # refuse an unknown camera here, not in the renderer
        self.world = world
        self.config = config
        self.path = path
        self.control_period_s = control_period_s
        self.frames_written = 0  # frames handed to the renderer
        self.frames_encoded: int | None = None  # frames in the file, once closed
        self.failure = ""  # why the renderer is gone, once it is
        self._abandoned = False
        context = multiprocessing.get_context("spawn")
        self._queue = context.Queue(maxsize=VIDEO_QUEUE_FRAMES)
        self._queue.cancel_join_thread()  # never wait at exit on a feeder blocked by a dead renderer
        self._stop = context.Event()
        self._result, child = context.Pipe(duplex=False)
        self._process = context.Process(
            target=_render_worker,
            args=(pickle.dumps(world), config, path, self._queue, child, self._stop,
                  renderer_count() if renderers is None else max(1, int(renderers))),
            daemon=False, name="video-renderer",  # not daemonic: it starts its helpers; supervise kills it at exit
        )
        with group_signals_deferred():
            self._process.start()
            supervise(self._process)
        child.close()

    def _frames_due(self, time_s: float) -> int:
        """Frames due on the tick starting at ``time_s``: its state stands for [t, t + control period)."""
        until = time_s + self.control_period_s - 1e-9
        repeats = 0
        while (self.frames_written + repeats) / self.config.fps < until:
            repeats += 1
        return repeats

    def reads_decorations(self, time_s: float) -> bool:
        """Only a tick with a frame due is drawn (at 30 fps a third of a 100 Hz run's ticks)."""
        return self._frames_due(time_s) > 0

    def on_tick(self, frame: Frame) -> None:
        repeats = self._frames_due(frame.observation.time_s)
        if repeats:
            if self._process.exitcode is not None:  # a cheap look (waitpid): it died since the last frame
                raise self._fail()
            # Pickled now, not by the queue's feeder thread later: the strategy may reuse its arrays.
            self._put(pickle.dumps((FrameView.of(frame), repeats), protocol=pickle.HIGHEST_PROTOCOL))
            self.frames_written += repeats

    def abandon(self) -> None:
        """Finish the file at the next frame (safe in a signal handler: it only sets a flag)."""
        self._abandoned = True

    def _put(self, item, until: float = float("inf")) -> bool:
        """Queue ``item``, waiting for a free slot while the renderer lives;
        False when abandoned or past ``until`` (monotonic)."""
        stalled = time.monotonic() + STALL_S
        while not self._abandoned and time.monotonic() < until:
            try:
                self._queue.put(item, timeout=min(WORKER_POLL_S, max(0.01, until - time.monotonic())))
                return True
            except queue.Full:  # back-pressure: the renderer is behind
                if self._process.exitcode is None and time.monotonic() > stalled:
                    self._process.kill()
                    self._process.join(WORKER_POLL_S)
                    self.failure = f"video renderer hung (no frame taken for {STALL_S:g} s; killed)"
                if self._process.exitcode is not None:
                    raise self._fail() from None
        return False

    def _fail(self):
        """The ObserverFailure of a renderer that is gone (its report, else its exit code)."""
        if not self.failure:
            report = None
            try:
                if self._result.poll(0.5):
                    report = self._result.recv()
            except (EOFError, OSError):
                pass
            from viz.painter import exit_reason

            self._process.join(0.5)
            if isinstance(report, str):  # its error (a traceback's text): the last line says what
                lines = [line for line in report.strip().splitlines() if line.strip()]
                self.failure = f"video renderer failed ({exit_reason(self._process.exitcode)}): " \
                               f"{lines[-1] if lines else 'no report'}"
            else:
                self.failure = f"video renderer died ({exit_reason(self._process.exitcode)})"
                from pathlib import Path

                from sim.outputs import no_space_left

                if no_space_left(Path(self.path).parent):  # its encoder's disk is full: say so
                    self.failure += f", {Path(self.path).name} cut short: No space left on device (ENOSPC)"
        from sim.loop import ObserverFailure

        return ObserverFailure(self.failure)

    def _wait_result(self, hurry: float):
        """The renderer's report (frames written, or an error's text); None when it
        died without one. Bounded: rendering stops at ``hurry`` (monotonic: an
        interrupted run's INTERRUPTED_CLOSE_S) or at once when abandoned, and a renderer silent
        for RESULT_TIMEOUT_S is stopped."""
        give_up = time.monotonic() + RESULT_TIMEOUT_S
        while True:
            try:
                if self._result.poll(0.1):
                    return self._result.recv()
            except (EOFError, OSError):
                return None
            if self._process.exitcode is not None and not self._result.poll(0):
                return None
            now = time.monotonic()
            if self._abandoned or now > hurry:
                if not self._stop.is_set():
                    self._stop.set()  # finish the file at the next frame
                    give_up = min(give_up, now + 5.0)
            if now > give_up:
                self._process.kill()
                return None

    def close(self, status: str) -> None:
        from viz.painter import stop_process

        try:
            if self.failure:  # already reported (the run ends "failed")
                return
            if status == "failed":
                self._stop.set()  # the run is failing anyway: finish the file, do not render the queue
            hurry = time.monotonic() + INTERRUPTED_CLOSE_S if status == "interrupted" else float("inf")
            queued = self._put(None) if hurry == float("inf") else self._put(None, hurry)  # end of the video
            if self._process.exitcode is None and not queued:
                self._stop.set()
            result = self._wait_result(hurry)  # after the last frame is encoded
            if not isinstance(result, int):
                raise self._fail()
            self.frames_encoded = result
            if result != self.frames_written and not self._stop.is_set():
                self.failure = f"video renderer wrote {result} frames of {self.frames_written}"
                from sim.loop import ObserverFailure

                raise ObserverFailure(self.failure)
        finally:
            stop_process(self._process)
            self._queue.close()
            self._result.close()


def _next_state(states, parent, stop, first: bool = False):
    """The next queued state; None at the end of the video, when the run asks
    to stop (``stop`` set; the ``first`` frame is still taken when queued,
    so the file exists), or once the simulation's process is gone (killed:
    this process holds the queue's write end too, so no end of file would
    come): the file is then closed and stays readable up to the last frame."""
    while not stop.is_set():
        try:
            return states.get(timeout=WORKER_POLL_S)
        except queue.Empty:
            if parent is not None and not parent.is_alive():
                return None
    if first:
        try:
            return states.get(timeout=WORKER_POLL_S)
        except queue.Empty:
            pass
    return None


MAX_RENDERERS = 3  # processes drawing a video's frames (the renderer and its helpers), at most the CPUs usable
HELPERS_AFTER_FRAMES = 30  # the renderer starts its helpers once a video has this many frames (a short one never pays)
HELPER_OUTSTANDING = 2  # frames a helper may have in hand before the renderer waits for its first


def renderer_count() -> int:
    """Processes drawing a long video: the renderer and its helpers, one per CPU this process may use,
    at most ``MAX_RENDERERS`` (frames are independent given their state: each process draws its share)."""
    import os

    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    return max(1, min(MAX_RENDERERS, cpus))


class _Helpers:
    """The renderer's helper processes: each draws the frames it is handed (in turn) and sends
    their pixels back in order; the renderer writes every frame to the encoder in the video's
    order. Supervised as the renderer is: they ignore the group's signals, every wait on one is
    bounded and checks that it lives (one that died is the renderer's error, naming it), and each
    ends when the renderer closes its pipes or is gone (killed: its pipes close with it)."""

    def __init__(self, world_pickle: bytes, config: VideoConfig, count: int, write):
        import multiprocessing

        context = multiprocessing.get_context("spawn")
        self.shape = (config.height, config.width, 3)
        self.processes, self.inboxes, self.outboxes = [], [], []
        try:
            self._start(context, world_pickle, config, count)
        except BaseException:
            self.close()  # those started end at their end of file
            raise
        self.pending: list = []  # the frames not yet written, in order: (helper index or None, image, repeats)
        self.outstanding = [0] * count
        self._turn = 0
        self.write = write  # (image, repeats): to the encoder

    def _start(self, context, world_pickle: bytes, config: VideoConfig, count: int) -> None:
        for k in range(count):
            inbox_read, inbox_write = context.Pipe(duplex=False)
            outbox_read, outbox_write = context.Pipe(duplex=False)
            process = context.Process(target=_helper_worker, args=(config, inbox_read, outbox_write),
                                      daemon=True, name=f"video-renderer-helper-{k + 1}")
            process.start()
            inbox_read.close()  # the helper's ends are the helper's: its death closes them
            outbox_write.close()
            self.processes.append(process)
            self.inboxes.append(inbox_write)
            self.outboxes.append(outbox_read)
            # The world through the pipe, not the start's arguments: a start writes those to a pipe whose
            # reading end it holds itself until done, so a child killed while starting would block it for good.
            self._send(k, world_pickle)

    def __len__(self) -> int:
        return len(self.processes)

    def hand(self, item: bytes, repeats: int) -> bool:
        """Give the frame ``item`` to the helper whose turn it is (False: the renderer draws it, its share)."""
        k = self._turn
        self._turn = (self._turn + 1) % (len(self) + 1)
        if k == len(self):
            return False
        while self.outstanding[k] >= HELPER_OUTSTANDING:
            self._write_next(block=True)
        self._send(k, item)
        self.outstanding[k] += 1
        self.pending.append((k, None, repeats))
        return True

    def _send(self, k: int, data: bytes) -> None:
        self._alive(k)
        try:
            self.inboxes[k].send_bytes(data)
        except OSError:  # its end closed: it died meanwhile
            self.processes[k].join(WORKER_POLL_S)
            self._alive(k)
            raise

    def _alive(self, k: int) -> None:
        if self.processes[k].exitcode is not None:
            from viz.painter import exit_reason

            raise RuntimeError(f"video renderer helper {k + 1} died ({exit_reason(self.processes[k].exitcode)})")

    def _image(self, k: int) -> np.ndarray:
        """Helper ``k``'s next frame (bounded waits, each checking that it lives)."""
        while not self.outboxes[k].poll(WORKER_POLL_S):
            self._alive(k)
        try:
            data = self.outboxes[k].recv_bytes()
        except (EOFError, OSError):  # OSError: it died while sending a frame ("got end of file during message")
            self.processes[k].join(WORKER_POLL_S)
            self._alive(k)
            raise RuntimeError(f"video renderer helper {k + 1} closed its pipe") from None
        if len(data) != int(np.prod(self.shape)):
            raise RuntimeError(f"video renderer helper {k + 1} failed: {data.decode(errors='replace')}")
        self.outstanding[k] -= 1
        return np.frombuffer(data, dtype=np.uint8).reshape(self.shape)

    def _write_next(self, block: bool) -> bool:
        if not self.pending:
            return False
        k, image, repeats = self.pending[0]
        if image is None:
            if not block and not self.outboxes[k].poll(0):
                return False
            image = self._image(k)
        self.pending.pop(0)
        self.write(image, repeats)
        return True

    def drawn(self, image: np.ndarray, repeats: int) -> None:
        """The renderer's own frame, written in its place in the order."""
        self.pending.append((None, image, repeats))
        while self._write_next(block=False):
            pass

    def flush(self) -> None:
        """Every frame handed out, written (waits for the helpers)."""
        while self._write_next(block=True):
            pass

    def close(self) -> None:
        from viz.painter import stop_process

        for connection in (*self.inboxes, *self.outboxes):
            connection.close()  # a helper's end of file: it ends
        for process in self.processes:
            stop_process(process)


def _helper_worker(config: VideoConfig, inbox, outbox) -> None:
    """A helper process: the world (pickled) first, then draw each frame handed to it and send its
    pixels back (or an error's text, then end); end at the renderer's end of file or once the
    renderer is gone."""
    import multiprocessing
    import traceback

    from viz.painter import ignore_group_signals

    ignore_group_signals()
    parent = multiprocessing.parent_process()
    try:
        view = None
        while True:
            if not inbox.poll(WORKER_POLL_S):
                if parent is not None and not parent.is_alive():
                    return
                continue
            try:
                item = inbox.recv_bytes()
            except EOFError:
                return
            if view is None:
                view = FrameRenderer(pickle.loads(item), config)
                continue
            frame, _ = pickle.loads(item)
            image = np.ascontiguousarray(view.render(frame))
            outbox.send_bytes(memoryview(image).cast("B"))  # flat: its length is in bytes
    except (BrokenPipeError, EOFError):  # the renderer is gone
        return
    except BaseException:  # noqa: BLE001 - the renderer reports it with this text
        text = traceback.format_exc().strip().splitlines()[-1][:400].encode()  # never a frame's length (768 B and up)
        with contextlib.suppress(OSError):
            outbox.send_bytes(text)


class _Writer:
    """Frames to the encoder in the video's order: the renderer's own, and its helpers' once started."""

    def __init__(self, writer, world_pickle: bytes, config: VideoConfig, renderers: int):
        self.writer = writer
        self.renderers = renderers
        self.world_pickle = world_pickle
        self.config = config
        self.helpers: _Helpers | None = None
        self.written = 0
        self.received = 0

    def take(self, item: bytes, repeats: int) -> bool:
        """True when a helper draws ``item``; False: the renderer draws it (then :meth:`drawn`)."""
        self.received += 1
        if self.helpers is None and self.received > HELPERS_AFTER_FRAMES and self.renderers > 1:
            self.helpers = _Helpers(self.world_pickle, self.config, self.renderers - 1, self._write)
        return self.helpers is not None and self.helpers.hand(item, repeats)

    def _write(self, image: np.ndarray, repeats: int) -> None:
        for _ in range(repeats):
            self.writer.append_data(image)
            self.written += 1

    def drawn(self, image: np.ndarray, repeats: int) -> None:
        if self.helpers is None:
            self._write(image, repeats)
        else:
            self.helpers.drawn(image, repeats)

    def finish(self) -> None:
        """Every frame handed to the helpers, written; the helpers ended."""
        if self.helpers is not None:
            try:
                self.helpers.flush()
            finally:
                self.helpers.close()


ORPHAN_EXIT_S = 10.0  # a renderer whose run is gone (killed) and that has not ended by then exits


def _orphan_watch(parent) -> None:
    """Once the run's process is gone the renderer ends: it renders what is queued and closes the file
    (:func:`_next_state`); a run killed while queuing a frame leaves half a message in the queue, whose
    read would wait for good, so past ``ORPHAN_EXIT_S`` this thread ends the process (its helpers and
    the encoder see their pipes close: ffmpeg finishes the file up to the last frame it got)."""
    import os
    import threading

    def watch() -> None:
        parent.join()  # its sentinel: returns once the run's process is gone
        time.sleep(ORPHAN_EXIT_S)
        os._exit(1)

    if parent is not None:
        threading.Thread(target=watch, name="orphan-watch", daemon=True).start()


def _render_worker(world_pickle: bytes, config: VideoConfig, path: str, states, result, stop,
                   renderers: int = 1) -> None:
    """The renderer process: draw and encode every state from ``states`` until
    None (or ``stop``); send the number of frames written (or the error's
    text) on ``result``. The group's SIGINT and SIGTERM are the run's. Past
    ``HELPERS_AFTER_FRAMES`` frames it shares the drawing with helper
    processes (``renderers`` processes in all), each frame drawn by one of
    them in turn and written in order."""
    import multiprocessing
    import traceback

    from viz.painter import ignore_group_signals

    ignore_group_signals()
    frames = None
    try:
        import imageio.v2 as imageio

        world = pickle.loads(world_pickle)
        view = FrameRenderer(world, config)
        # ffmpeg says only what is fatal: its failures reach the run as the writer's exception, which the run
        # reports in its one line (a full disk: "Error writing trailer" would be two lines more).
        writer = imageio.get_writer(
            path, fps=config.fps, codec="libx264", quality=None, macro_block_size=1,
            ffmpeg_log_level="fatal", output_params=["-pix_fmt", "yuv420p", *ENCODER_OPTIONS],
        )
        frames = _Writer(writer, world_pickle, config, renderers)
        parent = multiprocessing.parent_process()
        _orphan_watch(parent)
        try:
            while (item := _next_state(states, parent, stop, first=frames.received == 0)) is not None:
                frame, repeats = pickle.loads(item)
                if not frames.take(item, repeats):
                    frames.drawn(view.render(frame), repeats)  # its own state (frame.state)
            frames.finish()
        finally:
            if frames.helpers is not None:
                frames.helpers.close()
            writer.close()
            view.close()
        _send(result, frames.written)
    except BaseException:  # noqa: BLE001 - the parent reports it with this text
        _send(result, traceback.format_exc())


def _send(result, report) -> None:
    try:
        result.send(report)
    except OSError:  # the run is gone
        pass
