"""``tether compare``: seed 000's Table I on this simulator.

Runs every (scenario, method, seed) trial headless (no video, recording or
plots), appends one JSON line per finished trial to ``OUT/trials.jsonl`` and
skips, on a later call, every trial already there with the same scenario,
method, seed, duration and overrides: an interrupted sweep resumes where it
stopped, and more seeds can be added later. Then it prints the table (and
writes it to ``OUT/table.md``, with a bar chart ``OUT/table.png``): for each
scenario and method, the mean over seeds of each run's time averages
e_g-bar (eq. 13a) and lambda-bar (eq. 13b), "±" the mean over seeds of each
run's standard deviation over time (how the paper's Table I reports a run),
the spread of the run averages across seeds, and the paper's numbers beside.

Methods are the strategy kinds ``all_time`` (the paper's "all-time"),
``random_meeting`` ("heuristic") and ``intermittent``; every scenario runs
each of them through ``strategy.kind``, everything else unchanged.
"""

from __future__ import annotations

import json
import math
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Callable, Iterable

import numpy as np

METHODS = ("all_time", "random_meeting", "intermittent")  # Table I's column order
LABELS = {"all_time": "all-time", "random_meeting": "heuristic", "intermittent": "intermittent"}
DEFAULT_SCENARIOS = ("intermittent-4", "intermittent-8")
DEFAULT_SEEDS = 10
DEFAULT_DURATION_S = 300.0

# Seed 000, Table I: (mean, +/-) of e_g-bar (m) and lambda-bar (m^2).
PAPER_TABLE = {
    4: {
        "all_time": ((1.030, 0.466), (0.226, 0.061)),
        "random_meeting": ((1.993, 0.566), (0.405, 0.181)),
        "intermittent": ((0.879, 0.461), (0.167, 0.084)),
    },
    8: {
        "all_time": ((2.517, 0.810), (0.563, 0.129)),
        "random_meeting": ((1.201, 0.570), (0.334, 0.161)),
        "intermittent": ((0.929, 0.561), (0.177, 0.068)),
    },
}

ROW_METRICS = (
    "sim_time_s", "wall_time_s", "n_robots", "n_moving_targets",
    "e_g_mean_m", "e_g_std_m", "lambda_bar_mean_m2", "lambda_bar_std_m2",
    "meetings_scheduled", "meetings_held", "meetings_connected", "max_wait_s",
    "delay_bound_epochs", "max_delay_epochs_observed", "plan_time_mean_s", "plan_time_max_s",
    "plans", "plan_failures", "plan_fallbacks", "tracking_error_max_m", "closest_robots_m",
    "formation_connected_share",
)


@dataclass(frozen=True)
class Trial:
    scenario: str
    method: str
    seed: int
    duration_s: float
    overrides: tuple[str, ...] = ()

    @property
    def key(self) -> str:
        return json.dumps([self.scenario, self.method, self.seed, float(self.duration_s), list(self.overrides)])


def trials_for(scenarios: Iterable[str], methods: Iterable[str], seeds: Iterable[int], duration_s: float,
               overrides: Iterable[str] = ()) -> list[Trial]:
    overrides = tuple(overrides)
    return [Trial(s, m, seed, float(duration_s), overrides) for s in scenarios for seed in seeds for m in methods]


def load_trial(trial: Trial):
    """The trial's validated Scenario (ConfigError on bad input)."""
    from sim.scenario import load

    overrides = [*trial.overrides, f"strategy.kind={trial.method}"]
    return load(trial.scenario, overrides, seed=trial.seed, duration_s=trial.duration_s)


def run_trial(trial: Trial) -> dict:
    """Run one trial headless; the row written to trials.jsonl."""
    import os

    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    from sim.loop import run

    start = time.perf_counter()
    row = {"key": trial.key, **asdict(trial)}
    row["overrides"] = list(trial.overrides)
    try:
        result = run(load_trial(trial))
        row["status"] = result.status
        row["message"] = result.metrics.get("message", "")
        row.update({k: result.metrics.get(k) for k in ROW_METRICS})
    except Exception as err:  # a failed trial is recorded and retried on the next call
        row["status"] = "error"
        row["message"] = f"{type(err).__name__}: {err}"
    row["trial_wall_s"] = time.perf_counter() - start
    return row


def read_rows(path: Path) -> list[dict]:
    if not path.is_file():
        return []
    rows = []
    with open(path) as f:
        for line in f:
            line = line.strip()
            if line:
                try:
                    rows.append(json.loads(line))
                except json.JSONDecodeError:
                    continue  # a line cut by an interruption
    return rows


def finished_keys(rows: Iterable[dict]) -> set[str]:
    return {r["key"] for r in rows if r.get("status") in ("completed", "time limit", "diverged")}


def run_trials(trials: list[Trial], path: Path, jobs: int = 1,
               progress: Callable[[str], None] | None = None) -> list[dict]:
    """Run the trials not yet in ``path`` (``jobs`` processes), appending rows."""
    path.parent.mkdir(parents=True, exist_ok=True)
    done = finished_keys(read_rows(path))
    todo = [t for t in trials if t.key not in done]
    say = progress or (lambda text: None)
    say(f"{len(trials) - len(todo)} of {len(trials)} trials already in {path}; running {len(todo)}")

    def append(row: dict, index: int) -> None:
        with open(path, "a") as f:
            f.write(json.dumps(row) + "\n")
        e_g = row.get("e_g_mean_m")
        lam = row.get("lambda_bar_mean_m2")
        figures = f"e_g {e_g:.3f} m, lambda-bar {lam:.3f} m^2" if e_g is not None and lam is not None else row.get("message", "")
        say(f"[{index}/{len(todo)}] {row['scenario']} {row['method']} seed {row['seed']}: {row['status']}, "
            f"{figures} ({row['trial_wall_s']:.0f} s)")

    if jobs <= 1:
        for index, trial in enumerate(todo, 1):
            append(run_trial(trial), index)
    else:
        with ProcessPoolExecutor(max_workers=jobs, mp_context=get_context("spawn")) as pool:
            futures = [pool.submit(run_trial, trial) for trial in todo]
            for index, future in enumerate(as_completed(futures), 1):
                append(future.result(), index)
    return read_rows(path)


@dataclass(frozen=True)
class Cell:
    """Statistics of one (scenario, method) over its seeds."""

    runs: int
    e_g: float  # mean over seeds of e_g-bar, m
    e_g_time_std: float  # mean over seeds of the std over time, m
    e_g_seed_std: float  # std over seeds of e_g-bar, m
    lam: float  # mean over seeds of lambda-bar, m^2
    lam_time_std: float
    lam_seed_std: float
    seeds: tuple[int, ...]
    e_g_by_seed: dict
    lam_by_seed: dict


def summarize(rows: Iterable[dict], scenarios: Iterable[str], methods: Iterable[str], seeds: Iterable[int],
              duration_s: float, overrides: Iterable[str] = ()) -> dict[tuple[str, str], Cell]:
    """Cells of the table from the rows of the requested trials (latest row per trial)."""
    wanted = {t.key: t for t in trials_for(scenarios, methods, seeds, duration_s, overrides)}
    latest: dict[str, dict] = {}
    for row in rows:
        if row.get("key") in wanted and row.get("status") == "completed" and row.get("e_g_mean_m") is not None:
            latest[row["key"]] = row
    out = {}
    for scenario in scenarios:
        for method in methods:
            chosen = [r for r in latest.values() if r["scenario"] == scenario and r["method"] == method]
            chosen.sort(key=lambda r: r["seed"])
            if not chosen:
                continue
            e_g = np.array([r["e_g_mean_m"] for r in chosen])
            lam = np.array([r["lambda_bar_mean_m2"] for r in chosen])
            out[(scenario, method)] = Cell(
                runs=len(chosen),
                e_g=float(e_g.mean()), e_g_time_std=float(np.mean([r["e_g_std_m"] for r in chosen])),
                e_g_seed_std=float(e_g.std()),
                lam=float(lam.mean()), lam_time_std=float(np.mean([r["lambda_bar_std_m2"] for r in chosen])),
                lam_seed_std=float(lam.std()),
                seeds=tuple(r["seed"] for r in chosen),
                e_g_by_seed={r["seed"]: r["e_g_mean_m"] for r in chosen},
                lam_by_seed={r["seed"]: r["lambda_bar_mean_m2"] for r in chosen},
            )
    return out


def _targets_of(scenario: str) -> int | None:
    try:
        from sim.scenario import read_table

        table, _ = read_table(scenario)
        return len(table.get("targets", []))
    except Exception:
        return None


def wins(cells: dict, scenario: str, metric: str) -> dict[str, tuple[int, int]]:
    """Per baseline: (seeds where intermittent is lower, seeds compared)."""
    out = {}
    mine = cells.get((scenario, "intermittent"))
    if mine is None:
        return out
    for method in ("all_time", "random_meeting"):
        other = cells.get((scenario, method))
        if other is None:
            continue
        a = getattr(mine, f"{metric}_by_seed")
        b = getattr(other, f"{metric}_by_seed")
        common = sorted(set(a) & set(b))
        out[method] = (sum(a[s] < b[s] for s in common), len(common))
    return out


def format_table(cells: dict, scenarios: list[str], methods: list[str], duration_s: float) -> str:
    """Markdown: our figures beside the paper's Table I."""
    lines = []
    for scenario in scenarios:
        n_targets = _targets_of(scenario)
        paper = PAPER_TABLE.get(n_targets, {})
        runs = [cells[(scenario, m)].runs for m in methods if (scenario, m) in cells]
        lines.append(f"**{scenario}** ({n_targets} targets, {duration_s:g} s runs, "
                     f"{min(runs) if runs else 0} seeds per method)")
        lines.append("")
        header = "| | " + " | ".join(f"{LABELS.get(m, m)} (ours)" for m in methods) + " | " + \
                 " | ".join(f"{LABELS.get(m, m)} (paper)" for m in methods if m in paper) + " |"
        lines.append(header)
        lines.append("|" + " --- |" * (1 + len(methods) + sum(m in paper for m in methods)))
        for name, metric, unit, index in (("e_g", "e_g", "m", 0), ("lambda-bar", "lam", "m^2", 1)):
            ours = []
            for m in methods:
                cell = cells.get((scenario, m))
                if cell is None:
                    ours.append("-")
                else:
                    ours.append(f"{getattr(cell, metric):.3f} ± {getattr(cell, metric + '_time_std'):.3f} "
                                f"(seeds: ±{getattr(cell, metric + '_seed_std'):.3f})")
            theirs = [f"{paper[m][index][0]:.3f} ± {paper[m][index][1]:.3f}" for m in methods if m in paper]
            lines.append(f"| {name} ({unit}) | " + " | ".join(ours) + " | " + " | ".join(theirs) + " |")
        lines.append("")
        for name, metric in (("e_g", "e_g"), ("lambda-bar", "lam")):
            w = wins(cells, scenario, metric)
            if w:
                text = ", ".join(f"lower than {LABELS[m]} in {k}/{n} seeds" for m, (k, n) in w.items())
                lines.append(f"- intermittent {name}: {text}")
        verdict = beats_baselines(cells, scenario)
        if verdict is not None:
            lines.append(f"- intermittent beats both baselines on both mean metrics: {'yes' if verdict else 'no'}")
        lines.append("")
    return "\n".join(lines)


def beats_baselines(cells: dict, scenario: str) -> bool | None:
    mine = cells.get((scenario, "intermittent"))
    others = [cells.get((scenario, m)) for m in ("all_time", "random_meeting")]
    if mine is None or any(o is None for o in others):
        return None
    return all(mine.e_g < o.e_g and mine.lam < o.lam for o in others)


def plot_table(cells: dict, scenarios: list[str], methods: list[str], path: Path) -> None:
    """Bar chart of the table (ours, with the paper's values as markers)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, len(scenarios), figsize=(4.2 * len(scenarios), 6), squeeze=False)
    for col, scenario in enumerate(scenarios):
        paper = PAPER_TABLE.get(_targets_of(scenario), {})
        for row, (metric, label, index) in enumerate((("e_g", "e_g-bar (m)", 0), ("lam", "lambda-bar (m^2)", 1))):
            ax = axes[row, col]
            x = np.arange(len(methods))
            values = [getattr(cells[(scenario, m)], metric) if (scenario, m) in cells else math.nan for m in methods]
            spread = [getattr(cells[(scenario, m)], metric + "_seed_std") if (scenario, m) in cells else 0.0
                      for m in methods]
            ax.bar(x, values, yerr=spread, color=["#8c8c8c", "#d98c3a", "#3a78d9"][: len(methods)], capsize=4,
                   label="ours (mean, std over seeds)")
            theirs = [paper[m][index][0] if m in paper else math.nan for m in methods]
            ax.plot(x, theirs, "k_", markersize=22, mew=2, label="paper, Table I")
            ax.set_xticks(x, [LABELS.get(m, m) for m in methods])
            ax.set_ylabel(label)
            ax.set_title(scenario, fontsize=9)
            ax.grid(axis="y", alpha=0.3)
            if row == 0 and col == 0:
                ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(args) -> int:
    """``tether compare`` (arguments parsed by sim.cli)."""
    import sys

    from sim.config import ConfigError

    def fail(message: str) -> int:
        print(f"tether: error: {message}", file=sys.stderr)
        return 2

    if args.seeds < 1:
        return fail(f"--seeds: must be at least 1, got {args.seeds}")
    if args.jobs < 1:
        return fail(f"--jobs: must be at least 1, got {args.jobs}")
    if args.duration <= 0:
        return fail(f"--duration: must be positive, got {args.duration}")
    unknown = [m for m in args.methods if m not in METHODS]
    if unknown:
        return fail(f"--methods: unknown method {unknown[0]!r} (one of: {', '.join(METHODS)})")
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    trials = trials_for(args.scenarios, args.methods, seeds, args.duration, args.overrides)
    try:  # refuse bad input before running anything
        for scenario in args.scenarios:
            for method in args.methods:
                load_trial(Trial(scenario, method, seeds[0], args.duration, tuple(args.overrides)))
    except ConfigError as err:
        return fail(str(err))
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        return fail(f"--out: {out} exists and is not a folder")
    path = out / "trials.jsonl"
    if args.no_run:
        rows = read_rows(path)
    else:
        rows = run_trials(trials, path, args.jobs, progress=lambda text: print(text, file=sys.stderr, flush=True))
    cells = summarize(rows, args.scenarios, args.methods, seeds, args.duration, args.overrides)
    table = format_table(cells, list(args.scenarios), list(args.methods), args.duration)
    out.mkdir(parents=True, exist_ok=True)
    (out / "table.md").write_text(table + "\n")
    if cells:
        plot_table(cells, list(args.scenarios), list(args.methods), out / "table.png")
    print(table)
    missing = [t for t in trials if t.key not in finished_keys(rows)]
    if missing:
        print(f"{len(missing)} trial(s) not finished (see {path}); run the same command again to resume",
              file=sys.stderr)
        return 1
    return 0
