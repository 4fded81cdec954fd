"""`echoloc warmup`, `demo`, `simulate` and `template`."""

from __future__ import annotations

import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import click
import numpy as np
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TextColumn,
    TimeElapsedColumn,
)
from rich.table import Table

from echoloc.cli.app import _check_plot, _finite, _frames_option, _path_option, _progress, cli, stderr, stdout
from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording, read_recording, write_recording
from echoloc.localise.evaluation import evaluate, match
from echoloc.pipeline import (
    frame_echoes,
    frame_objects,
    learn_chain_echo_shape,
    prepare,
    recording_speed_of_sound_m_s,
)
from echoloc.sim.scene import default_scene
from echoloc.sim.scenefile import load_scene, preset_names
from echoloc.sim.simulation import recording_header, simulate, simulate_to_file
from echoloc.tof.envelope_peaks import peak_delay_s
from echoloc.tof.templates import cut_template, write_template

# --- warmup ------------------------------------------------------------------------


@cli.command(name="warmup")
@click.option(
    "--workers",
    type=click.IntRange(1, 256),
    default=2,
    show_default=True,
    help="Also compile the threaded matched filter as `--workers N` runs it (1: skip it).",
)
def warmup_command(workers: int) -> None:
    """Compile the numba kernels now, once, with progress; later runs load them from the cache."""
    from echoloc._jit import HAVE_NUMBA
    from echoloc.warmup import kernels_cold, warm_up_steps

    if not HAVE_NUMBA:
        click.echo("nothing to compile: numba is not installed (pip install 'echoloc[fast]')")
        return

    steps = warm_up_steps(workers)
    cold = kernels_cold()
    start = time.perf_counter()
    with Progress(
        SpinnerColumn(),
        TextColumn("{task.description}"),
        BarColumn(),
        MofNCompleteColumn(),
        TimeElapsedColumn(),
        console=stderr,
        transient=True,
        disable=not stderr.is_terminal,
    ) as progress:
        task = progress.add_task("compiling kernels", total=len(steps))
        for step in steps:
            progress.update(task, description=f"compiling: {step.name}")
            step_start = time.perf_counter()
            step.run()
            progress.advance(task)
            click.echo(f"{step.name}: {time.perf_counter() - step_start:.1f} s")
    state = "compiled" if cold else "loaded from the cache (already compiled)"
    click.echo(f"kernels {state} in {time.perf_counter() - start:.0f} s")


# --- demo --------------------------------------------------------------------------

DEMO_MATCH_RADIUS_M = 0.001
"""The demo's promise: every ball found within 1 mm."""


@cli.command()
@_path_option(
    "-o",
    "--output",
    default=Path("echoloc-demo.h5"),
    show_default=True,
    help="Where to write the demo recording.",
)
@click.option("--frames", "n_frames", type=click.IntRange(1, 100_000), default=20, show_default=True)
@_path_option("--plot", default=None, help="Also draw the first frame to this PNG.")
def demo(output: Path, n_frames: int, plot: Path | None) -> None:
    """Simulate the report's set-up (three balls), locate them and compare with the truth."""
    _check_plot(plot)
    scene = default_scene()
    recording = simulate(scene, n_frames)
    written = write_recording(recording, output)
    chain = prepare(recording)
    results = [frame_objects(chain, frame_echoes(chain, i)) for i in range(n_frames)]
    truth = scene.reflector_positions_m
    first = results[0]

    waveform = scene.waveform()
    stdout.print(
        f"[bold]echoloc demo[/bold]: transmitter at the origin, receivers at (±0.25, 0, 0) and "
        f"(0, ±0.25, 0) m; {waveform.name} × {scene.pulse.cycles_per_bit} cycles at "
        f"{scene.pulse.carrier_hz / 1e3:g} kHz, sampled at {scene.sample_rate_hz / 1e3:g} kHz, "
        f"{scene.temperature_c:g} °C (c = {chain.speed_of_sound_m_s:.2f} m/s)."
    )
    table = Table(title=f"Frame 0 of {n_frames}: three balls (report table 4.3 ranges)")
    for column in (
        "ball",
        "range mm",
        "truth x, y, z (mm)",
        "estimate x, y, z (mm)",
        "error mm",
        "±1σ mm",
        "rx",
    ):
        table.add_column(column, justify="right")
    assert recording.truth_positions_m is not None  # simulate() always records the truth
    evaluation = evaluate(results, recording.truth_positions_m, DEMO_MATCH_RADIUS_M)
    estimates = np.array([o.position_m for o in first.objects]).reshape(-1, 3)
    found_for = {t: e for e, t in match(estimates, truth, DEMO_MATCH_RADIUS_M)}
    for k, position in enumerate(truth):
        if k in found_for:
            found = first.objects[found_for[k]]
            error = float(np.linalg.norm(found.position_m - position))
            table.add_row(
                str(k + 1),
                f"{np.linalg.norm(position) * 1e3:.1f}",
                _mm(position),
                _mm(found.position_m),
                f"{error * 1e3:.3f}",
                _mm(found.std_m, digits=2),
                str(len(found.receivers)),
            )
        else:
            table.add_row(
                str(k + 1), f"{np.linalg.norm(position) * 1e3:.1f}", _mm(position), "not found", "", "", ""
            )
    stdout.print(table)
    max_error_mm = (
        float(np.max(np.linalg.norm(evaluation.errors_m, axis=1))) * 1e3
        if evaluation.n_matched
        else float("nan")
    )
    stdout.print(
        f"Over {n_frames} frames: {evaluation.n_matched} of {evaluation.n_truth} balls found within 1 mm "
        f"(recall {evaluation.recall:.3f}), {evaluation.n_false} false objects, largest error "
        f"{max_error_mm:.3f} mm, RMSE x/y/z {_mm(evaluation.rmse_m, digits=3)} mm."
    )
    stdout.print(
        "±1σ comes from the fit's covariance with the default a-priori path error of "
        f"{chain.locate_options.path_sigma_m * 1e3:g} mm (--path-sigma-m), "
        "which the demo's clean air does not reach."
    )
    stdout.print(f"Recording written to [bold]{written}[/bold]; try `echoloc locate {written}`.")
    if plot is not None:
        from echoloc.plots.frame import plot_frame

        plot_frame(chain, 0, plot)
        stdout.print(f"Plot written to [bold]{plot}[/bold].")


def _mm(values: Any, digits: int = 1) -> str:
    return ", ".join(f"{v * 1e3:.{digits}f}" for v in np.asarray(values))


def _object_cells(obj: Any) -> list[str]:
    """A located object as the tables of `locate` and `stream` show it: x, y, z, ±σ and
    range in mm, receivers, score."""
    x, y, z = obj.position_m * 1e3
    return [
        f"{x:.1f}",
        f"{y:.1f}",
        f"{z:.1f}",
        _mm(obj.std_m, digits=2),
        f"{np.linalg.norm(obj.position_m) * 1e3:.1f}",
        str(len(set(obj.receivers))),
        f"{obj.score:.2f}",
    ]


def _class_cells(obj: Any) -> list[str]:
    """The class with its confidence, and a plane's normal or a corner's or edge's direction."""
    surface = obj.surface
    if surface is None:
        return ["-", "-"]
    direction = surface.normal if surface.normal is not None else surface.edge_direction
    shown = "-" if direction is None else "(" + ", ".join(f"{v:+.3f}" for v in direction) + ")"
    return [f"{surface.kind} {surface.confidence:.2f}", shown]


# --- simulate ----------------------------------------------------------------------


@cli.command(name="simulate", epilog=f"Presets: {', '.join(preset_names())}.")
@click.argument("scene_path", metavar="SCENE", type=click.Path(path_type=Path))
@_path_option("-o", "--output", required=True, help="Recording to write (.h5 or .npz).")
@click.option("--frames", "n_frames", type=click.IntRange(1, 10_000_000), default=1, show_default=True)
@click.option("--seed", type=int, default=None, help="Override the scene's random seed.")
def simulate_command(scene_path: Path, output: Path, n_frames: int, seed: int | None) -> None:
    """Simulate a scene (a TOML file, or a preset shipped with echoloc by name) and write
    the recording, with truth_positions per frame."""
    scene = load_scene(scene_path)
    if seed is not None:
        scene = replace(scene, seed=seed)
    header = recording_header(scene)
    with _progress(n_frames, "simulating", True) as advance:
        written = simulate_to_file(scene, n_frames, output, progress=advance)
    stderr.print(
        f"wrote {n_frames} frame(s) × {header.n_receivers} receivers × "
        f"{header.n_samples} {header.signal_kind} samples to {written}"
    )


# --- template ----------------------------------------------------------------------


@cli.command(name="template")
@click.argument("recording_path", metavar="RECORDING", type=click.Path(path_type=Path))
@_path_option("-o", "--output", required=True, help="Template file (.npz).")
@click.option(
    "--arrival",
    default="truth",
    show_default=True,
    help="When the echo arrives: 'direct' (transmitter to receiver), 'truth' (nearest truth_positions "
    "reflector) or a time in seconds; for envelope and iq recordings 'truth' or 'peaks' (strong "
    "isolated echoes, aligned on their peaks), learnt over every receiver.",
)
@click.option("--receiver", type=int, default=0, show_default=True, help="Receiver to cut from.")
@click.option(
    "--frames", "frames_text", default=None, help="Frames to average: N or START:STOP [default: all]."
)
@click.option("--start-s", type=float, default=None, help="Window start, s [default: arrival - 50 µs].")
@click.option("--stop-s", type=float, default=None, help="Window end, s [default: arrival + pulse + 100 µs].")
@click.option("--name", default=None, help="Name stored in the template [default: the arrival kind].")
def template_command(
    recording_path: Path,
    output: Path,
    arrival: str,
    receiver: int,
    frames_text: str | None,
    start_s: float | None,
    stop_s: float | None,
    name: str | None,
) -> None:
    """Cut a matched-filter template (DIRECT, or a recorded echo such as BALL) from RECORDING.

    The report's templates (ch. 4.1): record the transmitter straight into a receiver
    for DIRECT, or a small ball at a known position for BALL; the template is the
    average of the selected frames around the echo, aligned on each frame's arrival.
    Use it with `echoes`, `locate` or `evaluate --template FILE`.
    """
    recording = read_recording(recording_path)
    if recording.signal_kind != "rf":
        _learn_template(recording, output, arrival, frames_text, name)
        return
    when: str | float = arrival
    if arrival not in ("direct", "truth"):
        try:
            when = float(arrival)
        except ValueError:
            raise EchoLocError(f"--arrival must be 'direct', 'truth' or seconds, got {arrival!r}") from None
        _finite("--arrival", when, minimum=0.0)
    _finite("--start-s", start_s, minimum=0.0)
    _finite("--stop-s", stop_s, minimum=0.0)
    frames = _frames_option(frames_text, recording.n_frames)
    template = cut_template(
        recording,
        receiver=receiver,
        frames=frames,
        arrival=when,  # type: ignore[arg-type]
        speed_of_sound_m_s=recording_speed_of_sound_m_s(recording),
        start_s=start_s,
        stop_s=stop_s,
        name=name,
    )
    written = write_template(template, output)
    stderr.print(
        f"wrote the {template.name} template ({len(template.samples)} samples, echo arriving "
        f"{template.arrival_s * 1e6:.2f} µs in, {len(frames)} frame(s) averaged) to {written}"
    )


def _learn_template(
    recording: Recording, output: Path, arrival: str, frames_text: str | None, name: str | None
) -> None:
    """`echoloc template` on envelope or iq data: the echo shape learnt from the frames,
    conditioned as the envelope-peak chain conditions them (:func:`learn_chain_echo_shape`)."""
    frames = _frames_option(frames_text, recording.n_frames)
    template = learn_chain_echo_shape(prepare(recording, estimator="envelope-peak"), frames, arrival, name)
    written = write_template(template, output)
    stderr.print(
        f"wrote the {template.name} echo shape ({len(template.samples)} points at "
        f"{template.sample_rate_hz:g} Hz, peak {peak_delay_s(template) * 1e6:.1f} µs after the arrival, "
        f"from {len(frames)} frame(s)) to {written}"
    )
