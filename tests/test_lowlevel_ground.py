"""Differential-drive low-level control in real MuJoCo simulation of
models/robots/ground_robot.xml.

The test world is built with MjSpec: a floor plus N attached copies of the
robot file (prefixes ground0/, ground1/, ...), 2 ms physics with the scenes'
implicitfast integrator, the controller evaluated every 10 ms and its wheel
speed commands held for 5 physics steps.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import mujoco
import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from controllers.lowlevel.ground import (
    DEFAULT_OFFSET,
    GroundRobotParams,
    offset_point,
    track_velocity,
    unicycle_command,
    velocity_to_target,
    wheel_speeds,
    yaw_from_quaternion,
)
from controllers.lowlevel.model_params import ground_robot_params

ROBOT_FILE = Path(__file__).resolve().parents[1] / "models" / "robots" / "ground_robot.xml"
TIMESTEP = 0.002  # s, physics step (as in the scenes)
CONTROL_PERIOD = 0.01  # s
STEPS_PER_CONTROL = round(CONTROL_PERIOD / TIMESTEP)
SPACING = 0.5  # m, between robots along y in the test world
SPEED = 0.08  # m/s, cruise command (about half the 0.154 m/s top speed)
PARAMS = ground_robot_params(mujoco.MjModel.from_xml_path(str(ROBOT_FILE)))


def build_world(count: int) -> mujoco.MjModel:
    spec = mujoco.MjSpec()
    spec.option.timestep = TIMESTEP
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    spec.worldbody.add_geom(name="floor", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[10, 10, 0.1])
    for i in range(count):
        frame = spec.worldbody.add_frame(pos=[0.0, SPACING * i, 0.0])
        spec.attach(mujoco.MjSpec.from_file(str(ROBOT_FILE)), prefix=f"ground{i}/", frame=frame)
    return spec.compile()


@dataclass
class Fleet:
    """Name-resolved addresses of N ground robots in a model (looked up once)."""

    model: mujoco.MjModel
    data: mujoco.MjData
    qpos: np.ndarray  # (N,) free-joint qpos addresses
    dof: np.ndarray  # (N,) free-joint dof addresses
    actuators: np.ndarray  # (N, 2) actuator ids (left, right)
    wheel_dofs: np.ndarray  # (N, 2) wheel joint dof addresses (left, right)
    params: GroundRobotParams

    @staticmethod
    def make(count: int) -> "Fleet":
        model = build_world(count)
        roots = [model.joint(f"ground{i}/root") for i in range(count)]
        wheels = ("left_wheel", "right_wheel")
        fleet = Fleet(
            model,
            mujoco.MjData(model),
            np.array([j.qposadr[0] for j in roots]),
            np.array([j.dofadr[0] for j in roots]),
            np.array([[model.actuator(f"ground{i}/{w}").id for w in wheels] for i in range(count)]),
            np.array([[model.joint(f"ground{i}/{w}").dofadr[0] for w in wheels] for i in range(count)]),
            ground_robot_params(model, "ground0/"),
        )
        mujoco.mj_forward(model, fleet.data)
        return fleet

    def place(self, xy: np.ndarray, yaw: np.ndarray) -> None:
        """Put robot i at (x, y) with heading yaw, wheels on the floor, at rest."""
        for i, (p, th) in enumerate(zip(xy, yaw)):
            a = self.qpos[i]
            self.data.qpos[a : a + 7] = [p[0], p[1], PARAMS.wheel_radius, np.cos(th / 2), 0, 0, np.sin(th / 2)]
        self.data.qvel[:] = 0.0
        mujoco.mj_forward(self.model, self.data)

    def pose(self) -> tuple[np.ndarray, np.ndarray]:
        """Centre position (N, 3), m, world frame, and heading (N,), rad."""
        q = self.data.qpos
        position = np.array([q[a : a + 3] for a in self.qpos])
        yaw = yaw_from_quaternion(np.array([q[a + 3 : a + 7] for a in self.qpos]))
        return position, yaw

    def apply(self, wheels: np.ndarray) -> None:
        self.data.ctrl[self.actuators.ravel()] = wheels.ravel()
        mujoco.mj_step(self.model, self.data, nstep=STEPS_PER_CONTROL)

    def wheel_velocities(self) -> np.ndarray:
        return self.data.qvel[self.wheel_dofs]

    def warnings(self) -> int:
        return int(sum(w.number for w in self.data.warning))


def drive(fleet: Fleet, duration: float, command) -> dict[str, np.ndarray]:
    """Run ``command(t, centre_xy, yaw, offset_xy) -> (N, 2) m/s`` through
    :func:`track_velocity`; log the offset point, centre, commands, wheels."""
    log = {k: [] for k in ("t", "point", "centre", "yaw", "u", "cmd", "wheel")}
    for _ in range(int(round(duration / CONTROL_PERIOD))):
        centre, yaw = fleet.pose()
        point = offset_point(centre, yaw)
        u = command(fleet.data.time, centre[:, :2], yaw, point)
        cmd = track_velocity(fleet.params, u, yaw)
        for key, value in zip(log, (fleet.data.time, point, centre, yaw, u, cmd, fleet.wheel_velocities().copy())):
            log[key].append(value)
        fleet.apply(cmd)
    out = {k: np.array(v) for k, v in log.items()}
    # Offset-point velocity over each control period (forward difference).
    out["velocity"] = np.diff(out["point"], axis=0) / CONTROL_PERIOD
    return out


# ----------------------------------------------------------------- pure math


def test_params_from_bare_file_and_prefixed_copy():
    fleet = Fleet.make(2)
    for prefix in ("ground0/", "ground1/"):
        assert ground_robot_params(fleet.model, prefix) == PARAMS
    assert PARAMS.wheel_radius == pytest.approx(0.0205)
    assert PARAMS.half_axle == pytest.approx(0.0265)
    assert PARAMS.wheel_speed_max == pytest.approx(7.5)
    assert PARAMS.wheel_direction == (1.0, 1.0)
    assert PARAMS.max_speed == pytest.approx(0.15375)
    with pytest.raises(KeyError):
        ground_robot_params(fleet.model, "ground9/")


@settings(max_examples=100, deadline=None)
@given(
    u=st.tuples(st.floats(-0.2, 0.2), st.floats(-0.2, 0.2)),
    yaw=st.floats(-np.pi, np.pi),
    offset=st.floats(0.005, 0.05),
)
@example(u=(0.1953125, 0.19921875), yaw=-0.75, offset=0.005)  # failed at h = 1e-4 (CI, a fresh clone)
def test_offset_point_moves_with_the_command(u, yaw, offset):
    """Moving the unicycle exactly with (v, omega) moves P_b at velocity u
    (central difference over +-h of the closed-form unicycle motion)."""
    u = np.array([u])
    v, omega = unicycle_command(u, np.array([yaw]), offset)

    def pose(t):  # exact unicycle motion from (0, 0, yaw), constant v and omega
        a = omega[0] * t
        mid = yaw + a / 2
        chord = v[0] * t * np.sinc(a / (2 * np.pi))  # 2 v / omega sin(a / 2), stable at 0
        return np.array([[chord * np.cos(mid), chord * np.sin(mid)]]), np.array([yaw + a])

    # P_b turns at omega (up to 0.28 / 0.005 = 57 rad/s here): the central difference's error,
    # |u| (omega h)^2 / 6, was 1.5e-6 m/s at h = 1e-4 against the 1e-6 tolerance; 1.5e-8 at 1e-5.
    h = 1e-5
    velocity = (offset_point(*pose(h), offset) - offset_point(*pose(-h), offset)) / (2 * h)
    np.testing.assert_allclose(velocity, u, atol=1e-6)


@settings(max_examples=200, deadline=None)
@given(v=st.floats(-1.0, 1.0), omega=st.floats(-30.0, 30.0))
def test_wheel_limits_keep_curvature(v, omega):
    w = wheel_speeds(PARAMS, np.array([v]), np.array([omega]))
    assert np.all(np.abs(w) <= PARAMS.wheel_speed_max + 1e-12)
    r, half = PARAMS.wheel_radius, PARAMS.half_axle
    v_out = r * (w[0, 0] + w[0, 1]) / 2
    omega_out = r * (w[0, 1] - w[0, 0]) / (2 * half)
    # Same direction in (v, omega): the output is the command scaled by s in (0, 1].
    assert v_out * omega - omega_out * v == pytest.approx(0.0, abs=1e-9)
    assert v_out * v + omega_out * omega >= 0.0
    if max(abs(v - half * omega), abs(v + half * omega)) / r <= PARAMS.wheel_speed_max:
        assert v_out == pytest.approx(v, abs=1e-12) and omega_out == pytest.approx(omega, abs=1e-12)


def test_velocity_to_target_saturates():
    pos = np.array([[0.0, 0.0], [0.0, 0.0]])
    target = np.array([[1.0, 0.0], [0.0, 0.02]])
    u = velocity_to_target(pos, target, gain=1.0, max_speed=0.1)
    np.testing.assert_allclose(u, [[0.1, 0.0], [0.0, 0.02]])


def test_shape_asserts():
    with pytest.raises(AssertionError):
        track_velocity(PARAMS, np.zeros((3, 2)), np.zeros(2))
    with pytest.raises(AssertionError):
        velocity_to_target(np.zeros((2, 3)), np.zeros((2, 3)), 1.0, 0.1)


# ------------------------------------------------------------ in simulation


@pytest.mark.parametrize("yaw0", [0.0, np.pi / 2], ids=["aligned", "sideways"])
def test_constant_velocity_command(yaw0):
    """0.08 m/s along +x; the sideways start has to turn a quarter first."""
    fleet = Fleet.make(1)
    fleet.place(np.zeros((1, 2)), np.array([yaw0]))
    log = drive(fleet, 10.0, lambda t, c, y, p: np.array([[SPEED, 0.0]]))
    settled = log["t"][:-1] >= 1.5
    err = np.linalg.norm(log["velocity"][settled, 0] - log["u"][:-1][settled, 0], axis=1)
    heading = np.abs(log["yaw"][log["t"] >= 1.5, 0])
    lateral = np.abs(log["point"][log["t"] >= 1.5, 0, 1] - log["point"][0, 0, 1])
    print(
        f"constant {SPEED} m/s ({'sideways' if yaw0 else 'aligned'} start): velocity error mean "
        f"{err.mean() * 1000:.2f} mm/s, max {err.max() * 1000:.2f} mm/s, heading error max {heading.max():.1e} rad, "
        f"lateral offset {lateral.max() * 1000:.1f} mm"
    )
    assert err.mean() <= 0.03 * SPEED and err.max() <= 0.05 * SPEED
    assert heading.max() <= 0.01
    assert lateral.max() <= 0.03  # the quarter turn on the spot shifts the point by ~b
    assert fleet.warnings() == 0


def test_turning_command():
    """Open loop: u(t) = 0.08 (cos 0.4 t, sin 0.4 t), a 0.2 m circle for the offset
    point; closed loop: the same path with u = u_ref + k (p_ref - P_b)."""
    rate, gain = 0.4, 2.0  # rad/s, 1/s

    def u_ref(t):
        return SPEED * np.array([[np.cos(rate * t), np.sin(rate * t)]])

    fleet = Fleet.make(2)
    fleet.place(np.array([[0.0, 0.0], [0.0, SPACING]]), np.zeros(2))
    centre0, yaw0 = fleet.pose()
    start = offset_point(centre0, yaw0)

    def p_ref(t):  # integral of u_ref from the start point
        return start + (SPEED / rate) * np.column_stack(
            [np.full(2, np.sin(rate * t)), np.full(2, 1.0 - np.cos(rate * t))]
        )

    def command(t, centre, yaw, point):
        open_loop = u_ref(t)[0]
        closed = u_ref(t)[0] + gain * (p_ref(t)[1] - point[1])
        return np.vstack([open_loop, closed])

    log = drive(fleet, 16.0, command)
    t = log["t"]
    ref = np.array([p_ref(s) for s in t])
    vel_err = np.linalg.norm(log["velocity"][:, 0] - np.array([u_ref(s)[0] for s in t[:-1]]), axis=1)[t[:-1] >= 1.0]
    open_pos = np.linalg.norm(log["point"][:, 0] - ref[:, 0], axis=1)
    closed_pos = np.linalg.norm(log["point"][:, 1] - ref[:, 1], axis=1)[t >= 1.0]
    print(
        f"turning 0.08 m/s at 0.4 rad/s: open-loop velocity error mean {vel_err.mean() * 1000:.2f} mm/s, "
        f"max {vel_err.max() * 1000:.2f} mm/s, open-loop drift after 16 s {open_pos[-1] * 1000:.1f} mm; "
        f"closed loop (k=2/s) position error mean {closed_pos.mean() * 1000:.2f} mm, max {closed_pos.max() * 1000:.2f} mm"
    )
    assert vel_err.mean() <= 0.03 * SPEED and vel_err.max() <= 0.05 * SPEED
    assert open_pos[-1] <= 0.03
    assert closed_pos.max() <= 0.005
    assert fleet.warnings() == 0


@pytest.mark.parametrize("yaw0", [0.0, np.pi / 2, 3.0], ids=["facing", "sideways", "away"])
def test_drives_to_waypoint_and_stops(yaw0):
    """Waypoint 1 m ahead along +x, P gain 1/s, at most 0.1 m/s: the robot's
    centre stops within 2 cm of it (closing the loop on the centre)."""
    fleet = Fleet.make(1)
    fleet.place(np.zeros((1, 2)), np.array([yaw0]))
    waypoint = np.array([[1.0, 0.0]])
    log = drive(fleet, 16.0, lambda t, c, y, p: velocity_to_target(c, waypoint, 1.0, 0.1))
    final = np.linalg.norm(log["centre"][-1, 0, :2] - waypoint[0])
    speed = np.linalg.norm(log["velocity"][-50:, 0], axis=1).max()
    print(f"waypoint 1 m (start yaw {yaw0:.2f}): centre stops {final * 1000:.2f} mm away, last 0.5 s speed <= {speed * 1000:.2f} mm/s")
    assert final <= 0.02
    assert speed <= 0.001
    assert np.all(np.abs(log["cmd"]) <= PARAMS.wheel_speed_max)
    assert fleet.warnings() == 0


def test_offset_point_reaches_waypoint():
    """The offset point is an exact single integrator: it converges onto the
    waypoint; the centre stops b behind it."""
    fleet = Fleet.make(1)
    fleet.place(np.zeros((1, 2)), np.array([-1.0]))
    waypoint = np.array([[0.7, 0.7]])
    log = drive(fleet, 16.0, lambda t, c, y, p: velocity_to_target(p, waypoint, 1.0, 0.1))
    final = np.linalg.norm(log["point"][-1, 0] - waypoint[0])
    centre = np.linalg.norm(log["centre"][-1, 0, :2] - waypoint[0])
    print(f"offset point to waypoint: {final * 1000:.2f} mm away, centre {centre * 1000:.1f} mm away")
    assert final <= 0.005
    assert centre <= DEFAULT_OFFSET + 0.005
    assert fleet.warnings() == 0


def test_wheel_limits_respected_in_simulation():
    """Commands far beyond top speed (1 m/s, changing direction): commands and
    wheel velocities stay within the limit and the robot stays upright."""
    fleet = Fleet.make(1)
    fleet.place(np.zeros((1, 2)), np.zeros(1))

    def command(t, c, y, p):
        return np.array([[np.cos(1.5 * t), np.sin(1.5 * t)]])  # 1 m/s, turning

    log = drive(fleet, 5.0, command)
    limit = PARAMS.wheel_speed_max
    assert np.abs(log["cmd"]).max() <= limit
    assert np.abs(log["wheel"]).max() <= 1.02 * limit  # servo overshoot only
    assert np.abs(log["centre"][:, 0, 2] - PARAMS.wheel_radius).max() < 0.002  # no tipping
    saturated = np.abs(log["cmd"]).max(axis=2)[:, 0] >= limit - 1e-9
    assert saturated.mean() > 0.9
    assert fleet.warnings() == 0


def test_batch_equals_each_alone():
    """Three robots with different commands in one call give the commands of
    three single calls, and each robot moves as it does alone in its world."""
    yaw0 = np.array([0.3, -2.0, 1.2])
    targets = np.array([[0.8, 0.2], [-0.5, SPACING + 0.6], [0.3, 2 * SPACING - 0.4]])
    fleet = Fleet.make(3)
    fleet.place(np.array([[0.0, i * SPACING] for i in range(3)]), yaw0)

    def command(t, c, y, p):
        return velocity_to_target(c, targets[: len(c)], 1.0, 0.1)

    batched = []
    for _ in range(300):
        centre, yaw = fleet.pose()
        u = command(0.0, centre[:, :2], yaw, None)
        cmd = track_velocity(fleet.params, u, yaw)
        single = np.vstack([track_velocity(fleet.params, u[i : i + 1], yaw[i : i + 1]) for i in range(3)])
        np.testing.assert_allclose(cmd, single, rtol=0, atol=1e-15)
        batched.append(centre.copy())
        fleet.apply(cmd)
    alone = Fleet.make(1)
    alone.place(np.array([[0.0, SPACING]]), yaw0[1:2])
    for k in range(300):
        centre, yaw = alone.pose()
        np.testing.assert_allclose(centre[0], batched[k][1], atol=1e-9)
        alone.apply(track_velocity(alone.params, velocity_to_target(centre[:, :2], targets[1:2], 1.0, 0.1), yaw))
    assert fleet.warnings() == 0


def test_rest_keyframe_is_at_rest():
    """The robot file alone: the rest keyframe settles without moving (the
    caster carries part of the weight; the robot does not tip)."""
    spec = mujoco.MjSpec.from_file(str(ROBOT_FILE))
    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[1, 1, 0.1])
    spec.option.integrator = mujoco.mjtIntegrator.mjINT_IMPLICITFAST
    model = spec.compile()
    data = mujoco.MjData(model)
    mujoco.mj_resetDataKeyframe(model, data, model.key("rest").id)
    mujoco.mj_step(model, data, nstep=1000)
    assert np.linalg.norm(data.qpos[:2]) < 1e-3
    assert abs(data.qpos[2] - PARAMS.wheel_radius) < 1e-3
    assert np.abs(data.qvel).max() < 1e-3
    assert sum(w.number for w in data.warning) == 0


@pytest.mark.parametrize("offset", [0.0, 0.03, 0.06])
@pytest.mark.parametrize("angle_deg", [0, 60, 90, 135, 180])
def test_a_robot_driving_into_another_never_climbs_or_tips_it(angle_deg, offset):
    """Robot 0 drives at full wheel speed for 5 s into robot 1 (standing, heading +y),
    approaching at ``angle_deg`` with its line ``offset`` m beside robot 1's centre.
    With the chassis' default friction the 6 cm offsets turned a robot over."""
    fleet = Fleet.make(2)
    heading = np.radians(angle_deg)
    start = -0.2 * np.array([np.cos(heading), np.sin(heading)]) + offset * np.array([-np.sin(heading), np.cos(heading)])
    fleet.place(np.array([start, [0.0, 0.0]]), np.array([heading, np.pi / 2]))
    full = PARAMS.wheel_speed_max
    highest, most_tilted = 0.0, 1.0
    for _ in range(int(round(5.0 / CONTROL_PERIOD))):
        fleet.apply(np.array([[full, full], [0.0, 0.0]]))
        for address in fleet.qpos:
            w, x, y, _ = fleet.data.qpos[address + 3 : address + 7]
            most_tilted = min(most_tilted, 1.0 - 2.0 * (x * x + y * y))  # the body's up axis, z component
            highest = max(highest, fleet.data.qpos[address + 2] - PARAMS.wheel_radius)
    centres, _ = fleet.pose()
    assert np.linalg.norm(centres[0, :2] - centres[1, :2]) > 0.065  # they did meet, and neither is on the other
    assert most_tilted > 0.97, f"tilted to an up-axis z of {most_tilted:.3f}"
    assert highest < 0.005, f"a body rose {highest * 1000:.1f} mm"

