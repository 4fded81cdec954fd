"""A sender of the echoloc stream protocol in plain Python, written from docs/STREAM_PROTOCOL.md only.

What a microcontroller firmware does, without echoloc, NumPy or anything but the
standard library: one session message (the head's geometry and the pulse), then a
frame message per shot with the samples of four receivers. Here the samples are
synthetic: the Barker-13 pulse (4 cycles of 50 kHz per bit) echoed by one point
reflector, with a little noise.

    echoloc stream --json &                       # in one shell
    python examples/minimal_sender.py --frames 5  # in another
"""

from __future__ import annotations

import argparse
import json
import math
import random
import socket
import struct
import time
import zlib

SAMPLE_RATE_HZ = 200_000.0
N_SAMPLES = 2400
CARRIER_HZ = 50_000.0
CYCLES_PER_BIT = 4
BARKER_13 = (1, 1, 1, 1, 1, -1, -1, 1, 1, -1, 1, -1, 1)
SPEED_OF_SOUND_M_S = 343.0
TRANSMITTER_M = (0.0, 0.0, 0.0)
RECEIVERS_M = ((0.25, 0.0, 0.0), (-0.25, 0.0, 0.0), (0.0, 0.25, 0.0), (0.0, -0.25, 0.0))

# Header: docs/STREAM_PROTOCOL.md, "Header (52 bytes, little-endian)", offsets 0..47, then the CRC.
HEADER = struct.Struct("<4sBBHIIddIHHBBHI")
KIND_SESSION, KIND_FRAME, KIND_END = 1, 2, 3
INT16, FLOAT32 = 1, 2
RF = 0


def pulse(t_s: float) -> float:
    """The emitted code at t_s after the emission started: bit * carrier, 0 outside."""
    bit_s = CYCLES_PER_BIT / CARRIER_HZ
    k = math.floor(t_s / bit_s)
    if t_s < 0 or k >= len(BARKER_13):
        return 0.0
    return BARKER_13[k] * math.sin(2 * math.pi * CARRIER_HZ * t_s)


def message(
    kind: int, payload: bytes, *, sequence: int = 0, time_s: float = math.nan, fmt: int = FLOAT32
) -> bytes:
    body = HEADER.pack(
        b"ECHL",  # magic
        1,  # version
        kind,
        52,  # header_bytes
        len(payload),
        sequence & 0xFFFFFFFF,
        time_s,
        SAMPLE_RATE_HZ if kind != KIND_END else 0.0,
        N_SAMPLES if kind != KIND_END else 0,
        len(RECEIVERS_M) if kind != KIND_END else 0,
        0,  # transmitter
        fmt if kind != KIND_END else 0,
        RF,
        1,  # flags: payload CRC present
        zlib.crc32(payload),
    )
    return body + struct.pack("<I", zlib.crc32(body)) + payload


def session() -> bytes:
    n_w = round(len(BARKER_13) * CYCLES_PER_BIT / CARRIER_HZ * SAMPLE_RATE_HZ)
    record = {
        "format": "echoloc-recording",
        "version": 1,
        "sample_rate_hz": SAMPLE_RATE_HZ,
        "signal_kind": "rf",
        "carrier_hz": CARRIER_HZ,
        "speed_of_sound_m_s": SPEED_OF_SOUND_M_S,
        "transmitters": [list(TRANSMITTER_M)],
        "receivers": [list(r) for r in RECEIVERS_M],
        "waveform": [pulse(k / SAMPLE_RATE_HZ) for k in range(n_w)],
    }
    return message(KIND_SESSION, json.dumps(record).encode())


def frame(sequence: int, reflector_m: tuple[float, float, float], noise: float, rng: random.Random) -> bytes:
    """Samples of every receiver, channel after channel, as int16 ADC counts (full scale 1 = 8000)."""
    samples = []
    for receiver in RECEIVERS_M:
        path_m = math.dist(TRANSMITTER_M, reflector_m) + math.dist(reflector_m, receiver)
        delay_s = path_m / SPEED_OF_SOUND_M_S
        for k in range(N_SAMPLES):
            value = 0.5 * pulse(k / SAMPLE_RATE_HZ - delay_s) + rng.gauss(0.0, noise)
            samples.append(max(-32768, min(32767, round(8000 * value))))
    payload = struct.pack(f"<{len(samples)}h", *samples)
    return message(KIND_FRAME, payload, sequence=sequence, time_s=sequence * 0.012, fmt=INT16)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--to", default="127.0.0.1:7447", help="HOST:PORT of echoloc stream / record.")
    parser.add_argument("--udp", action="store_true")
    parser.add_argument("--frames", type=int, default=5)
    parser.add_argument("--rate", type=float, default=50.0, help="Frames per second.")
    parser.add_argument("--reflector", type=float, nargs=3, default=(0.05, -0.03, 0.6), help="x y z, m.")
    parser.add_argument("--noise", type=float, default=0.01, help="Noise std, in units of full scale.")
    args = parser.parse_args()
    host, port = args.to.rsplit(":", 1)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM if args.udp else socket.SOCK_STREAM)
    sock.connect((host, int(port)))
    rng = random.Random(1)
    sock.sendall(session())
    for k in range(args.frames):
        sock.sendall(frame(k, tuple(args.reflector), args.noise, rng))
        time.sleep(1 / args.rate)
    sock.sendall(message(KIND_END, b"", sequence=args.frames))
    sock.close()


if __name__ == "__main__":
    main()
