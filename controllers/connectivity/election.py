"""Election of the 'prime traveler' by flooding (Nestmeyer et al. 2017, Sec. 3.3).

Messages travel by store-and-forward flooding (Lim and Kim 2001) over the
*current* communication graph: every robot that knows a message sends it to
all its neighbours at every control tick, and a message sent at tick t over
an edge present at tick t arrives at tick t + latency. If the graph is
connected at every tick, the set of robots knowing a message grows by at least
one per latency period, so a message reaches everybody within (N - 1) hops and
a reply comes back within 2 (N - 1) hops: the election window of the paper.

Protocol (one round, hosted by the robot that currently holds the role token):

1. the host floods ``Candidacy(epoch, host)``;
2. every 'secondary traveler' that receives it floods ``Reply(epoch, sender,
   remaining)`` with its remaining path length d_gamma (once per epoch);
3. after 2 (N - 1) hops the host picks argmin d_gamma (ties: lower index) among
   the replies that reached it and floods ``Handover(epoch, winner,
   next_epoch)``; the winner becomes 'prime traveler' only when the handover
   reaches it.

The right to be 'prime traveler' is this token: it is created once at the
start-up host, and only ever moves inside a ``Handover`` message, so at most
one robot holds it (or it is in flight) at any time, whatever the graph does.
``roles.RoleMachine`` decides when rounds start and what the token holder
does; this module only moves messages and tallies a round.

Two networks carry the messages. ``FloodingNetwork`` is the in-process
exchange over the adjacency matrix, used under the ideal radio (one hop per
``latency_ticks``). ``BusFlooding`` is the same flooding as messages on the
message bus (sim.radio.bus), used under a real radio: each tick every robot
sends one ``"election"`` broadcast carrying the messages it forwards
(``election_bytes``: their real encoded size), and a robot learns a message
only when a broadcast carrying it reaches it (``Observation.inbox``); lost
broadcasts are simply not heard. The election window is then a time bound:
the host decides 2 (N - 1) latency periods after opening the round, with the
replies that reached it by then. Over the bus the token does not travel in a
``Handover`` but hand to hand (roles.py, ``protocols.TokenHandover``).

Deviations from the paper
-------------------------
- The paper's "no 'prime traveler' in the group" (Alg. 1 line 7, assessed
  "by flooding on a low frequency", footnote 4) is realised by the token: a
  host without a travelling role keeps running rounds back to back, which is
  that low-frequency flooding, and hands the token to the first candidate.
- Each message is retired from the in-process network once it is obsolete
  (its round decided, or the handover delivered); a real network would stop
  forwarding it after a time-to-live. Over the bus a robot forwards a message
  for ``forward_ticks`` ticks after it learned it (a time-to-live), and the
  host stops forwarding its round's messages once the round is closed.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Union

import numpy as np

from sim.compiled import kernel
from sim.radio.bus import FLOAT64_BYTES, INDEX_BYTES, INT32_BYTES
from sim.radio.bus import Message as BusMessage

# "Never learned" for the per-robot arrival ticks.
_NEVER = np.iinfo(np.int64).max


@dataclass(frozen=True)
class Candidacy:
    """Announcement of an election round: 'prime traveler' candidacy is open."""

    epoch: int
    host: int


@dataclass(frozen=True)
class Reply:
    """A 'secondary traveler' enrolling as candidate with its remaining path length, m."""

    epoch: int
    sender: int
    remaining: float


@dataclass(frozen=True)
class Handover:
    """The round's result; carries the role token (and the next epoch number) to ``winner``."""

    epoch: int
    winner: int
    next_epoch: int


Message = Union[Candidacy, Reply, Handover]


# Encoded sizes on the air, bytes: a one-byte type tag, epochs as int32, robots as uint16, lengths as float64.
_TAG_BYTES = 1
MESSAGE_BYTES = {
    Candidacy: _TAG_BYTES + INT32_BYTES + INDEX_BYTES,
    Reply: _TAG_BYTES + INT32_BYTES + INDEX_BYTES + FLOAT64_BYTES,
    Handover: _TAG_BYTES + INT32_BYTES + INDEX_BYTES + INT32_BYTES,
}
ELECTION_KIND = "election"


def election_bytes(messages) -> int:
    """Size of one election broadcast carrying ``messages``, bytes."""
    return sum(MESSAGE_BYTES[type(m)] for m in messages)


def election_window_ticks(n_robots: int, latency_ticks: int) -> int:
    """Ticks a host waits for replies: 2 (N - 1) hops (Sec. 3.3)."""
    return 2 * (n_robots - 1) * latency_ticks


class FloodingNetwork:
    """Store-and-forward flooding with a latency of ``latency_ticks`` per hop.

    Per tick: ``delivered(tick)`` (what reached each robot this tick), then the
    robots act and ``broadcast`` new messages, then ``exchange(adjacency,
    tick)`` sends everything each robot knows to its current neighbours.
    """

    def __init__(self, n_robots: int, latency_ticks: int = 1) -> None:
        if n_robots < 1:
            raise ValueError(f"n_robots must be positive, got {n_robots!r}")
        if not (isinstance(latency_ticks, (int, np.integer)) and latency_ticks >= 1):
            raise ValueError(f"latency_ticks must be an integer >= 1, got {latency_ticks!r}")
        self.n_robots = n_robots
        self.latency_ticks = int(latency_ticks)
        self.messages: list[Message] = []
        self._origins: list[int] = []
        self._known_at = np.zeros((0, n_robots), dtype=np.int64)  # tick each robot learned each message

    def broadcast(self, sender: int, message: Message, tick: int) -> None:
        """``sender`` starts flooding ``message`` at ``tick``."""
        row = np.full((1, self.n_robots), _NEVER, dtype=np.int64)
        row[0, sender] = tick
        self.messages.append(message)
        self._origins.append(sender)
        self._known_at = np.vstack([self._known_at, row])

    def exchange(self, adjacency, tick: int) -> None:
        """Every robot that knows a message by ``tick`` sends it to its neighbours
        in ``adjacency`` (N, N) (bool or weights > 0); it arrives ``latency`` ticks later."""
        if not self.messages:
            return
        links = np.asarray(adjacency)
        if links.dtype != np.bool_:
            links = links > 0
        known_at = self._known_at.copy()  # (a new array: callers may hold the previous one)
        _flood(known_at, links, int(tick), int(tick + self.latency_ticks))
        self._known_at = known_at

    def delivered(self, tick: int) -> list[tuple[int, Message]]:
        """(receiver, message) pairs for messages reaching a robot exactly at ``tick``."""
        rows, robots = np.nonzero(self._known_at == tick)
        return [
            (int(j), self.messages[m]) for m, j in zip(rows, robots) if j != self._origins[m]
        ]

    def knows(self, message: Message, tick: int) -> np.ndarray:
        """Boolean (N,): which robots have received ``message`` by ``tick``."""
        return self._known_at[self.messages.index(message)] <= tick

    def retire(self, obsolete: Callable[[Message], bool], at: int | None = None) -> None:
        """Stop forwarding every message for which ``obsolete(message)`` is true (everywhere: the
        in-process network ignores ``at``, the robot that knows it is obsolete)."""
        keep = [not obsolete(m) for m in self.messages]
        self.messages = [m for m, k in zip(self.messages, keep) if k]
        self._origins = [o for o, k in zip(self._origins, keep) if k]
        self._known_at = self._known_at[np.array(keep, dtype=bool)] if self.messages else self._known_at[:0]


class BusFlooding:
    """Store-and-forward flooding as messages on the message bus, per robot.

    Per tick: ``receive(tick, inbox)`` (the bus's deliveries of the last tick),
    ``delivered(tick)`` (what each robot learned, first time only), the robots
    act and ``broadcast``, then ``outbox(tick)``: one ``"election"`` broadcast
    per robot that forwards anything. A robot forwards a message from the tick
    it learns it for ``forward_ticks`` ticks (None: until retired). A hop
    takes one tick on the bus; ``latency_ticks`` > 1 holds what arrived back
    for the rest of the latency, as the in-process network does.
    """

    def __init__(self, n_robots: int, latency_ticks: int = 1, forward_ticks: int | None = None) -> None:
        if n_robots < 1:
            raise ValueError(f"n_robots must be positive, got {n_robots!r}")
        if not (isinstance(latency_ticks, (int, np.integer)) and latency_ticks >= 1):
            raise ValueError(f"latency_ticks must be an integer >= 1, got {latency_ticks!r}")
        if forward_ticks is not None and forward_ticks < 1:
            raise ValueError(f"forward_ticks must be >= 1 or None, got {forward_ticks!r}")
        self.n_robots = n_robots
        self.latency_ticks = int(latency_ticks)
        self.forward_ticks = forward_ticks
        self._seen: list[set[Message]] = [set() for _ in range(n_robots)]  # every message ever learned
        self._forwarding: list[dict[Message, int]] = [{} for _ in range(n_robots)]  # message -> tick learned
        self._arriving: list[tuple[int, int, Message]] = []  # (tick learned, robot, message), in arrival order

    def broadcast(self, sender: int, message: Message, tick: int) -> None:
        """``sender`` starts flooding ``message`` at ``tick``."""
        self._seen[sender].add(message)
        self._forwarding[sender][message] = tick

    def receive(self, tick: int, inbox) -> None:
        """Read the election broadcasts among ``inbox[robot]`` (``Delivery``s of the bus) at ``tick``."""
        if not any(inbox):  # no delivery in the rows (most ticks)
            return
        due = tick + self.latency_ticks - 1
        for robot, deliveries in enumerate(inbox):
            for delivery in deliveries:
                message = delivery.message
                if message.kind != ELECTION_KIND or delivery.receiver != robot:
                    continue
                for carried in message.payload:
                    if carried not in self._seen[robot]:
                        self._seen[robot].add(carried)
                        self._arriving.append((due, robot, carried))

    def delivered(self, tick: int) -> list[tuple[int, Message]]:
        """(receiver, message) pairs for messages a robot learns exactly at ``tick``; it forwards them from now."""
        if not self._arriving:
            return []
        now = [(robot, message) for due, robot, message in self._arriving if due == tick]
        self._arriving = [entry for entry in self._arriving if entry[0] > tick]
        for robot, message in now:
            self._forwarding[robot][message] = tick
        return now

    def knows(self, message: Message, robot: int) -> bool:
        return message in self._seen[robot]

    def retire(self, obsolete: Callable[[Message], bool], at: int | None = None) -> None:
        """Robot ``at`` (every robot if None) stops forwarding every message for which ``obsolete`` is true."""
        for robot in range(self.n_robots) if at is None else (at,):
            forwarding = self._forwarding[robot]
            for message in [m for m in forwarding if obsolete(m)]:
                del forwarding[message]

    def outbox(self, tick: int) -> list[BusMessage]:
        """This tick's election broadcasts, one per robot that forwards anything."""
        if not any(self._forwarding):  # nobody forwards anything (most ticks)
            return []
        messages = []
        for robot, forwarding in enumerate(self._forwarding):
            if not forwarding:
                continue  # nothing to expire or to send (most robots, most ticks)
            if self.forward_ticks is not None:
                for message in [m for m, learned in forwarding.items() if tick - learned >= self.forward_ticks]:
                    del forwarding[message]
            if forwarding:
                carried = tuple(forwarding)
                # A newer broadcast carries all an unsent one would (bar what expired): it replaces it.
                messages.append(BusMessage(ELECTION_KIND, robot, None, carried, election_bytes(carried),
                                           latest_only=True))
        return messages


@kernel
def _flood(known_at, links, tick, arrival):
    """One exchange in place: robot j learns message m at ``arrival`` if a neighbour i (links[i, j])
    knows it by ``tick`` and j would not know it earlier. Arrival ticks are > tick, so who is
    informed does not change during the pass."""
    n_messages, n = known_at.shape
    for m in range(n_messages):
        for j in range(n):
            if known_at[m, j] <= arrival:
                continue
            for i in range(n):
                if links[i, j] and known_at[m, i] <= tick:
                    known_at[m, j] = arrival
                    break


@dataclass
class ElectionRound:
    """A round as seen by its host: who enrolled, and when to decide (tick)."""

    epoch: int
    host: int
    deadline: int
    candidates: dict[int, float] = field(default_factory=dict)  # robot -> remaining path length, m

    def enroll(self, robot: int, remaining: float) -> None:
        self.candidates[robot] = float(remaining)

    def withdraw(self, robot: int) -> None:
        self.candidates.pop(robot, None)

    def winner(self) -> int | None:
        """argmin of the remaining path length; the lower index on ties; None if nobody enrolled."""
        if not self.candidates:
            return None
        return min(self.candidates, key=lambda robot: (self.candidates[robot], robot))
