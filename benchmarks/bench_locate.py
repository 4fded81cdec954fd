"""Localisation on the issue's scene: accuracy over 1000 frames and time per frame by object count.

The scene is ``random-1m3-six``: 1 to 6 point reflectors per frame in the
cubic metre in front of the report's array (0.5 mm of random error on every path,
strengths 0.5-2). The echoes of every frame are found
once; then, on the same echoes:

- accuracy of ``echoloc.pipeline`` locate (association + solve) over all frames:
  recall, ghosts (false objects), RMSE per axis and the mean reported std;
- time of association + solve per frame, grouped by the number of reflectors,
  median of alternating rounds, beside the brute-force baseline of
  ``bench_pipeline.py`` (``least_squares`` on every combination of one echo per
  receiver, chi-square gate, greedy), which runs on ``--brute-frames`` frames per
  group only (it takes seconds per frame).

    python benchmarks/bench_locate.py --frames 1000 --rounds 3 --brute-frames 2
"""

from __future__ import annotations

import argparse
import statistics
import time
import tomllib
from datetime import date
from pathlib import Path

import numpy as np

from bench_pipeline import baseline_locate
from echoloc import pipeline
from echoloc.localise.evaluation import evaluate
from echoloc.sim.scenefile import scene_from_dict
from echoloc.sim.simulation import simulate
from echoloc.tof.echoes import FrameEchoes

ROOT = Path(__file__).resolve().parents[1]
RESULTS = Path(__file__).resolve().parent / "results" / "locate.md"


def _time_per_frame(job: list[FrameEchoes], chain: pipeline.Chain) -> float:
    """Mean time per frame of one pass over ``job``, s."""
    start = time.perf_counter()
    for echoes in job:
        pipeline.frame_objects(chain, echoes)
    return (time.perf_counter() - start) / len(job)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--brute-frames", type=int, default=2)
    parser.add_argument("--seed", type=int, default=None, help="another draw of the scene")
    args = parser.parse_args()

    data = tomllib.loads((ROOT / "src" / "echoloc" / "scenes" / "random-1m3-six.toml").read_text())
    if args.seed is not None:
        data["seed"] = args.seed
    recording = simulate(scene_from_dict(data, "random-1m3-six.toml"), args.frames)
    chain = pipeline.prepare(recording)
    echoes = [pipeline.frame_echoes(chain, i) for i in range(recording.n_frames)]
    results = [pipeline.frame_objects(chain, e) for e in echoes]
    assert recording.truth_positions_m is not None
    report = evaluate(results, recording.truth_positions_m)
    counts = np.sum(np.isfinite(recording.truth_positions_m[:, :, 0]), axis=1)

    lines = [
        "# bench_locate.py — last run",
        "",
        f"`python benchmarks/bench_locate.py --frames {args.frames} --rounds {args.rounds} "
        f"--brute-frames {args.brute_frames}"
        + ("" if args.seed is None else f" --seed {args.seed}")
        + f"` on {date.today()}, this project's shared 2-core machine.",
        "",
        f"## Accuracy: {report.n_frames} frames, {report.n_truth} reflectors (1-6 per frame), "
        "σ_path 0.5 mm, SNR 20 dB",
        "",
        "| figure | value |",
        "|---|---|",
        f"| recall | {report.recall:.4f} ({report.n_matched}/{report.n_truth}) |",
        f"| ghosts (false objects) | {report.false_rate:.4f} ({report.n_false}/{report.n_located}) |",
    ]
    for axis, name in enumerate("xyz"):
        ratio = report.mean_std_m[axis] / report.rmse_m[axis]
        lines.append(
            f"| {name}: RMSE / bias / mean reported std (mm), std/RMSE | "
            f"{report.rmse_m[axis] * 1e3:.3f} / {report.bias_m[axis] * 1e3:+.3f} / "
            f"{report.mean_std_m[axis] * 1e3:.3f}, {ratio:.3f} |"
        )
    lines += [
        "",
        "## Association + solve per frame, median of alternating rounds",
        "",
        "| reflectors | frames | echoloc ms/frame | brute force ms/frame | speed-up |",
        "|---|---|---|---|---|",
    ]
    for k in range(1, 7):
        group = [echoes[i] for i in np.flatnonzero(counts == k)]
        if not group:
            continue
        few = group[: args.brute_frames]
        ours, brute = [], []
        for _ in range(args.rounds):
            ours.append(_time_per_frame(group, chain))
            start = time.perf_counter()
            for e in few:
                paths = [ch.tof_s * e.speed_of_sound_m_s for ch in e.channels]
                baseline_locate(chain, e.frame, paths)
            brute.append((time.perf_counter() - start) / len(few))
        mine, theirs = statistics.median(ours), statistics.median(brute)
        lines.append(f"| {k} | {len(group)} | {mine * 1e3:.3f} | {theirs * 1e3:.1f} | {theirs / mine:.0f}x |")
        print(lines[-1], flush=True)
    text = "\n".join(lines) + "\n"
    RESULTS.write_text(text)
    print(text)


if __name__ == "__main__":
    main()
