"""Sensor-head files: a real head described in TOML, for capture and for the simulator.

A head file holds what a scene file says about the sensor (``[array]``,
``[transducers]``, ``[pulse]``, ``[acquisition]``, ``[air]`` and the receiver's
``signal_kind`` and gain), with the same keys and checks, plus what only hardware has:

- ``[head]``: ``name``, and ``description``;
- ``[channels]``: ``order``, the capture channel that carries each receiver (in
  ``array.receivers_m`` order); ``count``, how many channels a frame carries (default:
  one past the highest channel named); ``loopback``, a channel wired to the transmitter
  drive (a sound card's emission instant, exact to a fraction of a sample); ``output``,
  the sound-card output channel that drives the transmitter;
- ``[adc]``: ``format`` of a sample on the wire (``int16``, ``uint16``, ``int32`` or
  ``float32``), ``bits`` of the converter, ``offset`` in counts (the code of 0 V: 2048
  for a unipolar 12-bit converter) and ``full_scale`` in counts (default
  ``2**(bits - 1)``), so that a sample becomes ``(count - offset) / full_scale``:
  1.0 at full scale.

Every key is checked: an unknown key, a missing one or a value of the wrong kind raises
:class:`~echoloc.errors.SceneError` naming the file and the key. docs/HEAD.md is the
reference, with a worked example (``examples/heads/bench-4mic.toml``).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from echoloc._toml import tomllib
from echoloc.errors import EchoLocError, SceneError, read_text_input, scene_error_from
from echoloc.io.recording import Recording

HEAD_FILE_SUFFIX = ".toml"
"""What a head file's name ends with (recordings end .h5, .hdf5 or .npz)."""

MAX_HEAD_FILE_BYTES = 1 << 20
"""The largest head file read, bytes."""

SAMPLE_FORMATS: dict[str, str] = {"int16": "<i2", "uint16": "<u2", "int32": "<i4", "float32": "<f4"}
"""A sample's format on the wire: its numpy dtype (little-endian)."""

_SENSOR_SECTIONS = ("array", "transducers", "pulse", "acquisition", "air", "receiver")
_RECEIVER_KEYS = {"signal_kind", "output_rate_hz", "gain", "baseband_filter_s", "baseband_filter_order"}
_HEAD_KEYS = {"name", "description"}
_CHANNEL_KEYS = {"order", "count", "loopback", "output"}
_ADC_KEYS = {"format", "bits", "offset", "full_scale"}
_TOP_LEVEL = {*_SENSOR_SECTIONS, "head", "channels", "adc"}


@dataclass(frozen=True)
class AdcFormat:
    """How a captured sample reads: ``format`` (:data:`SAMPLE_FORMATS`), the converter's
    ``bits``, ``offset`` (counts at 0 V) and ``full_scale`` (counts at full scale)."""

    format: str = "int16"
    bits: int = 16
    offset: float = 0.0
    full_scale: float = 32768.0

    @property
    def dtype(self) -> np.dtype[Any]:
        return np.dtype(SAMPLE_FORMATS[self.format])


@dataclass(frozen=True, eq=False)
class SensorHead:
    """A sensor head: its geometry and pulse as a recording header, and how it is wired.

    ``header``: a :class:`~echoloc.io.recording.Recording` with no frames (what a session
    carries: geometry, waveform, rates, air); ``sensor_tables``: the head file's sensor
    sections, as a scene file has them (:meth:`scene` adds reflectors to simulate this
    head); ``channel_order[r]``: the
    capture channel of receiver ``r``; ``n_channels`` the channels a captured frame
    carries; ``loopback_channel`` and ``output_channel`` (sound cards) or None;
    ``frame_rate_hz`` how often the head fires.
    """

    name: str
    header: Recording
    sensor_tables: Mapping[str, Any]
    channel_order: tuple[int, ...]
    n_channels: int
    adc: AdcFormat
    frame_rate_hz: float
    loopback_channel: int | None = None
    output_channel: int | None = None
    description: str = ""
    source: str = "<head>"

    @property
    def n_samples(self) -> int:
        """Samples a channel carries a frame (complex samples for iq: twice as many numbers)."""
        return self.header.n_samples

    @property
    def values_per_channel(self) -> int:
        """Numbers a channel carries a frame: ``n_samples``, twice that for iq (I, Q interleaved)."""
        return self.n_samples * (2 if self.header.signal_kind == "iq" else 1)

    def scene(self, tables: Mapping[str, Any]) -> Any:
        """A simulator scene of this head, with ``tables`` of a scene file added (``reflectors``,
        ``noise``, ``ring_down``, ``seed``, ...): :class:`~echoloc.sim.scene.Scene`."""
        from echoloc.sim.scenefile import scene_from_dict

        return scene_from_dict({**self.sensor_tables, **tables}, self.source)

    def frame_bytes(self) -> int:
        """Bytes of one captured frame's samples."""
        return self.n_channels * self.values_per_channel * self.adc.dtype.itemsize

    def samples(self, counts: NDArray[Any]) -> NDArray[np.float64] | NDArray[np.complex128]:
        """One captured frame, (n_channels, values_per_channel) in ADC counts, as the chain takes it:
        the receivers' channels in ``channel_order``, ``(count - offset) / full_scale``; iq pairs
        (I, Q interleaved) as complex numbers."""
        raw = np.asarray(counts)
        expected = (self.n_channels, self.values_per_channel)
        if raw.shape != expected:
            raise EchoLocError(f"{self.source}: a frame must be {expected} samples, got {raw.shape}")
        picked = raw[list(self.channel_order)].astype(np.float64)
        values = (picked - self.adc.offset) / self.adc.full_scale
        if self.header.signal_kind == "iq":
            return values[:, 0::2] + 1j * values[:, 1::2]
        return values

    def counts(self, samples: NDArray[Any]) -> NDArray[Any]:
        """The inverse of :meth:`samples` (rounded to the wire format, clipped to its range):
        what this head's hardware would send for ``samples`` (n_rx, n_samples); the channels no
        receiver uses carry the offset. For test doubles and example senders."""
        values = np.asarray(samples)
        if self.header.signal_kind == "iq":
            pairs = np.empty((values.shape[0], 2 * values.shape[1]))
            pairs[:, 0::2], pairs[:, 1::2] = values.real, values.imag
            values = pairs
        dtype = self.adc.dtype
        wire = np.full((self.n_channels, self.values_per_channel), self.adc.offset)
        wire[list(self.channel_order)] = values.real * self.adc.full_scale + self.adc.offset
        if dtype.kind == "f":
            return wire.astype(dtype)
        info = np.iinfo(dtype)
        clipped: NDArray[Any] = np.clip(np.rint(wire), info.min, info.max).astype(dtype)
        return clipped


def is_head_file(path: str | Path) -> bool:
    """Does ``path`` name a head file (by its suffix) rather than a recording?"""
    return Path(path).suffix.lower() == HEAD_FILE_SUFFIX


def _sub(data: Mapping[str, Any], name: str, allowed: set[str]) -> dict[str, Any]:
    value = data.get(name, {})
    if not isinstance(value, dict):
        raise SceneError(f"[{name}] must be a table")
    unknown = sorted(set(value) - allowed)
    if unknown:
        raise SceneError(f"[{name}]: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(allowed))})")
    return value


def _whole(where: str, value: Any, low: int, high: int | None = None) -> int:
    if (
        isinstance(value, bool)
        or not isinstance(value, int)
        or value < low
        or (high is not None and value > high)
    ):
        bound = f"from {low} to {high}" if high is not None else f">= {low}"
        raise SceneError(f"{where} must be a whole number {bound}, got {value!r}")
    return value


def _adc(table: Mapping[str, Any]) -> AdcFormat:
    form = table.get("format", "int16")
    if not isinstance(form, str) or form not in SAMPLE_FORMATS:
        raise SceneError(f"adc.format must be one of {', '.join(SAMPLE_FORMATS)}; got {form!r}")
    width = 8 * np.dtype(SAMPLE_FORMATS[form]).itemsize
    bits = _whole("adc.bits", table.get("bits", 24 if form == "float32" else width), 1, 32)
    if form != "float32" and bits > width:
        raise SceneError(f"adc.bits ({bits}) cannot exceed the {width} bits of adc.format {form}")
    numbers: dict[str, float] = {}
    for key, default in (("offset", 0.0), ("full_scale", float(2 ** (bits - 1)))):
        value = table.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise SceneError(f"adc.{key} must be a finite number, got {value!r}")
        numbers[key] = float(value)
    if numbers["full_scale"] <= 0:
        raise SceneError(f"adc.full_scale must be > 0 counts, got {numbers['full_scale']!r}")
    return AdcFormat(form, bits, numbers["offset"], numbers["full_scale"])


def head_from_dict(data: Mapping[str, Any], source: str = "<head>") -> SensorHead:
    """Build a :class:`SensorHead` from a parsed head file, checking every key and value."""
    try:
        return _head_from_dict(data, source)
    except EchoLocError as error:
        raise scene_error_from(source, error) from None


def _head_from_dict(data: Mapping[str, Any], source: str) -> SensorHead:
    from echoloc.sim.scenefile import scene_from_dict
    from echoloc.sim.simulation import recording_header

    unknown = sorted(set(data) - _TOP_LEVEL)
    if unknown:
        raise SceneError(
            f"top level: unknown key {unknown[0]!r} (a head file has: {', '.join(sorted(_TOP_LEVEL))}; "
            "reflectors belong in scene files)"
        )
    _sub(data, "receiver", _RECEIVER_KEYS)
    for name in ("array", "acquisition"):
        if name not in data:
            raise SceneError(f"[{name}] is required: a head's transducers and its sampling")
        if not isinstance(data[name], dict):
            raise SceneError(f"[{name}] must be a table")
    if "receivers_m" not in data["array"] or "transmitters_m" not in data["array"]:
        raise SceneError("array.transmitters_m and array.receivers_m are required")
    sensor_tables = {k: data[k] for k in _SENSOR_SECTIONS if k in data}
    # The scene's checks, on the sensor with one far point (a scene without reflectors is refused).
    scene = scene_from_dict({**sensor_tables, "reflectors": [{"position_m": [0.0, 0.0, 1.0]}]}, source)
    head = _sub(data, "head", _HEAD_KEYS)
    name = head.get("name", Path(source).stem)
    description = head.get("description", "")
    if not isinstance(name, str) or not isinstance(description, str):
        raise SceneError("head.name and head.description must be strings")
    n_rx = len(scene.array.receivers_m)
    channels = _sub(data, "channels", _CHANNEL_KEYS)
    order_value = channels.get("order", list(range(n_rx)))
    if not isinstance(order_value, list) or len(order_value) != n_rx:
        raise SceneError(
            f"channels.order must list the capture channel of each of the {n_rx} receivers, "
            f"got {order_value!r}"
        )
    order = tuple(_whole("channels.order", c, 0, 255) for c in order_value)
    if len(set(order)) != n_rx:
        raise SceneError(f"channels.order names a channel twice: {list(order)}")
    loopback = channels.get("loopback")
    if loopback is not None:
        loopback = _whole("channels.loopback", loopback, 0, 255)
        if loopback in order:
            raise SceneError(f"channels.loopback ({loopback}) is also a receiver's channel in channels.order")
    output = None if channels.get("output") is None else _whole("channels.output", channels["output"], 0, 255)
    highest = max([*order, *([] if loopback is None else [loopback])])
    count = _whole("channels.count", channels.get("count", highest + 1), 1, 256)
    if count <= highest:
        raise SceneError(f"channels.count ({count}) must exceed the highest channel named ({highest})")
    header = dataclasses.replace(recording_header(scene), truth_kinds=None, source=source)
    return SensorHead(
        name=name,
        header=header,
        sensor_tables=sensor_tables,
        channel_order=order,
        n_channels=count,
        adc=_adc(_sub(data, "adc", _ADC_KEYS)),
        frame_rate_hz=scene.frame_rate_hz,
        loopback_channel=loopback,
        output_channel=output,
        description=description,
        source=source,
    )


_IMPORT_FORM_KEYS = {"sample_rate_hz", "signal_kind", "transmitters", "receivers", "waveform", "truth"}
"""Top-level keys of an import's flat head TOML (docs/IMPORT.md), which a head file has in sections."""


def _head_toml(path: Path) -> dict[str, Any]:
    text = read_text_input(path, what="head file", max_bytes=MAX_HEAD_FILE_BYTES, error=SceneError)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise SceneError(f"{path}: not valid TOML ({error})") from None
    except (ValueError, RecursionError) as error:
        reason = "nested too deeply" if isinstance(error, RecursionError) else str(error)
        raise SceneError(f"{path}: not valid TOML ({reason})") from None


def is_sectioned_head(path: str | Path) -> bool:
    """Is ``path`` a head file with sections (this module's), rather than an import's flat head
    TOML (docs/IMPORT.md)? Judged by its ``[array]`` or ``[acquisition]`` table."""
    data = _head_toml(Path(path))
    return isinstance(data.get("array"), dict) or isinstance(data.get("acquisition"), dict)


def load_head(path: str | Path) -> SensorHead:
    """Read and validate a head file (TOML)."""
    path = Path(path)
    data = _head_toml(path)
    flat = sorted(_IMPORT_FORM_KEYS & set(data))
    if flat and "array" not in data:
        raise SceneError(
            f"{path}: an import's head TOML (flat keys such as {flat[0]!r}, docs/IMPORT.md) lacks what a "
            "live head needs (samples a frame, frame rate, pulse, wiring): write it with sections "
            "[array], [acquisition], [pulse], [channels] (docs/HEAD.md)"
        )
    return head_from_dict(data, source=str(path))


def read_geometry(path: str | Path) -> Recording:
    """A session's header from a head file (``.toml``) or from a recording (its frames kept):
    what ``--geometry`` takes."""
    from echoloc.io.recording import read_recording

    return load_head(path).header if is_head_file(path) else read_recording(path)


@dataclass(frozen=True)
class HeadCheck:
    """What a head can do, and what is wrong with it (:func:`check_head`).

    ``frame_s`` a frame's recording time; ``max_range_m`` the farthest reflector a frame
    hears, ``c frame_s / 2`` (transmitter and receiver together); ``pulse_s`` the pulse's
    length and ``blind_range_m`` ``c pulse_s / 2``, the range its own emission masks;
    ``bytes_per_s`` the samples' data rate at ``frame_rate_hz``; ``beam_half_angle_deg`` the
    transducers' -3 dB half-angle (None: no ``[transducers] model``). ``problems`` are
    errors (the head cannot work as described), ``notes`` warnings.
    """

    frame_s: float
    max_range_m: float
    pulse_s: float
    blind_range_m: float
    bytes_per_s: float
    beam_half_angle_deg: float | None
    problems: tuple[str, ...]
    notes: tuple[str, ...]


def check_head(head: SensorHead) -> HeadCheck:
    """The figures of ``head`` and the mistakes a head file can hold that its keys' own
    checks cannot see: frames longer than the frame period, receivers that share a position
    or lie on one line (no 3-D position), a pulse longer than a frame."""
    from echoloc.physics.transducer import PRESETS, piston_beam_angles

    header = head.header
    c = float(header.speed_of_sound_m_s or 343.0)
    rate = header.sample_rate_hz
    frame_s = header.n_samples / rate
    waveform = header.waveform
    pulse_s = 0.0 if waveform is None else len(waveform) / rate
    problems: list[str] = []
    notes: list[str] = []
    if frame_s * head.frame_rate_hz > 1.0 + 1e-9:
        problems.append(
            f"a frame records {frame_s * 1e3:.2f} ms but the head fires every "
            f"{1e3 / head.frame_rate_hz:.2f} ms: frames would overlap (lower acquisition.frame_rate_hz "
            "or acquisition.n_samples)"
        )
    if pulse_s >= frame_s:
        problems.append(f"the pulse ({pulse_s * 1e3:.2f} ms) is as long as a frame ({frame_s * 1e3:.2f} ms)")
    receivers = np.asarray(header.receivers_m, dtype=float)
    spread = receivers - receivers.mean(axis=0)
    rank = int(np.linalg.matrix_rank(spread, tol=1e-6)) if len(receivers) > 1 else 0
    if len(np.unique(np.round(receivers, 6), axis=0)) < len(receivers):
        problems.append("two receivers share a position: their echoes add nothing to a position")
    elif len(receivers) < 3:
        notes.append(f"{len(receivers)} receiver(s): too few for 3-D positions (3 or more; 4 reject ghosts)")
    elif rank < 2:
        notes.append("the receivers lie on one line: a reflector is placed on a circle about it, not a point")
    elif len(receivers) == 3:
        notes.append("3 receivers: 3-D positions, but no fourth to reject ghosts among several reflectors")
    beam = None
    model = head.sensor_tables.get("transducers", {}).get("model")
    if model is not None and header.carrier_hz is not None:
        angle = piston_beam_angles(PRESETS[model].radius_m, header.carrier_hz, c).half_angle_3db_rad
        beam = math.degrees(angle) if math.isfinite(angle) else 90.0
    if head.loopback_channel is None and head.output_channel is not None:
        notes.append(
            "a sound-card head without channels.loopback: the emission instant comes from the "
            "driver's latency report (docs/SOUNDCARD.md)"
        )
    return HeadCheck(
        frame_s=frame_s,
        max_range_m=c * frame_s / 2,
        pulse_s=pulse_s,
        blind_range_m=c * pulse_s / 2,
        bytes_per_s=head.frame_bytes() * head.frame_rate_hz,
        beam_half_angle_deg=beam,
        problems=tuple(problems),
        notes=tuple(notes),
    )
