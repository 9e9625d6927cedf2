"""What a intermittent-task run writes, read back: the recording's series equal the
strategy's per-tick values and the figures in metrics.json, its entity tree
(targets true and estimated with covariance ellipsoids, team colours, plans,
meeting points, meetings as events), and the plots."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from helpers import (
    TickLog,
    check_static_once_and_both_timelines,
    png_is_a_drawn_figure,
    rrd_chunks,
    rrd_column,
    rrd_scalars,
    rrd_texts,
    unpack_rgba,
)
from intermittent_helpers import room_scenario
from tether.runner import run
from sim.scenario import load

DURATION_S = 10.0
CONTROL_PERIOD_S = 0.02  # the test room's
READING_TICKS = 50  # a range reading (one target step) every 1 s


@pytest.fixture(scope="module")
def room_recording(tmp_path_factory):
    folder = tmp_path_factory.mktemp("room_rrd")
    scenario = load(str(room_scenario(folder, duration=DURATION_S, n_sample=40)))
    log = TickLog()
    result = run(scenario, folder / "out", rrd=True, extra_observers=[log])
    assert result.status == "completed"
    metrics = json.loads((folder / "out" / "metrics.json").read_text())
    return metrics, rrd_chunks(folder / "out" / "run.rrd"), log, folder / "out"


def reading_ticks(metrics) -> list[int]:
    return list(range(0, metrics["control_ticks"], READING_TICKS))


def test_recorded_series_equal_the_strategy_per_tick_and_metrics_json(room_recording):
    metrics, chunks, log, _ = room_recording
    readings = reading_ticks(metrics)
    assert len(readings) == int(DURATION_S)
    for name in ("lambda_max_m2", "e_g_m", "t_star_s", "t_star_lag_s", "meetings_held"):
        ticks, values = rrd_scalars(chunks[f"/metrics/{name}"], "tick")
        assert set(readings) <= set(ticks), name  # every reading tick is recorded
        np.testing.assert_array_equal(values, log.series(name)[ticks], err_msg=name)
    # lambda-bar and e_g of eq. (13): mean and std over the reading steps t = 1 .. t_end.
    for name, mean, std in (("lambda_max_m2", "lambda_bar_mean_m2", "lambda_bar_std_m2"),
                            ("e_g_m", "e_g_mean_m", "e_g_std_m")):
        ticks, values = rrd_scalars(chunks[f"/metrics/{name}"], "tick")
        at_readings = np.array([v for t, v in zip(ticks, values) if t in readings[1:]])
        assert len(at_readings) == len(readings) - 1
        assert at_readings.mean() == pytest.approx(metrics[mean], rel=1e-12), name
        assert at_readings.std() == pytest.approx(metrics[std], rel=1e-9), name
    # t*(t) + (t - t*(t)) = t at every reading (eq. 14).
    _, t_star = rrd_scalars(chunks["/metrics/t_star_s"], "tick")
    ticks, lag = rrd_scalars(chunks["/metrics/t_star_lag_s"], "tick")
    for tick, a, b in zip(ticks, t_star, lag):
        if tick in readings and not np.isnan(a):  # NaN: no agreement yet, t*(t) undefined (not -1)
            assert a + b == pytest.approx(tick * CONTROL_PERIOD_S)
    assert not np.any(np.asarray(t_star) < 0.0)  # never a made-up -1 step
    # The last recorded row is the run's last tick: the meeting count is the final one.
    ticks, held = rrd_scalars(chunks["/metrics/meetings_held"], "tick")
    assert ticks[-1] == metrics["control_ticks"] - 1
    assert held[-1] == metrics["meetings_held"] >= 1


def test_recording_entity_tree_targets_teams_plans_and_meetings(room_recording):
    metrics, chunks, log, _ = room_recording
    check_static_once_and_both_timelines(chunks, CONTROL_PERIOD_S)
    readings = reading_ticks(metrics)
    (walls,) = chunks["/world/obstacles"]
    assert walls.is_static and len(walls.to_record_batch().column("Boxes3D:centers").to_pylist()[0]) == 6
    (names,) = [c for c in chunks["/world/robots"] if c.is_static]
    assert names.to_record_batch().column("Points3D:labels").to_pylist()[0] == [f"ground{i}" for i in range(4)]
    # Robots coloured by the team they head to: more than one colour, none the plain ground colour.
    colours = {unpack_rgba(c)[:3] for _, row in rrd_column(chunks["/world/robots"], "Points3D:colors") for c in row}
    from viz.recording import KIND_COLORS

    assert len(colours) >= 2 and KIND_COLORS["ground"] not in colours
    # True targets at every recorded tick; estimates and 2-sigma ellipsoids at each reading (when they change).
    true_ticks = [t for t, _ in rrd_column(chunks["/world/targets/true"], "Points3D:positions")]
    assert set(readings) <= set(true_ticks)
    estimates = rrd_column(chunks["/world/targets/estimate"], "Points3D:positions")
    assert [t for t, _ in estimates] == readings and all(len(p) == 2 for _, p in estimates)
    ellipsoids = rrd_column(chunks["/world/targets/covariance"], "Ellipsoids3D:half_sizes")
    assert [t for t, _ in ellipsoids] == readings
    assert all(len(h) == 2 and np.all(np.array(h) > 0) for _, h in ellipsoids)
    # lambda_max of the recorded covariance shrinks as readings come in: the ellipsoids shrink.
    largest = [max(max(h) for h in row) for _, row in ellipsoids]
    assert largest[-1] < largest[0]
    # Links: one segment per communication link at every recorded tick.
    for tick, strips in rrd_column(chunks["/world/links"], "LineStrips3D:strips"):
        assert len(strips) == log.links[tick], tick
    # Events: every plan and every meeting held, at its tick.
    events = rrd_texts(chunks["/events"])
    assert events[0] == (0, "run started: scenario room_intermittent_0, 4 robots")
    assert sum("planned epoch" in e for _, e in events) == metrics["plans"]
    held = [(t, e) for t, e in events if e.startswith("meeting held")]
    assert len(held) == metrics["meetings_held"]
    for tick, text in held:
        assert f"at t = {tick * CONTROL_PERIOD_S:.1f} s" in text
    assert events[-1] == (metrics["control_ticks"] - 1, "run ended: completed")
    # Plans and meeting points, logged when they change: the a-priori plans, then a new plan at each
    # meeting (held on a recorded tick here).
    plans = rrd_column(chunks["/world/plans"], "LineStrips3D:strips")
    meetings = rrd_column(chunks["/world/meetings"], "Points3D:positions")
    assert [t for t, _ in plans] == [t for t, _ in meetings] == [0] + [t for t, _ in held]
    assert all(len(points) >= 2 for _, points in meetings)
    assert all(len(strips) >= 4 for _, strips in plans)  # at least one path per robot
    # The legend says what the colours mean: teams, the plain colours, the true targets and estimates.
    legend = rrd_column(chunks["/legend"], "TextDocument:text")
    assert legend and legend[0][0] == 0
    text = str(legend[0][1])
    for words in ("team 0", "team 1", "no meeting planned", "target (true)", "target estimate", "reference",
                  "communication link", "**yellow**"):
        assert words in text, words


def test_plots_draw_the_figs_5_to_7_series(room_recording):
    from viz.plots import PANELS_PER_FIGURE

    metrics, _, log, out = room_recording
    # Fig. 5: e_g and lambda_max; Fig. 7: t*(t) and the local error; each in a panel.
    assert {"e_g_m", "lambda_max_m2", "t_star_s", "t_star_lag_s", "local_error_m"} <= set(log.scalars[-1])
    # (a series never defined, all NaN, gets no panel: t*(t) before any agreement)
    defined = [name for name in log.scalars[-1] if np.isfinite(log.series(name)).any()]
    panels = 2 + len(defined) + len(log.robot_scalar_names)
    pngs = sorted(out.glob("plots/timeseries*.png"))
    assert len(pngs) == math.ceil(panels / PANELS_PER_FIGURE) >= 2
    assert all(png_is_a_drawn_figure(p) for p in pngs)
