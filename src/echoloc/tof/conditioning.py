"""Frame conditioning: what is done to a frame before any estimator sees it.

Three steps, in the order the signal needs them undone, each a pure function, and a
frozen :class:`Conditioning` that says which to apply:

1. **Background subtraction** (:func:`subtract_background`): the recording's
   ``background``, a recording of the empty scene with the same gain (docs/FORMATS.md),
   (n_rx, n_samples) or one per frame (n_frames, n_rx, n_samples), is subtracted,
   which removes what is the same in every frame: crosstalk, the transmitter's
   ring-down, the direct path, fixed reflections. For envelope recordings the
   subtraction is in power, ``sqrt(max(|f|^2 - |b|^2, 0))``: an echo and the
   empty scene's signal with unrelated carrier phase add in power on average
   (``E|s + b|^2 = |s|^2 + |b|^2``), whereas magnitudes subtracted directly shift an
   echo that overlaps clutter (measured on real CH101 data: 1 mm less median 3-D error,
   ``benchmarks/real_ch101.py``); where the empty scene is stronger there is no echo.
2. **Time-varying gain compensation** (:func:`compensate_gain`): frames are divided
   by ``receiver_gain`` (n_samples,), so the samples are the signal at the transducer
   (docs/FORMATS.md, :class:`~echoloc.io.recording.Recording`) and noise added before the
   amplifier is stationary again.
3. **Blind zone** (:func:`blind_zone_s`): a time before which nothing is reported,
   either given in seconds or ``"auto"``: the end of the transmitter's ring-down
   found in each frame (:func:`ring_down_end_s`). It acts through the estimators'
   ``blanking_s`` (:class:`~echoloc.tof.echoes.EchoOptions`), which the effective
   blanking is the larger of, so that the estimators also leave it out of their
   levels and dynamic-range floors: a ring-down 60 dB above the echoes does not
   hide them. ``--blanking-s`` keeps working: it is a blind zone given by hand, and
   the larger of the two wins.

The automatic rule (:func:`ring_down_end_s`): per receiver, the envelope (analytic
signal for rf, magnitude for iq and envelope recordings) is compared with a level
``blind_zone_db`` above the channel's noise power (``median(e^2) / ln 2``, as the
estimators use; at least ``blind_zone_dynamic_range_db`` below the channel's
largest envelope, so clean data has a finite level too). If the envelope is above
the level at t = 0 (the ring-down starts with the emission), the ring-down lasts
until the envelope has stayed below the level for one template length (dips
shorter than that, e.g. at the code's phase reversals or between the ring-down and
the direct path, do not end it). Clipped samples are far above any level, so a
clipped ring-down is covered. The blind zone is the latest end over the receivers
plus one template length (``blind_zone_margin_s``): the ring-down's tail below the
level still correlates with the template, and an estimator with processing gain
(the matched filter) would see it. A direct path that arrives after the ring-down
has fallen below the level for a template length is an echo to this rule; give the
blind zone in seconds then.

:func:`conditioned` wraps an estimator so it does all three to each frame; the
per-frame chain (:mod:`echoloc.pipeline`) uses :func:`condition_frame`, which
knows the frame's index (for per-frame backgrounds), and :func:`blinded`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from functools import lru_cache
from typing import Any, Literal

import numpy as np
import scipy.fft
from numpy.typing import NDArray

from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording
from echoloc.tof.echoes import EchoOptions, analytic_weights, noise_power
from echoloc.tof.estimators import Estimator, prepare_estimator

Samples = NDArray[Any]
"""Frame samples: real (rf, envelope) or complex (iq)."""

BLIND_ZONE_CACHE = 16
"""Prepared estimators an automatic blind zone keeps, one per blanking time met."""


@dataclass(frozen=True)
class Conditioning:
    """Which conditioning steps to apply (module doc).

    Attributes
    ----------
    background
        Subtract the recording's ``background``. None (default): when it has one.
        True with a recording that has none is an error.
    tvg
        Divide by the recording's ``receiver_gain``. None (default): when it has one.
        True with a recording that has none is an error.
    blind_zone_s
        Nothing is reported before this time: seconds (>= 0), ``"auto"`` (the end of
        the ring-down in each frame, :func:`ring_down_end_s`), or None (no blind zone
        besides the estimators' own ``blanking_s``).
    blind_zone_db
        For ``"auto"``: the level above the noise power that the ring-down's
        envelope must exceed, dB. 10 dB: exponential noise power passes it with
        probability exp(-10) = 4.5e-5 per sample, so noise does not prolong the
        ring-down.
    blind_zone_dynamic_range_db
        For ``"auto"``: the level is at least this far below the channel's largest
        envelope, dB (a finite level for noise-free frames).
    blind_zone_margin_s
        For ``"auto"``: time added after the ring-down's end, s. None: the template's
        duration (or 0 without a template).
    """

    background: bool | None = None
    tvg: bool | None = None
    blind_zone_s: float | Literal["auto"] | None = None
    blind_zone_db: float = 10.0
    blind_zone_dynamic_range_db: float = 60.0
    blind_zone_margin_s: float | None = None

    def __post_init__(self) -> None:
        zone = self.blind_zone_s
        given = zone is not None and zone != "auto"
        if given and (isinstance(zone, bool) or not isinstance(zone, int | float) or not zone >= 0):
            raise EchoLocError(f"blind zone must be a time >= 0 s or 'auto', got {zone!r}")
        if given and not math.isfinite(float(zone)):  # type: ignore[arg-type]
            raise EchoLocError(f"blind zone must be a time >= 0 s or 'auto', got {zone!r}")
        for name in ("blind_zone_db", "blind_zone_dynamic_range_db"):
            if not math.isfinite(getattr(self, name)):
                raise EchoLocError(f"conditioning {name} must be finite, got {getattr(self, name)!r}")
        margin = self.blind_zone_margin_s
        if margin is not None and not (math.isfinite(margin) and margin >= 0):
            raise EchoLocError(f"blind-zone margin must be >= 0 s, got {margin!r}")


def parse_blind_zone(text: str) -> float | Literal["auto"]:
    """``--blind-zone`` text: ``auto`` or a time in seconds (finite, >= 0)."""
    if text.strip().lower() == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError:
        raise EchoLocError(f"--blind-zone must be SECONDS or auto, got {text!r}") from None
    if not (math.isfinite(value) and value >= 0):
        raise EchoLocError(f"--blind-zone must be a time >= 0 s or auto, got {text!r}")
    return value


# --- the steps ---------------------------------------------------------------------------


def subtract_background(frames: Samples, background: Samples, signal_kind: str = "rf") -> Samples:
    """``frames - background`` (broadcast over the leading axes); envelopes in power, floored at 0.

    ``background`` has the shape of one frame (n_rx, n_samples), or of ``frames``.
    """
    if signal_kind == "envelope":
        power = np.asarray(frames, dtype=float) ** 2 - np.asarray(background, dtype=float) ** 2
        return np.asarray(np.sqrt(np.maximum(power, 0.0)))
    difference: Samples = np.asarray(frames) - np.asarray(background)
    return difference


def compensate_gain(frames: Samples, gain: NDArray[np.floating]) -> Samples:
    """Undo a time-varying gain: ``frames / gain`` with ``gain`` (n_samples,) along the last axis."""
    g = np.asarray(gain, dtype=float)
    if g.ndim != 1 or g.shape[0] != np.shape(frames)[-1]:
        raise EchoLocError(f"receiver gain has shape {g.shape}, frames have {np.shape(frames)[-1]} samples")
    if not np.all(g > 0):
        raise EchoLocError("receiver gain must be > 0 at every sample")
    return np.asarray(np.asarray(frames) / g)


def _uses_background(recording: Recording, spec: Conditioning) -> bool:
    if spec.background and recording.background is None:
        raise EchoLocError(f"{recording.source}: background subtraction asked for, but it has no background")
    return recording.background is not None and spec.background is not False


def _uses_gain(recording: Recording, spec: Conditioning) -> bool:
    if spec.tvg and recording.receiver_gain is None:
        raise EchoLocError(f"{recording.source}: gain compensation asked for, but it has no receiver_gain")
    return recording.receiver_gain is not None and spec.tvg is not False


def condition_frame(
    frame: Samples, recording: Recording, spec: Conditioning, index: int | None = None
) -> Samples:
    """Background subtraction and gain compensation of one frame (n_rx, n_samples).

    ``index`` is the frame's index in ``recording``, needed only with one background
    per frame.
    """
    out = np.asarray(frame)
    if _uses_background(recording, spec):
        background = np.asarray(recording.background)
        if background.ndim == 3:
            if index is None:
                raise EchoLocError(
                    f"{recording.source}: its background has one frame per frame; give the frame's index"
                )
            background = background[index]
        out = subtract_background(out, background, recording.signal_kind)
    if _uses_gain(recording, spec):
        assert recording.receiver_gain is not None
        out = compensate_gain(out, recording.receiver_gain)
    return out


def condition_frames(
    frames: Samples, recording: Recording, spec: Conditioning, indices: Sequence[int] | None = None
) -> Samples:
    """:func:`condition_frame` of frames (n, n_rx, n_samples) at once.

    ``indices`` are the frames' indices in ``recording`` (for a per-frame background);
    None means all of the recording's frames, in order, when there are as many.
    """
    out = np.asarray(frames)
    if _uses_background(recording, spec):
        background = np.asarray(recording.background)
        if background.ndim == 3:
            if indices is None:
                if len(out) != recording.n_frames:
                    raise EchoLocError(
                        f"{recording.source}: its background has one frame per frame; give the frame indices"
                    )
                indices = range(recording.n_frames)
            background = background[np.asarray(indices, dtype=int)]
        out = subtract_background(out, background, recording.signal_kind)
    if _uses_gain(recording, spec):
        assert recording.receiver_gain is not None
        out = compensate_gain(out, recording.receiver_gain)
    return out


# --- blind zone ----------------------------------------------------------------------------


def frame_envelope(frame: Samples, signal_kind: str) -> NDArray[np.float64]:
    """Envelope of each channel of a frame: analytic-signal magnitude for rf, magnitude otherwise."""
    x = np.asarray(frame)
    if signal_kind != "rf" or np.iscomplexobj(x):
        return np.asarray(np.abs(x), dtype=float)
    n = x.shape[-1]
    n_fft = int(scipy.fft.next_fast_len(2 * n, real=True))
    spectrum = scipy.fft.rfft(x, n_fft, axis=-1) * analytic_weights(n_fft)
    return np.asarray(np.abs(scipy.fft.ifft(spectrum, n_fft, axis=-1)[..., :n]), dtype=float)


def _template_samples(recording: Recording) -> int:
    return 0 if recording.waveform is None else len(recording.waveform)


def _run_from_start(channel: NDArray[np.float64], spec: Conditioning, gap: int) -> int:
    """Where a channel's excursion above the level that starts with the frame ends (0: none).

    The level is ``blind_zone_db`` above ``median(x^2) / ln 2``, and at least
    ``blind_zone_dynamic_range_db`` below the channel's largest value. The excursion
    must begin within the first ``gap`` samples (a ring-down builds up through the
    transducer's resonance), and ends at the first sample after which the channel
    stays below the level for ``gap`` samples (shorter dips do not end it); the
    length of the channel if never.
    """
    noise = noise_power(channel)
    level = max(
        math.sqrt(noise * 10 ** (spec.blind_zone_db / 10)),
        float(channel.max(initial=0.0)) * 10 ** (-spec.blind_zone_dynamic_range_db / 20),
    )
    above = np.flatnonzero(channel >= level) if level > 0 else np.zeros(0, dtype=int)
    if len(above) == 0 or above[0] >= gap:
        return 0
    start = int(above[0])
    quiet = np.convolve(channel[start:] < level, np.ones(gap), mode="valid")
    settled = np.flatnonzero(quiet == gap)
    return start + int(settled[0]) if len(settled) else len(channel)


def ring_down_end_s(frame: Samples, recording: Recording, spec: Conditioning) -> float:
    """When the ring-down that starts with the emission has ended on every receiver, s (module doc).

    The latest end over the receivers of the envelope's excursion above the level
    that starts at t = 0 (:func:`_run_from_start`, dips shorter than a quarter
    template bridged); 0 when none starts there. Without the margin.
    """
    gap = max(1, _template_samples(recording) // 4)
    envelope = frame_envelope(frame, recording.signal_kind)
    latest = 0
    for channel in envelope.reshape(-1, envelope.shape[-1]):
        latest = max(latest, _run_from_start(channel, spec, gap))
    return latest / recording.sample_rate_hz


def blind_zone_s(frame: Samples, recording: Recording, spec: Conditioning) -> float:
    """The blind zone of a (conditioned) frame, s: 0, the given time, or the ring-down's end plus margin."""
    zone = spec.blind_zone_s
    if zone is None:
        return 0.0
    if zone != "auto":
        return float(zone)
    end = ring_down_end_s(frame, recording, spec)
    if end == 0:
        return 0.0
    margin = spec.blind_zone_margin_s
    if margin is None:
        margin = _template_samples(recording) / recording.sample_rate_hz
    return end + margin


def effective_options(options: EchoOptions, spec: Conditioning) -> EchoOptions:
    """``options`` with a blind zone given in seconds folded into ``blanking_s`` (the larger wins)."""
    zone = spec.blind_zone_s
    if zone is None or zone == "auto" or zone <= options.blanking_s:
        return options
    return replace(options, blanking_s=float(zone))


# --- wrappers ------------------------------------------------------------------------------

Prepare = Callable[[EchoOptions], Estimator]
"""Prepares an estimator for a recording with given options (e.g. a bound registry entry)."""


def blinded(prepare: Prepare, recording: Recording, spec: Conditioning, options: EchoOptions) -> Estimator:
    """An estimator that applies the blind zone to each (already conditioned) frame.

    A blind zone in seconds (or none) prepares the estimator once with
    :func:`effective_options`. ``"auto"`` finds the blind zone in each frame and runs
    the estimator prepared with ``blanking_s`` the larger of the options' and the
    frame's blind zone (whole samples); the prepared estimators are kept for the
    last :data:`BLIND_ZONE_CACHE` blanking times, since a ring-down ends at much the
    same time frame after frame.
    """
    base = effective_options(options, spec)
    if spec.blind_zone_s != "auto":
        return prepare(base)
    rate = recording.sample_rate_hz

    @lru_cache(maxsize=BLIND_ZONE_CACHE)
    def prepared(blanking_samples: int) -> Estimator:
        return prepare(replace(base, blanking_s=max(base.blanking_s, blanking_samples / rate)))

    prepared(0)  # prepares now, so a recording the estimator refuses is refused here

    def run(frame: NDArray[np.floating]) -> list[Any]:
        samples = math.ceil(blind_zone_s(frame, recording, spec) * rate - 1e-9)
        return prepared(samples)(frame)

    return run


def conditioned(
    estimator: str | Prepare, recording: Recording, spec: Conditioning, options: EchoOptions
) -> Estimator:
    """An estimator (a registry name, or a :data:`Prepare`) that conditions each frame first.

    Background subtraction, gain compensation (:func:`condition_frame`) and the blind
    zone (:func:`blinded`). A recording with one background per frame needs each
    frame's index: use :func:`condition_frame` and :func:`blinded` instead (as
    :func:`echoloc.pipeline.frame_echoes` does).
    """
    if _uses_background(recording, spec) and np.asarray(recording.background).ndim == 3:
        raise EchoLocError(
            f"{recording.source}: its background has one frame per frame; condition frames by index "
            "(condition_frame) rather than through conditioned()"
        )
    prepare: Prepare
    if isinstance(estimator, str):
        name = estimator

        def by_name(opts: EchoOptions) -> Estimator:
            return prepare_estimator(recording, opts, name)

        prepare = by_name
    else:
        prepare = estimator
    run = blinded(prepare, recording, spec, options)
    return lambda frame: run(condition_frame(frame, recording, spec))
