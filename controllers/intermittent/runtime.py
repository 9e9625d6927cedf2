"""Run-time pieces shared by the intermittent paper's strategies on the simulator.

The three strategies (``intermittent``, ``all_time``, ``random_meeting``)
drive MuJoCo ground robots with single-integrator plans, take the
simulator's range readings into EKF beliefs and report the same figures;
this module holds what they share:

- :class:`PlanningWorld` - the static workspace as the planners see it:
  obstacle boxes that reach the sensor height (the floor slab is dropped, or
  every move would collide with it), plane bounds and the sensor height.
- :class:`TimedPath` - a planned :class:`RobotPath` (integer steps) executed
  from a sim-time offset: the reference position and velocity a ground robot
  tracks (|v| <= u_max per step).
- (in :mod:`controllers.task`, shared with ``connected_tracking``) the
  readings as records, the prior, the time base, :class:`EstimateSeries`.
- the team colours of the decorations (:class:`sim.types.Decorations`:
  ``robot_colors``, ``paths``, ``meeting_points``).

Units: m, s; plane positions (x, y) in the world frame; discrete steps are
``sensing.period_s`` seconds (``step_s``).
"""

from __future__ import annotations

import bisect
import math
from dataclasses import dataclass

import numpy as np

from controllers.intermittent.params import IntermittentParams
from controllers.intermittent.planner import PlannerParams, RobotPath
# The intermittent paper's task as every method sees it (re-exported: the strategies import it from here).
from controllers.task import EstimateSeries, check_time_base, measurement_records, prior_state  # noqa: F401
from sim.compiled import kernel
from sim import palette
from sim.config import ConfigError
from sim.geometry import Boxes, boxes_reaching, clearance_at, pairwise_min_distance
from sim.types import PATH_STYLES, Commands, Observation, WorldInfo

PATH_HEIGHT_M = 0.01  # drawn paths lie this high above the floor, m

# Team colours (RGBA, 0..1), cycled by team index: the palette's (sim.palette).
TEAM_COLORS = palette.TEAMS


def team_color(team: int) -> np.ndarray:
    return palette.team(team)


def team_path_style(team: int) -> str:
    """Team ``team``'s path line style (sim.types.PATH_STYLES, cycled): teams next in index, whose
    colours can be near, differ in their line too."""
    return PATH_STYLES[team % len(PATH_STYLES)]


def as_config_error(err: ValueError, prefix: str = "strategy") -> ConfigError:
    """ValueError('field: problem') from a parameter check -> ConfigError('strategy.field', problem)."""
    if isinstance(err, ConfigError):
        return err
    name, sep, problem = str(err).partition(": ")
    if sep and " " not in name:
        return ConfigError(f"{prefix}.{name}", problem)
    return ConfigError(prefix, str(err))


@dataclass(frozen=True)
class PlanningWorld:
    """The static workspace as seen by the planners.

    boxes: obstacles that reach above half the sensor height (walls, pillars,
    ceiling), m; bounds: (2, 2) plane bounds [[x_min, y_min], [x_max, y_max]],
    m; sensor_height: z of the range sensors and radios, m.
    """

    boxes: Boxes
    bounds: np.ndarray
    sensor_height: float

    @staticmethod
    def from_world(world: WorldInfo, initial: Observation) -> "PlanningWorld":
        z = float(np.mean(initial.sensor_position[:, 2]))
        boxes = boxes_reaching(world.obstacles, 0.5 * z)
        return PlanningWorld(boxes, np.asarray(world.bounds, dtype=float)[:, :2].copy(), z)


def planner_params(params: IntermittentParams, world: WorldInfo, planning: PlanningWorld,
                   robot_radius: float | None = None) -> PlannerParams:
    """Algorithm 1's parameters from the strategy parameters and the world."""
    comm = world.comm_range_m - params.link_margin_m
    if comm <= 0:
        raise ConfigError("strategy.link_margin_m",
                          f"must be below sensing.comm_range_m ({world.comm_range_m} m), got {params.link_margin_m}")
    try:
        return PlannerParams(
            n_sample=params.n_sample,
            n_uniform=min(params.n_uniform, params.n_sample),
            step_size=params.step_size_m,
            u_max=params.speed_mps * world.sensing_period_s,
            comm_range=comm,
            delta=params.delta_m2,
            sensor_height=planning.sensor_height,
            robot_radius=params.clearance_m if robot_radius is None else robot_radius,
            sensing_range=world.target_range_m,
        )
    except ValueError as err:
        raise as_config_error(err) from None


def team_samples(n_sample: int, team_size: int) -> int:
    """Algorithm 1 samples for a team of ``team_size`` robots: ``n_sample``
    (the strategy's, for 2 robots) times team_size / 2 for larger teams.

    The joint space of a team of n has 2n dimensions and its goal set
    (connected and synchronised) is a thin slice of it: at a fixed n_sample
    a 4-robot team found a goal node in about half the plans; n_sample per
    robot pair keeps 2-robot (and 1-point formation) plans as they were.
    """
    return int(n_sample) * max(int(team_size), 2) // 2


@dataclass
class TimedPath:
    """A planned path executed from sim time ``offset_s`` on.

    path: waypoints at integer steps; step_s: seconds per step. The robot is
    at path step tau = (t - offset_s) / step_s; before the path's start it
    waits at the first waypoint, after its end at the last.
    """

    path: RobotPath
    step_s: float
    offset_s: float = 0.0

    def __post_init__(self) -> None:
        # Plain-float copies of the waypoints: reference() runs for every robot every tick, and
        # numpy's per-call overhead on (2,) arrays was nearly all of its cost.
        self._times = [float(t) for t in self.path.times]
        self._points = [(float(x), float(y)) for x, y in self.path.positions]
        self.end_step = self._times[-1]  # path.end_time as a float (the path never changes)

    def tau(self, t: float) -> float:
        return (t - self.offset_s) / self.step_s

    def finished(self, t: float) -> bool:
        return self.tau(t) >= self.path.end_time - 1e-9

    @property
    def end_time_s(self) -> float:
        return self.path.end_time * self.step_s + self.offset_s

    def reference(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Plane position (2,) m and velocity (2,) m/s at sim time ``t``."""
        position, velocity = self.reference_floats(t)
        return np.array(position), np.array(velocity)

    def reference_floats(self, t: float) -> tuple[tuple[float, float], tuple[float, float]]:
        """:meth:`reference` as Python floats ((x, y), (vx, vy)): the per-tick path, without arrays."""
        return self.reference_at_tau((t - self.offset_s) / self.step_s)

    def reference_at_tau(self, tau: float) -> tuple[tuple[float, float], tuple[float, float]]:
        """:meth:`reference_floats` at path step ``tau`` (:meth:`tau` of the sim time)."""
        times = self._times
        if tau <= times[0]:
            return self._points[0], (0.0, 0.0)
        if tau >= times[-1]:
            return self._points[-1], (0.0, 0.0)
        k = bisect.bisect_right(times, tau) - 1  # times[k] <= tau < times[k + 1]
        (x0, y0), (x1, y1) = self._points[k], self._points[k + 1]
        dt = (times[k + 1] - times[k]) * self.step_s
        velocity = ((x1 - x0) / dt, (y1 - y0) / dt)
        if tau == times[k]:
            return (x0, y0), velocity
        # The arithmetic of np.interp (RobotPath.position_at), so positions equal RobotPath.position_at's exactly.
        span = times[k + 1] - times[k]
        offset = tau - times[k]
        return ((x1 - x0) / span * offset + x0, (y1 - y0) / span * offset + y0), velocity

    def remaining(self, t: float) -> np.ndarray:
        """(K, 2) the reference now and every waypoint still ahead."""
        tau = min(max(self.tau(t), self.path.start_time), self.path.end_time)
        ahead = self.path.positions[self.path.times > tau]
        return np.vstack([self.path.position_at(tau)[None], ahead])


def shifted(path: RobotPath, steps: int) -> RobotPath:
    """The same path ``steps`` later."""
    return RobotPath(path.times + int(steps), path.positions)


def lifted(points: np.ndarray, z: float = PATH_HEIGHT_M) -> np.ndarray:
    points = np.asarray(points, dtype=float)
    return np.concatenate([points, np.full(points.shape[:-1] + (1,), z)], axis=-1)


def commands_from_plane(observation: Observation, positions: np.ndarray, velocities: np.ndarray):
    """Commands for ground robots from plane references (z kept at the body)."""
    n = len(positions)
    position = np.empty((n, 3))
    position[:, :2] = positions
    position[:, 2] = observation.position[:, 2]
    velocity = np.zeros((n, 3))
    velocity[:, :2] = velocities
    return Commands(position, velocity, np.zeros((n, 3)), np.zeros(n))


LAG_HOLD_M = 0.15  # a robot's path clock pauses while its body is this far behind its reference, m
# A path clock pauses at most this long in one stretch: a body held LAG_HOLD_M off its reference that long is not
# lagging but standing where it believes itself to be elsewhere (a biased position fix, docs/faults.md), and a
# clock that waited for it would stop its team for good. The longest stretch of the built-ins without faults
# is far shorter (docs/faults.md), s.
LAG_HOLD_MAX_S = 10.0


class LagHolds:
    """Each path clock's current stretch of waiting for its lagging body (the time scaling of the meeting
    methods' paths), bounded by ``max_s``: after that the clock goes on, and waits again only once its body
    has come within half of LAG_HOLD_M of its reference. A stretch ends there too, not at LAG_HOLD_M: a fix
    that wanders about a bias near LAG_HOLD_M would otherwise start a new stretch at every crossing."""

    def __init__(self, n_clocks: int, period_s: float, max_s: float = LAG_HOLD_MAX_S):
        self.period_s = float(period_s)  # the control period: a stretch of one held tick lasts this long, s
        self.max_s = float(max_s)
        self.since = [math.nan] * n_clocks  # when the clock's current stretch began, s (NaN: not lagging)
        self.cut = [False] * n_clocks  # the clock's last stretch reached max_s and its body has not come close
        self.longest_s = 0.0  # the longest stretch waited so far, s (held ticks times the period)
        self.released = 0  # stretches cut at max_s

    def engaged(self, clock: int) -> bool:
        """Whether clock ``clock`` is in a stretch or cut loose (else a tick without lag changes nothing)."""
        return self.cut[clock] or self.since[clock] == self.since[clock]

    def wait(self, clock: int, lagging: bool, t: float, lag_m: float) -> bool:
        """Whether clock ``clock`` waits this tick (at ``t``, s) for a body that is ``lagging`` (more than
        LAG_HOLD_M behind, as the caller decides it); ``lag_m``: the body's distance from its reference, m
        (0 where its path has not started or has ended)."""
        if lag_m <= 0.5 * LAG_HOLD_M:  # close: whatever stretch there was has ended
            self.since[clock], self.cut[clock] = math.nan, False
        if self.cut[clock] or not lagging:
            return False
        since = self.since[clock]
        if since != since:  # NaN: a new stretch
            self.since[clock] = since = t
        waited = t - since + self.period_s  # this tick's wait included
        if waited > self.max_s + 1e-9:
            self.cut[clock], self.since[clock] = True, math.nan
            self.released += 1
            return False
        self.longest_s = max(self.longest_s, waited)
        return True


WALL_KEEP_M = 0.06  # separation never moves a reference closer than this to a wall, m
SEPARATION_M = 0.12  # bodies (0.072 m across) closer than this push their references apart, m
SEPARATION_GAIN = 3.0  # reference offset per metre of intrusion, -


def separation_offsets(body_xy: np.ndarray, velocity: np.ndarray | None = None,
                       distance: float = SEPARATION_M, gain: float = SEPARATION_GAIN) -> np.ndarray:
    """(N, 2) reference offsets, m, that keep ground-robot bodies apart.

    The paper's robots are points; ours are 7 cm discs that push and can even
    tip each other over. For every pair closer than ``distance`` each robot's
    reference moves by gain * (distance - d) away from the other robot; a
    robot whose planned velocity (``velocity``, (N, 2) m/s) heads into the
    other also dodges by the same amount to its right, so two robots meeting
    head on pass each other and a follower overtakes on the right. Robots on
    one path side by side drift apart sideways (to about 0.1 m). Zero when
    every pair is at least ``distance`` apart: plans are tracked unchanged.
    """
    body_xy = np.asarray(body_xy, dtype=float)
    n = len(body_xy)
    offsets = np.zeros((n, 2))
    if n < 2 or pairwise_min_distance(body_xy) >= distance:  # no pair closer: the usual tick, compiled
        return offsets
    body_xy = np.ascontiguousarray(body_xy)
    moving = velocity is not None
    velocity = np.ascontiguousarray(velocity, dtype=float) if moving else body_xy
    _separation_kernel(body_xy, velocity, moving, float(distance), float(gain), offsets)
    return offsets


@kernel
def _separation_kernel(body_xy, velocity, moving, distance, gain, offsets):
    """:func:`separation_offsets` for pairs (i, j) in row-major order, each push added to ``offsets[i]``."""
    n = body_xy.shape[0]
    for i in range(n):
        for j in range(n):
            if i == j:
                continue
            dx, dy = body_xy[i, 0] - body_xy[j, 0], body_xy[i, 1] - body_xy[j, 1]
            dist = np.sqrt(dx * dx + dy * dy)
            if not dist < distance:
                continue
            scale = max(dist, 1e-6)
            away_x, away_y = dx / scale, dy / scale
            size = gain * (distance - dist)
            push_x, push_y = size * away_x, size * away_y
            if moving:
                vx, vy = velocity[i, 0], velocity[i, 1]
                speed = np.sqrt(vx * vx + vy * vy)
                heading_x = vx / max(speed, 1e-9) if speed > 1e-9 else 0.0
                heading_y = vy / max(speed, 1e-9) if speed > 1e-9 else 0.0
                towards = min(max(-(heading_x * away_x + heading_y * away_y), 0.0), 1.0)  # 1: straight at the other
                dodge = size * towards
                push_x += dodge * heading_y  # to the right of the heading
                push_y += dodge * -heading_x
            offsets[i, 0] += push_x
            offsets[i, 1] += push_y


def separated_references(references: np.ndarray, body_xy: np.ndarray, planning: PlanningWorld,
                         velocity: np.ndarray | None = None, closest: float | None = None) -> np.ndarray:
    """References plus :func:`separation_offsets`, except pushes that would
    put a reference within ``WALL_KEEP_M`` of a wall (those are dropped).
    ``closest``: ``pairwise_min_distance(body_xy)`` when the caller has it."""
    body_xy = np.ascontiguousarray(body_xy, dtype=float)
    out = np.array(references, dtype=float, copy=True)
    n = len(body_xy)
    if closest is None:
        closest = pairwise_min_distance(body_xy)
    if n < 2 or closest >= SEPARATION_M:  # no pair closer: the usual tick, compiled
        return out
    moving = velocity is not None
    velocity = np.ascontiguousarray(velocity, dtype=float) if moving else body_xy
    boxes = planning.boxes
    _separated_kernel(body_xy, velocity, moving, SEPARATION_M, SEPARATION_GAIN, np.zeros((n, 2)), out,
                      planning.bounds, float(planning.sensor_height), WALL_KEEP_M, boxes.centers, boxes.half_sizes,
                      np.ascontiguousarray(boxes.rotations), boxes.aligned)
    return out


@kernel
def _separated_kernel(body_xy, velocity, moving, distance, gain, offsets, out, bounds, z, margin,
                      centers, half_sizes, rotations, aligned):
    """:func:`separated_references` in one pass: the pushes (``offsets``, zeroed), then each pushed
    reference kept where :func:`points_free` (bounds shrunk by ``margin``, clearance above it) allows."""
    _separation_kernel(body_xy, velocity, moving, distance, gain, offsets)
    lo_x, lo_y = bounds[0, 0] + margin, bounds[0, 1] + margin
    hi_x, hi_y = bounds[1, 0] - margin, bounds[1, 1] - margin
    for i in range(out.shape[0]):
        if offsets[i, 0] != 0.0 or offsets[i, 1] != 0.0:
            x, y = out[i, 0] + offsets[i, 0], out[i, 1] + offsets[i, 1]
            if (x >= lo_x and y >= lo_y and x <= hi_x and y <= hi_y
                    and clearance_at(x, y, z, centers, half_sizes, rotations, aligned) > margin):
                out[i, 0], out[i, 1] = x, y
