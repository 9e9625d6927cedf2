"""A run's output folder: written beside ``--out``, moved into place at the end.

A run writes into a staging folder next to its output folder
(``OUT.partial-PID``) and, when it ends (completed, diverged or
interrupted), :meth:`Staging.commit` moves its files into ``OUT``: each file
replaces the one of the same name, and the files an earlier run left that
this run did not write (``plots/timeseries_3.png``, ``video.mp4`` of a run
with video) are removed, so the folder holds one run's files. A run that is
refused or crashes leaves ``OUT`` untouched (:meth:`Staging.discard`). A run
killed outright (SIGKILL) leaves its staging folder: ``progress.json`` (the
last tick's figures) and the recording's segments there are readable.

JSON files are always valid JSON: NaN and infinities become null
(:func:`json_safe`), and :func:`write_json` writes through a temporary file.
"""

from __future__ import annotations

import json
import math
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

from sim.observers import Observer
from sim.strategy import Status

# The files and folders a run writes; a reused output folder loses those of an earlier run.
RUN_FILES = ("metrics.json", "progress.json", "video.mp4", "run.rrd", "plots", "run.rrd.segments")
PARTIAL_SUFFIX = ".partial-"


def json_safe(obj: Any) -> Any:
    """``obj`` with NaN and +-inf replaced by None, numpy scalars and arrays
    as plain Python values (JSON has no NaN)."""
    if isinstance(obj, (float, np.floating)):
        value = float(obj)
        return value if math.isfinite(value) else None
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, np.ndarray):
        return json_safe(obj.tolist())
    if isinstance(obj, dict):
        return {str(k): json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    return obj


def non_finite_fields(obj: Any, prefix: str = "") -> list[str]:
    """Dotted names of the NaN / infinite numbers in a tree of dicts and lists."""
    if isinstance(obj, (float, np.floating)):
        return [] if math.isfinite(float(obj)) else [prefix]
    if isinstance(obj, dict):
        return [name for k, v in obj.items() for name in non_finite_fields(v, f"{prefix}.{k}" if prefix else str(k))]
    if isinstance(obj, (list, tuple)):
        return [name for i, v in enumerate(obj) for name in non_finite_fields(v, f"{prefix}.{i}")]
    return []


def write_json(path: Path, payload: Any) -> None:
    """Write valid JSON (non-finite numbers as null) through a temporary file."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w") as f:
        json.dump(json_safe(payload), f, indent=2, allow_nan=False)
        f.write("\n")
    os.replace(tmp, path)


class Staging:
    """The staging folder of a run whose results go to ``out``."""

    def __init__(self, out: str | Path):
        self.shown = Path(out)  # as the user wrote it, for the paths a run reports
        self.out = self.shown.resolve()  # "." and ".." have no name to put a suffix on
        self.out.parent.mkdir(parents=True, exist_ok=True)
        self.path = self.out.parent / f"{self.out.name}{PARTIAL_SUFFIX}{os.getpid()}"
        if self.path.exists():  # left by an earlier process of the same id
            shutil.rmtree(self.path)
        self.path.mkdir()

    def final(self, name: str) -> str:
        """Where file ``name`` of the staging folder ends up."""
        return str(self.shown / name)

    def commit(self) -> None:
        """Move the staged files into ``out``, replacing an earlier run's."""
        if not self.out.exists():
            os.rename(self.path, self.out)
            return
        staged = {p.name for p in self.path.iterdir()}
        for name in RUN_FILES:
            old = self.out / name
            if name not in staged and (old.exists() or old.is_symlink()):
                _remove(old)
        for name in sorted(staged):
            source, target = self.path / name, self.out / name
            if source.is_dir() and target.exists():
                trash = self.out / f".{name}.old-{os.getpid()}"
                os.rename(target, trash)
                os.rename(source, target)
                _remove(trash)
            else:
                os.replace(source, target)
        self.path.rmdir()

    def discard(self) -> None:
        shutil.rmtree(self.path, ignore_errors=True)


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        path.unlink()


class ProgressFile(Observer):
    """Observer: ``progress.json`` with the latest tick's figures (time,
    tick, links, the strategy's scalars), rewritten every ``period_s`` of
    wall time, so a run killed outright still says how far it got."""

    def __init__(self, path: str | Path, period_s: float = 1.0, clock=None):
        import time

        self.path = Path(path)
        self.period_s = period_s
        self._clock = clock or time.monotonic
        self._next = 0.0
        self._latest: dict[str, Any] = {}

    def on_tick(self, frame) -> None:
        obs = frame.observation
        self._latest = {"status": Status.RUNNING.value, "sim_time_s": obs.time_s, "tick": obs.tick,
                        "links": int(len(obs.links.edges)), **frame.scalars}
        now = self._clock()
        if now >= self._next:
            self._next = now + self.period_s
            write_json(self.path, self._latest)

    def close(self, status: str) -> None:
        write_json(self.path, {**self._latest, "status": str(status)})
