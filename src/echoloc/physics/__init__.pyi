"""Types of echoloc.physics's public names; lazy_loader reads its imports to load each on first use."""

from .air import absorption_db_per_m, speed_of_sound_cramer_m_s, speed_of_sound_m_s
from .transducer import PRESETS, Transducer, array_factor, piston_beam_angles, piston_directivity
from .waveform import (
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

__all__ = [
    "PRESETS",
    "Transducer",
    "Waveform",
    "WaveformMetrics",
    "absorption_db_per_m",
    "array_factor",
    "barker",
    "barker_waveform",
    "chirp_waveform",
    "code_metrics",
    "golay_pair",
    "kasami_set",
    "mls",
    "modulate",
    "piston_beam_angles",
    "piston_directivity",
    "speed_of_sound_cramer_m_s",
    "speed_of_sound_m_s",
    "tone_burst",
    "waveform_by_name",
    "waveform_metrics",
]
