"""Peaks to points against points to peaks: association and back-projection on the same recordings.

The issue's scene: ``random-1m3`` with 1 to 6 point reflectors per frame
at random in the cubic metre in front of the report's array, σ_path 0.5 mm, SNR
20 dB. Every approach sees the same frames:

- association ("peaks to points"): :func:`echoloc.pipeline.prepare` and
  :func:`echoloc.pipeline.run` (echoes per channel, then their combination);
- back-projection ("points to peaks") on CLEAN-restored envelopes, 5 mm grid over
  x, y in +-0.5 m, z 0.2-1.2 m: :func:`echoloc.localise.backprojection.run_backprojection`;
- back-projection on the raw matched-filter envelopes (``restore=False``), on the
  first ``--raw-frames`` frames only: what the code's sidelobes do to it.

Scored with :func:`echoloc.localise.evaluation.evaluate` (match radius 20 mm): recall, false
objects, RMSE and bias per axis, mean reported std. Time per frame is the whole
chain from samples to objects, one approach after the other (not interleaved: see
``bench_backprojection.py`` for side-by-side timing).

    python benchmarks/study_localisation.py --frames 1000 --raw-frames 20
"""

from __future__ import annotations

import argparse
import time
import tomllib
from dataclasses import replace
from datetime import date
from pathlib import Path

import numpy as np

from echoloc import pipeline
from echoloc.localise.backprojection import (
    BackprojectionOptions,
    frame_image,
    prepare_backprojection,
    run_backprojection,
)
from echoloc.localise.evaluation import Evaluation, evaluate
from echoloc.localise.locate import FrameObjects
from echoloc.plots.imaging import save_image_png
from echoloc.sim.scenefile import scene_from_dict
from echoloc.sim.simulation import simulate

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).resolve().parent / "results"


def _row(name: str, frames: int, report: Evaluation, seconds: float) -> str:
    rmse = report.rmse_m * 1e3
    bias = report.bias_m * 1e3
    ratio = report.mean_std_m / report.rmse_m
    return (
        f"| {name} | {frames} | {report.recall:.4f} ({report.n_matched}/{report.n_truth}) | "
        f"{report.false_rate:.4f} ({report.n_false}/{report.n_located}) | "
        f"{rmse[0]:.2f} / {rmse[1]:.2f} / {rmse[2]:.2f} | {bias[0]:+.2f} / {bias[1]:+.2f} / {bias[2]:+.2f} | "
        f"{ratio[0]:.2f} / {ratio[1]:.2f} / {ratio[2]:.2f} | {seconds * 1e3:.1f} |"
    )


def _by_count(results: list[FrameObjects], truth: np.ndarray, counts: np.ndarray) -> list[float]:
    out = []
    for k in range(1, 7):
        chosen = [r for r in results if counts[r.frame] == k]
        out.append(evaluate(chosen, truth).recall if chosen else float("nan"))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--raw-frames", type=int, default=20)
    parser.add_argument("--seed", type=int, default=29)
    args = parser.parse_args()

    data = tomllib.loads((ROOT / "src" / "echoloc" / "scenes" / "random-1m3.toml").read_text())
    data["random_reflectors"]["count"] = [1, 6]
    data["seed"] = args.seed
    recording = simulate(scene_from_dict(data, "random-1m3.toml (1-6 reflectors)"), args.frames)
    truth = recording.truth_positions_m
    assert truth is not None
    counts = np.sum(np.isfinite(truth[:, :, 0]), axis=1)

    chain = pipeline.prepare(recording)
    start = time.perf_counter()
    association = [objects for _, objects in pipeline.run(chain)]
    association_s = (time.perf_counter() - start) / recording.n_frames

    bp = prepare_backprojection(recording)
    start = time.perf_counter()
    restored = list(run_backprojection(bp))
    restored_s = (time.perf_counter() - start) / recording.n_frames

    raw_bp = replace(bp, options=replace(bp.options, restore=False), chain=None)
    raw_frames = range(min(args.raw_frames, recording.n_frames))
    start = time.perf_counter()
    raw = list(run_backprojection(raw_bp, raw_frames))
    raw_s = (time.perf_counter() - start) / len(raw_frames)

    reports = {
        "association": (evaluate(association, truth), association_s, recording.n_frames),
        "back-projection, restored envelopes": (evaluate(restored, truth), restored_s, recording.n_frames),
        "back-projection, raw envelopes": (evaluate(raw, truth), raw_s, len(raw_frames)),
        "association, same frames as raw": (
            evaluate(association[: len(raw_frames)], truth),
            association_s,
            len(raw_frames),
        ),
    }

    # A busy frame for the picture: the first with six reflectors.
    busy = int(np.flatnonzero(counts == counts.max())[0])
    image_path = RESULTS / "localisation_frame.png"
    save_image_png(
        frame_image(bp, busy),
        image_path,
        objects_m=np.array([o.position_m for o in restored[busy].objects]).reshape(-1, 3),
        truth_m=truth[busy],
        title=f"Frame {busy}: back-projection of restored envelopes, {counts[busy]} reflectors "
        f"(circles: truth, crosses: objects found)",
    )
    raw_path = RESULTS / "localisation_frame_raw.png"
    raw_objects = next(iter(run_backprojection(raw_bp, [busy])))
    save_image_png(
        frame_image(raw_bp, busy),
        raw_path,
        objects_m=np.array([o.position_m for o in raw_objects.objects]).reshape(-1, 3),
        truth_m=truth[busy],
        title=f"Frame {busy}: back-projection of raw matched-filter envelopes (Barker-13 sidelobes included)",
    )

    lines = [
        "# study_localisation.py — last run",
        "",
        f"`python benchmarks/study_localisation.py --frames {args.frames} --raw-frames {args.raw_frames}` "
        f"on {date.today()}, this project's shared 2-core machine.",
        "",
        f"{recording.n_frames} frames of random-1m3 with 1-6 point reflectors "
        f"({int(counts.sum())} in all), σ_path 0.5 mm, SNR 20 dB, strengths 0.5-2. Back-projection grid: "
        f"{bp.table.grid.shape} voxels of {bp.table.grid.voxel_m * 1e3:g} mm, support rule: "
        f"4 of 4 channels ({BackprojectionOptions().threshold_db:g} dB each).",
        "",
        "| approach | frames | recall | false objects | RMSE x / y / z (mm) | bias x / y / z (mm) | "
        "mean std / RMSE x / y / z | ms/frame, samples to objects |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, (report, seconds, frames) in reports.items():
        lines.append(_row(name, frames, report, seconds))
        print(lines[-1], flush=True)
    lines += [
        "",
        "Recall by reflectors per frame (1 … 6):",
        "",
        "| approach | " + " | ".join(str(k) for k in range(1, 7)) + " |",
        "|---|" + "---|" * 6,
    ]
    for name, results in (("association", association), ("back-projection, restored", restored)):
        values = _by_count(results, truth, counts)
        lines.append(f"| {name} | " + " | ".join(f"{v:.4f}" for v in values) + " |")
    lines += [
        "",
        f"![frame {busy}, restored envelopes]({image_path.name})",
        "",
        f"![frame {busy}, raw envelopes]({raw_path.name})",
        "",
    ]
    text = "\n".join(lines)
    (RESULTS / "localisation.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
