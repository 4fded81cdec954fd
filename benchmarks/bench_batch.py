"""`echoloc batch locate` on many recordings with one worker and with two, beside the serial command.

Simulates ``--files`` recordings of ``--frames`` frames once (five random reflectors in the
cubic metre, 4 receivers x 2400 samples, a seed each) into a temporary folder, then times,
in alternating rounds, as a user runs them (console scripts, wall clock):

- ``echoloc locate FILE --json > FILE.jsonl`` on one of the files (the serial command);
- ``echoloc batch locate FOLDER -o OUT --workers 1`` and ``--workers 2`` (a LocalCluster on
  127.0.0.1 started and stopped inside each run), ``--chunk-frames`` frames a task;
- starting and stopping a LocalCluster of 1 and of 2 workers alone (its share of a run).

It prints the speed-up from 1 to 2 workers and the batch's overhead against the serial
command run once per file, and checks the batch's output for the timed file is the serial
one, byte for byte. ``--markdown PATH`` writes the report.

    python benchmarks/bench_batch.py [--files 20] [--frames 1000] [--rounds 2] [--chunk-frames 256]
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from echoloc.benchmark import bench_scene
from echoloc.sim.simulation import simulate_to_file


def _echoloc() -> str:
    return shutil.which("echoloc") or str(Path(sys.executable).with_name("echoloc"))


def _timed(command: list[str], stdout: Path | None = None) -> float:
    """Wall-clock seconds of ``command``, which must succeed; its stdout to ``stdout`` (or dropped)."""
    start = time.perf_counter()
    with open(stdout or os.devnull, "wb") as out:
        completed = subprocess.run(command, stdout=out, stderr=subprocess.PIPE, check=False)
    seconds = time.perf_counter() - start
    if completed.returncode != 0:
        raise SystemExit(f"{' '.join(command)} failed:\n{completed.stderr.decode(errors='replace')}")
    return seconds


def _cluster_seconds(workers: int) -> float:
    """Starting and stopping a LocalCluster of ``workers`` (with echoloc's kernels loaded)."""
    code = (
        "from echoloc.scale.cluster import open_client\n"
        f"with open_client(workers={workers}) as client:\n"
        "    client.run(lambda: None)\n"
    )
    return _timed([sys.executable, "-c", code])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--files", type=int, default=20)
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--chunk-frames", type=int, default=256)
    parser.add_argument("--reflectors", type=int, default=5)
    parser.add_argument("--markdown", type=Path, default=None)
    args = parser.parse_args()

    echoloc = _echoloc()
    work = Path(tempfile.mkdtemp(prefix="echoloc-bench-batch-"))
    try:
        inputs = work / "in"
        inputs.mkdir()
        started = time.perf_counter()
        scene = bench_scene(args.reflectors)
        for k in range(args.files):
            simulate_to_file(
                dataclasses.replace(scene, seed=1000 + k), args.frames, inputs / f"rec{k:02d}.h5"
            )
        simulate_s = time.perf_counter() - started
        size_mb = sum(p.stat().st_size for p in inputs.iterdir()) / 1e6
        print(
            f"simulated {args.files} x {args.frames} frames ({size_mb:.0f} MB) in {simulate_s:.1f} s",
            flush=True,
        )
        one = inputs / "rec00.h5"
        serial_out = work / "serial.jsonl"
        _timed([echoloc, "locate", str(one), "--json"], serial_out)  # page cache and kernels warm

        times: dict[str, list[float]] = {"serial": [], "w1": [], "w2": [], "cluster1": [], "cluster2": []}
        for round_ in range(args.rounds):
            for workers in (1, 2):
                out = work / f"out{workers}"
                command = [
                    echoloc, "batch", "locate", str(inputs), "-o", str(out), "--workers", str(workers),
                    "--chunk-frames", str(args.chunk_frames), "--force",
                ]  # fmt: skip
                times[f"w{workers}"].append(_timed(command))
                times[f"cluster{workers}"].append(_cluster_seconds(workers))
            times["serial"].append(_timed([echoloc, "locate", str(one), "--json"], serial_out))
            print(
                f"round {round_ + 1}: serial one file {times['serial'][-1]:.2f} s, batch 1 worker "
                f"{times['w1'][-1]:.1f} s, 2 workers {times['w2'][-1]:.1f} s; clusters alone "
                f"{times['cluster1'][-1]:.1f} s, {times['cluster2'][-1]:.1f} s",
                flush=True,
            )
        same = all(
            (work / f"out{w}" / "rec00.locate.jsonl").read_bytes() == serial_out.read_bytes() for w in (1, 2)
        )
        load = os.getloadavg()
    finally:
        shutil.rmtree(work, ignore_errors=True)

    median = {name: statistics.median(values) for name, values in times.items()}
    frames = args.files * args.frames
    serial_all = median["serial"] * args.files
    rows = [
        ("`echoloc locate FILE --json`, one file", median["serial"], args.frames),
        (f"the same, once per file ({args.files} runs, estimated)", serial_all, frames),
        ("`echoloc batch locate`, 1 worker", median["w1"], frames),
        ("`echoloc batch locate`, 2 workers", median["w2"], frames),
    ]
    lines = [
        "# bench_batch.py — last run",
        "",
        f"`python benchmarks/bench_batch.py --files {args.files} --frames {args.frames} "
        f"--rounds {args.rounds} --chunk-frames {args.chunk_frames}` on {time.strftime('%Y-%m-%d')}, "
        "this project's shared "
        f"2-core machine (load average {load[0]:.2f} / {load[1]:.2f} / {load[2]:.2f} at the end: other "
        "people's jobs ran at the same time).",
        "",
        f"{args.files} recordings of {args.frames} frames (4 receivers x 2400 samples, float64, "
        f"{args.reflectors} random reflectors in the cubic metre; {size_mb:.0f} MB of HDF5), simulated once "
        f"in {simulate_s:.1f} s. Wall clock of the console scripts as a user runs them, median of "
        f"{args.rounds} alternating rounds; a batch run includes starting and stopping its LocalCluster "
        f"on 127.0.0.1 and the workers loading echoloc's kernels.",
        "",
        "| run | wall s | frames/s |",
        "|---|---|---|",
        *(f"| {name} | {seconds:.2f} | {n / seconds:.0f} |" for name, seconds, n in rows),
        "",
        f"Starting and stopping the LocalCluster alone: {median['cluster1']:.1f} s (1 worker), "
        f"{median['cluster2']:.1f} s (2 workers).",
        "",
        f"- Speed-up from 1 to 2 workers: {median['w1'] / median['w2']:.2f}x "
        f"({(median['w1'] - median['cluster1']) / (median['w2'] - median['cluster2']):.2f}x without the "
        "cluster's start and stop).",
        "- Against the serial command run once per file: 1 worker takes "
        f"{median['w1'] / serial_all:.2f}x its time, 2 workers {median['w2'] / serial_all:.2f}x.",
        "- The batch's output for rec00.h5 is the serial command's stdout, byte for byte: "
        f"{'yes' if same else 'NO'}.",
    ]
    print("\n".join(lines))
    if args.markdown is not None:
        args.markdown.write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
