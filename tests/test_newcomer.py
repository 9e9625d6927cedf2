"""A newcomer's first hour: the commands someone new to tether types, each
working or refused in one line (exit 2, no traceback), on real MuJoCo."""

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np

import pytest

from sim.scenario import builtin_scenarios


def run_cli(*args, cwd=None, timeout=300):
    return subprocess.run([sys.executable, "-m", "tether.cli", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=timeout)


def assert_works_or_one_line(result, out):
    """Exit 0 with metrics written, or exit 2 with one line naming a field and nothing written."""
    assert "Traceback" not in result.stderr, result.stderr
    if result.returncode == 2:
        lines = result.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("tether: error: "), result.stderr
        assert not out.exists()
    else:
        assert result.returncode == 0, result.stdout + result.stderr
        assert (out / "metrics.json").is_file()


TEAM_CHANGES = ["robots.0.count=3", "robots.0.starts=[[1.0, 1.0, 1.0]]", "robots.0.count=6"]


@pytest.mark.parametrize("change", TEAM_CHANGES)
def test_hover_team_size_changes_are_refused_in_one_line(tmp_path, change):
    out = tmp_path / "out"
    result = run_cli("run", "hover", "--duration", "0.2", "--set", change, "--out", str(out), "--quiet")
    assert result.returncode == 2, result.stdout + result.stderr
    assert_works_or_one_line(result, out)
    # The line says what to type.
    assert "strategy.routes" in result.stderr or "robots.0.count" in result.stderr, result.stderr


def test_hover_with_a_smaller_team_and_no_routes_runs(tmp_path):
    out = tmp_path / "out"
    result = run_cli("run", "hover", "--duration", "0.2", "--set", "robots.0.count=3", "--set", "strategy.routes=[]",
                     "--out", str(out), "--quiet")
    assert_works_or_one_line(result, out)
    assert result.returncode == 0


@pytest.mark.slow
@pytest.mark.parametrize("change", TEAM_CHANGES)
@pytest.mark.parametrize("scenario", sorted(builtin_scenarios()))
def test_team_size_changes_of_every_builtin_work_or_are_refused(tmp_path, scenario, change):
    out = tmp_path / "out"
    result = run_cli("run", scenario, "--duration", "0.1", "--set", change, "--out", str(out), "--quiet")
    assert_works_or_one_line(result, out)


def test_a_strategy_key_at_the_top_level_names_its_table():
    result = run_cli("run", "connected-office", "--set", "cruise_speed_mps=2")
    assert result.returncode == 2
    assert result.stderr.strip() == ("tether: error: cruise_speed_mps: unknown key at the top level; did you mean "
                                     "strategy.cruise_speed_mps (--set strategy.cruise_speed_mps=...)?")


def test_an_unknown_top_level_key_lists_strategy_among_the_allowed():
    result = run_cli("run", "hover", "--set", "colour=3")
    assert result.returncode == 2 and "strategy" in result.stderr and "physics" in result.stderr, result.stderr


def test_set_with_a_space_for_the_equals_sign_shows_the_one_word_form():
    result = run_cli("run", "connected-office", "--set", "strategy.cruise_speed_mps", "2")
    assert result.returncode == 2
    assert "--set strategy.cruise_speed_mps=2" in result.stderr and len(result.stderr.splitlines()) == 1


def test_sweep_given_a_scenario_file_says_how_a_sweep_file_names_it(tmp_path):
    scenario = tmp_path / "my.toml"
    init = run_cli("init", "intermittent-4")
    scenario.write_text(init.stdout)
    result = run_cli("sweep", str(scenario), "--out", str(tmp_path / "sweep"))
    assert result.returncode == 2 and len(result.stderr.splitlines()) == 1, result.stderr
    assert "is a scenario file" in result.stderr and f'scenario = "{scenario}"' in result.stderr
    assert not (tmp_path / "sweep").exists()


def test_sweep_given_a_builtin_scenario_name_says_how_a_sweep_file_names_it(tmp_path):
    result = run_cli("sweep", "intermittent-4", "--out", str(tmp_path / "sweep"))
    assert result.returncode == 2 and 'scenario = "intermittent-4"' in result.stderr, result.stderr


@pytest.mark.parametrize("command", [("sweeps",), ("scenarios",), ("run", "--help"), ("report", "--help")])
def test_cli_speaks_of_methods_and_papers_not_file_numbers(command):
    result = run_cli(*command)
    assert result.returncode == 0
    assert not re.search(r"seed[ _]?00\d", result.stdout, re.IGNORECASE), result.stdout


def test_readme_speaks_of_methods_and_papers_not_file_numbers():
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    assert not re.search(r"seed[ _]?00\d", readme, re.IGNORECASE)


def test_compile_watch_sees_a_compile_once_and_a_cached_kernel_not_at_all():
    import numba

    from sim.compiled import CompileWatch

    @numba.njit
    def twice(x):
        return 2.0 * x

    said = []
    with CompileWatch(on_first=lambda: said.append("compiling")) as watch:
        assert twice(1.5) == 3.0
        assert twice(2.5) == 5.0  # same signature: no second compile
    assert said == ["compiling"] and watch.count == 1 and watch.seconds > 0
    with CompileWatch() as again:
        twice(4.0)
    assert again.count == 0


@pytest.mark.slow
def test_the_first_run_says_it_compiles_kernels_and_how_long_it_took(tmp_path):
    import os

    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "empty-cache")}  # numba's first cache locator
    command = [sys.executable, "-m", "tether.cli", "run", "hover", "--duration", "0.1", "--out"]
    first = subprocess.run([*command, str(tmp_path / "a")], capture_output=True, text=True, env=env, timeout=300)
    assert first.returncode == 0, first.stderr
    assert "compiling kernels (once" in first.stderr
    assert re.search(r"compiled kernels in \d+ s", first.stderr), first.stderr
    second = subprocess.run([*command, str(tmp_path / "b")], capture_output=True, text=True, env=env, timeout=300)
    assert second.returncode == 0 and "compil" not in second.stderr, second.stderr


OWN_SWEEP = """
description = "my own: the waypoint demo at two speeds"
scenario = "hover"
duration_s = 0.3
seeds = 2

[grid]
"strategy.speed_mps" = [0.6, 0.3]
"sensing.comm_range_m" = [2.5, 1.0]
"""


def test_the_report_of_your_own_sweep_has_a_table_and_a_figure(tmp_path):
    import csv

    (tmp_path / "mine.toml").write_text(OWN_SWEEP)
    out = tmp_path / "runs"
    result = run_cli("sweep", str(tmp_path / "mine.toml"), "--out", str(out), "--workers", "2")
    assert result.returncode == 0, result.stderr
    assert "\r" not in result.stderr  # a log gets plain lines
    assert "mine: 8/8 trials" in result.stderr
    report = (out / "report.md").read_text()
    assert "## Every metric per grid cell" in report and "![main metrics against strategy.speed_mps](grid.png)" in report
    header = next(line for line in report.splitlines() if line.startswith("| metric |"))
    # the sweep file's order, both keys named
    assert header.index("strategy.speed_mps=0.6, sensing.comm_range_m=2.5") < header.index("strategy.speed_mps=0.3")
    rows = {line.split(" | ")[0][2:]: line for line in report.splitlines() if line.startswith("| ")}
    for metric in ("tracking_error_mean_m", "edges_mean", "sim_time_s", "control_ticks"):
        assert rows[metric].count("(n=2)") == 4, rows[metric]
    assert rows["sim_time_s"].count("0.3 ± 0 (n=2)") == 4
    assert (out / "grid.png").stat().st_size > 10_000
    with open(out / "grid.csv") as f:
        table = list(csv.DictReader(f))
    assert {(r["strategy.speed_mps"], r["sensing.comm_range_m"]) for r in table} == \
        {("0.6", "2.5"), ("0.6", "1.0"), ("0.3", "2.5"), ("0.3", "1.0")}
    assert all(r["n"] == "2" for r in table if r["metric"] == "edges_mean")
    assert rows["edges_mean"].count("4 ± 0 (n=2)") == 2 and rows["edges_mean"].count("| 0 ± 0 (n=2)") == 2


def test_report_help_documents_the_plot_flags():
    result = run_cli("report", "--help")
    assert result.returncode == 0
    for flag in ("--x KEY", "--y METRIC", "--hue KEY", "grid.png", "per grid cell"):
        assert flag in result.stdout, flag


def test_cell_statistics_by_hand():
    from tether.grid_report import cell_statistics

    rows = [{"k": "b", "seed": 0, "m": 1.0}, {"k": "b", "seed": 1, "m": 3.0}, {"k": "a", "seed": 0, "m": 5.0},
            {"k": "a", "seed": 1, "m": None}]
    cells = cell_statistics(rows, ["k"], ["m"], {"k": ["b", "a"]})
    assert cells == [(("b",), {"m": (2.0, 2.0 ** 0.5, 2)}), (("a",), {"m": (5.0, 0.0, 1)})]


def test_a_zip_group_is_named_by_its_first_key_in_the_grid_report(tmp_path):
    """The keys zipped with another move with it: the figure's legend and the table's header name
    a cell by the group's first key (the paradigms sweep's list of start positions ran off the figure)."""
    from tether.grid_report import grid_section, naming_keys

    starts = [[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], [[0.0, 0.0, 0.0], [2.0, 0.0, 0.0]]]
    manifest = {"definition": {"grid": {"strategy.kind": ["a", "b"]},
                               "zip": [{"sensing.comm_range_m": [0.5, 1.0], "robots.0.starts": starts}]}}
    keys = ["strategy.kind", "sensing.comm_range_m", "robots.0.starts"]
    assert naming_keys(keys, manifest) == {"strategy.kind", "sensing.comm_range_m"}
    assert naming_keys(keys, None) == set(keys)
    rows = [{"status": "completed", "seed": seed, "strategy.kind": kind, "sensing.comm_range_m": r,
             "robots.0.starts": json.dumps(start), "e_g_mean_m": 1.0 + seed + r}  # the results table's text
            for kind in ("a", "b") for r, start in zip((0.5, 1.0), starts) for seed in (0, 1)]
    lines, files = grid_section(rows, manifest, tmp_path)
    header = next(line for line in lines if line.startswith("| metric |"))
    assert "strategy.kind=a, sensing.comm_range_m=0.5 |" in header and "starts" not in header
    assert (tmp_path / "grid.png").is_file() and (tmp_path / "grid.csv").read_text().startswith(",".join(keys))


def test_connected_tracking_checks_its_invariant(tmp_path):
    """The issue's command: it loses lambda2 within two seconds and ends diverged, saying so."""
    out = tmp_path / "out"
    result = run_cli("run", "intermittent-8", "--seed", "29", "--duration", "150", "--set",
                     "strategy.kind=connected_tracking", "--set", "sensing.comm_range_m=1.0", "--out", str(out),
                     "--quiet")
    assert result.returncode == 1, result.stdout + result.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "diverged" and "lambda2" in metrics["message"], metrics["message"]
    assert metrics["sim_time_s"] < 150


def test_connected_tracking_refuses_starts_inside_r_c(tmp_path):
    starts = "[[4.57,3.94,0],[4.645,3.94,0],[4.81,3.94,0],[4.93,3.94,0],[4.57,4.06,0],[4.69,4.06,0],[4.81,4.06,0]," \
             "[4.93,4.06,0]]"  # ground0 and ground1 0.075 m apart: bodies clear (0.072 m), inside R_c = 0.08 m
    out = tmp_path / "out"
    result = run_cli("run", "intermittent-8", "--set", "strategy.kind=connected_tracking", "--set",
                     f"robots.0.starts={starts}", "--duration", "1", "--out", str(out))
    assert result.returncode == 2 and len(result.stderr.splitlines()) == 1, result.stderr
    assert "ground0 and ground1 start 0.07 m apart, within R_c = 0.08 m" in result.stderr
    assert not out.exists()


# A held-out scene: an ordinary 8 x 6 m flat with two interior walls (doorways at opposite ends),
# the room the newcomer tried. Written here, never shipped.
HELD_OUT_FLAT = """<mujoco model="held_out_flat">
  <custom><numeric name="tether_bounds" data="0 0 0 8 6 2.5"/></custom>
  <default><default class="obstacle"><geom type="box" group="0" contype="1" conaffinity="1"/></default></default>
  <worldbody>
    <light pos="4 3 8" dir="0 0 -1" directional="true"/>
    <geom name="floor" type="plane" size="4 3 0.05" pos="4 3 0" group="0"/>
    <geom name="wall_south" class="obstacle" size="4.1 0.05 1.25" pos="4 -0.05 1.25"/>
    <geom name="wall_north" class="obstacle" size="4.1 0.05 1.25" pos="4 6.05 1.25"/>
    <geom name="wall_west" class="obstacle" size="0.05 3 1.25" pos="-0.05 3 1.25"/>
    <geom name="wall_east" class="obstacle" size="0.05 3 1.25" pos="8.05 3 1.25"/>
    <geom name="wall_a" class="obstacle" size="0.05 2 1.25" pos="3 2 1.25"/>
    <geom name="wall_b" class="obstacle" size="0.05 2 1.25" pos="5.5 4 1.25"/>
  </worldbody>
</mujoco>
"""


@pytest.fixture
def flat(tmp_path):
    path = tmp_path / "yours.xml"
    path.write_text(HELD_OUT_FLAT)
    return path


def _placed_starts(flat, scenario, *overrides, connected=True):
    from tether.placement import SceneGeometry, starts_fit, load_in_scene

    loaded, notes = load_in_scene(scenario, str(flat), list(overrides))
    kinds = [k for k, _ in loaded.robot_starts()]
    starts = np.array([p for _, p in loaded.robot_starts()], dtype=float)
    assert starts_fit(SceneGeometry(flat), kinds, starts, loaded.sensing.comm_range_m, connected, tolerance_m=1e-3), \
        notes
    return loaded, starts, notes


@pytest.mark.parametrize("scenario", ["connected-office", "connected-lab", "intermittent-4", "intermittent-8",
                                      "hover"])
def test_placement_finds_a_start_for_every_indoor_builtin_in_a_held_out_flat(flat, scenario):
    loaded, starts, notes = _placed_starts(flat, scenario, connected=scenario != "hover")  # hover: spread out
    if scenario.startswith("connected"):  # their patterns do not fit as they are: each move is said
        assert any(note.startswith("robots:") for note in notes), notes


def test_a_grown_start_keeps_the_pattern_spacing_where_it_fits(flat):
    _, starts, notes = _placed_starts(flat, "connected-office")
    distance = np.linalg.norm(starts[:, None] - starts[None], axis=2)
    np.fill_diagonal(distance, np.inf)
    assert distance.min() >= 1.1 - 1e-9  # R'_c, the pattern's spacing
    assert any("grown over free space" in note for note in notes), notes


def test_a_team_size_does_not_turn_placement_off(flat):
    loaded, starts, notes = _placed_starts(flat, "connected-office", "robots.0.count=6")
    assert len(starts) == 6 and any(note.startswith("robots: the team's start pattern") for note in notes), notes


def test_explicit_starts_are_kept_and_said(flat):
    from tether.placement import load_in_scene

    loaded, notes = load_in_scene("connected-office", str(flat), ["robots.0.starts=[[1.0, 1.0, 1.0], [1.0, 2.0, 1.0]]",
                                                                  "robots.0.count=2"])
    assert [p for _, p in loaded.robot_starts()] == [(1.0, 1.0, 1.0), (1.0, 2.0, 1.0)]
    assert any("robots.0.starts" in note and "kept as given" in note for note in notes), notes


@pytest.mark.parametrize("scenario", ["connected-office", "connected-lab"])  # lab: fixed targets moved too
def test_the_readme_own_scene_command_runs_in_a_held_out_flat(flat, tmp_path, scenario):
    out = tmp_path / "out"
    result = run_cli("run", scenario, "--scene", str(flat), "--duration", "2", "--out", str(out), "--quiet")
    assert result.returncode == 0, result.stdout + result.stderr
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "time limit" and metrics["comm_lambda2_min"] > 0


def test_init_with_a_scene_always_writes_a_file(tmp_path):
    tiny = tmp_path / "tiny.xml"  # 2 x 2 m: no connected start for ten quadrotors 0.6 m from the walls exists
    tiny.write_text('<mujoco><custom><numeric name="tether_bounds" data="0 0 0 2 2 2.5"/></custom><worldbody>'
                    '<geom name="floor" type="plane" size="1 1 0.05" pos="1 1 0"/></worldbody></mujoco>')
    result = run_cli("init", "connected-office", "--scene", str(tiny))
    assert result.returncode == 0, result.stderr
    assert "robots: NOT placed" in result.stderr and "# " in result.stdout
    assert "NOT placed" in result.stdout and "[[robots]]" in result.stdout
    refused = run_cli("run", "connected-office", "--scene", str(tiny))
    assert refused.returncode == 2 and "tether init connected-office --scene" in refused.stderr


@pytest.mark.parametrize("scenario", ["connected-empty", "connected-town"])
def test_an_outdoor_team_that_fits_no_flat_is_refused_by_placement_in_one_line(flat, scenario, tmp_path):
    """Ten quadrotors of the outdoor preset need 0.8 m from walls (R_o = 0.75 m) and 1.75 m between
    starts (half way from R_c = 1 m to R'_c = 2.5 m): the flat holds no such connected team."""
    out = tmp_path / "out"
    result = run_cli("run", scenario, "--scene", str(flat), "--out", str(out))
    assert result.returncode == 2 and len(result.stderr.splitlines()) == 1, result.stderr
    assert result.stderr.startswith("tether: error: robots: no free place in yours.xml")
    assert not out.exists()
