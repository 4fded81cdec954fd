"""The echoloc wire protocol: frames of samples over TCP or UDP (``docs/STREAM_PROTOCOL.md``).

Every message is a fixed 52-byte little-endian header followed by a payload:

- a **session** message (kind 1) carries the per-recording fields of the recording
  contract (docs/FORMATS.md: geometry, waveform, air state...) as UTF-8 JSON under the
  contract's own names, so the receiver can prepare its chain;
- a **frame** message (kind 2) carries one frame, n_channels x n_samples samples,
  channel after channel, with its sequence number, start time and transmitter;
- an **end** message (kind 3) says the sender is done (no payload);
- a **refusal** message (kind 4) goes the other way, from a TCP receiver to its
  sender, saying in one line why it refused the session or the connection.

The header ends with a CRC-32 of the bytes before it, so a receiver that lost its
place in a TCP byte stream finds the next message by its magic and CRC, and a
corrupted UDP datagram is refused rather than misread. All functions here are pure:
they turn values into bytes and bytes into values, and refuse a malformed message
with a :class:`ProtocolError` of one line.
"""

from __future__ import annotations

import json
import math
import struct
import zlib
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording, contract_items, recording_from_items, validate_header

MAGIC = b"ECHL"
VERSION = 1
HEADER = struct.Struct("<4sBBHIIddIHHBBHI")
HEADER_CRC = struct.Struct("<I")
HEADER_BYTES = HEADER.size + HEADER_CRC.size  # 52
assert HEADER_BYTES == 52

KIND_SESSION = 1
KIND_FRAME = 2
KIND_END = 3
KIND_REFUSAL = 4
KINDS = {KIND_SESSION: "session", KIND_FRAME: "frame", KIND_END: "end", KIND_REFUSAL: "refusal"}

FLAG_PAYLOAD_CRC = 0x0001
#: A session whose ``sequence`` is the number of the next frame the sender will send (so a
#: receiver sees a sender that started again); without it a session's ``sequence`` means nothing.
FLAG_NEXT_SEQUENCE = 0x0002

#: Sample formats: code -> (name, NumPy dtype of one sample on the wire).
SAMPLE_FORMATS: dict[int, tuple[str, np.dtype[Any]]] = {
    1: ("int16", np.dtype("<i2")),
    2: ("float32", np.dtype("<f4")),
    3: ("float64", np.dtype("<f8")),
    4: ("complex64", np.dtype("<c8")),
}
SAMPLE_FORMAT_CODES = {name: code for code, (name, _) in SAMPLE_FORMATS.items()}
SIGNAL_KIND_CODES = {"rf": 0, "envelope": 1, "iq": 2}
SIGNAL_KINDS = {code: name for name, code in SIGNAL_KIND_CODES.items()}

#: Largest UDP payload over IPv4 (65535 - 8 UDP - 20 IP): one datagram is one message.
MAX_UDP_BYTES = 65_507
#: Largest payload accepted on TCP (a bound on what a bad peer can make us allocate).
MAX_PAYLOAD_BYTES = 64 * 1024 * 1024
#: Largest session payload a receiver decodes (its JSON; room for a background of a few channels
#: of thousands of samples). Decoding JSON can cost many times its size in memory (every ``[]``
#: becomes a list object), so the bound is kept well below what a frame may be.
MAX_SESSION_BYTES = 2 * 1024 * 1024
#: Largest frame a session may announce, in memory (float64, complex128 for iq): channels x
#: samples x 8 (16) bytes. 2 MiB: 4 channels x 65 536 samples, 32 x 8192. Preparing a chain
#: takes memory and time that grow with the frame (its templates, spectra and tables), and a
#: session is prepared before any frame comes: the bound keeps what one session can cost small.
MAX_FRAME_BYTES = 2 * 1024 * 1024
#: Longest refusal message (its one line of UTF-8).
MAX_REFUSAL_BYTES = 1024


class ProtocolError(EchoLocError):
    """A message that breaks the wire protocol (counted as malformed by a receiver)."""


@dataclass(frozen=True)
class MessageHeader:
    """The decoded 52-byte header of one message.

    Attributes
    ----------
    kind
        1 session, 2 frame, 3 end, 4 refusal.
    header_bytes, payload_bytes
        Length of the header (52 in version 1; later versions may add fields before
        the CRC) and of the payload that follows it.
    sequence
        Frame counter, uint32, +1 per frame sent, wrapping at 2**32.
    frame_time_s
        Start of the frame's emission on the sender's clock, s; NaN if unknown.
    sample_rate_hz, n_channels, n_samples, sample_format, signal_kind
        Layout of the frame's samples (for a session: of the frames that follow).
    transmitter
        Index into the session's transmitters fired in this frame.
    payload_crc32
        CRC-32 of the payload, or None when the sender did not compute one.
    announces_sequence
        A session whose ``sequence`` is the next frame's (:data:`FLAG_NEXT_SEQUENCE`).
    """

    kind: int
    header_bytes: int
    payload_bytes: int
    sequence: int
    frame_time_s: float
    sample_rate_hz: float
    n_channels: int
    n_samples: int
    sample_format: int
    signal_kind: str
    transmitter: int = 0
    payload_crc32: int | None = None
    announces_sequence: bool = False


@dataclass(frozen=True, eq=False)
class WireFrame:
    """One frame as received: samples (n_channels, n_samples) and what the header says of them."""

    sequence: int
    frame_time_s: float
    transmitter: int
    sample_rate_hz: float
    signal_kind: str
    samples: NDArray[np.floating] | NDArray[np.complexfloating]


def _pack(header: MessageHeader) -> bytes:
    flags = 0 if header.payload_crc32 is None else FLAG_PAYLOAD_CRC
    if header.announces_sequence:
        flags |= FLAG_NEXT_SEQUENCE
    body = HEADER.pack(
        MAGIC,
        VERSION,
        header.kind,
        HEADER_BYTES,
        header.payload_bytes,
        header.sequence & 0xFFFFFFFF,
        header.frame_time_s,
        header.sample_rate_hz,
        header.n_samples,
        header.n_channels,
        header.transmitter,
        header.sample_format,
        SIGNAL_KIND_CODES[header.signal_kind],
        flags,
        header.payload_crc32 or 0,
    )
    return body + HEADER_CRC.pack(zlib.crc32(body))


def decode_header(
    data: bytes | bytearray | memoryview, *, max_payload_bytes: int = MAX_PAYLOAD_BYTES
) -> MessageHeader:
    """Decode and check the header at the start of ``data`` (at least 52 bytes).

    ``max_payload_bytes``: the longest payload taken (a receiver's bound on what one
    message may make it hold).

    Raises
    ------
    ProtocolError
        Wrong magic, unknown version, bad CRC, an unknown kind, sample format or
        signal kind, or impossible sizes.
    """
    if len(data) < HEADER_BYTES:
        raise ProtocolError(f"message of {len(data)} bytes is shorter than the {HEADER_BYTES}-byte header")
    view = memoryview(data)
    fields = HEADER.unpack_from(view)
    magic, version, kind, header_bytes = fields[:4]
    if magic != MAGIC:
        raise ProtocolError(f"bad magic {bytes(magic)!r}, expected {MAGIC!r}")
    if version != VERSION:
        raise ProtocolError(f"protocol version {version}, this receiver reads version {VERSION}")
    if header_bytes < HEADER_BYTES or header_bytes > len(data):
        raise ProtocolError(
            f"header_bytes is {header_bytes}, expected {HEADER_BYTES} (or more, at most the data)"
        )
    (crc,) = HEADER_CRC.unpack_from(view, header_bytes - HEADER_CRC.size)
    if crc != zlib.crc32(view[: header_bytes - HEADER_CRC.size]):
        raise ProtocolError("header CRC-32 does not match (corrupted or misaligned message)")
    (
        _,
        _,
        _,
        _,
        payload_bytes,
        sequence,
        frame_time_s,
        sample_rate_hz,
        n_samples,
        n_channels,
        transmitter,
        sample_format,
        signal_code,
        flags,
        payload_crc,
    ) = fields
    if kind not in KINDS:
        raise ProtocolError(f"unknown message kind {kind} (1 session, 2 frame, 3 end, 4 refusal)")
    if sample_format not in SAMPLE_FORMATS and kind == KIND_FRAME:
        raise ProtocolError(
            f"unknown sample format {sample_format} (1 int16, 2 float32, 3 float64, 4 complex64)"
        )
    if signal_code not in SIGNAL_KINDS:
        raise ProtocolError(f"unknown signal kind {signal_code} (0 rf, 1 envelope, 2 iq)")
    limit = MAX_REFUSAL_BYTES if kind == KIND_REFUSAL else min(max_payload_bytes, MAX_PAYLOAD_BYTES)
    if payload_bytes > limit:
        raise ProtocolError(f"{KINDS[kind]} payload of {payload_bytes} bytes is over the limit of {limit}")
    if kind == KIND_FRAME:
        if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
            raise ProtocolError(f"frame {sequence}: sample_rate_hz is {sample_rate_hz}, expected > 0")
        expected = n_channels * n_samples * SAMPLE_FORMATS[sample_format][1].itemsize
        if payload_bytes != expected or expected == 0:
            raise ProtocolError(
                f"frame {sequence}: payload is {payload_bytes} bytes, {n_channels} channels x {n_samples} "
                f"samples of {SAMPLE_FORMATS[sample_format][0]} need {expected} (and at least one)"
            )
    return MessageHeader(
        kind=kind,
        header_bytes=header_bytes,
        payload_bytes=payload_bytes,
        sequence=sequence,
        frame_time_s=frame_time_s,
        sample_rate_hz=sample_rate_hz,
        n_channels=n_channels,
        n_samples=n_samples,
        sample_format=sample_format,
        signal_kind=SIGNAL_KINDS[signal_code],
        transmitter=transmitter,
        payload_crc32=payload_crc if flags & FLAG_PAYLOAD_CRC else None,
        announces_sequence=kind == KIND_SESSION and bool(flags & FLAG_NEXT_SEQUENCE),
    )


def _check_payload(header: MessageHeader, payload: bytes | bytearray | memoryview) -> None:
    if len(payload) != header.payload_bytes:
        raise ProtocolError(
            f"{KINDS[header.kind]} {header.sequence}: payload is {len(payload)} bytes, "
            f"the header says {header.payload_bytes}"
        )
    if header.payload_crc32 is not None and zlib.crc32(payload) != header.payload_crc32:
        raise ProtocolError(f"{KINDS[header.kind]} {header.sequence}: payload CRC-32 does not match")


# ----------------------------------------------------------------------------- frames


class FramePayload(NamedTuple):
    """A frame's samples as the wire carries them, with what its header says of them: the
    part of a frame message that a sender replaying a recording can keep from one loop to
    the next (:func:`frame_payload`, :func:`frame_message`)."""

    data: bytes
    crc32: int | None
    n_channels: int
    n_samples: int
    sample_format: int  # the code, SAMPLE_FORMAT_CODES


def frame_payload(
    samples: NDArray[Any],
    *,
    signal_kind: str = "rf",
    sample_format: str = "float32",
    payload_crc: bool = True,
) -> FramePayload:
    """``samples`` (n_channels, n_samples) in ``sample_format``, channel-major, and their CRC-32.

    ``sample_format`` ``int16`` rounds and clips to -32768..32767 (for ADC counts);
    ``complex64`` is required for ``iq`` data and refused for real data.
    """
    if sample_format not in SAMPLE_FORMAT_CODES:
        raise ProtocolError(
            f"unknown sample format {sample_format!r}, expected one of {sorted(SAMPLE_FORMAT_CODES)}"
        )
    if signal_kind not in SIGNAL_KIND_CODES:
        raise ProtocolError(f"unknown signal kind {signal_kind!r}, expected rf, envelope or iq")
    arr = np.asarray(samples)
    if arr.ndim != 2 or arr.size == 0:
        raise ProtocolError(f"samples have shape {arr.shape}, expected (n_channels, n_samples), not empty")
    if (signal_kind == "iq") != (sample_format == "complex64"):
        raise ProtocolError(f"signal kind {signal_kind} cannot be sent as {sample_format} (iq is complex64)")
    code = SAMPLE_FORMAT_CODES[sample_format]
    dtype = SAMPLE_FORMATS[code][1]
    if sample_format == "int16":
        wire = np.clip(np.rint(arr), -32768, 32767).astype(dtype)
    else:
        wire = np.ascontiguousarray(arr, dtype=dtype)
    data: bytes = wire.tobytes()
    crc = zlib.crc32(data) if payload_crc else None
    return FramePayload(data, crc, int(arr.shape[0]), int(arr.shape[1]), code)


def frame_message(
    payload: FramePayload,
    *,
    sequence: int,
    sample_rate_hz: float,
    frame_time_s: float = math.nan,
    transmitter: int = 0,
    signal_kind: str = "rf",
) -> bytes:
    """One frame message: the header, then ``payload`` (:func:`frame_payload`, made with the
    same ``signal_kind``)."""
    header = MessageHeader(
        kind=KIND_FRAME,
        header_bytes=HEADER_BYTES,
        payload_bytes=len(payload.data),
        sequence=sequence,
        frame_time_s=float(frame_time_s),
        sample_rate_hz=float(sample_rate_hz),
        n_channels=payload.n_channels,
        n_samples=payload.n_samples,
        sample_format=payload.sample_format,
        signal_kind=signal_kind,
        transmitter=int(transmitter),
        payload_crc32=payload.crc32,
    )
    return _pack(header) + payload.data


def encode_frame(
    samples: NDArray[Any],
    *,
    sequence: int,
    sample_rate_hz: float,
    frame_time_s: float = math.nan,
    transmitter: int = 0,
    signal_kind: str = "rf",
    sample_format: str = "float32",
    payload_crc: bool = True,
) -> bytes:
    """One frame message: header and ``samples`` (n_channels, n_samples), channel-major
    (:func:`frame_message` of :func:`frame_payload`).

    ``sample_format`` ``int16`` rounds and clips to -32768..32767 (for ADC counts);
    ``complex64`` is required for ``iq`` data and refused for real data.
    """
    payload = frame_payload(
        samples, signal_kind=signal_kind, sample_format=sample_format, payload_crc=payload_crc
    )
    return frame_message(
        payload,
        sequence=sequence,
        sample_rate_hz=sample_rate_hz,
        frame_time_s=frame_time_s,
        transmitter=transmitter,
        signal_kind=signal_kind,
    )


def decode_frame(header: MessageHeader, payload: bytes | bytearray | memoryview) -> WireFrame:
    """The frame of a frame message; samples as float64 (complex128 for iq), a fresh array."""
    if header.kind != KIND_FRAME:
        raise ProtocolError(f"expected a frame message, got a {KINDS[header.kind]} message")
    _check_payload(header, payload)
    dtype = SAMPLE_FORMATS[header.sample_format][1]
    if (header.signal_kind == "iq") != (dtype.kind == "c"):
        raise ProtocolError(
            f"frame {header.sequence}: signal kind {header.signal_kind} with sample format "
            f"{SAMPLE_FORMATS[header.sample_format][0]}"
        )
    raw = np.frombuffer(payload, dtype=dtype).reshape(header.n_channels, header.n_samples)
    samples: NDArray[np.floating] | NDArray[np.complexfloating] = (
        raw.astype(np.complex128) if dtype.kind == "c" else raw.astype(np.float64)
    )
    if not np.isfinite(samples).all():
        raise ProtocolError(f"frame {header.sequence}: NaN or infinite samples")
    return WireFrame(
        sequence=header.sequence,
        frame_time_s=header.frame_time_s,
        transmitter=header.transmitter,
        sample_rate_hz=header.sample_rate_hz,
        signal_kind=header.signal_kind,
        samples=samples,
    )


# ----------------------------------------------------------------------------- session


def _json_array(value: NDArray[Any]) -> Any:
    arr = np.asarray(value)
    if arr.dtype.kind == "c":
        return {"real": arr.real.tolist(), "imag": arr.imag.tolist()}
    return arr.tolist()


def session_record(header: Recording) -> dict[str, Any]:
    """The JSON object of a session message: docs/FORMATS.md's attributes and datasets by name.

    Per-frame fields (``frames``, ``frame_times``, ``frame_transmitter``, truth,
    poses) are not part of a session; a per-frame ``background`` is refused.
    """
    attrs, data = contract_items(header)
    record: dict[str, Any] = dict(attrs)
    for name in ("frames", "frame_times", "frame_transmitter", "truth_positions", "sensor_poses"):
        data.pop(name, None)
    if "background" in data and data["background"].ndim == 3:
        raise ProtocolError(
            f"{header.source}: a background per frame cannot travel in a session (send one background)"
        )
    for name, arr in data.items():
        record[name] = _json_array(arr)
    return record


def encode_session(
    header: Recording, *, sample_format: str = "float32", next_sequence: int | None = None
) -> bytes:
    """A session message for ``header`` (a recording or header; only per-recording fields travel).

    The header's n_channels, n_samples, sample rate, signal kind and sample format
    announce the frames that follow. ``next_sequence``: the sequence number of the
    next frame to be sent, announced with :data:`FLAG_NEXT_SEQUENCE` (a UDP receiver
    tells a sender that started again from one that repeats its session by it).
    """
    record = session_record(header)
    payload = json.dumps(record, separators=(",", ":"), allow_nan=False).encode()
    n_rx, n_samples = (int(d) for d in np.shape(header.frames)[1:])
    msg = MessageHeader(
        kind=KIND_SESSION,
        header_bytes=HEADER_BYTES,
        payload_bytes=len(payload),
        sequence=0 if next_sequence is None else next_sequence,
        frame_time_s=math.nan,
        sample_rate_hz=float(header.sample_rate_hz),
        n_channels=n_rx,
        n_samples=n_samples,
        sample_format=SAMPLE_FORMAT_CODES[sample_format],
        signal_kind=header.signal_kind,
        payload_crc32=zlib.crc32(payload),
        announces_sequence=next_sequence is not None,
    )
    return _pack(msg) + payload


def frame_bytes(n_channels: int, n_samples: int, signal_kind: str) -> int:
    """Bytes of one frame in memory as a receiver holds it: float64 samples, complex128 for iq."""
    return n_channels * n_samples * (16 if signal_kind == "iq" else 8)


def _from_json(value: Any) -> NDArray[Any]:
    if isinstance(value, dict):
        if set(value) != {"real", "imag"}:
            raise ProtocolError(f"an array object must have real and imag, got {sorted(value)[:4]}")
        return np.asarray(value["real"], dtype=np.float64) + 1j * np.asarray(value["imag"], dtype=np.float64)
    arr = np.asarray(value)
    if arr.dtype.kind not in "iuf":
        raise ProtocolError(f"expected an array of numbers, got {repr(value)[:40]}")
    return arr.astype(np.int64) if arr.dtype.kind in "iu" and arr.ndim == 0 else arr.astype(np.float64)


def _refuse_constant(name: str) -> Any:
    raise ProtocolError(f"{name} is not a number JSON allows")


def decode_session(
    header: MessageHeader,
    payload: bytes | bytearray | memoryview,
    source: str,
    *,
    max_frame_bytes: int = MAX_FRAME_BYTES,
    max_session_bytes: int = MAX_SESSION_BYTES,
) -> Recording:
    """The header :class:`Recording` a session message carries, validated (no frames).

    ``source`` (e.g. ``"tcp://127.0.0.1:7447"``) names it in messages. A session is
    bounded before its payload is read: its frames (``n_channels`` x ``n_samples``,
    in memory, :func:`frame_bytes`) at most ``max_frame_bytes``, its JSON at most
    ``max_session_bytes``.

    Raises
    ------
    ProtocolError
        For every session that cannot be used, whatever is wrong with it (one line that
        names ``source`` and the field): a peer's bytes make nothing else escape.
    """
    try:
        return _decode_session(header, payload, source, max_frame_bytes, max_session_bytes)
    except ProtocolError:
        raise
    except EchoLocError as error:  # the recording contract's checks: they name source and field
        raise ProtocolError(" ".join(str(error).split())) from None
    except RecursionError:
        raise ProtocolError(f"{source}: session JSON is nested too deeply") from None
    except MemoryError:
        raise ProtocolError(f"{source}: session too large to decode") from None
    except (ValueError, TypeError, ArithmeticError, LookupError) as error:
        # numpy on ragged or odd arrays, a 5000-digit integer, ...
        text = " ".join(str(error).split())[:200]
        raise ProtocolError(f"{source}: session payload is not a valid session ({text})") from None


def _decode_session(
    header: MessageHeader,
    payload: bytes | bytearray | memoryview,
    source: str,
    max_frame_bytes: int,
    max_session_bytes: int,
) -> Recording:
    if header.kind != KIND_SESSION:
        raise ProtocolError(f"expected a session message, got a {KINDS[header.kind]} message")
    size = frame_bytes(header.n_channels, header.n_samples, header.signal_kind)
    if size > max_frame_bytes:
        raise ProtocolError(
            f"{source}: session announces frames of {header.n_channels} channels x {header.n_samples} "
            f"samples, {size / 2**20:.1f} MiB each, over the limit of {max_frame_bytes / 2**20:g} MiB"
        )
    if header.n_channels == 0 or header.n_samples == 0:
        raise ProtocolError(
            f"{source}: session announces frames of {header.n_channels} channels x {header.n_samples} "
            "samples (at least 1 x 1)"
        )
    if header.payload_bytes > max_session_bytes:
        raise ProtocolError(
            f"{source}: session payload of {header.payload_bytes} bytes is over the limit of "
            f"{max_session_bytes}"
        )
    _check_payload(header, payload)
    try:
        record = json.loads(bytes(payload).decode("utf-8"), parse_constant=_refuse_constant)
    except (UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ProtocolError(f"{source}: session payload is not UTF-8 JSON ({error})") from None
    except ProtocolError as error:
        raise ProtocolError(f"{source}: session payload: {error}") from None
    if not isinstance(record, dict):
        raise ProtocolError(
            f"{source}: session payload is a JSON {type(record).__name__}, expected an object"
        )
    attrs: dict[str, object] = {}
    data: dict[str, NDArray[Any]] = {}
    array_names = {
        "transmitters",
        "receivers",
        "waveform",
        "background",
        "transmitter_axes",
        "receiver_axes",
        "receiver_gain",
        "transmitter_waveforms",
    }
    for name, value in record.items():
        if name in array_names:
            try:
                data[name] = _from_json(value)
            except ProtocolError as error:
                raise ProtocolError(f"{source}: session field {name}: {error}") from None
            except (ValueError, TypeError, OverflowError) as error:
                text = " ".join(str(error).split())[:120]
                raise ProtocolError(
                    f"{source}: session field {name} is not an array of numbers ({text})"
                ) from None
        elif isinstance(value, str | int | float):
            attrs[name] = value
        # Anything else is a field of a later contract: ignored, as docs/FORMATS.md asks.
    dtype = np.complex128 if header.signal_kind == "iq" else np.float64
    data["frames"] = np.zeros((0, header.n_channels, header.n_samples), dtype=dtype)
    rec = recording_from_items(source, attrs, data)
    if rec.signal_kind != header.signal_kind or rec.sample_rate_hz != header.sample_rate_hz:
        raise ProtocolError(
            f"{source}: session header says {header.signal_kind} at {header.sample_rate_hz:g} Hz, "
            f"its payload {rec.signal_kind} at {rec.sample_rate_hz:g} Hz"
        )
    return validate_header(rec)


def _control_message(kind: int, sequence: int, payload: bytes, payload_crc32: int | None) -> bytes:
    """A message that carries no samples (end, refusal): its header, then ``payload``.

    Such a header describes no frame: no start time (NaN), and rate, channels,
    samples and sample format all 0, signal kind ``"rf"`` (code 0).
    """
    header = MessageHeader(
        kind=kind,
        header_bytes=HEADER_BYTES,
        payload_bytes=len(payload),
        sequence=sequence,
        frame_time_s=math.nan,
        sample_rate_hz=0.0,
        n_channels=0,
        n_samples=0,
        sample_format=0,
        signal_kind="rf",
        payload_crc32=payload_crc32,
    )
    return _pack(header) + payload


def encode_end(sequence: int = 0) -> bytes:
    """The end message: the sender has sent its last frame (``sequence``: the next it would send)."""
    return _control_message(KIND_END, sequence, b"", payload_crc32=None)


def encode_refusal(reason: str) -> bytes:
    """The refusal message a TCP receiver sends its sender before it closes the connection:
    ``reason``, one line of UTF-8 (cut to :data:`MAX_REFUSAL_BYTES`)."""
    text = " ".join(reason.split()).encode("utf-8")[:MAX_REFUSAL_BYTES]
    payload = text.decode("utf-8", "ignore").encode("utf-8")  # not cut inside a character
    return _control_message(KIND_REFUSAL, 0, payload, payload_crc32=zlib.crc32(payload))


def decode_refusal(header: MessageHeader, payload: bytes | bytearray | memoryview) -> str:
    """The reason a refusal message gives (one line; undecodable bytes replaced)."""
    if header.kind != KIND_REFUSAL:
        raise ProtocolError(f"expected a refusal message, got a {KINDS[header.kind]} message")
    _check_payload(header, payload)
    return " ".join(bytes(payload).decode("utf-8", "replace").split())


# ----------------------------------------------------------------------------- byte streams


def split_messages(
    buffer: bytearray, *, max_payload_bytes: int = MAX_PAYLOAD_BYTES
) -> tuple[list[tuple[MessageHeader, bytes]], int, list[ProtocolError]]:
    """Complete messages at the front of a TCP byte ``buffer``; consumes them from it.

    Returns the messages (header and payload), the number of bytes skipped to
    resynchronise after garbage, and the errors met (one per bad header). An
    incomplete message is left in ``buffer`` for the next read: at most a header and
    ``max_payload_bytes`` (a header announcing more is refused as malformed).
    """
    messages: list[tuple[MessageHeader, bytes]] = []
    errors: list[ProtocolError] = []
    with memoryview(buffer) as view:  # released before the consumed bytes are deleted
        pos, skipped = _split_into(buffer, view, messages, errors, max_payload_bytes)
    del buffer[:pos]
    return messages, skipped, errors


def _split_into(
    buffer: bytearray,
    view: memoryview,
    messages: list[tuple[MessageHeader, bytes]],
    errors: list[ProtocolError],
    max_payload_bytes: int,
) -> tuple[int, int]:
    """:func:`split_messages`' scan: messages and errors appended, (bytes consumed, bytes
    skipped). Headers and payloads are copied once, out of ``view`` (slicing the bytearray
    and then making bytes of it copied every frame's samples twice)."""
    skipped = 0
    pos = 0
    while True:
        found = buffer.find(MAGIC, pos)
        if found < 0:
            # Keep a tail that might be the start of a magic.
            keep = max(pos, len(buffer) - (len(MAGIC) - 1))
            skipped += keep - pos
            pos = keep
            break
        if found > pos:
            skipped += found - pos
            pos = found
        if len(buffer) - pos < HEADER_BYTES:
            break
        try:
            header_bytes = max(HEADER_BYTES, _peek_header_bytes(buffer, pos))
            header = decode_header(bytes(view[pos : pos + header_bytes]), max_payload_bytes=max_payload_bytes)
        except ProtocolError as error:
            if "header_bytes" in str(error) and _peek_header_bytes(buffer, pos) > len(buffer) - pos:
                break  # a longer header of a later version still arriving
            errors.append(error)
            pos += 1
            skipped += 1
            continue
        end = pos + header.header_bytes + header.payload_bytes
        if end > len(buffer):
            break
        messages.append((header, bytes(view[pos + header.header_bytes : end])))
        pos = end
    return pos, skipped


def _peek_header_bytes(buffer: bytes | bytearray, pos: int) -> int:
    if len(buffer) - pos < 8:
        return HEADER_BYTES
    return int(struct.unpack_from("<H", buffer, pos + 6)[0])
