"""Scene files: TOML in, a validated :class:`~echoloc.sim.scene.Scene` out.

Every key is checked: an unknown key, a missing one or a value of the wrong kind
raises :class:`~echoloc.errors.SceneError` naming the file, the key and the value.
The README's "Scene files" section lists every key.

Scene presets ship with the package as ``echoloc/scenes/NAME.toml``, some in folders
(``report/ball-fixed``: a scene for each test set-up of the report's chapter 4;
``mapping/room``): :func:`preset_names`, :func:`preset_path`. :func:`load_scene` takes
such a name wherever no file of that name exists, so ``echoloc simulate ch101 -o
out.h5`` simulates the CH101-like head and ``echoloc simulate report/three-balls -o
out.h5`` the report's three balls.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from echoloc._toml import tomllib
from echoloc.errors import EchoLocError, SceneError, read_text_input, scene_error_from
from echoloc.io.recording import MAX_EXTENT_M
from echoloc.physics.transducer import PRESETS
from echoloc.sim.receiver import AdcSpec, GainSpec
from echoloc.sim.reflectors import Edge, Plane, PointReflector, Reflector, Sphere, corner
from echoloc.sim.scene import (
    REPORT_ARRAY,
    AirDrift,
    Array,
    PulseSpec,
    RandomReflectors,
    ReceiverSpec,
    RingDown,
    Scene,
    SensorMotion,
)

_SECTIONS: dict[str, set[str]] = {
    "array": {"transmitters_m", "receivers_m", "transmitter_axes", "receiver_axes", "aim_at_m", "firing"},
    "transducers": {"model", "absorption"},
    "pulse": {
        "code",
        "codes",
        "carrier_hz",
        "cycles_per_bit",
        "carrier",
        "chirp_bandwidth_hz",
        "chirp_duration_s",
    },
    "acquisition": {"sample_rate_hz", "n_samples", "frame_rate_hz"},
    "air": {
        "temperature_c",
        "relative_humidity",
        "temperature_drift_c_per_s",
        "humidity_drift_per_s",
        "turbulence",
    },
    "noise": {"snr_db", "path_jitter_m", "timing_jitter_s", "kind"},
    "ring_down": {"level", "levels", "decay_s", "direct_path"},
    "receiver": {
        "signal_kind",
        "output_rate_hz",
        "adc_rate_hz",
        "adc_bits",
        "full_scale",
        "gain",
        "baseband_filter_s",
        "baseband_filter_order",
        "record_waveform",
    },
    "motion": {"velocity_m_s", "angular_velocity_deg_s", "pan_deg", "tilt_deg", "scan_period_s"},
    "random_reflectors": {"count", "x_m", "y_m", "z_m", "strength"},
}
_GAIN_KEYS = {"kind", "gain_db", "slope_db_per_ms", "step_db", "step_s", "max_gain_db"}
_REFLECTOR_KEYS: dict[str, set[str]] = {
    "point": {"position_m", "strength", "velocity_m_s"},
    "sphere": {"centre_m", "radius_m", "velocity_m_s"},
    "plane": {
        "centre_m",
        "normal",
        "width_m",
        "height_m",
        "width_axis",
        "reflection",
        "velocity_m_s",
        "angular_velocity_deg_s",
        "spin_axis",
    },
    "edge": {"start_m", "end_m", "strength", "velocity_m_s"},
    "corner": {
        "edge_start_m",
        "edge_end_m",
        "normal_a",
        "normal_b",
        "face_width_m",
        "reflection",
        "edge_strength",
    },
}
_TOP_LEVEL = {*_SECTIONS, "reflectors", "seed", "max_order"}
_MISSING = object()

MAX_SCENE_FILE_BYTES = 4 << 20
"""The largest scene file read, bytes (a scene of 20 000 reflectors takes about 2 MB)."""


MAX_RANDOM_REFLECTORS = 10_000
"""The most random reflectors a frame may draw."""


@dataclass(frozen=True)
class _Table:
    """One TOML table and where it sits, for messages that name the key and value."""

    where: str
    data: Mapping[str, Any]

    def key(self, name: str) -> str:
        return f"{self.where}.{name}" if self.where else name

    def has(self, name: str) -> bool:
        return name in self.data

    def raw(self, name: str, default: Any = _MISSING) -> Any:
        if name in self.data:
            return self.data[name]
        if default is _MISSING:
            raise SceneError(f"{self.key(name)} is required")
        return default

    def number(self, name: str, default: Any = _MISSING) -> float:
        return _number(self.key(name), self.raw(name, default))

    def integer(self, name: str, default: Any = _MISSING) -> int:
        value = self.raw(name, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise SceneError(f"{self.key(name)} must be a whole number, got {value!r}")
        return value

    def boolean(self, name: str, default: Any = _MISSING) -> bool:
        value = self.raw(name, default)
        if not isinstance(value, bool):
            raise SceneError(f"{self.key(name)} must be true or false, got {value!r}")
        return value

    def choice(self, name: str, choices: tuple[str, ...], default: Any = _MISSING) -> str:
        value = self.raw(name, default)
        if not isinstance(value, str) or value not in choices:
            raise SceneError(f"{self.key(name)} must be one of {', '.join(choices)}; got {value!r}")
        return value

    def point(self, name: str, default: Any = _MISSING) -> NDArray[np.float64]:
        value = self.raw(name, default)
        if not isinstance(value, list) or len(value) != 3:
            raise SceneError(f"{self.key(name)} must be [x, y, z], got {value!r}")
        return np.array([_number(self.key(name), c) for c in value], dtype=float)

    def points(self, name: str) -> NDArray[np.float64]:
        return _points(self.key(name), self.raw(name))

    def numbers(self, name: str) -> tuple[float, ...]:
        """A non-empty list of finite numbers."""
        value = self.raw(name)
        if not isinstance(value, list) or not value:
            raise SceneError(f"{self.key(name)} must be a list of numbers, got {value!r}")
        return tuple(_number(self.key(name), v) for v in value)

    def number_or_numbers(self, name: str, default: float) -> float | tuple[float, ...]:
        """One finite number, or a list of them (e.g. one per receiver)."""
        return self.numbers(name) if isinstance(self.raw(name, default), list) else self.number(name, default)

    def pair(self, name: str, default: tuple[float, float]) -> tuple[float, float]:
        return _pair(self.key(name), self.raw(name, list(default)))

    def sub(self, name: str, allowed: set[str]) -> _Table:
        value = self.raw(name, {})
        if not isinstance(value, dict):
            raise SceneError(f"[{self.key(name)}] must be a table")
        table = _Table(self.key(name), value)
        table.check(allowed)
        return table

    def check(self, allowed: set[str]) -> None:
        unknown = sorted(set(self.data) - allowed)
        if unknown:
            where = f"[{self.where}]" if self.where else "top level"
            raise SceneError(f"{where}: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(allowed))})")


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


def scene_from_dict(data: Mapping[str, Any], source: str = "<scene>") -> Scene:
    """Build a :class:`Scene` from a parsed TOML table, checking every key and value."""
    try:
        return _scene_from_dict(data, source)
    except EchoLocError as error:
        raise scene_error_from(source, error) from None


def _array(table: _Table) -> Array:
    geometry = Array(
        transmitters_m=table.points("transmitters_m")
        if table.has("transmitters_m")
        else REPORT_ARRAY.transmitters_m,
        receivers_m=table.points("receivers_m") if table.has("receivers_m") else REPORT_ARRAY.receivers_m,
        transmitter_axes=table.points("transmitter_axes") if table.has("transmitter_axes") else None,
        receiver_axes=table.points("receiver_axes") if table.has("receiver_axes") else None,
    )
    if table.has("aim_at_m"):
        if table.has("transmitter_axes") or table.has("receiver_axes"):
            raise SceneError("array.aim_at_m and explicit array axes exclude each other")
        geometry = geometry.aimed_at(table.point("aim_at_m"))
    return geometry


def _pulse(table: _Table) -> tuple[PulseSpec, tuple[str, ...] | None]:
    code = table.raw("code", "barker13")
    if not isinstance(code, str):
        raise SceneError(f"pulse.code must be a waveform name such as 'barker13', got {code!r}")
    codes = None
    if table.has("codes"):
        value = table.raw("codes")
        if not (isinstance(value, list) and value and all(isinstance(c, str) for c in value)):
            raise SceneError(
                f"pulse.codes must be a list of waveform names, one per transmitter, got {value!r}"
            )
        codes = tuple(value)
    spec = PulseSpec(
        code=code,
        carrier_hz=table.number("carrier_hz", 50e3),
        cycles_per_bit=table.integer("cycles_per_bit", 4),
        carrier=table.choice("carrier", ("sine", "square"), "sine"),  # type: ignore[arg-type]
        chirp_bandwidth_hz=table.number("chirp_bandwidth_hz", 20e3),
        chirp_duration_s=table.number("chirp_duration_s", 1e-3),
    )
    return spec, codes


def _receiver(table: _Table, noise: str) -> ReceiverSpec:
    gain = table.sub("gain", _GAIN_KEYS)
    defaults = GainSpec()
    gain_spec = GainSpec(
        kind=gain.choice("kind", ("none", "continuous", "stepped"), defaults.kind),  # type: ignore[arg-type]
        gain_db=gain.number("gain_db", defaults.gain_db),
        slope_db_per_ms=gain.number("slope_db_per_ms", defaults.slope_db_per_ms),
        step_db=gain.number("step_db", defaults.step_db),
        step_s=gain.number("step_s", defaults.step_s),
        max_gain_db=gain.number("max_gain_db", defaults.max_gain_db),
    )
    adc = None
    if table.has("adc_bits") or table.has("full_scale"):
        adc = AdcSpec(
            bits=table.integer("adc_bits") if table.has("adc_bits") else None,
            full_scale=table.number("full_scale", AdcSpec().full_scale),
        )
    return ReceiverSpec(
        signal_kind=table.choice("signal_kind", ("rf", "envelope", "iq"), "rf"),  # type: ignore[arg-type]
        output_rate_hz=table.number("output_rate_hz") if table.has("output_rate_hz") else None,
        adc_rate_hz=table.number("adc_rate_hz") if table.has("adc_rate_hz") else None,
        noise=noise,  # type: ignore[arg-type]
        gain=gain_spec,
        adc=adc,
        baseband_filter_s=table.number("baseband_filter_s", 0.0),
        baseband_filter_order=table.integer("baseband_filter_order", 1),
        record_waveform=table.boolean("record_waveform", True),
    )


def _velocity(table: _Table) -> NDArray[np.float64]:
    return table.point("velocity_m_s", [0.0, 0.0, 0.0])


def _reflector(table: _Table) -> tuple[Reflector, ...]:
    kind = table.choice("kind", tuple(_REFLECTOR_KEYS), "point")
    table.check(_REFLECTOR_KEYS[kind] | {"kind"})
    if kind == "point":
        return (PointReflector(table.point("position_m"), table.number("strength", 1.0), _velocity(table)),)
    if kind == "sphere":
        return (Sphere(table.point("centre_m"), table.number("radius_m"), _velocity(table)),)
    if kind == "plane":
        return (
            Plane(
                centre_m=table.point("centre_m"),
                normal=table.point("normal"),
                width_m=table.number("width_m"),
                height_m=table.number("height_m"),
                width_axis=table.point("width_axis") if table.has("width_axis") else None,
                reflection=table.number("reflection", 1.0),
                velocity_m_s=_velocity(table),
                angular_velocity_deg_s=table.number("angular_velocity_deg_s", 0.0),
                spin_axis=table.point("spin_axis") if table.has("spin_axis") else None,
            ),
        )
    if kind == "edge":
        return (
            Edge(
                table.point("start_m"), table.point("end_m"), table.number("strength", 0.1), _velocity(table)
            ),
        )
    extra = {"edge_strength_m": table.number("edge_strength")} if table.has("edge_strength") else {}
    return corner(
        table.point("edge_start_m"),
        table.point("edge_end_m"),
        table.point("normal_a"),
        table.point("normal_b"),
        table.number("face_width_m"),
        reflection=table.number("reflection", 1.0),
        **extra,
    )


def _check_extents(table: _Table) -> None:
    """Every length and coordinate (a key ending in ``_m``) within :data:`MAX_EXTENT_M`."""
    for name, value in table.data.items():
        if not name.endswith("_m"):
            continue
        flat = value if isinstance(value, list) else [value]
        flat = [v for item in flat for v in (item if isinstance(item, list) else [item])]
        numbers = [abs(v) for v in flat if isinstance(v, int | float) and not isinstance(v, bool)]
        if any(not math.isfinite(v) or v > MAX_EXTENT_M for v in numbers):
            raise SceneError(f"{table.key(name)} must lie within {MAX_EXTENT_M:g} m, got {value!r}")


def _scene_from_dict(data: Mapping[str, Any], source: str) -> Scene:
    top = _Table("", data)
    top.check(_TOP_LEVEL)
    for name in ("array", "random_reflectors", "noise"):
        if isinstance(data.get(name), dict):
            _check_extents(_Table(name, data[name]))
    if isinstance(data.get("reflectors"), list):
        for i, entry in enumerate(data["reflectors"]):
            if isinstance(entry, dict):
                _check_extents(_Table(f"reflectors[{i}]", entry))
    sections = {name: top.sub(name, allowed) for name, allowed in _SECTIONS.items()}
    kwargs: dict[str, Any] = {"array": _array(sections["array"])}
    firing = sections["array"].choice("firing", ("sequential", "simultaneous"), "sequential")
    kwargs["firing"] = firing

    transducers = sections["transducers"]
    if transducers.has("model"):
        kwargs["transducer"] = transducers.choice("model", tuple(PRESETS))
    kwargs["absorption"] = transducers.boolean("absorption", False)

    kwargs["pulse"], kwargs["transmitter_codes"] = _pulse(sections["pulse"])

    acquisition = sections["acquisition"]
    kwargs["sample_rate_hz"] = acquisition.number("sample_rate_hz", 200e3)
    kwargs["n_samples"] = acquisition.integer("n_samples", 2400)
    kwargs["frame_rate_hz"] = acquisition.number("frame_rate_hz", 100.0)

    air = sections["air"]
    kwargs["temperature_c"] = air.number("temperature_c", 20.0)
    kwargs["relative_humidity"] = air.number("relative_humidity", 0.0)
    kwargs["drift"] = AirDrift(
        temperature_c_per_s=air.number("temperature_drift_c_per_s", 0.0),
        relative_humidity_per_s=air.number("humidity_drift_per_s", 0.0),
        turbulence=air.number("turbulence", 0.0),
    )

    noise = sections["noise"]
    if noise.has("snr_db"):
        kwargs["snr_db"] = noise.number("snr_db")
    kwargs["path_jitter_m"] = noise.number("path_jitter_m", 0.0)
    kwargs["timing_jitter_s"] = noise.number_or_numbers("timing_jitter_s", 0.0)
    noise_kind = noise.choice("kind", ("white", "band"), "white")

    ring = sections["ring_down"]
    defaults = RingDown()
    if ring.has("level") and ring.has("levels"):
        raise SceneError("ring_down.level and ring_down.levels exclude each other")
    kwargs["ring_down"] = RingDown(
        level=ring.number("level", defaults.level),
        decay_s=ring.number("decay_s", defaults.decay_s),
        direct_path=ring.boolean("direct_path", defaults.direct_path),
        levels=ring.numbers("levels") if ring.has("levels") else None,
    )
    kwargs["receiver"] = _receiver(sections["receiver"], noise_kind)
    motion = sections["motion"]
    kwargs["motion"] = SensorMotion(
        velocity_m_s=motion.point("velocity_m_s", [0.0, 0.0, 0.0]),
        angular_velocity_deg_s=motion.point("angular_velocity_deg_s", [0.0, 0.0, 0.0]),
        pan_deg=motion.number("pan_deg", 0.0),
        tilt_deg=motion.number("tilt_deg", 0.0),
        scan_period_s=motion.number("scan_period_s", 1.0),
    )

    reflectors = top.raw("reflectors", [])
    if not isinstance(reflectors, list):
        raise SceneError("[[reflectors]] must be an array of tables")
    positions: list[NDArray[np.float64]] = []
    strengths: list[float] = []
    objects: list[Reflector] = []
    for i, entry in enumerate(reflectors):
        if not isinstance(entry, dict):
            raise SceneError(f"reflectors[{i}] must be a table")
        table = _Table(f"reflectors[{i}]", entry)
        made = _reflector(table)
        # Still points stay in the scene's plain arrays (the simulator's fastest path).
        if len(made) == 1 and isinstance(made[0], PointReflector) and not np.any(made[0].velocity_m_s):
            positions.append(made[0].position_m)
            strengths.append(made[0].strength_m)
        else:
            objects.extend(made)
    kwargs["reflector_positions_m"] = np.array(positions).reshape(-1, 3)
    kwargs["reflector_strengths"] = np.array(strengths)
    kwargs["objects"] = tuple(objects)

    if top.has("random_reflectors"):
        table = sections["random_reflectors"]
        count = table.raw("count", [1, 5])
        if not (
            isinstance(count, list)
            and len(count) == 2
            and all(isinstance(c, int) and not isinstance(c, bool) for c in count)
        ):
            raise SceneError(f"random_reflectors.count must be [min, max] whole numbers, got {count!r}")
        if count[1] > MAX_RANDOM_REFLECTORS:
            raise SceneError(
                f"random_reflectors.count must be at most {MAX_RANDOM_REFLECTORS}, got {count!r}"
            )
        box = RandomReflectors()
        kwargs["random"] = RandomReflectors(
            count=(count[0], count[1]),
            x_m=table.pair("x_m", box.x_m),
            y_m=table.pair("y_m", box.y_m),
            z_m=table.pair("z_m", box.z_m),
            strength=table.pair("strength", box.strength),
        )

    seed = top.raw("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise SceneError(f"seed must be a whole number >= 0, got {seed!r}")
    kwargs["seed"] = seed
    kwargs["max_order"] = top.integer("max_order", 1)
    return Scene(**kwargs)


def preset_names() -> tuple[str, ...]:
    """Names of the scene presets shipped in ``echoloc/scenes``, sorted: their paths there
    without ``.toml``, ``/`` between folder and file (``ch101``, ``report/ball-fixed``)."""
    folder = resources.files("echoloc") / "scenes"
    if not folder.is_dir():
        return ()
    names = [item.name[:-5] for item in folder.iterdir() if item.name.endswith(".toml")]
    for sub in folder.iterdir():
        if sub.is_dir():
            names += [f"{sub.name}/{item.name[:-5]}" for item in sub.iterdir() if item.name.endswith(".toml")]
    return tuple(sorted(names))


def preset_path(name: str) -> Path:
    """Path of the shipped scene preset ``name`` (``ch101`` or ``ch101.toml``); SceneError if none."""
    stem = name.removesuffix(".toml")
    if stem not in preset_names():
        presets = ", ".join(preset_names()) or "none"
        raise SceneError(f"{name}: no scene preset of that name (presets: {presets})")
    *folders, file = stem.split("/")
    return Path(str(resources.files("echoloc").joinpath("scenes", *folders, f"{file}.toml")))


def load_scene(path: str | Path) -> Scene:
    """Read and validate a scene TOML file, or a shipped preset by name (:func:`preset_names`).

    A name that is not an existing file but names a preset loads the preset; an existing
    file always wins.
    """
    path = Path(path)
    if not path.exists() and path.as_posix().removesuffix(".toml") in preset_names():
        path = preset_path(path.as_posix())
    text = read_text_input(path, what="scene file", max_bytes=MAX_SCENE_FILE_BYTES, error=SceneError)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"{path}: not valid TOML ({error})") from None
    except (ValueError, RecursionError) as error:  # a 5000-digit integer; arrays nested 3000 deep
        reason = "nested too deeply" if isinstance(error, RecursionError) else str(error)
        raise SceneError(f"{path}: not valid TOML ({reason})") from None
    return scene_from_dict(data, source=str(path))
