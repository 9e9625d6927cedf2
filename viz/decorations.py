"""Drawing a strategy's decorations in the video and the Rerun recording.

What a strategy draws is :class:`sim.types.Decorations` (``commands.decorations``:
robot colours, paths, meeting points, markers, legend, overlay, events;
every field optional, empty draws nothing) and its target estimate
``commands.estimate`` (:class:`sim.types.TargetEstimate`: spheres in the
video, points and 2-sigma covariance ellipsoids in the recording).
Quadrotors get a small marker sphere on top: their ``robot_colors`` entry
(e.g. the prime traveler highlighted), else their kind's colour, so what
the legend names is what is drawn.

Colours come from :mod:`sim.palette`. Links under a radio preset other
than ``ideal`` are coloured by the pair's delivery probability
(``Observation.radio.delivery``) on the palette's link ramp, pale grey (0)
to charcoal (1), and drawn thinner the lower it is
(:func:`link_delivery_colors`); under ``ideal`` the connected strategy's
links take the same ramp by their weight (``link_weights``), other links
the ramp's full value. :func:`frame_legend` lists every kind of thing drawn,
the link scale with its meaning included: the video's side panel, the
tuning page, the viewer and the recording all show that one list.

Pure drawing helpers: they only read the frame.
"""

from __future__ import annotations

import functools

import numpy as np

from sim import palette

PATH_WIDTH_M = 0.012  # video: planned-path capsule width, m
PATH_MIN_PX = 1.2  # ... and at least this many pixels: thinner, a path breaks into dots
PATH_MERGE_PX = 0.25  # video: a solid path's vertex closer than this to the line past it is not drawn
MARKER_MIN_PX = 4.0  # video: meeting points, estimates, markers: at least this radius, px
MEETING_RADIUS_M = 0.05  # video: meeting-point sphere radius, m
ESTIMATE_RADIUS_M = 0.07  # video: estimated-target sphere radius, m
ESTIMATE_RGBA = palette.TARGET_ESTIMATE
HALO_ALPHA = 0.45
MARKER_RADIUS_M = 0.12  # video: ``markers`` sphere radius, m
QUAD_MARK_RADIUS_M = 0.12  # video: the ``robot_colors`` sphere on top of a quadrotor, m
QUAD_MARK_HEIGHT_M = 0.12  # ... and its height above the body origin, m
ELLIPSOID_SIGMAS = 2.0  # recording: covariance ellipsoid half-axes in standard deviations


TARGET_RGBA = palette.TARGET_TRUE  # models/robots/target.xml's marker


def delivery_rgba(delivery) -> np.ndarray:
    """RGBA (0..1, float32; shape (..., 4)) of delivery probabilities on the palette's link ramp."""
    return palette.link_rgba(delivery)


def radio_of(frame):
    """The frame's ``RadioState`` when its preset is not ideal, else None (links keep today's colours)."""
    return observation_radio(frame.observation)


def observation_radio(observation):
    """``observation.radio`` when its preset is not ideal, else None."""
    from sim.radio.presets import PRESETS

    radio = getattr(observation, "radio", None)
    preset = getattr(radio, "preset", None)
    if radio is None or preset not in PRESETS or PRESETS[preset].is_ideal:
        return None
    return radio


def link_delivery_colors(frame) -> np.ndarray | None:
    """(E, 4) RGBA of ``frame.observation.links.edges`` by the pair's delivery probability
    (:func:`delivery_rgba`) under a non-ideal radio; None under ideal."""
    radio = radio_of(frame)
    if radio is None:
        return None
    edges = np.asarray(frame.observation.links.edges, dtype=int).reshape(-1, 2)
    return delivery_rgba(np.asarray(radio.delivery)[edges[:, 0], edges[:, 1]])


def link_values(frame) -> np.ndarray | None:
    """(E,) link quality in [0, 1] of ``frame.observation.links.edges``: the pair's delivery
    probability under a non-ideal radio, else the strategy's ``link_weights``; None when neither."""
    edges = np.asarray(frame.observation.links.edges, dtype=int).reshape(-1, 2)
    radio = radio_of(frame)
    if radio is not None:
        return np.asarray(radio.delivery, dtype=float)[edges[:, 0], edges[:, 1]]
    weights = frame.commands.decorations.link_weights
    if weights is None:
        return None
    return np.asarray(weights, dtype=float)[edges[:, 0], edges[:, 1]]


def link_legend(frame) -> list[tuple[str, np.ndarray]]:
    """The legend's entries of the links: the ramp's swatches and what it measures."""
    if radio_of(frame) is not None:
        return [(f"link delivery {v:g}" + {0.0: " (packets lost)", 1.0: " (all delivered)"}.get(v, ""),
                 palette.link_rgba(v)) for v in palette.LINK_SCALE[::-1]]
    if frame.commands.decorations.link_weights is not None:
        return [(f"link weight {v:g}" + {0.0: " (about to break)", 1.0: " (strong)"}.get(v, ""),
                 palette.link_rgba(v)) for v in palette.LINK_SCALE[::-1]]
    return [("communication link", palette.link_rgba(1.0))]


def link_delivery_legend() -> list[tuple[str, np.ndarray]]:
    """The legend's entries of the delivery ramp, 1 first."""
    return [(f"link delivery {v:g}", palette.link_rgba(v)) for v in palette.LINK_SCALE[::-1]]


def frame_legend(frame, robot_kinds=(), scenery=()) -> list[tuple[str, np.ndarray]]:
    """What the colours of ``frame``'s picture mean, every kind of thing drawn: the
    strategy's ``legend`` (roles, teams, paths), the robots' kinds when the strategy
    colours none (``robot_kinds``: the world's, in robot order), the references, the
    links' scale, the scene's obstacles (``scenery``: :func:`viz.scenery.scenery_legend`),
    then the true targets and their estimates when shown."""
    decorations = frame.commands.decorations
    legend = list(decorations.legend)
    if decorations.robot_colors is None:
        legend += [(f"{kind} robot", palette.KIND[kind]) for kind in dict.fromkeys(robot_kinds)]
    if len(frame.commands.position):
        legend.append(("reference (point steered to)", palette.REFERENCE))
    legend += link_legend(frame)
    legend += list(scenery)
    if len(frame.target_positions):
        legend.append(("target (true)", TARGET_RGBA))
    estimate = frame.commands.estimate
    if estimate is not None and len(estimate.mean):
        legend.append(("target estimate (EKF)", ESTIMATE_RGBA))
    return legend


def halo_color(decorations, robot: int, default: np.ndarray) -> np.ndarray:
    """The video halo colour of ``robot``: its ``robot_colors`` entry, translucent."""
    colors = decorations.robot_colors
    if colors is None or robot >= len(colors):
        return default
    rgba = np.array(colors[robot], dtype=np.float32)
    rgba[3] = HALO_ALPHA
    return rgba


def draw_video_decorations(renderer, frame) -> None:
    """Planned paths, meeting points and target estimates into a
    :class:`viz.video.FrameRenderer`'s scene (its ``_add_capsule`` /
    ``_add_sphere``)."""
    decorations = frame.commands.decorations
    width = renderer.at_least(PATH_WIDTH_M, PATH_MIN_PX)
    period = renderer.at_least(DASH_PERIOD_M, DASH_PERIOD_PX)
    merge = PATH_MERGE_PX * renderer.metres_per_px
    styles = decorations.path_styles
    for k, (points, rgba) in enumerate(decorations.paths or ()):
        rgba = np.asarray(rgba, dtype=np.float32)
        style = styles[k] if styles is not None and k < len(styles) else "solid"
        points = np.asarray(points, dtype=float)
        if style == "solid":  # each capsule costs software GL ~70 us: nearly collinear runs become one
            points = _merged_path(points, merge)
        for a, b in styled_segments(points, style, period):
            renderer._add_capsule(a, b, width, rgba)
    _draw_spheres(renderer, decorations.meeting_points, decorations.meeting_point_colors,
                  renderer.at_least(MEETING_RADIUS_M, MARKER_MIN_PX),
                  np.array([1, 1, 1, 0.5], np.float32))
    estimate = frame.commands.estimate
    if estimate is not None:
        for p in np.asarray(estimate.mean, dtype=float):
            renderer._add_sphere(p, renderer.at_least(ESTIMATE_RADIUS_M, MARKER_MIN_PX), ESTIMATE_RGBA)
    _draw_spheres(renderer, decorations.markers, decorations.marker_colors,
                  renderer.at_least(MARKER_RADIUS_M, MARKER_MIN_PX),
                  np.array([1, 1, 1, 0.8], np.float32))
    # Every quadrotor gets a mark on top: its role or team colour, else its kind's (the legend's entry).
    robot_colors = decorations.robot_colors
    positions = frame.observation.position
    for i in renderer.world.kind_index["quadrotor"]:
        rgba = robot_colors[i] if robot_colors is not None and i < len(robot_colors) else palette.KIND["quadrotor"]
        top = positions[i] + np.array([0.0, 0.0, QUAD_MARK_HEIGHT_M])
        renderer._add_sphere(top, renderer.at_least(QUAD_MARK_RADIUS_M, MARKER_MIN_PX), np.asarray(rgba, np.float32))


DASH_PERIOD_M = 0.3  # a dashed or dotted path's pattern repeats every this many metres ...
DASH_PERIOD_PX = 18.0  # ... and at least every this many pixels of a view of the whole floor
DASH_ON_SHARE = {"dashed": 0.6, "dotted": 0.45}  # the drawn share of each period
# Each style's period as a share of the dashed one: dots at half the pitch read as a dotted line, not as
# specks (a fifth of 18 px every 18 px did not, at 960x540).
STYLE_PERIOD_SHARE = {"dashed": 1.0, "dotted": 0.5}


def styled_segments(points: np.ndarray, style: str, period_m: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """The pieces (start, end) of the polyline ``points`` (K, 3) to draw in ``style``: its
    segments ("solid"), or along its length the first ``DASH_ON_SHARE`` of every period
    (``period_m`` times the style's ``STYLE_PERIOD_SHARE``; "dashed", "dotted"; the pattern runs on
    across corners). Zero-length segments are dropped."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(points) < 2:
        return []
    steps = np.linalg.norm(np.diff(points, axis=0), axis=1)
    if style == "solid":
        return [(points[i], points[i + 1]) for i in np.flatnonzero(steps > 1e-6)]
    period_m = period_m * STYLE_PERIOD_SHARE[style]
    on = DASH_ON_SHARE[style] * period_m
    along = np.concatenate([[0.0], np.cumsum(steps)])
    pieces = []
    for start in np.arange(0.0, along[-1], period_m):
        stop = min(start + on, along[-1])
        if stop - start > 1e-6:
            pieces.append((_at(points, along, start), _at(points, along, stop)))
    return pieces


def merged_polyline(points: np.ndarray, tolerance_m: float) -> np.ndarray:
    """The vertices of the polyline ``points`` (K, 3) that its picture needs: going along it,
    a run of vertices is replaced by the segment from its first to its last while every vertex
    in between lies within ``tolerance_m`` of that segment (first and last vertices kept; a
    dashed or dotted path is not merged: its pattern runs along the original's length)."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(points) < 3 or tolerance_m <= 0:
        return points
    return points[_merge_keep(points, tolerance_m)]


def _merged_path(points: np.ndarray, tolerance_m: float) -> np.ndarray:
    """:func:`merged_polyline` of a drawn path, its first segment kept as it is: a path's first
    vertex is its robot's position, new every frame, the rest the same plan for many frames, so
    the merge of the rest is remembered (keyed on its bytes) instead of redone each frame."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    if len(points) < 4:
        return points
    rest = np.ascontiguousarray(points[1:])
    keep = _merged_indices(rest.tobytes(), float(tolerance_m))
    return np.concatenate([points[:1], rest[list(keep)]])


@functools.lru_cache(maxsize=256)
def _merged_indices(rest: bytes, tolerance_m: float) -> tuple[int, ...]:
    points = np.frombuffer(rest, dtype=float).reshape(-1, 3)
    return tuple(_merge_keep(points, tolerance_m))


def _merge_keep(points: np.ndarray, tolerance_m: float) -> list[int]:
    """The indices :func:`merged_polyline` keeps."""
    keep = [0]
    start = 0
    for end in range(2, len(points)):
        if _off_chord(points[start], points[end], points[start + 1:end]) > tolerance_m:
            start = end - 1
            keep.append(start)
    keep.append(len(points) - 1)
    return keep


def _off_chord(a: np.ndarray, b: np.ndarray, between: np.ndarray) -> float:
    """The largest distance of the points ``between`` (M, 3) from the segment ``a``-``b``."""
    ab = b - a
    length2 = float(ab @ ab)
    t = np.zeros(len(between)) if length2 < 1e-18 else np.clip((between - a) @ ab / length2, 0.0, 1.0)
    return float(np.max(np.linalg.norm(a + t[:, None] * ab - between, axis=1)))


def _at(points: np.ndarray, along: np.ndarray, s: float) -> np.ndarray:
    """The point at arc length ``s`` of the polyline (``along``: arc length at each vertex).
    A dash across a corner is drawn straight: at 0.3 m periods the corner cut is a few cm."""
    return np.array([np.interp(s, along, points[:, d]) for d in range(3)])


def _draw_spheres(renderer, points, colors, radius: float, default_rgba: np.ndarray) -> None:
    """One sphere per point, in its ``colors`` entry (or ``default_rgba``)."""
    if points is None or not len(points):
        return
    for k, p in enumerate(np.asarray(points, dtype=float)):
        rgba = np.asarray(colors[k], dtype=np.float32) if colors is not None else default_rgba
        renderer._add_sphere(p, radius, rgba)


def _rgb8(rgba: np.ndarray) -> np.ndarray:
    return np.clip(np.round(np.asarray(rgba, dtype=float) * 255), 0, 255).astype(np.uint8)


def colour_name(rgb) -> str:
    """The palette's plain name for an RGB colour (0..255): the recording's legend is text,
    so it says "blue" beside the hex code."""
    return palette.colour_name(np.asarray(rgb[:3], dtype=float) / 255)


def robot_colors_rgb8(decorations, default: np.ndarray) -> np.ndarray:
    """(N, 3) uint8 recording colours of the robots: ``robot_colors`` when the
    strategy gives one per robot, else ``default``."""
    colors = decorations.robot_colors
    if colors is None or len(colors) != len(default):
        return default
    return _rgb8(np.asarray(colors, dtype=float)[:, :3])


def _changed(logged: dict, key: str, value) -> bool:
    """True the first time and whenever ``value`` is a different object than
    last logged (strategies rebuild these only when they change)."""
    if key in logged and logged[key] is value:
        return False
    logged[key] = value
    return True


def log_recording_decorations(rec, frame, logged: dict) -> None:
    """Log the decorations of ``frame`` to the Rerun stream ``rec`` (time
    already set; the recorder colours the robots itself,
    :func:`robot_colors_rgb8`). Plans, meeting points and estimates are
    logged only when the strategy hands over new objects (``logged``: the
    caller's record of what it last logged), so the recording stays small."""
    import rerun as rr

    decorations = frame.commands.decorations
    paths = decorations.paths
    if paths is not None and _changed(logged, "paths", paths):
        rec.log("world/plans", rr.LineStrips3D([np.asarray(p, dtype=float) for p, _ in paths],
                                               colors=[_rgb8(c) for _, c in paths], radii=0.01))
    meeting = decorations.meeting_points
    if meeting is not None and _changed(logged, "meeting_points", meeting):
        point_colors = decorations.meeting_point_colors
        rec.log("world/meetings", rr.Points3D(np.asarray(meeting, dtype=float).reshape(-1, 3),
                                              colors=None if point_colors is None else _rgb8(point_colors),
                                              radii=0.05))
    estimate = frame.commands.estimate
    if estimate is not None and _changed(logged, "target_estimate", estimate):
        estimates = np.asarray(estimate.mean, dtype=float)
        rec.log("world/targets/estimate", rr.Points3D(estimates, colors=_rgb8(ESTIMATE_RGBA), radii=0.05))
        covariances = estimate.covariance
        if covariances is not None:
            values, vectors = np.linalg.eigh(np.asarray(covariances, dtype=float))
            vectors = vectors * np.where(np.linalg.det(vectors) < 0, -1.0, 1.0)[:, None, None]
            from scipy.spatial.transform import Rotation

            quats = Rotation.from_matrix(vectors).as_quat()  # x, y, z, w
            half = ELLIPSOID_SIGMAS * np.sqrt(np.maximum(values, 0.0))
            rec.log("world/targets/covariance", rr.Ellipsoids3D(centers=estimates, half_sizes=half,
                                                                quaternions=quats, colors=_rgb8(ESTIMATE_RGBA)))
    markers = decorations.markers
    if markers is not None:
        marker_colors = decorations.marker_colors
        rec.log("world/markers", rr.Points3D(np.asarray(markers, dtype=float).reshape(-1, 3),
                                             colors=None if marker_colors is None else _rgb8(marker_colors),
                                             radii=0.08))


def log_events(recorder, frame) -> None:
    """Every string in the decorations' ``events`` as one event of the recording."""
    for text in frame.commands.decorations.events:
        recorder.on_event(frame.observation.time_s, str(text), tick=frame.observation.tick)
