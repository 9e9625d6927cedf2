"""The radio channel of every robot pair, evaluated each tick: ``RadioChannel`` -> ``RadioState``.

Per pair i < j (batched over the N (N - 1) / 2 pairs): log-distance path loss
from the reference loss, the walls the segment crosses (``sim.radio.walls``,
each box's loss from the scene or ``radio.wall_loss_db``), log-normal
shadowing as a per-pair AR(1) in time (correlation exp(-dt / tau)), the mean
SNR over the noise floor and the delivery probability of the reference
packet (PER from the modulation's BER, ``sim.radio.channel``). Per-packet
fading is left to the message bus.

The shadowing advances once per distinct tick time, whoever reads the state,
so the draws depend only on the seed and the ticks; the rest is computed on
first read. Its generator is the caller's own (spawned from the run's, so it
never shifts the other streams). Under ``ideal`` nothing is drawn and the
delivery is the links' adjacency. Pure numpy: no MuJoCo.
"""

from __future__ import annotations

import numpy as np

from sim.compiled import compiled_call, generator_at, generator_pointers, kernel
from sim.geometry import Boxes
from sim.radio import channel
from sim.radio.config import RadioConfig
from sim.radio.medium import LinkMatrices, write_pair_matrices
from sim.radio.walls import SceneWalls, _pair_crossings
from sim.types import Links, RadioState


class RadioChannel:
    def __init__(self, config: RadioConfig, obstacles: Boxes, wall_loss_db: np.ndarray | None,
                 comm_range_m: float, rng: np.random.Generator):
        self.config = config
        self.obstacles = obstacles
        scene = np.full(len(obstacles), np.nan) if wall_loss_db is None else np.asarray(wall_loss_db, dtype=float)
        # The scene's figure where it gives one, the scenario's elsewhere.
        self.loss_per_box_db = np.where(np.isnan(scene), config.wall_loss_db, scene)
        self.walls = SceneWalls(obstacles, self.loss_per_box_db)
        self.comm_range_m = comm_range_m
        self.rng = rng
        self._pairs_n = -1
        self._shadowing: np.ndarray | None = None  # (P,) dB, the AR(1) state
        self._shadowing_time = -np.inf
        self._step: tuple[float, float, float] = (np.nan, 0.0, 0.0)  # dt, rho, innovation std of the last step
        self._rng_pointers: tuple | None = None  # (rng, sim.compiled.generator_pointers of it)
        self._figure_held: tuple | None = None  # ``_hold_figures``', for the next tick
        if not config.is_ideal:
            self._certain = self._certain_snr_db()

    def delivery_at_snr(self, snr_db: np.ndarray) -> np.ndarray:
        """Delivery probability of the reference packet at ``snr_db`` (dB): 1 - PER(BER(SNR))."""
        config = self.config
        ber = channel.bit_error_rate(config.radio.modulation, snr_db, config.radio.bandwidth_hz, config.bitrate_bps)
        return 1.0 - channel.packet_error_rate(ber, config.reference_length_bits)

    def _certain_snr_db(self) -> tuple[float, float]:
        """(below, above): SNRs (dB) at or below which the delivery is exactly 0.0 and at or above which
        it is exactly 1.0 in floating point; found by bisection on the curve itself, which never
        falls as the SNR rises, so pairs outside them are filled without evaluating it."""
        def edge(value: float, low: float, high: float) -> float:
            # invariant: delivery(inside) != value, delivery(outside) == value
            inside, outside = (low, high) if value == 1.0 else (high, low)
            if self.delivery_at_snr(np.array(outside)) != value:
                return np.inf if value == 1.0 else -np.inf
            for _ in range(80):
                middle = 0.5 * (inside + outside)
                if self.delivery_at_snr(np.array(middle)) == value:
                    outside = middle
                else:
                    inside = middle
            return outside

        return edge(0.0, -200.0, 200.0), edge(1.0, -200.0, 200.0)

    def pairs(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        """The index arrays (first, second) of the pairs i < j of ``n`` robots, row-major: the order of every
        per-pair array (``RadioState.pairs``)."""
        return self._pairs(n)

    def _pairs(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        if self._pairs_n != n:
            self._upper = np.triu_indices(n, 1)
            self._pairs_n = n
            self._shadowing = None
        return self._upper

    def _shadowing_step(self, time_s: float, pairs: int) -> tuple[float, float] | None:
        """Bring the shadowing to ``time_s``: drawn stationary at the first tick, one AR(1) step per later tick
        (``channel.shadowing_step_db``, its coefficients kept while the step length stays). Returns the step's
        (rho, innovation) where a compiled pass must take it now (``_shadowing_step_at``, or the channel's
        tick in ``_walls_and_pair_figures``), None where ``self._shadowing`` is already the shadowing at
        ``time_s`` (the first draw, the same time again, or a step taken here with numpy where the kernels
        are not compiled)."""
        config = self.config
        step = None
        if self._shadowing is None:
            self._shadowing = channel.shadowing_initial_db(config.shadowing_sigma_db, pairs, rng=self.rng)
        elif time_s > self._shadowing_time:
            dt = time_s - self._shadowing_time
            # Tick times are multiples of the control period: their differences vary in the last bits only.
            if not abs(dt - self._step[0]) <= 1e-9 * dt:
                rho = float(channel.shadowing_correlation(dt, config.shadowing_correlation_s))
                innovation = float(channel.shadowing_step_db(0.0, dt, config.shadowing_sigma_db,
                                                             config.shadowing_correlation_s, standard_normal=1.0))
                self._step = (dt, rho, innovation)
            _, rho, innovation = self._step
            held = self._rng_pointers
            if (held[1] if held is not None and held[0] is self.rng else self._pointers()) is None:
                innovations = self.rng.standard_normal(pairs)
                innovations *= innovation
                stepped = rho * self._shadowing
                stepped += innovations  # rho X + sigma_innovation z, as one expression would round it
                self._shadowing = stepped
            else:
                step = (rho, innovation)
        self._shadowing_time = time_s
        return step

    def _advance_shadowing(self, time_s: float, pairs: int) -> np.ndarray:
        """The shadowing at ``time_s`` (``_shadowing_step``, its step taken in one compiled pass)."""
        step = self._shadowing_step(time_s, pairs)
        if step is not None:  # the same draws and operations as numpy's, in one compiled pass
            stepped = np.empty(pairs)
            _shadowing_step_at(*self._pointers(), self._shadowing, step[0], step[1], stepped)
            self._shadowing = stepped
        return self._shadowing

    def _pointers(self) -> tuple[int, ...] | None:
        """``sim.compiled.generator_pointers`` of ``self.rng``, kept with it; None where the kernels are not
        compiled (numba's JIT disabled) or the generator is not numpy's."""
        held = self._rng_pointers
        if held is None or held[0] is not self.rng:
            usable = (isinstance(self.rng, np.random.Generator)
                      and getattr(_shadowing_step_at, "overloads", None) is not None)
            held = self._rng_pointers = (self.rng, generator_pointers(self.rng) if usable else None)
        return held[1]

    def pair_figures(self, distance_m: np.ndarray, wall_loss_db: np.ndarray,
                     shadowing_db: np.ndarray) -> dict[str, np.ndarray]:
        """Per pair ((P,) each: distance, m; walls' loss, dB; shadowing, dB): received power, SNR and the
        reference packet's delivery, as ``channel``'s chain log_distance_path_loss_db -> received_power_dbm
        -> snr_db -> delivery_at_snr gives them, bit for bit (tests/test_radio_link.py): the logarithm here
        and the BER of the pairs in the uncertain band with numpy, the rest in one compiled pass."""
        config = self.config
        # log10(max(d, d0) / d0) with d0 = 1 m: dividing by 1.0 changes no value, so it is left out
        log_ratio = np.maximum(np.asarray(distance_m, dtype=float), 1.0)
        np.log10(log_ratio, out=log_ratio)
        rx, snr, delivery = np.empty((3, len(log_ratio)))  # one block, three rows
        uncertain = np.empty(len(log_ratio), dtype=np.bool_)
        below, above = self._certain
        some = _pair_figures(log_ratio, np.ascontiguousarray(wall_loss_db, dtype=float),
                             np.ascontiguousarray(shadowing_db, dtype=float), 10.0 * config.path_loss_exponent,
                             float(config.reference_loss_db), float(config.tx_power_dbm),
                             float(config.noise_floor_dbm), below, above, rx, snr, delivery, uncertain)
        if some:
            delivery[uncertain] = self.delivery_at_snr(snr[uncertain])
        return {"rx_power_dbm": rx, "snr_db": snr, "shadowing_db": shadowing_db, "delivery": delivery}

    def _walls_and_figures(self, positions: np.ndarray, first: np.ndarray, second: np.ndarray, distance: np.ndarray,
                           shadowing_db: np.ndarray, step: tuple[float, float] | None = None
                           ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray]]:
        """``pair_figures`` over the walls ``SceneWalls.crossed_pairs`` finds, the graphs ``graph_figures``
        adds, and the bus's matrices of them (``"link_matrices"``: the SNR (N, N), NaN on the diagonal, and
        carrier sense, mean received power >= ``carrier_sense_dbm``, as ``sim.radio.bus.link_from_pairs``
        makes them), in one compiled call: the same values, without several calls' arguments and arrays each
        tick. With ``step`` (``_shadowing_step``'s), the shadowing's AR(1) step from ``shadowing_db`` is
        taken first in the same call, as ``_advance_shadowing`` takes it. Returns the figures and the walls'
        per-pair (count, loss_db), these in scratch that the next call overwrites (``state`` counts the walls
        again where they are read: nothing reads them every tick)."""
        n, pairs = len(positions), len(first)
        # pair_figures' logarithm with numpy, over the whole matrix: no gather in Python (the kernel's)
        log_ratio = np.maximum(distance, 1.0)
        np.log10(log_ratio, out=log_ratio)
        rx, snr, delivery = np.empty(pairs), np.empty(pairs), np.empty(pairs)
        linked, in_range = np.empty(pairs, dtype=np.bool_), np.empty(pairs, dtype=np.bool_)
        snr_matrix = np.empty((n, n))
        sense, comm = np.empty((n, n), dtype=np.bool_), np.empty((n, n), dtype=np.bool_)
        held = self._figure_held
        if held is None or held[0] is not first or held[1] is not self.rng:
            held = self._hold_figures(first, second)
        fixed, count, wall_loss = held[2], held[4], held[5]
        if step is None:
            shadowed, rho, innovation = shadowing_db, 0.0, 0.0
        else:
            shadowed, (rho, innovation) = np.empty(pairs), step
        # one signature per layout of the caller's distances (the rest is made here)
        key = ("channel tick", distance.dtype.num, distance.flags.c_contiguous, distance.flags.writeable)
        some = compiled_call(_walls_and_pair_figures, fixed + (
            step is not None, shadowing_db, rho, innovation, shadowed, positions, log_ratio, distance, rx, snr,
            delivery, linked, in_range, snr_matrix, sense, comm), key)
        if some:
            which = np.flatnonzero(held[3])  # the pairs in the uncertain band
            delivery[which] = self.delivery_at_snr(snr[which])
            now = delivery[which] >= self.config.delivery_threshold
            linked[which] = now
            comm[first[which], second[which]] = now
            comm[second[which], first[which]] = now
        snr_matrix.flags.writeable = False
        comm.flags.writeable = False
        return ({"rx_power_dbm": rx, "snr_db": snr, "shadowing_db": shadowed, "delivery": delivery, "linked": linked,
                 "in_range": in_range, "comm_adjacency": comm, "link_matrices": LinkMatrices(snr_matrix, sense)},
                {"count": count, "loss_db": wall_loss})

    def _hold_figures(self, first: np.ndarray, second: np.ndarray) -> tuple:
        """What ``_walls_and_figures`` passes its kernel every tick for these pairs (the Generator's pointers,
        the scene's boxes, the formulas' figures, the pairs and scratch), kept with the pairs and the
        generator: (first, rng, the kernel's fixed arguments, uncertain, count, wall_loss)."""
        config, walls, (below, above) = self.config, self.walls, self._certain
        pairs = len(first)
        pointers = self._pointers()
        scratch = (np.empty(pairs, dtype=np.bool_), np.empty(pairs, dtype=np.int64), np.empty(pairs))
        fixed = ((_NO_POINTERS if pointers is None else pointers) + (
            walls.centers, walls.halves, walls.rotations, walls.extents, walls.losses,
            10.0 * config.path_loss_exponent, float(config.reference_loss_db), float(config.tx_power_dbm),
            float(config.noise_floor_dbm), below, above, float(config.carrier_sense_dbm),
            float(config.delivery_threshold), float(self.comm_range_m), first, second, *scratch))
        self._figure_held = (first, self.rng, fixed, *scratch)
        return self._figure_held

    def graph_figures(self, figures: dict[str, np.ndarray], pair_distance_m: np.ndarray, n: int
                      ) -> dict[str, np.ndarray]:
        """``figures`` (a tick's per-pair figures of ``n`` robots, with their ``"delivery"``) with the graphs
        read from them:
        ``"linked"`` (P,) bool, delivery >= ``delivery_threshold`` (the communication graph's pairs),
        ``"in_range"`` (P,) bool, ``pair_distance_m`` <= the comm range, and ``"comm_adjacency"`` (N, N)
        bool, read-only, the communication graph (its diagonal as a delivery of 0 compares)."""
        first, second = self._pairs(n)
        threshold = self.config.delivery_threshold
        linked = figures["delivery"] >= threshold
        comm = np.full((n, n), 0.0 >= threshold)
        comm[first, second] = linked
        comm[second, first] = linked
        comm.flags.writeable = False
        return {**figures, "linked": linked, "in_range": pair_distance_m <= self.comm_range_m, "comm_adjacency": comm}

    def state(self, time_s: float, positions: np.ndarray, links: Links, extra_loss_db: np.ndarray | None = None,
              silent: np.ndarray | None = None) -> RadioState:
        """The channel of every pair of robots at ``positions`` ((N, 3), m) at ``time_s`` (s).

        Faults (``sim.faults``), real radios only: ``extra_loss_db`` ((P,) dB over the pairs, or None) adds
        to each pair's path loss (a blackout); the pairs with an end in ``silent`` ((N,) bool, or None: a
        failed robot) are dead: no power received, SNR -inf, delivery 0. Under ``ideal`` the caller cuts
        the links' adjacency instead."""
        n = len(positions)
        first, second = self._pairs(n)
        positions = np.array(positions, dtype=float)  # the closures keep this tick's
        config = self.config

        def walls() -> dict[str, np.ndarray]:
            crossed = self.walls.crossed_pairs(positions, first, second)
            return {"count": crossed.count, "loss_db": crossed.loss_db}

        if config.is_ideal:
            adjacency = links.adjacency

            def ideal() -> dict[str, np.ndarray]:
                nan = np.full(len(first), np.nan)
                return self.graph_figures({"rx_power_dbm": nan, "snr_db": nan, "shadowing_db": nan,
                                           "delivery": adjacency[first, second].astype(float)},
                                          links.distance[first, second], n)

            return RadioState(config.preset, config.delivery_threshold, self.comm_range_m, links.distance,
                              ideal, walls, (first, second))
        distance = links.distance
        if extra_loss_db is None and silent is None:  # the tick's channel in one compiled call
            step = self._shadowing_step(time_s, len(first))
            figures, _ = self._walls_and_figures(positions, first, second, distance, self._shadowing, step)
            self._shadowing = figures["shadowing_db"]
            return RadioState(config.preset, config.delivery_threshold, self.comm_range_m, distance,
                              lambda: figures, walls, (first, second))
        shadowing = self._advance_shadowing(time_s, len(first))
        computed: dict[str, dict[str, np.ndarray]] = {}  # the walls, once, for whichever reads first

        def walls_once() -> dict[str, np.ndarray]:
            if "walls" not in computed:
                computed["walls"] = walls()
            return computed["walls"]

        def figures_with_faults() -> dict[str, np.ndarray]:
            wall_loss = walls_once()["loss_db"]
            if extra_loss_db is not None:
                wall_loss = wall_loss + extra_loss_db  # a blackout adds to the path loss, as a wall does
            pair_distance = distance[first, second]
            figures = self.pair_figures(pair_distance, wall_loss, shadowing)
            if silent is not None:
                dead = silent[first] | silent[second]
                for key, value in (("rx_power_dbm", -np.inf), ("snr_db", -np.inf), ("delivery", 0.0)):
                    figures[key] = np.where(dead, value, figures[key])
            return self.graph_figures(figures, pair_distance, n)

        return RadioState(config.preset, config.delivery_threshold, self.comm_range_m, distance, figures_with_faults,
                          walls_once, (first, second))


@kernel
def _pair_figures(log_ratio, wall_loss_db, shadowing_db, distance_coefficient, reference_loss_db, tx_power_dbm,
                  noise_floor_dbm, below, above, rx, snr, delivery, uncertain):
    """The arithmetic of ``channel``'s chain, operation for operation in numpy's order: PL = (PL(d0) +
    10 n log10(d / d0)) + walls, P_rx = ((P_tx - PL) - X) + 0 (no fading), SNR = P_rx - N; the delivery 1
    or 0 outside (below, above), and the pairs inside marked. Returns how many are inside."""
    inside = 0
    for p in range(log_ratio.shape[0]):
        path_loss = (reference_loss_db + distance_coefficient * log_ratio[p]) + wall_loss_db[p]
        rx[p] = ((tx_power_dbm - path_loss) - shadowing_db[p]) + 0.0
        snr[p] = rx[p] - noise_floor_dbm
        delivery[p] = 1.0 if snr[p] >= above else 0.0
        uncertain[p] = snr[p] > below and snr[p] < above
        inside += uncertain[p]
    return inside


@kernel
def _walls_and_pair_figures(state_address, state, next_uint64, next_uint32, next_double, centers, halves, rotations,
                            extents, losses, distance_coefficient, reference_loss_db, tx_power_dbm, noise_floor_dbm,
                            below, above, carrier_sense_dbm, delivery_threshold, comm_range_m, first, second,
                            uncertain, count, wall_loss_db, step, shadowing_before, rho, innovation, shadowing_db,
                            positions, log_ratio_matrix, distance, rx, snr, delivery, linked, in_range, snr_matrix,
                            sense, comm):
    """One tick of the channel. With ``step``, the shadowing's AR(1) step from ``shadowing_before`` into
    ``shadowing_db``, drawn from the Generator of these ``sim.compiled.generator_pointers`` as
    ``_shadowing_step_at`` draws it (without, ``shadowing_db`` is the tick's shadowing and the pointers
    are not read). Then ``walls._pair_crossings`` (into ``count`` and ``wall_loss_db``, zeroed here),
    ``_pair_figures`` over them with each pair's entry of ``log_ratio_matrix`` ((N, N): log10(max(d, d0)
    / d0)), the graphs of ``RadioChannel.graph_figures`` (``linked``, ``in_range`` and ``comm``; a pair
    in the uncertain band is linked as a delivery of 0 compares, until its delivery is known), and the
    bus's (N, N) matrices of the figures: the SNR of both triangles with NaN on the diagonal, carrier
    sense where ``rx`` reaches ``carrier_sense_dbm`` (False on the diagonal). Returns ``_pair_figures``'
    count of pairs inside the uncertain band."""
    if step:
        _shadowing_step_at(state_address, state, next_uint64, next_uint32, next_double, shadowing_before, rho,
                           innovation, shadowing_db)
    count[:] = 0
    wall_loss_db[:] = 0.0
    if centers.shape[0]:
        _pair_crossings(positions, first, second, centers, halves, rotations, extents, losses, count, wall_loss_db)
    pairs = first.shape[0]
    log_ratio = np.empty(pairs)
    for p in range(pairs):
        log_ratio[p] = log_ratio_matrix[first[p], second[p]]
    inside = _pair_figures(log_ratio, wall_loss_db, shadowing_db, distance_coefficient, reference_loss_db,
                           tx_power_dbm, noise_floor_dbm, below, above, rx, snr, delivery, uncertain)
    write_pair_matrices(first, second, snr, rx, carrier_sense_dbm, snr_matrix, sense)
    comm[:] = 0.0 >= delivery_threshold
    for p in range(pairs):
        i, j = first[p], second[p]
        linked[p] = delivery[p] >= delivery_threshold
        comm[i, j] = linked[p]
        comm[j, i] = linked[p]
        in_range[p] = distance[i, j] <= comm_range_m
    return inside


_NO_POINTERS = (0, 0, 0, 0, 0)  # where there are none: ``_walls_and_pair_figures`` without a step reads none


@kernel
def _shadowing_step_at(state_address, state, next_uint64, next_uint32, next_double, shadowing, rho, innovation,
                       out):
    """One AR(1) step of the shadowing: out = rho X + innovation z, z standard normal drawn in order from the
    Generator of these ``sim.compiled.generator_pointers`` (numba's ``standard_normal`` advances it as
    numpy's does, tests/test_radio_link.py), with ``_advance_shadowing``'s numpy operations: z * innovation,
    rho * X, then their sum."""
    rng = generator_at(state_address, state, next_uint64, next_uint32, next_double)
    for p in range(shadowing.shape[0]):
        scaled = rng.standard_normal() * innovation
        out[p] = rho * shadowing[p] + scaled
