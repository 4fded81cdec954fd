"""Tests of ``echoloc import`` and :mod:`echoloc.io.importers`.

The SPiEL fixtures are built from ``/work/shared/data/ch101-spiel/dev.h5``, a
conversion of the real CH101 data set published with

    C. Hahne, "3-Dimensional Sonic Phase-invariant Echo Localization", ICRA 2023,
    pp. 4121-4127, doi:10.1109/ICRA48891.2023.10161199 (github:hahnec/spiel, folder
    ``dataset/``; Apache-2.0).

A few of its frames are written back into the data set's CSV layout (with the two
trailing columns the published loader drops) and imported; the result must equal
dev.h5 bit for bit. Every refusal must exit 2 with one line on stderr naming the file
and no traceback (docs/FORMATS.md, "Exit codes").
"""

from __future__ import annotations

import dataclasses
import os
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from echoloc.cli import commands as cli
from echoloc.errors import EchoLocError
from echoloc.io.importers import (
    SPIEL_HEAD,
    TruthSpan,
    natural_sort_key,
    parse_head,
    parse_table,
    read_spiel,
    truth_positions_m,
)
from echoloc.io.recording import read_recording

DEV_H5 = Path("/work/shared/data/ch101-spiel/dev.h5")
ECHOLOC = Path(sys.executable).parent / "echoloc"

# Frames of dev.h5 written as SPiEL files, in the order natural sort must give back:
# names starting with a digit sort before those starting with "-", 90 before 220, and
# the index _3_10 after _3_9 (plain string order would put it after _3_1).
FIXTURE: list[tuple[str, int]] = [
    ("0.0mm_0.0mm_90.0mm_1_0", 395),
    ("0.0mm_0.0mm_220.0mm_1_0", 355),
    *((f"-40.0mm_0.0mm_100.0mm_3_{b}", 40 + b) for b in range(12)),
]

needs_dev = pytest.mark.skipif(not DEV_H5.is_file(), reason=f"{DEV_H5} is not available")


# ----------------------------------------------------------------------------- helpers


@dataclasses.dataclass(frozen=True)
class Result:
    code: int
    out: str
    err: str


def run(capsys: pytest.CaptureFixture[str], *args: object) -> Result:
    """Run ``echoloc ARGS`` in-process; main() always ends with SystemExit."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as info:
        cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    code = info.value.code
    assert isinstance(code, int)
    return Result(code, out, err)


def assert_refused(result: Result, *names: str) -> None:
    """Exit 2, one line on stderr naming every one of ``names``, no traceback."""
    assert result.code == 2, result
    lines = result.err.splitlines()
    assert len(lines) == 1, result.err
    assert lines[0].startswith("echoloc: error: "), lines[0]
    assert "Traceback" not in result.err
    for name in names:
        assert name in lines[0], (name, lines[0])


@pytest.fixture(scope="module")
def dev() -> dict[str, np.ndarray]:
    if not DEV_H5.is_file():
        pytest.skip(f"{DEV_H5} is not available")
    with h5py.File(DEV_H5, "r") as f:
        return {name: f[name][()] for name in f}


def _label_rows(position_m: np.ndarray) -> np.ndarray:
    """A labels table: channel, a chip range (mm), a chip amplitude, target x, y, z (mm)."""
    position_mm = np.array([float(f"{v * 1000:.1f}") for v in position_m])  # the grid's mm
    return np.column_stack(
        [
            np.arange(4.0),
            [219.6, 214.3, 252.9, 246.4],
            [921.0, 1105.0, 540.0, 967.0],
            np.tile(position_mm, (4, 1)),
        ]
    )


def write_spiel(
    root: Path, dev: dict[str, np.ndarray], fixture: list[tuple[str, int]] = FIXTURE, background: bool = True
) -> Path:
    """Write dev.h5 frames as ``root/train_val`` (+ ``train_val_bg``) in the SPiEL layout."""
    folder = root / "train_val"
    folder.mkdir()
    targets = [(folder, dev["frames"])]
    if background:
        (root / "train_val_bg").mkdir()
        targets.append((root / "train_val_bg", dev["background"]))
    for stem, index in fixture:
        for where, samples in targets:
            extra = np.array([[11, 12], [13, 14], [15, 16], [17, 18]])  # what the loader drops
            rows = np.concatenate([samples[index].astype(np.int64), extra], axis=1)
            np.savetxt(where / f"{stem}_frames.csv", rows, fmt="%d")
            np.savetxt(where / f"{stem}_labels.csv", _label_rows(dev["truth_positions"][index, 0]))
    return folder


@pytest.fixture
def spiel(tmp_path: Path, dev: dict[str, np.ndarray]) -> Path:
    return write_spiel(tmp_path, dev)


# ----------------------------------------------------------------------------- SPiEL layout


@needs_dev
def test_spiel_import_equals_dev_h5_bit_for_bit(
    capsys: pytest.CaptureFixture[str], spiel: Path, dev: dict[str, np.ndarray], tmp_path: Path
) -> None:
    out = tmp_path / "out.h5"
    result = run(capsys, "import", "spiel", spiel, "-o", out)
    assert result.code == 0, result.err
    assert result.out == ""
    assert f"wrote {out}" in result.err
    assert "14 frame(s)" in result.err
    order = [index for _, index in FIXTURE]
    with h5py.File(out, "r") as got, h5py.File(DEV_H5, "r") as want:
        for name in ("frames", "background", "truth_positions"):
            assert got[name].dtype == want[name].dtype, name
            assert got[name][()].tobytes() == want[name][()][order].tobytes(), name
        for name in ("receivers", "transmitters"):
            assert got[name].dtype == want[name].dtype
            assert got[name][()].tobytes() == want[name][()].tobytes(), name
        for name in ("sample_rate_hz", "signal_kind", "carrier_hz", "format", "version"):
            assert got.attrs[name] == want.attrs[name], name
    recording = read_recording(out)
    assert recording.n_frames == len(FIXTURE)
    assert recording.waveform is None


@needs_dev
def test_spiel_head_override_reproduces_dev_h5_attributes(
    capsys: pytest.CaptureFixture[str], spiel: Path, tmp_path: Path
) -> None:
    head = tmp_path / "head.toml"
    head.write_text("speed_of_sound_m_s = 343.0\n")
    out = tmp_path / "out.h5"
    assert run(capsys, "import", "spiel", spiel, "-o", out, "--head", head).code == 0
    with h5py.File(out, "r") as got, h5py.File(DEV_H5, "r") as want:
        assert dict(got.attrs) == dict(want.attrs)


@needs_dev
def test_spiel_head_override_moves_receivers(spiel: Path, tmp_path: Path) -> None:
    receivers = [[0.0, 0.0, 0.0], [-0.04, -0.07, 0.0], [0.08, 0.0, 0.0], [-0.04, 0.07, 0.0]]
    head = parse_head({"receivers": receivers, "sample_rate_hz": 20000}, "head.toml", tmp_path)
    recording = read_spiel(spiel, head)
    np.testing.assert_array_equal(recording.receivers_m, receivers)
    assert recording.sample_rate_hz == 20000.0
    assert recording.carrier_hz == SPIEL_HEAD.carrier_hz


@needs_dev
def test_spiel_samples_option_and_missing_background_folder(
    tmp_path: Path, dev: dict[str, np.ndarray]
) -> None:
    folder = write_spiel(tmp_path, dev, FIXTURE[:2], background=False)
    whole = read_spiel(folder, n_samples=64)
    assert whole.background is None
    assert whole.n_samples == 64
    np.testing.assert_array_equal(whole.frames[0, :, 62:], [[11, 12], [13, 14], [15, 16], [17, 18]])
    assert read_spiel(folder, n_samples=10).n_samples == 10
    assert read_spiel(folder).n_samples == 62


@needs_dev
def test_spiel_refuses_more_samples_than_a_line_holds(
    capsys: pytest.CaptureFixture[str], spiel: Path, tmp_path: Path
) -> None:
    assert_refused(
        run(capsys, "import", "spiel", spiel, "-o", tmp_path / "o.h5", "--samples", 65), "train_val", "65"
    )


@needs_dev
def test_output_is_not_overwritten_without_force(
    capsys: pytest.CaptureFixture[str], spiel: Path, tmp_path: Path
) -> None:
    out = tmp_path / "out.h5"
    out.write_bytes(b"precious")
    assert_refused(run(capsys, "import", "spiel", spiel, "-o", out), str(out), "--force")
    assert out.read_bytes() == b"precious"
    assert run(capsys, "import", "spiel", spiel, "-o", out, "--force").code == 0
    assert read_recording(out).n_frames == len(FIXTURE)


def _break(folder: Path, name: str, text: str) -> Path:
    path = folder / name
    path.write_text(text)
    return path


FIRST = FIXTURE[0][0]
SECOND = FIXTURE[1][0]


def _replace_line(path: Path, line: int, text: str) -> None:
    lines = path.read_text().splitlines()
    lines[line] = text
    path.write_text("\n".join(lines) + "\n")


BROKEN_SPIEL = {
    "no labels": lambda f: ((f / f"{FIRST}_labels.csv").unlink(), f"{FIRST}_frames.csv")[1],
    "no frames": lambda f: ((f / f"{FIRST}_frames.csv").unlink(), f"{FIRST}_labels.csv")[1],
    "ragged row": lambda f: (_replace_line(f / f"{FIRST}_frames.csv", 2, "1 2 3"), "ragged")[1],
    "non-numeric": lambda f: (_replace_line(f / f"{FIRST}_frames.csv", 1, "1 2 x3" + " 4" * 61), "'x3'")[1],
    "nan": lambda f: (_replace_line(f / f"{FIRST}_frames.csv", 0, "nan" + " 4" * 63), "not finite")[1],
    "three channels": lambda f: (
        (f / f"{FIRST}_frames.csv").write_text(
            "\n".join((f / f"{FIRST}_frames.csv").read_text().split("\n")[:3])
        ),
        "3 channel lines",
    )[1],
    "short line in another file": lambda f: (
        _break(f, f"{SECOND}_frames.csv", ("1 " * 63 + "\n") * 4),
        f"{SECOND}_frames.csv",
    )[1],
    "labels of 5 columns": lambda f: (
        _break(f, f"{FIRST}_labels.csv", "0 1 2 3 4\n1 1 2 3 4\n2 1 2 3 4\n3 1 2 3 4\n"),
        "expected 6",
    )[1],
    "labels of 3 channels": lambda f: (
        _break(f, f"{FIRST}_labels.csv", "0 1 2 0 0 90\n1 1 2 0 0 90\n2 1 2 0 0 90\n"),
        f"{FIRST}_labels.csv",
    )[1],
    "labels channel order": lambda f: (
        _break(f, f"{FIRST}_labels.csv", "0 1 2 0 0 90\n2 1 2 0 0 90\n1 1 2 0 0 90\n3 1 2 0 0 90\n"),
        "channel 2",
    )[1],
    "labels disagree": lambda f: (
        _break(f, f"{FIRST}_labels.csv", "0 1 2 0 0 90\n1 1 2 0 0 90\n2 1 2 0 0 91\n3 1 2 0 0 90\n"),
        "line 3",
    )[1],
    "labels against name": lambda f: (
        _break(f, f"{FIRST}_labels.csv", "0 1 2 0 0 95\n1 1 2 0 0 95\n2 1 2 0 0 95\n3 1 2 0 0 95\n"),
        "file name",
    )[1],
    "missing background": lambda f: (
        (f.parent / "train_val_bg" / f"{SECOND}_frames.csv").unlink(),
        f"train_val_bg/{SECOND}_frames.csv",
    )[1],
    "negative envelope": lambda f: (
        _replace_line(f / f"{FIRST}_frames.csv", 0, "-5" + " 4" * 63),
        "negative",
    )[1],
    "empty folder": lambda f: ([p.unlink() for p in f.iterdir()], "no *_frames.csv")[1],
}


@needs_dev
@pytest.mark.parametrize("case", sorted(BROKEN_SPIEL))
def test_broken_spiel_input_is_refused_in_one_line(
    case: str, capsys: pytest.CaptureFixture[str], spiel: Path, tmp_path: Path
) -> None:
    expected = BROKEN_SPIEL[case](spiel)
    out = tmp_path / "out.h5"
    assert_refused(run(capsys, "import", "spiel", spiel, "-o", out), expected)
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.endswith(".tmp")]


def test_missing_folder_and_bad_output_are_refused(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    assert_refused(
        run(capsys, "import", "spiel", tmp_path / "nope", "-o", tmp_path / "o.h5"), "nope", "no such"
    )
    assert_refused(run(capsys, "import", "spiel", tmp_path, "-o", tmp_path / "o.txt"), "o.txt", "extension")
    assert_refused(run(capsys, "import", "spiel", tmp_path, "-o", tmp_path / "d" / "o.h5"), "does not exist")
    assert_refused(run(capsys, "import", "spiel"), "FOLDER")
    assert_refused(run(capsys, "import", "samples", tmp_path / "x.npy", "-o", tmp_path / "o.h5"), "--head")


@needs_dev
@pytest.mark.parametrize(
    ("toml", "expected"),
    [
        ("colour = 'red'\n", "unknown key 'colour'"),
        ("background = 'bg.npy'\n", "background is not used"),
        ("[[truth]]\nframes = 0\nposition_m = [0, 0, 0.1]\n", "truth is not used"),
        ("receivers = [[0, 0, 0]]\n", "3 channel lines, expected 1"),
        ("sample_rate_hz = -1\n", "sample_rate_hz must be > 0"),
        ("sample_rate_hz = \n", "not valid TOML"),
    ],
)
def test_bad_spiel_head_is_refused(
    toml: str, expected: str, capsys: pytest.CaptureFixture[str], spiel: Path, tmp_path: Path
) -> None:
    head = tmp_path / "head.toml"
    head.write_text(toml)
    result = run(capsys, "import", "spiel", spiel, "-o", tmp_path / "o.h5", "--head", head)
    if "channel lines" in expected:
        assert_refused(result, "train_val", "4 channel lines, expected 1")
    else:
        assert_refused(result, "head.toml", expected)


# ----------------------------------------------------------------------------- natural sort


def test_natural_sort_examples() -> None:
    names = ["a_10", "a_2", "a_1", "b", "a_02", "-40.0mm_1", "0.0mm_1", "0.0mm_10", "0.0mm_9"]
    assert sorted(names, key=natural_sort_key) == [
        "0.0mm_1",
        "0.0mm_9",
        "0.0mm_10",
        "-40.0mm_1",
        "a_1",
        "a_02",
        "a_2",
        "a_10",
        "b",
    ]


@given(st.lists(st.integers(0, 10**6), max_size=30), st.sampled_from(["f_", "x1y_", ""]))
def test_natural_sort_orders_numbers_by_value(numbers: list[int], prefix: str) -> None:
    names = [f"{prefix}{n}_frames.csv" for n in numbers]
    assert [name for name in sorted(names, key=natural_sort_key)] == [
        f"{prefix}{n}_frames.csv" for n in sorted(numbers)
    ]


@given(st.lists(st.text(alphabet="ab-_.0123456789", max_size=12), max_size=20))
def test_natural_sort_key_orders_any_names(names: list[str]) -> None:
    ordered = sorted(names, key=natural_sort_key)  # never mixes str and int in one position
    assert sorted(ordered) == sorted(names)


# ----------------------------------------------------------------------------- text tables


@settings(max_examples=50)
@given(
    arrays(np.float64, st.tuples(st.integers(1, 6), st.integers(1, 6)), elements=st.floats(-1e9, 1e9)),
    st.sampled_from([",", " ", "\t"]),
)
def test_parse_table_round_trips_exactly(values: np.ndarray, separator: str) -> None:
    text = "# a comment\n\n" + "\n".join(separator.join(repr(float(v)) for v in row) for row in values)
    delimiter = "," if separator == "," else None
    np.testing.assert_array_equal(parse_table(text, "t.csv", delimiter=delimiter), values)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("", "holds no rows"),
        ("1,2\n3\n", "line 2 has 1 values but line 1 has 2"),
        ("1,2\n3,\n", "line 2, column 2: an empty cell"),
        ("1,2\n3,inf\n", "line 2, column 2: 'inf' is not finite"),
        ("1,two\n", "line 1, column 2: 'two', not a number"),
    ],
)
def test_parse_table_refuses(text: str, expected: str) -> None:
    with pytest.raises(EchoLocError, match=expected) as info:
        parse_table(text, "t.csv", delimiter=",")
    assert str(info.value).startswith("t.csv: ")


# ----------------------------------------------------------------------------- samples layout

HEAD = """\
sample_rate_hz = 200000
signal_kind = "envelope"
carrier_hz = 40000.0
transmitters = [[0.0, 0.0, 0.0]]
receivers = [[-0.01, 0.0, 0.0], [0.01, 0.0, 0.0]]
temperature_c = 21.5
relative_humidity = 0.4
"""


def _samples(n_frames: int = 5, n_rx: int = 2, n_samples: int = 7, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).uniform(0.0, 3.0, (n_frames, n_rx, n_samples))


def test_samples_npy_round_trip_with_truth_and_background(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    samples = _samples()
    np.save(tmp_path / "samples.npy", samples)
    np.save(tmp_path / "bg.npy", samples[0])
    (tmp_path / "head.toml").write_text(
        HEAD
        + 'background = "bg.npy"\n'
        + "[[truth]]\nframes = '0:3'\nposition_m = [0.0, 0.0, 0.5]\n"
        + "[[truth]]\nframes = '2:'\nposition_m = [0.1, 0.0, 0.4]\n"
    )
    out = tmp_path / "out.h5"
    result = run(
        capsys, "import", "samples", tmp_path / "samples.npy", "--head", tmp_path / "head.toml", "-o", out
    )
    assert result.code == 0, result.err
    assert "one background" in result.err
    assert "truth for 5 frame(s)" in result.err
    recording = read_recording(out)
    np.testing.assert_array_equal(recording.frames, samples)
    np.testing.assert_array_equal(recording.background, samples[0])
    assert recording.sample_rate_hz == 200000.0
    assert recording.signal_kind == "envelope"
    assert (recording.carrier_hz, recording.temperature_c, recording.relative_humidity) == (
        40000.0,
        21.5,
        0.4,
    )
    np.testing.assert_array_equal(recording.receivers_m, [[-0.01, 0, 0], [0.01, 0, 0]])
    truth = recording.truth_positions_m
    assert truth is not None
    assert truth.shape == (5, 2, 3)
    np.testing.assert_array_equal(truth[0], [[0, 0, 0.5], [np.nan] * 3])
    np.testing.assert_array_equal(truth[2], [[0, 0, 0.5], [0.1, 0, 0.4]])
    np.testing.assert_array_equal(truth[4], [[0.1, 0, 0.4], [np.nan] * 3])


@settings(max_examples=25, deadline=None)
@given(
    st.integers(1, 4),
    st.integers(1, 3),
    st.integers(1, 9),
    st.sampled_from([",", " "]),
    st.booleans(),
)
def test_samples_csv_round_trip(
    n_frames: int, n_rx: int, n_samples: int, separator: str, whole: bool
) -> None:
    import tempfile

    samples = _samples(n_frames, n_rx, n_samples, seed=n_frames * 100 + n_rx * 10 + n_samples)
    if whole:
        samples = np.round(samples * 1000)
    receivers = ", ".join(f"[{0.01 * k}, 0.0, 0.0]" for k in range(n_rx))
    with tempfile.TemporaryDirectory() as name:
        root = Path(name)
        table = samples.reshape(n_frames * n_rx, n_samples)
        (root / "s.csv").write_text(
            "\n".join(separator.join(repr(float(v)) for v in row) for row in table) + "\n"
        )
        (root / "h.toml").write_text(
            'sample_rate_hz = 1e5\nsignal_kind = "envelope"\ntransmitters = [[0, 0, 0]]\n'
            f"receivers = [{receivers}]\n"
        )
        with pytest.raises(SystemExit) as info:
            cli.main(
                [
                    "import",
                    "samples",
                    str(root / "s.csv"),
                    "--head",
                    str(root / "h.toml"),
                    "-o",
                    str(root / "o.h5"),
                ]
            )
        assert info.value.code == 0
        recording = read_recording(root / "o.h5")
        np.testing.assert_array_equal(recording.frames, samples)
        with h5py.File(root / "o.h5", "r") as f:
            assert f["frames"].dtype == (np.float32 if whole else np.float64)


def test_samples_rf_with_waveform_and_iq(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rf = np.random.default_rng(1).normal(size=(3, 2, 16))
    np.save(tmp_path / "rf.npy", rf.astype(np.float32))
    (tmp_path / "w.csv").write_text("0.0\n1.0\n-1.0\n0.5\n")
    rf_head = HEAD.replace('"envelope"', '"rf"') + 'waveform = "w.csv"\n'
    (tmp_path / "rf.toml").write_text(rf_head)
    assert (
        run(
            capsys,
            "import",
            "samples",
            tmp_path / "rf.npy",
            "--head",
            tmp_path / "rf.toml",
            "-o",
            tmp_path / "rf.h5",
        ).code
        == 0
    )
    recording = read_recording(tmp_path / "rf.h5")
    np.testing.assert_array_equal(recording.waveform, [0.0, 1.0, -1.0, 0.5])
    np.testing.assert_array_equal(recording.frames, rf.astype(np.float32))

    iq = (rf + 1j * rf[::-1]).astype(np.complex64)
    np.save(tmp_path / "iq.npy", iq)
    (tmp_path / "iq.toml").write_text(rf_head.replace('"rf"', '"iq"').replace('"w.csv"', '"w.npy"'))
    np.save(tmp_path / "w.npy", np.array([1.0 + 0j, 0.5j]))
    assert (
        run(
            capsys,
            "import",
            "samples",
            tmp_path / "iq.npy",
            "--head",
            tmp_path / "iq.toml",
            "-o",
            tmp_path / "iq.h5",
        ).code
        == 0
    )
    np.testing.assert_array_equal(read_recording(tmp_path / "iq.h5").frames, iq)


def test_truth_positions_from_spans() -> None:
    spans = [TruthSpan(0, 2, (0.0, 0.0, 1.0)), TruthSpan(3, None, (1.0, 0.0, 0.0))]
    truth = truth_positions_m(spans, 4, "h.toml")
    assert truth is not None
    np.testing.assert_array_equal(truth[:, 0], [[0, 0, 1], [0, 0, 1], [np.nan] * 3, [1, 0, 0]])
    assert truth_positions_m([], 4, "h.toml") is None
    with pytest.raises(EchoLocError, match=r"h.toml: truth\[0\].frames '2:9' is outside the 4 frames"):
        truth_positions_m([TruthSpan(2, 9, (0.0, 0.0, 1.0))], 4, "h.toml")


def _write_samples_case(tmp_path: Path, case: str) -> tuple[Path, str]:
    """Set up one broken `import samples` input; returns the samples file and the expected text."""
    samples = _samples()
    data = tmp_path / "samples.npy"
    np.save(data, samples)
    head = HEAD
    expected = {
        "unknown key": "unknown key 'sample_rate'",
        "unknown truth key": "unknown key truth[0].where",
        "missing key": "missing key 'receivers'",
        "bad kind": "signal_kind must be one of",
        "bad receivers": "receivers[1] must be [x, y, z]",
        "truth outside": "truth[0].frames '7:9' is outside the 5 frames",
        "bad frames text": "truth[0].frames must be a frame index",
        "wrong channel count": "3 channels but the head has 2 receivers",
        "nan in npy": "NaN or infinite",
        "string npy": "expected numbers",
        "complex for envelope": "complex samples",
        "rows not a multiple": "5 rows, not a multiple of the head's 2 receivers",
        "missing samples file": "no such file",
        "missing background": "no such file",
        "background frame count": "holds 3 background frames but samples.npy holds 5",
        "background samples": "has 6 samples a channel but samples.npy has 7",
        "negative envelope": "negative",
        "iq from csv": "give them as a .npy",
        "rf without waveform": "waveform is missing",
        "not a npy": "not a readable .npy",
    }[case]
    if case == "unknown key":
        head = head.replace("sample_rate_hz", "sample_rate")
    elif case == "unknown truth key":
        head += "[[truth]]\nframes = 0\nposition_m = [0, 0, 1]\nwhere = 'here'\n"
    elif case == "missing key":
        head = "\n".join(line for line in head.splitlines() if not line.startswith("receivers"))
    elif case == "bad kind":
        head = head.replace('"envelope"', '"magnitude"')
    elif case == "bad receivers":
        head = head.replace("[0.01, 0.0, 0.0]", "[0.01, 0.0]")
    elif case == "truth outside":
        head += "[[truth]]\nframes = '7:9'\nposition_m = [0, 0, 1]\n"
    elif case == "bad frames text":
        head += "[[truth]]\nframes = 'a:b'\nposition_m = [0, 0, 1]\n"
    elif case == "wrong channel count":
        np.save(data, _samples(n_rx=3))
    elif case == "nan in npy":
        samples[1, 1, 1] = np.nan
        np.save(data, samples)
    elif case == "string npy":
        np.save(data, np.array([["a", "b"]]))
    elif case == "complex for envelope":
        np.save(data, samples.astype(np.complex128))
    elif case == "rows not a multiple":
        data = tmp_path / "samples.csv"
        data.write_text("1,2\n" * 5)
    elif case == "missing samples file":
        data = tmp_path / "gone.npy"
    elif case == "missing background":
        head += 'background = "nothere.npy"\n'
    elif case == "background frame count":
        np.save(tmp_path / "bg.npy", samples[:3])
        head += 'background = "bg.npy"\n'
    elif case == "background samples":
        np.save(tmp_path / "bg.npy", samples[0, :, :6])
        head += 'background = "bg.npy"\n'
    elif case == "negative envelope":
        np.save(data, samples - 1.0)
    elif case == "iq from csv":
        data = tmp_path / "samples.csv"
        data.write_text("1,2\n")
        head = head.replace('"envelope"', '"iq"')
    elif case == "rf without waveform":
        head = head.replace('"envelope"', '"rf"')
    elif case == "not a npy":
        data.write_bytes(b"not numpy at all")
    (tmp_path / "head.toml").write_text(head)
    return data, expected


SAMPLES_CASES = [
    "unknown key",
    "unknown truth key",
    "missing key",
    "bad kind",
    "bad receivers",
    "truth outside",
    "bad frames text",
    "wrong channel count",
    "nan in npy",
    "string npy",
    "complex for envelope",
    "rows not a multiple",
    "missing samples file",
    "missing background",
    "background frame count",
    "background samples",
    "negative envelope",
    "iq from csv",
    "rf without waveform",
    "not a npy",
]


@pytest.mark.parametrize("case", SAMPLES_CASES)
def test_broken_samples_input_is_refused_in_one_line(
    case: str, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    data, expected = _write_samples_case(tmp_path, case)
    out = tmp_path / "out.h5"
    result = run(capsys, "import", "samples", data, "--head", tmp_path / "head.toml", "-o", out)
    assert_refused(result, expected)
    assert not out.exists()


def test_a_refusal_through_the_console_script_has_no_traceback(tmp_path: Path) -> None:
    (tmp_path / "head.toml").write_text(HEAD + "mystery = 1\n")
    np.save(tmp_path / "s.npy", _samples())
    env = {k: v for k, v in os.environ.items() if k not in ("COLUMNS", "FORCE_COLOR")}
    completed = subprocess.run(
        [str(ECHOLOC), "import", "samples", "s.npy", "--head", "head.toml", "-o", "o.h5"],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        env=env,
        timeout=60,
        check=False,
    )
    assert completed.returncode == 2
    assert completed.stdout == ""
    assert completed.stderr.splitlines() == [
        "echoloc: error: head.toml: unknown key 'mystery' (known: sample_rate_hz, signal_kind, "
        "carrier_hz, transmitters, receivers, speed_of_sound_m_s, temperature_c, relative_humidity, "
        "background, waveform, truth)"
    ]
