"""Scene values that cannot be simulated are refused with a message naming them."""

from __future__ import annotations

import re

import numpy as np
import pytest

from echoloc.errors import SceneError
from echoloc.sim.scene import REPORT_ARRAY, Array, Scene
from echoloc.sim.scenefile import scene_from_dict

ONE = [{"position_m": [0.0, 0.0, 0.6]}]


@pytest.mark.parametrize(
    ("data", "named"),
    [
        ({"noise": {"snr_db": float("nan")}, "reflectors": ONE}, "noise.snr_db"),
        ({"noise": {"path_jitter_m": float("inf")}, "reflectors": ONE}, "noise.path_jitter_m"),
        ({"random_reflectors": {"x_m": [float("nan"), 1.0]}}, "random_reflectors.x_m"),
        ({"pulse": {"code": ["barker13"]}, "reflectors": ONE}, "pulse.code"),
        ({"seed": -1, "reflectors": ONE}, "seed"),
        ({"reflectors": [{"position_m": [0.0, 0.0, -0.5]}]}, "not in front"),
        ({"reflectors": [{"position_m": [0.25, 0.0, 0.0]}]}, "sits on a transducer"),
        ({"random_reflectors": {"z_m": [-0.2, 1.0]}}, "random_reflectors.z_m"),
        (
            {
                "array": {"transmitters_m": [[0, 0, 0], [0.1, 0, 0]], "firing": "simultaneous"},
                "reflectors": ONE,
            },
            "different code per transmitter",
        ),
        (
            {
                "pulse": {"codes": ["barker13"]},
                "array": {"transmitters_m": [[0, 0, 0], [0.1, 0, 0]]},
                "reflectors": ONE,
            },
            "pulse.codes",
        ),
        ({"receiver": {"signal_kind": "audio"}, "reflectors": ONE}, "receiver.signal_kind"),
        ({"receiver": {"gain": {"kind": "stepped", "step_s": 0.0}}, "reflectors": ONE}, "step_s"),
        ({"reflectors": [{"kind": "plane", "centre_m": [0, 0, 1], "normal": [0, 0, 0]}]}, "width_m"),
        ({"reflectors": [{"kind": "sphere", "centre_m": [0, 0, 1], "radius_m": -0.1}]}, "radius"),
        ({"reflectors": [{"kind": "disc", "centre_m": [0, 0, 1]}]}, "reflectors[0].kind"),
        ({"reflectors": [{"kind": "sphere", "centre_m": [0, 0, 1], "radius": 0.1}]}, "'radius'"),
        ({"max_order": 3, "reflectors": ONE}, "max_order"),
        ({"air": {"turbulence": 0.5}, "reflectors": ONE}, "air.turbulence"),
        ({"motion": {"velocity_m_s": [1, 0]}, "reflectors": ONE}, "motion.velocity_m_s must be [x, y, z]"),
        ({"motion": {"velocity_m_s": [400.0, 0, 0]}, "reflectors": ONE}, "half the speed of sound"),
        (
            {"reflectors": [{"position_m": [0.0, 0.0, 0.6], "velocity_m_s": [0.0, 0.0, -400.0]}]},
            "reflector 0 moves at 400 m/s",
        ),
        (
            {"receiver": {"signal_kind": "envelope", "output_rate_hz": 13.0}, "reflectors": ONE},
            "output_rate_hz",
        ),
        ({"receiver": {"output_rate_hz": 77777.0}, "reflectors": ONE}, "receiver.output_rate_hz"),
    ],
)
def test_unsimulatable_values_are_named(data: dict, named: str) -> None:  # type: ignore[type-arg]
    """NaN, infinities, negative seeds, reflectors behind the array or on a transducer, bad specs."""
    with pytest.raises(SceneError, match=re.escape(named)):
        scene_from_dict(data, "scene.toml")


def test_reflector_in_front_is_accepted() -> None:
    """The same checks let an ordinary scene through."""
    scene = Scene(
        REPORT_ARRAY, reflector_positions_m=np.array([[0.0, 0.0, 0.6]]), reflector_strengths=np.ones(1)
    )
    assert scene.reflector_positions_m.shape == (1, 3)
    assert isinstance(scene.array, Array)


@pytest.mark.parametrize("rate_hz", [float("nan"), 0.0, -1.0, 0.5, 5e-324, 1.01e9, float("inf")])
def test_scenes_and_recordings_refuse_the_same_sample_rates(rate_hz: float) -> None:
    """One range of sample rates, defined once (in the recording contract), for both."""
    from echoloc.errors import RecordingError
    from echoloc.io import recording
    from echoloc.sim import scene

    assert scene.SAMPLE_RATE_RANGE_HZ is recording.SAMPLE_RATE_RANGE_HZ
    assert not hasattr(scene, "MIN_SAMPLE_RATE_HZ")
    assert not hasattr(scene, "MAX_SAMPLE_RATE_HZ")
    with pytest.raises(SceneError, match=re.escape("acquisition.sample_rate_hz must lie in 1..1e+09 Hz")):
        Scene(REPORT_ARRAY, reflector_positions_m=np.zeros((0, 3)), sample_rate_hz=rate_hz)
    rec = recording.Recording(
        sample_rate_hz=rate_hz,
        transmitters_m=np.zeros((1, 3)),
        receivers_m=np.eye(3),
        frames=np.ones((1, 3, 8)),
        waveform=np.ones(4),
    )
    with pytest.raises(RecordingError, match=re.escape("sample_rate_hz must lie in 1..1e+09 Hz")):
        recording.validate_recording(rec)
