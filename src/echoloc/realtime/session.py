"""A live session: what ``echoloc stream`` does with each session and frame off a listener.

:func:`listener_events` takes what a :class:`~echoloc.realtime.transport.Listener`
queued (sessions, and frames in batches so that a backlog is worked off quickly) until a
stop condition. :class:`LiveSession` handles each: a new session prepares its chain and
(re)starts the processor, the recorder and the live view's map; frames are recorded
first (a frame the chain then refuses is kept too), processed, and handed to the
caller's ``on_result``. Its messages (a session began, a recording stopped, the final
counts) go to ``on_message``; how to show either is the caller's choice.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from echoloc.io.recording import Recording
from echoloc.pipeline import Chain
from echoloc.realtime.stream import STREAM_BATCH_FRAMES, StreamFrame, StreamProcessor, StreamResult

IDENTITY_POSE = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])
"""x, y, z, qx, qy, qz, qw of a sensor that does not move: live frames carry no pose."""

MAP_PUBLISH_EVERY_S = 0.5
"""How often the live view's floor plan is sent, s."""

MAP_CELL_M = 0.02
"""The live floor plan's cell, m."""


def listener_events(
    listener: Any,
    *,
    once: bool = False,
    max_frames: int | None = None,
    deadline_s: float | None = None,
    on_error: Callable[[str], None] = lambda message: None,
) -> Iterator[Any]:
    """Sessions (``SessionEvent``), and lists of the frames that queued up (at most
    ``STREAM_BATCH_FRAMES`` a list), off ``listener.queue`` until the first sender's end
    (``once``), ``max_frames`` frames or the monotonic time ``deadline_s``; the listener's
    errors go to ``on_error`` as they come."""
    from echoloc.realtime.transport import EndEvent

    frames = 0
    while True:
        for message in listener.errors():
            on_error(message)
        if deadline_s is not None and time.monotonic() >= deadline_s:
            return
        room = STREAM_BATCH_FRAMES if max_frames is None else min(STREAM_BATCH_FRAMES, max_frames - frames)
        items = listener.queue.get_batch(0.1, room)
        if not items:
            continue
        item = items[0]
        if isinstance(item, EndEvent):
            if once or item.final:
                return
            continue
        if not isinstance(item, StreamFrame):
            yield item
            continue
        yield items
        frames += len(items)
        if max_frames is not None and frames >= max_frames:
            return


def live_mapper(header: Recording, chain: Chain) -> Any:
    """A floor plan at :data:`MAP_CELL_M` around a sensor that does not move (so without
    tracks across poses, which need motion)."""
    from echoloc.maps.mapping import chain_accumulator, default_floor_plan

    spec = default_floor_plan(header, IDENTITY_POSE[None, :], MAP_CELL_M, chain.speed_of_sound_m_s)
    return chain_accumulator(chain, spec, tracks=False)


def _ignore_result(frame: StreamFrame, result: StreamResult) -> None:
    del frame, result


def _ignore_message(text: str) -> None:
    del text


@dataclass(eq=False)
class LiveSession:
    """Sessions and frames from a listener, through the chain, to the caller and the view.

    ``make_chain`` prepares a session's chain when the listener did not (``--geometry``);
    ``deadline_s`` is each frame's processing deadline; ``record_path``: record the first
    session's frames there; ``mcap_path``: write the first session's objects there as ROS 2
    messages (:class:`~echoloc.io.export.RosObjectsWriter`, stamped with the capture clock);
    ``view``: a :class:`~echoloc.realtime.liveview.LiveView`.
    The fields after those are its state: the processor (from the first session on), the
    recorder, the current session's header and live map, and a recorder's failure.
    """

    listener: Any
    make_chain: Callable[[Recording], Chain]
    deadline_s: float
    record_path: Path | None = None
    view: Any = field(default=None, kw_only=True)
    mcap_path: Path | None = field(default=None, kw_only=True)
    on_result: Callable[[StreamFrame, StreamResult], None] = field(default=_ignore_result, kw_only=True)
    on_message: Callable[[str], None] = field(default=_ignore_message, kw_only=True)
    processor: StreamProcessor | None = field(default=None, init=False)
    recorder: Any = field(default=None, init=False)
    header: Recording | None = field(default=None, init=False)
    mapper: Any = field(default=None, init=False)
    record_error: BaseException | None = field(default=None, init=False)
    ros_writer: Any = field(default=None, init=False)
    _ros_done: bool = field(default=False, init=False)
    _last_map: float = field(default=0.0, init=False)

    def stats(self) -> Any:
        """The stream's counters: the listener's and the processor's, over every session."""
        assert self.processor is not None
        return self.processor.stats(**self.listener.counters())

    def handle(self, item: Any) -> None:
        """A new session (a SessionEvent), or the frames that queued up (a list)."""
        from echoloc.realtime.transport import Recorder, SessionEvent

        if isinstance(item, SessionEvent):
            header = item.header
            # Prepared by the listener as the session arrived (accept_session); --geometry's is not.
            chain = item.prepared if isinstance(item.prepared, Chain) else self.make_chain(header)
            if self.processor is None:
                self.processor = StreamProcessor(chain, deadline_s=self.deadline_s)
            else:
                self.processor.start_session(chain)  # the counters go on across sessions
            self.processor.warm_up()
            if self.view is not None:
                self.view.set_session(header)
                self.mapper = live_mapper(header, chain)
            if self.recorder is not None and self.header is not None:
                self._stop_recording("the sender started a different session")
            if self.header is not None:
                self._stop_ros("the sender started a different session")
            if self.record_path is not None and self.recorder is None and self.header is None:
                self.recorder = Recorder(self.record_path, header)
            self.header = header
            self.on_message(
                f"session: {header.n_receivers} receivers, {len(header.transmitters_m)} transmitter(s), "
                f"{header.n_samples} samples at {header.sample_rate_hz:g} Hz, "
                f"c = {chain.speed_of_sound_m_s:.2f} m/s"
            )
            return
        frames: Sequence[StreamFrame] = item
        if self.recorder is not None:  # recorded first: a frame the chain refuses is kept too
            for frame in frames:
                self.recorder.add(frame)
        assert self.processor is not None, "frames before any session"
        for frame, result in zip(frames, self.processor.process_batch(frames), strict=True):
            self.on_result(frame, result)
            if self.mcap_path is not None and not self._ros_done:
                self._write_ros(result)
            # The live map takes only the frames the view shows (at most 20 a second): it
            # costs more than the chain per frame, and the view must never slow the chain.
            if self.view is not None and self.view.publish(result, frame.samples, self.stats()):
                self._map(result, frame.arrival_s)

    def _map(self, result: StreamResult, now: float) -> None:
        """Add a shown frame to the live floor plan; publish it every MAP_PUBLISH_EVERY_S, flat in the
        x-y plane of the sensor's body frame (x forward, y left, z up: REP-103)."""
        from echoloc.maps.map_export import map_floor_plan

        if self.mapper is None:
            return
        self.mapper.add_frame(
            result.echoes, IDENTITY_POSE, transmitter=result.transmitter, objects=result.objects
        )
        if now - self._last_map >= MAP_PUBLISH_EVERY_S:
            self._last_map = now
            grid = self.mapper.grid()
            cells, corner = map_floor_plan(grid)  # a still sensor: its body frame is the map
            self.view.publish_map(cells, grid.spec.cell_m, corner, stamp_s=result.objects.time_s)

    def _write_ros(self, result: StreamResult) -> None:
        """The frame's objects as ROS 2 messages; the file opens at the first frame (whose time
        stamps /tf_static). A failure (a full disk) stops the MCAP, never the stream."""
        from echoloc.io.export import RosObjectsWriter

        stamp_s = result.objects.time_s
        try:
            if self.ros_writer is None:
                assert self.mcap_path is not None
                assert self.header is not None
                self.ros_writer = RosObjectsWriter(self.mcap_path, self.header, first_stamp_s=stamp_s)
            self.ros_writer.add(result.objects, stamp_s)
        except (OSError, ValueError) as error:  # EchoLocError is a ValueError: a stamp ROS cannot hold
            self.record_error = error
            self._stop_ros(f"cannot write: {error}")

    def _stop_ros(self, why: str) -> None:
        """Finish the MCAP (if it was opened) and write no more to it."""
        if self._ros_done:
            return
        self._ros_done = True
        if self.ros_writer is None:
            return
        try:
            count = self.ros_writer.close()
        except (OSError, ValueError) as error:
            self.record_error = error
            return
        self.on_message(f"ROS 2 messages stopped ({why}): {count} messages in {self.mcap_path}")

    def _stop_recording(self, why: str) -> None:
        try:
            self.recorder.close()
        except BaseException as error:
            self.record_error = error
        self.on_message(f"recording stopped ({why}): {self.recorder.frames} frames in {self.record_path}")
        self.recorder = None

    def close(self, interrupted: bool) -> None:
        """Close the view and the recorder; the final counts go to ``on_message``."""
        if self.view is not None:
            self.view.close()
        if self.ros_writer is not None and not self._ros_done:
            self._ros_done = True
            try:
                count = self.ros_writer.close()
                self.on_message(f"wrote {count} ROS 2 messages to {self.mcap_path}")
            except (OSError, ValueError) as error:
                self.record_error = error
        if self.recorder is not None:
            try:
                self.recorder.close()
            except BaseException as error:
                self.record_error = error
        if self.processor is None:
            counters = self.listener.counters()
            none = "no session accepted" if self.listener.sessions_refused else "no session arrived"
            line = ", ".join(f"{k} {v}" for k, v in counters.items()) + f"; {none}"
        else:
            # The listener has stopped: what it received and the queue did not drop is either
            # processed or was left (queued, or in a batch an interrupt cut short).
            stats = self.stats()
            line = replace(stats, unprocessed=stats.received - stats.processed - stats.dropped).summary()
        self.on_message(line + (" (interrupted)" if interrupted else ""))
        if self.recorder is not None and self.record_error is None:
            self.on_message(
                f"recorded {self.recorder.frames} frames to {self.record_path} "
                f"({self.recorder.dropped} not recorded: the recorder fell behind)"
            )
