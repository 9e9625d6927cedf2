"""World assembly: one scene + N robots + M targets, compiled once.

Each robot file is attached N times through ``mujoco.MjSpec.attach`` with a
name prefix (``quad0/``, ``ground3/``, ``target1/``); every id the loop needs
is looked up by name here, once. Static collision geoms of the scene (group
``OBSTACLE_GROUP``) become the :class:`~sim.geometry.Boxes` obstacle set that
pure-math code (planners, clearance) uses.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np

from sim.config import ConfigError
from sim.geometry import Boxes, point_clearance
from sim.scenario import MODELS_DIR, Scenario

OBSTACLE_GROUP = 0  # scene geoms that collide and block line of sight
ROBOT_FILES = {
    "quadrotor": MODELS_DIR / "robots" / "quadrotor.xml",
    "ground": MODELS_DIR / "robots" / "ground_robot.xml",
}
TARGET_FILE = MODELS_DIR / "robots" / "target.xml"
ROBOT_PREFIX = {"quadrotor": "quad", "ground": "ground"}
ROBOT_RADIUS_M = {"quadrotor": 0.25, "ground": 0.036}  # footprint radius for start checks
SENSOR_SITE = {"quadrotor": "imu", "ground": "sensor"}
INFINITE_PLANE_HALF_SIZE = 1e3  # m: a plane with size 0 is infinite
PLANE_THICKNESS_M = 1.0  # planes become boxes this thick below their surface


def obstacle_geomgroup() -> np.ndarray:
    """mj_ray geomgroup mask that sees only static obstacles."""
    mask = np.zeros(6, dtype=np.uint8)
    mask[OBSTACLE_GROUP] = 1
    return mask


@dataclass
class World:
    """The compiled model plus the id tables of every robot and target."""

    model: mujoco.MjModel
    data: mujoco.MjData
    scene_path: Path
    robot_names: tuple[str, ...]
    robot_kinds: tuple[str, ...]
    body_ids: np.ndarray  # (N,) robot base bodies
    qpos_adr: np.ndarray  # (N,) freejoint qpos start (x y z qw qx qy qz)
    qvel_adr: np.ndarray  # (N,) freejoint qvel start (v_world, w_body)
    sensor_site_ids: np.ndarray  # (N,)
    actuator_ids: dict[str, np.ndarray]  # kind -> (N_kind, n_act) actuator ids
    kind_index: dict[str, np.ndarray]  # kind -> robot indices of that kind
    target_mocap_ids: np.ndarray  # (M,)
    obstacles: Boxes
    bounds: np.ndarray  # (2, 3)
    # (K,) radio loss per obstacle box, dB; NaN: the scene gives none (obstacle_wall_losses)
    wall_loss_db: np.ndarray | None = None

    @property
    def n_robots(self) -> int:
        return len(self.robot_names)


def _attach(spec: mujoco.MjSpec, path: Path, prefix: str, pos) -> None:
    child = mujoco.MjSpec.from_file(str(path))
    for key in list(child.keys):  # robot keyframes are per-file; the loop sets state
        child.delete(key)
    frame = spec.worldbody.add_frame(pos=[float(v) for v in pos])
    spec.attach(child, prefix=prefix, frame=frame)


DEFAULT_HEADLIGHT = {"ambient": (0.3, 0.3, 0.3), "diffuse": (0.3, 0.3, 0.3), "specular": (0.0, 0.0, 0.0)}
DEFAULT_SUN_DIFFUSE = (0.35, 0.35, 0.35)


def add_default_light(spec: mujoco.MjSpec, bounds) -> None:
    """A scene that sets no light gets a default one (docs/models.md): a soft headlight and a
    directional sun straight down from above the scene, summing to about full light on a floor
    seen from above, so its colours show as set (MuJoCo's own default washes a pale floor out
    to white). Neither has a specular highlight, so colours show as set everywhere in the picture.
    Pictures only: lights change no physics, sensing or radio."""
    headlight = spec.visual.headlight
    headlight.ambient, headlight.diffuse, headlight.specular = (DEFAULT_HEADLIGHT[k]
                                                                 for k in ("ambient", "diffuse", "specular"))
    lo, hi = (np.asarray(b, dtype=float) for b in bounds)
    centre = (lo + hi) / 2
    spec.worldbody.add_light(name="tether_default_sun", pos=(centre[0], centre[1], hi[2] + float(np.ptp((lo, hi), axis=0).max())),
                             dir=(0.0, 0.0, -1.0), type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL, castshadow=False,
                             diffuse=DEFAULT_SUN_DIFFUSE, specular=(0.0, 0.0, 0.0))


def load_scene_spec(scene_path: Path) -> mujoco.MjSpec:
    try:
        spec = mujoco.MjSpec.from_file(str(scene_path))
        spec.compile()
    except Exception as err:  # MuJoCo raises ValueError with a parser message over several lines
        reason = " ".join(line.strip() for line in str(err).splitlines() if line.strip()) or type(err).__name__
        raise ConfigError("scene", f"{scene_path} is not a valid MJCF scene: {reason}") from None
    return spec


def extract_obstacles(model: mujoco.MjModel, data: mujoco.MjData) -> Boxes:
    """Oriented boxes for every static obstacle geom (world body, obstacle group).

    Boxes are exact; planes become thick slabs below their surface; other
    shapes are replaced by their oriented bounding box (conservative).
    """
    centers, halves, rotations = [], [], []
    for g in obstacle_geom_ids(model):
        rot = data.geom_xmat[g].reshape(3, 3)
        center = data.geom_xpos[g].copy()
        gtype = model.geom_type[g]
        if gtype == mujoco.mjtGeom.mjGEOM_BOX:
            half = model.geom_size[g].copy()
        elif gtype == mujoco.mjtGeom.mjGEOM_PLANE:
            sx, sy = model.geom_size[g][:2]
            half = np.array([sx or INFINITE_PLANE_HALF_SIZE, sy or INFINITE_PLANE_HALF_SIZE, PLANE_THICKNESS_M / 2])
            center = center - rot[:, 2] * PLANE_THICKNESS_M / 2
        else:
            aabb = model.geom_aabb[g]  # local centre (3) then half sizes (3)
            center = center + rot @ aabb[:3]
            half = aabb[3:].copy()
        centers.append(center)
        halves.append(half)
        rotations.append(rot.copy())
    if not centers:
        return Boxes(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3, 3)))
    return Boxes(np.array(centers), np.array(halves), np.array(rotations))


def obstacle_geom_ids(model: mujoco.MjModel) -> list[int]:
    """The static obstacle geoms (world body, obstacle group, colliding), in :func:`extract_obstacles`' order."""
    return [g for g in range(model.ngeom)
            if model.geom_bodyid[g] == 0 and model.geom_group[g] == OBSTACLE_GROUP
            and not (model.geom_contype[g] == 0 and model.geom_conaffinity[g] == 0)]


WALL_LOSS_NUMERIC = "tether_wall_loss_db"  # the scene's default; "tether_wall_loss_db/GEOM" for one geom


def obstacle_wall_losses(model: mujoco.MjModel) -> np.ndarray:
    """(K,) radio loss of each obstacle box, dB, in :func:`extract_obstacles`' order; NaN where the
    scene says nothing (the scenario's ``radio.wall_loss_db`` applies). A geom's own
    ``tether_wall_loss_db/NAME`` numeric wins over the scene's ``tether_wall_loss_db``."""
    ids = obstacle_geom_ids(model)
    names = {model.geom(g).name: k for k, g in enumerate(ids) if model.geom(g).name}
    default, own = np.nan, {}
    for n in range(model.nnumeric):
        name = model.numeric(n).name
        if name != WALL_LOSS_NUMERIC and not name.startswith(WALL_LOSS_NUMERIC + "/"):
            continue
        data = np.asarray(model.numeric(n).data, dtype=float)
        if data.shape != (1,) or not np.isfinite(data[0]) or data[0] < 0:
            raise ConfigError("scene", f"numeric {name!r} must be one finite loss >= 0 dB, got {data.tolist()}")
        if name == WALL_LOSS_NUMERIC:
            default = float(data[0])
            continue
        geom = name[len(WALL_LOSS_NUMERIC) + 1:]
        if geom not in names:
            raise ConfigError("scene", f"numeric {name!r} names no static obstacle geom of group {OBSTACLE_GROUP}")
        own[names[geom]] = float(data[0])
    losses = np.full(len(ids), default)
    for k, value in own.items():
        losses[k] = value
    return losses


def scene_bounds(model: mujoco.MjModel, obstacles: Boxes) -> np.ndarray:
    """Free-space bounds: the scene's ``tether_bounds`` numeric, else the
    extent of its finite obstacles."""
    try:
        data = model.numeric("tether_bounds").data
        return np.array(data, dtype=float).reshape(2, 3)
    except KeyError:
        pass
    finite = np.all(obstacles.half_sizes < INFINITE_PLANE_HALF_SIZE / 2, axis=1)
    if not finite.any():
        return np.array([[-10.0, -10.0, 0.0], [10.0, 10.0, 5.0]])
    corners = np.abs(obstacles.rotations[finite]) @ obstacles.half_sizes[finite][..., None]
    lo = (obstacles.centers[finite] - corners[..., 0]).min(axis=0)
    hi = (obstacles.centers[finite] + corners[..., 0]).max(axis=0)
    lo[2] = max(lo[2], 0.0)
    return np.array([lo, hi])


def _robot_fields(scenario: Scenario) -> list[str]:
    """The scenario field that placed each robot, for error messages."""
    out = []
    for g, group in enumerate(scenario.robots):
        for k in range(len(group.positions())):
            out.append(f"robots.{g}.starts.{k}" if group.count is None else f"robots.{g} (robot {k} of the spawn grid)")
    return out


def validate_placements(scenario: Scenario, obstacles: Boxes, bounds: np.ndarray, target_paths) -> None:
    """Refuse robots and targets inside obstacles or outside the scene."""
    for (kind, start), where in zip(scenario.robot_starts(), _robot_fields(scenario)):
        p = np.array(start, dtype=float)
        shown = tuple(float(v) for v in p)
        radius = ROBOT_RADIUS_M[kind]
        lo, hi = bounds[0].copy(), bounds[1].copy()
        if kind == "ground":
            lo[2], hi[2] = -np.inf, np.inf
        if np.any(p < lo) or np.any(p > hi):
            raise ConfigError(where, f"start {shown} lies outside the scene bounds {bounds[0].tolist()} .. {bounds[1].tolist()}")
        probe = p.copy()
        if kind == "ground":
            probe[2] = max(bounds[0][2], 0.0) + 0.05  # check the footprint just above the floor
        if point_clearance(obstacles, probe[None])[0] < radius:
            raise ConfigError(where, f"start {shown} is inside or within {radius} m of an obstacle")
    for a, samples in enumerate(target_paths):
        outside = np.any((samples < bounds[0]) | (samples > bounds[1]), axis=1)
        if outside.any():
            raise ConfigError(f"targets.{a}", f"path leaves the scene bounds at {tuple(float(v) for v in np.round(samples[outside][0], 3))}")
        blocked = point_clearance(obstacles, samples) <= 0.0
        if blocked.any():
            raise ConfigError(f"targets.{a}", f"path passes through an obstacle at {tuple(float(v) for v in np.round(samples[blocked][0], 3))}")


def build_world(scenario: Scenario, target_starts: np.ndarray, target_path_samples=()) -> World:
    """Compile scene + robots + targets; validate placements (ConfigError)."""
    scene_path = scenario.scene_path
    spec = load_scene_spec(scene_path)
    scene_model = spec.compile()
    scene_data = mujoco.MjData(scene_model)
    mujoco.mj_forward(scene_model, scene_data)
    obstacles = extract_obstacles(scene_model, scene_data)
    wall_losses = obstacle_wall_losses(scene_model)
    bounds = scene_bounds(scene_model, obstacles)
    validate_placements(scenario, obstacles, bounds, target_path_samples)
    if scene_model.nlight == 0:
        add_default_light(spec, bounds)

    names, kinds = [], []
    counters = {kind: 0 for kind in ROBOT_FILES}
    for kind, start in scenario.robot_starts():
        name = f"{ROBOT_PREFIX[kind]}{counters[kind]}"
        counters[kind] += 1
        _attach(spec, ROBOT_FILES[kind], f"{name}/", (0.0, 0.0, 0.0))
        names.append(name)
        kinds.append(kind)
    for a, start in enumerate(target_starts):
        _attach(spec, TARGET_FILE, f"target{a}/", start)
    try:
        model = spec.compile()
    except ValueError as err:  # the scene compiled alone: a clash is with the robots' or targets' names
        if "repeated name" not in str(err):
            raise
        reason = " ".join(str(err).replace("Error:", "").split())
        raise ConfigError("scene", f"{scene_path.name}: {reason}: the scene names an element like one of the "
                                   f"robots or targets tether adds ({', '.join(f'{n}/...' for n in names[:3])}"
                                   f"{', target0/...' if len(target_starts) else ''}): rename it in the "
                                   "scene") from None
    data = mujoco.MjData(model)

    body_ids = np.array([model.body(f"{n}/base").id for n in names], dtype=int)
    joint_ids = [model.joint(f"{n}/root").id for n in names]
    qpos_adr = np.array([model.jnt_qposadr[j] for j in joint_ids], dtype=int)
    qvel_adr = np.array([model.jnt_dofadr[j] for j in joint_ids], dtype=int)
    sensor_sites = np.array([model.site(f"{n}/{SENSOR_SITE[k]}").id for n, k in zip(names, kinds)], dtype=int)
    kind_index = {k: np.array([i for i, kk in enumerate(kinds) if kk == k], dtype=int) for k in ROBOT_FILES}
    actuator_names = {"quadrotor": ["thrust1", "thrust2", "thrust3", "thrust4"], "ground": ["left_wheel", "right_wheel"]}
    actuator_ids = {
        k: np.array([[model.actuator(f"{names[i]}/{a}").id for a in actuator_names[k]] for i in idx], dtype=int).reshape(len(idx), len(actuator_names[k]))
        for k, idx in kind_index.items()
    }
    mocap_ids = np.array([model.body_mocapid[model.body(f"target{a}/base").id] for a in range(len(target_starts))], dtype=int)

    world = World(
        model=model, data=data, scene_path=scene_path, robot_names=tuple(names), robot_kinds=tuple(kinds),
        body_ids=body_ids, qpos_adr=qpos_adr, qvel_adr=qvel_adr, sensor_site_ids=sensor_sites,
        actuator_ids=actuator_ids, kind_index=kind_index, target_mocap_ids=mocap_ids,
        obstacles=obstacles, bounds=bounds, wall_loss_db=wall_losses,
    )
    place_robots(world, [np.array(s, dtype=float) for _, s in scenario.robot_starts()])
    return world


def place_robots(world: World, starts: list[np.ndarray]) -> None:
    """Put every robot at its start, level and at rest. Ground robots keep the
    wheel-contact height of their model file."""
    model, data = world.model, world.data
    mujoco.mj_resetData(model, data)
    for i, start in enumerate(starts):
        adr = world.qpos_adr[i]
        position = start.copy()
        if world.robot_kinds[i] == "ground":
            position[2] = model.body_pos[world.body_ids[i]][2]
        data.qpos[adr : adr + 3] = position
        data.qpos[adr + 3 : adr + 7] = (1.0, 0.0, 0.0, 0.0)
    mujoco.mj_forward(model, data)
