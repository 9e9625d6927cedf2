"""Rerun recording of a run: an observer writing ``run.rrd``.

Entity tree:
  world/obstacles          static boxes of the scene (logged once)
  world/robots             robot positions, coloured by kind (or by the strategy's
                           ``robot_colors``); names and sizes static
  world/references         each robot's reference (virtual point)
  world/targets/true       true target positions
  world/links              communication links as line segments (coloured by
                           the strategy's ``link_weights`` when given; by the
                           pair's delivery probability under a non-ideal radio)
  world/radio_map          under a non-ideal radio: the mean received power from
                           robot 0 at its start (sim.radio.radiomap), a static mesh
                           with vertex colours on the floor (viridis)
  world/plans, world/meetings, world/targets/estimate, world/targets/covariance,
  world/markers            the strategy's decorations (viz.decorations)
  metrics/...              scalar time series (tracking error, edges, and the
                           strategy's ``scalars``, which win a name clash)
  robots/...               per-robot series (the strategy's ``robot_scalars``)
  events                   text log (start, the strategy's events, warnings,
                           end status)
  legend                   what the colours mean (Markdown; logged when it changes)
Timelines: ``sim_time`` (s) and ``tick``; every temporal row has both. A
default blueprint (3D view beside time series and the event log) is embedded
in the file.

The file is written as complete segment files (``run.rrd.segments/``,
each with its footer; the first after 1 s of wall time, then ever longer up
to 30 s; the stream logs into memory and tether writes the files) and
merged into ``run.rrd`` when the run ends; a run killed outright leaves its
finished segments readable (``RrdReader(...).store()``; open them together
in the viewer: they share one recording id).

Live (``tether run --rerun-live``): :class:`LiveViewer` serves a gRPC stream
and the web viewer on 127.0.0.1 (or ``--host``); the recorder logs everything
to it as well as to the file, and the stream outlives the recorder so a viewer
that connects late still gets the whole run.
"""

from __future__ import annotations

import contextlib
import datetime
import errno
import os
import re
import shutil
import socket
import subprocess
import time
import uuid
from pathlib import Path
from urllib.parse import quote

import numpy as np

# Rerun's Rust side logs its file writer's errors (a full disk: three lines, coloured, of which none names
# the file the run lost) to stderr: the recorder reports a recording it could not write itself, in the
# run's message. Rerun reads RUST_LOG when it is imported; one the user set is kept.
os.environ.setdefault("RUST_LOG", "off")

import rerun as rr  # noqa: E402  (after RUST_LOG)
import rerun.blueprint as rrb  # noqa: E402
from rerun.chunk import RrdReader  # noqa: E402

from sim.loop import ObserverFailure  # noqa: E402
from sim.observers import Frame, Observer, link_figures, tracking_errors  # noqa: E402
from sim.outputs import no_space_left  # noqa: E402
from sim.strategy import Status  # noqa: E402
from sim.world import INFINITE_PLANE_HALF_SIZE, World  # noqa: E402
from sim import palette  # noqa: E402
from viz.decorations import (colour_name,  # noqa: E402
                              frame_legend, link_values, log_events, log_recording_decorations,
                             robot_colors_rgb8)

KIND_COLORS = {kind: palette.rgb8(rgba) for kind, rgba in palette.KIND.items()}
ROBOT_RADIUS_M = 0.08
TARGET_COLOR = palette.rgb8(palette.TARGET_TRUE)
LINK_COLOR = palette.rgb8(palette.link_rgba(1.0))
OBSTACLE_RGB = (150, 160, 175)  # the scene's static boxes, translucent: the robots inside show through
REFERENCE_COLOR = palette.rgb8(palette.REFERENCE)
FILE_FLUSH_PERIOD = datetime.timedelta(seconds=2)  # run.rrd: rows are batched this long (wall time)
FILE_FLUSH_BYTES = 8 * 1024 * 1024  # ... or up to this many bytes
# The recording is written as complete segment files, the first after SEGMENT_FIRST_S of wall time, each
# next one twice as long up to SEGMENT_MAX_S (a killed run keeps all but its last few seconds) ...
SEGMENT_FIRST_S = 1.0
SEGMENT_MAX_S = 30.0
SEGMENTS_SUFFIX = ".segments"
RADIO_MAP_LIFT_M = 0.01  # the radio map's mesh lies this far above the floor, m
# Every flush of the recording's streams (memory sinks: tether writes the files) is bounded.
SEGMENT_FLUSH_TIMEOUT_S = 20.0
MERGE_FLUSH_TIMEOUT_S = 20.0  # ... plus a second per MERGE_BYTES_PER_S of the segments
MERGE_BYTES_PER_S = 10 * 1024 * 1024
MERGE_SPARE_BYTES = 256 * 1024  # free space the merge needs beyond the segments' own size
PROPERTIES = "/__properties"  # Rerun's recording properties entity  # ... in run.rrd.segments/, merged into run.rrd when the run ends


def default_blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial3DView(name="World", origin="world"),
            rrb.Vertical(
                rrb.TimeSeriesView(name="Metrics", origin="metrics"),
                rrb.TextLogView(name="Events", origin="events"),
                rrb.TextDocumentView(name="Legend", origin="legend"),
                row_shares=[3, 1, 1],
            ),
            column_shares=[3, 2],
        ),
        collapse_panels=True,
    )



@contextlib.contextmanager
def _rerun_writing(path: Path):
    """Rerun's writes fail with a RuntimeError ("... (os error 28)"): as the OSError it is,
    naming ``path``, so the command's barrier says it in one line (a full disk)."""
    try:
        yield
    except RuntimeError as err:  # rerun's writer failing: with its os error, or only "thread shut down"
        found = re.search(r"os error (\d+)", str(err))
        if found:
            code = int(found.group(1))
            raise OSError(code, os.strerror(code), str(path)) from None
        raise OSError(errno.EIO, f"Rerun could not write it ({str(err).splitlines()[0]})", str(path)) from None

class LiveViewer:
    """Rerun's gRPC server and web viewer on ``host`` (default 127.0.0.1:
    this machine only), both bound there, streaming ``stream`` to viewers
    (``grpc_url``, ``web_url``); no browser is opened.

    rerun-sdk 0.41's ``serve_web_viewer`` takes no bind address (it listens
    on 0.0.0.0), so the servers are the ``rerun`` binary's own
    (``rerun --serve-web --bind HOST``), run as a child process that ends
    with this one; it buffers the whole stream for late viewers and serves
    until :meth:`close`."""

    def __init__(self, host: str = "127.0.0.1", grpc_port: int = 9876, web_port: int = 9090):
        command = [_rerun_binary(), "--serve-web", "--bind", host, "--port", str(grpc_port),
                   "--web-viewer-port", str(web_port)]
        self._server = subprocess.Popen(command, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                                        stderr=subprocess.DEVNULL, start_new_session=True,
                                        preexec_fn=_end_with_parent)
        connect = "127.0.0.1" if host in ("0.0.0.0", "") else "::1" if host == "::" else host
        try:
            for port in (grpc_port, web_port):
                _wait_for_port(connect, port, self._server)
        except OSError:
            self._stop_server()
            raise
        shown = f"[{connect}]" if ":" in connect else connect
        self.grpc_url = f"rerun+http://{shown}:{grpc_port}/proxy"
        self.grpc_port = grpc_port
        self.stream = rr.RecordingStream("tether")
        self.stream.set_sinks(rr.GrpcSink(self.grpc_url), default_blueprint=default_blueprint())
        self.web_url = f"http://{shown}:{web_port}/?url={quote(self.grpc_url, safe='')}"

    def close(self) -> None:
        self.stream.flush()
        self.stream.disconnect()
        self._stop_server()

    def _stop_server(self) -> None:
        if self._server.poll() is None:
            self._server.terminate()
            try:
                self._server.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self._server.kill()
                self._server.wait()


def _rerun_binary() -> str:
    """The viewer binary itself (rerun-sdk's ``rerun`` script is a Python
    wrapper that would leave it running when terminated)."""
    import os

    if os.environ.get("RERUN_CLI_PATH"):
        return os.environ["RERUN_CLI_PATH"]
    try:
        import rerun_cli

        bundled = Path(rerun_cli.__file__).parent / "rerun"
        if bundled.exists():
            return str(bundled)
    except ImportError:
        pass
    found = shutil.which("rerun")
    if not found:
        raise OSError("the rerun binary (from rerun-sdk) is not installed")
    return found


def _end_with_parent() -> None:
    """In the child: receive SIGTERM when the parent dies (Linux), so a killed run leaves no server behind."""
    try:
        import ctypes
        import signal

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _wait_for_port(host: str, port: int, server: subprocess.Popen, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise OSError(f"the rerun server could not listen on {host}:{port} (exit code {server.returncode})")
        try:
            with socket.create_connection((host, port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.1)
    raise OSError(f"the rerun server did not listen on {host}:{port} within {timeout_s:g} s")


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

    def disable_timeline(self, timeline: str) -> None:
        self.file_stream.disable_timeline(timeline)
        self.live_stream.disable_timeline(timeline)

    def flush(self) -> None:
        self.file_stream.flush()
        self.live_stream.flush()

    def disconnect(self) -> None:
        self.file_stream.disconnect()
        self.live_stream.flush()

    def __getattr__(self, name):
        return getattr(self.file_stream, name)


class RerunRecorder(Observer):
    """Logs a frame every ``period_s`` of sim time, and the run's last frame
    when it closes; events (``Decorations.events``) at the tick they happen.

    ``live_stream`` (e.g. :attr:`LiveViewer.stream`) gets everything the file
    gets; the recorder flushes it at the end but leaves it open.
    """

    def __init__(self, world: World, path: str, scenario_name: str, period_s: float = 0.05,
                 live_stream: rr.RecordingStream | None = None):
        self.world = world
        self.period_s = period_s
        # The file needs no low latency: batching rows for a few seconds of wall time gives fewer,
        # larger chunks, so a smaller file than with the SDK's default batching.
        self.path = Path(path)
        self.segments = self.path.with_name(self.path.name + SEGMENTS_SUFFIX)
        self.segments.mkdir(parents=True, exist_ok=True)
        self.recording_id = str(uuid.uuid4())
        self._segment_count = 0
        self._segment_period_s = SEGMENT_FIRST_S
        self._rotate_at = time.monotonic() + self._segment_period_s
        file_stream = self._segment_stream()
        self.rec = file_stream if live_stream is None else _Tee(file_stream, live_stream)
        self.failed = ""  # why the recording was given up ("": it was not)
        self.rows = 0
        self._next_time = 0.0
        self._unlogged: Frame | None = None  # the latest frame, when the period skipped it
        self._latest = (0.0, 0)  # latest (sim time, tick) logged at, for the closing event
        self._robot_series: set[str] = set()
        self._decorations_logged: dict = {}  # decoration key -> the object last logged
        self._legend = ""  # the legend text last logged
        self._radio_map_note = ""  # the legend's line on the radio map, when logged
        self._kind_colors = np.array([KIND_COLORS[k] for k in world.robot_kinds], dtype=np.uint8)
        self._log_static(scenario_name)

    def _segment_stream(self) -> rr.RecordingStream:
        """The file's stream: a memory sink (``binary_stream``) whose bytes, read at each rotation, are
        one complete .rrd file (header to footer), written here by Python. Rerun's own file writer is
        never used: once it has failed (a full disk) every flush, disconnect, sink change or collection
        of its stream waits for ever (rerun-sdk 0.41), so a stream given up could never be released."""
        batching = rr.ChunkBatcherConfig()
        batching.flush_tick = FILE_FLUSH_PERIOD
        batching.flush_num_bytes = FILE_FLUSH_BYTES
        stream = rr.RecordingStream("tether", recording_id=self.recording_id, batcher_config=batching)
        self._bytes = stream.binary_stream()
        stream.send_blueprint(default_blueprint())
        return stream

    def _file_stream(self) -> rr.RecordingStream:
        return self.rec.file_stream if isinstance(self.rec, _Tee) else self.rec

    def _write_segment(self) -> None:
        """What the stream holds since the last segment, as the next complete segment file; OSError if
        it could not be written (its partial file is removed with the segments)."""
        part = self.segments / f"part-{self._segment_count:05d}.rrd"
        with _rerun_writing(part):
            data = self._bytes.read(flush=True, flush_timeout_sec=SEGMENT_FLUSH_TIMEOUT_S)
        partial = part.with_name(part.name + ".partial")
        with open(partial, "wb") as file:
            file.write(data or b"")
        os.replace(partial, part)  # a part-*.rrd is complete, even in a run killed while writing it
        self._segment_count += 1

    def _rotate(self) -> None:
        try:
            self._write_segment()
        except OSError as err:
            self._give_up(err)
        self._segment_period_s = min(2 * self._segment_period_s, SEGMENT_MAX_S)
        self._rotate_at = time.monotonic() + self._segment_period_s

    def _merge(self) -> None:
        """run.rrd: every segment's chunks in one file; the segments go. The merged file is about as
        large as the segments together: the file system must have that much room first."""
        parts = sorted(self.segments.glob("part-*.rrd"))
        size = sum(part.stat().st_size for part in parts)
        free = shutil.disk_usage(self.segments).free
        if free < size + MERGE_SPARE_BYTES:
            raise OSError(errno.ENOSPC, f"{os.strerror(errno.ENOSPC)} (the merge needs about "
                                        f"{(size + MERGE_SPARE_BYTES) / 1024:.0f} KiB, {free / 1024:.0f} KiB free)",
                          str(self.path))
        merged = rr.RecordingStream("tether", recording_id=self.recording_id)
        try:
            merged_bytes = merged.binary_stream()
            merged.send_blueprint(default_blueprint())
            with _rerun_writing(self.path):
                for part in parts:  # each segment's first chunks are the recording properties: one set here
                    rr.send_chunks((c for c in RrdReader(part).stream()
                                    if not str(c.entity_path).startswith(PROPERTIES)), recording=merged)
                data = merged_bytes.read(flush=True,
                                         flush_timeout_sec=MERGE_FLUSH_TIMEOUT_S + size / MERGE_BYTES_PER_S)
        finally:
            merged.disconnect()
        with open(self.path, "wb") as file:
            file.write(data or b"")
        shutil.rmtree(self.segments)

    def _release(self) -> None:
        """The file's stream disconnected (a memory sink: it returns at once) and dropped, on every
        path: an API user's run leaves no Rerun stream behind."""
        stream = self._file_stream()
        if stream is None:
            return
        stream.disconnect()
        if isinstance(self.rec, _Tee):
            self.rec.file_stream = None
        else:
            self.rec = None
        self._bytes = None

    def _give_up(self, err: OSError) -> None:
        """The recording cannot be written: remove its files (tether's own), stop writing, and end the
        run "failed" with the reason (ObserverFailure). A writer that stopped without saying why, on a
        file system with no room left, is a full disk."""
        code = err.errno
        if code != errno.ENOSPC and no_space_left(self.segments.parent):
            code = errno.ENOSPC
        reason = err.strerror if code == err.errno else os.strerror(code)
        self.failed = f"recording failed, {self.path.name} not written: {reason} ({errno.errorcode.get(code, code)})"
        self._release()
        shutil.rmtree(self.segments, ignore_errors=True)
        with contextlib.suppress(OSError):
            self.path.unlink()
        raise ObserverFailure(self.failed)

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
            rr.Boxes3D(centers=centers, half_sizes=halves, quaternions=quats, colors=(*OBSTACLE_RGB, 90),
                       fill_mode="solid"),
            static=True,
        )
        # Names and sizes never change: static, so they show on every timeline (rows without a
        # sim_time would not show on it). Positions and colours are logged with each frame.
        labels = list(self.world.robot_names)
        self.rec.log("world/robots", rr.Points3D.from_fields(labels=labels, radii=ROBOT_RADIUS_M), static=True)
        self.on_event(0.0, f"run started: scenario {scenario_name}, {len(labels)} robots", tick=0)

    def _set_time(self, time_s: float, tick: int | None) -> None:
        self.rec.set_time("sim_time", duration=time_s)
        if tick is None:  # (no stale tick from an earlier frame)
            self.rec.disable_timeline("tick")
        else:
            self.rec.set_time("tick", sequence=tick)
        if time_s >= self._latest[0]:
            self._latest = (time_s, tick)

    def on_tick(self, frame: Frame) -> None:
        if self.failed:
            return
        if time.monotonic() >= self._rotate_at:
            self._rotate()
        log_events(self, frame)  # a strategy's decorations' events, every tick
        if frame.observation.time_s + 1e-9 < self._next_time:
            self._unlogged = frame
            return
        self._next_time += self.period_s
        self._unlogged = None
        self.log_frame(frame)

    def log_frame(self, frame: Frame) -> None:
        obs = frame.observation
        decorations = frame.commands.decorations
        self._set_time(obs.time_s, obs.tick)
        self.rec.log("world/robots", rr.Points3D(obs.position, colors=robot_colors_rgb8(decorations, self._kind_colors)))
        self.rec.log("world/references", rr.Points3D(frame.commands.position, colors=REFERENCE_COLOR, radii=0.03))
        if len(frame.target_positions):
            self.rec.log("world/targets/true", rr.Points3D(frame.target_positions, colors=TARGET_COLOR, radii=0.06))
        edges = obs.links.edges
        strips = obs.position[edges] if len(edges) else np.zeros((0, 2, 3))
        values = link_values(frame)  # delivery (non-ideal radio) or weight, on the palette's link ramp
        colors = LINK_COLOR if values is None or not len(edges) else \
            np.clip(np.round(palette.link_rgba(values)[:, :3] * 255), 0, 255).astype(np.uint8)
        self.rec.log("world/links", rr.LineStrips3D(strips, colors=colors, radii=0.01))
        error = tracking_errors(self.world.robot_kinds, obs.position, frame.commands.position)
        figures = link_figures(obs, frame.failed)
        foundation = {"edges": float(len(edges)), "tracking_error_mean_m": float(error.mean()),
                      "comm_lambda2": figures.comm_lambda2, "radio_delivery_mean": figures.radio_delivery_mean}
        # A strategy's series of the same name replaces the foundation's (as its summary does in
        # metrics.json): one value per entity and tick.
        for key, value in {**foundation, **frame.scalars}.items():
            self.rec.log(f"metrics/{key}", rr.Scalars(float(value)))
        # Optional per-robot series, decorations.robot_scalars = {name: (N,) values}: robots/NAME, one
        # series per robot named after it (NaN = not defined for that robot at this tick: a gap).
        for key, values in decorations.robot_scalars.items():
            if key not in self._robot_series:
                self._robot_series.add(key)
                self.rec.log(f"robots/{key}", rr.SeriesLines(names=list(self.world.robot_names)), static=True)
            self.rec.log(f"robots/{key}", rr.Scalars(np.asarray(values, dtype=float)))
        log_recording_decorations(self.rec, frame, self._decorations_logged)  # optional: plans, estimates, ...
        legend = self.legend(frame)
        if legend != self._legend:  # roles and teams change rarely: log the text when it does
            self._legend = legend
            self.rec.log("legend", rr.TextDocument(legend, media_type=rr.MediaType.MARKDOWN))
        self.rows += 1

    def legend(self, frame: Frame) -> str:
        """What the colours of ``frame`` mean, as Markdown: the pictures' one legend
        (:func:`viz.decorations.frame_legend`) with each colour's name and code."""
        entries = [(label, palette.rgb8(rgba)) for label, rgba in frame_legend(frame, self.world.robot_kinds)]
        entries.append(("the scene's obstacles (see-through boxes)", OBSTACLE_RGB))
        lines = [f"- **{colour_name(rgb)}** `#{rgb[0]:02x}{rgb[1]:02x}{rgb[2]:02x}`: {label}" for label, rgb in entries]
        if self._radio_map_note:
            lines.append(f"- {self._radio_map_note}")
        return "\n".join(["**Colours**", "", *lines])

    def log_radio_map(self, radio, robot_name: str) -> None:
        """``radio`` (a :class:`sim.radio.radiomap.RadioMap`) as a static mesh on the floor under
        ``world/radio_map``: one vertex per receiver, coloured by its power (viridis)."""
        from sim.radio.radiomap import colour_limits

        ny, nx = radio.power_dbm.shape
        gx, gy = np.meshgrid(radio.x, radio.y)
        floor = float(self.world.bounds[0][2]) + RADIO_MAP_LIFT_M
        vertices = np.column_stack([gx.ravel(), gy.ravel(), np.full(gx.size, floor)])
        corner = (np.arange(ny - 1)[:, None] * nx + np.arange(nx - 1)[None, :]).ravel()
        triangles = np.concatenate([np.column_stack([corner, corner + 1, corner + nx + 1]),
                                    np.column_stack([corner, corner + nx + 1, corner + nx])]).astype(np.uint32)
        colors = _power_rgb8(radio).reshape(-1, 3)
        self.rec.log("world/radio_map", rr.Mesh3D(vertex_positions=vertices, triangle_indices=triangles,
                                                  vertex_colors=colors), static=True)
        low, high = colour_limits(radio)
        self._radio_map_note = (f"the floor: mean received power from {robot_name} at its start (z = "
                                f"{radio.height_m:.2f} m; no shadowing or fading), viridis from {low:.0f} dBm "
                                f"(dark purple) to {high:.0f} dBm (yellow); 50 % delivery at "
                                f"{radio.sensitivity_dbm:.1f} dBm")
        self.on_event(0.0, f"radio map: {self._radio_map_note}", tick=0)

    def on_event(self, time_s: float, text: str, level: str = "INFO", tick: int | None = None) -> None:
        """One line of the event log at ``time_s`` (and ``tick``, when known)."""
        if self.failed:
            return
        self._set_time(time_s, tick)
        self.rec.log("events", rr.TextLog(text, level=level))

    def close(self, status: str) -> None:
        if self.failed:  # given up during the ticks: its files are gone already
            return
        if self._unlogged is not None:  # the run's last frame, off the period's grid
            self.log_frame(self._unlogged)
            self._unlogged = None
        time_s, tick = self._latest
        self.on_event(time_s, f"run ended: {status}", level="INFO" if Status(status).finished else "WARN",
                      tick=tick)
        if isinstance(self.rec, _Tee):
            self.rec.live_stream.flush()
        try:
            self._write_segment()
            self._release()
            self._merge()
        except OSError as err:
            self._give_up(err)


def _quat_xyzw(rotation: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(rotation).as_quat()  # x, y, z, w as rerun expects


def _power_rgb8(radio) -> np.ndarray:
    """(ny, nx, 3) uint8 image of the map (row 0 at the lowest y), viridis over :func:`colour_limits`."""
    from matplotlib import colormaps

    from sim.radio.radiomap import colour_limits

    low, high = colour_limits(radio)
    scaled = np.clip((radio.power_dbm - low) / (high - low), 0.0, 1.0)
    return (colormaps["viridis"](scaled)[..., :3] * 255).round().astype(np.uint8)
