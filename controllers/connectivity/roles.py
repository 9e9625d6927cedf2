"""Roles of Nestmeyer et al. 2017 and their switching: Algorithm 1, the Start-up procedure
and the 'prime traveler' election (Secs. 3.1-3.5).

``RoleMachine`` is the decision part of Algorithm 1 for all robots at once,
free of geometry: each control tick it is told, per robot, whether a
'connector' just extracted a target, whether a traveler is within R_z of its
target, whether an 'anchor' finished its task, and each traveler's remaining
path length; it returns the roles after the tick. Robots decide only on their
own state and on election messages that reached them: through
``election.FloodingNetwork`` over the current communication graph (the ideal
radio), or over the message bus (below).

Per robot i (Alg. 1):

- connector: when a target was extracted (line 5), become prime traveler if
  robot i holds the role token (line 7-8: "no prime traveler in the group"),
  secondary traveler otherwise (line 10);
- prime traveler: within R_z (line 12): open an election round ("permit
  candidacy within timeout", line 14), keep the role until the round is
  decided, then become anchor (line 15) and send the token to the winner;
- secondary traveler: within R_z (line 19): anchor (line 21); otherwise reply
  to every candidacy it receives (line 23) and become prime traveler when the
  token reaches it (line 24-25);
- anchor: when the task at the target is done (line 27): connector.

Start-up: robots with a target are secondary travelers (waiting for the
outcome), the others connectors; the host (robot 0, "robot 1" in the paper)
starts with the token and opens the first round at once, in which every robot
with a target replies, the host included (Sec. 3.3).

A token holder that is not a prime traveler (after a round with no
candidate, or a winner that reached its own target before the handover
arrived) keeps opening rounds back to back until it hands the token on, or
itself extracts a target as connector and becomes prime traveler.

Invariant: prime traveler => holds the token, and at most one robot holds it,
so there is never more than one prime traveler (Proposition 1), on any graph
sequence. With a connected graph at every tick, a waiting secondary traveler
becomes prime within about three election windows.

Over the message bus (a real radio, ``bus_period_s`` given): the election's
messages flood as ``"election"`` broadcasts (``election.BusFlooding``), and
the token goes hand to hand with ``protocols.TokenHandover`` over one
``protocols.ReliableLink`` per robot (acks, retransmission after
``HANDOVER_TIMEOUT_TICKS``, at most ``HANDOVER_MAX_ATTEMPTS`` copies): the
round's host offers it to the winner, and the winner becomes prime traveler
only when the host's confirm arrives, so two robots never hold it at once
whatever is lost. The offer carries the next epoch. If the offer is given up
(the winner out of reach), the host keeps the token and, no longer
travelling, opens a new round. If the confirm is given up
(``token_maybe_lost``: the winner acked the offer but may never have heard the
confirm), the host cannot take the token back, since the winner may hold it;
it re-sends the confirm as a new transfer until one is acknowledged
(``token_recoveries`` counts them), and the winner, while still waiting on
that offer, acts on whichever copy arrives. Until then nobody is prime
traveler and no round runs.

Deviations from the paper
-------------------------
- "No prime traveler in the group" is "holds the role token" (see
  election.py); the paper leaves the mechanism to a low-frequency flooding.
- If the round's winner is no longer a secondary traveler when the handover
  arrives (it reached its target meanwhile), it keeps the token and opens a
  new round instead of becoming prime traveler; the paper does not cover
  this race.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum

import numpy as np

from controllers.connectivity.election import (
    BusFlooding,
    Candidacy,
    ElectionRound,
    FloodingNetwork,
    Handover,
    Message,
    Reply,
    election_window_ticks,
)
from sim.compiled import kernel
from sim.radio.bus import INT32_BYTES
from sim.radio.bus import Message as BusMessage
from sim.radio.protocols import ReliableLink, TokenHandover

# The token's reliable link over the bus: a copy is sent again after this many control periods without an
# ack (an ack comes back two ticks after its copy when nothing waits in the queues), and given up after this
# many copies in all.
HANDOVER_TIMEOUT_TICKS = 5
HANDOVER_MAX_ATTEMPTS = 10
# Over the bus a robot forwards an election message for this many ticks after learning it: the first
# copy and two more against lost broadcasts (every tick until retired would fill a 250 kbit/s medium).
ELECTION_FORWARD_TICKS = 3


class _Sent:
    """The transport of the robots' reliable links: collects the tick's messages for ``Commands.outbox``."""

    def __init__(self) -> None:
        self.messages: list[BusMessage] = []

    def send(self, message: BusMessage, time_s: float) -> BusMessage:
        self.messages.append(message)
        return message


class Role(IntEnum):
    """Motion behaviours of Sec. 3.1, numbered as in the paper's Fig. 14d."""

    PRIME_TRAVELER = 1
    SECONDARY_TRAVELER = 2
    ANCHOR = 3
    CONNECTOR = 4


TRAVELERS = (Role.PRIME_TRAVELER, Role.SECONDARY_TRAVELER)

# The codes as plain ints for the per-tick comparisons: numpy compares an array with an IntEnum member
# about five times slower than with an int (same result).
PRIME_CODE, SECONDARY_CODE, ANCHOR_CODE, CONNECTOR_CODE = (int(role) for role in Role)


@dataclass(frozen=True)
class RoleChanges:
    """Roles after one tick and which robots switched into which role, all (N,)."""

    roles: np.ndarray  # Role codes (int)
    became_prime: np.ndarray  # bool
    became_anchor: np.ndarray  # bool
    became_connector: np.ndarray  # bool


class RoleMachine:
    """Algorithm 1 role switching with the token election, for N robots.

    latency_ticks: control ticks per message hop; host: start-up election host;
    bus_period_s: None for the in-process exchange over the adjacency (the
    ideal radio), or the control period, s, to exchange every message over the
    message bus (``step``'s ``inbox`` in, ``outbox`` out; see the module docstring).
    """

    def __init__(self, n_robots: int, latency_ticks: int = 1, host: int = 0,
                 bus_period_s: float | None = None) -> None:
        if not 0 <= host < n_robots:
            raise ValueError(f"host must be a robot index in [0, {n_robots}), got {host!r}")
        self.n_robots = n_robots
        self.host = host
        self.over_bus = bus_period_s is not None
        self.outbox: tuple[BusMessage, ...] = ()  # the messages of the last step (over the bus)
        self.token_recoveries = 0  # confirms re-sent after token_maybe_lost
        if self.over_bus:
            self.network = BusFlooding(n_robots, latency_ticks, ELECTION_FORWARD_TICKS)
            self._sent = _Sent()
            self.tokens = [TokenHandover(ReliableLink(self._sent, i, timeout_s=HANDOVER_TIMEOUT_TICKS * bus_period_s,
                                                      max_attempts=HANDOVER_MAX_ATTEMPTS))
                           for i in range(n_robots)]
            self._period_s = float(bus_period_s)
        else:
            self.network = FloodingNetwork(n_robots, latency_ticks)
        self._time_s = 0.0
        self.window_ticks = election_window_ticks(n_robots, latency_ticks)
        self.roles = np.full(n_robots, int(CONNECTOR_CODE))
        self.holds_token = np.zeros(n_robots, dtype=bool)
        self.next_epoch = np.zeros(n_robots, dtype=np.int64)  # meaningful at the token holder
        self.replied_epoch = np.full(n_robots, -1, dtype=np.int64)
        self.rounds: list[ElectionRound | None] = [None] * n_robots  # open round at its host
        self.started = False

    # -- queries ------------------------------------------------------------

    @property
    def prime(self) -> int:
        """Index of the prime traveler, -1 if none."""
        primes = np.flatnonzero(self.roles == PRIME_CODE)
        return int(primes[0]) if len(primes) else -1

    @property
    def token_in_flight(self) -> bool:
        """The token is between two robots: sent and not yet arrived (no robot holds it)."""
        if self.over_bus:
            return not any(token.acts_as_holder for token in self.tokens)
        return any(isinstance(m, Handover) for m in self.network.messages)

    # -- start-up -----------------------------------------------------------

    def start(self, has_target) -> None:
        """Start-up procedure, lines 1-11: travelers wait for the first round as secondary travelers."""
        has_target = np.asarray(has_target, dtype=bool)
        self.roles = np.where(has_target, int(SECONDARY_CODE), int(CONNECTOR_CODE))
        self.holds_token[:] = False
        self.holds_token[self.host] = True
        self.next_epoch[self.host] = 0
        if self.over_bus:
            self.tokens[self.host].state = "holder"
        self.started = True

    # -- one control tick ---------------------------------------------------

    def step(self, tick: int, adjacency, got_target, near_target, task_done, remaining, inbox=(),
             time_s: float | None = None) -> RoleChanges:
        """Advance Algorithm 1 by one control tick.

        tick: control tick counter (int); adjacency: (N, N) current graph (the
        in-process exchange's; unused over the bus); got_target: (N,) bool, a
        connector extracted a target and planned its path this tick;
        near_target: (N,) bool, ||q_i - z_i|| < R_z; task_done: (N,) bool, the
        anchor's dwell time elapsed; remaining: (N,) remaining path length
        d_gamma, m (read for travelers only). Over the bus: inbox, per robot the
        bus's deliveries since the last tick (``Observation.inbox``; () for
        none), and time_s, the tick's time, s (default tick * period); the
        messages to send are ``self.outbox`` afterwards.
        """
        if not self.started:
            raise RuntimeError("call start() before step()")
        before = self.roles.copy()
        got_target = np.asarray(got_target, dtype=bool)
        near_target = np.asarray(near_target, dtype=bool)
        task_done = np.asarray(task_done, dtype=bool)
        remaining = np.asarray(remaining, dtype=float)

        self._local_transitions(got_target, near_target, task_done)
        if self.over_bus:
            self._time_s = tick * self._period_s if time_s is None else float(time_s)
            self._sent.messages = []
            self._receive_token(inbox)
            self.network.receive(tick, inbox)
        for robot, message in self.network.delivered(tick):
            self._receive(robot, message, remaining, tick)
        holder = np.flatnonzero(self.holds_token)
        if len(holder):
            self._host(int(holder[0]), tick, near_target, remaining)
        if self.over_bus:
            self.outbox = (*self._sent.messages, *self.network.outbox(tick))
        else:
            self.network.exchange(adjacency, tick)

        roles = self.roles.copy()
        n = len(roles)
        became_prime, became_anchor, became_connector = (np.empty(n, dtype=bool) for _ in range(3))
        _switches(before, roles, became_prime, became_anchor, became_connector)
        return RoleChanges(roles=roles, became_prime=became_prime, became_anchor=became_anchor,
                           became_connector=became_connector)

    def _local_transitions(self, got_target: np.ndarray, near_target: np.ndarray, task_done: np.ndarray) -> None:
        """Each robot's own role switch, from its role before this tick (one switch per robot per tick)."""
        roles = self.roles
        starting = np.flatnonzero((roles == CONNECTOR_CODE) & got_target)
        arriving = (roles == SECONDARY_CODE) & near_target
        leaving = (roles == ANCHOR_CODE) & task_done
        roles[arriving] = ANCHOR_CODE
        roles[leaving] = CONNECTOR_CODE
        for i in starting:
            if self.holds_token[i]:
                roles[i] = PRIME_CODE
                self._close_round(int(i))  # the host needs no successor any more
            else:
                roles[i] = SECONDARY_CODE

    def _receive_token(self, inbox) -> None:
        """Over the bus: each robot's reliable link and token side read its deliveries of the tick."""
        time_s = self._time_s
        holds = self.holds_token.tolist()
        rows = inbox if inbox and any(inbox) else None  # None: no delivery in the rows (most ticks)
        for robot, token in enumerate(self.tokens):
            if ((rows is None or not rows[robot]) and not token.link.pending and not token.token_maybe_lost
                    and (holds[robot] or token.state != "holder")):
                continue  # nothing to read, resend or take up: the poll would return no events, and nothing acts
            handing_over = token.state == "handing_over"
            token.handle(token.link.poll(time_s, inbox[robot] if inbox else ()), time_s)
            if token.token_maybe_lost:
                token.resend_confirm(time_s)
                self.token_recoveries += 1
            if token.acts_as_holder and not self.holds_token[robot]:
                self.holds_token[robot] = True
                if not handing_over:  # the confirm arrived: the token, and the next epoch, are this robot's
                    self.next_epoch[robot] = token.token_data
                    if self.roles[robot] == SECONDARY_CODE:
                        self.roles[robot] = PRIME_CODE
                # else the offer was given up: the host keeps the token and opens a new round

    def _receive(self, robot: int, message: Message, remaining: np.ndarray, tick: int) -> None:
        if isinstance(message, Candidacy):
            if self.roles[robot] == SECONDARY_CODE and self.replied_epoch[robot] < message.epoch:
                self.replied_epoch[robot] = message.epoch
                self.network.broadcast(robot, Reply(message.epoch, robot, float(remaining[robot])), tick)
        elif isinstance(message, Reply):
            open_round = self.rounds[robot]
            if open_round is not None and open_round.epoch == message.epoch:
                open_round.enroll(message.sender, message.remaining)
        elif isinstance(message, Handover) and message.winner == robot:
            self.network.retire(lambda m: m == message)
            self.holds_token[robot] = True
            self.next_epoch[robot] = message.next_epoch
            if self.roles[robot] == SECONDARY_CODE:
                self.roles[robot] = PRIME_CODE

    def _host(self, host: int, tick: int, near_target: np.ndarray, remaining: np.ndarray) -> None:
        role = int(self.roles[host])
        if self.rounds[host] is None:
            if role == PRIME_CODE and not near_target[host]:
                return  # still travelling: no election yet
            # A prime traveler at its target (line 14), or an idle token holder.
            epoch = int(self.next_epoch[host])
            self.next_epoch[host] = epoch + 1
            self.rounds[host] = ElectionRound(epoch, host, tick + self.window_ticks)
            if role == SECONDARY_CODE:  # start-up: the host is a candidate too
                self.rounds[host].enroll(host, float(remaining[host]))
                self.replied_epoch[host] = epoch
            self.network.broadcast(host, Candidacy(epoch, host), tick)
        current = self.rounds[host]
        if tick < current.deadline:
            return
        if self.roles[host] != SECONDARY_CODE:
            current.withdraw(host)  # the host knows it is no longer travelling
        winner = current.winner()
        self._close_round(host)
        if self.roles[host] == PRIME_CODE:
            self.roles[host] = ANCHOR_CODE  # line 15: abdicate upon decision
        if winner is None:
            return  # keep the token; a new round opens next tick
        if winner == host:
            self.roles[host] = PRIME_CODE
            return
        self.holds_token[host] = False
        if self.over_bus:
            self.tokens[host].hand_over(winner, self._time_s, int(self.next_epoch[host]), INT32_BYTES)
        else:
            self.network.broadcast(host, Handover(current.epoch, winner, int(self.next_epoch[host])), tick)

    def _close_round(self, host: int) -> None:
        current = self.rounds[host]
        if current is None:
            return
        self.rounds[host] = None
        self.network.retire(lambda m: isinstance(m, (Candidacy, Reply)) and m.epoch == current.epoch, at=host)


@kernel
def _switches(before, roles, became_prime, became_anchor, became_connector):
    """Which robots switched into the prime, anchor and connector roles (one pass instead of nine numpy calls)."""
    for i in range(roles.shape[0]):
        became_prime[i] = roles[i] == PRIME_CODE and before[i] != PRIME_CODE
        became_anchor[i] = roles[i] == ANCHOR_CODE and before[i] != ANCHOR_CODE
        became_connector[i] = roles[i] == CONNECTOR_CODE and before[i] != CONNECTOR_CODE
