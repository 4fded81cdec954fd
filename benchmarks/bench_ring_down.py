"""`echoloc stream` on a ringing head, as a user runs it: latency with and without --blind-zone auto.

A head whose transmitter rings for about a millisecond shows some 14 echoes a channel
that are no reflector. The script simulates such a head (examples/heads/mcu-4ch.toml with
three points and a ring-down), writes the recording, and for each set of options starts
`echoloc stream --head HEAD.toml --json` and replays the recording to it at its own pace
(`echoloc send --speed 1`, 100 frames/s), then reads the stream's final line: frames
received, processed, dropped, late, and the latency p50/p99 from each frame's arrival.
Both runs go side by side in one invocation (the machine is shared: read them together).

    python benchmarks/bench_ring_down.py --frames 3000
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from pathlib import Path

from echoloc.io.head import load_head
from echoloc.io.recording import write_recording
from echoloc.sim.simulation import simulate

ROOT = Path(__file__).resolve().parents[1]
HEAD = ROOT / "examples" / "heads" / "mcu-4ch.toml"
RESULTS = Path(__file__).parent / "results" / "ring_down.md"
ECHOLOC = str(Path(sys.executable).with_name("echoloc"))
RINGING = {
    "reflectors": [
        {"position_m": [0.1, 0.05, 0.7]},
        {"position_m": [-0.2, 0.0, 1.1]},
        {"position_m": [0.3, -0.1, 0.5]},
    ],
    "ring_down": {"level": 3.0, "decay_s": 5e-4, "direct_path": True},
    "noise": {"snr_db": 20.0},
    "seed": 3,
}
"""The ringing head's scene: the ring-down leaves about 14 echoes a channel without a blind zone."""


def stream_run(recording: Path, options: list[str], duration_s: float) -> str:
    """Stream ``recording`` at its own pace through `echoloc stream` with ``options``; its last line."""
    stream = subprocess.Popen(
        [
            ECHOLOC,
            "stream",
            "--listen",
            "127.0.0.1:0",
            "--once",
            "--json",
            "--head",
            str(HEAD),
            *options,
            "--duration",
            str(duration_s),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert stream.stderr is not None
    lines = []
    for line in stream.stderr:
        lines.append(line.rstrip())
        found = re.search(r"listening on tcp://127\.0\.0\.1:(\d+)", line)
        if found:
            break
    else:
        raise SystemExit("stream did not start: " + "\n".join(lines))
    port = found.group(1)
    subprocess.run(
        [ECHOLOC, "send", str(recording), "--to", f"127.0.0.1:{port}", "--speed", "1"],
        check=True,
        capture_output=True,
        timeout=duration_s + 60,
    )
    rest = stream.stderr.read()
    stream.wait(timeout=120)
    return [line for line in (lines + rest.splitlines()) if "latency p50" in line][-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3000, help="Frames replayed (100 a second).")
    parser.add_argument("--without-frames", type=int, default=300, help="Frames without a blind zone.")
    args = parser.parse_args()
    head = load_head(HEAD)
    with tempfile.TemporaryDirectory() as folder:
        full = Path(folder) / "ringing.h5"
        short = Path(folder) / "ringing-short.h5"
        recording = simulate(head.scene(RINGING), args.frames)
        write_recording(recording, full)
        write_recording(simulate(head.scene(RINGING), args.without_frames), short)
        rows = []
        for name, path, options, frames in (
            ("--blind-zone auto", full, ["--blind-zone", "auto"], args.frames),
            ("no blind zone", short, [], args.without_frames),
        ):
            start = time.perf_counter()
            line = stream_run(path, options, frames / head.frame_rate_hz + 30)
            rows.append((name, frames, line, time.perf_counter() - start))
    stamp = datetime.now().strftime("%Y-%m-%d, %H:%M")
    text = [
        f"## Ringing head, `echoloc stream --head mcu-4ch.toml` ({stamp})",
        "",
        f"`python benchmarks/bench_ring_down.py --frames {args.frames} --without-frames "
        f"{args.without_frames}`: the head of examples/heads/mcu-4ch.toml with three points and a "
        "ring-down (level 3, decay 0.5 ms: about 14 echoes a channel without a blind zone), "
        "replayed at 100 frames/s over TCP on loopback, both runs in one invocation.",
        "",
    ]
    for name, frames, line, wall in rows:
        text.append(f"- {name}, {frames} frames sent ({wall:.0f} s): {line.split('stream: ')[-1]}")
    report = "\n".join(text) + "\n"
    print(report)
    old = RESULTS.read_text() if RESULTS.exists() else "# bench_ring_down.py — runs, newest first\n\n"
    head_line, _, rest = old.partition("\n\n")
    RESULTS.write_text(head_line + "\n\n" + report + "\n" + rest)


if __name__ == "__main__":
    main()
