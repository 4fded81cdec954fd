"""Tests of echoloc.sim.receiver: TVG, ADC, receiver noise, resampling, iq and envelope.

Sources: Bennett, Bell Syst. Tech. J. 27 (1948) (quantisation noise q²/12 for a busy
signal); Oppenheim & Schafer, Discrete-Time Signal Processing §2.10 (filtered white
noise: variance σ² Σh², spectrum σ² |H|²); the noise bandwidth of a single-tuned
resonator is π/2 times its -3 dB bandwidth; Crochiere & Rabiner (polyphase
resampling); Gabor 1946 (analytic signal); the report, ch. 4 (5 MHz decimated by 25
to 200 kHz) and appendix B (Polaroid 6500 stepped receiver gain).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from scipy.optimize import minimize_scalar

from echoloc.errors import SceneError
from echoloc.physics.transducer import PRESETS, apply_response, frequency_response
from echoloc.physics.waveform import barker_waveform
from echoloc.sim.receiver import (
    MAX_DENOMINATOR,
    SIGNAL_KINDS,
    TEMPLATE_FLOOR,
    AdcSpec,
    GainSpec,
    SignalKind,
    analytic_signal,
    band_limited_noise,
    gain_curve,
    gain_db_curve,
    noise_power_gain,
    output_samples,
    quantisation_noise_power,
    quantise,
    rate_ratio,
    resample,
    template_for_kind,
    to_signal_kind,
    white_noise,
)

FS = 200e3
SAMPLED_PRESETS = sorted(n for n, t in PRESETS.items() if t.centre_frequency_hz < FS / 2)
"""The presets these tests can sample at FS (the CH101's 175 kHz needs more than 350 kHz)."""
FC = 50e3
_RATES = {"sample_rate_hz": FS, "carrier_hz": FC, "output_rate_hz": FS}


def returned_pulse() -> NDArray[np.float64]:
    """The report's Barker-13 x 4 cycles at 50 kHz through the electrostatic pair, with its ringing."""
    code = barker_waveform(13, carrier_hz=FC, cycles_per_bit=4, sample_rate_hz=FS).samples
    return apply_response(np.r_[code, np.zeros(300)], PRESETS["electrostatic50"], FS)


def gaussian_burst(
    t_s: NDArray[np.float64], delay_s: float, sigma_s: float, carrier_hz: float, phase: float = 0.0
) -> NDArray[np.float64]:
    return np.exp(-0.5 * ((t_s - delay_s) / sigma_s) ** 2) * np.cos(
        2 * np.pi * carrier_hz * (t_s - delay_s) + phase
    )


# ------------------------------------------------------------------------------ ADC


def test_quantisation_noise_of_a_busy_signal_is_q_squared_over_12() -> None:
    """Bennett 1948: uniform input over many steps, error uniform in ±q/2, power q²/12."""
    spec = AdcSpec(bits=12, full_scale=2.5)
    q = 2 * 2.5 / 2**12
    assert quantisation_noise_power(spec) == pytest.approx(q * q / 12, rel=1e-15)
    x = np.random.default_rng(3).uniform(-0.9 * 2.5, 0.9 * 2.5, 200_000)
    error = quantise(x, spec) - x
    assert np.mean(error**2) == pytest.approx(q * q / 12, rel=0.03)
    assert abs(np.mean(error)) < 0.01 * q
    assert np.max(np.abs(error)) <= q / 2 * (1 + 1e-12)


@settings(max_examples=60, deadline=None)
@given(
    bits=st.integers(1, 24),
    full_scale=st.floats(1e-3, 1e3),
    values=st.lists(st.floats(-1e4, 1e4), min_size=1, max_size=50),
)
def test_quantised_values_lie_on_the_grid(bits: int, full_scale: float, values: list[float]) -> None:
    spec = AdcSpec(bits=bits, full_scale=full_scale)
    q = spec.step
    x = np.array(values)
    y = quantise(x, spec)
    assert y.dtype == np.float64
    codes = np.round(y / q)
    np.testing.assert_allclose(y / q, codes, rtol=0, atol=1e-6)
    assert np.all(codes >= -(2 ** (bits - 1)))
    assert np.all(codes <= 2 ** (bits - 1) - 1)
    np.testing.assert_array_equal(quantise(y, spec), y)  # idempotent
    inside = np.abs(x) <= full_scale - q
    assert np.all(np.abs(y - x)[inside] <= q / 2 * (1 + 1e-9))


def test_quantise_clips_at_full_scale() -> None:
    x = np.array([-10.0, -1.0, -0.3, 0.0, 0.3, 1.0, 10.0])
    np.testing.assert_array_equal(quantise(x, AdcSpec(None, 1.0)), [-1.0, -1.0, -0.3, 0.0, 0.3, 1.0, 1.0])
    spec = AdcSpec(bits=8, full_scale=1.0)
    y = quantise(x, spec)
    q = 2 / 256
    assert y[0] == y[1] == -1.0  # the most negative code is -full_scale
    assert y[-1] == y[-2] == 1.0 - q  # the most positive of 2**bits two's-complement codes
    assert y[3] == 0.0  # mid-tread: 0 is a level
    assert quantisation_noise_power(AdcSpec()) == 0.0


def test_quantise_complex_quantises_i_and_q_each() -> None:
    spec = AdcSpec(bits=6, full_scale=1.0)
    z = np.array([0.31 - 0.77j, 2.0 + 0.0j, -0.004 + 5j])
    y = quantise(z, spec)
    assert y.dtype == np.complex128
    np.testing.assert_array_equal(y.real, quantise(z.real, spec))
    np.testing.assert_array_equal(y.imag, quantise(z.imag, spec))


# ----------------------------------------------------------------------------- gain


def test_no_gain_is_flat_at_gain_db() -> None:
    g = gain_curve(GainSpec(gain_db=12.0), 1000, FS)
    assert g.shape == (1000,)
    np.testing.assert_allclose(g, 10 ** (12 / 20), rtol=1e-15)
    assert gain_curve(GainSpec(), 0, FS).shape == (0,)


def test_continuous_gain_grows_linearly_in_db() -> None:
    spec = GainSpec(kind="continuous", gain_db=-6.0, slope_db_per_ms=4.0, max_gain_db=60.0)
    g = gain_curve(spec, 2000, FS)
    k = round(2.5e-3 * FS)  # 2.5 ms: -6 + 4 * 2.5 = +4 dB
    assert 20 * math.log10(g[k]) == pytest.approx(4.0, abs=1e-12)
    assert g[0] == pytest.approx(10 ** (-6 / 20), rel=1e-15)
    np.testing.assert_allclose(np.diff(gain_db_curve(spec, 2000, FS)), 4.0 * 1e3 / FS, rtol=1e-9)


@settings(max_examples=30, deadline=None)
@given(samples_per_step=st.integers(1, 400), fs=st.sampled_from([20e3, 44.1e3, 200e3, 5e6]))
def test_stepped_gain_changes_exactly_at_multiples_of_step_s(samples_per_step: int, fs: float) -> None:
    spec = GainSpec(kind="stepped", gain_db=3.0, step_db=6.0, step_s=samples_per_step / fs, max_gain_db=1e3)
    g_db = gain_db_curve(spec, 10 * samples_per_step + 1, fs)
    changes = np.flatnonzero(np.diff(g_db)) + 1
    np.testing.assert_array_equal(changes, samples_per_step * np.arange(1, 11))
    np.testing.assert_allclose(g_db[changes], 3.0 + 6.0 * np.arange(1, 11), rtol=1e-15)


def test_stepped_gain_between_samples_takes_effect_at_the_next_sample() -> None:
    # 12.5 samples per step: the steps fall at samples 12.5, 25, 37.5, 50
    spec = GainSpec(kind="stepped", step_db=2.0, step_s=125e-6)
    changes = np.flatnonzero(np.diff(gain_db_curve(spec, 51, 100e3))) + 1
    np.testing.assert_array_equal(changes, [13, 25, 38, 50])


@pytest.mark.parametrize(
    "spec",
    [
        GainSpec(kind="continuous", gain_db=0.0, slope_db_per_ms=10.0, max_gain_db=25.0),
        GainSpec(kind="stepped", gain_db=0.0, step_db=6.0, step_s=1e-3, max_gain_db=25.0),
    ],
)
def test_gain_saturates_at_max_gain_db(spec: GainSpec) -> None:
    g_db = gain_db_curve(spec, 2000, FS)  # 10 ms
    assert g_db.max() == 25.0
    assert np.all(np.diff(g_db) >= 0)
    first = int(np.argmax(g_db == 25.0))
    # continuous: 25 dB at 2.5 ms; stepped: 24 dB at 4 ms, capped 30 dB from 5 ms on
    expected_s = 2.5e-3 if spec.kind == "continuous" else 5e-3
    assert first == round(expected_s * FS)
    assert gain_curve(spec, 2000, FS).max() == pytest.approx(10 ** (25 / 20), rel=1e-15)


# ---------------------------------------------------------------------------- noise


def test_white_noise_mean_and_std() -> None:
    x = white_noise((8, 50_000), 0.25, np.random.default_rng(7))
    assert x.shape == (8, 50_000)
    assert x.dtype == np.float64
    assert x.std() == pytest.approx(0.25, rel=0.01)
    assert abs(x.mean()) < 0.25 * 5 / math.sqrt(x.size)
    assert white_noise(5, 0.0, np.random.default_rng(0)).tolist() == [0.0] * 5


@pytest.mark.parametrize("name", SAMPLED_PRESETS)
def test_band_limited_noise_has_std_sigma_from_the_first_sample(name: str) -> None:
    transducer = PRESETS[name]
    x = band_limited_noise((2000, 512), 0.3, np.random.default_rng(11), transducer, FS)
    assert x.shape == (2000, 512)
    assert x.std() == pytest.approx(0.3, rel=0.03)
    # No start-up transient: the first samples, across draws, are as loud as the last.
    assert x[:, 0].std() == pytest.approx(0.3, rel=0.06)
    assert x[:, :5].std() == pytest.approx(x[:, -5:].std(), rel=0.06)


@pytest.mark.parametrize("name", SAMPLED_PRESETS)
def test_band_limited_noise_spectrum_follows_the_transducer(name: str) -> None:
    transducer = PRESETS[name]
    sigma = 0.5
    x = band_limited_noise((64, 16384), sigma, np.random.default_rng(5), transducer, FS)
    f, psd = scipy.signal.welch(x, fs=FS, nperseg=1024, axis=-1)
    psd = psd.mean(axis=0)
    h2 = np.abs(frequency_response(transducer, f, sample_rate_hz=FS)) ** 2
    expected = 2 / FS * sigma**2 * h2 / noise_power_gain(transducer, FS)  # one-sided PSD, OS §2.10
    df = f[1] - f[0]
    assert psd.sum() * df == pytest.approx(sigma**2, rel=0.03)
    # The shape: 3.1 kHz bands where |H|² is at least 1 % of its peak follow it within 5 %.
    groups = slice(0, len(f) - 1)
    measured = psd[groups].reshape(-1, 16).sum(axis=1)
    theory = expected[groups].reshape(-1, 16).sum(axis=1)
    strong = h2[groups].reshape(-1, 16).max(axis=1) > 0.01
    np.testing.assert_allclose(measured[strong], theory[strong], rtol=0.05)
    # Most power inside the band, and in-band/out-of-band as |H|² says.
    q = transducer.quality_factor
    f0 = transducer.centre_frequency_hz
    lo, hi = (
        f0 * (math.sqrt(1 + 1 / (4 * q * q)) - 1 / (2 * q)),
        f0 * (math.sqrt(1 + 1 / (4 * q * q)) + 1 / (2 * q)),
    )
    band = (f >= lo) & (f <= hi)
    inside = psd[band].sum() / psd[~band].sum()
    assert inside == pytest.approx(expected[band].sum() / expected[~band].sum(), rel=0.05)
    wide = (f >= f0 - 2 * transducer.bandwidth_hz) & (f <= f0 + 2 * transducer.bandwidth_hz)
    assert psd[wide].sum() > 0.7 * psd.sum()
    far = (f < 0.2 * f0) | (f > 1.8 * f0)
    assert psd[far].mean() < 0.02 * psd[band].mean()


@pytest.mark.parametrize("name", SAMPLED_PRESETS)
def test_noise_power_gain_is_the_mean_of_h_squared_and_pi_over_2_b(name: str) -> None:
    transducer = PRESETS[name]
    f = np.linspace(0, FS, 400_001)
    h2 = np.abs(frequency_response(transducer, f, sample_rate_hz=FS)) ** 2
    assert noise_power_gain(transducer, FS) == pytest.approx(np.trapezoid(h2, f) / FS, rel=1e-6)
    fast = 20e6  # far above the band the digital resonator is the analog one: (π/2) B
    bandwidth = noise_power_gain(transducer, fast) * fast / 2
    assert bandwidth == pytest.approx(math.pi / 2 * transducer.bandwidth_hz, rel=0.005)


# ----------------------------------------------------------------------- resampling


def fitted_delay_and_amplitude(
    y: NDArray[np.float64], rate_hz: float, guess_s: float, sigma_s: float, carrier_hz: float
) -> tuple[float, float]:
    """Least-squares delay (s) and amplitude of a Gaussian burst in y."""
    t = np.arange(len(y)) / rate_hz

    def misfit(delay: float) -> float:
        g = gaussian_burst(t, delay, sigma_s, carrier_hz)
        return float(np.sum((y - (g @ y) / (g @ g) * g) ** 2))

    best = minimize_scalar(
        misfit,
        bounds=(guess_s - 0.6 / rate_hz, guess_s + 0.6 / rate_hz),
        method="bounded",
        options={"xatol": 1e-5 / rate_hz},
    )
    g = gaussian_burst(t, best.x, sigma_s, carrier_hz)
    return float(best.x), float((g @ y) / (g @ g))


@settings(max_examples=8, deadline=None)
@given(fraction=st.floats(0.0, 1.0))
def test_decimation_5mhz_to_200khz_keeps_arrival_time_and_amplitude(fraction: float) -> None:
    """The report's ch. 4 decimation by 25; the delay is a fraction of an output sample."""
    fin, fout = 5e6, 200e3
    delay = 1.3e-3 + fraction / fout
    x = 0.8 * gaussian_burst(np.arange(round(3e-3 * fin)) / fin, delay, 60e-6, FC)
    y = resample(x, fin, fout)
    assert len(y) == output_samples(len(x), fin, fout) == 600
    found, amplitude = fitted_delay_and_amplitude(y, fout, delay, 60e-6, FC)
    assert abs(found - delay) * fout < 0.01
    assert amplitude == pytest.approx(0.8, rel=0.01)


@settings(max_examples=8, deadline=None)
@given(fraction=st.floats(0.0, 1.0))
def test_decimation_200khz_to_20khz_keeps_arrival_time_and_amplitude(fraction: float) -> None:
    fin, fout = 200e3, 20e3
    delay = 2.1e-3 + fraction / fout
    x = gaussian_burst(np.arange(1000) / fin, delay, 300e-6, 3e3)
    y = resample(x, fin, fout)
    found, amplitude = fitted_delay_and_amplitude(y, fout, delay, 300e-6, 3e3)
    assert abs(found - delay) * fout < 0.01
    assert amplitude == pytest.approx(1.0, rel=0.01)


def test_rate_ratio_and_output_samples() -> None:
    assert rate_ratio(5e6, 200e3) == (1, 25)
    assert rate_ratio(200e3, 20e3) == (1, 10)
    assert rate_ratio(48e3, 44.1e3) == (147, 160)
    assert rate_ratio(200e3, 44.1e3) == (441, 2000)
    assert rate_ratio(200e3, 1e6) == (5, 1)
    for n in (1, 24, 25, 26, 1001):
        assert output_samples(n, 5e6, 200e3) == math.ceil(n / 25) == len(resample(np.ones(n), 5e6, 200e3))
        assert output_samples(n, 48e3, 44.1e3) == math.ceil(n * 147 / 160)
        assert len(resample(np.ones(n), 48e3, 44.1e3)) == output_samples(n, 48e3, 44.1e3)
    with pytest.raises(SceneError, match="to_hz/from_hz"):
        rate_ratio(200e3, 200e3 * math.pi / 3)
    assert MAX_DENOMINATOR >= 2000


def test_resample_works_on_any_axis_and_batch() -> None:
    x = np.random.default_rng(2).standard_normal((3, 4, 500))
    y = resample(x, 200e3, 40e3)
    assert y.shape == (3, 4, 100)
    np.testing.assert_allclose(y[1, 2], resample(x[1, 2], 200e3, 40e3), atol=1e-12)
    z = resample(np.moveaxis(x, -1, 0), 200e3, 40e3, axis=0)
    np.testing.assert_allclose(np.moveaxis(z, 0, -1), y, atol=1e-12)
    np.testing.assert_array_equal(resample(x, 1e5, 1e5), x)


# ------------------------------------------------------------------- iq, envelope


def test_iq_of_a_tone_turns_at_its_offset_from_the_carrier() -> None:
    """A cos(2π (fc + Δf) t + φ) -> A exp(j (2π Δf t + φ)), t from the frame start."""
    n = 4000
    t = np.arange(n) / FS
    amplitude, phase, offset = 0.7, 0.3, 2e3
    rf = amplitude * np.cos(2 * np.pi * (FC + offset) * t + phase)
    out = 20e3
    iq = to_signal_kind(rf, "iq", sample_rate_hz=FS, carrier_hz=FC, output_rate_hz=out)
    assert iq.dtype == np.complex128
    assert len(iq) == 400
    inner = slice(40, -40)
    t_out = np.arange(len(iq)) / out
    np.testing.assert_allclose(np.abs(iq[inner]), amplitude, rtol=0.01)
    slope, intercept = np.polyfit(t_out[inner], np.unwrap(np.angle(iq[inner])), 1)
    assert slope == pytest.approx(2 * np.pi * offset, rel=1e-4)
    assert abs(np.angle(np.exp(1j * (intercept - phase)))) < 0.01  # the phase at t = 0, modulo 2π
    # Below the carrier it turns the other way.
    rf_low = amplitude * np.cos(2 * np.pi * (FC - offset) * t)
    iq_low = to_signal_kind(rf_low, "iq", sample_rate_hz=FS, carrier_hz=FC, output_rate_hz=out)
    slope_low = np.polyfit(t_out[inner], np.unwrap(np.angle(iq_low[inner])), 1)[0]
    assert slope_low == pytest.approx(-2 * np.pi * offset, rel=1e-4)


def test_iq_reconstructs_the_rf_at_the_input_rate() -> None:
    frame = np.zeros(3000)
    pulse = returned_pulse()
    frame[700 : 700 + pulse.size] = pulse
    frame += 0.01 * band_limited_noise(3000, 1.0, np.random.default_rng(1), PRESETS["electrostatic50"], FS)
    iq = to_signal_kind(frame, "iq", sample_rate_hz=FS, carrier_hz=FC, output_rate_hz=FS)
    t = np.arange(3000) / FS
    rebuilt = np.real(iq * np.exp(2j * np.pi * FC * t))
    assert np.max(np.abs(rebuilt - frame)) < 0.01 * np.max(np.abs(frame))
    np.testing.assert_allclose(
        np.imag(analytic_signal(frame))[:5], np.imag(iq * np.exp(2j * np.pi * FC * t))[:5]
    )


@pytest.mark.parametrize("out", [200e3, 40e3, 20e3])
def test_envelope_of_a_gaussian_burst_is_the_gaussian(out: float) -> None:
    t = np.arange(2000) / FS
    sigma = 100e-6
    rf = 1.5 * gaussian_burst(t, 4e-3, sigma, FC, phase=1.0)
    env = to_signal_kind(rf, "envelope", sample_rate_hz=FS, carrier_hz=FC, output_rate_hz=out)
    assert env.dtype == np.float64
    assert np.all(env >= 0)
    t_out = np.arange(len(env)) / out
    expected = 1.5 * np.exp(-0.5 * ((t_out - 4e-3) / sigma) ** 2)
    assert np.max(np.abs(env - expected)) < 0.01 * 1.5


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), out=st.sampled_from([200e3, 100e3, 40e3, 25e3]))
def test_envelope_is_non_negative_and_the_magnitude_of_iq(seed: int, out: float) -> None:
    x = np.random.default_rng(seed).standard_normal((2, 300))
    kwargs = {"sample_rate_hz": FS, "carrier_hz": FC, "output_rate_hz": out}
    env = to_signal_kind(x, "envelope", **kwargs)
    assert np.all(env >= 0)
    np.testing.assert_allclose(env, np.abs(to_signal_kind(x, "iq", **kwargs)), rtol=1e-12, atol=0)


def test_rf_kind_only_resamples() -> None:
    x = np.random.default_rng(4).standard_normal((2, 1000))
    y = to_signal_kind(x, "rf", sample_rate_hz=1e6, carrier_hz=FC, output_rate_hz=FS)
    np.testing.assert_array_equal(y, resample(x, 1e6, FS))
    assert y.dtype == np.float64


# ------------------------------------------------------------------------ templates


@pytest.mark.parametrize(
    ("kind", "out"),
    [(kind, out) for kind in SIGNAL_KINDS for out in (1e6, 200e3, 40e3) if kind != "rf" or out > 2 * FC],
)
def test_template_is_the_kind_of_an_echo_at_time_zero(kind: SignalKind, out: float) -> None:
    pulse = returned_pulse()
    kwargs = {"sample_rate_hz": FS, "carrier_hz": FC, "output_rate_hz": out}
    template = template_for_kind(pulse, kind, **kwargs)
    frame = np.zeros(20 * pulse.size)
    frame[: pulse.size] = pulse
    full = to_signal_kind(frame, kind, **kwargs)
    peak = np.max(np.abs(full))
    assert template.dtype == (np.complex128 if kind == "iq" else np.float64)
    np.testing.assert_allclose(template, full[: len(template)], rtol=0, atol=1e-9 * peak)
    assert np.abs(template[-1]) >= TEMPLATE_FLOOR * peak
    assert np.max(np.abs(full[len(template) :])) < TEMPLATE_FLOOR * peak
    # It is much shorter than the frame: the cut is where the echo has died away.
    assert len(template) < output_samples(2 * pulse.size, FS, out)


@pytest.mark.parametrize(("kind", "out"), [("rf", 1e6), ("envelope", 100e3), ("iq", 100e3), ("iq", 1e6)])
def test_a_delayed_echo_records_as_the_shifted_template(kind: SignalKind, out: float) -> None:
    tau = 74 / FS  # 74 input samples
    delay = round(tau * out)  # a whole number of output samples too
    pulse = returned_pulse()
    kwargs = {"sample_rate_hz": FS, "carrier_hz": FC, "output_rate_hz": out}
    template = template_for_kind(pulse, kind, **kwargs)
    frame = np.zeros(3000)
    frame[74 : 74 + pulse.size] = pulse
    recorded = to_signal_kind(frame, kind, **kwargs)
    rotation = np.exp(-2j * np.pi * FC * tau) if kind == "iq" else 1.0
    # Equal but for the echo's precursor before its arrival (the Hilbert transform and the
    # resampling filter are not causal), which the template cannot hold before t = 0: it
    # reaches about 2e-4 of the peak when the output rate exceeds the input rate.
    np.testing.assert_allclose(
        recorded[delay : delay + len(template)], template * rotation, atol=1e-3 * np.abs(template).max()
    )
    # Before the arrival only the zero-phase filters' short precursor (a few output samples).
    assert (
        np.max(np.abs(recorded[: delay - round(8 * out / 100e3)])) < TEMPLATE_FLOOR * np.abs(template).max()
    )


# ---------------------------------------------------------------------------- errors


@pytest.mark.parametrize(
    ("make", "field"),
    [
        (lambda: GainSpec(kind="linear"), "kind"),  # type: ignore[arg-type]
        (lambda: GainSpec(gain_db=math.nan), "gain_db"),
        (lambda: GainSpec(slope_db_per_ms=-1.0), "slope_db_per_ms"),
        (lambda: GainSpec(step_db=math.inf), "step_db"),
        (lambda: GainSpec(step_s=0.0), "step_s"),
        (lambda: GainSpec(step_s=-1e-3), "step_s"),
        (lambda: GainSpec(max_gain_db=math.nan), "max_gain_db"),
        (lambda: GainSpec(gain_db=30.0, max_gain_db=20.0), "max_gain_db"),
        (lambda: AdcSpec(bits=0), "bits"),
        (lambda: AdcSpec(bits=40), "bits"),
        (lambda: AdcSpec(bits=12.5), "bits"),  # type: ignore[arg-type]
        (lambda: AdcSpec(bits=True), "bits"),
        (lambda: AdcSpec(full_scale=0.0), "full_scale"),
        (lambda: gain_curve(GainSpec(), -1, FS), "n_samples"),
        (lambda: gain_curve(GainSpec(), 10, 0.0), "sample_rate_hz"),
        (lambda: white_noise(10, -1.0, np.random.default_rng()), "sigma"),
        (
            lambda: band_limited_noise(10, 1.0, np.random.default_rng(), PRESETS["piezo40"], 60e3),
            "sample_rate_hz",
        ),
        (lambda: resample(np.ones(10), 0.0, 1e3), "from_hz"),
        (lambda: resample(np.ones(10), 1e3, math.inf), "to_hz"),
        (lambda: resample(np.ones(10), 1e3, 2e3, axis=1), "axis"),
        (lambda: output_samples(-3, 1e3, 2e3), "n_samples"),
        (lambda: to_signal_kind(np.ones(10), "baseband", **_RATES), "kind"),  # type: ignore[arg-type]
        (
            lambda: to_signal_kind(np.ones(10), "iq", sample_rate_hz=FS, carrier_hz=-1.0, output_rate_hz=FS),
            "carrier_hz",
        ),
        (
            lambda: to_signal_kind(np.ones(10), "iq", sample_rate_hz=90e3, carrier_hz=FC, output_rate_hz=FS),
            "sample_rate_hz",
        ),
        (
            lambda: to_signal_kind(np.ones(10), "rf", sample_rate_hz=FS, carrier_hz=FC, output_rate_hz=80e3),
            "output_rate_hz",
        ),
        (lambda: to_signal_kind(np.ones(10) + 0j, "iq", **_RATES), "rf"),
        (lambda: template_for_kind(np.zeros(10), "rf", **_RATES), "returned_pulse"),
        (lambda: template_for_kind(np.ones((2, 10)), "rf", **_RATES), "returned_pulse"),
    ],
)
def test_bad_input_raises_scene_error_naming_the_field(make: object, field: str) -> None:
    with pytest.raises(SceneError, match=field) as info:
        make()  # type: ignore[operator]
    assert isinstance(info.value, ValueError)
    assert "\n" not in str(info.value)
