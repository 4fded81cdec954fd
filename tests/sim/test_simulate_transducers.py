"""The simulator with a transducer model and air absorption (issue 3: the physics enters the simulator)."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from echoloc.errors import SceneError
from echoloc.physics.air import absorption_db_per_m
from echoloc.physics.transducer import PRESETS, apply_response, directivity
from echoloc.pipeline import find_echoes
from echoloc.sim.scene import Array, Scene
from echoloc.sim.scenefile import load_scene
from echoloc.sim.simulation import simulate

MONOSTATIC = Array(np.zeros((1, 3)), np.array([[0.001, 0.0, 0.0]]))


def one_echo(scene: Scene) -> tuple[float, float]:
    """(tof_s, amplitude) of the single echo the matched filter finds in a clean frame."""
    channel = find_echoes(simulate(scene, 1))[0].channels[0]
    assert len(channel.tof_s) == 1
    return float(channel.tof_s[0]), float(channel.amplitude[0])


def scene_with(position: list[float], **changes: object) -> Scene:
    return Scene(
        array=MONOSTATIC,
        reflector_positions_m=np.array([position]),
        reflector_strengths=np.array([1.0]),
        **changes,  # type: ignore[arg-type]
    )


def test_template_is_the_pulse_through_the_transducer_pair() -> None:
    """docs/FORMATS.md: the waveform is what an ideal point reflector returns, here through both
    transducers."""
    scene = scene_with([0.0, 0.0, 0.6], transducer="electrostatic50")
    recording = simulate(scene, 1)
    pulse = scene.waveform().samples
    through = apply_response(np.concatenate([pulse, np.zeros(400)]), PRESETS["electrostatic50"], 200e3)
    assert recording.waveform is not None
    assert recording.waveform == pytest.approx(through[: len(recording.waveform)], abs=1e-12)
    assert len(recording.waveform) > len(pulse)  # the ringing is kept


def test_round_trip_with_transducer_is_exact() -> None:
    """With the returned pulse as template, the matched filter's delay is the path time, exactly."""
    scene = scene_with([0.0, 0.0, 0.6], transducer="electrostatic50")
    tof, _ = one_echo(scene)
    path = 0.6 + np.linalg.norm(np.array([0.0, 0.0, 0.6]) - MONOSTATIC.receivers_m[0])
    assert tof == pytest.approx(path / scene.speed_of_sound_m_s, abs=1e-9)


def test_directivity_weights_the_echo_by_both_beams() -> None:
    """Off axis by theta, the echo falls by D(theta) for the transmitter and again for the receiver."""
    model = PRESETS["electrostatic50"]
    r = 0.6
    theta = np.radians(6.0)
    _, on_axis = one_echo(scene_with([0.0, 0.0, r], transducer="electrostatic50"))
    _, off_axis = one_echo(
        scene_with([r * np.sin(theta), 0.0, r * np.cos(theta)], transducer="electrostatic50")
    )
    # Receiver 1 mm from the transmitter: its angle differs by well under 0.1 degree.
    expected = float(directivity(model, theta, 50e3, 343.21)) ** 2
    assert off_axis / on_axis == pytest.approx(expected, rel=0.01)


def test_aiming_the_array_moves_the_beam() -> None:
    """A reflector off the boresight but on the aimed axis returns the on-axis amplitude."""
    point = np.array([0.2, 0.0, 0.6])
    aimed = dataclasses.replace(MONOSTATIC).aimed_at(point)
    _, straight = one_echo(scene_with(point.tolist(), transducer="electrostatic50"))
    _, pointed = one_echo(
        dataclasses.replace(scene_with(point.tolist(), transducer="electrostatic50"), array=aimed)
    )
    _, reference = one_echo(
        scene_with([0.0, 0.0, float(np.linalg.norm(point))], transducer="electrostatic50")
    )
    assert pointed == pytest.approx(reference, rel=0.01)
    assert straight < 0.5 * pointed


def test_absorption_attenuates_by_iso_9613_1_over_the_path() -> None:
    """ISO 9613-1 at the carrier over the two-way path: 10**(-alpha L / 20), for this narrow-band pulse."""
    r = 1.5
    _, dry = one_echo(scene_with([0.0, 0.0, r], relative_humidity=0.5))
    _, absorbed = one_echo(scene_with([0.0, 0.0, r], relative_humidity=0.5, absorption=True))
    alpha = float(absorption_db_per_m(50e3, 20.0, 0.5))
    assert absorbed / dry == pytest.approx(10 ** (-alpha * 2 * r / 20), rel=0.02)


def test_scene_file_transducers_section(tmp_path: Path) -> None:
    """[transducers] and aim_at_m are read from TOML; an unknown model is named in the error."""
    folder = tmp_path
    good = folder / "good.toml"
    good.write_text(
        '[array]\naim_at_m = [0.0, 0.0, 0.6]\n[transducers]\nmodel = "electrostatic50"\nabsorption = true\n'
        "[[reflectors]]\nposition_m = [0.0, 0.0, 0.6]\n"
    )
    scene = load_scene(good)
    assert scene.transducer == "electrostatic50"
    assert scene.absorption
    _, rx_axes = scene.array.axes()
    expected = np.array([0.0, 0.0, 0.6]) - scene.array.receivers_m
    assert rx_axes == pytest.approx(expected / np.linalg.norm(expected, axis=1, keepdims=True))
    bad = folder / "bad.toml"
    bad.write_text('[transducers]\nmodel = "sonar9000"\n[[reflectors]]\nposition_m = [0.0, 0.0, 0.6]\n')
    with pytest.raises(SceneError, match="sonar9000"):
        load_scene(bad)
