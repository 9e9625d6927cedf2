"""One output policy: tether never deletes or replaces a file it did not write.

Every fault is made to happen for real, in a subprocess of ``tether`` (exit
code, stderr, files): user files in a run's folder survive a run byte for
byte, a folder of foreign files is refused untouched, ``/`` and "" are
refused, names of 250 and 256 characters, a pipe closed early, /dev/full,
and a full disk (a 600 KiB tmpfs, or RLIMIT_FSIZE where mounting fails).
"""

from __future__ import annotations

import json
import os
import resource
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
TIMEOUT_S = 240


def tether(args: list[str], cwd: Path, stdout=subprocess.PIPE, preexec_fn=None) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO), "OPENBLAS_NUM_THREADS": "1", "MUJOCO_GL": "egl"}
    return subprocess.run([sys.executable, "-m", "tether.cli", *args], cwd=cwd, env=env, stdout=stdout,
                          stderr=subprocess.PIPE, text=True, timeout=TIMEOUT_S, preexec_fn=preexec_fn)


def run_hover(out: str, cwd: Path, *extra: str, **kwargs) -> subprocess.CompletedProcess:
    return tether(["run", "hover", "--duration", "0.05", "--out", out, "--quiet", *extra], cwd, **kwargs)


def snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def assert_one_line(proc: subprocess.CompletedProcess, code: int, *words: str) -> str:
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == code, proc.stderr
    assert "Traceback" not in proc.stderr, proc.stderr
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("tether: error: "), lines[0]
    for word in words:
        assert word in lines[0], (word, lines[0])
    return lines[0]


def test_user_files_in_a_runs_folder_survive_runs(tmp_path):
    out = tmp_path / "out"
    assert run_hover("out", tmp_path).returncode == 0
    mine = {"notes.txt": b"my notes\n", "plots/figure1.svg": b"<svg/>", "analysis/a.csv": b"1,2\n"}
    for name, data in mine.items():
        (out / name).parent.mkdir(parents=True, exist_ok=True)
        (out / name).write_bytes(data)
    for extra in (["--video-size", "160x120"], []):  # with video, then without: video.mp4 goes, mine stay
        proc = run_hover("out", tmp_path, *extra)
        assert proc.returncode == 0, proc.stderr
        files = snapshot(out)
        for name, data in mine.items():
            assert files[name] == data
    assert not (out / "video.mp4").exists()
    assert json.loads((out / "metrics.json").read_text())["status"] == "completed"
    assert not list(tmp_path.glob("out.partial-*"))


def test_a_folder_of_foreign_files_is_refused_and_untouched(tmp_path):
    out = tmp_path / "d"
    (out / "plots").mkdir(parents=True)
    (out / "plots" / "figure1.svg").write_text("x\n")
    (out / "video.mp4").write_text("x\n")
    (out / "metrics.json").write_text('{"mine": 1}\n')  # not a run's metrics.json
    before = snapshot(out)
    proc = run_hover("d", tmp_path)
    assert_one_line(proc, 2, "--out", "did not write")
    assert snapshot(out) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]


@pytest.mark.parametrize("command", ["run", "sweep", "report"])
@pytest.mark.parametrize("out", ["/", ""])
def test_root_and_empty_paths_are_refused(command, out, tmp_path):
    args = {"run": ["run", "hover", "--duration", "0.05", "--quiet"], "sweep": ["sweep", "fig9-small"],
            "report": ["report", str(tmp_path)]}[command]
    before = sorted(os.listdir("/"))
    proc = tether([*args, "--out", out], tmp_path)
    assert_one_line(proc, 2, "--out")
    assert sorted(os.listdir("/")) == before and not (tmp_path / "runs").exists()


def test_the_home_folder_is_refused(tmp_path):
    home = tmp_path / "home"
    home.mkdir()
    env_home = {**os.environ, "HOME": str(home)}
    proc = subprocess.run([sys.executable, "-m", "tether.cli", "run", "hover", "--duration", "0.05", "--out",
                           str(home), "--quiet"], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                          text=True, timeout=TIMEOUT_S, env={**env_home, "PYTHONPATH": str(REPO)})
    assert_one_line(proc, 2, "--out", "home")
    assert list(home.iterdir()) == []


def test_a_250_character_name_runs_and_its_staging_name_fits(tmp_path):
    name = "a" * 250
    proc = run_hover(name, tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert (tmp_path / name / "metrics.json").is_file()
    assert sorted(p.name for p in tmp_path.iterdir()) == [name]


@pytest.mark.parametrize("command", ["run", "sweep"])
def test_a_256_character_name_is_refused_in_one_line(command, tmp_path):
    name = "b" * 256
    args = ["run", "hover", "--duration", "0.05", "--quiet"] if command == "run" else ["sweep", "fig9-small"]
    proc = tether([*args, "--out", name], tmp_path)
    assert_one_line(proc, 2, "--out", "256")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("where", ["proc", "under-a-file"])
def test_report_out_that_cannot_be_written_is_one_line(where, tmp_path):
    from tests.test_sweep import fixture_table

    results = tmp_path / "results"
    results.mkdir()
    fixture_table(results)
    (tmp_path / "file").write_text("a file\n")
    out = "/proc/x" if where == "proc" else str(tmp_path / "file" / "sub")
    before = snapshot(tmp_path)
    proc = tether(["report", str(results), "--out", out], tmp_path)
    assert_one_line(proc, 2, "--out")
    assert snapshot(tmp_path) == before


def test_report_out_refuses_a_folder_of_foreign_files_and_reuses_its_own(tmp_path):
    from tests.test_sweep import fixture_table

    results = tmp_path / "results"
    results.mkdir()
    fixture_table(results)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "fig9.png").write_bytes(b"my figure")
    proc = tether(["report", str(results), "--out", str(foreign)], tmp_path)
    assert_one_line(proc, 2, "--out", "did not write")
    assert snapshot(foreign) == {"fig9.png": b"my figure"}
    mine = tmp_path / "report"
    for _ in range(2):  # a new folder, then the report's own folder again
        proc = tether(["report", str(results), "--out", str(mine)], tmp_path)
        assert proc.returncode == 0, proc.stderr
    assert (mine / "report.md").is_file()


def test_a_pipe_closed_early_ends_quietly(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    for args in (["sweep", "fig9", "--list"], ["init", "hover"]):
        proc = subprocess.Popen([sys.executable, "-m", "tether.cli", *args], cwd=tmp_path, env=env,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        first = proc.stdout.readline()  # `| head -1`: read one line, then close the pipe
        proc.stdout.close()
        try:
            err = proc.stderr.read().decode()
            code = proc.wait(timeout=TIMEOUT_S)
        finally:
            proc.kill()
        assert first
        assert code == 0, err
        assert err == "", err


def test_writing_to_dev_full_is_one_line(tmp_path):
    if not os.path.exists("/dev/full"):
        pytest.skip("no /dev/full")
    with open("/dev/full", "w") as full:
        proc = tether(["init", "hover"], tmp_path, stdout=full)
    assert_one_line(proc, 1, "No space left on device")


def _mount_small_tmpfs(folder: Path) -> bool:
    folder.mkdir()
    try:
        done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=600k", "tmpfs", str(folder)],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return False
    return done.returncode == 0


def test_a_full_disk_ends_in_one_line_and_keeps_earlier_results(tmp_path):
    disk = tmp_path / "disk"
    mounted = _mount_small_tmpfs(disk)
    try:
        earlier = disk / "out"
        proc = run_hover(str(tmp_path / "first"), tmp_path)  # an earlier run's files, made where space is
        assert proc.returncode == 0, proc.stderr
        shutil.copytree(tmp_path / "first", earlier)
        (earlier / "notes.txt").write_text("mine\n")
        before = snapshot(earlier)
        limit = None
        if mounted:  # fill the disk but for a few KiB: the plots cannot be written
            stat = os.statvfs(disk)
            free = stat.f_bavail * stat.f_frsize
            (disk / "filler").write_bytes(b"\0" * max(free - 8 * 1024, 0))
        else:  # no mount here: the run may write no file over 4 KiB
            limit = 4 * 1024

        def small_files():
            if limit is not None:
                resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

        proc = run_hover(str(earlier), tmp_path, preexec_fn=small_files)
        assert proc.returncode == 1, proc.stderr
        assert snapshot(earlier) == before
        assert not list(disk.glob("out.partial-*"))
        last = proc.stderr.strip().splitlines()[-1]
        assert last.startswith("tether: error: ") and ("No space left" in last or "too large" in last), last
        assert_one_line(proc, 1)
    finally:
        if mounted:
            subprocess.run(["umount", str(disk)], timeout=30)
