"""The intermittent paper's heuristic baseline (Sec. IV-B): ``strategy.kind = "random_meeting"``.

"An intermittent connectivity heuristic that employs the same decomposition
of robots into teams, but selects random meeting locations for each team."
Everything but the design of the segments is Algorithm 5 as in
:mod:`controllers.intermittent.strategy`: the same teams, conflict-free
schedule, logs exchanged at meetings, beliefs and metrics. When a team meets
it draws its next meeting location uniformly from the free space (keeping
``random_clearance_m`` from walls) and every member drives the geodesic path
(:mod:`controllers.baselines.geodesic`) from the end of its committed segment
to its stop on a small ring around that location, at the full speed
``speed_mps``; "the time constraint is not satisfied and the robots need to
wait at their meeting locations for their team members". The first meetings
are drawn the same way, a priori.

No informative planning happens, so ``plan_time_*`` report the time to draw
the point and compute the geodesics.
"""

from __future__ import annotations

import time


from controllers.intermittent.strategy import MeetingStrategy, TeamDesign, ring_points
from controllers.baselines.geodesic import GeodesicPlanner

MAX_DRAWS = 200  # meeting-location draws before giving up (the free space is connected, so never in practice)


class RandomMeetingStrategy(MeetingStrategy):
    kind = "random_meeting"

    def reset(self, world, initial, rng) -> None:
        self._locations: GeodesicPlanner | None = None
        super().reset(world, initial, rng)

    def _location_space(self) -> GeodesicPlanner:
        if self._locations is None:
            self._locations = GeodesicPlanner(self.planning.boxes, self.planning.bounds,
                                              self.planning.sensor_height, self.params.random_clearance_m)
        return self._locations

    def design(self, team, epoch, members, starts, belief_step, estimate) -> TeamDesign:
        start = time.perf_counter()
        space = self._location_space()
        lo = self.planning.bounds[0] + self.params.random_clearance_m
        hi = self.planning.bounds[1] - self.params.random_clearance_m
        for _ in range(MAX_DRAWS):
            location = self.rng.uniform(lo, hi)
            if not space.is_free(location[None])[0]:
                continue
            design = self.geodesic_design(members, starts, ring_points(location, len(members), self.geodesic))
            if design is not None:
                wall = time.perf_counter() - start
                return TeamDesign(design.paths, design.meeting_time, design.points, None, wall, 0.0, 0, False)
        raise RuntimeError(f"team {team}: no reachable random meeting location in {MAX_DRAWS} draws")
