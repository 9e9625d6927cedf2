"""`tether sweep` / `tether report`: tiny sweeps of the `hover` scenario on
the process pool and on a local Ray instance, a driver killed mid-sweep, a
failing trial, the report on a fixture table, and every refused input."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from tether.cli import main
from tether.sweep import ResultsFolder, load_sweep, local_ray_cluster, read_results

# Columns that differ between two runs of the same trial: when and where it ran, how long it took.
WALL_CLOCK_COLUMNS = {"wall_time_s", "run_wall_time_s", "host", "finished_at", "real_time_factor", "timing"}

# A robot start outside the scene passes the scenario loader (and so the
# sweep's validation) but makes the world build raise: a trial that raises.
HOVER_STARTS = "[[1.0, 4.0, 1.0], [5.0, 4.5, 1.0], [8.8, 5.5, 1.0], [5.0, 6.0, 1.2]]"
OUTSIDE_STARTS = "[[50.0, 4.0, 1.0], [5.0, 4.5, 1.0], [8.8, 5.5, 1.0], [5.0, 6.0, 1.2]]"


def write_sweep(folder: Path, name: str, body: str) -> Path:
    path = folder / f"{name}.toml"
    path.write_text(f'description = "test sweep"\nscenario = "hover"\n{body}')
    return path


@pytest.fixture
def tiny(tmp_path) -> Path:
    """4 trials of 0.3 s: 2 seeds x 2 speeds."""
    return write_sweep(tmp_path, "tiny", 'duration_s = 0.3\nseeds = 2\n[grid]\n"strategy.speed_mps" = [0.3, 0.5]\n')


def comparable(table: pa.Table) -> list[dict]:
    rows = table.to_pylist()
    return [{k: v for k, v in r.items() if k not in WALL_CLOCK_COLUMNS} for r in rows]


def folder_state(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_builtin_sweeps_are_listed_and_expand_to_their_trial_counts(capsys):
    assert main(["sweeps"]) == 0
    listed = [line.split()[0] for line in capsys.readouterr().out.splitlines()]
    expected = {"fig9-small": 180, "fig9": 1800, "table1": 60, "teams": 20, "paradigms": 160,
                "radio-tracking": 200, "radio-exploration": 120, "failures": 80}
    assert sorted(listed) == sorted(expected)
    for name, count in expected.items():
        sweep = load_sweep(name)  # validates every trial
        assert len(sweep.trials) == count
    fig9_small = load_sweep("fig9-small").trials
    assert {t.scenario for t in fig9_small} == {"connected-office", "connected-empty", "connected-town"}
    assert sorted({dict(t.swept)["robots.0.count"] for t in fig9_small}) == [10, 15, 20, 25, 30, 35]
    assert len({t.seed for t in fig9_small}) == 10


def test_grid_and_zip_expand_into_trials_with_stable_ids(tmp_path):
    sweep = write_sweep(tmp_path, "expand", 'duration_s = 0.3\nseeds = [4, 7]\n[grid]\n"sensing.comm_range_m" = [2.0, 3.0]\n'
                                            '[[zip]]\n"strategy.speed_mps" = [0.3, 0.5]\n"strategy.dwell_s" = [0.5, 1.0]\n')
    trials = load_sweep(str(sweep)).trials
    assert len(trials) == 2 * 2 * 2
    pairs = {(dict(t.swept)["strategy.speed_mps"], dict(t.swept)["strategy.dwell_s"]) for t in trials}
    assert pairs == {(0.3, 0.5), (0.5, 1.0)}  # tied keys vary together
    assert {t.seed for t in trials} == {4, 7} and len({t.trial_id for t in trials}) == 8
    # An id depends on what decides the result, not on the file or the trial's place in it.
    reordered = write_sweep(tmp_path, "reordered", 'duration_s = 0.3\nseeds = [7]\n[grid]\n"strategy.dwell_s" = [1.0]\n'
                                                  '"strategy.speed_mps" = [0.5]\n"sensing.comm_range_m" = [3.0]\n')
    (only,) = load_sweep(str(reordered)).trials
    assert only.trial_id in {t.trial_id for t in trials}


def test_pool_sweep_runs_to_the_end_and_a_rerun_skips_every_trial(tiny, tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["sweep", str(tiny), "--out", str(out), "--workers", "2", "--rrd", "1"]) == 0
    summary = capsys.readouterr().out
    assert "4 finished, 0 failed, 0 not run of 4" in summary and str(out / "results.parquet") in summary

    table = pq.read_table(out / "results.parquet")
    rows = table.to_pylist()
    assert [r["trial_index"] for r in rows] == [0, 1, 2, 3]
    assert {r["status"] for r in rows} == {"completed"}
    assert sorted((r["seed"], r["strategy.speed_mps"]) for r in rows) == [(0, 0.3), (0, 0.5), (1, 0.3), (1, 0.5)]
    for row in rows:  # every parameter, status, metrics, wall time and host in the row
        assert row["scenario"] == "hover" and row["error"] == "" and row["attempt"] == 1
        assert row["sim_time_s"] == pytest.approx(0.3) and row["wall_time_s"] > 0 and row["host"]
        assert "tracking_error_max_m" in row
    # Only the chosen trial was recorded; the others ran headless.
    recorded = rows[1]["trial_id"]
    assert [p.name for p in (out / "recordings").iterdir()] == [recorded]
    assert (out / "recordings" / recorded / "run.rrd").stat().st_size > 0
    # The per-trial files are one Parquet dataset too.
    assert pq.ParquetDataset(out / "trials").read().num_rows == 4

    before = folder_state(out / "trials")
    assert main(["sweep", str(tiny), "--out", str(out), "--workers", "2"]) == 0
    assert folder_state(out / "trials") == before  # nothing rerun, nothing rewritten


def test_a_trial_that_raises_is_recorded_and_the_others_finish(tmp_path, capsys):
    sweep = write_sweep(tmp_path, "raises", f'duration_s = 0.2\nseeds = [3]\n[grid]\n'
                                            f'"robots.0.starts" = [{HOVER_STARTS}, {OUTSIDE_STARTS}]\n'
                                            '"strategy.speed_mps" = [0.3, 0.5]\n')
    out = tmp_path / "out"
    assert main(["sweep", str(sweep), "--out", str(out), "--workers", "2"]) == 1
    assert "2 finished, 2 failed, 0 not run of 4" in capsys.readouterr().out
    rows = read_results(out).to_pylist()
    failed = [r for r in rows if r["status"] != "completed"]
    assert [r["trial_index"] for r in failed] == [2, 3]
    assert all(r["status"] == "failed" and "outside the scene" in r["error"] for r in failed)
    assert "outside the scene" in (out / "report.md").read_text()

    completed_files = {p.name: p.read_bytes() for p in (out / "trials").glob("*.a1.parquet")
                       if pq.read_table(p).column("status")[0].as_py() == "completed"}
    assert main(["sweep", str(sweep), "--out", str(out), "--workers", "2", "--retry-failed"]) == 1
    second = sorted(p.name for p in (out / "trials").glob("*.a2.parquet"))
    assert len(second) == 2  # only the failed trials ran again, as attempt 2
    assert {p.name: p.read_bytes() for p in (out / "trials").glob("*.a1.parquet") if p.name in completed_files} \
        == completed_files
    assert sorted(r["attempt"] for r in read_results(out).to_pylist()) == [1, 1, 2, 2]
    assert read_results(out, all_attempts=True).num_rows == 6


def test_time_limited_trials_are_results_and_interrupted_ones_run_again(tmp_path, capsys):
    """A trial stopped by its duration cap ("time limit") finished: it is counted as done and never
    rerun, even with --retry-failed; a row saying "interrupted" is not a result and runs again."""
    sweep_path = write_sweep(tmp_path, "statuses", 'duration_s = 0.2\nseeds = 3\n')
    sweep = load_sweep(str(sweep_path))
    out = tmp_path / "out"
    folder = ResultsFolder(out)
    folder.claim(sweep)
    capped, interrupted, _ = sweep.trials
    for trial, status in ((capped, "time limit"), (interrupted, "interrupted")):
        folder.store({"trial_id": trial.trial_id, "trial_index": trial.index, "attempt": 1, "scenario": "hover",
                      "seed": trial.seed, "status": status, "error": f"stopped: {status}"})
    folder.release()  # claim() locked the folder for this process: the driver below claims it again
    assert main(["sweep", str(sweep_path), "--out", str(out), "--workers", "1", "--retry-failed"]) == 0
    assert "3 finished, 0 failed, 0 not run of 3" in capsys.readouterr().out
    latest = {r["trial_id"]: (r["attempt"], r["status"]) for r in read_results(out).to_pylist()}
    assert latest[capped.trial_id] == (1, "time limit")
    assert latest[interrupted.trial_id] == (2, "completed")
    assert "1 of them stopped at their time limit" in (out / "report.md").read_text()


def test_driver_killed_mid_sweep_and_rerun_gives_the_uninterrupted_table(tmp_path):
    sweep = write_sweep(tmp_path, "kill", 'duration_s = 0.4\nseeds = 4\n[grid]\n"strategy.speed_mps" = [0.3, 0.5]\n')
    whole, killed = tmp_path / "whole", tmp_path / "killed"
    assert main(["sweep", str(sweep), "--out", str(whole), "--workers", "2", "--no-report"]) == 0

    command = [sys.executable, "-m", "tether.cli", "sweep", str(sweep), "--out", str(killed), "--workers", "2"]
    driver = subprocess.Popen(command, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 120
        while len(list((killed / "trials").glob("*.parquet"))) < 2:
            assert driver.poll() is None, "the sweep ended before it could be killed"
            assert time.monotonic() < deadline
            time.sleep(0.05)
        driver.send_signal(signal.SIGKILL)
        driver.wait()
    finally:
        try:  # the pool's workers, orphaned by the kill
            os.killpg(driver.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    stored = len(list((killed / "trials").glob("*.parquet")))
    assert 2 <= stored < 8, "the kill must land mid-sweep"
    assert not (killed / "results.parquet").exists()

    assert subprocess.run(command, capture_output=True).returncode == 0
    assert comparable(pq.read_table(killed / "results.parquet")) == comparable(pq.read_table(whole / "results.parquet"))


def _session_members(session: int) -> list[int]:
    """Pids of the live processes in a session (Linux /proc; zombies do not count)."""
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        if int(fields[3]) == session and fields[0] != "Z":  # fields: state, ppid, pgrp, session, ...
            members.append(int(stat.parent.name))
    return members


def test_pool_workers_end_when_their_driver_is_killed(tmp_path):
    """SIGKILL of the driver alone: its pool workers (and the pool's helper processes) stop within
    seconds instead of finishing their trial and the queued ones, whose rows nobody would store."""
    sweep = write_sweep(tmp_path, "orphans", 'duration_s = 30.0\nseeds = 6\n')
    command = [sys.executable, "-m", "tether.cli", "sweep", str(sweep), "--out", str(tmp_path / "out"), "--workers", "2"]
    driver = subprocess.Popen(command, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 60
        while len(_session_members(driver.pid)) < 4:  # driver, forkserver, 2 workers (at least)
            assert driver.poll() is None and time.monotonic() < deadline
            time.sleep(0.1)
        time.sleep(2.0)  # the workers are inside their first trial
        driver.send_signal(signal.SIGKILL)
        driver.wait()
        deadline = time.monotonic() + 15
        while _session_members(driver.pid) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert _session_members(driver.pid) == []
    finally:
        try:
            os.killpg(driver.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass


# ---------------------------------------------------------------- Ray

def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture(scope="module")
def ray_address(tmp_path_factory):
    """One local single-node Ray instance for the module (starting one takes seconds)."""
    pytest.importorskip("ray")
    with local_ray_cluster(num_cpus=2, temp_dir=tmp_path_factory.mktemp("ray")) as address:
        yield address


def test_ray_sweep_gives_the_pool_table(tiny, tmp_path, ray_address):
    pool, on_ray = tmp_path / "pool", tmp_path / "ray"
    assert main(["sweep", str(tiny), "--out", str(pool), "--workers", "2", "--no-report"]) == 0
    assert main(["sweep", str(tiny), "--out", str(on_ray), "--ray", ray_address, "--no-report"]) == 0
    assert comparable(pq.read_table(on_ray / "results.parquet")) == comparable(pq.read_table(pool / "results.parquet"))


# ---------------------------------------------------------------- report

def fixture_table(folder: Path) -> Path:
    """A results table holding every kind of row the report knows, partly failed."""
    rng = np.random.default_rng(0)
    rows = []

    def row(**values):
        base = {"trial_id": f"t{len(rows):04d}", "trial_index": len(rows), "attempt": 1, "status": "completed",
                "error": "", "seed": len(rows) % 5}
        rows.append({**base, **values})

    for scene in ("connected-office", "connected-town"):
        for count in (10, 20, 35):
            for seed in range(4):
                capped = seed == 3 and count == 35  # stopped at its time limit: no completion time
                row(scenario=scene, strategy="connected", n_robots=count, seed=seed,
                    status="time limit" if capped else "completed",
                    completion_time_s=None if capped else 300 - 4 * count + rng.normal(0, 10),
                    mean_travel_m=40 + rng.normal(0, 3), max_stretch_m=20 + count / 5, lambda2_mean=0.1 + count / 300)
    row(scenario="connected-town", strategy="connected", n_robots=20, status="error", error="RuntimeError: boom")
    for scenario, targets in (("intermittent-4", 4), ("intermittent-8", 8)):
        for method in ("all_time", "random_meeting", "intermittent"):
            for seed in range(3):
                row(scenario=scenario, strategy=method, n_moving_targets=targets, seed=seed, duration_s=300.0,
                    overrides=json.dumps([f'strategy.kind="{method}"']),
                    e_g_mean_m=1 + rng.random(), e_g_std_m=0.4, lambda_bar_mean_m2=0.2 + rng.random() / 5,
                    lambda_bar_std_m2=0.1, delay_bound_epochs=5, max_delay_epochs_observed=4,
                    t_star_lag_mean_s=10.0, t_star_lag_max_s=20.0)
    for seed in range(3):
        row(scenario="intermittent-8-dense", strategy="intermittent", n_moving_targets=8, seed=seed,
            e_g_mean_m=1.1 + rng.random() / 5, e_g_std_m=0.5, lambda_bar_mean_m2=0.5, lambda_bar_std_m2=0.1,
            delay_bound_epochs=4, max_delay_epochs_observed=3, t_star_lag_mean_s=8.0, t_star_lag_max_s=16.0)
    columns = list(dict.fromkeys(key for r in rows for key in r))  # from_pylist reads the first row's keys only
    path = folder / "results.parquet"
    pq.write_table(pa.Table.from_pylist([{k: r.get(k) for k in columns} for r in rows]), path)
    return path


def assert_non_blank_png(path: Path) -> None:
    import matplotlib.image

    image = matplotlib.image.imread(path)[..., :3]
    assert image.shape[0] > 100 and image.shape[1] > 100
    assert image.std() > 0.05 and (image < 0.5).mean() > 0.002  # drawn on, not a blank canvas


def test_report_on_a_fixture_table_writes_figures_and_tables(tmp_path, capsys):
    fixture_table(tmp_path)
    assert main(["report", str(tmp_path), "--x", "n_robots", "--y", "max_stretch_m", "--hue", "scenario"]) == 0
    printed = capsys.readouterr().out.split()
    for name in ("fig9.png", "table1.png", "teams.png", "plot_max_stretch_m_vs_n_robots_by_scenario.png"):
        assert str(tmp_path / name) in printed
        assert_non_blank_png(tmp_path / name)
    report = (tmp_path / "report.md").read_text()
    assert "1 failed" in report and "RuntimeError: boom" in report
    assert "2 of them stopped at their time limit" in report
    # Fig. 9: the 35-robot cells have one trial stopped at its time limit: no completion time,
    # but its distance, stretch and lambda2 count.
    assert "| 35 | " in report and "(n=3/4, 1 capped)" in report and "(n=4/4)" in report
    # Table I beside the paper, per target count (metrics.json's n_moving_targets), with n per cell.
    assert "**4 targets**" in report and "**8 targets**" in report and "**0 targets**" not in report
    assert "0.929 ± 0.561" in report and "2.517 ± 0.810" in report and "n=3)" in report
    # Team graphs beside the paper's figures.
    assert "G_T^1" in report and "G_T^2" in report and "1.127" in report and "0.532" in report
    assert_tables_well_formed(report)


def test_a_users_own_sweep_of_the_meeting_methods_is_not_set_beside_the_papers(tmp_path):
    """The paper's numbers stand only beside its set-up: another scenario, another duration or an
    extra override gets ours alone, under a heading that does not name the paper's table."""
    import matplotlib.image

    from tether.report import write_report

    rng = np.random.default_rng(1)
    rows = []
    for scenario, duration, extra in (("my-room", 300.0, []), ("intermittent-8", 60.0, []),
                                      ("intermittent-4", 300.0, ["sensing.comm_noise=0.1"])):
        rows = []
        for method in ("all_time", "random_meeting", "intermittent"):
            for seed in range(2):
                rows.append({"trial_id": f"t{len(rows)}", "trial_index": len(rows), "attempt": 1, "error": "",
                             "status": "completed", "scenario": scenario,
                             "strategy": method, "seed": seed, "duration_s": duration,
                             "overrides": json.dumps([f'strategy.kind="{method}"', *extra]),
                             "n_moving_targets": 8 if scenario == "intermittent-8" else 4,
                             "e_g_mean_m": 1 + rng.random(), "e_g_std_m": 0.3,
                             "lambda_bar_mean_m2": 0.2 + rng.random() / 5, "lambda_bar_std_m2": 0.1})
        folder = tmp_path / scenario
        folder.mkdir()
        pq.write_table(pa.Table.from_pylist(rows), folder / "results.parquet")
        files = write_report(folder)
        report = (folder / "report.md").read_text()
        assert "## The meeting methods compared" in report and "Table I is not shown" in report, scenario
        for paper_value in ("0.929 ± 0.561", "2.517 ± 0.810", "0.879 ± 0.461", "1.030 ± 0.466"):
            assert paper_value not in report, (scenario, paper_value)
        assert "(paper)" not in report
        assert_tables_well_formed(report)
        assert any(p.name == "table1.png" for p in files)
        assert matplotlib.image.imread(folder / "table1.png").std() > 0.05


def test_report_reads_the_target_count_of_tables_written_before_its_rename():
    from tether.report import _moving_targets

    assert _moving_targets({"n_moving_targets": 8}) == 8
    assert _moving_targets({"n_targets": 4}) == 4  # results.parquet of an older sweep
    assert _moving_targets({"n_moving_targets": 0, "n_targets": None}) == 0


def test_report_names_an_unknown_column(tmp_path, capsys):
    fixture_table(tmp_path)
    before = folder_state(tmp_path)
    assert main(["report", str(tmp_path), "--x", "n_robots", "--y", "no_such_metric"]) == 2
    assert "--y: no column 'no_such_metric'" in capsys.readouterr().err
    assert folder_state(tmp_path) == before  # nothing written


# ---------------------------------------------------------------- bad input

BAD_SWEEPS = {
    "unknown sweep key": ('seeds = 1\nrepeats = 3\n', "repeats: unknown sweep key"),
    "unknown scenario key": ('seeds = 1\n[grid]\n"strategy.speeed_mps" = [0.3]\n', "strategy.speeed_mps"),
    "value out of range": ('seeds = 1\n[grid]\n"sensing.comm_range_m" = [2.0, -1.0]\n',
                           "sensing.comm_range_m: must be positive, got -1.0 (trial 1"),
    "empty grid": ('seeds = 1\n[grid]\n"strategy.speed_mps" = []\n', "grid.strategy.speed_mps: must be a non-empty"),
    "zip of unequal lists": ('seeds = 1\n[[zip]]\n"strategy.speed_mps" = [0.3, 0.5]\n"seed" = [1]\n',
                             "zip.0: lists of different lengths"),
    "negative duration": ('duration_s = -1\n', "duration_s: must be a positive number"),
}


@pytest.mark.parametrize("case", sorted(BAD_SWEEPS))
def test_bad_sweep_file_exits_2_naming_the_key(case, tmp_path, capsys):
    body, message = BAD_SWEEPS[case]
    sweep = write_sweep(tmp_path, "bad", body)
    out = tmp_path / "out"
    assert main(["sweep", str(sweep), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and message in err
    assert not out.exists()


def test_folder_of_another_sweep_is_refused(tiny, tmp_path, capsys):
    out = tmp_path / "out"
    ResultsFolder(out).claim(load_sweep(str(tiny)))
    other = write_sweep(tmp_path, "other", 'duration_s = 0.3\nseeds = 3\n')
    before = folder_state(out)
    assert main(["sweep", str(other), "--out", str(out)]) == 2
    assert "holds another sweep's results ('tiny'" in capsys.readouterr().err
    assert folder_state(out) == before


@pytest.mark.parametrize("damage", ["garbage sweep.json", "foreign sweep.json", "garbage row", "foreign row",
                                    "unrelated files"])
def test_unreadable_or_foreign_results_are_refused(damage, tiny, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    if damage == "unrelated files":
        (out / "notes.txt").write_text("mine")
        expected = "is not empty and holds no sweep.json"
    elif damage.endswith("sweep.json"):
        (out / "sweep.json").write_text("{not json" if damage.startswith("garbage") else json.dumps({"a": 1}))
        expected = "sweep.json is unreadable" if damage.startswith("garbage") else "is not a tether sweep file"
    else:
        ResultsFolder(out).claim(load_sweep(str(tiny)))
        row = out / "trials" / "0123456789abcdef.a1.parquet"
        if damage == "garbage row":
            row.write_bytes(b"PAR1 cut short")
            expected = "is not a readable trial row"
        else:
            pq.write_table(pa.Table.from_pylist([{"trial_id": "0123456789abcdef", "attempt": 1, "status": "completed"}]),
                           row)
            expected = "which is not in this sweep"
    before = folder_state(out)
    assert main(["sweep", str(tiny), "--out", str(out)]) == 2
    assert expected in capsys.readouterr().err
    assert folder_state(out) == before


def test_unreachable_ray_address_is_refused(tiny, tmp_path, capsys):
    pytest.importorskip("ray")
    out = tmp_path / "out"
    assert main(["sweep", str(tiny), "--out", str(out), "--ray", f"127.0.0.1:{_free_port()}"]) == 2
    assert "--ray: cannot reach Ray at 127.0.0.1:" in capsys.readouterr().err
    assert not out.exists()


def test_missing_ray_is_refused(tiny, tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray -> ImportError, as without the extra
    out = tmp_path / "out"
    assert main(["sweep", str(tiny), "--out", str(out), "--ray", "auto"]) == 2
    assert "--ray: Ray is not installed" in capsys.readouterr().err
    assert not out.exists()


def test_fig9_is_left_out_of_a_sweep_that_varies_more_than_scene_and_team_size(tmp_path):
    """A radio ladder of connected-office trials: Fig. 9's percentiles would pool the radios into one band."""
    from tether.report import fig9_section

    rows = [dict(trial_id=f"t{i}", scenario="connected-office", strategy="connected", status="completed",
                 n_robots=10, seed=i % 2, completion_time_s=150.0 + i, mean_travel_m=40.0, max_stretch_m=8.0,
                 lambda2_mean=0.2, **{"radio.preset": preset, "robots.0.count": 10})
            for i, preset in enumerate(["ideal", "ideal", "nrf24", "nrf24"])]
    assert fig9_section(rows, tmp_path) == ([], [])
    assert not (tmp_path / "fig9.png").exists()
    same_radio = [dict(row, **{"radio.preset": "ideal"}) for row in rows]
    lines, files = fig9_section(same_radio, tmp_path)
    assert files == [tmp_path / "fig9.png"] and lines[0].startswith("## Nestmeyer et al. 2017, Fig. 9")


def assert_tables_well_formed(markdown: str) -> None:
    """Every Markdown table has as many cells in each row as in its header (a renderer drops one that does
    not)."""
    block: list[str] = []
    for line in [*markdown.splitlines(), ""]:
        if line.startswith("|"):
            block.append(line)
            continue
        if block:
            cells = [len(row.strip().strip("|").split("|")) for row in block]
            assert len(set(cells)) == 1, block
        block = []
