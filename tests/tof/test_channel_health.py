"""Degraded receiver channels (issue 31, finding 10): found, named, corrected or left out."""

from __future__ import annotations

import warnings
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from echoloc.io.recording import Recording
from echoloc.localise.evaluation import evaluate
from echoloc.localise.locate import model_paths_m
from echoloc.pipeline import _excusing_clipped, prepare, run, samples_echoes_batch, transmitter_objects
from echoloc.sim.scenefile import load_scene
from echoloc.sim.simulation import simulate
from echoloc.tof.channel_health import (
    ASSESS_FRAMES,
    ChannelHealth,
    ChannelWarning,
    ChannelWatch,
    _rail_count,
    assess_channels,
    clipped_samples,
    correct_frames,
    reread_clipped,
)
from echoloc.tof.echoes import EchoOptions, FrameEchoes, MatchedFilter
from echoloc.tof.estimators import MatchedEstimator
from repo_paths import REPO

EXAMPLE = REPO / "src" / "echoloc" / "scenes" / "random-1m3.toml"


def _noise(rng: np.random.Generator, n_frames: int = 8, n_rx: int = 4, n: int = 2400) -> np.ndarray:
    return rng.normal(size=(n_frames, n_rx, n))


# --- detectors, closed forms -------------------------------------------------------------------


def test_a_clipped_sine_has_the_known_fraction_at_the_rail() -> None:
    """A sine of amplitude 1 clipped at r spends 1 - (2/pi) arcsin(r) of its time at a rail (each
    rail half of it); sampled at an incommensurate rate, the count follows, and the channel is
    flagged clipped while the others are not."""
    rng = np.random.default_rng(1)
    n = 20_000
    t = np.arange(n)
    rail = 0.3
    sine = np.sin(2 * np.pi * t * 0.0123456 + 0.3)
    frames = sine + 0.001 * rng.normal(size=(1, 3, n))
    frames[0, 0] = np.clip(frames[0, 0], -rail, rail)
    expected = (1 - 2 / np.pi * np.arcsin(rail)) / 2 * n
    top = _rail_count(frames[:, 0], rail, gap=1)
    assert abs(top - expected) < 0.01 * n
    health = assess_channels(frames, min_receivers=2)
    assert health.problems[0] == ("clipped",)
    assert health.problems[1:] == ((), ())
    assert health.excluded == (0,)


@pytest.mark.parametrize("noise_lsb", [0.25, 0.5])
def test_quantised_noise_and_echoes_are_not_a_flat_top(noise_lsb: float) -> None:
    """An 8-bit converter whose noise is a fraction of a code: the top code of a noise-only
    channel holds many samples, but as many sit one code below: no clipping; an echo on it
    neither. The same converter saturating on an echo at four times full scale is clipping."""
    rng = np.random.default_rng(2)
    q = 2 / 2**8
    frames = noise_lsb * q * rng.normal(size=(4, 4, 2400))
    t = np.arange(400)
    envelope = np.minimum(1.0, np.minimum(t, 400 - t) / 40)
    echo = envelope * np.sin(2 * np.pi * t / 4 + 0.4)
    frames[:, 1, 1000:1400] += 0.9 * echo
    quantised = np.round(frames / q) * q
    assert _rail_count(quantised[:, 0], float(quantised[:, 0].max()), gap=1) >= 8
    assert assess_channels(quantised).healthy
    frames[:, 2, 1000:1400] += 4 * echo
    saturated = np.clip(np.round(frames / q) * q, -1.0, 1.0 - q)
    assert assess_channels(saturated).problems == ((), (), ("clipped",), ())


def test_a_saturated_ring_down_is_not_clipping() -> None:
    """Every receiver's ADC saturating on the transmitter's ring-down at the frame's start is
    normal (it lies in the blind zone); the same saturation mid-frame is clipping."""
    rng = np.random.default_rng(3)
    frames = 0.05 * rng.normal(size=(8, 4, 2400))
    t = np.arange(300)
    ring = 10 * np.exp(-t / 120) * np.sin(2 * np.pi * t / 4 + 0.2)
    frames[:, :, :300] += ring
    frames = np.clip(frames, -1.0, 1.0)
    assert assess_channels(frames, ring_down_samples=52).healthy
    frames[:, 2, 1200:1500] = np.clip(frames[:, 2, 1200:1500] + ring, -1.0, 1.0)
    health = assess_channels(frames, ring_down_samples=52)
    assert health.problems == ((), (), ("clipped",), ())


def test_a_dc_offset_is_recovered_within_its_noise_and_removed() -> None:
    """The offset is the median of the frames' medians: within a few sigma / sqrt(n) of the truth.
    Corrected frames have each frame's median at 0; the healthy channels are left untouched."""
    rng = np.random.default_rng(4)
    sigma, offset, n = 0.5, 7.0, 2400
    frames = sigma * _noise(rng, 16, 4, n)
    frames[:, 3] += offset
    health = assess_channels(frames)
    assert health.problems == ((), (), (), ("dc-offset",))
    assert health.dc == (3,)
    assert health.excluded == ()
    assert abs(health.offsets[3] - offset) < 5 * 1.25 * sigma / np.sqrt(16 * n)
    assert abs(health.sigmas[3] - sigma) < 0.05 * sigma
    fixed = correct_frames(frames, health)
    assert np.max(np.abs(np.median(fixed[:, 3], axis=-1))) < 1e-12
    assert np.array_equal(fixed[:, :3], frames[:, :3])
    assert np.array_equal(
        frames[:, 3] - fixed[:, 3], np.broadcast_to(np.median(frames[:, 3], -1)[:, None], (16, n))
    )


def test_an_iq_offset_is_complex() -> None:
    """LO leakage: a complex constant on one IQ channel is found with its phase and removed."""
    rng = np.random.default_rng(5)
    frames = rng.normal(size=(8, 3, 1000)) + 1j * rng.normal(size=(8, 3, 1000))
    frames[:, 1] += 4 - 3j
    health = assess_channels(frames, "iq")
    assert health.problems == ((), ("dc-offset",), ())
    assert abs(health.offsets[1] - (4 - 3j)) < 0.1
    assert abs(np.median(correct_frames(frames, health)[:, 1].real)) < 0.05


def test_an_envelope_offset_is_its_noise_floor() -> None:
    """An envelope is >= 0: its median is its noise floor, not an offset to remove."""
    rng = np.random.default_rng(6)
    frames = np.abs(rng.normal(size=(8, 4, 1000)) + 1j * rng.normal(size=(8, 4, 1000)))
    assert assess_channels(frames, "envelope").healthy


def test_dead_non_finite_and_noisy_channels() -> None:
    """A flat channel is dead, a NaN one non-finite (its samples zeroed), one with 10 times the
    others' noise is noisy: the first two always left out, the noisy one while 3 others work."""
    rng = np.random.default_rng(7)
    frames = _noise(rng, 8, 6)
    frames[:, 0] = 0.25
    frames[3, 1, ::7] = np.nan
    frames[:, 4] *= 10
    health = assess_channels(frames, min_receivers=3)
    assert health.problems == (("dead",), ("non-finite",), (), (), ("noisy",), ())
    assert health.excluded == (0, 1, 4)
    assert abs(health.sigmas[4] / health.sigmas[2] - 10) < 0.5
    fixed = correct_frames(frames, health)
    assert np.isfinite(fixed).all()
    assert np.all(fixed[3, 1, ::7] == 0)
    # With only four channels, leaving the noisy one out would leave two: it is kept.
    kept = assess_channels(frames[:, [0, 2, 3, 4]], min_receivers=3)
    assert kept.excluded == (0,)
    assert kept.kept == (3,)


def test_correction_of_healthy_frames_is_the_identity() -> None:
    """Nothing to correct: the very same array comes back (the batch chain's answers stay bit
    for bit what they were)."""
    frames = _noise(np.random.default_rng(8))
    health = assess_channels(frames)
    assert health.healthy
    assert correct_frames(frames, health) is frames


# --- healthy channels are never flagged -----------------------------------------------------------


@settings(max_examples=40, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n_frames=st.integers(1, 6),
    n_rx=st.integers(2, 6),
    sigma=st.floats(1e-3, 1e3),
    echoes=st.integers(0, 6),
    snr_db=st.floats(0.0, 50.0),
    offset_sigmas=st.floats(-1.0, 1.0),
    spread=st.floats(0.5, 2.0),
)
def test_healthy_gaussian_noise_with_echoes_is_never_flagged(
    seed: int,
    n_frames: int,
    n_rx: int,
    sigma: float,
    echoes: int,
    snr_db: float,
    offset_sigmas: float,
    spread: float,
) -> None:
    """Gaussian noise (channels' sigmas within a factor 2 of each other, a harmless offset under
    one sigma) plus Barker-coded echoes of any strength up to 50 dB: no problem is found."""
    rng = np.random.default_rng(seed)
    n = 1200
    sigmas = sigma * spread ** rng.uniform(-1, 1, n_rx)
    frames = rng.normal(size=(n_frames, n_rx, n)) * sigmas[None, :, None] + offset_sigmas * sigma * 0.5
    code = np.repeat([1, 1, 1, 1, 1, -1, -1, 1, 1, -1, 1, -1, 1], 16)
    pulse = code * np.sin(2 * np.pi * np.arange(len(code)) / 4 + rng.uniform(0, 2 * np.pi))
    for f in range(n_frames):
        for rx in range(n_rx):
            for _ in range(echoes):
                start = int(rng.integers(0, n - len(pulse)))
                amplitude = sigma * 10 ** (rng.uniform(0, snr_db) / 20)
                frames[f, rx, start : start + len(pulse)] += amplitude * pulse
    health = assess_channels(frames)
    assert health.healthy, health.problems


def test_healthy_simulated_recordings_raise_no_warning() -> None:
    """Four seeds of the acceptance scene: no channel flagged (filterwarnings=error would fail the
    test on any warning)."""
    scene = load_scene(EXAMPLE)
    for seed in range(4):
        recording = simulate(replace(scene, seed=seed), 16)
        chain = prepare(recording)
        assert chain.health.healthy
        assert chain.usable_receivers.all()


# --- a live session -------------------------------------------------------------------------------


def test_a_live_session_is_assessed_on_its_first_frames_and_warned_once() -> None:
    """Frames one at a time: the first one with a DC offset is found, warned about once (naming
    the source and receiver) and corrected from then on; after ASSESS_FRAMES nothing is
    assessed any more."""
    rng = np.random.default_rng(9)
    watch = ChannelWatch("tcp://127.0.0.1:5000", "rf", 4)
    healthy_frame = rng.normal(size=(1, 4, 2400))
    assert watch.observe(healthy_frame).healthy
    degraded = rng.normal(size=(1, 4, 2400))
    degraded[:, 2] += 50
    with pytest.warns(ChannelWarning, match=r"tcp://127\.0\.0\.1:5000: receiver 2 .*DC offset.*removed"):
        health = watch.observe(degraded)
    assert health.dc == (2,)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for _ in range(ASSESS_FRAMES):
            frame = rng.normal(size=(1, 4, 2400))
            frame[:, 2] += 50
            assert watch.observe(frame).dc == (2,)
    assert watch.frames_seen == ASSESS_FRAMES


# --- end to end: the acceptance scene --------------------------------------------------------------


@pytest.fixture(scope="module")
def scene_recording() -> Recording:
    """The acceptance scene (1-5 random reflectors, 20 dB), 150 frames."""
    return replace(simulate(load_scene(EXAMPLE), 150), source="scene.h5")


def _figures(recording: Recording, check: bool = True) -> tuple[float, float]:
    chain = prepare(recording, check_channels=check)
    figures = evaluate([objects for _, objects in run(chain)], recording.truth_positions_m)
    return figures.recall, figures.false_rate


def _degraded(recording: Recording, kind: str, channel: int = 0) -> Recording:
    frames = np.array(recording.frames, dtype=float)
    peak = float(np.max(np.abs(frames[:, channel])))
    if kind == "clip":
        frames[:, channel] = np.clip(frames[:, channel], -0.1 * peak, 0.1 * peak)
    else:
        frames[:, channel] += peak
    return replace(recording, frames=frames)


def test_a_dc_offset_equal_to_the_peak_is_removed_end_to_end(scene_recording: Recording) -> None:
    """A DC offset equal to the channel's peak: warned about (file and receiver), removed, and the
    figures are those of the clean recording (recall >= 0.99, <= 1 % false objects); without the
    check the offset's ringing through the matched filter costs recall."""
    clean = _figures(scene_recording)
    degraded = _degraded(scene_recording, "dc", channel=1)
    unchecked = _figures(degraded, check=False)
    with pytest.warns(ChannelWarning, match=r"scene\.h5: receiver 1 .*DC offset.*offset removed"):
        checked = _figures(degraded)
    assert checked[0] >= 0.99
    assert checked[1] <= 0.01
    assert checked == pytest.approx(clean, abs=0.003)
    assert unchecked[0] < checked[0] - 0.02


def test_a_clipped_channel_is_reread_end_to_end(scene_recording: Recording) -> None:
    """One channel clipped at 10 % of its peak: warned about (file and receiver), kept, and its
    echoes near clipped samples re-read from the matched filter's peaks: recall >= 0.99 with
    <= 1 % false objects, where leaving the channel out (three receivers cannot reject ghosts
    among 1-5 points) does worse on both (0.984 and 1.4 % on these frames)."""
    degraded = _degraded(scene_recording, "clip", channel=0)
    with pytest.warns(
        ChannelWarning, match=r"scene\.h5: receiver 0 .*clipped.*kept, its echoes near clipped"
    ):
        chain = prepare(degraded)
    assert chain.usable_receivers.all()
    assert chain.health.reread == (0,)
    assert chain.health.excluded == ()
    figures = evaluate([objects for _, objects in run(chain)], degraded.truth_positions_m)
    assert figures.recall >= 0.99
    assert figures.false_rate <= 0.01
    left_out = replace(chain, usable_receivers=np.array([False, True, True, True]))
    without = evaluate([objects for _, objects in run(left_out)], degraded.truth_positions_m)
    assert figures.recall > without.recall
    assert figures.false_rate < without.false_rate


def test_healthy_recordings_give_the_same_answers_with_the_check(scene_recording: Recording) -> None:
    """The channel check changes nothing when no channel is degraded: echoes and objects bit for
    bit those of the chain without it."""
    indices = range(40)
    checked = list(run(prepare(scene_recording), indices))
    unchecked = list(run(prepare(scene_recording, check_channels=False), indices))
    for (echoes, objects), (echoes_0, objects_0) in zip(checked, unchecked, strict=True):
        for channel, channel_0 in zip(echoes.channels, echoes_0.channels, strict=True):
            assert np.array_equal(channel.tof_s, channel_0.tof_s)
            assert np.array_equal(channel.amplitude, channel_0.amplitude)
        assert [o.position_m.tolist() for o in objects.objects] == [
            o.position_m.tolist() for o in objects_0.objects
        ]


def _barker_echoes(
    delays_amplitudes: list[tuple[float, float]], n: int = 2400
) -> tuple[np.ndarray, np.ndarray]:
    """A Barker-13 pulse (4 cycles a bit at a quarter of the sample rate) and a frame of its
    echoes at fractional delays (samples), band-limited (FFT phase ramp)."""
    code = np.repeat([1, 1, 1, 1, 1, -1, -1, 1, 1, -1, 1, -1, 1], 16)
    pulse = code * np.sin(2 * np.pi * np.arange(len(code)) / 4)
    padded = np.zeros(2 * n)
    padded[: len(pulse)] = pulse
    f = np.fft.rfftfreq(2 * n)
    frame = sum(
        a * np.fft.irfft(np.fft.rfft(padded) * np.exp(-2j * np.pi * f * tau), 2 * n)[:n]
        for tau, a in delays_amplitudes
    )
    return pulse, np.asarray(frame)


def test_a_clipped_channel_is_reread_from_the_correlation_peaks() -> None:
    """Two overlapping echoes 12 and 7 times the rail and a weak one far from them: CLEAN reads
    the clipped pair as 14 echoes; the re-read keeps both within a quarter sample (clipping
    moves the carrier's phase) and at most two
    distortion products, and leaves the unclipped echo, and the unclipped channel, exactly
    as the estimator read them."""
    rng = np.random.default_rng(10)
    truth = [(700.3, 12.0), (770.6, 7.0), (1500.2, 0.6)]
    pulse, frame = _barker_echoes(truth)
    frame = frame + 0.05 * rng.normal(size=frame.shape)
    frames = np.stack([np.clip(frame, -1.0, 1.0), 0.1 * frame])[None]
    mf = MatchedFilter(pulse, frames.shape[-1], 200e3, decimation=2)
    options = EchoOptions()
    estimated = MatchedEstimator(mf, options).batch(frames)
    health = ChannelHealth((("clipped",), ()), reread=(0,), rails=np.array([[-1.0, 1.0], [-np.inf, np.inf]]))
    clipped = clipped_samples(frames, health)
    assert clipped[0, 0].any()
    assert not clipped[0, 1].any()
    reread = reread_clipped(frames, clipped, estimated, mf, options)
    assert reread[0][1] is estimated[0][1]

    def near(tof_s: np.ndarray, delay: float) -> np.ndarray:
        return np.abs(tof_s * 200e3 - delay) < 0.25

    before, after = estimated[0][0], reread[0][0]
    assert len(before.tof_s) >= 10
    for delay, _ in truth:
        assert near(after.tof_s, delay).sum() == 1
    assert len(after.tof_s) <= len(truth) + 2
    weak_before, weak_after = near(before.tof_s, 1500.2), near(after.tof_s, 1500.2)
    assert before.tof_s[weak_before] == after.tof_s[weak_after]
    assert before.amplitude[weak_before] == after.amplitude[weak_after]


def test_an_object_whose_clipped_echo_was_lost_is_found_where_it_was_clipped(
    scene_recording: Recording,
) -> None:
    """Two reflectors, the clipped channel 0 showing the echo of only one: the association of the
    four channels finds that one; the other is found with channel 0 excused when its echo
    there falls on clipped samples, and not when channel 0 was clean where it should be."""
    chain = prepare(scene_recording)
    recording = chain.recording
    points = np.array([[0.1, -0.2, 0.6], [-0.25, 0.15, 0.9]])
    paths = model_paths_m(recording.transmitters_m[0], recording.receivers_m, points)
    c = chain.speed_of_sound_m_s
    base = samples_echoes_batch(chain, [recording.frames[0]], [0], [0.0])[0]
    template = base.channels[1]
    channels = []
    for rx in range(4):
        delays = paths[:, rx] / c if rx else paths[:1, rx] / c
        order = np.argsort(delays)
        channels.append(
            replace(
                template,
                tof_s=delays[order],
                amplitude=np.ones(len(delays)),
                snr_db=np.full(len(delays), 40.0),
            )
        )
    echoes = FrameEchoes(0, 0.0, c, tuple(channels))
    objects = transmitter_objects(chain, echoes, 0)
    assert len(objects.objects) == 1
    n = recording.n_samples
    lost_at = int(paths[1, 0] / c * recording.sample_rate_hz)
    clipped = np.zeros((4, n), dtype=bool)
    clipped[0, lost_at + 20 : lost_at + 60] = True
    found = _excusing_clipped(chain, echoes, objects, 0, clipped)
    assert len(found.objects) == 2
    assert np.linalg.norm(found.objects[1].position_m - points[1]) < 1e-3
    assert found.objects[1].receivers == (1, 2, 3)
    elsewhere = np.zeros((4, n), dtype=bool)
    elsewhere[0, lost_at + 600 : lost_at + 640] = True
    assert len(_excusing_clipped(chain, echoes, objects, 0, elsewhere).objects) == 1
