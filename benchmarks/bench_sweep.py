"""`echoloc sweep` on a LocalCluster of 1 and 2 workers, against the same points run serially in-process.

A 200-point grid on the report's three balls (`echoloc demo`'s scene): 20 SNRs x 2 codes x
5 receiver spacings, ``--frames`` frames a point (small, so that the cost of a task shows).
The points run three ways, each timed on its own (best of ``--rounds``):

1. serially in this process (:func:`echoloc.scale.sweep.run_sweep_serial`), after one point
   to load the kernels: the cost of a point without any cluster;
2. as Dask tasks on a LocalCluster of 1 worker process (:func:`echoloc.scale.sweep.run_sweep`),
   a point a task and grouped as ``run_sweep`` groups small points: that, less the serial
   time, is the overhead of the cluster a point (pickling the points, scheduling, sending the
   rows back);
3. the same on 2 workers: the speed-up over 1 worker.

The cluster's start-up (processes spawned, kernels loaded from numba's cache) is timed apart.
Both clusters run again with the ``MALLOC_TRIM_THRESHOLD_`` dask's nanny sets in its workers
unset: glibc then keeps its dynamic mmap threshold, and a numpy-heavy task no longer pays page
faults for every large array. Every table must agree byte for byte with the serial one (all
but ``time_per_frame_s``), and the script checks that they do.

    OMP_NUM_THREADS=1 python benchmarks/bench_sweep.py --frames 16 --rounds 2 \
        --markdown benchmarks/results/sweep.md
"""

from __future__ import annotations

import argparse
import datetime
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import dask
import numpy as np

from echoloc.scale.cluster import open_client
from echoloc.scale.sweep import (
    Sweep,
    csv_text,
    points_per_task,
    run_point,
    run_sweep,
    run_sweep_serial,
    sweep_from_dict,
)

METRICS = ["median_error_m", "rms_error_m", "spread_m", "recall", "false_rate"]


def bench_sweep(frames: int) -> Sweep:
    """The 200 points: 20 SNRs x 2 codes x 5 spacings of the report's cross."""
    return sweep_from_dict(
        {
            "scene": "report-three-balls",
            "frames": frames,
            "seed": 1,
            "metrics": METRICS,
            "processing": {"estimator": "matched"},
            "array_layout": {"kind": "cross"},
            "grid": {
                "noise": {"snr_db": [float(v) for v in range(0, 40, 2)]},
                "pulse": {"code": ["barker13", "golay16a"]},
                "array": {"spacing_m": [0.1, 0.15, 0.2, 0.25, 0.3]},
            },
        },
        source="bench_sweep",
    )


def timed_serial(sweep: Sweep) -> str:
    """The table in-process, after one point to load the kernels and warm the caches."""
    run_point(sweep.study, sweep.points[0])
    return csv_text(sweep, run_sweep_serial(sweep))


Timing = tuple[float, dict[str, float], list[str]]
"""A cluster's start-up seconds, its best sweep seconds by grouping, and its tables."""


def timed_cluster(sweep: Sweep, workers: int, rounds: int, trim: bool = True) -> Timing:
    """On a LocalCluster of ``workers``: the sweep a point a task, grouped as :func:`run_sweep`
    groups by default, and serially in this process alongside; ``trim=False``: without the
    ``MALLOC_TRIM_THRESHOLD_`` dask's nanny sets in its workers."""
    import distributed  # noqa: F401  (its configuration, before it is changed)

    settings = {} if trim else {"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}
    if not trim:
        # A nanny sets its workers' variables in its own process's environment too, which
        # every later worker inherits: take it out again.
        os.environ.pop("MALLOC_TRIM_THRESHOLD_", None)
    start = time.perf_counter()
    best: dict[str, float] = {}
    tables: list[str] = []
    with dask.config.set(settings), open_client(workers=workers) as client:
        client.wait_for_workers(workers)
        startup = time.perf_counter() - start
        # Interleaved with the serial run, round by round: the machine is shared, and what
        # else runs on it changes over minutes.
        ways: dict[str, Callable[[], list[dict[str, Any]]]] = {
            "serial": lambda: run_sweep_serial(sweep),
            "a point a task": lambda: run_sweep(sweep, client, group=1),
            "grouped": lambda: run_sweep(sweep, client),
        }
        best = dict.fromkeys(ways, np.inf)
        for _ in range(rounds):
            for name, way in ways.items():
                start = time.perf_counter()
                rows = way()
                best[name] = min(best[name], time.perf_counter() - start)
                tables.append(csv_text(sweep, rows))
    return startup, best, tables


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=16, help="frames a point")
    parser.add_argument("--rounds", type=int, default=2, help="runs of each way; the best is kept")
    parser.add_argument("--markdown", type=Path, default=None, help="also write the results here")
    args = parser.parse_args()
    sweep = bench_sweep(args.frames)
    n = len(sweep.points)
    serial_table = timed_serial(sweep)
    runs = {(w, trim): timed_cluster(sweep, w, args.rounds, trim) for trim in (True, False) for w in (1, 2)}
    same = all(table == serial_table for _, _, tables in runs.values() for table in tables)
    load = os.getloadavg()
    lines: list[str] = [
        "# bench_sweep.py — last run",
        "",
        f"`OMP_NUM_THREADS=1 python benchmarks/bench_sweep.py --frames {args.frames} --rounds "
        f"{args.rounds}` on {datetime.date.today().isoformat()}, this project's shared "
        f"{os.cpu_count()}-core machine (load average {load[0]:.2f} when it ended: another job "
        "shared it at times).",
        "",
        f"python {sys.version.split()[0]}, numpy {np.__version__}; {n} points (20 SNRs x 2 codes x 5 "
        f"spacings of the report's cross, the three balls of `echoloc demo`), {args.frames} frames a "
        f"point, {n * args.frames} frames in all. Each cluster runs the sweep a point a task, then "
        f"grouped ({points_per_task(args.frames, n, 1)} points a task on 1 worker, "
        f"{points_per_task(args.frames, n, 2)} on 2: `points_per_task`), and the same points run "
        f"serially in this process alongside, round by round; best of {args.rounds} rounds each.",
        "",
        "| workers | worker environment | start-up s | serial s | a point a task s | grouped s | "
        "overhead a point, a point a task | grouped | grouped vs serial |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for trim in (True, False):
        for workers in (1, 2):
            startup, best, _ = runs[workers, trim]
            environment = "as dask sets it" if trim else "MALLOC_TRIM_THRESHOLD_ unset"
            serial = best["serial"]
            each = 1e3 * (best["a point a task"] - serial) / n
            grouped = 1e3 * (best["grouped"] - serial) / n
            overheads = f"{each:+.1f} ms | {grouped:+.1f} ms" if workers == 1 else "- | -"
            each_s, grouped_s = best["a point a task"], best["grouped"]
            lines.append(
                f"| {workers} | {environment} | {startup:.1f} | {serial:.2f} | {each_s:.2f} | "
                f"{grouped_s:.2f} | {overheads} | {serial / grouped_s:.2f}x |"
            )

    def overhead(trim: bool, way: str) -> float:
        best = runs[1, trim][1]
        return 1e3 * (best[way] - best["serial"]) / n

    def speed_up(trim: bool) -> float:
        return runs[1, trim][1]["grouped"] / runs[2, trim][1]["grouped"]

    point_ms = 1e3 * min(run[1]["serial"] for run in runs.values()) / n
    lines += [
        "",
        f"- A point of {args.frames} frames takes {point_ms:.1f} ms in-process (the best serial run).",
        f"- Overhead a point on 1 worker, MALLOC_TRIM_THRESHOLD_ unset, against the serial run "
        f"alongside: **{overhead(False, 'a point a task'):+.1f} ms** a point a task, "
        f"**{overhead(False, 'grouped'):+.1f} ms** grouped; as dask sets the environment, "
        f"{overhead(True, 'a point a task'):+.1f} ms and {overhead(True, 'grouped'):+.1f} ms.",
        f"- Speed-up of 2 workers over 1, grouped: **{speed_up(True):.2f}x** "
        f"({speed_up(False):.2f}x with MALLOC_TRIM_THRESHOLD_ unset).",
        "- dask's nanny puts `MALLOC_TRIM_THRESHOLD_=65536` in its workers' environment "
        "(`distributed.nanny.pre-spawn-environ`): glibc then gives up its dynamic mmap threshold "
        "and every array over 128 kB is a fresh mmap, page faults and all.",
        f"- Every table agrees byte for byte with the serial one (all columns but "
        f"time_per_frame_s): **{same}**.",
        "",
    ]
    text = "\n".join(lines)
    print(text)
    if args.markdown is not None:
        args.markdown.write_text(text)
    if not same:
        raise SystemExit("the tables differ")


if __name__ == "__main__":
    main()
