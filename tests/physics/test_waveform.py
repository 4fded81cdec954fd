"""Tests of echoloc.physics.waveform: Barker codes and the BPSK pulses built from them.

Sources: docs/METHOD.md ("Emitted code", report ch. 3.4): Barker sequences, N carrier cycles
per bit, bit -1 sends the inverted carrier; R. H. Barker (1953): aperiodic
autocorrelation sidelobes |r| <= 1 against a peak equal to the length.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from echoloc.errors import WaveformError
from echoloc.physics.waveform import (
    BARKER_CODES,
    aperiodic_autocorrelation,
    barker,
    barker_waveform,
    modulate,
)

ALL_BARKER = [(n, v) for n, variants in BARKER_CODES.items() for v in range(len(variants))]
REPORT_CODES = {
    2: "++",
    3: "++-",
    4: "++-+",
    5: "+++-+",
    7: "+++--+-",
    11: "+++---+--+-",
    13: "+++++--++-+-+",
}


def _autocorrelation(code: np.ndarray) -> np.ndarray:
    """r[k] = sum_n c[n] c[n + k] for k = -(N-1)..N-1, by explicit sums."""
    n = len(code)
    return np.array(
        [sum(code[i] * code[i + k] for i in range(max(0, -k), min(n, n - k))) for k in range(-n + 1, n)]
    )


@pytest.mark.parametrize(("length", "variant"), ALL_BARKER)
def test_barker_autocorrelation_peak_and_sidelobes(length: int, variant: int) -> None:
    """Barker property: peak N at lag 0 and every sidelobe |r_k| <= 1."""
    code = barker(length, variant).astype(int)
    assert len(code) == length
    assert set(code.tolist()) <= {-1, 1}
    r = _autocorrelation(code)
    assert r[length - 1] == length
    assert np.all(np.abs(np.delete(r, length - 1)) <= 1)
    assert np.array_equal(aperiodic_autocorrelation(code), r)


@pytest.mark.parametrize(("length", "text"), REPORT_CODES.items())
def test_default_variants_are_the_reports_sequences(length: int, text: str) -> None:
    """The default variant of each length is the sequence listed in the report (docs/METHOD.md)."""
    assert barker(length).tolist() == [1 if ch == "+" else -1 for ch in text]


def test_barker_lengths_are_exactly_the_known_ones() -> None:
    """Binary Barker codes exist only for lengths 2, 3, 4, 5, 7, 11, 13."""
    assert sorted(BARKER_CODES) == [2, 3, 4, 5, 7, 11, 13]


@pytest.mark.parametrize("length", [1, 6, 8, 9, 10, 12, 14])
def test_lengths_without_barker_code_raise_naming_valid_lengths(length: int) -> None:
    """No Barker code of these lengths; the message lists the valid ones."""
    with pytest.raises(WaveformError, match=r"2, 3, 4, 5, 7, 11, 13") as info:
        barker(length)
    assert str(length) in str(info.value)


@pytest.mark.parametrize(("length", "variant"), [(13, 1), (2, 2), (4, -1)])
def test_unknown_variant_raises(length: int, variant: int) -> None:
    """Only the listed variants exist."""
    with pytest.raises(WaveformError, match="variant"):
        barker(length, variant)


@settings(max_examples=60, deadline=None)
@given(
    code=st.lists(st.sampled_from([-1, 1]), min_size=1, max_size=13),
    carrier_hz=st.integers(min_value=20_000, max_value=90_000),
    ratio=st.floats(min_value=2.2, max_value=10.0),
    cycles_per_bit=st.integers(min_value=1, max_value=8),
)
def test_sine_samples_equal_bit_times_carrier(
    code: list[int], carrier_hz: int, ratio: float, cycles_per_bit: int
) -> None:
    """BPSK: sample n is sin(2 pi fc n / fs) times the bit in force at t = n / fs.

    Independent formula in exact integer arithmetic: bit index floor(n fc / (fs N)).
    Length is round(n_bits N fs / fc) samples.
    """
    fs = round(carrier_hz * ratio)
    w = modulate(code, carrier_hz=carrier_hz, cycles_per_bit=cycles_per_bit, sample_rate_hz=fs)
    n_expected = len(code) * cycles_per_bit * fs / carrier_hz
    assert abs(len(w.samples) - n_expected) <= 0.5
    n = np.arange(len(w.samples), dtype=np.int64)
    phase = (n * carrier_hz % fs) / fs  # cycles elapsed, reduced mod 1 exactly
    bit = np.minimum(n * carrier_hz // (fs * cycles_per_bit), len(code) - 1)
    expected = np.sin(2 * np.pi * phase) * np.asarray(code)[bit]
    assert np.allclose(w.samples, expected, rtol=0.0, atol=1e-8)


@pytest.mark.parametrize(("fs", "fc", "n_cycles"), [(200e3, 50e3, 4), (1e6, 40e3, 2), (500e3, 25e3, 8)])
def test_length_is_bits_times_cycles_times_samples_per_cycle(fs: float, fc: float, n_cycles: int) -> None:
    """Whole samples per cycle: exactly n_bits N fs / fc samples; chip_s = N / fc."""
    w = barker_waveform(13, carrier_hz=fc, cycles_per_bit=n_cycles, sample_rate_hz=fs)
    assert len(w.samples) == round(13 * n_cycles * fs / fc)
    assert 13 * n_cycles * fs / fc == pytest.approx(len(w.samples), abs=1e-9)
    assert w.chip_s == pytest.approx(n_cycles / fc, rel=1e-15)
    assert w.duration_s == pytest.approx(13 * n_cycles / fc, rel=1e-12)


def test_report_pulse_is_1_04_ms_of_208_samples() -> None:
    """Barker-13 × 4 cycles at 50 kHz: 52 cycles = 1.04 ms = 208 samples at 200 kHz."""
    w = barker_waveform()
    assert len(w.samples) == 208
    assert w.chip_s == pytest.approx(80e-6)
    assert w.carrier_hz == 50e3
    assert w.sample_rate_hz == 200e3
    assert np.max(np.abs(w.samples)) == pytest.approx(1.0)


def test_minus_bit_inverts_the_carrier() -> None:
    """Code [+1, -1]: the second half is minus the continuation of the pure carrier (180° jump)."""
    fs, fc, n_cycles = 1e6, 50e3, 3
    w = modulate([1, -1], carrier_hz=fc, cycles_per_bit=n_cycles, sample_rate_hz=fs).samples
    pure = modulate([1, 1], carrier_hz=fc, cycles_per_bit=n_cycles, sample_rate_hz=fs).samples
    half = len(w) // 2
    assert half == round(n_cycles * fs / fc)
    t = np.arange(len(w)) / fs
    assert np.allclose(pure, np.sin(2 * np.pi * fc * t), atol=1e-8)
    assert np.allclose(w[:half], pure[:half], atol=0)
    assert np.allclose(w[half:], -pure[half:], atol=1e-12)
    assert np.allclose(w[half:], -np.sin(2 * np.pi * fc * t[half:]), atol=1e-8)


@pytest.mark.parametrize(("fs", "fc"), [(200e3, 50e3), (1e6, 50e3), (1.2e6, 40e3)])
def test_square_carrier_takes_plus_minus_one_with_the_carrier_period(fs: float, fc: float) -> None:
    """Square carrier: values ±1, +1 in the first half cycle and -1 in the second, period fs / fc."""
    w = modulate([1, 1, 1], carrier_hz=fc, cycles_per_bit=2, sample_rate_hz=fs, carrier="square").samples
    assert set(np.unique(w).tolist()) == {-1.0, 1.0}
    period = round(fs / fc)
    assert np.array_equal(w[period:], w[:-period])
    assert np.array_equal(w[: period // 2], np.ones(period // 2))
    assert np.array_equal(w[period // 2 : period], -np.ones(period - period // 2))
    assert np.mean(w) == pytest.approx(0.0, abs=1e-12)


def test_square_carrier_inverts_with_the_bit() -> None:
    """Bit -1 sends the inverted square carrier."""
    kw = {"carrier_hz": 50e3, "cycles_per_bit": 4, "sample_rate_hz": 400e3, "carrier": "square"}
    plus = modulate([1, 1], **kw).samples
    mixed = modulate([1, -1], **kw).samples
    half = len(plus) // 2
    assert np.array_equal(mixed[:half], plus[:half])
    assert np.array_equal(mixed[half:], -plus[half:])


@pytest.mark.parametrize(("fc", "fs"), [(100e3, 200e3), (150e3, 200e3), (50e3, 100e3)])
def test_carrier_at_or_above_nyquist_raises(fc: float, fs: float) -> None:
    """Sampling theorem: the carrier must lie below fs / 2."""
    with pytest.raises(WaveformError, match="Nyquist"):
        modulate([1, -1, 1], carrier_hz=fc, cycles_per_bit=1, sample_rate_hz=fs)


def test_carrier_just_below_nyquist_is_accepted() -> None:
    """Just below fs / 2 is allowed."""
    w = modulate([1], carrier_hz=99e3, cycles_per_bit=1, sample_rate_hz=200e3)
    assert len(w.samples) == round(200e3 / 99e3)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"code": [1, 0, -1]},
        {"code": []},
        {"code": [[1, -1], [1, 1]]},
        {"cycles_per_bit": 0},
        {"cycles_per_bit": 2.5},
        {"carrier_hz": 0.0},
        {"sample_rate_hz": -200e3},
        {"carrier": "triangle"},
    ],
)
def test_invalid_modulate_arguments_raise(kwargs: dict[str, object]) -> None:
    """A code is a non-empty ±1 sequence; cycles a positive integer; rates positive."""
    args: dict[str, object] = {
        "code": [1, -1],
        "carrier_hz": 50e3,
        "cycles_per_bit": 4,
        "sample_rate_hz": 200e3,
        "carrier": "sine",
    }
    args.update(kwargs)
    with pytest.raises(WaveformError):
        modulate(**args)  # type: ignore[arg-type]


def test_spectrum_of_report_pulse_peaks_at_the_carrier() -> None:
    """Barker-13: |sum c_n e^{-j w n T}|² = 13 + 2 sum_{k even} cos(w k T) is largest at w = 0,
    so the sine-carrier pulse (4 samples per cycle) peaks at the carrier, 50 kHz."""
    w = barker_waveform(13, carrier_hz=50e3, cycles_per_bit=4, sample_rate_hz=200e3)
    n_fft = 1 << 16
    spectrum = np.abs(np.fft.rfft(w.samples, n_fft))
    freqs = np.fft.rfftfreq(n_fft, 1 / w.sample_rate_hz)
    assert abs(freqs[np.argmax(spectrum)] - 50e3) <= freqs[1]
    # Peak height: 8 odd samples per bit × |sum of the code| = 8 × 5 (sin splits between ±fc).
    assert spectrum.max() == pytest.approx(5 * 16 / 2, rel=1e-3)


def test_sine_pulse_energy_is_half_per_sample() -> None:
    """A full-cycle sine of unit amplitude has mean square 1/2 (bit signs do not change it)."""
    w = barker_waveform(13)
    assert np.mean(w.samples**2) == pytest.approx(0.5, rel=1e-12)
