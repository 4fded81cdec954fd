"""Time per frame of `echoes` and `locate`, side by side with straightforward baselines.

Baselines, written the obvious way with scipy (echoloc.benchmark, shared with
`echoloc bench` and bench_stream.py):

- echoes: per channel, ``scipy.signal.correlate`` with the pulse, ``scipy.signal.hilbert``
  for the envelope, ``scipy.signal.find_peaks`` (height 5 sigma of the envelope noise,
  distance one chip) and a parabolic fit of the peak;
- locate: every combination of one echo per receiver solved by
  ``scipy.optimize.least_squares``, kept when its residual passes the same chi-square
  gate, then taken greedily by residual.

Both run on the same frames in alternating rounds (this machine is shared and noisy),
and the median of the rounds is reported, with the ratio and the accuracy of each, so
a speed-up never hides a loss of accuracy.

    python benchmarks/bench_pipeline.py [--frames 40] [--rounds 5]
"""

from __future__ import annotations

import numpy as np

from _common import matched_filter, parse_arguments, seconds
from echoloc.benchmark import baseline_echoes, baseline_locate, bench_scene
from echoloc.localise.evaluation import evaluate
from echoloc.pipeline import Chain, frame_echoes, frame_objects, prepare
from echoloc.sim.simulation import simulate
from echoloc.tof.echoes import matched_filter_batch


def bench(name: str, chain: Chain, n_frames: int, rounds: int, brute_frames: int) -> None:
    frames = range(n_frames)
    # The brute-force locate takes seconds a frame: it runs on the first few frames only.
    few = range(min(brute_frames, n_frames))
    recording = chain.recording
    echoes = [frame_echoes(chain, i) for i in frames]
    base_paths = [baseline_echoes(chain, recording.frames[i]) for i in frames]
    timings: dict[str, list[float]] = {
        k: [] for k in ("echoes", "echoes_batch", "echoes_base", "locate", "locate_base")
    }
    mf = matched_filter(recording)
    block = recording.frames[:n_frames]
    for _ in range(rounds):
        timings["echoes"].append(seconds(lambda: [frame_echoes(chain, i) for i in frames]) / n_frames)
        timings["echoes_batch"].append(
            seconds(lambda: matched_filter_batch(block, mf, chain.echo_options)) / n_frames
        )
        timings["echoes_base"].append(
            seconds(lambda: [baseline_echoes(chain, recording.frames[i]) for i in frames]) / n_frames
        )
        timings["locate"].append(seconds(lambda: [frame_objects(chain, e) for e in echoes]) / n_frames)
        timings["locate_base"].append(
            seconds(lambda: [baseline_locate(chain, i, base_paths[i]) for i in few]) / len(few)
        )
    median = {k: float(np.median(v)) for k, v in timings.items()}
    truth = chain.recording.truth_positions_m
    assert truth is not None
    ours = evaluate([frame_objects(chain, e) for e in echoes], truth)
    theirs = evaluate([baseline_locate(chain, i, base_paths[i]) for i in few], truth)
    print(
        f"\n## {name}: {n_frames} frames x {chain.recording.n_receivers} receivers x "
        f"{chain.recording.n_samples} samples, median of {rounds} alternating rounds\n"
    )
    print("| stage | echoloc ms/frame | baseline ms/frame | speed-up |")
    print("|---|---|---|---|")
    for stage, base in (("echoes", "echoes"), ("echoes_batch", "echoes"), ("locate", "locate")):
        label = "echoes, all frames in one batch" if stage == "echoes_batch" else stage
        print(
            f"| {label} | {median[stage] * 1e3:.3f} | {median[base + '_base'] * 1e3:.3f} | "
            f"{median[base + '_base'] / median[stage]:.1f}x |"
        )
    total = median["echoes"] + median["locate"]
    print(
        f"| full chain | {total * 1e3:.3f} | {(median['echoes_base'] + median['locate_base']) * 1e3:.3f} | "
        f"{(median['echoes_base'] + median['locate_base']) / total:.1f}x |"
    )
    print(
        f"\nAccuracy on the same frames: echoloc recall {ours.recall:.3f}, false {ours.false_rate:.3f}, "
        f"RMSE {np.round(ours.rmse_m * 1e3, 3).tolist()} mm; baseline recall {theirs.recall:.3f}, "
        f"false {theirs.false_rate:.3f}, RMSE {np.round(theirs.rmse_m * 1e3, 3).tolist()} mm"
    )


def main() -> None:
    args = parse_arguments(
        __doc__, frames=40, rounds=5, more=[("--brute-frames", 2, "frames for the brute-force locate")]
    )
    for name, reflectors in (
        ("Default scene (report set-up, 3 balls)", 0),
        ("Five random reflectors in 1 m^3", 5),
    ):
        chain = prepare(simulate(bench_scene(reflectors), args.frames))
        bench(name, chain, args.frames, args.rounds, args.brute_frames)


if __name__ == "__main__":
    main()
