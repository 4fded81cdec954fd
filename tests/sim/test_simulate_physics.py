"""End-to-end physics of :func:`echoloc.sim.simulation.simulate`: closed forms, symmetries and round trips.

Every echo delay here is measured, not read back from the simulator: the peak of the
cross-correlation of the frame with the scene's returned pulse, band-limited
interpolated 64 times by FFT zero padding and refined by a parabola through the three
highest points (the autocorrelation of any pulse is symmetric about its peak, so the
peak lies at the echo's delay; ~1e-5 sample for a clean echo).

Sources: reciprocity of linear acoustics (exchanging source and receiver leaves the
transfer unchanged); spherical spreading ``s / (r1 r2)`` and Parseval (the energy of
a band-limited signal does not depend on its delay); the image-source method (Allen
and Berkley 1979); the Doppler factor ``alpha = (c - dr_rx/dt) / (c + dr_tx/dt)`` of the
module docstring of :mod:`echoloc.sim.simulation` (Kinsler et al., sec. 11.9); Bennett
(1948) for the quantisation error ``q²/12``; Oppenheim and Schafer §2.10 for white
noise through a filter (power gain ``Σ h²``); the noise convention of
:mod:`echoloc.sim.scene`; the complex-baseband convention of :mod:`echoloc.sim.receiver`.
"""

from __future__ import annotations

import tracemalloc
import warnings
from pathlib import Path

import numpy as np
import pytest
import scipy.fft
import scipy.signal
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from echoloc.io.recording import read_recording, write_recording
from echoloc.physics.air import speed_of_sound_m_s
from echoloc.sim.receiver import AdcSpec, GainSpec, gain_curve, resample
from echoloc.sim.reflectors import Plane, PointReflector, Reflector, Sphere
from echoloc.sim.scene import AirDrift, Array, PulseSpec, ReceiverSpec, RingDown, Scene, SensorMotion
from echoloc.sim.scenefile import load_scene
from echoloc.sim.simulation import simulate, simulate_to_file
from echoloc.sim.synthesis import synthesize_frames
from repo_paths import REPO

FloatArray = NDArray[np.float64]

FS = 200e3
FC = 50e3
C20 = float(speed_of_sound_m_s(20.0, 0.0))
SCENES = REPO / "src" / "echoloc" / "scenes"


# --- helpers -------------------------------------------------------------------------


def pair_scene(tx: list[float], rx: list[float], **kw: object) -> Scene:
    """One transmitter and one receiver, noiseless unless told otherwise."""
    return Scene(
        array=Array(transmitters_m=np.array([tx], dtype=float), receivers_m=np.array([rx], dtype=float)),
        **kw,  # type: ignore[arg-type]
    )


def xcorr_delays_s(
    frames: FloatArray,
    template: FloatArray,
    sample_rate_hz: float = FS,
    *,
    oversample: int = 64,
    gate_s: tuple[float, float] | None = None,
) -> FloatArray:
    """Delay of ``template`` in each frame (..., n): peak of the band-limited cross-correlation.

    The cross-spectrum is zero-padded ``oversample`` times (band-limited interpolation of
    the correlation), the highest point within ``gate_s`` (lags in s) is found and a
    parabola through it and its neighbours gives the sub-grid peak.
    """
    x = np.atleast_2d(np.asarray(frames, dtype=float))
    n_frame = x.shape[-1]
    n_fft = scipy.fft.next_fast_len(n_frame + len(template) + 1, real=True)
    n_fft += n_fft % 2
    cross = scipy.fft.rfft(x, n_fft, axis=-1) * np.conj(scipy.fft.rfft(template, n_fft))
    cross[..., -1] *= 0.5  # the Nyquist bin is shared by +fs/2 and -fs/2
    fine = scipy.fft.irfft(cross, n_fft * oversample, axis=-1)
    lags = np.arange(n_fft * oversample) / oversample
    lags = np.where(lags > n_frame, lags - n_fft, lags)
    allowed = np.ones(lags.shape, dtype=bool)
    if gate_s is not None:
        allowed = (lags >= gate_s[0] * sample_rate_hz) & (lags <= gate_s[1] * sample_rate_hz)
    candidates = np.flatnonzero(allowed)
    best = candidates[np.argmax(fine[:, candidates], axis=-1)]
    rows = np.arange(len(best))
    m = fine.shape[-1]
    y0, y1, y2 = fine[rows, (best - 1) % m], fine[rows, best], fine[rows, (best + 1) % m]
    offset = 0.5 * (y0 - y2) / (y0 - 2.0 * y1 + y2)
    return np.asarray((lags[best] + offset / oversample) / sample_rate_hz).reshape(x.shape[:-1])


def delayed(
    template: FloatArray, delay_s: float, n_samples: int, *, time_scale: float | None = None
) -> FloatArray:
    """``template`` delayed by ``delay_s`` (band-limited, optionally time-scaled), unit amplitude."""
    scale = None if time_scale is None else np.array([[[time_scale]]])
    frames = synthesize_frames(
        np.asarray(template, dtype=float),
        np.array([[[delay_s]]]),
        np.ones((1, 1, 1)),
        sample_rate_hz=FS,
        n_samples=n_samples,
        time_scale=scale,
    )
    return np.asarray(frames[0, 0])


def ls_amplitude(frame: FloatArray, template: FloatArray) -> float:
    """Least-squares amplitude a minimising |frame - a template|²."""
    return float(np.dot(frame, template) / np.dot(template, template))


def compressed_delay_s(frame: FloatArray, pulse: FloatArray, alpha: float) -> float:
    """Arrival tau of an echo ``a p(alpha (t - tau))``: cross-correlation with the pulse compressed by alpha.

    The compressed template starts 40 samples late so that its leading band-limited
    ringing is kept; that lead is added back.
    """
    lead_s = 40 / FS
    template = delayed(pulse, lead_s, int(len(pulse) / alpha) + 120, time_scale=alpha)
    return float(xcorr_delays_s(frame, template)[0]) + lead_s


def envelope(x: FloatArray) -> FloatArray:
    """|analytic signal| along the last axis, zero-padded so the FFT's wrap-round stays out."""
    n = x.shape[-1]
    return np.asarray(np.abs(scipy.signal.hilbert(x, N=scipy.fft.next_fast_len(4 * n), axis=-1)[..., :n]))


def mirrored(point: FloatArray, centre: FloatArray, normal: FloatArray) -> FloatArray:
    """``point`` mirrored in the plane through ``centre`` with unit ``normal`` (image source)."""
    return np.asarray(point - 2.0 * np.dot(point - centre, normal) * normal)


def unit(v: list[float]) -> FloatArray:
    a = np.asarray(v, dtype=float)
    return np.asarray(a / np.linalg.norm(a))


# --- (1) reciprocity -----------------------------------------------------------------

T_POS = [0.02, 0.01, 0.0]
R_POS = [-0.05, 0.03, 0.01]
WALL = Plane([0.35, 0.0, 0.8], [-1.0, 0.0, 0.1], 1.0, 1.0, width_axis=[0.0, 0.0, 1.0], reflection=0.9)
RECIPROCITY_SCENES: dict[str, tuple[tuple[Reflector, ...], int]] = {
    "point": ((PointReflector([0.1, -0.05, 0.6], 1.0),), 1),
    "sphere": ((Sphere([0.05, 0.02, 0.7], 0.05),), 1),
    "plane": ((Plane([0.05, 0.0, 0.8], [0.2, 0.1, -1.0], 0.6, 0.5),), 1),
    "plane+point order 2": ((WALL, PointReflector([0.1, 0.05, 0.6], 0.8)), 2),
    "two points order 2": (
        (PointReflector([0.1, 0.05, 0.6], 0.8), PointReflector([-0.1, 0.05, 0.7], 0.5)),
        2,
    ),
}


@pytest.mark.parametrize("transducer", [None, "electrostatic50"])
@pytest.mark.parametrize("name", list(RECIPROCITY_SCENES))
def test_swapping_transmitter_and_receiver_leaves_frame_unchanged(name: str, transducer: str | None) -> None:
    """Reciprocity: T -> reflectors -> R records what R -> reflectors -> T does, every path included.

    With the transducer model both face +z, so their beams swap with their positions;
    absorption is symmetric in the path. Second-order scenes must hold the double
    reflections both ways round (plane > point from T is point > plane from R).
    """
    objects, order = RECIPROCITY_SCENES[name]
    kw = {"objects": objects, "max_order": order, "transducer": transducer, "n_samples": 1200}
    if transducer is not None:
        kw |= {"absorption": True, "relative_humidity": 0.5}
    forward = simulate(pair_scene(T_POS, R_POS, **kw)).frames
    backward = simulate(pair_scene(R_POS, T_POS, **kw)).frames
    peak = np.max(np.abs(forward))
    assert peak > 1e-3
    assert np.max(np.abs(forward - backward)) <= 1e-12 * peak
    if order == 2:
        first = simulate(pair_scene(T_POS, R_POS, **(kw | {"max_order": 1}))).frames
        assert np.max(np.abs(forward - first)) > 1e-2 * peak  # the double reflections are really there


# --- (2) spherical spreading -----------------------------------------------------------


@pytest.mark.parametrize(
    ("r1", "r2", "angle"),
    [(0.3, 0.3, 0.4), (0.5, 1.2, 0.9), (1.0, 0.4, 0.3), (0.8, 0.8, 1.2), (1.5, 0.6, 0.2)],
)
def test_point_echo_energy_is_inverse_square_of_r1_r2(r1: float, r2: float, angle: float) -> None:
    """E_echo = (s / (r1 r2))² E_pulse: spreading both ways; the fractional delay keeps energy (Parseval)."""
    strength = 0.7
    point = np.array([0.0, 0.0, r1])
    direction = unit([np.sin(angle), 0.3 * np.sin(angle), -np.cos(angle)])
    receiver = point + r2 * direction
    scene = pair_scene(
        [0.0, 0.0, 0.0],
        receiver.tolist(),
        reflector_positions_m=[point],
        reflector_strengths=[strength],
        n_samples=1600,
    )
    frame = simulate(scene).frames[0, 0]
    pulse_energy = float(np.sum(scene.waveform().samples ** 2))
    energy = float(np.sum(frame**2))
    assert energy * (r1 * r2 / strength) ** 2 == pytest.approx(pulse_energy, rel=1e-3)


# --- (3) finite plane: image source ----------------------------------------------------


def specular_point(t: FloatArray, r: FloatArray, centre: FloatArray, normal: FloatArray) -> FloatArray:
    """Where the line from the transmitter's image to the receiver crosses the plane."""
    image = mirrored(t, centre, normal)
    d_image, d_r = np.dot(image - centre, normal), np.dot(r - centre, normal)
    return np.asarray(image + (r - image) * d_image / (d_image - d_r))


@settings(max_examples=12, deadline=None)
@given(
    tilt=st.tuples(st.floats(-0.4, 0.4), st.floats(-0.4, 0.4)),
    tx=st.tuples(st.floats(-0.15, 0.15), st.floats(-0.15, 0.15)),
    rx=st.tuples(st.floats(-0.15, 0.15), st.floats(-0.15, 0.15)),
    depth=st.floats(0.4, 1.2),
    reflection=st.floats(-1.0, 1.0).filter(lambda r: abs(r) > 0.05),
)
def test_tilted_plane_echo_arrives_at_image_source_distance(
    tilt: tuple[float, float],
    tx: tuple[float, float],
    rx: tuple[float, float],
    depth: float,
    reflection: float,
) -> None:
    """Bistatic pair, tilted finite plane: one echo R / L at L / c, L = |receiver - image of transmitter|."""
    t = np.array([tx[0], tx[1], 0.0])
    r = np.array([rx[0], rx[1], 0.02])
    normal = unit([tilt[0], tilt[1], -1.0])
    spot = specular_point(t, r, np.array([0.0, 0.0, depth]), normal)
    # The plane through the same surface, centred near the specular point, so that it lies on it.
    probe = Plane(spot, normal, 0.3, 0.2, width_axis=[1.0, 0.2, 0.0])
    centre = spot + 0.05 * probe.width_axis - 0.03 * probe.height_axis
    plane = Plane(centre, normal, 0.3, 0.2, width_axis=[1.0, 0.2, 0.0], reflection=reflection)
    scene = pair_scene(t.tolist(), r.tolist(), objects=(plane,), n_samples=1600)
    frame = simulate(scene).frames[0, 0]
    length = float(np.linalg.norm(r - mirrored(t, centre, normal)))
    c = scene.speed_of_sound_m_s
    measured = xcorr_delays_s(frame * np.sign(reflection), scene.waveform().samples)[0]
    assert (measured - length / c) * FS == pytest.approx(0.0, abs=0.01)
    expected = delayed(scene.waveform().samples, length / c, scene.n_samples) * (reflection / length)
    assert np.max(np.abs(frame - expected)) <= 1e-9 * abs(reflection / length)


@pytest.mark.parametrize("axis", ["width", "height"])
@pytest.mark.parametrize("side", [1.0, -1.0])
@pytest.mark.parametrize(("fraction", "echo"), [(0.98, True), (1.02, False)])
def test_plane_echo_exists_only_while_specular_point_is_on_it(
    axis: str, side: float, fraction: float, echo: bool
) -> None:
    """Moving the rectangle within its plane so that the specular point sits at 0.98 / 1.02 of its
    half-size from the centre: a full echo R / L inside, silence outside (no edge diffraction)."""
    t, r = np.array([-0.1, 0.02, 0.0]), np.array([0.15, -0.03, 0.02])
    normal = unit([0.25, -0.15, -1.0])
    spot = specular_point(t, r, np.array([0.05, 0.02, 0.8]), normal)
    probe = Plane(spot, normal, 0.3, 0.2, width_axis=[1.0, 0.2, 0.0])
    direction, half = (probe.width_axis, 0.15) if axis == "width" else (probe.height_axis, 0.10)
    centre = spot - side * fraction * half * direction
    plane = Plane(centre, normal, 0.3, 0.2, width_axis=[1.0, 0.2, 0.0], reflection=0.8)
    frame = simulate(pair_scene(t.tolist(), r.tolist(), objects=(plane,), n_samples=1200)).frames[0, 0]
    length = float(np.linalg.norm(r - mirrored(t, centre, normal)))
    if echo:
        template = delayed(probe_pulse(), length / C20, 1200)
        assert ls_amplitude(frame, template) == pytest.approx(0.8 / length, rel=1e-9)
    else:
        assert np.max(np.abs(frame)) == 0.0


def probe_pulse() -> FloatArray:
    """The default scene's emitted pulse (Barker-13, 4 cycles per chip at 50 kHz, 200 kHz)."""
    return np.asarray(
        pair_scene([0, 0, 0], [0, 0, 0], reflector_positions_m=[[0, 0, 1]], reflector_strengths=[1.0])
        .waveform()
        .samples
    )


# --- (4) Doppler ---------------------------------------------------------------------

DOPPLER_T = np.zeros(3)
DOPPLER_R = np.array([0.01, 0.0, 0.0])
DOPPLER_P0 = np.array([0.0, 0.0, 0.5])


def doppler_scene(speed: float, code: str) -> Scene:
    """A point 0.5 m ahead moving along the boresight at ``speed`` (> 0: receding); receiver 1 cm aside."""
    mover = PointReflector(DOPPLER_P0, 1.0, [0.0, 0.0, speed])
    return pair_scene(
        DOPPLER_T.tolist(), DOPPLER_R.tolist(), objects=(mover,), n_samples=1200, pulse=PulseSpec(code=code)
    )


def doppler_alpha(speed: float, c: float) -> float:
    """(c - dr_rx/dt) / (c + dr_tx/dt) at the frame start."""
    towards_rx = (DOPPLER_P0 - DOPPLER_R) / np.linalg.norm(DOPPLER_P0 - DOPPLER_R)
    return float((c - speed * towards_rx[2]) / (c + speed))


@pytest.mark.parametrize("speed", [-20.0, -5.0, 5.0, 20.0])
def test_doppler_compresses_the_carrier_by_alpha(speed: float) -> None:
    """A tone burst from a reflector moving at v returns at alpha f_c (phase slope of the analytic signal).

    1 - alpha (0.029 at 5 m/s, 0.11 at 20 m/s; negative when approaching) within 10 %.
    """
    scene = doppler_scene(speed, "tone40")
    frame = simulate(scene).frames[0, 0]
    n = len(frame)
    analytic = scipy.signal.hilbert(frame, N=scipy.fft.next_fast_len(4 * n))[:n]
    strong = np.flatnonzero(np.abs(analytic) > 0.5 * np.max(np.abs(analytic)))
    assert np.all(np.diff(strong) == 1)  # one echo, one contiguous stretch
    phase = np.unwrap(np.angle(analytic[strong]))
    frequency = np.polyfit(strong / FS, phase, 1)[0] / (2 * np.pi)
    alpha = doppler_alpha(speed, scene.speed_of_sound_m_s)
    assert 1.0 - frequency / FC == pytest.approx(1.0 - alpha, rel=0.1)


@pytest.mark.parametrize("speed", [-20.0, -5.0, 5.0, 20.0])
def test_doppler_echo_arrives_at_path_at_instant_of_reflection(speed: float) -> None:
    """The echo starts at path(t_r) / c, t_r the exact instant the pulse meets the moving reflector.

    t_r solves ``c t = |P0 + v t - T|`` (constant velocity, still air). Measured by
    cross-correlation with the pulse compressed by alpha; within 0.05 sample.
    """
    scene = doppler_scene(speed, "barker13")
    c = scene.speed_of_sound_m_s
    frame = simulate(scene).frames[0, 0]
    arrival = compressed_delay_s(frame, scene.waveform().samples, doppler_alpha(speed, c))
    velocity = np.array([0.0, 0.0, speed])
    reflection_time = 0.0
    for _ in range(50):  # fixed point of t = |P0 + v t - T| / c, a contraction for |v| < c
        reflection_time = float(np.linalg.norm(DOPPLER_P0 + velocity * reflection_time - DOPPLER_T) / c)
    at_reflection = DOPPLER_P0 + np.array([0.0, 0.0, speed]) * reflection_time
    path = np.linalg.norm(at_reflection - DOPPLER_T) + np.linalg.norm(at_reflection - DOPPLER_R)
    assert (arrival - path / c) * FS == pytest.approx(0.0, abs=0.05)
    still = np.linalg.norm(DOPPLER_P0 - DOPPLER_T) + np.linalg.norm(DOPPLER_P0 - DOPPLER_R)
    assert abs(path - still) / c * FS > 0.5  # the correction is measurable, not lost in the tolerance


# --- (5) moving sensor -----------------------------------------------------------------


def moving_objects(velocity: FloatArray) -> tuple[Reflector, ...]:
    return (
        PointReflector([0.1, 0.05, 0.6], 1.0, velocity),
        Sphere([-0.1, 0.0, 0.9], 0.04, velocity),
        Plane([0.0, 0.1, 1.2], [0.1, -0.1, -1.0], 0.8, 0.6, velocity_m_s=velocity),
    )


def test_moving_sensor_records_what_a_world_moving_the_other_way_does() -> None:
    """Only relative motion counts (still air, no wind): the sensor at +v records the world at -v.

    Same frames (Doppler included), same truth in the sensor frame; the poses are
    ``[v t, 0, 0, 0, 1]`` with unit quaternions.
    """
    v = np.array([0.3, -0.2, 0.5])
    kw = {"n_samples": 1200, "frame_rate_hz": 20.0}
    sensor = simulate(
        pair_scene(
            [0, 0, 0],
            [0.1, 0.02, 0],
            objects=moving_objects(np.zeros(3)),
            motion=SensorMotion(velocity_m_s=v),
            **kw,
        ),
        n_frames=5,
    )
    world = simulate(pair_scene([0, 0, 0], [0.1, 0.02, 0], objects=moving_objects(-v), **kw), n_frames=5)
    peak = np.max(np.abs(world.frames))
    assert peak > 0
    assert np.max(np.abs(sensor.frames - world.frames)) <= 1e-12 * peak
    assert sensor.truth_positions_m is not None
    assert world.truth_positions_m is not None
    assert np.allclose(sensor.truth_positions_m, world.truth_positions_m, rtol=0, atol=1e-12, equal_nan=True)
    times = np.arange(5) / 20.0
    assert sensor.frame_times_s is not None
    assert np.allclose(sensor.frame_times_s, times, rtol=0, atol=1e-15)
    # The frames do change with the motion (else the comparison would be empty).
    assert np.max(np.abs(sensor.frames[-1] - sensor.frames[0])) > 0.1 * peak
    poses = sensor.sensor_poses
    assert poses is not None
    assert poses.shape == (5, 7)
    assert np.allclose(poses[:, :3], v * times[:, None], rtol=0, atol=1e-15)
    assert np.allclose(poses[:, 3:], [0.0, 0.0, 0.0, 1.0], rtol=0, atol=1e-15)
    assert world.sensor_poses is None


def test_rotating_sensor_sees_world_points_at_r_transpose_p_minus_x() -> None:
    """Poses ``[v t, q(omega t)]`` with unit q; a world point is seen at ``R(t)^T (p - v t)`` (truth)."""
    v = np.array([0.1, 0.0, 0.2])
    omega_deg = np.array([0.0, 30.0, 10.0])
    p = np.array([0.1, -0.05, 0.8])
    scene = pair_scene(
        [0, 0, 0],
        [0.05, 0, 0],
        reflector_positions_m=[p],
        reflector_strengths=[1.0],
        n_samples=1200,
        frame_rate_hz=4.0,
        motion=SensorMotion(velocity_m_s=v, angular_velocity_deg_s=omega_deg),
    )
    rec = simulate(scene, n_frames=6)
    times = np.arange(6) / 4.0
    poses, truth = rec.sensor_poses, rec.truth_positions_m
    assert poses is not None
    assert truth is not None
    assert np.allclose(np.linalg.norm(poses[:, 3:], axis=1), 1.0, rtol=0, atol=1e-12)
    assert np.allclose(poses[:, :3], v * times[:, None], rtol=0, atol=1e-15)
    rotation = Rotation.from_quat(poses[:, 3:])
    expected = Rotation.from_rotvec(np.radians(omega_deg) * times[:, None])
    assert np.allclose((expected.inv() * rotation).magnitude(), 0.0, rtol=0, atol=1e-12)
    assert rotation[-1].magnitude() > 0.1  # the head really turns (13 degrees by the last frame)
    assert np.allclose(truth[:, 0], rotation.inv().apply(p - poses[:, :3]), rtol=0, atol=1e-12)
    # Each echo comes from that point as the sensor sees it at the instant of reflection,
    # compressed by the Doppler factor of its legs' rates at the frame start.
    receiver = scene.array.receivers_m[0]
    c = scene.speed_of_sound_m_s

    def seen_at(when: FloatArray) -> FloatArray:
        turn = Rotation.from_rotvec(np.radians(omega_deg) * when[:, None]).inv()
        return np.asarray(turn.apply(p - v * when[:, None]))

    def legs(when: FloatArray) -> tuple[FloatArray, FloatArray]:
        point = seen_at(when)
        return np.linalg.norm(point, axis=1), np.linalg.norm(point - receiver, axis=1)

    r_tx, _r_rx = legs(times)
    dt = 1e-6
    (tx_late, rx_late), (tx_early, rx_early) = legs(times + dt), legs(times - dt)
    alpha = (c - (rx_late - rx_early) / (2 * dt)) / (c + (tx_late - tx_early) / (2 * dt))
    at_tx, at_rx = legs(times + r_tx / c)
    for k in range(6):
        arrival = compressed_delay_s(rec.frames[k, 0], scene.waveform().samples, float(alpha[k]))
        assert (arrival - (at_tx[k] + at_rx[k]) / c) * FS == pytest.approx(0.0, abs=0.05)


# --- (6) and (7) ADC --------------------------------------------------------------------


def decimator_noise_gain(adc_rate_hz: float) -> float:
    """Power gain of the chain's decimator for white noise, ``Σ h²`` (O&S §2.10).

    Measured on :func:`echoloc.sim.receiver.resample` itself: the output power of a unit
    impulse summed over the ``ratio`` input phases is ``Σ h²`` of the polyphase filter.
    """
    ratio = round(adc_rate_hz / FS)
    n = 60 * ratio
    return float(
        sum(np.sum(resample(np.eye(1, n, n // 2 + j)[0], adc_rate_hz, FS) ** 2) for j in range(ratio))
    )


@pytest.mark.parametrize("adc_rate_hz", [None, 1e6])
def test_quantisation_error_power_is_q2_over_12_through_the_chain(adc_rate_hz: float | None) -> None:
    """Quantised minus unquantised (same seed, no clipping): power ``q²/12`` at the ADC [Bennett 1948],
    times the decimator's white-noise power gain ``Σ h²`` (≈ 1/5) when the ADC runs at 1 MHz."""
    adc = AdcSpec(bits=10, full_scale=1.0)
    kw = {
        "reflector_positions_m": [[0, 0, 0.3]],
        "reflector_strengths": [0.03],
        "n_samples": 2400,
        "snr_db": 26.0,
    }
    quantised = simulate(
        pair_scene([0, 0, 0], [0.02, 0, 0], receiver=ReceiverSpec(adc_rate_hz=adc_rate_hz, adc=adc), **kw),
        n_frames=8,
    ).frames
    ideal = simulate(
        pair_scene([0, 0, 0], [0.02, 0, 0], receiver=ReceiverSpec(adc_rate_hz=adc_rate_hz), **kw), n_frames=8
    ).frames
    assert np.max(np.abs(ideal)) < 0.8  # nothing clips: the error is quantisation alone
    assert np.std(ideal) > 20 * adc.step  # busy: the noise spans many steps
    gain = 1.0 if adc_rate_hz is None else decimator_noise_gain(adc_rate_hz)
    assert np.mean((quantised - ideal) ** 2) == pytest.approx(adc.step**2 / 12 * gain, rel=0.05)


@pytest.mark.parametrize("bits", [None, 8, 12])
def test_adc_clips_at_full_scale_with_twos_complement_top_code(bits: int | None) -> None:
    """Echo peak 11.3 against full scale 5: the frame tops out at full_scale - q (two's complement;
    full_scale without quantisation) and bottoms at -full_scale; elsewhere within q/2 of the ideal."""
    kw = {"reflector_positions_m": [[0, 0, 0.3]], "reflector_strengths": [1.0], "n_samples": 1200}
    adc = AdcSpec(bits=bits, full_scale=5.0)
    clipped = simulate(pair_scene([0, 0, 0], [0.02, 0, 0], receiver=ReceiverSpec(adc=adc), **kw)).frames[0, 0]
    ideal = simulate(pair_scene([0, 0, 0], [0.02, 0, 0], **kw)).frames[0, 0]
    assert np.max(ideal) > 2 * adc.full_scale
    assert np.min(ideal) < -2 * adc.full_scale
    q = adc.step
    top, bottom = adc.full_scale - q, -adc.full_scale
    assert np.max(clipped) == top
    assert np.min(clipped) == bottom
    assert np.array_equal(clipped == top, ideal >= top - q / 2)
    assert np.array_equal(clipped == bottom, ideal <= bottom + (q / 2 if bits else 0.0))
    inside = (ideal < top - q / 2) & (ideal > bottom + q / 2)
    assert np.max(np.abs(clipped[inside] - ideal[inside])) <= q / 2 * (1 + 1e-12)
    if bits is not None:
        codes = clipped / q
        assert np.array_equal(codes, np.rint(codes))
        assert codes.min() >= -(2 ** (bits - 1))
        assert codes.max() <= 2 ** (bits - 1) - 1


# --- (8) noise convention -----------------------------------------------------------------


def noise_scene(noise: str, transducer: str | None, adc_rate_hz: float | None, snr_db: float) -> Scene:
    """Noise only: the one reflector's echo arrives after the frame ends."""
    return pair_scene(
        [0, 0, 0],
        [0.02, 0, 0],
        reflector_positions_m=[[0, 0, 5.0]],
        reflector_strengths=[1.0],
        n_samples=2400,
        snr_db=snr_db,
        transducer=transducer,
        receiver=ReceiverSpec(adc_rate_hz=adc_rate_hz, noise=noise),
    )


@pytest.mark.parametrize(
    ("noise", "transducer", "adc_rate_hz"),
    [
        ("white", None, 1e6),
        ("white", "electrostatic50", None),
        ("band", "electrostatic50", None),
        ("band", "electrostatic50", 1e6),
        ("band", "electrostatic50", 5e6),
    ],
)
@pytest.mark.parametrize("snr_db", [10.0, 30.0])
def test_recorded_noise_std_is_ten_to_minus_snr_over_20(
    noise: str, transducer: str | None, adc_rate_hz: float | None, snr_db: float
) -> None:
    """scene.py: sigma of the recorded rf samples at sample_rate_hz, after decimation, is 10^(-snr/20)."""
    frames = simulate(noise_scene(noise, transducer, adc_rate_hz, snr_db), n_frames=16).frames
    assert np.std(frames) == pytest.approx(10 ** (-snr_db / 20), rel=0.03)


def test_decimated_white_noise_std_is_exact() -> None:
    """As above with 64 frames (std of the estimate 0.2 %): the convention holds to 0.5 %."""
    frames = simulate(noise_scene("white", None, 1e6, 20.0), n_frames=64).frames
    assert np.std(frames) == pytest.approx(0.1, rel=0.005)


# --- (9) decimation ---------------------------------------------------------------------------


@pytest.mark.parametrize("transducer", [None, "electrostatic50"])
@pytest.mark.parametrize("code", ["barker13", "tone16"])
@pytest.mark.parametrize("depth", [0.4, 0.61234])
def test_adc_at_1_mhz_decimated_matches_direct_sampling(
    transducer: str | None, code: str, depth: float
) -> None:
    """Sampling at 1 MHz then decimating to 200 kHz records the echo of direct 200 kHz sampling:
    arrival within 0.02 sample (and at path / c), amplitude within 1 %."""
    p = np.array([0.02, 0.01, depth])
    kw = {
        "reflector_positions_m": [p],
        "reflector_strengths": [1.0],
        "n_samples": 1200,
        "transducer": transducer,
        "pulse": PulseSpec(code=code),
    }
    fast = pair_scene([0, 0, 0], [0.03, 0, 0], receiver=ReceiverSpec(adc_rate_hz=1e6), **kw)
    direct = pair_scene([0, 0, 0], [0.03, 0, 0], **kw)
    frame_fast, frame_direct = simulate(fast).frames[0, 0], simulate(direct).frames[0, 0]
    template = direct.returned_pulse()
    d_fast, d_direct = xcorr_delays_s(np.stack([frame_fast, frame_direct]), template)
    assert (d_fast - d_direct) * FS == pytest.approx(0.0, abs=0.02)
    path = np.linalg.norm(p) + np.linalg.norm(p - [0.03, 0, 0])
    assert (d_direct - path / direct.speed_of_sound_m_s) * FS == pytest.approx(0.0, abs=0.02)
    a_fast = ls_amplitude(frame_fast, delayed(template, d_fast, 1200))
    a_direct = ls_amplitude(frame_direct, delayed(template, d_direct, 1200))
    assert a_fast == pytest.approx(a_direct, rel=0.01)


# --- (10) signal kinds -------------------------------------------------------------------------


def two_echo_scene(receiver: ReceiverSpec, transducer: str | None = None) -> Scene:
    """The pair 3 cm apart with two reflectors (0.4 m and 0.7 m deep), noiseless, 1200 samples."""
    return pair_scene(
        [0, 0, 0],
        [0.03, 0, 0],
        reflector_positions_m=[[0.02, 0.01, 0.4], [-0.1, 0.05, 0.7]],
        reflector_strengths=[1.0, 0.6],
        n_samples=1200,
        transducer=transducer,
        receiver=receiver,
    )


def kinds_scene(kind: str, transducer: str | None, output_rate_hz: float | None = None) -> Scene:
    return two_echo_scene(ReceiverSpec(signal_kind=kind, output_rate_hz=output_rate_hz), transducer)


@pytest.mark.parametrize("transducer", [None, "electrostatic50"])
def test_iq_envelope_and_rf_recordings_agree(transducer: str | None) -> None:
    """|iq| = envelope and Re(iq exp(2j pi f_c t)) = rf (receiver.py baseband convention), also at 20 kHz."""
    rf = simulate(kinds_scene("rf", transducer))
    iq = simulate(kinds_scene("iq", transducer))
    env = simulate(kinds_scene("envelope", transducer))
    assert iq.frames.dtype == np.complex128
    assert env.signal_kind == "envelope"
    assert iq.signal_kind == "iq"
    peak = np.max(np.abs(rf.frames))
    assert np.max(np.abs(np.abs(iq.frames) - env.frames)) <= 1e-12 * peak
    t = np.arange(rf.n_samples) / FS
    back = (iq.frames * np.exp(2j * np.pi * FC * t)).real
    assert np.max(np.abs(back - rf.frames)[..., 20:-20]) <= 0.01 * peak
    assert np.min(env.frames) >= 0.0
    slow_iq = simulate(kinds_scene("iq", transducer, 20e3))
    slow_env = simulate(kinds_scene("envelope", transducer, 20e3))
    assert slow_env.sample_rate_hz == 20e3
    assert slow_env.frames.shape == (1, 1, 120)
    assert np.max(np.abs(np.abs(slow_iq.frames) - slow_env.frames)) <= 1e-12 * peak
    # The templates follow the same conventions.
    assert iq.waveform is not None
    assert env.waveform is not None
    assert np.max(np.abs(np.abs(iq.waveform) - env.waveform[: len(iq.waveform)])) <= 1e-12


def test_envelope_template_peaks_where_the_rf_template_envelope_does() -> None:
    """The envelope recording's waveform is >= 0 and peaks where |analytic(rf waveform)| peaks, as high.

    With the transducer model the returned pulse's envelope has one clear maximum.
    """
    rf = simulate(kinds_scene("rf", "electrostatic50"))
    env = simulate(kinds_scene("envelope", "electrostatic50"))
    assert rf.waveform is not None
    assert env.waveform is not None
    assert np.min(env.waveform) >= 0.0
    reference = envelope(np.concatenate([rf.waveform, np.zeros(400)]))
    assert abs(int(np.argmax(env.waveform)) - int(np.argmax(reference))) <= 1
    assert np.max(env.waveform) == pytest.approx(np.max(reference), rel=0.01)


# --- (11) time-varying gain ----------------------------------------------------------------------

GAINS = {
    "constant": GainSpec(gain_db=20.0),
    "continuous": GainSpec(kind="continuous", gain_db=6.0, slope_db_per_ms=4.0, max_gain_db=40.0),
    "stepped": GainSpec(kind="stepped", step_db=6.0, step_s=1e-3, max_gain_db=30.0),
}


def gained(gain: GainSpec | None, adc_rate_hz: float | None, kind: str) -> Scene:
    spec = GainSpec() if gain is None else gain
    return two_echo_scene(ReceiverSpec(adc_rate_hz=adc_rate_hz, gain=spec, signal_kind=kind))


@pytest.mark.parametrize(
    ("name", "adc_rate_hz", "kind", "tolerance"),
    [
        ("constant", None, "rf", 1e-12),
        ("continuous", None, "rf", 1e-12),
        ("stepped", None, "rf", 1e-12),
        ("constant", 1e6, "envelope", 1e-12),
        ("continuous", 1e6, "rf", 1e-3),
        ("continuous", None, "envelope", 1e-3),
        ("stepped", 1e6, "rf", 1e-3),
        ("stepped", None, "envelope", 1e-2),
    ],
)
def test_receiver_gain_is_the_gain_curve_and_divides_out(
    name: str, adc_rate_hz: float | None, kind: str, tolerance: float
) -> None:
    """recording.receiver_gain = gain_curve(spec, n, output rate); frames / receiver_gain = the ungained run
    (Recording: "frames / receiver_gain is the signal at the transducer")."""
    with_gain = simulate(gained(GAINS[name], adc_rate_hz, kind))
    without = simulate(gained(None, adc_rate_hz, kind))
    assert without.receiver_gain is None
    assert with_gain.receiver_gain is not None
    expected_gain = gain_curve(GAINS[name], with_gain.n_samples, with_gain.sample_rate_hz)
    assert np.array_equal(with_gain.receiver_gain, expected_gain)
    assert np.ptp(np.log(with_gain.receiver_gain)) > 0 or name == "constant"
    peak = np.max(np.abs(without.frames))
    error = np.abs(with_gain.frames / with_gain.receiver_gain - without.frames)
    if name == "stepped" and (adc_rate_hz is not None or kind != "rf"):
        # The amplifier steps before the decimator and the envelope detector, whose filters
        # smear each step over a few samples (Recording.receiver_gain says so): away from
        # the steps the gain divides out.
        steps = np.flatnonzero(np.diff(with_gain.receiver_gain)) + 1
        near = np.min(np.abs(np.arange(with_gain.n_samples)[:, None] - steps[None, :]), axis=1) < 40
        error = error[..., ~near]
    assert np.max(error) <= tolerance * peak


# --- (12) air ----------------------------------------------------------------------------------

AIR_P = np.array([0.05, 0.02, 0.5])
AIR_R = np.array([0.03, 0.0, 0.0])
AIR_PATH = float(np.linalg.norm(AIR_P) + np.linalg.norm(AIR_P - AIR_R))


def air_scene(**kw: object) -> Scene:
    """The pair with one reflector at AIR_P, the receiver at AIR_R, 800 samples; the air as told."""
    return pair_scene(
        [0, 0, 0],
        AIR_R.tolist(),
        reflector_positions_m=[AIR_P],
        reflector_strengths=[1.0],
        n_samples=800,
        **kw,
    )


def test_drifting_air_delays_follow_speed_of_sound_at_frame_time() -> None:
    """Frame k at t = k / frame_rate: delay = path / c(T0 + dT t, RH0 + dRH t) within 0.05 sample."""
    drift = AirDrift(temperature_c_per_s=20.0, relative_humidity_per_s=0.1)
    scene = air_scene(
        frame_rate_hz=10.0,
        temperature_c=15.0,
        relative_humidity=0.3,
        drift=drift,
    )
    rec = simulate(scene, n_frames=6)
    assert rec.frame_times_s is not None
    t = rec.frame_times_s
    c = speed_of_sound_m_s(15.0 + 20.0 * t, 0.3 + 0.1 * t)
    measured = xcorr_delays_s(rec.frames[:, 0], scene.waveform().samples)
    assert np.allclose(measured * FS, AIR_PATH / c * FS, rtol=0, atol=0.05)
    assert (AIR_PATH / c[0] - AIR_PATH / c[-1]) * FS > 5  # the drift moves the echo by many samples


def test_turbulence_spreads_delays_by_its_relative_std() -> None:
    """c (1 + 1e-3 N(0, 1)) per frame: delays path / c spread by 1e-3 relative (400 frames: ±3.5 %)."""
    scene = air_scene(
        drift=AirDrift(turbulence=1e-3),
        seed=3,
    )
    frames = simulate(scene, n_frames=400).frames[:, 0]
    measured = xcorr_delays_s(frames, scene.waveform().samples, oversample=16)
    assert np.std(measured) / np.mean(measured) == pytest.approx(1e-3, rel=0.15)
    assert np.mean(measured) == pytest.approx(AIR_PATH / scene.speed_of_sound_m_s, rel=3e-4)


# --- (13) ring-down -----------------------------------------------------------------------------


@pytest.mark.parametrize("transducer", [None, "electrostatic50"])
@pytest.mark.parametrize("adc_rate_hz", [None, 1e6])
def test_ring_down_level_decay_and_superposition(transducer: str | None, adc_rate_hz: float | None) -> None:
    """Envelope peak = level (within 1 %); envelope decays as exp(-t / decay_s) after the drive
    (fit within 10 %); ring-down and a later echo superpose: the echo is untouched."""
    level, decay = 20.0, 0.3e-3
    far = {"reflector_positions_m": [[0, 0, 5.0]], "reflector_strengths": [1.0]}  # beyond the frame
    near = {"reflector_positions_m": [[0, 0, 0.9]], "reflector_strengths": [1.0]}
    common = {"n_samples": 1400, "transducer": transducer, "receiver": ReceiverSpec(adc_rate_hz=adc_rate_hz)}
    ring = RingDown(level=level, decay_s=decay)
    both = simulate(pair_scene([0, 0, 0], [0.03, 0, 0], ring_down=ring, **near, **common)).frames[0, 0]
    echo = simulate(pair_scene([0, 0, 0], [0.03, 0, 0], **near, **common)).frames[0, 0]
    alone_scene = pair_scene([0, 0, 0], [0.03, 0, 0], ring_down=ring, **far, **common)
    alone = simulate(alone_scene).frames[0, 0]
    assert np.max(np.abs(both - (echo + alone))) <= 1e-12 * level
    ringing = envelope(alone)
    assert np.max(ringing) == pytest.approx(level, rel=0.01)
    drive_end = len(alone_scene.waveform().samples)
    k = np.arange(drive_end + 20, drive_end + 220)  # 0.1 ms to 1.1 ms after the drive stops
    slope = np.polyfit(k / FS, np.log(ringing[k]), 1)[0]
    assert -1.0 / slope == pytest.approx(decay, rel=0.1)
    arrival = int((0.9 + np.hypot(0.9, 0.03)) / C20 * FS) - 40
    # By the echo (5 ms later, 17 decay times) the ringing is below 1e-4 of it: the echo is untouched.
    assert np.max(np.abs(echo[arrival:])) > 1e4 * np.max(np.abs(alone[arrival:]))
    assert np.max(np.abs(both[arrival:] - echo[arrival:])) <= 1e-4 * np.max(np.abs(echo))


def test_direct_path_is_the_pulse_over_distance_at_distance_over_c() -> None:
    """ring_down.direct_path: the wave straight from transmitter to receiver, 1 / d at d / c."""
    kw = {"reflector_positions_m": [[0, 0, 5.0]], "reflector_strengths": [1.0], "n_samples": 600}
    receiver = [0.25, 0.1, 0.0]
    d = float(np.linalg.norm(receiver))
    frame = simulate(pair_scene([0, 0, 0], receiver, ring_down=RingDown(direct_path=True), **kw)).frames[0, 0]
    expected = delayed(probe_pulse(), d / C20, 600) / d
    assert np.max(np.abs(frame - expected)) <= 1e-9 / d
    assert xcorr_delays_s(frame, probe_pulse())[0] * FS == pytest.approx(d / C20 * FS, abs=0.01)


# --- (14) several transmitters -----------------------------------------------------------------------

TWO_TX = np.array([[-0.1, 0.0, 0.0], [0.1, 0.0, 0.0]])
TWO_RX = np.array([[0.0, 0.05, 0.0], [0.0, -0.05, 0.0]])
TWO_P = np.array([[0.05, 0.02, 0.5], [-0.2, 0.1, 0.8]])


def test_sequential_firing_alternates_transmitters_and_their_paths() -> None:
    """Frame k fires transmitter k mod 2; its first echo arrives at (|p - T_k| + |p - R|) / c."""
    scene = Scene(
        array=Array(TWO_TX, TWO_RX),
        reflector_positions_m=TWO_P,
        reflector_strengths=[1.0, 0.7],
        n_samples=1400,
    )
    rec = simulate(scene, n_frames=4)
    assert rec.frame_transmitter is not None
    assert rec.frame_transmitter.tolist() == [0, 1, 0, 1]
    assert rec.transmitter_waveforms is None  # one code for both
    c = scene.speed_of_sound_m_s
    for k in range(4):
        tx = TWO_TX[rec.frame_transmitter[k]]
        for r in range(2):
            path = np.linalg.norm(TWO_P[0] - tx) + np.linalg.norm(TWO_P[0] - TWO_RX[r])
            gate = (path / c - 30 / FS, path / c + 30 / FS)
            measured = xcorr_delays_s(rec.frames[k, r], scene.waveform().samples, gate_s=gate)[0]
            assert (measured - path / c) * FS == pytest.approx(0.0, abs=0.01)
    assert np.max(np.abs(rec.frames[0] - rec.frames[1])) > 0.1 * np.max(np.abs(rec.frames))
    assert np.array_equal(rec.frames[0], rec.frames[2])


@pytest.mark.parametrize("codes", [("barker13", "barker11"), ("golay16a", "golay16b")])
@pytest.mark.parametrize("kind", ["rf", "iq"])
@pytest.mark.parametrize("transducer", [None, "electrostatic50"])
def test_simultaneous_firing_is_the_sum_of_single_transmitters(
    codes: tuple[str, str], kind: str, transducer: str | None
) -> None:
    """Linearity: both transmitters at once record the sum of each alone; transmitter_waveforms[i]
    is transmitter i's template (zero-padded), waveform is transmitter 0's."""
    kw = {
        "reflector_positions_m": TWO_P,
        "reflector_strengths": [1.0, 0.7],
        "n_samples": 1400,
        "transducer": transducer,
        "receiver": ReceiverSpec(signal_kind=kind),
    }
    both = simulate(
        Scene(array=Array(TWO_TX, TWO_RX), firing="simultaneous", transmitter_codes=codes, **kw), 2
    )
    singles = [
        simulate(Scene(array=Array(TWO_TX[i : i + 1], TWO_RX), pulse=PulseSpec(code=codes[i]), **kw), 2)
        for i in range(2)
    ]
    total = singles[0].frames + singles[1].frames
    assert np.max(np.abs(both.frames - total)) <= 1e-12 * np.max(np.abs(total))
    assert both.firing == "simultaneous"
    assert both.frame_transmitter is not None
    assert both.frame_transmitter.tolist() == [0, 0]
    rows = both.transmitter_waveforms
    assert rows is not None
    assert rows.shape[0] == 2
    for i, single in enumerate(singles):
        assert single.waveform is not None
        width = len(single.waveform)
        assert np.array_equal(rows[i, :width], single.waveform)
        assert not np.any(rows[i, width:])
    assert both.waveform is not None
    assert singles[0].waveform is not None
    assert np.array_equal(both.waveform, singles[0].waveform)


def test_simultaneous_truth_is_seen_from_the_frame_transmitter() -> None:
    """truth_positions of a frame belong to transmitters_m[frame_transmitter] (as calibrate pairs them)."""
    objects = (Sphere([0.0, 0.0, 0.6], 0.1), Plane([0, 0, 1.0], [0, 0, -1], 1.0, 1.0))
    kw = {"objects": objects, "transmitter_codes": ("barker13", "barker11"), "n_samples": 1400}
    sequential = simulate(Scene(array=Array(TWO_TX, TWO_RX[:1]), **kw), 2)
    simultaneous = simulate(Scene(array=Array(TWO_TX, TWO_RX[:1]), firing="simultaneous", **kw), 2)
    assert sequential.truth_positions_m is not None
    assert simultaneous.truth_positions_m is not None
    assert simultaneous.frame_transmitter is not None
    assert simultaneous.frame_transmitter.tolist() == [0, 0]
    # sequential frame 0 fired transmitter 0: its truth is transmitter 0's view.
    assert np.allclose(simultaneous.truth_positions_m[0], sequential.truth_positions_m[0], atol=1e-12)


# --- (15) second order ---------------------------------------------------------------------------------


def test_second_order_ghosts_arrive_at_image_path_lengths() -> None:
    """max_order = 2 adds exactly, for each point x of strength s beside a wall of reflection R:
    T' -> x -> R and T -> x -> R' (gain s R / (leg 1 leg 2), T' and R' the images in the wall), and
    p -> q, q -> p (s_p s_q / (r1 r12 r2)). They vanish with max_order = 1; truth never holds them."""
    t, r = np.array([0.0, 0.0, 0.0]), np.array([0.2, 0.0, 0.0])
    centre, normal = np.array([0.35, 0.0, 0.8]), np.array([-1.0, 0.0, 0.0])
    wall = Plane(centre, normal, 1.5, 1.0, width_axis=[0.0, 0.0, 1.0], reflection=0.9)
    points = {"p": (np.array([0.15, 0.05, 0.6]), 0.8), "q": (np.array([-0.2, -0.1, 1.0]), 0.6)}
    objects = (wall, *(PointReflector(x, strength) for x, strength in points.values()))
    kw = {"objects": objects, "n_samples": 1800, "pulse": PulseSpec(cycles_per_bit=1)}
    first = simulate(pair_scene(t.tolist(), r.tolist(), max_order=1, **kw))
    second = simulate(pair_scene(t.tolist(), r.tolist(), max_order=2, **kw))
    ghosts = second.frames[0, 0] - first.frames[0, 0]
    t_image, r_image = mirrored(t, centre, normal), mirrored(r, centre, normal)
    paths: dict[str, float] = {}
    gains: dict[str, float] = {}
    for name, (x, strength) in points.items():
        for label, start, finish in ((f"wall>{name}", t_image, r), (f"{name}>wall", t, r_image)):
            # The unfolded straight segment crosses the wall inside its rectangle (checked, not assumed).
            a, b = (start, x) if label.startswith("wall") else (x, finish)
            spot = a + (b - a) * np.dot(a - centre, normal) / np.dot(a - b, normal)
            assert abs(spot[1]) < 0.45
            assert abs(spot[2] - 0.8) < 0.7
            leg_1, leg_2 = np.linalg.norm(x - start), np.linalg.norm(finish - x)
            paths[label], gains[label] = leg_1 + leg_2, strength * 0.9 / (leg_1 * leg_2)
    (p, s_p), (q, s_q) = points["p"], points["q"]
    r12 = float(np.linalg.norm(q - p))
    for label, (one, two) in {"p>q": (p, q), "q>p": (q, p)}.items():
        a, b = np.linalg.norm(one - t), np.linalg.norm(two - r)
        paths[label], gains[label] = a + r12 + b, s_p * s_q / (a * r12 * b)
    c = second.speed_of_sound_m_s
    assert c is not None
    pulse = pair_scene(t.tolist(), r.tolist(), **kw).waveform().samples
    predicted = synthesize_frames(
        pulse,
        np.array([[list(paths.values())]]) / c,
        np.array([[list(gains.values())]]),
        sample_rate_hz=FS,
        n_samples=1800,
    )[0, 0]
    assert np.max(np.abs(ghosts)) > 0.1
    assert np.max(np.abs(ghosts - predicted)) <= 1e-9 * np.max(np.abs(ghosts))
    # p's two wall ghosts are 60 samples apart (pulse: 52) and far from the rest: each is found
    # at its own image path.
    for label in ("wall>p", "p>wall"):
        others = [abs(paths[label] - other) / c * FS for key, other in paths.items() if key != label]
        assert min(others) > 55
        gate = (paths[label] / c - 5 / FS, paths[label] / c + 5 / FS)
        measured = xcorr_delays_s(ghosts, pulse, gate_s=gate)[0]
        assert (measured - paths[label] / c) * FS == pytest.approx(0.0, abs=0.02)
    assert first.truth_positions_m is not None
    assert second.truth_positions_m is not None
    assert second.truth_positions_m.shape == (1, 3, 3)  # two points and the wall: no ghost rows
    assert np.array_equal(first.truth_positions_m, second.truth_positions_m, equal_nan=True)
    assert np.array_equal(second.truth_positions_m[0, :2], [p, q])


# --- (16) memory ---------------------------------------------------------------------------------------


def test_simulate_to_file_memory_does_not_grow_with_frames(tmp_path: Path) -> None:
    """Streaming to .h5: the peak traced memory for 6400 frames is that for 640 (ratio < 1.5), where
    holding the 6400 frames (20 MB) would not be; the file reads back as simulate() makes it."""
    scene = pair_scene(
        [0, 0, 0],
        [0.03, 0, 0],
        objects=(PointReflector([0, 0, 0.3], 1.0, [0, 0, 0.2]),),
        n_samples=400,
        snr_db=20.0,
        transducer="electrostatic50",
        receiver=ReceiverSpec(
            adc_rate_hz=1e6,
            adc=AdcSpec(bits=12, full_scale=2.0),
            gain=GainSpec(kind="continuous", slope_db_per_ms=3.0),
        ),
        ring_down=RingDown(level=0.5),
        motion=SensorMotion(velocity_m_s=[0.01, 0.0, 0.0]),
    )
    peaks = {}
    for n in (640, 6400):
        tracemalloc.start()
        try:
            simulate_to_file(scene, n, tmp_path / f"run{n}.h5")
            peaks[n] = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
    assert peaks[6400] < 1.5 * peaks[640]
    assert 1.5 * peaks[640] < 6400 * 400 * 8  # holding every frame would show
    back = read_recording(tmp_path / "run640.h5")
    direct = simulate(scene, 640)
    assert back.frames.shape == direct.frames.shape
    assert np.allclose(back.frames, direct.frames, rtol=1e-6, atol=1e-6 * np.max(np.abs(direct.frames)))
    assert back.sensor_poses is not None
    assert direct.sensor_poses is not None
    assert np.array_equal(back.sensor_poses, direct.sensor_poses)


# --- (17) example scene files ---------------------------------------------------------------------------

SCENE_FILES = sorted(SCENES.glob("**/*.toml"))


@pytest.mark.parametrize("path", SCENE_FILES, ids=[str(p.relative_to(SCENES)) for p in SCENE_FILES])
def test_example_scene_simulates_and_round_trips(path: Path, tmp_path: Path) -> None:
    """Every **/* loads and simulates 2 frames without a warning; the recording carries
    the scene's shape, rate and frame times, and survives a write / read round trip."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        scene = load_scene(path)
        rec = simulate(scene, n_frames=2)
        written = write_recording(rec, tmp_path / "example.h5")
        back = read_recording(written)
    n_rx = len(scene.array.receivers_m)
    n_out = int(np.ceil(scene.n_samples * scene.output_rate_hz / scene.sample_rate_hz - 1e-9))
    assert rec.frames.shape == (2, n_rx, n_out)
    assert np.all(np.isfinite(rec.frames))
    assert rec.sample_rate_hz == scene.output_rate_hz
    assert rec.frame_times_s is not None
    assert np.allclose(rec.frame_times_s, np.arange(2) / scene.frame_rate_hz, rtol=0, atol=1e-15)
    assert back.frames.shape == rec.frames.shape
    assert np.allclose(back.frames, rec.frames, rtol=0, atol=0)
    assert back.signal_kind == rec.signal_kind
