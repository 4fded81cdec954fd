"""Speed of the full chain against a straightforward scipy chain and against the physics.

The scipy chain is the obvious way to write the same job:

- echoes: per channel, ``scipy.signal.correlate`` with the pulse, ``scipy.signal.hilbert``
  for the envelope, ``scipy.signal.find_peaks`` (height 5 sigma of the envelope noise,
  distance one chip) and a parabolic fit of the peak;
- locate: every combination of one echo per receiver solved by
  ``scipy.optimize.least_squares``, kept when its residual passes the chi-square gate
  echoloc uses, then taken greedily by residual.

echoloc's chain runs as a stream (:class:`echoloc.realtime.stream.StreamProcessor`, the code
``echoloc stream`` runs). Both are timed frame by frame on one core (the process
is pinned to one CPU while timing, so FFT worker threads cannot borrow the other),
and the peak of memory allocated while processing is measured with
:mod:`tracemalloc` in a separate pass (tracing slows the code down).

The physics: a frame cannot start before the echoes of the previous one have come
back. For a range of ``range_m`` the longest path is ``2 * range_m`` (out and back),
which takes ``2 * range_m / c``: 11.7 ms for 2 m at 343 m/s, at most 85 frames a
second per transmitter.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import os
import time
import tracemalloc
from collections.abc import Callable, Iterator
from dataclasses import replace
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import optimize, signal, stats

from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording
from echoloc.localise.evaluation import evaluate
from echoloc.localise.locate import FrameObjects, LocatedObject, model_paths_m
from echoloc.pipeline import Chain, prepare, samples_echoes
from echoloc.realtime.stream import STREAM_BATCH_FRAMES, StreamProcessor, recording_frames
from echoloc.sim.scene import RandomReflectors, Scene, default_scene
from echoloc.tof.echoes import EchoOptions

#: Range whose echoes one frame must wait for (the report's working volume), m.
PHYSICS_RANGE_M = 2.0


def bench_scene(reflectors: int = 5) -> Scene:
    """The default scene (the report's 4-receiver head), with ``reflectors`` random reflectors.

    0 keeps its three balls. Random reflectors lie in the cubic metre in front, with
    strengths 0.5..2, SNR 20 dB and 0.5 mm path jitter (``bench_pipeline.py``'s scene).
    """
    scene = default_scene()
    if reflectors == 0:
        return scene
    return replace(
        scene,
        reflector_positions_m=np.zeros((0, 3)),
        reflector_strengths=np.zeros(0),
        random=RandomReflectors(count=(reflectors, reflectors), strength=(0.5, 2.0)),
        snr_db=20.0,
        path_jitter_m=0.5e-3,
    )


def baseline_echoes(chain: Chain, samples: NDArray[np.floating]) -> list[NDArray[np.float64]]:
    """Paths (m) per receiver by correlate + hilbert + find_peaks + parabola."""
    recording = chain.recording
    pulse = np.asarray(recording.waveform)
    fs = recording.sample_rate_hz
    chip = round(4 / 50e3 * fs)
    result = []
    for channel in samples:
        correlation = signal.correlate(channel, pulse, mode="full")[len(pulse) - 1 :]
        envelope = np.abs(signal.hilbert(correlation))
        noise = np.median(envelope) / np.sqrt(np.log(4))
        peaks, _ = signal.find_peaks(envelope, height=5 * noise, distance=chip)
        peaks = peaks[envelope[peaks] > 0.1 * envelope.max()]
        a, b, c = envelope[peaks - 1], envelope[peaks], envelope[np.minimum(peaks + 1, len(envelope) - 1)]
        offset = 0.5 * (a - c) / np.where(a - 2 * b + c < 0, a - 2 * b + c, -1.0)
        result.append((peaks + offset) / fs * chain.speed_of_sound_m_s)
    return result


def baseline_locate(chain: Chain, index: int, paths: list[NDArray[np.float64]]) -> FrameObjects:
    """Brute force: least_squares on every combination, chi-square gate, greedy by residual."""
    recording = chain.recording
    tx, rx = recording.transmitters_m[0], recording.receivers_m
    sigma = chain.locate_options.path_sigma_m
    gate = stats.chi2.ppf(chain.locate_options.gate_probability, 1)
    found = []
    for combo in itertools.product(*[range(len(p)) for p in paths]):
        measured = np.array([paths[i][k] for i, k in enumerate(combo)])

        def residual(p: NDArray[np.float64], measured: NDArray[np.float64] = measured) -> NDArray[np.float64]:
            return (model_paths_m(tx, rx, p[None])[0] - measured) / sigma  # type: ignore[no-any-return]

        fit = optimize.least_squares(residual, x0=np.array([0.0, 0.0, np.mean(measured) / 2]))
        chi2 = float(np.sum(fit.fun**2))
        if chi2 <= gate and fit.x[2] > 0:
            found.append((chi2, combo, fit.x))
    used: list[set[int]] = [set() for _ in paths]
    objects = []
    for chi2, combo, position in sorted(found, key=lambda f: f[0]):
        if any(k in used[i] for i, k in enumerate(combo)):
            continue
        for i, k in enumerate(combo):
            used[i].add(k)
        receivers = tuple(range(len(paths)))
        objects.append(LocatedObject(position, np.eye(3) * sigma**2, receivers, combo, chi2, 1.0))
    return FrameObjects(index, 0.0, tuple(objects))


@contextlib.contextmanager
def pinned_cores(count: int = 1) -> Iterator[list[int] | None]:
    """Pin this process to ``count`` CPUs (the first it may use) for the block; yields them
    (None: pinning unsupported). Fewer when fewer are allowed."""
    if not hasattr(os, "sched_getaffinity"):
        yield None
        return
    before = os.sched_getaffinity(0)
    cpus = sorted(before)[: max(count, 1)]
    os.sched_setaffinity(0, set(cpus))
    try:
        yield cpus
    finally:
        os.sched_setaffinity(0, before)


def _frame_rate_hz(recording: Recording) -> float:
    """Frames a second the recording was taken at: its frame_times, else back-to-back frames."""
    times = recording.frame_times_s
    if times is not None and len(times) > 1:
        return float(1 / np.median(np.diff(times)))
    return recording.sample_rate_hz / recording.n_samples


def _figures(latencies_s: list[float], wall_s: float) -> dict[str, float]:
    arr = np.asarray(latencies_s)
    return {
        "frames": len(arr),
        "ms_per_frame": wall_s / len(arr) * 1e3,
        "frames_per_s": len(arr) / wall_s,
        "latency_p50_ms": float(np.percentile(arr, 50)) * 1e3,
        "latency_p99_ms": float(np.percentile(arr, 99)) * 1e3,
    }


def _peak_mib(job: Callable[[], object]) -> float:
    """Peak memory allocated while ``job`` runs, above what was allocated before, MiB."""
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        base, _ = tracemalloc.get_traced_memory()
        job()
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    return (peak - base) / 2**20


def _stream_pass(
    chain: Chain, recording: Recording, batch_frames: int
) -> tuple[float, list[float], list[FrameObjects]]:
    """One pass of a fresh :class:`StreamProcessor` over ``recording``, ``batch_frames`` frames a
    call: (wall s, each frame's latency s, its objects). A batch's frames are taken off the
    recording as it starts, so a frame's latency runs from then to when its result is made
    (:meth:`StreamProcessor.process_batch`: after the batch's one call)."""
    processor = StreamProcessor(chain)
    frames = recording_frames(recording)
    latencies: list[float] = []
    found: list[FrameObjects] = []
    start = time.perf_counter()
    while True:
        t0 = time.perf_counter()
        batch = list(itertools.islice(frames, batch_frames))
        if not batch:
            break
        results = processor.process_batch(batch)
        if batch_frames == 1:  # perf_counter's own clock; process_batch's is monotonic
            latencies.append(time.perf_counter() - t0)
        else:
            latencies += [r.latency_s for r in results]
        found += [r.objects for r in results]
    return time.perf_counter() - start, latencies, found


def bench_chains(
    recording: Recording,
    *,
    baseline_frames: int = 2,
    warmup_frames: int = 5,
    workers: int = 1,
    rounds: int = 3,
    backlog_frames: int = STREAM_BATCH_FRAMES,
) -> dict[str, Any]:
    """Time echoloc's streamed chain and the scipy chain on ``recording``; the figures as a dict.

    Both run pinned to ``workers`` cores (one by default), echoloc's echoes stage with
    that many threads (:attr:`echoloc.tof.echoes.EchoOptions.workers`); the scipy chain uses one.
    echoloc's stream makes ``rounds`` passes over the recording, one frame a call, and as many
    working off a backlog ``backlog_frames`` frames a call as ``echoloc stream`` does when
    frames queue up, the two kinds of pass alternating: its ms/frame is the median pass (this
    machine is shared, and a pass another process interrupts is an outlier), its latency
    percentiles are over every frame of every pass.
    """
    if rounds < 1:
        raise EchoLocError(f"rounds must be >= 1, got {rounds}")
    if backlog_frames < 2:  # one frame a call is the other row
        raise EchoLocError(f"backlog_frames must be >= 2, got {backlog_frames}")
    chain = prepare(recording, echo_options=EchoOptions(workers=workers))
    n = recording.n_frames
    few = min(baseline_frames, n)
    # Compile the numba kernels and warm the caches before timing.
    warm = StreamProcessor(chain)
    warm.warm_up()  # what `echoloc stream` does before its first frame
    for frame in itertools.islice(recording_frames(recording), warmup_frames):
        warm.process(frame)

    def ours() -> list[FrameObjects]:
        processor = StreamProcessor(chain)
        return [processor.process(frame).objects for frame in recording_frames(recording)]

    def theirs() -> list[FrameObjects]:
        return [baseline_locate(chain, i, baseline_echoes(chain, recording.frames[i])) for i in range(few)]

    with pinned_cores(workers) as cpus:
        passes: dict[int, list[tuple[float, list[float], list[FrameObjects]]]] = {1: [], backlog_frames: []}
        for _ in range(rounds):
            for batch_frames in passes:
                wall, latencies, found = _stream_pass(chain, recording, batch_frames)
                # The first pass's objects are kept for recall; later ones are dropped, as a
                # stream drops what it has sent (kept, they made Python's collector ever slower).
                passes[batch_frames].append((wall, latencies, found if not passes[batch_frames] else []))
        base_latencies: list[float] = []
        base_found: list[FrameObjects] = []
        base_start = time.perf_counter()
        for i in range(few):
            t0 = time.perf_counter()
            base_found.append(baseline_locate(chain, i, baseline_echoes(chain, recording.frames[i])))
            base_latencies.append(time.perf_counter() - t0)
        base_wall = time.perf_counter() - base_start
        # The echoes stage alone, both ways, on every frame (the scipy locate is the slow part).
        # The stream finds echoes and objects in one compiled call: the echoes' own kernel is
        # loaded first, untimed (its loading would otherwise swamp this figure).
        samples_echoes(chain, recording.frames[0], 0, 0.0)
        stage_start = time.perf_counter()
        for i in range(n):
            samples_echoes(chain, recording.frames[i], i, 0.0)
        echoes_s = (time.perf_counter() - stage_start) / n
        stage_start = time.perf_counter()
        for i in range(n):
            baseline_echoes(chain, recording.frames[i])
        base_echoes_s = (time.perf_counter() - stage_start) / n

    def stream_figures(runs: list[tuple[float, list[float], list[FrameObjects]]]) -> dict[str, Any]:
        walls = [wall for wall, _, _ in runs]
        latencies = np.asarray([t for _, pass_latencies, _ in runs for t in pass_latencies])
        median_s = float(np.median(walls))
        return {
            "frames": n,
            "rounds": len(runs),
            "ms_per_frame": median_s / n * 1e3,
            "frames_per_s": n / median_s,
            "ms_per_frame_range": [min(walls) / n * 1e3, max(walls) / n * 1e3],
            "latency_p50_ms": float(np.percentile(latencies, 50)) * 1e3,
            "latency_p99_ms": float(np.percentile(latencies, 99)) * 1e3,
        }

    echoloc_figures = stream_figures(passes[1])
    echoloc_figures["peak_mib"] = _peak_mib(lambda: ours()[: min(n, 50)])
    backlog_figures = stream_figures(passes[backlog_frames])
    backlog_figures["batch_frames"] = backlog_frames
    baseline_figures = _figures(base_latencies, base_wall)
    baseline_figures["peak_mib"] = _peak_mib(theirs)
    truth = recording.truth_positions_m
    if truth is not None:
        results_of = ((echoloc_figures, passes[1][0][2]), (backlog_figures, passes[backlog_frames][0][2]))
        for figures, results in (*results_of, (baseline_figures, base_found)):
            report = evaluate(results, truth)
            figures["recall"] = float(report.recall)
            figures["false_rate"] = float(report.false_rate)
    c = chain.speed_of_sound_m_s
    physics_fps = c / (2 * PHYSICS_RANGE_M)
    try:
        import resource

        max_rss_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    except ImportError:  # not on this platform
        max_rss_mib = math.nan
    return {
        "frames": n,
        "receivers": recording.n_receivers,
        "samples": recording.n_samples,
        "objects": int(np.isfinite(truth[0, :, 0]).sum()) if truth is not None else None,
        "cpu": None if cpus is None else cpus[0],
        "cpus": cpus,
        "workers": workers,
        "speed_of_sound_m_s": c,
        "physics_frames_per_s": physics_fps,
        "recording_frames_per_s": _frame_rate_hz(recording),
        "echoloc": echoloc_figures,
        "echoloc_backlog": backlog_figures,
        "scipy": baseline_figures,
        "speedup": baseline_figures["ms_per_frame"] / echoloc_figures["ms_per_frame"],
        "echoes_ms_per_frame": echoes_s * 1e3,
        "scipy_echoes_ms_per_frame": base_echoes_s * 1e3,
        "times_physics": echoloc_figures["frames_per_s"] / physics_fps,
        "backlog_times_physics": backlog_figures["frames_per_s"] / physics_fps,
        "process_max_rss_mib": max_rss_mib,
    }


def _cores_text(report: dict[str, Any]) -> str:
    """Where the bench ran: "one core (CPU 0)", "2 cores (CPUs 0, 1), echoes on 2 threads"."""
    cpus = report.get("cpus")
    workers = int(report.get("workers", 1))
    threads = "" if workers == 1 else f", echoes on {workers} threads"
    if cpus is None:
        return f"cores not pinned (unsupported here){threads}"
    if len(cpus) == 1:
        return f"one core (CPU {cpus[0]}){threads}"
    return f"{len(cpus)} cores (CPUs {', '.join(map(str, cpus))}){threads}"


def format_bench(report: dict[str, Any]) -> str:
    """The figures as a Markdown table and two lines of ratios."""
    lines = [
        f"Full chain (echoes + locate), {report['frames']} frames of {report['receivers']} receivers x "
        f"{report['samples']} samples, {report['objects']} objects, {_cores_text(report)}:",
        "",
        "| chain | frames | ms/frame | frames/s | latency p50 ms | latency p99 ms | peak MiB | recall |",
        "|---|---|---|---|---|---|---|---|",
    ]
    backlog = report["echoloc_backlog"]
    rows = (
        ("echoloc", "echoloc (stream, a frame a call)"),
        ("echoloc_backlog", f"echoloc (stream, a backlog {backlog['batch_frames']} frames a call)"),
        ("scipy", "straightforward scipy"),
    )
    for name, label in rows:
        f = report[name]
        recall = f"{f['recall']:.3f}" if "recall" in f else "-"
        peak = f"{f['peak_mib']:.2f}" if "peak_mib" in f else "-"
        lines.append(
            f"| {label} | {f['frames']} | {f['ms_per_frame']:.3f} | {f['frames_per_s']:.1f} | "
            f"{f['latency_p50_ms']:.3f} | {f['latency_p99_ms']:.3f} | {peak} | {recall} |"
        )
    low, high = report["echoloc"]["ms_per_frame_range"]
    low_b, high_b = backlog["ms_per_frame_range"]
    lines += [
        "",
        f"echoloc's ms/frame is the median of {report['echoloc']['rounds']} passes over the frames "
        f"(a frame a call: {low:.3f}-{high:.3f} ms; a backlog: {low_b:.3f}-{high_b:.3f} ms); "
        "its latencies are over every pass.",
        "",
        f"The echoes stage alone, every frame: echoloc {report['echoes_ms_per_frame']:.3f} ms, "
        f"scipy (correlate + hilbert + find_peaks) {report['scipy_echoes_ms_per_frame']:.3f} ms a frame.",
        "",
        f"echoloc is {report['speedup']:.1f}x the scipy chain, and {report['times_physics']:.1f}x the "
        f"{report['physics_frames_per_s']:.1f} frames/s that sound allows one transmitter for "
        f"{PHYSICS_RANGE_M:g} m of range (c = {report['speed_of_sound_m_s']:.1f} m/s) a frame a call, "
        f"{report['backlog_times_physics']:.1f}x working off a backlog; "
        f"this recording's frames come at {report['recording_frames_per_s']:.1f} frames/s.",
    ]
    return "\n".join(lines)
