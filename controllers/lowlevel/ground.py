"""Differential-drive ground robot control: single-integrator commands to wheels.

Numpy and small compiled kernels (:mod:`sim.compiled`), never imports
MuJoCo; batched over all N ground robots (all share one
:class:`GroundRobotParams`). The heading's trigonometry stays numpy's (its
vectorised sin/cos/arctan2 differ from libm's in the last bit); the kernels
do the same elementwise arithmetic as the numpy expressions they replaced,
so wheel commands are bit-identical to them.

Seed 000 plans for single integrators, p(t+1) = p(t) + u(t). A differential
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

from dataclasses import dataclass

import numpy as np

from sim.compiled import kernel

DEFAULT_OFFSET = 0.02  # m, distance of the controlled point ahead of the axle


@dataclass(frozen=True)
class GroundRobotParams:
    """Geometry and limits of one differential-drive model (every copy shares them).

    Extracted from a compiled MuJoCo model by ``sim.robot_params``.
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


def yaw_from_quaternion(q: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (w, x, y, z), body-to-world -> (N,) heading of body x, rad."""
    q = np.asarray(q, dtype=float)
    assert q.ndim == 2 and q.shape[1] == 4, q.shape
    w, x, y, z = q.T
    return np.arctan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))


def offset_point(position: np.ndarray, yaw: np.ndarray, offset: float = DEFAULT_OFFSET,
                 cos_sin: tuple[np.ndarray, np.ndarray] | None = None) -> np.ndarray:
    """Point P_b (N, 2), m, world frame, ``offset`` m ahead of the axle centre.

    position: (N, 2) or (N, 3) robot centre (only x, y are used), m, world frame.
    yaw: (N,) heading, rad. cos_sin: ``(np.cos(yaw), np.sin(yaw))`` when the caller has them.
    """
    position = np.asarray(position, dtype=float)
    yaw = np.asarray(yaw, dtype=float)
    n = len(yaw)
    assert yaw.shape == (n,), yaw.shape
    assert position.ndim == 2 and position.shape[0] == n and position.shape[1] in (2, 3), position.shape
    c, s = cos_sin if cos_sin is not None else (np.cos(yaw), np.sin(yaw))
    return position[:, :2] + offset * np.column_stack([c, s])


@kernel
def _unicycle_kernel(velocity, c, s, offset):
    n = velocity.shape[0]
    v, omega = np.empty(n), np.empty(n)
    for i in range(n):
        v[i] = c[i] * velocity[i, 0] + s[i] * velocity[i, 1]
        omega[i] = (-s[i] * velocity[i, 0] + c[i] * velocity[i, 1]) / offset
    return v, omega


def unicycle_command(velocity: np.ndarray, yaw: np.ndarray, offset: float = DEFAULT_OFFSET,
                     cos_sin: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Forward speed v (N,), m/s, and turn rate omega (N,), rad/s, that move
    the offset point with ``velocity`` (N, 2), m/s, world frame (``cos_sin``:
    ``(np.cos(yaw), np.sin(yaw))`` when the caller has them)."""
    velocity = np.asarray(velocity, dtype=float)
    yaw = np.asarray(yaw, dtype=float)
    n = len(yaw)
    assert velocity.shape == (n, 2), velocity.shape
    assert yaw.shape == (n,), yaw.shape
    assert offset > 0.0, offset
    c, s = cos_sin if cos_sin is not None else (np.cos(yaw), np.sin(yaw))
    return _unicycle_kernel(velocity, c, s, float(offset))


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
def _wheel_kernel(v, omega, r, half, wheel_max, left_direction, right_direction):
    n = v.shape[0]
    wheels = np.empty((n, 2))
    for i in range(n):
        left, right = (v[i] - half * omega[i]) / r, (v[i] + half * omega[i]) / r
        scale = min(1.0, wheel_max / max(max(abs(left), abs(right)), 1e-12))
        # np.clip's min(max(.)) for round-off, then the motors' sense.
        wheels[i, 0] = min(max(left * scale, -wheel_max), wheel_max) * left_direction
        wheels[i, 1] = min(max(right * scale, -wheel_max), wheel_max) * right_direction
    return wheels


def track_velocity(
    params: GroundRobotParams,
    velocity: np.ndarray,
    yaw: np.ndarray,
    offset: float = DEFAULT_OFFSET,
    cos_sin: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Wheel angular velocities (N, 2), rad/s (left, right), that move the
    offset point (see :func:`offset_point`) with the single-integrator
    velocity command ``velocity`` (N, 2), m/s, world frame; ``yaw`` (N,), rad.

    Commands beyond the wheel limits are slowed down along the same curvature,
    so the offset point then moves slower than asked (and, while turning, not
    exactly along ``velocity``).
    """
    v, omega = unicycle_command(velocity, yaw, offset, cos_sin)
    return wheel_speeds(params, v, omega)


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
