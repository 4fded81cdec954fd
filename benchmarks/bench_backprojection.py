"""Back-projection of 1 m^3 at 5 mm per frame: coarse-to-fine against the brute-force full grid.

Scene: ``random-1m3`` (the report's array: T at the origin, four
receivers 0.25 m away on x and y) with 1 to 6 point reflectors per frame. Grid: x, y
in +-0.5 m, z 0.2-1.2 m, 5 mm voxels (200^3 = 8 million voxels, 4 channels).

What is timed, per frame, side by side in one run (alternating rounds, median of
the rounds' means):

- ``search``: every voxel whose image value (4th-largest channel SNR) reaches the
  14 dB threshold, coarse to fine (:func:`echoloc.localise.backprojection.search`) against
  the full 5 mm grid (:func:`echoloc.localise.backprojection.brute_force_image`);
- ``objects``: the whole back-projection step of a frame, image -> peaks -> paths ->
  Gauss-Newton -> objects (:func:`echoloc.localise.backprojection.locate_channels`), with
  either search; both must return the same objects;
- ``signals``: what both need first and is not back-projection: conditioning, the
  matched filter and the CLEAN-restored envelopes (it runs the echo finder of
  :mod:`echoloc.tof.echoes`), timed once for reference.

The brute force runs on ``--brute-frames`` frames only (it takes about a second per
frame); coarse-to-fine is timed on the same frames and on all of them.

    python benchmarks/bench_backprojection.py --frames 100 --rounds 5 --brute-frames 10
"""

from __future__ import annotations

import argparse
import statistics
import time
import tomllib
from collections.abc import Callable
from dataclasses import replace
from datetime import date
from pathlib import Path

import numpy as np

from echoloc.localise.backprojection import (
    BackprojectionOptions,
    Backprojector,
    brute_force_image,
    channel_signals,
    envelopes,
    locate_channels,
    prepare_backprojection,
    search,
)
from echoloc.localise.locate import LocatedObject
from echoloc.sim.scenefile import scene_from_dict
from echoloc.sim.simulation import simulate

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).resolve().parent / "results" / "backprojection.md"

Signals = tuple[np.ndarray, np.ndarray, list[tuple[np.ndarray, np.ndarray]] | None]


def _objects(bp: Backprojector, options: BackprojectionOptions, item: Signals) -> list[LocatedObject]:
    channels, signals, components = item
    models = [bp.models[int(t)] for t in bp.channel_transmitters[channels]]
    return locate_channels(
        bp.table,
        signals.copy(),
        channels,
        models,
        options,
        components=components,
        channel_receivers=bp.channel_receivers,
    )


def _per_frame(job: Callable[[Signals], object], items: list[Signals]) -> float:
    start = time.perf_counter()
    for item in items:
        job(item)
    return (time.perf_counter() - start) / len(items)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--brute-frames", type=int, default=10)
    parser.add_argument("--seed", type=int, default=17)
    args = parser.parse_args()

    data = tomllib.loads((ROOT / "src" / "echoloc" / "scenes" / "random-1m3.toml").read_text())
    data["random_reflectors"]["count"] = [1, 6]
    data["seed"] = args.seed
    recording = simulate(scene_from_dict(data, "random-1m3.toml (1-6 reflectors)"), args.frames)

    start = time.perf_counter()
    bp = prepare_backprojection(recording)
    build_s = time.perf_counter() - start
    table = bp.table
    fine_options = bp.options
    brute_options = replace(fine_options, brute_force=True)
    k = 4
    threshold = 10 ** (fine_options.threshold_db / 20)

    start = time.perf_counter()
    items: list[Signals] = [channel_signals(bp, i) for i in range(recording.n_frames)]
    signals_s = (time.perf_counter() - start) / recording.n_frames
    few = items[: args.brute_frames]

    def search_fine(item: Signals) -> np.ndarray:
        env = envelopes(item[0], np.abs(item[1]), table)
        return search(table, env, k, threshold)[0]

    def search_brute(item: Signals) -> np.ndarray:
        env = envelopes(item[0], np.abs(item[1]), table)
        image = brute_force_image(table, env, k).ravel()
        return np.flatnonzero(image >= threshold)

    # Same answers first: the voxels above threshold, and the objects.
    same_voxels = all(np.array_equal(np.sort(search_fine(item)), search_brute(item)) for item in few)
    same_objects = True
    for item in few:
        a = _objects(bp, fine_options, item)
        b = _objects(bp, brute_options, item)
        same_objects &= len(a) == len(b) and all(
            np.array_equal(x.position_m, y.position_m) for x, y in zip(a, b, strict=True)
        )

    jobs: dict[str, tuple[Callable[[Signals], object], list[Signals]]] = {
        "search, coarse-to-fine": (search_fine, few),
        "search, brute force": (search_brute, few),
        "objects, coarse-to-fine": (lambda item: _objects(bp, fine_options, item), few),
        "objects, brute force": (lambda item: _objects(bp, brute_options, item), few),
        "objects, coarse-to-fine, all frames": (lambda item: _objects(bp, fine_options, item), items),
    }
    timings: dict[str, list[float]] = {name: [] for name in jobs}
    for _ in range(args.rounds):
        for name, (job, frames) in jobs.items():
            timings[name].append(_per_frame(job, frames))
    median = {name: statistics.median(values) for name, values in timings.items()}
    refined = [len(search_fine(item)) for item in items]
    counts = np.sum(np.isfinite(recording.truth_positions_m[:, :, 0]), axis=1)  # type: ignore[index]

    lines = [
        "# bench_backprojection.py — last run",
        "",
        f"`python benchmarks/bench_backprojection.py --frames {args.frames} --rounds {args.rounds} "
        f"--brute-frames {args.brute_frames}` on {date.today()}, this project's shared 2-core machine "
        "(other people's jobs ran at the same time; the ratios matter more than the absolute times).",
        "",
        f"Scene: random-1m3 with 1-6 reflectors ({counts.mean():.1f} per frame on average), "
        f"{recording.n_frames} frames. Grid {table.grid.shape[0]} x {table.grid.shape[1]} x "
        f"{table.grid.shape[2]} voxels of {table.grid.voxel_m * 1e3:g} mm (x, y in +-0.5 m, z 0.2-1.2 m), "
        f"4 channels, image = 4th-largest channel SNR, threshold {fine_options.threshold_db:g} dB.",
        "",
        f"Lookup table: {table.nbytes / 1e6:.0f} MB (uint16 paths in 1/16 sample plus "
        f"{len(table.levels)} coarse levels up to {table.grid.voxel_m * 2 ** len(table.levels) * 1e3:g} mm "
        f"cells), built once in {build_s:.1f} s.",
        "",
        f"## Per frame, median of {args.rounds} alternating rounds",
        "",
        "| step | frames | coarse-to-fine ms/frame | brute force ms/frame | speed-up |",
        "|---|---|---|---|---|",
        f"| voxels above threshold (search) | {len(few)} | {median['search, coarse-to-fine'] * 1e3:.1f} | "
        f"{median['search, brute force'] * 1e3:.0f} | "
        f"{median['search, brute force'] / median['search, coarse-to-fine']:.0f}x |",
        f"| back-projection to objects | {len(few)} | {median['objects, coarse-to-fine'] * 1e3:.1f} | "
        f"{median['objects, brute force'] * 1e3:.0f} | "
        f"{median['objects, brute force'] / median['objects, coarse-to-fine']:.0f}x |",
        f"| back-projection to objects | {len(items)} | "
        f"{median['objects, coarse-to-fine, all frames'] * 1e3:.1f} | | |",
        "",
        f"Same voxels above threshold on the brute-force frames: {'yes' if same_voxels else 'NO'}; "
        f"same objects: {'yes' if same_objects else 'NO'}.",
        f"Fine voxels at or above threshold (coarse-to-fine ends with these): {int(np.median(refined))}, "
        f"max {max(refined)} of {table.grid.n_voxels} "
        f"({100 * np.median(refined) / table.grid.n_voxels:.2f} %), median over frames.",
        "",
        "Before back-projection, every frame needs its channel signals (conditioning, matched filter, "
        f"the echo finder and the CLEAN restoration): {signals_s * 1e3:.1f} ms/frame, the same for both "
        "searches and not included above.",
        "",
    ]
    text = "\n".join(lines)
    RESULTS.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
