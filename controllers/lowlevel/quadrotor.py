"""Quadrotor low-level control: geometric SE(3) tracking and motor mixing.

Pure math, never imports MuJoCo; batched over all N quadrotors of a team (all
share one :class:`QuadrotorParams`, since they come from one robot file). The
controller (heading trigonometry included, libm's) and the mixer are one
compiled call (numba, cached on disk, see :mod:`sim.compiled`): at N <= 35
numpy's per-call overhead cost ~20x their arithmetic.

Frames and conventions
----------------------
- World frame: SI units, z up, gravity along -z.
- Body frame: the quadrotor's ``base`` body frame (x forward between rotors 1
  and 4, y left, z along the rotor thrust). Positions refer to the body-frame
  origin, which coincides with the centre of mass for our model (the offset,
  if any, is taken into account for the torque arms of the rotors).
- Quaternions are MuJoCo's (w, x, y, z), body-to-world.
- Angular velocity is in the body frame (MuJoCo free-joint ``qvel[3:6]`` and
  the ``gyro`` sensor both give it that way).

Controller
----------
Lee, Leok and McClamroch, "Geometric tracking control of a quadrotor UAV on
SE(3)", CDC 2010, with the gains normalised by mass and inertia (so a gain is
a squared natural frequency or twice a damping rate, independent of the robot)
and two practical additions:

- a bound on the commanded force direction (tilt <= ``max_tilt``, upward force
  >= ``min_thrust_ratio`` m g), so the attitude loop never receives a
  reference it cannot track and the collective thrust stays away from zero,
  where the rotors would lose roll/pitch authority;
- a bound on the heading error (``max_yaw_error``): a far-away yaw reference
  is approached through a heading that leads the current one by at most that
  angle, since the geometric attitude error is not meant for half-turns;
- optional jerk and yaw-rate feedforward: the desired body rates follow from
  differential flatness (Mellinger and Kumar 2011). Without them the desired
  rates are zero and the attitude loop lags a turning reference slightly.

Mixer
-----
The rotors produce, about the centre of mass in the body frame,
``[T, tau_x, tau_y, tau_z] = A f`` with ``A[0] = 1``, ``A[1] = y_i``,
``A[2] = -x_i`` (arm of a thrust along body z at rotor position (x_i, y_i))
and ``A[3] = kappa_i`` (signed rotor drag: yaw torque per newton of thrust).
:func:`mix` inverts A and keeps every rotor inside [thrust_min, thrust_max]
with a fixed priority:

1. the collective thrust T is clipped to what the rotors can give with no
   torque at all;
2. the roll/pitch torque (tau_x, tau_y) is scaled down as a vector (its
   direction is kept, so the tilt correction points the right way) until it
   fits on top of T;
3. the yaw torque is scaled down to fit in the margin that is left.

So yaw is given up first, then roll/pitch magnitude; T is never changed by
the torques. The controller's tilt and thrust bounds keep T in the middle of
the range, so steps 2 and 3 rarely bite.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np

from sim.compiled import kernel


@dataclass(frozen=True)
class QuadrotorParams:
    """Physical parameters of one quadrotor model (every copy shares them).

    Extracted from a compiled MuJoCo model by ``controllers.lowlevel.model_params``.
    """

    mass: float  # kg, whole robot (subtree of the base body)
    inertia: np.ndarray  # (3, 3) kg m^2, about the centre of mass, body frame
    rotor_positions: np.ndarray  # (4, 3) m, rotor thrust points relative to the CoM, body frame
    rotor_drag: np.ndarray  # (4,) N m / N, signed yaw torque per newton of thrust
    thrust_min: np.ndarray  # (4,) N, lowest thrust of each rotor
    thrust_max: np.ndarray  # (4,) N, highest thrust of each rotor
    gravity: float = 9.81  # m/s^2, magnitude, acting along world -z

    def __post_init__(self) -> None:
        assert self.mass > 0.0, self.mass
        assert np.shape(self.inertia) == (3, 3), np.shape(self.inertia)
        assert np.shape(self.rotor_positions) == (4, 3), np.shape(self.rotor_positions)
        for name in ("rotor_drag", "thrust_min", "thrust_max"):
            assert np.shape(getattr(self, name)) == (4,), (name, np.shape(getattr(self, name)))
        assert np.all(np.asarray(self.thrust_max) > np.asarray(self.thrust_min))
        assert self.gravity > 0.0, self.gravity

    @property
    def allocation(self) -> np.ndarray:
        """A (4, 4): [T (N), tau_x, tau_y, tau_z (N m, body frame)] = A @ f (N)."""
        r = np.asarray(self.rotor_positions, dtype=float)
        return np.stack([np.ones(4), r[:, 1], -r[:, 0], np.asarray(self.rotor_drag, dtype=float)])

    @functools.cached_property
    def mixer_tables(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, float]:
        """Inverse allocation (4, 4), thrust_min (4,), thrust_max (4,), and the
        collective thrust range (N) the rotors give with no torque at all."""
        a_inv = np.linalg.inv(self.allocation)
        per_newton = a_inv[:, 0]  # rotor thrusts for 1 N of collective thrust
        assert np.all(per_newton > 0), "centre of mass outside the rotor polygon"
        lo = np.ascontiguousarray(self.thrust_min, dtype=float)
        hi = np.ascontiguousarray(self.thrust_max, dtype=float)
        return a_inv, lo, hi, float(np.max(lo / per_newton)), float(np.min(hi / per_newton))

    @functools.cached_property
    def controller_constants(self) -> tuple[float, float, np.ndarray]:
        """mass (kg), gravity (m/s^2), inertia (3, 3) as the compiled controller takes them."""
        return float(self.mass), float(self.gravity), np.ascontiguousarray(self.inertia, dtype=np.float64)

    @property
    def hover_thrust(self) -> float:
        """Collective thrust that balances gravity, N."""
        return self.mass * self.gravity


@dataclass(frozen=True)
class QuadrotorGains:
    """Gains of the geometric controller, normalised by mass / inertia.

    The defaults place the translational loop at a natural frequency of
    4 rad/s (damping 0.9) and roll/pitch at 25 rad/s (damping 0.8), well
    below the 100 Hz controller rate (the 10 ms zero-order hold costs about
    0.125 rad of phase at 25 rad/s); yaw is slower (8 rad/s) because rotor
    drag gives it little authority.
    """

    kx: float = 16.0  # 1/s^2, position gain (force = mass * kx * error)
    kv: float = 7.2  # 1/s, velocity gain
    kr: tuple[float, float, float] = (625.0, 625.0, 64.0)  # 1/s^2, attitude gain per body axis
    kw: tuple[float, float, float] = (40.0, 40.0, 12.8)  # 1/s, body-rate gain per body axis
    max_tilt: float = 0.6  # rad, largest angle between commanded thrust and world z
    min_thrust_ratio: float = 0.3  # upward command force >= this * m g
    max_thrust_ratio: float = 2.0  # commanded force magnitude <= this * m g
    max_yaw_error: float = 0.5  # rad, larger heading errors are approached this far ahead

    def __post_init__(self) -> None:
        assert self.kx > 0 and self.kv > 0
        assert len(self.kr) == 3 and len(self.kw) == 3
        assert 0.0 < self.max_tilt < np.pi / 2
        assert 0.0 < self.min_thrust_ratio < 1.0 < self.max_thrust_ratio
        assert 0.0 < self.max_yaw_error < np.pi / 2

    @functools.cached_property
    def controller_constants(self) -> tuple:
        """kx, kv, kr (3,), kw (3,), tan(max_tilt), min / max thrust ratio, max_yaw_error, as the
        compiled controller takes them (built once, not every tick)."""
        return (float(self.kx), float(self.kv), np.array(self.kr, dtype=np.float64),
                np.array(self.kw, dtype=np.float64), float(np.tan(self.max_tilt)), float(self.min_thrust_ratio),
                float(self.max_thrust_ratio), float(self.max_yaw_error))


@dataclass(frozen=True)
class QuadrotorState:
    """State of N quadrotors.

    position: (N, 3) m, body origin, world frame.
    velocity: (N, 3) m/s, world frame.
    quaternion: (N, 4) body-to-world, (w, x, y, z).
    angular_velocity: (N, 3) rad/s, body frame.
    """

    position: np.ndarray
    velocity: np.ndarray
    quaternion: np.ndarray
    angular_velocity: np.ndarray

    def __post_init__(self) -> None:
        n = len(self.position)
        assert np.shape(self.position) == (n, 3), np.shape(self.position)
        assert np.shape(self.velocity) == (n, 3), np.shape(self.velocity)
        assert np.shape(self.quaternion) == (n, 4), np.shape(self.quaternion)
        assert np.shape(self.angular_velocity) == (n, 3), np.shape(self.angular_velocity)


@dataclass(frozen=True)
class QuadrotorReference:
    """Reference for N quadrotors (a flat output and its derivatives).

    position: (N, 3) m, world frame.
    velocity: (N, 3) m/s, world frame.
    acceleration: (N, 3) m/s^2, world frame (without gravity).
    yaw: (N,) rad, heading of body x about world z.
    jerk: (N, 3) m/s^3, world frame, optional (zeros): feeds the desired body rates.
    yaw_rate: (N,) rad/s, optional (zeros).
    """

    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    yaw: np.ndarray
    jerk: np.ndarray | None = field(default=None)
    yaw_rate: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        n = len(self.position)
        assert np.shape(self.position) == (n, 3), np.shape(self.position)
        assert np.shape(self.velocity) == (n, 3), np.shape(self.velocity)
        assert np.shape(self.acceleration) == (n, 3), np.shape(self.acceleration)
        assert np.shape(self.yaw) == (n,), np.shape(self.yaw)
        if self.jerk is not None:
            assert np.shape(self.jerk) == (n, 3), np.shape(self.jerk)
        if self.yaw_rate is not None:
            assert np.shape(self.yaw_rate) == (n,), np.shape(self.yaw_rate)

    @staticmethod
    def hover(position: np.ndarray, yaw: np.ndarray | None = None) -> "QuadrotorReference":
        """Hold ``position`` (N, 3) m with heading ``yaw`` (N,) rad (default 0)."""
        position = np.atleast_2d(np.asarray(position, dtype=float))
        n = len(position)
        yaw = np.zeros(n) if yaw is None else np.asarray(yaw, dtype=float)
        zeros = np.zeros((n, 3))
        return QuadrotorReference(position, zeros, zeros.copy(), yaw)


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """(N, 4) unit quaternions (w, x, y, z) -> (N, 3, 3) rotation matrices."""
    q = np.asarray(q, dtype=float)
    assert q.ndim == 2 and q.shape[1] == 4, q.shape
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    w, x, y, z = q.T
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=1,
    )


@kernel
def _geometric_control_kernel(position, velocity, quaternion, omega, ref_position, ref_velocity,
                              ref_acceleration, ref_yaw, jerk, yaw_rate, use_jerk, use_yaw_rate,
                              mass, gravity, inertia, kx, kv, kr, kw, tan_tilt, min_thrust_ratio,
                              max_thrust_ratio, max_yaw_error, thrust_out, torque_out):
    """Per robot: Lee et al. (2010) eqs. 15-16 with the bounds of :func:`geometric_control`."""
    weight = mass * gravity
    rot = np.empty((3, 3))
    rot_d = np.empty((3, 3))
    rt_rd = np.empty((3, 3))
    force = np.empty(3)
    omega_d = np.empty(3)
    omega_ref = np.empty(3)
    ang = np.empty(3)
    for n in range(position.shape[0]):
        # Rotation matrix of the normalised quaternion (body -> world).
        w, x, y, z = quaternion[n, 0], quaternion[n, 1], quaternion[n, 2], quaternion[n, 3]
        norm = np.sqrt(w * w + x * x + y * y + z * z)
        w, x, y, z = w / norm, x / norm, y / norm, z / norm
        rot[0, 0] = 1 - 2 * (y * y + z * z)
        rot[0, 1] = 2 * (x * y - w * z)
        rot[0, 2] = 2 * (x * z + w * y)
        rot[1, 0] = 2 * (x * y + w * z)
        rot[1, 1] = 1 - 2 * (x * x + z * z)
        rot[1, 2] = 2 * (y * z - w * x)
        rot[2, 0] = 2 * (x * z - w * y)
        rot[2, 1] = 2 * (y * z + w * x)
        rot[2, 2] = 1 - 2 * (x * x + y * y)
        # Commanded heading: toward the reference yaw, at most max_yaw_error ahead of the current one
        # (the error wrapped to (-pi, pi] as the angle of exp(i error)).
        heading = math.atan2(rot[1, 0], rot[0, 0])
        yaw_error = ref_yaw[n] - heading
        yaw_error = math.atan2(math.sin(yaw_error), math.cos(yaw_error))
        yaw_cmd = heading + min(max(yaw_error, -max_yaw_error), max_yaw_error)
        # Desired force, then the tilt / thrust envelope.
        for i in range(3):
            e_x = position[n, i] - ref_position[n, i]
            e_v = velocity[n, i] - ref_velocity[n, i]
            force[i] = mass * (-kx * e_x - kv * e_v + ref_acceleration[n, i] + (gravity if i == 2 else 0.0))
        fz = min(max(force[2], min_thrust_ratio * weight), max_thrust_ratio * weight)
        h_norm = np.sqrt(force[0] * force[0] + force[1] * force[1])
        h_max = fz * tan_tilt
        scale = h_max / max(h_norm, 1e-12) if h_norm > h_max else 1.0
        force[0] *= scale
        force[1] *= scale
        force[2] = fz
        f_norm = np.sqrt(force[0] * force[0] + force[1] * force[1] + force[2] * force[2])
        shrink = min(1.0, max_thrust_ratio * weight / f_norm)
        for i in range(3):
            force[i] *= shrink
        f_norm = np.sqrt(force[0] * force[0] + force[1] * force[1] + force[2] * force[2])
        b3x, b3y, b3z = force[0] / f_norm, force[1] / f_norm, force[2] / f_norm
        c1x, c1y = math.cos(yaw_cmd), math.sin(yaw_cmd)
        # b2_d = unit(b3_d x b1_c) with b1_c = (c1x, c1y, 0); b1_d = b2_d x b3_d.
        b2x, b2y, b2z = b3y * 0.0 - b3z * c1y, b3z * c1x - b3x * 0.0, b3x * c1y - b3y * c1x
        b2_norm = np.sqrt(b2x * b2x + b2y * b2y + b2z * b2z)
        b2x, b2y, b2z = b2x / b2_norm, b2y / b2_norm, b2z / b2_norm
        b1x, b1y, b1z = b2y * b3z - b2z * b3y, b2z * b3x - b2x * b3z, b2x * b3y - b2y * b3x
        rot_d[0, 0], rot_d[1, 0], rot_d[2, 0] = b1x, b1y, b1z
        rot_d[0, 1], rot_d[1, 1], rot_d[2, 1] = b2x, b2y, b2z
        rot_d[0, 2], rot_d[1, 2], rot_d[2, 2] = b3x, b3y, b3z
        thrust_out[n] = force[0] * rot[0, 2] + force[1] * rot[1, 2] + force[2] * rot[2, 2]
        # Desired body rates from differential flatness (zero without jerk / yaw rate).
        omega_d[0] = omega_d[1] = omega_d[2] = 0.0
        if use_jerk:
            jx, jy, jz = jerk[n, 0], jerk[n, 1], jerk[n, 2]
            # Dot products summed as numpy's einsum does, (x + z) + y.
            along = (b3x * jx + b3z * jz) + b3y * jy
            gain = mass / f_norm
            hx, hy, hz = gain * (jx - along * b3x), gain * (jy - along * b3y), gain * (jz - along * b3z)
            omega_d[0] = -((hx * b2x + hz * b2z) + hy * b2y)
            omega_d[1] = (hx * b1x + hz * b1z) + hy * b1y
        if use_yaw_rate:
            omega_d[2] = yaw_rate[n] * b3z
        for i in range(3):
            for k in range(3):
                rt_rd[i, k] = rot[0, i] * rot_d[0, k] + rot[1, i] * rot_d[1, k] + rot[2, i] * rot_d[2, k]
        for i in range(3):  # summed (0 + 2) + 1, numpy einsum's order: equal to the numpy law's round-off
            omega_ref[i] = (rt_rd[i, 0] * omega_d[0] + rt_rd[i, 2] * omega_d[2]) + rt_rd[i, 1] * omega_d[1]
        # e_R = 0.5 vee(R_d^T R - R^T R_d), e_W = Omega - R^T R_d Omega_d.
        e_r0 = 0.5 * (rt_rd[1, 2] - rt_rd[2, 1])
        e_r1 = 0.5 * (rt_rd[2, 0] - rt_rd[0, 2])
        e_r2 = 0.5 * (rt_rd[0, 1] - rt_rd[1, 0])
        w0, w1, w2 = omega[n, 0], omega[n, 1], omega[n, 2]
        ang[0] = -kr[0] * e_r0 - kw[0] * (w0 - omega_ref[0])
        ang[1] = -kr[1] * e_r1 - kw[1] * (w1 - omega_ref[1])
        ang[2] = -kr[2] * e_r2 - kw[2] * (w2 - omega_ref[2])
        # Feedforward: Omega x J Omega - J (Omega^ R^T R_d Omega_d); Omega_d_dot taken as 0.
        ang[0] -= w1 * omega_ref[2] - w2 * omega_ref[1]
        ang[1] -= w2 * omega_ref[0] - w0 * omega_ref[2]
        ang[2] -= w0 * omega_ref[1] - w1 * omega_ref[0]
        jw0 = inertia[0, 0] * w0 + inertia[0, 1] * w1 + inertia[0, 2] * w2
        jw1 = inertia[1, 0] * w0 + inertia[1, 1] * w1 + inertia[1, 2] * w2
        jw2 = inertia[2, 0] * w0 + inertia[2, 1] * w1 + inertia[2, 2] * w2
        for i in range(3):
            torque_out[n, i] = inertia[i, 0] * ang[0] + inertia[i, 1] * ang[1] + inertia[i, 2] * ang[2]
        torque_out[n, 0] += w1 * jw2 - w2 * jw1
        torque_out[n, 1] += w2 * jw0 - w0 * jw2
        torque_out[n, 2] += w0 * jw1 - w1 * jw0


_NO_JERK = np.zeros((0, 3))  # stands in for an absent reference jerk (never read)
_NO_YAW_RATE = np.zeros(0)


def _controller_inputs(params: QuadrotorParams, gains: QuadrotorGains, position, velocity, quaternion,
                       angular_velocity, ref_position, ref_velocity, ref_acceleration, ref_yaw, ref_jerk,
                       ref_yaw_rate) -> tuple:
    """The controller kernel's arguments before its outputs: float64 C arrays, the constants built once."""
    f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
    return (f64(position), f64(velocity), f64(quaternion), f64(angular_velocity), f64(ref_position),
            f64(ref_velocity), f64(ref_acceleration), f64(ref_yaw), _NO_JERK if ref_jerk is None else f64(ref_jerk),
            _NO_YAW_RATE if ref_yaw_rate is None else f64(ref_yaw_rate), ref_jerk is not None,
            ref_yaw_rate is not None, *params.controller_constants, *gains.controller_constants)


def _state_and_reference(state: QuadrotorState, reference: QuadrotorReference) -> tuple:
    return (state.position, state.velocity, state.quaternion, state.angular_velocity, reference.position,
            reference.velocity, reference.acceleration, reference.yaw, reference.jerk, reference.yaw_rate)


def geometric_control(
    params: QuadrotorParams,
    gains: QuadrotorGains,
    state: QuadrotorState,
    reference: QuadrotorReference,
) -> tuple[np.ndarray, np.ndarray]:
    """Collective thrust (N,), N, and body torque (N, 3), N m, body frame.

    Geometric tracking on SE(3) (Lee et al. 2010, eqs. 15-16), gains normalised
    by mass and inertia. The thrust is the desired force projected on the
    current body z axis, so a tilted robot does not climb while it turns.

    The desired force is clamped to the envelope: upward component within
    [min_thrust_ratio, max_thrust_ratio] m g, tilt <= max_tilt (horizontal
    part scaled down), magnitude <= max_thrust_ratio m g. The heading turns
    toward the reference yaw at most max_yaw_error ahead of the current
    heading, so the attitude error stays where e_R is near-linear (near a
    half-turn it vanishes and would couple yaw into roll/pitch).
    """
    n = len(state.position)
    assert len(reference.position) == n, (len(reference.position), n)
    thrust = np.empty(n)
    torque = np.empty((n, 3))
    _geometric_control_kernel(*_controller_inputs(params, gains, *_state_and_reference(state, reference)),
                              thrust, torque)
    return thrust, torque


@kernel
def _max_scale(base, step, lo, hi):
    """Largest s in [0, 1] with lo <= base + s step <= hi for the 4 rotors (base inside)."""
    scale = np.inf
    for r in range(4):
        if step[r] > 1e-12:
            scale = min(scale, (hi[r] - base[r]) / step[r])
        elif step[r] < -1e-12:
            scale = min(scale, (lo[r] - base[r]) / step[r])
    return min(max(scale, 0.0), 1.0)


@kernel
def _mix_kernel(thrust, torque, a_inv, lo, hi, t_lo, t_hi, rotor):
    base = np.empty(4)
    step = np.empty(4)
    for n in range(thrust.shape[0]):
        collective = min(max(thrust[n], t_lo), t_hi)
        for r in range(4):
            base[r] = collective * a_inv[r, 0]
            step[r] = torque[n, 0] * a_inv[r, 1] + torque[n, 1] * a_inv[r, 2]
        scale = _max_scale(base, step, lo, hi)
        for r in range(4):
            base[r] = base[r] + scale * step[r]
            step[r] = torque[n, 2] * a_inv[r, 3]
        scale = _max_scale(base, step, lo, hi)
        for r in range(4):
            rotor[n, r] = min(max(base[r] + scale * step[r], lo[r]), hi[r])  # clip: round-off only


def mix(params: QuadrotorParams, thrust: np.ndarray, torque: np.ndarray) -> np.ndarray:
    """Rotor thrusts (N, 4), N, in actuator order, inside the thrust limits.

    thrust: (N,) collective thrust, N; torque: (N, 3) body torque, N m.
    Priority when saturated: collective thrust, then roll/pitch (scaled as a
    vector), then yaw (see the module docstring).
    """
    thrust = np.ascontiguousarray(thrust, dtype=float)
    torque = np.ascontiguousarray(torque, dtype=float)
    n = len(thrust)
    assert thrust.shape == (n,), thrust.shape
    assert torque.shape == (n, 3), torque.shape
    a_inv, lo, hi, t_lo, t_hi = params.mixer_tables
    rotor = np.empty((n, 4))
    _mix_kernel(thrust, torque, a_inv, lo, hi, t_lo, t_hi, rotor)
    return rotor


def rotor_thrusts(
    params: QuadrotorParams,
    gains: QuadrotorGains,
    state: QuadrotorState,
    reference: QuadrotorReference,
) -> np.ndarray:
    """Controller plus mixer: rotor thrusts (N, 4), N, actuator order thrust1..4."""
    assert len(reference.position) == len(state.position), (len(reference.position), len(state.position))
    return track_reference(params, gains, *_state_and_reference(state, reference))


def track_reference(params: QuadrotorParams, gains: QuadrotorGains, position: np.ndarray, velocity: np.ndarray,
                    quaternion: np.ndarray, angular_velocity: np.ndarray, ref_position: np.ndarray,
                    ref_velocity: np.ndarray, ref_acceleration: np.ndarray, ref_yaw: np.ndarray,
                    ref_jerk: np.ndarray | None = None, ref_yaw_rate: np.ndarray | None = None) -> np.ndarray:
    """:func:`rotor_thrusts` on the plain arrays of :class:`QuadrotorState` and
    :class:`QuadrotorReference` (same shapes and units), without building them:
    the simulation's per-tick path. Rotor thrusts (N, 4), N."""
    inputs = _controller_inputs(params, gains, position, velocity, quaternion, angular_velocity, ref_position,
                                ref_velocity, ref_acceleration, ref_yaw, ref_jerk, ref_yaw_rate)
    n = len(inputs[0])
    for array, columns in zip(inputs[:8], (3, 3, 4, 3, 3, 3, 3, 0)):
        assert array.shape == ((n, columns) if columns else (n,)), (array.shape, n)
    assert ref_jerk is None or inputs[8].shape == (n, 3), inputs[8].shape
    assert ref_yaw_rate is None or inputs[9].shape == (n,), inputs[9].shape
    thrust, torque, rotor = np.empty(n), np.empty((n, 3)), np.empty((n, 4))
    _rotor_thrusts_kernel(*inputs, thrust, torque, *params.mixer_tables, rotor)
    return rotor


@kernel
def _rotor_thrusts_kernel(position, velocity, quaternion, omega, ref_position, ref_velocity, ref_acceleration,
                          ref_yaw, jerk, yaw_rate, use_jerk, use_yaw_rate, mass, gravity, inertia, kx, kv, kr, kw,
                          tan_tilt, min_thrust_ratio, max_thrust_ratio, max_yaw_error, thrust, torque,
                          a_inv, lo, hi, t_lo, t_hi, rotor):
    """Controller and mixer in one compiled call (one call's argument handling instead of two)."""
    _geometric_control_kernel(position, velocity, quaternion, omega, ref_position, ref_velocity,
                              ref_acceleration, ref_yaw, jerk, yaw_rate, use_jerk, use_yaw_rate, mass, gravity,
                              inertia, kx, kv, kr, kw, tan_tilt, min_thrust_ratio, max_thrust_ratio, max_yaw_error,
                              thrust, torque)
    _mix_kernel(thrust, torque, a_inv, lo, hi, t_lo, t_hi, rotor)
