"""Mapping throughput: frames/s and memory of the occupancy grid, compiled beside numpy.

Echoes and objects of the room scene (mapping/room) are computed first
and not timed; what is timed is the map update alone: every channel's inverse sensor
model and the frame's combination, by :class:`echoloc.maps.mapping.MapAccumulator`
(compiled loops) and by the same model written in numpy
(``channel_update_reference`` of ``tests/mapping_oracle.py``), in alternating rounds of
one run (the machine is shared). Grids: the issue's 200 x 200 x 100 cells of 1 cm
(x and z 2 m, y 1 m: 4 M cells) and floor plans at 1 and 2 cm.

    python benchmarks/bench_mapping.py [--frames 100] [--rounds 3]
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import statistics
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from echoloc import pipeline
from echoloc.io.recording import Recording
from echoloc.maps.mapping import (
    GridSpec,
    MapAccumulator,
    SensorModel,
    beam_table,
    channel_window,
    half_power_angle_deg,
)
from echoloc.sim.scenefile import load_scene
from echoloc.sim.simulation import simulate
from echoloc.tof.echoes import FrameEchoes

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from mapping_oracle import channel_update_reference

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results" / "mapping_speed.md"


def _numpy_map(spec: GridSpec, recording: Recording, frames: list[FrameEchoes]) -> np.ndarray:
    """The same model as MapAccumulator (echoes only, no objects) in numpy, frame by frame."""
    model = SensorModel()
    fov = recording.field_of_view_deg or 90.0
    cos_null, table = beam_table(fov)
    clear_cos = math.cos(math.radians(half_power_angle_deg(fov)))
    log_odds = np.zeros(spec.n_cells)
    hit_axes = np.zeros((spec.n_cells, 3))
    shape = np.array(spec.shape)
    poses = recording.sensor_poses
    assert poses is not None
    low, high = (math.log(p / (1 - p)) for p in model.clamp_probability)
    for echoes in frames:
        rotation = Rotation.from_quat(poses[echoes.frame, 3:]).as_matrix()
        t = poses[echoes.frame, :3]
        tx = rotation @ recording.transmitters_m[0] + t
        tx_axis = rotation @ np.array([0.0, 0.0, 1.0])
        window = recording.n_samples / recording.sample_rate_hz * echoes.speed_of_sound_m_s
        parts = []
        for rx_index, channel in enumerate(echoes.channels):
            rx = rotation @ recording.receivers_m[rx_index] + t
            paths = np.sort(np.asarray(channel.tof_s) * echoes.speed_of_sound_m_s)
            paths = paths[paths <= window]
            free_below, margin, reach = channel_window(
                paths, model.clear_fraction * window, model.path_sigma_m, spec.cell_m, model.arc_sigmas
            )
            half = (reach + float(np.linalg.norm(tx - rx))) / 2
            lower = np.maximum(np.floor((tx - half - spec.origin_m) / spec.cell_m).astype(int), 0)
            upper = np.minimum(np.floor((tx + half - spec.origin_m) / spec.cell_m).astype(int) + 1, shape)
            if np.any(upper <= lower):
                continue
            parts.append(
                channel_update_reference(
                    spec.origin_m,
                    spec.cell_m,
                    shape,
                    lower,
                    upper,
                    tx,
                    rx,
                    tx_axis,
                    tx_axis,
                    cos_null,
                    table,
                    model.min_beam_gain,
                    free_below,
                    margin,
                    0.0,
                    paths,
                    model.path_sigma_m,
                    model.arc_sigmas,
                    reach,
                    model.hit_probability - 0.5,
                    math.log(model.free_probability / (1 - model.free_probability)),
                    hit_axes,
                    clear_cos,
                    model.silent_clear,
                )
            )
        if not parts:
            continue
        cells = np.concatenate([p[0] for p in parts])
        occupied = np.zeros(spec.n_cells)
        support = np.zeros(spec.n_cells, int)
        free = np.zeros(spec.n_cells)
        np.add.at(occupied, cells, np.concatenate([p[1] for p in parts]))
        np.add.at(support, cells, np.concatenate([p[3] for p in parts]).astype(int))
        central = np.zeros(spec.n_cells, bool)
        central[np.concatenate([p[0][p[4]] for p in parts])] = True
        np.minimum.at(free, cells, np.concatenate([p[2] for p in parts]))
        unique = np.unique(cells)
        marked = occupied[unique] > 0
        enough = support[unique] >= min(model.min_support, len(echoes.channels))
        delta = np.where(marked, np.where(enough, occupied[unique], 0.0), free[unique])
        log_odds[unique] = np.clip(log_odds[unique] + delta, low, high)
        axial = unique[marked & enough & central[unique]]
        hit_axes[axial] += occupied[axial, None] * tx_axis
    return log_odds.reshape(spec.shape)


def _compiled(
    spec: GridSpec, recording: Recording, frames: list[FrameEchoes]
) -> tuple[float, MapAccumulator]:
    accumulator = MapAccumulator(spec, recording)
    poses = recording.sensor_poses
    assert poses is not None
    started = time.perf_counter()
    for echoes in frames:
        accumulator.add_frame(echoes, poses[echoes.frame])
    return time.perf_counter() - started, accumulator


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=100, help="frames of the room scene mapped per round")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds (median reported)")
    parser.add_argument("--numpy-frames", type=int, default=20, help="frames for the numpy statement")
    args = parser.parse_args()

    load = os.getloadavg()[0]
    recording = simulate(
        load_scene(ROOT / "src" / "echoloc" / "scenes" / "mapping" / "room.toml"), args.frames
    )
    chain = pipeline.prepare(recording)
    frames = [echoes for echoes, _ in pipeline.run(chain)]
    grids = {
        "3-D 200 x 100 x 200 (x, y, z) at 1 cm, 4.0 M cells": GridSpec.box(
            [-1.0, -0.5, -0.2], [1.0, 0.5, 1.8], 0.01
        ),
        "floor plan 340 x 340 at 1 cm": GridSpec.floor_plan((-1.6, 1.8), (-1.2, 2.2), 0.01),
        "floor plan 170 x 170 at 2 cm": GridSpec.floor_plan((-1.6, 1.8), (-1.2, 2.2), 0.02),
    }
    _compiled(grids["floor plan 170 x 170 at 2 cm"], recording, frames[:2])  # compile once
    rows = []
    for name, spec in grids.items():
        compiled_s: list[float] = []
        numpy_s: list[float] = []
        for _ in range(args.rounds):
            elapsed, accumulator = _compiled(spec, recording, frames)
            compiled_s.append(elapsed / len(frames))
            subset = frames[: args.numpy_frames]
            started = time.perf_counter()
            reference = _numpy_map(spec, recording, subset)
            numpy_s.append((time.perf_counter() - started) / len(subset))
        check, _ = _compiled(spec, recording, frames[: args.numpy_frames])
        same = MapAccumulator(spec, recording)
        for echoes in frames[: args.numpy_frames]:
            same.add_frame(echoes, recording.sensor_poses[echoes.frame])  # type: ignore[index]
        agree = float(np.max(np.abs(same.grid().log_odds - reference)))
        tracemalloc.start()
        _compiled(spec, recording, frames[:10])
        peak = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        c, n = statistics.median(compiled_s), statistics.median(numpy_s)
        rows.append((name, 1 / c, 1 / n, n / c, accumulator.memory_bytes / 2**20, peak / 2**20, agree))
        del check
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    lines = [
        "# bench_mapping.py — last run",
        "",
        f"`python benchmarks/bench_mapping.py --frames {args.frames} --rounds {args.rounds}`",
        "",
        f"Load average at start: {load:.2f} on {os.cpu_count()} cores (the machine is shared).",
        "",
        f"Room scene (mapping/room), {args.frames} frames x 4 receivers, echoes computed "
        "beforehand; the map update alone, one core, median of alternating rounds "
        f"(numpy on the first {args.numpy_frames} frames).",
        "",
        "| grid | compiled frames/s | numpy frames/s | compiled / numpy | grid + scratch MiB | "
        "peak traced MiB | max abs log-odds difference |",
        "|---|---|---|---|---|---|---|",
    ]
    for name, fc, fn, ratio, held, peak, agree in rows:
        lines.append(
            f"| {name} | {fc:.0f} | {fn:.1f} | {ratio:.0f}x | {held:.0f} | {peak:.0f} | {agree:.1e} |"
        )
    lines += ["", f"Peak resident memory of the whole run: {rss:.0f} MiB.", ""]
    text = "\n".join(lines)
    print(text)
    RESULTS.write_text(text)


if __name__ == "__main__":
    main()
