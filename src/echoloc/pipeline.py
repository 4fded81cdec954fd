"""The per-frame chain, recording -> echoes -> objects, with what it precomputes once.

:func:`prepare` turns a recording and the user's options into a :class:`Chain`: the
estimator with its template spectra and tables, the speed of sound and the
localisation options derived from the recording (pulse resolution, carrier,
observable window, receivers to use). :func:`run` then maps frames to results.
"""

from __future__ import annotations

import functools
import itertools
import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording, dead_receivers
from echoloc.localise.calibrate import Calibration, apply_calibration
from echoloc.localise.locate import (
    FrameLocator,
    FrameObjects,
    LocatedObject,
    LocateKernelArguments,
    LocateOptions,
    LocateWarning,
    combine_frames,
    model_paths_m,
)
from echoloc.localise.reflector_kinds import classify_points, locate_with_classes
from echoloc.physics.air import speed_of_sound_m_s
from echoloc.tof.channel_health import (
    ChannelHealth,
    ChannelWatch,
    assess_channels,
    assessed_frames,
    clipped_samples,
    correct_frames,
    healthy,
    reread_clipped,
    touches_clipping,
    warn_health,
)
from echoloc.tof.conditioning import Conditioning, blinded, condition_frame, effective_options
from echoloc.tof.echoes import (
    ChannelEchoes,
    EchoOptions,
    FrameEchoes,
    MatchedFilter,
    echo_kernel_arguments,
    frame_time_s,
    kernel_channels,
    run_kernel,
    with_clean,
)
from echoloc.tof.envelope_peaks import (
    arrivals_from_peaks,
    arrivals_from_truth,
    learn_echo_shape,
    prepare_peak_detector,
)
from echoloc.tof.estimators import (
    Estimator,
    MatchedEstimator,
    default_threshold_db,
    estimate_frames,
    prepare_estimator,
    resolve_estimator,
)
from echoloc.tof.templates import Template

PLAUSIBLE_SPEED_OF_SOUND_M_S = (100.0, 2000.0)
"""Speeds of sound (m/s) :func:`prepare` takes without a warning: every gas a sensor could
work in lies inside (air 331-386 m/s from 0 to 100 °C, CO2 267, helium 1007 at 20 °C); a
value outside is most likely in other units (0.343 m/ms, 34 320 cm/s)."""


def recording_speed_of_sound_m_s(recording: Recording) -> float:
    """Speed of sound for a recording (docs/FORMATS.md): the stored value, else from the air state."""
    if recording.speed_of_sound_m_s is not None:
        return float(recording.speed_of_sound_m_s)
    temperature = 20.0 if recording.temperature_c is None else recording.temperature_c
    humidity = 0.0 if recording.relative_humidity is None else recording.relative_humidity
    return float(speed_of_sound_m_s(temperature, humidity))


@dataclass(frozen=True, eq=False)
class Chain:
    """Everything the per-frame chain reuses for one recording."""

    recording: Recording
    estimator: Estimator
    echo_options: EchoOptions
    locate_options: LocateOptions
    speed_of_sound_m_s: float
    usable_receivers: NDArray[np.bool_]
    calibration: Calibration | None = None
    conditioning: Conditioning = field(default_factory=Conditioning)
    channel_watch: ChannelWatch | None = None

    @property
    def health(self) -> ChannelHealth:
        """The receivers' health (:mod:`echoloc.tof.channel_health`) as assessed so far."""
        watch = self.channel_watch
        return healthy(self.recording.n_receivers) if watch is None else watch.health

    @property
    def working_receivers(self) -> NDArray[np.bool_]:
        """Receivers localisation uses: the usable ones less those a live session's channel
        check left out since (a recording's are left out of ``usable_receivers`` already)."""
        return np.asarray(self.usable_receivers, dtype=bool) & ~self.health.excluded_mask(
            len(self.usable_receivers)
        )

    @cached_property
    def _by_receivers(self) -> dict[tuple[object, ...], Any]:
        """Locators and one-call arguments per set of working receivers (a live session's
        channel check can leave one out after its first frames)."""
        return {}

    @property
    def locators(self) -> tuple[FrameLocator, ...]:
        """A :class:`echoloc.localise.locate.FrameLocator` per transmitter: the set-up its frames share,
        looked up once for the whole recording or stream (and its working receivers)."""
        working = self.working_receivers
        key = ("locators", working.tobytes())
        found: tuple[FrameLocator, ...] | None = self._by_receivers.get(key)
        if found is None:
            recording = self.recording
            found = tuple(
                FrameLocator(transmitter_m, recording.receivers_m, self.locate_options, working)
                for transmitter_m in recording.transmitters_m
            )
            self._by_receivers[key] = found
        return found

    @property
    def one_call(self) -> tuple[MatchedEstimator, FrameLocator, LocateKernelArguments] | None:
        """What :func:`samples_results_batch` takes to find frames' echoes and objects in one
        compiled call: the matched estimator, the locator and its kernel's arguments. None
        where that path does not apply and the stages run one after the other: another
        estimator, a calibration (it corrects the echoes between the stages), several
        transmitters, a clipped channel re-read (:func:`echoloc.tof.channel_health.reread_clipped`
        works between the stages), reflector classes, or a locator without a compiled path."""
        if (
            self.calibration is not None
            or len(self.recording.transmitters_m) != 1
            or self.health.reread
            or self.locate_options.reflector_classes
        ):
            return None
        estimator = self.estimator
        if not isinstance(estimator, MatchedEstimator):
            return None
        key = ("one_call", self.working_receivers.tobytes())
        if key not in self._by_receivers:
            locator = self.locators[0]
            arguments = locator.kernel_arguments(self.speed_of_sound_m_s)
            self._by_receivers[key] = None if arguments is None else (estimator, locator, arguments)
        found: tuple[MatchedEstimator, FrameLocator, LocateKernelArguments] | None = self._by_receivers[key]
        return found


def prepare(
    recording: Recording,
    *,
    estimator: str = "matched",
    echo_options: EchoOptions | None = None,
    locate_options: LocateOptions | None = None,
    speed_of_sound_m_s: float | None = None,
    calibration: Calibration | None = None,
    conditioning: Conditioning | None = None,
    check_channels: bool = True,
) -> Chain:
    """Precompute the chain for ``recording``; options not given take recording-based defaults.

    With a ``calibration`` its speed of sound is used and its receiver delays are
    taken off every echo (an explicit ``speed_of_sound_m_s`` still wins); without
    ``echo_options``, its measured detection threshold is the envelope-peak estimator's.
    ``conditioning`` (:mod:`echoloc.tof.conditioning`; default: subtract the background
    and undo the receiver gain when the recording has them) is applied to every
    frame; a blind zone in seconds raises ``blanking_s`` to it. ``check_channels``
    (default): degraded receiver channels are found, warned about (a
    :class:`echoloc.tof.channel_health.ChannelWarning` naming the recording and the
    receiver), corrected or left out of localisation (:func:`channel_watch`); with the
    matched filter, a clipped channel is kept and its echoes near clipped samples re-read
    (:func:`echoloc.tof.channel_health.reread_clipped`).
    """
    conditioning = conditioning or Conditioning()
    estimator = resolve_estimator(estimator, recording)
    if echo_options is None:
        calibrated_db = None if calibration is None else calibration.threshold_db
        echo_options = EchoOptions(threshold_db=default_threshold_db(estimator, calibrated_db))
    if (
        calibration is not None
        and calibration.echo_shape is not None
        and echo_options.template is None
        and estimator == "envelope-peak"
    ):
        # The echo shape learnt at calibration times every peak (its arrival-to-peak delay).
        echo_options = replace(echo_options, template=calibration.echo_shape)
    echo_options = effective_options(echo_options, conditioning)
    if calibration is not None and len(calibration.receiver_delays_s) != recording.n_receivers:
        raise EchoLocError(
            f"{recording.source}: the calibration has delays for {len(calibration.receiver_delays_s)} "
            f"receivers, the recording has {recording.n_receivers}"
        )
    frame_s = recording.n_samples / recording.sample_rate_hz
    if calibration is not None and any(abs(d) >= frame_s for d in calibration.receiver_delays_s):
        receiver, delay = max(enumerate(calibration.receiver_delays_s), key=lambda rd: abs(rd[1]))
        raise EchoLocError(
            f"{recording.source}: the calibration delays receiver {receiver} by {delay:g} s, "
            f"more than a whole frame ({frame_s:g} s): are its delays in seconds?"
        )
    if calibration is not None and speed_of_sound_m_s is None:
        speed_of_sound_m_s = calibration.speed_of_sound_m_s
    c = speed_of_sound_m_s or recording_speed_of_sound_m_s(recording)
    if not PLAUSIBLE_SPEED_OF_SOUND_M_S[0] <= c <= PLAUSIBLE_SPEED_OF_SOUND_M_S[1]:
        warnings.warn(
            f"{recording.source}: a speed of sound of {c:g} m/s is far from any gas's "
            "(air: about 331 m/s at 0 °C, 386 at 100 °C): is it in m/s?",
            LocateWarning,
            stacklevel=2,
        )
    run_estimator = blinded(
        lambda options: prepare_estimator(recording, options, estimator),
        recording,
        conditioning,
        echo_options,
    )
    if locate_options is None:
        locate_options = LocateOptions()
        if recording.waveform is not None and recording.signal_kind == "rf":
            mf = MatchedFilter(
                np.asarray(recording.waveform, float), recording.n_samples, recording.sample_rate_hz
            )
            resolution_m = mf.mainlobe_lags / mf.lag_rate_hz * c
        else:
            resolution_m = None
        axes = recording.transmitter_axes
        boresight = (
            (0.0, 0.0, 1.0) if axes is None else tuple(float(v) for v in axes[0] / np.linalg.norm(axes[0]))
        )
        locate_options = replace(
            locate_options,
            resolution_m=resolution_m,
            carrier_hz=recording.carrier_hz if estimator == "matched" else None,
            window_m=(echo_options.blanking_s * c, recording.n_samples / recording.sample_rate_hz * c),
            boresight=boresight,
            transmitter_axes=recording.transmitter_axes,
            receiver_axes=recording.receiver_axes,
            field_of_view_deg=90.0 if recording.field_of_view_deg is None else recording.field_of_view_deg,
        )
        if estimator == "envelope-peak":
            # A ToF chip's channel misses weak echoes (the monostatic one far off axis): a
            # 3-of-4 object beats none.
            locate_options = replace(locate_options, excuse_one_channel=True)
        if calibration is not None and calibration.path_sigma_m is not None:
            # The path error measured on the rig's own targets, not the a-priori 0.5 mm.
            locate_options = replace(locate_options, path_sigma_m=calibration.path_sigma_m)
    # Dead receivers (the reader warns about them) are left out of localisation.
    usable = np.ones(recording.n_receivers, dtype=bool)
    dead = dead_receivers(recording)
    usable[dead] = False
    watch = None
    if check_channels:
        watch = channel_watch(
            recording,
            locate_options.min_receivers,
            dead,
            reread_clipped=isinstance(run_estimator, MatchedEstimator),
        )
        usable &= ~watch.health.excluded_mask(recording.n_receivers)
    return Chain(
        recording, run_estimator, echo_options, locate_options, c, usable, calibration, conditioning, watch
    )


def channel_watch(
    recording: Recording, min_receivers: int, dead: Sequence[int] = (), *, reread_clipped: bool = False
) -> ChannelWatch:
    """The channel check of a chain (:mod:`echoloc.tof.channel_health`), warning about what it finds.

    A recording with frames is assessed now, on up to :data:`ASSESS_FRAMES` of them spread
    over it (its ``dead`` receivers, which the reader warned about, are not warned about
    again); a session header (no frames) is assessed on its first frames as they come.
    Rail samples in a run that starts with the frame (a saturated ring-down) within a
    quarter pulse of each other are not clipping. ``reread_clipped``: clipped channels are
    kept and re-read rather than left out (the chain's estimator is the matched filter).
    """
    n_rx = recording.n_receivers
    pulse = 0 if recording.waveform is None else len(recording.waveform)
    ring_down = max(1, pulse // 4)
    watch = functools.partial(
        ChannelWatch,
        recording.source,
        recording.signal_kind,
        n_rx,
        min_receivers=min_receivers,
        ring_down_samples=ring_down,
        reread_clipped=reread_clipped,
    )
    if recording.n_frames == 0:  # a session header: assessed on its first frames as they come
        return watch()
    health = assess_channels(
        np.asarray(recording.frames)[assessed_frames(recording.n_frames)],
        recording.signal_kind,
        min_receivers=min_receivers,
        ring_down_samples=ring_down,
        reread_clipped=reread_clipped,
    )
    known = ChannelHealth(tuple(("dead",) if rx in dead else () for rx in range(n_rx)))
    warn_health(health, recording.source, known, stacklevel=4)
    return watch(health=health, settled=True)


def check_locatable(chain: Chain) -> None:
    """Raise when too few receivers work to locate anything."""
    working = int(chain.working_receivers.sum())
    if working < chain.locate_options.min_receivers:
        raise EchoLocError(
            f"{chain.recording.source}: only {working} working receiver(s), "
            f"at least {chain.locate_options.min_receivers} are needed to locate"
        )
    positions = np.asarray(chain.recording.receivers_m, dtype=float)[chain.working_receivers]
    transmitters = np.asarray(chain.recording.transmitters_m, dtype=float)
    if np.all(positions == positions[0]) and np.all(transmitters == transmitters[0]):
        raise EchoLocError(
            f"{chain.recording.source}: every working receiver is at {positions[0].tolist()} m: "
            "their ellipsoids share their foci, so no position can be located"
        )


def frame_echoes(chain: Chain, index: int) -> FrameEchoes:
    """Echoes of frame ``index``."""
    recording = chain.recording
    return samples_echoes(chain, recording.frames[index], index, frame_time_s(recording, index))


def frame_objects(chain: Chain, echoes: FrameEchoes) -> FrameObjects:
    """Objects of one frame from its echoes."""
    recording = chain.recording
    tx_index = 0 if recording.frame_transmitter is None else int(recording.frame_transmitter[echoes.frame])
    return transmitter_objects(chain, echoes, tx_index)


def combines_transmitters(chain: Chain) -> bool:
    """Whether frames of different transmitters are located together (sequential firing of several)."""
    return recording_combines_transmitters(chain.recording, chain.recording.frame_transmitter)


def recording_combines_transmitters(header: Recording, frame_transmitter: NDArray[np.int64] | None) -> bool:
    """:func:`combines_transmitters` of a recording's ``header`` whose frames' transmitters are
    ``frame_transmitter`` (read apart from the header when a file is read in parts)."""
    several = len(header.transmitters_m) > 1
    return several and header.firing != "simultaneous" and frame_transmitter is not None


RUN_BATCH_FRAMES = 32
"""Frames :func:`run` hands the estimator in one call: the matched filter's FFTs and compiled
loops then take 128 channels at once, in less time a frame than one frame a call
(`benchmarks/bench_echoes.py` measures it), for 2.5 MB of samples at 4 x 2400."""


def run(
    chain: Chain, frames: Iterable[int] | None = None, *, batch_frames: int = RUN_BATCH_FRAMES
) -> Iterator[tuple[FrameEchoes, FrameObjects]]:
    """Echoes and objects of every frame (or of ``frames``), in order.

    Echoes and objects are found ``batch_frames`` frames at a time
    (:func:`samples_results_batch`; with transmitters combined, the echoes by
    :func:`samples_echoes_batch`): the same answers as one at a time. With several
    transmitters fired in turn, each frame
    is located together with the latest frame of every other transmitter
    (:func:`echoloc.localise.locate.combine_frames`): n_tx times the ellipsoids per object once
    every transmitter has fired.
    """
    if batch_frames < 1:
        raise EchoLocError(f"batch_frames must be >= 1, got {batch_frames}")
    indices = iter(range(chain.recording.n_frames) if frames is None else frames)
    recording = chain.recording
    combine = combines_transmitters(chain)
    latest: dict[int, FrameEchoes] = {}
    fired = recording.frame_transmitter
    while block := list(itertools.islice(indices, batch_frames)):
        samples = [recording.frames[index] for index in block]
        times = [frame_time_s(recording, index) for index in block]
        transmitters = [0 if fired is None else int(fired[index]) for index in block]
        if not combine:
            try:
                results = samples_results_batch(chain, samples, block, times, transmitters)
            except EchoLocError:
                # One frame of the block is refused: the frames before it still come out, one
                # at a time, and the error is raised at that frame.
                for sample, index, time_s, transmitter in zip(
                    samples, block, times, transmitters, strict=True
                ):
                    yield samples_results_batch(chain, [sample], [index], [time_s], [transmitter])[0]
            else:
                yield from results
            continue
        found: Iterable[FrameEchoes]
        try:
            found = samples_echoes_batch(chain, samples, block, times)
        except EchoLocError:
            found = (samples_echoes(chain, *frame) for frame in zip(samples, block, times, strict=True))
        for echoes, transmitter in zip(found, transmitters, strict=True):
            latest, objects = combine_latest(chain, latest, echoes, transmitter)
            yield echoes, objects


def find_echoes(
    recording: Recording,
    *,
    estimator: str = "matched",
    options: EchoOptions | None = None,
    frames: Iterable[int] | None = None,
) -> list[FrameEchoes]:
    """Echoes of every frame (or of ``frames``) of a recording."""
    chain = prepare(recording, estimator=estimator, echo_options=options)
    indices = range(recording.n_frames) if frames is None else frames
    return [frame_echoes(chain, i) for i in indices]


# ----------------------------------------------------------------------------- streaming
# The same chain, fed samples instead of a recording's frame index (echoloc.realtime.stream).


def samples_echoes(
    chain: Chain,
    samples: NDArray[np.floating] | NDArray[np.complexfloating],
    index: int,
    time_s: float,
) -> FrameEchoes:
    """Echoes of one frame given by its samples (n_rx, n_samples), as :func:`frame_echoes` finds them.

    ``index`` is the frame's number (it indexes a per-frame background of
    ``chain.recording`` when there is one); ``time_s`` its start time.
    """
    return samples_echoes_batch(chain, [samples], [index], [time_s])[0]


def samples_echoes_batch(
    chain: Chain,
    samples: Sequence[NDArray[np.floating] | NDArray[np.complexfloating]],
    indices: Sequence[int],
    times_s: Sequence[float],
) -> list[FrameEchoes]:
    """:func:`samples_echoes` of several frames, in one call of the estimator where it takes
    batches (:func:`echoloc.tof.estimators.estimate_frames`): the same echoes, more frames a second."""
    raw, frames = _raw_and_conditioned(chain, samples, indices)
    return _echoes_of_conditioned(chain, raw, frames, indices, times_s)[0]


def _echoes_of_conditioned(
    chain: Chain,
    raw: NDArray[Any] | None,
    frames: NDArray[Any],
    indices: Sequence[int],
    times_s: Sequence[float],
) -> tuple[list[FrameEchoes], NDArray[np.bool_] | None]:
    """:func:`samples_echoes_batch` of frames conditioned (``frames``) from ``raw`` (None: the
    frames differ in shape, nothing is re-read), and the samples of channels it re-read that
    are clipped (:func:`echoloc.tof.channel_health.clipped_samples`; None: none). Clipped
    channels the channel check keeps are re-read near their clipped samples
    (:func:`echoloc.tof.channel_health.reread_clipped`)."""
    channels_of_frames: Sequence[Sequence[Any]] = estimate_frames(chain.estimator, frames)
    health = chain.health
    estimator = chain.estimator
    clipped = None
    if health.reread and raw is not None and isinstance(estimator, MatchedEstimator):
        clipped = clipped_samples(raw, health)
        if clipped.shape == np.shape(frames) and clipped.any():
            channels_of_frames = reread_clipped(
                frames, clipped, channels_of_frames, estimator.mf, estimator.options
            )
        else:
            clipped = None
    found = [
        _frame_echoes(chain, index, time_s, channels)
        for channels, index, time_s in zip(channels_of_frames, indices, times_s, strict=True)
    ]
    return found, clipped


def learn_chain_echo_shape(
    chain: Chain, frames: Sequence[int], arrival: str = "truth", name: str | None = None
) -> Template:
    """The echo shape of ``frames`` of the chain's recording, conditioned as the chain does
    (:func:`echoloc.tof.envelope_peaks.learn_echo_shape`), aligned on ``arrival``: ``"truth"``,
    the known targets' paths (the report's BALL template), or ``"peaks"``, strong isolated
    echoes (their peaks). Errors name the recording."""
    recording = chain.recording
    if arrival not in ("truth", "peaks"):
        raise EchoLocError(
            f"{recording.source}: the arrival to align a learnt echo shape on must be 'truth' or "
            f"'peaks', got {arrival!r}"
        )
    indices = list(frames)
    conditioned = _raw_and_conditioned(chain, [recording.frames[i] for i in indices], indices)[1]
    if arrival == "truth":
        arrivals = arrivals_from_truth(recording, indices, chain.speed_of_sound_m_s)
    else:
        detector = prepare_peak_detector(recording, None)
        arrivals = arrivals_from_peaks(conditioned, detector, chain.echo_options)
    try:
        return learn_echo_shape(
            conditioned, arrivals, recording.sample_rate_hz, name=name or f"learnt-{arrival}"
        )
    except EchoLocError as error:
        raise EchoLocError(f"{recording.source}: {error}") from None


def _conditioned(
    chain: Chain,
    samples: Sequence[NDArray[np.floating] | NDArray[np.complexfloating]],
    indices: Sequence[int],
) -> NDArray[Any]:
    """The frames' samples conditioned, stacked (:func:`_raw_and_conditioned`)."""
    return _raw_and_conditioned(chain, samples, indices)[1]


def _raw_and_conditioned(
    chain: Chain,
    samples: Sequence[NDArray[np.floating] | NDArray[np.complexfloating]],
    indices: Sequence[int],
) -> tuple[NDArray[Any] | None, NDArray[Any]]:
    """The frames' samples as they came, stacked (None without a channel check, or when they
    differ in shape), and conditioned (:func:`echoloc.tof.conditioning.condition_frame`),
    stacked (n_frames, n_rx, n_samples)."""
    recording = chain.recording
    watch = chain.channel_watch
    raw = None
    if watch is not None and len(samples):
        # Degraded channels (echoloc.tof.channel_health): a live session's first frames are
        # assessed as they come; DC offsets and non-finite samples are corrected.
        try:
            raw = np.stack([np.asarray(frame) for frame in samples])
        except ValueError:
            pass  # frames of different shapes: refused below, frame by frame
        else:
            samples = list(correct_frames(raw, watch.observe(raw)))
    conditioned = [
        condition_frame(frame, recording, chain.conditioning, index)
        for frame, index in zip(samples, indices, strict=True)
    ]
    return raw, np.asarray(conditioned[0])[None] if len(conditioned) == 1 else np.stack(conditioned)


def _frame_echoes(chain: Chain, index: int, time_s: float, channels: Sequence[Any]) -> FrameEchoes:
    """A frame's echoes from its channels, the chain's calibration taken off."""
    echoes = FrameEchoes(index, time_s, chain.speed_of_sound_m_s, tuple(channels))
    if chain.calibration is not None:
        echoes = replace(
            apply_calibration(echoes, chain.calibration), speed_of_sound_m_s=chain.speed_of_sound_m_s
        )
    return echoes


def transmitter_objects(chain: Chain, echoes: FrameEchoes, transmitter: int) -> FrameObjects:
    """Objects of one frame fired by ``transmitter``, as :func:`frame_objects` finds them
    (:func:`echoloc.localise.locate.locate_frame`, its set-up done once: :attr:`Chain.locators`),
    with reflector classes when the chain's options ask for them."""
    locator = chain.locators[transmitter]
    if not chain.locate_options.reflector_classes:
        return locator(echoes)
    recording = chain.recording
    return locate_with_classes(
        [(transmitter, echoes)],
        recording.transmitters_m,
        recording.receivers_m,
        chain.locate_options,
        chain.working_receivers,
        lambda frames: locator(frames[0][1]),
    )


def samples_results_batch(
    chain: Chain,
    samples: Sequence[NDArray[np.floating] | NDArray[np.complexfloating]],
    indices: Sequence[int],
    times_s: Sequence[float],
    transmitters: Sequence[int],
) -> list[tuple[FrameEchoes, FrameObjects]]:
    """Echoes and objects of frames each located alone (no transmitters combined): the
    answers of :func:`samples_echoes_batch` then :func:`transmitter_objects`.

    Where the chain allows (:attr:`Chain.one_call`), both stages run in one compiled call
    (:func:`echoloc._chain_kernels.echoes_and_objects`): a stream's frame then costs less
    (`benchmarks/bench_chain_kernel.py` measures it). Frames with a channel left to CLEAN, or
    with tied weights, finish as the stages do. Frames of another channel count than the
    recording's receivers are refused there (the kernel trusts its shapes).
    """
    raw, frames = _raw_and_conditioned(chain, samples, indices)
    one_call = chain.one_call  # after the channel check has seen these frames
    if one_call is not None:
        n_rx = len(one_call[1].receivers_m)
        if frames.shape[1] != n_rx:
            raise EchoLocError(f"frames of {frames.shape[1]} channels for a chain of {n_rx} receivers")
        return _one_call_results(chain, one_call, frames, indices, times_s)
    found, clipped = _echoes_of_conditioned(chain, raw, frames, indices, times_s)
    results = []
    for f, (echoes, transmitter) in enumerate(zip(found, transmitters, strict=True)):
        objects = transmitter_objects(chain, echoes, transmitter)
        if clipped is not None and clipped[f].any():
            objects = _excusing_clipped(chain, echoes, objects, transmitter, clipped[f])
        results.append((echoes, objects))
    return results


def _excusing_clipped(
    chain: Chain, echoes: FrameEchoes, objects: FrameObjects, transmitter: int, clipped: NDArray[np.bool_]
) -> FrameObjects:
    """``objects`` and those a re-read clipped channel's lost echoes hid.

    Where a strong clipped echo overlaps weaker ones, the clipped channel can lose an echo
    (its correlation shows one peak for two): that object then lacks one channel and the
    association, which needs every channel's echo, drops it. So the echoes no object uses
    are associated again with that channel excused, and each object found is kept when its
    predicted echo on the excused channel touches clipped samples
    (:func:`echoloc.tof.channel_health.touches_clipping`), where the channel may have lost it;
    elsewhere the channel would have shown its echo, and the object is a ghost. ``clipped``
    (n_rx, n_samples): the frame's clipped samples of the re-read channels.
    """
    estimator = chain.estimator
    if not isinstance(estimator, MatchedEstimator):
        return objects
    recording = chain.recording
    used: list[set[int]] = [set() for _ in echoes.channels]
    for found in objects.objects:
        for rx, index in zip(found.receivers, found.echo_indices, strict=True):
            used[rx].add(index)
    added: list[LocatedObject] = []
    for rx in np.flatnonzero(clipped.any(axis=1)).tolist():
        working = chain.working_receivers.copy()
        if rx >= len(working) or not working[rx]:
            continue
        working[rx] = False
        kept = [
            np.array([c != rx and i not in used[c] for i in range(len(ch.tof_s))], dtype=bool)
            for c, ch in enumerate(echoes.channels)
        ]
        if any(not k.any() for c, k in enumerate(kept) if working[c]):
            continue  # a working channel has no echo left: nothing more to find
        left = replace(
            echoes,
            channels=tuple(
                ChannelEchoes(ch.tof_s[k], ch.amplitude[k], ch.snr_db[k])
                for ch, k in zip(echoes.channels, kept, strict=True)
            ),
        )
        key = ("excusing", transmitter, working.tobytes())
        locator = chain._by_receivers.get(key)
        if locator is None:
            locator = chain._by_receivers[key] = FrameLocator(
                recording.transmitters_m[transmitter], recording.receivers_m, chain.locate_options, working
            )
        hidden = locator(left).objects
        if not hidden:
            continue
        positions = np.array([o.position_m for o in hidden])
        paths_m = model_paths_m(recording.transmitters_m[transmitter], recording.receivers_m, positions)[
            :, rx
        ]
        lost = touches_clipping(clipped[rx], paths_m / echoes.speed_of_sound_m_s, estimator.mf)
        for found, keep in zip(hidden, lost.tolist(), strict=True):
            if keep:
                # Indices into the channels' own echoes, not the ones left.
                indices = tuple(
                    int(np.flatnonzero(kept[c])[i])
                    for c, i in zip(found.receivers, found.echo_indices, strict=True)
                )
                added.append(replace(found, echo_indices=indices))
                for c, i in zip(found.receivers, indices, strict=True):
                    used[c].add(i)
    if not added:
        return objects
    if chain.locate_options.reflector_classes:
        added = classify_points(
            added,
            [(transmitter, echoes)],
            recording.transmitters_m,
            recording.receivers_m,
            chain.locate_options,
        )
    return replace(objects, objects=objects.objects + tuple(added))


def _one_call_results(
    chain: Chain,
    one_call: tuple[MatchedEstimator, FrameLocator, LocateKernelArguments],
    frames: NDArray[Any],
    indices: Sequence[int],
    times_s: Sequence[float],
) -> list[tuple[FrameEchoes, FrameObjects]]:
    """:func:`samples_results_batch` of conditioned ``frames`` (n_frames, n_rx, n_samples) in
    one compiled call, CLEAN and the locator finishing the frames it leaves to them."""
    from echoloc import _chain_kernels as kernels  # numba: imported (and compiled) on first use

    estimator, locator, locate_arguments = one_call
    n_rx = frames.shape[1]
    options = estimator.options
    echo_arguments = echo_kernel_arguments(frames, estimator.mf, options, options.threads)
    status, found_rows, echo_use, positions, covariances, chi2 = run_kernel(
        echo_arguments.parts, kernels.echoes_and_objects, echo_arguments, n_rx, locate_arguments
    )
    channels = with_clean(frames, kernel_channels(echo_arguments), estimator.mf, options)
    statuses: list[int] = status.tolist()
    rows: list[int] = found_rows.tolist()
    results = []
    for f, (index, time_s) in enumerate(zip(indices, times_s, strict=True)):
        echoes = _frame_echoes(chain, index, time_s, channels[f])
        objects = None
        if statuses[f] != kernels.LEFT_TO_CLEAN:
            own = slice(rows[f], rows[f + 1])
            objects = locator.kernel_objects(
                statuses[f], echo_use[own], positions[own], covariances[own], chi2[own], n_rx
            )
        located = locator(echoes) if objects is None else FrameObjects(index, time_s, tuple(objects))
        results.append((echoes, located))
    return results


def combine_latest(
    chain: Chain, latest: dict[int, FrameEchoes], echoes: FrameEchoes, transmitter: int
) -> tuple[dict[int, FrameEchoes], FrameObjects]:
    """One step of :func:`run` with transmitters fired in turn: the new ``latest`` and the objects.

    ``latest`` maps a transmitter to its most recent echoes; only those of the last
    n_tx frame numbers are kept, so a transmitter that stopped firing, or frames
    lost on the way, never lend old echoes.
    """
    recording = chain.recording
    n_tx = len(recording.transmitters_m)
    kept = {t: e for t, e in {**latest, transmitter: echoes}.items() if 0 <= echoes.frame - e.frame < n_tx}

    def located(frames: list[tuple[int, FrameEchoes]]) -> FrameObjects:
        return combine_frames(
            frames,
            recording.transmitters_m,
            recording.receivers_m,
            chain.locate_options,
            chain.working_receivers,
        )

    frames = sorted(kept.items())
    if not chain.locate_options.reflector_classes:
        return kept, located(frames)
    objects = locate_with_classes(
        frames,
        recording.transmitters_m,
        recording.receivers_m,
        chain.locate_options,
        chain.working_receivers,
        located,
    )
    return kept, objects
