"""What the echoes stage of a stream's frame would gain if its FFTs ran inside the compiled kernel.

Today a frame's echoes take several calls from Python (:func:`echoloc.echoes.matched_filter_batch`):
scipy.fft's rfft, the compiled fold, scipy.fft's inverse FFT, then the compiled batch path
(:func:`echoloc._echoes_kernels.batch_channels`), with the padding, dispatch and checks of each in
between. `profile_stream.py` puts about a quarter of a frame in the Python interpreter. This
benchmark measures the alternative on the frames of `echoloc bench`: the same four steps in one
compiled call, the FFTs by rocket-fft (pocketfft, as scipy.fft, callable from numba code), and the
same ChannelEchoes built from its output. Both run in alternating rounds on one core; the median
of the rounds is reported, with how far the two answers differ (float32 FFTs of two builds of
pocketfft round differently).

Needs rocket-fft, which the dev extra installs (``python3 dev.py bench``); echoloc itself does not
depend on it.

It then times the whole frame (echoes + locate) as `echoloc stream` runs it, both ways.

    python benchmarks/bench_fft_kernel.py [--frames 100] [--rounds 7]
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from typing import Any

import numpy as np
from numpy.typing import NDArray

from echoloc.benchmark import bench_scene, pinned_cores
from echoloc.echoes import (
    _MAX_SPLITS,
    _NOISE_STEP,
    ChannelEchoes,
    EchoOptions,
    FrameEchoes,
    MatchedFilter,
    _batch_channels,
    _kernel_constants,
)
from echoloc.pipeline import prepare
from echoloc.simulate import simulate
from echoloc.stream import StreamProcessor, recording_frames


def fused_echoes(mf: MatchedFilter, options: EchoOptions) -> Callable[[NDArray[np.float64]], list[Any]]:
    """The echoes of one frame (n_rx, n_samples) in one compiled call: pad, rfft, fold, inverse
    FFT, batch path; the channels as :func:`echoloc.echoes._batch_channels` returns them."""
    try:
        import rocket_fft  # noqa: F401  (registers scipy.fft for numba)
    except ImportError:
        sys.exit("bench_fft_kernel.py needs rocket-fft: pip install rocket-fft")
    import scipy.fft
    from numba import njit

    from echoloc import _echoes_kernels as kernels

    weigh_and_fold, batch_channels = kernels.weigh_and_fold, kernels.batch_channels

    @njit
    def kernel(frame, n_fft, n_ifft, weights, n_lags, constants, finishing, out, kept, ok):  # type: ignore[no-untyped-def]  # pragma: no cover
        rows, n = frame.shape
        padded = np.zeros((rows, n_fft), np.float32)
        padded[:, : min(n, n_fft)] = frame[:, : min(n, n_fft)]
        spectrum = scipy.fft.rfft(padded, axis=-1)
        folded = np.empty((rows, n_ifft), np.complex64)
        weigh_and_fold(spectrum, weights, folded)
        correlation = scipy.fft.ifft(folded, axis=-1)
        batch_channels(1, correlation.view(np.float32), n_lags, constants, finishing, out, kept, ok)

    constants, finishing = _kernel_constants(mf, options, _NOISE_STEP, _MAX_SPLITS)
    weights = mf._spectrum_single

    def run(frame: NDArray[np.float64]) -> list[Any]:
        n_ch = frame.shape[0]
        out = np.zeros((3, n_ch, 4 * options.max_echoes))
        kept = np.zeros(n_ch, dtype=np.int64)
        ok = np.zeros(n_ch, dtype=np.bool_)
        kernel(frame, mf.n_fft, mf.n_ifft, weights, mf.n_lags, constants, finishing, out, kept, ok)
        tof_s, amplitude, snr_db = out
        return [
            ChannelEchoes(tof_s[c, : kept[c]], amplitude[c, : kept[c]], snr_db[c, : kept[c]])
            if ok[c]
            else None
            for c in range(n_ch)
        ]

    return run


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args()
    with pinned_cores(1) as cores:
        recording = simulate(bench_scene(5), args.frames)
        chain = prepare(recording, echo_options=EchoOptions(workers=1))
        mf, options = chain.estimator.mf, chain.estimator.options  # type: ignore[attr-defined]
        frames = [np.asarray(f, dtype=float) for f in recording.frames]

        def today(frame: NDArray[np.float64]) -> list[Any]:
            rows = mf.correlate_single_rows(frame[None]).reshape(frame.shape[0], -1)
            return _batch_channels(rows, mf, options, 1)

        fused = fused_echoes(mf, options)
        started = time.perf_counter()
        fused(frames[0])
        compile_s = time.perf_counter() - started
        ways = {
            "today: scipy.fft from Python, then the batch kernel": today,
            "one compiled call (rocket-fft)": fused,
        }
        for way in ways.values():
            for frame in frames[:5]:
                way(frame)
        times: dict[str, list[float]] = {name: [] for name in ways}
        for _ in range(args.rounds):
            for name, way in ways.items():
                started = time.perf_counter()
                for frame in frames:
                    way(frame)
                times[name].append((time.perf_counter() - started) / len(frames))
        # The whole frame (echoes + locate, as `echoloc stream` runs it) both ways: the stages of a
        # frame a call start cold after one another (bench_kernel_share.py), and fewer, larger
        # calls may start less cold. Frames with a channel for CLEAN go through the processor.
        locator, c = chain.locators[0], chain.speed_of_sound_m_s
        stream_frames = list(recording_frames(recording))

        def stream_today(processor: StreamProcessor) -> None:
            for frame in stream_frames:
                processor.process(frame)

        def stream_fused(processor: StreamProcessor) -> None:
            for frame in stream_frames:
                channels = fused(np.asarray(frame.samples))
                if any(channel is None for channel in channels):
                    processor.process(frame)
                else:
                    locator(FrameEchoes(frame.index, frame.time_s, c, tuple(channels)))

        frame_times: dict[str, list[float]] = {"today": [], "fused": []}
        warm = StreamProcessor(chain)
        warm.warm_up()
        stream_today(warm)
        stream_fused(warm)
        for _ in range(args.rounds):
            for name, stream_pass in (("today", stream_today), ("fused", stream_fused)):
                started = time.perf_counter()
                stream_pass(StreamProcessor(chain))
                frame_times[name].append((time.perf_counter() - started) / len(stream_frames))
        worst_s, differ = 0.0, 0
        for frame in frames:
            for a, b in zip(today(frame), fused(frame), strict=True):
                if (a is None) != (b is None) or (a is not None and len(a.tof_s) != len(b.tof_s)):
                    differ += 1
                elif a is not None and len(a.tof_s):
                    worst_s = max(worst_s, float(np.max(np.abs(a.tof_s - b.tof_s))))
    medians = {name: float(np.median(t)) for name, t in times.items()}
    base = medians[next(iter(ways))]
    print(
        f"echoes stage of {len(frames)} `echoloc bench` frames, a frame a call, on CPU {cores}, "
        f"median of {args.rounds} rounds:\n"
    )
    print("| way | µs/frame | × today |\n|---|---|---|")
    for name, median in medians.items():
        print(f"| {name} | {median * 1e6:.1f} | {base / median:.2f} |")
    frame_medians = {name: float(np.median(t)) * 1e6 for name, t in frame_times.items()}
    print(
        f"\nThe whole frame (echoes + locate, the stream's way), same rounds: today "
        f"{frame_medians['today']:.1f} µs, with the fused echoes {frame_medians['fused']:.1f} µs "
        f"({frame_medians['today'] / frame_medians['fused']:.2f}x)."
    )
    print(
        f"\nrocket-fft kernel compiled in {compile_s:.1f} s. Channels whose echoes differ in number "
        f"or CLEAN hand-over: {differ} of {len(frames) * frames[0].shape[0]}; largest delay "
        f"difference of the rest {worst_s * 1e9:.3f} ns."
    )


if __name__ == "__main__":
    main()
