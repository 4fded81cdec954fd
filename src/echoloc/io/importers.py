"""Importers: contract recordings (``docs/FORMATS.md``) from the layouts users already have.

Two layouts are read (``docs/IMPORT.md`` describes both for users):

``spiel``
    The CSV layout of the public CH101 data set published with C. Hahne,
    "3-Dimensional Sonic Phase-invariant Echo Localization", ICRA 2023,
    doi:10.1109/ICRA48891.2023.10161199 (Apache-2.0): a folder of
    ``<x>mm_<y>mm_<z>mm_<a>_<b>_frames.csv`` / ``..._labels.csv`` pairs, one frame per
    pair, with the empty-scene frames under the same names in the sibling folder
    ``<folder>_bg``. :func:`read_spiel` reads it; :data:`SPIEL_HEAD` is its sensor head.
``samples``
    Plain samples, a ``.npy`` of shape (n_frames, n_rx, n_samples) or a text table
    with one row per frame and receiver, plus a sensor-head TOML
    (:func:`read_head`) that gives everything the samples do not.
    :func:`read_samples` reads it.

Both return a validated :class:`~echoloc.io.recording.Recording` whose ``source`` is the
file or folder read; write it with :func:`echoloc.io.recording.write_recording`. Every
bad input raises :class:`~echoloc.errors.EchoLocError` with one line naming the file
and the problem.

The building blocks are pure: :func:`natural_sort_key`, :func:`parse_table`,
:func:`parse_head`, :func:`merge_heads`, :func:`truth_positions_m`,
:func:`spiel_recording` and :func:`samples_recording` touch no file.
"""

from __future__ import annotations

import math
import os
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields, replace
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from numpy.typing import NDArray

from echoloc._toml import tomllib
from echoloc.errors import EchoLocError, open_input, read_text_input
from echoloc.io.recording import (
    MAX_RECORDING_BYTES,
    SIGNAL_KINDS,
    Recording,
    read_npy_header,
    validate_recording,
)

Position = tuple[float, float, float]

_ABSOLUTE_ZERO_C = -273.15
_FLOAT32_EXACT_INTEGER = 2**24  # every integer of magnitude <= this is exact in float32
_FRAMES_SUFFIX = "_frames.csv"
_LABELS_SUFFIX = "_labels.csv"
_BACKGROUND_FOLDER_SUFFIX = "_bg"
_LABEL_COLUMNS = 6  # channel index, range (mm), amplitude, target x, y, z (mm)
_SPIEL_DROPPED_COLUMNS = 2  # the published loader drops the last 2 samples of every row
_SPIEL_POSITION_TOLERANCE_MM = 1e-6
_NAME_POSITION = re.compile(
    r"^(?P<x>[-+]?\d+(?:\.\d*)?)mm_(?P<y>[-+]?\d+(?:\.\d*)?)mm_(?P<z>[-+]?\d+(?:\.\d*)?)mm_"
)
_DIGITS = re.compile(r"(\d+)")
_NPY_SUFFIXES = (".npy",)

# Size limits of the files read, checked before a byte is read (a device or a huge file
# must not fill the memory).
MAX_HEAD_BYTES = 4 << 20
"""The largest sensor-head TOML, bytes: like a scene file, a few lines per receiver and truth span."""
MAX_SPIEL_FILE_BYTES = 16 << 20
"""The largest SPiEL frames or labels CSV, bytes: each holds one frame of a few channels
(a few hundred kB of text)."""
MAX_TABLE_BYTES = 256 << 20
"""The largest text table of samples, bytes: parsing takes about five times the text's
size in memory, and 256 MiB is some 30 M values, thousands of frames; longer
recordings belong in a ``.npy``, which is read without parsing."""


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _error(source: object, message: str) -> EchoLocError:
    """The one-line error ``"<source>: <message>"``."""
    return EchoLocError(_one_line(f"{source}: {message}"))


# ----------------------------------------------------------------------------- sensor head


@dataclass(frozen=True)
class TruthSpan:
    """One known reflector position over a range of frames.

    Attributes
    ----------
    start_frame, stop_frame
        The frames ``start_frame <= k < stop_frame``; ``stop_frame`` None: to the last.
    position_m
        The reflector's position in the sensor frame, m.
    """

    start_frame: int
    stop_frame: int | None
    position_m: Position


@dataclass(frozen=True)
class ImportHead:
    """What an import's flat head TOML says (docs/IMPORT.md section 3): the geometry, rates
    and air, and an import's own files and truth; ``None`` where it says nothing. A live
    head's file, with sections (:mod:`echoloc.io.head`), is read by
    :func:`read_samples_with_head` instead.

    Attributes
    ----------
    source
        Where it came from (the TOML's path, or a name), for messages.
    sample_rate_hz
        Sample rate of the samples, Hz.
    signal_kind
        ``"rf"``, ``"envelope"`` or ``"iq"``.
    carrier_hz
        Carrier / centre frequency, Hz.
    transmitters_m, receivers_m
        Positions in the sensor frame, m; one receiver per channel of the samples.
    speed_of_sound_m_s
        Speed of sound, m/s.
    temperature_c
        Air temperature, °C.
    relative_humidity
        Relative humidity, a fraction 0..1.
    background_path
        A recording of the empty scene (samples layout), resolved against the TOML's folder.
    waveform_path
        The SENT template (needed for ``rf`` and ``iq``), resolved likewise.
    truth
        Known reflector positions per range of frames (spans may overlap: each adds
        one reflector to its frames).
    """

    source: str
    sample_rate_hz: float | None = None
    signal_kind: str | None = None
    carrier_hz: float | None = None
    transmitters_m: tuple[Position, ...] | None = None
    receivers_m: tuple[Position, ...] | None = None
    speed_of_sound_m_s: float | None = None
    temperature_c: float | None = None
    relative_humidity: float | None = None
    background_path: Path | None = None
    waveform_path: Path | None = None
    truth: tuple[TruthSpan, ...] = ()


SPIEL_RECEIVER_Y_M = 0.0649519052838329  # 0.075 m x sin(120°): the circle of radius 75 mm
SPIEL_HEAD = ImportHead(
    source="the SPiEL CH101 head",
    sample_rate_hz=22000.0,
    signal_kind="envelope",
    carrier_hz=175000.0,
    transmitters_m=((0.0, 0.0, 0.0),),
    receivers_m=(
        (0.0, 0.0, 0.0),  # channel 0: the transmitter itself (monostatic)
        (-0.0375, -SPIEL_RECEIVER_Y_M, 0.0),
        (0.075, 0.0, 0.0),
        (-0.0375, SPIEL_RECEIVER_Y_M, 0.0),
    ),
)
"""The CH101 head of the SPiEL data set: one transmitter at the origin, channel 0 the
transmitter itself, channels 1-3 on a circle of radius 75 mm in z = 0; envelope samples
at 22 kHz of a 175 kHz carrier; no known pulse."""

HEAD_KEYS: dict[str, str] = {
    "sample_rate_hz": "sample rate of the samples, Hz (required for `import samples`)",
    "signal_kind": '"rf", "envelope" or "iq" (required for `import samples`)',
    "carrier_hz": "carrier / centre frequency, Hz",
    "transmitters": "list of [x, y, z] transmitter positions, m (required for `import samples`)",
    "receivers": "list of [x, y, z] receiver positions, m, one per channel (required for `import samples`)",
    "speed_of_sound_m_s": "speed of sound, m/s",
    "temperature_c": "air temperature, °C",
    "relative_humidity": "relative humidity, a fraction 0..1",
    "background": "file of empty-scene samples (.npy or text), relative to the TOML",
    "waveform": "file of the SENT template (.npy or text), relative to the TOML; needed for rf and iq",
    "truth": "array of tables [[truth]] with frames = N or 'START:STOP' and position_m = [x, y, z]",
}
"""Every key a sensor-head TOML may hold, with what it means (units in the text)."""

TRUTH_KEYS = ("frames", "position_m")
SAMPLES_REQUIRED_KEYS = ("sample_rate_hz", "signal_kind", "transmitters", "receivers")


def _number(source: str, key: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise _error(source, f"{key} must be a number, got {value!r}")
    number = float(value)
    if not math.isfinite(number):
        raise _error(source, f"{key} must be finite, got {value!r}")
    return number


def _positions(source: str, key: str, value: object) -> tuple[Position, ...]:
    if not isinstance(value, list) or not value:
        raise _error(source, f"{key} must be a non-empty list of [x, y, z] positions in m, got {value!r}")
    out: list[Position] = []
    for k, item in enumerate(value):
        out.append(_position(source, f"{key}[{k}]", item))
    return tuple(out)


def _position(source: str, key: str, value: object) -> Position:
    if not isinstance(value, list) or len(value) != 3:
        raise _error(source, f"{key} must be [x, y, z] in m, got {value!r}")
    x, y, z = (_number(source, key, v) for v in value)
    return (x, y, z)


def _frames_range(source: str, key: str, value: object) -> tuple[int, int | None]:
    """``N`` (one frame) or ``"START:STOP"`` (stop exclusive, either may be left out)."""
    if isinstance(value, int) and not isinstance(value, bool):
        if value < 0:
            raise _error(source, f"{key} must be >= 0, got {value}")
        return value, value + 1
    if isinstance(value, str) and value.count(":") == 1:
        start_text, stop_text = (part.strip() for part in value.split(":"))
        try:
            start = int(start_text) if start_text else 0
            stop = int(stop_text) if stop_text else None
        except ValueError:
            pass
        else:
            if start < 0 or (stop is not None and stop <= start):
                raise _error(source, f"{key} = {value!r} must satisfy 0 <= START < STOP")
            return start, stop
    raise _error(source, f"{key} must be a frame index N or 'START:STOP' (STOP exclusive), got {value!r}")


def _truth(source: str, value: object) -> tuple[TruthSpan, ...]:
    if not isinstance(value, list):
        raise _error(source, "truth must be an array of tables ([[truth]] with frames and position_m)")
    spans: list[TruthSpan] = []
    for k, table in enumerate(value):
        where = f"truth[{k}]"
        if not isinstance(table, dict):
            raise _error(source, f"{where} must be a table with frames and position_m, got {table!r}")
        for key in table:
            if key not in TRUTH_KEYS:
                raise _error(source, f"unknown key {where}.{key} (known: {', '.join(TRUTH_KEYS)})")
        for key in TRUTH_KEYS:
            if key not in table:
                raise _error(source, f"{where} is missing {key}")
        start, stop = _frames_range(source, f"{where}.frames", table["frames"])
        spans.append(TruthSpan(start, stop, _position(source, f"{where}.position_m", table["position_m"])))
    return tuple(spans)


def _file_key(source: str, key: str, value: object, base_dir: Path) -> Path:
    if not isinstance(value, str) or not value:
        raise _error(source, f"{key} must be a file name (a string), got {value!r}")
    path = Path(value)
    return path if path.is_absolute() else base_dir / path


def parse_head(data: Mapping[str, object], source: str, base_dir: Path) -> ImportHead:
    """A :class:`ImportHead` from the parsed TOML ``data`` (no file is touched).

    Parameters
    ----------
    data
        The TOML document as :func:`tomllib.loads` returns it.
    source
        The TOML's name, for messages.
    base_dir
        The folder relative file names (``background``, ``waveform``) are resolved against.

    Raises
    ------
    EchoLocError
        On an unknown key (named), a value of the wrong type, or out of its range.
    """
    for key in data:
        if key not in HEAD_KEYS:
            raise _error(source, f"unknown key {key!r} (known: {', '.join(HEAD_KEYS)})")
    values: dict[str, Any] = {}
    for key in ("sample_rate_hz", "carrier_hz", "speed_of_sound_m_s"):
        if key in data:
            number = _number(source, key, data[key])
            if number <= 0:
                raise _error(source, f"{key} must be > 0, got {data[key]!r}")
            values[key] = number
    if "temperature_c" in data:
        values["temperature_c"] = _number(source, "temperature_c", data["temperature_c"])
        if values["temperature_c"] <= _ABSOLUTE_ZERO_C:
            raise _error(
                source, f"temperature_c must be above {_ABSOLUTE_ZERO_C} °C, got {data['temperature_c']!r}"
            )
    if "relative_humidity" in data:
        values["relative_humidity"] = _number(source, "relative_humidity", data["relative_humidity"])
        if not 0.0 <= values["relative_humidity"] <= 1.0:
            raise _error(source, f"relative_humidity is a fraction 0..1, got {data['relative_humidity']!r}")
    if "signal_kind" in data:
        kind = data["signal_kind"]
        if kind not in SIGNAL_KINDS:
            kinds = ", ".join(repr(k) for k in SIGNAL_KINDS)
            raise _error(source, f"signal_kind must be one of {kinds}, got {kind!r}")
        values["signal_kind"] = kind
    for key in ("transmitters", "receivers"):
        if key in data:
            values[f"{key}_m"] = _positions(source, key, data[key])
    for key in ("background", "waveform"):
        if key in data:
            values[f"{key}_path"] = _file_key(source, key, data[key], base_dir)
    if "truth" in data:
        values["truth"] = _truth(source, data["truth"])
    return ImportHead(source=source, **values)


def read_head(path: Path) -> ImportHead:
    """Read a sensor-head TOML (keys: :data:`HEAD_KEYS`); see :func:`parse_head`.

    Raises
    ------
    EchoLocError
        If the file cannot be read, is not TOML, or :func:`parse_head` refuses it.
    """
    text = read_text_input(path, what="sensor head", max_bytes=MAX_HEAD_BYTES)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise _error(path, f"not valid TOML: {exc}") from None
    except RecursionError:  # arrays nested thousands deep
        raise _error(path, "not valid TOML: nested too deeply") from None
    return parse_head(data, str(path), path.parent)


def merge_heads(base: ImportHead, override: ImportHead) -> ImportHead:
    """``base`` with every field that ``override`` gives replaced (``source`` from ``override``)."""
    changes: dict[str, Any] = {"source": override.source}
    for field in fields(ImportHead):
        value = getattr(override, field.name)
        if field.name != "source" and value is not None and value != ():
            changes[field.name] = value
    return replace(base, **changes)


def _require(head: ImportHead, keys: Sequence[str], what: str) -> None:
    attribute = {"transmitters": "transmitters_m", "receivers": "receivers_m"}
    for key in keys:
        if getattr(head, attribute.get(key, key)) is None:
            raise _error(head.source, f"missing key {key!r}, which {what} needs ({HEAD_KEYS[key]})")


def truth_positions_m(spans: Sequence[TruthSpan], n_frames: int, source: str) -> NDArray[np.float64] | None:
    """Per-frame truth from ``spans``: (n_frames, n_max, 3) m, NaN rows as padding.

    Each span adds one reflector to the frames it covers; ``n_max`` is the most spans
    covering one frame. None when there are no spans.

    Raises
    ------
    EchoLocError
        If a span starts at or beyond ``n_frames`` or ends beyond it (names ``source``).
    """
    if not spans:
        return None
    ranges = []
    for k, span in enumerate(spans):
        stop = n_frames if span.stop_frame is None else span.stop_frame
        if span.start_frame >= n_frames or stop > n_frames:
            shown = f"{span.start_frame}:{'' if span.stop_frame is None else span.stop_frame}"
            raise _error(source, f"truth[{k}].frames {shown!r} is outside the {n_frames} frames")
        ranges.append((span.start_frame, stop))
    count = np.zeros(n_frames, dtype=np.int64)
    for start, stop in ranges:
        count[start:stop] += 1
    truth = np.full((n_frames, int(count.max()), 3), np.nan)
    filled = np.zeros(n_frames, dtype=np.int64)
    for (start, stop), span in zip(ranges, spans, strict=True):
        for frame in range(start, stop):
            truth[frame, filled[frame]] = span.position_m
            filled[frame] += 1
    return truth


def _geometry(positions: tuple[Position, ...] | None) -> NDArray[np.float64]:
    return np.asarray(positions, dtype=np.float64).reshape(-1, 3)


# ----------------------------------------------------------------------------- text tables


def natural_sort_key(name: str) -> tuple[tuple[str | int, ...], str]:
    """Sort key that orders digit runs by value: ``a_2`` before ``a_10``.

    Text between digit runs compares as text (case-sensitive); signs and decimal
    points are text. Names equal but for leading zeros fall back to plain order.
    """
    parts = _DIGITS.split(name)  # text at even indices, digit runs at odd ones
    return tuple(int(part) if k % 2 else part for k, part in enumerate(parts)), name


def parse_table(text: str, source: str, *, delimiter: str | None = None) -> NDArray[np.float64]:
    """The rows of numbers in ``text`` as a 2-D float64 array (rows, columns).

    Cells are separated by ``delimiter`` (None: runs of whitespace); blank lines and
    lines starting with ``#`` are skipped.

    Raises
    ------
    EchoLocError
        Naming ``source`` and the line: no rows, a non-numeric or empty cell, rows of
        different lengths, a NaN or infinite value.
    """
    rows: list[NDArray[np.float64]] = []
    first_line = 0
    for number, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped or stripped.startswith("#"):
            continue
        cells = stripped.split(delimiter)
        try:
            row = np.array(cells, dtype=np.float64)
        except ValueError:
            for column, cell in enumerate(cells, start=1):
                try:
                    float(cell)
                except ValueError:
                    shown = "an empty cell" if not cell.strip() else f"{cell.strip()!r}, not a number"
                    raise _error(source, f"line {number}, column {column}: {shown}") from None
            raise _error(source, f"line {number}: not a row of numbers") from None
        if not rows:
            first_line = number
        elif row.shape[0] != rows[0].shape[0]:
            raise _error(
                source,
                f"line {number} has {row.shape[0]} values but line {first_line} has {rows[0].shape[0]} "
                "(ragged rows)",
            )
        bad = ~np.isfinite(row)
        if bad.any():
            column = int(np.argmax(bad)) + 1
            raise _error(source, f"line {number}, column {column}: {cells[column - 1]!r} is not finite")
        rows.append(row)
    if not rows:
        raise _error(source, "holds no rows of numbers")
    return np.stack(rows)


def _read_text(path: Path, max_bytes: int) -> str:
    """The UTF-8 text of the regular file ``path`` of at most ``max_bytes``."""
    return read_text_input(path, what="file", max_bytes=max_bytes)


def read_table(path: Path) -> NDArray[np.float64]:
    """A text table of numbers, comma- or whitespace-separated (see :func:`parse_table`).

    The separator is a comma when the first row holds one, else whitespace.
    """
    text = _read_text(path, MAX_TABLE_BYTES)
    first = next(
        (line for line in text.splitlines() if line.strip() and not line.strip().startswith("#")), ""
    )
    return parse_table(text, str(path), delimiter="," if "," in first else None)


def _samples_dtype(values: NDArray[Any]) -> type[np.floating[Any]]:
    """float32 for whole numbers float32 holds exactly (ADC counts), else float64."""
    whole = bool(np.all(values == np.round(values)))
    small = values.size == 0 or float(np.max(np.abs(values))) <= _FLOAT32_EXACT_INTEGER
    return np.float32 if whole and small else np.float64


# ----------------------------------------------------------------------------- SPiEL layout


@dataclass(frozen=True)
class SpielLabels:
    """The content of one ``*_labels.csv``.

    Attributes
    ----------
    chip_range_mm
        (n_ch,) the chip's own range reading per channel, mm.
    chip_amplitude
        (n_ch,) the chip's amplitude reading per channel (chip units).
    position_mm
        The target's position (x, y, z), mm.
    """

    chip_range_mm: NDArray[np.float64]
    chip_amplitude: NDArray[np.float64]
    position_mm: Position


def parse_spiel_labels(table: NDArray[np.float64], source: str) -> SpielLabels:
    """Check and split a labels table: one row per channel, 6 columns.

    Columns: channel index (0, 1, ... in order), range (mm), amplitude, target x, y, z
    (mm, the same on every row).
    """
    if table.shape[1] != _LABEL_COLUMNS:
        raise _error(
            source,
            f"has {table.shape[1]} values a line, expected {_LABEL_COLUMNS} "
            "(channel, range mm, amplitude, x mm, y mm, z mm)",
        )
    channels = table[:, 0]
    expected = np.arange(table.shape[0], dtype=np.float64)
    if not np.array_equal(channels, expected):
        k = int(np.argmax(channels != expected))
        raise _error(source, f"line {k + 1} is labelled channel {channels[k]:g}, expected {k}")
    positions = table[:, 3:6]
    differ = np.any(positions != positions[0], axis=1)
    if differ.any():
        k = int(np.argmax(differ))
        raise _error(
            source,
            f"line {k + 1} puts the target at {positions[k].tolist()} mm but line 1 at "
            f"{positions[0].tolist()} mm",
        )
    x, y, z = (float(v) for v in positions[0])
    return SpielLabels(table[:, 1].copy(), table[:, 2].copy(), (x, y, z))


def _distance_mm(a: Position, b: Position) -> float:
    """The largest coordinate difference of two positions (same unit)."""
    return max(abs(p - q) for p, q in zip(a, b, strict=True))


def _name_position_mm(name: str) -> Position | None:
    match = _NAME_POSITION.match(name)
    if match is None:
        return None
    return (float(match["x"]), float(match["y"]), float(match["z"]))


def spiel_frame_names(folder: Path) -> list[str]:
    """The stems (``name`` of ``name_frames.csv``) in ``folder``, in natural sort order.

    Raises
    ------
    EchoLocError
        If ``folder`` is not a folder, holds no ``*_frames.csv``, or a frames file has
        no labels file or a labels file no frames file.
    """
    if not folder.is_dir():
        raise _error(folder, "no such folder" if not folder.exists() else "is not a folder")
    try:
        names = [entry.name for entry in folder.iterdir() if entry.is_file()]
    except OSError as exc:
        raise _error(folder, f"cannot list: {exc.strerror or exc}") from None
    frames = {name[: -len(_FRAMES_SUFFIX)] for name in names if name.endswith(_FRAMES_SUFFIX)}
    labels = {name[: -len(_LABELS_SUFFIX)] for name in names if name.endswith(_LABELS_SUFFIX)}
    if not frames:
        raise _error(folder, f"holds no *{_FRAMES_SUFFIX} files (the SPiEL layout)")
    if unlabelled := sorted(frames - labels, key=natural_sort_key):
        stem = unlabelled[0]
        raise _error(folder / f"{stem}{_FRAMES_SUFFIX}", f"has no labels file {stem}{_LABELS_SUFFIX}")
    if orphans := sorted(labels - frames, key=natural_sort_key):
        stem = orphans[0]
        raise _error(folder / f"{stem}{_LABELS_SUFFIX}", f"has no frames file {stem}{_FRAMES_SUFFIX}")
    return sorted(frames, key=natural_sort_key)


def _spiel_frame(path: Path, n_channels: int, n_columns: int | None) -> NDArray[np.float64]:
    table = parse_table(_read_text(path, MAX_SPIEL_FILE_BYTES), str(path))
    if table.shape[0] != n_channels:
        raise _error(path, f"has {table.shape[0]} channel lines, expected {n_channels} (one per receiver)")
    if n_columns is not None and table.shape[1] != n_columns:
        raise _error(path, f"has {table.shape[1]} samples a line, but the first frame has {n_columns}")
    return table


def spiel_recording(
    frames: NDArray[np.float64],
    positions_mm: NDArray[np.float64],
    background: NDArray[np.float64] | None,
    head: ImportHead,
    source: str,
) -> Recording:
    """Build and validate the recording of a SPiEL data set (no file is touched).

    Parameters
    ----------
    frames
        (n_frames, n_rx, n_samples) envelope samples (chip units).
    positions_mm
        (n_frames, 3) target position per frame, mm.
    background
        (n_frames, n_rx, n_samples) empty-scene samples, or None.
    head
        The complete sensor head (:data:`SPIEL_HEAD`, possibly overridden).
    source
        The folder, for messages.
    """
    dtype = _samples_dtype(frames if background is None else np.concatenate([frames, background]))
    return _head_recording(
        head,
        source,
        frames=frames.astype(dtype),
        background=None if background is None else background.astype(dtype),
        truth_positions_m=(np.asarray(positions_mm, dtype=np.float64) / 1000.0)[:, np.newaxis, :],
    )


def _head_recording(head: ImportHead, source: str, **data: Any) -> Recording:
    """The validated recording of ``head``'s attributes and geometry with the ``data`` arrays."""
    recording = Recording(
        sample_rate_hz=_given(head.sample_rate_hz),
        signal_kind=_given(head.signal_kind),
        carrier_hz=head.carrier_hz,
        speed_of_sound_m_s=head.speed_of_sound_m_s,
        temperature_c=head.temperature_c,
        relative_humidity=head.relative_humidity,
        transmitters_m=_geometry(head.transmitters_m),
        receivers_m=_geometry(head.receivers_m),
        source=source,
        **data,
    )
    return validate_recording(recording)


def _given(value: Any) -> Any:
    if value is None:  # pragma: no cover - SPIEL_HEAD gives every required field
        raise EchoLocError("the sensor head lacks a required field")
    return value


def read_spiel(folder: Path, head: ImportHead | None = None, n_samples: int | None = None) -> Recording:
    """Read a folder of the SPiEL CSV layout into a validated recording.

    Every ``<name>_frames.csv`` (4 lines of 64 integers: the channels' envelope
    samples) pairs with ``<name>_labels.csv`` (4 lines of 6 numbers: channel, the
    chip's range in mm, its amplitude, and the target's x, y, z in mm); frames follow
    the natural sort order of the names. When the sibling folder ``<folder>_bg``
    exists, each frame's ``<name>_frames.csv`` there is its background.

    Parameters
    ----------
    folder
        The folder of frame/label pairs (for example ``dataset/train_val``).
    head
        Overrides of :data:`SPIEL_HEAD` (a sensor-head TOML without ``background``
        or ``truth``), or None.
    n_samples
        Samples kept per channel, the first ones; None drops the last 2 of every
        line as the published loader does (64 -> 62).

    Raises
    ------
    EchoLocError
        Naming the file: missing partners or background files, ragged or
        non-numeric lines, NaN, a channel count that does not match the receivers,
        labels that disagree with each other or with the position in the name,
        ``n_samples`` beyond the line length.
    """
    if head is not None:
        for key, value in (("background", head.background_path), ("truth", head.truth or None)):
            if value is not None:
                raise _error(
                    head.source,
                    f"{key} is not used by the SPiEL import (backgrounds come from the "
                    f"{_BACKGROUND_FOLDER_SUFFIX} folder, truth from the labels)",
                )
        if head.waveform_path is not None:
            raise _error(
                head.source, "waveform is not used by the SPiEL import (the chip's pulse is unknown)"
            )
    full = SPIEL_HEAD if head is None else merge_heads(SPIEL_HEAD, head)
    n_channels = len(_given(full.receivers_m))
    stems = spiel_frame_names(folder)
    named_folder = folder if folder.name not in ("", "..") else folder.resolve()  # "." names no folder
    bg_folder = named_folder.parent / f"{named_folder.name}{_BACKGROUND_FOLDER_SUFFIX}"
    has_background = bg_folder.is_dir()

    frames: list[NDArray[np.float64]] = []
    backgrounds: list[NDArray[np.float64]] = []
    positions: list[Position] = []
    n_columns: int | None = None
    for stem in stems:
        frame_path = folder / f"{stem}{_FRAMES_SUFFIX}"
        frame = _spiel_frame(frame_path, n_channels, n_columns)
        n_columns = frame.shape[1]
        labels_path = folder / f"{stem}{_LABELS_SUFFIX}"
        labels_table = parse_table(_read_text(labels_path, MAX_SPIEL_FILE_BYTES), str(labels_path))
        if labels_table.shape[0] != n_channels:
            raise _error(
                labels_path,
                f"has {labels_table.shape[0]} channel lines but {frame_path.name} has {n_channels}",
            )
        labels = parse_spiel_labels(labels_table, str(labels_path))
        named = _name_position_mm(stem)
        if named is not None and _distance_mm(named, labels.position_mm) > _SPIEL_POSITION_TOLERANCE_MM:
            raise _error(
                labels_path,
                f"puts the target at {list(labels.position_mm)} mm but the file name at {list(named)} mm",
            )
        frames.append(frame)
        positions.append(labels.position_mm)
        if has_background:
            bg_path = bg_folder / f"{stem}{_FRAMES_SUFFIX}"
            if not bg_path.is_file():
                raise _error(bg_path, f"is missing: the background of {frame_path.name}")
            backgrounds.append(_spiel_frame(bg_path, n_channels, n_columns))

    assert n_columns is not None  # spiel_frame_names returns at least one
    if n_samples is None:
        keep = n_columns - _SPIEL_DROPPED_COLUMNS
        if keep < 1:
            raise _error(folder, f"frames have {n_columns} samples a line, too few to drop the last 2")
    else:
        keep = n_samples
        if not 1 <= keep <= n_columns:
            raise _error(folder, f"frames have {n_columns} samples a line, cannot keep {n_samples}")
    stacked = np.stack(frames)[:, :, :keep]
    background = np.stack(backgrounds)[:, :, :keep] if has_background else None
    return spiel_recording(stacked, np.asarray(positions), background, full, str(folder))


# ----------------------------------------------------------------------------- samples layout


def _npy_declared_bytes(fh: BinaryIO) -> int:
    """The bytes of data a ``.npy`` header declares (shape times item size), from the header alone."""
    shape, dtype = read_npy_header(fh)
    return math.prod(shape) * dtype.itemsize


def _load_npy(path: Path) -> NDArray[Any]:
    """A regular ``.npy`` file's array, its declared size checked against the file before it is read."""
    with open_input(path, what="file", max_bytes=MAX_RECORDING_BYTES) as fh:
        try:
            declared = _npy_declared_bytes(fh)
            stored = os.fstat(fh.fileno()).st_size - fh.tell()
            if declared <= stored:
                fh.seek(0)
                array = np.load(fh, allow_pickle=False)
        except (OSError, ValueError, EOFError) as exc:
            raise _error(path, f"not a readable .npy file ({_one_line(str(exc))})") from None
    if declared > stored:
        raise _error(
            path, f"declares {declared} bytes of data but holds {stored} (a truncated or corrupt .npy)"
        )
    if not isinstance(array, np.ndarray):
        raise _error(path, "is not a single .npy array")
    return array


def _numeric(path: Path, array: NDArray[Any], allow_complex: bool) -> NDArray[Any]:
    """float32/float64 (complex64/complex128 where allowed); integers become float64."""
    kind = array.dtype.kind
    if kind in "iu":
        converted: NDArray[Any] = array.astype(np.float64)
    elif kind == "f":
        converted = array.astype(np.float64 if array.dtype.itemsize > 4 else np.float32)
    elif kind == "c" and allow_complex:
        converted = array.astype(np.complex128 if array.dtype.itemsize > 8 else np.complex64)
    elif kind == "c":
        raise _error(path, f"holds complex samples ({array.dtype}) but signal_kind is not 'iq'")
    else:
        raise _error(path, f"holds {array.dtype} values, expected numbers")
    bad = ~np.isfinite(converted)
    if bad.any():
        index = [int(i) for i in np.argwhere(bad)[0]]
        raise _error(path, f"holds {int(bad.sum())} NaN or infinite value(s), first at index {index}")
    return converted


def _read_array(path: Path, allow_complex: bool) -> NDArray[Any]:
    """A ``.npy`` (any numeric dtype) or a text table (float64) of numbers."""
    if path.suffix.lower() in _NPY_SUFFIXES:
        return _numeric(path, _load_npy(path), allow_complex)
    return read_table(path)


def _as_frames(path: Path, array: NDArray[Any], n_rx: int, what: str) -> NDArray[Any]:
    """(n_frames, n_rx, n_samples) from a 3-D array, or a 2-D one of n_frames * n_rx rows."""
    if array.ndim == 3:
        if array.shape[1] != n_rx:
            raise _error(path, f"{what} have {array.shape[1]} channels but the head has {n_rx} receivers")
        return array
    if array.ndim == 2:
        rows = array.shape[0]
        if rows % n_rx:
            raise _error(
                path,
                f"has {rows} rows, not a multiple of the head's {n_rx} receivers "
                "(one row per frame and receiver)",
            )
        return array.reshape(rows // n_rx, n_rx, array.shape[1])
    raise _error(path, f"has shape {array.shape}, expected (n_frames, n_rx, n_samples)")


def samples_recording(
    frames: NDArray[Any],
    head: ImportHead,
    source: str,
    background: NDArray[Any] | None = None,
    waveform: NDArray[Any] | None = None,
) -> Recording:
    """Build and validate a recording from samples and a complete head (no file is touched).

    Parameters
    ----------
    frames
        (n_frames, n_rx, n_samples) samples.
    head
        A head with sample_rate_hz, signal_kind, transmitters and receivers.
    source
        The samples file, for messages.
    background
        (n_rx, n_samples) or (n_frames, n_rx, n_samples) empty-scene samples, or None.
    waveform
        (n_w,) SENT template, or None.
    """
    _require(head, SAMPLES_REQUIRED_KEYS, "`import samples`")
    return _head_recording(
        head,
        source,
        frames=frames,
        background=background,
        waveform=waveform,
        truth_positions_m=truth_positions_m(head.truth, int(frames.shape[0]), head.source),
    )


def read_samples(path: Path, head: ImportHead) -> Recording:
    """Read plain samples described by a sensor head into a validated recording.

    Parameters
    ----------
    path
        A ``.npy`` of shape (n_frames, n_rx, n_samples), or a text table (``.csv``,
        ``.txt``, ...; comma- or whitespace-separated, ``#`` comments) with one row
        per frame and receiver: row ``r`` is frame ``r // n_rx``, receiver
        ``r % n_rx``, ``n_rx`` the head's receiver count.
    head
        The sensor head (:func:`read_head`); its ``background`` is read the same
        way, shaped (n_rx, n_samples) or one per frame; its ``waveform`` is a 1-D
        ``.npy`` or a text table of one row or one column.

    Raises
    ------
    EchoLocError
        Naming the file: a missing key in the head, an unreadable or non-numeric
        file, ragged rows, NaN, a channel count that does not fit the receivers, a
        background of the wrong shape, truth outside the frames.
    """
    _require(head, SAMPLES_REQUIRED_KEYS, "`import samples`")
    n_rx = len(_given(head.receivers_m))
    iq = head.signal_kind == "iq"
    if iq and path.suffix.lower() not in _NPY_SUFFIXES:
        raise _error(path, "iq samples are complex: give them as a .npy (text tables hold real numbers)")
    raw = _read_array(path, iq)
    frames = _as_frames(path, raw, n_rx, "samples")
    if raw.dtype.kind == "f" and path.suffix.lower() not in _NPY_SUFFIXES:
        frames = frames.astype(_samples_dtype(frames))
    background = None
    if head.background_path is not None:
        bg_path = head.background_path
        bg = _read_array(bg_path, iq)
        if bg.ndim == 2 and bg.shape[0] == n_rx:
            background = bg
        else:
            background = _as_frames(bg_path, bg, n_rx, "background")
            if background.shape[0] != frames.shape[0]:
                raise _error(
                    bg_path,
                    f"holds {background.shape[0]} background frames but {path.name} holds {frames.shape[0]} "
                    f"(give one background of {n_rx} rows, or one per frame)",
                )
        if background.shape[-1] != frames.shape[-1]:
            raise _error(
                bg_path,
                f"has {background.shape[-1]} samples a channel but {path.name} has {frames.shape[-1]}",
            )
    waveform = None
    if head.waveform_path is not None:
        wave = _read_array(head.waveform_path, iq)
        if wave.ndim == 2 and 1 in wave.shape:
            wave = wave.reshape(-1)
        if wave.ndim != 1:
            raise _error(head.waveform_path, f"has shape {wave.shape}, expected one row or one column")
        waveform = wave.astype(np.complex128 if wave.dtype.kind == "c" else np.float64)
    return samples_recording(frames, head, str(path), background, waveform)


def read_samples_with_head(path: Path, head: Any) -> Recording:
    """Read plain samples (as :func:`read_samples`: a ``.npy`` or a text table, receivers in
    ``receivers_m`` order) described by a head file with sections
    (:class:`echoloc.io.head.SensorHead`): its header gives the geometry, rates, air and pulse."""
    header = head.header
    iq = header.signal_kind == "iq"
    if iq and path.suffix.lower() not in _NPY_SUFFIXES:
        raise _error(path, "iq samples are complex: give them as a .npy (text tables hold real numbers)")
    raw = _read_array(path, iq)
    frames = _as_frames(path, raw, header.n_receivers, "samples")
    if raw.dtype.kind == "f" and path.suffix.lower() not in _NPY_SUFFIXES:
        frames = frames.astype(_samples_dtype(frames))
    elif raw.dtype.kind in "iu":
        frames = frames.astype(np.float64)
    receiver_gain = header.receiver_gain
    if receiver_gain is not None and receiver_gain.shape[-1] != frames.shape[-1]:
        raise _error(
            path,
            f"has {frames.shape[-1]} samples a channel but the head's gain curve has "
            f"{receiver_gain.shape[-1]}",
        )
    return validate_recording(replace(header, frames=frames, source=str(path)))
