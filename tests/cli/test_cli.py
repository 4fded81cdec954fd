"""End-to-end tests of the ``echoloc`` command line against docs/FORMATS.md.

Most cases run in-process through :func:`echoloc.cli.commands.main` (which always ends with
``sys.exit``) and capture stdout/stderr with ``capsys``; a few run the installed
console script as a real subprocess, to prove what a user's shell sees: the exit
code, a clean stdout and no traceback on stderr.

docs/FORMATS.md rules checked here: the recording file (readers reject with exit 2), the
JSON Lines of ``echoes --json`` and ``locate --json``, and the exit codes (0 success,
2 bad input or usage with one line on stderr naming the file and the problem, no
traceback).
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
import shutil
import subprocess
import sys
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import pytest

from echoloc.cli import app, processing
from echoloc.cli import commands as cli
from echoloc.io.recording import Recording, read_recording, write_recording
from echoloc.sim.scene import default_scene
from echoloc.sim.simulation import path_lengths_m, simulate
from raw_files import write_raw
from repo_paths import REPO

SCENES = REPO / "src" / "echoloc" / "scenes"
ECHOLOC = Path(sys.executable).parent / "echoloc"
COMMANDS = ("demo", "simulate", "echoes", "locate", "evaluate")
N_FRAMES = 2

ECHOES_FRAME_KEYS = {"frame", "time_s", "channels"}
CHANNEL_KEYS = {"receiver", "echoes"}
ECHO_KEYS = {"tof_s", "path_m", "amplitude", "snr_db"}
LOCATE_FRAME_KEYS = {"frame", "time_s", "objects"}
OBJECT_KEYS = {"position_m", "std_m", "receivers", "score"}
# Optional fields echoloc adds (docs/FORMATS.md allows optional additions; README documents them).
OPTIONAL_OBJECT_KEYS = {"channels", "shared_echoes"}
EVALUATE_KEYS = {
    "estimator",
    "frames",
    "truth_objects",
    "located_objects",
    "matched",
    "recall",
    "false_objects",
    "false_rate",
    "rmse_m",
    "bias_m",
    "mean_reported_std_m",
    "match_radius_m",
}


# ----------------------------------------------------------------------------- helpers


@dataclasses.dataclass(frozen=True)
class Result:
    """What a run of the command line left behind."""

    code: int
    out: str
    err: str

    @property
    def err_lines(self) -> list[str]:
        return self.err.splitlines()


def run(capsys: pytest.CaptureFixture[str], *args: object) -> Result:
    """Run ``echoloc ARGS`` in-process; main() always ends with SystemExit."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as info:
        cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    code = info.value.code
    assert isinstance(code, int), f"exit code {code!r} is not an int"
    return Result(code, out, err)


def _clean_env() -> dict[str, str]:
    """The environment of a user's pipe: no forced terminal width or colour."""
    env = dict(os.environ)
    for name in ("COLUMNS", "LINES", "FORCE_COLOR", "TTY_COMPATIBLE", "TTY_INTERACTIVE"):
        env.pop(name, None)
    return env


def run_process(*args: object, cwd: Path) -> Result:
    """Run the installed ``echoloc`` console script as a real subprocess."""
    completed = subprocess.run(
        [str(ECHOLOC), *(str(a) for a in args)],
        capture_output=True,
        text=True,
        cwd=cwd,
        env=_clean_env(),
        timeout=60,
        check=False,
    )
    return Result(completed.returncode, completed.stdout, completed.stderr)


def _reject_constant(name: str) -> Any:
    raise ValueError(f"{name} is not valid JSON")


def json_lines(text: str) -> list[dict[str, Any]]:
    """Parse JSON Lines strictly: every line one JSON object, no NaN or Infinity."""
    records = []
    for line in text.splitlines():
        record = json.loads(line, parse_constant=_reject_constant)
        assert isinstance(record, dict), line
        records.append(record)
    return records


def assert_bad_input(result: Result, *names: str) -> None:
    """Exit 2, exactly one line on stderr naming ``names``, nothing on stdout, no traceback."""
    assert result.code == 2, result
    assert "Traceback" not in result.out + result.err
    assert result.out == ""
    assert len(result.err_lines) == 1, f"expected one line on stderr, got {result.err!r}"
    line = result.err_lines[0]
    assert line.startswith("echoloc: error: "), line
    for name in names:
        assert name in line, f"{name!r} not named in {line!r}"


def is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def read_h5(path: Path) -> tuple[dict[str, Any], dict[str, Any]]:
    """Root attributes and datasets of an HDF5 recording, as plain values."""
    with h5py.File(path, "r") as f:
        attrs = {name: f.attrs[name] for name in f.attrs}
        data = {name: f[name][()] for name in f}
    return attrs, data


def broken_copy(good: Path, target: Path, breaker: Callable[[dict[str, Any], dict[str, Any]], None]) -> Path:
    """Copy every field of a good HDF5 recording to ``target``, then let ``breaker`` break one."""
    attrs, data = read_h5(good)
    breaker(attrs, data)
    if target.suffix == ".npz":
        np.savez(target, **{name: np.asarray(value) for name, value in {**attrs, **data}.items()})
        return target
    return write_raw(target, attrs, data)


def true_paths(rec: Recording, positions: np.ndarray) -> np.ndarray:
    """Exact transmitter -> reflector -> receiver paths, shape (n_reflectors, n_rx)."""
    path, _, _ = path_lengths_m(rec.transmitters_m[0], rec.receivers_m, positions)
    return path


# ----------------------------------------------------------------------------- fixtures


@pytest.fixture(scope="module")
def good_h5(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A valid recording of the report's three balls, N_FRAMES frames."""
    path = tmp_path_factory.mktemp("good") / "balls.h5"
    return write_recording(simulate(default_scene(), n_frames=N_FRAMES), path)


@pytest.fixture(scope="module")
def dead_h5(tmp_path_factory: pytest.TempPathFactory, good_h5: Path) -> Path:
    """The three-ball recording with receiver 2 all zeros (a dead channel)."""

    def kill_receiver_2(attrs: dict[str, Any], data: dict[str, Any]) -> None:
        data["frames"][:, 2, :] = 0.0

    return broken_copy(good_h5, tmp_path_factory.mktemp("dead") / "dead.h5", kill_receiver_2)


@pytest.fixture
def in_tmp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Work in tmp_path, so that file names in messages are short relative names."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


@pytest.fixture
def wide_stdout(monkeypatch: pytest.MonkeyPatch) -> None:
    """Room for the tables whatever COLUMNS the test run inherited."""
    monkeypatch.setattr(app.stdout, "width", 200)


# ----------------------------------------------------------------------------- demo


def test_demo_writes_a_readable_recording_and_finds_the_three_balls(
    capsys: pytest.CaptureFixture[str], in_tmp: Path, wide_stdout: None
) -> None:
    """User expectation: `echoloc demo` works out of the box, writes the recording it
    talks about, and its table shows each of the three balls with a sub-mm error."""
    (in_tmp / "tmp").mkdir()
    result = run(capsys, "demo", "-o", "tmp/demo.h5", "--frames", 3)
    assert result.code == 0, result
    assert "Traceback" not in result.err
    rec = read_recording(in_tmp / "tmp" / "demo.h5")
    assert rec.n_frames == 3
    assert rec.truth_positions_m is not None

    for column in ("ball", "range mm", "error mm", "rx"):
        assert column in result.out
    errors_mm = {}
    for line in result.out.splitlines():
        cells = [cell.strip() for cell in line.split("│")]
        if len(cells) == 9 and cells[1] in {"1", "2", "3"}:
            errors_mm[int(cells[1])] = float(cells[5])
    assert sorted(errors_mm) == [1, 2, 3], result.out
    assert all(0 <= error < 1.0 for error in errors_mm.values()), errors_mm
    assert "3 frames" in result.out
    assert "9 of 9 balls found" in result.out


def test_demo_recording_located_within_1_mm_in_every_frame(
    capsys: pytest.CaptureFixture[str], in_tmp: Path
) -> None:
    """User expectation: `echoloc locate` on the demo's own recording finds each of the
    report's three balls (default_scene) within 1 mm, in every frame (docs/FORMATS.md
    `locate --json`, one line per frame)."""
    assert run(capsys, "demo", "-o", "demo.h5", "--frames", 3).code == 0
    result = run(capsys, "locate", "demo.h5", "--json")
    assert result.code == 0, result
    records = json_lines(result.out)
    assert [r["frame"] for r in records] == [0, 1, 2]
    truth = default_scene().reflector_positions_m
    for record in records:
        found = np.array([o["position_m"] for o in record["objects"]]).reshape(-1, 3)
        assert len(found), record
        for ball in truth:
            distance = np.min(np.linalg.norm(found - ball, axis=1))
            assert distance < 1e-3, (record["frame"], ball, distance)


def test_demo_into_a_missing_directory_is_bad_input(capsys: pytest.CaptureFixture[str], in_tmp: Path) -> None:
    """docs/FORMATS.md exit codes: an output path that cannot be written is bad input (2),
    one line naming the file, no traceback."""
    assert_bad_input(run(capsys, "demo", "-o", "nodir/demo.h5", "--frames", 1), "nodir/demo.h5")
    assert not (in_tmp / "nodir").exists()


# ----------------------------------------------------------------------------- echoes --json


def check_echoes_records(records: list[dict[str, Any]], rec: Recording) -> None:
    """The shape rules of docs/FORMATS.md `echoes --json`, for every record."""
    assert rec.speed_of_sound_m_s is not None
    c = rec.speed_of_sound_m_s
    for record in records:
        assert set(record) == ECHOES_FRAME_KEYS, record.keys()
        assert isinstance(record["frame"], int)
        assert is_number(record["time_s"])
        assert [ch["receiver"] for ch in record["channels"]] == list(range(rec.n_receivers))
        for channel in record["channels"]:
            assert set(channel) == CHANNEL_KEYS, channel.keys()
            tofs = [echo["tof_s"] for echo in channel["echoes"]]
            assert tofs == sorted(tofs), f"echoes not in ascending tof: {tofs}"
            for echo in channel["echoes"]:
                assert set(echo) == ECHO_KEYS, echo.keys()
                assert all(is_number(echo[key]) for key in ECHO_KEYS), echo
                assert echo["tof_s"] > 0
                assert echo["path_m"] == pytest.approx(echo["tof_s"] * c, rel=1e-12, abs=0)


def test_echoes_json_follows_the_contract_and_finds_every_true_path(
    capsys: pytest.CaptureFixture[str], good_h5: Path
) -> None:
    """docs/FORMATS.md `echoes --json`: one object per frame with exactly the keys frame,
    time_s, channels[{receiver, echoes[{tof_s, path_m, amplitude, snr_db}]}]; echoes in
    ascending tof; path_m = tof_s x the speed of sound; every true path of the default
    scene matched by an echo within 0.5 mm."""
    result = run(capsys, "echoes", good_h5, "--json")
    assert result.code == 0, result
    assert result.err == ""
    rec = read_recording(good_h5)
    records = json_lines(result.out)
    assert len(records) == rec.n_frames == N_FRAMES
    assert [r["frame"] for r in records] == list(range(N_FRAMES))
    assert rec.frame_times_s is not None
    assert [r["time_s"] for r in records] == pytest.approx(list(rec.frame_times_s))
    check_echoes_records(records, rec)

    paths = true_paths(rec, default_scene().reflector_positions_m)
    for record in records:
        for channel in record["channels"]:
            measured = np.array([echo["path_m"] for echo in channel["echoes"]])
            assert len(measured), (record["frame"], channel["receiver"])
            for true_path in paths[:, channel["receiver"]]:
                miss = np.min(np.abs(measured - true_path))
                assert miss < 0.5e-3, (record["frame"], channel["receiver"], true_path, miss)


def test_echoes_json_threshold_estimator_first_echo_within_2_mm(
    capsys: pytest.CaptureFixture[str], good_h5: Path
) -> None:
    """docs/FORMATS.md `echoes --json`: tof_s is the path over c "whatever the estimator";
    with --estimator threshold the first echo of each channel is the nearest ball's
    path within 2 mm, and the format rules hold as for the matched filter."""
    result = run(capsys, "echoes", good_h5, "--json", "--estimator", "threshold")
    assert result.code == 0, result
    rec = read_recording(good_h5)
    records = json_lines(result.out)
    assert len(records) == N_FRAMES
    check_echoes_records(records, rec)
    shortest = true_paths(rec, default_scene().reflector_positions_m).min(axis=0)
    for record in records:
        for channel in record["channels"]:
            assert channel["echoes"], (record["frame"], channel["receiver"])
            first = channel["echoes"][0]["path_m"]
            assert abs(first - shortest[channel["receiver"]]) < 2e-3, (record["frame"], channel)


def test_echoes_speed_of_sound_override_scales_path_not_tof(
    capsys: pytest.CaptureFixture[str], good_h5: Path
) -> None:
    """docs/FORMATS.md: path_m is tof_s times "the speed of sound used", so with
    --speed-of-sound the paths follow the given value."""
    result = run(capsys, "echoes", good_h5, "--json", "--speed-of-sound", 340.0, "--frames", 0)
    assert result.code == 0, result
    (record,) = json_lines(result.out)
    echoes = [echo for channel in record["channels"] for echo in channel["echoes"]]
    assert echoes
    for echo in echoes:
        assert echo["path_m"] == pytest.approx(echo["tof_s"] * 340.0, rel=1e-12, abs=0)


# ----------------------------------------------------------------------------- locate --json


def test_locate_json_follows_the_contract(capsys: pytest.CaptureFixture[str], good_h5: Path) -> None:
    """docs/FORMATS.md `locate --json`: one object per frame with exactly the keys frame,
    time_s, objects[{position_m[3], std_m[3], receivers, score}]; receivers an int
    3..4 (how many receivers support the object), score in [0, 1], std_m > 0; and the
    three balls found within 1 mm."""
    result = run(capsys, "locate", good_h5, "--json")
    assert result.code == 0, result
    assert result.err == ""
    records = json_lines(result.out)
    assert [r["frame"] for r in records] == list(range(N_FRAMES))
    truth = default_scene().reflector_positions_m
    for record in records:
        assert set(record) == LOCATE_FRAME_KEYS, record.keys()
        assert is_number(record["time_s"])
        assert record["objects"], record
        for obj in record["objects"]:
            assert OBJECT_KEYS <= set(obj) <= OBJECT_KEYS | OPTIONAL_OBJECT_KEYS, obj.keys()
            assert obj["channels"] >= obj["receivers"]
            assert 0 <= obj["shared_echoes"] <= obj["channels"]
            assert len(obj["position_m"]) == 3
            assert all(map(is_number, obj["position_m"]))
            assert len(obj["std_m"]) == 3
            assert all(map(is_number, obj["std_m"]))
            assert all(s > 0 for s in obj["std_m"]), obj
            assert type(obj["receivers"]) is int, obj
            assert 3 <= obj["receivers"] <= 4, obj
            assert is_number(obj["score"]), obj
            assert 0 <= obj["score"] <= 1, obj
            assert obj["position_m"][2] > 0, "in front of the array (z is the boresight)"
        found = np.array([o["position_m"] for o in record["objects"]])
        for ball in truth:
            assert np.min(np.linalg.norm(found - ball, axis=1)) < 1e-3


@pytest.mark.parametrize("command", ["echoes", "locate"])
def test_workers_change_no_output_and_a_bad_count_is_one_line(
    capsys: pytest.CaptureFixture[str], good_h5: Path, command: str
) -> None:
    """--workers 2 and -1 give the JSON of one thread byte for byte; 0 is refused with exit 2
    and one line naming the option's value, before the file is read."""
    one = run(capsys, command, good_h5, "--json")
    assert one.code == 0, one
    for workers in (2, -1):
        threaded = run(capsys, command, good_h5, "--json", "--workers", workers)
        assert threaded.code == 0, threaded
        assert threaded.out == one.out
    bad = run(capsys, command, "no-such-file.h5", "--workers", 0)
    assert bad.code == 2
    assert bad.err.strip().splitlines() == ["echoloc: error: workers must be >= 1 (or -1: one a core), got 0"]


def test_locate_reads_npz_recordings(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """docs/FORMATS.md: "the same names in a NumPy .npz are accepted too"."""
    path = write_recording(simulate(default_scene(), n_frames=1), tmp_path / "balls.npz")
    result = run(capsys, "locate", path, "--json")
    assert result.code == 0, result
    (record,) = json_lines(result.out)
    assert len(record["objects"]) == 3


# ----------------------------------------------------------------------------- --frames


@pytest.mark.parametrize("command", ["echoes", "locate"])
@pytest.mark.parametrize("frames", ["1:2", "1"])
def test_frames_selects_one_frame(
    capsys: pytest.CaptureFixture[str], good_h5: Path, command: str, frames: str
) -> None:
    """User expectation: --frames 1:2 (a slice) and --frames 1 select exactly frame 1,
    reported with its own frame index and time."""
    result = run(capsys, command, good_h5, "--json", "--frames", frames)
    assert result.code == 0, result
    (record,) = json_lines(result.out)
    assert record["frame"] == 1
    assert record["time_s"] == pytest.approx(0.01)


@pytest.mark.parametrize("frames", [":", "0:", ":2"])
def test_frames_open_slices_select_all(
    capsys: pytest.CaptureFixture[str], good_h5: Path, frames: str
) -> None:
    """User expectation: --frames with an open end means "to the start/end"."""
    result = run(capsys, "locate", good_h5, "--json", "--frames", frames)
    assert result.code == 0, result
    assert [r["frame"] for r in json_lines(result.out)] == [0, 1]


@pytest.mark.parametrize("command", ["echoes", "locate", "evaluate"])
@pytest.mark.parametrize("frames", ["x", "5:2", "2", "0:3", "-1", "1:2:3", "1.5", ""])
def test_bad_frames_is_a_usage_error(
    capsys: pytest.CaptureFixture[str], good_h5: Path, command: str, frames: str
) -> None:
    """docs/FORMATS.md exit codes: a --frames value that is not N or START:STOP inside the
    recording is bad usage: exit 2, one line on stderr naming --frames."""
    result = run(capsys, command, good_h5, "--json", "--frames", frames)
    assert_bad_input(result, "--frames")


# ----------------------------------------------------------------------------- evaluate


def test_simulate_then_evaluate_random_scene(capsys: pytest.CaptureFixture[str], in_tmp: Path) -> None:
    """User expectation (random-1m3, the acceptance scene): 30 simulated
    frames are evaluated with recall >= 0.95 and a false rate <= 0.05."""
    result = run(capsys, "simulate", SCENES / "random-1m3.toml", "-o", "random.h5", "--frames", 30)
    assert result.code == 0, result
    assert result.out == ""
    assert "Traceback" not in result.err
    assert read_recording(in_tmp / "random.h5").n_frames == 30

    result = run(capsys, "evaluate", "random.h5", "--json")
    assert result.code == 0, result
    (report,) = json_lines(result.out)
    assert set(report) == EVALUATE_KEYS
    assert report["frames"] == 30
    assert report["estimator"] == "matched"
    assert report["truth_objects"] >= 30
    assert report["recall"] >= 0.95, report
    assert report["false_rate"] <= 0.05, report
    assert all(0 <= v < 5e-3 for v in report["rmse_m"]), report


def test_evaluate_without_truth_is_bad_input(
    capsys: pytest.CaptureFixture[str], in_tmp: Path, good_h5: Path
) -> None:
    """docs/FORMATS.md: truth_positions is read by `evaluate`; a recording without it is bad
    input for evaluate: exit 2, one line naming the file and truth_positions."""
    rec = dataclasses.replace(read_recording(good_h5), truth_positions_m=None)
    write_recording(rec, in_tmp / "notruth.h5")
    assert_bad_input(run(capsys, "evaluate", "notruth.h5"), "notruth.h5", "truth_positions")
    assert_bad_input(run(capsys, "evaluate", "notruth.h5", "--json"), "notruth.h5", "truth_positions")


def test_locate_ignores_truth(capsys: pytest.CaptureFixture[str], in_tmp: Path, good_h5: Path) -> None:
    """docs/FORMATS.md: truth_positions is "never" read by echoes or locate: removing it does
    not change their output."""
    rec = dataclasses.replace(read_recording(good_h5), truth_positions_m=None)
    write_recording(rec, in_tmp / "notruth.h5")
    for command in ("echoes", "locate"):
        with_truth = run(capsys, command, good_h5, "--json")
        without = run(capsys, command, "notruth.h5", "--json")
        assert with_truth.code == without.code == 0
        assert with_truth.out == without.out


# ----------------------------------------------------------------------------- bad input

Breaker = Callable[[dict[str, Any], dict[str, Any]], None]


def _set_attr(name: str, value: Any) -> Breaker:
    def breaker(attrs: dict[str, Any], data: dict[str, Any]) -> None:
        attrs[name] = value

    return breaker


def _drop_receiver_channel(attrs: dict[str, Any], data: dict[str, Any]) -> None:
    data["frames"] = data["frames"][:, :3, :]


def _nan_sample(attrs: dict[str, Any], data: dict[str, Any]) -> None:
    data["frames"][0, 1, 5] = np.nan


def _drop_receivers(attrs: dict[str, Any], data: dict[str, Any]) -> None:
    del data["receivers"]


BROKEN_FILES: dict[str, tuple[str, Breaker, tuple[str, ...]]] = {
    # id: (file name, what breaks, what the message must name besides the file)
    "channels-vs-receivers": ("channels.h5", _drop_receiver_channel, ("frames", "receivers")),
    "nan-sample": ("nan.h5", _nan_sample, ("frames",)),
    "wrong-format": ("format.h5", _set_attr("format", "wav-recording"), ("format",)),
    "version-2": ("v2.h5", _set_attr("version", 2), ("version",)),
    "version-2-npz": ("v2.npz", _set_attr("version", 2), ("version",)),
    "negative-sample-rate": ("rate.h5", _set_attr("sample_rate_hz", -200e3), ("sample_rate_hz",)),
    "missing-receivers": ("norx.h5", _drop_receivers, ("receivers",)),
}


@pytest.mark.parametrize("command", ["echoes", "locate", "evaluate"])
@pytest.mark.parametrize("case", BROKEN_FILES.values(), ids=BROKEN_FILES.keys())
def test_broken_recording_is_bad_input(
    capsys: pytest.CaptureFixture[str],
    in_tmp: Path,
    good_h5: Path,
    command: str,
    case: tuple[str, Breaker, tuple[str, ...]],
) -> None:
    """docs/FORMATS.md recording file: "A reader rejects with a clear message (exit code 2 on
    the command line)" a channel count that does not match receivers, NaN samples, a
    wrong format or version, a sample rate that is not positive, a missing required
    item; exit codes: one line on stderr naming the file and the field, no traceback."""
    name, breaker, fields = case
    broken_copy(good_h5, in_tmp / name, breaker)
    assert_bad_input(run(capsys, command, name, "--json"), name, *fields)


def test_missing_file_is_bad_input(capsys: pytest.CaptureFixture[str], in_tmp: Path) -> None:
    """docs/FORMATS.md exit codes: a missing recording is exit 2, one line naming the file."""
    assert_bad_input(run(capsys, "locate", "missing.h5"), "missing.h5")


def test_text_file_named_h5_is_bad_input(capsys: pytest.CaptureFixture[str], in_tmp: Path) -> None:
    """docs/FORMATS.md exit codes: a file that is not HDF5 despite its .h5 name is exit 2,
    one line naming the file (not an h5py traceback)."""
    (in_tmp / "notes.h5").write_text("these are my notes, not a recording\n")
    assert_bad_input(run(capsys, "echoes", "notes.h5"), "notes.h5", "HDF5")


def test_unknown_extension_is_bad_input(
    capsys: pytest.CaptureFixture[str], in_tmp: Path, good_h5: Path
) -> None:
    """docs/FORMATS.md: a recording is .h5 or .npz; any other extension is exit 2, one line
    naming the file and the extension."""
    shutil.copy(good_h5, in_tmp / "balls.wav")
    assert_bad_input(run(capsys, "locate", "balls.wav"), "balls.wav", ".wav")


def test_directory_as_recording_is_bad_input(capsys: pytest.CaptureFixture[str], in_tmp: Path) -> None:
    """docs/FORMATS.md exit codes: a directory where a recording is expected is exit 2."""
    (in_tmp / "folder.h5").mkdir()
    assert_bad_input(run(capsys, "locate", "folder.h5"), "folder.h5")


def test_simulate_scene_with_unknown_key_is_bad_input(
    capsys: pytest.CaptureFixture[str], in_tmp: Path
) -> None:
    """docs/FORMATS.md exit codes: a scene file with an unknown key (a typo) is exit 2, one
    line naming the file and the key, and no recording is written."""
    (in_tmp / "bad.toml").write_text("seed = 1\nbogus = 2\n")
    assert_bad_input(run(capsys, "simulate", "bad.toml", "-o", "out.h5"), "bad.toml", "bogus")
    assert not (in_tmp / "out.h5").exists()


def test_simulate_missing_scene_is_bad_input(capsys: pytest.CaptureFixture[str], in_tmp: Path) -> None:
    """docs/FORMATS.md exit codes: a missing scene file is exit 2, one line naming it."""
    assert_bad_input(run(capsys, "simulate", "nope.toml", "-o", "out.h5"), "nope.toml")
    assert not (in_tmp / "out.h5").exists()


@pytest.mark.parametrize(
    ("command", "option", "value"),
    [
        ("locate", "--speed-of-sound", "-1"),
        ("echoes", "--speed-of-sound", "0"),
        ("locate", "--speed-of-sound", "nan"),
        ("locate", "--blanking-s", "-1"),
        ("echoes", "--blanking-s", "-1"),
        ("locate", "--path-sigma-m", "0"),
        ("locate", "--field-of-view-deg", "0"),
        ("evaluate", "--field-of-view-deg", "181"),
        ("evaluate", "--match-radius-m", "0"),
    ],
)
def test_bad_option_value_is_bad_input(
    capsys: pytest.CaptureFixture[str], good_h5: Path, command: str, option: str, value: str
) -> None:
    """docs/FORMATS.md exit codes: an option value out of its range (a negative speed of
    sound or blanking time, ...) is exit 2, one line naming the option."""
    assert_bad_input(run(capsys, command, good_h5, "--json", option, value), option)


@pytest.mark.parametrize(
    ("command", "option", "value"),
    [
        ("locate", "--blanking-s", "nan"),
        ("locate", "--blanking-s", "inf"),
        ("locate", "--speed-of-sound", "inf"),
        ("echoes", "--threshold-db", "nan"),
    ],
)
def test_non_finite_option_value_is_bad_input(
    capsys: pytest.CaptureFixture[str], good_h5: Path, command: str, option: str, value: str
) -> None:
    """docs/FORMATS.md exit codes, user expectation: a NaN or infinite number is never a
    meaningful option value; it is bad input (exit 2) rather than a run that silently
    finds nothing."""
    assert_bad_input(run(capsys, command, good_h5, "--json", option, value), option)


@pytest.mark.parametrize(
    "args",
    [
        ("locate", "{good}", "--bogus"),
        ("echoes", "{good}", "--estimator", "psychic"),
        ("locate",),
        ("simulate", "scene.toml"),
        ("nosuchcommand",),
    ],
    ids=["unknown-option", "unknown-estimator", "missing-argument", "missing-output", "unknown-command"],
)
def test_click_usage_errors_exit_2(
    capsys: pytest.CaptureFixture[str], good_h5: Path, args: tuple[str, ...]
) -> None:
    """docs/FORMATS.md exit codes: bad usage is exit 2, one line on stderr naming the
    problem and pointing to the command's --help, no traceback."""
    result = run(capsys, *(a.format(good=good_h5) for a in args))
    assert result.code == 2, result
    assert "Traceback" not in result.out + result.err
    assert result.out == ""
    assert len(result.err_lines) == 1, result.err
    assert result.err_lines[0].startswith("echoloc: error: "), result.err
    assert "--help" in result.err_lines[0]


@pytest.mark.filterwarnings("always::echoloc.io.recording.RecordingWarning")
def test_nan_sample_with_repair_warns_and_succeeds(
    capsys: pytest.CaptureFixture[str], in_tmp: Path, good_h5: Path
) -> None:
    """docs/FORMATS.md: NaN samples are rejected "unless asked to repair them";
    --repair-nonfinite succeeds (exit 0) with one warning line on stderr."""
    broken_copy(good_h5, in_tmp / "nan.h5", _nan_sample)
    result = run(capsys, "locate", "nan.h5", "--json", "--repair-nonfinite")
    assert result.code == 0, result
    assert len(result.err_lines) == 1, result.err
    assert result.err_lines[0].startswith("echoloc: warning: nan.h5"), result.err
    assert "1 non-finite" in result.err
    assert len(json_lines(result.out)) == N_FRAMES


@pytest.mark.filterwarnings("always::echoloc.io.recording.RecordingWarning")
def test_dead_channel_warns_and_locates_with_three_receivers(
    capsys: pytest.CaptureFixture[str], dead_h5: Path
) -> None:
    """User expectation: one dead receiver (all zeros) is not fatal: locate exits 0 with
    a warning on stderr naming the file and receiver, and reports objects supported by
    the 3 remaining receivers (docs/FORMATS.md `receivers`: how many support the object)."""
    result = run(capsys, "locate", dead_h5, "--json")
    assert result.code == 0, result
    assert "Traceback" not in result.err
    warning = [line for line in result.err_lines if line.startswith("echoloc: warning: ")]
    assert warning, result.err
    assert "dead.h5" in result.err
    assert re.search(r"receiver\s+2\b", result.err), result.err
    records = json_lines(result.out)
    assert len(records) == N_FRAMES
    for record in records:
        assert record["objects"], record
        assert all(obj["receivers"] == 3 for obj in record["objects"]), record


@pytest.mark.filterwarnings("always::echoloc.io.recording.RecordingWarning")
def test_dead_channel_single_ball_found_with_three_receivers(
    capsys: pytest.CaptureFixture[str], in_tmp: Path
) -> None:
    """User expectation: with one receiver dead, a lone reflector (no ghosts possible)
    is still located from the 3 remaining receivers, within 5 mm."""
    ball = default_scene().reflector_positions_m[1:2]
    scene = dataclasses.replace(default_scene(), reflector_positions_m=ball, reflector_strengths=np.ones(1))
    rec = simulate(scene, n_frames=2)
    frames = rec.frames.copy()
    frames[:, 0, :] = 0.0
    write_recording(dataclasses.replace(rec, frames=frames), in_tmp / "lone.h5")
    result = run(capsys, "locate", "lone.h5", "--json")
    assert result.code == 0, result
    assert re.search(r"receiver\s+0\b", result.err), result.err
    for record in json_lines(result.out):
        (obj,) = record["objects"]
        assert obj["receivers"] == 3
        assert np.linalg.norm(np.array(obj["position_m"]) - ball[0]) < 5e-3, obj


# ----------------------------------------------------------------------------- help, tables


@pytest.mark.parametrize("command", COMMANDS)
def test_help_for_every_command(capsys: pytest.CaptureFixture[str], command: str) -> None:
    """User expectation: `echoloc COMMAND --help` (and -h) prints usage, exit 0."""
    for flag in ("--help", "-h"):
        result = run(capsys, command, flag)
        assert result.code == 0, result
        assert f"Usage: echoloc {command}" in result.out
        assert result.err == ""


def test_help_lists_every_command(capsys: pytest.CaptureFixture[str]) -> None:
    """User expectation: `echoloc --help` lists every command; --version works."""
    result = run(capsys, "--help")
    assert result.code == 0
    for command in COMMANDS:
        assert command in result.out
    assert set(COMMANDS) <= set(cli.cli.commands)
    version = run(capsys, "--version")
    assert version.code == 0
    assert "echoloc" in version.out


@pytest.mark.usefixtures("wide_stdout")
@pytest.mark.parametrize(
    ("command", "columns"),
    [
        ("echoes", ("frame", "receiver", "tof µs", "path m", "amplitude", "SNR dB")),
        ("locate", ("frame", "x mm", "y mm", "z mm", "±σ x, y, z mm", "range mm", "rx", "score")),
        ("evaluate", ("figure", "value", "recall", "false objects", "match radius")),
    ],
)
def test_human_tables(
    capsys: pytest.CaptureFixture[str], good_h5: Path, command: str, columns: tuple[str, ...]
) -> None:
    """User expectation: without --json each command prints a readable table with its
    column names, exit 0, nothing on stderr."""
    result = run(capsys, command, good_h5)
    assert result.code == 0, result
    assert result.err == ""
    for column in columns:
        assert column in result.out, column
    with pytest.raises(json.JSONDecodeError):
        json.loads(result.out.splitlines()[0])


@pytest.mark.usefixtures("wide_stdout")
def test_human_table_shows_frames_without_objects(capsys: pytest.CaptureFixture[str], good_h5: Path) -> None:
    """User expectation: a frame where nothing is found (here every echo is blanked)
    still gets a row of "-" in the table rather than vanishing or failing."""
    result = run(capsys, "locate", good_h5, "--blanking-s", 0.011)
    assert result.code == 0, result
    rows = [line for line in result.out.splitlines() if re.match(r"^│\s+\d+\s+│", line)]
    assert len(rows) == N_FRAMES, result.out
    assert all("-" in row for row in rows)


@pytest.mark.filterwarnings("always::echoloc.io.recording.RecordingWarning")
def test_too_few_working_receivers_is_bad_input(capsys: pytest.CaptureFixture[str], in_tmp: Path) -> None:
    """docs/FORMATS.md exit codes: two dead receivers leave too few to locate in 3-D; that is
    bad input (exit 2, one error line naming the file), not an empty result."""
    rec = simulate(default_scene(), n_frames=1)
    frames = rec.frames.copy()
    frames[:, :2, :] = 0.0
    write_recording(dataclasses.replace(rec, frames=frames), in_tmp / "two-dead.h5")
    result = run(capsys, "locate", "two-dead.h5", "--json")
    assert result.code == 2, result
    assert "Traceback" not in result.err
    # Each line is a whole warning or the error; exactly one error, naming the file.
    assert all(line.startswith(("echoloc: warning: ", "echoloc: error: ")) for line in result.err_lines), (
        result.err
    )
    errors = [line for line in result.err_lines if line.startswith("echoloc: error: ")]
    assert len(errors) == 1, result.err
    assert errors[0].startswith("echoloc: error: two-dead.h5"), result.err


# ----------------------------------------------------------------------------- real subprocess


def test_subprocess_locate_json_stdout_is_pure_json_lines(tmp_path: Path, good_h5: Path) -> None:
    """docs/FORMATS.md `locate --json`: a real run's stdout is nothing but JSON Lines, one
    per frame, and stderr is empty (no progress bar, no log noise)."""
    result = run_process("locate", good_h5, "--json", cwd=tmp_path)
    assert result.code == 0, result
    assert result.err == ""
    assert [r["frame"] for r in json_lines(result.out)] == list(range(N_FRAMES))


def test_subprocess_missing_file_one_line_no_traceback(tmp_path: Path) -> None:
    """docs/FORMATS.md exit codes, as a shell sees them: exit 2, one line naming the file."""
    assert_bad_input(run_process("echoes", "missing.h5", "--json", cwd=tmp_path), "missing.h5")


def test_subprocess_bad_option_one_line_no_traceback(tmp_path: Path, good_h5: Path) -> None:
    """docs/FORMATS.md exit codes, as a shell sees them: --blanking-s -1 is exit 2, one line."""
    result = run_process("locate", good_h5, "--blanking-s", "-1", cwd=tmp_path)
    assert_bad_input(result, "--blanking-s")


def test_subprocess_unknown_option_is_usage_error(tmp_path: Path, good_h5: Path) -> None:
    """docs/FORMATS.md exit codes, as a shell sees them: an unknown option is click's usage
    error, exit 2, no traceback."""
    result = run_process("locate", good_h5, "--bogus", cwd=tmp_path)
    assert result.code == 2, result
    assert "Traceback" not in result.err
    assert "--bogus" in result.err_lines[-1]


def test_subprocess_repair_nonfinite_warns_on_one_line(tmp_path: Path, good_h5: Path) -> None:
    """docs/FORMATS.md: NaN samples are bad input (exit 2, one line) unless --repair-nonfinite,
    which succeeds with one warning line; as a shell sees them."""
    broken_copy(good_h5, tmp_path / "nan.h5", _nan_sample)
    refused = run_process("locate", "nan.h5", "--json", cwd=tmp_path)
    assert refused.code == 2, refused
    assert "Traceback" not in refused.err
    assert "nan.h5" in refused.err
    repaired = run_process("locate", "nan.h5", "--json", "--repair-nonfinite", cwd=tmp_path)
    assert repaired.code == 0, repaired
    assert "Traceback" not in repaired.err
    assert repaired.err_lines == ["echoloc: warning: nan.h5: replaced 1 non-finite sample(s) with 0"]
    assert len(json_lines(repaired.out)) == N_FRAMES


def test_subprocess_long_error_message_stays_on_one_line(tmp_path: Path) -> None:
    """docs/FORMATS.md exit codes: "one line on stderr naming the file and the problem",
    however long the file's name (stderr piped, so no terminal width applies)."""
    name = "a-recording-with-a-rather-long-but-perfectly-ordinary-descriptive-file-name.h5"
    result = run_process("locate", name, cwd=tmp_path)
    assert_bad_input(result, name)


def test_a_hostile_value_quoted_in_an_error_does_not_bury_the_file(tmp_path: Path, good_h5: Path) -> None:
    """A 5000-character value in a calibration file: the refusal stays one short line that
    still names the file and the key (the fuzz campaign found messages of 5000+ characters)."""
    calibration = tmp_path / "cal.json"
    calibration.write_text(json.dumps({"format": "echoloc-calibration", "version": "x" * 5000}))
    result = run_process("locate", good_h5, "--calibration", calibration, cwd=tmp_path)
    assert_bad_input(result, "cal.json")
    assert "version" in result.err_lines[-1]
    assert len(result.err_lines[-1]) < 450


def test_a_numpy_warning_names_the_input_it_came_from(
    capsys: pytest.CaptureFixture[str], good_h5: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """numpy's floating-point warnings know no file ("invalid value encountered in cast",
    seen by the fuzz campaign): the line names the command's input."""
    checked = processing.check_locatable

    def check_with_a_cast(chain: Any) -> None:
        np.array([np.nan]).astype(np.int64)  # numpy warns: invalid value encountered in cast
        checked(chain)

    monkeypatch.setattr(processing, "check_locatable", check_with_a_cast)
    with warnings.catch_warnings():
        warnings.simplefilter("default")
        result = run(capsys, "locate", good_h5, "--json")
    assert result.code == 0, result
    cast = [line for line in result.err_lines if "invalid value encountered in cast" in line]
    assert cast
    assert cast[0].startswith(f"echoloc: warning: {good_h5}: ")


def test_export_writes_what_locate_finds_as_mcap_and_ply(
    capsys: pytest.CaptureFixture[str], good_h5: Path, in_tmp: Path
) -> None:
    """`echoloc export` writes the objects `locate --json` reports: the MCAP's PointCloud2
    messages (read back with the MCAP reader) and the PLY's vertices hold the same points."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory
    from plyfile import PlyData

    located = json_lines(run(capsys, "locate", good_h5, "--json").out)
    expected = np.array([o["position_m"] for r in located for o in r["objects"]])
    assert run(capsys, "export", good_h5, "-o", "out.mcap").code == 0
    clouds = []
    with open(in_tmp / "out.mcap", "rb") as stream:
        for _, _channel, _, message in make_reader(
            stream, decoder_factories=[DecoderFactory()]
        ).iter_decoded_messages(topics=["/echoloc/objects"]):
            assert message.header.frame_id == "echoloc_sensor_optical_frame"
            points = np.frombuffer(bytes(message.data), dtype=np.float32).reshape(message.width, -1)[:, :3]
            clouds.append(points)
    assert len(clouds) == len(located)
    assert np.vstack(clouds) == pytest.approx(expected, abs=1e-6)
    assert run(capsys, "export", good_h5, "-o", "out.ply").code == 0
    vertex = PlyData.read(str(in_tmp / "out.ply"))["vertex"]
    assert np.column_stack([vertex["x"], vertex["y"], vertex["z"]]) == pytest.approx(expected, abs=1e-6)


def test_export_to_an_unknown_format_is_bad_input(
    capsys: pytest.CaptureFixture[str], good_h5: Path, in_tmp: Path
) -> None:
    assert_bad_input(run(capsys, "export", good_h5, "-o", "out.bt"), "out.bt")
    assert not (in_tmp / "out.bt").exists()


@pytest.mark.parametrize(
    ("output", "options", "ignored"),
    [
        ("out.ply", ["--start-time-s", "5"], "--start-time-s"),
        ("out.ply", ["--start-time-s", "-1"], "--start-time-s"),  # not checked: not used
        ("out.mcap", ["--ascii"], "--ascii is"),
        ("out.mcap", ["--per-frame"], "--per-frame is"),
        ("out.mcap", ["--ascii", "--per-frame"], "--ascii and --per-frame are"),
    ],
)
def test_export_says_which_options_its_format_ignores(
    capsys: pytest.CaptureFixture[str],
    good_h5: Path,
    in_tmp: Path,
    output: str,
    options: list[str],
    ignored: str,
) -> None:
    """An option the chosen format has no use for is named in one warning line; the file is
    written as without it."""
    result = run(capsys, "export", good_h5, "-o", output, *options)
    assert result.code == 0, result
    assert len(result.err_lines) == 1
    assert result.err_lines[0].startswith(f"echoloc: warning: {ignored} ")
    assert result.err_lines[0].endswith("ignored")
    written = (in_tmp / output).read_bytes()
    assert run(capsys, "export", good_h5, "-o", "plain" + output[3:]).code == 0
    assert written == (in_tmp / ("plain" + output[3:])).read_bytes()


def test_export_with_the_options_of_its_format_warns_of_nothing(
    capsys: pytest.CaptureFixture[str], good_h5: Path, in_tmp: Path
) -> None:
    """The options of the chosen format, used, raise no warning (and a bad MCAP time is refused)."""
    assert run(capsys, "export", good_h5, "-o", "out.mcap", "--start-time-s", "5").err_lines == []
    assert run(capsys, "export", good_h5, "-o", "out.ply", "--ascii").err_lines == []
    assert_bad_input(
        run(capsys, "export", good_h5, "-o", "out.mcap", "--start-time-s", "-1"), "--start-time-s"
    )


def test_backprojection_locates_two_transmitters_reflectors(
    capsys: pytest.CaptureFixture[str], in_tmp: Path
) -> None:
    """`--method backprojection` ("points to peaks") finds the three reflectors of
    two-transmitters within 5 mm in every frame, and nothing else."""
    scene = REPO / "src" / "echoloc" / "scenes" / "two-transmitters.toml"
    assert run(capsys, "simulate", scene, "-o", "two.h5", "--frames", "3").code == 0
    result = run(
        capsys, "evaluate", "two.h5", "--method", "backprojection", "--json", "--match-radius-m", "0.005"
    )
    assert result.code == 0, result.err
    figures = json.loads(result.out)
    assert figures["recall"] == 1.0
    assert figures["false_objects"] == 0


def test_image_writes_a_png_and_refuses_a_frame_outside(
    capsys: pytest.CaptureFixture[str], good_h5: Path, in_tmp: Path
) -> None:
    result = run(capsys, "image", good_h5, "--frame", "1", "--voxel-m", "0.01", "-o", "frame.png")
    assert result.code == 0, result.err
    assert (in_tmp / "frame.png").read_bytes()[:4] == b"\x89PNG"
    assert "3 objects in frame 1" in result.out
    assert_bad_input(run(capsys, "image", good_h5, "--frame", "99", "-o", "x.png"), "--frame")


# ----------------------------------------------------------------------------- the bad-input audit
# Cases a black-box audit of every command found crashing (exit 1, "internal error"),
# hanging, or naming the wrong thing; each must now be one line naming the problem and
# exit 2, or carry on with a warning.


@pytest.mark.parametrize(
    "args",
    [
        ("echoes", "{good}", "--threshold-db", "4000"),  # 10^400: no float
        ("locate", "{good}", "--threshold-db", "-1e308"),
        ("template", "{good}", "-o", "t.npz", "--arrival", "nan"),
        ("template", "{good}", "-o", "t.npz", "--arrival", "inf"),
        ("export", "{good}", "-o", "e.mcap", "--start-time-s", "1e300"),
        ("waveform", "barker13", "--sample-rate", "1e12"),  # a 10^9-sample pulse: hung
        ("waveform", "barker13", "--sample-rate", "80e3"),  # the 50 kHz carrier above Nyquist
        ("send", "{good}", "--to", "127.0.0.1:9", "--connect-timeout", "nan"),  # retried forever
        ("send", "{good}", "--to", "127.0.0.1:9", "--connect-timeout", "-1"),
    ],
    ids=[
        "threshold-huge",
        "threshold-minus-huge",
        "arrival-nan",
        "arrival-inf",
        "ros-stamp-huge",
        "sample-rate-huge",
        "carrier-above-nyquist",
        "connect-timeout-nan",
        "connect-timeout-negative",
    ],
)
def test_out_of_range_numbers_are_one_line_naming_the_option(
    capsys: pytest.CaptureFixture[str], in_tmp: Path, good_h5: Path, args: tuple[str, ...]
) -> None:
    result = run(capsys, *(a.format(good=good_h5) for a in args))
    assert_bad_input(result, args[-2])  # the option whose value is refused
    assert list(in_tmp.iterdir()) == [], "nothing written for a refused option"


def test_a_huge_threshold_is_refused_by_the_library_too() -> None:
    from echoloc.errors import EchoLocError
    from echoloc.tof.echoes import THRESHOLD_DB_LIMIT, EchoOptions

    EchoOptions(threshold_db=THRESHOLD_DB_LIMIT)
    with pytest.raises(EchoLocError, match="threshold_db"):
        EchoOptions(threshold_db=4000.0)
    with pytest.raises(EchoLocError, match="threshold_db"):
        EchoOptions(threshold_db=math.nan)


@pytest.mark.parametrize(
    ("field", "value"),
    [("echoes_used", "x"), ("echoes_used", math.nan), ("echoes_used", -1), ("residual_rms_s", "x")],
)
def test_a_calibration_with_a_bad_optional_field_is_bad_input(
    capsys: pytest.CaptureFixture[str], in_tmp: Path, good_h5: Path, field: str, value: object
) -> None:
    record = {
        "format": "echoloc-calibration",
        "version": 1,
        "speed_of_sound_m_s": 343.2,
        "receiver_delays_s": [0.0, 0.0, 0.0, 0.0],
        "echoes_used": 12,
        "residual_rms_s": 1e-8,
        field: value,
    }
    (in_tmp / "cal.json").write_text(json.dumps(record))  # NaN as JSON's NaN, as Python writes it
    assert_bad_input(run(capsys, "echoes", good_h5, "--calibration", "cal.json"), "cal.json", field)


@pytest.mark.parametrize(
    "args",
    [
        ("air", "--plot", "a.txt"),
        ("beam", "--plot", "b.txt"),
        ("waveform", "barker13", "--plot", "w.txt"),
        ("demo", "--frames", "2", "-o", "d.h5", "--plot", "d.txt"),
    ],
    ids=["air", "beam", "waveform", "demo"],
)
def test_a_plot_in_a_format_matplotlib_cannot_draw_is_refused_before_the_work(
    capsys: pytest.CaptureFixture[str], in_tmp: Path, args: tuple[str, ...]
) -> None:
    assert_bad_input(run(capsys, *args), args[-1], "--plot")
    assert list(in_tmp.iterdir()) == [], "the demo's recording is not written for a plot it cannot draw"


@pytest.mark.filterwarnings("always::echoloc.io.recording.RecordingWarning")
@pytest.mark.filterwarnings("always::echoloc.localise.locate.LocateWarning")
def test_backprojection_degrades_to_three_receivers_and_refuses_none(
    capsys: pytest.CaptureFixture[str], in_tmp: Path, good_h5: Path, dead_h5: Path
) -> None:
    """One dead receiver: back-projection takes 3 channels, not its default 4, and warns that
    ghosts pass then; every receiver dead: one line naming the file, not a crash in np.stack."""
    result = run(capsys, "locate", dead_h5, "--method", "backprojection", "--frames", "0", "--json")
    assert result.code == 0, result
    assert re.search(r"receiver\s+2\b", result.err), result.err
    assert "ghosts" in result.err, result.err  # three paths cross at ghosts too: said, not hidden
    found = np.array([o["position_m"] for o in json_lines(result.out)[0]["objects"]])
    truth = default_scene().reflector_positions_m
    # Some of the crossings are the balls (here one of three; the others are ghosts that the
    # fourth receiver would have rejected).
    assert np.any(np.linalg.norm(found[:, None] - truth[None], axis=2) < 1e-3)

    def kill_all(attrs: dict[str, Any], data: dict[str, Any]) -> None:
        data["frames"][:] = 0.0

    broken_copy(good_h5, in_tmp / "silent.h5", kill_all)
    result = run(capsys, "image", "silent.h5", "-o", "i.png")
    assert result.code == 2, result
    assert "Traceback" not in result.err
    assert result.err_lines[-1].startswith("echoloc: error: silent.h5: only 0 working receiver"), result.err
    assert not (in_tmp / "i.png").exists()


def test_messages_name_the_real_problem(
    capsys: pytest.CaptureFixture[str], in_tmp: Path, good_h5: Path
) -> None:
    """Where a message named the wrong thing: a directory given as a recording, a file where
    an output's directory should be, a non-HDF5 stream recording, a zero carrier, a zero waveform."""
    (in_tmp / "folder").mkdir()
    assert_bad_input(run(capsys, "echoes", "folder"), "folder", "is a directory")
    shutil.copy(good_h5, in_tmp / "good.h5")
    assert_bad_input(
        run(capsys, "simulate", SCENES / "report-three-balls.toml", "-o", "good.h5/x.h5", "--frames", "1"),
        "'good.h5' is not a directory",
    )
    result = run(capsys, "record", "r.txt", "--duration", "1")
    assert_bad_input(result, "r.txt", "HDF5")
    assert ".npz" not in result.err
    scene = (SCENES / "report-three-balls.toml").read_text()
    (in_tmp / "zero.toml").write_text(re.sub(r"carrier_hz\s*=\s*[0-9.e]+", "carrier_hz = 0", scene))
    assert_bad_input(run(capsys, "simulate", "zero.toml", "-o", "z.h5"), "zero.toml", "pulse.carrier_hz")

    def zero_waveform(attrs: dict[str, Any], data: dict[str, Any]) -> None:
        data["waveform"][:] = 0.0

    broken_copy(good_h5, in_tmp / "flat.h5", zero_waveform)
    assert_bad_input(run(capsys, "echoes", "flat.h5"), "flat.h5", "waveform is all zero")
    # An OS error names its file, not only its errno text.
    assert_bad_input(run(capsys, "image", "good.h5", "-o", "nodir/i.png"), "nodir/i.png: No such file")


@pytest.mark.filterwarnings("always::echoloc.io.recording.RecordingWarning")
def test_a_template_cut_from_a_dead_receiver_names_it(
    capsys: pytest.CaptureFixture[str], in_tmp: Path, dead_h5: Path
) -> None:
    result = run(capsys, "template", dead_h5, "--receiver", "2", "-o", "t.npz")
    assert result.code == 2, result
    assert result.err_lines[-1].endswith("receiver 2 is all zero in the template window (a dead receiver?)")
    assert not (in_tmp / "t.npz").exists()


def test_stream_reads_its_calibration_before_listening(
    capsys: pytest.CaptureFixture[str], in_tmp: Path
) -> None:
    """A missing calibration file fails at once, not when the first frame arrives (before, with
    no sender, `stream` even exited 0)."""
    result = run(
        capsys, "stream", "--listen", "127.0.0.1:0", "--calibration", "missing.json", "--duration", "1"
    )
    assert_bad_input(result, "missing.json", "no such calibration file")


def test_library_refuses_times_no_float_or_ros_time_holds() -> None:
    """The checks below the CLI's own: a stamp of 1e300 s (its nanoseconds overflow an int) or
    NaN, and a NaN or negative template arrival."""
    from echoloc.errors import EchoLocError
    from echoloc.io.export import ros_time
    from echoloc.tof.templates import arrival_time_s

    assert ros_time(1.5) == {"sec": 1, "nanosec": 500_000_000}
    for stamp in (1e300, math.nan, math.inf, 2.0**31):
        with pytest.raises(EchoLocError, match="does not fit a ROS time"):
            ros_time(stamp)
    recording = simulate(default_scene(), n_frames=1)
    assert arrival_time_s(recording, 0, 0, 1e-3, 343.0) == 1e-3
    for arrival in (math.nan, -1e-3):
        with pytest.raises(EchoLocError, match="arrival must be a finite time"):
            arrival_time_s(recording, 0, 0, arrival, 343.0)


def test_sigterm_removes_a_half_written_recording_and_keeps_the_old_one(in_tmp: Path, good_h5: Path) -> None:
    """`kill` (SIGTERM) mid-simulate: as Ctrl-C, the temporary file goes and the file that was
    there stays, bit for bit (before, the temporary file stayed: 2.7 GB in one run)."""
    import signal
    import time

    target = in_tmp / "keep.h5"
    shutil.copy(good_h5, target)
    before = target.read_bytes()
    scene = SCENES / "report-three-balls.toml"
    process = subprocess.Popen(
        [str(ECHOLOC), "simulate", str(scene), "--frames", "200000", "-o", str(target)],
        cwd=in_tmp,
        env=_clean_env(),
        stderr=subprocess.PIPE,
        text=True,
    )
    deadline = time.monotonic() + 60
    while not list(in_tmp.glob(".keep.h5.*.tmp")):  # writing has started
        assert process.poll() is None, process.communicate()
        assert time.monotonic() < deadline, "no temporary file after 60 s"
        time.sleep(0.05)
    process.send_signal(signal.SIGTERM)
    try:
        _, err = process.communicate(timeout=60)
    except subprocess.TimeoutExpired:
        process.kill()
        _, err = process.communicate()
        pytest.fail(f"simulate ran on for 60 s after SIGTERM: {err[-2000:]}")
    assert process.returncode == 1, err
    assert "Traceback" not in err
    assert err.strip().endswith("echoloc: aborted"), err
    assert list(in_tmp.glob(".keep.h5.*")) == []
    assert target.read_bytes() == before


@pytest.mark.parametrize("sigint", ["handled", "ignored"])
def test_an_interrupt_a_finaliser_swallowed_is_raised_again(sigint: str) -> None:
    """Python swallows a KeyboardInterrupt raised inside a ``__del__`` or weakref callback
    (h5py runs them all the time): a killed simulate ran on for minutes. Under the CLI's
    handler it is raised again in the main thread, at once, and nothing is printed; also
    when the parent made SIGINT ignored (the SIGTERM handler raises it then)."""
    import gc
    import signal
    import time

    from echoloc.cli.app import _interrupt_cleanly

    class InterruptedFinaliser:
        def __del__(self) -> None:
            raise KeyboardInterrupt  # as the signal handler does when SIGTERM lands here

    def work_that_meets_the_finaliser() -> None:
        InterruptedFinaliser()  # finalised at once: the interrupt is swallowed
        gc.collect()
        while time.monotonic() - started < 10:  # the command's work, carrying on
            time.sleep(0.001)

    parent_wish = signal.SIG_IGN if sigint == "ignored" else signal.default_int_handler
    before = signal.signal(signal.SIGINT, parent_wish)
    try:
        started = time.monotonic()
        with _interrupt_cleanly(), pytest.raises(KeyboardInterrupt):
            work_that_meets_the_finaliser()
        assert time.monotonic() - started < 5
    finally:
        signal.signal(signal.SIGINT, before)


def test_echoloc_alone_shows_its_help(capsys: pytest.CaptureFixture[str]) -> None:
    """``echoloc`` without a command is a request for help, as ``--help``, not an error
    (click 8.2 raises it as a usage error, which read "echoloc: error: Usage: ...")."""
    bare = run(capsys)
    assert bare == run(capsys, "--help")
    assert bare.code == 0
    assert bare.err == ""
    assert bare.out.startswith("Usage: echoloc [OPTIONS] COMMAND")
    assert "locate" in bare.out


def test_python_dash_m_echoloc_is_the_command() -> None:
    """``python -m echoloc`` runs the command (robots often have several Pythons)."""
    done = subprocess.run(
        [sys.executable, "-m", "echoloc", "--version"], capture_output=True, text=True, env=_clean_env()
    )
    assert (done.returncode, done.stdout.strip(), done.stderr) == (0, "echoloc, version 0.1.0", "")


def test_a_signal_the_parent_ignores_stays_ignored() -> None:
    """A background job's SIGINT (or nohup's) is ignored by the parent's wish: the CLI's
    handler takes SIGTERM and leaves that SIGINT alone, and restores both after."""
    import signal

    from echoloc.cli.app import _interrupt_cleanly

    before = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        term_before = signal.getsignal(signal.SIGTERM)
        with _interrupt_cleanly():
            assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
            assert signal.getsignal(signal.SIGTERM) not in (term_before, signal.SIG_IGN, signal.SIG_DFL)
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        assert signal.getsignal(signal.SIGTERM) is term_before
    finally:
        signal.signal(signal.SIGINT, before)


@pytest.mark.filterwarnings("always::echoloc.io.recording.RecordingWarning")
def test_recordings_no_echo_can_be_located_in_are_said_so(
    capsys: pytest.CaptureFixture[str], in_tmp: Path, good_h5: Path
) -> None:
    """Receivers all at one point (the same foci for every ellipsoid) is bad input for
    locate; frames shorter than the pulse are read, with a warning that no echo fits."""

    def same_point(attrs: dict[str, Any], data: dict[str, Any]) -> None:
        data["receivers"][:] = data["receivers"][0]

    broken_copy(good_h5, in_tmp / "one.h5", same_point)
    assert_bad_input(run(capsys, "locate", "one.h5"), "one.h5", "every working receiver is at")

    def short_frames(attrs: dict[str, Any], data: dict[str, Any]) -> None:
        data["frames"] = data["frames"][:, :, :50]

    broken_copy(good_h5, in_tmp / "short.h5", short_frames)
    result = run(capsys, "echoes", "short.h5", "--json")
    assert result.code == 0, result
    assert "shorter than the" in result.err, result.err


@pytest.mark.filterwarnings("always::echoloc.localise.locate.LocateWarning")
def test_a_speed_of_sound_in_other_units_is_warned_about(
    capsys: pytest.CaptureFixture[str], good_h5: Path
) -> None:
    """0.343 (m/ms) is a valid number but no gas's speed in m/s: the run goes on, warned."""
    result = run(capsys, "locate", good_h5, "--json", "--speed-of-sound", "0.343")
    assert result.code == 0, result
    assert "0.343 m/s is far from any gas's" in result.err, result.err
    result = run(capsys, "locate", good_h5, "--json", "--speed-of-sound", "343.2")
    assert result.code == 0, result
    assert "warning" not in result.err, result.err
