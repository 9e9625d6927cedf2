"""Typed containers passed between the loop, strategies and observers.

Pure numpy, no MuJoCo: strategies and controllers import these without
depending on the simulator. All arrays are batched over robots (N first) or
targets (M first). Units: m, s, rad; world frame, z up; quaternions w, x, y, z.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from sim.geometry import Boxes


@dataclass(frozen=True)
class WorldInfo:
    """Static facts a strategy may use, fixed for the run."""

    robot_names: tuple[str, ...]
    robot_kinds: tuple[str, ...]  # "quadrotor" | "ground"
    obstacles: Boxes  # static collision geometry, world frame
    bounds: np.ndarray  # (2, 3) scene min / max corner, m
    control_period_s: float
    comm_range_m: float  # robot-robot link range (with line of sight), m
    target_range_m: float  # range-sensor limit, m
    n_targets: int
    sensing_period_s: float = 1.0  # target range readings every this many s
    # The targets' motion model x(k+1) = A x(k) + B u(k) + w (Khodayi-mehr et al. 2019 eq. 11,
    # estimation.target_motion.TargetMotion, a private copy): known to the
    # estimators by Assumption II.3. Never the true states.
    target_motion: Any = None

    @property
    def n_robots(self) -> int:
        return len(self.robot_names)


@dataclass(frozen=True)
class Links:
    """Robot-robot sensing/communication state, all (N, N), symmetric."""

    distance: np.ndarray  # centre distance, m
    line_of_sight: np.ndarray  # bool: segment free of obstacles (mj_ray)
    adjacency: np.ndarray  # bool: within comm range and in line of sight, no self-loops
    # Computes :attr:`clearance` on first use (no strategy reads it every tick).
    clearance_of: Callable[[], np.ndarray] | None = field(default=None, repr=False, compare=False)

    @functools.cached_property
    def clearance(self) -> np.ndarray:
        """Segment distance to the nearest obstacle, m, for pairs in comm range (inf elsewhere)."""
        if self.clearance_of is None:
            return np.full(self.distance.shape, np.inf)
        return self.clearance_of()

    @functools.cached_property
    def edges(self) -> np.ndarray:
        """(E, 2) index pairs i < j of communicating robots (built once, on first use)."""
        i, j = np.nonzero(np.triu(self.adjacency, 1))
        return np.stack([i, j], axis=1)


@dataclass(frozen=True)
class Observation:
    """What the robots sense at one control tick."""

    time_s: float
    tick: int
    position: np.ndarray  # (N, 3) body position, m
    velocity: np.ndarray  # (N, 3) linear velocity, m/s, world frame
    quaternion: np.ndarray  # (N, 4) body orientation, w x y z
    angular_velocity: np.ndarray  # (N, 3) body-frame angular velocity, rad/s
    sensor_position: np.ndarray  # (N, 3) range-sensor site, m
    links: Links
    target_ranges: np.ndarray | None = None  # (N, M) noisy range, m; NaN = not seen; None = no reading this tick
    target_step: int | None = None  # discrete target time step k of the readings
    # Whether an observer reads the strategy's figures and decorations
    # (``Commands.info``: scalars, colours, paths, overlay, events) this tick.
    # When False a strategy may skip building them; ``info`` must still carry
    # what metrics need (``target_estimate``, ``target_estimate_step``).
    # The loop sets it from the observers' ``reads_info`` (sim.observers).
    info_wanted: bool = True


@dataclass
class Commands:
    """A strategy's output: the reference ("virtual point") of every robot.

    Quadrotors track position/velocity/acceleration and yaw; ground robots
    track the horizontal reference as a single integrator.
    """

    position: np.ndarray  # (N, 3) m
    velocity: np.ndarray  # (N, 3) m/s
    acceleration: np.ndarray  # (N, 3) m/s^2
    yaw: np.ndarray  # (N,) rad
    info: dict[str, Any] = field(default_factory=dict)  # strategy figures for observers

    def __post_init__(self):
        n = len(self.position)
        for name in ("position", "velocity", "acceleration"):
            assert getattr(self, name).shape == (n, 3), (name, getattr(self, name).shape)
        assert self.yaw.shape == (n,), self.yaw.shape


@dataclass(frozen=True)
class SceneChange:
    """A scenario moved from its own scene into another one, as
    :meth:`sim.strategy.Strategy.adapt_to_scene` sees it (a :class:`sim.free_space.FloorPlan`)."""

    scene_name: str  # the new scene's file name, for the user's messages
    obstacles: Boxes  # the new scene's static collision geometry, world frame
    bounds: np.ndarray  # (2, 3) the new scene's min / max corner, m
    old_bounds: np.ndarray  # (2, 3) the scenario's own scene's (or its starts' box without one), m
    robot_names: tuple[str, ...]  # robot order, as the run names them
    robot_kinds: tuple[str, ...]  # "quadrotor" | "ground"
    starts: np.ndarray  # (N, 3) the robots' starts as placed in the new scene, m
    n_targets: int

    @property
    def center(self) -> np.ndarray:
        """(3,) the new scene's centre, m."""
        return self.bounds.mean(axis=0)
