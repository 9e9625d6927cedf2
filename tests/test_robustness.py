"""Nothing crashes, nothing is lost: the bad-input catalogue.

Each case runs ``tether run`` in-process against an output folder that holds
an earlier run's files, and asserts: exit code 2, one line on stderr naming
the field, no traceback, the folder untouched and nothing written beside it.
A hypothesis property test mutates a valid scenario file (types, signs,
NaN/inf, missing and extra keys, huge sizes) and checks that a run always
exits 0, 1 or 2 without a traceback and never leaves a half-written folder.
"""

from __future__ import annotations

import copy
import json
import math
import os
import signal
import subprocess
import sys
import time
import textwrap
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tether.cli import main
from sim.scenario import dumps_toml
from tests.helpers import WALL_SCENE, write_scene, write_scenario

TINY = """
name = "tiny"
scene = "scene.xml"
duration_s = 0.1
seed = 3

[strategy]
kind = "waypoints"
speed_mps = 0.5

[[robots]]
kind = "quadrotor"
starts = [[2.0, 2.0, 1.0]]

[[robots]]
kind = "ground"
starts = [[3.0, 2.0, 0.0]]

[[targets]]
path = "circular"
center = [2.0, 7.0, 1.0]
radius_m = 0.5
speed_mps = 0.05
"""

NO_FLOOR_SCENE = """
<mujoco model="no_floor">
  <custom><numeric name="tether_bounds" data="0 0 0 10 10 5"/></custom>
  <worldbody>
    <geom name="wall" type="box" size="0.1 3 2" pos="5 5 2" group="0"/>
  </worldbody>
</mujoco>
"""

BROKEN_SCENE = """
<mujoco model="broken">
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.05"
  </worldbody>
</mujoco>
"""


def tiny(folder: Path, replace: tuple[str, str] | None = None, extra: str = "", name: str = "tiny.toml") -> Path:
    """The tiny scenario (its scene beside it), with one text replacement and extra lines."""
    write_scene(folder)
    body = textwrap.dedent(TINY)
    if replace is not None:
        assert replace[0] in body, replace[0]
        body = body.replace(*replace)
    return write_scenario(folder, body + textwrap.dedent(extra), name)


def earlier_results(out: Path) -> dict[str, bytes]:
    """An output folder as an earlier run left it; returns its snapshot."""
    (out / "plots").mkdir(parents=True)
    (out / "metrics.json").write_text('{"scenario": "tiny", "status": "completed", "earlier": true}\n')
    (out / "video.mp4").write_bytes(b"earlier video")
    (out / "run.rrd").write_bytes(b"earlier recording")
    (out / "plots" / "timeseries.png").write_bytes(b"earlier plot")
    return snapshot(out)


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def run_cli(argv: list[str], capsys) -> tuple[int, list[str], str]:
    code = main(argv)
    captured = capsys.readouterr()
    return code, captured.err.strip().splitlines(), captured.out


def assert_refused(code: int, err: list[str], field: str) -> None:
    text = "\n".join(err)
    assert code == 2, text
    assert len(err) == 1, text
    assert err[0].startswith("tether: error: "), text
    assert "Traceback" not in text
    assert field in err[0], (field, err[0])
    assert "[0]" not in err[0] and "[1]" not in err[0], err[0]  # one path syntax: robots.0.count


def _binary(folder: Path) -> Path:
    path = folder / "binary.toml"
    path.write_bytes(bytes(range(256)) * 4)
    return path


# (id, argv builder(folder, out) -> argv, field the message names)
CASES = [
    ("duration-inf", lambda f, o: [str(tiny(f)), "--duration", "inf"], "--duration"),
    ("duration-nan", lambda f, o: [str(tiny(f)), "--duration", "nan"], "--duration"),
    ("duration-negative", lambda f, o: [str(tiny(f)), "--duration", "-1"], "--duration"),
    ("duration-zero", lambda f, o: [str(tiny(f)), "--duration", "0"], "--duration"),
    ("duration-below-a-tick", lambda f, o: [str(tiny(f)), "--duration", "0.001"], "duration_s"),
    ("duration-huge", lambda f, o: [str(tiny(f)), "--duration", "1e300"], "duration_s"),
    ("duration-not-a-number", lambda f, o: [str(tiny(f)), "--duration", "long"], "--duration"),
    ("file-duration-inf", lambda f, o: [str(tiny(f, ("duration_s = 0.1", "duration_s = inf")))], "duration_s"),
    ("file-duration-nan", lambda f, o: [str(tiny(f, ("duration_s = 0.1", "duration_s = nan")))], "duration_s"),
    ("file-duration-overflow", lambda f, o: [str(tiny(f, ("duration_s = 0.1", "duration_s = 1e400")))],
     "duration_s"),
    ("file-duration-string", lambda f, o: [str(tiny(f, ("duration_s = 0.1", 'duration_s = "long"')))],
     "duration_s"),
    ("seed-negative", lambda f, o: [str(tiny(f)), "--seed", "-1"], "seed"),
    ("seed-too-large", lambda f, o: [str(tiny(f)), "--seed", str(2**64)], "seed"),
    ("seed-not-an-integer", lambda f, o: [str(tiny(f)), "--seed", "1.5"], "--seed"),
    ("file-seed-negative", lambda f, o: [str(tiny(f, ("seed = 3", "seed = -1")))], "seed"),
    ("file-seed-huge", lambda f, o: [str(tiny(f, ("seed = 3", f"seed = {10**30}")))], "seed"),
    ("file-binary", lambda f, o: [str(_binary(f))], "scenario"),
    ("file-missing", lambda f, o: [str(f / "nowhere.toml")], "scenario"),
    ("file-is-a-folder", lambda f, o: [str(f)], "scenario"),
    ("file-not-toml", lambda f, o: [str(write_scenario(f, "this is = = not toml", "bad.toml"))], "scenario"),
    ("start-nan", lambda f, o: [str(tiny(f, ("[[2.0, 2.0, 1.0]]", "[[nan, 2.0, 1.0]]")))], "robots.0.starts.0.0"),
    ("start-inf", lambda f, o: [str(tiny(f, ("[[2.0, 2.0, 1.0]]", "[[2.0, inf, 1.0]]")))], "robots.0.starts.0.1"),
    ("start-short", lambda f, o: [str(tiny(f, ("[[2.0, 2.0, 1.0]]", "[[2.0, 2.0]]")))], "robots.0.starts.0"),
    ("start-outside-scene", lambda f, o: [str(tiny(f, ("[[2.0, 2.0, 1.0]]", "[[20.0, 2.0, 1.0]]")))],
     "robots.0.starts.0"),
    ("start-in-a-wall", lambda f, o: [str(tiny(f, ("[[2.0, 2.0, 1.0]]", "[[5.0, 5.0, 1.0]]")))],
     "robots.0.starts.0"),
    ("starts-overlap", lambda f, o: [str(tiny(f, ("[[2.0, 2.0, 1.0]]", "[[2.0, 2.0, 1.0], [2.1, 2.0, 1.0]]")))],
     "robots.0.starts.1"),
    ("ground-starts-overlap", lambda f, o: [str(tiny(f, ("[[3.0, 2.0, 0.0]]", "[[3.0, 2.0, 0.0], [3.0, 2.0, 0.0]]")))],
     "robots.1.starts.1"),
    ("count-huge", lambda f, o: [str(tiny(f, ('kind = "ground"\nstarts = [[3.0, 2.0, 0.0]]',
                                              'kind = "ground"\ncount = 100000\nspawn_center = [3.0, 2.0, 0.0]')))],
     "robots.1.count"),
    ("count-zero", lambda f, o: [str(tiny(f)), "--set", "robots.0.count=0"], "robots.0.count"),
    ("target-center-nan", lambda f, o: [str(tiny(f, ("center = [2.0, 7.0, 1.0]", "center = [2.0, nan, 1.0]")))],
     "targets.0.center.1"),
    ("target-speed-nan", lambda f, o: [str(tiny(f, ("speed_mps = 0.05", "speed_mps = nan")))],
     "targets.0.speed_mps"),
    ("target-outside-scene", lambda f, o: [str(tiny(f, ("center = [2.0, 7.0, 1.0]", "center = [2.0, 12.0, 1.0]")))],
     "targets.0"),
    ("comm-range-inf", lambda f, o: [str(tiny(f, extra="[sensing]\ncomm_range_m = inf\n"))], "sensing.comm_range_m"),
    ("comm-range-negative", lambda f, o: [str(tiny(f)), "--set", "sensing.comm_range_m=-1"],
     "sensing.comm_range_m"),
    ("unknown-key", lambda f, o: [str(tiny(f, extra="colour = 'red'\n"))], "colour"),
    ("radio-unknown-preset", lambda f, o: [str(tiny(f)), "--set", "radio.preset=lora"], "radio.preset"),
    ("radio-unknown-key", lambda f, o: [str(tiny(f, extra="[radio]\nantenna_gain_db = 2\n"))],
     "radio.antenna_gain_db"),
    ("radio-bitrate-negative", lambda f, o: [str(tiny(f)), "--set", "radio.bitrate_bps=-250000"], "radio.bitrate_bps"),
    ("radio-exponent-below-1", lambda f, o: [str(tiny(f)), "--set", "radio.path_loss_exponent=0.5"],
     "radio.path_loss_exponent"),
    ("radio-unknown-fading", lambda f, o: [str(tiny(f)), "--set", "radio.fading=nakagami"], "radio.fading"),
    ("radio-wall-loss-inf", lambda f, o: [str(tiny(f, extra="[radio]\nwall_loss_db = inf\n"))],
     "radio.wall_loss_db"),
    ("scene-wall-loss-negative",
     lambda f, o: [str(write_scene(f, WALL_SCENE.replace("<custom>", '<custom><numeric name="tether_wall_loss_db" '
                                                         'data="-3"/>'), "lossy.xml")
                       and tiny(f, ('scene = "scene.xml"', 'scene = "lossy.xml"')))], "tether_wall_loss_db"),
    ("radio-wall-loss-nan", lambda f, o: [str(tiny(f)), "--set", "radio.wall_loss_db=nan"], "radio.wall_loss_db"),
    ("unknown-strategy-key", lambda f, o: [str(tiny(f)), "--set", "strategy.dwell_time_s=1"],
     "strategy.dwell_time_s"),
    ("unknown-strategy", lambda f, o: [str(tiny(f)), "--set", "strategy.kind=teleport"], "strategy.kind"),
    ("no-robots", lambda f, o: [str(write_scenario(f, 'scene = "empty"\nrobots = []\n[strategy]\nkind = "waypoints"\n',
                                                   "empty.toml"))], "robots"),
    ("timestep-zero", lambda f, o: [str(tiny(f)), "--set", "physics.timestep_s=0"], "physics.timestep_s"),
    ("control-period-off-grid", lambda f, o: [str(tiny(f)), "--set", "physics.control_period_s=0.003"],
     "physics.control_period_s"),
    ("set-without-value", lambda f, o: [str(tiny(f)), "--set", "duration_s"], "--set"),
    ("set-no-list-entry", lambda f, o: [str(tiny(f)), "--set", "robots.5.count=1"], "robots.5"),
    ("scene-missing", lambda f, o: [str(tiny(f, ('scene = "scene.xml"', 'scene = "nowhere.xml"')))], "scene"),
    ("scene-parse-error", lambda f, o: [str(write_scene(f, BROKEN_SCENE, "broken.xml") and
                                            tiny(f, ('scene = "scene.xml"', 'scene = "broken.xml"')))],
     "Error=XML_ERROR"),
    ("scene-without-floor", lambda f, o: [str(write_scene(f, NO_FLOOR_SCENE, "nofloor.xml") and
                                              tiny(f, ('scene = "scene.xml"', 'scene = "nofloor.xml"')))],
     "nothing to stand on"),
    ("target-counts-huge", lambda f, o: ["connected-empty", "--set", "strategy.target_counts=[100000]"],
     "strategy.target_counts"),
    ("n-sample-huge", lambda f, o: ["intermittent-4", "--set", "strategy.n_sample=1000000000"], "strategy.n_sample"),
    ("video-size-odd", lambda f, o: [str(tiny(f)), "--video-size", "641x480"], "video.width"),
    ("video-size-garbage", lambda f, o: [str(tiny(f)), "--video-size", "big"], "--video-size"),
    ("video-fps-nan", lambda f, o: [str(tiny(f)), "--video-fps", "nan"], "video.fps"),
    ("video-camera-unknown", lambda f, o: [str(tiny(f)), "--video-camera", "nowhere"], "video.camera"),
    ("rerun-port-too-large", lambda f, o: [str(tiny(f)), "--rerun-live", "--rerun-port", "70000"], "--rerun-port"),
    ("rerun-host-unknown", lambda f, o: [str(tiny(f)), "--rerun-live", "--host", "no-such-host.invalid"], "--host"),
]


@pytest.mark.parametrize("case", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_refused_in_one_line_and_leaves_earlier_results(case, tmp_path, capsys):
    _, argv, field = case
    out = tmp_path / "out"
    before = earlier_results(out)
    code, err, _ = run_cli(["run", *argv(tmp_path, out), "--out", str(out), "--quiet"], capsys)
    assert_refused(code, err, field)
    assert snapshot(out) == before
    assert not list(tmp_path.glob("out.partial-*"))


@pytest.mark.parametrize("where", ["under-a-file", "a-file", "unwritable"])
def test_an_output_folder_that_cannot_be_written_is_refused_first(where, tmp_path, capsys):
    (tmp_path / "file").write_text("not a folder")
    out = {"under-a-file": tmp_path / "file" / "out", "a-file": tmp_path / "file",
           "unwritable": Path("/proc/tether-out")}[where]
    # The scenario is broken too: the folder is checked first.
    code, err, _ = run_cli(["run", str(tmp_path / "nowhere.toml"), "--out", str(out)], capsys)
    assert_refused(code, err, "--out")
    assert (tmp_path / "file").read_text() == "not a folder"


TUNE_CASES = [
    ("port-not-a-number", ["--port", "abc"], "--port"),
    ("port-too-large", ["--port", "70000"], "--port"),
    ("speed-nan", ["--speed", "nan"], "--speed"),
    ("host-unknown", ["--host", "no-such-host.invalid"], "--host"),
    ("view-fps-zero", ["--view-fps", "0"], "--view-fps"),
    ("start-nan", ["--set", "robots.0.starts.0=[nan, 2.0, 1.0]"], "robots.0.starts.0.0"),
    ("starts-overlap", ["--set", "robots.0.starts.1=[2.0, 2.0, 1.0]"], "robots.0.starts.1"),
]


@pytest.mark.parametrize("case", TUNE_CASES, ids=[c[0] for c in TUNE_CASES])
def test_tune_refuses_bad_input_before_serving(case, tmp_path, capsys):
    _, flags, field = case
    scenario = tiny(tmp_path, ("[[2.0, 2.0, 1.0]]", "[[2.0, 2.0, 1.0], [2.0, 4.0, 1.0]]"))
    code, err, out = run_cli(["tune", str(scenario), "--port", "0", *flags], capsys)
    assert_refused(code, err, field)
    assert "tuning page" not in out


def test_argparse_errors_are_one_line_too(capsys):
    code, err, _ = run_cli(["run"], capsys)
    assert code == 2 and len(err) == 1 and err[0].startswith("tether: error: ")


def test_a_reused_folder_holds_one_runs_files(tmp_path, capsys):
    out = tmp_path / "out"
    earlier_results(out)
    (out / "plots" / "timeseries_3.png").write_bytes(b"stale page")
    (out / "notes.txt").write_text("mine")
    code, err, _ = run_cli(["run", str(tiny(tmp_path)), "--out", str(out), "--quiet"], capsys)
    assert code == 0, err
    names = {str(p.relative_to(out)) for p in out.rglob("*")}
    assert names == {"metrics.json", "progress.json", "plots", "plots/timeseries.png", "notes.txt", ".tether-files.json"}
    assert json.loads((out / "metrics.json").read_text())["status"] == "completed"
    assert not list(tmp_path.glob("out.partial-*"))


def test_a_run_that_raises_leaves_earlier_results_untouched(tmp_path):
    from sim.observers import Observer
    from sim.scenario import load
    from tether.runner import run

    class Raises(Observer):  # an observer with a bug, two ticks in
        ticks = 0

        def on_tick(self, frame):
            self.ticks += 1
            if self.ticks == 2:
                raise RuntimeError("observer bug")

        def close(self, status):
            pass

    out = tmp_path / "out"
    before = earlier_results(out)
    with pytest.raises(RuntimeError, match="observer bug"):
        run(load(str(tiny(tmp_path))), out, rrd=True, extra_observers=[Raises()])
    assert snapshot(out) == before
    assert not list(tmp_path.glob("out.partial-*"))


def test_metrics_are_valid_json_when_a_figure_is_not_finite(tmp_path):
    from sim.outputs import json_safe, non_finite_fields, write_json

    payload = {"a": float("nan"), "b": [1.0, float("inf")], "c": {"d": -math.inf}, "e": 2}
    assert non_finite_fields(payload) == ["a", "b.1", "c.d"]
    write_json(tmp_path / "m.json", payload)
    assert json.loads((tmp_path / "m.json").read_text(), parse_constant=pytest.fail) == json_safe(payload)


def _falling_scenario(folder: Path) -> Path:
    """The tiny scenario on a 0.6 m floor tile whose edge the ground robot starts beside and drives off.
    (MuJoCo planes collide everywhere whatever their size: a box is a floor with an edge.)"""
    scene = WALL_SCENE.replace('type="plane" size="5 5 0.05" pos="5 5 0"',
                               'type="box" size="0.3 0.3 0.05" pos="3 2 -0.05"')
    write_scene(folder, scene)
    body = textwrap.dedent(TINY).replace('kind = "waypoints"\nspeed_mps = 0.5',
                                         'kind = "waypoints"\nground_speed_mps = 0.15\ndwell_s = 0.0\n'
                                         'routes = [[[2.0, 2.0, 1.0]], [[3.9, 2.0, 0.0]]]')
    body = body.replace("duration_s = 0.1", "duration_s = 3.0").replace("[[3.0, 2.0, 0.0]]", "[[3.29, 2.0, 0.0]]")
    return write_scenario(folder, body, "falls.toml")


def test_a_ground_robot_that_falls_stops_the_run_diverged(tmp_path):
    """A floor too small for a robot's route: it drives off the edge; the run stops at once.
    (Exit code 1 for "diverged": tests/test_run_outputs.py.)"""
    from tether.runner import run
    from sim.scenario import load

    result = run(load(str(_falling_scenario(tmp_path))))
    message = result.metrics["message"]
    assert result.status == "diverged" and "ground0" in message and ("fell" in message or "tipped" in message)
    assert result.metrics["sim_time_s"] < 3.0


def test_the_compiled_tick_check_finds_what_the_numpy_formulation_finds():
    """sim.validate's one-pass kernel against the numpy expressions it replaced, on random states."""
    from types import SimpleNamespace

    from sim.validate import BOUNDS_MARGIN_M, FALL_DEPTH_M, NON_FINITE, TIP_COSINE, tick_sanity

    rng = np.random.default_rng(7)
    world = SimpleNamespace(bounds=np.array([[0.0, 0.0, 0.0], [4.0, 3.0, 2.0]]),
                            kind_index={"ground": np.array([1, 3])})
    adr = np.array([0, 7, 14, 21], dtype=np.int64)
    lo, hi = world.bounds[0] - BOUNDS_MARGIN_M, world.bounds[1] + BOUNDS_MARGIN_M
    for _ in range(500):
        qpos = rng.uniform(-1.3, 5.3, 28)
        qpos[[3, 10, 17, 24]] = 1.0
        qpos[[4, 5, 11, 12, 18, 19, 25, 26]] = rng.uniform(-0.7, 0.7, 8)
        qvel = rng.normal(size=24)
        if rng.random() < 0.1:
            (qpos if rng.random() < 0.5 else qvel)[rng.integers(20)] = rng.choice([np.nan, np.inf])
        start = rng.uniform(-0.3, 1.0, 4)
        position, quaternion = qpos[adr[:, None] + np.arange(3)], qpos[adr[:, None] + np.arange(3, 7)]
        g = world.kind_index["ground"]
        if not (np.all(np.isfinite(qpos)) and np.all(np.isfinite(qvel))):
            expected = (NON_FINITE, -1)
        elif np.any(outside := np.any((position < lo) | (position > hi), axis=1)):
            expected = (2, int(np.flatnonzero(outside)[0]))
        elif np.any(fallen := position[g, 2] < start[g] - FALL_DEPTH_M):
            expected = (3, int(g[np.flatnonzero(fallen)[0]]))
        elif np.any(tipped := 1.0 - 2.0 * (quaternion[g, 1] ** 2 + quaternion[g, 2] ** 2) < TIP_COSINE):
            expected = (4, int(g[np.flatnonzero(tipped)[0]]))
        else:
            expected = (0, -1)
        assert tuple(int(v) for v in tick_sanity(world, qpos, qvel, adr, start)) == expected


# ---------------------------------------------------------------- property test

def _valid_table() -> dict:
    import tomllib

    return tomllib.loads(textwrap.dedent(TINY))


def _paths(node, prefix=()) -> list[tuple]:
    out = []
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else []
    for key, value in items:
        out.append(prefix + (key,))
        out += _paths(value, prefix + (key,))
    return out


VALUES = st.one_of(
    st.sampled_from([float("nan"), float("inf"), -float("inf"), -1, 0, -1.0, 0.0, 1e308, 10**30, 2**63, True,
                     "text", "", [], [1.0, 2.0], {"x": 1}, 100000, 1e-9]),
    st.floats(allow_nan=True, allow_infinity=True),
    st.integers(min_value=-(2**70), max_value=2**70),
    st.text(max_size=5),
)


@st.composite
def mutated_tables(draw):
    table = _valid_table()
    for _ in range(draw(st.integers(1, 3))):
        paths = _paths(table)
        path = draw(st.sampled_from(paths))
        parent = table
        for key in path[:-1]:
            parent = parent[key]
        action = draw(st.sampled_from(["replace", "replace", "delete", "extra"]))
        if action == "delete":
            del parent[path[-1]]
        elif action == "extra" and isinstance(parent, dict):
            parent[draw(st.sampled_from(["extra", "count", "end", "start", "radius_m"]))] = copy.deepcopy(draw(VALUES))
        else:  # a copy: a later mutation must not change VALUES' shared list or dict for the next examples
            parent[path[-1]] = copy.deepcopy(draw(VALUES))
    return table


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(table=mutated_tables())
def test_mutated_scenarios_exit_cleanly_and_never_leave_a_half_written_folder(table, tmp_path_factory, capsys):
    folder = tmp_path_factory.mktemp("mutant")
    write_scene(folder)
    try:
        text = dumps_toml(table)
    except TypeError:
        return  # not expressible as TOML
    path = folder / "mutant.toml"
    path.write_text(text)
    out = folder / "out"
    code = main(["run", str(path), "--out", str(out), "--duration", "0.05", "--quiet"])
    err = capsys.readouterr().err
    assert code in (0, 1, 2), err
    assert "Traceback" not in err
    assert not list(folder.glob("out.partial-*"))
    if code == 2:
        assert len(err.strip().splitlines()) == 1 and not out.exists(), err
    else:
        metrics = json.loads((out / "metrics.json").read_text(), parse_constant=pytest.fail)
        assert metrics["status"] in ("completed", "diverged")



# ---------------------------------------------------------------- interruptions (real signals, a real process)

REPO = Path(__file__).resolve().parent.parent
SIGNAL_ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}


def _start_long_run(tmp_path: Path, *flags: str) -> tuple[subprocess.Popen, Path, Path]:
    scenario = tiny(tmp_path, ("duration_s = 0.1", "duration_s = 600.0"))
    out = tmp_path / "out"
    proc = subprocess.Popen([sys.executable, "-m", "tether.cli", "run", str(scenario), "--out", str(out), "--quiet",
                             "--rrd", *flags], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=SIGNAL_ENV, cwd=REPO)
    return proc, out, tmp_path / f"out.partial-{proc.pid}"


def _wait_for_progress(proc: subprocess.Popen, staging: Path, segments: int = 0, timeout_s: float = 120) -> dict:
    """The staging folder's progress.json once the run ticks (and ``segments`` recording files are complete)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()
        try:
            progress = json.loads((staging / "progress.json").read_text())
        except (OSError, ValueError):
            progress = None
        parts = sorted((staging / "run.rrd.segments").glob("part-*.rrd"))
        if progress and progress["tick"] >= 5 and len(parts) > segments:
            return progress
        time.sleep(0.2)
    proc.kill()
    raise AssertionError("the run never made progress")


def _events(path: Path) -> list[str]:
    from tests.helpers import rrd_chunks, rrd_texts

    return [text for _, text in rrd_texts(rrd_chunks(path)["/events"])]


@pytest.mark.parametrize("sig", [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.slow)],
                         ids=["ctrl-c", "sigterm"])
def test_an_interrupted_run_closes_cleanly(sig, tmp_path):
    from rerun.chunk import RrdReader

    flags = ("--video", "--video-size", "160x120", "--video-fps", "10") if sig == signal.SIGINT else ()
    proc, out, staging = _start_long_run(tmp_path, *flags)
    _wait_for_progress(proc, staging)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, err
    assert "Traceback" not in err
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "interrupted" and signal.Signals(sig).name in metrics["message"]
    assert 0 < metrics["sim_time_s"] < 600
    assert json.loads((out / "progress.json").read_text())["status"] == "interrupted"
    assert RrdReader(str(out / "run.rrd")).store()
    events = _events(out / "run.rrd")
    assert events[-1] == "run ended: interrupted" and any("interrupted (" in e for e in events)
    assert not staging.exists() and not (out / "run.rrd.segments").exists()
    if sig == signal.SIGINT:
        import imageio.v2 as imageio

        with imageio.get_reader(out / "video.mp4") as video:
            assert sum(1 for _ in video) >= 1


def test_a_killed_run_leaves_readable_progress_and_recording(tmp_path):
    from rerun.chunk import RrdReader

    out_before = earlier_results(tmp_path / "out")
    proc, out, staging = _start_long_run(tmp_path, "--video", "--video-size", "160x120", "--video-fps", "10")
    _wait_for_progress(proc, staging, segments=1)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    assert snapshot(out) == out_before  # the earlier results are untouched
    progress = json.loads((staging / "progress.json").read_text())
    assert progress["status"] == "running" and progress["tick"] >= 5
    first = staging / "run.rrd.segments" / "part-00000.rrd"
    store = RrdReader(str(first)).store()  # complete: footer and all
    assert store
    assert "/world/obstacles" in {str(c.entity_path) for c in RrdReader(str(first)).stream()}
    # The encoder is a process of its own: when its input ends it finishes the file.
    import imageio.v2 as imageio

    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            with imageio.get_reader(staging / "video.mp4") as video:
                assert sum(1 for _ in video) >= 1
            break
        except (OSError, RuntimeError, IndexError):
            time.sleep(0.5)
    else:
        raise AssertionError("the video of the killed run is not readable")


# ---------------------------------------------------------------- the tuning page

@pytest.fixture(scope="module")
def tuning(tmp_path_factory):
    """A real tuning server (in this process) on the falling scenario, ticking as fast as it can."""
    import threading

    from sim.scenario import load
    from tether.runner import build_simulation
    from viz.tuning import TuningServer, TuningSession

    folder = tmp_path_factory.mktemp("tune")
    scenario = load(str(_falling_scenario(folder)), ["video.width=160", "video.height=120"])
    session = TuningSession(scenario, build_simulation, view_fps=1.0, speed=0.0, save_path=folder / "saved.toml")
    server = TuningServer(session, "127.0.0.1", 0)
    thread = threading.Thread(target=server.serve_forever, kwargs={"poll_interval": 0.1}, daemon=True)
    thread.start()
    session.start()
    yield server
    server.shutdown()
    server.server_close()
    session.stop()


def _raw_request(port: int, data: bytes, close_write: bool = True) -> tuple[int, dict]:
    import socket

    with socket.create_connection(("127.0.0.1", port), timeout=30) as s:
        s.sendall(data)
        if close_write:
            s.shutdown(socket.SHUT_WR)
        reply = b""
        while chunk := s.recv(65536):
            reply += chunk
    head, _, body = reply.partition(b"\r\n\r\n")
    return int(head.split()[1]), json.loads(body)


MALFORMED = {
    "length-not-a-number": b"POST /api/params HTTP/1.1\r\nHost: {host}\r\nContent-Length: abc\r\n\r\n{{}}",
    "length-negative": b"POST /api/params HTTP/1.1\r\nHost: {host}\r\nContent-Length: -5\r\n\r\n{{}}",
    "body-truncated": b"POST /api/params HTTP/1.1\r\nHost: {host}\r\nContent-Length: 100\r\n\r\n{{\"changes\"",
    "body-not-json": b"POST /api/control HTTP/1.1\r\nHost: {host}\r\nContent-Length: 5\r\n\r\nhello",
    "body-not-an-object": b"POST /api/control HTTP/1.1\r\nHost: {host}\r\nContent-Length: 2\r\n\r\n[]",
    "request-line-garbage": b"HELLO\r\n\r\n",
    "unknown-action": b"POST /api/control HTTP/1.1\r\nHost: {host}\r\nContent-Length: 19\r\n\r\n{{\"action\": \"fly\"}}",
}


@pytest.mark.parametrize("name", list(MALFORMED))
def test_tuning_page_answers_malformed_requests_with_400_json(name, tuning, capfd):
    host = f"127.0.0.1:{tuning.port}".encode()
    status, body = _raw_request(tuning.port, MALFORMED[name].replace(b"{host}", host).replace(b"{{", b"{")
                                .replace(b"}}", b"}"))
    assert status == 400 and body["ok"] is False and body["error"], body
    assert "Traceback" not in capfd.readouterr().err


def test_tuning_page_listens_on_loopback_only(tuning):
    listening = {(host, port) for host, port in _listening_addresses(os.getpid()) if port == tuning.port}
    assert listening == {("127.0.0.1", tuning.port)}


def test_tuning_page_shows_why_a_run_diverged(tuning):
    session = tuning.session
    deadline = time.monotonic() + 120
    while session.state != "diverged" and time.monotonic() < deadline:
        time.sleep(0.2)
    assert session.state == "diverged" and session.paused
    assert session.message.startswith("diverged: ground0 "), session.message
    status = json.loads(_get(f"http://127.0.0.1:{tuning.port}/api/status"))
    assert status["state"] == "diverged" and status["message"].startswith("diverged: ")


def _get(url: str) -> bytes:
    import urllib.request

    with urllib.request.urlopen(url, timeout=30) as response:
        return response.read()


def test_a_tuning_change_that_breaks_an_invariant_is_refused_before_it_applies():
    import dataclasses

    from sim.config import ConfigError
    from tether.runner import build_simulation
    from sim.scenario import load

    sim = build_simulation(load("connected-empty", ["strategy.target_counts=[1]"]))
    params = sim.scenario.strategy.params
    frame, healthy = sim.tick()
    lambda2 = frame.commands.scalars["lambda2"]
    assert healthy and sim.strategy.violation(frame.commands) is None
    assert params.lambda2_min < lambda2
    with pytest.raises(ConfigError) as refused:  # legal values (min < null, in bounds), but above lambda2 now
        sim.set_strategy_params(dataclasses.replace(params, lambda2_min=lambda2 + 0.5, lambda2_null=lambda2 + 1.0))
    assert refused.value.field == "strategy.lambda2_min" and "current lambda2" in refused.value.problem
    assert sim.scenario.strategy.params == params  # unchanged
    with pytest.raises(ConfigError) as refused:  # the grid is 2.5 m apart: an R_c of 2.6 m has robots inside it
        sim.set_strategy_params(dataclasses.replace(params, min_robot_distance_m=2.6,
                                                    full_weight_robot_distance_m=3.0))
    assert refused.value.field == "strategy.min_robot_distance_m" and "inside" in refused.value.problem
    with pytest.raises(ConfigError) as refused:  # R'_s must stay below R_s, the scenario's comm range: named as it is
        sim.set_strategy_params(dataclasses.replace(params, full_weight_range_m=sim.info.comm_range_m + 1.0))
    assert refused.value.field == "strategy.full_weight_range_m", refused.value
    assert "R_s = sensing.comm_range_m" in refused.value.problem
    frame, healthy = sim.tick()
    assert healthy, sim.divergence


def test_live_rerun_servers_listen_only_where_asked():
    """Every listening socket of --rerun-live is on 127.0.0.1 (the rerun binary's --bind)."""
    import socket

    from viz.recording import LiveViewer

    ports = []
    for _ in range(2):
        with socket.socket() as s:
            s.bind(("127.0.0.1", 0))
            ports.append(s.getsockname()[1])
    live = LiveViewer("127.0.0.1", *ports)
    try:
        listening = _listening_addresses(live._server.pid)
        assert {port for _, port in listening} >= set(ports)
        assert {host for host, _ in listening} == {"127.0.0.1"}, listening
    finally:
        live.close()


def _listening_addresses(pid: int) -> set[tuple[str, int]]:
    """(address, port) of the TCP sockets process ``pid`` listens on (from /proc)."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:  # closed while listing
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    out = set()
    for table in ("tcp", "tcp6"):
        for line in Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]:
            fields = line.split()
            if fields[3] == "0A" and fields[9] in inodes:  # LISTEN
                address, port = fields[1].split(":")
                if table == "tcp":
                    host = ".".join(str(int(address[i:i + 2], 16)) for i in (6, 4, 2, 0))
                else:
                    host = "::" if set(address) == {"0"} else address
                out.add((host, int(port, 16)))
    return out
