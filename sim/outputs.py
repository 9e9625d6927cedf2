"""Where tether writes: one output policy, and a run's staging folder.

**The policy** (:func:`check_out_folder`, :func:`check_out_file`): tether
never deletes or replaces a file it did not write. An output folder is
accepted when it does not exist, is empty, or is one tether wrote for the
same purpose: a run's folder holds ``.tether-files.json`` (the manifest of
the files the run wrote) or, from before the manifest, a ``metrics.json``
with ``scenario`` and ``status`` keys; a report's folder holds the manifest
(kind ``report``) or a sweep's results. Anything else is refused (ConfigError
naming the flag; nothing written). ``/``, the home folder and an empty path
are refused; so is a name longer than the file system allows. A single
output file (the tuning page's TOML) may replace only a file tether wrote
(its first line is tether's header).

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

import contextlib
import errno
import json
import math
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from sim.config import ConfigError
from sim.observers import Observer
from sim.strategy import Status

# The files and folders a run writes; a reused output folder loses those of an earlier run.
RUN_FILES = ("metrics.json", "progress.json", "video.mp4", "run.rrd", "plots", "run.rrd.segments")
PARTIAL_SUFFIX = ".partial-"
MANIFEST = ".tether-files.json"  # what tether wrote into a folder: {"format", "kind", "files"}
MANIFEST_FORMAT = "tether-files/1"
LEGACY_PLOT_PREFIX = "timeseries"  # plots/ files of a run from before the manifest
SAVED_TOML_MARKERS = ("# tether scenario",)  # first line of a TOML tether wrote
SWEEP_MARKERS = ("sweep.json", "results.parquet", "trials")
DEFAULT_NAME_MAX = 255


# ---------------------------------------------------------------- the policy

def name_max(folder: Path) -> int:
    """The longest file name the file system under ``folder`` (nearest existing) allows."""
    try:
        return int(os.pathconf(_nearest_existing(folder), "PC_NAME_MAX"))
    except (OSError, ValueError):
        return DEFAULT_NAME_MAX


def _nearest_existing(path: Path) -> Path:
    path = Path(path).absolute()
    while not path.exists() and path != path.parent:
        path = path.parent
    return path


def check_out_path(out: str | Path | None, flag: str = "--out") -> Path:
    """ConfigError for a path no output may go to: empty, ``/``, the home
    folder itself, or a name longer than the file system allows. Returns
    the path."""
    if out is None or str(out).strip() == "":
        raise ConfigError(flag, "is empty: name a new or empty folder")
    path = Path(out)
    resolved = path.absolute()
    try:
        resolved = path.resolve()
    except (OSError, RuntimeError):
        pass
    if resolved == Path(resolved.anchor):
        raise ConfigError(flag, f"{out} is the root folder: name a new or empty folder under it")
    home = Path(os.path.expanduser("~"))
    if home != Path(home.anchor) and resolved == home.resolve():
        raise ConfigError(flag, f"{out} is the home folder: name a new or empty folder under it")
    limit = name_max(resolved.parent)
    for part in resolved.parts:
        if len(os.fsencode(part)) > limit:
            raise ConfigError(flag, f"a name in {flag} is {len(os.fsencode(part))} bytes long; this file system "
                                    f"allows {limit}: choose a shorter name")
    if len(os.fsencode(str(resolved))) >= 4000:
        raise ConfigError(flag, "the path is too long: choose a shorter one")
    return path


def read_manifest(folder: Path) -> dict | None:
    """The folder's manifest (a dict with ``kind`` and ``files``), None if absent or not tether's."""
    try:
        manifest = json.loads((Path(folder) / MANIFEST).read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return None
    if not isinstance(manifest, dict) or manifest.get("format") != MANIFEST_FORMAT:
        return None
    files = manifest.get("files")
    if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
        return None
    return manifest


def _legacy_run(folder: Path) -> bool:
    """A run's folder from before the manifest: metrics.json with scenario and status."""
    try:
        metrics = json.loads((folder / "metrics.json").read_text())
    except (OSError, UnicodeDecodeError, ValueError):
        return False
    return isinstance(metrics, dict) and "scenario" in metrics and "status" in metrics


def written_by_tether(folder: str | Path, kind: str) -> bool:
    """Whether ``folder`` is one tether wrote for ``kind`` ("run" or "report")."""
    folder = Path(folder)
    manifest = read_manifest(folder)
    if manifest is not None:
        return manifest.get("kind") == kind or (kind == "report" and _holds_sweep(folder))
    if kind == "run":
        return _legacy_run(folder)
    return _holds_sweep(folder)


def _holds_sweep(folder: Path) -> bool:
    return any((folder / name).exists() for name in SWEEP_MARKERS)


def previous_files(folder: Path, kind: str = "run") -> set[str]:
    """The files (relative, POSIX) an earlier ``kind`` output wrote into ``folder``."""
    manifest = read_manifest(folder)
    if manifest is not None and manifest.get("kind") == kind:
        return set(manifest["files"])
    if kind == "run" and _legacy_run(folder):
        names = {n for n in RUN_FILES if n != "plots" and (folder / n).is_file()}
        plots = folder / "plots"
        if plots.is_dir():
            names |= {f"plots/{p.name}" for p in plots.iterdir()
                      if p.is_file() and p.name.startswith(LEGACY_PLOT_PREFIX) and p.suffix == ".png"}
        return names
    return set()


def check_out_folder(out: str | Path | None, kind: str = "run", flag: str = "--out") -> Path:
    """ConfigError unless ``out`` may receive a ``kind`` output: it does not
    exist, is empty, or is a folder tether wrote for ``kind`` (see the module
    docstring); and it can be written. Leaves nothing behind (one empty probe
    folder is created and removed)."""
    out = check_out_path(out, flag)
    if out.exists() and not out.is_dir():
        raise ConfigError(flag, f"{out} exists and is not a folder")
    if out.is_dir():
        if not os.access(out, os.W_OK | os.X_OK):
            raise ConfigError(flag, f"{out} is not writable")
        try:
            entries = sorted(p.name for p in out.iterdir())
        except OSError as err:
            raise ConfigError(flag, f"cannot read {out}: {err.strerror or err}") from None
        if entries and not written_by_tether(out, kind):
            what = "a tether run" if kind == "run" else "a tether report or sweep"
            raise ConfigError(flag, f"{out} holds files tether did not write ({', '.join(entries[:3])}"
                                    f"{', ...' if len(entries) > 3 else ''}) and is not {what}'s folder: "
                                    "choose a new or empty folder")
    existing = out.absolute().parent
    while not existing.exists():
        existing = existing.parent
    if not existing.is_dir():
        raise ConfigError(flag, f"{out} lies under {existing}, which is a file, not a folder")
    try:  # os.access says yes to root everywhere; only trying tells (read-only mounts, /proc)
        os.rmdir(tempfile.mkdtemp(prefix=".tp-", dir=existing))
    except OSError as err:
        raise ConfigError(flag, f"cannot write {out}: {existing}: {err.strerror or err}") from None
    return out


def check_out_file(path: str | Path | None, flag: str) -> Path:
    """ConfigError unless file ``path`` may be written: new, or a file tether
    wrote (its first line is one of ``SAVED_TOML_MARKERS``)."""
    path = check_out_path(path, flag)
    if path.is_dir():
        raise ConfigError(flag, f"{path} is a folder, not a file")
    if path.exists() or path.is_symlink():
        try:
            with open(path, "rb") as f:
                first = f.readline(200).decode("utf-8", "replace")
        except OSError as err:
            raise ConfigError(flag, f"cannot read {path}: {err.strerror or err}") from None
        if not path.is_file() or not first.startswith(SAVED_TOML_MARKERS):
            raise ConfigError(flag, f"{path} exists and tether did not write it: choose a new file name")
    existing = _nearest_existing(path.absolute().parent)
    if not existing.is_dir():
        raise ConfigError(flag, f"{path} lies under {existing}, which is a file, not a folder")
    return path


def write_manifest(folder: Path, kind: str, files: set[str] | list[str]) -> None:
    write_json(Path(folder) / MANIFEST, {"format": MANIFEST_FORMAT, "kind": kind, "files": sorted(set(files) | {MANIFEST})})


def _tree(folder: Path) -> set[str]:
    """Files under ``folder``, relative POSIX paths."""
    return {p.relative_to(folder).as_posix() for p in folder.rglob("*") if p.is_file() or p.is_symlink()}


def staging_name(out: Path, pid: int | None = None) -> str:
    """``OUT.partial-PID``, its ``OUT`` part shortened to fit the file system's name limit."""
    suffix = f"{PARTIAL_SUFFIX}{os.getpid() if pid is None else pid}"
    name = out.name
    limit = name_max(out.parent) - len(os.fsencode(suffix))
    while len(os.fsencode(name)) > limit:
        name = name[:-1]
    return f"{name}{suffix}"


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


SPACE_PROBE_BYTES = 64 * 1024  # written to tell a full disk from another failure of a writer


def no_space_left(folder: Path) -> bool:
    """Whether ``folder``'s file system refuses SPACE_PROBE_BYTES more (tried, not guessed from
    statvfs: reserved blocks and quotas count too). For a writer (Rerun's, a child's encoder) that
    stopped without saying why."""
    probe = Path(folder) / f".space-probe-{os.getpid()}"
    try:
        with open(probe, "wb") as f:
            f.write(b"\0" * SPACE_PROBE_BYTES)
            f.flush()
            os.fsync(f.fileno())
        return False
    except OSError as err:
        return err.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG)
    finally:
        with contextlib.suppress(OSError):
            probe.unlink()


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
        self.path = self.out.parent / staging_name(self.out)
        if self.path.exists():  # left by an earlier process of the same id
            shutil.rmtree(self.path)
        self.path.mkdir()

    def final(self, name: str) -> str:
        """Where file ``name`` of the staging folder ends up."""
        return str(self.shown / name)

    def commit(self) -> None:
        """Move the staged files into ``out``: each replaces the one of the
        same name, and the files the earlier run wrote (its manifest) that
        this run did not are removed; any other file stays."""
        staged = _tree(self.path) - {MANIFEST}
        write_manifest(self.path, "run", staged | {MANIFEST})  # before anything moves (a full disk stops here)
        if not self.out.exists():
            os.rename(self.path, self.out)
            return
        if not written_by_tether(self.out, "run") and any(self.out.iterdir()):
            raise ConfigError("--out", f"{self.out} now holds files tether did not write: nothing was moved "
                                       "into it; choose a new or empty folder")
        for name in sorted(previous_files(self.out) - staged - {MANIFEST}):
            old = self.out / name
            if old.is_file() or old.is_symlink():
                old.unlink()
        for name in ("plots", "run.rrd.segments"):  # folders the run made, if now empty
            folder = self.out / name
            if folder.is_dir() and not folder.is_symlink() and not any(folder.iterdir()):
                folder.rmdir()
        for name in sorted(staged):
            source, target = self.path / name, self.out / name
            if target.parent != self.out:
                if target.parent.is_symlink() or (target.parent.exists() and not target.parent.is_dir()):
                    raise ConfigError("--out", f"{target.parent} is not a folder: choose a new or empty "
                                               "folder")
                target.parent.mkdir(parents=True, exist_ok=True)
            if target.is_dir() and not target.is_symlink():
                raise ConfigError("--out", f"{target} is a folder, not a run's file: choose a new or empty folder")
            os.replace(source, target)
        os.replace(self.path / MANIFEST, self.out / MANIFEST)  # last: until here the old one holds
        shutil.rmtree(self.path, ignore_errors=True)

    def discard(self) -> None:
        shutil.rmtree(self.path, ignore_errors=True)


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
        self.failed = False

    def _write(self, payload: dict[str, Any]) -> None:
        """write_json; a full disk ends the run "failed" naming it (ObserverFailure), then nothing more."""
        try:
            write_json(self.path, payload)
        except OSError as err:
            from sim.loop import ObserverFailure  # sim.loop imports this module

            self.failed = True
            with contextlib.suppress(OSError):
                self.path.with_name(self.path.name + ".tmp").unlink()
            code = errno.errorcode.get(err.errno, err.errno)
            raise ObserverFailure(f"{self.path.name} not written: {err.strerror} ({code})") from None

    def on_tick(self, frame) -> None:
        if self.failed:
            return
        obs = frame.observation
        self._latest = {"status": Status.RUNNING.value, "sim_time_s": obs.time_s, "tick": obs.tick,
                        "links": int(len(obs.links.edges)), **frame.scalars}
        now = self._clock()
        if now >= self._next:
            self._next = now + self.period_s
            self._write(self._latest)

    def close(self, status: str) -> None:
        if not self.failed:
            self._write({**self._latest, "status": str(status)})
