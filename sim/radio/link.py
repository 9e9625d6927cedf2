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

from sim.geometry import Boxes
from sim.radio import channel
from sim.radio.config import RadioConfig
from sim.radio.walls import walls_crossed
from sim.types import Links, RadioState


class RadioChannel:
    def __init__(self, config: RadioConfig, obstacles: Boxes, wall_loss_db: np.ndarray | None,
                 comm_range_m: float, rng: np.random.Generator):
        self.config = config
        self.obstacles = obstacles
        scene = np.full(len(obstacles), np.nan) if wall_loss_db is None else np.asarray(wall_loss_db, dtype=float)
        # The scene's figure where it gives one, the scenario's elsewhere.
        self.loss_per_box_db = np.where(np.isnan(scene), config.wall_loss_db, scene)
        self.comm_range_m = comm_range_m
        self.rng = rng
        self._pairs_n = -1
        self._shadowing: np.ndarray | None = None  # (P,) dB, the AR(1) state
        self._shadowing_time = -np.inf

    def _pairs(self, n: int) -> tuple[np.ndarray, np.ndarray]:
        if self._pairs_n != n:
            self._upper = np.triu_indices(n, 1)
            self._pairs_n = n
            self._shadowing = None
        return self._upper

    def _advance_shadowing(self, time_s: float, pairs: int) -> np.ndarray:
        """The shadowing at ``time_s``: drawn stationary at the first tick, one AR(1) step per later tick."""
        config = self.config
        if self._shadowing is None:
            self._shadowing = channel.shadowing_initial_db(config.shadowing_sigma_db, pairs, rng=self.rng)
        elif time_s > self._shadowing_time:
            self._shadowing = channel.shadowing_step_db(
                self._shadowing, time_s - self._shadowing_time, config.shadowing_sigma_db,
                config.shadowing_correlation_s, rng=self.rng)
        self._shadowing_time = time_s
        return self._shadowing

    def state(self, time_s: float, positions: np.ndarray, links: Links) -> RadioState:
        """The channel of every pair of robots at ``positions`` ((N, 3), m) at ``time_s`` (s)."""
        n = len(positions)
        first, second = self._pairs(n)
        positions = np.array(positions, dtype=float)  # the closures keep this tick's
        config = self.config

        def walls() -> dict[str, np.ndarray]:
            crossed = walls_crossed(positions[first], positions[second], self.obstacles, self.loss_per_box_db)
            return {"count": _symmetric(n, first, second, crossed.count, 0),
                    "loss_db": _symmetric(n, first, second, crossed.loss_db, 0.0)}

        if config.is_ideal:
            adjacency = links.adjacency

            def ideal() -> dict[str, np.ndarray]:
                nan = np.full((n, n), np.nan)
                return {"rx_power_dbm": nan, "snr_db": nan, "shadowing_db": nan,
                        "delivery": adjacency.astype(float)}

            return RadioState(config.preset, config.delivery_threshold, self.comm_range_m, links.distance,
                              ideal, walls)
        shadowing = self._advance_shadowing(time_s, len(first))
        distance = links.distance
        state: RadioState

        def figures() -> dict[str, np.ndarray]:
            radio = config.radio
            path_loss = channel.log_distance_path_loss_db(
                distance[first, second], config.path_loss_exponent, config.reference_loss_db,
                total_wall_loss_db=state._walls["loss_db"][first, second])
            rx = channel.received_power_dbm(config.tx_power_dbm, path_loss, shadowing)
            snr = channel.snr_db(rx, config.noise_floor_dbm)
            ber = channel.bit_error_rate(radio.modulation, snr, radio.bandwidth_hz, config.bitrate_bps)
            delivery = 1.0 - channel.packet_error_rate(ber, config.reference_length_bits)
            return {"rx_power_dbm": _symmetric(n, first, second, rx, np.nan),
                    "snr_db": _symmetric(n, first, second, snr, np.nan),
                    "shadowing_db": _symmetric(n, first, second, shadowing, np.nan),
                    "delivery": _symmetric(n, first, second, delivery, 0.0)}

        state = RadioState(config.preset, config.delivery_threshold, self.comm_range_m, distance, figures, walls)
        return state


def _symmetric(n: int, first: np.ndarray, second: np.ndarray, values: np.ndarray, diagonal) -> np.ndarray:
    """(N, N) from the pairs' values (i < j), mirrored; ``diagonal`` on the diagonal."""
    out = np.empty((n, n), dtype=np.asarray(values).dtype)
    out[first, second] = values
    out[second, first] = values
    np.fill_diagonal(out, diagonal)
    return out
