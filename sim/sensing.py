"""Line-of-sight sensing with ``mj_ray``: robot links and target ranges.

Rays see only static obstacles (geom group 0), so robot and target bodies
never occlude. One ``mj_multiRay`` call per robot covers every ray that
robot casts in a tick (to targets in range and to robots of higher index in
comm range); rays are cast with unnormalised direction vectors, so a hit at
parameter x < 1 means the segment is blocked. A link whose segment stays
clear of every obstacle's bounding box (MuJoCo's ``geom_aabb``, by
``RAY_CULL_MARGIN_M``) cannot be blocked and is not cast. Segment clearance (exact box
geometry, :mod:`sim.geometry`) is computed only when ``Links.clearance`` is read.
"""

from __future__ import annotations

import functools

import mujoco
import numpy as np

from estimation.range_model import range_sigma
from sim.compiled import kernel
from sim.geometry import segment_clearance
from sim.types import Links
from sim.world import World, obstacle_geomgroup


class RaySensors:
    def __init__(self, world: World, comm_range_m: float, target_range_m: float, noisy: bool):
        self.world = world
        self.comm_range = comm_range_m
        self.target_range = target_range_m
        self.noisy = noisy
        self._groups = obstacle_geomgroup()
        self.rays_cast = 0  # for benchmarks
        self._buffers_n = -1
        self._bounds = None  # the obstacles' bounding boxes for culling rays (_obstacle_bounds), on first use

    def sensor_positions(self) -> np.ndarray:
        return self.world.data.site_xpos[self.world.sensor_site_ids]  # a copy (index array)

    def _blocked(self, origin: np.ndarray, ends: np.ndarray) -> np.ndarray:
        """Boolean (K,): the segment origin -> ends[k] hits an obstacle."""
        k = len(ends)
        if k == 0:
            return np.zeros(0, dtype=bool)
        vec = np.ascontiguousarray((ends - origin).reshape(-1))
        geomid = np.empty(k, dtype=np.int32)
        dist = np.empty(k, dtype=np.float64)
        mujoco.mj_multiRay(self.world.model, self.world.data, origin, vec, self._groups, 1, -1, geomid, dist, None, k, 1.0)
        self.rays_cast += k
        return (geomid >= 0) & (dist >= 0) & (dist < 1.0)

    def links(self, positions: np.ndarray) -> Links:
        """Pairwise distance, line of sight and adjacency of robots (clearance on demand)."""
        n = len(positions)
        positions = np.ascontiguousarray(positions, dtype=np.float64)
        if self._buffers_n != n:  # the pair buffers, allocated once per team size
            pairs = n * (n - 1) // 2
            self._pair_buffers = (np.empty(pairs, dtype=np.int64), np.empty(pairs, dtype=np.int64),
                                  np.empty(3 * pairs), np.empty(n + 1, dtype=np.int64))
            self._cast_buffers = (np.empty(pairs, dtype=np.int64), np.empty(3 * pairs), np.empty(n + 1, dtype=np.int64))
            self._buffers_n = n
        first, second, vectors, group_starts = self._pair_buffers
        distance = np.empty((n, n))
        in_range = np.empty((n, n), dtype=bool)
        # Every pair i < j in range, grouped by i (row-major): one mj_multiRay per origin robot,
        # all writing into one buffer.
        count, groups = _pairs_in_range(positions, self.comm_range, distance, in_range, first, second, vectors,
                                        group_starts)
        # Only the pairs whose segment comes near an obstacle's bounding box are cast (the others
        # cannot hit one before their far end: free, as mj_multiRay would find).
        bounds = self._bounds if self._bounds is not None else self._obstacle_bounds()
        cull, centers, rotations, halves, planes = bounds
        cast_index, cast_vectors, cast_starts = self._cast_buffers
        if cull:
            cast, groups = _rays_needed(positions, first, vectors, count, centers, rotations, halves, planes,
                                        RAY_CULL_MARGIN_M, cast_index, cast_vectors, cast_starts)
        else:
            cast_index[:count] = np.arange(count)
            cast_vectors[: 3 * count] = vectors[: 3 * count]
            cast, groups = count, _group_starts(first, cast_index, count, cast_starts)
        geomid = np.empty(cast, dtype=np.int32)
        hit = np.empty(cast, dtype=np.float64)
        model, data, mask = self.world.model, self.world.data, self._groups
        for group in range(groups):
            start, end = int(cast_starts[group]), int(cast_starts[group + 1])
            mujoco.mj_multiRay(model, data, positions[first[cast_index[start]]], cast_vectors[3 * start : 3 * end],
                               mask, 1, -1, geomid[start:end], hit[start:end], None, end - start, 1.0)
        self.rays_cast += cast
        los = np.zeros((n, n), dtype=bool)
        adjacency = np.zeros((n, n), dtype=bool)
        _sight(first, second, count, cast_index, geomid, hit, los, adjacency)
        return Links(distance, los, adjacency, functools.partial(self._clearance, positions.copy(), in_range))

    def _obstacle_bounds(self):
        """(cull, centres (K, 3), rotations (K, 9), half extents (K, 3), is plane (K,)) of every geom
        the rays can see, in the world frame: each geom's bounding box (MuJoCo's ``geom_aabb`` about
        ``geom_xpos`` / ``geom_xmat``). Culling only while all of them are fixed to the world."""
        model, data = self.world.model, self.world.data
        ids = np.array([g for g in range(model.ngeom) if model.geom_group[g] < len(self._groups)
                        and self._groups[model.geom_group[g]]], dtype=np.int64)
        static = bool(np.all(model.body_weldid[model.geom_bodyid[ids]] == 0)) if len(ids) else True
        planes = model.geom_type[ids] == mujoco.mjtGeom.mjGEOM_PLANE
        rotations = np.ascontiguousarray(data.geom_xmat[ids], dtype=np.float64)
        aabb = model.geom_aabb[ids].reshape(-1, 6)
        # the box's centre offset (local frame) moved into the world frame
        offset = np.einsum("kij,kj->ki", rotations.reshape(-1, 3, 3), aabb[:, :3])
        centers = np.ascontiguousarray(data.geom_xpos[ids] + offset, dtype=np.float64)
        halves = np.ascontiguousarray(aabb[:, 3:], dtype=np.float64)
        bounds = static and len(ids) > 0, centers, rotations, halves, np.ascontiguousarray(planes)
        if len(ids) and np.all(np.any(rotations != 0.0, axis=1)):  # placed (mj_forward ran): kept
            self._bounds = bounds
        return bounds

    def _clearance(self, positions: np.ndarray, in_range: np.ndarray) -> np.ndarray:
        """(N, N) segment clearance of the pairs in comm range, m; inf elsewhere."""
        n = len(positions)
        clearance = np.full((n, n), np.inf)
        ii, jj = np.nonzero(np.triu(in_range, 1))
        if len(ii):
            c = segment_clearance(self.world.obstacles, positions[ii], positions[jj]).distance
            clearance[ii, jj] = c
            clearance[jj, ii] = c
        return clearance

    def target_ranges(self, sensors: np.ndarray, targets: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """(N, M) range readings of Khodayi-mehr et al. 2019, eq. (12); NaN where the target is
        out of range or hidden. Noise is drawn from ``rng`` only when enabled."""
        n, m = len(sensors), len(targets)
        true_range = np.linalg.norm(targets[None, :, :] - sensors[:, None, :], axis=-1)
        readings = np.full((n, m), np.nan)
        for i in range(n):
            candidates = np.nonzero(true_range[i] <= self.target_range)[0]
            if len(candidates):
                visible = candidates[~self._blocked(sensors[i], targets[candidates])]
                readings[i, visible] = true_range[i, visible]
        if self.noisy:
            seen = ~np.isnan(readings)
            readings[seen] += rng.normal(0.0, range_sigma(readings[seen]))
        return readings


@kernel
def _pairs_in_range(positions, comm_range, distance, in_range, first, second, vectors, group_starts):
    """Fill ``distance`` and ``in_range`` (N, N, no self-pairs) and list the pairs i < j in range,
    row-major, with their ray vectors p_j - p_i; ``group_starts`` marks where each origin's run
    begins. Returns (pairs, origins with pairs)."""
    n = positions.shape[0]
    count = groups = 0
    for i in range(n):
        distance[i, i] = 0.0
        in_range[i, i] = False
        for j in range(n):
            if j == i:
                continue
            dx = positions[j, 0] - positions[i, 0]
            dy = positions[j, 1] - positions[i, 1]
            dz = positions[j, 2] - positions[i, 2]
            d = np.sqrt(dx * dx + dy * dy + dz * dz)
            distance[i, j] = d
            in_range[i, j] = d <= comm_range
            if j > i and d <= comm_range:
                if count == 0 or first[count - 1] != i:
                    group_starts[groups] = count
                    groups += 1
                first[count], second[count] = i, j
                vectors[3 * count], vectors[3 * count + 1], vectors[3 * count + 2] = dx, dy, dz
                count += 1
    group_starts[groups] = count
    return count, groups


@kernel
def _sight(first, second, count, cast_index, geomid, hit, line_of_sight, adjacency):
    """Mark the pairs in range free of obstacles (no hit before the far end) in both (N, N) matrices:
    the ``count`` pairs are free unless their ray (cast ``k`` is pair ``cast_index[k]``) hit."""
    for k in range(count):
        i, j = first[k], second[k]
        line_of_sight[i, j] = line_of_sight[j, i] = True
        adjacency[i, j] = adjacency[j, i] = True
    for k in range(geomid.shape[0]):
        free = not (geomid[k] >= 0 and hit[k] >= 0 and hit[k] < 1.0)
        i, j = first[cast_index[k]], second[cast_index[k]]
        line_of_sight[i, j] = line_of_sight[j, i] = free
        adjacency[i, j] = adjacency[j, i] = free


RAY_CULL_MARGIN_M = 1e-6  # a segment this far outside every obstacle's bounding box is not cast, m


@kernel
def _group_starts(first, cast_index, cast, starts):
    """Where each origin's run of casts begins (``starts``); returns the number of runs."""
    groups = 0
    for k in range(cast):
        if k == 0 or first[cast_index[k - 1]] != first[cast_index[k]]:
            starts[groups] = k
            groups += 1
    starts[groups] = cast
    return groups


@kernel
def _segment_may_hit(px, py, pz, vx, vy, vz, centers, rotations, halves, planes, margin):
    """Whether the segment p + s v, s in [0, 1], comes within ``margin`` of some obstacle's bounding
    box (a plane: whether its ends are not both more than ``margin`` on one side)."""
    for g in range(centers.shape[0]):
        dx, dy, dz = px - centers[g, 0], py - centers[g, 1], pz - centers[g, 2]
        if planes[g]:
            nx, ny, nz = rotations[g, 2], rotations[g, 5], rotations[g, 8]
            a = dx * nx + dy * ny + dz * nz
            b = (dx + vx) * nx + (dy + vy) * ny + (dz + vz) * nz
            if (a > margin and b > margin) or (a < -margin and b < -margin):
                continue
            return True
        low, high = 0.0, 1.0
        outside = False
        for axis in range(3):
            # local frame: the columns of geom_xmat are the box's axes
            p = dx * rotations[g, axis] + dy * rotations[g, 3 + axis] + dz * rotations[g, 6 + axis]
            v = vx * rotations[g, axis] + vy * rotations[g, 3 + axis] + vz * rotations[g, 6 + axis]
            lo, hi = -halves[g, axis] - margin, halves[g, axis] + margin
            if abs(v) < 1e-300:
                if p < lo or p > hi:
                    outside = True
                    break
                continue
            t1, t2 = (lo - p) / v, (hi - p) / v
            if t1 > t2:
                t1, t2 = t2, t1
            low, high = max(low, t1), min(high, t2)
            if low > high:
                outside = True
                break
        if not outside:
            return True
    return False


@kernel
def _rays_needed(positions, first, vectors, count, centers, rotations, halves, planes, margin,
                 cast_index, cast_vectors, starts):
    """The pairs whose ray :func:`_segment_may_hit`, in order (``cast_index``, their vectors and
    per-origin runs ``starts``). Returns (casts, runs)."""
    cast = groups = 0
    for k in range(count):
        i = first[k]
        vx, vy, vz = vectors[3 * k], vectors[3 * k + 1], vectors[3 * k + 2]
        if not _segment_may_hit(positions[i, 0], positions[i, 1], positions[i, 2], vx, vy, vz,
                                centers, rotations, halves, planes, margin):
            continue
        if cast == 0 or first[cast_index[cast - 1]] != i:
            starts[groups] = cast
            groups += 1
        cast_index[cast] = k
        cast_vectors[3 * cast], cast_vectors[3 * cast + 1], cast_vectors[3 * cast + 2] = vx, vy, vz
        cast += 1
    starts[groups] = cast
    return cast, groups
