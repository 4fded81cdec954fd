"""A serial line at 1.9 MB/s: the mcu-4ch head's frames over a pty, through the serial source and the chain.

``examples/serial_sender.py --pty`` (its own process, as a board is its own machine)
simulates the head ``examples/heads/mcu-4ch.toml`` (4 channels x 2400 uint16 counts at 100
frames/s: 19 232 bytes a frame in the serial framing, 1.92 MB/s) and writes its frames to a
pseudo-terminal at the head's rate. This process reads the pty with
:class:`echoloc.realtime.serial_source.SerialSource` (queue of 64 frames, oldest dropped when
full) and runs `echoloc stream`'s :class:`~echoloc.realtime.session.LiveSession` on everything it
queues, the chain prepared as the session is offered (``accept_session``), as `stream` does.

Every ``--window-s`` it notes the frames received and processed, those lost (sequence gaps),
duplicated or out of order, malformed and rejected, and two latencies of the window:

- *processing*: from a frame's complete arrival (when the source hands it on, ``_deliver``) to
  the end of its processing through the chain: :class:`~echoloc.realtime.stream.StreamProcessor`'s
  figure, the one `echoloc stream` reports;
- *transit*: from the frame's due time on the sender (its timestamp: the sender stamps this
  machine's monotonic clock, the one the reader reads) to its arrival: the time to write
  19 kB through the pty, read and check it.

At the end it accounts for every frame: sent by the sender = received + lost on the line, and
received = processed + dropped.

    python benchmarks/serial_pty.py --seconds 600 --markdown benchmarks/results/serial_pty.md
"""

from __future__ import annotations

import argparse
import json
import math
import os
import resource
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from echoloc.io.head import load_head
from echoloc.pipeline import prepare
from echoloc.realtime.serial_source import SerialSource
from echoloc.realtime.session import LiveSession, listener_events
from echoloc.realtime.stream import FrameQueue, LatencyHistogram, StreamFrame, StreamResult, warm_kernels
from echoloc.realtime.transport import SessionEvent

REPO = Path(__file__).resolve().parents[1]
HEAD = REPO / "examples" / "heads" / "mcu-4ch.toml"
SENDER = REPO / "examples" / "serial_sender.py"


def cpu_s() -> float:
    """CPU time this process has used (user + system), s."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


def ms(value: float) -> str:
    return "-" if math.isnan(value) else f"{value * 1e3:.2f}"


class Windows:
    """The rows of the report: one every ``window_s`` of the stream."""

    def __init__(self, source: SerialSource, session: LiveSession, window_s: float) -> None:
        self.source = source
        self.session = session
        self.window_s = window_s
        self.latency = LatencyHistogram()
        self.transit = LatencyHistogram()
        self.all_transit = LatencyHistogram()
        self.start = time.monotonic()
        self.next_note = self.start + window_s
        self.cpu = cpu_s()
        self.last = {"received": 0, "processed": 0}
        self.rows = [
            "| t min | received/s | processed/s | lost (total) | duplicated or out of order | malformed "
            "| dropped | latency p50 ms | latency p99 ms | transit p50 ms | transit p99 ms | CPU % |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|",
        ]

    def result(self, frame: StreamFrame, result: StreamResult) -> None:
        self.latency.add(result.latency_s)
        transit = frame.arrival_s - frame.time_s
        self.transit.add(transit)
        self.all_transit.add(transit)

    def note(self, force: bool = False) -> None:
        now = time.monotonic()
        if (now < self.next_note and not force) or self.session.processor is None:
            return
        span = now - (self.next_note - self.window_s)
        counters = {**self.source.counters(), "processed": self.session.processor.processed}
        rate = {k: (counters[k] - self.last[k]) / span for k in self.last}
        cpu = cpu_s()
        self.rows.append(
            f"| {(now - self.start) / 60:.1f} | {rate['received']:.1f} | {rate['processed']:.1f} | "
            f"{counters['lost']} | {counters['out_of_order']} | {counters['malformed']} | "
            f"{counters['dropped']} | {ms(self.latency.quantile(0.5))} | {ms(self.latency.quantile(0.99))} | "
            f"{ms(self.transit.quantile(0.5))} | {ms(self.transit.quantile(0.99))} | "
            f"{100 * (cpu - self.cpu) / span:.1f} |"
        )
        print(self.rows[-1], flush=True)
        self.last = {k: counters[k] for k in self.last}
        self.latency.reset()
        self.transit.reset()
        self.cpu = cpu
        self.next_note = now + self.window_s


def run(seconds: float, window_s: float, sim_frames: int) -> list[str]:
    """Stream for ``seconds``; the Markdown lines of the report."""
    head = load_head(HEAD)
    load_before = os.getloadavg()[0]
    command = [
        sys.executable,
        str(SENDER),
        "--head",
        str(HEAD),
        "--pty",
        "--seconds",
        str(seconds),
        "--sim-frames",
        str(sim_frames),
    ]
    sender = subprocess.Popen(command, stdout=subprocess.PIPE, text=True)
    assert sender.stdout is not None
    path = sender.stdout.readline().strip()
    source = SerialSource(head, FrameQueue(64), path, accept_session=prepare)
    session = LiveSession(source, prepare, 0.1)  # --deadline-ms 100, stream's default
    windows = Windows(source, session, window_s)
    session.on_result = windows.result
    errors: list[str] = []
    warm_kernels()  # as `echoloc stream` does before it starts its source
    started = time.monotonic()
    cpu_start = cpu_s()
    try:
        source.start()
        # once: until the sender's end hangs the pty up (after the reader has read every byte)
        for item in listener_events(
            source, once=True, deadline_s=started + seconds + 30, on_error=errors.append
        ):
            session.handle(item)
            if isinstance(item, SessionEvent):
                windows = Windows(source, session, window_s)  # the clock starts with the stream
                session.on_result = windows.result
            windows.note()
        windows.note(force=True)
        summary: dict[str, Any] = json.loads(sender.stdout.readline() or "{}")
    finally:
        source.stop()
        sender.wait(30)
        sender.stdout.close()
    elapsed = time.monotonic() - started
    cpu = cpu_s() - cpu_start
    errors += list(source.errors())
    stats = session.stats()
    unprocessed = stats.received - stats.processed - stats.dropped
    sent = summary.get("sent", 0)
    on_the_line = stats.received + stats.lost
    mb_s = summary.get("bytes", 0) / max(summary.get("seconds", elapsed), 1e-9) / 1e6
    lines = [
        f"{seconds:g} s of the head {head.name} ({head.n_channels} channels x {head.values_per_channel} "
        f"{head.adc.format} at {head.frame_rate_hz:g} frames/s: {head.frame_bytes() + 32} bytes a frame "
        f"framed) over a pty; load average {load_before:.2f} at the start, {os.getloadavg()[0]:.2f} at the "
        f"end, {os.cpu_count()} cores.",
        "",
        *windows.rows,
        "",
        f"Sender: sent {sent} frames, skipped {summary.get('skipped', 0)} (a whole frame late: the "
        f"board's overruns), {mb_s:.2f} MB/s.",
        f"Reader: {stats.summary()}; {source.bytes_skipped} bytes skipped; transit p50 "
        f"{ms(windows.all_transit.quantile(0.5))} ms, p99 {ms(windows.all_transit.quantile(0.99))} ms, max "
        f"{ms(windows.all_transit.max_s)} ms; this process used {100 * cpu / elapsed:.1f} % of a core "
        "(reader thread, chain and all).",
        f"Every frame accounted for: sent {sent} + skipped {summary.get('skipped', 0)} = received "
        f"{stats.received} + lost {stats.lost}"
        + (" (exactly)" if sent + summary.get("skipped", 0) == on_the_line else " (NOT equal)")
        + f"; received = processed {stats.processed} + dropped {stats.dropped}"
        + (" (exactly)." if unprocessed == 0 else f" + {unprocessed} unprocessed."),
    ]
    if errors:
        lines += ["", "Warnings of the source:", "", *(f"    {line}" for line in errors)]
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=600.0)
    parser.add_argument("--window-s", type=float, default=60.0, help="Seconds per row.")
    parser.add_argument("--sim-frames", type=int, default=100, help="Distinct frames the sender loops.")
    parser.add_argument("--markdown", type=Path, default=None, help="Also write the report here.")
    args = parser.parse_args()
    lines = run(args.seconds, args.window_s, args.sim_frames)
    report = [
        "# serial_pty.py — last run",
        "",
        f"`python benchmarks/serial_pty.py --seconds {args.seconds:g}` ({time.strftime('%Y-%m-%d %H:%M')})",
        "",
        *lines,
        "",
    ]
    print("\n".join(report[-8:]), flush=True)
    if args.markdown is not None:
        args.markdown.write_text("\n".join(report))


if __name__ == "__main__":
    main()
