"""The scenario's ``[radio]`` table: a preset and every channel figure it fills, each overridable.

A key left out takes the preset's figure (``sim.radio.presets``). Under the
``ideal`` preset the channel keys are filled with the IEEE 802.15.4 figures so
that every key reads as a number, but the ideal radio uses none of them: its
links are today's disk with line of sight.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Literal

from sim.config import check_params, param, require
from sim.radio import channel
from sim.radio.bus import BusParameters
from sim.radio.presets import IEEE802154, PRESETS, RadioPreset

# Carrier sense: a robot defers to every robot whose mean received power reaches the preset's
# sensitivity minus this margin. IEEE 802.15.4-2006 6.9.9 lets a CCA's energy-detection threshold be
# up to 10 dB above the receiver sensitivity; sensing a few dB below the sensitivity instead makes a
# sender defer to every frame it could decode, so the bus's missing hidden-terminal collisions
# (sim.radio.bus) stay rare: pairs that could interfere share the air.
CARRIER_SENSE_MARGIN_DB = 3.0

# Marks a key the preset fills (a NaN a scenario cannot write: tables refuse NaN).
FROM_PRESET = math.nan


@dataclass(frozen=True)
class RadioConfig:
    # "ideal" (today's disk with line of sight, lossless), "ieee802154" (CC2420), "nrf24" or "wifi"
    preset: str = "ideal"
    # -- transmitter and receiver
    tx_power_dbm: float = param(FROM_PRESET, unit="dBm", min=-60.0, max=40.0)  # output power, antenna gains folded in
    bitrate_bps: float = param(FROM_PRESET, unit="bit/s", above=0.0, max=1e10, tunable=False)  # air data rate
    noise_floor_dbm: float = param(FROM_PRESET, unit="dBm", min=-200.0, max=0.0)  # receiver noise floor kTB + NF
    # -- propagation
    path_loss_exponent: float = param(FROM_PRESET, min=1.0, max=8.0)  # n of the log-distance model (free space: 2)
    reference_loss_db: float = param(FROM_PRESET, unit="dB", min=0.0, max=200.0)  # path loss at 1 m
    # loss of each wall crossed that the scene gives no figure of its own (docs/models.md)
    wall_loss_db: float = param(FROM_PRESET, unit="dB", min=0.0, max=200.0)
    shadowing_sigma_db: float = param(FROM_PRESET, unit="dB", min=0.0, max=40.0)  # log-normal shadowing std
    # shadowing correlation time: exp(-dt / tau) between ticks dt apart; inf freezes it, 0 redraws every tick
    shadowing_correlation_s: float = param(FROM_PRESET, unit="s", min=0.0, allow_inf=True)
    # per-packet small-scale fading, for the message bus: "none", "rayleigh" or "rician"; unset: the preset's
    fading: Literal["none", "rayleigh", "rician"] | None = None
    # Rician K-factor (LOS over scattered power); -inf is K = 0 (Rayleigh); "rician" only
    rician_k_db: float = param(FROM_PRESET, unit="dB", max=60.0, allow_inf=True)
    # -- the message bus's shared medium
    # mean received power at which two robots hear each other's carrier and share the air (CSMA);
    # default: the preset's sensitivity - CARRIER_SENSE_MARGIN_DB
    carrier_sense_dbm: float = param(FROM_PRESET, unit="dBm", min=-200.0, max=40.0)
    # -- the communication graph
    reference_payload_bytes: int = param(20, unit="byte", min=0, max=1500)  # payload of the packet whose delivery is reported
    delivery_threshold: float = param(0.5, above=0.0, max=1.0)  # a link is in the communication graph at this delivery probability

    def __post_init__(self) -> None:
        require(self.preset in PRESETS, "preset", f"unknown radio preset {self.preset!r} (one of: {', '.join(PRESETS)})")
        figures = preset_figures(self.preset)
        for f in fields(self):
            value = getattr(self, f.name)
            if f.name in figures and (value is None or (isinstance(value, float) and math.isnan(value))):
                object.__setattr__(self, f.name, figures[f.name])
        check_params(self)
        require(self.reference_payload_bytes <= self.radio.packet.max_payload_bytes, "reference_payload_bytes",
                f"must be at most {self.radio.packet.max_payload_bytes} bytes ({self.radio.name} frames), "
                f"got {self.reference_payload_bytes}")

    @property
    def is_ideal(self) -> bool:
        return PRESETS[self.preset].is_ideal

    @property
    def radio(self) -> RadioPreset:
        """The preset whose modulation, bandwidth and frame format apply (802.15.4's under ideal)."""
        chosen = PRESETS[self.preset]
        return IEEE802154 if chosen.is_ideal else chosen

    @property
    def bus_parameters(self) -> BusParameters:
        """What the message bus needs: the preset's frame format with this table's bit rate, fading and K."""
        chosen = PRESETS[self.preset]
        if chosen.is_ideal:
            return BusParameters.from_preset(chosen)
        k = 0.0 if self.rician_k_db == -math.inf else 10.0 ** (self.rician_k_db / 10.0)
        return replace(BusParameters.from_preset(chosen), bitrate_bps=self.bitrate_bps, fading_model=self.fading,
                       rician_k=k)

    @property
    def reference_length_bits(self) -> int:
        """Bits of the reference packet whose errors lose it: PHY header, MAC overhead and payload."""
        packet = self.radio.packet
        return packet.header_bits + packet.mac_overhead_bits + 8 * self.reference_payload_bytes


def preset_figures(name: str) -> dict[str, float | str]:
    """The keys a preset fills, key -> value (802.15.4's figures for ``ideal``, which uses none)."""
    preset = PRESETS[name]
    if preset.is_ideal:
        preset = IEEE802154
    k = preset.fading.rician_k
    return {
        "tx_power_dbm": preset.tx_power_dbm,
        "bitrate_bps": preset.bitrate_bps,
        "noise_floor_dbm": round(preset.noise_floor_dbm, 6),
        "path_loss_exponent": preset.path_loss.exponent,
        "reference_loss_db": round(preset.path_loss.reference_loss_db, 6),
        "wall_loss_db": preset.path_loss.loss_per_wall_db,
        "shadowing_sigma_db": preset.shadowing.sigma_db,
        "shadowing_correlation_s": preset.shadowing.tau_s,
        "fading": preset.fading.model,
        "rician_k_db": -math.inf if k == 0 else 10.0 * math.log10(k),
        "carrier_sense_dbm": preset.sensitivity.datasheet_dbm - CARRIER_SENSE_MARGIN_DB,
    }


assert set(channel.FADING_MODELS) == {"none", "rayleigh", "rician"}  # RadioConfig.fading's Literal
