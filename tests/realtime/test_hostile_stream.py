"""Listeners under hostile input: a bad session is refused and the next one served, idle
connections block no one, sizes are bounded, restarts are seen, and complaints stay few."""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import re
import socket
import threading
import time
import warnings
import zlib
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from echoloc.errors import EchoLocError, RecordingError
from echoloc.io.recording import write_recording
from echoloc.realtime.protocol import (
    HEADER,
    HEADER_BYTES,
    HEADER_CRC,
    KIND_REFUSAL,
    KIND_SESSION,
    MAGIC,
    MAX_REFUSAL_BYTES,
    MAX_SESSION_BYTES,
    ProtocolError,
    decode_header,
    decode_refusal,
    decode_session,
    encode_end,
    encode_frame,
    encode_refusal,
    encode_session,
    session_record,
    split_messages,
)
from echoloc.realtime.stream import FrameQueue, SequenceTracker, StreamFrame, rare_counts
from echoloc.realtime.transport import (
    MAX_REFUSING_THREADS,
    EndEvent,
    Endpoint,
    ExposedListenerWarning,
    Listener,
    SessionEvent,
    _Replies,
    send_recording,
)
from echoloc.sim.scene import default_scene
from echoloc.sim.simulation import simulate

N_FRAMES = 3


@pytest.fixture(scope="module")
def recording():
    return simulate(default_scene(), N_FRAMES)


@pytest.fixture(scope="module")
def good(recording) -> dict[str, Any]:
    return session_record(recording)


def session_message(
    payload: bytes,
    *,
    n_channels: int = 4,
    n_samples: int = 2400,
    sample_rate_hz: float = 200e3,
    sequence: int = 0,
    flags: int = 1,
) -> bytes:
    """A session message with any payload, its header laid out as docs/STREAM_PROTOCOL.md says."""
    body = HEADER.pack(
        MAGIC,
        1,
        KIND_SESSION,
        HEADER_BYTES,
        len(payload),
        sequence,
        math.nan,
        sample_rate_hz,
        n_samples,
        n_channels,
        0,
        2,
        0,
        flags,
        zlib.crc32(payload),
    )
    return body + HEADER_CRC.pack(zlib.crc32(body)) + payload


def changed(record: dict[str, Any], **fields: Any) -> bytes:
    """``record`` with fields replaced (None: removed), as JSON (NaN written as the bare token)."""
    out = dict(record)
    for name, value in fields.items():
        if value is None:
            out.pop(name)
        else:
            out[name] = value
    return json.dumps(out).encode()


def variants(good: dict[str, Any], udp: bool) -> dict[str, tuple[bytes, str]]:
    """The 12 malformed sessions of issue 31, each with a word its refusal must contain."""
    depth = 30_000 if udp else 100_000  # one UDP datagram holds at most 65 507 bytes
    return {
        "missing field": (session_message(changed(good, receivers=None)), "receivers"),
        "ragged receivers": (
            session_message(changed(good, receivers=[[0, 0, 0], [1, 2], [0, 1, 0], [1, 1, 1]])),
            "receivers",
        ),
        "string rate": (session_message(changed(good, sample_rate_hz="fast")), "sample_rate_hz"),
        "negative rate": (session_message(changed(good, sample_rate_hz=-2e5)), "Hz"),
        "empty waveform": (session_message(changed(good, waveform=[])), "waveform"),
        "channel mismatch": (session_message(changed(good), n_channels=3), "channels"),
        "version 2": (session_message(changed(good, version=2)), "version"),
        "NaN receivers": (session_message(changed(good, receivers=[[math.nan] * 3] * 4)), "NaN"),
        "deep nesting": (session_message(b"[" * depth + b"]" * depth), "nested"),
        "2^31 samples": (session_message(changed(good), n_samples=2**31), "limit"),
        "unknown signal kind": (session_message(changed(good, signal_kind="sonar")), "sonar"),
        "not an object": (session_message(b"[1, 2, 3]"), "object"),
    }


VARIANT_NAMES = [
    "missing field",
    "ragged receivers",
    "string rate",
    "negative rate",
    "empty waveform",
    "channel mismatch",
    "version 2",
    "NaN receivers",
    "deep nesting",
    "2^31 samples",
    "unknown signal kind",
    "not an object",
]


def frames_of(listener: Listener, n_frames: int, timeout_s: float = 10.0) -> list[StreamFrame]:
    """The frames that reach the listener's queue, until ``n_frames`` or ``timeout_s``."""
    frames: list[StreamFrame] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline and len(frames) < n_frames:
        item = listener.queue.get(0.05)
        if isinstance(item, StreamFrame):
            frames.append(item)
    return frames


def wait_until(condition: Callable[[], bool], timeout_s: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if condition():
            return True
        time.sleep(0.01)
    return condition()


def refusal_of(client: socket.socket, timeout_s: float = 5.0) -> str | None:
    """Read a TCP connection to its end: the reason of the refusal that came, if one did."""
    client.settimeout(timeout_s)
    inbox = bytearray()
    with contextlib.suppress(OSError):
        while chunk := client.recv(4096):
            inbox += chunk
    messages, _, _ = split_messages(inbox)
    reasons = [decode_refusal(h, p) for h, p in messages if h.kind == KIND_REFUSAL]
    return reasons[0] if reasons else None


def send_raw(port: int, transport: str, message: bytes) -> str | None:
    """``message`` on a connection (datagram) of its own; on TCP the refusal that came back."""
    if transport == "udp":
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as out:
            out.sendto(message, ("127.0.0.1", port))
        return None
    with socket.create_connection(("127.0.0.1", port), timeout=5) as client:
        client.sendall(message)
        return refusal_of(client)


# ----------------------------------------------------------------------------- the 12 sessions


@pytest.mark.parametrize("transport", ["tcp", "udp"])
@pytest.mark.parametrize("variant", VARIANT_NAMES)
def test_a_malformed_session_is_refused_and_the_next_sender_is_served(recording, good, transport, variant):
    """Issue 31, finding 1: the listener died on 10 of these 12; every later sender was told
    "sent 5 frames" and nothing was processed."""
    message, word = variants(good, transport == "udp")[variant]
    with Listener(Endpoint("127.0.0.1", 0, transport), FrameQueue(64)) as listener:
        reason = send_raw(listener.address.port, transport, message)
        if transport == "tcp":  # the sender is told, in one line naming what is wrong
            assert reason is not None
            assert reason.startswith("session refused: ")
            assert word in reason
        assert wait_until(lambda: listener.refused == 1)
        assert listener.serving
        # A valid session and its frames, on a new connection: every frame reaches the queue.
        report = send_recording(recording, listener.address, speed=0, sample_format="float32")
        frames = frames_of(listener, N_FRAMES)
        counters = listener.counters()
        lines = list(listener.errors())
    assert len(frames) == N_FRAMES
    np.testing.assert_array_equal(frames[-1].samples, recording.frames[-1].astype(np.float32).astype(float))
    assert counters["received"] == N_FRAMES
    assert counters["refused"] == 1
    assert report.confirmed is (True if transport == "tcp" else None)
    refusal = [line for line in lines if "refused" in line]
    assert len(refusal) == 1
    assert word in refusal[0]
    assert "\n" not in refusal[0]


def test_every_one_of_the_12_in_a_row_leaves_one_listener_serving(recording, good):
    """The same, one listener taking all twelve in turn, each followed by a valid sender."""
    with Listener(Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(64)) as listener:
        for k, (message, _) in enumerate(variants(good, udp=False).values()):
            assert send_raw(listener.address.port, "tcp", message) is not None
            send_recording(recording, listener.address, speed=0)
            assert len(frames_of(listener, N_FRAMES)) == N_FRAMES, f"after variant {k}"
        counters = listener.counters()
    assert (counters["refused"], counters["received"]) == (12, 12 * N_FRAMES)


# ----------------------------------------------------------------------------- any exception


@pytest.mark.parametrize(
    "error",
    [
        RecordingError("head.h5: receivers broken"),
        ValueError("odd array"),
        RecursionError("deep"),
        OverflowError("huge"),
        MemoryError(),
        ZeroDivisionError("5e-324 Hz"),
        KeyError("missing"),
    ],
    ids=lambda e: type(e).__name__,
)
def test_whatever_a_session_makes_the_listener_raise_refuses_only_that_session(recording, error):
    """A peer must never end the listener's thread, whatever its session provokes."""
    calls: list[int] = []

    def accept(header):
        calls.append(1)
        if len(calls) == 1:
            raise error
        return "prepared"

    with Listener(Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(64), accept_session=accept) as listener:
        with pytest.raises(EchoLocError, match="the receiver refused: session refused"):
            send_recording(recording, listener.address, speed=0)
        send_recording(recording, listener.address, speed=0)
        session = listener.queue.get(5.0)
        frames = frames_of(listener, N_FRAMES)
        assert listener.serving
    assert isinstance(session, SessionEvent)
    assert session.prepared == "prepared"
    assert len(frames) == N_FRAMES
    assert listener.refused == 1


def test_a_frame_that_makes_the_decoder_raise_is_counted_and_the_next_is_taken(recording, monkeypatch):
    import echoloc.realtime.transport as transport

    real = transport.decode_frame
    raised = []

    def flaky(header, payload):
        if not raised:
            raised.append(1)
            raise ValueError("a bug a peer found")
        return real(header, payload)

    monkeypatch.setattr(transport, "decode_frame", flaky)
    with Listener(Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(64)) as listener:
        send_recording(recording, listener.address, speed=0)
        frames = frames_of(listener, N_FRAMES - 1)
        assert wait_until(lambda: listener.malformed == 1)
        lines = list(listener.errors())
        assert listener.serving
    assert [f.index for f in frames] == [1, 2]
    assert any("ValueError: a bug a peer found" in line for line in lines)


def test_send_says_its_session_was_refused_with_exit_2(tmp_path, recording, capsys):
    from echoloc.cli import commands as cli

    path = tmp_path / "head.h5"
    write_recording(recording, path)

    def accept(header):
        raise EchoLocError("this receiver cannot locate with 4 receivers in a line")

    listener = Listener(Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(64), accept_session=accept)
    with listener, pytest.raises(SystemExit) as info:
        cli.main(["send", str(path), "--to", f"127.0.0.1:{listener.address.port}", "--speed", "0"])
    _, err = capsys.readouterr()
    assert info.value.code == 2
    assert err.count("\n") == 1
    assert "the receiver refused: session refused: this receiver cannot locate" in err


def test_an_old_sender_that_never_reads_still_works(recording):
    """The refusal is the only thing a receiver ever writes: a sender that never reads (every
    sender before it existed) streams as before."""
    listener = Listener(Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(64))
    with (
        listener,
        socket.create_connection(("127.0.0.1", listener.address.port), timeout=5) as client,
    ):
        client.sendall(encode_session(recording))
        for k in range(N_FRAMES):
            client.sendall(encode_frame(recording.frames[k], sequence=k, sample_rate_hz=2e5))
        client.sendall(encode_end(N_FRAMES))
        frames = frames_of(listener, N_FRAMES)
        client.shutdown(socket.SHUT_WR)
        assert refusal_of(client) is None  # nothing came back; closed once read
    assert len(frames) == N_FRAMES


# ----------------------------------------------------------------------------- connections


def test_idle_connections_do_not_keep_a_sender_out(recording):
    """Issue 31, finding 4: one idle connection blocked every other sender (listen(1), served
    one at a time, no timeout). 100 idle connections now: those past the 8 are refused, and
    once the 8 have been silent for the grace period the sender is served at once, the oldest
    idle one closed to make room."""
    with Listener(
        Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(64), max_connections=8, close_grace_s=0.2
    ) as listener:
        idle = [socket.create_connection(("127.0.0.1", listener.address.port), timeout=5) for _ in range(100)]
        try:
            time.sleep(0.3)
            started = time.monotonic()
            send_recording(recording, listener.address, speed=0)
            frames = frames_of(listener, N_FRAMES)
            took_s = time.monotonic() - started
            assert wait_until(lambda: listener.connections <= 8)
        finally:
            for client in idle:
                client.close()
    assert len(frames) == N_FRAMES
    assert took_s < 3.0


def test_an_idle_connection_is_closed_after_the_idle_timeout(recording):
    """A sender whose session was taken and that then says nothing holds the stream only until
    the idle timeout: a sender waiting behind it is served then, and the idle one is told."""
    listener = Listener(Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(64), idle_timeout_s=0.5)
    with listener, socket.create_connection(("127.0.0.1", listener.address.port), timeout=5) as holder:
        holder.sendall(encode_session(recording))
        assert isinstance(listener.queue.get(5.0), SessionEvent)
        started = time.monotonic()
        sender = threading.Thread(
            target=send_recording, args=(recording, listener.address), kwargs={"speed": 0}
        )
        sender.start()
        frames = frames_of(listener, N_FRAMES)
        waited_s = time.monotonic() - started
        sender.join(10)
        reason = refusal_of(holder)
    assert len(frames) == N_FRAMES
    assert 0.3 < waited_s < 3.0
    assert reason is not None
    assert "idle for" in reason


def test_senders_at_once_are_all_served_in_turn_their_frames_never_mixed(recording):
    with Listener(Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(256, block=True)) as listener:
        senders = [
            threading.Thread(target=send_recording, args=(recording, listener.address), kwargs={"speed": 0})
            for _ in range(4)
        ]
        for sender in senders:
            sender.start()
        items = []
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline and sum(isinstance(i, StreamFrame) for i in items) < 4 * N_FRAMES:
            if (item := listener.queue.get(0.05)) is not None:
                items.append(item)
        for sender in senders:
            sender.join(10)
        ends = [listener.queue.get(1.0) for _ in range(2)]
    frames = [i.index for i in items if isinstance(i, StreamFrame)]
    # Each connection's frames in a row, numbered afresh: 0 1 2, 0 1 2, ...
    assert frames == list(range(N_FRAMES)) * 4
    assert sum(isinstance(i, SessionEvent) for i in items) == 1  # the same session: told once
    assert any(isinstance(e, EndEvent) for e in ends)


def test_a_connection_refused_when_all_are_streaming_is_told_so(recording):
    with Listener(Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(64), max_connections=1) as listener:
        with socket.create_connection(("127.0.0.1", listener.address.port), timeout=5) as holder:
            holder.sendall(encode_session(recording))
            assert isinstance(listener.queue.get(5.0), SessionEvent)
            with pytest.raises(EchoLocError, match="too many connections"):
                send_recording(recording, listener.address, speed=0)
        assert listener.serving


def test_sixty_garbage_connections_make_a_few_lines_and_every_one_is_counted():
    """Issue 31, finding 11: 60 garbage connections printed 7 314 warning lines."""
    with Listener(Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(16)) as listener:
        for k in range(60):
            with socket.create_connection(("127.0.0.1", listener.address.port), timeout=5) as client:
                client.sendall(bytes(range(256)) * 4 + b"ECHL" + bytes(48) + b"noise %d" % k)
        assert wait_until(lambda: listener.connections == 0 and listener.malformed >= 60)
        lines = list(listener.errors())
        malformed = listener.malformed
    lines += list(listener.errors())  # stopped: the counts of those held back
    assert len(lines) <= 6, lines
    held = [int(line.rsplit("(", 1)[1].split()[0]) for line in lines if "more like it" in line]
    assert held, lines
    # Every complaint is in a line: shown alone, or counted in the line that ends its interval.
    assert len(lines) - len(held) + sum(held) == malformed


def test_binding_beyond_loopback_warns_once_and_loopback_does_not():
    with pytest.warns(ExposedListenerWarning, match="no authentication"):
        exposed = Listener(Endpoint("0.0.0.0", 0, "udp"), FrameQueue(4))
    exposed.stop()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Listener(Endpoint("127.0.0.1", 0, "udp"), FrameQueue(4)).stop()


# ----------------------------------------------------------------------------- sizes


def test_sessions_over_the_size_limits_are_refused_before_their_payload_is_read(recording):
    message = encode_session(recording)
    header = decode_header(message)
    with pytest.raises(ProtocolError, match=r"2400 samples, 0\.1 MiB each, over the limit of 0\.0625 MiB"):
        decode_session(header, message[HEADER_BYTES:], "tcp://x", max_frame_bytes=2**16)
    with pytest.raises(ProtocolError, match=r"session payload of \d+ bytes is over the limit of 100"):
        decode_session(header, message[HEADER_BYTES:], "tcp://x", max_session_bytes=100)
    # The listener's own limits: the sender is told.
    with (
        Listener(
            Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(4), max_frame_bytes=4 * 2400 * 8 - 1
        ) as listener,
        pytest.raises(EchoLocError, match=r"the receiver refused: .*MiB each, over the limit"),
    ):
        send_recording(recording, listener.address, speed=0)


def test_a_connection_never_buffers_a_message_over_the_limit():
    """A header announcing a payload over the limit is refused as it arrives, not waited for."""
    body = bytearray(encode_frame(np.zeros((4, 10)), sequence=0, sample_rate_hz=1.0))
    # A header intact (its CRC made anew) that announces one byte over the limit.
    start = session_message(b"{}")
    fields = start[:8] + (MAX_SESSION_BYTES + 1).to_bytes(4, "little") + start[12 : HEADER.size]
    buffer = bytearray(fields + HEADER_CRC.pack(zlib.crc32(fields)))
    _, _, errors = split_messages(buffer, max_payload_bytes=MAX_SESSION_BYTES)
    assert [str(e) for e in errors] == [
        f"session payload of {MAX_SESSION_BYTES + 1} bytes is over the limit of {MAX_SESSION_BYTES}"
    ]
    assert len(buffer) < HEADER_BYTES  # refused as it arrives, never waited for
    buffer = bytearray(body)
    _, _, errors = split_messages(buffer, max_payload_bytes=79)
    assert any("over the limit of 79" in str(e) for e in errors)
    assert len(buffer) < len(body)


def test_the_queue_is_bounded_in_bytes_as_well_as_in_frames():
    """Issue 31, finding 5: the queue was bounded in frames only; large frames drove it to 8.7 GB."""
    frame = np.zeros((4, 1000))  # 32 000 bytes
    queue = FrameQueue(1000, max_bytes=3 * frame.nbytes)
    for k in range(10):
        queue.put(StreamFrame(k, frame, 0.0))
    queue.put(SessionEvent(None))  # control items cost nothing and are never dropped
    assert len(queue) == 3
    assert queue.nbytes == 3 * frame.nbytes
    assert queue.dropped == 7
    got = queue.get_batch(0.1, 10)
    assert [f.index for f in got] == [7, 8, 9]
    assert queue.nbytes == 0
    # A single frame larger than the bound is still taken into an empty queue.
    big = FrameQueue(4, max_bytes=10)
    big.put(StreamFrame(0, frame, 0.0))
    assert len(big) == 1


def test_the_recorder_hand_over_is_bounded_in_bytes(tmp_path, recording):
    """Frames waiting for the writer take at most max_bytes; the rest are counted dropped."""
    from echoloc.io.recording import read_recording
    from echoloc.realtime.transport import Recorder

    release = threading.Event()

    class Stalled(Recorder):
        def _run(self) -> None:
            release.wait(10)  # a disk that has stopped answering
            super()._run()

    frame = recording.frames[0]
    recorder = Stalled(tmp_path / "r.h5", recording, max_bytes=3 * frame.nbytes)
    for k in range(10):
        recorder.add(StreamFrame(k, frame, 0.01 * k))
    release.set()
    recorder.close()
    assert (recorder.frames, recorder.dropped) == (3, 7)
    assert read_recording(tmp_path / "r.h5").n_frames == 3


# ----------------------------------------------------------------------------- sequence numbers


def test_one_forged_sequence_number_costs_one_frame_not_two_to_the_31_lost():
    """Issue 31, finding 11: one forged sequence number added 2^31 to `lost`."""
    tracker = SequenceTracker()
    numbers = [tracker.observe(s) for s in (0, 1, 2, 2**31 + 1, 3, 4)]
    assert numbers == [0, 1, 2, None, 3, 4]
    assert (tracker.lost, tracker.out_of_order, tracker.restarts) == (0, 1, 0)


def test_a_sender_that_starts_again_is_followed_after_one_frame():
    tracker = SequenceTracker()
    for s in range(500):
        tracker.observe(s)
    numbers = [tracker.observe(s) for s in (0, 1, 2, 3)]
    assert numbers == [None, 1, 2, 3]
    assert (tracker.lost, tracker.restarts) == (0, 1)
    # Reordered a little and lost a little: counted as such, no restart.
    assert [tracker.observe(s) for s in (5, 4, 7)] == [5, None, 7]
    assert (tracker.lost, tracker.out_of_order, tracker.restarts) == (2, 2, 1)


def _unconfirmed(sequences: list[int]) -> bool:
    """No number in ``sequences`` followed by the next one: no jump is ever confirmed."""
    return all((b - a) & 0xFFFFFFFF != 1 for a, b in itertools.pairwise(sequences))


@settings(max_examples=200, deadline=None)
@given(st.lists(st.integers(0, 2**32 - 1), max_size=60).filter(_unconfirmed))
def test_forged_sequence_numbers_never_count_more_lost_than_a_dropout_a_frame(sequences):
    """Far-off numbers that the next frame does not follow (forged, corrupted) cost a frame each."""
    tracker = SequenceTracker()
    accepted = [n for n in map(tracker.observe, sequences) if n is not None]
    assert tracker.lost <= tracker.max_dropout * len(sequences)
    assert len(accepted) + tracker.out_of_order == len(sequences)


def test_a_long_outage_is_counted_lost_and_a_single_far_frame_is_not():
    """Review of issue 31: a confirmed jump of 3000 or more forward counted as a restart, its
    gap never lost: a 30 s outage at 100 Hz vanished from `lost`."""
    tracker = SequenceTracker()
    for s in range(100):
        tracker.observe(s)
    assert [tracker.observe(s) for s in (3100, 3101, 3102)] == [None, 3101, 3102]
    # 100..3100 never came through: 3000 lost on the way, and 3100, refused until 3101 confirmed it.
    assert (tracker.lost, tracker.out_of_order, tracker.restarts) == (3001, 0, 0)
    # One far frame alone, forward or back, is still one discarded frame.
    assert [tracker.observe(s) for s in (900_000, 3103, 5, 3104)] == [None, 3103, None, 3104]
    assert (tracker.lost, tracker.out_of_order, tracker.restarts) == (3001, 2, 0)
    # A sender that announces a number ahead in its session is in an outage, not a new start.
    assert tracker.follows(3105 + 10_000)
    assert not tracker.follows(0)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(1, 2**24), max_size=20), st.integers(0, 2**32 - 1))
@example(steps=[3000, 3001, 3002], first=2**32 - 3001)  # either side of max_dropout, across the wrap
def test_outages_of_any_length_are_counted_lost_exactly(steps, first):
    """Every number from the first frame to the last is a frame taken or one counted lost."""
    tracker = SequenceTracker()
    sequence = first
    tracker.observe(sequence)
    taken = 1
    for step in steps:
        sequence += step
        number = tracker.observe(sequence & 0xFFFFFFFF)
        if step > tracker.max_dropout:  # frames of the gap: step - 1; believed when the next follows
            assert number is None
            sequence += 1
            number = tracker.observe(sequence & 0xFFFFFFFF)
        assert number == sequence
        taken += 1
    assert tracker.lost == sequence - first + 1 - taken
    assert tracker.restarts == tracker.out_of_order == 0


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(1, 40), max_size=30), st.integers(0, 2**32 - 1))
def test_frames_lost_on_the_way_are_counted_exactly(steps, first):
    tracker = SequenceTracker()
    sequence = first
    tracker.observe(sequence)
    for step in steps:
        sequence = (sequence + step) & 0xFFFFFFFF
        assert tracker.observe(sequence) is not None
    assert tracker.lost == sum(steps) - len(steps)
    assert tracker.restarts == tracker.out_of_order == 0


def test_a_udp_sender_that_starts_again_is_seen_by_its_session(recording):
    """Issue 31, finding 6: a UDP sender that restarted was ignored as out of order until its
    sequence number passed the old one."""
    with Listener(Endpoint("127.0.0.1", 0, "udp"), FrameQueue(256)) as listener:
        out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        address = ("127.0.0.1", listener.address.port)
        frame = recording.frames[0]
        out.sendto(encode_session(recording, next_sequence=0), address)
        for s in range(50):
            out.sendto(encode_frame(frame, sequence=s, sample_rate_hz=2e5), address)
        first = frames_of(listener, 50)
        # Rebooted: its session again (announcing frame 0), then frames from 0.
        out.sendto(encode_session(recording, next_sequence=0), address)
        for s in range(5):
            out.sendto(encode_frame(frame, sequence=s, sample_rate_hz=2e5), address)
        again = frames_of(listener, 5)
        for s in range(5, 200):
            out.sendto(encode_frame(frame, sequence=s, sample_rate_hz=2e5), address)
            if s % 50 == 0:  # paced: no datagram lost in the socket's buffer
                time.sleep(0.02)
        assert len(frames_of(listener, 195)) == 195
        # And a sender that sends no sessions (a firmware for --geometry): seen on its second frame.
        for s in range(5):
            out.sendto(encode_frame(frame, sequence=s, sample_rate_hz=2e5), address)
        frames_only = frames_of(listener, 4)
        out.close()
        counters = listener.counters()
    assert len(first) == 50
    assert [f.index for f in again] == [0, 1, 2, 3, 4]
    assert [f.index for f in frames_only] == [1, 2, 3, 4]
    assert (counters["restarts"], counters["out_of_order"], counters["lost"]) == (2, 1, 0)


# ----------------------------------------------------------------------------- the decoder


JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=5), inner, max_size=4),
    max_leaves=20,
)
FIELDS = [
    "format",
    "version",
    "sample_rate_hz",
    "transmitters",
    "receivers",
    "waveform",
    "signal_kind",
    "background",
    "receiver_gain",
    "transmitter_waveforms",
    "carrier_hz",
    "firing",
]


def _decoded_or_refused(message: bytes, source: str) -> Any:
    """decode_session's header, or the one line of its ProtocolError (anything else escapes)."""
    try:
        return decode_session(decode_header(message), message[HEADER_BYTES:], source)
    except ProtocolError as error:
        return str(error)


@settings(max_examples=150, deadline=None)
@given(
    st.dictionaries(st.sampled_from(FIELDS), JSON, max_size=4),
    st.integers(0, 8),
    st.integers(0, 3000),
)
def test_a_session_decodes_or_raises_protocol_error_and_nothing_else(good, fields, n_channels, n_samples):
    payload = json.dumps({**good, **fields}).encode()
    got = _decoded_or_refused(
        session_message(payload, n_channels=n_channels, n_samples=n_samples), "tcp://fuzz"
    )
    if isinstance(got, str):
        assert got.startswith("tcp://fuzz: ")
        assert "\n" not in got
    else:
        assert got.n_receivers == n_channels


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=300), st.text(max_size=1500))
def test_any_bytes_in_a_session_decode_or_raise_protocol_error(junk, reason):
    got = _decoded_or_refused(session_message(junk), "udp://fuzz")
    assert isinstance(got, str)  # no bytes of 300 make a session
    assert "\n" not in got
    # A refusal is one line of at most MAX_REFUSAL_BYTES, whatever it is given.
    message = encode_refusal(reason + "\n é")
    header = decode_header(message)
    said = decode_refusal(header, message[HEADER_BYTES:])
    assert "\n" not in said
    assert len(said.encode()) <= MAX_REFUSAL_BYTES


# ----------------------------------------------------------------------------- the commands


@pytest.fixture(scope="module")
def recording_path(tmp_path_factory, recording):
    path = tmp_path_factory.mktemp("hostile") / "head.h5"
    write_recording(recording, path)
    return path


def test_stream_serves_a_sender_after_the_12_malformed_sessions(recording_path, good):
    """`echoloc stream` as a user runs it: the twelve refused, each with one line, and then an
    `echoloc send` is located frame for frame as `echoloc locate` locates its file."""
    from test_stream_cli import Proc, echoloc

    stream = Proc("stream", "--listen", "127.0.0.1:0", "--once", "--json")
    port = stream.port()
    for message, _ in variants(good, udp=False).values():
        assert send_raw(port, "tcp", message) is not None
    sent = echoloc("send", recording_path, "--to", f"127.0.0.1:{port}", "--speed", "0")
    assert sent.returncode == 0, sent.stderr
    code, stdout = stream.finish()
    assert code == 0, stream.lines
    assert stdout == echoloc("locate", recording_path, "--json", check=True).stdout
    assert f"received {N_FRAMES}, processed {N_FRAMES}, lost 0" in stream.lines[-1]
    assert "refused 12" in stream.lines[-1]
    warned = [line for line in stream.lines if line.startswith("echoloc: warning: ")]
    assert 1 <= len(warned) <= 3  # one line, and the count of those like it
    assert not any("Traceback" in line for line in stream.lines)


@pytest.mark.parametrize("command", ["stream", "record"])
def test_a_command_that_refused_every_session_says_what_and_exits_2(tmp_path, good, command):
    """`stream` said "no session arrived" and exited 0 after refusing (or dying on) every session."""
    from test_stream_cli import Proc

    out = tmp_path / "none.h5"
    args = [out] if command == "record" else []
    proc = Proc(command, *args, "--listen", "127.0.0.1:0", "--duration", "1.5")
    port = proc.port()
    message, _ = variants(good, udp=False)["version 2"]
    assert "version is 2" in (send_raw(port, "tcp", message) or "")
    code, _ = proc.finish()
    assert code == 2, proc.lines
    where = f"{out}: " if command == "record" else ""
    assert re.search(
        rf"echoloc: error: {re.escape(where)}no session accepted on tcp://127\.0\.0\.1:\d+: 1 session "
        "refused, the last: version is 2",
        proc.lines[-1],
    ), proc.lines
    assert not any("no session arrived" in line for line in proc.lines)
    assert not out.exists()


def test_record_refuses_to_replace_a_file_without_force(tmp_path, capsys):
    from echoloc.cli import commands as cli

    out = tmp_path / "kept.h5"
    out.write_bytes(b"an earlier recording")
    with pytest.raises(SystemExit) as info:
        cli.main(["record", str(out), "--listen", "127.0.0.1:0", "--duration", "0.2"])
    _, err = capsys.readouterr()
    assert info.value.code == 2
    assert err == f"echoloc: error: {out}: already exists; give --force to replace it\n"
    with pytest.raises(SystemExit) as info:
        cli.main(["stream", "--record", str(out), "--listen", "127.0.0.1:0", "--duration", "0.2"])
    assert info.value.code == 2
    assert "already exists; give --force" in capsys.readouterr().err
    assert out.read_bytes() == b"an earlier recording"


def test_record_with_force_replaces_the_file(tmp_path, recording_path, recording):
    from test_stream_cli import Proc, echoloc

    from echoloc.io.recording import read_recording

    out = tmp_path / "again.h5"
    out.write_bytes(b"an earlier recording")
    record = Proc("record", out, "--force", "--listen", "127.0.0.1:0", "--once")
    sent = echoloc("send", recording_path, "--to", f"127.0.0.1:{record.port()}", "--speed", "0")
    assert sent.returncode == 0, sent.stderr
    code, _ = record.finish()
    assert code == 0, record.lines
    np.testing.assert_array_equal(read_recording(out).frames, recording.frames)


# ----------------------------------------------------------------------------- review of the fixes


def _quietly(target: Callable[..., Any], *args: Any, **kwargs: Any) -> threading.Thread:
    """``target`` in a thread whose exception (a sender refused or cut off) is its own business."""

    def run() -> None:
        with contextlib.suppress(EchoLocError, OSError):
            target(*args, **kwargs)

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    return thread


def test_a_flood_of_sessions_behind_a_slow_chain_stays_within_max_connections(recording):
    """Connections being closed did not count, and one waiting its turn to decode could not see
    it was to close: with a slow chain every new connection closed one more waiting one and was
    admitted (60 connections open, 62 threads). Now the bound holds, threads included."""
    before = threading.active_count()

    def slow_chain(header: Any) -> None:
        time.sleep(0.3)

    peak = {"connections": 0, "threads": 0}
    done = threading.Event()

    def watch(listener: Listener) -> None:
        while not done.is_set():
            peak["connections"] = max(peak["connections"], listener.connections)
            peak["threads"] = max(peak["threads"], threading.active_count())
            time.sleep(0.002)

    message = encode_session(recording)
    clients = []
    listener = Listener(
        Endpoint("127.0.0.1", 0, "tcp"),
        FrameQueue(16),
        max_connections=4,
        accept_session=slow_chain,
        close_grace_s=0.1,
    )
    with listener:
        watcher = threading.Thread(target=watch, args=(listener,))
        watcher.start()
        try:
            for _ in range(40):  # over 0.8 s: those waiting their turn pass the grace and are closed
                client = socket.create_connection(("127.0.0.1", listener.address.port), timeout=5)
                client.sendall(message)
                clients.append(client)
                time.sleep(0.02)
            # Every one refused or closed but those whose session was taken (one each 0.3 s).
            all_sorted = wait_until(lambda: listener.refused >= 40 - 4, timeout_s=3.0)
        finally:
            done.set()
            watcher.join()
            for client in clients:
                client.close()
    assert all_sorted, listener.refused
    assert peak["connections"] <= 4
    # The listener's thread, the watcher, 4 connections and the threads telling refusals.
    assert peak["threads"] <= before + 2 + 4 + MAX_REFUSING_THREADS


def test_a_sender_that_just_connected_is_read_before_a_flood_can_close_it(recording):
    """A new connection was checked for closing before its first read: under a flood of
    connections a sender was closed with its session unread."""
    with Listener(Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(64), max_connections=1) as listener:
        sender = socket.create_connection(("127.0.0.1", listener.address.port), timeout=5)
        assert wait_until(lambda: listener.connections == 1)
        flood = [socket.create_connection(("127.0.0.1", listener.address.port), timeout=5) for _ in range(20)]
        try:
            assert wait_until(lambda: listener.refused == 20)
            sender.sendall(encode_session(recording))
            for k in range(N_FRAMES):
                sender.sendall(encode_frame(recording.frames[k], sequence=k, sample_rate_hz=2e5))
            sender.sendall(encode_end(N_FRAMES))
            frames = frames_of(listener, N_FRAMES)
            sender.shutdown(socket.SHUT_WR)
            assert refusal_of(sender) is None
        finally:
            sender.close()
            for client in flood:
                client.close()
    assert [f.index for f in frames] == list(range(N_FRAMES))


def test_garbage_does_not_keep_an_idle_stream_owner(recording):
    """Any byte reset the idle timer: a stream owner sending one garbage byte now and then kept
    the stream for ever, and every other sender waited. Only what is taken counts now."""
    listener = Listener(Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(64), idle_timeout_s=0.5)
    with listener, socket.create_connection(("127.0.0.1", listener.address.port), timeout=5) as holder:
        holder.sendall(encode_session(recording))
        assert isinstance(listener.queue.get(5.0), SessionEvent)
        stop = threading.Event()

        def trickle() -> None:
            while not stop.wait(0.1):
                with contextlib.suppress(OSError):
                    holder.send(b"x")

        trickler = threading.Thread(target=trickle)
        trickler.start()
        started = time.monotonic()
        sender = _quietly(send_recording, recording, listener.address, speed=0)
        frames = frames_of(listener, N_FRAMES, timeout_s=4.0)
        waited_s = time.monotonic() - started
        stop.set()
        trickler.join()
        sender.join(10)
        reason = refusal_of(holder)
    assert len(frames) == N_FRAMES
    assert waited_s < 3.0
    assert reason is not None
    assert "idle for" in reason


def test_a_connection_refused_as_one_too_many_is_told_even_with_its_session_unread(recording):
    """The refusal went out and the connection was closed at once, the sender's session unread:
    the reset that sends could discard the refusal. It is now told, drained and closed cleanly."""
    with (
        Listener(Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(64), max_connections=1) as listener,
        socket.create_connection(("127.0.0.1", listener.address.port), timeout=5) as holder,
    ):
        holder.sendall(encode_session(recording))
        assert isinstance(listener.queue.get(5.0), SessionEvent)
        with socket.create_connection(("127.0.0.1", listener.address.port), timeout=5) as late:
            late.sendall(encode_session(recording))
            late.sendall(encode_frame(recording.frames[0], sequence=0, sample_rate_hz=2e5))
            time.sleep(0.2)  # the receiver has answered, with all this unread
            inbox = bytearray()
            while chunk := late.recv(4096):  # a reset raises here
                inbox += chunk
    messages, _, _ = split_messages(inbox)
    assert [decode_refusal(h, p) for h, p in messages] == [
        "too many connections (1), all busy: try again later"
    ]


def test_a_connection_marked_to_close_that_proves_itself_is_kept_and_counted(recording):
    """A connection marked to close that then had its session taken stayed marked (and
    uncounted: more than max_connections served). Now it is kept, counted, and its frames come."""

    def slow_chain(header: Any) -> None:
        time.sleep(0.6)

    listener = Listener(
        Endpoint("127.0.0.1", 0, "tcp"),
        FrameQueue(64),
        max_connections=1,
        accept_session=slow_chain,
        close_grace_s=0.1,
    )
    port = listener.address.port
    with listener, socket.create_connection(("127.0.0.1", port), timeout=5) as first:
        first.sendall(encode_session(recording))
        time.sleep(0.25)
        # The first is past the grace with nothing taken (its chain is being prepared): marked to
        # close for this one, which, finding no room in time, is refused.
        assert send_raw(port, "tcp", encode_session(recording)) == (
            "too many connections (1), all busy: try again later"
        )
        assert listener.connections == 1
        assert isinstance(listener.queue.get(5.0), SessionEvent)  # its session taken: proven
        for k in range(N_FRAMES):
            first.sendall(encode_frame(recording.frames[k], sequence=k, sample_rate_hz=2e5))
        frames = frames_of(listener, N_FRAMES)
        first.sendall(encode_end(N_FRAMES))
        first.shutdown(socket.SHUT_WR)
        assert refusal_of(first) is None
    assert [f.index for f in frames] == list(range(N_FRAMES))


def test_a_refusal_is_read_from_a_descriptor_past_1024():
    """select() raised ValueError past descriptor 1023, taken for "closed": `send` said the
    receiver had read everything."""
    fcntl = pytest.importorskip("fcntl")
    resource = pytest.importorskip("resource")
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < 1200:
        if hard != resource.RLIM_INFINITY and hard < 1200:
            pytest.skip("cannot open a descriptor past 1024 here")
        resource.setrlimit(resource.RLIMIT_NOFILE, (1200, hard))
    ours, theirs = socket.socketpair()
    try:
        high = fcntl.fcntl(ours.fileno(), fcntl.F_DUPFD, 1100)
        ours.close()
        ours = socket.socket(fileno=high)
        assert ours.fileno() >= 1024
        replies = _Replies(ours, Endpoint())
        replies.poll()
        assert not replies.closed  # nothing came: still open
        theirs.sendall(encode_refusal("busy"))
        with pytest.raises(EchoLocError, match="the receiver refused: busy"):
            replies.poll()
    finally:
        ours.close()
        theirs.close()
        if soft < 1200:
            resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


def test_stream_without_a_session_exits_0_when_only_connections_were_closed():
    """A probe that stayed connected past the idle timeout counted as refused, and `stream`
    exited 2 ("no session accepted"): only refused sessions make it exit 2."""
    from test_stream_cli import Proc

    proc = Proc("stream", "--listen", "127.0.0.1:0", "--idle-timeout", "0.3", "--duration", "1.5")
    port = proc.port()
    with socket.create_connection(("127.0.0.1", port), timeout=5) as probe:
        probe.sendall(b"GET / HTTP/1.0\r\n\r\n")
        assert "idle for" in (refusal_of(probe) or "")
    code, _ = proc.finish()
    assert code == 0, proc.lines
    assert "refused 1" in proc.lines[-1]
    assert proc.lines[-1].endswith("no session arrived"), proc.lines


def test_the_rarely_seen_counts_are_shown_only_when_not_zero():
    assert rare_counts(refused=0, restarts=0) == ""
    assert rare_counts(refused=2, restarts=0) == ", refused 2"
    assert rare_counts(refused=2, restarts=1) == ", refused 2, restarts 1"
