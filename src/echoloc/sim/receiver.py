"""The receiver chain: gain, noise, sample-rate change, demodulation and the ADC.

What happens to the acoustic signal at a receiver between the transducer and the
recorded samples, as pure functions of plain values and small frozen specs
(:class:`GainSpec`, :class:`AdcSpec`). Arrays carry samples on the last axis (the
batch axes first) unless an ``axis`` says otherwise. Times are measured from the
start of the frame, which is the instant emission starts (sample k at
``k / sample_rate_hz``, ``docs/FORMATS.md``).

Sources
-------
- [R] the reference report (docs/METHOD.md, References): ch. 4 records
  at 5 MHz and decimates by 25 to 200 kHz; appendix B, the Polaroid 6500 ranging
  module, whose "receiver amplifier gain is incremented higher at discrete times"
  until "at approximately 38 milliseconds the maximum gain is attained" (fig. 3,
  gain against gain-step number).
- [B] W. R. Bennett, "Spectra of quantized signals", Bell Syst. Tech. J. 27 (1948)
  446-472: a busy signal quantised with step q has an error uniform in ±q/2, of
  power ``q²/12``.
- [OS] A. V. Oppenheim, R. W. Schafer, *Discrete-Time Signal Processing*, 3rd ed.,
  §2.10: white noise of variance σ² through a filter h has variance ``σ² Σ h[n]²``
  and power spectrum ``σ² |H|²``.
- [CR] R. E. Crochiere, L. R. Rabiner, *Multirate Digital Signal Processing*,
  Prentice Hall 1983: rational sample-rate change by polyphase FIR filtering
  (``scipy.signal.resample_poly``, a linear-phase filter whose delay it removes).
- [G] D. Gabor, "Theory of communication", J. IEE 93 (1946) 429-457: the analytic
  signal ``x + j H{x}``; computed by FFT as in S. L. Marple, IEEE Trans. Signal
  Process. 47 (1999) 2600-2603 (``scipy.signal.hilbert``).

Complex baseband convention
---------------------------
For a real band-pass signal ``rf`` with analytic signal ``a = rf + j H{rf}``, the
complex baseband ("iq") samples are ``iq(t) = a(t) exp(-2j π f_c t)`` with t from the
frame start, so that ``rf(t) = Re(iq(t) exp(+2j π f_c t))``. A tone
``A cos(2π (f_c + Δf) t + φ)`` becomes ``A exp(j (2π Δf t + φ))``: frequencies above
the carrier turn counter-clockwise. An echo delayed by τ multiplies the baseband of
the echo at t = 0 by ``exp(-2j π f_c τ)`` and shifts it by τ. The envelope is ``|iq|``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from fractions import Fraction
from typing import Any, Literal, get_args

import numpy as np
import scipy.fft
import scipy.signal
from numpy.typing import ArrayLike, NDArray

from echoloc.errors import SceneError
from echoloc.physics.transducer import Transducer, impulse_response, resonator_coefficients

GainKind = Literal["none", "continuous", "stepped"]
SignalKind = Literal["rf", "envelope", "iq"]

SIGNAL_KINDS: tuple[str, ...] = get_args(SignalKind)
"""The recorded representations, as in ``docs/FORMATS.md`` (``signal_kind``)."""

MAX_DENOMINATOR = 10_000
"""Largest ``down`` of the rational rate ratio ``up / down`` that :func:`resample` uses."""

RATE_TOLERANCE = 1e-9
"""Largest relative error allowed between the rational ratio and ``to_hz / from_hz``.

Small enough that the output is at ``to_hz`` for any practical frame (1e-9 of a 1 s
frame is 1 ns), so a recording never declares a rate it does not have."""

TEMPLATE_FLOOR = 1e-4
"""A template ends at its last sample at or above this fraction of its peak magnitude."""

_STEP_EPSILON = 1e-9
"""Samples within this fraction of a sample before a gain step already have the new gain."""


# --------------------------------------------------------------------------- checks


def _finite(value: float, name: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise SceneError(f"{name} must be a finite number, got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(v):
        raise SceneError(f"{name} must be a finite number, got {value!r}")
    return v


def _positive(value: float, name: str) -> float:
    v = _finite(value, name)
    if v <= 0.0:
        raise SceneError(f"{name} must be > 0, got {value!r}")
    return v


def _non_negative(value: float, name: str) -> float:
    v = _finite(value, name)
    if v < 0.0:
        raise SceneError(f"{name} must be >= 0, got {value!r}")
    return v


def _whole(value: int, name: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < minimum:
        raise SceneError(f"{name} must be a whole number >= {minimum}, got {value!r}")
    return int(value)


def _shape(shape: int | tuple[int, ...]) -> tuple[int, ...]:
    dims = (shape,) if isinstance(shape, int | np.integer) else tuple(shape)
    if not dims:
        raise SceneError("shape must have at least one axis (the samples, last)")
    return tuple(_whole(d, "shape", 0) for d in dims)


# ----------------------------------------------------------------------------- gain


@dataclass(frozen=True)
class GainSpec:
    """Time-varying gain (TVG) of the receive amplifier, in dB against time from emission.

    ``none``: ``gain_db`` throughout. ``continuous``: ``gain_db + slope_db_per_ms * t_ms``,
    a gain rising linearly in dB. ``stepped``: ``gain_db + step_db * floor(t / step_s)``,
    a jump of ``step_db`` at every multiple of ``step_s`` as the Polaroid 6500 ranging
    module's gain steps do ([R] appendix B, fig. 3). All saturate at ``max_gain_db``.

    Attributes
    ----------
    kind : {"none", "continuous", "stepped"}

    gain_db : float
        Gain at t = 0, dB; at most ``max_gain_db``.
    slope_db_per_ms : float
        Rise of a continuous gain, dB/ms, >= 0.
    step_db : float
        Height of each step of a stepped gain, dB, >= 0.
    step_s : float
        Time between steps, s, > 0.
    max_gain_db : float
        Saturation of the amplifier's gain, dB.
    """

    kind: GainKind = "none"
    gain_db: float = 0.0
    slope_db_per_ms: float = 0.0
    step_db: float = 6.0
    step_s: float = 1e-3
    max_gain_db: float = 60.0

    @property
    def active(self) -> bool:
        """Whether the amplifier's gain differs from 1 anywhere (else nothing to apply or record)."""
        return self.kind != "none" or self.gain_db != 0

    def __post_init__(self) -> None:
        if self.kind not in get_args(GainKind):
            raise SceneError(f"GainSpec.kind must be 'none', 'continuous' or 'stepped', got {self.kind!r}")
        checks = {
            "gain_db": _finite,
            "slope_db_per_ms": _non_negative,
            "step_db": _non_negative,
            "step_s": _positive,
            "max_gain_db": _finite,
        }
        for name, check in checks.items():
            object.__setattr__(self, name, check(getattr(self, name), f"GainSpec.{name}"))
        if self.max_gain_db < self.gain_db:
            raise SceneError(
                f"GainSpec.max_gain_db must be >= gain_db ({self.gain_db:g} dB), got {self.max_gain_db:g}"
            )


def gain_db_curve(spec: GainSpec, n_samples: int, sample_rate_hz: float) -> NDArray[np.float64]:
    """Gain of ``spec`` in dB at samples ``k / sample_rate_hz`` s after emission, shape (n_samples,).

    A stepped gain takes its m-th step at the first sample with ``k >= m step_s fs``
    (to within 1e-9 of a sample, so rounding of ``step_s fs`` cannot move a step).
    """
    n = _whole(n_samples, "n_samples", 0)
    fs = _positive(sample_rate_hz, "sample_rate_hz")
    k = np.arange(n, dtype=np.float64)
    if spec.kind == "continuous":
        g = spec.gain_db + spec.slope_db_per_ms * 1e3 * k / fs
    elif spec.kind == "stepped":
        g = spec.gain_db + spec.step_db * np.floor(k / (spec.step_s * fs) + _STEP_EPSILON)
    else:
        g = np.full(n, spec.gain_db)
    return np.asarray(np.minimum(g, spec.max_gain_db), dtype=np.float64)


def gain_curve(spec: GainSpec, n_samples: int, sample_rate_hz: float) -> NDArray[np.float64]:
    """Linear amplitude gain ``10**(G_dB / 20)`` of ``spec`` per sample, shape (n_samples,).

    Multiply a frame ``(..., n_samples)`` by it (broadcasting) to apply the TVG;
    :func:`gain_db_curve` gives ``G_dB``.
    """
    return np.asarray(10.0 ** (gain_db_curve(spec, n_samples, sample_rate_hz) / 20.0), dtype=np.float64)


# ------------------------------------------------------------------------------ ADC


@dataclass(frozen=True)
class AdcSpec:
    """Analog-to-digital converter: clipping at ``±full_scale`` and a uniform quantiser.

    Attributes
    ----------
    bits : int or None
        Resolution, 1 to 32 bits; None: clipping only, no quantisation.
    full_scale : float
        Clipping level, in the amplitude units of the signal, > 0.

    The quantiser is mid-tread (0 is a level) with step ``q = 2 full_scale / 2**bits``
    and the ``2**bits`` levels of a two's-complement converter, ``k q`` for
    ``k = -2**(bits-1) .. 2**(bits-1) - 1``: from ``-full_scale`` to ``full_scale - q``.
    """

    bits: int | None = None
    full_scale: float = 1.0

    def __post_init__(self) -> None:
        if self.bits is not None and (
            isinstance(self.bits, bool)
            or not isinstance(self.bits, int | np.integer)
            or not 1 <= self.bits <= 32
        ):
            raise SceneError(f"AdcSpec.bits must be a whole number from 1 to 32, or None, got {self.bits!r}")
        if self.bits is not None:
            object.__setattr__(self, "bits", int(self.bits))
        object.__setattr__(self, "full_scale", _positive(self.full_scale, "AdcSpec.full_scale"))

    @property
    def step(self) -> float:
        """Quantisation step q = 2 full_scale / 2**bits (0 without quantisation)."""
        return 0.0 if self.bits is None else 2.0 * self.full_scale / 2.0**self.bits


def _quantise_real(x: NDArray[np.float64], spec: AdcSpec) -> NDArray[np.float64]:
    clipped = np.clip(x, -spec.full_scale, spec.full_scale)
    if spec.bits is None:
        return np.asarray(clipped, dtype=np.float64)
    half = 2 ** (spec.bits - 1)
    codes = np.clip(np.rint(clipped / spec.step), -half, half - 1)
    return np.asarray(codes * spec.step, dtype=np.float64)


def quantise(samples: ArrayLike, spec: AdcSpec) -> NDArray[Any]:
    """Clip to ``±full_scale``, then round to the nearest level of the quantiser of ``spec``.

    Returns float64 samples, each a level ``k q`` of :class:`AdcSpec` (or the clipped
    input when ``bits`` is None). Complex input (I and Q, each on its own converter)
    is quantised part by part and returned as complex128. Within the range the error
    is at most ``q/2``; for a busy signal its power is ``q²/12`` [B]
    (:func:`quantisation_noise_power`).
    """
    x = np.asarray(samples)
    if np.iscomplexobj(x):
        z = np.asarray(x, dtype=np.complex128)
        return _quantise_real(z.real, spec) + 1j * _quantise_real(z.imag, spec)
    return _quantise_real(np.asarray(x, dtype=np.float64), spec)


def quantisation_noise_power(spec: AdcSpec) -> float:
    """Power ``q²/12`` of the quantisation error of a busy signal, amplitude units squared [B].

    0 without quantisation. Per part (I or Q) for complex samples.
    """
    return spec.step**2 / 12.0


# ---------------------------------------------------------------------------- noise


def white_noise(shape: int | tuple[int, ...], sigma: float, rng: np.random.Generator) -> NDArray[np.float64]:
    """Gaussian white noise of zero mean and standard deviation ``sigma``, float64 of ``shape``."""
    dims = _shape(shape)
    s = _non_negative(sigma, "sigma")
    return np.asarray(rng.normal(0.0, s, size=dims), dtype=np.float64)


def _check_band(transducer: Transducer, sample_rate_hz: float) -> float:
    fs = _positive(sample_rate_hz, "sample_rate_hz")
    if transducer.centre_frequency_hz >= fs / 2.0:
        raise SceneError(
            f"sample_rate_hz={fs:g} must exceed twice the centre frequency of "
            f"{transducer.name} ({transducer.centre_frequency_hz:g} Hz)"
        )
    return fs


def noise_power_gain(transducer: Transducer, sample_rate_hz: float, *, passes: int = 1) -> float:
    """Power gain ``Σ h[n]²`` of ``passes`` receiver resonators for white noise [OS §2.10].

    ``h`` is :func:`echoloc.physics.transducer.impulse_response` (long enough for its envelope
    to fall below 1e-12); by Parseval this is the mean of ``|H|²`` over the band
    0..fs. Times ``fs / 2`` it is the one-sided noise bandwidth (the analog
    resonator's is ``(π/2) B``).
    """
    p = _whole(passes, "passes", 1)
    h = impulse_response(transducer, _check_band(transducer, sample_rate_hz), passes=p)
    return float(np.sum(h * h))


def band_limited_noise(
    shape: int | tuple[int, ...],
    sigma: float,
    rng: np.random.Generator,
    transducer: Transducer,
    sample_rate_hz: float,
    *,
    passes: int = 1,
) -> NDArray[np.float64]:
    """Gaussian noise shaped by the receiver transducer's band-pass, standard deviation ``sigma``.

    White noise through ``passes`` (default 1: the receiver alone) digital resonators
    of :func:`echoloc.physics.transducer.resonator_coefficients` (``scipy.signal.lfilter``),
    scaled by ``sigma / sqrt(Σ h²)`` (:func:`noise_power_gain`), so its variance is
    ``sigma²`` in expectation and its power spectrum ``∝ |H(f)|^(2 passes)`` [OS §2.10].
    The filter runs over ``len(h)`` extra leading samples that are dropped, so the
    start-up transient (below 1e-12 of the impulse response by then) is gone and
    the noise is stationary from the first sample.
    """
    dims = _shape(shape)
    s = _non_negative(sigma, "sigma")
    p = _whole(passes, "passes", 1)
    fs = _check_band(transducer, sample_rate_hz)
    h = impulse_response(transducer, fs, passes=p)
    b, a = resonator_coefficients(transducer, fs)
    x = rng.standard_normal((*dims[:-1], dims[-1] + h.size))
    for _ in range(p):
        x = scipy.signal.lfilter(b, a, x, axis=-1)
    return np.asarray(x[..., h.size :] * (s / math.sqrt(float(np.sum(h * h)))), dtype=np.float64)


# ---------------------------------------------------------------------- resampling


def rate_ratio(from_hz: float, to_hz: float) -> tuple[int, int]:
    """``(up, down)``, coprime, with ``up / down = to_hz / from_hz``: the resampling factors.

    ``Fraction(to_hz / from_hz).limit_denominator(MAX_DENOMINATOR)``; a ratio that is
    not within :data:`RATE_TOLERANCE` (relative) of such a fraction raises
    :class:`SceneError`, since the output would not be at ``to_hz``.
    """
    f_in = _positive(from_hz, "from_hz")
    f_out = _positive(to_hz, "to_hz")
    exact = f_out / f_in
    ratio = Fraction(exact).limit_denominator(MAX_DENOMINATOR)
    if ratio == 0 or abs(float(ratio) / exact - 1.0) > RATE_TOLERANCE:
        raise SceneError(
            f"to_hz/from_hz = {f_out:g}/{f_in:g} is not within {RATE_TOLERANCE:g} of a ratio of whole "
            f"numbers with denominator <= {MAX_DENOMINATOR}"
        )
    return ratio.numerator, ratio.denominator


def output_samples(n_samples: int, from_hz: float, to_hz: float) -> int:
    """Samples :func:`resample` makes of ``n_samples``: ``ceil(n_samples up / down)``."""
    n = _whole(n_samples, "n_samples", 0)
    up, down = rate_ratio(from_hz, to_hz)
    return -(-n * up // down)


def resample(samples: ArrayLike, from_hz: float, to_hz: float, *, axis: int = -1) -> NDArray[Any]:
    """Change the sample rate from ``from_hz`` to ``to_hz`` along ``axis``, keeping every time.

    ``scipy.signal.resample_poly`` with ``(up, down)`` from :func:`rate_ratio` and its
    default Kaiser-windowed (β = 5) low-pass at the lower Nyquist frequency [CR]. The
    filter is linear-phase and its delay is removed, so output sample m is the signal
    at ``m / to_hz`` (zero phase: an echo keeps its arrival time); outside the input
    the signal is taken as zero. :func:`output_samples` samples. Real input gives
    float64, complex input complex128; equal rates return a copy.
    """
    x = np.asarray(samples)
    if not np.iscomplexobj(x):
        x = np.asarray(x, dtype=np.float64)
    if not -x.ndim <= axis < x.ndim:
        raise SceneError(f"axis={axis} does not exist in samples of shape {x.shape}")
    up, down = rate_ratio(from_hz, to_hz)
    if up == down:
        return x.copy()
    return np.asarray(scipy.signal.resample_poly(x, up, down, axis=axis))


# -------------------------------------------------------------------- signal kinds


def check_signal_kind(kind: str, carrier_hz: float, sample_rate_hz: float, output_rate_hz: float) -> None:
    """Raise SceneError unless ``kind`` can be made from rf at ``sample_rate_hz`` into ``output_rate_hz``."""
    if kind not in SIGNAL_KINDS:
        raise SceneError(f"signal kind must be 'rf', 'envelope' or 'iq', got {kind!r}")
    fc = _positive(carrier_hz, "carrier_hz")
    fs = _positive(sample_rate_hz, "sample_rate_hz")
    out = _positive(output_rate_hz, "output_rate_hz")
    if fs <= 2.0 * fc:
        raise SceneError(f"sample_rate_hz={fs:g} must exceed twice carrier_hz ({fc:g} Hz)")
    if kind == "rf" and out <= 2.0 * fc:
        raise SceneError(f"output_rate_hz={out:g} must exceed twice carrier_hz ({fc:g} Hz) for rf samples")


def analytic_signal(rf: ArrayLike) -> NDArray[np.complex128]:
    """Analytic signal ``rf + j H{rf}`` along the last axis [G], complex128 of the same shape.

    ``scipy.signal.hilbert`` on the frame zero-padded to at least twice its length,
    then cut back: the FFT method is circular, and the padding keeps the Hilbert
    transform's tails of one edge from wrapping round into the other.
    """
    x = np.asarray(rf, dtype=np.float64)
    n = x.shape[-1]
    padded = scipy.fft.next_fast_len(2 * n)
    return np.asarray(scipy.signal.hilbert(x, N=padded, axis=-1)[..., :n], dtype=np.complex128)


def _real_frames(rf: ArrayLike, name: str) -> NDArray[np.float64]:
    x = np.asarray(rf)
    if np.iscomplexobj(x):
        raise SceneError(f"{name} must be real band-pass samples, got dtype {x.dtype}")
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 0 or x.shape[-1] == 0:
        raise SceneError(f"{name} must have at least one sample on its last axis, got shape {x.shape}")
    return x


def to_signal_kind(
    rf: ArrayLike,
    kind: SignalKind,
    *,
    sample_rate_hz: float,
    carrier_hz: float,
    output_rate_hz: float,
) -> NDArray[Any]:
    """Real band-pass frames ``(..., n)`` at ``sample_rate_hz`` -> the recorded samples at ``output_rate_hz``.

    - ``"rf"``: :func:`resample` only; float64.
    - ``"iq"``: complex baseband ``iq(t) = a(t) exp(-2j π f_c t)`` (module docstring),
      with ``a`` the :func:`analytic_signal` and t = k / sample_rate_hz from the frame
      start, then low-passed and resampled by :func:`resample`; complex128.
      ``Re(iq(t) exp(2j π f_c t))`` is the rf within the band ``±output_rate_hz / 2``
      around ``f_c`` (exactly the rf when the rates are equal).
    - ``"envelope"``: ``|iq|`` at ``output_rate_hz``, float64 >= 0: the magnitude an
      ultrasonic time-of-flight chip reports.

    Output sample m is at ``m / output_rate_hz`` s after emission; there are
    :func:`output_samples` of them.
    """
    check_signal_kind(kind, carrier_hz, sample_rate_hz, output_rate_hz)
    x = _real_frames(rf, "rf")
    if kind == "rf":
        return resample(x, sample_rate_hz, output_rate_hz)
    n = x.shape[-1]
    cycles = np.mod(float(carrier_hz) / float(sample_rate_hz) * np.arange(n), 1.0)
    baseband = analytic_signal(x) * np.exp(-2j * np.pi * cycles)
    iq = np.asarray(resample(baseband, sample_rate_hz, output_rate_hz), dtype=np.complex128)
    if kind == "iq":
        return iq
    return np.asarray(np.abs(iq), dtype=np.float64)


def template_for_kind(
    returned_pulse: ArrayLike,
    kind: SignalKind,
    *,
    sample_rate_hz: float,
    carrier_hz: float,
    output_rate_hz: float,
) -> NDArray[Any]:
    """The recording's ``waveform``: an ideal echo arriving at t = 0, as ``kind`` at ``output_rate_hz``.

    :func:`to_signal_kind` of ``returned_pulse`` (1-D, at ``sample_rate_hz``, first
    sample at t = 0) placed at the start of a zero frame, cut after its last sample
    at or above :data:`TEMPLATE_FLOOR` of its peak magnitude. The frame is at least
    twice the pulse plus the resampling filter's span, and is doubled (up to 8
    times) while that sample lies in the last quarter of the frame, so the cut is
    where the response has fallen, not where the frame ends. An echo arriving at
    τ then records as this template shifted by τ (times ``exp(-2j π f_c τ)`` for iq).
    """
    check_signal_kind(kind, carrier_hz, sample_rate_hz, output_rate_hz)
    pulse = _real_frames(returned_pulse, "returned_pulse")
    if pulse.ndim != 1:
        raise SceneError(f"returned_pulse must be one pulse (1-D), got shape {pulse.shape}")
    if not np.all(np.isfinite(pulse)) or not np.any(pulse):
        raise SceneError("returned_pulse must be finite and not all zeros")
    up, down = rate_ratio(sample_rate_hz, output_rate_hz)
    span = math.ceil(10 * max(up, down) / up) + 1  # resample_poly's filter half-length, input samples
    n_frame = 2 * (pulse.size + span)
    for _ in range(9):
        frame = np.zeros(n_frame)
        frame[: pulse.size] = pulse
        y = to_signal_kind(
            frame, kind, sample_rate_hz=sample_rate_hz, carrier_hz=carrier_hz, output_rate_hz=output_rate_hz
        )
        magnitude = np.abs(y)
        last = int(np.flatnonzero(magnitude >= TEMPLATE_FLOOR * magnitude.max())[-1])
        if 4 * last < 3 * len(y):
            break
        n_frame *= 2
    return np.asarray(y[: last + 1])
