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

Deviations from the paper
-------------------------
- The paper's "no 'prime traveler' in the group" (Alg. 1 line 7, assessed
  "by flooding on a low frequency", footnote 4) is realised by the token: a
  host without a travelling role keeps running rounds back to back, which is
  that low-frequency flooding, and hands the token to the first candidate.
- Each message is retired from the simulated network once it is obsolete
  (its round decided, or the handover delivered); a real network would stop
  forwarding it after a time-to-live.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Union

import numpy as np

from sim.compiled import kernel

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

    def retire(self, obsolete: Callable[[Message], bool]) -> None:
        """Stop forwarding every message for which ``obsolete(message)`` is true."""
        keep = [not obsolete(m) for m in self.messages]
        self.messages = [m for m, k in zip(self.messages, keep) if k]
        self._origins = [o for o, k in zip(self._origins, keep) if k]
        self._known_at = self._known_at[np.array(keep, dtype=bool)] if self.messages else self._known_at[:0]


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
