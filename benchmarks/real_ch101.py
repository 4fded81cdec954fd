"""echoloc on real CH101 recordings, with defaults only: calibrate on every other target
position, locate the frames of the others, and score them; the naive baseline beside it.

Data: a real CH101 recording in the contract format (``--data``; by default ``DATA``, the
development half kept beside this checkout), converted from the data set of C. Hahne,
"3-Dimensional Sonic Phase-invariant Echo Localization", ICRA 2023, pp. 4121-4127,
doi:10.1109/ICRA48891.2023.10161199 (github hahnec/spiel, Apache-2.0).

Figures per located frame (the metric of the issue): the object echoloc ranks first
(highest score) against the frame's one true target: median and p90 3-D error, share of
frames with an object, and the share whose first object lies within 50 mm. The naive
baseline (a 50-line method: background subtraction, the strongest envelope peak per
channel after a fixed blind zone, one delay per channel fitted on the calibration frames,
least squares over the four paths) runs on the same split in the same run.

    .venv/bin/python benchmarks/real_ch101.py [--data PATH] [--plot PNG] [--split 0::2]
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.optimize import least_squares

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "ch101-spiel" / "dev.h5"
ECHOLOC = Path(sys.executable).parent / "echoloc"


def _run(*args: str) -> str:
    done = subprocess.run([str(ECHOLOC), *args], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        raise SystemExit(f"echoloc {' '.join(args)} failed: {done.stderr.strip()}")
    return done.stdout


def echoloc_figures(data: Path, calibrate_on: str, test_on: str) -> dict[str, object]:
    """Calibrate and locate through the command line, as a user would, with defaults only."""
    with tempfile.TemporaryDirectory() as folder:
        calibration = Path(folder) / "calibration.json"
        _run("calibrate", str(data), "--positions", calibrate_on, "-o", str(calibration))
        # Each command three times, the least kept (a shared machine only ever adds time);
        # the same command on one frame gives the start-up (imports, the compiled kernels'
        # cache, the file's header), which the long run pays once.
        whole = ["locate", str(data), "--positions", test_on, "--calibration", str(calibration), "--json"]
        one = ["locate", str(data), "--frames", "0", "--calibration", str(calibration), "--json"]
        elapsed_s, startup_s = math.inf, math.inf
        for _ in range(3):
            started = time.perf_counter()
            lines = _run(*whole)
            elapsed_s = min(elapsed_s, time.perf_counter() - started)
            started = time.perf_counter()
            _run(*one)
            startup_s = min(startup_s, time.perf_counter() - started)
        record = json.loads(calibration.read_text())
    frames = [json.loads(line) for line in lines.splitlines()]
    return {"frames": frames, "elapsed_s": elapsed_s, "startup_s": startup_s, "calibration": record}


def library_ms_per_frame(data: Path, calibration: dict[str, object], frames: list[int]) -> float:
    """The chain's own time a frame (recording in memory, warm), ms: the median of five passes."""
    from echoloc.io.recording import read_recording
    from echoloc.localise.calibrate import read_calibration
    from echoloc.pipeline import prepare, run

    recording = read_recording(data)
    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "calibration.json"
        path.write_text(json.dumps(calibration))
        chain = prepare(recording, estimator="auto", calibration=read_calibration(path))
    list(run(chain, frames[:20]))
    passes = []
    for _ in range(5):
        started = time.perf_counter()
        for _ in run(chain, frames):
            pass
        passes.append((time.perf_counter() - started) / len(frames) * 1e3)
    return float(np.median(passes))


def baseline_positions(data: Path, calibrate: list[int], test: list[int]) -> dict[int, np.ndarray]:
    """The naive method of the issue, side by side (module doc)."""
    import h5py

    with h5py.File(data, "r") as file:
        frames = file["frames"][:].astype(float)
        background = file["background"][:].astype(float)
        truth = file["truth_positions"][:, 0, :]
        receivers = file["receivers"][:]
        fs = float(file.attrs["sample_rate_hz"])
        c = float(file.attrs.get("speed_of_sound_m_s", 343.0))
    signal = np.clip(frames - background, 0, None)
    signal[:, :, :9] = 0  # a fixed blind zone past the transmitter's ring-down
    peaks = np.argmax(signal, axis=2).astype(float)
    paths = np.linalg.norm(truth, axis=1)[:, None] + np.linalg.norm(truth[:, None] - receivers[None], axis=2)
    delay = np.median(peaks[calibrate] - paths[calibrate] / c * fs, axis=0)
    measured = (peaks - delay) / fs * c
    out = {}
    for index in test:

        def residual(p: np.ndarray, i: int = index) -> np.ndarray:
            return np.linalg.norm(p) + np.linalg.norm(p - receivers, axis=1) - measured[i]

        out[index] = least_squares(residual, np.array([0.0, 0.0, 0.2])).x
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--plot", type=Path, default=ROOT / "benchmarks" / "results" / "real_ch101_error.png")
    parser.add_argument("--split", default="0::2", help="positions to calibrate on; the test set is the rest")
    args = parser.parse_args()
    import h5py

    evaluate_module = importlib.import_module("echoloc.localise.evaluation")
    with h5py.File(args.data, "r") as file:
        truth_all = file["truth_positions"][:]
    every = range(len(truth_all))
    start = int(args.split.split(":")[0] or 0)
    test_split = f"{1 - start}::2" if args.split.endswith("::2") else None
    if test_split is None:
        raise SystemExit("--split must be 0::2 or 1::2")
    calibrate = evaluate_module.frames_at_positions(truth_all, args.split, every)
    test = evaluate_module.frames_at_positions(truth_all, test_split, every)
    truth = truth_all[:, 0, :]

    ours = echoloc_figures(args.data, args.split, test_split)
    errors, nearest, found, ranks = [], [], 0, []
    for frame in ours["frames"]:
        objects = frame["objects"]
        if not objects:
            errors.append(np.nan)
            nearest.append(np.nan)
            continue
        found += 1
        target = truth[frame["frame"]]
        best = max(objects, key=lambda o: o["score"])
        errors.append(float(np.linalg.norm(np.array(best["position_m"]) - target)))
        nearest.append(min(float(np.linalg.norm(np.array(o["position_m"]) - target)) for o in objects))
        ranks.append(len(objects))
    err = np.array(errors) * 1e3
    near = np.array(nearest) * 1e3
    base = baseline_positions(args.data, calibrate, test)
    base_err = np.array([np.linalg.norm(base[i] - truth[i]) for i in test]) * 1e3

    n = len(test)
    ms_per_frame = ours["elapsed_s"] / n * 1e3
    print(
        f"data: {args.data} ({n} test frames, calibrated on {len(calibrate)} frames, positions {args.split})"
    )
    print(f"{'method':36s} {'found':>8s} {'median mm':>10s} {'p90 mm':>8s} {'<=50 mm':>8s}")
    for label, e, share in (
        ("echoloc (defaults), first object", err, found / n),
        ("echoloc (defaults), nearest", near, found / n),
        ("naive baseline", base_err, 1.0),
    ):
        good = e[np.isfinite(e)]
        print(
            f"{label:36s} {share:8.3f} {np.median(good):10.1f} {np.percentile(good, 90):8.1f} "
            f"{np.mean(np.nan_to_num(e, nan=1e9) <= 50):8.3f}"
        )
    print(f"objects per frame with any: {np.mean(ranks):.2f}")
    library_ms = library_ms_per_frame(args.data, ours["calibration"], test)
    print(f"echoloc's chain, recording in memory (warm): {library_ms:.3f} ms a frame")
    beyond_ms = (ours["elapsed_s"] - ours["startup_s"]) / (n - 1) * 1e3
    print(
        f"echoloc locate, file to JSON: {ms_per_frame:.3f} ms a frame ({ours['elapsed_s']:.2f} s, "
        f"startup included); startup {ours['startup_s']:.2f} s (the same command on one frame), "
        f"then {beyond_ms:.3f} ms a frame"
    )
    calibration = ours["calibration"]
    print(
        f"calibration: c = {calibration['speed_of_sound_m_s']:.2f} m/s, path sigma "
        f"{calibration['path_sigma_m'] * 1e3:.2f} mm, delays "
        + ", ".join(f"{d * 1e6:+.1f}" for d in calibration["receiver_delays_s"])
        + " us"
        + (
            f", detection threshold {calibration['threshold_db']:.2f} dB"
            if "threshold_db" in calibration
            else ""
        )
    )
    _plot(args.plot, truth[test], err, base_err)
    print(f"plot: {args.plot}")


def _plot(path: Path, truth: np.ndarray, err: np.ndarray, base_err: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rng = np.linalg.norm(truth, axis=1) * 1e3
    angle = np.degrees(np.arccos(truth[:, 2] / np.linalg.norm(truth, axis=1)))
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2), sharey=True)
    for ax, x, label in (
        (axes[0], rng, "range to the target, mm"),
        (axes[1], angle, "angle off boresight, °"),
    ):
        ax.scatter(x, base_err, s=9, alpha=0.35, color="tab:gray", label="naive baseline")
        ax.scatter(x, err, s=9, alpha=0.6, color="tab:blue", label="echoloc, defaults")
        ax.set_xlabel(label)
        ax.set_yscale("log")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].set_ylabel("3-D error of the first object, mm")
    axes[0].legend(loc="upper left")
    fig.suptitle("Real CH101 data (Hahne, ICRA 2023): held-out positions, calibrated on the others")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
