"""Bad input for the intermittent-task strategies: one line naming the field, exit 2,
nothing written (a robot in one or three teams, a disconnected team
graph, delta <= 0, n_sample < 1, and the other checks of the strategies)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from intermittent_helpers import room_scenario
from tether.cli import main

CASES = {
    "robot in one team": (["strategy.teams=[[0,1],[0,2],[2,3]]"], "strategy.teams: robot 1 belongs to 1 team(s)"),
    "robot in three teams": (["strategy.teams=[[0,1],[0,2],[0,3],[1,2,3]]"],
                             "strategy.teams: robot 0 belongs to 3 team(s)"),
    "disconnected team graph": (["strategy.teams=[[0,1],[0,1],[2,3],[2,3]]"],
                                "strategy.teams: the graph of teams is not connected"),
    "delta zero": (["strategy.delta_m2=0.0"], "strategy.delta_m2: must be positive"),
    "delta negative": (["strategy.delta_m2=-0.01"], "strategy.delta_m2: must be positive"),
    "n_sample zero": (["strategy.n_sample=0"], "strategy.n_sample: must be an integer >= 1"),
    "n_sample not an integer": (["strategy.n_sample=2.5"], "strategy.n_sample: must be an integer"),
    "robot index out of range": (["strategy.teams=[[0,1],[0,2],[2,3],[1,4],[3,4]]"],
                                 "strategy.teams: robot index 4 does not exist"),
    "no teams": (["strategy.teams=[]"], "strategy.teams: is required"),
    "negative speed": (["strategy.speed_mps=-0.1"], "strategy.speed_mps: must be positive"),
    "step is the sensing period": (["strategy.step_s=2.0"],
                                   "strategy.step_s: is no longer a key; set sensing.period_s"),
    "target model steps differ from the readings": (["target_motion.step_s=2.0"],
                                                    "target_motion.step_s: must equal sensing.period_s"),
    "prior of the wrong size": (["strategy.prior_mean=[[1.0,1.0,1.0]]"], "strategy.prior_mean: has 1 entries"),
    "lag team out of range": (["strategy.lag_team=4"], "strategy.lag_team: must be a team index below 4"),
    "all_time needs a connected start": (
        ["strategy.kind=all_time", "robots.0.starts=[[1.0,1.0,0.0],[3.0,1.0,0.0],[1.0,2.0,0.0],[3.0,2.0,0.0]]"],
        "robots: all_time keeps the start configuration"),
    "link margin eats the range": (["strategy.link_margin_m=0.3"], "strategy.link_margin_m: must be below"),
    "quadrotors are refused": (["robots.0.kind=\"quadrotor\"",
                                "robots.0.starts=[[1.0,1.0,1.0],[1.6,1.0,1.0],[1.0,1.6,1.0],[1.6,1.6,1.0]]"],
                               "robots: the intermittent-task strategies drive ground robots only"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_one_line_exit_2_nothing_written(tmp_path, capsys, case):
    overrides, expected = CASES[case]
    path = room_scenario(tmp_path, duration=1.0)
    out = tmp_path / "out"
    args = ["run", str(path), "--out", str(out), "--quiet"]
    for assignment in overrides:
        args += ["--set", assignment]
    code = main(args)
    err = capsys.readouterr().err
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in err, err
    assert expected in lines[0], lines[0]
    assert not out.exists()


def test_bad_input_through_the_installed_command(tmp_path):
    path = room_scenario(tmp_path, duration=1.0)
    result = subprocess.run([sys.executable, "-m", "tether.cli", "run", str(path), "--set", "strategy.delta_m2=-1",
                             "--out", str(tmp_path / "o")], capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert result.stderr.strip().splitlines() == [
        "tether: error: strategy.delta_m2: must be positive (a variance threshold, m^2), got -1.0"]


def test_table1_sweep_refuses_bad_input(capsys, tmp_path):
    """A Table I sweep with a bad method, scenario, override or seed count: exit 2, one line, nothing written."""
    base = 'scenario = "intermittent-8"\nduration_s = 30.0\n'
    for body, expected in (('seeds = 0\n', "seeds: must be a count from 1 to 100000"),
                           ('seeds = 1\n[grid]\n"strategy.kind" = ["intermittent", "magic"]\n',
                            "strategy.kind: unknown strategy 'magic'"),
                           ('seeds = 1\n[grid]\nscenario = ["intermittent-8", "nope"]\n', "' is neither a built-in"),
                           ('seeds = 1\nset = ["strategy.n_sample=0"]\n', "strategy.n_sample: must be an integer >= 1")):
        sweep = tmp_path / "table.toml"
        sweep.write_text(base + body)
        code = main(["sweep", str(sweep), "--out", str(tmp_path / "c")])
        err = capsys.readouterr().err
        assert code == 2 and expected in err and err.count("\n") == 1, err
    assert not (tmp_path / "c").exists()
