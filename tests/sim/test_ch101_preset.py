"""The shipped CH101 scene preset against figures measured on real CH101 data, and its new physics.

The real figures are hard-coded from ``benchmarks/results/ch101_sim_vs_real.md``
(``benchmarks/compare_ch101.py`` on ``/work/shared/data/ch101-spiel/dev.h5``, 751
frames of the SPiEL data set: C. Hahne, ICRA 2023, doi:10.1109/ICRA48891.2023.10161199),
so these tests do not need the data.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from echoloc.errors import SceneError
from echoloc.sim.reflectors import Sphere
from echoloc.sim.scene import REPORT_ARRAY, PulseSpec, ReceiverSpec, RingDown, Scene
from echoloc.sim.scenefile import load_scene, preset_names, preset_path, scene_from_dict
from echoloc.sim.simulation import moving_average, simulate
from echoloc.tof.envelope_stats import (
    arrival_samples,
    frame_start_levels,
    measure_echoes,
    within_group_spread,
)

# Real CH101 figures (dev.h5, per channel 0..3), from benchmarks/results/ch101_sim_vs_real.md.
REAL_FWHM_MEDIAN = (4.03, 3.72, 3.79, 3.93)  # samples at 22 kHz
REAL_SNR_P10 = (10.63, 8.19, 11.04, 12.03)  # dB against each channel's own noise
REAL_SNR_MEDIAN = (19.53, 21.01, 19.08, 21.68)
REAL_SNR_P90 = (25.19, 27.69, 26.91, 27.71)
REAL_SPREAD_WITHIN = (0.19, 0.21, 0.17, 0.20)  # samples, frame to frame at one position
REAL_FRAME_START_PEAK = (11015.0, 262.0, 223.0, 397.0)  # counts, mean background


@pytest.fixture(scope="module")
def preset() -> Scene:
    return load_scene("ch101")


def test_the_preset_is_shipped_and_loads_by_name(preset: Scene) -> None:
    assert "ch101" in preset_names()
    assert preset_path("ch101.toml").is_file()
    assert load_scene(preset_path("ch101")).pulse.carrier_hz == preset.pulse.carrier_hz
    with pytest.raises(SceneError, match="no scene preset"):
        preset_path("ch999")


def test_the_preset_records_envelopes_at_22_khz_with_no_waveform(preset: Scene) -> None:
    recording = simulate(preset, 3)
    assert recording.signal_kind == "envelope"
    assert recording.sample_rate_hz == pytest.approx(22e3)
    assert recording.carrier_hz == pytest.approx(175e3)
    assert recording.frames.shape == (3, 4, 62)
    assert recording.waveform is None
    assert np.all(recording.frames >= 0)
    assert np.allclose(recording.receivers_m[2], [0.075, 0.0, 0.0])


@pytest.fixture(scope="module")
def measured(preset: Scene) -> tuple[object, np.ndarray, np.ndarray]:
    """The preset at four target positions like the real data's, 40 frames each, with backgrounds."""
    positions = np.array([[0.0, 0.0, 0.12], [0.04, -0.04, 0.15], [-0.06, 0.02, 0.18], [0.02, 0.06, 0.22]])
    radius = 0.01
    frames, backgrounds, truth, groups = [], [], [], []
    for i, position in enumerate(positions):
        centre = position + radius * position / np.linalg.norm(position)
        shot = simulate(dataclasses.replace(preset, objects=(Sphere(centre, radius),), seed=10 + i), 40)
        empty = simulate(dataclasses.replace(preset, objects=(), seed=50 + i), 40)
        assert shot.truth_positions_m is not None
        frames.append(shot.frames)
        backgrounds.append(empty.frames)
        truth.append(shot.truth_positions_m[:, 0])
        groups.append(np.full(40, i))
    all_truth = np.concatenate(truth)
    arrivals = arrival_samples(
        preset.array.transmitters_m[0], preset.array.receivers_m, all_truth, preset.speed_of_sound_m_s, 22e3
    )
    figures = measure_echoes(np.concatenate(frames), np.concatenate(backgrounds), arrivals)
    return figures, np.concatenate(groups), np.concatenate(backgrounds)


def test_echo_width_matches_the_real_chip(measured: tuple[object, np.ndarray, np.ndarray]) -> None:
    figures = measured[0]
    width = np.nanmedian(figures.fwhm_samples, axis=0)  # type: ignore[attr-defined]
    assert np.all(np.isfinite(width))
    # Within 0.4 samples (10 %) of the real median width on every channel.
    assert np.all(np.abs(width - np.array(REAL_FWHM_MEDIAN)) < 0.4), width


def test_snr_range_matches_the_real_chip(measured: tuple[object, np.ndarray, np.ndarray]) -> None:
    snr = measured[0].snr_db  # type: ignore[attr-defined]
    median = np.nanmedian(snr, axis=0)
    # The median SNR within 4 dB of the real one, and inside the real p10..p90 range.
    assert np.all(np.abs(median - np.array(REAL_SNR_MEDIAN)) < 4.0), median
    assert np.all(median > np.array(REAL_SNR_P10))
    assert np.all(median < np.array(REAL_SNR_P90))


def test_timing_spread_matches_the_real_chip(measured: tuple[object, np.ndarray, np.ndarray]) -> None:
    figures, groups, _ = measured
    spread = within_group_spread(figures.residual_samples, groups)  # type: ignore[attr-defined]
    # Frame-to-frame spread within 0.07 samples (about the sampling error of 160 frames).
    assert np.all(np.abs(spread - np.array(REAL_SPREAD_WITHIN)) < 0.07), spread


def test_ring_down_and_cross_talk_match_the_real_chip(
    measured: tuple[object, np.ndarray, np.ndarray],
) -> None:
    start = frame_start_levels(measured[2])
    assert np.allclose(start.peak, REAL_FRAME_START_PEAK, rtol=0.1), start.peak
    assert np.all(np.abs(start.peak_sample - 5) <= 1)


# --- the simulator features the preset needs -----------------------------------------


def _jitter_scene(jitter: float | tuple[float, ...], seed: int = 3) -> Scene:
    """A noise-free rf scene at 1 MHz, one point reflector, so echo times can be read exactly."""
    return Scene(
        array=REPORT_ARRAY,
        pulse=PulseSpec(code="barker13", carrier_hz=50e3),
        sample_rate_hz=1e6,
        n_samples=6000,
        reflector_positions_m=np.array([[0.05, -0.02, 0.6]]),
        reflector_strengths=np.array([1.0]),
        timing_jitter_s=jitter,
        seed=seed,
    )


def _energy_centroid_s(frames: np.ndarray, rate_hz: float) -> np.ndarray:
    """Energy centroid of each channel's echo, s: shifts exactly with a band-limited echo's delay."""
    energy = frames.astype(float) ** 2
    k = np.arange(frames.shape[-1])
    return np.asarray(np.sum(energy * k, axis=-1) / np.sum(energy, axis=-1) / rate_hz)


def test_timing_jitter_of_sigma_gives_a_peak_time_spread_of_sigma() -> None:
    sigmas = (2e-6, 5e-6, 10e-6, 0.0)
    n = 400
    recording = simulate(_jitter_scene(sigmas), n)
    times = _energy_centroid_s(recording.frames, recording.sample_rate_hz)
    spread = np.std(times, axis=0, ddof=1)
    # The standard deviation of n normal draws has a relative sampling error of 1/sqrt(2(n-1)) = 3.5 %.
    for got, want in zip(spread[:3], sigmas[:3], strict=True):
        assert got == pytest.approx(want, rel=4 * 0.035)
    assert spread[3] < 1e-9  # no jitter: the echo stays put
    still = _energy_centroid_s(simulate(_jitter_scene(0.0), 1).frames, recording.sample_rate_hz)[0]
    # Zero-mean: each channel's mean time is its jitter-free time within 4 standard errors.
    assert np.all(np.abs(np.mean(times, axis=0) - still) <= 4 * np.array(sigmas) / np.sqrt(n) + 1e-9)


def test_zero_timing_jitter_gives_identical_frames() -> None:
    frames = simulate(_jitter_scene(0.0), 5).frames
    assert np.array_equal(frames, np.broadcast_to(frames[0], frames.shape))
    jittered = simulate(_jitter_scene(1e-6), 5).frames
    assert not np.array_equal(jittered[0], jittered[1])


def test_timing_jitter_is_validated() -> None:
    with pytest.raises(SceneError, match=r"timing_jitter_s names 2 values for 4 receivers"):
        _jitter_scene((1e-6, 1e-6))
    with pytest.raises(SceneError, match=r"timing_jitter_s must be >= 0"):
        _jitter_scene(-1e-6)
    base = {"reflectors": [{"position_m": [0.0, 0.0, 1.0]}]}
    scene = scene_from_dict({**base, "noise": {"timing_jitter_s": [1e-6, 2e-6, 3e-6, 4e-6]}})
    assert np.allclose(scene.timing_jitter_per_receiver_s(), [1e-6, 2e-6, 3e-6, 4e-6])
    assert np.allclose(
        scene_from_dict({**base, "noise": {"timing_jitter_s": 2e-6}}).timing_jitter_per_receiver_s(), 2e-6
    )
    with pytest.raises(SceneError, match=r"noise\.timing_jitter_s"):
        scene_from_dict({**base, "noise": {"timing_jitter_s": "big"}})


def test_ring_down_levels_per_receiver() -> None:
    levels = (2.0, 0.1, 0.0, 0.5)
    scene = Scene(array=REPORT_ARRAY, ring_down=RingDown(levels=levels, decay_s=0.2e-3))
    frames = simulate(scene, 1).frames[0]
    assert np.allclose(np.max(np.abs(frames), axis=1), levels)
    assert RingDown(levels=levels).active
    assert not RingDown(levels=(0.0,)).active
    with pytest.raises(SceneError, match="exclude each other"):
        RingDown(level=1.0, levels=levels)
    with pytest.raises(SceneError, match="names 3 levels for 4 receivers"):
        Scene(array=REPORT_ARRAY, ring_down=RingDown(levels=(1.0, 1.0, 1.0)))
    with pytest.raises(SceneError, match="exclude each other"):
        scene_from_dict({"ring_down": {"level": 1.0, "levels": [1.0, 1.0, 1.0, 1.0]}})


def test_moving_average_has_unit_gain_and_its_stated_delay() -> None:
    impulse = np.zeros(200)
    impulse[10] = 1.0
    out = moving_average(impulse, 9, order=3)
    assert np.sum(out) == pytest.approx(1.0)
    centroid = np.sum(np.arange(200) * out) / np.sum(out)
    assert centroid == pytest.approx(10 + 3 * (9 - 1) / 2)
    assert np.allclose(moving_average(np.ones(50) * (2 + 1j), 5)[10:], 2 + 1j)
    with pytest.raises(ValueError, match=r">= 1"):
        moving_average(impulse, 0)


def test_baseband_filter_widens_the_envelope_and_delays_it(preset: Scene) -> None:
    plain = dataclasses.replace(
        preset,
        receiver=dataclasses.replace(preset.receiver, baseband_filter_s=0.0),
        snr_db=None,
        timing_jitter_s=0.0,
    )
    filtered = dataclasses.replace(plain, receiver=preset.receiver)
    a = simulate(plain, 1).frames[0, 1]
    b = simulate(filtered, 1).frames[0, 1]
    assert np.argmax(b[14:]) > np.argmax(a[14:])
    assert np.sum(b[14:] > 0.5 * b[14:].max()) > np.sum(a[14:] > 0.5 * a[14:].max())


def test_receiver_chip_keys_are_validated() -> None:
    with pytest.raises(SceneError, match="baseband_filter_s needs signal_kind"):
        ReceiverSpec(baseband_filter_s=1e-4)
    with pytest.raises(SceneError, match=r"record_waveform = false needs signal_kind 'envelope'"):
        ReceiverSpec(signal_kind="iq", record_waveform=False)
    with pytest.raises(SceneError, match=r"baseband_filter_order must be a whole number"):
        ReceiverSpec(signal_kind="envelope", baseband_filter_order=0)
    with pytest.raises(SceneError, match=r"receiver\.record_waveform must be true or false"):
        scene_from_dict({"receiver": {"record_waveform": "no"}, "reflectors": [{"position_m": [0, 0, 1.0]}]})
