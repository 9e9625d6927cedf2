"""A scenario moved into another scene (``tether run NAME --scene my.xml``).

A built-in scenario is written for its own scene: its starts, fixed targets
and (for the intermittent methods) its EKF prior are coordinates of that
scene. :func:`place_in_scene` rewrites them for a user's scene, on the raw
TOML table, before the scenario is validated:

- starts: if the scenario's starts do not fit (outside the bounds, too close
  to an obstacle, or the team not connected), the whole start pattern is
  moved, unchanged, to the free spot nearest the scene's centre where every
  robot is clear of obstacles and the team is connected (links within the
  communication range and in line of sight). The pattern keeps the spacing
  the method was tuned for (the connected method's lattice at R'_c, the
  intermittent teams' 0.12 m cluster). A pattern that fits nowhere is tried
  turned by 90, 180 and 270 degrees; one that fits nowhere turned either is
  grown over free space instead (:func:`grow_team`: robot after robot, each
  linked to one already placed, at the pattern's spacing or, where that does
  not fit, at 0.8, 0.64 or 0.5 of it). Starts the user set (``robots.N.starts``,
  ``spawn_center``...) are kept, and a note says so; a team size
  (``robots.N.count``) is still placed.
  A team spread out on purpose (the waypoint demo, not connected at the
  start) is placed robot by robot instead: each start is scaled from the old
  scene's floor plan into the new one's and moved to the nearest free spot.
- targets (``[[targets]]``): a path that leaves the bounds or passes through
  an obstacle is redrawn, same shape and speed, at the first free spot of a
  deterministic low-discrepancy sequence over the scene.
- the ``[strategy]`` table: the method's own coordinates are its business, so
  its class adapts them (:meth:`sim.strategy.Strategy.adapt_to_scene`, given a
  :class:`sim.types.SceneChange`): waypoint routes are scaled the same way as
  the starts and moved clear of obstacles; the EKF prior of the tracking
  methods (intermittent, all_time, random_meeting, connected_tracking) is made
  non-informative over the new scene.

Every change is returned as one line for the user. Nothing here is random:
the same scenario, scene and overrides always give the same placement, so
same seed, same run. Keys the user set with ``--set`` are left alone.
"""

from __future__ import annotations

import copy
from pathlib import Path

import mujoco
import numpy as np

from sim.config import ConfigError, build
from sim.free_space import GROUND_PROBE_LIFT_M, candidate_grid, nearest_free, scale_plan
from sim.geometry import Boxes, point_clearance, segment_clearance
from sim.scenario import SCENE_DIR, Scenario, TargetConfig, from_table, load_table, resolve_scene
from sim.strategy import strategy_class
from sim.targets import nominal_path_samples
from sim.types import SceneChange
from sim.world import ROBOT_PREFIX, extract_obstacles, load_scene_spec, scene_bounds

# Clearance of each start from obstacles, m. Quadrotors: the connected method's
# full-weight line-of-sight clearance in the office (R'_o = 0.6 m), so the
# start graph has full weights. Ground robots: their 0.036 m radius plus the
# intermittent planner's 0.08 m path clearance, rounded up.
START_CLEARANCE_M = {"quadrotor": 0.6, "ground": 0.12}
# Robots placed one by one keep at least this distance between their starts, m.
START_SEPARATION_M = 0.6
# Redrawn targets keep this clearance from obstacles and bounds, m.
TARGET_CLEARANCE_M = 0.3
# Low-discrepancy candidates tried per redrawn target.
TARGET_CANDIDATES = 4096


class SceneGeometry:
    """Obstacle boxes and free-space bounds of one MJCF scene."""

    def __init__(self, scene_path: Path):
        model = load_scene_spec(scene_path).compile()
        data = mujoco.MjData(model)
        mujoco.mj_forward(model, data)
        self.obstacles: Boxes = extract_obstacles(model, data)
        self.bounds: np.ndarray = scene_bounds(model, self.obstacles)  # (2, 3): min, max corner, m

    @property
    def center(self) -> np.ndarray:
        return self.bounds.mean(axis=0)


def _is_connected(adjacency: np.ndarray) -> bool:
    n = len(adjacency)
    seen = np.zeros(n, dtype=bool)
    seen[0] = True
    frontier = [0]
    while frontier:
        i = frontier.pop()
        for j in np.flatnonzero(adjacency[i] & ~seen):
            seen[j] = True
            frontier.append(j)
    return bool(seen.all())


def connected_by_range(starts: np.ndarray, comm_range_m: float) -> bool:
    """The team's graph of pairs within ``comm_range_m`` is connected (walls aside)."""
    return _is_connected(np.linalg.norm(starts[:, None] - starts[None], axis=2) <= comm_range_m)


def starts_fit(geometry: SceneGeometry, kinds: list[str], starts: np.ndarray, comm_range_m: float,
               connected: bool = True, tolerance_m: float = 0.0, clearance: dict[str, float] | None = None) -> bool:
    """Every start inside the bounds and clear of obstacles and, if ``connected``,
    the team connected by links within ``comm_range_m`` whose line of sight keeps
    the same clearance (less ``tolerance_m``: starts written rounded to the mm)."""
    lo, hi = geometry.bounds
    clearance = START_CLEARANCE_M if clearance is None else clearance
    margin = np.array([clearance[k] for k in kinds]) - tolerance_m
    probe = starts.copy()
    ground = np.array([k == "ground" for k in kinds])
    probe[ground, 2] = lo[2] + margin[ground] + GROUND_PROBE_LIFT_M
    inside = np.all((probe[:, :2] >= lo[:2] + margin[:, None]) & (probe[:, :2] <= hi[:2] - margin[:, None]), axis=1)
    inside &= ground | ((probe[:, 2] >= lo[2] + margin) & (probe[:, 2] <= hi[2] - margin))
    if not inside.all() or np.any(point_clearance(geometry.obstacles, probe) < margin):
        return False
    n = len(probe)
    if n == 1 or not connected:
        return True
    i, j = np.triu_indices(n, 1)
    in_range = np.linalg.norm(probe[i] - probe[j], axis=1) <= comm_range_m
    i, j = i[in_range], j[in_range]
    adjacency = np.zeros((n, n), dtype=bool)
    if len(i):
        # Ground robots' links only need an unblocked line; quadrotors' keep the start clearance.
        needed = np.minimum(margin[i], margin[j])
        needed[ground[i] | ground[j]] = 0.0
        clear = segment_clearance(geometry.obstacles, probe[i], probe[j]).distance > needed
        adjacency[i[clear], j[clear]] = adjacency[j[clear], i[clear]] = True
    return _is_connected(adjacency)


def move_team(geometry: SceneGeometry, kinds: list[str], starts: np.ndarray, comm_range_m: float,
              connected: bool = True, clearance: dict[str, float] | None = None) -> np.ndarray | None:
    """The start pattern translated (in x and y; in z only as far as the bounds
    require) to the fitting spot nearest the scene's centre, or None."""
    lo, hi = geometry.bounds
    clearance = START_CLEARANCE_M if clearance is None else clearance
    pattern = starts.copy()
    flying = np.array([k != "ground" for k in kinds])
    if flying.any():
        margin = max(clearance[k] for k in kinds if k != "ground")
        z = pattern[flying, 2]
        shift = max(0.0, lo[2] + margin - z.min()) - max(0.0, z.max() - (hi[2] - margin))
        pattern[flying, 2] += shift
    centroid = pattern[:, :2].mean(axis=0)
    grid = candidate_grid(geometry)
    # Nearest the centre first; ties broken by position so the order is fixed.
    order = np.lexsort((grid[:, 1], grid[:, 0], np.linalg.norm(grid - geometry.center[:2], axis=1).round(9)))
    for c in grid[order]:
        moved = pattern.copy()
        moved[:, :2] += c - centroid
        if starts_fit(geometry, kinds, moved, comm_range_m, connected, clearance=clearance):
            return moved
    return None


def _rotated(starts: np.ndarray, quarter_turns: int) -> np.ndarray:
    """The pattern turned by ``quarter_turns`` x 90 degrees about its centroid (x, y only)."""
    out = starts.copy()
    centroid = starts[:, :2].mean(axis=0)
    c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][quarter_turns % 4]
    d = starts[:, :2] - centroid
    out[:, :2] = centroid + np.column_stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1]])
    return out


def pattern_spacing(starts: np.ndarray) -> float:
    """The pattern's spacing: the smallest distance between two of its starts, m."""
    distance = np.linalg.norm(starts[:, None] - starts[None], axis=2)
    np.fill_diagonal(distance, np.inf)
    return float(distance.min()) if len(starts) > 1 else 0.0


# Where the pattern's spacing does not fit, a grown team tries these fractions of it, never closer
# than the method accepts (Strategy.start_separation_m: the connected method's half way from R_c to R'_c).
GROW_SPACING_FRACTIONS = (1.0, 0.8, 0.64, 0.5)


def grow_spacings(pattern: float, least: float) -> list[float]:
    """The spacings a grown team tries, m: fractions of the pattern's, then the least accepted."""
    out = [f * pattern for f in GROW_SPACING_FRACTIONS if f * pattern >= least]
    return out + ([least] if least < pattern and least not in out else [])


def grow_team(geometry: SceneGeometry, kinds: list[str], starts: np.ndarray, comm_range_m: float,
              spacing: float | None = None, clearance: dict[str, float] | None = None) -> np.ndarray | None:
    """A connected start grown over free space where the pattern fits nowhere: from the free
    spot nearest the scene's centre, robot after robot, each at the free spot nearest that seed
    (lowest of the pattern's heights first) that is at least the pattern's spacing from every
    robot placed and links to one of them (within the spacing x 1.5 and the communication range,
    line of sight clear). Robot order: the lowest layer first, as the pattern has it. None if the
    free space holds no such team."""
    n = len(starts)
    spacing = pattern_spacing(starts) if spacing is None else spacing
    if n < 2 or spacing <= 0:
        return None
    reach = min(1.5 * spacing, comm_range_m)
    lo, hi = geometry.bounds
    clearance = START_CLEARANCE_M if clearance is None else clearance
    flying = [k for k in kinds if k != "ground"]
    margin = max(clearance[k] for k in kinds)
    if flying:
        if len(set(kinds)) > 1:
            return None  # mixed teams keep their pattern
        layers = sorted({float(np.clip(z, lo[2] + margin, hi[2] - margin)) for z in starts[:, 2]})
    else:
        layers = [lo[2] + margin + GROUND_PROBE_LIFT_M]
    step = max(0.05, spacing / 4)
    xs = np.arange(lo[0] + margin, hi[0] - margin + 1e-9, step)
    ys = np.arange(lo[1] + margin, hi[1] - margin + 1e-9, step)
    plane = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    if not len(plane):
        return None
    points = np.vstack([np.column_stack([plane, np.full(len(plane), z)]) for z in layers])
    layer = np.repeat(np.arange(len(layers)), len(plane))
    free = point_clearance(geometry.obstacles, points) >= margin
    points, layer = points[free], layer[free]
    if not len(points):
        return None
    to_centre = np.linalg.norm(points[:, :2] - geometry.center[:2], axis=1).round(9)
    seed = int(np.lexsort((points[:, 1], points[:, 0], to_centre, layer))[0])
    chosen = [seed]
    from_seed = np.linalg.norm(points[:, :2] - points[seed, :2], axis=1).round(9)
    order = np.lexsort((points[:, 1], points[:, 0], from_seed, layer))  # preference: lowest layer, near the seed
    ground = not flying
    while len(chosen) < n:
        placed = points[chosen]
        distance = np.linalg.norm(points[order, None] - placed[None], axis=2)  # (K, placed)
        apart = np.all(distance >= spacing - 1e-9, axis=1)
        near = (distance <= reach + 1e-9) & apart[:, None]
        found = None
        for k in np.flatnonzero(near.any(axis=1)):
            others = np.flatnonzero(near[k])
            ends = placed[others]
            if ground:
                clear = segment_clearance(geometry.obstacles, np.repeat(points[order[k]][None], len(ends), 0),
                                          ends).distance > 0.0
            else:
                clear = segment_clearance(geometry.obstacles, np.repeat(points[order[k]][None], len(ends), 0),
                                          ends).distance > margin
            if clear.any():
                found = int(order[k])
                break
        if found is None:
            return None
        chosen.append(found)
    team = points[chosen]
    team = team[np.lexsort((np.arange(n), team[:, 2]))]  # lowest layer first, growth order within it
    if ground:
        team[:, 2] = starts[:, 2]
    return team if starts_fit(geometry, kinds, team, comm_range_m, True, clearance=clearance) else None


def place_each(geometry: SceneGeometry, kinds: list[str], starts: np.ndarray,
               old_bounds: np.ndarray) -> np.ndarray | None:
    """A team that need not be connected, placed robot by robot: each start scaled from the old
    floor plan into the new one, then moved to the nearest free spot apart from those already placed."""
    grid = candidate_grid(geometry)
    wanted = scale_plan(starts, old_bounds, geometry.bounds)
    placed: list[np.ndarray] = []
    for kind, point in zip(kinds, wanted):
        spot = nearest_free(geometry, grid, point, START_CLEARANCE_M[kind], kind == "ground", placed,
                            START_SEPARATION_M)
        if spot is None:
            return None
        placed.append(spot)
    return np.array(placed)


def _halton(count: int, base: int) -> np.ndarray:
    """The first ``count`` points (from index 1) of the van der Corput sequence in ``base``."""
    out = np.zeros(count)
    for k in range(count):
        f, i, x = 1.0, k + 1, 0.0
        while i:
            f /= base
            x += f * (i % base)
            i //= base
        out[k] = x
    return out


def path_problem(geometry: SceneGeometry, target: dict) -> str | None:
    """Why a target's nominal path does not fit the scene, or None if it does."""
    samples = nominal_path_samples(build(TargetConfig, target, "targets"))
    lo, hi = geometry.bounds
    if np.any(samples < lo) or np.any(samples > hi):
        return "leaves the scene bounds"
    if np.any(point_clearance(geometry.obstacles, samples) < TARGET_CLEARANCE_M):
        return f"passes through or within {TARGET_CLEARANCE_M:g} m of an obstacle"
    return None


def _fits_beside(geometry: SceneGeometry, target: dict, taken: list[np.ndarray]) -> bool:
    """A redrawn path fits, keeps clear of the bounds' walls, and does not cross the others."""
    if path_problem(geometry, target) is not None:
        return False
    samples = nominal_path_samples(build(TargetConfig, target, "targets"))
    lo, hi = geometry.bounds
    if np.any(samples[:, :2] < lo[:2] + TARGET_CLEARANCE_M) or np.any(samples[:, :2] > hi[:2] - TARGET_CLEARANCE_M):
        return False
    return all(np.min(np.linalg.norm(samples[:, None] - other[None], axis=2)) > 2 * TARGET_CLEARANCE_M
               for other in taken)


def _moved_target(target: dict, anchor: np.ndarray, turn: int) -> dict:
    """``target`` with its path moved so that its first point (centre of a circle) is
    ``anchor`` (x, y), a linear path's direction turned by ``turn`` quarter turns."""
    out = copy.deepcopy(target)
    key = "center" if target["path"] == "circular" else "start"
    first = np.array(target[key], dtype=float)
    new_first = np.array([anchor[0], anchor[1], first[2]])
    out[key] = [round(float(v), 3) for v in new_first]
    if target["path"] == "linear":
        d = np.array(target["end"], dtype=float) - first
        c, s = [(1, 0), (0, 1), (-1, 0), (0, -1)][turn]
        d[:2] = [c * d[0] - s * d[1], s * d[0] + c * d[1]]
        out["end"] = [round(float(v), 3) for v in new_first + d]
    return out


def redraw_targets(geometry: SceneGeometry, targets: list[dict], scene_name: str) -> tuple[list[dict], list[str]]:
    """Targets whose path fits the scene are kept; the others are moved to the first
    fitting spot of a Halton sequence over the bounds (same shape, speed, height)."""
    lo, hi = geometry.bounds
    candidates = lo[:2] + np.stack([_halton(TARGET_CANDIDATES, 2), _halton(TARGET_CANDIDATES, 3)], axis=1) * (hi - lo)[:2]
    out, notes, taken = [], [], []
    next_candidate = 0
    for index, target in enumerate(targets):
        problem = path_problem(geometry, target)
        if problem is not None:
            placed = None
            while placed is None and next_candidate < len(candidates):
                anchor = candidates[next_candidate]
                next_candidate += 1
                turns = range(4) if target["path"] == "linear" else range(1)
                placed = next((m for m in (_moved_target(target, anchor, t) for t in turns)
                               if _fits_beside(geometry, m, taken)), None)
            if placed is None:
                raise ConfigError(f"targets.{index}", f"its {target['path']} path {problem} in {scene_name} and no "
                                  f"free place was found for it; set targets.{index} by hand (tether init writes a file to edit)")
            key = "center" if target["path"] == "circular" else "start"
            notes.append(f"targets.{index}: its {target['path']} path {problem} in {scene_name}; "
                         f"redrawn at {tuple(placed[key])} m")
            target = placed
        out.append(target)
        taken.append(nominal_path_samples(build(TargetConfig, target, "targets")))
    return out, notes


def place_in_scene(table: dict, source: str, scene: str, keep: set[str] = frozenset(),
                   unplaced_ok: bool = False) -> tuple[dict, list[str]]:
    """``table`` (a scenario's raw TOML table, overrides applied) moved into ``scene``
    (a built-in scene name or an MJCF path); returns the new table and one line per
    change. Keys in ``keep`` (those set by --set, dotted) are left as they are.
    ``unplaced_ok`` (``tether init``): a team no free place holds keeps its starts and
    a note says so, instead of a ConfigError."""
    table = copy.deepcopy(table)
    new_path = resolve_scene(scene).resolve()
    old_path = resolve_scene(table.get("scene", ""), source).resolve() if table.get("scene") else None
    table["scene"] = scene if (SCENE_DIR / f"{scene}.xml").is_file() else str(new_path)
    if new_path == old_path:
        return table, []
    scene_name = new_path.name
    geometry = SceneGeometry(new_path)
    notes: list[str] = []
    scenario: Scenario = from_table(table, source)

    # The old scene's floor plan (for scaling starts and routes); the starts' own box without one.
    starts = np.array([p for _, p in scenario.robot_starts()], dtype=float)
    old_bounds = SceneGeometry(old_path).bounds if old_path is not None and old_path.is_file() else \
        np.array([starts.min(axis=0), starts.max(axis=0)])
    # A team size (robots.N.count) or kind is the built-in's pattern resized: still placed. Starts the user
    # gave (robots.N.starts, spawn_center, spacing, or the whole table) are theirs: kept, and said so.
    explicit = sorted(k for k in keep if k == "robots" or k.startswith("robots.")
                      and k.split(".")[-1] not in ("count", "kind"))
    if explicit:
        notes.append(f"robots: your starts ({', '.join(explicit)}) kept as given; placement moves only a "
                     "built-in's starts")
    else:
        kinds = [kind for kind, _ in scenario.robot_starts()]
        comm = scenario.sensing.comm_range_m
        # A team that starts connected (the methods rely on it) must stay so; one
        # spread out on purpose (the waypoint demo) need not.
        connected = connected_by_range(starts, comm)
        method = strategy_class(scenario.strategy.kind)
        clearance = {kind: max(own, method.start_clearance_m(table.get("strategy", {}), kind))
                     for kind, own in START_CLEARANCE_M.items()}
        if not starts_fit(geometry, kinds, starts, comm, connected, clearance=clearance):
            how = "moved"
            if connected:
                moved = move_team(geometry, kinds, starts, comm, connected, clearance)
                for turns in (1, 2, 3):  # a pattern too long one way may fit turned
                    if moved is not None:
                        break
                    moved = move_team(geometry, kinds, _rotated(starts, turns), comm, connected, clearance)
                    how = f"turned {90 * turns} degrees and moved"
                spacings = [] if moved is not None else \
                    grow_spacings(pattern_spacing(starts), method.start_separation_m(table.get("strategy", {})))
                for grown_spacing in spacings:
                    moved = grow_team(geometry, kinds, starts, comm, grown_spacing, clearance)
                    how = "grown"
                    if moved is not None:
                        break
            else:
                moved = place_each(geometry, kinds, starts, old_bounds)
            if moved is None:
                needs = "clear of obstacles and connected" if connected else "clear of obstacles"
                problem = f"no free place in {scene_name} holds the team's start pattern {needs}"
                if not unplaced_ok:
                    raise ConfigError("robots", f"{problem}; set the starts of each robots entry (tether init "
                                      f"{scenario.name} --scene {scene} > my.toml writes a file to edit)")
                notes.append(f"robots: NOT placed: {problem}, turned, moved or grown; the starts below are the "
                             "built-in's and do not fit: edit them before running this file")
            if moved is not None:
                groups, k = [], 0
                for group in scenario.robots:
                    n = len(group.positions())
                    groups.append({"kind": group.kind,
                                   "starts": [[round(float(v), 3) for v in p] for p in moved[k:k + n]]})
                    k += n
                table["robots"] = groups
                centre = tuple(round(float(v), 2) for v in moved[:, :2].mean(axis=0))
                if connected and how == "grown":
                    closer = "" if grown_spacing >= pattern_spacing(starts) else \
                        f", closer than the pattern's {pattern_spacing(starts):.2f} m"
                    notes.append(f"robots: the team's start pattern fits nowhere in {scene_name}, turned or not; a "
                                 f"connected start grown over free space instead, robots {grown_spacing:.2f} m or more "
                                 f"apart{closer}, centred at {centre} m")
                elif connected:
                    notes.append(f"robots: the team's start pattern {how} to {centre} m in {scene_name}, the free spot "
                                 "nearest its centre where every robot is clear of obstacles and the team is connected")
                else:
                    notes.append(f"robots: the starts (a team spread out, not connected) scaled to {scene_name}'s floor "
                                 "plan, each moved to the nearest free spot")
                starts = moved

    # The method adapts its own coordinates (routes, prior): placement names no strategy kind.
    kinds = tuple(kind for kind, _ in scenario.robot_starts())
    change = SceneChange(
        scene_name=scene_name, obstacles=geometry.obstacles, bounds=geometry.bounds, old_bounds=old_bounds,
        robot_names=tuple(f"{ROBOT_PREFIX[kind]}{kinds[:i].count(kind)}" for i, kind in enumerate(kinds)),
        robot_kinds=kinds, starts=starts, n_targets=len(table.get("targets", ())))
    strategy_table = table.get("strategy", {})
    notes += strategy_class(scenario.strategy.kind).adapt_to_scene(strategy_table, change, frozenset(keep))
    if strategy_table:
        table["strategy"] = strategy_table

    if table.get("targets") and not any(k == "targets" or k.startswith("targets.") for k in keep):
        table["targets"], target_notes = redraw_targets(geometry, list(table["targets"]), scene_name)
        notes += target_notes
    return table, notes


def override_keys(overrides: list[str]) -> set[str]:
    """The dotted keys of ``--set key=value`` overrides."""
    return {assignment.partition("=")[0].strip() for assignment in overrides}


def load_in_scene(name_or_path: str, scene: str, overrides: list[str] = (), seed: int | None = None,
                  duration_s: float | None = None, unplaced_ok: bool = False) -> tuple[Scenario, list[str]]:
    """:func:`sim.scenario.load` with the scenario moved into ``scene``; also the
    lines that say what was moved (raises ConfigError; see :func:`place_in_scene`
    for ``unplaced_ok``)."""
    table, source = load_table(name_or_path, overrides, seed, duration_s)
    table, notes = place_in_scene(table, source, scene, override_keys(list(overrides)), unplaced_ok)
    return from_table(table, source), notes
