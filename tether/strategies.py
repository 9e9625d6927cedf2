"""The built-in strategy kinds, registered with :mod:`sim.strategy` by import path.

The table names each kind's parameter dataclass and :class:`sim.strategy.Strategy`
class as ``module:Class``, loaded on first use, so the scenario loader can
validate ``strategy.kind`` without importing every method's dependencies.
"""

from __future__ import annotations

from sim.strategy import StrategyKind, register_strategy

BUILTIN_STRATEGIES: dict[str, StrategyKind] = {
    "waypoints": StrategyKind(
        "controllers.waypoints:WaypointParams",
        "controllers.waypoints:WaypointStrategy",
        "each robot follows its own closed route of waypoints on smooth minimum-jerk segments",
    ),
    # Khodayi-mehr et al. 2019 and its two baselines share one parameter class, so a scenario
    # runs with any of them through --set strategy.kind=...
    "intermittent": StrategyKind(
        "controllers.intermittent.params:IntermittentParams",
        "controllers.intermittent.strategy:IntermittentStrategy",
        "Khodayi-mehr et al. 2019: teams meet on a conflict-free schedule at places and times chosen by a joint-space "
        "informative RRT* (Algorithm 5)",
    ),
    "all_time": StrategyKind(
        "controllers.intermittent.params:IntermittentParams",
        "controllers.baselines.all_time:AllTimeStrategy",
        "Khodayi-mehr et al. 2019, baseline: the robots keep their connected start formation, whose centre follows "
        "informative RRT* paths",
    ),
    "random_meeting": StrategyKind(
        "controllers.intermittent.params:IntermittentParams",
        "controllers.baselines.random_meeting:RandomMeetingStrategy",
        "Khodayi-mehr et al. 2019, baseline: the same teams and schedule, geodesic paths to random meeting points",
    ),
    "connected_tracking": StrategyKind(
        "controllers.tracking.params:ConnectedTrackingParams",
        "controllers.tracking.strategy:ConnectedTrackingStrategy",
        "Nestmeyer et al.'s connected controller on Khodayi-mehr et al.'s tracking task: explorers visit viewpoints of the EKF's most "
        "uncertain targets while the team keeps lambda2 > 0; every reading fused at once",
    ),
    "connected": StrategyKind(
        "controllers.connectivity.connected_params:ConnectedParams",
        "controllers.connectivity.strategy:ConnectedStrategy",
        "Nestmeyer et al. 2017: quadrotors (or ground robots, in the sensors' plane) track virtual points driven by "
        "lambda2-gradient connectivity forces while "
        "explorers visit their targets under prime-traveler election",
    ),
}



def register_builtin_strategies() -> None:
    for kind, spec in BUILTIN_STRATEGIES.items():
        register_strategy(kind, spec)
