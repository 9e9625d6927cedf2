"""``tether sweep``: many headless trials, on a process pool or a Ray cluster.

A sweep file (TOML; built-ins in ``tether/sweeps/``) names a base scenario, a
duration, seeds and a grid of ``--set`` overrides::

    description = "what it measures"
    scenario = "connected-office"     # built-in name or path (relative to the sweep file)
    duration_s = 400.0                # optional: the scenario's own otherwise
    seeds = 10                        # 0..9, or an explicit list [1, 2, 5]
    set = ["strategy.dwell_time_s=3.0"]   # optional: fixed overrides of every trial

    [grid]                            # every key a `--set` key (or "scenario"), a list of values;
    "robots.0.count" = [10, 20, 35]   # the trials are the product of all lists

    [[zip]]                           # keys tied together: the i-th values go in one trial
    scenario = ["connected-office", "connected-town"]
    "strategy.preset" = ["office", "outdoor"]

    [record]                          # optional: these trials (indices or ids) also write
    video = [0]                       # video.mp4 / run.rrd / plots under DIR/recordings/ID/
    rrd = []

The trials are the product of seeds, the grid and each zip group. A trial's
id is a hash of everything that decides its result (scenario, overrides,
seed, duration), so the same trial has the same id in every sweep.

Results: the driver (the only writer) stores each finished trial at once as
a one-row Parquet file ``DIR/trials/ID.aN.parquet`` (written to a temporary
name and renamed, so a file is whole or absent), then, at the end,
``DIR/results.parquet`` (latest attempt per trial, one row each).
``DIR/sweep.json`` holds the sweep's definition and its hash: a folder
holding another sweep's results is refused. A rerun of the same command
skips every trial whose latest row is finished ("completed", or "time limit":
the trial ran to its duration cap) or failed ("diverged", "failed");
``--retry-failed`` also reruns the failed ones (a new attempt file; the old
one stays). A row that says "interrupted" (a trial stopped by a signal) is
never a result: the next call runs that trial again.
"""

from __future__ import annotations

import abc
import hashlib
import json
import math
import os
import signal
import socket
import subprocess
import sys
import time
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from datetime import datetime, timezone
from itertools import product
from pathlib import Path
from typing import Any, Callable, Iterable

from sim.config import ConfigError, builtin_descriptions, builtin_or_file, read_toml_file
from sim.strategy import Status

SWEEP_DIR = Path(__file__).parent / "sweeps"
FORMAT = "tether-sweep/1"  # sweep.json's format tag: anything else is a foreign folder
TRIALS_FOLDER = "trials"
RESULTS_FILE = "results.parquet"
MANIFEST_FILE = "sweep.json"
CUT_SHORT_HINT = ("a file cut short (a full disk, a copy interrupted): delete it and run the same command "
                  "again; that trial runs again")
LOCK_FILE = ".sweep.lock"  # flock()ed by the driver that runs the sweep (its pid inside)
MAX_TRIALS = 100_000  # trials of one sweep (fig9 has 1,800): the expansion and its rows stay in memory
SWEEP_KEYS = {"description", "scenario", "duration_s", "seeds", "set", "grid", "zip", "record"}
# Columns every row has, before the swept keys and the metrics.
ROW_KEYS = ("trial_id", "trial_index", "attempt", "scenario", "seed", "duration_s", "overrides", "status",
            "error", "wall_time_s", "host", "finished_at")
# Statuses of a trial's row (sim.strategy.Status): "completed" (its mission ended, or it ran its
# whole duration), "time limit" (stopped by the duration cap before its mission ended: a finished
# trial with a censored completion time), "diverged", "interrupted", "failed" (an exception; folders
# written before the shared vocabulary say "error").
FINISHED = (Status.COMPLETED.value, Status.TIME_LIMIT.value)
FAILED = (Status.DIVERGED.value, Status.FAILED.value, "error")
NOT_A_RESULT = (Status.INTERRUPTED.value,)  # always run again


# ---------------------------------------------------------------- sweep files

@dataclass(frozen=True)
class Trial:
    """One headless ``tether run``: base scenario + overrides + seed (+ duration)."""

    index: int  # position in the sweep's expansion order
    scenario: str  # built-in name or absolute path of the base scenario
    seed: int
    duration_s: float | None  # None: the scenario's own duration
    overrides: tuple[str, ...]  # "key=value" as --set takes them, in application order
    swept: tuple[tuple[str, Any], ...] = ()  # (grid key, value): the trial's own columns
    video: bool = False
    rrd: bool = False

    @property
    def trial_id(self) -> str:
        """Hash of what decides the result (not the index, not what is recorded)."""
        # Sorted: no two overrides set the same key (load_sweep refuses it), so their order
        # does not change the result, and a sweep file with its keys reordered keeps its ids.
        identity = {"scenario": self.scenario, "seed": self.seed, "duration_s": self.duration_s,
                    "overrides": sorted(self.overrides)}
        return hashlib.sha256(json.dumps(identity, sort_keys=True).encode()).hexdigest()[:16]


@dataclass(frozen=True)
class Sweep:
    name: str
    description: str
    definition: dict  # the normalised sweep table (what the hash covers)
    trials: tuple[Trial, ...] = field(repr=False)

    @property
    def definition_hash(self) -> str:
        return hashlib.sha256(json.dumps(self.definition, sort_keys=True).encode()).hexdigest()[:16]


def builtin_sweeps() -> dict[str, str]:
    """Built-in sweep name -> description."""
    return builtin_descriptions(SWEEP_DIR)


def _read_sweep_table(name_or_path: str) -> tuple[dict, Path]:
    from tether.catalog import SCENARIO_DIR

    try:
        path = builtin_or_file(name_or_path, SWEEP_DIR, "sweep")
    except ConfigError as err:
        if (SCENARIO_DIR / f"{name_or_path}.toml").is_file():
            raise ConfigError("sweep", f"{err.problem}; {name_or_path!r} is a built-in scenario (tether run "
                              f"{name_or_path}): a sweep file names it with scenario = \"{name_or_path}\" "
                              "(docs/sweeps.md)") from None
        raise
    return read_toml_file(path, "sweep"), path


def _base_scenario(name: Any, sweep_path: Path, key: str) -> str:
    """A built-in scenario name as is; a file path made absolute (relative to the sweep file)."""
    from tether.catalog import SCENARIO_DIR

    if not isinstance(name, str) or not name:
        raise ConfigError(key, f"must be a scenario name or file, got {name!r}")
    if (SCENARIO_DIR / f"{name}.toml").is_file():
        return name
    path = Path(name).expanduser()
    if not path.is_absolute():
        path = sweep_path.parent / path
    return str(path.resolve())


def _seeds(value: Any) -> list[int]:
    """The seeds a sweep's ``seeds`` names, every one checked (a run's range), the count
    bounded before the list is made."""
    from sim.scenario import MAX_SEED

    if isinstance(value, int) and not isinstance(value, bool):
        if not 1 <= value <= MAX_TRIALS:
            raise ConfigError("seeds", f"must be a count from 1 to {MAX_TRIALS} or a list of seeds, got {value}")
        return list(range(value))
    if isinstance(value, list) and value and all(isinstance(s, int) and not isinstance(s, bool) for s in value):
        wrong = [s for s in value if not 0 <= s <= MAX_SEED]
        if wrong:
            raise ConfigError("seeds", f"every seed must be in [0, 2**63 - 1], got {wrong[0]}")
        if len(set(value)) != len(value):
            raise ConfigError("seeds", "lists a seed twice")
        return list(value)
    raise ConfigError("seeds", f"must be a count or a non-empty list of integers, got {value!r}")


def _axis(table: Any, where: str) -> list[tuple[str, list]]:
    """(key, values) pairs of a [grid] or one [[zip]] group."""
    if not isinstance(table, dict):
        raise ConfigError(where, "must be a table of key = [values]")
    axes = []
    for key, values in table.items():
        if not isinstance(values, list) or not values:
            raise ConfigError(f"{where}.{key}", f"must be a non-empty list of values, got {values!r}")
        for value in values:
            _check_toml_value(value, f"{where}.{key}")
        axes.append((key, values))
    return axes


def _check_toml_value(value: Any, where: str) -> None:
    """ConfigError for a value a scenario cannot hold (TOML's dates and times): numbers,
    strings, booleans, lists and tables only."""
    stack = [value]
    while stack:
        node = stack.pop()
        if isinstance(node, dict):
            stack.extend(node.values())
        elif isinstance(node, list):
            stack.extend(node)
        elif not isinstance(node, (bool, int, float, str)):
            raise ConfigError(where, f"a scenario value is a number, string, boolean, list or table, got the "
                                     f"{type(node).__name__} {node}")


def load_sweep(name_or_path: str, video: Iterable[str] = (), rrd: Iterable[str] = ()) -> Sweep:
    """Read, expand and validate a sweep (ConfigError naming the key on bad input).

    ``video``/``rrd``: trial indices or ids to record, beside the file's [record].
    Every trial is loaded like ``tether run`` loads a scenario, so a bad key
    or value is refused before anything runs.
    """
    from sim.scenario import load, toml_value

    table, path = _read_sweep_table(name_or_path)
    unknown = sorted(set(table) - SWEEP_KEYS)
    if "scenario" not in table and "strategy" in table and "robots" in table:
        raise ConfigError("sweep", f"{path} is a scenario file (run it with: tether run {path}); a sweep file "
                          f"names it with scenario = \"{path}\" and lists what to vary under [grid] "
                          "(docs/sweeps.md)")
    if unknown:
        raise ConfigError(unknown[0], f"unknown sweep key (known: {', '.join(sorted(SWEEP_KEYS))})")
    if "scenario" not in table:
        raise ConfigError("scenario", "is required (the base scenario: a built-in name or a file)")
    base = _base_scenario(table["scenario"], path, "scenario")
    duration = table.get("duration_s")
    if duration is not None and (isinstance(duration, bool) or not isinstance(duration, (int, float))
                                 or not duration > 0 or not math.isfinite(duration)):
        raise ConfigError("duration_s", f"must be a positive number of seconds, got {duration!r}")
    seeds = _seeds(table.get("seeds", 1))
    fixed = table.get("set", [])
    if not isinstance(fixed, list) or not all(isinstance(s, str) and "=" in s for s in fixed):
        raise ConfigError("set", f"must be a list of \"key=value\" strings, got {fixed!r}")

    grid = _axis(table.get("grid", {}), "grid")
    zips = table.get("zip", [])
    if isinstance(zips, dict):
        zips = [zips]
    if not isinstance(zips, list):
        raise ConfigError("zip", "must be [[zip]] tables")
    groups: list[list[tuple]] = []  # each: the list of choices, a choice = ((key, value), ...)
    for key, values in grid:
        groups.append([((key, v),) for v in values])
    for i, group in enumerate(zips):
        axes = _axis(group, f"zip.{i}")
        if not axes:
            raise ConfigError(f"zip.{i}", "is empty")
        lengths = {len(values) for _, values in axes}
        if len(lengths) != 1:
            raise ConfigError(f"zip.{i}", f"lists of different lengths {sorted(lengths)}: tied keys need one value each")
        groups.append([tuple((key, values[j]) for key, values in axes) for j in range(lengths.pop())])
    n_trials = len(seeds) * math.prod(len(group) for group in groups)  # before a trial is made
    if n_trials > MAX_TRIALS:
        sizes = " x ".join(str(n) for n in (len(seeds), *(len(group) for group in groups)))
        raise ConfigError("grid", f"expands to {n_trials} trials ({sizes}, seeds first), at most {MAX_TRIALS}: "
                                  "split the sweep")
    keys = [key for group in groups for key, _ in group[0]]
    twice = sorted({k for k in keys if keys.count(k) > 1})
    if twice:
        raise ConfigError(twice[0], "is swept twice (in [grid] and a [[zip]], or in two groups)")

    record = table.get("record", {})
    if not isinstance(record, dict):
        raise ConfigError("record", "must be a table: video = [trials], rrd = [trials]")
    unknown = sorted(set(record) - {"video", "rrd"})
    if unknown:
        raise ConfigError(f"record.{unknown[0]}", "unknown key (known: video, rrd)")
    for kind in record:
        if not isinstance(record[kind], list):
            raise ConfigError(f"record.{kind}", f"must be a list of trial indices or ids, got {record[kind]!r}")
    chosen = {"video": {str(v) for v in (*record.get("video", []), *video)},
              "rrd": {str(v) for v in (*record.get("rrd", []), *rrd)}}
    fixed_keys = [assignment.partition("=")[0].strip() for assignment in fixed]
    both = sorted(set(fixed_keys) & set(keys)) or sorted({k for k in fixed_keys if fixed_keys.count(k) > 1})
    if both:
        raise ConfigError(both[0], "is set twice (in set = [...] and swept, or twice in set)")
    if "seed" in keys:
        raise ConfigError("seed", "is swept by the top-level seeds = [...], not in [grid] or [[zip]]")
    if "duration_s" in keys and duration is not None:
        raise ConfigError("duration_s", "is both swept and set at the top level")

    trials = []
    for seed, *choices in product(seeds, *groups):
        swept = tuple(pair for choice in choices for pair in choice)
        scenario, trial_duration = base, duration
        overrides = list(fixed)
        for key, value in swept:
            if key == "scenario":
                scenario = _base_scenario(value, path, "grid.scenario")
            elif key == "duration_s":
                if isinstance(value, bool) or not isinstance(value, (int, float)):
                    raise ConfigError("grid.duration_s", f"must be numbers of seconds, got {value!r}")
                trial_duration = value
            else:
                overrides.append(f"{key}={toml_value(value)}")
        trials.append(Trial(len(trials), scenario, seed, None if trial_duration is None else float(trial_duration),
                            tuple(overrides), swept))
    if not trials:
        raise ConfigError("grid", "expands to no trials")

    seen: dict[str, Trial] = {}
    validated: set[tuple] = set()
    for trial in trials:
        if trial.trial_id in seen:
            raise ConfigError("grid", f"trials {seen[trial.trial_id].index} and {trial.index} are the same trial")
        seen[trial.trial_id] = trial
        # The seed cannot make a scenario invalid (checked non-negative above), so trials that
        # differ only by seed are validated once: 18 loads instead of 1,800 for fig9.
        if (trial.scenario, trial.overrides, trial.duration_s) in validated:
            continue
        validated.add((trial.scenario, trial.overrides, trial.duration_s))
        try:
            load(trial.scenario, list(trial.overrides), seed=trial.seed, duration_s=trial.duration_s)
        except ConfigError as err:
            where = ", ".join(f"{k}={v}" for k, v in trial.swept) or "every trial"
            raise ConfigError(err.field, f"{err.problem} (trial {trial.index}: {where}, seed {trial.seed})") from None

    def pick(kind: str) -> set[int]:
        out = set()
        for item in chosen[kind]:
            if item.isdigit() and int(item) < len(trials):
                out.add(int(item))
            elif item in seen:
                out.add(seen[item].index)
            else:
                raise ConfigError(f"record.{kind}", f"no trial {item!r} (an index below {len(trials)} or a trial id)")
        return out

    record_video, record_rrd = pick("video"), pick("rrd")
    trials = [Trial(**{**t.__dict__, "video": t.index in record_video, "rrd": t.index in record_rrd})
              for t in trials]
    definition = {"scenario": base, "duration_s": duration, "seeds": seeds, "set": fixed,
                  "grid": {k: v for k, v in grid}, "zip": [dict(_axis(z, "zip")) for z in zips]}
    return Sweep(path.stem, table.get("description", ""), definition, tuple(trials))


# ---------------------------------------------------------------- one trial

def _column_value(value: Any) -> Any:
    """A metric as a Parquet cell: numbers, strings and booleans as they are,
    anything else (lists, tables) as JSON text."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value
    if hasattr(value, "item"):  # numpy scalars
        return value.item()
    return json.dumps(value)


def run_trial(trial: Trial, recordings: str | None = None) -> dict:
    """Run one trial headless and return its row; never raises for a failed run.

    Runs in a pool worker or a Ray task. ``recordings``: folder of
    ``ID/`` run outputs for trials chosen for video/rrd (headless otherwise).
    """
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    start = time.perf_counter()
    row: dict[str, Any] = {
        "trial_id": trial.trial_id, "trial_index": trial.index, "scenario": trial.scenario, "seed": trial.seed,
        "duration_s": trial.duration_s, "overrides": json.dumps(list(trial.overrides)),
        **{key: _column_value(value) for key, value in trial.swept},
    }
    metrics: dict[str, Any] = {}
    try:
        import sim  # noqa: F401  (GL backend before mujoco)
        from tether.runner import run
        from sim.scenario import load

        scenario = load(trial.scenario, list(trial.overrides), seed=trial.seed, duration_s=trial.duration_s)
        out = None
        if recordings is not None and (trial.video or trial.rrd):
            out = Path(recordings) / trial.trial_id
        result = run(scenario, out, video=trial.video, rrd=trial.rrd)
        metrics = result.metrics
        row["status"] = result.status.value
        row["error"] = metrics.get("message", "") if result.status != Status.COMPLETED else ""
    except Exception as err:  # recorded as a failed trial; the sweep goes on
        row["status"] = Status.FAILED.value
        row["error"] = f"{type(err).__name__}: {err}"
    row["wall_time_s"] = time.perf_counter() - start
    row["host"] = socket.gethostname()
    row["finished_at"] = datetime.now(timezone.utc).isoformat(timespec="seconds")
    # The run's own wall time (world build + loop) beside the trial's (also loading and imports);
    # the other metrics that repeat a row key (scenario name, seed, status, message) are left out.
    if "wall_time_s" in metrics:
        row["run_wall_time_s"] = metrics["wall_time_s"]
    for key, value in metrics.items():
        if key not in row and key != "message":
            row[key] = _column_value(value)
    return row


# ---------------------------------------------------------------- the results folder

class ResultsFolder:
    """DIR/sweep.json, DIR/trials/*.parquet and DIR/results.parquet."""

    def __init__(self, out: str | Path):
        self.out = Path(out)
        self.trials_dir = self.out / TRIALS_FOLDER

    @property
    def manifest_path(self) -> Path:
        return self.out / MANIFEST_FILE

    def read_manifest(self) -> dict | None:
        """sweep.json, None if absent; ConfigError if unreadable or foreign."""
        if not self.manifest_path.exists():
            return None
        try:
            manifest = json.loads(self.manifest_path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise ConfigError("--out", f"{self.manifest_path} is unreadable: {err}") from None
        if not isinstance(manifest, dict) or manifest.get("format") != FORMAT:
            raise ConfigError("--out", f"{self.manifest_path} is not a tether sweep file (no format {FORMAT!r})")
        return manifest

    def check(self, sweep: Sweep) -> None:
        """Refuse (ConfigError) a folder holding anything but this sweep's
        results, or an unreadable or foreign row; creates nothing."""
        from sim.outputs import check_out_path

        check_out_path(self.out, "--out")  # not "", /, home, nor a name too long
        if self.out.exists() and not self.out.is_dir():
            raise ConfigError("--out", f"{self.out} exists and is not a folder")
        manifest = self.read_manifest()
        if manifest is None:
            if self.out.exists() and any(p.name != LOCK_FILE for p in self.out.iterdir()):
                raise ConfigError("--out", f"{self.out} is not empty and holds no {MANIFEST_FILE}: "
                                           "choose an empty or new folder")
            return
        if manifest.get("definition_hash") != sweep.definition_hash:
            raise ConfigError("--out", f"{self.out} holds another sweep's results ({manifest.get('sweep')!r}, "
                                       f"definition {manifest.get('definition_hash')}; this one is "
                                       f"{sweep.definition_hash}): use another folder")
        self.latest_status({t.trial_id for t in sweep.trials})

    def claim(self, sweep: Sweep) -> None:
        """Make DIR this sweep's folder (after :meth:`check`), locked for this process: a
        second driver in the same folder is refused (ConfigError) instead of running every
        trial again beside the first. The lock goes with the process (however it ends)."""
        self.check(sweep)
        self.out.mkdir(parents=True, exist_ok=True)
        self._lock()
        self.check(sweep)  # again, under the lock: another driver may have claimed it meanwhile
        if self.read_manifest() is None:
            _write_atomic(self.manifest_path, json.dumps({
                "format": FORMAT, "sweep": sweep.name, "description": sweep.description,
                "definition_hash": sweep.definition_hash, "definition": sweep.definition,
                "trials": len(sweep.trials),
                "created": datetime.now(timezone.utc).isoformat(timespec="seconds"),
            }, indent=2).encode() + b"\n")
        self.trials_dir.mkdir(exist_ok=True)

    def _lock(self) -> None:
        import fcntl

        path = self.out / LOCK_FILE
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "?"
            os.close(fd)
            raise ConfigError("--out", f"{self.out} is in use by another tether sweep (process {holder}): "
                                       "wait for it to end, or choose another folder") from None
        try:  # the holder's pid, for the message above; a full disk may leave it empty
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError:
            pass
        self._lock_fd = fd  # held until release() or the end of the process

    def release(self) -> None:
        """Let another driver claim the folder (the lock file stays: it is the sweep's)."""
        fd, self._lock_fd = getattr(self, "_lock_fd", None), None
        if fd is not None:
            os.close(fd)

    def trial_files(self) -> list[Path]:
        if not self.trials_dir.is_dir():
            return []
        return sorted(p for p in self.trials_dir.glob("*.parquet") if not p.name.startswith("."))

    def latest_status(self, known_ids: set[str] | None = None) -> dict[str, tuple[int, str]]:
        """trial id -> (latest attempt, its status); ConfigError on an unreadable or foreign file."""
        import pyarrow.parquet as pq

        out: dict[str, tuple[int, str]] = {}
        for path in self.trial_files():
            try:
                table = pq.read_table(path, columns=["trial_id", "attempt", "status"])
            except Exception as err:
                raise ConfigError("--out", f"{path} is not a readable trial row ({str(err).splitlines()[0]}): "
                                           f"{CUT_SHORT_HINT}") from None
            for trial_id, attempt, status in zip(*(table.column(c).to_pylist() for c in table.column_names)):
                if known_ids is not None and trial_id not in known_ids:
                    raise ConfigError("--out", f"{path} holds trial {trial_id}, which is not in this sweep")
                if trial_id not in out or attempt > out[trial_id][0]:
                    out[trial_id] = (attempt, status)
        return out

    def store(self, row: dict) -> Path:
        """Write one trial's row at once, atomically (whole file or none)."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        path = self.trials_dir / f"{row['trial_id']}.a{row['attempt']}.parquet"
        tmp = self.trials_dir / f".{path.name}.{os.getpid()}.tmp"
        with _writing(path, tmp):
            pq.write_table(pa.Table.from_pylist([row]), tmp)
            _fsync_replace(tmp, path)
        return path

    def consolidate(self) -> Path | None:
        """results.parquet: the latest attempt of every trial, in sweep order."""
        import pyarrow.parquet as pq

        table = read_results(self.out)
        if table is None:
            return None
        path = self.out / RESULTS_FILE
        tmp = self.out / f".{RESULTS_FILE}.{os.getpid()}.tmp"
        with _writing(path, tmp):
            pq.write_table(table, tmp)
            _fsync_replace(tmp, path)
        return path


def _fsync_replace(tmp: Path, path: Path) -> None:
    with open(tmp, "rb") as f:
        os.fsync(f.fileno())
    os.replace(tmp, path)


@contextmanager
def _writing(path: Path, tmp: Path):
    """Around a write of ``path`` through ``tmp``: on any failure (a full disk) no
    half-written ``tmp`` is left, and an OSError names ``path`` (pyarrow's and the lock's
    name no file), so the command's one line says where."""
    import errno as errnos
    import re

    try:
        yield
    except BaseException as err:
        tmp.unlink(missing_ok=True)
        if isinstance(err, OSError) and err.filename is None:
            code = err.errno
            if code is None:
                found = re.search(r"\[errno (\d+)\]", str(err))
                code = int(found.group(1)) if found else errnos.EIO
            raise OSError(code, os.strerror(code), str(path)) from None
        raise


def _write_atomic(path: Path, data: bytes) -> None:
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with _writing(path, tmp):
        tmp.write_bytes(data)
        _fsync_replace(tmp, path)


def read_results(out: str | Path, all_attempts: bool = False):
    """The sweep's table (pyarrow.Table; None if there are no rows yet).

    From the per-trial files when DIR/trials exists (the truth while a sweep
    runs), else from DIR/results.parquet; the latest attempt per trial unless
    ``all_attempts``. Rows of different strategies have different metric
    columns: the union is taken, missing cells are null.
    """
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    folder = ResultsFolder(out)
    files = folder.trial_files()
    try:
        if files:
            try:
                table = pa.concat_tables([pq.read_table(p) for p in files], promote_options="permissive")
            except Exception as err:  # a row cut short: the consolidated table, when there is one, still holds it
                if not (folder.out / RESULTS_FILE).is_file():
                    raise ConfigError("results", f"{out}: a trial row is unreadable ({str(err).splitlines()[0]}): "
                                                 f"{CUT_SHORT_HINT}") from None
                table = pq.read_table(folder.out / RESULTS_FILE)
        elif (folder.out / RESULTS_FILE).is_file():
            table = pq.read_table(folder.out / RESULTS_FILE)
        elif folder.out.is_file() and folder.out.suffix == ".parquet":
            table = pq.read_table(folder.out)
        else:
            return None
    except ConfigError:
        raise
    except Exception as err:
        raise ConfigError("results", f"{out}: unreadable results: {err}") from None
    missing = [c for c in ("trial_id", "attempt", "status") if c not in table.column_names]
    if missing:
        raise ConfigError("results", f"{out}: not a tether sweep table (no column {missing[0]!r})")
    if not all_attempts and table.num_rows:
        ids = table.column("trial_id").to_pylist()
        attempts = table.column("attempt").to_pylist()
        best: dict[str, int] = {}
        for i, (trial_id, attempt) in enumerate(zip(ids, attempts)):
            if trial_id not in best or attempt > attempts[best[trial_id]]:
                best[trial_id] = i
        table = table.take(sorted(best.values()))
    if "trial_index" in table.column_names and table.num_rows:
        table = table.take(pc.sort_indices(table, sort_keys=[("trial_index", "ascending")]))
    return table


# ---------------------------------------------------------------- engines

class SweepStopped(RuntimeError):
    """An engine cannot go on (e.g. its process pool broke); rows stored so far stay."""


class Engine(abc.ABC):
    """Runs trials and yields their rows as they finish (any order)."""

    @abc.abstractmethod
    def run(self, trials: list[Trial], recordings: str) -> Iterable[dict]:
        """Yield one row per trial as it finishes."""

    def close(self) -> None:
        pass


class ProcessPool(Engine):
    """concurrent.futures on this machine. Workers are started with
    'forkserver' (a clean process, not a fork of a driver that may have
    imported MuJoCo or opened an EGL context)."""

    def __init__(self, workers: int):
        self.workers = workers
        self.pool = None

    def run(self, trials, recordings):
        from concurrent.futures import ProcessPoolExecutor, as_completed
        from multiprocessing import get_context

        from concurrent.futures.process import BrokenProcessPool

        # no more processes than trials to run (each is a process of ~200 MB)
        self.pool = ProcessPoolExecutor(max_workers=max(1, min(self.workers, len(trials))),
                                        mp_context=get_context("forkserver"), initializer=_end_with_driver,
                                        initargs=(os.getpid(),))
        from viz.painter import group_signals_deferred

        # The workers start in these submits: a signal is held until each is started and in the pool's
        # table (close() kills those), not raised inside a start, which would leave a worker the pool
        # does not know opening the pool's queues by name after this process dropped them.
        with group_signals_deferred():
            futures = [self.pool.submit(run_trial, trial, recordings) for trial in trials]
        try:
            for future in as_completed(futures):
                yield future.result()
        except BrokenProcessPool:
            raise SweepStopped("a worker process died (killed or out of memory); "
                               "the trials it and the others were running have no row yet") from None

    def close(self):
        if self.pool is None:
            return
        # Queued trials are dropped and running ones stopped now rather than
        # finished: they have no row, so the next call runs them again.
        workers = list(getattr(self.pool, "_processes", {}).values())  # no public handle before Python 3.14
        self.pool.shutdown(wait=False, cancel_futures=True)
        for process in workers:
            if process.is_alive():
                process.kill()  # they ignore SIGTERM (_end_with_driver)
        for process in workers:
            process.join(timeout=10)


DRIVER_CHECK_S = 1.0  # how often a pool worker checks that its driver still runs


def _end_with_driver(driver_pid: int) -> None:
    """Pool worker initializer: end this worker when the driver is gone (killed, even by SIGKILL).
    Without it a worker would finish its trial and take the next queued ones, whose rows nobody
    stores: CPU spent for nothing while the next call runs them again."""
    import threading

    # The group's Ctrl-C or SIGTERM is the driver's to handle (it stores the rows it has, then
    # stops the workers); a worker that died of it would break the pool first. A trial's ticks
    # install their own handlers (sim.loop): a signal then ends that trial "interrupted".
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, (signal.SIGINT, signal.SIGTERM))  # started with them held

    def watch() -> None:
        while True:
            time.sleep(DRIVER_CHECK_S)
            if os.getppid() == 1 or not _alive(driver_pid):
                os._exit(1)

    threading.Thread(target=watch, name="end-with-driver", daemon=True).start()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, owned by someone else
        pass
    return True


class RayCluster(Engine):
    """The same trials as Ray tasks on an existing cluster. Ray retries a task
    whose worker or node died (``max_retries``); an exception inside a trial
    is already a row, so it is never retried."""

    MAX_RETRIES = 3

    def __init__(self, address: str):
        self.address = address
        try:
            import ray
        except ImportError:
            raise ConfigError("--ray", "Ray is not installed (pip install -e '.[ray]')") from None
        self.ray = ray
        _probe_ray_address(address)
        # ray.init retries an address that does not answer as Ray for ever: it runs in a thread of
        # its own, waited for RAY_INIT_TIMEOUT_S. Workers must import tether: it is installed in the
        # cluster's environment (see docs/sweeps.md).
        import threading

        outcome: list[BaseException | None] = []
        self._stderr = _CoreLogsAside()  # before ray.init: its core worker logs from its first line

        def connect() -> None:
            try:
                ray.init(address=address, log_to_driver=False, logging_level="ERROR")
                outcome.append(None)
            except BaseException as err:  # noqa: BLE001  (handed to the main thread)
                outcome.append(err)

        threading.Thread(target=connect, name="ray-init", daemon=True).start()
        deadline = time.monotonic() + RAY_INIT_TIMEOUT_S
        try:
            while not outcome and time.monotonic() < deadline:
                time.sleep(0.05)  # not Thread.join: a signal still interrupts the wait
        except BaseException:
            self._stderr.restore()
            raise
        if not outcome:  # (fd 2 stays aside: the thread goes on retrying, and logging)
            raise RayTimeout("--ray", f"{address} answered like a gRPC server but ray.init had not connected "
                                      f"within {RAY_INIT_TIMEOUT_S:.0f} s: is it a Ray cluster's GCS port "
                                      "(ray start --head --port)?")
        if outcome[0] is not None:
            self._stderr.restore()
        if isinstance(outcome[0], (ConnectionError, RuntimeError, ValueError)):
            raise ConfigError("--ray", f"cannot connect to Ray at {address!r}: "
                                       f"{str(outcome[0]).splitlines()[0]}") from None
        if outcome[0] is not None:
            raise outcome[0]
        _quiet_cluster_errors(ray)
        host, _, port = ray.get_runtime_context().gcs_address.rpartition(":")
        self.gcs = (host, int(port))
        self.name = address if address != "auto" else f"{host}:{port}"

    def head_answers(self) -> bool:
        """Whether the head's GCS port still accepts a connection (a killed head refuses it at once)."""
        try:
            socket.create_connection(self.gcs, timeout=RAY_HEAD_PROBE_TIMEOUT_S).close()
            return True
        except OSError:
            return False

    def run(self, trials, recordings):
        ray = self.ray
        task = ray.remote(num_cpus=1, max_retries=self.MAX_RETRIES)(run_trial)
        pending = {task.remote(trial, recordings): trial for trial in trials}
        # Ray itself notices a dead head only after a minute (its GCS reconnection timeout) and then ends
        # the process: the driver looks at the head every second and stops with its rows first.
        misses, checked = 0, time.monotonic()
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1, timeout=RAY_HEAD_CHECK_S)
            if time.monotonic() - checked >= RAY_HEAD_CHECK_S or not done:
                checked = time.monotonic()
                misses = 0 if self.head_answers() else misses + 1
                if misses >= RAY_HEAD_MISSES:
                    raise SweepStopped(f"the Ray cluster at {self.name} is gone")
            if not done:
                continue
            trial = pending.pop(done[0])
            try:
                row = ray.get(done[0])
            except ray.exceptions.RayError as err:  # worker or node lost more than MAX_RETRIES times
                if not self.head_answers():  # not the trial's failure: it has no row and runs again
                    raise SweepStopped(f"the Ray cluster at {self.name} is gone") from None
                row = _error_row(trial, f"{type(err).__name__}: {str(err).splitlines()[0]}")
            yield row

    def close(self):
        """ray.shutdown, waited for at most RAY_SHUTDOWN_TIMEOUT_S (with the head gone it may wait for
        the GCS): past that the driver goes on, and Ray's own shutdown at exit is dropped too."""
        import atexit
        import threading

        ray = self.ray
        if not ray.is_initialized():
            self._stderr.restore()
            return
        finished = threading.Event()

        def shutdown() -> None:
            try:
                ray.shutdown()
            finally:
                finished.set()

        threading.Thread(target=shutdown, name="ray-shutdown", daemon=True).start()
        if finished.wait(RAY_SHUTDOWN_TIMEOUT_S):
            self._stderr.restore()
        else:  # its threads may still log: file descriptor 2 stays aside until the process ends
            atexit.unregister(ray.shutdown)


class _CoreLogsAside:
    """File descriptor 2 pointed at /dev/null while Ray's core worker lives in this process, and
    ``sys.stderr`` (Python's own writes: the sweep's progress, its summary, tracebacks) on a
    duplicate of the original, so they reach the terminal as before.

    Ray's C++ core worker and GCS client (Ray 2.60) write every log record of level ERROR to file
    descriptor 2 as well as to the driver's log file in the Ray session's ``logs/``
    (``python-core-driver-*.log``): a raylet killed during a sweep printed ``task_manager.cc: Failed
    to push error to driver for task ...`` between the sweep's lines. ``RAY_BACKEND_LOG_LEVEL=fatal``
    would drop those records from the log file too, and prints a line of its own; nothing here is
    lost (the log file has every record). Not done when the user asked for Ray's logs on stderr
    (``RAY_LOG_TO_STDERR=1``: the core worker has no log file then)."""

    def __init__(self):
        self.python_stderr = None
        if os.environ.get("RAY_LOG_TO_STDERR") == "1":
            return
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (AttributeError, OSError, ValueError):  # no stderr at all: nothing to keep apart
            return
        stream = sys.stderr
        sys.stderr = open(saved, "w", buffering=1, encoding=getattr(stream, "encoding", None) or "utf-8",
                          errors=getattr(stream, "errors", None) or "backslashreplace")
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 2)
        os.close(devnull)
        self.python_stderr, self._saved = stream, saved

    def restore(self) -> None:
        """File descriptor 2 back where it was; ``sys.stderr`` back to the original object (the duplicate
        stays open: a progress bar may still hold it, and it writes to the same file)."""
        if self.python_stderr is None:
            return
        with suppress(OSError, ValueError):
            sys.stderr.flush()
        os.dup2(self._saved, 2)
        sys.stderr, self.python_stderr = self.python_stderr, None


def _quiet_cluster_errors(ray) -> None:
    """Drop the cluster's error messages that Ray prints into the driver's stdout (a node's death comes
    with the last 20 lines of its raylet's log, ~47 lines in all). ``log_to_driver=False`` silences the
    workers' output but not this channel, which ``ray.init`` always listens to; Ray (2.60) prints it
    through ``ray._private.worker.print_to_stdstream``, replaced here for the records of that channel
    (``pid`` "raylet"). The sweep says what became of its trials itself: a row per trial, and one line
    when the cluster is gone."""
    import ray._private.worker as ray_worker

    if _ray_printer:  # replaced once per process
        return
    _ray_printer.append(ray_worker.print_to_stdstream)

    def print_to_stdstream(data, ignore_prefix: bool) -> None:
        if data.get("pid") != "raylet":
            _ray_printer[0](data, ignore_prefix)

    ray_worker.print_to_stdstream = print_to_stdstream


_ray_printer: list = []  # Ray's own printer, once _quiet_cluster_errors has replaced it


def _error_row(trial: Trial, error: str) -> dict:
    return {"trial_id": trial.trial_id, "trial_index": trial.index, "scenario": trial.scenario, "seed": trial.seed,
            "duration_s": trial.duration_s, "overrides": json.dumps(list(trial.overrides)),
            **{k: _column_value(v) for k, v in trial.swept}, "status": Status.FAILED.value, "error": error,
            "wall_time_s": None, "host": None,
            "finished_at": datetime.now(timezone.utc).isoformat(timespec="seconds")}


RAY_INIT_TIMEOUT_S = 60.0  # a Ray head answers within seconds; its own retries go on for ever
RAY_HEAD_CHECK_S = 0.5  # how often the driver looks at the head during a sweep
RAY_HEAD_PROBE_TIMEOUT_S = 1.0
RAY_HEAD_MISSES = 3  # probes in a row the head must miss to be gone (one missed probe may be a busy head)
RAY_SHUTDOWN_TIMEOUT_S = 10.0
RAY_PROBE_TIMEOUT_S = 3.0
# HTTP/2's connection preface and an empty SETTINGS frame: a Ray head's GCS (gRPC) answers with a SETTINGS frame.
HTTP2_PREFACE = b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + b"\x00\x00\x00\x04\x00\x00\x00\x00\x00"
HTTP2_SETTINGS = 0x04


class RayTimeout(ConfigError):
    """ray.init did not return in time; its thread is still retrying (the command must end at once)."""


def _probe_ray_address(address: str) -> None:
    """Fail fast (ConfigError) on a host:port nobody listens on, or one that does not speak
    gRPC as a Ray head does (an HTTP server, a port that accepts and says nothing): ray.init
    itself retries such an address for ever."""
    if address == "auto":
        return
    host_port = address.split("://", 1)[-1]
    host, sep, port = host_port.rpartition(":")
    if not sep or not (port.isascii() and port.isdigit()) or int(port) > 65535:
        raise ConfigError("--ray", f"expected 'auto' or HOST:PORT, got {address!r}")
    try:
        with socket.create_connection((host, int(port)), timeout=RAY_PROBE_TIMEOUT_S) as probe:
            probe.sendall(HTTP2_PREFACE)
            answer = b""
            while len(answer) < 9:
                chunk = probe.recv(9 - len(answer))
                if not chunk:
                    break
                answer += chunk
    except TimeoutError:
        answer = None
    except OSError as err:
        raise ConfigError("--ray", f"cannot reach Ray at {host}:{port}: {err.strerror or err}") from None
    if answer is None or not answer:
        said = "said nothing" if answer is None else "closed the connection"
        raise ConfigError("--ray", f"{host}:{port} is not a Ray cluster: it {said} to an HTTP/2 (gRPC) greeting "
                                   "(give the head's GCS port, ray start --head --port)")
    if len(answer) < 9 or answer[3] != HTTP2_SETTINGS:
        first = answer.split(b"\r\n", 1)[0][:40].decode("latin-1")
        what = f"it answers like an HTTP/1 server ({first!r})" if answer.startswith((b"HTTP/", b"<")) else \
            f"it answered {first!r} to an HTTP/2 (gRPC) greeting"
        raise ConfigError("--ray", f"{host}:{port} is not a Ray cluster: {what} (give the head's GCS port, "
                                   "ray start --head --port)")


@contextmanager
def local_ray_cluster(num_cpus: int, temp_dir: str | Path | None = None, timeout_s: float = 120.0):
    """A throwaway single-node Ray cluster (tests, benchmarks): yields its
    address. ``ray start --block`` in its own process group, so stopping it
    ends this cluster's processes only (``ray stop`` would end every Ray
    process of the user on the machine)."""
    ray_bin = Path(sys.executable).parent / "ray"
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    command = [str(ray_bin), "start", "--head", "--block", f"--port={port}", f"--num-cpus={num_cpus}",
               "--include-dashboard=false", "--disable-usage-stats"]
    if temp_dir is not None:
        command.append(f"--temp-dir={temp_dir}")
    head = subprocess.Popen(command, start_new_session=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + timeout_s
        while True:
            if head.poll() is not None:
                raise RuntimeError(f"ray start exited with {head.returncode}")
            try:
                socket.create_connection(("127.0.0.1", port), timeout=1).close()
                break
            except OSError:
                if time.monotonic() > deadline:
                    raise RuntimeError(f"Ray did not listen on port {port} within {timeout_s:.0f} s") from None
                time.sleep(0.2)
        yield f"127.0.0.1:{port}"
    finally:
        # SIGTERM lets `ray start --block` end its processes; whatever is left after a
        # short grace goes with SIGKILL to the group.
        try:
            os.killpg(head.pid, signal.SIGTERM)
            head.wait(timeout=5)
        except (ProcessLookupError, subprocess.TimeoutExpired):
            pass
        try:
            os.killpg(head.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        head.wait()


# ---------------------------------------------------------------- the driver

@dataclass
class SweepOutcome:
    total: int
    finished: int  # "completed" or "time limit"
    failed: int
    not_run: int
    results: Path | None
    stopped: str = ""  # why the sweep stopped before its end ("" if it did not)


class _SweepProgress:
    """The sweep's progress on stderr: a tqdm bar on a terminal; into a pipe or a
    log, as ``tether run`` does, one plain line every 10 % of the trials or 30 s
    of wall time (the policy of :class:`tether.progress.RunProgress`), no carriage returns."""

    def __init__(self, name: str, total: int, initial: int, enabled: bool):
        from tether.progress import PLAIN_EVERY_FRACTION, PLAIN_EVERY_WALL_S

        self.name, self.total, self.n, self.enabled = name, total, initial, enabled
        self._postfix = ""
        self._every_trials = max(1, math.ceil(PLAIN_EVERY_FRACTION * total))
        self._every_wall_s = PLAIN_EVERY_WALL_S
        self._start = time.monotonic()
        self._last_line = (initial, self._start)
        self._bar = None
        if enabled and sys.stderr.isatty():
            from tqdm import tqdm

            self._bar = tqdm(total=total, initial=initial, desc=name, unit="trial", file=sys.stderr,
                             dynamic_ncols=True, smoothing=0.1)

    def set_postfix_str(self, text: str, refresh: bool = False) -> None:
        self._postfix = text
        if self._bar is not None:
            self._bar.set_postfix_str(text, refresh=refresh)

    def update(self, count: int) -> None:
        self.n += count
        if self._bar is not None:
            self._bar.update(count)
            return
        now = time.monotonic()
        if self.enabled and (self.n - self._last_line[0] >= self._every_trials or self.n == self.total
                             or now - self._last_line[1] >= self._every_wall_s):
            self._last_line = (self.n, now)
            print(f"  {self.name}: {self.n}/{self.total} trials, {self._postfix}, {now - self._start:.0f} s wall",
                  file=sys.stderr, flush=True)

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()


def run_sweep(sweep: Sweep, out: str | Path, engine: Engine, retry_failed: bool = False,
              progress: bool = True, on_row: Callable[[dict], None] | None = None) -> SweepOutcome:
    """Run the sweep's trials that have no row in ``out`` (and, with
    ``retry_failed``, those whose latest row failed); store each row as it
    comes. The folder must have been claimed (:meth:`ResultsFolder.claim`)."""
    folder = ResultsFolder(out)
    status = folder.latest_status({t.trial_id for t in sweep.trials})
    todo = [t for t in sweep.trials
            if t.trial_id not in status or status[t.trial_id][1] in NOT_A_RESULT
            or (retry_failed and status[t.trial_id][1] in FAILED)]
    finished = sum(s in FINISHED for _, s in status.values())
    rerun = {t.trial_id for t in todo}
    failed = sum(s in FAILED for trial_id, (_, s) in status.items() if trial_id not in rerun)
    bar = _SweepProgress(sweep.name, len(sweep.trials), len(sweep.trials) - len(todo), progress)

    def show() -> None:
        remaining = len(sweep.trials) - finished - failed
        bar.set_postfix_str(f"done {finished}, failed {failed}, remaining {remaining}", refresh=False)

    show()
    stopped = ""
    try:
        for row in engine.run(todo, str(folder.out / "recordings")):
            row["attempt"] = status.get(row["trial_id"], (0, ""))[0] + 1
            folder.store(row)
            if row["status"] in FINISHED:
                finished += 1
            elif row["status"] in FAILED:
                failed += 1
            if on_row is not None:
                on_row(row)
            show()
            bar.update(1)
    except KeyboardInterrupt:
        stopped = Status.INTERRUPTED.value
    except SweepStopped as err:
        stopped = str(err)
    finally:
        engine.close()
        bar.close()
    results = folder.consolidate()
    return SweepOutcome(len(sweep.trials), finished, failed, len(sweep.trials) - finished - failed, results,
                        stopped)
