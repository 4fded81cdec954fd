"""Hostile peers for ``echoloc stream``: malformed sessions, lying headers, garbage, idle and
slow connections, forged sequence numbers, over TCP and UDP.

One ``echoloc stream --json`` process per transport listens on loopback for the whole
run. After every hostile session a valid sender replays a small recording whose frame
times mark the round; the round passes when every one of its frames comes out of the
stream within :data:`harness.HANG_S`. A stream that exits, stops answering or grows past
:data:`harness.MEMORY_LIMIT_BYTES` is a finding ("stopped serving").
"""

from __future__ import annotations

import contextlib
import json
import math
import random
import socket
import subprocess
import sys
import threading
import time
import zlib
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

import harness
from echoloc.io.recording import Recording, read_recording
from echoloc.realtime.protocol import (
    HEADER,
    KIND_END,
    KIND_FRAME,
    KIND_SESSION,
    MAGIC,
    VERSION,
    encode_end,
    encode_frame,
)
from echoloc.realtime.transport import Endpoint, send_recording

N_VALID_FRAMES = 3
IDLE_TIMEOUT_S = 2.0


def header_bytes(**fields: Any) -> bytes:
    """A 52-byte message header from the documented layout (docs/STREAM_PROTOCOL.md), with
    any field overridden: a hostile peer writes its own bytes."""
    values = {
        "magic": MAGIC,
        "version": VERSION,
        "kind": KIND_SESSION,
        "header_bytes": HEADER.size + 4,
        "payload_bytes": 0,
        "sequence": 0,
        "frame_time_s": math.nan,
        "sample_rate_hz": 0.0,
        "n_samples": 0,
        "n_channels": 0,
        "transmitter": 0,
        "sample_format": 2,
        "signal_kind": 0,
        "flags": 0,
        "payload_crc32": 0,
    }
    values.update(fields)
    packed = HEADER.pack(*values.values())
    return packed + zlib.crc32(packed).to_bytes(4, "little")


def session_message(record: Any, like: Recording, payload: bytes | None = None, **fields: Any) -> bytes:
    """A session message carrying ``record`` as JSON (or ``payload`` as given), its header
    announcing ``like``'s frames unless ``fields`` say otherwise."""
    if payload is None:
        payload = json.dumps(record, allow_nan=True).encode()
    announced = {
        "kind": KIND_SESSION,
        "payload_bytes": len(payload),
        "sample_rate_hz": float(like.sample_rate_hz),
        "n_samples": like.n_samples,
        "n_channels": like.n_receivers,
        "flags": 1,
        "payload_crc32": zlib.crc32(payload),
    }
    announced.update(fields)
    return header_bytes(**announced) + payload


def valid_frames(recording: Recording, first_sequence: int = 0) -> list[bytes]:
    return [
        encode_frame(
            np.asarray(recording.frames[i], dtype=np.float32),
            sequence=first_sequence + i,
            sample_rate_hz=recording.sample_rate_hz,
            signal_kind=recording.signal_kind,
        )
        for i in range(recording.n_frames)
    ]


def hostile_messages(
    rng: random.Random, recording: Recording, record: dict[str, Any]
) -> tuple[list[bytes], str]:
    """The messages of one hostile session (one TCP connection, or one UDP sender), and what they are."""
    frames = valid_frames(recording)
    kind = rng.randrange(10)
    if kind == 0:
        tree, what = harness.mutate_tree(rng, record, n_mutations=rng.choice((1, 2)))
        return [session_message(tree, recording), *frames[:2]], f"session JSON: {what}"
    if kind == 1:
        depth = rng.choice((1000, 100_000))
        return [
            session_message(None, recording, payload=b"[" * depth + b"]" * depth)
        ], f"JSON nested {depth} deep"
    if kind == 2:
        return [
            session_message(None, recording, payload=rng.randbytes(rng.randrange(1, 400)))
        ], "session of random bytes"
    if kind == 3:
        field, value = rng.choice(
            (
                ("version", 2),
                ("kind", rng.randrange(4, 256)),
                ("n_samples", 2**31),
                ("n_samples", 2**32 - 1),
                ("n_channels", 65535),
                ("sample_rate_hz", rng.choice((math.nan, -1.0, 0.0, 5e-324, 1e300, math.inf))),
                ("sample_format", rng.randrange(5, 256)),
                ("signal_kind", rng.randrange(3, 256)),
                ("header_bytes", rng.choice((0, 4, 51, 53, 65535))),
                ("payload_bytes", 2**32 - 1),
                ("flags", 0xFFFF),
            )
        )
        message = session_message(record, recording, **{field: value})
        return [message, *frames[:1]], f"session header {field} = {value}"
    if kind == 4:
        stream = b"".join([session_message(record, recording), *frames, encode_end(len(frames))])
        data, what = harness.mutate_bytes(rng, stream)
        return [data], f"valid session corrupted: {what}"
    if kind == 5:
        sequences = [rng.choice((2**31, 2**32 - 1, rng.randrange(2**32))) for _ in frames]
        forged = [
            encode_frame(
                np.asarray(recording.frames[i], dtype=np.float32),
                sequence=sequence,
                sample_rate_hz=recording.sample_rate_hz,
                signal_kind=recording.signal_kind,
            )
            for i, sequence in enumerate(sequences)
        ]
        return [session_message(record, recording), *forged], f"forged sequence numbers {sequences}"
    if kind == 6:
        wrong = np.zeros((recording.n_receivers + rng.choice((-1, 1)), recording.n_samples), dtype=np.float32)
        frame = encode_frame(wrong, sequence=0, sample_rate_hz=recording.sample_rate_hz)
        return [session_message(record, recording), frame], "a frame with the wrong number of channels"
    if kind == 7:
        return [rng.randbytes(rng.randrange(1, 200_000))], "garbage bytes"
    if kind == 8:
        lying = header_bytes(kind=KIND_FRAME, payload_bytes=2**26, n_samples=2**24, n_channels=2, sequence=1)
        return [
            session_message(record, recording),
            lying + rng.randbytes(100),
        ], "a frame header promising 64 MiB"
    end = header_bytes(kind=KIND_END, sequence=rng.randrange(2**32))
    return [end, end, *frames[:1]], "ends and frames without a session"


class StreamUnderTest:
    """``echoloc stream --json`` on a loopback port, its output lines collected by a thread."""

    def __init__(self, transport: str, folder: Path) -> None:
        self.transport = transport
        self.port = _free_port(transport)
        command = [sys.executable, "-m", "echoloc", "stream", "--listen", f"127.0.0.1:{self.port}", "--json"]
        if transport == "tcp":  # a silent owner gives the stream up after this (10 s by default)
            command += ["--idle-timeout", str(IDLE_TIMEOUT_S)]
        if transport == "udp":
            command.append("--udp")
        folder.mkdir(parents=True, exist_ok=True)
        self.stderr_path = folder / f"stream-{transport}.stderr"
        self._stderr = self.stderr_path.open("w")
        self.process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=self._stderr, text=True)
        self.times: set[float] = set()
        self.lines = 0
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()

    @property
    def endpoint(self) -> Endpoint:
        return Endpoint("127.0.0.1", self.port, self.transport)

    def _read(self) -> None:
        assert self.process.stdout is not None
        for line in self.process.stdout:
            with contextlib.suppress(ValueError, KeyError):
                time_s = round(float(json.loads(line)["time_s"]), 6)
                with self._lock:
                    self.times.add(time_s)
                    self.lines += 1

    def has_all(self, times: list[float]) -> bool:
        with self._lock:
            return all(round(t, 6) in self.times for t in times)

    def stderr_lines(self) -> int:
        return len(self.stderr_path.read_text(errors="replace").splitlines())

    def stop(self) -> None:
        self.process.terminate()
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
        self._reader.join(timeout=5)  # the pipe ends with the process
        if self.process.stdout is not None:
            self.process.stdout.close()
        self._stderr.close()


def _free_port(transport: str) -> int:
    kind = socket.SOCK_STREAM if transport == "tcp" else socket.SOCK_DGRAM
    with socket.socket(socket.AF_INET, kind) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@contextlib.contextmanager
def _hostile_peer(
    stream: StreamUnderTest, messages: list[bytes], owner: list[bytes], rng: random.Random
) -> Iterator[str]:
    """Send ``messages`` as a hostile peer. On TCP, sometimes instead keep the connection
    open while the valid sender runs: idle, half-way through a header, or owning the
    stream (``owner``: a valid session and a frame) and then silent or trickling a garbage
    byte every 0.3 s, which must not keep the stream from the next sender for ever."""
    if stream.transport == "udp":
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as peer:
            for message in messages:
                with contextlib.suppress(OSError):  # a datagram too big for UDP: the kernel refuses it
                    peer.sendto(message, ("127.0.0.1", stream.port))
            yield ""
        return
    peer = socket.create_connection(("127.0.0.1", stream.port), timeout=5)
    done = threading.Event()
    trickle: threading.Thread | None = None
    note = ""
    try:
        behaviour = rng.random()
        with contextlib.suppress(OSError):  # the listener may refuse and close first
            if behaviour < 0.08:
                note = ", then idle while the valid sender runs"
            elif behaviour < 0.16:
                peer.sendall(messages[0][:20])
                note = ", 20 bytes of it, then silent while the valid sender runs"
            elif behaviour < 0.24:
                peer.sendall(b"".join(owner))
                note = " (instead: a valid session and a frame, then silent while the valid sender runs)"
            elif behaviour < 0.32:
                peer.sendall(b"".join(owner))
                trickle = threading.Thread(target=_trickle, args=(peer, done), daemon=True)
                trickle.start()
                note = " (instead: a valid session and a frame, then a garbage byte every 0.3 s)"
            else:
                for message in messages:
                    peer.sendall(message)
                peer.shutdown(socket.SHUT_WR)
        if not note:
            peer.close()
        yield note
    finally:
        done.set()
        if trickle is not None:
            trickle.join()
        peer.close()


def _trickle(peer: socket.socket, done: threading.Event) -> None:
    """A garbage byte every 0.3 s until ``done`` or the listener closes the connection."""
    while not done.wait(0.3):
        try:
            peer.sendall(b"\x00")
        except OSError:
            return


def run_sessions(
    seeds: harness.Seeds, rng: random.Random, tally: harness.Tally, count: int, folder: Path
) -> None:
    """``count`` hostile sessions, alternately over TCP and UDP, each followed by a valid sender."""
    recording = read_recording(seeds.recordings[0])
    from echoloc.realtime.protocol import session_record

    record = session_record(recording)
    owner = [session_message(record, recording), *valid_frames(recording)[:1]]
    streams = {transport: StreamUnderTest(transport, folder) for transport in ("tcp", "udp")}
    try:
        for stream in streams.values():
            _wait_ready(stream, recording)
        for index in range(count):
            transport = ("tcp", "udp")[index % 2]
            stream = streams[transport]
            messages, what = hostile_messages(rng, recording, record)
            start = time.monotonic()
            marker = 1000.0 + index * 10.0
            times = [marker + 0.01 * i for i in range(N_VALID_FRAMES)]
            valid = replace(recording, frame_times_s=np.asarray(times))
            served, confirmed = False, transport == "udp"  # UDP cannot confirm (STREAM_PROTOCOL.md)
            problem = "the valid sender after it was not fully processed"
            with _hostile_peer(stream, messages, owner, rng) as note:
                try:
                    report = send_recording(valid, stream.endpoint, speed=0)
                    confirmed = confirmed or report.confirmed is True
                except Exception as error:
                    problem = f"the valid sender after it failed: {error}"
                deadline = time.monotonic() + harness.HANG_S
                while time.monotonic() < deadline and stream.process.poll() is None:
                    if stream.has_all(times):
                        served = confirmed
                        if not confirmed:
                            problem = "the valid sender after it was processed but not confirmed"
                        break
                    time.sleep(0.005)
            alive = stream.process.poll() is None
            rss = harness.rss_bytes(stream.process.pid)
            outcome = harness.Outcome(
                exit=0 if served else (None if alive else stream.process.returncode),
                stderr="" if served else problem,
                seconds=time.monotonic() - start,
                peak_rss_bytes=rss,
                hung=alive and not served,
            )
            tally.add(f"sessions ({transport})", outcome, f"{what}{note}")
            if not alive:  # counted above; a fresh stream carries on
                stream.stop()
                streams[transport] = StreamUnderTest(transport, folder)
                _wait_ready(streams[transport], recording)
    finally:
        for transport, stream in streams.items():
            stream.stop()
            tally.notes[f"stream ({transport}) warning lines"] = stream.stderr_lines()
            tracebacks = stream.stderr_path.read_text(errors="replace").count("Traceback")
            tally.notes[f"stream ({transport}) tracebacks"] = tracebacks
            if tracebacks:
                tally.problems[f"sessions ({transport})", "traceback"] += tracebacks
            tally.notes[f"stream ({transport}) exit code on SIGTERM"] = stream.process.returncode


def _wait_ready(stream: StreamUnderTest, recording: Recording) -> None:
    """Send until the stream answers (its start-up imports and compiles)."""
    deadline = time.monotonic() + 600
    while time.monotonic() < deadline:
        times = [1.0 + 0.01 * i for i in range(N_VALID_FRAMES)]
        with contextlib.suppress(Exception):
            send_recording(replace(recording, frame_times_s=np.asarray(times)), stream.endpoint, speed=0)
        for _ in range(100):
            if stream.has_all(times):
                return
            time.sleep(0.1)
        if stream.process.poll() is not None:
            raise RuntimeError(f"echoloc stream exited: {stream.stderr_path.read_text()[-500:]}")
    raise RuntimeError("echoloc stream never processed a valid sender")
