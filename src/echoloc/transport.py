"""Sockets: receiving and sending the wire protocol (:mod:`echoloc.protocol`) over TCP or UDP.

The edges of a live stream, kept apart from the processing:

- :class:`Listener` binds a TCP or UDP port (127.0.0.1 by default), decodes
  messages in a background thread and puts sessions and frames on a
  :class:`~echoloc.stream.FrameQueue`, counting what it cannot use (malformed
  messages, frames that do not fit the session, sequence gaps, disorder);
- :func:`send_recording` replays a recording at real time, N times faster, at a
  fixed rate, or as fast as the receiver takes it, once or in a loop;
- :class:`Recorder` appends frames to an HDF5 recording in batches from its own
  thread (:func:`echoloc.recording.append_recording_stream`: flushed after every
  batch).
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import queue
import socket
import threading
import time
import warnings
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from echoloc.echoes import frame_time_s
from echoloc.errors import EchoLocError, missing_directory
from echoloc.protocol import (
    KIND_END,
    KIND_FRAME,
    KIND_SESSION,
    MAX_UDP_BYTES,
    FramePayload,
    MessageHeader,
    ProtocolError,
    decode_frame,
    decode_header,
    decode_session,
    encode_end,
    encode_session,
    frame_message,
    frame_payload,
    session_record,
    split_messages,
)
from echoloc.recording import FrameBatch, Recording, append_recording_stream, as_header
from echoloc.stream import FrameQueue, Samples, SequenceTracker, StreamFrame

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 7447
TRANSPORTS = ("tcp", "udp")


@dataclass(frozen=True)
class Endpoint:
    """Where a stream is sent or received: host, port and ``"tcp"`` or ``"udp"``."""

    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    transport: str = "tcp"

    def __str__(self) -> str:
        return f"{self.transport}://{self.host}:{self.port}"


def parse_endpoint(text: str, transport: str = "tcp") -> Endpoint:
    """``PORT``, ``HOST:PORT`` or ``tcp://HOST:PORT`` / ``udp://HOST:PORT`` as an :class:`Endpoint`."""
    rest = text
    if "://" in text:
        transport, rest = text.split("://", 1)
    if transport not in TRANSPORTS:
        raise EchoLocError(f"endpoint {text!r}: transport {transport!r}, expected tcp or udp")
    host, _, port_text = rest.rpartition(":")
    host = host.strip("[]") or DEFAULT_HOST
    try:
        port = int(port_text)
    except ValueError:
        raise EchoLocError(f"endpoint {text!r}: port {port_text!r} is not a number") from None
    if not 0 <= port <= 65535:
        raise EchoLocError(f"endpoint {text!r}: port {port} is outside 0..65535")
    return Endpoint(host, port, transport)


@dataclass(frozen=True, eq=False)
class SessionEvent:
    """A new session on the queue: the header every following frame belongs to."""

    header: Recording


@dataclass(frozen=True)
class EndEvent:
    """The sender said it is done (an end message), or, on TCP, it disconnected."""

    disconnected: bool = False


# ----------------------------------------------------------------------------- receiving


class Listener:
    """Receives the wire protocol on ``endpoint`` in a background thread, into ``queue``.

    Parameters
    ----------
    endpoint
        Where to listen; port 0 picks a free port (see :attr:`address`).
    queue
        Sessions, frames and ends are put there in arrival order.
    geometry
        A recording (or header) to use instead of the senders' session messages
        (``--geometry REC.h5``); frames must still fit it.

    TCP serves one sender at a time and waits for the next when one disconnects;
    every new connection starts its sequence numbers afresh. On UDP every datagram
    is one message.
    """

    def __init__(self, endpoint: Endpoint, frames: FrameQueue, *, geometry: Recording | None = None) -> None:
        self.endpoint = endpoint
        self.queue = frames
        self.geometry = None if geometry is None else as_header(geometry)
        self.session: Recording | None = None
        self._session_key: str | None = None
        self.tracker = SequenceTracker()
        self.received = 0
        self.malformed = 0
        self.rejected = 0
        self.bytes_skipped = 0
        self.last_error: str | None = None
        # Bounded: a caller that never reads errors() must not make a flood of garbage grow memory.
        self._errors: deque[str] = deque(maxlen=100)
        self._stop = threading.Event()
        self._first_arrival: float | None = None
        family = socket.AF_INET6 if ":" in endpoint.host else socket.AF_INET
        kind = socket.SOCK_STREAM if endpoint.transport == "tcp" else socket.SOCK_DGRAM
        self._socket = socket.socket(family, kind)
        try:
            self._socket.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if kind == socket.SOCK_DGRAM:
                with contextlib.suppress(OSError):  # room for a burst of datagrams
                    self._socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
            self._socket.bind((endpoint.host, endpoint.port))
            if kind == socket.SOCK_STREAM:
                self._socket.listen(1)
            self._socket.settimeout(0.1)
        except OSError as error:
            self._socket.close()
            raise EchoLocError(f"cannot listen on {endpoint}: {error.strerror or error}") from None
        # Kept: the socket's own name is gone once stop() has closed it.
        self._address = replace(endpoint, port=int(self._socket.getsockname()[1]))
        if self.geometry is not None:
            self._set_session(self.geometry)
        self._thread = threading.Thread(target=self._run, name=f"echoloc-listener {endpoint}", daemon=True)

    @property
    def address(self) -> Endpoint:
        """The bound endpoint (with the port the system chose for port 0)."""
        return self._address

    def start(self) -> Listener:
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop receiving and close the socket (waits for the thread)."""
        self._stop.set()
        self.queue.close()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self._socket.close()

    def __enter__(self) -> Listener:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    def errors(self) -> Iterator[str]:
        """Messages about refused input since the last call (one line each, for stderr)."""
        while True:
            try:
                yield self._errors.popleft()
            except IndexError:
                return

    def counters(self) -> dict[str, int]:
        """What the receiving side counted, for :meth:`echoloc.stream.StreamProcessor.stats`."""
        return {
            "received": self.received,
            "lost": self.tracker.lost,
            "dropped": self.queue.dropped,
            "out_of_order": self.tracker.out_of_order,
            "malformed": self.malformed,
            "rejected": self.rejected,
        }

    # -- the thread

    def _complain(self, counter: str, message: str) -> None:
        setattr(self, counter, getattr(self, counter) + 1)
        if message != self.last_error:  # one line per kind of problem in a row, not one per frame
            self._errors.append(message)
        self.last_error = message

    def _run(self) -> None:
        try:
            if self.endpoint.transport == "tcp":
                self._run_tcp()
            else:
                self._run_udp()
        except OSError as error:
            if not self._stop.is_set():
                self._errors.append(f"{self.endpoint}: {error}")

    def _run_tcp(self) -> None:
        while not self._stop.is_set():
            try:
                connection, _ = self._socket.accept()
            except TimeoutError:
                continue
            self.tracker.restart()
            with connection:
                connection.settimeout(0.1)
                buffer = bytearray()
                while not self._stop.is_set():
                    try:
                        chunk = connection.recv(1 << 20)
                    except TimeoutError:
                        continue
                    except OSError:
                        break
                    if not chunk:
                        break
                    buffer += chunk
                    messages, skipped, errors = split_messages(buffer)
                    self.bytes_skipped += skipped
                    for error in errors:
                        self._complain("malformed", f"{self.endpoint}: {error}")
                    if skipped and not errors:
                        self._complain(
                            "malformed", f"{self.endpoint}: skipped {skipped} bytes that began no message"
                        )
                    for header, payload in messages:
                        self._message(header, payload)
            if not self._stop.is_set():
                self.queue.put(EndEvent(disconnected=True))

    def _run_udp(self) -> None:
        while not self._stop.is_set():
            try:
                datagram = self._socket.recv(MAX_UDP_BYTES + 1)
            except TimeoutError:
                continue
            try:
                header = decode_header(datagram)
                end = header.header_bytes + header.payload_bytes
                if len(datagram) != end:
                    raise ProtocolError(
                        f"datagram of {len(datagram)} bytes, its header says {end} "
                        "(one datagram must hold exactly one message)"
                    )
            except ProtocolError as error:
                self._complain("malformed", f"{self.endpoint}: {error}")
                continue
            self._message(header, datagram[header.header_bytes :])

    def _set_session(self, header: Recording) -> None:
        key = json.dumps(session_record(header), sort_keys=True)
        if key == self._session_key:
            return  # the same session again (UDP senders repeat it)
        self._session_key = key
        self.session = header
        self.queue.put(SessionEvent(header))

    def _message(self, header: MessageHeader, payload: bytes) -> None:
        arrival = time.monotonic()
        try:
            if header.kind == KIND_SESSION:
                announced = decode_session(header, payload, str(self.endpoint))
                if self.geometry is None:
                    if self._session_key not in (None, json.dumps(session_record(announced), sort_keys=True)):
                        self.tracker.restart()  # a new session numbers its frames afresh
                    self._set_session(announced)
                return
            if header.kind == KIND_END:
                self.queue.put(EndEvent())
                return
            assert header.kind == KIND_FRAME
            wire = decode_frame(header, payload)
        except ProtocolError as error:
            self._complain("malformed", f"{self.endpoint}: {error}")
            return
        current = self.session
        if current is None:
            self._complain(
                "rejected",
                f"{self.endpoint}: frames before any session message (send one, or give --geometry REC.h5)",
            )
            return
        session: Recording = current
        n_rx, n_samples = (int(d) for d in session.frames.shape[1:])
        problem = None
        if wire.samples.shape != (n_rx, n_samples):
            problem = (
                f"{wire.samples.shape[0]} channels x {wire.samples.shape[1]} samples, "
                f"the session has {n_rx} x {n_samples}"
            )
        elif wire.sample_rate_hz != session.sample_rate_hz:
            problem = f"{wire.sample_rate_hz:g} Hz, the session {session.sample_rate_hz:g} Hz"
        elif wire.signal_kind != session.signal_kind:
            problem = f"signal kind {wire.signal_kind}, the session {session.signal_kind}"
        elif wire.transmitter >= len(session.transmitters_m):
            problem = f"transmitter {wire.transmitter}, the session has {len(session.transmitters_m)}"
        if problem is not None:
            self._complain("rejected", f"{self.endpoint}: frame {wire.sequence} refused: {problem}")
            return
        number = self.tracker.observe(wire.sequence)
        if number is None:
            return
        self.received += 1
        if self._first_arrival is None:
            self._first_arrival = arrival
        time_s = wire.frame_time_s if math.isfinite(wire.frame_time_s) else arrival - self._first_arrival
        self.queue.put(StreamFrame(number, wire.samples, time_s, wire.transmitter, arrival))


# ----------------------------------------------------------------------------- sending


@dataclass(frozen=True)
class SendReport:
    """What :func:`send_recording` sent."""

    frames: int
    seconds: float
    bytes: int
    late: int

    def summary(self, endpoint: Endpoint) -> str:
        rate = self.frames / self.seconds if self.seconds > 0 else math.inf
        return (
            f"sent {self.frames} frames ({self.bytes / 1e6:.2f} MB) to {endpoint} in {self.seconds:.2f} s: "
            f"{rate:.1f} frames/s; {self.late} sent behind schedule"
        )


def recording_span_s(recording: Recording) -> float:
    """Length of one pass of a recording on its own clock: first to last frame, plus one period.

    The period is the median step of its frame times (back-to-back frames without them).
    """
    times = np.array([frame_time_s(recording, i) for i in range(recording.n_frames)])
    period = recording.n_samples / recording.sample_rate_hz
    if len(times) > 1:
        period = float(np.median(np.diff(times)))
    return float(times[-1] - times[0] + period)


def _schedule_s(recording: Recording, speed: float, rate_hz: float | None) -> tuple[np.ndarray, float]:
    """When each frame is due after the start, s, and the length of one pass."""
    n = recording.n_frames
    if rate_hz is not None:
        return np.arange(n) / rate_hz, n / rate_hz
    if speed <= 0:
        return np.zeros(n), 0.0
    times = np.array([frame_time_s(recording, i) for i in range(n)])
    return (times - times[0]) / speed, recording_span_s(recording) / speed


def send_recording(
    recording: Recording,
    endpoint: Endpoint,
    *,
    speed: float = 1.0,
    rate_hz: float | None = None,
    loops: int = 1,
    sample_format: str = "auto",
    connect_timeout_s: float = 5.0,
    session_every_s: float = 1.0,
    stop: threading.Event | None = None,
    end: bool = True,
) -> SendReport:
    """Replay ``recording`` to ``endpoint`` in the wire protocol.

    A session message goes first (on UDP again every ``session_every_s``, so a
    receiver started late still learns it), then the frames with sequence numbers
    0, 1, 2... running on across loops, then an end message (unless ``end`` is
    False). ``speed``: 1 plays at the recording's pace (its ``frame_times``, else
    back-to-back frames), N is N times faster, 0 as fast as the receiver takes it
    (on TCP the receiver's back-pressure sets the pace). ``rate_hz`` fixes frames per
    second instead. ``sample_format`` ``"auto"``: :func:`lossless_format`. ``loops`` 0
    loops until ``stop`` is set.
    """
    if rate_hz is not None and not (math.isfinite(rate_hz) and rate_hz > 0):
        raise EchoLocError(f"--rate must be > 0 frames/s, got {rate_hz}")
    if not (math.isfinite(speed) and speed >= 0):
        raise EchoLocError(f"--speed must be >= 0 (0: as fast as possible), got {speed}")
    if not (math.isfinite(connect_timeout_s) and connect_timeout_s >= 0):
        raise EchoLocError(
            f"--connect-timeout must be a finite number of seconds >= 0, got {connect_timeout_s}"
        )
    udp = endpoint.transport == "udp"
    if recording.signal_kind == "iq":
        sample_format = "complex64"
    elif sample_format == "auto":
        sample_format = lossless_format(recording, udp)
    stop = stop or threading.Event()
    session = encode_session(recording, sample_format=sample_format)
    due, pass_s = _schedule_s(recording, speed, rate_hz)
    times = [frame_time_s(recording, i) for i in range(recording.n_frames)]
    span_s = recording_span_s(recording)  # frame times of pass k are shifted by k spans
    if sample_format == "int16":
        peak = float(np.max(np.abs(recording.frames)))
        if peak < 256:
            warnings.warn(
                f"{recording.source}: int16 rounds samples to whole ADC counts and the largest is "
                f"{peak:.3g}: the signal keeps fewer than 9 bits (use float32 unless these are counts)",
                stacklevel=2,
            )
    if udp and len(session) > MAX_UDP_BYTES:
        raise EchoLocError(
            f"the session message is {len(session)} bytes, over the {MAX_UDP_BYTES} of one UDP datagram "
            "(a large background?): use TCP, or --geometry REC.h5 on the receiving side"
        )
    # Replayed more than once, a recording's payloads (the samples in the wire's format and
    # their CRC) are made once and kept, up to REPLAY_PAYLOAD_BYTES: later loops send them again.
    payloads: dict[int, FramePayload] = {}
    room_bytes = REPLAY_PAYLOAD_BYTES if loops != 1 else 0
    sock = _connect(endpoint, connect_timeout_s)
    sent_frames = sent_bytes = late = 0
    try:

        def send(message: bytes) -> None:
            nonlocal sent_bytes
            if udp:
                sock.send(message)
            else:
                sock.sendall(message)
            sent_bytes += len(message)

        send(session)
        last_session = time.monotonic()
        start = time.monotonic()
        loop = 0
        while not stop.is_set() and (loops == 0 or loop < loops):
            for index in range(recording.n_frames):
                if stop.is_set():
                    break
                target = start + loop * pass_s + float(due[index])
                wait = target - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                elif wait < -0.010 and speed != 0:
                    late += 1
                if udp and time.monotonic() - last_session >= session_every_s:
                    send(session)
                    last_session = time.monotonic()
                transmitter = (
                    0 if recording.frame_transmitter is None else int(recording.frame_transmitter[index])
                )
                payload = payloads.get(index)
                if payload is None:
                    payload = frame_payload(
                        recording.frames[index],
                        signal_kind=recording.signal_kind,
                        sample_format=sample_format,
                    )
                    if len(payload.data) <= room_bytes:
                        payloads[index] = payload
                        room_bytes -= len(payload.data)
                message = frame_message(
                    payload,
                    sequence=sent_frames,
                    sample_rate_hz=recording.sample_rate_hz,
                    frame_time_s=times[index] + loop * span_s,
                    transmitter=transmitter,
                    signal_kind=recording.signal_kind,
                )
                if udp and len(message) > MAX_UDP_BYTES:
                    raise EchoLocError(
                        f"a frame is {len(message)} bytes, over the {MAX_UDP_BYTES} of one UDP datagram: "
                        "use --sample-format int16 (or float32), or TCP"
                    )
                send(message)
                sent_frames += 1
            loop += 1
        if end:
            send(encode_end(sent_frames))
        return SendReport(sent_frames, time.monotonic() - start, sent_bytes, late)
    except (BrokenPipeError, ConnectionResetError):
        raise EchoLocError(
            f"{endpoint}: the receiver closed the connection after {sent_frames} frames"
        ) from None
    except ConnectionRefusedError:
        raise EchoLocError(f"{endpoint}: nothing listens there (start `echoloc stream` first)") from None
    finally:
        sock.close()


REPLAY_PAYLOAD_BYTES = 256 * 2**20
"""The most wire bytes of a recording :func:`send_recording` keeps to send again on its next
loops (making a float32 frame of 4 x 2400 samples, its bytes and CRC-32, took about half of
the sender's 39 µs a frame)."""


def lossless_format(recording: Recording, udp: bool = False) -> str:
    """float32 when every sample is a float32 value (no rounding), else float64 (float32 on UDP).

    On UDP a frame must fit one datagram: float64 frames of more than about 8000
    samples in all do not, and are sent rounded to float32 (a relative error of
    6e-8, far below any ADC's).
    """
    return "float32" if udp or _single_precision_exact(recording.frames) else "float64"


def _single_precision_exact(frames: Any) -> bool:
    """Is every sample a float32 value (complex64 for complex samples)?"""
    frames = np.asarray(frames)
    return bool(
        np.array_equal(frames.astype(np.complex64 if frames.dtype.kind == "c" else np.float32), frames)
    )


def _connect(endpoint: Endpoint, timeout_s: float) -> socket.socket:
    """A connected socket; TCP retries until ``timeout_s`` so the sender may start first."""
    family = socket.AF_INET6 if ":" in endpoint.host else socket.AF_INET
    if endpoint.transport == "udp":
        sock = socket.socket(family, socket.SOCK_DGRAM)
        sock.connect((endpoint.host, endpoint.port))
        return sock
    deadline = time.monotonic() + timeout_s
    while True:
        sock = socket.socket(family, socket.SOCK_STREAM)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            sock.connect((endpoint.host, endpoint.port))
            return sock
        except OSError as error:
            sock.close()
            if time.monotonic() >= deadline:
                raise EchoLocError(
                    f"{endpoint}: cannot connect ({error.strerror or error}); is `echoloc stream` running?"
                ) from None
            time.sleep(0.05)


# ----------------------------------------------------------------------------- recording


def _lossless_storage(first: FrameBatch | None) -> type[np.floating[Any]]:
    """float32 when every sample of the first batch is a float32 value (float32 or int16 on
    the wire, or complex64), else float64: frames arrive as float64 whatever the wire carried,
    and a sender that chose float64 (:func:`lossless_format`) must not be rounded on disk."""
    return np.float32 if first is None or _single_precision_exact(first.frames) else np.float64


class Recorder:
    """Appends frames to an HDF5 recording from its own thread, one flushed batch at a time.

    Frames given to :meth:`add` are gathered into batches of ``batch_frames`` frames
    or ``batch_s`` seconds, whichever comes first, and appended by
    :func:`echoloc.recording.append_recording_stream`: a recorder killed at any
    moment loses at most the batch it was gathering or writing. The file is made with the
    first batch, in the precision the samples came in (:func:`_lossless_storage`; a sender
    that changes precision later is rounded to the first). The hand-over queue
    is bounded (``max_frames``); frames that find it full are counted in
    :attr:`dropped`, never waited for, so recording never holds up the stream.
    """

    @staticmethod
    def check_path(path: Path) -> None:
        """Refuse, before anything arrives, a target that cannot be recorded to (one line)."""
        suffix = path.suffix.lower()
        if suffix not in (".h5", ".hdf5"):
            why = ": a .npz is readable only once complete" if suffix == ".npz" else ""
            raise EchoLocError(f"{path}: a stream is recorded to HDF5 (.h5 or .hdf5){why}")
        if problem := missing_directory(path):
            raise EchoLocError(f"{path}: {problem}")

    def __init__(
        self,
        path: Path,
        header: Recording,
        *,
        batch_frames: int = 64,
        batch_s: float = 0.5,
        max_frames: int = 1024,
        on_batch: Callable[[int], None] | None = None,
    ) -> None:
        if batch_frames < 1:
            raise EchoLocError(f"--batch-frames must be >= 1, got {batch_frames}")
        if not (math.isfinite(batch_s) and batch_s > 0):
            raise EchoLocError(f"--batch-seconds must be > 0, got {batch_s}")
        self.path = path
        self.header = as_header(header)
        self.batch_frames = batch_frames
        self.batch_s = batch_s
        self.frames = 0
        self.batches = 0
        self.dropped = 0
        self.error: BaseException | None = None
        self._on_batch = on_batch
        self._queue: queue.Queue[StreamFrame | None] = queue.Queue(maxsize=max_frames)
        self._thread = threading.Thread(target=self._run, name=f"echoloc-recorder {path}", daemon=True)
        self._thread.start()

    def add(self, frame: StreamFrame) -> None:
        """Hand over one frame (never blocks; after a write error frames are counted as dropped)."""
        if self.error is not None:
            self.dropped += 1
            return
        try:
            self._queue.put_nowait(frame)
        except queue.Full:
            self.dropped += 1

    def close(self) -> None:
        """Write what is gathered, close the file, and raise what the writer met (an EchoLocError)."""
        while self._thread.is_alive():
            try:
                self._queue.put(None, timeout=0.1)
                break
            except queue.Full:
                continue
        self._thread.join()
        if self.error is not None:
            raise self.error

    def _batches(self) -> Iterator[FrameBatch]:
        done = False
        while not done:
            frames: list[StreamFrame] = []
            started = time.monotonic()
            while len(frames) < self.batch_frames:
                left = self.batch_s - (time.monotonic() - started) if frames else 3600.0
                try:
                    item = self._queue.get(timeout=max(left, 1e-3))
                except queue.Empty:
                    break
                if item is None:
                    done = True
                    break
                frames.append(item)
            if frames:
                stacked: Samples = np.stack([np.asarray(f.samples) for f in frames])
                batch = FrameBatch(
                    frames=stacked,
                    frame_times_s=np.array([f.time_s for f in frames], dtype=np.float64),
                    frame_transmitter=np.array([f.transmitter for f in frames], dtype=np.int64),
                )
                del frames
                yield batch
                self.frames += batch.n_frames
                self.batches += 1
                if self._on_batch is not None:
                    self._on_batch(self.frames)

    def _run(self) -> None:
        try:
            batches = self._batches()
            first = next(batches, None)
            append_recording_stream(
                self.header,
                batches if first is None else itertools.chain([first], batches),
                self.path,
                frames_dtype=_lossless_storage(first),
            )
        except BaseException as error:  # handed to close(), which raises it in the caller's thread
            self.error = error
            while True:  # what was handed over and will not be written
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                self.dropped += item is not None
