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
        self._masks_n = -1

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
        diff = positions[None, :, :] - positions[:, None, :]
        distance = np.sqrt(np.add.reduce(diff * diff, axis=-1))  # np.linalg.norm's own sum, without its checks
        not_self, upper = self._masks(n)
        in_range = (distance <= self.comm_range) & not_self
        los = np.zeros((n, n), dtype=bool)
        # Every pair i < j in range, grouped by i (row-major): one mj_multiRay per origin robot,
        # all writing into one buffer, and one comparison for all rays.
        first, second = np.nonzero(in_range & upper)
        count = len(first)
        if count:
            vectors = (positions[second] - positions[first]).reshape(-1)
            geomid = np.empty(count, dtype=np.int32)
            hit = np.empty(count, dtype=np.float64)
            model, data, groups = self.world.model, self.world.data, self._groups
            origins = first.tolist()
            start = 0
            for end in range(1, count + 1):
                if end == count or origins[end] != origins[start]:
                    mujoco.mj_multiRay(model, data, positions[origins[start]], vectors[3 * start : 3 * end], groups,
                                       1, -1, geomid[start:end], hit[start:end], None, end - start, 1.0)
                    start = end
            self.rays_cast += count
            free = ~((geomid >= 0) & (hit >= 0) & (hit < 1.0))
            los[first, second] = free
            los[second, first] = free
        return Links(distance, los, los & in_range, functools.partial(self._clearance, positions.copy(), in_range))

    def _masks(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """(N, N) bool: off-diagonal, and strictly upper triangle (built once per team size)."""
        if self._masks_n != n:
            self._off_diagonal = ~np.eye(n, dtype=bool)
            self._upper = np.triu(np.ones((n, n), dtype=bool), 1)
            self._masks_n = n
        return self._off_diagonal, self._upper

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
