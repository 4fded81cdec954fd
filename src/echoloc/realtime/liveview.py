"""The live view: what a stream sees, published on a Foxglove WebSocket server on 127.0.0.1.

Why Foxglove rather than a page of our own: it is the viewer robot integrators
already run beside ROS 2, it shows 3-D scenes, plots and grids with no code of
ours in a browser, and the ``foxglove-sdk`` server speaks its documented WebSocket
protocol, so any client can subscribe too. Connect Foxglove to ``ws://127.0.0.1:8765``
(Open connection -> Foxglove WebSocket).

**Subprotocols.** The protocol's WebSocket subprotocol is ``foxglove.websocket.v1`` for
the clients of Foxglove's older ``ws-protocol`` libraries and bridges (Lichtblick, the
``foxglove_bridge`` 0.x clients, roslibjs-foxglove) and ``foxglove.sdk.v1`` since the
foxglove-sdk; Foxglove states the two are the same protocol under two names. The SDK's
server accepts only ``foxglove.sdk.v1`` (its handshake source, and releases 0.5.0,
0.29.2 and 0.30.3 checked) and answers any other offer with HTTP 400, with no option to
change that. So the port a client connects to is a small relay
(:class:`SubprotocolRelay`) in front of the SDK server, which listens on a free port of
127.0.0.1: a handshake that offers only ``foxglove.websocket.v1`` reaches the SDK
offering ``foxglove.sdk.v1``, and the SDK's answer goes back naming
``foxglove.websocket.v1``, the name the client offered; every other byte, both ways,
passes unchanged. Clients offering ``foxglove.sdk.v1`` are passed through untouched.

Topics, stamped with the frame's time on the capture clock, in the sensor frame
``echoloc_sensor_optical_frame`` (x right, y down, z ahead; docs/FORMATS.md) unless said:

- ``/tf`` (``foxglove.FrameTransforms``): that frame under the body frame
  ``echoloc_sensor_link`` (x forward, y left, z up; REP-103), with every frame shown;

- ``/echoloc/objects`` (``foxglove.SceneUpdate``): one sphere per object, 2 sigma
  wide, and its range as text;
- ``/echoloc/points`` (``foxglove.PointCloud``): the objects as points (x, y, z, score,
  float32);
- ``/echoloc/locate`` (JSON): the frame's line of ``echoloc locate --json``;
- ``/echoloc/echo_traces`` (JSON): per receiver, the matched filter's envelope (rf
  with a waveform; else the signal's envelope), max-pooled to about ``trace_points``
  points (``path_step_m`` apart), and the echoes' paths, for the Plot panel (x axis:
  index);
- ``/echoloc/stats`` (JSON): the stream's counters (:class:`echoloc.realtime.stream.StreamStats`);
- ``/echoloc/map`` (``foxglove.Grid``): an occupancy grid, when a mapper publishes one
  (:meth:`LiveView.publish_map`); `stream --view`'s floor plan lies flat in the body frame.

Publishing is throttled to ``max_rate_hz`` (objects and traces of the latest
frame), so viewing never slows the chain down; nothing is computed for the view
while no client is subscribed.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
import time
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy import signal

from echoloc.errors import EchoLocError
from echoloc.extras import missing_extra
from echoloc.io.export import BODY_FRAME_ID, OPTICAL_ROTATION_XYZW, SENSOR_FRAME_ID
from echoloc.io.output import objects_record
from echoloc.io.recording import Recording
from echoloc.realtime.stream import StreamResult, StreamStats
from echoloc.tof.echoes import MatchedFilter

try:
    import foxglove
    from foxglove.channels import FrameTransformsChannel, GridChannel, PointCloudChannel, SceneUpdateChannel
    from foxglove.messages import (
        Color,
        FrameTransform,
        FrameTransforms,
        Grid,
        PackedElementField,
        PackedElementFieldNumericType,
        PointCloud,
        Pose,
        Quaternion,
        SceneEntity,
        SceneUpdate,
        SpherePrimitive,
        TextPrimitive,
        Timestamp,
        Vector3,
    )
except ImportError:
    raise missing_extra("live", "the live view (--view)") from None

DEFAULT_VIEW_PORT = 8765
SDK_SUBPROTOCOL = "foxglove.sdk.v1"
"""The WebSocket subprotocol the foxglove-sdk server accepts."""
LEGACY_SUBPROTOCOL = "foxglove.websocket.v1"
"""The same protocol's older name, which clients of Foxglove's ``ws-protocol`` libraries offer."""
_HANDSHAKE_TIMEOUT_S = 10.0
TOPICS = (
    "/echoloc/objects",
    "/echoloc/points",
    "/echoloc/locate",
    "/echoloc/echo_traces",
    "/echoloc/stats",
    "/echoloc/map",
)

_IDENTITY = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)


def _timestamp(ns: int) -> Timestamp:
    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def _capture_stamp(time_s: float) -> Timestamp:
    """A frame time on the capture clock, s, as a message stamp (a negative or non-finite one: 0)."""
    seconds = time_s if np.isfinite(time_s) and time_s > 0 else 0.0
    return _timestamp(round(seconds * 1e9))


def _body_to_optical(stamp: Timestamp) -> FrameTransforms:
    """The sensor's optical frame (x right, y down, z ahead) in its body frame (x forward, y left,
    z up), REP-103's fixed rotation: what lets a viewer show the optical frame's points upright."""
    qx, qy, qz, qw = OPTICAL_ROTATION_XYZW
    return FrameTransforms(
        transforms=[
            FrameTransform(
                timestamp=stamp,
                parent_frame_id=BODY_FRAME_ID,
                child_frame_id=SENSOR_FRAME_ID,
                translation=Vector3(x=0.0, y=0.0, z=0.0),
                rotation=Quaternion(x=qx, y=qy, z=qz, w=qw),
            )
        ]
    )


def _header_lines(head: bytes) -> list[bytes]:
    return head.split(b"\r\n")


def _offered_subprotocols(head: bytes) -> list[str]:
    """The subprotocols a WebSocket upgrade request offers (every ``Sec-WebSocket-Protocol`` line)."""
    offered = []
    for line in _header_lines(head)[1:]:
        name, _, value = line.partition(b":")
        if name.strip().lower() == b"sec-websocket-protocol":
            offered += [token.strip() for token in value.decode("latin-1").split(",") if token.strip()]
    return offered


def _replace_subprotocol_header(head: bytes, subprotocol: str) -> bytes:
    """``head`` (an HTTP head ending in a blank line) with its ``Sec-WebSocket-Protocol`` lines
    replaced by one naming ``subprotocol``."""
    lines = _header_lines(head)
    kept = [
        line
        for line in lines[1:]
        if line and line.partition(b":")[0].strip().lower() != b"sec-websocket-protocol"
    ]
    header = b"Sec-WebSocket-Protocol: " + subprotocol.encode("ascii")
    return b"\r\n".join([lines[0], *kept, header, b"", b""])


class SubprotocolRelay:
    """A TCP relay on ``host:port`` to the SDK server on ``127.0.0.1:upstream_port`` that lets
    clients offering only :data:`LEGACY_SUBPROTOCOL` in (module doc).

    Per connection it reads the client's HTTP upgrade request; if it offers the legacy name
    and not :data:`SDK_SUBPROTOCOL`, the request goes on offering the SDK's name and the
    SDK's response comes back naming the legacy one (the ``Sec-WebSocket-Accept`` key does
    not depend on the subprotocol); otherwise both pass unchanged. After the handshake it
    copies bytes both ways until either side closes. It runs an asyncio loop on a daemon
    thread; :meth:`close` stops it and drops the connections.
    """

    def __init__(self, host: str, port: int, upstream_port: int) -> None:
        self.upstream_port = upstream_port
        self._loop = asyncio.new_event_loop()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._server: asyncio.base_events.Server | None = None
        self._tasks: set[asyncio.Task[None]] = set()
        self.port = 0
        self._thread = threading.Thread(
            target=self._run, args=(host, port), name="echoloc-liveview-relay", daemon=True
        )
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            self._thread.join()
            raise self._error

    def _run(self, host: str, port: int) -> None:
        asyncio.set_event_loop(self._loop)
        try:
            self._server = self._loop.run_until_complete(asyncio.start_server(self._connection, host, port))
            self.port = int(self._server.sockets[0].getsockname()[1])
        except BaseException as error:  # a busy port, a bad host: said by the constructor
            self._error = error
            self._ready.set()
            self._loop.close()
            return
        self._ready.set()
        try:
            self._loop.run_forever()
        finally:
            self._server.close()
            for task in list(self._tasks):
                task.cancel()
            if self._tasks:
                self._loop.run_until_complete(asyncio.gather(*self._tasks, return_exceptions=True))
            self._loop.run_until_complete(self._server.wait_closed())
            self._loop.close()

    def close(self) -> None:
        """Stop listening, drop every connection and end the thread."""
        if self._thread.is_alive():
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._thread.join(timeout=10)

    def _connection(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        task = asyncio.ensure_future(self._relay(reader, writer))
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _relay(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        upstream: asyncio.StreamWriter | None = None
        try:
            try:
                request = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), _HANDSHAKE_TIMEOUT_S)
            except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, asyncio.TimeoutError):
                return
            offered = _offered_subprotocols(request)
            legacy = LEGACY_SUBPROTOCOL in offered and SDK_SUBPROTOCOL not in offered
            if legacy:
                request = _replace_subprotocol_header(request, SDK_SUBPROTOCOL)
            up_reader, upstream = await asyncio.open_connection("127.0.0.1", self.upstream_port)
            upstream.write(request)
            await upstream.drain()
            try:
                response = await asyncio.wait_for(up_reader.readuntil(b"\r\n\r\n"), _HANDSHAKE_TIMEOUT_S)
            except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, asyncio.TimeoutError):
                return
            if legacy and SDK_SUBPROTOCOL in _offered_subprotocols(response):
                response = _replace_subprotocol_header(response, LEGACY_SUBPROTOCOL)
            writer.write(response)
            await writer.drain()
            await asyncio.gather(_pipe(reader, upstream), _pipe(up_reader, writer))
        except OSError:
            return
        finally:
            for stream in (writer, upstream):
                if stream is not None:
                    stream.close()
                    with contextlib.suppress(OSError, asyncio.CancelledError):
                        await stream.wait_closed()


async def _pipe(source: asyncio.StreamReader, target: asyncio.StreamWriter) -> None:
    """Copy ``source`` to ``target`` until end of stream, then half-close ``target``."""
    try:
        while chunk := await source.read(65536):
            target.write(chunk)
            await target.drain()
        if target.can_write_eof():
            target.write_eof()
    except OSError:
        target.close()


def envelope_trace(
    samples: NDArray[Any], points: int, matched: MatchedFilter | None = None
) -> tuple[NDArray[np.float64], int]:
    """Envelope of each channel (n_rx, n_samples), max-pooled to about ``points`` points.

    With ``matched``, the magnitude of the analytic correlation with the template
    (:meth:`echoloc.tof.echoes.MatchedFilter.correlate_single`), which peaks where an
    echo arrives; otherwise the magnitude of the analytic signal of real samples
    (``scipy.signal.hilbert``), or of complex (iq) samples themselves. Returns the
    pooled envelopes and the pooling factor (samples per point).
    """
    arr = np.asarray(samples)
    if matched is not None:
        envelope = np.abs(matched.correlate_single(arr))
    elif arr.dtype.kind == "c":
        envelope = np.abs(arr)
    else:
        envelope = np.abs(signal.hilbert(arr, axis=-1))
    factor = max(1, int(np.ceil(arr.shape[-1] / max(points, 1))))
    n = envelope.shape[-1] // factor * factor
    pooled = envelope[:, :n].reshape(envelope.shape[0], -1, factor).max(axis=-1)
    return pooled, factor


class LiveView:
    """A Foxglove WebSocket server with echoloc's topics (see the module's table).

    Parameters
    ----------
    host, port
        Where to serve; 127.0.0.1 keeps it on this machine. Port 0 picks a free one
        (see :attr:`port`).
    max_rate_hz
        At most this many frames a second are published.
    trace_points
        About this many points per receiver in ``/echoloc/echo_traces``.
    """

    def __init__(
        self,
        host: str = "127.0.0.1",
        port: int = DEFAULT_VIEW_PORT,
        *,
        max_rate_hz: float = 20.0,
        trace_points: int = 600,
    ) -> None:
        self.context = foxglove.Context()
        try:
            # The SDK's own server, on a free port of this machine; clients reach it through the relay.
            self.server = foxglove.start_server(
                name="echoloc", host="127.0.0.1", port=0, context=self.context
            )
        except Exception as error:  # the SDK raises its own error types
            raise EchoLocError(f"cannot start the live view's server: {error}") from None
        try:
            self.relay = SubprotocolRelay(host, port, int(self.server.port))
        except (OSError, ValueError) as error:
            self.server.stop()
            raise EchoLocError(f"cannot start the live view on ws://{host}:{port}: {error}") from None
        self.host = host
        self.max_rate_hz = max_rate_hz
        self.trace_points = trace_points
        self._objects = SceneUpdateChannel("/echoloc/objects", context=self.context)
        self._points = PointCloudChannel("/echoloc/points", context=self.context)
        self._locate = foxglove.Channel("/echoloc/locate", message_encoding="json", context=self.context)
        self._traces = foxglove.Channel("/echoloc/echo_traces", message_encoding="json", context=self.context)
        self._stats = foxglove.Channel("/echoloc/stats", message_encoding="json", context=self.context)
        self._map = GridChannel("/echoloc/map", context=self.context)
        self._tf = FrameTransformsChannel("/tf", context=self.context)
        self._last_ns = 0
        self._sample_rate_hz = 1.0
        self._matched: MatchedFilter | None = None
        self.published = 0

    @property
    def port(self) -> int:
        """The port clients connect to (the relay's)."""
        return self.relay.port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def close(self) -> None:
        self.relay.close()
        self.server.stop()

    def __enter__(self) -> LiveView:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def set_session(self, header: Recording) -> None:
        """The session the frames to come belong to: prepares the traces' matched filter once."""
        self._sample_rate_hz = float(header.sample_rate_hz)
        self._matched = None
        if header.signal_kind == "rf" and header.waveform is not None:
            self._matched = MatchedFilter(
                np.asarray(header.waveform, float), header.n_samples, self._sample_rate_hz
            )

    def publish(self, result: StreamResult, samples: NDArray[Any], stats: StreamStats | None = None) -> bool:
        """Publish one frame's objects and traces (and ``stats``), unless throttled; True if published.

        ``samples`` (n_rx, n_samples) are the frame's, of the session given to
        :meth:`set_session`.
        """
        now = time.time_ns()
        if now - self._last_ns < 1e9 / self.max_rate_hz:
            return False
        self._last_ns = now
        objects = result.objects
        stamp = _capture_stamp(objects.time_s)  # the frame's emission on the capture clock
        if self._tf.has_sinks():  # sent with every frame shown: a client that joins late gets it too
            self._tf.log(_body_to_optical(stamp), log_time=now)
        if self._objects.has_sinks():
            self._objects.log(self._scene(result, stamp), log_time=now)
        if self._points.has_sinks():
            self._points.log(self._cloud(result, stamp), log_time=now)
        if self._locate.has_sinks():
            self._locate.log(objects_record(objects), log_time=now)
        if self._traces.has_sinks():
            self._traces.log(self._trace_record(result, samples), log_time=now)
        if stats is not None and self._stats.has_sinks():
            self._stats.log(stats.record(), log_time=now)
        self.published += 1
        return True

    def publish_map(
        self,
        occupancy: NDArray[np.floating],
        cell_size_m: float,
        origin_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
        orientation_xyzw: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 1.0),
        *,
        frame_id: str = BODY_FRAME_ID,
        stamp_s: float | None = None,
    ) -> None:
        """Publish an occupancy grid (rows along y, columns along x, values 0..1) as ``foxglove.Grid``.

        The hook for a mapper (an occupancy grid of the sensor's surroundings): the
        grid lies in its own x-y plane, placed in ``frame_id`` (default the body frame,
        x forward, y left, z up: a floor plan lies flat) by ``origin_m`` (its cell (0, 0))
        and ``orientation_xyzw``; values are sent as float32 ``occupancy`` (-1 where
        unknown). ``stamp_s``: the newest frame's time on the capture clock (None: now).
        """
        grid = np.ascontiguousarray(occupancy, dtype=np.float32)
        if grid.ndim != 2 or grid.size == 0:
            raise EchoLocError(f"an occupancy grid must be 2-D and not empty, got shape {grid.shape}")
        now = time.time_ns()
        columns = grid.shape[1]
        self._map.log(
            Grid(
                timestamp=_timestamp(now) if stamp_s is None else _capture_stamp(stamp_s),
                frame_id=frame_id,
                pose=Pose(
                    position=Vector3(x=origin_m[0], y=origin_m[1], z=origin_m[2]),
                    orientation=Quaternion(
                        x=orientation_xyzw[0],
                        y=orientation_xyzw[1],
                        z=orientation_xyzw[2],
                        w=orientation_xyzw[3],
                    ),
                ),
                column_count=columns,
                cell_size=foxglove.messages.Vector2(x=cell_size_m, y=cell_size_m),
                row_stride=columns * 4,
                cell_stride=4,
                fields=[
                    PackedElementField(name="occupancy", offset=0, type=PackedElementFieldNumericType.Float32)
                ],
                data=grid.tobytes(),
            ),
            log_time=now,
        )

    # -- messages

    def _scene(self, result: StreamResult, stamp: Timestamp) -> SceneUpdate:
        spheres = []
        texts = []
        for obj in result.objects.objects:
            x, y, z = (float(v) for v in obj.position_m)
            size = float(max(4 * np.max(obj.std_m), 0.01))  # 2 sigma each side, at least 1 cm
            pose = Pose(position=Vector3(x=x, y=y, z=z), orientation=_IDENTITY)
            spheres.append(
                SpherePrimitive(
                    pose=pose,
                    size=Vector3(x=size, y=size, z=size),
                    color=Color(r=1.0, g=0.45, b=0.1, a=0.8),
                )
            )
            texts.append(
                TextPrimitive(
                    pose=Pose(position=Vector3(x=x, y=y - 0.02, z=z), orientation=_IDENTITY),
                    billboard=True,
                    font_size=12.0,
                    scale_invariant=True,
                    color=Color(r=1.0, g=1.0, b=1.0, a=1.0),
                    text=f"{np.linalg.norm(obj.position_m) * 1e3:.0f} mm",
                )
            )
        entity = SceneEntity(
            timestamp=stamp,
            frame_id=SENSOR_FRAME_ID,
            id="objects",
            frame_locked=True,
            spheres=spheres,
            texts=texts,
            metadata=[],
        )
        return SceneUpdate(entities=[entity])

    def _cloud(self, result: StreamResult, stamp: Timestamp) -> PointCloud:
        objects = result.objects.objects
        data = np.zeros((len(objects), 4), dtype="<f4")
        for k, obj in enumerate(objects):
            data[k, :3] = obj.position_m
            data[k, 3] = obj.score
        fields = [
            PackedElementField(name=name, offset=4 * k, type=PackedElementFieldNumericType.Float32)
            for k, name in enumerate(("x", "y", "z", "score"))
        ]
        return PointCloud(
            timestamp=stamp,
            frame_id=SENSOR_FRAME_ID,
            pose=Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=_IDENTITY),
            point_stride=16,
            fields=fields,
            data=data.tobytes(),
        )

    def _trace_record(self, result: StreamResult, samples: NDArray[Any]) -> dict[str, Any]:
        pooled, factor = envelope_trace(samples, self.trace_points, self._matched)
        rate = self._sample_rate_hz
        echoes = result.echoes
        c = echoes.speed_of_sound_m_s
        return {
            "frame": echoes.frame,
            "time_s": float(echoes.time_s),
            "sample_step_s": factor / rate,
            "path_step_m": factor / rate * c,
            "channels": [
                {
                    "receiver": receiver,
                    "envelope": [round(float(v), 6) for v in pooled[receiver]],
                    "echo_paths_m": [float(t * c) for t in channel.tof_s],
                }
                for receiver, channel in enumerate(echoes.channels)
            ],
        }
