"""Closest-point frames on several paths at once (one compiled pass for all travelers).

:meth:`SplinePath.closest_frame` answers for one path; a team has up to one
path per robot and asks every control tick, so the per-call overhead of
numpy dominates. :class:`PathBatch` stacks the piecewise-cubic tables of R
paths (built once per set of paths) and projects robot r onto path r for all
r in one compiled loop, with the same algorithm and the same numbers as
``SplinePath.closest_frame`` (nearest table node, then Newton on
c'(u).(c(u) - q) inside that node's bracket, arc length by Gauss-Legendre).

Parameters of path r are shifted into a global parameter axis (path r
occupies [start_r, end_r] + shift_r, with a gap between paths), so a single
``searchsorted`` finds every robot's knot span; each robot's lookups are then
clamped to its own path's spans.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from controllers.connectivity import paths as _paths
from controllers.connectivity.paths import SplinePath
from sim.compiled import kernel

_GAP = 1.0  # global-parameter gap between two paths


class PathBatch:
    """R paths (each with a spline, i.e. of positive length) evaluated together."""

    def __init__(self, paths: Sequence[SplinePath]):
        if any(p.spline is None for p in paths):
            raise ValueError("PathBatch needs paths of positive length (SplinePath with a spline)")
        self.paths = tuple(paths)
        r = len(paths)
        self.lengths = np.array([p.length for p in paths])
        shifts, breaks, coefficients, first_span, last_span = [], [], [], [], []
        u_tables, s_tables, p_tables = [], [], []
        offset = 0.0
        position = 0
        for path in paths:
            shift = offset - path._breaks[0]
            shifts.append(shift)
            b = path._breaks + shift
            breaks.append(b)
            # One coefficient row per break; the last break of a path gets a dummy row.
            coefficients.append(np.concatenate([path._coefficients, np.zeros((4, 1, 3))], axis=1))
            first_span.append(position)
            last_span.append(position + len(b) - 2)
            position += len(b)
            offset = b[-1] + _GAP
            u_tables.append(path._u_table + shift)
            s_tables.append(path._s_table)
            p_tables.append(path._p_table)
        self.shifts = np.array(shifts)
        self.breaks = np.concatenate(breaks)
        self.coefficients = np.concatenate(coefficients, axis=1)
        self.first_span = np.array(first_span)
        self.last_span = np.array(last_span)
        # Arc-length tables, concatenated (global u increasing) and padded per path.
        sizes = np.array([len(t) for t in u_tables])
        self.table_start = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(int)
        self.table_size = sizes
        self.u_table = np.concatenate(u_tables)
        self.s_table = np.concatenate(s_tables)
        width = int(sizes.max()) if r else 0
        self.p_padded = np.full((r, width, 3), np.inf)
        for k, table in enumerate(p_tables):
            self.p_padded[k, : len(table)] = table

    def __len__(self) -> int:
        return len(self.paths)

    def closest_frame(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Robot r at ``points[r]`` (R, 3) projected on path r: arc lengths (R,),
        closest points (R, 3), unit tangents (R, 3), curvature vectors (R, 3),
        distances (R,) - as ``SplinePath.closest_frame`` row by row."""
        points = np.ascontiguousarray(points, dtype=float).reshape(len(self), 3)
        r = len(self)
        arc_base, arc_span, distance = np.empty(r), np.empty(r), np.empty(r)
        node_speed = np.empty((r, len(_paths._GL_X)))
        closest, tangent, curvature = np.empty((r, 3)), np.empty((r, 3)), np.empty((r, 3))
        _closest_frame_kernel(points, self.breaks, self.coefficients, self.first_span, self.last_span,
                              self.table_start, self.table_size, self.u_table, self.s_table, self.p_padded,
                              _paths._NEWTON_STEPS, _paths._GL_X, arc_base, arc_span, node_speed,
                              closest, tangent, curvature, distance)
        # Gauss-Legendre sum with numpy's matmul, the summation of SplinePath.arc_length, so both give equal lengths.
        arc = arc_base + arc_span * (node_speed @ _paths._GL_W)
        return arc, closest, tangent, curvature, distance


@kernel
def _evaluate(breaks, coefficients, first_span, last_span, u, out_position, out_first, out_second):
    """Position, c', c'' (3,) of the path owning spans [first_span, last_span] at global parameter u."""
    span = np.searchsorted(breaks, u, side="right") - 1
    span = min(max(span, first_span), last_span)
    x = u - breaks[span]
    for i in range(3):
        a, b, c, d = coefficients[0, span, i], coefficients[1, span, i], coefficients[2, span, i], coefficients[3, span, i]
        out_position[i] = ((a * x + b) * x + c) * x + d
        out_first[i] = (3.0 * a * x + 2.0 * b) * x + c
        out_second[i] = 6.0 * a * x + 2.0 * b


@kernel
def _closest_frame_kernel(points, breaks, coefficients, first_span, last_span, table_start, table_size, u_table,
                          s_table, p_padded, newton_steps, gl_x, arc_base_out, arc_span_out, node_speed_out,
                          closest_out, tangent_out, curvature_out, distance_out):
    """SplinePath.project_parameter / derivatives_at_parameter / arc_length, robot r on path r."""
    position, d1, d2 = np.empty(3), np.empty(3), np.empty(3)
    for r in range(points.shape[0]):
        q = points[r]
        # Nearest table node of the robot's own path, then Newton on c'(u).(c(u) - q) inside its bracket.
        nearest, nearest_sq = 0, np.inf
        for k in range(table_size[r]):
            sq = 0.0
            for i in range(3):
                gap = p_padded[r, k, i] - q[i]
                sq += gap * gap
            if sq < nearest_sq:
                nearest, nearest_sq = k, sq
        base, last = table_start[r], table_size[r] - 1
        lo = u_table[base + max(nearest - 1, 0)]
        hi = u_table[base + min(nearest + 1, last)]
        u = u_table[base + nearest]
        for _ in range(newton_steps):
            _evaluate(breaks, coefficients, first_span[r], last_span[r], u, position, d1, d2)
            gradient, curvature_term, speed_sq = 0.0, 0.0, 0.0
            for i in range(3):
                diff = position[i] - q[i]
                gradient += d1[i] * diff
                curvature_term += d2[i] * diff
                speed_sq += d1[i] * d1[i]
            hessian = curvature_term + speed_sq
            step = gradient / hessian if hessian > 1e-12 else 0.0
            u = min(max(u - step, lo), hi)
        _evaluate(breaks, coefficients, first_span[r], last_span[r], u, position, d1, d2)
        speed = np.sqrt(d1[0] * d1[0] + d1[1] * d1[1] + d1[2] * d1[2])
        along = 0.0
        for i in range(3):
            tangent_out[r, i] = d1[i] / speed
            along += d2[i] * tangent_out[r, i]
        distance_sq = 0.0
        for i in range(3):
            curvature_out[r, i] = (d2[i] - along * tangent_out[r, i]) / speed**2
            closest_out[r, i] = position[i]
            gap = q[i] - position[i]
            distance_sq += gap * gap
        distance_out[r] = np.sqrt(distance_sq)
        # Arc length of u: table node below it plus a Gauss-Legendre integral of the speed
        # (the speeds at the nodes; the weighted sum is the caller's).
        node = np.searchsorted(u_table, u, side="right") - 1
        node = min(max(node, base), base + last - 1)
        u0 = u_table[node]
        for g in range(gl_x.shape[0]):
            _evaluate(breaks, coefficients, first_span[r], last_span[r], u0 + (u - u0) * gl_x[g], position, d1, d2)
            node_speed_out[r, g] = np.sqrt(d1[0] * d1[0] + d1[1] * d1[1] + d1[2] * d1[2])
        arc_base_out[r] = s_table[node]
        arc_span_out[r] = u - u0
