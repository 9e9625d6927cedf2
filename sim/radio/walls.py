"""Walls a radio link crosses: segment against oriented obstacle boxes, exact and batched.

Each static obstacle box (``sim.geometry.Boxes``, the scene's group-0 geoms)
that a segment passes through counts once, however thick it is; a segment
that ends inside a box, or only touches one, crosses it. The test is the slab
test in each box's own frame: the segment's parameter intervals inside the
three slabs overlap within [0, 1]. Pure math, no MuJoCo.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sim.compiled import kernel
from sim.geometry import Boxes


@dataclass(frozen=True)
class WallCrossings:
    """Per segment: the obstacle boxes crossed and the loss they add (COST 231 multi-wall: losses sum)."""

    count: np.ndarray  # (P,) int: boxes crossed
    loss_db: np.ndarray  # (P,) dB: sum of the crossed boxes' losses


class SceneWalls:
    """A scene's obstacle boxes and their losses, prepared once for :meth:`crossed` every tick."""

    def __init__(self, boxes: Boxes, loss_per_box_db: np.ndarray):
        losses = np.ascontiguousarray(loss_per_box_db, dtype=np.float64)
        if losses.shape != (len(boxes),):
            raise ValueError(f"loss_per_box_db has shape {losses.shape}, expected ({len(boxes)},)")
        self.centers = np.ascontiguousarray(boxes.centers, dtype=np.float64)
        self.halves = np.ascontiguousarray(boxes.half_sizes, dtype=np.float64)
        self.rotations = np.ascontiguousarray(boxes.rotations, dtype=np.float64)
        self.losses = losses
        # Each box's world-frame bounding half extents |R| h, never tighter than the box (round-off
        # included): a segment whose own bounding box misses them skips the slab test.
        extents = np.einsum("kij,kj->ki", np.abs(self.rotations), self.halves)
        self.extents = np.ascontiguousarray(extents * (1.0 + 1e-12) + 1e-12)

    def crossed(self, starts: np.ndarray, ends: np.ndarray) -> WallCrossings:
        """Boxes each segment ``starts[p] -> ends[p]`` ((P, 3) each, m) crosses, and their summed loss."""
        starts = np.ascontiguousarray(starts, dtype=np.float64)
        ends = np.ascontiguousarray(ends, dtype=np.float64)
        if starts.shape != ends.shape or starts.ndim != 2 or starts.shape[1] != 3:
            raise ValueError(f"starts {starts.shape} and ends {ends.shape} must both be (P, 3)")
        count = np.zeros(len(starts), dtype=np.int64)
        loss = np.zeros(len(starts))
        if len(self.centers):
            _crossings(starts, ends, self.centers, self.halves, self.rotations, self.extents, self.losses,
                       count, loss)
        return WallCrossings(count, loss)


    def crossed_pairs(self, positions: np.ndarray, first: np.ndarray, second: np.ndarray) -> WallCrossings:
        """``crossed`` of the segments ``positions[first[p]] -> positions[second[p]]`` ((N, 3), m; index
        arrays (P,)), without gathering the end points."""
        positions = np.ascontiguousarray(positions, dtype=np.float64)
        count = np.zeros(len(first), dtype=np.int64)
        loss = np.zeros(len(first))
        if len(self.centers):
            _pair_crossings(positions, first, second, self.centers, self.halves, self.rotations, self.extents,
                            self.losses, count, loss)
        return WallCrossings(count, loss)


def walls_crossed(starts: np.ndarray, ends: np.ndarray, boxes: Boxes, loss_per_box_db: np.ndarray) -> WallCrossings:
    """Boxes each segment ``starts[p] -> ends[p]`` ((P, 3) each, m) crosses, and their summed loss.

    ``loss_per_box_db`` (K,) in dB, one per box of ``boxes``. Symmetric in
    start and end; a longer segment along the same line never crosses fewer.
    """
    return SceneWalls(boxes, loss_per_box_db).crossed(np.atleast_2d(starts), np.atleast_2d(ends))


@kernel
def segment_crosses_box(ax, ay, az, bx, by, bz, center, half, rotation):
    """Whether the closed segment a -> b meets the closed box (``center`` (3,), ``half`` (3,),
    box-to-world ``rotation`` (3, 3), columns the box axes)."""
    dx, dy, dz = ax - center[0], ay - center[1], az - center[2]
    vx, vy, vz = bx - ax, by - ay, bz - az
    low, high = 0.0, 1.0
    for axis in range(3):
        p = dx * rotation[0, axis] + dy * rotation[1, axis] + dz * rotation[2, axis]
        v = vx * rotation[0, axis] + vy * rotation[1, axis] + vz * rotation[2, axis]
        h = half[axis]
        if v == 0.0:
            if p < -h or p > h:
                return False
            continue
        t1, t2 = (-h - p) / v, (h - p) / v
        if t1 > t2:
            t1, t2 = t2, t1
        low, high = max(low, t1), min(high, t2)
        if low > high:
            return False
    return True


@kernel
def _crossings(starts, ends, centers, halves, rotations, extents, losses, count, loss):
    for s in range(starts.shape[0]):
        n = 0
        total = 0.0
        for k in range(centers.shape[0]):
            apart = False
            for axis in range(3):
                low, high = min(starts[s, axis], ends[s, axis]), max(starts[s, axis], ends[s, axis])
                if high < centers[k, axis] - extents[k, axis] or low > centers[k, axis] + extents[k, axis]:
                    apart = True
                    break
            if apart:
                continue
            if segment_crosses_box(starts[s, 0], starts[s, 1], starts[s, 2], ends[s, 0], ends[s, 1], ends[s, 2],
                                   centers[k], halves[k], rotations[k]):
                n += 1
                total += losses[k]
        count[s] = n
        loss[s] = total


@kernel
def _pair_crossings(positions, first, second, centers, halves, rotations, extents, losses, count, loss):
    """``_crossings`` of the segments between ``positions[first[p]]`` and ``positions[second[p]]``. Each
    robot's side of each box's bounding extents, per axis (-1 below, +1 above, 0 within), is found once
    rather than per pair: a segment misses the extents, and skips the slab test, exactly when both its ends
    lie on the same side (-1 or +1) along some axis, as ``_crossings``' comparisons of its bounds decide."""
    n, boxes = positions.shape[0], centers.shape[0]
    side = np.empty((n, boxes, 3), dtype=np.int8)
    for r in range(n):
        for k in range(boxes):
            for axis in range(3):
                x = positions[r, axis]
                if x < centers[k, axis] - extents[k, axis]:
                    side[r, k, axis] = -1
                elif x > centers[k, axis] + extents[k, axis]:
                    side[r, k, axis] = 1
                else:
                    side[r, k, axis] = 0
    for s in range(first.shape[0]):
        i, j = first[s], second[s]
        a, b = positions[i], positions[j]
        n_crossed = 0
        total = 0.0
        for k in range(boxes):
            apart = False
            for axis in range(3):
                if side[i, k, axis] != 0 and side[i, k, axis] == side[j, k, axis]:
                    apart = True
                    break
            if apart:
                continue
            if segment_crosses_box(a[0], a[1], a[2], b[0], b[1], b[2], centers[k], halves[k], rotations[k]):
                n_crossed += 1
                total += losses[k]
        count[s] = n_crossed
        loss[s] = total
