"""The streaming processor: frames in, echoes and objects out, with bounded memory.

A stream reuses one :class:`~echoloc.pipeline.Chain` (:func:`echoloc.pipeline.prepare`:
template spectra, FFT plans, tables, localisation options) for every frame, and the
same per-frame functions as the batch chain (:func:`echoloc.pipeline.samples_results_batch`,
or with transmitters combined :func:`~echoloc.pipeline.samples_echoes_batch` and
:func:`~echoloc.pipeline.combine_latest`), so a recording streamed gives exactly what
``echoloc locate`` gives.

What a live stream adds, and this module holds:

- :class:`SequenceTracker`: frame numbers from the wire's 32-bit sequence numbers,
  counting frames lost on the way (gaps) and those that arrive out of order;
- :class:`FrameQueue`: a bounded queue between the socket and the processor, which
  drops the *oldest* frame when full (a robot wants the freshest echoes) and
  counts it, or blocks the producer (back-pressure, for replaying a file);
- :class:`LatencyHistogram`: p50/p99 of latency in constant memory;
- :class:`StreamProcessor`: the chain with its state (the latest echoes of each
  transmitter fired in turn) and its counters, frame by frame or in batches.

Nothing here grows with the length of a stream.
"""

from __future__ import annotations

import contextlib
import math
import threading
import time
from collections import deque
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording
from echoloc.localise.locate import FrameObjects, model_paths_m
from echoloc.pipeline import (
    Chain,
    combine_latest,
    combines_transmitters,
    prepare,
    samples_echoes,
    samples_echoes_batch,
    samples_results_batch,
)
from echoloc.sim.scene import default_scene
from echoloc.sim.simulation import recording_header
from echoloc.tof.echoes import EchoOptions, FrameEchoes, frame_time_s

Samples = NDArray[np.floating] | NDArray[np.complexfloating]


@dataclass(frozen=True, eq=False)
class StreamFrame:
    """One frame entering the processor.

    Attributes
    ----------
    index
        Frame number (the unwrapped wire sequence number, or the index in a file).
    samples
        (n_rx, n_samples).
    time_s
        Start of the frame's emission, s.
    transmitter
        Index of the transmitter fired.
    arrival_s
        ``time.monotonic()`` when the frame arrived (latency is measured from it).
    """

    index: int
    samples: Samples
    time_s: float
    transmitter: int = 0
    arrival_s: float = math.nan


@dataclass(frozen=True, eq=False)
class StreamResult:
    """What the processor made of one frame."""

    echoes: FrameEchoes
    objects: FrameObjects
    transmitter: int
    latency_s: float
    late: bool


@dataclass(frozen=True)
class StreamStats:
    """Counters of a stream, a snapshot.

    Attributes
    ----------
    received
        Frames that arrived intact (after decoding).
    processed
        Frames turned into results.
    lost
        Frames missing from the sequence numbers (lost on the network, or never sent).
    dropped
        Frames that arrived but were dropped because the queue was full.
    late
        Processed frames older than the deadline when their processing started.
    out_of_order
        Frames whose sequence number was older than one already seen (discarded).
    malformed
        Messages refused by the protocol decoder (bad CRC, sizes, garbage bytes).
    rejected
        Well-formed frames that do not fit the session (channels, samples, rate), or
        that came before any session.
    unprocessed
        Frames received but not processed when the stream stopped: still queued, or in a
        batch that an interrupt cut short (``echoloc stream`` counts them as it ends, so that
        received = processed + dropped + unprocessed; 0 while it runs).
    refused
        Sessions refused (malformed, over the size limits, or a chain that cannot use
        them), and connections the receiver closed (too many, idle).
    restarts
        Times a sender's frame numbering started afresh mid-session (a UDP sender that
        started again).
    xruns
        Breaks in a sound card's sample stream (PortAudio's over- and underflows); the frames
        a break cut are counted lost.
    latency_p50_s, latency_p99_s, latency_max_s
        From arrival to result, s (NaN before the first frame).
    """

    received: int = 0
    processed: int = 0
    lost: int = 0
    dropped: int = 0
    late: int = 0
    out_of_order: int = 0
    malformed: int = 0
    rejected: int = 0
    unprocessed: int = 0
    refused: int = 0
    restarts: int = 0
    xruns: int = 0
    latency_p50_s: float = math.nan
    latency_p99_s: float = math.nan
    latency_max_s: float = math.nan

    def record(self) -> dict[str, Any]:
        """The counters as a JSON object (latencies in ms, null before the first frame)."""

        def ms(value: float) -> float | None:
            return None if math.isnan(value) else round(value * 1e3, 4)

        return {
            "received": self.received,
            "processed": self.processed,
            "lost": self.lost,
            "dropped": self.dropped,
            "late": self.late,
            "out_of_order": self.out_of_order,
            "malformed": self.malformed,
            "rejected": self.rejected,
            "unprocessed": self.unprocessed,
            "refused": self.refused,
            "restarts": self.restarts,
            "xruns": self.xruns,
            "latency_p50_ms": ms(self.latency_p50_s),
            "latency_p99_ms": ms(self.latency_p99_s),
            "latency_max_ms": ms(self.latency_max_s),
        }

    def summary(self) -> str:
        """One line for a person."""
        r = self.record()

        def fmt(v: float | None) -> str:
            return "-" if v is None else f"{v:.3f}"

        unprocessed = f", unprocessed {self.unprocessed}" if self.unprocessed else ""
        return (
            f"received {self.received}, processed {self.processed}, lost {self.lost}, "
            f"dropped {self.dropped}{unprocessed}, late {self.late}, out of order {self.out_of_order}, "
            f"malformed {self.malformed}, rejected {self.rejected}"
            f"{rare_counts(refused=self.refused, restarts=self.restarts, xruns=self.xruns)}; latency p50 "
            f"{fmt(r['latency_p50_ms'])} ms, p99 {fmt(r['latency_p99_ms'])} ms, "
            f"max {fmt(r['latency_max_ms'])} ms"
        )


def rare_counts(**counts: int) -> str:
    """``", refused 2, restarts 1"``: the counters given, each only when it is not 0 (most streams
    never see them), for the summary lines of `echoloc stream` and `echoloc record`."""
    return "".join(f", {name} {count}" for name, count in counts.items() if count)


class LatencyHistogram:
    """Quantiles of positive durations in constant memory: log-spaced bins, 1 % wide.

    Bins cover 100 ns to 1000 s; a quantile is the geometric centre of its bin, so it is
    within 0.5 % of the exact order statistic for values in that range (values outside are
    counted in the end bins), and never outside the smallest and largest value counted (a
    bin's centre can lie beyond them: a p99 above the maximum). Memory: about 2300 counters
    (18 kB), whatever the stream's length.
    """

    LOW_S = 1e-7
    HIGH_S = 1e3
    GROWTH = 1.01

    def __init__(self) -> None:
        self._log_growth = math.log(self.GROWTH)
        self._n = math.ceil(math.log(self.HIGH_S / self.LOW_S) / self._log_growth) + 1
        # A list: incrementing one element of a list costs less than of a NumPy array.
        self._counts = [0] * self._n
        self.count = 0
        self.min_s = math.nan
        self.max_s = math.nan

    def add(self, value_s: float) -> None:
        """Count one duration, s."""
        if not math.isfinite(value_s):
            return
        ratio = max(value_s, self.LOW_S) / self.LOW_S
        self._counts[min(self._n - 1, int(math.log(ratio) / self._log_growth))] += 1
        self.count += 1
        if not value_s <= self.max_s:  # also the first value: NaN compares False
            self.max_s = value_s
        if not value_s >= self.min_s:
            self.min_s = value_s

    def quantile(self, q: float) -> float:
        """The ``q`` quantile (0..1), s; NaN when empty."""
        if self.count == 0:
            return math.nan
        rank = max(1, math.ceil(q * self.count))
        k = int(np.searchsorted(np.cumsum(self._counts), rank))
        centre = self.LOW_S * self.GROWTH ** (k + 0.5)
        return float(min(max(centre, self.min_s), self.max_s))

    def reset(self) -> None:
        """Forget every value (for a window of the stream)."""
        self._counts = [0] * self._n
        self.count = 0
        self.min_s = math.nan
        self.max_s = math.nan


class SequenceTracker:
    """Frame numbers from 32-bit wrapping sequence numbers, with gaps, disorder and restarts counted.

    The first sequence number seen becomes frame number ``sequence`` (so a file sent
    from its frame 0 keeps its frame numbers). As RTP receivers do (RFC 3550, A.1):

    - a jump forward of less than ``max_dropout`` counts the frames between as lost;
    - a frame at most ``max_misorder`` behind the newest is an old frame arriving late
      (reordered or duplicated): refused, counted out of order (results go out in frame
      order);
    - any other jump is believed only when the next frame follows it. Until then the frame
      is refused and counted out of order, so one forged or corrupted sequence number costs
      one frame, never 2^31 lost ones. Once it is confirmed:

      - a jump forward (less than 2^31 ahead) is an outage: the numbering goes on, and the
        frames of the gap, with the one that waited for confirmation, are counted lost (a
        30 s outage at 100 Hz is 3000 frames lost, never none);
      - a jump back is a new numbering (a sender that started again): it starts afresh
        there, counted in ``restarts``.

      A sender that starts again numbers from lower down, or announces its next sequence
      number in its session (:meth:`follows`, :meth:`restart`).
    """

    def __init__(self, *, max_dropout: int = 3000, max_misorder: int = 100) -> None:
        if not (0 < max_dropout < 1 << 31 and 0 < max_misorder < 1 << 31):
            raise EchoLocError(
                f"max_dropout and max_misorder must be in 1..2^31-1, got {max_dropout}, {max_misorder}"
            )
        self.max_dropout = max_dropout
        self.max_misorder = max_misorder
        self.next: int | None = None
        self.lost = 0
        self.out_of_order = 0
        self.restarts = 0
        self._probation: int | None = None  # the sequence number that would confirm a new numbering

    def observe(self, sequence: int) -> int | None:
        """The frame number of ``sequence``, or None for a frame refused (late, or off the numbering)."""
        sequence &= 0xFFFFFFFF
        if self.next is None:
            self.next = sequence + 1
            self._probation = None
            return sequence
        gap = (sequence - self.next) & 0xFFFFFFFF
        if gap < self.max_dropout:
            self._probation = None
            self.lost += gap
            number = self.next + gap
            self.next = number + 1
            return number
        if gap >= (1 << 32) - self.max_misorder:
            self.out_of_order += 1
            return None
        if sequence == self._probation:  # two in a row off the old numbering: confirmed
            self._probation = None
            if gap - 1 < 1 << 31:  # forward, from the frame that waited: an outage
                self.out_of_order -= 1  # that frame was refused: lost with those of the gap
                self.lost += gap
                number = self.next + gap
                self.next = number + 1
                return number
            self.restarts += 1  # back: the sender started again
            self.next = sequence + 1
            return sequence
        self._probation = (sequence + 1) & 0xFFFFFFFF
        self.out_of_order += 1
        return None

    def restart(self, next_sequence: int | None = None, *, counted: bool = False) -> None:
        """A new session (or a new connection): numbering starts afresh, at ``next_sequence``
        when it is known, else at the next sequence number seen. ``counted``: a restart of the
        same sender (counted in ``restarts``)."""
        self.next = None if next_sequence is None else next_sequence & 0xFFFFFFFF
        self._probation = None
        self.restarts += counted

    def follows(self, next_sequence: int) -> bool:
        """Does a sender's ``next_sequence`` (announced in its session) fit this numbering: not
        behind the next frame expected (at most 2^31 ahead: an outage, its frames counted lost
        as they come)? A sender that started again announces a number already seen."""
        if self.next is None:
            return True
        return (next_sequence - self.next) & 0xFFFFFFFF < 1 << 31


STREAM_BATCH_FRAMES = 16
"""Most frames `echoloc stream` takes off its queue at once, when a backlog has built up: in one
call the matched filter needs less time a frame, so a backlog clears sooner; a frame waits at
most for the 15 before it."""


DEFAULT_QUEUE_BYTES = 64 * 2**20
"""What the frames held in a :class:`FrameQueue` may take at most by default, bytes: the
queue is bounded in bytes as well as in frames, so frames of a large session cannot make
it grow past this (64 frames of 4 x 2400 float64 samples take 4.9 MB)."""


def _nbytes(item: object) -> int:
    return int(getattr(item.samples, "nbytes", 0)) if isinstance(item, StreamFrame) else 0


class FrameQueue:
    """A bounded, thread-safe queue of frames and control items between a socket and the processor.

    Bounded in frames (``max_frames``) and in the bytes of their samples (``max_bytes``).
    ``put`` on a full queue drops the oldest *frames* (never a control item such as a
    new session) until the new one fits, and counts them in ``dropped``; with
    ``block=True`` it waits for room instead, which on TCP pushes back on the sender.
    A frame larger than ``max_bytes`` alone is still taken into an empty queue. ``get``
    waits up to a timeout.
    """

    def __init__(self, max_frames: int, *, block: bool = False, max_bytes: int = DEFAULT_QUEUE_BYTES) -> None:
        if max_frames < 1:
            raise EchoLocError(f"the queue must hold at least 1 frame, got {max_frames}")
        if max_bytes < 1:
            raise EchoLocError(f"the queue must hold at least 1 byte, got {max_bytes}")
        self.max_frames = max_frames
        self.max_bytes = max_bytes
        self.block = block
        self.dropped = 0
        self._items: deque[object] = deque()
        self._frames = 0
        self._bytes = 0
        self._cond = threading.Condition()
        self._closed = False

    def _full(self, size: int) -> bool:
        return self._frames > 0 and (self._frames >= self.max_frames or self._bytes + size > self.max_bytes)

    def put(self, item: object) -> None:
        """Add ``item``; a :class:`StreamFrame` counts against the bounds, anything else does not."""
        is_frame = isinstance(item, StreamFrame)
        size = _nbytes(item)
        with self._cond:
            if is_frame:
                while self.block and self._full(size) and not self._closed:
                    self._cond.wait(0.1)
                while self._full(size):
                    for k, old in enumerate(self._items):
                        if isinstance(old, StreamFrame):
                            del self._items[k]
                            self._bytes -= _nbytes(old)
                            break
                    self._frames -= 1
                    self.dropped += 1
                self._frames += 1
                self._bytes += size
            self._items.append(item)
            self._cond.notify_all()

    def get(self, timeout_s: float) -> object | None:
        """The oldest item, or None after ``timeout_s`` without one."""
        with self._cond:
            if not self._items:
                self._cond.wait(timeout_s)
            if not self._items:
                return None
            item = self._items.popleft()
            if isinstance(item, StreamFrame):
                self._frames -= 1
                self._bytes -= _nbytes(item)
            self._cond.notify_all()
            return item

    def get_batch(self, timeout_s: float, max_frames: int) -> list[object]:
        """What has queued up, oldest first: one control item, or up to ``max_frames`` consecutive
        frames (those waiting, without waiting for more); [] after ``timeout_s`` without any."""
        first = self.get(timeout_s)
        if first is None:
            return []
        batch = [first]
        if not isinstance(first, StreamFrame):
            return batch
        with self._cond:
            while len(batch) < max_frames and self._items and isinstance(self._items[0], StreamFrame):
                frame = self._items.popleft()
                batch.append(frame)
                self._frames -= 1
                self._bytes -= _nbytes(frame)
            self._cond.notify_all()
        return batch

    def close(self) -> None:
        """Release a producer blocked in ``put``."""
        with self._cond:
            self._closed = True
            self._cond.notify_all()

    @property
    def nbytes(self) -> int:
        """Bytes of the samples of the frames held."""
        with self._cond:
            return self._bytes

    def __len__(self) -> int:
        with self._cond:
            return self._frames


class StreamProcessor:
    """The per-frame chain over a stream: results in frame order, counters, bounded state.

    Parameters
    ----------
    chain
        From :func:`echoloc.pipeline.prepare`, on the recording (or session header)
        the frames belong to.
    deadline_s
        A frame whose processing starts more than this after its arrival is counted
        as late (and still processed: its echoes are real, only old). None: never.
    """

    def __init__(self, chain: Chain, *, deadline_s: float | None = None) -> None:
        self.deadline_s = deadline_s
        self.latency = LatencyHistogram()
        self.processed = 0
        self.late = 0
        self.start_session(chain)

    def start_session(self, chain: Chain) -> None:
        """Go on with a new session's ``chain`` (a sender that started again, another head):
        the frames it takes and the transmitters it combines are the new chain's; the counters
        and latencies go on, so :meth:`stats` stays the stream's."""
        self.chain = chain
        recording = chain.recording
        # A recording says with frame_transmitter whether its frames are combined (as
        # pipeline.run does); a session header has no per-frame fields: its frames
        # name their transmitter on the wire.
        self._combine = (
            combines_transmitters(chain)
            if recording.n_frames > 0
            else len(recording.transmitters_m) > 1 and recording.firing != "simultaneous"
        )
        self._latest: dict[int, FrameEchoes] = {}
        n_rx, n_samples = (int(d) for d in np.shape(chain.recording.frames)[1:])
        self._shape = (n_rx, n_samples)

    def warm_up(self) -> None:
        """Run the chain once on a made-up frame (:meth:`warm_up_frame`), so the first real
        frame does not pay for compiling the kernels or filling caches. The processor's state
        and counters are left untouched, and so is the chain's channel check: the made-up
        frame runs on a copy of the chain without it (sharing its caches), so it is never
        taken for one of the stream's frames."""
        chain = replace(self.chain, channel_watch=None)
        # The locators the copy builds are the chain's: its receivers are all working, as the
        # chain's are until its channel check says otherwise (the key says which are).
        vars(chain)["_by_receivers"] = self.chain._by_receivers
        frame = self.warm_up_frame()
        if self._combine:
            combine_latest(chain, {}, samples_echoes(chain, frame, 0, 0.0), 0)
        else:
            samples_results_batch(chain, [frame], [0], [0.0], [0])

    def warm_up_frame(self) -> Samples:
        """A frame that takes every path of the chain: noise, and for rf with a waveform the echoes
        of a reflector on the transmitter's axis mid-window, each followed 1.5 samples later by a
        weaker one: echoes that overlap so closely that the matched filter hands them to CLEAN.

        A frame of noise alone leaves CLEAN's and the association's kernels to load on the first
        crowded frame of a stream: a latency spike where the stream can least afford one.
        """
        recording = self.chain.recording
        rng = np.random.default_rng(0)
        noise: Samples = rng.normal(size=self._shape)
        if recording.signal_kind == "iq":
            return noise + 1j * rng.normal(size=self._shape)
        if recording.signal_kind == "envelope":
            return np.abs(noise)
        if recording.waveform is None or not len(recording.waveform):
            return noise
        waveform = np.asarray(recording.waveform, dtype=float)
        n_samples = self._shape[1]
        fs, c = recording.sample_rate_hz, self.chain.speed_of_sound_m_s
        transmitter = np.asarray(recording.transmitters_m[0], dtype=float)
        axes = recording.transmitter_axes
        axis = np.asarray(self.chain.locate_options.boresight if axes is None else axes[0], dtype=float)
        if axis.shape != transmitter.shape:
            return noise
        # Mid-way between the end of blanking and the last echo that fits in the frame.
        first_s = self.chain.echo_options.blanking_s
        last_s = (n_samples - len(waveform)) / fs
        if last_s <= first_s:
            return noise
        range_m = c * (first_s + last_s) / 4
        point = transmitter + range_m * axis / np.linalg.norm(axis)
        paths = model_paths_m(transmitter, np.asarray(recording.receivers_m, dtype=float), point[None])[0]
        frame: NDArray[np.float64] = 0.01 * float(np.max(np.abs(waveform))) * np.asarray(noise, dtype=float)
        for receiver, path_m in enumerate(paths):
            for delay_samples, amplitude in ((path_m / c * fs, 1.0), (path_m / c * fs + 1.5, 0.8)):
                start = round(delay_samples)
                stop = min(start + len(waveform), n_samples)
                if 0 <= start < stop:
                    frame[receiver, start:stop] += amplitude * waveform[: stop - start]
        return frame

    def check(self, frame: StreamFrame) -> None:
        """Raise if ``frame`` does not fit the chain's recording (shape, transmitter)."""
        shape = tuple(np.shape(frame.samples))
        if shape != self._shape:
            raise EchoLocError(
                f"frame {frame.index} has {shape[0]} channels x {shape[-1]} samples, "
                f"the session {self._shape[0]} x {self._shape[1]}"
            )
        n_tx = len(self.chain.recording.transmitters_m)
        if not 0 <= frame.transmitter < n_tx:
            raise EchoLocError(
                f"frame {frame.index} names transmitter {frame.transmitter}, the session has {n_tx}"
            )

    def process(self, frame: StreamFrame) -> StreamResult:
        """Echoes and objects of one frame (frames of one stream must come in frame order):
        :meth:`process_batch` of one frame."""
        return self.process_batch((frame,))[0]

    def process_batch(self, frames: Sequence[StreamFrame]) -> list[StreamResult]:
        """Echoes and objects of each frame of a batch, in order, the echoes (and, frames
        located alone, the objects) of all of them in one call
        (:func:`echoloc.pipeline.samples_results_batch`: the same answers as frame by frame,
        more frames a second, as when frames have queued up). A frame's latency runs to when
        the batch's results are ready (with transmitters combined, its own objects); frames
        without an arrival time count from the batch's start."""
        if not frames:
            return []
        started = time.monotonic()
        for frame in frames:
            self.check(frame)
        samples = [f.samples for f in frames]
        indices = [f.index for f in frames]
        times = [f.time_s for f in frames]
        chain = self.chain
        if not self._combine:
            found = samples_results_batch(chain, samples, indices, times, [f.transmitter for f in frames])
            return [
                self._result(frame, *result, started) for frame, result in zip(frames, found, strict=True)
            ]
        results = []
        for frame, echoes in zip(frames, samples_echoes_batch(chain, samples, indices, times), strict=True):
            self._latest, objects = combine_latest(chain, self._latest, echoes, frame.transmitter)
            results.append(self._result(frame, echoes, objects, started))
        return results

    def _result(
        self, frame: StreamFrame, echoes: FrameEchoes, objects: FrameObjects, started: float
    ) -> StreamResult:
        """One frame's result, its latency and lateness counted; ``started``: when its
        processing (or its batch's) began, ``time.monotonic()``."""
        arrival_s = frame.arrival_s
        arrived = math.isfinite(arrival_s)
        late = self.deadline_s is not None and arrived and started - arrival_s > self.deadline_s
        latency = time.monotonic() - (arrival_s if arrived else started)
        self.latency.add(latency)
        self.processed += 1
        self.late += late
        return StreamResult(echoes, objects, frame.transmitter, latency, late)

    def stats(self, **counters: int) -> StreamStats:
        """A snapshot; ``counters`` adds what the receiving side counted (lost, dropped, ...)."""
        return StreamStats(
            processed=self.processed,
            late=self.late,
            latency_p50_s=self.latency.quantile(0.5),
            latency_p99_s=self.latency.quantile(0.99),
            latency_max_s=self.latency.max_s,
            **counters,
        )


def warm_kernels(estimator: str = "matched", workers: int = 1) -> None:
    """Load (or compile) the chain's kernels before any session is known.

    The compiled kernels do not depend on the geometry: running a chain on the
    default scene's header once loads them, so the first frames of a stream do not
    wait for them (loading, or on the very first run compiling, them takes far longer
    than a frame); with ``workers`` above 1 the threaded ones, and their threads start. An
    estimator that the default scene does not suit is left cold.
    """
    options = EchoOptions(workers=workers)
    with contextlib.suppress(EchoLocError):
        chain = prepare(recording_header(default_scene()), estimator=estimator, echo_options=options)
        StreamProcessor(chain).warm_up()


def recording_frames(recording: Recording, frames: Iterable[int] | None = None) -> Iterator[StreamFrame]:
    """The frames of a recording as a stream (arrival: when each is taken)."""
    indices = range(recording.n_frames) if frames is None else frames
    for index in indices:
        transmitter = 0 if recording.frame_transmitter is None else int(recording.frame_transmitter[index])
        yield StreamFrame(
            index,
            recording.frames[index],
            frame_time_s(recording, index),
            transmitter,
            time.monotonic(),
        )


def stream_recording(
    chain: Chain, frames: Iterable[int] | None = None, *, batch_frames: int = 1
) -> Iterator[StreamResult]:
    """Every frame of ``chain.recording`` through a :class:`StreamProcessor`, ``batch_frames`` at a time."""
    if batch_frames < 1:
        raise EchoLocError(f"batch_frames must be >= 1, got {batch_frames}")
    processor = StreamProcessor(chain)
    batch: list[StreamFrame] = []
    for frame in recording_frames(chain.recording, frames):
        batch.append(frame)
        if len(batch) == batch_frames:
            yield from processor.process_batch(batch)
            batch = []
    yield from processor.process_batch(batch)
