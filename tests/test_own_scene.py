"""A built-in scenario in a user's scene, end to end, for both methods.

The README's walk-through with the shipped example scene: `tether run NAME
--scene flat.xml` places starts, targets and prior in the new scene and says
so; `tether init NAME --scene flat.xml > my.toml` writes a commented file
that reloads to the same scenario and runs. Real MuJoCo, short durations.
"""

import contextlib
import io
import json
import re
import tomllib
from pathlib import Path

import numpy as np
import pytest

from tether.cli import main
from sim.geometry import point_clearance, segment_clearance
from sim.loop import end_of_run
from tether.runner import run
from controllers.waypoints import ROUTE_CLEARANCE_M
from tether.placement import START_SEPARATION_M, SceneGeometry, load_in_scene, starts_fit
from sim.scenario import MODELS_DIR, builtin_scenarios, load, to_scenario_table
from sim.targets import nominal_path_samples

FLAT = MODELS_DIR / "scenes" / "examples" / "flat.xml"
CONNECTED, INTERMITTENT, WAYPOINTS = "connected-office", "intermittent-4", "hover"


def cli(*argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(list(argv))
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def flat() -> SceneGeometry:
    return SceneGeometry(FLAT)


@pytest.mark.parametrize("name", [CONNECTED, INTERMITTENT])
def test_starts_are_placed_clear_and_connected(name, flat):
    built_in = load(name)
    # The office's quadrotor lattice stands where the flat has its dividing wall; the
    # intermittent team's 0.12 m cluster of e-pucks happens to fit beside it.
    fits_already = starts_fit(flat, [k for k, _ in built_in.robot_starts()],
                              np.array([p for _, p in built_in.robot_starts()]), built_in.sensing.comm_range_m)
    assert fits_already == (name == INTERMITTENT)
    scenario, notes = load_in_scene(name, str(FLAT))
    kinds = [k for k, _ in scenario.robot_starts()]
    starts = np.array([p for _, p in scenario.robot_starts()])
    assert starts_fit(flat, kinds, starts, scenario.sensing.comm_range_m)
    assert scenario.scene_path.resolve() == FLAT.resolve()
    moved = [n for n in notes if n.startswith("robots:")]
    assert len(moved) == (0 if fits_already else 1)
    if moved:
        # The pattern is moved, not reshaped: the method's spacing is kept.
        original = np.array([p for _, p in load(name).robot_starts()])
        assert np.allclose(np.diff(starts, axis=0), np.diff(original, axis=0), atol=2e-3)


def test_a_spread_out_waypoint_team_is_placed_robot_by_robot_with_clear_routes(flat):
    """hover's 8 robots span the office on purpose (no connected start); in the flat its dividing
    wall stands where some starts and route legs were. Each robot gets a free start and a route
    whose every leg (a closed loop through its start) keeps its clearance."""
    scenario, notes = load_in_scene(WAYPOINTS, str(FLAT))
    kinds = [k for k, _ in scenario.robot_starts()]
    starts = np.array([p for _, p in scenario.robot_starts()])
    assert starts_fit(flat, kinds, starts, scenario.sensing.comm_range_m, connected=False)
    gaps = np.linalg.norm(starts[:, None, :2] - starts[None, :, :2], axis=2) + np.eye(len(starts)) * 1e9
    assert gaps.min() >= START_SEPARATION_M - 1e-9
    assert any(n.startswith("robots: the starts") for n in notes)
    assert any(n.startswith("strategy.routes:") and "back-and-forth" in n for n in notes)
    for kind, start, route in zip(kinds, starts, scenario.strategy.params.routes):
        assert route, kind  # every robot still moves
        loop = np.array([start, *route, start], dtype=float)
        if kind == "ground":
            loop[:, 2] = flat.bounds[0, 2] + ROUTE_CLEARANCE_M[kind] + 0.01  # the floor is no obstacle
        assert segment_clearance(flat.obstacles, loop[:-1], loop[1:]).distance.min() >= ROUTE_CLEARANCE_M[kind] - 1e-9


def test_targets_that_do_not_fit_are_redrawn_in_free_space_and_said_so(flat):
    scenario, notes = load_in_scene(INTERMITTENT, str(FLAT))
    built_in = load(INTERMITTENT)
    redrawn = {int(n.split(":")[0].split(".")[1]) for n in notes if n.startswith("targets.")}
    assert redrawn  # the office's targets sit where the flat has walls
    for index, (new, old) in enumerate(zip(scenario.targets, built_in.targets)):
        samples = nominal_path_samples(new)
        assert np.all(samples >= flat.bounds[0]) and np.all(samples <= flat.bounds[1])
        assert point_clearance(flat.obstacles, samples).min() > 0.0
        assert (new == old) == (index not in redrawn)
        assert (new.path, new.speed_mps, new.radius_m) == (old.path, old.speed_mps, old.radius_m)


def test_intermittent_prior_is_non_informative_over_the_new_scene_and_printed(flat):
    scenario, notes = load_in_scene(INTERMITTENT, str(FLAT))
    params = scenario.strategy.params
    assert np.allclose(params.prior_mean, [flat.center] * len(scenario.targets))
    # 2 sigma reach from the centre to the scene's corners.
    assert 2 * np.sqrt(params.prior_variance_m2) == pytest.approx(
        np.linalg.norm(flat.bounds[1, :2] - flat.bounds[0, :2]) / 2, rel=1e-3)
    # No informed prior: each target's estimate starts from its readings (estimation.target_init).
    assert params.init_from_readings
    assert any(n.startswith("strategy.prior_mean:") and "starts from its first readings" in n for n in notes)


def test_values_set_with_set_are_kept():
    scenario, notes = load_in_scene(INTERMITTENT, str(FLAT), ["strategy.prior_mean=[[1,1,1],[2,2,1],[3,3,1],[4,4,1]]"])
    assert scenario.strategy.params.prior_mean[1] == (2.0, 2.0, 1.0)
    assert not any(n.startswith("strategy.prior_mean") for n in notes)
    assert not scenario.strategy.params.init_from_readings  # the user's prior is informed


def test_placement_is_deterministic():
    first, notes_first = load_in_scene(CONNECTED, str(FLAT), seed=5)
    second, notes_second = load_in_scene(CONNECTED, str(FLAT), seed=5)
    assert first == second and notes_first == notes_second


def test_same_scene_changes_nothing():
    scenario, notes = load_in_scene(INTERMITTENT, "indoor")
    assert notes == [] and to_scenario_table(scenario) == to_scenario_table(load(INTERMITTENT))


@pytest.mark.parametrize("name", [CONNECTED, INTERMITTENT])
def test_init_writes_every_key_commented_and_reloads_to_the_same_scenario(name, tmp_path):
    code, text, err = cli("init", name, "--scene", str(FLAT))
    assert code == 0
    path = tmp_path / "my.toml"
    path.write_text(text)
    table = tomllib.loads(text)
    assert table["scene"] == str(FLAT)
    reloaded = load(str(path))
    placed, notes = load_in_scene(name, str(FLAT))
    assert to_scenario_table(reloaded) == to_scenario_table(placed)
    # Every change is said on stderr and kept in the file's header.
    for note in notes:
        assert note in err and note in text.replace("\n#   ", " ")
    # Every key (unset ones commented out) sits under its meaning and a [unit; default; range] line.
    lines = text.splitlines()
    keys = [i for i, line in enumerate(lines) if re.match(r"(# )?\w+ = ", line)]
    assert len(keys) > 20
    for i in keys:
        assert re.fullmatch(r"# \[.*(default|required).*\]", lines[i - 1]), lines[i]
        assert lines[i - 2].startswith("# ") or lines[i].split()[0] in ("kind", "count", "spawn_center"), lines[i]
    if name == CONNECTED:
        assert ("# R'_s: range factor is 1 up to this distance (below R_s)\n"
                "# [unit m; default from the preset; 0.01 to 50]\nfull_weight_range_m = 1.1\n") in text


def test_end_of_run_words():
    from sim.strategy import Strategy

    class Mission(Strategy):
        mission_can_end = True

        def reset(self, world, initial, rng):
            pass

        def step(self, observation):
            pass

        def progress(self):
            return "7/25 targets visited"

    class Endless(Mission):
        mission_can_end = False

        def progress(self):
            return ""

    assert end_of_run(Mission(), mission_ended=True, duration_s=400, time_s=193.06) == (
        "completed", "mission completed at t = 193.1 s: 7/25 targets visited")
    assert end_of_run(Mission(), mission_ended=False, duration_s=20, time_s=20.0) == (
        "time limit", "stopped at the 20 s time limit before the mission ended: 7/25 targets visited")
    assert end_of_run(Endless(), mission_ended=False, duration_s=30, time_s=30.0) == ("completed", "ran the full 30 s")


# Fewer RRT* samples for the intermittent team's a priori plans (300 and 100 in the
# scenario), which would otherwise cost most of this test.
CHEAP_PLANNING = ("--set", "strategy.n_sample=40", "--set", "strategy.n_uniform=20")


@pytest.mark.parametrize("name, duration, extra, status, progress", [
    (CONNECTED, "1.0", (), "time limit", "/25 targets visited"),
    (INTERMITTENT, "3.0", CHEAP_PLANNING, "completed", "scheduled meetings held"),
    (WAYPOINTS, "2.0", (), "completed", "ran the full 2 s"),
])
def test_walk_through_runs_in_the_example_scene(name, duration, extra, status, progress, tmp_path):
    code, text, err = cli("run", name, "--scene", str(FLAT), "--duration", duration, "--out", str(tmp_path), "--quiet",
                          *extra)
    assert code == 0, err
    metrics = json.loads((tmp_path / "metrics.json").read_text())
    assert metrics["status"] == status and progress in metrics["message"]
    assert any(line.startswith(f"{status}: {name} ") for line in text.splitlines())  # the printed summary
    assert metrics["sim_time_s"] == pytest.approx(float(duration))


def test_the_init_file_runs(tmp_path):
    code, text, _ = cli("init", INTERMITTENT, "--scene", str(FLAT))
    path = tmp_path / "my.toml"
    path.write_text(text)
    result = run(load(str(path), ["strategy.n_sample=40", "strategy.n_uniform=20"], duration_s=2.0), tmp_path / "out")
    assert result.status == "completed"
    assert result.metrics["n_moving_targets"] == 4


@pytest.mark.parametrize("name", sorted(builtin_scenarios()))
def test_init_of_every_built_in_reloads_to_the_same_scenario(name, tmp_path):
    code, text, _ = cli("init", name)
    assert code == 0
    path = tmp_path / f"{name}.toml"
    path.write_text(text)
    assert to_scenario_table(load(str(path))) == to_scenario_table(load(name))


TINY_ROOM = """
<mujoco model="tiny">
  <custom><numeric name="tether_bounds" data="0 0 0 2 2 2"/></custom>
  <worldbody>
    <geom name="floor" type="plane" size="1 1 0.05" pos="1 1 0" group="0"/>
  </worldbody>
</mujoco>
"""


def test_a_scene_too_small_for_the_team_says_in_one_line_what_to_set(tmp_path):
    scene = tmp_path / "tiny.xml"
    scene.write_text(TINY_ROOM)
    code, text, err = cli("run", CONNECTED, "--scene", str(scene), "--out", str(tmp_path / "out"))
    assert code == 2 and text == "" and not (tmp_path / "out").exists()
    assert err.count("\n") == 1
    assert "robots: no free place in tiny.xml" in err and "set the starts" in err and "tether init" in err


def test_tune_places_the_scenario_in_the_scene_too(tmp_path):
    """`tether tune NAME --scene my.xml`: the placement's lines first, then the page, whose scenario
    (what "save as scenario TOML" writes) is the placed one."""
    import os
    import select
    import signal
    import subprocess
    import sys
    import urllib.request

    proc = subprocess.Popen([sys.executable, "-m", "tether.cli", "tune", WAYPOINTS, "--scene", str(FLAT), "--port", "0",
                             "--view-fps", "1", "--video-size", "160x120", "--save", str(tmp_path / "tuned.toml")],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env={**os.environ, "OPENBLAS_NUM_THREADS": "1"})
    try:
        printed = []
        while not any("tuning page:" in line for line in printed):
            ready, _, _ = select.select([proc.stdout], [], [], 120)
            assert ready, f"no URL printed: {printed} {proc.stderr.read() if proc.poll() is not None else ''}"
            printed.append(proc.stdout.readline())
        assert printed[0].startswith("robots: the starts") and any(p.startswith("strategy.routes:") for p in printed)
        url = re.search(r"http://127\.0\.0\.1:\d+/", printed[-1]).group(0)
        with urllib.request.urlopen(url + "scenario.toml", timeout=10) as response:
            table = tomllib.loads(response.read().decode())
        placed, _ = load_in_scene(WAYPOINTS, str(FLAT))
        assert Path(table["scene"]).resolve() == FLAT.resolve()
        assert table["robots"] == to_scenario_table(placed)["robots"]
        assert table["strategy"]["routes"] == to_scenario_table(placed)["strategy"]["routes"]
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        finally:
            if proc.poll() is None:
                proc.kill()
