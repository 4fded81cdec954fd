"""Reflector hypotheses: the mirror law, the corner's image, reciprocity, and the simulator's
planes, points and corners classified and measured back (echoloc.localise.surfaces)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from echoloc.localise import surfaces
from echoloc.sim.reflectors import Edge, Plane, PointReflector, corner, echo_paths, edge_point, states_at

CROSS = np.array([[0.25, 0.0, 0.0], [-0.25, 0.0, 0.0], [0.0, 0.25, 0.0], [0.0, -0.25, 0.0]])
TRANSMITTERS = np.array([[0.0, 0.0, 0.0], [0.12, 0.12, 0.0]])
SIGMA_M = 0.5e-3

coordinate = st.floats(-0.4, 0.4)
unit_vectors = st.tuples(st.floats(-1, 1), st.floats(-1, 1), st.floats(-1, 1)).filter(
    lambda v: 0.2 < math.hypot(*v) <= 1.0
)


def _unit(v: tuple[float, float, float]) -> np.ndarray:
    a = np.asarray(v, dtype=float)
    return a / np.linalg.norm(a)


def _mirror(points: np.ndarray, foot: np.ndarray, normal: np.ndarray) -> np.ndarray:
    return points - 2 * ((points - foot) @ normal)[..., None] * normal


# --- geometry ---------------------------------------------------------------------------


@settings(max_examples=200, deadline=None)
@given(
    normal=unit_vectors,
    distance=st.floats(0.3, 3.0),
    tx=st.tuples(coordinate, coordinate, coordinate),
    rx=st.lists(st.tuples(coordinate, coordinate, coordinate), min_size=1, max_size=5),
)
def test_a_planes_specular_points_obey_the_mirror_law(normal, distance, tx, rx) -> None:
    """Each specular point lies on the plane, the rays to it from T and R make equal angles
    with the normal on opposite sides, and the path through it is the image's distance."""
    u = _unit(normal)
    t = np.asarray(tx, dtype=float)
    receivers = np.asarray(rx, dtype=float)
    transmitters = np.broadcast_to(t, receivers.shape)
    # Every transducer on the sensor's side, at least 5 cm from the plane.
    assume(np.all(distance - (receivers - t) @ u > 0.05))
    foot = t + distance * u
    specular = surfaces.specular_points_m(distance * u, transmitters, receivers, t)
    np.testing.assert_allclose((specular - foot) @ u, 0.0, atol=1e-9)
    to_t = (t - specular) / np.linalg.norm(t - specular, axis=1, keepdims=True)
    to_r = (receivers - specular) / np.linalg.norm(receivers - specular, axis=1, keepdims=True)
    np.testing.assert_allclose(to_t @ u, to_r @ u, atol=1e-9)  # angle of incidence = of reflection
    tangential = (to_t - (to_t @ u)[:, None] * u) + (to_r - (to_r @ u)[:, None] * u)
    np.testing.assert_allclose(tangential, 0.0, atol=1e-9)  # in one plane with the normal, opposite
    unfolded = np.linalg.norm(t - specular, axis=1) + np.linalg.norm(receivers - specular, axis=1)
    paths = surfaces.plane_paths_m((distance * u)[None], transmitters, receivers, t)[0]
    np.testing.assert_allclose(unfolded, paths, rtol=1e-12)


@settings(max_examples=200, deadline=None)
@given(
    foot=st.tuples(coordinate, coordinate, st.floats(0.5, 2.0)),
    angle=st.floats(0.0, math.pi),
    turn=st.floats(0.0, math.pi),
    tx=st.tuples(coordinate, coordinate, coordinate),
)
def test_a_corners_image_is_where_its_two_mirrors_put_it(foot, angle, turn, tx) -> None:
    """The half turn about the edge is the composition of the mirrors in any two perpendicular
    planes through the edge, in either order."""
    t_ref = np.zeros(3)
    g = np.asarray(foot, dtype=float)
    parameters = np.array([[*g, angle]])
    helper = surfaces._helper(g[None])
    e = surfaces._edge_directions(parameters, t_ref, helper)[0]
    np.testing.assert_allclose(e @ g, 0.0, atol=1e-12)  # G is the edge's foot from the reference
    # Two perpendicular normals, both perpendicular to the edge, turned by `turn` about it.
    first = np.cross(e, [1.0, 0.0, 0.0] if abs(e[0]) < 0.9 else [0.0, 1.0, 0.0])
    first /= np.linalg.norm(first)
    second = np.cross(e, first)
    n_a = math.cos(turn) * first + math.sin(turn) * second
    n_b = np.cross(e, n_a)
    t = np.asarray(tx, dtype=float)
    image = surfaces.corner_images_m(parameters, t[None], t_ref, helper)[0, 0]
    np.testing.assert_allclose(image, _mirror(_mirror(t, g, n_a), g, n_b), atol=1e-12)
    np.testing.assert_allclose(image, _mirror(_mirror(t, g, n_b), g, n_a), atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    position=st.tuples(coordinate, coordinate, st.floats(0.6, 1.8)),
    noise_seed=st.integers(0, 2**16),
)
def test_swapping_transmitters_and_receivers_leaves_the_class_unchanged(position, noise_seed) -> None:
    """Reciprocity: every hypothesis's path is the same both ways round, so the fits, their
    chi-squares and the class do not change when every channel's T and R change places."""
    p = np.asarray(position, dtype=float)
    transmitters = np.repeat(TRANSMITTERS, 4, axis=0)
    receivers = np.tile(CROSS, (2, 1))
    paths = surfaces.point_paths_m(p[None], transmitters, receivers)
    paths = paths + np.random.default_rng(noise_seed).normal(0.0, SIGMA_M, paths.shape)
    reference = np.zeros(3)
    forward = surfaces.hypotheses(transmitters, receivers, paths, SIGMA_M, reference, p[None])
    backward = surfaces.hypotheses(receivers, transmitters, paths, SIGMA_M, reference, p[None])
    assert forward.kind[0] == backward.kind[0]
    np.testing.assert_allclose(forward.chi2[:, :2], backward.chi2[:, :2], rtol=1e-5, atol=1e-6)


@settings(max_examples=100, deadline=None)
@given(
    image=st.tuples(st.floats(-1.5, 1.5), st.floats(-1.5, 1.5), st.floats(0.5, 4.0)),
    flat=st.booleans(),
)
def test_the_closed_form_finds_a_virtual_source_from_exact_paths(image, flat) -> None:
    """Four receivers in a plane (the cross), or five in space: exact paths give the source back."""
    receivers = CROSS if flat else np.vstack([CROSS, [[0.1, 0.05, 0.2]]])
    v = np.asarray(image, dtype=float)
    paths = surfaces.mirror_paths_m(v[None], receivers)
    found = surfaces.image_start_m(receivers, paths, np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(found[0], v, atol=1e-7)


def test_class_probabilities_are_schwarz_weights() -> None:
    """Equal fits of equal size share the probability; one more parameter costs sqrt(n)."""
    equal = surfaces.class_probabilities(np.array([[1.0, 1.0, np.inf]]), np.array([4]))
    np.testing.assert_allclose(equal, [[0.5, 0.5, 0.0]])
    costlier = surfaces.class_probabilities(np.array([[1.0, 1.0, 1.0]]), np.array([8]))
    np.testing.assert_allclose(costlier[0, 2] / costlier[0, 1], 1 / math.sqrt(8))
    worse = surfaces.class_probabilities(np.array([[0.0, 2 * math.log(9), np.inf]]), np.array([4]))
    np.testing.assert_allclose(worse[0, 0] / worse[0, 1], 9.0)


@settings(max_examples=100, deadline=None)
@given(
    across=st.tuples(st.floats(-1.0, 1.0), st.floats(0.4, 2.0)),
    axis=unit_vectors,
)
def test_an_edges_path_is_keller_s_shortest_path(across, axis) -> None:
    """The unfolded edge path equals the simulator's shortest path via a long segment."""
    e, a, b = surfaces.axis_basis(_unit(axis))
    line = np.array([across])
    point_on_line = across[0] * a + across[1] * b
    assume(abs(point_on_line @ np.array([0.0, 0.0, 1.0])) > 0.3)
    start, end = point_on_line - 50 * e, point_on_line + 50 * e
    transmitters = np.broadcast_to(TRANSMITTERS[1], CROSS.shape)
    paths = surfaces.edge_paths_m(line, e, transmitters, CROSS)[0]
    q = edge_point(TRANSMITTERS[1], CROSS, start, end)
    expected = np.linalg.norm(q - TRANSMITTERS[1], axis=1) + np.linalg.norm(q - CROSS, axis=1)
    np.testing.assert_allclose(paths, expected, rtol=1e-9)
    foot = surfaces.edge_foot_m(line, e, TRANSMITTERS[1])[0]
    np.testing.assert_allclose(foot, edge_point(TRANSMITTERS[1], TRANSMITTERS[1], start, end), atol=1e-9)


# --- the simulator's reflectors, classified ---------------------------------------------


def _simulated(reflectors, labels: tuple[str, ...], n_tx: int, seed: int = 0):
    """Channels and noisy paths of the first path labelled one of ``labels`` per channel."""
    states = states_at(reflectors, np.zeros(1), frequency_hz=50e3, speed_of_sound_m_s=343.0)
    transmitters, receivers, paths = [], [], []
    for t in TRANSMITTERS[:n_tx]:
        found = echo_paths(t, CROSS, states, max_order=2)
        columns = [k for k, label in enumerate(found.labels or ()) if label in labels]
        transmitters.append(np.broadcast_to(t, CROSS.shape))
        receivers.append(CROSS)
        paths.append(np.nanmin(found.path_m[0][:, columns], axis=1))
    measured = np.concatenate(paths)
    assert np.all(np.isfinite(measured))
    noise = np.random.default_rng(seed).normal(0.0, SIGMA_M, measured.shape)
    return np.vstack(transmitters), np.vstack(receivers), (measured + noise)[None]


WALL = Plane(centre_m=[0.3, 0.0, 1.2], normal=[-0.3, 0.0, -1.0], width_m=3.0, height_m=3.0)
BALL = PointReflector([0.3, 0.1, 1.0])
CORNER = corner([-0.6, -1.5, 1.4], [-0.6, 1.5, 1.4], [0, 0, -1], [1, 0, 0], 2.0)
DOUBLE_BOUNCE = ("plane 0 > plane 1", "plane 1 > plane 0")


def _classify(transmitters, receivers, paths):
    """The hypotheses from a rough start 1 m ahead, and the first group's description."""
    start = np.array([[0.0, 0.0, 1.0]])
    found = surfaces.hypotheses(transmitters, receivers, paths, SIGMA_M, TRANSMITTERS[0], start)
    return found, surfaces.describe(found, 0, transmitters, receivers, TRANSMITTERS[0])


@pytest.mark.parametrize("n_tx", [1, 2])
def test_a_tilted_wall_is_a_plane_with_its_normal_and_distance(n_tx: int) -> None:
    """A wall 17 degrees off the boresight: a plane, with the normal within 0.1 degree and the
    distance within 0.5 mm of the simulator's (noise 0.5 mm a path)."""
    _, (surface, position, _) = _classify(*_simulated([WALL], ("plane 0",), n_tx))
    assert surface.kind == "plane"
    assert surface.confidence > 0.7
    true_normal = WALL.normal  # the simulator's faces the sensor, as echoloc reports it
    distance = -float(WALL.centre_m @ WALL.normal)
    assert surface.normal is not None
    assert math.degrees(math.acos(min(1.0, surface.normal @ true_normal))) < 0.1
    assert surface.distance_m == pytest.approx(distance, abs=0.5e-3)
    np.testing.assert_allclose(position, -distance * true_normal, atol=1e-3)  # the foot from T0
    assert surface.extent_m is not None
    assert 0.0 < surface.extent_m < 0.5  # the heard patch spans about half the array


@pytest.mark.parametrize("n_tx", [1, 2])
def test_a_ball_off_the_diagonals_is_a_point(n_tx: int) -> None:
    _, (surface, position, _) = _classify(*_simulated([BALL], ("point 0",), n_tx))
    assert surface.kind == "point"
    np.testing.assert_allclose(position, BALL.position_m, atol=2e-3)


def test_one_transmitter_cannot_tell_a_corner_from_a_plane() -> None:
    """A corner's double bounce is one image, as a plane's: with one transmitter it is reported
    as a plane (there is no corner hypothesis to test), at the edge's foot."""
    found, (surface, position, _) = _classify(*_simulated(CORNER, DOUBLE_BOUNCE, 1))
    assert not np.isfinite(found.chi2[0, 2])
    assert surface.kind == "plane"
    np.testing.assert_allclose(position, [-0.6, 0.0, 1.4], atol=2e-3)


def test_two_transmitters_tell_a_corner_and_find_its_edge() -> None:
    """With a second transmitter across the edge, the half turn and the mirror differ: the
    corner wins, at its edge's foot, with the edge's direction within a degree."""
    _, (surface, position, _) = _classify(*_simulated(CORNER, DOUBLE_BOUNCE, 2))
    assert surface.kind == "corner"
    assert surface.confidence > 0.99
    np.testing.assert_allclose(position, [-0.6, 0.0, 1.4], atol=3e-3)
    assert surface.edge_direction is not None
    assert math.degrees(math.acos(abs(surface.edge_direction @ [0.0, 1.0, 0.0]))) < 1.0


def test_an_edge_along_the_baseline_makes_a_corner_the_planes_twin() -> None:
    """Kleeman and Kuc's blind case: a corner whose edge runs along the transmitters' baseline
    makes exactly a plane's images, so the corner is not offered as a hypothesis, even where it
    is fitted (a gate of probability ~0 makes every hypothesis fail it, so the corner is tried);
    across the baseline the same corner is one."""
    baseline = TRANSMITTERS[1] - TRANSMITTERS[0]
    along = baseline / np.linalg.norm(baseline)
    across = np.array([along[1], -along[0], 0.0])  # level, perpendicular to the baseline
    centre = np.array([0.0, 0.0, 1.3]) - 0.4 * across  # the whole array on the open side
    twin = corner(centre - 2 * along, centre + 2 * along, [0.0, 0.0, -1.0], across, 2.0)
    start = np.array([[0.0, 0.0, 1.0]])
    transmitters, receivers, paths = _simulated(twin, DOUBLE_BOUNCE, 2)
    found = surfaces.hypotheses(transmitters, receivers, paths, SIGMA_M, TRANSMITTERS[0], start, 1e-12)
    assert found.corner is not None  # fitted ...
    assert not np.isfinite(found.chi2[0, 2])  # ... and dropped as the plane's twin
    assert surfaces.KINDS[found.kind[0]] == "plane"
    transmitters, receivers, paths = _simulated(CORNER, DOUBLE_BOUNCE, 2)
    found = surfaces.hypotheses(transmitters, receivers, paths, SIGMA_M, TRANSMITTERS[0], start, 1e-12)
    assert np.isfinite(found.chi2[0, 2])
    assert surfaces.KINDS[found.kind[0]] == "corner"


def test_an_edge_is_no_point() -> None:
    """A vertical post across the cross: its echo slides along it, which no point explains."""
    post = Edge([0.2, -1.0, 1.0], [0.2, 1.0, 1.0], strength_m=0.3)
    transmitters, receivers, paths = _simulated([post], ("edge 0",), 1)
    found, _ = _classify(transmitters, receivers, paths)
    vertical = np.array([0.0, 1.0, 0.0])
    _, a, b = surfaces.axis_basis(vertical)
    ahead = np.array([0.0, 0.0, 1.0])
    edge = surfaces.fit(
        lambda q: surfaces.edge_paths_m(q, vertical, transmitters, receivers),
        np.array([[ahead @ a, ahead @ b]]),
        paths,
        np.full(paths.shape, SIGMA_M),
    )
    assert edge.chi2[0] < 15.0
    assert found.chi2[0, 0] > 100.0


@settings(max_examples=100, deadline=None)
@given(
    position=st.tuples(coordinate, coordinate, st.floats(0.5, 2.0)),
    transmitter=st.integers(0, 1),
)
def test_the_analytic_jacobians_are_the_models_derivatives(position, transmitter) -> None:
    """Point, plane and image paths: the closed-form gradients against central differences."""
    p = np.array([position], dtype=float)
    transmitters = np.broadcast_to(TRANSMITTERS[transmitter], CROSS.shape)
    reference = TRANSMITTERS[0]
    cases = [
        (
            lambda q: surfaces.point_paths_m(q, transmitters, CROSS),
            surfaces.point_jacobian(p, transmitters, CROSS),
        ),
        (
            lambda q: surfaces.plane_paths_m(q, transmitters, CROSS, reference),
            surfaces.plane_jacobian(p, transmitters, CROSS, reference),
        ),
        (lambda q: surfaces.mirror_paths_m(q, CROSS), surfaces.mirror_jacobian(CROSS)(p)),
    ]
    for model, exact in cases:
        step = 1e-6
        numeric = np.stack(
            [
                (model(p + step * np.eye(3)[k]) - model(p - step * np.eye(3)[k])) / (2 * step)
                for k in range(3)
            ],
            axis=-1,
        )
        np.testing.assert_allclose(exact, numeric, atol=1e-7)


@settings(max_examples=60, deadline=None)
@given(across=st.tuples(st.floats(-1.0, 1.0), st.floats(0.4, 2.0)), axis=unit_vectors)
def test_the_edges_jacobian_is_its_derivative(across, axis) -> None:
    line = np.array([across])
    transmitters = np.broadcast_to(TRANSMITTERS[1], CROSS.shape)
    exact = surfaces.edge_jacobian(line, np.asarray(axis), transmitters, CROSS)
    step = 1e-6
    numeric = np.stack(
        [
            (
                surfaces.edge_paths_m(line + step * np.eye(2)[k], np.asarray(axis), transmitters, CROSS)
                - surfaces.edge_paths_m(line - step * np.eye(2)[k], np.asarray(axis), transmitters, CROSS)
            )
            / (2 * step)
            for k in range(2)
        ],
        axis=-1,
    )
    np.testing.assert_allclose(exact, numeric, atol=1e-6)


@pytest.mark.skipif(not surfaces.HAVE_NUMBA, reason="the kernels run compiled only with numba")
@settings(max_examples=40, deadline=None)
@given(
    position=st.tuples(coordinate, coordinate, st.floats(0.6, 1.8)),
    noise_seed=st.integers(0, 2**16),
)
def test_the_compiled_fits_are_the_numpy_fits(position, noise_seed) -> None:
    """Point, plane, image, edge and corner fits, compiled and in numpy (with the Jacobians the
    numpy path uses), from the same noisy paths and rough starts: the same parameters,
    chi-squares and covariances (to rounding)."""
    rng = np.random.default_rng(noise_seed)
    p = np.asarray(position, dtype=float)
    tx = np.repeat(TRANSMITTERS, 4, axis=0)
    rx = np.tile(CROSS, (2, 1))
    paths = surfaces.point_paths_m(p[None], tx, rx) + rng.normal(0.0, SIGMA_M, (1, 8))
    sigmas = np.full(paths.shape, SIGMA_M)
    start = p[None] + rng.normal(0.0, 0.05, (1, 3))
    axis = np.array([0.0, 1.0, 0.0])
    _, a, b = surfaces.axis_basis(axis)
    t0 = TRANSMITTERS[0]
    cases = [
        (
            surfaces.CompiledModel(surfaces.POINT_MODEL, tx, rx),
            lambda q: surfaces.point_paths_m(q, tx, rx),
            lambda q: surfaces.point_jacobian(q, tx, rx),
            start,
        ),
        (
            surfaces.CompiledModel(surfaces.PLANE_MODEL, tx, rx, t0),
            lambda q: surfaces.plane_paths_m(q, tx, rx, t0),
            lambda q: surfaces.plane_jacobian(q, tx, rx, t0),
            start,
        ),
        (
            surfaces.CompiledModel(surfaces.IMAGE_MODEL, rx, rx),
            lambda q: surfaces.mirror_paths_m(q, rx),
            surfaces.mirror_jacobian(rx),
            2 * start,
        ),
        (
            surfaces.CompiledModel(surfaces.EDGE_MODEL, tx, rx, axis=axis),
            lambda q: surfaces.edge_paths_m(q, axis, tx, rx),
            lambda q: surfaces.edge_jacobian(q, axis, tx, rx),
            np.array([[start[0] @ a, start[0] @ b]]),
        ),
    ]
    corner_start = np.array([[*start[0], 0.3]])
    helpers = surfaces._helper(start - t0)
    corner_paths = surfaces.mirror_paths_images(
        surfaces.corner_images_m(np.array([[*p, 0.2]]), tx, t0, helpers), rx
    ) + rng.normal(0.0, SIGMA_M, (1, 8))
    corner = surfaces.fit(
        lambda q: surfaces.mirror_paths_images(surfaces.corner_images_m(q, tx, t0, helpers), rx),
        corner_start,
        corner_paths,
        sigmas,
        kernel=surfaces.CompiledModel(surfaces.CORNER_MODEL, tx, rx, t0, helpers=helpers),
    )
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(surfaces, "_COMPILED", False)
        corner_reference = surfaces.fit(
            lambda q: surfaces.mirror_paths_images(surfaces.corner_images_m(q, tx, t0, helpers), rx),
            corner_start,
            corner_paths,
            sigmas,
        )
    np.testing.assert_allclose(corner.parameters, corner_reference.parameters, atol=1e-6)
    np.testing.assert_allclose(corner.chi2, corner_reference.chi2, rtol=1e-4, atol=1e-5)
    for kernel, model, jacobian, first in cases:
        compiled = surfaces.fit(model, first, paths, sigmas, jacobian=jacobian, kernel=kernel)
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(surfaces, "_COMPILED", False)
            reference = surfaces.fit(model, first, paths, sigmas, jacobian=jacobian, kernel=kernel)
        np.testing.assert_allclose(compiled.parameters, reference.parameters, atol=1e-7)
        np.testing.assert_allclose(compiled.chi2, reference.chi2, rtol=1e-5, atol=1e-6)
        scale = float(np.max(np.abs(reference.covariance)))
        np.testing.assert_allclose(compiled.covariance, reference.covariance, rtol=1e-4, atol=1e-6 * scale)


@pytest.mark.parametrize(
    ("degrees", "residual_mm"), [(0.0, 0.0), (5.0, 0.053), (10.0, 0.212), (20.0, 0.829), (30.0, 1.789)]
)
def test_one_transmitter_tells_a_point_from_a_mirror_only_off_the_boresight(
    degrees: float, residual_mm: float
) -> None:
    """docs/METHOD.md 10.10: the best image fitted to a point's exact paths (1 m away, turned
    about y, the cross of radius 0.25 m) misses them by the RMS residual the docs quote, and not
    at all on a diagonal, where the two receiver pairs see the same."""
    transmitters = np.zeros((4, 3))
    for azimuth, expected in ((0.0, residual_mm), (45.0, 0.0)):
        t, a = math.radians(degrees), math.radians(azimuth)
        point = np.array([[math.sin(t) * math.cos(a), math.sin(t) * math.sin(a), math.cos(t)]])
        paths = surfaces.point_paths_m(point, transmitters, CROSS)
        start = surfaces.image_start_m(CROSS, paths, np.array([0.0, 0.0, 1.0]))
        image = surfaces.fit(lambda v: surfaces.mirror_paths_m(v, CROSS), start, paths, np.full((1, 4), 1e-3))
        residual = paths - surfaces.mirror_paths_m(image.parameters, CROSS)
        assert float(np.sqrt(np.mean(residual**2))) * 1e3 == pytest.approx(expected, abs=2e-3)
