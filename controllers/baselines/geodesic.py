"""Geodesic (shortest obstacle-free) paths in the plane, for ground robots.

The intermittent paper's heuristic baseline (Sec. IV-B) moves the robots along "the
geodesic paths that connect the initial locations to the randomly selected
meeting location", computed there with a fast-marching toolbox [53]. Here:

1. an occupancy grid over the workspace bounds (``resolution`` m cells); a
   cell is free when its centre keeps more than ``margin`` plus half a cell
   diagonal from every obstacle box at the sensor height ``z``, so the
   straight move between two neighbouring free cells keeps ``margin``;
2. Dijkstra over the 8-connected free cells (scipy.sparse.csgraph), exact
   Euclidean step lengths, diagonal moves only when both side cells are free;
3. string pulling: from each kept waypoint jump to the farthest later one
   reachable in a straight line that keeps ``margin``
   (:func:`controllers.intermittent.planner_geometry.edges_free`, exact).

The result is the shortest path on the grid graph, shortened by straight
cuts; it is within a few per cent of the true geodesic at 5 cm cells. Pure
numpy/scipy over :class:`sim.geometry.Boxes`; no MuJoCo. Plane positions in
m, world frame.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from controllers.intermittent.planner_geometry import edges_free, lift
from sim.config import ConfigError
from sim.geometry import Boxes, point_clearance

DEFAULT_RESOLUTION_M = 0.05  # grid cell size, m
# Cells of one grid: the 50 x 70 m outdoor scenes fit at 5 cm (1.4 million, ~0.5 GB while the
# graph is built); a 1 km scene would need 400 million.
MAX_CELLS = 2_000_000


class GeodesicPlanner:
    """Shortest collision-free plane paths in one static workspace.

    boxes: obstacles; bounds: (2, 2) [[x_min, y_min], [x_max, y_max]] m; z:
    sensor/body height at which boxes are tested, m; margin: clearance kept
    from boxes and bounds, m.
    """

    def __init__(self, boxes: Boxes, bounds: np.ndarray, z: float, margin: float,
                 resolution: float = DEFAULT_RESOLUTION_M):
        if resolution <= 0 or margin < 0:
            raise ValueError("resolution must be > 0 and margin >= 0")
        self.boxes = boxes
        self.bounds = np.asarray(bounds, dtype=float)
        self.z = float(z)
        self.margin = float(margin)
        self.resolution = float(resolution)
        lo = self.bounds[0] + margin
        hi = self.bounds[1] - margin
        if np.any(hi <= lo):
            raise ValueError("bounds too small for the margin")
        self.shape = tuple(int(v) for v in np.floor((hi - lo) / resolution) + 1)  # (nx, ny)
        if math.prod(self.shape) > MAX_CELLS:  # before any array of the grid is allocated
            side = math.sqrt(MAX_CELLS) * resolution
            raise ConfigError("scene", f"the geodesic planner's grid of {resolution * 100:g} cm cells over the "
                                       f"{hi[0] - lo[0]:.0f} x {hi[1] - lo[1]:.0f} m floor plan (the scene's "
                                       f"bounds less the clearance) would have {math.prod(self.shape):,} cells, "
                                       f"at most {MAX_CELLS:,} (about {side:.0f} x {side:.0f} m): "
                                       "use a smaller scene")
        self.origin = lo + 0.5 * ((hi - lo) - (np.array(self.shape) - 1) * resolution)
        gx, gy = np.meshgrid(np.arange(self.shape[0]), np.arange(self.shape[1]), indexing="ij")
        self.cells = self.origin + resolution * np.stack([gx.ravel(), gy.ravel()], axis=1)
        need = margin + resolution * math.sqrt(2) / 2
        if len(boxes):
            clearance = point_clearance(boxes, lift(self.cells, self.z))
        else:
            clearance = np.full(len(self.cells), np.inf)
        self.free = (clearance > need).reshape(self.shape)
        self._graph = self._build_graph()

    def _index(self, ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
        return ix * self.shape[1] + iy

    def _build_graph(self):
        nx, ny = self.shape
        free = self.free
        rows, cols, weights = [], [], []
        for dx, dy in ((1, 0), (0, 1), (1, 1), (1, -1)):
            x0, x1 = max(0, -dx), nx - max(0, dx)
            y0, y1 = max(0, -dy), ny - max(0, dy)
            a = free[x0:x1, y0:y1] & free[x0 + dx : x1 + dx, y0 + dy : y1 + dy]
            if dx and dy:  # no corner cutting
                a &= free[x0 + dx : x1 + dx, y0:y1] & free[x0:x1, y0 + dy : y1 + dy]
            ix, iy = np.nonzero(a)
            ix, iy = ix + x0, iy + y0
            rows.append(self._index(ix, iy))
            cols.append(self._index(ix + dx, iy + dy))
            weights.append(np.full(len(ix), self.resolution * math.hypot(dx, dy)))
        rows, cols, weights = (np.concatenate(v) for v in (rows, cols, weights))
        n = nx * ny
        return coo_matrix((np.r_[weights, weights], (np.r_[rows, cols], np.r_[cols, rows])), shape=(n, n)).tocsr()

    def is_free(self, points: np.ndarray) -> np.ndarray:
        """(P,) bool: plane points keep ``margin`` from boxes and bounds."""
        points = np.atleast_2d(np.asarray(points, dtype=float))
        inside = np.all((points >= self.bounds[0] + self.margin) & (points <= self.bounds[1] - self.margin), axis=1)
        if len(self.boxes) == 0:
            return inside
        return inside & (point_clearance(self.boxes, lift(points, self.z)) > self.margin)

    def _nearest_free_cell(self, point: np.ndarray) -> int | None:
        """Index of the closest free cell joined to ``point`` by a straight free move."""
        free_idx = np.flatnonzero(self.free.ravel())
        if len(free_idx) == 0:
            return None
        d2 = ((self.cells[free_idx] - point) ** 2).sum(axis=1)
        order = free_idx[np.argsort(d2)[:64]]
        ok = edges_free(self.boxes, np.broadcast_to(point, (len(order), 2)), self.cells[order], self.z, self.margin)
        hits = order[ok]
        return int(hits[0]) if len(hits) else None

    def path(self, start: np.ndarray, goal: np.ndarray) -> np.ndarray | None:
        """Waypoints (K, 2), K >= 2, from ``start`` to ``goal`` (plane, m), or
        None when either is not free or they are not connected."""
        start = np.asarray(start, dtype=float)
        goal = np.asarray(goal, dtype=float)
        if not self.is_free(np.stack([start, goal])).all():
            return None
        if edges_free(self.boxes, start[None], goal[None], self.z, self.margin)[0]:
            return np.stack([start, goal])
        a, b = self._nearest_free_cell(start), self._nearest_free_cell(goal)
        if a is None or b is None:
            return None
        _, predecessors = dijkstra(self._graph, directed=False, indices=a, return_predecessors=True)
        if b != a and predecessors[b] < 0:
            return None
        chain = [b]
        while chain[-1] != a:
            chain.append(int(predecessors[chain[-1]]))
        points = np.vstack([start, self.cells[chain[::-1]], goal])
        return self._shortcut(points)

    def _shortcut(self, points: np.ndarray) -> np.ndarray:
        """String pulling: keep only waypoints needed to stay collision free."""
        kept = [points[0]]
        i, last = 0, len(points) - 1
        while i < last:
            candidates = np.arange(last, i, -1)
            ok = edges_free(self.boxes, np.broadcast_to(points[i], (len(candidates), 2)), points[candidates],
                            self.z, self.margin)
            j = int(candidates[np.argmax(ok)]) if ok.any() else i + 1
            kept.append(points[j])
            i = j
        return np.array(kept)

    def length(self, waypoints: np.ndarray) -> float:
        """Length of a waypoint polyline, m."""
        return float(np.linalg.norm(np.diff(waypoints, axis=0), axis=1).sum())


def timed_waypoints(waypoints: np.ndarray, start_step: int, u_max: float) -> tuple[np.ndarray, np.ndarray]:
    """Integer step times for a polyline driven at <= ``u_max`` m per step.

    Each leg takes ceil(length / u_max) steps (legs shorter than 1e-9 m are
    dropped). Returns (times (K,), positions (K, 2)) with strictly increasing
    times starting at ``start_step``.
    """
    waypoints = np.asarray(waypoints, dtype=float)
    times = [int(start_step)]
    points = [waypoints[0]]
    for p in waypoints[1:]:
        leg = float(np.linalg.norm(p - points[-1]))
        if leg <= 1e-9:
            continue
        times.append(times[-1] + max(1, int(math.ceil(leg / u_max - 1e-9))))
        points.append(p)
    return np.array(times, dtype=int), np.array(points)
