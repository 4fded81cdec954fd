"""The batch path's noise median: radix selection on the bits against the quickselect.

Every channel of every frame takes its noise power from the median of its correlation's power
at every second lag (600 values for 2400 samples). Since 2026-12-05 that median is found by
radix selection on the values' IEEE-754 bits (:func:`echoloc.tof._echoes_kernels._noise_median`)
instead of the branch-free quickselect (:func:`echoloc.tof._echoes_kernels._median_in`), which it
still falls back to. This times both in compiled loops over the same rows, alternating rounds
(medians reported), on noise powers with echo peaks like a channel's, and checks that they
agree with numpy's median.

    python benchmarks/bench_noise_median.py [--rows 64] [--values 600] [--rounds 7]
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Any

import numpy as np
from numba import njit
from numba.typed import List

from echoloc.benchmark import pinned_cores
from echoloc.tof._echoes_kernels import _EXPONENT_BUCKETS, _MANTISSA_BUCKETS, _median_in, _noise_median


@njit(cache=True)
def _quickselect_rows(rows: Any, scratch: Any) -> float:  # pragma: no cover - compiled
    total = 0.0
    for row in rows:
        total += _median_in(row, scratch[0], scratch[1], scratch[2])
    return total


@njit(cache=True)
def _radix_rows(rows: Any, counts: Any, scratch: Any) -> float:  # pragma: no cover - compiled
    total = 0.0
    for row in rows:
        total += _noise_median(row, counts, scratch)
    return total


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=64)
    parser.add_argument("--values", type=int, default=600)
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args()
    rng = np.random.default_rng(0)
    rows = List()
    for _ in range(args.rows):
        noise = rng.normal(size=args.values) + 1j * rng.normal(size=args.values)
        power = np.abs(noise) ** 2 * 10 ** rng.uniform(-3, 3)
        power[rng.integers(0, args.values, 10)] *= 1e4  # echoes' peaks
        rows.append(power)
    scratch = np.zeros((3, args.values))
    counts = np.zeros(_EXPONENT_BUCKETS + _MANTISSA_BUCKETS, dtype=np.int32)
    ways = {
        "quickselect": lambda: _quickselect_rows(rows, scratch),
        "radix": lambda: _radix_rows(rows, counts, scratch),
    }
    same = all(_noise_median(row, counts, scratch) == np.median(row) for row in rows)
    times: dict[str, list[float]] = {name: [] for name in ways}
    with pinned_cores(1) as cores:
        for _ in range(args.rounds):
            for name, way in ways.items():
                started = time.perf_counter()
                for _ in range(100):
                    way()
                times[name].append((time.perf_counter() - started) / (100 * args.rows) * 1e6)
    quick, radix = statistics.median(times["quickselect"]), statistics.median(times["radix"])
    print(f"Median of {args.values} noise powers, {args.rows} rows, CPU {cores}, {args.rounds} rounds:")
    print(f"quickselect {quick:.2f} µs, radix {radix:.2f} µs ({quick / radix:.2f}x); numpy's median: {same}")


if __name__ == "__main__":
    main()
