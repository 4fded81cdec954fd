"""`echoloc send`, `stream`, `record` and `bench`: live frames."""

from __future__ import annotations

import contextlib
import functools
import json
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import click
from rich.table import Table

from echoloc.cli.app import (
    ChainSettings,
    _chain_options,
    _Decorated,
    _finite,
    _interrupt_cleanly,
    _path_option,
    _warn,
    cli,
    stderr,
)
from echoloc.cli.basics import _class_cells, _object_cells
from echoloc.errors import EchoLocError, refuse_new_output
from echoloc.io.head import is_head_file, load_head, read_geometry
from echoloc.io.output import json_line, objects_record
from echoloc.io.recording import Recording, read_recording
from echoloc.localise.locate import FrameObjects
from echoloc.pipeline import (
    Chain,
    check_locatable,
)
from echoloc.sim.simulation import simulate

# --- real time: send, stream, record, bench ----------------------------------------

DEFAULT_BAUD = 2_000_000
"""--source serial's rate when none is given, baud (USB-CDC ignores it; a UART needs it)."""


def _int_range_option(
    *names: str, low: int, high: int | None, default: int, **settings: Any
) -> Callable[[_Decorated], _Decorated]:
    """A click option taking a whole number from ``low`` to ``high`` (None: no upper bound), its
    default shown in the help: the form of these commands' counts (frames, passes, a port)."""
    return click.option(
        *names, type=click.IntRange(low, high), default=default, show_default=True, **settings
    )


@dataclass(frozen=True)
class _Listening:
    """The options of :func:`_listen_options`, as `stream` and `record` take them: where and how
    to listen (address, UDP, geometry, queue, blocking, idle timeout in s) and when to stop (once,
    after frames or after a duration in s). Fields are named as the options' parameters."""

    source_text: str
    listen_text: str
    udp: bool
    geometry_path: Path | None
    queue_frames: int
    block: bool
    once: bool
    max_frames: int | None
    duration_s: float | None
    idle_timeout_s: float


def _listen_options(func: Callable[..., None]) -> Callable[..., None]:
    """--listen, --udp, --geometry, --queue and the rest, shared by stream and record: ``func``
    takes them together, as one :class:`_Listening` named ``listening``."""
    from echoloc.realtime.transport import DEFAULT_HOST, DEFAULT_IDLE_TIMEOUT_S, DEFAULT_PORT

    @functools.wraps(func)
    def command(**values: Any) -> None:
        # click passes every option by its parameter's name: those of listening go in one value.
        listening = _Listening(**{field.name: values.pop(field.name) for field in fields(_Listening)})
        func(listening=listening, **values)

    decorators = [
        click.option(
            "--source",
            "source_text",
            metavar="net|serial:PORT[@BAUD]|soundcard[:DEVICE]",
            default="net",
            show_default=True,
            help="Where frames come from: the network (the stream protocol, --listen), a board on a "
            "serial or USB-CDC port (docs/SERIAL_PROTOCOL.md; PORT as pyserial takes it: /dev/ttyACM0, "
            "loop://, socket://HOST:PORT) or a sound card (docs/SOUNDCARD.md). serial and soundcard "
            "need --head.",
        ),
        click.option(
            "--listen",
            "listen_text",
            metavar="[HOST:]PORT",
            default=f"{DEFAULT_HOST}:{DEFAULT_PORT}",
            show_default=True,
            help="Where to listen (127.0.0.1: this machine only; 0.0.0.0 for every interface).",
        ),
        click.option("--udp", is_flag=True, help="UDP (one datagram a frame) instead of TCP."),
        _path_option(
            "--head",
            "--geometry",
            "geometry_path",
            help="The sensor head: a head file (HEAD.toml, docs/HEAD.md) or a recording whose geometry, "
            "waveform and air to take; on the network, instead of the sender's session message.",
        ),
        _int_range_option(
            "--queue",
            "queue_frames",
            low=1,
            high=1_000_000,
            default=64,
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
    decorated: Callable[..., None] = command
    for decorator in reversed(decorators):
        decorated = decorator(decorated)
    return decorated


def _events(listener: Any, listening: _Listening) -> Iterator[Any]:
    """What the listener queued, until a stop condition of ``listening`` (:func:`listener_events`);
    its errors to stderr as warnings."""
    from echoloc.realtime.session import listener_events

    duration_s = listening.duration_s
    _finite("--duration", duration_s, positive=True)
    deadline = None if duration_s is None else time.monotonic() + duration_s
    return listener_events(
        listener, once=listening.once, max_frames=listening.max_frames, deadline_s=deadline, on_error=_warn
    )


def _open_listener(listening: _Listening, accept_session: Callable[[Recording], object] | None = None) -> Any:
    """The source of `stream` and `record` (:mod:`echoloc.realtime.capture`): the network
    listener, or a capture source reading the head's hardware. ``accept_session`` refuses (by
    raising) a session they cannot use, before it reaches them (a network sender is told, and
    the stream goes on)."""
    from echoloc.realtime.stream import FrameQueue

    queue = FrameQueue(listening.queue_frames, block=listening.block)
    kind, _, where = listening.source_text.partition(":")
    if kind != "net":
        return _open_capture(kind, where, listening, queue, accept_session)
    if where:
        raise EchoLocError(
            f"--source net takes no address (give it with --listen), got {listening.source_text!r}"
        )
    from echoloc.realtime.transport import Listener, parse_endpoint

    endpoint = parse_endpoint(listening.listen_text, "udp" if listening.udp else "tcp")
    _finite("--idle-timeout", listening.idle_timeout_s, positive=True)
    geometry = None if listening.geometry_path is None else read_geometry(listening.geometry_path)
    return Listener(
        endpoint,
        queue,
        geometry=geometry,
        idle_timeout_s=listening.idle_timeout_s,
        accept_session=accept_session,
    )


def _open_capture(
    kind: str,
    where: str,
    listening: _Listening,
    queue: Any,
    accept_session: Callable[[Recording], object] | None,
) -> Any:
    """A capture source: ``serial`` at port ``where`` (``PORT[@BAUD]``) or ``soundcard`` (device
    ``where``, an index or part of a name; empty: the default device)."""
    if kind not in ("serial", "soundcard"):
        raise EchoLocError(
            f"--source must be net, serial:PORT[@BAUD] or soundcard[:DEVICE], got {listening.source_text!r}"
        )
    if listening.udp:
        raise EchoLocError(f"--udp is for --source net, not {kind}")
    if listening.geometry_path is None or not is_head_file(listening.geometry_path):
        raise EchoLocError(
            f"--source {kind} needs --head HEAD.toml: the head's geometry, pulse and wiring (docs/HEAD.md)"
        )
    head = load_head(listening.geometry_path)
    if kind == "serial":
        from echoloc.realtime.serial_source import SerialSource

        port, _, baud_text = where.partition("@")
        if not port:
            raise EchoLocError("--source serial needs a port: serial:/dev/ttyACM0, serial:loop://, ...")
        try:
            baudrate = int(baud_text) if baud_text else DEFAULT_BAUD
        except ValueError:
            raise EchoLocError(
                f"--source serial:PORT@BAUD: BAUD must be a whole number, got {baud_text!r}"
            ) from None
        return SerialSource(head, queue, port, baudrate=baudrate, accept_session=accept_session)
    from echoloc.realtime.soundcard_source import SoundCardSource

    device: int | str | None = int(where) if where.isdigit() else (where or None)
    return SoundCardSource(head, queue, device=device, accept_session=accept_session)


def _reading(source: Any) -> str:
    """What a started source does, for the first line on stderr."""
    from echoloc.realtime.capture import CaptureSource

    return (
        f"capturing from {source.address}"
        if isinstance(source, CaptureSource)
        else f"listening on {source.address}"
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
@_int_range_option("--loop", "loops", low=0, high=None, default=1, help="Passes; 0: forever.")
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
@_path_option("--record", "record_path", default=None, help="Also record to HDF5.")
@_path_option(
    "--mcap",
    "mcap_path",
    default=None,
    help="Also write the objects as ROS 2 messages to this MCAP, as they come (docs/ROS.md).",
)
@click.option("--force", is_flag=True, help="Let --record and --mcap replace existing files.")
@click.option("--view", is_flag=True, help="Serve the live view (Foxglove WebSocket) on 127.0.0.1.")
@_int_range_option("--view-port", low=0, high=65535, default=8765, help="Live view's port.")
@click.option(
    "--deadline-ms",
    type=float,
    default=100.0,
    show_default=True,
    help="Frames waiting longer than this before processing are counted as late.",
)
@_chain_options
def stream_command(
    listening: _Listening,
    settings: ChainSettings,
    as_json: bool,
    record_path: Path | None,
    mcap_path: Path | None,
    force: bool,
    view: bool,
    view_port: int,
    deadline_ms: float,
) -> None:
    """Locate objects in frames as they arrive: over the network, from a serial port or a sound card.

    Listens for the stream protocol (docs/STREAM_PROTOCOL.md; `echoloc send` replays a
    recording in it), or captures from a head's hardware (--source, --head; docs/HEAD.md),
    runs the chain of `echoloc locate` with the same options on every frame and shows
    the latest objects (a live table on a terminal; with --json the lines of `locate
    --json` on stdout). Lost, dropped and late frames are counted and reported at the
    end; Ctrl-C or SIGTERM ends the stream cleanly.
    """
    from rich.live import Live

    from echoloc.realtime.session import LiveSession
    from echoloc.realtime.stream import warm_kernels
    from echoloc.realtime.transport import Recorder

    _finite("--deadline-ms", deadline_ms, positive=True)
    if settings.method != "association":
        raise EchoLocError(
            f"--method {settings.method} is for recordings: stream locates each frame by association"
        )
    template = settings.check()  # bad options and files now, before any frame

    def make_chain(header: Recording) -> Chain:
        chain = settings.chain(header, template)
        check_locatable(chain)
        return chain

    if record_path is not None:
        Recorder.check_path(record_path, force=force)
    if mcap_path is not None:
        _check_mcap_path(mcap_path, force=force)
    _finite("--duration", listening.duration_s, positive=True)
    # A session is prepared as it arrives, in the listener: one the chain cannot use is refused
    # to its sender, and the stream goes on serving.
    listener = _open_listener(listening, accept_session=make_chain)
    warm_kernels(settings.estimator, settings.workers)
    printer = _StreamPrinter(as_json, settings.classes)
    session = LiveSession(
        listener,
        make_chain,
        deadline_ms / 1e3,
        record_path,
        mcap_path=mcap_path,
        on_result=printer.result,
        on_message=printer.message,
    )
    printer.session = session
    interrupted = False
    listener.start()  # a device that cannot be opened: its one line, before anything else
    try:
        if view:
            from echoloc.realtime.liveview import LiveView

            session.view = LiveView(port=view_port)
            stderr.print(
                f"echoloc: stream: live view on {session.view.url} (Foxglove: open connection)", markup=False
            )
        stderr.print(f"echoloc: stream: {_reading(listener)}", markup=False, highlight=False)
        table = not as_json and stderr.is_terminal
        with (
            _interrupt_cleanly(),
            Live(console=stderr, refresh_per_second=4, transient=True)
            if table
            else contextlib.nullcontext() as live,
        ):
            printer.live = live
            try:
                for item in _events(listener, listening):
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


def _check_mcap_path(path: Path, *, force: bool) -> None:
    """Refuse, before anything arrives, an MCAP target that cannot be written (one line), and one
    that exists unless ``force``."""
    if path.suffix.lower() != ".mcap":
        raise EchoLocError(f"{path}: --mcap writes an .mcap file, not {path.suffix or 'no extension'!r}")
    refuse_new_output(path, force=force)


class _StreamPrinter:
    """How `echoloc stream` shows a live session: JSON Lines, a live table on a terminal, or
    a status line every STATUS_EVERY_S; its messages on stderr (or above the table)."""

    STATUS_EVERY_S = 10.0

    def __init__(self, as_json: bool, classes: bool = False) -> None:
        self.as_json = as_json
        self.classes = classes
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
                self.live.update(_stream_table(result.objects, self.session.stats(), self.classes))
        elif now - self._last_status > self.STATUS_EVERY_S:
            self._last_status = now
            self.message(self.session.stats().summary())

    def message(self, text: str) -> None:
        (self.live.console if self.live is not None else stderr).print(
            f"echoloc: stream: {text}", markup=False, highlight=False
        )


def _stream_table(objects: FrameObjects, stats: Any, classes: bool = False) -> Table:
    """The live view on a terminal: the latest frame's objects and the stream's counters."""
    table = Table(
        title=f"frame {objects.frame} at {objects.time_s:.3f} s: {len(objects.objects)} objects",
        caption=stats.summary(),
    )
    columns = ["x mm", "y mm", "z mm", "±σ x, y, z mm", "range mm", "rx", "score"]
    for column in columns + (["kind", "normal or edge"] if classes else []):
        table.add_column(column, justify="right")
    for obj in objects.objects:
        table.add_row(*_object_cells(obj), *(_class_cells(obj) if classes else []))
    return table


@cli.command(name="record")
@click.argument("output", metavar="OUT.h5", type=click.Path(path_type=Path))
@_listen_options
@_int_range_option(
    "--batch-frames", low=1, high=1_000_000, default=64, help="Frames appended and flushed at a time."
)
@click.option(
    "--batch-seconds", "batch_s", type=float, default=0.5, show_default=True, help="...or after this long."
)
@click.option("--force", is_flag=True, help="Replace OUT.h5 if it exists.")
@click.option("-v", "--verbose", is_flag=True, help="One line on stderr per batch written.")
def record_command(
    output: Path,
    listening: _Listening,
    batch_frames: int,
    batch_s: float,
    force: bool,
    verbose: bool,
) -> None:
    """Record arriving frames (network, serial port or sound card: --source) to OUT.h5, in batches.

    Each batch is flushed as it is written.

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
    _finite("--duration", listening.duration_s, positive=True)
    _finite("--batch-seconds", batch_s, positive=True)
    listener = _open_listener(listening)
    recorder: Recorder | None = None
    interrupted = False
    listener.start()  # a device that cannot be opened: its one line, before anything else
    try:
        stderr.print(f"echoloc: record: {_reading(listener)}", markup=False, highlight=False)
        with _interrupt_cleanly():
            try:
                for item in _events(listener, listening):
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
    xruns = counters.get("xruns", 0)  # a sound card's breaks
    end = " (interrupted)" if interrupted else ""
    stderr.print(
        f"echoloc: record: {recorder.frames} frames in {recorder.batches} "
        f"batch{'' if recorder.batches == 1 else 'es'} to {output}; "
        f"received {counters['received']}, lost {counters['lost']}, dropped {dropped}{left}, "
        f"malformed {counters['malformed']}, rejected {counters['rejected']}"
        f"{rare_counts(refused=counters['refused'], restarts=counters['restarts'], xruns=xruns)}{end}",
        markup=False,
        highlight=False,
    )


@cli.command(name="bench")
@_int_range_option(
    "--reflectors",
    low=0,
    high=50,
    default=5,
    help="Random reflectors in the default scene (0: the report's three balls).",
)
@_int_range_option("--frames", "n_frames", low=2, high=100_000, default=200)
@_int_range_option(
    "--baseline-frames",
    low=1,
    high=1000,
    default=2,
    help="Frames for the scipy chain (its brute-force locate takes seconds a frame).",
)
@_int_range_option(
    "--workers",
    low=1,
    high=1024,
    default=1,
    help="Cores to pin the bench to, and threads for echoloc's echoes stage.",
)
@_int_range_option(
    "--rounds",
    low=1,
    high=100,
    default=3,
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
