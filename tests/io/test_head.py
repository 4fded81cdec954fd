"""Sensor-head files: what they say reaches the session, the wire format round-trips, and a
head that cannot work is told apart from one that can."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from echoloc.errors import SceneError
from echoloc.io.head import SAMPLE_FORMATS, check_head, head_from_dict, is_head_file, load_head, read_geometry
from repo_paths import REPO

HEADS = REPO / "examples" / "heads"


def tables(**overrides: object) -> dict[str, object]:
    """A small valid head, with sections replaced."""
    base: dict[str, object] = {
        "array": {
            "transmitters_m": [[0.0, 0.0, 0.0]],
            "receivers_m": [[0.2, 0.0, 0.0], [-0.2, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, -0.2, 0.0]],
        },
        "acquisition": {"sample_rate_hz": 200e3, "n_samples": 1600, "frame_rate_hz": 100},
        "channels": {"order": [3, 2, 1, 0]},
    }
    base.update(overrides)
    return base


@pytest.mark.parametrize("name", ["bench-4mic", "mcu-4ch"])
def test_example_heads_load_and_can_work(name):
    head = load_head(HEADS / f"{name}.toml")
    assert is_head_file(HEADS / f"{name}.toml")
    assert head.header.n_frames == 0
    assert head.header.waveform is not None
    assert len(head.channel_order) == head.header.n_receivers == 4
    assert check_head(head).problems == ()
    assert read_geometry(HEADS / f"{name}.toml").receivers_m.tolist() == head.header.receivers_m.tolist()


def test_the_session_carries_the_files_geometry_air_and_pulse():
    head = head_from_dict(
        tables(
            air={"temperature_c": 30.0}, pulse={"code": "barker7", "carrier_hz": 40e3, "cycles_per_bit": 3}
        )
    )
    header = head.header
    assert header.receivers_m.tolist() == [[0.2, 0, 0], [-0.2, 0, 0], [0, 0.2, 0], [0, -0.2, 0]]
    assert header.temperature_c == 30.0
    # Dry air at 30 C: 331.3 sqrt(1 + 30/273.15) = 349.0 m/s (within the humidity-free models).
    assert header.speed_of_sound_m_s == pytest.approx(349.0, abs=0.5)
    # Barker-7 at 3 cycles a bit on 40 kHz: 21 carrier cycles, 0.525 ms, 105 samples at 200 kHz.
    assert len(header.waveform) == 105
    assert header.carrier_hz == 40e3


def test_a_channel_reaches_the_receiver_wired_to_it():
    head = head_from_dict(tables())  # receiver r on channel 3 - r
    counts = np.zeros((4, 1600), dtype=np.int16)
    for channel in range(4):
        counts[channel] = 1000 * (channel + 1)
    samples = head.samples(counts)
    for receiver in range(4):
        assert np.all(samples[receiver] == 1000 * (4 - receiver) / 32768)


@settings(max_examples=60, deadline=None)
@given(
    form=st.sampled_from(sorted(SAMPLE_FORMATS)),
    bits=st.integers(8, 16),
    iq=st.booleans(),
    seed=st.integers(0, 2**16),
)
def test_counts_and_samples_round_trip_within_half_a_count(form, bits, iq, seed):
    offset = 2.0 ** (bits - 1) if form.startswith("u") else 0.0  # unipolar: 0 V at mid-scale
    head = head_from_dict(
        tables(
            adc={"format": form, "bits": bits, "offset": offset},
            receiver={"signal_kind": "iq" if iq else "rf", "output_rate_hz": 50e3} if iq else {},
        )
    )
    rng = np.random.default_rng(seed)
    shape = (4, head.n_samples)
    samples = rng.uniform(-0.9, 0.9, shape) + (1j * rng.uniform(-0.9, 0.9, shape) if iq else 0)
    wire = head.counts(samples)
    assert wire.dtype == np.dtype(SAMPLE_FORMATS[form])
    assert wire.shape == (4, head.values_per_channel)
    back = head.samples(wire)
    lsb = 1 / head.adc.full_scale
    tolerance = 1e-6 if form == "float32" else 0.5 * lsb + 1e-12
    error = back - samples  # I and Q are quantised each on its own
    assert max(np.max(np.abs(error.real)), np.max(np.abs(np.imag(error)))) <= tolerance


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"reflectors": [{"position_m": [0, 0, 1]}]}, "unknown key 'reflectors'"),
        ({"channels": {"order": [0, 0, 1, 2]}}, "names a channel twice"),
        ({"channels": {"order": [0, 1, 2]}}, "each of the 4 receivers"),
        ({"channels": {"order": [0, 1, 2, 3], "loopback": 2}}, "loopback (2) is also a receiver's"),
        ({"channels": {"order": [0, 1, 2, 3], "count": 3}}, "channels.count (3) must exceed"),
        ({"adc": {"format": "int16", "bits": 20}}, "cannot exceed the 16 bits"),
        ({"adc": {"format": "int12"}}, "adc.format must be one of"),
        ({"adc": {"full_scale": 0}}, "adc.full_scale must be > 0"),
        ({"channels": {"order": [0, 1, 2, 3], "colour": 1}}, "[channels]: unknown key 'colour'"),
        ({"receiver": {"adc_bits": 12}}, "[receiver]: unknown key 'adc_bits'"),
        ({"acquisition": {"sample_rate_hz": -1}}, "sample_rate_hz"),
        ({"array": {"receivers_m": [[0, 0, 0]]}}, "transmitters_m and array.receivers_m are required"),
        ({"array": 5}, "[array] must be a table"),
        ({"adc": {"format": ["int16"]}}, "adc.format must be one of"),
    ],
)
def test_a_bad_head_file_is_one_clear_error_naming_the_key(change, message):
    with pytest.raises(SceneError) as info:
        head_from_dict(tables(**change), "bad.toml")
    assert str(info.value).startswith("bad.toml: ")
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_not_toml_is_one_clear_error(tmp_path: Path):
    path = tmp_path / "head.toml"
    path.write_text("[array\n")
    with pytest.raises(SceneError, match="not valid TOML"):
        load_head(path)


def test_the_figures_of_a_head_are_its_closed_forms():
    head = head_from_dict(tables())
    check = check_head(head)
    c = head.header.speed_of_sound_m_s
    assert check.frame_s == pytest.approx(1600 / 200e3)
    assert check.max_range_m == pytest.approx(c * 8e-3 / 2)
    assert check.blind_range_m == pytest.approx(c * check.pulse_s / 2)
    assert check.pulse_s == pytest.approx(13 * 4 / 50e3)  # barker13, 4 cycles a bit, 50 kHz
    assert check.bytes_per_s == 4 * 1600 * 2 * 100


def test_frames_longer_than_the_pulse_period_are_a_problem():
    # 2400 samples at 200 kHz: 12 ms, but a pulse every 10 ms.
    overlapping = tables(acquisition={"sample_rate_hz": 200e3, "n_samples": 2400, "frame_rate_hz": 100})
    assert any("overlap" in p for p in check_head(head_from_dict(overlapping)).problems)
    fitting = tables(acquisition={"sample_rate_hz": 200e3, "n_samples": 2000, "frame_rate_hz": 100})
    assert check_head(head_from_dict(fitting)).problems == ()


def test_receivers_on_a_line_are_noted_and_at_one_place_refused():
    line = {"transmitters_m": [[0, 0, 0]], "receivers_m": [[0.1, 0, 0], [0.2, 0, 0], [0.3, 0, 0]]}
    notes = check_head(head_from_dict(tables(array=line, channels={"order": [0, 1, 2]}))).notes
    assert any("one line" in n for n in notes)
    same = {"transmitters_m": [[0, 0, 0]], "receivers_m": [[0.1, 0, 0], [0.1, 0, 0], [0.3, 0, 0]]}
    problems = check_head(head_from_dict(tables(array=same, channels={"order": [0, 1, 2]}))).problems
    assert any("share a position" in p for p in problems)


def test_a_known_transducer_gives_the_piston_beam():
    head = head_from_dict(tables(transducers={"model": "piezo40"}, pulse={"carrier_hz": 40e3}))
    beam = check_head(head).beam_half_angle_deg
    # Piston: sin(theta_3dB) = 1.61634 / (k a), k = 2 pi f / c.
    from echoloc.physics.transducer import PRESETS

    ka = 2 * math.pi * 40e3 / head.header.speed_of_sound_m_s * PRESETS["piezo40"].radius_m
    assert beam == pytest.approx(math.degrees(math.asin(1.61634 / ka)), rel=1e-4)


def test_an_import_head_given_as_a_live_head_says_what_it_lacks(tmp_path: Path):
    path = tmp_path / "flat.toml"
    path.write_text('sample_rate_hz = 200000\nsignal_kind = "rf"\nreceivers = [[0.1, 0, 0]]\n')
    with pytest.raises(SceneError) as info:
        load_head(path)
    assert "import's head TOML" in str(info.value)
    assert "docs/HEAD.md" in str(info.value)


def test_import_samples_takes_a_live_head_file(tmp_path: Path):
    """One head file serves capture and import: samples imported with it locate as the head's
    simulation says (the geometry, pulse and air all come from the file)."""
    from click.testing import CliRunner

    from echoloc.cli.commands import cli
    from echoloc.io.recording import read_recording
    from echoloc.localise.evaluation import evaluate
    from echoloc.pipeline import prepare, run
    from echoloc.sim.simulation import simulate

    head_path = HEADS / "mcu-4ch.toml"
    head = load_head(head_path)
    simulated = simulate(head.scene({"reflectors": [{"position_m": [0.1, -0.05, 0.8]}], "seed": 2}), 3)
    samples = tmp_path / "samples.npy"
    np.save(samples, simulated.frames)
    out = tmp_path / "imported.h5"
    result = CliRunner().invoke(
        cli, ["import", "samples", str(samples), "--head", str(head_path), "-o", str(out)]
    )
    assert result.exit_code == 0, result.output
    imported = read_recording(out)
    assert np.array_equal(imported.frames, simulated.frames)
    assert np.array_equal(imported.waveform, head.header.waveform)
    objects = [o for _, o in run(prepare(imported))]
    assert evaluate(objects, np.tile([[[0.1, -0.05, 0.8]]], (3, 1, 1))).recall == 1.0


def test_head_check_prints_the_figures_and_refuses_a_head_that_cannot_work(tmp_path: Path, capsys):
    from click.testing import CliRunner

    from echoloc.cli import commands
    from echoloc.cli.commands import cli

    picture = tmp_path / "head.png"
    result = CliRunner().invoke(cli, ["head", "check", str(HEADS / "mcu-4ch.toml"), "--plot", str(picture)])
    assert result.exit_code == 0, result.output
    # 2400 samples at 250 kHz: 9.6 ms, c T / 2 = 343.2 x 0.0096 / 2 = 1.65 m; 4 x 2400 x 2 B x 100/s.
    assert "hears to 1.65 m" in result.output
    assert "19200 bytes a frame, 1.92 MB/s" in result.output
    assert picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    overlapping = tmp_path / "overlap.toml"
    text = (HEADS / "mcu-4ch.toml").read_text().replace("sample_rate_hz = 250e3", "sample_rate_hz = 200e3")
    overlapping.write_text(text)
    with pytest.raises(SystemExit) as info:
        commands.main(["head", "check", str(overlapping)])
    assert info.value.code == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("echoloc: error: ")
    assert "\n" not in error
    assert "frames would overlap" in error


def test_a_head_named_in_brackets_is_shown_as_written(tmp_path: Path):
    from click.testing import CliRunner

    from echoloc.cli.commands import cli

    text = (HEADS / "mcu-4ch.toml").read_text().replace('name = "mcu-4ch"', 'name = "board [/b] v2"')
    path = tmp_path / "head.toml"
    path.write_text(text)
    result = CliRunner().invoke(cli, ["head", "check", str(path)])
    assert result.exit_code == 0, result.output
    assert "board [/b] v2" in result.output
