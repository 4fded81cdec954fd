"""The wire protocol: byte layout, round trips, and refusal of every kind of damage."""

from __future__ import annotations

import math
import struct
import zlib
from dataclasses import replace

import numpy as np
import pytest

from echoloc.errors import EchoLocError
from echoloc.realtime.protocol import (
    HEADER_BYTES,
    KIND_END,
    KIND_FRAME,
    KIND_SESSION,
    MAGIC,
    ProtocolError,
    decode_frame,
    decode_header,
    decode_session,
    encode_end,
    encode_frame,
    encode_session,
    frame_message,
    frame_payload,
    split_messages,
)
from echoloc.sim.scene import default_scene
from echoloc.sim.simulation import recording_header, simulate
from repo_paths import REPO


@pytest.fixture(scope="module")
def recording():
    return simulate(default_scene(), 3)


def test_header_layout_matches_the_documented_byte_offsets():
    samples = np.arange(6, dtype=np.float32).reshape(2, 3)
    message = encode_frame(
        samples, sequence=7, sample_rate_hz=200e3, frame_time_s=1.5, transmitter=1, payload_crc=True
    )
    assert len(message) == HEADER_BYTES + 24
    # docs/STREAM_PROTOCOL.md, header table: offset, type.
    assert message[0:4] == b"ECHL"
    assert message[4] == 1  # version
    assert message[5] == KIND_FRAME
    assert struct.unpack_from("<H", message, 6)[0] == 52  # header_bytes
    assert struct.unpack_from("<I", message, 8)[0] == 24  # payload_bytes
    assert struct.unpack_from("<I", message, 12)[0] == 7  # sequence
    assert struct.unpack_from("<d", message, 16)[0] == 1.5  # frame_time_s
    assert struct.unpack_from("<d", message, 24)[0] == 200e3  # sample_rate_hz
    assert struct.unpack_from("<I", message, 32)[0] == 3  # n_samples
    assert struct.unpack_from("<H", message, 36)[0] == 2  # n_channels
    assert struct.unpack_from("<H", message, 38)[0] == 1  # transmitter
    assert message[40] == 2  # float32
    assert message[41] == 0  # rf
    assert struct.unpack_from("<H", message, 42)[0] == 1  # flags: payload CRC present
    assert struct.unpack_from("<I", message, 44)[0] == zlib.crc32(message[52:])
    assert struct.unpack_from("<I", message, 48)[0] == zlib.crc32(message[:48])
    # Channel-major payload: channel 0's samples first.
    np.testing.assert_array_equal(np.frombuffer(message[52:], "<f4"), [0, 1, 2, 3, 4, 5])


@pytest.mark.parametrize("sample_format", ["float32", "float64", "int16"])
def test_frame_round_trip(sample_format):
    rng = np.random.default_rng(1)
    samples = rng.normal(scale=1000.0, size=(4, 2400))
    if sample_format == "float32":
        samples = samples.astype(np.float32).astype(np.float64)
    elif sample_format == "int16":
        samples = np.rint(samples)
    message = encode_frame(
        samples, sequence=2**32 + 5, sample_rate_hz=2e5, frame_time_s=0.25, sample_format=sample_format
    )
    header = decode_header(message)
    frame = decode_frame(header, message[header.header_bytes :])
    assert frame.sequence == 5  # 32 bits on the wire
    assert frame.frame_time_s == 0.25
    assert frame.samples.dtype == np.float64
    np.testing.assert_array_equal(frame.samples, samples)


def test_int16_clips_to_the_adc_range_and_iq_is_complex():
    message = encode_frame(
        np.array([[40000.0, -40000.0, 1.4]]), sequence=0, sample_rate_hz=1.0, sample_format="int16"
    )
    header = decode_header(message)
    np.testing.assert_array_equal(decode_frame(header, message[52:]).samples, [[32767, -32768, 1]])
    iq = np.array([[1 + 2j, -3 - 0.5j]])
    message = encode_frame(iq, sequence=0, sample_rate_hz=1.0, signal_kind="iq", sample_format="complex64")
    header = decode_header(message)
    np.testing.assert_array_equal(decode_frame(header, message[52:]).samples, iq)
    with pytest.raises(ProtocolError, match="complex64"):
        encode_frame(iq.real, sequence=0, sample_rate_hz=1.0, signal_kind="iq", sample_format="float32")


def test_session_carries_every_per_recording_field(recording):
    message = encode_session(recording)
    header = decode_header(message)
    assert header.kind == KIND_SESSION
    assert (header.n_channels, header.n_samples) == (4, 2400)
    back = decode_session(header, message[52:], "tcp://test")
    assert back.n_frames == 0
    assert back.source == "tcp://test"
    for name in ("sample_rate_hz", "signal_kind", "carrier_hz", "speed_of_sound_m_s", "temperature_c"):
        assert getattr(back, name) == getattr(recording, name), name
    for name in ("transmitters_m", "receivers_m", "waveform"):
        np.testing.assert_array_equal(getattr(back, name), getattr(recording, name))
    assert back.truth_positions_m is None  # per-frame fields never travel in a session


def test_session_of_iq_recording_keeps_complex_templates():
    scene = default_scene()
    iq = replace(scene, receiver=replace(scene.receiver, signal_kind="iq"))
    header = recording_header(iq)
    message = encode_session(header)
    back = decode_session(decode_header(message), message[52:], "udp://test")
    assert back.signal_kind == "iq"
    np.testing.assert_array_equal(back.waveform, header.waveform)
    assert np.iscomplexobj(back.waveform)


def _session_refusal(recording, geometry: bytes) -> str:
    """Why ``decode_session`` refuses a session whose fields after the sample rate are ``geometry``."""
    payload = b'{"format": "echoloc-recording", "version": 1, "sample_rate_hz": 200000.0, ' + geometry + b"}"
    header = replace(decode_header(encode_session(recording)), payload_bytes=len(payload), payload_crc32=None)
    with pytest.raises(EchoLocError) as info:
        decode_session(header, payload, "tcp://x")
    return str(info.value)


def test_session_refuses_bad_geometry_in_one_line(recording):
    why = _session_refusal(
        recording, b'"transmitters": [[0, 0, 0]], "receivers": [[0, 0, 1e999]], "waveform": [1, 0]'
    )
    assert "\n" not in why
    assert "tcp://x" in why
    assert "receivers" in why
    header = decode_header(encode_session(recording))
    with pytest.raises(ProtocolError, match="not UTF-8 JSON"):
        decode_session(replace(header, payload_bytes=3, payload_crc32=None), b"{no", "tcp://x")


def test_an_array_field_that_is_text_with_a_line_break_is_refused_in_one_line(recording):
    """The refusal quotes the bad value: quoted as Python writes it, its line breaks stay
    escaped (hypothesis found ``"waveform": "\\n"`` printed across two lines)."""
    why = _session_refusal(
        recording, b'"transmitters": [[0, 0, 0]], "receivers": [[0, 0, 1]], "waveform": "\\n1"'
    )
    assert "\n" not in why
    assert "waveform" in why
    assert "'\\n1'" in why


@pytest.mark.parametrize(
    ("offset", "match"),
    [(0, "magic"), (4, "version"), (20, "CRC"), (50, "CRC")],
)
def test_corruption_is_refused(offset, match):
    message = bytearray(encode_frame(np.ones((2, 4)), sequence=1, sample_rate_hz=10.0))
    message[offset] ^= 0x5A
    with pytest.raises(ProtocolError, match=match):
        decode_header(message)


def test_payload_damage_and_length_mismatch_are_refused():
    message = bytearray(encode_frame(np.ones((2, 4)), sequence=1, sample_rate_hz=10.0))
    header = decode_header(message)
    message[60] ^= 1
    with pytest.raises(ProtocolError, match="payload CRC"):
        decode_frame(header, message[52:])
    with pytest.raises(ProtocolError, match="payload is 31 bytes"):
        decode_frame(header, message[52:-1])
    with pytest.raises(ProtocolError, match="shorter"):
        decode_header(message[:20])


def test_nan_samples_are_refused():
    message = encode_frame(
        np.array([[1.0, math.nan]]), sequence=3, sample_rate_hz=10.0, sample_format="float64"
    )
    with pytest.raises(ProtocolError, match="frame 3: NaN"):
        decode_frame(decode_header(message), message[52:])


def test_byte_stream_split_resynchronises_after_garbage():
    frames = [encode_frame(np.full((2, 3), k, float), sequence=k, sample_rate_hz=10.0) for k in range(3)]
    corrupted = bytearray(frames[1])
    corrupted[30] ^= 0xFF  # bad header CRC
    stream = b"junk" + frames[0] + b"\x00" * 7 + bytes(corrupted) + MAGIC + frames[2] + encode_end(3)
    buffer = bytearray()
    got = []
    errors = []
    # Arrives in awkward pieces, as TCP may deliver it.
    for k in range(0, len(stream), 17):
        buffer += stream[k : k + 17]
        messages, _, errs = split_messages(buffer)
        got += messages
        errors += errs
    kinds = [h.kind for h, _ in got]
    assert kinds == [KIND_FRAME, KIND_FRAME, KIND_END]
    assert [h.sequence for h, _ in got[:2]] == [0, 2]
    assert [decode_frame(h, p).samples[0, 0] for h, p in got[:2]] == [0.0, 2.0]
    assert len(errors) >= 1
    assert all(isinstance(e, ProtocolError) and "\n" not in str(e) for e in errors)
    assert len(buffer) < len(MAGIC)


def test_the_protocol_page_example_is_what_the_encoder_writes():
    """docs/STREAM_PROTOCOL.md's hex dump decodes to the frame it describes, and back."""

    page = (REPO / "docs" / "STREAM_PROTOCOL.md").read_text()
    dump = page.split("payload CRC set:\n\n```\n", 1)[1].split("```", 1)[0]
    data = bytes.fromhex("".join(line[6:] for line in dump.splitlines()))
    header = decode_header(data)
    frame = decode_frame(header, data[header.header_bytes :])
    np.testing.assert_array_equal(frame.samples, [[1, 2, 3], [-1, -2, -3]])
    assert (frame.sequence, frame.frame_time_s, frame.sample_rate_hz) == (1, 0.01, 200e3)
    samples = np.array([[1, 2, 3], [-1, -2, -3]])
    assert (
        encode_frame(samples, sequence=1, sample_rate_hz=200e3, frame_time_s=0.01, sample_format="int16")
        == data
    )
    # The CRC the page gives as the check value.
    assert zlib.crc32(b"123456789") == 0xCBF43926
    assert "0xCBF43926" in page


@pytest.mark.parametrize(
    ("signal_kind", "sample_format"),
    [("rf", "float32"), ("rf", "float64"), ("rf", "int16"), ("envelope", "float32"), ("iq", "complex64")],
)
def test_a_message_of_a_kept_payload_is_encode_frame_s(signal_kind: str, sample_format: str) -> None:
    """frame_message of a frame_payload is the message encode_frame makes, byte for byte."""
    rng = np.random.default_rng(1)
    samples = 1000 * rng.normal(size=(3, 50))
    if signal_kind == "iq":
        samples = samples + 1j * rng.normal(size=(3, 50))
    fields = {"sequence": 9, "sample_rate_hz": 2e5, "frame_time_s": 0.25, "transmitter": 1}
    payload = frame_payload(samples, signal_kind=signal_kind, sample_format=sample_format)
    expected = encode_frame(samples, signal_kind=signal_kind, sample_format=sample_format, **fields)
    assert frame_message(payload, signal_kind=signal_kind, **fields) == expected


@pytest.mark.parametrize("loops", [1, 3])
def test_a_replay_s_loops_send_the_recording_s_frames_each_time(recording, loops: int) -> None:
    """Loops after the first send the payloads they kept: the same samples each loop, with the
    sequence running on and the frame times shifted by a pass."""
    import socket
    import threading

    from echoloc.realtime.transport import Endpoint, recording_span_s, send_recording

    server = socket.create_server(("127.0.0.1", 0))
    received = bytearray()

    def take() -> None:
        connection, _ = server.accept()
        with connection:
            while chunk := connection.recv(1 << 16):
                received.extend(chunk)

    reader = threading.Thread(target=take)
    reader.start()
    send_recording(recording, Endpoint("127.0.0.1", server.getsockname()[1]), speed=0, loops=loops)
    reader.join(timeout=30)
    server.close()
    messages, skipped, errors = split_messages(received)
    assert skipped == 0
    assert not errors
    frames = [decode_frame(header, payload) for header, payload in messages if header.kind == KIND_FRAME]
    n = recording.n_frames
    assert [f.sequence for f in frames] == list(range(loops * n))
    span = recording_span_s(recording)
    for k, frame in enumerate(frames):
        first = frames[k % n]
        np.testing.assert_allclose(first.samples, recording.frames[k % n], rtol=1e-7)  # float32 at worst
        np.testing.assert_array_equal(frame.samples, first.samples)
        assert frame.frame_time_s == pytest.approx(first.frame_time_s + (k // n) * span)
