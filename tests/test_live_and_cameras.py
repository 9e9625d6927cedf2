"""`tether run --rerun-live` (gRPC + web viewer while the file is still
written) and the video options: camera presets, --video-fps, --video-size."""

import dataclasses
import os
import queue
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request

import imageio.v2 as imageio
import numpy as np
import pytest
from rerun.chunk import RrdReader

from tether.cli import main
from tether.runner import build_simulation
from sim.scenario import load
from viz.video import FrameRenderer

from helpers import recorded_ticks, rrd_chunks, rrd_rows, write_scenario, write_scene

ENV = {**os.environ, "OPENBLAS_NUM_THREADS": "1"}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def read_lines_until(proc: subprocess.Popen, marker: str, timeout_s: float = 120) -> list[str]:
    """stdout lines up to the one containing ``marker`` (read in a thread, so a
    silent process cannot hang the test)."""
    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: [lines.put(line) for line in proc.stdout], daemon=True).start()
    seen, deadline = [], time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            line = lines.get(timeout=max(0.01, deadline - time.monotonic()))
        except queue.Empty:
            break
        seen.append(line.rstrip("\n"))
        if marker in line:
            return seen
    proc.kill()
    raise AssertionError(f"no {marker!r} in output: {seen}")


def is_http2_server(port: int) -> bool:
    """gRPC runs over HTTP/2: answer the client preface with a SETTINGS frame."""
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(b"PRI * HTTP/2.0\r\n\r\nSM\r\n\r\n" + bytes([0, 0, 0, 4, 0, 0, 0, 0, 0]))
        header = s.recv(9)
    return len(header) == 9 and header[3] == 4


def test_rerun_live_serves_grpc_and_web_viewer_and_still_writes_the_file(tmp_path):
    grpc_port, web_port = free_port(), free_port()
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "tether.cli", "run", "hover", "--duration", "0.5", "--out", str(out), "--quiet",
         "--rerun-live", "--rerun-port", str(grpc_port), "--rerun-web-port", str(web_port)],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True, env=ENV,
    )
    try:
        lines = read_lines_until(proc, "still serving")
        text = "\n".join(lines)
        assert f"rerun+http://127.0.0.1:{grpc_port}/proxy" in text
        assert f"http://127.0.0.1:{web_port}/?url=" in text
        assert "completed" in text
        # The gRPC server answers (and keeps answering after the run), on loopback.
        assert is_http2_server(grpc_port)
        with urllib.request.urlopen(f"http://127.0.0.1:{web_port}/", timeout=10) as page:
            assert page.status == 200 and b"<html" in page.read(2000).lower()
        # The file is complete (footer written) while the live stream is still served.
        chunks = rrd_chunks(out / "run.rrd")
        assert rrd_rows(chunks["/world/robots"]) >= round(0.5 / 0.05)
        assert rrd_rows(chunks["/metrics/edges"]) == len(recorded_ticks(50, 5))  # 0.05 s apart, and the last tick
        assert RrdReader(str(out / "run.rrd")).blueprints()
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            code = proc.wait(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise
    assert code == 0


def test_rerun_live_refuses_a_port_in_use(tmp_path, capsys):
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        code = main(["run", "hover", "--duration", "0.1", "--out", str(tmp_path / "o"), "--rerun-live",
                     "--rerun-port", str(port)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and err[0].startswith("tether: error: --rerun-port: cannot listen")
    assert not (tmp_path / "o").exists()


def test_video_flags_follow_camera_size_and_fps(tmp_path):
    out = tmp_path / "out"
    result = subprocess.run(
        [sys.executable, "-m", "tether.cli", "run", "hover", "--duration", "1.0", "--out", str(out), "--quiet",
         "--video-fps", "12", "--video-size", "320x240", "--video-camera", "follow:quad0"],
        capture_output=True, text=True, timeout=300, env=ENV,
    )
    assert result.returncode == 0, result.stderr
    frames = [frame for frame in imageio.get_reader(out / "video.mp4")]  # the flags imply --video
    assert len(frames) == round(1.0 * 12)
    assert frames[0].shape == (240, 320, 3)
    assert frames[0].mean() > 30
    assert np.abs(frames[0].astype(float) - frames[-1].astype(float)).mean() > 0.1  # the view moves with quad0


BAD_VIDEO_FLAGS = {
    "size without x": (["--video-size", "640"], "--video-size: expected WIDTHxHEIGHT"),
    "odd size": (["--video-size", "321x240"], "video.width: must be even"),
    "tiny size": (["--video-size", "8x8"], "video.width: must be in [16, 4096] px"),
    "negative fps": (["--video-fps", "-2"], "video.fps: must be positive"),
    "fps not a number": (["--video-fps", "fast"], "video.fps: must be a number"),
    "unknown robot": (["--video-camera", "follow:quad9"], "video.camera: no robot 'quad9' to follow"),
    "unknown camera": (["--video-camera", "side"], "video.camera: no camera 'side'"),
}


@pytest.mark.parametrize("case", sorted(BAD_VIDEO_FLAGS))
def test_bad_video_flags_exit_2_with_one_line(tmp_path, capsys, case):
    flags, expected = BAD_VIDEO_FLAGS[case]
    out = tmp_path / "o"
    code = main(["run", "hover", "--duration", "0.1", "--out", str(out), *flags])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and expected in err[0], err
    assert not out.exists() or not (out / "video.mp4").exists()


@pytest.fixture(scope="module")
def hover_sim():
    sim = build_simulation(load("hover"))
    for _ in range(100):
        frame, healthy = sim.tick()
        assert healthy
    return sim, frame


def render(sim, frame, camera, size=(160, 120)):
    config = dataclasses.replace(sim.scenario.video, camera=camera, width=size[0], height=size[1])
    view = FrameRenderer(sim.world, config)
    try:
        return view.render(frame).astype(float)
    finally:
        view.close()


def test_camera_presets_give_distinct_non_black_views(hover_sim):
    sim, frame = hover_sim
    views = {name: render(sim, frame, name) for name in ("top", "overview", "follow:quad0", "follow:ground1")}
    for name, image in views.items():
        assert image.mean() > 20 and image.std() > 5, name
    names = list(views)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            assert np.abs(views[a] - views[b]).mean() > 5, (a, b)


NO_CAMERA_SCENE = """
<mujoco model="bare">
  <custom><numeric name="tether_bounds" data="0 0 0 10 10 5"/></custom>
  <worldbody>
    <light pos="5 5 8" dir="0 0 -1" directional="true"/>
    <geom name="floor" type="plane" size="5 5 0.05" pos="5 5 0" rgba="0.7 0.7 0.7 1" group="0"/>
    <geom name="block" type="box" size="0.5 0.5 1" pos="7 7 1" rgba="0.3 0.4 0.8 1" group="0"/>
  </worldbody>
</mujoco>
"""


def test_presets_work_in_a_scene_without_cameras(tmp_path):
    write_scene(tmp_path, NO_CAMERA_SCENE)
    path = write_scenario(tmp_path, """
        scene = "scene.xml"
        duration_s = 1.0
        [strategy]
        kind = "waypoints"
        [[robots]]
        kind = "quadrotor"
        starts = [[2.0, 2.0, 1.0], [3.0, 2.0, 1.0]]
    """)
    sim = build_simulation(load(str(path)))
    frame, _ = sim.tick()
    top, overview, follow = (render(sim, frame, c) for c in ("top", "overview", "follow:quad1"))
    for image in (top, overview, follow):
        assert image.mean() > 20 and image.std() > 5
    assert np.abs(top - overview).mean() > 5 and np.abs(top - follow).mean() > 5
