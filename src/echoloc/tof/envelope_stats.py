"""Figures of single-target envelope recordings: echo width, SNR, timing spread, frame-start levels.

Used to hold the simulator's chip presets (``echoloc/scenes/ch101.toml``) against real
recordings (``benchmarks/compare_ch101.py``). Every figure is measured the same way
on real and simulated data, from plain arrays:

- ``frames`` and ``background`` (n_frames, n_rx, n_samples): envelope samples and
  an empty-scene recording per frame; the echo is in ``frames - background``.
- ``arrival_samples`` (n_frames, n_rx): the geometric arrival of the one target's
  echo, in samples after emission (:func:`arrival_samples`).

Per frame and channel, :func:`measure_echoes` finds the largest sample of the
subtracted frame from the arrival to ``search_samples`` after it, refines its time by
a parabola through it and its neighbours, and measures its full width at half
maximum by linear interpolation between samples. The noise of each channel is the
robust standard deviation (1.4826 × median absolute deviation) of its subtracted
samples away from the echo and the frame start, over all frames. Timing residuals are
peak time minus arrival, less the channel's median (a chip's fixed delay is a
calibration constant, docs/FORMATS.md).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from echoloc.tof.envelope_peaks import MAD_TO_SIGMA

FloatArray = NDArray[np.float64]


def robust_sigma(values: FloatArray, axis: int | None = None) -> FloatArray:
    """1.4826 × the median absolute deviation from the median, ignoring NaN (same units as ``values``)."""
    x = np.asarray(values, dtype=float)
    centre = np.nanmedian(x, axis=axis, keepdims=True)
    return np.asarray(MAD_TO_SIGMA * np.nanmedian(np.abs(x - centre), axis=axis), dtype=float)


def arrival_samples(
    transmitter_m: FloatArray,
    receivers_m: FloatArray,
    targets_m: FloatArray,
    speed_of_sound_m_s: float,
    sample_rate_hz: float,
) -> FloatArray:
    """Transmitter -> target -> receiver travel time, samples, (n_frames, n_rx), for targets (n_frames, 3)."""
    targets = np.asarray(targets_m, dtype=float)
    r_tx = np.linalg.norm(targets - np.asarray(transmitter_m, dtype=float), axis=-1)
    r_rx = np.linalg.norm(targets[:, None, :] - np.asarray(receivers_m, dtype=float)[None], axis=-1)
    return np.asarray((r_tx[:, None] + r_rx) / speed_of_sound_m_s * sample_rate_hz, dtype=float)


@dataclass(frozen=True, eq=False)
class EchoFigures:
    """Per frame and channel (n_frames, n_rx), NaN where no echo was found.

    ``peak_sample``: the echo's peak time (samples after emission, sub-sample);
    ``amplitude``: its peak value (the recording's units); ``fwhm_samples``: full width
    at half maximum (samples); ``snr_db``: ``20 log10(amplitude / noise)`` with the
    channel's ``noise`` (n_rx,); ``residual_samples``: peak time minus arrival, less
    the channel's median.
    """

    peak_sample: FloatArray
    amplitude: FloatArray
    fwhm_samples: FloatArray
    noise: FloatArray
    snr_db: FloatArray
    residual_samples: FloatArray


def _half_crossing(signal: FloatArray, peak: int, half: float, step: int, limit: int) -> float:
    """Sub-sample position where ``signal`` first falls below ``half`` walking from ``peak`` by ``step``."""
    k = peak
    for _ in range(limit):
        nxt = k + step
        if not 0 <= nxt < len(signal):
            return float("nan")
        if signal[nxt] < half:
            fraction = (signal[k] - half) / (signal[k] - signal[nxt])
            return float(k + step * fraction)
        k = nxt
    return float("nan")


def measure_echoes(
    frames: FloatArray,
    background: FloatArray,
    arrivals: FloatArray,
    *,
    search_samples: int = 6,
    quiet_from: int = 14,
    guard_samples: tuple[int, int] = (3, 10),
    width_limit: int = 10,
) -> EchoFigures:
    """Echo peak, amplitude, FWHM, SNR and timing residual of one target per frame and channel.

    ``search_samples``: the peak is looked for from the arrival to this many samples
    after it. ``quiet_from``: samples before it (ring-down, cross-talk) are not noise.
    ``guard_samples``: samples this far before and after the arrival are not noise
    either. ``width_limit``: a half-maximum crossing further than this from the peak
    makes the width NaN (a merged echo).
    """
    diff = np.asarray(frames, dtype=float) - np.asarray(background, dtype=float)
    n_frames, n_rx, n_samples = diff.shape
    arrivals = np.asarray(arrivals, dtype=float)
    peak = np.full((n_frames, n_rx), np.nan)
    amplitude = np.full((n_frames, n_rx), np.nan)
    fwhm = np.full((n_frames, n_rx), np.nan)
    index = np.arange(n_samples)
    quiet = np.broadcast_to(index >= quiet_from, diff.shape).copy()
    for f in range(n_frames):
        for r in range(n_rx):
            tau = arrivals[f, r]
            if not np.isfinite(tau):
                quiet[f, r] = False
                continue
            quiet[f, r] &= (index < tau - guard_samples[0]) | (index > tau + guard_samples[1])
            low = max(int(np.floor(tau)), 1)
            high = min(int(np.ceil(tau)) + search_samples, n_samples - 2)
            if high < low:
                continue
            trace = diff[f, r]
            k = low + int(np.argmax(trace[low : high + 1]))
            top = trace[k]
            if top <= 0:
                continue
            left, right = trace[k - 1], trace[k + 1]
            curvature = left - 2 * top + right
            shift = 0.5 * (left - right) / curvature if curvature < 0 else 0.0
            peak[f, r] = k + float(np.clip(shift, -0.5, 0.5))
            amplitude[f, r] = top
            half = 0.5 * top
            fwhm[f, r] = _half_crossing(trace, k, half, +1, width_limit) - _half_crossing(
                trace, k, half, -1, width_limit
            )
    noise = np.array([robust_sigma(diff[:, r][quiet[:, r]]) for r in range(n_rx)], dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        snr = 20.0 * np.log10(amplitude / noise[None, :])
    offset = peak - arrivals
    residual = offset - np.nanmedian(offset, axis=0, keepdims=True)
    return EchoFigures(
        peak_sample=peak,
        amplitude=amplitude,
        fwhm_samples=fwhm,
        noise=noise,
        snr_db=snr,
        residual_samples=residual,
    )


def within_group_spread(residuals: FloatArray, groups: NDArray[np.int64]) -> FloatArray:
    """Per channel, the robust spread (samples) of residuals about their own group's median.

    ``groups`` (n_frames,) labels frames taken at the same target position, so the
    spread is the frame-to-frame jitter without the position-dependent errors.
    """
    res = np.asarray(residuals, dtype=float)
    centred = np.full_like(res, np.nan)
    for label in np.unique(groups):
        rows = groups == label
        centred[rows] = res[rows] - np.nanmedian(res[rows], axis=0, keepdims=True)
    return robust_sigma(centred, axis=0)


@dataclass(frozen=True, eq=False)
class FrameStart:
    """The frame start of an empty-scene recording per channel (n_rx,): ring-down or cross-talk.

    ``peak``: largest value of the mean background over the first ``window`` samples;
    ``peak_sample``: where it is; ``tail_ratio``: the mean background ``tail_samples``
    after the peak as a fraction of the peak (how far it has decayed by then).
    """

    peak: FloatArray
    peak_sample: FloatArray
    tail_ratio: FloatArray


def frame_start_levels(background: FloatArray, *, window: int = 14, tail_samples: int = 5) -> FrameStart:
    """Ring-down and cross-talk levels of the mean of ``background`` (n_frames, n_rx, n_samples)."""
    mean = np.mean(np.asarray(background, dtype=float), axis=0)
    peak_sample = np.argmax(mean[:, :window], axis=1)
    rows = np.arange(len(mean))
    peak = mean[rows, peak_sample]
    tail = mean[rows, np.minimum(peak_sample + tail_samples, mean.shape[1] - 1)]
    return FrameStart(peak=peak, peak_sample=peak_sample.astype(float), tail_ratio=tail / peak)
