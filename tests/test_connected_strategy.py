"""The ``connected`` strategy (Nestmeyer et al. 2017) on MuJoCo quadrotors: parameters, bad
input, invariants on every tick of every built-in connected scenario, outputs.

Short runs here; whole missions are in test_connected_missions.py (slow).
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from connected_helpers import run_checked
from helpers import TickLog, recorded_ticks, rrd_chunks, rrd_column, rrd_scalars, rrd_texts
from controllers.connectivity.connected_params import ConnectedParams
from controllers.connectivity.estimator import SubspaceEstimator
from controllers.connectivity.estimator_messages import MessageFedEstimator
from controllers.connectivity.roles import Role
from sim.config import ConfigError, build, to_table
from tether.runner import build_simulation, run
from sim.scenario import load

CONNECTED_SCENARIOS = ("connected-office", "connected-empty", "connected-town")


# -- parameters ------------------------------------------------------------------


def test_presets_fill_table_2_and_explicit_values_win():
    office, outdoor = (load(name).strategy.params.at_range(load(name).sensing.comm_range_m)  # R_s: the comm range
                       for name in ("connected-office", "connected-town"))
    row = lambda p: (p.sensing_range_m, p.full_weight_range_m, p.min_obstacle_clearance_m,  # noqa: E731
                     p.full_weight_obstacle_clearance_m, p.min_robot_distance_m, p.full_weight_robot_distance_m,
                     p.grid_resolution_m, p.cruise_speed_mps, p.target_radius_m, p.dwell_time_s, p.sigma)
    assert row(office) == (2.5, 1.1, 0.25, 0.6, 0.8, 1.1, 0.25, 1.0, 1.0, 3.0, 3.0)
    assert row(outdoor) == (6.0, 2.5, 0.75, 1.75, 1.0, 2.5, 0.75, 3.0, 1.8, 3.0, 3.0)
    assert (office.efficiency_error_full_mps, office.efficiency_error_zero_mps) == pytest.approx((0.1, 0.6))
    assert outdoor.efficiency_error_zero_mps == pytest.approx(1.8)  # (0.1, 0.6) v_cruise
    tuned = build(ConnectedParams, {"preset": "outdoor", "cruise_speed_mps": 2.0}, "strategy")
    assert tuned.cruise_speed_mps == 2.0 and tuned.efficiency_error_zero_mps == pytest.approx(1.2)
    assert tuned.at_range(6.0).sensing_range_m == 6.0 and tuned.sensing_range_m is None  # R_s: the scenario's
    assert tuned.virtual_mass_kg == 1.0  # one M for the connectivity and the exploration layer
    # The path planner's margins follow the link weights' obstacle clearances unless given.
    assert (tuned.path_clearance_m, tuned.path_min_clearance_m) == (1.75, 0.75)
    assert ConnectedParams(full_weight_obstacle_clearance_m=0.7).path_clearance_m == 0.7
    # A written table is complete and reads back to the same parameters.
    assert build(ConnectedParams, to_table(tuned), "strategy") == tuned


def test_tunable_fields_carry_unit_and_bounds():
    import dataclasses

    tunable = [f for f in dataclasses.fields(ConnectedParams) if f.init and f.metadata.get("tunable", True)]
    assert len(tunable) >= 15
    for f in tunable:
        assert f.metadata["min"] is not None and f.metadata["max"] is not None, f.name
        default = getattr(ConnectedParams(), f.name)
        assert f.metadata["min"] <= default <= f.metadata["max"], f.name


@pytest.mark.parametrize(
    "table, field",
    [
        ({"full_weight_obstacle_clearance_m": 0.2}, "strategy.min_obstacle_clearance_m"),  # R_o >= R'_o
        ({"path_min_clearance_m": 0.7}, "strategy.path_min_clearance_m"),  # beyond path_clearance_m (R'_o)
        ({"sigma": 0.5}, "strategy.sigma"),
        ({"efficiency_error_full_ratio": 0.7}, "strategy.efficiency_error_full_ratio"),
        ({"lambda2_source": "oracle"}, "strategy.lambda2_source"),
        ({"targets": "fixed"}, "strategy.target_lists"),
        ({"target_counts": [3, -1]}, "strategy.target_counts"),
        ({"sensing_range_m": 2.5}, "strategy.sensing_range_m"),  # no longer a key: sensing.comm_range_m
        ({"bogus": 1}, "strategy.bogus"),
    ],
)
def test_bad_parameters_name_the_field(table, field):
    with pytest.raises(ConfigError) as err:
        build(ConnectedParams, table, "strategy")
    assert err.value.field == field


def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "tether.cli", "run", *args], capture_output=True, text=True,
                          timeout=300)


@pytest.mark.parametrize(
    "overrides, expected",
    [
        (["strategy.min_robot_distance_m=2.5"], "strategy.min_robot_distance_m: R_c (2.5 m) must be smaller than R_s"),
        (["robots.0.starts.9=[8.5, 8.5, 1.0]"], "robots: the starting graph is disconnected"),
    ],
)
def test_cli_refuses_bad_connected_input(tmp_path, overrides, expected):
    out = tmp_path / "out"
    args = ["connected-office", "--out", str(out), "--duration", "1"]
    for item in overrides:
        args += ["--set", item]
    result = run_cli(*args)
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stderr, result.stderr
    assert expected in lines[0], lines[0]
    assert not out.exists()


@pytest.mark.parametrize(
    "overrides, field, expected",
    [
        (["robots.0.starts.9=[8.5, 8.5, 1.0]"], "robots", "quad9 cannot reach quad0"),
        (["robots.0.starts.1=[4.55, 0.9, 1.0]"], "robots", "start 0.40 m apart, within R_c = 0.8 m"),
        (["robots.0.starts.1=[5.25, 0.4, 1.0]", "strategy.min_obstacle_clearance_m=0.5"], "robots", "within R_o = 0.5 m"),
        (["sensing.comm_range_m=1.0"], "strategy.full_weight_range_m",
         "smaller than R_s = sensing.comm_range_m"),
        (["sensing.comm_range_m=inf"], "sensing.comm_range_m", "must be a finite number"),
        (["strategy.min_robot_distance_m=3.0"], "strategy.min_robot_distance_m", "smaller than R_s"),  # R_c >= R_s
        (["strategy.full_weight_range_m=3.0"], "strategy.full_weight_range_m", "smaller than R_s"),
        (["strategy.target_lists=[[[2.0, 5.0, 1.0]]]", 'strategy.targets="fixed"'], "strategy.target_lists.0.0",
         "inside an obstacle"),
        (["strategy.target_counts=[1, 1, 1, 1, 1, 1, 1, 1, 1, 1, 1]"], "strategy.target_counts", "lists 11 robots"),
    ],
)
def test_refused_set_ups_name_the_field(overrides, field, expected):
    with pytest.raises(ConfigError) as err:
        build_simulation(load("connected-office", overrides))
    assert err.value.field == field
    assert expected in err.value.problem, err.value.problem


def test_robot_count_from_10_to_35_starts_connected():
    for count in (10, 20, 35):
        scenario = load("connected-office", [f"robots.0.count={count}"])
        sim = build_simulation(scenario)
        assert len(sim.strategy.q) == count
        assert sim.strategy.targets_total == 25  # the paper's 5 x 3 + 5 x 2 targets
        assert sim.strategy.explorers.tolist() == list(range(10))
    # Fewer than 10 starts the paper's allocation truncated; more than the slots is refused.
    with pytest.raises(ConfigError, match="spawn_center"):
        load("connected-office", ["robots.0.count=40"])


def test_same_seed_same_targets_whatever_the_robot_count():
    targets = []
    for count in (10, 35):
        sim = build_simulation(load("connected-office", [f"robots.0.count={count}"], seed=4))
        queues = sim.strategy.queues
        targets.append(np.array([t.position for q in queues._queues for t in q]))
    np.testing.assert_array_equal(targets[0], targets[1])


# -- invariants on every tick ------------------------------------------------------


@pytest.mark.parametrize("name, duration", [("connected-office", 5.0), ("connected-empty", 3.0),
                                            ("connected-town", 3.0)])
def test_invariants_hold_on_every_tick_of_each_builtin_scenario(name, duration):
    sim, log = run_checked(load(name), duration)
    assert log.ticks == int(round(duration / sim.dt))
    stats = sim.strategy.summary()
    assert stats["prime_travelers_max"] == 1  # the start-up election produced the prime traveler
    assert stats["lambda2_min"] == pytest.approx(log.lambda2_min)
    # The quadrotors fly: the explorers moved and the bodies follow their virtual points.
    assert stats["mean_travel_m"] > 0.5
    tracking = np.linalg.norm(sim.observe().position - sim.strategy.q, axis=1)
    assert tracking.max() < 0.3


def test_estimator_mode_tracks_lambda2_and_reports_its_error():
    # Only the first second (the defaults: two tracked modes, speedup 10); whole missions are
    # compared in the README (estimator vs exact) and in the slow tests.
    sim = build_simulation(load("connected-office", ['strategy.lambda2_source="estimator"']))
    assert isinstance(sim.strategy.estimator, SubspaceEstimator)  # two modes: the Ritz estimate
    for tick in range(100):
        frame, healthy = sim.tick()
        assert healthy
        if tick == 49:
            estimates = frame.commands.decorations.robot_scalars["lambda2_estimate"]
            exact = frame.commands.scalars["lambda2"]
            assert np.abs(estimates - exact).max() < 0.05 * exact
            assert np.all(np.isfinite(frame.commands.scalars["connectivity_force_max_n"]))
    estimates = frame.commands.decorations.robot_scalars["lambda2_estimate"]
    exact = frame.commands.scalars["lambda2"]
    assert np.abs(estimates - exact).max() < 0.15 * exact
    summary = sim.strategy.summary()
    assert summary["lambda2_source"] == "estimator"
    assert 0 <= summary["lambda2_estimate_error_mean"] < 0.05
    assert "radio_lambda2_estimate_packets_sent" not in sim.bus.summary()  # ideal radio: in process


def test_estimator_over_a_real_radio_sends_its_state_on_the_bus():
    sim = build_simulation(load("connected-office", ['strategy.lambda2_source="estimator"',
                                                     'radio.preset="ieee802154"']))
    estimator = sim.strategy.estimator
    assert isinstance(estimator, MessageFedEstimator) and estimator.modes == 1
    for _ in range(30):
        frame, healthy = sim.tick()
        assert healthy, sim.divergence
    summary = sim.bus.summary()
    assert summary["radio_lambda2_estimate_packets_sent"] > 0
    assert summary["radio_lambda2_estimate_packets_delivered"] > 0
    assert summary["radio_lambda2_estimate_bytes_sent"] == 38 * summary["radio_lambda2_estimate_packets_sent"]
    # The air holds about two 38-byte 802.15.4 frames of the ten robots' a tick: the rest are superseded.
    assert summary["radio_lambda2_estimate_packets_superseded"] > 0
    assert estimator.heard_s.max() > 0.2  # the states arrived during the run, not only in the warm-up
    exact = frame.commands.scalars["lambda2"]
    assert np.abs(estimator.estimate.lambda2 - exact).max() < 0.1 * exact


def test_estimator_gains_too_fast_for_the_radio_are_refused_by_name():
    scenario = load("connected-office", ['strategy.lambda2_source="estimator"', 'radio.preset="wifi"',
                                         "strategy.estimator_message_speedup=1.0"])
    with pytest.raises(ConfigError, match="unstable") as err:
        build_simulation(scenario)
    assert err.value.field == "strategy.estimator_message_speedup"


def test_papers_raw_lambda2_gradient_keeps_the_invariants():
    sim, log = run_checked(load("connected-office", ["strategy.spectrum_smoothing=0.0"]), 3.0)
    assert sim.strategy.summary()["mean_travel_m"] > 0.5


# -- a whole (small) mission, outputs --------------------------------------------------


SMALL_MISSION = [
    "strategy.targets=\"fixed\"",
    # robot 0: two targets in its room; robot 3 one; the rest connectors.
    "strategy.target_lists=[[[5.2, 2.6, 1.5], [4.5, 3.5, 2.0]], [], [], [[6.0, 3.5, 1.2]]]",
    "strategy.dwell_time_s=0.5",
    "duration_s=40.0",
    "video.fps=10.0",
    "video.width=320",
    "video.height=240",
]


@pytest.fixture(scope="module")
def small_mission(tmp_path_factory):
    """The run's result, its folder and every tick's strategy scalars (an extra observer)."""
    out = tmp_path_factory.mktemp("mission")
    log = TickLog()
    result = run(load("connected-office", SMALL_MISSION), out, video=True, rrd=True, extra_observers=[log])
    return result, out, log


def test_small_mission_completes_and_stops_early(small_mission):
    result, out, _ = small_mission
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "completed"
    assert metrics["targets_to_visit"] == metrics["targets_visited"] == 3
    assert metrics["completion_time_s"] is not None
    assert metrics["sim_time_s"] < 40.0  # the loop stopped when the strategy finished
    assert metrics["completion_time_s"] == pytest.approx(metrics["sim_time_s"], abs=0.02)
    for key in ("completion_time_s", "targets_to_visit", "targets_visited", "lambda2_min", "lambda2_mean",
                "edges_min", "max_stretch_m", "mean_travel_m", "min_robot_distance_m", "min_obstacle_distance_m",
                "prime_travelers_max", "lambda2_estimate_error_mean", "tracking_error_mean_m", "real_time_factor"):
        assert key in metrics, key
    assert metrics["lambda2_min"] > 0 and metrics["prime_travelers_max"] == 1
    assert metrics["min_robot_distance_m"] > 0.8 and metrics["min_obstacle_distance_m"] > 0.25
    assert metrics["lambda2_estimate_error_mean"] is None  # exact mode
    assert metrics["explorers"] == 2 and metrics["connectors"] == 8
    assert metrics["tracking_error_mean_m"] < 0.05


def test_recording_logs_the_fig_14_series(small_mission):
    _, out, _ = small_mission
    chunks = rrd_chunks(out / "run.rrd")
    for entity in ("/metrics/lambda2", "/metrics/edges", "/metrics/prime_efficiency",
                   "/metrics/prime_efficiency_estimate_mean", "/metrics/prime_traveler", "/robots/role",
                   "/robots/prime_efficiency_estimate", "/robots/alignment", "/robots/gain", "/world/plans",
                   "/world/markers"):
        assert entity in chunks, (entity, sorted(chunks))
    roles = []
    for chunk in chunks["/robots/role"]:
        batch = chunk.to_record_batch()
        columns = [i for i, n in enumerate(batch.schema.names) if n.endswith("scalars")]
        if columns:  # (the static chunk holds the series names)
            roles += [row for row in batch.column(columns[0]).to_pylist() if row is not None]
    assert all(len(row) == 10 for row in roles)  # one series per robot
    robot0 = [row[0] for row in roles]
    assert Role.PRIME_TRAVELER in robot0 and Role.ANCHOR in robot0
    _, lambda2 = rrd_scalars(chunks["/metrics/lambda2"])
    assert min(lambda2) > 0


def test_video_shows_the_team(small_mission):
    import imageio.v2 as imageio

    _, out, _ = small_mission
    frames = [f for f in imageio.get_reader(out / "video.mp4")]
    metrics = json.loads((out / "metrics.json").read_text())
    # 10 fps over the run, which stopped early (6.22 s: frames at 0, 0.1, ..., 6.2 s).
    assert len(frames) == int(np.ceil(metrics["sim_time_s"] * 10 - 1e-9)) > 30
    middle = frames[len(frames) // 2].astype(float)
    assert middle.std() > 10
    # The prime traveler's marker and its planned path (the palette's vermillion) are drawn in some
    # frame's scene (left of the legend panel, whose swatch has that colour too).
    from sim.palette import PRIME_TRAVELER, rgb8

    scene_width = frames[0].shape[0]  # the office is square: the scene is as wide as the frame is tall
    red, green, blue = rgb8(PRIME_TRAVELER)
    vermillion = [(np.abs(f[:, :scene_width, 0].astype(int) - red) < 40) & (np.abs(f[:, :scene_width, 1].astype(int)
                  - green) < 40) & (f[:, :scene_width, 2] < 60) for f in frames]
    assert max(int(t.sum()) for t in vermillion) > 8


RECORDING_PERIOD_TICKS = 5  # the recorder's 0.05 s at the office's 0.01 s control period
CONTROL_PERIOD_S = 0.01


def test_recording_lambda2_and_edges_equal_every_tick_and_metrics_json(small_mission):
    _, out, log = small_mission
    metrics = json.loads((out / "metrics.json").read_text())
    n = metrics["control_ticks"]
    assert len(log.scalars) == n
    # metrics.json summarises the exact lambda2 of every tick ...
    lambda2 = log.series("lambda2")
    assert lambda2.min() == metrics["lambda2_min"]
    assert lambda2.mean() == pytest.approx(metrics["lambda2_mean"], rel=1e-12)
    # ... and the recording holds that very value at each recorded tick (every 0.05 s, and the last).
    chunks = rrd_chunks(out / "run.rrd")
    ticks, values = rrd_scalars(chunks["/metrics/lambda2"], "tick")
    assert ticks == recorded_ticks(n, RECORDING_PERIOD_TICKS)
    np.testing.assert_array_equal(values, lambda2[ticks])
    assert min(values) >= metrics["lambda2_min"] > 0
    # One edges series (the weighted graph's, W_ij > 0), the one edges_min / edges_mean summarise.
    edges = log.series("edges")
    assert edges.min() == metrics["edges_min"]
    assert edges.mean() == pytest.approx(metrics["edges_mean"], rel=1e-12)
    ticks, values = rrd_scalars(chunks["/metrics/edges"], "tick")
    assert ticks == recorded_ticks(n, RECORDING_PERIOD_TICKS)
    np.testing.assert_array_equal(values, edges[ticks])
    # Stretch, visits and prime travelers agree with their summaries.
    assert log.series("stretch_m").max() == metrics["max_stretch_m"]
    assert max(rrd_scalars(chunks["/metrics/stretch_m"], "tick")[1]) <= metrics["max_stretch_m"]
    assert rrd_scalars(chunks["/metrics/targets_visited"], "tick")[1][-1] == metrics["targets_visited"] == 3
    assert max(rrd_scalars(chunks["/metrics/prime_travelers"], "tick")[1]) == metrics["prime_travelers_max"] == 1


def test_recording_entity_tree_colours_events_and_static_data(small_mission):
    from controllers.connectivity.strategy import ROLE_COLORS
    from helpers import check_static_once_and_both_timelines, unpack_rgba
    from viz.video import link_color

    _, out, log = small_mission
    metrics = json.loads((out / "metrics.json").read_text())
    n = metrics["control_ticks"]
    expected = recorded_ticks(n, RECORDING_PERIOD_TICKS)
    chunks = rrd_chunks(out / "run.rrd")
    check_static_once_and_both_timelines(chunks, CONTROL_PERIOD_S)
    # The scene's walls: static boxes, logged once.
    world = build_simulation(load("connected-office", SMALL_MISSION)).world
    (walls,) = chunks["/world/obstacles"]
    assert walls.is_static and walls.num_rows == 1
    assert len(walls.to_record_batch().column("Boxes3D:half_sizes").to_pylist()[0]) == len(world.obstacles.centers)
    # Robots: names static, positions and role colours at every recorded tick.
    (names,) = [c for c in chunks["/world/robots"] if c.is_static]
    assert names.to_record_batch().column("Points3D:labels").to_pylist()[0] == list(world.robot_names)
    for entity, column in (("/world/robots", "Points3D:positions"), ("/world/references", "Points3D:positions"),
                           ("/world/links", "LineStrips3D:strips"), ("/world/markers", "Points3D:positions")):
        assert [t for t, _ in rrd_column(chunks[entity], column)] == expected, entity
    assert 0 < len(rrd_column(chunks["/world/plans"], "LineStrips3D:strips")) <= len(expected)
    prime_rgb = tuple(int(round(255 * c)) for c in ROLE_COLORS[Role.PRIME_TRAVELER][:3])
    prime_ticks = 0
    for tick, colors in rrd_column(chunks["/world/robots"], "Points3D:colors"):
        rgb = [unpack_rgba(c)[:3] for c in colors]
        prime = log.scalars[tick]["prime_traveler"]
        prime = int(prime) if np.isfinite(prime) else -1  # NaN: no prime traveler
        assert [i for i, c in enumerate(rgb) if c == prime_rgb] == ([prime] if prime >= 0 else []), tick
        prime_ticks += prime >= 0
    assert prime_ticks > len(expected) / 2
    # Links: one segment per communication link, coloured by weight on the palette's ramp (grey 0 ... charcoal 1).
    from sim.palette import LINK_STRONG, LINK_WEAK

    seen = set()
    for tick, strips in rrd_column(chunks["/world/links"], "LineStrips3D:strips"):
        assert len(strips) == log.links[tick], tick
    for _, colors in rrd_column(chunks["/world/links"], "LineStrips3D:colors"):
        for r, g, b, _ in map(unpack_rgba, colors):
            weight = (LINK_WEAK[0] - r / 255) / (LINK_WEAK[0] - LINK_STRONG[0])
            assert np.allclose((r, g, b), np.round(255 * link_color(weight)[:3]), atol=1), (r, g, b)
            seen.add((r, g, b))
    assert len(seen) > 5  # weights vary
    # Events: start, every election (role change to prime traveler) and visit, at its own tick; the end.
    events = rrd_texts(chunks["/events"])
    assert events[0] == (0, "run started: scenario connected-office, 10 robots")
    elections = [(t, e) for t, e in events if "becomes prime traveler" in e]
    assert len(elections) == metrics["prime_elections"] >= 2
    assert sum("visited its target" in e for _, e in events) == metrics["targets_visited"]
    for tick, text in events:
        if text.startswith("t = "):
            assert tick == round(float(text.split()[2]) / CONTROL_PERIOD_S), (tick, text)
    assert events[-2:] == [(n, f"strategy finished at t = {n * CONTROL_PERIOD_S:.2f} s"), (n, "run ended: completed")]
    assert max(t for t, _ in events) == n


def test_plots_draw_every_series_with_the_fig_14_panels(small_mission):
    import math

    from helpers import png_is_a_drawn_figure
    from viz.plots import PANELS_PER_FIGURE

    _, out, log = small_mission
    # Fig. 14 a-c, f-i as series (d: roles, g-i per robot too); every one gets a panel.
    fig_14 = {"lambda2", "edges", "stretch_m", "prime_efficiency", "prime_efficiency_estimate_mean",
              "alignment_mean", "gain_mean", "secondary_travelers", "anchors"}
    assert fig_14 <= set(log.scalars[-1])
    assert {"role", "prime_efficiency_estimate", "alignment", "gain"} <= log.robot_scalar_names
    # + tracking error, links, the communication graph's lambda2 and the radio's delivery
    # (less the foundation's link count, which the strategy's edges repeat, and series never defined)
    defined = [name for name in log.scalars[-1] if np.isfinite(log.series(name)).any()]
    panels = 4 - 1 + len(defined) + len(log.robot_scalar_names)
    pngs = sorted((out / "plots").glob("timeseries*.png"))
    assert len(pngs) == math.ceil(panels / PANELS_PER_FIGURE)
    assert all(png_is_a_drawn_figure(p) for p in pngs)


def test_tuning_updates_gains_in_place_and_restarts_for_set_up_fields():
    import dataclasses

    sim = build_simulation(load("connected-office"))
    for _ in range(5):
        sim.tick()
    strategy = sim.strategy
    params = strategy.params
    assert sim.set_strategy_params(dataclasses.replace(params, potential_gain_j=8.0, cruise_speed_mps=0.8)) == "updated"
    assert sim.strategy is strategy and strategy.params.potential_gain_j == 8.0
    assert strategy.explorer.params.cruise_speed_mps == 0.8
    sim.tick()
    assert sim.set_strategy_params(dataclasses.replace(strategy.params, grid_resolution_m=0.3)) == "restarted"
    assert sim.strategy is not strategy
    np.testing.assert_allclose(sim.strategy.q, sim.observe().position)  # virtual points restart at the bodies
