"""Scenes: the sensor head, the emitted pulse, the air and the reflectors.

A :class:`Scene` is everything :func:`echoloc.simulate.simulate` needs. It is read
from TOML by :func:`load_scene` (every key checked; an unknown key is an error that
names it) or built in code; :func:`default_scene` is the report's set-up.

Noise convention (documented once, used everywhere): ``snr_db`` is the per-sample
amplitude signal-to-noise ratio, ``20 log10(A / sigma)``, of the echo from a
unit-strength point reflector with 1 m from the transmitter and 1 m to the
receiver, where ``A`` is the emitted pulse's peak amplitude (1) and ``sigma`` the
standard deviation of the white noise added to every sample. Closer or stronger
reflectors have proportionally higher SNR: the noise is the receiver's, not the
scene's.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from echoloc.air import speed_of_sound_m_s
from echoloc.errors import EchoLocError, SceneError
from echoloc.transducer import PRESETS, apply_response, impulse_response
from echoloc.waveform import BARKER_CODES, Carrier, Waveform, barker_waveform


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
    """The emitted code: a Barker sequence of ``barker_length`` on a carrier."""

    barker_length: int = 13
    carrier_hz: float = 50e3
    cycles_per_bit: int = 4
    carrier: Carrier = "sine"


@dataclass(frozen=True)
class RandomReflectors:
    """Draw ``count`` (an inclusive range) point reflectors uniformly in a box per frame."""

    count: tuple[int, int] = (1, 5)
    x_m: tuple[float, float] = (-0.5, 0.5)
    y_m: tuple[float, float] = (-0.5, 0.5)
    z_m: tuple[float, float] = (0.2, 1.2)
    strength: tuple[float, float] = (1.0, 1.0)


@dataclass(frozen=True, eq=False)
class Scene:
    """A complete simulation set-up.

    ``reflector_positions_m`` (n, 3) and ``reflector_strengths`` (n,) are fixed
    point reflectors; a reflector's echo amplitude is ``strength / (r_tx r_rx)``
    times the emitted pulse (strength in m²). ``random`` adds reflectors drawn anew
    each frame. ``path_jitter_m`` is the standard deviation of an independent random
    error on every transmitter-reflector-receiver path (air turbulence, transducer
    jitter). ``snr_db`` follows the module's noise convention; None means no noise.
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
    random: RandomReflectors | None = None
    snr_db: float | None = None
    path_jitter_m: float = 0.0
    seed: int | None = 0
    transducer: str | None = None
    absorption: bool = False

    def __post_init__(self) -> None:
        positions = np.asarray(self.reflector_positions_m, dtype=float).reshape(-1, 3)
        strengths = np.asarray(self.reflector_strengths, dtype=float).reshape(-1)
        if len(positions) != len(strengths):
            raise SceneError(f"{len(positions)} reflector positions but {len(strengths)} strengths")
        if not (np.all(np.isfinite(positions)) and np.all(np.isfinite(strengths))):
            raise SceneError("reflector positions and strengths must be finite")
        object.__setattr__(self, "reflector_positions_m", positions)
        object.__setattr__(self, "reflector_strengths", strengths)
        if not self.sample_rate_hz > 0:
            raise SceneError(f"sample_rate_hz must be > 0, got {self.sample_rate_hz}")
        if self.n_samples < 1:
            raise SceneError(f"n_samples must be >= 1, got {self.n_samples}")
        if not self.frame_rate_hz > 0:
            raise SceneError(f"frame_rate_hz must be > 0, got {self.frame_rate_hz}")
        if not self.temperature_c > -273.15:
            raise SceneError(f"air.temperature_c must be above absolute zero, got {self.temperature_c}")
        if not 0 <= self.relative_humidity <= 1:
            raise SceneError(
                f"air.relative_humidity must be a fraction in 0..1, got {self.relative_humidity}"
            )
        if self.path_jitter_m < 0:
            raise SceneError(f"path_jitter_m must be >= 0, got {self.path_jitter_m}")
        if self.random is None and len(positions) == 0:
            raise SceneError("the scene has no reflectors: give [[reflectors]] or [random_reflectors]")
        if self.random is not None:
            low, high = self.random.count
            if not 0 <= low <= high:
                raise SceneError(
                    f"random_reflectors.count must be [min, max] with 0 <= min <= max, got {[low, high]}"
                )
        if self.seed is not None and self.seed < 0:
            raise SceneError(f"seed must be >= 0, got {self.seed}")
        if len(self.array.transmitters_m) > 1:
            raise SceneError(
                f"the simulator fires one transmitter; this scene has {len(self.array.transmitters_m)}"
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
        # Raises early for an impossible pulse.
        self.waveform()

    def waveform(self) -> Waveform:
        """The sampled emitted pulse (peak amplitude 1)."""
        return barker_waveform(
            self.pulse.barker_length,
            carrier_hz=self.pulse.carrier_hz,
            cycles_per_bit=self.pulse.cycles_per_bit,
            sample_rate_hz=self.sample_rate_hz,
            carrier=self.pulse.carrier,
        )

    def returned_pulse(self) -> NDArray[np.float64]:
        """The pulse as an ideal point reflector returns it at unit gain (the SENT template).

        The emitted pulse through the transmitter and receiver responses in series,
        cut where its ringing has fallen below 1e-4 of its peak; without a transducer
        model, the emitted pulse itself.
        """
        pulse = self.waveform().samples
        if self.transducer is None:
            return pulse
        model = PRESETS[self.transducer]
        ringing = len(impulse_response(model, self.sample_rate_hz))
        returned = apply_response(np.concatenate([pulse, np.zeros(ringing)]), model, self.sample_rate_hz)
        significant = np.flatnonzero(np.abs(returned) >= 1e-4 * np.max(np.abs(returned)))
        return np.asarray(returned[: significant[-1] + 1])

    @property
    def speed_of_sound_m_s(self) -> float:
        return float(speed_of_sound_m_s(self.temperature_c, self.relative_humidity))


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


# --- TOML --------------------------------------------------------------------------

_SECTIONS: dict[str, set[str]] = {
    "array": {"transmitters_m", "receivers_m", "transmitter_axes", "receiver_axes", "aim_at_m"},
    "transducers": {"model", "absorption"},
    "pulse": {"code", "carrier_hz", "cycles_per_bit", "carrier"},
    "acquisition": {"sample_rate_hz", "n_samples", "frame_rate_hz"},
    "air": {"temperature_c", "relative_humidity"},
    "noise": {"snr_db", "path_jitter_m"},
    "random_reflectors": {"count", "x_m", "y_m", "z_m", "strength"},
}
_REFLECTOR_KEYS = {"position_m", "strength"}
_TOP_LEVEL = {*_SECTIONS, "reflectors", "seed"}


def _number(where: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise SceneError(f"{where} must be a finite number, got {value!r}")
    return float(value)


def _pair(where: str, value: Any) -> tuple[float, float]:
    if not isinstance(value, list) or len(value) != 2:
        raise SceneError(f"{where} must be [min, max], got {value!r}")
    low, high = (_number(where, v) for v in value)
    if low > high:
        raise SceneError(f"{where} must be [min, max] with min <= max, got {value!r}")
    return low, high


def _points(where: str, value: Any) -> NDArray[np.float64]:
    if not isinstance(value, list) or not all(isinstance(p, list) and len(p) == 3 for p in value):
        raise SceneError(f"{where} must be a list of [x, y, z] points, got {value!r}")
    return np.array([[_number(where, c) for c in p] for p in value], dtype=float)


def _check_keys(where: str, table: Mapping[str, Any], allowed: set[str]) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise SceneError(f"{where}: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(allowed))})")


def scene_from_dict(data: Mapping[str, Any], source: str = "<scene>") -> Scene:
    """Build a :class:`Scene` from a parsed TOML table, checking every key and value."""
    try:
        return _scene_from_dict(data, source)
    except EchoLocError as error:
        message = str(error)
        raise SceneError(message if message.startswith(source) else f"{source}: {message}") from None


def _scene_from_dict(data: Mapping[str, Any], source: str) -> Scene:
    _check_keys("top level", data, _TOP_LEVEL)
    for name, allowed in _SECTIONS.items():
        section = data.get(name, {})
        if not isinstance(section, dict):
            raise SceneError(f"[{name}] must be a table")
        _check_keys(f"[{name}]", section, allowed)
    kwargs: dict[str, Any] = {}

    array = data.get("array", {})
    geometry = Array(
        transmitters_m=_points("array.transmitters_m", array["transmitters_m"])
        if "transmitters_m" in array
        else REPORT_ARRAY.transmitters_m,
        receivers_m=_points("array.receivers_m", array["receivers_m"])
        if "receivers_m" in array
        else REPORT_ARRAY.receivers_m,
        transmitter_axes=_points("array.transmitter_axes", array["transmitter_axes"])
        if "transmitter_axes" in array
        else None,
        receiver_axes=_points("array.receiver_axes", array["receiver_axes"])
        if "receiver_axes" in array
        else None,
    )
    if "aim_at_m" in array:
        if "transmitter_axes" in array or "receiver_axes" in array:
            raise SceneError("array.aim_at_m and explicit array axes exclude each other")
        geometry = geometry.aimed_at(_points("array.aim_at_m", [array["aim_at_m"]])[0])
    kwargs["array"] = geometry

    transducers = data.get("transducers", {})
    if "model" in transducers:
        model = transducers["model"]
        if not isinstance(model, str) or model not in PRESETS:
            raise SceneError(f"transducers.model {model!r} is not one of {', '.join(PRESETS)}")
        kwargs["transducer"] = model
    if "absorption" in transducers:
        if not isinstance(transducers["absorption"], bool):
            raise SceneError(
                f"transducers.absorption must be true or false, got {transducers['absorption']!r}"
            )
        kwargs["absorption"] = transducers["absorption"]

    pulse = data.get("pulse", {})
    code = pulse.get("code", "barker13")
    lengths = {f"barker{n}": n for n in BARKER_CODES}
    if not isinstance(code, str) or code not in lengths:
        raise SceneError(f"pulse.code {code!r} is not one of {', '.join(lengths)}")
    cycles = pulse.get("cycles_per_bit", 4)
    if isinstance(cycles, bool) or not isinstance(cycles, int):
        raise SceneError(f"pulse.cycles_per_bit must be a whole number, got {cycles!r}")
    carrier = pulse.get("carrier", "sine")
    if carrier not in ("sine", "square"):
        raise SceneError(f"pulse.carrier must be 'sine' or 'square', got {carrier!r}")
    kwargs["pulse"] = PulseSpec(
        barker_length=lengths[code],
        carrier_hz=_number("pulse.carrier_hz", pulse.get("carrier_hz", 50e3)),
        cycles_per_bit=cycles,
        carrier=carrier,
    )

    acquisition = data.get("acquisition", {})
    kwargs["sample_rate_hz"] = _number("acquisition.sample_rate_hz", acquisition.get("sample_rate_hz", 200e3))
    n_samples = acquisition.get("n_samples", 2400)
    if isinstance(n_samples, bool) or not isinstance(n_samples, int):
        raise SceneError(f"acquisition.n_samples must be a whole number, got {n_samples!r}")
    kwargs["n_samples"] = n_samples
    kwargs["frame_rate_hz"] = _number("acquisition.frame_rate_hz", acquisition.get("frame_rate_hz", 100.0))

    air = data.get("air", {})
    kwargs["temperature_c"] = _number("air.temperature_c", air.get("temperature_c", 20.0))
    humidity = _number("air.relative_humidity", air.get("relative_humidity", 0.0))
    if not 0 <= humidity <= 1:
        raise SceneError(f"air.relative_humidity must be a fraction in 0..1, got {humidity}")
    kwargs["relative_humidity"] = humidity

    noise = data.get("noise", {})
    if "snr_db" in noise:
        kwargs["snr_db"] = _number("noise.snr_db", noise["snr_db"])
    kwargs["path_jitter_m"] = _number("noise.path_jitter_m", noise.get("path_jitter_m", 0.0))

    reflectors = data.get("reflectors", [])
    if not isinstance(reflectors, list):
        raise SceneError("[[reflectors]] must be an array of tables")
    positions, strengths = [], []
    for i, reflector in enumerate(reflectors):
        where = f"reflectors[{i}]"
        if not isinstance(reflector, dict):
            raise SceneError(f"{where} must be a table")
        _check_keys(where, reflector, _REFLECTOR_KEYS)
        if "position_m" not in reflector:
            raise SceneError(f"{where} needs position_m = [x, y, z]")
        positions.append(_points(f"{where}.position_m", [reflector["position_m"]])[0])
        strengths.append(_number(f"{where}.strength", reflector.get("strength", 1.0)))
    kwargs["reflector_positions_m"] = np.array(positions).reshape(-1, 3)
    kwargs["reflector_strengths"] = np.array(strengths)

    if "random_reflectors" in data:
        table = data["random_reflectors"]
        count = table.get("count", [1, 5])
        if not (
            isinstance(count, list)
            and len(count) == 2
            and all(isinstance(c, int) and not isinstance(c, bool) for c in count)
        ):
            raise SceneError(f"random_reflectors.count must be [min, max] whole numbers, got {count!r}")
        defaults = RandomReflectors()
        kwargs["random"] = RandomReflectors(
            count=(count[0], count[1]),
            x_m=_pair("random_reflectors.x_m", table.get("x_m", list(defaults.x_m))),
            y_m=_pair("random_reflectors.y_m", table.get("y_m", list(defaults.y_m))),
            z_m=_pair("random_reflectors.z_m", table.get("z_m", list(defaults.z_m))),
            strength=_pair("random_reflectors.strength", table.get("strength", list(defaults.strength))),
        )

    seed = data.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise SceneError(f"seed must be a whole number >= 0, got {seed!r}")
    kwargs["seed"] = seed
    return Scene(**kwargs)


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene TOML file."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise SceneError(f"{path}: no such scene file") from None
    except (OSError, UnicodeDecodeError) as error:
        raise SceneError(f"{path}: cannot read scene file ({error})") from None
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"{path}: not valid TOML ({error})") from None
    return scene_from_dict(data, source=str(path))
