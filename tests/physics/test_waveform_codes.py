"""Tests of echoloc.physics.waveform beyond Barker: Golay, MLS, Kasami, chirps, bursts, names, metrics.

Sources: M. J. E. Golay, "Complementary series" (1961): r_a + r_b = 2N delta.
S. W. Golomb, "Shift Register Sequences" (1967): an m-sequence of order m has period
2**m - 1, every non-zero m-bit window once per period, 2**(m-1) ones, periodic
autocorrelation N and -1. Kasami (1966), Sarwate & Pursley, Proc. IEEE 68(5) (1980): the small
Kasami set's periodic correlations take only -1, -(2**(m/2)+1), 2**(m/2)-1. Merit factors
of the Barker codes (Golay 1972; Jedwab, "What can be used instead of a Barker sequence?",
2008): 2, 4.5, 4, 6.25, 8.17, 12.1, 14.08. Polaroid 6500 ranging module data sheet: 16
cycles at 49.4 kHz. Matched-filter envelopes (Levanon & Mozeson, "Radar Signals", 2004):
a rectangular pulse of duration T gives a triangle of half-width T, so the -3 dB full
width is 2T(1 - 1/sqrt 2) = 0.586 T and the -3 dB bandwidth of sinc²(fT) is 0.886/T;
a linear chirp of bandwidth B gives about |sinc(B tau)|, -3 dB width 0.886/B.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st

from echoloc.errors import WaveformError
from echoloc.physics.waveform import (
    MLS_TAPS,
    WAVEFORM_NAMES,
    Waveform,
    barker,
    barker_waveform,
    chirp_waveform,
    code_by_name,
    code_metrics,
    golay_pair,
    kasami_set,
    mls,
    modulate,
    peak_cross_correlation,
    tone_burst,
    waveform_by_name,
    waveform_metrics,
)

C_20C = 343.2


def _acf(x: np.ndarray) -> np.ndarray:
    """Aperiodic autocorrelation by numpy, lags -(N-1)..N-1, as integers."""
    x = np.asarray(x, dtype=np.int64)
    return np.correlate(x, x, mode="full")


def _cyclic(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """theta[k] = sum_n x[n] y[(n + k) mod N], exact integers via FFT (values are small)."""
    spectrum = np.conj(np.fft.fft(x.astype(float))) * np.fft.fft(y.astype(float))
    return np.rint(np.fft.ifft(spectrum).real).astype(np.int64)


# ----------------------------------------------------------------------------- Golay


@pytest.mark.parametrize("length", [2**k for k in range(1, 11)])
def test_golay_autocorrelations_add_to_a_delta_of_2n(length: int) -> None:
    """Golay (1961): r_a[k] + r_b[k] = 2N at k = 0 and 0 at every other lag."""
    a, b = golay_pair(length)
    assert a.shape == b.shape == (length,)
    assert a.dtype == b.dtype == np.int8
    assert set(np.unique(np.concatenate((a, b))).tolist()) == {-1, 1}
    total = _acf(a) + _acf(b)
    expected = np.zeros(2 * length - 1, dtype=np.int64)
    expected[length - 1] = 2 * length
    assert np.array_equal(total, expected)


def test_golay_pair_follows_the_recursion() -> None:
    """a' = a|b, b' = a|-b from ([1], [1]): length 2 is (++, +-), length 4 is (+++-, ++-+)."""
    assert [c.tolist() for c in golay_pair(2)] == [[1, 1], [1, -1]]
    assert [c.tolist() for c in golay_pair(4)] == [[1, 1, 1, -1], [1, 1, -1, 1]]
    a, b = golay_pair(64)
    a2, b2 = golay_pair(128)
    assert np.array_equal(a2, np.concatenate((a, b)))
    assert np.array_equal(b2, np.concatenate((a, -b)))


@pytest.mark.parametrize("length", [0, 1, 3, 6, 12, 1000, 2**21, 2.5, -4])
def test_golay_lengths_other_than_powers_of_two_raise(length: int) -> None:
    with pytest.raises(WaveformError, match="Golay"):
        golay_pair(length)


# ----------------------------------------------------------------------------- MLS


@pytest.mark.parametrize("order", sorted(MLS_TAPS))
def test_every_tabulated_mls_is_maximal(order: int) -> None:
    """Golomb: period exactly 2**m - 1 (every non-zero m-bit window once, and the taps'
    recurrence holds cyclically), two-valued periodic ACF {N, -1}, balance (one more -1
    than +1 with bit b -> (-1)**b)."""
    u = mls(order)
    n = 2**order - 1
    assert u.shape == (n,)
    assert u.dtype == np.int8
    bits = (1 - u.astype(np.int64)) // 2
    assert set(np.unique(bits).tolist()) == {0, 1}
    # The recurrence of the tabulated taps holds at every index, wrapping around.
    taps = MLS_TAPS[order]
    assert taps[0] == order
    feedback = np.zeros(n, dtype=np.int64)
    for t in taps:
        feedback ^= np.roll(bits, t)  # bits[i - t], cyclically
    assert np.array_equal(bits, feedback)
    # Each of the 2**m - 1 cyclic windows of m bits is a different non-zero state.
    windows = np.zeros(n, dtype=np.int64)
    for j in range(order):
        windows = (windows << 1) | np.roll(bits, -j)
    assert np.unique(windows).size == n
    assert np.all(windows != 0)
    # Two-valued periodic autocorrelation and balance.
    acf = _cyclic(u, u)
    assert acf[0] == n
    assert np.all(acf[1:] == -1)
    assert int(np.sum(u == -1)) == 2 ** (order - 1)
    assert int(np.sum(u == 1)) == 2 ** (order - 1) - 1


def test_mls_order_3_is_the_textbook_sequence() -> None:
    """x^3 + x^2 + 1 from fill 111: s[n] = s[n-3] ^ s[n-2] gives 1110010 (hand-computed)."""
    assert mls(3).tolist() == [-1, -1, -1, 1, 1, -1, 1]


@pytest.mark.parametrize(("order", "taps"), [(4, (4, 1)), (5, (5, 2)), (7, (7, 1)), (10, (10, 3))])
def test_mls_with_other_primitive_taps(order: int, taps: tuple[int, ...]) -> None:
    """Reciprocal primitive polynomials (x^4 + x + 1, x^5 + x^2 + 1, ...) also give m-sequences."""
    u = mls(order, taps)
    acf = _cyclic(u, u)
    assert acf[0] == 2**order - 1
    assert np.all(acf[1:] == -1)


@pytest.mark.parametrize(
    ("order", "taps", "match"),
    [
        (4, (4, 2), "maximal"),  # x^4 + x^2 + 1 = (x^2 + x + 1)^2
        (5, (5, 4, 3, 2, 1), "maximal"),  # (x^6 - 1)/(x - 1): period 6
        (4, (3, 1), "include 4"),
        (4, (4, 5), "1..4"),
        (1, None, "order"),
        (17, None, "order"),
        (21, (21, 2), "order"),
    ],
)
def test_mls_rejects_bad_orders_and_non_primitive_taps(
    order: int, taps: tuple[int, ...] | None, match: str
) -> None:
    with pytest.raises(WaveformError, match=match):
        mls(order, taps)


# ----------------------------------------------------------------------------- Kasami


@pytest.mark.parametrize("order", [4, 6, 8, 10])
def test_kasami_correlations_are_three_valued_and_bounded(order: int) -> None:
    """Kasami; Sarwate & Pursley: cross-correlations and off-peak autocorrelations are in
    {-1, -(2**(m/2) + 1), 2**(m/2) - 1}, so |theta| <= 2**(m/2) + 1."""
    codes = kasami_set(order)
    n = 2**order - 1
    half = 2 ** (order // 2)
    assert codes.shape == (half, n)
    assert codes.dtype == np.int8
    assert np.array_equal(codes[0], mls(order))
    spectra = np.fft.fft(codes.astype(float), axis=1)
    theta = np.rint(np.fft.ifft(np.conj(spectra)[:, None, :] * spectra[None, :, :], axis=2).real)
    peaks = theta[np.arange(half), np.arange(half), 0]
    assert np.all(peaks == n)
    theta[np.arange(half), np.arange(half), 0] = -1  # set the peaks aside
    assert set(np.unique(theta).tolist()) <= {-1, -(half + 1), half - 1}
    assert np.max(np.abs(theta)) == half + 1
    # The same bound through the library's normalised measure, for one pair.
    assert peak_cross_correlation(codes[1], codes[-1], periodic=True) == pytest.approx((half + 1) / n)


@pytest.mark.parametrize("order", [2, 3, 5, 18, 4.5])
def test_kasami_needs_an_even_order_from_4(order: int) -> None:
    with pytest.raises(WaveformError, match="Kasami"):
        kasami_set(order)


# ----------------------------------------------------------------------------- chirps and bursts


def _instantaneous_frequency(x: np.ndarray, fs: float) -> tuple[np.ndarray, np.ndarray]:
    """(times, frequency) from the unwrapped phase of the analytic signal."""
    phase = np.unwrap(np.angle(scipy.signal.hilbert(x)))
    return (np.arange(x.size - 1) + 0.5) / fs, np.diff(phase) * fs / (2 * np.pi)


@pytest.mark.parametrize(("f0", "f1"), [(40e3, 60e3), (70e3, 30e3)])
def test_lfm_instantaneous_frequency_is_linear(f0: float, f1: float) -> None:
    """LFM: f(t) = f0 + (f1 - f0) t / T, within 1 % away from the edges of the pulse."""
    fs, duration = 1e6, 2e-3
    w = chirp_waveform(f0, f1, duration, fs, window="rect")
    assert w.name == "lfm"
    assert w.carrier_hz == pytest.approx((f0 + f1) / 2)
    assert len(w.samples) == 2000
    assert w.samples[0] == pytest.approx(0.0, abs=1e-12)  # sine phase 0 at t = 0
    t, f = _instantaneous_frequency(w.samples, fs)
    inner = (t > 0.1 * duration) & (t < 0.9 * duration)
    expected = f0 + (f1 - f0) * t / duration
    assert np.max(np.abs(f[inner] / expected[inner] - 1)) < 0.01


def test_hfm_period_is_linear_in_time() -> None:
    """HFM (linear-period modulation): 1/f(t) = 1/f0 + (1/f1 - 1/f0) t / T, within 1 %."""
    fs, duration, f0, f1 = 1e6, 2e-3, 35e3, 65e3
    w = chirp_waveform(f0, f1, duration, fs, method="hyperbolic", window="rect")
    assert w.name == "hfm"
    assert w.carrier_hz == pytest.approx(math.sqrt(f0 * f1))
    t, f = _instantaneous_frequency(w.samples, fs)
    inner = (t > 0.1 * duration) & (t < 0.9 * duration)
    period = 1 / f0 + (1 / f1 - 1 / f0) * t / duration
    assert np.max(np.abs(f[inner] * period[inner] - 1)) < 0.01
    # And it is not linear: at mid-pulse an LFM would be at (f0 + f1)/2 = 50 kHz,
    # HFM at 2 f0 f1 / (f0 + f1) = 45.5 kHz.
    mid = np.argmin(np.abs(t - duration / 2))
    assert f[mid] == pytest.approx(2 * f0 * f1 / (f0 + f1), rel=0.01)


def test_chirp_windows_shape_the_envelope() -> None:
    """Hann: zero at both ends; Tukey(0.25): the middle 75 % equals the unwindowed sweep."""
    args = (40e3, 60e3, 1e-3, 1e6)
    rect = chirp_waveform(*args, window="rect").samples
    hann = chirp_waveform(*args, window="hann").samples
    tukey = chirp_waveform(*args, window="tukey", tukey_alpha=0.25).samples
    assert hann[0] == hann[-1] == 0.0
    middle = slice(130, 870)
    assert np.array_equal(tukey[middle], rect[middle])
    assert np.max(np.abs(tukey[:100])) < np.max(np.abs(rect[:100]))


@pytest.mark.parametrize(
    "kwargs",
    [
        {"f0_hz": 0.0},
        {"f1_hz": 100e3},
        {"duration_s": 0.0},
        {"duration_s": 1e-6},
        {"method": "quadratic"},
        {"window": "kaiser"},
        {"tukey_alpha": 1.5},
    ],
)
def test_invalid_chirps_raise(kwargs: dict[str, object]) -> None:
    args: dict[str, object] = {"f0_hz": 40e3, "f1_hz": 60e3, "duration_s": 1e-3, "sample_rate_hz": 200e3}
    args.update(kwargs)
    with pytest.raises(WaveformError):
        chirp_waveform(**args)  # type: ignore[arg-type]


def test_polaroid_burst_is_16_cycles_at_49_4_khz() -> None:
    """Data sheet: 16 cycles at 49.4 kHz; 2 MHz sampling puts no sample on a zero crossing
    but the first, so the 16 cycles show as 31 sign changes; the spectrum peaks at 49.4 kHz."""
    fs = 2e6
    w = tone_burst(sample_rate_hz=fs)
    assert len(w.samples) == round(16 * fs / 49.4e3) == 648
    assert w.carrier_hz == 49.4e3
    assert w.duration_s == pytest.approx(16 / 49.4e3, abs=0.5 / fs)
    signs = np.sign(w.samples[1:])
    assert np.all(signs != 0)
    assert np.count_nonzero(np.diff(signs)) == 2 * 16 - 1
    n_fft = 1 << 18
    spectrum = np.abs(np.fft.rfft(w.samples, n_fft))
    peak_hz = np.argmax(spectrum) * fs / n_fft
    assert peak_hz == pytest.approx(49.4e3, rel=0.005)
    by_name = waveform_by_name("polaroid", sample_rate_hz=fs, carrier_hz=40e3)
    assert by_name.name == "polaroid"
    assert np.array_equal(by_name.samples, w.samples)


# ----------------------------------------------------------------------------- names


@pytest.mark.parametrize(
    ("name", "code"),
    [
        ("barker13", barker(13)),
        ("barker4b", barker(4, 1)),
        ("barker2b", barker(2, 1)),
        ("golay16a", golay_pair(16)[0]),
        ("golay16b", golay_pair(16)[1]),
        ("mls7", mls(7)),
        ("kasami6:2", kasami_set(6)[2]),
        ("kasami8:15", kasami_set(8)[15]),
    ],
)
def test_code_names_give_the_code_on_the_carrier(name: str, code: np.ndarray) -> None:
    """A code name is the code modulated with the given carrier settings; its name round-trips."""
    w = waveform_by_name(name, carrier_hz=40e3, cycles_per_bit=2, sample_rate_hz=400e3, carrier="square")
    expected = modulate(code, carrier_hz=40e3, cycles_per_bit=2, sample_rate_hz=400e3, carrier="square")
    assert np.array_equal(w.samples, expected.samples)
    assert len(w.samples) == len(code) * 2 * 10
    assert w.name == name
    assert np.array_equal(code_by_name(name), code)
    again = waveform_by_name(
        w.name, carrier_hz=40e3, cycles_per_bit=2, sample_rate_hz=400e3, carrier="square"
    )
    assert np.array_equal(again.samples, w.samples)


@pytest.mark.parametrize(
    ("alias", "canonical"),
    [("barker4a", "barker4"), (" Barker13 ", "barker13"), ("golay8", "golay8a"), ("kasami4", "kasami4:0")],
)
def test_name_aliases_map_to_canonical_names(alias: str, canonical: str) -> None:
    assert waveform_by_name(alias).name == canonical


def test_default_barker_name_is_the_report_pulse() -> None:
    """barker13 with the defaults is barker_waveform(): 208 samples at 200 kHz."""
    assert np.array_equal(waveform_by_name("barker13").samples, barker_waveform().samples)


def test_chirp_names_are_centred_on_the_carrier() -> None:
    """lfm: carrier ± B/2; hfm: the band of width B whose geometric centre is the carrier."""
    lfm = waveform_by_name("lfm", carrier_hz=50e3, chirp_bandwidth_hz=20e3, chirp_duration_s=1e-3)
    hfm = waveform_by_name("hfm", carrier_hz=50e3, chirp_bandwidth_hz=20e3, chirp_duration_s=1e-3)
    assert len(lfm.samples) == len(hfm.samples) == 200
    assert lfm.carrier_hz == pytest.approx(50e3)
    assert hfm.carrier_hz == pytest.approx(50e3)
    expected = chirp_waveform(40e3, 60e3, 1e-3, 200e3)
    assert np.array_equal(lfm.samples, expected.samples)
    f0 = math.sqrt(50e3**2 + 10e3**2) - 10e3
    assert np.allclose(hfm.samples, chirp_waveform(f0, f0 + 20e3, 1e-3, 200e3, method="hyperbolic").samples)
    tone = waveform_by_name("tone8", carrier_hz=40e3, sample_rate_hz=400e3)
    assert (tone.name, len(tone.samples)) == ("tone8", 80)


@pytest.mark.parametrize("name", ["chirp", "", "barker", "golay", "mls", "barker13c", "kasami6:", "gold7"])
def test_unknown_names_raise_listing_the_accepted_forms(name: str) -> None:
    with pytest.raises(WaveformError, match="accepted forms") as info:
        waveform_by_name(name)
    for form in WAVEFORM_NAMES:
        assert form in str(info.value)


@pytest.mark.parametrize(
    ("name", "match"),
    [
        ("barker6", "Barker"),
        ("barker13b", "variant"),
        ("golay12a", "Golay"),
        ("mls1", "MLS"),
        ("mls40", "MLS"),
        ("kasami5", "Kasami"),
        ("kasami6:8", "members 0..7"),
    ],
)
def test_well_formed_names_with_bad_parameters_raise(name: str, match: str) -> None:
    with pytest.raises(WaveformError, match=match):
        waveform_by_name(name)


@pytest.mark.parametrize("name", ["lfm", "hfm", "polaroid", "tone16"])
def test_pulses_that_are_not_codes_have_no_code(name: str) -> None:
    waveform_by_name(name)
    with pytest.raises(WaveformError, match="not a binary code"):
        code_by_name(name)


# ----------------------------------------------------------------------------- code metrics

BARKER_MERIT_FACTORS = {2: 2.0, 3: 4.5, 4: 4.0, 5: 6.25, 7: 8.17, 11: 12.1, 13: 14.08}


@pytest.mark.parametrize(("length", "merit"), BARKER_MERIT_FACTORS.items())
def test_barker_code_metrics_match_published_merit_factors(length: int, merit: float) -> None:
    """Barker codes: PSL 1, PSLR = N, the published merit factors, ISL = -10 log10 F."""
    m = code_metrics(barker(length))
    assert (m.length, m.psl) == (length, 1)
    assert m.pslr_ratio == length
    assert m.pslr_db == pytest.approx(20 * math.log10(length))
    assert m.merit_factor == pytest.approx(merit, abs=0.005)
    assert m.isl_db == pytest.approx(-10 * math.log10(merit), abs=0.01)


def test_barker13_code_figures() -> None:
    """Barker-13: PSLR 22.3 dB, F = 169/12 = 14.08, ISL = -11.49 dB."""
    m = code_metrics(barker(13))
    assert m.pslr_db == pytest.approx(22.3, abs=0.05)
    assert m.merit_factor == pytest.approx(169 / 12)
    assert m.isl_db == pytest.approx(-11.49, abs=0.005)


def test_golay_halves_have_equal_sidelobe_figures() -> None:
    """r_a[k] = -r_b[k] off the peak (the sidelobes cancel), so both halves have the same PSL
    and merit factor; a one-bit code has no sidelobe at all."""
    for length in (8, 64, 512):
        a, b = golay_pair(length)
        ma, mb = code_metrics(a), code_metrics(b)
        assert ma.psl == mb.psl
        assert ma.merit_factor == pytest.approx(mb.merit_factor, rel=1e-12)
    single = code_metrics([1])
    assert (single.psl, single.pslr_ratio, single.merit_factor) == (0, math.inf, math.inf)


def test_code_metrics_rejects_non_binary_codes() -> None:
    with pytest.raises(WaveformError):
        code_metrics([1, 0, -1])


# ----------------------------------------------------------------------------- waveform metrics


@pytest.mark.parametrize(
    ("carrier", "cycles", "fs"),
    [("sine", 4, 200e3), ("square", 4, 200e3), ("sine", 2, 1e6), ("sine", 8, 1e6)],
)
def test_barker13_envelope_pslr_is_13(carrier: str, cycles: int, fs: float) -> None:
    """Report ch. 3.4: PSLR 13 = 22.3 dB. The envelope is |R_c(tau)| of the rectangular-chip
    code, linear between the code's r_k (13, 0, 1, 0, 1, ...): largest sidelobe 1 chip.
    ISLR: segments from a to b over a chip integrate to T(a² + ab + b²)/3 with ab = 0 here,
    so sidelobe/main-lobe energy = 12/169: -11.49 dB, the code's ISL."""
    w = barker_waveform(13, cycles_per_bit=cycles, sample_rate_hz=fs, carrier=carrier)  # type: ignore[arg-type]
    m = waveform_metrics(w)
    assert m.pslr_ratio == pytest.approx(13, rel=0.05)
    assert m.pslr_db == pytest.approx(22.3, abs=0.45)
    assert m.islr_db == pytest.approx(-11.49, abs=0.3)
    assert m.peak_lag_s == pytest.approx(0.0, abs=1e-9)
    assert m.duration_s == pytest.approx(13 * cycles / 50e3)
    # Main lobe: the triangle of half-width one chip, -3 dB full width 0.586 chip.
    assert m.mainlobe_width_s == pytest.approx(2 * (1 - 1 / math.sqrt(2)) * w.chip_s, rel=0.05)


@pytest.mark.parametrize(("cycles", "fc", "fs"), [(16, 50e3, 200e3), (16, 49.4e3, 1e6), (5, 40e3, 500e3)])
def test_tone_burst_mainlobe_is_0_586_t_and_bandwidth_0_886_over_t(cycles: int, fc: float, fs: float) -> None:
    """Rectangular envelope of duration T: triangular matched-filter envelope of half-width T,
    -3 dB where 1 - |tau|/T = 1/sqrt 2, full width 2T(1 - 1/sqrt 2) = 0.586 T; no sidelobes;
    power spectrum sinc²(f T): half power at |f - fc| = 0.443/T, bandwidth 0.886/T."""
    w = tone_burst(cycles, fc, sample_rate_hz=fs)
    duration = len(w.samples) / fs
    m = waveform_metrics(w, speed_of_sound_m_s=340.0)
    assert m.mainlobe_width_s == pytest.approx(2 * (1 - 1 / math.sqrt(2)) * duration, rel=0.02)
    assert m.range_resolution_m == pytest.approx(340.0 * m.mainlobe_width_s / 2, rel=1e-12)
    assert m.pslr_ratio > 1e3
    assert m.bandwidth_hz == pytest.approx(0.8859 / duration, rel=0.02)
    assert m.time_bandwidth == pytest.approx(m.duration_s * m.bandwidth_hz)


def test_lfm_mainlobe_is_0_886_over_b() -> None:
    """Rectangular LFM, B = 20 kHz, T = 2 ms (BT = 40): envelope ~ |sinc(B tau)|, -3 dB width
    0.886/B = 44.3 us within 10 %; range resolution c w / 2 = 7.6 mm at 343.2 m/s; and the
    first sidelobe of sinc, 13.3 dB down, within 1.5 dB."""
    w = chirp_waveform(40e3, 60e3, 2e-3, 1e6, window="rect")
    m = waveform_metrics(w)
    assert m.mainlobe_width_s == pytest.approx(0.886 / 20e3, rel=0.10)
    assert m.range_resolution_m == pytest.approx(C_20C * 0.886 / 20e3 / 2, rel=0.10)
    assert m.pslr_db == pytest.approx(13.26, abs=1.5)
    wider = waveform_metrics(chirp_waveform(30e3, 70e3, 2e-3, 1e6, window="rect"))
    assert wider.mainlobe_width_s == pytest.approx(m.mainlobe_width_s / 2, rel=0.10)


def test_windowing_a_chirp_trades_sidelobes_for_width() -> None:
    """Hann taper: far lower sidelobes (PSLR above 30 dB) and a wider main lobe than rect."""
    rect = waveform_metrics(chirp_waveform(40e3, 60e3, 2e-3, 1e6, window="rect"))
    hann = waveform_metrics(chirp_waveform(40e3, 60e3, 2e-3, 1e6, window="hann"))
    assert hann.pslr_db > 30 > rect.pslr_db
    assert hann.mainlobe_width_s > 1.5 * rect.mainlobe_width_s


@settings(max_examples=25, deadline=None)
@given(delay=st.integers(min_value=0, max_value=40), gain=st.floats(min_value=1e-2, max_value=1e2))
def test_delta_response_leaves_metrics_unchanged(delay: int, gain: float) -> None:
    """A delayed, scaled delta is an ideal transducer: only the peak lag moves, by the delay."""
    w = barker_waveform()
    plain = waveform_metrics(w)
    response = np.zeros(delay + 1)
    response[delay] = gain
    for template in (None, "received"):
        m = waveform_metrics(w, response=response, template=template)
        assert m.pslr_ratio == pytest.approx(plain.pslr_ratio, rel=1e-6)
        assert m.islr_db == pytest.approx(plain.islr_db, abs=1e-3)
        assert m.mainlobe_width_s == pytest.approx(plain.mainlobe_width_s, rel=1e-6)
        assert m.bandwidth_hz == pytest.approx(plain.bandwidth_hz, rel=1e-6)
        expected_lag = delay / w.sample_rate_hz if template is None else 0.0
        assert m.peak_lag_s == pytest.approx(expected_lag, abs=1e-9)


def test_unit_delta_and_explicit_sent_template_give_identical_metrics() -> None:
    w = barker_waveform()
    plain = waveform_metrics(w)
    assert waveform_metrics(w, response=[1.0]) == plain
    assert waveform_metrics(w, template="sent") == plain
    assert waveform_metrics(w, template=w.samples) == plain


def test_band_pass_transducer_smears_barker13() -> None:
    """A narrow band-pass (Butterworth, 48-52 kHz, narrower than the 12.5 kHz chip rate)
    averages the 2-chip main lobe with its neighbours: with the SENT template the PSLR
    falls well below 13 (the report measured 9), the main lobe widens and the peak is
    delayed (a causal filter)."""
    w = barker_waveform()
    b, a = scipy.signal.butter(2, [48e3, 52e3], btype="bandpass", fs=w.sample_rate_hz)
    response = scipy.signal.lfilter(b, a, np.r_[1.0, np.zeros(999)])
    plain = waveform_metrics(w)
    sent = waveform_metrics(w, response=response)
    assert sent.pslr_ratio < 0.85 * plain.pslr_ratio
    assert sent.mainlobe_width_s > 1.5 * plain.mainlobe_width_s
    assert sent.peak_lag_s > 0.5 / w.sample_rate_hz
    assert sent.duration_s == plain.duration_s
    matched = waveform_metrics(w, response=response, template="received")
    assert matched.peak_lag_s == pytest.approx(0.0, abs=1e-9)  # an autocorrelation peaks at 0


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"response": []}, "response"),
        ({"response": [0.0, 0.0]}, "zero"),
        ({"response": [1.0, np.nan]}, "non-finite"),
        ({"template": "direct"}, "template"),
        ({"speed_of_sound_m_s": 0.0}, "speed"),
        ({"oversample": 0}, "oversample"),
    ],
)
def test_invalid_metric_arguments_raise(kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(WaveformError, match=match):
        waveform_metrics(barker_waveform(), **kwargs)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- cross-correlation


@settings(max_examples=40, deadline=None)
@given(
    a=st.lists(st.sampled_from([-1, 1]), min_size=1, max_size=20),
    b=st.lists(st.sampled_from([-1, 1]), min_size=1, max_size=20),
)
def test_peak_cross_correlation_is_the_largest_sum_over_sqrt_lengths(a: list[int], b: list[int]) -> None:
    """max_k |sum_n a[n] b[n + k]| / sqrt(N_a N_b), by explicit sums over every overlap."""
    sums = [
        abs(sum(a[n] * b[n + k] for n in range(len(a)) if 0 <= n + k < len(b)))
        for k in range(-len(a) + 1, len(b))
    ]
    expected = max(sums) / math.sqrt(len(a) * len(b))
    assert peak_cross_correlation(a, b) == pytest.approx(expected, rel=1e-12)
    assert peak_cross_correlation(a, a) == pytest.approx(1.0, rel=1e-12)


def test_periodic_cross_correlation_of_shifted_mls_is_one_and_of_kasami_pair_is_small() -> None:
    u = mls(8)
    assert peak_cross_correlation(u, np.roll(u, 17), periodic=True) == pytest.approx(1.0)
    assert peak_cross_correlation(u, np.roll(u, 17)) < 1.0  # aperiodically the overlap is partial
    k = kasami_set(8)
    assert peak_cross_correlation(k[3], k[9], periodic=True) <= 17 / 255 + 1e-12


def test_waveform_cross_correlation_uses_the_envelope() -> None:
    """A pulse against a delayed copy: 1 whatever the carrier phase at the delay; sine burst
    against its cosine version (90° apart): still 1, since the envelope ignores phase."""
    w = tone_burst(16, 50e3, sample_rate_hz=1e6)
    delayed = Waveform(np.r_[np.zeros(7), w.samples], w.sample_rate_hz, w.carrier_hz, "late")
    assert peak_cross_correlation(w, delayed) == pytest.approx(1.0, abs=1e-3)
    t = np.arange(len(w.samples)) / w.sample_rate_hz
    cosine = Waveform(np.cos(2 * np.pi * 50e3 * t), w.sample_rate_hz, 50e3, "cos")
    assert peak_cross_correlation(w, cosine) == pytest.approx(1.0, abs=1e-2)
    assert abs(float(np.dot(w.samples, cosine.samples))) < 1e-6 * len(t)  # raw product is ~0


@pytest.mark.parametrize(
    ("a", "b", "periodic"),
    [
        ([1, -1, 1], [1, 1], True),
        (tone_burst(), [1, -1], False),
        (tone_burst(), tone_burst(), True),
        (tone_burst(sample_rate_hz=200e3), tone_burst(sample_rate_hz=400e3), False),
    ],
)
def test_invalid_cross_correlations_raise(a: object, b: object, periodic: bool) -> None:
    with pytest.raises(WaveformError):
        peak_cross_correlation(a, b, periodic=periodic)  # type: ignore[arg-type]
