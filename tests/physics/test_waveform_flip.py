"""The ``flip{N}`` pulse: two trains of N carrier cycles, the second inverted (report ch. 3.3).

Source: docs/METHOD.md, "Time of flight": envelope-zero detection with two pulse trains;
the envelope of the carrier passes through zero at the phase reversal.
"""

from __future__ import annotations

import numpy as np
import pytest

from echoloc.errors import WaveformError
from echoloc.physics.waveform import WAVEFORM_NAMES, code_by_name, modulate, waveform_by_name
from echoloc.sim.receiver import analytic_signal


@pytest.mark.parametrize("cycles", [1, 4, 8, 16])
def test_flip_is_n_cycles_then_n_inverted_cycles(cycles: int) -> None:
    """flip{N}: sin(2 pi f t) for N cycles, then -sin(2 pi f t) for N more, 2 N / f long."""
    fs, fc = 200e3, 50e3
    w = waveform_by_name(f"flip{cycles}", carrier_hz=fc, sample_rate_hz=fs)
    n = round(2 * cycles * fs / fc)
    t = np.arange(n) / fs
    expected = np.where(t < cycles / fc - 0.5 / fs, 1.0, -1.0) * np.sin(2 * np.pi * np.round(t * fc, 9))
    assert w.name == f"flip{cycles}"
    assert len(w.samples) == n
    np.testing.assert_allclose(w.samples, expected, atol=1e-12)
    assert w.chip_s == pytest.approx(cycles / fc)
    same = modulate([1, -1], carrier_hz=fc, cycles_per_bit=cycles, sample_rate_hz=fs)
    np.testing.assert_array_equal(w.samples, same.samples)


def test_flip_envelope_has_its_zero_at_the_phase_reversal() -> None:
    """The analytic envelope of flip8 vanishes at the reversal, 8 / f_c after emission, only there."""
    fs, fc = 200e3, 50e3
    w = waveform_by_name("flip8", carrier_hz=fc, sample_rate_hz=fs)
    envelope = np.abs(analytic_signal(np.concatenate([np.zeros(64), w.samples, np.zeros(64)])))[64:-64]
    inside = envelope[4:-4]
    assert int(np.argmin(inside)) + 4 == round(8 / fc * fs)
    assert inside.min() < 1e-3 * envelope.max()
    assert np.sort(inside)[1] > 0.5 * envelope.max()


def test_existing_names_still_work_and_flip_is_listed() -> None:
    assert "flip{cycles}" in WAVEFORM_NAMES
    assert waveform_by_name("barker13").name == "barker13"
    assert waveform_by_name("tone16").name == "tone16"
    assert waveform_by_name(" FLIP4 ").name == "flip4"


def test_flip_is_not_a_code_name_and_zero_cycles_are_refused() -> None:
    with pytest.raises(WaveformError, match="not a binary code"):
        code_by_name("flip8")
    with pytest.raises(WaveformError, match="cycles_per_bit"):
        waveform_by_name("flip0")
