"""The strategy contract, the run's status vocabulary, and the table of strategy kinds.

A strategy is a method that drives the robots: the loop hands it an
:class:`~sim.types.Observation` each control tick and applies the
:class:`~sim.types.Commands` it returns; it never knows which method runs.
Every hook the loop, the progress line, the tuning page, the viewer and the
sweeps call is declared here with its default, so a method (or a wrapper of
one) overrides what it needs and inherits the rest.

``sim`` never imports a method: the application registers its kinds
(:func:`register_strategy`) with import paths, loaded on first use, and the
scenario loader validates ``strategy.kind`` and its parameters through this
table.
"""

from __future__ import annotations

import abc
import enum
import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

if TYPE_CHECKING:
    from sim.types import Commands, Observation, SceneChange, WorldInfo


class Status(str, enum.Enum):
    """How a run stands or ended, one vocabulary for run, tune, view and sweeps
    (``metrics.json``'s and a sweep row's ``status``, the tuning page's state)."""

    RUNNING = "running"  # a live run or session, ticking (progress.json, the tuning page)
    PAUSED = "paused"  # a live session its user paused (tuning page, viewer)
    STOPPED = "stopped"  # a live session its user ended before the run did (viewer window closed, server stopped)
    COMPLETED = "completed"  # the mission ended, or a method without an end ran its full duration
    TIME_LIMIT = "time limit"  # the duration ran out before the mission ended
    DIVERGED = "diverged"  # physics, a robot out of the scene or tipped over, or a broken invariant
    INTERRUPTED = "interrupted"  # SIGINT / SIGTERM: stopped at the next tick
    FAILED = "failed"  # an error inside the run (a strategy or observer raised, a child died): files closed

    @property
    def finished(self) -> bool:
        """A result: the run went to its end (its mission's, or its duration's)."""
        return self in (Status.COMPLETED, Status.TIME_LIMIT)

    def __str__(self) -> str:
        return self.value


class Strategy(abc.ABC):
    """What the loop needs from a method.

    Subclasses implement :meth:`reset` and :meth:`step`; every other hook has
    a default that means "this method has nothing to say here". A method
    talks between robots through the message bus: it sends with
    ``Commands.outbox`` and receives ``Observation.inbox`` (see :meth:`step`).
    """

    #: True for a mission that can end (every target visited): once
    #: :attr:`finished` reads True the run stops "completed"; a duration that
    #: runs out first ends it "time limit". False: the method has done its job
    #: when it ran the full duration (waypoints, tracking over [0, t_end]).
    mission_can_end: ClassVar[bool] = False

    @abc.abstractmethod
    def reset(self, world: WorldInfo, initial: Observation, rng: np.random.Generator) -> None:
        """Prepare for a run starting at ``initial``; keep ``rng`` for all randomness."""

    @abc.abstractmethod
    def step(self, observation: Observation) -> Commands:
        """References for every robot for the next control period.

        ``Commands.decorations`` may be left empty when
        ``observation.decorations_wanted`` is False (no observer draws this tick);
        ``Commands.estimate`` must always be filled by a method that estimates.

        Messages go through the message bus (``sim.radio.bus``, docs/radio.md):
        ``Commands.outbox`` holds the messages the team sends this tick (each
        ``Message`` names its sender and receivers and carries its real size);
        the loop sends them at ``observation.time_s`` and steps the bus over the
        control period with this tick's radio. ``observation.inbox[i]`` holds
        the ``Delivery``s that reached robot ``i`` since the last tick, in order
        of arrival (under ``ideal``: last tick's messages to robots within the
        disk, latency 0). Both are read-only, like the rest of the observation.
        """

    @property
    def finished(self) -> bool:
        """Whether the mission is over (read after each tick; see :attr:`mission_can_end`)."""
        return False

    def progress(self) -> str:
        """How far the mission got, for the status message ("7/25 targets visited"); "" for nothing."""
        return ""

    def summary(self) -> dict[str, Any]:
        """The method's own figures, merged into metrics.json (documented per method in docs/)."""
        return {}

    def violation(self, commands: Commands) -> str | None:
        """The method's invariant after each tick: None when kept, else the reason
        (the run stops "diverged" with it and the tuning page pauses)."""
        return None

    def update_params(self, params: Any) -> bool:
        """Take new parameters (same dataclass, validated) from the next tick on.

        True: taken. False: the loop rebuilds the strategy with them and resets
        it at the current state. May raise ValueError("field: problem") to
        refuse a change that would break the invariant at the current state.
        """
        return False

    @classmethod
    def start_clearance_m(cls, strategy_table: dict[str, Any], robot_kind: str) -> float:
        """The clearance from obstacles this method needs of a ``robot_kind`` robot's start
        and of the line of sight between starts, m, given its raw ``[strategy]`` table (read
        when placing a team in another scene: placement keeps the larger of this and its
        own). Default 0: nothing beyond placement's own."""
        return 0.0

    @classmethod
    def start_separation_m(cls, strategy_table: dict[str, Any]) -> float:
        """The least distance between two starts this method accepts, m, given its raw
        ``[strategy]`` table (placement grows a team no closer). Default 0: any."""
        return 0.0

    @classmethod
    def adapt_to_scene(cls, strategy_table: dict[str, Any], change: SceneChange, keep: frozenset[str]) -> list[str]:
        """Adapt the raw ``[strategy]`` table of a scenario moved into another
        scene (``change`` describes both floor plans and the robots' starts),
        in place; keys in ``keep`` (set by the user, e.g. ``strategy.routes``)
        stay. Returns one line per change, for the user. Default: nothing to
        adapt."""
        return []


class WrappingStrategy(Strategy):
    """A strategy built around another one (``self.inner``, set in :meth:`reset`)
    that changes part of it: every hook it does not override is the inner
    strategy's, so a wrapper cannot forget the inner method's invariant."""

    inner: Strategy

    @property
    def finished(self) -> bool:
        return self.inner.finished

    def progress(self) -> str:
        return self.inner.progress()

    def summary(self) -> dict[str, Any]:
        return self.inner.summary()

    def violation(self, commands: Commands) -> str | None:
        return self.inner.violation(commands)


@dataclass(frozen=True)
class StrategyKind:
    """One registered ``strategy.kind``: its parameter dataclass and its
    :class:`Strategy` class, as ``"module:Name"`` (loaded on first use) or the objects."""

    params: str | type
    factory: str | type
    summary: str  # one line, for `tether scenarios`, `tether init` and the docs

    def params_class(self) -> type:
        return _load(self.params)

    def strategy_class(self) -> type[Strategy]:
        return _load(self.factory)


def _load(path: str | type) -> Any:
    if not isinstance(path, str):
        return path
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


_KINDS: dict[str, StrategyKind] = {}


def register_strategy(kind: str, spec: StrategyKind) -> None:
    """Make ``kind`` a valid ``strategy.kind`` (a later registration replaces an earlier one)."""
    _KINDS[kind] = spec


def strategy_kinds() -> list[str]:
    return sorted(_KINDS)


def strategy_kind(kind: str) -> StrategyKind:
    """The registered kind (KeyError for an unknown one: the scenario loader checks first)."""
    return _KINDS[kind]


def strategy_params_class(kind: str) -> type:
    return _KINDS[kind].params_class()


def strategy_class(kind: str) -> type[Strategy]:
    return _KINDS[kind].strategy_class()


def build_strategy(kind: str, params: Any) -> Strategy:
    """A fresh strategy of ``kind`` with ``params`` (not yet reset)."""
    return strategy_class(kind)(params)
