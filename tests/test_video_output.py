"""The video: a link appearing changes the frame where it is drawn and the
overlay's link count; frames == duration x fps at any fps, without changing
the trajectory; frames stream to the encoder, so memory stays flat."""

from __future__ import annotations

import dataclasses
import math

import imageio.v2 as imageio
import numpy as np
import pytest

from helpers import write_scenario, write_scene
from tether.runner import build_simulation, run
from sim.scenario import load
from viz.video import HELPERS_AFTER_FRAMES, FrameRenderer, VideoRecorder

OPEN_FLOOR = """
<mujoco model="open_floor">
  <custom><numeric name="tether_bounds" data="0 0 0 10 10 5"/></custom>
  <worldbody>
    <light pos="5 5 8" dir="0 0 -1" directional="true"/>
    <geom name="floor" type="plane" size="5 5 0.05" pos="5 5 0" rgba="0.8 0.8 0.8 1" group="0"/>
    <camera name="top" pos="5 5 8" xyaxes="1 0 0 0 1 0" projection="orthographic" fovy="4"/>
  </worldbody>
</mujoco>
"""
# Two quadrotors 2 m apart, centred under an orthographic top camera 4 m tall: 60 px per metre in
# the 240 x 240 scene of a 400 x 240 frame (the legend panel to its right), the robots at columns 60
# and 180 of row 120.
TWO_QUADS = """
scene = "scene.xml"
duration_s = 1.0
[video]
width = 400
height = 240
camera = "top"
[strategy]
kind = "waypoints"
[[robots]]
kind = "quadrotor"
starts = [[4.0, 5.0, 1.0], [6.0, 5.0, 1.0]]
"""
SCENE_COLUMNS = 240  # the scene's width in the frame; the panel starts here


def first_frame(path, comm_range_m: float):
    sim = build_simulation(load(str(path), [f"sensing.comm_range_m={comm_range_m}"]))
    frame, healthy = sim.tick()
    assert healthy
    view = FrameRenderer(sim.world, sim.scenario.video)
    try:
        return frame, view.render(frame).astype(int)
    finally:
        view.close()


def test_a_link_appearing_changes_its_pixels_and_the_overlay_count(tmp_path):
    write_scene(tmp_path, OPEN_FLOOR)
    path = write_scenario(tmp_path, TWO_QUADS)
    # The same bodies in the same place; only the communication range differs: 1.5 m (no link) or 2.5 m.
    apart, without = first_frame(path, 1.5)
    linked, with_link = first_frame(path, 2.5)
    np.testing.assert_array_equal(apart.observation.position, linked.observation.position)
    assert len(apart.observation.links.edges) == 0 and len(linked.observation.links.edges) == 1
    changed = np.abs(with_link - without).sum(axis=2) > 0
    # Between the robots (clear of their bodies), every column shows the line, darker than the floor
    # (the palette's link ramp at full value is charcoal).
    between = with_link[114:127, 75:166].sum(axis=2)
    before = without[114:127, 75:166].sum(axis=2)
    assert np.all(before.min(axis=0) - between.min(axis=0) > 150)
    assert np.ptp(before, axis=0).max() < 60  # bare floor before
    # The panel's "links 0" became "links 1".
    assert changed[:, SCENE_COLUMNS:].sum() > 5
    # Nothing else changed: in the scene, only pixels on the segment between the two robots.
    rows, cols = np.nonzero(changed[:, :SCENE_COLUMNS])
    assert rows.min() >= 116 and rows.max() <= 124
    assert cols.min() >= 55 and cols.max() <= 185


def count_frames(path) -> int:
    return sum(1 for _ in imageio.get_reader(path))


def without_timing(metrics: dict) -> dict:
    return {k: v for k, v in metrics.items() if k not in ("wall_time_s", "real_time_factor", "timing")}


@pytest.fixture(scope="module")
def hover_plain():
    scenario = load("hover", ["video.width=64", "video.height=48"], duration_s=1.0)
    return scenario, run(scenario, keep_trajectory=True)


@pytest.mark.parametrize("fps", [100.0, 250.0, 7.0])  # the control rate, above it, and not a divisor of it
def test_frames_equal_duration_times_fps_and_video_leaves_the_trajectory_alone(tmp_path, hover_plain, fps):
    scenario, plain = hover_plain
    scenario = dataclasses.replace(scenario, video=dataclasses.replace(scenario.video, fps=fps))
    watched = run(scenario, tmp_path, video=True, rrd=True, keep_trajectory=True)
    np.testing.assert_array_equal(plain.trajectory, watched.trajectory)
    assert without_timing(plain.metrics) == without_timing(watched.metrics)
    video = tmp_path / "video.mp4"
    assert count_frames(video) == math.ceil(scenario.duration_s * fps)
    assert imageio.get_reader(video).get_meta_data()["fps"] == pytest.approx(fps)


def test_connected_run_rendered_at_the_control_rate_follows_the_same_trajectory(tmp_path):
    scenario = load("connected-office", ["video.width=64", "video.height=48", "video.fps=100"], duration_s=0.5)
    plain = run(scenario, keep_trajectory=True)
    watched = run(scenario, tmp_path, video=True, rrd=True, keep_trajectory=True)
    np.testing.assert_array_equal(plain.trajectory, watched.trajectory)
    assert without_timing(plain.metrics) == without_timing(watched.metrics)
    assert count_frames(tmp_path / "video.mp4") == 50  # one per control tick


def vm_rss_bytes() -> int:
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
    raise AssertionError("no VmRSS in /proc/self/status")


def test_frames_stream_to_the_encoder_so_memory_stays_flat(tmp_path):
    frames, width, height = 600, 320, 240
    sim = build_simulation(load("hover", [f"video.width={width}", f"video.height={height}", "video.fps=100"]))
    recorder = VideoRecorder(sim.world, sim.scenario.video, str(tmp_path / "video.mp4"), sim.dt)
    warm_up = 60  # GL buffers, the encoder's pipe and first allocations
    rss = []
    for _ in range(frames):
        frame, healthy = sim.tick()
        assert healthy
        recorder.on_tick(frame)
        rss.append(vm_rss_bytes())
    recorder.close("completed")
    assert recorder.frames_written == frames
    growth = max(rss[warm_up:]) - rss[warm_up - 1]
    kept_frames = (frames - warm_up) * width * height * 3  # what a list of the frames would hold
    assert growth < 0.1 * kept_frames, (growth, kept_frames)
    assert count_frames(tmp_path / "video.mp4") == frames


def test_helper_renderers_draw_the_frames_a_lone_renderer_draws(tmp_path):
    """Past HELPERS_AFTER_FRAMES frames the renderer hands every third frame to each of two helper
    processes: the frames in the file, in order, are those one renderer alone writes."""
    scenario = load("hover", ["video.width=320", "video.height=180"], duration_s=2.5)
    frames = {}
    for renderers in (1, 3):
        sim = build_simulation(scenario)
        path = tmp_path / f"{renderers}.mp4"
        recorder = VideoRecorder(sim.world, sim.scenario.video, str(path), sim.dt, renderers=renderers)
        for _ in range(round(scenario.duration_s / sim.dt)):
            frame, healthy = sim.tick()
            assert healthy
            recorder.on_tick(frame)
        recorder.close("completed")
        frames[renderers] = np.array([image for image in imageio.get_reader(path)])
    assert len(frames[1]) == math.ceil(2.5 * scenario.video.fps) > HELPERS_AFTER_FRAMES + 3
    assert frames[1].std() > 10  # not blank
    np.testing.assert_array_equal(frames[1], frames[3])


def test_a_run_stopped_while_its_renderer_starts_leaves_no_child_and_no_traceback(tmp_path, monkeypatch, capfd):
    """An interrupt in the set-up after the renderer and painters were spawned: they are killed at once,
    before this process drops the queue whose semaphores they open by name as they start (else each
    prints its bootstrap's FileNotFoundError after the run reported its interrupt)."""
    import gc
    import multiprocessing
    import time

    import viz.recording

    def interrupted(*_args, **_kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(viz.recording.RerunRecorder, "__init__", interrupted)
    scenario = load("hover", ["video.width=64", "video.height=48"], duration_s=1.0)
    with pytest.raises(KeyboardInterrupt):
        run(scenario, tmp_path / "out", video=True, rrd=True)
    assert [child.name for child in multiprocessing.active_children()] == []
    gc.collect()
    time.sleep(1.0)
    assert "Traceback" not in capfd.readouterr().err
    assert not (tmp_path / "out").exists()
