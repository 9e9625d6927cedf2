"""Line-of-sight sensing with ``mj_ray``: robot links and target ranges.

Rays see only static obstacles (geom group 0), so robot and target bodies
never occlude. One ``mj_multiRay`` call per robot covers every ray that
robot casts in a tick (to targets in range and to robots of higher index in
comm range); rays are cast with unnormalised direction vectors, so a hit at
parameter x < 1 means the segment is blocked. Segment clearance (exact box
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

    def sensor_positions(self) -> np.ndarray:
        return self.world.data.site_xpos[self.world.sensor_site_ids].copy()

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
            self._buffers_n = n
        first, second, vectors, group_starts = self._pair_buffers
        distance = np.empty((n, n))
        in_range = np.empty((n, n), dtype=bool)
        # Every pair i < j in range, grouped by i (row-major): one mj_multiRay per origin robot,
        # all writing into one buffer.
        count, groups = _pairs_in_range(positions, self.comm_range, distance, in_range, first, second, vectors,
                                        group_starts)
        geomid = np.empty(count, dtype=np.int32)
        hit = np.empty(count, dtype=np.float64)
        model, data, mask = self.world.model, self.world.data, self._groups
        for group in range(groups):
            start, end = int(group_starts[group]), int(group_starts[group + 1])
            mujoco.mj_multiRay(model, data, positions[first[start]], vectors[3 * start : 3 * end], mask,
                               1, -1, geomid[start:end], hit[start:end], None, end - start, 1.0)
        self.rays_cast += count
        los = np.zeros((n, n), dtype=bool)
        adjacency = np.zeros((n, n), dtype=bool)
        _sight(first, second, geomid, hit, los, adjacency)
        return Links(distance, los, adjacency, functools.partial(self._clearance, positions.copy(), in_range))

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
        """(N, M) range readings of seed 000, eq. (12); NaN where the target is
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
def _sight(first, second, geomid, hit, line_of_sight, adjacency):
    """Mark the cast pairs free of obstacles (no hit before the far end) in both (N, N) matrices."""
    for k in range(geomid.shape[0]):
        free = not (geomid[k] >= 0 and hit[k] >= 0 and hit[k] < 1.0)
        i, j = first[k], second[k]
        line_of_sight[i, j] = line_of_sight[j, i] = free
        adjacency[i, j] = adjacency[j, i] = free
