"""The ``echoloc`` command line: a thin edge over the library.

Exit codes (docs/FORMATS.md): 0 success, 2 bad input or usage (one line on stderr), 1 an
internal error.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import os
import sys
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Any

import click
import numpy as np
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    SpinnerColumn,
    TextColumn,
    TimeElapsedColumn,
    TimeRemainingColumn,
)
from rich.table import Table

from echoloc import __version__
from echoloc.errors import EchoLocError, unwritable
from echoloc.io.output import echoes_record, json_line, objects_record
from echoloc.io.recording import Recording, read_recording, write_recording
from echoloc.localise.calibrate import fit_calibration, read_calibration, write_calibration
from echoloc.localise.evaluation import Evaluation, evaluate, frames_at_positions, match
from echoloc.localise.locate import FrameObjects, LocateOptions
from echoloc.physics.air import (
    absorption_db_per_m,
    air_density_kg_m3,
    characteristic_impedance_rayl,
    speed_of_sound_cramer_m_s,
    speed_of_sound_m_s,
)
from echoloc.physics.transducer import (
    PRESETS,
    ShadingKind,
    grating_lobe_angles,
    impulse_response,
    near_field_length_m,
    piston_beam_angles,
    shading_weights,
    transducers_to_cover,
)
from echoloc.physics.waveform import (
    Carrier,
    CodeMetrics,
    WaveformMetrics,
    code_by_name,
    code_metrics,
    waveform_by_name,
    waveform_metrics,
)
from echoloc.pipeline import (
    Chain,
    check_locatable,
    frame_echoes,
    frame_objects,
    learn_chain_echo_shape,
    prepare,
    recording_speed_of_sound_m_s,
    run,
)
from echoloc.sim.scene import default_scene
from echoloc.sim.scenefile import load_scene
from echoloc.sim.simulation import recording_header, simulate, simulate_to_file
from echoloc.tof.conditioning import Conditioning, parse_blind_zone
from echoloc.tof.echoes import THRESHOLD_DB_LIMIT, EchoOptions, FrameEchoes, frame_time_s
from echoloc.tof.envelope_peaks import peak_delay_s
from echoloc.tof.estimators import (
    AUTO,
    ENVELOPE_PEAK_THRESHOLD_DB,
    ESTIMATORS,
    default_threshold_db,
    resolve_estimator,
)
from echoloc.tof.templates import Template, cut_template, read_template, write_template

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
    threshold_db: float | None
    blanking_s: float
    speed_of_sound_m_s: float | None
    frames_text: str | None
    repair_nonfinite: bool
    calibration_path: Path | None = None
    path_sigma_m: float | None = None
    template_path: Path | None = None
    background: bool | None = None
    tvg: bool | None = None
    blind_zone_text: str | None = None
    field_of_view_deg: float | None = None
    method: str = "association"
    workers: int = 1
    positions_text: str | None = None

    def open(self) -> tuple[Recording, Chain, Sequence[int]]:
        """Check the options, read the recording, prepare the chain and pick the frames to run."""
        _finite("--speed-of-sound", self.speed_of_sound_m_s, positive=True)
        _finite("--blanking-s", self.blanking_s, minimum=0.0)
        if self.threshold_db is not None:
            _threshold_db(self.threshold_db)
        _finite("--path-sigma-m", self.path_sigma_m, positive=True)
        _finite("--field-of-view-deg", self.field_of_view_deg, positive=True)
        if self.field_of_view_deg is not None and self.field_of_view_deg > 180:
            raise EchoLocError(f"--field-of-view-deg must be at most 180, got {self.field_of_view_deg:g}")
        EchoOptions(workers=self.workers)  # refuses a bad --workers before the file is read
        template = None if self.template_path is None else read_template(self.template_path)
        recording = read_recording(self.recording_path, repair_nonfinite=self.repair_nonfinite)
        frames: Sequence[int] = _frames_option(self.frames_text, recording.n_frames)
        if self.positions_text is not None:
            if recording.truth_positions_m is None:
                raise EchoLocError(
                    f"{self.recording_path}: --positions needs truth_positions in the recording"
                )
            frames = frames_at_positions(recording.truth_positions_m, self.positions_text, frames)
        return recording, self.chain(recording, template), frames

    def estimator_name(self, recording: Recording) -> str:
        """The estimator that runs: ``--estimator``, or the recording's default for ``auto``."""
        return resolve_estimator(self.estimator, recording)

    def chain(self, recording: Recording, template: Template | None) -> Chain:
        """The chain for ``recording`` with these options; ``template``: the matched filter's or
        the learnt echo shape (None: the recording's own, or the calibration's shape)."""
        threshold_db = self.threshold_db
        if threshold_db is None:
            threshold_db = default_threshold_db(self.estimator_name(recording))
        echo_options = EchoOptions(
            threshold_db=threshold_db, blanking_s=self.blanking_s, template=template, workers=self.workers
        )
        calibration = (
            None
            if self.calibration_path is None
            else read_calibration(self.calibration_path, recording.n_receivers)
        )
        blind_zone = None if self.blind_zone_text is None else parse_blind_zone(self.blind_zone_text)
        conditioning = Conditioning(background=self.background, tvg=self.tvg, blind_zone_s=blind_zone)
        chain = prepare(
            recording,
            estimator=self.estimator,
            echo_options=echo_options,
            speed_of_sound_m_s=self.speed_of_sound_m_s,
            calibration=calibration,
            conditioning=conditioning,
        )
        if self.path_sigma_m is not None:
            chain = replace(
                chain, locate_options=replace(chain.locate_options, path_sigma_m=self.path_sigma_m)
            )
        if self.field_of_view_deg is not None:
            chain = replace(
                chain,
                locate_options=replace(chain.locate_options, field_of_view_deg=self.field_of_view_deg),
            )
        return chain


_PROCESSING_FIELDS = [f.name for f in fields(Processing)]

_WORKERS_OPTION = click.option(
    "--workers",
    type=int,
    default=1,
    show_default=True,
    help="Threads the matched estimator spreads each frame's channels over (-1: one a core; "
    "the other estimators use one); the echoes do not depend on it.",
)


def _located(
    processing: Processing, recording: Recording, chain: Chain, frames: Sequence[int]
) -> Iterator[FrameObjects]:
    """Objects of every frame by the chosen method (``--method``)."""
    if processing.method == "backprojection":
        from echoloc.localise.backprojection import prepare_backprojection, run_backprojection

        bp = prepare_backprojection(
            recording, speed_of_sound_m_s=chain.speed_of_sound_m_s, conditioning=chain.conditioning
        )
        yield from run_backprojection(bp, frames)
        return
    for _, objects in run(chain, frames):
        yield objects


def _processing_options(
    *, locating: bool, calibrated: bool = True
) -> Callable[[Callable[..., None]], Callable[..., None]]:
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
                type=click.Choice([AUTO, *sorted(ESTIMATORS)]),
                default=AUTO,
                show_default=True,
                help="Time-of-flight estimator; auto: matched for rf, envelope-peak for envelope and "
                "iq recordings without a waveform, envelope-fit with one.",
            ),
            click.option(
                "--threshold-db",
                type=float,
                default=None,
                help="Detection threshold on the echo's output SNR, dB "
                f"[default: {EchoOptions.threshold_db:g}; "
                f"envelope-peak {ENVELOPE_PEAK_THRESHOLD_DB:g}, on data without processing gain].",
            ),
            click.option(
                "--blanking-s",
                type=float,
                default=0.0,
                show_default=True,
                help="Ignore echoes arriving earlier than this (transmitter ring-down), s; "
                "with --blind-zone the later of the two applies.",
            ),
            click.option(
                "--background/--no-background",
                default=None,
                help="Subtract the recording's background (empty scene) from every frame "
                "[default: when the recording has one].",
            ),
            click.option(
                "--tvg/--no-tvg",
                default=None,
                help="Undo the receiver's time-varying gain (divide by receiver_gain) "
                "[default: when the recording has one].",
            ),
            click.option(
                "--blind-zone",
                "blind_zone_text",
                metavar="SECONDS|auto",
                default=None,
                help="Report nothing before this time: seconds, or auto (the end of the transmitter's "
                "ring-down found in each frame, plus one pulse length).",
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
                "--positions",
                "positions_text",
                default=None,
                metavar="START:STOP:STEP",
                help="Only the frames of these target positions (distinct truth_positions, ordered by "
                "z, y, x), e.g. 0::2 to calibrate on every other and 1::2 to test on the rest.",
            ),
            click.option(
                "--repair-nonfinite",
                is_flag=True,
                help="Replace NaN or infinite samples by 0 (with a warning) instead of refusing the file.",
            ),
            _WORKERS_OPTION,
            click.option(
                "--template",
                "template_path",
                type=click.Path(path_type=Path),
                default=None,
                help="Template from `echoloc template`: the matched filter's (DIRECT, a recorded echo; "
                "default: the recording's waveform, SENT) or envelope-peak's learnt echo shape "
                "(default: the calibration's).",
            ),
        ]
        if calibrated:
            decorators.append(
                click.option(
                    "--calibration",
                    "calibration_path",
                    type=click.Path(path_type=Path),
                    default=None,
                    help="Speed of sound and receiver delays from `echoloc calibrate`.",
                )
            )
        if locating:
            decorators.append(
                click.option(
                    "--path-sigma-m",
                    type=float,
                    default=None,
                    help=f"A-priori path error, m [default: {LocateOptions.path_sigma_m}].",
                )
            )
            decorators.append(
                click.option(
                    "--method",
                    type=click.Choice(["association", "backprojection"]),
                    default="association",
                    show_default=True,
                    help="Peaks to points (echoes combined across receivers) or points to peaks "
                    "(envelopes back-projected on a 5 mm grid of the cubic metre in front).",
                )
            )
            decorators.append(
                click.option(
                    "--field-of-view-deg",
                    type=float,
                    default=None,
                    help="Half-angle of the beams, degrees: points outside are rejected "
                    "[default: the recording's field_of_view_deg, else 90].",
                )
            )
        for decorator in reversed(decorators):
            command = decorator(command)
        return command

    return decorate


def _finite(
    name: str,
    value: float | None,
    *,
    positive: bool = False,
    minimum: float | None = None,
    maximum: float | None = None,
) -> None:
    """Refuse NaN, infinities and out-of-range option values with one clear line."""
    if value is None:
        return
    if not math.isfinite(value):
        raise EchoLocError(f"{name} must be a finite number, got {value}")
    if positive and not value > 0:
        raise EchoLocError(f"{name} must be > 0, got {value}")
    if minimum is not None and value < minimum:
        raise EchoLocError(f"{name} must be >= {minimum:g}, got {value}")
    if maximum is not None and value > maximum:
        raise EchoLocError(f"{name} must be <= {maximum:g}, got {value}")


def _threshold_db(value: float) -> None:
    """--threshold-db: finite, within :data:`echoloc.tof.echoes.THRESHOLD_DB_LIMIT` either way."""
    _finite("--threshold-db", value, minimum=-THRESHOLD_DB_LIMIT, maximum=THRESHOLD_DB_LIMIT)


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


_KERNEL_COMMANDS = frozenset(
    {"demo", "echoes", "locate", "image", "export", "map", "evaluate", "calibrate", "stream", "bench"}
)
"""The commands that run compiled kernels: on a first run they compile them first."""

FIRST_RUN_NOTICE = (
    "echoloc: compiling the numba kernels on this first run (once, about 3 minutes on a "
    "2-core machine; later runs load them in about a second). `echoloc warmup` compiles "
    "them ahead, with progress."
)


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="echoloc")
@click.pass_context
def cli(context: click.Context) -> None:
    """Airborne ultrasonic echolocation: coded pulses, time of flight, 3-D obstacle positions.

    Start with `echoloc demo`. Recordings are HDF5 (or NPZ) files in the format of
    docs/FORMATS.md; `echoloc simulate` makes them from a scene file.
    """
    # A first run would otherwise sit silent for minutes while numba compiles. Said on a
    # terminal only: scripts and pipes read stderr for errors.
    if context.invoked_subcommand in _KERNEL_COMMANDS and stderr.is_terminal:
        from echoloc.warmup import kernels_cold

        if kernels_cold():
            stderr.print(FIRST_RUN_NOTICE, style="yellow", highlight=False)


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
    from echoloc.warmup import kernels_cold, warm_up_steps

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
@click.option("-o", "--output", type=click.Path(path_type=Path), required=True, help="Template file (.npz).")
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


# --- echoes, locate, evaluate ------------------------------------------------------


@cli.command()
@_processing_options(locating=False)
@click.option("--json", "as_json", is_flag=True, help="JSON Lines per docs/FORMATS.md instead of a table.")
def echoes(processing: Processing, as_json: bool) -> None:
    """Times of flight of the echoes in every frame of RECORDING, per receiver."""
    recording, chain, frames = processing.open()
    if as_json:
        for index in frames:
            click.echo(json_line(echoes_record(frame_echoes(chain, index))))
        return
    table = Table(
        title=f"Echoes in {processing.recording_path} ({processing.estimator_name(recording)}, "
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
@click.option("--json", "as_json", is_flag=True, help="JSON Lines per docs/FORMATS.md instead of a table.")
def locate(processing: Processing, as_json: bool) -> None:
    """3-D positions of the reflectors in every frame of RECORDING."""
    recording, chain, frames = processing.open()
    check_locatable(chain)
    if as_json:
        for objects in _located(processing, recording, chain, frames):
            click.echo(json_line(objects_record(objects)))
        return
    table = Table(title=f"Objects in {processing.recording_path} ({processing.estimator_name(recording)})")
    for column in ("frame", "x mm", "y mm", "z mm", "±σ x, y, z mm", "range mm", "rx", "score"):
        table.add_column(column, justify="right")
    for objects in _located(processing, recording, chain, frames):
        _object_rows(table, objects)
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
            str(len(set(obj.receivers))),
            f"{obj.score:.2f}",
        )


@cli.command(name="image")
@_processing_options(locating=True)
@click.option("--frame", "frame_index", type=int, default=0, show_default=True, help="Frame to image.")
@click.option("--voxel-m", type=float, default=0.005, show_default=True, help="Voxel edge of the grid, m.")
@click.option("-o", "--output", "output_path", required=True, type=click.Path(path_type=Path), help="PNG.")
def image_command(processing: Processing, frame_index: int, voxel_m: float, output_path: Path) -> None:
    """Back-project one frame of RECORDING onto the cubic metre in front and save the image.

    Maximum-intensity projections and slices through the brightest voxel, with the
    objects back-projection locates (crosses) and the recording's truth (circles).
    """
    from echoloc.localise.backprojection import (
        backproject_frame,
        default_grid,
        frame_image,
        prepare_backprojection,
    )
    from echoloc.plots.imaging import save_image_png

    _finite("--voxel-m", voxel_m, positive=True)
    if not 0.001 <= voxel_m <= 0.1:
        raise EchoLocError(f"--voxel-m must be between 0.001 and 0.1 m, got {voxel_m:g}")
    if output_path.suffix.lower() != ".png":
        raise EchoLocError(f"{output_path}: the image is written as PNG (.png)")
    recording, chain, _ = processing.open()
    if not 0 <= frame_index < recording.n_frames:
        raise EchoLocError(f"--frame {frame_index} is outside the recording's {recording.n_frames} frames")
    if recording.transmitters_m.shape[1] != 3:
        raise EchoLocError(f"{processing.recording_path}: images are drawn for 3-D recordings")
    bp = prepare_backprojection(
        recording,
        default_grid(voxel_m),
        speed_of_sound_m_s=chain.speed_of_sound_m_s,
        conditioning=chain.conditioning,
    )
    objects = backproject_frame(bp, frame_index)
    truth = None
    if recording.truth_positions_m is not None:
        rows = recording.truth_positions_m[frame_index]
        truth = rows[np.all(np.isfinite(rows), axis=1)]
    located = np.array([o.position_m for o in objects.objects]).reshape(-1, 3)
    written = save_image_png(
        frame_image(bp, frame_index),
        output_path,
        objects_m=located,
        truth_m=truth,
        title=f"{processing.recording_path.name}, frame {frame_index}: {len(located)} objects",
    )
    stdout.print(f"{len(located)} objects in frame {frame_index}; image written to {written}")


@cli.command(name="export")
@_processing_options(locating=True)
@click.option(
    "-o",
    "--output",
    "output_path",
    required=True,
    type=click.Path(path_type=Path),
    help="OUT.mcap (ROS 2 Jazzy PointCloud2 + Range per receiver) or OUT.ply (points).",
)
@click.option("--start-time-s", type=float, default=0.0, show_default=True, help="ROS time of frame 0, s.")
@click.option("--ascii", "ascii_ply", is_flag=True, help="PLY as text instead of binary.")
@click.option("--per-frame", is_flag=True, help="PLY: one file per frame (OUT_000000.ply, ...).")
def export_command(
    processing: Processing, output_path: Path, start_time_s: float, ascii_ply: bool, per_frame: bool
) -> None:
    """Locate every frame of RECORDING and write the objects for robots: MCAP or PLY.

    MCAP: sensor_msgs/msg/PointCloud2 on /echoloc/objects (x, y, z, intensity, the
    covariance's diagonal) and sensor_msgs/msg/Range on /echoloc/range/rx{N}, in the
    frame echoloc_sensor_optical_frame (REP 103), with /tf_static for the receivers.
    """
    from echoloc.io.export import write_mcap, write_ply

    suffix = output_path.suffix.lower()
    if suffix not in (".mcap", ".ply"):
        raise EchoLocError(f"{output_path}: choose the format by extension, .mcap or .ply")
    given = click.get_current_context().get_parameter_source
    if suffix == ".mcap":
        _finite("--start-time-s", start_time_s, minimum=0.0, maximum=2**31 - 1)  # ROS time: int32 seconds
        if ply_only := [name for name, on in (("--ascii", ascii_ply), ("--per-frame", per_frame)) if on]:
            verb = "is" if len(ply_only) == 1 else "are"
            _warn(f"{' and '.join(ply_only)} {verb} for PLY; MCAP is binary, one file: ignored")
    elif given("start_time_s") is not click.core.ParameterSource.DEFAULT:
        _warn("--start-time-s sets MCAP's ROS times; PLY has no time stamps: ignored")
    recording, chain, frames = processing.open()
    check_locatable(chain)
    results = []
    with _progress(len(frames), "locating", True) as advance:
        for objects in _located(processing, recording, chain, frames):
            results.append(objects)
            advance(1)
    if suffix == ".mcap":
        count = write_mcap(output_path, recording, results, start_time_s=start_time_s)
        stdout.print(f"wrote {count} messages ({len(results)} frames) to {output_path}")
    else:
        written = write_ply(output_path, results, binary=not ascii_ply, per_frame=per_frame)
        points = sum(len(r.objects) for r in results)
        where = written[0] if len(written) == 1 else f"{len(written)} files like {written[0]}"
        stdout.print(f"wrote {points} points ({len(results)} frames) to {where}")


_MAP_FORMATS = (".png", ".npz", ".ply", ".bt", ".ot", ".mcap")


def _check_writable(path: Path) -> None:
    """Refuse an output that cannot be written before the work that would fill it."""
    if problem := unwritable(path):
        raise EchoLocError(f"{path}: {problem}")


def _check_plot(path: Path | None) -> None:
    """Refuse a ``--plot`` target matplotlib cannot draw to, or cannot write, before the work."""
    if path is None:
        return
    from matplotlib.backend_bases import FigureCanvasBase

    formats = FigureCanvasBase.get_supported_filetypes()
    if path.suffix.lower().lstrip(".") not in formats:
        shown = path.suffix or "no extension"
        raise EchoLocError(
            f"{path}: --plot draws .png, .svg, .pdf or another matplotlib format, not {shown!r}"
        )
    _check_writable(path)


_MAX_SAMPLE_RATE_HZ = 100e6
"""The highest sample rate `waveform` takes: 100 MHz, far above any ultrasonic ADC's, where a
millisecond's pulse is already 100 000 samples (at 1 THz it would be 10^9)."""


def _extent_option(text: str | None, dims: int) -> list[tuple[float, float]] | None:
    """``--extent-m``: "x0,x1,z0,z1" for a floor plan, "x0,x1,y0,y1,z0,z1" in 3-D."""
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise EchoLocError(
            f"--extent-m: expected {2 * dims} numbers separated by commas, got {text!r}"
        ) from None
    if len(values) != 2 * dims or not all(math.isfinite(v) for v in values):
        raise EchoLocError(f"--extent-m: expected {2 * dims} finite numbers, got {text!r}")
    pairs = [(values[2 * i], values[2 * i + 1]) for i in range(dims)]
    if any(high <= low for low, high in pairs):
        raise EchoLocError(f"--extent-m: every range must go from low to high, got {text!r}")
    return pairs


@cli.command(name="map")
@_processing_options(locating=True)
@click.option(
    "-o",
    "--output",
    "output_path",
    required=True,
    type=click.Path(path_type=Path),
    help="OUT.png (picture), .npz (arrays), .ply (occupied cells), .bt/.ot (OctoMap) "
    "or .mcap (ROS 2: nav_msgs/OccupancyGrid or a cloud, /tf, objects).",
)
@click.option("--cell-m", type=float, default=0.02, show_default=True, help="Cell edge, m.")
@click.option(
    "--3d", "three_d", is_flag=True, help="A 3-D grid instead of the floor plan (x-z at one height)."
)
@click.option(
    "--height-m",
    type=float,
    default=None,
    help="Height (y) of the floor plan, m [default: the sensor's mean].",
)
@click.option(
    "--extent-m",
    "extent_text",
    default=None,
    help="Grid extent: x0,x1,z0,z1 (floor plan) or x0,x1,y0,y1,z0,z1 (3-D), m "
    "[default: everywhere the sensor could hear].",
)
@click.option(
    "--trajectory",
    "trajectory_path",
    type=click.Path(path_type=Path),
    default=None,
    help="Sensor poses, TUM format (time x y z qx qy qz qw per line) "
    "[default: the recording's sensor_poses].",
)
@click.option(
    "--objects/--no-objects",
    "with_objects",
    default=True,
    show_default=True,
    help="Also add the located objects with their covariance.",
)
def map_command(
    processing: Processing,
    output_path: Path,
    cell_m: float,
    three_d: bool,
    height_m: float | None,
    extent_text: str | None,
    trajectory_path: Path | None,
    with_objects: bool,
) -> None:
    """Build an occupancy grid from every frame of RECORDING and write it; the format by extension.

    Each receiver's echoes clear the beam before the first echo and mark the echo's
    arc (ellipse with the transmitter and receiver as foci) occupied; located objects
    add their covariance. The map frame is the frame of the sensor poses (the
    recording's sensor_poses or --trajectory); without poses, the sensor frame.
    """
    from echoloc.maps.map_export import write_grid_npz, write_grid_ply, write_map_mcap, write_octomap
    from echoloc.maps.mapping import chain_accumulator, choose_grid, frame_poses, integrate, read_trajectory
    from echoloc.plots.maps import plot_grid

    suffix = output_path.suffix.lower()
    if suffix not in _MAP_FORMATS:
        raise EchoLocError(f"{output_path}: choose the format by extension: {', '.join(_MAP_FORMATS)}")
    _finite("--cell-m", cell_m, positive=True)
    if not 0.001 <= cell_m <= 1.0:
        raise EchoLocError(f"--cell-m must be between 0.001 and 1 m, got {cell_m:g}")
    if height_m is not None:
        _finite("--height-m", height_m)
        if three_d:
            raise EchoLocError(
                "--height-m sets the floor plan's height; a --3d grid takes --extent-m instead"
            )
    _check_writable(output_path)
    if processing.method != "association":
        raise EchoLocError(
            "map reads every receiver's echoes and the association's objects; "
            "--method backprojection is for locate, evaluate, export and image"
        )
    extent = _extent_option(extent_text, 3 if three_d else 2)
    trajectory = read_trajectory(trajectory_path) if trajectory_path is not None else None
    recording, chain, frames = processing.open()
    poses = frame_poses(recording, trajectory)
    spec = choose_grid(
        recording,
        poses[list(frames)],
        cell_m,
        chain.speed_of_sound_m_s,
        three_d=three_d,
        extent_m=extent,
        height_m=height_m,
    )
    accumulator = chain_accumulator(chain, spec, path_sigma_m=processing.path_sigma_m)
    located: list[FrameObjects] = []

    def results() -> Iterator[tuple[FrameEchoes, FrameObjects | None]]:
        for echoes, objects in run(chain, frames):
            located.append(objects)
            yield echoes, objects if with_objects else None

    started = time.perf_counter()
    with _progress(len(frames), "mapping", True) as advance:
        grid = integrate(accumulator, results(), poses, progress=advance)
    elapsed = time.perf_counter() - started
    if suffix == ".png":
        written = plot_grid(grid, output_path, sensor_path_m=poses[list(frames), :3])
    elif suffix == ".npz":
        written = write_grid_npz(grid, output_path)
    elif suffix == ".ply":
        written = write_grid_ply(grid, output_path)
    elif suffix in (".bt", ".ot"):
        written = write_octomap(grid, output_path)
    else:
        times = np.array([frame_time_s(recording, i) for i in range(recording.n_frames)])
        write_map_mcap(
            output_path,
            grid,
            poses=poses,
            frame_times_s=times,
            frames=list(frames),
            objects_per_frame=located,
        )
        written = output_path
    n_cells = spec.n_cells
    occupied = int(grid.occupied().sum())
    free = int(grid.free().sum())
    known = int(grid.known().sum())
    shape = " x ".join(str(n) for n in spec.shape)
    stdout.print(
        f"{len(frames)} frames mapped in {elapsed:.1f} s "
        f"({len(frames) / max(elapsed, 1e-9):.0f} frames/s, echoes and objects included) onto "
        f"{shape} cells of {cell_m * 100:g} cm: {occupied} occupied, {free} free, "
        f"{n_cells - known} unknown; written to {written}"
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
        for objects in _located(processing, recording, chain, frames):
            results.append(objects)
            advance(1)
    report = evaluate(results, recording.truth_positions_m, match_radius_m)
    if as_json:
        click.echo(
            json.dumps(
                _json_safe(_evaluation_record(report, processing.estimator_name(recording))),
                allow_nan=False,
            )
        )
        return
    _print_evaluation(report, processing.recording_path, processing.estimator_name(recording))


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


@cli.command(name="calibrate")
@_processing_options(locating=False, calibrated=False)
@click.option(
    "-o", "--output", type=click.Path(path_type=Path), required=True, help="Calibration JSON to write."
)
def calibrate_command(processing: Processing, output: Path) -> None:
    """Fit the speed of sound and a delay per receiver from frames with known targets (truth_positions).

    The file also holds the path error measured from the fit's residuals, which `locate
    --calibration` assumes, and, for envelope-peak (envelope or iq data without a
    waveform), the echo shape learnt from these targets.
    """
    recording, chain, frames = processing.open()
    if recording.truth_positions_m is None:
        raise EchoLocError(f"{processing.recording_path}: has no truth_positions to calibrate against")
    shape = None
    if processing.estimator_name(recording) == "envelope-peak" and processing.template_path is None:
        # No pulse is known: learn the echo's shape from these frames' known targets (the
        # report's BALL template), then time the echoes with it.
        shape = learn_chain_echo_shape(chain, frames, "truth", "learnt")
        chain = processing.chain(recording, shape)
    echoes = []
    with _progress(len(frames), "finding echoes", True) as advance:
        for index in frames:
            echoes.append(frame_echoes(chain, index))
            advance(1)
    calibration = fit_calibration(
        recording, echoes, speed_of_sound_m_s=chain.speed_of_sound_m_s, echo_shape=shape
    )
    written = write_calibration(calibration, output)
    delays = ", ".join(f"{d * 1e6:+.3f}" for d in calibration.receiver_delays_s)
    sigma = calibration.path_sigma_m or 0.0
    learnt = "" if shape is None else "; the echo shape learnt from them"
    how = "fitted; assumed" if calibration.speed_fitted else "kept: the targets do not determine it; assumed"
    stdout.print(
        f"speed of sound {calibration.speed_of_sound_m_s:.3f} m/s ({how} "
        f"{chain.speed_of_sound_m_s:.3f}); "
        f"receiver delays {delays} µs; {calibration.echoes_used} echoes from {len(frames)} frames, "
        f"residual {calibration.residual_rms_s * 1e9:.1f} ns rms, path σ {sigma * 1e3:.2f} mm{learnt}. "
        f"Written to {written}."
    )


# --- physics: waveform, air, beam ---------------------------------------------------


def _metrics_record(metrics: WaveformMetrics) -> dict[str, float]:
    return {k: float(v) for k, v in asdict(metrics).items()}


def _json_safe(value: Any) -> Any:
    """Plain JSON values: numpy numbers become floats, NaN and infinities become null."""
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer):
        return int(value)
    return value


@cli.command(name="waveform")
@click.argument("name")
@click.option(
    "--carrier", "carrier_hz", type=float, default=50e3, show_default=True, help="Carrier frequency, Hz."
)
@click.option("--cycles-per-bit", type=int, default=4, show_default=True, help="Carrier cycles per code bit.")
@click.option("--sample-rate", "sample_rate_hz", type=float, default=200e3, show_default=True, help="Hz.")
@click.option("--carrier-shape", type=click.Choice(["sine", "square"]), default="sine", show_default=True)
@click.option(
    "--transducer",
    "transducer_name",
    type=click.Choice([*PRESETS, "none"]),
    default="electrostatic50",
    show_default=True,
    help="Transmit-receive pair whose band-pass response the echo goes through.",
)
@click.option(
    "--speed-of-sound", "speed_of_sound_m_s", type=float, default=343.2, show_default=True, help="m/s."
)
@click.option("--json", "as_json", is_flag=True, help="One JSON object with the figures.")
@click.option(
    "--plot", type=click.Path(path_type=Path), default=None, help="Draw pulse, spectrum and correlation."
)
def waveform_command(
    name: str,
    carrier_hz: float,
    cycles_per_bit: int,
    sample_rate_hz: float,
    carrier_shape: Carrier,
    transducer_name: str,
    speed_of_sound_m_s: float,
    as_json: bool,
    plot: Path | None,
) -> None:
    """Figures of merit of a pulse NAME, before and after a transducer pair.

    NAME is a code on a carrier (barker13, barker4b, golay16a, mls7, kasami6:2), a
    burst (tone16, polaroid) or a chirp (lfm, hfm). Reports the peak-to-sidelobe
    ratio, integrated sidelobe level, -3 dB main lobe and range resolution of the
    matched filter: for the emitted pulse, and after the transducer pair with the
    emitted pulse as template (the report's SENT) and with the received pulse
    (matched).
    """
    for option, value in (("--carrier", carrier_hz), ("--sample-rate", sample_rate_hz)):
        _finite(option, value, positive=True)
    _finite("--sample-rate", sample_rate_hz, maximum=_MAX_SAMPLE_RATE_HZ)
    if not carrier_hz < sample_rate_hz / 2:
        nyquist_hz = sample_rate_hz / 2
        raise EchoLocError(
            f"--carrier {carrier_hz:g} Hz must be below half --sample-rate ({nyquist_hz:g} Hz)"
        )
    _finite("--speed-of-sound", speed_of_sound_m_s, positive=True)
    _check_plot(plot)
    pulse = waveform_by_name(
        name,
        carrier_hz=carrier_hz,
        cycles_per_bit=cycles_per_bit,
        sample_rate_hz=sample_rate_hz,
        carrier=carrier_shape,
    )
    rows: list[tuple[str, WaveformMetrics]] = [
        ("emitted (autocorrelation)", waveform_metrics(pulse, speed_of_sound_m_s=speed_of_sound_m_s))
    ]
    transducer = None if transducer_name == "none" else PRESETS[transducer_name]
    if transducer is not None:
        response = impulse_response(transducer, sample_rate_hz)
        for label, template in (("SENT template", "sent"), ("matched", "received")):
            rows.append(
                (
                    f"after {transducer.name} pair, {label}",
                    waveform_metrics(
                        pulse, response=response, template=template, speed_of_sound_m_s=speed_of_sound_m_s
                    ),
                )
            )
    try:
        code: CodeMetrics | None = code_metrics(code_by_name(name))
    except EchoLocError:
        code = None
    if as_json:
        record: dict[str, Any] = {
            "waveform": pulse.name,
            "sample_rate_hz": pulse.sample_rate_hz,
            "carrier_hz": pulse.carrier_hz,
            "samples": len(pulse.samples),
            "duration_s": pulse.duration_s,
            "transducer": transducer_name,
            "code": None if code is None else {k: float(v) for k, v in asdict(code).items()},
            "metrics": {label: _metrics_record(m) for label, m in rows},
        }
        click.echo(json.dumps(_json_safe(record), allow_nan=False))
    else:
        stdout.print(
            f"[bold]{pulse.name}[/bold]: {len(pulse.samples)} samples at {sample_rate_hz / 1e3:g} kHz, "
            f"{pulse.duration_s * 1e3:.4g} ms, carrier {pulse.carrier_hz / 1e3:g} kHz"
            + (
                ""
                if code is None
                else f"; code: PSL {code.psl:g} of {code.length}, merit factor {code.merit_factor:.2f}"
            )
        )
        table = Table()
        for column in (
            "matched-filter output",
            "PSLR",
            "PSLR dB",
            "ISLR dB",
            "-3 dB lobe µs",
            "resolution mm",
            "peak lag µs",
        ):
            table.add_column(column, justify="right")
        for label, m in rows:
            table.add_row(
                label,
                f"{m.pslr_ratio:.2f}",
                f"{m.pslr_db:.1f}",
                f"{m.islr_db:.1f}",
                f"{m.mainlobe_width_s * 1e6:.1f}",
                f"{m.range_resolution_m * 1e3:.2f}",
                f"{m.peak_lag_s * 1e6:.1f}",
            )
        stdout.print(table)
    if plot is not None:
        from echoloc.plots.physics import plot_waveform

        written = plot_waveform(pulse, plot, transducer=transducer)
        stderr.print(f"plot written to {written}")


@cli.command(name="air")
@click.option("--temperature", "temperature_c", type=float, default=20.0, show_default=True, help="°C.")
@click.option(
    "--humidity", "relative_humidity", type=float, default=0.5, show_default=True, help="Fraction 0..1."
)
@click.option("--pressure", "pressure_pa", type=float, default=101325.0, show_default=True, help="Pa.")
@click.option(
    "--frequency",
    "frequencies_hz",
    type=float,
    multiple=True,
    default=(40e3, 50e3),
    show_default=True,
    help="Frequencies for absorption, Hz (repeat the option for several).",
)
@click.option("--json", "as_json", is_flag=True, help="One JSON object with the figures.")
@click.option(
    "--plot", type=click.Path(path_type=Path), default=None, help="Draw absorption and speed of sound."
)
def air_command(
    temperature_c: float,
    relative_humidity: float,
    pressure_pa: float,
    frequencies_hz: tuple[float, ...],
    as_json: bool,
    plot: Path | None,
) -> None:
    """Speed of sound, impedance and absorption (ISO 9613-1) for the given air."""
    _check_plot(plot)
    _finite("--temperature", temperature_c, minimum=-90.0)
    if temperature_c > 100:
        raise EchoLocError(f"--temperature must be at most 100 °C, got {temperature_c}")
    _finite("--humidity", relative_humidity, minimum=0.0)
    if relative_humidity > 1:
        raise EchoLocError(f"--humidity is a fraction 0..1, got {relative_humidity}")
    _finite("--pressure", pressure_pa, positive=True)
    for f in frequencies_hz:
        _finite("--frequency", f, positive=True)
    c = float(speed_of_sound_m_s(temperature_c, relative_humidity, pressure_pa))
    try:
        c_cramer: float | None = float(
            speed_of_sound_cramer_m_s(temperature_c, relative_humidity, pressure_pa)
        )
    except EchoLocError:
        c_cramer = None  # outside Cramer's range of validity
    density = float(air_density_kg_m3(temperature_c, relative_humidity, pressure_pa))
    impedance = float(characteristic_impedance_rayl(density, c))
    freqs = np.array(frequencies_hz, dtype=float)
    alpha = absorption_db_per_m(freqs, temperature_c, relative_humidity, pressure_pa)
    if as_json:
        click.echo(
            json.dumps(
                {
                    "temperature_c": temperature_c,
                    "relative_humidity": relative_humidity,
                    "pressure_pa": pressure_pa,
                    "speed_of_sound_m_s": c,
                    "speed_of_sound_cramer_m_s": c_cramer,
                    "density_kg_m3": density,
                    "impedance_rayl": impedance,
                    "absorption": [
                        {"frequency_hz": float(f), "wavelength_m": c / float(f), "db_per_m": float(a)}
                        for f, a in zip(freqs, alpha, strict=True)
                    ],
                }
            )
        )
    else:
        stdout.print(
            f"Air at {temperature_c:g} °C, {relative_humidity:.0%} RH, {pressure_pa / 1e3:g} kPa: "
            f"c = {c:.2f} m/s (ideal mixture)"
            + (f", {c_cramer:.2f} m/s (Cramer 1993)" if c_cramer is not None else ", outside Cramer's range")
            + f"; ρ = {density:.4f} kg/m³; Z = ρc = {impedance:.1f} rayl"
        )
        table = Table()
        for column in (
            "frequency kHz",
            "wavelength mm",
            "absorption dB/m",
            "loss at 1 m range dB",
            "at 2 m range dB",
        ):
            table.add_column(column, justify="right")
        for f, a in zip(freqs, alpha, strict=True):
            table.add_row(f"{f / 1e3:g}", f"{c / f * 1e3:.3f}", f"{a:.3f}", f"{2 * a:.2f}", f"{4 * a:.2f}")
        stdout.print(table)
        stdout.print("Losses are absorption over the two-way path only (spreading comes on top).")
    if plot is not None:
        from echoloc.plots.physics import plot_air

        written = plot_air(
            plot,
            temperature_c=temperature_c,
            relative_humidity=relative_humidity,
            pressure_pa=pressure_pa,
            frequencies_hz=freqs,
        )
        stderr.print(f"plot written to {written}")


@cli.command(name="beam")
@click.option(
    "--transducer",
    "transducer_name",
    type=click.Choice(list(PRESETS)),
    default="electrostatic50",
    show_default=True,
)
@click.option("--radius-m", type=float, default=None, help="Piston radius, m [default: the preset's].")
@click.option(
    "--frequency", "frequency_hz", type=float, default=None, help="Hz [default: the preset's centre]."
)
@click.option(
    "--speed-of-sound", "speed_of_sound_m_s", type=float, default=343.2, show_default=True, help="m/s."
)
@click.option(
    "--elements", type=click.IntRange(1, 1000), default=1, show_default=True, help="Line array size."
)
@click.option(
    "--spacing-m", type=float, default=None, help="Element spacing, m [default: half a wavelength]."
)
@click.option("--steer-deg", type=float, default=0.0, show_default=True, help="Steering angle, degrees.")
@click.option(
    "--shading", type=click.Choice(["uniform", "hann", "chebyshev"]), default="uniform", show_default=True
)
@click.option(
    "--fov-deg", type=float, default=90.0, show_default=True, help="Field of view to cover, degrees."
)
@click.option("--json", "as_json", is_flag=True, help="One JSON object with the figures.")
@click.option("--plot", type=click.Path(path_type=Path), default=None, help="Draw the beam pattern (polar).")
def beam_command(
    transducer_name: str,
    radius_m: float | None,
    frequency_hz: float | None,
    speed_of_sound_m_s: float,
    elements: int,
    spacing_m: float | None,
    steer_deg: float,
    shading: ShadingKind,
    fov_deg: float,
    as_json: bool,
    plot: Path | None,
) -> None:
    """Beam widths of a transducer (exact and as the report approximates them), and of a line array."""
    _check_plot(plot)
    preset = PRESETS[transducer_name]
    _finite("--radius-m", radius_m, positive=True)
    _finite("--frequency", frequency_hz, positive=True)
    _finite("--speed-of-sound", speed_of_sound_m_s, positive=True)
    _finite("--spacing-m", spacing_m, positive=True)
    _finite("--steer-deg", steer_deg)
    _finite("--fov-deg", fov_deg, positive=True)
    transducer = replace(preset, radius_m=radius_m) if radius_m is not None else preset
    f = frequency_hz or transducer.centre_frequency_hz
    c = speed_of_sound_m_s
    beam = piston_beam_angles(transducer.radius_m, f, c)
    if not math.isfinite(beam.full_angle_3db_rad):
        raise EchoLocError(
            f"a piston of radius {transducer.radius_m:g} m at {f:g} Hz has ka = {beam.ka:.3g} < 1.616: "
            "it never falls 3 dB, so it has no beam width (raise --radius-m or --frequency)"
        )
    wavelength = c / f
    spacing = spacing_m if spacing_m is not None else wavelength / 2
    steer = math.radians(steer_deg)
    grating = grating_lobe_angles(spacing, f, c, steer) if elements > 1 else np.zeros(0)
    cover = transducers_to_cover(fov_deg, beam.full_angle_3db_deg)
    record: dict[str, Any] = {
        "transducer": transducer.name,
        "radius_m": transducer.radius_m,
        "frequency_hz": f,
        "wavelength_m": wavelength,
        "ka": beam.ka,
        "full_angle_3db_deg": beam.full_angle_3db_deg,
        "report_full_angle_3db_deg": math.degrees(2 * beam.report_half_angle_3db_rad),
        "full_angle_null_deg": beam.full_angle_null_deg,
        "report_full_angle_null_deg": math.degrees(2 * beam.report_half_angle_null_rad),
        "near_field_m": near_field_length_m(transducer.radius_m, f, c),
        "transducers_for_fov": cover,
        "fov_deg": fov_deg,
    }
    if elements > 1:
        record |= {
            "elements": elements,
            "spacing_m": spacing,
            "steer_deg": steer_deg,
            "grating_lobes_deg": [math.degrees(a) for a in grating],
        }
    if as_json:
        click.echo(json.dumps(_json_safe(record), allow_nan=False))
    else:
        table = Table(
            title=f"{transducer.name}: piston radius {transducer.radius_m * 1e3:.2f} mm at {f / 1e3:g} kHz"
        )
        table.add_column("figure")
        table.add_column("exact", justify="right")
        table.add_column("report's approximation", justify="right")
        table.add_row("ka", f"{beam.ka:.2f}", "")
        table.add_row(
            "-3 dB full beam, °",
            f"{beam.full_angle_3db_deg:.2f}",
            f"{record['report_full_angle_3db_deg']:.2f}",
        )
        table.add_row(
            "first nulls, full angle, °",
            f"{beam.full_angle_null_deg:.2f}",
            f"{record['report_full_angle_null_deg']:.2f}",
        )
        table.add_row("near field a²/λ, mm", f"{record['near_field_m'] * 1e3:.1f}", "")
        table.add_row(f"transducers to cover {fov_deg:g}°", str(cover), "")
        if elements > 1:
            lobes = ", ".join(f"{math.degrees(a):.1f}" for a in grating) or "none"
            table.add_row(f"{elements} elements at {spacing * 1e3:.2f} mm: grating lobes, °", lobes, "")
        stdout.print(table)
    if plot is not None:
        from echoloc.plots.physics import plot_beam

        written = plot_beam(
            plot,
            transducer=transducer,
            frequency_hz=f,
            speed_of_sound=c,
            elements=elements,
            spacing_m=spacing,
            steer_rad=steer,
            weights=shading_weights(elements, shading) if elements > 1 else None,
        )
        stderr.print(f"plot written to {written}")


# --- design: uncertainty and receiver spacing --------------------------------------


@cli.command(name="design")
@click.option(
    "--path-m",
    type=float,
    default=None,
    help="Hold the path l = l1 = l2, m, as the report's figure 4.13 does [default: 1.0].",
)
@click.option("--range-m", type=float, default=None, help="Hold the reflector's range instead, m.")
@click.option(
    "--path-error-m", type=float, default=0.005, show_default=True, help="Path error Δl (and path std), m."
)
@click.option(
    "--spacing-m",
    type=float,
    default=None,
    help="Spacing d for the figure 4.12 area and the GDOP map, m [default: the recommended one].",
)
@click.option(
    "--max-cross-range-error-m",
    type=float,
    default=None,
    help="Across-beam error allowed, m [default: the path error].",
)
@click.option(
    "--max-range-error-m", type=float, default=None, help="Range error allowed, m: an upper spacing limit."
)
@click.option(
    "--scene",
    "scene_path",
    metavar="SCENE.toml",
    type=click.Path(path_type=Path),
    default=None,
    help="Array for the GDOP map [default: the report's cross with spacing d].",
)
@click.option("--plane", type=click.Choice(["xz", "yz", "xy"]), default="xz", show_default=True)
@click.option(
    "--offset-m",
    type=float,
    default=None,
    help="Third coordinate of the plane, m [default: 0, or the study's range for the xy plane].",
)
@click.option(
    "-o", "--output", type=click.Path(path_type=Path), default=None, help="Directory for the three PNGs."
)
@click.option("--json", "as_json", is_flag=True, help="One JSON object with the figures.")
def design_command(
    path_m: float | None,
    range_m: float | None,
    path_error_m: float,
    spacing_m: float | None,
    max_cross_range_error_m: float | None,
    max_range_error_m: float | None,
    scene_path: Path | None,
    plane: str,
    offset_m: float | None,
    output: Path | None,
    as_json: bool,
) -> None:
    """Receiver spacing against range and angle error (report figs 4.12, 4.13) and GDOP maps.

    The default reproduces the report's study: path l = 1 m, path error 5 mm.
    """
    from echoloc.localise.design import design_record, design_study

    for name, value in (
        ("--path-m", path_m),
        ("--range-m", range_m),
        ("--path-error-m", path_error_m),
        ("--spacing-m", spacing_m),
        ("--max-cross-range-error-m", max_cross_range_error_m),
        ("--max-range-error-m", max_range_error_m),
    ):
        _finite(name, value, positive=True)
    _finite("--offset-m", offset_m)
    if path_m is not None and range_m is not None:
        raise EchoLocError("give --path-m or --range-m, not both")
    if path_m is None and range_m is None:
        path_m = 1.0
    if path_m is not None and spacing_m is not None and spacing_m >= path_m:
        raise EchoLocError(f"--spacing-m {spacing_m:g} must be below the path --path-m {path_m:g}")
    held = f"path l = {path_m:g} m" if path_m is not None else f"range r = {range_m:g} m"
    array = load_scene(scene_path).array if scene_path is not None else None
    study = design_study(
        path_error_m,
        path_m=path_m,
        range_m=range_m,
        spacing_m=spacing_m,
        max_cross_range_error_m=max_cross_range_error_m,
        max_range_error_m=max_range_error_m,
        array_m=None if array is None else (array.transmitters_m, array.receivers_m),
        array_name=None if scene_path is None else str(scene_path),
        plane=plane,  # type: ignore[arg-type]
        offset_m=offset_m,
    )
    rec, spacing, rows, area = study.recommendation, study.spacing_m, study.table, study.area
    array_name, at_point, area_path = study.array_name, study.on_boresight, study.area_path_m
    record = design_record(study)
    if output is not None:
        from echoloc.plots.design import plot_error_map, plot_spacing_study, plot_uncertainty_area

        try:
            output.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise EchoLocError(f"{output}: cannot create the output directory ({error.strerror})") from None
        written = [
            plot_uncertainty_area(area, output / "uncertainty_area.png"),
            plot_spacing_study(study.curves, rec, output / "spacing_study.png"),
            plot_error_map(study.gdop_map, output / "gdop_map.png", title=array_name),
        ]
        record["plots"] = [str(p) for p in written]
    if as_json:
        click.echo(json.dumps(_json_safe(record), allow_nan=False))
    else:
        table = Table(
            title=f"Spacing study (report fig. 4.13): {held}, Δl1 = ±{path_error_m * 1e3:g} mm, Δl2 = 0"
        )
        for column in (
            "d m",
            "range m",
            "Δr mm",
            "Δr lin mm",
            "Δθ °",
            "Δθ lin °",
            "r·|Δθ| mm",
        ):
            table.add_column(column, justify="right", no_wrap=True)
        table.add_column("", no_wrap=True)
        table.caption = (
            "Δr, Δθ: exact for +Δl1/−Δl1; lin: first order for +Δl1; r·|Δθ|: across-beam error, worst sign"
        )
        for j, d in enumerate(rows.spacings_m):
            mark = math.isclose(d, rec.spacing_m, rel_tol=1e-9)
            chosen = math.isclose(d, spacing, rel_tol=1e-9) and not mark
            table.add_row(
                f"{d:.3f}",
                f"{rows.range_m[j]:.3f}",
                f"{rows.range_error_m[0, j] * 1e3:+.2f}/{rows.range_error_m[1, j] * 1e3:+.2f}",
                f"{rows.linear_range_error_m[0, j] * 1e3:+.2f}",
                f"{math.degrees(rows.angle_error_rad[0, j]):+.2f}/"
                f"{math.degrees(rows.angle_error_rad[1, j]):+.2f}",
                f"{math.degrees(rows.linear_angle_error_rad[0, j]):+.2f}",
                f"{np.max(rows.cross_range_error_m[:, j]) * 1e3:.1f}",
                "◀ recommended" if mark else "◀ chosen" if chosen else "",
                style="bold" if mark else None,
            )
        stdout.print(table)
        limit = (
            f"; at most {rec.largest_spacing_m:.3f} m keeps the range error within "
            f"{rec.max_range_error_m * 1e3:g} mm"
            if rec.largest_spacing_m is not None and rec.max_range_error_m is not None
            else ""
        )
        stdout.print(
            f"Recommended spacing d = {rec.spacing_m:.3f} m ({rec.criterion}){limit}. There: "
            f"range {rec.range_m:.3f} m, |Δr| <= {rec.range_error_m * 1e3:.2f} mm, "
            f"|Δθ| <= {math.degrees(rec.angle_error_rad):.2f}°, "
            f"r·|Δθ| = {rec.cross_range_error_m * 1e3:.2f} mm.",
            highlight=False,
        )
        corners = Table(
            title=f"Uncertainty area (fig. 4.12): d = {spacing:.3f} m, l1 = l2 = {area_path:.3f} m, "
            f"Δl1 = Δl2 = {path_error_m * 1e3:g} mm"
        )
        for column in ("corner", "paths", "x mm", "z m", "Δr mm", "Δθ °"):
            corners.add_column(column, justify="right")
        for k, (name, paths) in enumerate(
            zip("abcd", ("l1+Δl1, l2−Δl2", "l1−Δl1, l2−Δl2", "l1−Δl1, l2+Δl2", "l1+Δl1, l2+Δl2"), strict=True)
        ):
            corners.add_row(
                name,
                paths,
                f"{area.corners_m[k, 0] * 1e3:+.2f}",
                f"{area.corners_m[k, 1]:.4f}",
                f"{(area.corner_range_m[k] - area.range_m) * 1e3:+.2f}",
                f"{math.degrees(area.corner_angle_rad[k] - area.angle_rad):+.3f}",
            )
        stdout.print(corners)
        stdout.print(
            f"{array_name}: on the boresight at {area.range_m:.3f} m, GDOP {float(at_point.gdop):.2f}; "
            f"with σ_path = {path_error_m * 1e3:g} mm, std per axis "
            + ", ".join(f"{v * 1e3:.2f}" for v in at_point.std_m)
            + f" mm, range std {float(at_point.range_std_m) * 1e3:.2f} mm, angle std "
            f"{math.degrees(float(at_point.angle_std_rad)):.3f}°.",
            highlight=False,
        )
    if output is not None:
        for written_path in record["plots"]:
            stderr.print(f"plot written to {written_path}")


# --- real time: send, stream, record, bench ----------------------------------------


def _listen_options(func: Callable[..., None]) -> Callable[..., None]:
    """--listen, --udp, --geometry, --queue and the rest, shared by stream and record."""
    from echoloc.realtime.transport import DEFAULT_HOST, DEFAULT_IDLE_TIMEOUT_S, DEFAULT_PORT

    decorators = [
        click.option(
            "--listen",
            "listen_text",
            metavar="[HOST:]PORT",
            default=f"{DEFAULT_HOST}:{DEFAULT_PORT}",
            show_default=True,
            help="Where to listen (127.0.0.1: this machine only; 0.0.0.0 for every interface).",
        ),
        click.option("--udp", is_flag=True, help="UDP (one datagram a frame) instead of TCP."),
        click.option(
            "--geometry",
            "geometry_path",
            type=click.Path(path_type=Path),
            default=None,
            help="Take the session (geometry, waveform, air) from this recording instead of the "
            "sender's session message.",
        ),
        click.option(
            "--queue",
            "queue_frames",
            type=click.IntRange(1, 1_000_000),
            default=64,
            show_default=True,
            help="Frames held between the socket and the processor; when full the oldest is dropped.",
        ),
        click.option(
            "--block",
            is_flag=True,
            help="Never drop a frame that arrived: make a TCP sender wait instead (replaying files).",
        ),
        click.option(
            "--once", is_flag=True, help="Stop when the sender says it is done or (TCP) disconnects."
        ),
        click.option(
            "--max-frames",
            type=click.IntRange(1, None),
            default=None,
            help="Stop after this many frames.",
        ),
        click.option(
            "--duration", "duration_s", type=float, default=None, help="Stop after this many seconds."
        ),
        click.option(
            "--idle-timeout",
            "idle_timeout_s",
            type=float,
            default=DEFAULT_IDLE_TIMEOUT_S,
            show_default=True,
            help="Close a TCP connection that sends nothing for this many seconds.",
        ),
    ]
    for decorator in reversed(decorators):
        func = decorator(func)
    return func


INTERRUPT_RETRY_S = 0.01
"""How long after a swallowed interrupt it is raised again, s: long enough for the
finaliser that swallowed it to return, short against a person's patience."""


@contextmanager
def _interrupt_cleanly() -> Iterator[None]:
    """Ctrl-C and SIGTERM (a service manager, or `kill`) end a command cleanly, always.

    Python raises KeyboardInterrupt at the main thread's next bytecode. When that is
    inside a finaliser (a ``__del__`` or a weakref callback, which h5py and
    ``weakref.WeakValueDictionary`` run all the time) Python prints "Exception ignored"
    with a traceback and swallows it: a killed ``simulate`` of 200 000 frames ran on
    (1 run in 8 here). ``sys.unraisablehook`` sees every swallowed exception; for an
    interrupt it prints nothing and has a helper thread raise it again in the main
    thread (``_thread.interrupt_main``) once the finaliser has returned, if this context
    is still running. Only a swallowed interrupt is raised again, so the clean-up of one that
    got through is not cut short by it (a second signal still interrupts, as a second Ctrl-C).
    """
    import _thread
    import signal
    import threading

    # A signal the parent asked to ignore (a background job's SIGINT, nohup) stays ignored.
    previous = {
        signum: signal.getsignal(signum)
        for signum in (signal.SIGTERM, signal.SIGINT)
        if signal.getsignal(signum) is not signal.SIG_IGN
    }
    # Handlers can be set only in the main thread (tests call main() from others too).
    if not previous or threading.current_thread() is not threading.main_thread():
        yield
        return
    # Raised again through a signal handled here: interrupt_main does nothing for an ignored one.
    handled = next(iter(previous))

    def interrupt(signum: int, frame: object) -> None:
        del signum, frame
        raise KeyboardInterrupt

    active = threading.Event()  # a retry fires only while this context is still the one running

    def fire() -> None:
        if active.is_set():
            _thread.interrupt_main(handled)

    def raise_again() -> None:
        retry = threading.Timer(INTERRUPT_RETRY_S, fire)
        retry.daemon = True
        retry.start()

    previous_hook = sys.unraisablehook

    def swallowed(unraisable: Any) -> None:
        if unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt):
            raise_again()
        else:
            previous_hook(unraisable)

    for signum in previous:
        signal.signal(signum, interrupt)
    sys.unraisablehook = swallowed
    active.set()
    try:
        yield
    finally:
        active.clear()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
        sys.unraisablehook = previous_hook


def _events(listener: Any, once: bool, max_frames: int | None, duration_s: float | None) -> Iterator[Any]:
    """What the listener queued, until a stop condition (:func:`listener_events`); its errors
    to stderr as warnings."""
    from echoloc.realtime.session import listener_events

    _finite("--duration", duration_s, positive=True)
    deadline = None if duration_s is None else time.monotonic() + duration_s
    return listener_events(listener, once=once, max_frames=max_frames, deadline_s=deadline, on_error=_warn)


def _open_listener(
    listen_text: str,
    udp: bool,
    geometry_path: Path | None,
    queue_frames: int,
    block: bool,
    idle_timeout_s: float,
    accept_session: Callable[[Recording], object] | None = None,
) -> Any:
    """The listener of `stream` and `record`; ``accept_session`` refuses (by raising) a session
    they cannot use, before it reaches them (the sender is told, the stream goes on)."""
    from echoloc.realtime.stream import FrameQueue
    from echoloc.realtime.transport import Listener, parse_endpoint

    endpoint = parse_endpoint(listen_text, "udp" if udp else "tcp")
    _finite("--idle-timeout", idle_timeout_s, positive=True)
    geometry = None if geometry_path is None else read_recording(geometry_path)
    return Listener(
        endpoint,
        FrameQueue(queue_frames, block=block),
        geometry=geometry,
        idle_timeout_s=idle_timeout_s,
        accept_session=accept_session,
    )


def _flush_listener_errors(listener: Any) -> None:
    """The warnings a stopped listener still holds (counts of those rate-limited), to stderr."""
    for message in listener.errors():
        _warn(message)


def _no_session_error(output: str, listener: Any) -> EchoLocError:
    """Why nothing was streamed or recorded: no session arrived, or every one was refused (only
    sessions count: a connection closed idle or refused as one too many is not a session)."""
    refused = listener.sessions_refused
    if refused:
        return EchoLocError(
            f"{output}no session accepted on {listener.address}: {refused} "
            f"session{'' if refused == 1 else 's'} refused, the last: {listener.last_session_refusal}"
        )
    return EchoLocError(f"{output}no session arrived on {listener.address}")


@cli.command(name="send")
@click.argument("recording_path", metavar="RECORDING", type=click.Path(path_type=Path))
@click.option(
    "--to", "to_text", metavar="[HOST:]PORT", default="127.0.0.1:7447", show_default=True, help="Receiver."
)
@click.option("--udp", is_flag=True, help="UDP (one datagram a frame) instead of TCP.")
@click.option(
    "--speed",
    type=float,
    default=1.0,
    show_default=True,
    help="1: the recording's own pace; N: N times faster; 0: as fast as the receiver takes it.",
)
@click.option("--rate", "rate_hz", type=float, default=None, help="Frames per second instead of --speed.")
@click.option(
    "--loop", "loops", type=click.IntRange(0, None), default=1, show_default=True, help="Passes; 0: forever."
)
@click.option(
    "--sample-format",
    type=click.Choice(["auto", "float32", "float64", "int16"]),
    default="auto",
    show_default=True,
    help="Samples on the wire. auto: float32 if that is exact, else float64 (float32 on UDP); "
    "int16: rounded, as ADC counts; iq recordings are sent complex64.",
)
@click.option(
    "--connect-timeout", "connect_timeout_s", type=float, default=5.0, show_default=True, help="TCP, s."
)
def send_command(
    recording_path: Path,
    to_text: str,
    udp: bool,
    speed: float,
    rate_hz: float | None,
    loops: int,
    sample_format: str,
    connect_timeout_s: float,
) -> None:
    """Replay RECORDING to a receiver in the stream protocol (docs/STREAM_PROTOCOL.md)."""
    from echoloc.realtime.transport import parse_endpoint, send_recording

    endpoint = parse_endpoint(to_text, "udp" if udp else "tcp")
    recording = read_recording(recording_path)
    try:
        with _interrupt_cleanly():
            report = send_recording(
                recording,
                endpoint,
                speed=speed,
                rate_hz=rate_hz,
                loops=loops,
                sample_format=sample_format,
                connect_timeout_s=connect_timeout_s,
            )
    except KeyboardInterrupt:
        stderr.print("echoloc: send: interrupted", markup=False)
        return
    stderr.print(f"echoloc: send: {report.summary(endpoint)}", markup=False, highlight=False)


@cli.command(name="stream")
@_listen_options
@click.option("--json", "as_json", is_flag=True, help="JSON Lines of `echoloc locate --json`, one a frame.")
@click.option(
    "--record", "record_path", type=click.Path(path_type=Path), default=None, help="Also record to HDF5."
)
@click.option("--force", is_flag=True, help="Let --record replace an existing file.")
@click.option("--view", is_flag=True, help="Serve the live view (Foxglove WebSocket) on 127.0.0.1.")
@click.option(
    "--view-port", type=click.IntRange(0, 65535), default=8765, show_default=True, help="Live view's port."
)
@click.option(
    "--deadline-ms",
    type=float,
    default=100.0,
    show_default=True,
    help="Frames waiting longer than this before processing are counted as late.",
)
@click.option(
    "--estimator",
    type=click.Choice(sorted(ESTIMATORS)),
    default="matched",
    show_default=True,
    help="Time-of-flight estimator.",
)
@click.option(
    "--threshold-db",
    type=float,
    default=EchoOptions.threshold_db,
    show_default=True,
    help="Detection threshold on the echo's output SNR, dB.",
)
@click.option("--blanking-s", type=float, default=0.0, show_default=True, help="Ignore earlier echoes, s.")
@click.option("--speed-of-sound", "speed_of_sound_m_s", type=float, default=None, help="Override, m/s.")
@click.option(
    "--calibration",
    "calibration_path",
    type=click.Path(path_type=Path),
    default=None,
    help="From `echoloc calibrate`.",
)
@_WORKERS_OPTION
def stream_command(
    listen_text: str,
    udp: bool,
    geometry_path: Path | None,
    queue_frames: int,
    block: bool,
    once: bool,
    max_frames: int | None,
    duration_s: float | None,
    idle_timeout_s: float,
    as_json: bool,
    record_path: Path | None,
    force: bool,
    view: bool,
    view_port: int,
    deadline_ms: float,
    estimator: str,
    threshold_db: float,
    blanking_s: float,
    speed_of_sound_m_s: float | None,
    calibration_path: Path | None,
    workers: int,
) -> None:
    """Locate objects in frames arriving over the network, as they arrive.

    Listens for the stream protocol (docs/STREAM_PROTOCOL.md; `echoloc send` replays a
    recording in it), runs the chain of `echoloc locate` on every frame and shows
    the latest objects (a live table on a terminal; with --json the lines of `locate
    --json` on stdout). Lost, dropped and late frames are counted and reported at the
    end; Ctrl-C or SIGTERM ends the stream cleanly.
    """
    from rich.live import Live

    from echoloc.realtime.session import LiveSession
    from echoloc.realtime.stream import warm_kernels
    from echoloc.realtime.transport import Recorder

    _finite("--deadline-ms", deadline_ms, positive=True)
    _finite("--speed-of-sound", speed_of_sound_m_s, positive=True)
    _finite("--blanking-s", blanking_s, minimum=0.0)
    _threshold_db(threshold_db)
    options = EchoOptions(threshold_db=threshold_db, blanking_s=blanking_s, workers=workers)
    if calibration_path is not None:
        read_calibration(calibration_path)  # a missing or broken file now, not when frames come

    def make_chain(header: Recording) -> Chain:
        calibration = (
            None if calibration_path is None else read_calibration(calibration_path, header.n_receivers)
        )
        chain = prepare(
            header,
            estimator=estimator,
            echo_options=options,
            speed_of_sound_m_s=speed_of_sound_m_s,
            calibration=calibration,
        )
        check_locatable(chain)
        return chain

    if record_path is not None:
        Recorder.check_path(record_path, force=force)
    _finite("--duration", duration_s, positive=True)
    # A session is prepared as it arrives, in the listener: one the chain cannot use is refused
    # to its sender, and the stream goes on serving.
    listener = _open_listener(
        listen_text, udp, geometry_path, queue_frames, block, idle_timeout_s, accept_session=make_chain
    )
    warm_kernels(estimator, workers)
    printer = _StreamPrinter(as_json)
    session = LiveSession(
        listener,
        make_chain,
        deadline_ms / 1e3,
        record_path,
        on_result=printer.result,
        on_message=printer.message,
    )
    printer.session = session
    interrupted = False
    try:
        if view:
            from echoloc.realtime.liveview import LiveView

            session.view = LiveView(port=view_port)
            stderr.print(
                f"echoloc: stream: live view on {session.view.url} (Foxglove: open connection)", markup=False
            )
        listener.start()
        stderr.print(f"echoloc: stream: listening on {listener.address}", markup=False, highlight=False)
        table = not as_json and stderr.is_terminal
        with (
            _interrupt_cleanly(),
            Live(console=stderr, refresh_per_second=4, transient=True)
            if table
            else contextlib.nullcontext() as live,
        ):
            printer.live = live
            try:
                for item in _events(listener, once, max_frames, duration_s):
                    session.handle(item)
            except KeyboardInterrupt:
                interrupted = True
    finally:
        listener.stop()
        _flush_listener_errors(listener)
        session.close(interrupted)
    if session.record_error is not None:
        raise session.record_error
    if session.processor is None and listener.sessions_refused:
        raise _no_session_error("", listener)


class _StreamPrinter:
    """How `echoloc stream` shows a live session: JSON Lines, a live table on a terminal, or
    a status line every STATUS_EVERY_S; its messages on stderr (or above the table)."""

    STATUS_EVERY_S = 10.0

    def __init__(self, as_json: bool) -> None:
        self.as_json = as_json
        self.session: Any = None
        self.live: Any = None
        self._last_status = time.monotonic()  # the first status line comes after STATUS_EVERY_S
        self._last_table = 0.0

    def result(self, frame: Any, result: Any) -> None:
        if self.as_json:
            click.echo(json_line(objects_record(result.objects)))
        now = frame.arrival_s
        if self.live is not None:
            if now - self._last_table > 0.2:
                self._last_table = now
                self.live.update(_stream_table(result.objects, self.session.stats()))
        elif now - self._last_status > self.STATUS_EVERY_S:
            self._last_status = now
            self.message(self.session.stats().summary())

    def message(self, text: str) -> None:
        (self.live.console if self.live is not None else stderr).print(
            f"echoloc: stream: {text}", markup=False, highlight=False
        )


def _stream_table(objects: FrameObjects, stats: Any) -> Table:
    """The live view on a terminal: the latest frame's objects and the stream's counters."""
    table = Table(
        title=f"frame {objects.frame} at {objects.time_s:.3f} s: {len(objects.objects)} objects",
        caption=stats.summary(),
    )
    for column in ("x mm", "y mm", "z mm", "±σ x, y, z mm", "range mm", "rx", "score"):
        table.add_column(column, justify="right")
    for obj in objects.objects:
        x, y, z = obj.position_m * 1e3
        table.add_row(
            f"{x:.1f}",
            f"{y:.1f}",
            f"{z:.1f}",
            _mm(obj.std_m, digits=2),
            f"{np.linalg.norm(obj.position_m) * 1e3:.1f}",
            str(len(set(obj.receivers))),
            f"{obj.score:.2f}",
        )
    return table


@cli.command(name="record")
@click.argument("output", metavar="OUT.h5", type=click.Path(path_type=Path))
@_listen_options
@click.option(
    "--batch-frames",
    type=click.IntRange(1, 1_000_000),
    default=64,
    show_default=True,
    help="Frames appended and flushed at a time.",
)
@click.option(
    "--batch-seconds", "batch_s", type=float, default=0.5, show_default=True, help="...or after this long."
)
@click.option("--force", is_flag=True, help="Replace OUT.h5 if it exists.")
@click.option("-v", "--verbose", is_flag=True, help="One line on stderr per batch written.")
def record_command(
    output: Path,
    listen_text: str,
    udp: bool,
    geometry_path: Path | None,
    queue_frames: int,
    block: bool,
    once: bool,
    max_frames: int | None,
    duration_s: float | None,
    idle_timeout_s: float,
    batch_frames: int,
    batch_s: float,
    force: bool,
    verbose: bool,
) -> None:
    """Record frames arriving over the network to OUT.h5, in batches flushed as they are written.

    A recorder killed at any moment (even SIGKILL, or a power cut) leaves OUT.h5
    readable, with every frame but at most those of the last batch. An existing OUT.h5
    is replaced only with --force.
    """
    from echoloc.realtime.stream import rare_counts
    from echoloc.realtime.transport import Recorder, SessionEvent

    def progress(frames: int) -> None:
        if verbose:
            stderr.print(
                f"echoloc: record: {frames} frames written to {output}", markup=False, highlight=False
            )

    Recorder.check_path(output, force=force)
    _finite("--duration", duration_s, positive=True)
    _finite("--batch-seconds", batch_s, positive=True)
    listener = _open_listener(listen_text, udp, geometry_path, queue_frames, block, idle_timeout_s)
    recorder: Recorder | None = None
    interrupted = False
    try:
        listener.start()
        stderr.print(f"echoloc: record: listening on {listener.address}", markup=False, highlight=False)
        with _interrupt_cleanly():
            try:
                for item in _events(listener, once, max_frames, duration_s):
                    if isinstance(item, SessionEvent):
                        if recorder is not None:
                            stderr.print(
                                "echoloc: warning: the sender started a different session; "
                                f"{output} keeps the first (start a new recording for the new one)",
                                markup=False,
                            )
                            break
                        recorder = Recorder(
                            output, item.header, batch_frames=batch_frames, batch_s=batch_s, on_batch=progress
                        )
                    elif isinstance(item, list) and recorder is not None:  # the frames that queued up
                        for frame in item:
                            recorder.add(frame)
            except KeyboardInterrupt:
                interrupted = True
    finally:
        listener.stop()
        _flush_listener_errors(listener)
        counters = listener.counters()
        if recorder is not None:
            recorder.close()
    if recorder is None:
        error = _no_session_error(f"{output}: ", listener)
        raise EchoLocError(f"{error}; nothing recorded")
    dropped = counters["dropped"] + recorder.dropped
    # Received and neither recorded nor dropped: still queued when recording stopped, or of a
    # second session.
    unrecorded = counters["received"] - recorder.frames - dropped
    left = f", unrecorded {unrecorded}" if unrecorded else ""
    end = " (interrupted)" if interrupted else ""
    stderr.print(
        f"echoloc: record: {recorder.frames} frames in {recorder.batches} "
        f"batch{'' if recorder.batches == 1 else 'es'} to {output}; "
        f"received {counters['received']}, lost {counters['lost']}, dropped {dropped}{left}, "
        f"malformed {counters['malformed']}, rejected {counters['rejected']}"
        f"{rare_counts(refused=counters['refused'], restarts=counters['restarts'])}{end}",
        markup=False,
        highlight=False,
    )


@cli.command(name="bench")
@click.option(
    "--reflectors",
    type=click.IntRange(0, 50),
    default=5,
    show_default=True,
    help="Random reflectors in the default scene (0: the report's three balls).",
)
@click.option("--frames", "n_frames", type=click.IntRange(2, 100_000), default=200, show_default=True)
@click.option(
    "--baseline-frames",
    type=click.IntRange(1, 1000),
    default=2,
    show_default=True,
    help="Frames for the scipy chain (its brute-force locate takes seconds a frame).",
)
@click.option(
    "--workers",
    type=click.IntRange(1, 1024),
    default=1,
    show_default=True,
    help="Cores to pin the bench to, and threads for echoloc's echoes stage.",
)
@click.option(
    "--rounds",
    type=click.IntRange(1, 100),
    default=3,
    show_default=True,
    help="Passes of echoloc's stream over the frames, each way; the median pass is reported.",
)
@click.option("--json", "as_json", is_flag=True, help="One JSON object with the figures.")
def bench_command(
    reflectors: int, n_frames: int, baseline_frames: int, workers: int, rounds: int, as_json: bool
) -> None:
    """Frames/s, latency p50/p99 and peak memory of the full chain, beside a plain scipy chain."""
    from echoloc.benchmark import bench_chains, bench_scene, format_bench

    cores = "one core" if workers == 1 else f"{workers} cores"
    stderr.print(
        f"echoloc: bench: simulating {n_frames} frames, then timing both chains on {cores}...",
        markup=False,
    )
    recording = simulate(bench_scene(reflectors), n_frames)
    report = bench_chains(recording, baseline_frames=baseline_frames, workers=workers, rounds=rounds)
    if as_json:
        click.echo(json.dumps(report, allow_nan=False))
        return
    click.echo(format_bench(report))


# --- entry point -------------------------------------------------------------------


def _show_warning(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    file: Any = None,
    line: str | None = None,
) -> None:
    text = str(message)
    if issubclass(category, RuntimeWarning) and not any(name in text for name in _INPUT_FILES):
        # numpy's floating-point warnings ("invalid value encountered in cast") know no file:
        # they come from processing the command's input, so name it.
        text = (
            f"{', '.join(_INPUT_FILES)}: {text} (numpy, in {Path(filename).name}:{lineno})"
            if _INPUT_FILES
            else text
        )
    _warn(text)


_INPUT_FILES: list[str] = []
"""The files given on the command line that exist (for warnings that know no file)."""


def _is_file(argument: str) -> bool:
    try:
        return not argument.startswith("-") and Path(argument).is_file()
    except (OSError, ValueError):  # a name too long, a NUL byte
        return False


def _warn(message: str) -> None:
    """One warning line on stderr, as every command writes them."""
    stderr.print(f"echoloc: warning: {_one_line(message)}", markup=False, highlight=False)


MAX_MESSAGE_CHARS = 400


def _one_line(message: str) -> str:
    """``message`` on one line of at most :data:`MAX_MESSAGE_CHARS`: a hostile value quoted in
    it (a 5000-character string) must not bury the file and key named at its start."""
    text = " ".join(message.split())
    if len(text) <= MAX_MESSAGE_CHARS:
        return text
    keep = MAX_MESSAGE_CHARS // 2 - 10
    return f"{text[:keep]} [... {len(text) - 2 * keep} characters ...] {text[-keep:]}"


_BARE_GROUP: Any = getattr(click.exceptions, "NoArgsIsHelpError", ())
"""What click (8.2 on) raises for ``echoloc`` without a command: its help, not an error
(click 8.1 printed the help and exited 0 itself)."""

from echoloc.cli.importing import import_group  # noqa: E402  (registered beside its use)

cli.add_command(import_group, name="import")


def main(argv: list[str] | None = None) -> None:
    """Run the CLI; bad input becomes one line on stderr and exit code 2."""
    warnings.showwarning = _show_warning
    _INPUT_FILES[:] = [arg for arg in (sys.argv[1:] if argv is None else argv) if _is_file(arg)][:2]
    try:
        # SIGTERM ends every command as Ctrl-C does, so a half-written output's temporary
        # file is removed and what was written before stays (not only in `stream`).
        with _interrupt_cleanly():
            cli.main(args=argv, prog_name="echoloc", standalone_mode=False)
    except EchoLocError as error:
        stderr.print(f"echoloc: error: {_one_line(str(error))}", markup=False, highlight=False)
        sys.exit(2)
    except click.exceptions.Abort:
        stderr.print("echoloc: aborted", markup=False)
        sys.exit(1)
    except _BARE_GROUP as request:
        click.echo(request.ctx.get_help())
        sys.exit(0)
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
        where = f"{error.filename}: " if error.filename else ""
        stderr.print(f"echoloc: error: {where}{error.strerror or error}", markup=False, highlight=False)
        sys.exit(2)
    except MemoryError:
        stderr.print(
            "echoloc: error: not enough memory for this request (fewer frames or samples?)", markup=False
        )
        sys.exit(2)
    except Exception as error:
        stderr.print(
            f"echoloc: internal error: {type(error).__name__}: {error} (please report this)",
            markup=False,
            highlight=False,
        )
        sys.exit(1)
    sys.exit(0)
