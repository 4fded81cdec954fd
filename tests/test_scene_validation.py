"""Scene values that cannot be simulated are refused with a message naming them."""

from __future__ import annotations

import numpy as np
import pytest

from echoloc.errors import SceneError
from echoloc.scene import REPORT_ARRAY, Array, Scene, scene_from_dict

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
        ({"array": {"transmitters_m": [[0, 0, 0], [0.1, 0, 0]]}, "reflectors": ONE}, "one transmitter"),
    ],
)
def test_unsimulatable_values_are_named(data: dict, named: str) -> None:  # type: ignore[type-arg]
    """NaN, infinities, negative seeds, reflectors behind the array or on a transducer, two transmitters."""
    with pytest.raises(SceneError, match=named.replace(".", r"\.")):
        scene_from_dict(data, "scene.toml")


def test_reflector_in_front_is_accepted() -> None:
    """The same checks let an ordinary scene through."""
    scene = Scene(
        REPORT_ARRAY, reflector_positions_m=np.array([[0.0, 0.0, 0.6]]), reflector_strengths=np.ones(1)
    )
    assert scene.reflector_positions_m.shape == (1, 3)
    assert isinstance(scene.array, Array)
