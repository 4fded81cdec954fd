"""Tests of echoloc.sim.reflectors: echo-path geometry and amplitudes of every reflector kind.

Sources: the image-source method (Allen & Berkley, JASA 65 (1979) 943) with Borish's
visibility test (JASA 75 (1984) 1827); the law of reflection; Keller's equal-angle
law for edge rays (JOSA 52 (1962) 116); the rigid-sphere partial-wave series
(Anderson 1950, Faran 1951), its Rayleigh limit F = (5/3)(ka)^2 (Morse & Ingard,
Theoretical Acoustics ch. 8) and geometric limit F -> 1 (Neubauer, Vogt & Dragonette,
JASA 55 (1974) 1123), and the optical theorem sigma_t = (4 pi / k) Im f(0);
reciprocity of the wave equation (swapping source and receiver leaves every path).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import quad
from scipy.optimize import minimize, minimize_scalar
from scipy.spatial.transform import Rotation

from echoloc.errors import SceneError
from echoloc.sim.reflectors import (
    EchoPaths,
    Edge,
    Plane,
    PointReflector,
    ReflectorStates,
    Sphere,
    concat_paths,
    corner,
    echo_paths,
    edge_point,
    rigid_sphere_amplitude,
    rigid_sphere_form_function,
    sphere_specular_point,
    states_at,
    truth_positions_m,
)

C = 343.2
F_HZ = 40e3
ORIGIN = np.zeros(3)


def states(*reflectors: object, times_s: object = (0.0,)) -> ReflectorStates:
    return states_at(reflectors, times_s, frequency_hz=F_HZ, speed_of_sound_m_s=C)  # type: ignore[arg-type]


def unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def mirror(p: np.ndarray, centre: np.ndarray, normal: np.ndarray) -> np.ndarray:
    n = unit(np.asarray(normal, dtype=float))
    return p - 2 * np.dot(p - centre, n) * n


def column(paths: EchoPaths, label: str) -> int:
    assert paths.labels is not None
    return paths.labels.index(label)


# ---------------------------------------------------------------------------------------
# Planes: image source, specular point, finite extent.


def test_plane_path_is_distance_from_mirrored_transmitter() -> None:
    centre = np.array([0.1, -0.2, 1.7])
    normal = np.array([0.2, 0.1, -1.0])
    plane = Plane(centre, normal, width_m=3.0, height_m=3.0, reflection=0.8)
    tx = np.array([0.02, 0.01, 0.0])
    rx = np.array([[0.1, 0.0, 0.0], [-0.07, 0.05, 0.03]])
    paths = echo_paths(tx, rx, states(plane))
    image = mirror(tx, centre, normal)
    expected = np.linalg.norm(rx - image, axis=1)
    np.testing.assert_allclose(paths.path_m[0, :, 0], expected, rtol=1e-13)
    np.testing.assert_allclose(paths.gain[0, :, 0], 0.8 / expected, rtol=1e-13)
    np.testing.assert_array_equal(paths.order, [1])


def test_specular_point_lies_on_plane_with_equal_angles() -> None:
    centre = np.array([-0.3, 0.2, 2.0])
    normal = unit(np.array([0.3, -0.2, -1.0]))
    plane = Plane(centre, normal, width_m=4.0, height_m=4.0)
    tx = np.array([0.05, 0.0, 0.0])
    rx = np.array([[0.3, -0.1, 0.1]])
    paths = echo_paths(tx, rx, states(plane))
    spot = tx + paths.first_leg_m[0, 0, 0] * paths.departure[0, 0, 0]
    same_spot = rx[0] + paths.last_leg_m[0, 0, 0] * paths.arrival[0, 0, 0]
    np.testing.assert_allclose(spot, same_spot, atol=1e-12)
    assert abs(np.dot(spot - centre, normal)) < 1e-12
    incoming = paths.departure[0, 0, 0]
    outgoing = -paths.arrival[0, 0, 0]
    # Law of reflection: the tangential part is kept, the normal part reversed.
    np.testing.assert_allclose(outgoing, incoming - 2 * np.dot(incoming, normal) * normal, atol=1e-12)
    assert paths.first_leg_m[0, 0, 0] + paths.last_leg_m[0, 0, 0] == pytest.approx(paths.path_m[0, 0, 0])


@pytest.mark.parametrize("axis", [0, 1])
@pytest.mark.parametrize(("shift_m", "echo"), [(1e-6, True), (-1e-6, False)])
def test_finite_plane_echo_only_when_specular_point_is_inside(axis: int, shift_m: float, echo: bool) -> None:
    # Monostatic: the specular point is the foot (0, 0, 1). The plate (0.5 m wide along
    # x, 0.3 m high along y) is moved along one axis so that the foot is just inside
    # (shift > 0) or just outside its border.
    half = [0.25, 0.15][axis]
    centre = np.array([0.0, 0.0, 1.0])
    centre[axis] = half - shift_m
    plate = Plane(centre, [0, 0, -1], width_m=0.5, height_m=0.3, width_axis=[1, 0, 0])
    paths = echo_paths(ORIGIN, ORIGIN[None], states(plate))
    assert np.isfinite(paths.path_m[0, 0, 0]) == echo
    assert (paths.gain[0, 0, 0] != 0) == echo
    assert np.isfinite(truth_positions_m(ORIGIN, states(plate))[0, 0]).all() == echo
    if echo:
        assert paths.path_m[0, 0, 0] == pytest.approx(2.0)
    else:
        assert np.all(np.isnan(paths.departure[0, 0, 0]))


def test_no_plane_echo_when_receiver_is_behind_the_plane() -> None:
    plane = Plane([0, 0, 1.0], [0, 0, -1], width_m=5.0, height_m=5.0)
    paths = echo_paths(ORIGIN, np.array([[0.1, 0, 0.0], [0.1, 0, 2.0]]), states(plane))
    assert np.isfinite(paths.path_m[0, 0, 0])
    assert np.isnan(paths.path_m[0, 1, 0])
    assert paths.gain[0, 1, 0] == 0


def test_plane_default_and_given_width_axes() -> None:
    wall = Plane([0, 0, 1.0], [0, 0, -1], 1.0, 1.0)
    np.testing.assert_allclose(wall.width_axis, [1, 0, 0])
    np.testing.assert_allclose(wall.spin_axis, np.cross(wall.normal, wall.width_axis))
    floor = Plane([0, 0.5, 1.0], [0, -2, 0], 1.0, 1.0)
    np.testing.assert_allclose(floor.normal, [0, -1, 0])
    np.testing.assert_allclose(floor.width_axis, [1, 0, 0])
    tilted = Plane([0, 0, 1.0], [0, 0, -1], 1.0, 1.0, width_axis=[1, 0, 0.5])
    np.testing.assert_allclose(tilted.width_axis, [1, 0, 0], atol=1e-15)


# ---------------------------------------------------------------------------------------
# Points.


def test_point_echo_energy_falls_as_inverse_square_of_both_ranges() -> None:
    s = 0.7
    rx = np.array([[0.2, 0.0, 0.0]])
    positions = [[0.0, 0.0, 0.5], [0.3, 0.1, 1.0], [-0.4, 0.2, 2.0], [0.0, 0.0, 4.0]]
    paths = echo_paths(ORIGIN, rx, states(*(PointReflector(p, s) for p in positions)))
    r1 = np.linalg.norm(np.array(positions), axis=1)
    r2 = np.linalg.norm(np.array(positions) - rx[0], axis=1)
    energy = paths.gain[0, 0] ** 2
    np.testing.assert_allclose(energy * (r1 * r2) ** 2, s**2, rtol=1e-13)
    np.testing.assert_allclose(paths.path_m[0, 0], r1 + r2, rtol=1e-14)
    np.testing.assert_allclose(paths.departure[0, 0], unit(np.array(positions)), atol=1e-15)


def test_absent_points_give_nan_paths_and_zero_gain() -> None:
    base = states(PointReflector([0, 0, 1.0]), times_s=[0.0, 0.1])
    extra = np.full((2, 2, 3), np.nan)
    strengths = np.full((2, 2), np.nan)
    extra[1, 0] = [0.1, 0.0, 2.0]
    strengths[1, 0] = 2.0
    paths = echo_paths(ORIGIN, ORIGIN[None], base.with_points(extra, strengths), max_order=2)
    first = paths.path_m[:, 0, :3]
    assert np.isnan(first[0, 1])
    assert np.isnan(first[:, 2]).all()
    assert first[1, 1] == pytest.approx(2 * math.hypot(0.1, 2.0))
    assert np.all(paths.gain[np.isnan(paths.path_m)] == 0)
    assert np.all(np.isnan(paths.arrival[np.isnan(paths.path_m)]))


def test_point_pairs_both_ways() -> None:
    p1, p2 = np.array([0.1, 0.0, 1.0]), np.array([-0.2, 0.1, 1.5])
    rx = np.array([[0.05, 0.0, 0.0]])
    paths = echo_paths(ORIGIN, rx, states(PointReflector(p1, 2.0), PointReflector(p2, 0.5)), max_order=2)
    for label, a, b in (("point 0 > point 1", p1, p2), ("point 1 > point 0", p2, p1)):
        k = column(paths, label)
        r1, r12, r2 = np.linalg.norm(a), np.linalg.norm(b - a), np.linalg.norm(b - rx[0])
        assert paths.path_m[0, 0, k] == pytest.approx(r1 + r12 + r2, rel=1e-14)
        assert paths.gain[0, 0, k] == pytest.approx(1.0 / (r1 * r12 * r2), rel=1e-14)
        assert paths.order[k] == 2
    assert "point 0 > point 1" not in (
        echo_paths(ORIGIN, rx, states(PointReflector(p1)), max_order=2).labels or ()
    )
    no_pairs = echo_paths(
        ORIGIN, rx, states(PointReflector(p1), PointReflector(p2)), max_order=2, point_pairs=False
    )
    assert no_pairs.n_paths == 2


# ---------------------------------------------------------------------------------------
# Spheres.


def test_form_function_geometric_limit() -> None:
    # F(50) from the series is 0.998; the creeping-wave ripple around 1 is below 1 %.
    assert rigid_sphere_form_function(50.0) == pytest.approx(1.0, abs=0.02)
    ka = np.linspace(45.0, 55.0, 401)
    values = rigid_sphere_form_function(ka)
    assert np.max(np.abs(values - 1)) < 0.01
    assert np.mean(values) == pytest.approx(1.0, abs=2e-3)


def test_form_function_rayleigh_law() -> None:
    ka = np.array([0.005, 0.01, 0.02, 0.05, 0.08])
    values = rigid_sphere_form_function(ka)
    slope = np.polyfit(np.log(ka), np.log(values), 1)[0]
    assert slope == pytest.approx(2.0, abs=0.01)
    # Rigid immovable sphere, long wavelength: f = (k^2 a^3 / 3)(-1 + 1.5 cos theta).
    assert values[0] / ka[0] ** 2 == pytest.approx(5.0 / 3.0, rel=1e-3)
    # With its sign: 2 f / a = (2/3)(ka)^2 (-1 + 1.5 cos theta), real to leading order.
    for angle, factor in ((math.pi, -5.0 / 3.0), (0.0, 1.0 / 3.0), (math.pi / 2, -2.0 / 3.0)):
        g = complex(rigid_sphere_amplitude(0.01, angle))
        assert g.real / 0.01**2 == pytest.approx(factor, rel=1e-3)
        assert abs(g.imag) < 1e-3 * abs(g.real)


@pytest.mark.parametrize("ka", [0.5, 2.0, 8.0])
def test_partial_waves_obey_the_optical_theorem(ka: float) -> None:
    # sigma_t = (4 pi / k) Im f(0) = integral of |f|^2 over the sphere; with g = 2 f / a:
    # Im g(0) = (ka / 4) * integral_0^pi |g(theta)|^2 sin(theta) d theta.
    def integrand(theta: float) -> float:
        return float(abs(rigid_sphere_amplitude(ka, theta)) ** 2 * math.sin(theta))

    scattered = ka / 4 * quad(integrand, 0.0, math.pi, limit=200)[0]
    assert float(rigid_sphere_amplitude(ka, 0.0).imag) == pytest.approx(scattered, rel=1e-6)


def test_sphere_strength_is_half_radius_times_form_function() -> None:
    sphere = Sphere([0, 0, 1.0], 0.05)
    ka = 2 * math.pi * F_HZ / C * 0.05
    assert sphere.strength_m(F_HZ, C) == pytest.approx(
        0.025 * float(rigid_sphere_form_function(ka)), rel=1e-14
    )
    assert Sphere([0, 0, 1.0], 2.0).strength_m(F_HZ, C) == pytest.approx(1.0, rel=0.02)
    assert states(sphere).sphere_strengths_m[0] == sphere.strength_m(F_HZ, C)


def test_sphere_monostatic_path() -> None:
    centre, a = np.array([0.13, -0.07, 1.21]), 0.08
    tx = np.array([0.01, 0.02, 0.0])
    sphere = Sphere(centre, a)
    paths = echo_paths(tx, tx[None], states(sphere))
    d = np.linalg.norm(centre - tx)
    assert paths.path_m[0, 0, 0] == pytest.approx(2 * d - 2 * a, rel=1e-14)
    assert paths.gain[0, 0, 0] == pytest.approx(sphere.strength_m(F_HZ, C) / (d - a) ** 2, rel=1e-13)
    np.testing.assert_allclose(truth_positions_m(tx, states(sphere))[0, 0], centre - a * unit(centre - tx))


@pytest.mark.parametrize(
    ("rx", "centre", "a"),
    [
        ([0.3, 0.0, 0.0], [0.0, 0.1, 0.6], 0.2),
        ([1.5, 0.4, 0.2], [0.4, -0.2, 0.9], 0.3),
        ([0.02, 0.0, 0.0], [0.5, 0.3, 3.0], 0.05),
    ],
)
def test_sphere_bistatic_specular_point(rx: list[float], centre: list[float], a: float) -> None:
    tx, receiver, c = ORIGIN, np.array(rx), np.array(centre)
    paths = echo_paths(tx, receiver[None], states(Sphere(c, a)))
    spot = tx + paths.first_leg_m[0, 0, 0] * paths.departure[0, 0, 0]
    assert np.linalg.norm(spot - c) == pytest.approx(a, rel=1e-12)
    # Law of reflection: the outward normal bisects the rays to transmitter and receiver.
    bisector = unit(tx - spot) + unit(receiver - spot)
    np.testing.assert_allclose(np.cross(unit(spot - c), bisector), 0.0, atol=1e-10)
    assert np.dot(bisector, spot - c) > 0

    # The shortest path over the surface, found independently.
    def length(angles: np.ndarray) -> float:
        theta, phi = angles
        s = c + a * np.array(
            [math.sin(theta) * math.cos(phi), math.sin(theta) * math.sin(phi), math.cos(theta)]
        )
        return float(np.linalg.norm(s - tx) + np.linalg.norm(s - receiver))

    start = unit(unit(tx - c) + unit(receiver - c))
    best = minimize(length, [math.acos(start[2]), math.atan2(start[1], start[0])], method="Nelder-Mead",
                    options={"xatol": 1e-12, "fatol": 1e-14, "maxiter": 4000})  # fmt: skip
    assert paths.path_m[0, 0, 0] == pytest.approx(best.fun, rel=1e-9)
    assert paths.path_m[0, 0, 0] <= best.fun + 1e-12


def test_no_sphere_echo_in_its_shadow_or_from_inside() -> None:
    sphere = Sphere([0, 0, 1.0], 0.2)
    behind = echo_paths(ORIGIN, np.array([[0.0, 0.0, 2.0], [0.0, 0.0, 1.1]]), states(sphere))
    assert np.isnan(behind.path_m[0, :, 0]).all()
    _, ok = sphere_specular_point(ORIGIN, [0, 0, 2.0], [0, 0, 1.0], 0.2)
    assert not ok


# ---------------------------------------------------------------------------------------
# Edges and corners.


def test_edge_point_is_the_stationary_point() -> None:
    start, end = np.array([-0.5, 0.3, 1.0]), np.array([0.6, -0.1, 1.4])
    tx, rx = np.array([0.0, 0.0, 0.0]), np.array([0.4, 0.2, 0.1])
    point = edge_point(tx, rx, start, end)
    along = unit(end - start)
    length = np.linalg.norm(end - start)

    def path(t: float) -> float:
        e = start + t * along
        return float(np.linalg.norm(e - tx) + np.linalg.norm(e - rx))

    best = minimize_scalar(path, bounds=(0.0, length), method="bounded", options={"xatol": 1e-12})
    np.testing.assert_allclose(point, start + best.x * along, atol=1e-7)
    # Keller: incoming and outgoing rays make equal angles with the edge.
    assert np.dot(unit(point - tx), along) == pytest.approx(np.dot(unit(rx - point), along), abs=1e-12)
    paths = echo_paths(tx, rx[None], states(Edge(start, end, strength_m=0.2)))
    r1, r2 = np.linalg.norm(point - tx), np.linalg.norm(point - rx)
    assert paths.path_m[0, 0, 0] == pytest.approx(r1 + r2, rel=1e-14)
    assert paths.gain[0, 0, 0] == pytest.approx(0.2 / (r1 * r2), rel=1e-13)
    # Beyond the end the shortest point is the end itself.
    np.testing.assert_allclose(edge_point([3.0, -1.0, 2.0], [3.2, -1.1, 1.8], start, end), end, atol=1e-15)


def test_corner_faces_share_the_edge_and_enclose_the_wedge() -> None:
    n_a, n_b = np.array([1.0, 0, 0]), np.array([0, 1.0, 0])
    face_a, face_b, edge = corner(
        [0, 0, 1.0], [0, 0, 2.0], n_a, n_b, 0.4, reflection=0.9, edge_strength_m=0.05
    )
    np.testing.assert_allclose(face_a.centre_m, [0, 0.2, 1.5])  # face a extends towards +y (n_b)
    np.testing.assert_allclose(face_b.centre_m, [0.2, 0, 1.5])
    assert face_a.width_m == pytest.approx(1.0)
    assert face_a.height_m == pytest.approx(0.4)
    assert face_a.reflection == 0.9
    assert edge.strength_m == 0.05
    np.testing.assert_allclose(abs(np.dot(face_a.width_axis, [0, 0, 1])), 1.0)


@pytest.mark.parametrize("rx", [[0.0, 0.0, 0.0], [0.06, 0.01, 0.0], [-0.1, 0.03, 0.02]])
def test_corner_double_bounce_is_the_image_through_the_edge_line(rx: list[float]) -> None:
    # A 90° corner whose open side faces the sensor: its two reflections equal a turn
    # by 180° about the edge line, so the path is |image - receiver|.
    normal_a, normal_b = unit(np.array([-1.0, 0, -1])), unit(np.array([1.0, 0, -1]))
    start, end = np.array([0.02, -0.5, 1.5]), np.array([0.02, 0.5, 1.5])
    faces = corner(start, end, normal_a, normal_b, face_width_m=0.6, reflection=0.9)
    tx = np.array([0.05, 0.02, 0.0])
    receiver = np.array(rx)
    paths = echo_paths(tx, receiver[None], states(*faces), max_order=2)
    on_line = start + np.dot(tx - start, unit(end - start)) * unit(end - start)
    image = 2 * on_line - tx
    double = [column(paths, "plane 0 > plane 1"), column(paths, "plane 1 > plane 0")]
    found = paths.path_m[0, 0, double]
    assert np.isfinite(found).any()
    np.testing.assert_allclose(found[np.isfinite(found)], np.linalg.norm(image - receiver), rtol=1e-13)
    np.testing.assert_allclose(
        paths.gain[0, 0, double][np.isfinite(found)], 0.81 / np.linalg.norm(image - receiver)
    )
    # The two reflection points lie on the two faces.
    k = double[int(np.argmax(np.isfinite(found)))]
    first = paths.labels[k].split(" > ")[0]  # type: ignore[index]
    face_first, face_last = (faces[0], faces[1]) if first == "plane 0" else (faces[1], faces[0])
    spot_1 = tx + paths.first_leg_m[0, 0, k] * paths.departure[0, 0, k]
    spot_2 = receiver + paths.last_leg_m[0, 0, k] * paths.arrival[0, 0, k]
    assert abs(np.dot(spot_1 - face_first.centre_m, face_first.normal)) < 1e-12
    assert abs(np.dot(spot_2 - face_last.centre_m, face_last.normal)) < 1e-12


def test_monostatic_corner_double_bounce_through_the_edge_counts_once() -> None:
    # Seen from the transmitter itself, a 90° corner's double bounce runs through the
    # edge, on the border of both faces: both orders exist and share R^2 / path.
    faces = corner(
        [0.1, -0.5, 1.2], [0.1, 0.5, 1.2], [-1.0, 0, -1], [1.0, 0, -1], face_width_m=0.4, reflection=0.9
    )
    tx = np.array([-0.03, 0.02, 0.0])
    paths = echo_paths(tx, tx[None], states(*faces), max_order=2)
    double = [column(paths, "plane 0 > plane 1"), column(paths, "plane 1 > plane 0")]
    distance = math.hypot(0.1 + 0.03, 1.2)
    np.testing.assert_allclose(paths.path_m[0, 0, double], 2 * distance, rtol=1e-13)
    assert paths.gain[0, 0, double].sum() == pytest.approx(0.81 / (2 * distance), rel=1e-13)
    # Off the monostatic point only one order exists, with the whole gain.
    apart = echo_paths(tx, tx[None] + [0.02, 0, 0], states(*faces), max_order=2)
    assert np.isfinite(apart.path_m[0, 0, double]).sum() == 1
    assert apart.gain[0, 0, double].sum() == pytest.approx(0.81 / np.nanmax(apart.path_m[0, 0, double]))


def test_plane_with_point_both_ways() -> None:
    wall = Plane([0, 0, 2.0], [0, 0, -1], width_m=4.0, height_m=4.0, reflection=0.7)
    p, s = np.array([0.2, 0.1, 1.0]), 1.5
    rx = np.array([0.05, 0.0, 0.0])
    paths = echo_paths(ORIGIN, rx[None], states(wall, PointReflector(p, s)), max_order=2)
    image_tx = mirror(ORIGIN, wall.centre_m, wall.normal)
    image_rx = mirror(rx, wall.centre_m, wall.normal)
    k = column(paths, "plane 0 > point 0")
    leg_a, leg_b = np.linalg.norm(p - image_tx), np.linalg.norm(p - rx)
    assert paths.path_m[0, 0, k] == pytest.approx(leg_a + leg_b, rel=1e-14)
    assert paths.gain[0, 0, k] == pytest.approx(s * 0.7 / (leg_a * leg_b), rel=1e-13)
    spot = paths.first_leg_m[0, 0, k] * paths.departure[0, 0, k]
    assert spot[2] == pytest.approx(2.0)
    k = column(paths, "point 0 > plane 0")
    leg_a, leg_b = np.linalg.norm(p), np.linalg.norm(image_rx - p)
    assert paths.path_m[0, 0, k] == pytest.approx(leg_a + leg_b, rel=1e-14)
    assert paths.gain[0, 0, k] == pytest.approx(s * 0.7 / (leg_a * leg_b), rel=1e-13)
    # A small plate that the unfolded path misses: no second-order echo, first order kept.
    plate = Plane([1.0, 0, 2.0], [0, 0, -1], width_m=0.2, height_m=0.2)
    missed = echo_paths(ORIGIN, rx[None], states(plate, PointReflector(p, s)), max_order=2)
    assert np.isnan(missed.path_m[0, 0, column(missed, "plane 0 > point 0")])
    assert np.isnan(missed.path_m[0, 0, column(missed, "point 0 > plane 0")])
    assert np.isfinite(missed.path_m[0, 0, column(missed, "point 0")])


# ---------------------------------------------------------------------------------------
# Reciprocity and rigid motion, every kind, second order included.

SCENE = (
    PointReflector([0.137, -0.052, 1.113], 0.9),
    PointReflector([-0.211, 0.093, 1.571], 1.3),
    Sphere([0.043, 0.217, 1.937], 0.117),
    Plane([0.071, -0.033, 2.513], [0.11, -0.07, -1.0], width_m=2.71, height_m=2.29, reflection=0.83),
    Edge([-0.61, 0.31, 1.29], [-0.37, -0.43, 1.41], strength_m=0.07),
    *corner(
        [0.347, -0.41, 1.31], [0.347, 0.39, 1.31], [-0.7071, 0.0, -0.7071], [0.7071, 0.0, -0.7071], 0.53, 0.91
    ),
)

transducer = st.tuples(
    st.floats(-0.3, 0.3, allow_nan=False),
    st.floats(-0.3, 0.3, allow_nan=False),
    st.floats(-0.2, 0.2, allow_nan=False),
)


def reversed_label(label: str) -> str:
    return " > ".join(reversed(label.split(" > ")))


@settings(max_examples=60, deadline=None)
@given(tx=transducer, rx=transducer)
def test_reciprocity_for_every_kind_and_order(tx: tuple[float, ...], rx: tuple[float, ...]) -> None:
    world = states(*SCENE, times_s=[0.0])
    forward = echo_paths(np.array(tx), np.array([rx]), world, max_order=2)
    backward = echo_paths(np.array(rx), np.array([tx]), world, max_order=2)
    assert forward.labels is not None
    assert backward.labels is not None
    index = [backward.labels.index(reversed_label(label)) for label in forward.labels]
    np.testing.assert_allclose(backward.path_m[..., index], forward.path_m, rtol=1e-11)
    np.testing.assert_allclose(backward.gain[..., index], forward.gain, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(backward.last_leg_m[..., index], forward.first_leg_m, rtol=1e-9)
    np.testing.assert_allclose(backward.arrival[..., index, :], forward.departure, atol=1e-9)
    np.testing.assert_array_equal(backward.order[index], forward.order)


def test_scene_has_echoes_of_every_kind() -> None:
    # Guards the reciprocity test against passing on NaN only.
    paths = echo_paths([0.01, 0.0, 0.0], [[-0.02, 0.01, 0.0]], states(*SCENE), max_order=2)
    assert paths.labels is not None
    alive = {label for label, ok in zip(paths.labels, np.isfinite(paths.path_m[0, 0]), strict=True) if ok}
    for wanted in ("point 0", "sphere 0", "plane 0", "edge 0", "plane 1 > plane 2", "plane 0 > sphere 0",
                   "edge 0 > plane 0", "point 1 > point 0"):  # fmt: skip
        assert wanted in alive


def test_rigid_motion_preserves_every_path() -> None:
    times = [0.0, 0.05, 0.1]
    moving = (
        PointReflector([0.1, 0.0, 1.0], velocity_m_s=[0.3, -0.1, 0.5]),
        Plane(
            [0, 0, 2.0], [0.1, 0.0, -1.0], 3.0, 2.0, angular_velocity_deg_s=40.0, velocity_m_s=[0, 0, -0.2]
        ),
        *SCENE[1:],
    )
    world = states(*moving, times_s=times)
    tx = np.array([0.01, -0.02, 0.0])
    rx = np.array([[0.06, 0.0, 0.0], [-0.05, 0.03, 0.01]])
    turn = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    shift = np.array([1.0, -2.0, 0.5])
    moved = world.transformed(np.tile(turn, (3, 1, 1)), np.tile(shift, (3, 1)))
    before = echo_paths(tx, rx, world, max_order=2)
    after = echo_paths(turn @ tx + shift, rx @ turn.T + shift, moved, max_order=2)
    assert np.isfinite(before.path_m).sum() > 20
    np.testing.assert_allclose(after.path_m, before.path_m, rtol=1e-11)
    np.testing.assert_allclose(after.gain, before.gain, rtol=1e-9)
    np.testing.assert_allclose(after.departure, before.departure @ turn.T, atol=1e-9)
    np.testing.assert_allclose(
        truth_positions_m(turn @ tx + shift, moved), truth_positions_m(tx, world) @ turn.T + shift, atol=1e-12
    )


# ---------------------------------------------------------------------------------------
# Motion, states, truth.


def test_states_at_moves_every_kind_by_velocity_times_time() -> None:
    v = np.array([0.2, -0.1, 0.4])
    t = np.array([0.0, 0.5, 2.0])
    moved = states(
        PointReflector([0, 0, 1.0], velocity_m_s=v),
        Sphere([0, 0, 2.0], 0.1, velocity_m_s=v),
        Plane([0, 0, 3.0], [0, 0, -1], 1.0, 1.0, velocity_m_s=v),
        Edge([0, 0, 1.0], [0, 1.0, 1.0], velocity_m_s=v),
        times_s=t,
    )
    np.testing.assert_allclose(moved.points_m[:, 0], [0, 0, 1.0] + t[:, None] * v)
    np.testing.assert_allclose(moved.sphere_centres_m[:, 0], [0, 0, 2.0] + t[:, None] * v)
    np.testing.assert_allclose(moved.plane_centres_m[:, 0], [0, 0, 3.0] + t[:, None] * v)
    np.testing.assert_allclose(moved.edge_ends_m[:, 0], [0, 1.0, 1.0] + t[:, None] * v)
    np.testing.assert_allclose(moved.plane_normals[:, 0], np.tile([0, 0, -1.0], (3, 1)))
    assert moved.n_frames == 3
    assert moved.n_truth == 4


def test_take_keeps_the_chosen_frames_paths_exactly() -> None:
    """states.take(rows) gives, frame for frame, the paths of those rows of the whole batch."""
    v = np.array([0.2, -0.1, 0.4])
    moved = states(
        PointReflector([0.1, 0, 1.0], velocity_m_s=v),
        Sphere([0, 0.1, 2.0], 0.1, velocity_m_s=v),
        Plane([0, 0, 3.0], [0.1, 0, -1], 2.0, 2.0, velocity_m_s=v, angular_velocity_deg_s=5.0),
        Edge([0, 0, 1.0], [0, 1.0, 1.0], velocity_m_s=v),
        times_s=np.array([0.0, 0.5, 1.0, 2.0]),
    )
    receivers = np.array([[0.25, 0, 0], [-0.25, 0, 0]])
    rows = np.array([3, 1])
    whole = echo_paths(ORIGIN, receivers, moved, max_order=2)
    part = echo_paths(ORIGIN, receivers, moved.take(rows), max_order=2)
    np.testing.assert_array_equal(part.path_m, whole.path_m[rows])
    np.testing.assert_array_equal(part.gain, whole.gain[rows])
    np.testing.assert_array_equal(
        truth_positions_m(ORIGIN, moved.take(rows)), truth_positions_m(ORIGIN, moved)[rows]
    )


@pytest.mark.parametrize("spin_axis", [None, [0.3, 0.0, 1.0]])
def test_states_at_spins_plane_normal_by_omega_t(spin_axis: list[float] | None) -> None:
    plane = Plane([0.5, 0, 2.0], [0, 0, -1], 1.0, 1.0, width_axis=[1, 0, 0], angular_velocity_deg_s=90.0,
                  spin_axis=spin_axis)  # fmt: skip
    t = np.array([0.0, 0.5, 1.0, 1.7])
    moved = states(plane, times_s=t)
    axis = unit(np.array(spin_axis)) if spin_axis is not None else np.array([0, -1.0, 0])
    turns = Rotation.from_rotvec(np.radians(90.0) * t[:, None] * axis)
    np.testing.assert_allclose(moved.plane_normals[:, 0], turns.apply([0, 0, -1.0]), atol=1e-14)
    np.testing.assert_allclose(moved.plane_width_axes[:, 0], turns.apply([1.0, 0, 0]), atol=1e-14)
    np.testing.assert_allclose(moved.plane_centres_m[:, 0], np.tile([0.5, 0, 2.0], (4, 1)))
    if spin_axis is None:
        np.testing.assert_allclose(moved.plane_normals[2, 0], [1.0, 0, 0], atol=1e-15)
        angle = np.degrees(np.arccos(np.clip(moved.plane_normals[:, 0] @ [0, 0, -1.0], -1, 1)))
        np.testing.assert_allclose(angle, [0, 45, 90, 153], atol=1e-9)


def test_truth_positions_of_every_kind() -> None:
    tx = np.array([0.0, 0.0, 0.0])
    world = states(
        PointReflector([0.1, 0.0, 1.0]),
        Sphere([0.0, 0.3, 1.5], 0.1),
        Plane([0.0, 0.0, 2.0], [0, 0, -1], 1.0, 1.0),
        Plane([2.0, 0.0, 2.0], [0, 0, -1], 1.0, 1.0),
        Edge([-1.0, 0.2, 1.2], [1.0, 0.2, 1.2]),
        Edge([0.5, 0.0, 1.0], [1.0, 0.0, 1.0]),
    )
    truth = truth_positions_m(tx, world)
    assert truth.shape == (1, 6, 3)
    np.testing.assert_allclose(truth[0, 0], [0.1, 0.0, 1.0])
    np.testing.assert_allclose(truth[0, 1], [0.0, 0.3, 1.5] - 0.1 * unit(np.array([0.0, 0.3, 1.5])))
    np.testing.assert_allclose(truth[0, 2], [0.0, 0.0, 2.0])
    assert np.isnan(truth[0, 3]).all()
    np.testing.assert_allclose(truth[0, 4], [0.0, 0.2, 1.2])
    np.testing.assert_allclose(truth[0, 5], [0.5, 0.0, 1.0])
    # First-order paths come in the same order; monostatic, each is twice the range.
    paths = echo_paths(tx, tx[None], world)
    np.testing.assert_allclose(paths.path_m[0, 0], 2 * np.linalg.norm(truth[0], axis=1), rtol=1e-12)


def test_empty_kinds_and_concatenation() -> None:
    none = states_at([], [0.0, 1.0], frequency_hz=F_HZ, speed_of_sound_m_s=C)
    assert none.points_m.shape == (2, 0, 3)
    assert none.plane_sizes_m.shape == (0, 2)
    paths = echo_paths(ORIGIN, np.zeros((3, 3)), none, max_order=2)
    assert paths.path_m.shape == (2, 3, 0)
    assert paths.departure.shape == (2, 3, 0, 3)
    one = echo_paths(
        ORIGIN, np.zeros((3, 3)), ReflectorStates.empty(2).with_points(np.ones((2, 1, 3)), np.ones((2, 1)))
    )
    joined = concat_paths([one, paths, one])
    assert joined.n_paths == 2
    assert joined.labels == ("point 0", "point 0")
    np.testing.assert_array_equal(joined.path_m[..., 1], one.path_m[..., 0])


# ---------------------------------------------------------------------------------------
# Bad input: SceneError naming the field.


@pytest.mark.parametrize(
    ("make", "field"),
    [
        (lambda: PointReflector([0, np.nan, 1]), "PointReflector.position_m"),
        (lambda: PointReflector([0, 0, 1], strength_m=np.inf), "PointReflector.strength_m"),
        (lambda: PointReflector([0, 0, 1], velocity_m_s=[0, 0]), "PointReflector.velocity_m_s"),
        (lambda: Sphere([0, 0, 1], -0.1), "Sphere.radius_m"),
        (lambda: Sphere([0, 0, 1], 0.0), "Sphere.radius_m"),
        (lambda: Sphere([np.inf, 0, 1], 0.1), "Sphere.centre_m"),
        (lambda: Sphere([0, 0, 1], 0.1).strength_m(0.0, C), "frequency_hz"),
        (lambda: Plane([0, 0, 1], [0, 0, 0], 1, 1), "Plane.normal"),
        (lambda: Plane([0, 0, 1], [0, 0, 1], 1, 1, reflection=1.5), "Plane.reflection"),
        (lambda: Plane([0, 0, 1], [0, 0, 1], 1, 1, reflection=-1.01), "Plane.reflection"),
        (lambda: Plane([0, 0, 1], [0, 0, 1], 0.0, 1), "Plane.width_m"),
        (lambda: Plane([0, 0, 1], [0, 0, 1], 1, np.nan), "Plane.height_m"),
        (lambda: Plane([0, 0, 1], [0, 0, 1], 1, 1, width_axis=[0, 0, -2]), "Plane.width_axis"),
        (lambda: Plane([0, 0, 1], [0, 0, 1], 1, 1, spin_axis=[0, 0, 0]), "Plane.spin_axis"),
        (
            lambda: Plane([0, 0, 1], [0, 0, 1], 1, 1, angular_velocity_deg_s=np.nan),
            "Plane.angular_velocity_deg_s",
        ),
        (lambda: Plane([0, 0, np.nan], [0, 0, 1], 1, 1), "Plane.centre_m"),
        (lambda: Edge([0, 0, 1], [0, 0, 1]), "Edge has zero length: start_m = end_m"),
        (lambda: Edge([0, 0, 1], [np.nan, 0, 1]), "Edge.end_m"),
        (lambda: Edge([0, 0, 1], [1, 0, 1], strength_m=np.nan), "Edge.strength_m"),
        (lambda: corner([0, 0, 1], [0, 1, 1], [1, 0, 0], [2, 0, 0], 0.5), "corner normals"),
        (lambda: corner([0, 0, 1], [0, 1, 1], [1, 0.1, 0], [0, 0, 1], 0.5), "corner normal_a"),
        (lambda: corner([0, 0, 1], [0, 1, 1], [1, 0, 0], [0, 0, 1], -0.5), "corner face_width_m"),
        (lambda: corner([0, 0, 1], [0, 0, 1], [1, 0, 0], [0, 0, 1], 0.5), "corner edge"),
        (lambda: rigid_sphere_form_function([1.0, 0.0]), "ka"),
        (lambda: states_at([], [0.0, np.nan], frequency_hz=F_HZ, speed_of_sound_m_s=C), "times_s"),
        (lambda: states_at([], [0.0], frequency_hz=F_HZ, speed_of_sound_m_s=-1.0), "speed_of_sound_m_s"),
        (lambda: echo_paths(ORIGIN, ORIGIN[None], ReflectorStates.empty(1), max_order=3), "max_order"),
        (lambda: echo_paths(ORIGIN, ORIGIN, ReflectorStates.empty(1)), "receivers_m"),
        (lambda: echo_paths([0, np.inf, 0], ORIGIN[None], ReflectorStates.empty(1)), "transmitter_m"),
        (lambda: ReflectorStates.empty(2).transformed(np.ones((2, 3, 3)), np.zeros((2, 3))), "rotation"),
        (
            lambda: ReflectorStates.empty(2).transformed(np.tile(np.eye(3), (2, 1, 1)), np.zeros(3)),
            "translation_m",
        ),
        (lambda: ReflectorStates.empty(2).with_points(np.zeros((1, 1, 3)), np.zeros((1, 1))), "points_m"),
        (lambda: ReflectorStates.empty(2).with_points(np.zeros((2, 1, 3)), np.zeros(2)), "strengths_m"),
        (lambda: concat_paths([]), "concat_paths"),
    ],
)
def test_bad_input_raises_scene_error_naming_the_field(make: object, field: str) -> None:
    with pytest.raises(SceneError, match=field.replace(".", r"\.")):
        make()  # type: ignore[operator]
