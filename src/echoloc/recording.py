"""The Recording value and its file formats (HDF5 and NPZ), per ``FORMATS.md``.

A :class:`Recording` holds exactly what the contract's recording file holds, with
units in the field names. :func:`read_recording` and :func:`write_recording` move it
to and from disk; :func:`validate_recording` enforces every rule of the contract
and raises :class:`~echoloc.errors.RecordingError` naming the file, the field and the
value.
"""

from __future__ import annotations

import contextlib
import os
import secrets
import warnings
import zipfile
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import h5py
import numpy as np
from numpy.typing import NDArray

from echoloc.errors import RecordingError

FORMAT_NAME = "echoloc-recording"
FORMAT_VERSION = 1
SIGNAL_KINDS = ("rf", "envelope", "iq")


@dataclass(frozen=True, eq=False)
class Recording:
    """Frames of received samples with the geometry and air state they were taken in.

    Attributes
    ----------
    sample_rate_hz
        Sample rate of ``frames`` and ``waveform``, Hz.
    transmitters_m, receivers_m
        Positions in the sensor frame (z = boresight), m, shapes (n_tx, 3), (n_rx, 3).
    frames
        (n_frames, n_rx, n_samples); sample k was taken k / sample_rate_hz after the
        frame's emission started.
    waveform
        The pulse an ideal point reflector returns (the SENT template); sample 0 is
        the instant of emission. Required for ``rf`` and ``iq`` data.
    signal_kind
        ``"rf"``, ``"envelope"`` or ``"iq"``.
    truth_positions_m
        (n_frames, n_max, 3) known reflector positions, NaN rows as padding; used by
        ``calibrate`` and ``evaluate`` only.
    source
        Where the recording came from (a path, or ``"<memory>"``), for messages.
    """

    sample_rate_hz: float
    transmitters_m: NDArray[np.float64]
    receivers_m: NDArray[np.float64]
    frames: NDArray[np.floating] | NDArray[np.complexfloating]
    waveform: NDArray[np.float64] | None = None
    signal_kind: str = "rf"
    carrier_hz: float | None = None
    speed_of_sound_m_s: float | None = None
    temperature_c: float | None = None
    relative_humidity: float | None = None
    frame_times_s: NDArray[np.float64] | None = None
    frame_transmitter: NDArray[np.int64] | None = None
    background: NDArray[np.floating] | NDArray[np.complexfloating] | None = None
    transmitter_axes: NDArray[np.float64] | None = None
    receiver_axes: NDArray[np.float64] | None = None
    truth_positions_m: NDArray[np.float64] | None = None
    source: str = "<memory>"

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[0])

    @property
    def n_receivers(self) -> int:
        return int(self.receivers_m.shape[0])

    @property
    def n_samples(self) -> int:
        return int(self.frames.shape[2])


class RecordingWarning(UserWarning):
    """A recording was read but something in it deserves the user's attention."""


# Contract (file) names of the root attributes and datasets, mapped to Recording fields.
_REQUIRED_ATTRS = ("format", "version", "sample_rate_hz")
_OPTIONAL_FLOAT_ATTRS = ("carrier_hz", "speed_of_sound_m_s", "temperature_c", "relative_humidity")
_DATASET_FIELDS: dict[str, str] = {
    "transmitters": "transmitters_m",
    "receivers": "receivers_m",
    "frames": "frames",
    "waveform": "waveform",
    "frame_times": "frame_times_s",
    "frame_transmitter": "frame_transmitter",
    "background": "background",
    "transmitter_axes": "transmitter_axes",
    "receiver_axes": "receiver_axes",
    "truth_positions": "truth_positions_m",
}
_REQUIRED_DATASETS = ("transmitters", "receivers", "frames")
_HDF5_SUFFIXES = (".h5", ".hdf5")
_NPZ_SUFFIXES = (".npz",)
_ABSOLUTE_ZERO_C = -273.15
_ZIP_MAGIC = b"PK\x03\x04"

_AnyArray = NDArray[Any]


def _one_line(text: str) -> str:
    """Collapse ``text`` to a single line (messages go to one line of stderr)."""
    return " ".join(text.split())


def _error(source: str, message: str) -> RecordingError:
    """Build the one-line :class:`RecordingError` ``"<source>: <message>"``."""
    return RecordingError(_one_line(f"{source}: {message}"))


def _is_sample_dtype(dtype: np.dtype[Any]) -> bool:
    """True for float32/float64/complex64/complex128 in either byte order."""
    return (dtype.kind == "f" and dtype.itemsize in (4, 8)) or (
        dtype.kind == "c" and dtype.itemsize in (8, 16)
    )


def _is_real_number(value: object) -> bool:
    """True for Python or NumPy ints and floats (not bools, not complex)."""
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(
        value, bool | np.bool_
    )


# ----------------------------------------------------------------------------- validation


def _check_array(source: str, name: str, value: object) -> _AnyArray:
    if not isinstance(value, np.ndarray):
        raise _error(source, f"{name} must be a numpy array, got {type(value).__name__}")
    return value


def _check_real_float(source: str, name: str, arr: _AnyArray) -> None:
    if arr.dtype.kind != "f":
        raise _error(source, f"{name} has dtype {arr.dtype}, expected a float dtype (float64)")


def _check_shape(source: str, name: str, arr: _AnyArray, expected: tuple[int, ...]) -> None:
    if arr.shape != expected:
        want = "(" + ", ".join(str(n) for n in expected) + ("," if len(expected) == 1 else "") + ")"
        raise _error(source, f"{name} has shape {arr.shape}, expected {want}")


def _check_finite(source: str, name: str, arr: _AnyArray) -> None:
    bad = ~np.isfinite(arr)
    if bad.any():
        first = tuple(int(i) for i in np.argwhere(bad)[0])
        raise _error(
            source,
            f"{name} has {int(bad.sum())} non-finite value(s), "
            f"first {arr[first].item()} at index {list(first)}",
        )


def _check_geometry(source: str, name: str, value: object, n: int | None) -> _AnyArray:
    """Positions or axes: finite float array of shape (n, 3) (n >= 1 when not given)."""
    arr = _check_array(source, name, value)
    _check_real_float(source, name, arr)
    if n is None:
        if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] < 1:
            raise _error(source, f"{name} has shape {arr.shape}, expected (n, 3) with n >= 1")
    else:
        _check_shape(source, name, arr, (n, 3))
    _check_finite(source, name, arr)
    return arr


def _check_optional_float(
    source: str,
    name: str,
    value: object,
    low: float | None,
    low_inclusive: bool,
    high: float | None = None,
) -> None:
    if value is None:
        return
    if not _is_real_number(value):
        raise _error(source, f"{name} must be a number, got {value!r}")
    number = float(value)  # type: ignore[arg-type]
    if not np.isfinite(number):
        raise _error(source, f"{name} must be finite, got {number!r}")
    if low is not None and (number < low or (number == low and not low_inclusive)):
        relation = ">=" if low_inclusive else ">"
        raise _error(source, f"{name} must be {relation} {low:g}, got {number!r}")
    if high is not None and number > high:
        raise _error(source, f"{name} must be <= {high:g}, got {number!r}")


def _check_nonnegative(source: str, name: str, arr: _AnyArray) -> None:
    negative = (arr < 0) & np.isfinite(arr)
    if negative.any():
        first = tuple(int(i) for i in np.argwhere(negative)[0])
        raise _error(
            source,
            f"{name} is envelope data but has {int(negative.sum())} negative sample(s), "
            f"first {arr[first].item()} at index {list(first)}",
        )


def _validate(rec: Recording, *, allow_nonfinite: bool) -> None:
    """Check every rule of the contract; non-finite samples may be let through."""
    src = rec.source

    # Scalars.
    if not _is_real_number(rec.sample_rate_hz):
        raise _error(src, f"sample_rate_hz must be a number, got {rec.sample_rate_hz!r}")
    rate = float(rec.sample_rate_hz)
    if not np.isfinite(rate) or rate <= 0:
        raise _error(src, f"sample_rate_hz must be finite and > 0, got {rate!r}")
    if rec.signal_kind not in SIGNAL_KINDS:
        kinds = ", ".join(repr(k) for k in SIGNAL_KINDS)
        raise _error(src, f"signal_kind is {rec.signal_kind!r}, expected one of {kinds}")
    _check_optional_float(src, "carrier_hz", rec.carrier_hz, 0.0, False)
    _check_optional_float(src, "speed_of_sound_m_s", rec.speed_of_sound_m_s, 0.0, False)
    _check_optional_float(src, "temperature_c", rec.temperature_c, _ABSOLUTE_ZERO_C, False)
    _check_optional_float(src, "relative_humidity", rec.relative_humidity, 0.0, True, 1.0)

    # Geometry.
    tx = _check_geometry(src, "transmitters", rec.transmitters_m, None)
    rx = _check_geometry(src, "receivers", rec.receivers_m, None)
    n_tx, n_rx = int(tx.shape[0]), int(rx.shape[0])

    # Frames.
    frames = _check_array(src, "frames", rec.frames)
    if frames.ndim != 3:
        raise _error(src, f"frames has shape {frames.shape}, expected 3-D (n_frames, n_rx, n_samples)")
    is_complex = frames.dtype.kind == "c"
    if not _is_sample_dtype(frames.dtype):
        raise _error(src, f"frames has dtype {frames.dtype}, expected float32, float64 or complex64")
    if is_complex and rec.signal_kind != "iq":
        raise _error(
            src,
            f"frames has complex dtype {frames.dtype} but signal_kind is "
            f"{rec.signal_kind!r} (complex samples need signal_kind 'iq')",
        )
    if not is_complex and rec.signal_kind == "iq":
        raise _error(src, f"frames has real dtype {frames.dtype} but signal_kind 'iq' needs complex")
    n_frames, n_ch, n_samples = (int(n) for n in frames.shape)
    if n_ch != n_rx:
        raise _error(src, f"frames has {n_ch} channels but receivers has {n_rx}")
    if n_frames < 1:
        raise _error(src, f"frames has shape {frames.shape}: no frames")
    if n_samples < 1:
        raise _error(src, f"frames has shape {frames.shape}: no samples")
    if not allow_nonfinite:
        _check_finite(src, "frames", frames)
    if rec.signal_kind == "envelope":
        _check_nonnegative(src, "frames", frames)

    # Waveform.
    if rec.waveform is None:
        if rec.signal_kind in ("rf", "iq"):
            raise _error(src, f"waveform is missing; it is required for signal_kind {rec.signal_kind!r}")
    else:
        waveform = _check_array(src, "waveform", rec.waveform)
        allowed = "fc" if rec.signal_kind == "iq" else "f"
        if waveform.dtype.kind not in allowed:
            expected = "float64 or complex" if rec.signal_kind == "iq" else "float64"
            raise _error(src, f"waveform has dtype {waveform.dtype}, expected {expected}")
        if waveform.ndim != 1 or waveform.shape[0] < 1:
            raise _error(src, f"waveform has shape {waveform.shape}, expected (n_w,) with n_w >= 1")
        _check_finite(src, "waveform", waveform)

    # Per-frame metadata.
    if rec.frame_times_s is not None:
        times = _check_array(src, "frame_times", rec.frame_times_s)
        _check_real_float(src, "frame_times", times)
        _check_shape(src, "frame_times", times, (n_frames,))
        _check_finite(src, "frame_times", times)
    if rec.frame_transmitter is not None:
        fired = _check_array(src, "frame_transmitter", rec.frame_transmitter)
        if fired.dtype.kind not in "iu":
            raise _error(src, f"frame_transmitter has dtype {fired.dtype}, expected an integer dtype")
        _check_shape(src, "frame_transmitter", fired, (n_frames,))
        outside = (fired < 0) | (fired >= n_tx)
        if outside.any():
            k = int(np.argmax(outside))
            raise _error(
                src,
                f"frame_transmitter[{k}] is {int(fired[k])}, expected 0..{n_tx - 1} "
                f"(transmitters has {n_tx})",
            )

    # Background.
    if rec.background is not None:
        bg = _check_array(src, "background", rec.background)
        allowed = "fc" if rec.signal_kind == "iq" else "f"
        if bg.dtype.kind not in allowed:
            expected = "float or complex" if rec.signal_kind == "iq" else "float"
            raise _error(src, f"background has dtype {bg.dtype}, expected a {expected} dtype")
        if bg.shape not in ((n_rx, n_samples), (n_frames, n_rx, n_samples)):
            raise _error(
                src,
                f"background has shape {bg.shape}, expected ({n_rx}, {n_samples}) "
                f"or ({n_frames}, {n_rx}, {n_samples})",
            )
        if not allow_nonfinite:
            _check_finite(src, "background", bg)
        if rec.signal_kind == "envelope":
            _check_nonnegative(src, "background", bg)

    # Axes.
    for name, axes, n in (
        ("transmitter_axes", rec.transmitter_axes, n_tx),
        ("receiver_axes", rec.receiver_axes, n_rx),
    ):
        if axes is None:
            continue
        arr = _check_geometry(src, name, axes, n)
        lengths = np.linalg.norm(arr, axis=1)
        if (lengths == 0).any():
            k = int(np.argmax(lengths == 0))
            raise _error(src, f"{name}[{k}] is {arr[k].tolist()}, a zero-length axis")

    # Truth.
    if rec.truth_positions_m is not None:
        truth = _check_array(src, "truth_positions", rec.truth_positions_m)
        _check_real_float(src, "truth_positions", truth)
        if truth.ndim != 3 or truth.shape[0] != n_frames or truth.shape[2] != 3:
            raise _error(src, f"truth_positions has shape {truth.shape}, expected ({n_frames}, n_max, 3)")
        if np.isinf(truth).any():
            raise _error(src, "truth_positions has infinite values (only NaN rows are padding)")
        nan = np.isnan(truth)
        partial = nan.any(axis=2) & ~nan.all(axis=2)
        if partial.any():
            frame, row = (int(i) for i in np.argwhere(partial)[0])
            raise _error(
                src,
                f"truth_positions[{frame}, {row}] is {truth[frame, row].tolist()}: "
                "a padding row must be NaN in all three coordinates",
            )


def validate_recording(rec: Recording) -> Recording:
    """Check a recording against every rule of the interchange contract.

    Parameters
    ----------
    rec
        The recording to check.

    Returns
    -------
    Recording
        ``rec`` itself, unchanged.

    Raises
    ------
    RecordingError
        One line naming ``rec.source``, the offending field and its value or shape.
    """
    _validate(rec, allow_nonfinite=False)
    return rec


def _zero_nonfinite(arr: _AnyArray) -> tuple[_AnyArray, int]:
    bad = ~np.isfinite(arr)
    count = int(bad.sum())
    if count == 0:
        return arr, 0
    fixed = arr.copy()
    fixed[bad] = 0
    return fixed, count


def repair_nonfinite(rec: Recording) -> tuple[Recording, int]:
    """Replace NaN and infinite samples by 0.

    Parameters
    ----------
    rec
        The recording; it is not modified.

    Returns
    -------
    tuple of (Recording, int)
        A copy whose ``frames`` (and ``background``, if given) hold 0 where they held
        a non-finite value, and how many samples were replaced in total.
    """
    frames, count = _zero_nonfinite(rec.frames)
    background = rec.background
    if background is not None:
        background, bg_count = _zero_nonfinite(background)
        count += bg_count
    return replace(rec, frames=frames, background=background), count


def dead_receivers(rec: Recording) -> list[int]:
    """Indices of receivers whose samples are all identical across the whole recording.

    Parameters
    ----------
    rec
        A recording with 3-D ``frames``.

    Returns
    -------
    list of int
        Receiver indices, ascending; empty when each channel holds only one sample.
    """
    frames = rec.frames
    if frames.shape[0] * frames.shape[2] < 2:
        return []
    constant = (frames == frames[:1, :, :1]).all(axis=(0, 2))
    return [int(i) for i in np.flatnonzero(constant)]


# ----------------------------------------------------------------------------- reading


def _scalar(value: object) -> object:
    """Turn an attribute as h5py or NumPy returns it into a plain Python value."""
    if isinstance(value, np.ndarray) and value.size == 1:
        value = value.reshape(()).item()
    elif isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bytes):
        with contextlib.suppress(UnicodeDecodeError):
            value = value.decode("utf-8")
    return value


def _attr_str(source: str, name: str, value: object) -> str:
    value = _scalar(value)
    if not isinstance(value, str):
        raise _error(source, f"attribute {name} must be a string, got {value!r}")
    return value


def _attr_float(source: str, name: str, value: object) -> float:
    value = _scalar(value)
    if not _is_real_number(value):
        raise _error(source, f"attribute {name} must be a number, got {value!r}")
    return float(value)  # type: ignore[arg-type]


def _as_real(source: str, name: str, arr: _AnyArray) -> NDArray[np.float64]:
    if arr.dtype.kind != "f":
        raise _error(source, f"{name} has dtype {arr.dtype}, expected float64")
    return np.asarray(arr, dtype=np.float64)


def _as_samples(source: str, name: str, arr: _AnyArray, allow_complex: bool) -> _AnyArray:
    """Samples in memory: float64, or complex128 where complex is allowed."""
    if arr.dtype.kind == "f":
        return np.asarray(arr, dtype=np.float64)
    if arr.dtype.kind == "c" and allow_complex:
        return np.asarray(arr, dtype=np.complex128)
    expected = "float64 or complex128" if allow_complex else "float64"
    raise _error(source, f"{name} has dtype {arr.dtype}, expected {expected}")


def _build(source: str, attrs: dict[str, object], data: dict[str, _AnyArray]) -> Recording:
    """Make a Recording from the raw attributes and datasets of a file."""
    for name in _REQUIRED_ATTRS:
        if name not in attrs:
            raise _error(source, f"missing required attribute {name}")
    for name in _REQUIRED_DATASETS:
        if name not in data:
            raise _error(source, f"missing required dataset {name}")

    fmt = _scalar(attrs["format"])
    if not isinstance(fmt, str) or fmt != FORMAT_NAME:
        raise _error(source, f"format is {fmt!r}, expected {FORMAT_NAME!r}")
    version = _scalar(attrs["version"])
    if not _is_real_number(version) or version != FORMAT_VERSION:
        raise _error(
            source,
            f"version is {version!r}, this reader reads version {FORMAT_VERSION} (an integer)",
        )
    sample_rate_hz = _attr_float(source, "sample_rate_hz", attrs["sample_rate_hz"])
    signal_kind = _attr_str(source, "signal_kind", attrs.get("signal_kind", "rf"))
    optional = {
        name: _attr_float(source, name, attrs[name]) if name in attrs else None
        for name in _OPTIONAL_FLOAT_ATTRS
    }

    fields: dict[str, Any] = {}
    iq = signal_kind == "iq"
    for name, field in _DATASET_FIELDS.items():
        if name not in data:
            continue
        arr = data[name]
        if name == "frame_transmitter":
            if arr.dtype.kind not in "iu":
                raise _error(source, f"{name} has dtype {arr.dtype}, expected an integer dtype")
            fields[field] = np.asarray(arr, dtype=np.int64)
        elif name == "frames":
            if not _is_sample_dtype(arr.dtype):
                raise _error(source, f"frames has dtype {arr.dtype}, expected float32, float64 or complex64")
            fields[field] = _as_samples(source, name, arr, allow_complex=True)
        elif name in ("waveform", "background"):
            fields[field] = _as_samples(source, name, arr, allow_complex=iq)
        else:
            fields[field] = _as_real(source, name, arr)

    return Recording(
        sample_rate_hz=sample_rate_hz,
        signal_kind=signal_kind,
        carrier_hz=optional["carrier_hz"],
        speed_of_sound_m_s=optional["speed_of_sound_m_s"],
        temperature_c=optional["temperature_c"],
        relative_humidity=optional["relative_humidity"],
        source=source,
        **fields,
    )


def _load_hdf5(source: str, path: Path) -> tuple[dict[str, object], dict[str, _AnyArray]]:
    attrs: dict[str, object] = {}
    data: dict[str, _AnyArray] = {}
    if not h5py.is_hdf5(path):
        raise _error(source, "not an HDF5 file (no HDF5 signature)")
    with h5py.File(path, "r") as f:
        for name in (*_REQUIRED_ATTRS, "signal_kind", *_OPTIONAL_FLOAT_ATTRS):
            if name in f.attrs:
                attrs[name] = f.attrs[name]
        for name in _DATASET_FIELDS:
            if name not in f:
                continue
            item = f[name]
            if not isinstance(item, h5py.Dataset):
                raise _error(source, f"{name} is a {type(item).__name__}, expected a dataset")
            data[name] = np.asarray(item[()])
    return attrs, data


def _load_npz(source: str, path: Path) -> tuple[dict[str, object], dict[str, _AnyArray]]:
    attrs: dict[str, object] = {}
    data: dict[str, _AnyArray] = {}
    with open(path, "rb") as fh:  # our own handle: closed even when np.load fails
        if fh.read(len(_ZIP_MAGIC)) != _ZIP_MAGIC:
            raise _error(source, "not an NPZ file (no zip signature)")
        fh.seek(0)
        loaded = np.load(fh, allow_pickle=False)
        if not isinstance(loaded, np.lib.npyio.NpzFile):
            raise _error(source, "not an NPZ archive (it holds a single .npy array)")
        with loaded:
            keys = set(loaded.files)
            for name in (*_REQUIRED_ATTRS, "signal_kind", *_OPTIONAL_FLOAT_ATTRS):
                if name in keys:
                    attrs[name] = loaded[name]
            for name in _DATASET_FIELDS:
                if name in keys:
                    data[name] = np.asarray(loaded[name])
    return attrs, data


_repair = repair_nonfinite  # read_recording's keyword shadows the function's name


def read_recording(path: str | os.PathLike[str], *, repair_nonfinite: bool = False) -> Recording:
    """Read and validate a recording file (``.h5``/``.hdf5`` or ``.npz``).

    Parameters
    ----------
    path
        The file. Its extension selects the format.
    repair_nonfinite
        Replace NaN and infinite samples by 0 (with a :class:`RecordingWarning`
        saying how many) instead of rejecting the file.

    Returns
    -------
    Recording
        Validated, with ``source=str(path)``; samples are float64 (``rf``,
        ``envelope``) or complex128 (``iq``) arrays in memory.

    Raises
    ------
    RecordingError
        One line naming the file and the problem: missing or unreadable file,
        unknown extension, missing required item, or any broken contract rule.

    Warns
    -----
    RecordingWarning
        When samples were repaired, and when a receiver's samples are all identical
        (a dead channel).
    """
    file = Path(path)
    source = str(path)
    suffix = file.suffix.lower()
    if suffix not in _HDF5_SUFFIXES + _NPZ_SUFFIXES:
        raise _error(source, f"unknown extension {file.suffix!r}, expected .h5, .hdf5 or .npz")
    if not file.exists():
        raise _error(source, "no such file")
    if not file.is_file():
        raise _error(source, "not a regular file")

    kind = "HDF5" if suffix in _HDF5_SUFFIXES else "NPZ"
    try:
        if kind == "HDF5":
            attrs, data = _load_hdf5(source, file)
        else:
            attrs, data = _load_npz(source, file)
    except RecordingError:
        raise
    except (
        OSError,
        ValueError,
        KeyError,
        TypeError,
        RuntimeError,
        EOFError,
        zipfile.BadZipFile,
    ) as exc:
        raise _error(source, f"cannot read as {kind}: {exc}") from exc

    rec = _build(source, attrs, data)
    _validate(rec, allow_nonfinite=repair_nonfinite)
    if repair_nonfinite:
        rec, count = _repair(rec)
        if count:
            warnings.warn(
                _one_line(f"{source}: replaced {count} non-finite sample(s) with 0"),
                RecordingWarning,
                stacklevel=2,
            )
        validate_recording(rec)

    dead = dead_receivers(rec)
    if dead:
        per_channel = rec.n_frames * rec.n_samples
        if len(dead) == 1:
            value = rec.frames[0, dead[0], 0]
            what = f"receiver {dead[0]} looks dead: all {per_channel} samples equal {value}"
        else:
            indices = ", ".join(str(i) for i in dead)
            what = f"receivers {indices} look dead: each has all {per_channel} samples equal"
        warnings.warn(_one_line(f"{source}: {what}"), RecordingWarning, stacklevel=2)
    return rec


# ----------------------------------------------------------------------------- writing


def _file_items(rec: Recording) -> tuple[dict[str, object], dict[str, _AnyArray]]:
    """The root attributes and datasets of ``rec``, by their contract names."""
    attrs: dict[str, object] = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "sample_rate_hz": float(rec.sample_rate_hz),
        "signal_kind": rec.signal_kind,
    }
    for name in _OPTIONAL_FLOAT_ATTRS:
        value = getattr(rec, name)
        if value is not None:
            attrs[name] = float(value)
    data: dict[str, _AnyArray] = {}
    for name, field in _DATASET_FIELDS.items():
        value = getattr(rec, field)
        if value is not None:
            data[name] = np.asarray(value)
    return attrs, data


def _write_hdf5(tmp: Path, rec: Recording) -> None:
    attrs, data = _file_items(rec)
    with h5py.File(tmp, "w") as f:
        for name, value in attrs.items():
            f.attrs[name] = value
        for name, arr in data.items():
            if name == "frames":
                f.create_dataset(name, data=arr, chunks=(1, *arr.shape[1:]))
            else:
                f.create_dataset(name, data=arr)


def _write_npz(tmp: Path, rec: Recording) -> None:
    attrs, data = _file_items(rec)
    items: dict[str, Any] = {name: np.asarray(value) for name, value in attrs.items()}
    items.update(data)
    with open(tmp, "r+b") as fh:
        np.savez(fh, **items)


def _fsync(path: Path, directory: bool = False) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        if directory:  # some platforms cannot open a directory; durability is best effort
            return
        raise
    try:
        os.fsync(fd)
    except OSError:
        if not directory:
            raise
    finally:
        os.close(fd)


def write_recording(rec: Recording, path: str | os.PathLike[str]) -> Path:
    """Validate ``rec`` and write it atomically as ``.h5``/``.hdf5`` or ``.npz``.

    The file is written under a temporary name in the target directory and then
    renamed over ``path``, so an interrupted write never leaves a partial file
    under the target name. Optional fields that are ``None`` are not written; HDF5
    ``frames`` are stored one frame per chunk, uncompressed.

    Parameters
    ----------
    rec
        The recording.
    path
        The target file; its extension selects the format.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    RecordingError
        If ``rec`` is invalid, the extension is unknown, the directory does not
        exist, or the file cannot be written.
    """
    target = Path(path)
    source = str(path)
    suffix = target.suffix.lower()
    if suffix not in _HDF5_SUFFIXES + _NPZ_SUFFIXES:
        raise _error(source, f"unknown extension {target.suffix!r}, expected .h5, .hdf5 or .npz")
    validate_recording(rec)
    parent = target.parent
    if not parent.is_dir():
        raise _error(source, f"directory {str(parent)!r} does not exist")
    if target.is_dir():
        raise _error(source, "is a directory")

    tmp = parent / f".{target.name}.{secrets.token_hex(6)}.tmp"
    try:
        with open(tmp, "xb"):  # created with the user's umask, like a plain open()
            pass
        if suffix in _HDF5_SUFFIXES:
            _write_hdf5(tmp, rec)
        else:
            _write_npz(tmp, rec)
        _fsync(tmp)
        os.replace(tmp, target)
    except BaseException as exc:
        tmp.unlink(missing_ok=True)
        if isinstance(exc, OSError | ValueError | TypeError | RuntimeError) and not isinstance(
            exc, RecordingError
        ):
            raise _error(source, f"cannot write: {exc}") from exc
        raise
    _fsync(parent, directory=True)
    return target
