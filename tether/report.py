"""``tether report DIR``: a sweep's figures and tables, from its results table alone.

Sections are chosen by the columns and rows the table holds, so a partial
table (a sweep still running, or stopped) gives the same report with fewer
trials, and every cell states its n:

- the continuous-connectivity paper's Fig. 9 (``connected`` trials: ``completion_time_s`` against
  ``n_robots``): four rows of percentile bands, one column per scenario;
- the intermittent paper's Table I (``e_g_mean_m`` of two or more strategy kinds): mean +-
  std per method and target count, the paper's numbers beside;
- the intermittent paper's Sec. IV-A team graphs (``intermittent`` trials of two or more
  scenarios with the same targets): e_g, lambda-bar, delay against its
  bound and the t*(t) lag, the paper's figures beside;
- both paradigms against the communication range (sweep
  ``paradigms``: ``e_g_mean_m`` of two or more strategy kinds with a swept
  ``sensing.comm_range_m``): e_g and lambda-bar per method and range, mean
  and spread over seeds, a table and a plot (``paradigms.png``);
- every sweep: each numeric metric's mean +- std and n per grid cell and the
  main metrics against the first swept key (:mod:`tether.grid_report`);
- with ``--x KEY --y METRIC [--hue KEY]``: any metric against any column.

Finished rows (status "completed", or "time limit": ran to the duration cap)
enter statistics; Fig. 9's completion time counts only trials whose mission
completed, and each cell says how many stopped at the time limit. The trial
counts and failures head the report. Writes ``report.md`` and PNGs into the folder.
"""

from __future__ import annotations

import json
import math
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from sim.config import ConfigError
from sim.palette import METHOD, PAPER, hex_code
from viz.painter import REPORT_DPI
from tether.sweep import FINISHED

# Nestmeyer et al. 2017, Fig. 9: rows (column, axis label).
FIG9_ROWS = (
    ("completion_time_s", "completion time (s)"),
    ("mean_travel_m", "explorers' mean distance (m)"),
    ("max_stretch_m", "max stretch between explorers (m)"),
    ("lambda2_mean", "mean lambda2"),
)
FIG9_PERCENTILES = (10, 25, 50, 75, 90)

# Khodayi-mehr et al. 2019, Table I: (mean, +-) of e_g-bar (m) and lambda-bar (m^2), per target count and method.
PAPER_TABLE_I = {
    4: {"all_time": ((1.030, 0.466), (0.226, 0.061)),
        "random_meeting": ((1.993, 0.566), (0.405, 0.181)),
        "intermittent": ((0.879, 0.461), (0.167, 0.084))},
    8: {"all_time": ((2.517, 0.810), (0.563, 0.129)),
        "random_meeting": ((1.201, 0.570), (0.334, 0.161)),
        "intermittent": ((0.929, 0.561), (0.177, 0.068))},
}
METHOD_ORDER = ("all_time", "random_meeting", "intermittent")  # Table I's column order
# The paper's set-up as tether reproduces it (sweep table1, and teams for Sec. IV-A): the scenario of
# each target count, the duration, and the only override a trial may carry. A paper's numbers stand
# beside a sweep's only when its rows match (a user's own sweep of these methods gets ours alone).
TABLE_I_SCENARIOS = {4: "intermittent-4", 8: "intermittent-8"}
PAPER_DURATION_S = 300.0  # tether/sweeps/table1.toml and teams.toml (the built-ins' own duration too)
METHOD_LABELS = {"all_time": "all-time", "random_meeting": "random meeting", "intermittent": "intermittent",
                 "connected_tracking": "connected (Nestmeyer et al. 2017)"}
# Both paradigms on one task: the methods in plotting order, and the swept range column.
PARADIGM_METHODS = ("all_time", "random_meeting", "intermittent", "connected_tracking")
PARADIGM_COLORS = {m: hex_code(METHOD[m]) for m in PARADIGM_METHODS}
OURS_COLOR = hex_code(METHOD["intermittent"])  # a figure with one series of ours
PAPER_COLOR = hex_code(PAPER)
RANGE_COLUMN = "sensing.comm_range_m"

# Khodayi-mehr et al. 2019, Sec. IV-A (8 targets): team graph -> (e_g-bar m, lambda-bar m^2, delay bound D_G epochs).
PAPER_TEAMS = {
    "intermittent-8": ("G_T^1 (ring, 8 teams of 2)", 0.929, 0.177, 5),
    "intermittent-8-dense": ("G_T^2 (5 teams)", 1.127, 0.532, 4),
}


def _overridden_keys(row: dict) -> set[str]:
    """The keys a trial's ``--set`` overrides changed (the row's JSON list of "key=value")."""
    text = row.get("overrides")
    if not text:
        return set()
    try:
        items = json.loads(text) if isinstance(text, str) else list(text)
    except ValueError:
        return {"?"}
    return {str(item).split("=", 1)[0] for item in items}


def reproduces_paper(rows: list[dict], scenario: str, methods: set[str] | None, allowed: set[str]) -> bool:
    """Whether ``rows`` are the paper's set-up as tether reproduces it: every row of the
    built-in ``scenario`` at :data:`PAPER_DURATION_S` (or the scenario's own, which is it),
    with no override beyond the keys in ``allowed``, and (``methods``) exactly those methods."""
    if not rows:
        return False
    for r in rows:
        duration = _number(r.get("duration_s"))
        if str(r.get("scenario")) != scenario or (duration is not None and duration != PAPER_DURATION_S):
            return False
        if _overridden_keys(r) - allowed:
            return False
    return methods is None or {r.get("strategy") for r in rows} == methods


def _label(scenario: Any) -> str:
    """A scenario column value as a short label (a file path as its stem)."""
    text = str(scenario)
    return Path(text).stem if ("/" in text or text.endswith(".toml")) else text


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or value is None:
        return None
    if isinstance(value, (int, float)) and math.isfinite(value):
        return float(value)
    return None


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


# ---------------------------------------------------------------- sections

def trials_section(rows: list[dict], manifest: dict | None) -> list[str]:
    total = manifest.get("trials") if manifest else None
    finished = sum(r.get("status") in FINISHED for r in rows)
    time_limited = sum(r.get("status") == "time limit" for r in rows)
    failed = [r for r in rows if r.get("status") not in FINISHED]
    name = manifest.get("sweep", "") if manifest else ""
    lines = [f"# Sweep report{': ' + name if name else ''}", ""]
    if manifest and manifest.get("description"):
        lines += [manifest["description"], ""]
    not_run = f", {total - len(rows)} not run" if total is not None else ""
    capped = f" ({time_limited} of them stopped at their time limit)" if time_limited else ""
    lines += [f"Trials: {finished} finished{capped}, {len(failed)} failed{not_run}"
              f"{f' (of {total})' if total is not None else ''}. "
              "Statistics use finished trials only; n is given per cell.", ""]
    if failed:
        lines += ["| trial | seed | status | error |", "| --- | --- | --- | --- |"]
        for r in failed[:20]:
            error = str(r.get("error") or "").replace("|", "/").replace("\n", " ")[:160]
            lines.append(f"| {r.get('trial_id')} | {r.get('seed')} | {r.get('status')} | {error} |")
        if len(failed) > 20:
            lines.append(f"| ... {len(failed) - 20} more | | | |")
        lines.append("")
    return lines


# Fig. 9 varies the scene and the team size only; a sweep's own grid keys (the scenario's and the team
# size aside) vary what its percentiles would pool (a radio ladder, position noise, a parameter).
FIG9_AXES = frozenset({"scenario", "robots.0.count"})


def fig9_confounded(rows: list[dict]) -> bool:
    """Whether ``rows`` vary a grid key (a dotted column) other than the scene and the team size: Fig. 9
    would pool those conditions into one percentile band; the grid and study sections show them instead."""
    keys = {key for row in rows for key in row if "." in key and key not in FIG9_AXES}
    return any(len({json.dumps(row.get(key), default=str) for row in rows}) > 1 for key in keys)


def fig9_section(rows: list[dict], out: Path) -> tuple[list[str], list[Path]]:
    """The continuous-connectivity paper's Fig. 9 from connected trials: percentiles against robot count, one column per scenario."""
    mine = [r for r in rows if r.get("strategy") == "connected" and _number(r.get("n_robots")) is not None]
    if not mine or fig9_confounded(mine):
        return [], []
    done = [r for r in mine if r.get("status") in FINISHED]
    scenes = sorted({_label(r["scenario"]) for r in mine})
    counts = sorted({int(r["n_robots"]) for r in mine})
    # values[metric][scene][count] -> list; trials[scene][count] -> finished trials in the cell
    values: dict = {m: defaultdict(lambda: defaultdict(list)) for m, _ in FIG9_ROWS}
    trials: dict = defaultdict(lambda: defaultdict(int))
    capped: dict = defaultdict(lambda: defaultdict(int))  # stopped at the time limit: no completion time
    for r in done:
        scene, count = _label(r["scenario"]), int(r["n_robots"])
        trials[scene][count] += 1
        capped[scene][count] += r.get("status") == "time limit"
        for metric, _ in FIG9_ROWS:
            if metric == "completion_time_s" and r.get("status") != "completed":
                continue
            value = _number(r.get(metric))
            if value is not None:
                values[metric][scene][count].append(value)

    plt = _plt()
    fig, axes = plt.subplots(len(FIG9_ROWS), len(scenes), figsize=(3.6 * len(scenes), 2.4 * len(FIG9_ROWS)),
                             squeeze=False, sharex=True)
    for col, scene in enumerate(scenes):
        for row_i, (metric, label) in enumerate(FIG9_ROWS):
            ax = axes[row_i, col]
            xs = [c for c in counts if values[metric][scene][c]]
            if xs:
                p = np.array([np.percentile(values[metric][scene][c], FIG9_PERCENTILES) for c in xs])
                ax.fill_between(xs, p[:, 0], p[:, 4], color=OURS_COLOR, alpha=0.18, lw=0, label="10-90 %")
                ax.fill_between(xs, p[:, 1], p[:, 3], color=OURS_COLOR, alpha=0.35, lw=0, label="25-75 %")
                ax.plot(xs, p[:, 2], "o-", color=OURS_COLOR, ms=3, label="median")
                for x in xs:
                    ax.annotate(f"{len(values[metric][scene][x])}", (x, p[xs.index(x), 2]), fontsize=6,
                                textcoords="offset points", xytext=(0, 4), ha="center", color="#555")
            else:
                ax.text(0.5, 0.5, "no finished trials", ha="center", va="center", transform=ax.transAxes,
                        fontsize=8, color="#777")
            ax.grid(alpha=0.3)
            if col == 0:
                ax.set_ylabel(label, fontsize=8)
            if row_i == 0:
                ax.set_title(scene, fontsize=9)
            if row_i == len(FIG9_ROWS) - 1:
                ax.set_xlabel("robots")
                ax.set_xticks(counts)  # team sizes: integer ticks
            if row_i == 0 and col == 0 and xs:
                ax.legend(fontsize=6)
    joint = ": " if len(scenes) > 1 else ":\n"  # one column is too narrow for the title on one line
    fig.suptitle(f"Nestmeyer et al. 2017 Fig. 9{joint}percentiles over target configurations (numbers: n per point)",
                 fontsize=9)
    fig.tight_layout()
    png = out / "fig9.png"
    fig.savefig(png, dpi=REPORT_DPI)
    plt.close(fig)

    lines = ["## Nestmeyer et al. 2017, Fig. 9 (connected)", "",
             f"![Fig. 9]({png.name})", "",
             "Cells: median [25th, 75th percentile] (n = trials with a value / finished trials in the cell). "
             "Completion time counts only trials that visited every target before the scenario's cap; "
             "\"k capped\" says how many stopped at that cap instead.", ""]
    for metric, label in FIG9_ROWS:
        lines += [f"**{label}**", "", "| robots | " + " | ".join(scenes) + " |",
                  "| --- |" + " --- |" * len(scenes)]
        for c in counts:
            cells = []
            for scene in scenes:
                v = values[metric][scene][c]
                note = f", {capped[scene][c]} capped" if metric == "completion_time_s" and capped[scene][c] else ""
                if v:
                    q25, q50, q75 = np.percentile(v, (25, 50, 75))
                    cells.append(f"{q50:.3g} [{q25:.3g}, {q75:.3g}] (n={len(v)}/{trials[scene][c]}{note})")
                else:
                    cells.append(f"- (n=0/{trials[scene][c]}{note})")
            lines.append(f"| {c} | " + " | ".join(cells) + " |")
        lines.append("")
    trend = []
    for scene in scenes:
        xs = [c for c in counts if values["completion_time_s"][scene][c]]
        if len(xs) >= 2:
            first, last = (float(np.median(values["completion_time_s"][scene][c])) for c in (xs[0], xs[-1]))
            medians = [float(np.median(values["completion_time_s"][scene][c])) for c in xs]
            falling = all(b <= a for a, b in zip(medians, medians[1:]))
            trend.append(f"- {scene}: median completion {first:.0f} s at {xs[0]} robots -> {last:.0f} s at "
                         f"{xs[-1]} ({last / first:.2f}x; {'falls at every step' if falling else 'not monotone'}; "
                         "paper: roughly 0.5x from 10 to 35)")
    if trend:
        lines += ["Completion time against robot count:", "", *trend, ""]
    return lines, [png]


def _table1_cells(rows: list[dict]) -> dict:
    cells: dict = {}
    groups = defaultdict(list)
    for r in rows:
        if r.get("status") in FINISHED and _number(r.get("e_g_mean_m")) is not None \
                and _number(r.get("lambda_bar_mean_m2")) is not None:
            groups[(_moving_targets(r), r.get("strategy"))].append(r)
    for key, chosen in groups.items():
        e_g = np.array([r["e_g_mean_m"] for r in chosen])
        lam = np.array([r["lambda_bar_mean_m2"] for r in chosen])
        cells[key] = {
            "n": len(chosen),
            "e_g": float(e_g.mean()), "e_g_time_std": float(np.mean([_number(r.get("e_g_std_m")) or 0.0 for r in chosen])),
            "e_g_seed_std": float(e_g.std()),
            "lam": float(lam.mean()),
            "lam_time_std": float(np.mean([_number(r.get("lambda_bar_std_m2")) or 0.0 for r in chosen])),
            "lam_seed_std": float(lam.std()),
        }
    return cells


def _moving_targets(row: dict) -> int:
    """The trial's number of moving targets: metrics.json's ``n_moving_targets``
    (``n_targets`` in tables written before it was renamed)."""
    value = row.get("n_moving_targets")
    if value is None:
        value = row.get("n_targets")
    return int(value or 0)


def _paired_wins(rows: list[dict], n_targets: int) -> list[str]:
    """Per baseline and metric: in how many seeds (same scenario, same seed)
    the intermittent method is lower."""
    value = {}
    for r in rows:
        if r.get("status") in FINISHED and _moving_targets(r) == n_targets:
            value[(r.get("strategy"), r.get("scenario"), r.get("seed"))] = r
    out = []
    for key, name in (("e_g_mean_m", "e_g"), ("lambda_bar_mean_m2", "lambda-bar")):
        parts = []
        for baseline in ("all_time", "random_meeting"):
            pairs = [(value[("intermittent", sc, seed)][key], r[key]) for (m, sc, seed), r in value.items()
                     if m == baseline and ("intermittent", sc, seed) in value]
            pairs = [(a, b) for a, b in pairs if _number(a) is not None and _number(b) is not None]
            if pairs:
                parts.append(f"lower than {METHOD_LABELS[baseline]} in {sum(a < b for a, b in pairs)}/{len(pairs)} seeds")
        if parts:
            out.append(f"intermittent {name}: " + ", ".join(parts))
    return out


def table1_section(rows: list[dict], out: Path) -> tuple[list[str], list[Path]]:
    """The intermittent paper's Table I: mean +- std per method and target count, the paper's beside."""
    # Trials at a swept communication range belong to the paradigms section, not to Table I.
    with_e_g = [r for r in rows if "e_g_mean_m" in r and r.get("strategy") in METHOD_ORDER
                and r.get(RANGE_COLUMN) is None]
    # Only scenarios run with two or more methods compare methods (not, e.g., a teams sweep's graphs).
    methods_of = defaultdict(set)
    for r in with_e_g:
        methods_of[r.get("scenario")].add(r.get("strategy"))
    with_e_g = [r for r in with_e_g if len(methods_of[r.get("scenario")]) >= 2]
    if not with_e_g:
        return [], []
    cells = _table1_cells(with_e_g)
    targets = sorted({_moving_targets(r) for r in with_e_g})
    methods = [m for m in METHOD_ORDER if any(r.get("strategy") == m for r in with_e_g)]
    # Per target count: the paper's Table I beside ours only for its set-up (TABLE_I_SCENARIOS).
    papers = {n: PAPER_TABLE_I.get(n, {}) if reproduces_paper(
        [r for r in with_e_g if _moving_targets(r) == n], TABLE_I_SCENARIOS.get(n, ""), set(METHOD_ORDER),
        {"strategy.kind"}) else {} for n in targets}
    reproduced = any(papers.values())
    lines = ["## Khodayi-mehr et al. 2019, Table I" if reproduced else "## The meeting methods compared", "",
             "Ours: mean over trials of each run's time average, +- the mean over trials of each run's std "
             "over time (how the paper reports a run), then the std of the run averages across seeds, and n. "
             + ("Paper: Table I, beside the target counts run in its set-up (sweep table1: "
                + ", ".join(f"{n} targets in {TABLE_I_SCENARIOS[n]}" for n in TABLE_I_SCENARIOS)
                + f", {PAPER_DURATION_S:g} s, all three methods)." if reproduced else
                "The intermittent paper's Table I is not shown: these trials are not its set-up (sweep table1: "
                + ", ".join(f"{TABLE_I_SCENARIOS[n]}" for n in TABLE_I_SCENARIOS)
                + f", {PAPER_DURATION_S:g} s, all three methods, no other overrides)."), ""]
    for n_targets in targets:
        paper = papers[n_targets]
        header = ["", *(f"{METHOD_LABELS[m]} (ours)" for m in methods),
                  *(f"{METHOD_LABELS[m]} (paper)" for m in methods if m in paper)]
        lines += [f"**{n_targets} targets**", "", "| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
        for name, key, unit, index in (("e_g", "e_g", "m", 0), ("lambda-bar", "lam", "m^2", 1)):
            ours = []
            for m in methods:
                c = cells.get((n_targets, m))
                ours.append("- (n=0)" if c is None else
                            f"{c[key]:.3f} ± {c[key + '_time_std']:.3f} (seeds ±{c[key + '_seed_std']:.3f}, n={c['n']})")
            theirs = [f"{paper[m][index][0]:.3f} ± {paper[m][index][1]:.3f}" for m in methods if m in paper]
            lines.append(f"| {name} ({unit}) | " + " | ".join(ours) + (" | " + " | ".join(theirs) if theirs else "")
                         + " |")
        mine = cells.get((n_targets, "intermittent"))
        others = [cells.get((n_targets, m)) for m in ("all_time", "random_meeting")]
        if mine and all(others):
            beats = all(mine["e_g"] < o["e_g"] and mine["lam"] < o["lam"] for o in others)
            lines += ["", f"Intermittent beats both baselines on both means: {'yes' if beats else 'no'}."]
        lines += [f"- {text}" for text in _paired_wins(with_e_g, n_targets)]
        lines.append("")

    plt = _plt()
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    fig, axes = plt.subplots(2, len(targets), figsize=(4.6 * len(targets), 6.4), squeeze=False)
    for col, n_targets in enumerate(targets):
        paper = papers[n_targets]
        for row_i, (key, label, index) in enumerate((("e_g", "e_g-bar, time average (m)", 0),
                                                     ("lam", "lambda-bar (m²)", 1))):
            ax = axes[row_i, col]
            x = np.arange(len(methods))
            c = [cells.get((n_targets, m)) for m in methods]
            ax.bar(x, [v[key] if v else math.nan for v in c], yerr=[v[key + "_seed_std"] if v else 0 for v in c],
                   color=[PARADIGM_COLORS[m] for m in methods], capsize=4, width=0.6)
            if paper:  # beside the bar, not over it: the bar's top and its error bar stay readable
                ax.plot(x + 0.38, [paper[m][index][0] if m in paper else math.nan for m in methods], "_",
                        color=PAPER_COLOR, ms=14, mew=3)
            # n in the tick label: a label drawn in the plot can sit under a marker.
            ax.set_xticks(x, [f"{METHOD_LABELS[m]}\nn={v['n'] if v else 0}" for m, v in zip(methods, c)],
                          fontsize=9)
            ax.set_ylabel(label, fontsize=9)
            ax.set_ylim(bottom=0)
            ax.set_title(f"{n_targets} targets", fontsize=10)
            ax.grid(axis="y", alpha=0.3)
    handles = [Patch(color=PARADIGM_COLORS[m], label=f"{METHOD_LABELS[m]} (ours: mean, std over seeds)")
               for m in methods]
    if reproduced:
        handles.append(Line2D([], [], color=PAPER_COLOR, marker="_", ls="", ms=14, mew=3,
                              label="Khodayi-mehr et al. 2019, Table I"))
    columns = 1 if len(targets) == 1 else min(len(handles), 2)  # one panel wide: the labels would be cut
    fig.legend(handles=handles, loc="lower center", ncol=columns, fontsize=9, frameon=False)
    fig.tight_layout(rect=(0, 0.045 * math.ceil(len(handles) / columns) + 0.015, 1, 1))
    return _with_figure(lines, fig, out / "table1.png", "Table I" if reproduced else "meeting methods")


def _with_figure(lines: list[str], fig, png: Path, alt: str) -> tuple[list[str], list[Path]]:
    """Save ``fig`` as ``png`` and place it under the section's heading (the first two lines)."""
    fig.savefig(png, dpi=REPORT_DPI)
    _plt().close(fig)
    return [*lines[:2], f"![{alt}]({png.name})", "", *lines[2:]], [png]


def paradigms_section(rows: list[dict], out: Path) -> tuple[list[str], list[Path]]:
    """Both paradigms on the intermittent paper's task: e_g and lambda-bar of every method against the communication range."""
    chosen = [r for r in rows if r.get("status") in FINISHED and _number(r.get(RANGE_COLUMN)) is not None
              and r.get("strategy") in PARADIGM_METHODS and _number(r.get("e_g_mean_m")) is not None
              and _number(r.get("lambda_bar_mean_m2")) is not None]
    methods = [m for m in PARADIGM_METHODS if any(r.get("strategy") == m for r in chosen)]
    ranges = sorted({float(r[RANGE_COLUMN]) for r in chosen})
    if len(methods) < 2 or len(ranges) < 2:
        return [], []
    cells = {}
    for m in methods:
        for rng in ranges:
            group = [r for r in chosen if r.get("strategy") == m and float(r[RANGE_COLUMN]) == rng]
            if group:
                e_g = np.array([float(r["e_g_mean_m"]) for r in group])
                lam = np.array([float(r["lambda_bar_mean_m2"]) for r in group])
                cells[(m, rng)] = {"n": len(group), "e_g": e_g, "lam": lam}
    lines = ["## Both paradigms against the communication range", "",
             "Per method and range: mean over seeds of each run's time-averaged e_g (m) and lambda-bar (m^2), "
             "+- their std over seeds, [min, max] over seeds, and n (finished trials).", ""]
    for key, name in (("e_g", "e_g (m)"), ("lam", "lambda-bar (m^2)")):
        lines += [f"**{name}**", "", "| method | " + " | ".join(f"R = {rng:g} m" for rng in ranges) + " |",
                  "|" + " --- |" * (1 + len(ranges))]
        for m in methods:
            row = []
            for rng in ranges:
                c = cells.get((m, rng))
                row.append("- (n=0)" if c is None else f"{c[key].mean():.3f} ± {c[key].std():.3f} "
                           f"[{c[key].min():.3f}, {c[key].max():.3f}] (n={c['n']})")
            lines.append(f"| {METHOD_LABELS[m]} | " + " | ".join(row) + " |")
        lines.append("")
    plt = _plt()
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, (key, label) in zip(axes, (("e_g", "e_g, time average (m)"), ("lam", "lambda-bar (m^2)"))):
        for m in methods:
            xs = [rng for rng in ranges if (m, rng) in cells]
            mean = np.array([cells[(m, rng)][key].mean() for rng in xs])
            low = np.array([cells[(m, rng)][key].min() for rng in xs])
            high = np.array([cells[(m, rng)][key].max() for rng in xs])
            ax.plot(xs, mean, "o-", color=PARADIGM_COLORS[m], label=METHOD_LABELS[m])
            ax.fill_between(xs, low, high, color=PARADIGM_COLORS[m], alpha=0.15)
        ax.set_xscale("log")
        ax.minorticks_off()
        ax.set_xticks(ranges, [f"{rng:g}" for rng in ranges])
        ax.set_xlabel("communication range R (m)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("mean over seeds; band: min-max over seeds", fontsize=9)
    fig.tight_layout()
    return _with_figure(lines, fig, out / "paradigms.png", "paradigms")


def teams_section(rows: list[dict], out: Path) -> tuple[list[str], list[Path]]:
    """Khodayi-mehr et al. 2019 Sec. IV-A: the team graphs compared on the same targets."""
    mine = [r for r in rows if r.get("strategy") == "intermittent" and "e_g_mean_m" in r]
    by_targets = defaultdict(set)
    for r in mine:
        by_targets[_moving_targets(r)].add(_label(r["scenario"]))
    compared = {n: s for n, s in by_targets.items() if len(s) >= 2}
    if not compared:
        return [], []
    columns = (("e_g_mean_m", "e_g-bar (m)"), ("lambda_bar_mean_m2", "lambda-bar (m^2)"),
               ("delay_bound_epochs", "delay bound D_G (epochs)"),
               ("max_delay_epochs_observed", "max observed delay (epochs)"),
               ("t_star_lag_mean_s", "t - t*(t) mean (s)"), ("t_star_lag_max_s", "t - t*(t) max (s)"))
    lines = ["## Khodayi-mehr et al. 2019, Sec. IV-A: team graphs", "",
             "Ours: mean ± std over finished trials (n). Paper: 8 targets, one run each, beside the scenarios "
             f"run in its set-up (sweep teams: {PAPER_DURATION_S:g} s, no other overrides).", "",
             "| scenario | team graph | n | " + " | ".join(label for _, label in columns)
             + " | paper e_g-bar (m) | paper lambda-bar (m^2) | paper D_G |",
             "|" + " --- |" * (3 + len(columns) + 3)]
    stats = {}
    for n_targets in sorted(compared, key=lambda n: n or 0):
        for scenario in sorted(compared[n_targets]):
            chosen = [r for r in mine if _label(r["scenario"]) == scenario and r.get("status") in FINISHED]
            cell = []
            stats[scenario] = {}
            for key, _ in columns:
                v = [x for x in (_number(r.get(key)) for r in chosen) if x is not None]
                stats[scenario][key] = (float(np.mean(v)), float(np.std(v))) if v else None
                cell.append(f"{np.mean(v):.3f} ± {np.std(v):.3f}" if v else "-")
            graph, e_g, lam, bound = PAPER_TEAMS.get(scenario, ("?", None, None, None))
            if not reproduces_paper([r for r in mine if _label(r["scenario"]) == scenario], scenario, None,
                                    {"strategy.kind"}):
                e_g = lam = bound = None  # not the paper's set-up: its figures would compare unlike runs
            paper = [f"{e_g:.3f}" if e_g else "-", f"{lam:.3f}" if lam else "-", str(bound) if bound else "-"]
            lines.append(f"| {scenario} | {graph} | {len(chosen)} | " + " | ".join(cell) + " | " + " | ".join(paper)
                         + " |")
    lines.append("")

    plt = _plt()
    from matplotlib.lines import Line2D
    from matplotlib.patches import Patch

    scenarios = list(stats)
    paper_of = {s: PAPER_TEAMS[s] for s in scenarios if s in PAPER_TEAMS and reproduces_paper(
        [r for r in mine if _label(r["scenario"]) == s], s, None, {"strategy.kind"})}
    fig, axes = plt.subplots(1, 3, figsize=(11, 3.8))
    for ax, (key, label, paper_index) in zip(axes, (("e_g_mean_m", "e_g-bar (m)", 1),
                                                    ("lambda_bar_mean_m2", "lambda-bar (m²)", 2),
                                                    ("t_star_lag_mean_s", "mean t - t*(t) (s)", None))):
        x = np.arange(len(scenarios))
        v = [stats[s][key] or (math.nan, 0.0) for s in scenarios]
        ax.bar(x, [a for a, _ in v], yerr=[b for _, b in v], color=OURS_COLOR, capsize=4, width=0.6)
        if paper_index is not None and paper_of:
            ax.plot(x + 0.38, [paper_of[s][paper_index] if s in paper_of else math.nan for s in scenarios], "_",
                    color=PAPER_COLOR, ms=14, mew=3)
        ax.set_xticks(x, scenarios, fontsize=8)
        ax.set_ylabel(label, fontsize=9)
        ax.set_ylim(bottom=0)
        ax.grid(axis="y", alpha=0.3)
    handles = [Patch(color=OURS_COLOR, label="ours: mean, std over seeds")]
    if paper_of:
        handles.append(Line2D([], [], color=PAPER_COLOR, marker="_", ls="", ms=14, mew=3,
                              label="Khodayi-mehr et al. 2019, Sec. IV-A"))
    fig.legend(handles=handles, loc="lower center", ncol=len(handles), fontsize=9, frameon=False)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    return _with_figure(lines, fig, out / "teams.png", "team graphs")


def generic_section(rows: list[dict], out: Path, x: str, y: str, hue: str | None) -> tuple[list[str], list[Path]]:
    """Any metric against any column: median and 25-75 % band per x, one line per hue value."""
    done = [r for r in rows if r.get("status") in FINISHED and _number(r.get(y)) is not None]
    groups: dict = defaultdict(lambda: defaultdict(list))
    for r in done:
        groups[_label(r.get(hue)) if hue else ""][r.get(x)].append(float(r[y]))
    xs_all = sorted({r.get(x) for r in done}, key=lambda v: (isinstance(v, str), v))
    numeric = all(_number(v) is not None for v in xs_all)
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    lines = [f"## {y} against {x}" + (f" by {hue}" if hue else ""), ""]
    for name, by_x in sorted(groups.items()):
        xs = [v for v in xs_all if by_x.get(v)]
        pos = xs if numeric else [xs_all.index(v) for v in xs]
        p = np.array([np.percentile(by_x[v], (25, 50, 75)) for v in xs])
        ax.fill_between(pos, p[:, 0], p[:, 2], alpha=0.25, lw=0)
        ax.plot(pos, p[:, 1], "o-", ms=3, label=f"{hue}={name} (median, 25-75 %)" if hue else "median, 25-75 %")
    if not numeric:
        ax.set_xticks(range(len(xs_all)), [_label(v) for v in xs_all], fontsize=7, rotation=20)
    if not done:
        ax.text(0.5, 0.5, "no finished trials", ha="center", va="center", transform=ax.transAxes)
    ax.set_xlabel(x)
    ax.set_ylabel(y)
    ax.grid(alpha=0.3)
    if groups:
        ax.legend(fontsize=7)
    fig.tight_layout()
    safe = "".join(ch if ch.isalnum() or ch in "_-" else "_" for ch in f"{y}_vs_{x}" + (f"_by_{hue}" if hue else ""))
    png = out / f"plot_{safe}.png"
    fig.savefig(png, dpi=REPORT_DPI)
    plt.close(fig)
    lines += [f"![{y} against {x}]({png.name})", "", f"| {hue or ''} | {x} | n | median | 25 % | 75 % |",
              "| --- | --- | --- | --- | --- | --- |"]
    for name, by_x in sorted(groups.items()):
        for v in xs_all:
            if by_x.get(v):
                q25, q50, q75 = np.percentile(by_x[v], (25, 50, 75))
                lines.append(f"| {name} | {v} | {len(by_x[v])} | {q50:.4g} | {q25:.4g} | {q75:.4g} |")
    lines.append("")
    return lines, [png]


# ---------------------------------------------------------------- entry point

def write_report(results: str | Path, out: str | Path | None = None, x: str | None = None, y: str | None = None,
                 hue: str | None = None) -> list[Path]:
    """Write report.md and the PNGs; returns their paths (report.md first).
    ConfigError if there is no readable table or a named column is missing."""
    from sim.outputs import check_out_folder, read_manifest, written_by_tether, write_manifest
    from tether.sweep import MANIFEST_FILE, read_results

    if out is not None:  # first, tether's output policy: new, empty, or a report's / sweep's folder
        check_out_folder(out, "report", "--out")
    source = Path(results)
    table = read_results(source)
    if table is None:
        raise ConfigError("DIR", f"{source}: no results (no trials/*.parquet or results.parquet)")
    rows = table.to_pylist()
    for flag, key in (("--x", x), ("--y", y), ("--hue", hue)):  # before anything is written
        if key is not None and key not in table.column_names:
            raise ConfigError(flag, f"no column {key!r} in the table (columns: {', '.join(sorted(table.column_names))})")
    manifest = None
    if (source / MANIFEST_FILE).is_file():
        try:
            manifest = json.loads((source / MANIFEST_FILE).read_text())
        except (OSError, ValueError):
            manifest = None  # the report needs only the table
    target = Path(out) if out is not None else (source if source.is_dir() else source.parent)
    marked = target.is_dir() and written_by_tether(target, "report")
    target.mkdir(parents=True, exist_ok=True)
    lines = trials_section(rows, manifest)
    pngs: list[Path] = []
    for section in (fig9_section, table1_section, paradigms_section, teams_section):
        text, files = section(rows, target)
        lines += text
        pngs += files
    from tether.grid_report import grid_section
    from tether.study_report import study_section

    text, files = study_section(rows, target, manifest)  # the faults study: radio ladder, noise, failures
    lines += text
    pngs += files

    text, files = grid_section(rows, manifest, target)  # every sweep, the user's own included
    lines += text
    pngs += files
    if x is not None and y is not None:
        text, files = generic_section(rows, target, x, y, hue)
        lines += text
        pngs += files
    report = target / "report.md"
    tmp = target / ".report.md.tmp"
    tmp.write_text("\n".join(lines) + "\n")
    tmp.replace(report)
    written = {p.name for p in (report, *pngs)}
    own = read_manifest(target)
    if own is not None and own.get("kind") == "report":
        written |= set(own["files"])
    if own is not None or not marked:  # a new folder: mark it as a report's
        write_manifest(target, "report", written)
    return [report, *pngs]
