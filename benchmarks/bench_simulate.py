"""Simulator speed (frames/s) beside a straightforward per-echo simulator, and its memory on disk runs.

The case of the issue: 4 receivers, 5 point reflectors, 2400 samples per frame at
200 kHz, Barker-13 × 4 at 50 kHz, white noise. Both simulators make the same frames
(checked: the largest difference is reported) in alternating rounds on this shared,
noisy machine; the median of the rounds is reported with the ratio.

The baseline is what one writes first: for every frame, receiver and reflector, the
path length, then the pulse delayed by that exact time through its FFT
(``irfft(rfft(pulse) exp(-2j pi f tau))``) and added into the frame, then the noise.

Memory: ``simulate_to_file`` writes N frames to an HDF5 file in a child process whose
peak resident memory (``ru_maxrss``) is reported for two N ten times apart; flat memory
means the same peak for both.

    python benchmarks/bench_simulate.py [--frames 512] [--rounds 5] [--disk-frames 10000 100000]
"""

from __future__ import annotations

import argparse
import os
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import scipy.fft

from echoloc.sim.scene import REPORT_ARRAY, RandomReflectors, Scene
from echoloc.sim.simulation import path_lengths_m, simulate, simulate_batches

BENCH_SCENE = Scene(
    array=REPORT_ARRAY,
    random=RandomReflectors(count=(5, 5), z_m=(0.3, 1.2)),
    snr_db=20.0,
    seed=7,
)


def baseline_frames(scene: Scene, truth_m: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Frames by one FFT fractional delay per echo (per frame, receiver and reflector), plus noise."""
    pulse = scene.returned_pulse()
    fs, n = scene.sample_rate_hz, scene.n_samples
    n_fft = scipy.fft.next_fast_len(n + 2 * len(pulse) + 128, real=True)
    spectrum = scipy.fft.rfft(pulse, n_fft)
    freqs = scipy.fft.rfftfreq(n_fft, 1 / fs)
    c = scene.speed_of_sound_m_s
    tx = scene.array.transmitters_m[0]
    receivers = scene.array.receivers_m
    frames = np.zeros((len(truth_m), len(receivers), n))
    for f, points in enumerate(truth_m):
        for r, receiver in enumerate(receivers):
            for point in points:
                if not np.all(np.isfinite(point)):
                    continue
                path, r_tx, r_rx = path_lengths_m(tx, receiver[None, :], point)
                echo = scipy.fft.irfft(spectrum * np.exp(-2j * np.pi * freqs * path[0] / c), n_fft)[:n]
                frames[f, r] += echo / (r_tx * r_rx[0])
    if scene.snr_db is None:
        return frames
    return frames + rng.normal(0.0, 10 ** (-scene.snr_db / 20), frames.shape)


def rounds(n_frames: int, n_rounds: int) -> None:
    noiseless = simulate(replace(BENCH_SCENE, snr_db=None), n_frames)
    assert noiseless.truth_positions_m is not None
    truth = noiseless.truth_positions_m
    rng = np.random.default_rng(1)
    clean = baseline_frames(replace(BENCH_SCENE, snr_db=None), truth, rng)
    worst = float(np.max(np.abs(clean - noiseless.frames)) / np.max(np.abs(clean)))
    echoloc_s, baseline_s = [], []
    for _ in range(n_rounds):
        start = time.perf_counter()
        for _batch in simulate_batches(BENCH_SCENE, n_frames):
            pass
        echoloc_s.append(time.perf_counter() - start)
        start = time.perf_counter()
        baseline_frames(BENCH_SCENE, truth, rng)
        baseline_s.append(time.perf_counter() - start)
    ours, theirs = float(np.median(echoloc_s)), float(np.median(baseline_s))
    case = "frames/s, 4 rx × 5 reflectors × 2400 samples"
    print(f"| {case} | {n_frames / ours:,.0f} | {n_frames / theirs:,.0f} | {theirs / ours:.1f}× |")
    print(f"(largest sample difference between the two, noiseless: {worst:.1e} of the largest sample; "
          f"median of {n_rounds} rounds of {n_frames} frames)")  # fmt: skip


_CHILD = """
import resource, sys, time
from echoloc.sim.simulation import simulate_to_file
sys.path.insert(0, {bench_dir!r})
from bench_simulate import BENCH_SCENE
start = time.perf_counter()
simulate_to_file(BENCH_SCENE, {n}, {path!r})
elapsed = time.perf_counter() - start
print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss, elapsed)
"""


def memory(frame_counts: list[int]) -> None:
    print("| frames written to .h5 | peak RSS MiB | seconds | frames/s | file GB |")
    print("|---|---|---|---|---|")
    with tempfile.TemporaryDirectory(dir=Path.cwd()) as tmp:
        for n in frame_counts:
            path = os.path.join(tmp, "bench.h5")
            code = _CHILD.format(bench_dir=str(Path(__file__).parent), n=n, path=path)
            out = subprocess.run([sys.executable, "-c", code], check=True, capture_output=True, text=True)
            rss_kib, seconds = out.stdout.split()
            size_gb = os.path.getsize(path) / 1e9
            print(f"| {n:,} | {int(rss_kib) / 1024:.0f} | {float(seconds):.1f} | "
                  f"{n / float(seconds):,.0f} | {size_gb:.2f} |")  # fmt: skip
            os.remove(path)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=512)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--disk-frames", type=int, nargs="*", default=[10_000, 100_000])
    args = parser.parse_args()
    print(f"python {sys.version.split()[0]}, numpy {np.__version__}, scipy {scipy.__version__}, "
          f"{os.cpu_count()} CPUs; this process's peak RSS before: "
          f"{resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024:.0f} MiB")  # fmt: skip
    print()
    print("| case | echoloc | per-echo FFT baseline | speed-up |")
    print("|---|---|---|---|")
    rounds(args.frames, args.rounds)
    print()
    if args.disk_frames:
        memory(args.disk_frames)


if __name__ == "__main__":
    main()
