"""Differential-drive ground robot control: single-integrator commands to wheels.

Small compiled kernels (:mod:`sim.compiled`), never imports MuJoCo; batched
over all N ground robots (all share one :class:`GroundRobotParams`). The
simulation's per-tick path is :func:`track_reference`, one compiled pass from
the body pose to the wheels. The heading is libm's atan2 (numpy's vectorised
arctan2 differs from it in the last bit on some CPUs, so figures computed
with numpy's may differ by round-off).

Intermittent plans for single integrators, p(t+1) = p(t) + u(t). A differential
drive robot (a unicycle: forward speed v, turn rate omega, heading theta) is
not one, but the point P_b a distance b ahead of the wheel axle is
(point-offset feedback linearisation, e.g. Robotarium's si-to-uni mapping)::

    P_b = p + b (cos theta, sin theta)
    dP_b/dt = [[cos theta, -b sin theta], [sin theta, b cos theta]] [v, omega]^T

The matrix is invertible for b > 0, so any planar velocity u of P_b is
produced exactly by::

    v     =  cos theta u_x + sin theta u_y
    omega = (-sin theta u_x + cos theta u_y) / b

The body centre p trails P_b by b and follows its path with a lag that
shrinks as b does; a sideways command makes the robot turn on the spot at a
rate |u| / b. ``DEFAULT_OFFSET`` = 0.02 m puts P_b just inside the front rim
of the 35 mm radius body: small enough that the centre stays within 2 cm of
the planned point, large enough that a full-speed sideways command (0.154 m/s)
asks for 7.7 rad/s of turn, which the wheels can give at reduced speed.

Wheel limits are met by scaling v and omega together (both wheels by the same
factor), which keeps the path curvature omega / v and only slows the robot.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sim.compiled import kernel

DEFAULT_OFFSET = 0.02  # m, distance of the controlled point ahead of the axle


@dataclass(frozen=True)
class GroundRobotParams:
    """Geometry and limits of one differential-drive model (every copy shares them).

    Extracted from a compiled MuJoCo model by ``controllers.lowlevel.model_params``.
    """

    wheel_radius: float  # m
    half_axle: float  # m, lateral distance from the robot centre to each wheel
    wheel_speed_max: float  # rad/s, largest wheel angular velocity command
    # +1 / -1 per wheel (left, right): sign of the joint velocity that drives forward.
    wheel_direction: tuple[float, float] = (1.0, 1.0)

    def __post_init__(self) -> None:
        assert self.wheel_radius > 0 and self.half_axle > 0 and self.wheel_speed_max > 0
        assert len(self.wheel_direction) == 2 and all(abs(s) == 1 for s in self.wheel_direction)

    @property
    def max_speed(self) -> float:
        """Top forward speed, m/s (both wheels at the limit)."""
        return self.wheel_radius * self.wheel_speed_max


@kernel
def _heading(w, x, y, z):
    """Heading of body x about world z, rad, of one quaternion (w, x, y, z)."""
    return math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


@kernel
def _yaw_kernel(q):
    yaw = np.empty(q.shape[0])
    for i in range(q.shape[0]):
        yaw[i] = _heading(q[i, 0], q[i, 1], q[i, 2], q[i, 3])
    return yaw


def yaw_from_quaternion(q: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (w, x, y, z), body-to-world -> (N,) heading of body x, rad."""
    q = np.ascontiguousarray(q, dtype=np.float64)
    assert q.ndim == 2 and q.shape[1] == 4, q.shape
    return _yaw_kernel(q)


def offset_point(position: np.ndarray, yaw: np.ndarray, offset: float = DEFAULT_OFFSET) -> np.ndarray:
    """Point P_b (N, 2), m, world frame, ``offset`` m ahead of the axle centre.

    position: (N, 2) or (N, 3) robot centre (only x, y are used), m, world frame.
    yaw: (N,) heading, rad.
    """
    position = np.asarray(position, dtype=float)
    yaw = np.asarray(yaw, dtype=float)
    n = len(yaw)
    assert yaw.shape == (n,), yaw.shape
    assert position.ndim == 2 and position.shape[0] == n and position.shape[1] in (2, 3), position.shape
    return position[:, :2] + offset * np.column_stack([np.cos(yaw), np.sin(yaw)])


@kernel
def _unicycle(c, s, ux, uy, offset):
    """v, omega of one robot (heading cos c, sin s) moving its offset point with (ux, uy)."""
    return c * ux + s * uy, (-s * ux + c * uy) / offset


@kernel
def _unicycle_kernel(velocity, yaw, offset):
    n = velocity.shape[0]
    v, omega = np.empty(n), np.empty(n)
    for i in range(n):
        v[i], omega[i] = _unicycle(math.cos(yaw[i]), math.sin(yaw[i]), velocity[i, 0], velocity[i, 1], offset)
    return v, omega


def unicycle_command(velocity: np.ndarray, yaw: np.ndarray,
                     offset: float = DEFAULT_OFFSET) -> tuple[np.ndarray, np.ndarray]:
    """Forward speed v (N,), m/s, and turn rate omega (N,), rad/s, that move
    the offset point with ``velocity`` (N, 2), m/s, world frame; ``yaw`` (N,), rad."""
    velocity = np.ascontiguousarray(velocity, dtype=np.float64)
    yaw = np.ascontiguousarray(yaw, dtype=np.float64)
    n = len(yaw)
    assert velocity.shape == (n, 2), velocity.shape
    assert yaw.shape == (n,), yaw.shape
    assert offset > 0.0, offset
    return _unicycle_kernel(velocity, yaw, float(offset))


def wheel_speeds(params: GroundRobotParams, v: np.ndarray, omega: np.ndarray) -> np.ndarray:
    """Wheel angular velocity commands (N, 2), rad/s, columns (left, right).

    v: (N,) forward speed, m/s; omega: (N,) turn rate, rad/s (counter-clockwise
    positive). If a wheel would exceed ``wheel_speed_max`` both are scaled by
    the same factor, which keeps the curvature omega / v.
    """
    v = np.asarray(v, dtype=float)
    omega = np.asarray(omega, dtype=float)
    n = len(v)
    assert v.shape == (n,) and omega.shape == (n,), (v.shape, omega.shape)
    return _wheel_kernel(v, omega, params.wheel_radius, params.half_axle, params.wheel_speed_max,
                         float(params.wheel_direction[0]), float(params.wheel_direction[1]))


@kernel
def _wheels(v, omega, r, half, wheel_max, left_direction, right_direction):
    """Left and right wheel commands, rad/s, of one robot (see :func:`wheel_speeds`)."""
    left, right = (v - half * omega) / r, (v + half * omega) / r
    scale = min(1.0, wheel_max / max(max(abs(left), abs(right)), 1e-12))
    # np.clip's min(max(.)) for round-off, then the motors' sense.
    return (min(max(left * scale, -wheel_max), wheel_max) * left_direction,
            min(max(right * scale, -wheel_max), wheel_max) * right_direction)


@kernel
def _wheel_kernel(v, omega, r, half, wheel_max, left_direction, right_direction):
    n = v.shape[0]
    wheels = np.empty((n, 2))
    for i in range(n):
        wheels[i, 0], wheels[i, 1] = _wheels(v[i], omega[i], r, half, wheel_max, left_direction, right_direction)
    return wheels


def track_velocity(
    params: GroundRobotParams,
    velocity: np.ndarray,
    yaw: np.ndarray,
    offset: float = DEFAULT_OFFSET,
) -> np.ndarray:
    """Wheel angular velocities (N, 2), rad/s (left, right), that move the
    offset point (see :func:`offset_point`) with the single-integrator
    velocity command ``velocity`` (N, 2), m/s, world frame; ``yaw`` (N,), rad.

    Commands beyond the wheel limits are slowed down along the same curvature,
    so the offset point then moves slower than asked (and, while turning, not
    exactly along ``velocity``).
    """
    v, omega = unicycle_command(velocity, yaw, offset)
    return wheel_speeds(params, v, omega)


@kernel
def _track_reference_kernel(position, quaternion, ref_position, ref_velocity, gain, offset, r, half, wheel_max,
                            left_direction, right_direction):
    wheels = np.empty((position.shape[0], 2))
    for i in range(position.shape[0]):
        yaw = _heading(quaternion[i, 0], quaternion[i, 1], quaternion[i, 2], quaternion[i, 3])
        c, s = math.cos(yaw), math.sin(yaw)
        ux = ref_velocity[i, 0] + gain * (ref_position[i, 0] - (position[i, 0] + offset * c))
        uy = ref_velocity[i, 1] + gain * (ref_position[i, 1] - (position[i, 1] + offset * s))
        v, omega = _unicycle(c, s, ux, uy, offset)
        wheels[i, 0], wheels[i, 1] = _wheels(v, omega, r, half, wheel_max, left_direction, right_direction)
    return wheels


def track_reference(params: GroundRobotParams, position: np.ndarray, quaternion: np.ndarray,
                    ref_position: np.ndarray, ref_velocity: np.ndarray, gain: float,
                    offset: float = DEFAULT_OFFSET) -> np.ndarray:
    """Wheel angular velocities (N, 2), rad/s (left, right), that make the offset
    point follow a horizontal reference as a single integrator:
    u = ref_velocity + gain (ref_position - P_b), then :func:`track_velocity`.

    position: (N, 3) body centre, m; quaternion: (N, 4) body-to-world (w, x, y, z);
    ref_position, ref_velocity: (N, 2) or (N, 3), m and m/s, world frame (x, y used); gain, 1/s.
    One compiled pass: the same arithmetic as :func:`yaw_from_quaternion`,
    :func:`offset_point` and :func:`track_velocity` in sequence.
    """
    f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    position, quaternion, ref_position, ref_velocity = (f64(position), f64(quaternion), f64(ref_position),
                                                        f64(ref_velocity))
    n = len(position)
    assert position.shape == (n, 3) and quaternion.shape == (n, 4), (position.shape, quaternion.shape)
    assert ref_position.shape[0] == n and ref_velocity.shape[0] == n and ref_position.shape[1] >= 2
    assert gain > 0.0 and offset > 0.0, (gain, offset)
    return _track_reference_kernel(position, quaternion, ref_position, ref_velocity, float(gain), float(offset),
                                   params.wheel_radius, params.half_axle, params.wheel_speed_max,
                                   float(params.wheel_direction[0]), float(params.wheel_direction[1]))


def velocity_to_target(
    position: np.ndarray,
    target: np.ndarray,
    gain: float,
    max_speed: float,
) -> np.ndarray:
    """Saturated proportional velocity command (N, 2), m/s, toward ``target``.

    u = gain * (target - position), scaled down to norm ``max_speed`` when
    longer (direction kept). position, target: (N, 2), m, world frame; gain,
    1/s; max_speed, m/s. Fed to :func:`track_velocity` with ``position`` the
    offset point, the offset point converges exponentially (rate ``gain``) once
    inside ``max_speed / gain`` of the target.
    """
    position = np.asarray(position, dtype=float)
    target = np.asarray(target, dtype=float)
    n = len(position)
    assert position.shape == (n, 2), position.shape
    assert target.shape == (n, 2), target.shape
    assert gain > 0.0 and max_speed > 0.0, (gain, max_speed)
    u = gain * (target - position)
    norm = np.linalg.norm(u, axis=1)
    scale = np.minimum(1.0, max_speed / np.maximum(norm, 1e-12))
    return u * scale[:, None]
