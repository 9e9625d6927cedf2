"""Quadrotor low-level control in real MuJoCo simulation of models/robots/quadrotor.xml.

The test world is built with MjSpec: a floor plus N attached copies of the
robot file (prefixes quad0/, quad1/, ...), 2 ms physics with the scenes'
implicitfast integrator, the controller evaluated every 10 ms and its rotor
thrusts held for 5 physics steps.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.lowlevel.quadrotor import (
    QuadrotorGains,
    QuadrotorParams,
    QuadrotorReference,
    QuadrotorState,
    geometric_control,
    mix,
    quaternion_to_matrix,
    rotor_thrusts,
    track_reference,
)
from controllers.lowlevel.model_params import quadrotor_params

ROBOT_FILE = Path(__file__).resolve().parents[1] / "models" / "robots" / "quadrotor.xml"
TIMESTEP = 0.002  # s, physics step (as in the scenes)
CONTROL_PERIOD = 0.01  # s
STEPS_PER_CONTROL = round(CONTROL_PERIOD / TIMESTEP)
GAINS = QuadrotorGains()


def build_world(count: int) -> mujoco.MjModel:
    spec = mujoco.MjSpec()
    spec.option.timestep = TIMESTEP
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[20, 20, 0.1])
    for i in range(count):
        frame = spec.worldbody.add_frame(pos=[2.0 * i, 0.0, 0.0])
        spec.attach(mujoco.MjSpec.from_file(str(ROBOT_FILE)), prefix=f"quad{i}/", frame=frame)
    return spec.compile()


@dataclass
class Team:
    """Name-resolved addresses of N quadrotors in a model (looked up once)."""

    model: mujoco.MjModel
    data: mujoco.MjData
    qpos: np.ndarray  # (N,) free-joint qpos addresses
    dof: np.ndarray  # (N,) free-joint dof addresses
    actuators: np.ndarray  # (N, 4) actuator ids thrust1..4
    params: QuadrotorParams

    @staticmethod
    def make(count: int) -> "Team":
        model = build_world(count)
        joints = [model.joint(f"quad{i}/root") for i in range(count)]
        return Team(
            model,
            mujoco.MjData(model),
            np.array([j.qposadr[0] for j in joints]),
            np.array([j.dofadr[0] for j in joints]),
            np.array([[model.actuator(f"quad{i}/thrust{k}").id for k in range(1, 5)] for i in range(count)]),
            quadrotor_params(model, "quad0/"),
        )

    def set_state(self, position, quaternion, velocity=None, angular_velocity=None) -> None:
        n = len(self.qpos)
        velocity = np.zeros((n, 3)) if velocity is None else velocity
        angular_velocity = np.zeros((n, 3)) if angular_velocity is None else angular_velocity
        for i in range(n):
            self.data.qpos[self.qpos[i] : self.qpos[i] + 7] = np.r_[position[i], quaternion[i]]
            self.data.qvel[self.dof[i] : self.dof[i] + 6] = np.r_[velocity[i], angular_velocity[i]]
        mujoco.mj_forward(self.model, self.data)

    def state(self) -> QuadrotorState:
        q, v = self.data.qpos, self.data.qvel
        return QuadrotorState(
            position=np.array([q[a : a + 3] for a in self.qpos]),
            velocity=np.array([v[a : a + 3] for a in self.dof]),
            quaternion=np.array([q[a + 3 : a + 7] for a in self.qpos]),
            angular_velocity=np.array([v[a + 3 : a + 6] for a in self.dof]),
        )

    def apply(self, thrusts: np.ndarray) -> None:
        self.data.ctrl[self.actuators.ravel()] = thrusts.ravel()
        mujoco.mj_step(self.model, self.data, nstep=STEPS_PER_CONTROL)

    def warnings(self) -> int:
        return int(sum(w.number for w in self.data.warning))


def circle_reference(t: float, centers: np.ndarray, radius=1.0, speed=0.5, height=1.0) -> QuadrotorReference:
    """Horizontal circle at ``speed`` m/s, consistent position..jerk, yaw 0."""
    n = len(centers)
    w = speed / radius
    c, s = np.cos(w * t), np.sin(w * t)
    one = np.ones((n, 1))
    pos = centers + np.array([radius * c, radius * s, height]) * one
    vel = np.array([-radius * w * s, radius * w * c, 0.0]) * one
    acc = np.array([-radius * w**2 * c, -radius * w**2 * s, 0.0]) * one
    jerk = np.array([radius * w**3 * s, -radius * w**3 * c, 0.0]) * one
    return QuadrotorReference(pos, vel, acc, np.zeros(n), jerk=jerk)


def lemniscate_reference(t: float, center: np.ndarray, a=1.5, period=20.0, height=1.2) -> QuadrotorReference:
    """Gerono lemniscate x = a sin(wt), y = a sin(wt) cos(wt), z wobbling; yaw
    turning slowly. Peak speed a w ~ 0.47 m/s."""
    w = 2 * np.pi / period
    th = w * t
    s, c = np.sin(th), np.cos(th)
    s2, c2 = np.sin(2 * th), np.cos(2 * th)
    h = 0.2
    pos = np.array([a * s, 0.5 * a * s2, height + h * s])
    vel = np.array([a * w * c, a * w * c2, h * w * c])
    acc = np.array([-a * w**2 * s, -2 * a * w**2 * s2, -h * w**2 * s])
    jerk = np.array([-a * w**3 * c, -4 * a * w**3 * c2, -h * w**3 * c])
    yaw_rate = 0.1
    return QuadrotorReference(
        (center + pos)[None], vel[None], acc[None], np.array([yaw_rate * t]), jerk=jerk[None], yaw_rate=np.array([yaw_rate])
    )


def quat_about(axis, angle) -> np.ndarray:
    q = np.zeros(4)
    mujoco.mju_axisAngle2Quat(q, np.asarray(axis, dtype=float), angle)
    return q


def yaw_of(quaternion: np.ndarray) -> np.ndarray:
    rot = quaternion_to_matrix(quaternion)
    return np.arctan2(rot[:, 1, 0], rot[:, 0, 0])


# ----------------------------------------------------------------- pure math


def test_params_from_bare_file_and_prefixed_copy():
    bare = quadrotor_params(mujoco.MjModel.from_xml_path(str(ROBOT_FILE)))
    team = Team.make(2)
    for prefix in ("quad0/", "quad1/"):
        p = quadrotor_params(team.model, prefix)
        assert p.mass == pytest.approx(bare.mass)
        np.testing.assert_allclose(p.rotor_positions, bare.rotor_positions)
    assert bare.mass == pytest.approx(1.0)
    np.testing.assert_allclose(np.diag(bare.inertia), [0.0082, 0.0082, 0.0149])
    np.testing.assert_allclose(bare.rotor_drag, [-0.016, 0.016, -0.016, 0.016])
    np.testing.assert_allclose(bare.thrust_max, 6.0)
    np.testing.assert_allclose(bare.thrust_min, 0.0)
    with pytest.raises(KeyError):
        quadrotor_params(team.model, "quad7/")


def test_allocation_matches_mujoco_wrench():
    """A f reproduces the body-frame wrench MuJoCo applies for rotor thrusts f."""
    model = mujoco.MjModel.from_xml_path(str(ROBOT_FILE))
    data = mujoco.MjData(model)
    params = quadrotor_params(model)
    f = np.array([1.0, 2.5, 0.5, 3.0])
    data.qpos[:] = model.key("hover").qpos
    data.ctrl[:] = f
    mujoco.mj_forward(model, data)
    # Free-joint generalised force: world-frame force, body-frame torque (about the CoM here).
    gen = data.qfrc_actuator[:6]
    wrench = params.allocation @ f
    assert gen[2] == pytest.approx(wrench[0])
    np.testing.assert_allclose(gen[3:], wrench[1:], atol=1e-12)


@settings(max_examples=200, deadline=None)
@given(
    thrust=st.floats(-5.0, 40.0),
    torque=st.tuples(st.floats(-3, 3), st.floats(-3, 3), st.floats(-0.5, 0.5)),
)
def test_mixer_limits_and_priority(thrust, torque):
    params = quadrotor_params(mujoco.MjModel.from_xml_path(str(ROBOT_FILE)))
    torque = np.array([torque])
    f = mix(params, np.array([thrust]), torque)
    assert f.shape == (1, 4)
    assert np.all(f >= params.thrust_min - 1e-12) and np.all(f <= params.thrust_max + 1e-12)
    wrench = params.allocation @ f[0]
    # Collective thrust is exact once clipped to the achievable range.
    assert wrench[0] == pytest.approx(np.clip(thrust, 0.0, 24.0), abs=1e-9)
    # Roll/pitch keeps its direction and never grows; yaw never grows or flips.
    rp, rp_cmd = wrench[1:3], torque[0, :2]
    assert np.linalg.norm(rp) <= np.linalg.norm(rp_cmd) + 1e-9
    assert abs(rp[0] * rp_cmd[1] - rp[1] * rp_cmd[0]) <= 1e-9
    assert rp @ rp_cmd >= -1e-12
    assert 0.0 <= wrench[3] * torque[0, 2] + 1e-12 and abs(wrench[3]) <= abs(torque[0, 2]) + 1e-9


def test_mixer_exact_inside_limits():
    params = quadrotor_params(mujoco.MjModel.from_xml_path(str(ROBOT_FILE)))
    thrust = np.array([9.81, 12.0])
    torque = np.array([[0.05, -0.03, 0.01], [-0.1, 0.02, -0.02]])
    f = mix(params, thrust, torque)
    np.testing.assert_allclose(f @ params.allocation.T, np.column_stack([thrust, torque]), atol=1e-12)


def test_mixer_gives_up_yaw_before_roll_pitch():
    params = quadrotor_params(mujoco.MjModel.from_xml_path(str(ROBOT_FILE)))
    f = mix(params, np.array([12.0]), np.array([[0.3, 0.0, 0.5]]))
    wrench = params.allocation @ f[0]
    assert wrench[0] == pytest.approx(12.0)
    assert wrench[1] == pytest.approx(0.3)  # fits: kept in full
    assert 0.0 <= wrench[3] < 0.5  # yaw cut back to what is left


def test_hover_equilibrium_needs_no_torque():
    params = quadrotor_params(mujoco.MjModel.from_xml_path(str(ROBOT_FILE)))
    state = QuadrotorState(np.array([[0.0, 0, 1]]), np.zeros((1, 3)), np.array([[1.0, 0, 0, 0]]), np.zeros((1, 3)))
    thrust, torque = geometric_control(params, GAINS, state, QuadrotorReference.hover([[0.0, 0, 1]]))
    assert thrust[0] == pytest.approx(params.mass * params.gravity)
    np.testing.assert_allclose(torque, 0.0, atol=1e-12)
    np.testing.assert_allclose(mix(params, thrust, torque), params.mass * params.gravity / 4)


def test_shape_asserts():
    with pytest.raises(AssertionError):
        QuadrotorState(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((3, 4)), np.zeros((2, 3)))
    with pytest.raises(AssertionError):
        QuadrotorReference(np.zeros((2, 3)), np.zeros((2, 3)), np.zeros((2, 3)), np.zeros(3))


# ------------------------------------------------------------ in simulation


def test_hover_holds_within_2cm():
    """Start 5 cm off, tilted 0.15 rad, yaw 0.4 rad off and spinning; after a 1 s
    settle the position stays within 2 cm of the set point for 5 s."""
    team = Team.make(1)
    target = np.array([[0.0, 0.0, 1.0]])
    tilt = quat_about([1, 1, 0], 0.15)
    yaw = quat_about([0, 0, 1], 0.4)
    q0 = np.zeros(4)
    mujoco.mju_mulQuat(q0, yaw, tilt)
    team.set_state(target + [0.05, -0.03, -0.04], q0[None], angular_velocity=np.array([[0.3, -0.2, 0.5]]))
    reference = QuadrotorReference.hover(target)
    errors, times = [], []
    for _ in range(int(6.0 / CONTROL_PERIOD)):
        state = team.state()
        errors.append(np.linalg.norm(state.position[0] - target[0]))
        times.append(team.data.time)
        f = rotor_thrusts(team.params, GAINS, state, reference)
        assert np.all(f >= 0.0) and np.all(f <= 6.0)
        team.apply(f)
    errors, times = np.array(errors), np.array(times)
    settled = errors[times >= 1.0]
    print(f"hover: max error after 1 s {settled.max() * 100:.3f} cm, final {errors[-1] * 1000:.4f} mm")
    assert settled.max() <= 0.02
    assert errors[-1] <= 1e-3
    assert abs(yaw_of(team.state().quaternion)[0]) < 1e-3
    assert team.warnings() == 0


def run_circle(team: Team, duration: float, centers: np.ndarray, batched: bool = True, jerk: bool = True):
    """Fly the circle reference; start on it at its initial velocity.
    ``jerk``: pass the jerk feedforward (else position, velocity, acceleration, yaw only)."""
    n = len(centers)
    ref0 = circle_reference(0.0, centers)
    team.set_state(ref0.position, np.tile([1.0, 0, 0, 0], (n, 1)), velocity=ref0.velocity)
    errors, times, thrusts = [], [], []
    for _ in range(int(duration / CONTROL_PERIOD)):
        state = team.state()
        reference = circle_reference(team.data.time, centers)
        if not jerk:
            reference = QuadrotorReference(reference.position, reference.velocity, reference.acceleration, reference.yaw)
        if batched:
            f = rotor_thrusts(team.params, GAINS, state, reference)
        else:
            f = np.vstack([rotor_thrusts(team.params, GAINS, _row(state, i), _row(reference, i)) for i in range(n)])
        errors.append(np.linalg.norm(state.position - reference.position, axis=1))
        times.append(team.data.time)
        thrusts.append(f)
        team.apply(f)
    return np.array(errors), np.array(times), np.array(thrusts)


def _row(obj, i):
    """Robot i of a batched state / reference, as a batch of one."""
    fields = {k: (None if v is None else np.asarray(v)[i : i + 1]) for k, v in vars(obj).items()}
    return type(obj)(**fields)


@pytest.mark.parametrize("jerk", [True, False], ids=["jerk_ff", "no_jerk_ff"])
def test_tracks_circle_at_half_metre_per_second(jerk):
    """One lap (12.6 s) of a 1 m radius circle at 0.5 m/s, errors after 2 s."""
    team = Team.make(1)
    errors, times, thrusts = run_circle(team, 14.0, np.zeros((1, 3)), jerk=jerk)
    after = errors[times >= 2.0, 0]
    print(f"circle r=1 m, 0.5 m/s, jerk feedforward {jerk}: mean error {after.mean() * 1000:.3f} mm, max {after.max() * 1000:.3f} mm")
    assert after.mean() <= 0.02
    assert after.max() <= 0.02
    assert thrusts.min() >= 0.0 and thrusts.max() <= 6.0
    assert team.warnings() == 0


def test_tracks_lemniscate_with_yaw():
    team = Team.make(1)
    center = np.array([0.0, 0.0, 0.0])
    ref0 = lemniscate_reference(0.0, center)
    team.set_state(ref0.position, np.array([[1.0, 0, 0, 0]]))  # at rest, so a transient first
    errors, times, yaw_errors = [], [], []
    for _ in range(int(20.0 / CONTROL_PERIOD)):
        state = team.state()
        reference = lemniscate_reference(team.data.time, center)
        errors.append(np.linalg.norm(state.position[0] - reference.position[0]))
        yaw_errors.append(np.angle(np.exp(1j * (yaw_of(state.quaternion)[0] - reference.yaw[0]))))
        times.append(team.data.time)
        f = rotor_thrusts(team.params, GAINS, state, reference)
        assert np.all(f >= 0.0) and np.all(f <= 6.0)
        team.apply(f)
    errors, times, yaw_errors = map(np.array, (errors, times, yaw_errors))
    after = times >= 3.0
    print(
        f"lemniscate: mean error {errors[after].mean() * 1000:.3f} mm, max {errors[after].max() * 1000:.3f} mm, "
        f"max yaw error {np.abs(yaw_errors[after]).max():.2e} rad"
    )
    assert errors[after].mean() <= 0.02
    assert np.abs(yaw_errors[after]).max() <= 0.01
    assert team.warnings() == 0


def test_batch_of_four_equals_each_alone():
    """One call for 4 robots gives the same thrusts as 4 calls of one robot,
    and each robot's trajectory equals that of the same robot flown alone."""
    centers = np.array([[2.0 * i, 0.0, 0.0] for i in range(4)])
    team = Team.make(4)
    batched = run_circle(team, 4.0, centers, batched=True)
    team_single = Team.make(4)
    single = run_circle(team_single, 4.0, centers, batched=False)
    np.testing.assert_allclose(batched[2], single[2], rtol=0, atol=1e-12)
    np.testing.assert_allclose(batched[0], single[0], rtol=0, atol=1e-12)
    # Robot 2 alone in its own world (its frame offset reproduced by the centre).
    alone = Team.make(1)
    errors, _, thrusts = run_circle(alone, 4.0, centers[2:3])
    np.testing.assert_allclose(errors[:, 0], batched[0][:, 2], atol=1e-9)
    np.testing.assert_allclose(thrusts[:, 0], batched[2][:, 2], atol=1e-9)
    assert team.warnings() == 0


def test_large_step_saturates_safely():
    """A 3 m step with a half-turn of yaw: the tilt bound and the mixer keep the
    rotors in limits, the robot does not flip and it arrives."""
    team = Team.make(1)
    team.set_state(np.array([[0.0, 0.0, 1.0]]), np.array([[1.0, 0, 0, 0]]))
    target = np.array([[3.0, -1.0, 2.0]])
    reference = QuadrotorReference.hover(target, yaw=np.array([np.pi - 0.01]))
    min_up = 1.0
    for _ in range(int(8.0 / CONTROL_PERIOD)):
        state = team.state()
        f = rotor_thrusts(team.params, GAINS, state, reference)
        assert np.all(f >= 0.0) and np.all(f <= 6.0)
        min_up = min(min_up, quaternion_to_matrix(state.quaternion)[0, 2, 2])
        team.apply(f)
    final = team.state()
    assert abs(np.angle(np.exp(1j * (yaw_of(final.quaternion)[0] - reference.yaw[0])))) < 1e-3
    assert min_up > np.cos(GAINS.max_tilt + 0.05)  # tilt overshoot < 3 deg
    assert np.linalg.norm(final.position[0] - target[0]) < 0.01
    assert team.warnings() == 0


# ------------------------------------------------- numpy oracle of the compiled controller
#
# RotorPy's SE3Control.update (rotorpy/controllers/quadrotor_control.py), batched over robots in plain numpy, with
# tether's documented choices where its law differs on purpose: test_compiled_controller_equals_numpy_rotorpy_oracle
# lists them.


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _vee(s: np.ndarray) -> np.ndarray:
    """RotorPy's vee_map, batched: (N, 3, 3) skew -> (N, 3)."""
    return np.stack([-s[:, 1, 2], s[:, 0, 2], -s[:, 0, 1]], axis=-1)


def _rotations(quaternion: np.ndarray) -> np.ndarray:
    """(N, 4) quaternions (w, x, y, z), any norm -> (N, 3, 3) body-to-world, by MuJoCo's own conversion."""
    out = np.empty((len(quaternion), 9))
    for row, q in zip(out, quaternion):
        mujoco.mju_quat2Mat(row, q / np.linalg.norm(q))
    return out.reshape(-1, 3, 3)


def oracle_force(params: QuadrotorParams, gains: QuadrotorGains, position, velocity, ref_pos, ref_vel, ref_acc):
    """F_des of RotorPy, then tether's envelope. (N, 3) N and which bound acted, per robot."""
    m, g = params.mass, params.gravity
    weight = m * g
    pos_err = position - ref_pos
    dpos_err = velocity - ref_vel
    f_des = m * (-gains.kx * pos_err - gains.kv * dpos_err + ref_acc + np.array([0.0, 0.0, g]))
    lo, hi = gains.min_thrust_ratio * weight, gains.max_thrust_ratio * weight
    up = np.clip(f_des[:, 2], lo, hi)
    side = np.linalg.norm(f_des[:, :2], axis=1)
    side_max = up * np.tan(gains.max_tilt)
    tilt = side > side_max
    force = np.column_stack([f_des[:, :2] * np.where(tilt, side_max / np.where(tilt, side, 1.0), 1.0)[:, None], up])
    size = np.linalg.norm(force, axis=1)
    magnitude = size > hi
    force = force * np.minimum(1.0, hi / size)[:, None]
    bounds = {"min_thrust": f_des[:, 2] < lo, "max_thrust": f_des[:, 2] > hi, "tilt": tilt, "magnitude": magnitude}
    return force, bounds


def oracle_control(params, gains, position, velocity, quaternion, omega, ref_pos, ref_vel, ref_acc, ref_yaw,
                   ref_jerk=None, ref_yaw_rate=None):
    """Collective thrust u1 (N,), N, moment u2 (N, 3), N m, and the bounds that acted (dict of (N,) bool)."""
    n = len(position)
    mass, inertia = params.mass, np.asarray(params.inertia, dtype=float)
    force, bounds = oracle_force(params, gains, position, velocity, ref_pos, ref_vel, ref_acc)
    rot = _rotations(quaternion)
    u1 = np.einsum("ni,ni->n", force, rot[:, :, 2])  # F_des . b3, b3 = R e3
    # Heading bound (tether), then RotorPy's desired attitude.
    heading = np.arctan2(rot[:, 1, 0], rot[:, 0, 0])
    yaw_error = (ref_yaw - heading + np.pi) % (2 * np.pi) - np.pi
    yaw_cmd = heading + np.clip(yaw_error, -gains.max_yaw_error, gains.max_yaw_error)
    bounds["yaw"] = np.abs(yaw_error) > gains.max_yaw_error
    b3_des = _unit(force)
    c1_des = np.column_stack([np.cos(yaw_cmd), np.sin(yaw_cmd), np.zeros(n)])
    b2_des = _unit(np.cross(b3_des, c1_des))
    b1_des = np.cross(b2_des, b3_des)
    r_des = np.stack([b1_des, b2_des, b3_des], axis=-1)  # columns b1, b2, b3
    s_err = 0.5 * (np.swapaxes(r_des, 1, 2) @ rot - np.swapaxes(rot, 1, 2) @ r_des)
    att_err = _vee(s_err)
    # Desired body rates (tether: flatness, desired frame; zero without jerk / yaw rate).
    omega_des = np.zeros((n, 3))
    if ref_jerk is not None:
        h = (mass / np.linalg.norm(force, axis=1))[:, None] * (
            ref_jerk - np.einsum("ni,ni->n", ref_jerk, b3_des)[:, None] * b3_des)
        omega_des[:, 0] = -np.einsum("ni,ni->n", h, b2_des)
        omega_des[:, 1] = np.einsum("ni,ni->n", h, b1_des)
    if ref_yaw_rate is not None:
        omega_des[:, 2] = ref_yaw_rate * b3_des[:, 2]
    omega_ref = np.einsum("nji,njk,nk->ni", rot, r_des, omega_des)  # R^T R_des Omega_d
    w_err = omega - omega_ref
    kr, kw = np.asarray(gains.kr, dtype=float), np.asarray(gains.kw, dtype=float)
    angular = -kr * att_err - kw * w_err - np.cross(omega, omega_ref)
    u2 = angular @ inertia.T + np.cross(omega, omega @ inertia.T)  # I (...) + w x I w
    return u1, u2, bounds


def _largest_fit(base: np.ndarray, step: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(N,) the largest s in [0, 1] with lo <= base + s step <= hi on every rotor."""
    with np.errstate(divide="ignore", invalid="ignore"):
        room = np.where(step > 0, (hi - base) / step, np.where(step < 0, (lo - base) / step, np.inf))
    return np.clip(room.min(axis=1), 0.0, 1.0)


def oracle_mix(params: QuadrotorParams, u1: np.ndarray, u2: np.ndarray):
    """Rotor thrusts (N, 4), N, and which priority stage cut back (dict of (N,) bool)."""
    rotor_pos = np.asarray(params.rotor_positions, dtype=float)
    f_to_tm = np.vstack([np.ones((1, 4)), np.cross(rotor_pos, [0.0, 0.0, 1.0])[:, :2].T,
                         np.asarray(params.rotor_drag, dtype=float)[None]])
    tm_to_f = np.linalg.inv(f_to_tm)
    lo, hi = np.asarray(params.thrust_min, dtype=float), np.asarray(params.thrust_max, dtype=float)
    per_newton = tm_to_f[:, 0]
    t_lo, t_hi = np.max(lo / per_newton), np.min(hi / per_newton)
    collective = np.clip(u1, t_lo, t_hi)
    base = collective[:, None] * per_newton
    roll_pitch = u2[:, :2] @ tm_to_f[:, 1:3].T
    s_rp = _largest_fit(base, roll_pitch, lo, hi)
    base = base + s_rp[:, None] * roll_pitch
    yaw = u2[:, 2:3] * tm_to_f[:, 3]
    s_yaw = _largest_fit(base, yaw, lo, hi)
    rotor = np.clip(base + s_yaw[:, None] * yaw, lo, hi)
    stages = {"collective": collective != u1, "roll_pitch": s_rp < 1.0, "yaw": s_yaw < 1.0}
    return rotor, stages


def _asymmetric_params() -> QuadrotorParams:
    """The robot file compiled with its centre of mass off centre, a full inertia, rotors moved, unequal drag
    coefficients and thrust ranges: every index of the controller and mixer matters."""
    spec = mujoco.MjSpec.from_file(str(ROBOT_FILE))
    base = spec.body("base")
    base.mass = 1.2
    base.ipos = [0.011, -0.007, -0.004]
    base.inertia = [0.0, 0.0, 0.0]
    base.fullinertia = [0.0091, 0.0077, 0.0152, 0.0004, -0.0003, 0.0002]
    rotors = [(-0.015, 0.0, 6.0, (0.004, 0.0)), (0.017, 0.1, 5.5, (0.0, -0.006)), (-0.016, 0.0, 6.4, (-0.003, 0.002)),
              (0.018, 0.05, 5.8, (0.0, 0.0))]
    for k, (drag, lo, hi, shift) in enumerate(rotors, 1):
        actuator = spec.actuator(f"thrust{k}")
        actuator.gear = [0.0, 0.0, 1.0, 0.0, 0.0, drag]
        actuator.ctrlrange = [lo, hi]
        site = spec.site(f"thrust{k}")
        site.pos = site.pos + np.r_[shift, 0.0]
    params = quadrotor_params(spec.compile())
    assert abs(params.inertia[0, 1]) > 0 and len(set(params.thrust_max)) == 4  # the model took the changes
    return params


ORACLE_MODELS = {"robot_file": lambda: quadrotor_params(mujoco.MjModel.from_xml_path(str(ROBOT_FILE))),
                 "asymmetric": _asymmetric_params}
ORACLE_GAINS = {"default": GAINS,
                "per_axis": QuadrotorGains(kx=11.0, kv=5.3, kr=(410.0, 530.0, 9.0), kw=(33.0, 47.0, 4.1), max_tilt=0.45,
                                           min_thrust_ratio=0.4, max_thrust_ratio=1.6, max_yaw_error=0.35)}


def _matrix_quaternions(rot: np.ndarray) -> np.ndarray:
    out = np.empty((len(rot), 4))
    for q, r in zip(out, rot):
        mujoco.mju_mat2Quat(q, r.ravel())
    return out


def _axis_angle_matrices(vectors: np.ndarray) -> np.ndarray:
    """(N, 3) rotation vectors -> (N, 3, 3)."""
    out = np.empty((len(vectors), 9))
    for row, v in zip(out, vectors):
        q = np.zeros(4)
        angle = np.linalg.norm(v)
        mujoco.mju_axisAngle2Quat(q, v / angle if angle > 0 else np.array([0.0, 0.0, 1.0]), angle)
        mujoco.mju_quat2Mat(row, q)
    return out.reshape(-1, 3, 3)


def random_case(rng: np.random.Generator, params: QuadrotorParams, gains: QuadrotorGains, n: int) -> dict:
    """Random states and references for n robots, each in one of three regimes:

    - near: small errors, attitude close to the commanded one (rotors within limits, the law as such);
    - envelope: large position / velocity / acceleration errors (force bounds), attitude still close to the
      commanded force direction, the reference yaw near the heading or anywhere (heading bound);
    - wild: any attitude (upside down included), fast spin, any yaw (every mixer stage saturates).
    The attitude is a rotation vector away from the commanded force direction at a random heading; the
    quaternion is given with a random sign and a norm within 1e-3 of 1.
    """
    regime = rng.choice(["near", "envelope", "wild"], size=n, p=[0.35, 0.4, 0.25])
    near, envelope, wild = (regime == r for r in ("near", "envelope", "wild"))

    def spread(near_scale, envelope_scale, wild_scale, shape=(3,)):
        scale = np.select([near, envelope, wild], [near_scale, envelope_scale, wild_scale])
        return rng.normal(size=(n, *shape)) * scale.reshape((n,) + (1,) * len(shape))

    ref_pos = rng.uniform(-5.0, 5.0, (n, 3))
    ref_vel = rng.normal(size=(n, 3))
    ref_acc = spread(0.3, 4.0, 6.0)
    position = ref_pos + spread(0.03, 0.6, 2.0)
    velocity = ref_vel + spread(0.05, 1.0, 3.0)
    force, _ = oracle_force(params, gains, position, velocity, ref_pos, ref_vel, ref_acc)
    # Attitude: body z along the commanded force (minimal rotation from e3), at a random heading, perturbed.
    b3 = _unit(force)
    tilt_axis = np.cross([0.0, 0.0, 1.0], b3)
    tilt_angle = np.arccos(np.clip(b3[:, 2], -1.0, 1.0))
    to_force = _axis_angle_matrices(_unit(tilt_axis) * tilt_angle[:, None])
    heading = _axis_angle_matrices(np.column_stack([np.zeros((n, 2)), rng.uniform(-np.pi, np.pi, n)]))
    perturbation = _axis_angle_matrices(spread(0.02, 0.02, 0.0))
    rot = to_force @ heading @ perturbation
    rot[wild] = _rotations(rng.normal(size=(int(wild.sum()), 4)))  # uniform on SO(3)
    quaternion = _matrix_quaternions(rot) * rng.choice([-1.0, 1.0], (n, 1)) * rng.uniform(1 - 1e-3, 1 + 1e-3, (n, 1))
    current_heading = np.arctan2(rot[:, 1, 0], rot[:, 0, 0])
    far_yaw = rng.uniform(size=n) < 0.5
    yaw_offset = np.where(far_yaw & ~near, rng.uniform(-3.0, 3.0, n), rng.normal(size=n) * 0.02)
    ref_yaw = np.where(wild, rng.uniform(-np.pi, np.pi, n), current_heading + yaw_offset)
    ref_yaw = ref_yaw + 2 * np.pi * rng.integers(-2, 3, n)  # any branch of the angle
    omega = spread(0.2, 0.2, 4.0)
    choice = rng.integers(4)
    return dict(position=position, velocity=velocity, quaternion=quaternion, angular_velocity=omega,
                ref_pos=ref_pos, ref_vel=ref_vel, ref_acc=ref_acc, ref_yaw=ref_yaw,
                ref_jerk=spread(0.5, 2.0, 5.0) if choice & 1 else None,
                ref_yaw_rate=rng.normal(size=n) * 0.5 if choice & 2 else None)


ORACLE_CALLS = 300  # per model and gain set: 1200 calls, N = 1..8 robots each (5400 robots)


@pytest.mark.parametrize("gains_name", list(ORACLE_GAINS))
@pytest.mark.parametrize("model_name", list(ORACLE_MODELS))
def test_compiled_controller_equals_numpy_rotorpy_oracle(model_name, gains_name):
    """The compiled track_reference (controller + mixer) equals a plain numpy oracle of the same law.

    The oracle (oracle_force, oracle_control, oracle_mix) is RotorPy's SE3Control.update written over a batch,
    with tether's documented choices where its law differs from RotorPy's on purpose:

    - gains: RotorPy's position / velocity gains already act as m (...) and its attitude gains as I (...),
      i.e. normalised by mass and inertia; so are tether's, kx / kv scalar and kr / kw one per body axis;
    - the commanded force is bounded before it is used (RotorPy uses F_des as it is): upward component in
      [min_thrust_ratio, max_thrust_ratio] m g, then the horizontal part scaled down to tilt <= max_tilt, then the
      magnitude to <= max_thrust_ratio m g;
    - b1 comes from a bounded heading, not from the reference yaw itself: yaw_cmd = heading +
      clip(wrap(yaw_ref - heading), +-max_yaw_error), heading = atan2(R[1, 0], R[0, 0]) of the current attitude;
    - desired body rates: RotorPy takes w_des = (0, 0, yaw_dot) in the body frame. Tether takes Lee et al.'s
      Omega_d from differential flatness (Mellinger and Kumar 2011), in the desired frame: with
      h = m / |F| (jerk - (b3_des . jerk) b3_des), Omega_d = (-h . b2_des, h . b1_des, yaw_rate b3_des,z), each
      part zero when its reference (jerk, yaw rate) is absent; it uses R^T R_des Omega_d in the rate error and
      adds Lee's eq. 16 feedforward -I (w x R^T R_des Omega_d) (dOmega_d/dt taken as 0);
    - quaternions are (w, x, y, z), normalised first (RotorPy's are unit (x, y, z, w));
    - mixer: RotorPy applies TM_to_f = inv(f_to_TM) (built here as RotorPy builds it: rows 1, cross(r, e3)[:2],
      signed drag) without limits. Tether keeps every rotor in [thrust_min, thrust_max] with a fixed priority:
      the collective thrust clipped to what the rotors give with no torque, then the roll/pitch torque scaled as a
      vector by the largest factor in [0, 1] that fits, then the yaw torque likewise, then a clip (round-off).

    Where none of these acts (no bound active, rotors within limits, no jerk or yaw rate given) the oracle is
    RotorPy's law term by term.

    Params come from the compiled robot file and from a compiled asymmetric variant of it (every index of
    inertia, rotor geometry and limits matters), with the default gains and with per-axis gains. Over
    ORACLE_CALLS seeded random batched calls (N = 1..8 robots) per pair, the rotor thrusts agree to 1e-9
    relative (plus 1e-12 N) everywhere - rotors within their limits or not - and exactly the same rotors sit at a
    limit (both clip the same way). The controller alone (geometric_control: u1, u2) and the mixer alone (mix)
    agree with the oracle's halves too, and rotor_thrusts with track_reference bit for bit. Each branch - the
    four force bounds, the heading bound, jerk and yaw-rate feedforward, the three mixer stages, upside-down
    attitudes, and RotorPy's law as is - is hit by at least a stated number of robots.
    """
    params, gains = ORACLE_MODELS[model_name](), ORACLE_GAINS[gains_name]
    rng = np.random.default_rng([2010, list(ORACLE_MODELS).index(model_name), list(ORACLE_GAINS).index(gains_name)])
    lo, hi = params.thrust_min, params.thrust_max
    counts: dict[str, int] = {}
    worst = 0.0
    for call in range(ORACLE_CALLS):
        n = call % 8 + 1
        case = random_case(rng, params, gains, n)
        args = [case[k] for k in ("position", "velocity", "quaternion", "angular_velocity", "ref_pos", "ref_vel",
                                  "ref_acc", "ref_yaw", "ref_jerk", "ref_yaw_rate")]
        compiled = track_reference(params, gains, *args)
        u1, u2, bounds = oracle_control(params, gains, *args)
        expected, stages = oracle_mix(params, u1, u2)
        assert compiled.shape == (n, 4)
        error = np.abs(compiled - expected)
        worst = max(worst, float((error / (np.abs(expected) + 1e-3)).max()))
        bad = np.flatnonzero(np.any(error > 1e-9 * np.abs(expected) + 1e-12, axis=1))
        assert bad.size == 0, (f"call {call}, robots {bad}: compiled {compiled[bad]}, oracle {expected[bad]}",
                               {k: None if v is None else v[bad] for k, v in case.items()})
        at_limit = lambda f: np.column_stack([np.isclose(f, lo, rtol=0, atol=1e-10),  # noqa: E731
                                              np.isclose(f, hi, rtol=0, atol=1e-10)])
        assert np.array_equal(at_limit(compiled), at_limit(expected)), (call, compiled, expected)
        # The two halves, each alone.
        state = QuadrotorState(*args[:4])
        reference = QuadrotorReference(*args[4:])
        thrust, torque = geometric_control(params, gains, state, reference)
        np.testing.assert_allclose(thrust, u1, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(torque, u2, rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(mix(params, u1, u2), expected, rtol=1e-9, atol=1e-12)
        np.testing.assert_array_equal(rotor_thrusts(params, gains, state, reference), compiled)
        # What was exercised.
        flags = {**bounds, **{f"mixer_{k}": v for k, v in stages.items()}}
        flags["jerk"] = np.full(n, case["ref_jerk"] is not None)
        flags["yaw_rate"] = np.full(n, case["ref_yaw_rate"] is not None)
        bounded = np.any([bounds[k] for k in bounds], axis=0)
        saturated = np.any([stages[k] for k in stages], axis=0)
        flags["rotorpy_as_is"] = ~bounded & ~saturated & ~flags["jerk"] & ~flags["yaw_rate"]
        for key in bounds:
            flags[f"{key}_in_limits"] = bounds[key] & ~saturated
        flags["feedforward_in_limits"] = (flags["jerk"] | flags["yaw_rate"]) & ~saturated
        flags["upside_down"] = u1 < 0
        for key, value in flags.items():
            counts[key] = counts.get(key, 0) + int(np.sum(value))
    print(f"{model_name}/{gains_name}: worst relative difference {worst:.2e}; robots per branch {counts}")
    least = {"min_thrust": 50, "max_thrust": 50, "tilt": 100, "magnitude": 50, "yaw": 100, "jerk": 300, "yaw_rate": 300,
             "mixer_collective": 100, "mixer_roll_pitch": 100, "mixer_yaw": 100, "upside_down": 50,
             "rotorpy_as_is": 50, "feedforward_in_limits": 100, "tilt_in_limits": 30, "min_thrust_in_limits": 5}
    if gains.max_thrust_ratio * params.mass * params.gravity < params.mixer_tables[4]:  # the force bound below T's
        least.update(max_thrust_in_limits=10, magnitude_in_limits=10)
    if gains_name == "per_axis":  # default kr[2]: a heading error at the bound asks more yaw torque than there is
        least["yaw_in_limits"] = 20
    missed = {key: (counts[key], at_least) for key, at_least in least.items() if counts[key] < at_least}
    assert not missed, missed


def test_oracle_pinned_cases():
    """Hand-checked figures of the oracle itself (so that it is not only self-consistent with the compiled
    controller): hover needs m g / 4 per rotor of the robot file; a robot 0.25 m below its set point asks
    m (g + 0.25 kx) up; upside down it asks nothing of the rotors; a yaw reference a half-turn away is
    approached max_yaw_error ahead (the yaw torque's sign says which way)."""
    params = ORACLE_MODELS["robot_file"]()
    mg = params.mass * params.gravity
    zero, one = np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0, 0.0]])
    at = np.array([[0.0, 0.0, 1.0]])
    u1, u2, _ = oracle_control(params, GAINS, at, zero, one, zero, at, zero, zero, np.zeros(1))
    np.testing.assert_allclose(oracle_mix(params, u1, u2)[0], mg / 4, rtol=1e-12)
    u1, u2, bounds = oracle_control(params, GAINS, at - [0, 0, 0.25], zero, one, zero, at, zero, zero, np.zeros(1))
    assert u1[0] == pytest.approx(params.mass * (params.gravity + 0.25 * GAINS.kx))
    assert not any(b[0] for b in bounds.values())
    np.testing.assert_allclose(u2, 0.0, atol=1e-15)
    flipped = np.array([[0.0, 1.0, 0.0, 0.0]])  # half-turn about x
    u1, _, _ = oracle_control(params, GAINS, at, zero, flipped, zero, at, zero, zero, np.zeros(1))
    assert u1[0] == pytest.approx(-mg)
    assert np.all(oracle_mix(params, u1, np.zeros((1, 3)))[0] == 0.0)
    _, u2, bounds = oracle_control(params, GAINS, at, zero, one, zero, at, zero, zero, np.array([3.0]))
    assert bounds["yaw"][0]
    assert u2[0, 2] == pytest.approx(params.inertia[2, 2] * GAINS.kr[2] * np.sin(GAINS.max_yaw_error))
    np.testing.assert_allclose(u2[0, :2], 0.0, atol=1e-15)
