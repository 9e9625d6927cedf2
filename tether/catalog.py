"""The built-ins, registered with the layers below: strategy kinds and scenarios.

Importing :mod:`tether` imports this module, so ``sim.scenario.load("hover")``
and ``strategy.kind = "connected"`` work in any program that imports tether.
"""

from __future__ import annotations

from pathlib import Path

from sim.scenario import register_scenario_folder
from tether.strategies import register_builtin_strategies

SCENARIO_DIR = Path(__file__).resolve().parent / "scenarios"

register_builtin_strategies()
register_scenario_folder(SCENARIO_DIR)
