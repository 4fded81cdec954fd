"""Time per frame of the matched filter (`echoes`), side by side with a straightforward scipy chain.

The baseline, written the obvious way: per channel ``scipy.signal.correlate`` with the
pulse, ``scipy.signal.hilbert`` for the envelope, ``scipy.signal.find_peaks`` (height
5 sigma of the envelope noise, distance one chip) and a parabola through the peak.

echoloc's `matched` estimator is timed two ways: one frame at a time
(``matched_filter_echoes``: the latency of a frame) and all frames in one call
(``matched_filter_batch``: the throughput), with its parts beside them: the
single-precision correlation, the compiled batch path, its numpy statement, and CLEAN
on the channels the batch path hands over (compiled, and its Python statement). All
run on the same frames in alternating rounds (this machine is shared and noisy); the
median of the rounds is reported with the ratios, and the accuracy of both chains on
the same echoes, so that a speed-up never hides a loss of accuracy.

The threaded rows spread each call's channels over ``--threads`` threads
(``EchoOptions.workers``, `--workers` on the CLI); every other row runs on one.

    python benchmarks/bench_echoes.py [--frames 40] [--rounds 7] [--threads 2]
"""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from _common import matched_filter, parse_arguments, seconds
from echoloc.benchmark import baseline_echoes, bench_scene
from echoloc.io.recording import Recording
from echoloc.localise.locate import model_paths_m
from echoloc.pipeline import Chain, prepare
from echoloc.sim.scene import Scene
from echoloc.sim.simulation import simulate
from echoloc.tof.echoes import (
    EchoOptions,
    _Clean,
    _compiled_echoes,
    _isolated_echoes,
    matched_filter_batch,
    matched_filter_echoes,
)


def scipy_chain(chain: Chain, frames: NDArray[np.float64]) -> list[list[NDArray[np.float64]]]:
    """Delays (s) per frame and channel by correlate + hilbert + find_peaks + parabola
    (:func:`echoloc.benchmark.baseline_echoes`, the baseline of `echoloc bench` too)."""
    c = chain.speed_of_sound_m_s
    return [[paths / c for paths in baseline_echoes(chain, frame)] for frame in frames]


def accuracy(
    recording: Recording,
    tofs: list[list[NDArray[np.float64]]],
    speed_of_sound_m_s: float,
    gate_m: float = 5e-3,
) -> tuple[float, float, float]:
    """Recall of the true echo paths (nearest echo within ``gate_m`` of path), RMSE of the
    path error of those found (mm), and the echoes per channel that match no reflector."""
    truth = recording.truth_positions_m
    assert truth is not None
    found, errors, extra, total, n_channels = 0, [], 0, 0, 0
    for index, channels in enumerate(tofs):
        paths = model_paths_m(recording.transmitters_m[0], recording.receivers_m, truth[index])
        for rx, delays in enumerate(channels):
            measured = np.asarray(delays) * speed_of_sound_m_s
            n_channels += 1
            used = np.zeros(len(measured), dtype=bool)
            for path in paths[:, rx]:
                total += 1
                if len(measured) == 0:
                    continue
                j = int(np.argmin(np.abs(measured - path)))
                if abs(measured[j] - path) <= gate_m:
                    found += 1
                    used[j] = True
                    errors.append(measured[j] - path)
            extra += int(np.sum(~used))
    rmse_mm = float(np.sqrt(np.mean(np.square(errors))) * 1e3) if errors else float("nan")
    return found / max(total, 1), rmse_mm, extra / max(n_channels, 1)


def bench(name: str, scene: Scene, n_frames: int, rounds: int, threads: int) -> None:
    chain = prepare(simulate(scene, n_frames))
    recording = chain.recording
    options: EchoOptions = chain.echo_options
    frames = np.asarray(recording.frames[:n_frames], dtype=float)
    mf = matched_filter(recording)
    rows = frames.reshape(-1, recording.n_samples)
    matched_filter_batch(frames[:1], mf, options)  # compile (or load) the kernels, build the tables
    correlation = mf.correlate_single(frames).reshape(rows.shape[0], -1)
    fast = _compiled_echoes(correlation, mf, options)
    hard = [i for i, f in enumerate(fast) if f is None]
    clean = _Clean(mf, options)
    clean_python = _Clean(mf, options, compiled=False)
    threaded = replace(options, workers=threads)
    matched_filter_batch(frames[:2], mf, threaded)  # the threaded kernels and their threads

    jobs: dict[str, Callable[[], object]] = {
        "scipy": lambda: scipy_chain(chain, frames),
        "frame": lambda: [matched_filter_echoes(frame, mf, options) for frame in frames],
        "batch": lambda: matched_filter_batch(frames, mf, options),
        "frame_threads": lambda: [matched_filter_echoes(frame, mf, threaded) for frame in frames],
        "batch_threads": lambda: matched_filter_batch(frames, mf, threaded),
        "correlation": lambda: mf.correlate_single(frames),
        "compiled": lambda: _compiled_echoes(correlation, mf, options),
        "numpy": lambda: _isolated_echoes(correlation, mf, options),
        # As matched_filter_batch runs CLEAN: the hard channels' double-precision correlation in one call.
        "clean": lambda: [clean.run(row) for row in mf.correlate(rows[hard])],
        "clean_python": lambda: [clean_python.run(row) for row in mf.correlate(rows[hard])],
    }
    timings: dict[str, list[float]] = {k: [] for k in jobs}
    for _ in range(rounds):
        for key, job in jobs.items():
            timings[key].append(seconds(job) / n_frames)
    median = {k: float(np.median(v)) * 1e6 for k, v in timings.items()}

    ours = [[c.tof_s for c in channels] for channels in matched_filter_batch(frames, mf, options)]
    theirs = scipy_chain(chain, frames)
    c = chain.speed_of_sound_m_s
    acc_ours, acc_theirs = accuracy(recording, ours, c), accuracy(recording, theirs, c)

    print(
        f"\n## {name}: {n_frames} frames x {recording.n_receivers} receivers x "
        f"{recording.n_samples} samples, median of {rounds} alternating rounds\n"
    )
    print("| what | µs/frame | scipy chain / this |")
    print("|---|---|---|")
    rows_out = (
        ("scipy chain (correlate + hilbert + find_peaks per channel)", "scipy"),
        ("echoloc `matched`, one frame per call (latency)", "frame"),
        ("echoloc `matched`, all frames in one call (throughput)", "batch"),
        (f"echoloc `matched`, one frame per call, {threads} threads (--workers)", "frame_threads"),
        (f"echoloc `matched`, all frames in one call, {threads} threads", "batch_threads"),
        ("  of which: correlation, single precision, all channels", "correlation"),
        ("  of which: batch path, compiled", "compiled"),
        ("  of which: CLEAN on the channels the batch path hands over", "clean"),
        ("  (the batch path's numpy statement, for comparison)", "numpy"),
        ("  (CLEAN's Python statement on the same channels, for comparison)", "clean_python"),
    )
    for label, key in rows_out:
        print(f"| {label} | {median[key]:.1f} | {median['scipy'] / median[key]:.1f}x |")
    print(
        f"\nChannels handed to CLEAN: {len(hard)} of {len(fast)} "
        f"({100 * len(hard) / max(len(fast), 1):.1f} %). Per-frame cost of the CLEAN channels alone: "
        f"{median['clean']:.1f} µs/frame."
    )
    print(
        f"\nAccuracy on the same frames (true echo paths, nearest echo within 5 mm of path): "
        f"echoloc recall {acc_ours[0]:.3f}, path RMSE {acc_ours[1]:.4f} mm, "
        f"{acc_ours[2]:.2f} unmatched echoes per channel; scipy chain recall {acc_theirs[0]:.3f}, "
        f"path RMSE {acc_theirs[1]:.4f} mm, {acc_theirs[2]:.2f} unmatched echoes per channel."
    )


def main() -> None:
    args = parse_arguments(
        __doc__, frames=40, rounds=7, more=[("--threads", 2, "threads of the threaded rows (--workers)")]
    )
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(
        "# bench_echoes.py — last run\n\n"
        f"`python benchmarks/bench_echoes.py --frames {args.frames} --rounds {args.rounds} "
        f"--threads {args.threads}`"
    )
    print(f"\nLoad average at start: {load:.2f} on {os.cpu_count()} cores (the machine is shared).")
    bench("Default scene (report set-up, 3 balls)", bench_scene(0), args.frames, args.rounds, args.threads)
    bench("Five random reflectors in 1 m^3", bench_scene(5), args.frames, args.rounds, args.threads)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"\nLoad average at the end: {load:.2f}.")


if __name__ == "__main__":
    main()
