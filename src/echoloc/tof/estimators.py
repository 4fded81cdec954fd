"""The registry of time-of-flight estimators: every estimator, by name, in one place.

Tests and studies iterate :data:`ESTIMATORS`, so an estimator enrolled here is
checked on clean data against its documented tolerance and measured against the
Cramér-Rao bound without further wiring.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
from numpy.typing import NDArray

from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording
from echoloc.tof.echoes import (
    MATCHED_DECIMATION,
    ChannelEchoes,
    EchoOptions,
    MatchedFilter,
    matched_filter_batch,
    matched_filter_echoes,
)
from echoloc.tof.envelope_fit import envelope_fit_echoes, envelope_fitter
from echoloc.tof.envelope_peaks import peak_echoes, prepare_peak_detector
from echoloc.tof.envelopes import (
    EnvelopeOptions,
    ThresholdDetector,
    energy_echoes,
    envelope_zero_echoes,
    leading_edge_echoes,
    threshold_echoes,
)
from echoloc.tof.templates import sent_template

Estimator = Callable[[NDArray[np.floating]], list[ChannelEchoes]]
"""A prepared estimator: one frame (n_rx, n_samples) -> echoes per receiver. One that can
take many frames in one call too is a :class:`BatchEstimator` (:func:`estimate_frames`)."""


@dataclass(frozen=True, eq=False)
class MatchedEstimator:
    """The prepared matched filter: one frame per call, or a batch (:meth:`batch`), with the
    same answers either way."""

    mf: MatchedFilter
    options: EchoOptions

    def __call__(self, frame: NDArray[np.floating]) -> list[ChannelEchoes]:
        return matched_filter_echoes(frame, self.mf, self.options)

    def batch(self, frames: NDArray[np.floating]) -> list[list[ChannelEchoes]]:
        """Echoes of frames (n_frames, n_rx, n_samples): :func:`echoloc.tof.echoes.matched_filter_batch`,
        whose FFTs and compiled loops take every channel of the batch at once."""
        return matched_filter_batch(frames, self.mf, self.options)


@runtime_checkable
class BatchEstimator(Protocol):
    """An :data:`Estimator` that also takes many frames (n_frames, n_rx, n_samples) in one call."""

    def __call__(self, frame: NDArray[np.floating]) -> list[ChannelEchoes]: ...

    def batch(self, frames: NDArray[np.floating]) -> list[list[ChannelEchoes]]: ...


def estimate_frames(estimator: Estimator, frames: NDArray[np.floating]) -> list[list[ChannelEchoes]]:
    """Echoes of frames (n_frames, n_rx, n_samples): in one call where the estimator takes
    batches (a :class:`BatchEstimator` such as :class:`MatchedEstimator`), else frame by
    frame; the same answers either way."""
    if len(frames) > 1 and isinstance(estimator, BatchEstimator):
        return estimator.batch(frames)
    return [estimator(frame) for frame in frames]


def _prepare_matched(recording: Recording, options: EchoOptions) -> Estimator:
    if recording.signal_kind != "rf":
        raise EchoLocError(
            f"{recording.source}: the matched estimator needs signal_kind 'rf', "
            f"this recording is {recording.signal_kind!r} (use --estimator threshold)"
        )
    template = options.template or sent_template(recording)
    if not np.isclose(template.sample_rate_hz, recording.sample_rate_hz, rtol=1e-9):
        raise EchoLocError(
            f"{recording.source}: the {template.name} template is sampled at {template.sample_rate_hz:g} Hz, "
            f"the recording at {recording.sample_rate_hz:g} Hz"
        )
    mf = MatchedFilter(
        template.samples,
        recording.n_samples,
        recording.sample_rate_hz,
        arrival_s=template.arrival_s,
        decimation=MATCHED_DECIMATION,
    )
    return MatchedEstimator(mf, options)


def _envelope_detector(
    recording: Recording, name: str, kinds: tuple[str, ...], envelope: EnvelopeOptions
) -> ThresholdDetector:
    """The shared envelope machinery of the envelope estimators (:mod:`echoloc.tof.envelopes`)."""
    if recording.signal_kind not in kinds:
        raise EchoLocError(
            f"{recording.source}: the {name} estimator needs signal_kind {' or '.join(map(repr, kinds))}, "
            f"not {recording.signal_kind!r}"
        )
    if recording.waveform is None:
        raise EchoLocError(
            f"{recording.source}: the {name} estimator needs the recording's waveform as its reference"
        )
    return ThresholdDetector(
        np.asarray(recording.waveform, float),
        recording.n_samples,
        recording.sample_rate_hz,
        recording.signal_kind,
        envelope=envelope,
        carrier_hz=recording.carrier_hz,
    )


def _prepare_threshold(recording: Recording, options: EchoOptions) -> Estimator:
    detector = _envelope_detector(recording, "threshold", ("rf", "envelope"), EnvelopeOptions())
    return lambda frame: threshold_echoes(frame, detector, options)


def _prepare_threshold_fir(recording: Recording, options: EchoOptions) -> Estimator:
    detector = _envelope_detector(recording, "threshold-fir", ("rf",), EnvelopeOptions(method="fir"))
    detector.fir_taps  # noqa: B018 -- designs the filter now, so a bad design is refused here
    return lambda frame: threshold_echoes(frame, detector, options)


def _prepare_threshold_cfar(recording: Recording, options: EchoOptions) -> Estimator:
    detector = _envelope_detector(
        recording, "threshold-cfar", ("rf", "envelope"), EnvelopeOptions(noise="cfar")
    )
    return lambda frame: threshold_echoes(frame, detector, options)


def _prepare_energy(recording: Recording, options: EchoOptions) -> Estimator:
    detector = _envelope_detector(recording, "energy", ("rf", "envelope"), EnvelopeOptions())
    return lambda frame: energy_echoes(frame, detector, options)


def _prepare_leading_edge(recording: Recording, options: EchoOptions) -> Estimator:
    detector = _envelope_detector(recording, "leading-edge", ("rf",), EnvelopeOptions())
    detector.edge_onset_samples  # noqa: B018 -- refuses a template without a rising edge now
    return lambda frame: leading_edge_echoes(frame, detector, options)


def _prepare_envelope_zero(recording: Recording, options: EchoOptions) -> Estimator:
    detector = _envelope_detector(recording, "envelope-zero", ("rf",), EnvelopeOptions())
    try:
        detector.template_zero  # noqa: B018 -- refuses a template without an envelope zero now
    except EchoLocError as error:
        raise EchoLocError(f"{recording.source}: {error}") from None
    return lambda frame: envelope_zero_echoes(frame, detector, options)


def _prepare_envelope_fit(recording: Recording, options: EchoOptions) -> Estimator:
    fitter = envelope_fitter(recording, "template")
    fitter.kernel  # noqa: B018 -- builds the template's interpolant now, so a bad template is refused here
    return lambda frame: envelope_fit_echoes(frame, fitter, options)


def _prepare_envelope_emg(recording: Recording, options: EchoOptions) -> Estimator:
    fitter = envelope_fitter(recording, "emg")
    fitter.model_error  # noqa: B018 -- calibrates the EMG on the template now
    return lambda frame: envelope_fit_echoes(frame, fitter, options)


def _prepare_envelope_peak(recording: Recording, options: EchoOptions) -> Estimator:
    detector = prepare_peak_detector(recording, options.template)
    return lambda frame: peak_echoes(frame, detector, options)


@dataclass(frozen=True)
class EstimatorInfo:
    """A registered estimator.

    ``prepare(recording, options)`` precomputes what the estimator reuses and returns
    it ready for frames; ``clean_tolerance_s`` is the largest error of its ``tof_s``
    on a clean, isolated echo (enforced by the tests for every registered estimator).
    """

    prepare: Callable[[Recording, EchoOptions], Estimator]
    clean_tolerance_s: float
    signal_kinds: tuple[str, ...]
    summary: str


ESTIMATORS: dict[str, EstimatorInfo] = {
    "matched": EstimatorInfo(
        _prepare_matched,
        clean_tolerance_s=1e-9,
        signal_kinds=("rf",),
        summary="matched filter (SENT template), CLEAN extraction, carrier-phase refinement",
    ),
    "threshold": EstimatorInfo(
        _prepare_threshold,
        clean_tolerance_s=5e-8,  # measured: 10 ns on the tests' pulse (rf)
        signal_kinds=("rf", "envelope"),
        summary="first envelope crossing of a level, corrected for the pulse's rise time",
    ),
    "threshold-fir": EstimatorInfo(
        _prepare_threshold_fir,
        # Squaring a pulse with abrupt chips at 4 samples per cycle aliases its edges
        # into the envelope: up to 0.41 us on the tests' pulse, 1 ns through a transducer.
        clean_tolerance_s=6e-7,
        signal_kinds=("rf",),
        summary="threshold on the report's envelope: squared rf through a linear-phase FIR low-pass",
    ),
    "threshold-cfar": EstimatorInfo(
        _prepare_threshold_cfar,
        clean_tolerance_s=5e-8,  # measured: 10 ns on the tests' pulse (rf)
        signal_kinds=("rf", "envelope"),
        summary="threshold with a cell-averaging CFAR level (noise that varies along the frame)",
    ),
    "energy": EstimatorInfo(
        _prepare_energy,
        clean_tolerance_s=3e-8,  # measured: 12 ns (rf)
        signal_kinds=("rf", "envelope"),
        summary="first crossing of the running energy over one chip, corrected for its rise time",
    ),
    "leading-edge": EstimatorInfo(
        _prepare_leading_edge,
        clean_tolerance_s=1e-7,  # measured: 41 ns on the tests' pulse (rf)
        signal_kinds=("rf",),
        summary="parabola fitted to the envelope's leading edge (20-80 % of the peak), onset at its vertex",
    ),
    "envelope-zero": EstimatorInfo(
        _prepare_envelope_zero,
        clean_tolerance_s=3e-9,  # measured: 0.5 ns on the tests' Barker pulse, 0.9 ns on flip8 (rf)
        signal_kinds=("rf",),
        summary="zero of the envelope at a phase reversal (two pulse trains, the second inverted)",
    ),
    "envelope-fit": EstimatorInfo(
        _prepare_envelope_fit,
        # Measured on clean echoes: 1.5 us on 20 kHz envelopes (the squared envelope's
        # aliasing), 0.6 ns on 20 kHz iq (carrier phase), 0.01 ns on rf.
        clean_tolerance_s=2e-6,
        signal_kinds=("rf", "iq", "envelope"),
        summary="template fit with sub-sample delay: coherent on iq/rf (carrier phase), "
        "squared envelope less the noise power on envelopes; overlapping echoes fitted jointly",
    ),
    "envelope-emg": EstimatorInfo(
        _prepare_envelope_emg,
        clean_tolerance_s=5e-7,  # measured: 0.3 us on 20 kHz envelopes and iq, 0.13 us on rf
        signal_kinds=("rf", "iq", "envelope"),
        summary="exponentially modified Gaussian fitted to the squared envelope, onset calibrated "
        "on the template, shape held near the template's for weak echoes",
    ),
    "envelope-peak": EstimatorInfo(
        _prepare_envelope_peak,
        # Measured: 0.6 us (0.013 sample) on clean Gaussian-shaped envelope echoes at 22 kHz.
        clean_tolerance_s=2e-6,
        signal_kinds=("iq", "envelope"),
        summary="peaks above each channel's own noise, Gaussian sub-sample vertex, arrival from the "
        "learnt echo shape; needs no waveform (real ToF chips)",
    ),
}
"""Every time-of-flight estimator, by name."""

AUTO = "auto"
"""The estimator name that picks :func:`default_estimator` for the recording."""


ENVELOPE_PEAK_THRESHOLD_DB = 3.0
"""The envelope-peak estimator's default threshold, dB over its noise level (1.4 sigma): an
envelope sample has no processing gain behind it, unlike the matched filter's output the
14 dB default is set for, and a missed echo costs the whole frame while a noise peak
rarely lies on the ellipsoids of three other channels (the association's gate rejects it).
On real CH101 data (``benchmarks/real_ch101.py``, the calibration half) 3 dB finds the
target's echo on enough channels in 98 % of frames, 8 dB in 78 %. A calibration with known
targets measures the rig's own threshold, at most this one, and ``locate --calibration``
uses it."""


def default_threshold_db(name: str, calibrated_db: float | None = None) -> float:
    """The default detection threshold of estimator ``name``, dB: for envelope-peak, the one a
    calibration measured on its targets (``calibrated_db``, see
    :func:`echoloc.localise.calibrate.detection_threshold_db`) where there is one."""
    if name != "envelope-peak":
        return EchoOptions.threshold_db
    return ENVELOPE_PEAK_THRESHOLD_DB if calibrated_db is None else calibrated_db


def default_estimator(recording: Recording) -> str:
    """The best estimator for the recording's kind of data.

    rf: the matched filter. envelope and iq: the envelope fit where the recording has its
    pulse (``waveform``), else the peak detector, which needs nothing but the data and
    learns the echo's shape from it (:mod:`echoloc.tof.envelope_peaks`).
    """
    if recording.signal_kind == "rf":
        return "matched"
    return "envelope-fit" if recording.waveform is not None else "envelope-peak"


def resolve_estimator(name: str, recording: Recording) -> str:
    """The estimator that runs for ``name``: :func:`default_estimator` for ``"auto"``, else ``name``."""
    return default_estimator(recording) if name == AUTO else name


def prepare_estimator(recording: Recording, options: EchoOptions, name: str = "matched") -> Estimator:
    """Look up estimator ``name`` (``"auto"``: :func:`default_estimator`) and precompute what it
    reuses for ``recording``."""
    name = resolve_estimator(name, recording)
    if name not in ESTIMATORS:
        raise EchoLocError(f"unknown estimator {name!r}; choose from {', '.join(ESTIMATORS)}")
    if options.template is not None and name not in ("matched", "envelope-peak"):
        # The other estimators take their reference from the recording's waveform; a
        # template given to them would be ignored without a word.
        raise EchoLocError(
            f"a template applies only to the matched and envelope-peak estimators, not to {name!r}"
        )
    return ESTIMATORS[name].prepare(recording, options)
