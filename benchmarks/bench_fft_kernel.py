"""The echoes stage with its FFTs inside the compiled kernel, against scipy.fft called from Python.

Until 2026-12-05 a frame's echoes took four calls from Python: scipy.fft's rfft, the compiled
fold, scipy.fft's inverse FFT, then the compiled batch path
(:func:`echoloc.tof._echoes_kernels.batch_channels`), with the padding, dispatch and checks of each
in between. Since then :func:`echoloc.tof.echoes.matched_filter_batch` makes one call
(:func:`echoloc.tof._echoes_kernels.correlate_and_fit`), its FFTs scipy.fft's own in compiled code
(rocket-fft). This benchmark times both ways on the frames of `echoloc bench`, a frame a call on
one core, in alternating rounds (medians reported), and checks that they find the same echoes:

1. the echoes stage alone;
2. the whole frame (echoes + locate) as `echoloc stream` runs it. Frames with a channel for
   CLEAN go through :class:`echoloc.realtime.stream.StreamProcessor` both ways.

    python benchmarks/bench_fft_kernel.py [--frames 200] [--rounds 7]
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np
import scipy.fft
from numpy.typing import NDArray

from _common import one_worker_chain, parse_arguments
from echoloc.benchmark import bench_scene, pinned_cores
from echoloc.realtime.stream import StreamProcessor, recording_frames
from echoloc.sim.simulation import simulate
from echoloc.tof.echoes import (
    EchoOptions,
    FrameEchoes,
    MatchedFilter,
    _batch_channels,
    _correlated_channels,
)


def scipy_echoes(mf: MatchedFilter, options: EchoOptions) -> Callable[[NDArray[np.float64]], list[Any]]:
    """A frame's channels the way before 2026-12-05: pad, scipy.fft's rfft, the compiled fold,
    scipy.fft's inverse FFT, then the batch kernel: four calls from Python."""

    def run(frame: NDArray[np.float64]) -> list[Any]:
        padded = np.zeros((frame.shape[0], mf.n_fft), dtype=np.float32)
        padded[:, : frame.shape[-1]] = frame[:, : mf.n_fft]
        spectrum = scipy.fft.rfft(padded, axis=-1, overwrite_x=True)
        folded = mf._weigh_and_fold(spectrum, mf._spectrum_single)
        correlation = np.asarray(scipy.fft.ifft(folded, axis=-1, overwrite_x=True))
        return _batch_channels(correlation, mf, options, 1)

    return run


def main() -> None:
    args = parse_arguments(__doc__, frames=200, rounds=7)
    with pinned_cores(1) as cores:
        recording = simulate(bench_scene(5), args.frames)
        chain = one_worker_chain(recording)
        mf, options = chain.estimator.mf, chain.estimator.options  # type: ignore[attr-defined]
        frames = [np.asarray(f, dtype=float) for f in recording.frames]
        before = scipy_echoes(mf, options)

        def now(frame: NDArray[np.float64]) -> list[Any]:
            return _correlated_channels(frame, mf, options)

        locator, c = chain.locators[0], chain.speed_of_sound_m_s
        stream_frames = list(recording_frames(recording))

        def frame_before(processor: StreamProcessor) -> None:
            for frame in stream_frames:
                channels = before(np.asarray(frame.samples))
                if any(channel is None for channel in channels):
                    processor.process(frame)
                else:
                    locator(FrameEchoes(frame.index, frame.time_s, c, tuple(channels)))

        def frame_now(processor: StreamProcessor) -> None:
            for frame in stream_frames:
                processor.process(frame)

        stage: dict[str, list[float]] = {"before": [], "now": []}
        whole: dict[str, list[float]] = {"before": [], "now": []}
        warm = StreamProcessor(chain)
        warm.warm_up()
        frame_before(warm)
        frame_now(warm)
        for _ in range(args.rounds):
            for name, way in (("before", before), ("now", now)):
                started = time.perf_counter()
                for frame in frames:
                    way(frame)
                stage[name].append((time.perf_counter() - started) / len(frames) * 1e6)
            for name, stream_pass in (("before", frame_before), ("now", frame_now)):
                started = time.perf_counter()
                stream_pass(StreamProcessor(chain))
                whole[name].append((time.perf_counter() - started) / len(stream_frames) * 1e6)
        worst_s, differ = 0.0, 0
        for frame in frames:
            for a, b in zip(before(frame), now(frame), strict=True):
                if (a is None) != (b is None) or (a is not None and len(a.tof_s) != len(b.tof_s)):
                    differ += 1
                elif a is not None and len(a.tof_s):
                    worst_s = max(worst_s, float(np.max(np.abs(a.tof_s - b.tof_s))))
    print(
        f"{len(frames)} `echoloc bench` frames, a frame a call, on CPU {cores}, "
        f"median of {args.rounds} alternating rounds:\n"
    )
    print("| µs a frame | four calls, scipy.fft from Python | one compiled call | × |\n|---|---|---|---|")
    for label, times in (("echoes stage", stage), ("whole frame (echoes + locate)", whole)):
        b, n = float(np.median(times["before"])), float(np.median(times["now"]))
        print(f"| {label} | {b:.1f} | {n:.1f} | {b / n:.2f} |")
    print(
        f"\nChannels whose echoes differ in number or CLEAN hand-over: {differ} of "
        f"{len(frames) * frames[0].shape[0]}; largest delay difference of the rest {worst_s * 1e9:.3f} ns."
    )


if __name__ == "__main__":
    main()
