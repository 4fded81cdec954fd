"""The air the sound travels through: speed of sound and spherical spreading.

Sources
-------
- Dry-air speed of sound of an ideal gas, ``c = c0 * sqrt(T / T0)`` with
  c0 = 331.3 m/s at T0 = 273.15 K (the report's ch. 2.4 uses the same law with
  331.4 m/s; 331.3 m/s is the widely tabulated value for dry air at 0 °C).
- Humidity: ideal-gas mixture of dry air (molar mass 28.9647 g/mol, gamma = 7/5)
  and water vapour (18.01528 g/mol, gamma = 4/3), ``c**2 = gamma_mix R T / M_mix``,
  applied as a ratio to the dry value. Saturation vapour pressure over water from
  the Magnus form of Alduchov & Eskridge (1996), J. Appl. Meteor. 35, 601-609:
  ``e_s = 610.94 Pa * exp(17.625 t / (t + 243.04))``, t in °C.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from echoloc.errors import EchoLocError

KELVIN_AT_0C = 273.15
SPEED_OF_SOUND_DRY_0C_M_S = 331.3
STANDARD_PRESSURE_PA = 101_325.0
MOLAR_MASS_DRY_AIR_KG_MOL = 28.9647e-3
MOLAR_MASS_WATER_KG_MOL = 18.01528e-3
# Molar heat capacities in units of R: diatomic dry air 7/2 and 5/2, water vapour 4 and 3.
_CP_DRY, _CV_DRY = 3.5, 2.5
_CP_WATER, _CV_WATER = 4.0, 3.0


def saturation_vapour_pressure_pa(temperature_c: ArrayLike) -> NDArray[np.float64]:
    """Saturation vapour pressure over water, Pa (Magnus form, Alduchov & Eskridge 1996)."""
    t = np.asarray(temperature_c, dtype=float)
    return np.asarray(610.94 * np.exp(17.625 * t / (t + 243.04)))


def water_mole_fraction(
    temperature_c: ArrayLike, relative_humidity: ArrayLike, pressure_pa: float = STANDARD_PRESSURE_PA
) -> NDArray[np.float64]:
    """Mole fraction of water vapour for a relative humidity in 0..1 (dimensionless)."""
    rh = np.asarray(relative_humidity, dtype=float)
    if not np.all((rh >= 0) & (rh <= 1)):
        raise EchoLocError(f"relative_humidity must be a fraction in 0..1, got {rh}")
    return np.asarray(rh * saturation_vapour_pressure_pa(temperature_c) / pressure_pa)


def speed_of_sound_m_s(
    temperature_c: ArrayLike = 20.0,
    relative_humidity: ArrayLike = 0.0,
    pressure_pa: float = STANDARD_PRESSURE_PA,
) -> NDArray[np.float64]:
    """Speed of sound in air, m/s.

    ``c = 331.3 * sqrt(1 + t / 273.15) * sqrt((gamma_mix / gamma_dry) (M_dry / M_mix))``:
    the dry ideal-gas law, times the humidity ratio of an ideal mixture of dry air
    and water vapour. Gives 331.3 m/s at 0 °C and 343.2 m/s at 20 °C in dry air;
    at 20 °C saturated air is about 0.37 % faster. Pressure enters only through the
    water mole fraction (in an ideal gas c does not depend on pressure).
    """
    t = np.asarray(temperature_c, dtype=float)
    if np.any(t <= -KELVIN_AT_0C) or not np.all(np.isfinite(t)):
        raise EchoLocError(f"temperature_c must be finite and above absolute zero, got {t}")
    if not (np.isfinite(pressure_pa) and pressure_pa > 0):
        raise EchoLocError(f"pressure_pa must be positive, got {pressure_pa}")
    dry = SPEED_OF_SOUND_DRY_0C_M_S * np.sqrt(1.0 + t / KELVIN_AT_0C)
    x_w = water_mole_fraction(t, relative_humidity, pressure_pa)
    gamma_mix = ((1 - x_w) * _CP_DRY + x_w * _CP_WATER) / ((1 - x_w) * _CV_DRY + x_w * _CV_WATER)
    molar_mass = (1 - x_w) * MOLAR_MASS_DRY_AIR_KG_MOL + x_w * MOLAR_MASS_WATER_KG_MOL
    ratio = np.sqrt((gamma_mix / (_CP_DRY / _CV_DRY)) * (MOLAR_MASS_DRY_AIR_KG_MOL / molar_mass))
    return np.asarray(dry * ratio)


def spreading_gain(distance_tx_m: ArrayLike, distance_rx_m: ArrayLike) -> NDArray[np.float64]:
    """Amplitude factor of a point-reflector echo, 1 / (r_tx * r_rx) (1/m²).

    Spherical spreading on the way out and on the way back: pressure falls as 1/r
    from the transmitter to the reflector and again as 1/r from the reflector
    (a point re-radiator) to the receiver.
    """
    r1 = np.asarray(distance_tx_m, dtype=float)
    r2 = np.asarray(distance_rx_m, dtype=float)
    return np.asarray(1.0 / (r1 * r2))
