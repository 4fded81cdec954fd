"""Scenes: the sensor head, the emitted pulse, the air and the reflectors.

A :class:`Scene` is everything :func:`echoloc.sim.simulation.simulate` needs. It is read
from TOML by :func:`echoloc.sim.scenefile.load_scene` (every key checked; an unknown key
is an error that names it) or built in code; :func:`default_scene` is the report's
set-up.

Noise convention (documented once, used everywhere): ``snr_db`` is the per-sample
amplitude signal-to-noise ratio, ``20 log10(A / sigma)``, of the echo from a
unit-strength point reflector with 1 m from the transmitter and 1 m to the
receiver, where ``A`` is the emitted pulse's peak amplitude (1) and ``sigma`` the
standard deviation of the noise in the recorded rf samples at ``sample_rate_hz``
(after any decimation from the ADC rate, before the receiver's gain). Closer or
stronger reflectors have proportionally higher SNR: the noise is the receiver's, not
the scene's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from echoloc.errors import SceneError, WaveformError
from echoloc.io.recording import SAMPLE_RATE_RANGE_HZ
from echoloc.physics.air import speed_of_sound_m_s
from echoloc.physics.transducer import PRESETS, apply_response, impulse_response
from echoloc.physics.waveform import Carrier, Waveform, waveform_by_name
from echoloc.sim.receiver import AdcSpec, GainSpec, SignalKind, check_signal_kind, output_samples
from echoloc.sim.reflectors import Reflector


@dataclass(frozen=True, eq=False)
class Array:
    """Transducer positions in the sensor frame, m: (n_tx, 3) and (n_rx, 3).

    ``transmitter_axes`` and ``receiver_axes`` are the unit boresight vectors (None:
    every transducer faces +z); they matter only with a transducer model.
    """

    transmitters_m: NDArray[np.float64]
    receivers_m: NDArray[np.float64]
    transmitter_axes: NDArray[np.float64] | None = None
    receiver_axes: NDArray[np.float64] | None = None

    def __post_init__(self) -> None:
        for name in ("transmitters_m", "receivers_m"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.ndim != 2 or value.shape[1] != 3 or value.shape[0] == 0:
                raise SceneError(f"array {name} must have shape (n, 3), got {value.shape}")
            if not np.all(np.isfinite(value)):
                raise SceneError(f"array {name} has non-finite coordinates")
            object.__setattr__(self, name, value)
        for name, positions in (("transmitter_axes", "transmitters_m"), ("receiver_axes", "receivers_m")):
            axes = getattr(self, name)
            if axes is None:
                continue
            axes = np.asarray(axes, dtype=float)
            count = len(getattr(self, positions))
            if axes.shape != (count, 3):
                raise SceneError(f"array {name} must have shape ({count}, 3), got {axes.shape}")
            norms = np.linalg.norm(axes, axis=1)
            if not (np.all(np.isfinite(axes)) and np.all(norms > 0)):
                raise SceneError(f"array {name} must be finite, non-zero vectors")
            object.__setattr__(self, name, axes / norms[:, None])

    def axes(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Unit boresights of transmitters and receivers (+z where not given)."""
        up = np.array([0.0, 0.0, 1.0])
        tx = (
            self.transmitter_axes
            if self.transmitter_axes is not None
            else np.tile(up, (len(self.transmitters_m), 1))
        )
        rx = self.receiver_axes if self.receiver_axes is not None else np.tile(up, (len(self.receivers_m), 1))
        return tx, rx

    def aimed_at(self, point_m: NDArray[np.float64]) -> Array:
        """The same array with every transducer facing ``point_m``."""
        point = np.asarray(point_m, dtype=float)
        return Array(
            self.transmitters_m, self.receivers_m, point - self.transmitters_m, point - self.receivers_m
        )


@dataclass(frozen=True)
class PulseSpec:
    """The emitted pulse: a code or chirp by name (:func:`echoloc.physics.waveform.waveform_by_name`).

    ``code`` is e.g. ``barker13``, ``golay16a``, ``mls7``, ``kasami6:2``, ``tone16``,
    ``lfm``; codes ride on ``carrier_hz`` with ``cycles_per_bit`` carrier cycles per
    chip; chirps sweep ``chirp_bandwidth_hz`` in ``chirp_duration_s``.
    """

    code: str = "barker13"
    carrier_hz: float = 50e3
    cycles_per_bit: int = 4
    carrier: Carrier = "sine"
    chirp_bandwidth_hz: float = 20e3
    chirp_duration_s: float = 1e-3


@dataclass(frozen=True)
class RandomReflectors:
    """Draw ``count`` (an inclusive range) point reflectors uniformly in a box per frame.

    The box is in the sensor frame of each frame (the reflectors move with the sensor).
    """

    count: tuple[int, int] = (1, 5)
    x_m: tuple[float, float] = (-0.5, 0.5)
    y_m: tuple[float, float] = (-0.5, 0.5)
    z_m: tuple[float, float] = (0.2, 1.2)
    strength: tuple[float, float] = (1.0, 1.0)


@dataclass(frozen=True)
class AirDrift:
    """How the air changes during a recording.

    Temperature and relative humidity drift linearly with time; ``turbulence`` is the
    relative standard deviation of a random speed-of-sound error drawn anew each
    frame and shared by every path of that frame (slow air movement, thermal plumes).
    """

    temperature_c_per_s: float = 0.0
    relative_humidity_per_s: float = 0.0
    turbulence: float = 0.0

    def __post_init__(self) -> None:
        for name in ("temperature_c_per_s", "relative_humidity_per_s", "turbulence"):
            _finite(f"air.{name}", getattr(self, name))
        if not 0 <= self.turbulence < 0.1:
            raise SceneError(f"air.turbulence must be a relative std in [0, 0.1), got {self.turbulence}")


@dataclass(frozen=True)
class RingDown:
    """The transmitter's ring-down that every receiver records at the start of a frame.

    ``level`` is the peak of the ring-down at each receiver relative to the emitted
    pulse's peak (electrical and mechanical crosstalk; real heads reach 10-100, far
    above any echo). The ringing is the drive through a resonator at the carrier whose
    envelope decays as ``exp(-t / decay_s)`` after the drive stops. ``direct_path``
    adds the acoustic wave that travels straight from the transmitter to each receiver
    (weighted by both beams at 90° off boresight for a flat head).

    ``levels``, if given, is the peak per receiver instead (one value per receiver, same
    units as ``level``, which must then be 0): a monostatic chip records its own
    transmitter's ring-down at its full level while the other receivers of the head see
    only electrical cross-talk of the drive, tens of times weaker.
    """

    level: float = 0.0
    decay_s: float = 0.3e-3
    direct_path: bool = False
    levels: tuple[float, ...] | None = None

    def __post_init__(self) -> None:
        _finite("ring_down.level", self.level)
        _finite("ring_down.decay_s", self.decay_s)
        if self.level < 0:
            raise SceneError(f"ring_down.level must be >= 0, got {self.level}")
        if not self.decay_s > 0:
            raise SceneError(f"ring_down.decay_s must be > 0, got {self.decay_s}")
        if self.levels is not None:
            levels = tuple(self.levels)
            for value in levels:
                _finite("ring_down.levels", value)
                if value < 0:
                    raise SceneError(f"ring_down.levels must all be >= 0, got {list(levels)}")
            if not levels:
                raise SceneError("ring_down.levels must name one level per receiver, got []")
            if self.level != 0:
                raise SceneError("ring_down.level and ring_down.levels exclude each other")
            object.__setattr__(self, "levels", tuple(float(v) for v in levels))

    @property
    def active(self) -> bool:
        """Whether any receiver records a ring-down (a level above 0 anywhere)."""
        return self.level > 0 or (self.levels is not None and max(self.levels) > 0)

    def receiver_levels(self, n_rx: int) -> NDArray[np.float64]:
        """Ring-down peak at each of ``n_rx`` receivers, relative to the emitted pulse's peak, (n_rx,)."""
        if self.levels is None:
            return np.full(n_rx, float(self.level))
        if len(self.levels) != n_rx:
            raise SceneError(f"ring_down.levels names {len(self.levels)} levels for {n_rx} receivers")
        return np.array(self.levels, dtype=float)


@dataclass(frozen=True)
class ReceiverSpec:
    """The receiver chain after the transducer, in the order the signal meets it.

    1. The ADC samples at ``adc_rate_hz`` (default: the scene's ``sample_rate_hz``);
       white noise is scaled so that its standard deviation is the scene's noise
       level once decimated to ``sample_rate_hz``; ``noise = "band"`` passes it through
       the receiver transducer's band first (same standard deviation).
    2. The amplifier applies ``gain`` (time-varying gain, TVG).
    3. The ADC clips and quantises (``adc``; None: an ideal converter).
    4. The samples are decimated to ``sample_rate_hz`` (the report: 5 MHz to 200 kHz).
    5. They are recorded as ``signal_kind`` at ``output_rate_hz`` (default
       ``sample_rate_hz``): ``rf``, ``iq`` (complex baseband) or ``envelope`` (the
       magnitude a ToF chip reports, typically at ~20 kHz).

    A ToF chip demodulates to complex baseband and decimates with a CIC filter:
    ``baseband_filter_s`` > 0 (envelope or iq only) passes the baseband at
    ``sample_rate_hz`` through ``baseband_filter_order`` cascaded moving averages, each
    ``baseband_filter_s`` long (causal: it delays an echo by about
    ``order * baseband_filter_s / 2``), before it is resampled to ``output_rate_hz``.
    ``record_waveform = False`` (envelope only) leaves the recording without a
    ``waveform``, as a chip that does not report its pulse (docs/FORMATS.md allows that for
    envelope data; the echo's delay is then a calibration constant).
    """

    signal_kind: SignalKind = "rf"
    output_rate_hz: float | None = None
    adc_rate_hz: float | None = None
    noise: Literal["white", "band"] = "white"
    gain: GainSpec = field(default_factory=GainSpec)
    adc: AdcSpec | None = None
    baseband_filter_s: float = 0.0
    baseband_filter_order: int = 1
    record_waveform: bool = True

    def __post_init__(self) -> None:
        if self.signal_kind not in ("rf", "envelope", "iq"):
            raise SceneError(
                f"receiver.signal_kind must be 'rf', 'envelope' or 'iq', got {self.signal_kind!r}"
            )
        if self.noise not in ("white", "band"):
            raise SceneError(f"receiver.noise must be 'white' or 'band', got {self.noise!r}")
        for name in ("output_rate_hz", "adc_rate_hz"):
            value = getattr(self, name)
            if value is not None and not (math.isfinite(value) and value > 0):
                raise SceneError(f"receiver.{name} must be > 0, got {value}")
        _finite("receiver.baseband_filter_s", self.baseband_filter_s)
        if self.baseband_filter_s < 0:
            raise SceneError(f"receiver.baseband_filter_s must be >= 0, got {self.baseband_filter_s}")
        order = self.baseband_filter_order
        if isinstance(order, bool) or not isinstance(order, int) or order < 1:
            raise SceneError(f"receiver.baseband_filter_order must be a whole number >= 1, got {order!r}")
        if self.baseband_filter_s > 0 and self.signal_kind == "rf":
            raise SceneError("receiver.baseband_filter_s needs signal_kind 'envelope' or 'iq'")
        if not self.record_waveform and self.signal_kind != "envelope":
            raise SceneError(
                "receiver.record_waveform = false needs signal_kind 'envelope' (rf and iq recordings "
                "must carry their waveform)"
            )


@dataclass(frozen=True, eq=False)
class SensorMotion:
    """The sensor head's motion: constant velocity and rate, plus an optional pan/tilt scan.

    Velocity (m/s) and angular velocity (deg/s) are in the world frame, which is the
    sensor frame at time 0. A mechanical scan (the report's pan/tilt "reversed
    joystick") swings the head about its own ``y`` axis (pan; ``y`` points down in the
    sensor frame, so pan turns the boresight left and right) by up to ``pan_deg`` and
    about its own ``x`` axis (tilt) by up to ``tilt_deg``, as triangle waves of period
    ``scan_period_s`` (pan starts at 0 going positive, tilt a quarter period behind).
    The world-from-sensor pose at time ``t`` is
    ``R(t) = Rot(angular_velocity * t) · Rot_y(pan(t)) · Rot_x(tilt(t))`` and
    ``t_m(t) = velocity * t``.
    """

    velocity_m_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    angular_velocity_deg_s: NDArray[np.float64] = field(default_factory=lambda: np.zeros(3))
    pan_deg: float = 0.0
    tilt_deg: float = 0.0
    scan_period_s: float = 1.0

    def __post_init__(self) -> None:
        for name in ("velocity_m_s", "angular_velocity_deg_s"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != (3,) or not np.all(np.isfinite(value)):
                raise SceneError(f"motion.{name} must be a finite [x, y, z], got {value.tolist()}")
            object.__setattr__(self, name, value)
        for name in ("pan_deg", "tilt_deg"):
            value = getattr(self, name)
            if not (math.isfinite(value) and 0.0 <= value <= 90.0):
                raise SceneError(f"motion.{name} must be between 0 and 90 degrees, got {value}")
        if not (math.isfinite(self.scan_period_s) and self.scan_period_s > 0):
            raise SceneError(f"motion.scan_period_s must be > 0, got {self.scan_period_s}")

    @property
    def moving(self) -> bool:
        return bool(
            np.any(self.velocity_m_s)
            or np.any(self.angular_velocity_deg_s)
            or self.pan_deg > 0
            or self.tilt_deg > 0
        )

    def scan_angles_deg(
        self, times_s: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Pan and tilt (deg) of the scan at ``times_s``: triangle waves, tilt a quarter period late."""
        phase = np.asarray(times_s, dtype=float) / self.scan_period_s
        return self.pan_deg * _triangle(phase), self.tilt_deg * _triangle(phase - 0.25)

    def _rotations(self, times_s: NDArray[np.float64]) -> Rotation:
        times = np.asarray(times_s, dtype=float)
        rotation = Rotation.from_rotvec(np.radians(self.angular_velocity_deg_s)[None, :] * times[:, None])
        if self.pan_deg > 0 or self.tilt_deg > 0:
            pan, tilt = self.scan_angles_deg(times)
            rotation = rotation * Rotation.from_euler("YX", np.column_stack([pan, tilt]), degrees=True)
        return rotation

    def poses(self, times_s: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """World-from-sensor rotations (n, 3, 3) and translations (n, 3) at ``times_s``."""
        times = np.asarray(times_s, dtype=float)
        return self._rotations(times).as_matrix().reshape(-1, 3, 3), self.velocity_m_s[None, :] * times[
            :, None
        ]

    def pose_quaternions(self, times_s: NDArray[np.float64]) -> NDArray[np.float64]:
        """Poses as rows ``[x, y, z, qx, qy, qz, qw]`` (ROS order), world from sensor."""
        times = np.asarray(times_s, dtype=float)
        quaternion = self._rotations(times).as_quat().reshape(-1, 4)
        return np.hstack([self.velocity_m_s[None, :] * times[:, None], quaternion])


def _triangle(phase: NDArray[np.float64]) -> NDArray[np.float64]:
    """Triangle wave of period 1: 0 at phase 0, +1 at 1/4, 0 at 1/2, -1 at 3/4."""
    return np.asarray(2.0 / np.pi * np.arcsin(np.sin(2.0 * np.pi * phase)), dtype=float)


Firing = Literal["sequential", "simultaneous"]

MAX_FRAME_VALUES = 1 << 24
"""The most values a frame may hold at the ADC, n_rx x n_samples x (ADC rate / sample
rate), 16.8 M (134 MB as float64): the simulator holds a few copies of a frame at once."""

SNR_DB_RANGE = (-200.0, 400.0)
"""The signal-to-noise ratios a scene may ask for, dB: beyond them the noise's amplitude
under- or overflows float64 (snr_db = -2^63 divided by zero)."""

AIR_TEMPERATURE_RANGE_C = (-100.0, 200.0)
"""The air temperatures a scene may give, °C: wider than any air a sensor works in (the
humidity and absorption formulas hold over less); 1e307 °C overflowed them."""

FRAME_RATE_HZ_RANGE = (1e-6, 1e6)
"""The frame rates a scene may ask for, Hz (frame times must stay finite and distinct)."""


@dataclass(frozen=True, eq=False)
class Scene:
    """A complete simulation set-up.

    Reflectors: ``reflector_positions_m`` (n, 3) with ``reflector_strengths`` (n,) are
    fixed point reflectors (echo amplitude ``strength / (r_tx r_rx)`` times the pulse,
    strength in m); ``objects`` holds any :mod:`echoloc.sim.reflectors` kind (points,
    spheres, finite planes, edges, corners), each possibly moving; ``random`` adds
    point reflectors drawn anew each frame. ``max_order = 2`` adds the double
    reflections between them (the "ghosts" localisation must reject).

    ``path_jitter_m`` is the standard deviation of an independent random error on
    every path (transducer jitter); ``drift.turbulence`` is the shared per-frame one.
    ``timing_jitter_s`` is the receiving chip's timing jitter, s: every echo of a
    receiver in a frame arrives later by one delay drawn from ``N(0, sigma²)`` for that
    receiver and frame (a ToF chip's sampling start wanders against its transmit).
    One sigma for every receiver, or a tuple of one per receiver. It moves the echoes
    only; the frame start (ring-down, cross-talk, direct path) stays where it is.
    ``snr_db`` follows the module's noise convention; None means no noise.

    Transmitters: with several, ``firing = "sequential"`` fires one per frame in turn
    (frame k fires transmitter k mod n_tx) and ``"simultaneous"`` fires all at once,
    which needs a different code per transmitter (``transmitter_codes``).
    """

    array: Array
    pulse: PulseSpec = field(default_factory=PulseSpec)
    sample_rate_hz: float = 200e3
    n_samples: int = 2400
    frame_rate_hz: float = 100.0
    temperature_c: float = 20.0
    relative_humidity: float = 0.0
    reflector_positions_m: NDArray[np.float64] = field(default_factory=lambda: np.zeros((0, 3)))
    reflector_strengths: NDArray[np.float64] = field(default_factory=lambda: np.zeros(0))
    objects: tuple[Reflector, ...] = ()
    random: RandomReflectors | None = None
    snr_db: float | None = None
    path_jitter_m: float = 0.0
    timing_jitter_s: float | tuple[float, ...] = 0.0
    seed: int | None = 0
    transducer: str | None = None
    absorption: bool = False
    max_order: int = 1
    drift: AirDrift = field(default_factory=AirDrift)
    ring_down: RingDown = field(default_factory=RingDown)
    receiver: ReceiverSpec = field(default_factory=ReceiverSpec)
    motion: SensorMotion = field(default_factory=SensorMotion)
    firing: Firing = "sequential"
    transmitter_codes: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        positions = np.asarray(self.reflector_positions_m, dtype=float).reshape(-1, 3)
        strengths = np.asarray(self.reflector_strengths, dtype=float).reshape(-1)
        if len(positions) != len(strengths):
            raise SceneError(f"{len(positions)} reflector positions but {len(strengths)} strengths")
        if not (np.all(np.isfinite(positions)) and np.all(np.isfinite(strengths))):
            raise SceneError("reflector positions and strengths must be finite")
        object.__setattr__(self, "reflector_positions_m", positions)
        object.__setattr__(self, "reflector_strengths", strengths)
        object.__setattr__(self, "objects", tuple(self.objects))
        low_hz, high_hz = SAMPLE_RATE_RANGE_HZ
        if not low_hz <= self.sample_rate_hz <= high_hz:  # NaN fails too
            raise SceneError(
                f"acquisition.sample_rate_hz must lie in {low_hz:g}..{high_hz:g} Hz, "
                f"got {self.sample_rate_hz:g}"
            )
        if self.n_samples < 1:
            raise SceneError(f"n_samples must be >= 1, got {self.n_samples}")
        if self.n_samples > MAX_FRAME_VALUES:
            raise SceneError(
                f"acquisition.n_samples must be at most {MAX_FRAME_VALUES}, got {self.n_samples}"
            )
        if not (math.isfinite(self.frame_rate_hz) and self.frame_rate_hz > 0):
            raise SceneError(f"frame_rate_hz must be > 0, got {self.frame_rate_hz}")
        low, high = FRAME_RATE_HZ_RANGE
        if not low <= self.frame_rate_hz <= high:
            raise SceneError(
                f"acquisition.frame_rate_hz must lie in {low:g}..{high:g} Hz, got {self.frame_rate_hz:g}"
            )
        if self.snr_db is not None:
            _finite("noise.snr_db", self.snr_db)
            low, high = SNR_DB_RANGE
            if not low <= self.snr_db <= high:
                raise SceneError(f"noise.snr_db must lie in {low:g}..{high:g} dB, got {self.snr_db:g}")
        if not self.temperature_c > -273.15:
            raise SceneError(f"air.temperature_c must be above absolute zero, got {self.temperature_c}")
        low, high = AIR_TEMPERATURE_RANGE_C
        if not low <= self.temperature_c <= high:
            raise SceneError(
                f"air.temperature_c must lie in {low:g}..{high:g} °C, got {self.temperature_c:g}"
            )
        if not 0 <= self.relative_humidity <= 1:
            raise SceneError(
                f"air.relative_humidity must be a fraction in 0..1, got {self.relative_humidity}"
            )
        if self.path_jitter_m < 0:
            raise SceneError(f"path_jitter_m must be >= 0, got {self.path_jitter_m}")
        self._check_timing_jitter()
        if self.max_order not in (1, 2):
            raise SceneError(f"max_order must be 1 or 2, got {self.max_order}")
        empty = self.random is None and len(positions) == 0 and not self.objects
        if empty and not (self.ring_down.direct_path or self.ring_down.active):
            # An empty scene records only noise; with a ring-down or direct path it is
            # the background (or the DIRECT template) a user may want.
            raise SceneError("the scene has no reflectors: give [[reflectors]] or [random_reflectors]")
        if self.random is not None:
            low, high = self.random.count
            if not 0 <= low <= high:
                raise SceneError(
                    f"random_reflectors.count must be [min, max] with 0 <= min <= max, got {[low, high]}"
                )
        if self.seed is not None and self.seed < 0:
            raise SceneError(f"seed must be >= 0, got {self.seed}")
        n_tx = len(self.array.transmitters_m)
        if self.firing not in ("sequential", "simultaneous"):
            raise SceneError(f"array.firing must be 'sequential' or 'simultaneous', got {self.firing!r}")
        if self.transmitter_codes is not None:
            object.__setattr__(self, "transmitter_codes", tuple(self.transmitter_codes))
            if len(self.transmitter_codes) != n_tx:
                raise SceneError(
                    f"pulse.codes names {len(self.transmitter_codes)} codes for {n_tx} transmitters"
                )
        if self.firing == "simultaneous" and n_tx > 1:
            codes = self.codes()
            if len({code.strip().lower() for code in codes}) < n_tx:
                raise SceneError(
                    "simultaneous firing needs a different code per transmitter (pulse.codes), "
                    f"got {list(codes)}"
                )
        transducers = np.vstack([self.array.transmitters_m, self.array.receivers_m])
        for i, point in enumerate(positions):
            if np.min(np.linalg.norm(transducers - point, axis=1)) < 1e-3:
                raise SceneError(f"reflector {i} at {point.tolist()} sits on a transducer")
            if point[2] <= 0:
                raise SceneError(
                    f"reflector {i} at {point.tolist()} is not in front of the array (z must be > 0)"
                )
        if self.random is not None and self.random.z_m[0] <= 0:
            raise SceneError(
                f"random_reflectors.z_m must lie in front of the array (> 0), got {list(self.random.z_m)}"
            )
        if self.transducer is not None and self.transducer not in PRESETS:
            raise SceneError(f"transducer {self.transducer!r} is not one of {', '.join(PRESETS)}")
        if self.receiver.noise == "band" and self.transducer is None:
            raise SceneError("receiver.noise = 'band' needs a transducer model ([transducers] model)")
        adc_rate = self.adc_rate_hz
        if not adc_rate <= SAMPLE_RATE_RANGE_HZ[1]:
            raise SceneError(
                f"receiver.adc_rate_hz must be at most {SAMPLE_RATE_RANGE_HZ[1]:g} Hz, got {adc_rate:g}"
            )
        if adc_rate < self.sample_rate_hz:
            raise SceneError(
                f"receiver.adc_rate_hz ({adc_rate:g}) must be >= acquisition.sample_rate_hz "
                f"({self.sample_rate_hz:g})"
            )
        ratio = adc_rate / self.sample_rate_hz
        if abs(ratio - round(ratio)) > 1e-9 * ratio:
            raise SceneError(
                f"receiver.adc_rate_hz ({adc_rate:g}) must be a whole multiple of acquisition.sample_rate_hz "
                f"({self.sample_rate_hz:g}): the ADC's samples are decimated by an integer factor"
            )
        n_rx = len(self.array.receivers_m)
        frame_values = n_rx * self.n_samples * round(ratio)
        if frame_values > MAX_FRAME_VALUES:
            raise SceneError(
                f"acquisition.n_samples: a frame of {n_rx} receivers x {self.n_samples} samples "
                f"x {round(ratio)} (ADC decimation) is {frame_values} values, more than the "
                f"{MAX_FRAME_VALUES} a frame may hold"
            )
        frame_s = self.n_samples / self.sample_rate_hz
        if self.receiver.baseband_filter_s > frame_s:
            raise SceneError(
                f"receiver.baseband_filter_s ({self.receiver.baseband_filter_s:g} s) must be at most "
                f"a frame's duration ({frame_s:g} s)"
            )
        if self.output_rate_hz > self.sample_rate_hz:
            raise SceneError(
                f"receiver.output_rate_hz ({self.output_rate_hz:g}) must be <= acquisition.sample_rate_hz "
                f"({self.sample_rate_hz:g})"
            )
        carrier_hz = self.pulse.carrier_hz
        if not (math.isfinite(carrier_hz) and carrier_hz > 0):
            raise SceneError(f"pulse.carrier_hz must be > 0, got {carrier_hz:g}")
        if not self.sample_rate_hz > 2 * carrier_hz:
            raise SceneError(
                f"pulse.carrier_hz ({carrier_hz:g}) must be below half acquisition.sample_rate_hz "
                f"({self.sample_rate_hz:g})"
            )
        try:
            # The receiver chain's own checks, run now so that the message names the key.
            output_samples(self.n_samples, self.sample_rate_hz, self.output_rate_hz)
            check_signal_kind(
                self.receiver.signal_kind, self.pulse.carrier_hz, self.sample_rate_hz, self.output_rate_hz
            )
        except SceneError as error:
            raise SceneError(f"receiver.output_rate_hz: {error}") from None
        try:
            self.ring_down.receiver_levels(len(self.array.receivers_m))
        except SceneError as error:
            raise SceneError(f"{error} (the array has {len(self.array.receivers_m)})") from None
        self._check_speeds()
        # Raises early for an impossible pulse.
        for transmitter in range(n_tx):
            self.waveform(transmitter)

    def _check_timing_jitter(self) -> None:
        """``timing_jitter_s``: one finite sigma >= 0, or one per receiver."""
        value = self.timing_jitter_s
        n_rx = len(self.array.receivers_m)
        if isinstance(value, tuple | list):
            sigmas = tuple(value)
            if len(sigmas) != n_rx:
                raise SceneError(f"noise.timing_jitter_s names {len(sigmas)} values for {n_rx} receivers")
            object.__setattr__(self, "timing_jitter_s", sigmas)
        else:
            sigmas = (value,)
        for sigma in sigmas:
            _finite("noise.timing_jitter_s", sigma)
            if sigma < 0:
                raise SceneError(f"noise.timing_jitter_s must be >= 0, got {sigma}")

    def timing_jitter_per_receiver_s(self) -> NDArray[np.float64]:
        """Standard deviation of each receiver's per-frame timing jitter, s, (n_rx,)."""
        return np.broadcast_to(
            np.asarray(self.timing_jitter_s, dtype=float), (len(self.array.receivers_m),)
        ).copy()

    def _check_speeds(self) -> None:
        """Every reflector and the head must move slower than sound (Doppler needs c - v > 0)."""
        c = self.speed_of_sound_m_s * (1 - 5 * self.drift.turbulence)
        head = float(np.linalg.norm(self.motion.velocity_m_s))
        for i, obj in enumerate(self.objects):
            speed = float(np.linalg.norm(obj.velocity_m_s)) + head
            if speed >= 0.5 * c:
                raise SceneError(
                    f"reflector {i} moves at {speed:g} m/s relative to the head; the simulator needs "
                    f"less than half the speed of sound ({0.5 * c:.0f} m/s)"
                )
        if head >= 0.5 * c:
            raise SceneError(f"motion.velocity_m_s ({head:g} m/s) must be below half the speed of sound")

    # --- derived values --------------------------------------------------------

    @property
    def adc_rate_hz(self) -> float:
        """Rate at which the ADC samples (before decimation to ``sample_rate_hz``)."""
        return self.receiver.adc_rate_hz or self.sample_rate_hz

    @property
    def output_rate_hz(self) -> float:
        """Rate of the recorded samples (``sample_rate_hz`` unless the receiver says otherwise)."""
        return self.receiver.output_rate_hz or self.sample_rate_hz

    @property
    def frame_duration_s(self) -> float:
        return self.n_samples / self.sample_rate_hz

    def codes(self) -> tuple[str, ...]:
        """The code each transmitter emits."""
        if self.transmitter_codes is not None:
            return self.transmitter_codes
        return (self.pulse.code,) * len(self.array.transmitters_m)

    def waveform(self, transmitter: int = 0, sample_rate_hz: float | None = None) -> Waveform:
        """The sampled pulse ``transmitter`` emits (peak amplitude 1)."""
        try:
            return waveform_by_name(
                self.codes()[transmitter],
                carrier_hz=self.pulse.carrier_hz,
                cycles_per_bit=self.pulse.cycles_per_bit,
                sample_rate_hz=sample_rate_hz or self.sample_rate_hz,
                carrier=self.pulse.carrier,
                chirp_bandwidth_hz=self.pulse.chirp_bandwidth_hz,
                chirp_duration_s=self.pulse.chirp_duration_s,
            )
        except WaveformError as error:
            key = "pulse.code" if self.transmitter_codes is None else f"pulse.codes[{transmitter}]"
            raise SceneError(f"{key} {self.codes()[transmitter]!r}: {error}") from None

    def returned_pulse(
        self, transmitter: int = 0, sample_rate_hz: float | None = None
    ) -> NDArray[np.float64]:
        """The pulse as an ideal point reflector returns it at unit gain (the SENT template).

        The emitted pulse through the transmitter and receiver responses in series,
        cut where its ringing has fallen below 1e-4 of its peak; without a transducer
        model, the emitted pulse itself.
        """
        rate = sample_rate_hz or self.sample_rate_hz
        pulse = self.waveform(transmitter, rate).samples
        if self.transducer is None:
            return pulse
        model = PRESETS[self.transducer]
        ringing = len(impulse_response(model, rate))
        returned = apply_response(np.concatenate([pulse, np.zeros(ringing)]), model, rate)
        significant = np.flatnonzero(np.abs(returned) >= 1e-4 * np.max(np.abs(returned)))
        return np.asarray(returned[: significant[-1] + 1])

    @property
    def speed_of_sound_m_s(self) -> float:
        """Speed of sound at the start of the recording."""
        return float(speed_of_sound_m_s(self.temperature_c, self.relative_humidity))


def _finite(where: str, value: float) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise SceneError(f"{where} must be a finite number, got {value!r}")


REPORT_ARRAY = Array(
    transmitters_m=np.array([[0.0, 0.0, 0.0]]),
    receivers_m=np.array([[0.25, 0.0, 0.0], [-0.25, 0.0, 0.0], [0.0, 0.25, 0.0], [0.0, -0.25, 0.0]]),
)
"""The report's sensor head: transmitter at the origin, receivers 0.25 m away on x and y."""


def _ball_at(range_m: float, x_m: float, y_m: float) -> list[float]:
    return [x_m, y_m, float(np.sqrt(range_m**2 - x_m**2 - y_m**2))]


def default_scene() -> Scene:
    """The report's set-up with its table 4.3 balls: ranges 580, 596 and 665 mm.

    Barker-13 × 4 cycles at 50 kHz, 200 kHz sampling, 20 °C dry air. The first two
    balls are 16 mm apart in range (the code's range resolution is 13.7 mm). The
    noise gives the nearest ball a per-sample SNR of about 13, as in the report.
    """
    return Scene(
        array=REPORT_ARRAY,
        reflector_positions_m=np.array(
            [_ball_at(0.580, 0.010, -0.005), _ball_at(0.596, 0.030, 0.020), _ball_at(0.665, -0.090, 0.120)]
        ),
        reflector_strengths=np.array([1.0, 1.0, 1.0]),
        snr_db=13.5,
        seed=2026,
    )
