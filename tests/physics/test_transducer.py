"""Tests of echoloc.physics.transducer: piston beams, near field, resonator response, Doppler, arrays.

Sources: Kinsler, Frey, Coppens & Sanders, Fundamentals of Acoustics (4th ed.) §7.4
(baffled piston: 2 J1(x)/x, first null x = 3.8317, on-axis pressure, near field);
the report (ch. 2.4.2.5 eqs. 2.19-2.20: x = 1.62 from a three-term series, 0.61 λ/r;
ch. 2.4.2.6: Murata 40 kHz ±2 kHz, 30°; ch. 2.4.4: Polaroid 15°, N_T = θ/α = 90/30 = 3;
eqs. 2.25-2.26 line arrays; eqs. 2.28-2.30 two-way Doppler); Orfanidis, Introduction
to Signal Processing §11.3 (digital resonator); Van Trees, Optimum Array Processing
ch. 2-3 (grating lobes, Dolph-Chebyshev); the noise bandwidth of a single-tuned
resonator is π/2 times its -3 dB bandwidth.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import quad
from scipy.optimize import brentq, minimize_scalar, root_scalar
from scipy.special import j0, j1, jn_zeros

from echoloc.errors import EchoLocError
from echoloc.physics.air import speed_of_sound_m_s
from echoloc.physics.transducer import (
    PRESETS,
    SPEED_OF_SOUND_20C_M_S,
    X_FIRST_NULL,
    X_MINUS_3DB,
    ShadingKind,
    Transducer,
    apply_response,
    array_factor,
    directivity,
    doppler_shift_hz,
    doppler_time_scale,
    frequency_response,
    grating_lobe_angles,
    group_delay_s,
    impulse_response,
    max_spacing_without_grating_lobes_m,
    near_field_length_m,
    piston_beam_angles,
    piston_directivity,
    piston_half_angle_rad,
    piston_on_axis_pressure,
    planar_array_factor,
    radius_for_beam_width,
    rayleigh_distance_m,
    resonator_coefficients,
    shading_weights,
    transducers_to_cover,
    transducers_to_cover_cone,
)

C = 343.2
X_3DB_PUBLISHED = 1.6163  # 2 J1(x)/x = 1/sqrt(2)
X_NULL_PUBLISHED = 3.8317  # first zero of J1


def _x_3db_by_newton() -> float:
    """Root of 2 J1(x)/x - 1/sqrt(2) by Newton's method, d/dx J1 = J0 - J1/x."""

    def g(x: float) -> float:
        return float(2 * j1(x) / x - 2**-0.5)

    def dg(x: float) -> float:
        return float(2 * (j0(x) - j1(x) / x) / x - 2 * j1(x) / x**2)

    sol = root_scalar(g, fprime=dg, x0=1.5, method="newton", xtol=1e-14)
    assert sol.converged
    return float(sol.root)


def _bandwidth_hz(response: object, f_lo: float, f_hi: float, f0: float) -> float:
    """Width between the two half-power points of |response(f)| around its peak f0."""
    assert callable(response)

    def g(f: float) -> float:
        return float(abs(response(f))) - 2**-0.5

    return float(brentq(g, f0, f_hi, xtol=1e-6) - brentq(g, f_lo, f0, xtol=1e-6))


# ------------------------------------------------------------------ piston beam


def test_minus_3db_root_is_the_published_1_6163() -> None:
    """2 J1(x)/x = 1/√2 at x = 1.6163, solved independently by Newton's method."""
    x_newton = _x_3db_by_newton()
    assert x_newton == pytest.approx(X_3DB_PUBLISHED, abs=5e-5)
    assert pytest.approx(x_newton, abs=1e-10) == X_MINUS_3DB


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_piston_minus_3db_angle_within_1_percent_of_the_root(name: str) -> None:
    """Done-criterion: ka sin θ_-3dB is within 1 % of the root 1.6163 (solved independently)."""
    t = PRESETS[name]
    beam = piston_beam_angles(t.radius_m, t.centre_frequency_hz, C)
    ka = 2 * math.pi * t.centre_frequency_hz / C * t.radius_m
    assert beam.ka == pytest.approx(ka, rel=1e-12)
    if ka < X_MINUS_3DB:
        # A piston this small (the CH101's port) is within 3 dB at every angle: no -3 dB point.
        assert math.isnan(beam.half_angle_3db_rad)
        return
    x = ka * math.sin(beam.half_angle_3db_rad)
    assert x == pytest.approx(_x_3db_by_newton(), rel=0.01)
    assert x == pytest.approx(X_3DB_PUBLISHED, rel=1e-4)
    assert beam.full_angle_3db_rad == pytest.approx(2 * beam.half_angle_3db_rad, rel=1e-15)


@given(
    radius_m=st.floats(min_value=2e-3, max_value=0.05),
    frequency_hz=st.floats(min_value=20e3, max_value=200e3),
)
@settings(max_examples=60, deadline=None)
def test_directivity_is_half_power_at_the_minus_3db_angle(radius_m: float, frequency_hz: float) -> None:
    """D(θ_-3dB) = 1/√2 wherever the -3 dB point exists (ka > 1.6163), and D < 1/√2 beyond it."""
    theta = piston_half_angle_rad(radius_m, frequency_hz, C)
    ka = 2 * math.pi * frequency_hz / C * radius_m
    if ka <= X_3DB_PUBLISHED:
        assert math.isnan(theta)
        return
    assert float(piston_directivity(theta, radius_m, frequency_hz, C)) == pytest.approx(2**-0.5, abs=1e-9)
    assert piston_beam_angles(radius_m, frequency_hz, C).half_angle_3db_rad == pytest.approx(theta, rel=1e-12)
    if theta < 1.5:
        assert float(piston_directivity(theta * 1.01, radius_m, frequency_hz, C)) < 2**-0.5


def test_first_null_is_the_first_zero_of_j1() -> None:
    """First null at ka sin θ = 3.8317 = jn_zeros(1, 1), where the pattern is 0."""
    assert float(jn_zeros(1, 1)[0]) == pytest.approx(X_NULL_PUBLISHED, abs=5e-5)
    assert pytest.approx(float(jn_zeros(1, 1)[0]), abs=1e-12) == X_FIRST_NULL
    a, f = 0.0192, 50e3
    beam = piston_beam_angles(a, f, C)
    assert 2 * math.pi * f / C * a * math.sin(beam.half_angle_null_rad) == pytest.approx(3.8317, abs=1e-4)
    assert float(piston_directivity(beam.half_angle_null_rad, a, f, C)) == pytest.approx(0.0, abs=1e-12)
    # 3.8317 / (2π) = 0.6098: the report's "0.61 λ/r".
    assert math.sin(beam.half_angle_null_rad) == pytest.approx(0.60983 * beam.wavelength_m / a, rel=1e-4)


def test_report_approximations_and_what_they_mean() -> None:
    """x = 1.62 is the three-term-series root of 2J1(x)/x = 1/√2; 0.61 λ/a is the first null."""
    # Three terms of J1: 2 J1(x)/x ≈ 1 - x²/8 + x⁴/192; solve for 1/√2 (report ch. 2.4.2.5).
    x_series = brentq(lambda x: 1 - x**2 / 8 + x**4 / 192 - 2**-0.5, 1.0, 2.0)
    assert round(x_series, 2) == 1.62
    assert x_series == pytest.approx(1.6223, abs=1e-4)
    beam = piston_beam_angles(0.0192, 50e3, C)
    assert math.sin(beam.report_half_angle_3db_rad) * beam.ka == pytest.approx(1.62, rel=1e-12)
    assert math.sin(beam.report_half_angle_null_rad) == pytest.approx(0.61 * beam.wavelength_m / 0.0192)
    # The approximations are close: 1.62 vs 1.6163 (+0.23 %), 0.61 vs 0.60983 (+0.03 %).
    assert beam.report_half_angle_3db_rad / beam.half_angle_3db_rad == pytest.approx(1.0023, abs=2e-4)
    assert beam.report_half_angle_null_rad / beam.half_angle_null_rad == pytest.approx(1.0003, abs=1e-4)


def test_piston_directivity_against_the_aperture_integral() -> None:
    """Far field of a uniform disc: (2/πa²) ∫ sqrt(a² - x²) cos(k x sin θ) dx = 2 J1(v)/v."""
    a, f = 0.0135, 50e3
    k = 2 * math.pi * f / C
    for theta in (0.05, 0.13, 0.3, 0.6, 1.2):
        s = math.sin(theta)
        # weight "alg" integrates f(x) (x + a)^0.5 (a - x)^0.5: the sqrt(a² - x²) chord exactly.
        integral, _ = quad(lambda x, s=s: math.cos(k * x * s), -a, a, weight="alg", wvar=(0.5, 0.5))
        expected = 2 * integral / (math.pi * a * a)
        assert float(piston_directivity(theta, a, f, C)) == pytest.approx(expected, abs=1e-9)


def test_piston_directivity_on_axis_symmetry_and_baffle() -> None:
    """Exactly 1 on the axis, even in θ, and 0 behind the infinite baffle."""
    theta = np.array([0.0, 0.2, -0.2, 2.0, -2.5, math.pi])
    d = piston_directivity(theta, 0.01, 40e3, C)
    assert d[0] == 1.0
    assert d[1] == d[2]
    assert np.all(d[3:] == 0.0)
    assert d.shape == theta.shape


def test_half_angle_at_minus_6db_and_pulse_echo() -> None:
    """-6 dB: 2J1(x)/x = 1/2 at x = 2.2151; pulse-echo -3 dB (D² = 1/√2): x = 1.1603."""
    a, f = 0.02, 50e3
    ka = 2 * math.pi * f / C * a
    x6 = ka * math.sin(piston_half_angle_rad(a, f, C, pressure_ratio=0.5))
    assert x6 == pytest.approx(2.2151, abs=1e-4)
    x_pe = ka * math.sin(piston_half_angle_rad(a, f, C, pressure_ratio=2**-0.25))
    assert float(2 * j1(x_pe) / x_pe) ** 2 == pytest.approx(2**-0.5, abs=1e-10)


@given(
    full_deg=st.floats(min_value=2.0, max_value=170.0),
    frequency_hz=st.floats(min_value=20e3, max_value=100e3),
)
@settings(max_examples=40, deadline=None)
def test_radius_for_beam_width_round_trip(full_deg: float, frequency_hz: float) -> None:
    """The radius found for a -3 dB full width gives that width back."""
    a = radius_for_beam_width(full_deg, frequency_hz, C)
    beam = piston_beam_angles(a, frequency_hz, C)
    assert beam.full_angle_3db_deg == pytest.approx(full_deg, rel=1e-9)


def test_beam_widths_are_nan_when_ka_is_too_small() -> None:
    """ka < 1.6163: no -3 dB point before 90°; ka < 3.8317: no null."""
    a = 0.5 * X_3DB_PUBLISHED / (2 * math.pi * 40e3 / C)
    beam = piston_beam_angles(a, 40e3, C)
    assert math.isnan(beam.half_angle_3db_rad)
    assert math.isnan(beam.half_angle_null_rad)
    a = 2.5 / (2 * math.pi * 40e3 / C)
    beam = piston_beam_angles(a, 40e3, C)
    assert not math.isnan(beam.half_angle_3db_rad)
    assert math.isnan(beam.full_angle_null_deg)


# -------------------------------------------------------------------- near field


@pytest.mark.parametrize(("radius_m", "frequency_hz"), [(0.0192, 50e3), (0.0085, 40e3), (0.005, 40e3)])
def test_near_field_lengths(radius_m: float, frequency_hz: float) -> None:
    """a²/λ (report eq. 2.11); the last axial maximum at (a² - λ²/4)/λ; Rayleigh distance πa²/λ."""
    lam = C / frequency_hz
    assert near_field_length_m(radius_m, frequency_hz, C) == pytest.approx(radius_m**2 / lam, rel=1e-12)
    assert rayleigh_distance_m(radius_m, frequency_hz, C) == pytest.approx(math.pi * radius_m**2 / lam)
    exact = near_field_length_m(radius_m, frequency_hz, C, exact=True)
    assert exact == pytest.approx((radius_m**2 - lam**2 / 4) / lam, rel=1e-12)
    # The last maximum of the exact on-axis pressure, found numerically, is there.
    res = minimize_scalar(
        lambda z: -float(piston_on_axis_pressure(z, radius_m, frequency_hz, C)),
        bounds=(0.6 * exact, 3 * exact),
        method="bounded",
        options={"xatol": 1e-9},
    )
    assert res.x == pytest.approx(exact, rel=1e-4)
    assert -res.fun == pytest.approx(1.0, abs=1e-9)
    # Beyond it the axial pressure only falls.
    z = np.linspace(exact, 50 * exact, 2000)
    assert np.all(np.diff(piston_on_axis_pressure(z, radius_m, frequency_hz, C)) < 0)


def test_on_axis_pressure_far_field_falls_as_one_over_distance() -> None:
    """Far away, |sin(k a²/(4z))| → k a²/(4z): pressure × distance tends to k a²/4."""
    a, f = 0.0135, 50e3
    k = 2 * math.pi * f / C
    z = 100 * rayleigh_distance_m(a, f, C)
    assert float(piston_on_axis_pressure(z, a, f, C)) * z == pytest.approx(k * a * a / 4, rel=1e-4)


def test_no_axial_maximum_for_a_small_piston() -> None:
    """a <= λ/2: the axial pressure falls from the face on; the exact near field is 0."""
    lam = C / 40e3
    assert near_field_length_m(0.4 * lam, 40e3, C, exact=True) == 0.0
    z = np.linspace(0.0, 0.1, 500)
    assert np.all(np.diff(piston_on_axis_pressure(z, 0.4 * lam, 40e3, C)) < 0)


# ----------------------------------------------------------------- presets, response


def test_presets_have_the_stated_beam_widths() -> None:
    """electrostatic50: 15° at -3 dB at 50 kHz (report ch. 2.4.4); piezo40: 30° at 40 kHz (ch. 2.4.2.6)."""
    for name, full_deg in (("electrostatic50", 15.0), ("piezo40", 30.0)):
        t = PRESETS[name]
        beam = piston_beam_angles(t.radius_m, t.centre_frequency_hz, C)
        assert beam.full_angle_3db_deg == pytest.approx(full_deg, abs=1.0)
        # Cross-check with the directivity: a brute-force search for the half-power angle.
        theta = np.radians(np.linspace(0.0, full_deg, 200_001))
        d = directivity(t, theta, speed_of_sound_m_s=C)
        measured = 2 * math.degrees(theta[np.argmax(d < 2**-0.5)])
        assert measured == pytest.approx(full_deg, abs=1.0)


def test_preset_bandwidths_measured_from_the_frequency_response() -> None:
    """piezo40: -3 dB band 4 kHz (±2 kHz) within 10 %; electrostatic50: broad (Q <= 3)."""
    piezo = PRESETS["piezo40"]
    bw = _bandwidth_hz(lambda f: frequency_response(piezo, f)[()], 30e3, 50e3, 40e3)
    assert bw == pytest.approx(4000.0, rel=0.10)
    assert bw == pytest.approx(piezo.bandwidth_hz, rel=1e-6)
    es = PRESETS["electrostatic50"]
    bw_es = _bandwidth_hz(lambda f: frequency_response(es, f)[()], 10e3, 150e3, 50e3)
    assert bw_es == pytest.approx(es.bandwidth_hz, rel=1e-6)
    assert 50e3 / bw_es <= 3.0
    assert bw_es >= 5 * bw


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_resonator_band_edges_gain_and_pair(name: str) -> None:
    """Analog resonator: gain 1 at f0, edges f0 (sqrt(1 + 1/4Q²) ∓ 1/2Q), pair width 0.6436 B."""
    t = PRESETS[name]
    f0, q = t.centre_frequency_hz, t.quality_factor
    assert frequency_response(t, f0)[()] == pytest.approx(1.0 + 0.0j, abs=1e-15)
    edges = f0 * (math.sqrt(1 + 1 / (4 * q * q)) + np.array([-1, 1]) / (2 * q))
    assert np.abs(frequency_response(t, edges)) == pytest.approx(2**-0.5, abs=1e-12)
    pair_bw = _bandwidth_hz(lambda f: frequency_response(t, f, passes=2)[()], 1e3, 4 * f0, f0)
    assert pair_bw == pytest.approx(math.sqrt(math.sqrt(2) - 1) * t.bandwidth_hz, rel=1e-6)
    f = np.array([-45e3, 0.0, 45e3])
    h = frequency_response(t, f)
    assert h[1] == 0
    assert h[0] == pytest.approx(np.conj(h[2]))


@pytest.mark.parametrize("sample_rate_hz", [200e3, 1e6])
@pytest.mark.parametrize("name", sorted(PRESETS))
def test_digital_resonator_keeps_centre_gain_and_bandwidth(name: str, sample_rate_hz: float) -> None:
    """The sampled-signal resonator: gain 1 at f0 and the same -3 dB width, at 200 kHz and 1 MHz."""
    t = PRESETS[name]
    f0 = t.centre_frequency_hz
    if f0 >= sample_rate_hz / 2:
        pytest.skip(f"{name} at {f0:g} Hz cannot be sampled at {sample_rate_hz:g} Hz")

    def h(f: float) -> complex:
        return complex(frequency_response(t, f, sample_rate_hz=sample_rate_hz)[()])

    assert h(f0) == pytest.approx(1.0, abs=1e-12)
    assert _bandwidth_hz(h, 100.0, sample_rate_hz / 2 - 100.0, f0) == pytest.approx(t.bandwidth_hz, rel=1e-6)


def test_group_delay_is_one_over_pi_b_per_pass() -> None:
    """Resonator phase -atan(Q (f/f0 - f0/f)): slope at f0 gives 1/(π B) per pass."""
    for t in PRESETS.values():
        f0, df = t.centre_frequency_hz, 0.01
        phase = np.unwrap(np.angle(frequency_response(t, [f0 - df, f0 + df], passes=2)))
        numeric = -(phase[1] - phase[0]) / (2 * math.pi * 2 * df)
        assert group_delay_s(t, passes=2) == pytest.approx(numeric, rel=1e-6)
        assert group_delay_s(t, passes=1) == pytest.approx(1 / (math.pi * t.bandwidth_hz), rel=1e-12)
        assert group_delay_s(t, sample_rate_hz=4e6) == pytest.approx(group_delay_s(t), rel=1e-3)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_impulse_response_is_the_inverse_fft_of_the_pair_response(name: str) -> None:
    """h = irfft(H_tx H_rx); its energy equals (1/fs) ∫ |H_tx H_rx|² df (Parseval) and lfilter agrees."""
    t = PRESETS[name]
    fs = 500e3
    h = impulse_response(t, fs)
    spectrum = np.fft.rfft(h)
    freqs = np.fft.rfftfreq(len(h), 1 / fs)
    product = frequency_response(t, freqs, sample_rate_hz=fs) ** 2
    assert np.max(np.abs(spectrum[:-1] - product[:-1])) < 1e-12
    energy, _ = quad(
        lambda f: abs(complex(frequency_response(t, f, sample_rate_hz=fs)[()])) ** 4,
        -fs / 2,
        fs / 2,
        points=[-t.centre_frequency_hz, t.centre_frequency_hz],
        limit=400,
    )
    assert np.sum(h**2) == pytest.approx(energy / fs, rel=1e-6)
    # The same response by the time-domain recursion, twice: causal, no pre-ringing.
    b, a = resonator_coefficients(t, fs)
    delta = np.zeros(len(h))
    delta[0] = 1.0
    recursive = scipy.signal.lfilter(b, a, scipy.signal.lfilter(b, a, delta))
    assert np.max(np.abs(h - recursive)) < 1e-6 * np.max(np.abs(h))


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_single_pass_energy_is_the_noise_bandwidth(name: str) -> None:
    """One resonator: ∫|H|² df over ±∞ = 2 · (π/2) B (noise bandwidth of a single-tuned circuit).

    The digital resonator tends to the analog one as fs grows (its deficit is O(B/fs)).
    """
    t = PRESETS[name]
    fs = 200e6
    h = impulse_response(t, fs, passes=1)
    assert np.sum(h**2) * fs == pytest.approx(math.pi * t.bandwidth_hz, rel=1e-3)


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_apply_response_leaves_a_centre_tone_unchanged(name: str) -> None:
    """Gain normalised to 1 (phase 0) at f0: a long tone at f0 comes out as it went in."""
    t = PRESETS[name]
    fs = 400e3
    n = round(0.02 * fs)
    tone = np.sin(2 * np.pi * t.centre_frequency_hz * np.arange(n) / fs)
    out = apply_response(tone, t, fs)
    assert out.shape == tone.shape
    settled = round(0.01 * fs)  # 10 ms: > 30 decay times 1/(πB) of even the piezo pair
    assert np.max(np.abs(out[settled:] - tone[settled:])) < 1e-6
    # Causal: nothing comes out before the tone starts (pad the front with zeros).
    padded = np.concatenate([np.zeros(100), tone])
    assert np.max(np.abs(apply_response(padded, t, fs)[:100])) < 1e-9


def test_apply_response_matches_lfilter_along_any_axis() -> None:
    """FFT filtering with padding = linear convolution = the recursion applied twice, per channel."""
    t = PRESETS["electrostatic50"]
    fs = 200e3
    rng = np.random.default_rng(7)
    x = rng.standard_normal((3, 2000))
    b, a = resonator_coefficients(t, fs)
    expected = scipy.signal.lfilter(b, a, scipy.signal.lfilter(b, a, x, axis=-1), axis=-1)
    assert np.max(np.abs(apply_response(x, t, fs) - expected)) < 1e-8
    assert np.max(np.abs(apply_response(x.T, t, fs, axis=0) - expected.T)) < 1e-8
    one = scipy.signal.lfilter(b, a, x[0])
    assert np.max(np.abs(apply_response(x[0], t, fs, passes=1) - one)) < 1e-8


def test_transducer_is_a_frozen_value_with_q() -> None:
    """Q = f0/B, from_quality_factor round-trips, fields cannot be reassigned, bad values raise."""
    t = Transducer.from_quality_factor("x", 40e3, 10.0, 0.005)
    assert t.bandwidth_hz == pytest.approx(4e3)
    assert t.quality_factor == pytest.approx(10.0)
    with pytest.raises(dataclasses.FrozenInstanceError):
        t.radius_m = 0.01  # type: ignore[misc]
    with pytest.raises(EchoLocError, match="bandwidth_hz"):
        Transducer("bad", 40e3, -1.0, 0.005)
    with pytest.raises(EchoLocError, match="Nyquist"):
        impulse_response(t, 60e3)


def test_default_speed_of_sound_is_dry_air_at_20c() -> None:
    """The 343.2 m/s default is echoloc.physics.air's dry air at 20 °C."""
    assert float(speed_of_sound_m_s(20.0)) == pytest.approx(SPEED_OF_SOUND_20C_M_S, abs=0.02)


# ------------------------------------------------------------------------- Doppler


def test_doppler_exact_value_at_10_m_s() -> None:
    """50 kHz, reflector approaching at 10 m/s: f' - f = 2 f v/(c - v) = 3001.2 Hz; first order 2913.8 Hz."""
    assert float(doppler_shift_hz(50e3, 10.0, C)) == pytest.approx(2 * 50e3 * 10 / (C - 10), rel=1e-12)
    assert float(doppler_shift_hz(50e3, 10.0, C)) == pytest.approx(3001.2005, abs=1e-4)
    assert float(doppler_shift_hz(50e3, 10.0, C, exact=False)) == pytest.approx(2913.7529, abs=1e-4)
    # Report eq. (2.29), v measured away from the source: fd = -2 f0 (v/c) / (1 + v/c).
    away = 10.0
    assert float(doppler_shift_hz(50e3, -away, C)) == pytest.approx(-2 * 50e3 * (away / C) / (1 + away / C))


@given(
    v=st.floats(min_value=-30.0, max_value=30.0, allow_nan=False),
    f=st.floats(min_value=20e3, max_value=100e3),
)
@settings(max_examples=60, deadline=None)
def test_doppler_first_order_agrees_to_second_order(v: float, f: float) -> None:
    """exact - first order = 2 f (v/c)² / (1 - v/c) = O((v/c)²)."""
    exact = float(doppler_shift_hz(f, v, C))
    first = float(doppler_shift_hz(f, v, C, exact=False))
    assert exact - first == pytest.approx(2 * f * (v / C) ** 2 / (1 - v / C), rel=1e-9, abs=1e-9)
    assert abs(exact - first) <= 2.2 * f * (v / C) ** 2 + 1e-9  # 1e-9 Hz: rounding at tiny v


@pytest.mark.parametrize("v", [-20.0, -1.0, 0.0, 5.0, 40.0])
def test_doppler_time_scale_from_the_moving_geometry(v: float) -> None:
    """Emit at t_e, meet the reflector (range r0 - v t) at t_m, arrive at t: dt/dt_e = (c - v)/(c + v)."""
    r0 = 2.0

    def arrival(t_e: float) -> float:
        t_m = brentq(lambda tm: (tm - t_e) * C - (r0 - v * tm), t_e, t_e + 1.0)
        return float(t_m + (r0 - v * t_m) / C)

    dt_e = 1e-3
    ratio = (arrival(dt_e) - arrival(0.0)) / dt_e
    assert float(doppler_time_scale(v, C)) == pytest.approx(ratio, rel=1e-9)
    # Frequencies scale by the inverse: consistent with the exact shift.
    assert 1 / float(doppler_time_scale(v, C)) == pytest.approx(1 + float(doppler_shift_hz(1.0, v, C)))


def test_doppler_rejects_supersonic_speeds() -> None:
    """|v| >= c has no echo: one-line EchoLocError."""
    with pytest.raises(EchoLocError, match="radial_velocity_m_s"):
        doppler_shift_hz(50e3, C, C)
    with pytest.raises(EchoLocError, match="radial_velocity_m_s"):
        doppler_time_scale(-400.0, C)


# --------------------------------------------------------------------------- arrays


@given(
    theta=st.floats(min_value=-math.pi / 2, max_value=math.pi / 2),
    steer=st.floats(min_value=-1.2, max_value=1.2),
)
@settings(max_examples=100, deadline=None)
def test_array_factor_n10_half_wavelength_matches_closed_form(theta: float, steer: float) -> None:
    """N = 10, d = λ/2: |sin(Nψ/2) / (N sin(ψ/2))| with ψ = k d (sin θ - sin θs) (report eq. 2.25)."""
    f = 40e3
    lam = C / f
    n, d = 10, lam / 2
    psi = 2 * math.pi / lam * d * (math.sin(theta) - math.sin(steer))
    s = math.sin(psi / 2)
    expected = 1.0 if abs(s) < 1e-12 else abs(math.sin(n * psi / 2) / (n * s))
    got = float(array_factor(theta, n, d, f, C, steer_rad=steer))
    assert got == pytest.approx(expected, abs=1e-9)


def test_array_factor_peak_and_first_null() -> None:
    """1 at the steering angle; first null of a uniform array at sin θ - sin θs = λ/(N d)."""
    f, n = 40e3, 10
    lam = C / f
    d = lam / 2
    steer = math.radians(20)
    assert float(array_factor(steer, n, d, f, C, steer_rad=steer)) == pytest.approx(1.0, abs=1e-12)
    null = math.asin(math.sin(steer) + lam / (n * d))
    assert float(array_factor(null, n, d, f, C, steer_rad=steer)) == pytest.approx(0.0, abs=1e-12)
    w = shading_weights(n, "hann")
    assert float(array_factor(steer, n, d, f, C, steer_rad=steer, weights=w)) == pytest.approx(1.0)


def test_chebyshev_shading_gives_equal_side_lobes_at_the_asked_level() -> None:
    """Dolph-Chebyshev, N = 10, d = λ/2: every side lobe at -30 dB; uniform is about -13 dB."""
    f, n = 40e3, 10
    lam = C / f
    theta = np.linspace(-math.pi / 2, math.pi / 2, 200_001)
    # Uniform, N = 10: max of |sin(5ψ)/(10 sin(ψ/2))| between its nulls 2π/10 and 4π/10 is -12.97 dB.
    cases: tuple[tuple[ShadingKind, float], ...] = (("chebyshev", -30.0), ("uniform", -12.97))
    for kind, level_db in cases:
        af = array_factor(theta, n, lam / 2, f, C, weights=shading_weights(n, kind, sidelobe_db=30.0))
        peaks = scipy.signal.argrelmax(af)[0]
        side = np.sort(af[peaks])[:-1]  # all local maxima but the main lobe
        assert 20 * np.log10(side.max()) == pytest.approx(level_db, abs=0.05)
        if kind == "chebyshev":
            assert 20 * np.log10(side.min()) == pytest.approx(level_db, abs=0.3)


def test_shading_weights_shapes_and_values() -> None:
    """Uniform ones; Hann without zero ends ([0.5, 1, 0.5] for 3); symmetric; peak 1."""
    assert shading_weights(4).tolist() == [1.0, 1.0, 1.0, 1.0]
    assert shading_weights(3, "hann") == pytest.approx([0.5, 1.0, 0.5])
    kinds: tuple[ShadingKind, ...] = ("hann", "chebyshev")
    for kind in kinds:
        w = shading_weights(9, kind)
        assert w.max() == pytest.approx(1.0)
        assert np.all(w > 0)
        assert w == pytest.approx(w[::-1])
    with pytest.raises(EchoLocError, match="shading kind"):
        shading_weights(5, "taylor")  # type: ignore[arg-type]


def test_planar_array_factor_is_the_product_of_line_factors() -> None:
    """4 x 6 grid: AF = AF_x(u - u_s) AF_y(v - v_s); with φ = 0 and ny = 1 it is the line array."""
    f = 40e3
    lam = C / f
    rng = np.random.default_rng(3)
    theta = rng.uniform(0, math.pi / 2, 50)
    phi = rng.uniform(-math.pi, math.pi, 50)
    ts, ps = 0.3, 0.8
    got = planar_array_factor(
        theta, phi, 4, 6, lam / 2, 0.4 * lam, f, C, steer_theta_rad=ts, steer_phi_rad=ps
    )
    u = np.sin(theta) * np.cos(phi) - math.sin(ts) * math.cos(ps)
    v = np.sin(theta) * np.sin(phi) - math.sin(ts) * math.sin(ps)

    def line(x: np.ndarray, n: int, d: float) -> np.ndarray:
        psi = 2 * math.pi / lam * d * x
        return np.asarray(np.abs(np.sin(n * psi / 2) / (n * np.sin(psi / 2))))

    assert got == pytest.approx(line(u, 4, lam / 2) * line(v, 6, 0.4 * lam), abs=1e-9)
    steered = planar_array_factor(
        ts, ps, 4, 6, lam / 2, 0.4 * lam, f, C, steer_theta_rad=ts, steer_phi_rad=ps
    )
    assert float(steered) == pytest.approx(1.0)
    line_theta = np.linspace(-1.5, 1.5, 31)
    flat = planar_array_factor(line_theta, 0.0, 8, 1, lam / 2, lam / 2, f, C)
    assert flat == pytest.approx(array_factor(line_theta, 8, lam / 2, f, C), abs=1e-12)


@given(ratio=st.floats(min_value=0.01, max_value=0.5))
@settings(max_examples=40, deadline=None)
def test_no_grating_lobes_up_to_half_a_wavelength(ratio: float) -> None:
    """d <= λ/2: no grating lobe at any steering angle, in particular unsteered."""
    f = 40e3
    d = ratio * C / f
    assert grating_lobe_angles(d, f, C).size == 0
    for steer in (-1.5, -0.7, 0.7, 1.5):
        assert grating_lobe_angles(d, f, C, steer_rad=steer).size == 0


def test_grating_lobes_for_one_and_two_wavelengths() -> None:
    """d = λ: lobes at ±90°; d = 2λ: ±30° and ±90° (report fig. 2.12); each is a full-height lobe."""
    f = 40e3
    lam = C / f
    g1 = grating_lobe_angles(lam, f, C)
    assert np.degrees(g1) == pytest.approx([-90.0, 90.0])
    g2 = grating_lobe_angles(2 * lam, f, C)
    assert np.degrees(g2) == pytest.approx([-90.0, -30.0, 30.0, 90.0])
    assert array_factor(g2, 10, 2 * lam, f, C) == pytest.approx(np.ones(4), abs=1e-9)


def test_grating_lobe_of_a_steered_array() -> None:
    """d = 0.75 λ: none unsteered; steered to 30°, one at sin θ = 0.5 - 1/0.75 (-56.4°)."""
    f = 40e3
    lam = C / f
    assert grating_lobe_angles(0.75 * lam, f, C).size == 0
    g = grating_lobe_angles(0.75 * lam, f, C, steer_rad=math.radians(30))
    assert np.degrees(g) == pytest.approx([math.degrees(math.asin(0.5 - 1 / 0.75))])
    assert float(array_factor(g[0], 10, 0.75 * lam, f, C, steer_rad=math.radians(30))) == pytest.approx(1.0)
    assert max_spacing_without_grating_lobes_m(f, C) == pytest.approx(lam / 2)
    assert max_spacing_without_grating_lobes_m(f, C, 0.0) == pytest.approx(lam)
    assert max_spacing_without_grating_lobes_m(f, C, math.radians(30)) == pytest.approx(lam / 1.5)


# ------------------------------------------------------------------------- coverage


@pytest.mark.parametrize(
    ("fov", "beam", "overlap", "expected"),
    [
        (90.0, 30.0, 0.0, 3),  # the report's example, N_T = 90/30
        (90.0, 30.0, 0.1, 4),  # 90 / 27 = 3.33
        (360.0, 15.0, 0.0, 24),
        (360.0, 15.0, 0.25, 32),
        (100.0, 30.0, 0.0, 4),
        (10.0, 30.0, 0.0, 1),
    ],
)
def test_transducers_to_cover_a_fan(fov: float, beam: float, overlap: float, expected: int) -> None:
    """ceil(FOV / (α (1 - overlap)))."""
    assert transducers_to_cover(fov, beam, overlap) == expected


def test_transducers_to_cover_a_cone_by_solid_angle() -> None:
    """Ω = 2π(1 - cos(α/2)): a hemisphere with 180° beams is 1; the sphere 2; 90° cone with 15° beams 35."""
    assert transducers_to_cover_cone(180.0, 180.0) == 1
    assert transducers_to_cover_cone(360.0, 180.0) == 2
    ratio = (1 - math.cos(math.radians(45))) / (1 - math.cos(math.radians(7.5)))
    assert ratio == pytest.approx(34.24, abs=0.01)
    assert transducers_to_cover_cone(90.0, 15.0) == 35
    assert transducers_to_cover_cone(90.0, 15.0, gap_free=True) == math.ceil(ratio * 2 * math.pi / 27**0.5)
    assert transducers_to_cover_cone(90.0, 30.0, 0.5) == transducers_to_cover_cone(90.0, 15.0)


@pytest.mark.parametrize(
    ("call", "field"),
    [
        (lambda: transducers_to_cover(90.0, 30.0, 1.0), "overlap"),
        (lambda: transducers_to_cover(0.0, 30.0), "field_of_view_deg"),
        (lambda: piston_directivity(0.1, -0.01, 40e3), "radius_m"),
        (lambda: piston_beam_angles(0.01, 0.0), "frequency_hz"),
        (lambda: radius_for_beam_width(180.0, 40e3), "full_angle_deg"),
        (lambda: array_factor(0.1, 0, 0.004, 40e3), "n_elements"),
        (lambda: array_factor(0.1, 3, 0.004, 40e3, weights=[1, -1, 0]), "weights"),
        (lambda: frequency_response(PRESETS["piezo40"], 40e3, passes=-1), "passes"),
        (lambda: piston_on_axis_pressure(-1.0, 0.01, 40e3), "distance_m"),
        (lambda: apply_response(np.ones(5), PRESETS["piezo40"], 200e3, axis=1), "axis"),
        (lambda: doppler_shift_hz(50e3, 10.0, -343.0), "speed_of_sound_m_s"),
    ],
)
def test_bad_input_raises_one_line_echolocerror(call: object, field: str) -> None:
    """Every bad value raises EchoLocError with one line naming it."""
    assert callable(call)
    with pytest.raises(EchoLocError, match=field) as info:
        call()
    assert "\n" not in str(info.value)
