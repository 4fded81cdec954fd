"""The streamed full chain against the scipy chain and the physics, and a long soak over TCP.

Two parts, each optional:

1. ``--frames N``: `echoloc bench` (echoloc.benchmark.bench_chains): frames/s,
   latency p50/p99 and peak memory of the full chain (echoes + locate) on the
   default 4-receiver frame of 2400 samples with ``--reflectors`` objects, on one
   core, side by side with the straightforward scipy chain.
2. ``--soak-minutes M``: a live stream for M minutes. ``echoloc send`` (its own
   process) replays the recording over TCP on loopback at ``--speed`` times real
   time, looping; this process receives it (echoloc.realtime.transport.Listener, queue of
   64 frames, oldest dropped when full) and runs the chain on every frame it can
   (echoloc.realtime.stream.StreamProcessor). Every ``--window-s`` it notes the resident
   memory (VmRSS), the frames received, processed, lost and dropped, and the
   latency p50/p99 of that window (arrival to result). Memory is flat when the
   largest and smallest RSS after the first window differ by little.

    python benchmarks/bench_stream.py --frames 200 --baseline-frames 2
    python benchmarks/bench_stream.py --soak-minutes 10 --speed 10 --markdown benchmarks/results/stream.md
"""

from __future__ import annotations

import argparse
import math
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from echoloc.benchmark import bench_chains, bench_scene, format_bench
from echoloc.io.recording import write_recording
from echoloc.pipeline import prepare
from echoloc.realtime.stream import (
    STREAM_BATCH_FRAMES,
    FrameQueue,
    LatencyHistogram,
    StreamFrame,
    StreamProcessor,
)
from echoloc.realtime.transport import Endpoint, Listener, SessionEvent
from echoloc.sim.simulation import simulate


def rss_mib() -> float:
    """Resident memory of this process, MiB (Linux /proc)."""
    with open("/proc/self/status") as status:
        for line in status:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    return math.nan


def soak(minutes: float, speed: float, reflectors: int, n_frames: int, window_s: float) -> list[str]:
    """Run the soak; the Markdown lines of its report."""
    recording = simulate(bench_scene(reflectors), n_frames)
    # The recording's own pace: its frame_times (the scene's frame rate), as `echoloc send` plays it.
    period_s = (
        float(np.median(np.diff(recording.frame_times_s)))
        if recording.frame_times_s is not None
        else recording.n_samples / recording.sample_rate_hz
    )
    tmp = Path(tempfile.mkdtemp(prefix="echoloc-soak-"))
    path = write_recording(recording, tmp / "soak.h5")
    echoloc = shutil.which("echoloc") or str(Path(sys.executable).with_name("echoloc"))
    rows: list[str] = []
    listener = Listener(Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(64)).start()
    port = listener.address.port
    command = [echoloc, "send", str(path), "--to", f"127.0.0.1:{port}", "--speed", str(speed), "--loop", "0"]
    sender = subprocess.Popen(command, stderr=subprocess.PIPE, text=True)
    processor: StreamProcessor | None = None
    window = LatencyHistogram()
    rss: list[float] = []
    p99: list[float] = []
    start = time.monotonic()
    next_note = start + window_s
    last = {"received": 0, "processed": 0, "dropped": 0, "lost": 0}
    header = (
        "| t min | RSS MiB | received/s | processed/s | dropped/s | lost | latency p50 ms | latency p99 ms |"
    )
    rows += [header, "|---|---|---|---|---|---|---|---|"]
    try:
        while time.monotonic() - start < minutes * 60:
            # As `echoloc stream` takes them: a session, or the frames that queued up, in one batch.
            items = listener.queue.get_batch(0.1, STREAM_BATCH_FRAMES)
            item = items[0] if items else None
            if isinstance(item, SessionEvent):
                processor = StreamProcessor(prepare(item.header))
                processor.warm_up()
            elif isinstance(item, StreamFrame) and processor is not None:
                frames = [frame for frame in items if isinstance(frame, StreamFrame)]  # all of them
                for result in processor.process_batch(frames):
                    window.add(result.latency_s)
            now = time.monotonic()
            if now >= next_note and processor is not None:
                counters = {**listener.counters(), "processed": processor.processed}
                rate = {k: (counters[k] - last[k]) / window_s for k in ("received", "processed", "dropped")}
                rss.append(rss_mib())
                p99.append(window.quantile(0.99) * 1e3)
                rows.append(
                    f"| {(now - start) / 60:.1f} | {rss[-1]:.1f} | {rate['received']:.0f} | "
                    f"{rate['processed']:.0f} | {rate['dropped']:.0f} | {counters['lost']} | "
                    f"{window.quantile(0.5) * 1e3:.2f} | {p99[-1]:.2f} |"
                )
                print(rows[-1], flush=True)
                last = {k: counters[k] for k in last}
                window.reset()
                next_note = now + window_s
    finally:
        sender.terminate()
        sender.wait(10)
        queued = len(listener.queue)  # frames that arrived but were still waiting at the stop
        listener.stop()
        shutil.rmtree(tmp, ignore_errors=True)
    assert processor is not None
    stats = processor.stats(**listener.counters())
    waiting = queued  # a session cannot be queued mid-stream: only frames wait
    unaccounted = stats.received - stats.processed - stats.dropped - waiting
    steady = rss[1:] or rss
    steady_p99 = p99[1:] or p99
    elapsed = time.monotonic() - start
    summary = [
        "",
        f"{minutes:g} minutes at {speed:g}x real time: frames sent every {period_s / speed * 1e3:.2f} ms "
        f"({1 / period_s * speed:.0f} frames/s; real time is {1 / period_s:.1f} frames/s), "
        f"{reflectors or 3} objects, {recording.n_frames} frames looped.",
        f"Memory after the first window: {min(steady):.1f} .. {max(steady):.1f} MiB "
        f"(drift {max(steady) - min(steady):.1f} MiB). Latency p99 per window: "
        f"{min(steady_p99):.1f} .. {max(steady_p99):.1f} ms.",
        f"Totals: {stats.summary()}; {stats.processed / elapsed:.0f} frames/s processed on average.",
        f"Every frame accounted for: received {stats.received} = processed {stats.processed} + dropped "
        f"{stats.dropped} + still queued at the stop {waiting}"
        + (" (exactly)." if unaccounted == 0 else f"; {unaccounted} unaccounted."),
    ]
    return rows + summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=0, help="Frames for the bench (0: no bench).")
    parser.add_argument("--baseline-frames", type=int, default=2)
    parser.add_argument("--reflectors", type=int, default=5)
    parser.add_argument("--soak-minutes", type=float, default=0.0, help="0: no soak.")
    parser.add_argument("--speed", type=float, default=10.0, help="Soak: times real time.")
    parser.add_argument("--soak-frames", type=int, default=200, help="Soak: frames in the looped recording.")
    parser.add_argument("--window-s", type=float, default=30.0, help="Soak: seconds per row.")
    parser.add_argument("--markdown", type=Path, default=None, help="Also write the report here.")
    args = parser.parse_args()
    lines: list[str] = []
    if args.frames:
        report = bench_chains(
            simulate(bench_scene(args.reflectors), args.frames), baseline_frames=args.baseline_frames
        )
        lines += ["## Full chain, one core", "", format_bench(report), ""]
        print("\n".join(lines), flush=True)
    if args.soak_minutes:
        soak_lines = soak(args.soak_minutes, args.speed, args.reflectors, args.soak_frames, args.window_s)
        lines += ["## Soak: a live stream over TCP on loopback", "", *soak_lines, ""]
        print("\n".join(soak_lines[-3:]), flush=True)
    if args.markdown is not None:
        args.markdown.write_text("\n".join(lines))


if __name__ == "__main__":
    main()
