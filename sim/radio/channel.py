"""Pure formulas of a radio link: path loss, shadowing, fading, noise, bit and packet errors, airtime.

Every function takes numbers or numpy arrays (batched over links where that
makes sense: any shape broadcasts) and returns the same shape. Powers are in
dBm, gains and losses in dB, distances in m, times in s, rates in bit/s,
bandwidths in Hz. Randomness comes only from what the caller passes in,
standard normal draws or an ``np.random.Generator``, never numpy's global state.

Standards and models followed (each function names its own):

- log-distance path loss with the ITU-R P.1238 indoor coefficients and the
  COST 231 multi-wall term;
- log-normal shadowing as a first-order Gauss-Markov process, the time form of
  Gudmundson's exponential correlation model (Electronics Letters 27(23), 1991);
- Rayleigh and Rician small-scale fading of the received power;
- thermal noise kTB with a receiver noise figure;
- bit error rates of IEEE 802.15.4-2006 O-QPSK/DSSS (Annex E), non-coherent
  binary FSK, and BPSK/QPSK (Gray-coded) on an AWGN channel;
- packet error rate of independent bit errors; airtime of a frame;
  sensitivity by bisection.
"""

from __future__ import annotations

from collections.abc import Callable
from math import comb

import numpy as np
from numpy.typing import ArrayLike
from scipy.special import erfc

SPEED_OF_LIGHT_M_PER_S = 299_792_458.0
# kT at the standard reference temperature 290 K is -173.98 dBm/Hz; -174 is the
# figure every datasheet and standard rounds it to.
THERMAL_NOISE_DENSITY_DBM_PER_HZ = -174.0

FADING_MODELS = ("none", "rayleigh", "rician")
MODULATIONS = ("oqpsk_dsss_802154", "noncoherent_fsk", "bpsk", "qpsk")

# (-1)^k C(16, k) for k = 2..16, the coefficients of IEEE 802.15.4-2006 eq. (E.4.1.7).
_K_802154 = np.arange(2, 17)
_SIGNED_BINOMIALS_802154 = np.array([(-1) ** k * comb(16, k) for k in range(2, 17)], dtype=float)
_LN10_OVER_10 = np.log(10.0) / 10.0


# --- Path loss -----------------------------------------------------------------------------------

def free_space_path_loss_db(distance_m: ArrayLike, frequency_hz: float) -> np.ndarray:
    """Friis free-space path loss 20 log10(4 pi d f / c), dB (ITU-R P.525).

    ``distance_m`` in m (> 0), ``frequency_hz`` in Hz. Isotropic antennas.
    """
    d = np.asarray(distance_m, dtype=float)
    return 20.0 * np.log10(4.0 * np.pi * d * frequency_hz / SPEED_OF_LIGHT_M_PER_S)


def itu_p1238_reference_loss_db(frequency_hz: float) -> float:
    """Loss at the 1 m reference distance of ITU-R P.1238, 20 log10(f_MHz) - 28, dB.

    P.1238's site-general indoor model is L = 20 log10 f + N log10 d + Lf(n) - 28
    (f in MHz, d in m): the first and last terms are this reference loss, close
    to free space at 1 m (which is 20 log10 f_MHz - 27.55). At 2.4 GHz: 39.6 dB.
    """
    return 20.0 * float(np.log10(frequency_hz / 1e6)) - 28.0


def wall_loss_db(wall_count: ArrayLike, loss_per_wall_db: ArrayLike) -> np.ndarray:
    """Total loss of the walls a link crosses, sum_i k_i L_i, dB (COST 231 multi-wall model).

    Either one wall type: ``wall_count`` of any shape (walls crossed per link)
    times a scalar ``loss_per_wall_db``; or several types: ``wall_count`` of
    shape (..., n_types) and ``loss_per_wall_db`` of shape (n_types,), summed
    over the last axis. COST 231 Final Report (1999), indoor: at about 1.8 GHz
    a light wall costs about 3.4 dB and a heavy wall about 6.9 dB. Floors
    (COST 231's non-linear floor term) are not modelled.
    """
    counts = np.asarray(wall_count, dtype=float)
    losses = np.asarray(loss_per_wall_db, dtype=float)
    if losses.ndim == 0:
        return counts * losses
    if counts.shape[-1:] != losses.shape:
        raise ValueError(f"wall counts of shape {counts.shape} do not end in the {losses.shape[0]} wall types")
    return counts @ losses


def log_distance_path_loss_db(distance_m: ArrayLike, exponent: float, reference_loss_db: float,
                              reference_distance_m: float = 1.0,
                              total_wall_loss_db: ArrayLike = 0.0) -> np.ndarray:
    """Log-distance path loss with a multi-wall term, dB.

    PL(d) = PL(d0) + 10 n log10(max(d, d0) / d0) + sum of wall losses
    (ITU-R P.1238 distance power loss, with P.1238's N = 10 n; COST 231
    multi-wall for the last term, see ``wall_loss_db``). ``distance_m`` in m,
    clipped at ``reference_distance_m`` d0 (m) because the model says nothing
    nearer than d0 and a link can't gain over its reference loss;
    ``exponent`` n (dimensionless; 2 in free space, 3.0 in P.1238's 2.4 GHz
    office); ``reference_loss_db`` PL(d0) in dB; ``total_wall_loss_db`` per
    link, in dB, broadcast against the distances.
    """
    d = np.maximum(np.asarray(distance_m, dtype=float), reference_distance_m)
    distance_loss = 10.0 * exponent * np.log10(d / reference_distance_m)
    return reference_loss_db + distance_loss + np.asarray(total_wall_loss_db, dtype=float)


def received_power_dbm(tx_power_dbm: ArrayLike, path_loss_db: ArrayLike, shadowing_db: ArrayLike = 0.0,
                       fading_gain_db: ArrayLike = 0.0) -> np.ndarray:
    """Link budget P_rx = P_tx - PL - X_shadow + G_fading, dBm.

    ``tx_power_dbm`` in dBm (antenna gains folded in, if any); ``path_loss_db``
    and ``shadowing_db`` are losses in dB (shadowing is zero-mean, so its sign
    is a convention); ``fading_gain_db`` is the small-scale power gain in dB
    (mean power 1, so 0 dB on average in linear terms).
    """
    return (np.asarray(tx_power_dbm, dtype=float) - np.asarray(path_loss_db, dtype=float)
            - np.asarray(shadowing_db, dtype=float) + np.asarray(fading_gain_db, dtype=float))


# --- Shadowing -----------------------------------------------------------------------------------

def shadowing_correlation(dt_s: ArrayLike, tau_s: float) -> np.ndarray:
    """Correlation exp(-dt / tau) of shadowing samples dt apart, dimensionless.

    Gudmundson (1991) measured shadowing correlated over distance as
    exp(-|dx| / d_corr); a link whose ends move at speed v sees that as time
    correlation exp(-dt / tau) with tau = d_corr / v. ``tau_s`` in s:
    ``inf`` freezes shadowing, 0 redraws it independently every step.
    """
    dt = np.asarray(dt_s, dtype=float)
    if np.any(dt < 0):
        raise ValueError("dt_s must be non-negative")
    if tau_s <= 0:
        return np.where(dt > 0, 0.0, 1.0)
    return np.exp(-dt / tau_s)


def shadowing_initial_db(sigma_db: float, size: int | tuple[int, ...] | None = None, *,
                         standard_normal: ArrayLike | None = None,
                         rng: np.random.Generator | None = None) -> np.ndarray:
    """A stationary first sample of log-normal shadowing, N(0, sigma^2), dB.

    Pass exactly one of ``standard_normal`` (draws z ~ N(0, 1)) or ``rng``
    (with ``size``). ``sigma_db`` is the shadowing standard deviation in dB.
    """
    z = _standard_normal_draws(standard_normal, rng, size)
    return sigma_db * z


def shadowing_step_db(previous_db: ArrayLike, dt_s: ArrayLike, sigma_db: float, tau_s: float, *,
                      standard_normal: ArrayLike | None = None,
                      rng: np.random.Generator | None = None) -> np.ndarray:
    """Advance per-link log-normal shadowing by dt: first-order Gauss-Markov (AR(1)) update, dB.

    X(t + dt) = rho X(t) + sigma sqrt(1 - rho^2) z,  rho = exp(-dt / tau),  z ~ N(0, 1).
    Started from N(0, sigma^2) (``shadowing_initial_db``) the process stays
    stationary with variance sigma^2 and correlation exp(-dt / tau) between
    samples dt apart, for any sequence of steps: the exact discretisation of
    the Ornstein-Uhlenbeck process behind Gudmundson's exponential model.
    ``previous_db`` (dB) and ``dt_s`` (s) broadcast; ``sigma_db`` in dB;
    ``tau_s`` in s (see ``shadowing_correlation``). Pass exactly one of
    ``standard_normal`` (shaped like the result) or ``rng``.
    """
    previous = np.asarray(previous_db, dtype=float)
    dt = np.asarray(dt_s, dtype=float)
    rho = shadowing_correlation(dt, tau_s)
    # 1 - rho^2 = -expm1(-2 dt / tau), without the cancellation of 1 - rho^2 at dt << tau.
    innovation_variance = (np.where(dt > 0, 1.0, 0.0) if tau_s <= 0 else -np.expm1(-2.0 * dt / tau_s))
    shape = np.broadcast_shapes(previous.shape, rho.shape)
    z = _standard_normal_draws(standard_normal, rng, shape)
    return rho * previous + sigma_db * np.sqrt(innovation_variance) * z


def _standard_normal_draws(standard_normal: ArrayLike | None, rng: np.random.Generator | None,
                           size: int | tuple[int, ...] | None) -> np.ndarray:
    if (standard_normal is None) == (rng is None):
        raise ValueError("pass exactly one of standard_normal (the draws) or rng (a numpy Generator)")
    if standard_normal is None:
        return rng.standard_normal(size)
    z = np.asarray(standard_normal, dtype=float)
    # One draw per link: a smaller array would broadcast into links sharing their noise.
    expected = () if size is None else ((size,) if isinstance(size, int) else tuple(size))
    if size is not None and z.shape != expected:
        raise ValueError(f"standard_normal has shape {z.shape}, expected {expected}")
    return z


# --- Small-scale fading --------------------------------------------------------------------------

def rayleigh_power_gain(rng: np.random.Generator, size: int | tuple[int, ...] | None = None) -> np.ndarray:
    """Rayleigh fading power gain |h|^2 ~ Exponential(mean 1), linear.

    The envelope |h| of a sum of many scattered paths without a dominant one is
    Rayleigh distributed; its square, the power gain, is exponential.
    """
    return rng.standard_exponential(size)


def rician_power_gain(rng: np.random.Generator, k_factor: float,
                      size: int | tuple[int, ...] | None = None) -> np.ndarray:
    """Rician fading power gain with K-factor ``k_factor`` (linear, LOS power / scattered power), mean 1.

    h = sqrt(K / (K + 1)) + sqrt(1 / (K + 1)) w, w ~ CN(0, 1), so
    2 (K + 1) |h|^2 is noncentral chi-square with 2 degrees of freedom and
    noncentrality 2K. K = 0 is Rayleigh; K = inf is no fading (gain 1).
    """
    if k_factor < 0:
        raise ValueError("the Rician K-factor must be >= 0")
    if np.isinf(k_factor):
        return np.ones(size)
    if k_factor == 0:
        return rayleigh_power_gain(rng, size)
    return rng.noncentral_chisquare(2.0, 2.0 * k_factor, size) / (2.0 * (k_factor + 1.0))


def fading_gain_db(model: str, rng: np.random.Generator | None, size: int | tuple[int, ...] | None = None,
                   k_factor: float = 0.0) -> np.ndarray:
    """Per-packet small-scale fading power gain, dB: ``model`` one of 'none', 'rayleigh', 'rician'.

    Draw once per packet and link (block fading: constant over one packet).
    'none' returns 0 dB (and needs no ``rng``); 'rician' uses ``k_factor``
    (linear). The linear gains have mean 1, so the mean received power is the
    path-loss budget's; in dB the mean is below 0 (-2.5 dB for Rayleigh).
    """
    if model == "none":
        return np.zeros(size)
    if rng is None:
        raise ValueError(f"{model!r} fading needs an rng")
    if model == "rayleigh":
        gain = rayleigh_power_gain(rng, size)
    elif model == "rician":
        gain = rician_power_gain(rng, k_factor, size)
    else:
        raise ValueError(f"unknown fading model {model!r}; known: {', '.join(FADING_MODELS)}")
    # A draw of exactly 0 is possible in principle; keep the dB finite.
    return 10.0 * np.log10(np.maximum(gain, np.finfo(float).tiny))


# --- Noise and SNR -------------------------------------------------------------------------------

def thermal_noise_dbm(bandwidth_hz: ArrayLike, noise_figure_db: ArrayLike = 0.0) -> np.ndarray:
    """Receiver noise floor kTB + NF = -174 dBm/Hz + 10 log10(B) + NF, dBm.

    ``bandwidth_hz`` the noise bandwidth in Hz (the channel's), ``noise_figure_db``
    the receiver's noise figure in dB.
    """
    return (THERMAL_NOISE_DENSITY_DBM_PER_HZ + 10.0 * np.log10(np.asarray(bandwidth_hz, dtype=float))
            + np.asarray(noise_figure_db, dtype=float))


def snr_db(received_power_dbm: ArrayLike, noise_floor_dbm: ArrayLike,
           interference_dbm: ArrayLike | None = None) -> np.ndarray:
    """Signal to noise (and interference) ratio, dB.

    SNR = P_rx - N (dBm - dBm). With ``interference_dbm`` (total interfering
    power at the receiver, dBm), noise and interference add in mW:
    SINR = P_rx - 10 log10(10^(N/10) + 10^(I/10)).
    """
    rx = np.asarray(received_power_dbm, dtype=float)
    noise = np.asarray(noise_floor_dbm, dtype=float)
    if interference_dbm is not None:
        noise = np.logaddexp(noise * _LN10_OVER_10, np.asarray(interference_dbm, dtype=float) * _LN10_OVER_10)
        noise = noise / _LN10_OVER_10
    return rx - noise


def ebn0_db_from_snr_db(snr_db: ArrayLike, bandwidth_hz: float, bitrate_bps: float) -> np.ndarray:
    """Energy per bit over noise density, Eb/N0 = SNR + 10 log10(B / R), dB.

    SNR = (Eb R) / (N0 B), so Eb/N0 = SNR B / R. ``bandwidth_hz`` the noise
    bandwidth B (Hz), ``bitrate_bps`` the bit rate R (bit/s).
    """
    return np.asarray(snr_db, dtype=float) + 10.0 * np.log10(bandwidth_hz / bitrate_bps)


def _db_to_linear(value_db: ArrayLike) -> np.ndarray:
    return np.power(10.0, np.asarray(value_db, dtype=float) / 10.0)


# --- Bit error rates -----------------------------------------------------------------------------

def ber_oqpsk_dsss_802154(sinr_db: ArrayLike) -> np.ndarray:
    """Bit error rate of the IEEE 802.15.4 2.4 GHz O-QPSK PHY with DSSS (16-ary orthogonal chips).

    IEEE Std 802.15.4-2006, Annex E (E.4.1.7), AWGN:
    BER = (8/15) (1/16) sum_{k=2}^{16} (-1)^k C(16, k) exp(20 SINR (1/k - 1)),
    with SINR linear, over the 2 MHz channel. ``sinr_db`` in dB. The sum is
    0.5 at SINR = 0 and falls monotonically; results are clipped to [0, 0.5]
    against rounding of the alternating sum.
    """
    sinr = _db_to_linear(sinr_db)
    exponents = 20.0 * sinr[..., None] * (1.0 / _K_802154 - 1.0)
    ber = (8.0 / 15.0) * (1.0 / 16.0) * np.sum(_SIGNED_BINOMIALS_802154 * np.exp(exponents), axis=-1)
    return np.clip(ber, 0.0, 0.5)


def ber_noncoherent_fsk(ebn0_db: ArrayLike) -> np.ndarray:
    """Bit error rate of non-coherent binary FSK (and GFSK read as such), AWGN: 0.5 exp(-Eb/N0 / 2).

    ``ebn0_db`` in dB (Proakis, Digital Communications, orthogonal binary FSK
    with envelope detection). GFSK receivers with a frequency discriminator,
    like the nRF24L01+, land near this curve; implementation losses are left to
    the receiver's noise figure.
    """
    return 0.5 * np.exp(-_db_to_linear(ebn0_db) / 2.0)


def ber_bpsk(ebn0_db: ArrayLike) -> np.ndarray:
    """Bit error rate of coherent BPSK, AWGN: Q(sqrt(2 Eb/N0)) = erfc(sqrt(Eb/N0)) / 2.

    ``ebn0_db`` in dB. Uncoded: a convolutional code (802.11's rate-1/2 BCC)
    gains several dB on this, which a preset folds into its effective noise figure.
    """
    return 0.5 * erfc(np.sqrt(_db_to_linear(ebn0_db)))


def ber_qpsk(ebn0_db: ArrayLike) -> np.ndarray:
    """Bit error rate of Gray-coded coherent QPSK per bit, AWGN: Q(sqrt(2 Eb/N0)), the same as BPSK's.

    ``ebn0_db`` in dB. QPSK carries 2 bits per symbol, so at a given SNR and
    bandwidth its Eb/N0 (see ``ebn0_db_from_snr_db``) is 3 dB lower than BPSK's
    at half the bit rate.
    """
    return ber_bpsk(ebn0_db)


def bit_error_rate(modulation: str, snr_db: ArrayLike, bandwidth_hz: float, bitrate_bps: float) -> np.ndarray:
    """Bit error rate of ``modulation`` at ``snr_db`` (dB) in a channel of ``bandwidth_hz`` (Hz) at ``bitrate_bps``.

    'oqpsk_dsss_802154' takes the SNR over the channel as the standard's SINR;
    'noncoherent_fsk', 'bpsk' and 'qpsk' take Eb/N0 = SNR + 10 log10(B / R).
    """
    if modulation == "oqpsk_dsss_802154":
        return ber_oqpsk_dsss_802154(snr_db)
    ebn0 = ebn0_db_from_snr_db(snr_db, bandwidth_hz, bitrate_bps)
    if modulation == "noncoherent_fsk":
        return ber_noncoherent_fsk(ebn0)
    if modulation == "bpsk":
        return ber_bpsk(ebn0)
    if modulation == "qpsk":
        return ber_qpsk(ebn0)
    raise ValueError(f"unknown modulation {modulation!r}; known: {', '.join(MODULATIONS)}")


# --- Packets -------------------------------------------------------------------------------------

def packet_error_rate(ber: ArrayLike, length_bits: ArrayLike) -> np.ndarray:
    """Packet error rate of ``length_bits`` independent bits at bit error rate ``ber``: 1 - (1 - BER)^L.

    Dimensionless, in [0, 1]. Computed as -expm1(L log1p(-BER)) so that small
    BERs (1e-9 over 1000 bits) keep their precision. No coding, no error
    correction: any wrong bit loses the packet, as a CRC check would.
    """
    b = np.clip(np.asarray(ber, dtype=float), 0.0, 1.0)
    length = np.asarray(length_bits, dtype=float)
    if np.any(length < 0):
        raise ValueError("length_bits must be non-negative")
    with np.errstate(divide="ignore", invalid="ignore"):
        log_success = length * np.log1p(-b)
        per = -np.expm1(log_success)
    # 0 bits never fail (0 * log(0) is nan above); clip rounding at the ends.
    return np.clip(np.where(length == 0, 0.0, per), 0.0, 1.0)


_OQPSK_EXPONENT_FACTORS = 1.0 / _K_802154 - 1.0
_OQPSK_SCALE = (8.0 / 15.0) * (1.0 / 16.0)


def packet_error_rate_at_snr(modulation: str, snr_db: np.ndarray, bandwidth_hz: float, bitrate_bps: float,
                             length_bits: np.ndarray) -> np.ndarray:
    """PER of packets of ``length_bits`` (> 0 each) at ``snr_db`` (1-d, dB): ``packet_error_rate`` of
    ``bit_error_rate``, the same floating-point operations in the same order with fewer temporaries and
    checks, for the message bus's every frame (802.15.4; the other modulations take the chain itself)."""
    if modulation != "oqpsk_dsss_802154":
        return packet_error_rate(bit_error_rate(modulation, snr_db, bandwidth_hz, bitrate_bps), length_bits)
    sinr = np.power(10.0, np.asarray(snr_db, dtype=float) / 10.0)
    terms = 20.0 * sinr[:, None] * _OQPSK_EXPONENT_FACTORS
    np.exp(terms, out=terms)
    terms *= _SIGNED_BINOMIALS_802154
    ber = np.add.reduce(terms, axis=-1)
    ber *= _OQPSK_SCALE
    np.clip(ber, 0.0, 0.5, out=ber)  # within [0, 1] already: packet_error_rate's clip changes nothing
    np.negative(ber, out=ber)
    np.log1p(ber, out=ber)
    ber *= length_bits
    np.expm1(ber, out=ber)
    np.negative(ber, out=ber)
    return np.clip(ber, 0.0, 1.0, out=ber)


def packet_error_rate_at_power(received_power_dbm: ArrayLike, length_bits: ArrayLike, *, modulation: str,
                               noise_floor_dbm: float, bandwidth_hz: float, bitrate_bps: float) -> np.ndarray:
    """PER of a ``length_bits`` packet received at ``received_power_dbm`` (dBm) over noise ``noise_floor_dbm`` (dBm).

    The chain SNR -> BER (``bit_error_rate``) -> PER (``packet_error_rate``).
    """
    snr = snr_db(received_power_dbm, noise_floor_dbm)
    return packet_error_rate(bit_error_rate(modulation, snr, bandwidth_hz, bitrate_bps), length_bits)


def packet_airtime_s(payload_bytes: ArrayLike, bitrate_bps: float, *, preamble_bits: int = 0,
                     header_bits: int = 0, mac_overhead_bits: int = 0, fixed_overhead_s: float = 0.0) -> np.ndarray:
    """Time on air of one frame, s: (preamble + header + 8 payload + MAC overhead) / bitrate + fixed overhead.

    ``payload_bytes`` the application payload (bytes); ``bitrate_bps`` the
    rate these bits go at (bit/s); ``preamble_bits``, ``header_bits`` (PHY
    header) and ``mac_overhead_bits`` (MAC header and checksum) in bits, since
    some formats have fields of odd bit counts (Enhanced ShockBurst's 9-bit
    control field); ``fixed_overhead_s`` per frame (s): turnaround, PLL
    settling, or a preamble sent at its own rate (802.11's), as the preset says.
    """
    payload = np.asarray(payload_bytes, dtype=float)
    if np.any(payload < 0):
        raise ValueError("payload_bytes must be non-negative")
    bits = preamble_bits + header_bits + 8.0 * payload + mac_overhead_bits
    return bits / bitrate_bps + fixed_overhead_s


def sensitivity_dbm(per_of_received_power: Callable[[float], float], per_threshold: float, *,
                    low_dbm: float = -150.0, high_dbm: float = 30.0, tolerance_db: float = 1e-4) -> float:
    """Received power (dBm) at which a PER curve crosses ``per_threshold``, by bisection.

    ``per_of_received_power`` maps a received power in dBm to a PER in [0, 1],
    non-increasing in power (e.g. a preset's PER of its datasheet reference
    packet: 20 octets at 1 % for 802.15.4; a 1-bit "packet" at 1e-3 for a BER
    defined sensitivity). The bracket [``low_dbm``, ``high_dbm``] must hold the
    crossing; the answer is within ``tolerance_db`` (dB) above it.
    """
    if not 0.0 < per_threshold < 1.0:
        raise ValueError("per_threshold must lie strictly between 0 and 1")
    if per_of_received_power(low_dbm) <= per_threshold or per_of_received_power(high_dbm) > per_threshold:
        raise ValueError(f"the PER does not cross {per_threshold} between {low_dbm} and {high_dbm} dBm")
    low, high = low_dbm, high_dbm  # invariant: PER(low) > threshold >= PER(high)
    while high - low > tolerance_db:
        middle = 0.5 * (low + high)
        if per_of_received_power(middle) > per_threshold:
            low = middle
        else:
            high = middle
    return high
