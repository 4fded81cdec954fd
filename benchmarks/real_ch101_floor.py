"""How well can any per-echo timing locate the target of a real CH101 recording? An oracle bound.

Data: a real CH101 recording in the contract format (``--data``; by default ``DATA``, the
development half kept beside this checkout), converted from the data set of C. Hahne,
"3-Dimensional Sonic Phase-invariant Echo Localization", ICRA 2023, pp. 4121-4127,
doi:10.1109/ICRA48891.2023.10161199 (github hahnec/spiel, Apache-2.0).

This script gives every advantage that echoloc does not have, to find the error that remains
when detection and association are perfect:

1. **Oracle association.** On each receiver, the envelope peak (background subtracted,
   above the channel's noise, Gaussian sub-sample interpolation, as echoloc's envelope-peak)
   nearest to where the known target puts it, within 3 samples, is taken as the target's
   echo.
2. **Calibration as echoloc's:** one delay per receiver and the speed of sound, least
   squares over the calibration positions' matched echoes.
3. **Least squares** over the receivers that have the echo (3 or 4), from a start near the
   array's axis.

It then splits each receiver's path residual at the known positions into what is common to
a position's frames (between positions: the target's own scattering, the labels) and what
varies from frame to frame (within a position: noise and the chip's timing jitter). Only the
second averages out; the first is a floor for any method that times one echo per receiver
under a per-receiver delay, unless it is smooth over space: the script also predicts each
position's offsets from its nearest positions of the other half. Labels whose frames
disagree with the echoes are listed: a position is flagged when fewer than half of its
frames have the label's echo on 3 receivers.

    .venv/bin/python benchmarks/real_ch101_floor.py [--data PATH] > benchmarks/results/real_ch101_floor.md
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from echoloc.io.recording import read_recording
from echoloc.localise.evaluation import target_positions

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "ch101-spiel" / "dev.h5"
MAD_TO_SIGMA = 1.4826
"""sigma of Gaussian errors over their median absolute deviation."""
GATE_SAMPLES = 3.0
"""The oracle takes the peak nearest to the label's prediction within this many samples."""


def peak_times(envelope: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """Sub-sample times (samples) of the local maxima of each channel that rise above its noise
    (``MAD_TO_SIGMA`` times the median of its positive samples), by a Gaussian fit through
    three samples (a parabola where a neighbour is not positive)."""
    out = []
    for values in envelope:
        positive = values[values > 0]
        noise = MAD_TO_SIGMA * float(np.median(positive)) if len(positive) else 0.0
        inner = (
            np.flatnonzero(
                (values[1:-1] > values[:-2]) & (values[1:-1] >= values[2:]) & (values[1:-1] > noise)
            )
            + 1
        )
        times = []
        for k in inner:
            a, b, c = values[k - 1], values[k], values[k + 1]
            if min(a, b, c) > 0:
                a, b, c = np.log(a), np.log(b), np.log(c)
            curvature = a - 2 * b + c
            times.append(k + 0.5 * (a - c) / curvature if curvature < 0 else float(k))
        out.append(np.array(times))
    return out


def oracle_peaks(
    peaks: list[list[NDArray[np.float64]]], predicted: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(n_frames, n_rx) the peak nearest to ``predicted`` (samples) within the gate, NaN if none."""
    chosen = np.full(predicted.shape, np.nan)
    for f, channels in enumerate(peaks):
        for r, times in enumerate(channels):
            if len(times):
                j = int(np.argmin(np.abs(times - predicted[f, r])))
                if abs(times[j] - predicted[f, r]) <= GATE_SAMPLES:
                    chosen[f, r] = times[j]
    return chosen


def calibrate(peak_s: NDArray[np.float64], paths_m: NDArray[np.float64]) -> tuple[float, NDArray[np.float64]]:
    """Speed of sound (m/s) and a delay per receiver (s), least squares over the matched echoes."""
    rows, observed = [], []
    for f, r in zip(*np.nonzero(np.isfinite(peak_s)), strict=True):
        row = np.zeros(1 + peak_s.shape[1])
        row[0], row[1 + r] = paths_m[f, r], 1.0
        rows.append(row)
        observed.append(peak_s[f, r])
    solution = np.linalg.lstsq(np.array(rows), np.array(observed), rcond=None)[0]
    return 1.0 / solution[0], solution[1:]


def solve(
    path_m: NDArray[np.float64], tx: NDArray[np.float64], rx: NDArray[np.float64]
) -> NDArray[np.float64] | None:
    """Least-squares position (m) from the paths of the receivers that have one; None below 3."""
    have = np.isfinite(path_m)
    if have.sum() < 3:
        return None

    def residual(p: NDArray[np.float64]) -> NDArray[np.float64]:
        return (np.linalg.norm(p - tx) + np.linalg.norm(p - rx, axis=1) - path_m)[have]

    start = tx + np.array([0.0, 0.0, float(np.nanmedian(path_m)) / 2])
    return np.asarray(least_squares(residual, start).x)


def position_offsets(
    residual_m: NDArray[np.float64], position: NDArray[np.int64], usable: NDArray[np.bool_]
) -> NDArray[np.float64]:
    """(n_positions, n_rx) each position's median path residual (m) over its usable frames,
    per receiver; NaN where it has none."""
    offsets = np.full((int(position.max()) + 1, residual_m.shape[1]), np.nan)
    for p in range(len(offsets)):
        frames = (position == p) & usable
        if np.isfinite(residual_m[frames]).any():
            offsets[p] = np.nanmedian(residual_m[frames], axis=0)
    return offsets


def robust_sigma(values: NDArray[np.float64]) -> float:
    values = values[np.isfinite(values)]
    return (
        float(MAD_TO_SIGMA * np.median(np.abs(values - np.median(values)))) if len(values) else float("nan")
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DATA)
    args = parser.parse_args()
    recording = read_recording(args.data)
    truth = recording.truth_positions_m
    if truth is None or recording.background is None or recording.signal_kind != "envelope":
        raise SystemExit(f"{args.data}: needs an envelope recording with truth_positions and a background")
    fs = recording.sample_rate_hz
    tx, rx = recording.transmitters_m[0], recording.receivers_m
    target = truth[:, 0, :]
    _, position = target_positions(truth)
    paths = np.linalg.norm(target - tx, axis=1)[:, None] + np.linalg.norm(target[:, None] - rx[None], axis=2)
    envelope = np.clip(np.asarray(recording.frames, float) - np.asarray(recording.background, float), 0, None)
    peaks = [peak_times(frame) for frame in envelope]

    # Two passes: a first delay from a nominal speed of sound and a guessed 1-sample lag,
    # then the median lag of what the first pass matched.
    speed = 343.0
    lag = np.ones(len(rx))
    for _ in range(2):
        chosen = oracle_peaks(peaks, paths / speed * fs + lag)
        lag = np.nanmedian(chosen - paths / speed * fs, axis=0)

    n_positions = int(position.max()) + 1
    print(
        f"# Oracle bound on real CH101 data\n\nData: `{args.data.name}`, {recording.n_frames} frames, "
        f"{n_positions} target positions. Reproduce: `.venv/bin/python benchmarks/real_ch101_floor.py`.\n"
    )

    print("## Labels that disagree with the echoes\n")
    flagged = []
    for p in range(n_positions):
        frames = position == p
        agree = float(np.mean(np.sum(np.isfinite(chosen[frames]), axis=1) >= 3))
        if agree < 0.5:
            flagged.append(p)
            label = ", ".join(f"{v * 1e3:.0f}" for v in target[frames][0])
            print(
                f"- position {p} at ({label}) mm, {int(frames.sum())} frames: the label's echo on 3 "
                f"receivers in {agree:.0%} of them"
            )
    if not flagged:
        print("- none")
    usable = ~np.isin(position, flagged)

    print("\n## Oracle association, echoloc's calibration model\n")
    print("| test positions | frames | located | median 3-D error, mm | p90, mm | c, m/s |")
    print("|---|---|---|---|---|---|")
    residual_m = np.full(chosen.shape, np.nan)
    for name, test_parity in (("1::2 (calibrated on 0::2)", 1), ("0::2 (calibrated on 1::2)", 0)):
        test = usable & (position % 2 == test_parity)
        train = usable & ~test
        c, delay_s = calibrate(chosen[train] / fs, paths[train])
        measured_m = (chosen / fs - delay_s) * c
        residual_m[test] = (measured_m - paths)[test]
        errors = []
        for f in np.flatnonzero(test):
            found = solve(measured_m[f], tx, rx)
            errors.append(np.nan if found is None else float(np.linalg.norm(found - target[f])) * 1e3)
        e = np.array(errors)
        print(
            f"| {name} | {len(e)} | {np.isfinite(e).mean():.3f} | {np.nanmedian(e):.1f} | "
            f"{np.nanpercentile(e, 90):.1f} | {c:.1f} |"
        )

    print("\n## Path residual at the test positions, mm (robust sigma)\n")
    print("| receiver | between positions | within a position (frame to frame) | all |")
    print("|---|---|---|---|")
    means = position_offsets(residual_m, position, usable)
    for r in range(len(rx)):
        within = residual_m[:, r] - means[position, r]
        print(
            f"| {r} | {robust_sigma(means[:, r]) * 1e3:.1f} | {robust_sigma(within) * 1e3:.1f} | "
            f"{robust_sigma(residual_m[:, r]) * 1e3:.1f} |"
        )
    # Are the offsets smooth over space, so that a correction learnt at the calibration
    # positions could be carried to their neighbours? Under one calibration on every usable
    # position (so that two halves' fits do not differ by their own error), predict each
    # position's offsets by the mean of its nearest positions of the other half.
    c_all, delay_all = calibrate(chosen[usable] / fs, paths[usable])
    residual_all = (chosen / fs - delay_all) * c_all - paths
    offsets = position_offsets(residual_all, position, usable)
    first = np.array([target[position == p][0] for p in range(n_positions)])
    kept = np.array([p not in flagged for p in range(n_positions)])
    print("\n| neighbours of the other half | offset sigma left, mm (was, all receivers) |\n|---|---|")
    for k in (1, 2, 4):
        left = []
        for p in np.flatnonzero(kept):
            others = np.flatnonzero(kept & (np.arange(n_positions) % 2 != p % 2))
            nearest = others[np.argsort(np.linalg.norm(first[others] - first[p], axis=1))[:k]]
            left.append(offsets[p] - np.nanmean(offsets[nearest], axis=0))
        was = robust_sigma(offsets[kept].ravel())
        print(f"| {k} | {robust_sigma(np.ravel(left)) * 1e3:.1f} ({was * 1e3:.1f}) |")
    complete = np.all(np.isfinite(means), axis=1)
    common = means[complete].mean(axis=1)
    differential = means[complete] - common[:, None]
    print(
        f"\nBetween positions, the part common to all receivers (a range error) has sigma "
        f"{robust_sigma(common) * 1e3:.1f} mm; the part that differs between receivers (an "
        f"angle error, magnified by the {np.linalg.norm(rx - tx, axis=1).max() * 1e3:.0f} mm "
        f"baseline) {robust_sigma(differential.ravel()) * 1e3:.1f} mm."
    )


if __name__ == "__main__":
    main()
