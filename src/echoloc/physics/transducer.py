"""Transducers: piston directivity, beam widths, near field, band-pass response, arrays.

Everything here is a pure function of plain values, or a small frozen value
(:class:`PistonBeam`, :class:`Transducer`). Angles are in radians unless the name
says ``_deg``; frequencies in Hz, lengths in m, speeds in m/s.

Sources
-------
- [K] L. E. Kinsler, A. R. Frey, A. B. Coppens, J. V. Sanders, *Fundamentals of
  Acoustics*, 4th ed., Wiley 2000, §7.4 "Radiation from a baffled circular piston":
  far-field directivity ``H(θ) = 2 J1(ka sin θ) / (ka sin θ)``, first null at
  ``ka sin θ = 3.83`` (``sin θ = 0.61 λ/a``), on-axis pressure
  ``2 ρ0 c U0 |sin(k (sqrt(r² + a²) - r) / 2)|``, Rayleigh distance ``π a²/λ``.
- [R] the reference report (docs/METHOD.md, References): ch. 2.4.2.1
  eq. (2.11) near-field length ``r²/λ``; ch. 2.4.2.5 eqs. (2.19)-(2.20), the piston
  model and the beam widths "x = 1.62" (-3 dB) and "0.61 λ/r" (first null);
  ch. 2.4.2.6 the Murata MA40L1S/MA40L2T pair (40 kHz, ±2 kHz, 30° at -3 dB) and
  the Polaroid electrostatic transducer; ch. 2.4.4 "A Polaroid transducer ... has
  approximately a beam width of 15°"; ch. 2.4.4.1 eqs. (2.21)-(2.26), line arrays,
  steering and shading; ch. 2.4.4.2 the number of transducers ``N_T = θ/α``;
  ch. 2.4.4.6 eqs. (2.27)-(2.30), the two-way Doppler shift; appendix A, the
  Polaroid 607281 data sheet (foil diameter 1.513 in = 38.4 mm).
- [O] S. J. Orfanidis, *Introduction to Signal Processing*, Prentice Hall 1996,
  §11.3: the second-order peak (resonator) filter by the bilinear transform, with
  exact centre frequency and exact -3 dB bandwidth; this is ``scipy.signal.iirpeak``.
- [VT] H. L. Van Trees, *Optimum Array Processing*, Wiley 2002, ch. 2-3: the
  uniform linear array beam pattern, grating lobes, Dolph-Chebyshev weighting
  (C. L. Dolph, Proc. IRE 34 (1946) 335-348).

What the report's beam-width numbers mean
-----------------------------------------
Both numbers come from ``x = ka sin θ`` (k = 2π/λ, a the piston *radius*):

- "x = 1.62" is the value of the argument at the -3 dB (half-power) point of the
  pressure pattern, ``2 J1(x)/x = 1/√2``; the report gets it by keeping three terms
  of the series of J1 (``1 - x²/8 + x⁴/192``), which gives 1.6223. The exact root
  is 1.61634 (:data:`X_MINUS_3DB`), so ``sin θ_-3dB = 1.616/(ka) = 0.2572 λ/a``.
  Read as ``sin θ = 1.62 λ/a`` (as the scanned eq. (2.19) looks) it would be 2π
  too large; 1.62 is a value of ka sin θ, not a multiple of λ/a.
- "0.61 λ/r" is the first null (edge of the main lobe), ``J1(x) = 0`` at
  x = 3.83171 (:data:`X_FIRST_NULL`), ``sin θ_0 = 3.8317/(2π) λ/a = 0.60983 λ/a``:
  the Airy value, ``1.22 λ/D`` with the diameter D.

Both are half-angles from the axis; the full beam width is twice that.

Response model
--------------
One transducer (transmitter or receiver) is modelled as a second-order resonator,
``H(f) = 1 / (1 + j Q (f/f0 - f0/f))``: the velocity of a damped mass-spring (the
motional branch of the Butterworth-Van Dyke equivalent circuit of a piezo; for the
electrostatic foil, tension and air-gap stiffness against the foil mass, heavily
damped by the grooved backplate). Its gain is 1 at f0, its -3 dB points are
``f0 (sqrt(1 + 1/(4Q²)) ∓ 1/(2Q))``, exactly ``f0/Q`` apart, and its group delay at
f0 is ``2Q/ω0 = 1/(π B)``. A transmit-receive pair applies it twice (``passes=2``).
For sampled signals the same resonator is the bilinear-transform biquad of [O]
(same centre, same -3 dB bandwidth, gain 1 at f0, causal); :func:`impulse_response`
and :func:`apply_response` use it. The directivity is not part of ``H``: off axis
multiply by :func:`directivity` at each frequency.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.fft
import scipy.signal
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import brentq
from scipy.special import j1, jn_zeros

from echoloc.errors import EchoLocError

SPEED_OF_SOUND_20C_M_S = 343.2
"""Default speed of sound: dry air at 20 °C (``echoloc.physics.air.speed_of_sound_m_s(20)`` = 343.21)."""

HALF_POWER = 1.0 / math.sqrt(2.0)
"""Pressure ratio of the -3 dB (half-power) point, 1/√2."""

X_FIRST_NULL = float(jn_zeros(1, 1)[0])
"""First zero of J1, 3.831706: ``ka sin θ`` at the first null of a piston [K §7.4]."""


def _piston_x(x: float) -> float:
    """``2 J1(x)/x`` for a scalar x > 0."""
    return float(2.0 * j1(x) / x)


def _x_at_level(pressure_ratio: float) -> float:
    """The x in (0, 3.8317) where ``2 J1(x)/x = pressure_ratio`` (monotonic there)."""
    if not 0.0 < pressure_ratio < 1.0:
        raise EchoLocError(f"pressure_ratio must lie strictly between 0 and 1, got {pressure_ratio}")
    return float(brentq(lambda x: _piston_x(x) - pressure_ratio, 1e-9, X_FIRST_NULL, xtol=1e-14))


X_MINUS_3DB = _x_at_level(HALF_POWER)
"""Root of ``2 J1(x)/x = 1/√2``: x = 1.616340, the -3 dB point of a piston (brentq)."""

REPORT_X_MINUS_3DB = 1.62
"""The report's -3 dB value of ``ka sin θ`` (eq. 2.19; three-term series of J1)."""

REPORT_NULL_COEFFICIENT = 0.61
"""The report's first-null coefficient: ``sin θ = 0.61 λ/r`` (eq. 2.20)."""


# --------------------------------------------------------------------------- checks


def _positive(value: float, name: str) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0.0):
        raise EchoLocError(f"{name} must be a positive finite number, got {value}")
    return v


def _wavenumber(frequency_hz: float, speed_of_sound_m_s: float) -> float:
    f = _positive(frequency_hz, "frequency_hz")
    c = _positive(speed_of_sound_m_s, "speed_of_sound_m_s")
    return 2.0 * math.pi * f / c


def _asin_or_nan(s: float) -> float:
    """arcsin(s) for 0 <= s <= 1, NaN when s > 1 (the angle is not in the front half-space)."""
    return math.asin(s) if s <= 1.0 else math.nan


# ------------------------------------------------------------------- piston physics


def piston_directivity(
    theta_rad: ArrayLike,
    radius_m: float,
    frequency_hz: float,
    speed_of_sound_m_s: float = SPEED_OF_SOUND_20C_M_S,
) -> NDArray[np.float64]:
    """Far-field pressure directivity of a baffled circular piston, 1 on the axis.

    ``D(θ) = 2 J1(x) / x`` with ``x = k a sin θ``, ``k = 2π f / c`` [K §7.4; R eq. 2.19].

    Parameters
    ----------
    theta_rad : array_like
        Angle from the piston axis, rad.
    radius_m : float
        Piston radius a, m.
    frequency_hz : float
        Frequency, Hz.
    speed_of_sound_m_s : float
        Speed of sound, m/s.

    Returns
    -------
    numpy.ndarray
        The signed pressure ratio (negative in the odd side lobes; take ``abs`` for
        the magnitude). Exactly 1 at θ = 0. Zero behind the baffle (``cos θ < 0``):
        the infinite-baffle model radiates into the front half-space only.
    """
    a = _positive(radius_m, "radius_m")
    k = _wavenumber(frequency_hz, speed_of_sound_m_s)
    theta = np.asarray(theta_rad, dtype=float)
    x = k * a * np.sin(theta)
    small = np.abs(x) < 1e-8
    safe = np.where(small, 1.0, x)
    # Series 1 - x²/8 below 1e-8: exact to double precision, and exactly 1 at θ = 0.
    d = np.where(small, 1.0 - x * x / 8.0, 2.0 * j1(safe) / safe)
    return np.asarray(np.where(np.cos(theta) < 0.0, 0.0, d), dtype=np.float64)


def piston_half_angle_rad(
    radius_m: float,
    frequency_hz: float,
    speed_of_sound_m_s: float = SPEED_OF_SOUND_20C_M_S,
    *,
    pressure_ratio: float = HALF_POWER,
) -> float:
    """Angle from the axis where the piston pattern falls to ``pressure_ratio``, rad.

    Solves ``2 J1(x)/x = pressure_ratio`` for x in the main lobe by root finding
    (``scipy.optimize.brentq``), then ``sin θ = x / (ka)`` [K §7.4]. The default is
    the one-way -3 dB point (x = 1.6163). For the pulse-echo pattern ``D²`` of one
    transducer used to send and receive, its -3 dB point is
    ``pressure_ratio = 2**-0.25``; the one-way -6 dB point is ``0.5``.

    Returns NaN when ``ka`` is too small for the pattern to fall that far before
    90° (the beam is then wider than the front half-space).
    """
    a = _positive(radius_m, "radius_m")
    ka = _wavenumber(frequency_hz, speed_of_sound_m_s) * a
    return _asin_or_nan(_x_at_level(pressure_ratio) / ka)


@dataclass(frozen=True)
class PistonBeam:
    """Beam widths of a baffled circular piston, exact and as the report approximates them.

    Half-angles are measured from the axis; full angles are twice the half-angles.
    An angle that does not exist in the front half-space (ka too small) is NaN.

    Attributes
    ----------
    ka : float
        k times the radius (dimensionless).
    half_angle_3db_rad, full_angle_3db_rad : float
        Exact -3 dB (half-power, ``D = 1/√2``) angles: ``sin θ = 1.61634 / ka``.
    half_angle_null_rad, full_angle_null_rad : float
        Exact first null, ``J1(ka sin θ) = 0``: ``sin θ = 3.83171 / ka = 0.60983 λ/a``.
    report_half_angle_3db_rad : float
        The report's eq. (2.19): ``sin θ = 1.62 / ka`` (x = 1.62 from a three-term series).
    report_half_angle_null_rad : float
        The report's eq. (2.20): ``sin θ = 0.61 λ / a``.
    """

    radius_m: float
    frequency_hz: float
    speed_of_sound_m_s: float
    wavelength_m: float
    ka: float
    half_angle_3db_rad: float
    full_angle_3db_rad: float
    half_angle_null_rad: float
    full_angle_null_rad: float
    report_half_angle_3db_rad: float
    report_half_angle_null_rad: float

    @property
    def full_angle_3db_deg(self) -> float:
        """Exact -3 dB full beam width, degrees."""
        return math.degrees(self.full_angle_3db_rad)

    @property
    def full_angle_null_deg(self) -> float:
        """Exact full angle between the first nulls, degrees."""
        return math.degrees(self.full_angle_null_rad)


def piston_beam_angles(
    radius_m: float,
    frequency_hz: float,
    speed_of_sound_m_s: float = SPEED_OF_SOUND_20C_M_S,
) -> PistonBeam:
    """Exact -3 dB and first-null beam angles of a piston, with the report's approximations.

    -3 dB: root of ``2 J1(x)/x = 1/√2`` by brentq (x = 1.61634); first null: first
    zero of J1 (x = 3.83171, ``scipy.special.jn_zeros``); ``sin θ = x/(ka)`` [K §7.4].
    Report: ``sin θ = 1.62/(ka)`` (eq. 2.19) and ``sin θ = 0.61 λ/a`` (eq. 2.20).
    """
    a = _positive(radius_m, "radius_m")
    c = _positive(speed_of_sound_m_s, "speed_of_sound_m_s")
    k = _wavenumber(frequency_hz, c)
    ka = k * a
    wavelength = c / float(frequency_hz)
    half_3db = _asin_or_nan(X_MINUS_3DB / ka)
    half_null = _asin_or_nan(X_FIRST_NULL / ka)
    return PistonBeam(
        radius_m=a,
        frequency_hz=float(frequency_hz),
        speed_of_sound_m_s=c,
        wavelength_m=wavelength,
        ka=ka,
        half_angle_3db_rad=half_3db,
        full_angle_3db_rad=2.0 * half_3db,
        half_angle_null_rad=half_null,
        full_angle_null_rad=2.0 * half_null,
        report_half_angle_3db_rad=_asin_or_nan(REPORT_X_MINUS_3DB / ka),
        report_half_angle_null_rad=_asin_or_nan(REPORT_NULL_COEFFICIENT * wavelength / a),
    )


def radius_for_beam_width(
    full_angle_deg: float,
    frequency_hz: float,
    speed_of_sound_m_s: float = SPEED_OF_SOUND_20C_M_S,
    *,
    pressure_ratio: float = HALF_POWER,
) -> float:
    """Piston radius whose full beam width at ``pressure_ratio`` (default -3 dB) is given, m.

    Inverse of :func:`piston_half_angle_rad`: ``a = x / (k sin(full/2))`` with x the
    root of ``2 J1(x)/x = pressure_ratio`` [K §7.4].
    """
    full = float(full_angle_deg)
    if not (math.isfinite(full) and 0.0 < full < 180.0):
        raise EchoLocError(f"full_angle_deg must lie strictly between 0 and 180, got {full_angle_deg}")
    k = _wavenumber(frequency_hz, speed_of_sound_m_s)
    return _x_at_level(pressure_ratio) / (k * math.sin(math.radians(full) / 2.0))


def near_field_length_m(
    radius_m: float,
    frequency_hz: float,
    speed_of_sound_m_s: float = SPEED_OF_SOUND_20C_M_S,
    *,
    exact: bool = False,
) -> float:
    """Length of a piston's near field (Fresnel zone), m.

    ``exact=False``: ``a²/λ``, the report's eq. (2.11) (the usual near-field length
    N = D²/(4λ) of ultrasonic testing). ``exact=True``: the distance of the last
    maximum of the on-axis pressure, ``(a² - λ²/4)/λ``, where
    ``sqrt(z² + a²) - z = λ/2`` in :func:`piston_on_axis_pressure` [K §7.4]. When
    ``a <= λ/2`` the axial pressure has no maximum in front of the face and the
    exact length is 0. Beyond it the axial pressure falls monotonically, and as
    ``1/z`` beyond about the Rayleigh distance (:func:`rayleigh_distance_m`).
    """
    a = _positive(radius_m, "radius_m")
    c = _positive(speed_of_sound_m_s, "speed_of_sound_m_s")
    wavelength = c / _positive(frequency_hz, "frequency_hz")
    if not exact:
        return a * a / wavelength
    return max((a * a - wavelength * wavelength / 4.0) / wavelength, 0.0)


def rayleigh_distance_m(
    radius_m: float,
    frequency_hz: float,
    speed_of_sound_m_s: float = SPEED_OF_SOUND_20C_M_S,
) -> float:
    """Rayleigh distance ``π a²/λ = k a²/2`` of a piston, m [K §7.4].

    Kinsler et al. use this name for the distance beyond which the axial pressure
    approaches the far-field ``1/z`` law; it is π times the near-field length
    ``a²/λ`` of :func:`near_field_length_m`.
    """
    return math.pi * near_field_length_m(radius_m, frequency_hz, speed_of_sound_m_s)


def piston_on_axis_pressure(
    distance_m: ArrayLike,
    radius_m: float,
    frequency_hz: float,
    speed_of_sound_m_s: float = SPEED_OF_SOUND_20C_M_S,
) -> NDArray[np.float64]:
    """On-axis pressure amplitude of a baffled piston, relative to its maximum ``2 ρ0 c U0``.

    ``|sin(k (sqrt(z² + a²) - z) / 2)|`` [K §7.4], exact at every distance z >= 0
    (not only in the far field). Maxima (value 1) where ``sqrt(z² + a²) - z`` is an
    odd multiple of λ/2, zeros where it is an even multiple.
    """
    a = _positive(radius_m, "radius_m")
    k = _wavenumber(frequency_hz, speed_of_sound_m_s)
    z = np.asarray(distance_m, dtype=float)
    if np.any(z < 0) or not np.all(np.isfinite(z)):
        raise EchoLocError(f"distance_m must be finite and >= 0, got {z}")
    # sqrt(z² + a²) - z written as a² / (sqrt(z² + a²) + z): no cancellation far away.
    path_difference = a * a / (np.hypot(z, a) + z)
    return np.asarray(np.abs(np.sin(k * path_difference / 2.0)), dtype=np.float64)


# ------------------------------------------------------------------- transducers


@dataclass(frozen=True)
class Transducer:
    """A transducer as a circular piston with a second-order resonant response.

    Attributes
    ----------
    name : str
        Label.
    centre_frequency_hz : float
        Resonance f0, Hz: the response is 1 there.
    bandwidth_hz : float
        -3 dB bandwidth of one transducer (one pass), Hz: ``f0 / Q``.
    radius_m : float
        Piston radius used for the directivity, m (an effective radius: see PRESETS).
    """

    name: str
    centre_frequency_hz: float
    bandwidth_hz: float
    radius_m: float

    def __post_init__(self) -> None:
        _positive(self.centre_frequency_hz, f"{self.name}: centre_frequency_hz")
        _positive(self.bandwidth_hz, f"{self.name}: bandwidth_hz")
        _positive(self.radius_m, f"{self.name}: radius_m")

    @property
    def quality_factor(self) -> float:
        """Q = f0 / B (dimensionless)."""
        return self.centre_frequency_hz / self.bandwidth_hz

    @classmethod
    def from_quality_factor(
        cls, name: str, centre_frequency_hz: float, quality_factor: float, radius_m: float
    ) -> Transducer:
        """The transducer with bandwidth ``f0 / Q``."""
        q = _positive(quality_factor, f"{name}: quality_factor")
        return cls(name, centre_frequency_hz, centre_frequency_hz / q, radius_m)


CH101_BANDWIDTH_HZ = 10_000.0
"""-3 dB bandwidth of one CH101 transducer (one pass), Hz, as fitted to real echo widths."""

PRESETS: dict[str, Transducer] = {
    # Polaroid 600-series / 607281 electrostatic transducer (report ch. 2.4.2.6, appendix A).
    # Centre 50 kHz as the report uses it (the Polaroid 6500 ranging module drives 16
    # cycles at 49.4 kHz). Band: the report calls the electrostatic type "large
    # bandwidth"; Polaroid's original 4-frequency ranging board (part 606191, R. Moyle,
    # BARG Newsletter 3/4, 1985) sent "a combination of frequencies" in one burst where
    # the later boards send 49.4 kHz only (commonly quoted as 49.4-60 kHz; the figures
    # were not verified here), so the transducer is usable well away from 50 kHz.
    # Q = 2.5 (-3 dB band 41.0-61.0 kHz in the analog model) is a modelling choice
    # consistent with that, not a data-sheet figure (Graph 1 of the data sheet is
    # unreadable in the scan). Radius: chosen so the -3 dB full beam at 50 kHz in air at
    # 20 °C is the report's 15° (13.53 mm). The physical foil (1.513 in = 38.4 mm diameter,
    # a = 19.2 mm) as a uniform piston gives 10.6° at -3 dB, 14.5° at -6 dB and first
    # nulls at ±12.6°: the report's 15° matches its -6 dB width rather than -3 dB.
    "electrostatic50": Transducer(
        name="electrostatic50",
        centre_frequency_hz=50_000.0,
        bandwidth_hz=20_000.0,
        radius_m=radius_for_beam_width(15.0, 50_000.0),
    ),
    # Murata MA40L1S (transmitter) / MA40L2T (receiver) pair, report ch. 2.4.2.6:
    # 40 kHz, "small operating bandwidth, ±2 kHz" (taken as the -3 dB band of each,
    # B = 4 kHz, Q = 10), "3 dB beam width of main lobe is around 30°". The radius that
    # gives 30° at -3 dB at 40 kHz (20 °C) is 8.53 mm; the report's "10 mm diameter" (a = 5 mm)
    # as a plain piston would give 52°. These open-type sensors radiate through a conical
    # resonator, so the radius is an effective one fitted to the stated beam.
    "piezo40": Transducer(
        name="piezo40",
        centre_frequency_hz=40_000.0,
        bandwidth_hz=4_000.0,
        radius_m=radius_for_beam_width(30.0, 40_000.0),
    ),
    # TDK InvenSense (Chirp) CH101: a PMUT at 175 kHz (the SPiEL data's carrier_hz;
    # C. Hahne, ICRA 2023, doi:10.1109/ICRA48891.2023.10161199). Bandwidth: fitted to
    # that data's echo envelopes (benchmarks/compare_ch101.py), not a data-sheet figure.
    # Radius: an effective one for a beam that stays within 1 dB (two ways) out to 50°
    # off axis, as the data's echo amplitudes times range² do (the chip's port is a
    # sub-millimetre opening, far smaller than the 1.96 mm wavelength).
    "ch101": Transducer(
        name="ch101",
        centre_frequency_hz=175_000.0,
        bandwidth_hz=CH101_BANDWIDTH_HZ,
        radius_m=0.35e-3,
    ),
}
"""Named transducer models; see the comments in the source for the source of each number."""


def _check_passes(passes: int) -> int:
    if isinstance(passes, bool) or int(passes) != passes or passes < 0:
        raise EchoLocError(f"passes must be a whole number >= 0, got {passes}")
    return int(passes)


def _check_sample_rate(transducer: Transducer, sample_rate_hz: float) -> float:
    fs = _positive(sample_rate_hz, "sample_rate_hz")
    if transducer.centre_frequency_hz >= fs / 2.0:
        raise EchoLocError(
            f"{transducer.name}: centre frequency {transducer.centre_frequency_hz:g} Hz is not below "
            f"the Nyquist frequency {fs / 2:g} Hz of sample_rate_hz={fs:g}"
        )
    return fs


def resonator_coefficients(
    transducer: Transducer, sample_rate_hz: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """``(b, a)`` of the digital second-order resonator of one pass, for ``scipy.signal.lfilter``.

    The bilinear transform of the analog resonator with the centre and the -3 dB
    bandwidth pre-warped [O §11.3] (``scipy.signal.iirpeak``): gain exactly 1 (phase 0)
    at f0, -3 dB points exactly ``bandwidth_hz`` apart, zeros at 0 Hz and Nyquist.
    """
    fs = _check_sample_rate(transducer, sample_rate_hz)
    b, a = scipy.signal.iirpeak(transducer.centre_frequency_hz, transducer.quality_factor, fs=fs)
    return np.asarray(b, dtype=np.float64), np.asarray(a, dtype=np.float64)


def frequency_response(
    transducer: Transducer,
    freqs_hz: ArrayLike,
    *,
    passes: int = 1,
    sample_rate_hz: float | None = None,
) -> NDArray[np.complex128]:
    """Complex response of ``passes`` resonators in series (1: one transducer; 2: a pair).

    Analog (``sample_rate_hz=None``): ``H(f) = 1 / (1 + j Q (f/f0 - f0/f))``, raised to
    ``passes``; ``H(0) = 0``, ``H(-f) = conj(H(f))``. One pass has gain 1 at f0 and
    its -3 dB points ``f0/Q`` apart; a transmit-receive pair of identical transducers
    is the square (its -3 dB bandwidth is ``sqrt(sqrt(2) - 1) = 0.644`` times one's).
    With ``sample_rate_hz``: the response of the digital biquad of
    :func:`resonator_coefficients` at those frequencies (what the sampled-signal
    functions apply); it equals the analog one at f0 and has the same -3 dB width.
    """
    p = _check_passes(passes)
    f = np.asarray(freqs_hz, dtype=float)
    if not np.all(np.isfinite(f)):
        raise EchoLocError("freqs_hz must be finite")
    if sample_rate_hz is None:
        f0 = transducer.centre_frequency_hz
        safe = np.where(f == 0.0, 1.0, f)
        h = np.where(f == 0.0, 0.0, 1.0 / (1.0 + 1j * transducer.quality_factor * (safe / f0 - f0 / safe)))
    else:
        b, a = resonator_coefficients(transducer, sample_rate_hz)
        _, h_flat = scipy.signal.freqz(b, a, worN=f.ravel(), fs=float(sample_rate_hz))
        h = np.asarray(h_flat).reshape(f.shape)
    return np.asarray(h**p, dtype=np.complex128)


def group_delay_s(transducer: Transducer, *, passes: int = 2, sample_rate_hz: float | None = None) -> float:
    """Group delay at the centre frequency of ``passes`` resonators, s.

    Analog: ``2 Q / ω0 = 1 / (π B)`` per pass (the slope of the resonator phase
    ``-atan(Q (f/f0 - f0/f))`` at f0). This is the delay a time-of-flight estimator sees
    on top of the path time: 31.8 µs (10.9 mm of path) for the ``electrostatic50`` pair,
    159 µs (54.6 mm) for ``piezo40``. With ``sample_rate_hz``, the digital biquad's
    (``scipy.signal.group_delay``).
    """
    p = _check_passes(passes)
    if sample_rate_hz is None:
        return p / (math.pi * transducer.bandwidth_hz)
    b, a = resonator_coefficients(transducer, sample_rate_hz)
    _, gd = scipy.signal.group_delay((b, a), w=[transducer.centre_frequency_hz], fs=float(sample_rate_hz))
    return p * float(gd[0]) / float(sample_rate_hz)


def _ringing_samples(transducer: Transducer, sample_rate_hz: float, passes: int) -> int:
    """Samples for the envelope ``t^(p-1) exp(-t/τ)`` to fall below about 1e-12 of its peak.

    τ = 2Q/ω0 = 1/(π B) is the amplitude decay time of one resonator; ``28 + 8 (p - 1)``
    decay times take ``passes`` = p = 1, 2, 3 below 1e-12 (-240 dB).
    """
    tau_s = 1.0 / (math.pi * transducer.bandwidth_hz)
    return math.ceil((28.0 + 8.0 * max(passes - 1, 0)) * tau_s * sample_rate_hz) + 1


def impulse_response(
    transducer: Transducer,
    sample_rate_hz: float,
    duration_s: float | None = None,
    *,
    passes: int = 2,
) -> NDArray[np.float64]:
    """Sampled impulse response of ``passes`` resonators (default 2: transmitter and receiver).

    The inverse FFT of the product response,
    ``irfft(frequency_response(t, rfftfreq(n), passes=passes, sample_rate_hz=fs), n)``,
    i.e. the causal impulse response of the digital resonator applied ``passes``
    times, to within the ringing that wraps past ``n`` samples. Convolving with it
    leaves a tone at f0 unchanged in the steady state (gain 1). ``duration_s``
    defaults to the time the envelope takes to fall below 1e-12 of its peak
    (``28 + 8 (passes - 1)`` decay times ``1/(π B)``: 2.8 ms for the ``piezo40``
    pair, 0.57 ms for ``electrostatic50``).

    Away from the band the digital resonator falls faster than the analog one (its
    zero at Nyquist), so its energy is slightly below the analog ``(π/2) B`` per
    unit gain: by 6 % for ``electrostatic50`` at 1 MHz, 0.03 % at 200 MHz.
    """
    p = _check_passes(passes)
    fs = _check_sample_rate(transducer, sample_rate_hz)
    if duration_s is None:
        n = _ringing_samples(transducer, fs, p)
    else:
        n = round(_positive(duration_s, "duration_s") * fs)
        if n < 1:
            raise EchoLocError(f"duration_s={duration_s} is shorter than one sample at {fs:g} Hz")
    h = frequency_response(transducer, scipy.fft.rfftfreq(n, 1.0 / fs), passes=p, sample_rate_hz=fs)
    return np.asarray(scipy.fft.irfft(h, n), dtype=np.float64)


def apply_response(
    samples: ArrayLike,
    transducer: Transducer,
    sample_rate_hz: float,
    *,
    passes: int = 2,
    axis: int = -1,
) -> NDArray[np.float64]:
    """Filter signals by ``passes`` resonators (default 2: a transmit-receive pair), by FFT.

    Multiplies the spectrum by :func:`frequency_response` (digital) on a grid long
    enough for the ringing (zero padding), so the result is the linear, causal
    convolution with :func:`impulse_response` (what ``scipy.signal.lfilter`` applied
    ``passes`` times gives), not a circular one. Works along ``axis`` of any array.
    The output has as many samples as the input: ringing after the last input
    sample is cut (pad the input with zeros to keep it).
    """
    p = _check_passes(passes)
    fs = _check_sample_rate(transducer, sample_rate_hz)
    x = np.asarray(samples, dtype=float)
    if not -x.ndim <= axis < x.ndim:
        raise EchoLocError(f"axis={axis} does not exist in samples of shape {x.shape}")
    if x.shape[axis] == 0:
        raise EchoLocError("samples must have at least one sample along the filtered axis")
    n = x.shape[axis]
    n_fft = scipy.fft.next_fast_len(n + _ringing_samples(transducer, fs, p), real=True)
    h = frequency_response(transducer, scipy.fft.rfftfreq(n_fft, 1.0 / fs), passes=p, sample_rate_hz=fs)
    shape = [1] * x.ndim
    shape[axis] = h.size
    spectrum = scipy.fft.rfft(x, n_fft, axis=axis) * h.reshape(shape)
    y = scipy.fft.irfft(spectrum, n_fft, axis=axis)
    return np.asarray(np.take(y, np.arange(n), axis=axis), dtype=np.float64)


def directivity(
    transducer: Transducer,
    theta_rad: ArrayLike,
    frequency_hz: float | None = None,
    speed_of_sound_m_s: float = SPEED_OF_SOUND_20C_M_S,
) -> NDArray[np.float64]:
    """Piston directivity of a transducer at ``frequency_hz`` (default: its centre frequency).

    :func:`piston_directivity` with the transducer's radius. One way (transmit or
    receive); a pulse-echo path from transmitter to receiver is the product of the
    two, each at its own angle.
    """
    f = transducer.centre_frequency_hz if frequency_hz is None else frequency_hz
    return piston_directivity(theta_rad, transducer.radius_m, f, speed_of_sound_m_s)


# ----------------------------------------------------------------------- Doppler


def _check_velocity(radial_velocity_m_s: ArrayLike, speed_of_sound_m_s: float) -> NDArray[np.float64]:
    c = _positive(speed_of_sound_m_s, "speed_of_sound_m_s")
    v = np.asarray(radial_velocity_m_s, dtype=float)
    if not np.all(np.abs(v) < c):
        raise EchoLocError(f"radial_velocity_m_s must be finite and slower than sound ({c:g} m/s), got {v}")
    return v


def doppler_shift_hz(
    frequency_hz: ArrayLike,
    radial_velocity_m_s: ArrayLike,
    speed_of_sound_m_s: float = SPEED_OF_SOUND_20C_M_S,
    *,
    exact: bool = True,
) -> NDArray[np.float64]:
    """Doppler shift ``f' - f`` of the echo from a moving reflector, Hz (two-way).

    Transmitter and receiver co-located and at rest; the reflector moves with radial
    speed v, **v > 0 approaching** (range decreasing). The reflector receives
    ``f (c + v)/c`` and re-radiates it as a moving source, so the echo has
    ``f' = f (c + v)/(c - v)``: the shift is ``2 f v / (c - v)`` (``exact=True``) or,
    to first order in v/c, ``2 f v / c = 2 v/λ`` (``exact=False``). The report's
    eqs. (2.28)-(2.30) are the same with its opposite sign (its v is the speed
    *away* from the source). The two differ by ``2 f (v/c)² / (1 - v/c)``.
    """
    f = np.asarray(frequency_hz, dtype=float)
    v = _check_velocity(radial_velocity_m_s, speed_of_sound_m_s)
    c = float(speed_of_sound_m_s)
    shift = 2.0 * f * v / (c - v) if exact else 2.0 * f * v / c
    return np.asarray(shift, dtype=np.float64)


def doppler_time_scale(
    radial_velocity_m_s: ArrayLike, speed_of_sound_m_s: float = SPEED_OF_SOUND_20C_M_S
) -> NDArray[np.float64]:
    """Factor ``(c - v)/(c + v)`` by which the echo's duration is multiplied (v > 0 approaching).

    The echo of an emitted ``s(t)`` off a reflector moving at constant radial speed
    is ``s((t - t0) / scale)``: compressed in time (scale < 1) when approaching,
    stretched when receding; every frequency is multiplied by ``1/scale``, matching
    :func:`doppler_shift_hz` with ``exact=True``.
    """
    v = _check_velocity(radial_velocity_m_s, speed_of_sound_m_s)
    c = float(speed_of_sound_m_s)
    return np.asarray((c - v) / (c + v), dtype=np.float64)


# ------------------------------------------------------------------------- arrays


def _line_factor(
    u: NDArray[np.float64], n_elements: int, spacing_m: float, k: float, weights: NDArray[np.float64]
) -> NDArray[np.float64]:
    """``|Σ w_n exp(j n k d u)| / |Σ w_n|`` for direction-cosine offsets u."""
    n = np.arange(n_elements)
    phase = np.exp(1j * k * spacing_m * u[..., None] * n)
    return np.asarray(np.abs(phase @ weights) / abs(weights.sum()), dtype=np.float64)


def _check_weights(weights: ArrayLike | None, n_elements: int, name: str) -> NDArray[np.float64]:
    if weights is None:
        return np.ones(n_elements)
    w = np.asarray(weights, dtype=float)
    if w.shape != (n_elements,) or not np.all(np.isfinite(w)):
        raise EchoLocError(f"{name} must be {n_elements} finite numbers, got shape {w.shape}")
    if abs(w.sum()) == 0.0:
        raise EchoLocError(f"{name} sum to zero: the pattern cannot be normalised at the steering angle")
    return w


def _check_count(n: int, name: str) -> int:
    if isinstance(n, bool) or int(n) != n or n < 1:
        raise EchoLocError(f"{name} must be a whole number >= 1, got {n}")
    return int(n)


def array_factor(
    theta_rad: ArrayLike,
    n_elements: int,
    spacing_m: float,
    frequency_hz: float,
    speed_of_sound_m_s: float = SPEED_OF_SOUND_20C_M_S,
    *,
    steer_rad: float = 0.0,
    weights: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Magnitude of the array factor of a uniform line array, 1 at the steering angle.

    ``AF(θ) = |Σ_n w_n exp(j n ψ)| / |Σ_n w_n|``, ``ψ = k d (sin θ - sin θ_s)``, with
    θ from the array normal (broadside) in the plane of the line [R eqs. 2.24-2.26;
    VT ch. 2]. Steering by the delays ``n d sin θ_s / c``. Uniform weights give
    ``|sin(N ψ/2) / (N sin(ψ/2))|`` (the report's eq. 2.25). Elements are taken as
    omnidirectional: multiply by the element directivity for real transducers.
    """
    n = _check_count(n_elements, "n_elements")
    d = _positive(spacing_m, "spacing_m")
    k = _wavenumber(frequency_hz, speed_of_sound_m_s)
    w = _check_weights(weights, n, "weights")
    u = np.sin(np.asarray(theta_rad, dtype=float)) - math.sin(steer_rad)
    return _line_factor(u, n, d, k, w)


def planar_array_factor(
    theta_rad: ArrayLike,
    phi_rad: ArrayLike,
    nx: int,
    ny: int,
    dx_m: float,
    dy_m: float,
    frequency_hz: float,
    speed_of_sound_m_s: float = SPEED_OF_SOUND_20C_M_S,
    *,
    steer_theta_rad: float = 0.0,
    steer_phi_rad: float = 0.0,
    weights_x: ArrayLike | None = None,
    weights_y: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Array factor of an ``nx`` by ``ny`` rectangular grid in the x-y plane, 1 at the steer direction.

    θ is the polar angle from the array normal (+z), φ the azimuth from +x. With
    direction cosines ``u = sin θ cos φ``, ``v = sin θ sin φ`` and separable weights
    ``w_x[i] w_y[j]``, the factor is the product of two line factors,
    ``AF_x(u - u_s) AF_y(v - v_s)`` [VT ch. 4].
    """
    mx = _check_count(nx, "nx")
    my = _check_count(ny, "ny")
    ddx = _positive(dx_m, "dx_m")
    ddy = _positive(dy_m, "dy_m")
    k = _wavenumber(frequency_hz, speed_of_sound_m_s)
    wx = _check_weights(weights_x, mx, "weights_x")
    wy = _check_weights(weights_y, my, "weights_y")
    theta = np.asarray(theta_rad, dtype=float)
    phi = np.asarray(phi_rad, dtype=float)
    us = math.sin(steer_theta_rad) * math.cos(steer_phi_rad)
    vs = math.sin(steer_theta_rad) * math.sin(steer_phi_rad)
    u = np.sin(theta) * np.cos(phi) - us
    v = np.sin(theta) * np.sin(phi) - vs
    return np.asarray(_line_factor(u, mx, ddx, k, wx) * _line_factor(v, my, ddy, k, wy))


def grating_lobe_angles(
    spacing_m: float,
    frequency_hz: float,
    speed_of_sound_m_s: float = SPEED_OF_SOUND_20C_M_S,
    steer_rad: float = 0.0,
) -> NDArray[np.float64]:
    """Angles of the grating lobes of a line array in -90°..90°, rad, ascending.

    Full-height copies of the main lobe where ``ψ`` is a non-zero multiple of 2π:
    ``sin θ_g = sin θ_s + m λ/d``, m ≠ 0, ``|sin θ_g| <= 1`` [VT §2.4]. Unsteered,
    none exist for d < λ (the first reach ±90° at d = λ); steered anywhere up to ±90°,
    none exist for d < λ/2: the general condition is ``d < λ / (1 + |sin θ_s|)``
    (:func:`max_spacing_without_grating_lobes_m`). Empty when there are none.
    """
    d = _positive(spacing_m, "spacing_m")
    wavelength = _positive(speed_of_sound_m_s, "speed_of_sound_m_s") / _positive(frequency_hz, "frequency_hz")
    s0 = math.sin(steer_rad)
    m_max = math.floor(2.0 * d / wavelength) + 1
    angles = []
    for m in range(-m_max, m_max + 1):
        s = s0 + m * wavelength / d
        if m != 0 and abs(s) <= 1.0 + 1e-12:
            angles.append(math.asin(max(-1.0, min(1.0, s))))
    return np.asarray(sorted(angles), dtype=np.float64)


def max_spacing_without_grating_lobes_m(
    frequency_hz: float,
    speed_of_sound_m_s: float = SPEED_OF_SOUND_20C_M_S,
    max_steer_rad: float = math.pi / 2.0,
) -> float:
    """Spacing ``λ / (1 + |sin θ_max|)`` at which a grating lobe first reaches ±90°, m [VT §2.4].

    Smaller spacings keep every grating lobe out of real space for every steering
    angle up to ``max_steer_rad``; λ/2 for steering to ±90° (the rule the report
    states in ch. 2.4.4.1), λ for an unsteered array.
    """
    wavelength = _positive(speed_of_sound_m_s, "speed_of_sound_m_s") / _positive(frequency_hz, "frequency_hz")
    return wavelength / (1.0 + abs(math.sin(max_steer_rad)))


ShadingKind = Literal["uniform", "hann", "chebyshev"]


def shading_weights(n: int, kind: ShadingKind = "uniform", sidelobe_db: float = 30.0) -> NDArray[np.float64]:
    """Amplitude shading of ``n`` elements, largest weight 1.

    ``uniform``: all ones (first side lobe -13.3 dB). ``hann``: the Hann window of
    ``n + 2`` points without its two zero end points, so every element is used.
    ``chebyshev``: Dolph-Chebyshev weights (``scipy.signal.windows.chebwin``), every
    side lobe at ``-sidelobe_db`` dB for the narrowest main lobe with that level
    [Dolph 1946; VT §3.4]. (scipy warns that such windows are unsuited to *spectral
    analysis* below 45 dB; that concerns noise bandwidth, not array patterns, and is
    silenced here.)
    """
    count = _check_count(n, "n")
    if kind == "uniform":
        w = np.ones(count)
    elif kind == "hann":
        w = scipy.signal.windows.hann(count + 2)[1:-1]
    elif kind == "chebyshev":
        level = _positive(sidelobe_db, "sidelobe_db")
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="This window is not suitable", category=UserWarning)
            w = scipy.signal.windows.chebwin(count, at=level)
    else:
        raise EchoLocError(f"shading kind must be 'uniform', 'hann' or 'chebyshev', got {kind!r}")
    w = np.asarray(w, dtype=np.float64)
    return np.asarray(w / w.max(), dtype=np.float64)


# ------------------------------------------------------------------------ coverage


def _check_angle_deg(value: float, name: str) -> float:
    v = float(value)
    if not (math.isfinite(v) and 0.0 < v <= 360.0):
        raise EchoLocError(f"{name} must lie in (0, 360] degrees, got {value}")
    return v


def _check_overlap(overlap: float) -> float:
    o = float(overlap)
    if not (math.isfinite(o) and 0.0 <= o < 1.0):
        raise EchoLocError(f"overlap must be a fraction in [0, 1), got {overlap}")
    return o


def transducers_to_cover(field_of_view_deg: float, beam_full_angle_deg: float, overlap: float = 0.0) -> int:
    """Transducers needed to cover a fan (1-D field of view) side by side.

    ``ceil(FOV / (α (1 - overlap)))`` with α the full beam width and ``overlap`` the
    fraction of each beam shared with its neighbour: the report's ``N_T = θ/α``
    (ch. 2.4.4.2, 90° with 30° beams: 3) rounded up, with the overlap it recommends
    against dead zones. Exact for a closed 360° ring; for an open fan it counts one
    overlap per beam, so it can exceed the minimum ``1 + ceil((FOV - α)/(α (1 - overlap)))``
    by one.
    """
    fov = _check_angle_deg(field_of_view_deg, "field_of_view_deg")
    beam = _check_angle_deg(beam_full_angle_deg, "beam_full_angle_deg")
    step = beam * (1.0 - _check_overlap(overlap))
    return max(1, math.ceil(fov / step - 1e-9))


KERSHNER_COVERING_DENSITY = 2.0 * math.pi / math.sqrt(27.0)
"""2π/√27 = 1.2092: the thinnest covering of the plane by equal discs (Kershner 1939)."""


def transducers_to_cover_cone(
    field_of_view_deg: float,
    beam_full_angle_deg: float,
    overlap: float = 0.0,
    *,
    gap_free: bool = False,
) -> int:
    """Estimate of the transducers needed to cover a cone (2-D field of view), by solid angle.

    The solid angle of a cone of full angle α is ``Ω = 2π (1 - cos(α/2))`` sr; the
    estimate is ``ceil(Ω_FOV / Ω_beam)`` with the beam narrowed to ``α (1 - overlap)``.
    Circular beams cannot tile a surface, so this is a lower bound; ``gap_free=True``
    multiplies by Kershner's covering density 2π/√27 = 1.209 (discs on a hexagonal
    lattice, the thinnest covering of the plane without gaps), a good estimate when the
    beams are small against the field of view. A field of view of 360° is the whole
    sphere (4π sr).
    """
    fov = _check_angle_deg(field_of_view_deg, "field_of_view_deg")
    beam = _check_angle_deg(beam_full_angle_deg, "beam_full_angle_deg") * (1.0 - _check_overlap(overlap))
    ratio = (1.0 - math.cos(math.radians(fov) / 2.0)) / (1.0 - math.cos(math.radians(beam) / 2.0))
    if gap_free:
        ratio *= KERSHNER_COVERING_DENSITY
    return max(1, math.ceil(ratio - 1e-9))
