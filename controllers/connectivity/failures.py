"""The continuous-connectivity method's reaction to a team mate that went silent (docs/faults.md).

Nestmeyer et al. 2017 assume robots never fail. Here a robot that the whole
team has stopped hearing is dropped from the team, and taken back once it is
heard again (a healthy robot behind a blackout, say):

- **Who is dropped.** Under a real radio, robot j is dropped once every
  robot still in the team that ever heard j counts j as silent
  (``sim.radio.protocols.HeartbeatMonitor``: nothing from j for
  ``heartbeat_timeout_s``). Under ``ideal`` the in-process exchange reads the
  adjacency, the disk model: a link between every pair in range and line of
  sight, so a team mate in range and sight without a link hears nothing.
  Robot j is dropped on the first tick at which every team mate in range and
  sight of it has no link to it (detection is immediate, like a heartbeat
  timeout of one tick). Without a fault that never happens; a robot with no
  team mate in range at all is cut off, not silent: the graph split.
- **Its graph.** The dropped robot leaves the weights, lambda2, the
  gradient, the election, the consensus and the lambda2 estimator; its virtual point is frozen
  where it was (at rest), so it no longer drags the team nor is dragged by
  it, and the invariants (lambda2, R_c) are those of the team without it.
  Its body is still there: condition (c) of the weights keeps counting it,
  at its frozen virtual point, as a bystander (graph.link_weights), so its
  team mates keep clear of it.
- **The token.** Every robot knows the last announced token holder (the
  round host's candidacy and the handover flood to everybody). When the
  dropped robot held it, or was the end of a transfer in progress, the token
  is gone with it: the robot in the team with the lowest index takes a new
  one, with an epoch above every epoch used so far (stale replies to the
  dead holder's rounds are ignored), and opens a round. A transfer towards
  the dropped robot is called off, and its sender holds the token again.
  A dropped robot's token state is cleared at the drop, so a robot taken back
  returns as a connector without one: never two prime travelers.
- **Its targets.** Its current target (unless already visited) and its
  queue go, each to the robot still in the team that had targets of its own
  (an explorer) and whose virtual point is nearest; with no explorer left
  they are lost. Both counts are kept per dropped robot.
- **Its point, in the plans.** Its team mates keep clear of its frozen
  point (condition (c) counts it, graph.py); the path planner does too, so
  that no path leads a traveler through it (a prime traveler held 0.85 m
  from it by its collision factor, its path through the point, stalled a
  mission for good): a box round the point joins the planner's obstacles
  (``obstacles_with_dropped``) and every traveler replans. The box is a
  preference (ExplorationController._plan): where no path avoids it the
  scene's own obstacles decide, and only a target inside it is skipped.
- **Taking it back** (exact mode). A dropped robot is taken back once a robot
  of the team hears it again (under ``ideal``, a link to it; under a real
  radio, any message from it that arrived after its drop) and the team with
  it is connected over a strong link: a weight W_ij of at least
  ``TAKE_BACK_MIN_WEIGHT`` to a team mate (not a link about to fade, which
  would hold the team's lambda2 at the barrier), the team's graph with it
  connected, and its virtual point, frozen since the drop, no closer than R_c
  to any other. It comes back as a connector
  whose virtual point starts from rest where it was frozen; the targets
  handed on stay with their new explorers. A robot that really failed is
  never heard again, so it is never taken back. In estimator mode a dropped
  robot stays out: its estimator state (consensus averages of the team it
  left) would bias the team's averages, and the restart that would avoid it
  needs every robot to restart in the same tick.

The functions below act on the shared state of the exploration layer; the
strategy (strategy.py) calls them once per dropped robot.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controllers.connectivity.election import Handover, Reply
from controllers.connectivity.roles import CONNECTOR_CODE
from controllers.connectivity.targets import Target
from sim.geometry import Boxes


# A dropped robot is taken back only over a link at least this strong (W_ij in [0, 1]; 1 within R'_s in clear
# sight): taken back over a link at the edge of range, it would hold the team's lambda2 at the barrier (a robot
# left behind and heard again over a fading link brought lambda2 to 7e-8 in connected-office).
TAKE_BACK_MIN_WEIGHT = 0.5


@dataclass
class DroppedRobot:
    """What dropping one robot did, for metrics.json and the run's message."""

    robot: int
    at_s: float
    was_prime: bool
    held_token: bool
    targets_reassigned: int = 0
    targets_lost: int = 0
    token_reissued_to: int | None = None
    taken_back_at_s: float | None = None  # when the team took it back (heard again), s; None: still out

    def summary(self) -> dict:
        # Tick times are sums of the control period: rounded to the microsecond for metrics.json.
        return {"robot": self.robot, "dropped_at_s": round(self.at_s, 6), "was_prime_traveler": self.was_prime,
                "held_token": self.held_token, "targets_reassigned": self.targets_reassigned,
                "targets_lost": self.targets_lost, "token_reissued_to": self.token_reissued_to,
                "taken_back_at_s": None if self.taken_back_at_s is None else round(self.taken_back_at_s, 6)}


def newly_silent(in_team: np.ndarray, links, heartbeats, comm_range_m: float) -> list[int]:
    """Robots of the team that every live team mate who ever heard them counts as silent now (``heartbeats``,
    a HeartbeatMonitor). Under ``ideal`` (``heartbeats`` None) the disk model links every pair within
    ``comm_range_m`` and in line of sight (``links``, the observation's): a team mate there without a link
    hears nothing from j, so j is silent once every team mate in range and sight of it has no link to it.

    Only live witnesses count: a team mate that is itself silent now hears nobody, so its silence about j
    says nothing of j. A robot whose only witnesses are silent (its one neighbour failed) is not silent but
    cut off: the team's graph split, which the method's own invariant reports; so is a robot with no team
    mate in range at all."""
    witnesses = np.zeros((len(in_team), len(in_team)), dtype=bool)  # [j, i]: i's silence about j is evidence
    quiet = np.zeros(len(in_team), dtype=bool)  # [j]: every witness of j hears nothing from it
    for j in np.flatnonzero(in_team):
        others = in_team.copy()
        others[j] = False
        if heartbeats is None:
            witnesses[j] = others & links.line_of_sight[j] & (links.distance[j] <= comm_range_m)
            quiet[j] = witnesses[j].any() and not links.adjacency[j, witnesses[j]].any()
        else:
            witnesses[j] = others & np.isfinite(heartbeats.last_heard[:, j])
            quiet[j] = witnesses[j].any() and heartbeats.silent[witnesses[j], j].all()
    silent = quiet.copy()
    while True:  # until no silent robot rests on silent witnesses alone
        live = silent & (witnesses & ~silent[None, :]).any(axis=1)
        if np.array_equal(live, silent):
            return [int(j) for j in np.flatnonzero(silent)]
        silent = live


def obstacles_with_dropped(boxes: Boxes, points: np.ndarray, bounds: np.ndarray, params) -> Boxes:
    """The scene's ``boxes`` and, for the path planner, a box round each dropped robot's frozen point
    (``points`` (K, 3), m): wide enough that a path at the planner's preferred clearance passes it at R'_c
    (full weight) and one at its fallback clearance at R_c, and as tall as the scene (``bounds`` (2, 3))."""
    if not len(points):
        return boxes
    half_width = max(params.full_weight_robot_distance_m - params.path_clearance_m,
                     params.min_robot_distance_m - params.path_min_clearance_m, 0.01)
    centers = np.array(points, dtype=float).reshape(-1, 3).copy()
    centers[:, 2] = 0.5 * (bounds[0, 2] + bounds[1, 2])
    half = np.empty_like(centers)
    half[:, :2] = half_width
    half[:, 2] = max(0.5 * (bounds[1, 2] - bounds[0, 2]), half_width)
    extra = Boxes.axis_aligned(centers, half)
    return Boxes(np.concatenate([boxes.centers, extra.centers]), np.concatenate([boxes.half_sizes, extra.half_sizes]),
                 np.concatenate([boxes.rotations, extra.rotations]))


def heard_again(robot: int, dropped_at_s: float, in_team: np.ndarray, links, heartbeats) -> bool:
    """Whether a robot of the team hears the dropped ``robot`` again: under ``ideal`` (``heartbeats`` None)
    a link to it (``links``, the observation's); under a real radio a message from it that reached a team
    mate after ``dropped_at_s`` (a HeartbeatMonitor's ``last_heard``)."""
    if heartbeats is None:
        return bool(links.adjacency[robot, in_team].any())
    return bool((heartbeats.last_heard[in_team, robot] > dropped_at_s).any())


def _token_in_team(machine, in_team: np.ndarray) -> bool:
    """The token is with a robot of the team, or on its way between two of them."""
    if machine.holds_token[in_team].any():
        return True
    if machine.over_bus:
        return any(machine.tokens[i].state in ("holder", "handing_over", "pending") for i in np.flatnonzero(in_team))
    return any(isinstance(m, Handover) and in_team[m.winner] for m in machine.network.messages)


def drop_from_election(machine, robot: int, in_team: np.ndarray) -> tuple[bool, int | None]:
    """Take ``robot`` out of the role machine (roles.RoleMachine): a connector without token or round,
    out of every open round, every transfer towards it called off; a new token at the lowest-indexed
    robot of ``in_team`` (``robot`` already out) if the team no longer has one. Returns whether
    ``robot`` held the token and who got a new one (None: nobody needed one)."""
    if not machine.started:
        # Dropped before the start-up (a robot failing at 0 s): the start-up gives the token to its host.
        if machine.host != robot or not in_team.any():
            return False, None
        machine.host = int(np.flatnonzero(in_team)[0])
        return True, machine.host
    held = bool(machine.holds_token[robot]) or (machine.over_bus and machine.tokens[robot].state != "idle")
    machine.roles[robot] = CONNECTOR_CODE
    machine.holds_token[robot] = False
    machine._close_round(robot)
    for current in machine.rounds:
        if current is not None:
            current.withdraw(robot)
    if machine.over_bus:
        machine.tokens[robot].state = "idle"
        for i in np.flatnonzero(in_team):
            machine.tokens[i].call_off(robot)
            if machine.tokens[i].acts_as_holder:
                machine.holds_token[i] = True
    else:
        machine.network.retire(lambda m: (isinstance(m, Handover) and m.winner == robot)
                               or (isinstance(m, Reply) and m.sender == robot))
    if _token_in_team(machine, in_team) or not in_team.any():
        return held, None
    heir = int(np.flatnonzero(in_team)[0])
    machine.holds_token[heir] = True
    machine.next_epoch[heir] = int(max(machine.next_epoch.max(), machine.replied_epoch.max())) + 1
    if machine.over_bus:
        machine.tokens[heir].state = "holder"
    return True, heir


def reassign_targets(explorer, robot: int, in_team: np.ndarray, explorers: np.ndarray,
                     q: np.ndarray) -> tuple[int, int]:
    """Move ``robot``'s current target (not yet visited) and its queue to the nearest explorer of the team
    (by virtual point); (reassigned, lost: no explorer left)."""
    orphans: list[Target] = []
    current = explorer.targets[robot]
    if current is not None:
        orphans.append(current)
    explorer.targets[robot] = None
    explorer.paths[robot] = None
    explorer.arrival_time[robot] = np.nan
    explorer._target_table = None
    while (target := explorer.queues.pop(robot)) is not None:
        orphans.append(target)
    takers = np.array([i for i in explorers if in_team[i]], dtype=int)
    if not len(takers):
        return 0, len(orphans)
    for target in orphans:
        nearest = takers[int(np.argmin(np.linalg.norm(q[takers] - target.position, axis=1)))]
        explorer.queues.push(int(nearest), target.position, target.dwell_time)
    return len(orphans), 0
