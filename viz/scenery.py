"""What a scene's own geometry looks like from the top camera: the lights' gain on a surface facing
up, and the legend's entries for the scene's obstacles (walls, furniture, buildings).

MuJoCo lights a surface as ``rgb * (sum over lights of ambient + diffuse * cos)`` plus a specular
term (Phong: the light's and the surface's specular times a power of the half-way vector's
cosine), clamped to 1; a textured surface multiplies its texture by that clamped light. Seen from
above, a surface facing up gets the headlight's ambient and diffuse in full and each light's
ambient plus its diffuse times the cosine of its direction with the vertical. The decorations
(:mod:`viz.video`) have no specular term and divide their colours by this gain, so a robot's mark
shows the palette's colour its legend entry names, whatever the scene's lights; the legend's
obstacle swatches are the scene's colours lit the same way, with their specular term as the
camera sees it at the centre of the material's most opaque top (it fades across the picture).
The built-in scenes and tether's default light set no specular (docs/models.md), so there the
swatch is exact everywhere.
"""

from __future__ import annotations

import mujoco
import numpy as np

MUJOCO_DEFAULT_RGBA = (0.5, 0.5, 0.5, 1.0)  # a geom's rgba when its material's colour applies
MUJOCO_DEFAULT_SPECULAR = (0.5, 0.5)  # (specular, shininess) of a geom without a material
OBSTACLE_GROUP = 0


def top_light_gain(model: mujoco.MjModel) -> np.ndarray:
    """(3,) RGB gain of the scene's lights on a surface facing up, seen from above (the
    headlight along the view). Spot and point lights count as directional ones along their
    axis (their cone and attenuation are left out)."""
    headlight = model.vis.headlight
    gain = np.asarray(headlight.ambient, dtype=float) + np.asarray(headlight.diffuse, dtype=float)
    for k in range(model.nlight):
        if not model.light_active[k]:
            continue
        facing = max(0.0, -float(model.light_dir[k][2]))
        gain = gain + np.asarray(model.light_ambient[k], dtype=float) + facing * np.asarray(model.light_diffuse[k], dtype=float)
    return np.maximum(gain, 1e-3)


def _specular_gain(model: mujoco.MjModel, shininess: float, point: np.ndarray, eye: np.ndarray | None,
                   forward: np.ndarray | None) -> np.ndarray:
    """(3,) the lights' specular on a surface facing up at ``point``, seen from a camera at ``eye``
    looking along ``forward`` (None: straight from above, looking down), for a material of
    ``shininess``. MuJoCo's viewer is local: the view direction runs from the surface to the
    camera, so a highlight fades towards the picture's edges even under an orthographic camera.
    Phong: each light's specular times the power (128 times the shininess) of the cosine between
    the surface's normal (up) and the half-way vector of the light's and the view's directions;
    the headlight is a directional light along the camera's axis."""
    view = np.array([0.0, 0.0, 1.0]) if eye is None else np.asarray(eye, dtype=float) - point
    view = view / max(np.linalg.norm(view), 1e-12)
    exponent = 128.0 * shininess

    def highlight(towards_light: np.ndarray) -> float:
        if towards_light[2] <= 0.0:
            return 0.0
        half = towards_light + view
        return max(0.0, half[2] / max(np.linalg.norm(half), 1e-12)) ** exponent

    axis = np.array([0.0, 0.0, -1.0]) if forward is None else np.asarray(forward, dtype=float)
    gain = np.asarray(model.vis.headlight.specular, dtype=float) * highlight(-axis / max(np.linalg.norm(axis), 1e-12))
    for k in range(model.nlight):
        if not model.light_active[k]:
            continue
        towards = -np.asarray(model.light_dir[k], dtype=float)
        gain = gain + np.asarray(model.light_specular[k], dtype=float) * highlight(towards / max(np.linalg.norm(towards), 1e-12))
    return gain


def _material_of(model: mujoco.MjModel, geom: int) -> int:
    """The material whose colour ``geom`` shows, or -1 (an explicit geom rgba wins, as in MuJoCo)."""
    material = int(model.geom_matid[geom])
    if material >= 0 and np.allclose(model.geom_rgba[geom], MUJOCO_DEFAULT_RGBA):
        return material
    return -1


def _texture_mean(model: mujoco.MjModel, material: int) -> np.ndarray | None:
    """Mean RGB (0..1) of ``material``'s colour texture, or None when it has none."""
    texture = int(model.mat_texid[material][mujoco.mjtTextureRole.mjTEXROLE_RGB]) if material >= 0 else -1
    if texture < 0:
        return None
    channels = int(model.tex_nchannel[texture])
    count = int(model.tex_width[texture]) * int(model.tex_height[texture]) * channels
    pixels = model.tex_data[int(model.tex_adr[texture]):int(model.tex_adr[texture]) + count]
    return pixels.reshape(-1, channels)[:, :3].mean(axis=0) / 255.0


def _surface_rgb(model: mujoco.MjModel, geom: int, gain: np.ndarray, eye: np.ndarray | None = None,
                 forward: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """(RGB as drawn from above, alpha) of the centre of ``geom``'s top, seen from a camera at
    ``eye`` looking along ``forward`` (None: straight from above)."""
    material = _material_of(model, geom)
    rgba = np.asarray(model.mat_rgba[material] if material >= 0 else model.geom_rgba[geom], dtype=float)
    finish = int(model.geom_matid[geom])  # the material's specular applies even under an explicit rgba
    specular, shininess = ((float(model.mat_specular[finish]), float(model.mat_shininess[finish])) if finish >= 0
                           else MUJOCO_DEFAULT_SPECULAR)
    top = np.asarray(model.geom_pos[geom], dtype=float) + np.array([0.0, 0.0, float(model.geom_rbound[geom])])
    if model.geom_type[geom] == mujoco.mjtGeom.mjGEOM_BOX:
        top[2] = float(model.geom_pos[geom][2] + model.geom_size[geom][2])
    lit = np.minimum(1.0, rgba[:3] * gain + specular * _specular_gain(model, shininess, top, eye, forward))
    texture = _texture_mean(model, material)
    return (lit * texture if texture is not None else lit), float(rgba[3])


def _is_scenery(model: mujoco.MjModel, geom: int) -> bool:
    """A static obstacle of the scene (on the world body, in the obstacle group)."""
    return int(model.geom_bodyid[geom]) == 0 and int(model.geom_group[geom]) == OBSTACLE_GROUP


def floor_rgb(model: mujoco.MjModel, gain: np.ndarray | None = None) -> np.ndarray:
    """RGB (0..1) of the scene's floor as drawn from above: its largest plane's (mid grey if it has none)."""
    gain = top_light_gain(model) if gain is None else gain
    planes = [g for g in range(model.ngeom)
              if _is_scenery(model, g) and model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE]
    if not planes:
        return np.full(3, 0.5)
    largest = max(planes, key=lambda g: float(model.geom_size[g][0] * model.geom_size[g][1]))
    return _surface_rgb(model, largest, gain)[0]


def scenery_legend(model: mujoco.MjModel, eye: np.ndarray | None = None,
                   forward: np.ndarray | None = None) -> list[tuple[str, np.ndarray]]:
    """The legend's entries of the scene's visible obstacles: one per material (its name, ``_``
    as spaces; "obstacle" for geoms without one), in the colour its most opaque geom
    shows at the centre of its top seen from a camera at ``eye`` looking along ``forward``
    (None: straight from above, looking down), a see-through one blended over the floor. Planes (floors) are the background
    and not listed; fully transparent geoms are not drawn."""
    gain = top_light_gain(model)
    floor = floor_rgb(model, gain)
    entries: dict[str, tuple[float, np.ndarray]] = {}
    for g in range(model.ngeom):
        if not _is_scenery(model, g) or model.geom_type[g] == mujoco.mjtGeom.mjGEOM_PLANE:
            continue
        rgb, alpha = _surface_rgb(model, g, gain, eye, forward)
        if alpha <= 0.0:
            continue
        material = int(model.geom_matid[g])
        name = mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_MATERIAL, material) if material >= 0 else None
        label = (name or "obstacle").replace("_", " ")
        if label not in entries or alpha > entries[label][0]:
            entries[label] = (alpha, alpha * rgb + (1.0 - alpha) * floor)
    return [(label, np.array([*rgb, 1.0], dtype=np.float32)) for label, (_, rgb) in entries.items()]
