"""The matched filter on one thread and on several (`--workers`), repeated, side by side.

On a shared machine a second thread only helps while a second core is free, so one
number says little: this runs ``--repeats`` rounds, each timing ``echoes`` on the same
40 frames (the report's scene, or five random reflectors) with one thread and with
``--threads``, batched and one frame per call (median of 7 calls each), and prints
every round. The echoes are the same to the bit whatever the threads (a test holds
them to it).

    python benchmarks/bench_threads.py [--repeats 8] [--threads 2] [--reflectors 0]
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np

from echoloc.benchmark import bench_scene
from echoloc.pipeline import prepare
from echoloc.sim.simulation import simulate
from echoloc.tof.echoes import MATCHED_DECIMATION, MatchedFilter, matched_filter_batch, matched_filter_echoes


def _median_us_per_frame(job: Callable[[], object], n_frames: int, calls: int = 7) -> float:
    times = []
    for _ in range(calls):
        start = time.perf_counter()
        job()
        times.append(time.perf_counter() - start)
    return float(np.median(times)) / n_frames * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=8)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--reflectors", type=int, default=0, help="0: the report's three balls")
    parser.add_argument("--frames", type=int, default=40)
    args = parser.parse_args()
    chain = prepare(simulate(bench_scene(args.reflectors), args.frames))
    recording = chain.recording
    one = chain.echo_options
    many = replace(one, workers=args.threads)
    mf = MatchedFilter(
        np.asarray(recording.waveform, float),
        recording.n_samples,
        recording.sample_rate_hz,
        decimation=MATCHED_DECIMATION,
    )
    frames = np.asarray(recording.frames[: args.frames], dtype=float)
    for options in (one, many):  # compile or load the kernels, start the threads
        matched_filter_batch(frames[:2], mf, options)
    scene = "the report's three balls" if args.reflectors == 0 else f"{args.reflectors} random reflectors"
    print("# bench_threads.py — last run\n")
    print(
        f"`python benchmarks/bench_threads.py --repeats {args.repeats} --threads {args.threads} "
        f"--reflectors {args.reflectors}`\n"
    )
    print(
        f"{scene}, {args.frames} frames x {recording.n_receivers} receivers x {recording.n_samples} "
        f"samples; µs a frame, median of 7 calls; load average at start "
        f"{os.getloadavg()[0]:.2f} on {os.cpu_count()} cores.\n"
    )
    print(
        f"| round | batched, 1 thread | batched, {args.threads} | "
        f"one frame a call, 1 | one frame a call, {args.threads} |"
    )
    print("|---|---|---|---|---|")
    rows = []
    for round_ in range(args.repeats):
        row = [
            _median_us_per_frame(lambda o=options: matched_filter_batch(frames, mf, o), args.frames)
            for options in (one, many)
        ] + [
            _median_us_per_frame(
                lambda o=options: [matched_filter_echoes(f, mf, o) for f in frames], args.frames
            )
            for options in (one, many)
        ]
        rows.append(row)
        print(f"| {round_ + 1} | " + " | ".join(f"{v:.0f}" for v in row) + " |", flush=True)
    best = np.min(rows, axis=0)
    median = np.median(rows, axis=0)
    print("| best | " + " | ".join(f"{v:.0f}" for v in best) + " |")
    print("| median | " + " | ".join(f"{v:.0f}" for v in median) + " |")


if __name__ == "__main__":
    main()
