"""Rerun recording of a run: an observer writing ``run.rrd``.

Entity tree:
  world/obstacles          static boxes of the scene (logged once)
  world/robots             robot positions, coloured by kind, labelled
  world/references         each robot's reference (virtual point)
  world/targets/true       true target positions
  world/links              communication links as line segments
  metrics/...              scalar time series (tracking error, edges, ...)
  events                   text log (start, warnings, end status)
Timelines: ``sim_time`` (s) and ``tick``. A default blueprint (3D view beside
time series and the event log) is embedded in the file.

Live (``tether run --rerun-live``): :class:`LiveViewer` serves a gRPC stream
on 127.0.0.1 and the web viewer; the recorder logs everything to it as well as
to the file, and the stream outlives the recorder so a viewer that connects
late still gets the whole run.
"""

from __future__ import annotations

import datetime
from urllib.parse import quote

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from sim.observers import Frame, tracking_errors
from sim.world import INFINITE_PLANE_HALF_SIZE, World
from viz.decorations import log_events, log_recording_decorations
from viz.video import link_color

KIND_COLORS = {"quadrotor": (230, 120, 40), "ground": (60, 160, 80)}
TARGET_COLOR = (240, 200, 30)
LINK_COLOR = (40, 190, 60)
REFERENCE_COLOR = (60, 110, 255)
FILE_FLUSH_PERIOD = datetime.timedelta(seconds=2)  # run.rrd: rows are batched this long (wall time)
FILE_FLUSH_BYTES = 8 * 1024 * 1024  # ... or up to this many bytes


def default_blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="World", origin="world"),
            rrb.Vertical(
                rrb.TimeSeriesView(name="Metrics", origin="metrics"),
                rrb.TextLogView(name="Events", origin="events"),
                row_shares=[3, 1],
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )


class LiveViewer:
    """A gRPC server on ``host:grpc_port`` streaming ``stream`` to viewers
    (``grpc_url``), and Rerun's web viewer on ``host:web_port`` connected to it
    (``web_url``); no browser is opened. The server buffers the whole stream
    for late viewers and runs until :meth:`close` (or the process ends)."""

    def __init__(self, host: str = "127.0.0.1", grpc_port: int = 9876, web_port: int = 9090):
        self.stream = rr.RecordingStream("tether")
        sink = rr.GrpcServerSink(host, grpc_port)
        self.stream.set_sinks(sink, default_blueprint=default_blueprint())
        self.grpc_url = sink.uri  # rerun+http://HOST:PORT/proxy
        self.grpc_port = grpc_port
        rr.serve_web_viewer(web_port=web_port, open_browser=False, connect_to=self.grpc_url)
        self.web_url = f"http://{host}:{web_port}/?url={quote(self.grpc_url, safe='')}"

    def close(self) -> None:
        self.stream.flush()
        self.stream.disconnect()


class _Tee:
    """Forwards logging to the file stream and a live stream; closing it
    finishes the file and only flushes the live stream (its owner closes it)."""

    def __init__(self, file_stream: rr.RecordingStream, live_stream: rr.RecordingStream):
        self.file_stream, self.live_stream = file_stream, live_stream

    def log(self, *args, **kwargs) -> None:
        self.file_stream.log(*args, **kwargs)
        self.live_stream.log(*args, **kwargs)

    def set_time(self, *args, **kwargs) -> None:
        self.file_stream.set_time(*args, **kwargs)
        self.live_stream.set_time(*args, **kwargs)

    def flush(self) -> None:
        self.file_stream.flush()
        self.live_stream.flush()

    def disconnect(self) -> None:
        self.file_stream.disconnect()
        self.live_stream.flush()

    def __getattr__(self, name):
        return getattr(self.file_stream, name)


class RerunRecorder:
    """Logs a frame every ``period_s`` of sim time (and always the last one).

    ``live_stream`` (e.g. :attr:`LiveViewer.stream`) gets everything the file
    gets; the recorder flushes it at the end but leaves it open.
    """

    def __init__(self, world: World, path: str, scenario_name: str, period_s: float = 0.05,
                 live_stream: rr.RecordingStream | None = None):
        self.world = world
        self.period_s = period_s
        # The file needs no low latency: batching rows for a few seconds of wall time gives fewer,
        # larger chunks (a 200 s connected-office run: about 5x smaller than with the default 200 ms).
        batching = rr.ChunkBatcherConfig()
        batching.flush_tick = FILE_FLUSH_PERIOD
        batching.flush_num_bytes = FILE_FLUSH_BYTES
        file_stream = rr.RecordingStream("tether", recording_id=None, batcher_config=batching)
        file_stream.save(path, default_blueprint=default_blueprint())
        self.rec = file_stream if live_stream is None else _Tee(file_stream, live_stream)
        self.rows = 0
        self._next_time = 0.0
        self._robot_series: set[str] = set()
        self._log_static(scenario_name)

    def _log_static(self, scenario_name: str) -> None:
        boxes = self.world.obstacles
        lo, hi = self.world.bounds
        halves = boxes.half_sizes.copy()
        centers = boxes.centers.copy()
        # Infinite planes would swamp the view: clip them to the scene extent.
        huge = halves >= INFINITE_PLANE_HALF_SIZE / 2
        halves[huge] = np.broadcast_to((hi - lo) / 2, halves.shape)[huge]
        centers[huge] = np.broadcast_to((hi + lo) / 2, centers.shape)[huge]
        quats = [_quat_xyzw(r) for r in boxes.rotations]
        self.rec.log(
            "world/obstacles",
            rr.Boxes3D(centers=centers, half_sizes=halves, quaternions=quats, colors=(150, 160, 175, 90),
                       fill_mode="solid"),
            static=True,
        )
        labels = list(self.world.robot_names)
        self.rec.log("world/robots", rr.Points3D(np.zeros((len(labels), 3)), labels=labels,
                                                  colors=[KIND_COLORS[k] for k in self.world.robot_kinds],
                                                  radii=0.08), static=False)
        self.rec.log("events", rr.TextLog(f"run started: scenario {scenario_name}, {len(labels)} robots"), static=False)

    def _set_time(self, frame: Frame) -> None:
        self.rec.set_time("sim_time", duration=frame.observation.time_s)
        self.rec.set_time("tick", sequence=frame.observation.tick)

    def on_tick(self, frame: Frame) -> None:
        log_events(self, frame)  # a strategy's info['events'], every tick
        if frame.observation.time_s + 1e-9 < self._next_time:
            return
        self._next_time += self.period_s
        self.log_frame(frame)

    def log_frame(self, frame: Frame) -> None:
        obs = frame.observation
        self._set_time(frame)
        self.rec.log("world/robots", rr.Points3D(obs.position))
        self.rec.log("world/references", rr.Points3D(frame.commands.position, colors=REFERENCE_COLOR, radii=0.03))
        if len(frame.target_positions):
            self.rec.log("world/targets/true", rr.Points3D(frame.target_positions, colors=TARGET_COLOR, radii=0.06))
        edges = obs.links.edges
        strips = obs.position[edges] if len(edges) else np.zeros((0, 2, 3))
        weights = frame.commands.info.get("link_weights")  # optional (N, N): green (1) to red (0)
        colors = LINK_COLOR if weights is None or not len(edges) else [
            tuple(int(round(255 * c)) for c in link_color(weights[i, j])[:3]) for i, j in edges]
        self.rec.log("world/links", rr.LineStrips3D(strips, colors=colors, radii=0.01))
        self.rec.log("metrics/edges", rr.Scalars(float(len(edges))))
        error = tracking_errors(self.world.robot_kinds, obs.position, frame.commands.position)
        self.rec.log("metrics/tracking_error_mean_m", rr.Scalars(float(error.mean())))
        for key, value in frame.commands.info.get("scalars", {}).items():
            self.rec.log(f"metrics/{key}", rr.Scalars(float(value)))
        # Optional per-robot series, info['robot_scalars'] = {name: (N,) values}: robots/NAME, one
        # series per robot named after it (NaN = not defined for that robot at this tick: a gap).
        for key, values in frame.commands.info.get("robot_scalars", {}).items():
            if key not in self._robot_series:
                self._robot_series.add(key)
                self.rec.log(f"robots/{key}", rr.SeriesLines(names=list(self.world.robot_names)), static=True)
            self.rec.log(f"robots/{key}", rr.Scalars(np.asarray(values, dtype=float)))
        log_recording_decorations(self, frame)  # optional info keys: team colours, plans, estimates
        self.rows += 1

    def event(self, time_s: float, text: str, level: str = "INFO") -> None:
        self.rec.set_time("sim_time", duration=time_s)
        self.rec.log("events", rr.TextLog(text, level=level))

    def close(self, status: str) -> None:
        self.rec.log("events", rr.TextLog(f"run ended: {status}", level="INFO" if status == "completed" else "WARN"))
        self.rec.flush()
        self.rec.disconnect()


def _quat_xyzw(rotation: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(rotation).as_quat()  # x, y, z, w as rerun expects
