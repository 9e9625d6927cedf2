"""Quadrotor low-level control: geometric SE(3) tracking and motor mixing.

Pure numpy, never imports MuJoCo; batched over all N quadrotors of a team (all
share one :class:`QuadrotorParams`, since they come from one robot file).

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

from dataclasses import dataclass, field

import numpy as np

_E3 = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class QuadrotorParams:
    """Physical parameters of one quadrotor model (every copy shares them).

    Extracted from a compiled MuJoCo model by ``sim.robot_params``.
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


def _vee(m: np.ndarray) -> np.ndarray:
    """(N, 3, 3) skew-symmetric -> (N, 3)."""
    return np.stack([m[:, 2, 1], m[:, 0, 2], m[:, 1, 0]], axis=-1)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _bounded_force(force: np.ndarray, params: QuadrotorParams, gains: QuadrotorGains) -> np.ndarray:
    """Clamp the desired force (N, 3), N, world frame, to the tilt / thrust envelope."""
    weight = params.mass * params.gravity
    fz = np.clip(force[:, 2], gains.min_thrust_ratio * weight, gains.max_thrust_ratio * weight)
    horizontal = force[:, :2]
    h_norm = np.linalg.norm(horizontal, axis=1)
    h_max = fz * np.tan(gains.max_tilt)
    scale = np.where(h_norm > h_max, h_max / np.maximum(h_norm, 1e-12), 1.0)
    bounded = np.column_stack([horizontal * scale[:, None], fz])
    norm = np.linalg.norm(bounded, axis=1)
    limit = gains.max_thrust_ratio * weight
    return bounded * np.minimum(1.0, limit / norm)[:, None]


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
    """
    n = len(state.position)
    assert len(reference.position) == n, (len(reference.position), n)
    m, g = params.mass, params.gravity
    inertia = np.asarray(params.inertia, dtype=float)
    rot = quaternion_to_matrix(state.quaternion)  # body -> world

    e_x = state.position - reference.position
    e_v = state.velocity - reference.velocity
    force = m * (-gains.kx * e_x - gains.kv * e_v + reference.acceleration + g * _E3)
    force = _bounded_force(force, params, gains)

    b3_d = _unit(force)
    # Heading: turn toward the reference yaw at most max_yaw_error ahead of the
    # current heading, so the attitude error stays where e_R is near-linear
    # (near a half-turn it vanishes and would couple yaw into roll/pitch).
    heading = np.arctan2(rot[:, 1, 0], rot[:, 0, 0])
    yaw_error = np.angle(np.exp(1j * (reference.yaw - heading)))
    yaw_cmd = heading + np.clip(yaw_error, -gains.max_yaw_error, gains.max_yaw_error)
    b1_c = np.column_stack([np.cos(yaw_cmd), np.sin(yaw_cmd), np.zeros(n)])
    b2_d = _unit(np.cross(b3_d, b1_c))
    b1_d = np.cross(b2_d, b3_d)
    rot_d = np.stack([b1_d, b2_d, b3_d], axis=-1)  # columns are desired body axes

    thrust = np.einsum("ni,ni->n", force, rot[:, :, 2])

    # Desired body rates from differential flatness (zero without jerk / yaw rate).
    omega_d = np.zeros((n, 3))
    if reference.jerk is not None:
        f_norm = np.linalg.norm(force, axis=1)
        jerk = reference.jerk
        h = (m / f_norm)[:, None] * (jerk - np.einsum("ni,ni->n", b3_d, jerk)[:, None] * b3_d)
        omega_d[:, 0] = -np.einsum("ni,ni->n", h, b2_d)
        omega_d[:, 1] = np.einsum("ni,ni->n", h, b1_d)
    if reference.yaw_rate is not None:
        omega_d[:, 2] = reference.yaw_rate * b3_d[:, 2]

    rt_rd = np.einsum("nji,njk->nik", rot, rot_d)  # R^T R_d
    e_r = 0.5 * _vee(np.swapaxes(rt_rd, 1, 2) - rt_rd)  # 0.5 vee(R_d^T R - R^T R_d)
    omega_ref = np.einsum("nij,nj->ni", rt_rd, omega_d)  # R^T R_d Omega_d
    omega = state.angular_velocity
    e_w = omega - omega_ref

    ang_acc = -np.asarray(gains.kr) * e_r - np.asarray(gains.kw) * e_w
    # Feedforward: Omega x J Omega - J (Omega^ R^T R_d Omega_d); Omega_d_dot taken as 0.
    j_omega = omega @ inertia.T
    torque = (
        (ang_acc - np.cross(omega, omega_ref)) @ inertia.T
        + np.cross(omega, j_omega)
    )
    assert thrust.shape == (n,) and torque.shape == (n, 3)
    return thrust, torque


def _max_scale(base: np.ndarray, step: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Largest s in [0, 1] per row with lo <= base + s step <= hi (base inside).

    base, step: (N, 4); lo, hi: (4,). Returns (N,).
    """
    up = np.divide(hi - base, step, out=np.full_like(step, np.inf), where=step > 1e-12)
    down = np.divide(lo - base, step, out=np.full_like(step, np.inf), where=step < -1e-12)
    return np.clip(np.minimum(up, down).min(axis=1), 0.0, 1.0)


def mix(params: QuadrotorParams, thrust: np.ndarray, torque: np.ndarray) -> np.ndarray:
    """Rotor thrusts (N, 4), N, in actuator order, inside the thrust limits.

    thrust: (N,) collective thrust, N; torque: (N, 3) body torque, N m.
    Priority when saturated: collective thrust, then roll/pitch (scaled as a
    vector), then yaw (see the module docstring).
    """
    thrust = np.asarray(thrust, dtype=float)
    torque = np.asarray(torque, dtype=float)
    n = len(thrust)
    assert thrust.shape == (n,), thrust.shape
    assert torque.shape == (n, 3), torque.shape
    lo = np.asarray(params.thrust_min, dtype=float)
    hi = np.asarray(params.thrust_max, dtype=float)
    a_inv = np.linalg.inv(params.allocation)  # (4, 4)

    per_newton = a_inv[:, 0]  # rotor thrusts for 1 N of collective thrust
    assert np.all(per_newton > 0), "centre of mass outside the rotor polygon"
    t_lo = np.max(lo / per_newton)
    t_hi = np.min(hi / per_newton)
    base = np.clip(thrust, t_lo, t_hi)[:, None] * per_newton

    roll_pitch = torque[:, :2] @ a_inv[:, 1:3].T
    base = base + _max_scale(base, roll_pitch, lo, hi)[:, None] * roll_pitch

    yaw = torque[:, 2:3] * a_inv[:, 3]
    rotor = base + _max_scale(base, yaw, lo, hi)[:, None] * yaw
    rotor = np.clip(rotor, lo, hi)  # round-off only
    assert rotor.shape == (n, 4)
    return rotor


def rotor_thrusts(
    params: QuadrotorParams,
    gains: QuadrotorGains,
    state: QuadrotorState,
    reference: QuadrotorReference,
) -> np.ndarray:
    """Controller plus mixer: rotor thrusts (N, 4), N, actuator order thrust1..4."""
    thrust, torque = geometric_control(params, gains, state, reference)
    return mix(params, thrust, torque)
