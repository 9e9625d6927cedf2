"""Teams and conflict-free communication schedules of Khodayi-mehr et al. 2019 (Sec. III-A,
Definition III.1, Proposition III.2), against the paper's examples G_T^1 and
G_T^2 and hypothesis properties over random connected graphs of teams."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from controllers.intermittent.schedules import (
    IDLE,
    CommunicationSchedule,
    build_schedule,
    format_sequence,
    greedy_colouring,
    propagation_epochs,
    worst_case_delay,
)
from controllers.intermittent.teams import (
    PAPER_DENSE_TEAMS,
    PAPER_FOUR_ROBOT_TEAMS,
    PAPER_RING_TEAMS,
    Teams,
)

# ----------------------------------------------------------------- teams


def test_paper_teams_are_valid():
    ring = Teams(PAPER_RING_TEAMS)
    assert ring.n_teams == 8 and ring.n_robots == 8
    assert ring.degrees == (2,) * 8
    assert ring.teams_of(18) == (0, 7)
    dense = Teams(PAPER_DENSE_TEAMS)
    assert dense.n_teams == 5 and dense.n_robots == 8
    assert dense.degrees == (3, 3, 3, 3, 4)
    assert dense.shared_robots(0, 4) == (15,)
    assert dense.neighbours(4) == (0, 1, 2, 3)


def test_robot_in_three_teams_is_named_with_its_count():
    with pytest.raises(ValueError, match=r"robot 1 belongs to 3 team\(s\)"):
        Teams(((1, 2), (1, 3), (1, 2, 3)))


def test_robot_in_one_team_is_named_with_its_count():
    with pytest.raises(ValueError, match=r"robot 9 belongs to 1 team\(s\)"):
        Teams(((1, 2), (1, 2, 9)))


def test_disconnected_team_graph_is_rejected():
    # Two separate 2-team pairs: {T0, T1} via robots 1, 2 and {T2, T3} via 3, 4.
    with pytest.raises(ValueError, match=r"not connected; teams \[2, 3\]"):
        Teams(((1, 2), (1, 2), (3, 4), (3, 4)))


@pytest.mark.parametrize(
    "members, message",
    [
        (((1,),), "at least two teams"),
        (((1, 2), ()), "team 1 is empty"),
        (((1, 1, 2), (1, 2)), r"team 0 lists robot\(s\) \[1\] more than once"),
        (((-1, 2), (-1, 2)), "negative robot id"),
    ],
)
def test_team_validation_messages(members, message):
    with pytest.raises(ValueError, match=message):
        Teams(members)


def test_unknown_robot_lookup_raises():
    with pytest.raises(ValueError, match="robot: 99"):
        Teams(PAPER_RING_TEAMS).teams_of(99)


# ------------------------------------------------------- paper examples


def test_ring_g1_reproduces_printed_schedules():
    """Sec. IV-A: T = 2 and sched_12 = [1,2], sched_23 = [3,2], ...; odd teams
    communicate at epoch 1 and reconnect at epoch 3."""
    schedule = build_schedule(Teams(PAPER_RING_TEAMS))
    assert schedule.period == 2
    printed = {
        12: "[1, 2]^w",
        23: "[3, 2]^w",
        34: "[3, 4]^w",
        45: "[5, 4]^w",
        56: "[5, 6]^w",
        67: "[7, 6]^w",
        78: "[7, 8]^w",
        18: "[1, 8]^w",
    }
    for robot, text in printed.items():
        assert format_sequence(schedule.sequence(robot)) == text
    assert schedule.teams_meeting_at(1) == (0, 2, 4, 6)  # T1, T3, T5, T7
    assert schedule.teams_meeting_at(3) == (0, 2, 4, 6)
    assert schedule.teams_meeting_at(2) == (1, 3, 5, 7)


def test_dense_g2_matches_fig2_schedule_of_r14():
    """Fig. 2: sched_14 = [1, 4, X] with T = 3; r14 meets T4 at epoch 5 (path
    designed at epoch 2), T1 at epoch 7 (designed at 4), idles at epoch 6."""
    schedule = build_schedule(Teams(PAPER_DENSE_TEAMS))
    assert schedule.period == 3
    assert format_sequence(schedule.sequence(14)) == "[1, 4, X]^w"
    assert schedule.team_at(14, 2) == 3 and schedule.team_at(14, 5) == 3
    assert schedule.team_at(14, 4) == 0 and schedule.team_at(14, 7) == 0
    assert schedule.team_at(14, 6) is IDLE
    assert schedule.next_meeting_epoch(3, 2) == 5
    assert schedule.next_meeting_epoch(0, 4) == 7
    assert schedule.first_epoch(4) == 3  # T5, adjacent to all, gets its own slot


def test_delay_bound_reconciled_with_section_iv():
    """Prop. III.2 counts nodes on the longest shortest path (L). G_T^1: L = 5
    and D = (2-1)*5 = 5 as printed, and replaying packets hits it exactly.
    G_T^2: L = 3 so D = (3-1)*3 = 6; the paper's D = (3-1)*2 = 4 counts the 2
    edges instead, and the replayed worst case, 5 epochs, exceeds it."""
    ring = build_schedule(Teams(PAPER_RING_TEAMS))
    assert ring.teams.longest_shortest_path_nodes == 5
    assert ring.delay_bound == 5
    assert worst_case_delay(ring) == 5

    dense = build_schedule(Teams(PAPER_DENSE_TEAMS))
    assert dense.teams.longest_shortest_path_nodes == 3
    assert dense.teams.diameter_edges == 2
    assert dense.delay_bound == 6
    assert (dense.period - 1) * dense.teams.diameter_edges == 4  # the paper's number
    assert worst_case_delay(dense) == 5
    # Not an artefact of the colouring order: every order gives T = 3 and 5.
    for order in itertools.permutations(range(5)):
        other = build_schedule(dense.teams, order)
        assert (other.period, worst_case_delay(other)) == (3, 5)


def test_worst_packet_of_g2_hand_traced():
    """r12 collects right after meeting T2 at epoch 2: T1 gets it at 4, T2 and
    T4 at 5, T5 at 6, T3 only at 7 -> 5 epochs."""
    dense = build_schedule(Teams(PAPER_DENSE_TEAMS))
    assert propagation_epochs(dense, 12, 2) == {0: 4, 1: 5, 3: 5, 4: 6, 2: 7}


def test_four_robot_ring_of_table_1():
    schedule = build_schedule(Teams(PAPER_FOUR_ROBOT_TEAMS))
    assert schedule.period == 2
    assert schedule.delay_bound == 3 == worst_case_delay(schedule)


# ------------------------------------------------------------ validation


def test_schedule_with_conflict_is_rejected():
    teams = Teams(PAPER_RING_TEAMS)
    with pytest.raises(ValueError, match="teams 0 and 1 share robot 12"):
        CommunicationSchedule(teams, (0, 0, 1, 0, 1, 0, 1, 1))


def test_schedule_with_gap_or_wrong_length_is_rejected():
    teams = Teams(PAPER_RING_TEAMS)
    with pytest.raises(ValueError, match=r"slot\(s\) \[1\] hold no team"):
        CommunicationSchedule(teams, (0, 2) * 4)
    with pytest.raises(ValueError, match="one slot per team"):
        CommunicationSchedule(teams, (0, 1))
    schedule = build_schedule(teams)
    with pytest.raises(ValueError, match="epoch"):
        schedule.team_at(12, 0)


def test_greedy_colouring_validation():
    with pytest.raises(ValueError, match="symmetric"):
        greedy_colouring(np.array([[0, 1], [0, 0]], dtype=bool))
    with pytest.raises(ValueError, match="permutation"):
        greedy_colouring(np.zeros((2, 2), dtype=bool), order=[0, 0])


# ---------------------------------------------------------- properties


@st.composite
def team_structures(draw):
    """Random connected graph of teams: a random spanning tree plus extra
    edges, one robot per edge (sometimes two robots on one edge); shuffled
    robot ids. Returns (Teams, colouring order)."""
    m = draw(st.integers(2, 9))
    edges = [(draw(st.integers(0, v - 1)), v) for v in range(1, m)]
    extra = draw(st.lists(st.tuples(st.integers(0, m - 1), st.integers(0, m - 1)), max_size=2 * m))
    edges += [(i, j) for i, j in extra if i != j]
    edges += draw(st.lists(st.sampled_from(edges), max_size=2))  # parallel robots
    ids = draw(st.permutations(range(100, 100 + len(edges))))
    members = [[] for _ in range(m)]
    for robot, (i, j) in zip(ids, edges):
        members[i].append(robot)
        members[j].append(robot)
    order = draw(st.permutations(range(m)))
    return Teams.from_lists(members), order


@settings(max_examples=150, deadline=None)
@given(team_structures())
def test_schedules_are_conflict_free_and_periodic(structure):
    teams, order = structure
    schedule = build_schedule(teams, order)
    period = schedule.period
    assert period <= teams.max_degree + 1
    horizon = 3 * period
    for robot in teams.robots:
        sequence = schedule.sequence(robot)
        i, j = teams.teams_of(robot)
        # Definition III.1: exactly one i, one j, X elsewhere.
        assert len(sequence) == period
        assert sorted(e for e in sequence if e is not IDLE) == [i, j]
    for epoch in range(1, horizon + 1):
        meeting = schedule.teams_meeting_at(epoch)
        # Conflict-free: no robot is needed by two teams in one epoch.
        robots = [r for team in meeting for r in teams.members[team]]
        assert len(robots) == len(set(robots))
        for team in range(teams.n_teams):
            # All members agree on the epochs their team meets.
            agree = {schedule.team_at(r, epoch) == team for r in teams.members[team]}
            assert agree == {schedule.meets(team, epoch)}
    for team in range(teams.n_teams):
        epochs = [k for k in range(1, horizon + 1) if schedule.meets(team, k)]
        # Exactly once in every window of T epochs.
        assert epochs == list(range(schedule.first_epoch(team), horizon + 1, period))
        assert schedule.next_meeting_epoch(team, 0) == epochs[0]


@settings(max_examples=100, deadline=None)
@given(team_structures())
def test_replayed_delays_respect_proposition_3_2(structure):
    teams, order = structure
    schedule = build_schedule(teams, order)
    worst = worst_case_delay(schedule)
    assert worst <= schedule.delay_bound
    # Every packet eventually reaches every team.
    robot = teams.robots[0]
    assert len(propagation_epochs(schedule, robot, 0)) == teams.n_teams
