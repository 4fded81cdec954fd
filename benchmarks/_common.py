"""What the benchmark scripts share: their command line, a stopwatch, the chains and filters they time.

The scripts run as ``python benchmarks/bench_*.py``, so this folder is on ``sys.path`` and
they import this module as ``_common``. It is no benchmark itself: ``python3 dev.py bench``
runs the ``bench_*.py`` files only.
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable, Sequence

import numpy as np

from echoloc.io.recording import Recording
from echoloc.pipeline import Chain, prepare
from echoloc.tof.echoes import MATCHED_DECIMATION, EchoOptions, MatchedFilter


def parse_arguments(
    doc: str, frames: int, rounds: int, more: Sequence[tuple[str, int, str]] = ()
) -> argparse.Namespace:
    """The script's command line, described by the first line of ``doc`` (its docstring):
    ``--frames`` and ``--rounds`` defaulting to ``frames`` and ``rounds``, and each of
    ``more``, ``(flag, default, help)``, one more whole-number option."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    parser.add_argument("--frames", type=int, default=frames)
    parser.add_argument("--rounds", type=int, default=rounds)
    for flag, default, text in more:
        parser.add_argument(flag, type=int, default=default, help=text)
    return parser.parse_args()


def seconds(job: Callable[[], object]) -> float:
    """Wall-clock seconds one call of ``job`` takes."""
    start = time.perf_counter()
    job()
    return time.perf_counter() - start


def one_worker_chain(recording: Recording) -> Chain:
    """The recording's chain with every call on one thread (``EchoOptions(workers=1)``)."""
    return prepare(recording, echo_options=EchoOptions(workers=1))


def matched_filter(recording: Recording) -> MatchedFilter:
    """The matched filter of the recording's pulse, decimated as the `matched` estimator's."""
    return MatchedFilter(
        np.asarray(recording.waveform, float),
        recording.n_samples,
        recording.sample_rate_hz,
        decimation=MATCHED_DECIMATION,
    )
