"""Parameter tables: the documentation's tables of strategy keys are the parameter classes'
own metadata, and the validation rules the classes declare (bounds, removed keys, keys shared
between strategy kinds) hold for tables, ``--set`` and objects built in code alike."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from controllers.connectivity.connected_params import PRESETS, ConnectedParams
from controllers.intermittent.params import IntermittentParams
from controllers.tracking.params import ConnectedTrackingParams
from sim.config import DOCS_BEGIN, DOCS_END, ConfigError, build, replace_generated
from sim.strategy import strategy_kinds, strategy_params_class
from tether.annotated import strategy_keys_section
from tether.cli import main
from sim.scenario import load

SCENARIO_FILES = Path(__file__).resolve().parent.parent / "docs" / "scenario-files.md"


def test_the_docs_table_of_strategy_keys_is_the_generated_one():
    text = SCENARIO_FILES.read_text()
    assert replace_generated(text, strategy_keys_section()) == text, (
        "docs/scenario-files.md is stale: python -m tether.annotated docs/scenario-files.md rewrites it")
    section = text.split(DOCS_BEGIN)[1].split(DOCS_END)[0]
    for kind in strategy_kinds():
        for f in dataclasses.fields(strategy_params_class(kind)):
            if f.init:
                assert f"| `strategy.{f.name}` |" in section, (kind, f.name)


def test_removed_keys_are_refused_naming_the_key_to_use(capsys, tmp_path):
    for scenario, assignment, instead in (("connected-office", "strategy.sensing_range_m=2.5", "sensing.comm_range_m"),
                                          ("intermittent-4", "strategy.step_s=1.0", "sensing.period_s")):
        code = main(["run", scenario, "--set", assignment, "--out", str(tmp_path / "out"), "--quiet"])
        lines = capsys.readouterr().err.strip().splitlines()
        assert code == 2 and len(lines) == 1, lines
        key = assignment.split("=")[0]
        assert f"{key}: is no longer a key; set {instead}" in lines[0], lines[0]
    assert not (tmp_path / "out").exists()


def test_connected_tracking_holds_only_its_own_keys_and_checks_the_intermittent_ones():
    own = {f.name for f in dataclasses.fields(ConnectedTrackingParams)}
    assert not own & {"teams", "n_sample", "n_uniform", "step_size_m", "lag_team", "max_replans"}
    assert not issubclass(ConnectedTrackingParams, IntermittentParams)
    params = load("intermittent-8", ["strategy.kind=connected_tracking"]).strategy.params
    assert type(params) is ConnectedTrackingParams and params.delta_m2 == 0.0144
    with pytest.raises(ConfigError) as err:  # an intermittent key is still checked by its class
        load("intermittent-8", ["strategy.kind=connected_tracking", "strategy.n_sample=0"])
    assert err.value.field == "strategy.n_sample" and "must be an integer >= 1" in err.value.problem
    with pytest.raises(ConfigError) as err:
        load("intermittent-8", ["strategy.kind=connected_tracking", "strategy.explorer=3"])
    assert err.value.field == "strategy.explorer" and "unknown key" in err.value.problem


def test_bounds_hold_for_objects_built_in_code():
    with pytest.raises(ValueError, match=r"^explorers: must be an integer >= 1, got 0"):
        ConnectedTrackingParams(explorers=0)
    with pytest.raises(ValueError, match=r"^viewpoint_radii_m: entry 1 must be positive, got -0.5"):
        ConnectedTrackingParams(viewpoint_radii_m=(0.3, -0.5))
    with pytest.raises(ValueError, match=r"^cruise_speed_mps: must be in \[0.1, 10\] m/s, got 50.0"):
        ConnectedParams(cruise_speed_mps=50.0)
    with pytest.raises(ConfigError, match=r"strategy.target_counts: entry 1 must be an integer >= 0, got -1"):
        build(ConnectedParams, {"target_counts": [3, -1]}, "strategy")


def test_each_preset_value_is_written_once():
    """A preset entry differs from the field's default (a value shared by every preset is the default),
    and the planner's margins are the link weights' obstacle clearances unless given."""
    defaults = {f.name: f.default for f in dataclasses.fields(ConnectedParams)}
    for preset, values in PRESETS.items():
        for name, value in values.items():
            assert value != defaults[name], (preset, name)
        params = ConnectedParams(preset=preset)
        assert params.path_clearance_m == params.full_weight_obstacle_clearance_m
        assert params.path_min_clearance_m == params.min_obstacle_clearance_m
    # The ground preset's values that scale with R_s are filled for the scenario's range.
    ground = ConnectedParams(preset="ground")
    assert ground.potential_gain_j is None
    assert ground.at_range(0.5).potential_gain_j == pytest.approx(0.1)
    assert ground.at_range(0.5).full_weight_range_m == pytest.approx(0.22)
