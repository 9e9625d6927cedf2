"""The continuous-connectivity method's reaction to a team mate that went silent (docs/faults.md).

Nestmeyer et al. 2017 assume robots never fail. Here a robot that the whole
team has stopped hearing is dropped from the team for good:

- **Who is dropped.** Under a real radio, robot j is dropped once every
  robot still in the team that ever heard j counts j as silent
  (``sim.radio.protocols.HeartbeatMonitor``: nothing from j for
  ``heartbeat_timeout_s``). Under ``ideal`` the in-process exchange reads the
  adjacency, the disk model: a link between every pair in range and line of
  sight, so a team mate in sight without a link hears nothing. Robot j is
  dropped on the first tick at which every team mate in range and sight of
  it has no link to it (detection is immediate, like a heartbeat timeout of
  one tick). Without a fault that never happens.
- **Its graph.** The dropped robot leaves the weights, lambda2, the
  gradient, the election, the consensus and the lambda2 estimator; its virtual point is frozen
  where it was (at rest), so it no longer drags the team nor is dragged by
  it, and the invariants (lambda2, R_c) are those of the team without it.
- **The token.** Every robot knows the last announced token holder (the
  round host's candidacy and the handover flood to everybody). When the
  dropped robot held it, or was the end of a transfer in progress, the token
  is gone with it: the robot in the team with the lowest index takes a new
  one, with an epoch above every epoch used so far (stale replies to the
  dead holder's rounds are ignored), and opens a round. A transfer towards
  the dropped robot is called off, and its sender holds the token again.
  Dropping is final, so the dead robot's token can never come back: never
  two prime travelers.
- **Its targets.** Its current target (unless already visited) and its
  queue go, each to the robot still in the team that had targets of its own
  (an explorer) and whose virtual point is nearest; with no explorer left
  they are lost. Both counts are kept per dropped robot.

The functions below act on the shared state of the exploration layer; the
strategy (strategy.py) calls them once per dropped robot.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controllers.connectivity.election import Handover, Reply
from controllers.connectivity.roles import CONNECTOR_CODE
from controllers.connectivity.targets import Target


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

    def summary(self) -> dict:
        return {"robot": self.robot, "dropped_at_s": self.at_s, "was_prime_traveler": self.was_prime,
                "held_token": self.held_token, "targets_reassigned": self.targets_reassigned,
                "targets_lost": self.targets_lost, "token_reissued_to": self.token_reissued_to}


def newly_silent(in_team: np.ndarray, links, heartbeats) -> list[int]:
    """Robots of the team that every team mate who ever heard them counts as silent now (``heartbeats``, a
    HeartbeatMonitor). Under ``ideal`` (``heartbeats`` None) the disk model links every pair in range and
    line of sight (``links``, the observation's): a team mate that sees j there without a link hears
    nothing from j, so j is silent once every team mate in range and sight of it has no link to it (and at
    least one has it in sight)."""
    out = []
    for j in np.flatnonzero(in_team):
        others = in_team.copy()
        others[j] = False
        if heartbeats is None:
            in_sight = others & links.line_of_sight[j]
            if in_sight.any() and not links.adjacency[j, in_sight].any():
                out.append(int(j))
            continue
        heard = others & np.isfinite(heartbeats.last_heard[:, j])
        if heard.any() and heartbeats.silent[heard, j].all():
            out.append(int(j))
    return out


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
