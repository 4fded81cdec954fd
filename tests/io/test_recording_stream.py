"""Tests of the streaming writer, ``write_recording_stream`` (one batch in memory at a time)."""

from __future__ import annotations

import dataclasses
import itertools
import re
import tracemalloc
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from test_recording import EXTENSIONS, N_RX, N_SAMPLES, assert_same, make_recording

from echoloc.errors import RecordingError
from echoloc.io.recording import (
    FrameBatch,
    Recording,
    as_header,
    read_recording,
    validate_header,
    validate_recording,
    write_recording,
    write_recording_stream,
)

N_STREAM = 11  # frames in the streamed recordings
SPLIT = (0, 4, 4, 9, 11)  # batch boundaries: batches of 4, 0, 5 and 2 frames


def stream_recording(*, iq: bool = False) -> Recording:
    """A valid recording of two transmitters with every optional field, N_STREAM frames."""
    rng = np.random.default_rng(11)
    shape = (N_STREAM, N_RX, N_SAMPLES)
    truth = rng.uniform(-1.0, 1.0, (N_STREAM, 2, 3))
    truth[::3, 1] = np.nan
    angle = rng.uniform(0.0, np.pi, N_STREAM)
    poses = np.zeros((N_STREAM, 7))
    poses[:, :3] = rng.uniform(-5.0, 5.0, (N_STREAM, 3))
    poses[:, 5], poses[:, 6] = np.sin(angle / 2), np.cos(angle / 2)  # rotations about z
    codes = np.sin(np.linspace(0.0, 20.0, 16)) * np.array([[1.0], [-1.0]])
    rec = make_recording(
        full=True,
        transmitters_m=np.array([[-0.02, 0.0, 0.0], [0.02, 0.0, 0.0]]),
        transmitter_axes=None,
        frames=rng.standard_normal(shape),
        frame_times_s=np.arange(N_STREAM) * 0.02,
        frame_transmitter=np.arange(N_STREAM) % 2,
        truth_positions_m=truth,
        truth_kinds=("point",) * truth.shape[1],
        sensor_poses=poses,
        waveform=codes[0],
        transmitter_waveforms=codes,
    )
    if iq:
        rec = dataclasses.replace(
            rec,
            signal_kind="iq",
            frames=rec.frames + 1j * rng.standard_normal(shape),
            waveform=codes[0] * 1j,
            transmitter_waveforms=codes * 1j,
            background=None,
        )
    return validate_recording(rec)


def batches_of(rec: Recording, split: tuple[int, ...] = SPLIT) -> Iterator[FrameBatch]:
    for start, stop in itertools.pairwise(split):
        yield FrameBatch(
            frames=rec.frames[start:stop],
            frame_times_s=None if rec.frame_times_s is None else rec.frame_times_s[start:stop],
            frame_transmitter=None if rec.frame_transmitter is None else rec.frame_transmitter[start:stop],
            truth_positions_m=None if rec.truth_positions_m is None else rec.truth_positions_m[start:stop],
            sensor_poses=None if rec.sensor_poses is None else rec.sensor_poses[start:stop],
        )


def changed(batch: FrameBatch, **changes: Any) -> FrameBatch:
    return dataclasses.replace(batch, **changes)


# ----------------------------------------------------------------------------- equivalence


@pytest.mark.parametrize("ext", [".h5", ".hdf5", ".npz"])
@pytest.mark.parametrize("iq", [False, True])
def test_stream_reads_back_as_the_batch_write(tmp_path: Path, ext: str, iq: bool) -> None:
    rec = stream_recording(iq=iq)
    streamed = write_recording_stream(as_header(rec), batches_of(rec), tmp_path / f"stream{ext}")
    assert streamed == tmp_path / f"stream{ext}"
    back = read_recording(streamed)

    rounded = dataclasses.replace(
        rec, frames=rec.frames.astype(np.complex64) if iq else rec.frames.astype(np.float32)
    )
    assert_same(read_recording(write_recording(rounded, tmp_path / f"batch{ext}")), back)
    assert np.allclose(back.frames, rec.frames, rtol=1e-6, atol=1e-6)
    assert_same(dataclasses.replace(rec, frames=back.frames), back)  # everything else exact
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([f"batch{ext}", f"stream{ext}"])


@pytest.mark.parametrize("ext", EXTENSIONS)
def test_stream_float64_is_exact(tmp_path: Path, ext: str) -> None:
    rec = stream_recording()
    path = write_recording_stream(
        as_header(rec), batches_of(rec), tmp_path / f"r{ext}", frames_dtype=np.float64
    )
    assert_same(rec, read_recording(path))


def test_stream_without_per_frame_fields(tmp_path: Path) -> None:
    rec = make_recording()
    path = write_recording_stream(as_header(rec), batches_of(rec, (0, 1, 2)), tmp_path / "r.h5")
    with h5py.File(path, "r") as f:
        assert set(f) == {"transmitters", "receivers", "frames", "waveform"}
    assert np.allclose(read_recording(path).frames, rec.frames, rtol=1e-6)


def test_stream_h5_datasets_are_chunked_and_resizable(tmp_path: Path) -> None:
    rec = stream_recording()
    path = write_recording_stream(as_header(rec), batches_of(rec), tmp_path / "r.h5")
    with h5py.File(path, "r") as f:
        frames = f["frames"]
        assert frames.dtype == np.float32
        assert frames.shape == (N_STREAM, N_RX, N_SAMPLES)
        assert frames.maxshape == (None, N_RX, N_SAMPLES)
        assert frames.chunks == (4, N_RX, N_SAMPLES)  # one (first) batch: 4 frames, well under 1 MiB
        assert f["sensor_poses"].maxshape == (None, 7)
        assert f["frame_transmitter"].dtype == np.int64
        assert f.attrs["firing"] == "sequential"


def test_stream_truth_with_no_rows(tmp_path: Path) -> None:
    rec = make_recording(truth_positions_m=np.zeros((2, 0, 3)))
    path = write_recording_stream(as_header(rec), batches_of(rec, (0, 1, 2)), tmp_path / "r.h5")
    back = read_recording(path)
    assert back.truth_positions_m is not None
    assert back.truth_positions_m.shape == (2, 0, 3)


# ----------------------------------------------------------------------------- header


def test_as_header_strips_per_frame_fields_and_frames() -> None:
    rec = stream_recording()
    header = as_header(rec)
    assert header.frames.shape == (0, N_RX, N_SAMPLES)
    assert header.frames.dtype == rec.frames.dtype
    assert header.frames.base is None  # no view keeping the recording's frames alive
    assert header.frame_times_s is None
    assert header.frame_transmitter is None
    assert header.truth_positions_m is None
    assert header.sensor_poses is None
    assert header.receiver_gain is rec.receiver_gain
    assert header.transmitter_waveforms is rec.transmitter_waveforms
    assert validate_header(header) is header


def test_header_built_directly_with_no_frames() -> None:
    header = make_recording(frames=np.empty((0, N_RX, N_SAMPLES)), source="hdr")
    assert validate_header(header) is header
    with pytest.raises(RecordingError, match=r"^hdr: frames has shape .*: no frames$"):
        validate_recording(header)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"frame_times_s": np.zeros(0)}, "frame_times is a per-frame field"),
        ({"frame_transmitter": np.zeros(0, dtype=int)}, "frame_transmitter is a per-frame field"),
        ({"truth_positions_m": np.zeros((0, 1, 3))}, "truth_positions is a per-frame field"),
        ({"sensor_poses": np.zeros((0, 7))}, "sensor_poses is a per-frame field"),
        ({"background": np.zeros((0, N_RX, N_SAMPLES))}, "background has shape"),
        ({"receiver_gain": np.ones(N_SAMPLES + 1)}, "receiver_gain has shape"),
        ({"frames": np.empty((0, N_RX + 1, N_SAMPLES))}, "frames has 5 channels"),
        ({"waveform": None}, "waveform is missing"),
        ({"firing": "both"}, "firing is 'both'"),
    ],
)
def test_invalid_header_is_rejected_before_writing(
    tmp_path: Path, changes: dict[str, Any], message: str
) -> None:
    header = dataclasses.replace(as_header(make_recording(full=True)), source="hdr", **changes)
    with pytest.raises(RecordingError, match=f"^hdr: {message}"):
        write_recording_stream(header, batches_of(make_recording()), tmp_path / "r.h5")
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- bad batches

BadBatches = list[tuple[str, list[FrameBatch], str]]


def bad_batches() -> BadBatches:
    """(id, batches, pattern of the message); the fault is in batch 1, from frame 4."""
    rec = stream_recording()
    good = list(batches_of(rec, (0, 4, 8)))
    b = good[1]
    nan_frames = b.frames.copy()
    nan_frames[2, 1, 3] = np.nan
    tilted = b.sensor_poses.copy()  # type: ignore[union-attr]
    tilted[3, 6] = 1.5
    cases: list[tuple[str, FrameBatch, str]] = [
        (
            "fewer samples",
            changed(b, frames=b.frames[:, :, :-1]),
            r"frames has shape \(4, 4, 63\), expected \(n, 4, 64\)",
        ),
        ("fewer channels", changed(b, frames=b.frames[:, :-1]), "frames has 3 channels but receivers has 4"),
        ("complex frames", changed(b, frames=b.frames.astype(complex)), "frames has complex dtype"),
        ("integer frames", changed(b, frames=b.frames.astype(np.int32)), "frames has dtype int32"),
        ("2-D frames", changed(b, frames=b.frames[0]), "frames has shape"),
        (
            "nan sample",
            changed(b, frames=nan_frames),
            r"frames has 1 non-finite value\(s\), first nan at index \[2, 1, 3\]",
        ),
        ("missing field", changed(b, sensor_poses=None), "per-frame fields .* but batch 0 carried"),
        (
            "n_max changes",
            changed(b, truth_positions_m=np.full((4, 3, 3), np.nan)),
            r"truth_positions has shape \(4, 3, 3\), expected \(4, 2, 3\) as in batch 0",
        ),
        ("short frame_times", changed(b, frame_times_s=b.frame_times_s[:3]), "frame_times has shape"),  # type: ignore[index]
        ("poses wrong shape", changed(b, sensor_poses=np.zeros((4, 6))), "sensor_poses has shape"),
        (
            "non-unit quaternion",
            changed(b, sensor_poses=tilted),
            r"sensor_poses\[3\] has quaternion .* unit quaternion",
        ),
        (
            "bad transmitter",
            changed(b, frame_transmitter=np.full(4, 2)),
            r"frame_transmitter\[0\] is 2, expected 0..1",
        ),
        ("frames not an array", changed(b, frames=b.frames.tolist()), "frames must be a numpy array"),
        ("float32 overflow", changed(b, frames=b.frames * 1e300), "beyond the range of float32"),
    ]
    out: BadBatches = [(name, [good[0], batch], pattern) for name, batch, pattern in cases]
    extra = dataclasses.replace(good[0], sensor_poses=None)
    out.append(("extra field", [extra, b], "carries per-frame fields .*sensor_poses.* but batch 0 carried"))
    out.append(("not a batch", [good[0], b.frames], "is a ndarray, expected a FrameBatch"))  # type: ignore[list-item]
    return out


BAD = bad_batches()


@pytest.mark.parametrize("ext", EXTENSIONS)
@pytest.mark.parametrize(("batches", "pattern"), [c[1:] for c in BAD], ids=[c[0] for c in BAD])
def test_bad_batch_is_rejected_and_nothing_written(
    tmp_path: Path, ext: str, batches: list[FrameBatch], pattern: str
) -> None:
    path = tmp_path / f"r{ext}"
    with pytest.raises(RecordingError, match=pattern) as info:
        write_recording_stream(as_header(stream_recording()), iter(batches), path)
    message = str(info.value)
    assert message.startswith(f"{path}: batch 1 (from frame 4): ")
    assert "\n" not in message
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("ext", EXTENSIONS)
@pytest.mark.parametrize("batches", [[], [FrameBatch(np.zeros((0, N_RX, N_SAMPLES)))]], ids=["none", "empty"])
def test_no_frames_is_rejected(tmp_path: Path, ext: str, batches: list[FrameBatch]) -> None:
    path = tmp_path / f"r{ext}"
    with pytest.raises(RecordingError, match=f"^{re.escape(str(path))}: no frames"):
        write_recording_stream(as_header(make_recording()), batches, path)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(("path", "pattern"), [("r.mat", "extension"), ("absent/r.h5", "does not exist")])
def test_bad_target_is_rejected(tmp_path: Path, path: str, pattern: str) -> None:
    with pytest.raises(RecordingError, match=pattern):
        write_recording_stream(
            as_header(make_recording()), batches_of(make_recording(), (0, 2)), tmp_path / path
        )


@pytest.mark.parametrize("frames_dtype", [np.int16, np.float16, "complex64", "no such type"])
def test_bad_frames_dtype_is_rejected(tmp_path: Path, frames_dtype: Any) -> None:
    with pytest.raises(RecordingError, match="frames_dtype"):
        write_recording_stream(
            as_header(make_recording()),
            batches_of(make_recording(), (0, 2)),
            tmp_path / "r.h5",
            frames_dtype=frames_dtype,
        )
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- atomicity


class SimulatorError(Exception):
    """The simulator feeding the writer failed."""


@pytest.mark.parametrize("ext", EXTENSIONS)
@pytest.mark.parametrize(
    "error",
    [SimulatorError("simulator failed"), KeyboardInterrupt()],
    ids=["SimulatorError", "KeyboardInterrupt"],
)
@pytest.mark.parametrize("existing", [False, True])
def test_exception_mid_stream_leaves_destination_untouched(
    tmp_path: Path, ext: str, error: BaseException, existing: bool
) -> None:
    rec = stream_recording()
    path = tmp_path / f"r{ext}"
    if existing:
        write_recording(make_recording(seed=3), path)
    before = path.read_bytes() if existing else None

    def failing() -> Iterator[FrameBatch]:
        batches = batches_of(rec)
        yield next(batches)
        yield next(batches)
        raise error

    with pytest.raises(type(error)) as info:
        write_recording_stream(as_header(rec), failing(), path)
    assert info.value is error  # re-raised as it was, not wrapped
    assert [p.name for p in tmp_path.iterdir()] == ([path.name] if existing else [])
    if existing:
        assert path.read_bytes() == before


def test_write_failure_is_recording_error_and_cleans_up(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def full_disk(*args: object, **kwargs: object) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr("shutil.copyfileobj", full_disk)
    rec = stream_recording()
    with pytest.raises(RecordingError, match=r"cannot write: .*No space left"):
        write_recording_stream(as_header(rec), batches_of(rec), tmp_path / "r.npz")
    assert list(tmp_path.iterdir()) == []


# ----------------------------------------------------------------------------- memory


@pytest.mark.parametrize("ext", EXTENSIONS)
def test_stream_memory_is_flat(tmp_path: Path, ext: str) -> None:
    n_batches, shape = 200, (50, 4, 2400)
    batch_bytes = np.zeros(shape).nbytes  # 3.84 MB of float64 per batch; 768 MB in all
    header = make_recording(frames=np.empty((0, *shape[1:])))

    def batches() -> Iterator[FrameBatch]:
        for i in range(n_batches):
            times = np.arange(i * shape[0], (i + 1) * shape[0], dtype=np.float64) * 1e-3
            yield FrameBatch(np.full(shape, float(i)), frame_times_s=times)

    tracemalloc.start()
    try:
        path = write_recording_stream(header, batches(), tmp_path / f"r{ext}")
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    # One batch alive, plus its float32 copy and finiteness masks: about 1.6 batches. The
    # previous batch still alive while the next is made would be 2 or more.
    assert peak < 2 * batch_bytes, f"peak {peak / batch_bytes:.2f} batches"
    if ext == ".h5":
        with h5py.File(path, "r") as f:
            assert f["frames"].shape == (n_batches * shape[0], *shape[1:])
            assert f["frames"][-1, 0, 0] == n_batches - 1
    else:
        with np.load(path) as z:
            assert z["frame_times"].shape == (n_batches * shape[0],)
