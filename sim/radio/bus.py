"""The message bus: every message a robot sends, with its real size, over a shared, lossy medium.

numpy and, under a real preset, a compiled frame table (``sim.radio.medium``:
the queues, one compiled call per send batch and per period;
``ReferenceMessageBus`` keeps the plain loop it replaces), no MuJoCo. Time
advances in control periods: the
caller ``send``s messages during a tick and calls ``step(time_s, link)``
once per tick, which puts the queued frames on the air during
[time_s, time_s + control_period_s) and returns, per receiver, the
``Delivery``s whose arrival falls in that period.

The model, per control period:

- **Frames.** A message of ``size_bytes`` goes out as ceil(size / max payload)
  frames of the preset's format; each frame's airtime is
  ``channel.packet_airtime_s`` of its payload. A receiver gets the message
  only if it gets every frame; it arrives at the end of the last frame.
- **Shared medium.** Robots ``i`` and ``j`` with ``carrier_sense[i, j]`` share
  the air: a sender starts a frame only when no robot in its carrier-sense set
  is on the air, and only if the frame ends within this period. What does not
  fit stays queued, FIFO per sender, for a later tick, so latency grows with
  load. Senders that become ready at the same instant are ordered at random
  (the role of CSMA's random backoff, without its slots). A message sent
  ``latest_only`` replaces the sender's waiting message of the same kind (one
  none of whose frames is on the air yet) and joins the queue's end, as a
  transmit buffer that holds only the newest value does; the replaced one
  counts as superseded, not sent.
- **Loss.** Each receiver of a frame draws its own fading gain
  (``channel.fading_gain_db``, the preset's model) and gets the frame with
  probability 1 - PER(mean SNR + fading, frame bits), PER from the preset's
  modulation (``channel.bit_error_rate``, ``channel.packet_error_rate``). The
  bits that count are the PHY header, MAC overhead and payload (not the
  preamble). A broadcast (``receivers=None``) is tried at every other robot.
- **Latency** = arrival - ``sent_s``: queueing plus airtime.

Under the ``ideal`` preset nothing of this applies: every message reaches
every intended receiver with a link in the tick it was sent, latency 0, no
airtime, and no random number is drawn. A receiver has a link when its
``snr_db`` from the sender is not -inf (every robot if no link is given); a
unicast to a robot without one is lost (addressed, not delivered), a
broadcast is tried only at the robots with one.

A ``step`` with nothing queued returns at once (no link state read).

Not modelled: hidden terminals and collisions between senders outside each
other's carrier-sense range (their frames never interfere), the capture
effect, half-duplex loss (a receiver on the air still receives), MAC
acknowledgements, backoff slots and retries (``sim.radio.protocols`` does
acknowledgements and retransmission above the bus), and frames that would
straddle two control periods.
"""

from __future__ import annotations

import copy
import math
from array import array
from collections import deque
from itertools import chain
from dataclasses import dataclass, field
from typing import Any, Callable, Protocol

import numpy as np

from sim.compiled import compiled_call, generator_pointers, kernel
from sim.radio import channel, medium
from sim.radio.medium import _NO_DRAW, _EXPONENTIAL, _NONCENTRAL_CHISQUARE, _ZERO_BER_SNR_DB, _per_802154  # noqa: F401
from sim.radio.presets import IdealDisk, RadioPreset

FLOAT64_BYTES = 8
INT32_BYTES = 4
INDEX_BYTES = 2  # a robot or target index, or a short sequence number, as a uint16
STEP_BYTES = 4  # a discrete time step k, as a uint32
# A range record (estimation.beliefs.RangeMeasurement) as it holds: the step, the observer and the
# target, the sensor's position (the receiver's EKF needs it) and the range.
RANGE_RECORD_BYTES = STEP_BYTES + 2 * INDEX_BYTES + 3 * FLOAT64_BYTES + FLOAT64_BYTES


def float64_bytes(count: int) -> int:
    """Size of ``count`` float64 values, bytes."""
    return FLOAT64_BYTES * int(count)


def range_records_bytes(count: int) -> int:
    """Size of ``count`` range records (step, observer, target, sensor position, range), bytes."""
    return RANGE_RECORD_BYTES * int(count)


def array_bytes(array: Any) -> int:
    """Size of a numpy array's data as it would be sent, bytes (at least 1)."""
    return max(1, int(np.asarray(array).nbytes))


@dataclass(frozen=True)
class Message:
    """One application message. ``sequence`` and ``sent_s`` are filled in by ``MessageBus.send``."""

    kind: str  # what it is for: 'election', 'handover', 'consensus', 'range_records', ...
    sender: int  # robot index
    receivers: tuple[int, ...] | None  # intended receivers; None broadcasts to whoever hears it
    payload: Any
    size_bytes: int  # the real payload size on the air, bytes (> 0)
    sequence: int = -1  # assigned by the bus, increasing over all messages
    sent_s: float = math.nan  # when it was handed to the bus, s
    # True: it replaces its sender's waiting latest_only message of the same kind (none of whose frames has
    # gone out), taking its place in the queue: a state update where only the newest value counts
    latest_only: bool = False
    # True: its arrivals come as columns (``MessageBus.arrivals``, ``Observation.arrivals``), not as one
    # ``Delivery`` per receiver in the rows; the payload must be a number. The same frames, draws and losses.
    as_arrays: bool = False

    def __post_init__(self) -> None:
        if not isinstance(self.size_bytes, (int, np.integer)) or self.size_bytes <= 0:
            raise ValueError(f"size_bytes must be a positive integer, got {self.size_bytes!r}")
        if self.as_arrays and not isinstance(self.payload, (int, float, np.integer, np.floating)):
            raise ValueError(f"a message sent as_arrays carries a number, got {type(self.payload).__name__}")
        if self.receivers is not None:
            if not isinstance(self.receivers, tuple):
                raise ValueError("receivers must be a tuple of robot indices or None")
            if self.sender in self.receivers:
                raise ValueError(f"robot {self.sender} sends message {self.kind!r} to itself")
            if len(set(self.receivers)) != len(self.receivers):
                raise ValueError("receivers must not repeat")


_new_object = object.__new__


def broadcasts(kind: str, values: Any, size_bytes: int, latest_only: bool = False,
               as_arrays: bool = False) -> tuple[Message, ...]:
    """One broadcast ``Message`` per robot, robot i's carrying ``values[i]`` (a number each): every robot's
    share of a per-tick state at once, checked once (per kind, size and flags) instead of per message."""
    values = np.asarray(values, dtype=float).tolist()
    if not values:
        return ()
    key = (kind, size_bytes, latest_only, as_arrays)
    fields = _BROADCAST_FIELDS.get(key)
    if fields is None:  # the checks depend on these alone (the payloads are floats)
        fields = _BROADCAST_FIELDS[key] = dict(
            Message(kind, 0, None, values[0], size_bytes, latest_only=latest_only, as_arrays=as_arrays).__dict__)
    messages = []
    for sender, value in enumerate(values):
        message = _new_object(Message)
        message_fields = message.__dict__
        message_fields.update(fields)
        message_fields["sender"] = sender
        message_fields["payload"] = value
        messages.append(message)
    return tuple(messages)


_BROADCAST_FIELDS: dict[tuple, dict[str, Any]] = {}  # broadcasts' checked fields per (kind, size, flags)
_NO_ROBOTS = np.empty(0, dtype=np.int64)  # no receivers listed


class Broadcasts:
    """Many robots' broadcasts of one number each as ONE outbox item: robot ``senders[i]`` sends ``values[i]``,
    latest_only or not, always ``as_arrays``. The bus treats it as ``messages()``, in order at its place in
    the outbox (the same sequences, frames, draws and arrivals); the frame table takes it without a
    ``Message`` per robot. ``senders`` None: robots 0 .. len(values) - 1."""

    __slots__ = ("kind", "values", "size_bytes", "latest_only", "senders")
    receivers = None  # every one is a broadcast

    def __init__(self, kind: str, values: Any, size_bytes: int, latest_only: bool = False,
                 senders: Any = None) -> None:
        values = np.array(values, dtype=float).reshape(-1)  # a copy: the caller may overwrite its array
        if not isinstance(size_bytes, (int, np.integer)) or size_bytes <= 0:
            raise ValueError(f"size_bytes must be a positive integer, got {size_bytes!r}")
        if senders is not None:
            senders = np.array(senders, dtype=np.int64).reshape(-1)
            if senders.shape != values.shape:
                raise ValueError(f"{len(senders)} senders for {len(values)} values")
            if len(np.unique(senders)) != len(senders):
                raise ValueError("senders must not repeat")
        self.kind, self.values, self.size_bytes = kind, values, int(size_bytes)
        self.latest_only, self.senders = bool(latest_only), senders

    @classmethod
    def handed_over(cls, kind: str, values: np.ndarray, size_bytes: int, latest_only: bool = False) -> Broadcasts:
        """Robot i broadcasts ``values[i]``, every robot, from a float64 vector the caller hands over and no
        longer changes (not copied, as the constructor copies; a strategy's per-tick array)."""
        flags = values.flags
        if (values.dtype != np.float64 or values.ndim != 1 or not flags.c_contiguous or not flags.writeable
                or type(size_bytes) is not int or size_bytes <= 0):
            return cls(kind, values, size_bytes, latest_only)  # the constructor's checks and copy
        batch = _new_object(cls)
        batch.kind, batch.values, batch.size_bytes, batch.latest_only, batch.senders = (
            kind, values, size_bytes, bool(latest_only), None)
        return batch

    def __len__(self) -> int:
        return len(self.values)

    def sender_indices(self) -> np.ndarray:
        """(M,) int64: who sends each value."""
        return np.arange(len(self.values)) if self.senders is None else self.senders

    def messages(self) -> tuple[Message, ...]:
        """The same broadcasts as ``Message``s, one per sender in order (``broadcasts``')."""
        made = broadcasts(self.kind, self.values, self.size_bytes, self.latest_only, as_arrays=True)
        if self.senders is not None:
            for message, sender in zip(made, self.senders.tolist()):
                message.__dict__["sender"] = sender
        return made

    def kept(self, keep: np.ndarray) -> Broadcasts:
        """Only the broadcasts of the senders where ``keep`` ((N,) bool over the robots) is True."""
        senders = self.sender_indices()
        chosen = np.asarray(keep, dtype=bool)[senders]
        return Broadcasts(self.kind, self.values[chosen], self.size_bytes, self.latest_only, senders[chosen])

    def __repr__(self) -> str:
        return f"Broadcasts({self.kind!r}, {len(self)} senders, {self.size_bytes} B)"


def each_message(outbox: Any) -> Any:
    """The ``Message``s of an outbox in order, each ``Broadcasts`` item as its ``messages()``."""
    for item in outbox:
        if type(item) is Broadcasts:
            yield from item.messages()
        else:
            yield item


def _stamped(message: Message, sequence: int, sent_s: float) -> Message:
    """``message`` with the bus's stamps: ``dataclasses.replace`` without re-running the checks it passed."""
    stamped = object.__new__(type(message))
    stamped.__dict__.update(message.__dict__)
    stamped.__dict__["sequence"] = sequence
    stamped.__dict__["sent_s"] = sent_s
    return stamped


@dataclass(frozen=True)
class Delivery:
    """A message arriving at one receiver."""

    message: Message
    receiver: int
    arrival_s: float  # end of the message's last frame (its send time under 'ideal'), s

    @property
    def latency_s(self) -> float:
        return self.arrival_s - self.message.sent_s


@dataclass(frozen=True)
class Arrivals:
    """One kind's ``as_arrays`` messages that arrived in one period, one entry per (message, receiver): the
    ``Delivery``s they stand for, as columns, by receiver, then by (arrival, sequence) as the rows are."""

    receiver: np.ndarray  # (D,) int64
    sender: np.ndarray  # (D,) int64
    arrival_s: np.ndarray  # (D,) s
    sent_s: np.ndarray  # (D,) s
    sequence: np.ndarray  # (D,) int64
    payload: np.ndarray  # (D,) float64

    def __len__(self) -> int:
        return len(self.receiver)

    def where(self, keep: np.ndarray) -> Arrivals:
        """The entries where ``keep`` ((D,) bool) holds."""
        return Arrivals(*(column[keep] for column in vars(self).values()))


def _arrivals_of(records: list[tuple[Message, Any, float]], n: int) -> Arrivals:
    """``Arrivals`` from (message, receivers reached, arrival s) records of ``n`` robots, in the rows' order."""
    table = _ArrivalTable()
    for message, reached, arrival_s in records:
        table.add(message, reached, arrival_s, n - 1)
    return table.columns(n)


class _ArrivalTable:
    """One kind's ``as_arrays`` arrivals of a period as they are recorded: per message a row of numbers
    (sender, arrival, sent, sequence, payload, receivers reached or -1 for every other robot: all exact as
    float64) and the receivers of the rows that list theirs, flat."""

    __slots__ = ("rows", "receivers")

    def __init__(self) -> None:
        self.rows: list[tuple[float, ...]] = []
        self.receivers: list[int] = []

    def add(self, message: Message, reached: Any, arrival_s: float, everyone: int) -> None:
        """``message`` reached ``reached`` at ``arrival_s``; ``everyone``: how many robots but its sender."""
        if message.receivers is None and len(reached) == everyone:
            self.rows.append((message.sender, arrival_s, message.sent_s, message.sequence, message.payload, -1))
        else:
            self.rows.append((message.sender, arrival_s, message.sent_s, message.sequence, message.payload,
                              len(reached)))
            self.receivers.extend(reached)

    def columns(self, n: int) -> Arrivals:
        """The ``Arrivals``, in the rows' order (``_arrival_columns``), read-only."""
        integers, floats = _arrival_columns(n, np.array(self.rows, dtype=float),
                                            np.array(self.receivers, dtype=np.int64))
        integers.flags.writeable = False  # before the views: they inherit it
        floats.flags.writeable = False
        arrivals = _new_object(Arrivals)
        arrivals.__dict__.update(receiver=integers[0], sender=integers[1], arrival_s=floats[0], sent_s=floats[1],
                                 sequence=integers[2], payload=floats[2])
        return arrivals


@kernel
def _arrival_columns(n, table, receivers):
    """One entry per (message, receiver reached), ordered by receiver, then (arrival, sequence): the messages
    (rows of ``table``: sender, arrival, sent, sequence, payload, how many of ``receivers`` are theirs, in
    order, or -1: every robot of ``n`` but the sender) by (arrival, sequence), then a stable counting sort
    by receiver, which is what ``numpy.lexsort((sequence, arrival, receiver))`` gives (no two entries tie).
    Returns the columns as two blocks (one array each to box, not six): (receiver, sender, sequence) int64
    and (arrival, sent, payload) float64, (3, D) each."""
    m = table.shape[0]
    starts = np.empty(m, dtype=np.int64)
    counts = np.empty(m, dtype=np.int64)
    listed = 0
    total = 0
    for k in range(m):
        starts[k] = listed
        counts[k] = int(table[k, 5])
        if counts[k] < 0:
            total += n - 1
        else:
            listed += counts[k]
            total += counts[k]
    robots = n
    for d in range(receivers.shape[0]):
        robots = max(robots, receivers[d] + 1)
    slot = np.zeros(robots + 1, dtype=np.int64)
    for k in range(m):
        if counts[k] < 0:
            sender = int(table[k, 0])
            for r in range(n):
                if r != sender:
                    slot[r + 1] += 1
    for d in range(receivers.shape[0]):
        slot[receivers[d] + 1] += 1
    order = np.arange(m)
    for a in range(1, m):  # insertion sort: the messages come nearly in order of arrival
        k = order[a]
        b = a - 1
        while b >= 0 and (table[order[b], 1] > table[k, 1] or (table[order[b], 1] == table[k, 1]
                                                              and table[order[b], 3] > table[k, 3])):
            order[b + 1] = order[b]
            b -= 1
        order[b + 1] = k
    for r in range(robots):
        slot[r + 1] += slot[r]
    integers = np.empty((3, total), dtype=np.int64)  # receiver, sender, sequence
    floats = np.empty((3, total))  # arrival, sent, payload
    for a in range(m):
        k = order[a]
        everyone = counts[k] < 0
        for d in range(n if everyone else counts[k]):
            if everyone:
                receiver = d
                if receiver == int(table[k, 0]):
                    continue
            else:
                receiver = receivers[starts[k] + d]
            e = slot[receiver]
            slot[receiver] += 1
            integers[0, e] = receiver
            integers[1, e] = int(table[k, 0])
            integers[2, e] = int(table[k, 3])
            floats[0, e] = table[k, 1]
            floats[1, e] = table[k, 2]
            floats[2, e] = table[k, 4]
    return integers, floats


class LinkState(Protocol):
    """What the bus reads of the channel each tick: (N, N) arrays, sender by row."""

    snr_db: np.ndarray  # mean SNR from i to j, dB, before per-packet fading; -inf: no link
    carrier_sense: np.ndarray  # bool: i and j hear each other's carrier and share the air


@dataclass(frozen=True)
class LinkConditions:
    """A plain ``LinkState``; build it with ``link_conditions``."""

    snr_db: np.ndarray
    carrier_sense: np.ndarray


def link_conditions(snr_db: Any, carrier_sense: Any = True) -> LinkConditions:
    """A ``LinkState`` from an (N, N) SNR array (dB) and a carrier-sense array or one bool for all pairs.

    The diagonal of the carrier-sense matrix is always True (a robot hears itself).
    """
    snr = np.array(snr_db, dtype=float)
    if snr.ndim != 2 or snr.shape[0] != snr.shape[1]:
        raise ValueError(f"snr_db must be (N, N), got shape {snr.shape}")
    sense = np.broadcast_to(np.asarray(carrier_sense, dtype=bool), snr.shape).copy()
    np.fill_diagonal(sense, True)
    snr.setflags(write=False)
    sense.setflags(write=False)
    return LinkConditions(snr, sense)


def link_from_pairs(n: int, pairs: tuple[np.ndarray, np.ndarray], snr_db: np.ndarray, rx_power_dbm: np.ndarray,
                    carrier_sense_dbm: float) -> LinkConditions:
    """The bus's ``LinkState`` from a channel's per-pair figures ((P,) over the pairs (first[p], second[p]),
    i < j, every pair of ``n`` robots): the SNR matrix (NaN on the diagonal) and carrier sense where the mean
    received power reaches ``carrier_sense_dbm``, as ``RadioState.snr_db`` and
    ``RadioState.rx_power_dbm >= carrier_sense_dbm`` give them, in one compiled pass."""
    first, second = pairs
    snr, sense = _pair_matrices(int(n), first, second, np.asarray(snr_db, dtype=float),
                                np.asarray(rx_power_dbm, dtype=float), float(carrier_sense_dbm))
    snr.flags.writeable = False
    return LinkConditions(snr, sense)


@kernel
def _pair_matrices(n, first, second, snr_db, rx_power_dbm, carrier_sense_dbm):
    """``link_from_pairs``' two (N, N) matrices, both triangles from each pair."""
    snr = np.empty((n, n))
    sense = np.empty((n, n), dtype=np.bool_)
    medium.write_pair_matrices(first, second, snr_db, rx_power_dbm, carrier_sense_dbm, snr, sense)
    return snr, sense


@dataclass(frozen=True)
class BusParameters:
    """What the bus needs of a channel preset (``from_preset``)."""

    name: str
    is_ideal: bool
    bitrate_bps: float = math.inf  # bit/s
    bandwidth_hz: float = math.inf  # Hz
    modulation: str = ""  # one of channel.MODULATIONS
    preamble_bits: int = 0
    header_bits: int = 0  # PHY header, bits
    mac_overhead_bits: int = 0  # MAC header and checksum, bits
    fixed_overhead_s: float = 0.0  # per frame, s
    max_payload_bytes: int = 0  # per frame, bytes
    fading_model: str = "none"  # 'none', 'rayleigh', 'rician'
    rician_k: float = 0.0  # linear

    @classmethod
    def from_preset(cls, preset: IdealDisk | RadioPreset) -> BusParameters:
        if preset.is_ideal:
            return cls(name=preset.name, is_ideal=True)
        packet = preset.packet
        return cls(name=preset.name, is_ideal=False, bitrate_bps=preset.bitrate_bps,
                   bandwidth_hz=preset.bandwidth_hz, modulation=preset.modulation,
                   preamble_bits=packet.preamble_bits, header_bits=packet.header_bits,
                   mac_overhead_bits=packet.mac_overhead_bits, fixed_overhead_s=packet.fixed_overhead_s,
                   max_payload_bytes=packet.max_payload_bytes, fading_model=preset.fading.model,
                   rician_k=preset.fading.rician_k)

    def frame_payloads(self, size_bytes: int) -> list[int]:
        """Payload bytes of each frame carrying ``size_bytes``."""
        full, rest = divmod(int(size_bytes), self.max_payload_bytes)
        return [self.max_payload_bytes] * full + ([rest] if rest else [])

    def airtime_s(self, payload_bytes: Any) -> np.ndarray:
        """Airtime of one frame carrying ``payload_bytes`` (<= max payload), s."""
        return channel.packet_airtime_s(payload_bytes, self.bitrate_bps, preamble_bits=self.preamble_bits,
                                        header_bits=self.header_bits, mac_overhead_bits=self.mac_overhead_bits,
                                        fixed_overhead_s=self.fixed_overhead_s)

    def error_bits(self, payload_bytes: Any) -> np.ndarray:
        """Bits of a frame whose errors lose it: PHY header, MAC overhead and payload."""
        return self.header_bits + self.mac_overhead_bits + 8 * np.asarray(payload_bytes)

    def packet_error_rate(self, snr_db: Any, payload_bytes: Any) -> np.ndarray:
        """PER of one frame carrying ``payload_bytes`` at ``snr_db`` (dB, fading included)."""
        ber = channel.bit_error_rate(self.modulation, snr_db, self.bandwidth_hz, self.bitrate_bps)
        return channel.packet_error_rate(ber, self.error_bits(payload_bytes))


class _Frame:
    """One frame of a queued message."""

    __slots__ = ("message", "payload_bytes", "last", "airtime_s", "error_bits", "numbers")

    def __init__(self, message: Message, payload_bytes: int, last: bool, airtime_s: float, error_bits: float = 0.0):
        self.message = message
        self.payload_bytes = payload_bytes
        self.last = last  # the message's last frame
        self.airtime_s = airtime_s
        self.error_bits = error_bits  # bits whose errors lose it (``BusParameters.error_bits``), as a float
        # What the scheduling kernel reads of it, made once, not per period it waits: the send time, the
        # airtime, the error bits and how many receivers it lists (-1: every other robot, a broadcast)
        receivers = message.receivers
        self.numbers = (message.sent_s, airtime_s, error_bits, -1.0 if receivers is None else float(len(receivers)))


@dataclass
class _InFlight:
    """A message whose frames are going out: the receivers still holding every frame."""

    audience: tuple[int, ...]
    alive: Any  # bool per audience member (a list in MessageBus, an array in ReferenceMessageBus)


@dataclass
class _KindCounters:
    packets_sent: int = 0
    frames_sent: int = 0
    bytes_sent: int = 0
    addressed: int = 0  # (message, receiver) pairs tried
    delivered: int = 0
    latencies_s: list[float] = field(default_factory=list)
    airtime_s: list[float] | None = None  # per robot, s (a list: one float added per frame)
    superseded: int = 0  # latest_only messages replaced unsent by a newer one


@dataclass(frozen=True)
class TickStats:
    """The last ``step``'s period: messages that finished going out in it and what they reached."""

    time_s: float
    packets_sent: int
    packets_delivered: int
    delivery_ratio: float  # delivered / addressed; nan if nothing was addressed
    latency_mean_s: float  # over this period's deliveries; nan if none
    queued: int  # messages still waiting at their senders after the period


def _rows_to_records(deliveries: list[list[Delivery]], records: dict[str, _ArrivalTable]) -> None:
    """Move the rows' deliveries of ``as_arrays`` messages into ``records`` (what the compiled period does
    as it goes; the ideal bus and the reference make them as rows)."""
    for receiver, row in enumerate(deliveries):
        if any(d.message.as_arrays for d in row):
            kept = []
            for d in row:
                if d.message.as_arrays:
                    table = records.get(d.message.kind)
                    if table is None:
                        table = records[d.message.kind] = _ArrivalTable()
                    table.add(d.message, (receiver,), d.arrival_s, len(deliveries) - 1)
                else:
                    kept.append(d)
            deliveries[receiver] = kept


def _latencies_in_row_order(deliveries: list[list[Delivery]], arrivals: Any) -> np.ndarray:
    """Every delivery's latency, rows' and columns', in the order of rows that held them all (by receiver,
    then (arrival, sequence)): the order the period's mean latency has always been summed in."""
    rows = [(d.receiver, d.arrival_s, d.message.sequence, d.arrival_s - d.message.sent_s)
            for row in deliveries for d in row]
    receiver = [np.array([r[0] for r in rows], dtype=np.int64)]
    arrival = [np.array([r[1] for r in rows], dtype=float)]
    sequence = [np.array([r[2] for r in rows], dtype=np.int64)]
    latency = [np.array([r[3] for r in rows], dtype=float)]
    for columns in arrivals:
        receiver.append(columns.receiver)
        arrival.append(columns.arrival_s)
        sequence.append(columns.sequence)
        latency.append(columns.arrival_s - columns.sent_s)
    order = np.lexsort((np.concatenate(sequence), np.concatenate(arrival), np.concatenate(receiver)))
    return np.concatenate(latency)[order]


def _arrival_order(delivery: Delivery) -> tuple[float, int]:
    return delivery.arrival_s, delivery.message.sequence


def _delivery(message: Message, receiver: int, arrival_s: float) -> Delivery:
    """``Delivery(message, receiver, arrival_s)`` without the frozen dataclass's per-field ``__setattr__``."""
    delivery = _new_object(Delivery)
    delivery.__dict__.update(message=message, receiver=receiver, arrival_s=arrival_s)
    return delivery


class _QueueBus:
    """The bus with its queues as deques of ``_Frame``s, stepped in Python: ``MessageBus`` under 'ideal' and
    ``ReferenceMessageBus``. See the module docstring."""

    def __init__(self, params: BusParameters, rng: np.random.Generator | None, control_period_s: float,
                 robot_count: int | None = None) -> None:
        if control_period_s <= 0:
            raise ValueError("control_period_s must be > 0")
        if not params.is_ideal and rng is None:
            raise ValueError(f"the {params.name!r} bus draws fading and losses: pass a numpy Generator")
        self.params = params
        self.rng = rng
        self.control_period_s = float(control_period_s)
        self._n = robot_count
        self._sequence = 0
        self._queues: dict[int, deque[_Frame]] = {}
        self._waiting: dict[int, int] = {}  # per sender, messages whose last frame is still queued
        self._waiting_total = 0
        self._frames_of_size: dict[int, tuple[tuple[int, float], ...]] = {}  # (payload, airtime) of each frame
        self._broadcast_audiences: dict[tuple[int, int], tuple[int, ...]] = {}  # (sender, robots): every other
        self._broadcast_audience_lists: dict[int, list[tuple[int, ...]]] = {}  # robots: ``_audience`` per sender
        self._in_flight: dict[int, _InFlight] = {}
        self._arrays_sent = False  # some message went as_arrays: the rows' such deliveries move to columns
        self._array_records: dict[str, _ArrivalTable] = {}  # this period's, per kind
        self._arrivals: dict[str, Arrivals] = {}
        self._kinds: dict[str, _KindCounters] = {}
        self._elapsed_s = 0.0
        self._last: TickStats | None = TickStats(math.nan, 0, 0, math.nan, math.nan, 0)
        self._idle_s = math.nan

    @property
    def params(self) -> BusParameters:
        return self._params

    @params.setter
    def params(self, params: BusParameters) -> None:
        """New parameters (the tuning page's retuning) drop the frames' airtimes computed under the old."""
        self._params = params
        self._frames_of_size = {}

    # --- sending ---------------------------------------------------------------------------------

    def send(self, message: Message, time_s: float) -> Message:
        """Queue ``message`` at its sender at ``time_s``; returns it with its ``sequence`` and ``sent_s``."""
        robots = self._n
        if robots is not None and (not 0 <= message.sender < robots or (
                message.receivers and any(not 0 <= r < robots for r in message.receivers))):
            raise ValueError(f"message {message.kind!r} names a robot outside 0..{robots - 1}")
        frames = None if self.params.is_ideal else self._frames(message.size_bytes)
        stamped = _stamped(message, self._sequence, float(time_s))
        self._sequence += 1
        queue = self._queues.get(stamped.sender)
        if queue is None:
            queue = self._queues[stamped.sender] = deque()
        elif stamped.latest_only and queue:
            self._supersede(queue, stamped)
        if frames is None:
            queue.append(_Frame(stamped, stamped.size_bytes, True, 0.0))
        else:
            last = len(frames) - 1
            for k, (payload, airtime, bits) in enumerate(frames):
                queue.append(_Frame(stamped, payload, k == last, airtime, bits))
        self._waiting[stamped.sender] = self._waiting.get(stamped.sender, 0) + 1
        self._waiting_total += 1
        if stamped.as_arrays:
            self._arrays_sent = True
        return stamped

    def send_all(self, messages: Any, time_s: float) -> None:
        """``send`` each of ``messages`` at ``time_s``, in order (a tick's outbox): the same stamps, queues and
        superseding, with the per-message lookups and calls done once."""
        robots = self._n
        ideal = self.params.is_ideal
        time_s = float(time_s)
        queues, waiting, sizes, kinds = self._queues, self._waiting, self._frames_of_size, self._kinds
        in_flight = self._in_flight
        sequence = self._sequence
        added = 0  # to self._waiting_total (which _supersede may lower meanwhile)
        try:
            for message in each_message(messages):
                sender = message.sender
                receivers = message.receivers
                if robots is not None and (not 0 <= sender < robots or (
                        receivers and any(not 0 <= r < robots for r in receivers))):
                    raise ValueError(f"message {message.kind!r} names a robot outside 0..{robots - 1}")
                if ideal:
                    frames = None
                else:
                    frames = sizes.get(message.size_bytes)
                    if frames is None:
                        frames = self._frames(message.size_bytes)
                stamped = _new_object(type(message))
                fields = stamped.__dict__
                fields.update(message.__dict__)
                fields["sequence"] = sequence
                fields["sent_s"] = time_s
                sequence += 1
                self._sequence = sequence
                queue = queues.get(sender)
                if queue is None:
                    queue = queues[sender] = deque()
                elif queue and fields["latest_only"]:
                    if len(queue) == 1:  # a state update left over from the last period, usually: _supersede inline
                        head = queue[0].message
                        if head.latest_only and head.kind == stamped.kind and head.sequence not in in_flight:
                            counters = kinds.get(stamped.kind)
                            if counters is None or len(counters.airtime_s) < (robots or sender + 1):
                                counters = self._counters(stamped.kind, robots or sender + 1)
                            counters.superseded += 1
                            replaced = queue[0]
                            if frames is not None and len(frames) == 1 and replaced.payload_bytes == frames[0][0]:
                                # A frame of the same payload, so the same airtime and error bits: the queue's
                                # entry takes the new message, as a new _Frame would (the waiting counts stay,
                                # one message replacing one)
                                replaced.message = stamped
                                replaced.numbers = (time_s, replaced.airtime_s, replaced.error_bits,
                                                    -1.0 if receivers is None else float(len(receivers)))
                                if fields["as_arrays"]:
                                    self._arrays_sent = True
                                continue
                            queue.clear()
                            waiting[sender] -= 1
                            added -= 1
                    else:
                        self._supersede(queue, stamped)
                if frames is None:
                    queue.append(_Frame(stamped, stamped.size_bytes, True, 0.0))
                elif len(frames) == 1:
                    payload, airtime, bits = frames[0]
                    queue.append(_Frame(stamped, payload, True, airtime, bits))
                else:
                    last = len(frames) - 1
                    for k, (payload, airtime, bits) in enumerate(frames):
                        queue.append(_Frame(stamped, payload, k == last, airtime, bits))
                waiting[sender] = waiting.get(sender, 0) + 1
                added += 1
                if fields["as_arrays"]:
                    self._arrays_sent = True
        finally:
            self._waiting_total += added

    def _frames(self, size_bytes: int) -> tuple[tuple[int, float, float], ...]:
        """(payload bytes, airtime s, error bits) of each frame of a ``size_bytes`` message, computed once per
        size."""
        frames = self._frames_of_size.get(size_bytes)
        if frames is None:
            payloads = self.params.frame_payloads(size_bytes)
            airtimes = self.params.airtime_s(np.array(payloads))
            if airtimes.max() > self.control_period_s:
                raise ValueError(f"a {self.params.name} frame takes {airtimes.max():.6f} s, longer than the "
                                 f"control period {self.control_period_s} s: it would never go out")
            # The error bits as _step_medium summed them: 8 * payload, then plus the headers, in float64.
            frames = self._frames_of_size[size_bytes] = tuple(
                (payload, float(airtime), 8.0 * payload + (self.params.header_bits + self.params.mac_overhead_bits))
                for payload, airtime in zip(payloads, airtimes))
        return frames

    def _popped(self, sender: int, frame: _Frame) -> None:
        """Bookkeeping of ``frame`` leaving ``sender``'s queue."""
        if frame.last:
            self._waiting[sender] -= 1
            self._waiting_total -= 1

    def _supersede(self, queue: deque[_Frame], newer: Message) -> None:
        """Drop from ``queue`` the waiting latest_only messages of ``newer``'s kind (none of their frames
        sent); ``newer`` then joins the queue's end, as a fresh frame in a transmit buffer does."""
        kind, in_flight = newer.kind, self._in_flight
        stale = set()
        everything = True  # every frame of the queue is stale
        for frame in queue:
            message = frame.message
            if message.latest_only and message.kind == kind and message.sequence not in in_flight:
                stale.add(message.sequence)
            else:
                everything = False
        if stale:
            self._drop_superseded(queue, newer, stale, everything)

    def _drop_superseded(self, queue: deque[_Frame], newer: Message, stale: set[int], everything: bool) -> None:
        """Remove the messages ``stale`` (sequences; ``everything``: the whole queue) that ``newer`` replaces."""
        if everything:
            queue.clear()
        else:
            kept = [frame for frame in queue if frame.message.sequence not in stale]
            queue.clear()
            queue.extend(kept)
        self._waiting[newer.sender] -= len(stale)
        self._waiting_total -= len(stale)
        self._counters(newer.kind, self._n or newer.sender + 1).superseded += len(stale)

    def queued(self, sender: int | None = None) -> int:
        """Messages waiting (some of their frames not yet on the air), at ``sender`` or at all."""
        return self._waiting_total if sender is None else self._waiting.get(sender, 0)

    # --- one control period ----------------------------------------------------------------------

    def step(self, time_s: float, link: LinkState | None) -> list[list[Delivery]]:
        """Advance [time_s, time_s + control period): returns each robot's deliveries, by arrival time.

        ``link`` gives this tick's (N, N) ``snr_db`` and ``carrier_sense``; under
        'ideal' it may be None (a broadcast then reaches every other robot).
        The messages sent ``as_arrays`` are not in the rows: their arrivals are ``arrivals``.
        """
        self._arrivals = {}
        if not self._queues_busy():
            # Nothing queued (no frame in flight either: a message's frames all go out of one queue).
            self._elapsed_s += self.control_period_s
            self._last = None  # an empty period at self._idle_s, built only when read
            self._idle_s = time_s
            n = self._robot_count(link) if link is not None else self._n or 0
            return [[] for _ in range(n)]
        n = self._robot_count(link)
        before = self._totals()
        deliveries: list[list[Delivery]] = [[] for _ in range(n)]
        records = self._array_records = {}
        if self.params.is_ideal:
            self._step_ideal(link, n, deliveries)
        else:
            if link is None:
                raise ValueError(f"the {self.params.name!r} bus needs this tick's link state")
            self._step_medium(float(time_s), link, n, deliveries)
        self._elapsed_s += self.control_period_s
        for row in deliveries:
            if len(row) > 1:
                row.sort(key=_arrival_order)
        if self._arrays_sent:
            _rows_to_records(deliveries, records)
        sent, addressed, delivered = (a - b for a, b in zip(self._totals(), before))
        latencies = [d.arrival_s - d.message.sent_s for row in deliveries for d in row]  # each one's latency_s
        if records:
            self._arrivals = {kind: table.columns(n) for kind, table in records.items()}
            if latencies or len(records) > 1:
                latencies = _latencies_in_row_order(deliveries, self._arrivals.values())
            else:  # one kind's columns alone: already in the rows' order
                columns = next(iter(self._arrivals.values()))
                latencies = columns.arrival_s - columns.sent_s
        if len(latencies):
            latencies = np.asarray(latencies, dtype=float)
            # numpy.mean's own sum and division, without its wrapper (this runs every tick)
            latency_mean_s = float(np.add.reduce(latencies) / latencies.size)
        else:
            latency_mean_s = math.nan
        # TickStats(...) without the frozen dataclass's per-field __setattr__
        self._last = last = _new_object(TickStats)
        last.__dict__.update(time_s=float(time_s), packets_sent=sent, packets_delivered=delivered,
                             delivery_ratio=delivered / addressed if addressed else math.nan,
                             latency_mean_s=latency_mean_s, queued=self._waiting_total)
        return deliveries

    def inbox(self, time_s: float, link: LinkState | None) -> tuple[tuple[Delivery, ...], ...] | None:
        """``step``, its rows as an observation's inbox (a tuple per robot), or None where no row holds a
        delivery (what the loop takes each tick: most ticks' messages arrive as ``arrivals``)."""
        rows = self.step(time_s, link)
        return tuple(map(tuple, rows)) if any(rows) else None

    def exchange(self, outbox: Any, time_s: float, link_of: Callable[[], LinkState]
                 ) -> tuple[tuple[Delivery, ...], ...] | None | bool:
        """A tick's messages, as the loop hands them over: ``send_all(outbox, time_s)``, then one period.
        Where nothing waits it is ``step(time_s, None)`` and returns False (no link state read, nothing
        drawn); else ``inbox(time_s, link_of())``."""
        if outbox:
            self.send_all(outbox, time_s)
        if self.idle:
            self.step(time_s, None)
            return False
        return self.inbox(time_s, link_of())

    @property
    def arrivals(self) -> dict[str, Arrivals]:
        """The last ``step``'s arrivals of the messages sent ``as_arrays``, per kind (only kinds that arrived)."""
        return self._arrivals

    def _queues_busy(self) -> bool:
        return any(self._queues.values()) if self._queues else False

    @property
    def idle(self) -> bool:
        """Nothing waits to go out: the next ``step`` needs no link state and costs next to nothing."""
        return not self._queues_busy()

    def _robot_count(self, link: LinkState | None) -> int:
        if link is not None:
            n = len(link.snr_db)
            if n != self._n:
                if self._n is not None:
                    raise ValueError(f"the link has {n} robots, the bus {self._n}")
                self._n = n
            return n
        if self._n is None:
            senders = max(self._queues, default=-1)
            receivers = max((max(f.message.receivers or (-1,)) for q in self._queues.values() for f in q),
                            default=-1)
            return max(senders, receivers) + 1
        return self._n

    def _audience(self, message: Message, n: int) -> tuple[int, ...]:
        if message.receivers is not None:
            return message.receivers
        key = (message.sender, n)
        audience = self._broadcast_audiences.get(key)
        if audience is None:
            audience = self._broadcast_audiences[key] = tuple(j for j in range(n) if j != message.sender)
        return audience

    def _step_ideal(self, link: LinkState | None, n: int, deliveries: list[list[Delivery]]) -> None:
        for sender in sorted(self._queues):
            queue = self._queues[sender]
            while queue:
                frame = queue.popleft()
                self._popped(sender, frame)
                message = frame.message
                audience = self._audience(message, n)
                if link is not None:  # the ideal disk: only receivers with a link
                    audience = tuple(j for j in audience if link.snr_db[sender, j] > -np.inf)
                    addressed = len(message.receivers) if message.receivers is not None else len(audience)
                else:
                    addressed = len(audience)
                counters = self._counters(message.kind, n)
                counters.packets_sent += 1
                counters.frames_sent += 1
                counters.bytes_sent += message.size_bytes
                counters.addressed += addressed
                counters.delivered += len(audience)
                counters.latencies_s += [0.0] * len(audience)
                for receiver in audience:
                    deliveries[receiver].append(Delivery(message, receiver, message.sent_s))

    # Tolerance on instants: airtimes are sums of microseconds; 1 ns never changes an order.
    _EPS_S = 1e-9

    # --- metrics ---------------------------------------------------------------------------------

    def _counters(self, kind: str, n: int) -> _KindCounters:
        counters = self._kinds.get(kind)
        if counters is None:
            counters = self._kinds[kind] = _KindCounters()
        if counters.airtime_s is None or len(counters.airtime_s) < n:
            grown = [0.0] * n
            if counters.airtime_s is not None:
                grown[:len(counters.airtime_s)] = counters.airtime_s
            counters.airtime_s = grown
        return counters

    def _totals(self) -> tuple[int, int, int]:
        sent = addressed = delivered = 0
        for counters in self._kinds.values():
            sent += counters.packets_sent
            addressed += counters.addressed
            delivered += counters.delivered
        return sent, addressed, delivered

    @property
    def last_tick(self) -> TickStats:
        """Per-tick values of the latest ``step``, for time series."""
        if self._last is None:
            self._last = TickStats(float(self._idle_s), 0, 0, math.nan, math.nan, 0)
        return self._last

    def summary(self) -> dict[str, float | int]:
        """``radio_*`` metrics over all steps so far, in total and per message kind (``radio_<kind>_*``).

        Packets are messages (a message of several frames counts once); the
        delivery ratio is deliveries over (message, receiver) pairs tried; the
        airtime share is the busiest robot's time on the air over the time
        stepped. Ratios and latencies of nothing are nan.
        """
        return self._summary_of(self._kinds)

    def _summary_of(self, kinds: dict[str, _KindCounters]) -> dict[str, float | int]:
        """``summary`` of these counters (in the order their kinds' counters were made)."""
        robots = max([self._n or 0] + [len(c.airtime_s) for c in kinds.values()])
        merged = _KindCounters(airtime_s=np.zeros(robots))
        for counters in kinds.values():
            merged.packets_sent += counters.packets_sent
            merged.frames_sent += counters.frames_sent
            merged.bytes_sent += counters.bytes_sent
            merged.addressed += counters.addressed
            merged.delivered += counters.delivered
            merged.latencies_s += counters.latencies_s
            merged.superseded += counters.superseded
            merged.airtime_s[:len(counters.airtime_s)] += counters.airtime_s
        result = self._metrics("radio", merged)
        result["radio_packets_queued"] = self.queued()
        for kind in sorted(kinds):
            counters = kinds[kind]
            result.update(self._metrics(f"radio_{kind}", counters))
        return result

    def _metrics(self, prefix: str, counters: _KindCounters) -> dict[str, float | int]:
        latencies = np.array(counters.latencies_s)
        airtime = (np.asarray(counters.airtime_s, dtype=float) if counters.airtime_s is not None
                   and len(counters.airtime_s) else np.zeros(1))
        return {
            f"{prefix}_packets_sent": counters.packets_sent,
            f"{prefix}_frames_sent": counters.frames_sent,
            f"{prefix}_packets_delivered": counters.delivered,
            f"{prefix}_delivery_ratio": counters.delivered / counters.addressed if counters.addressed else math.nan,
            f"{prefix}_bytes_sent": counters.bytes_sent,
            f"{prefix}_latency_mean_s": float(latencies.mean()) if latencies.size else math.nan,
            f"{prefix}_latency_p95_s": float(np.percentile(latencies, 95)) if latencies.size else math.nan,
            f"{prefix}_airtime_max_share": float(airtime.max() / self._elapsed_s) if self._elapsed_s else 0.0,
            f"{prefix}_packets_superseded": counters.superseded,
        }


class ReferenceMessageBus(_QueueBus):
    """The same bus, each period stepped by the plain loop that ``MessageBus``'s compiled scheduling replaces,
    and a superseding send's plain filter of the queue: the specification the fast bus is held to
    (tests/test_radio_bus_fast.py), frame by frame and draw by draw."""

    def send_all(self, messages: Any, time_s: float) -> None:
        for message in each_message(messages):
            self.send(message, time_s)

    def _supersede(self, queue: deque[_Frame], newer: Message) -> None:
        stale = {frame.message.sequence for frame in queue
                 if frame.message.latest_only and frame.message.kind == newer.kind
                 and frame.message.sequence not in self._in_flight}
        if stale:
            self._drop_superseded(queue, newer, stale, everything=False)

    def _step_medium(self, start_s: float, link: LinkState, n: int, deliveries: list[list[Delivery]]) -> None:
        end_s = start_s + self.control_period_s
        sense = np.asarray(link.carrier_sense, dtype=bool) | np.eye(n, dtype=bool)
        snr = np.nan_to_num(np.asarray(link.snr_db, dtype=float), nan=-np.inf)
        on_air_until = np.full(n, -np.inf)  # end of each robot's latest frame
        done = np.zeros(n, dtype=bool)  # its head frame does not fit in this period
        # Tolerance on instants: airtimes are sums of microseconds; 1 ns never changes an order.
        eps = self._EPS_S
        while True:
            ready = np.full(n, np.inf)
            for sender, queue in self._queues.items():
                if queue and not done[sender] and queue[0].message.sent_s < end_s - eps:
                    ready[sender] = max(start_s, queue[0].message.sent_s)
            if not np.isfinite(ready).any():
                return
            medium_free = np.where(sense, on_air_until[None, :], -np.inf).max(axis=1)
            start = np.maximum(ready, medium_free)
            earliest = start.min()
            tied = np.flatnonzero(start <= earliest + eps)
            sender = int(tied[self.rng.integers(len(tied))]) if len(tied) > 1 else int(tied[0])
            frame = self._queues[sender][0]
            finish = earliest + frame.airtime_s
            if finish > end_s + eps:
                done[sender] = True
                continue
            self._popped(sender, self._queues[sender].popleft())
            on_air_until[sender] = finish
            self._transmit(frame, finish, snr, n, deliveries)

    def _transmit(self, frame: _Frame, finish_s: float, snr: np.ndarray, n: int,
                  deliveries: list[list[Delivery]]) -> None:
        message = frame.message
        counters = self._counters(message.kind, n)
        counters.frames_sent += 1
        counters.airtime_s[message.sender] += frame.airtime_s
        flight = self._in_flight.get(message.sequence)
        if flight is None:
            audience = self._audience(message, n)
            flight = self._in_flight[message.sequence] = _InFlight(audience, np.ones(len(audience), dtype=bool))
        if flight.audience:
            receivers = np.array(flight.audience)
            fading = channel.fading_gain_db(self.params.fading_model, self.rng, len(receivers),
                                            self.params.rician_k)
            per = self.params.packet_error_rate(snr[message.sender, receivers] + fading, frame.payload_bytes)
            flight.alive &= self.rng.random(len(receivers)) >= per
        if not frame.last:
            return
        del self._in_flight[message.sequence]
        counters.packets_sent += 1
        counters.bytes_sent += message.size_bytes
        counters.addressed += len(flight.audience)
        for receiver, alive in zip(flight.audience, flight.alive):
            if alive:
                counters.delivered += 1
                counters.latencies_s.append(finish_s - message.sent_s)
                deliveries[receiver].append(Delivery(message, receiver, finish_s))


class MessageBus(_QueueBus):
    """Queues, airtime, loss and latency of every message. See the module docstring.

    Under a real preset the queues are a frame table (``sim.radio.medium``): a tick's outbox enters it in one
    compiled call (``_enqueue``) and a period is one compiled call (``_period``) that gathers, schedules,
    pops and books the frames, keeps the counters and makes the arrivals, so no Python object is made or
    touched per frame; only the messages not sent ``as_arrays`` are kept as objects, for their ``Delivery``s.
    Under 'ideal' it is ``_QueueBus``. ``ReferenceMessageBus`` is the plain loop both are held to."""

    def __init__(self, params: BusParameters, rng: np.random.Generator | None, control_period_s: float,
                 robot_count: int | None = None) -> None:
        self._tabled = False  # the queues are the frame table (a real preset), not _QueueBus's deques
        super().__init__(params, rng, control_period_s, robot_count)
        self._rng_pointers: tuple[Any, tuple[int, ...] | None] | None = None  # (rng, its pointers)
        if not params.is_ideal:
            self._enter_table()

    @property
    def params(self) -> BusParameters:
        return self._params

    @params.setter
    def params(self, params: BusParameters) -> None:
        """New parameters (the tuning page's retuning): as ``_QueueBus``'s, and the queues move between the
        deques and the frame table when the preset turns ideal or real."""
        self._params = params
        self._frames_of_size = {}
        self._flat_frames: dict[int, tuple[float, ...]] = {}  # ``_frames``' numbers of a size, flat
        self._batch_templates: dict[tuple, tuple] = {}  # ``_batch_template``'s per batch shape
        self._medium_constants: tuple | None = None  # ``_constants_of_medium``, made at the next period
        self._per_sender = (-1, 0)  # (frame sizes known, frames a period can take per sender) for ``_period``
        self._period_held: tuple | None = None  # ``_hold_period``'s, for the next period
        self._table_generation = getattr(self, "_table_generation", 0) + 1  # the medium's constants changed
        if not hasattr(self, "_kinds"):  # still in __init__
            return
        if params.is_ideal and self._tabled:
            self._leave_table()
        elif not params.is_ideal and not self._tabled:
            self._enter_table()

    # --- the frame table ---------------------------------------------------------------------------

    def _enter_table(self) -> None:
        """Make the frame table and move the deques' frames and the kinds' counters into it."""
        robots = max([self._n or 1] + [s + 1 for s in self._queues] + [
            max(f.message.receivers or (0,)) + 1 for q in self._queues.values() for f in q])
        self._tabled = True
        self._slots = 0
        self._robots_held = 0
        self._ints = np.empty((0, 7), dtype=np.int64)
        self._floats = np.empty((0, 5))
        self._listed = np.empty((0, 1), dtype=np.int64)
        self._free = np.empty(0, dtype=np.int64)
        self._counts = np.zeros(4, dtype=np.int64)
        self._queue_rows = np.empty((0, 4), dtype=np.int64)
        self._alive = np.zeros((0, 0), dtype=np.bool_)
        self._kind_rows = np.empty((0, 7), dtype=np.int64)
        self._kind_airtime = np.zeros((0, 1))
        self._kind_ids: dict[str, int] = {}
        self._kind_names: list[str] = []
        self._log_latency = np.empty(1024)
        self._log_kind = np.empty(1024, dtype=np.int64)
        self._objects: dict[int, Message] = {}  # the queued messages not sent as_arrays, by sequence
        self._dropped = np.empty(64, dtype=np.int64)
        self._scratch_rows: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._present = np.empty(0, dtype=np.int64)  # the period's groups with arrivals (scratch)
        self._arrival_columns: tuple[np.ndarray, np.ndarray] | None = None  # the last period's arrivals
        self._tally = np.zeros(2, dtype=np.int64)  # _schedule_frames' (unsure draws, draws lost in it)
        self._hold_robots(robots)
        self._hold_slots(64)
        self._table_generation += 1
        for name, counters in self._kinds.items():  # in the order they were made
            kind = self._kind(name)
            self._kind_rows[kind, :medium.K_RANK + 1] = (
                counters.packets_sent, counters.frames_sent, counters.bytes_sent, counters.addressed,
                counters.delivered, counters.superseded, self._counts[medium.T_KINDS_MADE])
            self._counts[medium.T_KINDS_MADE] += 1
            self._kind_airtime[kind, :len(counters.airtime_s)] = counters.airtime_s
            self._log(np.asarray(counters.latencies_s, dtype=float), kind)
        for sender, queue in self._queues.items():
            for frame in queue:
                message = frame.message
                self._hold_slots(1)
                self._counts[medium.T_FREE] -= 1
                slot = self._free[self._counts[medium.T_FREE]]
                flags = ((medium.LAST if frame.last else 0) | (medium.AS_ARRAYS if message.as_arrays else 0)
                         | (medium.LATEST_ONLY if message.latest_only else 0))
                self._ints[slot] = (sender, message.sequence, self._kind(message.kind), flags, -1,
                                    message.size_bytes, frame.payload_bytes)
                audience = -1 if message.receivers is None else len(message.receivers)
                self._floats[slot] = (message.sent_s, frame.airtime_s, frame.error_bits, audience,
                                      float(message.payload) if message.as_arrays else 0.0)
                if audience > 0:
                    self._listed[slot, :audience] = message.receivers
                tail = self._queue_rows[sender, medium.Q_TAIL]
                if tail < 0:
                    self._queue_rows[sender, medium.Q_HEAD] = slot
                else:
                    self._ints[tail, medium.I_NEXT] = slot
                self._queue_rows[sender, medium.Q_TAIL] = slot
                if not message.as_arrays:
                    self._objects[message.sequence] = message
                flight = self._in_flight.get(message.sequence)
                if flight is not None:
                    self._queue_rows[sender, medium.Q_FLYING] = message.sequence
                    self._alive[sender, :len(flight.audience)] = flight.alive
            self._queue_rows[sender, medium.Q_WAITING] = self._waiting.get(sender, 0)
        self._counts[medium.T_WAITING] = self._waiting_total
        # the frames moved in bound a period's frames per sender with their airtimes too (0 under 'ideal')
        self._shortest_held_s = min([f.airtime_s for q in self._queues.values() for f in q], default=np.inf)
        self._queues, self._waiting, self._waiting_total, self._in_flight, self._kinds = {}, {}, 0, {}, {}

    def _leave_table(self) -> None:
        """Move the frame table's frames and counters back into ``_QueueBus``'s deques and counters."""
        self._kinds = self._table_counters()
        n = self._robots_held
        for sender in range(n):
            slot = int(self._queue_rows[sender, medium.Q_HEAD])
            queue: deque[_Frame] = deque()
            while slot >= 0:
                (_, sequence, kind, flags, following, size, payload_bytes) = self._ints[slot].tolist()
                sent_s, airtime_s, error_bits, audience, value = self._floats[slot].tolist()
                message = self._objects.get(sequence)
                if message is None:  # sent as_arrays: its Message again, as it was stamped
                    message = _new_object(Message)
                    message.__dict__.update(
                        kind=self._kind_names[kind], sender=sender,
                        receivers=None if audience < 0 else tuple(self._listed[slot, :int(audience)].tolist()),
                        payload=value, size_bytes=size, sequence=sequence, sent_s=sent_s,
                        latest_only=bool(flags & medium.LATEST_ONLY), as_arrays=True)
                queue.append(_Frame(message, payload_bytes, bool(flags & medium.LAST), airtime_s, error_bits))
                if sequence == self._queue_rows[sender, medium.Q_FLYING]:
                    audience_size = n - 1 if audience < 0 else int(audience)
                    self._in_flight[sequence] = _InFlight(self._audience(message, n),
                                                          self._alive[sender, :audience_size].tolist())
                slot = following
            if queue:
                self._queues[sender] = queue
            self._waiting[sender] = int(self._queue_rows[sender, medium.Q_WAITING])
        self._waiting_total = int(self._counts[medium.T_WAITING])
        self._tabled = False

    def _table_counters(self) -> dict[str, _KindCounters]:
        """The table's per-kind counters as ``_QueueBus`` keeps them, in the order they were made."""
        logged = int(self._counts[medium.T_LOGGED])
        latencies, latency_kinds = self._log_latency[:logged], self._log_kind[:logged]
        made = [(int(self._kind_rows[kind, medium.K_RANK]), kind) for kind in range(len(self._kind_names))
                if self._kind_rows[kind, medium.K_RANK] >= 0]
        kinds = {}
        for _, kind in sorted(made):
            packets, frames, sent_bytes, addressed, delivered, superseded, _ = self._kind_rows[kind].tolist()
            kinds[self._kind_names[kind]] = _KindCounters(
                packets, frames, sent_bytes, addressed, delivered, latencies[latency_kinds == kind].tolist(),
                self._kind_airtime[kind, :self._robots_held].tolist(), superseded)
        return kinds

    def _hold_slots(self, more: int) -> None:
        """Room in the table for ``more`` frames."""
        if self._counts[medium.T_FREE] >= more:
            return
        old = self._slots
        slots = max(2 * old, old + more, 64)
        self._ints = np.concatenate([self._ints, np.zeros((slots - old, 7), dtype=np.int64)])
        self._floats = np.concatenate([self._floats, np.zeros((slots - old, 5))])
        self._listed = np.concatenate([self._listed, np.zeros((slots - old, self._listed.shape[1]),
                                                              dtype=np.int64)])
        free = np.empty(slots, dtype=np.int64)
        held = int(self._counts[medium.T_FREE])
        free[:held] = self._free[:held]
        free[held:held + slots - old] = np.arange(old, slots)
        self._free = free
        self._counts[medium.T_FREE] += slots - old
        self._slots = slots
        self._table_generation += 1

    def _hold_robots(self, robots: int) -> None:
        """Room for senders and receivers 0 .. robots - 1."""
        old = self._robots_held
        if robots <= old:
            return
        queue_rows = np.empty((robots, 4), dtype=np.int64)
        queue_rows[:old] = self._queue_rows
        queue_rows[old:] = (-1, -1, 0, -1)
        self._queue_rows = queue_rows
        alive = np.zeros((robots, robots), dtype=np.bool_)
        alive[:old, :old] = self._alive
        self._alive = alive
        listed = np.zeros((self._listed.shape[0], robots), dtype=np.int64)
        listed[:, :self._listed.shape[1]] = self._listed
        self._listed = listed
        airtime = np.zeros((self._kind_airtime.shape[0], robots))
        airtime[:, :self._kind_airtime.shape[1]] = self._kind_airtime
        self._kind_airtime = airtime
        self._robots_held = robots
        self._table_generation += 1

    def _kind(self, name: str) -> int:
        """The table's number of a message kind (its row of counters)."""
        kind = self._kind_ids.get(name)
        if kind is None:
            kind = self._kind_ids[name] = len(self._kind_names)
            self._kind_names.append(name)
            if kind >= len(self._kind_rows):
                rows = np.zeros((2 * kind + 2, 7), dtype=np.int64)
                rows[:, medium.K_RANK] = -1
                rows[:kind] = self._kind_rows
                self._kind_rows = rows
                airtime = np.zeros((len(rows), self._kind_airtime.shape[1]))
                airtime[:kind] = self._kind_airtime
                self._kind_airtime = airtime
                self._table_generation += 1
        return kind

    def _log(self, latencies: np.ndarray, kind: int) -> None:
        """Append latencies of one kind to the table's log (what ``book`` does as it goes)."""
        logged = int(self._counts[medium.T_LOGGED])
        self._hold_log(len(latencies))
        self._log_latency[logged:logged + len(latencies)] = latencies
        self._log_kind[logged:logged + len(latencies)] = kind
        self._counts[medium.T_LOGGED] += len(latencies)

    def _hold_log(self, more: int) -> None:
        logged = int(self._counts[medium.T_LOGGED])
        if logged + more > len(self._log_latency):
            size = max(2 * len(self._log_latency), logged + more)
            latency, kinds = np.empty(size), np.empty(size, dtype=np.int64)
            latency[:logged] = self._log_latency[:logged]
            kinds[:logged] = self._log_kind[:logged]
            self._log_latency, self._log_kind = latency, kinds
            self._table_generation += 1

    # --- sending -----------------------------------------------------------------------------------

    def send(self, message: Message, time_s: float) -> Message:
        if not self._tabled:
            return super().send(message, time_s)
        sequence = self._sequence
        self.send_all((message,), time_s)
        return self._objects.get(sequence) or _stamped(message, sequence, float(time_s))

    def send_all(self, messages: Any, time_s: float) -> None:
        """``send`` each of ``messages`` at ``time_s``, in order (a tick's outbox), into the frame table in one
        compiled call."""
        if not self._tabled:
            return super().send_all(messages, time_s)
        time_s = float(time_s)
        if type(messages) is tuple and len(messages) == 1 and type(messages[0]) is Broadcasts:
            # the consensus alone (most ticks): its kept rows go in as they are
            batch = messages[0]
            rows, frames, top = self._batch_template(batch)
            if len(batch):
                self._enqueue(rows, batch.values, _NO_ROBOTS, frames, top, time_s)
            return
        robots = self._n
        kind_ids, objects = self._kind_ids, self._objects
        start = sequence = self._sequence
        # the rows of _enqueue's arrays, flat (array.array extends from a tuple without a Python loop); each
        # message's sequence from the first one's
        rows, values, listed, spec = array("q"), array("d"), array("q"), array("d")
        top = -1  # the highest robot named
        try:
            for message in messages:
                if type(message) is Broadcasts:
                    block, frames, highest = self._batch_template(message)
                    block = block.reshape(-1, 7).copy()
                    block[:, 1] += sequence - start
                    rows.frombytes(block.tobytes())
                    values.frombytes(message.values.tobytes())
                    spec.frombytes(frames.tobytes())
                    sequence += len(message)
                    top = max(top, highest)
                    continue
                sender = message.sender
                receivers = message.receivers
                if robots is not None and (not 0 <= sender < robots or (
                        receivers and any(not 0 <= r < robots for r in receivers))):
                    raise ValueError(f"message {message.kind!r} names a robot outside 0..{robots - 1}")
                frames = self._flat_frames.get(message.size_bytes)
                if frames is None:
                    frames = self._flat_frames[message.size_bytes] = tuple(chain.from_iterable(
                        self._frames(message.size_bytes)))
                kind = kind_ids.get(message.kind)
                if kind is None:
                    kind = self._kind(message.kind)
                fields = message.__dict__
                if fields["as_arrays"]:
                    flags = medium.AS_ARRAYS
                    values.append(fields["payload"])
                else:
                    stamped = objects[sequence] = _new_object(type(message))
                    stamped.__dict__.update(fields)
                    stamped.__dict__["sequence"] = sequence
                    stamped.__dict__["sent_s"] = time_s
                    flags = 0
                    values.append(0.0)
                if fields["latest_only"]:
                    flags |= medium.LATEST_ONLY
                if receivers is None:
                    audience = -1
                else:
                    audience = len(receivers)
                    listed.extend(receivers)
                if sender > top:
                    top = sender
                rows.extend((sender, sequence - start, kind, flags, message.size_bytes, len(frames) // 3, audience))
                spec.extend(frames)
                sequence += 1
        finally:
            if rows:
                self._enqueue(np.frombuffer(rows, dtype=np.int64), np.frombuffer(values),
                              np.frombuffer(listed, dtype=np.int64), np.frombuffer(spec),
                              max(top, max(listed, default=-1)), time_s, start)
            else:
                self._sequence = sequence

    def _batch_template(self, batch: Broadcasts) -> tuple[np.ndarray, np.ndarray, int]:
        """A ``Broadcasts`` item's rows for ``_enqueue`` (flat; sequences from 0), its frames' rows (flat), and
        the highest robot it names: what ``send_all`` makes of its messages one by one. Kept per kind, size,
        flags and count when every robot sends (the consensus, every tick)."""
        senders = batch.senders
        key = (batch.kind, batch.size_bytes, batch.latest_only, len(batch.values)) if senders is None else None
        template = self._batch_templates.get(key)
        if template is None:
            count = len(batch)
            frames = self._flat_frames.get(batch.size_bytes)
            if frames is None:
                frames = self._flat_frames[batch.size_bytes] = tuple(chain.from_iterable(
                    self._frames(batch.size_bytes)))
            flags = medium.AS_ARRAYS | (medium.LATEST_ONLY if batch.latest_only else 0)
            # sender, sequence (from 0), kind, flags, size, frames, audience (-1: a broadcast)
            block = np.array([(0, 0, self._kind(batch.kind), flags, batch.size_bytes, len(frames) // 3, -1)],
                             dtype=np.int64).repeat(count, axis=0)
            block[:, 0] = batch.sender_indices()
            block[:, 1] = np.arange(count)
            highest = int(block[:, 0].max(initial=-1))
            template = (block.reshape(-1), np.tile(np.array(frames, dtype=float), count), highest)
            if key is not None:
                self._batch_templates[key] = template
        robots = self._n
        if robots is not None and (template[2] >= robots or (senders is not None and len(senders)
                                                             and senders.min() < 0)):
            raise ValueError(f"message {batch.kind!r} names a robot outside 0..{robots - 1}")
        return template

    def _enqueue(self, rows: np.ndarray, values: np.ndarray, listed: np.ndarray, spec: np.ndarray, top: int,
                 time_s: float, first_sequence: int | None = None) -> None:
        """``medium._enqueue`` of these rows sent at ``time_s``, their sequences from ``first_sequence`` (the
        next one when None), the table made large enough first."""
        first_sequence = self._room_to_enqueue(len(values), len(spec) // 3, top, first_sequence)
        dropped = compiled_call(medium._enqueue, (self._ints, self._floats, self._listed, self._queue_rows, self._free,
                                                  self._counts, self._kind_rows, rows, values, listed, spec,
                                                  first_sequence, time_s, self._dropped), ("enqueue",))
        self._forget_superseded(dropped)

    def _room_to_enqueue(self, messages: int, frames: int, top: int, first_sequence: int | None) -> int:
        """The first of ``messages`` sequences from ``first_sequence`` (the next one when None), taken, and room
        in the table for them, their ``frames`` and senders up to ``top``, made first."""
        if first_sequence is None:
            first_sequence = self._sequence
        self._sequence = first_sequence + messages
        counts = self._counts
        if top >= self._robots_held:
            self._hold_robots(top + 1)
        if counts[medium.T_FREE] < frames:
            self._hold_slots(frames)
        if len(self._dropped) < counts[medium.T_WAITING] + messages:
            self._dropped = np.empty(2 * (counts[medium.T_WAITING] + messages), dtype=np.int64)
        return first_sequence

    def _forget_superseded(self, count: int) -> None:
        """Let go of the objects of the ``count`` messages ``medium._enqueue`` superseded (in ``_dropped``)."""
        if count and self._objects:
            for sequence in self._dropped[:count].tolist():
                self._objects.pop(sequence, None)

    # --- one control period ------------------------------------------------------------------------

    def queued(self, sender: int | None = None) -> int:
        if not self._tabled:
            return super().queued(sender)
        if sender is None:
            return int(self._counts[medium.T_WAITING])
        return int(self._queue_rows[sender, medium.Q_WAITING]) if 0 <= sender < self._robots_held else 0

    def _queues_busy(self) -> bool:
        if not self._tabled:
            return super()._queues_busy()
        return self._counts[medium.T_WAITING] > 0

    def step(self, time_s: float, link: LinkState | None) -> list[list[Delivery]]:
        if not self._tabled:
            return super().step(time_s, link)
        n, rows = self._table_step(time_s, link)
        return [[] for _ in range(n)] if rows is None else rows

    def inbox(self, time_s: float, link: LinkState | None) -> tuple[tuple[Delivery, ...], ...] | None:
        if not self._tabled:
            return super().inbox(time_s, link)
        _, rows = self._table_step(time_s, link)
        return None if rows is None else tuple(map(tuple, rows))

    def exchange(self, outbox: Any, time_s: float, link_of: Callable[[], LinkState]
                 ) -> tuple[tuple[Delivery, ...], ...] | None | bool:
        if not self._tabled or type(outbox) is not tuple or len(outbox) != 1 or type(outbox[0]) is not Broadcasts:
            return super().exchange(outbox, time_s, link_of)
        # An outbox of one batch (the consensus alone, most ticks): it enters the table and the period runs in
        # one compiled call, as send_all then inbox would
        batch = outbox[0]
        rows, frames, top = self._batch_template(batch)
        held = self._period_held
        if not len(batch) or held is None or not held[6]:  # nothing sent, or the kernels not compiled
            return super().exchange(outbox, time_s, link_of)
        time_s = float(time_s)
        self._arrivals = {}
        n, sense, snr = self._link_arrays(link_of())
        values, frames_sent = batch.values, len(frames) // 3
        first_sequence = self._room_to_enqueue(len(values), frames_sent, top, None)
        held, columns, arrived = self._period_room(n, frames_sent)
        superseded, result = compiled_call(medium._enqueue_then_period_at, held[5] + (
            self._dropped, rows, values, _NO_ROBOTS, frames, first_sequence, time_s, time_s,
            time_s + self.control_period_s, sense, snr, columns, arrived),
            ("enqueue, period", sense.flags.writeable, snr.flags.writeable))
        self._forget_superseded(superseded)
        if result[0] < 0:
            result = self._finish_period(result, n, columns, arrived)
        deliveries = self._take_period(n, time_s, result)
        return None if deliveries is None else tuple(map(tuple, deliveries))

    def _table_step(self, time_s: float, link: LinkState | None) -> tuple[int, list[list[Delivery]] | None]:
        """``step`` over the frame table: the robots, and their rows (None when no row holds a delivery)."""
        self._arrivals = {}
        if not self._counts[medium.T_WAITING]:  # nothing queued, nothing in flight
            self._elapsed_s += self.control_period_s
            self._last = None  # an empty period at self._idle_s, built only when read
            self._idle_s = time_s
            return (self._robot_count(link) if link is not None else self._n or 0), None
        n, sense, snr = self._link_arrays(link)
        return n, self._take_period(n, float(time_s), self._period(float(time_s), sense, snr, n))

    def _link_arrays(self, link: LinkState | None) -> tuple[int, np.ndarray, np.ndarray]:
        """(N, carrier sense, SNR) of a period's link state, checked, the table's robots made room for."""
        if link is None:
            raise ValueError(f"the {self.params.name!r} bus needs this tick's link state")
        if type(link) is medium.LinkMatrices:  # the channel's own: C arrays of their types, (N, N) each
            snr, sense = link.snr_db, link.carrier_sense
            n = len(snr)
            if n != self._n:
                n = self._robot_count(link)
        else:
            n = self._robot_count(link)
            sense = np.ascontiguousarray(link.carrier_sense, dtype=bool)
            snr = np.ascontiguousarray(link.snr_db, dtype=float)
            if sense.shape != (n, n) or snr.shape != (n, n):
                raise ValueError(f"the link's arrays must be ({n}, {n})")
        if n > self._robots_held:
            self._hold_robots(n)
        return n, sense, snr

    def _take_period(self, n: int, time_s: float, result: tuple) -> list[list[Delivery]] | None:
        """A period's kernel's figures (``medium.book``'s) into the bus: its arrivals, the rows of the messages
        not sent as_arrays (None when there are none), the finished messages let go, the tick's figures."""
        sent, packets, addressed, delivered, entries, finished, present, latency_total_s = result
        self._elapsed_s += self.control_period_s
        deliveries = None
        if entries:
            columns, values = self._arrival_columns
            columns.flags.writeable = False  # before the views: they inherit it
            values.flags.writeable = False
            arrivals, names, others = self._arrivals, self._kind_names, len(self._kind_rows)
            groups = iter(self._present[:3 * present].tolist())
            for group, start, end in zip(groups, groups, groups):  # (group, first entry, end) triples
                if group < others:
                    columns_of_kind = _new_object(Arrivals)
                    columns_of_kind.__dict__.update(
                        receiver=columns[0, start:end], sender=columns[1, start:end], arrival_s=values[0, start:end],
                        sent_s=values[1, start:end], sequence=columns[2, start:end], payload=values[2, start:end])
                    arrivals[names[group]] = columns_of_kind
                else:  # the messages not sent as_arrays, in the rows' order
                    deliveries = [[] for _ in range(n)]
                    objects = self._objects
                    for receiver, sequence, arrival_s in zip(columns[0, start:end].tolist(),
                                                             columns[2, start:end].tolist(),
                                                             values[0, start:end].tolist()):
                        deliveries[receiver].append(_delivery(objects[sequence], receiver, arrival_s))
            latency_mean_s = latency_total_s / entries  # numpy.mean's sum (the kernel's) and division
        else:
            latency_mean_s = math.nan
        if finished:
            for sequence in self._scratch_rows[0][15, :finished].tolist():
                del self._objects[sequence]
        # TickStats(...) without the frozen dataclass's per-field __setattr__
        self._last = last = _new_object(TickStats)
        last.__dict__.update(time_s=float(time_s), packets_sent=packets, packets_delivered=delivered,
                             delivery_ratio=delivered / addressed if addressed else math.nan,
                             latency_mean_s=latency_mean_s, queued=int(self._counts[medium.T_WAITING]))
        return deliveries

    def _period(self, start_s: float, sense: np.ndarray, snr: np.ndarray, n: int) -> tuple:
        """The medium's period over the frame table (``medium._period``), numpy deciding the draws the kernel
        leaves to its exact PER."""
        held, columns, values = self._period_room(n, 0)
        end_s = start_s + self.control_period_s
        if held[6]:  # one signature per writeability of the link's arrays (a caller's read-only ones apart)
            result = compiled_call(medium._period_at, held[5] + (start_s, end_s, sense, snr, columns, values),
                                   ("period", sense.flags.writeable, snr.flags.writeable))
        else:  # numba's JIT disabled, or a generator that is not numpy's
            result = medium._period_with(self.rng, *held[5], start_s, end_s, sense, snr, columns, values)
        return result if result[0] >= 0 else self._finish_period(result, n, columns, values)

    def _period_room(self, n: int, more_frames: int) -> tuple[tuple, np.ndarray, np.ndarray]:
        """``_hold_period``'s kept arguments for a period over ``n`` robots with ``more_frames`` yet to enter the
        table, room in the latency log for what it can deliver, and the arrivals' two blocks (new each period:
        their views go out as ``arrivals``)."""
        held = self._period_held
        if (held is None or held[0] != self._table_generation or held[1] != n or held[2] is not self.rng
                or held[3] != len(self._frames_of_size)):
            held = self._hold_period(n)
        counts = self._counts
        # at most the frames in the table, or a period's most, go out, each to at most n - 1 receivers
        most = min(self._slots - int(counts[medium.T_FREE]) + more_frames, held[4]) * n + 1
        if counts[medium.T_LOGGED] + most > len(self._log_latency):
            self._hold_log(most)
            held = self._hold_period(n)
        columns = np.empty((3, most), dtype=np.int64)  # receiver, sender, sequence
        values = np.empty((3, most))  # arrival, send time, value
        self._arrival_columns = (columns, values)
        return held, columns, values

    def _finish_period(self, result: tuple, n: int, columns: np.ndarray, values: np.ndarray) -> tuple:
        """A period whose kernel left draws to numpy's exact PER (``result[0]`` -1): decide them, then book."""
        integers, reals, flags = self._scratch_rows
        constants = self._medium_constants
        # Some draws' SNR with fading lies too near the PER's edge for the kernel: numpy's exact PER decides them
        sent = result[1]
        draws = int(integers[2, sent])
        unsure = np.flatnonzero(flags[0, :draws])
        level = reals[2][unsure]
        if constants[0] != _NO_DRAW or self.params.fading_model != "none":
            fading_db = np.maximum(reals[4][unsure], np.finfo(float).tiny)
            np.log10(fading_db, out=fading_db)
            fading_db *= 10.0
            level = level + fading_db
        per = channel.packet_error_rate_at_snr(self.params.modulation, level, self.params.bandwidth_hz,
                                               self.params.bitrate_bps, reals[3][unsure])
        flags[1][unsure] = reals[5][unsure] >= per
        return medium.book(n, self._ints, self._floats, self._queue_rows, self._alive, self._free, self._counts,
                           self._kind_rows, self._kind_airtime, self._log_latency, self._log_kind, integers, reals,
                           flags, sent, columns, values, self._present)

    def _hold_period(self, n: int) -> tuple:
        """What every period over ``n`` robots passes the period's kernel until the table next grows (its
        arrays, the medium's constants, the Generator's pointers and scratch rows wide enough for the most
        frames a period can gather), kept with what it depends on: (table generation, n, rng, frame sizes
        known, the most frames a period can take, the kernel's fixed arguments, whether compiled)."""
        constants = self._medium_constants
        if constants is None:
            constants = self._medium_constants = self._constants_of_medium()
        # The frames a period can gather: per sender those whose airtime before them fits, and one more
        reach_s = self.control_period_s + 1e-6
        sizes, per_sender = self._per_sender
        if sizes != len(self._frames_of_size):  # a new frame size since: its airtime may be the shortest
            shortest = self._shortest_airtime_s
            per_sender = int(reach_s / shortest) + 2 if shortest > 0 else -1
            self._per_sender = (len(self._frames_of_size), per_sender)
        per_period = self._slots if per_sender < 0 else n * per_sender
        gathered = min(self._slots, per_period)
        width = max(4 * gathered, gathered * n, n, 255) + 1
        rows = self._scratch_rows
        if rows is None or rows[0].shape[1] < width:
            rows = self._scratch_rows = (np.empty((16, width), dtype=np.int64), np.empty((9, width)),
                                         np.empty((2, width), dtype=np.bool_))
        if len(self._present) < 3 * (len(self._kind_rows) + 1):
            self._present = np.empty(3 * (len(self._kind_rows) + 1), dtype=np.int64)
        pointers = self._pointers()
        compiled = pointers is not None and getattr(medium._period_at, "overloads", None) is not None
        fixed = ((pointers if compiled else ()) + (
            self._EPS_S, reach_s, self._ints, self._floats, self._listed, self._queue_rows, self._alive, self._free,
            self._counts, self._kind_rows, self._kind_airtime, self._log_latency, self._log_kind, *constants, *rows,
            self._tally, self._present))
        held = self._period_held = (self._table_generation, n, self.rng, len(self._frames_of_size), per_period,
                                    fixed, compiled)
        return held

    @property
    def _shortest_airtime_s(self) -> float:
        """The shortest airtime of a frame queued under these parameters or earlier ones (bounds a period's
        frames per sender)."""
        shortest = min((frame[1] for frames in self._frames_of_size.values() for frame in frames), default=np.inf)
        held = getattr(self, "_shortest_held_s", np.inf)
        if shortest < held:
            self._shortest_held_s = held = shortest
        return held

    def _constants_of_medium(self) -> tuple[int, float, float, float, bool]:
        """The scheduling kernel's arguments that only the parameters set: how it draws the fading gain, the
        Rician noncentrality and the gain's divisor, the zero-BER SNR and whether it computes 802.15.4 PERs."""
        fading_code, gain_scale = self._fading_draw
        modulation = self.params.modulation
        return (int(fading_code), float(2.0 * self.params.rician_k), float(gain_scale),
                float(_ZERO_BER_SNR_DB.get(modulation, np.inf)), modulation == "oqpsk_dsss_802154")

    def _pointers(self) -> tuple[int, ...] | None:
        """``sim.compiled.generator_pointers`` of ``self.rng`` (None for a generator that is not numpy's),
        kept with the generator they belong to."""
        held = self._rng_pointers
        if held is None or held[0] is not self.rng:
            pointers = generator_pointers(self.rng) if isinstance(self.rng, np.random.Generator) else None
            held = self._rng_pointers = (self.rng, pointers)
        return held[1]

    @property
    def _fading_draw(self) -> tuple[int, float]:
        """How ``_schedule_frames`` draws the fading gain of this bus's model, and the gain's divisor."""
        fading, rician_k = self.params.fading_model, self.params.rician_k
        if fading == "none" or (fading == "rician" and math.isinf(rician_k)):
            return _NO_DRAW, 1.0
        if fading == "rayleigh" or (fading == "rician" and rician_k == 0):
            return _EXPONENTIAL, 1.0
        if fading == "rician":
            if rician_k < 0:
                raise ValueError("the Rician K-factor must be >= 0")
            return _NONCENTRAL_CHISQUARE, 2.0 * (rician_k + 1.0)
        raise ValueError(f"unknown fading model {fading!r}; known: {', '.join(channel.FADING_MODELS)}")


    # --- metrics -----------------------------------------------------------------------------------

    def summary(self) -> dict[str, float | int]:
        return self._summary_of(self._table_counters() if self._tabled else self._kinds)


