"""Calibration recovers a known speed of sound and receiver delays (the report's correction, generalised)."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import scipy.fft
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from echoloc.cli.commands import main
from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording, write_recording
from echoloc.localise.calibrate import Calibration, fit_calibration, read_calibration, write_calibration
from echoloc.localise.evaluation import evaluate
from echoloc.pipeline import frame_echoes, frame_objects, prepare
from echoloc.sim.scene import RandomReflectors, default_scene
from echoloc.sim.simulation import simulate
from echoloc.tof.echoes import ChannelEchoes, FrameEchoes

DELAYS_S = np.array([3.1e-6, -2.4e-6, 7.25e-6, 0.0])
TRUE_TEMPERATURE_C = 30.0
ASSUMED_SPEED_M_S = 343.21  # what the recording claims (20 °C)


def delayed(frames: np.ndarray, delays_s: np.ndarray, sample_rate_hz: float) -> np.ndarray:
    """Each receiver's channel delayed by its own fractional delay (band-limited, by FFT)."""
    n = frames.shape[-1]
    n_fft = scipy.fft.next_fast_len(2 * n)
    freqs = scipy.fft.rfftfreq(n_fft, 1 / sample_rate_hz)
    spectrum = scipy.fft.rfft(frames, n_fft, axis=-1) * np.exp(-2j * np.pi * freqs * delays_s[:, None])
    return np.asarray(scipy.fft.irfft(spectrum, n_fft, axis=-1)[..., :n])


@pytest.fixture(scope="module")
def miscalibrated() -> Recording:
    """Warm air (30 °C) recorded as if at 20 °C, with a fixed delay on each receiver."""
    scene = dataclasses.replace(
        default_scene(),
        reflector_positions_m=np.zeros((0, 3)),
        reflector_strengths=np.zeros(0),
        random=RandomReflectors(count=(1, 3), strength=(0.5, 2.0)),
        temperature_c=TRUE_TEMPERATURE_C,
        snr_db=25.0,
        seed=11,
    )
    recording = simulate(scene, 30)
    frames = delayed(recording.frames, DELAYS_S, recording.sample_rate_hz)
    return dataclasses.replace(recording, frames=frames, speed_of_sound_m_s=ASSUMED_SPEED_M_S)


def test_calibration_recovers_speed_and_delays(miscalibrated: Recording) -> None:
    """Fitted c within 0.02 % of the true 30 °C value, delays within 25 ns."""
    chain = prepare(miscalibrated)
    echoes = [frame_echoes(chain, i) for i in range(miscalibrated.n_frames)]
    calibration = fit_calibration(miscalibrated, echoes, speed_of_sound_m_s=ASSUMED_SPEED_M_S)
    true_speed = dataclasses.replace(default_scene(), temperature_c=TRUE_TEMPERATURE_C).speed_of_sound_m_s
    assert calibration.speed_of_sound_m_s == pytest.approx(true_speed, rel=2e-4)
    # 25 ns: the errors are mostly common to the four delays (traded against c); on this seed
    # they reach 19.4 ns at every sample and 20.2 ns at the matched filter's decimation of 2.
    assert np.array(calibration.receiver_delays_s) == pytest.approx(DELAYS_S, abs=25e-9)
    assert calibration.residual_rms_s < 100e-9  # phase noise at this SNR: tens of ns


def test_calibrated_localisation_is_back_on_target(miscalibrated: Recording) -> None:
    """Uncalibrated, every position is off by millimetres; calibrated, RMSE drops below 0.2 mm."""
    raw = prepare(miscalibrated)
    echoes = [frame_echoes(raw, i) for i in range(miscalibrated.n_frames)]
    calibration = fit_calibration(miscalibrated, echoes, speed_of_sound_m_s=ASSUMED_SPEED_M_S)
    assert miscalibrated.truth_positions_m is not None
    before = evaluate([frame_objects(raw, e) for e in echoes], miscalibrated.truth_positions_m, 0.05)
    fixed = prepare(miscalibrated, calibration=calibration)
    after = evaluate(
        [frame_objects(fixed, frame_echoes(fixed, i)) for i in range(miscalibrated.n_frames)],
        miscalibrated.truth_positions_m,
        0.05,
    )
    assert np.max(before.rmse_m) > 2e-3
    assert np.max(after.rmse_m) < 0.2e-3
    assert after.recall == pytest.approx(1.0)


def test_file_round_trip_and_bad_files(tmp_path: Path) -> None:
    """What is written reads back; a wrong format, a bad delay or a receiver mismatch is refused."""
    calibration = Calibration(344.5, (1e-6, 0.0, -2e-6, 3e-6), echoes_used=40, residual_rms_s=1e-8)
    path = write_calibration(calibration, tmp_path / "cal.json")
    assert read_calibration(path, 4) == calibration
    with pytest.raises(EchoLocError, match="receivers"):
        read_calibration(path, 3)
    record = json.loads(path.read_text())
    for key, value in (("format", "other"), ("speed_of_sound_m_s", -1), ("receiver_delays_s", [1, "x"])):
        broken = tmp_path / f"broken-{key}.json"
        broken.write_text(json.dumps({**record, key: value}))
        with pytest.raises(EchoLocError, match=key if key != "format" else "format"):
            read_calibration(broken)


def test_cli_calibrate_then_locate(
    miscalibrated: Recording, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`echoloc calibrate REC -o cal.json`, then `locate --calibration cal.json` uses it."""
    recording_path = write_recording(miscalibrated, tmp_path / "warm.h5")
    calibration_path = tmp_path / "cal.json"
    with pytest.raises(SystemExit) as exit_info:
        main(["calibrate", str(recording_path), "-o", str(calibration_path)])
    assert exit_info.value.code == 0
    assert read_calibration(calibration_path, 4).speed_of_sound_m_s > 347
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        main(["evaluate", str(recording_path), "--calibration", str(calibration_path), "--json"])
    assert exit_info.value.code == 0
    record = json.loads(capsys.readouterr().out)
    assert max(record["rmse_m"]) < 0.2e-3
    with pytest.raises(SystemExit) as exit_info:
        main(["locate", str(recording_path), "--calibration", str(tmp_path / "missing.json")])
    assert exit_info.value.code == 2


def test_delay_longer_than_a_frame_is_refused(
    miscalibrated: Recording, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Delays written in µs where seconds belong (3.1 for 3.1e-6) would shift every echo out of
    its frame: `locate` names the receiver and the frame's length, exit 2, no traceback; a
    delay just inside the frame is still taken."""
    recording_path = write_recording(miscalibrated, tmp_path / "warm.h5")
    frame_s = miscalibrated.n_samples / miscalibrated.sample_rate_hz
    in_microseconds = Calibration(ASSUMED_SPEED_M_S, tuple(DELAYS_S * 1e6), echoes_used=30)
    expected = rf"receiver 2 by 7\.25 s, more than a whole frame \({frame_s:g} s\)"
    with pytest.raises(EchoLocError, match=expected):
        prepare(miscalibrated, calibration=in_microseconds)
    prepare(miscalibrated, calibration=Calibration(ASSUMED_SPEED_M_S, (0.0, 0.0, 0.0, 0.99 * frame_s)))
    path = write_calibration(in_microseconds, tmp_path / "us.json")
    capsys.readouterr()
    with pytest.raises(SystemExit) as exit_info:
        main(["locate", str(recording_path), "--calibration", str(path)])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert "more than a whole frame" in err
    assert "Traceback" not in err


# --- a rig's calibration: the measured path sigma, and a speed the targets cannot fix ------

RIG_RECEIVERS_M = np.array(
    [[0.0, 0.0, 0.0], [0.075, 0.0, 0.0], [-0.0375, 0.065, 0.0], [-0.0375, -0.065, 0.0]]
)
RIG_DELAYS_S = np.array([4e-6, -20e-6, -3e-6, 11e-6])


def rig_echoes(
    targets_m: np.ndarray, speed_m_s: float, path_sigma_m: float, seed: int
) -> tuple[Recording, list[FrameEchoes]]:
    """One echo per receiver and frame at ``path / c + delay``, its path off by Gaussian
    noise of ``path_sigma_m``: what a calibration should measure back."""
    rng = np.random.default_rng(seed)
    n = len(targets_m)
    recording = Recording(
        22_000.0,
        np.zeros((1, 3)),
        RIG_RECEIVERS_M,
        np.zeros((n, 4, 62)),
        None,
        signal_kind="envelope",
        truth_positions_m=targets_m[:, None, :],
    )
    paths = np.linalg.norm(targets_m, axis=1)[:, None] + np.linalg.norm(
        targets_m[:, None] - RIG_RECEIVERS_M[None], axis=2
    )
    measured = paths + rng.normal(0, path_sigma_m, paths.shape)
    echoes = [
        FrameEchoes(
            f, 0.0, 343.0, tuple(ChannelEchoes(np.array([t]), np.ones(1), np.full(1, 20.0)) for t in row)
        )
        for f, row in enumerate(measured / speed_m_s + RIG_DELAYS_S)
    ]
    return recording, echoes


def test_the_path_sigma_is_measured_back_from_the_residuals() -> None:
    """Paths off by 6 mm (Gaussian): the calibration reports 6 mm within its sampling error
    (the MAD's standard error on 4000 residuals is about 2 %), and fits c and the delays."""
    rng = np.random.default_rng(2)
    targets = np.column_stack([rng.uniform(-0.1, 0.1, (1000, 2)), rng.uniform(0.1, 0.6, 1000)])
    recording, echoes = rig_echoes(targets, 346.0, 0.006, seed=3)
    calibration = fit_calibration(recording, echoes, speed_of_sound_m_s=343.0, gate_m=0.05)
    assert calibration.speed_fitted
    assert calibration.speed_of_sound_m_s == pytest.approx(346.0, rel=2e-3)
    assert calibration.path_sigma_m == pytest.approx(0.006, rel=0.08)


def test_a_speed_the_targets_do_not_fix_is_kept_as_assumed() -> None:
    """Targets all at one point (0.1 mm apart): the paths barely differ, so c trades with the
    delays; the assumed speed is kept and the delays take up the constant."""
    targets = np.tile([[0.0, 0.0, 0.2]], (50, 1)) + np.random.default_rng(4).normal(0, 1e-4, (50, 3))
    recording, echoes = rig_echoes(targets, 343.0, 0.0005, seed=5)
    calibration = fit_calibration(recording, echoes, speed_of_sound_m_s=343.0, gate_m=0.05)
    assert not calibration.speed_fitted
    assert calibration.speed_of_sound_m_s == 343.0
    # The median of 50 echoes off by 1.5 us each (0.5 mm): within 1 us, about 4 sigma.
    np.testing.assert_allclose(calibration.receiver_delays_s, RIG_DELAYS_S, atol=1e-6)


def test_the_speed_fitted_flag_survives_the_file(tmp_path: Path) -> None:
    calibration = Calibration(343.0, (0.0, 1e-6), speed_fitted=False)
    assert not read_calibration(write_calibration(calibration, tmp_path / "c.json")).speed_fitted
    record = json.loads((tmp_path / "c.json").read_text())
    record["speed_of_sound_fitted"] = "no"
    (tmp_path / "c.json").write_text(json.dumps(record))
    with pytest.raises(EchoLocError, match="speed_of_sound_fitted must be true or false"):
        read_calibration(tmp_path / "c.json")
    record["speed_of_sound_fitted"], record["speed_of_sound_m_s"] = True, True
    (tmp_path / "c.json").write_text(json.dumps(record))
    with pytest.raises(EchoLocError, match="speed_of_sound_m_s must be a positive number"):
        read_calibration(tmp_path / "c.json")


def test_unknown_fields_are_read_past_with_a_warning(tmp_path: Path) -> None:
    """A field this version does not know (a later echoloc's optional one, or a typo) is
    named in one warning; the fields it knows still read as written."""
    from echoloc.localise.calibrate import CalibrationWarning

    calibration = Calibration(343.5, (1e-6, -2e-6, 0.0, 3e-6), echoes_used=40, residual_rms_s=1e-7)
    path = write_calibration(calibration, tmp_path / "c.json")
    record = json.loads(path.read_text())
    path.write_text(json.dumps({**record, "temperature_c": 21.5, "speed_of_sound_m_S": 1.0}))
    with pytest.warns(CalibrationWarning, match=r"c\.json: .*speed_of_sound_m_S, temperature_c"):
        assert read_calibration(path, 4) == calibration


def snr_echoes(
    snr_db: np.ndarray, clutter_db: float | None = None
) -> tuple[Recording, list[FrameEchoes], Calibration]:
    """Frames of targets whose echo on each receiver has the given SNR (dB; -inf: no echo),
    at exactly its calibrated arrival; ``clutter_db``: an echo that strong 50 mm of path later
    on every receiver, far outside the gate. With the calibration that predicts them."""
    rng = np.random.default_rng(8)
    n = len(snr_db)
    targets = np.column_stack([rng.uniform(-0.1, 0.1, (n, 2)), rng.uniform(0.1, 0.6, n)])
    recording, _ = rig_echoes(targets, 343.0, 0.0, seed=1)
    calibration = Calibration(343.0, tuple(RIG_DELAYS_S), path_sigma_m=0.001)
    paths = np.linalg.norm(targets, axis=1)[:, None] + np.linalg.norm(
        targets[:, None] - RIG_RECEIVERS_M[None], axis=2
    )
    echoes = []
    for f in range(n):
        channels = []
        for i in range(4):
            tof, snr = [], []
            if np.isfinite(snr_db[f, i]):
                tof.append(paths[f, i] / 343.0 + RIG_DELAYS_S[i])
                snr.append(snr_db[f, i])
            if clutter_db is not None:
                tof.append((paths[f, i] + 0.05) / 343.0 + RIG_DELAYS_S[i])
                snr.append(clutter_db)
            channels.append(ChannelEchoes(np.array(tof), np.ones(len(tof)), np.array(snr)))
        echoes.append(FrameEchoes(f, 0.0, 343.0, tuple(channels)))
    return recording, echoes, calibration


def test_the_detection_threshold_keeps_99_percent_of_the_targets_on_three_receivers() -> None:
    """200 targets whose echoes stand 0-12 dB above the noise: the threshold is the level that
    the third-strongest echo of 99 % of them reaches (the lower 1 % sample), whatever strong
    clutter lies outside the gate; a target heard on two receivers only does not count."""
    from echoloc.localise.calibrate import detection_threshold_db

    snr = np.random.default_rng(3).uniform(0.0, 12.0, (200, 4))
    snr[:5, 1:] = -np.inf  # heard on one receiver: no object at any threshold
    snr[5:20, 0] = -np.inf  # one receiver misses it: the third of the other three counts
    recording, echoes, calibration = snr_echoes(snr, clutter_db=30.0)
    needed = np.sort(snr[5:], axis=1)[:, ::-1][:, 2]
    expected = float(np.quantile(needed, 0.01, method="lower"))
    assert np.mean(needed >= expected) >= 0.99
    measured = detection_threshold_db(recording, echoes, calibration, ceiling_db=20.0)
    assert measured == expected
    assert detection_threshold_db(recording, echoes, calibration, ceiling_db=0.1) == 0.1
    assert detection_threshold_db(recording, echoes, calibration, ceiling_db=20.0, min_receivers=4) == float(
        np.quantile(np.min(snr[20:], axis=1), 0.01, method="lower")
    )


def test_a_weak_peak_nearer_the_arrival_does_not_hide_the_targets_echo() -> None:
    """A noise peak at 0.5 dB a quarter sigma from the arrival, the target's echo at 6 dB half a
    sigma after it: the echo is what a threshold must keep, so 6 dB is the level needed."""
    from echoloc.localise.calibrate import detection_threshold_db

    snr = np.full((50, 4), 6.0)
    recording, echoes, calibration = snr_echoes(snr)
    sigma_s = 0.001 / 343.0

    def with_decoy(channel: ChannelEchoes) -> ChannelEchoes:
        arrival = channel.tof_s[0]
        tof = np.array([arrival + 0.25 * sigma_s, arrival + 0.5 * sigma_s])
        return ChannelEchoes(tof, np.ones(2), np.array([0.5, 6.0]))

    echoes = [
        dataclasses.replace(frame, channels=tuple(with_decoy(c) for c in frame.channels)) for frame in echoes
    ]
    assert detection_threshold_db(recording, echoes, calibration, ceiling_db=20.0) == 6.0


def test_no_detection_threshold_where_no_target_is_heard_on_enough_receivers() -> None:
    from echoloc.localise.calibrate import detection_threshold_db

    snr = np.full((30, 4), -np.inf)
    snr[:, :2] = 10.0
    recording, echoes, calibration = snr_echoes(snr)
    assert detection_threshold_db(recording, echoes, calibration, ceiling_db=3.0) is None


@settings(max_examples=40, deadline=None)
@given(
    snr=arrays(np.float64, (40, 4), elements=st.floats(-10.0, 40.0)),
    keep=st.floats(0.5, 1.0),
    ceiling=st.floats(-5.0, 30.0),
)
def test_the_detection_threshold_keeps_what_it_promises(snr: np.ndarray, keep: float, ceiling: float) -> None:
    """Whatever the SNRs: at most the ceiling, and at least ``keep`` of the targets still have
    three echoes at or above it."""
    from echoloc.localise.calibrate import detection_threshold_db

    recording, echoes, calibration = snr_echoes(snr)
    measured = detection_threshold_db(recording, echoes, calibration, ceiling_db=ceiling, keep=keep)
    assert measured is not None
    assert measured <= ceiling
    needed = np.sort(snr, axis=1)[:, ::-1][:, 2]
    assert np.mean(needed >= measured) >= keep - 1e-12


def test_the_detection_threshold_survives_the_file_and_sets_the_default(tmp_path: Path) -> None:
    """Written and read back; envelope-peak takes it as its default, the other estimators keep
    theirs; a threshold that is not a number from -20 to 300 dB is refused, naming the file."""
    from echoloc.tof.estimators import ENVELOPE_PEAK_THRESHOLD_DB, default_threshold_db

    calibration = Calibration(343.0, (0.0, 1e-6), threshold_db=1.25)
    read = read_calibration(write_calibration(calibration, tmp_path / "c.json"))
    assert read.threshold_db == 1.25
    assert default_threshold_db("envelope-peak", read.threshold_db) == 1.25
    assert default_threshold_db("envelope-peak", None) == ENVELOPE_PEAK_THRESHOLD_DB
    assert default_threshold_db("matched", read.threshold_db) == default_threshold_db("matched")
    recording, _ = rig_echoes(np.array([[0.0, 0.0, 0.2]]), 343.0, 0.0, seed=1)
    four = Calibration(343.0, tuple(RIG_DELAYS_S), threshold_db=1.25)
    chain = prepare(recording, estimator="auto", calibration=four, check_channels=False)
    assert chain.echo_options.threshold_db == 1.25
    assert "threshold_db" not in json.loads(
        write_calibration(Calibration(343.0, (0.0, 1e-6)), tmp_path / "d.json").read_text()
    )
    record = json.loads((tmp_path / "c.json").read_text())
    for bad in ("3", -25.0, 500.0, float("nan")):
        (tmp_path / "c.json").write_text(json.dumps({**record, "threshold_db": bad}))
        with pytest.raises(EchoLocError, match=r"c\.json: threshold_db must be a number from -20 to 300 dB"):
            read_calibration(tmp_path / "c.json")
