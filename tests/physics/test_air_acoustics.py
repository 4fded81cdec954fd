"""Tests of the acoustics of air in echoloc.physics.air: Cramer's speed of sound, ISO 9613-1
absorption, density, impedance, reflection and transmission, levels.

Sources (each test names the ones it uses):

- O. Cramer (1993), J. Acoust. Soc. Am. 93(5), 2510-2516, doi:10.1121/1.405827: Eq. (15),
  Table III, Appendix Eqs. (A1)-(A3), Fig. 1. The Fig. 1 points below were digitised from
  the paper's plot by the pyfar project (pyfar/pyfar, tests/test_constants_speed_of_sound_cramer.py);
  reading a plot is good to about +-0.1 m/s, hence the 0.15 m/s tolerance.
- ISO 9613-1:1993, Table 1 (pure-tone attenuation coefficients, dB/km, 101.325 kPa,
  computed at the exact one-third-octave midband frequencies 1000 * 10**(k/10) Hz, its
  Note 5). Values transcribed from the standard in commuted/sound-propagation
  (tests/test_atmospheric_absorption.py), in the ITA-Toolbox check script for
  ita_atmospheric_absorption_iso9613 (RWTH Aachen), and in pyfar/pyfar
  (tests/test_constants_air_attenuation.py).
- ISO 9613-2:1996, Table 2 (attenuation coefficients for octave bands at the exact
  midband frequencies 1000 * 10**(0.3 k) Hz, dB/km), reproduced identically in many
  noise-mapping codes; only its three-significant-figure entries (>= 10 dB/km) are used
  for a 1 % comparison.
- B. D. Lawrence and J. A. Simmons (1982), "Measurements of atmospheric attenuation at
  ultrasonic frequencies and the significance for echolocation by bats", J. Acoust. Soc.
  Am. 71(3), 585-590: measured 0.7 dB/m at 30 kHz and 8 dB/m at 200 kHz, 25 °C, 50 % RH.
- ISO 2533:1975 standard atmosphere: dry air at 15 °C and 101 325 Pa has 1.225 kg/m³.
- L. E. Kinsler, A. R. Frey, A. B. Coppens, J. V. Sanders, Fundamentals of Acoustics, 4th ed.
  (2000): ch. 5 (rho c, levels), ch. 6 (normal-incidence R, T, energy; air to water
  transmits about 0.1 % of the intensity) and its tables of material properties
  (water at 20 °C: rho 998 kg/m³, c 1481 m/s; steel: rho 7700 kg/m³, bulk c 6100 m/s).
- IAPWS-95 saturation pressures (Wagner & Pruß 2002, J. Phys. Chem. Ref. Data 31, 387),
  as in tests/test_air.py.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from echoloc.errors import EchoLocError
from echoloc.physics.air import (
    absorption_db_per_m,
    absorption_gain,
    air_density_kg_m3,
    characteristic_impedance_rayl,
    enhancement_factor,
    intensity_level_db,
    intensity_reflection_coefficient,
    intensity_transmission_coefficient,
    reflection_coefficient,
    saturation_vapour_pressure_giacomo_pa,
    sound_pressure_level_db,
    speed_of_sound_cramer_m_s,
    speed_of_sound_m_s,
    transmission_coefficient,
)

NAN = float("nan")
cramer_temperatures_c = st.floats(min_value=0.0, max_value=30.0, allow_nan=False)
cramer_pressures_pa = st.floats(min_value=60_000.0, max_value=110_000.0, allow_nan=False)
humidities = st.floats(min_value=0.0, max_value=1.0, allow_nan=False)
impedances_rayl = st.floats(min_value=1.0, max_value=1e8, allow_nan=False)
distances_m = st.floats(min_value=0.0, max_value=100.0, allow_nan=False)


def third_octave_hz(k: int) -> float:
    """Exact one-third-octave midband frequency, Hz (ISO 9613-1, Note 5): 1000 * 10**(k/10)."""
    return float(1000.0 * 10.0 ** (k / 10.0))


# Exact midband frequencies of the nominal bands used below.
F_800 = third_octave_hz(-1)
F_1K = third_octave_hz(0)
F_2K = third_octave_hz(3)
F_4K = third_octave_hz(6)
F_6K3 = third_octave_hz(8)
F_8K = third_octave_hz(9)
F_10K = third_octave_hz(10)


# ------------------------------------------------------------------ Cramer (1993)


@pytest.mark.parametrize(
    ("t_c", "rh", "published_m_s"),
    [
        (0.0, 0.0047393, 331.5079),
        (0.0, 0.60032, 331.7063),
        (10.0, 0.0063191, 337.4603),
        (10.0, 0.6019, 337.8571),
        (20.0, 0.0078989, 343.3333),
        (20.0, 0.30174, 343.7302),
        (20.0, 0.6019, 344.1667),
        (20.0, 0.98736, 344.6825),
        (30.0, 0.0047393, 349.1667),
        (30.0, 0.6019, 350.5556),
        (30.0, 0.98894, 351.5079),
    ],
)
def test_cramer_matches_figure_1_against_humidity(t_c: float, rh: float, published_m_s: float) -> None:
    """Cramer (1993) Fig. 1, c against relative humidity at 101.325 kPa, 314 ppm CO2.

    Points digitised from the figure by pyfar (see module docstring); the humidity
    effect spans 1.3-2.3 m/s over 0..100 % RH, so 0.15 m/s catches a wrong sign or scale.
    """
    assert float(speed_of_sound_cramer_m_s(t_c, rh)) == pytest.approx(published_m_s, abs=0.15)


@pytest.mark.parametrize(
    ("t_c", "co2_percent", "published_m_s"),
    [
        (0.0, 0.006079, 331.4818),
        (0.0, 0.9924, 330.6839),
        (10.0, 0.99088, 336.7249),
        (20.0, 0.30091, 343.1459),
        (20.0, 0.98784, 342.5760),
        (30.0, 0.60182, 348.6170),
    ],
)
def test_cramer_matches_figure_1_against_co2(t_c: float, co2_percent: float, published_m_s: float) -> None:
    """Cramer (1993) Fig. 1, c against CO2 concentration, dry air at 101.325 kPa (pyfar digitisation)."""
    c = float(speed_of_sound_cramer_m_s(t_c, 0.0, 101_325.0, co2_percent / 100.0))
    assert c == pytest.approx(published_m_s, abs=0.15)


def test_cramer_dry_air_at_0c_is_331_455() -> None:
    """Eq. (15) at 0 °C, dry, 101 325 Pa, 314 ppm CO2, by hand from Table III:
    331.5024 - 1.82e-7 p - 85.20931 x_c - 2.15e-13 p^2 + 29.179762 x_c^2 = 331.4550 m/s
    (quoted as 331.46 m/s; the ideal-gas value 331.3 m/s is 0.05 % lower)."""
    p, x_c = 101_325.0, 314e-6
    by_hand = 331.5024 - 1.82e-7 * p - 85.20931 * x_c - 2.15e-13 * p**2 + 29.179762 * x_c**2
    assert by_hand == pytest.approx(331.455, abs=5e-4)
    assert float(speed_of_sound_cramer_m_s(0.0, 0.0)) == pytest.approx(by_hand, abs=1e-9)


def test_cramer_at_20c_50_percent_is_343_99() -> None:
    """20 °C, 50 % RH, 101 325 Pa, 314 ppm: 343.99 m/s (x_w = 0.01159; humidity adds 0.63 m/s)."""
    assert float(speed_of_sound_cramer_m_s(20.0, 0.5)) == pytest.approx(343.99, abs=0.01)


@given(cramer_temperatures_c, cramer_pressures_pa)
def test_cramer_dry_is_within_0_1_percent_of_ideal_gas(t_c: float, pressure_pa: float) -> None:
    """Dry air: the real-gas fit and c = 331.3 sqrt(T / 273.15 K) agree within 0.1 % over 0..30 °C."""
    cramer = float(speed_of_sound_cramer_m_s(t_c, 0.0, pressure_pa))
    assert cramer == pytest.approx(float(speed_of_sound_m_s(t_c)), rel=1e-3)


@given(cramer_temperatures_c, humidities, humidities)
def test_cramer_humidity_raises_speed(t_c: float, rh1: float, rh2: float) -> None:
    """Water vapour is lighter than dry air: more humidity, faster sound (Cramer Fig. 1)."""
    lo, hi = sorted((rh1, rh2))
    assert float(speed_of_sound_cramer_m_s(t_c, lo)) <= float(speed_of_sound_cramer_m_s(t_c, hi))


@given(
    cramer_temperatures_c, st.floats(min_value=0.0, max_value=0.01), st.floats(min_value=0.0, max_value=0.01)
)
def test_cramer_co2_lowers_speed(t_c: float, x1: float, x2: float) -> None:
    """CO2 (44 g/mol) is heavier than air: more CO2, slower sound (Cramer Fig. 1)."""
    lo, hi = sorted((x1, x2))
    assert float(speed_of_sound_cramer_m_s(t_c, 0.5, 101_325.0, hi)) <= float(
        speed_of_sound_cramer_m_s(t_c, 0.5, 101_325.0, lo)
    )


@pytest.mark.parametrize("t_c", [0.0, 10.0, 20.0, 30.0])
def test_cramer_humidity_effect_agrees_with_ideal_gas_mixture(t_c: float) -> None:
    """Saturation raises c by the same fraction (within 5 %) in Cramer's fit and the ideal mixture."""
    cramer = float(speed_of_sound_cramer_m_s(t_c, 1.0) / speed_of_sound_cramer_m_s(t_c, 0.0)) - 1.0
    ideal = float(speed_of_sound_m_s(t_c, 1.0) / speed_of_sound_m_s(t_c, 0.0)) - 1.0
    assert cramer == pytest.approx(ideal, rel=0.05)


@pytest.mark.parametrize(("t_c", "published_pa"), [(20.0, 2339.3), (30.0, 4247.0), (40.0, 7384.9)])
def test_giacomo_saturation_pressure_matches_iapws(t_c: float, published_pa: float) -> None:
    """Cramer Eq. (A3) (Giacomo 1982) within 0.1 % of IAPWS-95 saturation pressures."""
    assert float(saturation_vapour_pressure_giacomo_pa(t_c)) == pytest.approx(published_pa, rel=1e-3)


def test_enhancement_factor_uses_celsius() -> None:
    """Cramer Eq. (A2): f = 1.00062 + 3.14e-8 p + 5.6e-7 t^2 with t in °C; about 1.0040 at 20 °C, 1 atm.

    (t in kelvin would give 1.052, a 5 % error in the water mole fraction.)"""
    f = float(enhancement_factor(20.0, 101_325.0))
    assert f == pytest.approx(1.00062 + 3.14e-8 * 101_325.0 + 5.6e-7 * 400.0, rel=1e-12)
    assert 1.003 < f < 1.005


def test_cramer_broadcasts_over_all_arguments() -> None:
    """Temperature, humidity, pressure and CO2 broadcast like numpy; each element is the scalar result."""
    t = np.array([0.0, 15.0, 30.0])[:, None, None, None]
    rh = np.array([0.0, 0.5])[:, None, None]
    p = np.array([80_000.0, 101_325.0])[:, None]
    co2 = np.array([0.0, 314e-6, 0.004])
    c = speed_of_sound_cramer_m_s(t, rh, p, co2)
    assert c.shape == (3, 2, 2, 3)
    assert c[2, 1, 0, 2] == pytest.approx(
        float(speed_of_sound_cramer_m_s(30.0, 0.5, 80_000.0, 0.004)), rel=1e-15
    )


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"temperature_c": -5.0}, "temperature_c"),
        ({"temperature_c": 31.0}, "temperature_c"),
        ({"temperature_c": NAN}, "temperature_c"),
        ({"relative_humidity": -0.1}, "relative_humidity"),
        ({"relative_humidity": 1.1}, "relative_humidity"),
        ({"relative_humidity": NAN}, "relative_humidity"),
        ({"pressure_pa": 0.0}, "pressure_pa"),
        ({"pressure_pa": -101_325.0}, "pressure_pa"),
        ({"pressure_pa": 50_000.0}, "pressure_pa"),
        ({"pressure_pa": NAN}, "pressure_pa"),
        ({"co2_mole_fraction": -1e-4}, "co2_mole_fraction"),
        ({"co2_mole_fraction": 0.02}, "co2_mole_fraction"),
    ],
)
def test_cramer_rejects_values_outside_its_range(kwargs: dict[str, float], name: str) -> None:
    """Out-of-range or NaN input: one EchoLocError naming the argument, never a silent extrapolation."""
    args = {
        "temperature_c": 20.0,
        "relative_humidity": 0.5,
        "pressure_pa": 101_325.0,
        "co2_mole_fraction": 314e-6,
    }
    args.update(kwargs)
    with pytest.raises(EchoLocError, match=name) as info:
        speed_of_sound_cramer_m_s(**args)
    assert "\n" not in str(info.value)


def test_cramer_names_the_first_bad_element_of_an_array() -> None:
    """An array with one bad element reports that element, in one line."""
    with pytest.raises(EchoLocError, match=r"relative_humidity .* got 1\.5$"):
        speed_of_sound_cramer_m_s(20.0, np.array([0.2, 0.4, 1.5, 0.6]))


# ------------------------------------------------------------------ ISO 9613-1 absorption


@pytest.mark.parametrize(
    ("rh", "frequency_hz", "table_db_per_km"),
    [
        (0.10, F_1K, 14.1),  # Table 1, 20 °C (commuted/sound-propagation transcription)
        (0.10, F_4K, 109.0),
        (0.70, F_1K, 4.98),
        (1.00, F_1K, 5.42),
        (1.00, F_4K, 19.4),
        (0.15, F_6K3, 175.0),  # Table 1, 20 °C (ITA-Toolbox check script)
        (0.80, F_1K, 5.15),
        (0.80, F_10K, 105.0),
    ],
)
def test_iso_9613_1_table_1_at_20c(rh: float, frequency_hz: float, table_db_per_km: float) -> None:
    """ISO 9613-1:1993 Table 1, 20 °C, 101.325 kPa, within 1 % (sources in the module docstring)."""
    alpha_db_per_km = 1e3 * float(absorption_db_per_m(frequency_hz, 20.0, rh, 101_325.0))
    assert alpha_db_per_km == pytest.approx(table_db_per_km, rel=0.01)


@pytest.mark.parametrize(
    ("t_c", "rh", "frequency_hz", "table_db_per_km"),
    [
        (-20.0, 0.30, F_800, 4.92),  # pyfar
        (-20.0, 0.10, F_8K, 10.9),  # commuted/sound-propagation
        (-10.0, 0.70, F_8K, 86.2),
        (0.0, 0.15, F_1K, 18.3),
        (10.0, 0.10, F_1K, 21.6),  # pyfar
        (10.0, 0.10, F_4K, 57.3),
        (30.0, 0.10, F_4K, 96.0),
        (35.0, 0.60, F_4K, 25.8),  # pyfar
        (50.0, 0.70, F_1K, 8.03),  # pyfar
        (50.0, 0.10, F_8K, 155.0),
    ],
)
def test_iso_9613_1_table_1_other_temperatures(
    t_c: float, rh: float, frequency_hz: float, table_db_per_km: float
) -> None:
    """ISO 9613-1:1993 Table 1 from -20 to +50 °C, within 1 %: temperature enters correctly."""
    alpha_db_per_km = 1e3 * float(absorption_db_per_m(frequency_hz, t_c, rh))
    assert alpha_db_per_km == pytest.approx(table_db_per_km, rel=0.01)


@pytest.mark.parametrize(
    ("t_c", "rh", "octave_k", "table_db_per_km"),
    [
        (20.0, 0.70, 2, 22.9),
        (20.0, 0.70, 3, 76.6),
        (10.0, 0.70, 2, 32.8),
        (10.0, 0.70, 3, 117.0),
        (30.0, 0.70, 1, 12.7),
        (30.0, 0.70, 3, 59.3),
        (15.0, 0.20, 1, 28.2),
        (15.0, 0.20, 3, 202.0),
        (15.0, 0.50, 1, 10.8),
        (15.0, 0.50, 2, 36.2),
        (15.0, 0.50, 3, 129.0),
        (15.0, 0.80, 2, 23.7),
        (15.0, 0.80, 3, 82.8),
    ],
)
def test_iso_9613_2_table_2_octave_bands(
    t_c: float, rh: float, octave_k: int, table_db_per_km: float
) -> None:
    """ISO 9613-2:1996 Table 2 (computed with ISO 9613-1 at 1000 * 10**(0.3 k) Hz), within 1 %.

    k = 1, 2, 3 are the 2, 4 and 8 kHz octave bands; this covers the 50 % row at 15 °C.
    """
    frequency_hz = 1000.0 * 10.0 ** (0.3 * octave_k)
    alpha_db_per_km = 1e3 * float(absorption_db_per_m(frequency_hz, t_c, rh))
    assert alpha_db_per_km == pytest.approx(table_db_per_km, rel=0.01)


def test_ultrasonic_absorption_at_50khz_is_1_to_2_db_per_m() -> None:
    """At a sonar's 50 kHz in room air (20 °C, 50 % RH) alpha is 1.66 dB/m: 1-2 dB/m.

    A 2 m echo path therefore loses about 3.3 dB to the air on top of spreading.
    """
    alpha = float(absorption_db_per_m(50e3, 20.0, 0.5))
    assert 1.0 < alpha < 2.0
    assert alpha == pytest.approx(1.66, abs=0.01)


@pytest.mark.parametrize(("frequency_hz", "measured_db_per_m"), [(30e3, 0.7), (200e3, 8.0)])
def test_ultrasonic_absorption_agrees_with_bat_sonar_measurements(
    frequency_hz: float, measured_db_per_m: float
) -> None:
    """Lawrence & Simmons (1982) measured 0.7 dB/m at 30 kHz and 8 dB/m at 200 kHz (25 °C, 50 % RH).

    ISO 9613-1 gives 0.91 and 9.2 dB/m; the measurement is quoted to one figure, so the
    check is 35 %. Classical absorption alone (0.14 dB/m at 30 kHz) or a dB/km mix-up fails it.
    """
    alpha = float(absorption_db_per_m(frequency_hz, 25.0, 0.5))
    assert alpha == pytest.approx(measured_db_per_m, rel=0.35)


@given(
    st.floats(min_value=1.0, max_value=1e6),
    st.floats(min_value=1.0, max_value=1e6),
    st.floats(min_value=-20.0, max_value=50.0),
    humidities,
)
def test_absorption_grows_with_frequency(f1: float, f2: float, t_c: float, rh: float) -> None:
    """Every term of Eq. (5) grows with f: a higher tone is never absorbed less."""
    lo, hi = sorted((f1, f2))
    assert float(absorption_db_per_m(lo, t_c, rh)) <= float(absorption_db_per_m(hi, t_c, rh))


def test_absorption_vanishes_at_zero_frequency_and_goes_as_f_squared_below_relaxation() -> None:
    """alpha(0) = 0; far below both relaxation frequencies alpha is proportional to f^2."""
    assert float(absorption_db_per_m(0.0)) == 0.0
    ratio = float(absorption_db_per_m(2.0) / absorption_db_per_m(1.0))
    assert ratio == pytest.approx(4.0, rel=1e-4)


@pytest.mark.parametrize("pressure_pa", [50_662.5, 101_325.0])
def test_absorption_tends_to_classical_far_above_relaxation(pressure_pa: float) -> None:
    """For f >> f_rO, f_rN only the classical term remains: alpha / f^2 -> 8.686 * 1.84e-11 (p_r / p_a)
    at 20 °C (ISO 9613-1, Eq. 5), so at fixed f halving the pressure doubles alpha."""
    f = 1e8
    classical = 8.686 * 1.84e-11 * (101_325.0 / pressure_pa)
    assert float(absorption_db_per_m(f, 20.0, 0.5, pressure_pa)) / f**2 == pytest.approx(classical, rel=1e-5)


def test_absorption_broadcasts_over_all_arguments() -> None:
    """frequency, temperature, humidity and pressure broadcast; each element is the scalar result."""
    f = np.array([1e3, 4e4, 5e4])[:, None, None, None]
    t = np.array([0.0, 20.0])[:, None, None]
    rh = np.array([0.1, 0.5, 0.9])[:, None]
    p = np.array([90_000.0, 101_325.0])
    alpha = absorption_db_per_m(f, t, rh, p)
    assert alpha.shape == (3, 2, 3, 2)
    assert alpha[1, 0, 2, 0] == pytest.approx(float(absorption_db_per_m(4e4, 0.0, 0.9, 90_000.0)), rel=1e-15)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        ({"frequency_hz": -1.0}, "frequency_hz"),
        ({"frequency_hz": NAN}, "frequency_hz"),
        ({"frequency_hz": float("inf")}, "frequency_hz"),
        ({"relative_humidity": -0.01}, "relative_humidity"),
        ({"relative_humidity": 1.01}, "relative_humidity"),
        ({"relative_humidity": NAN}, "relative_humidity"),
        ({"pressure_pa": 0.0}, "pressure_pa"),
        ({"pressure_pa": -1.0}, "pressure_pa"),
        ({"pressure_pa": NAN}, "pressure_pa"),
        ({"temperature_c": -273.15}, "temperature_c"),
        ({"temperature_c": NAN}, "temperature_c"),
    ],
)
def test_absorption_rejects_invalid_input(kwargs: dict[str, float], name: str) -> None:
    """Negative frequency, humidity outside 0..1, pressure <= 0 and NaN raise one EchoLocError line."""
    args = {"frequency_hz": 40e3, "temperature_c": 20.0, "relative_humidity": 0.5, "pressure_pa": 101_325.0}
    args.update(kwargs)
    with pytest.raises(EchoLocError, match=name) as info:
        absorption_db_per_m(**args)
    assert "\n" not in str(info.value)


def test_absorption_rejects_non_numeric_input() -> None:
    """A string is not a frequency: EchoLocError, not a numpy traceback."""
    with pytest.raises(EchoLocError, match="frequency_hz"):
        absorption_db_per_m("forty kHz")


# ------------------------------------------------------------------ absorption gain


@given(distances_m, st.floats(min_value=0.0, max_value=2e5), humidities)
def test_absorption_gain_is_the_db_law(distance_m: float, frequency_hz: float, rh: float) -> None:
    """Amplitude factor 10**(-alpha d / 20) (ISO 9613-1, Eq. 2), in (0, 1]."""
    gain = float(absorption_gain(distance_m, frequency_hz, 20.0, rh))
    expected = 10.0 ** (-float(absorption_db_per_m(frequency_hz, 20.0, rh)) * distance_m / 20.0)
    assert gain == pytest.approx(expected, rel=1e-12)
    assert 0.0 < gain <= 1.0


@given(distances_m, distances_m)
def test_absorption_gain_multiplies_over_path_segments(d1: float, d2: float) -> None:
    """Absorbing d1 then d2 is absorbing d1 + d2 (exponential decay)."""
    f = 50e3
    assert float(absorption_gain(d1 + d2, f)) == pytest.approx(
        float(absorption_gain(d1, f) * absorption_gain(d2, f)), rel=1e-12
    )


def test_absorption_gain_for_a_2_m_echo_path_at_50khz() -> None:
    """2 m at 50 kHz, 20 °C, 50 % RH: 3.32 dB, amplitude factor 0.682; zero distance: exactly 1."""
    assert float(absorption_gain(2.0, 50e3)) == pytest.approx(0.682, abs=0.001)
    assert float(absorption_gain(0.0, 50e3)) == 1.0


def test_absorption_gain_broadcasts_frames_channels_and_frequencies() -> None:
    """Path lengths of shape (frames, channels, 1) against a frequency axis give (frames, channels, bins)."""
    d = np.full((4, 3, 1), 1.5)
    f = np.linspace(0.0, 1e5, 11)
    assert absorption_gain(d, f).shape == (4, 3, 11)


@pytest.mark.parametrize("distance_m", [-0.1, NAN])
def test_absorption_gain_rejects_bad_distance(distance_m: float) -> None:
    """A path length is finite and >= 0."""
    with pytest.raises(EchoLocError, match="distance_m"):
        absorption_gain(distance_m, 50e3)


# ------------------------------------------------------------------ density and impedance


def test_dry_air_density_matches_standard_atmosphere() -> None:
    """ISO 2533 standard atmosphere at sea level: 15 °C, 101 325 Pa, 1.225 kg/m³."""
    assert float(air_density_kg_m3(15.0)) == pytest.approx(1.225, rel=2e-4)


@given(st.floats(min_value=-30.0, max_value=50.0), st.floats(min_value=5e4, max_value=1.2e5))
def test_dry_air_density_is_ideal_gas(t_c: float, pressure_pa: float) -> None:
    """Dry air: rho = p M / (R T), proportional to p and to 1 / T (CIPM-2007 with Z = 1)."""
    expected = pressure_pa * 28.9647e-3 / (8.314462618 * (t_c + 273.15))
    assert float(air_density_kg_m3(t_c, 0.0, pressure_pa)) == pytest.approx(expected, rel=1e-12)


@given(st.floats(min_value=0.0, max_value=40.0), humidities, humidities)
def test_humid_air_is_lighter(t_c: float, rh1: float, rh2: float) -> None:
    """Water (18 g/mol) replaces dry air (29 g/mol) at equal pressure: humid air is lighter."""
    lo, hi = sorted((rh1, rh2))
    assert float(air_density_kg_m3(t_c, hi)) <= float(air_density_kg_m3(t_c, lo))


def test_air_impedance_at_20c_is_about_413_rayl() -> None:
    """rho c of air at 20 °C, 1 atm: 1.204 kg/m³ x 343.2 m/s = 413 rayl (Kinsler ch. 5, 415 rayl
    with rho rounded to 1.21 kg/m³)."""
    z = float(characteristic_impedance_rayl(air_density_kg_m3(20.0), speed_of_sound_m_s(20.0)))
    assert z == pytest.approx(413.0, rel=0.01)


@pytest.mark.parametrize(
    ("density", "speed", "name"),
    [
        (0.0, 343.0, "density_kg_m3"),
        (NAN, 343.0, "density_kg_m3"),
        (1.2, -343.0, "speed_m_s"),
        (1.2, NAN, "speed_m_s"),
    ],
)
def test_impedance_rejects_non_positive_input(density: float, speed: float, name: str) -> None:
    """Density and speed of sound of a medium are finite and > 0."""
    with pytest.raises(EchoLocError, match=name):
        characteristic_impedance_rayl(density, speed)


# ------------------------------------------------------------------ reflection and transmission

Z_AIR = 413.0
Z_WATER = 998.0 * 1481.0  # Kinsler, fresh water at 20 °C: 1.48e6 rayl
Z_STEEL = 7700.0 * 6100.0  # Kinsler, steel, bulk (longitudinal) wave: 47e6 rayl


@given(impedances_rayl, impedances_rayl)
def test_energy_is_conserved_at_an_interface(z1: float, z2: float) -> None:
    """R_I + T_I = 1: what is not reflected is transmitted (Kinsler ch. 6)."""
    total = float(intensity_reflection_coefficient(z1, z2) + intensity_transmission_coefficient(z1, z2))
    assert total == pytest.approx(1.0, abs=1e-12)


@given(impedances_rayl, impedances_rayl)
def test_pressure_coefficients_obey_boundary_conditions(z1: float, z2: float) -> None:
    """Continuity of pressure, T = 1 + R; intensity T_I = (Z1 / Z2) T^2; swapping media negates R."""
    r = float(reflection_coefficient(z1, z2))
    t = float(transmission_coefficient(z1, z2))
    assert t == pytest.approx(1.0 + r, abs=1e-12)
    assert float(intensity_transmission_coefficient(z1, z2)) == pytest.approx(z1 / z2 * t**2, rel=1e-9)
    assert float(reflection_coefficient(z2, z1)) == pytest.approx(-r, abs=1e-12)
    assert -1.0 < r < 1.0


def test_matched_impedances_do_not_reflect() -> None:
    """Z1 = Z2: no interface, R = 0 and T = 1."""
    assert float(reflection_coefficient(Z_AIR, Z_AIR)) == 0.0
    assert float(transmission_coefficient(Z_AIR, Z_AIR)) == 1.0


@pytest.mark.parametrize("z_solid_or_liquid", [Z_WATER, Z_STEEL])
def test_air_to_water_and_steel_reflect_almost_everything(z_solid_or_liquid: float) -> None:
    """Sound in air meeting water or steel: |R| > 0.999, R > 0 (a rigid, in-phase reflector)."""
    r = float(reflection_coefficient(Z_AIR, z_solid_or_liquid))
    assert abs(r) > 0.999
    assert r > 0.0


def test_air_to_water_transmits_about_minus_30_db() -> None:
    """Kinsler ch. 6: only about 0.1 % of the intensity crosses from air into water (-29.5 dB)."""
    t_i = float(intensity_transmission_coefficient(Z_AIR, Z_WATER))
    assert t_i == pytest.approx(1.1e-3, rel=0.03)
    assert 10.0 * math.log10(t_i) == pytest.approx(-29.5, abs=0.1)


def test_water_to_air_pressure_release() -> None:
    """From water into air the boundary is nearly pressure-release: R close to -1, T close to 0."""
    assert float(reflection_coefficient(Z_WATER, Z_AIR)) == pytest.approx(-1.0, abs=1e-3)
    assert float(transmission_coefficient(Z_WATER, Z_AIR)) == pytest.approx(0.0, abs=1e-3)


@pytest.mark.parametrize(
    ("z1", "z2", "name"),
    [(0.0, 413.0, "z1"), (413.0, -1.0, "z2"), (NAN, 413.0, "z1"), (413.0, float("inf"), "z2")],
)
def test_reflection_rejects_non_positive_impedance(z1: float, z2: float, name: str) -> None:
    """Characteristic impedances of real media are finite and > 0."""
    for function in (
        reflection_coefficient,
        transmission_coefficient,
        intensity_reflection_coefficient,
        intensity_transmission_coefficient,
    ):
        with pytest.raises(EchoLocError, match=name):
            function(z1, z2)


# ------------------------------------------------------------------ levels


def test_levels_of_textbook_values() -> None:
    """1 W/m² is 120 dB re 1 pW/m²; 1 Pa rms is 93.98 dB re 20 µPa (the '94 dB' calibrator)."""
    assert float(intensity_level_db(1.0)) == pytest.approx(120.0, abs=1e-12)
    assert float(intensity_level_db(1e-12)) == pytest.approx(0.0, abs=1e-12)
    assert float(sound_pressure_level_db(1.0)) == pytest.approx(93.979, abs=1e-3)
    assert float(sound_pressure_level_db(20e-6)) == pytest.approx(0.0, abs=1e-12)


@given(st.floats(min_value=1e-6, max_value=1e3))
def test_plane_wave_levels_agree_where_rho_c_is_400(p_rms: float) -> None:
    """I = p^2 / (rho c); with rho c = 400 rayl the references match exactly (20e-6^2 / 400 = 1e-12)."""
    level_i = float(intensity_level_db(p_rms**2 / 400.0))
    assert level_i == pytest.approx(float(sound_pressure_level_db(p_rms)), abs=1e-9)


def test_room_air_levels_differ_by_a_tenth_of_a_db() -> None:
    """In room air (rho c = 413 rayl) L_I = L_p - 10 log10(413 / 400) = L_p - 0.14 dB."""
    p_rms = 2.0
    z = float(characteristic_impedance_rayl(air_density_kg_m3(20.0), speed_of_sound_m_s(20.0)))
    difference = float(sound_pressure_level_db(p_rms) - intensity_level_db(p_rms**2 / z))
    assert difference == pytest.approx(10.0 * math.log10(z / 400.0), abs=1e-9)
    assert 0.1 < difference < 0.2


def test_level_with_custom_reference() -> None:
    """A doubled reference lowers an intensity level by 3.01 dB and a pressure level by 6.02 dB."""
    assert float(intensity_level_db(1.0, 2e-12)) == pytest.approx(120.0 - 10 * math.log10(2), abs=1e-12)
    assert float(sound_pressure_level_db(1.0, 40e-6)) == pytest.approx(93.979 - 6.0206, abs=1e-3)


@pytest.mark.parametrize("value", [0.0, -1.0, NAN])
def test_levels_reject_non_positive_input(value: float) -> None:
    """Silence or a negative rms pressure has no finite level: EchoLocError, not -inf or NaN."""
    with pytest.raises(EchoLocError, match="intensity_w_m2"):
        intensity_level_db(value)
    with pytest.raises(EchoLocError, match="pressure_pa"):
        sound_pressure_level_db(value)
    with pytest.raises(EchoLocError, match="reference_pa"):
        sound_pressure_level_db(1.0, value)
