"""Signals to the whole process group, as a terminal's Ctrl-C sends them, and
child processes that die: every phase ends within seconds, exit 130 (or 1
"failed" for a dead child), no traceback from any process, the files
written, no process of the group left (docs/robustness.md).

Each run is a real ``tether run`` in a process group of its own
(``start_new_session``), signalled with ``os.killpg``.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.test_robustness import tiny

REPO = Path(__file__).resolve().parent.parent
ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
EXIT_LIMIT_S = 10.0  # docs/robustness.md promises 5 s; twice that absorbs a loaded test machine (2 CPUs, load 7)
WAIT_LIMIT_S = 20.0  # what a test waits before it calls the run hung (a loaded machine)


class Run:
    """A ``tether run`` in its own process group, its output in files (a pipe could fill)."""

    def __init__(self, tmp_path: Path, *args: str, module: str = "tether.cli"):
        self.out = tmp_path / "out"
        self.log_out, self.log_err = tmp_path / "stdout.txt", tmp_path / "stderr.txt"
        with open(self.log_out, "w") as stdout, open(self.log_err, "w") as stderr:
            self.proc = subprocess.Popen([sys.executable, "-m", module, "run", *args, "--out", str(self.out)],
                                         stdout=stdout, stderr=stderr, env=ENV, cwd=REPO, start_new_session=True)
        self.staging = tmp_path / f"out.partial-{self.proc.pid}"
        self.started = time.monotonic()

    def progress(self) -> dict | None:
        try:
            return json.loads((self.staging / "progress.json").read_text())
        except (OSError, ValueError):
            return None

    def wait_for(self, ready, timeout_s: float = 120.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            assert self.proc.poll() is None, self.output()
            if ready():
                return
            time.sleep(0.05)
        self.kill()
        raise AssertionError("the run never reached the phase")

    def wait_for_entry(self, timeout_s: float = 60.0) -> float:
        """Wait until the process runs tether's code (``tether.entry`` has taken SIGTERM, its last
        handler): the seconds Python's own start-up took. Before that moment (the interpreter and
        ``site``, 40-150 ms here) a Ctrl-C is Python's own KeyboardInterrupt: the one window tether
        cannot reach (docs/robustness.md)."""
        self.wait_for(self.has_handlers, timeout_s)
        return time.monotonic() - self.started

    def has_handlers(self) -> bool:
        """Whether tether's code catches SIGTERM (tether.entry's start, or tether.cli's main once its
        imports are done): a signal from then on is tether's to handle."""
        return signal.SIGTERM in caught_signals(self.proc.pid)

    def ticking(self) -> bool:
        progress = self.progress()
        return bool(progress) and progress["tick"] >= 5

    def signal_group(self, sig: int) -> float:
        """Signal the whole group; the seconds until the run's process exited."""
        sent = time.monotonic()
        os.killpg(self.proc.pid, sig)
        try:
            self.proc.wait(timeout=WAIT_LIMIT_S)
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError(f"no exit {WAIT_LIMIT_S:g} s after {signal.Signals(sig).name}: {self.output()}")
        return time.monotonic() - sent

    def ends_after_killing(self, pid: int, what: str) -> float:
        """SIGKILL ``pid``, one of the run's children (``what``); the seconds until the run's process exited."""
        killed = time.monotonic()
        os.kill(pid, signal.SIGKILL)
        try:
            self.proc.wait(timeout=WAIT_LIMIT_S)
        except subprocess.TimeoutExpired:
            self.kill()
            raise AssertionError(f"the run went on after its {what} died: {self.output()}")
        return time.monotonic() - killed

    def kill(self) -> None:
        try:
            os.killpg(self.proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.proc.wait(timeout=30)

    def output(self) -> str:
        return self.log_out.read_text() + self.log_err.read_text()

    def metrics(self) -> dict:
        return json.loads((self.out / "metrics.json").read_text())

    def assert_clean(self) -> None:
        """No traceback from any process (they share stdout and stderr) and none of the group left."""
        text = self.output()
        assert "Traceback" not in text and "KeyboardInterrupt" not in text, text
        assert group_gone(self.proc.pid), group_members(self.proc.pid)


def caught_signals(pid: int) -> set[int]:
    """The signals ``pid`` has a handler for (``SigCgt`` of /proc/PID/status); empty once it is gone."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return set()
    mask = next((int(line.split()[1], 16) for line in text.splitlines() if line.startswith("SigCgt:")), 0)
    return {sig for sig in range(1, 65) if mask >> (sig - 1) & 1}


def proc_stats():
    """(pid, command, the fields after "pid (comm) ") of every process in /proc."""
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue
        yield int(stat.parent.name), text[text.index("(") + 1:text.rindex(")")], text[text.rindex(")") + 2:].split()


def group_members(pgid: int) -> list[str]:
    """The live (not zombie) processes of group ``pgid``: 'pid command'.

    A zombie is dead; one reparented to a PID 1 that does not reap (a
    container's init) would stay, and ``os.killpg(pgid, 0)`` still finds it."""
    return [f"{pid} {command}" for pid, command, fields in proc_stats() if int(fields[2]) == pgid and fields[0] != "Z"]


def group_gone(pgid: int, timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return True
        if not group_members(pgid):
            return True
        time.sleep(0.1)
    return False


def children(pid: int) -> list[int]:
    """``pid``'s child processes (psutil when installed, else /proc)."""
    try:
        import psutil

        return [child.pid for child in psutil.Process(pid).children()]
    except ImportError:
        return [child for child, _, fields in proc_stats() if int(fields[1]) == pid]


def command(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode()
    except OSError:
        return ""


def renderer_pid(run_pid: int) -> int | None:
    """The video renderer: the run's child whose own child is ffmpeg."""
    for child in children(run_pid):
        if any("ffmpeg" in command(grandchild) for grandchild in children(child)):
            return child
    return None


def helper_pid(run_pid: int) -> int | None:
    """A helper of the video renderer: the renderer's child that is not ffmpeg (nor a zombie)."""
    renderer = renderer_pid(run_pid)
    for child in children(renderer) if renderer is not None else ():
        if "ffmpeg" not in command(child) and command(child):
            return child
    return None


def long_tiny(tmp_path: Path, duration_s: float = 600.0) -> Path:
    return tiny(tmp_path, ("duration_s = 0.1", f"duration_s = {duration_s}"))


VIDEO = ("--video", "--video-size", "160x120", "--video-fps", "10")


def assert_interrupted(run: Run, sig: int, took_s: float) -> dict:
    assert run.proc.returncode == 130, run.output()
    assert took_s < EXIT_LIMIT_S, f"{took_s:.1f} s to exit"
    run.assert_clean()
    metrics = run.metrics()
    assert metrics["status"] == "interrupted" and signal.Signals(sig).name in metrics["message"], metrics["message"]
    assert not run.staging.exists()
    return metrics


# ---------------------------------------------------------------- while ticking

@pytest.mark.parametrize("sig", [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.slow)],
                         ids=["ctrl-c", "sigterm"])
def test_a_signal_to_the_group_while_ticking_ends_the_run_in_seconds(sig, tmp_path):
    run = Run(tmp_path, str(long_tiny(tmp_path)), "--quiet", "--rrd", *VIDEO)
    run.wait_for(run.ticking)
    took = run.signal_group(sig)
    print(f"exit {took:.2f} s after {signal.Signals(sig).name}")
    assert_interrupted(run, sig, took)
    for name in ("video.mp4", "run.rrd", "plots/timeseries.png", "progress.json"):
        assert (run.out / name).is_file(), name


@pytest.mark.slow
def test_ctrl_c_to_the_group_without_video_prints_no_painter_traceback(tmp_path):
    run = Run(tmp_path, str(long_tiny(tmp_path)), "--quiet")
    run.wait_for(run.ticking)
    took = run.signal_group(signal.SIGINT)
    print(f"exit {took:.2f} s after SIGINT")
    assert_interrupted(run, signal.SIGINT, took)
    assert (run.out / "plots" / "timeseries.png").is_file()


# ---------------------------------------------------------------- during set-up

@pytest.mark.parametrize("sig", [signal.SIGTERM, pytest.param(signal.SIGINT, marks=pytest.mark.slow)],
                         ids=["sigterm", "ctrl-c"])
def test_a_signal_during_setup_writes_nothing(sig, tmp_path):
    # While the run builds its world and starts its children (after Python's own start-up: see
    # docs/robustness.md); a slow machine may already tick: then the files are written as when ticking.
    run = Run(tmp_path, str(long_tiny(tmp_path)), "--rrd", *VIDEO)
    run.wait_for(lambda: run.staging.exists() or run.has_handlers() and time.monotonic() - run.started > 2.0)
    took = run.signal_group(sig)
    print(f"exit {took:.2f} s after {signal.Signals(sig).name}")
    assert run.proc.returncode == 130, run.output()
    assert took < EXIT_LIMIT_S, f"{took:.1f} s to exit"
    run.assert_clean()
    assert not run.staging.exists()
    if run.out.exists():  # it was ticking already
        assert run.metrics()["status"] == "interrupted"
    else:
        assert "nothing written" in run.output()


# ---------------------------------------------------------------- while the command starts

@pytest.mark.parametrize("sig", [signal.SIGINT, pytest.param(signal.SIGTERM, marks=pytest.mark.slow)],
                         ids=["ctrl-c", "sigterm"])
def test_a_signal_while_the_libraries_load_prints_one_line(sig, tmp_path):
    # 0.1 s after its entry point took the signals the command is still importing numpy, scipy and MuJoCo
    # (1 s or more): the entry point (python -m tether, as the tether command) takes them before those imports.
    run = Run(tmp_path, str(long_tiny(tmp_path)), "--quiet", module="tether")
    run.wait_for_entry()
    time.sleep(0.1)
    took = run.signal_group(sig)
    assert run.proc.returncode == 130, run.output()
    assert took < EXIT_LIMIT_S
    run.assert_clean()
    lines = run.log_err.read_text().strip().splitlines()
    assert len(lines) == 1 and "interrupted" in lines[0] and "nothing written" in lines[0], lines
    assert not run.out.exists() and not run.staging.exists()


@pytest.mark.slow
def test_ctrl_c_at_any_moment_of_a_short_run_is_clean(tmp_path):
    # Start-up, set-up, ticks, closing and the interpreter's own exit, as the delay grows: every outcome
    # is 0 (the run was over) or 130, never a traceback, a death by the signal (-2) or a staging folder.
    # The delays count from the entry point's first line (tether.entry has taken the signals), 0 s
    # included: Python's own start-up before it is the one window left to Python (docs/robustness.md).
    codes = []
    for index, delay_s in enumerate([0.0, 0.05, 0.4, 0.8, 1.2, 1.6, 2.0, 2.5, 3.0, 4.0]):
        folder = tmp_path / str(index)
        folder.mkdir()
        run = Run(folder, str(tiny(folder)), "--quiet", module="tether")
        run.wait_for_entry()  # (the imports after it take a second or more: it is found running)
        time.sleep(delay_s)
        try:
            os.killpg(run.proc.pid, signal.SIGINT)
        except ProcessLookupError:
            pass
        run.proc.wait(timeout=WAIT_LIMIT_S)
        codes.append(run.proc.returncode)
        assert run.proc.returncode in (0, 130), (delay_s, run.output())
        run.assert_clean()
        assert not run.staging.exists()
        if run.out.exists():
            assert run.metrics()["status"] in ("completed", "interrupted")
    print("exit codes by delay:", codes)


# ---------------------------------------------------------------- while closing

@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_a_signal_while_closing_ends_the_run_in_seconds(sig, tmp_path):
    # A video the renderer cannot keep up with: at the run's end its queue is full and closing takes time.
    run = Run(tmp_path, str(long_tiny(tmp_path, 6.0)), "--quiet", "--video", "--video-size", "1280x720",
              "--video-fps", "60")
    run.wait_for(lambda: (run.progress() or {}).get("status", "running") != "running", timeout_s=300)
    took = run.signal_group(sig)
    print(f"exit {took:.2f} s after {signal.Signals(sig).name}")
    metrics = assert_interrupted(run, sig, took)
    assert "while closing" in metrics["message"] or "as the run ended" in metrics["message"]
    assert (run.out / "video.mp4").is_file()


# ---------------------------------------------------------------- a child that dies

def test_a_killed_video_renderer_ends_the_run_failed(tmp_path):
    run = Run(tmp_path, str(long_tiny(tmp_path)), "--rrd", *VIDEO)
    run.wait_for(lambda: run.ticking() and renderer_pid(run.proc.pid) is not None)
    took = run.ends_after_killing(renderer_pid(run.proc.pid), "renderer")
    print(f"exit {took:.2f} s after the renderer was killed")
    assert took < 10.0
    assert run.proc.returncode == 1, run.output()
    run.assert_clean()
    metrics = run.metrics()
    assert metrics["status"] == "failed"
    assert "video renderer died (exit -9" in metrics["message"], metrics["message"]
    assert "video renderer died" in run.output()
    for name in ("run.rrd", "plots/timeseries.png", "progress.json"):
        assert (run.out / name).is_file(), name
    assert not run.staging.exists()


def test_a_killed_renderer_helper_ends_the_run_failed_naming_it(tmp_path):
    # 160 x 120 at 10 fps: the renderer starts its helpers after 3 s of sim time (HELPERS_AFTER_FRAMES).
    run = Run(tmp_path, str(long_tiny(tmp_path)), *VIDEO)
    run.wait_for(lambda: run.ticking() and helper_pid(run.proc.pid) is not None, timeout_s=120)
    assert run.ends_after_killing(helper_pid(run.proc.pid), "renderer helper") < 10.0
    assert run.proc.returncode == 1, run.output()
    run.assert_clean()
    metrics = run.metrics()
    assert metrics["status"] == "failed"
    assert "video renderer helper 1 died (exit -9" in metrics["message"], metrics["message"]
    assert (run.out / "video.mp4").is_file()
    assert not run.staging.exists()


# ---------------------------------------------------------------- the real scenarios (slow)

@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
@pytest.mark.parametrize("phase", ["setup", "ticks"])
def test_connected_office_with_video_and_recording(phase, sig, tmp_path):
    run = Run(tmp_path, "connected-office", "--duration", "30", "--video", "--rrd")
    if phase == "setup":
        run.wait_for(lambda: run.has_handlers() and time.monotonic() - run.started > 1.5)
    else:
        run.wait_for(run.ticking, timeout_s=300)
    took = run.signal_group(sig)
    print(f"exit {took:.2f} s after {signal.Signals(sig).name}")
    assert run.proc.returncode == 130, run.output()
    assert took < EXIT_LIMIT_S, f"{took:.1f} s to exit"
    run.assert_clean()
    assert not run.staging.exists()
    if phase == "ticks":
        assert_interrupted(run, sig, took)
        assert (run.out / "video.mp4").is_file() and (run.out / "run.rrd").is_file()


@pytest.mark.slow
def test_sigterm_during_intermittent_8_setup_leaves_nothing(tmp_path):
    run = Run(tmp_path, "intermittent-8", "--duration", "30")
    run.wait_for(lambda: run.has_handlers() and time.monotonic() - run.started > 2.0)
    took = run.signal_group(signal.SIGTERM)
    print(f"exit {took:.2f} s after SIGTERM")
    assert run.proc.returncode == 130, run.output()
    assert took < EXIT_LIMIT_S, f"{took:.1f} s to exit"
    run.assert_clean()
    assert not run.staging.exists()
    assert not run.out.exists() or run.metrics()["status"] == "interrupted"


# ---------------------------------------------------------------- a signal the set-up swallows

SWALLOWED = r'''
import ctypes, os, signal, sys, threading, time
from tether import cli

signal.signal(signal.SIGINT, cli._raise_interrupt)
cli._resend.armed, cli._resend.generation = True, 1
if sys.argv[1:] == ["command"]:  # as during a command (cli.main)
    sys.unraisablehook = cli._signals_unraisable(sys.unraisablehook)

def busy():  # Python code called from C: the KeyboardInterrupt raised in it is printed and dropped
    end = time.monotonic() + 1.0
    while time.monotonic() < end:
        pass

threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT)).start()
ctypes.CFUNCTYPE(None)(busy)()
swallowed = time.monotonic()
print("swallowed", flush=True)
try:
    time.sleep(30)  # the set-up going on
except KeyboardInterrupt:
    print(f"interrupted {time.monotonic() - swallowed:.1f} s after", flush=True)
    sys.exit(130)
'''


@pytest.mark.parametrize("hook", ["python", "command"])
def test_a_signal_swallowed_by_a_callback_during_setup_comes_again(hook, tmp_path):
    # A ctypes callback (as a compiled or C library's callback into Python, numba's LLVM object cache in a
    # run's set-up): Python drops the KeyboardInterrupt. The set-up's handler sends the signal again.
    # Python's own hook prints "Exception ignored" and a traceback; a command's (cli.main) prints nothing.
    proc = subprocess.run([sys.executable, "-c", SWALLOWED, hook], env=ENV, cwd=tmp_path, capture_output=True,
                          text=True, timeout=60)
    if hook == "python":
        assert "Exception ignored" in proc.stderr and "KeyboardInterrupt" in proc.stderr, proc.stderr  # really lost
    else:
        assert proc.stderr == "", proc.stderr
    assert proc.returncode == 130, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    assert lines[0] == "swallowed" and lines[1].startswith("interrupted"), lines
    from tether.cli import RESEND_AFTER_S

    assert float(lines[1].split()[1]) < RESEND_AFTER_S + 2.0


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_a_signal_to_the_group_during_intermittent_8_planning_writes_nothing(sig, tmp_path):
    # intermittent-8 plans for seconds before its first tick (numba kernels loading, the geodesic
    # grid, the meeting schedule); the tether command's entry point, as a user runs it.
    run = Run(tmp_path, "intermittent-8", "--duration", "30", module="tether")
    run.wait_for(lambda: run.staging.exists(), timeout_s=60)  # the staging folder: the set-up's last part
    took = run.signal_group(sig)
    print(f"exit {took:.2f} s after {signal.Signals(sig).name}")
    assert run.proc.returncode == 130, run.output()
    assert took < EXIT_LIMIT_S, f"{took:.1f} s to exit"
    run.assert_clean()
    assert not list(tmp_path.glob("out.partial-*"))
    if run.out.exists():  # a fast machine was ticking already
        assert run.metrics()["status"] == "interrupted"
    else:
        lines = [line for line in run.log_err.read_text().splitlines()
                 if line.strip() and not line.startswith(("compiling kernels", "compiled kernels"))]  # a fresh cache
        assert lines == ["tether: interrupted before the run started; nothing written"], lines
