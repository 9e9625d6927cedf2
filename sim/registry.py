"""Strategy kinds a scenario may name, loaded lazily by ``module:Class``.

Keeping the table here (not in the strategies) lets the scenario loader
validate ``strategy.kind`` and its parameters without importing every
strategy's dependencies.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass


@dataclass(frozen=True)
class StrategySpec:
    params: str  # "module:Class" of the frozen parameter dataclass
    factory: str  # "module:Class" implementing sim.types.Strategy
    summary: str


STRATEGIES: dict[str, StrategySpec] = {
    "waypoints": StrategySpec(
        "controllers.waypoints:WaypointParams",
        "controllers.waypoints:WaypointStrategy",
        "each robot follows its own closed route of waypoints on smooth minimum-jerk segments",
    ),
}


def _load(path: str):
    module, _, name = path.partition(":")
    return getattr(importlib.import_module(module), name)


def strategy_kinds() -> list[str]:
    return sorted(STRATEGIES)


def strategy_params_class(kind: str) -> type:
    return _load(STRATEGIES[kind].params)


def strategy_class(kind: str) -> type:
    return _load(STRATEGIES[kind].factory)
