"""Offscreen video through MuJoCo's renderer (EGL), streamed to ffmpeg.

An observer: it reads ``MjData`` and the tick's frame, never writes to the
simulation. Frames are taken at the video fps in sim time and written one by
one to the encoder, so memory does not grow with the video's length.
Communication links are drawn as capsules between robots; robot references
(virtual points) as small spheres.
"""

from __future__ import annotations

import mujoco
import numpy as np

from sim.config import ConfigError
from sim.observers import Frame
from sim.scenario import VideoConfig
from sim.world import World

LINK_RGBA = np.array([0.1, 0.75, 0.2, 0.9], dtype=np.float32)
REFERENCE_RGBA = np.array([0.2, 0.4, 1.0, 0.6], dtype=np.float32)
LINK_WIDTH_M = 0.02
GROUND_HALO_RGBA = np.array([0.2, 0.8, 0.3, 0.35], dtype=np.float32)
GROUND_HALO_RADIUS_M = 0.12


def link_color(weight: float) -> np.ndarray:
    """Green (strong, weight 1) to red (about to break, weight 0)."""
    w = float(np.clip(weight, 0.0, 1.0))
    return np.array([1.0 - w, 0.2 + 0.6 * w, 0.15, 0.9], dtype=np.float32)


def resolve_camera(model: mujoco.MjModel, name: str) -> str:
    """The camera a video uses; ConfigError if the scene lacks a named one."""
    names = [model.camera(i).name for i in range(model.ncam)]
    if name == "auto":
        return "top" if "top" in names else "free"
    if name != "free" and name not in names:
        raise ConfigError("video.camera", f"no camera {name!r} in the scene (choose from {names + ['free', 'auto']})")
    return name


def overlay_text(frame: Frame) -> str:
    """Sim time, link count and the strategy's own line (``info['overlay']``)."""
    parts = [f"t = {frame.observation.time_s:6.1f} s", f"links {len(frame.observation.links.edges)}"]
    extra = frame.commands.info.get("overlay")
    if extra:
        parts.append(str(extra))
    return "   ".join(parts)


def burn_overlay(image: np.ndarray, text: str) -> np.ndarray:
    """Draw ``text`` on a dark band at the top-left of the frame."""
    from PIL import Image, ImageDraw

    canvas = Image.fromarray(image)
    draw = ImageDraw.Draw(canvas)
    left, top, right, bottom = draw.textbbox((6, 4), text)
    draw.rectangle((0, 0, right + 6, bottom + 4), fill=(20, 20, 28))
    draw.text((6, 4), text, fill=(235, 235, 235))
    return np.asarray(canvas)


class VideoRecorder:
    def __init__(self, world: World, config: VideoConfig, path: str):
        import imageio.v2 as imageio

        self.world = world
        self.config = config
        self.path = path
        model = world.model
        # The offscreen buffer must be at least the frame size.
        model.vis.global_.offwidth = max(model.vis.global_.offwidth, config.width)
        model.vis.global_.offheight = max(model.vis.global_.offheight, config.height)
        self.renderer = mujoco.Renderer(model, config.height, config.width)
        self.options = mujoco.MjvOption()
        # Show scene (0), robot visuals (2) and targets (3); hide collision shells (1).
        self.options.geomgroup[:] = (1, 0, 1, 1, 0, 0)
        self.options.sitegroup[:] = 0
        if config.shadows:
            self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 1
        else:
            self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
        self.renderer.scene.flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
        self.camera = self._camera(resolve_camera(world.model, config.camera))
        self.writer = imageio.get_writer(
            path, fps=config.fps, codec="libx264", quality=7, macro_block_size=1,
            ffmpeg_log_level="error", output_params=["-pix_fmt", "yuv420p"],
        )
        self.frames_written = 0
        self._next_time = 0.0

    def _camera(self, name: str):
        if name != "free":
            return self.world.model.camera(name).id
        cam = mujoco.MjvCamera()
        lo, hi = self.world.bounds
        cam.lookat[:] = (lo + hi) / 2
        cam.distance = 1.6 * float(np.linalg.norm(hi[:2] - lo[:2]))
        cam.elevation = -60
        cam.azimuth = 90
        return cam

    def _add_capsule(self, a: np.ndarray, b: np.ndarray, width: float, rgba: np.ndarray) -> None:
        scene = self.renderer.scene
        if scene.ngeom >= scene.maxgeom:
            return
        geom = scene.geoms[scene.ngeom]
        mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_CAPSULE, np.zeros(3), np.zeros(3), np.zeros(9), rgba)
        mujoco.mjv_connector(geom, mujoco.mjtGeom.mjGEOM_CAPSULE, width, a, b)
        scene.ngeom += 1

    def _add_sphere(self, p: np.ndarray, radius: float, rgba: np.ndarray) -> None:
        scene = self.renderer.scene
        if scene.ngeom >= scene.maxgeom:
            return
        geom = scene.geoms[scene.ngeom]
        mujoco.mjv_initGeom(geom, mujoco.mjtGeom.mjGEOM_SPHERE, np.full(3, radius), p, np.eye(3).ravel(), rgba)
        scene.ngeom += 1

    def on_tick(self, frame: Frame) -> None:
        if frame.observation.time_s + 1e-9 < self._next_time:
            return
        self._next_time += 1.0 / self.config.fps
        self.write_frame(frame)

    def write_frame(self, frame: Frame) -> None:
        self.renderer.update_scene(self.world.data, self.camera, self.options)
        positions = frame.observation.position
        weights = frame.commands.info.get("link_weights")
        for i, j in frame.observation.links.edges:
            rgba = LINK_RGBA if weights is None else link_color(weights[i, j])
            self._add_capsule(positions[i], positions[j], LINK_WIDTH_M, rgba)
        for p in frame.commands.position:
            self._add_sphere(p, 0.03, REFERENCE_RGBA)
        # Ground robots are 7 cm across: a translucent halo keeps them visible.
        for i in self.world.kind_index["ground"]:
            self._add_sphere(positions[i], GROUND_HALO_RADIUS_M, GROUND_HALO_RGBA)
        image = self.renderer.render()
        self.writer.append_data(burn_overlay(image, overlay_text(frame)))
        self.frames_written += 1

    def close(self, status: str) -> None:
        self.writer.close()
        self.renderer.close()
