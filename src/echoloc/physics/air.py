"""The air the sound travels through: speed of sound, absorption, spreading, impedance.

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
- The standard full model of the speed of sound: O. Cramer (1993), "The variation of
  the specific heat ratio and the speed of sound in air with temperature, pressure,
  humidity, and CO2 concentration", J. Acoust. Soc. Am. 93(5), 2510-2516, doi:10.1121/1.405827
  (Eq. 15 with the coefficients of its Table III; water mole fraction from its Appendix,
  Eqs. A1-A3, which take the enhancement factor and saturation vapour pressure of
  P. Giacomo (1982), Metrologia 18, 33-40, the CIPM-81 equation for moist air).
- Atmospheric absorption: ISO 9613-1:1993, "Acoustics - Attenuation of sound during
  propagation outdoors - Part 1: Calculation of the absorption of sound by the
  atmosphere", Eqs. (3)-(5), with the molar concentration of water vapour from its
  Annex B.
- Density of moist air: the CIPM-2007 equation, A. Picard, R. S. Davis, M. Gläser and
  K. Fujii (2008), Metrologia 45, 149-155, Eq. (1), taken as an ideal-gas mixture
  (compressibility Z = 1, which is within 0.05 % at room conditions).
- Impedance, normal-incidence reflection and transmission, levels: L. E. Kinsler,
  A. R. Frey, A. B. Coppens and J. V. Sanders, *Fundamentals of Acoustics*, 4th ed.
  (Wiley, 2000), ch. 5 (specific acoustic impedance, intensity level, sound pressure
  level) and ch. 6 (transmission from one fluid to another, normal incidence);
  reference values of the levels from ISO 1683 (1 pW/m², 20 µPa).
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


# ---------------------------------------------------------------------------------------
# Input checks shared by the functions below: one EchoLocError, one line, naming the
# first offending value (an array may be large; its first bad element is what matters).


def _float_array(name: str, value: ArrayLike) -> NDArray[np.float64]:
    """``value`` as a float array, or EchoLocError naming ``name`` if it is not numeric."""
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise EchoLocError(f"{name} must be a number or an array of numbers, got {value!r}") from exc


def _check(name: str, values: NDArray[np.float64], ok: NDArray[np.bool_], requirement: str) -> None:
    """Raise EchoLocError for the first element of ``values`` where ``ok`` is False."""
    if not np.all(ok):
        bad = values[np.logical_not(ok)].flat[0] if values.ndim else values
        raise EchoLocError(f"{name} must be {requirement}, got {float(bad)}")


def _positive(name: str, value: ArrayLike) -> NDArray[np.float64]:
    a = _float_array(name, value)
    _check(name, a, np.isfinite(a) & (a > 0), "finite and > 0")
    return a


def _non_negative(name: str, value: ArrayLike) -> NDArray[np.float64]:
    a = _float_array(name, value)
    _check(name, a, np.isfinite(a) & (a >= 0), "finite and >= 0")
    return a


def _fraction(name: str, value: ArrayLike) -> NDArray[np.float64]:
    a = _float_array(name, value)
    _check(name, a, (a >= 0) & (a <= 1), "a fraction in 0..1")
    return a


def _celsius(name: str, value: ArrayLike) -> NDArray[np.float64]:
    a = _float_array(name, value)
    _check(name, a, np.isfinite(a) & (a > -KELVIN_AT_0C), "finite and above absolute zero (-273.15 °C)")
    return a


# ---------------------------------------------------------------------------------------
# The standard full model of the speed of sound: Cramer (1993).

CO2_MOLE_FRACTION_CRAMER = 0.000314
"""CO2 mole fraction of the standard air of Cramer (1993), 314 ppm (dimensionless)."""

# Cramer (1993), Table III: c = a0 + a1 t + a2 t^2 + (a3 + a4 t + a5 t^2) x_w
#   + (a6 + a7 t + a8 t^2) p + (a9 + a10 t + a11 t^2) x_c + a12 x_w^2 + a13 p^2
#   + a14 x_c^2 + a15 x_w p x_c, with t in °C, p in Pa, mole fractions x_w, x_c.
# Cross-checked against four independent transcriptions: pyfar (constants/speed_of_sound.py),
# gorbatschow/Sonar.m (sound_speed_air_cramer.m), the notes of the USP "Speed of Sound
# Calculator" applet (gsd.ime.usp.br) and a Mitsuba acoustic-rendering plugin.
_CRAMER_A = (
    331.5024,
    0.603055,
    -0.000528,
    51.471935,
    0.1495874,
    -0.000782,
    -1.82e-7,
    3.73e-8,
    -2.93e-10,
    -85.20931,
    -0.228525,
    5.91e-5,
    -2.835149,
    -2.15e-13,
    29.179762,
    0.000486,
)
# Range over which Cramer's interpolating equation and its Appendix are stated valid.
CRAMER_TEMPERATURE_RANGE_C = (0.0, 30.0)
CRAMER_PRESSURE_RANGE_PA = (60_000.0, 110_000.0)
CRAMER_MAX_WATER_MOLE_FRACTION = 0.06
CRAMER_MAX_CO2_MOLE_FRACTION = 0.01


def saturation_vapour_pressure_giacomo_pa(temperature_c: ArrayLike) -> NDArray[np.float64]:
    """Saturation vapour pressure of water in moist air, Pa (CIPM-81, as Cramer uses it).

    ``p_sv = exp(1.2811805e-5 T^2 - 1.9509874e-2 T + 34.04926034 - 6.3536311e3 / T)`` Pa
    with T in kelvin: Cramer (1993), Appendix, Eq. (A3), from Giacomo (1982),
    Metrologia 18, 33-40. (Davis (1992), Metrologia 29, 67-70, later refitted these
    coefficients; the two differ by about 0.04 % of p_sv at 20 °C, i.e. by less than
    0.001 m/s in the speed of sound.)
    """
    t_k = _celsius("temperature_c", temperature_c) + KELVIN_AT_0C
    return np.asarray(np.exp(1.2811805e-5 * t_k**2 - 1.9509874e-2 * t_k + 34.04926034 - 6.3536311e3 / t_k))


def enhancement_factor(temperature_c: ArrayLike, pressure_pa: ArrayLike) -> NDArray[np.float64]:
    """Enhancement factor of water vapour in air (dimensionless), CIPM-81.

    ``f = 1.00062 + 3.14e-8 p + 5.6e-7 t^2`` with p in Pa and t in °C (not kelvin):
    Cramer (1993), Appendix, Eq. (A2), from Giacomo (1982), Metrologia 18, 33-40.
    """
    t = _celsius("temperature_c", temperature_c)
    p = _positive("pressure_pa", pressure_pa)
    return np.asarray(1.00062 + 3.14e-8 * p + 5.6e-7 * t**2)


def speed_of_sound_cramer_m_s(
    temperature_c: ArrayLike,
    relative_humidity: ArrayLike,
    pressure_pa: ArrayLike = STANDARD_PRESSURE_PA,
    co2_mole_fraction: ArrayLike = CO2_MOLE_FRACTION_CRAMER,
) -> NDArray[np.float64]:
    """Zero-frequency speed of sound in humid air, m/s, after Cramer (1993).

    ``c = a0 + a1 t + a2 t^2 + (a3 + a4 t + a5 t^2) x_w + (a6 + a7 t + a8 t^2) p
    + (a9 + a10 t + a11 t^2) x_c + a12 x_w^2 + a13 p^2 + a14 x_c^2 + a15 x_w p x_c``,
    Cramer (1993), J. Acoust. Soc. Am. 93, 2510-2516, Eq. (15) with the coefficients
    of Table III (t in °C, p in Pa). The water-vapour mole fraction is
    ``x_w = h f(p, t) p_sv(t) / p`` (Appendix, Eq. A1) with
    :func:`enhancement_factor` and :func:`saturation_vapour_pressure_giacomo_pa`.
    Stated uncertainty: below 300 ppm. Valid from 0 to 30 °C, 60 to 110 kPa, x_w <= 0.06
    and x_c <= 0.01; outside that use :func:`speed_of_sound_m_s`.

    Parameters
    ----------
    temperature_c : array_like
        Air temperature, °C, 0..30.
    relative_humidity : array_like
        Relative humidity as a fraction, 0..1.
    pressure_pa : array_like, optional
        Static pressure, Pa, 60 000..110 000 (default 101 325 Pa).
    co2_mole_fraction : array_like, optional
        CO2 mole fraction, 0..0.01 (default 314 ppm, Cramer's standard air; today's
        outdoor air is about 420 ppm, which lowers c by about 0.01 m/s).

    Returns
    -------
    ndarray
        Speed of sound, m/s, broadcast over all arguments.

    Raises
    ------
    EchoLocError
        A value is NaN, outside its physical range or outside Cramer's validity range.
    """
    t = _celsius("temperature_c", temperature_c)
    h = _fraction("relative_humidity", relative_humidity)
    p = _positive("pressure_pa", pressure_pa)
    x_c = _fraction("co2_mole_fraction", co2_mole_fraction)
    t_lo, t_hi = CRAMER_TEMPERATURE_RANGE_C
    _check("temperature_c", t, (t >= t_lo) & (t <= t_hi), f"in {t_lo:g}..{t_hi:g} °C for Cramer's equation")
    p_lo, p_hi = CRAMER_PRESSURE_RANGE_PA
    _check("pressure_pa", p, (p >= p_lo) & (p <= p_hi), f"in {p_lo:g}..{p_hi:g} Pa for Cramer's equation")
    _check(
        "co2_mole_fraction",
        x_c,
        x_c <= CRAMER_MAX_CO2_MOLE_FRACTION,
        f"at most {CRAMER_MAX_CO2_MOLE_FRACTION:g} for Cramer's equation",
    )
    x_w = h * enhancement_factor(t, p) * saturation_vapour_pressure_giacomo_pa(t) / p
    _check(
        "relative_humidity",
        h * np.ones_like(x_w),
        x_w <= CRAMER_MAX_WATER_MOLE_FRACTION,
        f"low enough for a water mole fraction <= {CRAMER_MAX_WATER_MOLE_FRACTION:g} (Cramer's range)",
    )
    a = _CRAMER_A
    c = (
        a[0]
        + a[1] * t
        + a[2] * t**2
        + (a[3] + a[4] * t + a[5] * t**2) * x_w
        + (a[6] + a[7] * t + a[8] * t**2) * p
        + (a[9] + a[10] * t + a[11] * t**2) * x_c
        + a[12] * x_w**2
        + a[13] * p**2
        + a[14] * x_c**2
        + a[15] * x_w * p * x_c
    )
    return np.asarray(c, dtype=np.float64)


# ---------------------------------------------------------------------------------------
# Atmospheric absorption: ISO 9613-1:1993.

ISO_REFERENCE_TEMPERATURE_K = 293.15
"""T0 of ISO 9613-1: reference air temperature, 20 °C, in kelvin."""
ISO_TRIPLE_POINT_K = 273.16
"""T01 of ISO 9613-1 (Annex B): triple-point isotherm temperature of water, K."""
_ISO_REFERENCE_PRESSURE_KPA = 101.325  # p_r of ISO 9613-1


def _iso_water_vapour_percent(
    temperature_k: NDArray[np.float64],
    relative_humidity: NDArray[np.float64],
    pressure_ratio: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Molar concentration of water vapour h, % (ISO 9613-1, Annex B).

    ``h = h_r (p_sat / p_r) / (p_a / p_r)`` with ``p_sat / p_r = 10**C`` and
    ``C = -6.8346 (T01 / T)**1.261 + 4.6151``; h_r in percent.
    """
    exponent = -6.8346 * (ISO_TRIPLE_POINT_K / temperature_k) ** 1.261 + 4.6151
    return np.asarray(100.0 * relative_humidity * 10.0**exponent / pressure_ratio)


def absorption_db_per_m(
    frequency_hz: ArrayLike,
    temperature_c: ArrayLike = 20.0,
    relative_humidity: ArrayLike = 0.5,
    pressure_pa: ArrayLike = STANDARD_PRESSURE_PA,
) -> NDArray[np.float64]:
    """Pure-tone atmospheric absorption coefficient alpha, dB/m (ISO 9613-1:1993).

    ISO 9613-1, Eq. (5)::

        alpha = 8.686 f^2 [ 1.84e-11 (p_a/p_r)^-1 (T/T0)^(1/2)
                + (T/T0)^(-5/2) ( 0.01275 exp(-2239.1/T) / (f_rO + f^2/f_rO)
                                 + 0.1068 exp(-3352.0/T) / (f_rN + f^2/f_rN) ) ]

    with the relaxation frequencies of oxygen and nitrogen, Eqs. (3) and (4)::

        f_rO = (p_a/p_r) (24 + 4.04e4 h (0.02 + h) / (0.391 + h))
        f_rN = (p_a/p_r) (T/T0)^(-1/2) (9 + 280 h exp(-4.170 ((T/T0)^(-1/3) - 1)))

    and h the molar concentration of water vapour in percent from Annex B (see
    ``_iso_water_vapour_percent``, T01 = 273.16 K). T0 = 293.15 K, p_r = 101.325 kPa.
    The standard states +-10 % accuracy for 0.05 < h < 5 %, 253 K < T < 323 K,
    p_a < 200 kPa and 4e-4 < f/p_a < 10 Hz/Pa (up to about 1 MHz at one atmosphere,
    so the airborne ultrasound of a robot's sonar is inside it); the formula is
    evaluated, not refused, outside that range.

    Parameters
    ----------
    frequency_hz : array_like
        Frequency of the tone, Hz, >= 0.
    temperature_c : array_like, optional
        Air temperature, °C (default 20 °C).
    relative_humidity : array_like, optional
        Relative humidity as a fraction, 0..1 (default 0.5).
    pressure_pa : array_like, optional
        Ambient pressure, Pa, > 0 (default 101 325 Pa).

    Returns
    -------
    ndarray
        Attenuation coefficient, dB/m (of sound pressure level), broadcast over all
        arguments.

    Raises
    ------
    EchoLocError
        Negative or non-finite frequency, humidity outside 0..1 (or NaN), temperature
        at or below absolute zero, pressure <= 0 or non-finite.
    """
    f = _non_negative("frequency_hz", frequency_hz)
    t_k = _celsius("temperature_c", temperature_c) + KELVIN_AT_0C
    h_r = _fraction("relative_humidity", relative_humidity)
    p_ratio = _positive("pressure_pa", pressure_pa) / (_ISO_REFERENCE_PRESSURE_KPA * 1e3)
    h = _iso_water_vapour_percent(t_k, h_r, p_ratio)
    t_ratio = t_k / ISO_REFERENCE_TEMPERATURE_K
    f_ro = p_ratio * (24.0 + 4.04e4 * h * (0.02 + h) / (0.391 + h))
    f_rn = p_ratio * t_ratio**-0.5 * (9.0 + 280.0 * h * np.exp(-4.170 * (t_ratio ** (-1.0 / 3.0) - 1.0)))
    f2 = f**2
    classical = 1.84e-11 / p_ratio * t_ratio**0.5
    oxygen = 0.01275 * np.exp(-2239.1 / t_k) / (f_ro + f2 / f_ro)
    nitrogen = 0.1068 * np.exp(-3352.0 / t_k) / (f_rn + f2 / f_rn)
    alpha = 8.686 * f2 * (classical + t_ratio**-2.5 * (oxygen + nitrogen))
    return np.asarray(alpha, dtype=np.float64)


def absorption_gain(
    distance_m: ArrayLike,
    frequency_hz: ArrayLike,
    temperature_c: ArrayLike = 20.0,
    relative_humidity: ArrayLike = 0.5,
    pressure_pa: ArrayLike = STANDARD_PRESSURE_PA,
) -> NDArray[np.float64]:
    """Amplitude factor of atmospheric absorption over a path, ``10**(-alpha d / 20)``.

    alpha from :func:`absorption_db_per_m` (ISO 9613-1, Eq. 5); the attenuation over a
    path of length d is ``alpha d`` dB of sound pressure level (ISO 9613-1, clause 5),
    so the pressure amplitude is multiplied by ``10**(-alpha d / 20)``. Multiply by
    :func:`spreading_gain` for the whole propagation loss of a point-reflector echo
    (use the total path, out and back, as d).

    Parameters
    ----------
    distance_m : array_like
        Path length, m, >= 0.
    frequency_hz, temperature_c, relative_humidity, pressure_pa : array_like
        As in :func:`absorption_db_per_m`.

    Returns
    -------
    ndarray
        Pressure-amplitude factor in (0, 1], broadcast over all arguments.
    """
    d = _non_negative("distance_m", distance_m)
    alpha = absorption_db_per_m(frequency_hz, temperature_c, relative_humidity, pressure_pa)
    return np.asarray(10.0 ** (-alpha * d / 20.0), dtype=np.float64)


# ---------------------------------------------------------------------------------------
# Density, impedance, reflection and transmission, levels.

GAS_CONSTANT_J_MOL_K = 8.314462618
"""Molar gas constant R, J/(mol K) (CODATA 2018, exact)."""
REFERENCE_INTENSITY_W_M2 = 1e-12
"""Reference sound intensity for the intensity level, W/m² (ISO 1683)."""
REFERENCE_PRESSURE_PA = 20e-6
"""Reference rms sound pressure in air for the sound pressure level, Pa (ISO 1683)."""


def air_density_kg_m3(
    temperature_c: ArrayLike,
    relative_humidity: ArrayLike = 0.0,
    pressure_pa: ArrayLike = STANDARD_PRESSURE_PA,
) -> NDArray[np.float64]:
    """Density of moist air as an ideal-gas mixture, kg/m³.

    ``rho = p M_a / (R T) (1 - x_w (1 - M_w / M_a))``: the CIPM-2007 equation (Picard
    et al. 2008, Metrologia 45, 149-155, Eq. 1) with compressibility Z = 1, molar
    masses M_a = 28.9647 g/mol (dry air) and M_w = 18.01528 g/mol (water), R from
    CODATA 2018 and x_w = RH e_s(t) / p (Dalton, with the Magnus e_s of
    :func:`saturation_vapour_pressure_pa`, as in :func:`water_mole_fraction`). Gives
    1.2250 kg/m³ for dry air at 15 °C and 101 325 Pa (the ISO 2533 standard
    atmosphere at sea level) and 1.2041 kg/m³ at 20 °C.

    Parameters
    ----------
    temperature_c : array_like
        Air temperature, °C.
    relative_humidity : array_like, optional
        Relative humidity as a fraction, 0..1 (default dry air).
    pressure_pa : array_like, optional
        Static pressure, Pa (default 101 325 Pa).

    Returns
    -------
    ndarray
        Density, kg/m³, broadcast over all arguments.
    """
    t = _celsius("temperature_c", temperature_c)
    h = _fraction("relative_humidity", relative_humidity)
    p = _positive("pressure_pa", pressure_pa)
    x_w = h * saturation_vapour_pressure_pa(t) / p
    molar_mass = (1.0 - x_w) * MOLAR_MASS_DRY_AIR_KG_MOL + x_w * MOLAR_MASS_WATER_KG_MOL
    return np.asarray(p * molar_mass / (GAS_CONSTANT_J_MOL_K * (t + KELVIN_AT_0C)), dtype=np.float64)


def characteristic_impedance_rayl(density_kg_m3: ArrayLike, speed_m_s: ArrayLike) -> NDArray[np.float64]:
    """Characteristic (specific acoustic) impedance of a medium, ``Z = rho c``, rayl (Pa s/m).

    Kinsler et al., *Fundamentals of Acoustics*, 4th ed., ch. 5: for a plane wave the
    ratio of pressure to particle velocity is rho0 c. Air at 20 °C: about 413 rayl.
    """
    rho = _positive("density_kg_m3", density_kg_m3)
    c = _positive("speed_m_s", speed_m_s)
    return np.asarray(rho * c, dtype=np.float64)


def _impedances(z1: ArrayLike, z2: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    return _positive("z1", z1), _positive("z2", z2)


def reflection_coefficient(z1: ArrayLike, z2: ArrayLike) -> NDArray[np.float64]:
    """Pressure reflection coefficient at normal incidence, ``R = (Z2 - Z1) / (Z2 + Z1)``.

    A plane wave in medium 1 (impedance z1, rayl) meets medium 2 (z2) at normal
    incidence: Kinsler et al., 4th ed., ch. 6 (normal incidence). R -> +1 at a rigid (much
    harder) medium, -1 at a pressure-release one; dimensionless, in (-1, 1).
    """
    a, b = _impedances(z1, z2)
    return np.asarray((b - a) / (b + a), dtype=np.float64)


def transmission_coefficient(z1: ArrayLike, z2: ArrayLike) -> NDArray[np.float64]:
    """Pressure transmission coefficient at normal incidence, ``T = 2 Z2 / (Z1 + Z2)``.

    Kinsler et al., 4th ed., ch. 6; ``T = 1 + R`` (continuity of pressure).
    Dimensionless, in (0, 2).
    """
    a, b = _impedances(z1, z2)
    return np.asarray(2.0 * b / (a + b), dtype=np.float64)


def intensity_reflection_coefficient(z1: ArrayLike, z2: ArrayLike) -> NDArray[np.float64]:
    """Intensity (power) reflection coefficient at normal incidence, ``R_I = R**2``.

    Kinsler et al., 4th ed., ch. 6: ``((Z2 - Z1) / (Z2 + Z1))**2``.
    """
    return np.asarray(reflection_coefficient(z1, z2) ** 2, dtype=np.float64)


def intensity_transmission_coefficient(z1: ArrayLike, z2: ArrayLike) -> NDArray[np.float64]:
    """Intensity (power) transmission coefficient at normal incidence, ``4 Z1 Z2 / (Z1 + Z2)**2``.

    Kinsler et al., 4th ed., ch. 6: ``T_I = (Z1 / Z2) T**2``; with
    :func:`intensity_reflection_coefficient` it conserves energy, ``R_I + T_I = 1``.
    """
    a, b = _impedances(z1, z2)
    return np.asarray(4.0 * a * b / (a + b) ** 2, dtype=np.float64)


def intensity_level_db(
    intensity_w_m2: ArrayLike, reference_w_m2: ArrayLike = REFERENCE_INTENSITY_W_M2
) -> NDArray[np.float64]:
    """Sound intensity level, ``10 log10(I / I_ref)`` dB re 1 pW/m² by default.

    Kinsler et al., 4th ed., ch. 5; reference 1e-12 W/m² (ISO 1683). The
    intensity must be > 0 (silence has no finite level).
    """
    i = _positive("intensity_w_m2", intensity_w_m2)
    ref = _positive("reference_w_m2", reference_w_m2)
    return np.asarray(10.0 * np.log10(i / ref), dtype=np.float64)


def sound_pressure_level_db(
    pressure_pa: ArrayLike, reference_pa: ArrayLike = REFERENCE_PRESSURE_PA
) -> NDArray[np.float64]:
    """Sound pressure level, ``20 log10(p_rms / p_ref)`` dB re 20 µPa by default.

    Kinsler et al., 4th ed., ch. 5; reference 20 µPa for air (ISO 1683). ``pressure_pa``
    is an rms (or peak, with a peak reference) pressure and must be > 0. For a plane
    wave ``I = p**2 / (rho c)``, so the intensity level is lower by
    ``10 log10(rho c / 400 rayl)``: 0.14 dB in air at 20 °C, zero where rho c = 400 rayl.
    """
    p = _positive("pressure_pa", pressure_pa)
    ref = _positive("reference_pa", reference_pa)
    return np.asarray(20.0 * np.log10(p / ref), dtype=np.float64)
