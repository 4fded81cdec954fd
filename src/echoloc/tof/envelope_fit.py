"""Time of flight at low sample rates: echo-model fits to envelope and IQ data.

A time-of-flight chip that reports its envelope (or its complex baseband) at about
20 kHz gives 17 mm of path (8.6 mm of range) per sample, so picking the largest
sample is not enough. These estimators fit a model of a whole echo to the samples,
with the delay as a continuous parameter, and so locate each echo to a small
fraction of a sample.

``envelope-fit``
    *IQ data* (and RF data, demodulated to IQ at its own rate first): the model of
    an echo is ``c T(t - τ)``, the recording's template ``T`` (``waveform``, an echo
    arriving at t = 0) shifted by τ and scaled by a complex amplitude ``c``. The
    template between samples is its band-limited interpolant (see
    :class:`BandLimitedShape`). The least-squares delay of that model is the
    envelope-level estimate. Then the carrier phase: by the receiver's complex
    baseband convention (:mod:`echoloc.sim.receiver`) an echo with real reflection
    coefficient ``a`` arriving at τ is ``a exp(-2jπ f_c τ) T(t - τ)``, so the phase of
    ``c`` gives τ modulo half a carrier period (a may be negative: an inverted
    echo); the candidate nearest the envelope-level delay is taken, and the delay
    and real amplitude are fitted once more with the phase tied to the delay. This
    is what the matched filter does for RF (:mod:`echoloc.tof.echoes`), and it brings
    the error down by the ratio of the carrier to the envelope's bandwidth. Measured
    on simulated 20 kHz IQ (Barker-13 × 4 cycles at 50 kHz through the
    ``electrostatic50`` transducers): 0.6 ns clean, and an RMSE equal to the
    Cramér-Rao bound (ratio 0.97 to 0.99 at per-sample SNR 5 to 100,
    ``tests/tof/test_envelope_fit.py``). Overlapping IQ echoes are modelled exactly (the
    sum of their complex models) and separate to within 10 ns even when four fifths
    of their length overlaps.

    *Envelope data*: the model is fitted to the **squared** envelope, low-passed.
    For an echo ``s`` in circular Gaussian noise ``n`` of power ``σ² = E|n|²``,
    ``E|s + n|² = |s|² + σ²`` exactly, whatever the SNR, whereas the magnitude
    ``E|s + n|`` is Rician, ``σ_p sqrt(π/2) L_{1/2}(-|s|²/2σ_p²)`` with ``σ_p² = σ²/2``
    per part [Ri], biased upwards where the echo is weak. Subtracting the noise
    power (estimated from the frame's median, below) removes the noise bias of the
    squared envelope completely (the Rician correction): the amplitude of weak
    echoes is then unbiased, and the arrival is not biased either way, since over
    the echo's whole support a constant is orthogonal to a shift. A squared
    envelope also suits a low rate better than the envelope itself: the magnitude
    of a band-limited IQ signal has kinks where the signal passes near zero (the
    phase reversals of a Barker code), so the envelope template sampled at one
    phase does not say what the envelope looks like half a sample later; its
    square is smooth (band-limited to twice the IQ band), and its spectrum below a
    quarter of the sample rate aliases only from the far edge of that band. Data
    and template are both low-passed to ``lowpass_fraction`` (0.25) of the sample
    rate (a Kaiser-window FIR filter, zero phase) and the model ``q Q(t - τ)``,
    ``Q = h * |T|²`` with ``q = A²``, is fitted there. Measured as above on 20 kHz
    envelopes: the clean error is at most 0.03 sample (1.5 µs), what is left of
    the aliasing (a template of exactly band-limited IQ shows the same); a fit to
    the envelope itself with a cubic, band-limited or monotone interpolant of the
    template is off by 0.15 to 0.6 sample. The price is statistical efficiency: the
    low-pass gives up the information in the envelope's sharp dips, and the RMSE is
    6.4 to 8 times the envelope Cramér-Rao bound at per-sample SNR 5 to 30 (17 at
    SNR 100, where the clean error dominates).

    Overlapping envelopes hold an interference term ``2 Re(s_i s_j*)`` that depends
    on the echoes' relative carrier phase and the template's own phase, neither of
    which an envelope recording carries (at 20 kHz a chip lasts 1.6 samples, too
    short to recover the template's sign changes from its magnitude). Groups of
    overlapping echoes are therefore fitted with the sum of their squared
    envelopes, weighting each sample by the noise and the bound on that term
    (:meth:`_Channel.interference`), after a global search over each member's delay
    (:meth:`_Channel.search`). Measured at half overlap: 58 of 64 configurations
    separated, 90 % of the delays within 0.2 sample, the rest reported as one echo.

``envelope-emg``
    The same extraction with a parametric echo shape in place of the template: the
    envelope is an exponentially modified Gaussian (EMG) [G], a Gaussian rise of
    width ``s`` (at least one sample: a narrower rise is not resolved, and sampled
    it would alias) convolved with an exponential decay of time ``d``, with onset μ
    (the Gaussian's centre) and amplitude; all four are fitted per echo, on the
    low-passed squared envelope with the noise power subtracted as above. The
    template is used once, to calibrate: an EMG fitted to the template (an echo
    arriving at t = 0) has onset ``μ_0``, width ``s_0`` and decay ``d_0``, and an
    echo's arrival is its fitted onset minus ``μ_0``. A weak echo does not determine
    its own width and decay, and left free they make its onset late (an
    amplitude-dependent bias: +6.7 µs at per-sample SNR 5 on the tests' geometry);
    a Gaussian prior on ``ln s`` and ``ln d`` about the calibration (``shape_prior``,
    0.1) holds them near the template's shape unless the echo says otherwise, a
    maximum a posteriori fit that brings that bias to +2.3 µs. Clean error 0.3 µs at
    20 kHz; RMSE 9 to 11 times the envelope bound. A smooth single-peaked shape does
    not separate overlapping echoes; it is the estimator to use when an echo's shape
    differs from the template's (absorption, spheres of different size). For RF
    and IQ data it fits the squared magnitude of the (demodulated) signal.

Extraction (both): echoes are taken out strongest first, as the matched filter's
CLEAN does: the residual (the data minus every fitted echo) is correlated with the
model at whole-sample delays, the delay explaining the most energy is fitted, the
fit is subtracted, and the search repeats. An echo that overlaps earlier ones is
refitted with them, each in turn with the others removed (successive refinement),
and every group of overlapping echoes is finally fitted jointly (all delays and
amplitudes at once). A candidate is accepted when its per-sample SNR reaches
``threshold_db`` and when it is stronger than what the echoes found so far may
leave on it: their model error (:data:`MODEL_ERROR`) times the overlap of their
models, and for envelopes their interference (:func:`_limits`); after the joint
fit, members that fail the same test against the stronger ones are dropped and
the rest fitted again. So the imperfect subtraction of a strong echo does not
become an echo of its own.

Noise: the noise power ``σ²`` (mean ``|n|²`` of the complex baseband, or of the
envelope's squared noise) is ``median(|x|²) / ln 2``, as for Rayleigh-distributed
magnitudes (:func:`echoloc.tof.echoes.noise_power`), estimated again after the first
extraction from the samples that no echo covers.

Reported: ``tof_s`` the arrival; ``amplitude`` the echo's scale in the template's
units (``|a|`` for IQ, ``sqrt(q)`` for envelopes, so an echo equal to the template
has amplitude 1); ``snr_db = 10 log10(amplitude² / σ²)``, the per-sample peak SNR
of an echo whose template peaks at 1.

Sources
-------
- [Ri] S. O. Rice, "Mathematical analysis of random noise", Bell Syst. Tech. J. 24
  (1945) 46-156, sec. 3.10: the distribution of the envelope of a sine wave plus
  noise; its mean is the Laguerre form above, and ``E|s+n|² = |s|² + σ²``.
- [K] S. M. Kay, *Fundamentals of Statistical Signal Processing: Estimation
  Theory*, Prentice Hall 1993, sec. 3.11 (range estimation), ch. 8 (least squares):
  the delay CRLB ``σ_p² / (A² Σ |ṡ|²)`` for a known signal shape in white Gaussian
  noise of variance ``σ_p²`` per real dimension.
- [OS] A. V. Oppenheim, R. W. Schafer, *Discrete-Time Signal Processing*, 3rd ed.,
  sec. 4.6 (band-limited interpolation), sec. 7.6 (Kaiser-window FIR design).
- [G] E. Grushka, "Characterization of exponentially modified Gaussian peaks in
  chromatography", Anal. Chem. 44 (1972) 1733-1738: the EMG
  ``(λ/2) exp(λ/2 (2μ + λ s² - 2t)) erfc((μ + λ s² - t) / (√2 s))``, ``λ = 1/d``.
- [MF] :mod:`echoloc.tof.echoes`, the matched filter: CLEAN extraction and the
  carrier-phase refinement with the envelope resolving the half-cycle ambiguity.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, Literal, Protocol

import numpy as np
import scipy.fft
import scipy.signal
import scipy.special
from numpy.typing import NDArray
from scipy import optimize
from scipy.interpolate import CubicSpline

from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording
from echoloc.sim.receiver import analytic_signal
from echoloc.tof.echoes import ChannelEchoes, EchoOptions, finish_channel, noise_power

FloatArray = NDArray[np.float64]
ShapeKind = Literal["template", "emg"]

_LN2 = float(np.log(2.0))

MODEL_ERROR: dict[str, float] = {"coherent": 1e-3, "power": 0.2}
"""Relative error of a fitted echo's model on clean data, per domain.

A candidate overlapping an earlier echo must have more than this fraction of that
echo's power (``|c|²`` for IQ, ``q`` for squared envelopes), times the overlap of
their models (:func:`overlap_table`), to count as an echo. Measured on clean
simulated 20 kHz data, what a fitted echo leaves for a candidate is at most 4e-6
of its power for IQ (1e-3 keeps a wide margin), and 5e-3 for squared envelopes
(1.5e-2 per unit of overlap; 0.2 also covers the distortion the interference of
overlapping echoes leaves in their fits). The EMG takes twice what its own
calibration leaves, if more (:attr:`EnvelopeFitter.model_error`).
"""

TEMPLATE_FLOOR = 1e-4
"""Shapes are cut where they fall below this fraction of their peak magnitude."""

MAX_EVALUATIONS = 60
"""Model evaluations a Levenberg-Marquardt fit may take: a good start converges in a handful,
and a parameter that no longer changes the model (an EMG rise at its one-sample
floor) must not keep it searching."""

INTERFERENCE_SHARE = 0.5
"""Fraction of the interference bound of overlapping envelopes a further echo must exceed.

The bound adds every cross term with the same sign; a coded pulse's chips and the
echoes' relative phase make them cancel in part, so a new echo must beat half of it.
"""

INTERFERENCE_FLOOR = 0.01
"""Error of the squared-envelope model, as a fraction of the echo's power.

The floor of the per-sample standard deviation the fits weigh misfits by: on clean
data the EMG's shape prior still counts, and in a group of overlapping echoes the
samples free of interference are not weighted as if the model were exact there."""


# ----------------------------------------------------------------- interpolation


def fft_upsample(samples: NDArray[Any], factor: int) -> NDArray[Any]:
    """Band-limited (periodic sinc) interpolation of ``samples`` onto a grid ``factor`` times finer.

    The spectrum is zero-padded, its Nyquist bin (even lengths) split between the
    two halves [OS 4.6]; output j is the interpolant at ``j / factor`` samples.
    Real input gives a real output.
    """
    x = np.asarray(samples)
    n = len(x)
    spectrum = scipy.fft.fft(x)
    fine = np.zeros(n * factor, dtype=complex)
    half = (n + 1) // 2
    fine[:half] = spectrum[:half]
    fine[len(fine) - (n - half) :] = spectrum[half:]
    if n % 2 == 0:
        fine[n // 2] = spectrum[n // 2] / 2
        fine[len(fine) - n // 2] = spectrum[n // 2] / 2
    out = scipy.fft.ifft(fine) * factor
    return np.asarray(out if np.iscomplexobj(x) else out.real)


@dataclass(frozen=True, eq=False)
class BandLimitedShape:
    """A sampled echo shape evaluated, with its derivative, at any time.

    ``samples[j]`` is the shape at ``start_samples + j`` samples after the echo's
    arrival. Between samples it is the band-limited interpolant [OS 4.6] of the
    samples with ``guard`` zeros on either side (FFT zero-padding onto a grid
    ``oversample`` times finer), then a cubic spline through that fine grid. The
    band-limited part is exact for a shape sampled above twice its bandwidth and
    zero outside the kept samples; the spline adds a relative error of about
    ``(5/384) (π / oversample)⁴``, 1e-7 at the default 32. The shape is zero
    outside ``support``.
    """

    samples: NDArray[Any]
    start_samples: float = 0.0
    oversample: int = 32
    guard: int = 8

    @cached_property
    def _spline(self) -> CubicSpline:
        padded = np.concatenate([np.zeros(self.guard), self.samples, np.zeros(self.guard)])
        fine = fft_upsample(padded, self.oversample)
        # The last oversample - 1 points interpolate towards the periodic wrap: dropped.
        keep = (len(padded) - 1) * self.oversample + 1
        times = self.start_samples - self.guard + np.arange(keep) / self.oversample
        return CubicSpline(times, fine[:keep])

    @property
    def support(self) -> tuple[float, float]:
        """First and last time (samples after the arrival) where the shape may be non-zero."""
        return self.start_samples - self.guard, self.start_samples + len(self.samples) - 1 + self.guard

    @cached_property
    def is_complex(self) -> bool:
        return bool(np.iscomplexobj(self.samples))

    def __call__(self, t: FloatArray) -> tuple[NDArray[Any], NDArray[Any]]:
        """The shape and its time derivative (per sample) at times ``t`` (samples after the arrival)."""
        lo, hi = self.support
        inside = (t >= lo) & (t <= hi)
        dtype = complex if self.is_complex else float
        values = np.zeros(t.shape, dtype=dtype)
        slopes = np.zeros(t.shape, dtype=dtype)
        if np.any(inside):
            spline = self._spline
            values[inside] = spline(t[inside])
            slopes[inside] = spline(t[inside], 1)
        return values, slopes


def lowpass_taps(fraction: float, half_length: int = 20, beta: float = 6.0) -> FloatArray:
    """Zero-phase low-pass FIR taps, cut-off ``fraction`` of the sample rate, ``2 half_length + 1`` taps.

    Kaiser-window design [OS 7.6] (``scipy.signal.firwin``), unit gain at DC. With
    the defaults the stop band (from ~0.33 fs at the 0.25 cut-off) is 60 dB down.
    """
    return np.asarray(scipy.signal.firwin(2 * half_length + 1, 2 * fraction, window=("kaiser", beta)))


def _lowpass(values: NDArray[Any], taps: FloatArray) -> NDArray[Any]:
    """``values`` filtered along the last axis by the symmetric ``taps``, zero phase, same length."""
    return np.asarray(scipy.signal.convolve(values, taps[(None,) * (values.ndim - 1)], mode="same"))


# ------------------------------------------------------------------ echo models


class _Model(Protocol):
    """One echo's model on sample indices ``k``, in the domain the data is fitted in.

    Parameters are a float vector; ``evaluate`` gives the values (real or complex)
    and the Jacobian (n_params, len(k)).
    """

    @property
    def n_params(self) -> int: ...

    @property
    def domain(self) -> str: ...

    def values(self, params: FloatArray, k: FloatArray) -> NDArray[Any]: ...

    def evaluate(self, params: FloatArray, k: FloatArray) -> tuple[NDArray[Any], NDArray[Any]]: ...

    def prior(self, params: FloatArray) -> tuple[FloatArray, FloatArray]: ...

    def start(self, tof_samples: float, scale: complex) -> FloatArray: ...

    def tof(self, params: FloatArray) -> float: ...

    def power(self, params: FloatArray) -> float: ...

    def extent(self, params: FloatArray) -> tuple[float, float]: ...


@dataclass(frozen=True, eq=False)
class _ShiftedShapeModel:
    """What the template models share: a ``shape`` shifted by the delay ``τ = params[0]`` (samples).

    The arrival, the extent (the shape's support from τ) and the absent prior are the
    same for the complex, coherent and squared-envelope models; each gives its own
    ``evaluate``, ``start`` and ``power``.
    """

    shape: BandLimitedShape

    def evaluate(self, params: FloatArray, k: FloatArray) -> tuple[NDArray[Any], NDArray[Any]]:
        raise NotImplementedError  # pragma: no cover - every model defines it

    def values(self, params: FloatArray, k: FloatArray) -> NDArray[Any]:
        return self.evaluate(params, k)[0]

    def prior(self, params: FloatArray) -> tuple[FloatArray, FloatArray]:
        return _NO_PRIOR

    def tof(self, params: FloatArray) -> float:
        return float(params[0])

    def extent(self, params: FloatArray) -> tuple[float, float]:
        lo, hi = self.shape.support
        return params[0] + lo, params[0] + hi


@dataclass(frozen=True, eq=False)
class _ComplexModel(_ShiftedShapeModel):
    """``c T(k - τ)``, parameters ``[τ, Re c, Im c]``: the envelope-level fit to IQ."""

    n_params: int = 3
    domain: str = "coherent"

    def evaluate(self, params: FloatArray, k: FloatArray) -> tuple[NDArray[Any], NDArray[Any]]:
        c = complex(params[1], params[2])
        values, slopes = self.shape(k - params[0])
        return c * values, np.array([-c * slopes, values, 1j * values])

    def start(self, tof_samples: float, scale: complex) -> FloatArray:
        return np.array([tof_samples, scale.real, scale.imag])

    def power(self, params: FloatArray) -> float:
        return float(params[1] ** 2 + params[2] ** 2)


@dataclass(frozen=True, eq=False)
class _CoherentModel(_ShiftedShapeModel):
    """``a exp(-2jπ ν τ) T(k - τ)``, parameters ``[τ, a]``, ν the carrier in cycles per sample."""

    cycles_per_sample: float
    n_params: int = 2
    domain: str = "coherent"

    def evaluate(self, params: FloatArray, k: FloatArray) -> tuple[NDArray[Any], NDArray[Any]]:
        tau, a = float(params[0]), float(params[1])
        omega = 2 * math.pi * self.cycles_per_sample
        rotation = complex(math.cos(omega * tau), -math.sin(omega * tau))
        values, slopes = self.shape(k - tau)
        unit = rotation * values
        return a * unit, np.array([a * rotation * (-1j * omega * values - slopes), unit])

    def start(self, tof_samples: float, scale: complex) -> FloatArray:
        return np.array([tof_samples, scale.real])

    def power(self, params: FloatArray) -> float:
        return float(params[1] ** 2)


@dataclass(frozen=True, eq=False)
class _PowerModel(_ShiftedShapeModel):
    """``q Q(k - τ)``, parameters ``[τ, q]``: the low-passed squared envelope ``Q = h * |T|²``."""

    n_params: int = 2
    domain: str = "power"

    def evaluate(self, params: FloatArray, k: FloatArray) -> tuple[NDArray[Any], NDArray[Any]]:
        tau, q = float(params[0]), float(params[1])
        values, slopes = self.shape(k - tau)
        return q * values, np.array([-q * slopes, values])

    def start(self, tof_samples: float, scale: complex) -> FloatArray:
        return np.array([tof_samples, scale.real])

    def power(self, params: FloatArray) -> float:
        return float(params[1])


def emg(u: FloatArray, width: float, decay: float) -> FloatArray:
    """Exponentially modified Gaussian [G] at ``u = t - μ``: rise ``width`` (s), decay time ``decay`` (1/λ).

    Written as ``(λ/2) exp(-u²/2s²) erfcx((λ s² - u) / (√2 s))`` (``erfc = erfcx
    exp(-z²)``), which neither overflows nor loses the tail; unit area.
    """
    rate = 1.0 / decay
    z = (rate * width**2 - u) / (math.sqrt(2.0) * width)
    gauss = np.exp(-0.5 * (u / width) ** 2)
    # Far after the peak (z very negative) erfcx(z) ~ 2 exp(z²): use the pure exponential tail.
    tail = rate * np.exp(np.minimum(0.5 * (rate * width) ** 2 - rate * u, 600.0))
    safe = np.maximum(z, -20.0)
    return np.asarray(np.where(z > -20.0, 0.5 * rate * gauss * scipy.special.erfcx(safe), tail))


@dataclass(frozen=True, eq=False)
class _EmgModel:
    """``h * (q g(k - μ)²)`` with ``g`` an EMG of peak 1; parameters ``[μ, q, ln s, ln d]``.

    ``onset_samples`` is the onset of an echo arriving at t = 0 (the calibration),
    so the arrival is ``μ - onset_samples``. ``span`` bounds the echo's extent.
    """

    taps: FloatArray
    onset_samples: float = 0.0
    span: tuple[float, float] = (-10.0, 50.0)
    n_params: int = 4
    domain: str = "power"
    calibration: FloatArray = field(default_factory=lambda: np.zeros(4))
    prior_width: float | None = None

    def _power(self, params: FloatArray, k: FloatArray) -> FloatArray:
        mu, q = float(params[0]), float(params[1])
        width, decay = (math.exp(min(max(float(v), -7.0), 9.0)) for v in params[2:4])
        # A rise narrower than a sample is not resolved at the sample rate, and sampled
        # it would alias: the Gaussian is at least one sample wide.
        width = math.hypot(1.0, width)
        half = len(self.taps) // 2
        grid = np.arange(k[0] - half, k[-1] + half + 1)
        g = emg(grid - mu, width, decay)
        peak = _emg_peak(width, decay)
        filtered = _lowpass(q * (g / peak) ** 2, self.taps)
        return np.asarray(filtered[np.asarray(k - grid[0], dtype=int)])

    def values(self, params: FloatArray, k: FloatArray) -> NDArray[Any]:
        return self._power(params, k)

    def evaluate(self, params: FloatArray, k: FloatArray) -> tuple[NDArray[Any], NDArray[Any]]:
        values = self._power(params, k)
        jac = np.empty((4, len(k)))
        jac[1] = values / params[1] if params[1] != 0 else self._power(_with(params, 1, 1.0), k)
        for i, step in ((0, 1e-4), (2, 1e-5), (3, 1e-5)):
            jac[i] = (
                self._power(_with(params, i, params[i] + step), k)
                - self._power(_with(params, i, params[i] - step), k)
            ) / (2 * step)
        return values, jac

    def prior(self, params: FloatArray) -> tuple[FloatArray, FloatArray]:
        """``(ln s - ln s_0) / w`` and ``(ln d - ln d_0) / w``: the calibrated shape, ``w = prior_width``."""
        if self.prior_width is None:
            return _NO_PRIOR
        rows = (params[2:4] - self.calibration[2:4]) / self.prior_width
        jac = np.zeros((2, 4))
        jac[0, 2] = jac[1, 3] = 1.0 / self.prior_width
        return rows, jac

    def start(self, tof_samples: float, scale: complex) -> FloatArray:
        return np.array(
            [tof_samples + self.onset_samples, scale.real, self.calibration[2], self.calibration[3]]
        )

    def tof(self, params: FloatArray) -> float:
        return float(params[0] - self.onset_samples)

    def power(self, params: FloatArray) -> float:
        return float(params[1])

    def extent(self, params: FloatArray) -> tuple[float, float]:
        tof = self.tof(params)
        return tof + self.span[0], tof + self.span[1]


_NO_PRIOR: tuple[FloatArray, FloatArray] = (np.zeros(0), np.zeros((0, 0)))


def _with(params: FloatArray, index: int, value: float) -> FloatArray:
    out = params.copy()
    out[index] = value
    return out


@functools.lru_cache(maxsize=4096)
def _emg_peak(width: float, decay: float) -> float:
    """Largest value of the unit-area EMG of ``width`` and ``decay``.

    Its derivative is ``λ (φ(u/s)/s - f(u))`` (φ the standard normal density), so at
    the peak ``f = φ/s``, i.e. ``erfcx(z) = sqrt(2/π) d / s`` with
    ``z = (λ s² - u) / (√2 s)``; erfcx decreases monotonically, so one root, found
    by Brent's method; the peak value is then ``φ(u/s)/s``.
    """
    target = math.log(math.sqrt(2.0 / math.pi) * decay / width)

    def gap(z: float) -> float:
        return math.log(float(scipy.special.erfcx(z))) - target

    lo, hi = -30.0, 1.0
    while gap(hi) > 0:
        hi *= 4.0
    z = float(optimize.brentq(gap, lo, hi, xtol=1e-12))
    u = width**2 / decay - math.sqrt(2.0) * width * z
    return math.exp(-0.5 * (u / width) ** 2) / (math.sqrt(2.0 * math.pi) * width)


# ------------------------------------------------------------------- the fitter


@dataclass(frozen=True, eq=False)
class EnvelopeFitter:
    """Everything an envelope or IQ fit reuses for one recording's template and rate.

    Attributes
    ----------
    template : ndarray
        The recording's ``waveform``: real RF, complex IQ, or a non-negative envelope.

    sample_rate_hz : float

    signal_kind : {"rf", "iq", "envelope"}

    carrier_hz : float or None
        Carrier of the IQ convention; RF data is demodulated with it. Without it,
        IQ delays stay at the envelope level (no carrier-phase refinement), and RF
        data is demodulated at the template's mean frequency.
    shape : {"template", "emg"}
        ``envelope-fit`` or ``envelope-emg``.
    noise_correction : bool
        Subtract the noise power from squared envelopes (the Rician correction);
        off only to measure what it corrects.
    lowpass_fraction : float
        Cut-off of the squared-envelope low-pass, fraction of the sample rate.
    shape_prior : float or None
        Standard deviation of the EMG's prior on ``ln s`` and ``ln d`` about the
        calibration; None fits them freely (to measure the bias the prior removes).
    """

    template: NDArray[Any]
    sample_rate_hz: float
    signal_kind: str
    carrier_hz: float | None = None
    shape: ShapeKind = "template"
    noise_correction: bool = True
    lowpass_fraction: float = 0.25
    shape_prior: float | None = 0.1

    @cached_property
    def demodulation_hz(self) -> float:
        """Frequency RF data is demodulated at: ``carrier_hz``, else the template's mean frequency."""
        if self.carrier_hz is not None:
            return float(self.carrier_hz)
        power = np.abs(np.fft.rfft(np.asarray(self.template, float))) ** 2
        freqs = np.fft.rfftfreq(len(self.template), 1 / self.sample_rate_hz)
        return float(np.sum(freqs * power) / np.sum(power))

    @cached_property
    def baseband_template(self) -> tuple[NDArray[Any], int]:
        """The template as the fitted data sees it, and the sample of its first value (<= 0).

        IQ: the waveform. Envelope: its magnitude. RF: the complex baseband of the
        waveform computed with zeros before it, so the analytic signal's tail before
        the arrival (the Hilbert transform is not causal) is kept.
        """
        if self.signal_kind == "rf":
            w = np.asarray(self.template, float)
            lead = 64
            padded = np.concatenate([np.zeros(lead), w, np.zeros(len(w) + lead)])
            t = np.arange(len(padded)) - lead
            iq = analytic_signal(padded) * np.exp(
                -2j * np.pi * self.demodulation_hz / self.sample_rate_hz * t
            )
            keep = np.flatnonzero(np.abs(iq) >= TEMPLATE_FLOOR * np.abs(iq).max())
            return iq[keep[0] : keep[-1] + 1], int(keep[0]) - lead
        if self.signal_kind == "iq":
            return np.asarray(self.template, complex), 0
        return np.abs(np.asarray(self.template, float)), 0

    @cached_property
    def coherent(self) -> bool:
        """True when the data is fitted as IQ with the template (``envelope-fit`` on RF or IQ)."""
        return self.shape == "template" and self.signal_kind in ("rf", "iq")

    @cached_property
    def cycles_per_sample(self) -> float | None:
        """Carrier in cycles per sample for the phase refinement, or None without a carrier."""
        if self.signal_kind == "rf":
            return self.demodulation_hz / self.sample_rate_hz
        if self.carrier_hz is None:
            return None
        return float(self.carrier_hz) / self.sample_rate_hz

    @cached_property
    def taps(self) -> FloatArray:
        return lowpass_taps(self.lowpass_fraction)

    @cached_property
    def complex_shape(self) -> BandLimitedShape:
        samples, start = self.baseband_template
        return BandLimitedShape(np.asarray(samples, complex), float(start))

    @cached_property
    def magnitude_shape(self) -> BandLimitedShape:
        """``|T|``, the template's magnitude, for the bound on overlapping echoes' interference."""
        samples, start = self.baseband_template
        return BandLimitedShape(np.abs(samples), float(start))

    def magnitude_overlap(self, lag_samples: float) -> float:
        """``Σ |T(k)| |T(k - L)| / Σ |T(k)|²``: how much two echoes ``L`` samples apart interfere (0 to 1)."""
        shape = self.magnitude_shape
        lo, hi = shape.support
        k = np.arange(math.floor(lo), math.ceil(hi) + 1, dtype=float)
        first = np.abs(shape(k)[0])
        second = np.abs(shape(k - lag_samples)[0])
        return float(np.sum(first * second) / np.sum(first**2))

    @cached_property
    def power_shape(self) -> BandLimitedShape:
        """``Q = h * |T|²`` over the template and the filter's reach, cut at :data:`TEMPLATE_FLOOR`."""
        samples, start = self.baseband_template
        half = len(self.taps) // 2
        power = np.concatenate([np.zeros(half), np.abs(samples) ** 2, np.zeros(half)])
        filtered = _lowpass(power, self.taps)
        keep = np.flatnonzero(np.abs(filtered) >= TEMPLATE_FLOOR * np.abs(filtered).max())
        return BandLimitedShape(filtered[keep[0] : keep[-1] + 1], float(start - half + keep[0]), guard=4)

    @cached_property
    def model(self) -> _Model:
        """The model extraction fits: complex template, squared-envelope template, or EMG."""
        if self.coherent:
            return _ComplexModel(self.complex_shape)
        if self.shape == "template":
            return _PowerModel(self.power_shape)
        return self.emg_model

    @cached_property
    def emg_model(self) -> _EmgModel:
        """The EMG model with its onset and shape calibrated on the template."""
        q_shape = self.power_shape
        lo, hi = q_shape.support
        k = np.arange(math.floor(lo), math.ceil(hi) + 1, dtype=float)
        data, _ = q_shape(k)
        peak = float(np.max(data))
        above = np.flatnonzero(data >= 0.5 * peak)
        onset = float(k[above[0]])
        duration = float(k[above[-1]] - k[above[0]]) + 1.0
        base = _EmgModel(self.taps, 0.0, (lo, hi))
        best: tuple[float, FloatArray] | None = None
        for width in (0.5, 1.0, 2.0, 4.0):
            for decay in (0.25, 0.5, 1.0, 2.0):
                guess = np.array([onset, peak, math.log(width), math.log(decay * duration)])
                fitted = _least_squares(base, data, k, [guess])
                if fitted is None:
                    continue
                cost = float(np.sum((data - base.values(fitted[0], k)) ** 2))
                if best is None or cost < best[0]:
                    best = (cost, fitted[0])
        if best is None:  # pragma: no cover - the grid always has a converging start
            raise EchoLocError("the EMG could not be fitted to the recording's waveform")
        params = best[1]
        mu, q = float(params[0]), float(params[1])
        calibration = np.array([mu, q, params[2], params[3]])
        # The EMG's amplitude for the template is q: dividing by it reports echoes in template units.
        return _EmgModel(
            self.taps, mu, (lo - 2, hi + 2), calibration=calibration, prior_width=self.shape_prior
        )

    @cached_property
    def unit_power(self) -> float:
        """The model's power parameter for an echo equal to the template (1 except for the EMG)."""
        if self.shape == "emg":
            return float(self.emg_model.calibration[1])
        return 1.0

    @cached_property
    def kernel(self) -> tuple[NDArray[Any], int]:
        """The model of a unit echo arriving at 0, at whole samples, and the sample of its first value."""
        if self.model.domain == "coherent":
            shape = self.complex_shape
            start = math.ceil(shape.start_samples)
            values, _ = shape(np.arange(start, start + len(shape.samples), dtype=float))
            return values, start
        unit = self.model.start(0.0, 1.0)
        lo, hi = self.model.extent(unit)
        start = math.ceil(lo)
        return self.model.values(unit, np.arange(start, math.floor(hi) + 1, dtype=float)), start

    @cached_property
    def overlap_table(self) -> FloatArray:
        return overlap_table(self.kernel[0])

    @cached_property
    def mainlobe_samples(self) -> float:
        """-6 dB width of the kernel's autocorrelation magnitude, samples."""
        kernel = self.kernel[0]
        acf = np.abs(np.correlate(kernel, kernel, mode="full"))
        above = np.flatnonzero(acf >= 0.5 * acf.max())
        return float(above[-1] - above[0] + 1)

    @cached_property
    def model_error(self) -> float:
        """Relative model error that candidates overlapping an echo must exceed (:data:`MODEL_ERROR`).

        For the EMG, at least twice the largest candidate its own calibration fit
        leaves in the template (relative to the template's power, per unit of
        overlap): a smooth shape leaves much of a coded pulse unexplained.
        """
        error = MODEL_ERROR[self.model.domain]
        if self.shape != "emg":
            return error
        model = self.emg_model
        q_shape = self.power_shape
        lo, hi = q_shape.support
        k = np.arange(math.floor(lo) - 2, math.ceil(hi) + 3, dtype=float)
        residual = q_shape(k)[0] - model.values(model.calibration, k)
        kernel, start = self.kernel
        leftover = _explained(_scores(residual, kernel, start), "power") / model.calibration[1]
        leak = _overlap(self.overlap_table, k)
        ratio = np.where(leak > 0, leftover / np.maximum(leak, 1e-12), 0.0)
        return max(error, 2.0 * float(ratio.max()))

    def prepare_data(self, frame: NDArray[Any]) -> NDArray[Any]:
        """The channels (n_rx, n) in the fitted representation: IQ (complex) or envelope magnitude."""
        x = np.asarray(frame)
        if self.signal_kind == "rf":
            t = np.arange(x.shape[-1])
            rotation = np.exp(-2j * np.pi * self.demodulation_hz / self.sample_rate_hz * t)
            return np.asarray(analytic_signal(np.asarray(x, float)) * rotation)
        if self.signal_kind == "iq":
            return np.asarray(x, complex)
        return np.asarray(np.abs(np.asarray(x, float)))


def envelope_fitter(recording: Recording, shape: ShapeKind = "template") -> EnvelopeFitter:
    """The :class:`EnvelopeFitter` of ``recording``, or an :class:`EchoLocError` naming what is missing."""
    name = "envelope-fit" if shape == "template" else "envelope-emg"
    if recording.signal_kind not in ("rf", "iq", "envelope"):
        raise EchoLocError(f"{recording.source}: {name} cannot read signal_kind {recording.signal_kind!r}")
    if recording.waveform is None:
        raise EchoLocError(
            f"{recording.source}: {name} needs the recording's waveform (the echo template) to fit echoes"
        )
    template = np.asarray(recording.waveform)
    if template.ndim != 1 or len(template) < 2 or not np.all(np.isfinite(template)) or not np.any(template):
        raise EchoLocError(f"{recording.source}: {name} needs a finite, non-zero 1-D waveform")
    if recording.signal_kind == "iq" and not np.iscomplexobj(template):
        template = template.astype(complex)
    return EnvelopeFitter(template, float(recording.sample_rate_hz), recording.signal_kind,
                          recording.carrier_hz, shape)  # fmt: skip


# ---------------------------------------------------------------- least squares


def _split(values: NDArray[Any]) -> FloatArray:
    if np.iscomplexobj(values):
        return np.concatenate([values.real, values.imag], axis=-1)
    return np.asarray(values, dtype=float)


def _predict(model: _Model, params: Sequence[FloatArray], k: FloatArray, dtype: Any) -> NDArray[Any]:
    total = np.zeros(len(k), dtype=dtype)
    for p in params:
        total = total + model.values(p, k)
    return total


def _least_squares(
    model: _Model,
    data: NDArray[Any],
    k: FloatArray,
    starts: Sequence[FloatArray],
    noise_std: float | FloatArray = 1.0,
) -> list[FloatArray] | None:
    """Fit ``sum_i model(params_i)`` to ``data`` at indices ``k`` jointly (Levenberg-Marquardt).

    The data's misfit is measured in units of ``noise_std`` (a number, or one per
    sample: weighted least squares) so that a model's prior (rows already in units
    of their own width) weighs against it correctly: a maximum a posteriori fit
    [K sec. 11]; without a prior a constant ``noise_std`` changes nothing. Returns
    the fitted parameters per echo, or None when the fit fails or runs away from
    the window (a delay outside ``k``).
    """
    m = model.n_params
    x0 = np.concatenate(starts)
    n_echoes = len(starts)
    scale = np.broadcast_to(np.asarray(noise_std, dtype=float), k.shape)
    if np.iscomplexobj(data):
        scale = np.concatenate([scale, scale])

    def residual(x: FloatArray) -> FloatArray:
        total = data.copy()
        priors = []
        for i in range(n_echoes):
            total = total - model.values(x[i * m : (i + 1) * m], k)
            priors.append(model.prior(x[i * m : (i + 1) * m])[0])
        return np.concatenate([_split(total) / scale, *priors])

    def jacobian(x: FloatArray) -> FloatArray:
        columns = [-model.evaluate(x[i * m : (i + 1) * m], k)[1] for i in range(n_echoes)]
        data_rows = _split(np.concatenate(columns, axis=0)).T / scale[:, None]
        prior_rows = []
        for i in range(n_echoes):
            rows = model.prior(x[i * m : (i + 1) * m])[1]
            if len(rows) == 0:
                continue
            block = np.zeros((len(rows), len(x)))
            block[:, i * m : (i + 1) * m] = rows
            prior_rows.append(block)
        return np.vstack([data_rows, *prior_rows])

    if 2 * len(k) < len(x0):
        return None
    try:
        fit = optimize.least_squares(
            residual, x0, jac=jacobian, method="lm", x_scale="jac", max_nfev=MAX_EVALUATIONS
        )
    except (ValueError, OverflowError, np.linalg.LinAlgError):
        return None
    if not np.all(np.isfinite(fit.x)):
        return None
    out = [fit.x[i * m : (i + 1) * m].copy() for i in range(len(starts))]
    if any(not k[0] - 2 <= model.tof(p) <= k[-1] + 2 for p in out):
        return None
    return out


# ------------------------------------------------------------------- extraction


def _scores(residual: NDArray[Any], kernel: NDArray[Any], kernel_start: int) -> NDArray[Any]:
    """Least-squares scale of ``kernel`` (its first value ``kernel_start`` samples after the
    arrival) for an arrival at each sample of ``residual``."""
    n, width = len(residual), len(kernel)
    pad_before = max(0, -kernel_start) + width
    pad_after = max(0, kernel_start) + width
    padded = np.concatenate([np.zeros(pad_before), residual, np.zeros(pad_after)])
    full = scipy.signal.correlate(padded, kernel, mode="valid")
    index = np.arange(n) + kernel_start + pad_before
    return np.asarray(full[index] / np.sum(np.abs(kernel) ** 2))


def _explained(scale: NDArray[Any], domain: str) -> FloatArray:
    """Echo power (model units) a score stands for: ``|c|²``, or the positive squared-envelope scale."""
    if domain == "coherent":
        return np.asarray(np.abs(scale) ** 2)
    return np.asarray(np.maximum(scale.real, 0.0))


def overlap_table(kernel: NDArray[Any]) -> FloatArray:
    """How much of an echo's model error a candidate ``L`` samples away can pick up, lags ``-(n-1)..n-1``.

    ``ρ(L) = |R(L)| / R(0)``, the kernel's normalised autocorrelation made
    non-increasing away from lag 0, raised to ``min(0.1, 10 ρ)``: where two echoes'
    models overlap only by their ends, the autocorrelation is small but the model's
    error (the template's ends) is not (measured: up to 0.8 ρ where ρ < 0.003).
    """
    acf = np.abs(np.correlate(kernel, kernel, mode="full"))
    acf = acf / acf.max()
    centre = len(kernel) - 1
    right = np.maximum.accumulate(acf[centre:][::-1])[::-1]
    left = np.maximum.accumulate(acf[: centre + 1])
    rho = np.concatenate([left[:-1], right])
    return np.asarray(np.maximum(rho, np.minimum(0.1, 10 * rho)))


def _overlap(table: FloatArray, lags: FloatArray) -> FloatArray:
    centre = len(table) // 2
    index = np.clip(np.rint(lags).astype(int) + centre, 0, len(table) - 1)
    out = table[index]
    out[np.abs(lags) > centre] = 0.0
    return np.asarray(out)


@dataclass
class _Echo:
    params: FloatArray


@dataclass(frozen=True, eq=False)
class _Channel:
    """One channel's data in the fitted domain, with the model and limits extraction uses."""

    data: NDArray[Any]
    noise_power: float
    fitter: EnvelopeFitter
    model: _Model
    options: EchoOptions

    @cached_property
    def first(self) -> int:
        """First sample an echo may arrive at (blanking)."""
        return max(0, math.ceil(self.options.blanking_s * self.fitter.sample_rate_hz))

    @cached_property
    def threshold(self) -> float:
        """Smallest accepted echo power (model units): ``threshold_db`` above the noise power."""
        return 10 ** (self.options.threshold_db / 10) * self.noise_power * self.fitter.unit_power

    def residual(self, echoes: Sequence[_Echo]) -> NDArray[Any]:
        k = np.arange(len(self.data), dtype=float)
        out = self.data.copy()
        for echo in echoes:
            lo, hi = self.window([echo])
            out[lo:hi] -= self.model.values(echo.params, k[lo:hi])
        return out

    def window(self, echoes: Sequence[_Echo], margin: int = 2) -> tuple[int, int]:
        """Sample range [lo, hi) covering the extent of ``echoes`` and ``margin`` samples more."""
        extents = [self.model.extent(e.params) for e in echoes]
        lo = math.floor(min(a for a, _ in extents)) - margin
        hi = math.ceil(max(b for _, b in extents)) + margin + 1
        return max(lo, 0), min(hi, len(self.data))

    def fit(self, echoes: list[_Echo], others: Sequence[_Echo]) -> list[_Echo] | None:
        """Fit ``echoes`` jointly, starting from their parameters, to the data less the ``others``.

        Overlapping squared envelopes are fitted by iteratively reweighted least
        squares: their interference term (:meth:`interference`) is unknown, so each
        sample's misfit is measured against the noise and that term's bound, taken
        at the previous iteration's echoes (three passes).
        """
        lo, hi = self.window(echoes)
        k = np.arange(lo, hi, dtype=float)
        data = self.data[lo:hi] - _predict(self.model, [e.params for e in others], k, self.data.dtype)
        params = [e.params for e in echoes]
        passes = 3 if self.model.domain == "power" and len(echoes) > 1 else 1
        for _ in range(passes):
            std: float | FloatArray = self.noise_std(echoes)
            if passes > 1:
                std = np.sqrt(std**2 + self.interference([_Echo(p) for p in params], k) ** 2)
            fitted = _least_squares(self.model, data, k, params, std)
            if fitted is None:
                return None
            params = fitted
        return [_Echo(p) for p in params]

    def search(self, group: list[_Echo], others: Sequence[_Echo], passes: int = 2) -> list[_Echo]:
        """Global search for overlapping squared envelopes, one member's delay at a time.

        Each member's delay is tried at every whole sample of the group's window
        with the others held, the powers solved by weighted linear least squares
        (at least 0), and the delay kept whose Gaussian negative log-likelihood
        ``Σ r²/v + ln v`` is least, with ``v`` the noise and interference variance
        of :meth:`fit` (so down-weighting cannot be bought by more overlap). The
        local fits of successive refinement otherwise settle where one template
        spans both echoes.
        """
        model = self.model
        lo, hi = self.window(group)
        k = np.arange(lo, hi, dtype=float)
        data = self.data[lo:hi] - _predict(model, [e.params for e in others], k, self.data.dtype)
        params = [e.params.copy() for e in group]

        def unit(p: FloatArray, tof: float) -> FloatArray:
            out = p.copy()
            out[0] += tof - model.tof(p)
            out[1] = 1.0
            return out

        def score(trial: list[FloatArray]) -> tuple[float, FloatArray]:
            shapes = np.array([model.values(unit(p, model.tof(p)), k) for p in trial])
            noise = self.noise_std([_Echo(p) for p in trial])
            var = noise**2 + self.interference([_Echo(p) for p in trial], k) ** 2
            weight = 1 / np.sqrt(var)
            powers, _ = optimize.nnls((shapes * weight).T, data * weight)
            misfit = data - powers @ shapes
            return float(np.sum(misfit**2 / var) + np.sum(np.log(var))), powers

        best, _ = score(params)
        for _ in range(passes):
            for i, p in enumerate(params):
                for tof in np.arange(lo, hi, dtype=float):
                    trial = [*params[:i], _with(unit(p, tof), 1, p[1]), *params[i + 1 :]]
                    cost, powers = score(trial)
                    if cost < best and np.all(powers > 0):
                        best = cost
                        params = [_with(t, 1, float(q)) for t, q in zip(trial, powers, strict=True)]
        return [_Echo(p) for p in params]

    def interference(self, echoes: Sequence[_Echo], k: FloatArray) -> FloatArray:
        """Bound on the cross terms of overlapping echoes' squared envelopes at samples ``k``.

        ``|s_i + s_j|² = |s_i|² + |s_j|² + 2 Re(s_i s_j*)``; without the carrier phases
        (envelope data) the last term is unknown but at most
        ``2 A_i A_j |T(k - τ_i)| |T(k - τ_j)|``, low-passed as the data is. Zero for IQ.
        """
        out = np.zeros(len(k))
        if self.model.domain != "power" or len(echoes) < 2:
            return out
        fitter, model = self.fitter, self.model
        half = len(fitter.taps) // 2
        grid = np.arange(k[0] - half, k[-1] + half + 1)
        magnitudes = []
        for echo in echoes:
            amplitude = math.sqrt(max(model.power(echo.params), 0.0) / fitter.unit_power)
            magnitudes.append(amplitude * np.abs(fitter.magnitude_shape(grid - model.tof(echo.params))[0]))
        cross = np.zeros(len(grid))
        for i in range(len(magnitudes)):
            for j in range(i + 1, len(magnitudes)):
                cross += 2 * magnitudes[i] * magnitudes[j]
        filtered = _lowpass(cross, fitter.taps) * fitter.unit_power
        return np.asarray(np.abs(filtered[half : half + len(k)]))

    def noise_std(self, echoes: Sequence[_Echo]) -> float:
        """Standard deviation of the fitted data's noise where ``echoes`` are.

        IQ: ``sqrt(σ²/2)`` per part. Low-passed squared envelope: ``|s+n|² - σ²`` has
        variance ``2|s|²σ² + σ⁴``, taken at half the strongest echo's power ``q``, times
        ``Σ h²`` for the low-pass; and the model is never closer than
        :data:`INTERFERENCE_FLOOR` of ``q`` (so that on clean data a prior still counts).
        """
        sigma2 = self.noise_power
        if self.model.domain == "coherent":
            return math.sqrt(sigma2 / 2)
        q = max(max(self.model.power(e.params) for e in echoes), 0.0) / self.fitter.unit_power
        floor = INTERFERENCE_FLOOR * q
        return math.sqrt(float(np.sum(self.fitter.taps**2)) * (q * sigma2 + sigma2**2) + floor**2)

    def acceptable(self, echo: _Echo) -> bool:
        power = self.model.power(echo.params)
        return bool(np.isfinite(power) and power >= self.threshold and power > 0)


def _overlaps(model: _Model, a: _Echo, b: _Echo) -> bool:
    a_lo, a_hi = model.extent(a.params)
    b_lo, b_hi = model.extent(b.params)
    return a_lo <= b_hi and b_lo <= a_hi


def _clusters(model: _Model, echoes: list[_Echo]) -> list[list[_Echo]]:
    """Groups of echoes whose extents chain together."""
    groups: list[list[_Echo]] = []
    for echo in sorted(echoes, key=lambda e: model.tof(e.params)):
        if groups and any(_overlaps(model, echo, other) for other in groups[-1]):
            groups[-1].append(echo)
        else:
            groups.append([echo])
    return groups


def _extract(channel: _Channel) -> list[_Echo]:
    """Echoes strongest first: search, fit, subtract, refit what overlaps; then joint fits."""
    model, options = channel.model, channel.options
    kernel, kernel_start = channel.fitter.kernel
    echoes: list[_Echo] = []
    while len(echoes) < options.max_echoes:
        scale = _scores(channel.residual(echoes), kernel, kernel_start)
        power = _explained(scale, model.domain)
        # A candidate must beat the noise, and what the echoes found so far leave on it.
        limit = _limits(channel, echoes)
        ratio = power / limit
        ratio[: channel.first] = 0.0
        best = int(np.argmax(ratio))
        if ratio[best] < 1.0:
            break
        fitted = channel.fit([_Echo(model.start(float(best), complex(scale[best])))], echoes)
        if fitted is None or not channel.acceptable(fitted[0]):
            break
        new = fitted[0]
        echoes.append(new)
        cluster = [e for e in echoes if e is not new and _overlaps(model, e, new)]
        if cluster:
            _refine(channel, [*cluster, new], echoes)
    return _finish(channel, echoes)


def _refine(channel: _Channel, cluster: list[_Echo], echoes: list[_Echo]) -> None:
    """Successive refinement: refit each member of ``cluster`` alone with the others removed."""
    for _ in range(channel.options.refine_passes):
        for member in cluster:
            refitted = channel.fit([member], [e for e in echoes if e is not member])
            if refitted is not None and channel.acceptable(refitted[0]):
                member.params = refitted[0].params


def _limits(channel: _Channel, echoes: Sequence[_Echo]) -> FloatArray:
    """Least power (model units) an echo arriving at each sample needs beside ``echoes``.

    The detection threshold; the dynamic range below the strongest; what each echo's
    model error leaves on a neighbour (``model_error × power × overlap``); and for
    squared envelopes what the interference of overlapping echoes could leave.
    """
    model, fitter = channel.model, channel.fitter
    n = len(channel.data)
    lags = np.arange(n, dtype=float)
    floor = 10 ** (-channel.options.dynamic_range_db / 10)
    strongest = max((model.power(e.params) for e in echoes), default=0.0)
    limit = np.full(n, max(channel.threshold, floor * strongest))
    for echo in echoes:
        leak = _overlap(fitter.overlap_table, lags - model.tof(echo.params))
        limit = np.maximum(limit, fitter.model_error * model.power(echo.params) * leak)
    if model.domain == "power" and len(echoes) > 1:
        kernel, kernel_start = fitter.kernel
        bound = _scores(channel.interference(echoes, lags), kernel, kernel_start)
        limit = np.maximum(limit, INTERFERENCE_SHARE * np.abs(bound))
        # A pair that interferes is fitted with an incomplete model: what it leaves
        # spreads over both echoes' reach, in proportion to their interference.
        for i, a in enumerate(echoes):
            for b in echoes[i + 1 :]:
                strength = 2 * math.sqrt(max(model.power(a.params) * model.power(b.params), 0.0))
                share = fitter.magnitude_overlap(model.tof(b.params) - model.tof(a.params))
                if share <= 0:
                    continue
                reach = np.maximum(
                    _overlap(fitter.overlap_table, lags - model.tof(a.params)),
                    _overlap(fitter.overlap_table, lags - model.tof(b.params)),
                )
                limit = np.maximum(limit, INTERFERENCE_SHARE * strength * share * reach)
    return limit


def _significant(channel: _Channel, members: list[_Echo]) -> list[_Echo]:
    """Members, strongest first, that pass :func:`_limits` beside the stronger ones kept.

    Also drops a member closer than a quarter main lobe to a stronger one (one echo
    split in two).
    """
    model = channel.model
    n = len(channel.data)
    kept: list[_Echo] = []
    for echo in sorted(members, key=lambda e: -model.power(e.params)):
        tof, power = model.tof(echo.params), model.power(echo.params)
        if any(abs(tof - model.tof(e.params)) < channel.fitter.mainlobe_samples / 4 for e in kept):
            continue
        index = min(max(round(tof), 0), n - 1)
        if power > 0 and power >= _limits(channel, kept)[index]:
            kept.append(echo)
    return kept


def _finish(channel: _Channel, echoes: list[_Echo]) -> list[_Echo]:
    """Joint fits of overlapping groups, dropping members that are not significant, until none is dropped.

    Squared envelopes are searched globally first (:meth:`_Channel.search`).
    """
    model = channel.model
    result: list[_Echo] = []
    for group in _clusters(model, echoes):
        others = [e for e in echoes if all(e is not g for g in group)]
        members = group
        for _ in range(len(group)):
            if len(members) > 1:
                start = channel.search(members, others) if model.domain == "power" else members
                members = channel.fit(start, others) or members
            elif len(members) < len(group):
                members = channel.fit(members, others) or members
            kept = _significant(channel, members)
            if len(kept) == len(members):
                break
            members = kept
        result.extend(e for e in members if channel.acceptable(e))
    return sorted(result, key=lambda e: model.tof(e.params))


def _coherent_refinement(channel: _Channel, echoes: list[_Echo]) -> tuple[_Model, list[_Echo]]:
    """From envelope-level ``[τ, c]`` to carrier-phase ``[τ, a]`` fits, group by group.

    ``c exp(2jπ ν τ)`` should be real (``a``); its phase moves τ by at most a quarter
    carrier period to the nearest delay where it is (0 or π: the half-cycle
    ambiguity is resolved by the envelope-level delay) [MF]. Overlapping echoes are
    then fitted jointly with the coherent model; a fit that moves a delay by a
    quarter period or more (to another branch) is not taken.
    """
    fitter = channel.fitter
    nu = fitter.cycles_per_sample
    assert nu is not None
    coherent = _CoherentModel(fitter.complex_shape, nu)
    starts: list[_Echo] = []
    for echo in echoes:
        tau, c = float(echo.params[0]), complex(echo.params[1], echo.params[2])
        delta = math.remainder(float(np.angle(c * np.exp(2j * np.pi * nu * tau))), math.pi)
        tau_phase = tau - delta / (2 * math.pi * nu)
        a = (c * np.exp(2j * np.pi * nu * tau_phase)).real
        starts.append(_Echo(coherent.start(tau_phase, complex(a))))
    refined = _Channel(channel.data, channel.noise_power, fitter, coherent, channel.options)
    result: list[_Echo] = []
    quarter = 0.25 / nu
    for group in _clusters(coherent, starts):
        fitted = refined.fit(group, [e for e in starts if all(e is not g for g in group)])
        if fitted is not None and all(
            abs(f.params[0] - g.params[0]) < quarter for f, g in zip(fitted, group, strict=True)
        ):
            group = fitted
        result.extend(group)
    return coherent, result


def _channel(fitter: EnvelopeFitter, x: NDArray[Any], noise: float, options: EchoOptions) -> _Channel:
    if fitter.model.domain == "coherent":
        data: NDArray[Any] = np.asarray(x, complex)
    else:
        data = _lowpass(np.abs(x) ** 2 - (noise if fitter.noise_correction else 0.0), fitter.taps)
    return _Channel(data, noise, fitter, fitter.model, options)


def fit_channel(fitter: EnvelopeFitter, x: NDArray[Any], options: EchoOptions) -> ChannelEchoes:
    """Echoes of one channel ``x`` (already in the fitted representation, see ``prepare_data``).

    Extraction runs twice: the first noise estimate includes the echoes, so it is
    estimated again from the samples no echo covers (when at least an eighth of the
    frame is left) and the echoes are extracted again with it.
    """
    noise = noise_power(x)
    channel = _channel(fitter, x, noise, options)
    echoes = _extract(channel)
    if echoes:
        quiet = np.ones(len(x), dtype=bool)
        for echo in echoes:
            lo, hi = fitter.model.extent(echo.params)
            quiet[max(math.floor(lo), 0) : max(math.ceil(hi) + 1, 0)] = False
        if quiet.sum() >= max(16, len(x) // 8):
            noise = noise_power(x[quiet])
            channel = _channel(fitter, x, noise, options)
            echoes = _extract(channel)
    model = fitter.model
    if fitter.coherent and fitter.cycles_per_sample is not None and echoes:
        model, echoes = _coherent_refinement(channel, echoes)
    tof = np.array([model.tof(e.params) for e in echoes]) / fitter.sample_rate_hz
    power = np.array([model.power(e.params) for e in echoes]) / fitter.unit_power
    amplitude = np.sqrt(np.maximum(power, 0.0))
    snr_db = 10 * np.log10(np.maximum(power, 1e-300) / noise)
    return finish_channel(tof, amplitude, snr_db, options)


def envelope_fit_echoes(
    frames: NDArray[Any], fitter: EnvelopeFitter, options: EchoOptions
) -> list[ChannelEchoes]:
    """Fitted echoes of one frame (n_rx, n_samples), one :class:`ChannelEchoes` per receiver."""
    data = fitter.prepare_data(frames)
    return [fit_channel(fitter, channel, options) for channel in data]
