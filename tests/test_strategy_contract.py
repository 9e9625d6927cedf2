"""Every registered strategy kind through the contract of :mod:`sim.strategy`.

Each kind runs a few ticks of a built-in scenario (one that ships with it, or
one whose parameters it extends, with ``--set strategy.kind=KIND``) and every
hook is called with the documented types; a kind with an invariant reports a
broken one; moving its scenario into the example scene goes through its
``adapt_to_scene``; every figure its ``summary()`` returns is documented.
Real MuJoCo, short runs.
"""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest

import tether.catalog  # noqa: F401 (registers the built-in strategies and scenarios)
from sim.config import ConfigError
from sim.scenario import MODELS_DIR, builtin_scenarios, load
from sim.strategy import Status, Strategy, WrappingStrategy, strategy_class, strategy_kinds, strategy_params_class
from sim.types import Commands, Decorations, SceneChange
from tether.placement import SceneGeometry, load_in_scene
from tether.runner import build_simulation, run

KINDS = strategy_kinds()
FLAT = MODELS_DIR / "scenes" / "examples" / "flat.xml"
DOCS = Path(__file__).resolve().parent.parent / "docs"
# Each method's pages: its summary() figures are documented there or in outputs.md
# (connected_tracking's come from both methods it joins and its own page).
DOC_PAGES = {"connected": ("connected.md",), "intermittent": ("intermittent.md",),
             "all_time": ("intermittent.md",), "random_meeting": ("intermittent.md",), "waypoints": (),
             "connected_tracking": ("paradigms.md", "connected.md", "intermittent.md")}
# Fewer RRT* samples for the intermittent kinds' a priori plans; the other kinds ignore these fields.
CHEAP_PLANNING = ["strategy.n_sample=40", "strategy.n_uniform=20"]
TICKS = 3


def _loads(name: str, overrides: list[str]) -> bool:
    try:
        load(name, overrides)
    except ConfigError:
        return False
    return True


def scenario_for(kind: str) -> tuple[str, list[str]]:
    """The built-in scenario a short run of ``kind`` uses, and its overrides."""
    names = sorted(builtin_scenarios())
    own = [n for n in names if load(n).strategy.kind == kind]
    if own:
        name, overrides = own[0], []
    else:  # a kind without a scenario of its own runs the first built-in whose table it reads
        fitting = [n for n in names if _loads(n, [f"strategy.kind={kind}"])]
        assert fitting, f"{kind}: no built-in scenario runs it; ship one or accept a shipped kind's table"
        name, overrides = fitting[0], [f"strategy.kind={kind}"]
    if any(f.name == "n_sample" for f in dataclasses.fields(strategy_params_class(kind))):
        overrides += CHEAP_PLANNING
    return name, overrides


def with_broken_connectivity(commands: Commands) -> Commands:
    """The same references, reported with lambda2 = 0 (the connected controller's invariant broken)."""
    return dataclasses.replace(commands, scalars={**commands.scalars, "lambda2": 0.0})


# Kinds with an invariant: the commands of a tick that broke it, and what the reason says.
BROKEN = {
    "connected": (with_broken_connectivity, "connectivity lost"),
    "connected_tracking": (with_broken_connectivity, "connectivity lost"),
}


def has_invariant(strategy: Strategy) -> bool:
    core = strategy.inner if isinstance(strategy, WrappingStrategy) else strategy
    return type(core).violation is not Strategy.violation


@pytest.fixture(scope="module", params=KINDS)
def short_run(request):
    """(kind, scenario, simulation, commands of every tick) after a few ticks."""
    kind = request.param
    name, overrides = scenario_for(kind)
    scenario = load(name, overrides)
    assert scenario.strategy.kind == kind
    sim = build_simulation(scenario)
    commands = []
    for _ in range(TICKS):
        frame, healthy = sim.tick()
        assert healthy, (kind, sim.divergence)
        commands.append(frame.commands)
    return kind, scenario, sim, commands


def test_every_kind_is_a_strategy():
    assert {"waypoints", "intermittent", "all_time", "random_meeting", "connected", "connected_tracking"} <= set(KINDS)
    for kind in KINDS:
        cls = strategy_class(kind)
        assert isinstance(cls, type) and issubclass(cls, Strategy), kind
        assert isinstance(cls.mission_can_end, bool), kind


def test_every_hook_answers_with_its_documented_type(short_run):
    kind, scenario, sim, commands = short_run
    strategy = sim.strategy
    assert isinstance(strategy, strategy_class(kind))
    n = len(sim.world.robot_names)
    for c in commands:
        assert isinstance(c, Commands) and c.position.shape == (n, 3) and isinstance(c.decorations, Decorations)
        assert strategy.violation(c) is None
    assert isinstance(strategy.finished, bool) and not strategy.finished
    assert isinstance(strategy.progress(), str)
    summary = strategy.summary()
    assert isinstance(summary, dict) and all(isinstance(key, str) for key in summary)
    assert isinstance(strategy.update_params(scenario.strategy.params), bool)
    sim.tick()  # a tick after update_params (taken or not, the strategy goes on)


def test_every_invariant_is_checked(short_run):
    kind, _, sim, commands = short_run
    strategy = sim.strategy
    assert has_invariant(strategy) == (kind in BROKEN), f"{kind}: list its invariant in BROKEN"
    if kind in BROKEN:
        broken, reason = BROKEN[kind]
        message = strategy.violation(broken(commands[-1]))
        assert isinstance(message, str) and reason in message


def test_every_summary_key_is_documented(short_run):
    kind, _, sim, _ = short_run
    assert kind in DOC_PAGES, f"{kind}: name its docs page in DOC_PAGES"
    pages = [*DOC_PAGES[kind], "outputs.md"]
    documented = {key for page in pages for key in re.findall(r"`([A-Za-z0-9_]+)`", (DOCS / page).read_text())}
    missing = sorted(set(sim.strategy.summary()) - documented)
    assert not missing, f"{kind}: document {missing} in docs/{pages[0]}"


@pytest.mark.parametrize("kind", KINDS)
def test_scene_adaptation_goes_through_every_kind(kind, monkeypatch):
    """Moving the kind's scenario into the example scene calls its adapt_to_scene, and a
    kind with an EKF prior gets the non-informative one over the new scene."""
    cls = strategy_class(kind)
    original = cls.adapt_to_scene
    calls = []

    def recording(klass, strategy_table, change, keep):
        lines = original(strategy_table, change, keep)
        calls.append((strategy_table, change, keep, lines))
        return lines

    monkeypatch.setattr(cls, "adapt_to_scene", classmethod(recording))
    name, overrides = scenario_for(kind)
    scenario, notes = load_in_scene(name, str(FLAT), overrides)
    assert len(calls) == 1
    strategy_table, change, keep, lines = calls[0]
    assert isinstance(strategy_table, dict) and isinstance(keep, frozenset)
    assert isinstance(change, SceneChange) and change.scene_name == "flat.xml"
    assert change.n_targets == len(scenario.targets) and change.starts.shape == (len(change.robot_kinds), 3)
    assert isinstance(lines, list) and all(isinstance(line, str) and line in notes for line in lines)
    assert scenario.strategy.kind == kind
    params = scenario.strategy.params
    if hasattr(params, "prior_mean"):
        flat = SceneGeometry(FLAT)
        assert np.allclose(params.prior_mean, [flat.center] * len(scenario.targets))
        assert any(n.startswith("strategy.prior_mean:") and "first readings" in n for n in notes)
        assert params.init_from_readings
    else:
        assert not any(n.startswith("strategy.prior_mean") for n in notes)


def test_connected_tracking_stops_when_the_connected_controller_loses_connectivity(tmp_path):
    """At a 1 m range the team's graph falls apart within two seconds: the run ends
    "diverged" with the connected controller's reason (the wrapper inherits its invariant)."""
    scenario = load("intermittent-8", ["strategy.kind=connected_tracking", "sensing.comm_range_m=1.0"], seed=29,
                    duration_s=150.0)
    # With an output folder (observers draw every tick) and headless (no observer draws): the
    # invariant is checked either way.
    for out in (tmp_path / "out", None):
        result = run(scenario, out)
        assert result.status == Status.DIVERGED
        assert "connectivity lost" in result.metrics["message"]
        assert result.metrics["sim_time_s"] < 5.0
