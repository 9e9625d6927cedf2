"""Faults a scenario injects: robots that fail, radio blackouts, noisy relative positions.

The ``[[faults]]`` tables of a scenario (``docs/faults.md``), one per fault,
each with a ``kind``:

- ``robot_failure``: robot ``robot`` fails at ``at_s``. ``mode = "stop"``: its
  actuators are commanded to hold where it is (a quadrotor hovers in place, a
  ground robot stops); ``"drift"``: its actuators freeze at their last
  command. Either way its radio goes silent from ``at_s`` on: nothing it sends
  goes out, nothing reaches it, and every link with it is dead in the channel.
- ``radio_blackout``: every link with an end inside the ball (``center``,
  ``radius_m``) loses ``extra_loss_db`` more from ``from_s`` to ``to_s``.
- ``position_noise``: the positions the strategy reads (and the distances
  between robots it weighs) carry Gaussian noise ``sigma_m`` per axis, drawn
  every tick, plus a per-robot bias of length ``bias_m`` in a random
  direction, redrawn every ``period_s``.

The strategy is never told: the simulator applies the faults where they act
(the actuators, the channel and the message bus, the observation's positions)
and records the truth for the metrics only. This module is the configuration
and the per-tick arithmetic; ``sim.loop`` applies it. Pure numpy, no MuJoCo.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np

from sim.config import ConfigError, build, check_params, param, require

Vec3 = tuple[float, float, float]

# Under the ``ideal`` radio there is no link budget to take a partial loss from: a blackout of at least this
# much extra loss cuts every link with an end inside its region, a weaker one changes nothing. 10 dB is ten
# times less received power, several times the width of every preset's packet-error waterfall (2 to 3 dB
# from delivered to lost), so a real radio near its range would lose such a link too.
IDEAL_BLACKOUT_CUT_DB = 10.0


@dataclass(frozen=True, kw_only=True)
class RobotFailure:
    """A robot that fails at ``at_s`` and goes silent."""

    kind: Literal["robot_failure"] = "robot_failure"
    robot: int = param(unit="", min=0)  # the failing robot's index in the run's robot order (0 = first)
    at_s: float = param(unit="s", min=0.0)  # when it fails, s (within the run)
    mode: Literal["stop", "drift"] = "stop"  # "stop": hold where it is; "drift": actuators frozen at their last command

    def __post_init__(self):
        check_params(self)

    def describe(self) -> str:
        return f"robot {self.robot} failed at {self.at_s:.1f} s ({self.mode})"


@dataclass(frozen=True, kw_only=True)
class RadioBlackout:
    """A region where every link with an end inside loses ``extra_loss_db`` during [from_s, to_s)."""

    kind: Literal["radio_blackout"] = "radio_blackout"
    center: Vec3  # the region's centre, m, world frame
    radius_m: float = param(unit="m", above=0.0)  # the region's radius, m (a ball)
    extra_loss_db: float = param(unit="dB", min=0.0, max=400.0)  # added to the path loss of every link with an end inside, dB
    from_s: float = param(0.0, unit="s", min=0.0)  # the blackout starts, s
    to_s: float = param(math.inf, unit="s", min=0.0)  # and ends, s (inf: to the end of the run)

    def __post_init__(self):
        check_params(self)
        require(self.to_s > self.from_s, "to_s", f"must be after from_s ({self.from_s:g} s), got {self.to_s:g}")

    def describe(self) -> str:
        end = "the end" if math.isinf(self.to_s) else f"{self.to_s:.1f} s"
        c = ", ".join(f"{x:g}" for x in self.center)
        return (f"radio blackout of {self.extra_loss_db:g} dB within {self.radius_m:g} m of ({c}) "
                f"from {self.from_s:.1f} s to {end}")

    def active(self, time_s: float) -> bool:
        return self.from_s <= time_s < self.to_s


@dataclass(frozen=True, kw_only=True)
class PositionNoise:
    """Noise on the positions the strategy reads: white Gaussian plus a per-robot bias."""

    kind: Literal["position_noise"] = "position_noise"
    sigma_m: float = param(0.0, unit="m", min=0.0, max=100.0)  # standard deviation per axis, drawn every tick, m
    bias_m: float = param(0.0, unit="m", min=0.0, max=100.0)  # length of each robot's bias, in a random direction, m
    period_s: float = param(math.inf, unit="s", above=0.0)  # the biases are redrawn every this many s (inf: once)

    def __post_init__(self):
        check_params(self)

    def describe(self) -> str:
        every = "" if math.isinf(self.period_s) else f", redrawn every {self.period_s:g} s"
        return f"position noise sigma {self.sigma_m:g} m, bias {self.bias_m:g} m{every}"

    @property
    def acts(self) -> bool:
        return self.sigma_m > 0 or self.bias_m > 0


FAULT_KINDS: dict[str, type] = {"robot_failure": RobotFailure, "radio_blackout": RadioBlackout,
                                "position_noise": PositionNoise}
Fault = RobotFailure | RadioBlackout | PositionNoise


def parse_faults(entries: Any, n_robots: int, duration_s: float) -> tuple[Fault, ...]:
    """The ``faults`` list of a scenario (TOML tables or fault objects) as fault objects, checked against
    the run: a robot index that exists, times within the run. ConfigError names the key (``faults.0.robot``)."""
    out = []
    for i, entry in enumerate(entries):
        where = f"faults.{i}"
        if isinstance(entry, tuple(FAULT_KINDS.values())):
            fault = entry
        else:
            if not isinstance(entry, dict):
                raise ConfigError(where, f"must be a table with a kind, got {entry!r}")
            kind = entry.get("kind")
            if kind not in FAULT_KINDS:
                raise ConfigError(f"{where}.kind", f"must be one of {', '.join(FAULT_KINDS)}, got {kind!r}"
                                  if kind is not None else f"is required (one of {', '.join(FAULT_KINDS)})")
            fault = build(FAULT_KINDS[kind], entry, where)
        if isinstance(fault, RobotFailure):
            if fault.robot >= n_robots:
                raise ConfigError(f"{where}.robot", f"must be a robot index below {n_robots} (the run has "
                                                    f"{n_robots} robots), got {fault.robot}")
            if not fault.at_s < duration_s:  # at the end of the run it would never act
                raise ConfigError(f"{where}.at_s", f"must be within the run (0 to below {duration_s:g} s), "
                                                   f"got {fault.at_s:g}")
        elif isinstance(fault, RadioBlackout) and not fault.from_s < duration_s:
            raise ConfigError(f"{where}.from_s", f"must be within the run (0 to below {duration_s:g} s), "
                                                 f"got {fault.from_s:g}")
        out.append(fault)
    failed = [f.robot for f in out if isinstance(f, RobotFailure)]
    for robot in failed:
        if failed.count(robot) > 1:
            index = [i for i, f in enumerate(out) if isinstance(f, RobotFailure) and f.robot == robot][1]
            raise ConfigError(f"faults.{index}.robot", f"robot {robot} already fails in an earlier fault")
    if sum(isinstance(f, PositionNoise) for f in out) > 1:
        index = [i for i, f in enumerate(out) if isinstance(f, PositionNoise)][1]
        raise ConfigError(f"faults.{index}.kind", "at most one position_noise fault")
    return tuple(out)


def seconds(value: float) -> str:
    """A fault's time for a message: one decimal (60.0), more where it has them (0.01)."""
    return f"{value:.1f}" if round(value, 1) == value else f"{value:g}"


def position_noise_draw(rng: np.random.Generator, n: int, sigma_m: float) -> np.ndarray:
    """(n, 3) white Gaussian noise, standard deviation ``sigma_m`` per axis, m."""
    return sigma_m * rng.standard_normal((n, 3))


def bias_draw(rng: np.random.Generator, n: int, bias_m: float) -> np.ndarray:
    """(n, 3) biases of length ``bias_m`` each, in directions uniform on the sphere, m."""
    direction = rng.standard_normal((n, 3))
    norm = np.linalg.norm(direction, axis=1, keepdims=True)
    return bias_m * direction / np.where(norm > 0, norm, 1.0)


def pairs_touching(inside: np.ndarray, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """(P,) bool: pairs (first[p], second[p]) with at least one end in ``inside`` ((N,) bool)."""
    return inside[first] | inside[second]


@dataclass
class FaultState:
    """The faults of one run as they act at each tick, and the record of what was injected.

    ``failed`` is the (N,) mask of robots failed so far (the truth: the strategy never reads it).
    """

    faults: tuple[Fault, ...]
    n_robots: int
    rng: np.random.Generator | None = None  # the position noise's stream (spawned from the run's)
    ideal_radio: bool = False  # the radio is the ideal disk: a blackout below IDEAL_BLACKOUT_CUT_DB does nothing
    failed: np.ndarray = field(init=False)
    events: list[tuple[float, str]] = field(init=False, default_factory=list)  # (t, what happened), for messages

    def __post_init__(self):
        self.failed = np.zeros(self.n_robots, dtype=bool)
        self.failures = tuple(f for f in self.faults if isinstance(f, RobotFailure))
        self.blackouts = tuple(f for f in self.faults if isinstance(f, RadioBlackout))
        noise = [f for f in self.faults if isinstance(f, PositionNoise) and f.acts]
        self.noise: PositionNoise | None = noise[0] if noise else None
        self.fail_time = np.full(self.n_robots, np.inf)
        self.fail_mode = [""] * self.n_robots
        for f in self.failures:
            self.fail_time[f.robot] = f.at_s
            self.fail_mode[f.robot] = f.mode
        self._bias = np.zeros((self.n_robots, 3))
        self._bias_until = -np.inf
        self._blackout_seen = [False] * len(self.blackouts)
        self._noise_seen = False

    @property
    def any_failed(self) -> bool:
        return bool(self.failed.any())

    def advance(self, time_s: float) -> np.ndarray:
        """The robots failed at ``time_s`` (s): (N,) indices of those that fail now, first tick at or after at_s."""
        newly = np.flatnonzero(~self.failed & (self.fail_time <= time_s + 1e-9))
        for robot in newly:
            self.failed[robot] = True
            self.events.append((time_s, f"robot {robot} failed at {seconds(self.fail_time[robot])} s "
                                        f"({self.fail_mode[robot]}): it {'holds in place' if self.fail_mode[robot] == 'stop' else 'drifts on its last command'} and its radio is silent"))
        for k, blackout in enumerate(self.blackouts):
            if not self._blackout_seen[k] and blackout.active(time_s):
                self._blackout_seen[k] = True
                weak = self.ideal_radio and blackout.extra_loss_db < IDEAL_BLACKOUT_CUT_DB
                self.events.append((time_s, blackout.describe() + (
                    f" (no effect: the ideal radio cuts a link only from {IDEAL_BLACKOUT_CUT_DB:g} dB on)" if weak else "")))
        return newly

    def blackout_inside(self, time_s: float, positions: np.ndarray) -> list[tuple[np.ndarray, float]]:
        """Per blackout active at ``time_s``: ((N,) bool robots inside its region, its extra loss in dB)."""
        out = []
        for blackout in self.blackouts:
            if blackout.active(time_s):
                inside = np.linalg.norm(positions - np.asarray(blackout.center), axis=1) <= blackout.radius_m
                out.append((inside, blackout.extra_loss_db))
        return out

    def extra_loss_pairs_db(self, time_s: float, positions: np.ndarray, first: np.ndarray,
                            second: np.ndarray) -> np.ndarray | None:
        """(P,) extra path loss of each pair at ``time_s`` from the active blackouts, dB (None: none active).
        Blackouts add up where they overlap on a pair."""
        regions = self.blackout_inside(time_s, positions)
        if not regions:
            return None
        extra = np.zeros(len(first))
        for inside, loss_db in regions:
            extra += np.where(pairs_touching(inside, first, second), loss_db, 0.0)
        return extra

    def cut_adjacency(self, time_s: float, positions: np.ndarray, adjacency: np.ndarray) -> np.ndarray:
        """The ideal radio's disk ``adjacency`` ((N, N) bool) with the failed robots' links and the links
        touching a blackout of at least IDEAL_BLACKOUT_CUT_DB cut (itself when nothing is cut)."""
        dead = self.failed.copy()
        for inside, loss_db in self.blackout_inside(time_s, positions):
            if loss_db >= IDEAL_BLACKOUT_CUT_DB:
                dead |= inside
        if not dead.any():
            return adjacency
        out = np.array(adjacency, dtype=bool)
        out[dead, :] = False
        out[:, dead] = False
        return out

    def noisy_positions(self, time_s: float, positions: np.ndarray) -> np.ndarray:
        """``positions`` ((N, 3), m) as the strategy reads them: plus this tick's noise and the robots' biases."""
        noise = self.noise
        if not self._noise_seen:
            self._noise_seen = True
            self.events.append((time_s, noise.describe()))
        if time_s + 1e-9 >= self._bias_until:
            if noise.bias_m > 0:
                self._bias = bias_draw(self.rng, self.n_robots, noise.bias_m)
            self._bias_until = (time_s + noise.period_s) if math.isfinite(noise.period_s) else math.inf
        out = positions + self._bias
        if noise.sigma_m > 0:
            out = out + position_noise_draw(self.rng, self.n_robots, noise.sigma_m)
        return out

    def summary(self) -> list[dict]:
        """metrics.json's ``faults``: each injected fault's table, with what the run saw of it."""
        out = []
        for fault in self.faults:
            entry = {f: getattr(fault, f) for f in fault.__dataclass_fields__}
            entry = {k: (list(v) if isinstance(v, tuple) else (None if isinstance(v, float) and math.isinf(v) else v))
                     for k, v in entry.items()}
            if isinstance(fault, RobotFailure):
                entry["happened"] = bool(self.failed[fault.robot])
            elif isinstance(fault, RadioBlackout):
                entry["happened"] = self._blackout_seen[self.blackouts.index(fault)]
            else:
                entry["happened"] = fault.acts
            out.append(entry)
        return out

    def message(self) -> str:
        """What the faults did, for the run's message ("" when nothing happened)."""
        return "; ".join(text for _, text in self.events)
