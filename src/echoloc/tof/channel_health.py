"""Degraded receiver channels: found from the data, named, corrected or left out.

A receiver's channel can fail in ways the reader does not see: its amplifier or ADC
clips, it sits on a DC offset, it is dead (every sample the same), it carries NaN or
infinite samples, or it is far noisier than its neighbours (a loose cable, a broken
pre-amplifier). Each of these misleads the echo stage quietly: a clipped echo leaves
a residual the matched filter reads as more echoes, an offset makes the frame's edges
ring through the filter, a noisy channel misses echoes. :func:`assess_channels` looks
at a batch of raw frames with robust statistics and returns a :class:`ChannelHealth`
(each channel's problems and what is done about it); :func:`correct_frames` applies
the corrections to frames; :func:`health_messages` words the warnings.

Detectors, per channel over the batch (``sigma``: the noise, 3.138 times the lower
quartile of the absolute deviation from the frame's median, the median of it over the
frames; :data:`LOWER_QUARTILE_TO_SIGMA`):

- **non-finite**: any NaN or infinite sample. The samples are set to 0 and the channel
  is left out of localisation.
- **dead**: every sample equal. Left out of localisation.
- **DC offset** (rf and iq only): the median of the per-frame medians is more than
  :attr:`HealthLimits.dc_sigmas` noise sigmas from 0. Corrected: each frame of the
  channel has its own median subtracted. An envelope's offset is part of its noise
  floor (an envelope is >= 0), which the envelope estimators measure themselves: it is
  not assessed.
- **clipped**: samples pile up at the channel's largest (or smallest) value, a flat
  top: at least :attr:`HealthLimits.rail_min_samples` of them, and at least
  :attr:`HealthLimits.rail_pileup` times as many as in the band just below the rail
  (an unclipped peak, even a quantised one, has as many samples just below its top as
  on it; a clipped one has almost none; the band spans at least one quantiser step).
  Samples at the rail in the frame's leading run (a transmitter's ring-down saturating
  the ADC, normal on real heads and inside the blind zone) do not count. Left out of
  localisation: a clipped echo's delay is still right (clipping keeps the zero
  crossings) but the clipping's residual shows as extra echoes on that channel, which
  cross with the other channels' echoes into ghosts. Where the chain can read the
  channel again (the matched filter on rf samples: ``reread_clipped``), it is kept
  instead and its echoes near clipped samples are re-read (:func:`reread_clipped`).
- **noisy**: sigma more than :attr:`HealthLimits.noisy_ratio` times the median sigma
  of the other channels. Left out of localisation: its echoes are the ones missed.

Clipped and noisy channels are left out only while enough others remain
(``min_receivers``); otherwise they are kept, and the warning says so. Dead and
non-finite channels are always left out.

Re-reading a clipped channel: the matched filter's envelope of a clipped frame keeps a
peak at every echo (a hard limiter passes each input scaled, plus distortion that does
not correlate with the template: Bussgang's theorem), but the estimator's CLEAN, which
subtracts the template's autocorrelation scaled to each echo, does not fit clipped
echoes: around a strong clipped echo it reports misplaced echoes and distortion
products and drops real ones (on the acceptance scene clipped at 10 % of its peak: 610
spurious echoes on the channel, 65 of 874 lost). Near clipped samples (within the
template's reach) the channel's echoes are therefore the correlation's own peaks: local
maxima of its envelope above the threshold and within
:attr:`HealthLimits.clipped_range_db` of the strongest correlation within the template's
reach, each timed by the estimator's rule (envelope parabola, refined by the carrier
phase). Elsewhere the estimator's echoes stand.

On a live stream the channels are assessed from the first frames of a session
(:class:`ChannelWatch`: up to :data:`ASSESS_FRAMES`, batch by batch as they come, a
problem once found kept for the session); on a recording, from up to
:data:`ASSESS_FRAMES` frames spread over it. A channel that fails later in a session
is not seen (only its non-finite samples are still zeroed).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage

from echoloc.tof.echoes import ChannelEchoes, EchoOptions, MatchedFilter, finish_channel, noise_power

ASSESS_FRAMES = 64
"""Frames a recording or a live session's start is assessed on: 150 k samples a channel at
4 x 2400, enough for the medians to settle (their spread is 1.25 sigma / sqrt(n))."""


def assessed_frames(n_frames: int) -> NDArray[np.intp]:
    """The frames a recording of ``n_frames`` frames has its channels assessed on: up to
    :data:`ASSESS_FRAMES` spread evenly over it, the first and the last among them."""
    picks = np.unique(np.linspace(0, n_frames - 1, min(n_frames, ASSESS_FRAMES)).round())
    return picks.astype(np.intp)


MAD_TO_SIGMA = 1.482602218505602
"""Median absolute deviation to the standard deviation of Gaussian noise: 1 / Phi^-1(3/4)."""

LOWER_QUARTILE_TO_SIGMA = 3.138344200661294
"""The lower quartile of the absolute deviation to the standard deviation of Gaussian noise:
1 / Phi^-1(5/8). Echoes that fill half a short frame lift the median absolute deviation
(a two-channel frame of 1200 samples with three 25 dB echoes on one channel read 4 sigma
there), its lower quartile hardly: the noise sigma is taken from it."""

PROBLEMS = ("non-finite", "dead", "clipped", "dc-offset", "noisy")
"""Every problem a channel can have, in the order warnings name them."""

EXCLUDING = frozenset({"non-finite", "dead", "clipped", "noisy"})
"""Problems that leave a channel out of localisation (DC is corrected instead)."""


class ChannelWarning(UserWarning):
    """A receiver channel is degraded (clipped, DC offset, dead, non-finite, noisy)."""


@dataclass(frozen=True)
class HealthLimits:
    """Thresholds of the detectors (module doc).

    dc_sigmas
        An offset beyond this many noise sigmas is removed. 3: the median of a
        healthy frame of 2400 samples strays 0.026 sigma, so a healthy channel is
        100 standard errors away; an offset below 3 sigma changes no echo.
    rail_min_samples
        Samples at one rail (after the ring-down) that make a flat top.
    rail_pileup
        Samples at the rail per sample in the band just below it.
    rail_band
        Width of that band, as a fraction of the rail's distance from the offset.
    noisy_ratio
        Noise sigma, as a multiple of the median of the other channels', above which a
        channel is noisy (12 dB: more than a healthy array's spread of gains).
    clipped_range_db
        Near clipped samples, a correlation peak weaker than the strongest within the
        template's reach by more than this is distortion, not an echo (dB). A hard
        limiter's intermodulation products stand 10 dB or more below the signals that
        make them, the Barker code's sidelobes 22 dB: 14 dB lies between the two (the
        recall and false objects it gives beside 10-20 dB are in
        ``benchmarks/results/channel_health.md``).
    """

    dc_sigmas: float = 3.0
    rail_min_samples: int = 8
    rail_pileup: float = 2.0
    rail_band: float = 0.05
    noisy_ratio: float = 4.0
    clipped_range_db: float = 14.0


@dataclass(frozen=True, eq=False)
class ChannelHealth:
    """Each channel's problems and what is done about them.

    ``problems[i]``: the problems of channel ``i`` (names from :data:`PROBLEMS`,
    empty: healthy). ``excluded``: channels left out of localisation. ``dc``: channels
    whose per-frame median is subtracted. ``kept``: degraded channels left in because
    too few others work. ``reread``: clipped channels kept, their echoes near clipped
    samples re-read (:func:`reread_clipped`). ``offsets`` and ``sigmas``: what was
    measured, per channel. ``rails`` (n_rx, 2): the lower and upper rail of each
    channel's flat tops in raw samples (-inf and inf where it has none).
    """

    problems: tuple[tuple[str, ...], ...]
    excluded: tuple[int, ...] = ()
    dc: tuple[int, ...] = ()
    kept: tuple[int, ...] = ()
    offsets: NDArray[Any] = field(default_factory=lambda: np.zeros(0))
    sigmas: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    reread: tuple[int, ...] = ()
    rails: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 2)))

    @property
    def healthy(self) -> bool:
        return not any(self.problems)

    def excluded_mask(self, n_receivers: int) -> NDArray[np.bool_]:
        """Boolean mask (n_receivers,): True where a channel is left out."""
        mask = np.zeros(n_receivers, dtype=bool)
        mask[[i for i in self.excluded if i < n_receivers]] = True
        return mask


def healthy(n_receivers: int) -> ChannelHealth:
    """The health of ``n_receivers`` channels with nothing wrong."""
    return ChannelHealth(
        ((),) * n_receivers,
        offsets=np.zeros(n_receivers),
        sigmas=np.zeros(n_receivers),
        rails=_no_rails(n_receivers),
    )


def _no_rails(n_receivers: int) -> NDArray[np.float64]:
    return np.tile([-np.inf, np.inf], (n_receivers, 1))


# --- the detectors ---------------------------------------------------------------------------


def _parts(frames: NDArray[Any]) -> NDArray[np.float64]:
    """Real parts of samples (n_frames, n_rx, n_samples) as (n_parts, n_frames, n_rx, n_samples):
    the samples themselves, or I and Q of complex ones (an IQ ADC clips each)."""
    x = np.asarray(frames)
    if np.iscomplexobj(x):
        return np.stack([x.real, x.imag]).astype(float, copy=False)
    return np.asarray(x, dtype=float)[None]


def _leading_run(hits: NDArray[np.intp], gap: int) -> int:
    """How many of the sorted sample indices ``hits`` belong to a run that starts within
    ``gap`` samples of the frame's start, successive hits less than ``gap`` apart (a
    saturated ring-down: it starts with the emission)."""
    if len(hits) == 0 or hits[0] >= gap:
        return 0
    breaks = np.flatnonzero(np.diff(hits) >= gap)
    return int(breaks[0]) + 1 if len(breaks) else len(hits)


def _rail_count(x: NDArray[np.float64], rail: float, gap: int) -> int:
    """Samples of one channel (n_frames, n_samples) at ``rail``, the leading run of each frame left out."""
    at = x == rail
    count = 0
    for frame in np.flatnonzero(at.any(axis=1)):
        hits = np.flatnonzero(at[frame])
        count += len(hits) - _leading_run(hits, gap)
    return count


def _clipped(
    x: NDArray[np.float64], offset: float, limits: HealthLimits, gap: int, lower: bool
) -> tuple[float, float]:
    """The lower and upper rail of one channel's samples (n_frames, n_samples) where they make
    a flat top (module doc); -inf and inf where they do not."""
    found = [-math.inf, math.inf]
    finite = x[np.isfinite(x)]
    if finite.size == 0:
        return found[0], found[1]
    rails = [(float(finite.max()), 1.0)] + ([(float(finite.min()), -1.0)] if lower else [])
    # The quantiser's step (the smallest gap between sample values): the band below a rail
    # spans at least one code, so noise of a fraction of a code piling up on its top code
    # is no flat top.
    levels = np.unique(finite)
    step = float(np.min(np.diff(levels))) if len(levels) > 1 else 0.0
    for rail, sign in rails:
        reach = sign * (rail - offset)
        if not reach > 0:
            continue
        on_rail = _rail_count(x, rail, gap)
        if on_rail < limits.rail_min_samples:
            continue
        band = sign * (finite - rail)
        width = max(limits.rail_band * reach, 1.5 * step)
        below = int(np.count_nonzero((band < 0) & (band >= -width)))
        if on_rail >= limits.rail_pileup * max(below, 1):
            found[sign > 0] = rail
    return found[0], found[1]


def assess_channels(
    frames: NDArray[Any],
    signal_kind: str = "rf",
    *,
    min_receivers: int = 3,
    ring_down_samples: int = 1,
    limits: HealthLimits | None = None,
    reread_clipped: bool = False,
) -> ChannelHealth:
    """Each channel's health from a batch of raw frames (n_frames, n_rx, n_samples) (module doc).

    ``signal_kind``: ``rf``, ``iq`` (complex samples) or ``envelope`` (no DC offset
    assessed, only the top rail). ``min_receivers``: clipped and noisy channels are left
    out only while at least this many other channels work. ``ring_down_samples``: rail
    samples in a run starting within this many samples of a frame's start, each less
    than this far from the next, are a saturated ring-down and do not count as clipping
    (a quarter of the pulse is a good value). ``reread_clipped``: a clipped channel (of
    rf samples, and not noisy too) is kept and re-read (:func:`reread_clipped`) instead
    of left out. Pure: the frames are not modified.
    """
    limits = limits or HealthLimits()
    x = np.asarray(frames)
    if x.ndim == 2:
        x = x[None]
    n_frames, n_rx, _ = x.shape
    gap = max(1, int(ring_down_samples))
    finite = np.isfinite(x).all(axis=(0, 2)) if n_frames else np.ones(n_rx, dtype=bool)
    parts = _parts(np.where(np.isfinite(x), x, 0) if not finite.all() else x)
    dead = np.ptp(parts, axis=(1, 3)).max(axis=0) == 0 if n_frames else np.zeros(n_rx, dtype=bool)
    medians = np.median(parts, axis=3)  # (n_parts, n_frames, n_rx)
    quartile = np.quantile(np.abs(parts - medians[..., None]), 0.25, axis=3)
    sigmas_parts = LOWER_QUARTILE_TO_SIGMA * np.median(quartile, axis=1)  # (n_parts, n_rx)
    sigmas = np.sqrt(np.mean(sigmas_parts**2, axis=0))
    offsets_parts = np.median(medians, axis=1)  # (n_parts, n_rx)
    offsets: NDArray[Any] = (
        offsets_parts[0] + 1j * offsets_parts[1] if len(offsets_parts) == 2 else offsets_parts[0]
    )
    problems: list[list[str]] = [[] for _ in range(n_rx)]
    rails = _no_rails(n_rx)
    for rx in range(n_rx):
        if not finite[rx]:
            problems[rx].append("non-finite")
        if dead[rx]:
            problems[rx].append("dead")
            continue
        found = [
            _clipped(
                parts[p, :, rx], float(offsets_parts[p, rx]), limits, gap, lower=signal_kind != "envelope"
            )
            for p in range(len(parts))
        ]
        if any(math.isfinite(rail) for pair in found for rail in pair):
            problems[rx].append("clipped")
            if len(parts) == 1:
                rails[rx] = found[0]
        if (
            signal_kind != "envelope"
            and sigmas[rx] > 0
            and np.max(np.abs(offsets_parts[:, rx])) > limits.dc_sigmas * sigmas[rx]
        ):
            problems[rx].append("dc-offset")
        others = np.delete(sigmas, np.flatnonzero(dead | (np.arange(n_rx) == rx)))
        if len(others) and np.median(others) > 0 and sigmas[rx] > limits.noisy_ratio * np.median(others):
            problems[rx].append("noisy")
    return _decided(
        tuple(tuple(p for p in PROBLEMS if p in found) for found in problems),
        min_receivers,
        reread_clipped and signal_kind == "rf",
        lambda rx: ("noisy" not in problems[rx], -sigmas[rx]),  # the worst first
        offsets=offsets,
        sigmas=sigmas,
        rails=rails,
    )


def _decided(
    problems: tuple[tuple[str, ...], ...],
    min_receivers: int,
    reread_clipped: bool,
    worst_first: Any,
    **measured: Any,
) -> ChannelHealth:
    """The health of channels with ``problems``: which are left out, corrected, re-read or kept.
    Non-finite and dead channels are left out; a channel whose only exclusion is clipping is
    re-read when ``reread_clipped``; the others (noisy, or clipped) are left out, in the order
    of the key ``worst_first``, while ``min_receivers`` others remain."""
    n_rx = len(problems)
    always = [rx for rx in range(n_rx) if {"non-finite", "dead"} & set(problems[rx])]
    reread = [
        rx
        for rx in range(n_rx)
        if reread_clipped and rx not in always and EXCLUDING & set(problems[rx]) == {"clipped"}
    ]
    optional = [
        rx for rx in range(n_rx) if rx not in always and rx not in reread and EXCLUDING & set(problems[rx])
    ]
    optional.sort(key=worst_first)
    room = max(0, n_rx - len(always) - min_receivers)
    return ChannelHealth(
        problems=problems,
        excluded=tuple(sorted(always + optional[:room])),
        dc=tuple(rx for rx in range(n_rx) if "dc-offset" in problems[rx]),
        kept=tuple(sorted(optional[room:])),
        reread=tuple(reread),
        **measured,
    )


def merge(
    first: ChannelHealth, later: ChannelHealth, min_receivers: int = 3, reread_clipped: bool = False
) -> ChannelHealth:
    """The health of a session that showed ``first`` and then ``later``: every problem seen
    in either kept, and every rail; a channel left out by either stays out while enough
    others remain."""
    n_rx = len(first.problems)
    problems = tuple(
        tuple(p for p in PROBLEMS if p in set(a) | set(b))
        for a, b in zip(first.problems, later.problems, strict=True)
    )
    rails = _no_rails(n_rx)
    for health in (first, later):
        if len(health.rails) == n_rx:
            rails[:, 0] = np.maximum(rails[:, 0], health.rails[:, 0])
            rails[:, 1] = np.minimum(rails[:, 1], health.rails[:, 1])
    return _decided(
        problems,
        min_receivers,
        reread_clipped,
        lambda rx: (rx not in first.excluded, "noisy" not in problems[rx]),
        offsets=later.offsets,
        sigmas=later.sigmas,
        rails=rails,
    )


# --- corrections -----------------------------------------------------------------------------


def correct_frames(frames: NDArray[Any], health: ChannelHealth) -> NDArray[Any]:
    """Frames (n_frames, n_rx, n_samples) corrected for ``health``: non-finite samples set
    to 0, and each DC channel's per-frame median subtracted (of I and Q apart for complex
    samples). The input is returned unchanged (the same array) when nothing applies."""
    x = np.asarray(frames)
    finite = bool(np.isfinite(x).all())
    if finite and not health.dc:
        return x
    out = x.copy() if finite else np.where(np.isfinite(x), x, 0).astype(x.dtype, copy=False)
    for rx in health.dc:
        if rx >= out.shape[1]:
            continue
        channel = out[:, rx]
        if np.iscomplexobj(channel):
            median = np.median(channel.real, axis=-1) + 1j * np.median(channel.imag, axis=-1)
        else:
            median = np.median(channel, axis=-1)
        out[:, rx] = channel - median[:, None]
    return out


# --- re-reading clipped channels ------------------------------------------------------------


def clipped_samples(frames: NDArray[Any], health: ChannelHealth) -> NDArray[np.bool_]:
    """Which raw samples of frames (n_frames, n_rx, n_samples) lie on a rail of a re-read
    channel (``health.reread``): (n_frames, n_rx, n_samples), False on every other channel."""
    x = np.asarray(frames)
    at = np.zeros(x.shape, dtype=bool)
    for rx in health.reread:
        if rx < x.shape[1] and rx < len(health.rails) and not np.iscomplexobj(x):
            lower, upper = health.rails[rx]
            at[:, rx] = (x[:, rx] >= upper) | (x[:, rx] <= lower)
    return at


def reread_clipped(
    conditioned: NDArray[np.floating],
    clipped: NDArray[np.bool_],
    channels_of_frames: Sequence[Sequence[ChannelEchoes]],
    mf: MatchedFilter,
    options: EchoOptions,
    limits: HealthLimits | None = None,
) -> list[list[ChannelEchoes]]:
    """The estimator's echoes (``channels_of_frames[f][rx]``) of frames (n_frames, n_rx,
    n_samples, as conditioned for the estimator), each channel with ``clipped`` samples
    (:func:`clipped_samples`) re-read near them (module doc): its echoes whose template
    reaches a clipped sample are replaced by the matched filter's peaks there. Channels
    without clipped samples come back as they were (the same objects)."""
    limits = limits or HealthLimits()
    out = [list(channels) for channels in channels_of_frames]
    rows = np.argwhere(np.asarray(clipped).any(axis=-1))
    if len(rows) == 0:
        return out
    samples = np.asarray(conditioned)[rows[:, 0], rows[:, 1]]
    correlations = mf.correlate(samples.astype(float, copy=False), options.threads)
    lobe = math.ceil(mf.mainlobe_lags) * mf.decimation
    reach = mf.residue_lags * mf.decimation
    for (f, rx), correlation in zip(rows.tolist(), correlations, strict=True):
        touches = _clipping_within(clipped[f, rx], mf, lobe)
        reaches = _clipping_within(clipped[f, rx], mf, reach)
        echoes = out[f][rx]
        strongest, tof_s, amplitude, snr_db = _peaks(correlation, mf, limits)
        # The estimator's echoes clipping reaches stand where they are no weaker than the
        # correlation's peaks there; those it touches are re-read.
        floor = strongest[_lag_index(echoes.tof_s, mf, len(correlation))] * 10 ** (
            -limits.clipped_range_db / 20
        )
        own = ~touches(echoes.tof_s) & (~reaches(echoes.tof_s) | (np.abs(echoes.amplitude) >= floor))
        peaks = touches(tof_s)
        found = finish_channel(
            np.concatenate([echoes.tof_s[own], tof_s[peaks]]),
            np.concatenate([echoes.amplitude[own], amplitude[peaks]]),
            np.concatenate([echoes.snr_db[own], snr_db[peaks]]),
            options,
            mf.support_s,
        )
        if len(found.tof_s) > options.max_echoes:
            strongest = np.sort(np.argsort(-np.abs(found.amplitude), kind="stable")[: options.max_echoes])
            found = ChannelEchoes(found.tof_s[strongest], found.amplitude[strongest], found.snr_db[strongest])
        out[f][rx] = found
    return out


def touches_clipping(
    clipped: NDArray[np.bool_], tof_s: NDArray[np.float64], mf: MatchedFilter
) -> NDArray[np.bool_]:
    """Whether echoes arriving at ``tof_s`` (s) on a channel whose samples ``clipped``
    (n_samples,) marks would have a clipped sample within their template's samples (widened
    by a main lobe either side): where :func:`reread_clipped` reads the channel anew, and
    where the channel may have lost an echo."""
    lobe = math.ceil(mf.mainlobe_lags) * mf.decimation
    return np.asarray(_clipping_within(np.asarray(clipped, dtype=bool), mf, lobe)(tof_s))


def _lag_index(tof_s: NDArray[np.float64], mf: MatchedFilter, n_lags: int) -> NDArray[np.intp]:
    """The correlation's lag nearest each delay (s), within 0..n_lags - 1."""
    lags = np.nan_to_num((np.asarray(tof_s, dtype=float) - mf.arrival_s) * mf.lag_rate_hz)
    return np.clip(np.round(lags), 0, n_lags - 1).astype(np.intp)


def _clipping_within(clipped: NDArray[np.bool_], mf: MatchedFilter, reach: int) -> Any:
    """A test of delays (s): whether an echo arriving then has a clipped sample among its
    template's samples or within ``reach`` samples on either side."""
    counts = np.concatenate([[0], np.cumsum(clipped)])
    n = len(clipped)
    length = len(mf.template)
    rate = mf.sample_rate_hz

    def near(tof_s: NDArray[np.float64]) -> NDArray[np.bool_]:
        start = np.floor((np.asarray(tof_s, dtype=float) - mf.arrival_s) * rate)
        start = np.nan_to_num(start, nan=-2.0 * (n + length + reach))
        lo = np.clip(start - reach, 0, n).astype(int)
        hi = np.clip(start + length + reach + 1, 0, n).astype(int)
        return np.asarray(counts[hi] > counts[lo])

    return near


def _peaks(
    correlation: NDArray[np.complex128], mf: MatchedFilter, limits: HealthLimits
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """The strongest envelope of one channel's analytic correlation within the template's
    reach of each lag, and the delays (s), amplitudes and SNRs (dB) of the envelope's local
    maxima that stand within :attr:`HealthLimits.clipped_range_db` of it; the threshold and
    blanking are left to :func:`echoloc.tof.echoes.finish_channel`. Each delay as the estimator
    times an echo: the envelope's parabola, refined by the carrier phase at the peak and its
    neighbours."""
    magnitude = np.abs(correlation)
    power = noise_power(correlation)
    n = len(magnitude)
    strongest = ndimage.maximum_filter1d(magnitude, 2 * mf.residue_lags + 1, mode="constant")
    if n < 3:
        return strongest, np.zeros(0), np.zeros(0), np.zeros(0)
    inner = magnitude[1:-1]
    peaks = np.flatnonzero((inner > magnitude[:-2]) & (inner >= magnitude[2:])) + 1
    peaks = peaks[magnitude[peaks] >= strongest[peaks] * 10 ** (-limits.clipped_range_db / 20)]
    a, b, c = magnitude[peaks - 1], magnitude[peaks], magnitude[peaks + 1]
    curvature = a - 2 * b + c
    with np.errstate(divide="ignore", invalid="ignore"):
        offset = np.where(curvature < 0, np.clip(0.5 * (a - c) / curvature, -0.5, 0.5), 0.0)
    coarse = peaks + offset
    rate = mf.phase_rate_rad_per_lag
    period = np.pi / rate  # half a carrier cycle, in lags
    lags = peaks[:, None] + np.arange(-1, 2)[None, :]
    values = correlation[lags]
    estimates = lags - np.angle(values) / rate
    estimates += period * np.round((coarse[:, None] - estimates) / period)
    weights = np.abs(values) ** 2
    tof = np.sum(weights * estimates, axis=1) / np.sum(weights, axis=1)
    tof = np.where(np.abs(tof - coarse) > 1.5, coarse, tof)
    amplitude = b  # the estimator's amplitudes are magnitudes too (the sign goes into the delay)
    snr_db = 10 * np.log10(np.maximum(b**2, np.finfo(float).tiny) / power)
    return strongest, tof / mf.lag_rate_hz + mf.arrival_s, amplitude, snr_db


# --- words -----------------------------------------------------------------------------------


def health_messages(health: ChannelHealth, source: str, previous: ChannelHealth | None = None) -> list[str]:
    """One line per degraded channel naming ``source``, the channel, what is wrong and what
    is done; with ``previous``, only channels whose problems are new."""
    lines = []
    for rx, found in enumerate(health.problems):
        if not found:
            continue
        if previous is not None and rx < len(previous.problems) and set(found) <= set(previous.problems[rx]):
            continue
        what = []
        for problem in found:
            if problem == "dc-offset":
                offset = health.offsets[rx]
                what.append(
                    f"a DC offset of {_number(offset)} ({_ratio(offset, health.sigmas[rx])} noise sigma)"
                )
            elif problem == "noisy":
                what.append(f"noise sigma {health.sigmas[rx]:.3g}, far above the other channels'")
            else:
                what.append(problem)
        if rx in health.excluded:
            done = "left out of localisation"
        elif rx in health.reread:
            done = "kept, its echoes near clipped samples read from the matched filter's peaks"
        elif rx in health.kept:
            done = "kept: too few other receivers work"
        else:
            done = "corrected"
        if "dc-offset" in found and rx not in health.kept:
            done = "offset removed" + ("" if rx not in health.excluded else f", {done}")
        elif "non-finite" in found:
            done = f"non-finite samples set to 0, {done}"
        lines.append(f"{source}: receiver {rx} is degraded ({', '.join(what)}): {done}")
    return lines


def warn_health(
    health: ChannelHealth, source: str, previous: ChannelHealth | None = None, stacklevel: int = 2
) -> None:
    """Issue :func:`health_messages` as :class:`ChannelWarning` s."""
    for line in health_messages(health, source, previous):
        warnings.warn(line, ChannelWarning, stacklevel=stacklevel + 1)


def _number(value: complex | float) -> str:
    if isinstance(value, complex) or np.iscomplexobj(value):
        z = complex(value)
        return f"{z.real:.3g}{z.imag:+.3g}j"
    return f"{float(value):.3g}"


def _ratio(offset: complex | float, sigma: float) -> str:
    return f"{abs(complex(offset)) / sigma:.3g}" if sigma > 0 and math.isfinite(sigma) else "inf"


# --- a live session --------------------------------------------------------------------------


class ChannelWatch:
    """The channels' health over a session's first frames (mutable: it learns as frames come).

    Frames are assessed batch by batch (:meth:`observe`) until :data:`ASSESS_FRAMES`
    have been seen (or from the start, when ``settled``); every problem found is kept
    for the session and warned about once, naming ``source``.
    """

    def __init__(
        self,
        source: str,
        signal_kind: str,
        n_receivers: int,
        *,
        min_receivers: int = 3,
        ring_down_samples: int = 1,
        health: ChannelHealth | None = None,
        settled: bool = False,
        limits: HealthLimits | None = None,
        reread_clipped: bool = False,
    ) -> None:
        self.source = source
        self.signal_kind = signal_kind
        self.min_receivers = min_receivers
        self.ring_down_samples = ring_down_samples
        self.limits = limits
        self.reread_clipped = reread_clipped
        self.health = health or healthy(n_receivers)
        self.frames_seen = ASSESS_FRAMES if settled else 0

    def observe(self, frames: Sequence[NDArray[Any]] | NDArray[Any]) -> ChannelHealth:
        """The health to correct ``frames`` (n_frames, n_rx, n_samples) with, after assessing
        them too while the session is young."""
        if self.frames_seen >= ASSESS_FRAMES:
            return self.health
        batch = np.asarray(frames)
        if batch.ndim != 3 or batch.shape[1] != len(self.health.problems):
            return self.health
        batch = batch[: ASSESS_FRAMES - self.frames_seen]
        found = assess_channels(
            batch,
            self.signal_kind,
            min_receivers=self.min_receivers,
            ring_down_samples=self.ring_down_samples,
            limits=self.limits,
            reread_clipped=self.reread_clipped,
        )
        self.frames_seen += len(batch)
        previous = self.health
        self.health = merge(
            previous, found, self.min_receivers, self.reread_clipped and self.signal_kind == "rf"
        )
        warn_health(self.health, self.source, previous, stacklevel=4)
        return self.health
