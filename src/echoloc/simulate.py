"""Scene -> Recording: what the receivers of a sensor head record.

Each echo is the emitted pulse, delayed by its exact path time and scaled by
spherical spreading. Delays are band-limited fractional delays applied in the
frequency domain, ``Y(f) = W(f) * sum_k a_k exp(-2j pi f tau_k)``: the sampled
result equals sampling the band-limited (sinc) interpolation of the pulse shifted
by ``tau_k``, not a shift rounded to a sample. The FFT length leaves room for the
pulse after the last sample so that nothing wraps around into the frame.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from functools import partial

import numpy as np
import scipy.fft
from numpy.typing import NDArray

from echoloc.air import absorption_db_per_m, spreading_gain
from echoloc.errors import SceneError
from echoloc.recording import Recording
from echoloc.scene import Scene
from echoloc.transducer import PRESETS, directivity

_BATCH_FRAMES = 64


def path_lengths_m(
    transmitter_m: NDArray[np.float64],
    receivers_m: NDArray[np.float64],
    points_m: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Transmitter -> point -> receiver geometry for points (..., 3).

    Returns ``(path_m, r_tx_m, r_rx_m)`` with shapes (..., n_rx), (...,), (..., n_rx).
    """
    r_tx = np.linalg.norm(points_m - transmitter_m, axis=-1)
    r_rx = np.linalg.norm(points_m[..., None, :] - receivers_m, axis=-1)
    return r_tx[..., None] + r_rx, r_tx, r_rx


def draw_reflectors(
    scene: Scene, n_frames: int, rng: np.random.Generator
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Reflector positions (n_frames, n_max, 3) with NaN padding, and strengths (NaN-padded).

    Fixed reflectors come first in every frame; random ones are drawn per frame.
    """
    fixed = scene.reflector_positions_m
    n_fixed = len(fixed)
    spec = scene.random
    n_random_max = spec.count[1] if spec is not None else 0
    positions = np.full((n_frames, n_fixed + n_random_max, 3), np.nan)
    strengths = np.full((n_frames, n_fixed + n_random_max), np.nan)
    positions[:, :n_fixed] = fixed
    strengths[:, :n_fixed] = scene.reflector_strengths
    if spec is not None:
        counts = rng.integers(spec.count[0], spec.count[1] + 1, size=n_frames)
        low = np.array([spec.x_m[0], spec.y_m[0], spec.z_m[0]])
        high = np.array([spec.x_m[1], spec.y_m[1], spec.z_m[1]])
        drawn = rng.uniform(low, high, size=(n_frames, n_random_max, 3))
        drawn_strength = rng.uniform(*spec.strength, size=(n_frames, n_random_max))
        present = np.arange(n_random_max) < counts[:, None]
        positions[:, n_fixed:] = np.where(present[..., None], drawn, np.nan)
        strengths[:, n_fixed:] = np.where(present, drawn_strength, np.nan)
    return positions, strengths


def synthesize_frames(
    waveform: NDArray[np.float64],
    tof_s: NDArray[np.float64],
    amplitude: NDArray[np.float64],
    *,
    sample_rate_hz: float,
    n_samples: int,
    path_m: NDArray[np.float64] | None = None,
    absorption_db_per_m: Callable[[NDArray[np.float64]], NDArray[np.float64]] | None = None,
) -> NDArray[np.float64]:
    """Sum of delayed, scaled copies of ``waveform``, band-limited fractional delays.

    ``tof_s`` and ``amplitude`` have shape (n_frames, n_rx, n_echoes); NaN entries
    (padding) contribute nothing. With ``absorption_db_per_m`` (a function of
    frequency, e.g. ISO 9613-1) every echo is also attenuated by
    ``10**(-alpha(f) path / 20)`` at each frequency over its ``path_m``.
    Returns (n_frames, n_rx, n_samples).
    """
    guard = 64  # samples of room for the band-limited pulse's tails
    n_fft = scipy.fft.next_fast_len(n_samples + 2 * len(waveform) + 2 * guard, real=True)
    spectrum = scipy.fft.rfft(waveform, n_fft)
    freqs_hz = scipy.fft.rfftfreq(n_fft, 1.0 / sample_rate_hz)
    # An echo arriving after the frame has ended leaves no trace in it; left in, the
    # circular FFT would wrap it round into the frame.
    arrives_in_time = tof_s * sample_rate_hz < n_samples + guard
    valid = np.isfinite(tof_s) & np.isfinite(amplitude) & arrives_in_time
    tof = np.where(valid, tof_s, 0.0)
    amp = np.where(valid, amplitude, 0.0)
    # exp(-(alpha(f) L + 2j pi f tau)): absorption in nepers per metre over path L.
    exponent = 2j * np.pi * freqs_hz
    nepers = np.zeros_like(freqs_hz)
    if absorption_db_per_m is not None:
        if path_m is None:
            raise ValueError("absorption needs the path lengths")
        nepers = np.asarray(absorption_db_per_m(freqs_hz)) * np.log(10) / 20
        paths = np.where(valid, path_m, 0.0)
    # sum_k a_k exp(-2j pi f tau_k), accumulated echo by echo to bound memory.
    total = np.zeros((*tof.shape[:2], len(freqs_hz)), dtype=complex)
    for k in range(tof.shape[2]):
        phase = exponent * tof[..., k, None]
        if absorption_db_per_m is not None:
            phase = phase + nepers * paths[..., k, None]
        total += amp[..., k, None] * np.exp(-phase)
    frames = scipy.fft.irfft(total * spectrum, n_fft, axis=-1)[..., :n_samples]
    return np.asarray(frames)


def beam_gain(
    scene: Scene,
    points_m: NDArray[np.float64],
    transmitter_m: NDArray[np.float64],
    transmitter_axis: NDArray[np.float64],
    receivers_m: NDArray[np.float64],
    receiver_axes: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Transmit times receive directivity of the scene's transducer for points (..., 3): (..., n_rx).

    Piston directivity at the carrier frequency (narrow-band), each at the angle
    between the transducer's boresight and the direction to the point.
    """
    assert scene.transducer is not None
    model = PRESETS[scene.transducer]
    f = scene.pulse.carrier_hz
    c = scene.speed_of_sound_m_s
    to_point = points_m - transmitter_m
    cos_tx = (to_point @ transmitter_axis) / np.linalg.norm(to_point, axis=-1)
    from_rx = points_m[..., None, :] - receivers_m
    cos_rx = np.sum(from_rx * receiver_axes, axis=-1) / np.linalg.norm(from_rx, axis=-1)
    theta_tx = np.arccos(np.clip(np.nan_to_num(cos_tx, nan=1.0), -1, 1))
    theta_rx = np.arccos(np.clip(np.nan_to_num(cos_rx, nan=1.0), -1, 1))
    gain = directivity(model, theta_tx, f, c)[..., None] * directivity(model, theta_rx, f, c)
    return np.asarray(gain)


def _air_absorption_db_per_m(scene: Scene, freqs_hz: NDArray[np.float64]) -> NDArray[np.float64]:
    """ISO 9613-1 absorption in the scene's air (dB/m); DC is taken as 1 Hz."""
    return absorption_db_per_m(np.maximum(freqs_hz, 1.0), scene.temperature_c, scene.relative_humidity)


def _frames_in_batches(
    scene: Scene,
    returned_pulse: NDArray[np.float64],
    emitted_peak: float,
    positions: NDArray[np.float64],
    strengths: NDArray[np.float64],
    rng: np.random.Generator,
) -> Iterator[NDArray[np.float64]]:
    waveform = returned_pulse
    c = scene.speed_of_sound_m_s
    transmitter = scene.array.transmitters_m[0]
    receivers = scene.array.receivers_m
    tx_axes, rx_axes = scene.array.axes()
    # scene.py's noise convention refers to the emitted pulse's peak.
    noise_std = None if scene.snr_db is None else 10.0 ** (-scene.snr_db / 20.0) * emitted_peak
    absorption = partial(_air_absorption_db_per_m, scene) if scene.absorption else None
    for start in range(0, len(positions), _BATCH_FRAMES):
        batch = positions[start : start + _BATCH_FRAMES]
        path, r_tx, r_rx = path_lengths_m(transmitter, receivers, batch)
        if scene.path_jitter_m > 0:
            path = path + rng.normal(0.0, scene.path_jitter_m, size=path.shape)
        amplitude = strengths[start : start + _BATCH_FRAMES, :, None] * spreading_gain(r_tx[..., None], r_rx)
        if scene.transducer is not None:
            amplitude = amplitude * beam_gain(scene, batch, transmitter, tx_axes[0], receivers, rx_axes)
        # (frames, echoes, rx) -> (frames, rx, echoes)
        frames = synthesize_frames(
            waveform,
            np.swapaxes(path / c, 1, 2),
            np.swapaxes(amplitude, 1, 2),
            sample_rate_hz=scene.sample_rate_hz,
            n_samples=scene.n_samples,
            path_m=np.swapaxes(path, 1, 2),
            absorption_db_per_m=absorption,
        )
        if noise_std is not None:
            frames = frames + rng.normal(0.0, noise_std, size=frames.shape)
        yield frames


def simulate(scene: Scene, n_frames: int = 1, *, progress: Callable[[int], None] | None = None) -> Recording:
    """Simulate ``n_frames`` frames of ``scene``; the result carries ``truth_positions_m``.

    ``progress``, if given, is called with the number of frames finished after each batch.
    """
    if n_frames < 1:
        raise SceneError(f"the number of frames must be >= 1, got {n_frames}")
    rng = np.random.default_rng(scene.seed)
    positions, strengths = draw_reflectors(scene, n_frames, rng)
    waveform = scene.waveform()
    returned = scene.returned_pulse()
    emitted_peak = float(np.max(np.abs(waveform.samples)))
    batches = []
    for batch in _frames_in_batches(scene, returned, emitted_peak, positions, strengths, rng):
        batches.append(batch)
        if progress is not None:
            progress(len(batch))
    frames = np.concatenate(batches, axis=0)
    return Recording(
        sample_rate_hz=scene.sample_rate_hz,
        transmitters_m=scene.array.transmitters_m,
        receivers_m=scene.array.receivers_m,
        frames=frames,
        waveform=returned,
        transmitter_axes=scene.array.transmitter_axes,
        receiver_axes=scene.array.receiver_axes,
        signal_kind="rf",
        carrier_hz=waveform.carrier_hz,
        speed_of_sound_m_s=scene.speed_of_sound_m_s,
        temperature_c=scene.temperature_c,
        relative_humidity=scene.relative_humidity,
        frame_times_s=np.arange(n_frames) / scene.frame_rate_hz,
        frame_transmitter=np.zeros(n_frames, dtype=np.int64),
        truth_positions_m=positions,
    )
