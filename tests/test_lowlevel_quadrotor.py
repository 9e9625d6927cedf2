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
