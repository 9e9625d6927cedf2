"""The message bus: every message a robot sends, with its real size, over a shared, lossy medium.

Pure Python and numpy, no MuJoCo. Time advances in control periods: the
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

import math
from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any, Protocol

import numpy as np

from sim.radio import channel
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

    def __post_init__(self) -> None:
        if not isinstance(self.size_bytes, (int, np.integer)) or self.size_bytes <= 0:
            raise ValueError(f"size_bytes must be a positive integer, got {self.size_bytes!r}")
        if self.receivers is not None:
            if not isinstance(self.receivers, tuple):
                raise ValueError("receivers must be a tuple of robot indices or None")
            if self.sender in self.receivers:
                raise ValueError(f"robot {self.sender} sends message {self.kind!r} to itself")
            if len(set(self.receivers)) != len(self.receivers):
                raise ValueError("receivers must not repeat")


@dataclass(frozen=True)
class Delivery:
    """A message arriving at one receiver."""

    message: Message
    receiver: int
    arrival_s: float  # end of the message's last frame (its send time under 'ideal'), s

    @property
    def latency_s(self) -> float:
        return self.arrival_s - self.message.sent_s


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


@dataclass
class _Frame:
    message: Message
    payload_bytes: int
    last: bool
    airtime_s: float


@dataclass
class _InFlight:
    """A message whose frames are going out: the receivers still holding every frame."""

    audience: tuple[int, ...]
    alive: np.ndarray  # bool per audience member


@dataclass
class _KindCounters:
    packets_sent: int = 0
    frames_sent: int = 0
    bytes_sent: int = 0
    addressed: int = 0  # (message, receiver) pairs tried
    delivered: int = 0
    latencies_s: list[float] = field(default_factory=list)
    airtime_s: np.ndarray | None = None  # per robot, s
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


class MessageBus:
    """Queues, airtime, loss and latency of every message. See the module docstring."""

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
        self._in_flight: dict[int, _InFlight] = {}
        self._kinds: dict[str, _KindCounters] = {}
        self._elapsed_s = 0.0
        self._last: TickStats | None = TickStats(math.nan, 0, 0, math.nan, math.nan, 0)
        self._idle_s = math.nan

    # --- sending ---------------------------------------------------------------------------------

    def send(self, message: Message, time_s: float) -> Message:
        """Queue ``message`` at its sender at ``time_s``; returns it with its ``sequence`` and ``sent_s``."""
        if self._n is not None:
            targets = message.receivers or ()
            if not 0 <= message.sender < self._n or any(not 0 <= r < self._n for r in targets):
                raise ValueError(f"message {message.kind!r} names a robot outside 0..{self._n - 1}")
        stamped = replace(message, sequence=self._sequence, sent_s=float(time_s))
        self._sequence += 1
        queue = self._queues.setdefault(stamped.sender, deque())
        if stamped.latest_only and queue:
            self._supersede(queue, stamped)
        frames: list[_Frame] = []
        if self.params.is_ideal:
            frames.append(_Frame(stamped, stamped.size_bytes, True, 0.0))
        else:
            payloads = self.params.frame_payloads(stamped.size_bytes)
            airtimes = self.params.airtime_s(np.array(payloads))
            if airtimes.max() > self.control_period_s:
                raise ValueError(f"a {self.params.name} frame takes {airtimes.max():.6f} s, longer than the "
                                 f"control period {self.control_period_s} s: it would never go out")
            for k, (payload, airtime) in enumerate(zip(payloads, airtimes)):
                frames.append(_Frame(stamped, payload, k == len(payloads) - 1, float(airtime)))
        queue.extend(frames)
        return stamped

    def _supersede(self, queue: deque[_Frame], newer: Message) -> None:
        """Drop from ``queue`` the waiting latest_only messages of ``newer``'s kind (none of their frames
        sent); ``newer`` then joins the queue's end, as a fresh frame in a transmit buffer does."""
        stale = {frame.message.sequence for frame in queue
                 if frame.message.latest_only and frame.message.kind == newer.kind
                 and frame.message.sequence not in self._in_flight}
        if stale:
            kept = [frame for frame in queue if frame.message.sequence not in stale]
            queue.clear()
            queue.extend(kept)
            self._counters(newer.kind, self._n or newer.sender + 1).superseded += len(stale)

    def queued(self, sender: int | None = None) -> int:
        """Messages waiting (some of their frames not yet on the air), at ``sender`` or at all."""
        queues = self._queues.values() if sender is None else [self._queues.get(sender, deque())]
        return sum(sum(frame.last for frame in queue) for queue in queues)

    # --- one control period ----------------------------------------------------------------------

    def step(self, time_s: float, link: LinkState | None) -> list[list[Delivery]]:
        """Advance [time_s, time_s + control period): returns each robot's deliveries, by arrival time.

        ``link`` gives this tick's (N, N) ``snr_db`` and ``carrier_sense``; under
        'ideal' it may be None (a broadcast then reaches every other robot).
        """
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
        if self.params.is_ideal:
            self._step_ideal(link, n, deliveries)
        else:
            if link is None:
                raise ValueError(f"the {self.params.name!r} bus needs this tick's link state")
            self._step_medium(float(time_s), link, n, deliveries)
        self._elapsed_s += self.control_period_s
        for row in deliveries:
            row.sort(key=lambda d: (d.arrival_s, d.message.sequence))
        after = self._totals()
        sent, addressed, delivered = (a - b for a, b in zip(after, before))
        latencies = [d.latency_s for row in deliveries for d in row]
        self._last = TickStats(float(time_s), sent, delivered, delivered / addressed if addressed else math.nan,
                               float(np.mean(latencies)) if latencies else math.nan, self.queued())
        return deliveries

    def _queues_busy(self) -> bool:
        return any(self._queues.values()) if self._queues else False

    @property
    def idle(self) -> bool:
        """Nothing waits to go out: the next ``step`` needs no link state and costs next to nothing."""
        return not self._queues_busy()

    def _robot_count(self, link: LinkState | None) -> int:
        if link is not None:
            n = int(np.shape(link.snr_db)[0])
            if self._n is not None and n != self._n:
                raise ValueError(f"the link has {n} robots, the bus {self._n}")
            self._n = n
        if self._n is None:
            senders = max(self._queues, default=-1)
            receivers = max((max(f.message.receivers or (-1,)) for q in self._queues.values() for f in q),
                            default=-1)
            return max(senders, receivers) + 1
        return self._n

    def _audience(self, message: Message, n: int) -> tuple[int, ...]:
        if message.receivers is not None:
            return message.receivers
        return tuple(j for j in range(n) if j != message.sender)

    def _step_ideal(self, link: LinkState | None, n: int, deliveries: list[list[Delivery]]) -> None:
        for sender in sorted(self._queues):
            queue = self._queues[sender]
            while queue:
                message = queue.popleft().message
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

    def _step_medium(self, start_s: float, link: LinkState, n: int, deliveries: list[list[Delivery]]) -> None:
        end_s = start_s + self.control_period_s
        sense = np.asarray(link.carrier_sense, dtype=bool) | np.eye(n, dtype=bool)
        snr = np.nan_to_num(np.asarray(link.snr_db, dtype=float), nan=-np.inf)
        on_air_until = np.full(n, -np.inf)  # end of each robot's latest frame
        done = np.zeros(n, dtype=bool)  # its head frame does not fit in this period
        # Tolerance on instants: airtimes are sums of microseconds; 1 ns never changes an order.
        eps = 1e-9
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
            self._queues[sender].popleft()
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

    # --- metrics ---------------------------------------------------------------------------------

    def _counters(self, kind: str, n: int) -> _KindCounters:
        counters = self._kinds.setdefault(kind, _KindCounters())
        if counters.airtime_s is None or len(counters.airtime_s) < n:
            grown = np.zeros(n)
            if counters.airtime_s is not None:
                grown[:len(counters.airtime_s)] = counters.airtime_s
            counters.airtime_s = grown
        return counters

    def _totals(self) -> tuple[int, int, int]:
        return (sum(c.packets_sent for c in self._kinds.values()), sum(c.addressed for c in self._kinds.values()),
                sum(c.delivered for c in self._kinds.values()))

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
        robots = max([self._n or 0] + [len(c.airtime_s) for c in self._kinds.values()])
        merged = _KindCounters(airtime_s=np.zeros(robots))
        for counters in self._kinds.values():
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
        for kind in sorted(self._kinds):
            counters = self._kinds[kind]
            result.update(self._metrics(f"radio_{kind}", counters))
        return result

    def _metrics(self, prefix: str, counters: _KindCounters) -> dict[str, float | int]:
        latencies = np.array(counters.latencies_s)
        airtime = counters.airtime_s if counters.airtime_s is not None and len(counters.airtime_s) else np.zeros(1)
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
