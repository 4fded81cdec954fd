"""Weak wall echoes beside a strong direct path: detection follows the noise, not the strongest echo.

A pyroomacoustics (pra) shoebox, built as the cross-check does
(``tests/test_crosscheck_pyroomacoustics.py``: no high-pass filter, pra's 40-sample offset
subtracted): a transmitter and a receiver 0.25 m apart inside it, the transmitter's direct
path to the receiver in the frame, and the six first-order wall echoes. Each component is
pra's own: the direct path is the box with every wall absorbing, a wall's echo the box
with that wall reflecting minus it. pra keeps a wall's reflection in float32
(``sqrt(1 - absorption)``), which cannot go below about 2e-4, so the echoes are scaled after
the fact, by linearity: wall ``w``'s echo times ``g_w`` is the echo of a wall of pressure
reflection ``g_w``, chosen to put its peak a set number of dB below the direct path's.

The rf frame is the direct path, the scaled echoes and white noise at 80 dB per-sample SNR
for the direct path (echoloc's convention, :mod:`echoloc.sim.scene`: its peak amplitude over the
noise's standard deviation). The matched filter gains ``10 log10(E / 2)`` = 17.2 dB on top
(E = 104, the Barker pulse's energy; the analytic correlation's noise power is 2 sigma^2 / E
per unit amplitude), so the direct path's output SNR is 97 dB, an echo 80 dB below it 17 dB,
above the 14 dB threshold, and one 100 dB below it -3 dB: below the noise.

Every wall echo whose pulse lies wholly in the frame and whose output SNR is at least 3 dB
above the threshold must be found; an echo below the noise must not be; nothing else may be
reported (the direct path aside).

The noise power is the median of the correlation's power (:func:`echoloc.tof.echoes.noise_power`),
which counts the lags that strong echoes' sidelobes occupy: with the 97 dB direct path and
echoes 40 and 60 dB below it, a third of the frame's lags, it comes out 2.9 dB high. Hence the
3 dB margin above the threshold, and no echo at 80 dB below beside stronger ones.

Delay tolerance: six times the Cramér-Rao bound on the delay at the echo's SNR
(:func:`echoloc.physics.crlb.coherent_tof_bound`; 0.06 sample at 17 dB, so 0.37 sample), plus 0.01
sample for the two simulators' interpolators (the cross-check's tolerance; they differ by
5e-4 sample). Half a carrier cycle is 2 samples: an echo read on the wrong half-cycle fails.
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from echoloc.io.recording import Recording
from echoloc.physics.crlb import coherent_tof_bound
from echoloc.physics.waveform import barker_waveform
from echoloc.tof.echoes import ChannelEchoes, EchoOptions, MatchedFilter, _Clean
from echoloc.tof.estimators import ESTIMATORS

pra = pytest.importorskip("pyroomacoustics")

from pra_support import _pra_without_highpass, pra_offset_samples  # noqa: E402, F401  (the fixture is autouse)

FloatArray = NDArray[np.float64]

FS = 200_000  # an int: pra's impulse-response builder takes an integer rate
C = 343.21  # m/s
N_SAMPLES = 4096  # 20.5 ms: 7.03 m of path, which leaves the north wall's echo (7.40 m) out
PULSE = barker_waveform(13, carrier_hz=50e3, cycles_per_bit=4, sample_rate_hz=FS).samples
DIRECT_SNR_DB = 80.0
CRLB_FACTOR = 6.0
MODEL_TOLERANCE_SAMPLES = 0.01

WALLS = ("west", "east", "south", "north", "floor", "ceiling")
# A box in which the six first-order paths (1.65, 6.55, 3.21, 7.40, 2.41, 4.01 m) lie more than
# a template's length (1.04 ms, 0.36 m) from the direct path (0.25 m) and from each other.
SIZE_M = (4.1, 5.3, 3.2)
TX_M = (0.7, 1.6, 1.2)
RX_M = (0.95, 1.6, 1.2)


def shoebox(reflecting: str | None) -> FloatArray:
    """What pra's receiver records of the pulse in the box, every wall absorbing but ``reflecting``."""
    materials = {name: pra.Material(0.0 if name == reflecting else 1.0) for name in WALLS}
    room = pra.ShoeBox(np.array(SIZE_M), fs=FS, materials=materials, max_order=1)
    room.set_sound_speed(C)
    room.add_source(np.array(TX_M), signal=PULSE)
    room.add_microphone(np.array(RX_M))
    room.simulate()
    return np.asarray(room.mic_array.signals[0], dtype=float)


def path_m(wall: str | None) -> float:
    """The path transmitter -> (wall's image) -> receiver, m; None: the direct path."""
    source = np.array(TX_M)
    if wall is not None:
        axis = {"west": 0, "east": 0, "south": 1, "north": 1, "floor": 2, "ceiling": 2}[wall]
        plane = 0.0 if wall in ("west", "south", "floor") else SIZE_M[axis]
        source[axis] = 2 * plane - source[axis]
    return float(np.linalg.norm(source - np.array(RX_M)))


def delay_samples(wall: str | None) -> float:
    """Where the matched filter must put the arrival: the path's delay plus pra's offset."""
    return path_m(wall) / C * FS + pra_offset_samples()


def noise_sigma() -> float:
    """The noise's standard deviation: 80 dB below the direct path's peak amplitude."""
    return 10 ** (-DIRECT_SNR_DB / 20) / path_m(None)


def output_snr_db(amplitude: float) -> float:
    """The matched filter's output SNR of an echo ``amplitude * PULSE`` in that noise."""
    energy = float(np.sum(PULSE**2))
    return float(10 * np.log10(amplitude**2 * energy / (2 * noise_sigma() ** 2)))


def tolerance_samples(amplitude: float) -> float:
    bound = coherent_tof_bound(PULSE, FS, amplitude=amplitude, noise_sigma=noise_sigma()).std_s
    return CRLB_FACTOR * bound * FS + MODEL_TOLERANCE_SAMPLES


def in_frame(wall: str) -> bool:
    """Whether the wall's echo lies wholly in the frame."""
    return delay_samples(wall) + len(PULSE) < N_SAMPLES


def room_frame(levels_db: dict[str, float], seed: int = 0) -> tuple[FloatArray, dict[str, float]]:
    """The rf frame (n_samples,): pra's direct path, each wall's echo ``levels_db[wall]`` below
    its peak, noise; and each echo's amplitude (the pulse's scale)."""
    direct = shoebox(None)
    frame = direct.copy()
    amplitudes = {}
    for wall, level in levels_db.items():
        # pra's echo has amplitude 1 / path: scaled to the direct path's 1 / d times 10^(-level/20).
        gain = 10 ** (-level / 20) * path_m(wall) / path_m(None)
        echo = shoebox(wall) - direct
        frame[: len(echo)] += gain * echo
        amplitudes[wall] = gain / path_m(wall)
    frame = np.pad(frame, (0, max(N_SAMPLES - len(frame), 0)))[:N_SAMPLES]
    frame += np.random.default_rng(seed).normal(0.0, noise_sigma(), N_SAMPLES)
    return frame, amplitudes


def matched_echoes(frame: FloatArray, options: EchoOptions | None = None) -> ChannelEchoes:
    """The registered matched estimator's echoes of a one-receiver frame."""
    recording = Recording(
        float(FS), np.array([TX_M]), np.array([RX_M]), frame[None, None, :], PULSE, carrier_hz=50e3
    )
    estimator = ESTIMATORS["matched"].prepare(recording, options or EchoOptions())
    return estimator(frame[None, :])[0]


LEVEL_CASES = {
    "40dB": dict.fromkeys(WALLS, 40.0),
    "60dB": dict.fromkeys(WALLS, 60.0),
    "80dB": dict.fromkeys(WALLS, 80.0),
    # Echoes of different strengths together; the weakest 70 dB down, not 80: beside the 40 and
    # 60 dB ones, the median noise power is 2.9 dB high (module doc), which takes an echo 80 dB down
    # (17 dB output SNR) to the threshold.
    "mixed-one-below-noise": {
        "west": 70.0,
        "east": 60.0,
        "south": 100.0,  # -3 dB output SNR: below the noise
        "north": 40.0,  # out of the frame
        "floor": 40.0,
        "ceiling": 70.0,
    },
}


@pytest.mark.parametrize("levels", LEVEL_CASES.values(), ids=LEVEL_CASES.keys())
def test_wall_echoes_far_below_the_direct_path_are_found(levels: dict[str, float]) -> None:
    """Every in-frame first-order wall echo above the noise is found, however far below the
    direct path (40, 60, 80 dB); one below the noise is not reported; nothing else is."""
    threshold_db = EchoOptions().threshold_db
    frame, amplitudes = room_frame(levels)
    channel = matched_echoes(frame)
    found = channel.tof_s * FS

    expected: dict[str | None, float] = {None: delay_samples(None)}
    tolerance: dict[str | None, float] = {None: tolerance_samples(1 / path_m(None))}
    absent: list[str] = []
    for wall, amplitude in amplitudes.items():
        if not in_frame(wall):
            continue
        snr = output_snr_db(amplitude)
        if snr >= threshold_db + 3.0:
            expected[wall], tolerance[wall] = delay_samples(wall), tolerance_samples(amplitude)
        else:
            assert snr <= 0.0, (
                f"{wall}: {snr:.1f} dB, neither clearly above the threshold nor below the noise"
            )
            absent.append(wall)
    assert len(expected) > 1
    assert not all(in_frame(w) for w in WALLS)  # the frame's end is exercised

    for wall, delay in expected.items():
        error = np.min(np.abs(found - delay)) if len(found) else np.inf
        assert error <= tolerance[wall], (
            f"{wall or 'direct'} echo at {delay:.3f}: nearest {error:.3f} samples"
        )
    for wall in absent:
        assert not np.any(np.abs(found - delay_samples(wall)) < len(PULSE) / 2), f"{wall}: below the noise"
    # Nothing but the direct path and the expected echoes.
    matched = [min(abs(t - d) for d in expected.values()) <= max(tolerance.values()) for t in found]
    assert all(matched), f"false echoes at {found[~np.array(matched)]} samples"
    assert len(found) == len(expected)


def test_direct_path_residue_stays_within_the_dynamic_range() -> None:
    """The direct path's own residue is not an echo: pra's windowed-sinc delay leaves 0.2 % of
    it (-54 dB, 43 dB above the noise here) after the subtraction of echoloc's template,
    within a template's length of it, where the dynamic range drops it. With no wall
    reflecting, the direct path is all that is reported."""
    frame, _ = room_frame({})
    channel = matched_echoes(frame)
    assert channel.tof_s * FS == pytest.approx([delay_samples(None)], abs=tolerance_samples(1 / path_m(None)))


def test_a_weak_echo_inside_the_direct_path_s_support_is_held_to_it() -> None:
    """The dynamic range is local, not gone: an echo within a template's length after the
    direct path and more than 40 dB below it is dropped, with the residue it cannot be told
    from; the same echo a template's length later is found."""
    direct = shoebox(None)
    for offset, kept in ((60.0, False), (len(PULSE) + 40.0, True)):
        frame = np.pad(direct, (0, max(N_SAMPLES - len(direct), 0)))[:N_SAMPLES]
        shift = delay_samples(None) + offset
        echo = 10 ** (-50 / 20) / path_m(None)
        n = np.arange(N_SAMPLES, dtype=float)
        k = np.arange(len(PULSE), dtype=float)
        frame = frame + echo * (np.sinc(n[:, None] - shift - k[None, :]) @ PULSE)
        frame += np.random.default_rng(1).normal(0.0, noise_sigma(), N_SAMPLES)
        found = matched_echoes(frame).tof_s * FS
        near = np.abs(found - shift) < 1.0
        assert bool(np.any(near)) == kept, (offset, found)


@pytest.mark.parametrize("levels", [LEVEL_CASES["80dB"], LEVEL_CASES["mixed-one-below-noise"]])
def test_compiled_clean_masks_as_its_python_statement(levels: dict[str, float]) -> None:
    """CLEAN's compiled extraction and its Python statement leave the same samples to the search
    (the dynamic range's masks around the direct path): the same echoes, to rounding."""
    frame, _ = room_frame(levels)
    mf = MatchedFilter(PULSE, N_SAMPLES, float(FS), decimation=2)
    correlation = mf.correlate(frame)
    a, power_a = _Clean(mf, EchoOptions()).run(correlation)
    b, power_b = _Clean(mf, EchoOptions(), compiled=False).run(correlation)
    assert power_a == pytest.approx(power_b, rel=1e-12)
    assert len(a) == len(b) >= 4
    assert [c.tof_samples for c in a] == pytest.approx([c.tof_samples for c in b], abs=1e-8)
    assert [c.amplitude for c in a] == pytest.approx([c.amplitude for c in b], rel=1e-8)
