"""The serial framing and its capture source: byte-exact round trips, resynchronisation after
anything a serial line does, and frames through loop:// and a pty that give what the batch
chain gives on the same samples."""

from __future__ import annotations

import dataclasses
import itertools
import json
import os
import subprocess
import sys
import threading
import time
import zlib
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from echoloc.errors import EchoLocError
from echoloc.io.head import SAMPLE_FORMATS, SensorHead, load_head
from echoloc.io.output import objects_record
from echoloc.io.recording import Recording
from echoloc.pipeline import prepare, run
from echoloc.realtime.serial_source import (
    FLAG_INTERLEAVED,
    FLAG_TIME32,
    FORMAT_CODES,
    HEADER,
    HEADER_BYTES,
    CaptureClock,
    SerialDecoder,
    SerialFrame,
    SerialLayout,
    SerialProblem,
    SerialSource,
    decode_serial_header,
    encode_serial_frame,
)
from echoloc.realtime.session import LiveSession, listener_events
from echoloc.realtime.stream import FrameQueue, StreamFrame, StreamResult
from echoloc.realtime.transport import EndEvent, SessionEvent
from echoloc.sim.simulation import simulate
from repo_paths import REPO

HEAD_PATH = REPO / "examples" / "heads" / "mcu-4ch.toml"
N_FRAMES = 6
REFLECTORS = [
    {"position_m": [0.10, 0.05, 0.80], "strength": 0.4},
    {"position_m": [-0.20, 0.10, 1.30], "strength": 0.5},
]


@pytest.fixture(scope="module")
def head() -> SensorHead:
    return load_head(HEAD_PATH)


@pytest.fixture(scope="module")
def played(head: SensorHead) -> tuple[list[np.ndarray], list[int], Recording]:
    """A simulated head played as its board would: the ADC counts of each frame, its capture
    timestamp (us, a board up for a while, not a whole number of ms), and the recording of the
    same samples as the chain reads them (counts -> samples) with those times, for the batch
    chain."""
    recording = simulate(
        head.scene({"seed": 7, "noise": {"snr_db": 20.0}, "reflectors": REFLECTORS}), N_FRAMES
    )
    counts = [head.counts(frame) for frame in recording.frames]
    stamps = [123_456_789 + 10_000 * k + 3 * k * k for k in range(N_FRAMES)]
    samples = np.stack([head.samples(c) for c in counts])
    as_read = dataclasses.replace(recording, frames=samples, frame_times_s=np.array(stamps) / 1e6)
    return counts, stamps, as_read


def _frames(items: list[SerialFrame | SerialProblem]) -> list[SerialFrame]:
    return [item for item in items if isinstance(item, SerialFrame)]


def _problems(items: list[SerialFrame | SerialProblem]) -> list[SerialProblem]:
    return [item for item in items if isinstance(item, SerialProblem)]


def _counts(rng: np.random.Generator, shape: tuple[int, int], name: str = "int16") -> np.ndarray:
    dtype = np.dtype(SAMPLE_FORMATS[name])
    if dtype.kind == "f":  # any bit pattern: NaNs of every payload, infinities, -0.0
        return rng.integers(0, 2**32, size=shape, dtype=np.uint32).view(dtype)
    info = np.iinfo(dtype)
    return rng.integers(info.min, info.max, size=shape, endpoint=True).astype(dtype)


# ----------------------------------------------------------------------------- the framing


def test_the_header_is_what_the_protocol_page_says() -> None:
    """Offsets and sizes as docs/SERIAL_PROTOCOL.md lays them out, and both CRC-32s zlib's."""
    counts = np.array([[1, 2, 3], [-1, -2, -3]], dtype="<i2")
    data = encode_serial_frame(counts, sequence=7, timestamp_us=10_000, transmitter=2)
    assert HEADER_BYTES == 28
    assert len(data) == 28 + 12 + 4
    assert data[:4] == b"ECHS"
    assert data[4:12] == bytes([1, FORMAT_CODES["int16"], 2, 0, 3, 0, 2, 0])
    assert int.from_bytes(data[12:16], "little") == 7
    assert int.from_bytes(data[16:24], "little") == 10_000
    assert int.from_bytes(data[24:28], "little") == zlib.crc32(data[:24])
    assert data[28:40] == counts.tobytes()
    assert int.from_bytes(data[40:44], "little") == zlib.crc32(data[28:40])


@settings(max_examples=150, deadline=None)
@given(
    n_channels=st.integers(1, 9),
    n_values=st.integers(1, 70),
    name=st.sampled_from(sorted(FORMAT_CODES)),
    sequence=st.integers(0, 2**32 - 1),
    timestamp_us=st.integers(0, 2**64 - 1),
    transmitter=st.integers(0, 255),
    time32=st.booleans(),
    interleaved=st.booleans(),
    seed=st.integers(0, 2**32 - 1),
    cuts=st.lists(st.integers(0, 2000), max_size=6),
)
def test_a_frame_decodes_to_what_was_encoded_byte_for_byte(
    n_channels: int,
    n_values: int,
    name: str,
    sequence: int,
    timestamp_us: int,
    transmitter: int,
    time32: bool,
    interleaved: bool,
    seed: int,
    cuts: list[int],
) -> None:
    """Any layout, format, sequence number and timestamp, the bytes fed in pieces of any size:
    the same counts bit for bit, the same header fields, and encoded again the same bytes."""
    counts = _counts(np.random.default_rng(seed), (n_channels, n_values), name)
    data = encode_serial_frame(
        counts,
        sequence=sequence,
        timestamp_us=timestamp_us,
        transmitter=transmitter,
        time32=time32,
        interleaved=interleaved,
    )
    decoder = SerialDecoder()
    items: list[SerialFrame | SerialProblem] = []
    edges = sorted({0, len(data), *(c % (len(data) + 1) for c in cuts)})
    for a, b in itertools.pairwise(edges):
        items += decoder.feed(data[a:b])
    (frame,) = items
    assert isinstance(frame, SerialFrame)
    assert frame.counts.dtype == np.dtype(SAMPLE_FORMATS[name])
    assert frame.counts.shape == counts.shape
    assert frame.counts.tobytes() == counts.tobytes()  # bit for bit, NaN payloads and -0.0 too
    assert (frame.sequence, frame.transmitter) == (sequence, transmitter)
    assert frame.timestamp_us == (timestamp_us & 0xFFFFFFFF if time32 else timestamp_us)
    assert frame.flags == (FLAG_TIME32 if time32 else 0) | (FLAG_INTERLEAVED if interleaved else 0)
    again = encode_serial_frame(
        frame.counts,
        sequence=frame.sequence,
        timestamp_us=frame.timestamp_us,
        transmitter=frame.transmitter,
        time32=time32,
        interleaved=interleaved,
    )
    assert again == data
    assert decoder.bytes_skipped == decoder.malformed == 0
    assert decoder.wanted() == HEADER_BYTES


def test_an_interleaved_payload_is_sample_after_sample() -> None:
    """FLAG_INTERLEAVED: what a scanning ADC's DMA writes (ch0, ch1, ch0, ch1, ...), read back
    as channel after channel."""
    counts = np.array([[1, 2, 3], [10, 20, 30]], dtype="<u2")
    data = encode_serial_frame(counts, sequence=0, timestamp_us=0, interleaved=True)
    assert np.frombuffer(data[28:40], "<u2").tolist() == [1, 10, 2, 20, 3, 30]
    (frame,) = SerialDecoder().feed(data)
    assert isinstance(frame, SerialFrame)
    np.testing.assert_array_equal(frame.counts, counts)


def test_the_encoder_refuses_what_the_framing_cannot_carry() -> None:
    with pytest.raises(EchoLocError, match="float64"):
        encode_serial_frame(np.zeros((2, 3)), sequence=0, timestamp_us=0)
    with pytest.raises(EchoLocError, match="65535"):
        encode_serial_frame(np.zeros((1, 70_000), "<i2"), sequence=0, timestamp_us=0)
    with pytest.raises(EchoLocError, match="transmitter 256"):
        encode_serial_frame(np.zeros((1, 3), "<i2"), sequence=0, timestamp_us=0, transmitter=256)
    with pytest.raises(EchoLocError, match="timestamp_us"):
        encode_serial_frame(np.zeros((1, 3), "<i2"), sequence=0, timestamp_us=-1)


def _header(**fields: Any) -> bytes:
    values = {
        "sync": b"ECHS",
        "version": 1,
        "code": 1,
        "n_channels": 2,
        "n_values": 3,
        "transmitter": 0,
        "flags": 0,
        "sequence": 0,
        "timestamp": 0,
    }
    body = HEADER.pack(*{**values, **fields}.values())
    return body + zlib.crc32(body).to_bytes(4, "little")


@pytest.mark.parametrize(
    ("fields", "match"),
    [
        ({"version": 2}, "version 2; this reader reads version 1"),
        ({"code": 3}, "unknown sample format code 3"),
        ({"n_channels": 0}, "no samples"),
        ({"n_values": 0}, "no samples"),
    ],
)
def test_a_header_that_checks_but_cannot_be_read_is_refused_in_one_line(
    fields: dict[str, int], match: str
) -> None:
    with pytest.raises(EchoLocError, match=match):
        decode_serial_header(_header(**fields))
    header = bytearray(_header())
    header[9] ^= 0x40
    with pytest.raises(EchoLocError, match="CRC-32 does not match"):
        decode_serial_header(header)


# ----------------------------------------------------------------------------- resynchronising


def _stream(n: int, shape: tuple[int, int] = (3, 40), first: int = 0) -> tuple[list[bytes], list[np.ndarray]]:
    rng = np.random.default_rng(n)
    counts = [_counts(rng, shape) for _ in range(n)]
    return [
        encode_serial_frame(c, sequence=first + k, timestamp_us=1000 * k) for k, c in enumerate(counts)
    ], counts


def _feed(decoder: SerialDecoder, data: bytes, piece: int) -> list[SerialFrame | SerialProblem]:
    items: list[SerialFrame | SerialProblem] = []
    for start in range(0, len(data), piece):
        items += decoder.feed(data[start : start + piece])
    return items


@pytest.mark.parametrize("piece", [1, 7, 10_000])
def test_garbage_before_the_first_frame_is_skipped_quietly_between_frames_counted_once(piece: int) -> None:
    """A port opened mid-frame starts with the end of one: skipped, no problem. Bytes between
    two frames (with a false sync word among them) are one malformed problem, whatever their
    length; every frame is read."""
    frames, counts = _stream(3)
    opened_mid_frame = frames[2][100:]
    noise = b"\x00\xffECHS" + bytes(range(200)) + b"ECH"
    decoder = SerialDecoder()
    items = _feed(decoder, opened_mid_frame + frames[0] + noise + frames[1] + frames[2], piece)
    got = _frames(items)
    assert [f.sequence for f in got] == [0, 1, 2]
    assert all(np.array_equal(f.counts, c) for f, c in zip(got, counts, strict=True))
    (problem,) = _problems(items)
    assert problem.counter == "malformed"
    assert f"{len(noise)} bytes between frames" in problem.message
    assert decoder.malformed == 1
    assert decoder.bytes_skipped == len(opened_mid_frame) + len(noise)


@pytest.mark.parametrize("where", ["payload", "header", "payload CRC"])
def test_a_flipped_byte_costs_its_frame_only(where: str) -> None:
    frames, counts = _stream(4)
    offset = {"payload": 28 + 50, "header": 13, "payload CRC": len(frames[1]) - 2}[where]
    broken = bytearray(frames[1])
    broken[offset] ^= 0x10
    decoder = SerialDecoder()
    items = _feed(decoder, frames[0] + bytes(broken) + frames[2] + frames[3], 64)
    got = _frames(items)
    assert [f.sequence for f in got] == [0, 2, 3]
    assert all(np.array_equal(f.counts, counts[f.sequence]) for f in got)
    (problem,) = _problems(items)
    assert problem.counter == "malformed"
    assert decoder.malformed == 1
    if where == "header":  # no frame starts there: its bytes are a run of bytes that are no frame's
        assert f"{len(frames[1])} bytes between frames" in problem.message
    else:
        assert "frame 1: the samples' CRC-32 does not match" in problem.message


@pytest.mark.parametrize("lost_at", [5, 28 + 40, 200])
def test_a_byte_lost_on_the_line_costs_its_frame_and_the_next_comes_at_once(lost_at: int) -> None:
    """A UART drops a byte: the frame is one byte short. The next frame is read as soon as it is
    complete (its header found inside the short one), not when enough bytes have come to fill
    the short frame."""
    frames, _ = _stream(3)
    short = frames[1][:lost_at] + frames[1][lost_at + 1 :]
    decoder = SerialDecoder()
    items = _feed(decoder, frames[0] + short + frames[2], 16)
    assert [f.sequence for f in _frames(items)] == [0, 2]
    assert decoder.malformed == 1
    assert len(_problems(items)) == 1


def test_a_frame_cut_short_by_a_restarted_board_is_one_problem() -> None:
    """A board reset mid-frame starts again at a header: the half frame is dropped as one
    problem, and the frames after it are all read, each at once."""
    frames, _ = _stream(3)
    restarted, _ = _stream(2, first=0)
    decoder = SerialDecoder()
    items = decoder.feed(frames[0] + frames[1][: len(frames[1]) // 2])
    assert [f.sequence for f in _frames(items)] == [0]
    items = decoder.feed(restarted[0])
    (problem, frame) = items
    assert isinstance(problem, SerialProblem)
    assert "cut short" in problem.message
    assert isinstance(frame, SerialFrame)
    assert frame.sequence == 0
    assert [f.sequence for f in _frames(decoder.feed(restarted[1]))] == [1]
    assert decoder.malformed == 1
    assert decoder.frames == 3


def test_a_frame_of_another_layout_is_rejected_at_its_header_and_its_bytes_skipped() -> None:
    """A board programmed for another head: one rejected problem a frame, naming both layouts,
    its samples never waited for nor counted malformed; the frames that fit are read."""
    frames, _ = _stream(3, shape=(3, 40))
    other = encode_serial_frame(np.zeros((4, 40), "<i2"), sequence=9, timestamp_us=0)
    decoder = SerialDecoder(SerialLayout(3, 40, "int16"), expecting="the head 'h'")
    items = _feed(decoder, frames[0] + other[:40], 7)
    (problem,) = _problems(items)
    assert problem.counter == "rejected"
    assert problem.sequence == 9
    assert (
        "4 channels x 40 int16 values, where the head 'h' has 3 channels x 40 int16 values" in problem.message
    )
    items = _feed(decoder, other[40:] + frames[1] + frames[2], 7)
    assert [f.sequence for f in _frames(items)] == [1, 2]
    assert not _problems(items)
    assert (decoder.rejected, decoder.malformed) == (1, 0)


def test_a_decoder_without_a_head_waits_for_no_giant_payload() -> None:
    header = _header(n_channels=65535, n_values=65535, code=6)
    decoder = SerialDecoder(max_payload_bytes=1 << 20)
    frames, _ = _stream(2)
    items = decoder.feed(frames[0] + header + frames[1])
    assert [f.sequence for f in _frames(items)] == [0, 1]
    (problem,) = _problems(items)
    assert "more than the 1048576 taken" in problem.message


def test_a_32_bit_clock_is_unwrapped_and_a_64_bit_one_taken_as_it_is() -> None:
    clock = CaptureClock()
    stamps = [2**32 - 20_000, 2**32 - 10_000, 5_000, 15_000, 10_000]  # wraps, then one late
    assert [clock.time_s(t, FLAG_TIME32) for t in stamps] == [
        (2**32 - 20_000) / 1e6,
        (2**32 - 10_000) / 1e6,
        (2**32 + 5_000) / 1e6,
        (2**32 + 15_000) / 1e6,
        (2**32 + 10_000) / 1e6,
    ]
    assert CaptureClock().time_s(2**40 + 1, 0) == (2**40 + 1) / 1e6


# ----------------------------------------------------------------------------- the source


def _collect(source: Any, n_frames: int, timeout_s: float = 20.0) -> list[Any]:
    """What the source queued: its session, then frames until ``n_frames`` came (or an end)."""
    items: list[Any] = []
    deadline = time.monotonic() + timeout_s
    while sum(isinstance(i, StreamFrame) for i in items) < n_frames and time.monotonic() < deadline:
        item = source.queue.get(0.1)
        if item is not None:
            items.append(item)
        if isinstance(item, EndEvent):
            break
    return items


def _through_the_chain(source: Any, n_frames: int) -> tuple[list[StreamFrame], list[StreamResult]]:
    """The source's session and frames through `echoloc stream`'s LiveSession, the chain
    prepared as the session arrives (accept_session), as `stream` prepares it."""
    got: list[tuple[StreamFrame, StreamResult]] = []
    session = LiveSession(source, prepare, 10.0, on_result=lambda f, r: got.append((f, r)))
    for item in listener_events(source, max_frames=n_frames, deadline_s=time.monotonic() + 30):
        session.handle(item)
    return [f for f, _ in got], [r for _, r in got]


def _play(write: Any, counts: list[np.ndarray], stamps: list[int], skip: int) -> bytes:
    """The frames as the board sends them, sequence number ``skip`` never sent (lost)."""
    data = b"".join(
        encode_serial_frame(c, sequence=k, timestamp_us=t)
        for k, (c, t) in enumerate(zip(counts, stamps, strict=True))
        if k != skip
    )
    thread = threading.Thread(target=write, args=(data,), daemon=True)
    thread.start()
    return data


def _assert_as_the_batch_chain(
    frames: list[StreamFrame], results: list[StreamResult], stamps: list[int], as_read: Recording, skip: int
) -> None:
    sent = [k for k in range(N_FRAMES) if k != skip]
    assert [f.index for f in frames] == sent
    assert [f.time_s for f in frames] == [stamps[k] / 1e6 for k in sent]  # the board's clock, exactly
    batch = [objects_record(objects) for _, objects in run(prepare(as_read))]
    streamed = [objects_record(r.objects) for r in results]
    assert streamed == [batch[k] for k in sent]  # every field, positions to the last bit
    assert all(len(line["objects"]) == 2 for line in streamed)


def test_a_head_played_through_loop_gives_the_batch_chain_s_objects(head: SensorHead, played: Any) -> None:
    counts, stamps, as_read = played
    source = SerialSource(head, FrameQueue(64), "loop://", accept_session=prepare)
    try:
        source.start()
        _play(source.port.write, counts, stamps, skip=3)
        frames, results = _through_the_chain(source, N_FRAMES - 1)
        counters = source.counters()
    finally:
        source.stop()
    _assert_as_the_batch_chain(frames, results, stamps, as_read, skip=3)
    assert counters["received"] == N_FRAMES - 1
    assert counters["lost"] == 1
    assert counters["malformed"] == counters["rejected"] == 0


class Pty:
    """A pseudo-terminal: ``path`` is its slave, the port; the test writes to ``master``."""

    def __init__(self) -> None:
        self.master, slave = os.openpty()
        self.path = os.ttyname(slave)
        os.close(slave)
        self.open = True

    def write(self, data: bytes) -> None:
        view = memoryview(data)
        while view:
            view = view[os.write(self.master, view) :]

    def close(self) -> None:
        """Hang the port up, as a board unplugged (once: the number may be reused after)."""
        if self.open:
            self.open = False
            os.close(self.master)


@pytest.fixture
def pty() -> Iterator[Pty]:
    line = Pty()
    yield line
    line.close()


def test_a_head_played_through_a_pty_gives_the_batch_chain_s_objects_then_the_unplug_ends_it(
    head: SensorHead, played: Any, pty: Pty
) -> None:
    """A pseudo-terminal, as a USB-CDC port: the frames (one never sent) reach the chain as
    they left the board; the board then goes away (the master closed): a warning line, an end,
    no exception."""
    path = pty.path
    counts, stamps, as_read = played
    source = SerialSource(head, FrameQueue(64), path, accept_session=prepare)
    try:
        source.start()
        _play(pty.write, counts, stamps, skip=1)
        frames, results = _through_the_chain(source, N_FRAMES - 1)
        counters = source.counters()
        pty.close()
        end = source.queue.get(5.0)
        deadline = time.monotonic() + 2.0
        while source.serving and time.monotonic() < deadline:  # the thread ends after the end event
            time.sleep(0.01)
        assert not source.serving
    finally:
        source.stop()
    _assert_as_the_batch_chain(frames, results, stamps, as_read, skip=1)
    assert counters["received"] == N_FRAMES - 1
    assert counters["lost"] == 1
    assert counters["malformed"] == 0
    assert end == EndEvent(disconnected=True, final=True)  # nothing can follow: the stream ends
    (line,) = source.errors()
    assert line == f"serial:{path}: the port went away (disconnected): capture stopped"


def test_a_pty_line_with_damage_counts_it_and_reads_on(head: SensorHead, pty: Pty) -> None:
    """Garbage, a flipped byte, a frame of another head and one with no such transmitter on a
    live port: counted (malformed, rejected; never also lost), one warning line each, and the
    frames around them delivered."""
    path = pty.path
    rng = np.random.default_rng(5)
    counts = [_counts(rng, (head.n_channels, head.values_per_channel), head.adc.format) for _ in range(6)]
    frames = [encode_serial_frame(c, sequence=k, timestamp_us=k) for k, c in enumerate(counts)]
    flipped = bytearray(frames[2])
    flipped[1000] ^= 1
    other_head = encode_serial_frame(np.zeros((2, 2400), "<u2"), sequence=3, timestamp_us=3)
    no_transmitter = encode_serial_frame(counts[4], sequence=4, timestamp_us=4, transmitter=1)
    data = frames[0] + b"noise" * 9 + frames[1] + bytes(flipped) + other_head + no_transmitter + frames[5]
    source = SerialSource(head, FrameQueue(64), path, warn_interval_s=0.0)
    try:
        source.start()
        threading.Thread(target=pty.write, args=(data,), daemon=True).start()
        items = _collect(source, 3)
        counters = source.counters()
    finally:
        source.stop()
    assert isinstance(items[0], SessionEvent)
    assert items[0].header is head.header
    got = [i for i in items if isinstance(i, StreamFrame)]
    assert [f.index for f in got] == [0, 1, 5]
    assert all(
        np.array_equal(f.samples, head.samples(counts[k])) for f, k in zip(got, [0, 1, 5], strict=True)
    )
    assert counters == {
        "received": 3,
        "lost": 1,  # frame 2, whose bytes came broken
        "dropped": 0,
        "out_of_order": 0,
        "malformed": 2,  # the noise, the flipped byte
        "rejected": 2,  # the other head's frame, the transmitter
        "refused": 0,
        "restarts": 0,
    }
    lines = list(source.errors())
    assert len(lines) == 4
    assert all(line.startswith(f"serial:{path}: ") for line in lines)
    assert "45 bytes between frames" in lines[0]
    assert "frame 2: the samples' CRC-32 does not match" in lines[1]
    assert (
        "frame 3 refused: 2 channels x 2400 uint16 values, where the head 'mcu-4ch' has 4 channels"
        in lines[2]
    )
    assert "frame 4: no transmitter 1" in lines[3]


def test_a_port_that_cannot_be_opened_is_one_line_naming_it(head: SensorHead, tmp_path: Any) -> None:
    missing = tmp_path / "ttyACM9"
    with pytest.raises(EchoLocError) as info:
        SerialSource(head, FrameQueue(4), str(missing)).start()
    message = str(info.value)
    assert message.startswith(f"cannot open serial port {missing}: No such file or directory")
    assert "\n" not in message
    assert message.count(str(missing)) == 1
    with pytest.raises(EchoLocError, match="cannot open serial port nope://x: invalid URL"):
        SerialSource(head, FrameQueue(4), "nope://x").start()


def test_a_second_reader_of_a_port_is_refused_not_left_to_take_half_the_bytes(
    head: SensorHead, pty: Pty
) -> None:
    first = SerialSource(head, FrameQueue(4), pty.path).start()
    try:
        with pytest.raises(EchoLocError, match=f"cannot open serial port {pty.path}: .*another echoloc"):
            SerialSource(head, FrameQueue(4), pty.path).start()
    finally:
        first.stop()


def test_without_pyserial_the_source_names_the_serial_extra(
    head: SensorHead, monkeypatch: pytest.MonkeyPatch
) -> None:
    for name in [m for m in sys.modules if m == "serial" or m.startswith("serial.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "serial", None)
    with pytest.raises(EchoLocError, match=r"capture from a serial port needs pyserial.*'echoloc\[serial\]'"):
        SerialSource(head, FrameQueue(4), "loop://")


def test_the_example_sender_is_read_as_it_sends(head: SensorHead) -> None:
    """examples/serial_sender.py --pty, written from the protocol page with struct and zlib: its
    frames (a 32-bit clock, every 4th capture skipped) read by the source, all of them, the gaps
    counted lost, the clock at the head's frame rate."""
    command = [
        sys.executable,
        str(REPO / "examples" / "serial_sender.py"),
        "--head",
        str(HEAD_PATH),
        "--pty",
        "--frames",
        "9",
        "--drop-every",
        "4",
        "--time32",
        "--sim-frames",
        "3",
    ]
    with subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True) as sender:
        try:
            assert sender.stdout is not None
            path = sender.stdout.readline().strip()
            source = SerialSource(head, FrameQueue(64), path).start()
            try:
                items = _collect(source, 9)
                summary = json.loads(sender.stdout.readline())
                counters = source.counters()
            finally:
                source.stop()
        finally:
            sender.kill()
    got = [i for i in items if isinstance(i, StreamFrame)]
    indices = [f.index for f in got]
    # Sequence numbers 3 and 7 never sent; on a busy machine the sender may skip more (a frame
    # it is a whole period late for, as a board overruns): those are counted lost too.
    assert summary["sent"] == counters["received"] == len(got) == 9
    assert 3 not in indices
    assert 7 not in indices
    assert counters["lost"] == summary["skipped"] == summary["next_sequence"] - 9 >= 2
    assert counters["malformed"] == 0
    # The board's 32-bit clock, unwrapped: 10 ms a capture.
    np.testing.assert_allclose(np.diff([f.time_s for f in got]), 0.01 * np.diff(indices), atol=1e-6)
