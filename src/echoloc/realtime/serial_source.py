"""Capture from a board on a serial or USB-CDC port: the serial framing (docs/SERIAL_PROTOCOL.md).

A microcontroller that digitises the receivers writes each frame to its serial port as it
comes out of the ADC's DMA buffer: a 28-byte header (sync word ``ECHS``, layout, sequence
number, capture timestamp, and a CRC-32 of the header), the ADC counts in the head file's
``[adc] format``, and a CRC-32 of them. There is no session on the line: the head file
(:class:`~echoloc.io.head.SensorHead`) says what the board is and how it is wired.

- :func:`encode_serial_frame` turns counts into the bytes of one frame (for senders and tests;
  ``examples/serial_sender.py`` is a Python stand-in for firmware);
- :class:`SerialDecoder` turns a byte stream, fed in pieces as they come, into
  :class:`SerialFrame` s and :class:`SerialProblem` s: pure, no port needed. It finds its
  place again after anything (a byte lost on a UART, a board reset mid-frame, garbage) on the
  next sync word whose header CRC checks;
- :class:`SerialSource` reads a port through pyserial (``serial.serial_for_url``: a device
  path, ``loop://``, ``socket://HOST:PORT``, ``rfc2217://HOST:PORT``, a pty) and puts the
  head's session and the frames on a :class:`~echoloc.realtime.stream.FrameQueue`, as the
  network listener does (:class:`~echoloc.realtime.capture.CaptureSource`).
"""

from __future__ import annotations

import contextlib
import errno
import importlib
import os
import struct
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from echoloc.errors import EchoLocError
from echoloc.extras import missing_extra
from echoloc.io.head import SAMPLE_FORMATS, SensorHead
from echoloc.io.recording import Recording
from echoloc.realtime.capture import CaptureSource
from echoloc.realtime.stream import FrameQueue
from echoloc.realtime.transport import WARN_INTERVAL_S

SYNC = b"ECHS"
"""The sync word every frame starts with (0x45 0x43 0x48 0x53)."""

VERSION = 1

HEADER = struct.Struct("<4sBBHHBBIQ")
"""sync, version, sample format, n_channels, values_per_channel, transmitter, flags, sequence,
timestamp_us: 24 bytes, every field at an offset that is a multiple of its size."""
CRC = struct.Struct("<I")
HEADER_BYTES = HEADER.size + CRC.size
"""The header with its CRC-32: 28 bytes."""
TRAILER_BYTES = CRC.size
"""The payload's CRC-32 after the samples: 4 bytes."""
assert HEADER.size == 24
assert HEADER_BYTES == 28

FORMAT_CODES: dict[str, int] = {"int16": 1, "float32": 2, "uint16": 5, "int32": 6}
"""A sample format's code in the header: the stream protocol's codes (1 int16, 2 float32) and
two more for ADCs (3 and 4, the stream protocol's float64 and complex64, are no ADC's)."""
FORMAT_NAMES = {code: name for name, code in FORMAT_CODES.items()}

FLAG_TIME32 = 0x01
"""``timestamp_us`` is a 32-bit counter of microseconds that wraps (its high 32 bits are 0):
the reader unwraps it."""
FLAG_INTERLEAVED = 0x02
"""The payload is sample after sample (value 0 of every channel, then value 1, ...), as a
scanning ADC's DMA fills its buffer, instead of channel after channel."""

MAX_PAYLOAD_BYTES = 64 * 2**20
"""The largest payload a decoder that knows no head waits for, bytes (one with a head waits for
exactly its frame and refuses any other at its header)."""

DEFAULT_BAUDRATE = 2_000_000
"""The rate a port is opened at by default, baud (USB-CDC ignores it; a UART needs the board's)."""
READ_TIMEOUT_S = 0.1
"""A read of the port returns after this long even if the frame is incomplete, s: how soon a
stopped source notices."""
MAX_READ_BYTES = 1 << 20
"""The most bytes read in one call, however many are waiting."""


@dataclass(frozen=True)
class SerialLayout:
    """What a frame on the line must hold: ``n_channels`` x ``values_per_channel`` samples in
    ``sample_format`` (a name of :data:`FORMAT_CODES`)."""

    n_channels: int
    values_per_channel: int
    sample_format: str

    @classmethod
    def of_head(cls, head: SensorHead) -> SerialLayout:
        return cls(head.n_channels, head.values_per_channel, head.adc.format)

    @property
    def payload_bytes(self) -> int:
        return (
            self.n_channels * self.values_per_channel * np.dtype(SAMPLE_FORMATS[self.sample_format]).itemsize
        )

    def __str__(self) -> str:
        return f"{self.n_channels} channels x {self.values_per_channel} {self.sample_format} values"


@dataclass(frozen=True)
class SerialHeader:
    """One frame's header, decoded and checked (its CRC, version and format)."""

    layout: SerialLayout
    transmitter: int
    flags: int
    sequence: int
    timestamp_us: int

    @property
    def frame_bytes(self) -> int:
        """Bytes of the whole frame: header, payload and the payload's CRC."""
        return HEADER_BYTES + self.layout.payload_bytes + TRAILER_BYTES


@dataclass(frozen=True, eq=False)
class SerialFrame:
    """One frame off the line: ``counts`` (n_channels, values_per_channel), channel after channel
    whatever the order on the line, in the format sent; the header's fields as sent
    (``timestamp_us`` raw: a 32-bit counter when ``flags`` has :data:`FLAG_TIME32`)."""

    sequence: int
    timestamp_us: int
    transmitter: int
    flags: int
    counts: NDArray[Any]


@dataclass(frozen=True)
class SerialProblem:
    """Something on the line that is no usable frame: ``counter`` is ``"malformed"`` (the framing
    was broken: a CRC, garbage, a frame cut short) or ``"rejected"`` (a well-formed frame that does
    not fit the head); ``kind`` groups the warnings; ``message`` is one line;
    ``sequence``: the rejected frame's sequence number (None for malformed input)."""

    counter: str
    kind: str
    message: str
    sequence: int | None = None


def encode_serial_frame(
    counts: NDArray[Any],
    *,
    sequence: int,
    timestamp_us: int,
    transmitter: int = 0,
    sample_format: str | None = None,
    time32: bool = False,
    interleaved: bool = False,
) -> bytes:
    """The bytes of one frame of the serial framing.

    ``counts`` (n_channels, values_per_channel), ADC counts, channel after channel; written in
    ``sample_format`` (default: the array's own, which must be one of :data:`FORMAT_CODES`);
    ``sequence`` wraps at 2**32; ``timestamp_us`` the capture clock's microseconds at the
    emission (0 .. 2**64 - 1; with ``time32``, its low 32 bits, flagged as a wrapping counter);
    ``interleaved``: the samples go sample after sample (:data:`FLAG_INTERLEAVED`).
    """
    values = np.asarray(counts)
    if values.ndim != 2 or 0 in values.shape or max(values.shape) > 0xFFFF:
        raise EchoLocError(f"a frame must be (n_channels, values) with both in 1..65535, got {values.shape}")
    name = sample_format if sample_format is not None else values.dtype.name
    if name not in FORMAT_CODES:
        raise EchoLocError(f"sample format {name!r}: the serial framing takes {', '.join(FORMAT_CODES)}")
    if not 0 <= transmitter <= 0xFF:
        raise EchoLocError(f"transmitter {transmitter}: the serial framing numbers 0..255")
    if not 0 <= timestamp_us < 1 << 64:
        raise EchoLocError(f"timestamp_us {timestamp_us}: must be in 0 .. 2**64 - 1")
    flags = (FLAG_TIME32 if time32 else 0) | (FLAG_INTERLEAVED if interleaved else 0)
    wire = values.astype(SAMPLE_FORMATS[name], copy=False)
    payload = (wire.T if interleaved else wire).tobytes()
    header = HEADER.pack(
        SYNC,
        VERSION,
        FORMAT_CODES[name],
        values.shape[0],
        values.shape[1],
        transmitter,
        flags,
        sequence & 0xFFFFFFFF,
        timestamp_us & 0xFFFFFFFF if time32 else timestamp_us,
    )
    return b"".join((header, CRC.pack(zlib.crc32(header)), payload, CRC.pack(zlib.crc32(payload))))


def decode_serial_header(data: bytes | bytearray | memoryview) -> SerialHeader:
    """Decode and check the 28-byte header at the start of ``data``.

    Raises
    ------
    EchoLocError
        Not the sync word, a CRC that does not match, another version, an unknown sample format,
        or a frame of no samples: one line.
    """
    view = memoryview(data)[:HEADER_BYTES]
    if len(view) < HEADER_BYTES:
        raise EchoLocError(f"{len(view)} bytes: shorter than the {HEADER_BYTES}-byte header")
    sync, version, code, n_channels, n_values, transmitter, flags, sequence, timestamp = HEADER.unpack_from(
        view
    )
    if sync != SYNC:
        raise EchoLocError(f"no sync word: {bytes(sync)!r}, expected {SYNC!r}")
    if CRC.unpack_from(view, HEADER.size)[0] != zlib.crc32(view[: HEADER.size]):
        raise EchoLocError("a header's CRC-32 does not match (bytes lost or corrupted on the line)")
    if version != VERSION:
        raise EchoLocError(
            f"a frame of serial framing version {version}; this reader reads version {VERSION}"
        )
    if code not in FORMAT_NAMES:
        known = ", ".join(f"{c} {name}" for c, name in FORMAT_NAMES.items())
        raise EchoLocError(f"a frame of unknown sample format code {code} (known: {known})")
    if n_channels == 0 or n_values == 0:
        raise EchoLocError(f"a frame of {n_channels} channels x {n_values} values: no samples")
    return SerialHeader(
        SerialLayout(n_channels, n_values, FORMAT_NAMES[code]), transmitter, flags, sequence, timestamp
    )


class SerialDecoder:
    """Frames out of a byte stream that comes in pieces of any size (:meth:`feed`).

    ``layout``: the frames expected (a head's, :meth:`SerialLayout.of_head`; ``expecting``
    names it in messages); a well-formed frame of another layout is refused at its header (a
    ``"rejected"`` :class:`SerialProblem`; its bytes are skipped without waiting for them).
    None: any layout, payloads up to ``max_payload_bytes``.

    The decoder finds a frame by its sync word and a header whose CRC checks. After anything
    else it looks for the next one from the byte after the last sync word it trusted, so a
    byte lost inside a frame costs that frame only. Each place the framing broke is one
    ``"malformed"`` problem, however many bytes it took: a header or payload CRC that does
    not match, a frame cut short by the next frame's header, bytes between two frames that
    belong to neither. What comes before the first good header is the end of a frame the
    port was opened in the middle of: skipped without a problem. Every byte that is not part
    of a frame handed out is counted in :attr:`bytes_skipped`. Memory: one frame and one
    read's worth of bytes.
    """

    def __init__(
        self,
        layout: SerialLayout | None = None,
        *,
        expecting: str = "the head",
        max_payload_bytes: int = MAX_PAYLOAD_BYTES,
    ) -> None:
        self.layout = layout
        self.expecting = expecting
        self.max_payload_bytes = max_payload_bytes
        self.frames = 0
        self.malformed = 0
        self.rejected = 0
        self.bytes_skipped = 0
        self._buffer = bytearray()
        self._start = 0  # where the bytes not yet consumed begin in _buffer
        self._header: SerialHeader | None = None  # the good header at _start, waiting for its payload
        self._scanned = 0  # how far into the pending frame the next frame's header was looked for
        self._lost = True  # out of step: the bytes skipped now belong to a problem already said
        self._skipped_run = 0  # bytes skipped since the last good header

    def wanted(self) -> int:
        """Bytes still needed before anything more can come out (at least 1): what a reader asks
        its port for, so that a read returns the moment a frame is complete."""
        held = len(self._buffer) - self._start
        if self._header is not None:
            return max(1, self._header.frame_bytes - held)
        return max(1, HEADER_BYTES - held)

    def feed(self, data: bytes | bytearray | memoryview) -> list[SerialFrame | SerialProblem]:
        """Take ``data``; the frames and problems it completes, in order."""
        self._buffer += data
        out: list[SerialFrame | SerialProblem] = []
        while self._step(out):
            pass
        if self._start:
            del self._buffer[: self._start]
            self._scanned = max(0, self._scanned - self._start)
            self._start = 0
        return out

    # -- inside

    def _step(self, out: list[SerialFrame | SerialProblem]) -> bool:
        """One step on: True if it consumed bytes (there may be more to do), False if it waits."""
        if self._header is None:
            return self._seek(out)
        end = self._start + self._header.frame_bytes
        if len(self._buffer) >= end:
            self._complete(self._header, end, out)
            return True
        return self._cut_short(self._header, out)

    def _skip_to(self, position: int) -> None:
        skipped = position - self._start
        self.bytes_skipped += skipped
        self._skipped_run += skipped
        self._start = position

    def _broken(self, out: list[SerialFrame | SerialProblem], kind: str, message: str) -> None:
        """The framing broke at the sync word at ``_start``: said (unless the decoder was out of
        step already: one problem a break), and the next sync word looked for after it."""
        if not self._lost:
            self.malformed += 1
            out.append(SerialProblem("malformed", kind, message))
        self._lost = True
        self._header = None
        self._skip_to(self._start + 1)

    def _checks(self, at: int) -> bool:
        """Does a header whose sync word and CRC check begin at ``at`` (its 28 bytes there)?"""
        with memoryview(self._buffer) as view:
            if view[at : at + len(SYNC)] != SYNC:
                return False
            (crc,) = CRC.unpack_from(view, at + HEADER.size)
            return bool(crc == zlib.crc32(view[at : at + HEADER.size]))

    def _seek(self, out: list[SerialFrame | SerialProblem]) -> bool:
        """Find the next good header and take it (True), or wait for more bytes (False). A sync
        word whose header CRC does not check is more bytes that are no frame's."""
        buffer = self._buffer
        at = buffer.find(SYNC, self._start)
        if at < 0:  # keep what could be the beginning of a sync word
            self._skip_to(max(self._start, len(buffer) - len(SYNC) + 1))
            return False
        self._skip_to(at)
        if len(buffer) - at < HEADER_BYTES:
            return False
        if not self._checks(at):
            self._skip_to(at + 1)
            return True
        if self._skipped_run and not self._lost:
            self.malformed += 1
            out.append(
                SerialProblem(
                    "malformed",
                    "garbage",
                    f"{self._skipped_run} bytes between frames that belong to no frame (a frame whose "
                    "header came corrupted, or bytes lost or added on the line): skipped",
                )
            )
        self._skipped_run = 0
        self._lost = False
        try:
            with memoryview(buffer) as view:
                header = decode_serial_header(view[at : at + HEADER_BYTES])
        except EchoLocError as error:  # the board's own header, that this reader cannot read
            self.malformed += 1
            out.append(SerialProblem("malformed", "header", f"{error}: skipped"))
            self._lost = True  # said: its samples are skipped in silence
            self._skip_to(at + 1)
            return True
        layout = header.layout
        if self.layout is not None and layout != self.layout:
            self.rejected += 1
            out.append(
                SerialProblem(
                    "rejected",
                    "layout",
                    f"frame {header.sequence} refused: {layout}, where {self.expecting} has {self.layout} "
                    "(is the board programmed for another head file?)",
                    header.sequence,
                )
            )
            self._lost = True
            self._skip_to(at + 1)
            return True
        if self.layout is None and layout.payload_bytes > self.max_payload_bytes:
            self._broken(
                out,
                "header",
                f"frame {header.sequence}: {layout} ({layout.payload_bytes} bytes), more than the "
                f"{self.max_payload_bytes} taken: skipped",
            )
            return True
        self._header = header
        self._scanned = at + HEADER_BYTES
        return True

    def _cut_short(self, header: SerialHeader, out: list[SerialFrame | SerialProblem]) -> bool:
        """The pending frame is still incomplete. If a good header has begun inside it, the frame
        was cut short (bytes lost, or the board restarted it): said, and on to that header at
        once, rather than when enough bytes have come to fill the frame that will never be."""
        buffer = self._buffer
        while True:
            at = buffer.find(SYNC, self._scanned)
            if at < 0:
                self._scanned = max(self._scanned, len(buffer) - len(SYNC) + 1)
                return False
            if len(buffer) - at < HEADER_BYTES:
                self._scanned = at
                return False
            if self._checks(at):
                self._cut(header, at, out)
                return True
            self._scanned = at + 1

    def _cut(self, header: SerialHeader, at: int, out: list[SerialFrame | SerialProblem]) -> None:
        """The pending frame was cut short by the good header at ``at``: said, and on to it."""
        self._broken(
            out,
            "cut",
            f"frame {header.sequence} cut short after {at - self._start} of its {header.frame_bytes} "
            "bytes by the next frame (bytes lost on the line, or the board restarted): dropped",
        )
        self._skip_to(at)
        self._skipped_run = 0  # this problem's bytes

    def _complete(self, header: SerialHeader, end: int, out: list[SerialFrame | SerialProblem]) -> None:
        buffer = self._buffer
        payload_start = self._start + HEADER_BYTES
        payload_end = end - TRAILER_BYTES
        with memoryview(buffer) as view:
            good = CRC.unpack_from(view, payload_end)[0] == zlib.crc32(view[payload_start:payload_end])
        if not good:
            at = self._buffer.find(SYNC, payload_start, end)
            while at >= 0 and at + HEADER_BYTES <= len(buffer) and not self._checks(at):
                at = self._buffer.find(SYNC, at + 1, end)
            if at >= 0 and at + HEADER_BYTES <= len(buffer):  # the next frame began inside this one
                self._cut(header, at, out)
                return
            self._broken(
                out,
                "crc",
                f"frame {header.sequence}: the samples' CRC-32 does not match (bytes lost or "
                "corrupted on the line): dropped",
            )
            return
        layout = header.layout
        dtype = np.dtype(SAMPLE_FORMATS[layout.sample_format])
        count = layout.n_channels * layout.values_per_channel
        flat = np.frombuffer(buffer, dtype=dtype, count=count, offset=payload_start)
        if header.flags & FLAG_INTERLEAVED:
            counts = flat.reshape(layout.values_per_channel, layout.n_channels).T.copy()
        else:
            counts = flat.reshape(layout.n_channels, layout.values_per_channel).copy()
        del flat  # the buffer is resized next: no view of it may outlive this call
        self._header = None
        self._start = end
        self._skipped_run = 0
        self.frames += 1
        out.append(
            SerialFrame(header.sequence, header.timestamp_us, header.transmitter, header.flags, counts)
        )


class CaptureClock:
    """A frame's ``time_s`` from its header's ``timestamp_us``: the board's clock in seconds, as
    the board counts it (typically since it started). A 32-bit counter (:data:`FLAG_TIME32`)
    is unwrapped: each stamp is taken as the nearest to the last one (within 2**31 us, 36
    minutes, either way), so it goes on past 2**32 us (71.6 minutes) instead of falling back."""

    def __init__(self) -> None:
        self._last: int | None = None  # the last 32-bit stamp, unwrapped

    def time_s(self, timestamp_us: int, flags: int) -> float:
        if not flags & FLAG_TIME32:
            return timestamp_us / 1e6
        raw = timestamp_us & 0xFFFFFFFF
        if self._last is None:
            self._last = raw
        else:
            step = ((raw - self._last + (1 << 31)) & 0xFFFFFFFF) - (1 << 31)
            self._last += step
        return self._last / 1e6


def _pyserial() -> Any:
    try:  # pyserial has no type stubs: taken as Any
        return importlib.import_module("serial")
    except ImportError:
        raise missing_extra("serial", "capture from a serial port") from None


def _why(error: BaseException) -> str:
    """What an OS or pyserial error says, shortly, with a hint where one helps."""
    number = getattr(error, "errno", None)
    text = os.strerror(number) if isinstance(number, int) and number > 0 else str(error)
    hints = {
        errno.EACCES: " (is your user in the dialout group, or uucp on some systems?)",
        errno.EBUSY: " (another program has it open?)",
        errno.EAGAIN: " (locked: another program is reading it, another echoloc perhaps)",
        errno.ENOENT: " (unplugged, or another name? ls /dev/ttyACM* /dev/ttyUSB*)",
    }
    return text + (hints.get(number, "") if isinstance(number, int) else "")


class SerialSource(CaptureSource):
    """Frames of the serial framing read from ``port``, into ``frames``.

    Parameters
    ----------
    head
        The head the board belongs to: its header is the session, its channels, values and
        ``[adc] format`` what every frame must carry (others are refused, one warning line).
    frames
        Where the session, the frames and the end go.
    port
        What pyserial opens (``serial.serial_for_url``): ``/dev/ttyACM0``, ``COM3``, a pty,
        ``loop://``, ``socket://HOST:PORT``, ``rfc2217://HOST:PORT``.
    baudrate
        The UART's rate (USB-CDC ignores it).
    accept_session
        As :class:`~echoloc.realtime.capture.CaptureSource`'s.

    A port that cannot be opened raises :class:`~echoloc.errors.EchoLocError` from
    :meth:`start` (one line naming it); a port that goes away (a board unplugged) is one
    warning line and an :class:`~echoloc.realtime.transport.EndEvent`. A frame's ``time_s``
    is its header's timestamp on the board's clock (:class:`CaptureClock`), its number the
    unwrapped sequence number (gaps counted lost); :attr:`bytes_skipped` counts the bytes that
    were no frame's (the end of the frame the port was opened in, and whatever came broken).
    """

    kind = "serial"

    def __init__(
        self,
        head: SensorHead,
        frames: FrameQueue,
        port: str,
        *,
        baudrate: int = DEFAULT_BAUDRATE,
        accept_session: Callable[[Recording], object] | None = None,
        warn_interval_s: float = WARN_INTERVAL_S,
        read_timeout_s: float = READ_TIMEOUT_S,
    ) -> None:
        self._serial = _pyserial()
        if head.adc.format not in FORMAT_CODES:
            raise EchoLocError(
                f"{head.source}: adc.format {head.adc.format!r} has no code in the serial framing"
            )
        self.url = port
        self.baudrate = baudrate
        self.read_timeout_s = read_timeout_s
        self.port: Any = None  # the pyserial port, once open
        self.decoder = SerialDecoder(SerialLayout.of_head(head), expecting=f"the head {head.name!r}")
        self.clock = CaptureClock()
        super().__init__(head, frames, accept_session=accept_session, warn_interval_s=warn_interval_s)

    @property
    def address(self) -> str:
        return f"serial:{self.url}"

    @property
    def bytes_skipped(self) -> int:
        """Bytes read that were no frame's."""
        return self.decoder.bytes_skipped

    def _open(self) -> None:
        serial = self._serial
        # exclusive: a second reader of the same device (another echoloc, say) is refused rather
        # than left to take every other read's bytes (pyserial locks the device where it can).
        exclusive = None if "://" in self.url else True
        try:
            self.port = serial.serial_for_url(
                self.url, baudrate=self.baudrate, timeout=self.read_timeout_s, exclusive=exclusive
            )
        except (OSError, ValueError) as error:
            reason = _why(error) if isinstance(error, OSError) and error.errno else str(error)
            reason = reason.split(f"{self.url}: ", 1)[-1]  # pyserial's "could not open port PORT: ..."
            raise EchoLocError(f"cannot open serial port {self.url}: {reason}") from None

    def _close(self) -> None:
        port, self.port = self.port, None
        if port is not None:
            with contextlib.suppress(Exception):  # the device may be gone already: nothing to release
                port.close()

    def _run(self) -> None:
        port = self.port
        decoder = self.decoder
        while not self._stop.is_set():
            try:
                waiting = port.in_waiting
                data = port.read(min(MAX_READ_BYTES, max(decoder.wanted(), waiting)))
            except (OSError, self._serial.SerialException) as error:
                if not self._stop.is_set():
                    # pyserial: "device reports readiness to read but returned no data (device
                    # disconnected or multiple access on port?)": a USB device unplugged, a pty closed.
                    reason = "disconnected" if "returned no data" in str(error) else _why(error)
                    self._warnings.add(
                        "device", f"{self.address}: the port went away ({reason}): capture stopped"
                    )
                return
            if not data:
                continue
            for item in decoder.feed(data):
                if isinstance(item, SerialFrame):
                    time_s = self.clock.time_s(item.timestamp_us, item.flags)
                    self._deliver(item.counts, time_s, item.sequence, item.transmitter)
                elif item.counter == "rejected":
                    self._reject(item.sequence, item.kind, f"{self.address}: {item.message}")
                else:
                    self._complain(item.counter, item.kind, f"{self.address}: {item.message}")
