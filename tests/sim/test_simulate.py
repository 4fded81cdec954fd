"""Tests of echoloc.sim.simulation: what the receivers of a sensor head record.

Sources: docs/METHOD.md (path l = |p - T| + |p - R|, ToF = l / c, report ch. 3.5), air.py
(spherical spreading 1 / (r_tx r_rx)), scene.py (noise convention: sigma = 10^(-snr/20)
for a unit echo at 1 m + 1 m), the sampling theorem (a band-limited signal delayed by any
real tau is sampled exactly by the band-limited fractional delay), and reciprocity
of linear acoustics (exchanging source and receiver leaves the transfer unchanged).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from echoloc.errors import SceneError
from echoloc.sim.scene import Array, RandomReflectors, Scene, default_scene
from echoloc.sim.scenefile import load_scene
from echoloc.sim.simulation import path_lengths_m, simulate
from echoloc.sim.synthesis import synthesize_frames
from repo_paths import REPO

RANDOM_TOML = REPO / "src" / "echoloc" / "scenes" / "random-1m3.toml"
FS = 200e3
FC = 50e3
# Gaussian-windowed 50 kHz tone: spectral std fs / (2 pi sigma) = 4 kHz, so its energy
# 50 kHz away (at DC and at Nyquist) is ~exp(-78): band-limited to double precision.
TONE_SIGMA = 8.0
TONE_CENTRE = 64.0
TONE_LEN = 128

coords = st.floats(min_value=-2.0, max_value=2.0, allow_nan=False)
points = st.tuples(coords, coords, coords)


def tone(t_samples: np.ndarray) -> np.ndarray:
    """The analytic test pulse at (fractional) sample times t."""
    u = np.asarray(t_samples, dtype=float) - TONE_CENTRE
    return np.exp(-0.5 * (u / TONE_SIGMA) ** 2) * np.sin(2 * np.pi * FC / FS * u)


def one_echo_scene(
    transmitter: list[float], receiver: list[float], reflector: list[float], **kw: object
) -> Scene:
    """A noiseless scene with one transmitter, one receiver and one unit reflector."""
    return Scene(
        array=Array(transmitters_m=np.array([transmitter]), receivers_m=np.array([receiver])),
        reflector_positions_m=np.array([reflector]),
        reflector_strengths=np.array([1.0]),
        snr_db=None,
        **kw,  # type: ignore[arg-type]
    )


def ls_amplitude(frame: np.ndarray, template: np.ndarray) -> float:
    """Least-squares amplitude a minimising |frame - a template|²."""
    return float(np.dot(frame, template) / np.dot(template, template))


# --- (1) band-limited fractional delay --------------------------------------------


@settings(max_examples=40, deadline=None)
@given(
    whole=st.integers(min_value=0, max_value=360),
    fraction=st.floats(min_value=0.01, max_value=0.99),
    amplitude=st.floats(min_value=0.1, max_value=10.0),
)
def test_fractional_delay_is_exact_for_band_limited_pulse(
    whole: int, fraction: float, amplitude: float
) -> None:
    """Sampling theorem: the frame equals a * g(n - tau fs) sample by sample.

    The synthesis interpolates a table 128 times finer than the samples linearly; its
    error bound max|g''| / (8 * 128²) is 2e-5 of the peak for this 50 kHz tone.
    """
    n_samples = 512
    delay = whole + fraction
    frames = synthesize_frames(
        tone(np.arange(TONE_LEN)),
        np.array([[[delay / FS]]]),
        np.array([[[amplitude]]]),
        sample_rate_hz=FS,
        n_samples=n_samples,
    )
    assert frames.shape == (1, 1, n_samples)
    expected = amplitude * tone(np.arange(n_samples) - delay)
    assert np.max(np.abs(frames[0, 0] - expected)) < 2e-5 * amplitude


def test_echoes_superpose_and_nan_padding_is_silent() -> None:
    """Linearity: several echoes add; NaN (padding) echoes contribute nothing, per channel."""
    n_samples = 600
    tof_samples = np.array([[[30.25, 200.7, np.nan], [111.5, np.nan, np.nan]]])
    amp = np.array([[[1.0, -0.5, 3.0], [2.0, 7.0, np.nan]]])
    frames = synthesize_frames(
        tone(np.arange(TONE_LEN)), tof_samples / FS, amp, sample_rate_hz=FS, n_samples=n_samples
    )
    n = np.arange(n_samples)
    assert np.max(np.abs(frames[0, 0] - (tone(n - 30.25) - 0.5 * tone(n - 200.7)))) < 4e-5
    assert np.max(np.abs(frames[0, 1] - 2.0 * tone(n - 111.5))) < 4e-5


# --- (2) spherical spreading -------------------------------------------------------


def test_echo_amplitude_is_inverse_square_on_boresight() -> None:
    """Receiver at the transmitter, reflector at range r on +z: echo = w delayed 2r/c, amplitude 1/r².

    Ranges chosen so that 2r/c is a whole number k of samples: the echo is then exactly
    the pulse shifted by k. Doubling r divides the least-squares amplitude by 4.
    """
    base = one_echo_scene([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 1.0])
    c = base.speed_of_sound_m_s
    w = base.waveform().samples
    amplitudes = []
    for k in (600, 1200):
        r = k * c / (2 * FS)
        scene = dataclasses.replace(base, reflector_positions_m=np.array([[0.0, 0.0, r]]))
        frame = simulate(scene).frames[0, 0]
        template = np.zeros_like(frame)
        template[k : k + len(w)] = w
        a = ls_amplitude(frame, template)
        assert a == pytest.approx(1.0 / r**2, rel=1e-9)
        assert np.max(np.abs(frame - a * template)) < 1e-9 * a
        amplitudes.append(a)
    assert amplitudes[0] / amplitudes[1] == pytest.approx(4.0, rel=1e-9)


@settings(max_examples=25, deadline=None)
@given(
    p=st.tuples(
        st.floats(min_value=-0.5, max_value=0.5),
        st.floats(min_value=-0.5, max_value=0.5),
        st.floats(min_value=0.2, max_value=1.2),
    ),
    strength=st.floats(min_value=0.1, max_value=5.0),
)
def test_echo_is_strength_over_rtx_rrx_at_path_over_c(p: tuple[float, float, float], strength: float) -> None:
    """Each receiver records strength / (r_tx r_rx) times the pulse delayed by (r_tx + r_rx) / c."""
    scene = dataclasses.replace(
        default_scene(),
        reflector_positions_m=np.array([p]),
        reflector_strengths=np.array([strength]),
        snr_db=None,
    )
    frames = simulate(scene).frames[0]
    point = np.array(p)
    r_tx = np.linalg.norm(point - scene.array.transmitters_m[0])
    r_rx = np.linalg.norm(scene.array.receivers_m - point, axis=1)
    tof = ((r_tx + r_rx) / scene.speed_of_sound_m_s)[None, :, None]
    unit = synthesize_frames(
        scene.waveform().samples, tof, np.ones_like(tof), sample_rate_hz=FS, n_samples=scene.n_samples
    )[0]
    for i in range(len(r_rx)):
        assert ls_amplitude(frames[i], unit[i]) == pytest.approx(strength / (r_tx * r_rx[i]), rel=1e-9)
    assert np.allclose(
        frames, unit * (strength / (r_tx * r_rx))[:, None], rtol=0, atol=1e-10 * np.max(np.abs(frames))
    )


# --- (3) geometry ------------------------------------------------------------------


@given(
    t=points,
    receivers=st.lists(points, min_size=1, max_size=4),
    batch=st.lists(points, min_size=1, max_size=3),
)
def test_path_lengths_are_sums_of_distances(
    t: tuple[float, ...], receivers: list[tuple[float, ...]], batch: list[tuple[float, ...]]
) -> None:
    """l = |p - T| + |p - R_i| (the ellipsoid with foci T and R_i), for a batch of points."""
    T, R, P = np.array(t), np.array(receivers), np.array(batch)
    path, r_tx, r_rx = path_lengths_m(T, R, P)
    assert path.shape == (len(P), len(R))
    for j, p in enumerate(P):
        assert r_tx[j] == pytest.approx(np.sqrt(np.sum((p - T) ** 2)), abs=1e-12)
        for i, rec in enumerate(R):
            d_rx = np.sqrt(np.sum((p - rec) ** 2))
            assert r_rx[j, i] == pytest.approx(d_rx, abs=1e-12)
            assert path[j, i] == pytest.approx(r_tx[j] + d_rx, abs=1e-12)


@given(t=points, receivers=st.lists(points, min_size=1, max_size=4), p=points)
def test_path_lengths_are_mirror_symmetric(
    t: tuple[float, ...], receivers: list[tuple[float, ...]], p: tuple[float, ...]
) -> None:
    """Mirroring x -> -x of transmitter, receivers and point leaves every path unchanged."""
    mirror = np.array([-1.0, 1.0, 1.0])
    T, R, P = np.array(t), np.array(receivers), np.array(p)
    path, _, _ = path_lengths_m(T, R, P)
    mirrored, _, _ = path_lengths_m(T * mirror, R * mirror, P * mirror)
    assert np.allclose(path, mirrored, rtol=1e-14, atol=1e-14)


@given(t=points, r=points, p=points)
def test_path_length_is_reciprocal(t: tuple[float, ...], r: tuple[float, ...], p: tuple[float, ...]) -> None:
    """Exchanging transmitter and receiver leaves the path unchanged."""
    forward, _, _ = path_lengths_m(np.array(t), np.array([r]), np.array(p))
    backward, _, _ = path_lengths_m(np.array(r), np.array([t]), np.array(p))
    assert forward[0] == pytest.approx(backward[0], abs=1e-12)


def test_report_array_mirror_pairs_record_equal_frames() -> None:
    """A reflector on the z axis is equidistant from all four report receivers: four equal frames."""
    scene = dataclasses.replace(
        default_scene(),
        reflector_positions_m=np.array([[0.0, 0.0, 0.7]]),
        reflector_strengths=np.ones(1),
        snr_db=None,
    )
    frames = simulate(scene).frames[0]
    for i in range(1, 4):
        assert np.allclose(frames[i], frames[0], rtol=0, atol=1e-10 * np.max(np.abs(frames)))


# --- (4) noise ---------------------------------------------------------------------


@pytest.mark.parametrize("snr_db", [0.0, 13.5, 40.0])
def test_noise_std_follows_snr_convention(snr_db: float) -> None:
    """Noise sigma = 10^(-snr/20) × pulse peak (1); white zero-mean Gaussian (scene.py convention)."""
    scene = dataclasses.replace(
        default_scene(),
        reflector_positions_m=np.array([[0.0, 0.0, 0.5]]),
        reflector_strengths=np.array([1e-12]),
        snr_db=snr_db,
    )
    frames = simulate(scene, n_frames=4).frames
    sigma = 10 ** (-snr_db / 20)
    n = frames.size
    assert n >= 30_000
    assert np.std(frames) == pytest.approx(sigma, rel=0.03)
    assert abs(np.mean(frames)) < 5 * sigma / np.sqrt(n)
    # White: neighbouring samples uncorrelated (|rho| < 5 / sqrt(n)).
    x = frames.reshape(-1)
    rho = np.corrcoef(x[:-1], x[1:])[0, 1]
    assert abs(rho) < 5 / np.sqrt(n)
    # Gaussian (thermal receiver noise): excess kurtosis 0, its std sqrt(24 / n) = 0.025 here.
    z = (x - x.mean()) / x.std()
    assert abs(np.mean(z**4) - 3.0) < 6 * np.sqrt(24 / n)


@pytest.mark.parametrize("range_m", [2.5, 3.0, 4.0, 6.0])
def test_reflector_beyond_the_frame_leaves_it_silent(range_m: float) -> None:
    """Causality: an echo arriving after the frame's last sample (path/c > n_samples/fs) is not recorded.

    Frame: 2400 samples = 12 ms = 4.12 m of path; here the path is 2 × range_m >= 5 m.
    """
    scene = one_echo_scene([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, range_m])
    assert 2 * range_m / scene.speed_of_sound_m_s > scene.n_samples / scene.sample_rate_hz + 1e-3
    frame = simulate(scene).frames[0, 0]
    echo_peak = 1.0 / range_m**2
    assert np.max(np.abs(frame)) < 1e-3 * echo_peak


@pytest.mark.parametrize("range_m", [0.3, 1.0, 2.0, 2.4, 3.0])
def test_recording_longer_does_not_change_earlier_samples(range_m: float) -> None:
    """Causality: the first n samples of a longer recording equal the shorter recording."""
    scene = one_echo_scene([0.0, 0.0, 0.0], [0.25, 0.0, 0.0], [0.0, 0.0, range_m])
    short = simulate(scene).frames[0, 0]
    long = simulate(dataclasses.replace(scene, n_samples=4 * scene.n_samples)).frames[0, 0, : scene.n_samples]
    echo_peak = 1.0 / (range_m * np.hypot(range_m, 0.25))
    assert np.max(np.abs(short - long)) < 1e-3 * echo_peak


# --- (5) reproducibility -----------------------------------------------------------


def test_same_seed_same_frames_different_seed_only_noise_differs() -> None:
    """Seeded noise: same seed identical; another seed differs by noise of std sqrt(2) sigma."""
    scene = default_scene()
    a = simulate(scene, n_frames=2).frames
    b = simulate(scene, n_frames=2).frames
    c = simulate(dataclasses.replace(scene, seed=scene.seed + 1), n_frames=2).frames
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
    assert scene.snr_db is not None
    sigma = 10 ** (-scene.snr_db / 20)
    assert np.std(a - c) == pytest.approx(np.sqrt(2) * sigma, rel=0.05)


def test_random_scene_is_reproducible() -> None:
    """A random scene with a fixed seed draws the same reflectors and noise every time."""
    scene = load_scene(RANDOM_TOML)
    a, b = simulate(scene, n_frames=3), simulate(scene, n_frames=3)
    assert np.array_equal(a.frames, b.frames)
    assert np.array_equal(a.truth_positions_m, b.truth_positions_m, equal_nan=True)
    c = simulate(dataclasses.replace(scene, seed=8), n_frames=3)
    assert not np.array_equal(a.truth_positions_m, c.truth_positions_m, equal_nan=True)


# --- (6) truth positions -----------------------------------------------------------


def test_truth_positions_are_nan_padded_and_counts_in_range() -> None:
    """truth_positions (n_frames, n_max, 3): present rows first, NaN rows pad; counts in [min, max]."""
    scene = load_scene(RANDOM_TOML)
    assert scene.random is not None
    low, high = scene.random.count
    rec = simulate(scene, n_frames=100)
    truth = rec.truth_positions_m
    assert truth is not None
    assert truth.shape == (100, high, 3)
    finite = np.isfinite(truth)
    assert np.all(finite.all(axis=2) | (~finite).all(axis=2))  # whole rows NaN or whole rows finite
    present = finite.all(axis=2)
    counts = present.sum(axis=1)
    assert np.all((counts >= low) & (counts <= high))
    assert np.array_equal(present, np.arange(high) < counts[:, None])  # padding only at the end
    # 100 uniform draws of 1..5 reach both ends.
    assert counts.min() == low
    assert counts.max() == high
    p = truth[present]
    box = scene.random
    for axis, (lo, hi) in enumerate((box.x_m, box.y_m, box.z_m)):
        assert np.all((p[:, axis] >= lo) & (p[:, axis] <= hi))


def test_random_frame_equals_its_truth_reflectors() -> None:
    """Each random frame is exactly the echoes of its truth reflectors (padding rows are silent)."""
    scene = dataclasses.replace(
        load_scene(RANDOM_TOML),
        random=RandomReflectors(count=(0, 4), strength=(1.0, 1.0)),
        snr_db=None,
        path_jitter_m=0.0,
    )
    rec = simulate(scene, n_frames=6)
    truth = rec.truth_positions_m
    assert truth is not None
    for k in range(rec.n_frames):
        rows = truth[k][np.isfinite(truth[k]).all(axis=1)]
        if len(rows) == 0:
            assert np.array_equal(rec.frames[k], np.zeros_like(rec.frames[k]))
            continue
        fixed = Scene(
            array=scene.array, reflector_positions_m=rows, reflector_strengths=np.ones(len(rows)), snr_db=None
        )
        assert np.allclose(
            rec.frames[k], simulate(fixed).frames[0], rtol=0, atol=1e-10 * np.max(np.abs(rec.frames[k]))
        )


def test_fixed_reflectors_come_first_in_truth() -> None:
    """Fixed reflectors occupy the first truth rows of every frame, random ones follow."""
    scene = dataclasses.replace(default_scene(), random=RandomReflectors(count=(2, 2)))
    truth = simulate(scene, n_frames=3).truth_positions_m
    assert truth is not None
    assert truth.shape == (3, 5, 3)
    assert np.array_equal(truth[:, :3], np.broadcast_to(scene.reflector_positions_m, (3, 3, 3)))
    assert np.all(np.isfinite(truth[:, 3:]))


# --- (7) reciprocity and recording metadata ----------------------------------------


@settings(max_examples=15, deadline=None)
@given(
    t=st.tuples(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-0.05, 0.05)),
    r=st.tuples(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-0.05, 0.05)),
    p=st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(0.3, 1.5)),
)
def test_swapping_transmitter_and_receiver_leaves_echo_unchanged(
    t: tuple[float, float, float], r: tuple[float, float, float], p: tuple[float, float, float]
) -> None:
    """Acoustic reciprocity: T -> p -> R records the same as R -> p -> T."""
    forward = simulate(one_echo_scene(list(t), list(r), list(p))).frames
    backward = simulate(one_echo_scene(list(r), list(t), list(p))).frames
    assert np.allclose(forward, backward, rtol=0, atol=1e-10 * np.max(np.abs(forward)))
    assert np.max(np.abs(forward)) > 0.1


def test_recording_carries_the_scene() -> None:
    """The recording holds the scene's geometry, pulse, sample rate, c and frame times k / frame_rate."""
    scene = default_scene()
    rec = simulate(scene, n_frames=3)
    assert rec.frames.shape == (3, 4, scene.n_samples)
    assert rec.sample_rate_hz == scene.sample_rate_hz
    assert np.array_equal(rec.receivers_m, scene.array.receivers_m)
    assert np.array_equal(rec.transmitters_m, scene.array.transmitters_m)
    assert np.array_equal(rec.waveform, scene.waveform().samples)
    assert rec.speed_of_sound_m_s == pytest.approx(343.2, abs=0.05)
    assert rec.carrier_hz == 50e3
    assert rec.signal_kind == "rf"
    assert rec.frame_times_s is not None
    assert np.allclose(rec.frame_times_s, [0.0, 0.01, 0.02])


def test_zero_frames_raises() -> None:
    """At least one frame."""
    with pytest.raises(SceneError, match="number of frames"):
        simulate(default_scene(), n_frames=0)


def test_the_absorption_table_of_a_long_frame_stays_small_and_exact_at_its_rows() -> None:
    """A frame of seconds made a table row per half metre of path, each the whole
    oversampled pulse: gigabytes (the fuzz campaign's 1 M-sample scene). Past 64 rows the
    rows widen; at every row the pulse is still attenuated by exactly alpha * path (ISO
    9613-1), and a short frame keeps its half-metre rows."""
    from echoloc.physics.air import absorption_db_per_m
    from echoloc.sim.synthesis import MAX_ABSORPTION_BINS, pulse_table

    t = np.arange(200) / 200e3
    pulse = np.sin(2 * np.pi * 50e3 * t) * np.hanning(200)
    alpha = functools.partial(absorption_db_per_m, temperature_c=20.0, relative_humidity=0.5)
    short = pulse_table(pulse, 200e3, absorption_db_per_m=alpha, max_path_m=10.0)
    assert short.bin_m == 0.5
    long = pulse_table(pulse, 200e3, absorption_db_per_m=alpha, max_path_m=1700.0)
    assert long.fine.shape[0] <= MAX_ABSORPTION_BINS + 2
    assert long.bin_m == pytest.approx(1700.0 / MAX_ABSORPTION_BINS)
    # Row 1 against row 0: the carrier's absorption over one (wider) bin, in dB.
    ratio_db = 20 * np.log10(np.max(np.abs(long.fine[1])) / np.max(np.abs(long.fine[0])))
    assert ratio_db == pytest.approx(-float(alpha(np.array([50e3]))[0]) * long.bin_m, rel=0.05)
