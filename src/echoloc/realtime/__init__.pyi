"""Types of echoloc.realtime's public names; lazy_loader reads its imports to load each on first use."""

from .capture import CaptureSource
from .liveview import LiveView
from .protocol import (
    ProtocolError,
    WireFrame,
    decode_frame,
    decode_header,
    decode_session,
    encode_end,
    encode_frame,
    encode_session,
)
from .serial_source import SerialSource
from .session import LiveSession, listener_events
from .soundcard_source import SoundCardSource
from .stream import (
    FrameQueue,
    LatencyHistogram,
    SequenceTracker,
    StreamFrame,
    StreamProcessor,
    StreamResult,
    StreamStats,
    stream_recording,
    warm_kernels,
)
from .transport import Endpoint, Listener, Recorder, parse_endpoint, send_recording

__all__ = [
    "CaptureSource",
    "Endpoint",
    "FrameQueue",
    "LatencyHistogram",
    "Listener",
    "LiveSession",
    "LiveView",
    "ProtocolError",
    "Recorder",
    "SequenceTracker",
    "SerialSource",
    "SoundCardSource",
    "StreamFrame",
    "StreamProcessor",
    "StreamResult",
    "StreamStats",
    "WireFrame",
    "decode_frame",
    "decode_header",
    "decode_session",
    "encode_end",
    "encode_frame",
    "encode_session",
    "listener_events",
    "parse_endpoint",
    "send_recording",
    "stream_recording",
    "warm_kernels",
]
