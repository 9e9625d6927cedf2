"""Observers get immutable frames: the video draws the state of the tick it is
handed (the recording's positions at that tick), no observer changes what
another one reads whatever their order, and writing to a frame's arrays
raises."""

from __future__ import annotations

import dataclasses
import pickle

import mujoco
import numpy as np
import pytest

from helpers import rrd_chunks, rrd_column
from intermittent_helpers import room_scenario
from sim.estimation_observer import EstimationMetrics
from sim.loop import run_ticks
from sim.observers import Observer
from sim.scenario import load
from tether.runner import _observers, build_simulation, run


def test_video_frames_show_the_bodies_where_the_recording_has_them_at_that_tick(tmp_path, monkeypatch):
    from viz.video import VideoRecorder

    sent = []
    put = VideoRecorder._put

    def keep(self, item):
        sent.append(item)
        put(self, item)

    monkeypatch.setattr(VideoRecorder, "_put", keep)
    scenario = load("hover", ["video.width=160", "video.height=120", "video.fps=20"], duration_s=1.0)
    result = run(scenario, tmp_path / "out", video=True, rrd=True)
    assert result.status == "completed"
    recorded = {tick: np.array(points, dtype=float) for tick, points in
                rrd_column(rrd_chunks(tmp_path / "out" / "run.rrd")["/world/robots"], "Points3D:positions")}
    # The renderer process's own world: the frame's state loaded and the kinematics recomputed.
    world = build_simulation(scenario).world
    dt = scenario.physics.control_period_s
    compared = 0
    for item in sent:
        if item is None:
            continue
        frame, _ = pickle.loads(item)
        frame.state.load_into(world.data)
        mujoco.mj_forward(world.model, world.data)
        bodies = world.data.xpos[world.body_ids]
        tick = int(round(frame.observation.time_s / dt))
        later = [t for t in recorded if t > tick]
        if tick not in recorded or not later:
            continue
        np.testing.assert_allclose(bodies, frame.observation.position, atol=1e-12)
        np.testing.assert_allclose(bodies, recorded[tick], atol=1e-5)  # the recording stores float32
        # Where a robot moves more than that tolerance per tick, a state one tick ahead fails above.
        compared += np.abs(recorded[min(later)] - recorded[tick]).max() > 2e-5 * (min(later) - tick)
    assert compared >= 10, (compared, sorted(recorded))


def _canonical(value) -> str:
    """A value as text that equal values share (NaN included, no pickle memo)."""
    if isinstance(value, np.ndarray):
        return f"{value.dtype}{value.shape}{value.tobytes().hex()}"
    if isinstance(value, (tuple, list)):
        return "(" + ",".join(_canonical(v) for v in value) + ")"
    if isinstance(value, dict) or hasattr(value, "keys"):
        return "{" + ",".join(f"{k!r}:{_canonical(v)}" for k, v in value.items()) + "}"
    if dataclasses.is_dataclass(value):
        return type(value).__name__ + _canonical({f.name: getattr(value, f.name) for f in dataclasses.fields(value)})
    return repr(value)


def _physical(frame) -> str:
    """What the tick's frame says of the world (no wall-clock figures: plan times, their events)."""
    cmd = frame.commands
    return _canonical([frame.observation.position, frame.observation.target_ranges, cmd.position, cmd.velocity,
                       cmd.estimate, frame.target_positions, frame.state, frame.estimation])


def _digest(frame) -> str:
    """Everything an observer can read of ``frame``, as text."""
    obs = frame.observation
    links = obs.links
    return _canonical([dataclasses.replace(obs, links=None), links.distance, links.line_of_sight,
                       links.adjacency, links.edges, frame.commands, frame.target_positions, frame.state,
                       frame.estimation, dict(frame.scalars)])


class _Digests(Observer):
    """Between every two observers: the frame's digest, per tick."""

    def __init__(self, log: list):
        self.log = log

    def reads_decorations(self, time_s: float) -> bool:
        return False

    def on_tick(self, frame) -> None:
        self.log.append((frame.observation.tick, _digest(frame), _physical(frame)))


def _run_in_order(folder, reverse: bool):
    sim = build_simulation(load(str(room_scenario(folder, duration=3.0, n_sample=40))))
    observers, named, _ = _observers(sim, folder / "staged", video=False, rrd=True, live=None, final=str)
    if reverse:
        observers.reverse()
    log: list = []
    interleaved = [_Digests(log)]
    for observer in observers:
        interleaved += [observer, _Digests(log)]
    outcome = run_ticks(sim, interleaved, 3.0)
    return outcome, log, named


def test_no_observer_changes_what_another_reads_in_either_order(tmp_path):
    (tmp_path / "a" / "staged").mkdir(parents=True)
    (tmp_path / "b" / "staged").mkdir(parents=True)
    forward, forward_log, forward_named = _run_in_order(tmp_path / "a", reverse=False)
    backward, backward_log, backward_named = _run_in_order(tmp_path / "b", reverse=True)
    assert forward.status == backward.status == "completed"
    for log in (forward_log, backward_log):
        by_tick: dict[int, set] = {}
        for tick, digest, _ in log:
            by_tick.setdefault(tick, set()).add(digest)
        assert len(by_tick) == 150
        assert all(len(digests) == 1 for digests in by_tick.values())  # unchanged by every observer
    assert [d for *_, d in forward_log[::8]] == [d for *_, d in backward_log[::8]]  # the same run
    estimation = forward_named["estimation"].summary()
    assert estimation and estimation == backward_named["estimation"].summary()
    assert forward_named["tracking"].summary() == backward_named["tracking"].summary()
    # The plots and the recording read e_g from the frame, whatever their place.
    assert "e_g_m" in forward_named["plots"].series and "e_g_m" in backward_named["plots"].series
    np.testing.assert_array_equal(forward_named["plots"].series["e_g_m"], backward_named["plots"].series["e_g_m"])


def test_writing_to_a_frame_raises(tmp_path):
    sim = build_simulation(load(str(room_scenario(tmp_path, duration=1.0, n_sample=40))))
    frame = None
    while frame is None or frame.commands.estimate is None or frame.observation.target_ranges is None:
        frame, healthy = sim.tick()
        assert healthy
    obs, cmd, decorations = frame.observation, frame.commands, frame.commands.decorations
    arrays = [obs.position, obs.velocity, obs.quaternion, obs.angular_velocity, obs.sensor_position,
              obs.target_ranges, obs.links.distance, obs.links.adjacency, obs.links.edges,
              cmd.position, cmd.velocity, cmd.acceleration, cmd.yaw, frame.target_positions,
              frame.state.qpos, frame.state.mocap_pos, cmd.estimate.mean, cmd.estimate.covariance,
              decorations.robot_colors, decorations.meeting_points, decorations.paths[0][0]]
    for array in arrays:
        with pytest.raises(ValueError, match="read-only"):
            array.flat[0] = 1.0
    with pytest.raises(TypeError):
        cmd.scalars["robots_waiting"] = 1.0
    with pytest.raises(TypeError):
        frame.scalars["e_g_m"] = 0.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        cmd.position = np.zeros_like(cmd.position)
    with pytest.raises(dataclasses.FrozenInstanceError):
        decorations.overlay = ""
    # The strategy's own arrays stay writeable: the frame holds read-only views.
    assert sim.observe().position.flags.writeable


def test_a_target_estimate_is_one_frozen_array_pair():
    from sim.types import TargetEstimate

    mean = np.ones((2, 3))
    estimate = TargetEstimate(3, mean, np.zeros((2, 3, 3)))
    assert mean.flags.writeable and not estimate.mean.flags.writeable
    np.testing.assert_array_equal(estimate.mean, mean)
    assert EstimationMetrics().summary() == {}
