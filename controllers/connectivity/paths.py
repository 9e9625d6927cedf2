"""Smooth obstacle-free paths gamma_i for the travelers of Nestmeyer et al. 2017 (Sec. 3.2).

The paper builds gamma_i "with a two-step optimization method": a shortest
path on a grid of spacing R_grid (Tables 2-3), then a smoothing cubic B-spline
through it (Biagiotti and Melchiorri 2008), giving a C2 path. We do the same:

1. Grid search. Cell centres of a regular 3D grid over the scene bounds keep
   the ones whose clearance from obstacles (and from the bound faces, treated
   as walls) exceeds the margin; 26-neighbour edges are kept when the
   1-Lipschitz bound (c_a + c_b - |a - b|) / 2 on the clearance along the edge
   exceeds the margin, so every grid edge is free by construction. Dijkstra
   (scipy.sparse.csgraph) gives the shortest grid path; the robot position and
   the target are joined to their nearest free cells by straight free segments.
2. Shortcutting. Greedy string pulling over the grid path: from each kept
   vertex jump to the farthest later vertex reachable by a segment that keeps
   the margin; then each corner slides towards the chord of its neighbours as
   far as both its segments keep the margin (a few passes). This removes the
   45-degree staircase of the grid and gives an any-angle polyline within a
   few per cent of the Euclidean shortest path.
3. Smoothing. A clamped cubic B-spline (simple knots: C2) is fitted by
   penalised least squares (second differences of the control points) to dense
   samples of the polyline, with its end control points pinned to the robot
   position and the target. The smoothing weight is the largest that keeps the
   spline within ``smoothing_tolerance`` of the polyline; the margin used in
   steps 1-2 is the clearance plus this tolerance, so the spline keeps the
   requested clearance.

The spline is reparametrised by arc length s in [0, length]; ``derivatives``
gives the position, the unit tangent dp/ds and the curvature vector d2p/ds2;
``project`` the closest point q_gamma, its arc length and the distance to it.

Grid resolution. The planner uses R_grid of the preset (0.25 m office: a
10 x 10 x 5 m room is 41 x 41 x 21 cells; 0.75 m outdoor: 50 x 70 x 15 m is
67 x 94 x 21 cells), coarsened by ``planning_resolution`` when a scene would
exceed ``max_cells`` (default 400 000), so one Dijkstra query stays in the tens
of milliseconds. Free cells, edges and nearest-cell trees are built once per
margin and cached: obstacles are static.

Deviations from the paper
-------------------------
- The paper's smoothing "is not guaranteed to leave enough clearance" and
  leaves collision avoidance to f_lambda. We plan with a margin instead: first
  ``clearance`` (+ smoothing tolerance), and only if no path exists with it,
  ``min_clearance`` (+ tolerance). The first and last straight pieces, from
  the robot to its nearest free cell and from the target's, are only required
  not to cross an obstacle (the robot may already be closer than the margin).
- Grid search is followed by shortcutting and corner sliding (not mentioned in
  the paper) so the path is close to the Euclidean shortest path rather than
  the 26-connected grid one.
- The paths stay inside the scene bounds shrunk by the margin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import BSpline
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from controllers.connectivity.connected_params import ConnectedParams
from sim.geometry import Boxes, point_clearance, segments_free

# Gauss-Legendre nodes/weights on [0, 1] for arc-length integrals: 5 nodes are
# exact for polynomials of degree 9, far beyond |c'(u)| on a sub-interval.
_GL_X, _GL_W = np.polynomial.legendre.leggauss(5)
_GL_X = 0.5 * (_GL_X + 1.0)
_GL_W = 0.5 * _GL_W
# Sub-intervals per knot span for the arc-length and projection tables.
_TABLE_PER_SPAN = 8
# Newton iterations for inverse arc length and for closest-point projection.
_NEWTON_STEPS = 4
# Points per chunk when computing clearances of many grid cells (memory bound).
_CLEARANCE_CHUNK = 20_000
# Nearest free cells tried when joining the robot / target to the grid.
_SNAP_CANDIDATES = 48
# Smoothing weights tried, largest (smoothest) first; 0 is a plain least-squares fit.
_SMOOTHING_WEIGHTS = (1e3, 3e2, 1e2, 3e1, 1e1, 3.0, 1.0, 0.3, 0.1, 0.03, 0.01, 0.0)
# Halvings of the knot spacing allowed when even the least-squares fit is too far.
_KNOT_REFINEMENTS = 4
# Corner-sliding passes after string pulling, and the fractions of the way
# to the neighbours' chord tried for each corner (largest first; 0 = stay).
_TAUT_PASSES = 3
_SLIDE_FRACTIONS = np.array([1.0, 0.9, 0.8, 0.7, 0.6, 0.5, 0.4, 0.3, 0.2, 0.1, 0.05, 0.0])
# The 13 "forward" neighbour offsets of the 26-neighbourhood (the rest are mirrors).
_OFFSETS = np.array(
    [(dx, dy, dz) for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1) if (dx, dy, dz) > (0, 0, 0)]
)


class NoPathError(RuntimeError):
    """No obstacle-free path joins the two points within the scene bounds."""


def planning_resolution(lower, upper, preferred: float, max_cells: int = 400_000) -> float:
    """Grid spacing, m: ``preferred`` (R_grid), coarsened so the grid has at most ``max_cells`` cells."""
    span = np.asarray(upper, dtype=float) - np.asarray(lower, dtype=float)
    if preferred <= 0 or np.any(span < 0) or not np.any(span > 0):
        raise ValueError(f"resolution must be positive and upper >= lower (> on some axis), got {preferred!r}, "
                         f"span {span}")
    resolution = float(preferred)
    while np.prod(np.floor(span / resolution) + 1) > max_cells:
        resolution *= 1.1
    return resolution


class SplinePath:
    """A C2 path (clamped cubic B-spline) parametrised by arc length.

    waypoints: (V, 3) the polyline the spline smooths, m (for drawing/debugging).
    length: total arc length, m. A zero-length path is a single point.
    """

    def __init__(self, spline: BSpline | None, waypoints: np.ndarray) -> None:
        self.waypoints = np.asarray(waypoints, dtype=float)
        self.spline = spline
        if spline is None:
            self._point = self.waypoints[-1].copy()
            self.length = 0.0
            return
        # Piecewise-cubic Taylor coefficients per knot span, so one call yields
        # the position and both derivatives (much cheaper than BSpline calls).
        self._breaks = np.unique(spline.t)
        left, middle = self._breaks[:-1], 0.5 * (self._breaks[:-1] + self._breaks[1:])
        self._coefficients = np.stack(
            [
                spline.derivative(3)(middle) / 6.0,  # constant on each span
                spline.derivative(2)(left) / 2.0,
                spline.derivative(1)(left),
                spline(left),
            ]
        )  # (4, spans, 3), highest power first
        fractions = np.arange(_TABLE_PER_SPAN) / _TABLE_PER_SPAN
        table = (left[:, None] + np.diff(self._breaks)[:, None] * fractions).ravel()
        self._u_table = np.append(table, self._breaks[-1])
        pieces = self._arc_length_between(self._u_table[:-1], self._u_table[1:])
        self._s_table = np.concatenate([[0.0], np.cumsum(pieces)])
        self.length = float(self._s_table[-1])
        self._p_table = self._evaluate(self._u_table)[0]

    # -- construction -------------------------------------------------------

    @staticmethod
    def fit(waypoints: np.ndarray, tolerance: float, knot_spacing: float) -> "SplinePath":
        """Smoothest clamped cubic B-spline from the first to the last waypoint
        that stays within ``tolerance`` (m) of the polyline ``waypoints`` (V, 3).

        Knots are uniform in chord length with spacing about ``knot_spacing``
        (m); if no smoothing weight meets the tolerance, the knot spacing is
        halved a few times; the closest fit found is returned otherwise.
        """
        waypoints = np.asarray(waypoints, dtype=float)
        keep = np.concatenate([[True], np.linalg.norm(np.diff(waypoints, axis=0), axis=1) > 1e-9])
        waypoints = waypoints[keep]
        if len(waypoints) < 2:
            return SplinePath(None, waypoints)
        if len(waypoints) == 2:
            # A straight segment: the clamped spline with collinear, evenly spaced
            # control points is the segment itself at uniform speed.
            a, b = waypoints
            knots = np.array([0, 0, 0, 0, 1, 1, 1, 1], dtype=float) * np.linalg.norm(b - a)
            control = a + np.linspace(0.0, 1.0, 4)[:, None] * (b - a)
            return SplinePath(BSpline(knots, control, 3), waypoints)
        best, best_deviation = None, np.inf
        spacing = knot_spacing
        for _ in range(_KNOT_REFINEMENTS + 1):
            setup = _fit_setup(waypoints, spacing)  # what does not depend on the weight, once per spacing
            for weight in _SMOOTHING_WEIGHTS:
                spline = _penalised_fit(waypoints, spacing, weight, setup)
                deviation = _max_distance_to_polyline(spline, waypoints, spacing)
                if deviation < best_deviation:
                    best, best_deviation = spline, deviation
                if deviation <= tolerance:
                    return SplinePath(spline, waypoints)
            spacing *= 0.5
        return SplinePath(best, waypoints)

    # -- evaluation ---------------------------------------------------------

    @property
    def start(self) -> np.ndarray:
        return self.point(np.array([0.0]))[0]

    @property
    def end(self) -> np.ndarray:
        return self.point(np.array([self.length]))[0]

    def _evaluate(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """c(u), c'(u), c''(u), each (..., 3), at spline parameters u (...)."""
        u = np.minimum(np.maximum(u, self._breaks[0]), self._breaks[-1])
        span = np.minimum(np.searchsorted(self._breaks, u, side="right") - 1, len(self._breaks) - 2)
        a, b, c, d = (coefficient[span] for coefficient in self._coefficients)
        x = (u - self._breaks[span])[..., None]
        position = ((a * x + b) * x + c) * x + d
        first = (3.0 * a * x + 2.0 * b) * x + c
        second = 6.0 * a * x + 2.0 * b
        return position, first, second

    def _speed(self, u: np.ndarray) -> np.ndarray:
        return np.linalg.norm(self._evaluate(u)[1], axis=-1)

    def _arc_length_between(self, u0: np.ndarray, u1: np.ndarray) -> np.ndarray:
        nodes = u0[:, None] + (u1 - u0)[:, None] * _GL_X
        return (u1 - u0) * (self._speed(nodes) @ _GL_W)

    def parameter(self, s) -> np.ndarray:
        """Spline parameter u (P,) at arc lengths s (P,), clipped to [0, length]."""
        s = np.clip(np.atleast_1d(np.asarray(s, dtype=float)), 0.0, self.length)
        if self.spline is None:
            return np.zeros_like(s)
        k = np.clip(np.searchsorted(self._s_table, s, side="right") - 1, 0, len(self._s_table) - 2)
        u0, s0 = self._u_table[k], self._s_table[k]
        u1, s1 = self._u_table[k + 1], self._s_table[k + 1]
        u = u0 + (u1 - u0) * np.where(s1 > s0, (s - s0) / np.where(s1 > s0, s1 - s0, 1.0), 0.0)
        for _ in range(_NEWTON_STEPS):
            residual = s0 + self._arc_length_between(u0, u) - s
            u = np.clip(u - residual / np.maximum(self._speed(u), 1e-12), u0, u1)
        return u

    def arc_length(self, u) -> np.ndarray:
        """Arc length s (P,) at spline parameters u (P,)."""
        if self.spline is None:
            return np.zeros(np.size(u))
        u = np.clip(np.atleast_1d(np.asarray(u, dtype=float)), self._u_table[0], self._u_table[-1])
        k = np.clip(np.searchsorted(self._u_table, u, side="right") - 1, 0, len(self._u_table) - 2)
        return self._s_table[k] + self._arc_length_between(self._u_table[k], u)

    def point(self, s) -> np.ndarray:
        """Positions (P, 3), m, at arc lengths s (P,)."""
        s = np.atleast_1d(np.asarray(s, dtype=float))
        if self.spline is None:
            return np.broadcast_to(self._point, (len(s), 3)).copy()
        return self._evaluate(self.parameter(s))[0]

    def derivatives(self, s) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position (P, 3), unit tangent dp/ds (P, 3) and curvature vector
        d2p/ds2 (P, 3), 1/m, at arc lengths s (P,). Zero tangent on a zero-length path."""
        s = np.atleast_1d(np.asarray(s, dtype=float))
        if self.spline is None:
            zeros = np.zeros((len(s), 3))
            return self.point(s), zeros, zeros.copy()
        return self.derivatives_at_parameter(self.parameter(s))

    def derivatives_at_parameter(self, u) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """As ``derivatives`` but at spline parameters u (P,), e.g. from ``project``."""
        position, d1, d2 = self._evaluate(np.atleast_1d(np.asarray(u, dtype=float)))
        speed = np.linalg.norm(d1, axis=-1, keepdims=True)
        tangent = d1 / speed
        # d2p/ds2 = (c'' - (c''.t) t) / |c'|^2: the part of c'' normal to the path.
        curvature = (d2 - np.sum(d2 * tangent, axis=-1, keepdims=True) * tangent) / speed**2
        return position, tangent, curvature

    def project(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest path points to ``points`` (P, 3): arc lengths (P,), points
        q_gamma (P, 3) and distances ||q - q_gamma|| (P,), m."""
        points = np.atleast_2d(np.asarray(points, dtype=float))
        if self.spline is None:
            closest = self.point(np.zeros(len(points)))
            return np.zeros(len(points)), closest, np.linalg.norm(points - closest, axis=1)
        u = self.project_parameter(points)
        closest = self._evaluate(u)[0]
        return self.arc_length(u), closest, np.linalg.norm(points - closest, axis=1)

    def closest_frame(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``project`` and ``derivatives`` at once: arc lengths (P,), closest points
        (P, 3), unit tangents (P, 3), curvature vectors (P, 3), distances (P,)."""
        points = np.atleast_2d(np.asarray(points, dtype=float))
        if self.spline is None:
            arc, closest, distance = self.project(points)
            _, tangent, curvature = self.derivatives(arc)
            return arc, closest, tangent, curvature, distance
        u = self.project_parameter(points)
        closest, tangent, curvature = self.derivatives_at_parameter(u)
        return self.arc_length(u), closest, tangent, curvature, np.linalg.norm(points - closest, axis=1)

    def project_parameter(self, points) -> np.ndarray:
        """Spline parameter u (P,) of the closest path point to each of ``points`` (P, 3)."""
        points = np.atleast_2d(np.asarray(points, dtype=float))
        if self.spline is None:
            return np.zeros(len(points))
        sq = np.sum((points[:, None, :] - self._p_table[None]) ** 2, axis=-1)
        k = np.argmin(sq, axis=1)
        lo = self._u_table[np.maximum(k - 1, 0)]
        hi = self._u_table[np.minimum(k + 1, len(self._u_table) - 1)]
        u = self._u_table[k]
        # Newton on g(u) = c'(u).(c(u) - q), kept inside the bracket of the nearest table node.
        for _ in range(_NEWTON_STEPS):
            position, d1, d2 = self._evaluate(u)
            diff = position - points
            gradient = np.sum(d1 * diff, axis=1)
            hessian = np.sum(d2 * diff, axis=1) + np.sum(d1 * d1, axis=1)
            step = np.where(hessian > 1e-12, gradient / np.where(hessian > 1e-12, hessian, 1.0), 0.0)
            u = np.clip(u - step, lo, hi)
        return u

    def sample(self, spacing: float) -> np.ndarray:
        """Points (M, 3) every ``spacing`` metres of arc length, both ends included."""
        if self.length == 0.0:
            return self.point(np.zeros(1))
        count = max(2, int(np.ceil(self.length / spacing)) + 1)
        return self.point(np.linspace(0.0, self.length, count))


def _fit_setup(waypoints: np.ndarray, knot_spacing: float) -> tuple:
    """The parts of ``_penalised_fit`` that do not depend on the weight: knots, the design matrix and
    the normal equations' data terms (computed as the fit does, so a refit reproduces it exactly)."""
    chord = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(waypoints, axis=0), axis=1))])
    total = chord[-1]
    spans = max(1, int(np.ceil(total / knot_spacing)))
    breaks = np.linspace(0.0, total, spans + 1)
    knots = np.concatenate([[0.0] * 3, breaks, [total] * 3])
    n_control = spans + 3
    # Samples: every polyline vertex plus about four points per knot span.
    u_samples = np.unique(np.concatenate([chord, np.linspace(0.0, total, 4 * spans + 1)]))
    x_samples = np.stack([np.interp(u_samples, chord, waypoints[:, d]) for d in range(3)], axis=1)
    basis = BSpline.design_matrix(u_samples, knots, 3).toarray()
    difference = np.diff(np.eye(n_control), n=2, axis=0)
    fixed = np.array([0, n_control - 1])
    free = np.arange(1, n_control - 1)
    control = np.zeros((n_control, 3))
    control[0], control[-1] = waypoints[0], waypoints[-1]
    d_free = normal = data = pinned = None
    if len(free):
        b_free, b_fixed = basis[:, free], basis[:, fixed]
        d_free, d_fixed = difference[:, free], difference[:, fixed]
        normal = b_free.T @ b_free
        data = b_free.T @ (x_samples - b_fixed @ control[fixed])
        pinned = d_fixed @ control[fixed]
    return knots, n_control, len(u_samples), free, control, d_free, normal, data, pinned


def _penalised_fit(waypoints: np.ndarray, knot_spacing: float, weight: float, setup: tuple | None = None) -> BSpline:
    """Clamped cubic B-spline, ends pinned to the first/last waypoint, fitted to
    dense polyline samples with a second-difference penalty of relative ``weight``
    (``setup``: ``_fit_setup`` of the same waypoints and spacing, when the caller has it)."""
    knots, n_control, n_samples, free, control, d_free, normal, data, pinned = (
        _fit_setup(waypoints, knot_spacing) if setup is None else setup)
    # Penalty relative to the number of samples per control point, so the
    # weight means the same thing for short and long paths.
    penalty = weight * n_samples / n_control
    control = control.copy()
    if len(free):
        lhs = normal + penalty * d_free.T @ d_free
        rhs = data - penalty * d_free.T @ pinned
        # A tiny ridge keeps the normal equations regular when a span holds no sample.
        control[free] = np.linalg.solve(lhs + 1e-12 * np.eye(len(free)), rhs)
    return BSpline(knots.copy(), control, 3)


def _max_distance_to_polyline(spline: BSpline, waypoints: np.ndarray, knot_spacing: float) -> float:
    """Largest distance from dense spline samples to the polyline, m."""
    u = np.linspace(spline.t[0], spline.t[-1], 8 * int(np.ceil((spline.t[-1] - spline.t[0]) / knot_spacing)) + 2)
    points = spline(u)
    a, b = waypoints[:-1], waypoints[1:]
    ab = b - a
    t = np.clip(
        np.einsum("pkd,kd->pk", points[:, None, :] - a[None], ab) / np.maximum(np.sum(ab * ab, axis=1), 1e-18),
        0.0,
        1.0,
    )
    nearest = a[None] + t[..., None] * ab[None]
    return float(np.linalg.norm(points[:, None, :] - nearest, axis=-1).min(axis=1).max())


def _densify(polyline: np.ndarray, spacing: float) -> np.ndarray:
    """The polyline with extra vertices so no segment is longer than ``spacing``."""
    pieces = [polyline[:1]]
    for a, b in zip(polyline[:-1], polyline[1:]):
        count = max(1, int(np.ceil(np.linalg.norm(b - a) / spacing)))
        pieces.append(a + np.linspace(0.0, 1.0, count + 1)[1:, None] * (b - a))
    return np.concatenate(pieces)


@dataclass
class _MarginGraph:
    """Free cells and grid edges keeping a given margin; built once per margin."""

    margin: float
    node_cells: np.ndarray  # (F,) flat cell index of each graph node
    positions: np.ndarray  # (F, 3) node positions, m
    graph: csr_matrix  # (F, F) edge lengths, m
    components: np.ndarray  # (F,) connected-component label
    tree: cKDTree


class GridPlanner:
    """Shortest smooth obstacle-free paths in a static box scene (see module docstring).

    boxes: static obstacles; lower, upper: (3,) scene bounds, m (axis-aligned,
    world frame); resolution: grid spacing R_grid, m; clearance: preferred
    distance of the path from obstacles and bound faces, m; min_clearance:
    fallback distance for narrow passages, m; smoothing_tolerance: how far the
    spline may round corners of the grid path, m.

    Planar scenes (ground robots): ``lower`` and ``upper`` may coincide on an
    axis; the grid is then one layer at that coordinate, paths stay in it,
    and that axis's bound faces are not walls (``planar_axes``).
    """

    def __init__(
        self,
        boxes: Boxes,
        lower,
        upper,
        resolution: float,
        clearance: float,
        min_clearance: float | None = None,
        smoothing_tolerance: float = 0.0,
        max_cells: int = 400_000,
    ) -> None:
        self.boxes = boxes
        self.lower = np.asarray(lower, dtype=float).reshape(3)
        self.upper = np.asarray(upper, dtype=float).reshape(3)
        if np.any(self.upper < self.lower) or np.all(self.upper == self.lower):
            raise ValueError(f"upper {self.upper} must not be below lower {self.lower} and exceed it on some axis")
        # Axes with lower == upper: a planar grid, whose bound faces on that axis are not walls.
        self.planar_axes = np.flatnonzero(self.upper == self.lower)
        self._bounded_axes = np.flatnonzero(self.upper > self.lower)
        min_clearance = clearance if min_clearance is None else min_clearance
        if not 0 <= min_clearance <= clearance:
            raise ValueError(f"min_clearance ({min_clearance}) must lie in [0, clearance ({clearance})]")
        if smoothing_tolerance < 0:
            raise ValueError(f"smoothing_tolerance must be non-negative, got {smoothing_tolerance!r}")
        self.preferred_resolution = float(resolution)
        self.max_cells = int(max_cells)
        self.resolution = planning_resolution(self.lower, self.upper, resolution, max_cells)
        self.clearance = float(clearance)
        self.min_clearance = float(min_clearance)
        self.smoothing_tolerance = float(smoothing_tolerance)
        # Margins tried in order: preferred, then fallback, each inflated by the
        # smoothing tolerance so the spline keeps the un-inflated clearance.
        self.margins = tuple(dict.fromkeys(m + self.smoothing_tolerance for m in (self.clearance, self.min_clearance)))
        span = self.upper - self.lower
        self.shape = tuple(int(n) for n in np.floor(span / self.resolution) + 1)
        offset = (span - (np.array(self.shape) - 1) * self.resolution) / 2.0
        axes = [self.lower[d] + offset[d] + self.resolution * np.arange(self.shape[d]) for d in range(3)]
        self.cell_positions = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
        self.cell_clearance = self.clearance_of(self.cell_positions)
        self._graphs: dict[float, _MarginGraph] = {}

    @classmethod
    def from_params(cls, boxes: Boxes, lower, upper, params: ConnectedParams) -> "GridPlanner":
        """Planner with R_grid, clearances and smoothing tolerance of ``params``."""
        return cls(
            boxes,
            lower,
            upper,
            params.grid_resolution_m,
            params.path_clearance_m,
            params.path_min_clearance_m,
            params.smoothing_tolerance_m,
        )

    @property
    def coarsened(self) -> bool:
        """Whether the cell cap made the grid coarser than the resolution asked for."""
        return self.resolution > self.preferred_resolution * (1 + 1e-9)

    def coarsening(self) -> str:
        """The cell cap's effect, for messages: what a failure on a coarsened grid really comes from."""
        span = " x ".join(f"{v:g}" for v in self.upper - self.lower)
        return (f"the connectivity planner's grid is coarsened from {self.preferred_resolution:g} m to "
                f"{self.resolution:.2g} m cells over the {span} m bounds (at most {self.max_cells:,} cells)")

    # -- geometry queries ---------------------------------------------------

    def bounds_clearance(self, points) -> np.ndarray:
        """Distance (P,) from each point to the nearest bound face (negative outside), m."""
        points = np.atleast_2d(points)
        axes = self._bounded_axes
        return np.minimum(points[:, axes] - self.lower[axes], self.upper[axes] - points[:, axes]).min(axis=1)

    def clearance_of(self, points) -> np.ndarray:
        """Distance (P,) to the nearest obstacle or bound face, m."""
        points = np.atleast_2d(np.asarray(points, dtype=float))
        chunks = range(0, len(points), _CLEARANCE_CHUNK)
        obstacle = np.concatenate(
            [np.zeros(0)] + [point_clearance(self.boxes, points[i : i + _CLEARANCE_CHUNK]) for i in chunks]
        )
        return np.minimum(obstacle, self.bounds_clearance(points))

    def is_free(self, points, margin: float | None = None) -> np.ndarray:
        """Boolean (P,): farther than ``margin`` (default min_clearance) from obstacles and bound faces."""
        margin = self.min_clearance if margin is None else margin
        return self.clearance_of(points) > margin

    def connected(self, a, b) -> bool:
        """Whether a path joins a and b (3,) at the fallback margin."""
        graph = self._graph(self.margins[-1])
        nodes = self._snap(graph, np.stack([np.asarray(a, float), np.asarray(b, float)]))
        return bool(np.all(nodes >= 0) and graph.components[nodes[0]] == graph.components[nodes[1]])

    def connected_to(self, a, points) -> np.ndarray:
        """Boolean (P,): ``connected(a, point)`` for each of ``points`` (P, 3), with ``a`` snapped once and
        the points whose snap candidates all lie outside ``a``'s component skipped (the snap picks one of
        them): the same answers, without a segment test per point in a scene where few are reachable."""
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        result = np.zeros(len(points), dtype=bool)
        graph = self._graph(self.margins[-1])
        start = self._snap(graph, np.asarray(a, dtype=float).reshape(1, 3))[0]
        if start < 0 or not len(points):
            return result
        k = min(_SNAP_CANDIDATES, len(graph.positions))
        _, candidates = graph.tree.query(points, k=k)
        component = graph.components[start]
        hopeful = np.flatnonzero(np.any(graph.components[np.asarray(candidates).reshape(len(points), k)] == component,
                                        axis=1))
        nodes = self._snap(graph, points[hopeful])
        result[hopeful] = (nodes >= 0) & (graph.components[nodes] == component)
        return result

    # -- planning -----------------------------------------------------------

    def plan(self, start, goal) -> SplinePath:
        """C2 path from ``start`` to ``goal`` (3,), m. Raises NoPathError."""
        start = np.asarray(start, dtype=float).reshape(3)
        goal = np.asarray(goal, dtype=float).reshape(3)
        for margin in self.margins:
            polyline = self._polyline(start, goal, margin)
            if polyline is None:
                continue
            knot_spacing = max(self.smoothing_tolerance, 0.5 * self.resolution)
            return SplinePath.fit(polyline, self.smoothing_tolerance, knot_spacing)
        raise NoPathError(f"no path from {start} to {goal} keeping {self.min_clearance} m from obstacles")

    def _polyline(self, start: np.ndarray, goal: np.ndarray, margin: float) -> np.ndarray | None:
        ends = np.stack([start, goal])
        if np.all(self.bounds_clearance(ends) > margin) and segments_free(self.boxes, start, goal, margin)[0]:
            return ends
        graph = self._graph(margin)
        nodes = self._snap(graph, ends)
        if np.any(nodes < 0) or graph.components[nodes[0]] != graph.components[nodes[1]]:
            return None
        _, predecessors = dijkstra(graph.graph, directed=True, indices=nodes[0], return_predecessors=True)
        chain = [nodes[1]]
        while chain[-1] != nodes[0]:
            chain.append(predecessors[chain[-1]])
        cells = graph.positions[np.array(chain[::-1])]
        polyline = self._shortcut(np.concatenate([start[None], cells, goal[None]]), margin)
        # Re-densify and pull again, then let the corners slide off the grid
        # cells towards the obstacles' margin: closer to the taut string.
        polyline = self._shortcut(_densify(polyline, self.resolution), margin)
        for _ in range(_TAUT_PASSES):
            polyline = self._shortcut(self._tighten(polyline, margin), margin)
        return polyline

    def _tighten(self, polyline: np.ndarray, margin: float) -> np.ndarray:
        """Move each interior vertex as far towards the chord of its neighbours as
        both adjacent segments stay free with the margin."""
        polyline = polyline.copy()
        fractions = _SLIDE_FRACTIONS[:, None]
        for i in range(1, len(polyline) - 1):
            a, vertex, b = polyline[i - 1], polyline[i], polyline[i + 1]
            chord = b - a
            along = np.clip(np.dot(vertex - a, chord) / max(np.dot(chord, chord), 1e-18), 0.0, 1.0)
            moved = vertex + fractions * (a + along * chord - vertex)
            inside = self.bounds_clearance(moved) > margin
            free = inside & segments_free(self.boxes, np.repeat(a[None], len(moved), 0), moved, margin)
            free &= segments_free(self.boxes, moved, np.repeat(b[None], len(moved), 0), margin)
            if np.any(free):
                polyline[i] = moved[np.argmax(free)]  # fractions are sorted, largest first
        return polyline

    def _shortcut(self, polyline: np.ndarray, margin: float) -> np.ndarray:
        """Greedy string pulling: keep the farthest vertex visible with the margin."""
        inside = self.bounds_clearance(polyline) > margin
        kept = [0]
        i = 0
        while i < len(polyline) - 1:
            later = np.arange(i + 1, len(polyline))
            visible = inside[later] & inside[i]
            if np.any(visible):
                visible[visible] = segments_free(
                    self.boxes, np.repeat(polyline[i][None], visible.sum(), axis=0), polyline[later[visible]], margin
                )
            i = int(later[visible].max()) if np.any(visible) else i + 1
            kept.append(i)
        return polyline[kept]

    def _snap(self, graph: _MarginGraph, points: np.ndarray) -> np.ndarray:
        """Nearest graph node joined to each point by an obstacle-free segment; -1 if none."""
        result = np.full(len(points), -1)
        if len(graph.positions) == 0:
            return result
        k = min(_SNAP_CANDIDATES, len(graph.positions))
        _, candidates = graph.tree.query(points, k=k)
        candidates = np.asarray(candidates).reshape(len(points), k)
        for p, point in enumerate(points):
            free = segments_free(self.boxes, np.repeat(point[None], k, axis=0), graph.positions[candidates[p]], 0.0)
            if np.any(free):
                result[p] = candidates[p][np.argmax(free)]
        return result

    def _graph(self, margin: float) -> _MarginGraph:
        if margin in self._graphs:
            return self._graphs[margin]
        shape = np.array(self.shape)
        clearance = self.cell_clearance.reshape(self.shape)
        free = clearance > margin
        node_of_cell = np.full(free.size, -1)
        node_cells = np.flatnonzero(free)
        node_of_cell[node_cells] = np.arange(len(node_cells))
        node_of_cell = node_of_cell.reshape(self.shape)
        rows, cols, lengths = [], [], []
        for offset in _OFFSETS:
            a = tuple(slice(max(0, -o), n - max(0, o)) for o, n in zip(offset, shape))
            b = tuple(slice(max(0, o), n - max(0, -o)) for o, n in zip(offset, shape))
            length = self.resolution * float(np.linalg.norm(offset))
            # Clearance along the edge is at least (c_a + c_b - length) / 2.
            keep = free[a] & free[b] & ((clearance[a] + clearance[b] - length) / 2.0 > margin)
            rows.append(node_of_cell[a][keep])
            cols.append(node_of_cell[b][keep])
            lengths.append(np.full(int(keep.sum()), length))
        rows, cols, lengths = np.concatenate(rows), np.concatenate(cols), np.concatenate(lengths)
        n = len(node_cells)
        graph = csr_matrix(
            (np.concatenate([lengths, lengths]), (np.concatenate([rows, cols]), np.concatenate([cols, rows]))),
            shape=(n, n),
        )
        _, components = connected_components(graph, directed=False)
        positions = self.cell_positions[node_cells]
        tree = cKDTree(positions if n else np.zeros((1, 3)))  # a dummy point keeps an empty graph queryable
        built = _MarginGraph(margin, node_cells, positions, graph, components, tree)
        self._graphs[margin] = built
        return built
