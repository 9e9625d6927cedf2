"""Checks a run's inputs before anything is built or written.

``check_scenario`` takes a loaded :class:`~sim.scenario.Scenario` (its
fields were already type- and range-checked by :mod:`sim.config`) and
checks what needs the scene: the MJCF parses (MuJoCo's reason kept), robots
start apart, inside the scene and clear of obstacles, ground robots have a
floor under them, targets stay inside the scene. ``check_output_folder``
checks that ``--out`` can be written. Both raise :class:`ConfigError`
naming the field; neither builds the robots' world nor leaves a byte
behind, so a sweep can call them on every trial before it runs any.

``tick_violation`` is the per-tick physical sanity check the loop (and the
tuning page) apply: a robot that leaves the scene, falls or tips over.
"""

from __future__ import annotations

import dataclasses
import math
import os
from pathlib import Path

import mujoco
import numpy as np

from sim.compiled import kernel
from sim.config import ConfigError, allows_infinity
from sim.scenario import Scenario

FLOOR_PROBE_HEIGHT_M = 0.05  # ground robots: a floor must lie within this below the wheels' contact height ...
FLOOR_PROBE_DEPTH_M = 0.10  # ... looking this far down
BOUNDS_MARGIN_M = 1.0  # a robot this far outside the scene bounds has left the scene
FALL_DEPTH_M = 0.10  # a ground robot this far below its start height has fallen
TIP_COSINE = 0.5  # a ground robot whose up axis is more than 60 degrees from vertical has tipped over


def check_numbers(obj, field: str = "") -> None:
    """ConfigError for any NaN (or infinity where the field does not allow
    it) in a tree of config dataclasses; a Scenario built in code passes
    through here as a loaded file passes through :func:`sim.config.build`."""
    if dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            if f.init:
                value = getattr(obj, f.name)
                name = f"{field}.{f.name}" if field else f.name
                if isinstance(value, float) and math.isinf(value) and allows_infinity(f):
                    continue
                check_numbers(value, name)
    elif isinstance(obj, (list, tuple)):
        for i, value in enumerate(obj):
            check_numbers(value, f"{field}.{i}")
    elif isinstance(obj, float) and not math.isfinite(obj):
        raise ConfigError(field, f"must be a finite number, got {obj}")


def check_starts_apart(scenario: Scenario) -> None:
    """Refuse two robots whose bodies would overlap at the start."""
    from sim.world import ROBOT_RADIUS_M, _robot_fields

    starts = scenario.robot_starts()
    if len(starts) < 2:
        return
    p = np.array([[x, y, 0.0 if kind == "ground" else z] for kind, (x, y, z) in starts], dtype=float)
    radius = np.array([ROBOT_RADIUS_M[kind] for kind, _ in starts])
    distance = np.linalg.norm(p[:, None] - p[None], axis=-1)
    clash = distance < radius[:, None] + radius[None]
    np.fill_diagonal(clash, False)
    if clash.any():
        i, j = (int(k) for k in np.argwhere(clash)[0])
        where = _robot_fields(scenario)
        raise ConfigError(where[j], f"starts {distance[i, j]:.3f} m from {where[i]}, closer than their bodies allow "
                                    f"({radius[i] + radius[j]:.3f} m)")


def check_floor(scenario: Scenario, model: mujoco.MjModel, data: mujoco.MjData) -> None:
    """Refuse a ground robot with nothing to stand on (no colliding geom just
    under its wheels)."""
    from sim.world import _robot_fields

    down = np.array([0.0, 0.0, -1.0])
    geom = np.zeros(1, dtype=np.int32)
    for (kind, (x, y, _)), where in zip(scenario.robot_starts(), _robot_fields(scenario)):
        if kind != "ground":
            continue
        origin = np.array([x, y, FLOOR_PROBE_HEIGHT_M], dtype=float)
        hit = mujoco.mj_ray(model, data, origin, down, None, 1, -1, geom)
        collides = hit >= 0 and (model.geom_contype[geom[0]] or model.geom_conaffinity[geom[0]])
        if not collides or hit > FLOOR_PROBE_HEIGHT_M + FLOOR_PROBE_DEPTH_M:
            raise ConfigError(where, f"a ground robot at ({x:g}, {y:g}) has nothing to stand on: the scene has no "
                                     f"floor within {FLOOR_PROBE_DEPTH_M:g} m below z = 0")


def check_scenario(scenario: Scenario) -> None:
    """Everything about a loaded scenario that can be checked before the
    robots' world is built: numbers, sizes (sim.config / sim.scenario did
    most), starts apart, the scene file, floors, placements. ConfigError."""
    from sim.targets import nominal_path_samples
    from sim.world import extract_obstacles, load_scene_spec, scene_bounds, validate_placements

    check_numbers(scenario)
    period = scenario.physics.control_period_s
    if round(scenario.duration_s / period) < 1:
        raise ConfigError("duration_s", f"must last at least one control period ({period:g} s), "
                                        f"got {scenario.duration_s:g}")
    check_starts_apart(scenario)
    spec = load_scene_spec(scenario.scene_path)
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_forward(model, data)
    obstacles = extract_obstacles(model, data)
    bounds = scene_bounds(model, obstacles)
    if not np.all(np.isfinite(bounds)) or np.any(bounds[1] < bounds[0]):
        raise ConfigError("scene", f"{scenario.scene_path}: tether_bounds must be finite with lo <= hi, "
                                   f"got {bounds.tolist()}")
    samples = [nominal_path_samples(t) for t in scenario.targets]
    validate_placements(scenario, obstacles, bounds, samples)
    check_floor(scenario, model, data)


def check_output_folder(out: str | Path, flag: str = "--out") -> None:
    """ConfigError unless ``out`` may hold a run's files under tether's
    output policy (:func:`sim.outputs.check_out_folder`): new, empty, or a
    folder a tether run wrote; not ``/``, the home folder or an empty path;
    writable (the run's files are written beside it first, then moved in).
    Leaves nothing behind."""
    from sim.outputs import check_out_folder

    check_out_folder(out, "run", flag)


NON_FINITE = 1  # _tick_sanity's codes (0: sane)
_OUTSIDE, _FALLEN, _TIPPED = 2, 3, 4


@kernel
def _tick_sanity(qpos, qvel, qpos_adr, lo, hi, ground, start_height):
    """(code, robot) of the first insanity in one pass over the state, in
    :func:`tick_violation`'s order: a non-finite qpos or qvel entry, then any
    robot outside [lo, hi], then a ground robot fallen, then one tipped."""
    for k in range(qpos.shape[0]):
        if not np.isfinite(qpos[k]):
            return NON_FINITE, -1
    for k in range(qvel.shape[0]):
        if not np.isfinite(qvel[k]):
            return NON_FINITE, -1
    for i in range(qpos_adr.shape[0]):
        a = qpos_adr[i]
        for d in range(3):
            if qpos[a + d] < lo[d] or qpos[a + d] > hi[d]:
                return _OUTSIDE, i
    for i in ground:
        if qpos[qpos_adr[i] + 2] < start_height[i] - FALL_DEPTH_M:
            return _FALLEN, i
    for i in ground:
        a = qpos_adr[i]
        q1, q2 = qpos[a + 4], qpos[a + 5]
        if 1.0 - 2.0 * (q1 ** 2 + q2 ** 2) < TIP_COSINE:
            return _TIPPED, i
    return 0, -1


def sanity_limits(world) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lo, hi, ground robots' indices) of :func:`tick_sanity` for ``world``: the scene bounds
    widened by ``BOUNDS_MARGIN_M``, m."""
    return world.bounds[0] - BOUNDS_MARGIN_M, world.bounds[1] + BOUNDS_MARGIN_M, world.kind_index["ground"]


def tick_sanity(world, qpos: np.ndarray, qvel: np.ndarray, qpos_adr: np.ndarray,
                start_height: np.ndarray, limits: tuple | None = None) -> tuple[int, int]:
    """One compiled pass over MuJoCo's ``qpos`` / ``qvel``: ``(0, -1)`` if the
    state is sane, ``(NON_FINITE, -1)`` if an entry is NaN or inf, else a code
    and the robot for :func:`tick_violation` to name (``qpos_adr``: each
    robot's free-joint qpos address, int64). ``limits``: :func:`sanity_limits`
    of ``world`` when the caller keeps them (computed here otherwise)."""
    lo, hi, ground = limits if limits is not None else sanity_limits(world)
    return _tick_sanity(qpos, qvel, qpos_adr, lo, hi, ground, start_height)


def tick_violation(world, code: int, robot: int, qpos: np.ndarray, qpos_adr: np.ndarray) -> str | None:
    """Physical sanity of one tick's state, from :func:`tick_sanity`'s
    ``(code, robot)``: a robot outside the scene bounds (by more than
    ``BOUNDS_MARGIN_M``), a ground robot fallen below its start height (by
    more than ``FALL_DEPTH_M``) or tipped over. Returns the reason, or None."""
    if robot < 0:
        return None
    name, position = world.robot_names[robot], qpos[qpos_adr[robot]:qpos_adr[robot] + 3]
    if code == _OUTSIDE:
        return f"{name} left the scene bounds at {tuple(round(float(v), 2) for v in position)}"
    if code == _FALLEN:
        return f"{name} fell to z = {position[2]:.2f} m (nothing to stand on)"
    return f"{name} tipped over"
