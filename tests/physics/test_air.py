"""Tests of echoloc.physics.air: speed of sound in air and spherical spreading.

Sources: docs/METHOD.md ("Speed of sound": c ∝ sqrt(T), +1 K ≈ +0.17 %, humidity adds about
0.3 % at 20 °C); the tabulated 331.3 m/s for dry air at 0 °C; saturation vapour
pressures of water from IAPWS-95 (Wagner & Pruß 2002, J. Phys. Chem. Ref. Data 31, 387).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from echoloc.errors import EchoLocError
from echoloc.physics.air import (
    KELVIN_AT_0C,
    saturation_vapour_pressure_pa,
    speed_of_sound_m_s,
    spreading_gain,
    water_mole_fraction,
)

temperatures_c = st.floats(min_value=-50.0, max_value=60.0, allow_nan=False)
humidities = st.floats(min_value=0.0, max_value=1.0, allow_nan=False)
distances_m = st.floats(min_value=1e-3, max_value=1e3, allow_nan=False)


def test_dry_air_at_0c_is_331_3() -> None:
    """Dry air at 0 °C: 331.3 m/s (tabulated value)."""
    assert float(speed_of_sound_m_s(0.0)) == pytest.approx(331.3, abs=1e-9)


def test_dry_air_at_20c_is_343_2() -> None:
    """Dry air at 20 °C: 343.2 m/s (331.3 sqrt(293.15/273.15) = 343.21)."""
    assert float(speed_of_sound_m_s(20.0)) == pytest.approx(343.2, abs=0.05)


@given(temperatures_c)
def test_dry_air_follows_sqrt_of_absolute_temperature(t_c: float) -> None:
    """Ideal gas: c = 331.3 sqrt(T / 273.15 K) in dry air (docs/METHOD.md)."""
    expected = 331.3 * math.sqrt((t_c + KELVIN_AT_0C) / KELVIN_AT_0C)
    assert float(speed_of_sound_m_s(t_c, 0.0)) == pytest.approx(expected, rel=1e-12)


def test_one_kelvin_warmer_is_0_17_percent_faster() -> None:
    """+1 K at 20 °C raises c by about 0.17 % (docs/METHOD.md; closed form 1/(2 T) = 0.1706 %)."""
    gain = float(speed_of_sound_m_s(21.0) / speed_of_sound_m_s(20.0)) - 1.0
    assert gain == pytest.approx(0.0017, abs=0.00005)
    assert gain == pytest.approx(math.sqrt(294.15 / 293.15) - 1.0, rel=1e-9)


def test_saturated_air_at_20c_is_0_3_to_0_4_percent_faster() -> None:
    """Water vapour (lighter molecules) raises c; saturated at 20 °C by 0.3-0.4 % (docs/METHOD.md)."""
    gain = float(speed_of_sound_m_s(20.0, 1.0) / speed_of_sound_m_s(20.0, 0.0)) - 1.0
    assert 0.003 <= gain <= 0.004


@given(temperatures_c, temperatures_c, humidities)
def test_monotonic_in_temperature(t1: float, t2: float, rh: float) -> None:
    """Warmer air (same relative humidity) is never slower."""
    lo, hi = sorted((t1, t2))
    assert float(speed_of_sound_m_s(lo, rh)) <= float(speed_of_sound_m_s(hi, rh))


@given(temperatures_c, humidities, humidities)
def test_monotonic_in_humidity(t_c: float, rh1: float, rh2: float) -> None:
    """More water vapour (lower molar mass) never slows sound."""
    lo, hi = sorted((rh1, rh2))
    assert float(speed_of_sound_m_s(t_c, lo)) <= float(speed_of_sound_m_s(t_c, hi))


@given(temperatures_c, st.floats(min_value=5e4, max_value=2e5))
def test_dry_air_does_not_depend_on_pressure(t_c: float, pressure_pa: float) -> None:
    """Ideal gas: c = sqrt(gamma R T / M) has no pressure term."""
    assert float(speed_of_sound_m_s(t_c, 0.0, pressure_pa)) == pytest.approx(
        float(speed_of_sound_m_s(t_c, 0.0)), rel=1e-12
    )


def test_lower_pressure_raises_humid_speed() -> None:
    """At fixed relative humidity, lower total pressure means more water per mole, so faster sound."""
    assert float(speed_of_sound_m_s(20.0, 1.0, 80_000.0)) > float(speed_of_sound_m_s(20.0, 1.0, 101_325.0))


@pytest.mark.parametrize(
    ("t_c", "published_pa"),
    [(0.01, 611.657), (20.0, 2339.3), (30.0, 4247.0), (40.0, 7384.9)],
)
def test_saturation_vapour_pressure_matches_iapws(t_c: float, published_pa: float) -> None:
    """Magnus form within 0.5 % of IAPWS-95 saturation pressures (Alduchov & Eskridge 1996)."""
    assert float(saturation_vapour_pressure_pa(t_c)) == pytest.approx(published_pa, rel=0.005)


def test_water_mole_fraction_is_partial_pressure_ratio() -> None:
    """Dalton: x_w = RH e_s(T) / p."""
    x = float(water_mole_fraction(20.0, 0.5, 100_000.0))
    assert x == pytest.approx(0.5 * float(saturation_vapour_pressure_pa(20.0)) / 100_000.0, rel=1e-12)


@pytest.mark.parametrize("rh", [-0.01, 1.01, 1.5, -1.0])
def test_humidity_outside_0_1_raises(rh: float) -> None:
    """Relative humidity is a fraction 0..1 (docs/FORMATS.md, "Units")."""
    with pytest.raises(EchoLocError, match="relative_humidity"):
        speed_of_sound_m_s(20.0, rh)


def test_nan_humidity_raises() -> None:
    """A NaN humidity is not a fraction in 0..1 and must not give a NaN speed of sound."""
    with pytest.raises(EchoLocError, match="relative_humidity"):
        speed_of_sound_m_s(20.0, float("nan"))


@pytest.mark.parametrize("t_c", [-KELVIN_AT_0C, -300.0, float("nan"), float("inf")])
def test_temperature_at_or_below_absolute_zero_raises(t_c: float) -> None:
    """No gas below 0 K; non-finite temperatures are rejected too."""
    with pytest.raises(EchoLocError, match="temperature_c"):
        speed_of_sound_m_s(t_c)


@pytest.mark.parametrize("pressure_pa", [0.0, -101_325.0, float("nan"), float("inf")])
def test_non_positive_pressure_raises(pressure_pa: float) -> None:
    """Pressure must be positive and finite."""
    with pytest.raises(EchoLocError, match="pressure_pa"):
        speed_of_sound_m_s(20.0, 0.5, pressure_pa)


def test_array_input_broadcasts() -> None:
    """Vector temperatures give the element-wise scalar results."""
    temps = np.array([-10.0, 0.0, 20.0, 35.0])
    assert np.allclose(speed_of_sound_m_s(temps), [float(speed_of_sound_m_s(t)) for t in temps], rtol=1e-14)


@given(distances_m, distances_m)
def test_spreading_gain_is_inverse_product(r1: float, r2: float) -> None:
    """Spherical spreading out and back: amplitude 1 / (r_tx r_rx)."""
    assert float(spreading_gain(r1, r2)) == pytest.approx(1.0 / (r1 * r2), rel=1e-12)


@given(distances_m, distances_m)
def test_spreading_gain_is_reciprocal(r1: float, r2: float) -> None:
    """Reciprocity: exchanging transmitter and receiver leaves the gain unchanged."""
    assert float(spreading_gain(r1, r2)) == float(spreading_gain(r2, r1))


def test_spreading_gain_unit_distances_and_doubling() -> None:
    """1 m out and 1 m back is gain 1 (the SNR reference); doubling both divides by 4."""
    assert float(spreading_gain(1.0, 1.0)) == 1.0
    assert float(spreading_gain(0.6, 0.6) / spreading_gain(1.2, 1.2)) == pytest.approx(4.0, rel=1e-14)
