"""The ``echoloc`` command line: a thin edge over the library.

Exit codes (FORMATS.md): 0 success, 2 bad input or usage (one line on stderr), 1 an
internal error.
"""

from __future__ import annotations

import functools
import json
import math
import os
import sys
import warnings
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any

import click
import numpy as np
from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn
from rich.table import Table

from echoloc import __version__
from echoloc.echoes import ESTIMATORS, EchoOptions, FrameEchoes
from echoloc.errors import EchoLocError
from echoloc.evaluate import Evaluation, evaluate
from echoloc.locate import FrameObjects, LocateOptions
from echoloc.output import echoes_record, json_line, objects_record
from echoloc.pipeline import Chain, check_locatable, frame_echoes, frame_objects, prepare
from echoloc.recording import Recording, read_recording, write_recording
from echoloc.scene import default_scene, load_scene
from echoloc.simulate import simulate

# Tables wrap at 80 columns when piped; give them room (COLUMNS still wins).
stdout = Console() if sys.stdout.isatty() else Console(width=int(os.environ.get("COLUMNS", 120)))
# Messages on stderr are one line each, however long: never wrap them.
stderr = Console(stderr=True, soft_wrap=True)


def _frames_option(value: str | None, n_frames: int) -> range:
    """Parse ``--frames``: ``N`` (one frame), ``A:B`` (a slice), or all frames when None."""
    if value is None:
        return range(n_frames)
    try:
        if ":" in value:
            start_text, stop_text = value.split(":", 1)
            start = int(start_text) if start_text else 0
            stop = int(stop_text) if stop_text else n_frames
        else:
            start = int(value)
            stop = start + 1
    except ValueError:
        raise EchoLocError(f"--frames must be N or START:STOP, got {value!r}") from None
    if not (0 <= start < stop <= n_frames):
        raise EchoLocError(f"--frames {value} is outside the recording's {n_frames} frames")
    return range(start, stop)


@dataclass(frozen=True)
class Processing:
    """What echoes, locate and evaluate share: the recording and how to process it."""

    recording_path: Path
    estimator: str
    threshold_db: float
    blanking_s: float
    speed_of_sound_m_s: float | None
    frames_text: str | None
    repair_nonfinite: bool
    path_sigma_m: float | None = None

    def open(self) -> tuple[Recording, Chain, range]:
        """Read the recording, check the options, prepare the chain and the frames to run."""
        _finite("--speed-of-sound", self.speed_of_sound_m_s, positive=True)
        _finite("--blanking-s", self.blanking_s, minimum=0.0)
        _finite("--threshold-db", self.threshold_db)
        _finite("--path-sigma-m", self.path_sigma_m, positive=True)
        recording = read_recording(self.recording_path, repair_nonfinite=self.repair_nonfinite)
        chain = prepare(
            recording,
            estimator=self.estimator,
            echo_options=EchoOptions(threshold_db=self.threshold_db, blanking_s=self.blanking_s),
            speed_of_sound_m_s=self.speed_of_sound_m_s,
        )
        if self.path_sigma_m is not None:
            chain = replace(
                chain, locate_options=replace(chain.locate_options, path_sigma_m=self.path_sigma_m)
            )
        return recording, chain, _frames_option(self.frames_text, recording.n_frames)


_PROCESSING_FIELDS = [f.name for f in fields(Processing)]


def _processing_options(*, locating: bool) -> Callable[[Callable[..., None]], Callable[..., None]]:
    """Add the shared options to a command and hand it one ``Processing`` value."""

    def decorate(func: Callable[..., None]) -> Callable[..., None]:
        @functools.wraps(func)
        def command(**kwargs: Any) -> None:
            processing = Processing(**{k: kwargs.pop(k) for k in _PROCESSING_FIELDS if k in kwargs})
            func(processing, **kwargs)

        decorators = [
            click.argument("recording_path", metavar="RECORDING", type=click.Path(path_type=Path)),
            click.option(
                "--estimator",
                type=click.Choice(sorted(ESTIMATORS)),
                default="matched",
                show_default=True,
                help="Time-of-flight estimator.",
            ),
            click.option(
                "--threshold-db",
                type=float,
                default=EchoOptions.threshold_db,
                show_default=True,
                help="Detection threshold on the echo's output SNR, dB.",
            ),
            click.option(
                "--blanking-s",
                type=float,
                default=0.0,
                show_default=True,
                help="Ignore echoes arriving earlier than this (transmitter ring-down), s.",
            ),
            click.option(
                "--speed-of-sound",
                "speed_of_sound_m_s",
                type=float,
                default=None,
                help="Override the recording's speed of sound, m/s.",
            ),
            click.option("--frames", "frames_text", default=None, help="Frames to process: N or START:STOP."),
            click.option(
                "--repair-nonfinite",
                is_flag=True,
                help="Replace NaN or infinite samples by 0 (with a warning) instead of refusing the file.",
            ),
        ]
        if locating:
            decorators.append(
                click.option(
                    "--path-sigma-m",
                    type=float,
                    default=None,
                    help=f"A-priori path error, m [default: {LocateOptions.path_sigma_m}].",
                )
            )
        for decorator in reversed(decorators):
            command = decorator(command)
        return command

    return decorate


def _finite(name: str, value: float | None, *, positive: bool = False, minimum: float | None = None) -> None:
    """Refuse NaN, infinities and out-of-range option values with one clear line."""
    if value is None:
        return
    if not math.isfinite(value):
        raise EchoLocError(f"{name} must be a finite number, got {value}")
    if positive and not value > 0:
        raise EchoLocError(f"{name} must be > 0, got {value}")
    if minimum is not None and value < minimum:
        raise EchoLocError(f"{name} must be >= {minimum:g}, got {value}")


@contextmanager
def _progress(total: int, label: str, enabled: bool) -> Iterator[Callable[[int], None]]:
    """A rich progress bar on stderr; ``advance(n)`` moves it. Hidden when not a terminal."""
    if not enabled or not stderr.is_terminal:

        def ignore(n: int) -> None:
            del n

        yield ignore
        return
    with Progress(
        TextColumn(label),
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=stderr,
        transient=True,
    ) as progress:
        task = progress.add_task(label, total=total)

        def advance(n: int) -> None:
            progress.advance(task, n)

        yield advance


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="echoloc")
def cli() -> None:
    """Airborne ultrasonic echolocation: coded pulses, time of flight, 3-D obstacle positions.

    Start with `echoloc demo`. Recordings are HDF5 (or NPZ) files in the format of
    FORMATS.md; `echoloc simulate` makes them from a scene file.
    """


# --- demo --------------------------------------------------------------------------


@cli.command()
@click.option(
    "-o",
    "--output",
    type=click.Path(path_type=Path),
    default=Path("echoloc-demo.h5"),
    show_default=True,
    help="Where to write the demo recording.",
)
@click.option("--frames", "n_frames", type=click.IntRange(1, 100_000), default=20, show_default=True)
@click.option(
    "--plot", type=click.Path(path_type=Path), default=None, help="Also draw the first frame to this PNG."
)
def demo(output: Path, n_frames: int, plot: Path | None) -> None:
    """Simulate the report's set-up (three balls), locate them and compare with the truth."""
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
    evaluation = evaluate(
        results,
        recording.truth_positions_m if recording.truth_positions_m is not None else np.zeros((0, 0, 3)),
        0.01,
    )
    for k, position in enumerate(truth):
        estimates = np.array([o.position_m for o in first.objects]).reshape(-1, 3)
        if len(estimates):
            nearest = int(np.argmin(np.linalg.norm(estimates - position, axis=1)))
            found = first.objects[nearest]
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
        f"Over {n_frames} frames: {evaluation.n_matched} of {evaluation.n_truth} balls found "
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
        from echoloc.plot import plot_frame

        plot_frame(chain, 0, plot)
        stdout.print(f"Plot written to [bold]{plot}[/bold].")


def _mm(values: Any, digits: int = 1) -> str:
    return ", ".join(f"{v * 1e3:.{digits}f}" for v in np.asarray(values))


# --- simulate ----------------------------------------------------------------------


@cli.command(name="simulate")
@click.argument("scene_path", metavar="SCENE.toml", type=click.Path(path_type=Path))
@click.option(
    "-o", "--output", type=click.Path(path_type=Path), required=True, help="Recording to write (.h5 or .npz)."
)
@click.option("--frames", "n_frames", type=click.IntRange(1, 10_000_000), default=1, show_default=True)
@click.option("--seed", type=int, default=None, help="Override the scene's random seed.")
def simulate_command(scene_path: Path, output: Path, n_frames: int, seed: int | None) -> None:
    """Simulate a scene file and write the recording, with truth_positions per frame."""
    scene = load_scene(scene_path)
    if seed is not None:
        scene = replace(scene, seed=seed)
    with _progress(n_frames, "simulating", True) as advance:
        recording = simulate(scene, n_frames, progress=advance)
    written = write_recording(recording, output)
    stderr.print(
        f"wrote {n_frames} frame(s) × {recording.n_receivers} receivers × "
        f"{recording.n_samples} samples to {written}"
    )


# --- echoes, locate, evaluate ------------------------------------------------------


@cli.command()
@_processing_options(locating=False)
@click.option("--json", "as_json", is_flag=True, help="JSON Lines per FORMATS.md instead of a table.")
def echoes(processing: Processing, as_json: bool) -> None:
    """Times of flight of the echoes in every frame of RECORDING, per receiver."""
    _, chain, frames = processing.open()
    if as_json:
        for index in frames:
            click.echo(json_line(echoes_record(frame_echoes(chain, index))))
        return
    table = Table(
        title=f"Echoes in {processing.recording_path} ({processing.estimator}, "
        f"c = {chain.speed_of_sound_m_s:.2f} m/s)"
    )
    for column in ("frame", "receiver", "tof µs", "path m", "amplitude", "SNR dB"):
        table.add_column(column, justify="right")
    for index in frames:
        _echo_rows(table, frame_echoes(chain, index))
    stdout.print(table)


def _echo_rows(table: Table, result: FrameEchoes) -> None:
    for receiver, channel in enumerate(result.channels):
        if len(channel.tof_s) == 0:
            table.add_row(str(result.frame), str(receiver), "-", "-", "-", "-")
        for tof, amplitude, snr in zip(channel.tof_s, channel.amplitude, channel.snr_db, strict=True):
            table.add_row(
                str(result.frame),
                str(receiver),
                f"{tof * 1e6:.3f}",
                f"{tof * result.speed_of_sound_m_s:.5f}",
                f"{amplitude:.4g}",
                f"{snr:.1f}",
            )


@cli.command()
@_processing_options(locating=True)
@click.option("--json", "as_json", is_flag=True, help="JSON Lines per FORMATS.md instead of a table.")
def locate(processing: Processing, as_json: bool) -> None:
    """3-D positions of the reflectors in every frame of RECORDING."""
    _, chain, frames = processing.open()
    check_locatable(chain)
    if as_json:
        for index in frames:
            click.echo(json_line(objects_record(frame_objects(chain, frame_echoes(chain, index)))))
        return
    table = Table(title=f"Objects in {processing.recording_path} ({processing.estimator})")
    for column in ("frame", "x mm", "y mm", "z mm", "±σ x, y, z mm", "range mm", "rx", "score"):
        table.add_column(column, justify="right")
    for index in frames:
        _object_rows(table, frame_objects(chain, frame_echoes(chain, index)))
    stdout.print(table)


def _object_rows(table: Table, result: FrameObjects) -> None:
    if not result.objects:
        table.add_row(str(result.frame), "-", "-", "-", "-", "-", "-", "-")
    for obj in result.objects:
        x, y, z = obj.position_m * 1e3
        table.add_row(
            str(result.frame),
            f"{x:.1f}",
            f"{y:.1f}",
            f"{z:.1f}",
            _mm(obj.std_m, digits=2),
            f"{np.linalg.norm(obj.position_m) * 1e3:.1f}",
            str(len(obj.receivers)),
            f"{obj.score:.2f}",
        )


@cli.command(name="evaluate")
@_processing_options(locating=True)
@click.option(
    "--match-radius-m",
    type=float,
    default=0.02,
    show_default=True,
    help="Largest distance of a located object from its true reflector, m.",
)
@click.option("--json", "as_json", is_flag=True, help="One JSON object with the figures.")
def evaluate_command(processing: Processing, match_radius_m: float, as_json: bool) -> None:
    """Compare located objects with the recording's truth_positions: recall, false objects, RMSE."""
    _finite("--match-radius-m", match_radius_m, positive=True)
    recording, chain, frames = processing.open()
    if recording.truth_positions_m is None:
        raise EchoLocError(f"{processing.recording_path}: has no truth_positions to evaluate against")
    check_locatable(chain)
    results = []
    with _progress(len(frames), "locating", not as_json) as advance:
        for index in frames:
            results.append(frame_objects(chain, frame_echoes(chain, index)))
            advance(1)
    report = evaluate(results, recording.truth_positions_m, match_radius_m)
    if as_json:
        click.echo(json.dumps(_evaluation_record(report, processing.estimator)))
        return
    _print_evaluation(report, processing.recording_path, processing.estimator)


def _evaluation_record(report: Evaluation, estimator: str) -> dict[str, Any]:
    return {
        "estimator": estimator,
        "frames": report.n_frames,
        "truth_objects": report.n_truth,
        "located_objects": report.n_located,
        "matched": report.n_matched,
        "recall": report.recall,
        "false_objects": report.n_false,
        "false_rate": report.false_rate,
        "rmse_m": [float(v) for v in report.rmse_m],
        "bias_m": [float(v) for v in report.bias_m],
        "mean_reported_std_m": [float(v) for v in report.mean_std_m],
        "match_radius_m": report.match_radius_m,
    }


def _print_evaluation(report: Evaluation, path: Path, estimator: str) -> None:
    table = Table(title=f"{path}: {report.n_frames} frames, {report.n_truth} true reflectors ({estimator})")
    table.add_column("figure")
    table.add_column("value", justify="right")
    table.add_row("recall", f"{report.recall:.4f} ({report.n_matched}/{report.n_truth})")
    table.add_row("false objects", f"{report.false_rate:.4f} ({report.n_false}/{report.n_located})")
    for axis, rmse, bias, std in zip("xyz", report.rmse_m, report.bias_m, report.mean_std_m, strict=True):
        table.add_row(
            f"{axis}: RMSE / bias / reported σ (mm)",
            f"{rmse * 1e3:.3f} / {bias * 1e3:+.3f} / {std * 1e3:.3f}",
        )
    table.add_row("match radius", f"{report.match_radius_m * 1e3:g} mm")
    stdout.print(table)


# --- entry point -------------------------------------------------------------------


def _show_warning(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    file: Any = None,
    line: str | None = None,
) -> None:
    stderr.print(f"echoloc: warning: {message}", markup=False, highlight=False)


def main(argv: list[str] | None = None) -> None:
    """Run the CLI; bad input becomes one line on stderr and exit code 2."""
    warnings.showwarning = _show_warning
    try:
        cli.main(args=argv, prog_name="echoloc", standalone_mode=False)
    except EchoLocError as error:
        stderr.print(f"echoloc: error: {error}", markup=False, highlight=False)
        sys.exit(2)
    except click.exceptions.Abort:
        stderr.print("echoloc: aborted", markup=False)
        sys.exit(1)
    except click.UsageError as error:
        command = error.ctx.command_path if error.ctx is not None else "echoloc"
        stderr.print(
            f"echoloc: error: {error.format_message()} (see `{command} --help`)",
            markup=False,
            highlight=False,
        )
        sys.exit(2)
    except click.ClickException as error:
        stderr.print(f"echoloc: error: {error.format_message()}", markup=False, highlight=False)
        sys.exit(2 if error.exit_code == 2 else 1)
    except BrokenPipeError:
        # The reader went away (`echoloc locate rec.h5 --json | head`): not an error of ours.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        sys.exit(0)
    except OSError as error:
        stderr.print(f"echoloc: error: {error}", markup=False, highlight=False)
        sys.exit(2)
    except Exception as error:
        stderr.print(
            f"echoloc: internal error: {type(error).__name__}: {error} (please report this)",
            markup=False,
            highlight=False,
        )
        sys.exit(1)
    sys.exit(0)
