"""echoloc: airborne ultrasonic echolocation for robots.

The data flow is the architecture: ``scene -> simulate -> Recording -> echoes ->
locate -> objects``, one module per stage (see DESIGN.md).
"""

from echoloc.air import speed_of_sound_m_s
from echoloc.echoes import ESTIMATORS, ChannelEchoes, EchoOptions, FrameEchoes, MatchedFilter
from echoloc.errors import EchoLocError, GeometryError, RecordingError, SceneError, WaveformError
from echoloc.evaluate import Evaluation, evaluate
from echoloc.locate import (
    FrameObjects,
    LocatedObject,
    LocateOptions,
    associate,
    paired_closed_form,
    solve_positions,
)
from echoloc.pipeline import Chain, find_echoes, frame_echoes, frame_objects, prepare, run
from echoloc.recording import Recording, RecordingWarning, read_recording, write_recording
from echoloc.scene import Array, Scene, default_scene, load_scene
from echoloc.simulate import simulate
from echoloc.waveform import Waveform, barker, barker_waveform, modulate

__version__ = "0.1.0"

__all__ = [
    "ESTIMATORS",
    "Array",
    "Chain",
    "ChannelEchoes",
    "EchoLocError",
    "EchoOptions",
    "Evaluation",
    "FrameEchoes",
    "FrameObjects",
    "GeometryError",
    "LocateOptions",
    "LocatedObject",
    "MatchedFilter",
    "Recording",
    "RecordingError",
    "RecordingWarning",
    "Scene",
    "SceneError",
    "Waveform",
    "WaveformError",
    "__version__",
    "associate",
    "barker",
    "barker_waveform",
    "default_scene",
    "evaluate",
    "find_echoes",
    "frame_echoes",
    "frame_objects",
    "load_scene",
    "modulate",
    "paired_closed_form",
    "prepare",
    "read_recording",
    "run",
    "simulate",
    "solve_positions",
    "speed_of_sound_m_s",
    "write_recording",
]
