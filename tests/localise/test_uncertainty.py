"""Uncertainty and design: the report's figures 4.12 and 4.13, covariance, GDOP and `echoloc design`."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from echoloc.cli.commands import main
from echoloc.errors import EchoLocError, GeometryError
from echoloc.localise.locate import solve_positions
from echoloc.localise.uncertainty import (
    array_channels,
    cross_array,
    error_map,
    paired_paths,
    paired_range_angle,
    position_errors,
    recommended_spacing,
    report_array_2d,
    spacing_study,
    uncertainty_area,
)
from repo_paths import REPO

# --- the paired closed forms and the corners of figure 4.12 ------------------------


@settings(max_examples=200, deadline=None)
@given(
    x=st.floats(-1.0, 1.0),
    z=st.floats(0.05, 2.0),
    d1=st.floats(0.02, 0.6),
    d2=st.floats(0.02, 0.6),
)
def test_closed_form_round_trips_any_point_and_unequal_spacings(
    x: float, z: float, d1: float, d2: float
) -> None:
    """(3.5)/(3.6), generalised to d1 != d2 (appendix F): paths of a point give its r and theta back."""
    l1, l2 = paired_paths(np.array([x, z]), d1, d2)
    r, theta = paired_range_angle(l1, l2, d1, d2)
    assert float(r) == pytest.approx(math.hypot(x, z), abs=1e-9)
    assert float(theta) == pytest.approx(math.atan2(x, z), abs=1e-7)


def test_closed_form_gives_nan_for_paths_no_point_explains() -> None:
    """|l1 - l2| > 2d: the ellipses do not cross in front of the array."""
    _, theta = paired_range_angle(1.0, 1.6, 0.25)
    assert np.isnan(theta)
    with pytest.raises(GeometryError, match="do not cross"):
        uncertainty_area(1.0, 1.6, 0.005, 0.005, 0.25)


@settings(max_examples=100, deadline=None)
@given(
    x=st.floats(-0.3, 0.3),
    z=st.floats(0.2, 1.5),
    d=st.floats(0.05, 0.5),
    e1=st.floats(1e-4, 0.01),
    e2=st.floats(1e-4, 0.01),
)
def test_corners_lie_on_the_band_edges_the_report_names(
    x: float, z: float, d: float, e1: float, e2: float
) -> None:
    """Corner a has paths (l1 + dl1, l2 - dl2), b (-, -), c (-, +), d (+, +); a/c bound theta, b/d bound r.

    Far to the side of a short baseline a corner's path difference reaches the receivers'
    spacing 2d, where its ellipses no longer cross in front (a refusal, tested above)."""
    l1, l2 = (float(v) for v in paired_paths(np.array([x, z]), d))
    assume(abs(l1 - l2) + e1 + e2 < 1.9 * d)
    area = uncertainty_area(l1, l2, e1, e2, d)
    assert area.position_m == pytest.approx([x, z], abs=1e-9)
    p1, p2 = paired_paths(area.corners_m, d)
    assert p1 == pytest.approx([l1 + e1, l1 - e1, l1 - e1, l1 + e1], abs=1e-9)
    assert p2 == pytest.approx([l2 - e2, l2 - e2, l2 + e2, l2 + e2], abs=1e-9)
    theta_a, _, theta_c, _ = area.corner_angle_rad
    _, r_b, _, r_d = area.corner_range_m
    assert theta_a < area.angle_rad < theta_c
    assert r_b < area.range_m < r_d
    assert r_b == min(area.corner_range_m)
    assert r_d == max(area.corner_range_m)


def test_corners_at_zero_error_collapse_onto_the_exact_point() -> None:
    area = uncertainty_area(1.0, 1.02, 0.0, 0.0, 0.25)
    for corner in area.corners_m:
        assert corner == pytest.approx(area.position_m, abs=1e-12)


@settings(max_examples=100, deadline=None)
@given(z=st.floats(0.2, 1.5), d=st.floats(0.05, 0.5), e=st.floats(1e-4, 0.01))
def test_mirrored_errors_give_a_mirrored_area_on_the_boresight(z: float, d: float, e: float) -> None:
    """l1 = l2, dl1 = dl2: a and c mirror each other in x; b and d lie on the boresight."""
    path, _ = paired_paths(np.array([0.0, z]), d)
    area = uncertainty_area(float(path), float(path), e, e, d)
    a, b, c, dd = area.corners_m
    assert a == pytest.approx([-c[0], c[1]], abs=1e-12)
    assert b[0] == pytest.approx(0.0, abs=1e-12)
    assert dd[0] == pytest.approx(0.0, abs=1e-12)
    lo, hi = area.range_error_m
    # To first order the range moves by dl (l^2 + d^2) / (2 l^2) with both paths in error.
    assert hi == pytest.approx(e * (path**2 + d**2) / (2 * path**2), rel=0.02)
    assert lo == pytest.approx(-hi, rel=0.02)


def test_swapping_the_receivers_mirrors_the_area() -> None:
    """(l1, dl1) <-> (l2, dl2) is the mirror image x -> -x: a <-> c, b and d mirror."""
    one = uncertainty_area(1.00, 1.03, 0.004, 0.002, 0.2)
    two = uncertainty_area(1.03, 1.00, 0.002, 0.004, 0.2)
    mirror = np.array([-1.0, 1.0])
    assert two.corners_m[[2, 1, 0, 3]] == pytest.approx(one.corners_m * mirror, abs=1e-12)


# --- covariance, GDOP -------------------------------------------------------------


@pytest.mark.parametrize(("z", "d"), [(0.5, 0.25), (1.0, 0.1), (0.3, 0.6)])
def test_broadside_gdop_of_the_report_pair_matches_its_closed_form(z: float, d: float) -> None:
    """T between R at +-d, point (0, z): J^T J = diag(2 d^2/s^2, 2 (1 + z/s)^2), s = sqrt(z^2 + d^2)."""
    tx, rx = array_channels(*report_array_2d(d))
    errors = position_errors(np.array([0.0, z]), tx, rx, sigma_m=0.002)
    s = math.hypot(z, d)
    std_x = 0.002 * s / (math.sqrt(2) * d)
    std_z = 0.002 / (math.sqrt(2) * (1 + z / s))
    assert errors.std_m == pytest.approx([std_x, std_z], rel=1e-12)
    assert float(errors.gdop) == pytest.approx(math.hypot(std_x, std_z) / 0.002, rel=1e-12)
    assert float(errors.range_std_m) == pytest.approx(std_z, rel=1e-12)
    assert float(errors.angle_std_rad) == pytest.approx(std_x / z, rel=1e-12)


def test_broadside_gdop_of_the_report_cross_matches_its_closed_form() -> None:
    """Four receivers at +-d on x and y: GDOP^2 = s^2/d^2 + 1 / (4 (1 + z/s)^2)."""
    z, d = 0.6, 0.25
    tx, rx = array_channels(*cross_array(d))
    gdop = float(position_errors(np.array([0.0, 0.0, z]), tx, rx).gdop)
    s = math.hypot(z, d)
    assert gdop == pytest.approx(math.sqrt(s**2 / d**2 + 1 / (4 * (1 + z / s) ** 2)), rel=1e-12)


def test_monostatic_transceivers_measure_twice_the_distance() -> None:
    """Two transducers that each send and hear only themselves: rows 2u, std_x = sigma s / (2 sqrt 2 d)."""
    d, z, sigma = 0.2, 0.5, 0.001
    pair = np.array([[d, 0.0], [-d, 0.0]])
    errors = position_errors(np.array([0.0, z]), pair, pair, sigma)
    s = math.hypot(z, d)
    assert errors.std_m == pytest.approx(
        [sigma * s / (2 * math.sqrt(2) * d), sigma * s / (2 * math.sqrt(2) * z)], rel=1e-12
    )


def test_a_point_in_the_plane_of_a_flat_array_has_no_finite_gdop() -> None:
    """All transducers at z = 0: on that plane the paths do not change with z to first order."""
    tx, rx = array_channels(*cross_array(0.25))
    errors = position_errors(np.array([[0.4, 0.1, 0.0], [0.4, 0.1, 0.5]]), tx, rx)
    assert np.isinf(errors.gdop[0])
    assert np.isfinite(errors.gdop[1])


def test_covariance_matches_the_monte_carlo_spread_of_the_exact_2d_solution() -> None:
    """Paths with sigma = 1 mm through (3.5)/(3.6): the solutions scatter with the predicted covariance."""
    rng = np.random.default_rng(7)
    d, sigma = 0.2, 0.001
    truth = np.array([0.15, 0.55])
    l1, l2 = paired_paths(truth, d)
    n = 40_000
    r, theta = paired_range_angle(l1 + sigma * rng.standard_normal(n), l2 + sigma * rng.standard_normal(n), d)
    solved = np.stack([r * np.sin(theta), r * np.cos(theta)], axis=-1)
    predicted = position_errors(truth, *array_channels(*report_array_2d(d)), sigma_m=sigma)
    spread = np.cov(solved.T)
    assert np.sqrt(np.diag(spread)) == pytest.approx(predicted.std_m, rel=0.03)
    correlation = spread[0, 1] / np.sqrt(spread[0, 0] * spread[1, 1])
    cov = predicted.covariance_m2
    assert correlation == pytest.approx(cov[0, 1] / np.sqrt(cov[0, 0] * cov[1, 1]), abs=0.02)
    assert np.std(theta) == pytest.approx(float(predicted.angle_std_rad), rel=0.03)
    assert np.std(r) == pytest.approx(float(predicted.range_std_m), rel=0.03)


def test_covariance_matches_the_monte_carlo_spread_of_the_3d_solver() -> None:
    """The report's head, sigma = 1 mm: locate's Gauss-Newton scatters as (J^T W J)^-1 predicts."""
    rng = np.random.default_rng(11)
    tx, rx = cross_array(0.25)
    truth = np.array([0.10, -0.05, 0.60])
    sigma = 0.001
    paths = np.linalg.norm(truth - tx[0]) + np.linalg.norm(truth - rx, axis=1)
    n = 4000
    noisy = paths + sigma * rng.standard_normal((n, len(rx)))
    solution = solve_positions(tx[0], rx, noisy, sigma, np.array([0.0, 0.0, 1.0]))
    assert np.all(solution.converged)
    predicted = position_errors(truth, *array_channels(tx, rx), sigma_m=sigma)
    assert np.std(solution.position_m, axis=0) == pytest.approx(predicted.std_m, rel=0.05)
    # The solver's own covariance is this propagation, evaluated at its estimate.
    at_estimate = position_errors(solution.position_m[:50], *array_channels(tx, rx), sigma_m=sigma)
    assert solution.covariance_m2[:50] == pytest.approx(at_estimate.covariance_m2, rel=1e-6, abs=1e-15)


def _asymmetric_array() -> tuple[np.ndarray, np.ndarray]:
    transmitters = np.array([[0.0, 0.0, 0.0], [0.12, 0.05, 0.0]])
    receivers = np.array([[0.3, 0.02, 0.0], [-0.15, 0.1, 0.0], [0.05, -0.2, 0.01], [0.12, 0.05, 0.0]])
    return transmitters, receivers  # the second transmitter also receives


def test_mirrored_arrays_mirror_the_gdop_map() -> None:
    transmitters, receivers = _asymmetric_array()
    flip = np.array([-1.0, 1.0, 1.0])
    u = np.linspace(-0.6, 0.6, 25)
    v = np.linspace(0.1, 1.0, 19)
    one = error_map(transmitters, receivers, u, v, plane="xz", offset_m=0.05, sigma_m=0.001)
    two = error_map(transmitters * flip, receivers * flip, u, v, plane="xz", offset_m=0.05, sigma_m=0.001)
    assert two.errors.gdop == pytest.approx(one.errors.gdop[:, ::-1], rel=1e-9)
    assert two.errors.range_std_m == pytest.approx(one.errors.range_std_m[:, ::-1], rel=1e-9)
    assert two.errors.angle_std_rad == pytest.approx(one.errors.angle_std_rad[:, ::-1], rel=1e-9)
    # The x-z covariance changes sign under the mirror.
    assert two.errors.covariance_m2[..., 0, 2] == pytest.approx(
        -one.errors.covariance_m2[:, ::-1, 0, 2], rel=1e-9, abs=1e-15
    )


@settings(max_examples=60, deadline=None)
@given(
    scale=st.floats(0.1, 10.0),
    sigma=st.floats(1e-5, 1e-2),
    point=st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(0.2, 1.5)),
)
def test_gdop_is_scale_free_and_stds_scale_with_sigma(
    scale: float, sigma: float, point: tuple[float, float, float]
) -> None:
    """GDOP depends on the shape of the geometry only; the covariance on sigma squared only."""
    transmitters, receivers = _asymmetric_array()
    channels = array_channels(transmitters, receivers)
    p = np.array(point)
    base = position_errors(p, *channels, sigma_m=1.0)
    scaled = position_errors(p * scale, *(c * scale for c in channels), sigma_m=sigma)
    assert float(scaled.gdop) == pytest.approx(float(base.gdop), rel=1e-7)
    assert scaled.std_m == pytest.approx(base.std_m * sigma, rel=1e-7)
    assert float(scaled.angle_std_rad) == pytest.approx(float(base.angle_std_rad) * sigma / scale, rel=1e-7)


# --- the spacing study (figure 4.13) and the recommendation -------------------------


def test_spacing_study_reproduces_the_reports_angle_spread_at_small_spacing() -> None:
    """At d = 0.01 m, dl1 = -5...+5 mm swings theta over about 0.5 rad (the report: "0.5 rad (~29°)")."""
    study = spacing_study([0.01], [-0.005, 0.005], path_m=1.0)
    swing = float(study.angle_error_rad[0, 0] - study.angle_error_rad[1, 0])
    assert swing == pytest.approx(0.505, abs=0.01)
    assert math.degrees(swing) == pytest.approx(29.0, abs=0.5)


def test_spacing_study_matches_first_order_closed_forms() -> None:
    """Fixed path l: dr = dl (l^2 + d^2) / (4 l^2), r dtheta = -dl sqrt(r^2 + d^2) / (2 d)."""
    d = np.array([0.05, 0.25, 0.5])
    study = spacing_study(d, [1e-6], path_m=1.0)
    r = (1.0 - d**2) / 2
    assert study.range_m == pytest.approx(r)
    assert study.linear_range_error_m[0] == pytest.approx(1e-6 * (1 + d**2) / 4, rel=1e-12)
    assert study.linear_angle_error_rad[0] == pytest.approx(-1e-6 * np.hypot(r, d) / (2 * d * r), rel=1e-12)
    # Exact and linear agree as dl -> 0 ...
    assert study.range_error_m == pytest.approx(study.linear_range_error_m, rel=1e-4)
    assert study.angle_error_rad == pytest.approx(study.linear_angle_error_rad, rel=1e-4)
    # ... and the range error grows with spacing while the angle error falls (the trade-off; at
    # a fixed path the point also comes closer, so the angle error bottoms out near d = 0.49 m).
    big = spacing_study(np.linspace(0.01, 0.45, 50), [0.005], path_m=1.0)
    assert np.all(np.diff(big.range_error_m[0]) > 0)
    assert np.all(np.diff(np.abs(big.angle_error_rad[0])) < 0)


def test_range_held_study_puts_the_point_at_that_range() -> None:
    study = spacing_study([0.1, 0.3], [0.0], range_m=0.8)
    assert study.range_m == pytest.approx([0.8, 0.8])
    assert study.path_m == pytest.approx(0.8 + np.hypot(0.8, [0.1, 0.3]))
    assert study.range_error_m == pytest.approx(np.zeros((1, 2)), abs=1e-12)


def test_recommended_spacing_reproduces_the_reports_quarter_metre() -> None:
    """Report section 4.3: "a transducer spacing of 0.25 m would suffice" at l = 1 m, dl = 5 mm."""
    rec = recommended_spacing(0.005, path_m=1.0)
    assert 0.2 <= rec.spacing_m <= 0.3
    # First order: sqrt(r^2 + d^2) = 2 d with r = l - 2 d  =>  d = l / (2 + sqrt 3).
    assert rec.spacing_m == pytest.approx(1 / (2 + math.sqrt(3)), rel=0.01)
    assert rec.cross_range_error_m == pytest.approx(0.005, rel=1e-6)
    # Smallest: a little less spacing breaks the criterion.
    worse = spacing_study([0.97 * rec.spacing_m], [-0.005, 0.005], path_m=1.0)
    assert np.max(worse.cross_range_error_m) > 0.005


@settings(max_examples=25, deadline=None)
@given(range_m=st.floats(0.3, 3.0), path_error_m=st.floats(2e-4, 5e-3))
def test_recommended_spacing_grows_with_range_as_first_order_predicts(
    range_m: float, path_error_m: float
) -> None:
    """Range held: sqrt(r^2 + d^2) = 2 d, i.e. d = r / sqrt(3), whatever the path error."""
    rec = recommended_spacing(path_error_m, range_m=range_m)
    assert rec.spacing_m == pytest.approx(range_m / math.sqrt(3), rel=0.02)
    assert rec.range_m == pytest.approx(range_m)


def test_a_range_error_bound_gives_the_largest_spacing() -> None:
    rec = recommended_spacing(0.005, path_m=1.0, max_range_error_m=0.0015)
    assert rec.largest_spacing_m is not None
    assert rec.spacing_m < rec.largest_spacing_m
    at_limit = spacing_study([rec.largest_spacing_m], [0.005, -0.005], path_m=1.0)
    assert np.max(np.abs(at_limit.range_error_m)) == pytest.approx(0.0015, rel=1e-6)
    with pytest.raises(EchoLocError, match="relax one of the bounds"):
        recommended_spacing(0.005, path_m=1.0, max_range_error_m=0.001)


@pytest.mark.parametrize(
    ("args", "kwargs", "message"),
    [
        ((0.0,), {"path_m": 1.0}, "path_error_m"),
        ((0.005,), {}, "exactly one"),
        ((0.005,), {"path_m": 1.0, "range_m": 1.0}, "exactly one"),
        ((0.005,), {"range_m": -1.0}, "range_m"),
        ((0.005,), {"range_m": 1.0, "max_cross_range_error_m": 0.001}, "raise the tolerance"),
    ],
)
def test_recommended_spacing_refuses_bad_requests(args: tuple, kwargs: dict, message: str) -> None:  # type: ignore[type-arg]
    with pytest.raises(EchoLocError, match=message):
        recommended_spacing(*args, **kwargs)


def test_spacing_study_refuses_a_spacing_beyond_the_path() -> None:
    with pytest.raises(EchoLocError, match="below the path"):
        spacing_study([0.5, 1.2], [0.005], path_m=1.0)


# --- echoloc design ---------------------------------------------------------------


def test_design_command_reproduces_figure_4_13_and_draws_three_plots(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["design", "--json", "-o", str(tmp_path)])
    assert exit_info.value.code == 0
    record = json.loads(capsys.readouterr().out)
    assert record["held"] == {"path_m": 1.0}
    assert 0.2 <= record["recommendation"]["spacing_m"] <= 0.3
    corners = record["uncertainty_area"]["corners"]
    assert corners["a"]["position_m"][0] == pytest.approx(-corners["c"]["position_m"][0])
    assert record["array"]["on_boresight"]["gdop"] > 1
    for name in ("uncertainty_area.png", "spacing_study.png", "gdop_map.png"):
        png = tmp_path / name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert png.stat().st_size > 20_000


def test_design_command_table_names_the_recommendation(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["design", "--range-m", "1.0", "--path-error-m", "0.002"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    assert "Recommended spacing d = 0.57" in out
    assert "◀ recommended" in out


@pytest.mark.parametrize(
    "args",
    [
        ["--path-error-m", "-0.005"],
        ["--path-error-m", "nan"],
        ["--path-m", "1", "--range-m", "1"],
        ["--spacing-m", "1.5"],
        ["--max-range-error-m", "0.001"],
        ["--scene", "no-such-scene.toml"],
        ["--plane", "zz"],
        ["--range-m", "inf"],
    ],
)
def test_design_command_bad_values_give_one_line_and_exit_2(
    args: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["design", *args])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("echoloc: error:")
    assert len(err.strip().splitlines()) == 1
    assert "Traceback" not in err


def test_design_command_maps_a_scene_files_array(capsys: pytest.CaptureFixture[str]) -> None:
    """--scene: the GDOP figures are those of the scene's array, here the report's head (d = 0.25 m)."""
    scene = REPO / "src" / "echoloc" / "scenes" / "report-three-balls.toml"
    with pytest.raises(SystemExit) as exit_info:
        main(["design", "--scene", str(scene), "--plane", "xy", "--json"])
    assert exit_info.value.code == 0
    record = json.loads(capsys.readouterr().out)
    assert np.abs(record["array"]["receivers_m"]).max() == pytest.approx(0.25)
    z = record["array"]["on_boresight"]["position_m"][2]
    s = math.hypot(z, 0.25)
    expected = math.sqrt(s**2 / 0.25**2 + 1 / (4 * (1 + z / s) ** 2))
    assert record["array"]["on_boresight"]["gdop"] == pytest.approx(expected, rel=1e-9)
