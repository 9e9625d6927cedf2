"""Channel parameter presets: the ideal disk, IEEE 802.15.4 (CC2420), nRF24L01+, and 802.11n-class Wi-Fi.

Each preset names its source in ``source``. docs/radio.md lists the figures
that could not be checked against the primary documents.

Each preset's noise figure is an effective figure, fitted so that the
formulas in ``sim.radio.channel`` give the datasheet's sensitivity for the
datasheet's reference packet: it lumps the front end's noise figure with the
demodulator's implementation loss (and, for Wi-Fi, minus the coding gain the
uncoded BPSK formula leaves out). ``RadioPreset.computed_sensitivity_dbm``
recomputes the sensitivity; the tests hold it within 2 dB of the datasheet's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from sim.radio import channel

# COST 231 Final Report (1999), indoor multi-wall model fitted at about 1.8 GHz.
LIGHT_WALL_LOSS_DB = 3.4  # plasterboard, light partitions, dB per wall crossed
HEAVY_WALL_LOSS_DB = 6.9  # concrete, brick, load-bearing walls, dB per wall crossed
# ITU-R P.1238 distance power loss coefficient N for offices at 2.4 GHz; exponent n = N / 10.
P1238_OFFICE_2_4_GHZ_EXPONENT = 3.0


@dataclass(frozen=True)
class PathLossParameters:
    """Log-distance path loss with walls (``channel.log_distance_path_loss_db``)."""

    exponent: float = P1238_OFFICE_2_4_GHZ_EXPONENT  # n, dimensionless (P.1238's N = 10 n)
    reference_loss_db: float = channel.itu_p1238_reference_loss_db(2.44e9)  # PL(d0), dB: 39.7 at 2.44 GHz
    reference_distance_m: float = 1.0  # d0, m
    # tether's indoor scene has 10 cm interior partitions: light walls.
    loss_per_wall_db: float = LIGHT_WALL_LOSS_DB  # dB per wall crossed


@dataclass(frozen=True)
class ShadowingParameters:
    """Log-normal shadowing, AR(1) in time per link (``channel.shadowing_step_db``)."""

    # Chosen, not from a verified table: indoor shadowing spreads of 3 to 12 dB are reported.
    sigma_db: float = 4.0  # standard deviation, dB
    # Gudmundson's decorrelation distance over the robots' speed; chosen for ~1 m at ~0.5 m/s.
    tau_s: float = 2.0  # correlation time, s


@dataclass(frozen=True)
class FadingParameters:
    """Per-packet small-scale fading (``channel.fading_gain_db``)."""

    model: str = "rayleigh"  # 'none', 'rayleigh' or 'rician'; Rayleigh: indoor links without line of sight
    rician_k: float = 0.0  # K-factor, linear (LOS power / scattered power); used by 'rician' only

    def __post_init__(self) -> None:
        if self.model not in channel.FADING_MODELS:
            raise ValueError(f"unknown fading model {self.model!r}; known: {', '.join(channel.FADING_MODELS)}")
        if self.rician_k < 0:
            raise ValueError("the Rician K-factor must be >= 0")


@dataclass(frozen=True)
class PacketFormat:
    """Frame layout for ``channel.packet_airtime_s``; bits go at the preset's bit rate."""

    preamble_bits: int  # preamble and sync word, bits
    header_bits: int  # PHY header, bits
    mac_overhead_bits: int  # MAC header and checksum around the payload, bits
    fixed_overhead_s: float  # per frame, s: turnaround, settling, a separately timed preamble
    max_payload_bytes: int  # the largest payload one frame carries, bytes


@dataclass(frozen=True)
class SensitivityReference:
    """How the datasheet defines its sensitivity: PER of a reference packet at a threshold."""

    datasheet_dbm: float  # the datasheet's (or standard's) sensitivity, dBm
    reference_length_bits: int  # bits whose errors count (1 for a BER-defined sensitivity)
    per_threshold: float  # PER (or BER, with 1 bit) at the sensitivity, dimensionless


@dataclass(frozen=True)
class IdealDisk:
    """tether's original radio: a disk with line of sight, instant and lossless. No channel formula applies."""

    name: str = "ideal"
    source: str = "tether's ideal radio: range disk (sensing.comm_range_m) with line of sight; no losses, no delay"
    is_ideal: bool = field(default=True, init=False)


@dataclass(frozen=True)
class RadioPreset:
    """A radio and its channel: transmit side, receiver, modulation, propagation, frame format."""

    name: str
    source: str  # where each figure comes from
    frequency_hz: float  # carrier, Hz
    tx_power_dbm: float  # conducted output power with antenna gains folded in, dBm
    bitrate_bps: float  # air data rate, bit/s
    bandwidth_hz: float  # noise bandwidth of the channel, Hz
    modulation: str  # one of channel.MODULATIONS
    noise_figure_db: float  # effective receiver noise figure, dB (see the module docstring)
    sensitivity: SensitivityReference
    packet: PacketFormat
    path_loss: PathLossParameters = PathLossParameters()
    shadowing: ShadowingParameters = ShadowingParameters()
    fading: FadingParameters = FadingParameters()
    is_ideal: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        if self.modulation not in channel.MODULATIONS:
            raise ValueError(f"unknown modulation {self.modulation!r}; known: {', '.join(channel.MODULATIONS)}")

    @property
    def noise_floor_dbm(self) -> float:
        """kTB + NF over the channel, dBm."""
        return float(channel.thermal_noise_dbm(self.bandwidth_hz, self.noise_figure_db))

    def packet_error_rate(self, received_power_dbm: ArrayLike, length_bits: ArrayLike) -> np.ndarray:
        """PER of ``length_bits`` bits received at ``received_power_dbm`` (dBm), dimensionless."""
        return channel.packet_error_rate_at_power(
            received_power_dbm, length_bits, modulation=self.modulation, noise_floor_dbm=self.noise_floor_dbm,
            bandwidth_hz=self.bandwidth_hz, bitrate_bps=self.bitrate_bps)

    def computed_sensitivity_dbm(self) -> float:
        """Received power (dBm) at which the reference packet's PER reaches the datasheet's threshold."""
        reference = self.sensitivity
        return channel.sensitivity_dbm(
            lambda power_dbm: float(self.packet_error_rate(power_dbm, reference.reference_length_bits)),
            reference.per_threshold)

    def airtime_s(self, payload_bytes: ArrayLike) -> np.ndarray:
        """Time on air of a frame carrying ``payload_bytes`` (bytes), s."""
        payload = np.asarray(payload_bytes)
        if np.any(payload > self.packet.max_payload_bytes):
            raise ValueError(f"{self.name} carries at most {self.packet.max_payload_bytes} payload bytes a frame")
        return channel.packet_airtime_s(
            payload, self.bitrate_bps, preamble_bits=self.packet.preamble_bits,
            header_bits=self.packet.header_bits, mac_overhead_bits=self.packet.mac_overhead_bits,
            fixed_overhead_s=self.packet.fixed_overhead_s)


IDEAL = IdealDisk()

IEEE802154 = RadioPreset(
    name="ieee802154",
    source=("TI (Chipcon) CC2420 datasheet SWRS041: 0 dBm output, 250 kbit/s O-QPSK DSSS (2 Mchip/s), "
            "-95 dBm typical sensitivity (PER 1 %, 20-byte PSDU, as IEEE 802.15.4 defines it; the standard "
            "requires -85 dBm); IEEE Std 802.15.4-2006: 2 MHz channel, Annex E BER, frame format, "
            "aTurnaroundTime 12 symbols"),
    frequency_hz=2.44e9,
    tx_power_dbm=0.0,
    bitrate_bps=250e3,
    bandwidth_hz=2e6,
    modulation="oqpsk_dsss_802154",
    noise_figure_db=15.6,  # fitted: kTB over 2 MHz is -111.0 dBm, PER 1 % of 160 bits needs SINR 0.4 dB
    sensitivity=SensitivityReference(datasheet_dbm=-95.0, reference_length_bits=20 * 8, per_threshold=0.01),
    packet=PacketFormat(
        preamble_bits=(4 + 1) * 8,  # 4-byte preamble + 1-byte start-of-frame delimiter
        header_bits=8,  # 1-byte PHY header (frame length)
        # MAC header with 16-bit addresses and PAN ID compression (2 frame control + 1 sequence
        # + 2 PAN ID + 2 + 2 addresses) and the 2-byte FCS.
        mac_overhead_bits=(9 + 2) * 8,
        # rx-to-tx turnaround, 12 symbols of 16 us, and one clear channel assessment, 8 symbols;
        # CSMA-CA backoff and acknowledgements are not included.
        fixed_overhead_s=(12 + 8) * 16e-6,
        max_payload_bytes=127 - 11,  # aMaxPHYPacketSize 127 less the MAC overhead
    ),
)

NRF24 = RadioPreset(
    name="nrf24",
    source=("Nordic nRF24L01+ Product Specification v1.0 (2008): 0 dBm output, 2 Mbit/s GFSK, -82 dBm "
            "sensitivity at 2 Mbit/s (0.1 % BER), Enhanced ShockBurst frame (1-byte preamble, 5-byte "
            "address, 9-bit packet control field, up to 32-byte payload, 2-byte CRC), 130 us TX settling. "
            "The link of the Crazyflie 2.x and its Crazyradio (nRF24-compatible ESB at 2 Mbit/s)"),
    frequency_hz=2.44e9,
    tx_power_dbm=0.0,
    bitrate_bps=2e6,
    bandwidth_hz=2e6,  # 2 MHz channel spacing is required at 2 Mbit/s
    modulation="noncoherent_fsk",
    noise_figure_db=18.0,  # fitted: kTB over 2 MHz is -111.0 dBm, BER 1e-3 needs Eb/N0 = SNR = 10.9 dB
    sensitivity=SensitivityReference(datasheet_dbm=-82.0, reference_length_bits=1, per_threshold=1e-3),
    packet=PacketFormat(
        preamble_bits=8,
        header_bits=5 * 8 + 9,  # 5-byte address + 9-bit packet control field
        mac_overhead_bits=2 * 8,  # 2-byte CRC
        fixed_overhead_s=130e-6,  # standby-II to TX settling
        max_payload_bytes=32,
    ),
)

WIFI = RadioPreset(
    name="wifi",
    source=("IEEE Std 802.11-2016 HT PHY (802.11n), 2.4 GHz, 20 MHz, MCS0 (BPSK rate 1/2, 6.5 Mbit/s, "
            "800 ns GI): -82 dBm receiver minimum input sensitivity (Table 19-23, PER 10 % for a "
            "4096-octet PSDU); 15 dBm output, a typical client; HT-mixed preamble 36 us, "
            "DIFS 28 us (short slot)"),
    frequency_hz=2.437e9,
    tx_power_dbm=15.0,
    bitrate_bps=6.5e6,
    bandwidth_hz=20e6,
    modulation="bpsk",
    # fitted: kTB over 20 MHz is -101.0 dBm; uncoded BPSK at PER 10 % of 32768 bits needs Eb/N0
    # 10.1 dB, i.e. SNR 5.2 dB. The standard's own budget is NF 10 dB plus 5 dB implementation
    # margin with the code's gain; this one figure stands for all three.
    noise_figure_db=13.8,
    sensitivity=SensitivityReference(datasheet_dbm=-82.0, reference_length_bits=4096 * 8, per_threshold=0.1),
    packet=PacketFormat(
        preamble_bits=0,  # the HT-mixed preamble has its own timing: in fixed_overhead_s
        header_bits=16 + 6,  # SERVICE field and convolutional code tail, sent at the data rate
        # QoS data MAC header 26 bytes, FCS 4, LLC/SNAP 8.
        mac_overhead_bits=(26 + 4 + 8) * 8,
        # L-STF 8 + L-LTF 8 + L-SIG 4 + HT-SIG 8 + HT-STF 4 + HT-LTF 4 us, and DIFS (SIFS 10 + 2 slots
        # of 9 us). OFDM symbol padding (up to 4 us), backoff and the ACK are not included.
        fixed_overhead_s=36e-6 + 28e-6,
        max_payload_bytes=1500,
    ),
)

PRESETS: dict[str, IdealDisk | RadioPreset] = {preset.name: preset for preset in (IDEAL, IEEE802154, NRF24, WIFI)}


def preset(name: str) -> IdealDisk | RadioPreset:
    """The preset called ``name``: 'ideal', 'ieee802154', 'nrf24' or 'wifi'."""
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown radio preset {name!r}; known: {', '.join(PRESETS)}") from None
