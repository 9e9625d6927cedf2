"""Conflict-free communication schedules of Khodayi-mehr et al. 2019 (Sec. III-A).

Definition III.1: robot r_ij follows sched_ij = s_ij s_ij ..., the infinite
repetition of a finite sequence s_ij of length T that holds the event i (meet
team T_i), the event j (meet T_j) and idle entries X everywhere else. A
schedule is conflict-free when no two teams that share a robot meet in the
same epoch, and every robot of a team agrees on the epochs its team meets.

Construction (the paper's reference [17], Sec. V): colour the graph of teams
G_T so that adjacent teams get different colours; colour c is the slot c of
the period, so team T_i meets at epochs k = c(i) + 1 + nT, n = 0, 1, ...;
s_ij has i at position c(i), j at position c(j) and X elsewhere. A greedy
colouring uses at most max_i d_i + 1 colours, and the period is the number
of colours, T <= max degree + 1 (the paper's T = max degree + 1 is the bound;
its ring example G_T^1 has max degree 2 and period T = 2).

Proposition III.2: information collected by any robot reaches every other
robot within D = (T - 1) L epochs, L the number of nodes on the longest
shortest path of G_T. ``worst_case_delay`` measures the true worst case by
replaying every packet over the schedule, for comparison with the bound.

Epochs are numbered from 1 as in the paper; epoch 0 means "before the first
meeting". ``None`` stands for the idle entry X. Team indices are 0-based; the
paper-style text form (``format_sequence``) prints them 1-based.

Reconciling the paper's examples (Sec. IV-A). With the greedy colouring in
team order, G_T^1 (8-team ring) gets T = 2 and the printed schedules
sched_12 = [1, 2], sched_23 = [3, 2], ... (odd teams at epoch 1); its longest
shortest path has 5 nodes (4 edges), so D = (2 - 1) * 5 = 5, as printed.
G_T^2 (5 teams, the 4-ring T_1..T_4 plus T_5 adjacent to all) gets T = 3 and
sched_14 = [1, 4, X] as in Fig. 2; its longest shortest path has 3 nodes
(2 edges), so the formula gives D = (3 - 1) * 3 = 6. The paper prints
D = (3 - 1) x 2 = 4, counting edges for G_T^2 while it counts nodes for
G_T^1. Replaying every packet gives a true worst case of 5 epochs for both
graphs, so 4 is not a bound for G_T^2 and 6 is (see tests/test_schedules.py).

Deviations from the paper:
- The colouring is the sequential greedy colouring in a given team order
  (default: team index), computed centrally once; [17] describes the same
  bound T <= max degree + 1 but lets the robots run it distributedly.
- The period is the number of colours used (<= max degree + 1), not the
  worst-case max degree + 1, so no epoch is idle for the whole network.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property
from typing import Sequence

import numpy as np

from controllers.intermittent.teams import Teams

IDLE = None  # the paper's X entry: no communication event for this robot


def greedy_colouring(adjacency: np.ndarray, order: Sequence[int] | None = None) -> tuple[int, ...]:
    """Colour each node, in ``order``, with the smallest colour unused by its
    already coloured neighbours. Returns colours 0..C-1 per node, C <= max
    degree + 1.

    adjacency: (M, M) symmetric bool matrix; order: a permutation of range(M)
    (default: 0, 1, ..., M - 1).
    """
    adjacency = np.asarray(adjacency, dtype=bool)
    m = adjacency.shape[0]
    if adjacency.shape != (m, m):
        raise ValueError(f"adjacency: must be square, got shape {adjacency.shape}")
    if not np.array_equal(adjacency, adjacency.T):
        raise ValueError("adjacency: must be symmetric (undirected graph of teams)")
    if np.any(np.diag(adjacency)):
        raise ValueError("adjacency: must have no self loops")
    order = list(range(m)) if order is None else [int(i) for i in order]
    if sorted(order) != list(range(m)):
        raise ValueError(f"order: must be a permutation of 0..{m - 1}, got {order}")
    colours = [-1] * m
    for node in order:
        taken = {colours[other] for other in np.flatnonzero(adjacency[node])}
        colour = 0
        while colour in taken:
            colour += 1
        colours[node] = colour
    return tuple(colours)


@dataclass(frozen=True)
class CommunicationSchedule:
    """Periodic, conflict-free meeting schedule of all teams.

    teams: the teams; slots: slot (colour) 0..T-1 of each team, team i meets at
    epochs k = slots[i] + 1 + n T. Validation (ValueError): one slot per team,
    teams that share a robot in different slots, slots 0..T-1 all used.
    """

    teams: Teams
    slots: tuple[int, ...]

    def __post_init__(self) -> None:
        slots = tuple(int(s) for s in self.slots)
        object.__setattr__(self, "slots", slots)
        if len(slots) != self.teams.n_teams:
            raise ValueError(
                f"slots: need one slot per team ({self.teams.n_teams}), got {len(slots)}"
            )
        if min(slots) < 0:
            raise ValueError(f"slots: must be non-negative, got {slots}")
        unused = sorted(set(range(max(slots) + 1)) - set(slots))
        if unused:
            raise ValueError(f"slots: slot(s) {unused} hold no team; use slots 0..T-1 without gaps")
        for robot in self.teams.robots:
            i, j = self.teams.teams_of(robot)
            if slots[i] == slots[j]:
                raise ValueError(
                    f"slots: teams {i} and {j} share robot {robot} but both meet in slot "
                    f"{slots[i]}; the schedule would not be conflict-free"
                )

    @property
    def period(self) -> int:
        """T, the length of every s_ij, in epochs."""
        return max(self.slots) + 1

    @property
    def delay_bound(self) -> int:
        """D = (T - 1) L of Proposition III.2, epochs (L counts nodes)."""
        return (self.period - 1) * self.teams.longest_shortest_path_nodes

    def sequence(self, robot: int) -> tuple[int | None, ...]:
        """s_ij of ``robot``: length T, team index at its meeting slots, None (X) elsewhere."""
        i, j = self.teams.teams_of(robot)
        entries: list[int | None] = [IDLE] * self.period
        entries[self.slots[i]] = i
        entries[self.slots[j]] = j
        return tuple(entries)

    def team_at(self, robot: int, epoch: int) -> int | None:
        """sched_ij(k): the team ``robot`` meets at ``epoch`` (>= 1), or None (X)."""
        _check_epoch(epoch)
        return self.sequence(robot)[(epoch - 1) % self.period]

    def meets(self, team: int, epoch: int) -> bool:
        """Whether team ``team`` has a communication event at ``epoch`` (>= 1)."""
        _check_epoch(epoch)
        return (epoch - 1) % self.period == self.slots[team]

    def teams_meeting_at(self, epoch: int) -> tuple[int, ...]:
        """All teams that meet at ``epoch`` (>= 1), sorted; they share no robot."""
        _check_epoch(epoch)
        return self._slot_teams[(epoch - 1) % self.period]

    @cached_property
    def _slot_teams(self) -> tuple[tuple[int, ...], ...]:
        return tuple(
            tuple(i for i, s in enumerate(self.slots) if s == slot) for slot in range(self.period)
        )

    def first_epoch(self, team: int) -> int:
        """k_i^1, the first epoch at which team ``team`` meets."""
        return self.slots[team] + 1

    def next_meeting_epoch(self, team: int, after_epoch: int) -> int:
        """Smallest epoch k > ``after_epoch`` (>= 0) at which ``team`` meets."""
        if after_epoch < 0:
            raise ValueError(f"after_epoch: must be >= 0, got {after_epoch}")
        first = self.first_epoch(team)
        if after_epoch < first:
            return first
        return first + ((after_epoch - first) // self.period + 1) * self.period


def _check_epoch(epoch: int) -> None:
    if epoch < 1:
        raise ValueError(f"epoch: epochs are numbered from 1, got {epoch}")


def build_schedule(teams: Teams, order: Sequence[int] | None = None) -> CommunicationSchedule:
    """Conflict-free schedule from a greedy colouring of G_T in ``order``."""
    return CommunicationSchedule(teams, greedy_colouring(teams.adjacency, order))


def format_sequence(sequence: Sequence[int | None]) -> str:
    """Paper notation with 1-based teams, e.g. (0, 3, None) -> '[1, 4, X]^w'."""
    return "[" + ", ".join("X" if e is IDLE else str(e + 1) for e in sequence) + "]^w"


def propagation_epochs(
    schedule: CommunicationSchedule, robot: int, collected_after_epoch: int
) -> dict[int, int]:
    """Epoch at which each team first meets holding a packet that ``robot``
    collected after its meeting at ``collected_after_epoch`` (0: before any).

    A team that meets with at least one member holding the packet passes it to
    all its members; teams meeting in one epoch share no robot, so a packet
    moves at most one hop per epoch. Returns {team: epoch} for all teams.
    """
    if collected_after_epoch < 0:
        raise ValueError(f"collected_after_epoch: must be >= 0, got {collected_after_epoch}")
    teams = schedule.teams
    holders = {robot}
    reached: dict[int, int] = {}
    epoch = collected_after_epoch
    # Every team meets once per period and the graph of teams is connected, so
    # the packet advances at least one hop per period.
    last_epoch = collected_after_epoch + schedule.period * (teams.n_teams + 1)
    while len(reached) < teams.n_teams and epoch < last_epoch:
        epoch += 1
        for team in schedule.teams_meeting_at(epoch):
            members = teams.members[team]
            if team not in reached and holders.intersection(members):
                reached[team] = epoch
            if team in reached:
                holders.update(members)
    return reached


def worst_case_delay(schedule: CommunicationSchedule) -> int:
    """Largest number of epochs between a packet's collection (right after its
    robot's last meeting) and the epoch its last team receives it, over every
    robot and every collection epoch. By periodicity it suffices to start from
    epoch 0 and from each of the robot's meetings in the first two periods.
    """
    worst = 0
    for robot in schedule.teams.robots:
        starts = [0] + [
            k for k in range(1, 2 * schedule.period + 1) if schedule.team_at(robot, k) is not IDLE
        ]
        for start in starts:
            reached = propagation_epochs(schedule, robot, start)
            worst = max(worst, max(reached.values()) - start)
    return worst
