"""Envelope estimators of the time of flight: threshold, energy, leading edge and envelope zero.

These are the report's own detectors (report ch. 3.3): they look at the echo's
envelope, not at its carrier phase, and each corrects its raw time by the same
measurement made on the template (the recording's ``waveform``), so that a clean echo
comes out at its arrival, ``tof_s`` (docs/FORMATS.md), whatever its amplitude.

Envelopes (:class:`EnvelopeOptions` ``method``)
    ``analytic``
        The magnitude of the analytic signal ``x + j H{x}``, by FFT (D. Gabor,
        "Theory of communication", J. IEE 93 (1946) 429-457; S. L. Marple, IEEE Trans.
        Signal Process. 47 (1999) 2600-2603). No delay and no carrier ripple.
    ``fir``
        The report's demodulator (report ch. 3.3): square the rf (square law, the
        default) or rectify it (full wave), then a linear-phase FIR low-pass designed
        by the window method (``scipy.signal.firwin``, Blackman window: transition
        width 4.6 fs / (N - 1), stop band -74 dB, so its step response barely rings
        before the edge, which the square root would magnify; A. V. Oppenheim,
        R. W. Schafer, *Discrete-Time Signal Processing*, 3rd ed., §7.5, table 7.2).
        With N odd its group delay is exactly (N - 1) / 2 samples (ibid. §5.7.3),
        removed by reading the filter's output that much later, so the envelope is
        not shifted. Scaling: ``A sin(wt)`` squared has mean
        ``A^2 / 2``, so the square-law envelope is ``sqrt(2 LP{x^2})``; rectified it
        has mean ``2 A / pi``, so the rectifier's envelope is ``(pi / 2) LP{|x|}``.
        The square law makes one harmonic, at 2 f_c, which the low-pass removes as
        long as its image (folded about the sample rate) lies above the pass band.
        The rectifier makes every harmonic 2k f_c (relative size 2 / (4k^2 - 1)):
        at 200 kHz and a 50 kHz carrier (4 samples per cycle) they land on 0 Hz, and
        the rectified envelope of a unit tone is ``(pi/4)(|sin phi| + |cos phi|)``,
        0.79 to 1.11 with the carrier's phase. The report rectified at 5 MHz, where
        the aliased harmonics are below 1e-3; at the stored rate the square law is
        the one to use.

    Between samples the envelope is read exactly: the band-limited signal it comes
    from (the analytic signal, or the FIR's low-passed power) is evaluated by its DFT
    interpolant (:class:`Trace`). Envelope recordings (``signal_kind``
    ``"envelope"``) are used as recorded, with linear interpolation between samples.

Noise reference (``noise``)
    ``median``
        One noise power per channel, ``median(e^2) / ln 2`` (exact for the exponential
        power of circular Gaussian noise), as the matched filter does.
    ``cfar``
        Cell-averaging constant false-alarm rate (H. M. Finn, R. S. Johnson, "Adaptive
        detection mode with threshold control as a function of spatially sampled
        clutter-level estimates", RCA Review 29 (1968) 414-464; M. A. Richards,
        *Fundamentals of Radar Signal Processing*, McGraw-Hill 2005, §7.4): the noise
        power at each sample is the mean of ``e^2`` over training cells on both sides,
        beyond guard cells, and the level is that mean times
        ``alpha = N (Pfa^(-1/N) - 1)`` (:func:`cfar_alpha`) for the false-alarm
        probability ``Pfa = exp(-10^(threshold_db / 10))`` that the fixed level has on
        exponential noise. Noise that changes along the frame (time-varying gain, the
        tail of a ring-down) then does not raise false alarms. The guard is one
        template length, so an echo does not mask its own onset; the training cells
        are one template length on each side.

Estimators (registered in :data:`echoloc.tof.estimators.ESTIMATORS`)
    ``threshold`` (:func:`threshold_echoes`)
        The first crossing of a level by the envelope, located between samples on the
        band-limited envelope, minus the time the template's envelope takes to rise
        to the same fraction of its peak (report ch. 3.3, threshold detection). Both
        crossings are taken on the main edge, the last rise through the level before
        the envelope first reaches half its peak: the band-limited onset of a pulse
        with abrupt chips rings before it by some 10 % of the peak, and whether noise
        lifts such a ripple over a low level must not move the estimate.
    ``energy`` (:func:`energy_echoes`)
        The first crossing of a level by the running energy: the squared envelope
        summed over a trailing window of one chip (the -6 dB width of the template's
        autocorrelation: one chip for a code, the whole pulse for a tone), minus the
        time the template's running energy takes to reach the same fraction of its
        peak. The squared envelope, not the squared rf, so the energy has no carrier
        ripple. Its level is the per-sample level times the window length.
    ``leading-edge`` (:func:`leading_edge_echoes`)
        The parabola ``e(t) = a (t - t0)^2`` fitted, as a straight line through
        ``sqrt(e)``, to the envelope's leading edge between 20 % and 80 % of the
        echo's amplitude (the least-squares scale of the template's envelope, which
        noise lifts less than the peak), gives the onset ``t0``; the template's own ``t0`` from the same
        fit is subtracted. Why this parabola: a tone driving two second-order
        resonators in series (the transmitting and the receiving transducer) has an
        envelope that starts as ``t^2``, with its vertex at the onset, so ``t0`` is
        where the fitted curve touches zero; the fit is linear least squares on
        ``sqrt(e)``. On the fine (interpolated) envelope, so which samples fall on
        the edge does not depend on the fractional delay; the 20 % / 80 % window is
        relative to the echo's amplitude, so clean data is unbiased at any amplitude.
    ``envelope-zero`` (:func:`envelope_zero_echoes`)
        Two consecutive pulse trains, the second inverted (``flip{N}`` in
        :func:`echoloc.physics.waveform.waveform_by_name`; report ch. 3.3): the envelope
        passes through zero at the phase reversal. Near it the squared envelope is a
        parabola whose vertex is the zero; it is fitted over the dip (where the
        envelope is below half the echo's amplitude) and the template's own zero
        time is subtracted. Any template whose envelope has a zero works (a code's first
        phase reversal does too); one without (a tone, a chirp) is refused.

Every estimator reports each echo it detects; like the threshold, each sees only the
first of overlapping echoes (report ch. 4, table 4.3), and an overlap inflates the
measured peak and so biases the correction. Conventions: ``amplitude`` is the echo's
scale against the template (the echo is about ``amplitude`` times the template), as
the matched filter reports it: the echo's peak envelope divided by the template's
(``leading-edge`` and ``envelope-zero``: the least-squares scale of the template's
envelope, steadier in noise). ``snr_db`` is ``10 log10(e^2 / P)`` with ``e`` the
echo's peak envelope and P the noise power of the envelope (the median reference,
or the CFAR cells' mean at the echo). For FIR envelopes the median rule
overestimates P by about 1 dB (low-passed power is no longer exponential), which
only makes detection more cautious.

Limits, measured on clean echoes (the registry's ``clean_tolerance_s`` is for rf):
on rf at 200 kHz every estimator here is within 50 ns, ``threshold-fir`` within
0.5 us (the square law aliases the edges of chips with abrupt phase reversals at 4
samples per cycle; through a transducer's band, 1 ns). On envelope recordings at
20 kHz (2.5 samples per chip) the envelope is only interpolated linearly between
samples and its template cannot hold the demodulator's rise before t = 0: up to
25 us (``threshold``) and 9 us (``energy``); ``leading-edge`` and ``envelope-zero``
are for rf only (the edge and the dip last about one sample there).
CA-CFAR masks: an echo within one to two pulse lengths after another sits in the
other's training cells, which raises its level (Richards 2005, §7.5); and at the
frame's ends only one side has cells, so a noise level still changing there (a gain
that has not levelled off by the frame's end) biases it. Undo a known gain with
:mod:`echoloc.tof.conditioning` instead where possible.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from typing import Literal

import numpy as np
import scipy.fft
import scipy.ndimage
import scipy.signal
from numpy.typing import NDArray

from echoloc.errors import EchoLocError
from echoloc.tof.echoes import ChannelEchoes, EchoOptions, analytic_weights, fft_workers, finish_channel

_LN2 = float(np.log(2.0))
_TINY = float(np.finfo(float).tiny)

EnvelopeMethod = Literal["analytic", "fir"]
Detector = Literal["square", "rectify"]
NoiseReference = Literal["median", "cfar"]

EDGE_LOW = 0.2
"""Lower end of the leading edge the ``leading-edge`` estimator fits, fraction of the peak."""
EDGE_HIGH = 0.8
"""Upper end of that edge."""
ZERO_DEPTH = 0.1
"""A template's envelope has a zero where a dip inside the pulse falls below this fraction of its peak."""
DIP_FIT = 0.5
"""``envelope-zero`` fits the dip where the envelope is below this fraction of the echo's peak."""
MAIN_EDGE = 0.5
"""An echo's main edge is where its envelope first reaches this fraction of its peak."""
FIT_POINTS = 33
"""Points, evenly spaced, of the leading-edge and dip fits."""

Sampler = Callable[[float, float, int], NDArray[np.float64]]
"""The envelope at ``start + j step`` samples, j = 0 .. count - 1: ``sample(start, step, count)``."""


@dataclass(frozen=True)
class EnvelopeOptions:
    """Which envelope and which noise reference an envelope estimator uses (module doc).

    Attributes
    ----------
    method
        ``"analytic"`` (default) or ``"fir"`` (square or rectify, then a low-pass).
    detector
        For ``fir``: ``"square"`` (default) or ``"rectify"``.
    cutoff_hz
        For ``fir``: the low-pass's cutoff (-6 dB), Hz. None: half the carrier, which
        is the null-to-null bandwidth 2 / T_chip of a code with 4 carrier cycles per
        chip (the report's), and at most half the square law's image frequency.
    transition_hz
        For ``fir``: the width of the transition band, Hz (sets the number of taps,
        ``4.6 fs / transition + 1`` rounded up to odd). None: the cutoff, so the pass band
        is flat to half the cutoff.
    noise
        ``"median"`` (default) or ``"cfar"``.
    cfar_guard_s, cfar_training_s
        For ``cfar``: guard and training interval on each side of the cell under
        test, s. None: one template length each.
    """

    method: EnvelopeMethod = "analytic"
    detector: Detector = "square"
    cutoff_hz: float | None = None
    transition_hz: float | None = None
    noise: NoiseReference = "median"
    cfar_guard_s: float | None = None
    cfar_training_s: float | None = None

    def __post_init__(self) -> None:
        if self.method not in ("analytic", "fir"):
            raise EchoLocError(f"envelope method must be 'analytic' or 'fir', got {self.method!r}")
        if self.detector not in ("square", "rectify"):
            raise EchoLocError(f"envelope detector must be 'square' or 'rectify', got {self.detector!r}")
        if self.noise not in ("median", "cfar"):
            raise EchoLocError(f"noise reference must be 'median' or 'cfar', got {self.noise!r}")
        for name in ("cutoff_hz", "transition_hz", "cfar_training_s"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise EchoLocError(f"envelope option {name} must be > 0, got {value!r}")
        guard = self.cfar_guard_s
        if guard is not None and not (math.isfinite(guard) and guard >= 0):
            raise EchoLocError(f"envelope option cfar_guard_s must be >= 0, got {guard!r}")


# --- FIR envelope ----------------------------------------------------------------------


def lowpass_taps(sample_rate_hz: float, cutoff_hz: float, transition_hz: float) -> NDArray[np.float64]:
    """Linear-phase FIR low-pass by the window method (Blackman), an odd number of taps.

    ``N = 4.6 fs / transition + 1`` rounded up to odd (Oppenheim & Schafer, 3rd ed.,
    table 7.2: the Blackman window's transition width 9.19 pi / (N - 1) rad), at
    least 3; the gain is 1/2 (-6 dB) at ``cutoff_hz``, the stop band below -74 dB and
    the group delay exactly ``(N - 1) / 2`` samples.
    """
    if not 0 < cutoff_hz < sample_rate_hz / 2:
        raise EchoLocError(
            f"FIR envelope cutoff {cutoff_hz:g} Hz must lie between 0 and the Nyquist frequency "
            f"{sample_rate_hz / 2:g} Hz"
        )
    if not transition_hz > 0:
        raise EchoLocError(f"FIR envelope transition width must be > 0, got {transition_hz:g} Hz")
    n = max(3, math.ceil(4.6 * sample_rate_hz / transition_hz) + 1)
    n += 1 - n % 2
    return np.asarray(scipy.signal.firwin(n, cutoff_hz, window="blackman", fs=sample_rate_hz), dtype=float)


def image_frequency_hz(carrier_hz: float, sample_rate_hz: float) -> float:
    """Where the square law's harmonic at 2 f_c lands after sampling: ``|2 f_c - k fs|``, k nearest."""
    return abs(2 * carrier_hz - sample_rate_hz * round(2 * carrier_hz / sample_rate_hz))


def fir_design(sample_rate_hz: float, carrier_hz: float, options: EnvelopeOptions) -> tuple[float, float]:
    """Cutoff and transition width of the FIR envelope for a carrier, Hz (defaults: :class:`EnvelopeOptions`).

    Refuses a square-law design whose 2 f_c image would fall in the pass band: the
    cutoff must be at most half the image frequency.
    """
    image = image_frequency_hz(carrier_hz, sample_rate_hz)
    cutoff = options.cutoff_hz if options.cutoff_hz is not None else min(carrier_hz / 2, image / 2)
    transition = options.transition_hz if options.transition_hz is not None else cutoff
    if options.detector == "square" and cutoff > image / 2:
        raise EchoLocError(
            f"FIR envelope cutoff {cutoff:g} Hz is above half the square law's image at {image:g} Hz "
            f"(carrier {carrier_hz:g} Hz sampled at {sample_rate_hz:g} Hz)"
        )
    return cutoff, transition


def fir_envelope_signal(
    frames: NDArray[np.floating], taps: NDArray[np.float64], detector: Detector = "square"
) -> NDArray[np.float64]:
    """The low-passed square (``2 LP{x^2}``) or rectified rf (``(pi/2) LP{|x|}``), not delayed.

    ``taps`` must be a linear-phase filter of odd length N (:func:`lowpass_taps`);
    output sample k is the filter's output at k + (N - 1)/2, so the result lines up
    with the input. For the square law this is the envelope squared; for the
    rectifier the envelope itself (see :func:`fir_envelope`).
    """
    if len(taps) % 2 != 1:
        raise EchoLocError(f"a FIR envelope needs an odd number of taps, got {len(taps)}")
    x = np.asarray(frames, dtype=float)
    detected = x**2 if detector == "square" else np.abs(x)
    delay = (len(taps) - 1) // 2
    padded = np.concatenate([detected, np.zeros((*x.shape[:-1], delay))], axis=-1)
    filtered = scipy.signal.lfilter(taps, 1.0, padded, axis=-1)[..., delay:]
    scale = 2.0 if detector == "square" else np.pi / 2
    return np.asarray(scale * filtered, dtype=float)


def fir_envelope(
    frames: NDArray[np.floating], taps: NDArray[np.float64], detector: Detector = "square"
) -> NDArray[np.float64]:
    """The report's envelope: square (or rectify), low-pass, delay removed, scaled to the carrier's amplitude.

    ``sqrt(2 LP{x^2})`` for the square law, ``(pi/2) LP{|x|}`` for the rectifier
    (module doc); a tone ``A sin(wt)`` of slowly varying ``A`` gives ``A``.
    """
    signal = fir_envelope_signal(frames, taps, detector)
    return _magnitude(signal, detector)


def _magnitude(signal: NDArray[np.generic], detector: Detector) -> NDArray[np.float64]:
    """The envelope from the FIR signal: the square root of the power, or the rectified mean."""
    real = np.maximum(np.asarray(signal, dtype=float), 0.0)
    return np.asarray(np.sqrt(real) if detector == "square" else real)


def centroid_frequency_hz(template: NDArray[np.floating], sample_rate_hz: float) -> float:
    """The power-weighted mean frequency of a pulse, Hz (its carrier when none is recorded)."""
    power = np.abs(scipy.fft.rfft(np.asarray(template, dtype=float))) ** 2
    freqs = scipy.fft.rfftfreq(len(template), 1 / sample_rate_hz)
    return float(np.sum(freqs * power) / np.sum(power))


# --- CFAR ----------------------------------------------------------------------------


def cfar_alpha(n_training: int | NDArray[np.int64], pfa: float) -> NDArray[np.float64]:
    """Cell-averaging CFAR scale ``alpha = N (Pfa^(-1/N) - 1)`` for exponential (square-law) noise.

    With the threshold ``alpha`` times the mean of N independent training cells, a
    cell of exponential noise of the same mean exceeds it with probability ``Pfa``
    exactly (Richards, *Fundamentals of Radar Signal Processing*, 2005, §7.4.1:
    ``Pfa = (1 + alpha / N)^(-N)``). Computed as ``N expm1(-ln(Pfa) / N)``; infinite
    where N is 0.
    """
    if not 0 < pfa < 1:
        raise EchoLocError(f"the false-alarm probability must lie in (0, 1), got {pfa!r}")
    return _alpha(np.asarray(n_training), -math.log(pfa))


def _alpha(count: NDArray[np.generic], minus_log_pfa: float) -> NDArray[np.float64]:
    n = np.asarray(count, dtype=float)
    safe = np.maximum(n, 1.0)
    return np.asarray(np.where(n > 0, safe * np.expm1(minus_log_pfa / safe), np.inf))


def training_mean(
    power: NDArray[np.floating], guard_cells: int, training_cells: int, first: int = 0
) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Mean of the training cells of every sample (along the last axis), and their number.

    Cells ``k - guard - training .. k - guard - 1`` and ``k + guard + 1 .. k + guard +
    training``; only those inside the frame and at or after ``first`` (the end of a
    blind zone, whose ring-down is not noise), so fewer near the ends, and a larger
    alpha there. Running sums make it O(n).
    """
    if guard_cells < 0 or training_cells < 1:
        raise EchoLocError(
            f"CFAR needs guard >= 0 and training >= 1 cells, got {guard_cells}, {training_cells}"
        )
    p = np.asarray(power, dtype=float)
    n = p.shape[-1]
    sums = np.concatenate([np.zeros((*p.shape[:-1], 1)), np.cumsum(p, axis=-1)], axis=-1)
    k = np.arange(n)
    start = min(max(first, 0), n)
    lead_lo = np.clip(k - guard_cells - training_cells, start, n)
    lead_hi = np.clip(k - guard_cells, lead_lo, n)
    lag_lo = np.clip(k + guard_cells + 1, start, n)
    lag_hi = np.clip(k + guard_cells + 1 + training_cells, lag_lo, n)
    total = sums[..., lead_hi] - sums[..., lead_lo] + sums[..., lag_hi] - sums[..., lag_lo]
    count = (lead_hi - lead_lo) + (lag_hi - lag_lo)
    mean = np.maximum(total, 0.0) / np.maximum(count, 1)
    return np.asarray(mean, dtype=float), np.asarray(count, dtype=np.int64)


def ca_cfar_threshold(
    power: NDArray[np.floating], guard_cells: int, training_cells: int, pfa: float
) -> NDArray[np.float64]:
    """Cell-averaging CFAR threshold for every sample of a power (squared envelope) signal.

    ``alpha(N) * mean(training cells)`` (:func:`training_mean`, :func:`cfar_alpha`):
    a sample of exponential noise exceeds it with probability ``pfa`` whatever the
    local noise level, as long as the level is constant (or linear) across the window
    (Finn & Johnson 1968; Richards 2005, §7.4).
    """
    mean, count = training_mean(power, guard_cells, training_cells)
    return np.asarray(cfar_alpha(count, pfa) * mean)


# --- the envelope detector shared by every estimator -----------------------------------


@dataclass(frozen=True, eq=False)
class ThresholdDetector:
    """The envelope of frames and of the template, between samples too, and its reference features.

    Everything the envelope estimators reuse for frames of one shape and template:
    the envelope (:class:`EnvelopeOptions`), the template's envelope on a fine grid
    (``oversample`` points per sample, peak 1, times from the template's start),
    its rise, its energy, its leading-edge onset and its zero.

    Between samples the envelope is read exactly (:class:`Trace`); envelope
    recordings are interpolated linearly. The template goes through the same steps,
    placed in the middle of a frame of zeros as long as the frames, so an echo and
    its template agree between samples. ``interpolation_taps`` is the margin, in
    samples, kept around the template for the envelope's spread before and after it.
    """

    template: NDArray[np.float64]
    n_samples: int
    sample_rate_hz: float
    signal_kind: str = "rf"
    oversample: int = 32
    interpolation_taps: int = 32
    envelope: EnvelopeOptions = field(default_factory=EnvelopeOptions)
    carrier_hz: float | None = None

    # --- the envelope of frames ---------------------------------------------------

    @cached_property
    def uses_fir(self) -> bool:
        return self.envelope.method == "fir" and self.signal_kind != "envelope"

    @cached_property
    def fir_taps(self) -> NDArray[np.float64]:
        """The FIR envelope's low-pass (empty unless the FIR envelope is used)."""
        if not self.uses_fir:
            return np.zeros(0)
        carrier = self.carrier_hz or centroid_frequency_hz(self.template, self.sample_rate_hz)
        cutoff, transition = fir_design(self.sample_rate_hz, carrier, self.envelope)
        return lowpass_taps(self.sample_rate_hz, cutoff, transition)

    @cached_property
    def fir_delay(self) -> int:
        """Half the FIR's length: how far its envelope spreads an echo on each side, samples."""
        return (len(self.fir_taps) - 1) // 2 if self.uses_fir else 0

    @cached_property
    def n_fft(self) -> int:
        return int(scipy.fft.next_fast_len(self.n_samples + 2 * len(self.template), real=True))

    def signal(self, frames: NDArray[np.floating]) -> NDArray[np.complex128] | NDArray[np.float64]:
        """What the envelope is taken from, band-limited: analytic signal, FIR power or recorded envelope."""
        return self._signal(frames, self.n_fft)

    def _signal(
        self, frames: NDArray[np.floating], n_fft: int
    ) -> NDArray[np.complex128] | NDArray[np.float64]:
        if self.signal_kind == "envelope":
            return np.asarray(np.abs(frames), dtype=float)
        if self.uses_fir:
            return fir_envelope_signal(frames, self.fir_taps, self.envelope.detector)
        n = frames.shape[-1]
        workers = fft_workers(os.cpu_count() or 1, math.prod(frames.shape[:-1]))
        spectrum = scipy.fft.rfft(frames, n_fft, axis=-1, workers=workers)
        analytic = scipy.fft.ifft(spectrum * analytic_weights(n_fft), n_fft, axis=-1, workers=workers)
        return np.asarray(analytic[..., :n])

    def magnitude(self, signal: NDArray[np.generic]) -> NDArray[np.float64]:
        """The envelope, sample by sample, from :meth:`signal`."""
        if self.uses_fir:
            return _magnitude(signal, self.envelope.detector)
        return np.asarray(np.abs(signal), dtype=float)

    def trace(self, signal: NDArray[np.generic]) -> Trace:
        """One channel's :meth:`signal`, ready to be read between samples."""
        return Trace(self, np.asarray(signal))

    # --- the template ---------------------------------------------------------------

    @cached_property
    def _pad(self) -> int:
        """Zeros put before and after the template: the interpolation's and the FIR's reach."""
        return self.interpolation_taps + self.fir_delay + 2

    @cached_property
    def _template_trace(self) -> tuple[Trace, int]:
        """The template's :meth:`signal` in a frame of zeros, and where the template starts in it.

        The frame has the frames' length (longer if the template needs it) and the
        template sits in its middle, so the analytic signal's tails, computed by a
        circular FFT, fall off as they do for an echo inside a frame.
        """
        pad = self._pad
        length = max(self.n_samples, len(self.template) + 2 * pad)
        offset = max(pad, (length - len(self.template)) // 2)
        frame = np.zeros(length)
        frame[offset : offset + len(self.template)] = self.template
        n_fft = int(scipy.fft.next_fast_len(length + 2 * len(self.template), real=True))
        return self.trace(self._signal(frame[None, :], n_fft)[0]), offset

    @cached_property
    def _template_fine(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The template's envelope on the fine grid (peak 1) and its times from the template's start.

        The times start before 0: a band-limited (or low-passed) envelope of an
        abruptly starting pulse rises a little before the pulse itself.
        """
        trace, offset = self._template_trace
        pad = self._pad
        fine, t = trace.fine(offset - pad, offset + len(self.template) + pad)
        return np.asarray(fine / self.template_envelope_peak), t - offset

    @cached_property
    def template_envelope_peak(self) -> float:
        """The largest value of the template's own envelope (the scale of :attr:`_template_fine`)."""
        trace, offset = self._template_trace
        fine, _ = trace.fine(offset - self._pad, offset + len(self.template) + self._pad)
        return _refined_max(fine)

    @cached_property
    def template_sampler(self) -> Sampler:
        """The template's envelope (peak 1) at any uniform grid of times from its start."""
        trace, offset = self._template_trace
        peak = self.template_envelope_peak
        return lambda start, step, count: trace.at(start + offset, step, count) / peak

    def rise_time_samples(self, level: float) -> float:
        """Time from the echo's start until its envelope rises through ``level`` of its peak on its main edge.

        The main edge is the last rise through the level before the envelope first
        reaches half its peak (:func:`_main_rise`): a band-limited onset rings before
        it (Gibbs), by some 10 % of the peak for abrupt chips, and noise decides
        whether such a ripple reaches a low level; on the main edge it does not matter.
        """
        fine, times = self._template_fine
        crossing = _main_rise(fine, times, level, MAIN_EDGE)
        return float(times[0]) if crossing is None else crossing

    @cached_property
    def main_edge_samples(self) -> int:
        """How long after an echo's first sample above a level its main edge may come, samples."""
        fine, times = self._template_fine
        half = float(times[int(np.flatnonzero(fine >= MAIN_EDGE)[0])])
        return math.ceil(half - float(times[0])) + 2

    @cached_property
    def duration_samples(self) -> int:
        """How long an echo's envelope lasts after its first crossing: the template, plus the FIR's spread."""
        return len(self.template) + 2 * self.fir_delay

    @cached_property
    def hold_samples(self) -> int:
        """Samples the envelope must stay below the level before the detector re-arms.

        Longer than the deepest dip inside the pulse itself (phase reversals), so a
        dip within one echo, or within overlapping echoes, is not a new echo.
        """
        fine, times = self._template_fine
        below = fine[(times >= 0) & (times < len(self.template))] < 0.5
        longest = run = 0
        for flag in below:
            run = run + 1 if flag else 0
            longest = max(longest, run)
        return int(np.ceil(longest / self.oversample)) + 2

    # --- levels -----------------------------------------------------------------------

    @cached_property
    def cfar_cells(self) -> tuple[int, int]:
        """CFAR guard and training cells on each side (defaults: one template length each)."""
        rate = self.sample_rate_hz
        guard_s, training_s = self.envelope.cfar_guard_s, self.envelope.cfar_training_s
        guard = len(self.template) if guard_s is None else round(guard_s * rate)
        training = len(self.template) if training_s is None else max(1, round(training_s * rate))
        return guard + self.fir_delay, training

    def noise_reference(
        self, env: NDArray[np.float64], options: EchoOptions, first: int = 0
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Per sample: the noise power P, and the level in power units for ``threshold_db``.

        ``median``: one P for the channel, level ``10^(threshold_db/10) P``. ``cfar``:
        P the mean of the training cells at or after ``first`` (the blanking: a
        ring-down is not noise), level ``alpha P`` with the CFAR alpha for
        ``Pfa = exp(-10^(threshold_db/10))`` (module doc).
        """
        power = env**2
        snr = 10 ** (options.threshold_db / 10)
        if self.envelope.noise == "median":
            noise = max(float(np.median(power)) / _LN2, _TINY)
            return np.full(len(env), noise), np.full(len(env), snr * noise)
        guard, training = self.cfar_cells
        mean, count = training_mean(power, guard, training, first)
        noise_k = np.maximum(mean, _TINY)
        return noise_k, np.asarray(_alpha(count, snr) * noise_k)

    def floor(
        self, curve: NDArray[np.float64], first: int, fraction: float, width: int
    ) -> NDArray[np.float64]:
        """The least level per sample, so that clean data is not cut at its noise floor.

        Median reference: ``fraction`` of the channel's largest value after ``first``.
        CFAR: ``fraction`` of the largest value within the next ``width`` samples, a
        local floor, so that a ring-down or a gain ramp elsewhere in the frame does
        not lift it.
        """
        if self.envelope.noise == "median":
            return np.full(len(curve), fraction * float(curve[first:].max(initial=0.0)))
        ahead = scipy.ndimage.maximum_filter1d(
            curve, size=width, origin=-(width // 2), mode="constant", cval=0.0
        )
        return np.asarray(fraction * ahead)

    # --- crossings and peaks ----------------------------------------------------------

    def crossing(self, trace: Trace, index: int, level: float, peak: float) -> float:
        """Time (samples) where the envelope rises through ``level`` on the echo's main edge.

        ``index`` is the first sample at or above the level. The envelope between
        samples may cross earlier (its ripple can dip below the level at a sample),
        so the search starts a few samples before it (one for envelope recordings);
        and the crossing taken is the last before the envelope first reaches half
        of ``peak`` (:meth:`rise_time_samples`), up to :attr:`main_edge_samples` later.
        """
        back = min(1 if self.signal_kind == "envelope" else 4, index)
        stop = min(index + self.main_edge_samples, len(trace.envelope) - 1)
        fine, t = trace.fine(index - back, max(stop, index))
        crossing = _main_rise(fine, t, level, MAIN_EDGE * peak)
        return _first_rise(fine, t, level, float(index)) if crossing is None else crossing

    def peak(self, trace: Trace, start: int, stop: int) -> float:
        """Largest envelope value of the echo in samples [start, stop], between samples too.

        The fine grid's largest value refined by a parabola through it and its
        neighbours, as for the template, so both peaks are measured alike.
        """
        if self.signal_kind == "envelope":
            return float(trace.envelope[start : stop + 1].max())
        fine, _ = trace.fine(start, min(stop, len(trace.envelope) - 1))
        return _refined_max(fine)

    def scale(self, trace: Trace, arrival: float) -> float:
        """The least-squares scale of the template's envelope, arriving at ``arrival``, to the echo's.

        Over the samples the template spans. In noise a steadier reference than the
        echo's largest envelope value, which noise lifts; on clean data the same.
        """
        n = len(trace.envelope)
        first = min(max(math.ceil(arrival), 0), n - 1)
        last = min(max(math.floor(arrival + len(self.template) - 1), first), n - 1)
        model = self.template_sampler(first - arrival, 1.0, last - first + 1)
        norm = float(np.dot(model, model))
        return float(np.dot(trace.envelope[first : last + 1], model)) / norm if norm > 0 else 0.0

    # --- energy -------------------------------------------------------------------------

    @cached_property
    def energy_window_samples(self) -> int:
        """The energy estimator's window: the -6 dB width of the template's autocorrelation envelope.

        One chip for a code (the main lobe of a Barker code's autocorrelation is one
        chip wide), the whole pulse for a tone; at least 1 sample.
        """
        pad = self._pad
        frame = np.zeros(len(self.template) + 2 * pad)
        frame[pad : pad + len(self.template)] = self.template
        if self.signal_kind == "envelope":
            signal: NDArray[np.generic] = frame
        else:
            n_fft = int(scipy.fft.next_fast_len(2 * len(frame), real=True))
            spectrum = scipy.fft.rfft(frame, n_fft) * analytic_weights(n_fft)
            signal = scipy.fft.ifft(spectrum, n_fft)[: len(frame)]
        values = np.asarray(signal, dtype=complex)
        acf = np.abs(np.correlate(values, values, mode="full"))
        centre = int(np.argmax(acf))
        above = acf >= 0.5 * acf[centre]
        right = centre
        while right + 1 < len(acf) and above[right + 1]:
            right += 1
        left = centre
        while left > 0 and above[left - 1]:
            left -= 1
        return max(1, right - left + 1)

    def _running_energy(self, fine: NDArray[np.float64], count: int) -> NDArray[np.float64]:
        """``E(t) = sum_{m=0}^{W-1} e^2(t - m)`` for the last ``count`` points of a fine envelope.

        ``fine`` must start W samples before the first of them (zeros where it does not).
        """
        u, w = self.oversample, self.energy_window_samples
        power = fine**2
        index = w * u + np.arange(count)[:, None] - u * np.arange(w)[None, :]
        return np.asarray(power[index].sum(axis=1))

    @cached_property
    def _energy_template(self) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
        """The template's running energy up to its peak (monotonic, peak 1), its times, and its peak value."""
        fine, times = self._template_fine
        lead = np.zeros(self.energy_window_samples * self.oversample)
        energy = self._running_energy(np.concatenate([lead, fine]), len(fine))
        top = int(np.argmax(energy))
        peak = float(energy[top])
        return np.maximum.accumulate(energy[: top + 1] / peak), times[: top + 1], peak

    def energy_rise_time_samples(self, level: float) -> float:
        """Time from the echo's start until its running energy first reaches ``level`` of its peak."""
        energy, times, _ = self._energy_template
        return float(np.interp(level, energy, times))

    def fine_energy(
        self, trace: Trace, start: int, stop: int
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The running energy on the fine grid over [start, stop], and the times."""
        fine, t = trace.fine(start - self.energy_window_samples, stop)
        count = (stop - start) * self.oversample + 1
        return self._running_energy(fine, count), t[-count:]

    # --- leading edge ---------------------------------------------------------------------

    @cached_property
    def edge_onset_samples(self) -> float:
        """The template's onset by the leading-edge fit (:func:`edge_onset`), samples from its start."""
        fine, times = self._template_fine
        high = int(np.flatnonzero(fine >= EDGE_HIGH)[0])
        onset = edge_onset(self.template_sampler, fine, times, 1.0, high)
        if onset is None:
            raise EchoLocError("the template's envelope has no rising edge to fit")
        return onset

    @cached_property
    def edge_reach_samples(self) -> int:
        """How far from a crossing the leading edge can lie: the template's rise to 80 %, samples."""
        fine, times = self._template_fine
        high = float(times[int(np.flatnonzero(fine >= EDGE_HIGH)[0])])
        return math.ceil(high - float(times[0])) + 4

    @cached_property
    def edge_span_samples(self) -> float:
        """How long the template's envelope takes from 20 % to 80 % of its peak on its first edge, samples."""
        fine, times = self._template_fine
        high = int(np.flatnonzero(fine >= EDGE_HIGH)[0])
        low = int(np.flatnonzero(fine[: high + 1] < EDGE_LOW)[-1]) + 1
        return float(times[high] - times[low])

    # --- envelope zero ------------------------------------------------------------------

    @cached_property
    def template_zero(self) -> tuple[float, float, float]:
        """The template's first envelope zero, the search half-width around it, the dip's half-width.

        All three in samples (the zero from the template's start).

        A zero is a local minimum of the envelope, between its first rise to and last
        fall from half its peak, below :data:`ZERO_DEPTH` of the peak. The search
        half-width is a quarter of the distance to the nearest other stretch below
        half the peak (another dip, or the pulse's edges), at least 2 samples. The
        dip's half-width is how far from the zero it stays below :data:`DIP_FIT`.
        """
        fine, times = self._template_fine
        half = np.flatnonzero(fine >= 0.5)
        inner = np.arange(half[0] + 1, half[-1])
        minima = inner[
            (fine[inner] <= fine[inner - 1]) & (fine[inner] < fine[inner + 1]) & (fine[inner] <= ZERO_DEPTH)
        ]
        if len(minima) == 0:
            raise EchoLocError(
                f"the template's envelope has no zero (no dip below {ZERO_DEPTH:.0%} of its peak "
                "inside the pulse); envelope-zero needs two pulse trains, the second inverted (code flip8)"
            )
        index = int(minima[0])
        zero = dip_vertex(self.template_sampler, fine, times, 1.0, index)
        if zero is None:
            raise EchoLocError("the template's envelope zero cannot be fitted")
        dip = _run_around(fine < DIP_FIT, index)
        width = float(np.max(np.abs(times[dip] - zero)))
        low = fine < 0.5
        others = times[low & ~_run_around(low, index)]
        gap = float(np.min(np.abs(others - zero)))
        return zero, max(2.0, gap / 4), width


@dataclass(frozen=True, eq=False)
class Trace:
    """One channel's envelope signal (:meth:`ThresholdDetector.signal`), read between samples exactly.

    Between samples the band-limited signal (analytic signal, or the FIR envelope's
    power, band-limited by its low-pass) is its DFT interpolant: the signal
    zero-padded to ``n_fft``, its spectrum, and the inverse DFT evaluated at the fine
    times by a chirp-z transform (L. R. Rabiner, R. W. Schafer, C. M. Rader, "The
    chirp z-transform algorithm", IEEE Trans. Audio Electroacoust. 17 (1969) 86-92),
    which is the sinc interpolation with an unlimited kernel. Then the magnitude.
    Envelope recordings are interpolated linearly.
    """

    detector: ThresholdDetector
    signal: NDArray[np.generic]

    @cached_property
    def envelope(self) -> NDArray[np.float64]:
        """The envelope at the samples."""
        return self.detector.magnitude(self.signal)

    @cached_property
    def _spectrum(self) -> NDArray[np.complex128]:
        """The signal's DFT, zero-padded by 128 samples at least, in signed-frequency order."""
        n_fft = int(scipy.fft.next_fast_len(len(self.signal) + 128))
        return np.asarray(scipy.fft.fftshift(scipy.fft.fft(self.signal, n_fft)))

    def fine(self, start: int, stop: int) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The envelope on a grid of 1/oversample samples over [start, stop], and the times (samples)."""
        u = self.detector.oversample
        count = (stop - start) * u + 1
        return self.at(float(start), 1.0 / u, count), start + np.arange(count) / u

    def at(self, start: float, step: float, count: int) -> NDArray[np.float64]:
        """The envelope at ``start + j step`` samples, j = 0 .. count - 1."""
        t = start + step * np.arange(count)
        if self.detector.signal_kind == "envelope":
            grid = np.arange(len(self.signal))
            values = np.asarray(self.signal, dtype=float)
            return np.asarray(np.interp(t, grid, values, left=0.0, right=0.0))
        spectrum = self._spectrum
        n_fft = len(spectrum)
        # x(t) = (1/N) sum_k X_k exp(2 pi i k t / N), k = idx - N//2 over the shifted spectrum;
        # the start is a phase ramp on the spectrum, the steps a chirp-z transform.
        ramp = np.exp(2j * np.pi * start / n_fft * np.arange(n_fft))
        values = _chirp_z(n_fft, count, step)(spectrum * ramp)
        values = values * np.exp(-2j * np.pi * (n_fft // 2) * t / n_fft) / n_fft
        if not np.iscomplexobj(self.signal):
            values = values.real
        return self.detector.magnitude(values)


@lru_cache(maxsize=64)
def _chirp_z(n: int, count: int, step: float) -> Callable[[NDArray[np.complex128]], NDArray[np.complex128]]:
    """``X -> sum_k X_k exp(2 pi i k j step / n)`` for j < count (scipy.signal.CZT, reused)."""
    transform: Callable[[NDArray[np.complex128]], NDArray[np.complex128]] = scipy.signal.CZT(
        n, count, w=np.exp(2j * np.pi * step / n), a=1.0
    )
    return transform


# --- fits ------------------------------------------------------------------------------


def _first_rise(fine: NDArray[np.float64], t: NDArray[np.float64], level: float, fallback: float) -> float:
    """The first time ``fine`` reaches ``level``, interpolated linearly on the grid."""
    above = np.flatnonzero(fine >= level)
    if len(above) == 0:
        return fallback
    k = int(above[0])
    if k == 0:
        return float(t[0])
    lo, hi = fine[k - 1], fine[k]
    return float(t[k - 1] + (level - lo) / (hi - lo) * (t[k] - t[k - 1]))


def _main_rise(
    fine: NDArray[np.float64], t: NDArray[np.float64], level: float, height: float
) -> float | None:
    """The last rise of ``fine`` through ``level`` before it first reaches ``max(level, height)``.

    Interpolated linearly on the grid; the first grid time if it starts above the
    level; None if it never reaches that height.
    """
    top = np.flatnonzero(fine >= max(level, height))
    if len(top) == 0:
        return None
    below = np.flatnonzero(fine[: int(top[0]) + 1] < level)
    if len(below) == 0:
        return float(t[0])
    k = int(below[-1]) + 1
    lo, hi = fine[k - 1], fine[k]
    return float(t[k - 1] + (level - lo) / (hi - lo) * (t[k] - t[k - 1]))


def _run_around(mask: NDArray[np.bool_], index: int) -> NDArray[np.bool_]:
    """The contiguous run of True in ``mask`` that contains ``index`` (all False if mask[index] is)."""
    run = np.zeros(len(mask), dtype=bool)
    if not mask[index]:
        return run
    false = np.flatnonzero(~mask)
    lo = int(false[false < index][-1]) + 1 if np.any(false < index) else 0
    hi = int(false[false > index][0]) if np.any(false > index) else len(mask)
    run[lo:hi] = True
    return run


def _refined_max(values: NDArray[np.float64]) -> float:
    """The largest value, refined by the parabola through it and its two neighbours."""
    i = int(np.argmax(values))
    top = float(values[i])
    if 0 < i < len(values) - 1:
        a, c = float(values[i - 1]), float(values[i + 1])
        if a < top and c < top:  # a strict maximum, not a corner or a flat top
            return top - 0.125 * (a - c) ** 2 / (a - 2 * top + c)
    return top


def _level_time(fine: NDArray[np.float64], t: NDArray[np.float64], index: int, level: float) -> float:
    """Where ``fine`` passes ``level`` between grid points ``index - 1`` and ``index`` (linear)."""
    lo, hi = float(fine[index - 1]), float(fine[index])
    if hi == lo:
        return float(t[index])
    return float(t[index - 1] + (level - lo) / (hi - lo) * (t[index] - t[index - 1]))


def edge_onset(
    sample: Sampler, fine: NDArray[np.float64], times: NDArray[np.float64], peak: float, high: int
) -> float | None:
    """Onset of a leading edge: the parabola ``a (t - t0)^2`` fitted between 20 % and 80 % of ``peak``.

    ``fine`` on the grid ``times`` locates the edge: ``high`` is the first grid
    point of the stretch at or above :data:`EDGE_HIGH` of the peak, and the edge runs
    back from it while the envelope stays at or above :data:`EDGE_LOW`. The times
    where it passes 20 % and 80 % are interpolated, and ``sample`` (the envelope at
    any uniform grid of times) gives :data:`FIT_POINTS` points evenly between them,
    so the fit moves smoothly with the echo's delay. The fit is the least-squares
    line through ``sqrt(e / peak)``; ``t0`` is where it reaches zero. None when there
    is no such edge or it does not rise.
    """
    below = np.flatnonzero(fine[: high + 1] < EDGE_LOW * peak)
    if high < 1 or len(below) == 0:
        return None
    low = int(below[-1]) + 1
    start = _level_time(fine, times, low, EDGE_LOW * peak)
    stop = _level_time(fine, times, high, EDGE_HIGH * peak)
    if not stop > start:
        return None
    step = (stop - start) / (FIT_POINTS - 1)
    t = start + step * np.arange(FIT_POINTS)
    y = np.sqrt(sample(start, step, FIT_POINTS) / peak)
    tm, ym = float(t.mean()), float(y.mean())
    slope = float(np.sum((t - tm) * (y - ym))) / float(np.sum((t - tm) ** 2))
    if slope <= 0:
        return None
    return tm - ym / slope


def dip_vertex(
    sample: Sampler, fine: NDArray[np.float64], times: NDArray[np.float64], peak: float, index: int
) -> float | None:
    """The zero of an envelope dip: vertex of the parabola fitted to ``(e / peak)^2`` over the dip.

    The dip is the stretch around grid point ``index`` where ``fine`` is below
    :data:`DIP_FIT` of ``peak``; its ends are interpolated and ``sample`` gives
    :data:`FIT_POINTS` points evenly between them. Near a phase reversal the
    carrier's amplitude passes linearly through zero, so the squared envelope is a
    parabola with its vertex at the zero. None when the dip is not inside ``fine``
    or the fit does not curve upwards to a vertex inside it.
    """
    inside = np.flatnonzero(_run_around(fine < DIP_FIT * peak, index))
    if len(inside) == 0 or inside[0] == 0 or inside[-1] == len(fine) - 1:
        return None
    start = _level_time(fine, times, int(inside[0]), DIP_FIT * peak)
    stop = _level_time(fine, times, int(inside[-1]) + 1, DIP_FIT * peak)
    if not stop > start:
        return None
    step = (stop - start) / (FIT_POINTS - 1)
    x = step * np.arange(FIT_POINTS) - (stop - start) / 2
    y = (sample(start, step, FIT_POINTS) / peak) ** 2
    design = np.stack([x**2, x, np.ones_like(x)], axis=1)
    (a, b, _), *_ = np.linalg.lstsq(design, y, rcond=None)
    if not a > 0:
        return None
    vertex = -float(b) / (2 * float(a))
    if not abs(vertex) <= (stop - start) / 2:
        return None
    return (start + stop) / 2 + vertex


# --- detection ---------------------------------------------------------------------------


def _detections(
    curve: NDArray[np.float64], level: NDArray[np.float64], first: int, count: int, duration: int, hold: int
) -> Iterator[tuple[int, int]]:
    """First crossings of ``level`` by ``curve``: (first sample at or above it, end of that echo).

    After each echo the detector re-arms once the echo has passed and the curve has
    stayed below the level for ``hold`` samples.
    """
    k = max(first, 1)
    found = 0
    n = len(curve)
    while found < count and k < n:
        above = np.flatnonzero((curve[k:] >= level[k:]) & (level[k:] > 0))
        if len(above) == 0:
            return
        cross = k + int(above[0])
        stop = min(cross + duration, n)
        yield cross, stop
        found += 1
        if stop + hold > n:
            return
        quiet = np.convolve(curve[stop:] < level[stop:], np.ones(hold), mode="valid")
        settled = np.flatnonzero(quiet == hold)
        if len(settled) == 0:
            return
        k = stop + int(settled[0]) + hold


def _envelope_crossings(
    trace: Trace, detector: ThresholdDetector, options: EchoOptions
) -> Iterator[tuple[int, int, float, float, float, float]]:
    """Threshold detections on one channel: (index, stop, level, crossing time, peak, noise power)."""
    env = trace.envelope
    first = math.ceil(options.blanking_s * detector.sample_rate_hz)
    noise, power_level = detector.noise_reference(env, options, first)
    floor = detector.floor(env, first, options.threshold_fraction, detector.duration_samples)
    level = np.maximum(np.sqrt(power_level), floor)
    for cross, stop in _detections(
        env, level, first, options.max_echoes, detector.duration_samples, detector.hold_samples
    ):
        at = float(level[cross])
        peak = detector.peak(trace, cross, stop)
        yield cross, stop, at, detector.crossing(trace, cross, at, peak), peak, float(noise[cross])


def _finish(
    tofs: list[float],
    peaks: list[float],
    noises: list[float],
    detector: ThresholdDetector,
    options: EchoOptions,
) -> ChannelEchoes:
    """Arrivals (samples), peak envelopes and noise powers -> ChannelEchoes (module doc, conventions)."""
    tof = np.array(tofs, dtype=float) / detector.sample_rate_hz
    peak = np.array(peaks, dtype=float)
    snr_db = 20 * np.log10(np.maximum(peak, 1e-150)) - 10 * np.log10(np.array(noises, dtype=float))
    return finish_channel(tof, peak / detector.template_envelope_peak, snr_db, options)


# --- estimators -------------------------------------------------------------------------------


def threshold_echoes(
    frames: NDArray[np.floating], detector: ThresholdDetector, options: EchoOptions
) -> list[ChannelEchoes]:
    """Threshold-crossing echoes of one frame (n_rx, n_samples) (module doc, ``threshold``).

    The level is ``threshold_db`` above the noise (median or CFAR reference), and at
    least ``threshold_fraction`` of the channel's strongest envelope sample (of the
    strongest within one echo's length ahead, with CFAR).
    """
    result = []
    for signal in detector.signal(frames):
        trace = detector.trace(signal)
        tofs, amplitudes, noises = [], [], []
        for _, _, level, time, peak, noise in _envelope_crossings(trace, detector, options):
            tofs.append(time - detector.rise_time_samples(level / peak))
            amplitudes.append(peak)
            noises.append(noise)
        result.append(_finish(tofs, amplitudes, noises, detector, options))
    return result


def energy_echoes(
    frames: NDArray[np.floating], detector: ThresholdDetector, options: EchoOptions
) -> list[ChannelEchoes]:
    """Running-energy echoes of one frame (n_rx, n_samples) (module doc, ``energy``).

    The level on the energy is W times the envelope's power level (the mean power
    over the window must clear ``threshold_db``), and at least ``threshold_fraction``
    squared of the strongest energy (the same fraction of the amplitude as the
    threshold's). The echo's peak envelope is ``sqrt(E_peak / E_template_peak)`` with
    the template's envelope at peak 1.
    """
    width = detector.energy_window_samples
    duration = detector.duration_samples + width
    first = math.ceil(options.blanking_s * detector.sample_rate_hz)
    _, _, template_peak = detector._energy_template
    result = []
    for signal in detector.signal(frames):
        trace = detector.trace(signal)
        env = trace.envelope
        sums = np.concatenate([[0.0], np.cumsum(env**2)])
        index = np.arange(len(env)) + 1
        energy = sums[index] - sums[np.maximum(index - width, 0)]
        noise, power_level = detector.noise_reference(env, options, first)
        floor = detector.floor(energy, first, options.threshold_fraction**2, duration)
        level = np.maximum(width * power_level, floor)
        tofs, amplitudes, noises = [], [], []
        hold = detector.hold_samples
        for cross, stop in _detections(energy, level, first, options.max_echoes, duration, hold):
            top = cross + int(np.argmax(energy[cross:stop]))
            fine_top, _ = detector.fine_energy(trace, max(top - 1, 0), min(top + 1, len(env) - 1))
            peak = max(float(fine_top.max()), float(energy[cross:stop].max()))
            at = float(level[cross])
            back = min(4, cross)
            fine, t = detector.fine_energy(trace, cross - back, cross)
            time = _first_rise(fine, t, at, float(cross))
            tofs.append(time - detector.energy_rise_time_samples(at / peak))
            amplitudes.append(math.sqrt(peak / template_peak))
            noises.append(float(noise[cross]))
        result.append(_finish(tofs, amplitudes, noises, detector, options))
    return result


def leading_edge_echoes(
    frames: NDArray[np.floating], detector: ThresholdDetector, options: EchoOptions
) -> list[ChannelEchoes]:
    """Leading-edge-fit echoes of one frame (n_rx, n_samples) (module doc, ``leading-edge``).

    Detection as :func:`threshold_echoes`; the echo's amplitude is the least-squares
    scale of the template's envelope at the threshold estimate
    (:meth:`ThresholdDetector.scale`), and the parabola is fitted to the edge between
    20 % and 80 % of it (:func:`edge_onset`). An echo whose edge cannot be fitted, or
    whose fitted onset strays from the threshold estimate by more than the
    template's own 20-80 % rise plus two samples (noise, an overlapping echo), keeps
    the threshold estimate.
    """
    reach = detector.edge_reach_samples
    onset_template = detector.edge_onset_samples
    stray = detector.edge_span_samples + 2
    result = []
    for signal in detector.signal(frames):
        trace = detector.trace(signal)
        n = len(signal)
        tofs, amplitudes, noises = [], [], []
        for cross, _, level, time, peak, noise in _envelope_crossings(trace, detector, options):
            estimate = time - detector.rise_time_samples(level / peak)
            amplitude = detector.scale(trace, estimate)
            start, stop = max(cross - reach, 0), min(cross + reach, n - 1)
            fine, t = trace.fine(start, stop)
            at = int(np.clip(np.searchsorted(t, time), 0, len(t) - 1))
            high = _edge_top(fine, at, amplitude) if amplitude > 0 else None
            onset = None if high is None else edge_onset(trace.at, fine, t, amplitude, high)
            arrival = None if onset is None else onset - onset_template
            good = arrival is not None and abs(arrival - estimate) <= stray
            tofs.append(arrival if good and arrival is not None else estimate)
            amplitudes.append(amplitude if amplitude > 0 else peak)
            noises.append(noise)
        result.append(_finish(tofs, amplitudes, noises, detector, options))
    return result


def _edge_top(fine: NDArray[np.float64], at: int, peak: float) -> int | None:
    """Grid index where the edge through grid index ``at`` reaches :data:`EDGE_HIGH` of the peak.

    Forward from the crossing when the crossing is below that height; else back to
    the start of the stretch at or above it.
    """
    high = fine >= EDGE_HIGH * peak
    if high[at]:
        run = _run_around(high, at)
        return int(np.flatnonzero(run)[0])
    ahead = np.flatnonzero(high[at:])
    return at + int(ahead[0]) if len(ahead) else None


def envelope_zero_echoes(
    frames: NDArray[np.floating], detector: ThresholdDetector, options: EchoOptions
) -> list[ChannelEchoes]:
    """Envelope-zero echoes of one frame (n_rx, n_samples) (module doc, ``envelope-zero``).

    Detection as :func:`threshold_echoes`; the echo's amplitude is the least-squares
    scale of the template's envelope at the threshold estimate
    (:meth:`ThresholdDetector.scale`). The threshold estimate plus the template's
    zero time says where the echo's zero should be; the deepest point of the
    envelope within the search half-width of it is the dip, whose vertex
    (:func:`dip_vertex`) minus the template's zero is the arrival. An echo without
    a dip there below half its amplitude (filled by noise or an overlapping echo)
    keeps the threshold estimate.
    """
    zero, reach, width = detector.template_zero
    result = []
    for signal in detector.signal(frames):
        trace = detector.trace(signal)
        n = len(signal)
        tofs, amplitudes, noises = [], [], []
        for _, _, level, time, peak, noise in _envelope_crossings(trace, detector, options):
            estimate = time - detector.rise_time_samples(level / peak)
            amplitude = detector.scale(trace, estimate)
            if not amplitude > 0:
                amplitude = peak
            expected = estimate + zero
            start = int(np.clip(math.floor(expected - reach - width) - 1, 0, n - 1))
            stop = int(np.clip(math.ceil(expected + reach + width) + 1, 0, n - 1))
            vertex = None
            if stop > start:
                fine, t = trace.fine(start, stop)
                near = np.flatnonzero(np.abs(t - expected) <= reach)
                deepest = int(near[np.argmin(fine[near])]) if len(near) else 0
                if len(near) and fine[deepest] < DIP_FIT * amplitude:
                    vertex = dip_vertex(trace.at, fine, t, amplitude, deepest)
            tofs.append(estimate if vertex is None else vertex - zero)
            amplitudes.append(amplitude)
            noises.append(noise)
        result.append(_finish(tofs, amplitudes, noises, detector, options))
    return result
