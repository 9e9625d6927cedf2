"""Typed containers passed between the loop, strategies and observers.

Pure numpy, no MuJoCo: strategies and controllers import these without
depending on the simulator. All arrays are batched over robots (N first) or
targets (M first). Units: m, s, rad; world frame, z up; quaternions w, x, y, z.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import TYPE_CHECKING, Any, Callable, Mapping

import numpy as np

from sim.geometry import Boxes

if TYPE_CHECKING:
    from sim.radio.bus import Arrivals, Delivery, Message


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
            return readonly(np.full(self.distance.shape, np.inf))
        return readonly(self.clearance_of())

    @functools.cached_property
    def edges(self) -> np.ndarray:
        """(E, 2) index pairs i < j of communicating robots (built once, on first use; read-only)."""
        i, j = np.nonzero(np.triu(self.adjacency, 1))
        edges = np.stack([i, j], axis=1)
        edges.flags.writeable = False
        return edges


class _lazy:
    """``functools.cached_property`` without its lock: computed on first read, then an instance attribute
    (several of a radio state's figures are read every tick)."""

    def __init__(self, function):
        self.function = function
        self.name = function.__name__
        self.__doc__ = function.__doc__

    def __get__(self, instance, owner=None):
        if instance is None:
            return self
        value = instance.__dict__[self.name] = self.function(instance)
        return value


@dataclass(frozen=True)
class RadioState:
    """The radio channel of every robot pair at one tick, all (N, N), symmetric, read-only.

    Figures are computed on first read (``sim.radio.link``) from per-pair
    values (pairs i < j, row-major). Under the ``ideal`` preset ``delivery``
    is the link adjacency (1 in comm range with line of sight, 0 elsewhere)
    and the power figures are NaN. The diagonal is NaN for powers, 0 for
    delivery and walls.
    """

    preset: str  # the scenario's radio.preset
    delivery_threshold: float  # a pair is in the communication graph at this delivery probability
    comm_range_m: float  # the scenario's sensing.comm_range_m (the ideal radio's disk)
    distance: np.ndarray  # centre distance, m (the links')
    # Per-pair values on first read: the channel's (rx_power_dbm, snr_db, shadowing_db, delivery; linked:
    # delivery >= delivery_threshold, in_range: distance <= comm_range_m, bool) and the walls' (count, loss_db),
    # each (P,) over the pairs (first[p], second[p]); the channel's also the (N, N) comm_adjacency.
    channel_of: Callable[[], dict[str, np.ndarray]] = field(repr=False, compare=False)
    walls_of: Callable[[], dict[str, np.ndarray]] = field(repr=False, compare=False)
    pairs: tuple[np.ndarray, np.ndarray] = field(repr=False, compare=False, default=None)

    @_lazy
    def channel_pairs(self) -> dict[str, np.ndarray]:
        """The channel's per-pair values (P,), computed once."""
        return self.channel_of()

    @_lazy
    def wall_pairs(self) -> dict[str, np.ndarray]:
        """The walls' per-pair values (P,), computed once."""
        return self.walls_of()

    def _matrix(self, values: np.ndarray, diagonal) -> np.ndarray:
        n = self.distance.shape[0]
        first, second = self.pairs
        out = np.empty((n, n), dtype=values.dtype)
        out[first, second] = values
        out[second, first] = values
        np.fill_diagonal(out, diagonal)
        return readonly(out)

    @_lazy
    def rx_power_dbm(self) -> np.ndarray:
        """Mean received power (path loss, walls, shadowing; no fading), dBm."""
        return self._matrix(self.channel_pairs["rx_power_dbm"], np.nan)

    @_lazy
    def snr_db(self) -> np.ndarray:
        """Mean SNR over the noise floor, dB (per-packet fading comes on top, in the message bus)."""
        return self._matrix(self.channel_pairs["snr_db"], np.nan)

    @_lazy
    def shadowing_db(self) -> np.ndarray:
        """This tick's log-normal shadowing loss, dB."""
        return self._matrix(self.channel_pairs["shadowing_db"], np.nan)

    @_lazy
    def delivery(self) -> np.ndarray:
        """Probability that the reference packet arrives at the mean SNR, 0..1."""
        return self._matrix(self.channel_pairs["delivery"], 0.0)

    @_lazy
    def walls(self) -> np.ndarray:
        """Obstacle boxes the segment between the pair crosses, int."""
        return self._matrix(self.wall_pairs["count"], 0)

    @_lazy
    def wall_loss_db(self) -> np.ndarray:
        """Their summed loss, dB."""
        return self._matrix(self.wall_pairs["loss_db"], 0.0)

    @_lazy
    def comm_adjacency(self) -> np.ndarray:
        """bool: the communication graph, delivery >= delivery_threshold (the diagonal as delivery's 0 there
        compares). Made with the channel's figures (a strategy reads it every tick under a real radio)."""
        return self.channel_pairs["comm_adjacency"]

    @_lazy
    def in_range(self) -> np.ndarray:
        """bool: pairs within comm_range_m, no self-loops."""
        near = self.distance <= self.comm_range_m
        np.fill_diagonal(near, False)
        return readonly(near)


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
    # Whether an observer reads the strategy's figures and drawings
    # (``Commands.scalars`` and ``Commands.decorations``) this tick. When
    # False a strategy may leave them empty; ``Commands.estimate`` is still
    # filled (the metrics read it every tick). The loop sets it from the
    # observers' ``reads_decorations`` (sim.observers).
    decorations_wanted: bool = True
    # The radio channel of every pair (sim.radio.link), computed on first read; None outside a Simulation.
    radio: RadioState | None = None
    # Per robot, the message bus's deliveries (sim.radio.bus.Delivery) that arrived since the last tick, by
    # arrival: the messages the strategy's Commands.outbox sent (its own or earlier ticks'). In a Simulation
    # N tuples; () in a hand-built observation.
    inbox: tuple[tuple[Delivery, ...], ...] = ()
    # Under a position_noise fault (sim.faults), what each robot's position fix adds to its true position,
    # (N, 3), m: the error of ``position``. A strategy that models its own relative measurements (the
    # continuous-connectivity method's virtual points) applies it to what it measures, never to correct
    # anything. None without noise.
    position_error: np.ndarray | None = None
    # The arrivals of the messages sent ``as_arrays`` (sim.radio.bus.Arrivals, per kind), which are not in
    # ``inbox``: one array per column instead of a Delivery per receiver. Empty when none arrived.
    arrivals: Mapping[str, Arrivals] = field(default_factory=lambda: NO_ARRIVALS)


NO_ARRIVALS: Mapping[str, Any] = MappingProxyType({})  # an Observation's arrivals when none came


def readonly(array: Any) -> np.ndarray:
    """``array`` as a read-only ndarray: itself when it already is one, else a
    read-only view (the owner's array stays writeable)."""
    if type(array) is not np.ndarray:
        array = np.asarray(array)
    if not array.flags.writeable:
        return array
    view = array.view()
    view.flags.writeable = False
    return view


@dataclass(frozen=True)
class TargetEstimate:
    """A method's global estimate of the moving targets at discrete step ``step``
    (what the estimation metrics compare with the truth and the viewers draw)."""

    step: int
    mean: np.ndarray  # (M, 3) estimated positions, m
    covariance: np.ndarray  # (M, 3, 3) each target's position covariance block, m^2

    def __post_init__(self):
        object.__setattr__(self, "mean", readonly(self.mean))
        object.__setattr__(self, "covariance", readonly(self.covariance))


class _PicklableMappings:
    """Pickling for a frozen dataclass with read-only mappings (a mappingproxy
    does not pickle): plain dicts on the wire, wrapped again on loading."""

    def __getstate__(self):
        return {key: dict(value) if isinstance(value, MappingProxyType) else value
                for key, value in self.__dict__.items()}

    def __setstate__(self, state):
        for key, value in state.items():
            object.__setattr__(self, key, MappingProxyType(value) if isinstance(value, dict) else value)


_EMPTY: Mapping = MappingProxyType({})
Rgba = np.ndarray  # (4,) red, green, blue, alpha in 0..1


PATH_STYLES = ("solid", "dashed", "dotted")  # Decorations.path_styles


@dataclass(frozen=True)
class Decorations(_PicklableMappings):
    """What a strategy draws in the video, the recording, the viewer, the
    tuning page and the plots; every field optional (empty: nothing drawn).

    A strategy that keeps a field's object between ticks (plans rebuilt only
    when they change) lets the recording log it only when it changes: arrays
    are stored read-only (their owner's copy stays writeable), sequences as
    tuples, and an unchanged object keeps its identity.
    """

    # (N, 4) per robot (e.g. its team's or role's colour): the video halo,
    # the quadrotors' top sphere, the recording's robot point.
    robot_colors: np.ndarray | None = None
    # Per-robot series {name: (N,) values} (NaN = undefined: a gap): plots, recording.
    robot_scalars: Mapping[str, np.ndarray] = field(default_factory=lambda: _EMPTY)
    # {name: {value: label}} for robot_scalars that are codes (roles): the plots label them.
    robot_scalar_levels: Mapping[str, Mapping[float, str]] = field(default_factory=lambda: _EMPTY)
    # (N, N) link weights in 0..1 (connectivity's W): link colours, red (0) to green (1).
    link_weights: np.ndarray | None = None
    # Polylines (points (K, 3) m, rgba): planned paths. None: no plans drawn
    # (the recording keeps the last logged); () clears them.
    paths: tuple[tuple[np.ndarray, Rgba], ...] | None = None
    # Per path, its line style (PATH_STYLES: "solid", "dashed", "dotted"), so paths of similar colours
    # (eight teams) are told apart by their line too; None: every path solid.
    path_styles: tuple[str, ...] | None = None
    meeting_points: np.ndarray | None = None  # (P, 3) m
    meeting_point_colors: np.ndarray | None = None  # (P, 4)
    markers: np.ndarray | None = None  # (K, 3) m, points of interest (the connected method's targets)
    marker_colors: np.ndarray | None = None  # (K, 4)
    overlay: str = ""  # one line burned into the video after the time and link count
    legend: tuple[tuple[str, Rgba], ...] = ()  # what the colours mean: video band, tuning page, recording
    events: tuple[str, ...] = ()  # logged once each in the recording's event log, at this tick

    def __post_init__(self):
        for name in ("robot_colors", "link_weights", "meeting_points", "meeting_point_colors", "markers",
                     "marker_colors"):
            value = getattr(self, name)
            if value is not None:
                object.__setattr__(self, name, readonly(value))
        if self.robot_scalars and not isinstance(self.robot_scalars, MappingProxyType):
            object.__setattr__(self, "robot_scalars", MappingProxyType(
                {key: readonly(values) for key, values in self.robot_scalars.items()}))
        if not isinstance(self.robot_scalar_levels, MappingProxyType):
            object.__setattr__(self, "robot_scalar_levels", MappingProxyType(dict(self.robot_scalar_levels)))
        if self.paths is not None and not _frozen_pairs(self.paths):
            object.__setattr__(self, "paths", tuple((readonly(points), readonly(rgba)) for points, rgba in self.paths))
        if not _frozen_pairs(self.legend):
            object.__setattr__(self, "legend", tuple((label, readonly(rgba)) for label, rgba in self.legend))
        if self.path_styles is not None:
            styles = tuple(self.path_styles)
            unknown = sorted(set(styles) - set(PATH_STYLES))
            if unknown:
                raise ValueError(f"Decorations.path_styles: unknown style(s) {unknown} (choose from {PATH_STYLES})")
            object.__setattr__(self, "path_styles", styles)
        if not isinstance(self.events, tuple):
            object.__setattr__(self, "events", tuple(self.events))


def _frozen_pairs(pairs: Any) -> bool:
    """Whether ``pairs`` (paths, legend) is already a tuple of tuples of read-only
    arrays (and labels): kept as it is, so its identity says it did not change."""
    return isinstance(pairs, tuple) and all(
        isinstance(pair, tuple) and all(isinstance(a, str) or (isinstance(a, np.ndarray) and not a.flags.writeable)
                                        for a in pair)
        for pair in pairs)


NO_DECORATIONS = Decorations()


@dataclass(frozen=True)
class Commands(_PicklableMappings):
    """A strategy's output: the reference ("virtual point") of every robot.

    Quadrotors track position/velocity/acceleration and yaw; ground robots
    track the horizontal reference as a single integrator. The arrays are
    read-only views (the strategy's own stay writeable), so the low-level
    control and the observers cannot change what the others read.
    """

    position: np.ndarray  # (N, 3) m
    velocity: np.ndarray  # (N, 3) m/s
    acceleration: np.ndarray  # (N, 3) m/s^2
    yaw: np.ndarray  # (N,) rad
    # The method's per-tick figures {name: value}, in the name's unit
    # (documented per method in docs/): plots, recording, progress.json,
    # tuning page; empty when ``Observation.decorations_wanted`` was False.
    scalars: Mapping[str, float] = field(default_factory=lambda: _EMPTY)
    # The method's target estimate, on every tick once it has one (None: it does not estimate).
    estimate: TargetEstimate | None = None
    # What it draws; may be empty when ``Observation.decorations_wanted`` was False.
    decorations: Decorations = NO_DECORATIONS
    # The messages the team sends this tick (sim.radio.bus.Message, each with its sender and real size, or a
    # sim.radio.bus.Broadcasts item: many robots' numbers at once): the loop hands them to the message bus at
    # the tick's time; they arrive in a later Observation.inbox.
    outbox: tuple[Message, ...] = ()

    def __post_init__(self):
        # Every tick, so the fields are set through __dict__ (a frozen dataclass's setattr is slow).
        fields = self.__dict__
        position = fields["position"] = readonly(self.position)
        velocity = fields["velocity"] = readonly(self.velocity)
        acceleration = fields["acceleration"] = readonly(self.acceleration)
        yaw = fields["yaw"] = readonly(self.yaw)
        n = len(position)
        assert position.shape == velocity.shape == acceleration.shape == (n, 3), (
            position.shape, velocity.shape, acceleration.shape)
        assert yaw.shape == (n,), yaw.shape
        if type(self.scalars) is not MappingProxyType:
            fields["scalars"] = MappingProxyType(self.scalars)
        if type(self.outbox) is not tuple:
            fields["outbox"] = tuple(self.outbox)


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
