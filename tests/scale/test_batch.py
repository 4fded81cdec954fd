"""``echoloc batch``: the serial commands' outputs, file by file, whatever the workers and chunks.

Three small simulated recordings, each with something that makes a frame's result depend
on more than the frame: the six-reflector scene with receiver 3 noisy in its first 30 of
40 frames (the channel check, made on frames spread over the file, leaves it out: a chunk
of the last frames alone would keep it), two transmitters fired in turn (each frame is
located with the one before), and a CH101-like envelope recording in an NPZ archive with
a ring-down at the start of every frame (envelope-peak measures it on the first frames of
the file). They run in chunks of 7 frames, which split them unevenly, on a cluster of one
worker and one of two, and every output must be the serial command's, byte for byte (the
map's arrays). The clusters listen on 127.0.0.1 and are shared by the module.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import signal
import subprocess
import sys
import warnings
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from echoloc.cli import commands
from echoloc.cli.app import ChainSettings
from echoloc.errors import RecordingError
from echoloc.io.recording import Recording, RecordingParts, read_recording, write_recording
from echoloc.scale import batch
from echoloc.scale.batch import BatchJob, find_inputs, output_path, run_batch, temporary_path
from echoloc.scale.cluster import open_client
from echoloc.sim.scenefile import load_scene, preset_path
from echoloc.sim.simulation import simulate
from echoloc.tof.channel_health import ASSESS_FRAMES, assessed_frames
from echoloc.tof.envelope_peaks import RING_DOWN_FRAMES

distributed = pytest.importorskip("distributed", reason="echoloc batch needs the cluster extra")

N_FRAMES = 40
CHUNK = 7
FILES = ("six.h5", "two.h5", "chirp.npz")
JOB_OUTPUT = {"echoes": ".echoes.jsonl", "locate": ".locate.jsonl", "evaluate": ".evaluate.json"}


# --- recordings and what the serial commands make of them -------------------------------------


def _noisy_six(n_frames: int) -> Recording:
    """The six-reflector scene, receiver 3 twenty times noisier in its first three quarters."""
    recording = simulate(load_scene(preset_path("random-1m3-six")), n_frames)
    frames = recording.frames.copy()
    noisy = n_frames * 3 // 4
    sigma = 20 * float(np.std(frames[noisy:, 3, -200:]))
    frames[:noisy, 3] += np.random.default_rng(1).normal(0.0, sigma, frames[:noisy, 3].shape)
    return dataclasses.replace(recording, frames=frames)


def _ringing_chirp(n_frames: int) -> Recording:
    """CH101-like envelopes (no waveform: envelope-peak) with a ring-down that varies frame to frame."""
    recording = simulate(load_scene(preset_path("ch101")), n_frames)
    frames = recording.frames.copy()
    rng = np.random.default_rng(3)
    scale = rng.uniform(0.2, 1.0, (n_frames, frames.shape[1], 1))
    frames[:, :, :8] += scale * float(frames.max()) * np.exp(-np.arange(8) / 3.0)
    return dataclasses.replace(recording, frames=frames)


def _write_recordings(folder: Path, n_frames: int) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    write_recording(_noisy_six(n_frames), folder / "six.h5")
    write_recording(simulate(load_scene(preset_path("two-transmitters")), n_frames), folder / "two.h5")
    write_recording(_ringing_chirp(n_frames), folder / "chirp.npz")
    return [folder / name for name in FILES]


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The three recordings, in a folder of their own (tests copy them where they write)."""
    folder = tmp_path_factory.mktemp("recordings")
    _write_recordings(folder, N_FRAMES)
    return folder


def _serial(*args: object) -> bytes:
    """What ``echoloc ARGS`` prints on stdout (in this process; warnings not shown)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        result = CliRunner().invoke(commands.cli, [str(a) for a in args])
    assert result.exit_code == 0, (args, result.output, result.exception)
    return result.stdout_bytes


def _map_arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as arrays:
        return {name: arrays[name] for name in arrays.files}


@pytest.fixture(scope="module")
def serial(recordings: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[tuple[str, str], Any]:
    """Each serial command's output for each recording: the bytes of stdout, the map's arrays."""
    maps = tmp_path_factory.mktemp("serial-maps")
    found: dict[tuple[str, str], Any] = {}
    for name in FILES:
        path = recordings / name
        for job in ("echoes", "locate", "evaluate"):
            found[name, job] = _serial(job, path, "--json")
        target = maps / f"{Path(name).stem}.map.npz"
        _serial("map", path, "-o", target)
        found[name, "map"] = _map_arrays(target)
    return found


def _assert_same(
    folder: Path, job: str, serial: dict[tuple[str, str], Any], names: tuple[str, ...] = FILES
) -> None:
    """Every output of ``job`` in ``folder`` is the serial command's."""
    for name in names:
        output = output_path(Path(name), job, folder)
        if job == "map":
            got = _map_arrays(output)
            want = serial[name, "map"]
            assert sorted(got) == sorted(want)
            for key in want:
                assert got[key].dtype == want[key].dtype, (name, key)
                np.testing.assert_array_equal(got[key], want[key], err_msg=f"{name}: {key}")
        else:
            assert output.read_bytes() == serial[name, job], (
                f"{output} differs from `echoloc {job} {name} --json`"
            )


# --- clusters ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def clients() -> Iterator[dict[int, Any]]:
    """A LocalCluster (on 127.0.0.1, with echoloc's worker plugin) of 1 and one of 2 workers,
    started when first asked for, shared by the module."""
    stack: list[Any] = []
    started: dict[int, Any] = {}

    class Clients(dict):  # type: ignore[type-arg]
        def __missing__(self, workers: int) -> Any:
            context = open_client(workers=workers)
            client = context.__enter__()
            stack.append(context)
            self[workers] = client
            return client

    held = Clients(started)
    yield held
    for context in reversed(stack):
        context.__exit__(None, None, None)


def _scheduler(client: Any) -> str:
    address = client.scheduler.address
    assert address.startswith("tcp://127.0.0.1:"), address  # nothing listens beyond this machine
    return str(address)


def _run(capsys: pytest.CaptureFixture[str], *args: object) -> tuple[int, str, str]:
    """``echoloc ARGS`` in this process: exit code, stdout, stderr."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as info:
        commands.main([str(a) for a in args])
    out, err = capsys.readouterr()
    code = info.value.code
    assert isinstance(code, int)
    return code, out, err


def _copy(recordings: Path, folder: Path, names: tuple[str, ...] = FILES) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name in names:
        shutil.copy(recordings / name, folder / name)
    return folder


# --- the outputs are the serial commands' ---------------------------------------------------------


@pytest.mark.parametrize("workers", [1, 2])
def test_every_job_gives_the_serial_outputs_whatever_the_workers(
    workers: int,
    recordings: Path,
    serial: dict[tuple[str, str], Any],
    clients: dict[int, Any],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    scheduler = _scheduler(clients[workers])
    out_dir = tmp_path / "out"
    for job in ("echoes", "locate", "evaluate", "map"):
        code, out, err = _run(
            capsys, "batch", job, recordings, "-o", out_dir, "--scheduler", scheduler, "--chunk-frames", CHUNK
        )
        assert code == 0, out + err
        assert "3 done, 0 skipped" in out
        _assert_same(out_dir, job, serial)
    # Nothing else was left there: no temporaries, one output per file and job.
    assert sorted(p.name for p in out_dir.iterdir()) == sorted(
        output_path(Path(name), job, out_dir).name
        for name in FILES
        for job in ("echoes", "locate", "evaluate", "map")
    )


def test_options_reach_every_chunk(
    recordings: Path, clients: dict[int, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Classes, the automatic blind zone and a frame range: still the serial output."""
    folder = _copy(recordings, tmp_path, ("two.h5",))
    options = ("--classes", "--blind-zone", "auto", "--frames", "3:37")
    code, out, err = _run(
        capsys,
        "batch",
        "locate",
        folder,
        "--scheduler",
        _scheduler(clients[2]),
        "--chunk-frames",
        5,
        *options,
    )
    assert code == 0, out + err
    want = _serial("locate", folder / "two.h5", "--json", *options)
    assert b'"kind"' in want
    assert (folder / "two.locate.jsonl").read_bytes() == want


def test_back_projection_gets_every_transmitter_s_latest_frame(
    recordings: Path, clients: dict[int, Any], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Back-projection locates a frame with the latest frame of every other transmitter however
    old, and prepares itself from the receivers of the whole file: chunks of 3 frames (2 of
    their own and the other transmitter's latest) still give the serial output. (Its table
    takes seconds to build, serially and on the worker: a few frames, one worker.)"""
    folder = _copy(recordings, tmp_path, ("two.h5",))
    options = ("--method", "backprojection", "--frames", "1:9")
    code, out, err = _run(
        capsys,
        "batch",
        "locate",
        folder,
        "--scheduler",
        _scheduler(clients[1]),
        "--chunk-frames",
        3,
        *options,
    )
    assert code == 0, out + err
    assert (folder / "two.locate.jsonl").read_bytes() == _serial(
        "locate", folder / "two.h5", "--json", *options
    )


def test_a_compressed_archive_runs_in_order_in_one_task(
    recordings: Path, clients: dict[int, Any], tmp_path: Path
) -> None:
    """A deflated NPZ can only be read from its start: its chunks run one after the other, the
    frames the next chunk needs kept from the last; the output is still the serial one."""
    source = read_recording(recordings / "two.h5")
    plain = tmp_path / "plain.npz"
    write_recording(source, plain)
    packed = tmp_path / "packed.npz"
    with zipfile.ZipFile(plain) as archive, zipfile.ZipFile(packed, "w", zipfile.ZIP_DEFLATED) as out:
        for info in archive.infolist():
            out.writestr(info.filename, archive.read(info.filename))
    plain.unlink()
    kinds: list[str] = []
    job = BatchJob(job="locate", settings=ChainSettings(), chunk_frames=CHUNK)
    outcomes = run_batch(clients[2], job, [packed], on_result=kinds.append)
    assert [o.status for o in outcomes] == ["done"]
    assert kinds == ["plan", "chunk"]  # one task for all its chunks
    assert (tmp_path / "packed.locate.jsonl").read_bytes() == _serial("locate", packed, "--json")


# --- a bad file fails alone ------------------------------------------------------------------------


def test_a_bad_file_is_one_line_of_the_summary_and_exit_2(
    recordings: Path,
    serial: dict[tuple[str, str], Any],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    folder = _copy(recordings, tmp_path / "in", ("six.h5", "two.h5"))
    whole = (folder / "six.h5").read_bytes()
    (folder / "cut.h5").write_bytes(whole[: len(whole) // 2])  # a truncated HDF5 file
    (folder / "words.h5").write_text("not a recording\n")  # a text file named .h5
    monkeypatch.chdir(folder)
    # Through a local cluster of its own (--workers), as a user runs it.
    code, out, err = _run(capsys, "batch", "locate", ".", "--workers", 1, "--chunk-frames", CHUNK)
    assert code == 2
    *warned, last = err.strip().splitlines()
    assert last == "echoloc: error: 2 of 4 input(s) failed (see the summary)"
    (warned_line,) = warned  # said once, not once a chunk
    assert warned_line.startswith("echoloc: warning: six.h5: receiver 3 is degraded (noise sigma")
    for name in ("cut.h5", "words.h5"):
        rows = [line for line in out.splitlines() if name in line]
        assert len(rows) == 1, out
        assert "failed" in rows[0]
        assert not Path(name.replace(".h5", ".locate.jsonl")).exists()
    assert "not an HDF5 file" in out
    assert "batch locate (.locate.jsonl): 2 done, 0 skipped (complete already), 2 failed" in out
    _assert_same(folder, "locate", serial, ("six.h5", "two.h5"))
    assert not list(folder.glob(".*partial*"))


def test_inputs_folders_globs_and_clashes(recordings: Path, tmp_path: Path) -> None:
    folder = _copy(recordings, tmp_path / "a")
    (folder / "six.locate.jsonl").write_text("")
    (folder / "six.map.npz").write_bytes(b"")  # an output of map is no input
    (folder / ".six.locate.partial.jsonl").write_text("")
    found, unmatched = find_inputs(
        [folder, str(folder / "*.h5"), str(folder / "none*.h5"), folder / "gone.h5"]
    )
    assert found == [folder / "chirp.npz", folder / "six.h5", folder / "two.h5", folder / "gone.h5"]
    assert [o.detail for o in unmatched] == [f"{folder / 'none*.h5'}: matches no file"]
    other = _copy(recordings, tmp_path / "b", ("six.h5",))
    outcomes = batch._prepared_outputs(
        "locate", [folder / "six.h5", other / "six.h5"], tmp_path / "out", False
    )[1]
    assert outcomes[other / "six.h5"].status == "failed"
    assert "would be that of" in outcomes[other / "six.h5"].detail


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (("--cell-m", "5"), "--cell-m must be between 0.001 and 1 m, got 5"),
        (("--3d", "--height-m", "0.1"), "--height-m sets the floor plan's height"),
    ],
)
def test_batch_map_refuses_the_grid_options_map_refuses(
    recordings: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    options: tuple[str, ...],
    message: str,
) -> None:
    """The same one line and exit 2 as `echoloc map`, before any cluster starts."""
    folder = _copy(recordings, tmp_path, ("six.h5",))
    serial = _run(capsys, "map", folder / "six.h5", "-o", tmp_path / "six.png", *options)
    code, _, err = _run(capsys, "batch", "map", folder, "--workers", 1, *options)
    assert code == serial[0] == 2
    assert message in err
    assert err.strip() == serial[2].strip()
    assert len(err.strip().splitlines()) == 1
    assert not list(folder.glob("six.map*"))


# --- resume --------------------------------------------------------------------------------------


def test_a_second_run_redoes_only_what_is_missing_or_half_written(
    recordings: Path, serial: dict[tuple[str, str], Any], clients: dict[int, Any], tmp_path: Path
) -> None:
    folder = _copy(recordings, tmp_path)
    inputs = [folder / name for name in FILES]
    job = BatchJob(job="locate", settings=ChainSettings(), chunk_frames=CHUNK)
    client = clients[2]
    assert [o.status for o in run_batch(client, job, inputs)] == ["done"] * 3
    six, two, chirp = (output_path(path, "locate") for path in inputs)
    six.unlink()  # lost
    two.unlink()  # and a run killed while writing it left this:
    temporary_path(two).write_text('{"frame": 0, "time_s": 0.0, "obj')
    kept = chirp.stat()
    kinds: list[str] = []
    outcomes = run_batch(client, job, inputs, on_result=kinds.append)
    assert [(o.status, o.detail) for o in outcomes] == [
        ("done", ""),
        ("done", "a half-written output of an earlier run was removed"),
        ("skipped", "complete already"),
    ]
    assert kinds.count("plan") == 2  # the third file was not even opened
    assert not temporary_path(two).exists()
    after = chirp.stat()
    assert (after.st_ino, after.st_mtime_ns) == (kept.st_ino, kept.st_mtime_ns)
    _assert_same(folder, "locate", serial)
    kinds.clear()
    assert [o.status for o in run_batch(client, job, inputs, force=True, on_result=kinds.append)] == [
        "done"
    ] * 3
    assert kinds.count("plan") == 3


def test_a_failing_file_leaves_no_output_and_no_temporary(clients: dict[int, Any], tmp_path: Path) -> None:
    """A NaN sample late in a file, in a frame the channel check does not read: the file fails
    in its chunk, naming the sample as the serial reader does, and nothing of it stays."""
    n_frames = 100
    late = max(set(range(n_frames)) - set(assessed_frames(n_frames).tolist()))
    path = tmp_path / "nan.h5"
    write_recording(simulate(load_scene(preset_path("random-1m3-six")), n_frames), path)
    with h5py.File(path, "r+") as file:
        file["frames"][late, 2, 100] = np.nan
    job = BatchJob(job="locate", settings=ChainSettings(), chunk_frames=10)
    kinds: list[str] = []
    (outcome,) = run_batch(clients[2], job, [path], on_result=kinds.append)
    assert kinds.count("chunk") >= 1  # its plan went through; a chunk failed
    assert outcome.status == "failed"
    assert f"nan.h5: frames[{late // 10 * 10}:{late // 10 * 10 + 10}] has 1 non-finite" in outcome.detail
    assert f"[{late}, 2, 100]" in outcome.detail
    assert not output_path(path, "locate").exists()
    assert not temporary_path(output_path(path, "locate")).exists()


# --- a worker that dies --------------------------------------------------------------------------


def test_a_worker_killed_mid_batch_changes_nothing(
    recordings: Path, serial: dict[tuple[str, str], Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = _copy(recordings, tmp_path)
    commits: list[Path] = []
    commit = batch._commit

    def counted(temporary: Path, output: Path) -> None:
        commits.append(output)
        commit(temporary, output)

    monkeypatch.setattr(batch, "_commit", counted)
    killed: list[tuple[int, int]] = []
    with open_client(workers=2) as client:
        pids: dict[str, int] = client.run(os.getpid)

        def kill_a_busy_worker(kind: str) -> None:
            if kind != "chunk" or killed:
                return
            busy = [address for address, keys in client.processing().items() if keys]
            assert busy, "no task left running to kill"
            killed.append((pids[busy[0]], len(client.processing()[busy[0]])))
            os.kill(pids[busy[0]], signal.SIGKILL)

        job = BatchJob(job="locate", settings=ChainSettings(), chunk_frames=5)
        outcomes = run_batch(client, job, [folder / name for name in FILES], on_result=kill_a_busy_worker)
        after = client.run(os.getpid)
    assert killed
    assert killed[0][0] not in after.values()  # that process is gone (its nanny started another)
    assert [o.status for o in outcomes] == ["done"] * 3
    _assert_same(folder, "locate", serial)
    assert sorted(commits) == sorted(output_path(folder / name, "locate") for name in FILES)  # once each


# --- memory -----------------------------------------------------------------------------------------


def test_a_task_never_holds_more_than_its_chunk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """On an in-process cluster (so that the reads can be watched): every chunk a task runs
    holds at most --chunk-frames frames, context included, and they are the frames processed,
    read once (two.h5's chunks also run the frame before them). Beyond that, a file's plan
    holds the 64 frames the channel check assesses, and for envelope-peak (chirp.npz) the
    first frames its ring-down is measured on, as every echoloc command does; never more."""
    n_frames, chunk = 150, 16
    folder = tmp_path / "long"
    files = _write_recordings(folder, n_frames)
    held: list[tuple[str, int]] = []
    recording_of = batch._Rows.recording
    frames_at = RecordingParts.frames_at
    samples = RecordingParts._samples

    def watched_recording(self: Any, indices: Any, keep: Any = ()) -> Recording:
        made = recording_of(self, indices, keep)
        held.append(("chunk", made.n_frames))
        return made

    def watched_frames_at(self: Any, indices: Any) -> np.ndarray:
        stacked = frames_at(self, indices)
        held.append(("stacked", len(stacked)))
        return stacked

    def watched_samples(self: Any, name: str, start: int, stop: int) -> np.ndarray:
        read = samples(self, name, start, stop)
        held.append(("read", len(read)))
        return read

    monkeypatch.setattr(batch._Rows, "recording", watched_recording)
    monkeypatch.setattr(RecordingParts, "frames_at", watched_frames_at)
    monkeypatch.setattr(RecordingParts, "_samples", watched_samples)
    with (
        distributed.LocalCluster(
            n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        for job in ("locate", "map"):
            held.clear()
            spec = BatchJob(job=job, settings=ChainSettings(), chunk_frames=chunk)
            outcomes = run_batch(client, spec, files)
            assert [o.status for o in outcomes] == ["done"] * 3
            chunks = [n for kind, n in held if kind == "chunk"]
            assert max(chunks) <= chunk
            assert sum(chunks) == 3 * n_frames + (n_frames - 1) // (chunk - 1)
            assert sorted(n for kind, n in held if kind == "stacked" and n > chunk) == [ASSESS_FRAMES] * 3
            assert [n for kind, n in held if kind == "read" and n > chunk] == [
                min(n_frames, RING_DOWN_FRAMES)
            ]


# --- the partial reader ----------------------------------------------------------------------------


def test_the_partial_reader_reads_what_read_recording_reads(recordings: Path, tmp_path: Path) -> None:
    for name in FILES:
        whole = read_recording(recordings / name)
        with RecordingParts(recordings / name) as parts:
            assert parts.n_frames == whole.n_frames
            assert parts.random_access
            for start, stop in ((0, 7), (33, 40), (5, 6), (0, 40)):
                got = parts.frames(start, stop)
                assert got.dtype == whole.frames.dtype
                np.testing.assert_array_equal(got, whole.frames[start:stop])
            np.testing.assert_array_equal(parts.frames_at([0, 1, 2, 17, 39]), whole.frames[[0, 1, 2, 17, 39]])
            for field, values in parts.per_frame.items():
                np.testing.assert_array_equal(values, getattr(whole, field))
            for field in ("waveform", "transmitters_m", "receivers_m", "background", "receiver_gain"):
                np.testing.assert_array_equal(getattr(parts.header, field), getattr(whole, field))
            assert parts.header.n_frames == 0


def test_the_partial_reader_refuses_as_read_recording_does(tmp_path: Path) -> None:
    path = tmp_path / "inf.h5"
    write_recording(simulate(load_scene(preset_path("random-1m3-six")), 12), path)
    with h5py.File(path, "r+") as file:  # a file the writer would refuse
        file["frames"][9, 1, 5] = np.inf
    with RecordingParts(path) as parts:
        parts.frames(0, 8)  # the samples are checked as they are read
        with pytest.raises(RecordingError, match=r"inf\.h5: frames\[8:12\] has 1 non-finite .*\[9, 1, 5\]"):
            parts.frames(8, 12)
    with (
        pytest.warns(Warning, match="replaced 1 non-finite"),
        RecordingParts(path, repair_nonfinite=True) as parts,
    ):
        assert parts.frames(8, 12)[1, 1, 5] == 0
    (tmp_path / "text.h5").write_text("hello")
    with pytest.raises(RecordingError, match="not an HDF5 file"):
        RecordingParts(tmp_path / "text.h5")
    with pytest.raises(RecordingError, match="no such file"):
        RecordingParts(tmp_path / "gone.npz")


def _python(code: str, *args: str, timeout_s: float, **env: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
        env={**os.environ, **env},
    )


def test_the_partial_reader_abandons_a_stalling_hdf5_file(tmp_path: Path) -> None:
    """A file that sends libhdf5 into an endless loop (tests/io/test_hostile_files.py's: one
    byte of its global heap's size changed) is refused by the reader process's watchdog, as
    read_recording refuses it, and that process does not stay behind."""
    rng = np.random.default_rng(0)
    small = Recording(
        sample_rate_hz=200e3,
        transmitters_m=np.zeros((1, 3)),
        receivers_m=np.array([[0.01, 0.0, 0.0], [-0.01, 0.0, 0.0], [0.0, 0.01, 0.0]]),
        frames=rng.standard_normal((4, 3, 256)),
        waveform=np.sin(np.arange(40) * 0.5),
        frame_times_s=np.arange(4) * 0.05,
    )
    path = write_recording(small, tmp_path / "hang.h5")
    content = bytearray(path.read_bytes())
    content[content.index(b"GCOL") + 8] = 0x10
    path.write_bytes(bytes(content))
    direct = "import sys, h5py\nwith h5py.File(sys.argv[1]) as f:\n    [f.attrs[n] for n in f.attrs]\n"
    try:
        _python(direct, str(path), timeout_s=3.0)
    except subprocess.TimeoutExpired:
        pass
    else:
        pytest.skip(f"h5py {h5py.version.hdf5_version}: a direct read of the corrupted file does not stall")
    code = (
        "import sys, time\n"
        "from echoloc.io.recording import RecordingError, RecordingParts\n"
        "start = time.monotonic()\n"
        "try:\n"
        "    RecordingParts(sys.argv[1]).frames(0, 1)\n"
        "except RecordingError as error:\n"
        "    print(f'{time.monotonic() - start:.2f}', error)\n"
    )
    done = _python(code, str(path), timeout_s=60, ECHOLOC_HDF5_STALL_S="1")
    seconds, message = done.stdout.strip().split(" ", 1)
    assert 1 <= float(seconds) < 10
    assert message == (
        f"{path}: cannot read as HDF5: libhdf5 made no progress for 1 s reading it "
        "(a corrupt file? on a slow disk, set ECHOLOC_HDF5_STALL_S to wait longer); abandoned"
    )
    leftovers = [
        entry.name
        for entry in Path("/proc").iterdir()
        if entry.name.isdigit()
        and b"_serve_hdf5" in _cmdline(entry)
        and str(path).encode() in _cmdline(entry)
    ]
    assert leftovers == []


def _cmdline(entry: Path) -> bytes:
    try:
        return (entry / "cmdline").read_bytes()
    except OSError:
        return b""
