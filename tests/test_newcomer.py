"""A newcomer's first hour: the commands someone new to tether types, each
working or refused in one line (exit 2, no traceback), on real MuJoCo."""

import subprocess
import sys

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
