"""The faults study's report section on fixture tables (synthetic results tables written with
pyarrow, as tether sweep writes them): figures and tables written, break points, missing metrics."""

from __future__ import annotations

import json

import pyarrow as pa
import pyarrow.parquet as pq

from tether.report import write_report
from tether.study_report import first_breaks, study_cells

LADDER = [("ideal", 3.4), ("ieee802154", 0.0), ("ieee802154", 6.0), ("ieee802154", 10.0)]


def _rows(with_guarantees: bool = True, with_faults: bool = False) -> list[dict]:
    rows = []
    index = 0
    for method in ("intermittent", "connected_tracking"):
        for rung, (preset, wall) in enumerate(LADDER):
            for seed in range(3):
                row = {"trial_id": f"t{index}", "trial_index": index, "attempt": 0, "scenario": "intermittent-8",
                       "seed": seed, "duration_s": 300.0, "overrides": "[]", "status": "completed", "error": "",
                       "strategy": method, "strategy.kind": method, "radio.preset": preset,
                       "radio.wall_loss_db": wall, "e_g_mean_m": 1.0 + 0.5 * rung + 0.1 * seed,
                       # each method its own delivery: the meeting method's bursts lose more
                       "radio_delivery_ratio": 1.0 - (0.2 if method == "intermittent" else 0.1) * rung}
                if with_guarantees:
                    if method == "intermittent":
                        # The delay bound breaks from the third rung on, in one seed only.
                        row["delay_bound_held"] = not (rung >= 2 and seed == 0)
                        row["meetings_held"], row["meetings_connected"] = 10, 10
                    else:
                        row["comm_lambda2_min"] = 0.0 if rung == 3 else 0.5
                        row["prime_travelers_max"] = 1
                if with_faults:
                    row["faults"] = json.dumps([{"kind": "robot_failure", "robot": 0, "at_s": 60.0,
                                                 "happened": True, "meetings_missed": rung}])
                rows.append(row)
                index += 1
    return rows


def _write(tmp_path, rows):
    folder = tmp_path / "sweep"
    folder.mkdir()
    columns = list(dict.fromkeys(k for r in rows for k in r))  # rows of different methods: the union, as sweep writes
    pq.write_table(pa.Table.from_pylist([{k: r.get(k) for k in columns} for r in rows]), folder / "results.parquet")
    return folder


def test_break_points_are_the_first_rung_where_a_trial_broke_the_guarantee():
    rungs, series, cells, _ = study_cells(_rows())
    assert [r[1:3] for r in rungs] == [("ideal", -1.0), ("ieee802154", 0.0), ("ieee802154", 6.0), ("ieee802154", 10.0)]
    breaks = first_breaks(rungs, series, cells)
    assert breaks[("intermittent", "delay bound exceeded")][1:3] == ("ieee802154", 6.0)
    assert breaks[("intermittent", "a meeting not connected")] is None
    assert breaks[("connected_tracking", "comm graph disconnected (lambda2 = 0)")][1:3] == ("ieee802154", 10.0)
    assert breaks[("connected_tracking", "two prime travelers")] is None


def test_report_writes_the_figure_and_tables_with_n_and_delivery(tmp_path):
    folder = _write(tmp_path, _rows(with_faults=True))
    files = write_report(folder)
    assert folder / "study.png" in files and (folder / "study.png").stat().st_size > 10_000
    text = (folder / "report.md").read_text()
    assert "## The faults study" in text
    # The delivery ratio is each method's at each rung, never one figure per rung pooled over the methods.
    assert "(delivery" not in text and "| series | ideal | ieee802154, 0 dB/wall | ieee802154, 6 dB/wall |" in text
    delivery = text.index("**measured delivery ratio** (`radio_delivery_ratio`)")
    assert delivery < text.index("**e_g, time average (m)**")  # tabled first: what each rung meant per method
    assert "| intermittent | 1 [1, 1] (n=3/3) | 0.8 [0.8, 0.8] (n=3/3) | 0.6 [0.6, 0.6] (n=3/3) |" in text
    assert "| connected_tracking | 1 [1, 1] (n=3/3) | 0.9 [0.9, 0.9] (n=3/3) | 0.8 [0.8, 0.8] (n=3/3) |" in text
    assert "| intermittent | delay bound exceeded | ieee802154, 6 dB/wall (1/3) |" in text
    assert "| connected_tracking | two prime travelers | held at every rung |" in text
    # e_g at the ideal rung, intermittent: seeds 1.0, 1.1, 1.2 -> median 1.1, n 3 of 3.
    assert "| intermittent | 1.1 [1.05, 1.15] (n=3/3) |" in text
    assert "`fault_meetings_missed`" in text  # a failure entry's reaction figures, when present


def test_report_without_guarantee_or_fault_metrics_still_writes(tmp_path):
    folder = _write(tmp_path, _rows(with_guarantees=False))
    write_report(folder)
    text = (folder / "report.md").read_text()
    assert "No guarantee metric" in text and "fault_" not in text
    assert (folder / "study.png").is_file()


def test_rungs_order_by_wall_loss_then_falling_power():
    rows = [r | {"radio.tx_power_dbm": power} for r in _rows() if r["radio.preset"] != "ideal"
            for power in (0.0, -45.0) if r["radio.wall_loss_db"] == 10.0]
    rungs, _, _, _ = study_cells(rows)
    from tether.study_report import _rung_name
    assert [_rung_name(r) for r in rungs] == ["ieee802154, 10 dB/wall, 0 dBm", "ieee802154, 10 dB/wall, -45 dBm"]


def test_tables_without_radio_or_faults_get_no_study_section(tmp_path):
    rows = [{k: v for k, v in r.items() if k not in ("radio.preset", "radio.wall_loss_db")} for r in _rows()]
    folder = _write(tmp_path, rows)
    write_report(folder)
    assert "faults study" not in (folder / "report.md").read_text()
    assert not (folder / "study.png").exists()


def test_reaction_metrics_of_a_failure_are_tabled_when_present(tmp_path):
    rows = _rows(with_faults=True)
    for r in rows:
        r["faults"] = json.dumps([{"kind": "robot_failure", "robot": 0, "at_s": 60.0, "dropped_after_s": 1.5}])
        r["dropped_robots"] = json.dumps([0])  # the ids, as a list: the report counts them
        r["meetings_missed"] = 2
    folder = _write(tmp_path, rows)
    write_report(folder)
    text = (folder / "report.md").read_text()
    assert "`fault_dropped_after_s`" in text and "| intermittent | 1.5 [1.5, 1.5] (n=3/3) |" in text
    assert "`dropped_robots`" in text and "| intermittent | 1 [1, 1] (n=3/3) |" in text
    assert "`meetings_missed`" in text and "| intermittent | 2 [2, 2] (n=3/3) |" in text


def test_a_diverged_trial_is_a_guarantee_broken_not_a_trial_left_out():
    rows = _rows()
    rung = max(study_cells(rows)[0])
    for r in rows:
        if r["strategy"] == "connected_tracking" and study_cells([r])[0] == [rung]:
            r["status"] = "diverged"
    rungs, series, cells, _ = study_cells(rows)
    breaks = first_breaks(rungs, series, cells)
    assert breaks[("connected_tracking", "run diverged (an invariant broke)")] == rung
    assert all(b is None for (s, g), b in breaks.items() if g.startswith("run diverged") and s != "connected_tracking")


def test_a_count_panel_has_integer_ticks_from_zero():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tether.study_report import _value_axis

    fig, ax = plt.subplots()
    ax.plot([0, 1, 2], [0.0, 0.0, 0.0])  # no robot dropped anywhere: matplotlib alone would span -0.055..0.055
    _value_axis(ax, "dropped_robots")
    fig.canvas.draw()
    assert ax.get_ylim() == (0.0, 1.0)
    ticks = [t for t in ax.get_yticks() if 0.0 <= t <= 1.0]
    assert ticks and all(float(t).is_integer() for t in ticks)
    ax.clear()
    ax.plot([0, 1], [3.0, 7.0])
    _value_axis(ax, "targets_visited")
    fig.canvas.draw()
    assert ax.get_ylim()[0] == 0.0 and all(float(t).is_integer() for t in ax.get_yticks())
    plt.close(fig)


def test_a_count_that_is_zero_everywhere_is_tabled_not_drawn(tmp_path):
    from tether.study_report import TASK_METRICS, figure_panels

    rows = _rows()
    for row in rows:
        row["dropped_robots"] = 0
        row["meetings_missed"] = row["seed"]
    _rungs, _series, cells, _keys = study_cells(rows, None)
    present = [(m, label) for m, label in TASK_METRICS if any(m in r for rs in cells.values() for r in rs)]
    drawn = [m for m, _ in figure_panels(present, cells)]
    assert "meetings_missed" in drawn and "dropped_robots" not in drawn
    assert drawn[0] == "radio_delivery_ratio"  # each method's delivery, its own first panel
    folder = _write(tmp_path, rows)
    write_report(folder)
    assert "**robots dropped from the team**" in (folder / "report.md").read_text()  # still tabled
