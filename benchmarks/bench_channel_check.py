"""What the degraded-channel check (echoloc.tof.channel_health) costs a healthy frame.

The chain runs the same frames with the check on and off, interleaved pass by pass so that
a shared machine's load falls on both alike; the report gives each pass's ms a frame and
their ratio, through ``pipeline.run`` (files, batches of frames) and through
``StreamProcessor.process`` (a live stream, a frame a call).

    .venv/bin/python benchmarks/bench_channel_check.py [--frames 200] [--passes 7]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from echoloc.io.recording import as_header
from echoloc.pipeline import prepare, run
from echoloc.realtime.stream import StreamProcessor, recording_frames
from echoloc.sim.scene import default_scene
from echoloc.sim.simulation import simulate


def _file_ms(chain: object, frames: list[int]) -> float:
    start = time.perf_counter()
    for _ in run(chain, frames):  # type: ignore[arg-type]
        pass
    return (time.perf_counter() - start) / len(frames) * 1e3


def _stream_ms(processor: StreamProcessor, stream_frames: list[object]) -> float:
    start = time.perf_counter()
    for frame in stream_frames:
        processor.process(frame)  # type: ignore[arg-type]
    return (time.perf_counter() - start) / len(stream_frames) * 1e3


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--passes", type=int, default=7)
    args = parser.parse_args()
    recording = simulate(default_scene(), n_frames=args.frames)
    frames = list(range(recording.n_frames))
    chains = {check: prepare(recording, estimator="matched", check_channels=check) for check in (True, False)}
    processors = {
        check: StreamProcessor(prepare(as_header(recording), estimator="matched", check_channels=check))
        for check in (True, False)
    }
    stream_frames = list(recording_frames(recording))
    for check in (True, False):  # compile and warm both
        _file_ms(chains[check], frames[:20])
        _stream_ms(processors[check], stream_frames[:20])
    timings: dict[tuple[str, bool], list[float]] = {}
    for _ in range(args.passes):
        for check in (True, False):
            timings.setdefault(("file", check), []).append(_file_ms(chains[check], frames))
            timings.setdefault(("stream", check), []).append(_stream_ms(processors[check], stream_frames))
    print(f"{args.frames} frames of the default scene, {args.passes} interleaved passes, median ms a frame:")
    print("| path | check on | check off | on / off |")
    print("|---|---|---|---|")
    for path in ("file", "stream"):
        on, off = (statistics.median(timings[path, check]) for check in (True, False))
        print(f"| {path} | {on:.3f} | {off:.3f} | {on / off:.2f} |")
    ratios = np.array(timings["stream", True]) / np.array(timings["stream", False])
    print(f"stream, per pass on/off: {', '.join(f'{r:.2f}' for r in ratios)}")


if __name__ == "__main__":
    main()
