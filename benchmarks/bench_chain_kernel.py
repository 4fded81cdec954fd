"""A stream's frames with echoes and objects in one compiled call, against the two stages in turn.

Since 2026-12-05 :func:`echoloc.pipeline.samples_results_batch` finds a frame's echoes and its
objects in one call (:func:`echoloc._chain_kernels.echoes_and_objects`) wherever the chain
allows (:attr:`echoloc.pipeline.Chain.one_call`). Before, the echoes came back to Python as
ChannelEchoes, were flattened again, and the association was a second call. This benchmark
streams `echoloc bench`'s frames through :class:`echoloc.realtime.stream.StreamProcessor` both ways, a
frame a call and 16 a call (a backlog), pinned to one core, in alternating rounds (medians
reported), and checks that both ways give the same records. Then it times every frame alone,
one call each (five times, averaged), to split the frames whose channels all stay on the
batch path from those with a channel left to CLEAN. Last, the one call alone on the batch-path
frames, four ways (one frame's buffer again and again, copies of that frame, each frame
repeated, cycling through the frames): what the samples' cache state costs, against the code
meeting different frames one after another.

    python benchmarks/bench_chain_kernel.py [--frames 200] [--rounds 7]
"""

from __future__ import annotations

import statistics
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray

from _common import one_worker_chain, parse_arguments
from echoloc.benchmark import _stream_pass, bench_scene, pinned_cores
from echoloc.io.output import echoes_record, objects_record
from echoloc.pipeline import Chain
from echoloc.realtime.stream import STREAM_BATCH_FRAMES, StreamFrame, StreamProcessor, recording_frames
from echoloc.sim.simulation import simulate
from echoloc.tof.echoes import _correlated_channels


def frame_order_study(
    chain: Chain, frames: list[StreamFrame], keep: NDArray[np.bool_], rounds: int
) -> dict[str, float]:
    """The one compiled call alone (µs a call, median of ``rounds``) over the frames ``keep``
    marks, four ways: one frame's arguments again and again; as many copies of that frame;
    each frame repeated 20 times (their mean); cycling through the frames."""
    from echoloc import _chain_kernels as kernels
    from echoloc.pipeline import _conditioned
    from echoloc.tof.echoes import echo_kernel_arguments

    assert chain.one_call is not None
    estimator, _, locate_arguments = chain.one_call
    n_rx = frames[0].samples.shape[0]

    def arguments(frame: StreamFrame) -> tuple[Any, ...]:
        samples = frame.samples.copy()  # a copy of its own
        conditioned = _conditioned(chain, [samples], [frame.index])
        return echo_kernel_arguments(conditioned, estimator.mf, estimator.options, 1)

    kept = [f for f, k in zip(frames, keep, strict=True) if k]
    one = arguments(kept[0])
    ways = {
        "one frame's buffer again and again": [one] * len(kept),
        "copies of that frame": [arguments(kept[0]) for _ in kept],
        "cycling through the frames": [arguments(f) for f in kept],
    }

    def per_call_us(calls: list[tuple[Any, ...]]) -> float:
        started = time.perf_counter()
        for call in calls:
            kernels.echoes_and_objects(call, n_rx, locate_arguments)
        return (time.perf_counter() - started) / len(calls) * 1e6

    timings: dict[str, list[float]] = {name: [] for name in ways}
    timings["each frame repeated (mean)"] = []
    for _ in range(rounds):
        for name, calls in ways.items():
            timings[name].append(per_call_us(calls))
        timings["each frame repeated (mean)"].append(
            float(np.mean([per_call_us([call] * 20) for call in ways["cycling through the frames"]]))
        )
    return {name: statistics.median(values) for name, values in timings.items()}


SOUND_LIMIT_FRAMES_S = 85.8
"""What sound allows one transmitter for 2 m of range at 343.2 m/s (`echoloc bench`)."""


def main() -> None:
    args = parse_arguments(__doc__, frames=200, rounds=7)
    with pinned_cores(1) as cores:
        recording = simulate(bench_scene(5), args.frames)
        one_call = one_worker_chain(recording)
        stages = one_worker_chain(recording)
        stages.__dict__["one_call"] = None  # the cached property, set: the stages in turn
        assert one_call.one_call is not None
        ways: dict[str, Chain] = {"two stages": stages, "one call": one_call}
        for chain in ways.values():
            StreamProcessor(chain).warm_up()
            _stream_pass(chain, recording, 1)
        records = {}
        for name, chain in ways.items():
            processor = StreamProcessor(chain)
            results = [processor.process(f) for f in recording_frames(recording)]
            records[name] = [(echoes_record(r.echoes), objects_record(r.objects)) for r in results]
        each_us = np.zeros(recording.n_frames)
        processor = StreamProcessor(one_call)
        frames = list(recording_frames(recording))
        for _ in range(5):
            for i, frame in enumerate(frames):
                started = time.perf_counter()
                processor.process(frame)
                each_us[i] += (time.perf_counter() - started) / 5 * 1e6
        estimator = one_call.one_call[0]
        channels = _correlated_channels(np.asarray(recording.frames), estimator.mf, estimator.options)
        n_rx = recording.n_receivers
        to_clean = np.array(
            [any(c is None for c in channels[i * n_rx : (i + 1) * n_rx]) for i in range(len(frames))]
        )
        order = frame_order_study(one_call, frames, ~to_clean, args.rounds)
        timings: dict[tuple[str, int], list[float]] = {}
        for _ in range(args.rounds):
            for batch in (1, STREAM_BATCH_FRAMES):
                for name, chain in ways.items():
                    wall_s = _stream_pass(chain, recording, batch)[0]
                    timings.setdefault((name, batch), []).append(wall_s / recording.n_frames * 1e6)
    print(
        f"{recording.n_frames} `echoloc bench` frames streamed on CPU {cores}, "
        f"median of {args.rounds} alternating rounds:\n"
    )
    print("| µs a frame | two stages | one call | × | one call, × 85.8 frames/s |\n|---|---|---|---|---|")
    for batch in (1, STREAM_BATCH_FRAMES):
        before = statistics.median(timings[("two stages", batch)])
        now = statistics.median(timings[("one call", batch)])
        label = "a frame a call" if batch == 1 else f"a backlog, {batch} frames a call"
        times_sound = 1e6 / now / SOUND_LIMIT_FRAMES_S
        print(f"| {label} | {before:.1f} | {now:.1f} | {before / now:.3f} | {times_sound:.1f} |")
    clean_share = (each_us[to_clean].sum() - to_clean.sum() * each_us[~to_clean].mean()) / len(each_us)
    print(
        f"\nEach frame alone, one call each: the {int((~to_clean).sum())} frames kept on the batch path "
        f"{each_us[~to_clean].mean():.1f} µs on average, the {int(to_clean.sum())} with a channel for CLEAN "
        f"{each_us[to_clean].mean():.1f} µs, which adds {clean_share:.1f} µs to the average frame."
    )
    print(f"\nThe one call alone on those {int((~to_clean).sum())} frames, µs a call:")
    for name, us in order.items():
        print(f"- {name}: {us:.1f}")
    same = records["one call"] == records["two stages"]
    print(
        f"\nThe same echoes and objects both ways: {'yes' if same else 'NO'} ({recording.n_frames} frames)."
    )


if __name__ == "__main__":
    main()
