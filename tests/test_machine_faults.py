"""Faults of the machine, made for real against ``tether sweep`` and the Ray
connection (docs/robustness.md): signals to the driver or its whole process
group, two drivers in one folder, a full disk (a small tmpfs), a port that
listens but is not Ray. Each asserts the exit code, one line, no traceback, a
bounded wait and the files.
"""

from __future__ import annotations

import http.server
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest

from tests.test_signals import group_gone, group_members

REPO = Path(__file__).resolve().parents[1]
ENV = {**os.environ, "PYTHONPATH": str(REPO), "OPENBLAS_NUM_THREADS": "1", "MUJOCO_GL": "egl"}
EXIT_LIMIT_S = 15.0  # a driver stops within 1-2 s; the rest absorbs a loaded machine
WAIT_S = 180.0


def sweep_file(folder: Path, body: str = "seeds = 40\n", duration_s: float = 2.0) -> Path:
    path = folder / "s.toml"
    path.write_text(f'scenario = "hover"\nduration_s = {duration_s}\n{body}')
    return path


class Driver:
    """``tether sweep`` in a process group of its own, its output in files."""

    def __init__(self, folder: Path, *args: str, name: str = "driver"):
        self.err_path, self.out_path = folder / f"{name}.err", folder / f"{name}.out"
        with open(self.out_path, "w") as out, open(self.err_path, "w") as err:
            self.proc = subprocess.Popen([sys.executable, "-m", "tether", "sweep", *args], cwd=folder, env=ENV,
                                         stdout=out, stderr=err, start_new_session=True)

    def wait(self, timeout: float = WAIT_S) -> int:
        try:
            return self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait()
            raise AssertionError(f"no exit within {timeout:g} s: {self.output()}") from None

    def output(self) -> str:
        return self.out_path.read_text() + self.err_path.read_text()

    def stored(self, out: Path) -> int:
        return len(list((out / "trials").glob("*.parquet"))) if (out / "trials").is_dir() else 0


def wait_until(ready, driver: Driver, timeout: float = WAIT_S) -> None:
    deadline = time.monotonic() + timeout
    while not ready():
        assert driver.proc.poll() is None, driver.output()
        assert time.monotonic() < deadline, driver.output()
        time.sleep(0.1)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["sigterm", "ctrl-c"])
@pytest.mark.parametrize("to_group", [False, True], ids=["driver", "group"])
def test_a_signal_stops_the_sweep_with_its_summary_and_table(sig, to_group, tmp_path):
    driver = Driver(tmp_path, str(sweep_file(tmp_path)), "--out", "out", "--workers", "2", "--no-report")
    out = tmp_path / "out"
    wait_until(lambda: driver.stored(out) >= 2, driver)
    sent = time.monotonic()
    (os.killpg if to_group else os.kill)(driver.proc.pid, sig)
    code = driver.wait()
    took = time.monotonic() - sent
    text = driver.output()
    assert code == 130, text
    assert took < EXIT_LIMIT_S, f"{took:.1f} s to stop"
    assert "Traceback" not in text and "leaked" not in text, text
    assert "stopped: interrupted; run the same command again to resume" in text
    summary = [line for line in driver.out_path.read_text().splitlines() if line.startswith("s: ")]
    assert len(summary) == 1 and "not run of 40" in summary[0], text
    rows = pq.read_table(out / "results.parquet")
    assert rows.num_rows >= 2 and set(rows.column("status").to_pylist()) <= {"completed", "interrupted"}
    assert group_gone(driver.proc.pid), group_members(driver.proc.pid)
    assert not list((out / "trials").glob(".*.tmp"))


def test_a_signal_early_in_a_sweep_is_an_interrupt(tmp_path):
    """SIGTERM while the driver imports, loads and checks 100,000 trials (or, on a fast machine, has
    just claimed the folder) is Ctrl-C there too: exit 130, no traceback, nothing half-written."""
    driver = Driver(tmp_path, str(sweep_file(tmp_path, 'seeds = 100000\n[grid]\n"strategy.speed_mps" = [0.3]\n')),
                    "--out", "out")
    time.sleep(1.5)
    assert driver.proc.poll() is None, driver.output()
    os.killpg(driver.proc.pid, signal.SIGTERM)
    assert driver.wait(timeout=EXIT_LIMIT_S) == 130, driver.output()
    assert "Traceback" not in driver.output() and "interrupted" in driver.output()
    out = tmp_path / "out"
    assert not out.exists() or (out / "sweep.json").is_file(), sorted(p.name for p in out.iterdir())
    assert group_gone(driver.proc.pid), group_members(driver.proc.pid)


def _forkserver_started(pid: int) -> bool:
    """Whether ``pid`` has started its pool's forkserver (the workers are being started from then on)."""
    from tests.test_signals import children, command

    return any("forkserver" in command(child) for child in children(pid))


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_a_signal_while_the_pool_starts_its_workers_is_clean(sig, tmp_path):
    """The group's signal as the pool's forkserver appears: the workers are being started and open the
    pool's queues by name. It is held until each is started and known to the pool, which kills them:
    exit 130, no worker's bootstrap traceback, no process of the group left."""
    driver = Driver(tmp_path, str(sweep_file(tmp_path, "seeds = 4\n", 2.0)), "--out", "out", "--workers", "2",
                    "--no-report")
    wait_until(lambda: _forkserver_started(driver.proc.pid), driver, timeout=120)
    os.killpg(driver.proc.pid, sig)
    code = driver.wait(timeout=60)
    text = driver.output()
    assert code == 130, text
    assert "Traceback" not in text and "leaked" not in text and "Error" not in text, text
    assert group_gone(driver.proc.pid), group_members(driver.proc.pid)


def test_a_second_driver_in_the_folder_is_refused(tmp_path):
    from tether.sweep import ResultsFolder

    first = Driver(tmp_path, str(sweep_file(tmp_path, "seeds = 40\n", 2.0)), "--out", "out", "--workers", "1",
                   "--no-report")
    out = tmp_path / "out"
    wait_until(lambda: (out / "sweep.json").exists(), first)
    second = subprocess.run([sys.executable, "-m", "tether.cli", "sweep", "s.toml", "--out", "out", "--workers", "1"],
                            cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=WAIT_S)
    lines = second.stderr.strip().splitlines()
    assert second.returncode == 2 and len(lines) == 1 and "Traceback" not in second.stderr, second.stderr
    assert "in use by another tether sweep" in lines[0] and str(first.proc.pid) in lines[0]
    assert first.proc.poll() is None, first.output()
    os.kill(first.proc.pid, signal.SIGTERM)
    assert first.wait() == 130, first.output()
    assert not list((out / "trials").glob("*.a2.parquet"))  # no trial ran twice
    folder = ResultsFolder(out)
    folder._lock()  # the lock went with the first driver
    folder.release()


def _mount_small_tmpfs(folder: Path) -> bool:
    folder.mkdir()
    try:
        return subprocess.run(["mount", "-t", "tmpfs", "-o", "size=600k", "tmpfs", str(folder)],
                              capture_output=True, timeout=30).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


@pytest.fixture
def full_disk(tmp_path):
    """A 600 KiB tmpfs with ``request.param`` KiB left free (skips where mounting is not allowed)."""
    disk = tmp_path / "disk"
    if not _mount_small_tmpfs(disk):
        pytest.skip("cannot mount a tmpfs here")
    try:
        yield disk
    finally:
        subprocess.run(["umount", str(disk)], timeout=30)


@pytest.mark.parametrize("free_kib, path", [(0, "sweep.json"), (10, "trials/")], ids=["claim", "store"])
def test_a_full_disk_in_a_sweep_is_one_line_and_the_rerun_is_accepted(free_kib, path, full_disk, tmp_path):
    filler = full_disk / "filler"
    with open(filler, "wb") as f:
        try:
            f.write(b"\0" * ((600 - free_kib) * 1024))
        except OSError:
            pass
    sweep = sweep_file(tmp_path, "seeds = 2\n", 0.05)
    out = full_disk / "sw"
    proc = subprocess.run([sys.executable, "-m", "tether.cli", "sweep", str(sweep), "--out", str(out), "--workers",
                           "1", "--no-report"], cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=WAIT_S)
    errors = [line for line in proc.stderr.splitlines() if line.startswith("tether: error:")]
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert len(errors) == 1 and f"cannot write {out}/{path}" in errors[0] and "No space left" in errors[0], errors
    assert not [p for p in out.rglob(".*.tmp")]
    filler.unlink()
    again = subprocess.run([sys.executable, "-m", "tether.cli", "sweep", str(sweep), "--out", str(out), "--workers",
                            "1", "--no-report"], cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=WAIT_S)
    assert again.returncode == 0 and "2 finished" in again.stdout, again.stderr


# ---------------------------------------------------------------- a port that is not Ray

class _Listener:
    """A TCP port on 127.0.0.1 that accepts and then does ``answer`` (bytes to send, or None: nothing)."""

    def __init__(self, answer: bytes | None):
        import socket

        self.sock = socket.socket()
        self.sock.bind(("127.0.0.1", 0))
        self.sock.listen(16)
        self.port = self.sock.getsockname()[1]
        self.answer, self.clients = answer, []
        threading.Thread(target=self._serve, daemon=True).start()

    def _serve(self) -> None:
        while True:
            try:
                client, _ = self.sock.accept()
            except OSError:
                return
            if self.answer:
                client.sendall(self.answer)
            self.clients.append(client)  # held open: a port that says nothing more

    def close(self) -> None:
        self.sock.close()
        for client in self.clients:
            client.close()


@pytest.fixture
def http_port():
    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), http.server.SimpleHTTPRequestHandler)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    yield server.server_address[1]
    server.shutdown()
    server.server_close()


def _ray_sweep(tmp_path: Path, port: int) -> subprocess.CompletedProcess:
    pytest.importorskip("ray")
    sweep = sweep_file(tmp_path, "seeds = 2\n", 0.05)
    start = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "tether.cli", "sweep", str(sweep), "--out", "out", "--ray",
                           f"127.0.0.1:{port}"], cwd=tmp_path, env=ENV, capture_output=True, text=True,
                          timeout=WAIT_S)
    proc.took_s = time.monotonic() - start
    errors = [line for line in proc.stderr.splitlines() if line.startswith("tether: error:")]
    assert proc.returncode == 2 and "Traceback" not in proc.stderr and len(errors) == 1, proc.stderr
    assert not (tmp_path / "out").exists()
    proc.error = errors[0]
    return proc


def test_an_http_server_on_the_ray_port_is_not_a_ray_cluster(http_port, tmp_path):
    proc = _ray_sweep(tmp_path, http_port)
    assert "is not a Ray cluster" in proc.error and "HTTP" in proc.error, proc.error
    assert proc.took_s < 30 and proc.stderr.strip() == proc.error


def test_a_port_that_says_nothing_is_not_a_ray_cluster(tmp_path):
    listener = _Listener(None)
    try:
        proc = _ray_sweep(tmp_path, listener.port)
    finally:
        listener.close()
    assert "is not a Ray cluster: it said nothing" in proc.error and proc.took_s < 30


@pytest.mark.slow
def test_a_grpc_port_that_is_not_ray_ends_in_a_minute(tmp_path):
    """Answers HTTP/2's SETTINGS, then nothing: ray.init would retry for ever; its timeout ends the sweep."""
    from tether.sweep import RAY_INIT_TIMEOUT_S

    listener = _Listener(b"\x00\x00\x00\x04\x00\x00\x00\x00\x00")
    try:
        proc = _ray_sweep(tmp_path, listener.port)
    finally:
        listener.close()
    assert "ray.init had not connected within" in proc.error
    assert RAY_INIT_TIMEOUT_S <= proc.took_s < RAY_INIT_TIMEOUT_S + 60


def _ray_head_group(address: str) -> int:
    """The process group of ``ray start --head`` on ``address``'s port (local_ray_cluster's own group)."""
    port = address.rpartition(":")[2]
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            words = cmdline.read_bytes().split(b"\0")
        except OSError:
            continue
        if b"start" in words and b"--head" in words and f"--port={port}".encode() in words:
            return os.getpgid(int(cmdline.parent.name))
    raise AssertionError(f"no ray start --head on port {port}")


def test_ray_core_logs_are_kept_off_the_sweeps_stderr(tmp_path):
    """What RayCluster does while Ray's core worker lives in the driver (its C++ writes ERROR records to
    file descriptor 2 at any moment, e.g. when a raylet dies): fd 2 goes aside, Python's stderr and the
    entry point's signal line still reach the terminal, and fd 2 is back once the engine closes. Made
    with the real file descriptors in a process of its own (a raylet's death writes the record only
    sometimes: the test above kills one for real)."""
    script = tmp_path / "aside.py"
    script.write_text(
        "import os, sys\n"
        "from tether.sweep import _CoreLogsAside\n"
        "aside = _CoreLogsAside()\n"
        "os.write(2, b'[2026-01-01 00:00:00,000 E 1 2] task_manager.cc:1545: Failed to push error\\n')\n"
        "print('python line', file=sys.stderr)\n"
        "aside.restore()\n"
        "os.write(2, b'fd 2 again\\n')\n"
        "aside = _CoreLogsAside()\n"
        "from tether.entry import _take_signals\n"
        "_take_signals('tether: interrupted while closing')\n"
        "import signal; signal.raise_signal(signal.SIGTERM)\n")
    proc = subprocess.run([sys.executable, str(script)], env=ENV, cwd=tmp_path, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 130, proc.stderr
    assert proc.stderr.split() == "python line fd 2 again tether: interrupted while closing".split(), proc.stderr


def _raylet(temp_dir: Path) -> int:
    """The raylet of the local cluster whose temporary folder is ``temp_dir``."""
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            words = cmdline.read_bytes().split(b"\0")
        except OSError:
            continue
        if words[0].endswith(b"/raylet") and any(str(temp_dir).encode() in word for word in words):
            return int(cmdline.parent.name)
    raise AssertionError(f"no raylet under {temp_dir}")


@pytest.mark.slow
@pytest.mark.parametrize("killed", ["head", "raylet"])
def test_a_killed_ray_head_stops_the_sweep_in_seconds_with_one_line(killed, tmp_path, tmp_path_factory):
    """Every process of the head killed mid-sweep (SIGKILL to its group), or its raylet alone: Ray itself
    would notice after a minute and end the process with its own lines (or, for a raylet, ~47 lines of its
    state), and its core worker in the driver writes its ERROR records to file descriptor 2 (``Failed to
    push error to driver``); the driver notices within seconds, prints its summary and one line, keeps its
    rows, and the sweep resumes."""
    pytest.importorskip("ray")
    from tether.sweep import local_ray_cluster

    # Enough trials that the sweep is still running when the cluster is killed (a 2 s hover trial takes
    # well under a second once its kernels are cached: six of them ended before the kill).
    sweep = sweep_file(tmp_path, "seeds = 30\n", 2.0)
    out = tmp_path / "out"
    temp_dir = tmp_path_factory.mktemp("ray")
    with local_ray_cluster(num_cpus=1, temp_dir=temp_dir) as address:
        driver = Driver(tmp_path, str(sweep), "--out", "out", "--ray", address, "--no-report")
        wait_until(lambda: driver.stored(out) >= 2, driver)
        killed_at = time.monotonic()
        if killed == "head":
            os.killpg(_ray_head_group(address), signal.SIGKILL)
        else:
            os.kill(_raylet(temp_dir), signal.SIGKILL)
        code = driver.wait(timeout=60)
        took = time.monotonic() - killed_at
    text = driver.output()
    print(f"exit {code} {took:.1f} s after the {killed} was killed")
    assert code == 1, text
    assert took < 20.0, f"{took:.1f} s to stop"  # ~2 s to notice, ray.shutdown bounded at 10 s
    assert "Traceback" not in text and "state-dump" not in text and "raylet" not in text, text
    assert ".cc:" not in text, text  # no record of Ray's C++ logging (they are in the session's logs/)
    progress = re.compile(r"  s: \d+/30 trials, ")
    lines = [line for line in driver.err_path.read_text().splitlines() if not progress.match(line)]
    assert lines == [f"stopped: the Ray cluster at {address} is gone; run the same command again to resume"], text
    summary = driver.out_path.read_text().strip().splitlines()
    assert len(summary) == 1 and summary[0].startswith("s: ") and "not run of 30" in summary[0], text
    rows = pq.read_table(out / "results.parquet")
    assert rows.num_rows == driver.stored(out) >= 2
    assert set(rows.column("status").to_pylist()) == {"completed"}  # the trials cut off have no row
    again = _tether(["sweep", str(sweep), "--out", "out", "--workers", "2", "--no-report"], tmp_path)
    assert again.returncode == 0 and "30 finished" in again.stdout, again.stdout + again.stderr
    assert pq.read_table(out / "results.parquet").num_rows == 30


# ---------------------------------------------------------------- files cut short, names that clash

def _tether(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "tether.cli", *args], cwd=cwd, env=ENV, capture_output=True,
                          text=True, timeout=WAIT_S)


def test_a_trial_row_cut_short_says_to_delete_it_and_report_uses_the_table(tmp_path):
    sweep = sweep_file(tmp_path, "seeds = 2\n", 0.05)
    assert _tether(["sweep", str(sweep), "--out", "out", "--workers", "1", "--no-report"], tmp_path).returncode == 0
    row = sorted((tmp_path / "out" / "trials").glob("*.parquet"))[0]
    row.write_bytes(row.read_bytes()[:100])  # as a full disk or an interrupted copy leaves it
    proc = _tether(["sweep", str(sweep), "--out", "out", "--workers", "1", "--no-report"], tmp_path)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert row.name in lines[0] and "delete it and run the same command again" in lines[0]
    report = _tether(["report", "out"], tmp_path)  # results.parquet holds every row
    assert report.returncode == 0 and "Traceback" not in report.stderr, report.stderr
    assert (tmp_path / "out" / "report.md").is_file()
    row.unlink()
    again = _tether(["sweep", str(sweep), "--out", "out", "--workers", "1", "--no-report"], tmp_path)
    assert again.returncode == 0 and "2 finished" in again.stdout, again.stderr


def test_a_scene_body_named_like_a_robot_is_one_line(tmp_path):
    scene = (REPO / "models" / "scenes" / "empty.xml").read_text().replace(
        '<camera name="top"', '<body name="quad0/base" pos="40 60 1"><geom type="box" size="0.2 0.2 0.2"/></body>'
                              '<camera name="top"')
    (tmp_path / "clash.xml").write_text(scene)
    proc = _tether(["run", "hover", "--scene", "clash.xml", "--duration", "0.05", "--out", "out", "--quiet"],
                   tmp_path)
    errors = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(errors) == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert errors[0].startswith("tether: error: scene: clash.xml: repeated name 'quad0/base'"), errors[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["clash.xml"]


def test_a_full_disk_under_a_recording_ends_the_run_failed(full_disk, tmp_path):
    """556 KiB free: the recording's segments fit, merging them into run.rrd would not. The merge is
    refused before it writes (Rerun's writer, once it has failed, waits for ever in a flush), the
    partial recording is removed, the run ends "failed" naming ENOSPC, metrics.json and the plots are
    written, no Rust log line, no traceback, no hang."""
    (full_disk / "filler").write_bytes(b"\0" * 44 * 1024)
    start = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "tether.cli", "run", "hover", "--duration", "20", "--rrd", "--out",
                           str(full_disk / "r")], cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=120)
    took = time.monotonic() - start
    print(f"exit {proc.returncode} in {took:.1f} s")
    assert proc.returncode == 1 and "Traceback" not in proc.stderr, proc.stderr
    assert took < 90.0
    noise = [line for line in proc.stderr.splitlines() if not line.startswith("  t = ")]
    assert noise == [], noise  # Rerun's Rust lines (ERROR re_log_encoding ...) included
    metrics = json.loads((full_disk / "r" / "metrics.json").read_text())
    assert metrics["status"] == "failed", metrics["message"]
    assert "recording failed, run.rrd not written: No space left on device" in metrics["message"]
    assert "(ENOSPC)" in metrics["message"]
    assert (full_disk / "r" / "plots" / "timeseries.png").is_file()
    assert not (full_disk / "r" / "run.rrd").exists() and not (full_disk / "r" / "run.rrd.segments").exists()
    assert "open the recording" not in proc.stdout and proc.stdout.startswith("failed: hover"), proc.stdout
    assert sorted(p.name for p in full_disk.iterdir()) == ["filler", "r"]


API_FULL_DISK = r'''
import gc, sys, time
import rerun as rr
import tether.catalog  # noqa: F401  (the built-in scenarios)
from sim.scenario import load
from tether.runner import run

if __name__ == "__main__":  # (the plot painters are spawned: they import this file)
    result = run(load("hover", duration_s=20.0), sys.argv[1], rrd=True)
    print(result.status.value, result.metrics["message"], flush=True)
    del result
    gc.collect()
    streams = [o for o in gc.get_objects() if isinstance(o, rr.RecordingStream)]
    print("streams", len(streams), flush=True)
'''


def test_a_full_disk_under_a_recording_from_the_runner_api_leaves_no_stream(full_disk, tmp_path):
    """tether.runner.run from Python (no CLI, no os._exit at the end): the recording given up on a full
    disk releases its stream; the interpreter then exits as any script does, its finalization included
    (a Rerun stream whose own file writer had failed would wait for ever there)."""
    (full_disk / "filler").write_bytes(b"\0" * 44 * 1024)
    script = tmp_path / "api.py"
    script.write_text(API_FULL_DISK)
    proc = subprocess.run([sys.executable, str(script), str(full_disk / "r")], cwd=tmp_path, env=ENV,
                          capture_output=True, text=True, timeout=150)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    assert len(lines) == 2 and lines[0].startswith("failed "), lines
    assert "recording failed, run.rrd not written: No space left on device" in lines[0], lines  # a segment or
    assert "(ENOSPC)" in lines[0], lines  # the merge that did not fit
    assert lines[1] == "streams 0", lines
    assert "Traceback" not in proc.stderr, proc.stderr
    assert not (full_disk / "r" / "run.rrd").exists() and not (full_disk / "r" / "run.rrd.segments").exists()
