"""Cramér-Rao bounds on the time of arrival: closed forms, scaling, and an ML estimator that reaches them."""

from __future__ import annotations

import math

import numpy as np
import pytest

from echoloc.errors import EchoLocError
from echoloc.physics.crlb import (
    amplitude_for_snr,
    bandlimited_derivative,
    coherent_tof_bound,
    energy_to_noise_ratio,
    envelope_derivative,
    envelope_noise_sigma,
    envelope_tof_bound,
    peak_amplitude,
    per_sample_snr,
    rms_bandwidth_hz,
    unknown_phase_tof_bound,
)
from echoloc.physics.waveform import barker_waveform
from echoloc.sim.receiver import to_signal_kind

F0_HZ = 50e3
FS_HZ = 1e6


def gaussian_tone(
    width_s: float, sample_rate_hz: float = FS_HZ, delay_s: float = 0.0, span: float = 8.0
) -> tuple[np.ndarray, np.ndarray]:
    """``exp(-t²/(2w²)) cos(2π f0 t)`` and its exact derivative, at ``n/fs - delay`` over ±span w."""
    half = math.ceil(span * width_s * sample_rate_hz)
    t = np.arange(-half, half + 1) / sample_rate_hz - delay_s
    g = np.exp(-(t**2) / (2 * width_s**2))
    w0 = 2 * np.pi * F0_HZ
    s = g * np.cos(w0 * t)
    ds = -t / width_s**2 * s - w0 * g * np.sin(w0 * t)
    return s, ds


def closed_form_derivative_energy(width_s: float, sample_rate_hz: float = FS_HZ) -> float:
    """``fs ∫ ṡ² dt = fs (√π w / 2) (1/(2w²) + (2π f0)²)`` for f0 w >> 1.

    ``ṡ = ġ cos - ω0 g sin`` with ``g = exp(-t²/2w²)``: ``∫ g² = √π w``, ``∫ ġ² = √π / (2w)``;
    the ``cos²``, ``sin²`` average to 1/2 and the cross term ``∫ g ġ sin(2ω0 t)`` is
    ``-ω0 √π w exp(-ω0² w²)``, negligible. A band-limited sum is ``fs`` times the integral.
    """
    w0 = 2 * np.pi * F0_HZ
    return sample_rate_hz * (math.sqrt(math.pi) * width_s / 2) * (1 / (2 * width_s**2) + w0**2)


def test_derivative_energy_of_gaussian_tone_matches_closed_form() -> None:
    width = 100e-6
    s, ds_exact = gaussian_tone(width)
    ds = bandlimited_derivative(s, FS_HZ)
    expected = closed_form_derivative_energy(width)
    assert float(np.sum(ds**2)) == pytest.approx(expected, rel=1e-6)
    assert float(np.sum(ds_exact**2)) == pytest.approx(expected, rel=1e-6)
    np.testing.assert_allclose(ds[: len(s)], ds_exact, atol=1e-6 * np.abs(ds_exact).max())


def test_derivative_energy_does_not_depend_on_the_sub_sample_delay() -> None:
    width = 40e-6
    sums = [float(np.sum(gaussian_tone(width, delay_s=d / FS_HZ)[1] ** 2)) for d in (0.0, 0.13, 0.5, 0.77)]
    np.testing.assert_allclose(sums, sums[0], rtol=1e-9)


@pytest.mark.parametrize("width", [40e-6, 100e-6])
def test_coherent_bound_is_the_closed_form_and_decouples_the_amplitude(width: float) -> None:
    s, _ = gaussian_tone(width)
    bound = coherent_tof_bound(s, FS_HZ, amplitude=2.0, noise_sigma=0.1)
    expected = 0.1 / (2.0 * math.sqrt(closed_form_derivative_energy(width)))
    assert bound.std_s == pytest.approx(expected, rel=1e-6)
    f = bound.fisher
    assert abs(f[0, 1]) < 1e-9 * math.sqrt(f[0, 0] * f[1, 1])
    assert bound.known_nuisance_std_s == pytest.approx(bound.std_s, rel=1e-12)
    assert bound.parameters == ("tof_s", "amplitude")


def test_bound_scales_as_sigma_over_amplitude() -> None:
    s, _ = gaussian_tone(40e-6)
    reference = coherent_tof_bound(s, FS_HZ, amplitude=1.0, noise_sigma=1.0).std_s
    for amplitude, sigma in [(2.0, 1.0), (1.0, 3.0), (0.25, 0.5), (10.0, 0.01)]:
        for bound in (coherent_tof_bound, unknown_phase_tof_bound):
            ratio = (
                bound(s, FS_HZ, amplitude=amplitude, noise_sigma=sigma).std_s
                / bound(s, FS_HZ, amplitude=1.0, noise_sigma=1.0).std_s
            )
            assert ratio == pytest.approx(sigma / amplitude, rel=1e-9)
    assert coherent_tof_bound(s, FS_HZ, amplitude=-1.0, noise_sigma=1.0).std_s == pytest.approx(reference)


def test_general_two_parameter_case_when_delay_and_amplitude_couple() -> None:
    """An envelope that starts abruptly, ``(1 + t/T2) exp(-t/T)`` from t = 0: Σ e ė ≈ -fs e(0)²/2 ≠ 0."""
    rate, decay, rise = 20e3, 0.5e-3, 0.2e-3
    t = np.arange(60) / rate
    e = (1 + t / rise) * np.exp(-t / decay)
    de = (1 / rise - (1 + t / rise) / decay) * np.exp(-t / decay)
    bound = envelope_tof_bound(e, rate, amplitude=1.5, noise_sigma=0.05, derivative=de)
    a, sigma = 1.5, 0.05
    f_tt = a**2 * np.sum(de**2) / sigma**2
    f_aa = np.sum(e**2) / sigma**2
    f_ta = -a * np.sum(e * de) / sigma**2
    assert bound.std_s == pytest.approx(math.sqrt(f_aa / (f_tt * f_aa - f_ta**2)), rel=1e-12)
    assert bound.std_s > 1.02 * bound.known_nuisance_std_s  # the unknown amplitude costs here
    # A pure exponential delayed is the same exponential scaled: the delay is not identifiable.
    with pytest.raises(EchoLocError, match="not identifiable"):
        envelope_tof_bound(
            np.exp(-t / decay), rate, amplitude=1.0, noise_sigma=0.05, derivative=-np.exp(-t / decay) / decay
        )


@pytest.mark.parametrize(
    ("amplitude", "message"),
    [(math.inf, "not finite"), (math.nan, "not finite"), (1e300, "not finite"), (0.0, "not identifiable")],
)
def test_an_amplitude_without_a_bound_is_one_clear_error(amplitude: float, message: str) -> None:
    """An infinite or NaN amplitude, or one whose square overflows the Fisher matrix, is said to
    be out of range; a zero amplitude leaves the delay unidentifiable. Never numpy's own error."""
    s = np.sin(np.arange(64) / 3) * np.hanning(64)
    with pytest.raises(EchoLocError, match=message):
        coherent_tof_bound(s, FS_HZ, amplitude=amplitude, noise_sigma=0.1)


def test_unknown_phase_bound_is_the_envelope_rms_bandwidth_formula() -> None:
    """Gaussian tone: the envelope's rms angular bandwidth is 1/(√2 w), so var = 2 w² σ² / (A² Σ s²)."""
    width, amplitude, sigma = 40e-6, 1.0, 0.2
    s, _ = gaussian_tone(width)
    bound = unknown_phase_tof_bound(s, FS_HZ, amplitude=amplitude, noise_sigma=sigma)
    energy = FS_HZ * math.sqrt(math.pi) * width / 2  # Σ s² for f0 w >> 1
    assert bound.std_s == pytest.approx(
        math.sqrt(2) * width * sigma / (amplitude * math.sqrt(energy)), rel=1e-6
    )
    b_c = rms_bandwidth_hz(s, FS_HZ, about="centroid")
    assert 2 * np.pi * b_c == pytest.approx(1 / (math.sqrt(2) * width), rel=1e-6)
    e_n0 = energy_to_noise_ratio(s, amplitude, sigma)
    assert bound.std_s == pytest.approx(1 / math.sqrt(2 * e_n0 * (2 * np.pi * b_c) ** 2), rel=1e-9)
    # The carrier is worth (f0² + B_c²) / B_c² in variance.
    coherent = coherent_tof_bound(s, FS_HZ, amplitude=amplitude, noise_sigma=sigma)
    assert (bound.std_s / coherent.std_s) ** 2 == pytest.approx((F0_HZ**2 + b_c**2) / b_c**2, rel=1e-6)


def test_bounds_equal_the_bandwidth_formulas_for_the_report_pulse() -> None:
    pulse = barker_waveform(13, carrier_hz=50e3, cycles_per_bit=4, sample_rate_hz=200e3).samples
    fs, amplitude, sigma = 200e3, 0.7, 0.05
    e_n0 = energy_to_noise_ratio(pulse, amplitude, sigma)
    coherent = coherent_tof_bound(pulse, fs, amplitude=amplitude, noise_sigma=sigma)
    beta = 2 * np.pi * rms_bandwidth_hz(pulse, fs)
    assert coherent.std_s == pytest.approx(1 / math.sqrt(2 * e_n0 * beta**2), rel=1e-9)
    incoherent = unknown_phase_tof_bound(pulse, fs, amplitude=amplitude, noise_sigma=sigma)
    b_c = 2 * np.pi * rms_bandwidth_hz(pulse, fs, about="centroid")
    assert incoherent.std_s == pytest.approx(1 / math.sqrt(2 * e_n0 * b_c**2), rel=1e-9)
    assert incoherent.std_s > 3 * coherent.std_s


def test_complex_envelope_with_unknown_phase_matches_the_real_pulse() -> None:
    """The same echo as rf at 1 MHz or as complex baseband at 100 kHz (σ² f_iq/fs·2 per quadrature)."""
    width, amplitude, sigma = 40e-6, 1.0, 0.2
    s, _ = gaussian_tone(width)
    rf_bound = unknown_phase_tof_bound(s, FS_HZ, amplitude=amplitude, noise_sigma=sigma)
    rate = 100e3
    t = np.arange(-40, 41) / rate
    u = np.exp(-(t**2) / (2 * width**2)) * np.exp(0.3j)
    sigma_q = envelope_noise_sigma(sigma, FS_HZ, rate)
    iq_bound = unknown_phase_tof_bound(u, rate, amplitude=amplitude, noise_sigma=sigma_q)
    assert iq_bound.std_s == pytest.approx(rf_bound.std_s, rel=1e-6)
    assert iq_bound.parameters == ("tof_s", "amplitude", "phase_rad")


def test_envelope_bound_of_an_unmodulated_pulse_equals_the_unknown_phase_bound() -> None:
    """A Gaussian envelope at 20 kHz, analytic derivative: nothing is lost by dropping the phase."""
    width, amplitude, sigma = 100e-6, 1.0, 0.2
    s, _ = gaussian_tone(width)
    rf_bound = unknown_phase_tof_bound(s, FS_HZ, amplitude=amplitude, noise_sigma=sigma)
    rate = 20e3
    t = np.arange(-30, 31) / rate
    e = np.exp(-(t**2) / (2 * width**2))
    de = -t / width**2 * e
    sigma_e = envelope_noise_sigma(sigma, FS_HZ, rate)
    analytic = envelope_tof_bound(e, rate, amplitude=amplitude, noise_sigma=sigma_e, derivative=de)
    bandlimited = envelope_tof_bound(e, rate, amplitude=amplitude, noise_sigma=sigma_e)
    assert analytic.std_s == pytest.approx(rf_bound.std_s, rel=1e-6)
    assert bandlimited.std_s == pytest.approx(rf_bound.std_s, rel=1e-6)


def test_envelope_derivative_of_a_complex_envelope() -> None:
    width, rate = 100e-6, 20e3
    t = np.arange(-30, 31) / rate
    g = np.exp(-(t**2) / (2 * width**2))
    derivative = envelope_derivative(g * np.exp(-1.1j), rate)
    np.testing.assert_allclose(derivative, -t / width**2 * g, atol=1e-6 / width)


def test_envelope_noise_sigma_matches_the_receiver_chain() -> None:
    """White rf noise demodulated and decimated to 20 kHz by the simulator's own receiver code."""
    sigma, fs, out = 0.3, 200e3, 20e3
    rng = np.random.default_rng(7)
    iq = to_signal_kind(
        rng.normal(0, sigma, (40, 20000)), "iq", sample_rate_hz=fs, carrier_hz=50e3, output_rate_hz=out
    )
    inner = iq[:, 50:-50]  # away from the frame edges
    per_quadrature = math.sqrt(float(np.mean(np.abs(inner) ** 2)) / 2)
    assert per_quadrature == pytest.approx(envelope_noise_sigma(sigma, fs, out), rel=0.05)


def test_snr_conventions() -> None:
    width, fs = 40e-6, 200e3
    # A quarter-cycle delay puts the samples off the carrier's crest: the sample peak is below 1.
    s, _ = gaussian_tone(width, fs, delay_s=0.5 / fs)
    assert np.max(np.abs(s)) < 0.8
    assert peak_amplitude(s) == pytest.approx(1.0, rel=1e-3)
    amplitude = amplitude_for_snr(s, 13.0, 0.05)
    assert amplitude == pytest.approx(0.65, rel=1e-3)
    assert per_sample_snr(s, amplitude, 0.05) == pytest.approx(13.0)
    # E/N0 = A² Σ s² / (2σ²) with Σ s² = fs √π w / 2.
    energy = fs * math.sqrt(math.pi) * width / 2
    assert energy_to_noise_ratio(s, amplitude, 0.05) == pytest.approx(
        amplitude**2 * energy / (2 * 0.05**2), rel=1e-6
    )
    e = np.exp(-((np.arange(-8, 9) / 20e3) ** 2) / (2 * (100e-6) ** 2))
    assert peak_amplitude(e, "envelope") == pytest.approx(1.0)
    bound = coherent_tof_bound(s, fs, amplitude=amplitude, noise_sigma=0.05)
    assert bound.path_std_m(343.0) == pytest.approx(343.0 * bound.std_s)
    assert bound.range_std_m(343.0) == pytest.approx(0.5 * 343.0 * bound.std_s)


def test_bad_input_is_refused() -> None:
    with pytest.raises(EchoLocError, match="not all zeros"):
        coherent_tof_bound(np.zeros(10), FS_HZ, amplitude=1.0, noise_sigma=1.0)
    with pytest.raises(EchoLocError, match="noise_sigma"):
        coherent_tof_bound(np.ones(10), FS_HZ, amplitude=1.0, noise_sigma=0.0)
    with pytest.raises(EchoLocError, match="derivative"):
        envelope_tof_bound(np.ones(10), 20e3, amplitude=1.0, noise_sigma=1.0, derivative=np.ones(9))
    with pytest.raises(EchoLocError, match="signal_kind"):
        peak_amplitude(np.ones(10), "audio")  # type: ignore[arg-type]


def test_ml_delay_estimator_reaches_the_coherent_bound() -> None:
    """Monte Carlo: the peak of the cross-correlation on a fine grid of delays, clean Gaussian tone.

    The ML estimate of (τ, A > 0) maximises ``Σ x[n] s(nT - τ)`` (``Σ s²`` does not depend
    on τ). A coarse grid over ±12 µs (more than half a carrier period either side) finds
    the peak; a 0.5-ns grid over ±200 ns around it refines. At per-sample SNR 20 the estimator must be
    efficient: its standard deviation within 15 % of the bound, its bias well inside it.
    """
    width, snr, trials = 40e-6, 20.0, 2000
    rng = np.random.default_rng(2026)
    half = math.ceil(8 * width * FS_HZ)
    n = np.arange(-half, half + 1) / FS_HZ
    true_delay = 0.37 / FS_HZ

    def template(delays: np.ndarray) -> np.ndarray:
        t = n[None, :] - delays[:, None]
        return np.exp(-(t**2) / (2 * width**2)) * np.cos(2 * np.pi * F0_HZ * t)

    clean = template(np.array([true_delay]))[0]
    sigma = 1.0 / snr
    frames = clean[None, :] + rng.normal(0.0, sigma, (trials, len(n)))
    coarse = true_delay + np.arange(-12e-6, 12e-6 + 1e-12, 0.1e-6)
    best = coarse[np.argmax(frames @ template(coarse).T, axis=1)]
    # One 0.5-ns grid covers every trial's ±200 ns around its coarse peak.
    fine = np.arange(best.min() - 200e-9, best.max() + 200e-9, 0.5e-9)
    scores = frames @ template(fine).T
    scores[np.abs(fine[None, :] - best[:, None]) > 200e-9] = -np.inf
    estimates = fine[np.argmax(scores, axis=1)]
    errors = estimates - true_delay
    bound = coherent_tof_bound(clean, FS_HZ, amplitude=1.0, noise_sigma=sigma).std_s
    assert np.max(np.abs(errors)) < 10 * bound  # no carrier-cycle slips at this SNR
    assert float(np.std(errors)) / bound == pytest.approx(1.0, abs=0.15)
    assert abs(float(np.mean(errors))) < 0.2 * bound
