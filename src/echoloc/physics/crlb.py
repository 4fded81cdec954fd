"""Cramér-Rao lower bounds on the time of arrival of an echo.

The smallest variance any unbiased estimator of an echo's delay can reach, for the
three ways this project records echoes:

``rf`` with a known carrier phase (:func:`coherent_tof_bound`)
    Real band-pass samples ``x[n] = A s(nT - τ) + w[n]``, white Gaussian noise of
    variance σ² per sample, the pulse ``s`` known, ``τ`` and ``A`` unknown. The
    Fisher information of ``τ`` is ``A² Σ ṡ(nT - τ)² / σ²`` with ``ṡ`` the time
    derivative of the band-limited (sinc-interpolated) pulse [K, eq. 3.39]. For a
    real pulse the cross term ``Σ s ṡ`` of delay and amplitude vanishes (``∫ s ṡ dt
    = [s²/2] = 0``, and a band-limited sum equals ``fs`` times the integral), so the
    unknown amplitude costs nothing and ``var(τ) ≥ σ² / (A² Σ ṡ²)``. The 2×2 Fisher
    matrix is inverted all the same, so a pulse for which the cross term is not
    negligible (sampled too slowly, cut abruptly) gets the right bound.
    Equivalently ``var(τ) ≥ 1 / ((2E/N0) β²)``, with ``β²`` the mean-square angular
    frequency of the pulse's spectrum ("Gabor bandwidth", :func:`rms_bandwidth_hz`)
    [K, eq. 3.40], [VT, sec. 2.4]: the carrier dominates ``β``, which is why an
    estimator that follows the carrier phase (the matched filter here) can reach
    micrometres.

``rf`` or ``iq`` with an unknown carrier phase (:func:`unknown_phase_tof_bound`)
    The phase of the echo is a nuisance parameter (an incoherent receiver, or IQ
    samples whose absolute phase is not trusted): Fisher matrix over delay,
    amplitude and phase, ``s_φ = s cos φ - H{s} sin φ`` for a real pulse
    (``H`` the Hilbert transform) or ``A e^{jφ} u(t - τ)`` for a complex envelope
    ``u``. Eliminating the phase leaves
    ``var(τ) ≥ 1 / ((2E/N0) (2π)² B_c²)`` with ``B_c`` the rms bandwidth of the
    spectrum about its centroid [VT, sec. 2.4; K, problem 3.24]: only the envelope
    carries information, the carrier frequency drops out.

Envelope samples at a low rate (:func:`envelope_tof_bound`)
    ``e[n] = A ε(nT - τ) + v[n]`` with ``ε`` the known envelope template (e.g. a
    time-of-flight chip's magnitude output at 20 kHz) and ``v`` white Gaussian noise
    of variance σ_e² on the envelope samples: ``var(τ) ≥ σ_e² / (A² Σ ε̇[n]²)``
    (the coherent formula applied to the envelope). The noise model is an
    approximation: the magnitude of a signal in complex Gaussian noise is Rician
    [R, sec. 3.10]; at high SNR its fluctuation is the in-phase noise component,
    Gaussian with the variance of one quadrature (:func:`envelope_noise_sigma`),
    and the bound holds; below an envelope SNR of a few the noise is not Gaussian,
    not zero-mean (the Rician bias) and the bound is not the right one. ``ε̇`` is
    the band-limited derivative of the samples, or, for an envelope that is not
    band-limited at its own rate (the magnitude of a band-limited complex signal
    has kinks where it passes near zero), an analytic one
    (:func:`envelope_derivative`).

Noise and SNR conventions (:func:`per_sample_snr`, :func:`energy_to_noise_ratio`):
the project's per-sample SNR is the echo's peak amplitude (the peak of its
band-limited envelope) over σ, as in :mod:`echoloc.sim.scene`; the energy ratio is
``E/N0 = A² Σ s² / (2 σ²)`` (real samples at rate ``fs`` carry white noise of
two-sided density ``N0/2 = σ² / fs``; the pulse's energy is ``E = A² Σ s² / fs``).
Every bound is returned in seconds (:attr:`TofBound.std_s`) and converts to metres
of path (× c) and of one-way range (× c / 2).

Sources
-------
- [K] S. M. Kay, *Fundamentals of Statistical Signal Processing, vol. I:
  Estimation Theory*, Prentice Hall 1993, sec. 3.11 (range estimation, eqs.
  3.37-3.40) and sec. 3.7-3.9 (vector parameters, the Fisher matrix, nuisance
  parameters).
- [VT] H. L. Van Trees, *Detection, Estimation, and Modulation Theory, part I*,
  Wiley 1968, sec. 2.4 and 4.2 (the delay of a known signal; mean-square
  bandwidth).
- [R] S. O. Rice, "Mathematical analysis of random noise", Bell Syst. Tech. J. 24
  (1945) 46-156, sec. 3.10 (the envelope of a sine wave plus noise).
- [OS] A. V. Oppenheim, R. W. Schafer, *Discrete-Time Signal Processing*, 3rd ed.,
  sec. 7.4 (band-limited differentiation by ``jω`` in frequency) and 12.2 (the
  discrete Hilbert transform).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import scipy.fft
from numpy.typing import ArrayLike, NDArray

from echoloc.errors import EchoLocError

SampleKind = Literal["rf", "iq", "envelope"]

PAD_FACTOR = 8
"""Pulses are zero-padded to at least this many times their length before the FFT.

The band-limited derivative and Hilbert transform have sinc-like tails that extend
beyond the pulse; the padding holds them. For the report's received pulse (244
samples at 200 kHz) the bounds change by less than 1e-11 relative from a factor of
8 to 64."""


@dataclass(frozen=True, eq=False)
class TofBound:
    """A Cramér-Rao bound on the time of arrival.

    Attributes
    ----------
    std_s : float
        Lower bound on the standard deviation of any unbiased delay estimate, s:
        ``sqrt((F⁻¹)₀₀)``.
    fisher : ndarray, shape (p, p)
        Fisher information matrix over ``parameters`` (delay in s, amplitude in the
        pulse's units, phase in rad).
    parameters : tuple of str
        Names of the parameters, the delay ``"tof_s"`` first.
    """

    std_s: float
    fisher: NDArray[np.float64]
    parameters: tuple[str, ...]

    @property
    def known_nuisance_std_s(self) -> float:
        """The bound if every parameter but the delay were known: ``1 / sqrt(F₀₀)``, s.

        Equal to :attr:`std_s` when the delay decouples from the other parameters
        (a real pulse's amplitude does).
        """
        return 1.0 / math.sqrt(float(self.fisher[0, 0]))

    def path_std_m(self, speed_of_sound_m_s: float) -> float:
        """The bound as a standard deviation of the path length (tof × c), m."""
        return self.std_s * float(speed_of_sound_m_s)

    def range_std_m(self, speed_of_sound_m_s: float) -> float:
        """The bound on one-way range (path / 2, a co-located transmitter and receiver), m."""
        return 0.5 * self.path_std_m(speed_of_sound_m_s)


# --- checks ------------------------------------------------------------------------


def _positive(value: float, name: str) -> float:
    v = float(value)
    if not (math.isfinite(v) and v > 0):
        raise EchoLocError(f"{name} must be a finite number > 0, got {value!r}")
    return v


def _pulse(samples: ArrayLike, name: str = "pulse") -> NDArray[np.float64] | NDArray[np.complex128]:
    x = np.asarray(samples)
    if x.ndim != 1 or x.size < 2:
        raise EchoLocError(f"{name} must be one pulse of at least 2 samples (1-D), got shape {x.shape}")
    x = np.asarray(x, dtype=np.complex128 if np.iscomplexobj(x) else np.float64)
    if not np.all(np.isfinite(x)) or not np.any(x):
        raise EchoLocError(f"{name} must be finite and not all zeros")
    return x


# --- band-limited operators --------------------------------------------------------


def _padded_length(n: int) -> int:
    return int(scipy.fft.next_fast_len(PAD_FACTOR * n + 64))


def _frequencies_hz(n_fft: int, sample_rate_hz: float) -> NDArray[np.float64]:
    """FFT bin frequencies with the Nyquist bin (even lengths) set to 0.

    The Nyquist bin's sign is ambiguous; zeroing it keeps the derivative and the
    Hilbert transform of a real signal real.
    """
    freqs = scipy.fft.fftfreq(n_fft, 1.0 / sample_rate_hz)
    if n_fft % 2 == 0:
        freqs[n_fft // 2] = 0.0
    return np.asarray(freqs)


def bandlimited_derivative(
    samples: ArrayLike, sample_rate_hz: float, *, n_fft: int | None = None
) -> NDArray[np.float64] | NDArray[np.complex128]:
    """Time derivative of the band-limited interpolant of ``samples``, at the sample instants.

    The samples are zero-padded to ``n_fft`` (default :data:`PAD_FACTOR` times their
    length), transformed, multiplied by ``2πjf`` and transformed back [OS, sec. 7.4]:
    exact for the periodic band-limited signal of period ``n_fft``, and for a pulse
    with no energy at the Nyquist frequency, the derivative of its sinc
    interpolant. The result has ``n_fft`` samples (the derivative's tails run past the
    pulse; the last ones are those before its start, by periodicity). Units: samples'
    units per second.
    """
    x = _pulse(samples, "samples")
    fs = _positive(sample_rate_hz, "sample_rate_hz")
    size = _padded_length(len(x)) if n_fft is None else int(n_fft)
    if size < len(x):
        raise EchoLocError(f"n_fft={size} is shorter than the {len(x)} samples")
    spectrum = scipy.fft.fft(x, size)
    derivative = scipy.fft.ifft(2j * np.pi * _frequencies_hz(size, fs) * spectrum)
    if np.iscomplexobj(x):
        return np.asarray(derivative, dtype=np.complex128)
    return np.asarray(derivative.real, dtype=np.float64)


def _padded(x: NDArray[np.float64] | NDArray[np.complex128], size: int) -> NDArray[np.complex128]:
    out = np.zeros(size, dtype=np.complex128)
    out[: len(x)] = x
    return out


def hilbert_transform(samples: ArrayLike, *, n_fft: int | None = None) -> NDArray[np.float64]:
    """Hilbert transform ``H{s}`` of a real pulse (multiplication by ``-j sign f``) [OS, sec. 12.2].

    ``s + j H{s}`` is the analytic signal; ``s cos φ - H{s} sin φ`` is the pulse with
    its carrier phase advanced by φ. Zero-padded as :func:`bandlimited_derivative`.
    """
    x = _pulse(samples, "samples")
    if np.iscomplexobj(x):
        raise EchoLocError("the Hilbert transform here is for real pulses; a complex envelope has its phase")
    size = _padded_length(len(x)) if n_fft is None else int(n_fft)
    freqs = _frequencies_hz(size, 1.0)
    spectrum = scipy.fft.fft(x, size)
    return np.asarray(scipy.fft.ifft(-1j * np.sign(freqs) * spectrum).real, dtype=np.float64)


def envelope_derivative(iq: ArrayLike, sample_rate_hz: float) -> NDArray[np.float64]:
    """Analytic derivative of the envelope ``|u(t)|`` of a complex envelope, at its samples.

    ``d|u|/dt = Re(conj(u) u̇) / |u|`` with ``u̇`` the band-limited derivative of the
    complex samples (:func:`bandlimited_derivative`, its first ``len(iq)`` samples),
    0 where ``u`` vanishes. Use it when the envelope itself is not band-limited at its
    rate: the magnitude of a phase-coded pulse has kinks at the phase reversals,
    while the complex envelope it comes from is band-limited (the receiver low-passes
    it before decimation).
    """
    u = _pulse(iq, "iq")
    u = np.asarray(u, dtype=np.complex128)
    du = np.asarray(bandlimited_derivative(u, sample_rate_hz), dtype=np.complex128)[: len(u)]
    magnitude = np.abs(u)
    product = np.real(np.conj(u) * du)
    safe = np.where(magnitude > 0, magnitude, 1.0)
    return np.asarray(np.where(magnitude > 0, product / safe, 0.0), dtype=np.float64)


# --- SNR ---------------------------------------------------------------------------


def peak_amplitude(samples: ArrayLike, signal_kind: SampleKind = "rf", *, oversample: int = 16) -> float:
    """Peak of a pulse's band-limited envelope: the "peak amplitude" of the per-sample SNR.

    ``rf``: the largest magnitude of the analytic signal (the carrier's crest can fall
    between samples, by up to ``1 - cos(π f0 / fs)`` of the peak; the envelope
    cannot); ``iq``: of the complex envelope; ``envelope``: of the samples
    themselves. Each on a grid ``oversample`` times finer (band-limited interpolation
    by zero-padding the FFT).
    """
    x = _pulse(samples, "samples")
    size = _padded_length(len(x))
    if signal_kind == "envelope":
        fine = scipy.fft.irfft(scipy.fft.rfft(np.real(x), size), size * oversample) * oversample
        return float(max(np.max(np.abs(fine)), np.max(np.abs(x))))
    spectrum = scipy.fft.fft(x, size)
    if signal_kind == "rf":
        if np.iscomplexobj(x):
            raise EchoLocError("signal_kind 'rf' needs real samples")
        freqs = _frequencies_hz(size, 1.0)
        spectrum = spectrum * (1.0 + np.sign(freqs))  # analytic: 2X for f > 0, X at 0
    elif signal_kind != "iq":
        raise EchoLocError(f"signal_kind must be 'rf', 'iq' or 'envelope', got {signal_kind!r}")
    fine_spectrum = np.zeros(size * oversample, dtype=complex)
    half = size // 2
    fine_spectrum[:half] = spectrum[:half]
    fine_spectrum[-(size - half) :] = spectrum[half:]
    fine = scipy.fft.ifft(fine_spectrum) * oversample
    return float(max(np.max(np.abs(fine)), np.max(np.abs(x))))


def per_sample_snr(
    samples: ArrayLike, amplitude: float, noise_sigma: float, signal_kind: SampleKind = "rf"
) -> float:
    """The project's per-sample amplitude SNR: ``|A| peak_amplitude(s) / σ`` (scene.py convention)."""
    return (
        abs(float(amplitude)) * peak_amplitude(samples, signal_kind) / _positive(noise_sigma, "noise_sigma")
    )


def amplitude_for_snr(
    samples: ArrayLike, snr: float, noise_sigma: float, signal_kind: SampleKind = "rf"
) -> float:
    """The echo amplitude ``A`` that gives per-sample SNR ``snr`` (linear, not dB) at noise ``σ``."""
    return float(snr) * _positive(noise_sigma, "noise_sigma") / peak_amplitude(samples, signal_kind)


def energy_to_noise_ratio(samples: ArrayLike, amplitude: float, noise_sigma: float) -> float:
    """``E / N0 = A² Σ|s|² / (2 σ²)`` (linear), σ the noise per real sample or per quadrature.

    For real samples at ``fs`` with white noise of variance σ², the two-sided noise
    density is ``N0/2 = σ²/fs`` and the pulse's energy ``E = A² Σ s² / fs``. For
    complex-envelope samples (``iq``, the receiver's convention ``rf = Re(u e^{jωt})``)
    with σ² per quadrature the same expression holds.
    """
    x = _pulse(samples)
    sigma = _positive(noise_sigma, "noise_sigma")
    return float(amplitude) ** 2 * float(np.sum(np.abs(x) ** 2)) / (2.0 * sigma**2)


def rms_bandwidth_hz(
    samples: ArrayLike, sample_rate_hz: float, *, about: Literal["zero", "centroid"] = "zero"
) -> float:
    """Root-mean-square frequency of a pulse's power spectrum, Hz [VT, sec. 2.4].

    ``about = "zero"``: ``sqrt(∫ f² |S|² df / ∫ |S|² df)`` (for a real pulse over the
    whole spectrum: ``β / 2π``, the carrier included). ``"centroid"``: about the
    power-weighted mean frequency of the positive-frequency (analytic) spectrum of a
    real pulse, or of the whole spectrum of a complex envelope: the envelope's rms
    bandwidth ``B_c``.
    """
    x = _pulse(samples)
    fs = _positive(sample_rate_hz, "sample_rate_hz")
    size = _padded_length(len(x))
    freqs = _frequencies_hz(size, fs)
    power = np.abs(scipy.fft.fft(x, size)) ** 2
    if about == "zero":
        return float(np.sqrt(np.sum(freqs**2 * power) / np.sum(power)))
    if about != "centroid":
        raise EchoLocError(f"about must be 'zero' or 'centroid', got {about!r}")
    if not np.iscomplexobj(x):
        power = np.where(freqs > 0, power, 0.0)
    mean = float(np.sum(freqs * power) / np.sum(power))
    return float(np.sqrt(np.sum((freqs - mean) ** 2 * power) / np.sum(power)))


# --- bounds ------------------------------------------------------------------------


_CONDITION_LIMIT = 1e12
"""Largest condition number of the normalised Fisher matrix still read as identifiable:
beyond it the bound's variance holds fewer than ~4 significant digits in float64."""


def _fisher(columns: list[NDArray[np.generic]], noise_sigma: float) -> NDArray[np.float64]:
    """``F_ij = Re(Σ conj(∂μ/∂θ_i) ∂μ/∂θ_j) / σ²`` for white Gaussian noise [K, eq. 3.31].

    Complex samples count as two real observations (real and imaginary part), each
    with variance σ², which gives the real part of the complex inner product.
    """
    stacked = np.vstack(columns)
    with np.errstate(over="ignore", invalid="ignore"):  # a non-finite result is _bound's error
        gram = np.conj(stacked) @ stacked.T
    return np.asarray(np.real(gram) / noise_sigma**2, dtype=np.float64)


def _bound(fisher: NDArray[np.float64], parameters: tuple[str, ...]) -> TofBound:
    singular = EchoLocError("the Fisher matrix is singular: the delay is not identifiable from this pulse")
    # Judge singularity on the correlation form D^-1/2 F D^-1/2 (units drop out): two
    # parameters whose derivatives are proportional give a condition number near 1/eps,
    # whatever LAPACK build and numpy version round the inverse.
    if not np.all(np.isfinite(fisher)):
        raise EchoLocError(
            "the Fisher matrix is not finite: the amplitude over the noise sigma is not a finite, "
            "representable ratio"
        )
    diagonal = np.diag(fisher)
    if not np.all(diagonal > 0):
        raise singular
    scale = 1.0 / np.sqrt(diagonal)
    if not np.linalg.cond(fisher * np.outer(scale, scale)) < _CONDITION_LIMIT:
        raise singular
    covariance = np.linalg.inv(fisher)
    variance = float(covariance[0, 0])
    if not variance > 0:
        raise singular
    return TofBound(std_s=math.sqrt(variance), fisher=fisher, parameters=parameters)


_Samples = NDArray[np.float64] | NDArray[np.complex128]
"""Real (rf, envelope) or complex (iq) samples."""


def _pulse_terms(
    pulse: ArrayLike, sample_rate_hz: float, amplitude: float, noise_sigma: float
) -> tuple[_Samples, float, float, int, _Samples]:
    """The checked inputs of a known-pulse bound and the pulse's band-limited derivative.

    Returns ``(s, A, σ, n_fft, ṡ)``: the pulse, amplitude and noise sigma, the padded
    FFT length the Fisher matrix's columns are taken at, and ``ṡ`` (units per second)
    at that length. Shared by the coherent and unknown-phase bounds so that both
    check the pulse, then the rate, then σ, and report the same first error.
    """
    s = _pulse(pulse)
    fs = _positive(sample_rate_hz, "sample_rate_hz")
    sigma = _positive(noise_sigma, "noise_sigma")
    a = float(amplitude)
    size = _padded_length(len(s))
    ds = bandlimited_derivative(s, fs, n_fft=size)
    return s, a, sigma, size, ds


def coherent_tof_bound(
    pulse: ArrayLike, sample_rate_hz: float, *, amplitude: float, noise_sigma: float
) -> TofBound:
    """Bound on the delay of a known pulse with unknown amplitude in white Gaussian noise.

    Model ``x[n] = A s(nT - τ) + w[n]``, ``w ~ N(0, σ²)`` white; parameters ``(τ, A)``.
    The derivatives ``∂μ/∂τ = -A ṡ`` and ``∂μ/∂A = s`` are band-limited (FFT, see
    :func:`bandlimited_derivative`) and summed over every sample the echo touches,
    which for a band-limited pulse does not depend on ``τ`` [K, sec. 3.11]:

        F = (1/σ²) [[A² Σ ṡ², -A Σ s ṡ], [-A Σ s ṡ, Σ s²]],   var(τ) ≥ (F⁻¹)₀₀.

    For a real pulse ``Σ s ṡ = 0`` and the bound is ``σ² / (A² Σ ṡ²)`` (see the
    module docstring); a complex pulse (``iq``, known phase) uses the complex form
    with σ² per quadrature.

    Parameters
    ----------
    pulse : array_like, shape (n,)
        The echo template ``s`` (real rf, or complex baseband), sample units.
    sample_rate_hz : float
        Rate of the samples, Hz.
    amplitude : float
        The echo's scale ``A`` (the echo is ``A s``).
    noise_sigma : float
        Standard deviation σ of the noise per sample (per quadrature if complex).

    Returns
    -------
    TofBound
        ``std_s`` in seconds; parameters ``("tof_s", "amplitude")``.
    """
    s, a, sigma, size, ds = _pulse_terms(pulse, sample_rate_hz, amplitude, noise_sigma)
    fisher = _fisher([-a * ds, _padded(s, size)], sigma)
    return _bound(fisher, ("tof_s", "amplitude"))


def unknown_phase_tof_bound(
    pulse: ArrayLike, sample_rate_hz: float, *, amplitude: float, noise_sigma: float
) -> TofBound:
    """Bound on the delay when the echo's carrier phase is unknown too (incoherent reception).

    Real pulse ``s``: model ``A (s(t - τ) cos φ - H{s}(t - τ) sin φ)``; complex envelope
    ``u``: ``A e^{jφ} u(t - τ)``; parameters ``(τ, A, φ)``, σ² per sample (per
    quadrature). The phase absorbs the carrier's part of the delay information and
    the bound becomes (module docstring; [VT, sec. 2.4])

        var(τ) ≥ 1 / ((2E/N0) (2π B_c)²)

    with ``B_c = rms_bandwidth_hz(pulse, fs, about="centroid")``; computed here from the
    3×3 Fisher matrix, which needs no assumption on the pulse.

    Returns
    -------
    TofBound
        ``std_s`` in seconds; parameters ``("tof_s", "amplitude", "phase_rad")``.
    """
    s, a, sigma, size, ds = _pulse_terms(pulse, sample_rate_hz, amplitude, noise_sigma)
    padded = _padded(s, size)
    if np.iscomplexobj(s):
        d_phase: NDArray[np.generic] = 1j * a * padded
    else:
        d_phase = -a * hilbert_transform(s, n_fft=size)
    fisher = _fisher([-a * ds, padded, d_phase], sigma)
    return _bound(fisher, ("tof_s", "amplitude", "phase_rad"))


def envelope_tof_bound(
    envelope: ArrayLike,
    sample_rate_hz: float,
    *,
    amplitude: float,
    noise_sigma: float,
    derivative: ArrayLike | None = None,
) -> TofBound:
    """Bound on the delay from envelope samples with additive Gaussian noise on them.

    Model ``e[n] = A ε(nT - τ) + v[n]``, ``v ~ N(0, σ_e²)`` white (the high-SNR
    approximation of Rician envelope noise: see the module docstring and
    :func:`envelope_noise_sigma`); parameters ``(τ, A)``:

        var(τ) ≥ σ_e² / (A² Σ ε̇[n]²)     (when Σ ε ε̇ = 0; the 2×2 inverse in general).

    Parameters
    ----------
    envelope : array_like, shape (n,)
        The envelope template ``ε`` (real, >= 0) at ``sample_rate_hz``.
    sample_rate_hz : float
        Rate of the envelope samples, Hz (e.g. 20 kHz).
    amplitude, noise_sigma : float
        The echo's scale ``A`` and the envelope noise's standard deviation σ_e.
    derivative : array_like, shape (n,), optional
        ``ε̇`` at the same instants, units per second: the analytic derivative of a
        smooth parametric envelope, or :func:`envelope_derivative` of the complex
        envelope. Sums then run over the given samples. Default: the band-limited
        derivative of the samples (exact only if the envelope is band-limited at
        its rate).

    Returns
    -------
    TofBound
        ``std_s`` in seconds; parameters ``("tof_s", "amplitude")``.
    """
    e = _pulse(envelope, "envelope")
    if np.iscomplexobj(e):
        raise EchoLocError("envelope samples must be real; pass complex samples to coherent_tof_bound")
    fs = _positive(sample_rate_hz, "sample_rate_hz")
    sigma = _positive(noise_sigma, "noise_sigma")
    a = float(amplitude)
    if derivative is None:
        return coherent_tof_bound(e, fs, amplitude=a, noise_sigma=sigma)
    de = np.asarray(derivative, dtype=np.float64)
    if de.shape != e.shape:
        raise EchoLocError(f"derivative has shape {de.shape}, the envelope {e.shape}")
    fisher = _fisher([-a * de, e], sigma)
    return _bound(fisher, ("tof_s", "amplitude"))


def envelope_noise_sigma(rf_noise_sigma: float, sample_rate_hz: float, output_rate_hz: float) -> float:
    """Standard deviation of the noise on envelope samples, high-SNR approximation.

    White rf noise of variance σ² at ``fs`` becomes, in the receiver's complex
    baseband (analytic signal times ``e^{-jωt}``, :mod:`echoloc.sim.receiver`), noise of
    density ``4σ²/fs`` over the band; low-passed to ``±f_out/2`` and sampled at
    ``f_out`` it is white with ``E|w|² = 4σ² f_out / fs``, so ``2σ² f_out / fs`` per
    quadrature. At high SNR the envelope ``|A u + w|`` moves with the quadrature in
    phase with the echo: ``σ_e = σ sqrt(2 f_out / fs)``. (An ideal low-pass; the
    resampler's transition band changes this by a few per cent. At low SNR the
    envelope noise is Rician, neither Gaussian nor zero-mean [R, sec. 3.10].)
    """
    sigma = _positive(rf_noise_sigma, "rf_noise_sigma")
    fs = _positive(sample_rate_hz, "sample_rate_hz")
    out = _positive(output_rate_hz, "output_rate_hz")
    return sigma * math.sqrt(2.0 * out / fs)
