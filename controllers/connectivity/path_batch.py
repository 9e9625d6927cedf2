"""Closest-point frames on several paths at once (one numpy pass for all travelers).

:meth:`SplinePath.closest_frame` answers for one path; a team has up to one
path per robot and asks every control tick, so the per-call overhead of
numpy dominates. :class:`PathBatch` stacks the piecewise-cubic tables of R
paths (built once per set of paths) and projects robot r onto path r for all
r in one pass, with the same algorithm and the same numbers as
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

    def _evaluate(self, u: np.ndarray, owner: np.ndarray):
        """Position, c', c'' (..., 3) at global parameters u (...) of paths ``owner`` (...)."""
        span = np.searchsorted(self.breaks, u, side="right") - 1
        span = np.clip(span, self.first_span[owner], self.last_span[owner])
        a, b, c, d = (coefficient[span] for coefficient in self.coefficients)
        x = (u - self.breaks[span])[..., None]
        position = ((a * x + b) * x + c) * x + d
        first = (3.0 * a * x + 2.0 * b) * x + c
        second = 6.0 * a * x + 2.0 * b
        return position, first, second

    def closest_frame(self, points) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Robot r at ``points[r]`` (R, 3) projected on path r: arc lengths (R,),
        closest points (R, 3), unit tangents (R, 3), curvature vectors (R, 3),
        distances (R,) - as ``SplinePath.closest_frame`` row by row."""
        points = np.asarray(points, dtype=float).reshape(len(self), 3)
        owner = np.arange(len(self))
        # Nearest table node of each robot's own path.
        sq = np.sum((self.p_padded - points[:, None, :]) ** 2, axis=-1)
        k = np.argmin(sq, axis=1)
        base = self.table_start
        last = self.table_size - 1
        lo = self.u_table[base + np.maximum(k - 1, 0)]
        hi = self.u_table[base + np.minimum(k + 1, last)]
        u = self.u_table[base + k]
        for _ in range(_paths._NEWTON_STEPS):
            position, d1, d2 = self._evaluate(u, owner)
            diff = position - points
            gradient = np.sum(d1 * diff, axis=1)
            hessian = np.sum(d2 * diff, axis=1) + np.sum(d1 * d1, axis=1)
            step = np.where(hessian > 1e-12, gradient / np.where(hessian > 1e-12, hessian, 1.0), 0.0)
            u = np.clip(u - step, lo, hi)
        closest, d1, d2 = self._evaluate(u, owner)
        speed = np.linalg.norm(d1, axis=-1, keepdims=True)
        tangent = d1 / speed
        curvature = (d2 - np.sum(d2 * tangent, axis=-1, keepdims=True) * tangent) / speed**2
        # Arc length of u: table node below it plus a Gauss-Legendre integral.
        node = np.searchsorted(self.u_table, u, side="right") - 1
        node = np.clip(node, base, base + last - 1)
        u0 = self.u_table[node]
        nodes = u0[:, None] + (u - u0)[:, None] * _paths._GL_X
        node_speed = np.linalg.norm(self._evaluate(nodes, owner[:, None])[1], axis=-1)
        arc = self.s_table[node] + (u - u0) * (node_speed @ _paths._GL_W)
        return arc, closest, tangent, curvature, np.linalg.norm(points - closest, axis=1)
