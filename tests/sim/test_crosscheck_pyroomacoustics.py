"""Cross-check of echoloc's simulator against an independent one: pyroomacoustics (pra).

Issue acceptance: for a plane wall and for a point-like path, echoloc's echo delays
agree with pra's within 0.01 sample and their amplitudes within 2 %.

What pra does (read from its source, version 0.10.1: ``room.py``
``Room.compute_rir``/``simulate``, ``simulation/ism.py`` ``compute_ism_rir``,
``libroom_src/rir_builder.cpp``, ``libroom_src/room.cpp``, ``libroom_src/wall.cpp``):

- Each image source contributes ``att / dist`` at time ``dist / c``: no ``1 / (4 pi)``
  (that factor only appears in its plotting helpers), and ``att`` is the product of
  ``sqrt(1 - energy_absorption)`` over the walls met, so a wall of absorption 0
  reflects with pressure coefficient 1 and one of absorption 1 not at all. That is
  echoloc's convention (a unit monopole at 1 m; ``R / |image - rx|`` for a plane), so
  amplitudes are compared as they are, with no scaling.
- The fractional delay is a Hann-windowed sinc of ``frac_delay_length`` (81) taps,
  read from a sinc table (``sinc_lut_granularity`` 20 points per sample, linear
  interpolation), computed in float32; ``frac_delay_length // 2`` = 40 samples are added
  to every arrival so that the filter stays causal. That fixed offset is subtracted.
- ``compute_rir`` runs a 10 Hz high-pass filter over every impulse response
  (``rir_hpf_enable``, on by default). It is switched off here, since it is no part
  of a propagation path.
- ``simulate`` convolves each source signal with the impulse response (fftconvolve);
  the signal here is the very pulse echoloc delays, ``Scene.returned_pulse()``
  (Barker-13 × 4 cycles of 50 kHz at 200 kHz, no transducer model).
- Positions go through float32 in pra's engine, so every coordinate below is a
  multiple of 1/1024 m (exact in float32); the path lengths themselves are irrational.

Comparisons (every case has a fractional delay named in its table; several near 0.5):

1. **Plane wall**: a pra ``ShoeBox`` whose walls all have energy absorption 1 except one
   with 0, ``max_order = 1``; the wall's echo is the output minus that of the same box
   with all six walls absorbing (which leaves the direct sound). echoloc: one
   :class:`Plane` covering the same wall, reflection 1, no direct path.
2. **Point-like path: the direct sound.** pra's ``AnechoicRoom`` (one free-field path,
   source to microphone) against echoloc's ``ring_down.direct_path`` (the frame with
   it minus the frame without). Both are the same physics, a unit monopole heard at
   distance d, amplitude 1/d, delay d/c: the one like-for-like single path.
3. **Point reflector**: pra has no scatterer, so an isotropic point reflector of
   strength s is built from two pra free-field paths: transmitter to a microphone at
   the reflector, whose signal, times s, is re-emitted by a source there towards the
   receiver (offset 2 × 40 samples). No echoloc formula goes into it; it must give
   echoloc's ``s / (r_tx r_rx)`` at ``(r_tx + r_rx) / c``.

Measurement: the delay D and amplitude a of ``a p(n - D)`` (p the pulse's band-limited
interpolant) that fit a signal best in least squares, i.e. the maximum of the
band-limited cross-correlation, found by Newton steps on its exact Fourier series. A
zero-phase error of either simulator's interpolator (pra's windowed sinc, echoloc's
table) changes the fitted amplitude, not the delay. On pulses delayed without it (the
first test) it is exact to 1e-12 sample for a Gaussian tone and to 2e-9 sample and
3e-9 in amplitude for the Barker pulse delayed by a direct sinc sum.

Measured worst cases, echoloc minus pra (pra 0.10.1; 5 walls, 5 direct paths, 4 point
reflectors; the asserted limits are 0.01 sample and 2 %):

- plane wall: delay 4.5e-4 sample, amplitude 0.22 %;
- direct path: delay 4.0e-4 sample, amplitude 0.14 %;
- point reflector: delay 7.4e-4 sample, amplitude 0.17 %.

The differences are pra's. Against the exact geometry, echoloc's delays are within
2.5e-6 sample and its amplitudes within 2.1e-5 (relative); pra's arrivals are
2.3e-4 to 4.6e-4 sample late per path (twice that for the two-path point echo),
because its float32 sinc table is built by adding 1/20 repeatedly (grid error up to
7e-4 sample), and its amplitudes 0.02 % to 0.22 % low (the Hann window stays on the
whole-sample grid while the sinc moves by the fractional delay). With pra's high-pass
filter left on, the delays move by less than 2e-5 sample.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pytest
import scipy.fft
from numpy.typing import NDArray

from echoloc.sim.reflectors import Plane, PointReflector
from echoloc.sim.scene import Array, RingDown, Scene
from echoloc.sim.simulation import simulate

pra = pytest.importorskip("pyroomacoustics")

from pra_support import _pra_without_highpass, pra_offset_samples  # noqa: E402, F401  (the fixture is autouse)

FloatArray = NDArray[np.float64]

FS = 200_000  # an int: pra's impulse-response builder takes an integer rate
DELAY_TOLERANCE_SAMPLES = 0.01
AMPLITUDE_TOLERANCE = 0.02
WALLS = ("west", "east", "south", "north", "floor", "ceiling")
WALL_AXIS = {"east": 0, "north": 1, "ceiling": 2}  # the far wall of each axis: x, y, z = L


# --------------------------------------------------------------------------- measurement


def fit_arrival(signal: FloatArray, pulse: FloatArray) -> tuple[float, float]:
    """Delay (samples) and amplitude of the least-squares fit ``a p(n - D)`` to ``signal``.

    ``p`` is the band-limited interpolant of ``pulse`` (``p(k) = pulse[k]``). With the
    cross-spectrum ``C_k = Y_k conj(P_k)`` on an FFT longer than both signals, the
    cross-correlation ``r(D) = (1/N) sum_k C_k exp(i w_k D)`` is a trigonometric
    polynomial: its maximum (started from the best whole lag) is found by Newton
    steps with exact derivatives, and ``a = r(D) / sum |p|²``. ``signal`` must hold one
    arrival, with positive amplitude.
    """
    y = np.asarray(signal, dtype=float)
    p = np.asarray(pulse, dtype=float)
    if not np.any(y):
        raise ValueError("the signal is silent: no arrival to fit")
    n_fft = scipy.fft.next_fast_len(len(y) + len(p) + 64, real=True)
    spectrum = scipy.fft.rfft(p, n_fft)
    cross = scipy.fft.rfft(y, n_fft) * np.conj(spectrum)
    weight = np.full(len(cross), 2.0)  # each rfft bin stands for +f and -f ...
    weight[0] = 1.0  # ... except DC ...
    if n_fft % 2 == 0:
        weight[-1] = 1.0  # ... and Nyquist
    omega = 2 * np.pi * np.arange(len(cross)) / n_fft
    lag = int(np.argmax(scipy.fft.irfft(cross, n_fft)))
    delay = float(lag if lag < len(y) else lag - n_fft)
    for _ in range(30):
        terms = weight * cross * np.exp(1j * omega * delay)
        slope = float(np.sum(np.real(1j * omega * terms)))
        curvature = float(np.sum(np.real(-(omega**2) * terms)))
        step = float(np.clip(-slope / curvature, -0.25, 0.25))
        delay += step
        if abs(step) < 1e-12:
            break
    correlation = float(np.sum(np.real(weight * cross * np.exp(1j * omega * delay))))
    energy = float(np.sum(weight * np.abs(spectrum) ** 2))
    return delay, correlation / energy


def tone(t_samples: FloatArray) -> FloatArray:
    """A Gaussian-windowed 50 kHz tone at 200 kHz (sigma 8 samples): band-limited to double precision."""
    u = np.asarray(t_samples, dtype=float) - 64.0
    return np.asarray(np.exp(-0.5 * (u / 8.0) ** 2) * np.sin(0.5 * np.pi * u))


def sinc_delayed(pulse: FloatArray, delay: float, n_samples: int) -> FloatArray:
    """``pulse`` delayed by ``delay`` samples by the band-limited interpolation formula, summed directly."""
    n = np.arange(n_samples, dtype=float)
    k = np.arange(len(pulse), dtype=float)
    return np.asarray(np.sinc(n[:, None] - delay - k[None, :]) @ pulse)


# --------------------------------------------------------------------------- simulators


def echoloc_scene(tx: FloatArray, rx: FloatArray, obj: Plane | PointReflector, **kw: object) -> Scene:
    """One transmitter, one receiver, one object; no noise, no transducer model, no absorption."""
    return Scene(
        array=Array(transmitters_m=np.array([tx]), receivers_m=np.array([rx])),
        objects=(obj,),
        snr_db=None,
        sample_rate_hz=float(FS),
        **kw,  # type: ignore[arg-type]
    )


def frame(scene: Scene) -> FloatArray:
    return np.asarray(simulate(scene).frames[0, 0], dtype=float)


def pra_signal(room: Any, source: FloatArray, mic: FloatArray, signal: FloatArray, c: float) -> FloatArray:
    """What pra's microphone at ``mic`` records from ``signal`` emitted at ``source`` in ``room``.

    ``Room.simulate`` convolves the signal with the impulse response from time 0.
    """
    room.set_sound_speed(c)
    room.add_source(np.asarray(source, dtype=float), signal=np.asarray(signal, dtype=float))
    room.add_microphone(np.asarray(mic, dtype=float))
    room.simulate()
    return np.asarray(room.mic_array.signals[0], dtype=float)


def free_field(source: FloatArray, mic: FloatArray, signal: FloatArray, c: float) -> FloatArray:
    """pra's one free-field path (AnechoicRoom: the direct sound only)."""
    return pra_signal(pra.AnechoicRoom(fs=FS), source, mic, signal, c)


def shoebox(
    size_m: FloatArray,
    reflecting: str | None,
    source: FloatArray,
    mic: FloatArray,
    signal: FloatArray,
    c: float,
) -> FloatArray:
    """pra's shoebox with every wall absorbing (energy absorption 1) except ``reflecting`` (0)."""
    materials = {name: pra.Material(0.0 if name == reflecting else 1.0) for name in WALLS}
    room = pra.ShoeBox(np.asarray(size_m, dtype=float), fs=FS, materials=materials, max_order=1)
    return pra_signal(room, source, mic, signal, c)


def assert_agree(echoloc_fit: tuple[float, float], pra_fit: tuple[float, float], pra_offset: int) -> None:
    delay, amplitude = echoloc_fit
    pra_delay, pra_amplitude = pra_fit
    assert abs(delay - (pra_delay - pra_offset)) < DELAY_TOLERANCE_SAMPLES, (delay, pra_delay - pra_offset)
    assert amplitude / pra_amplitude == pytest.approx(1.0, abs=AMPLITUDE_TOLERANCE), (
        f"echoloc {amplitude:.6g}, pra {pra_amplitude:.6g} (a ratio of 4 pi: a 1/(4 pi d) convention)"
    )


# --------------------------------------------------------------------------- cases


@dataclass(frozen=True)
class WallCase:
    """A shoebox (m) with transmitter and receiver inside; ``wall`` (at x, y or z = size) reflects."""

    size_m: tuple[float, float, float]
    tx_m: tuple[float, float, float]
    rx_m: tuple[float, float, float]
    wall: str

    def plane(self) -> Plane:
        """The reflecting wall as an echoloc plane: the whole face, normal into the box."""
        axis = WALL_AXIS[self.wall]
        size = np.array(self.size_m)
        centre = 0.5 * size
        centre[axis] = size[axis]
        normal = np.zeros(3)
        normal[axis] = -1.0
        width_axis = np.zeros(3)
        width_axis[(axis + 1) % 3] = 1.0
        height_axis = np.cross(normal, width_axis)
        return Plane(
            centre_m=centre,
            normal=normal,
            width_m=float(size[(axis + 1) % 3]),
            height_m=float(np.abs(height_axis) @ size),
            width_axis=width_axis,
            reflection=1.0,
        )


# Fractional parts of the wall path and of the direct path, in samples at 343.21 m/s
# (20 °C, dry), in the comments. Coordinates are multiples of 1/1024 m.
WALL_CASES = {
    "pair-0.24m-wall-0.65m": WallCase(  # wall .500, direct .500
        (2.0, 2.0, 0.7705078125), (1.0, 1.0, 0.125), (1.2421875, 0.982421875, 0.125), "ceiling"
    ),
    "pair-0.05m-wall-0.98m": WallCase(  # wall .502, direct .252
        (2.0, 2.0, 1.1083984375), (1.0, 1.0, 0.125), (1.0498046875, 0.9853515625, 0.125), "ceiling"
    ),
    "staggered-pair-wall-1.35m": WallCase(  # wall .097, direct .499
        (3.0, 3.0, 1.6025390625), (1.5, 1.5, 0.25), (1.880859375, 1.255859375, 0.125), "ceiling"
    ),
    "side-wall-1.24m": WallCase(  # wall .749, direct .902
        (1.3662109375, 2.0, 2.0), (0.125, 1.0, 1.0), (0.125, 1.2587890625, 1.1416015625), "east"
    ),
    "pair-0.51m-wall-1.48m": WallCase(  # wall .967, direct .019
        (4.0, 4.0, 1.6015625), (2.0, 2.0, 0.125), (2.505859375, 1.9794921875, 0.125), "ceiling"
    ),
}

# (transmitter, receiver, reflector): fractional parts of the whole path / of r_tx in the comments.
POINT_CASES = {
    "ball-0.58m": (
        (0.0, 0.0, 0.0),
        (0.25, 0.0, 0.0),
        (0.0029296875, -0.0185546875, 0.5771484375),
    ),  # .498/.497
    "ball-0.66m-off-axis": (  # .503 / .254
        (0.0, 0.0, 0.0),
        (-0.25, 0.0, 0.0),
        (-0.09765625, 0.1318359375, 0.638671875),
    ),
    "ball-1.2m-oblique": (  # .200 / .748
        (0.0, 0.0, 0.0),
        (0.0, 0.25, 0.0),
        (0.2861328125, -0.1962890625, 1.1943359375),
    ),
    "ball-2m": ((0.0625, 0.0, 0.0), (0.0, -0.0625, 0.0), (0.0, -0.0078125, 1.9853515625)),  # .852 / .498
}
POINT_STRENGTH_M = 0.03  # a rigid ball of radius 6 cm at high ka: a / 2


# --------------------------------------------------------------------------- tests


@pytest.mark.parametrize("fraction", [0.0, 0.1, 0.5, 0.73, 0.999])
def test_measurement_recovers_an_analytic_delay(fraction: float) -> None:
    """The estimator itself: far better than 0.01 sample on pulses delayed without it.

    A Gaussian tone evaluated at ``n - D`` (band-limited to double precision), and the
    cross-check's own Barker pulse delayed by the interpolation formula summed
    directly (no FFT); both far from the frame's ends.
    """
    delay = 700.0 + fraction
    n = np.arange(2048, dtype=float)
    measured, amplitude = fit_arrival(0.37 * tone(n - delay), tone(np.arange(128.0)))
    assert abs(measured - delay) < 1e-9
    assert amplitude == pytest.approx(0.37, rel=1e-9)

    pulse = echoloc_scene(np.zeros(3), np.zeros(3), PointReflector([0.0, 0.0, 1.0])).returned_pulse()
    measured, amplitude = fit_arrival(2.5 * sinc_delayed(pulse, delay, 2048), pulse)
    assert abs(measured - delay) < 1e-7
    assert amplitude == pytest.approx(2.5, rel=1e-7)


@pytest.mark.parametrize("case", WALL_CASES.values(), ids=WALL_CASES.keys())
def test_plane_wall_echo_agrees_with_pyroomacoustics(case: WallCase) -> None:
    """One reflecting wall: pra's first-order image against echoloc's Plane (image source)."""
    tx, rx = np.array(case.tx_m), np.array(case.rx_m)
    scene = echoloc_scene(tx, rx, case.plane(), n_samples=3072)
    pulse, c = scene.returned_pulse(), scene.speed_of_sound_m_s

    with_wall = shoebox(np.array(case.size_m), case.wall, tx, rx, pulse, c)
    without = shoebox(np.array(case.size_m), None, tx, rx, pulse, c)
    pra_fit = fit_arrival(with_wall - without, pulse)
    assert_agree(fit_arrival(frame(scene), pulse), pra_fit, pra_offset_samples())


@pytest.mark.parametrize("case", WALL_CASES.values(), ids=WALL_CASES.keys())
def test_direct_path_agrees_with_pyroomacoustics(case: WallCase) -> None:
    """One free-field path transmitter -> receiver: pra's direct sound against echoloc's direct path."""
    tx, rx = np.array(case.tx_m), np.array(case.rx_m)
    scene = echoloc_scene(tx, rx, case.plane(), n_samples=3072, ring_down=RingDown(direct_path=True))
    pulse, c = scene.returned_pulse(), scene.speed_of_sound_m_s

    direct = frame(scene) - frame(echoloc_scene(tx, rx, case.plane(), n_samples=3072))
    pra_fit = fit_arrival(free_field(tx, rx, pulse, c), pulse)
    assert_agree(fit_arrival(direct, pulse), pra_fit, pra_offset_samples())


@pytest.mark.parametrize("case", POINT_CASES.values(), ids=POINT_CASES.keys())
def test_point_reflector_agrees_with_two_pyroomacoustics_paths(
    case: tuple[tuple[float, ...], tuple[float, ...], tuple[float, ...]],
) -> None:
    """A point reflector is a receiver that re-emits what it hears, times its strength.

    pra: transmitter -> microphone at the reflector, then that signal times s from a
    source at the reflector -> receiver (two offsets of 40 samples). echoloc: its
    PointReflector echo ``s / (r_tx r_rx)`` at ``(r_tx + r_rx) / c``.
    """
    tx, rx, point = (np.array(v) for v in case)
    scene = echoloc_scene(tx, rx, PointReflector(point, strength_m=POINT_STRENGTH_M), n_samples=3072)
    pulse, c = scene.returned_pulse(), scene.speed_of_sound_m_s

    heard = free_field(tx, point, pulse, c)
    echo = free_field(point, rx, POINT_STRENGTH_M * heard, c)
    pra_fit = fit_arrival(echo, pulse)
    assert_agree(fit_arrival(frame(scene), pulse), pra_fit, 2 * pra_offset_samples())
