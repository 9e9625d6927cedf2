"""Observers see every control tick and never change the simulation.

The loop hands each one a :class:`Frame`; metrics, the video and the Rerun
recording are all observers, so a run with or without them follows the same
trajectory.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Any

import numpy as np

from sim.compiled import kernel
from sim.types import Commands, Observation


@dataclass(frozen=True)
class Frame:
    observation: Observation
    commands: Commands
    target_positions: np.ndarray  # (M, 3) true positions, m


class Observer:
    """Sees every tick's frame and never changes the simulation; closed once at the end.

    Subclasses implement :meth:`on_tick` and :meth:`close`; the other hooks
    have defaults.
    """

    def reads_info(self, time_s: float) -> bool:
        """Whether it reads ``frame.commands.decorations`` or the strategy's
        figures on the tick that starts at ``time_s``; the loop asks the
        strategy to build them only when some observer does."""
        return True

    def on_tick(self, frame: Frame) -> None:
        """One control tick: ``frame`` is the state before the step."""

    def on_event(self, time_s: float, text: str, level: str = "INFO", tick: int | None = None) -> None:
        """Something happened that the run reports (a mission's end, a divergence, an interruption)."""

    def start_closing(self, status: str) -> None:
        """Called on every observer before the first :meth:`close`: start
        closing work that can go on while the other observers close (the
        plots' painters draw while the video is encoded)."""

    def close(self, status: str) -> None:
        """The run is over with ``status``; finish writing."""


def tracking_errors(robot_kinds: tuple[str, ...], position: np.ndarray, reference: np.ndarray) -> np.ndarray:
    """(N,) body-to-reference distance, m: 3D for quadrotors, horizontal for
    ground robots (their reference height is meaningless)."""
    position = np.ascontiguousarray(position, dtype=np.float64)
    reference = np.ascontiguousarray(reference, dtype=np.float64)
    assert position.shape == reference.shape == (len(robot_kinds), 3), (position.shape, reference.shape)
    error = np.empty(len(position))
    _tracking_errors(_ground_mask(tuple(robot_kinds)), position, reference, error)
    return error


@functools.lru_cache(maxsize=16)
def _ground_mask(robot_kinds: tuple[str, ...]) -> np.ndarray:
    return np.array([k == "ground" for k in robot_kinds], dtype=bool)


@kernel
def _tracking_errors(ground, position, reference, error):
    # The sum of squares in np.linalg.norm's order (x + y) + z; a ground robot's z term is 0.
    for i in range(position.shape[0]):
        dx, dy = position[i, 0] - reference[i, 0], position[i, 1] - reference[i, 1]
        dz = 0.0 if ground[i] else position[i, 2] - reference[i, 2]
        error[i] = np.sqrt(dx * dx + dy * dy + dz * dz)


class TrackingMetrics(Observer):
    """Body vs reference ("virtual point") error: 3D for quadrotors, horizontal
    for ground robots (their reference height is meaningless)."""

    def __init__(self, robot_kinds: tuple[str, ...]):
        self._kinds = robot_kinds
        self._sum = 0.0
        self._count = 0
        self._max = 0.0
        self.last_error = np.zeros(len(robot_kinds))

    def reads_info(self, time_s: float) -> bool:
        return False

    def on_tick(self, frame: Frame) -> None:
        error = tracking_errors(self._kinds, frame.observation.position, frame.commands.position)
        self.last_error = error
        self._sum += float(error.sum())
        self._count += len(error)
        self._max = max(self._max, float(error.max(initial=0.0)))

    def close(self, status: str) -> None:
        pass

    def summary(self) -> dict[str, Any]:
        mean = self._sum / self._count if self._count else None
        return {"tracking_error_mean_m": mean, "tracking_error_max_m": self._max if self._count else None}


class LinkMetrics(Observer):
    """Communication-graph figures over the run."""

    def __init__(self):
        self.edges_min: int | None = None
        self.edges_sum = 0
        self.ticks = 0

    def reads_info(self, time_s: float) -> bool:
        return False

    def on_tick(self, frame: Frame) -> None:
        edges = int(np.count_nonzero(frame.observation.links.adjacency)) // 2
        self.edges_min = edges if self.edges_min is None else min(self.edges_min, edges)
        self.edges_sum += edges
        self.ticks += 1

    def close(self, status: str) -> None:
        pass

    def summary(self) -> dict[str, Any]:
        return {"edges_min": self.edges_min, "edges_mean": self.edges_sum / self.ticks if self.ticks else None}
