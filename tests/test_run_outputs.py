"""`tether run hover --video --rrd` end to end: files read back, determinism,
observers that do not perturb, divergence reported with readable outputs."""

import json
import subprocess
import sys

import imageio.v2 as imageio
import numpy as np
import pytest

from tether.runner import run
from sim import palette
from sim.scenario import load

from helpers import check_static_once_and_both_timelines, recorded_ticks, rrd_chunks, rrd_column, rrd_rows, write_scenario

DURATION_S = 2.0


@pytest.fixture(scope="module")
def hover_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("hover")
    result = subprocess.run(
        [sys.executable, "-m", "tether.cli", "run", "hover", "--duration", str(DURATION_S), "--out", str(out),
         "--video", "--rrd"],  # (not --quiet: that prints only the summary line, no file list)
        capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr
    return out, result.stdout


def test_metrics_json_has_the_foundation_keys(hover_run):
    out, stdout = hover_run
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("scenario", "strategy", "seed", "status", "sim_time_s", "wall_time_s", "real_time_factor",
                "n_robots", "tracking_error_mean_m", "tracking_error_max_m"):
        assert key in metrics, key
    assert metrics["status"] == "completed"
    assert metrics["n_robots"] == 8
    assert metrics["sim_time_s"] == pytest.approx(DURATION_S)
    assert 0 < metrics["tracking_error_mean_m"] < 0.05
    assert "rerun" in stdout and "run.rrd" in stdout


def test_timing_block_says_where_the_wall_time_went(hover_run):
    out, _ = hover_run
    metrics = json.loads((out / "metrics.json").read_text())
    timing = metrics["timing"]
    stages = ("physics_s", "sensing_s", "strategy_s", "lowlevel_s", "observers_s")
    assert set(timing) == {*stages, "setup_s", "closing_s", "stack_to_physics"}
    assert all(timing[key] > 0 for key in (*stages, "setup_s", "closing_s"))
    # The stages are parts of the run's wall time, and the ratio is theirs.
    assert sum(timing[key] for key in (*stages, "setup_s", "closing_s")) <= metrics["wall_time_s"]
    stack = sum(timing[key] for key in stages if key != "physics_s")
    assert timing["stack_to_physics"] == pytest.approx(stack / timing["physics_s"])


def test_strategy_figures_are_built_only_for_observers_that_read_them():
    from tether.runner import build_simulation

    simulation = build_simulation(load("hover", duration_s=1.0))
    frame, _ = simulation.tick(decorations_wanted=False)
    assert dict(frame.commands.scalars) == {}
    frame, _ = simulation.tick()
    assert "reference_speed_max_mps" in frame.commands.scalars


def test_plots_are_written_as_png(hover_run):
    out, _ = hover_run
    png = out / "plots" / "timeseries.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    image = imageio.imread(png)
    assert image.shape[0] > 200 and image.std() > 10  # a drawn figure, not a blank canvas


def test_video_frames_match_duration_and_move(hover_run):
    out, _ = hover_run
    fps = load("hover").video.fps
    reader = imageio.get_reader(out / "video.mp4")
    frames = [frame for frame in reader]
    assert len(frames) == round(DURATION_S * fps)
    first, last = frames[0].astype(float), frames[-1].astype(float)
    height, width = first.shape[:2]
    # The time, first line of the panel beside the scene (the frame's right half), changes from frame to frame.
    panel_top = (slice(0, height // 12), slice(width // 2, width))
    assert np.abs(first[panel_top] - frames[30][panel_top].astype(float)).mean() > 0.2
    assert first.mean() > 30  # not black
    assert np.abs(first - last).mean() > 0.05  # robots moved: frames differ
    assert first.shape == (540, 960, 3)  # the 16:9 default


def test_recording_has_entities_rows_and_a_blueprint(hover_run):
    out, _ = hover_run
    from rerun.chunk import RrdReader

    chunks = rrd_chunks(out / "run.rrd")
    for entity in ("/world/obstacles", "/world/robots", "/world/references", "/world/targets/true",
                   "/world/links", "/metrics/edges", "/events"):
        assert entity in chunks, entity
    expected_rows = len(recorded_ticks(round(DURATION_S / 0.01), 5))  # every 0.05 s, and the last tick
    assert rrd_rows(chunks["/world/targets/true"]) == expected_rows
    assert rrd_rows(chunks["/world/links"]) == expected_rows
    assert rrd_rows(chunks["/world/obstacles"]) == 1
    check_static_once_and_both_timelines(chunks, 0.01)
    (names,) = [c for c in chunks["/world/robots"] if c.is_static]  # labels show on every timeline
    assert names.to_record_batch().column("Points3D:labels").to_pylist()[0] == [
        *(f"quad{i}" for i in range(4)), *(f"ground{i}" for i in range(4))]
    assert RrdReader(str(out / "run.rrd")).blueprints(), "default blueprint missing"
    # Colours explained in the recording: hover's robots are coloured by kind.
    ((tick, text),) = rrd_column(chunks["/legend"], "TextDocument:text")  # logged once: it never changes
    assert tick == 0
    for colour, meaning in ((palette.KIND["quadrotor"], "quadrotor robot"), (palette.KIND["ground"], "ground robot"),
                            (palette.REFERENCE, "reference"), (palette.LINK_STRONG, "communication link"),
                            (palette.TARGET_TRUE, "target (true)")):
        line = f"**{palette.colour_name(colour)}** `{palette.hex_code(colour)}`: {meaning}"
        assert line in str(text), line
    # Each colour by a name of its own (the obstacles' blue grey was called "pale grey", as a weak link is).
    (document,) = text  # the column's one TextDocument
    names = [line.split("**")[1] for line in document.splitlines() if line.startswith("- **")]
    assert "blue grey" in names and len(set(names)) == len(names), names


def test_same_seed_same_run_and_observers_do_not_perturb(tmp_path):
    scenario = load("hover", duration_s=1.0)
    plain = run(scenario, keep_trajectory=True)
    watched = run(scenario, tmp_path, video=True, rrd=True, keep_trajectory=True)
    np.testing.assert_array_equal(plain.trajectory, watched.trajectory)
    timing = {"wall_time_s", "real_time_factor", "timing"}
    strip = lambda m: {k: v for k, v in m.items() if k not in timing}  # noqa: E731
    assert strip(plain.metrics) == strip(watched.metrics)


def test_seed_changes_target_motion(tmp_path):
    a = run(load("hover", duration_s=1.0, seed=1), keep_trajectory=True)
    b = run(load("hover", duration_s=1.0, seed=2), keep_trajectory=True)
    assert a.metrics["seed"] != b.metrics["seed"]
    from tether.runner import build_simulation

    s1, s2 = build_simulation(load("hover", seed=1)), build_simulation(load("hover", seed=2))
    assert not np.allclose(s1.targets.positions(5.0), s2.targets.positions(5.0))


UNSTABLE_SCENE = """
<mujoco model="unstable">
  <option integrator="Euler"/>
  <custom><numeric name="tether_bounds" data="0 0 0 10 10 5"/></custom>
  <worldbody>
    <geom name="floor" type="plane" size="5 5 0.05" pos="5 5 0"/>
    <body name="spring" pos="9 9 1">
      <joint name="spring" type="slide" axis="0 0 1" stiffness="1e12" springref="0.5"/>
      <geom name="bob" type="sphere" size="0.05" mass="0.001" contype="0" conaffinity="0" group="2"/>
    </body>
  </worldbody>
</mujoco>
"""


def test_diverging_run_stops_with_status_and_readable_outputs(tmp_path):
    (tmp_path / "unstable.xml").write_text(UNSTABLE_SCENE)
    path = write_scenario(tmp_path, """
        scene = "unstable.xml"
        duration_s = 2.0
        [strategy]
        kind = "waypoints"
        [[robots]]
        kind = "quadrotor"
        starts = [[2.0, 2.0, 1.0]]
    """)
    out = tmp_path / "out"
    result = subprocess.run([sys.executable, "-m", "tether.cli", "run", str(path), "--out", str(out), "--video",
                             "--rrd", "--quiet"], capture_output=True, text=True, timeout=120)
    assert result.returncode == 1
    assert "diverged" in result.stdout
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["status"] == "diverged" and "QACC" in metrics["message"]
    assert sum(1 for _ in imageio.get_reader(out / "video.mp4")) >= 1
    events = rrd_chunks(out / "run.rrd")["/events"]
    texts = [t for c in events for t in c.to_record_batch().column("TextLog:text").to_pylist()]
    assert any("diverged" in str(t) for t in texts)
