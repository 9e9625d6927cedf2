"""The part of ``tether report`` every sweep gets, the user's own included:
each numeric metric's mean +- std and n per grid cell (a table in
``report.md`` and ``grid.csv``), and a figure of the main metrics against the
first swept key (``grid.png``), one line per value of the second.

A grid cell is one combination of the swept keys (the sweep file's
``[grid]`` and ``[[zip]]`` keys, in the file's order); its trials differ by
seed only. Only finished trials (completed or time limit) enter the
statistics, like the paper sections of :mod:`tether.report`.
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from tether.sweep import FINISHED
from viz.painter import REPORT_DPI

# Columns that describe a trial rather than measure it.
BOOKKEEPING = frozenset({"trial_id", "trial_index", "seed", "attempt", "duration_s", "overrides", "status", "error",
                         "host", "finished_at", "strategy", "scenario", "timing"})
# The figure's metrics, the first present first (at most FIGURE_PANELS): each method's headline figures.
MAIN_METRICS = ("completion_time_s", "targets_visited", "e_g_mean_m", "lambda_bar_mean_m2", "lambda2_mean",
                "comm_lambda2_min", "mean_travel_m", "meetings_held", "tracking_error_mean_m")
FIGURE_PANELS = 4
# The figure's axis labels: words and a unit (other columns: viz.plots.axis_label, from the key's suffix).
METRIC_LABELS = {
    "completion_time_s": "mission time (s)",
    "targets_visited": "targets visited (count)",
    "e_g_mean_m": "e_g, time average (m)",
    "lambda_bar_mean_m2": "lambda-bar, time average (m²)",
    "lambda2_mean": "lambda2, time average (1)",
    "comm_lambda2_min": "lowest lambda2, comm. graph (1)",
    "mean_travel_m": "distance travelled, mean (m)",
    "meetings_held": "meetings held (count)",
    "tracking_error_mean_m": "tracking error, mean (m)",
}


def swept_keys(rows: list[dict], manifest: dict | None) -> list[str]:
    """The sweep's swept keys in its file's order (grid, then zip groups); without a
    manifest, the dotted columns (and ``scenario``) that take more than one value."""
    definition = (manifest or {}).get("definition") or {}
    keys = list(definition.get("grid") or {})
    for group in definition.get("zip") or []:
        keys += [k for k in group if k not in keys]
    if keys or manifest:
        return [k for k in keys if any(k in r for r in rows)]
    columns = sorted({k for r in rows for k in r if "." in k or k == "scenario"})
    return [k for k in columns if len({json.dumps(r.get(k), sort_keys=True, default=str) for r in rows}) > 1]


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return float(value)


def _key(value: Any) -> tuple:
    """An order for cell values: numbers by value, then anything else by its text."""
    number = _number(value)
    return (0, number, "") if number is not None else (1, 0.0, str(value))


def _text(value: Any) -> str:
    text = str(value)
    return Path(text).stem if ("/" in text or text.endswith(".toml")) else text


def metric_columns(rows: list[dict], keys: list[str]) -> list[str]:
    """Every column holding a number in some finished row, in the table's order."""
    seen: dict[str, None] = {}
    for r in rows:
        for k, v in r.items():
            if k not in BOOKKEEPING and k not in keys and _number(v) is not None:
                seen.setdefault(k, None)
    return list(seen)


def value_orders(manifest: dict | None) -> dict[str, list]:
    """Each swept key's values in the sweep file's order (the cells' order)."""
    definition = (manifest or {}).get("definition") or {}
    orders = {k: list(v) for k, v in (definition.get("grid") or {}).items() if isinstance(v, list)}
    for group in definition.get("zip") or []:
        orders.update({k: list(v) for k, v in group.items() if isinstance(v, list)})
    return orders


def _ordered(keys: list[str], orders: dict[str, list]):
    """A sort key for cell values: the file's order where known, else numbers by value then text."""
    def key(values: tuple) -> tuple:
        out = []
        for k, v in zip(keys, values):
            known = orders.get(k, [])
            out.append((0, known.index(v), 0.0, "") if v in known else (1, 0, *_key(v)[1:]))
        return tuple(out)
    return key


def cell_statistics(rows: list[dict], keys: list[str], metrics: list[str],
                    orders: dict[str, list] | None = None) -> list[tuple[tuple, dict]]:
    """[(cell values, {metric: (mean, std, n)})] in the sweep file's order of the values; std
    is the sample std (ddof 1; 0 for one trial), n the finished trials with a number."""
    cells: dict[str, tuple[tuple, list[dict]]] = {}
    for r in rows:
        values = tuple(r.get(k) for k in keys)
        cells.setdefault(json.dumps(values, default=str), (values, []))[1].append(r)
    out = []
    for values, members in sorted(cells.values(), key=lambda c: _ordered(keys, orders or {})(c[0])):
        stats = {}
        for m in metrics:
            data = np.array([x for x in (_number(r.get(m)) for r in members) if x is not None])
            if len(data):
                stats[m] = (float(data.mean()), float(data.std(ddof=1)) if len(data) > 1 else 0.0, len(data))
        out.append((values, stats))
    return out


def naming_keys(keys: list[str], manifest: dict | None) -> set[str]:
    """The swept keys that name a cell: every grid key and the first of each zip group (the rest
    of a group move with it, and a list of start positions made labels run off the figure)."""
    followers = {k for group in ((manifest or {}).get("definition") or {}).get("zip") or [] for k in list(group)[1:]}
    return {k for k in keys if k not in followers}


def _cell_name(keys: list[str], values: tuple, named: set[str] | None = None) -> str:
    return ", ".join(f"{k}={_text(v)}" for k, v in zip(keys, values) if named is None or k in named) or "all trials"


def grid_section(rows: list[dict], manifest: dict | None, out: Path) -> tuple[list[str], list[Path]]:
    """The table and figure of every sweep; (report lines, files written)."""
    done = [r for r in rows if r.get("status") in FINISHED]
    keys = swept_keys(rows, manifest)
    lines = ["## Every metric per grid cell", ""]
    if not done:
        return lines + ["No finished trials yet.", ""], []
    metrics = metric_columns(done, keys)
    cells = cell_statistics(done, keys, metrics, value_orders(manifest))
    swept = ", ".join(f"`{k}`" for k in keys) if keys else "nothing (the seeds only)"
    lines += [f"Swept: {swept}. Each cell: mean ± std over its finished trials (seeds), and n. "
              "Every figure also in `grid.csv`.", ""]
    files = [_write_csv(out / "grid.csv", keys, cells)]
    named = naming_keys(keys, manifest)
    png = _figure(out / "grid.png", keys, cells, metrics, named)
    if png is not None:
        lines += [f"![main metrics against {keys[0] if keys else 'the cells'}]({png.name})", ""]
        files.append(png)
    names = [_cell_name(keys, values, named) for values, _ in cells]
    lines += ["| metric | " + " | ".join(n.replace("|", "/") for n in names) + " |",
              "| --- |" + " --- |" * len(names)]
    for m in metrics:
        row = []
        for _, stats in cells:
            mean, std, n = stats.get(m, (None, None, 0))
            row.append(f"{mean:.4g} ± {std:.2g} (n={n})" if n else "-")
        lines.append(f"| {m} | " + " | ".join(row) + " |")
    lines.append("")
    return lines, files


def _write_csv(path: Path, keys: list[str], cells: list[tuple[tuple, dict]]) -> Path:
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow([*keys, "metric", "mean", "std", "n"])
        for values, stats in cells:
            for m, (mean, std, n) in stats.items():
                writer.writerow([*values, m, f"{mean:.10g}", f"{std:.10g}", n])
    tmp.replace(path)
    return path


def main_metrics(metrics: list[str]) -> list[str]:
    """The figure's metrics: the headline ones present, else the first columns."""
    chosen = [m for m in MAIN_METRICS if m in metrics][:FIGURE_PANELS]
    return chosen or metrics[:FIGURE_PANELS]


def _figure(png: Path, keys: list[str], cells: list[tuple[tuple, dict]], metrics: list[str],
            named: set[str] | None = None) -> Path | None:
    """Each main metric against the first swept key: mean +- std per cell, one line per
    value of the second key (cells differing in further keys are drawn as separate lines too)."""
    chosen = main_metrics(metrics)
    if not chosen:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    xs = list(dict.fromkeys(values[0] if keys else "all" for values, _ in cells))  # the cells' order
    numeric = all(_number(v) is not None for v in xs)
    lines: dict[tuple, list[tuple[Any, tuple]]] = {}
    for values, stats in cells:
        lines.setdefault(values[1:], []).append((values[0] if keys else "all", stats))
    from matplotlib.ticker import MaxNLocator

    from sim.palette import SERIES
    from viz.painter import axis_from_zero
    from viz.plots import axis_label

    fig, axes = plt.subplots(1, len(chosen), figsize=(4.2 * len(chosen), 3.9), squeeze=False)
    colors = {rest: tuple(SERIES[k % len(SERIES)]) for k, rest in enumerate(lines)}
    for ax, metric in zip(axes[0], chosen):
        means = []
        for index, (rest, points) in enumerate(lines.items()):
            points = [(x, s[metric]) for x, s in sorted(points, key=lambda p: float(p[0]) if numeric else xs.index(p[0])) if metric in s]
            if not points:
                continue
            # Categories side by side, unjoined (a line between two methods means nothing).
            shift = 0.0 if numeric else (index - (len(lines) - 1) / 2) * 0.08
            pos = [(float(x) if numeric else xs.index(x)) + shift for x, _ in points]
            label = _cell_name(keys[1:], rest, named) if rest else None
            ax.errorbar(pos, [s[0] for _, s in points], yerr=[s[1] for _, s in points], marker="o", ms=5,
                        capsize=3, label=label, color=colors[rest], ls="-" if numeric else "none")
            means += [s[0] for _, s in points]
        if not numeric:
            ax.set_xticks(range(len(xs)), [_text(x) for x in xs], fontsize=9, rotation=20 if len(xs) > 3 else 0)
            ax.set_xlim(-0.5, len(xs) - 0.5)
        label = METRIC_LABELS.get(metric) or axis_label(metric)
        if label.endswith("(count)") or (means and all(float(m).is_integer() for m in means) and "(" not in label):
            ax.yaxis.set_major_locator(MaxNLocator(integer=True, min_n_ticks=1))
        if means:
            axis_from_zero(ax, min(means), max(means))
        ax.set_xlabel(keys[0] if keys else "", fontsize=10)
        ax.set_ylabel(label, fontsize=10)
        ax.tick_params(labelsize=9)
        ax.grid(alpha=0.3)
    handles, labels = axes[0][0].get_legend_handles_labels()
    if labels:
        fig.legend(handles, labels, fontsize=9, loc="lower center", ncol=min(len(labels), 4))
    fig.suptitle("mean ± std over seeds per grid cell", fontsize=10)
    fig.tight_layout(rect=(0, 0.1 if labels else 0, 1, 1))
    fig.savefig(png, dpi=REPORT_DPI)
    plt.close(fig)
    return png
