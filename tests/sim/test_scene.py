"""Tests of echoloc.sim.scene: the report's set-up and the validated TOML scene files.

Sources: docs/METHOD.md (report ch. 4, table 4.3: balls at 580, 596 and 665 mm; Barker-13,
50 kHz, decimated to 200 kHz; four receivers 0.25 m from the transmitter), the scene presets, and errors.py
(messages name the file, the field, the value).
"""

from __future__ import annotations

import itertools
import math
import textwrap
from pathlib import Path

import numpy as np
import pytest

from echoloc.errors import EchoLocError, SceneError
from echoloc.sim.scene import Array, Scene, SensorMotion, default_scene
from echoloc.sim.scenefile import load_scene, preset_names, preset_path
from repo_paths import REPO

SCENES = REPO / "src" / "echoloc" / "scenes"
REPORT_TOML = SCENES / "report-three-balls.toml"
RANDOM_TOML = SCENES / "random-1m3.toml"
ONE_REFLECTOR = "[[reflectors]]\nposition_m = [0.0, 0.0, 1.0]\n"


def test_every_scene_file_shipped_is_a_preset_by_its_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Each TOML under echoloc/scenes loads by its name (folder/file without .toml) from any
    directory, as that file; a file of that name in the working directory wins."""
    files = sorted(SCENES.rglob("*.toml"))
    names = [path.relative_to(SCENES).with_suffix("").as_posix() for path in files]
    assert list(preset_names()) == sorted(names)
    assert {"ch101", "random-1m3", "report/ball-fixed", "mapping/room"} <= set(names)
    monkeypatch.chdir(tmp_path)
    for name, path in zip(names, files, strict=True):
        assert preset_path(name).read_bytes() == path.read_bytes()  # (the installed copy, in CI's oldest job)
        assert repr(load_scene(name)) == repr(load_scene(path))  # (arrays inside: no ==)
    (tmp_path / "random-1m3").write_text("[[reflectors]]\nposition_m = [0.0, 0.0, 2.0]\n")
    assert load_scene("random-1m3").reflector_positions_m.tolist() == [[0.0, 0.0, 2.0]]


def test_default_scene_array_is_the_reports() -> None:
    """Transmitter at the origin; receivers at (±0.25, 0, 0) and (0, ±0.25, 0)."""
    scene = default_scene()
    assert np.array_equal(scene.array.transmitters_m, [[0.0, 0.0, 0.0]])
    expected = {(0.25, 0.0, 0.0), (-0.25, 0.0, 0.0), (0.0, 0.25, 0.0), (0.0, -0.25, 0.0)}
    assert {tuple(r) for r in scene.array.receivers_m.tolist()} == expected


def test_default_scene_pulse_and_air_are_the_reports() -> None:
    """Barker-13 × 4 cycles at 50 kHz, sampled at 200 kHz, 20 °C dry air (343.2 m/s)."""
    scene = default_scene()
    assert scene.pulse.code == "barker13"
    assert scene.pulse.cycles_per_bit == 4
    assert scene.pulse.carrier_hz == 50e3
    assert scene.sample_rate_hz == 200e3
    assert scene.temperature_c == 20.0
    assert scene.relative_humidity == 0.0
    assert scene.speed_of_sound_m_s == pytest.approx(343.2, abs=0.05)
    w = scene.waveform()
    assert len(w.samples) == 13 * 4 * 4
    assert w.chip_s == pytest.approx(4 / 50e3)


def test_default_scene_balls_are_table_4_3() -> None:
    """Three balls at ranges 580, 596 and 665 mm in front of the head (z > 0); two 16 mm apart."""
    scene = default_scene()
    p = scene.reflector_positions_m
    ranges = np.linalg.norm(p - scene.array.transmitters_m[0], axis=1)
    assert np.allclose(ranges, [0.580, 0.596, 0.665], atol=1e-9)
    assert np.all(p[:, 2] > 0)
    assert ranges[1] - ranges[0] == pytest.approx(0.016, abs=1e-9)
    assert np.array_equal(scene.reflector_strengths, [1.0, 1.0, 1.0])


def test_default_scene_range_resolution_is_below_ball_spacing() -> None:
    """Range resolution c × chip / 2 = 343.2 × 80 µs / 2 = 13.7 mm < 16 mm between the first two balls."""
    scene = default_scene()
    resolution = scene.speed_of_sound_m_s * scene.waveform().chip_s / 2
    assert resolution == pytest.approx(0.0137, abs=0.00005)
    assert resolution < 0.016


def test_default_scene_snr_matches_the_report() -> None:
    """Echo peak / noise std about 13 for the nearest ball (report: 2 Vpp against 150 mV noise).

    SNR convention (scene.py): sigma = 10^(-snr_db/20) for a unit echo at 1 m + 1 m.
    """
    scene = default_scene()
    assert scene.snr_db is not None
    sigma = 10 ** (-scene.snr_db / 20)
    p = scene.reflector_positions_m[0]
    r_tx = np.linalg.norm(p)
    r_rx = np.linalg.norm(scene.array.receivers_m - p, axis=1)
    snr = 1.0 / (r_tx * r_rx) / sigma
    assert np.all((snr > 12.0) & (snr < 14.0))


def test_report_example_file_equals_default_scene() -> None:
    """report-three-balls is default_scene(): same array, pulse, air, noise, balls (1 µm)."""
    loaded = load_scene(REPORT_TOML)
    scene = default_scene()
    assert np.array_equal(loaded.array.transmitters_m, scene.array.transmitters_m)
    assert np.array_equal(loaded.array.receivers_m, scene.array.receivers_m)
    assert loaded.pulse == scene.pulse
    assert loaded.sample_rate_hz == scene.sample_rate_hz
    assert loaded.n_samples == scene.n_samples
    assert loaded.temperature_c == scene.temperature_c
    assert loaded.relative_humidity == scene.relative_humidity
    assert loaded.snr_db == scene.snr_db
    assert loaded.seed == scene.seed
    assert np.array_equal(loaded.reflector_strengths, scene.reflector_strengths)
    assert np.max(np.abs(loaded.reflector_positions_m - scene.reflector_positions_m)) < 1e-6


def test_random_example_file_loads() -> None:
    """random-1m3: 1-5 reflectors in the cubic metre ahead, 0.5 mm path jitter, SNR 20 dB."""
    scene = load_scene(RANDOM_TOML)
    assert scene.random is not None
    assert scene.random.count == (1, 5)
    assert scene.random.x_m == (-0.5, 0.5)
    assert scene.random.y_m == (-0.5, 0.5)
    assert scene.random.z_m == (0.2, 1.2)
    assert scene.random.strength == (0.5, 2.0)
    assert scene.path_jitter_m == 0.0005
    assert scene.snr_db == 20.0
    assert scene.seed == 7
    assert len(scene.reflector_positions_m) == 0


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "scene.toml"
    path.write_text(textwrap.dedent(text), encoding="utf-8")
    return path


@pytest.mark.parametrize(
    ("text", "needles"),
    [
        pytest.param("colour = 'red'\n" + ONE_REFLECTOR, ["colour"], id="unknown-top-level-key"),
        pytest.param("[pulse]\nbaud = 3\n" + ONE_REFLECTOR, ["baud", "pulse"], id="unknown-pulse-key"),
        pytest.param(
            "[pulse]\ncarrier_hz = '50k'\n" + ONE_REFLECTOR, ["pulse.carrier_hz", "50k"], id="string-carrier"
        ),
        pytest.param("[pulse]\ncode = 'barker6'\n" + ONE_REFLECTOR, ["pulse.code", "barker6"], id="barker6"),
        pytest.param(
            "[air]\nrelative_humidity = 1.5\n" + ONE_REFLECTOR,
            ["air.relative_humidity", "1.5"],
            id="humidity-1.5",
        ),
        pytest.param("[[reflectors]]\nstrength = 2.0\n", ["reflectors[0]", "position_m"], id="no-position"),
        pytest.param(
            ONE_REFLECTOR + "[[reflectors]]\nposition_m = [1.0, 2.0]\n",
            ["reflectors[1].position_m"],
            id="two-coordinates",
        ),
        pytest.param(
            "[acquisition]\nn_samples = 2.5\n" + ONE_REFLECTOR, ["n_samples", "2.5"], id="float-count"
        ),
        pytest.param(
            "[random_reflectors]\ncount = [3, 1]\n",
            ["random_reflectors.count", "[3, 1]"],
            id="count-reversed",
        ),
        pytest.param("seed = 1\n", ["no reflectors"], id="empty-scene"),
        pytest.param("[pulse\ncode = 'barker13'\n", ["not valid TOML"], id="bad-syntax"),
    ],
)
def test_bad_scene_file_raises_naming_the_problem(tmp_path: Path, text: str, needles: list[str]) -> None:
    """Every key is checked; the one-line message names the file and the offending key/value."""
    path = _write(tmp_path, text)
    with pytest.raises(SceneError) as info:
        load_scene(path)
    message = str(info.value)
    assert str(path) in message
    assert "\n" not in message
    for needle in needles:
        assert needle in message


def test_missing_scene_file_raises(tmp_path: Path) -> None:
    """A missing file is a SceneError naming the path."""
    path = tmp_path / "nowhere.toml"
    with pytest.raises(SceneError, match="no such scene file") as info:
        load_scene(path)
    assert str(path) in str(info.value)


def test_temperature_below_absolute_zero_is_rejected_when_loading(tmp_path: Path) -> None:
    """Scene validation checks the air too: -300 °C is rejected by load_scene, naming the key."""
    path = _write(tmp_path, "[air]\ntemperature_c = -300.0\n" + ONE_REFLECTOR)
    with pytest.raises(SceneError, match="temperature_c") as info:
        load_scene(path)
    assert str(path) in str(info.value)


def test_carrier_above_nyquist_in_file_names_the_file(tmp_path: Path) -> None:
    """An impossible pulse in a scene file is reported against the file (errors.py: name file and field)."""
    path = _write(tmp_path, "[pulse]\ncarrier_hz = 150e3\n" + ONE_REFLECTOR)
    with pytest.raises(EchoLocError) as info:
        load_scene(path)
    assert str(path) in str(info.value)
    assert "carrier" in str(info.value)


def test_minimal_file_takes_the_report_defaults(tmp_path: Path) -> None:
    """Omitted sections default to the report's array, pulse, sampling and air."""
    scene = load_scene(_write(tmp_path, ONE_REFLECTOR))
    report = default_scene()
    assert np.array_equal(scene.array.receivers_m, report.array.receivers_m)
    assert scene.pulse == report.pulse
    assert scene.sample_rate_hz == report.sample_rate_hz
    assert scene.temperature_c == 20.0
    assert np.array_equal(scene.reflector_positions_m, [[0.0, 0.0, 1.0]])
    assert np.array_equal(scene.reflector_strengths, [1.0])
    assert scene.snr_db is None


@pytest.mark.parametrize(
    ("transmitters", "receivers"),
    [
        (np.zeros((0, 3)), np.zeros((1, 3))),
        (np.zeros((1, 2)), np.zeros((1, 3))),
        (np.zeros((1, 3)), np.array([[0.0, np.nan, 0.0]])),
    ],
)
def test_array_rejects_bad_shapes_and_non_finite(transmitters: np.ndarray, receivers: np.ndarray) -> None:
    """Positions are (n >= 1, 3) finite coordinates."""
    with pytest.raises(SceneError):
        Array(transmitters_m=transmitters, receivers_m=receivers)


def test_scene_rejects_mismatched_reflectors() -> None:
    """One strength per reflector position."""
    with pytest.raises(SceneError, match="strengths"):
        Scene(array=default_scene().array, reflector_positions_m=np.zeros((2, 3)), reflector_strengths=[1.0])


def test_report_balls_are_pairwise_distinct_in_range() -> None:
    """All range gaps of table 4.3 (16, 69, 85 mm) exceed the 13.7 mm range resolution."""
    ranges = np.linalg.norm(default_scene().reflector_positions_m, axis=1)
    gaps = sorted(abs(a - b) for a, b in itertools.combinations(ranges, 2))
    assert np.allclose(gaps, [0.016, 0.069, 0.085], atol=1e-9)


def test_pan_scan_is_a_triangle_wave_about_the_heads_vertical() -> None:
    motion = SensorMotion(pan_deg=30.0, scan_period_s=4.0)
    pan, tilt = motion.scan_angles_deg(np.array([0.0, 1.0, 2.0, 3.0, 0.5]))
    np.testing.assert_allclose(pan, [0.0, 30.0, 0.0, -30.0, 15.0], atol=1e-9)
    np.testing.assert_allclose(tilt, 0.0)
    rotation, _ = motion.poses(np.array([1.0]))
    boresight = rotation[0] @ [0.0, 0.0, 1.0]
    np.testing.assert_allclose(
        boresight, [math.sin(math.radians(30)), 0.0, math.cos(math.radians(30))], atol=1e-12
    )
    assert motion.moving
    with pytest.raises(EchoLocError, match="pan_deg"):
        SensorMotion(pan_deg=120.0)


def test_scan_keys_are_read_from_scene_files() -> None:
    from echoloc.sim.scenefile import scene_from_dict

    ball = {"reflectors": [{"kind": "point", "position_m": [0.0, 0.0, 1.0]}]}
    scene = scene_from_dict({**ball, "motion": {"pan_deg": 20.0, "tilt_deg": 5.0, "scan_period_s": 2.0}})
    assert scene.motion.pan_deg == 20.0
    assert scene.motion.tilt_deg == 5.0
    pan, tilt = scene.motion.scan_angles_deg(np.array([0.5]))
    assert pan[0] == pytest.approx(20.0)
    assert tilt[0] == pytest.approx(0.0, abs=1e-12)  # a quarter period behind
    with pytest.raises(EchoLocError, match="scan_period_s"):
        scene_from_dict({**ball, "motion": {"scan_period_s": 0.0}})
