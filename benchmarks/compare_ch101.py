"""The CH101 scene preset beside real CH101 recordings: echo widths, SNRs, timing spread, ring-down.

Real data: ``/work/shared/data/ch101-spiel/dev.h5``, converted from the data set of
C. Hahne, "3-Dimensional Sonic Phase-invariant Echo Localization", ICRA 2023,
doi:10.1109/ICRA48891.2023.10161199 (github hahnec/spiel, Apache-2.0).

The preset (``echoloc/scenes/ch101.toml``) is simulated at the real data's target
positions, as many frames at each as the real data has, with its sphere placed so that
its nearest point to the transmitter is the real truth position; an empty-scene
recording of the preset (new noise) is each frame's background, as the real data's
``background`` is. Both are then measured by the same functions
(:mod:`echoloc.tof.envelope_stats`):

- FWHM of the echo in ``frames - background``, samples at 22 kHz;
- SNR, ``20 log10(peak / noise)``, dB, with each channel's noise the robust standard
  deviation of its own subtracted samples away from the echo and the frame start;
- timing spread: the echo peak time minus the geometric arrival, less the channel's
  median, as a robust standard deviation over all frames ("overall") and about each
  target position's own median ("within position": frame-to-frame jitter only);
- ring-down (channel 0) and cross-talk (channels 1-3): peak of the mean background,
  where it is, and how much of it is left 5 samples later.

Writes ``benchmarks/results/ch101_sim_vs_real.png`` and ``.md``.

    python benchmarks/compare_ch101.py [--real PATH] [--scene ch101] [--out benchmarks/results]
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import itertools
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from numpy.typing import NDArray

from echoloc.io.recording import read_recording
from echoloc.sim.reflectors import Sphere
from echoloc.sim.scene import Scene
from echoloc.sim.scenefile import load_scene
from echoloc.sim.simulation import simulate
from echoloc.tof.envelope_stats import (
    EchoFigures,
    FrameStart,
    arrival_samples,
    frame_start_levels,
    measure_echoes,
    robust_sigma,
    within_group_spread,
)

REAL = Path("/work/shared/data/ch101-spiel/dev.h5")
CHANNELS = ("ch0 (tx/rx)", "ch1", "ch2", "ch3")


@dataclasses.dataclass(frozen=True, eq=False)
class Measured:
    """One recording (real or simulated) and its figures."""

    name: str
    frames: NDArray[np.float64]
    background: NDArray[np.float64]
    truth_m: NDArray[np.float64]  # (n_frames, 3)
    groups: NDArray[np.int64]
    arrivals: NDArray[np.float64]
    echoes: EchoFigures
    start: FrameStart


def measure(
    name: str,
    frames: NDArray[np.float64],
    background: NDArray[np.float64],
    truth_m: NDArray[np.float64],
    transmitter_m: NDArray[np.float64],
    receivers_m: NDArray[np.float64],
    speed_of_sound_m_s: float,
    sample_rate_hz: float,
) -> Measured:
    _, groups = np.unique(truth_m, axis=0, return_inverse=True)
    arrivals = arrival_samples(transmitter_m, receivers_m, truth_m, speed_of_sound_m_s, sample_rate_hz)
    return Measured(
        name=name,
        frames=frames,
        background=background,
        truth_m=truth_m,
        groups=np.asarray(groups, dtype=np.int64).reshape(-1),
        arrivals=arrivals,
        echoes=measure_echoes(frames, background, arrivals),
        start=frame_start_levels(background),
    )


def simulate_at(scene: Scene, truth_m: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    """Frames, backgrounds and truth of ``scene``'s sphere moved to each real truth position in turn."""
    spheres = [obj for obj in scene.objects if isinstance(obj, Sphere)]
    radius = spheres[0].radius_m if spheres else 0.01
    positions, inverse, counts = np.unique(truth_m, axis=0, return_inverse=True, return_counts=True)
    inverse = np.asarray(inverse).reshape(-1)
    frames = np.zeros((len(truth_m), len(scene.array.receivers_m), 62))
    background = np.zeros_like(frames)
    truth = np.zeros((len(truth_m), 3))
    for i, (position, count) in enumerate(zip(positions, counts, strict=True)):
        centre = position + radius * position / np.linalg.norm(position)
        rows = np.flatnonzero(inverse == i)
        seed = (scene.seed or 0) * 1000 + 2 * i
        target = dataclasses.replace(scene, objects=(Sphere(centre, radius),), seed=seed)
        empty = dataclasses.replace(scene, objects=(), seed=seed + 1)
        shot = simulate(target, int(count))
        frames[rows] = shot.frames
        background[rows] = simulate(empty, int(count)).frames
        assert shot.truth_positions_m is not None
        truth[rows] = shot.truth_positions_m[:, 0]
    return frames, background, truth


def _pct(values: NDArray[np.float64], q: float) -> NDArray[np.float64]:
    return np.asarray(np.nanpercentile(values, q, axis=0), dtype=float)


def figures(m: Measured) -> dict[str, NDArray[np.float64]]:
    """The compared figures, one value per channel."""
    e = m.echoes
    return {
        "echoes found (share)": np.mean(np.isfinite(e.peak_sample), axis=0),
        "FWHM median (samples)": _pct(e.fwhm_samples, 50),
        "FWHM p10 (samples)": _pct(e.fwhm_samples, 10),
        "FWHM p90 (samples)": _pct(e.fwhm_samples, 90),
        "noise sigma (counts)": e.noise,
        "echo peak median (counts)": _pct(e.amplitude, 50),
        "SNR p10 (dB)": _pct(e.snr_db, 10),
        "SNR median (dB)": _pct(e.snr_db, 50),
        "SNR p90 (dB)": _pct(e.snr_db, 90),
        "peak - arrival, median (samples)": _pct(e.peak_sample - m.arrivals, 50),
        "timing spread overall (samples)": robust_sigma(e.residual_samples, axis=0),
        "timing spread within position (samples)": within_group_spread(e.residual_samples, m.groups),
        "ring-down / cross-talk peak (counts)": m.start.peak,
        "ring-down / cross-talk peak at (sample)": m.start.peak_sample,
        "ring-down / cross-talk 5 samples after its peak (share of peak)": m.start.tail_ratio,
    }


def _aligned_shape(m: Measured) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Median echo normalised to its peak, aligned on the peak sample, and its lags."""
    lags = np.arange(-5, 8)
    diff = m.frames - m.background
    rows = []
    for f, r in zip(*np.nonzero(np.isfinite(m.echoes.peak_sample)), strict=True):
        k = round(float(m.echoes.peak_sample[f, r]))
        if k + lags[0] >= 0 and k + lags[-1] < diff.shape[2]:
            rows.append(diff[f, r, k + lags] / diff[f, r, k])
    return lags.astype(float), np.median(np.array(rows), axis=0)


def plot(real: Measured, sim: Measured, path: Path) -> None:
    fig, axes = plt.subplots(2, 3, figsize=(15, 8.5))
    colours = {"real": "tab:blue", "simulated": "tab:orange"}
    pairs = ((real, "real"), (sim, "simulated"))

    ax = axes[0, 0]
    for m, label in pairs:
        lags, shape = _aligned_shape(m)
        ax.plot(lags, shape, "o-", color=colours[label], label=label)
    ax.axhline(0.5, color="grey", lw=0.8, ls=":")
    ax.set(title="(a) median echo, aligned on its peak", xlabel="samples from peak (22 kHz)",
           ylabel="frames - background, / peak")  # fmt: skip
    ax.legend()

    ax = axes[0, 1]
    bins = np.linspace(1.5, 7.0, 23)
    for m, label in pairs:
        widths = m.echoes.fwhm_samples.ravel()
        ax.hist(widths[np.isfinite(widths)], bins, histtype="step", lw=2, density=True,
                color=colours[label], label=f"{label}: median {np.nanmedian(widths):.2f}")  # fmt: skip
    ax.set(title="(b) echo width, all channels", xlabel="FWHM (samples)", ylabel="density")
    ax.legend()

    ax = axes[0, 2]
    bins = np.linspace(-5, 40, 46)
    for m, label in pairs:
        snr = m.echoes.snr_db.ravel()
        ax.hist(snr[np.isfinite(snr)], bins, histtype="step", lw=2, density=True, color=colours[label],
                label=f"{label}: median {np.nanmedian(snr):.1f} dB")  # fmt: skip
    ax.set(title="(c) echo SNR vs each channel's own noise", xlabel="SNR (dB)", ylabel="density")
    ax.legend()

    ax = axes[1, 0]
    x = np.arange(4)
    for offset, (m, label) in zip((-0.2, 0.2), pairs, strict=True):
        overall = robust_sigma(m.echoes.residual_samples, axis=0)
        within = within_group_spread(m.echoes.residual_samples, m.groups)
        ax.bar(x + offset, overall, 0.38, color=colours[label], alpha=0.45, label=f"{label}: overall")
        ax.bar(x + offset, within, 0.38, color=colours[label], label=f"{label}: within position")
    ax.set_xticks(x, CHANNELS)
    ax.set(title="(d) timing spread of the echo peak (robust sigma)", ylabel="samples (1 = 45.5 µs)")
    ax.legend(fontsize=8)

    ax = axes[1, 1]
    samples = np.arange(16)
    for m, label in pairs:
        mean = np.mean(m.background, axis=0)[:, :16]
        for r in range(4):
            ax.semilogy(samples, np.maximum(mean[r], 1.0), color=colours[label], lw=2 if r == 0 else 1,
                        ls="-" if r == 0 else "--", label=label if r == 0 else None)  # fmt: skip
    ax.set(title="(e) ring-down (ch0, solid) and cross-talk (ch1-3, dashed)", xlabel="sample (22 kHz)",
           ylabel="mean background (counts)")  # fmt: skip
    ax.legend()

    ax = axes[1, 2]
    for m, label in pairs:
        rng = np.linalg.norm(m.truth_m, axis=1)
        amp = m.echoes.amplitude
        ax.scatter(np.repeat(rng, 4), amp.ravel(), s=4, alpha=0.25, color=colours[label])
        edges = np.linspace(0.09, 0.25, 9)
        centres = 0.5 * (edges[1:] + edges[:-1])
        medians = [np.nanmedian(amp[(rng >= a) & (rng < b)]) if np.any((rng >= a) & (rng < b)) else np.nan
                   for a, b in itertools.pairwise(edges)]  # fmt: skip
        ax.plot(centres, medians, "o-", color=colours[label], lw=2, label=f"{label}: median")
    ax.set_yscale("log")
    ax.set(title="(f) echo peak against target range", xlabel="range of the target (m)",
           ylabel="echo peak (counts)")  # fmt: skip
    ax.legend()

    fig.suptitle("CH101: real recordings (SPiEL, Hahne ICRA 2023) vs the echoloc 'ch101' scene preset")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _row(name: str, real: NDArray[np.float64], sim: NDArray[np.float64]) -> str:
    cells = " | ".join(f"{a:.2f} / {b:.2f}" for a, b in zip(real, sim, strict=True))
    return f"| {name} | {cells} |"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--real", type=Path, default=REAL)
    parser.add_argument("--scene", default="ch101", help="scene file or preset name")
    parser.add_argument("--out", type=Path, default=Path(__file__).parent / "results")
    args = parser.parse_args(argv)

    recording = read_recording(args.real)
    assert recording.truth_positions_m is not None
    assert recording.background is not None
    truth = recording.truth_positions_m[:, 0]
    real = measure(
        "real",
        np.asarray(recording.frames, dtype=float),
        np.asarray(recording.background, dtype=float),
        truth,
        recording.transmitters_m[0],
        recording.receivers_m,
        recording.speed_of_sound_m_s or 343.0,
        recording.sample_rate_hz,
    )
    scene = load_scene(args.scene)
    frames, background, sim_truth = simulate_at(scene, truth)
    sim = measure(
        "simulated",
        frames,
        background,
        sim_truth,
        scene.array.transmitters_m[0],
        scene.array.receivers_m,
        scene.speed_of_sound_m_s,
        scene.output_rate_hz,
    )
    args.out.mkdir(parents=True, exist_ok=True)
    png = args.out / "ch101_sim_vs_real.png"
    plot(real, sim, png)
    real_fig, sim_fig = figures(real), figures(sim)
    table = [
        "| figure (real / simulated) | " + " | ".join(CHANNELS) + " |",
        "|---|" + "---|" * len(CHANNELS),
        *(_row(name, real_fig[name], sim_fig[name]) for name in real_fig),
    ]
    text = "\n".join(table)
    print(text)
    md = args.out / "ch101_sim_vs_real.md"
    md.write_text(
        MD_TEMPLATE.format(
            date=datetime.date.today().isoformat(),
            command="python " + " ".join(["benchmarks/compare_ch101.py", *(argv or sys.argv[1:])]),
            frames=len(truth),
            positions=len(np.unique(truth, axis=0)),
            table=text,
        ),
        encoding="utf-8",
    )
    print(f"wrote {png} and {md}")


MD_TEMPLATE = """# CH101 scene preset vs real CH101 recordings

Date: {date}. Command (from the repository root):

    {command}

Real data: `/work/shared/data/ch101-spiel/dev.h5`, {frames} frames at {positions} target
positions, from the data set of C. Hahne, "3-Dimensional Sonic Phase-invariant Echo
Localization", ICRA 2023, doi:10.1109/ICRA48891.2023.10161199 (Apache-2.0).
Simulated: the shipped preset `echoloc/scenes/ch101.toml` (`echoloc simulate ch101`),
its 20 mm ball moved to each real target position (nearest point = the real truth), as
many frames there as the real data has, and an empty-scene recording with new noise as
each frame's background. Both are measured by the same code (`echoloc.tof.envelope_stats`);
see the docstring of `benchmarks/compare_ch101.py` for each figure's definition.

![real vs simulated](ch101_sim_vs_real.png)

Each cell is real / simulated.

{table}

## What the preset models, and how it was fitted

- Geometry, carrier (175 kHz), envelope output at 22 kHz, no `waveform`: as the real file.
- Echo shape: a 16-cycle tone through the PMUT's band (two passes of a 10 kHz
  resonator, `transducer.model = "ch101"`) and the chip's decimating filter
  (`receiver.baseband_filter_s = 120 µs`, 3 stages): a near-Gaussian bump of about 4
  samples FWHM, panel (a). Without the filter the echo rises in one sample and decays
  slowly, unlike the real echoes.
- Ring-down and cross-talk: `ring_down.levels` per receiver (channel 0 is the
  transmitter itself; the others see electrical cross-talk of the drive), decaying
  with 55 µs. The chip's filter delays both to peak at sample 6 (real: 5).
- Noise (`noise.snr_db`) and gain (`receiver.gain`) put echoes and noise in the
  chip's counts; timing jitter (`noise.timing_jitter_s`, per receiver and frame).

## What still differs, and why

- **Timing spread overall vs within position.** The real residuals spread by about
  0.4-0.6 samples over all frames but only about 0.2 samples between frames at the
  same target position. The frame-to-frame part is the chip's jitter plus noise, and
  the preset matches it; the rest is fixed per position: target placement and its
  truth, the target mount, the speed of sound (the file says 343 m/s), and the
  direction-dependent delay of a real PMUT. None of that is the chip's per-frame
  jitter, so the preset does not fake it with a larger jitter; the simulated overall
  spread is therefore smaller than the real one.
- **Peak - arrival.** The simulated echo peaks about 6 samples after its arrival, the
  real one about 2 (the causal chip filter delays it; the real chip's time zero or the
  real truth positions may be offset too). A fixed delay per channel is a calibration
  constant (FORMATS.md), removed from the timing spread above.
- **SNR spread and echo peak against range** (panel f): the simulated echoes follow
  spherical spreading (1/r² for a ball); the real ones fall more slowly with range
  and scatter more at one range (target size and orientation, the mount, multipath
  in the lab), so the simulated SNRs reach about 2-5 dB higher at the top (p90).
- **Noise.** The real "noise" in a subtracted frame is partly clutter that is not
  repeated between a frame and its background (channel 0 most, whose near field
  holds a reflection at samples 13-17 that the preset does not model); the preset's
  noise is white, one level for all channels, so channel 0's extra is not reproduced
  and its simulated SNR is about 3.5 dB higher; the real widths also scatter more
  (p10-p90) for the same reason.
- **Ring-down shape.** The simulated ring-down peaks one sample later (the filter
  that gives the echoes their width delays it too) and the cross-talk of channels 1
  and 3 stays higher 5 samples on (the white noise's envelope mean lifts the simulated
  mean background; the real cross-talk decays faster); the real
  channel 0 background also has a second bump at samples 13-17 (a fixed near
  reflection of the mount or housing) that the preset leaves out.
"""


if __name__ == "__main__":
    main()
