"""The per-frame chain, recording -> echoes -> objects, with what it precomputes once.

:func:`prepare` turns a recording and the user's options into a :class:`Chain`: the
estimator with its template spectra and tables, the speed of sound and the
localisation options derived from the recording (pulse resolution, carrier,
observable window, receivers to use). :func:`run` then maps frames to results.
"""

from __future__ import annotations

import itertools
import warnings
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

from echoloc.air import speed_of_sound_m_s
from echoloc.calibrate import Calibration, apply_calibration
from echoloc.conditioning import Conditioning, blinded, condition_frame, effective_options
from echoloc.echoes import (
    EchoOptions,
    FrameEchoes,
    MatchedFilter,
    echo_kernel_arguments,
    frame_time_s,
    kernel_channels,
    run_kernel,
    with_clean,
)
from echoloc.envelope_peaks import (
    arrivals_from_peaks,
    arrivals_from_truth,
    learn_echo_shape,
    prepare_peak_detector,
)
from echoloc.errors import EchoLocError
from echoloc.estimators import (
    Estimator,
    MatchedEstimator,
    default_threshold_db,
    estimate_frames,
    prepare_estimator,
    resolve_estimator,
)
from echoloc.locate import FrameLocator, FrameObjects, LocateOptions, LocateWarning, combine_frames
from echoloc.recording import Recording, dead_receivers
from echoloc.templates import Template

PLAUSIBLE_SPEED_OF_SOUND_M_S = (100.0, 2000.0)
"""Speeds of sound (m/s) :func:`prepare` takes without a warning: every gas a sensor could
work in lies inside (air 331-386 m/s from 0 to 100 °C, CO2 267, helium 1007 at 20 °C); a
value outside is most likely in other units (0.343 m/ms, 34 320 cm/s)."""


def recording_speed_of_sound_m_s(recording: Recording) -> float:
    """Speed of sound for a recording (FORMATS.md): the stored value, else from the air state."""
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

    @cached_property
    def locators(self) -> tuple[FrameLocator, ...]:
        """A :class:`echoloc.locate.FrameLocator` per transmitter: the set-up its frames share,
        looked up once for the whole recording or stream."""
        recording = self.recording
        return tuple(
            FrameLocator(transmitter_m, recording.receivers_m, self.locate_options, self.usable_receivers)
            for transmitter_m in recording.transmitters_m
        )

    @cached_property
    def one_call(self) -> tuple[MatchedEstimator, FrameLocator, tuple[Any, ...]] | None:
        """What :func:`samples_results_batch` takes to find frames' echoes and objects in one
        compiled call: the matched estimator, the locator and its kernel's arguments. None
        where that path does not apply and the stages run one after the other: another
        estimator, a calibration (it corrects the echoes between the stages), several
        transmitters, or a locator without a compiled path."""
        if self.calibration is not None or len(self.recording.transmitters_m) != 1:
            return None
        estimator = self.estimator
        if not isinstance(estimator, MatchedEstimator):
            return None
        locator = self.locators[0]
        arguments = locator.kernel_arguments(self.speed_of_sound_m_s)
        return None if arguments is None else (estimator, locator, arguments)


def prepare(
    recording: Recording,
    *,
    estimator: str = "matched",
    echo_options: EchoOptions | None = None,
    locate_options: LocateOptions | None = None,
    speed_of_sound_m_s: float | None = None,
    calibration: Calibration | None = None,
    conditioning: Conditioning | None = None,
) -> Chain:
    """Precompute the chain for ``recording``; options not given take recording-based defaults.

    With a ``calibration`` its speed of sound is used and its receiver delays are
    taken off every echo (an explicit ``speed_of_sound_m_s`` still wins).
    ``conditioning`` (:mod:`echoloc.conditioning`; default: subtract the background
    and undo the receiver gain when the recording has them) is applied to every
    frame; a blind zone in seconds raises ``blanking_s`` to it.
    """
    conditioning = conditioning or Conditioning()
    estimator = resolve_estimator(estimator, recording)
    echo_options = echo_options or EchoOptions(threshold_db=default_threshold_db(estimator))
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
    usable[dead_receivers(recording)] = False
    return Chain(recording, run_estimator, echo_options, locate_options, c, usable, calibration, conditioning)


def check_locatable(chain: Chain) -> None:
    """Raise when too few receivers work to locate anything."""
    working = int(chain.usable_receivers.sum())
    if working < chain.locate_options.min_receivers:
        raise EchoLocError(
            f"{chain.recording.source}: only {working} working receiver(s), "
            f"at least {chain.locate_options.min_receivers} are needed to locate"
        )
    positions = np.asarray(chain.recording.receivers_m, dtype=float)[chain.usable_receivers]
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
    recording = chain.recording
    return (
        len(recording.transmitters_m) > 1
        and recording.firing != "simultaneous"
        and recording.frame_transmitter is not None
    )


RUN_BATCH_FRAMES = 32
"""Frames :func:`run` hands the estimator in one call: the matched filter's FFTs and compiled
loops then take 128 channels at once, a quarter less time a frame than one frame a call
(`benchmarks/bench_echoes.py`), for 2.5 MB of samples at 4 x 2400."""


def run(
    chain: Chain, frames: Iterable[int] | None = None, *, batch_frames: int = RUN_BATCH_FRAMES
) -> Iterator[tuple[FrameEchoes, FrameObjects]]:
    """Echoes and objects of every frame (or of ``frames``), in order.

    Echoes and objects are found ``batch_frames`` frames at a time
    (:func:`samples_results_batch`; with transmitters combined, the echoes by
    :func:`samples_echoes_batch`): the same answers as one at a time. With several
    transmitters fired in turn, each frame
    is located together with the latest frame of every other transmitter
    (:func:`echoloc.locate.combine_frames`): n_tx times the ellipsoids per object once
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
# The same chain, fed samples instead of a recording's frame index (echoloc.stream).


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
    batches (:func:`echoloc.estimators.estimate_frames`): the same echoes, more frames a second."""
    channels_of_frames = estimate_frames(chain.estimator, _conditioned(chain, samples, indices))
    return [
        _frame_echoes(chain, index, time_s, channels)
        for channels, index, time_s in zip(channels_of_frames, indices, times_s, strict=True)
    ]


def learn_chain_echo_shape(
    chain: Chain, frames: Sequence[int], arrival: str = "truth", name: str | None = None
) -> Template:
    """The echo shape of ``frames`` of the chain's recording, conditioned as the chain does
    (:func:`echoloc.envelope_peaks.learn_echo_shape`), aligned on ``arrival``: ``"truth"``,
    the known targets' paths (the report's BALL template), or ``"peaks"``, strong isolated
    echoes (their peaks). Errors name the recording."""
    recording = chain.recording
    if arrival not in ("truth", "peaks"):
        raise EchoLocError(
            f"{recording.source}: the arrival to align a learnt echo shape on must be 'truth' or "
            f"'peaks', got {arrival!r}"
        )
    indices = list(frames)
    conditioned = _conditioned(chain, [recording.frames[i] for i in indices], indices)
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
    """The frames' samples conditioned (:func:`echoloc.conditioning.condition_frame`), stacked
    (n_frames, n_rx, n_samples)."""
    recording = chain.recording
    conditioned = [
        condition_frame(frame, recording, chain.conditioning, index)
        for frame, index in zip(samples, indices, strict=True)
    ]
    return np.asarray(conditioned[0])[None] if len(conditioned) == 1 else np.stack(conditioned)


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
    (:func:`echoloc.locate.locate_frame`, its set-up done once: :attr:`Chain.locators`)."""
    return chain.locators[transmitter](echoes)


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
    (:func:`echoloc._chain_kernels.echoes_and_objects`): a stream's frame then costs 3-8 %
    less (`benchmarks/bench_chain_kernel.py`). Frames with a channel left to CLEAN, or with
    tied weights, finish as the stages do. Frames of another channel count than the
    recording's receivers are refused there (the kernel trusts its shapes).
    """
    one_call = chain.one_call
    if one_call is not None:
        frames = _conditioned(chain, samples, indices)
        n_rx = len(one_call[1].receivers_m)
        if frames.shape[1] != n_rx:
            raise EchoLocError(f"frames of {frames.shape[1]} channels for a chain of {n_rx} receivers")
        return _one_call_results(chain, one_call, frames, indices, times_s)
    found = samples_echoes_batch(chain, samples, indices, times_s)
    return [
        (echoes, transmitter_objects(chain, echoes, transmitter))
        for echoes, transmitter in zip(found, transmitters, strict=True)
    ]


def _one_call_results(
    chain: Chain,
    one_call: tuple[MatchedEstimator, FrameLocator, tuple[Any, ...]],
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
        echo_arguments[5], kernels.echoes_and_objects, echo_arguments, n_rx, locate_arguments
    )  # [5]: the echoes' parallel parts
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
    objects = combine_frames(
        sorted(kept.items()),
        recording.transmitters_m,
        recording.receivers_m,
        chain.locate_options,
        chain.usable_receivers,
    )
    return kept, objects
