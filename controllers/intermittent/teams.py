"""Robot teams and the graph of teams of Khodayi-mehr et al. 2019 (Sec. II, Fig. 1).

N robots are divided into M > 1 teams T_i; every robot belongs to exactly two
teams (the robot r_ij travels between T_i and T_j). The graph of teams G_T has
one node per team and an edge between T_i and T_j when they share a robot; it
must be connected so that information can flow between any two teams.

Robot ids are arbitrary non-negative integers (the paper's examples use the
labels 12, 18, ... of r_12, r_18, ...); team indices are 0-based here, so the
paper's team T_1 is index 0.

Deviations from the paper:
- Two teams may share more than one robot (parallel robots); the paper's
  definition of G_T (an edge when T_i and T_j intersect) allows it, its
  examples just do not use it.
- Pure combinatorics, no I/O: ``Teams`` only validates and answers graph
  questions; schedules live in ``schedules.py``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from functools import cached_property
from typing import Iterable, Sequence

import numpy as np

# Khodayi-mehr et al. 2019, Sec. IV-A and Fig. 1(a): N = 8 robots, M = 8 teams in a ring (G_T^1).
PAPER_RING_TEAMS: tuple[tuple[int, ...], ...] = (
    (12, 18),
    (12, 23),
    (23, 34),
    (34, 45),
    (45, 56),
    (56, 67),
    (67, 78),
    (18, 78),
)

# Khodayi-mehr et al. 2019, Sec. IV-A and Fig. 1(b): N = 8 robots, M = 5 teams (G_T^2).
PAPER_DENSE_TEAMS: tuple[tuple[int, ...], ...] = (
    (12, 14, 15),
    (12, 23, 25),
    (23, 34, 35),
    (14, 34, 45),
    (15, 25, 35, 45),
)

# Khodayi-mehr et al. 2019, Sec. IV-B (Table I, 4 targets): N = 4 robots, M = 4 teams in a ring.
PAPER_FOUR_ROBOT_TEAMS: tuple[tuple[int, ...], ...] = (
    (12, 14),
    (12, 23),
    (23, 34),
    (14, 34),
)


@dataclass(frozen=True)
class Teams:
    """Teams as tuples of robot ids; ``members[i]`` is team T_{i+1} of the paper.

    Validation (ValueError): at least two teams, no empty team, no robot
    listed twice in one team, every robot in exactly two teams, and a
    connected graph of teams.
    """

    members: tuple[tuple[int, ...], ...]

    def __post_init__(self) -> None:
        members = tuple(tuple(int(r) for r in team) for team in self.members)
        object.__setattr__(self, "members", members)
        if len(members) < 2:
            raise ValueError(f"members: need at least two teams (M > 1), got {len(members)}")
        for index, team in enumerate(members):
            if not team:
                raise ValueError(f"members: team {index} is empty")
            if any(r < 0 for r in team):
                raise ValueError(f"members: team {index} has a negative robot id {min(team)}")
            if len(set(team)) != len(team):
                repeated = sorted({r for r in team if team.count(r) > 1})
                raise ValueError(f"members: team {index} lists robot(s) {repeated} more than once")
        memberships: dict[int, list[int]] = {}
        for index, team in enumerate(members):
            for robot in team:
                memberships.setdefault(robot, []).append(index)
        for robot in sorted(memberships):
            teams = memberships[robot]
            if len(teams) != 2:
                raise ValueError(
                    f"members: robot {robot} belongs to {len(teams)} team(s) {teams}; "
                    "every robot must belong to exactly two teams"
                )
        unreached = self._unreached_from_first(members, memberships)
        if unreached:
            raise ValueError(
                f"members: the graph of teams is not connected; teams {sorted(unreached)} "
                "share no chain of robots with team 0"
            )

    @staticmethod
    def _unreached_from_first(
        members: tuple[tuple[int, ...], ...], memberships: dict[int, list[int]]
    ) -> set[int]:
        seen = {0}
        frontier = deque([0])
        while frontier:
            team = frontier.popleft()
            for robot in members[team]:
                for other in memberships[robot]:
                    if other not in seen:
                        seen.add(other)
                        frontier.append(other)
        return set(range(len(members))) - seen

    @classmethod
    def from_lists(cls, teams: Iterable[Sequence[int]]) -> "Teams":
        """Build from any iterable of robot-id sequences."""
        return cls(tuple(tuple(team) for team in teams))

    @property
    def n_teams(self) -> int:
        """M, the number of teams."""
        return len(self.members)

    @cached_property
    def robots(self) -> tuple[int, ...]:
        """All robot ids, sorted."""
        return tuple(sorted({r for team in self.members for r in team}))

    @property
    def n_robots(self) -> int:
        """N, the number of robots."""
        return len(self.robots)

    @cached_property
    def _memberships(self) -> dict[int, tuple[int, int]]:
        pairs: dict[int, list[int]] = {}
        for index, team in enumerate(self.members):
            for robot in team:
                pairs.setdefault(robot, []).append(index)
        return {robot: (teams[0], teams[1]) for robot, teams in pairs.items()}

    def teams_of(self, robot: int) -> tuple[int, int]:
        """The two teams (i, j), i < j, that ``robot`` travels between."""
        try:
            return self._memberships[robot]
        except KeyError:
            raise ValueError(f"robot: {robot} is in no team") from None

    def shared_robots(self, i: int, j: int) -> tuple[int, ...]:
        """Robots in both T_i and T_j, sorted (empty if not adjacent)."""
        return tuple(sorted(set(self.members[i]) & set(self.members[j])))

    @cached_property
    def adjacency(self) -> np.ndarray:
        """(M, M) bool adjacency of the graph of teams G_T (no self loops)."""
        adjacency = np.zeros((self.n_teams, self.n_teams), dtype=bool)
        for i, j in self._memberships.values():
            adjacency[i, j] = adjacency[j, i] = True
        adjacency.setflags(write=False)
        return adjacency

    def neighbours(self, team: int) -> tuple[int, ...]:
        """Teams adjacent to ``team`` in G_T, sorted."""
        return tuple(int(j) for j in np.flatnonzero(self.adjacency[team]))

    @cached_property
    def degrees(self) -> tuple[int, ...]:
        """d_i, the degree of each team in G_T."""
        return tuple(int(d) for d in self.adjacency.sum(axis=1))

    @property
    def max_degree(self) -> int:
        return max(self.degrees)

    @cached_property
    def hop_distances(self) -> np.ndarray:
        """(M, M) int: number of edges on the shortest path between teams (BFS)."""
        m = self.n_teams
        distances = np.full((m, m), -1, dtype=int)
        for source in range(m):
            distances[source, source] = 0
            frontier = deque([source])
            while frontier:
                team = frontier.popleft()
                for other in np.flatnonzero(self.adjacency[team]):
                    if distances[source, other] < 0:
                        distances[source, other] = distances[source, team] + 1
                        frontier.append(other)
        distances.setflags(write=False)
        return distances

    @property
    def diameter_edges(self) -> int:
        """Edges on the longest shortest path of G_T (the graph diameter)."""
        return int(self.hop_distances.max())

    @property
    def longest_shortest_path_nodes(self) -> int:
        """L_{G_T} of Proposition III.2: max over team pairs of |l_ie|, the
        number of *nodes* on the shortest path (diameter in edges + 1)."""
        return self.diameter_edges + 1
