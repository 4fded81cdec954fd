"""Time of flight: every estimator against known delays, sidelobes, overlap and noise."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import signal

from echoloc.io.recording import Recording
from echoloc.physics.waveform import barker_waveform
from echoloc.sim.synthesis import synthesize_frames
from echoloc.tof.echoes import ChannelEchoes, EchoOptions, MatchedFilter, noise_power
from echoloc.tof.estimators import ESTIMATORS

FS = 200e3
N_SAMPLES = 2400
PULSE = barker_waveform(13, carrier_hz=50e3, cycles_per_bit=4, sample_rate_hz=FS).samples


def frames_with_echoes(
    delays_samples: list[float], amplitudes: list[float], noise_std: float = 0.0, seed: int = 0
) -> np.ndarray:
    """One frame, 4 identical receivers, echoes at the given delays (band-limited)."""
    tof = np.array(delays_samples, dtype=float) / FS
    amp = np.array(amplitudes, dtype=float)
    frames = synthesize_frames(
        PULSE,
        np.broadcast_to(tof, (1, 4, len(tof))).copy(),
        np.broadcast_to(amp, (1, 4, len(amp))).copy(),
        sample_rate_hz=FS,
        n_samples=N_SAMPLES,
    )
    if noise_std:
        frames = frames + np.random.default_rng(seed).normal(0.0, noise_std, frames.shape)
    return frames


def recording_of(frames: np.ndarray) -> Recording:
    receivers = np.array([[0.25, 0, 0], [-0.25, 0, 0], [0, 0.25, 0], [0, -0.25, 0]], dtype=float)
    return Recording(FS, np.zeros((1, 3)), receivers, frames, PULSE, carrier_hz=50e3)


def run(name: str, frames: np.ndarray, options: EchoOptions | None = None) -> list[ChannelEchoes]:
    estimator = ESTIMATORS[name].prepare(recording_of(frames), options or EchoOptions())
    return estimator(frames[0])


@pytest.mark.parametrize("name", sorted(n for n, e in ESTIMATORS.items() if "rf" in e.signal_kinds))
@settings(max_examples=25, deadline=None)
@given(delay=st.floats(min_value=250.0, max_value=2000.0), amplitude=st.floats(0.05, 20.0))
def test_every_estimator_recovers_a_clean_delay(name: str, delay: float, amplitude: float) -> None:
    """Each registered estimator finds one clean echo within its documented tolerance."""
    channels = run(name, frames_with_echoes([delay], [amplitude]))
    for channel in channels:
        assert len(channel.tof_s) == 1
        assert abs(channel.tof_s[0] - delay / FS) <= ESTIMATORS[name].clean_tolerance_s


@settings(max_examples=20, deadline=None)
@given(delay=st.floats(min_value=250.0, max_value=2000.0))
def test_matched_filter_recovers_amplitude_and_inverted_echoes(delay: float) -> None:
    """An inverted echo (reflection with a sign change) has the same arrival and magnitude.

    The carrier phase alone is ambiguous by half a cycle for an inverted echo; the
    envelope must pick the right branch.
    """
    for sign in (1.0, -1.0):
        channel = run("matched", frames_with_echoes([delay], [2.5 * sign]))[0]
        assert channel.tof_s == pytest.approx([delay / FS], abs=1e-9)
        assert channel.amplitude == pytest.approx([2.5], rel=1e-4)


def test_matched_filter_separates_the_reports_two_balls() -> None:
    """Balls 16 mm apart in range (32 mm of path, 1.17 chips) give two echoes, each exact.

    Report table 4.3: correlation resolves two balls at 580 and 596 mm.
    """
    c = 343.2
    first = 2 * 0.580 / c * FS
    second = 2 * 0.596 / c * FS
    channel = run("matched", frames_with_echoes([first, second], [1.0, 0.9]))[0]
    assert channel.tof_s * c == pytest.approx(np.array([first, second]) / FS * c, abs=1e-6)
    assert channel.amplitude == pytest.approx([1.0, 0.9], rel=1e-3)


def test_threshold_sees_only_the_first_of_overlapping_echoes() -> None:
    """As the report notes, threshold detection cannot separate overlapping echoes.

    The overlap also inflates the measured peak, and with it the rise-time
    correction: the arrival comes out late by a few microseconds.
    """
    channel = run("threshold", frames_with_echoes([700.0, 720.0], [1.0, 1.0]))[0]
    assert len(channel.tof_s) == 1
    assert 0.0 < channel.tof_s[0] - 700.0 / FS < 10e-6


def test_weak_echo_is_found_beside_a_strong_one_without_sidelobe_detections() -> None:
    """Barker-13 sidelobes are 1/13 of the peak (-22 dB); a -30 dB echo far away is still found.

    CLEAN removes each echo with its sidelobes, so no sidelobe becomes an echo.
    """
    channel = run("matched", frames_with_echoes([600.0, 1500.3], [10.0, 0.3], noise_std=0.01))[0]
    assert len(channel.tof_s) == 2
    assert channel.tof_s == pytest.approx(np.array([600.0, 1500.3]) / FS, abs=20e-9)


def test_noise_alone_gives_no_echo() -> None:
    """At the default 14 dB threshold, Rayleigh noise exceeds it with probability 1.4e-11 per sample."""
    for seed in range(10):
        channels = run("matched", frames_with_echoes([], [], noise_std=1.0, seed=seed))
        assert all(len(channel.tof_s) == 0 for channel in channels)


def test_snr_follows_its_definition() -> None:
    """Output SNR = |a|^2 / P with P = 2 sigma^2 / E_w, the normalised analytic noise power."""
    amplitude, sigma = 1.0, 0.2
    energy = float(np.sum(PULSE**2))
    expected_db = 10 * np.log10(amplitude**2 * energy / (2 * sigma**2))
    snrs = [
        run("matched", frames_with_echoes([900.0], [amplitude], sigma, seed))[0].snr_db[0]
        for seed in range(5)
    ]
    assert np.mean(snrs) == pytest.approx(expected_db, abs=1.0)


def test_noise_power_is_the_mean_power_of_circular_gaussian_noise() -> None:
    """median(|z|^2) / ln 2 estimates E|z|^2 for circular Gaussian z (|z|^2 is exponential)."""
    rng = np.random.default_rng(1)
    z = rng.normal(0, 3.0, 100_000) + 1j * rng.normal(0, 3.0, 100_000)
    assert noise_power(z) == pytest.approx(18.0, rel=0.02)


def test_blanking_drops_early_echoes() -> None:
    """Echoes before the blanking time (transmitter ring-down) are not reported."""
    frames = frames_with_echoes([300.0, 900.0], [1.0, 1.0])
    channel = run("matched", frames, EchoOptions(blanking_s=500 / FS))[0]
    assert channel.tof_s == pytest.approx([900.0 / FS], abs=1e-9)


def test_autocorrelation_table_is_normalised_and_symmetric() -> None:
    """R(0) = 1 for the normalised analytic ACF, and |R(-m)| = |R(m)|."""
    mf = MatchedFilter(PULSE, N_SAMPLES, FS)
    row = mf.acf_table[0]
    centre = mf.half_width
    assert row[centre] == pytest.approx(1.0, abs=1e-12)
    assert np.abs(row) == pytest.approx(np.abs(row[::-1]), abs=1e-12)


def test_a_kept_autocorrelation_table_is_the_built_one_and_a_copy(monkeypatch: pytest.MonkeyPatch) -> None:
    """Filters of the same template share the table's building, not the table: the kept one
    is the one built to the bit, each filter gets its own copy (from a build or from the store),
    what the table does not depend on (sample rate, arrival) shares it, another pulse or
    oversampling or decimation gets its own, and the store drops the least recently used
    table first and never holds more than its bytes."""
    from echoloc.tof import echoes

    echoes._ACF_TABLES.clear()
    first = MatchedFilter(PULSE, N_SAMPLES, FS)
    built = first._built_acf_table()
    assert np.array_equal(first.acf_table, built)
    first.acf_table[0, 0] = 7.0  # the built table's copy written over
    second = MatchedFilter(PULSE.copy(), N_SAMPLES, FS * 2, arrival_s=1e-4)  # a hit
    assert np.array_equal(second.acf_table, built)
    second.acf_table[0, 1] = 7.0  # a kept table's copy written over
    assert np.array_equal(MatchedFilter(PULSE, N_SAMPLES, FS).acf_table, built)
    assert len(echoes._ACF_TABLES) == 1
    others = [
        MatchedFilter(PULSE, N_SAMPLES, FS, oversample=64),
        MatchedFilter(PULSE, N_SAMPLES, FS, decimation=2),
        MatchedFilter(PULSE.astype(np.float32), N_SAMPLES, FS),
        MatchedFilter(
            barker_waveform(7, carrier_hz=50e3, cycles_per_bit=4, sample_rate_hz=FS).samples, N_SAMPLES, FS
        ),
    ]
    for mf in others:
        assert np.array_equal(mf.acf_table, mf._built_acf_table())
    assert others[0].acf_table.shape[0] == 64
    assert len(echoes._ACF_TABLES) == 1 + len(others)
    # Room for three tables of the default head: the oldest goes, unless it was used since.
    monkeypatch.setattr(echoes, "_ACF_TABLES_BYTES", 3 * built.nbytes)
    echoes._ACF_TABLES.clear()
    lengths = [2000, 2400, 2500, 2800]  # FFTs of 2250, 2700, 2880, 3072
    filters = [MatchedFilter(PULSE, n, FS) for n in lengths]
    assert len({mf.n_fft for mf in filters}) == len(lengths)
    keys = []
    for mf in filters[:3]:
        mf.acf_table  # noqa: B018 - built and kept
        keys.append(next(reversed(echoes._ACF_TABLES)))
    MatchedFilter(PULSE, lengths[0], FS).acf_table  # noqa: B018 - the first, used again
    filters[3].acf_table  # noqa: B018 - a fourth: the least recently used (the second) goes
    assert keys[0] in echoes._ACF_TABLES
    assert keys[1] not in echoes._ACF_TABLES
    assert sum(t.nbytes for t in echoes._ACF_TABLES.values()) <= 3 * built.nbytes
    monkeypatch.setattr(echoes, "_ACF_TABLES_BYTES", built.nbytes - 1)
    echoes._ACF_TABLES.clear()
    assert np.array_equal(MatchedFilter(PULSE, N_SAMPLES, FS).acf_table, built)
    assert not echoes._ACF_TABLES  # too large to keep


def test_main_lobe_is_one_chip_wide() -> None:
    """The -6 dB width of a Barker code's ACF envelope is one chip (triangle of half-base one chip)."""
    mf = MatchedFilter(PULSE, N_SAMPLES, FS)
    chip_samples = 4 / 50e3 * FS
    assert mf.mainlobe_lags == pytest.approx(chip_samples, abs=1.5)


def test_phase_rate_is_the_carrier() -> None:
    """The ACF phase advances by 2 pi f_c / f_s per sample: 90 degrees at 4 samples per cycle."""
    mf = MatchedFilter(PULSE, N_SAMPLES, FS)
    assert mf.phase_rate_rad_per_lag == pytest.approx(np.pi / 2, rel=0.01)


@pytest.mark.parametrize("decimation", [1, 2, 3])
def test_a_decimated_correlation_is_every_dth_lag_of_the_full_one(decimation: int) -> None:
    """Folding the spectrum onto N/D bins gives the full correlation's lags 0, D, 2D, ... exactly,
    in double and single precision, for an odd frame length too (its last lag included; at D = 1
    the single-precision fold pads the spectrum's bins with zeros to the full inverse length)."""
    rng = np.random.default_rng(5)
    frames = rng.normal(size=(3, N_SAMPLES - 1))
    full = MatchedFilter(PULSE, N_SAMPLES - 1, FS)
    mf = MatchedFilter(PULSE, N_SAMPLES - 1, FS, decimation=decimation)
    assert mf.n_fft % decimation == 0
    assert mf.n_lags == len(range(0, N_SAMPLES - 1, decimation))
    expected = full.correlate(frames)[:, ::decimation]
    scale = np.abs(expected).max()
    assert mf.correlate(frames) == pytest.approx(expected, abs=1e-12 * scale)
    assert mf.correlate_single(frames) == pytest.approx(expected, abs=1e-5 * scale)


def test_the_correlation_is_numpys_correlate_made_analytic_by_scipys_hilbert() -> None:
    """Lag k is sum_n x[n + k] w[n] / sum w^2 plus j times its Hilbert transform: numpy's linear
    correlation, laid out circularly on the FFT's length, through scipy.signal.hilbert (the
    reference shares no code with the matched filter's spectrum product and fold)."""
    rng = np.random.default_rng(9)
    frames = rng.normal(size=(2, N_SAMPLES))
    mf = MatchedFilter(PULSE, N_SAMPLES, FS)
    assert mf.n_fft >= N_SAMPLES + len(PULSE) - 1  # no wrap-around onto the kept lags
    expected = []
    for frame in frames:
        linear = np.correlate(frame, PULSE, mode="full")  # lags -(L - 1) .. N - 1
        circular = np.zeros(mf.n_fft)
        lags = np.arange(-(len(PULSE) - 1), N_SAMPLES)
        circular[lags % mf.n_fft] = linear
        expected.append(signal.hilbert(circular)[: mf.n_lags] / np.sum(PULSE**2))
    scale = np.abs(expected).max()
    assert mf.correlate(frames) == pytest.approx(np.array(expected), abs=1e-12 * scale)
    assert mf.correlate_single(frames) == pytest.approx(np.array(expected), abs=1e-5 * scale)


def test_the_decimated_tables_are_the_full_ones_every_second_lag() -> None:
    """At D = 2 row j (shift 2j/U samples) is the full table's row 2j at even lags; the main lobe,
    phase rate and lag rate are those of the full rate in units of two samples."""
    full = MatchedFilter(PULSE, N_SAMPLES, FS)
    half = MatchedFilter(PULSE, N_SAMPLES, FS, decimation=2)
    assert half.half_width * 2 == full.half_width
    for j in (0, 1, 37, 127):
        assert half.acf_table[j] == pytest.approx(full.acf_table[2 * j, ::2], abs=1e-12)
    assert half.mainlobe_lags == pytest.approx(full.mainlobe_lags / 2)
    assert half.phase_rate_rad_per_lag == pytest.approx(2 * full.phase_rate_rad_per_lag)
    assert half.lag_rate_hz == FS / 2
    # The sidelobe envelope bounds |R| at every sample within a lag, not only at even ones.
    envelope = np.abs(full.autocorrelation)
    for lag in range(2, half.half_width - 1):
        bound = half.sidelobe_envelope[half.half_width + lag]
        assert bound >= envelope[full.half_width + 2 * lag + 1] - 1e-12


@given(delay=st.floats(500.0, 1800.0), spacing=st.floats(30.0, 200.0))
@settings(max_examples=25, deadline=None)
def test_full_and_decimated_filters_find_the_same_echoes(delay: float, spacing: float) -> None:
    """Two noiseless echoes: the registered (decimated) matched filter and one at every sample find
    both at their true delays, to a thousandth of a sample, and their amplitudes within 1 %
    (a lone echo's fit keeps the other echo's sidelobes as the single fits left them)."""
    from echoloc.tof.echoes import matched_filter_echoes

    frames = frames_with_echoes([delay, delay + spacing], [1.0, 0.6])[0]
    for decimation in (1, 2):
        mf = MatchedFilter(PULSE, N_SAMPLES, FS, decimation=decimation)
        channel = matched_filter_echoes(frames, mf, EchoOptions())[0]
        assert channel.tof_s * FS == pytest.approx([delay, delay + spacing], abs=1e-3)
        assert channel.amplitude == pytest.approx([1.0, 0.6], rel=1e-2)


def test_a_decimation_below_one_is_refused() -> None:
    from echoloc.errors import EchoLocError

    with pytest.raises(EchoLocError, match="decimation must be >= 1, got 0"):
        MatchedFilter(PULSE, N_SAMPLES, FS, decimation=0)


def test_matched_filter_is_unbiased_in_noise_at_the_reports_snr() -> None:
    """Per-sample SNR 13 (report ch. 4): errors are unbiased and far below a millimetre."""
    c = 343.2
    delay = 700.37
    errors = []
    for seed in range(30):
        channel = run("matched", frames_with_echoes([delay], [1.0], noise_std=1 / 13, seed=seed))[0]
        assert len(channel.tof_s) == 1
        errors.append((channel.tof_s[0] - delay / FS) * c)
    assert abs(np.mean(errors)) < 0.02e-3
    assert np.std(errors) < 0.05e-3


def test_blanked_ring_down_does_not_set_the_dynamic_range_floor() -> None:
    """A ring-down 60 dB above a later echo, inside the blanking interval, must not hide it.

    Were the blanked ring-down extracted first, it would set the 40 dB dynamic-range
    floor and the weak echo below it would be dropped.
    """
    frames = frames_with_echoes([20.0, 1200.0], [1000.0, 1.0], noise_std=1e-4)
    channel = run("matched", frames, EchoOptions(blanking_s=400 / FS))[0]
    assert channel.tof_s == pytest.approx([1200.0 / FS], abs=1e-9)


def test_two_equal_echoes_half_a_chip_apart_are_both_found_at_the_reports_snr() -> None:
    """Issue 8's resolution figure: reflectors 7 mm apart in range (half the 13.7 mm chip),
    equal echoes, per-sample SNR 13, the 50 kHz transducer pair: both echoes within 1 mm
    of range in at least 95 % of 40 noisy trials (200 of 200 with the study's protocol)."""
    from echoloc.physics.crlb import peak_amplitude
    from echoloc.sim.reflectors import PointReflector
    from echoloc.sim.scene import Array, Scene
    from echoloc.sim.simulation import simulate

    pair = Array(np.array([[-0.02, 0.0, 0.0]]), np.array([[0.02, 0.0, 0.0]]))
    tx, rx = pair.transmitters_m[0], pair.receivers_m[0]
    rng = np.random.default_rng(8)
    found = trials = 0
    for near in (0.57, 0.6, 0.63, 0.61):
        far = near + 7e-3
        reflectors = (
            PointReflector(np.array([0.0, 0.0, near]), 1.0),
            PointReflector(np.array([0.0, 0.0, far]), (far / near) ** 2),
        )
        scene = Scene(array=pair, objects=reflectors, n_samples=1500, transducer="electrostatic50", seed=None)
        recording = simulate(scene)
        single = simulate(
            Scene(array=pair, objects=reflectors[:1], n_samples=1500, transducer="electrostatic50")
        )
        sigma = peak_amplitude(single.frames[0, 0]) / 13.0
        c = scene.speed_of_sound_m_s
        ranges = [
            (np.linalg.norm(r.position_m - tx) + np.linalg.norm(r.position_m - rx)) / 2 for r in reflectors
        ]
        estimate = ESTIMATORS["matched"].prepare(recording, EchoOptions())
        for _ in range(10):
            frame = recording.frames[0] + rng.normal(0.0, sigma, recording.frames[0].shape)
            echoes = estimate(frame)[0].tof_s * c / 2
            trials += 1
            found += int(
                len(echoes) >= 2 and all(np.min(np.abs(echoes - r)) <= 1e-3 for r in ranges)
                and len({int(np.argmin(np.abs(echoes - r))) for r in ranges}) == 2
            )  # fmt: skip
    assert found >= 0.95 * trials, f"{found} of {trials}"
