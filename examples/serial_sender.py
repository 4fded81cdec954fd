"""A board on a serial port, in Python: frames of a head in the serial framing (docs/SERIAL_PROTOCOL.md).

A stand-in for a microcontroller's firmware. It reads a head file, takes its frames from a
recording of that head or simulates them (the head's geometry and pulse, point reflectors,
noise), turns them into the head's ADC counts, and writes them, at the head's frame rate, in
the serial framing: the 28-byte header, the counts, the CRC-32 of the counts. The framing is
written with ``struct`` and ``zlib`` only, from the protocol page, as firmware would write it;
echoloc only reads the head and makes the samples.

It writes to a port pyserial opens (``--port /dev/ttyUSB1``, ``socket://HOST:PORT``), or, with
``--pty``, to a pseudo-terminal it creates: a serial port without hardware.

    python examples/serial_sender.py --head examples/heads/mcu-4ch.toml --pty
    # prints /dev/pts/N, and waits for a reader; in another shell:
    echoloc stream --source serial:/dev/pts/N --head examples/heads/mcu-4ch.toml

Like a board, it numbers every frame it captures: a frame it cannot send in time (the port
is slower than the head fires, or ``--drop-every``) leaves a gap the reader counts as lost.
Timestamps are microseconds of this machine's monotonic clock at each frame's due time (a
board's clock since it started). When it ends it prints one JSON line on stdout: frames
sent, sequence numbers skipped, bytes written.
"""

from __future__ import annotations

import argparse
import array
import fcntl
import json
import os
import select
import struct
import sys
import termios
import time
import tty
import zlib
from collections.abc import Callable
from typing import Any

import numpy as np

from echoloc.io.head import SensorHead, load_head

# docs/SERIAL_PROTOCOL.md, "Header": sync, version, format, n_channels, values_per_channel,
# transmitter, flags, sequence, timestamp_us (24 bytes), then the CRC-32 of those 24 bytes.
HEADER = struct.Struct("<4sBBHHBBIQ")
FORMAT_CODES = {"int16": 1, "float32": 2, "uint16": 5, "int32": 6}
FLAG_TIME32 = 0x01

DEFAULT_REFLECTORS = ((0.10, 0.05, 0.80), (-0.20, 0.10, 1.30))


def head_frames(head: SensorHead, args: argparse.Namespace) -> tuple[list[np.ndarray], list[int]]:
    """The counts of each frame to send, (n_channels, values_per_channel) in the head's ADC
    format, and the transmitter each fires: from ``--recording``, or simulated."""
    if args.recording is not None:
        from echoloc.io.recording import read_recording

        recording = read_recording(args.recording)
        if recording.frames.shape[1:] != head.header.frames.shape[1:]:
            sys.exit(
                f"{args.recording}: frames of {recording.frames.shape[1:]}, the head has "
                f"{head.header.frames.shape[1:]} (receivers x samples)"
            )
        fired = recording.frame_transmitter
        transmitters = [0 if fired is None else int(t) for t in fired]
        return [head.counts(frame) for frame in recording.frames], transmitters
    from echoloc.sim.simulation import simulate

    reflectors = args.reflector or DEFAULT_REFLECTORS
    scene = head.scene(
        {
            "seed": args.seed,
            "noise": {"snr_db": args.snr_db},
            "reflectors": [{"position_m": list(p), "strength": args.strength} for p in reflectors],
        }
    )
    recording = simulate(scene, args.sim_frames)
    fired = recording.frame_transmitter
    transmitters = [0 if fired is None else int(t) for t in fired]
    return [head.counts(frame) for frame in recording.frames], transmitters


def frame_header(
    counts: np.ndarray, sequence: int, timestamp_us: int, transmitter: int, time32: bool
) -> bytes:
    """The header of one frame, its CRC-32 included: the counts and their CRC-32 follow it."""
    header = HEADER.pack(
        b"ECHS",
        1,  # version
        FORMAT_CODES[counts.dtype.name],
        counts.shape[0],  # n_channels
        counts.shape[1],  # values_per_channel
        transmitter,
        FLAG_TIME32 if time32 else 0,
        sequence & 0xFFFFFFFF,
        timestamp_us & 0xFFFFFFFF if time32 else timestamp_us,
    )
    return header + struct.pack("<I", zlib.crc32(header))


class Pty:
    """A pseudo-terminal: its slave is the port a reader opens; this writes to the master."""

    def __init__(self) -> None:
        self.master, slave = os.openpty()
        tty.setraw(slave)  # no line discipline: bytes go through as they are
        self.path = os.ttyname(slave)
        os.close(slave)  # until a reader opens it, the master hangs up (POLLHUP)
        os.set_blocking(self.master, False)

    def has_reader(self) -> bool:
        poller = select.poll()
        poller.register(self.master, select.POLLOUT)
        return not any(event & select.POLLHUP for _, event in poller.poll(0))

    def wait_for_reader(self, stop_at: float) -> bool:
        while not self.has_reader():
            if time.monotonic() >= stop_at:
                return False
            time.sleep(0.05)
        time.sleep(0.2)  # the reader sets the port up (pyserial flushes its input as it opens)
        return True

    def write(self, data: bytes) -> bool:
        """Write all of ``data``; False if the reader went away first."""
        view = memoryview(data)
        poller = select.poll()
        poller.register(self.master, select.POLLOUT)
        while view:
            events = poller.poll(100)
            if any(event & select.POLLHUP for _, event in events):
                return False
            try:
                view = view[os.write(self.master, view) :]
            except BlockingIOError:
                continue
        return True

    def close(self) -> None:
        """Close once the reader has read what was written (closing the master hangs the port
        up: what the reader has not read yet would be lost)."""
        if self.has_reader():
            unread = array.array("i", [1])
            slave = os.open(self.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
            deadline = time.monotonic() + 2.0
            while unread[0] and time.monotonic() < deadline:
                fcntl.ioctl(slave, termios.FIONREAD, unread)  # bytes the reader has yet to read
                time.sleep(0.01)
            os.close(slave)
        os.close(self.master)


def open_port(args: argparse.Namespace) -> tuple[Callable[[bytes], bool], Any]:
    if args.pty:
        pty = Pty()
        print(pty.path, flush=True)
        print(
            f"serial_sender: writing to {pty.path}; read it with: echoloc stream --source "
            f"serial:{pty.path} --head {args.head}",
            file=sys.stderr,
            flush=True,
        )
        return pty.write, pty
    import serial  # pyserial: pip install 'echoloc[serial]'

    port = serial.serial_for_url(args.port, baudrate=args.baud)

    def write(data: bytes) -> bool:
        port.write(data)
        return True

    return write, port


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--head", required=True, help="The head file (TOML) of the board.")
    where = parser.add_mutually_exclusive_group(required=True)
    where.add_argument("--port", help="A port as pyserial opens it: /dev/ttyUSB1, socket://HOST:PORT, ...")
    where.add_argument("--pty", action="store_true", help="Create a pseudo-terminal; print its path.")
    parser.add_argument("--baud", type=int, default=2_000_000, help="--port's rate (USB-CDC ignores it).")
    parser.add_argument(
        "--recording", help="Send this recording's frames (of the head) instead of simulating."
    )
    parser.add_argument(
        "--reflector", type=float, nargs=3, action="append", metavar=("X", "Y", "Z"), help="m; repeat."
    )
    parser.add_argument("--strength", type=float, default=0.4, help="Of each simulated reflector.")
    parser.add_argument("--snr-db", type=float, default=20.0, help="Of the simulation's noise.")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--sim-frames", type=int, default=50, help="Frames simulated, then sent in a loop.")
    parser.add_argument("--rate", type=float, default=None, help="Frames per second (the head's by default).")
    parser.add_argument("--frames", type=int, default=0, help="Stop after this many frames (0: no limit).")
    parser.add_argument(
        "--seconds", type=float, default=0.0, help="Stop this long after the first frame (0: no limit)."
    )
    parser.add_argument("--first-sequence", type=int, default=0)
    parser.add_argument(
        "--drop-every", type=int, default=0, help="Skip every Nth frame (a gap the reader counts lost)."
    )
    parser.add_argument("--time32", action="store_true", help="Stamp with a 32-bit microsecond counter.")
    args = parser.parse_args()

    head = load_head(args.head)
    frames, transmitters = head_frames(head, args)
    payloads = [
        (counts, counts.tobytes(), struct.pack("<I", zlib.crc32(counts.tobytes()))) for counts in frames
    ]
    rate = args.rate or head.frame_rate_hz
    write, port = open_port(args)
    if args.pty:
        port.wait_for_reader(float("inf"))
    sent = skipped = written = 0
    k = 0  # frames captured: the sequence number counts every one, sent or not
    t0 = time.monotonic()
    stop_at = t0 + args.seconds if args.seconds > 0 else float("inf")
    try:
        while (args.frames <= 0 or sent < args.frames) and time.monotonic() < stop_at:
            sequence, due = args.first_sequence + k, t0 + k / rate
            k += 1
            now = time.monotonic()
            if now < due:
                time.sleep(due - now)
            elif now - due > 1 / rate:  # a whole frame late: the ADC overwrote this capture
                skipped += 1
                continue
            if args.drop_every and k % args.drop_every == 0:
                skipped += 1
                continue
            counts, payload, payload_crc = payloads[(k - 1) % len(payloads)]
            transmitter = transmitters[(k - 1) % len(transmitters)]
            header = frame_header(counts, sequence, round(due * 1e6), transmitter, args.time32)
            if not write(header + payload + payload_crc):
                print("serial_sender: the reader closed the port; waiting for another", file=sys.stderr)
                if not port.wait_for_reader(stop_at):
                    break
                continue
            sent += 1
            written += len(header) + len(payload) + len(payload_crc)
    except KeyboardInterrupt:
        pass
    finally:
        elapsed = time.monotonic() - t0
        print(
            json.dumps(
                {
                    "sent": sent,
                    "skipped": skipped,
                    "first_sequence": args.first_sequence,
                    "next_sequence": args.first_sequence + k,
                    "bytes": written,
                    "seconds": round(elapsed, 3),
                }
            ),
            flush=True,
        )
        print(
            f"serial_sender: sent {sent} frames ({written / max(elapsed, 1e-9) / 1e6:.2f} MB/s), "
            f"skipped {skipped}",
            file=sys.stderr,
        )
        port.close()


if __name__ == "__main__":
    main()
