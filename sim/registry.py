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
    # Seed 000 and its two baselines share one parameter class, so a scenario
    # runs with any of them through --set strategy.kind=...
    "intermittent": StrategySpec(
        "controllers.intermittent.params:IntermittentParams",
        "controllers.intermittent.strategy:IntermittentStrategy",
        "Khodayi-mehr et al. 2019: teams meet on a conflict-free schedule at places and times chosen by a joint-space "
        "informative RRT* (Algorithm 5)",
    ),
    "all_time": StrategySpec(
        "controllers.intermittent.params:IntermittentParams",
        "controllers.baselines.all_time:AllTimeStrategy",
        "Khodayi-mehr et al. 2019, baseline: the robots keep their connected start formation, whose centre follows "
        "informative RRT* paths",
    ),
    "random_meeting": StrategySpec(
        "controllers.intermittent.params:IntermittentParams",
        "controllers.baselines.random_meeting:RandomMeetingStrategy",
        "Khodayi-mehr et al. 2019, baseline: the same teams and schedule, geodesic paths to random meeting points",
    ),
    "connected_tracking": StrategySpec(
        "controllers.tracking.params:ConnectedTrackingParams",
        "controllers.tracking.strategy:ConnectedTrackingStrategy",
        "Nestmeyer et al.'s connected controller on Khodayi-mehr et al.'s tracking task: explorers visit viewpoints of the EKF's most "
        "uncertain targets while the team keeps lambda2 > 0; every reading fused at once",
    ),
    "connected": StrategySpec(
        "controllers.connectivity.connected_params:ConnectedParams",
        "controllers.connectivity.strategy:ConnectedStrategy",
        "Nestmeyer et al. 2017: quadrotors (or ground robots, in the sensors' plane) track virtual points driven by "
        "lambda2-gradient connectivity forces while "
        "explorers visit their targets under prime-traveler election",
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
