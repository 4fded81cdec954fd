"""Sockets: receiving and sending the wire protocol (:mod:`echoloc.realtime.protocol`) over TCP or UDP.

The edges of a live stream, kept apart from the processing:

- :class:`Listener` binds a TCP or UDP port (127.0.0.1 by default), decodes
  messages in background threads (one per TCP connection, a bounded number, each
  with an idle timeout) and puts sessions and frames on a
  :class:`~echoloc.realtime.stream.FrameQueue`, counting what it cannot use (malformed
  messages, frames that do not fit the session, sequence gaps, disorder, refused
  sessions); nothing a peer sends ends it, and it tells a TCP sender why it
  refused its session;
- :func:`send_recording` replays a recording at real time, N times faster, at a
  fixed rate, or as fast as the receiver takes it, once or in a loop, and raises
  the receiver's refusal;
- :class:`Recorder` appends frames to an HDF5 recording in batches from its own
  thread (:func:`echoloc.io.recording.append_recording_stream`: flushed after every
  batch).
"""

from __future__ import annotations

import contextlib
import ipaddress
import itertools
import json
import math
import queue
import select
import socket
import threading
import time
import warnings
from collections import deque
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from echoloc.errors import EchoLocError, refuse_new_output
from echoloc.io.recording import FrameBatch, Recording, append_recording_stream, as_header
from echoloc.realtime.protocol import (
    KIND_END,
    KIND_REFUSAL,
    KIND_SESSION,
    KINDS,
    MAX_FRAME_BYTES,
    MAX_REFUSAL_BYTES,
    MAX_SESSION_BYTES,
    MAX_UDP_BYTES,
    FramePayload,
    MessageHeader,
    ProtocolError,
    decode_frame,
    decode_header,
    decode_refusal,
    decode_session,
    encode_end,
    encode_refusal,
    encode_session,
    frame_bytes,
    frame_message,
    frame_payload,
    session_record,
    split_messages,
)
from echoloc.realtime.stream import DEFAULT_QUEUE_BYTES, FrameQueue, Samples, SequenceTracker, StreamFrame
from echoloc.tof.echoes import frame_time_s

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 7447
TRANSPORTS = ("tcp", "udp")


@dataclass(frozen=True)
class Endpoint:
    """Where a stream is sent or received: host, port and ``"tcp"`` or ``"udp"``."""

    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    transport: str = "tcp"

    def __str__(self) -> str:
        return f"{self.transport}://{self.host}:{self.port}"


def parse_endpoint(text: str, transport: str = "tcp") -> Endpoint:
    """``PORT``, ``HOST:PORT`` or ``tcp://HOST:PORT`` / ``udp://HOST:PORT`` as an :class:`Endpoint`."""
    rest = text
    if "://" in text:
        transport, rest = text.split("://", 1)
    if transport not in TRANSPORTS:
        raise EchoLocError(f"endpoint {text!r}: transport {transport!r}, expected tcp or udp")
    host, _, port_text = rest.rpartition(":")
    host = host.strip("[]") or DEFAULT_HOST
    try:
        port = int(port_text)
    except ValueError:
        raise EchoLocError(f"endpoint {text!r}: port {port_text!r} is not a number") from None
    if not 0 <= port <= 65535:
        raise EchoLocError(f"endpoint {text!r}: port {port} is outside 0..65535")
    return Endpoint(host, port, transport)


# ----------------------------------------------------------------------------- receiving

DEFAULT_MAX_CONNECTIONS = 16
"""TCP connections served at once by default (each its own thread)."""
DEFAULT_IDLE_TIMEOUT_S = 10.0
"""A TCP connection that sends nothing for this long is closed, s (a sender at work sends
frames many times a second; a sensor that pauses longer reconnects)."""
WARN_INTERVAL_S = 1.0
"""Each kind of complaint becomes at most one warning line this often, s; the rest are counted."""
REFUSAL_LINGER_S = 0.5
"""How long a receiver that refused a TCP sender reads on (and discards) before it closes, s: so
the refusal reaches a sender that is still writing instead of being cut off by a reset."""
CLOSE_GRACE_S = 1.0
"""A TCP connection is closed to make room for a new one only once it has sent nothing usable for
this long, s: a sender that just connected has its session read first."""
ADMIT_WAIT_S = 0.25
"""How long a new TCP connection waits for the one closed to make room for it to go, s (one
reading goes at once; one waiting its turn to decode a session, within DECODING_POLL_S)."""
DECODING_POLL_S = 0.05
"""How often a connection waiting its turn to decode a session looks whether it is to close, s."""
MAX_REFUSING_THREADS = 8
"""Connections refused at once (too many) that are told why, each by a short thread; beyond
these a refused connection is told without waiting and closed at once (the refusal may be lost
to the reset; the connection is counted all the same)."""


class ExposedListenerWarning(UserWarning):
    """A listener bound where other hosts can reach it (the protocol has no authentication)."""


class _Warnings:
    """Warning lines, rate-limited: of each kind at most one line every ``interval_s``; the lines
    held back are counted, and said in one line (the last of them, with the count) once the
    interval is over. Bounded: a caller that never reads them does not make memory grow."""

    def __init__(self, interval_s: float, max_lines: int = 100) -> None:
        self.interval_s = interval_s
        self._lines: deque[str] = deque(maxlen=max_lines)
        self._shown: dict[str, float] = {}
        self._held: dict[str, tuple[int, str]] = {}  # kind -> (how many held, the last of them)
        self._lock = threading.Lock()

    def add(self, kind: str, message: str) -> None:
        now = time.monotonic()
        with self._lock:
            self._release(now)
            if kind in self._shown and now - self._shown[kind] < self.interval_s:
                held, _ = self._held.get(kind, (0, message))
                self._held[kind] = (held + 1, message)
                return
            self._shown[kind] = now
            self._lines.append(message)

    def _release(self, now: float, everything: bool = False) -> None:
        for kind, (held, message) in list(self._held.items()):
            since = now - self._shown[kind]
            if everything or since >= self.interval_s:
                del self._held[kind]
                self._shown[kind] = now
                more = "1 more like it" if held == 1 else f"{held} more like it"
                self._lines.append(f"{message} ({more} in {since:.1f} s, this the last)")

    def lines(self, everything: bool = False) -> Iterator[str]:
        """The lines due (``everything``: also those held back), oldest first, each once."""
        with self._lock:
            self._release(time.monotonic(), everything)
            lines = list(self._lines)
            self._lines.clear()
        yield from lines


@dataclass(frozen=True, eq=False)
class SessionEvent:
    """A new session on the queue: the header every following frame belongs to.

    ``prepared``: what the listener's ``accept_session`` returned for it (for `echoloc
    stream`, its chain), or None.
    """

    header: Recording
    prepared: object = None


@dataclass(frozen=True)
class EndEvent:
    """The sender said it is done (an end message), or, on TCP, it disconnected; ``final``:
    nothing can come after it (a capture source's device went away), so the stream ends
    whether or not it was asked to stop at the first end (``--once``)."""

    disconnected: bool = False
    final: bool = False


@dataclass(eq=False)
class _Peer:
    """One sender: a TCP connection, or (UDP) every datagram of the port."""

    name: str
    connection: socket.socket | None
    opened_s: float
    tracker: SequenceTracker = field(default_factory=SequenceTracker)
    session: Recording | None = None
    session_key: str | None = None
    prepared: object = None
    # The last session message taken or refused, as it came (a UDP sender repeats it every second).
    session_raw: tuple[object, ...] | None = None
    refused_raw: tuple[object, ...] | None = None
    refused_reason: str = ""
    proven: bool = False  # has sent a session or frame that was taken: never closed to make room
    # Why this connection is to be closed (set under the listener's lock by the thread accepting a
    # new one, cleared if it proves itself first).
    closing: str | None = None
    busy: bool = False  # handling what it sent (maybe waiting its turn to decode): never shut down
    waiting_turn: bool = False  # waiting its turn to decode a session: sees at once it is to close
    last_usable_s: float = 0.0  # when it last sent a usable message (a session, frame or end taken)

    def __post_init__(self) -> None:
        self.last_usable_s = self.opened_s


class _ClosingError(Exception):
    """Raised in a connection's thread waiting its turn to decode when it is to close instead."""

    def __init__(self, reason: str | None) -> None:
        super().__init__(reason)
        self.reason = reason


class Listener:
    """Receives the wire protocol on ``endpoint`` in background threads, into ``queue``.

    Parameters
    ----------
    endpoint
        Where to listen; port 0 picks a free port (see :attr:`address`). An address other
        hosts can reach is warned about (:class:`ExposedListenerWarning`).
    queue
        Sessions, frames and ends are put there in arrival order.
    geometry
        A recording (or header) to use instead of the senders' session messages
        (``--geometry REC.h5``); frames must still fit it.
    max_connections
        TCP connections open at once (those being closed included), each with its thread.
        When all are taken, the oldest connection that has sent nothing usable for
        ``close_grace_s`` is closed to make room; if none has, the new connection is
        refused (told so by a short thread, at most :data:`MAX_REFUSING_THREADS` at once).
    idle_timeout_s
        A TCP connection that sends nothing usable (a session, frame or end taken) for this
        long is closed (with a refusal): garbage and refused messages do not keep it open.
    close_grace_s
        How long a connection may send nothing usable before it may be closed to make room.
    max_frame_bytes, max_session_bytes
        Bounds of a session (:func:`echoloc.realtime.protocol.decode_session`): larger ones are
        refused. A connection never holds more than one message of these sizes.
    accept_session
        Called (in the listener's thread) on every new session before it is taken; what
        it returns travels on the :class:`SessionEvent`; what it raises refuses the
        session (`echoloc stream` prepares its chain here, so a session the chain cannot
        use is refused to its sender, and the stream goes on).
    warn_interval_s
        Each kind of complaint becomes at most one line of :meth:`errors` this often.

    A bad message never ends a listener: it is counted (:meth:`counters`), named in a
    rate-limited line of :meth:`errors`, and, for a session, refused (on TCP the sender is
    told, :func:`echoloc.realtime.protocol.encode_refusal`, and the connection closed); the next
    session is served. TCP serves up to ``max_connections`` connections at once, each
    numbering its frames afresh; one of them at a time owns the stream (the first whose
    session is taken): the others wait, unread (TCP makes their senders wait), until it
    disconnects. On UDP every datagram is one message; a sender that starts again is
    told by its session's announced sequence number or by numbers that jump far
    (:class:`~echoloc.realtime.stream.SequenceTracker`).
    """

    def __init__(
        self,
        endpoint: Endpoint,
        frames: FrameQueue,
        *,
        geometry: Recording | None = None,
        max_connections: int = DEFAULT_MAX_CONNECTIONS,
        idle_timeout_s: float = DEFAULT_IDLE_TIMEOUT_S,
        max_frame_bytes: int = MAX_FRAME_BYTES,
        max_session_bytes: int = MAX_SESSION_BYTES,
        accept_session: Callable[[Recording], object] | None = None,
        warn_interval_s: float = WARN_INTERVAL_S,
        close_grace_s: float = CLOSE_GRACE_S,
    ) -> None:
        if max_connections < 1:
            raise EchoLocError(f"max_connections must be >= 1, got {max_connections}")
        if not (math.isfinite(idle_timeout_s) and idle_timeout_s > 0):
            raise EchoLocError(f"--idle-timeout must be a number of seconds > 0, got {idle_timeout_s}")
        if max_frame_bytes < 1 or max_session_bytes < 1:
            raise EchoLocError(f"size limits must be >= 1 byte, got {max_frame_bytes}, {max_session_bytes}")
        self.endpoint = endpoint
        self.queue = frames
        self.geometry = None if geometry is None else as_header(geometry)
        self.max_connections = max_connections
        self.idle_timeout_s = idle_timeout_s
        self.close_grace_s = close_grace_s
        self.max_frame_bytes = max_frame_bytes
        self.max_session_bytes = max_session_bytes
        self.accept_session = accept_session
        # The longest message a connection waits for: a session, or a frame (--geometry's are the
        # user's own, whatever their size).
        self._max_payload_bytes = max(max_frame_bytes, max_session_bytes)
        if self.geometry is not None:
            n_rx, n_samples = (int(d) for d in self.geometry.frames.shape[1:])
            self._max_payload_bytes = max(
                self._max_payload_bytes, frame_bytes(n_rx, n_samples, self.geometry.signal_kind)
            )
        self.session: Recording | None = None  # the one the queue's consumer was last given
        self._session_key: str | None = None
        self.received = 0
        self.malformed = 0
        self.rejected = 0
        self.refused = 0  # sessions refused and connections closed or refused by the receiver
        self.sessions_refused = 0  # of these, the sessions
        self.bytes_skipped = 0
        self.last_error: str | None = None
        self.last_refusal: str | None = None
        self.last_session_refusal: str | None = None
        self._warnings = _Warnings(warn_interval_s)
        self._lock = threading.Lock()  # counters, peers
        self._left = threading.Condition(self._lock)  # notified when a connection's thread ends
        self._peers: set[_Peer] = set()
        self._refusing = 0  # threads telling a refused connection why
        self._retired = {"lost": 0, "out_of_order": 0, "restarts": 0}
        self._owner: _Peer | None = None  # the sender whose frames go on the queue
        # Sessions are decoded and prepared one at a time: what that costs (JSON, a chain) is
        # bounded by one session's, however many connections send one at once.
        self._decoding = threading.Lock()
        self._turn = threading.Condition()
        self._stop = threading.Event()
        self._first_arrival: float | None = None
        family = socket.AF_INET6 if ":" in endpoint.host else socket.AF_INET
        kind = socket.SOCK_STREAM if endpoint.transport == "tcp" else socket.SOCK_DGRAM
        self._socket = socket.socket(family, kind)
        try:
            self._socket.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if kind == socket.SOCK_DGRAM:
                with contextlib.suppress(OSError):  # room for a burst of datagrams
                    self._socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
            self._socket.bind((endpoint.host, endpoint.port))
            if kind == socket.SOCK_STREAM:
                self._socket.listen(socket.SOMAXCONN)  # a burst of connections waits to be sorted
            self._socket.settimeout(0.1)
            bound_host = str(self._socket.getsockname()[0])
        except OSError as error:
            self._socket.close()
            raise EchoLocError(f"cannot listen on {endpoint}: {error.strerror or error}") from None
        # Kept: the socket's own name is gone once stop() has closed it.
        self._address = replace(endpoint, port=int(self._socket.getsockname()[1]))
        if not _is_loopback(bound_host):
            warnings.warn(
                f"{self._address}: listening on {bound_host}, which other hosts can reach: anyone who "
                "reaches this port can send frames and sessions (the protocol has no authentication); "
                "keep it on a trusted network, or listen on 127.0.0.1",
                ExposedListenerWarning,
                stacklevel=2,
            )
        self._udp = _Peer("udp", None, time.monotonic())
        if self.geometry is not None:
            self._session_key = self._udp.session_key = "--geometry"
            self.session = self._udp.session = self.geometry
            self.queue.put(SessionEvent(self.geometry))
        self._thread = threading.Thread(target=self._run, name=f"echoloc-listener {endpoint}", daemon=True)
        self._peer_threads: set[threading.Thread] = set()

    @property
    def address(self) -> Endpoint:
        """The bound endpoint (with the port the system chose for port 0)."""
        return self._address

    @property
    def serving(self) -> bool:
        """Is the listener taking connections (TCP) or datagrams (UDP)? False before
        :meth:`start`, after :meth:`stop`, and if its thread ever ended otherwise (a bug)."""
        return self._thread.is_alive() and not self._stop.is_set()

    @property
    def connections(self) -> int:
        """TCP connections open now (each served by its own thread)."""
        with self._lock:
            return len(self._peers)

    def start(self) -> Listener:
        self._thread.start()
        return self

    def stop(self) -> None:
        """Stop receiving and close the sockets (waits for the threads)."""
        self._stop.set()
        self.queue.close()
        with self._turn:
            self._turn.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        with self._lock:
            threads = list(self._peer_threads)
        for thread in threads:
            thread.join(timeout=2.0)
        self._socket.close()

    def __enter__(self) -> Listener:
        return self.start()

    def __exit__(self, *exc_info: object) -> None:
        self.stop()

    def errors(self) -> Iterator[str]:
        """Messages about refused input since the last call (one line each, for stderr),
        rate-limited (``warn_interval_s``); once stopped, also the counts of those held back."""
        return self._warnings.lines(everything=self._stop.is_set())

    def counters(self) -> dict[str, int]:
        """What the receiving side counted, for :meth:`echoloc.realtime.stream.StreamProcessor.stats`."""
        with self._lock:
            trackers = [peer.tracker for peer in self._peers] + [self._udp.tracker]
            sums = {
                name: total + sum(getattr(t, name) for t in trackers) for name, total in self._retired.items()
            }
            return {
                "received": self.received,
                "lost": sums["lost"],
                "dropped": self.queue.dropped,
                "out_of_order": sums["out_of_order"],
                "malformed": self.malformed,
                "rejected": self.rejected,
                "refused": self.refused,
                "restarts": sums["restarts"],
            }

    # -- what every thread uses

    def _count(self, counter: str, n: int = 1) -> None:
        with self._lock:
            setattr(self, counter, getattr(self, counter) + n)

    def _complain(self, counter: str, kind: str, message: str) -> None:
        """Count one refused thing in ``counter``; one line, rate-limited per ``kind``."""
        self._count(counter)
        self.last_error = message
        self._warnings.add(kind, message)

    def _run(self) -> None:
        try:
            if self.endpoint.transport == "tcp":
                self._run_tcp()
            else:
                self._run_udp()
        except OSError as error:
            if not self._stop.is_set():
                self._warnings.add("socket", f"{self._address}: {error}")

    # -- TCP

    def _run_tcp(self) -> None:
        while not self._stop.is_set():
            try:
                connection, address = self._socket.accept()
            except TimeoutError:
                continue
            except OSError as error:
                if self._stop.is_set():
                    return
                # Out of file descriptors and the like: say so, and go on accepting.
                self._warnings.add("accept", f"{self._address}: cannot accept a connection ({error})")
                time.sleep(0.1)
                continue
            try:
                self._admit(connection, address)
            except Exception as error:  # a bug here must not end the listener
                connection.close()
                self._warnings.add("internal", f"{self._address}: {type(error).__name__}: {error}")

    def _admit(self, connection: socket.socket, address: Any) -> None:
        """Serve a new connection in its own thread, making room for it if need be; refuse it if
        there is none. Connections being closed count until their thread has ended: at most
        ``max_connections`` threads serve connections, whatever arrives."""
        peer = _Peer(f"{address[0]}:{address[1]}", connection, time.monotonic())
        if self.geometry is not None:
            peer.session, peer.session_key = self.geometry, self._session_key
        with self._lock:
            if len(self._peers) >= self.max_connections and self._make_room():
                deadline = time.monotonic() + ADMIT_WAIT_S
                while len(self._peers) >= self.max_connections and (left := deadline - time.monotonic()) > 0:
                    self._left.wait(left)
            admitted = len(self._peers) < self.max_connections
            if admitted:
                self._peers.add(peer)
        if not admitted:
            reason = f"too many connections ({self.max_connections}), all busy: try again later"
            self._refuse_connection(connection, peer.name, reason)
            return
        self._start_thread(self._serve, (peer,), f"echoloc-listener {peer.name}")

    def _make_room(self) -> bool:
        """Mark the connection to close to make room (under the lock): the oldest that has sent
        nothing usable for ``close_grace_s``: one idle rather than one waiting its turn to decode,
        and that rather than one at work on what it sent (which cannot see it before it is done).
        One that is reading is shut down, so that it ends at once. False if there is none."""
        now = time.monotonic()
        candidates = [
            p
            for p in self._peers
            if not p.proven and p.closing is None and now - p.last_usable_s >= self.close_grace_s
        ]
        if not candidates:
            return False
        victim = min(candidates, key=lambda p: (p.busy + (p.busy and not p.waiting_turn), p.opened_s))
        victim.closing = (
            f"too many connections ({self.max_connections}): closed to make room, having sent no "
            f"session or frame that was taken for {now - victim.last_usable_s:.1f} s"
        )
        if not victim.busy and victim.connection is not None:
            with contextlib.suppress(OSError):
                victim.connection.shutdown(socket.SHUT_RD)
        return True

    def _prove(self, peer: _Peer) -> None:
        """``peer`` sent a session or frame that was taken: kept, even if marked to close."""
        with self._lock:
            peer.proven = True
            peer.closing = None

    def _start_thread(self, target: Callable[..., None], args: tuple[object, ...], name: str) -> None:
        thread = threading.Thread(target=target, args=args, name=name, daemon=True)
        with self._lock:
            self._peer_threads.add(thread)
        thread.start()

    def _refuse_connection(self, connection: socket.socket, name: str, reason: str) -> None:
        """Count a connection refused, and tell it why from a short thread (:meth:`_tell`: the
        accept loop never waits on it), unless ``MAX_REFUSING_THREADS`` are at it already."""
        self._refusal_counted(f"{self._address}: connection from {name} refused: {reason}", reason)
        with self._lock:
            room = self._refusing < MAX_REFUSING_THREADS
            self._refusing += room
        if not room:  # told without waiting: it may be lost in the reset that closing sends
            with contextlib.suppress(OSError):
                connection.setblocking(False)
                connection.send(encode_refusal(reason))
            connection.close()
            return

        def tell() -> None:
            try:
                self._tell(connection, reason)
            finally:
                connection.close()
                with self._lock:
                    self._refusing -= 1
                    self._peer_threads.discard(threading.current_thread())

        self._start_thread(tell, (), f"echoloc-listener refusing {name}")

    def _refusal_counted(self, message: str, reason: str, *, session: bool = False) -> None:
        self.last_refusal = reason
        if session:
            with self._lock:
                self.sessions_refused += 1
            self.last_session_refusal = reason
        self._complain("refused", "refused", message)

    def _serve(self, peer: _Peer) -> None:
        """One TCP connection, to its end: read, split, handle; refuse, close, hand over."""
        connection = peer.connection
        assert connection is not None
        buffer = bytearray()
        reason: str | None = None  # told to the sender
        closed = False  # by the receiver (idle, or to make room), not for what it sent
        linger = True  # read on after a refusal: only a sender still writing needs it
        try:
            connection.settimeout(0.1)
            while not self._stop.is_set():
                chunk: bytes | None
                try:
                    chunk = connection.recv(1 << 20)
                except TimeoutError:
                    chunk = None
                except OSError:
                    break
                with self._lock:  # as _make_room looks at it: a busy connection is never shut down
                    reason = peer.closing
                    peer.busy = reason is None and bool(chunk)
                idle_s = time.monotonic() - peer.last_usable_s
                if reason is None and chunk is None and idle_s > self.idle_timeout_s:
                    reason = (
                        f"idle for {idle_s:.1f} s: no session, frame or end taken "
                        f"(the receiver's timeout: {self.idle_timeout_s:g} s)"
                    )
                if reason is not None:
                    closed = True
                    break
                if chunk is None:
                    continue
                if not chunk:
                    break
                buffer += chunk
                try:
                    reason = self._consume(peer, buffer)
                finally:
                    peer.busy = False
                if reason is not None:
                    break
        except _ClosingError as closing:
            reason, closed = closing.reason, closing.reason is not None
        except Exception as error:  # a bug here must not leave the connection or the stream hanging
            reason = f"internal error of the receiver ({type(error).__name__})"
            self._warnings.add("internal", f"{self._address}: {peer.name}: {type(error).__name__}: {error}")
        finally:
            if closed and reason is not None:
                linger = False  # it sent nothing usable: nothing to drain
                self._refusal_counted(
                    f"{self._address}: connection from {peer.name} closed: {reason}", reason
                )
            if reason is not None and not self._stop.is_set():
                self._tell(connection, reason, linger)
            connection.close()
            self._release(peer)
            with self._lock:
                self._peers.discard(peer)
                for name in self._retired:
                    self._retired[name] += getattr(peer.tracker, name)
                self._peer_threads.discard(threading.current_thread())
                self._left.notify_all()

    @contextlib.contextmanager
    def _decoding_turn(self, peer: _Peer) -> Iterator[None]:
        """Hold the right to decode and prepare a session; raise :class:`_ClosingError` instead if
        ``peer`` is to close (or the listener stops) while it waits its turn."""
        peer.waiting_turn = True
        try:
            while not self._decoding.acquire(timeout=DECODING_POLL_S):
                if self._stop.is_set() or peer.closing is not None:
                    raise _ClosingError(None if self._stop.is_set() else peer.closing)
        finally:
            peer.waiting_turn = False
        try:
            yield
        finally:
            self._decoding.release()

    def _tell(self, connection: socket.socket, reason: str, linger: bool = True) -> None:
        """Send the refusal, then (``linger``) read on, discarding, a moment, so that it is not
        lost in the reset that closing with unread data sends."""
        with contextlib.suppress(OSError):
            connection.settimeout(1.0)
            connection.sendall(encode_refusal(reason))
            connection.shutdown(socket.SHUT_WR)
            if not linger:
                return
            connection.settimeout(0.05)
            deadline = time.monotonic() + REFUSAL_LINGER_S
            while time.monotonic() < deadline and not self._stop.is_set():
                try:
                    if not connection.recv(1 << 16):
                        break
                except TimeoutError:
                    continue

    def _consume(self, peer: _Peer, buffer: bytearray) -> str | None:
        """Handle the complete messages in ``buffer``; the reason to refuse the connection, or None."""
        messages, skipped, errors = split_messages(buffer, max_payload_bytes=self._max_payload_bytes)
        self._count("bytes_skipped", skipped)
        for error in errors:
            self._complain("malformed", "header", f"{self._address}: from {peer.name}: {error}")
        if skipped and not errors:
            self._complain(
                "malformed",
                "garbage",
                f"{self._address}: from {peer.name}: skipped {skipped} bytes that began no message",
            )
        for header, payload in messages:
            reason = self._safely(peer, header, payload)
            if reason is not None:
                return reason
        return None

    def _claim(self, peer: _Peer) -> bool:
        """Make ``peer`` the stream's owner, waiting while another one is; False if stopped."""
        with self._turn:
            while self._owner is not None and self._owner is not peer:
                if self._stop.is_set():
                    return False
                self._turn.wait(0.1)
            if self._stop.is_set():
                return False
            self._owner = peer
            return True

    def _release(self, peer: _Peer) -> None:
        """``peer`` is gone: if it owned the stream, say so on the queue and let the next one in."""
        if self._owner is not peer:
            return
        if not self._stop.is_set():
            self.queue.put(EndEvent(disconnected=True))
        with self._turn:
            self._owner = None
            self._turn.notify_all()

    # -- UDP

    def _run_udp(self) -> None:
        peer = self._udp
        while not self._stop.is_set():
            try:
                datagram, address = self._socket.recvfrom(MAX_UDP_BYTES + 1)
            except TimeoutError:
                continue
            except OSError as error:
                if self._stop.is_set():
                    return
                self._warnings.add("socket", f"{self._address}: {error}")
                continue
            if isinstance(address, tuple) and len(address) >= 2:
                peer.name = f"{address[0]}:{address[1]}"
            try:
                header = decode_header(datagram)
                end = header.header_bytes + header.payload_bytes
                if len(datagram) != end:
                    raise ProtocolError(
                        f"datagram of {len(datagram)} bytes, its header says {end} "
                        "(one datagram must hold exactly one message)"
                    )
            except ProtocolError as error:
                self._complain("malformed", "header", f"{self._address}: from {peer.name}: {error}")
                continue
            self._safely(peer, header, datagram[header.header_bytes :])

    # -- messages

    def _safely(self, peer: _Peer, header: MessageHeader, payload: bytes) -> str | None:
        """:meth:`_handle`, whatever the message makes it raise: counted, never raised (but
        :class:`_ClosingError`, for the connection's thread)."""
        try:
            return self._handle(peer, header, payload)
        except _ClosingError:
            raise
        except ProtocolError as error:
            self._complain("malformed", KINDS[header.kind], f"{self._address}: from {peer.name}: {error}")
        except Exception as error:  # what a peer can provoke must never end the listener
            text = " ".join(str(error).split())[:200]
            what = f"{KINDS.get(header.kind, 'message')} refused ({type(error).__name__}: {text})"
            self._complain("malformed", "internal", f"{self._address}: from {peer.name}: {what}")
            if header.kind == KIND_SESSION:
                return what
        return None

    def _handle(self, peer: _Peer, header: MessageHeader, payload: bytes) -> str | None:
        """One message of ``peer``; the reason to refuse its connection, or None."""
        arrival = time.monotonic()
        if header.kind == KIND_SESSION:
            return self._session(peer, header, payload)
        if header.kind == KIND_END:
            if self._owner is peer:
                self.queue.put(EndEvent())
            peer.last_usable_s = time.monotonic()
            return None
        if header.kind == KIND_REFUSAL:
            raise ProtocolError("a refusal message: only a receiver sends those")
        wire = decode_frame(header, payload)
        session = peer.session
        if session is None:
            self._complain(
                "rejected",
                "before-session",
                f"{self._address}: from {peer.name}: frames before any session message "
                "(send one, or give --geometry REC.h5)",
            )
            return None
        n_rx, n_samples = (int(d) for d in session.frames.shape[1:])
        problem = None
        if wire.samples.shape != (n_rx, n_samples):
            problem = (
                f"{wire.samples.shape[0]} channels x {wire.samples.shape[1]} samples, "
                f"the session has {n_rx} x {n_samples}"
            )
        elif wire.sample_rate_hz != session.sample_rate_hz:
            problem = f"{wire.sample_rate_hz:g} Hz, the session {session.sample_rate_hz:g} Hz"
        elif wire.signal_kind != session.signal_kind:
            problem = f"signal kind {wire.signal_kind}, the session {session.signal_kind}"
        elif wire.transmitter >= len(session.transmitters_m):
            problem = f"transmitter {wire.transmitter}, the session has {len(session.transmitters_m)}"
        if problem is not None:
            self._complain(
                "rejected",
                "misfit",
                f"{self._address}: from {peer.name}: frame {wire.sequence} refused: {problem}",
            )
            with self._lock:  # still a frame of the numbering: refused, not also counted lost
                peer.tracker.observe(wire.sequence)
            return None
        self._prove(peer)
        if not self._claim(peer):
            return None
        peer.last_usable_s = time.monotonic()  # after the wait: a sender waiting its turn is not idle
        number = peer.tracker.observe(wire.sequence)
        if number is None:
            return None
        self._count("received")
        if self._first_arrival is None:
            self._first_arrival = arrival
        time_s = wire.frame_time_s if math.isfinite(wire.frame_time_s) else arrival - self._first_arrival
        self.queue.put(StreamFrame(number, wire.samples, time_s, wire.transmitter, arrival))
        return None

    def _session(self, peer: _Peer, header: MessageHeader, payload: bytes) -> str | None:
        """A session message: taken (and, if new, handed on), or refused with its reason."""
        source = str(self._address)
        if self.geometry is not None:  # --geometry: sessions are checked, never used
            with self._decoding_turn(peer):
                decode_session(
                    header,
                    payload,
                    source,
                    max_frame_bytes=self.max_frame_bytes,
                    max_session_bytes=self.max_session_bytes,
                )
            return None
        raw = (header.n_channels, header.n_samples, header.sample_rate_hz, header.signal_kind, payload)
        if raw == peer.session_raw:  # the same session again (UDP senders repeat it)
            self._announced(peer, header)
            return None
        announced: Recording | None = None
        key = ""
        prepared: object = None
        if raw == peer.refused_raw:  # refused already: not decoded again
            reason = peer.refused_reason
        else:
            try:
                with self._decoding_turn(peer):
                    announced = decode_session(
                        header,
                        payload,
                        source,
                        max_frame_bytes=self.max_frame_bytes,
                        max_session_bytes=self.max_session_bytes,
                    )
                    key = json.dumps(session_record(announced), sort_keys=True)
                    if key == peer.session_key:  # the same session, sent otherwise: what was prepared holds
                        prepared = peer.prepared
                    elif self.accept_session is not None:
                        prepared = self.accept_session(announced)
                reason = ""
            except _ClosingError:
                raise
            except Exception as error:  # every refusal, whatever raised it
                reason = _reason(error, source)
                peer.refused_raw, peer.refused_reason = raw, reason
        if reason or announced is None:
            self._refusal_counted(
                f"{source}: session from {peer.name} refused: {reason}", reason, session=True
            )
            return f"session refused: {reason}"
        if key != peer.session_key:
            if peer.session_key is not None:  # a new session numbers its frames afresh
                peer.tracker.restart(header.sequence if header.announces_sequence else None)
            peer.session, peer.session_key, peer.prepared = announced, key, prepared
        else:
            self._announced(peer, header)
        peer.session_raw = raw
        self._prove(peer)
        if not self._claim(peer):
            return None
        peer.last_usable_s = time.monotonic()
        if peer.session_key != self._session_key:  # only the owner's thread gets here
            self._session_key = peer.session_key
            self.session = peer.session
            self.queue.put(SessionEvent(announced, peer.prepared))
        return None

    def _announced(self, peer: _Peer, header: MessageHeader) -> None:
        """A session again: does the sequence number it announces say its sender started again?"""
        if not header.announces_sequence or peer.tracker.follows(header.sequence):
            return
        expected = peer.tracker.next
        # Numbered afresh from the next frame that comes: a session that overtook a frame or two
        # (a false restart) costs a count, never frames counted lost.
        peer.tracker.restart(counted=True)
        self._warnings.add(
            "restart",
            f"{self._address}: the sender at {peer.name} started again (its session announces frame "
            f"{header.sequence}, frame {expected} was next): numbering its frames afresh",
        )


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host.split("%", 1)[0]).is_loopback
    except ValueError:
        return False


def _reason(error: BaseException, source: str) -> str:
    """A refusal's reason in one line, without the ``source`` its message may begin with."""
    text = " ".join(str(error).split())
    if text.startswith(f"{source}: "):
        text = text[len(source) + 2 :]
    if not isinstance(error, EchoLocError):
        text = f"{type(error).__name__}: {text}"
    return text[:500] or type(error).__name__


# ----------------------------------------------------------------------------- sending


@dataclass(frozen=True)
class SendReport:
    """What :func:`send_recording` sent.

    ``confirmed``: on TCP, True when the receiver closed the connection after reading it to
    its end without refusing anything, False when it had not within the wait; None on UDP
    (nothing comes back).
    """

    frames: int
    seconds: float
    bytes: int
    late: int
    confirmed: bool | None = None

    def summary(self, endpoint: Endpoint) -> str:
        rate = self.frames / self.seconds if self.seconds > 0 else math.inf
        unconfirmed = (
            "; the receiver had not finished reading them when send stopped waiting"
            if self.confirmed is False
            else ""
        )
        return (
            f"sent {self.frames} frames ({self.bytes / 1e6:.2f} MB) to {endpoint} in {self.seconds:.2f} s: "
            f"{rate:.1f} frames/s; {self.late} sent behind schedule{unconfirmed}"
        )


REPLY_POLL_S = 0.02
"""How often a TCP sender looks for a refusal from its receiver while it sends, s."""


class _Replies:
    """What a TCP receiver sends back: nothing, or one refusal before it closes the connection
    (:func:`echoloc.realtime.protocol.encode_refusal`). Read without waiting while sending; a refusal
    is raised as an :class:`EchoLocError` naming the endpoint."""

    def __init__(self, sock: socket.socket, endpoint: Endpoint) -> None:
        self.sock = sock
        self.endpoint = endpoint
        self.closed = False  # the receiver closed its side (or reset the connection)
        self._inbox = bytearray()
        self._last_poll = time.monotonic()

    def poll(self, *, every_s: float = 0.0) -> None:
        """Read what has come (at most every ``every_s``); raise a refusal found in it."""
        now = time.monotonic()
        if now - self._last_poll < every_s:
            return
        self._last_poll = now
        while not self.closed:
            try:
                if not _readable_now(self.sock):
                    break
                chunk = self.sock.recv(1 << 12)
            except (BlockingIOError, InterruptedError):
                break
            except (OSError, ValueError):  # reset, or closed
                self.closed = True
                break
            self._take(chunk)

    def wait_closed(self, timeout_s: float) -> bool:
        """After the last message: wait until the receiver closes the connection (it has read
        everything) or ``timeout_s``; raise a refusal. True if it closed."""
        deadline = time.monotonic() + timeout_s
        while not self.closed:
            left = deadline - time.monotonic()
            if left <= 0:
                return False
            self.sock.settimeout(min(left, 0.1))
            try:
                chunk = self.sock.recv(1 << 12)
            except TimeoutError:
                continue
            except OSError:
                self.closed = True
                break
            self._take(chunk)
        return True

    def _take(self, chunk: bytes) -> None:
        if not chunk:
            self.closed = True
            return
        self._inbox += chunk
        messages, _, _ = split_messages(self._inbox, max_payload_bytes=MAX_REFUSAL_BYTES)
        for header, payload in messages:
            if header.kind == KIND_REFUSAL:
                self.closed = True
                raise EchoLocError(
                    f"{self.endpoint}: the receiver refused: {decode_refusal(header, payload)}"
                )


def _readable_now(sock: socket.socket) -> bool:
    """Has ``sock`` bytes (or its end, or an error) to read now? poll, not select: a busy process's
    descriptors pass 1024, beyond select's reach (as recording.py's reader pipe does it)."""
    if not hasattr(select, "poll"):  # Windows
        return bool(select.select([sock], [], [], 0)[0])
    poller = select.poll()
    poller.register(sock, select.POLLIN | select.POLLHUP | select.POLLERR)
    return bool(poller.poll(0))


def recording_span_s(recording: Recording) -> float:
    """Length of one pass of a recording on its own clock: first to last frame, plus one period.

    The period is the median step of its frame times (back-to-back frames without them).
    """
    times = np.array([frame_time_s(recording, i) for i in range(recording.n_frames)])
    period = recording.n_samples / recording.sample_rate_hz
    if len(times) > 1:
        period = float(np.median(np.diff(times)))
    return float(times[-1] - times[0] + period)


def _schedule_s(recording: Recording, speed: float, rate_hz: float | None) -> tuple[np.ndarray, float]:
    """When each frame is due after the start, s, and the length of one pass."""
    n = recording.n_frames
    if rate_hz is not None:
        return np.arange(n) / rate_hz, n / rate_hz
    if speed <= 0:
        return np.zeros(n), 0.0
    times = np.array([frame_time_s(recording, i) for i in range(n)])
    return (times - times[0]) / speed, recording_span_s(recording) / speed


def send_recording(
    recording: Recording,
    endpoint: Endpoint,
    *,
    speed: float = 1.0,
    rate_hz: float | None = None,
    loops: int = 1,
    sample_format: str = "auto",
    connect_timeout_s: float = 5.0,
    session_every_s: float = 1.0,
    stop: threading.Event | None = None,
    end: bool = True,
    confirm_timeout_s: float = 5.0,
) -> SendReport:
    """Replay ``recording`` to ``endpoint`` in the wire protocol.

    A session message goes first (on UDP again every ``session_every_s``, so a
    receiver started late still learns it; each announces the next frame's sequence
    number), then the frames with sequence numbers 0, 1, 2... running on across loops,
    then an end message (unless ``end`` is False). On TCP the receiver's refusal
    (a session it cannot use, too many connections) is raised as an
    :class:`EchoLocError` as soon as it arrives; after the last message the sender
    waits up to ``confirm_timeout_s`` for the receiver to read everything and close
    (:attr:`SendReport.confirmed`). ``speed``: 1 plays at the recording's pace (its ``frame_times``, else
    back-to-back frames), N is N times faster, 0 as fast as the receiver takes it
    (on TCP the receiver's back-pressure sets the pace). ``rate_hz`` fixes frames per
    second instead. ``sample_format`` ``"auto"``: :func:`lossless_format`. ``loops`` 0
    loops until ``stop`` is set.
    """
    if rate_hz is not None and not (math.isfinite(rate_hz) and rate_hz > 0):
        raise EchoLocError(f"--rate must be > 0 frames/s, got {rate_hz}")
    if not (math.isfinite(speed) and speed >= 0):
        raise EchoLocError(f"--speed must be >= 0 (0: as fast as possible), got {speed}")
    if not (math.isfinite(connect_timeout_s) and connect_timeout_s >= 0):
        raise EchoLocError(
            f"--connect-timeout must be a finite number of seconds >= 0, got {connect_timeout_s}"
        )
    udp = endpoint.transport == "udp"
    if recording.signal_kind == "iq":
        sample_format = "complex64"
    elif sample_format == "auto":
        sample_format = lossless_format(recording, udp)
    stop = stop or threading.Event()
    session = encode_session(recording, sample_format=sample_format, next_sequence=0)
    due, pass_s = _schedule_s(recording, speed, rate_hz)
    times = [frame_time_s(recording, i) for i in range(recording.n_frames)]
    span_s = recording_span_s(recording)  # frame times of pass k are shifted by k spans
    if sample_format == "int16":
        peak = float(np.max(np.abs(recording.frames)))
        if peak < 256:
            warnings.warn(
                f"{recording.source}: int16 rounds samples to whole ADC counts and the largest is "
                f"{peak:.3g}: the signal keeps fewer than 9 bits (use float32 unless these are counts)",
                stacklevel=2,
            )
    if udp and len(session) > MAX_UDP_BYTES:
        raise EchoLocError(
            f"the session message is {len(session)} bytes, over the {MAX_UDP_BYTES} of one UDP datagram "
            "(a large background?): use TCP, or --geometry REC.h5 on the receiving side"
        )
    # Replayed more than once, a recording's payloads (the samples in the wire's format and
    # their CRC) are made once and kept, up to REPLAY_PAYLOAD_BYTES: later loops send them again.
    payloads: dict[int, FramePayload] = {}
    room_bytes = REPLAY_PAYLOAD_BYTES if loops != 1 else 0
    sock = _connect(endpoint, connect_timeout_s)
    replies = _Replies(sock, endpoint)
    sent_frames = sent_bytes = late = 0
    try:

        def send(message: bytes) -> None:
            nonlocal sent_bytes
            if udp:
                sock.send(message)
            else:
                sock.sendall(message)
                replies.poll(every_s=REPLY_POLL_S)
            sent_bytes += len(message)

        send(session)
        last_session = time.monotonic()
        start = time.monotonic()
        loop = 0
        while not stop.is_set() and (loops == 0 or loop < loops):
            for index in range(recording.n_frames):
                if stop.is_set():
                    break
                target = start + loop * pass_s + float(due[index])
                wait = target - time.monotonic()
                if wait > 0:
                    time.sleep(wait)
                elif wait < -0.010 and speed != 0:
                    late += 1
                if udp and time.monotonic() - last_session >= session_every_s:
                    send(encode_session(recording, sample_format=sample_format, next_sequence=sent_frames))
                    last_session = time.monotonic()
                transmitter = (
                    0 if recording.frame_transmitter is None else int(recording.frame_transmitter[index])
                )
                payload = payloads.get(index)
                if payload is None:
                    payload = frame_payload(
                        recording.frames[index],
                        signal_kind=recording.signal_kind,
                        sample_format=sample_format,
                    )
                    if len(payload.data) <= room_bytes:
                        payloads[index] = payload
                        room_bytes -= len(payload.data)
                message = frame_message(
                    payload,
                    sequence=sent_frames,
                    sample_rate_hz=recording.sample_rate_hz,
                    frame_time_s=times[index] + loop * span_s,
                    transmitter=transmitter,
                    signal_kind=recording.signal_kind,
                )
                if udp and len(message) > MAX_UDP_BYTES:
                    raise EchoLocError(
                        f"a frame is {len(message)} bytes, over the {MAX_UDP_BYTES} of one UDP datagram: "
                        "use --sample-format int16 (or float32), or TCP"
                    )
                send(message)
                sent_frames += 1
            loop += 1
        if end:
            send(encode_end(sent_frames))
        seconds = time.monotonic() - start
        confirmed = None
        if not udp:
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_WR)
            confirmed = replies.wait_closed(confirm_timeout_s)
        return SendReport(sent_frames, seconds, sent_bytes, late, confirmed)
    except (BrokenPipeError, ConnectionResetError):
        if not udp:
            replies.poll()  # the refusal that came before the connection broke, if any
        raise EchoLocError(
            f"{endpoint}: the receiver closed the connection after {sent_frames} frames"
        ) from None
    except ConnectionRefusedError:
        raise EchoLocError(f"{endpoint}: nothing listens there (start `echoloc stream` first)") from None
    finally:
        sock.close()


REPLAY_PAYLOAD_BYTES = 256 * 2**20
"""The most wire bytes of a recording :func:`send_recording` keeps to send again on its next
loops (making a frame's payload, its bytes and CRC-32, is much of what sending it costs)."""


def lossless_format(recording: Recording, udp: bool = False) -> str:
    """float32 when every sample is a float32 value (no rounding), else float64 (float32 on UDP).

    On UDP a frame must fit one datagram: float64 frames of more than about 8000
    samples in all do not, and are sent rounded to float32 (a relative error of
    6e-8, far below any ADC's).
    """
    return "float32" if udp or _single_precision_exact(recording.frames) else "float64"


def _single_precision_exact(frames: Any) -> bool:
    """Is every sample a float32 value (complex64 for complex samples)?"""
    frames = np.asarray(frames)
    return bool(
        np.array_equal(frames.astype(np.complex64 if frames.dtype.kind == "c" else np.float32), frames)
    )


def _connect(endpoint: Endpoint, timeout_s: float) -> socket.socket:
    """A connected socket; TCP retries until ``timeout_s`` so the sender may start first."""
    family = socket.AF_INET6 if ":" in endpoint.host else socket.AF_INET
    if endpoint.transport == "udp":
        sock = socket.socket(family, socket.SOCK_DGRAM)
        sock.connect((endpoint.host, endpoint.port))
        return sock
    deadline = time.monotonic() + timeout_s
    while True:
        sock = socket.socket(family, socket.SOCK_STREAM)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        try:
            sock.connect((endpoint.host, endpoint.port))
            return sock
        except OSError as error:
            sock.close()
            if time.monotonic() >= deadline:
                raise EchoLocError(
                    f"{endpoint}: cannot connect ({error.strerror or error}); is `echoloc stream` running?"
                ) from None
            time.sleep(0.05)


# ----------------------------------------------------------------------------- recording


def _lossless_storage(first: FrameBatch | None) -> type[np.floating[Any]]:
    """float32 when every sample of the first batch is a float32 value (float32 or int16 on
    the wire, or complex64), else float64: frames arrive as float64 whatever the wire carried,
    and a sender that chose float64 (:func:`lossless_format`) must not be rounded on disk."""
    return np.float32 if first is None or _single_precision_exact(first.frames) else np.float64


class Recorder:
    """Appends frames to an HDF5 recording from its own thread, one flushed batch at a time.

    Frames given to :meth:`add` are gathered into batches of ``batch_frames`` frames
    or ``batch_s`` seconds, whichever comes first, and appended by
    :func:`echoloc.io.recording.append_recording_stream`: a recorder killed at any
    moment loses at most the batch it was gathering or writing. The file is made with the
    first batch, in the precision the samples came in (:func:`_lossless_storage`; a sender
    that changes precision later is rounded to the first). The hand-over queue
    is bounded (``max_frames``, and ``max_bytes`` of samples); frames that find it full are
    counted in :attr:`dropped`, never waited for, so recording never holds up the stream.
    """

    @staticmethod
    def check_path(path: Path, *, force: bool = False) -> None:
        """Refuse, before anything arrives, a target that cannot be recorded to (one line), and
        one that exists unless ``force`` (a recording is never replaced without asking)."""
        suffix = path.suffix.lower()
        if suffix not in (".h5", ".hdf5"):
            why = ": a .npz is readable only once complete" if suffix == ".npz" else ""
            raise EchoLocError(f"{path}: a stream is recorded to HDF5 (.h5 or .hdf5){why}")
        refuse_new_output(path, force=force)

    def __init__(
        self,
        path: Path,
        header: Recording,
        *,
        batch_frames: int = 64,
        batch_s: float = 0.5,
        max_frames: int = 1024,
        max_bytes: int = DEFAULT_QUEUE_BYTES,
        on_batch: Callable[[int], None] | None = None,
    ) -> None:
        if batch_frames < 1:
            raise EchoLocError(f"--batch-frames must be >= 1, got {batch_frames}")
        if not (math.isfinite(batch_s) and batch_s > 0):
            raise EchoLocError(f"--batch-seconds must be > 0, got {batch_s}")
        self.path = path
        self.header = as_header(header)
        self.batch_frames = batch_frames
        self.batch_s = batch_s
        self.frames = 0
        self.batches = 0
        self.dropped = 0
        self.max_bytes = max_bytes
        self._queued_bytes = 0  # samples handed over and not yet taken by the writer
        self._bytes_lock = threading.Lock()
        self.error: BaseException | None = None
        self._on_batch = on_batch
        self._queue: queue.Queue[StreamFrame | None] = queue.Queue(maxsize=max_frames)
        self._thread = threading.Thread(target=self._run, name=f"echoloc-recorder {path}", daemon=True)
        self._thread.start()

    def add(self, frame: StreamFrame) -> None:
        """Hand over one frame (never blocks; after a write error frames are counted as dropped)."""
        if self.error is not None:
            self.dropped += 1
            return
        size = int(np.asarray(frame.samples).nbytes)
        with self._bytes_lock:
            if self._queued_bytes > 0 and self._queued_bytes + size > self.max_bytes:
                self.dropped += 1
                return
            self._queued_bytes += size
        try:
            self._queue.put_nowait(frame)
        except queue.Full:
            self._taken(frame)
            self.dropped += 1

    def _taken(self, frame: StreamFrame) -> None:
        with self._bytes_lock:
            self._queued_bytes -= int(np.asarray(frame.samples).nbytes)

    def close(self) -> None:
        """Write what is gathered, close the file, and raise what the writer met (an EchoLocError)."""
        while self._thread.is_alive():
            try:
                self._queue.put(None, timeout=0.1)
                break
            except queue.Full:
                continue
        self._thread.join()
        if self.error is not None:
            raise self.error

    def _batches(self) -> Iterator[FrameBatch]:
        done = False
        while not done:
            frames: list[StreamFrame] = []
            started = time.monotonic()
            while len(frames) < self.batch_frames:
                left = self.batch_s - (time.monotonic() - started) if frames else 3600.0
                try:
                    item = self._queue.get(timeout=max(left, 1e-3))
                except queue.Empty:
                    break
                if item is None:
                    done = True
                    break
                self._taken(item)
                frames.append(item)
            if frames:
                stacked: Samples = np.stack([np.asarray(f.samples) for f in frames])
                batch = FrameBatch(
                    frames=stacked,
                    frame_times_s=np.array([f.time_s for f in frames], dtype=np.float64),
                    frame_transmitter=np.array([f.transmitter for f in frames], dtype=np.int64),
                )
                del frames
                yield batch
                self.frames += batch.n_frames
                self.batches += 1
                if self._on_batch is not None:
                    self._on_batch(self.frames)

    def _run(self) -> None:
        try:
            batches = self._batches()
            first = next(batches, None)
            append_recording_stream(
                self.header,
                batches if first is None else itertools.chain([first], batches),
                self.path,
                frames_dtype=_lossless_storage(first),
            )
        except BaseException as error:  # handed to close(), which raises it in the caller's thread
            self.error = error
            while True:  # what was handed over and will not be written
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                self.dropped += item is not None
