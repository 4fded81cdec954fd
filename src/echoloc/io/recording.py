"""The Recording value and its file formats (HDF5 and NPZ), per ``docs/FORMATS.md``.

A :class:`Recording` holds exactly what the contract's recording file holds, with
units in the field names. :func:`read_recording` and :func:`write_recording` move it
to and from disk; :func:`validate_recording` enforces every rule of the contract
and raises :class:`~echoloc.errors.RecordingError` naming the file, the field and the
value.

:func:`write_recording_stream` writes a recording too long to hold in memory: a
header :class:`Recording` (every per-recording field, no frames; see
:func:`as_header`) and an iterable of :class:`FrameBatch`, one batch in memory at a
time.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import secrets
import select
import shutil
import socket
import stat
import struct
import subprocess
import sys
import tempfile
import threading
import time
import tokenize
import warnings
import zipfile
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import IO, Any

import h5py
import numpy as np
from numpy.typing import DTypeLike, NDArray

from echoloc.errors import RecordingError, missing_directory

FORMAT_NAME = "echoloc-recording"
FORMAT_VERSION = 1
SIGNAL_KINDS = ("rf", "envelope", "iq")
FIRING_MODES = ("sequential", "simultaneous")
REFLECTOR_KINDS = ("point", "plane", "corner")
"""The classes a ``truth_kinds`` entry may name (those ``locate --classes`` reports)."""
QUATERNION_NORM_TOLERANCE = 1e-6


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
    sensor_poses
        (n_frames, 7) pose of the sensor frame in a fixed world frame at each frame's
        emission, ``[x, y, z, qx, qy, qz, qw]``: position in m and a unit quaternion
        (ROS order), so that ``p_world = R(q) @ p_sensor + [x, y, z]``.
    receiver_gain
        (n_samples,) linear amplitude gain the receive amplifier applied to each
        sample (time-varying gain), all > 0; ``frames / receiver_gain`` is the signal
        at the transducer, except within a few samples of a stepped gain's steps
        when filters (decimation, envelope detection) follow the amplifier.
    transmitter_waveforms
        (n_tx, n_w) SENT template of each transmitter when they use different codes,
        zero-padded to a common length; ``waveform`` is transmitter 0's template.
    field_of_view_deg
        Half-angle of the cone around each transducer's axis outside which it can
        neither send nor receive an echo (the first null of its beam), degrees;
        localisation rejects points outside it. None: the half-space in front.
    truth_kinds
        The class of each column of ``truth_positions_m`` (:data:`REFLECTOR_KINDS`), for
        scoring reflector classes; a file holds it as one comma-separated string.
    firing
        ``"sequential"`` (each frame fires the transmitter in ``frame_transmitter``;
        also the meaning of ``None``) or ``"simultaneous"`` (every transmitter fires
        at the start of every frame, each with its own template).
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
    sensor_poses: NDArray[np.float64] | None = None
    receiver_gain: NDArray[np.float64] | None = None
    transmitter_waveforms: NDArray[np.float64] | NDArray[np.complex128] | None = None
    firing: str | None = None
    truth_kinds: tuple[str, ...] | None = None
    field_of_view_deg: float | None = None
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
_STR_ATTRS = ("signal_kind", "firing", "truth_kinds")
_OPTIONAL_FLOAT_ATTRS = (
    "carrier_hz",
    "speed_of_sound_m_s",
    "temperature_c",
    "relative_humidity",
    "field_of_view_deg",
)
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
    "sensor_poses": "sensor_poses",
    "receiver_gain": "receiver_gain",
    "transmitter_waveforms": "transmitter_waveforms",
}
# The datasets with one row per frame: what a FrameBatch carries besides ``frames``.
_PER_FRAME_DATASETS: dict[str, str] = {
    "frame_times": "frame_times_s",
    "frame_transmitter": "frame_transmitter",
    "truth_positions": "truth_positions_m",
    "sensor_poses": "sensor_poses",
}
_REQUIRED_DATASETS = ("transmitters", "receivers", "frames")
_HDF5_SUFFIXES = (".h5", ".hdf5")
_NPZ_SUFFIXES = (".npz",)
_ABSOLUTE_ZERO_C = -273.15
_ZIP_MAGIC = b"PK\x03\x04"
_CHUNK_BYTES = 1 << 20  # target size of a streamed HDF5 chunk (h5py's default chunk cache)

SAMPLE_RATE_RANGE_HZ = (1.0, 1e9)
"""The sample rates a recording or a scene may have, Hz (also the most a scene's ADC may
run at). Below 1 Hz a sample period outlasts any echo and a rate as small as 5e-324
divides by zero downstream; no airborne ultrasonic ADC comes near 1 GHz, and every array
the simulator makes grows with the rate."""

MAX_RECORDING_BYTES = 16 << 30
"""The most a recording file may declare, in bytes once in memory (float64/complex128
samples): a recording must fit in memory beside its processing, and a file declaring
more is far more likely corrupt than real. Checked on the declared shapes before any
data is read."""

MAX_COMPRESSION_RATIO = 1100
"""The most a compressed dataset may expand: deflate's limit is about 1032:1, so a file
declaring more is corrupt."""

HDF5_STALL_TIMEOUT_S = 5.0
"""How long the HDF5 reader may make no progress before the file is refused, s, unless
:data:`HDF5_STALL_ENV` says otherwise: a corrupt file can make libhdf5 loop forever (see
:mod:`echoloc.io._hdf5_child`), while each step of a valid read (the metadata, or a 4 MiB
block of data) takes milliseconds on a local disk."""

HDF5_STALL_ENV = "ECHOLOC_HDF5_STALL_S"
"""The environment variable that sets the HDF5 stall timeout, s: a drive spinning up, a
network file system or a loaded machine can pause a valid read for longer than the default."""

_MAX_STALL_S = 3600.0  # a longer stall timeout would leave a hung read unnoticed

HDF5_START_TIMEOUT_S = 60.0
"""How long the HDF5 reader process may take to start (Python and h5py imports), s."""

_MAX_HEADER_BYTES = 16 << 20  # the largest header message the reader process may send
_MAX_ATTRIBUTE_BYTES = 1 << 16  # the largest NPZ member read as a root attribute

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


def _refuse_flagged(
    source: str, arr: _AnyArray, flagged: NDArray[np.bool_], has: str, what: str, first_row: int = 0
) -> None:
    """Raise if any element of ``arr`` is ``flagged``, saying how many and which comes first.

    The message reads ``"{has} {count} {what}, first {value} at index [i, j, ...]"``, so
    a reader can find the offending sample in the file (``arr`` holding the file's rows from
    ``first_row`` on: the index is the file's).
    """
    if flagged.any():
        first = tuple(int(i) for i in np.argwhere(flagged)[0])
        where = [first[0] + first_row, *first[1:]]
        raise _error(
            source,
            f"{has} {int(flagged.sum())} {what}, first {arr[first].item()} at index {where}",
        )


def _check_finite(source: str, name: str, arr: _AnyArray) -> None:
    _refuse_flagged(source, arr, ~np.isfinite(arr), f"{name} has", "non-finite value(s)")


MAX_EXTENT_M = 10_000.0
"""The largest coordinate or length a recording or scene may give, m: airborne ultrasound
fades within tens of metres, and coordinates of 1e300 m overflow the geometry's squares."""


def _check_geometry(source: str, name: str, value: object, n: int | None) -> _AnyArray:
    """Positions or axes: finite float array of shape (n, 3) (n >= 1 when not given), each
    coordinate within :data:`MAX_EXTENT_M`."""
    arr = _check_array(source, name, value)
    _check_real_float(source, name, arr)
    if n is None:
        if arr.ndim != 2 or arr.shape[1] != 3 or arr.shape[0] < 1:
            raise _error(source, f"{name} has shape {arr.shape}, expected (n, 3) with n >= 1")
    else:
        _check_shape(source, name, arr, (n, 3))
    _check_finite(source, name, arr)
    if arr.size and float(np.max(np.abs(arr))) > MAX_EXTENT_M:
        raise _error(source, f"{name} has a coordinate beyond {MAX_EXTENT_M:g} m (metres expected)")
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
    _refuse_flagged(source, arr, negative, f"{name} is envelope data but has", "negative sample(s)")


def _check_frames_layout(source: str, value: object, signal_kind: str, n_rx: int) -> _AnyArray:
    """Check the ``frames`` of a recording, a header or a batch, of any frame count.

    They must be 3-D, of a sample dtype that fits ``signal_kind``, with ``n_rx``
    channels and at least one sample.
    """
    frames = _check_array(source, "frames", value)
    if frames.ndim != 3:
        raise _error(source, f"frames has shape {frames.shape}, expected 3-D (n_frames, n_rx, n_samples)")
    is_complex = frames.dtype.kind == "c"
    if not _is_sample_dtype(frames.dtype):
        raise _error(source, f"frames has dtype {frames.dtype}, expected float32, float64 or complex64")
    if is_complex and signal_kind != "iq":
        raise _error(
            source,
            f"frames has complex dtype {frames.dtype} but signal_kind is "
            f"{signal_kind!r} (complex samples need signal_kind 'iq')",
        )
    if not is_complex and signal_kind == "iq":
        raise _error(source, f"frames has real dtype {frames.dtype} but signal_kind 'iq' needs complex")
    if frames.shape[1] != n_rx:
        raise _error(source, f"frames has {frames.shape[1]} channels but receivers has {n_rx}")
    if frames.shape[2] < 1:
        raise _error(source, f"frames has shape {frames.shape}: no samples")
    return frames


def _check_samples(source: str, frames: _AnyArray, signal_kind: str, allow_nonfinite: bool) -> None:
    """The values of ``frames``: finite (unless allowed otherwise), non-negative envelopes."""
    if not allow_nonfinite:
        _check_finite(source, "frames", frames)
    if signal_kind == "envelope":
        _check_nonnegative(source, "frames", frames)


def _check_truth_kinds(source: str, kinds: object, truth_positions_m: object) -> None:
    """``truth_kinds``: known classes, one per column of ``truth_positions`` when it is given."""
    if kinds is None:
        return
    if not isinstance(kinds, tuple) or not all(isinstance(k, str) for k in kinds):
        raise _error(source, f"truth_kinds must be a tuple of strings, got {kinds!r}")
    unknown = [k for k in kinds if k not in REFLECTOR_KINDS]
    if unknown:
        allowed = ", ".join(repr(k) for k in REFLECTOR_KINDS)
        raise _error(source, f"truth_kinds names {unknown[0]!r}, expected one of {allowed}")
    if isinstance(truth_positions_m, np.ndarray) and truth_positions_m.ndim == 3:
        columns = int(truth_positions_m.shape[1])
        if columns != len(kinds):
            raise _error(
                source, f"truth_kinds names {len(kinds)} classes for the {columns} columns of truth_positions"
            )


def _check_per_frame(
    source: str,
    n_frames: int,
    n_tx: int,
    frame_times_s: object,
    frame_transmitter: object,
    truth_positions_m: object,
    sensor_poses: object,
) -> None:
    """The datasets with one row per frame (those of a recording or of one batch)."""
    if frame_times_s is not None:
        times = _check_array(source, "frame_times", frame_times_s)
        _check_real_float(source, "frame_times", times)
        _check_shape(source, "frame_times", times, (n_frames,))
        _check_finite(source, "frame_times", times)
    if frame_transmitter is not None:
        fired = _check_array(source, "frame_transmitter", frame_transmitter)
        if fired.dtype.kind not in "iu":
            raise _error(source, f"frame_transmitter has dtype {fired.dtype}, expected an integer dtype")
        _check_shape(source, "frame_transmitter", fired, (n_frames,))
        outside = (fired < 0) | (fired >= n_tx)
        if outside.any():
            k = int(np.argmax(outside))
            raise _error(
                source,
                f"frame_transmitter[{k}] is {int(fired[k])}, expected 0..{n_tx - 1} "
                f"(transmitters has {n_tx})",
            )
    if truth_positions_m is not None:
        truth = _check_array(source, "truth_positions", truth_positions_m)
        _check_real_float(source, "truth_positions", truth)
        if truth.ndim != 3 or truth.shape[0] != n_frames or truth.shape[2] != 3:
            raise _error(source, f"truth_positions has shape {truth.shape}, expected ({n_frames}, n_max, 3)")
        if np.isinf(truth).any():
            raise _error(source, "truth_positions has infinite values (only NaN rows are padding)")
        nan = np.isnan(truth)
        partial = nan.any(axis=2) & ~nan.all(axis=2)
        if partial.any():
            frame, row = (int(i) for i in np.argwhere(partial)[0])
            raise _error(
                source,
                f"truth_positions[{frame}, {row}] is {truth[frame, row].tolist()}: "
                "a padding row must be NaN in all three coordinates",
            )
    if sensor_poses is not None:
        poses = _check_array(source, "sensor_poses", sensor_poses)
        _check_real_float(source, "sensor_poses", poses)
        _check_shape(source, "sensor_poses", poses, (n_frames, 7))
        _check_finite(source, "sensor_poses", poses)
        norms = np.linalg.norm(poses[:, 3:], axis=1)
        off = np.abs(norms - 1.0) > QUATERNION_NORM_TOLERANCE
        if off.any():
            k = int(np.argmax(off))
            raise _error(
                source,
                f"sensor_poses[{k}] has quaternion [qx, qy, qz, qw] = {poses[k, 3:].tolist()} "
                f"of norm {float(norms[k]):.9g}, expected a unit quaternion "
                f"(|norm - 1| <= {QUATERNION_NORM_TOLERANCE:g})",
            )


def _check_templates(
    source: str, signal_kind: str, waveform: object, transmitter_waveforms: object, n_tx: int
) -> None:
    """``waveform`` and ``transmitter_waveforms``, and that they agree on transmitter 0."""
    allowed = "fc" if signal_kind == "iq" else "f"
    expected = "float64 or complex" if signal_kind == "iq" else "float64"
    first: _AnyArray | None = None
    if waveform is None:
        if signal_kind in ("rf", "iq"):
            raise _error(source, f"waveform is missing; it is required for signal_kind {signal_kind!r}")
    else:
        first = _check_array(source, "waveform", waveform)
        if first.dtype.kind not in allowed:
            raise _error(source, f"waveform has dtype {first.dtype}, expected {expected}")
        if first.ndim != 1 or first.shape[0] < 1:
            raise _error(source, f"waveform has shape {first.shape}, expected (n_w,) with n_w >= 1")
        _check_finite(source, "waveform", first)
    if transmitter_waveforms is None:
        return
    codes = _check_array(source, "transmitter_waveforms", transmitter_waveforms)
    if codes.dtype.kind not in allowed:
        raise _error(source, f"transmitter_waveforms has dtype {codes.dtype}, expected {expected}")
    if codes.ndim != 2 or codes.shape[0] != n_tx or codes.shape[1] < 1:
        raise _error(
            source, f"transmitter_waveforms has shape {codes.shape}, expected ({n_tx}, n_w) with n_w >= 1"
        )
    _check_finite(source, "transmitter_waveforms", codes)
    if first is None:
        return
    # ``waveform`` is transmitter 0's template; either may carry trailing zero padding.
    n = max(first.shape[0], codes.shape[1])
    a = np.zeros(n, dtype=np.result_type(first, codes))
    b = np.zeros_like(a)
    a[: first.shape[0]] = first
    b[: codes.shape[1]] = codes[0]
    scale = max(float(np.max(np.abs(a))), float(np.max(np.abs(b))))
    difference = np.abs(a - b)
    if (difference > 1e-6 * scale).any():
        k = int(np.argmax(difference))
        raise _error(
            source,
            f"transmitter_waveforms[0] differs from waveform (by {float(difference[k]):.3g} at sample {k}); "
            "waveform must be transmitter 0's template",
        )


def _validate(rec: Recording, *, allow_nonfinite: bool, header_only: bool = False) -> None:
    """Check every rule of the contract; non-finite samples may be let through.

    With ``header_only`` the frames' count and values are not checked and the
    per-frame fields must be absent (a stream header, see :func:`validate_header`).
    """
    src = rec.source

    # Scalars.
    if not _is_real_number(rec.sample_rate_hz):
        raise _error(src, f"sample_rate_hz must be a number, got {rec.sample_rate_hz!r}")
    rate = float(rec.sample_rate_hz)
    low, high = SAMPLE_RATE_RANGE_HZ
    if not low <= rate <= high:  # NaN fails too
        raise _error(src, f"sample_rate_hz must lie in {low:g}..{high:g} Hz, got {rate!r}")
    if rec.signal_kind not in SIGNAL_KINDS:
        kinds = ", ".join(repr(k) for k in SIGNAL_KINDS)
        raise _error(src, f"signal_kind is {rec.signal_kind!r}, expected one of {kinds}")
    if rec.firing is not None and rec.firing not in FIRING_MODES:
        modes = ", ".join(repr(m) for m in FIRING_MODES)
        raise _error(src, f"firing is {rec.firing!r}, expected one of {modes}")
    _check_optional_float(src, "carrier_hz", rec.carrier_hz, 0.0, False)
    _check_optional_float(src, "speed_of_sound_m_s", rec.speed_of_sound_m_s, 0.0, False)
    _check_optional_float(src, "field_of_view_deg", rec.field_of_view_deg, 0.0, False, 180.0)
    _check_optional_float(src, "temperature_c", rec.temperature_c, _ABSOLUTE_ZERO_C, False)
    _check_optional_float(src, "relative_humidity", rec.relative_humidity, 0.0, True, 1.0)

    # Geometry.
    tx = _check_geometry(src, "transmitters", rec.transmitters_m, None)
    rx = _check_geometry(src, "receivers", rec.receivers_m, None)
    n_tx, n_rx = int(tx.shape[0]), int(rx.shape[0])

    # Frames and the per-frame fields.
    frames = _check_frames_layout(src, rec.frames, rec.signal_kind, n_rx)
    n_frames, n_samples = int(frames.shape[0]), int(frames.shape[2])
    per_frame = {name: getattr(rec, field) for name, field in _PER_FRAME_DATASETS.items()}
    if header_only:
        for name, value in per_frame.items():
            if value is not None:
                raise _error(
                    src,
                    f"{name} is a per-frame field, which a stream header does not carry "
                    "(pass it in the batches; as_header() strips it)",
                )
    else:
        if n_frames < 1:
            raise _error(src, f"frames has shape {frames.shape}: no frames")
        _check_samples(src, frames, rec.signal_kind, allow_nonfinite)
        _check_per_frame(src, n_frames, n_tx, *per_frame.values())
    _check_truth_kinds(src, rec.truth_kinds, rec.truth_positions_m)

    # Templates.
    _check_templates(src, rec.signal_kind, rec.waveform, rec.transmitter_waveforms, n_tx)

    # Receiver gain.
    if rec.receiver_gain is not None:
        gain = _check_array(src, "receiver_gain", rec.receiver_gain)
        _check_real_float(src, "receiver_gain", gain)
        _check_shape(src, "receiver_gain", gain, (n_samples,))
        _check_finite(src, "receiver_gain", gain)
        if (gain <= 0).any():
            k = int(np.argmax(gain <= 0))
            raise _error(src, f"receiver_gain[{k}] is {float(gain[k])!r}, expected > 0 (a linear gain)")

    # Background.
    if rec.background is not None:
        bg = _check_array(src, "background", rec.background)
        allowed = "fc" if rec.signal_kind == "iq" else "f"
        if bg.dtype.kind not in allowed:
            expected = "float or complex" if rec.signal_kind == "iq" else "float"
            raise _error(src, f"background has dtype {bg.dtype}, expected a {expected} dtype")
        if header_only and bg.shape != (n_rx, n_samples):
            raise _error(
                src,
                f"background has shape {bg.shape}, expected ({n_rx}, {n_samples}) "
                "(a stream header carries no per-frame background)",
            )
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


def validate_header(header: Recording) -> Recording:
    """Check a header for :func:`write_recording_stream`.

    A header is a :class:`Recording` that carries every per-recording field and no
    per-frame one: its ``frames`` only give (n_rx, n_samples) and the dtype kind
    (real or complex) and may hold 0 frames, whose values are not checked;
    ``frame_times_s``, ``frame_transmitter``, ``truth_positions_m`` and
    ``sensor_poses`` must be ``None`` and ``background``, if given, (n_rx, n_samples).
    Build one with :func:`as_header`, or directly with
    ``frames=np.empty((0, n_rx, n_samples))``.

    Parameters
    ----------
    header
        The header to check.

    Returns
    -------
    Recording
        ``header`` itself, unchanged.

    Raises
    ------
    RecordingError
        One line naming ``header.source``, the offending field and its value or shape.
    """
    _validate(header, allow_nonfinite=False, header_only=True)
    return header


def as_header(rec: Recording) -> Recording:
    """The per-recording part of ``rec``, as a header for :func:`write_recording_stream`.

    Parameters
    ----------
    rec
        A recording, or a header.

    Returns
    -------
    Recording
        A copy with ``frames`` emptied to (0, n_rx, n_samples) of the same dtype and the
        per-frame fields (``frame_times_s``, ``frame_transmitter``,
        ``truth_positions_m``, ``sensor_poses``) set to ``None``. Not validated.
    """
    frames = np.empty((0, *np.shape(rec.frames)[1:]), dtype=np.asarray(rec.frames).dtype)
    return replace(
        rec,
        frames=frames,
        frame_times_s=None,
        frame_transmitter=None,
        truth_positions_m=None,
        sensor_poses=None,
    )


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
    return constant_receivers([rec.frames])


def constant_receivers(blocks: Iterable[NDArray[Any]]) -> list[int]:
    """:func:`dead_receivers` of frames given block by block (n_frames_k, n_rx, n_samples), read
    no further than the block where every receiver has varied."""
    first: NDArray[Any] | None = None
    constant: NDArray[np.bool_] | None = None
    seen = 0
    for block in blocks:
        if block.shape[0] == 0:
            continue
        if first is None:
            first = block[:1, :, :1]
        same = (block == first).all(axis=(0, 2))
        constant = same if constant is None else constant & same
        seen += block.shape[0] * block.shape[2]
        if seen >= 2 and not constant.any():
            break
    if constant is None or seen < 2:
        return []
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
    firing = _attr_str(source, "firing", attrs["firing"]) if "firing" in attrs else None
    truth_kinds = None
    if "truth_kinds" in attrs:
        text = _attr_str(source, "truth_kinds", attrs["truth_kinds"])
        truth_kinds = tuple(text.split(",")) if text else ()
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
        elif name in ("waveform", "background", "transmitter_waveforms"):
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
        field_of_view_deg=optional["field_of_view_deg"],
        firing=firing,
        truth_kinds=truth_kinds,
        source=source,
        **fields,
    )


# The declared layout of a file, checked before any data is read: a few corrupt bytes can
# declare a dataset of gigabytes, which reading first would allocate before refusing it.


@dataclass(frozen=True)
class _Declared:
    """What a file says of one dataset before it is read: its shape, dtype and stored bytes.

    ``stored`` is None where the bytes on disk cannot bound the data (compressed);
    ``dtype`` is None for a dtype no recording field can have (strings, compounds).
    """

    shape: tuple[int, ...]
    dtype: np.dtype[Any] | None
    dtype_text: str
    stored: int | None

    @property
    def file_bytes(self) -> int:
        itemsize = 0 if self.dtype is None else self.dtype.itemsize
        return math.prod(self.shape) * itemsize

    @property
    def memory_bytes(self) -> int:
        """Bytes in memory once read: samples become float64/complex128, integers int64."""
        per_item = 16 if self.dtype is not None and self.dtype.kind == "c" else 8
        return max(self.file_bytes, math.prod(self.shape) * per_item)


def _expected_shapes(declared: dict[str, _Declared]) -> dict[str, tuple[tuple[int | None, ...], ...]]:
    """The shapes each dataset may have given the others (None: any length), from metadata."""
    rows = {
        name: declared[name].shape[0] if name in declared and declared[name].shape else None
        for name in ("transmitters", "receivers")
    }
    n_tx, n_rx = rows["transmitters"], rows["receivers"]
    frames = declared["frames"].shape if "frames" in declared else None
    n_frames, n_samples = (frames[0], frames[2]) if frames is not None and len(frames) == 3 else (None, None)
    return {
        "transmitters": ((None, 3),),
        "receivers": ((None, 3),),
        "frames": ((None, n_rx, None),),
        "waveform": ((None,),),
        "frame_times": ((n_frames,),),
        "frame_transmitter": ((n_frames,),),
        "background": ((n_rx, n_samples), (n_frames, n_rx, n_samples)),
        "transmitter_axes": ((n_tx, 3),),
        "receiver_axes": ((n_rx, 3),),
        "truth_positions": ((n_frames, None, 3),),
        "sensor_poses": ((n_frames, 7),),
        "receiver_gain": ((n_samples,),),
        "transmitter_waveforms": ((n_tx, None),),
    }


def _fits(shape: tuple[int, ...], pattern: tuple[int | None, ...]) -> bool:
    return len(shape) == len(pattern) and all(
        want is None or have == want for have, want in zip(shape, pattern, strict=False)
    )


def _pattern_text(pattern: tuple[int | None, ...]) -> str:
    """``(n, 3)`` for ``(None, 3)``: a shape pattern for messages."""
    return (
        "("
        + ", ".join("n" if n is None else str(n) for n in pattern)
        + ("," if len(pattern) == 1 else "")
        + ")"
    )


def _check_declared(
    source: str, declared: dict[str, _Declared], streamed: frozenset[str] = frozenset()
) -> None:
    """Check every dataset's declared shape, dtype and size before any of its data is read.

    The shapes must agree with one another as the contract says (frames with
    receivers, the per-frame fields with the frame count, ...); an uncompressed
    dataset must have all its declared bytes stored in the file (a corrupt dimension
    would otherwise read as gigabytes of fill values); a compressed one may expand at
    most :data:`MAX_COMPRESSION_RATIO`-fold; and all of them together must fit in
    :data:`MAX_RECORDING_BYTES` once in memory, except those ``streamed`` (read a range
    of frames at a time, :class:`RecordingParts`).
    """
    for name, item in declared.items():
        if item.dtype is None:
            raise _error(source, f"{name} has dtype {item.dtype_text}, expected a numeric dtype")
    for name in ("transmitters", "receivers"):
        geometry = declared.get(name)
        if geometry is not None and (
            len(geometry.shape) != 2 or geometry.shape[1] != 3 or geometry.shape[0] < 1
        ):
            raise _error(source, f"{name} has shape {geometry.shape}, expected (n, 3) with n >= 1")
    frames = declared.get("frames")
    if frames is not None:
        if len(frames.shape) != 3:
            raise _error(source, f"frames has shape {frames.shape}, expected 3-D (n_frames, n_rx, n_samples)")
        receivers = declared.get("receivers")
        if receivers is not None and frames.shape[1] != receivers.shape[0]:
            raise _error(
                source, f"frames has {frames.shape[1]} channels but receivers has {receivers.shape[0]}"
            )
        if frames.shape[2] < 1:
            raise _error(source, f"frames has shape {frames.shape}: no samples")
        if frames.shape[0] < 1:
            raise _error(source, f"frames has shape {frames.shape}: no frames")
    for name, patterns in _expected_shapes(declared).items():
        present = declared.get(name)
        if present is None or any(_fits(present.shape, pattern) for pattern in patterns):
            continue
        wanted = " or ".join(_pattern_text(pattern) for pattern in patterns)
        raise _error(source, f"{name} has shape {present.shape}, expected {wanted}")
    for name, item in declared.items():
        if item.stored is not None and item.stored < item.file_bytes:
            raise _error(
                source,
                f"{name} declares shape {item.shape} of {item.dtype_text} ({item.file_bytes} bytes) "
                f"but the file stores only {item.stored} bytes of it (a corrupt file?)",
            )
    total = sum(item.memory_bytes for name, item in declared.items() if name not in streamed)
    if total > MAX_RECORDING_BYTES:
        largest = max(declared, key=lambda name: declared[name].memory_bytes)
        raise _error(
            source,
            f"declares {total / 2**30:.1f} GiB of data in memory ({largest} has shape "
            f"{declared[largest].shape}), more than the {MAX_RECORDING_BYTES / 2**30:.0f} GiB "
            "a recording may hold",
        )


class _Shown:
    """An attribute value the reader cannot use, shown in messages by its repr."""

    def __init__(self, text: str) -> None:
        self._text = text

    def __repr__(self) -> str:
        return self._text


def _child_attribute(encoded: object) -> object:
    """An attribute as :mod:`echoloc.io._hdf5_child` sends it, back to a value."""
    if isinstance(encoded, dict):
        if "value" in encoded:
            return encoded["value"]
        if "bytes" in encoded and isinstance(encoded["bytes"], str):
            return bytes.fromhex(encoded["bytes"])
        return _Shown(str(encoded.get("repr")))
    return _Shown(repr(encoded))


class _ChildPipe:
    """Messages from the HDF5 reader child, each awaited at most the stall timeout.

    Every wait is a ``select`` in Python, so SIGTERM and Ctrl-C interrupt it.
    """

    def __init__(self, source: str, process: subprocess.Popen[bytes]) -> None:
        assert process.stdout is not None
        self._source = source
        self._process = process
        self._fd = process.stdout.fileno()

    def _readable(self, timeout_s: float) -> bool:
        """Wait until the pipe has bytes (or EOF); poll, not select: a descriptor past 1024
        (a busy listener) is beyond select's reach."""
        if hasattr(select, "poll"):
            poller = select.poll()
            poller.register(self._fd, select.POLLIN | select.POLLHUP | select.POLLERR)
            return bool(poller.poll(timeout_s * 1000))
        ready, _, _ = select.select([self._fd], [], [], timeout_s)
        return bool(ready)

    def _fill(self, view: memoryview, timeout_s: float) -> None:
        done = 0
        while done < len(view):
            if not self._readable(timeout_s):
                raise _error(
                    self._source,
                    f"cannot read as HDF5: libhdf5 made no progress for {timeout_s:g} s reading it "
                    f"(a corrupt file? on a slow disk, set {HDF5_STALL_ENV} to wait longer); abandoned",
                )
            n = os.readv(self._fd, [view[done:]])
            if n == 0:
                code = self._process.wait()
                raise _error(
                    self._source, f"cannot read as HDF5: the reader process ended (exit code {code})"
                )
            done += n

    def message(self, timeout_s: float, into: memoryview | None = None) -> tuple[bytes, bytes, int]:
        """The next message's kind, payload and length; a ``D`` payload goes into ``into``."""
        head = bytearray(9)
        self._fill(memoryview(head), timeout_s)
        kind, length = bytes(head[:1]), struct.unpack("<Q", head[1:])[0]
        if kind == b"D":
            if into is None or length > len(into):
                raise _error(
                    self._source, "cannot read as HDF5: the reader process sent more data than declared"
                )
            self._fill(into[:length], timeout_s)
            return kind, b"", length
        if length > _MAX_HEADER_BYTES:
            raise _error(self._source, f"cannot read as HDF5: a header of {length} bytes")
        payload = bytearray(length)
        self._fill(memoryview(payload), timeout_s)
        if kind == b"E":
            raise _error(self._source, payload.decode("utf-8", "replace"))
        return kind, bytes(payload), length

    def expect(self, wanted: bytes, timeout_s: float) -> bytes:
        kind, payload, _ = self.message(timeout_s)
        if kind != wanted:
            raise _error(
                self._source, f"cannot read as HDF5: the reader process sent {kind!r}, expected {wanted!r}"
            )
        return payload


def _hdf5_declared(source: str, described: dict[str, Any]) -> dict[str, _Declared]:
    """The child's description of each dataset, refused where a recording cannot use it."""
    declared: dict[str, _Declared] = {}
    for name, item in described.items():
        kind = item.get("kind")
        if kind != "Dataset":
            raise _error(source, f"{name} is a {kind}, expected a dataset")
        if item["external"] or item["virtual"]:
            where = "external files" if item["external"] else "other files (a virtual dataset)"
            raise _error(source, f"{name} keeps its data in {where}, which a recording may not")
        if item["shape"] is None:
            raise _error(source, f"{name} has no data (an empty dataspace)")
        descr = item["descr"]
        declared[name] = _Declared(
            shape=tuple(int(n) for n in item["shape"]),
            dtype=None if descr is None else np.lib.format.descr_to_dtype(descr),
            dtype_text=str(item["dtype"]),
            stored=None if item["filtered"] else int(item["stored"]),
        )
    for name, item in declared.items():
        if (
            item.stored is None
            and item.file_bytes > MAX_COMPRESSION_RATIO * int(described[name]["stored"]) + _CHUNK_BYTES
        ):
            raise _error(
                source,
                f"{name} declares shape {item.shape} ({item.file_bytes} bytes) from only "
                f"{described[name]['stored']} compressed bytes (a corrupt file?)",
            )
    return declared


def _child_sys_path() -> list[str]:
    """The import path for the HDF5 reader child: this process's own, without the current directory.

    The child must import the ``json``, ``numpy`` and ``h5py`` this process imported, never
    a file of that name in the folder the user runs echoloc from (a ``h5py.py`` lying next
    to the recording would run). So the child starts isolated (``-I``: no current
    directory, no ``PYTHON*`` variables) and gets this list: relative entries made
    absolute, the current directory ("" or its path) left out, and echoloc's own root
    appended last (after the standard library) for a process that found echoloc through
    something the child does not inherit, such as an import hook.
    """
    cwd = os.getcwd()
    paths: list[str] = []
    for entry in sys.path:
        if not isinstance(entry, str) or entry == "":
            continue
        absolute = os.path.abspath(entry)
        if absolute != cwd and absolute not in paths:
            paths.append(absolute)
    package_root = str(Path(__file__).resolve().parents[2])
    if package_root not in paths:
        paths.append(package_root)
    return paths


def hdf5_stall_timeout_s() -> float:
    """How long the HDF5 reader may make no progress, s: :data:`HDF5_STALL_TIMEOUT_S`, or the
    environment variable ``ECHOLOC_HDF5_STALL_S`` (a slow disk, NFS or a loaded machine)."""
    text = os.environ.get(HDF5_STALL_ENV)
    if text is None or not text.strip():
        return HDF5_STALL_TIMEOUT_S
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and 0 < value <= _MAX_STALL_S):
        raise RecordingError(
            _one_line(f"{HDF5_STALL_ENV}={text!r}: expected a number of seconds in (0, {_MAX_STALL_S:g}]")
        )
    return value


def _load_hdf5(source: str, path: Path) -> tuple[dict[str, object], dict[str, _AnyArray]]:
    """Read the file through :mod:`echoloc.io._hdf5_child`, abandoning a libhdf5 that stalls.

    The child costs a Python start and an h5py import on every read, and the data cross
    a pipe (each block is read straight into its array, so no second copy). Reading only
    the structure in the child and the data here would save the pipe, but a corrupt chunk
    index or filter could then still hang this process, deaf to signals: the whole read
    stays in the child. It is started with fork+exec (subprocess), which is safe with
    threads, isolated from the current directory (see :func:`_child_sys_path`).
    """
    stall_s = hdf5_stall_timeout_s()
    env = dict(os.environ)
    env.setdefault("OPENBLAS_NUM_THREADS", "1")
    names = json.dumps(list(_DATASET_FIELDS))
    bootstrap = (
        f"import sys; sys.path[:] = {_child_sys_path()!r}; from echoloc.io._hdf5_child import main; main()"
    )
    command = [sys.executable, "-I", "-c", bootstrap, str(path), names, str(os.getpid())]
    process = subprocess.Popen(
        command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env
    )
    assert process.stdin is not None
    assert process.stdout is not None
    try:
        pipe = _ChildPipe(source, process)
        pipe.expect(b"R", HDF5_START_TIMEOUT_S)
        header = json.loads(pipe.expect(b"H", stall_s))
        attrs = {name: _child_attribute(value) for name, value in header["attrs"].items()}
        declared = _hdf5_declared(source, header["datasets"])
        _check_declared(source, declared)
        try:
            process.stdin.write(json.dumps(list(declared)).encode() + b"\n")
            process.stdin.close()
        except BrokenPipeError:
            pass  # the child ended: its message, or its end, is read next
        data: dict[str, _AnyArray] = {}
        for name, item in declared.items():
            assert item.dtype is not None
            arr = np.empty(item.shape, dtype=item.dtype)
            view = arr.reshape(-1).view(np.uint8).data
            done = 0
            while done < len(view):
                kind, _, length = pipe.message(stall_s, view[done:])
                if kind != b"D" or length == 0:
                    raise _error(source, f"cannot read as HDF5: {name} ended early")
                done += length
            data[name] = arr
        pipe.expect(b"Z", stall_s)
        return attrs, data
    finally:
        for stream in (process.stdin, process.stdout):
            with contextlib.suppress(OSError):
                stream.close()
        if process.poll() is None:
            process.kill()
        process.wait()


def read_npy_header(fh: IO[bytes]) -> tuple[tuple[int, ...], np.dtype[Any]]:
    """The shape and dtype a ``.npy`` stream declares, from its header alone (the stream is
    left at the data); ValueError for anything that is not a readable version 1 or 2 header.

    numpy parses the header's dict with tokenize and ast, so a corrupt one raises
    TokenError, SyntaxError or TypeError too: all of them become ValueError here."""
    try:
        version = np.lib.format.read_magic(fh)
        if version == (1, 0):
            shape, _, dtype = np.lib.format.read_array_header_1_0(fh)
        elif version == (2, 0):
            shape, _, dtype = np.lib.format.read_array_header_2_0(fh)
        else:
            raise ValueError(f"a .npy of version {version}, expected 1.0 or 2.0")
    except (TypeError, SyntaxError, EOFError, tokenize.TokenError) as error:
        raise ValueError(f"{type(error).__name__}: {error}") from None
    return tuple(int(n) for n in shape), dtype


def _npy_header(source: str, archive: zipfile.ZipFile, member: str) -> tuple[_Declared, int]:
    """A member's declared shape and dtype, from its ``.npy`` header alone, and the header's length."""
    info = archive.getinfo(member)
    try:
        with archive.open(info) as fh:
            shape, dtype = read_npy_header(fh)
            header_bytes = fh.tell()
    except (ValueError, zipfile.BadZipFile) as error:
        raise _error(source, f"{member} has no readable .npy header ({error})") from None
    plain = dtype.kind in "biufcUS" and dtype.fields is None and dtype.subdtype is None
    declared = _Declared(
        shape=tuple(int(n) for n in shape),
        dtype=dtype if plain else None,
        dtype_text=str(dtype),
        stored=info.file_size - header_bytes,
    )
    if info.compress_type != zipfile.ZIP_STORED and declared.file_bytes > (
        MAX_COMPRESSION_RATIO * info.compress_size + _CHUNK_BYTES
    ):
        raise _error(
            source,
            f"{member} declares shape {declared.shape} ({declared.file_bytes} bytes) from only "
            f"{info.compress_size} compressed bytes (a corrupt file?)",
        )
    return declared, header_bytes


def _load_npz(source: str, path: Path) -> tuple[dict[str, object], dict[str, _AnyArray]]:
    """Read the archive's members, each only after its ``.npy`` header was checked."""
    attrs: dict[str, object] = {}
    data: dict[str, _AnyArray] = {}
    with open(path, "rb") as fh:  # our own handle: closed even when reading fails
        if fh.read(len(_ZIP_MAGIC)) != _ZIP_MAGIC:
            raise _error(source, "not an NPZ file (no zip signature)")
        fh.seek(0)
        with zipfile.ZipFile(fh) as archive:
            members = set(archive.namelist())
            if not members:
                raise _error(source, "not an NPZ archive (it holds no .npy member)")
            declared: dict[str, _Declared] = {}
            for name in (*_REQUIRED_ATTRS, *_STR_ATTRS, *_OPTIONAL_FLOAT_ATTRS):
                if f"{name}.npy" not in members:
                    continue
                item, _ = _npy_header(source, archive, f"{name}.npy")
                if item.file_bytes > _MAX_ATTRIBUTE_BYTES or item.dtype is None:
                    raise _error(
                        source,
                        f"attribute {name} is an array of shape {item.shape} and dtype {item.dtype_text}, "
                        "expected a single value",
                    )
                attrs[name] = _read_member(source, archive, name)
            for name in _DATASET_FIELDS:
                if f"{name}.npy" in members:
                    declared[name] = _npy_header(source, archive, f"{name}.npy")[0]
            _check_declared(source, declared)
            for name in declared:
                data[name] = np.asarray(_read_member(source, archive, name))
    return attrs, data


def _read_member(source: str, archive: zipfile.ZipFile, name: str) -> _AnyArray:
    with archive.open(f"{name}.npy") as member:
        arr = np.lib.format.read_array(member, allow_pickle=False)
    return np.asarray(arr)


_repair = repair_nonfinite  # read_recording's keyword shadows the function's name


_READ_ERRORS = (OSError, ValueError, KeyError, TypeError, RuntimeError, EOFError, zipfile.BadZipFile)
"""What reading a broken file raises besides RecordingError: each becomes one line naming the file."""


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
    file, source, kind = _check_recording_path(path)
    try:
        if kind == "HDF5":
            attrs, data = _load_hdf5(source, file)
        else:
            attrs, data = _load_npz(source, file)
    except RecordingError:
        raise
    except _READ_ERRORS as exc:
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
    if rec.waveform is not None and rec.n_samples < len(rec.waveform):
        warnings.warn(
            _one_line(
                f"{source}: frames of {rec.n_samples} samples are shorter than the "
                f"{len(rec.waveform)}-sample waveform: no whole echo fits in a frame"
            ),
            RecordingWarning,
            stacklevel=2,
        )
    return rec


# ----------------------------------------------------------------------------- reading in parts

STREAMED_DATASETS = ("frames", "background")
"""The datasets :class:`RecordingParts` reads a range of frames at a time (``background`` when
it has one frame per frame); every other dataset is read whole when the file is opened."""


def _check_recording_path(path: str | os.PathLike[str]) -> tuple[Path, str, str]:
    """The file, its name for messages and its kind ("HDF5" or "NPZ"), as :func:`read_recording`
    checks them before opening it."""
    file = Path(path)
    source = str(path)
    suffix = file.suffix.lower()
    if file.is_dir():
        raise _error(source, "is a directory, not a recording file (.h5, .hdf5 or .npz)")
    if suffix not in _HDF5_SUFFIXES + _NPZ_SUFFIXES:
        raise _error(source, f"unknown extension {file.suffix!r}, expected .h5, .hdf5 or .npz")
    if not file.exists():
        raise _error(source, "no such file")
    if not file.is_file():
        raise _error(source, "not a regular file")
    return file, source, "HDF5" if suffix in _HDF5_SUFFIXES else "NPZ"


def _serve_hdf5() -> None:
    """The reader child of :class:`RecordingParts` for an HDF5 file (started as
    :func:`_load_hdf5` starts :mod:`echoloc.io._hdf5_child`, with the same arguments).

    It sends ``R`` and ``H`` as that child does, then answers each request line on stdin,
    JSON ``[name, start, stop]`` (``start`` null: the whole dataset), with the ``D`` blocks
    of those rows (at most :data:`echoloc.io._hdf5_child.SLICE_BYTES` each) and ``Z``; ``E``
    ends it on an error. It stops at the end of stdin, or when its parent dies.
    """
    from echoloc.io import _hdf5_child as child

    out = sys.stdout.buffer
    child._die_with_parent(int(sys.argv[3]))
    child._limit_memory()
    child.send(out, b"R")
    path = sys.argv[1]
    try:
        if not h5py.is_hdf5(path):
            child.send(out, b"E", b"not an HDF5 file (no HDF5 signature)")
            return
        with h5py.File(path, "r") as f:
            attrs = {name: child._attribute(f.attrs[name]) for name in child.ATTRIBUTES if name in f.attrs}
            names = json.loads(sys.argv[2])
            datasets = {name: child._describe(f[name]) for name in names if name in f}
            child.send(out, b"H", json.dumps({"attrs": attrs, "datasets": datasets}).encode())
            for line in sys.stdin:
                name, start, stop = json.loads(line)
                dataset = f[name]
                if start is None:
                    child._stream(out, dataset)
                else:
                    row_bytes = max(1, dataset.dtype.itemsize * math.prod(dataset.shape[1:]))
                    rows = max(1, child.SLICE_BYTES // row_bytes)
                    for first in range(start, stop, rows):
                        block = np.ascontiguousarray(dataset[first : min(first + rows, stop)])
                        child.send(out, b"D", block.reshape(-1).view(np.uint8).data)
                child.send(out, b"Z")
    except BrokenPipeError:  # the parent went away
        return
    except (OSError, ValueError, KeyError, TypeError, RuntimeError, MemoryError) as exc:
        message = " ".join(f"cannot read as HDF5: {exc}".split())
        child.send(out, b"E", message.encode("utf-8", "replace"))


class _Hdf5Parts:
    """An HDF5 file served by a reader child (:func:`_serve_hdf5`) that stays up between reads:
    libhdf5 runs there, abandoned when it stalls, as in :func:`_load_hdf5`."""

    def __init__(self, source: str, path: Path) -> None:
        self._source = source
        self._stall_s = hdf5_stall_timeout_s()
        env = dict(os.environ)
        env.setdefault("OPENBLAS_NUM_THREADS", "1")
        names = json.dumps(list(_DATASET_FIELDS))
        bootstrap = (
            f"import sys; sys.path[:] = {_child_sys_path()!r}; "
            "from echoloc.io.recording import _serve_hdf5; _serve_hdf5()"
        )
        command = [sys.executable, "-I", "-c", bootstrap, str(path), names, str(os.getpid())]
        self._process: subprocess.Popen[bytes] | None = subprocess.Popen(
            command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env
        )
        try:
            self._pipe = _ChildPipe(source, self._process)
            self._pipe.expect(b"R", HDF5_START_TIMEOUT_S)
            header = json.loads(self._pipe.expect(b"H", self._stall_s))
            self.attrs = {name: _child_attribute(value) for name, value in header["attrs"].items()}
            self.declared = _hdf5_declared(source, header["datasets"])
        except BaseException:
            self.close()
            raise
        self.random_access = True

    def read(self, name: str, start: int | None = None, stop: int | None = None) -> _AnyArray:
        """The dataset ``name`` (rows ``start:stop`` along its first axis), in the file's dtype."""
        process = self._process
        if process is None:
            raise _error(self._source, "cannot read as HDF5: the file was closed after an error")
        item = self.declared[name]
        assert item.dtype is not None
        assert process.stdin is not None
        shape = item.shape if start is None or stop is None else (stop - start, *item.shape[1:])
        arr = np.empty(shape, dtype=item.dtype)
        try:
            try:
                process.stdin.write(json.dumps([name, start, stop]).encode() + b"\n")
                process.stdin.flush()
            except BrokenPipeError:
                pass  # the child ended: its message, or its end, is read next
            view = arr.reshape(-1).view(np.uint8).data
            done = 0
            while done < len(view):
                kind, _, length = self._pipe.message(self._stall_s, view[done:])
                if kind != b"D" or length == 0:
                    raise _error(self._source, f"cannot read as HDF5: {name} ended early")
                done += length
            self._pipe.expect(b"Z", self._stall_s)
        except BaseException:
            self.close()  # the conversation is out of step: no read after this one
            raise
        return arr

    def close(self) -> None:
        process, self._process = self._process, None
        if process is None:
            return
        for stream in (process.stdin, process.stdout):
            with contextlib.suppress(OSError):
                if stream is not None:
                    stream.close()
        if process.poll() is None:
            process.kill()
        process.wait()


def _npy_fortran_order(source: str, archive: zipfile.ZipFile, member: str) -> bool:
    """Whether a member's ``.npy`` header says its data are in Fortran (column-major) order."""
    try:
        with archive.open(member) as fh:
            version = np.lib.format.read_magic(fh)
            read = (
                np.lib.format.read_array_header_1_0
                if version == (1, 0)
                else np.lib.format.read_array_header_2_0
            )
            return bool(read(fh)[1])
    except (ValueError, TypeError, SyntaxError, EOFError, tokenize.TokenError, zipfile.BadZipFile) as error:
        raise _error(source, f"{member} has no readable .npy header ({error})") from None


class _NpzParts:
    """An NPZ archive read in parts. An uncompressed member in C order (what
    :func:`write_recording` writes) is read at any rows straight from the file; a compressed
    one can only be read from its start, so rows are read by going on from where the last
    read ended (starting again from the top for rows before it); a member in Fortran order
    is read whole, once."""

    def __init__(self, source: str, path: Path) -> None:
        self._source = source
        self._file = open(path, "rb")  # noqa: SIM115 -- closed by close()
        self._streams: dict[str, tuple[IO[bytes], int]] = {}
        self._whole: dict[str, _AnyArray] = {}
        try:
            if self._file.read(len(_ZIP_MAGIC)) != _ZIP_MAGIC:
                raise _error(source, "not an NPZ file (no zip signature)")
            self._file.seek(0)
            self._archive = zipfile.ZipFile(self._file)
            members = set(self._archive.namelist())
            if not members:
                raise _error(source, "not an NPZ archive (it holds no .npy member)")
            self.attrs: dict[str, object] = {}
            for name in (*_REQUIRED_ATTRS, *_STR_ATTRS, *_OPTIONAL_FLOAT_ATTRS):
                if f"{name}.npy" not in members:
                    continue
                item, _ = _npy_header(source, self._archive, f"{name}.npy")
                if item.file_bytes > _MAX_ATTRIBUTE_BYTES or item.dtype is None:
                    raise _error(
                        source,
                        f"attribute {name} is an array of shape {item.shape} and dtype {item.dtype_text}, "
                        "expected a single value",
                    )
                self.attrs[name] = _read_member(source, self._archive, name)
            self.declared: dict[str, _Declared] = {}
            self._header_bytes: dict[str, int] = {}
            for name in _DATASET_FIELDS:
                if f"{name}.npy" in members:
                    self.declared[name], self._header_bytes[name] = _npy_header(
                        source, self._archive, f"{name}.npy"
                    )
            self._offsets = {
                name: self._data_offset(name) for name in STREAMED_DATASETS if name in self.declared
            }
        except BaseException:
            self.close()
            raise
        self.random_access = all(offset is not None for offset in self._offsets.values())

    def _data_offset(self, name: str) -> int | None:
        """Where the rows of member ``name`` start in the file; None unless it is stored
        uncompressed, unencrypted and in C order."""
        info = self._archive.getinfo(f"{name}.npy")
        if info.compress_type != zipfile.ZIP_STORED or info.flag_bits & 0x1:
            return None
        if _npy_fortran_order(self._source, self._archive, f"{name}.npy"):
            return None
        self._file.seek(info.header_offset)
        local = self._file.read(30)
        if len(local) != 30 or local[:4] != _ZIP_MAGIC:
            raise _error(self._source, f"{name}.npy has no local zip header where the directory says")
        name_length, extra_length = struct.unpack("<HH", local[26:30])
        return int(info.header_offset) + 30 + int(name_length) + int(extra_length) + self._header_bytes[name]

    def read(self, name: str, start: int | None = None, stop: int | None = None) -> _AnyArray:
        """The member ``name`` (rows ``start:stop`` along its first axis), in the file's dtype."""
        if start is None or stop is None:
            return np.asarray(_read_member(self._source, self._archive, name))
        item = self.declared[name]
        assert item.dtype is not None
        if _npy_fortran_order(self._source, self._archive, f"{name}.npy"):
            if name not in self._whole:
                self._whole[name] = np.asarray(_read_member(self._source, self._archive, name))
            return np.ascontiguousarray(self._whole[name][start:stop])
        row_bytes = item.dtype.itemsize * math.prod(item.shape[1:])
        arr = np.empty((stop - start, *item.shape[1:]), dtype=item.dtype)
        view = arr.reshape(-1).view(np.uint8).data
        offset = self._offsets.get(name)
        if offset is not None:
            self._file.seek(offset + start * row_bytes)
            self._fill(self._file, name, view)
            return arr
        stream, row = self._streams.pop(name, (None, 0))
        if stream is None or row > start:
            if stream is not None:
                stream.close()
            stream = self._archive.open(f"{name}.npy")
            _skip(stream, self._header_bytes[name])
            row = 0
        try:
            _skip(stream, (start - row) * row_bytes)
            self._fill(stream, name, view)
        except BaseException:
            stream.close()
            raise
        self._streams[name] = (stream, stop)
        return arr

    def _fill(self, stream: IO[bytes], name: str, view: memoryview) -> None:
        done = 0
        while done < len(view):
            n = stream.readinto(view[done:])  # type: ignore[attr-defined]
            if not n:
                raise _error(self._source, f"{name}.npy ended early")
            done += n

    def close(self) -> None:
        for stream, _ in self._streams.values():
            with contextlib.suppress(OSError):
                stream.close()
        self._streams.clear()
        archive = getattr(self, "_archive", None)
        if archive is not None:
            archive.close()
        self._file.close()


def _skip(stream: IO[bytes], n_bytes: int) -> None:
    """Read and drop ``n_bytes`` of ``stream``, :data:`_CHUNK_BYTES` at a time."""
    while n_bytes > 0:
        got = len(stream.read(min(n_bytes, _CHUNK_BYTES)))
        if not got:
            raise EOFError("the member ended early")
        n_bytes -= got


class RecordingParts(contextlib.AbstractContextManager["RecordingParts"]):
    """A recording file (``.h5``/``.hdf5`` or ``.npz``) read in parts: every dataset but the
    samples when it is opened, the samples a range of frames at a time.

    Opening checks the file as :func:`read_recording` does, except for the values of the
    samples (``frames``, and a ``background`` with one frame per frame), which are checked
    range by range as they are read (a non-finite or, for envelopes, negative sample then
    raises naming its index in the file, or with ``repair_nonfinite`` is set to 0 with a
    :class:`RecordingWarning`); and the samples are left out of the
    :data:`MAX_RECORDING_BYTES` a recording may declare, since they never are in memory
    at once. A dead receiver (every sample equal, over the whole file) is not warned about:
    that takes every sample.

    An HDF5 file is read by a child process that stays up while the file is open (a corrupt
    file stalls it, not this process: :func:`_load_hdf5`), any rows at any time. In an NPZ
    archive, uncompressed members in C order (as :func:`write_recording` writes them) are
    read straight at any rows (:attr:`random_access`); a compressed member only from its
    start, each read going on from the last one (rows before it mean starting again).

    Use it as a context manager, or :meth:`close` it. Its reads are serialised (a lock), so
    threads may share it.

    Attributes
    ----------
    source
        The path as given, for messages.
    header
        Every per-recording field (:func:`as_header`: ``frames`` of shape (0, n_rx, n_samples),
        float64 or complex128; the per-frame fields None; ``background`` only when it is one
        frame for all).
    per_frame
        The per-frame datasets, whole, by field name (``frame_times_s``, ``frame_transmitter``,
        ``truth_positions_m``, ``sensor_poses``), None where the file has none.
    n_frames
        Frames in the file.
    per_frame_background
        Whether the file has one background per frame (:meth:`background` reads it).
    random_access
        Whether any range of frames is read without reading the ones before it.
    """

    def __init__(self, path: str | os.PathLike[str], *, repair_nonfinite: bool = False) -> None:
        file, source, kind = _check_recording_path(path)
        self.source = source
        self._kind = kind
        self._repair = repair_nonfinite
        self._lock = threading.Lock()
        self._backend: _Hdf5Parts | _NpzParts | None = None
        with self._errors():
            self._backend = _Hdf5Parts(source, file) if kind == "HDF5" else _NpzParts(source, file)
            self._open()

    @contextlib.contextmanager
    def _errors(self) -> Iterator[None]:
        """Errors of reading as :func:`read_recording` words them; the file closed after one."""
        try:
            yield
        except RecordingError:
            self.close()
            raise
        except _READ_ERRORS as exc:
            self.close()
            raise _error(self.source, f"cannot read as {self._kind}: {exc}") from exc
        except BaseException:
            self.close()
            raise

    def _open(self) -> None:
        backend = self._backend
        assert backend is not None
        source, declared = self.source, backend.declared
        background = declared.get("background")
        self.per_frame_background = background is not None and len(background.shape) == 3
        per_frame_background = self.per_frame_background
        streamed = frozenset(
            name for name in declared if name == "frames" or (name == "background" and per_frame_background)
        )
        _check_declared(source, declared, streamed)
        data = {name: backend.read(name) for name in declared if name not in streamed}
        for name in streamed:
            item = declared[name]
            data[name] = np.empty((0, *item.shape[1:]), dtype=item.dtype)
        rec = _build(source, backend.attrs, data)
        self.n_frames = declared["frames"].shape[0]
        self.per_frame: dict[str, _AnyArray | None] = {
            field: getattr(rec, field) for field in _PER_FRAME_DATASETS.values()
        }
        kept_background = None if self.per_frame_background else rec.background
        header = replace(
            rec,
            frame_times_s=None,
            frame_transmitter=None,
            truth_positions_m=None,
            sensor_poses=None,
            background=kept_background,
        )
        # Everything read_recording checks but the samples' values: the header as a stream's
        # (a background of one frame stands in for one per frame, for its dtype), then the
        # per-frame datasets against the frame count.
        stand_in = (
            np.zeros(rec.frames.shape[1:], dtype=np.asarray(rec.background).dtype)
            if self.per_frame_background
            else kept_background
        )
        _validate(replace(header, background=stand_in), allow_nonfinite=self._repair, header_only=True)
        _check_per_frame(source, self.n_frames, len(rec.transmitters_m), *self.per_frame.values())
        _check_truth_kinds(source, rec.truth_kinds, self.per_frame["truth_positions_m"])
        if self._repair and kept_background is not None:
            fixed, count = _zero_nonfinite(kept_background)
            if count:
                warnings.warn(
                    _one_line(f"{source}: replaced {count} non-finite sample(s) of background with 0"),
                    RecordingWarning,
                    stacklevel=3,
                )
                header = replace(header, background=fixed)
        self.header = header
        n_samples = header.n_samples
        if header.waveform is not None and n_samples < len(header.waveform):
            warnings.warn(
                _one_line(
                    f"{source}: frames of {n_samples} samples are shorter than the "
                    f"{len(header.waveform)}-sample waveform: no whole echo fits in a frame"
                ),
                RecordingWarning,
                stacklevel=3,
            )

    @property
    def random_access(self) -> bool:
        return self._backend is not None and self._backend.random_access

    def frames(self, start: int, stop: int) -> _AnyArray:
        """Frames ``start:stop`` (stop - start, n_rx, n_samples), float64 or complex128, checked."""
        return self._samples("frames", start, stop)

    def frames_at(self, indices: Iterable[int]) -> _AnyArray:
        """The frames at ``indices`` (ascending), stacked; each run of consecutive frames in one read."""
        return self.samples_at("frames", indices)

    def samples_at(self, name: str, indices: Iterable[int]) -> _AnyArray:
        """``frames`` or a per-frame ``background`` at ``indices`` (ascending), stacked, checked;
        each run of consecutive frames in one read."""
        if name not in STREAMED_DATASETS or (name == "background" and not self.per_frame_background):
            raise ValueError(f"{name} is not read by frames")
        runs: list[list[int]] = []
        for index in indices:
            if runs and index == runs[-1][1]:
                runs[-1][1] += 1
            else:
                runs.append([index, index + 1])
        parts = [self._samples(name, start, stop) for start, stop in runs]
        if not parts:
            return np.empty((0, *self.header.frames.shape[1:]), dtype=self.header.frames.dtype)
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def background(self, start: int, stop: int) -> _AnyArray | None:
        """The backgrounds of frames ``start:stop``, checked; None without one per frame."""
        return self._samples("background", start, stop) if self.per_frame_background else None

    def _samples(self, name: str, start: int, stop: int) -> _AnyArray:
        if not 0 <= start <= stop <= self.n_frames:
            raise _error(self.source, f"frames {start}:{stop} are outside its {self.n_frames} frames")
        with self._lock, self._errors():
            if self._backend is None:
                raise _error(self.source, "is closed")
            raw = self._backend.read(name, start, stop)
        kind = self.header.signal_kind
        arr = _as_samples(self.source, name, raw, allow_complex=name == "frames" or kind == "iq")
        what = f"{name}[{start}:{stop}]"
        if self._repair:
            arr, count = _zero_nonfinite(arr)
            if count:
                warnings.warn(
                    _one_line(f"{self.source}: replaced {count} non-finite sample(s) of {what} with 0"),
                    RecordingWarning,
                    stacklevel=3,
                )
        else:
            _refuse_flagged(
                self.source, arr, ~np.isfinite(arr), f"{what} has", "non-finite value(s)", first_row=start
            )
        if kind == "envelope":
            negative = (arr < 0) & np.isfinite(arr)
            _refuse_flagged(
                self.source,
                arr,
                negative,
                f"{what} is envelope data but has",
                "negative sample(s)",
                first_row=start,
            )
        return arr

    def close(self) -> None:
        """Close the file (and end its reader process). Idempotent."""
        backend, self._backend = self._backend, None
        if backend is not None:
            backend.close()

    def __exit__(self, *exc_info: object) -> None:
        self.close()


# ----------------------------------------------------------------------------- writing


def _file_items(rec: Recording) -> tuple[dict[str, object], dict[str, _AnyArray]]:
    """The root attributes and datasets of ``rec``, by their contract names."""
    attrs: dict[str, object] = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "sample_rate_hz": float(rec.sample_rate_hz),
        "signal_kind": rec.signal_kind,
    }
    if rec.firing is not None:
        attrs["firing"] = rec.firing
    if rec.truth_kinds is not None:
        attrs["truth_kinds"] = ",".join(rec.truth_kinds)
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


@contextlib.contextmanager
def _write_errors(source: str) -> Iterator[None]:
    """Turn a failure of the file system or of h5py/zipfile into a one-line RecordingError."""
    try:
        yield
    except RecordingError:
        raise
    except (OSError, ValueError, TypeError, RuntimeError) as exc:
        raise _error(source, f"cannot write: {exc}") from exc


def _target(path: str | os.PathLike[str]) -> tuple[Path, str, bool]:
    """The target path, its name for messages, and whether it is HDF5 (else NPZ)."""
    target = Path(path)
    suffix = target.suffix.lower()
    if suffix not in _HDF5_SUFFIXES + _NPZ_SUFFIXES:
        raise _error(str(path), f"unknown extension {target.suffix!r}, expected .h5, .hdf5 or .npz")
    return target, str(path), suffix in _HDF5_SUFFIXES


_HOST_TAG = hashlib.sha256(socket.gethostname().encode()).hexdigest()[:8]
"""Which machine (or container) a temporary file's writer ran on: its pid means nothing elsewhere."""

_TEMPORARY_NAME = re.compile(r"^\..+\.([0-9a-f]{8})-([0-9]+)-[0-9a-f]{12}\.tmp$")
_OLD_TEMPORARY_NAME = re.compile(r"^\..+\.(?:h5|hdf5|npz)\.[0-9a-f]{12}\.tmp$", re.IGNORECASE)

STALE_TEMPORARY_AGE_S = 600.0
"""How long a temporary file must have gone unmodified before it may be removed, s.
Containers that share a hostname but not their process ids see different processes
under the same pid: a writer alive in another one looks dead here, so its file is only
taken once it has stopped changing for this long."""

OLD_TEMPORARY_AGE_S = 86400.0
"""How long a temporary file named as echoloc named them before it tagged them with the
host and pid (``.<name>.<12 hex digits>.tmp``) must have gone unmodified before it may
be removed, s. Without a pid nothing tells a live writer from a dead one; a day without
a single write is the evidence, and those files of killed runs (hundreds of MB) would
otherwise stay for ever."""


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError, OSError):
        return True  # another user's, or cannot tell: keep its file
    return True


def _stale(name: str, age_s: float) -> bool:
    """Whether a file of this name, unmodified for ``age_s``, is a dead writer's temporary."""
    match = _TEMPORARY_NAME.match(name)
    if match is not None:
        return (
            match.group(1) == _HOST_TAG
            and age_s >= STALE_TEMPORARY_AGE_S
            and not _process_alive(int(match.group(2)))
        )
    return _OLD_TEMPORARY_NAME.match(name) is not None and age_s >= OLD_TEMPORARY_AGE_S


def remove_stale_temporaries(directory: str | os.PathLike[str]) -> list[Path]:
    """Remove the temporary files that killed writers left in ``directory``; return them.

    A write goes to ``.<name>.<host>-<pid>-<random>.tmp`` and is renamed over its target
    when complete (:func:`_atomic_write`); a writer killed by SIGKILL or a power cut
    leaves that file behind, as large as the recording. Every write into a folder first
    removes those whose writer ran on this host (by the tag of its name), is gone (no
    process of that pid) and has not modified it for :data:`STALE_TEMPORARY_AGE_S`; and
    those of the older naming unmodified for :data:`OLD_TEMPORARY_AGE_S`. Nothing else is
    touched: not a live writer's file, not one written on another machine sharing the
    folder, not a file of another name. A pid reused since only keeps a stale file until
    that process ends.
    """
    removed: list[Path] = []
    try:
        entries = list(os.scandir(directory))
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        if not (_TEMPORARY_NAME.match(entry.name) or _OLD_TEMPORARY_NAME.match(entry.name)):
            continue
        with contextlib.suppress(OSError):
            info = entry.stat(follow_symlinks=False)
            if stat.S_ISREG(info.st_mode) and _stale(entry.name, now - info.st_mtime):
                os.unlink(entry.path)
                removed.append(Path(entry.path))
    return removed


def _atomic_write(target: Path, source: str, write: Callable[[Path], None]) -> Path:
    """Run ``write`` on a new temporary file next to ``target``, then rename it over ``target``.

    On any exception (KeyboardInterrupt too) the temporary file is removed, ``target``
    is left as it was, and the exception propagates; ``write`` converts its own I/O
    errors (see :func:`_write_errors`) and lets everything else through.
    """
    parent = target.parent
    if problem := missing_directory(target):
        raise _error(source, problem)
    if target.is_dir():
        raise _error(source, "is a directory")
    remove_stale_temporaries(parent)
    tmp = parent / f".{target.name}.{_HOST_TAG}-{os.getpid()}-{secrets.token_hex(6)}.tmp"
    try:
        with _write_errors(source), open(tmp, "xb"):  # created with the user's umask, like open()
            pass
        write(tmp)
        with _write_errors(source):
            _fsync(tmp)
            os.replace(tmp, target)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    _fsync(parent, directory=True)
    return target


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
    target, source, hdf5 = _target(path)
    validate_recording(rec)

    def write(tmp: Path) -> None:
        with _write_errors(source):
            (_write_hdf5 if hdf5 else _write_npz)(tmp, rec)

    return _atomic_write(target, source, write)


# ----------------------------------------------------------------------------- streaming


@dataclass(frozen=True, eq=False)
class FrameBatch:
    """Consecutive frames and their per-frame fields, for :func:`write_recording_stream`.

    Attributes
    ----------
    frames
        (n, n_rx, n_samples), real or complex as the header's ``frames``.
    frame_times_s, frame_transmitter, truth_positions_m, sensor_poses
        The per-frame fields of :class:`Recording` for these n frames, or ``None``;
        every batch of a stream carries the same ones, with the same n_max.
    """

    frames: NDArray[np.floating] | NDArray[np.complexfloating]
    frame_times_s: NDArray[np.float64] | None = None
    frame_transmitter: NDArray[np.int64] | None = None
    truth_positions_m: NDArray[np.float64] | None = None
    sensor_poses: NDArray[np.float64] | None = None

    @property
    def n_frames(self) -> int:
        return int(np.shape(self.frames)[0])


def _storage_dtype(source: str, frames_dtype: DTypeLike, is_complex: bool) -> np.dtype[Any]:
    """float32/float64 as asked, or its complex counterpart (complex64/complex128)."""
    try:
        real = np.dtype(frames_dtype)
    except TypeError:
        real = None
    if real is None or real not in (np.dtype(np.float32), np.dtype(np.float64)):
        raise _error(source, f"frames_dtype is {frames_dtype!r}, expected float32 or float64")
    return np.result_type(real, np.complex64) if is_complex else real


def _to_storage(source: str, frames: _AnyArray, storage: np.dtype[Any]) -> _AnyArray:
    """``frames`` (already checked finite) in the storage dtype; overflow is an error."""
    with np.errstate(over="ignore", invalid="ignore"):
        stored = frames.astype(storage, copy=False)
    if stored is not frames and not np.isfinite(stored).all():
        peak = float(np.max(np.abs(frames)))
        raise _error(source, f"frames has a value of magnitude {peak:g}, beyond the range of {storage}")
    return stored


class _Hdf5Sink:
    """Appends per-frame datasets to an open HDF5 file, each resizable along axis 0."""

    def __init__(self, file: Any) -> None:
        self._file = file
        self._empty: dict[str, tuple[np.dtype[Any], tuple[int, ...], int]] = {}

    def append(self, name: str, arr: _AnyArray) -> None:
        n, row_shape = int(arr.shape[0]), tuple(int(d) for d in arr.shape[1:])
        if arr[0].size == 0:  # e.g. truth with n_max = 0: HDF5 cannot chunk it; made in finish()
            _, _, rows = self._empty.get(name, (arr.dtype, row_shape, 0))
            self._empty[name] = (arr.dtype, row_shape, rows + n)
            return
        if name not in self._file:
            rows_per_chunk = max(1, min(n, _CHUNK_BYTES // arr[0].nbytes))
            self._file.create_dataset(
                name,
                shape=(0, *row_shape),
                maxshape=(None, *row_shape),
                dtype=arr.dtype,
                chunks=(rows_per_chunk, *row_shape),
            )
        dataset = self._file[name]
        start = int(dataset.shape[0])
        dataset.resize(start + n, axis=0)
        dataset[start:] = arr

    def finish(self) -> None:
        for name, (dtype, row_shape, rows) in self._empty.items():
            self._file.create_dataset(name, shape=(rows, *row_shape), dtype=dtype)


@dataclass
class _Spool:
    """The raw C-order bytes of one per-frame dataset, in an anonymous temporary file."""

    file: IO[bytes]
    dtype: np.dtype[Any]
    row_shape: tuple[int, ...]
    rows: int = 0


class _NpzSink(contextlib.AbstractContextManager["_NpzSink"]):
    """Spools per-frame datasets to disk, then writes them into a zip as ``.npy`` members."""

    def __init__(self, directory: Path) -> None:
        self._directory = directory
        self._spools: dict[str, _Spool] = {}

    def append(self, name: str, arr: _AnyArray) -> None:
        spool = self._spools.get(name)
        if spool is None:
            # Closed in __exit__; anonymous, so nothing is left behind even on a crash.
            file = tempfile.TemporaryFile(dir=self._directory, prefix=".echoloc-spool-")  # noqa: SIM115
            spool = self._spools[name] = _Spool(file, arr.dtype, tuple(int(d) for d in arr.shape[1:]))
        spool.file.write(np.ascontiguousarray(arr).reshape(-1).view(np.uint8).data)
        spool.rows += int(arr.shape[0])

    def write_members(self, archive: zipfile.ZipFile) -> None:
        for name, spool in self._spools.items():
            header = {
                "descr": np.lib.format.dtype_to_descr(spool.dtype),
                "fortran_order": False,
                "shape": (spool.rows, *spool.row_shape),
            }
            spool.file.seek(0)
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                np.lib.format.write_array_header_1_0(member, header)
                shutil.copyfileobj(spool.file, member, _CHUNK_BYTES)

    def __exit__(self, *exc_info: object) -> None:
        for spool in self._spools.values():
            spool.file.close()


def _append_batch(
    source: str,
    header: Recording,
    batch: object,
    layout: dict[str, tuple[int, ...]] | None,
    storage: np.dtype[Any],
    append: Callable[[str, _AnyArray], None],
) -> tuple[int, dict[str, tuple[int, ...]]]:
    """Check one batch against the header and the first batch's ``layout``, and append it.

    ``source`` names the file and the batch. Returns the batch's frame count and its
    layout: the row shape of each per-frame dataset it carries.
    """
    if not isinstance(batch, FrameBatch):
        raise _error(source, f"is a {type(batch).__name__}, expected a FrameBatch")
    n_rx, n_samples = (int(d) for d in header.frames.shape[1:])
    frames = _check_frames_layout(source, batch.frames, header.signal_kind, n_rx)
    if frames.shape[2] != n_samples:
        raise _error(
            source, f"frames has shape {frames.shape}, expected (n, {n_rx}, {n_samples}) as in the header"
        )
    n = int(frames.shape[0])
    _check_samples(source, frames, header.signal_kind, allow_nonfinite=False)
    values = {name: getattr(batch, field) for name, field in _PER_FRAME_DATASETS.items()}
    _check_per_frame(source, n, int(header.transmitters_m.shape[0]), *values.values())
    present = {
        name: tuple(int(d) for d in value.shape[1:]) for name, value in values.items() if value is not None
    }
    if layout is not None and present.keys() != layout.keys():
        have, had = (", ".join(fields) or "none" for fields in (present, layout))
        raise _error(
            source,
            f"carries per-frame fields {have} but batch 0 carried {had} (every batch must carry the same)",
        )
    for name, row_shape in (layout or {}).items():
        if present[name] != row_shape:
            shape = (n, *present[name])
            raise _error(source, f"{name} has shape {shape}, expected {(n, *row_shape)} as in batch 0")
    _check_truth_kinds(source, header.truth_kinds, values["truth_positions"])
    if n == 0:
        return 0, present

    stored = _to_storage(source, frames, storage)
    with _write_errors(source):
        append("frames", stored)
        del stored
        for name, value in values.items():
            if value is not None:
                dtype = np.int64 if name == "frame_transmitter" else np.float64
                append(name, np.asarray(value, dtype=dtype))
    return n, present


def _append_batches(
    source: str,
    header: Recording,
    batches: Iterable[FrameBatch],
    storage: np.dtype[Any],
    append: Callable[[str, _AnyArray], None],
) -> int:
    """Check and append every batch, holding one at a time; returns the frame count (>= 1)."""
    layout: dict[str, tuple[int, ...]] | None = None
    total = 0
    index = 0
    # Not enumerate(): its reused result tuple would keep the previous batch alive while
    # the iterator makes the next one. Exceptions of the iterator propagate unchanged.
    for batch in batches:
        where = f"{source}: batch {index} (from frame {total})"
        n, present = _append_batch(where, header, batch, layout, storage, append)
        del batch  # not alive while the iterator makes the next one
        layout = present if layout is None else layout
        total += n
        index += 1  # noqa: SIM113 (see above)
    if total == 0:
        raise _error(source, "no frames: the batches held none (a recording needs at least 1 frame)")
    return total


def _stream_hdf5(
    tmp: Path,
    source: str,
    header: Recording,
    batches: Iterable[FrameBatch],
    storage: np.dtype[Any],
    *,
    durable: bool = False,
) -> None:
    """Write the header, then append every batch; ``durable`` flushes to disk after each."""
    attrs, data = _file_items(header)
    del data["frames"]
    with _write_errors(source):
        file = h5py.File(tmp, "w")
    with file:
        with _write_errors(source):
            for name, value in attrs.items():
                file.attrs[name] = value
            for name, arr in data.items():
                file.create_dataset(name, data=arr)
            if durable:
                _durable(file)
        sink = _Hdf5Sink(file)

        def flushed(batches: Iterable[FrameBatch]) -> Iterator[FrameBatch]:
            for batch in batches:
                yield batch
                # Back here once the batch is appended, before the next is made.
                with _write_errors(source):
                    _durable(file)

        _append_batches(source, header, flushed(batches) if durable else batches, storage, sink.append)
        with _write_errors(source):
            sink.finish()


def _stream_npz(
    tmp: Path, source: str, header: Recording, batches: Iterable[FrameBatch], storage: np.dtype[Any]
) -> None:
    attrs, data = _file_items(header)
    del data["frames"]
    items: dict[str, _AnyArray] = {name: np.asarray(value) for name, value in attrs.items()}
    items.update(data)
    with _NpzSink(tmp.parent) as sink:
        _append_batches(source, header, batches, storage, sink.append)
        with (
            _write_errors(source),
            open(tmp, "r+b") as fh,
            zipfile.ZipFile(fh, "w", zipfile.ZIP_STORED, allowZip64=True) as archive,
        ):
            for name, arr in items.items():  # as np.savez writes them
                with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                    np.lib.format.write_array(member, arr, allow_pickle=False)
            sink.write_members(archive)


def write_recording_stream(
    header: Recording,
    batches: Iterable[FrameBatch],
    path: str | os.PathLike[str],
    *,
    frames_dtype: DTypeLike = np.float32,
) -> Path:
    """Write a recording batch by batch, holding one batch in memory, atomically.

    The file reads back with :func:`read_recording` as the concatenated recording
    written by :func:`write_recording` would, with ``frames`` rounded to
    ``frames_dtype``. HDF5 (``.h5``/``.hdf5``) is the streaming format: each batch is
    appended to resizable chunked datasets (chunks of up to one batch and about 1 MiB).
    For ``.npz`` the per-frame datasets are spooled to anonymous temporary files in
    the target directory and copied into the archive at the end (memory stays flat,
    the target's disk briefly holds the data twice).

    Each batch is checked as it arrives (shapes against the header and against
    batch 0, which fixes the per-frame fields present and n_max; finite samples;
    unit quaternions; transmitter indices); nothing is read back. As with
    :func:`write_recording`, the file is written under a temporary name and renamed
    over ``path`` only when complete: on any exception, including one raised by
    ``batches`` and KeyboardInterrupt, the temporary file is removed, ``path`` is
    left as it was, and the exception propagates.

    Parameters
    ----------
    header
        Every per-recording field (see :func:`validate_header` and :func:`as_header`);
        its ``frames`` only give (n_rx, n_samples) and real or complex.
    batches
        The frames in order, at least one frame in all; an empty batch is allowed.
    path
        The target file; its extension selects the format.
    frames_dtype
        float32 or float64: the stored dtype of real ``frames``; complex (``iq``)
        frames are stored as complex64 or complex128 respectively.

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    RecordingError
        If the header or a batch is invalid, batches disagree, there are no frames,
        the extension or ``frames_dtype`` is unsupported, the directory does not
        exist, or the file cannot be written. Batch errors name the batch.
    """
    target, source, hdf5 = _target(path)
    validate_header(header)
    storage = _storage_dtype(source, frames_dtype, header.frames.dtype.kind == "c")
    stream = _stream_hdf5 if hdf5 else _stream_npz
    return _atomic_write(target, source, lambda tmp: stream(tmp, source, header, batches, storage))


def append_recording_stream(
    header: Recording,
    batches: Iterable[FrameBatch],
    path: str | os.PathLike[str],
    *,
    frames_dtype: DTypeLike = np.float32,
) -> Path:
    """Write a recording batch by batch into ``path`` itself, durable after every batch.

    For recording a live stream (``echoloc record``): unlike
    :func:`write_recording_stream` the file is not written under a temporary name,
    so whatever was written survives the writer. After every batch the HDF5 file is
    flushed (HDF5 keeps its metadata, such as a dataset's length, in memory until a
    flush, so an unflushed file may not open at all) and synced to disk. A writer
    killed at any moment therefore leaves a file that reads back with
    :func:`read_recording` holding every batch but at most the one it was writing;
    a writer killed before its first batch was flushed leaves a file without
    ``frames``, which the reader refuses. On an exception (KeyboardInterrupt too)
    the frames written so far are kept, the file is closed, and the exception
    propagates. HDF5 only (``.h5``/``.hdf5``): a zip archive is readable only once
    complete.

    Parameters
    ----------
    header, batches, frames_dtype
        As for :func:`write_recording_stream`.
    path
        The file to create (an existing file is replaced).

    Returns
    -------
    Path
        ``path``.

    Raises
    ------
    RecordingError
        As :func:`write_recording_stream`, and for a path that is not HDF5.
    """
    target, source, hdf5 = _target(path)
    if not hdf5:
        raise _error(source, "a stream is recorded to HDF5 (.h5): a .npz is readable only once complete")
    if problem := missing_directory(target):
        raise _error(source, problem)
    validate_header(header)
    storage = _storage_dtype(source, frames_dtype, header.frames.dtype.kind == "c")
    _stream_hdf5(target, source, header, batches, storage, durable=True)
    _fsync(target.parent, directory=True)
    return target


def _durable(file: Any) -> None:
    """Flush an open HDF5 file to the operating system, then to the disk."""
    file.flush()
    with contextlib.suppress(Exception):  # a driver without a file descriptor: flushed is all we get
        os.fsync(file.id.get_vfd_handle())


def contract_items(rec: Recording) -> tuple[dict[str, object], dict[str, NDArray[Any]]]:
    """The root attributes and datasets of ``rec`` by their docs/FORMATS.md names, as a file holds them.

    For other carriers of the contract (the stream protocol's session message).
    """
    return _file_items(rec)


def recording_from_items(source: str, attrs: dict[str, object], data: dict[str, NDArray[Any]]) -> Recording:
    """A :class:`Recording` from attributes and datasets by their docs/FORMATS.md names, as a reader makes it.

    Checks names, types and dtypes as :func:`read_recording` does (not the
    contract's other rules: validate the result). ``source`` names it in messages.
    """
    return _build(source, attrs, data)
