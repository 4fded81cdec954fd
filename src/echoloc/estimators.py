"""The registry of time-of-flight estimators: every estimator, by name, in one place.

Tests and studies iterate :data:`ESTIMATORS`, so an estimator enrolled here is
checked on clean data against its documented tolerance and measured against the
Cramér-Rao bound without further wiring.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from echoloc.echoes import ChannelEchoes, EchoOptions, MatchedFilter, matched_filter_echoes
from echoloc.envelopes import ThresholdDetector, threshold_echoes
from echoloc.errors import EchoLocError
from echoloc.recording import Recording
from echoloc.templates import sent_template

Estimator = Callable[[NDArray[np.floating]], list[ChannelEchoes]]
"""A prepared estimator: one frame (n_rx, n_samples) -> echoes per receiver."""


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
        template.samples, recording.n_samples, recording.sample_rate_hz, arrival_s=template.arrival_s
    )
    return lambda frame: matched_filter_echoes(frame, mf, options)


def _prepare_threshold(recording: Recording, options: EchoOptions) -> Estimator:
    if recording.signal_kind not in ("rf", "envelope"):
        raise EchoLocError(
            f"{recording.source}: the threshold estimator needs signal_kind 'rf' or 'envelope', "
            f"not {recording.signal_kind!r}"
        )
    if recording.waveform is None:
        raise EchoLocError(
            f"{recording.source}: the threshold estimator needs the recording's waveform "
            "to correct for the envelope's rise time"
        )
    detector = ThresholdDetector(
        np.asarray(recording.waveform, float),
        recording.n_samples,
        recording.sample_rate_hz,
        recording.signal_kind,
    )
    return lambda frame: threshold_echoes(frame, detector, options)


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
        clean_tolerance_s=1e-6,
        signal_kinds=("rf", "envelope"),
        summary="first envelope crossing of a level, corrected for the pulse's rise time",
    ),
}
"""Every time-of-flight estimator, by name."""


def prepare_estimator(recording: Recording, options: EchoOptions, name: str = "matched") -> Estimator:
    """Look up estimator ``name`` and precompute what it reuses for ``recording``."""
    if name not in ESTIMATORS:
        raise EchoLocError(f"unknown estimator {name!r}; choose from {', '.join(ESTIMATORS)}")
    return ESTIMATORS[name].prepare(recording, options)
