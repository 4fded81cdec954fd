"""The matched filter's batch path: compiled loops against their numpy statement, batches
against single frames, clusters against CLEAN, and the choice between two echoes and one."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from test_echoes import FS, N_SAMPLES, PULSE, frames_with_echoes

from echoloc.benchmark import bench_scene
from echoloc.errors import EchoLocError
from echoloc.localise.locate import model_paths_m
from echoloc.pipeline import prepare
from echoloc.sim.scene import default_scene
from echoloc.sim.simulation import simulate
from echoloc.tof import echoes as echoes_module
from echoloc.tof.echoes import (
    ChannelEchoes,
    EchoOptions,
    MatchedFilter,
    _batch_channels,
    _Clean,
    _compiled_batch,
    _compiled_echoes,
    _correlated_channels,
    _isolated_echoes,
    fft_workers,
    matched_filter_batch,
    matched_filter_echoes,
)

MF = MatchedFilter(PULSE, N_SAMPLES, FS)


def scene_frames(seed: int, n_frames: int = 6) -> np.ndarray:
    """Frames of 4 channels with 1-5 echoes each, some closer than two main lobes, noise σ 0.02."""
    rng = np.random.default_rng(seed)
    frames = []
    for _ in range(n_frames):
        delays = list(rng.uniform(300, 2000, rng.integers(1, 4)))
        delays.append(delays[0] + rng.uniform(10, 40))  # a cluster
        amplitudes = list(rng.uniform(0.3, 2.0, len(delays)))
        frames.append(
            frames_with_echoes(delays, amplitudes, noise_std=0.02, seed=int(rng.integers(1 << 30)))[0]
        )
    return np.array(frames)


@pytest.mark.parametrize("decimation", [1, 2])
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_compiled_loops_give_the_numpy_statement_s_answers(seed: int, decimation: int) -> None:
    """The compiled batch path and its numpy statement agree channel by channel (noise from all
    samples, no echo split), at every lag and at every second (the registered estimator's)."""
    mf = MatchedFilter(PULSE, N_SAMPLES, FS, decimation=decimation)
    frames = scene_frames(seed)
    correlation = mf.correlate_single(frames).reshape(-1, mf.n_lags)
    numpy_answer = _isolated_echoes(correlation, mf, EchoOptions())
    compiled = _compiled_echoes(correlation, mf, EchoOptions(), noise_step=1, max_splits=0)
    assert sum(a is not None for a in numpy_answer) >= len(numpy_answer) // 2  # the path is exercised
    for a, b in zip(numpy_answer, compiled, strict=True):
        assert (a is None) == (b is None)
        if a is not None and b is not None:
            assert b[0] == pytest.approx(a[0], abs=1e-9)
            assert b[1] == pytest.approx(a[1], rel=1e-9)
            assert b[2] == pytest.approx(a[2], rel=1e-6)


def test_echoes_unlike_the_template_stay_on_the_batch_path() -> None:
    """The report scene's receiver 2 sees its third ball's echo reshaped by the transducers, and
    at every second lag the phase-refined fit alone left it failing the residual checks (7 of 10
    channels to CLEAN). The least-squares step on lone echoes keeps all 10 on the batch path,
    every echo within 0.1 mm of its true path."""
    recording = simulate(default_scene(), 10)
    chain = prepare(recording)
    assert recording.waveform is not None
    assert recording.truth_positions_m is not None
    mf = MatchedFilter(np.asarray(recording.waveform, float), recording.n_samples, FS, decimation=2)
    correlation = mf.correlate_single(np.asarray(recording.frames, float)[:, 2])
    found = _compiled_echoes(correlation, mf, chain.echo_options)
    c = chain.speed_of_sound_m_s
    for frame, channel in enumerate(found):
        assert channel is not None, f"frame {frame}: receiver 2 handed to CLEAN"
        true_paths = model_paths_m(
            recording.transmitters_m[0], recording.receivers_m, recording.truth_positions_m[frame]
        )
        assert np.sort(channel[0]) / mf.lag_rate_hz * c == pytest.approx(np.sort(true_paths[:, 2]), abs=1e-4)


def test_correlation_and_fits_in_one_call_give_the_two_steps_answers() -> None:
    """The fused call (correlation and batch fits in one compiled call) finds, to the bit, what
    the single-precision correlation handed to the batch fits finds, channels for CLEAN included:
    the same weights, lags and constants reach the fits either way."""
    frames = scene_frames(5)
    fused = _correlated_channels(frames, MF, EchoOptions())
    stepwise = _batch_channels(
        MF.correlate_single_rows(frames).reshape(frames.shape[0] * frames.shape[1], -1), MF, EchoOptions()
    )
    assert sum(channel is not None and len(channel.tof_s) > 0 for channel in fused) >= len(fused) // 2
    for a, b in zip(fused, stepwise, strict=True):
        assert (a is None) == (b is None)
        if a is not None and b is not None:
            np.testing.assert_array_equal(a.tof_s, b.tof_s)
            np.testing.assert_array_equal(a.amplitude, b.amplitude)
            np.testing.assert_array_equal(a.snr_db, b.snr_db)


def test_a_batch_gives_each_frame_s_own_answer() -> None:
    """Echoes do not depend on the frames batched with them."""
    frames = scene_frames(4)
    batch = matched_filter_batch(frames, MF, EchoOptions())
    for frame, channels in zip(frames, batch, strict=True):
        for alone, batched in zip(matched_filter_echoes(frame, MF, EchoOptions()), channels, strict=True):
            np.testing.assert_array_equal(alone.tof_s, batched.tof_s)
            np.testing.assert_array_equal(alone.amplitude, batched.amplitude)


def test_threads_give_the_answers_of_one() -> None:
    """Spreading channels over threads (``workers``) changes no echo: channels are independent.

    The batch holds channels both paths take: isolated echoes and clusters (the batch path),
    and pairs 3 to 6 samples apart (CLEAN, several channels, so its rows are shared out too).
    """
    pairs = [[700.0, 703.0 + k, 1500.0] for k in range(4)]
    close = [frames_with_echoes(delays, [1.0, 0.8, 0.5], 0.02, seed=k)[0] for k, delays in enumerate(pairs)]
    frames = np.concatenate([scene_frames(5, n_frames=4), np.array(close)])
    correlation = MF.correlate_single(frames).reshape(-1, N_SAMPLES)
    hard = sum(found is None for found in _compiled_echoes(correlation, MF, EchoOptions()))
    assert hard >= 4  # CLEAN gets several rows
    one = matched_filter_batch(frames, MF, EchoOptions())
    two = matched_filter_batch(frames, MF, EchoOptions(workers=2))
    every = matched_filter_batch(frames, MF, EchoOptions(workers=-1))
    for answers in (two, every):
        for frame_one, frame_other in zip(one, answers, strict=True):
            for a, b in zip(frame_one, frame_other, strict=True):
                np.testing.assert_array_equal(a.tof_s, b.tof_s)
                np.testing.assert_array_equal(a.amplitude, b.amplitude)
                np.testing.assert_array_equal(a.snr_db, b.snr_db)


def test_fft_threads_only_from_32_rows_a_thread_and_never_change_the_correlation() -> None:
    """scipy.fft's threads cost more than they save on a few rows: none below 64 rows for two,
    never more than asked; the correlation is the same to the bit with any count."""
    assert [fft_workers(2, rows) for rows in (1, 4, 63, 64, 1000)] == [1, 1, 1, 2, 2]
    assert fft_workers(8, 100) == 3
    assert fft_workers(1, 1000) == 1
    frames = scene_frames(6, n_frames=20).reshape(-1, N_SAMPLES)  # 80 rows: two threads
    np.testing.assert_array_equal(MF.correlate(frames, 2), MF.correlate(frames, 1))


@pytest.mark.parametrize("workers", [0, -2])
def test_a_thread_count_below_one_is_refused(workers: int) -> None:
    with pytest.raises(EchoLocError, match="workers must be >= 1"):
        EchoOptions(workers=workers)


def test_half_cycle_slip_of_a_merged_pair_is_undone() -> None:
    """Two equal echoes 8 samples apart (under half the main lobe) at per-sample SNR 13: the
    joint fit with real amplitudes has a minimum every half carrier cycle (2 samples); the
    model choice tries each echo half a cycle off and left out, so both come out within a
    quarter cycle in at least 19 of 20 noisy frames."""
    delays = [700.37, 708.51]
    good = 0
    for seed in range(20):
        frames = frames_with_echoes(delays, [1.0, 1.0], noise_std=1 / 13, seed=seed)
        tof = matched_filter_echoes(frames[0], MF, EchoOptions())[0].tof_s * FS
        good += int(len(tof) == 2 and np.all(np.abs(tof - delays) < 0.5))
    assert good >= 19, good


MF2 = MatchedFilter(PULSE, N_SAMPLES, FS, decimation=2)  # the registered estimator's


@pytest.mark.parametrize(
    ("mf", "separations", "clean_tolerance"),
    [
        # Within two main lobes (17-sample main lobe), every lag: within the noise of CLEAN's joint fit.
        pytest.param(MF, (11.0, 30.0), 0.02, id="within-two-main-lobes"),
        # Within the main lobe, where the correlation may show one peak, every second lag (the
        # registered estimator's): the split on the batch path, or CLEAN.
        pytest.param(MF2, (6.0, 16.0), 0.03, id="within-a-main-lobe"),
    ],
)
@settings(max_examples=20, deadline=None)
@given(
    delay=st.floats(300.0, 2000.0),
    ratio=st.floats(0.5, 1.0),
    seed=st.integers(0, 1000),
    data=st.data(),
)
def test_close_pairs_are_found_as_clean_finds_them(
    mf: MatchedFilter,
    separations: tuple[float, float],
    clean_tolerance: float,
    delay: float,
    ratio: float,
    seed: int,
    data: st.DataObject,
) -> None:
    """Two echoes ``separations`` samples apart: both found within 0.05 samples at SNR 50, and
    within ``clean_tolerance`` samples of CLEAN's on the same channel, whichever path takes it."""
    separation = data.draw(st.floats(*separations), label="separation")
    delays = [delay, delay + separation]
    frames = frames_with_echoes(delays, [1.0, ratio], noise_std=0.02, seed=seed)
    channel = matched_filter_echoes(frames[0], mf, EchoOptions())[0]
    clean, _ = _Clean(mf, EchoOptions()).run(mf.correlate(frames[0, 0]))
    assert channel.tof_s * FS == pytest.approx(delays, abs=0.05)
    clean_delays = sorted(c.tof_samples / mf.lag_rate_hz + mf.arrival_s for c in clean)
    assert channel.tof_s == pytest.approx(clean_delays, abs=clean_tolerance / FS)


def test_the_split_keeps_pairs_within_a_main_lobe_on_the_batch_path() -> None:
    """Of 40 channels with a random pair 6-16 samples apart (amplitude ratio 0.5-1, SNR 50),
    without the split 27 go to CLEAN (at least 20 asked), with it none (at most 2 asked: a
    pair whose interference leaves more candidate peaks than the batch path takes goes)."""
    rng = np.random.default_rng(11)
    rows = []
    for k in range(40):
        delay, separation, ratio = rng.uniform(300, 2000), rng.uniform(6, 16), rng.uniform(0.5, 1.0)
        rows.append(frames_with_echoes([delay, delay + separation], [1.0, ratio], 0.02, seed=k)[0, 0])
    correlation = MF2.correlate_single(np.array(rows))
    without = sum(f is None for f in _compiled_echoes(correlation, MF2, EchoOptions(), max_splits=0))
    with_split = sum(f is None for f in _compiled_echoes(correlation, MF2, EchoOptions()))
    assert without >= 20, without
    assert with_split <= 2, with_split


def test_a_split_channel_reports_clean_s_noise_power() -> None:
    """Where the batch path splits an echo (five random reflectors, 40 frames: 25 channels), the
    channel's noise power is taken from what its echoes leave, as CLEAN takes it: within 40 %
    of CLEAN's on every such channel (0.90-1.37 of it), where the correlation's own median,
    which holds the crowd's sidelobes, is 1.8-3.3 times CLEAN's (its echoes' SNR 2.5-5 dB low)."""
    recording = simulate(bench_scene(5), 40)
    options = prepare(recording).echo_options
    assert recording.waveform is not None
    mf = MatchedFilter(np.asarray(recording.waveform, float), recording.n_samples, FS, decimation=2)
    rows = np.asarray(recording.frames, float).reshape(-1, recording.n_samples)
    correlation = mf.correlate_single(rows)
    unsplit = _compiled_batch(correlation, mf, options, max_splits=0)
    split = _compiled_batch(correlation, mf, options)
    channels = np.flatnonzero(split.ok & ~unsplit.ok)
    assert len(channels) >= 5
    clean = _Clean(mf, options)
    for channel in channels:
        _, clean_power = clean.run(mf.correlate(rows[channel]))
        assert split.power[channel] == pytest.approx(clean_power, rel=0.4)
        assert unsplit.power[channel] > 1.5 * clean_power


@pytest.mark.parametrize("separation", [6.3, 9.7, 14.2])
def test_a_noiseless_pair_is_split_exactly(separation: float) -> None:
    """Without noise the split's least-squares fit is the truth: a pair within a main lobe at
    every second lag comes out within 1e-4 samples, amplitudes within 1e-4."""
    delays = [900.37, 900.37 + separation]
    frames = frames_with_echoes(delays, [1.0, 0.7])
    channel = matched_filter_echoes(frames[0], MF2, EchoOptions())[0]
    assert channel.tof_s * FS == pytest.approx(delays, abs=1e-4)
    assert channel.amplitude / channel.amplitude[0] == pytest.approx([1.0, 0.7], abs=1e-4)


@pytest.mark.parametrize("separation", [1.0, 3.0, 4.0])
def test_a_pair_too_close_to_resolve_is_one_echo_as_clean_keeps_it(separation: float) -> None:
    """Two equal echoes 1-4 samples apart (under the quarter main lobe, 4.25 samples, below which
    CLEAN merges echoes; at 2 samples, half a carrier cycle, they cancel): the batch path keeps
    them as one echo between the two, as CLEAN does, on every one of 20 noisy channels, without
    handing the channel to CLEAN."""
    delays = [700.2, 700.2 + separation]
    for seed in range(20):
        frames = frames_with_echoes(delays, [1.0, 1.0], noise_std=0.02, seed=seed)
        assert _compiled_echoes(MF2.correlate_single(frames[0, :1]), MF2, EchoOptions())[0] is not None
        tof = matched_filter_echoes(frames[0], MF2, EchoOptions())[0].tof_s * FS
        clean, _ = _Clean(MF2, EchoOptions()).run(MF2.correlate(frames[0, 0]))
        assert len(tof) == len(clean) == 1
        assert delays[0] < tof[0] < delays[1]


def test_single_echoes_are_not_split_at_the_reports_snr() -> None:
    """The model choice adds an echo only when it pays more than its penalty: 40 noisy single
    echoes at per-sample SNR 13 come out as one echo each."""
    for seed in range(40):
        frames = frames_with_echoes([700.37 + seed * 0.1], [1.0], noise_std=1 / 13, seed=100 + seed)
        assert len(matched_filter_echoes(frames[0], MF, EchoOptions())[0].tof_s) == 1


def test_model_choice_survives_a_candidate_with_no_echo() -> None:
    """A stretch left with one echo offers "leave it out" as an empty model: it must lose, not raise
    (the study's SENT-template run hit this on 4 frames)."""
    frames = frames_with_echoes([700.37], [1.0], noise_std=0.02)
    clean = _Clean(MF, EchoOptions())
    components, power = clean.run(MF.correlate(frames[0, 0]))
    residual = MF.correlate(frames[0, 0]).copy()
    for c in components:
        shape, start = clean._shape(c.tof_samples)
        residual[start : start + len(shape)] -= c.amplitude * shape
    chosen = clean._try_models(residual, components, [[]], power, keep=lambda fitted: True)
    assert [c.tof_samples for c in chosen] == pytest.approx([700.37], abs=0.05)


def _same_runs(compiled: _Clean, python: _Clean, channel: np.ndarray) -> list:
    """CLEAN's compiled run and its Python statement on one channel: the same noise power and
    echoes to rounding; the compiled run's echoes."""
    correlation = MF.correlate(channel)
    a, power_a = compiled.run(correlation)
    b, power_b = python.run(correlation)
    assert power_a == pytest.approx(power_b, rel=1e-12)
    assert [c.tof_samples for c in a] == pytest.approx([c.tof_samples for c in b], abs=1e-8)
    assert [c.amplitude for c in a] == pytest.approx([c.amplitude for c in b], rel=1e-8)
    return a


@pytest.mark.parametrize("seed", [5, 6])
def test_compiled_clean_gives_the_python_statement_s_answers(seed: int) -> None:
    """CLEAN's compiled loops (extraction, successive refinement, the candidate models' fits) and
    its Python statement find the same echoes, channel by channel, to rounding: on channels with
    pairs closer than half a main lobe (the model choice) and far apart, at per-sample SNR 13."""
    rng = np.random.default_rng(seed)
    compiled, python = _Clean(MF, EchoOptions()), _Clean(MF, EchoOptions(), compiled=False)
    exercised = 0
    for _ in range(4):
        first = rng.uniform(300, 1800)
        delays = [first, first + rng.uniform(6, 14), first + rng.uniform(60, 400)]
        frames = frames_with_echoes(delays, list(rng.uniform(0.6, 1.0, 3)), noise_std=1 / 13, seed=seed)
        for channel in frames[0]:
            a = _same_runs(compiled, python, channel)
            exercised += len(a) >= 3
    assert exercised >= 8  # the pairs were found, so the model choice ran


def test_compiled_clean_extraction_matches_on_a_crowded_channel() -> None:
    """More echoes than ``max_echoes`` allows, some overlapping: both versions stop at the cap with
    the same echoes (the extraction loop's cap, clusters and refits)."""
    delays = [400.0, 409.0, 700.3, 712.0, 1000.0, 1300.7, 1310.2, 1600.0, 1900.0]
    frames = frames_with_echoes(delays, [1.0, 0.8, 1.2, 0.9, 0.5, 1.0, 1.0, 0.7, 0.4], noise_std=0.02)
    options = EchoOptions(max_echoes=6)
    correlation = MF.correlate(frames[0, 0])
    a, _ = _Clean(MF, options).run(correlation)
    b, _ = _Clean(MF, options, compiled=False).run(correlation)
    assert len(a) == len(b) >= 5
    assert [c.tof_samples for c in a] == pytest.approx([c.tof_samples for c in b], abs=1e-8)


@pytest.mark.parametrize("n", [1, 2, 3, 7, 600, 601])
def test_compiled_median_is_numpy_s_median(n: int) -> None:
    """The batch path's branch-free quickselect gives numpy's median exactly: on noise powers,
    with ties, sorted, reversed and organ-pipe orders (where a naive pivot degrades)."""
    from echoloc.tof._echoes_kernels import _median

    rng = np.random.default_rng(n)
    noise = rng.exponential(size=n)
    half = np.sort(noise[: n // 2])
    cases = [
        noise,
        np.round(noise, 1),
        np.sort(noise),
        np.sort(noise)[::-1],
        np.concatenate([half, half[::-1]]),
    ]
    for values in cases:
        if len(values):
            assert _median(np.ascontiguousarray(values)) == np.median(values)


@pytest.mark.parametrize("options", [EchoOptions(), EchoOptions(blanking_s=2.5e-3, dynamic_range_db=20.0)])
def test_compiled_finish_is_finish_channel(options: EchoOptions) -> None:
    """The batch path's compiled finishing (seconds, output SNR, blanking, threshold, dynamic range,
    ascending delay) gives finish_channel's echoes for every channel it fitted (fitted with the
    default options, so that stricter ones have echoes to drop)."""
    from echoloc.tof.echoes import _compiled_batch, _finish_batch, finish_channel

    frames = scene_frames(7)
    correlation = MF.correlate_single(frames).reshape(-1, N_SAMPLES)
    out = _compiled_batch(correlation, MF, EchoOptions())
    finished = _finish_batch(out, MF, options)
    assert sum(f is not None for f in finished) >= len(finished) // 2
    dropped = 0
    for c, channel in enumerate(finished):
        if channel is None:
            continue
        tof, amplitude = out.tof[c, : out.count[c]], out.amplitude[c, : out.count[c]]
        snr_db = 10 * np.log10(np.maximum(amplitude**2, 1e-300) / out.power[c])
        expected = finish_channel(tof / FS, amplitude, snr_db, options)
        dropped += len(tof) - len(expected.tof_s)
        np.testing.assert_array_equal(channel.tof_s, expected.tof_s)
        np.testing.assert_array_equal(channel.amplitude, expected.amplitude)
        np.testing.assert_allclose(channel.snr_db, expected.snr_db, rtol=1e-13)
    if options.blanking_s:
        assert dropped > 0  # the blanking and the dynamic range were exercised


def test_carrier_turning_fit_reaches_the_same_minimum() -> None:
    """joint_fit with complex amplitudes stepped in the frame turning with the carrier has the
    same cost and minima: on noiseless data of two echoes 12 samples apart (inside a main lobe),
    started a third of a sample and 20 % off, both parametrisations recover the true delays and
    amplitudes, and the rotated one also from half a carrier cycle (2 samples) off."""
    from echoloc.tof import _echoes_kernels as kernels
    from echoloc.tof.echoes import _shape_values

    delays, amplitudes = np.array([707.17, 719.4]), np.array([2.7 + 0.4j, -1.9 + 0.6j])
    lo, hi = 690, 737
    samples = np.arange(lo, hi)
    model = np.sum(
        amplitudes[:, None] * _shape_values(MF, delays, np.broadcast_to(samples, (2, hi - lo))), axis=0
    )
    data = np.ascontiguousarray(np.stack([model.real, model.imag], axis=-1))
    valid = np.ones(hi - lo, dtype=bool)
    rate = MF.phase_rate_rad_per_lag
    for rotation, offset in ((0.0, 0.3), (rate, 0.3), (rate, 2.0)):
        tofs, amps = delays + np.array([offset, -offset]), amplitudes * 0.8
        cost = kernels.joint_fit(
            MF.acf_table,
            MF.oversample,
            MF.half_width,
            data,
            lo,
            valid,
            tofs,
            amps,
            False,
            200,
            True,
            rotation,
            1e-9,
        )
        assert cost < 1e-16
        assert tofs == pytest.approx(delays, abs=1e-7)
        assert amps == pytest.approx(amplitudes, abs=1e-6)


@pytest.mark.parametrize("seed", [7, 8])
def test_compiled_clean_matches_on_three_overlapping_echoes(
    seed: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Three echoes a third to half a main lobe apart: the model choice reads a group of three (each
    member moved, each left out, each left out with another moved), and the compiled run finds the
    Python statement's echoes, channel by channel, to rounding."""
    rng = np.random.default_rng(seed)
    compiled, python = _Clean(MF, EchoOptions()), _Clean(MF, EchoOptions(), compiled=False)
    sizes: list[int] = []
    choose = _Clean._choose_overlapping

    def recording(self: _Clean, residual: np.ndarray, group: list, power: float) -> list:
        sizes.append(len(group))
        return choose(self, residual, group, power)

    monkeypatch.setattr(_Clean, "_choose_overlapping", recording)
    lobe = MF.mainlobe_lags
    for _ in range(3):
        first = rng.uniform(300, 1800)
        delays = [first, first + rng.uniform(0.35, 0.5) * lobe, first + rng.uniform(0.8, 1.0) * lobe]
        frames = frames_with_echoes(delays, list(rng.uniform(0.7, 1.0, 3)), noise_std=0.01, seed=seed)
        for channel in frames[0]:
            _same_runs(compiled, python, channel)
    assert max(sizes) >= 3  # a group of three reached the model choice


def test_stopping_the_complex_fit_on_a_small_gain_leaves_the_minimum() -> None:
    """The complex-amplitude stage stops once a step gains less than 1 % of the cost: on noisy data of
    two echoes 9 samples apart, started a third of a sample and half a carrier cycle off, the
    real-amplitude fit from there reaches the minimum it reaches after a complex stage run to 1e-9."""
    from echoloc.tof import _echoes_kernels as kernels
    from echoloc.tof.echoes import _shape_values

    delays, amplitudes = np.array([707.17, 716.2]), np.array([1.3, 0.9])
    lo, hi = 690, 734
    samples = np.arange(lo, hi)
    model = np.sum(
        amplitudes[:, None] * _shape_values(MF, delays, np.broadcast_to(samples, (2, hi - lo))), axis=0
    )
    rng = np.random.default_rng(3)
    noisy = model + 0.03 * (rng.normal(size=hi - lo) + 1j * rng.normal(size=hi - lo))
    data = np.ascontiguousarray(np.stack([noisy.real, noisy.imag], axis=-1))
    valid = np.ones(hi - lo, dtype=bool)
    rate = MF.phase_rate_rad_per_lag
    args = (MF.acf_table, MF.oversample, MF.half_width, data, lo, valid)
    for offset in (0.3, 2.0):
        found = []
        for tolerance, gain in ((1e-9, 0.0), (1e-3, 1e-2)):
            tofs, amps = delays + np.array([offset, -offset]), amplitudes * (0.8 + 0j)
            kernels.joint_fit(*args, tofs, amps, False, 200, True, rate, tolerance, gain)
            amps = np.where(amps.real >= 0, np.abs(amps), -np.abs(amps)) + 0j
            cost = kernels.joint_fit(*args, tofs, amps, True, 200, True, 0.0, 1e-6, 0.0)
            found.append((tofs, amps.real, cost))
        (full_tofs, full_amps, full_cost), (tofs, amps, cost) = found
        assert tofs == pytest.approx(full_tofs, abs=1e-7)
        assert amps == pytest.approx(full_amps, rel=1e-7)
        assert cost == pytest.approx(full_cost, rel=1e-10)
        assert tofs == pytest.approx(delays, abs=0.05)


def test_extraction_peak_search_is_the_first_largest_sample() -> None:
    """The extraction's running block maxima give the first sample of largest power at or after the
    blanking, as a full scan does: with ties, zeros and a refreshed stretch."""
    from echoloc.tof import _echoes_kernels as kernels

    rng = np.random.default_rng(11)
    residual = (rng.normal(size=1000) + 1j * rng.normal(size=1000)).round(1)  # many ties
    residual[:50] = 0
    for scan in (0, 37, 130):
        power = np.zeros(len(residual))
        block = np.zeros((len(residual) - scan + kernels._BLOCK - 1) // kernels._BLOCK)
        kernels._refresh_power(residual, power, block, scan, scan, len(residual))
        for lo, hi in ((400, 820), (0, 90), (990, 1000)):
            residual[lo:hi] *= rng.uniform(0.0, 1.2)
            kernels._refresh_power(residual, power, block, scan, lo, hi)
            expected = scan + int(np.argmax(np.abs(residual[scan:]) ** 2))
            peak, top = kernels._strongest(power, block, scan)
            assert peak == expected
            assert top == abs(residual[expected].real) ** 2 + abs(residual[expected].imag) ** 2
    nothing = np.zeros(100, dtype=complex)
    power, block = np.zeros(100), np.zeros(2)
    kernels._refresh_power(nothing, power, block, 0, 0, 100)
    assert kernels._strongest(power, block, 0) == (0, 0.0)


@pytest.mark.parametrize("n", [1024, 1025, 2400, 2401])
def test_sampled_median_is_numpy_s_median(n: int) -> None:
    """CLEAN's median bracketed by every 8th value gives numpy's median exactly: on noise powers, with
    ties, sorted, reversed, organ-pipe and constant orders, and where the sampled values mislead the
    bracket (all of them huge or zero: the full quickselect then)."""
    from echoloc.tof._echoes_kernels import _median_sampled

    rng = np.random.default_rng(n)
    for _ in range(5):
        powers = np.abs(rng.normal(size=n) + 1j * rng.normal(size=n)) ** 2
        ordered = np.sort(powers)
        huge, zero = powers.copy(), powers.copy()
        huge[::8], zero[::8] = 1e9, 0.0
        for values in (
            powers,
            powers.round(1),
            ordered,
            ordered[::-1],
            np.concatenate([ordered[::2], ordered[1::2][::-1]]),
            np.ones(n),
            huge,
            zero,
        ):
            assert _median_sampled(np.ascontiguousarray(values)) == np.median(values)


def _noise_median(values: np.ndarray) -> float:
    """The batch path's noise median of ``values``, its counters checked left at zero."""
    from echoloc.tof import _echoes_kernels as kernels

    counts = np.zeros(kernels._EXPONENT_BUCKETS + kernels._MANTISSA_BUCKETS, dtype=np.int32)
    found = kernels._noise_median(
        np.ascontiguousarray(values, dtype=float), counts, np.zeros((3, len(values)))
    )
    assert not counts.any()
    return float(found)


@settings(max_examples=300, deadline=None)
@given(
    values=st.lists(
        st.one_of(
            st.floats(0.0, 1e300),
            st.floats(0.0, 1e-300),  # subnormals among them
            st.sampled_from([0.0, 1.0, 2.0, 1.0 + 2**-40, np.inf]),
        ),
        min_size=1,
        max_size=80,
    )
)
def test_the_radix_noise_median_is_numpy_s_median(values: list[float]) -> None:
    """Exactly, on non-negative values: ties, zeros, subnormals, neighbours one bit apart, inf."""
    assert _noise_median(np.array(values)) == np.median(values)


@pytest.mark.parametrize("n", [599, 600, 601, 2400])
def test_the_radix_noise_median_on_noise_and_its_hard_cases(n: int) -> None:
    """On a channel's noise powers with echo peaks, sorted, constant (a dead channel: more
    values share a band than it sorts), and with a negative or NaN value (the quickselect then,
    which it equals): numpy's median, and with a NaN the quickselect's answer."""
    from echoloc.tof._echoes_kernels import _median

    rng = np.random.default_rng(n)
    powers = np.abs(rng.normal(size=n) + 1j * rng.normal(size=n)) ** 2
    powers[rng.integers(0, n, 12)] *= 1e4
    negative, nan = powers.copy(), powers.copy()
    negative[3], nan[5] = -1.0, np.nan
    for values in (powers, np.sort(powers), np.zeros(n), np.full(n, 3.5), powers * 1e-310, negative):
        assert _noise_median(values) == np.median(values)
    np.testing.assert_equal(_noise_median(nan), _median(np.ascontiguousarray(nan)))


@settings(max_examples=60, deadline=None)
@given(
    delay=st.floats(40.0, 60.0),
    start_error=st.floats(-0.4, 0.4),
    amplitude=st.floats(0.2, 3.0) | st.floats(-3.0, -0.2),
    noise=st.floats(0.0, 0.05),
    iterations=st.integers(1, 4),
    seed=st.integers(0, 2**16),
)
# Converged at a low SNR, a step whose cost change is at rounding level: one fit takes it,
# the other turns it down and takes a smaller one later (1.8e-9 lags apart after 4
# iterations, 1.4e-11 after 7).
@example(
    delay=40.0,
    start_error=0.044816103427745994,
    amplitude=0.2,
    noise=0.044816103427745994,
    iterations=4,
    seed=4,
)
def test_lone_echo_step_is_the_general_fit_s(
    delay: float, start_error: float, amplitude: float, noise: float, iterations: int, seed: int
) -> None:
    """The batch path's scalar step for a lone echo (_lone_fit) takes the general joint fit's
    Levenberg-Marquardt steps (_joint_fit_into, one echo, real amplitude) to rounding, or, where
    rounding decides whether a converged fit's last tiny step is taken, lands within 1e-7 lags
    (the filter keeps every 2nd sample: 2e-7 samples, 1 ps at 200 kHz; a wrong step would be
    off by thousandths of a lag or more)."""
    from echoloc.tof import _echoes_kernels as kernels

    mf = MatchedFilter(PULSE, N_SAMPLES, FS, decimation=2)
    rng = np.random.default_rng(seed)
    lo, w = int(delay) - 6, 13
    lags = np.arange(lo, lo + w)
    values = np.array(
        [
            kernels._model(
                mf.acf_table, mf.half_width, *_grid_of(mf, delay), np.array([amplitude + 0j]), 1, s, 0, 0
            )
            for s in lags
        ]
    )
    values += noise * (rng.normal(size=w) + 1j * rng.normal(size=w))
    data = np.stack([values.real, values.imag], axis=1)
    valid = np.ones(w, dtype=bool)
    valid[rng.integers(0, w)] = False  # a sample outside the frame
    start_tof, start_amp = delay + start_error, complex(amplitude * 0.9)
    tofs, amps = np.array([start_tof]), np.array([start_amp])
    kernels.joint_fit(
        mf.acf_table, mf.oversample, mf.half_width, data, lo, valid, tofs, amps, True, iterations
    )
    tof, amp = kernels._lone_fit(
        mf.acf_table, mf.oversample, mf.half_width, data, lo, valid, start_tof, start_amp, iterations
    )
    assert tof == pytest.approx(tofs[0], abs=1e-7)
    assert amp.real == pytest.approx(amps[0].real, rel=1e-7, abs=1e-12)
    assert amp.imag == 0.0


def _grid_of(mf: MatchedFilter, delay: float) -> tuple[np.ndarray, np.ndarray]:
    """The kernels' grid position (base and rows, weight) of one delay."""
    from echoloc.tof import _echoes_kernels as kernels

    grid_b, grid_w = np.zeros((1, 4), dtype=np.int64), np.zeros(1)
    kernels._prepare(mf.oversample, np.array([delay]), grid_b, grid_w)
    return grid_b, grid_w


def test_the_fast_channel_echoes_is_the_dataclass_value() -> None:
    """echoes._channel builds what ChannelEchoes(...) builds, field for field."""
    values = (np.array([1e-3, 2e-3]), np.array([0.5, 0.2]), np.array([30.0, 22.0]))
    fast, plain = echoes_module._channel(*values), ChannelEchoes(*values)
    assert type(fast) is ChannelEchoes
    assert vars(fast) == vars(plain)


def test_the_fixed_kernel_arguments_follow_the_options_threads_and_channels() -> None:
    """The memo of the compiled call's fixed arguments never hands one set of options' (or
    thread or channel count's) arguments to another."""
    recording = simulate(default_scene(), 1)
    mf = MatchedFilter(np.asarray(recording.waveform, float), recording.n_samples, recording.sample_rate_hz)
    base = EchoOptions()
    stricter = EchoOptions(threshold_db=base.threshold_db + 6)
    first = echoes_module._fixed_kernel_arguments(mf, base, 1, 4)
    assert echoes_module._fixed_kernel_arguments(mf, base, 1, 4) is first
    other = echoes_module._fixed_kernel_arguments(mf, stricter, 1, 4)
    assert other[-2][7] == pytest.approx(first[-2][7] * 10 ** (6 / 10))  # the threshold factor
    import numba

    threads = numba.get_num_threads()  # _kernel_threads sets numba's count for the thread
    try:
        assert echoes_module._fixed_kernel_arguments(mf, base, 2, 64)[3:5] == (
            fft_workers(2, 64),
            echoes_module._kernel_threads(2, 64),
        )
    finally:
        numba.set_num_threads(threads)


def test_two_threads_with_parallel_kernels_on_numba_s_workqueue_layer_do_not_kill_the_process() -> None:
    """Two chains with two workers each, run in two Python threads at once, on the threading
    layer numba falls back to without OpenMP or TBB: it terminated the process when both
    started parallel loops together; run_kernel takes them one at a time. Each thread's
    objects are those of one thread alone."""
    import os
    import subprocess
    import sys
    import textwrap

    child = textwrap.dedent(
        """
        import threading
        from echoloc.benchmark import bench_scene
        from echoloc.tof.echoes import EchoOptions
        from echoloc.pipeline import prepare, run
        from echoloc.sim.simulation import simulate

        recording = simulate(bench_scene(5), 64)
        chains = [prepare(recording, echo_options=EchoOptions(workers=2)) for _ in range(2)]
        alone = [len(o.objects) for _, o in run(chains[0], batch_frames=32)]
        found = {}

        def work(i):
            found[i] = [len(o.objects) for _, o in run(chains[i], batch_frames=32)]

        for _ in range(3):
            threads = [threading.Thread(target=work, args=(i,)) for i in range(2)]
            [t.start() for t in threads]
            [t.join() for t in threads]
            assert found[0] == found[1] == alone
        import numba
        print(numba.threading_layer(), sum(alone))
        """
    )
    env = {**os.environ, "NUMBA_THREADING_LAYER": "workqueue"}
    done = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=600, env=env)
    assert done.returncode == 0, (done.stdout + done.stderr)[-2000:]
    layer, objects = done.stdout.split()[-2:]
    assert layer == "workqueue"
    assert int(objects) >= 5 * 64 * 0.9
