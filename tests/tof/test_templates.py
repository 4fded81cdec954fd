"""Matched-filter templates (report ch. 4.1): SENT, DIRECT and a recorded echo report the same tof.

Without a transducer model every path carries the emitted pulse itself, so a template
cut from a recording is the SENT template scaled and shifted: the matched filter must
report the same arrival with any of them, to far below a sample. With a transducer
model the direct path and the echo share the transducers' response too.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from echoloc.errors import EchoLocError, RecordingError
from echoloc.io.recording import Recording, write_recording
from echoloc.sim.reflectors import PointReflector
from echoloc.sim.scene import Array, RingDown, Scene
from echoloc.sim.simulation import simulate
from echoloc.tof.echoes import EchoOptions
from echoloc.tof.estimators import ESTIMATORS
from echoloc.tof.templates import Template, cut_template, read_template, sent_template, write_template

FS = 200e3
# A transmitter and a receiver 0.3 m apart, facing +z.
PAIR = Array(transmitters_m=np.array([[0.0, 0.0, 0.0]]), receivers_m=np.array([[0.3, 0.0, 0.0]]))


def tof_s(recording: Recording, template: Template | None) -> float:
    """The first echo's tof after the blanked direct path, by the matched filter."""
    options = EchoOptions(template=template, blanking_s=2e-3)
    echoes = ESTIMATORS["matched"].prepare(recording, options)(recording.frames[0])
    return float(echoes[0].tof_s[0])


def direct_recording(transducer: str | None) -> Recording:
    """An empty scene: only the direct path from transmitter to receiver."""
    return simulate(
        Scene(array=PAIR, ring_down=RingDown(direct_path=True), transducer=transducer, snr_db=None), 4
    )


def ball_recording(range_m: float, transducer: str | None, frames: int = 1) -> Recording:
    """A small ball as a point reflector (its truth point is then exactly on its echo's path)."""
    ball = PointReflector(np.array([0.15, 0.0, range_m]), 0.01)
    return simulate(Scene(array=PAIR, objects=(ball,), transducer=transducer, snr_db=None), frames)


def expected_tof_s(recording: Recording) -> float:
    assert recording.truth_positions_m is not None
    point = recording.truth_positions_m[0, 0]
    path = np.linalg.norm(point - PAIR.transmitters_m[0]) + np.linalg.norm(point - PAIR.receivers_m[0])
    assert recording.speed_of_sound_m_s is not None
    return float(path / recording.speed_of_sound_m_s)


def test_sent_template_is_the_recordings_waveform() -> None:
    recording = ball_recording(0.6, None)
    template = sent_template(recording)
    assert recording.waveform is not None
    assert np.array_equal(template.samples, recording.waveform)
    assert template.arrival_s == 0.0


@pytest.mark.parametrize("transducer", [None, "electrostatic50"])
def test_direct_template_reports_the_same_arrival_as_sent(transducer: str | None) -> None:
    """The DIRECT template, cut at the direct path's arrival d/c, gives the SENT tof within 2 ns."""
    direct = direct_recording(transducer)
    assert direct.speed_of_sound_m_s is not None
    template = cut_template(
        direct, receiver=0, frames=range(4), arrival="direct", speed_of_sound_m_s=direct.speed_of_sound_m_s
    )
    assert template.name == "direct"
    assert 0 < template.arrival_s < 100e-6  # the window opens 50 µs before the arrival, to the sample below
    ball = ball_recording(0.55, transducer)
    sent = tof_s(ball, None)
    assert tof_s(ball, template) == pytest.approx(sent, abs=2e-9)
    if transducer is None:
        assert sent == pytest.approx(expected_tof_s(ball), abs=1e-9)


def test_ball_template_cut_at_the_truth_times_another_ball() -> None:
    """A BALL template averaged over 5 frames at 0.5 m times a ball at 0.8 m to 1 ns (no transducer)."""
    near = ball_recording(0.5, None, frames=5)
    assert near.speed_of_sound_m_s is not None
    template = cut_template(
        near, receiver=0, frames=range(5), arrival="truth", speed_of_sound_m_s=near.speed_of_sound_m_s
    )
    far = ball_recording(0.8, None)
    assert tof_s(far, template) == pytest.approx(expected_tof_s(far), abs=1e-9)


def test_an_explicit_arrival_shifts_the_reported_tof_by_the_same_amount() -> None:
    """Declaring the arrival 10 µs later than it is makes every tof 10 µs earlier."""
    direct = direct_recording(None)
    c = direct.speed_of_sound_m_s
    assert c is not None
    true_arrival = 0.3 / c
    honest = cut_template(direct, receiver=0, frames=range(1), arrival=true_arrival, speed_of_sound_m_s=c)
    late = cut_template(
        direct,
        receiver=0,
        frames=range(1),
        arrival=true_arrival + 10e-6,
        speed_of_sound_m_s=c,
        start_s=true_arrival - 50e-6,
        stop_s=true_arrival + 1.2e-3,
    )
    ball = ball_recording(0.7, None)
    assert tof_s(ball, honest) - tof_s(ball, late) == pytest.approx(-10e-6, abs=2e-9)


def test_template_file_round_trip(tmp_path: Path) -> None:
    template = Template(np.sin(np.arange(40) / 3.0), FS, 12.5e-6, "ball")
    back = read_template(write_template(template, tmp_path / "ball.npz"))
    assert np.array_equal(back.samples, template.samples)
    assert (back.sample_rate_hz, back.arrival_s, back.name) == (FS, 12.5e-6, "ball")


def test_bad_template_files_are_refused_with_one_line(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="no such template"):
        read_template(tmp_path / "missing.npz")
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(RecordingError, match="not a template file"):
        read_template(tmp_path / "junk.npz")
    np.savez(tmp_path / "other.npz", format="something-else", version=1)
    with pytest.raises(RecordingError, match="not an echoloc-template"):
        read_template(tmp_path / "other.npz")
    np.savez(tmp_path / "nan.npz", format="echoloc-template", version=1, samples=[np.nan, 1.0],
             sample_rate_hz=FS, arrival_s=0.0)  # fmt: skip
    with pytest.raises(RecordingError, match="finite"):
        read_template(tmp_path / "nan.npz")


def test_mismatched_rate_and_bad_windows_are_refused() -> None:
    ball = ball_recording(0.6, None)
    with pytest.raises(EchoLocError, match="sampled at 100000 Hz"):
        ESTIMATORS["matched"].prepare(ball, EchoOptions(template=Template(np.ones(8), 100e3)))
    c = ball.speed_of_sound_m_s
    assert c is not None
    with pytest.raises(EchoLocError, match="not inside the frame"):
        cut_template(ball, receiver=0, frames=range(1), arrival="truth", speed_of_sound_m_s=c, stop_s=1.0)
    with pytest.raises(EchoLocError, match="receiver 3"):
        cut_template(ball, receiver=3, frames=range(1), arrival="truth", speed_of_sound_m_s=c)
    no_truth = replace(ball, truth_positions_m=None)
    with pytest.raises(EchoLocError, match="truth_positions"):
        cut_template(no_truth, receiver=0, frames=range(1), arrival="truth", speed_of_sound_m_s=c)


def run_cli(capsys: pytest.CaptureFixture[str], *args: object) -> tuple[int, str, str]:
    """``echoloc ARGS`` in-process through main(), which turns errors into exit codes."""
    from echoloc.cli import commands as cli

    capsys.readouterr()
    with pytest.raises(SystemExit) as info:
        cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    assert isinstance(info.value.code, int)
    return info.value.code, out, err


def test_template_command_and_option(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`echoloc template` writes a DIRECT template that `echoes --template` uses; bad input exits 2."""
    direct = write_recording(direct_recording(None), tmp_path / "direct.h5")
    ball = write_recording(ball_recording(0.6, None), tmp_path / "ball.h5")
    code, _, err = run_cli(capsys, "template", direct, "-o", tmp_path / "d.npz", "--arrival", "direct")
    assert code == 0
    assert "direct template" in err
    args = ["echoes", ball, "--json", "--blanking-s", "2e-3"]
    code, sent, _ = run_cli(capsys, *args)
    assert code == 0
    code, with_direct, _ = run_cli(capsys, *args, "--template", tmp_path / "d.npz")
    assert code == 0

    def first_tof(output: str) -> float:
        return float(json.loads(output.splitlines()[0])["channels"][0]["echoes"][0]["tof_s"])

    assert first_tof(with_direct) == pytest.approx(first_tof(sent), abs=2e-9)
    code, _, err = run_cli(capsys, "template", direct, "-o", tmp_path / "x.npz", "--arrival", "soon")
    assert code == 2
    assert err.count("\n") == 1
    assert "--arrival" in err
    code, _, err = run_cli(capsys, *args, "--template", tmp_path / "none.npz")
    assert code == 2
    assert "no such template file" in err


def test_a_template_for_another_estimator_is_refused_not_ignored(tmp_path: Path) -> None:
    """Only the matched filter uses a template; any other estimator must say so, not ignore it."""
    from echoloc.tof.estimators import prepare_estimator

    ball = ball_recording(0.6, None)
    template = sent_template(ball)
    with pytest.raises(
        EchoLocError, match="only to the matched and envelope-peak estimators, not to 'envelope-zero'"
    ):
        prepare_estimator(ball, EchoOptions(template=template), "envelope-zero")
    (tmp_path / "object.npz").write_bytes(b"\x80\x04K\x01.")  # a pickle, not an .npz
    with pytest.raises(RecordingError, match="not a template file") as info:
        read_template(tmp_path / "object.npz")
    assert "allow_pickle" not in str(info.value)
