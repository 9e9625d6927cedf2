"""Robot parameters read from a compiled MuJoCo model.

Each robot file is attached N times with a name prefix (``quad0/``,
``ground3/``); the parameters of one copy are looked up by name under its
prefix, once, when the world is built. The bare robot file works with an
empty prefix. The parameter dataclasses live with the (MuJoCo-free)
controllers that use them and are re-exported here.

Quadrotor (``models/robots/quadrotor.xml``): body ``base``, sites and motor
actuators ``thrust1..4``. Ground robot (``models/robots/ground_robot.xml``):
body ``base``, wheel bodies / hinge joints / velocity actuators
``left_wheel`` and ``right_wheel``, tyre geoms ``left_tyre``, ``right_tyre``.
"""

from __future__ import annotations

import mujoco
import numpy as np

from controllers.lowlevel.ground import GroundRobotParams
from controllers.lowlevel.quadrotor import QuadrotorParams

__all__ = ["QuadrotorParams", "GroundRobotParams", "quadrotor_params", "ground_robot_params"]

QUAD_BASE = "base"
QUAD_ROTORS = ("thrust1", "thrust2", "thrust3", "thrust4")  # site and actuator names
GROUND_BASE = "base"
GROUND_WHEELS = ("left_wheel", "right_wheel")  # body, joint and actuator names
GROUND_TYRES = ("left_tyre", "right_tyre")

_TOL = 1e-9


def _id(model: mujoco.MjModel, obj: mujoco.mjtObj, name: str) -> int:
    i = mujoco.mj_name2id(model, obj, name)
    if i < 0:
        raise KeyError(f"no {obj.name.removeprefix('mjOBJ_').lower()} named {name!r} in the model")
    return i


def _quat_matrix(quat: np.ndarray) -> np.ndarray:
    mat = np.zeros(9)
    mujoco.mju_quat2Mat(mat, np.asarray(quat, dtype=float))
    return mat.reshape(3, 3)


def quadrotor_params(model: mujoco.MjModel, prefix: str = "") -> QuadrotorParams:
    """Parameters of the quadrotor whose element names start with ``prefix``.

    mass: subtree mass of the base body; inertia: the base body's principal
    inertia rotated into the body frame (the robot is one rigid body); rotor
    positions: thrust sites relative to the centre of mass, body frame; drag:
    gear[5] / gear[2] of each motor (yaw torque per newton of thrust); thrust
    limits: ctrlrange times gain times gear[2]. The motors must be plain
    ``motor`` actuators on sites of the base body whose thrust is along the
    body z axis; anything else raises ``ValueError``.
    """
    body = _id(model, mujoco.mjtObj.mjOBJ_BODY, prefix + QUAD_BASE)
    if model.body_rootid[body] != body or model.body_weldid[body] != body:
        raise ValueError("quadrotor base must be a free root body")
    if np.any(model.body_parentid == body):
        raise ValueError("quadrotor base must have no child bodies (one rigid body)")
    mass = float(model.body_subtreemass[body])
    rot_i = _quat_matrix(model.body_iquat[body])
    inertia = rot_i @ np.diag(model.body_inertia[body]) @ rot_i.T
    com = np.array(model.body_ipos[body])

    positions, drag, t_min, t_max = [], [], [], []
    for name in QUAD_ROTORS:
        site = _id(model, mujoco.mjtObj.mjOBJ_SITE, prefix + name)
        act = _id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, prefix + name)
        if model.site_bodyid[site] != body:
            raise ValueError(f"rotor site {prefix + name} is not on the base body")
        if (
            model.actuator_trntype[act] != mujoco.mjtTrn.mjTRN_SITE
            or model.actuator_trnid[act, 0] != site
        ):
            raise ValueError(f"actuator {prefix + name} does not act on site {prefix + name}")
        if model.actuator_biastype[act] != mujoco.mjtBias.mjBIAS_NONE or model.actuator_dyntype[act] != mujoco.mjtDyn.mjDYN_NONE:
            raise ValueError(f"actuator {prefix + name} is not a plain motor")
        gear = np.array(model.actuator_gear[act])
        site_rot = _quat_matrix(model.site_quat[site])
        force_dir = site_rot @ gear[:3]
        torque_dir = site_rot @ gear[3:]
        if np.abs(force_dir[:2]).max() > _TOL or force_dir[2] <= 0 or np.abs(torque_dir[:2]).max() > _TOL:
            raise ValueError(f"rotor {prefix + name} does not push along body z")
        newtons_per_ctrl = float(model.actuator_gainprm[act, 0] * force_dir[2])
        if abs(newtons_per_ctrl - 1.0) > _TOL:
            raise ValueError(f"actuator {prefix + name}: ctrl must be thrust in N (gain x gear = 1)")
        if not model.actuator_ctrllimited[act]:
            raise ValueError(f"actuator {prefix + name} has no ctrlrange (thrust limits)")
        lo, hi = model.actuator_ctrlrange[act]
        positions.append(np.array(model.site_pos[site]) - com)
        drag.append(torque_dir[2] / force_dir[2])
        t_min.append(lo * newtons_per_ctrl)
        t_max.append(hi * newtons_per_ctrl)

    return QuadrotorParams(
        mass=mass,
        inertia=inertia,
        rotor_positions=np.array(positions),
        rotor_drag=np.array(drag),
        thrust_min=np.array(t_min),
        thrust_max=np.array(t_max),
        gravity=float(np.linalg.norm(model.opt.gravity)),
    )


def ground_robot_params(model: mujoco.MjModel, prefix: str = "") -> GroundRobotParams:
    """Parameters of the ground robot whose element names start with ``prefix``.

    wheel radius: radius of the tyre cylinders; half axle: lateral offset of
    the wheel bodies from the base, body frame; wheel speed limit: the velocity
    actuators' ctrlrange (divided by their gear); wheel direction: sign of the
    joint rotation (about the base's y axis) that rolls the robot forward.
    Left and right must be mirror images; otherwise ``ValueError``.
    """
    base = _id(model, mujoco.mjtObj.mjOBJ_BODY, prefix + GROUND_BASE)
    radii, lateral, limits, direction = [], [], [], []
    for wheel, tyre in zip(GROUND_WHEELS, GROUND_TYRES):
        body = _id(model, mujoco.mjtObj.mjOBJ_BODY, prefix + wheel)
        joint = _id(model, mujoco.mjtObj.mjOBJ_JOINT, prefix + wheel)
        act = _id(model, mujoco.mjtObj.mjOBJ_ACTUATOR, prefix + wheel)
        geom = _id(model, mujoco.mjtObj.mjOBJ_GEOM, prefix + tyre)
        if model.body_parentid[body] != base or model.jnt_bodyid[joint] != body or model.geom_bodyid[geom] != body:
            raise ValueError(f"wheel {prefix + wheel}: body, joint and tyre must belong together under the base")
        if model.jnt_type[joint] != mujoco.mjtJoint.mjJNT_HINGE:
            raise ValueError(f"wheel joint {prefix + wheel} is not a hinge")
        if model.actuator_trntype[act] != mujoco.mjtTrn.mjTRN_JOINT or model.actuator_trnid[act, 0] != joint:
            raise ValueError(f"actuator {prefix + wheel} does not drive joint {prefix + wheel}")
        if model.geom_type[geom] != mujoco.mjtGeom.mjGEOM_CYLINDER:
            raise ValueError(f"tyre {prefix + tyre} is not a cylinder")
        axis = _quat_matrix(model.body_quat[body]) @ np.array(model.jnt_axis[joint])
        if np.abs(axis[[0, 2]]).max() > 1e-6:
            raise ValueError(f"wheel axis of {prefix + wheel} is not along the base's y axis")
        if abs(model.body_pos[body, 0]) > 1e-6:
            raise ValueError(f"wheel {prefix + wheel} is not on the base's y axis")
        if not model.actuator_ctrllimited[act]:
            raise ValueError(f"actuator {prefix + wheel} has no ctrlrange")
        gear = float(model.actuator_gear[act, 0])
        lo, hi = model.actuator_ctrlrange[act] / gear
        radii.append(float(model.geom_size[geom, 0]))
        lateral.append(float(model.body_pos[body, 1]))
        limits.append(min(-lo, hi))
        # Spin +1 about axis a at the contact -r z: centre moves with r (a x z) . x
        # i.e. forward iff a_y > 0.
        direction.append(1.0 if axis[1] > 0 else -1.0)

    (r_left, r_right), (y_left, y_right) = radii, lateral
    if abs(r_left - r_right) > 1e-9 or abs(y_left + y_right) > 1e-9 or y_left <= 0:
        raise ValueError("left and right wheels are not mirror images (left at +y)")
    return GroundRobotParams(
        wheel_radius=r_left,
        half_axle=y_left,
        wheel_speed_max=float(min(limits)),
        wheel_direction=(direction[0], direction[1]),
    )
