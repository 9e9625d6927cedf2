"""The faults study's section of ``tether report`` (sweeps ``radio-tracking``,
``radio-exploration``, ``failures``): each task metric against channel quality
per method, where each method's guarantee first breaks, and the tables.

A table gets this section when its rows carry ``radio.preset`` or a fault
(``faults`` column). Channel quality is a ladder of *rungs*: the ideal disk
first, then each real preset with its wall loss rising. What a rung delivers
differs by method (the meeting methods send bursts at the meetings, the
always-connected ones small messages over short hops), so the measured
delivery ratio (``radio_delivery_ratio``, the message bus's delivered /
addressed) is a metric per series and rung like the others, drawn in the
figure's first panel and tabled first, never one figure per rung pooled over
the methods. A *series* is a method plus every other swept key (position
noise, the failed robot, the scenario). Metrics a table lacks are left out, so
the section works on tables from before the faults' reactions existed.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from sim.palette import METHOD, SERIES, hex_code
from sim.strategy import Status
from viz.painter import REPORT_DPI
from tether.sweep import FINISHED

DIVERGED = Status.DIVERGED.value
STUDIED = (*FINISHED, DIVERGED)  # the trials the study reads (an error or a crash says nothing of a method)

CHANNEL_KEYS = ("radio.preset", "radio.wall_loss_db", "radio.tx_power_dbm")
PRESET_ORDER = ("ideal", "wifi", "nrf24", "ieee802154")
DELIVERY = "radio_delivery_ratio"
# (column, axis label); the first FIGURE_PANELS present are drawn, all present are tabled.
TASK_METRICS = (
    ("e_g_mean_m", "e_g, time average (m)"),
    ("lambda_bar_mean_m2", "lambda-bar (m^2)"),
    ("targets_visited", "targets visited"),
    ("completion_time_s", "completion time (s)"),
    ("comm_lambda2_min", "lowest lambda2 of the comm. graph"),
    (DELIVERY, "measured delivery ratio"),
    ("fault_targets_reassigned", "failed robot's targets reassigned"),
    ("fault_targets_lost", "failed robot's targets lost"),
    ("fault_meetings_missed", "meetings missed after the failure"),
    ("fault_e_g_before_fault_m", "e_g before the failure (m)"),
    ("fault_e_g_after_fault_m", "e_g after the failure (m)"),
    ("fault_detected_after_s", "failure detected after (s)"),
    ("fault_dropped_after_s", "failed robot dropped after (s)"),
    ("dropped_robots", "robots dropped from the team"),
    ("meetings_missed", "meetings missed"),
    ("e_g_before_fault_m", "e_g before the fault (m)"),
    ("e_g_after_fault_m", "e_g after the fault (m)"),
)
FIGURE_PANELS = 4
# Counts: drawn on an integer axis from 0 (no fractional or negative ticks).
COUNT_METRICS = frozenset({"targets_visited", "fault_targets_reassigned", "fault_targets_lost",
                           "fault_meetings_missed", "dropped_robots", "meetings_missed"})
FAULT_FIELDS = ("targets_reassigned", "targets_lost", "meetings_missed", "e_g_before_fault_m",
                "e_g_after_fault_m", "detected_after_s", "dropped_after_s")
SERIES_KEY_NAMES = {"faults.0.sigma_m": "position noise sigma (m)", "faults.0.robot": "failed robot"}
DODGE = 0.05  # x offset between series, so that equal series stay visible side by side
LAMBDA2_ZERO = 1e-9  # a communication graph's lambda2 at or below this is disconnected


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        return None
    return float(value)


def _broken(row: dict) -> dict[str, bool]:
    """Each guarantee this trial's metrics can judge: True where it broke, absent where unknown."""
    out = {}
    lam = _number(row.get("comm_lambda2_min"))
    if lam is not None and str(row.get("strategy", "")).startswith("connected"):
        out["comm graph disconnected (lambda2 = 0)"] = lam <= LAMBDA2_ZERO
    primes = _number(row.get("prime_travelers_max"))
    if primes is not None:
        out["two prime travelers"] = primes >= 2
    held, connected = _number(row.get("meetings_held")), _number(row.get("meetings_connected"))
    if held is not None and connected is not None and row.get("strategy") != "all_time":
        out["a meeting not connected"] = connected < held
    if isinstance(row.get("delay_bound_held"), bool):
        out["delay bound exceeded"] = not row["delay_bound_held"]
    timed_out = _number(row.get("meetings_timed_out"))
    if timed_out is not None:
        out["a meeting timed out"] = timed_out > 0
    if out or row.get("status") == DIVERGED:  # the method's own invariant (lambda2 > lambda2_min, R_c, ...)
        out = {"run diverged (an invariant broke)": row.get("status") == DIVERGED} | out
    return out


def _with_fault_fields(row: dict) -> dict:
    """The row with its first robot failure's reaction figures as ``fault_*`` columns (when present)."""
    dropped = row.get("dropped_robots")
    if isinstance(dropped, str) and dropped.startswith("["):
        try:
            dropped = json.loads(dropped)
        except ValueError:
            pass
    if isinstance(dropped, (list, tuple)):  # the robots' ids: the report counts them
        row = dict(row) | {"dropped_robots": len(dropped)}
    text = row.get("faults")
    try:
        entries = json.loads(text) if isinstance(text, str) else (text or [])
    except ValueError:
        entries = []
    failure = next((e for e in entries if isinstance(e, dict) and e.get("kind") == "robot_failure"), None)
    if failure is None:
        return row
    row = dict(row)
    for field in FAULT_FIELDS:
        if field in failure:
            row[f"fault_{field}"] = failure[field]
    return row


def _rung(row: dict) -> tuple:
    """(preset rank, preset, wall loss, -tx power): sorting puts the best channel first
    (more wall loss, then less power, is worse); -1 / +inf where the key is not swept."""
    preset = str(row.get("radio.preset") or "ideal")
    real = preset != "ideal"
    wall = _number(row.get("radio.wall_loss_db")) if real else None
    power = _number(row.get("radio.tx_power_dbm")) if real else None
    rank = PRESET_ORDER.index(preset) if preset in PRESET_ORDER else len(PRESET_ORDER)
    return (rank, preset, wall if wall is not None else -1.0, -power if power is not None else -math.inf)


def _rung_name(rung: tuple) -> str:
    _, preset, wall, minus_power = rung
    parts = [preset]
    if wall >= 0:
        parts.append(f"{wall:g} dB/wall")
    if math.isfinite(minus_power):
        parts.append(f"{-minus_power:g} dBm")
    return ", ".join(parts)


def _series_keys(rows: list[dict], manifest: dict | None) -> list[str]:
    definition = (manifest or {}).get("definition") or {}
    keys = list(definition.get("grid") or {})
    for group in definition.get("zip") or []:
        keys += [k for k in group if k not in keys]
    return [k for k in keys if k not in CHANNEL_KEYS and k != "strategy.kind"
            and len({json.dumps(r.get(k), default=str) for r in rows}) > 1]


def _series_name(row: dict, keys: list[str]) -> str:
    parts = [str(row.get("strategy"))]
    for k in keys:
        v = row.get(k)
        short = SERIES_KEY_NAMES.get(k, k)
        parts.append(str(v) if k == "scenario" else f"{short} {v}")
    return ", ".join(parts)


def study_cells(rows: list[dict], manifest: dict | None = None):
    """(rungs in channel order, series in table order, {(series, rung): [rows]}, series keys) of the finished
    and the diverged rows: a run that diverged is a guarantee broken, not a trial to leave out."""
    done = [_with_fault_fields(r) for r in rows if r.get("status") in STUDIED]
    keys = _series_keys(done, manifest)
    rungs = sorted({_rung(r) for r in done})
    series: list[str] = []
    cells: dict[tuple[str, tuple], list[dict]] = {}
    for r in done:
        name = _series_name(r, keys)
        if name not in series:
            series.append(name)
        cells.setdefault((name, _rung(r)), []).append(r)
    return rungs, series, cells, keys


def first_breaks(rungs: list[tuple], series: list[str], cells: dict) -> dict[tuple[str, str], tuple | None]:
    """{(series, guarantee): the first rung (channel order) where a trial broke it, or None if it held
    wherever it was judged}; only guarantees some trial of the series could judge."""
    out: dict[tuple[str, str], tuple | None] = {}
    for s in series:
        for rung in rungs:
            for r in cells.get((s, rung), []):
                for guarantee, broke in _broken(r).items():
                    out.setdefault((s, guarantee), None)
                    if broke and out[(s, guarantee)] is None:
                        out[(s, guarantee)] = rung
    return out


def _color(name: str, index: int) -> str:
    method = name.split(",")[0]
    if "," not in name and method in METHOD:
        return hex_code(METHOD[method])
    return hex_code(SERIES[index % len(SERIES)])


def figure_panels(present: list[tuple[str, str]], cells: dict) -> list[tuple[str, str]]:
    """The (metric, label) panels study.png draws: each series' measured delivery ratio first (when
    present), then the first FIGURE_PANELS task metrics of ``present`` but a count that is 0 in every trial
    (no robot dropped in a sweep without failures: tabled, not drawn)."""
    delivery = [(m, label) for m, label in present if m == DELIVERY]
    drawn = [(m, label) for m, label in present if m != DELIVERY and not (
        m in COUNT_METRICS and all(_number(r.get(m)) in (None, 0) for rs in cells.values() for r in rs))]
    return delivery + drawn[:FIGURE_PANELS]


def study_section(rows: list[dict], out: Path, manifest: dict | None = None) -> tuple[list[str], list[Path]]:
    """Report lines and files (``study.png``) of a faults-study table; nothing for other tables."""
    if not any("radio.preset" in r or r.get("faults") for r in rows):
        return [], []
    rungs, series, cells, _keys = study_cells(rows, manifest)
    if not cells:
        return [], []
    present = [(m, label) for m, label in TASK_METRICS
               if any(_number(r.get(m)) is not None for rs in cells.values() for r in rs)]
    present.sort(key=lambda entry: entry[0] != DELIVERY)  # each method's delivery first: what its rungs mean
    names = [_rung_name(rung) for rung in rungs]
    scenarios = sorted({str(r.get("scenario")) for rs in cells.values() for r in rs})
    delivered = any(m == DELIVERY for m, _ in present)
    lines = ["## The faults study: each method against channel quality", "",
             f"Scenario {', '.join(scenarios)}. Channel rungs from best to worst: {'; '.join(names)}. "
             + ("What each method's messages got through at each rung is its own: the table **measured delivery "
                "ratio** (the message bus's delivered / addressed, per series and rung). " if delivered else "")
             + "Each cell: median [25 %, 75 %] over its finished and diverged trials (seeds; a diverged trial's "
             "figures are those it reached before the invariant broke) and n.", ""]
    breaks = first_breaks(rungs, series, cells)
    if breaks:
        lines += ["**Where each guarantee first breaks** (the first rung at which any trial of the series broke it; "
                  "k/n: trials that broke it at that rung)", "", "| series | guarantee | first broken at |",
                  "| --- | --- | --- |"]
        for (s, guarantee), rung in breaks.items():
            if rung is None:
                where = "held at every rung"
            else:
                at = cells[(s, rung)]
                k = sum(_broken(r).get(guarantee, False) for r in at)
                where = f"{_rung_name(rung)} ({k}/{len(at)})"
            lines.append(f"| {s} | {guarantee} | {where} |")
        lines.append("")
    else:
        lines += ["No guarantee metric (comm_lambda2_min, prime_travelers_max, meetings_connected, "
                  "delay_bound_held, meetings_timed_out) in this table.", ""]
    for metric, label in present:
        lines += [f"**{label}** (`{metric}`)", "", "| series | " + " | ".join(n.replace("|", "/") for n in names) + " |",
                  "|" + " --- |" * (1 + len(rungs))]
        for s in series:
            row = []
            for rung in rungs:
                members = cells.get((s, rung), [])
                data = np.array([v for v in (_number(r.get(metric)) for r in members) if v is not None])
                if not len(data):
                    row.append(f"- (n=0/{len(members)})" if members else "-")
                    continue
                p25, p50, p75 = np.percentile(data, (25, 50, 75))
                row.append(f"{p50:.3g} [{p25:.3g}, {p75:.3g}] (n={len(data)}/{len(members)})")
            lines.append(f"| {s} | " + " | ".join(row) + " |")
        lines.append("")
    files = []
    drawn = figure_panels(present, cells)
    if drawn:
        sweep = str((manifest or {}).get("sweep") or "")
        png = _figure(out / "study.png", drawn, rungs, names, series, cells, breaks, scenarios, sweep)
        lines[2:2] = [f"![each task metric against channel quality per method]({png.name})", ""]
        files.append(png)
    return lines, files


def _value_axis(ax, metric: str) -> None:
    """The y axis of ``metric``'s panel: counts on integer ticks from 0; values equal to a few digits
    (lambda-bar is set by the targets, not the radio) would get an unreadable offset axis
    ("1e-7+2.58e-1"): plain ticks, a range of 10 % around them."""
    ax.ticklabel_format(axis="y", useOffset=False)
    low, high = ax.get_ylim()
    middle = (low + high) / 2
    if metric == DELIVERY:  # a ratio: its whole range, so that rungs and methods compare at a glance
        ax.set_ylim(0.0, 1.04)
    elif metric in COUNT_METRICS:
        from matplotlib.ticker import MaxNLocator

        ax.yaxis.set_major_locator(MaxNLocator(integer=True))
        ax.set_ylim(0, max(1.0, high))
    elif high - low < 1e-3 * abs(middle):
        ax.set_ylim(middle - 0.05 * abs(middle), middle + 0.05 * abs(middle))


def _figure(png: Path, drawn, rungs, names, series, cells, breaks, scenarios, sweep: str = "") -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    columns = min(len(drawn), 2)
    rows_n = math.ceil(len(drawn) / columns)
    fig, axes = plt.subplots(rows_n, columns, figsize=(6.4 * columns, 4.4 * rows_n + 1.2), squeeze=False)
    xs = np.arange(len(rungs))
    for ax, (metric, label) in zip(axes.flat, drawn):
        for index, s in enumerate(series):
            color = _color(s, index)
            shift = (index - (len(series) - 1) / 2) * DODGE
            pos, p10, p25, p50, p75, p90 = [], [], [], [], [], []
            for x, rung in zip(xs, rungs):
                data = [v for v in (_number(r.get(metric)) for r in cells.get((s, rung), [])) if v is not None]
                if data:
                    q = np.percentile(data, (10, 25, 50, 75, 90))
                    pos.append(x)
                    for store, v in zip((p10, p25, p50, p75, p90), q):
                        store.append(v)
            if not pos:
                continue
            at = np.array(pos) + shift
            ax.plot(at, p50, "o-", color=color, lw=2, label=s)
            ax.fill_between(at, p25, p75, color=color, alpha=0.22, lw=0)
            ax.fill_between(at, p10, p90, color=color, alpha=0.09, lw=0)
            for (name, guarantee), rung in breaks.items():
                if name == s and rung is not None:
                    x = rungs.index(rung)
                    if x in pos:
                        ax.plot([x + shift], [p50[pos.index(x)]], marker="X", ms=13, color=color, mec="black",
                                mew=1.0, ls="none")
        # Every panel spans every rung, with room for the dodged series (a panel with data at one rung
        # only would otherwise shrink to it and clip its outer series).
        ax.set_xlim(xs[0] - 0.3 - len(series) * DODGE / 2, xs[-1] + 0.3 + len(series) * DODGE / 2)
        ax.set_xticks(xs, [n.replace(", ", "\n").replace(" (", "\n(") for n in names], fontsize=9)
        ax.set_xlabel("radio channel, best to worst", fontsize=10)
        ax.set_ylabel(label, fontsize=10)
        ax.grid(alpha=0.3)
        _value_axis(ax, metric)
    for ax in axes.flat[len(drawn):]:
        ax.set_visible(False)
    handles, labels = [], []  # every panel's series: a series may be drawn in some panels only
    for ax in axes.flat[:len(drawn)]:
        for handle, label in zip(*ax.get_legend_handles_labels()):
            if label not in labels:
                handles.append(handle)
                labels.append(label)
    from matplotlib.lines import Line2D

    handles.append(Line2D([], [], marker="X", ms=11, color="white", mec="black", ls="none"))
    labels.append("first rung where a guarantee breaks (see report.md)")
    fig.legend(handles, labels, fontsize=9, loc="lower center", ncol=min(len(labels), 3))
    named = f"sweep {sweep}, " if sweep else ""
    fig.suptitle(f"{named}{', '.join(scenarios)}: each method against channel quality "
                 "(line: median; bands: 25-75 % and 10-90 % over seeds)", fontsize=11)
    legend_rows = math.ceil(len(labels) / 3)
    fig.tight_layout(rect=(0, 0.04 + 0.035 * legend_rows / rows_n, 1, 0.97))
    fig.savefig(png, dpi=REPORT_DPI)
    plt.close(fig)
    return png
