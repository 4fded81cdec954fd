"""Envelope estimators of the time of flight: threshold detection and its relatives.

``threshold``
    The first crossing of a level by the signal's envelope, corrected for the time
    the template's envelope takes to rise to that level for the echo's measured
    amplitude (report ch. 3.3, threshold detection). It sees only the first of
    overlapping echoes, as the report notes.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np
import scipy.fft
from numpy.typing import NDArray

from echoloc.echoes import ChannelEchoes, EchoOptions, analytic_weights, finish_channel

_LN2 = float(np.log(2.0))


@dataclass(frozen=True, eq=False)
class ThresholdDetector:
    """Envelope threshold detection with the template's rise-time correction.

    The crossing is located on the band-limited envelope between samples (sinc
    interpolation of the analytic signal), and the arrival is the crossing time
    minus the time the template's own envelope needs to rise from its start to the
    level, relative to the echo's measured peak.
    """

    template: NDArray[np.float64]
    n_samples: int
    sample_rate_hz: float
    signal_kind: str = "rf"
    oversample: int = 32
    interpolation_taps: int = 32

    @cached_property
    def n_fft(self) -> int:
        return int(scipy.fft.next_fast_len(self.n_samples + 2 * len(self.template), real=True))

    @cached_property
    def _rise(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Template envelope (peak 1), made monotonic, up to its peak, and its times in samples.

        The times start before 0: the band-limited envelope of an abruptly starting
        pulse rises a little before the pulse itself.
        """
        circular = self._circular_fine_envelope
        before = 0 if self.signal_kind == "envelope" else self.interpolation_taps * self.oversample
        after = len(self.template) * self.oversample
        fine = np.concatenate([circular[len(circular) - before :], circular[:after]])
        times = (np.arange(len(fine)) - before) / self.oversample
        top = int(np.argmax(fine))
        return np.maximum.accumulate(fine[: top + 1]), times[: top + 1]

    def rise_time_samples(self, level: float) -> float:
        """Time from the echo's start until its envelope first reaches ``level`` of its peak."""
        envelope, times = self._rise
        return float(np.interp(level, envelope, times))

    @cached_property
    def duration_samples(self) -> int:
        return len(self.template)

    @cached_property
    def hold_samples(self) -> int:
        """Samples the envelope must stay below the level before the detector re-arms.

        Longer than the deepest dip inside the pulse itself (phase reversals), so a
        dip within one echo, or within overlapping echoes, is not a new echo.
        """
        below = self._circular_fine_envelope[: len(self.template) * self.oversample] < 0.5
        longest = run = 0
        for flag in below:
            run = run + 1 if flag else 0
            longest = max(longest, run)
        return int(np.ceil(longest / self.oversample)) + 2

    @cached_property
    def _circular_fine_envelope(self) -> NDArray[np.float64]:
        """The template's band-limited envelope on the fine grid (peak 1); negative times wrap to the end."""
        if self.signal_kind == "envelope":
            envelope = np.abs(self.template).astype(float)
            times = np.arange(len(envelope) * self.oversample) / self.oversample
            fine = np.interp(times, np.arange(len(envelope)), envelope)
        else:
            spectrum = scipy.fft.rfft(self.template, self.n_fft) * analytic_weights(self.n_fft)
            fine = np.abs(scipy.fft.ifft(spectrum, self.n_fft * self.oversample))
        return np.asarray(fine / fine.max())

    def analytic(self, frames: NDArray[np.floating]) -> NDArray[np.complex128] | NDArray[np.float64]:
        """Analytic signal of RF frames; envelope frames are returned as they are."""
        if self.signal_kind == "envelope":
            return np.asarray(np.abs(frames), dtype=float)
        spectrum = scipy.fft.rfft(frames, self.n_fft, axis=-1, workers=-1)
        analytic = scipy.fft.ifft(spectrum * analytic_weights(self.n_fft), self.n_fft, axis=-1, workers=-1)
        return np.asarray(analytic[..., : self.n_samples])

    def fine_envelope(
        self, signal: NDArray[np.complex128], start: int, stop: int
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Band-limited envelope on a grid of 1/oversample samples over [start, stop], and the times.

        Windowed-sinc interpolation of the analytic samples, exact up to the
        truncation of the kernel (the analytic signal's band [0, fs/2) fits in the
        sampling band).
        """
        taps = np.arange(start - self.interpolation_taps, stop + self.interpolation_taps + 1)
        taps = taps[(taps >= 0) & (taps < len(signal))]
        t = start + np.arange((stop - start) * self.oversample + 1) / self.oversample
        offset = t[:, None] - taps[None, :]
        window = 0.5 * (1 + np.cos(np.pi * np.clip(offset / (self.interpolation_taps + 1), -1, 1)))
        return np.abs((np.sinc(offset) * window) @ signal[taps]), t

    def crossing(
        self, signal: NDArray[np.complex128] | NDArray[np.float64], index: int, level: float
    ) -> float:
        """Time (samples) where the band-limited envelope first rises through ``level``.

        ``index`` is the first sample at or above the level; the envelope between
        samples may cross earlier (its ripple can dip below the level at a sample),
        so the search starts a few samples before it.
        """
        if self.signal_kind == "envelope":
            lo, hi = float(signal[index - 1]), float(signal[index])
            return index - 1 + (level - lo) / (hi - lo) if hi > lo else float(index)
        fine, t = self.fine_envelope(np.asarray(signal, complex), index - min(4, index), index)
        above = np.flatnonzero(fine >= level)
        if len(above) == 0:
            return float(index)
        k = int(above[0])
        if k == 0:
            return float(t[0])
        lo, hi = fine[k - 1], fine[k]
        return float(t[k - 1] + (level - lo) / (hi - lo) * (t[k] - t[k - 1]))

    def peak(self, signal: NDArray[np.complex128] | NDArray[np.float64], start: int, stop: int) -> float:
        """Largest envelope value of the echo in samples [start, stop), between samples too."""
        env = np.abs(signal[start:stop])
        top = start + int(np.argmax(env))
        if self.signal_kind == "envelope":
            return float(env.max())
        fine, _ = self.fine_envelope(
            np.asarray(signal, complex), max(top - 1, 0), min(top + 1, len(signal) - 1)
        )
        return float(max(fine.max(), env.max()))


def threshold_echoes(
    frames: NDArray[np.floating], detector: ThresholdDetector, options: EchoOptions
) -> list[ChannelEchoes]:
    """Threshold-crossing echoes of one frame (n_rx, n_samples).

    The level is ``threshold_db`` above the noise power (from the median), and at
    least ``threshold_fraction`` of the channel's strongest envelope sample.
    """
    signals = detector.analytic(frames)
    result = []
    first = int(np.ceil(options.blanking_s * detector.sample_rate_hz))
    for signal in signals:
        env = np.abs(signal)
        power = max(float(np.median(env**2)) / _LN2, float(np.finfo(float).tiny))
        level = max(
            float(np.sqrt(10 ** (options.threshold_db / 10) * power)),
            options.threshold_fraction * float(env[first:].max(initial=0.0)),
        )
        tofs: list[float] = []
        amplitudes: list[float] = []
        k = max(first, 1)
        while len(tofs) < options.max_echoes and level > 0:
            above = np.flatnonzero(env[k:] >= level)
            if len(above) == 0:
                break
            cross = k + int(above[0])
            stop = min(cross + detector.duration_samples, len(env))
            peak = detector.peak(signal, cross, stop)
            t_cross = detector.crossing(signal, cross, level)
            tofs.append(t_cross - detector.rise_time_samples(level / peak))
            amplitudes.append(peak)
            # Re-arm once the pulse has passed and the envelope has stayed below the level.
            quiet = np.convolve(env[stop:] < level, np.ones(detector.hold_samples), mode="valid")
            settled = np.flatnonzero(quiet == detector.hold_samples)
            if len(settled) == 0:
                break
            k = stop + int(settled[0]) + detector.hold_samples
        tof = np.array(tofs) / detector.sample_rate_hz
        amplitude = np.array(amplitudes)
        snr_db = 10 * np.log10(np.maximum(amplitude**2, 1e-300) / power)
        result.append(finish_channel(tof, amplitude, snr_db, options))
    return result
