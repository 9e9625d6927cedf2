"""Observers see every control tick and never change the simulation.

The loop hands each one a :class:`Frame`; metrics, the video and the Rerun
recording are all observers, so a run with or without them follows the same
trajectory. A frame is immutable (its arrays are read-only), so no observer
can change what another one reads, whatever their order; figures derived
from the tick (the estimation error e_g) are computed by the loop and put in
the frame before any observer sees it.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Mapping

import numpy as np

from sim.compiled import kernel, numpy_sum_where
from sim.types import Commands, Observation, TargetEstimate


@dataclass(frozen=True)
class PhysicsState:
    """MuJoCo's state at the start of a tick, enough to redraw it (mj_forward):
    read-only copies of ``MjData``'s arrays."""

    qpos: np.ndarray
    qvel: np.ndarray
    act: np.ndarray
    mocap_pos: np.ndarray
    mocap_quat: np.ndarray

    @classmethod
    def of(cls, qpos, qvel, act, mocap_pos, mocap_quat) -> "PhysicsState":
        """Read-only copies of ``MjData``'s arrays (pass views kept once: each
        attribute read of MjData builds a new array object)."""
        arrays = [a.copy() for a in (qpos, qvel, act, mocap_pos, mocap_quat)]
        for array in arrays:
            array.flags.writeable = False
        return cls(*arrays)

    def load_into(self, data) -> None:
        """Write this state into ``data`` (a renderer's own MjData); mj_forward follows."""
        data.qpos[:], data.qvel[:], data.act[:] = self.qpos, self.qvel, self.act
        data.mocap_pos[:], data.mocap_quat[:] = self.mocap_pos, self.mocap_quat


@dataclass(frozen=True)
class EstimationError:
    """The loop's derived estimation figure (Khodayi-mehr et al. 2019, Sec. IV): e_g = ||x_g - x||
    (m, over all targets stacked) at the latest reading tick whose step the
    method's estimate matched, held until the next one."""

    e_g_m: float
    step: int  # the discrete target step it was computed at
    fresh: bool  # computed at this tick (a reading tick whose step the estimate matched)


def estimation_error(estimate: TargetEstimate | None, target_step: int | None,
                     truth: np.ndarray) -> float | None:
    """e_g of ``estimate`` against the true target positions ``truth`` ((M, 3),
    m) at a reading tick (``target_step`` not None) whose step it refers to;
    None on any other tick (at a reading tick the sim time is exactly the
    step's time, so ``truth`` is x(k))."""
    if estimate is None or target_step is None or estimate.step != target_step:
        return None
    return float(np.linalg.norm(np.asarray(estimate.mean, dtype=float) - np.asarray(truth, dtype=float)))


@dataclass(frozen=True)
class Frame:
    """One control tick as the observers see it: the state before the step."""

    observation: Observation  # read-only views of what the strategy sensed
    commands: Commands  # the strategy's output (read-only arrays)
    target_positions: np.ndarray  # (M, 3) true positions, m
    state: PhysicsState | None = None  # MuJoCo's state of the tick (the video redraws it)
    estimation: EstimationError | None = None  # None until the method's first matched estimate
    # The message bus's figures of this tick's step (``radio_tick_delivery_ratio``, ``radio_tick_latency_mean_s``;
    # NaN: none this tick), from the first tick that had messages on; None before.
    radio: Mapping[str, float] | None = None
    # (N,) bool, the robots a fault has failed by this tick (the truth: the graph figures count the survivors);
    # None while none has.
    failed: np.ndarray | None = None

    @functools.cached_property
    def scalars(self) -> Mapping[str, float]:
        """The method's scalars and the loop's derived figures (``e_g_m``, the bus's), read-only."""
        if self.estimation is None and self.radio is None:
            return self.commands.scalars
        derived = dict(self.radio or {})
        if self.estimation is not None:
            derived["e_g_m"] = self.estimation.e_g_m
        return MappingProxyType({**self.commands.scalars, **derived})


class Observer:
    """Sees every tick's frame and never changes the simulation; closed once at the end.

    Subclasses implement :meth:`on_tick` and :meth:`close`; the other hooks
    have defaults.
    """

    def reads_decorations(self, time_s: float) -> bool:
        """Whether it reads ``frame.commands.decorations`` or the strategy's
        scalars on the tick that starts at ``time_s``; the loop asks the
        strategy to build them only when some observer does
        (``Observation.decorations_wanted``)."""
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

    def reads_decorations(self, time_s: float) -> bool:
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


def graph_lambda2(adjacency: np.ndarray) -> float:
    """Algebraic connectivity lambda2 of the unweighted Laplacian of ``adjacency`` ((N, N) bool,
    symmetric); 0 for fewer than two robots. The last few graphs' values are kept: a team's graph
    changes only now and then, and the sensing and communication graphs are often the same."""
    key = (adjacency.shape[0], np.packbits(adjacency).tobytes())
    value = _LAMBDA2_SEEN.get(key)
    if value is None:
        value = _remembered(key, _laplacian_lambda2(adjacency))
    return value


def pairs_graph_lambda2(n: int, pairs: tuple[np.ndarray, np.ndarray], edges: np.ndarray) -> float:
    """``graph_lambda2`` of the graph on ``n`` robots whose pair ``(pairs[0][p], pairs[1][p])`` is linked
    where ``edges[p]`` (bool, (P,)), without building the (N, N) adjacency unless the graph is new."""
    key = (n, "pairs", edges.tobytes())  # a byte per pair: one call where packing the bits takes two
    value = _LAMBDA2_SEEN.get(key)
    if value is None:
        adjacency = np.zeros((n, n), dtype=bool)
        adjacency[pairs[0], pairs[1]] = edges
        adjacency[pairs[1], pairs[0]] = edges
        value = _remembered(key, _laplacian_lambda2(adjacency))
    return value


def _laplacian_lambda2(adjacency: np.ndarray) -> float:
    n = adjacency.shape[0]
    if n < 2:
        return 0.0
    weights = adjacency.astype(float)
    np.fill_diagonal(weights, 0.0)
    laplacian = np.diag(weights.sum(axis=1)) - weights
    return max(float(np.linalg.eigvalsh(laplacian)[1]), 0.0)


def _remembered(key: tuple, value: float) -> float:
    if len(_LAMBDA2_SEEN) >= 8:
        _LAMBDA2_SEEN.pop(next(iter(_LAMBDA2_SEEN)))
    _LAMBDA2_SEEN[key] = value
    return value


_LAMBDA2_SEEN: dict[tuple, float] = {}  # by graph: (n, packed adjacency) or (n, "pairs", packed pairs)


@dataclass(frozen=True)
class LinkFigures:
    """One tick's graph figures (the metrics' per-tick values, the plots' and the recording's series)."""

    edges: int  # links of the sensing graph (comm range and line of sight)
    sensing_lambda2: float  # lambda2 of the sensing graph
    comm_lambda2: float  # lambda2 of the radio's communication graph (delivery >= threshold)
    radio_delivery_mean: float  # mean delivery probability over the pairs in comm range; NaN: none


def link_figures(observation: Observation, failed: np.ndarray | None = None) -> LinkFigures:
    """The graph figures of ``observation`` (without a radio, as in a hand-built observation: the
    communication graph is the sensing one and the delivery is not known), over the robots still
    working when ``failed`` ((N,) bool) marks some: a dead robot's silence is a fault of its own, and
    whether the survivors can still talk is the question a guarantee asks."""
    if failed is not None and failed.any():
        return _survivors_link_figures(observation, ~np.asarray(failed, dtype=bool))
    adjacency = observation.links.adjacency
    edges = int(np.count_nonzero(adjacency)) // 2
    sensing = graph_lambda2(adjacency)
    radio = observation.radio
    if radio is None:
        return LinkFigures(edges, sensing, sensing, float("nan"))
    if radio.preset == "ideal":  # the disk: the communication graph is the sensing one, delivered surely
        n = adjacency.shape[0]
        near_pairs = (int(np.count_nonzero(radio.distance <= radio.comm_range_m)) - n) // 2
        return LinkFigures(edges, sensing, sensing, edges / near_pairs if near_pairs else float("nan"))
    channel = radio.channel_pairs
    # The graph of radio.comm_adjacency, read from the pairs (this runs every tick under a real radio).
    comm = pairs_graph_lambda2(adjacency.shape[0], radio.pairs, channel["linked"])
    # ndarray.mean's own sum and division over the pairs in range, in one compiled call (this runs every tick
    # under a real radio)
    total, near = numpy_sum_where(channel["delivery"], channel["in_range"])
    delivery = total / near if near else float("nan")
    return LinkFigures(edges, sensing, comm, delivery)


def _survivors_link_figures(observation: Observation, alive: np.ndarray) -> LinkFigures:
    """``link_figures`` of the graphs restricted to the ``alive`` robots."""
    adjacency = observation.links.adjacency[np.ix_(alive, alive)]
    edges = int(np.count_nonzero(adjacency)) // 2
    sensing = graph_lambda2(adjacency)
    radio = observation.radio
    if radio is None:
        return LinkFigures(edges, sensing, sensing, float("nan"))
    distance = radio.distance[np.ix_(alive, alive)]
    n = len(distance)
    near_pairs = (int(np.count_nonzero(distance <= radio.comm_range_m)) - n) // 2
    if radio.preset == "ideal":
        return LinkFigures(edges, sensing, sensing, edges / near_pairs if near_pairs else float("nan"))
    first, second = radio.pairs
    pair_delivery = radio.channel_pairs["delivery"]
    both = alive[first] & alive[second]
    full = np.zeros((len(alive), len(alive)), dtype=bool)
    linked = pair_delivery >= radio.delivery_threshold
    full[first, second] = linked
    full[second, first] = linked
    comm = graph_lambda2(full[np.ix_(alive, alive)])
    near = both & (radio.distance[first, second] <= radio.comm_range_m)
    delivery = float(pair_delivery[near].mean()) if near.any() else float("nan")
    return LinkFigures(edges, sensing, comm, delivery)


class LinkMetrics(Observer):
    """Sensing- and communication-graph figures over the run."""

    def __init__(self):
        self.edges_min: int | None = None
        self.edges_sum = 0
        self.ticks = 0
        self._lambda2 = {"sensing": [0.0, np.inf], "comm": [0.0, np.inf]}  # sum, min
        self._delivery = [0.0, 0]  # sum, ticks with pairs in comm range

    def reads_decorations(self, time_s: float) -> bool:
        return False

    def on_tick(self, frame: Frame) -> None:
        figures = link_figures(frame.observation, frame.failed)
        edges = figures.edges
        self.edges_min = edges if self.edges_min is None else min(self.edges_min, edges)
        self.edges_sum += edges
        self.ticks += 1
        for name, value in (("sensing", figures.sensing_lambda2), ("comm", figures.comm_lambda2)):
            kept = self._lambda2[name]
            kept[0] += value
            kept[1] = min(kept[1], value)
        if not np.isnan(figures.radio_delivery_mean):
            self._delivery[0] += figures.radio_delivery_mean
            self._delivery[1] += 1

    def close(self, status: str) -> None:
        pass

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {"edges_min": self.edges_min,
                               "edges_mean": self.edges_sum / self.ticks if self.ticks else None}
        for name, (total, smallest) in self._lambda2.items():
            out[f"{name}_lambda2_mean"] = total / self.ticks if self.ticks else None
            out[f"{name}_lambda2_min"] = smallest if self.ticks else None
        total, ticks = self._delivery
        out["radio_delivery_mean"] = total / ticks if ticks else None
        return out
