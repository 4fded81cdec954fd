"""The command group, the options and helpers the commands share, and the entry point."""

from __future__ import annotations

import functools
import math
import os
import sys
import warnings
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, TypeVar

import click
import numpy as np
from rich.console import Console
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeRemainingColumn,
)

from echoloc import __version__
from echoloc.errors import EchoLocError, unwritable
from echoloc.io.recording import Recording, read_recording
from echoloc.localise.calibrate import read_calibration
from echoloc.localise.evaluation import frames_at_positions
from echoloc.localise.locate import FrameObjects, LocateOptions
from echoloc.pipeline import (
    Chain,
    prepare,
    run,
)
from echoloc.tof.conditioning import Conditioning, parse_blind_zone
from echoloc.tof.echoes import THRESHOLD_DB_LIMIT, EchoOptions
from echoloc.tof.estimators import (
    AUTO,
    ENVELOPE_PEAK_THRESHOLD_DB,
    ESTIMATORS,
    default_threshold_db,
    resolve_estimator,
)
from echoloc.tof.templates import Template, read_template

# Tables wrap at 80 columns when piped; give them room (COLUMNS still wins).
# emoji=False: a path or port such as serial:loop:// is printed as written, never as an emoji.
stdout = (
    Console(emoji=False)
    if sys.stdout.isatty()
    else Console(width=int(os.environ.get("COLUMNS", 120)), emoji=False)
)
# Messages on stderr are one line each, however long: never wrap them.
stderr = Console(stderr=True, soft_wrap=True, emoji=False)


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


@dataclass(frozen=True, kw_only=True)
class ChainSettings:
    """How frames are processed: the options of every command that runs the chain, on a
    recording (`locate`, `echoes`, ...) or on live frames (`stream`), defined once."""

    estimator: str = AUTO
    threshold_db: float | None = None
    blanking_s: float = 0.0
    speed_of_sound_m_s: float | None = None
    calibration_path: Path | None = None
    path_sigma_m: float | None = None
    template_path: Path | None = None
    background: bool | None = None
    tvg: bool | None = None
    blind_zone_text: str | None = None
    field_of_view_deg: float | None = None
    method: str = "association"
    workers: int = 1
    classes: bool = False

    def check(self) -> Template | None:
        """Refuse bad values with one clear line, before any file or frame is read; read the
        template and check the calibration file. Returns the template (None: not given)."""
        _finite("--speed-of-sound", self.speed_of_sound_m_s, positive=True)
        _finite("--blanking-s", self.blanking_s, minimum=0.0)
        if self.threshold_db is not None:
            _threshold_db(self.threshold_db)
        _finite("--path-sigma-m", self.path_sigma_m, positive=True)
        _finite("--field-of-view-deg", self.field_of_view_deg, positive=True)
        if self.field_of_view_deg is not None and self.field_of_view_deg > 180:
            raise EchoLocError(f"--field-of-view-deg must be at most 180, got {self.field_of_view_deg:g}")
        EchoOptions(blanking_s=self.blanking_s, workers=self.workers)
        if self.blind_zone_text is not None:
            parse_blind_zone(self.blind_zone_text)
        if self.classes and self.method != "association":
            raise EchoLocError(
                "--classes needs --method association: back-projection finds no echo groups to classify"
            )
        if self.calibration_path is not None:
            read_calibration(self.calibration_path)  # a missing or broken file now, not at frame 1
        return None if self.template_path is None else read_template(self.template_path)

    def estimator_name(self, recording: Recording) -> str:
        """The estimator that runs: ``--estimator``, or the recording's default for ``auto``."""
        return resolve_estimator(self.estimator, recording)

    def chain(self, recording: Recording, template: Template | None) -> Chain:
        """The chain for ``recording`` (or a live session's header) with these options;
        ``template``: the matched filter's or the learnt echo shape (None: the recording's own,
        or the calibration's shape)."""
        calibration = (
            None
            if self.calibration_path is None
            else read_calibration(self.calibration_path, recording.n_receivers)
        )
        threshold_db = self.threshold_db
        if threshold_db is None:
            threshold_db = default_threshold_db(
                self.estimator_name(recording), None if calibration is None else calibration.threshold_db
            )
        echo_options = EchoOptions(
            threshold_db=threshold_db, blanking_s=self.blanking_s, template=template, workers=self.workers
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
        locate_options = chain.locate_options
        if self.path_sigma_m is not None:
            locate_options = replace(locate_options, path_sigma_m=self.path_sigma_m)
        if self.field_of_view_deg is not None:
            locate_options = replace(locate_options, field_of_view_deg=self.field_of_view_deg)
        if self.classes:
            locate_options = replace(locate_options, reflector_classes=True)
        return replace(chain, locate_options=locate_options)


@dataclass(frozen=True, kw_only=True)
class Processing(ChainSettings):
    """What echoes, locate and evaluate share: the recording, its frames, and how to process them."""

    recording_path: Path
    frames_text: str | None = None
    repair_nonfinite: bool = False
    positions_text: str | None = None

    def open(self) -> tuple[Recording, Chain, Sequence[int]]:
        """Check the options, read the recording, prepare the chain and pick the frames to run."""
        template = self.check()
        recording = read_recording(self.recording_path, repair_nonfinite=self.repair_nonfinite)
        frames: Sequence[int] = _frames_option(self.frames_text, recording.n_frames)
        if self.positions_text is not None:
            if recording.truth_positions_m is None:
                raise EchoLocError(
                    f"{self.recording_path}: --positions needs truth_positions in the recording"
                )
            frames = frames_at_positions(recording.truth_positions_m, self.positions_text, frames)
        return recording, self.chain(recording, template), frames


_PROCESSING_FIELDS = [f.name for f in fields(Processing)]
_CHAIN_FIELDS = [f.name for f in fields(ChainSettings)]


_Decorated = TypeVar("_Decorated", bound=Callable[..., Any])


def _path_option(*names: str, **settings: Any) -> Callable[[_Decorated], _Decorated]:
    """A click option whose value is a :class:`~pathlib.Path` (``None`` when not given)."""
    return click.option(*names, type=click.Path(path_type=Path), **settings)


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


def _chain_option_decorators(*, locating: bool, calibrated: bool = True) -> list[Callable[[Any], Any]]:
    """The click options of :class:`ChainSettings` (``locating``: also those of localisation;
    ``calibrated``: --calibration), as `locate` and `stream` both take them."""
    decorators = [
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
            f"envelope-peak {ENVELOPE_PEAK_THRESHOLD_DB:g}, on data without processing gain, or the "
            "one `calibrate` measured, with --calibration].",
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
        _WORKERS_OPTION,
        _path_option(
            "--template",
            "template_path",
            help="Template from `echoloc template`: the matched filter's (DIRECT, a recorded echo; "
            "default: the recording's waveform, SENT) or envelope-peak's learnt echo shape "
            "(default: the calibration's).",
        ),
    ]
    if calibrated:
        decorators.append(
            _path_option(
                "--calibration",
                "calibration_path",
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
                "--classes",
                is_flag=True,
                help="Tell points, planes and concave corners apart: a wall is located as a plane "
                "(its foot, normal and distance), a corner at its edge, and every object gets a "
                "kind and its confidence (association only).",
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
    return decorators


def _chain_options(func: Callable[..., None]) -> Callable[..., None]:
    """Add every option of :class:`ChainSettings` to a command that processes live frames and
    hand it one ``ChainSettings`` value named ``settings``."""

    @functools.wraps(func)
    def command(**kwargs: Any) -> None:
        settings = ChainSettings(**{k: kwargs.pop(k) for k in _CHAIN_FIELDS if k in kwargs})
        func(settings=settings, **kwargs)

    decorated: Callable[..., None] = command
    for decorator in reversed(_chain_option_decorators(locating=True)):
        decorated = decorator(decorated)
    return decorated


def _processing_options(
    *, locating: bool, calibrated: bool = True
) -> Callable[[Callable[..., None]], Callable[..., None]]:
    """Add the recording, its frames and the chain's options to a command and hand it one
    ``Processing`` value."""

    def decorate(func: Callable[..., None]) -> Callable[..., None]:
        @functools.wraps(func)
        def command(**kwargs: Any) -> None:
            processing = Processing(**{k: kwargs.pop(k) for k in _PROCESSING_FIELDS if k in kwargs})
            func(processing, **kwargs)

        decorators = [
            click.argument("recording_path", metavar="RECORDING", type=click.Path(path_type=Path)),
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
            *_chain_option_decorators(locating=locating, calibrated=calibrated),
        ]
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
    {
        "demo",
        "echoes",
        "locate",
        "image",
        "export",
        "map",
        "evaluate",
        "calibrate",
        "stream",
        "bench",
        "batch",
        "sweep",
    }
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
