"""echoloc: airborne ultrasonic echolocation for robots.

The data flow is the architecture: ``scene -> simulate -> Recording -> echoes ->
locate -> objects``, one module per stage (see DESIGN.md).
"""

from echoloc.air import absorption_db_per_m, speed_of_sound_cramer_m_s, speed_of_sound_m_s
from echoloc.backprojection import (
    BackprojectionOptions,
    Backprojector,
    Grid,
    backproject_frame,
    frame_image,
    prepare_backprojection,
    run_backprojection,
)
from echoloc.echoes import ChannelEchoes, EchoOptions, FrameEchoes, MatchedFilter
from echoloc.errors import EchoLocError, GeometryError, RecordingError, SceneError, WaveformError
from echoloc.estimators import ESTIMATORS
from echoloc.evaluate import Evaluation, evaluate
from echoloc.export import SENSOR_FRAME_ID, write_mcap, write_ply
from echoloc.locate import (
    FrameObjects,
    LocatedObject,
    LocateOptions,
    associate,
    paired_closed_form,
    solve_positions,
)
from echoloc.map_export import read_grid_npz, write_grid_npz, write_grid_ply, write_map_mcap, write_octomap
from echoloc.mapping import (
    GridSpec,
    MapAccumulator,
    OccupancyGrid,
    SensorModel,
    build_map,
    map_accuracy,
    read_trajectory,
)
from echoloc.pipeline import Chain, find_echoes, frame_echoes, frame_objects, prepare, run
from echoloc.recording import Recording, RecordingWarning, read_recording, write_recording
from echoloc.scene import Array, Scene, default_scene
from echoloc.scenefile import load_scene
from echoloc.simulate import simulate
from echoloc.transducer import PRESETS, Transducer, array_factor, piston_beam_angles, piston_directivity
from echoloc.uncertainty import (
    ErrorMap,
    PositionErrors,
    SpacingRecommendation,
    SpacingStudy,
    UncertaintyArea,
    error_map,
    position_errors,
    recommended_spacing,
    spacing_study,
    uncertainty_area,
)
from echoloc.waveform import (
    Waveform,
    WaveformMetrics,
    barker,
    barker_waveform,
    chirp_waveform,
    code_metrics,
    golay_pair,
    kasami_set,
    mls,
    modulate,
    tone_burst,
    waveform_by_name,
    waveform_metrics,
)

__version__ = "0.1.0"

__all__ = [
    "ESTIMATORS",
    "PRESETS",
    "SENSOR_FRAME_ID",
    "Array",
    "BackprojectionOptions",
    "Backprojector",
    "Chain",
    "ChannelEchoes",
    "EchoLocError",
    "EchoOptions",
    "ErrorMap",
    "Evaluation",
    "FrameEchoes",
    "FrameObjects",
    "GeometryError",
    "Grid",
    "GridSpec",
    "LocateOptions",
    "LocatedObject",
    "MapAccumulator",
    "MatchedFilter",
    "OccupancyGrid",
    "PositionErrors",
    "Recording",
    "RecordingError",
    "RecordingWarning",
    "Scene",
    "SceneError",
    "SensorModel",
    "SpacingRecommendation",
    "SpacingStudy",
    "Transducer",
    "UncertaintyArea",
    "Waveform",
    "WaveformError",
    "WaveformMetrics",
    "__version__",
    "absorption_db_per_m",
    "array_factor",
    "associate",
    "backproject_frame",
    "barker",
    "barker_waveform",
    "build_map",
    "chirp_waveform",
    "code_metrics",
    "default_scene",
    "error_map",
    "evaluate",
    "find_echoes",
    "frame_echoes",
    "frame_image",
    "frame_objects",
    "golay_pair",
    "kasami_set",
    "load_scene",
    "map_accuracy",
    "mls",
    "modulate",
    "paired_closed_form",
    "piston_beam_angles",
    "piston_directivity",
    "position_errors",
    "prepare",
    "prepare_backprojection",
    "read_grid_npz",
    "read_recording",
    "read_trajectory",
    "recommended_spacing",
    "run",
    "run_backprojection",
    "simulate",
    "solve_positions",
    "spacing_study",
    "speed_of_sound_cramer_m_s",
    "speed_of_sound_m_s",
    "tone_burst",
    "uncertainty_area",
    "waveform_by_name",
    "waveform_metrics",
    "write_grid_npz",
    "write_grid_ply",
    "write_map_mcap",
    "write_mcap",
    "write_octomap",
    "write_ply",
    "write_recording",
]
