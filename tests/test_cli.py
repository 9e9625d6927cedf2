"""Bad input: one line naming the field, exit code 2, nothing written."""

import subprocess
import sys

import pytest

from helpers import write_scenario, write_scene

BASE = """
scene = "{scene}"
duration_s = 1.0
{extra_top}
[strategy]
kind = "waypoints"
{extra_strategy}
[[robots]]
kind = "quadrotor"
starts = [{start}]
{extra}
"""


def scenario_text(scene="scene.xml", start="[2.0, 2.0, 1.0]", extra_top="", extra_strategy="", extra=""):
    return BASE.format(scene=scene, start=start, extra_top=extra_top, extra_strategy=extra_strategy, extra=extra)


def run_cli(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "tether.cli", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=120)


CASES = {
    "unknown top-level key": (dict(extra_top="colour = 3"), "colour: unknown key"),
    "unknown nested key": (dict(extra="[physics]\ndt = 0.001"), "physics.dt: unknown key"),
    "wrong type": (dict(extra_top='seed = "seven"'), "seed: must be an integer"),
    "non-positive range": (dict(extra="[sensing]\ncomm_range_m = 0.0"), "sensing.comm_range_m: must be positive"),
    "non-positive rate": (dict(extra="[physics]\ncontrol_period_s = -0.01"), "physics.control_period_s: must be positive"),
    "control period not a multiple": (dict(extra="[physics]\ncontrol_period_s = 0.005\ntimestep_s = 0.002"),
                                      "physics.control_period_s: must be a whole multiple"),
    "unknown strategy": (dict(extra_strategy='speed = 1'), "strategy.speed: unknown key"),
    "robot inside a wall": (dict(start="[5.0, 5.0, 1.0]"), "robots.0.starts.0: start (5.0, 5.0, 1.0) is inside"),
    "robot outside the scene": (dict(start="[12.0, 5.0, 1.0]"), "robots.0.starts.0: start (12.0, 5.0, 1.0) lies outside"),
    "target inside a wall": (dict(extra='[[targets]]\npath = "linear"\nstart = [4.0, 5.0, 1.0]\nend = [6.0, 5.0, 1.0]'),
                             "targets.0: path passes through an obstacle"),
    "target outside the scene": (dict(extra='[[targets]]\npath = "static"\nstart = [4.0, 5.0, 7.0]'),
                                 "targets.0: path leaves the scene bounds"),
    "missing MJCF": (dict(scene="nowhere.xml"), "scene: 'nowhere.xml' is neither a built-in scene"),
    "malformed MJCF": (dict(scene="broken.xml"), "scene: "),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_gives_one_line_and_exit_2(tmp_path, case):
    kwargs, expected = CASES[case]
    write_scene(tmp_path)
    (tmp_path / "broken.xml").write_text("<mujoco><worldbody><geom type='box'></worldbody>")
    path = write_scenario(tmp_path, scenario_text(**kwargs))
    out = tmp_path / "out"
    result = run_cli("run", str(path), "--out", str(out), "--video", "--rrd", cwd=tmp_path)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr
    assert "Traceback" not in result.stderr
    assert expected in lines[0], lines[0]
    assert not out.exists()


def test_bad_override_and_unknown_scenario(tmp_path):
    result = run_cli("run", "hover", "--set", "physics.timestep_s=-1", "--out", str(tmp_path / "o"))
    assert result.returncode == 2 and "physics.timestep_s: must be positive" in result.stderr
    result = run_cli("run", "no-such-scenario", "--out", str(tmp_path / "o"))
    assert result.returncode == 2 and "scenario: 'no-such-scenario'" in result.stderr
    result = run_cli("run", "hover", "--set", "robots.5.count=3", "--out", str(tmp_path / "o"))
    assert result.returncode == 2 and "robots.5: no list entry" in result.stderr
    assert not (tmp_path / "o").exists()


def test_scenarios_lists_builtins_with_a_description():
    result = run_cli("scenarios")
    assert result.returncode == 0
    lines = dict(line.split(None, 1) for line in result.stdout.strip().splitlines())
    assert "hover" in lines and len(lines["hover"]) > 20
