"""The physics commands: waveform, air and beam print the right figures and draw their plots."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from echoloc.cli.commands import main


def run_json(capsys: pytest.CaptureFixture[str], *args: str) -> dict:  # type: ignore[type-arg]
    with pytest.raises(SystemExit) as exit_info:
        main([*args, "--json"])
    assert exit_info.value.code == 0
    return json.loads(capsys.readouterr().out)  # type: ignore[no-any-return]


def test_waveform_barker13_reports_pslr_before_and_after_the_transducer(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Barker-13: PSLR 13 (22.3 dB) emitted; the band-pass pair can only smear it (report: 9:1 measured)."""
    record = run_json(
        capsys, "waveform", "barker13", "--cycles-per-bit", "4", "--carrier", "50e3", "--sample-rate", "200e3"
    )
    metrics = record["metrics"]
    emitted = metrics["emitted (autocorrelation)"]
    sent = metrics["after electrostatic50 pair, SENT template"]
    assert emitted["pslr_ratio"] == pytest.approx(13.0, rel=0.01)
    assert emitted["pslr_db"] == pytest.approx(22.28, abs=0.05)
    assert sent["pslr_ratio"] < emitted["pslr_ratio"]
    # The pair delays the SENT correlation peak by its group delay (31.8 µs analog, pair).
    assert 15e-6 < sent["peak_lag_s"] < 40e-6
    assert sent["mainlobe_width_s"] > emitted["mainlobe_width_s"]
    assert record["code"]["merit_factor"] == pytest.approx(14.08, abs=0.01)
    assert record["samples"] == 208


def test_waveform_without_sidelobes_gives_null_not_infinity(capsys: pytest.CaptureFixture[str]) -> None:
    """A plain tone burst has no sidelobes: JSON says null (JSON has no infinity)."""
    record = run_json(capsys, "waveform", "tone16", "--transducer", "none")
    assert record["metrics"]["emitted (autocorrelation)"]["pslr_ratio"] is None
    assert record["code"] is None


def test_air_reports_speed_and_iso_absorption(capsys: pytest.CaptureFixture[str]) -> None:
    """20 °C dry: 343.2 m/s; ISO 9613-1 at 50 kHz, 20 °C, 50 % RH: about 1.66 dB/m."""
    dry = run_json(capsys, "air", "--humidity", "0")
    assert dry["speed_of_sound_m_s"] == pytest.approx(343.2, abs=0.05)
    humid = run_json(capsys, "air", "--frequency", "50e3")
    assert humid["absorption"][0]["db_per_m"] == pytest.approx(1.66, abs=0.02)
    assert humid["impedance_rayl"] == pytest.approx(413, rel=0.01)


def test_beam_of_the_report_transducer(capsys: pytest.CaptureFixture[str]) -> None:
    """The 50 kHz preset has the report's 15° beam; the report's 1.62/ka formula is within 0.3 %."""
    record = run_json(capsys, "beam")
    assert record["full_angle_3db_deg"] == pytest.approx(15.0, abs=0.01)
    assert record["report_full_angle_3db_deg"] == pytest.approx(15.0, rel=0.003)
    assert record["transducers_for_fov"] == math.ceil(90 / 15)


def test_beam_array_grating_lobes(capsys: pytest.CaptureFixture[str]) -> None:
    """Spacing of one wavelength, unsteered: grating lobes at ±90° (sin θ = ±λ/d)."""
    wavelength = 343.2 / 40e3
    record = run_json(
        capsys, "beam", "--transducer", "piezo40", "--elements", "8", "--spacing-m", str(wavelength)
    )
    assert sorted(record["grating_lobes_deg"]) == pytest.approx([-90.0, 90.0], abs=1e-6)


@pytest.mark.parametrize(
    "args",
    [
        ("waveform", "barker13"),
        ("air",),
        ("beam", "--elements", "6"),
    ],
    ids=["waveform", "air", "beam"],
)
def test_each_command_draws_a_png(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, args: tuple[str, ...]
) -> None:
    """--plot writes a real PNG (signature and a plausible size)."""
    target = tmp_path / "figure.png"
    with pytest.raises(SystemExit) as exit_info:
        main([*args, "--plot", str(target)])
    assert exit_info.value.code == 0
    data = target.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(data) > 20_000


@pytest.mark.parametrize(
    "args",
    [
        ("waveform", "barker6"),
        ("waveform", "barker13", "--carrier", "150e3"),
        ("air", "--humidity", "1.5"),
        ("air", "--frequency", "-5"),
        ("beam", "--radius-m", "nan"),
        # A piston with ka < 1.616 never falls 3 dB; air colder than the formulas hold.
        ("beam", "--frequency", "1000"),
        ("air", "--temperature", "-273"),
    ],
)
def test_bad_physics_input_is_one_line_and_exit_2(
    capsys: pytest.CaptureFixture[str], args: tuple[str, ...]
) -> None:
    """Bad values name the problem in one line; exit code 2."""
    with pytest.raises(SystemExit) as exit_info:
        main(list(args))
    assert exit_info.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1
    assert lines[0].startswith("echoloc: error:")


def test_evaluate_json_is_valid_when_nothing_matches(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """JSON has no NaN: with no object found the RMSE is null, not NaN."""
    import dataclasses

    import numpy as np

    from echoloc.io.recording import write_recording
    from echoloc.sim.scene import default_scene
    from echoloc.sim.simulation import simulate

    recording = simulate(default_scene(), 1)
    noise = 1e-3 * np.random.default_rng(0).normal(size=recording.frames.shape)
    empty = dataclasses.replace(recording, frames=noise)
    path = write_recording(empty, tmp_path / "empty.h5")
    record = run_json(capsys, "evaluate", str(path))
    assert record["recall"] == 0.0
    assert record["rmse_m"] == [None, None, None]
