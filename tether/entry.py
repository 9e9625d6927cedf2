"""The ``tether`` command's entry point (``[project.scripts]``, ``python -m
tether``). It imports nothing but the standard library before it has taken
SIGINT and SIGTERM: the command's own modules pull in numpy, scipy and
MuJoCo, a second or two in which Ctrl-C would otherwise end in a
KeyboardInterrupt traceback from the middle of an import. The same holds once
the command has returned and the interpreter is closing (threads joined,
pools' finalizers): the command's files are written by then, and a late
Ctrl-C must not print a traceback over them.

In both windows a signal ends the process at once with one line and exit
130, as Ctrl-C does in every other phase (docs/robustness.md). A SIGINT
ignored from the start (a shell's background job) stays ignored."""

from __future__ import annotations

import atexit
import os
import signal
import sys

EXIT_INTERRUPTED = 130  # as tether.cli.EXIT_INTERRUPTED, not imported from there: that import is the slow part


def _exit_at_once(line: str):
    encoded = f"\n{line}\n".encode()

    def handler(_signum, _frame) -> None:
        try:
            fd = sys.stderr.fileno()  # 2, or its duplicate while a sweep keeps fd 2 from Ray (tether.sweep)
        except (AttributeError, OSError, ValueError):
            fd = 2
        try:
            os.write(fd, encoded)  # no buffer to finish, unlike print
        except OSError:
            pass
        os._exit(EXIT_INTERRUPTED)

    return handler


def _take_signals(line: str) -> None:
    """SIGINT (unless ignored), then SIGTERM: once SIGTERM is caught (``SigCgt`` in
    ``/proc/PID/status``, which Python's own start-up never sets) both are this module's."""
    signals = [signal.SIGTERM]
    if signal.getsignal(signal.SIGINT) is not signal.SIG_IGN:
        signals.insert(0, signal.SIGINT)
    for sig in signals:
        signal.signal(sig, _exit_at_once(line))


def _flush() -> None:
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):
            pass


def main() -> None:
    """Run the command and end the process with its exit code. The closing
    work (the pools' finalizers, Ray's shutdown, whatever registered with
    atexit) runs here under the closing handler; then the process ends with
    ``os._exit``, skipping the interpreter's own finalization, where CPython
    puts SIGINT back to its default action (a silent death, exit -2)."""
    _take_signals("tether: interrupted while starting; nothing written")
    from tether.cli import main as command  # installs its own handlers for the command's phases

    end_process(command())


def end_process(code: int) -> None:
    """Run the atexit work under the closing handler, then end with ``code`` (``os._exit``: the
    interpreter's finalization collects nothing, so no object's ``__del__`` can wait there either,
    e.g. a library's stream that waits on a failed writer). ``python -m tether.cli`` ends here too."""
    _flush()
    _take_signals("tether: interrupted while closing; the files above are written")
    atexit._run_exitfuncs()
    _flush()
    os._exit(code)
