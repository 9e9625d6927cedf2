"""The radio channel's pure formulas against hand-computed references, statistics and properties."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from sim.radio import channel
from sim.radio.presets import IDEAL, IEEE802154, NRF24, PRESETS, WIFI, FadingParameters, preset

RADIOS = (IEEE802154, NRF24, WIFI)


# --- Path loss ---------------------------------------------------------------------------------------

def test_log_distance_path_loss_by_hand():
    # n = 3, PL0 = 40 dB: 10 m costs 30 dB more, 100 m 60 dB; below d0 = 1 m the loss stays PL0.
    got = channel.log_distance_path_loss_db([0.2, 1.0, 2.0, 10.0, 100.0], exponent=3.0, reference_loss_db=40.0)
    want = [40.0, 40.0, 40.0 + 30.0 * math.log10(2.0), 70.0, 100.0]
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_log_distance_path_loss_other_reference_distance():
    # d0 = 2 m, n = 2, PL0 = 46 dB: at 8 m, 46 + 20 log10(4) = 58.04 dB.
    got = channel.log_distance_path_loss_db(8.0, exponent=2.0, reference_loss_db=46.0, reference_distance_m=2.0)
    assert got == pytest.approx(46.0 + 20.0 * math.log10(4.0), abs=1e-12)


def test_wall_term_with_0_1_and_3_walls():
    walls = channel.wall_loss_db([0, 1, 3], 3.4)
    np.testing.assert_allclose(walls, [0.0, 3.4, 10.2], atol=1e-12)
    got = channel.log_distance_path_loss_db([5.0, 5.0, 5.0], 3.0, 40.0, total_wall_loss_db=walls)
    base = 40.0 + 30.0 * math.log10(5.0)
    np.testing.assert_allclose(got, [base, base + 3.4, base + 10.2], atol=1e-12)


def test_wall_term_with_two_wall_types():
    # Per link: (light, heavy) walls crossed; 2 light + 1 heavy = 6.8 + 6.9.
    counts = np.array([[0, 0], [2, 1], [0, 3]])
    np.testing.assert_allclose(channel.wall_loss_db(counts, [3.4, 6.9]), [0.0, 13.7, 20.7], atol=1e-12)
    with pytest.raises(ValueError):
        channel.wall_loss_db(counts, [3.4, 6.9, 10.0])


def test_reference_losses_at_2_4_ghz():
    # P.1238: 20 log10(2400) - 28 = 39.60 dB; free space at 1 m: 40.05 dB.
    assert channel.itu_p1238_reference_loss_db(2.4e9) == pytest.approx(20 * math.log10(2400) - 28, abs=1e-12)
    assert channel.itu_p1238_reference_loss_db(2.4e9) == pytest.approx(39.60, abs=0.01)
    assert float(channel.free_space_path_loss_db(1.0, 2.4e9)) == pytest.approx(40.05, abs=0.01)


def test_received_power_budget():
    # 0 dBm - 70 dB - 4 dB shadowing + (-3 dB fade) = -77 dBm.
    assert float(channel.received_power_dbm(0.0, 70.0, 4.0, -3.0)) == pytest.approx(-77.0)
    np.testing.assert_allclose(channel.received_power_dbm(15.0, [60.0, 80.0]), [-45.0, -65.0])


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0.0, 500.0), min_size=2, max_size=20),
       st.floats(1.5, 5.0), st.floats(20.0, 60.0))
def test_path_loss_monotone_in_distance(distances, exponent, reference_loss):
    d = np.sort(np.asarray(distances))
    loss = channel.log_distance_path_loss_db(d, exponent, reference_loss)
    assert np.all(np.diff(loss) >= -1e-12)
    assert np.all(loss >= reference_loss - 1e-12)


# --- Noise, SNR, Eb/N0 -------------------------------------------------------------------------------

def test_thermal_noise_by_hand():
    # -174 + 10 log10(2e6) = -110.99 dBm; + 10 dB NF = -100.99 dBm; 20 MHz: -100.99 + 0 NF.
    assert float(channel.thermal_noise_dbm(2e6)) == pytest.approx(-174 + 10 * math.log10(2e6), abs=1e-12)
    assert float(channel.thermal_noise_dbm(2e6, 10.0)) == pytest.approx(-100.99, abs=0.01)
    assert float(channel.thermal_noise_dbm(20e6)) == pytest.approx(-100.99, abs=0.01)


def test_snr_and_sinr():
    assert float(channel.snr_db(-80.0, -100.0)) == pytest.approx(20.0)
    # Interference equal to the noise doubles it: 3.01 dB less.
    assert float(channel.snr_db(-80.0, -100.0, -100.0)) == pytest.approx(20.0 - 10 * math.log10(2), abs=1e-12)


def test_ebn0_from_snr():
    # 802.11 MCS0: 20 MHz over 6.5 Mbit/s adds 10 log10(3.077) = 4.88 dB.
    assert float(channel.ebn0_db_from_snr_db(5.0, 20e6, 6.5e6)) == pytest.approx(5.0 + 10 * math.log10(20 / 6.5))
    assert float(channel.ebn0_db_from_snr_db(7.0, 2e6, 2e6)) == pytest.approx(7.0)


# --- Bit error rates ---------------------------------------------------------------------------------

def _ber_802154_by_hand(sinr_db):
    sinr = 10 ** (sinr_db / 10)
    total = sum((-1) ** k * math.comb(16, k) * math.exp(20 * sinr * (1 / k - 1)) for k in range(2, 17))
    return 8 / 15 * 1 / 16 * total


@pytest.mark.parametrize("sinr_db", [-6.0, -2.0, 0.0, 1.0, 3.0])
def test_802154_ber_matches_the_standards_formula(sinr_db):
    want = _ber_802154_by_hand(sinr_db)
    assert float(channel.ber_oqpsk_dsss_802154(sinr_db)) == pytest.approx(want, rel=1e-9)


def test_802154_ber_limits_and_spot_value():
    # At SINR -> 0 the sum is (1 - 1)^16 - 1 + 16 = 15, so BER -> (8/15)(1/16) 15 = 1/2.
    assert float(channel.ber_oqpsk_dsss_802154(-90.0)) == pytest.approx(0.5, abs=1e-6)
    # At 0 dB the dominant k = 2 term is 120 e^-10 and the k = 3 one -560 e^(-40/3).
    by_hand = 8 / 15 / 16 * (120 * math.exp(-10) - 560 * math.exp(-40 / 3) + 1820 * math.exp(-15))
    assert float(channel.ber_oqpsk_dsss_802154(0.0)) == pytest.approx(by_hand, rel=0.05)


def test_noncoherent_fsk_ber_by_hand():
    # Eb/N0 = 10 dB = 10: 0.5 e^-5 = 3.369e-3; 0 dB: 0.5 e^-0.5 = 0.3033.
    np.testing.assert_allclose(channel.ber_noncoherent_fsk([10.0, 0.0]),
                               [0.5 * math.exp(-5.0), 0.5 * math.exp(-0.5)], rtol=1e-12)


def test_bpsk_and_qpsk_ber_by_hand():
    # Q(sqrt(2 Eb/N0)) = erfc(sqrt(Eb/N0)) / 2; at 9.6 dB BPSK's classic 1e-5.
    for ebn0_db in (0.0, 4.0, 9.6):
        want = 0.5 * math.erfc(math.sqrt(10 ** (ebn0_db / 10)))
        assert float(channel.ber_bpsk(ebn0_db)) == pytest.approx(want, rel=1e-12)
        assert float(channel.ber_qpsk(ebn0_db)) == pytest.approx(want, rel=1e-12)
    assert float(channel.ber_bpsk(9.6)) == pytest.approx(1.0e-5, rel=0.05)


def test_bit_error_rate_dispatch_uses_ebn0():
    # GFSK at 2 Mbit/s in 4 MHz: Eb/N0 is SNR + 3.01 dB.
    got = channel.bit_error_rate("noncoherent_fsk", 7.0, 4e6, 2e6)
    assert float(got) == pytest.approx(0.5 * math.exp(-10 ** ((7.0 + 10 * math.log10(2)) / 10) / 2))
    with pytest.raises(ValueError):
        channel.bit_error_rate("ook", 7.0, 1e6, 1e6)


# --- Packet error rate -------------------------------------------------------------------------------

def test_per_by_hand():
    # 1 - (1 - 1e-3)^100 = 0.09521; 1 - (1 - 0.01)^8 = 0.07726; L = 0 never fails; BER 1 always.
    np.testing.assert_allclose(channel.packet_error_rate([1e-3, 0.01], [100, 8]),
                               [1 - 0.999 ** 100, 1 - 0.99 ** 8], rtol=1e-12)
    assert float(channel.packet_error_rate(0.3, 0)) == 0.0
    assert float(channel.packet_error_rate(1.0, 10)) == 1.0
    assert float(channel.packet_error_rate(0.0, 10)) == 0.0


def test_per_keeps_precision_at_tiny_ber():
    # 1e-12 over 1000 bits: PER = 1e-9 (1 - 5e-10 ...); the naive 1 - (1 - p)^L loses ~4 digits.
    assert float(channel.packet_error_rate(1e-12, 1000)) == pytest.approx(1e-9, rel=1e-6)


@settings(max_examples=80, deadline=None)
@given(st.sampled_from(["oqpsk_dsss_802154", "noncoherent_fsk", "bpsk", "qpsk"]),
       st.lists(st.floats(-20.0, 30.0), min_size=2, max_size=15), st.integers(1, 20_000))
def test_per_in_unit_interval_and_non_increasing_in_snr(modulation, snrs, length_bits):
    snr = np.sort(np.asarray(snrs))
    per = channel.packet_error_rate(channel.bit_error_rate(modulation, snr, 2e6, 250e3), length_bits)
    assert np.all((per >= 0.0) & (per <= 1.0))
    assert np.all(np.diff(per) <= 1e-15)


@settings(max_examples=80, deadline=None)
@given(st.floats(0.0, 1.0), st.lists(st.integers(0, 100_000), min_size=2, max_size=15))
def test_per_non_decreasing_in_length(ber, lengths):
    per = channel.packet_error_rate(ber, np.sort(np.asarray(lengths)))
    assert np.all((per >= 0.0) & (per <= 1.0))
    assert np.all(np.diff(per) >= -1e-15)


# --- Fading ------------------------------------------------------------------------------------------

def test_rayleigh_power_is_exponential_with_mean_1():
    rng = np.random.default_rng(20240611)
    gain = channel.rayleigh_power_gain(rng, 40_000)
    assert gain.mean() == pytest.approx(1.0, abs=4 * 1 / math.sqrt(40_000))
    assert stats.kstest(gain, "expon").pvalue > 0.01
    gain_db = channel.fading_gain_db("rayleigh", np.random.default_rng(7), 40_000)
    np.testing.assert_allclose(np.mean(10 ** (gain_db / 10)), 1.0, atol=0.02)


@pytest.mark.parametrize("k_factor", [0.0, 1.0, 5.0, 20.0])
def test_rician_power_has_mean_1(k_factor):
    gain = channel.rician_power_gain(np.random.default_rng(11), k_factor, 40_000)
    # The variance of |h|^2 is (1 + 2K) / (1 + K)^2 <= 1: 4 standard errors.
    assert gain.mean() == pytest.approx(1.0, abs=4 * math.sqrt((1 + 2 * k_factor) / (1 + k_factor) ** 2 / 40_000))


def test_rician_tends_to_no_fading_as_k_grows():
    spreads = [np.std(channel.fading_gain_db("rician", np.random.default_rng(3), 20_000, k_factor=k))
               for k in (1.0, 10.0, 100.0, 1e4)]
    assert np.all(np.diff(spreads) < 0)
    assert spreads[-1] < 0.1  # dB: at K = 1e4 the gain is 1 within a few percent
    np.testing.assert_array_equal(channel.fading_gain_db("rician", np.random.default_rng(3), 5, k_factor=np.inf),
                                  np.zeros(5))


def test_no_fading_and_unknown_fading():
    np.testing.assert_array_equal(channel.fading_gain_db("none", None, (2, 3)), np.zeros((2, 3)))
    with pytest.raises(ValueError):
        channel.fading_gain_db("nakagami", np.random.default_rng(0), 3)
    with pytest.raises(ValueError):
        FadingParameters(model="nakagami")


# --- Shadowing ---------------------------------------------------------------------------------------

def test_shadowing_ar1_is_stationary_with_the_right_correlation():
    sigma, tau, dt = 4.0, 2.0, 0.5
    rho = math.exp(-dt / tau)
    rng = np.random.default_rng(12345)
    links, steps = 4000, 40
    x = channel.shadowing_initial_db(sigma, links, rng=rng)
    samples = [x]
    for _ in range(steps):
        x = channel.shadowing_step_db(x, dt, sigma, tau, rng=rng)
        samples.append(x)
    series = np.array(samples)  # (steps + 1, links)
    n = series.size
    # Variance: relative standard error sqrt(2 / n_eff); correlated samples, so be generous (5 %).
    assert series.var() == pytest.approx(sigma ** 2, rel=0.05)
    assert abs(series.mean()) < 0.1
    # Lag-1 correlation over independent links: standard error about (1 - rho^2) / sqrt(n).
    lag1 = np.mean(series[1:] * series[:-1]) / sigma ** 2
    assert lag1 == pytest.approx(rho, abs=5 * (1 - rho ** 2) / math.sqrt(n) + 0.01)
    # Lag 4 (2 s): exp(-1).
    lag4 = np.mean(series[4:] * series[:-4]) / sigma ** 2
    assert lag4 == pytest.approx(math.exp(-4 * dt / tau), abs=0.03)


def test_shadowing_step_with_given_draws_by_hand():
    # rho = e^-0.5; x' = rho * 2 + 3 sqrt(1 - rho^2) * 0.7.
    rho = math.exp(-0.5)
    got = channel.shadowing_step_db(np.array([2.0, -1.0]), 1.0, 3.0, 2.0, standard_normal=np.array([0.7, 0.0]))
    np.testing.assert_allclose(got, [rho * 2 + 3 * math.sqrt(1 - rho ** 2) * 0.7, -rho], rtol=1e-12)


def test_shadowing_limits_and_argument_checks():
    frozen = channel.shadowing_step_db(np.array([1.5]), 10.0, 4.0, math.inf, standard_normal=np.array([2.0]))
    np.testing.assert_allclose(frozen, [1.5])
    fresh = channel.shadowing_step_db(np.array([1.5]), 0.1, 4.0, 0.0, standard_normal=np.array([0.25]))
    np.testing.assert_allclose(fresh, [1.0])
    with pytest.raises(ValueError):
        channel.shadowing_step_db(np.zeros(3), 0.1, 4.0, 1.0)  # neither draws nor rng
    with pytest.raises(ValueError):
        channel.shadowing_step_db(np.zeros(3), 0.1, 4.0, 1.0, standard_normal=np.zeros(3),
                                  rng=np.random.default_rng(0))
    with pytest.raises(ValueError):
        channel.shadowing_step_db(np.zeros(3), 0.1, 4.0, 1.0, standard_normal=0.5)  # one draw for 3 links


def test_shadowing_uses_no_global_random_state():
    np.random.seed(0)
    state = np.random.get_state()[1].copy()
    channel.shadowing_step_db(np.zeros(10), 0.1, 4.0, 1.0, rng=np.random.default_rng(1))
    channel.fading_gain_db("rayleigh", np.random.default_rng(1), 10)
    np.testing.assert_array_equal(np.random.get_state()[1], state)


# --- Airtime -----------------------------------------------------------------------------------------

def test_nrf24_airtime_by_hand():
    # Enhanced ShockBurst, 32-byte payload at 2 Mbit/s: (8 (1 + 5 + 32 + 2) + 9) / 2e6 = 164.5 us, + 130 us.
    assert float(NRF24.airtime_s(32)) == pytest.approx((8 * (1 + 5 + 32 + 2) + 9) / 2e6 + 130e-6, rel=1e-12)


def test_802154_airtime_by_hand():
    # 20-byte payload: (6 PHY + 11 MAC + 20) bytes * 8 / 250 kbit/s = 1.184 ms, + 320 us.
    assert float(IEEE802154.airtime_s(20)) == pytest.approx(37 * 8 / 250e3 + 320e-6, rel=1e-12)


def test_generic_airtime_by_hand():
    got = channel.packet_airtime_s(10, 1e6, preamble_bits=16, header_bits=8, mac_overhead_bits=24,
                                   fixed_overhead_s=1e-4)
    assert float(got) == pytest.approx((16 + 8 + 80 + 24) / 1e6 + 1e-4, rel=1e-12)


@pytest.mark.parametrize("radio", RADIOS, ids=lambda radio: radio.name)
def test_airtime_monotone_in_payload(radio):
    payloads = np.arange(radio.packet.max_payload_bytes + 1)
    airtime = radio.airtime_s(payloads)
    assert np.all(np.diff(airtime) > 0)
    np.testing.assert_allclose(np.diff(airtime), 8 / radio.bitrate_bps, rtol=1e-9)
    with pytest.raises(ValueError):
        radio.airtime_s(radio.packet.max_payload_bytes + 1)


# --- Sensitivity and presets -------------------------------------------------------------------------

@pytest.mark.parametrize("radio", RADIOS, ids=lambda radio: radio.name)
def test_preset_sensitivity_matches_its_datasheet(radio):
    computed = radio.computed_sensitivity_dbm()
    assert computed == pytest.approx(radio.sensitivity.datasheet_dbm, abs=2.0)
    # At the computed sensitivity the reference packet is at its threshold PER.
    per = float(radio.packet_error_rate(computed, radio.sensitivity.reference_length_bits))
    assert per == pytest.approx(radio.sensitivity.per_threshold, rel=0.01)


def test_sensitivity_bisection_on_a_known_curve():
    # PER falls linearly from 1 at -100 dBm to 0 at -90 dBm: 10 % is at -91 dBm.
    def per(power_dbm):
        return float(np.clip((-90.0 - power_dbm) / 10.0, 0.0, 1.0))
    assert channel.sensitivity_dbm(per, 0.1) == pytest.approx(-91.0, abs=1e-3)
    with pytest.raises(ValueError):
        channel.sensitivity_dbm(per, 0.1, low_dbm=-80.0, high_dbm=-70.0)


def test_802154_noise_figure_and_sensitivity_by_hand():
    # kTB over 2 MHz with the preset's NF, plus the SINR at which 160 bits fail 1 % of the time.
    required_sinr_db = channel.sensitivity_dbm(
        lambda s: float(channel.packet_error_rate(channel.ber_oqpsk_dsss_802154(s), 160)), 0.01,
        low_dbm=-20.0, high_dbm=20.0)
    floor = -174 + 10 * math.log10(2e6) + IEEE802154.noise_figure_db
    assert IEEE802154.computed_sensitivity_dbm() == pytest.approx(floor + required_sinr_db, abs=1e-3)


def test_presets_name_their_sources_and_the_ideal_one_is_marked():
    assert set(PRESETS) == {"ideal", "ieee802154", "nrf24", "wifi"}
    assert IDEAL.is_ideal and not any(radio.is_ideal for radio in RADIOS)
    for radio in PRESETS.values():
        assert radio.source
    assert "CC2420" in IEEE802154.source and "nRF24L01+" in NRF24.source and "802.11" in WIFI.source
    assert preset("nrf24") is NRF24
    with pytest.raises(ValueError):
        preset("lora")


def test_presets_use_p1238_office_defaults():
    for radio in RADIOS:
        assert radio.path_loss.exponent == 3.0
        assert radio.path_loss.reference_loss_db == pytest.approx(40.0, abs=0.5)


def test_radio_modules_import_no_mujoco():
    import pathlib
    for path in pathlib.Path(channel.__file__).parent.glob("*.py"):
        assert "mujoco" not in path.read_text()


@settings(max_examples=200, deadline=None)
@given(snr=st.lists(st.one_of(st.floats(-40.0, 40.0), st.just(-math.inf)), min_size=1, max_size=50),
       bits=st.integers(1, 12000), modulation=st.sampled_from(list(channel.MODULATIONS)))
def test_packet_error_rate_at_snr_is_the_chain_to_the_bit(snr, bits, modulation):
    """The bus's per-frame PER against bit_error_rate -> packet_error_rate, the reference it shortens."""
    snr = np.array(snr)
    lengths = np.full(len(snr), float(bits))
    lengths[::3] += 8.0
    expected = channel.packet_error_rate(channel.bit_error_rate(modulation, snr, 2e6, 250e3), lengths)
    np.testing.assert_array_equal(channel.packet_error_rate_at_snr(modulation, snr, 2e6, 250e3, lengths), expected)
