"""Tests of the recording file contract (docs/FORMATS.md, "Recording file")."""

from __future__ import annotations

import dataclasses
import itertools
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from echoloc.errors import RecordingError
from echoloc.io.recording import (
    FORMAT_NAME,
    FORMAT_VERSION,
    QUATERNION_NORM_TOLERANCE,
    Recording,
    RecordingWarning,
    dead_receivers,
    read_recording,
    repair_nonfinite,
    validate_recording,
    write_recording,
)
from raw_files import write_raw

N_FRAMES, N_RX, N_SAMPLES, N_TX = 2, 4, 64, 1
EXTENSIONS = (".h5", ".npz")
NEW_DATASETS = ("sensor_poses", "receiver_gain", "transmitter_waveforms")

Attrs = dict[str, Any]
Data = dict[str, Any]


def make_recording(*, full: bool = False, seed: int = 0, **changes: Any) -> Recording:
    """A small valid rf recording; ``full`` fills every optional field."""
    rng = np.random.default_rng(seed)
    rec = Recording(
        sample_rate_hz=200_000.0,
        transmitters_m=np.zeros((N_TX, 3)),
        receivers_m=rng.uniform(-0.05, 0.05, (N_RX, 3)),
        frames=rng.standard_normal((N_FRAMES, N_RX, N_SAMPLES)),
        waveform=np.sin(np.linspace(0.0, 20.0, 16)),
    )
    if full:
        truth = np.full((N_FRAMES, 3, 3), np.nan)
        truth[0, 0] = [0.1, -0.2, 1.5]
        truth[1, :2] = [[0.0, 0.0, 0.7], [0.3, 0.1, 2.0]]
        rec = dataclasses.replace(
            rec,
            carrier_hz=40_000.0,
            speed_of_sound_m_s=343.2,
            temperature_c=21.5,
            relative_humidity=0.45,
            frame_times_s=np.array([0.0, 0.05]),
            frame_transmitter=np.zeros(N_FRAMES, dtype=np.int64),
            background=rng.standard_normal((N_RX, N_SAMPLES)),
            transmitter_axes=np.array([[0.0, 0.0, 1.0]]),
            receiver_axes=np.tile([0.0, 0.6, 0.8], (N_RX, 1)),
            truth_positions_m=truth,
            sensor_poses=np.array(
                [[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], [1.0, -2.0, 0.5, 0.0, 0.6, 0.0, 0.8]]
            ),
            receiver_gain=np.geomspace(1.0, 100.0, N_SAMPLES),
            transmitter_waveforms=np.pad(rec.waveform, (0, 4))[None, :],  # type: ignore[arg-type]
            firing="sequential",
            field_of_view_deg=18.0,
            truth_kinds=("point", "plane", "corner"),
        )
    return dataclasses.replace(rec, **changes)


def file_items(rec: Recording) -> tuple[Attrs, Data]:
    """Root attributes and datasets of ``rec`` by their contract names, built by hand."""
    attrs: Attrs = {
        "format": FORMAT_NAME,
        "version": FORMAT_VERSION,
        "sample_rate_hz": rec.sample_rate_hz,
        "signal_kind": rec.signal_kind,
    }
    for name in (
        "firing",
        "carrier_hz",
        "speed_of_sound_m_s",
        "temperature_c",
        "relative_humidity",
        "field_of_view_deg",
    ):
        if getattr(rec, name) is not None:
            attrs[name] = getattr(rec, name)
    if rec.truth_kinds is not None:
        attrs["truth_kinds"] = ",".join(rec.truth_kinds)
    fields = {
        "transmitters": rec.transmitters_m,
        "receivers": rec.receivers_m,
        "frames": rec.frames,
        "waveform": rec.waveform,
        "frame_times": rec.frame_times_s,
        "frame_transmitter": rec.frame_transmitter,
        "background": rec.background,
        "transmitter_axes": rec.transmitter_axes,
        "receiver_axes": rec.receiver_axes,
        "truth_positions": rec.truth_positions_m,
        "sensor_poses": rec.sensor_poses,
        "receiver_gain": rec.receiver_gain,
        "transmitter_waveforms": rec.transmitter_waveforms,
    }
    return attrs, {name: value for name, value in fields.items() if value is not None}


def assert_same(a: Recording, b: Recording) -> None:
    """Every field but ``source`` equal, arrays exactly (NaN equal to NaN)."""
    for field in dataclasses.fields(Recording):
        if field.name == "source":
            continue
        x, y = getattr(a, field.name), getattr(b, field.name)
        if isinstance(x, np.ndarray):
            assert isinstance(y, np.ndarray), field.name
            assert x.shape == y.shape, field.name
            assert np.array_equal(x, y, equal_nan=True), field.name
        else:
            assert x == y, field.name


# ----------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("ext", [".h5", ".hdf5", ".npz"])
@pytest.mark.parametrize("full", [False, True])
def test_round_trip_preserves_every_field(tmp_path: Path, ext: str, full: bool) -> None:
    rec = make_recording(full=full)
    path = write_recording(rec, tmp_path / f"rec{ext}")
    assert path == tmp_path / f"rec{ext}"
    back = read_recording(path)
    assert back.source == str(path)
    assert_same(rec, back)
    assert back.frames.dtype == np.float64


@pytest.mark.parametrize("ext", EXTENSIONS)
def test_round_trip_iq_envelope_and_float32(tmp_path: Path, ext: str) -> None:
    rng = np.random.default_rng(1)
    shape = (N_FRAMES, N_RX, N_SAMPLES)
    iq_frames = (rng.standard_normal(shape) + 1j * rng.standard_normal(shape)).astype(np.complex64)
    iq = make_recording(signal_kind="iq", frames=iq_frames, carrier_hz=40e3)
    back = read_recording(write_recording(iq, tmp_path / f"iq{ext}"))
    assert back.frames.dtype == np.complex128
    assert np.array_equal(back.frames, iq_frames)

    env = make_recording(signal_kind="envelope", frames=np.abs(iq_frames), waveform=None)
    back = read_recording(write_recording(env, tmp_path / f"env{ext}"))
    assert back.frames.dtype == np.float64
    assert back.waveform is None
    assert np.array_equal(back.frames, np.abs(iq_frames))


def two_transmitter_recording(*, iq: bool = False) -> Recording:
    """Two transmitters firing simultaneously with different codes (complex baseband if ``iq``)."""
    rng = np.random.default_rng(5)
    codes = np.array([[1.0, 1.0, -1.0, 1.0, 0.0, 0.0], [1.0, -1.0, -1.0, -1.0, 1.0, -1.0]])
    frames = rng.standard_normal((N_FRAMES, N_RX, N_SAMPLES))
    rec = make_recording(
        transmitters_m=np.array([[-0.02, 0.0, 0.0], [0.02, 0.0, 0.0]]),
        waveform=codes[0, :4],  # transmitter 0's code without its zero padding
        transmitter_waveforms=codes,
        firing="simultaneous",
        frames=frames,
    )
    if iq:
        rec = dataclasses.replace(
            rec,
            signal_kind="iq",
            frames=frames * np.exp(1j),
            waveform=codes[0] * np.exp(0.5j),
            transmitter_waveforms=codes * np.exp(0.5j),
        )
    return rec


@pytest.mark.parametrize("ext", EXTENSIONS)
@pytest.mark.parametrize("iq", [False, True])
def test_round_trip_transmitter_waveforms_and_simultaneous_firing(tmp_path: Path, ext: str, iq: bool) -> None:
    rec = validate_recording(two_transmitter_recording(iq=iq))
    back = read_recording(write_recording(rec, tmp_path / f"rec{ext}"))
    assert_same(rec, back)
    assert back.firing == "simultaneous"
    assert back.transmitter_waveforms is not None
    assert back.transmitter_waveforms.dtype == (np.complex128 if iq else np.float64)


@pytest.mark.parametrize("ext", EXTENSIONS)
def test_new_fields_are_optional_extensions(tmp_path: Path, ext: str) -> None:
    """What a reader that knows only the old fields sees: the same recording, minus the new ones."""
    rec = make_recording(full=True)
    attrs, data = file_items(rec)
    for name in NEW_DATASETS:
        del data[name]
    del attrs["firing"]
    old = dataclasses.replace(
        rec, sensor_poses=None, receiver_gain=None, transmitter_waveforms=None, firing=None
    )
    assert_same(old, read_recording(write_raw(tmp_path / f"old{ext}", attrs, data)))
    with h5py.File(write_recording(rec, tmp_path / "new.h5"), "r") as f:
        assert f.attrs["firing"] == "sequential"
        assert {f[name].dtype for name in NEW_DATASETS} == {np.dtype(np.float64)}
        assert f["sensor_poses"].shape == (N_FRAMES, 7)
        assert f["receiver_gain"].shape == (N_SAMPLES,)


def test_optional_none_fields_not_written(tmp_path: Path) -> None:
    path = write_recording(make_recording(), tmp_path / "rec.h5")
    with h5py.File(path, "r") as f:
        assert set(f.attrs) == {"format", "version", "sample_rate_hz", "signal_kind"}
        assert set(f) == {"transmitters", "receivers", "frames", "waveform"}
    path = write_recording(make_recording(), tmp_path / "rec.npz")
    with np.load(path) as z:
        assert "carrier_hz" not in z.files
        assert "background" not in z.files


def test_h5_frames_one_frame_per_chunk(tmp_path: Path) -> None:
    path = write_recording(make_recording(), tmp_path / "rec.h5")
    with h5py.File(path, "r") as f:
        assert f["frames"].chunks == (1, N_RX, N_SAMPLES)
        assert f["frames"].compression is None
        assert f.attrs["format"] == FORMAT_NAME
        assert f.attrs["version"] == FORMAT_VERSION


def test_reader_accepts_bytes_and_array_attributes_and_ignores_unknown(tmp_path: Path) -> None:
    rec = make_recording(full=True)
    attrs, data = file_items(rec)
    attrs["format"] = np.bytes_(FORMAT_NAME.encode())  # fixed-length HDF5 string
    attrs["signal_kind"] = np.bytes_(b"rf")
    attrs["version"] = np.array([1], dtype=np.int32)  # one-element array, as MATLAB writes
    attrs["operator"] = "someone"
    data["notes"] = np.arange(5)
    path = write_raw(tmp_path / "rec.h5", attrs, data)
    with h5py.File(path, "a") as f:
        f.create_group("extras")
    assert_same(rec, read_recording(path))


def test_reader_accepts_big_endian_datasets(tmp_path: Path) -> None:
    rec = make_recording(full=True)
    attrs, data = file_items(rec)
    data = {k: v.astype(v.dtype.newbyteorder(">")) for k, v in data.items()}
    back = read_recording(write_raw(tmp_path / "rec.h5", attrs, data))
    assert_same(rec, back)


def test_signal_kind_defaults_to_rf(tmp_path: Path) -> None:
    attrs, data = file_items(make_recording())
    del attrs["signal_kind"]
    assert read_recording(write_raw(tmp_path / "rec.npz", attrs, data)).signal_kind == "rf"


# ----------------------------------------------------------------------------- broken files

Breaker = Callable[[Attrs, Data], None]


def _set(where: str, name: str, value: Any) -> Breaker:
    def apply(attrs: Attrs, data: Data) -> None:
        (attrs if where == "attr" else data)[name] = value

    return apply


def _drop(where: str, name: str) -> Breaker:
    def apply(attrs: Attrs, data: Data) -> None:
        del (attrs if where == "attr" else data)[name]

    return apply


def _poke(name: str, index: tuple[int, ...], value: float) -> Breaker:
    def apply(attrs: Attrs, data: Data) -> None:
        arr = np.array(data[name])
        arr[index] = value
        data[name] = arr

    return apply


def _envelope_with_negative(attrs: Attrs, data: Data) -> None:
    attrs["signal_kind"] = "envelope"
    frames = np.abs(data["frames"])
    frames[1, 2, 3] = -0.5
    data["frames"] = frames


def _real_frames_for_iq(attrs: Attrs, data: Data) -> None:
    attrs["signal_kind"] = "iq"


_rng = np.random.default_rng(7)
_F = (N_FRAMES, N_RX, N_SAMPLES)

# (id, breaker, a word the message must contain)
BROKEN: list[tuple[str, Breaker, str]] = [
    ("wrong format name", _set("attr", "format", "echoloc-scene"), "format"),
    ("missing format", _drop("attr", "format"), "format"),
    ("wrong version", _set("attr", "version", 2), "version"),
    ("string version", _set("attr", "version", "1"), "version"),
    ("missing version", _drop("attr", "version"), "version"),
    ("missing sample rate", _drop("attr", "sample_rate_hz"), "sample_rate_hz"),
    ("zero sample rate", _set("attr", "sample_rate_hz", 0.0), "sample_rate_hz"),
    ("negative sample rate", _set("attr", "sample_rate_hz", -1.0), "sample_rate_hz"),
    ("nan sample rate", _set("attr", "sample_rate_hz", np.nan), "sample_rate_hz"),
    ("text sample rate", _set("attr", "sample_rate_hz", "fast"), "sample_rate_hz"),
    ("unknown signal kind", _set("attr", "signal_kind", "audio"), "signal_kind"),
    ("zero carrier", _set("attr", "carrier_hz", 0.0), "carrier_hz"),
    ("negative speed of sound", _set("attr", "speed_of_sound_m_s", -343.0), "speed_of_sound"),
    ("nan temperature", _set("attr", "temperature_c", np.nan), "temperature_c"),
    ("humidity above 1", _set("attr", "relative_humidity", 1.5), "relative_humidity"),
    ("field of view above 180", _set("attr", "field_of_view_deg", 200.0), "field_of_view_deg"),
    ("zero field of view", _set("attr", "field_of_view_deg", 0.0), "field_of_view_deg"),
    ("missing transmitters", _drop("data", "transmitters"), "transmitters"),
    ("transmitters wrong shape", _set("data", "transmitters", np.zeros(3)), "transmitters"),
    ("no transmitters", _set("data", "transmitters", np.zeros((0, 3))), "transmitters"),
    ("inf in transmitters", _poke("transmitters", (0, 2), np.inf), "transmitters"),
    ("integer transmitters", _set("data", "transmitters", np.zeros((1, 3), int)), "transmitters"),
    ("missing receivers", _drop("data", "receivers"), "receivers"),
    ("receivers wrong shape", _set("data", "receivers", np.zeros((N_RX, 2))), "receivers"),
    ("nan in receivers", _poke("receivers", (1, 0), np.nan), "receivers"),
    ("channel count mismatch", _set("data", "receivers", np.zeros((N_RX - 1, 3))), "channels"),
    ("missing frames", _drop("data", "frames"), "frames"),
    ("frames 2-D", _set("data", "frames", np.zeros((N_RX, N_SAMPLES))), "frames"),
    ("frames integer", _set("data", "frames", np.ones(_F, dtype=np.int16)), "frames"),
    ("frames float16", _set("data", "frames", np.ones(_F, dtype=np.float16)), "frames"),
    ("frames no samples", _set("data", "frames", np.zeros((N_FRAMES, N_RX, 0))), "frames"),
    ("frames no frames", _set("data", "frames", np.zeros((0, N_RX, N_SAMPLES))), "frames"),
    ("nan sample", _poke("frames", (1, 2, 3), np.nan), "frames"),
    ("inf sample", _poke("frames", (0, 0, 0), -np.inf), "frames"),
    (
        "complex frames for rf",
        _set("data", "frames", np.ones(_F, dtype=np.complex64)),
        "frames",
    ),
    ("real frames for iq", _real_frames_for_iq, "frames"),
    ("negative envelope", _envelope_with_negative, "frames"),
    ("missing waveform for rf", _drop("data", "waveform"), "waveform"),
    ("empty waveform", _set("data", "waveform", np.zeros(0)), "waveform"),
    ("waveform 2-D", _set("data", "waveform", np.zeros((2, 8))), "waveform"),
    ("nan in waveform", _poke("waveform", (3,), np.nan), "waveform"),
    ("frame_times wrong shape", _set("data", "frame_times", np.zeros(N_FRAMES + 1)), "frame_times"),
    ("nan frame_times", _poke("frame_times", (1,), np.nan), "frame_times"),
    (
        "frame_transmitter out of range",
        _set("data", "frame_transmitter", np.array([0, N_TX])),
        "frame_transmitter",
    ),
    (
        "negative frame_transmitter",
        _set("data", "frame_transmitter", np.array([-1, 0])),
        "frame_transmitter",
    ),
    (
        "float frame_transmitter",
        _set("data", "frame_transmitter", np.zeros(N_FRAMES)),
        "frame_transmitter",
    ),
    (
        "frame_transmitter wrong shape",
        _set("data", "frame_transmitter", np.zeros(N_FRAMES + 1, dtype=int)),
        "frame_transmitter",
    ),
    ("bad background shape", _set("data", "background", np.zeros((N_RX, 5))), "background"),
    ("nan background", _poke("background", (0, 0), np.nan), "background"),
    (
        "complex background for rf",
        _set("data", "background", np.zeros((N_RX, N_SAMPLES), dtype=complex)),
        "background",
    ),
    (
        "zero transmitter axis",
        _set("data", "transmitter_axes", np.zeros((N_TX, 3))),
        "transmitter_axes",
    ),
    (
        "receiver_axes wrong shape",
        _set("data", "receiver_axes", np.ones((N_RX + 1, 3))),
        "receiver_axes",
    ),
    ("nan receiver axis", _poke("receiver_axes", (0, 0), np.nan), "receiver_axes"),
    (
        "truth wrong frame count",
        _set("data", "truth_positions", np.zeros((N_FRAMES + 1, 2, 3))),
        "truth_positions",
    ),
    ("truth 2-D", _set("data", "truth_positions", np.zeros((N_FRAMES, 3))), "truth_positions"),
    ("inf in truth", _poke("truth_positions", (0, 0, 0), np.inf), "truth_positions"),
    ("half-NaN truth row", _poke("truth_positions", (0, 1, 0), 1.0), "truth_positions"),
    ("sensor_poses wrong shape", _set("data", "sensor_poses", np.zeros((N_FRAMES, 6))), "sensor_poses"),
    ("sensor_poses 1-D", _set("data", "sensor_poses", np.zeros(7)), "sensor_poses"),
    ("nan sensor pose", _poke("sensor_poses", (1, 2), np.nan), "sensor_poses"),
    ("non-unit quaternion", _poke("sensor_poses", (1, 6), 0.9), "sensor_poses.1. .*unit quaternion"),
    ("zero quaternion", _set("data", "sensor_poses", np.zeros((N_FRAMES, 7))), "unit quaternion"),
    ("integer sensor_poses", _set("data", "sensor_poses", np.zeros((N_FRAMES, 7), int)), "sensor_poses"),
    ("zero receiver_gain", _poke("receiver_gain", (5,), 0.0), r"receiver_gain\[5\] is 0.0, expected > 0"),
    ("negative receiver_gain", _poke("receiver_gain", (0,), -2.0), "receiver_gain"),
    ("inf receiver_gain", _poke("receiver_gain", (1,), np.inf), "receiver_gain"),
    ("receiver_gain wrong shape", _set("data", "receiver_gain", np.ones(N_SAMPLES - 1)), "receiver_gain"),
    ("receiver_gain per channel", _set("data", "receiver_gain", np.ones((N_RX, N_SAMPLES))), "receiver_gain"),
    (
        "transmitter_waveforms wrong count",
        _set("data", "transmitter_waveforms", np.ones((N_TX + 1, 16))),
        "transmitter_waveforms",
    ),
    (
        "transmitter_waveforms 1-D",
        _set("data", "transmitter_waveforms", np.ones(16)),
        "transmitter_waveforms",
    ),
    ("nan transmitter_waveforms", _poke("transmitter_waveforms", (0, 2), np.nan), "transmitter_waveforms"),
    (
        "complex transmitter_waveforms for rf",
        _set("data", "transmitter_waveforms", np.ones((N_TX, 16), dtype=complex)),
        "transmitter_waveforms",
    ),
    (
        "transmitter_waveforms[0] not the waveform",
        _poke("transmitter_waveforms", (0, 3), 7.0),
        r"transmitter_waveforms\[0\] differs from waveform",
    ),
    (
        "waveform padding not zero in transmitter_waveforms[0]",
        _poke("transmitter_waveforms", (0, 17), 0.5),
        "transmitter_waveforms",
    ),
    ("unknown firing", _set("attr", "firing", "round-robin"), "firing is 'round-robin', expected one of"),
    ("numeric firing", _set("attr", "firing", 1), "firing"),
]


@pytest.mark.parametrize("ext", EXTENSIONS)
@pytest.mark.parametrize(("breaker", "field"), [b[1:] for b in BROKEN], ids=[b[0] for b in BROKEN])
def test_broken_file_is_rejected(tmp_path: Path, ext: str, breaker: Breaker, field: str) -> None:
    attrs, data = file_items(make_recording(full=True))
    breaker(attrs, data)
    path = write_raw(tmp_path / f"rec{ext}", attrs, data)
    with pytest.raises(RecordingError, match=field) as info:
        read_recording(path)
    message = str(info.value)
    assert message.startswith(f"{path}: ")
    assert "\n" not in message


def test_channel_mismatch_message(tmp_path: Path) -> None:
    rec = make_recording(frames=np.zeros((N_FRAMES, 3, N_SAMPLES)) + 1.0, source="rec.h5")
    with pytest.raises(RecordingError) as info:
        validate_recording(rec)
    assert str(info.value) == "rec.h5: frames has 3 channels but receivers has 4"


@pytest.mark.parametrize(
    ("name", "content", "expected"),
    [
        ("text.h5", b"this is not hdf5\n", "HDF5"),
        ("text.hdf5", b"", "HDF5"),
        ("text.npz", b"this is not a zip archive\n" * 4, "NPZ"),
        ("truncated.npz", b"PK\x03\x04" + b"\x00" * 40, "NPZ"),
        ("rec.txt", b"", "extension"),
        ("rec", b"", "extension"),
    ],
)
def test_unreadable_file_is_rejected(tmp_path: Path, name: str, content: bytes, expected: str) -> None:
    path = tmp_path / name
    path.write_bytes(content)
    with pytest.raises(RecordingError, match=expected) as info:
        read_recording(path)
    assert str(info.value).startswith(f"{path}: ")
    assert "\n" not in str(info.value)


def test_npz_holding_a_single_array_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "array.npz"
    with open(path, "wb") as fh:
        np.save(fh, np.zeros(3))
    with pytest.raises(RecordingError, match="NPZ"):
        read_recording(path)


@pytest.mark.parametrize("ext", EXTENSIONS)
def test_missing_file_is_rejected(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"absent{ext}"
    with pytest.raises(RecordingError, match="no such file"):
        read_recording(path)


def test_directory_is_rejected(tmp_path: Path) -> None:
    path = tmp_path / "dir.h5"
    path.mkdir()
    with pytest.raises(RecordingError, match="is a directory"):
        read_recording(path)


def test_group_instead_of_dataset_is_rejected(tmp_path: Path) -> None:
    attrs, data = file_items(make_recording())
    del data["frames"]
    path = write_raw(tmp_path / "rec.h5", attrs, data)
    with h5py.File(path, "a") as f:
        f.create_group("frames")
    with pytest.raises(RecordingError, match="frames"):
        read_recording(path)


# ----------------------------------------------------------------------------- validation


def test_validate_returns_the_recording() -> None:
    rec = make_recording(full=True)
    assert validate_recording(rec) is rec


def test_validate_names_source_and_field() -> None:
    rec = make_recording(source="mem", sample_rate_hz=-5.0)
    with pytest.raises(RecordingError, match=r"^mem: sample_rate_hz .*-5\.0"):
        validate_recording(rec)


def test_validate_rejects_non_array_field() -> None:
    rec = make_recording(receivers_m=[[0.0, 0.0, 0.0]] * N_RX)
    with pytest.raises(RecordingError, match="receivers must be a numpy array"):
        validate_recording(rec)


def test_validate_non_unit_quaternion_message() -> None:
    poses = np.tile([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0], (N_FRAMES, 1))
    poses[1, 3:] = [0.0, 0.0, 0.6, 0.81]  # norm 1.00654...: not normalised, rejected
    with pytest.raises(RecordingError) as info:
        validate_recording(make_recording(source="mem", sensor_poses=poses))
    assert str(info.value) == (
        "mem: sensor_poses[1] has quaternion [qx, qy, qz, qw] = [0.0, 0.0, 0.6, 0.81] "
        "of norm 1.00801786, expected a unit quaternion (|norm - 1| <= 1e-06)"
    )
    within = poses.copy()
    within[1, 3:] = [0.0, 0.0, 0.6, 0.8 + 0.5 * QUATERNION_NORM_TOLERANCE]
    assert validate_recording(make_recording(sensor_poses=within)).sensor_poses is within


@pytest.mark.parametrize("gain", [0.0, -1.0])
def test_validate_receiver_gain_must_be_positive(gain: float) -> None:
    rec = make_recording(source="mem", receiver_gain=np.full(N_SAMPLES, gain))
    with pytest.raises(RecordingError) as info:
        validate_recording(rec)
    assert str(info.value) == f"mem: receiver_gain[0] is {gain!r}, expected > 0 (a linear gain)"


def test_validate_unknown_firing_message() -> None:
    with pytest.raises(RecordingError) as info:
        validate_recording(make_recording(source="mem", firing="alternate"))
    assert str(info.value) == "mem: firing is 'alternate', expected one of 'sequential', 'simultaneous'"


@pytest.mark.parametrize(
    ("kinds", "message"),
    [
        (
            ("point", "wall", "corner"),
            "mem: truth_kinds names 'wall', expected one of 'point', 'plane', 'corner'",
        ),
        (("point", "plane"), "mem: truth_kinds names 2 classes for the 3 columns of truth_positions"),
    ],
)
def test_validate_truth_kinds_message(kinds: tuple[str, ...], message: str) -> None:
    with pytest.raises(RecordingError) as info:
        validate_recording(make_recording(full=True, source="mem", truth_kinds=kinds))
    assert str(info.value) == message


def test_truth_kinds_without_truth_positions_are_kept_and_name_nothing() -> None:
    """A recording cut down to its samples (truth_positions dropped) keeps its classes valid: they
    name the columns of a truth that is not there, and nothing reads them then."""
    validate_recording(make_recording(source="mem", truth_kinds=("point",)))


def test_validate_waveform_and_transmitter_0_may_differ_only_by_zero_padding() -> None:
    rec = two_transmitter_recording()
    assert rec.transmitter_waveforms is not None
    longer = dataclasses.replace(rec, waveform=np.pad(rec.transmitter_waveforms[0], (0, 10)))
    assert validate_recording(longer) is longer
    codes = rec.transmitter_waveforms[::-1].copy()  # transmitter 0 got transmitter 1's code
    with pytest.raises(RecordingError, match=r"^<memory>: transmitter_waveforms\[0\] differs from waveform"):
        validate_recording(dataclasses.replace(rec, transmitter_waveforms=codes))


def test_validate_envelope_without_waveform_and_per_frame_background() -> None:
    rng = np.random.default_rng(3)
    rec = make_recording(
        signal_kind="envelope",
        waveform=None,
        frames=rng.uniform(0, 1, _F),
        background=rng.uniform(0, 1, _F),
    )
    assert validate_recording(rec) is rec


# ----------------------------------------------------------------------------- repair, dead


def test_repair_nonfinite_replaces_and_counts() -> None:
    frames = make_recording().frames.copy()
    frames[0, 1, 5] = np.nan
    frames[1, 3, 0] = np.inf
    frames[1, 3, 1] = -np.inf
    rec = make_recording(frames=frames)
    fixed, count = repair_nonfinite(rec)
    assert count == 3
    assert fixed is not rec
    assert np.isnan(rec.frames[0, 1, 5])  # the original is untouched
    assert fixed.frames[0, 1, 5] == 0
    assert fixed.frames[1, 3, 0] == 0
    assert fixed.frames[1, 3, 1] == 0
    mask = np.isfinite(frames)
    assert np.array_equal(fixed.frames[mask], frames[mask])
    assert validate_recording(fixed) is fixed


@pytest.mark.parametrize("ext", EXTENSIONS)
def test_read_with_repair_warns_with_count(tmp_path: Path, ext: str) -> None:
    attrs, data = file_items(make_recording())
    frames = np.array(data["frames"])
    frames[0, 0, :3] = np.nan
    frames[1, 2, 7] = np.inf
    data["frames"] = frames
    path = write_raw(tmp_path / f"rec{ext}", attrs, data)
    with pytest.raises(RecordingError, match="frames has 4 non-finite"):
        read_recording(path)
    with pytest.warns(RecordingWarning, match="replaced 4 non-finite"):
        rec = read_recording(path, repair_nonfinite=True)
    assert np.isfinite(rec.frames).all()
    assert rec.frames[1, 2, 7] == 0.0


def test_read_with_repair_clean_file_does_not_warn(tmp_path: Path) -> None:
    original = make_recording()
    path = write_recording(original, tmp_path / "rec.h5")
    back = read_recording(path, repair_nonfinite=True)  # filterwarnings=error would fail on a warning
    np.testing.assert_array_equal(back.frames, original.frames)  # and nothing was "repaired"


@pytest.mark.parametrize("ext", EXTENSIONS)
def test_dead_channel_warns_with_index(tmp_path: Path, ext: str) -> None:
    frames = make_recording().frames.copy()
    frames[:, 2, :] = 0.0
    path = write_recording(make_recording(frames=frames), tmp_path / f"rec{ext}")
    with pytest.warns(RecordingWarning, match="receiver 2 looks dead"):
        rec = read_recording(path)
    assert np.array_equal(rec.frames, frames)


def test_several_dead_channels_warn_once() -> None:
    frames = make_recording().frames.copy()
    frames[:, 0, :] = 1.5
    frames[:, 3, :] = 0.0
    assert dead_receivers(make_recording(frames=frames)) == [0, 3]
    assert dead_receivers(make_recording()) == []


def test_channel_constant_in_one_frame_is_not_dead() -> None:
    frames = make_recording().frames.copy()
    frames[0, 1, :] = 0.0
    assert dead_receivers(make_recording(frames=frames)) == []


# ----------------------------------------------------------------------------- writing


def test_write_rejects_invalid_recording_and_leaves_nothing(tmp_path: Path) -> None:
    rec = make_recording(waveform=None)
    with pytest.raises(RecordingError, match="waveform"):
        write_recording(rec, tmp_path / "rec.h5")
    assert list(tmp_path.iterdir()) == []


def test_write_missing_directory(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="does not exist"):
        write_recording(make_recording(), tmp_path / "absent" / "rec.h5")


def test_write_unknown_extension(tmp_path: Path) -> None:
    with pytest.raises(RecordingError, match="extension"):
        write_recording(make_recording(), tmp_path / "rec.mat")


@pytest.mark.parametrize("ext", EXTENSIONS)
def test_write_overwrites_and_leaves_no_temporary(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"rec{ext}"
    write_recording(make_recording(seed=1), path)
    write_recording(make_recording(seed=2), path)
    assert [p.name for p in tmp_path.iterdir()] == [path.name]
    assert_same(make_recording(seed=2), read_recording(path))


@pytest.mark.parametrize("ext", EXTENSIONS)
def test_interrupted_write_keeps_old_file(tmp_path: Path, ext: str, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / f"rec{ext}"
    write_recording(make_recording(seed=1), path)
    before = path.read_bytes()

    def crash(*args: object, **kwargs: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", crash)
    with pytest.raises(KeyboardInterrupt):
        write_recording(make_recording(seed=2), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == [path.name]


def test_write_failure_is_recording_error(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    def full_disk(*args: object, **kwargs: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez", full_disk)
    with pytest.raises(RecordingError, match="No space left"):
        write_recording(make_recording(), tmp_path / "rec.npz")
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("ext", [".h5", ".npz"])
def test_truth_kinds_of_no_column_round_trip(tmp_path: Path, ext: str) -> None:
    """A scene without reflectors has truth_positions of no column and no class (an empty string)."""
    rec = make_recording(truth_positions_m=np.zeros((N_FRAMES, 0, 3)), truth_kinds=())
    back = read_recording(write_recording(rec, tmp_path / f"r{ext}"))
    assert back.truth_kinds == ()


@settings(max_examples=60, deadline=None)
@given(
    st.integers(1, 6),
    st.integers(1, 4),
    st.integers(1, 5),
    st.lists(st.integers(1, 3), min_size=1, max_size=6),
    st.integers(0, 2**16),
)
def test_dead_receivers_read_block_by_block_are_those_of_the_whole(
    n_frames: int, n_rx: int, n_samples: int, cuts: list[int], seed: int
) -> None:
    """A receiver is dead when every sample of the file equals its first: the same receivers
    whether the frames come at once or in any blocks (as batch reads a file)."""
    from echoloc.io.recording import constant_receivers

    rng = np.random.default_rng(seed)
    frames = rng.integers(0, 3, size=(n_frames, n_rx, n_samples))
    frames[:, rng.random(n_rx) < 0.5, :] = 7  # some receivers constant
    whole = constant_receivers([frames])
    expected = [r for r in range(n_rx) if (frames[:, r] == frames[0, r, 0]).all()]
    assert whole == ([] if n_frames * n_samples < 2 else expected)
    edges = np.cumsum([0, *cuts])
    blocks = [frames[a:b] for a, b in itertools.pairwise(edges)] + [frames[edges[-1] :]]
    assert constant_receivers(blocks) == whole
