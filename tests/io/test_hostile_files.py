"""Hostile inputs (issue 31): readers check before they read, nothing hangs, every bad
value is one EchoLocError (exit 2) naming the file and the key, nothing is left behind."""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from echoloc.errors import EchoLocError, RecordingError, SceneError
from echoloc.io import recording as recording_module
from echoloc.io.recording import (
    FrameBatch,
    Recording,
    as_header,
    read_recording,
    remove_stale_temporaries,
    write_recording,
    write_recording_stream,
)
from echoloc.localise.calibrate import read_calibration
from echoloc.sim.scenefile import load_scene, scene_from_dict
from interactive import with_sigint
from repo_paths import REPO

SCENE = REPO / "src" / "echoloc" / "scenes" / "report-three-balls.toml"


def small_recording() -> Recording:
    rng = np.random.default_rng(0)
    return Recording(
        sample_rate_hz=200e3,
        transmitters_m=np.zeros((1, 3)),
        receivers_m=np.array([[0.01, 0.0, 0.0], [-0.01, 0.0, 0.0], [0.0, 0.01, 0.0]]),
        frames=rng.standard_normal((4, 3, 256)),
        waveform=np.sin(np.arange(40) * 0.5),
        frame_times_s=np.arange(4) * 0.05,
    )


def hanging_hdf5(path: Path) -> Path:
    """A valid recording with one byte changed that makes libhdf5 2.0 loop for ever.

    The low byte of the global heap collection's size (8 bytes after ``GCOL``, where the
    variable-length string attributes live) set to 0x10: found by flipping single bytes.
    """
    write_recording(small_recording(), path)
    content = bytearray(path.read_bytes())
    heap = content.index(b"GCOL")
    content[heap + 8] = 0x10
    path.write_bytes(bytes(content))
    return path


def run_python(
    code: str, *args: str, timeout_s: float = 30.0, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", code, *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        check=False,
        env=None if env is None else {**os.environ, **env},
    )


DIRECT_READ = (
    "import sys, h5py\n"
    "with h5py.File(sys.argv[1], 'r') as f:\n"
    "    [f.attrs[name] for name in f.attrs]\n"
    "    [f[name][()] for name in f]\n"
)


@pytest.fixture(scope="module")
def stalling_hdf5(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """:func:`hanging_hdf5`'s file, when a plain h5py read of it really stalls on this libhdf5.

    Whether the corruption loops depends on the libhdf5 release: where a direct read
    ends (or fails) within 3 s, there is no hang for echoloc to survive, and the tests
    that need one are skipped.
    """
    path = hanging_hdf5(tmp_path_factory.mktemp("hang") / "hang.h5")
    try:
        run_python(DIRECT_READ, str(path), timeout_s=3.0)
    except subprocess.TimeoutExpired:
        return path
    pytest.skip(f"h5py {h5py.version.hdf5_version}: a direct read of the corrupted file does not stall")


def children_reading(path: Path) -> list[int]:
    """Pids of the processes whose command line names ``path`` (the HDF5 reader children)."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        if b"_hdf5_child" in cmdline and str(path).encode() in cmdline:
            pids.append(int(entry.name))
    return pids


# ----------------------------------------------------------------------------- finding 2: the hang


def test_hanging_hdf5_is_refused_by_the_stall_watchdog(stalling_hdf5: Path) -> None:
    """Refused after the stall timeout that ECHOLOC_HDF5_STALL_S sets, by the watchdog's words."""
    path = stalling_hdf5
    code = (
        "import sys, time\n"
        "from echoloc.io import recording\n"
        "start = time.monotonic()\n"
        "try:\n"
        "    recording.read_recording(sys.argv[1])\n"
        "except recording.RecordingError as error:\n"
        "    print(f'{time.monotonic() - start:.2f}', error)\n"
    )
    done = run_python(code, str(path), timeout_s=30, env={"ECHOLOC_HDF5_STALL_S": "1"})
    seconds, message = done.stdout.strip().split(" ", 1)
    assert 1 <= float(seconds) < 5
    assert message == (
        f"{path}: cannot read as HDF5: libhdf5 made no progress for 1 s reading it "
        "(a corrupt file? on a slow disk, set ECHOLOC_HDF5_STALL_S to wait longer); abandoned"
    )
    assert children_reading(path) == []


@pytest.mark.parametrize("value", ["abc", "0", "-1", "nan", "inf", "1e9"])
def test_a_bad_stall_timeout_variable_is_refused_naming_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, value: str
) -> None:
    path = write_recording(small_recording(), tmp_path / "rec.h5")
    monkeypatch.setenv("ECHOLOC_HDF5_STALL_S", value)
    with pytest.raises(
        RecordingError, match=rf"^ECHOLOC_HDF5_STALL_S='{value}': expected a number of seconds"
    ):
        read_recording(path)


def test_the_stall_timeout_variable_lets_a_slow_read_through(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A child slower than the default timeout still delivers when the variable allows it."""
    rec = small_recording()
    path = write_recording(rec, tmp_path / "rec.h5")
    original = recording_module._ChildPipe.message
    waited: list[float] = []

    def slow(self: Any, timeout_s: float, into: Any = None) -> Any:
        waited.append(timeout_s)
        return original(self, timeout_s, into)

    monkeypatch.setattr(recording_module._ChildPipe, "message", slow)
    monkeypatch.setenv("ECHOLOC_HDF5_STALL_S", "42.5")
    np.testing.assert_array_equal(read_recording(path).frames, rec.frames)
    assert len(waited) > 1
    assert set(waited[1:]) == {42.5}  # every wait after the start-up one


@pytest.mark.skipif(sys.platform != "linux", reason="signals and /proc")
@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT])
def test_locate_on_a_hanging_file_honours_signals(stalling_hdf5: Path, signum: int) -> None:
    path = stalling_hdf5
    process = subprocess.Popen(
        with_sigint([sys.executable, "-m", "echoloc", "locate", str(path)]),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 20
        while not children_reading(path) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert children_reading(path), "the reader child never started"
        time.sleep(0.3)  # inside libhdf5's loop by now
        sent = time.monotonic()
        process.send_signal(signum)
        process.wait(timeout=3)  # before the 5 s stall deadline: the signal ended it
        assert time.monotonic() - sent < 3
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
    assert process.returncode != 0
    deadline = time.monotonic() + 3
    while children_reading(path) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert children_reading(path) == []  # the child went with it


@pytest.mark.skipif(sys.platform != "linux", reason="prctl and /proc")
def test_reader_child_dies_with_a_killed_parent(stalling_hdf5: Path) -> None:
    path = stalling_hdf5
    process = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sys; from echoloc.io.recording import read_recording; read_recording(sys.argv[1])",
            str(path),
        ],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    deadline = time.monotonic() + 20
    while not children_reading(path) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert children_reading(path)
    process.kill()
    process.wait()
    deadline = time.monotonic() + 3
    while children_reading(path) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert children_reading(path) == []


MALICIOUS_MODULES = ("h5py", "numpy", "json", "struct", "lazy_loader", "echoloc")


def test_the_reader_child_imports_nothing_from_the_current_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A ``h5py.py`` (or numpy.py, json.py, ...) beside the recording must never run."""
    rec = small_recording()
    folder = tmp_path / "work"
    folder.mkdir()
    write_recording(rec, folder / "r.h5")
    for name in MALICIOUS_MODULES:
        marker = folder / f"ran-{name}"
        (folder / f"{name}.py").write_text(f"open({str(marker)!r}, 'w').close()\n")
    monkeypatch.chdir(folder)
    back = read_recording("r.h5")
    np.testing.assert_array_equal(back.frames, rec.frames)
    assert sorted(p.name for p in folder.glob("ran-*")) == []


def test_the_reader_child_path_leaves_out_the_current_directory(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(sys, "path", ["", ".", str(tmp_path), "relative/dir", *sys.path])
    paths = recording_module._child_sys_path()
    assert str(tmp_path) not in paths
    assert "" not in paths
    assert str(tmp_path / "relative" / "dir") in paths  # made absolute, not left relative
    assert str(Path(recording_module.__file__).resolve().parents[2]) in paths  # echoloc's own root
    stdlib = os.path.dirname(os.__file__)
    assert paths.index(stdlib) < paths.index(os.path.dirname(os.path.dirname(np.__file__)))


def test_valid_hdf5_reads_back_through_the_child(tmp_path: Path) -> None:
    rec = small_recording()
    path = write_recording(rec, tmp_path / "rec.h5")
    back = read_recording(path)
    np.testing.assert_array_equal(back.frames, rec.frames)
    np.testing.assert_array_equal(back.frame_times_s, rec.frame_times_s)  # type: ignore[arg-type]


# ----------------------------------------------------------------------------- finding 3: sizes first


def test_hdf5_declaring_more_than_it_stores_is_refused_before_reading(tmp_path: Path) -> None:
    rec = small_recording()
    path = write_recording(rec, tmp_path / "rec.h5")
    with h5py.File(path, "a") as f:
        frames = f["frames"][()]
        del f["frames"], f["frame_times"]
        dataset = f.create_dataset("frames", data=frames, maxshape=(None, 3, 256), chunks=(1, 3, 256))
        dataset.resize(10_000_000, axis=0)  # 61 GB declared as float64, 24 kB stored
    start = time.monotonic()
    with pytest.raises(RecordingError, match=r"frames declares shape \(10000000, 3, 256\).*stores only"):
        read_recording(path)
    assert time.monotonic() - start < 5


def test_npz_member_declaring_more_than_it_holds_is_refused_before_reading(tmp_path: Path) -> None:
    rec = small_recording()
    path = write_recording(rec, tmp_path / "rec.npz")
    forged = tmp_path / "forged.npz"
    with zipfile.ZipFile(path) as source, zipfile.ZipFile(forged, "w") as target:
        for name in source.namelist():
            if name == "waveform.npy":
                with target.open(name, "w") as member:
                    header = {"descr": "<f8", "fortran_order": False, "shape": (10_000_000,)}
                    np.lib.format.write_array_header_1_0(member, header)
                    member.write(b"\0" * 32)
            else:
                target.writestr(name, source.read(name))
    with pytest.raises(RecordingError, match=r"waveform declares shape \(10000000,\).*stores only"):
        read_recording(forged)


@pytest.mark.parametrize("ext", [".h5", ".npz"])
def test_declared_size_beyond_the_limit_is_refused(tmp_path: Path, monkeypatch: Any, ext: str) -> None:
    path = write_recording(small_recording(), tmp_path / f"rec{ext}")
    monkeypatch.setattr(recording_module, "MAX_RECORDING_BYTES", 1000)
    with pytest.raises(RecordingError, match="GiB a recording may hold"):
        read_recording(path)


def test_declared_shapes_are_checked_against_each_other_before_reading(tmp_path: Path) -> None:
    rec = small_recording()
    path = write_recording(rec, tmp_path / "rec.npz")
    forged = tmp_path / "forged.npz"
    with zipfile.ZipFile(path) as source, zipfile.ZipFile(forged, "w") as target:
        for name in source.namelist():
            target.writestr(name, source.read(name))
        with target.open("receiver_gain.npy", "w") as member:  # (n_samples,) expected
            header = {"descr": "<f8", "fortran_order": False, "shape": (10_000_000,)}
            np.lib.format.write_array_header_1_0(member, header)
    with pytest.raises(RecordingError, match=r"receiver_gain has shape \(10000000,\), expected \(256,\)"):
        read_recording(forged)


# ----------------------------------------------------------------------------- findings 7, 8, 11: values


def scene_dict() -> dict[str, Any]:
    import tomllib

    return tomllib.loads(SCENE.read_text())


def with_value(section: str | None, key: str, value: object) -> dict[str, Any]:
    data = copy.deepcopy(scene_dict())
    if section is None:
        data[key] = value
    else:
        data.setdefault(section, {})[key] = value
    return data


ISSUE_VALUES = [
    ("acquisition", "sample_rate_hz", 5e-324, "sample_rate_hz"),
    ("acquisition", "sample_rate_hz", 1e300, "sample_rate_hz"),
    ("acquisition", "n_samples", 2**63 - 1, "n_samples"),
    ("pulse", "carrier_hz", 5e-324, "pulse"),
    ("pulse", "cycles_per_bit", 1_000_000, "samples"),
    ("noise", "snr_db", -(2**63), "snr_db"),
    ("acquisition", "frame_rate_hz", 5e-324, "frame_rate_hz"),
]


@pytest.mark.parametrize(("section", "key", "value", "named"), ISSUE_VALUES)
def test_issue_values_are_scene_errors(section: str, key: str, value: object, named: str) -> None:
    start = time.monotonic()
    with pytest.raises(SceneError, match=named) as info:
        scene_from_dict(with_value(section, key, value), "hostile.toml")
    assert str(info.value).startswith("hostile.toml: ")
    assert time.monotonic() - start < 2


def test_huge_geometry_and_counts_are_scene_errors() -> None:
    sphere = copy.deepcopy(scene_dict())
    sphere["reflectors"].append({"kind": "sphere", "centre_m": [0.0, 0.0, 2.0], "radius_m": 1e30})
    with pytest.raises(SceneError, match=r"reflectors\[\d+\]\.radius_m"):
        scene_from_dict(sphere, "s.toml")
    many = with_value(None, "random_reflectors", {"count": [1, 2**63 - 1]})
    with pytest.raises(SceneError, match=r"random_reflectors\.count"):
        scene_from_dict(many, "s.toml")
    envelope = copy.deepcopy(scene_dict())
    envelope.setdefault("receiver", {}).update(signal_kind="envelope", baseband_filter_s=1e300)
    with pytest.raises(SceneError, match="baseband_filter_s"):
        scene_from_dict(envelope, "s.toml")


NUMERIC_KEYS = [
    ("acquisition", "sample_rate_hz"),
    ("acquisition", "n_samples"),
    ("acquisition", "frame_rate_hz"),
    ("pulse", "carrier_hz"),
    ("pulse", "cycles_per_bit"),
    ("noise", "snr_db"),
    ("noise", "path_jitter_m"),
    ("air", "temperature_c"),
    ("receiver", "adc_rate_hz"),
    ("ring_down", "decay_s"),
]
HOSTILE_NUMBERS = st.one_of(
    st.sampled_from([5e-324, -5e-324, 1e300, -1e300, 2**63 - 1, -(2**63), 0, 1_000_000, 1e-300]),
    st.floats(allow_nan=False, allow_infinity=False),
    st.integers(min_value=-(2**64), max_value=2**64),
)


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(where=st.sampled_from(NUMERIC_KEYS), value=HOSTILE_NUMBERS)
def test_any_number_makes_a_scene_or_a_scene_error(where: tuple[str, str], value: float) -> None:
    section, key = where
    message = "h.toml: (a valid scene)"
    try:
        scene_from_dict(with_value(section, key, value), "h.toml")
    except SceneError as error:  # any other exception fails the test
        message = str(error)
    assert message.startswith("h.toml: ")
    assert "\n" not in message


@pytest.mark.parametrize(
    ("content", "named"),
    [
        ("x = " + "[" * 3000 + "]" * 3000, "nested too deeply"),
        ("seed = " + "9" * 5000, "digits"),
    ],
)
def test_unparseable_toml_is_a_scene_error(tmp_path: Path, content: str, named: str) -> None:
    path = tmp_path / "hostile.toml"
    path.write_text(content)
    with pytest.raises(SceneError, match=named):
        load_scene(path)


def calibration_text(speed: str) -> str:
    return (
        '{"format": "echoloc-calibration", "version": 1, '
        f'"speed_of_sound_m_s": {speed}, "receiver_delays_s": [0, 0, 0]}}'
    )


@pytest.mark.parametrize(
    ("content", "named"),
    [
        (calibration_text("9" * 5000), "not a calibration file"),
        (calibration_text("1" + "0" * 400), "speed_of_sound_m_s"),
        (calibration_text("true"), "speed_of_sound_m_s must be a positive number, got True"),
        ("[" * 3000 + "]" * 3000, "nested too deeply"),
        (calibration_text("343").replace('"version": 1', '"version": true'), "version"),
        (calibration_text("343").replace("}", ', "path_sigma_m": 1e300}'), "path_sigma_m must be"),
    ],
    ids=["5000 digits", "10**400", "true", "nested 3000 deep", "version true", "path sigma 1e300"],
)
def test_hostile_calibration_is_an_echoloc_error(tmp_path: Path, content: str, named: str) -> None:
    path = tmp_path / "cal.json"
    path.write_text(content)
    with pytest.raises(EchoLocError, match=named) as info:
        read_calibration(path)
    assert str(info.value).startswith(f"{path}: ")


def test_positions_beyond_reach_are_the_recording_s_error(tmp_path: Path) -> None:
    """Receivers at 1e300 m (a hostile session found them) overflowed the geometry's
    squares downstream; a recording or session refuses coordinates beyond 10 km."""
    from echoloc.io.recording import validate_header

    header = as_header(small_recording())
    far = np.array(header.receivers_m, dtype=float)
    far[0, 1] = -1e300
    with pytest.raises(RecordingError, match=r"receivers.* beyond 10000 m"):
        validate_header(dataclasses.replace(header, receivers_m=far))


def test_echoes_used_true_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "cal.json"
    record = json.loads(calibration_text("343"))
    record["echoes_used"] = True
    path.write_text(json.dumps(record))
    with pytest.raises(EchoLocError, match="echoes_used"):
        read_calibration(path)


@pytest.mark.skipif(not Path("/dev/zero").exists(), reason="needs /dev/zero")
def test_devices_fifos_and_oversize_files_are_not_read(tmp_path: Path, monkeypatch: Any) -> None:
    fifo = tmp_path / "fifo.toml"
    os.mkfifo(fifo)  # opening it for reading would block without O_NONBLOCK
    for path in (Path("/dev/zero"), fifo):
        with pytest.raises(SceneError, match="not a regular file"):
            load_scene(path)
        with pytest.raises(EchoLocError, match="not a regular file"):
            read_calibration(path)
    big = tmp_path / "big.json"
    big.write_bytes(b" " * (5 << 20))
    with pytest.raises(EchoLocError, match="more than the"):
        read_calibration(big)
    with pytest.raises(SceneError, match="more than the"):
        load_scene(big)


def test_cli_refuses_device_inputs_with_exit_2(tmp_path: Path, capsys: Any) -> None:
    from echoloc.cli.commands import main

    with pytest.raises(SystemExit) as info:
        main(["simulate", "/dev/zero", "-o", str(tmp_path / "out.h5")])
    assert info.value.code == 2
    assert "/dev/zero: not a regular file" in capsys.readouterr().err
    recording = write_recording(small_recording(), tmp_path / "rec.h5")
    with pytest.raises(SystemExit) as info:
        main(["locate", str(recording), "--calibration", "/dev/zero"])
    assert info.value.code == 2


# ----------------------------------------------------------------------------- finding 9: temporaries


def dead_pid() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


def age(path: Path, seconds: float) -> Path:
    """Make ``path`` look last modified ``seconds`` ago."""
    then = time.time() - seconds
    os.utime(path, (then, then))
    return path


def test_stale_temporaries_of_dead_writers_are_removed(tmp_path: Path) -> None:
    tag = recording_module._HOST_TAG
    other_tag = "0" * 8 if tag != "0" * 8 else "1" * 8
    gone = dead_pid()
    names = {
        "stale": f".rec.h5.{tag}-{gone}-0123456789ab.tmp",
        "live": f".rec.h5.{tag}-{os.getpid()}-0123456789ab.tmp",
        "elsewhere": f".rec.h5.{other_tag}-{gone}-0123456789ab.tmp",
        "unrelated": ".notes.tmp",
        # A writer in another pid namespace (a container with the same hostname) looks
        # dead here: its file is kept while it is recent.
        "recent": f".new.h5.{tag}-{gone}-0123456789ab.tmp",
        # Older naming, without host and pid: only a day without change makes it stale.
        "old style, 2 days": ".rec.npz.0123456789ab.tmp",
        "old style, 1 hour": ".rec.h5.0123456789ac.tmp",
        "old style, not a recording": ".notes.txt.0123456789ab.tmp",
    }
    paths = {key: tmp_path / name for key, name in names.items()}
    for key, path in paths.items():
        path.write_bytes(b"x")
        if key != "recent":
            age(path, 3600 if key == "old style, 1 hour" else 2 * 86400)
    age(paths["recent"], recording_module.STALE_TEMPORARY_AGE_S - 60)
    write_recording(small_recording(), tmp_path / "other.h5")
    left = {key for key, path in paths.items() if path.exists()}
    assert left == set(names) - {"stale", "old style, 2 days"}
    assert remove_stale_temporaries(tmp_path) == []
    age(paths["recent"], recording_module.STALE_TEMPORARY_AGE_S + 60)
    assert remove_stale_temporaries(tmp_path) == [paths["recent"]]


def test_a_killed_writer_leaves_a_temporary_the_next_write_removes(tmp_path: Path) -> None:
    target = tmp_path / "big.h5"
    script = (
        "import sys, time\n"
        "import numpy as np\n"
        "from echoloc.io.recording import FrameBatch, Recording, as_header, write_recording_stream\n"
        "rec = Recording(sample_rate_hz=200e3, transmitters_m=np.zeros((1, 3)),\n"
        "    receivers_m=np.eye(3), frames=np.zeros((1, 3, 64)), waveform=np.ones(8))\n"
        "def batches():\n"
        "    yield FrameBatch(frames=np.ones((4, 3, 64)))\n"
        "    print('written', flush=True)\n"
        "    time.sleep(60)\n"
        "    yield FrameBatch(frames=np.ones((4, 3, 64)))\n"
        "write_recording_stream(as_header(rec), batches(), sys.argv[1])\n"
    )
    process = subprocess.Popen([sys.executable, "-c", script, str(target)], stdout=subprocess.PIPE, text=True)
    assert process.stdout is not None
    assert process.stdout.readline().strip() == "written"
    process.kill()  # SIGKILL: no clean-up runs
    process.wait()
    process.stdout.close()
    left = list(tmp_path.glob(".big.h5.*.tmp"))
    assert len(left) == 1
    # The next write into the same folder removes it, once it has stopped changing for a while.
    age(left[0], recording_module.STALE_TEMPORARY_AGE_S + 1)
    rec = small_recording()
    write_recording_stream(as_header(rec), [FrameBatch(frames=rec.frames)], tmp_path / "next.h5")
    assert list(tmp_path.glob("*.tmp")) == []
    assert not target.exists()


@pytest.mark.parametrize("ext", [".h5", ".npz"])
@pytest.mark.parametrize("rate", [5e-324, 1e300, 0.5])
def test_recording_sample_rate_out_of_range_is_refused(tmp_path: Path, ext: str, rate: float) -> None:
    """5e-324 Hz passed the reader and divided by zero in `locate` (exit 1)."""
    from raw_files import write_raw

    rec = small_recording()
    attrs = {"format": "echoloc-recording", "version": 1, "sample_rate_hz": rate}
    data = {"transmitters": rec.transmitters_m, "receivers": rec.receivers_m, "frames": rec.frames}
    data["waveform"] = rec.waveform
    path = write_raw(tmp_path / f"rec{ext}", attrs, data)
    with pytest.raises(RecordingError, match=r"sample_rate_hz must lie in 1\.\.1e\+09 Hz") as info:
        read_recording(path)
    assert str(info.value).startswith(f"{path}: ")


# ----------------------------------------------------------------------------- finding 8: every text input


def _head_text() -> str:
    return (
        'sample_rate_hz = 200000\nsignal_kind = "envelope"\n'
        "transmitters = [[0, 0, 0]]\nreceivers = [[0, 0, 0]]\n"
    )


def _template_file(path: Path) -> Path:
    from echoloc.tof.templates import Template, write_template

    return write_template(Template(np.sin(np.arange(400) / 3.0), 200e3, 1e-5, "t"), path)


def _user_inputs() -> dict[str, tuple[Any, str, Any, str]]:
    """Each reader of a user-given file: (read, suffix, write valid content, limit's module:name)."""
    from echoloc.io import importers

    return {
        "sensor head": (
            importers.read_head,
            ".toml",
            lambda p: p.write_text(_head_text()),
            "io.importers:MAX_HEAD_BYTES",
        ),
        "samples table": (
            importers.read_table,
            ".csv",
            lambda p: p.write_text("1,2\n" * 40),
            "io.importers:MAX_TABLE_BYTES",
        ),
        "SPiEL frame": (
            lambda p: importers._spiel_frame(p, 40, None),
            ".csv",
            lambda p: p.write_text("1 2\n" * 40),
            "io.importers:MAX_SPIEL_FILE_BYTES",
        ),
        "samples .npy": (
            importers._load_npy,
            ".npy",
            lambda p: np.save(p, np.zeros(40)),
            "io.importers:MAX_RECORDING_BYTES",
        ),
        "trajectory": (
            _read_trajectory,
            ".txt",
            lambda p: p.write_text("".join(f"{t} 0 0 0 0 0 0 1\n" for t in range(10))),
            "maps.mapping:MAX_TRAJECTORY_BYTES",
        ),
        "template": (_read_template, ".npz", _template_file, "tof.templates:MAX_TEMPLATE_BYTES"),
    }


def _read_trajectory(path: Path) -> object:
    from echoloc.maps.mapping import read_trajectory

    return read_trajectory(path)


def _read_template(path: Path) -> object:
    from echoloc.tof.templates import read_template

    return read_template(path)


INPUTS = ["sensor head", "samples table", "SPiEL frame", "samples .npy", "trajectory", "template"]


@pytest.mark.skipif(not Path("/dev/null").exists(), reason="needs /dev/null")
@pytest.mark.parametrize("name", INPUTS)
def test_every_reader_refuses_a_device(tmp_path: Path, name: str) -> None:
    """A device is refused before it is read (``/dev/zero`` would grow memory without end)."""
    read, suffix, _, _ = _user_inputs()[name]
    path = tmp_path / f"input{suffix}"
    path.symlink_to("/dev/null")  # a device behind a name with the right extension
    with pytest.raises(EchoLocError, match="not a regular file") as info:
        read(path)
    assert str(info.value).startswith(f"{path}: ")


@pytest.mark.parametrize("name", INPUTS)
def test_every_reader_refuses_a_file_past_its_size_limit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, name: str
) -> None:
    import importlib

    read, suffix, write, limit = _user_inputs()[name]
    path = tmp_path / f"input{suffix}"
    write(path)
    read(path)  # valid under the real limit
    module, constant = limit.split(":")
    monkeypatch.setattr(importlib.import_module(f"echoloc.{module}"), constant, path.stat().st_size - 1)
    with pytest.raises(EchoLocError, match=f"of {path.stat().st_size} bytes, more than the") as info:
        read(path)
    assert str(info.value).startswith(f"{path}: ")


def test_npy_declaring_more_than_it_holds_is_refused_before_reading(tmp_path: Path) -> None:
    from echoloc.io.importers import _load_npy

    path = tmp_path / "samples.npy"
    with open(path, "wb") as fh:
        np.lib.format.write_array_header_1_0(
            fh, {"descr": "<f8", "fortran_order": False, "shape": (1_000_000_000_000,)}
        )
        fh.write(b"\0" * 32)
    with pytest.raises(EchoLocError, match=r"declares 8000000000000 bytes of data but holds 32"):
        _load_npy(path)


def test_template_unpacking_past_its_limit_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from echoloc.tof import templates

    path = tmp_path / "bomb.npz"
    np.savez_compressed(
        path, format="echoloc-template", version=1, samples=np.zeros(4000), sample_rate_hz=2e5, arrival_s=0.0
    )
    monkeypatch.setattr(templates, "MAX_TEMPLATE_BYTES", 10_000)
    assert path.stat().st_size < 10_000
    with pytest.raises(RecordingError, match=r"unpacks to \d+ bytes, more than the 10000"):
        templates.read_template(path)


def test_deeply_nested_sensor_head_is_an_echoloc_error(tmp_path: Path) -> None:
    from echoloc.io.importers import read_head

    path = tmp_path / "head.toml"
    path.write_text("x = " + "[" * 3000 + "]" * 3000)
    with pytest.raises(EchoLocError, match="nested too deeply"):
        read_head(path)


def test_an_npy_header_that_numpy_cannot_tokenize_is_the_file_s_error(tmp_path: Path) -> None:
    """A copied block left a member's header dict unclosed: numpy's parser raised
    tokenize.TokenError ('EOF in multi-line statement'), an internal error (fuzz run)."""
    good = write_recording(small_recording(), tmp_path / "good.npz")
    text = b"{'descr': '<f8', 'fortran_order': False, 'shape': (3, "
    header = text + b" " * (64 - 10 - len(text) - 1) + b"\n"
    broken_member = b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + bytes(24)
    bad = tmp_path / "bad.npz"
    with zipfile.ZipFile(good) as source, zipfile.ZipFile(bad, "w") as target:
        for name in source.namelist():
            target.writestr(name, broken_member if name == "frames.npy" else source.read(name))
    with pytest.raises(RecordingError, match=r"bad\.npz.*frames\.npy has no readable \.npy header"):
        read_recording(bad)
