"""Delivery that must succeed, above the message bus: a reliable link and a token handed hand to hand.

``ReliableLink`` is one robot's endpoint. Each message it sends carries a
transfer number (the link's own sequence numbers, one per endpoint; the
bus's ``sequence`` changes with each retransmission). The receiver answers
every copy with a small ack (``<kind>_ack``, ``ACK_BYTES``), which travels
through the bus and can be lost like anything else, and passes a transfer to
the application only the first time it arrives (duplicate suppression by
sender and transfer number). The sender retransmits after ``timeout_s``
without an ack, at most ``max_attempts`` times in all, then gives up. An
ack is only ever sent for a copy that arrived, so a transfer the sender sees
acknowledged was delivered; a transfer it gave up on may still have been
delivered (every ack lost), which the caller must allow for.

``TokenHandover`` passes one token (the intermittent method's handover
token, a leader's role) with a three-way exchange, so that two robots never
act as holder at once, whatever is lost:

1. the holder sends an *offer* reliably and stops acting (``handing_over``);
2. the receiver takes it as ``pending`` (it does not act) and acks it;
3. on the ack, the old holder becomes ``idle`` and sends a *confirm*
   reliably; the receiver acts as holder once the confirm for one of the
   offers it is pending on arrives.

A receiver keeps every offer it is pending on, not only the latest: a late
copy of an offer its sender gave up on can arrive after a newer offer, and
the confirm that comes is the newer one's. Acting on a confirm for any of
them is safe: a confirm is sent only for an acknowledged offer, by a sender
that stopped acting when the ack came, and nobody else can hold the token
before this robot passes it on.

If the offer is given up (no ack after every attempt) the old holder takes
the token back: it never sent, and never will send, that offer's confirm, so
the receiver stays pending and never acts on it. A lost ack therefore only
delays: the receiver waits pending, the sender retransmits, the receiver acks
the duplicate. The price of safety is liveness in one case: if the confirm is
given up, nobody may hold the token (``token_maybe_lost`` at the old holder).
The old holder cannot take it back (the receiver may have it), but it can
finish the handover: ``resend_confirm`` sends the same confirm again as a new
transfer, which the receiver acts on only while still pending on that offer.

An offer may carry the application's data with the token (``hand_over``'s
``data``); the new holder reads it as ``token_data``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from sim.compiled import kernel
from sim.radio.bus import INT32_BYTES, Delivery, Message

RELIABLE_HEADER_BYTES = INT32_BYTES  # the transfer number
ACK_BYTES = INT32_BYTES  # an ack carries the transfer number it answers
TOKEN_BYTES = INT32_BYTES  # an offer or a confirm: the offer's transfer number


class Transport(Protocol):
    """Where messages go: ``MessageBus`` or a test's scripted channel."""

    def send(self, message: Message, time_s: float) -> Message: ...


class Outbox:
    """A ``Transport`` that keeps what is sent for ``Commands.outbox``: the loop hands it to the bus."""

    def __init__(self) -> None:
        self._messages: list[Message] = []

    def send(self, message: Message, time_s: float) -> Message:
        self._messages.append(message)
        return message

    def drain(self) -> tuple[Message, ...]:
        """The messages sent since the last drain, in order."""
        messages, self._messages = tuple(self._messages), []
        return messages


def deliveries_of(inbox: Any, robot: int, kind: str) -> list[Delivery]:
    """``robot``'s deliveries in an ``Observation.inbox`` that belong to ``kind``'s reliable
    exchange (its data and its acks), so that one endpoint never answers another's messages."""
    if not inbox or robot >= len(inbox):
        return []
    ack = f"{kind}_ack"
    return [d for d in inbox[robot] if d.message.kind == kind or d.message.kind == ack]


@dataclass(frozen=True)
class ReliableData:
    """The payload of a reliable message on the bus."""

    transfer: int
    data: Any


@dataclass(frozen=True)
class Ack:
    transfer: int


@dataclass(frozen=True)
class Received:
    """A transfer handed to the application, once."""

    sender: int
    kind: str
    transfer: int
    data: Any
    arrival_s: float


@dataclass(frozen=True)
class LinkEvents:
    """What one ``poll`` found: first arrivals, and the endpoint's own transfers acknowledged or given up."""

    received: tuple[Received, ...] = ()
    acknowledged: tuple[int, ...] = ()
    gave_up: tuple[int, ...] = ()


_NO_EVENTS = LinkEvents()  # a poll that found nothing (frozen: shared)


@dataclass
class _Outgoing:
    kind: str
    receiver: int
    data: Any
    size_bytes: int
    attempts: int
    last_sent_s: float


class ReliableLink:
    """One robot's endpoint: sequence numbers, acks, retransmission, give-up, duplicate suppression."""

    def __init__(self, transport: Transport, robot: int, *, timeout_s: float, max_attempts: int) -> None:
        if timeout_s <= 0 or max_attempts < 1:
            raise ValueError("timeout_s must be > 0 and max_attempts >= 1")
        self.transport = transport
        self.robot = robot
        self.timeout_s = float(timeout_s)
        self.max_attempts = int(max_attempts)
        self._next_transfer = 0
        self._outgoing: dict[int, _Outgoing] = {}
        self._seen: set[tuple[int, int]] = set()
        self.delivered: set[int] = set()  # transfers whose ack came back
        self.given_up: set[int] = set()

    def send(self, kind: str, receiver: int, data: Any, size_bytes: int, time_s: float) -> int:
        """Send ``data`` (``size_bytes`` of application payload) to ``receiver``; returns the transfer number."""
        transfer = self._next_transfer
        self._next_transfer += 1
        self._outgoing[transfer] = _Outgoing(kind, receiver, data, int(size_bytes), 1, float(time_s))
        self._put(transfer, self._outgoing[transfer], time_s)
        return transfer

    def _put(self, transfer: int, out: _Outgoing, time_s: float) -> None:
        self.transport.send(Message(out.kind, self.robot, (out.receiver,), ReliableData(transfer, out.data),
                                    out.size_bytes + RELIABLE_HEADER_BYTES), time_s)

    def status(self, transfer: int) -> str:
        """'pending', 'delivered' (acknowledged) or 'gave_up'."""
        if transfer in self.delivered:
            return "delivered"
        if transfer in self.given_up:
            return "gave_up"
        if transfer in self._outgoing:
            return "pending"
        raise KeyError(f"robot {self.robot} has no transfer {transfer}")

    @property
    def pending(self) -> int:
        return len(self._outgoing)

    def poll(self, time_s: float, deliveries: list[Delivery]) -> LinkEvents:
        """Read this robot's deliveries of the tick, ack data, then retransmit or give up what timed out.

        Deliveries that are not reliable data or acks are ignored.
        """
        if not deliveries and not self._outgoing:
            return _NO_EVENTS
        received: list[Received] = []
        acknowledged: list[int] = []
        for delivery in deliveries:
            message = delivery.message
            if delivery.receiver != self.robot:
                continue
            if isinstance(message.payload, ReliableData):
                transfer = message.payload.transfer
                self.transport.send(Message(f"{message.kind}_ack", self.robot, (message.sender,), Ack(transfer),
                                            ACK_BYTES), time_s)
                if (message.sender, transfer) not in self._seen:
                    self._seen.add((message.sender, transfer))
                    received.append(Received(message.sender, message.kind, transfer, message.payload.data,
                                             delivery.arrival_s))
            elif isinstance(message.payload, Ack):
                out = self._outgoing.get(message.payload.transfer)
                if out is not None and out.receiver == message.sender:
                    del self._outgoing[message.payload.transfer]
                    self.delivered.add(message.payload.transfer)
                    acknowledged.append(message.payload.transfer)
        gave_up: list[int] = []
        for transfer, out in list(self._outgoing.items()):
            if time_s - out.last_sent_s < self.timeout_s - 1e-12:
                continue
            if out.attempts >= self.max_attempts:
                del self._outgoing[transfer]
                self.given_up.add(transfer)
                gave_up.append(transfer)
            else:
                out.attempts += 1
                out.last_sent_s = float(time_s)
                self._put(transfer, out, time_s)
        if not (received or acknowledged or gave_up):
            return _NO_EVENTS
        return LinkEvents(tuple(received), tuple(acknowledged), tuple(gave_up))


@dataclass(frozen=True)
class TokenOffer:
    data: Any = None  # what travels with the token (the application's)


@dataclass(frozen=True)
class TokenConfirm:
    offer: int  # the offer's transfer number at the old holder


@dataclass
class TokenHandover:
    """One robot's side of the token. ``acts_as_holder`` is the only state that may use the token."""

    link: ReliableLink
    state: str = "idle"  # 'holder', 'handing_over', 'pending', 'idle'
    token_maybe_lost: bool = False  # a confirm this robot sent was given up
    token_data: Any = None  # the data of the offer this robot acts on, once it holds the token
    _offer: tuple[int, int] | None = field(default=None, repr=False)  # (transfer, receiver) while handing over
    _confirm: int | None = field(default=None, repr=False)  # transfer of the confirm in flight
    _pending: dict[tuple[int, int], Any] = field(default_factory=dict, repr=False)  # (sender, offer) -> data
    _confirmed: tuple[int, int] | None = field(default=None, repr=False)  # (offer, receiver) of the last confirm

    OFFER_KIND = "handover"
    CONFIRM_KIND = "handover_confirm"

    @property
    def acts_as_holder(self) -> bool:
        return self.state == "holder"

    def hand_over(self, receiver: int, time_s: float, data: Any = None, data_bytes: int = 0) -> None:
        """Offer the token (with ``data``, ``data_bytes`` on the air) to ``receiver``; from now on this robot
        does not act as holder."""
        if self.state != "holder":
            raise RuntimeError(f"robot {self.link.robot} does not hold the token (state {self.state!r})")
        transfer = self.link.send(self.OFFER_KIND, receiver, TokenOffer(data), TOKEN_BYTES + int(data_bytes),
                                  time_s)
        self._offer = (transfer, receiver)
        self.state = "handing_over"

    def handle(self, events: LinkEvents, time_s: float) -> None:
        """Advance on this robot's link events of the tick."""
        if events is _NO_EVENTS:
            return
        for transfer in events.acknowledged:
            if self.state == "handing_over" and self._offer is not None and transfer == self._offer[0]:
                offer, receiver = self._offer
                self._confirm = self.link.send(self.CONFIRM_KIND, receiver, TokenConfirm(offer), TOKEN_BYTES,
                                               time_s)
                self._confirmed = (offer, receiver)
                self._offer = None
                self.state = "idle"
        for transfer in events.gave_up:
            if self.state == "handing_over" and self._offer is not None and transfer == self._offer[0]:
                # No ack, so no confirm was sent or ever will be: the receiver cannot act on this offer.
                self._offer = None
                self.state = "holder"
            elif transfer == self._confirm:
                self.token_maybe_lost = True
        for got in events.received:
            if got.kind == self.OFFER_KIND and isinstance(got.data, TokenOffer) and self.state in ("idle", "pending"):
                self._pending[(got.sender, got.transfer)] = got.data.data
                self.state = "pending"
            elif (got.kind == self.CONFIRM_KIND and isinstance(got.data, TokenConfirm) and self.state == "pending"
                  and (got.sender, got.data.offer) in self._pending):
                self.token_data = self._pending[(got.sender, got.data.offer)]
                self._pending = {}
                self.state = "holder"

    def call_off(self, peer: int) -> None:
        """Forget every transfer with ``peer``, a robot that will never answer again (dropped as failed):
        an offer to it is taken back (this robot holds the token again), a confirm to it is no longer
        re-sent, and an offer from it no longer awaited."""
        if self.state == "handing_over" and self._offer is not None and self._offer[1] == peer:
            self._offer, self.state = None, "holder"
        if self._confirmed is not None and self._confirmed[1] == peer:
            self._confirmed, self._confirm, self.token_maybe_lost = None, None, False
        if self.state == "pending":
            self._pending = {offer: data for offer, data in self._pending.items() if offer[0] != peer}
            if not self._pending:
                self.state = "idle"

    def resend_confirm(self, time_s: float) -> None:
        """After ``token_maybe_lost``: send the last confirm again, as a new reliable transfer.

        Safe whatever happened: the receiver acts on it only while pending on
        that very offer, and this robot gave the token up when the offer was
        acknowledged, so it never acts as holder meanwhile."""
        if not self.token_maybe_lost or self._confirmed is None:
            raise RuntimeError(f"robot {self.link.robot} has no confirm given up")
        offer, receiver = self._confirmed
        self._confirm = self.link.send(self.CONFIRM_KIND, receiver, TokenConfirm(offer), TOKEN_BYTES, time_s)
        self.token_maybe_lost = False


class HeartbeatMonitor:
    """Every robot's view of whom it still hears: a neighbour silent for ``timeout_s`` counts as failed.

    Any delivery counts as a heartbeat (the methods' periodic broadcasts, such as the consensus, are
    heartbeats already). Robot i declares robot j silent once it has heard j at least once and nothing
    from j has reached it for longer than ``timeout_s``; hearing j again withdraws it. Robot i learns
    nothing else: the monitor reads only i's own inbox, never the simulator's truth.
    """

    def __init__(self, n_robots: int, timeout_s: float, neighbours_at_start: np.ndarray | None = None,
                 start_s: float = 0.0):
        """``neighbours_at_start``: (N, N) bool, the pairs linked when the team starts (it knows its roster and
        starts connected), counted as heard at ``start_s``, so a robot that fails before its first message
        still falls silent."""
        self.timeout_s = float(timeout_s)
        self.last_heard = np.full((n_robots, n_robots), -np.inf)  # [receiver, sender] -> last arrival, s
        if neighbours_at_start is not None:
            self.last_heard[np.asarray(neighbours_at_start, dtype=bool)] = float(start_s)
        self.silent = np.zeros((n_robots, n_robots), dtype=bool)  # [receiver, sender]: declared silent
        self.detections: list[tuple[float, int, int]] = []  # (t, receiver, sender): each declaration
        self.withdrawn: list[tuple[float, int, int]] = []  # (t, receiver, sender): heard again
        # Per sender, the times at which a first robot declared it silent while none did: when its silence
        # was detected (a failure's detection time is the first of these after it).
        self.silence_detected_s: list[list[float]] = [[] for _ in range(n_robots)]
        self._back = np.empty(64, dtype=np.int64)  # step's scratch: the entries heard again
        self._quiet = np.empty((2, n_robots * n_robots), dtype=np.int64)  # and the quiet pairs

    def step(self, time_s: float, inbox: tuple[tuple[Delivery, ...], ...], arrivals: Any = None
             ) -> list[tuple[int, int]]:
        """Take this tick's inbox (per receiver) and the bus's columns of messages sent as arrays
        (``Observation.arrivals``, or None) at ``time_s`` (s); the pairs (receiver, sender) declared
        silent now."""
        last, silent = self.last_heard, self.silent
        for receiver, row in (enumerate(inbox) if any(inbox) else ()):
            if not row:
                continue
            for delivery in row:
                sender = delivery.message.sender
                last[receiver, sender] = max(last[receiver, sender], delivery.arrival_s)
                if silent[receiver, sender]:
                    silent[receiver, sender] = False
                    self.withdrawn.append((time_s, receiver, sender))
        kinds = tuple(arrivals.values()) if arrivals else ()
        if len(kinds) > 1:
            for columns in kinds[:-1]:
                back = np.empty(len(columns), dtype=np.int64)
                for k in back[:_hear_columns(columns.receiver, columns.sender, columns.arrival_s, last, silent, back)]:
                    self.withdrawn.append((time_s, int(columns.receiver[k]), int(columns.sender[k])))
        if kinds:  # the last kind's columns read in the same compiled call as the search for quiet pairs
            columns = kinds[-1]
            if len(self._back) < columns.receiver.shape[0]:
                self._back = np.empty(2 * columns.receiver.shape[0], dtype=np.int64)
            back = self._back
            heard_again, found = _hear_columns_then_quiet_pairs(columns.receiver, columns.sender, columns.arrival_s,
                                                                last, silent, back, time_s - self.timeout_s,
                                                                self._quiet)
            for k in (back[:heard_again].tolist() if heard_again else ()):
                self.withdrawn.append((time_s, int(columns.receiver[k]), int(columns.sender[k])))
            if not found:
                return []
            quiet = self._quiet[:, :found]
        else:
            quiet = _quiet_pairs(last, silent, time_s - self.timeout_s)
        if not quiet.shape[1]:
            return []
        new = list(zip(quiet[0].tolist(), quiet[1].tolist()))
        for sender in {j for _, j in new}:
            if not silent[:, sender].any():
                self.silence_detected_s[sender].append(float(time_s))
        for receiver, sender in new:
            silent[receiver, sender] = True
            self.detections.append((time_s, receiver, sender))
        return new


@kernel
def _hear_columns(receiver, sender, arrival_s, last_heard, silent, back):
    """``HeartbeatMonitor.step``'s reading of one delivery, for each entry of a bus's columns in order: the
    latest arrival per (receiver, sender), and a silent pair heard again no longer silent (its entry's index
    put in ``back``). Returns how many came back."""
    count = 0
    for d in range(receiver.shape[0]):
        r, s = receiver[d], sender[d]
        last_heard[r, s] = max(last_heard[r, s], arrival_s[d])
        if silent[r, s]:
            silent[r, s] = False
            back[count] = d
            count += 1
    return count


@kernel
def _hear_columns_then_quiet_pairs(receiver, sender, arrival_s, last_heard, silent, back, before_s, quiet):
    """``_hear_columns`` and then ``_write_quiet_pairs`` in one call (each compiled call costs microseconds of
    arguments), the quiet pairs written into ``quiet`` ((2, N M): a returned array costs its boxing each call):
    (how many came back, how many pairs are quiet)."""
    heard_again = _hear_columns(receiver, sender, arrival_s, last_heard, silent, back)
    return heard_again, _write_quiet_pairs(last_heard, silent, before_s, quiet)


@kernel
def _write_quiet_pairs(last_heard, silent, before_s, quiet):
    """The pairs (receiver, sender), row-major as ``numpy.nonzero`` lists them, heard at least once, last
    before ``before_s`` and not yet silent, written into the columns of ``quiet`` ((2, N M)): how many."""
    n, m = last_heard.shape
    found = 0
    for i in range(n):
        for j in range(m):
            heard = last_heard[i, j]
            if np.isfinite(heard) and heard < before_s and not silent[i, j]:
                quiet[0, found] = i
                quiet[1, found] = j
                found += 1
    return found


@kernel
def _quiet_pairs(last_heard, silent, before_s):
    """``_write_quiet_pairs``' pairs as a new (2, Q) int64 array."""
    quiet = np.empty((2, last_heard.size), dtype=np.int64)
    return quiet[:, :_write_quiet_pairs(last_heard, silent, before_s, quiet)].copy()
