"""`echoloc sweep`: the table does not depend on the workers, and its figures follow the physics.

One LocalCluster of two worker processes serves the module (:func:`client`); the
command-line run starts its own of one worker. The closed forms checked:

- the time of flight's Cramér-Rao bound falls as 1/amplitude SNR (``sigma_tau = 1 /
  (beta sqrt(2 E / N0))``): 20 dB more amplitude SNR, a spread ten times smaller;
- with a known random error sigma on every path, the position's covariance is
  ``sigma^2 (J^T J)^-1`` to first order (:func:`echoloc.localise.uncertainty.position_errors`,
  the GDOP behind ``echoloc design``): the angle error of the report's cross falls with
  its spacing as that says.
"""

from __future__ import annotations

import copy
import csv
import io
import itertools
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from echoloc.cli.commands import main
from echoloc.localise.uncertainty import position_errors
from echoloc.scale.sweep import (
    ArrayLayout,
    SweepError,
    cell,
    csv_text,
    layout_receivers,
    load_sweep,
    points_per_task,
    run_sweep,
    run_sweep_serial,
    sweep_from_dict,
)
from repo_paths import REPO

distributed = pytest.importorskip("distributed")

# A frame of 8 ms (2.7 m of path) is plenty for a reflector half a metre ahead.
ONE_BALL: dict[str, Any] = {
    "acquisition": {"n_samples": 1600},
    "noise": {"snr_db": 20.0},
    "reflectors": [{"position_m": [0.03, -0.02, 0.5]}],
}
DETERMINISTIC = ["median_error_m", "rms_error_m", "spread_m", "recall", "false_rate", "sigma_ratio"]


@pytest.fixture(scope="module")
def client() -> Iterator[Any]:
    from echoloc.scale.cluster import open_client

    with open_client(workers=2) as running:
        yield running


def _sweep(**changes: Any) -> dict[str, Any]:
    data: dict[str, Any] = {
        "scene": copy.deepcopy(ONE_BALL),
        "frames": 6,
        "seed": 3,
        "metrics": DETERMINISTIC,
        "grid": {"noise": {"snr_db": [0.0, 10.0, 20.0]}, "pulse.code": ["barker13", "golay16a"]},
    }
    data.update(changes)
    return {key: value for key, value in data.items() if value is not None}


def _column(text: str, name: str) -> list[float]:
    return [float(row[name]) for row in csv.DictReader(io.StringIO(text))]


# --- reproducibility -------------------------------------------------------------------


def test_the_table_is_the_same_bytes_whatever_the_workers_and_the_order(
    client: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """In this process, on 2 workers, on 1 of them a point a task, in reverse order 4 points a
    task, and from the command line on a cluster of its own with 1 worker: the same CSV, byte
    for byte."""
    path = tmp_path / "sweep.toml"
    path.write_text(
        'frames = 6\nseed = 3\nmetrics = ["median_error_m", "rms_error_m", "spread_m", "recall", '
        '"false_rate", "sigma_ratio"]\n'
        "[scene]\n[scene.acquisition]\nn_samples = 1600\n[scene.noise]\nsnr_db = 20.0\n"
        "[[scene.reflectors]]\nposition_m = [0.03, -0.02, 0.5]\n"
        '[grid]\nnoise.snr_db = [0.0, 10.0, 20.0]\n"pulse.code" = ["barker13", "golay16a"]\n'
    )
    sweep = load_sweep(path)
    assert sweep.columns == ("point", "noise.snr_db", "pulse.code", "seed", "frames", *DETERMINISTIC)
    serial = csv_text(sweep, run_sweep_serial(sweep))
    assert serial == csv_text(sweep_from_dict(_sweep()), run_sweep_serial(sweep_from_dict(_sweep())))
    done: list[int] = []
    two = csv_text(sweep, run_sweep(sweep, client, progress=done.append))
    assert sum(done) == 6
    one_worker = list(client.scheduler_info()["workers"])[:1]
    one = csv_text(sweep, run_sweep(sweep, client, workers=one_worker, group=1))
    backwards = csv_text(sweep, run_sweep(sweep, client, order=list(range(6))[::-1], group=4))
    assert serial == two == one == backwards
    assert len(serial.splitlines()) == 1 + 6
    output, picture = tmp_path / "table.csv", tmp_path / "table.png"
    with pytest.raises(SystemExit) as done:
        main(["sweep", str(path), "-o", str(output), "--workers", "1", "--plot", str(picture)])
    assert done.value.code == 0, capsys.readouterr().err
    assert output.read_bytes() == serial.encode()
    assert picture.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "6 points x 6 frames" in capsys.readouterr().out


def test_small_points_go_several_to_a_task_leaving_every_worker_enough() -> None:
    assert points_per_task(frames=16, n_points=200, n_workers=2) == 16
    assert points_per_task(frames=16, n_points=40, n_workers=2) == 5
    assert points_per_task(frames=1000, n_points=200, n_workers=2) == 1
    assert points_per_task(frames=1, n_points=3, n_workers=8) == 1


def test_a_point_keeps_its_row_when_the_grid_grows() -> None:
    """A point's seed comes from its values, not its place: adding values leaves it be."""
    small = sweep_from_dict(_sweep(grid={"noise.snr_db": [10.0, 20]}))
    large = sweep_from_dict(_sweep(grid={"noise.snr_db": [0.0, 10, 15.0, 20.0]}))
    assert [p.seed for p in small.points] == [large.points[1].seed, large.points[3].seed]
    rows_small = run_sweep_serial(small)
    rows_large = run_sweep_serial(large)
    for a, b in ((rows_small[0], rows_large[1]), (rows_small[1], rows_large[3])):
        columns = [name for name in small.columns if name != "point"]
        assert [cell(a[name]) for name in columns] == [cell(b[name]) for name in columns]


def test_a_random_sweep_is_the_same_with_the_same_seed_and_not_with_another(client: Any) -> None:
    def random(seed: int) -> Any:
        return sweep_from_dict(
            _sweep(
                grid=None,
                seed=seed,
                frames=3,
                random={
                    "points": 5,
                    "noise.snr_db": {"uniform": [5.0, 25.0]},
                    "pulse": {
                        "cycles_per_bit": {"integers": [2, 6]},
                        "code": {"choice": ["barker13", "mls5"]},
                    },
                    "array.spacing_m": {"log_uniform": [0.05, 0.3]},
                },
            )
        )

    first, again, other = random(11), random(11), random(12)
    assert first.kind == "random"
    assert first.points == again.points
    assert [p.values for p in first.points] != [p.values for p in other.points]
    assert len({p.seed for p in first.points}) == 5
    for point in first.points:
        values = dict(point.values)
        assert 5.0 <= values["noise.snr_db"] <= 25.0
        assert values["pulse.cycles_per_bit"] in range(2, 7)
        assert 0.05 <= values["array.spacing_m"] <= 0.3
        assert values["noise.snr_db"] == float(f"{values['noise.snr_db']:.4g}")  # as the table shows it
    table = csv_text(first, run_sweep(first, client))
    assert table == csv_text(again, run_sweep(again, client))
    assert table != csv_text(other, run_sweep(other, client))


# --- physics ---------------------------------------------------------------------------


def test_the_spread_falls_tenfold_for_20_db_more_snr(client: Any) -> None:
    """The ToF's Cramér-Rao bound scales as 1/amplitude SNR: 20 -> 40 dB divides the spread by 10.

    The matched estimator with its carrier phase reaches the bound here (the echo's output SNR
    is above 50 dB at both points, far above threshold). The spread is the error's scatter about
    its mean (the estimator's small fixed bias left out). With 128 frames, one reflector and
    two error axes that dominate, each spread is known to about 1/sqrt(2 x 256) = 4.4 %, the
    ratio to about 6 %: 10 ± 25 % is four standard deviations.
    """
    sweep = sweep_from_dict(_sweep(frames=128, grid={"noise.snr_db": [20.0, 30.0, 40.0]}))
    rows = run_sweep(sweep, client)
    spread = [row["spread_m"] for row in rows]
    assert [row["recall"] for row in rows] == [1.0, 1.0, 1.0]
    assert spread[0] > spread[1] > spread[2]
    assert spread[0] / spread[2] == pytest.approx(10.0, rel=0.25)
    assert spread[0] / spread[1] == pytest.approx(math.sqrt(10.0), rel=0.25)


def test_the_angle_error_falls_with_the_spacing_as_the_closed_form_says(client: Any) -> None:
    """The report's cross at spacings 5-40 cm, 2.5 mm of random error on every path (the chain
    told so): the RMS angle error falls with the spacing (report fig. 4.13) and is, at each
    spacing, the first-order GDOP figure for that path error (position_errors), within 25 %:
    64 frames, two cross-range axes, so each RMS is known to 1/sqrt(2 x 128) = 6 %."""
    scene = copy.deepcopy(ONE_BALL)
    scene["noise"] = {"snr_db": 13.5, "path_jitter_m": 0.0025}
    spacings = [0.05, 0.1, 0.2, 0.4]
    sweep = sweep_from_dict(
        _sweep(
            scene=scene,
            frames=64,
            match_radius_m=0.3,
            metrics=["rms_angle_error_deg", "recall", "sigma_ratio"],
            processing={"path_sigma_m": 0.0025},
            array_layout={"kind": "cross"},
            grid={"array": {"spacing_m": spacings}},
        )
    )
    rows = run_sweep(sweep, client)
    measured = [row["rms_angle_error_deg"] for row in rows]
    assert all(row["recall"] == 1.0 for row in rows)
    assert all(a > b for a, b in itertools.pairwise(measured))
    assert measured[0] / measured[-1] > 4.0
    ball = np.array(ONE_BALL["reflectors"][0]["position_m"])
    for d, found in zip(spacings, measured, strict=True):
        receivers = np.array(layout_receivers(ArrayLayout("cross", d), np.zeros(3)))
        predicted = position_errors(ball, np.zeros((4, 3)), receivers, 0.0025)
        assert found == pytest.approx(math.degrees(float(predicted.angle_std_rad)), rel=0.25), d
    # The chain reports the sigma it was told; the real spread matches it.
    assert all(row["sigma_ratio"] == pytest.approx(1.0, rel=0.25) for row in rows)


@pytest.mark.parametrize("name", ["report-spacing", "codes-and-snr", "random-design"])
def test_the_example_sweep_files_check(name: str) -> None:
    """Every point of the examples builds (they run in full in docs/SWEEP_SECTION.md)."""
    sweep = load_sweep(REPO / "examples" / "sweeps" / f"{name}.toml")
    assert len(sweep.points) == {"report-spacing": 27, "codes-and-snr": 30, "random-design": 60}[name]
    assert sweep.plot.y in sweep.study.metrics


def test_layouts_place_the_receivers_around_the_first_transmitter() -> None:
    cross = np.array(layout_receivers(ArrayLayout("cross", 0.1, 8), np.array([0.0, 0.0, 0.01])))
    assert cross.shape == (8, 3)
    assert cross[:4].tolist() == [[0.1, 0, 0.01], [-0.1, 0, 0.01], [0, 0.1, 0.01], [0, -0.1, 0.01]]
    assert np.allclose(np.linalg.norm(cross[4:, :2], axis=1), 0.2)
    ring = np.array(layout_receivers(ArrayLayout("ring", 0.075, 3), np.zeros(3)))
    assert np.allclose(np.linalg.norm(ring, axis=1), 0.075)
    assert np.allclose(ring.sum(axis=0), 0.0, atol=1e-12)
    with pytest.raises(SweepError, match="multiple of 4"):
        layout_receivers(ArrayLayout("cross", 0.1, 6), np.zeros(3))


# --- bad sweep files -------------------------------------------------------------------

S = 'scene = "report-three-balls"\n'
G = "[grid]\nnoise.snr_db = [1.0]\n"
BAD = {
    "unknown key": (S + "frame_rate = 3\n" + G, "top level: unknown key 'frame_rate'"),
    "unknown parameter": (S + "[grid]\nnoise.snr = [1.0]\n", "noise.snr"),
    "unknown section": (S + "[grid]\nnoize.snr_db = [1.0]\n", "noize.snr_db"),
    "refused value": (
        S + "[grid]\nnoise.snr_db = [10.0, 1000.0]\n",
        "point 1 (noise.snr_db = 1000): noise.snr_db must lie in",
    ),
    "refused code": (S + '[grid]\npulse.code = ["barker13", "nope"]\n', "'nope'"),
    "unknown processing key": (S + "[processing]\nthreshold = 3\n" + G, "threshold"),
    "bad processing value": (S + '[grid]\nestimator = ["matched", "best"]\n', "best"),
    "grid and random": (S + G + "[random]\npoints = 2\n", "[grid] or as [random]"),
    "unknown metric": (S + 'metrics = ["speed"]\n' + G, "speed"),
    "no such scene": ('scene = "no-such-scene"\n' + G, "no-such-scene"),
    "ring of two": (
        S + '[array_layout]\nkind = "ring"\n[grid]\narray.spacing_m = [0.1]\narray.n_receivers = [2, 3]\n',
        "point 0 (array.spacing_m = 0.1, array.n_receivers = 2): array.n_receivers of a ring must be >= 3",
    ),
    "seed varied": (S + "[grid]\nseed = [1, 2]\n", "seed cannot vary"),
    "bad distribution": (S + "[random]\npoints = 3\nnoise.snr_db = [1.0, 2.0]\n", "uniform"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_a_bad_sweep_file_is_one_line_and_exit_2_before_any_cluster_starts(
    case: str, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    text, expected = BAD[case]
    path = tmp_path / "bad.toml"
    path.write_text(text)

    def no_cluster(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("a cluster was started for a bad sweep file")

    monkeypatch.setattr("echoloc.scale.cluster.open_client", no_cluster)
    output = tmp_path / "out.csv"
    with pytest.raises(SystemExit) as done:
        main(["sweep", str(path), "-o", str(output)])
    assert done.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"echoloc: error: {path}")
    assert expected in lines[0]
    assert not output.exists()


def test_parquet_without_pyarrow_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "sweep.toml"
    path.write_text('scene = "report-three-balls"\n[grid]\nnoise.snr_db = [10.0]\n')
    monkeypatch.setattr("echoloc.cli.sweep.parquet_available", lambda: False)
    monkeypatch.setattr("echoloc.scale.cluster.open_client", None)
    with pytest.raises(SystemExit) as done:
        main(["sweep", str(path), "-o", str(tmp_path / "out.parquet")])
    assert done.value.code == 2
    lines = capsys.readouterr().err.strip().splitlines()
    assert lines == [f"echoloc: error: {tmp_path / 'out.parquet'}: needs pyarrow: pip install pyarrow"]
