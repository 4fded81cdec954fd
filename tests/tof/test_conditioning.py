"""Frame conditioning (echoloc.tof.conditioning): background, time-varying gain, blind zone; and its wiring.

Sources: docs/FORMATS.md (``background``: a recording of the empty scene, to subtract;
``receiver_gain``: ``frames / receiver_gain`` is the signal at the transducer);
the report's ch. 3-4 (the transmitter's ring-down and the direct path come before
any echo and must not be reported).
"""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from echoloc.cli import commands as cli
from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording, write_recording
from echoloc.pipeline import frame_echoes, prepare
from echoloc.sim.receiver import AdcSpec, GainSpec
from echoloc.sim.scene import REPORT_ARRAY, ReceiverSpec, RingDown, Scene
from echoloc.sim.simulation import simulate
from echoloc.tof.conditioning import (
    Conditioning,
    blind_zone_s,
    compensate_gain,
    condition_frame,
    condition_frames,
    conditioned,
    effective_options,
    parse_blind_zone,
    ring_down_end_s,
)
from echoloc.tof.echoes import EchoOptions
from echoloc.tof.estimators import ESTIMATORS

FS = 200e3


def small_recording(frames: np.ndarray, **fields: object) -> Recording:
    waveform = np.sin(2 * np.pi * 50e3 * np.arange(16) / FS)
    base = Recording(FS, np.zeros((1, 3)), REPORT_ARRAY.receivers_m[: frames.shape[1]], frames, waveform)
    return replace(base, **fields)  # type: ignore[arg-type]


def reflector_scene(**fields: object) -> Scene:
    """One ball at 0.6 m straight ahead of the report's head, the given extras."""
    return Scene(
        array=REPORT_ARRAY,
        reflector_positions_m=np.array([[0.02, -0.01, 0.6]]),
        reflector_strengths=np.array([1.0]),
        **fields,  # type: ignore[arg-type]
    )


def true_tof_s(scene: Scene) -> np.ndarray:
    p = scene.reflector_positions_m[0]
    return (
        np.linalg.norm(p) + np.linalg.norm(scene.array.receivers_m - p, axis=1)
    ) / scene.speed_of_sound_m_s


# --- background -------------------------------------------------------------------------


def test_background_subtraction_restores_the_frame() -> None:
    """frames = echo + background; subtracting the recorded background gives the echo back exactly."""
    rng = np.random.default_rng(3)
    echo = rng.normal(size=(2, 4, 300))
    background = rng.normal(size=(4, 300))
    recording = small_recording(echo + background, background=background)
    for index in range(2):
        np.testing.assert_allclose(
            condition_frame(recording.frames[index], recording, Conditioning(), index),
            echo[index],
            atol=1e-12,
        )
    np.testing.assert_allclose(
        condition_frames(recording.frames, recording, Conditioning()), echo, atol=1e-12
    )
    kept = condition_frame(recording.frames[0], recording, Conditioning(background=False))
    np.testing.assert_array_equal(kept, recording.frames[0])


def test_per_frame_background_needs_the_frame_index() -> None:
    rng = np.random.default_rng(4)
    echo = rng.normal(size=(3, 4, 200))
    background = rng.normal(size=(3, 4, 200))
    recording = small_recording(echo + background, background=background)
    np.testing.assert_allclose(condition_frame(recording.frames[2], recording, Conditioning(), 2), echo[2])
    np.testing.assert_allclose(
        condition_frames(recording.frames[1:], recording, Conditioning(), [1, 2]), echo[1:], atol=1e-12
    )
    with pytest.raises(EchoLocError, match="index"):
        condition_frame(recording.frames[2], recording, Conditioning())
    with pytest.raises(EchoLocError, match="one frame per frame"):
        conditioned("threshold", recording, Conditioning(), EchoOptions())


def test_envelope_background_is_subtracted_in_power_and_floored_at_zero() -> None:
    """Magnitudes of an echo and of a background with unrelated phase add in power on average
    (E|s + b|^2 = |s|^2 + |b|^2), so the echo's magnitude is sqrt(|f|^2 - |b|^2), 0 where the
    empty scene is the stronger: a 3-4-5 triangle gives exact values."""
    frames = np.array([[[5.0, 0.2, 13.0]]])
    recording = small_recording(frames, signal_kind="envelope", background=np.array([[3.0, 0.5, 5.0]]))
    np.testing.assert_allclose(condition_frame(frames[0], recording, Conditioning()), [[4.0, 0.0, 12.0]])


def test_envelope_power_subtraction_is_unbiased_over_random_phases() -> None:
    """Averaged over the relative phase of echo and background, the power-subtracted magnitude
    squared equals the echo's power exactly (the cross term averages to zero)."""
    echo, clutter = 2.0, 0.5  # |s + b|^2 - |b|^2 = 4 + 2 cos(phase) > 0: nothing floored
    phases = np.linspace(0, 2 * np.pi, 4096, endpoint=False)
    measured = np.abs(echo + clutter * np.exp(1j * phases))
    recording = small_recording(
        measured[None, None, :], signal_kind="envelope", background=np.full((1, 4096), clutter)
    )
    conditioned = condition_frame(measured[None, :], recording, Conditioning())
    assert np.mean(conditioned**2) == pytest.approx(echo**2, rel=1e-9)


def test_asking_for_missing_background_or_gain_is_an_error() -> None:
    recording = small_recording(np.zeros((1, 4, 50)))
    with pytest.raises(EchoLocError, match="no background"):
        condition_frame(recording.frames[0], recording, Conditioning(background=True))
    with pytest.raises(EchoLocError, match="no receiver_gain"):
        condition_frame(recording.frames[0], recording, Conditioning(tvg=True))


# --- time-varying gain -------------------------------------------------------------------


def test_tvg_compensation_inverts_a_known_gain() -> None:
    """A simulated frame through a rising gain, divided by receiver_gain, is the frame without it."""
    gain = GainSpec(kind="continuous", slope_db_per_ms=3.0, max_gain_db=30.0)
    with_gain = simulate(reflector_scene(receiver=ReceiverSpec(gain=gain)), 1)
    without = simulate(reflector_scene(), 1)
    assert with_gain.receiver_gain is not None
    restored = condition_frame(with_gain.frames[0], with_gain, Conditioning())
    np.testing.assert_allclose(restored, without.frames[0], rtol=1e-12, atol=1e-15)
    raw = condition_frame(with_gain.frames[0], with_gain, Conditioning(tvg=False))
    np.testing.assert_array_equal(raw, with_gain.frames[0])


def test_compensate_gain_checks_the_gain() -> None:
    np.testing.assert_allclose(
        compensate_gain(np.full((2, 4), 6.0), np.array([1.0, 2.0, 3.0, 6.0])), [[6, 3, 2, 1]] * 2
    )
    with pytest.raises(EchoLocError, match="samples"):
        compensate_gain(np.ones((2, 4)), np.ones(3))


# --- blind zone --------------------------------------------------------------------------------


def test_ring_down_end_follows_its_exponential_decay() -> None:
    """A ring-down A exp(-t / tau) in noise sigma ends where it meets the level: tau ln(A / L).

    L is blind_zone_db (10 dB) above the analytic noise power 2 sigma^2.
    """
    rng = np.random.default_rng(9)
    amplitude, tau_s, sigma = 20.0, 0.3e-3, 0.01
    t = np.arange(4000) / FS
    frames = amplitude * np.exp(-t / tau_s) * np.sin(2 * np.pi * 50e3 * t) + rng.normal(
        0, sigma, (2, 4, 4000)
    )
    recording = small_recording(frames)
    level = math.sqrt(2 * sigma**2 * 10)
    expected = tau_s * math.log(amplitude / level)
    for frame in frames:
        assert ring_down_end_s(frame, recording, Conditioning(blind_zone_s="auto")) == pytest.approx(
            expected, abs=0.5 * tau_s
        )


def test_no_ring_down_no_blind_zone() -> None:
    """A frame whose envelope is quiet at t = 0 has no automatic blind zone."""
    recording = simulate(reflector_scene(snr_db=30.0), 1)
    assert blind_zone_s(recording.frames[0], recording, Conditioning(blind_zone_s="auto")) == 0.0
    assert blind_zone_s(recording.frames[0], recording, Conditioning()) == 0.0
    assert blind_zone_s(recording.frames[0], recording, Conditioning(blind_zone_s=1e-3)) == 1e-3


RING_DOWN_ESTIMATORS = ("matched", "threshold", "threshold-cfar", "energy", "leading-edge")


@pytest.mark.parametrize(("level", "full_scale", "decay_s"), [(10.0, 4.0, 0.3e-3), (50.0, 5.0, 0.2e-3)])
def test_auto_blind_zone_drops_the_ring_down_and_keeps_the_echo(
    level: float, full_scale: float, decay_s: float
) -> None:
    """A ring-down 10-50 times the pulse, clipped by a 12-bit ADC, then the direct path: with the
    automatic blind zone every estimator reports exactly the ball's echo on every receiver.

    Without it the matched filter takes the ring-down apart into false echoes.
    """
    scene = reflector_scene(
        snr_db=40.0,
        ring_down=RingDown(level=level, decay_s=decay_s, direct_path=True),
        receiver=ReceiverSpec(adc=AdcSpec(bits=12, full_scale=full_scale)),
        seed=3,
    )
    recording = simulate(scene, 2)
    assert np.max(np.abs(recording.frames)) >= full_scale * (1 - 2**-11)  # the ring-down is clipped
    true = true_tof_s(scene)
    direct_end = 0.25 / scene.speed_of_sound_m_s + len(scene.waveform().samples) / FS
    spec = Conditioning(blind_zone_s="auto")
    for frame in recording.frames:
        zone = blind_zone_s(frame, recording, spec)
        assert direct_end < zone < true.min()
    for name in RING_DOWN_ESTIMATORS:
        estimator = conditioned(name, recording, spec, EchoOptions())
        for frame in recording.frames:
            for channel, tof in zip(estimator(frame), true, strict=True):
                assert channel.tof_s == pytest.approx([tof], abs=2e-6), name
    plain = ESTIMATORS["matched"].prepare(recording, EchoOptions())
    assert any(np.any(channel.tof_s < true.min() - 1e-4) for channel in plain(recording.frames[0]))


def test_blind_zone_in_seconds_and_blanking_take_the_later() -> None:
    """--blind-zone 2 ms with --blanking-s 1 ms blanks 2 ms; with --blanking-s 3 ms, 3 ms."""
    assert effective_options(EchoOptions(blanking_s=1e-3), Conditioning(blind_zone_s=2e-3)).blanking_s == 2e-3
    assert effective_options(EchoOptions(blanking_s=3e-3), Conditioning(blind_zone_s=2e-3)).blanking_s == 3e-3
    assert (
        effective_options(EchoOptions(blanking_s=1e-3), Conditioning(blind_zone_s="auto")).blanking_s == 1e-3
    )


@pytest.mark.parametrize("text", ["-1", "nan", "inf", "soon", ""])
def test_bad_blind_zones_are_refused(text: str) -> None:
    with pytest.raises(EchoLocError, match="blind-zone"):
        parse_blind_zone(text)


def test_blind_zone_parses_seconds_and_auto() -> None:
    assert parse_blind_zone("auto") == "auto"
    assert parse_blind_zone(" AUTO ") == "auto"
    assert parse_blind_zone("0.002") == pytest.approx(0.002)
    with pytest.raises(EchoLocError):
        Conditioning(blind_zone_s=-1.0)


# --- wiring ---------------------------------------------------------------------------------


def test_pipeline_applies_the_conditioning() -> None:
    """prepare(..., conditioning) and frame_echoes give what the conditioned estimator gives."""
    scene = reflector_scene(
        snr_db=40.0,
        ring_down=RingDown(level=10.0, direct_path=True),
        receiver=ReceiverSpec(gain=GainSpec(kind="continuous", slope_db_per_ms=2.0, max_gain_db=20.0)),
        seed=1,
    )
    recording = simulate(scene, 2)
    spec = Conditioning(blind_zone_s="auto")
    chain = prepare(recording, estimator="threshold", conditioning=spec)
    direct = conditioned("threshold", recording, spec, EchoOptions())
    for index in range(recording.n_frames):
        echoes = frame_echoes(chain, index)
        for mine, theirs, tof in zip(
            echoes.channels, direct(recording.frames[index]), true_tof_s(scene), strict=True
        ):
            np.testing.assert_array_equal(mine.tof_s, theirs.tof_s)
            assert mine.tof_s == pytest.approx([tof], abs=2e-6)
    fixed = prepare(recording, estimator="threshold", conditioning=Conditioning(blind_zone_s=2e-3))
    assert fixed.echo_options.blanking_s == 2e-3


def test_cli_conditioning_options(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--blind-zone auto removes the ring-down's echoes; a bad --blind-zone is exit 2 on one line."""
    scene = reflector_scene(snr_db=40.0, ring_down=RingDown(level=10.0, direct_path=True), seed=2)
    path = write_recording(simulate(scene, 1), tmp_path / "ring.h5")

    def echoes(*extra: str) -> tuple[int, str, str]:
        capsys.readouterr()
        with pytest.raises(SystemExit) as info:
            cli.main(["echoes", str(path), "--json", *extra])
        out, err = capsys.readouterr()
        assert isinstance(info.value.code, int)
        return info.value.code, out, err

    code, out, _ = echoes("--blind-zone", "auto", "--no-background", "--tvg")
    assert code == 2  # --tvg asked for, but the recording has no receiver_gain
    code, out, _ = echoes("--blind-zone", "auto", "--no-background", "--no-tvg")
    assert code == 0
    record = json.loads(out.splitlines()[0])
    true = true_tof_s(scene)
    for channel in record["channels"]:
        assert [e["tof_s"] for e in channel["echoes"]] == pytest.approx([true[channel["receiver"]]], abs=2e-6)
    code, out, _ = echoes()
    assert code == 0
    assert any(len(c["echoes"]) > 1 for c in json.loads(out.splitlines()[0])["channels"])
    code, _, err = echoes("--blind-zone", "soon")
    assert code == 2
    assert len(err.strip().splitlines()) == 1
    assert "--blind-zone" in err
