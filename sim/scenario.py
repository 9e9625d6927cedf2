"""Scenario files: TOML -> a validated, frozen :class:`Scenario`.

A scenario is a built-in name (a ``NAME.toml`` in the folder the application
registers: :func:`register_scenario_folder`) or a path to a TOML file. ``--set key=value`` overrides use dotted keys; list entries are
addressed by index (``robots.0.count=6``). Checks that need the compiled
world (robots inside walls, outside the scene) happen in :mod:`sim.world`.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import math
import tomllib
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

from sim.faults import parse_faults
from sim.radio.config import RadioConfig
from sim.config import (MAX_INT, MAX_TOML_BYTES, ConfigError, build, builtin_descriptions, builtin_or_file,
                        check_nesting, read_toml_file, require, to_table)
from sim.strategy import strategy_kinds, strategy_params_class
from models import MODELS_DIR

SCENE_DIR = MODELS_DIR / "scenes"
# The folder of built-in scenarios (NAME.toml), registered by the application
# (tether.catalog), which owns them: they name its strategy kinds.
_builtin_scenario_folder: list[Path] = []


def register_scenario_folder(folder: Path) -> None:
    """Make every ``folder/NAME.toml`` a built-in scenario ``NAME``."""
    _builtin_scenario_folder[:] = [Path(folder)]


def builtin_scenario_folder() -> Path:
    """The registered folder of built-in scenarios (a folder that does not exist before one is)."""
    return _builtin_scenario_folder[0] if _builtin_scenario_folder else MODELS_DIR / "no-builtin-scenarios"

Vec3 = tuple[float, float, float]

MAX_ROBOTS = 200  # robots in one scenario: the per-tick pairwise arrays stay small
MAX_TARGETS = 200  # moving targets in one scenario
# np.random.default_rng takes seeds up to 2**64 - 1, but a sweep stores them in an int64 Parquet
# column (and every integer of a scenario is int64): one range for runs and sweeps.
MAX_SEED = MAX_INT
MAX_DURATION_S = 1e6  # simulated seconds (about 11.6 days)
MAX_SCENARIO_BYTES = MAX_TOML_BYTES


@dataclass(frozen=True)
class PhysicsConfig:
    timestep_s: float = 0.002  # MuJoCo step, s
    control_period_s: float = 0.01  # strategy + low-level control period, s

    def __post_init__(self):
        require(self.timestep_s > 0, "timestep_s", f"must be positive, got {self.timestep_s}")
        require(self.control_period_s > 0, "control_period_s", f"must be positive, got {self.control_period_s}")
        ratio = self.control_period_s / self.timestep_s
        require(
            ratio >= 1 and abs(ratio - round(ratio)) < 1e-6,
            "control_period_s",
            f"must be a whole multiple of timestep_s ({self.timestep_s}), got {self.control_period_s}",
        )

    @property
    def substeps(self) -> int:
        return int(round(self.control_period_s / self.timestep_s))


@dataclass(frozen=True)
class SensingConfig:
    target_range_m: float = 5.0  # range-sensor limit, m (the intermittent paper: 5 m)
    comm_range_m: float = 2.5  # robot-robot link range with line of sight, m
    range_noise: bool = True  # add the intermittent paper's eq. (12) noise to range readings
    period_s: float = 1.0  # target range readings every period_s, s (the intermittent paper's Delta t)

    def __post_init__(self):
        for name in ("target_range_m", "comm_range_m", "period_s"):
            value = getattr(self, name)
            require(value > 0, name, f"must be positive, got {value}")


@dataclass(frozen=True)
class RobotGroup:
    """A group of robots of one kind: explicit ``starts`` or a grid of ``count``."""

    kind: Literal["quadrotor", "ground"]  # "quadrotor" or "ground" (e-puck-sized, differential drive)
    starts: tuple[Vec3, ...] = ()  # start positions, m (z ignored for ground robots)
    count: int | None = None  # how many robots: the first `count` of starts, or with spawn_center a square grid
    spawn_center: Vec3 | None = None  # grid centre, m
    spawn_spacing_m: float = 0.8  # grid spacing, m

    def __post_init__(self):
        require(len(self.starts) <= MAX_ROBOTS, "starts", f"lists {len(self.starts)} robots, at most {MAX_ROBOTS}")
        if self.count is not None:
            require(self.count >= 1, "count", f"must be at least 1, got {self.count}")
            require(self.count <= MAX_ROBOTS, "count", f"must be at most {MAX_ROBOTS} robots, got {self.count}")
            require(self.spawn_center is not None or len(self.starts) >= self.count,
                    "count", f"is {self.count} but starts lists {len(self.starts)} position(s); list {self.count} "
                    "starts, or set spawn_center (and spawn_spacing_m) for a grid of count robots")
        else:
            require(len(self.starts) >= 1, "starts", "must list at least one start position (or give count)")
        require(self.spawn_spacing_m > 0, "spawn_spacing_m", f"must be positive, got {self.spawn_spacing_m}")

    def positions(self) -> list[Vec3]:
        if self.count is None:
            return list(self.starts)
        if self.spawn_center is None or len(self.starts) >= self.count:
            return list(self.starts[: self.count])
        side = int(-(-self.count**0.5 // 1))
        cx, cy, cz = self.spawn_center
        offset = (side - 1) / 2
        out = []
        for i in range(self.count):
            row, col = divmod(i, side)
            out.append((cx + (col - offset) * self.spawn_spacing_m, cy + (row - offset) * self.spawn_spacing_m, cz))
        return out


@dataclass(frozen=True)
class TargetConfig:
    """One moving target (Khodayi-mehr et al. 2019 eq. 11): linear back-and-forth, circular, or static."""

    path: Literal["linear", "circular", "static"]  # "linear" (back and forth), "circular" or "static"
    start: Vec3 | None = None  # linear/static: first point, m
    end: Vec3 | None = None  # linear: second point, m
    center: Vec3 | None = None  # circular: centre, m
    radius_m: float = 0.5  # circular radius, m
    speed_mps: float = 0.05  # speed along the path, m/s (sign = direction on circles)
    phase_rad: float = 0.0  # circular start angle, rad

    def __post_init__(self):
        if self.path in ("linear", "static"):
            require(self.start is not None, "start", f"is required for a {self.path} target")
        if self.path == "linear":
            require(self.end is not None, "end", "is required for a linear target")
        if self.path == "circular":
            require(self.center is not None, "center", "is required for a circular target")
            require(self.radius_m > 0, "radius_m", f"must be positive, got {self.radius_m}")


@dataclass(frozen=True)
class TargetMotionConfig:
    step_s: float = 1.0  # discrete time step of eq. (11), s
    noise_std_m: float = 0.005  # process noise std per step and axis, m

    def __post_init__(self):
        require(self.step_s > 0, "step_s", f"must be positive, got {self.step_s}")
        require(self.noise_std_m >= 0, "noise_std_m", f"must be non-negative, got {self.noise_std_m}")


@dataclass(frozen=True)
class VideoConfig:
    width: int = 960  # frame width, px (even): 16:9, the scene at the left, the legend panel at the right
    height: int = 540  # frame height, px (even)
    fps: float = 30.0  # frames per second of sim time
    # "top" (top-down), "overview" (perspective), "follow:ROBOT" (tracks one robot, e.g. follow:quad0),
    # another camera named in the scene, "free" (default view), or "auto" ("top")
    camera: str = "auto"
    shadows: bool = False  # shadows cost render time

    def __post_init__(self):
        require(16 <= self.width <= 4096, "width", f"must be in [16, 4096] px, got {self.width}")
        require(16 <= self.height <= 4096, "height", f"must be in [16, 4096] px, got {self.height}")
        # H.264 in yuv420p needs even sizes.
        require(self.width % 2 == 0, "width", f"must be even (H.264), got {self.width}")
        require(self.height % 2 == 0, "height", f"must be even (H.264), got {self.height}")
        require(self.fps > 0, "fps", f"must be positive, got {self.fps}")
        require(self.fps <= 1000, "fps", f"must be at most 1000 frames/s, got {self.fps}")


@dataclass(frozen=True)
class StrategyConfig:
    kind: str
    params: Any  # the kind's parameter dataclass


@dataclass(frozen=True)
class ScenarioBody:
    """The scenario file's top level, the strategy table aside (its type
    depends on ``strategy.kind``, so it is built through the registry)."""

    name: str  # the scenario's name (a file's own name; not written to files)
    scene: str  # built-in scene name (indoor, empty, town) or path to an MJCF file, relative to this file or the working folder
    robots: tuple[RobotGroup, ...]  # groups of robots, each of one kind, in robot order
    description: str = ""  # one line, shown by `tether scenarios`
    duration_s: float = 30.0  # simulated time, s
    seed: int = 0  # seeds the run's single np.random.Generator
    physics: PhysicsConfig = field(default_factory=PhysicsConfig)
    sensing: SensingConfig = field(default_factory=SensingConfig)
    targets: tuple[TargetConfig, ...] = ()  # moving targets, seen by the range sensors
    target_motion: TargetMotionConfig = field(default_factory=TargetMotionConfig)
    video: VideoConfig = field(default_factory=VideoConfig)
    radio: RadioConfig = field(default_factory=RadioConfig)  # the radio channel between robots (docs/radio.md)
    # faults injected into the run, each a table with a kind: robot_failure, radio_blackout, position_noise
    # (docs/faults.md)
    faults: tuple[Any, ...] = ()

    def __post_init__(self):
        require(self.duration_s > 0, "duration_s", f"must be positive, got {self.duration_s}")
        require(self.duration_s <= MAX_DURATION_S, "duration_s",
                f"must be at most {MAX_DURATION_S:g} s, got {self.duration_s:g}")
        require(0 <= self.seed <= MAX_SEED, "seed", f"must be in [0, 2**63 - 1], got {self.seed}")
        require(len(self.robots) >= 1, "robots", "must define at least one robot group")
        n_robots = sum(len(g.positions()) for g in self.robots)
        require(n_robots <= MAX_ROBOTS, "robots", f"has {n_robots} robots, at most {MAX_ROBOTS}")
        require(len(self.targets) <= MAX_TARGETS, "targets",
                f"lists {len(self.targets)} targets, at most {MAX_TARGETS}")
        object.__setattr__(self, "faults", parse_faults(self.faults, n_robots, self.duration_s))


@dataclass(frozen=True)
class Scenario(ScenarioBody):
    strategy: StrategyConfig | None = None
    source: str = ""  # the file it came from, to resolve relative scene paths

    @property
    def scene_path(self) -> Path:
        return resolve_scene(self.scene, self.source)

    def robot_starts(self) -> list[tuple[str, Vec3]]:
        """(kind, start) for every robot, in robot order."""
        return [(g.kind, p) for g in self.robots for p in g.positions()]


def resolve_scene(scene: str, source: str = "") -> Path:
    builtin = SCENE_DIR / f"{scene}.xml"
    if builtin.is_file():
        return builtin
    path = Path(scene).expanduser()
    if not path.is_absolute() and source:
        candidate = Path(source).parent / path
        if candidate.exists():
            path = candidate
    if not path.is_file():
        names = ", ".join(builtin_scenes())
        raise ConfigError("scene", f"'{scene}' is neither a built-in scene ({names}) nor an existing MJCF file")
    return path


def builtin_scenes() -> list[str]:
    return sorted(p.stem for p in SCENE_DIR.glob("*.xml"))


def builtin_scenarios() -> dict[str, str]:
    """Built-in scenario name -> one-line description."""
    return builtin_descriptions(builtin_scenario_folder())


def _parse_value(text: str, key: str) -> Any:
    try:
        return check_nesting(tomllib.loads(f"v = {text}")["v"], key)
    except tomllib.TOMLDecodeError:
        return text  # a bare word: take it as a string
    except RecursionError:
        raise ConfigError(key, "lists or tables nested too deeply") from None


APPENDABLE_LIST = "faults"  # --set faults.N.KEY=VALUE with N one past the last fault adds a fault


def apply_override(table: dict, assignment: str) -> None:
    """Apply one ``key.path=value`` override in place (``faults.N.KEY`` with N the next index starts a
    new fault table)."""
    key, sep, text = assignment.partition("=")
    key = key.strip()
    if not sep or not key:
        raise ConfigError("--set", f"expected key=value, got {assignment!r}")
    parts = key.split(".")
    node: Any = table
    if parts[0] == APPENDABLE_LIST and len(parts) > 2 and table.get(APPENDABLE_LIST) is None:
        table[APPENDABLE_LIST] = []
    for i, part in enumerate(parts[:-1]):
        where = ".".join(parts[: i + 1])
        if isinstance(node, list):
            if i == 1 and parts[0] == APPENDABLE_LIST and part.isdigit() and int(part) == len(node):
                node.append({})  # faults.N.KEY with N the next index: a new fault table
            if not part.isdigit() or int(part) >= len(node):
                raise ConfigError(where, f"no list entry {part} (has {len(node)})")
            node = node[int(part)]
        else:
            node = node.setdefault(part, {})
        if not isinstance(node, (dict, list)):
            raise ConfigError(where, "is a value, not a table")
    last = parts[-1]
    if isinstance(node, list):
        if not last.isdigit() or int(last) >= len(node):
            raise ConfigError(key, f"no list entry {last} (has {len(node)})")
        node[int(last)] = _parse_value(text.strip(), key)
    else:
        node[last] = _parse_value(text.strip(), key)


def read_table(name_or_path: str) -> tuple[dict, str]:
    """The raw TOML table of a built-in name or a file, and its source path."""
    path = builtin_or_file(name_or_path, builtin_scenario_folder(), "scenario")
    return read_toml_file(path, "scenario"), str(path)


def from_table(table: dict, source: str = "") -> Scenario:
    table = copy.deepcopy(table)
    strategy_table = table.pop("strategy", None)
    if not isinstance(strategy_table, dict) or "kind" not in strategy_table:
        raise ConfigError("strategy.kind", f"is required (one of: {', '.join(strategy_kinds())})")
    kind = strategy_table.pop("kind")
    if kind not in strategy_kinds():
        raise ConfigError("strategy.kind", f"unknown strategy {kind!r} (one of: {', '.join(strategy_kinds())})")
    params = build(strategy_params_class(kind), strategy_table, "strategy")
    table.setdefault("name", Path(source).stem if source else "scenario")
    try:
        body = build(ScenarioBody, table)
    except ConfigError as err:
        if "." in err.field or not err.problem.startswith("unknown key"):
            raise
        raise ConfigError(err.field, _unknown_top_level(err.field, strategy_params_class(kind))) from None
    fields = {k: getattr(body, k) for k in ScenarioBody.__dataclass_fields__}
    return Scenario(**fields, strategy=StrategyConfig(kind, params), source=source)


def _unknown_top_level(key: str, params_class: type) -> str:
    """The problem of an unknown top-level key: where a key of that name lives (the
    strategy's table, [physics], ...), else the keys the top level allows."""
    tables = {"strategy": params_class}
    hints = typing.get_type_hints(ScenarioBody)
    for f in dataclasses.fields(ScenarioBody):
        if dataclasses.is_dataclass(hints[f.name]):
            tables[f.name] = hints[f.name]
    homes = [f"{name}.{key}" for name, cls in tables.items() if key in {f.name for f in dataclasses.fields(cls)}]
    if homes:
        return f"unknown key at the top level; did you mean {' or '.join(homes)} (--set {homes[0]}=...)?"
    allowed = sorted({f.name for f in dataclasses.fields(ScenarioBody) if f.name != "name"} | {"strategy"})
    return f"unknown key (allowed: {', '.join(allowed)})"


def load_table(name_or_path: str, overrides: list[str] = (), seed: int | None = None,
               duration_s: float | None = None) -> tuple[dict, str]:
    """A scenario's raw table with the overrides applied, and its source path."""
    table, source = read_table(name_or_path)
    for assignment in overrides:
        apply_override(table, assignment)
    if seed is not None:
        table["seed"] = seed
    if duration_s is not None:
        table["duration_s"] = duration_s
    return table, source


def load(name_or_path: str, overrides: list[str] = (), seed: int | None = None,
         duration_s: float | None = None) -> Scenario:
    """Load, override and validate a scenario (raises ConfigError)."""
    return from_table(*load_table(name_or_path, overrides, seed, duration_s))


def to_scenario_table(scenario: Scenario) -> dict:
    """A scenario as the TOML table :func:`from_table` reads back (the name is
    left out: a saved file takes its own file name; a scene file is written as
    an absolute path so the table works from any folder)."""
    table = {k: to_table(getattr(scenario, k)) for k in ScenarioBody.__dataclass_fields__ if k != "name"}
    if not (SCENE_DIR / f"{scenario.scene}.xml").is_file():
        table["scene"] = str(scenario.scene_path.resolve())
    table["strategy"] = {"kind": scenario.strategy.kind, **to_table(scenario.strategy.params)}
    return table


def toml_value(value: Any) -> str:
    """One value (number, bool, string, list, inline table) as TOML text."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # JSON's escapes are valid TOML basic-string escapes
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{_toml_key(k)} = {toml_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"cannot write {type(value).__name__} to TOML")


def _toml_key(key: str) -> str:
    return key if key.replace("_", "").replace("-", "").isalnum() and key.isascii() else json.dumps(key)


def dumps_toml(table: dict, _prefix: str = "") -> str:
    """Write a table of plain values, sub-tables and arrays of tables as TOML
    (the subset scenario files use)."""
    def is_table_array(v):
        return isinstance(v, (list, tuple)) and len(v) > 0 and all(isinstance(x, dict) for x in v)

    lines = [f"{_toml_key(k)} = {toml_value(v)}" for k, v in table.items()
             if not isinstance(v, dict) and not is_table_array(v)]
    blocks = ["\n".join(lines)] if lines else []
    for k, v in table.items():
        name = f"{_prefix}{_toml_key(k)}"
        if isinstance(v, dict):
            blocks.append(f"[{name}]\n" + dumps_toml(v, name + ".").rstrip("\n"))
        elif is_table_array(v):
            for entry in v:
                blocks.append(f"[[{name}]]\n" + dumps_toml(entry, name + ".").rstrip("\n"))
    return "\n\n".join(b for b in blocks if b) + "\n"
