"""Capture sources: frames from hardware, behind the interface `stream` and `record` use.

`echoloc stream` and `echoloc record` take frames from a *source*: the network
:class:`~echoloc.realtime.transport.Listener` (the stream protocol), or a capture
source of this module's family (:class:`CaptureSource`): a serial or USB-CDC board
(:mod:`echoloc.realtime.serial_source`), a sound card
(:mod:`echoloc.realtime.soundcard_source`). Every source has the same face:

- ``queue``: a :class:`~echoloc.realtime.stream.FrameQueue` it puts, in order, a
  :class:`~echoloc.realtime.transport.SessionEvent` (the head's header), then
  :class:`~echoloc.realtime.stream.StreamFrame` s, and an
  :class:`~echoloc.realtime.transport.EndEvent` when the device goes away;
- ``start()``, ``stop()``; ``address`` (what it reads, for messages);
- ``errors()`` (warning lines, rate-limited) and ``counters()`` (received, lost, dropped,
  out of order, malformed, rejected, refused, restarts);
- ``sessions_refused`` and ``last_session_refusal``.

A capture source knows its head (:class:`~echoloc.io.head.SensorHead`): there is no
session message on a serial line or a sound card, so the head file gives the geometry,
the pulse and the wiring. Frames are numbered by the device's sequence numbers where it
has them (gaps counted lost, as on the network) and stamped with the capture clock.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import numpy as np

from echoloc.errors import EchoLocError
from echoloc.io.head import SensorHead
from echoloc.io.recording import Recording
from echoloc.realtime.stream import FrameQueue, SequenceTracker, StreamFrame
from echoloc.realtime.transport import WARN_INTERVAL_S, EndEvent, SessionEvent, _Warnings


class CaptureSource:
    """The common part of the capture sources: a thread running :meth:`_run`, the session,
    the counters and the warnings; a subclass reads its device in :meth:`_run` and hands each
    frame to :meth:`_deliver`.

    Parameters
    ----------
    head
        The head being captured from: its header is the session.
    frames
        Where the session, frames and end go.
    accept_session
        Called on the session before it is queued (`stream` prepares its chain there);
        what it raises refuses the session, and the source then captures nothing.
    """

    kind = "capture"

    def __init__(
        self,
        head: SensorHead,
        frames: FrameQueue,
        *,
        accept_session: Callable[[Recording], object] | None = None,
        warn_interval_s: float = WARN_INTERVAL_S,
    ) -> None:
        self.head = head
        self.queue = frames
        self.accept_session = accept_session
        self.tracker = SequenceTracker()
        self.received = 0
        self.malformed = 0
        self.rejected = 0
        self.refused = 0
        self.sessions_refused = 0
        self.last_session_refusal: str | None = None
        self.last_error: str | None = None
        self._warnings = _Warnings(warn_interval_s)
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, name=f"echoloc-{self.kind}", daemon=True)

    @property
    def address(self) -> str:
        """What this source reads, for messages (``serial:/dev/ttyACM0``, ``soundcard:2``)."""
        return self.kind

    @property
    def serving(self) -> bool:
        return self._thread.is_alive() and not self._stop.is_set()

    def start(self) -> CaptureSource:
        """Offer the head's session, open the device, then capture in a thread. A session the
        caller refuses, or a device that cannot be opened: EchoLocError, nothing queued."""
        header = self.head.header
        try:
            prepared = None if self.accept_session is None else self.accept_session(header)
        except EchoLocError as error:  # no other session can come: capturing would wait forever
            with self._lock:
                self.refused += 1
                self.sessions_refused += 1
            self.last_session_refusal = str(error)
            raise EchoLocError(f"{self.address}: the head cannot be used: {error}") from None
        self._open()
        self.queue.put(SessionEvent(header, prepared))
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop capturing and release the device (waits for the thread)."""
        self._stop.set()
        self.queue.close()
        if self._thread.is_alive():
            self._thread.join(timeout=5.0)
        self._close()

    def __enter__(self) -> CaptureSource:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    def errors(self) -> Iterator[str]:
        """Warning lines since the last call (rate-limited; once stopped, also those held back)."""
        return self._warnings.lines(everything=self._stop.is_set())

    def counters(self) -> dict[str, int]:
        """What the capture side counted, as the network listener's :meth:`counters`."""
        with self._lock:
            return {
                "received": self.received,
                "lost": self.tracker.lost,
                "dropped": self.queue.dropped,
                "out_of_order": self.tracker.out_of_order,
                "malformed": self.malformed,
                "rejected": self.rejected,
                "refused": self.refused,
                "restarts": self.tracker.restarts,
            }

    # -- for subclasses

    def _open(self) -> None:
        """Open the device (before the thread starts); raise EchoLocError if it cannot be."""

    def _close(self) -> None:
        """Release the device (after the thread ended)."""

    def _run(self) -> None:
        """Read the device until :attr:`_stop` is set, handing frames to :meth:`_deliver`."""
        raise NotImplementedError

    def _serve(self) -> None:
        try:
            self._run()
        except Exception as error:  # the device went away, or a bug: said, and the stream ends
            if not self._stop.is_set():
                self._complain("malformed", "device", f"{self.address}: capture stopped: {error}")
        finally:
            if not self._stop.is_set():
                self.queue.put(EndEvent(disconnected=True, final=True))

    def _complain(self, counter: str, kind: str, message: str) -> None:
        """Count one refused thing in ``counter``; one warning line, rate-limited per ``kind``."""
        with self._lock:
            setattr(self, counter, getattr(self, counter) + 1)
        self.last_error = message
        self._warnings.add(kind, message)

    def _reject(self, sequence: int | None, kind: str, message: str) -> None:
        """A frame the device sent that does not fit the head, refused: counted in ``rejected``,
        one warning line (rate-limited per ``kind``). Its ``sequence`` number, when the device
        sent one it vouches for, still counts in the numbering, so the frame is not also
        counted lost."""
        if sequence is not None:
            with self._lock:
                self.tracker.observe(sequence)
        self._complain("rejected", kind, message)

    def _deliver(
        self, counts: np.ndarray[Any, Any], time_s: float, sequence: int | None = None, transmitter: int = 0
    ) -> StreamFrame | None:
        """Queue one captured frame, (n_channels, values_per_channel) in ADC counts, emitted at
        ``time_s`` on the capture clock; ``sequence``: the device's 32-bit frame number (None: one
        more than the last). A frame off the numbering (late or duplicated) is counted and
        refused; returns the frame queued, or None."""
        arrival_s = time.monotonic()  # latency counts from here: the conversion below is processing
        fits = 0 <= transmitter < len(self.head.header.transmitters_m)
        with self._lock:
            if sequence is None:
                sequence = 0 if self.tracker.next is None else self.tracker.next
            number = self.tracker.observe(sequence)
            # A frame refused is not received (received = processed + dropped + unprocessed).
            if number is not None and fits:
                self.received += 1
        if number is None:
            self._warnings.add("order", f"{self.address}: frame {sequence} arrived out of order, refused")
            return None
        if not fits:
            self._complain(
                "rejected", "transmitter", f"{self.address}: frame {sequence}: no transmitter {transmitter}"
            )
            return None
        frame = StreamFrame(
            index=number,
            samples=self.head.samples(counts),
            time_s=time_s,
            transmitter=transmitter,
            arrival_s=arrival_s,
        )
        self.queue.put(frame)
        return frame
