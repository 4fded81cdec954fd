"""Scene -> Recording: what the receivers of a sensor head record.

Per frame, in the order the sound meets them:

1. **Air.** The speed of sound follows the air's temperature and humidity at that
   frame's time (linear drift), times ``1 + turbulence * N(0, 1)`` drawn per frame.
2. **Sensor pose.** The head moves with constant velocity and angular velocity;
   reflectors live in the world frame (the sensor frame at t = 0) and are moved into
   each frame's sensor frame. Random reflectors are drawn in the sensor frame.
3. **Echo paths** (:mod:`echoloc.sim.reflectors`): points, spheres, finite planes by the
   image-source method, edges, and with ``max_order = 2`` the double reflections.
4. **Motion during the frame.** Each path's length is taken at the instant of
   reflection, ``t_r = first_leg / (c - d first_leg / dt)`` (exact for constant radial
   motion, first order in the rates otherwise), and the echo is
   compressed in time by the Doppler factor ``alpha = (c - dr_rx/dt) / (c + dr_tx/dt)``
   of its first and last legs (exact for a reflector moving at constant velocity
   in still air; Kinsler et al., *Fundamentals of Acoustics*, 4th ed., sec. 11.9).
5. **Transducers.** Both beams' piston directivity at the carrier, the band-pass
   of the transmitter and receiver (in the returned pulse), ISO 9613-1 absorption
   per frequency over each path, and the transmitter's ring-down at the frame start.
6. **Echo synthesis** (:mod:`echoloc.sim.synthesis`): band-limited fractional delays,
   each receiver's echoes late by its timing jitter for the frame
   (``timing_jitter_s``, :func:`timing_offsets_s`).
7. **Receiver chain** (:mod:`echoloc.sim.receiver`): noise, time-varying gain, ADC
   clipping and quantisation, decimation, and the recorded signal kind.

Frames are made in batches so that :func:`simulate_to_file` writes any number of them
with flat memory; :func:`simulate` collects them into one :class:`Recording`.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import scipy.signal
from numpy.typing import NDArray

from echoloc.errors import SceneError
from echoloc.io.recording import FrameBatch, Recording, write_recording_stream
from echoloc.physics.air import absorption_db_per_m, speed_of_sound_m_s
from echoloc.physics.transducer import PRESETS, directivity, impulse_response, piston_beam_angles
from echoloc.sim.receiver import (
    band_limited_noise,
    gain_curve,
    output_samples,
    quantise,
    resample,
    template_for_kind,
    to_signal_kind,
    white_noise,
)
from echoloc.sim.reflectors import (
    EchoPaths,
    Plane,
    PointReflector,
    Reflector,
    ReflectorStates,
    echo_paths,
    states_at,
    truth_kinds,
    truth_positions_m,
)
from echoloc.sim.scene import Scene
from echoloc.sim.synthesis import PulseTable, pulse_table, synthesize

FloatArray = NDArray[np.float64]

BATCH_FRAMES = 64
"""Frames made at once: large enough to amortise numpy's overhead, small enough for cache."""

BATCH_BYTES = 256 << 20
"""The most a batch's frames may take at the ADC (float64): frames of millions of samples
go fewer at a time (a batch of 64 such frames would take gigabytes). A scene of ordinary
frames keeps batches of :data:`BATCH_FRAMES`, so its random draws are as before."""


def batch_frames(scene: Scene) -> int:
    """Frames per batch for ``scene``: :data:`BATCH_FRAMES`, fewer for very long frames."""
    decimation = max(1, round(scene.adc_rate_hz / scene.sample_rate_hz))
    frame_bytes = 8 * len(scene.array.receivers_m) * scene.n_samples * decimation
    return max(1, min(BATCH_FRAMES, BATCH_BYTES // frame_bytes))


_RATE_STEP_S = 1e-3
"""Time step of the finite difference that gives each path's rate of change (Doppler)."""


def path_lengths_m(
    transmitter_m: FloatArray, receivers_m: FloatArray, points_m: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Transmitter -> point -> receiver geometry for points (..., 3).

    Returns ``(path_m, r_tx_m, r_rx_m)`` with shapes (..., n_rx), (...,), (..., n_rx).
    """
    r_tx = np.linalg.norm(points_m - transmitter_m, axis=-1)
    r_rx = np.linalg.norm(points_m[..., None, :] - receivers_m, axis=-1)
    return r_tx[..., None] + r_rx, r_tx, r_rx


@dataclass(frozen=True, eq=False)
class _Plan:
    """What stays the same for every frame of a recording, computed once."""

    objects: tuple[Reflector, ...]
    tables: tuple[PulseTable, ...]  # per transmitter, at the ADC rate
    frame_start: FloatArray  # (n_tx, n_rx, n_adc): ring-down and direct path, added to every frame
    n_adc: int
    noise_sigma_adc: float | None
    gain_adc: FloatArray | None  # (n_adc,) linear
    moving: bool


def _objects(scene: Scene) -> tuple[Reflector, ...]:
    """The scene's fixed point reflectors as objects, followed by its other objects."""
    points = tuple(
        PointReflector(position_m=p, strength_m=float(s))
        for p, s in zip(scene.reflector_positions_m, scene.reflector_strengths, strict=True)
    )
    return points + scene.objects


def _is_moving(scene: Scene, objects: tuple[Reflector, ...]) -> bool:
    if scene.motion.moving:
        return True
    return any(
        bool(np.any(obj.velocity_m_s)) or (isinstance(obj, Plane) and obj.angular_velocity_deg_s != 0)
        for obj in objects
    )


def _max_path_m(scene: Scene) -> float:
    """Longest path that can still arrive within the frame (absorption table range)."""
    slowest = scene.speed_of_sound_m_s * (1 + 5 * scene.drift.turbulence) + 50.0
    return scene.frame_duration_s * slowest


def _ring_down(scene: Scene, transmitter: int, n_adc: int) -> FloatArray:
    """The transmitter's ring-down at every receiver (n_rx, n_adc).

    The electrical drive through a two-pole resonator at the carrier whose impulse
    response decays as ``exp(-t / decay_s)``, scaled to a peak of ``level`` (or of
    each receiver's entry of ``levels``).
    """
    rate = scene.adc_rate_hz
    n_rx = len(scene.array.receivers_m)
    spec = scene.ring_down
    if not spec.active:
        return np.zeros((n_rx, n_adc))
    drive = np.zeros(n_adc)
    pulse = scene.waveform(transmitter, rate).samples[:n_adc]
    drive[: len(pulse)] = pulse
    radius = np.exp(-1.0 / (spec.decay_s * rate))
    omega = 2 * np.pi * scene.pulse.carrier_hz / rate
    ringing = scipy.signal.lfilter([1.0], [1.0, -2 * radius * np.cos(omega), radius**2], drive)
    ringing /= np.max(np.abs(ringing))
    return np.asarray(spec.receiver_levels(n_rx)[:, None] * ringing[None, :], dtype=float)


def timing_offsets_s(sigma_s: FloatArray, standard_normal: FloatArray) -> FloatArray:
    """Per-frame, per-receiver timing offsets, s: ``sigma_s * standard_normal``.

    ``sigma_s`` (n_rx,) is each receiver's timing jitter (standard deviation, s);
    ``standard_normal`` (n_frames, n_rx) are draws from N(0, 1). An echo of receiver r
    in frame f arrives ``offset[f, r]`` seconds late (early if negative).
    """
    sigma = np.asarray(sigma_s, dtype=float)
    return np.asarray(np.asarray(standard_normal, dtype=float) * sigma[None, :], dtype=float)


def _direct_path(scene: Scene, transmitter: int, table: PulseTable, n_adc: int) -> FloatArray:
    """The wave straight from the transmitter to each receiver (n_rx, n_adc), spreading 1/d.

    Computed once per recording at the initial speed of sound (the path is short: air
    drift moves it by a few ns), with absorption over the distance.
    """
    tx = scene.array.transmitters_m[transmitter]
    receivers = scene.array.receivers_m
    offset = receivers - tx
    distance = np.linalg.norm(offset, axis=1)
    gain = 1.0 / np.maximum(distance, 1e-6)
    if scene.transducer is not None:
        tx_axes, rx_axes = scene.array.axes()
        unit = offset / np.maximum(distance, 1e-12)[:, None]
        gain = (
            gain * _beam(scene, unit @ tx_axes[transmitter]) * _beam(scene, np.sum(-unit * rx_axes, axis=1))
        )
    delay = distance / scene.speed_of_sound_m_s
    frames = synthesize(
        table, delay[None, :, None], np.asarray(gain)[None, :, None], n_adc, path_m=distance[None, :, None]
    )
    return np.asarray(frames[0], dtype=float)


def _beam(scene: Scene, cos_angle: FloatArray) -> FloatArray:
    """Piston directivity of the scene's transducer at the carrier for angles given by their cosine."""
    assert scene.transducer is not None
    theta = np.arccos(np.clip(np.nan_to_num(cos_angle, nan=1.0), -1.0, 1.0))
    return np.asarray(
        directivity(PRESETS[scene.transducer], theta, scene.pulse.carrier_hz, scene.speed_of_sound_m_s)
    )


def _decimated_noise_gain(scene: Scene) -> float:
    """Variance of the recorded noise per unit variance of the noise generated at the ADC rate.

    The noise (white, or through the receiver's band-pass normalised to unit variance)
    passes the decimator, an FIR ``h_d`` followed by keeping every q-th sample; for
    stationary input of autocorrelation ``r`` the output variance is ``sum_k sum_l h_d[k]
    h_d[l] r[k - l]``, the energy of ``h_d * h_b`` for band noise (``h_b`` of unit
    energy) and of ``h_d`` for white noise (Oppenheim & Schafer, sec. 2.10). The
    energy is summed exactly by decimating unit impulses at each of the q phases.
    """
    ratio = round(scene.adc_rate_hz / scene.sample_rate_hz)
    if ratio == 1:
        return 1.0
    shaping = np.ones(1)
    if scene.receiver.noise == "band":
        assert scene.transducer is not None
        shaping = impulse_response(PRESETS[scene.transducer], scene.adc_rate_hz, passes=1)
        shaping = shaping / np.sqrt(np.sum(shaping**2))
    pad = 64 * ratio
    impulses = np.zeros((ratio, len(shaping) + 2 * pad))
    for phase in range(ratio):
        impulses[phase, pad + phase : pad + phase + len(shaping)] = shaping
    decimated = resample(impulses, scene.adc_rate_hz, scene.sample_rate_hz)
    return float(np.sum(decimated**2))


def _plan(scene: Scene) -> _Plan:
    rate = scene.adc_rate_hz
    n_adc = output_samples(scene.n_samples, scene.sample_rate_hz, rate)
    absorption: Callable[[FloatArray], FloatArray] | None = None
    if scene.absorption:
        absorption = partial(absorption_db_per_m, temperature_c=scene.temperature_c,
                             relative_humidity=scene.relative_humidity)  # fmt: skip
    n_tx = len(scene.array.transmitters_m)
    tables = tuple(
        pulse_table(
            scene.returned_pulse(tx, rate),
            rate,
            absorption_db_per_m=absorption,
            max_path_m=_max_path_m(scene),
        )
        for tx in range(n_tx)
    )
    frame_start = np.stack([_ring_down(scene, tx, n_adc) for tx in range(n_tx)])
    if scene.ring_down.direct_path:
        frame_start += np.stack([_direct_path(scene, tx, tables[tx], n_adc) for tx in range(n_tx)])
    noise_sigma = None
    if scene.snr_db is not None:
        emitted_peak = float(np.max(np.abs(scene.waveform(0).samples)))
        noise_sigma = 10.0 ** (-scene.snr_db / 20.0) * emitted_peak
        noise_sigma /= float(np.sqrt(_decimated_noise_gain(scene)))
    gain = None
    if scene.receiver.gain.active:
        gain = gain_curve(scene.receiver.gain, n_adc, rate)
    objects = _objects(scene)
    return _Plan(
        objects=objects,
        tables=tables,
        frame_start=frame_start,
        n_adc=n_adc,
        noise_sigma_adc=noise_sigma,
        gain_adc=gain,
        moving=_is_moving(scene, objects),
    )


def _states(
    scene: Scene,
    objects: tuple[Reflector, ...],
    times_s: FloatArray,
    drawn: tuple[FloatArray, FloatArray] | None,
) -> ReflectorStates:
    """Every reflector at ``times_s`` in that instant's sensor frame."""
    world = states_at(
        objects, times_s, frequency_hz=scene.pulse.carrier_hz, speed_of_sound_m_s=scene.speed_of_sound_m_s
    )
    states = world
    if scene.motion.moving:
        rotation, translation = scene.motion.poses(times_s)
        to_sensor = np.transpose(rotation, (0, 2, 1))
        states = world.transformed(to_sensor, -np.einsum("fij,fj->fi", to_sensor, translation))
    if drawn is not None:
        states = states.with_points(*drawn)
    return states


def _draw_random(scene: Scene, n: int, rng: np.random.Generator) -> tuple[FloatArray, FloatArray] | None:
    """Random point reflectors (n, n_max, 3) and strengths (n, n_max), NaN-padded."""
    spec = scene.random
    if spec is None:
        return None
    n_max = spec.count[1]
    counts = rng.integers(spec.count[0], spec.count[1] + 1, size=n)
    low = np.array([spec.x_m[0], spec.y_m[0], spec.z_m[0]])
    high = np.array([spec.x_m[1], spec.y_m[1], spec.z_m[1]])
    drawn = rng.uniform(low, high, size=(n, n_max, 3))
    strength = rng.uniform(*spec.strength, size=(n, n_max))
    present = np.arange(n_max) < counts[:, None]
    return np.where(present[..., None], drawn, np.nan), np.where(present, strength, np.nan)


def _echo_gain(scene: Scene, paths: EchoPaths, transmitter: int) -> FloatArray:
    """Path gain times both beams' directivity, (n, n_rx, n_paths)."""
    gain = np.where(np.isfinite(paths.path_m), paths.gain, np.nan)
    if scene.transducer is None:
        return gain
    tx_axes, rx_axes = scene.array.axes()
    cos_tx = paths.departure @ tx_axes[transmitter]
    cos_rx = np.einsum("frpk,rk->frp", paths.arrival, rx_axes)
    return gain * _beam(scene, cos_tx) * _beam(scene, cos_rx)


def _batch(scene: Scene, plan: _Plan, first_frame: int, n: int, rng: np.random.Generator) -> FrameBatch:
    frame = first_frame + np.arange(n)
    times = frame / scene.frame_rate_hz
    temperature = scene.temperature_c + scene.drift.temperature_c_per_s * times
    humidity = np.clip(scene.relative_humidity + scene.drift.relative_humidity_per_s * times, 0.0, 1.0)
    c = np.asarray(speed_of_sound_m_s(temperature, humidity), dtype=float)
    if scene.drift.turbulence > 0:
        c = c * (1.0 + scene.drift.turbulence * rng.standard_normal(n))
    drawn = _draw_random(scene, n, rng)
    states = _states(scene, plan.objects, times, drawn)
    later = _states(scene, plan.objects, times + _RATE_STEP_S, drawn) if plan.moving else None

    n_tx = len(scene.array.transmitters_m)
    receivers = scene.array.receivers_m
    if scene.firing == "simultaneous":
        fired = np.ones((n_tx, n), dtype=bool)
        frame_transmitter = np.zeros(n, dtype=np.int64)
    else:
        frame_transmitter = (frame % n_tx).astype(np.int64)
        fired = frame_transmitter[None, :] == np.arange(n_tx)[:, None]

    jitter_s = scene.timing_jitter_per_receiver_s()
    offsets_s = None
    if np.any(jitter_s > 0):
        # One delay per receiver and frame, shared by every transmitter fired in it.
        offsets_s = timing_offsets_s(jitter_s, rng.standard_normal((n, len(receivers))))
    analog = np.zeros((n, len(receivers), plan.n_adc))
    truth: FloatArray | None = None
    for tx in range(n_tx):
        # Only the frames this transmitter fires are computed for it.
        rows = np.flatnonzero(fired[tx])
        if len(rows) == 0:
            continue
        mine = states if len(rows) == n else states.take(rows)
        mine_later = None if later is None else later if len(rows) == n else later.take(rows)
        c_col = c[rows, None, None]
        tx_m = scene.array.transmitters_m[tx]
        paths = echo_paths(tx_m, receivers, mine, max_order=scene.max_order)
        path = paths.path_m
        alpha = None
        if mine_later is not None:
            moved = echo_paths(tx_m, receivers, mine_later, max_order=scene.max_order)
            first_rate = np.nan_to_num((moved.first_leg_m - paths.first_leg_m) / _RATE_STEP_S)
            last_rate = np.nan_to_num((moved.last_leg_m - paths.last_leg_m) / _RATE_STEP_S)
            # The path as it is when the pulse reaches the (first) reflection point, at
            # t_r = first_leg / (c - first_rate): exact for constant radial motion.
            path = path + (first_rate + last_rate) * paths.first_leg_m / (c_col - first_rate)
            alpha = (c_col - last_rate) / (c_col + first_rate)
        if scene.path_jitter_m > 0:
            path = path + rng.normal(0.0, scene.path_jitter_m, size=path.shape)
        gain = _echo_gain(scene, paths, tx)
        delay = path / c_col
        if offsets_s is not None:
            delay = delay + offsets_s[rows][:, :, None]
        analog[rows] += synthesize(plan.tables[tx], delay, gain, plan.n_adc, time_scale=alpha, path_m=path)
        analog[rows] += plan.frame_start[tx]
        if truth is None or scene.firing == "sequential":
            # Truth is seen from the frame's transmitter (transmitter 0 when all fire at once).
            if truth is None:
                truth = np.full((n, states.n_truth, 3), np.nan)
            truth[rows] = truth_positions_m(tx_m, mine)
    assert truth is not None

    frames = _receive(scene, plan, analog, rng)
    poses = scene.motion.pose_quaternions(times) if scene.motion.moving else None
    return FrameBatch(
        frames=frames,
        frame_times_s=times,
        frame_transmitter=frame_transmitter,
        truth_positions_m=truth,
        sensor_poses=poses,
    )


Samples = NDArray[np.floating[Any]] | NDArray[np.complexfloating[Any, Any]]


def _receive(scene: Scene, plan: _Plan, analog: FloatArray, rng: np.random.Generator) -> Samples:
    """The receiver chain: noise, gain, ADC, decimation and signal kind."""
    spec = scene.receiver
    signal = analog
    if plan.noise_sigma_adc is not None:
        if spec.noise == "band":
            assert scene.transducer is not None
            signal = signal + band_limited_noise(
                signal.shape, plan.noise_sigma_adc, rng, PRESETS[scene.transducer], scene.adc_rate_hz
            )
        else:
            signal = signal + white_noise(signal.shape, plan.noise_sigma_adc, rng)
    if plan.gain_adc is not None:
        signal = signal * plan.gain_adc
    if spec.adc is not None:
        signal = quantise(signal, spec.adc)
    if scene.adc_rate_hz != scene.sample_rate_hz:
        signal = resample(signal, scene.adc_rate_hz, scene.sample_rate_hz)[..., : scene.n_samples]
    if spec.baseband_filter_s > 0:
        return _chip_output(scene, signal)
    if spec.signal_kind != "rf" or scene.output_rate_hz != scene.sample_rate_hz:
        recorded: Samples = to_signal_kind(
            signal,
            spec.signal_kind,
            sample_rate_hz=scene.sample_rate_hz,
            carrier_hz=scene.pulse.carrier_hz,
            output_rate_hz=scene.output_rate_hz,
        )
        return recorded
    return signal


def moving_average(samples: NDArray[Any], length: int, order: int = 1) -> NDArray[Any]:
    """``order`` cascaded causal moving averages of ``length`` samples along the last axis.

    The decimating filter of a ToF chip (a CIC filter, E. B. Hogenauer, IEEE Trans.
    ASSP 29 (1981) 155-162, normalised to unit gain at 0 Hz): output sample k is the
    mean of the previous stage's samples k - length + 1 .. k, zero before the start.
    Each stage delays a signal by ``(length - 1) / 2`` samples. Real or complex input.
    """
    if length < 1 or order < 1:
        raise ValueError(f"length and order must be >= 1, got {length} and {order}")
    out = np.asarray(samples)
    kernel = np.ones(length) / length
    for _ in range(order):
        out = scipy.signal.lfilter(kernel, [1.0], out, axis=-1)
    return out


def _chip_output(scene: Scene, signal: FloatArray) -> Samples:
    """A ToF chip's output: baseband, its CIC filter (``baseband_filter_*``), resampled; envelope or iq."""
    spec = scene.receiver
    iq = to_signal_kind(
        signal,
        "iq",
        sample_rate_hz=scene.sample_rate_hz,
        carrier_hz=scene.pulse.carrier_hz,
        output_rate_hz=scene.sample_rate_hz,
    )
    length = max(round(spec.baseband_filter_s * scene.sample_rate_hz), 1)
    filtered = moving_average(iq, length, spec.baseband_filter_order)
    out = np.asarray(resample(filtered, scene.sample_rate_hz, scene.output_rate_hz), dtype=np.complex128)
    if spec.signal_kind == "envelope":
        return np.asarray(np.abs(out), dtype=np.float64)
    return out


def _chip_template(scene: Scene, returned_pulse: FloatArray) -> NDArray[Any]:
    """The echo template of a chip with a baseband filter: an echo at t = 0 through :func:`_chip_output`.

    Cut after its last sample at or above 1e-4 of its peak magnitude, as
    :func:`echoloc.sim.receiver.template_for_kind` cuts.
    """
    tail = 8 * round(
        scene.receiver.baseband_filter_order * scene.receiver.baseband_filter_s * scene.sample_rate_hz
    )
    frame = np.zeros(2 * len(returned_pulse) + tail + 64)
    frame[: len(returned_pulse)] = returned_pulse
    out = _chip_output(scene, frame)
    magnitude = np.abs(out)
    last = int(np.flatnonzero(magnitude >= 1e-4 * magnitude.max())[-1])
    return np.asarray(out[: last + 1])


def _templates(scene: Scene) -> list[NDArray[np.generic]]:
    """Each transmitter's echo template in the recorded representation and rate."""
    if scene.receiver.baseband_filter_s > 0:
        return [
            _chip_template(scene, scene.returned_pulse(tx)) for tx in range(len(scene.array.transmitters_m))
        ]
    return [
        template_for_kind(
            scene.returned_pulse(tx),
            scene.receiver.signal_kind,
            sample_rate_hz=scene.sample_rate_hz,
            carrier_hz=scene.pulse.carrier_hz,
            output_rate_hz=scene.output_rate_hz,
        )
        for tx in range(len(scene.array.transmitters_m))
    ]


def recording_header(scene: Scene) -> Recording:
    """Every per-recording field of what ``scene`` records; ``frames`` has 0 frames."""
    templates = _templates(scene)
    n_out = output_samples(scene.n_samples, scene.sample_rate_hz, scene.output_rate_hz)
    shape = (0, len(scene.array.receivers_m), n_out)
    frames: Samples = (
        np.zeros(shape, dtype=np.complex128) if scene.receiver.signal_kind == "iq" else np.zeros(shape)
    )
    n_tx = len(scene.array.transmitters_m)
    transmitter_waveforms = None
    if scene.receiver.record_waveform and n_tx > 1 and len(set(scene.codes())) > 1:
        width = max(len(t) for t in templates)
        transmitter_waveforms = np.zeros((n_tx, width), dtype=templates[0].dtype)
        for i, template in enumerate(templates):
            transmitter_waveforms[i, : len(template)] = template
    receiver_gain = None
    if scene.receiver.gain.active:
        receiver_gain = gain_curve(scene.receiver.gain, n_out, scene.output_rate_hz)
    return Recording(
        sample_rate_hz=scene.output_rate_hz,
        transmitters_m=scene.array.transmitters_m,
        receivers_m=scene.array.receivers_m,
        frames=frames,
        waveform=np.asarray(templates[0]) if scene.receiver.record_waveform else None,
        transmitter_axes=scene.array.transmitter_axes,
        receiver_axes=scene.array.receiver_axes,
        signal_kind=scene.receiver.signal_kind,
        carrier_hz=scene.pulse.carrier_hz,
        speed_of_sound_m_s=scene.speed_of_sound_m_s,
        temperature_c=scene.temperature_c,
        relative_humidity=scene.relative_humidity,
        receiver_gain=receiver_gain,
        transmitter_waveforms=transmitter_waveforms,
        firing=scene.firing if n_tx > 1 else None,
        field_of_view_deg=_field_of_view_deg(scene),
        truth_kinds=scene_truth_kinds(scene),
    )


def scene_truth_kinds(scene: Scene) -> tuple[str, ...]:
    """The class of each truth column of ``scene``'s recordings: its random points (drawn after
    the fixed ones, all points) and :func:`echoloc.sim.reflectors.truth_kinds` of the rest."""
    n_random = 0 if scene.random is None else scene.random.count[1]
    kinds = truth_kinds(_objects(scene))
    n_points = sum(1 for k in _objects(scene) if isinstance(k, PointReflector))
    return kinds[:n_points] + ("point",) * n_random + kinds[n_points:]


def _field_of_view_deg(scene: Scene) -> float | None:
    """The first-null half-angle of the transducers' piston beam at the carrier, degrees.

    Beyond it only sidelobes remain (-17.6 dB one way for a piston, so below -35 dB
    for transmitter and receiver together). None without a transducer model, or when
    the piston is too small to have a null (ka < 3.83).
    """
    if scene.transducer is None:
        return None
    model = PRESETS[scene.transducer]
    beam = piston_beam_angles(model.radius_m, scene.pulse.carrier_hz, scene.speed_of_sound_m_s)
    half = float(np.degrees(beam.half_angle_null_rad))
    return half if np.isfinite(half) else None


def simulate_batches(scene: Scene, n_frames: int) -> Iterator[FrameBatch]:
    """Frames of ``scene`` in batches of :func:`batch_frames`, reproducible from ``scene.seed``."""
    if n_frames < 1:
        raise SceneError(f"the number of frames must be >= 1, got {n_frames}")
    plan = _plan(scene)
    rng = np.random.default_rng(scene.seed)
    size = batch_frames(scene)
    for start in range(0, n_frames, size):
        yield _batch(scene, plan, start, min(size, n_frames - start), rng)


def simulate(scene: Scene, n_frames: int = 1, *, progress: Callable[[int], None] | None = None) -> Recording:
    """Simulate ``n_frames`` frames of ``scene`` in memory; the result carries ``truth_positions_m``.

    ``progress``, if given, is called with the number of frames finished after each batch.
    """
    header = recording_header(scene)
    frames = np.empty((n_frames, *header.frames.shape[1:]), dtype=header.frames.dtype)
    per_frame: dict[str, list[Any]] = {name: [] for name in _PER_FRAME}
    done = 0
    for batch in simulate_batches(scene, n_frames):
        frames[done : done + batch.n_frames] = batch.frames
        done += batch.n_frames
        for name, parts in per_frame.items():
            parts.append(getattr(batch, name))
        if progress is not None:
            progress(batch.n_frames)
    joined: dict[str, Any] = {
        name: None if parts[0] is None else np.concatenate(parts, axis=0) for name, parts in per_frame.items()
    }
    return dataclasses.replace(header, frames=frames, **joined)


_PER_FRAME = ("frame_times_s", "frame_transmitter", "truth_positions_m", "sensor_poses")


def simulate_to_file(
    scene: Scene, n_frames: int, path: str | Path, *, progress: Callable[[int], None] | None = None
) -> Path:
    """Simulate straight to a recording file, one batch in memory at a time (flat memory for .h5)."""

    def reported() -> Iterator[FrameBatch]:
        for batch in simulate_batches(scene, n_frames):
            yield batch
            if progress is not None:
                progress(len(batch.frames))

    return write_recording_stream(recording_header(scene), reported(), path)
