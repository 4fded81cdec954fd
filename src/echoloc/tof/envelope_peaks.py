"""Time of flight on envelope and IQ data whose pulse is unknown: the real sensor's case.

A ToF chip such as the CH101 reports envelope samples (magnitudes) at a low rate and
says nothing of its pulse. docs/FORMATS.md allows such a recording without a ``waveform``:
the delay between an echo's arrival and its envelope's features is then a calibration
constant. This module finds echoes on such data with nothing but the data:

1. **Noise that follows the data.** Each channel's noise level is measured on its own
   samples after the blind zone, robustly (:func:`noise_sigma`: ``1.4826`` times the
   median of the positive samples, the MAD's consistency factor for Gaussian noise): an
   echo is a local maximum more than ``threshold_db`` above it. No echo sets the scale
   for another, so a strong cross-talk residue does not hide a weak far echo.
2. **Ring-down and cross-talk from the data** (:func:`ring_down_samples`): the
   transmitter's ring-down and the direct path vary from frame to frame far more than
   the noise, so background subtraction cannot take them out exactly. Per receiver,
   the blind zone is the run of samples from t = 0 whose spread across frames (of the
   backgrounds, else of the frames) stays above twice the channel's median spread.
3. **Sub-sample peak** by a Gaussian (log-parabola) through the three samples around
   each maximum, exact for a Gaussian-shaped envelope peak; a plain parabola where a
   neighbour is not positive.
4. **The echo's shape, learnt** (:func:`learn_echo_shape`): frames with known targets
   (the report's BALL template, ch. 4.1) or strong isolated echoes are aligned on
   their arrival and their peak-normalised envelopes averaged (median). The shape is
   kept as a :class:`~echoloc.tof.templates.Template` (its ``arrival_s`` the arrival within
   it), stored with the calibration; its arrival-to-peak delay turns each peak time
   into an arrival time: ``tof = t_peak - peak_delay``. Without a shape that delay is
   0 and the calibration's receiver delays take it up.

Measured on real CH101 data (``benchmarks/real_ch101.py``): a template fit of the
learnt shape over its main lobe locates no better than the Gaussian peak (its tails
meet clutter that background subtraction leaves), so the shape times the peak and
the peak gives the delay.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording
from echoloc.tof.echoes import ChannelEchoes, EchoOptions
from echoloc.tof.templates import Template, arrival_time_s

MAD_TO_SIGMA = 1.4826
"""sigma of Gaussian noise over its median absolute deviation (1 / Phi^-1(3/4))."""

SHAPE_OVERSAMPLING = 8
"""Points of a learnt echo shape per sample of the recording."""

SHAPE_SPAN_SAMPLES = (-3.0, 9.0)
"""Where a learnt shape starts and ends, in samples of the recording around the arrival."""

RING_DOWN_SPREAD_FACTOR = 2.0
"""A sample belongs to the ring-down while its spread across frames exceeds this many
times the channel's median spread (:func:`ring_down_samples`)."""

RING_DOWN_FRAMES = 256
"""Frames :func:`ring_down_samples` reads at most (the first ones)."""

NOISE_FLOOR_FRACTION = 1e-5
"""A channel's noise level is at least this fraction of its largest sample, 100 dB down
(beyond what 16-bit samples resolve, as :data:`echoloc.tof.echoes.PRECISION_DB`): a frame of
exact zeros and one echo, as a noiseless simulation gives, still has a level, and the
echo's far numerical ripple stays below it."""


@dataclass(frozen=True, eq=False)
class PeakDetector:
    """What :func:`peak_echoes` reuses for every frame of one recording.

    ``blind_samples`` (n_rx,): samples of each receiver's ring-down, before which no
    peak counts; ``peak_delay_s``: the echo shape's arrival-to-peak delay, s;
    ``support_samples``: the echo shape's length, within which a peak weaker than a
    stronger one by more than the dynamic range is its ripple, not an echo.
    """

    sample_rate_hz: float
    blind_samples: NDArray[np.int64]
    peak_delay_s: float = 0.0
    support_samples: float = SHAPE_SPAN_SAMPLES[1] - SHAPE_SPAN_SAMPLES[0]


def peak_delay_s(shape: Template) -> float:
    """Time from an echo's arrival to its envelope's peak, s: the shape's Gaussian-interpolated
    maximum less its ``arrival_s``."""
    magnitude = np.abs(np.asarray(shape.samples))
    k = int(np.argmax(magnitude))
    offset = _peak_offset(magnitude, k) if 0 < k < len(magnitude) - 1 else 0.0
    return (k + offset) / shape.sample_rate_hz - shape.arrival_s


def ring_down_samples(recording: Recording) -> NDArray[np.int64]:
    """Per receiver, the samples from t = 0 of the transmitter's ring-down (module doc, point 2).

    The spread is the median absolute deviation across frames, of the per-frame
    ``background`` where the recording has one (it holds the ring-down without any
    echo), else of the frames themselves (echoes move between frames, the ring-down
    stays). With fewer than three frames nothing is blinded.
    """
    source: NDArray[Any]
    if recording.background is not None and np.ndim(recording.background) == 3:
        source = np.asarray(recording.background[:RING_DOWN_FRAMES])
    else:
        source = np.asarray(recording.frames[:RING_DOWN_FRAMES])
    n_rx, n_samples = recording.n_receivers, recording.n_samples
    if len(source) < 3:
        return np.zeros(n_rx, dtype=np.int64)
    magnitude = np.abs(source).astype(float)
    spread = np.median(np.abs(magnitude - np.median(magnitude, axis=0)), axis=0)  # (n_rx, n_samples)
    blind = np.zeros(n_rx, dtype=np.int64)
    for rx in range(n_rx):
        level = RING_DOWN_SPREAD_FACTOR * float(np.median(spread[rx]))
        loud = spread[rx] > level
        # The ring-down starts with the emission; samples before its first loud one (the
        # chip's first samples can be exact zeros) belong to it too.
        first = int(np.argmax(loud)) if loud[: max(n_samples // 8, 1)].any() else -1
        if first < 0:
            continue
        end = first
        while end < n_samples and loud[end]:
            end += 1
        blind[rx] = end
    return blind


def prepare_peak_detector(recording: Recording, template: Template | None) -> PeakDetector:
    """The detector for ``recording``; ``template`` is the learnt echo shape, if any."""
    if recording.signal_kind not in ("envelope", "iq"):
        raise EchoLocError(
            f"{recording.source}: the envelope-peak estimator needs signal_kind 'envelope' or 'iq', "
            f"not {recording.signal_kind!r}"
        )
    if template is None and recording.waveform is not None and np.any(recording.waveform):
        # docs/FORMATS.md: an envelope (or iq) recording's waveform is what an ideal echo arriving
        # at t = 0 produces, so its peak is the arrival-to-peak delay.
        template = Template(np.abs(np.asarray(recording.waveform)), recording.sample_rate_hz, 0.0, "waveform")
    delay = 0.0 if template is None else peak_delay_s(template)
    support = (
        PeakDetector.support_samples
        if template is None
        else len(template.samples) / template.sample_rate_hz * recording.sample_rate_hz
    )
    return PeakDetector(recording.sample_rate_hz, ring_down_samples(recording), delay, support)


def _three(values: NDArray[np.float64], k: int) -> tuple[float, float, float, bool]:
    """The samples around ``k``, as logs where the two neighbours are within 60 dB of the centre
    (a Gaussian's log is a parabola), else as they are; and whether logs were taken."""
    left, centre, right = float(values[k - 1]), float(values[k]), float(values[k + 1])
    if centre > 0 and min(left, right) > 1e-3 * centre:
        return math.log(left), math.log(centre), math.log(right), True
    return left, centre, right, False


def _peak_offset(values: NDArray[np.float64], k: int) -> float:
    """Sub-sample offset of the maximum at ``k``: the vertex of a Gaussian through the three
    samples, or of a parabola where a neighbour is (nearly) zero; within +-0.5 sample."""
    a, b, c, _ = _three(values, k)
    curvature = a - 2 * b + c
    if not curvature < 0:
        return 0.0
    return min(max(0.5 * (a - c) / curvature, -0.5), 0.5)


def peak_echoes(frame: NDArray[Any], detector: PeakDetector, options: EchoOptions) -> list[ChannelEchoes]:
    """Echoes of one conditioned frame (n_rx, n_samples): peaks above each channel's noise
    (module doc). ``tof_s`` is the peak time less the shape's arrival-to-peak delay;
    ``amplitude`` the interpolated peak; ``snr_db`` its power over the noise's."""
    magnitude = np.abs(np.asarray(frame)).astype(float, copy=False)
    fs = detector.sample_rate_hz
    blank = math.ceil(options.blanking_s * fs) if options.blanking_s > 0 else 0
    factor = 10 ** (options.threshold_db / 20)
    return [
        _channel_peaks(x, max(int(blind), blank, 1), factor, detector, options)
        for x, blind in zip(magnitude, detector.blind_samples, strict=True)
    ]


def noise_sigma(magnitude: NDArray[np.float64]) -> float:
    """A channel's noise level from its own samples: ``1.4826 median`` of its positive samples.

    Zero-mean Gaussian noise has ``median|n| = 0.6745 sigma``. After background subtraction
    in power about half of the noise-only samples are floored at 0 (where the empty scene's
    noise was the larger), so the zeros are left out; echoes, being few, move the median
    little."""
    positive = magnitude[magnitude > 0]
    return MAD_TO_SIGMA * float(np.median(positive)) if len(positive) else 0.0


def _channel_peaks(
    x: NDArray[np.float64], first: int, factor: float, detector: PeakDetector, options: EchoOptions
) -> ChannelEchoes:
    fs, delay_s = detector.sample_rate_hz, detector.peak_delay_s
    n = len(x)
    empty = ChannelEchoes(np.zeros(0), np.zeros(0), np.zeros(0))
    if first >= n - 1:
        return empty
    tail = x[first:]
    sigma = max(noise_sigma(tail), NOISE_FLOOR_FRACTION * float(tail.max()))
    if not sigma > 0:
        return empty
    inner = x[first : n - 1]
    peak = (inner > x[first - 1 : n - 2]) & (inner >= x[first + 1 : n]) & (inner > factor * sigma)
    ks = np.flatnonzero(peak) + first
    if len(ks) == 0:
        return empty
    # A peak far weaker than a stronger one within the echo's length is that echo's ripple
    # (the local dynamic range; nothing farther away sets its scale).
    floor = 10 ** (-options.dynamic_range_db / 20)
    near = np.abs(ks[:, None] - ks[None, :]) <= detector.support_samples
    stronger = np.where(near, x[ks][None, :], 0.0).max(axis=1)
    ks = ks[x[ks] >= floor * stronger]
    if len(ks) > options.max_echoes:
        ks = np.sort(ks[np.argsort(x[ks])[::-1][: options.max_echoes]])
    offsets = np.array([_peak_offset(x, int(k)) for k in ks])
    heights = np.array([_peak_height(x, int(k), float(o)) for k, o in zip(ks, offsets, strict=True)])
    tof = (ks + offsets) / fs - delay_s
    snr = 20 * np.log10(heights / sigma)
    return ChannelEchoes(tof, heights, snr)


def _peak_height(values: NDArray[np.float64], k: int, offset: float) -> float:
    """The Gaussian (or parabola) of :func:`_peak_offset` at ``k + offset``."""
    a, b, c, logs = _three(values, k)
    height = b + 0.5 * (c - a) * offset + 0.5 * (a - 2 * b + c) * offset**2
    return float(math.exp(height)) if logs else float(height)


def learn_echo_shape(
    frames: NDArray[Any],
    arrivals_s: NDArray[np.float64],
    sample_rate_hz: float,
    *,
    name: str = "learnt",
    min_snr: float = 4.0,
) -> Template:
    """The average echo envelope of conditioned ``frames`` (n, n_rx, n_samples), aligned on
    ``arrivals_s`` (n, n_rx; NaN: no echo to use), as a template (module doc, point 4).

    Each echo is resampled (linear interpolation) on a grid of
    :data:`SHAPE_OVERSAMPLING` points a sample over :data:`SHAPE_SPAN_SAMPLES` around its
    arrival and scaled to a peak of 1 within the first five samples after the arrival;
    echoes whose peak is below ``min_snr`` times their channel's noise (as
    :func:`peak_echoes` measures it) are left out. The median over echoes is the shape;
    its ``arrival_s`` is the arrival's place in it.
    """
    magnitude = np.abs(np.asarray(frames)).astype(float)
    arrivals = np.asarray(arrivals_s, dtype=float)
    if magnitude.ndim != 3 or arrivals.shape != magnitude.shape[:2]:
        raise EchoLocError(
            f"learn_echo_shape: frames {magnitude.shape} and arrivals {arrivals.shape} do not match"
        )
    start, stop = SHAPE_SPAN_SAMPLES
    grid = np.arange(start, stop + 1e-9, 1.0 / SHAPE_OVERSAMPLING)
    lobe = (grid >= -0.5) & (grid <= 5.0)
    n_samples = magnitude.shape[2]
    t = np.arange(n_samples, dtype=float)
    rows = []
    for f, rx in zip(*np.nonzero(np.isfinite(arrivals)), strict=True):
        at = arrivals[f, rx] * sample_rate_hz
        if not (at + start >= 0 and at + stop < n_samples):
            continue
        x = magnitude[f, rx]
        sigma = noise_sigma(x)
        segment = np.interp(at + grid, t, x)
        peak = float(segment[lobe].max())
        if not (peak > 0 and peak > min_snr * sigma):
            continue
        rows.append(segment / peak)
    if len(rows) < 3:
        raise EchoLocError(
            f"only {len(rows)} echo(es) clear of the noise and the frame's ends to learn the echo "
            "shape from (at least 3 are needed)"
        )
    shape = np.median(np.array(rows), axis=0)
    return Template(shape, sample_rate_hz * SHAPE_OVERSAMPLING, -start / sample_rate_hz, name)


def arrivals_from_truth(
    recording: Recording, frames: Sequence[int], speed_of_sound_m_s: float
) -> NDArray[np.float64]:
    """Arrival time (s) of the nearest known reflector's echo per frame and receiver (NaN where
    the frame has no truth position): the report's BALL template's alignment, as
    :func:`echoloc.tof.templates.arrival_time_s` times it."""
    truth = recording.truth_positions_m
    if truth is None:
        raise EchoLocError(f"{recording.source}: learning the echo shape needs truth_positions")
    out = np.full((len(frames), recording.n_receivers), np.nan)
    for row, index in enumerate(frames):
        if np.all(np.isfinite(truth[index]), axis=1).any():
            out[row] = [
                arrival_time_s(recording, index, rx, "truth", speed_of_sound_m_s)
                for rx in range(recording.n_receivers)
            ]
    return out


def arrivals_from_peaks(
    frames: NDArray[Any], detector: PeakDetector, options: EchoOptions
) -> NDArray[np.float64]:
    """Per frame and receiver, the time of its strongest echo's peak when it stands alone
    (no other peak above the noise within four samples), else NaN: strong isolated
    echoes to learn a shape from when no target position is known. The shape's arrival is
    then its peak; the calibration's delays take up the difference."""
    out = np.full(np.shape(frames)[:2], np.nan)
    no_delay = replace(detector, peak_delay_s=0.0)
    for f, frame in enumerate(frames):
        for rx, channel in enumerate(peak_echoes(frame, no_delay, options)):
            if len(channel.tof_s) == 0:
                continue
            strongest = int(np.argmax(channel.amplitude))
            others = np.delete(channel.tof_s, strongest)
            gap = np.abs(others - channel.tof_s[strongest]) * detector.sample_rate_hz
            if np.all(gap > 4):
                out[f, rx] = channel.tof_s[strongest]
    return out
