"""Types of echoloc.io's public names; lazy_loader reads its imports to load each on first use."""

from .export import SENSOR_FRAME_ID, write_mcap, write_ply
from .head import SensorHead, load_head
from .recording import (
    FrameBatch,
    Recording,
    RecordingWarning,
    append_recording_stream,
    read_recording,
    write_recording,
    write_recording_stream,
)

__all__ = [
    "SENSOR_FRAME_ID",
    "FrameBatch",
    "Recording",
    "RecordingWarning",
    "SensorHead",
    "append_recording_stream",
    "load_head",
    "read_recording",
    "write_mcap",
    "write_ply",
    "write_recording",
    "write_recording_stream",
]
