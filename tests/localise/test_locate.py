"""Localisation: closed forms, symmetries, round trips, covariance and ghost rejection."""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from echoloc.localise.locate import (
    FrameLocator,
    LocateOptions,
    associate,
    chi2_tail,
    combine_frames,
    exact_solutions,
    linear_start,
    model_paths_m,
    paired_closed_form,
    paired_closed_form_2d,
    solve_positions,
)
from echoloc.tof.echoes import ChannelEchoes, FrameEchoes

D = 0.25
TX = np.zeros(3)
CROSS = np.array([[D, 0, 0], [-D, 0, 0], [0, D, 0], [0, -D, 0]], dtype=float)
UP = np.array([0.0, 0.0, 1.0])

points_in_front = st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5), st.floats(0.2, 1.2)).map(
    lambda p: np.array(p, dtype=float)
)


@settings(max_examples=200, deadline=None)
@given(dof=st.integers(1, 6), chi2=st.floats(0.0, 800.0))
def test_chi2_tail_is_the_chi_square_survival_function(dof: int, chi2: float) -> None:
    """The closed forms for one and two degrees of freedom give scipy's chdtrc (and the
    Monte-Carlo-free check: P(X > x) of chi-square 1 is erfc(sqrt(x/2)), of 2 exp(-x/2))."""
    from scipy import special

    expected = float(special.chdtrc(dof, chi2))
    assert chi2_tail(dof, chi2) == pytest.approx(expected, rel=1e-12, abs=1e-300)


def test_chi2_tail_at_its_landmarks() -> None:
    """The 5 % points of chi-square 1 and 2 (3.841, 5.991: the published table) leave 5 %."""
    assert chi2_tail(1, 3.841458820694124) == pytest.approx(0.05, rel=1e-12)
    assert chi2_tail(2, 5.991464547107979) == pytest.approx(0.05, rel=1e-12)
    assert chi2_tail(1, 0.0) == 1.0
    assert chi2_tail(2, 0.0) == 1.0
    assert np.isnan(chi2_tail(1, float("nan")))


@settings(max_examples=50, deadline=None)
@given(point=points_in_front)
def test_closed_form_agrees_with_the_general_solver(point: np.ndarray) -> None:
    """docs/METHOD.md's paired-geometry formulas and the Gauss-Newton solver give the same point."""
    paths = model_paths_m(TX, CROSS, point[None])
    closed = paired_closed_form(paths, D)[0]
    general = solve_positions(TX, CROSS, paths, 0.5e-3).position_m[0]
    assert closed == pytest.approx(point, abs=1e-9)
    assert general == pytest.approx(closed, abs=1e-9)


@settings(max_examples=50, deadline=None)
@given(point=points_in_front)
def test_swapping_the_x_receivers_mirrors_x(point: np.ndarray) -> None:
    """Exchanging the receivers at +x and -x (paths kept) mirrors the answer in x."""
    paths = model_paths_m(TX, CROSS, point[None])
    swapped = CROSS[[1, 0, 2, 3]]
    mirrored = solve_positions(TX, swapped, paths, 0.5e-3).position_m[0]
    assert mirrored == pytest.approx(point * np.array([-1, 1, 1]), abs=1e-9)


@settings(max_examples=50, deadline=None)
@given(
    point=points_in_front,
    offsets=st.lists(
        st.tuples(st.floats(-0.3, 0.3), st.floats(-0.3, 0.3), st.floats(-0.1, 0.1)), min_size=4, max_size=6
    ),
)
def test_round_trip_for_any_array_of_four_or_more(point: np.ndarray, offsets: list) -> None:
    """Exact paths to any non-degenerate array of >= 4 receivers give the point back."""
    receivers = np.array(offsets, dtype=float)
    # A well-conditioned array: distinct receivers spanning 3-D, none at the point.
    separations = np.linalg.norm(receivers[:, None] - receivers[None], axis=2)
    assume(np.min(separations + np.eye(len(receivers))) > 0.05)
    assume(np.linalg.svd(receivers - TX, compute_uv=False)[-1] > 0.03)
    assume(np.min(np.linalg.norm(receivers - point, axis=1)) > 0.1)
    paths = model_paths_m(TX, receivers, point[None])
    solution = solve_positions(TX, receivers, paths, 0.5e-3)
    assert solution.converged[0]
    assert solution.position_m[0] == pytest.approx(point, abs=1e-7)
    assert solution.chi2[0] < 1e-6


@settings(max_examples=50, deadline=None)
@given(point=points_in_front, angle=st.floats(0, 2 * np.pi))
def test_flat_array_of_three_receivers(point: np.ndarray, angle: float) -> None:
    """Three receivers in the transmitter's plane fix the point (z > 0) exactly."""
    rotation = np.array([[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]])
    receivers = np.array([[0.3, 0, 0], [-0.15, 0.26, 0], [-0.15, -0.26, 0]]) @ rotation.T
    paths = model_paths_m(TX, receivers, point[None])
    solution = solve_positions(TX, receivers, paths, 0.5e-3)
    assert solution.position_m[0] == pytest.approx(point, abs=1e-7)


def test_linear_start_is_exact_for_exact_paths() -> None:
    """The squared equations are exact, so the linear start is exact with exact paths (docs/METHOD.md)."""
    points = np.array([[0.1, -0.2, 0.6], [-0.3, 0.3, 0.9], [0.0, 0.0, 0.3]])
    paths = model_paths_m(TX, CROSS, points)
    assert linear_start(TX, CROSS, paths, UP) == pytest.approx(points, abs=1e-9)


def test_transmitter_away_from_the_origin() -> None:
    """Coordinates are relative to the transmitter: shifting everything shifts the answer."""
    shift = np.array([0.4, -0.2, 0.0])
    point = np.array([0.1, 0.05, 0.7])
    paths = model_paths_m(TX + shift, CROSS + shift, (point + shift)[None])
    solution = solve_positions(TX + shift, CROSS + shift, paths, 0.5e-3)
    assert solution.position_m[0] == pytest.approx(point + shift, abs=1e-9)


def test_covariance_matches_the_monte_carlo_spread() -> None:
    """(J^T W J)^-1 predicts the scatter of positions under Gaussian path noise."""
    rng = np.random.default_rng(3)
    point = np.array([0.15, -0.1, 0.8])
    sigma = 0.5e-3
    exact = model_paths_m(TX, CROSS, point[None])
    noisy = exact + rng.normal(0, sigma, size=(4000, 4))
    solution = solve_positions(TX, CROSS, noisy, sigma)
    spread = np.cov(solution.position_m.T)
    predicted = solve_positions(TX, CROSS, exact, sigma).covariance_m2[0]
    assert np.sqrt(np.diag(spread)) == pytest.approx(np.sqrt(np.diag(predicted)), rel=0.08)
    assert np.mean(solution.position_m, axis=0) == pytest.approx(point, abs=3e-4)
    # chi2 with one degree of freedom has mean 1.
    assert np.mean(solution.chi2) == pytest.approx(1.0, abs=0.1)


def _paths_per_receiver(points: np.ndarray, receivers: np.ndarray = CROSS) -> list[np.ndarray]:
    paths = model_paths_m(TX, receivers, points)
    return [np.sort(paths[:, i]) for i in range(len(receivers))]


def _sigmas(paths: list[np.ndarray], sigma: float = 0.5e-3) -> list[np.ndarray]:
    return [np.full(len(p), sigma) for p in paths]


OPTIONS = LocateOptions(resolution_m=0.0275)


def test_three_objects_no_ghosts() -> None:
    """Three reflectors: twelve echoes, 81 combinations, exactly three objects come out."""
    points = np.array([[0.01, -0.005, 0.58], [0.03, 0.02, 0.595], [-0.09, 0.12, 0.648]])
    paths = _paths_per_receiver(points)
    objects = associate(TX, CROSS, paths, _sigmas(paths), OPTIONS)
    found = np.array(sorted((o.position_m for o in objects), key=lambda p: p[2]))
    assert len(objects) == 3
    assert found == pytest.approx(points, abs=1e-7)
    assert all(len(o.receivers) == 4 for o in objects)


def test_object_seen_by_three_of_four_receivers() -> None:
    """When two echoes merge on one receiver, both objects are found and share that echo."""
    first = np.array([0.05, 0.02, 0.6])
    # A second point whose path to receiver 3 equals the first's (echoes merge there).
    second = np.array([-0.12, 0.15, 0.0])
    target = model_paths_m(TX, CROSS, first[None])[0, 3]
    lo, hi = 0.3, 1.2
    for _ in range(100):
        second[2] = 0.5 * (lo + hi)
        if model_paths_m(TX, CROSS, second[None])[0, 3] > target:
            hi = second[2]
        else:
            lo = second[2]
    paths = _paths_per_receiver(np.array([first, second]))
    paths[3] = paths[3][:1]  # one merged detection
    objects = associate(TX, CROSS, paths, _sigmas(paths), OPTIONS)
    assert len(objects) == 2
    assert [len(o.receivers) for o in objects] == [4, 4]
    assert [o.shared for o in objects] == [1, 1]
    # The shared echo weighs as a merged peak: each object's fit leans on its own three.
    assert all(o.echo_indices[3] == 0 for o in objects)
    for point in (first, second):
        assert min(np.linalg.norm(o.position_m - point) for o in objects) < 1e-6


def test_lone_triple_without_a_merge_is_not_an_object() -> None:
    """Three echoes that meet, with nothing on the fourth receiver to explain its silence, are rejected."""
    point = np.array([0.1, 0.1, 0.7])
    paths = _paths_per_receiver(point[None])
    paths[2] = np.zeros(0)
    assert associate(TX, CROSS, paths, _sigmas(paths), OPTIONS) == []


@settings(max_examples=40, deadline=None)
@given(
    points=st.lists(points_in_front, min_size=1, max_size=4),
)
def test_random_scenes_round_trip(points: list[np.ndarray]) -> None:
    """1-4 reflectors with exact paths: every one is found exactly, and nothing else.

    Reflectors must be separable: paths at least 1 mm apart on every receiver and
    ranges at least 1 mm apart (equal ranges make a cross array ambiguous), and the
    paths must not admit another exact scene (see _unambiguous).
    """
    per_receiver = _separable_paths(points)
    objects = associate(TX, CROSS, per_receiver, _sigmas(per_receiver), OPTIONS)
    assert len(objects) == len(points)
    for point in points:
        assert min(np.linalg.norm(o.position_m - point) for o in objects) < 1e-6


def _separable_paths(points: list[np.ndarray]) -> list[np.ndarray]:
    """The exact paths of ``points`` per receiver, sorted; hypothesis rejects (``assume``) any
    scene whose reflectors are not separable as test_random_scenes_round_trip says."""
    array = np.array(points)
    paths = model_paths_m(TX, CROSS, array)
    for i in range(4):
        gaps = np.diff(np.sort(paths[:, i]))
        assume(len(gaps) == 0 or gaps.min() > 1e-3)
    ranges = np.sort(np.linalg.norm(array, axis=1))
    assume(len(ranges) < 2 or np.diff(ranges).min() > 1e-3)
    per_receiver = [np.sort(paths[:, i]) for i in range(4)]
    assume(_unambiguous(per_receiver, len(points)))
    return per_receiver


def _unambiguous(per_receiver: list[np.ndarray], n_points: int) -> bool:
    """Only the true combinations of one echo per receiver meet exactly in a point.

    Not so, for example, for two reflectors both on the plane x = y of the cross array:
    their x-pair and y-pair paths are equal, and swapping echoes between them gives
    two other points with exactly the same paths (no time-of-flight method can tell).
    """
    combos = np.array(list(itertools.product(*[range(len(p)) for p in per_receiver])))
    paths = np.stack([per_receiver[i][combos[:, i]] for i in range(4)], axis=1)
    solution = solve_positions(TX, CROSS, paths, 0.5e-3)
    exact = solution.converged & (solution.chi2 < 1e-10) & (solution.position_m[:, 2] > 0)
    return int(np.sum(exact)) == n_points


def test_equal_ranges_make_the_cross_array_ambiguous() -> None:
    """Two reflectors at the same range: swapping x-pair and y-pair echoes gives two other
    points with exactly the same eight paths. This is why the evaluation scene varies
    reflector strengths: amplitudes then tell the two solutions apart.
    """
    a = np.array([0.15, -0.3, 0.0])
    b = np.array([-0.4, 0.03, 0.0])
    r = 0.7
    a[2] = np.sqrt(r**2 - a[0] ** 2 - a[1] ** 2)
    b[2] = np.sqrt(r**2 - b[0] ** 2 - b[1] ** 2)
    ghost_1 = np.array([a[0], b[1], np.sqrt(r**2 - a[0] ** 2 - b[1] ** 2)])
    ghost_2 = np.array([b[0], a[1], np.sqrt(r**2 - b[0] ** 2 - a[1] ** 2)])
    truth_paths = np.sort(model_paths_m(TX, CROSS, np.array([a, b])), axis=0)
    ghost_paths = np.sort(model_paths_m(TX, CROSS, np.array([ghost_1, ghost_2])), axis=0)
    assert truth_paths == pytest.approx(ghost_paths, abs=1e-12)
    # Amplitudes from different strengths break the tie.
    strengths = {0: 2.0, 1: 0.5}
    paths = [truth_paths[:, i] for i in range(4)]
    amplitudes = []
    for i in range(4):
        per = []
        for path in paths[i]:
            k = int(np.argmin([abs(model_paths_m(TX, CROSS, p[None])[0, i] - path) for p in (a, b)]))
            p = (a, b)[k]
            per.append(strengths[k] / (np.linalg.norm(p) * np.linalg.norm(p - CROSS[i])))
        amplitudes.append(np.array(per))
    objects = associate(TX, CROSS, paths, _sigmas(paths), OPTIONS, amplitudes=amplitudes)
    assert len(objects) == 2
    for point in (a, b):
        assert min(np.linalg.norm(o.position_m - point) for o in objects) < 1e-6


def test_points_behind_the_array_are_not_reported() -> None:
    """The transducers face +z: the mirror solution at -z is never returned."""
    point = np.array([0.1, -0.2, 0.5])
    paths = _paths_per_receiver(point[None])
    objects = associate(TX, CROSS, paths, _sigmas(paths), OPTIONS)
    assert len(objects) == 1
    assert objects[0].position_m[2] > 0


def test_dead_receiver_is_left_out() -> None:
    """With receiver 1 unusable, the other three still locate the object."""
    point = np.array([0.1, -0.2, 0.5])
    paths = _paths_per_receiver(point[None])
    paths[1] = np.zeros(0)
    usable = np.array([True, False, True, True])
    objects = associate(TX, CROSS, paths, _sigmas(paths), OPTIONS, usable=usable)
    assert len(objects) == 1
    assert objects[0].receivers == (0, 2, 3)
    assert objects[0].position_m == pytest.approx(point, abs=1e-7)


# --- 2-D, ghosts, mirrors, several transmitters, beams ---------------------------------

points_2d = st.tuples(st.floats(-0.5, 0.5), st.floats(0.2, 1.2)).map(lambda p: np.array(p, dtype=float))
PAIR_2D = np.array([[D, 0.0], [-D, 0.0]])


@settings(max_examples=50, deadline=None)
@given(point=points_2d)
def test_2d_closed_form_agrees_with_the_general_solver(point: np.ndarray) -> None:
    """The report's formulas (3.5)/(3.6) and the solver in 2-D give the point back."""
    paths = model_paths_m(np.zeros(2), PAIR_2D, point[None])
    assert paired_closed_form_2d(paths, D)[0] == pytest.approx(point, abs=1e-9)
    assert solve_positions(np.zeros(2), PAIR_2D, paths, 0.5e-3).position_m[0] == pytest.approx(
        point, abs=1e-9
    )


def test_two_receivers_make_two_ghosts_and_a_third_removes_them() -> None:
    """Two objects, one transmitter, two receivers (2-D, report fig. 4.12's set-up): the
    four pairings of echoes cross at the two objects and at two ghosts, which are the
    crossings of each object's echo on one receiver with the other's on the other. A
    third receiver rejects the ghosts.
    """
    objects = np.array([[0.1, 0.6], [-0.15, 0.8]])
    paths = model_paths_m(np.zeros(2), PAIR_2D, objects)  # (object, receiver)
    crossings = []
    for i in range(2):
        for j in range(2):
            points, valid = exact_solutions(np.zeros(2), PAIR_2D, np.array([[paths[i, 0], paths[j, 1]]]))
            crossings.extend(points[0][valid[0] & (points[0][:, 1] > 0)])
    assert len(crossings) == 4
    ghosts = [p for p in crossings if np.min(np.linalg.norm(objects - p, axis=1)) > 1e-6]
    expected = paired_closed_form_2d(np.array([[paths[0, 0], paths[1, 1]], [paths[1, 0], paths[0, 1]]]), D)
    assert sorted(map(tuple, np.round(ghosts, 9))) == sorted(map(tuple, np.round(expected, 9)))
    options = LocateOptions(min_receivers=2, boresight=(0.0, 1.0))
    two = associate(
        np.zeros(2), PAIR_2D, [paths[:, 0], paths[:, 1]], _sigmas([paths[:, 0], paths[:, 1]]), options
    )
    # Two disjoint pairs of crossings: the truth or the ghosts, nothing tells them apart.
    pair = sorted(map(tuple, np.round([o.position_m for o in two], 6)))
    assert pair in (sorted(map(tuple, np.round(objects, 6))), sorted(map(tuple, np.round(expected, 6))))
    third = np.vstack([PAIR_2D, [[0.1, 0.0]]])
    per_receiver = [np.sort(model_paths_m(np.zeros(2), third, objects)[:, i]) for i in range(3)]
    found = associate(np.zeros(2), third, per_receiver, _sigmas(per_receiver), options)
    assert len(found) == 2
    for point in objects:
        assert min(np.linalg.norm(o.position_m - point) for o in found) < 1e-7
    for ghost in expected:
        assert min(np.linalg.norm(o.position_m - ghost) for o in found) > 0.01


@settings(max_examples=30, deadline=None)
@given(points=st.lists(points_in_front, min_size=1, max_size=3))
def test_mirrored_array_mirrors_the_objects(points: list[np.ndarray]) -> None:
    """Mirroring the array in x (receivers' x negated, paths kept) mirrors every object in x."""
    per_receiver = _separable_paths(points)
    mirror = np.array([-1.0, 1.0, 1.0])
    direct = associate(TX, CROSS, per_receiver, _sigmas(per_receiver), OPTIONS)
    mirrored = associate(TX, CROSS * mirror, per_receiver, _sigmas(per_receiver), OPTIONS)
    assert len(direct) == len(mirrored) == len(points)
    for obj in direct:
        assert min(np.linalg.norm(m.position_m - obj.position_m * mirror) for m in mirrored) < 1e-7


def _frame(index: int, paths: np.ndarray) -> FrameEchoes:
    """Echoes of one frame with the given paths (objects, receivers), c = 1 so tof = path."""
    channels = tuple(
        ChannelEchoes(
            tof_s=np.sort(paths[:, i]),
            amplitude=np.ones(len(paths)),
            snr_db=np.full(len(paths), 30.0),
        )
        for i in range(paths.shape[1])
    )
    return FrameEchoes(index, 0.0, 1.0, channels)


def test_frames_of_two_transmitters_are_located_together() -> None:
    """Two transmitters fired in turn: eight ellipsoids per object, a tighter position."""
    transmitters = np.array([[0.0, 0.0, 0.0], [0.1, 0.1, 0.0]])
    points = np.array([[0.1, -0.2, 0.7], [-0.2, 0.15, 0.9]])
    frames = [(t, _frame(t, model_paths_m(transmitters[t], CROSS, points))) for t in range(2)]
    both = combine_frames(frames, transmitters, CROSS, OPTIONS)
    one = combine_frames(frames[:1], transmitters, CROSS, OPTIONS)
    assert both.frame == 1
    assert len(both.objects) == len(one.objects) == 2
    for obj in both.objects:
        assert min(np.linalg.norm(obj.position_m - p) for p in points) < 1e-7
        assert sorted(set(obj.transmitters)) == [0, 1]
        assert len(obj.receivers) == 8
    shrink = [
        np.trace(b.covariance_m2) / np.trace(o.covariance_m2)
        for b, o in zip(both.objects, one.objects, strict=True)
    ]
    assert max(shrink) < 0.8


def test_transducers_that_send_and_receive() -> None:
    """Four transducers each sending and receiving in turn (monostatic channels: T = R)
    plus the cross pairs between them locate the point exactly."""
    transducers = np.array([[0.2, 0.0, 0.0], [-0.2, 0.0, 0.0], [0.0, 0.2, 0.0], [0.0, -0.2, 0.0]])
    point = np.array([0.05, 0.1, 0.6])
    frames = [(t, _frame(t, model_paths_m(transducers[t], transducers, point[None]))) for t in range(4)]
    located = combine_frames(frames, transducers, transducers, OPTIONS)
    assert len(located.objects) == 1
    assert located.objects[0].position_m == pytest.approx(point, abs=1e-7)
    assert len(located.objects[0].receivers) == 16


@pytest.mark.parametrize(("fov_deg", "found"), [(90.0, 1), (30.0, 0)])
def test_points_outside_the_beams_are_rejected(fov_deg: float, found: int) -> None:
    """A point 40 degrees off the boresight is outside a 30-degree beam: nothing can echo from there."""
    angle = np.radians(40)
    point = 0.8 * np.array([np.sin(angle), 0.0, np.cos(angle)])
    paths = _paths_per_receiver(point[None])
    options = LocateOptions(resolution_m=0.0275, field_of_view_deg=fov_deg)
    assert len(associate(TX, CROSS, paths, _sigmas(paths), options)) == found


def test_two_points_on_the_diagonal_plane_have_a_twin_scene() -> None:
    """On the plane x = y of the cross array l1 = l3 and l2 = l4, so two reflectors there
    and the two points from swapped echoes have exactly the same eight paths (found by
    hypothesis: the reason `_unambiguous` guards the round-trip tests)."""
    truth = np.array([[0.0, 0.0, 0.625], [0.25, 0.25, 0.5]])
    paths = model_paths_m(TX, CROSS, truth)
    twin = solve_positions(TX, CROSS, np.array([[paths[0, 0], paths[1, 1], paths[0, 2], paths[1, 3]]]), 5e-4)
    other = solve_positions(TX, CROSS, np.array([[paths[1, 0], paths[0, 1], paths[1, 2], paths[0, 3]]]), 5e-4)
    twins = np.vstack([twin.position_m, other.position_m])
    assert np.min(np.linalg.norm(twins[:, None] - truth[None], axis=2)) > 0.05
    assert np.sort(model_paths_m(TX, CROSS, twins), axis=0) == pytest.approx(
        np.sort(paths, axis=0), abs=1e-12
    )


# --- merged, moved, split and unseen echoes (cases a review found) --------------------


def _second_point_on_rx3(first: np.ndarray, gap_m: float) -> np.ndarray:
    """A point on the line (-0.12, 0.15, z) whose path to receiver 3 is ``gap_m`` longer than first's."""
    target = model_paths_m(TX, CROSS, first[None])[0, 3] + gap_m
    lo, hi = 0.2, 1.5
    point = np.array([-0.12, 0.15, 0.0])
    for _ in range(100):
        point[2] = 0.5 * (lo + hi)
        lo, hi = (lo, point[2]) if model_paths_m(TX, CROSS, point[None])[0, 3] > target else (point[2], hi)
    return point


@pytest.mark.parametrize("gap_m", [0.004, 0.008, 0.012])
def test_a_peak_merged_midway_between_two_echoes_serves_both(gap_m: float) -> None:
    """Two paths on receiver 3 closer than half the resolution come out as one peak midway:
    both reflectors are still found, each sharing that echo."""
    first = np.array([0.05, 0.02, 0.6])
    second = _second_point_on_rx3(first, gap_m)
    paths = _paths_per_receiver(np.array([first, second]))
    paths[3] = np.array([model_paths_m(TX, CROSS, first[None])[0, 3] + gap_m / 2])
    objects = associate(TX, CROSS, paths, _sigmas(paths), OPTIONS)
    assert len(objects) == 2
    assert all(o.shared >= 1 and len(o.receivers) == 4 for o in objects)
    for point in (first, second):
        nearest = min(objects, key=lambda o: float(np.linalg.norm(o.position_m - point)))
        # The merged peak is gap/2 off both paths: the error stays within the reported 3 sigma.
        assert np.linalg.norm(nearest.position_m - point) < 3 * np.linalg.norm(nearest.std_m)


@pytest.mark.parametrize("moved_m", [0.001, 0.003, 0.006])
def test_a_reflector_that_moved_since_the_older_frame_is_located_where_it_is_now(moved_m: float) -> None:
    """Combined frames: the older transmitter's echoes support an object only where they
    agree; a reflector that moved is located from the newest frame, at its new place."""
    transmitters = np.array([[0.0, 0.0, 0.0], [0.1, 0.1, 0.0]])
    before = np.array([[0.1, -0.2, 0.7]])
    now = before + np.array([0.0, 0.0, moved_m])
    frames = [
        (0, _frame(0, model_paths_m(transmitters[0], CROSS, before))),
        (1, _frame(1, model_paths_m(transmitters[1], CROSS, now))),
    ]
    located = combine_frames(frames, transmitters, CROSS, OPTIONS)
    assert len(located.objects) == 1
    assert located.objects[0].position_m == pytest.approx(now[0], abs=1e-4)


def test_an_echo_a_receiver_cannot_hear_does_not_spoil_the_object() -> None:
    """A point outside receiver 3's beam needs no echo there, and a stray echo of another
    reflector near its predicted path there must not take part (or reject it)."""
    options = LocateOptions(field_of_view_deg=26.0)
    a = np.array([0.0, 0.2, 0.7])  # 33 degrees from receiver 3's axis
    b = np.array([0.02, -0.05, 0.0])
    target = model_paths_m(TX, CROSS, a[None])[0, 3] + 3e-4
    lo, hi = 0.2, 2.0
    for _ in range(100):
        b[2] = 0.5 * (lo + hi)
        lo, hi = (lo, b[2]) if model_paths_m(TX, CROSS, b[None])[0, 3] > target else (b[2], hi)
    pa, pb = (model_paths_m(TX, CROSS, p[None])[0] for p in (a, b))
    paths = [np.sort([pa[i], pb[i]]) for i in range(3)] + [np.array([pb[3]])]
    objects = associate(TX, CROSS, paths, _sigmas(paths), options)
    assert len(objects) == 2
    found_a = min(objects, key=lambda o: float(np.linalg.norm(o.position_m - a)))
    assert found_a.position_m == pytest.approx(a, abs=1e-6)
    assert 3 not in found_a.receivers


@pytest.mark.parametrize("split_m", [0.002, 0.004])
def test_an_echo_split_in_two_does_not_double_the_object(split_m: float) -> None:
    """Two peaks a few mm apart on two receivers for one reflector: one object, not two a mm apart."""
    a, b = np.array([0.05, 0.02, 0.6]), np.array([-0.2, 0.1, 0.85])
    paths = _paths_per_receiver(np.array([a, b]))
    for i in (2, 3):
        paths[i] = np.sort(np.r_[paths[i], model_paths_m(TX, CROSS, a[None])[0, i] + split_m])
    objects = associate(TX, CROSS, paths, _sigmas(paths), OPTIONS)
    assert len(objects) == 2
    for point in (a, b):
        assert min(np.linalg.norm(o.position_m - point) for o in objects) < 1e-3


def test_channel_indices_of_any_integer_dtype() -> None:
    """int32 transmitter and receiver indices work as int64 ones do."""
    point = np.array([0.1, -0.2, 0.7])
    paths = _paths_per_receiver(point[None])
    objects = associate(
        TX,
        CROSS,
        paths,
        _sigmas(paths),
        OPTIONS,
        transmitter_index=np.zeros(4, np.int32),
        receiver_index=np.arange(4, dtype=np.int32),
    )
    assert len(objects) == 1


@settings(max_examples=200, deadline=None)
@given(
    point=st.tuples(st.floats(-0.6, 0.6), st.floats(-0.6, 0.6), st.floats(0.1, 1.5)),
    receivers=st.lists(
        st.tuples(*(st.floats(-r, r, allow_subnormal=False) for r in (0.4, 0.4, 0.2))), min_size=3, max_size=3
    ),
)
def test_the_compiled_exact_solution_matches_the_numpy_one(point: tuple, receivers: list) -> None:
    """The seed kernel's exact three-ellipsoid crossing equals exact_solutions (numpy)."""
    from echoloc.localise import _locate_kernels

    rx = np.array(receivers, dtype=float)
    assume(np.linalg.svd(rx, compute_uv=False)[-1] > 0.03)
    paths = model_paths_m(TX, rx, np.array([point]))[0]
    points, valid = exact_solutions(TX, rx, paths[None])
    compiled = np.empty((2, 3))
    n = _locate_kernels._exact(TX, rx, paths, compiled)
    expected = points[0][valid[0]]
    assert n == len(expected)
    for p in expected:
        assert np.min(np.linalg.norm(compiled[:n] - p, axis=1)) < 1e-6 * max(1.0, float(np.max(np.abs(p))))
    assert np.min(np.linalg.norm(points[0] - np.array(point), axis=1)) < 1e-6


def test_a_lone_triple_is_an_object_where_one_channel_may_be_excused() -> None:
    """The same three echoes with nothing on the fourth receiver: rejected by default, one
    object at the point when a channel may be excused, with the larger covariance of three
    ellipsoids than of four; a frame that has its four-echo object keeps it as it is."""
    point = np.array([0.1, 0.1, 0.7])
    paths = _paths_per_receiver(point[None])
    full = FrameEchoes(
        0, 0.0, 343.0, tuple(ChannelEchoes(p / 343.0, np.ones(len(p)), np.full(len(p), 30.0)) for p in paths)
    )
    missing = FrameEchoes(
        0,
        0.0,
        343.0,
        tuple(
            c if i != 2 else ChannelEchoes(np.zeros(0), np.zeros(0), np.zeros(0))
            for i, c in enumerate(full.channels)
        ),
    )
    strict = FrameLocator(TX, CROSS, OPTIONS)
    lenient = FrameLocator(TX, CROSS, dataclasses.replace(OPTIONS, excuse_one_channel=True))
    assert strict(missing).objects == ()
    (three,) = lenient(missing).objects
    assert three.position_m == pytest.approx(point, abs=1e-7)
    assert sorted(three.receivers) == [0, 1, 3]
    (four,) = lenient(full).objects
    assert len(four.receivers) == 4
    assert np.trace(three.covariance_m2) > np.trace(four.covariance_m2)
