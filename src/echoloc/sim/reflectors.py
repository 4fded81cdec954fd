"""Reflectors and the geometry of their echo paths: lengths, amplitudes, directions.

One transmitter emits, every receiver records; a path leaves the transmitter, meets
one reflector (first order) or two (second order) and reaches a receiver. This module
describes the reflectors (:class:`PointReflector`, :class:`Sphere`, :class:`Plane`,
:class:`Edge`, and :func:`corner` which builds two planes and an edge), moves them to
the frames' times (:func:`states_at`, giving :class:`ReflectorStates`), and finds
every path with its length, amplitude factor and directions (:func:`echo_paths`,
giving :class:`EchoPaths`). Lengths in m, times in s, speeds in m/s; any one frame of
reference (the caller's), typically the sensor frame (z boresight, x right, y down).

Amplitude convention: an echo is ``gain`` times the emitted pulse, where the emitted
pulse is the pressure at 1 m from the transmitter; ``gain`` holds spreading,
reflection coefficients and reflector strengths, not transducer directivity or air
absorption. A point reflector of strength ``s`` (m) returns ``s / (r_tx r_rx)``.

Models and sources
------------------
- **Point reflector**: an isotropic re-radiator, ``s / (r_tx r_rx)``.
- **Rigid sphere**: the far-field scattering amplitude from the exact partial-wave
  series of the rigid (immovable) sphere, V. C. Anderson, "Sound scattering from a
  fluid sphere", J. Acoust. Soc. Am. 22 (1950) 426-431 (the rigid sphere is its limit
  of infinite density and stiffness) and J. J. Faran, "Sound scattering by solid
  cylinders and spheres", J. Acoust. Soc. Am. 23 (1951) 405-418. With
  ``exp(-i omega t)``, an incident plane wave ``exp(ikz)`` and ``p_s = f(theta)
  exp(ikr) / r``, the rigid boundary ``d(p_i + p_s)/dr = 0`` at ``r = a`` gives
  ``f(theta) = (i/k) sum_n (2n+1) j_n'(ka) / h_n'(ka) P_n(cos theta)``
  (``h_n = j_n + i y_n``). The *form function* is ``F = 2 |f| / a`` (W. G. Neubauer,
  R. H. Vogt and L. R. Dragonette, "Acoustic reflection from elastic spheres. I.
  Steady-state signals", J. Acoust. Soc. Am. 55 (1974) 1123-1129): ``F -> 1`` for
  ``ka >> 1`` (the geometric echo, ``|f| = a/2``), and for ``ka << 1`` the Rayleigh law
  ``f = (k^2 a^3 / 3)(-1 + (3/2) cos theta)``, so backscatter ``F = (5/3)(ka)^2`` (P. M.
  Morse and K. U. Ingard, *Theoretical Acoustics*, McGraw-Hill 1968, ch. 8). The
  series is cut after ``ka + 4.05 (ka)^(1/3) + 10`` terms (W. J. Wiscombe, "Improved
  Mie scattering algorithms", Appl. Opt. 19 (1980) 1505-1509, plus a margin).
  The echo's strength is ``|f| = (a/2) F(ka)`` at the carrier and its path is the
  specular (shortest) one via the sphere's surface, with ``strength / (r1 r2)``, r1 and
  r2 measured to the specular point. This is an approximation: geometric optics for
  a convex mirror of radius a (focal length a/2) gives, monostatic, the amplitude
  ``(a/2) / (r (r + a))`` with r the range to the surface, so ``(a/2) / r^2`` is too
  large by the factor ``1 + a/r`` (5 % for a = 5 cm at 1 m); far from the sphere both
  tend to the far-field ``(a/2) / r^2``.
- **Finite plane**: the image-source method (J. B. Allen and D. A. Berkley, "Image
  method for efficiently simulating small-room acoustics", J. Acoust. Soc. Am. 65
  (1979) 943-950) with the visibility test of J. Borish, "Extension of the image model
  to arbitrary polyhedra", J. Acoust. Soc. Am. 75 (1984) 1827-1836: an image path is
  an echo only where the straight line from the image to the receiver crosses the
  reflector inside its outline. Gain ``R / path`` (spherical spreading from the
  image); no edge diffraction and no Fresnel-zone loss for small plates.
- **Edge**: the point of the segment where ``r_tx + r_rx`` is least; on the open
  segment that is Keller's stationary point, where the incoming and outgoing rays
  make equal angles with the edge (J. B. Keller, "Geometrical theory of
  diffraction", J. Opt. Soc. Am. 52 (1962) 116-130). The amplitude is point-like,
  ``strength / (r1 r2)``: not the diffraction coefficient of GTD nor the
  Biot-Tolstoy solution, only an echo at the right time from the right place.
- **Second order** (``max_order = 2``): plane-plane by the image of the image (a
  dihedral corner's double bounce); a point, sphere or edge with a plane, both ways
  round, by the image of the transmitter or of the receiver; point-point. Occlusion
  (one reflector shadowing another's path) is not modelled. Borders: a reflection
  point up to 1 nm outside a rectangle counts as inside (rounding); a reflector
  within 1 nm of a plane (a corner's edge in its own faces) makes no path with it;
  a double bounce through the line where two faces meet (a 90° corner seen by a
  transceiver: it always passes through the edge) lies on the border of both
  orders, which then share the gain, half each, so that it counts once.
- Spin of a plane: Rodrigues' rotation formula ``v cos t + (k x v) sin t + k (k . v)(1 - cos t)``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.special import eval_legendre, spherical_jn, spherical_yn

from echoloc.errors import SceneError

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

_NEWTON_STEPS = 60
"""Most safeguarded Newton steps for the sphere's specular point (it converges in a handful)."""

_ANGLE_TOLERANCE_RAD = 1e-14
"""The Newton iteration stops when no angle moves more than this."""

_BOUNDARY_TOLERANCE_M = 1e-9
"""A reflection point this close outside a rectangle still counts as inside (rounding)."""

_PERPENDICULAR_TOLERANCE = 1e-6
"""How far (as a cosine) a normal given to :func:`corner` may lean onto the edge; more is an error."""


def _zeros3() -> FloatArray:
    return np.zeros(3)


# ---------------------------------------------------------------------------------------
# Input checks: one SceneError naming the field and the value.


def _vector(value: ArrayLike, name: str) -> FloatArray:
    """``value`` as 3 finite floats, or SceneError naming ``name``."""
    try:
        vector = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise SceneError(f"{name} must be 3 numbers, got {value!r}") from exc
    if vector.shape != (3,):
        raise SceneError(f"{name} must be 3 numbers, got shape {vector.shape}")
    if not np.all(np.isfinite(vector)):
        raise SceneError(f"{name} must be finite, got {vector.tolist()}")
    return vector


def _direction(value: ArrayLike, name: str) -> FloatArray:
    """``value`` as a unit vector, or SceneError if it is not finite or is zero."""
    vector = _vector(value, name)
    norm = float(np.linalg.norm(vector))
    if norm == 0:
        raise SceneError(f"{name} must be a non-zero vector, got {vector.tolist()}")
    return vector / norm


def _scalar(value: float, name: str) -> float:
    """``value`` as a finite float, or SceneError naming ``name``."""
    try:
        number = float(value)
    except (TypeError, ValueError) as exc:
        raise SceneError(f"{name} must be a number, got {value!r}") from exc
    if not math.isfinite(number):
        raise SceneError(f"{name} must be finite, got {number}")
    return number


def _positive(value: float, name: str) -> float:
    number = _scalar(value, name)
    if number <= 0:
        raise SceneError(f"{name} must be > 0, got {number}")
    return number


def _reflection(value: float, name: str) -> float:
    number = _scalar(value, name)
    if abs(number) > 1:
        raise SceneError(f"{name} must be a pressure reflection coefficient with |R| <= 1, got {number}")
    return number


def _set(obj: object, name: str, value: object) -> None:
    object.__setattr__(obj, name, value)


# ---------------------------------------------------------------------------------------
# Rigid-sphere scattering.


def rigid_sphere_amplitude(ka: ArrayLike, angle_rad: float = math.pi) -> NDArray[np.complex128]:
    """Normalised far-field scattering amplitude ``2 f(theta) / a`` of a rigid sphere.

    The exact partial-wave series (Anderson 1950, Faran 1951; see the module notes),
    ``2 f / a = (2i / ka) sum_n (2n+1) j_n'(ka) / h_n'(ka) P_n(cos theta)``, for an
    incident plane wave along +z and ``theta`` measured from +z (``pi`` is
    backscatter). Time convention ``exp(-i omega t)``: ``Im f(0) > 0``, and the optical
    theorem ``sigma_total = (4 pi / k) Im f(0)`` holds term by term.

    Parameters
    ----------
    ka : array_like
        Wavenumber times radius, > 0.
    angle_rad : float
        Scattering angle, rad (pi: back towards the source).

    Returns
    -------
    ndarray of complex
        ``2 f / a``, the shape of ``ka``.
    """
    x = np.asarray(ka, dtype=float)
    if x.size == 0:
        return np.zeros(x.shape, dtype=complex)
    if not (np.all(np.isfinite(x)) and np.all(x > 0)):
        bad = x.ravel()[~(np.isfinite(x.ravel()) & (x.ravel() > 0))][0]
        raise SceneError(f"ka must be finite and > 0, got {bad}")
    largest = float(np.max(x))
    n = np.arange(math.ceil(largest + 4.05 * largest ** (1.0 / 3.0) + 10.0) + 1)
    xx = x[..., None]
    jp = spherical_jn(n, xx, derivative=True)
    yp = spherical_yn(n, xx, derivative=True)
    # j'/(j' + i y') without overflow: y' grows without bound for n >> ka (scipy gives
    # inf, then NaN), where the ratio is (j'/y') / (j'/y' + i) -> 0.
    small_y = np.abs(jp) >= np.abs(yp)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):  # the branch np.where drops
        q = np.where(small_y, yp / np.where(small_y, jp, 1.0), 0.0)
        p = np.where(small_y, 0.0, jp / np.where(small_y, 1.0, yp))
        ratio = np.where(small_y, 1.0 / (1.0 + 1j * q), p / (p + 1j))
    ratio = np.where(np.isfinite(yp), ratio, 0.0)  # y' overflowed (n >> ka): the term is 0
    legendre = eval_legendre(n, math.cos(angle_rad))
    total = np.sum((2 * n + 1) * ratio * legendre, axis=-1)
    return np.asarray(2j / x * total, dtype=complex)


def rigid_sphere_form_function(ka: ArrayLike) -> FloatArray:
    """Backscatter form function ``F(ka) = 2 |f(pi)| / a`` of a rigid sphere.

    ``F -> 1`` for ``ka >> 1`` (geometric echo), ``F = (5/3)(ka)^2`` for ``ka << 1``
    (Rayleigh). Neubauer, Vogt and Dragonette (1974); see the module notes.
    """
    return np.abs(rigid_sphere_amplitude(ka, math.pi))


# ---------------------------------------------------------------------------------------
# Reflectors (world frame, at time 0).


@dataclass(frozen=True, eq=False)
class PointReflector:
    """An isotropic point scatterer: echo ``strength_m / (r_tx r_rx)`` times the pulse.

    ``position_m`` (3,) at time 0, moving with ``velocity_m_s`` (3,).
    """

    position_m: FloatArray
    strength_m: float = 1.0
    velocity_m_s: FloatArray = field(default_factory=_zeros3)

    def __post_init__(self) -> None:
        _set(self, "position_m", _vector(self.position_m, "PointReflector.position_m"))
        _set(self, "strength_m", _scalar(self.strength_m, "PointReflector.strength_m"))
        _set(self, "velocity_m_s", _vector(self.velocity_m_s, "PointReflector.velocity_m_s"))


@dataclass(frozen=True, eq=False)
class Sphere:
    """A rigid sphere of radius ``radius_m`` centred at ``centre_m`` (3,) at time 0."""

    centre_m: FloatArray
    radius_m: float
    velocity_m_s: FloatArray = field(default_factory=_zeros3)

    def __post_init__(self) -> None:
        _set(self, "centre_m", _vector(self.centre_m, "Sphere.centre_m"))
        _set(self, "radius_m", _positive(self.radius_m, "Sphere.radius_m"))
        _set(self, "velocity_m_s", _vector(self.velocity_m_s, "Sphere.velocity_m_s"))

    def strength_m(self, frequency_hz: float, speed_of_sound_m_s: float) -> float:
        """Backscatter amplitude ``|f(pi)| = (a/2) F(ka)``, m, at one frequency.

        ``F`` is :func:`rigid_sphere_form_function` (exact partial-wave series), so the
        strength is ``a/2`` for ``ka >> 1`` and ``(5/6) k^2 a^3`` for ``ka << 1``.
        """
        frequency = _positive(frequency_hz, "frequency_hz")
        speed = _positive(speed_of_sound_m_s, "speed_of_sound_m_s")
        ka = 2 * math.pi * frequency / speed * self.radius_m
        return 0.5 * self.radius_m * float(rigid_sphere_form_function(ka))


@dataclass(frozen=True, eq=False)
class Plane:
    """A finite rectangular reflector, reflecting from either side.

    The rectangle is centred at ``centre_m``, ``width_m`` along ``width_axis`` and
    ``height_m`` along the height axis ``normal x width_axis``. ``normal`` is
    normalised. ``width_axis`` is made orthogonal to the normal (its component along
    the normal is removed) and normalised; None gives the horizontal direction
    ``normal x y`` of a frame whose y axis is vertical (the sensor frame, y down): for
    a wall facing the sensor (normal -z) that is +x; for a floor or ceiling (normal
    along y) it is +x projected onto the plane. ``reflection`` is the pressure
    reflection coefficient, ``|R| <= 1`` (negative: a pressure-release surface).

    Motion: the centre moves with ``velocity_m_s``; the normal and width axis turn at
    ``angular_velocity_deg_s`` about ``spin_axis`` (right-hand rule) through the
    centre; ``spin_axis`` None is the height axis.
    """

    centre_m: FloatArray
    normal: FloatArray
    width_m: float
    height_m: float
    width_axis: FloatArray | None = None
    reflection: float = 1.0
    velocity_m_s: FloatArray = field(default_factory=_zeros3)
    angular_velocity_deg_s: float = 0.0
    spin_axis: FloatArray | None = None

    def __post_init__(self) -> None:
        _set(self, "centre_m", _vector(self.centre_m, "Plane.centre_m"))
        normal = _direction(self.normal, "Plane.normal")
        _set(self, "normal", normal)
        _set(self, "width_m", _positive(self.width_m, "Plane.width_m"))
        _set(self, "height_m", _positive(self.height_m, "Plane.height_m"))
        if self.width_axis is None:
            width = np.cross(normal, [0.0, 1.0, 0.0])
            if np.linalg.norm(width) < _PERPENDICULAR_TOLERANCE:
                width = np.array([1.0, 0.0, 0.0]) - normal[0] * normal
        else:
            given = _direction(self.width_axis, "Plane.width_axis")
            width = given - np.dot(given, normal) * normal
            if np.linalg.norm(width) < _PERPENDICULAR_TOLERANCE:
                raise SceneError(
                    f"Plane.width_axis {given.tolist()} is parallel to the normal {normal.tolist()}"
                )
        width = width / np.linalg.norm(width)
        _set(self, "width_axis", width)
        _set(self, "reflection", _reflection(self.reflection, "Plane.reflection"))
        _set(self, "velocity_m_s", _vector(self.velocity_m_s, "Plane.velocity_m_s"))
        _set(
            self,
            "angular_velocity_deg_s",
            _scalar(self.angular_velocity_deg_s, "Plane.angular_velocity_deg_s"),
        )
        if self.spin_axis is None:
            _set(self, "spin_axis", np.cross(normal, width))
        else:
            _set(self, "spin_axis", _direction(self.spin_axis, "Plane.spin_axis"))

    @property
    def height_axis(self) -> FloatArray:
        """Unit vector along the height, ``normal x width_axis``."""
        return np.asarray(np.cross(self.normal, _resolved(self.width_axis)), dtype=float)


@dataclass(frozen=True, eq=False)
class Edge:
    """A straight edge from ``start_m`` to ``end_m`` returning a point-like echo.

    The echo comes from the point of the segment with the shortest path (see the
    module notes), with amplitude ``strength_m / (r1 r2)``. ``concave`` marks the edge
    where a concave corner's two faces meet (:func:`corner` sets it): its truth class
    (:func:`truth_kinds`) is then ``"corner"``, else ``"point"``.
    """

    start_m: FloatArray
    end_m: FloatArray
    strength_m: float = 0.1
    velocity_m_s: FloatArray = field(default_factory=_zeros3)
    concave: bool = False

    def __post_init__(self) -> None:
        start = _vector(self.start_m, "Edge.start_m")
        end = _vector(self.end_m, "Edge.end_m")
        if not np.linalg.norm(end - start) > 0:
            raise SceneError(f"Edge has zero length: start_m = end_m = {start.tolist()}")
        _set(self, "start_m", start)
        _set(self, "end_m", end)
        _set(self, "strength_m", _scalar(self.strength_m, "Edge.strength_m"))
        _set(self, "velocity_m_s", _vector(self.velocity_m_s, "Edge.velocity_m_s"))


Reflector = PointReflector | Sphere | Plane | Edge


def _resolved(vector: FloatArray | None) -> FloatArray:
    """A vector that ``__post_init__`` has filled in (never None after construction)."""
    if vector is None:  # pragma: no cover - __post_init__ always sets it
        raise SceneError("a plane axis was not resolved")
    return vector


def corner(
    edge_start_m: ArrayLike,
    edge_end_m: ArrayLike,
    normal_a: ArrayLike,
    normal_b: ArrayLike,
    face_width_m: float,
    reflection: float = 1.0,
    edge_strength_m: float = 0.1,
    *,
    velocity_m_s: ArrayLike = (0.0, 0.0, 0.0),
) -> tuple[Plane, Plane, Edge]:
    """A concave dihedral corner: two rectangular faces sharing an edge, and the edge.

    The open region of the corner is where both normals point (the intersection of
    their half-spaces); it is a wedge of opening ``pi - angle(normal_a, normal_b)``
    (90° for perpendicular normals). Each face lies in the plane through the edge
    with its normal and extends ``face_width_m`` from the edge towards the side the
    other normal points to, over the edge's whole length. The double reflection is
    found by :func:`echo_paths` with ``max_order = 2`` (plane-plane paths).

    Parameters
    ----------
    edge_start_m, edge_end_m : array_like (3,)
        Ends of the shared edge, m.
    normal_a, normal_b : array_like (3,)
        Face normals, perpendicular to the edge (within 1e-6 as a cosine; the rest
        is removed), not parallel to each other.
    face_width_m : float
        How far each face reaches from the edge, m.
    reflection : float
        Pressure reflection coefficient of both faces.
    edge_strength_m : float
        Strength of the edge's own echo, m.
    velocity_m_s : array_like (3,)
        Common velocity of the three parts.

    Returns
    -------
    (Plane, Plane, Edge)
        Face a, face b and the edge.
    """
    start = _vector(edge_start_m, "corner edge_start_m")
    end = _vector(edge_end_m, "corner edge_end_m")
    length = float(np.linalg.norm(end - start))
    if length == 0:
        raise SceneError(f"corner edge has zero length: edge_start_m = edge_end_m = {start.tolist()}")
    along = (end - start) / length
    width = _positive(face_width_m, "corner face_width_m")
    normals = []
    for name, value in (("normal_a", normal_a), ("normal_b", normal_b)):
        normal = _direction(value, f"corner {name}")
        if abs(np.dot(normal, along)) > _PERPENDICULAR_TOLERANCE:
            raise SceneError(
                f"corner {name} {normal.tolist()} is not perpendicular to the edge {along.tolist()}"
            )
        normal = normal - np.dot(normal, along) * along
        normals.append(normal / np.linalg.norm(normal))
    n_a, n_b = normals
    middle = 0.5 * (start + end)
    faces = []
    for own, other in ((n_a, n_b), (n_b, n_a)):
        outward = np.cross(own, along)
        towards = float(np.dot(outward, other))
        if abs(towards) < _PERPENDICULAR_TOLERANCE:
            raise SceneError(f"corner normals {n_a.tolist()} and {n_b.tolist()} are parallel: no corner")
        outward = outward * np.sign(towards)
        faces.append(
            Plane(
                centre_m=middle + 0.5 * width * outward,
                normal=own,
                width_m=length,
                height_m=width,
                width_axis=along,
                reflection=reflection,
                velocity_m_s=np.asarray(velocity_m_s, dtype=float),
            )
        )
    edge = Edge(
        start,
        end,
        strength_m=edge_strength_m,
        velocity_m_s=np.asarray(velocity_m_s, dtype=float),
        concave=True,
    )
    return faces[0], faces[1], edge


# ---------------------------------------------------------------------------------------
# Reflector states for a batch of frames.

_STATE_SHAPES: dict[str, tuple[str | int, ...]] = {
    "points_m": ("n_f", "n_p", 3),
    "point_strengths_m": ("n_f", "n_p"),
    "sphere_centres_m": ("n_f", "n_s", 3),
    "sphere_radii_m": ("n_s",),
    "sphere_strengths_m": ("n_s",),
    "plane_centres_m": ("n_f", "n_pl", 3),
    "plane_normals": ("n_f", "n_pl", 3),
    "plane_width_axes": ("n_f", "n_pl", 3),
    "plane_sizes_m": ("n_pl", 2),
    "plane_reflections": ("n_pl",),
    "edge_starts_m": ("n_f", "n_e", 3),
    "edge_ends_m": ("n_f", "n_e", 3),
    "edge_strengths_m": ("n_e",),
}


@dataclass(frozen=True, eq=False)
class ReflectorStates:
    """Every reflector's geometry in each of ``n_f`` frames, in one frame of reference.

    Points (``n_p``) may be NaN rows (absent: padding) with NaN strengths; spheres
    (``n_s``) are not among the points; sphere strengths are ``|f(pi)|`` at the
    carrier (:meth:`Sphere.strength_m`). Planes (``n_pl``) have unit normals and unit
    width axes per frame, sizes ``[width, height]`` and reflection coefficients;
    edges (``n_e``) have ends per frame and strengths. Shapes are in
    ``_STATE_SHAPES``; a kind with no reflectors has a 0-sized axis.
    """

    points_m: FloatArray
    point_strengths_m: FloatArray
    sphere_centres_m: FloatArray
    sphere_radii_m: FloatArray
    sphere_strengths_m: FloatArray
    plane_centres_m: FloatArray
    plane_normals: FloatArray
    plane_width_axes: FloatArray
    plane_sizes_m: FloatArray
    plane_reflections: FloatArray
    edge_starts_m: FloatArray
    edge_ends_m: FloatArray
    edge_strengths_m: FloatArray

    def __post_init__(self) -> None:
        sizes: dict[str, int] = {}
        for name, template in _STATE_SHAPES.items():
            value = np.asarray(getattr(self, name), dtype=float)
            if value.ndim != len(template):
                raise SceneError(
                    f"ReflectorStates.{name} must have {len(template)} axes, got shape {value.shape}"
                )
            for axis, (size, want) in enumerate(zip(value.shape, template, strict=True)):
                if isinstance(want, int):
                    if size != want:
                        raise SceneError(
                            f"ReflectorStates.{name} axis {axis} must be {want}, got shape {value.shape}"
                        )
                elif sizes.setdefault(want, size) != size:
                    raise SceneError(
                        f"ReflectorStates.{name} has shape {value.shape}: {want} = {size}, "
                        f"but other fields have {want} = {sizes[want]}"
                    )
            _set(self, name, value)

    @classmethod
    def empty(cls, n_frames: int) -> ReflectorStates:
        """No reflectors in ``n_frames`` frames (add points with :meth:`with_points`)."""
        f = int(n_frames)
        return cls(
            points_m=np.zeros((f, 0, 3)),
            point_strengths_m=np.zeros((f, 0)),
            sphere_centres_m=np.zeros((f, 0, 3)),
            sphere_radii_m=np.zeros(0),
            sphere_strengths_m=np.zeros(0),
            plane_centres_m=np.zeros((f, 0, 3)),
            plane_normals=np.zeros((f, 0, 3)),
            plane_width_axes=np.zeros((f, 0, 3)),
            plane_sizes_m=np.zeros((0, 2)),
            plane_reflections=np.zeros(0),
            edge_starts_m=np.zeros((f, 0, 3)),
            edge_ends_m=np.zeros((f, 0, 3)),
            edge_strengths_m=np.zeros(0),
        )

    @property
    def n_frames(self) -> int:
        """Number of frames."""
        return int(self.points_m.shape[0])

    @property
    def n_truth(self) -> int:
        """Rows of :func:`truth_positions_m` and first-order paths: points, spheres, planes, edges."""
        return int(
            self.points_m.shape[1]
            + self.sphere_radii_m.shape[0]
            + self.plane_sizes_m.shape[0]
            + self.edge_strengths_m.shape[0]
        )

    def transformed(self, rotation: ArrayLike, translation_m: ArrayLike) -> ReflectorStates:
        """The same reflectors seen in another frame: ``x' = R x + t`` per frame.

        Positions (points, sphere centres, plane centres, edge ends) get ``R x + t``;
        directions (plane normals and width axes) get ``R v``. ``rotation`` (n_f, 3, 3)
        must be orthogonal; ``translation_m`` is (n_f, 3).
        """
        n_f = self.n_frames
        rot = np.asarray(rotation, dtype=float)
        shift = np.asarray(translation_m, dtype=float)
        if rot.shape != (n_f, 3, 3) or not np.all(np.isfinite(rot)):
            raise SceneError(f"rotation must be finite with shape ({n_f}, 3, 3), got shape {rot.shape}")
        if shift.shape != (n_f, 3) or not np.all(np.isfinite(shift)):
            raise SceneError(f"translation_m must be finite with shape ({n_f}, 3), got shape {shift.shape}")
        gram = np.einsum("fji,fjk->fik", rot, rot)
        if n_f and np.max(np.abs(gram - np.eye(3))) > 1e-6:
            raise SceneError("rotation must be orthogonal (R^T R = I) in every frame")

        def turn(v: FloatArray) -> FloatArray:
            return np.asarray(np.einsum("fij,fkj->fki", rot, v), dtype=float)

        def move(x: FloatArray) -> FloatArray:
            return np.asarray(turn(x) + shift[:, None, :], dtype=float)

        return dataclasses.replace(
            self,
            points_m=move(self.points_m),
            sphere_centres_m=move(self.sphere_centres_m),
            plane_centres_m=move(self.plane_centres_m),
            plane_normals=turn(self.plane_normals),
            plane_width_axes=turn(self.plane_width_axes),
            edge_starts_m=move(self.edge_starts_m),
            edge_ends_m=move(self.edge_ends_m),
        )

    def take(self, frames: NDArray[np.int64]) -> ReflectorStates:
        """The states of the frames ``frames`` only (per-object constants unchanged)."""
        per_frame = (
            "points_m", "point_strengths_m", "sphere_centres_m", "plane_centres_m", "plane_normals",
            "plane_width_axes", "edge_starts_m", "edge_ends_m",
        )  # fmt: skip
        return replace(self, **{name: getattr(self, name)[frames] for name in per_frame})

    def with_points(self, points_m: ArrayLike, strengths_m: ArrayLike) -> ReflectorStates:
        """These states with extra point reflectors (n_f, k, 3) and strengths (n_f, k) appended.

        NaN rows (and NaN strengths) are absent points, as everywhere.
        """
        n_f = self.n_frames
        points = np.asarray(points_m, dtype=float)
        strengths = np.asarray(strengths_m, dtype=float)
        if points.ndim != 3 or points.shape[0] != n_f or points.shape[2] != 3:
            raise SceneError(f"points_m must have shape ({n_f}, k, 3), got {points.shape}")
        if strengths.shape != points.shape[:2]:
            raise SceneError(f"strengths_m must have shape {points.shape[:2]}, got {strengths.shape}")
        return dataclasses.replace(
            self,
            points_m=np.concatenate([self.points_m, points], axis=1),
            point_strengths_m=np.concatenate([self.point_strengths_m, strengths], axis=1),
        )


def _rotated(vector: FloatArray, axis: FloatArray, angle_rad: FloatArray) -> FloatArray:
    """Rodrigues: ``vector`` (3,) turned by ``angle_rad`` (n,) about unit ``axis`` (3,); (n, 3)."""
    cos = np.cos(angle_rad)[:, None]
    sin = np.sin(angle_rad)[:, None]
    return np.asarray(
        vector * cos + np.cross(axis, vector) * sin + axis * np.dot(axis, vector) * (1.0 - cos), dtype=float
    )


def states_at(
    reflectors: Sequence[Reflector],
    times_s: ArrayLike,
    *,
    frequency_hz: float,
    speed_of_sound_m_s: float,
) -> ReflectorStates:
    """Every reflector at the given times, in the reflectors' own (world) frame.

    Every kind moves as ``position + velocity * t``; a plane also turns its normal and
    width axis by ``angular_velocity * t`` about its spin axis (Rodrigues), its centre
    fixed apart from the velocity. Sphere strengths are evaluated at
    ``frequency_hz`` with ``speed_of_sound_m_s``.

    Parameters
    ----------
    reflectors : sequence of Reflector
        In any order; each kind keeps its order within its arrays.
    times_s : array_like (n_f,)
        Frame times, s.
    frequency_hz, speed_of_sound_m_s : float
        Carrier frequency (Hz) and speed of sound (m/s) for the sphere strengths.
    """
    t = np.asarray(times_s, dtype=float)
    if t.ndim != 1 or not np.all(np.isfinite(t)):
        raise SceneError(f"times_s must be a finite 1-D array, got shape {t.shape}")
    _positive(frequency_hz, "frequency_hz")
    _positive(speed_of_sound_m_s, "speed_of_sound_m_s")
    n_f = len(t)
    points: list[PointReflector] = []
    spheres: list[Sphere] = []
    planes: list[Plane] = []
    edges: list[Edge] = []
    for i, item in enumerate(reflectors):
        if isinstance(item, PointReflector):
            points.append(item)
        elif isinstance(item, Sphere):
            spheres.append(item)
        elif isinstance(item, Plane):
            planes.append(item)
        elif isinstance(item, Edge):
            edges.append(item)
        else:
            raise SceneError(
                f"reflector {i} is a {type(item).__name__}, not a PointReflector, Sphere, Plane or Edge"
            )

    def moved(positions: list[FloatArray], velocities: list[FloatArray]) -> FloatArray:
        if not positions:
            return np.zeros((n_f, 0, 3))
        return np.asarray(
            np.stack(positions)[None] + t[:, None, None] * np.stack(velocities)[None], dtype=float
        )

    plane_normals = np.zeros((n_f, len(planes), 3))
    plane_widths = np.zeros((n_f, len(planes), 3))
    for j, plane in enumerate(planes):
        angle = np.radians(plane.angular_velocity_deg_s) * t
        axis = _resolved(plane.spin_axis)
        plane_normals[:, j] = _rotated(plane.normal, axis, angle)
        plane_widths[:, j] = _rotated(_resolved(plane.width_axis), axis, angle)
    return ReflectorStates(
        points_m=moved([p.position_m for p in points], [p.velocity_m_s for p in points]),
        point_strengths_m=np.tile(np.array([p.strength_m for p in points], dtype=float), (n_f, 1)),
        sphere_centres_m=moved([s.centre_m for s in spheres], [s.velocity_m_s for s in spheres]),
        sphere_radii_m=np.array([s.radius_m for s in spheres], dtype=float),
        sphere_strengths_m=np.array(
            [s.strength_m(frequency_hz, speed_of_sound_m_s) for s in spheres], dtype=float
        ),
        plane_centres_m=moved([p.centre_m for p in planes], [p.velocity_m_s for p in planes]),
        plane_normals=plane_normals,
        plane_width_axes=plane_widths,
        plane_sizes_m=np.array([[p.width_m, p.height_m] for p in planes], dtype=float).reshape(-1, 2),
        plane_reflections=np.array([p.reflection for p in planes], dtype=float),
        edge_starts_m=moved([e.start_m for e in edges], [e.velocity_m_s for e in edges]),
        edge_ends_m=moved([e.end_m for e in edges], [e.velocity_m_s for e in edges]),
        edge_strengths_m=np.array([e.strength_m for e in edges], dtype=float),
    )


# ---------------------------------------------------------------------------------------
# Echo paths.


@dataclass(frozen=True, eq=False)
class EchoPaths:
    """Every echo path for ``n_f`` frames and ``n_rx`` receivers.

    Arrays are (n_f, n_rx, n_paths), directions (n_f, n_rx, n_paths, 3). Where a path
    does not exist in a frame (off a finite plane, an absent point, ...) ``path_m``,
    the legs and the directions are NaN and ``gain`` is 0.

    Attributes
    ----------
    path_m
        total length transmitter -> reflection(s) -> receiver, m.
    first_leg_m
        transmitter -> first reflection point, m.
    last_leg_m
        last reflection point -> receiver, m.
    gain
        linear amplitude factor: spreading, reflection coefficients, strengths;
        not transducer directivity nor air absorption.
    departure
        unit vector from the transmitter towards the first reflection point.
    arrival
        unit vector from the receiver towards the last reflection point.
    order
        (n_paths,) int, 1 or 2.
    labels
        (n_paths,) what each path meets, in travel order, e.g. ``"point 0"``,
        ``"plane 1 > sphere 0"``; None if unknown.
    """

    path_m: FloatArray
    first_leg_m: FloatArray
    last_leg_m: FloatArray
    gain: FloatArray
    departure: FloatArray
    arrival: FloatArray
    order: NDArray[np.int64]
    labels: tuple[str, ...] | None = None

    def __post_init__(self) -> None:
        path = np.asarray(self.path_m, dtype=float)
        if path.ndim != 3:
            raise SceneError(f"EchoPaths.path_m must be (n_f, n_rx, n_paths), got shape {path.shape}")
        _set(self, "path_m", path)
        for name in ("first_leg_m", "last_leg_m", "gain"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != path.shape:
                raise SceneError(f"EchoPaths.{name} has shape {value.shape}, path_m has {path.shape}")
            _set(self, name, value)
        for name in ("departure", "arrival"):
            value = np.asarray(getattr(self, name), dtype=float)
            if value.shape != (*path.shape, 3):
                raise SceneError(f"EchoPaths.{name} has shape {value.shape}, expected {(*path.shape, 3)}")
            _set(self, name, value)
        order = np.asarray(self.order, dtype=np.int64)
        if order.shape != (path.shape[2],):
            raise SceneError(f"EchoPaths.order has shape {order.shape}, expected ({path.shape[2]},)")
        _set(self, "order", order)
        if self.labels is not None:
            labels = tuple(str(label) for label in self.labels)
            if len(labels) != path.shape[2]:
                raise SceneError(f"EchoPaths.labels has {len(labels)} entries for {path.shape[2]} paths")
            _set(self, "labels", labels)

    @property
    def n_paths(self) -> int:
        """Number of paths (existing or not in a given frame)."""
        return int(self.path_m.shape[2])


def concat_paths(parts: Sequence[EchoPaths]) -> EchoPaths:
    """Join path sets of the same frames and receivers along the paths axis.

    Labels survive only if every part has them.
    """
    if not parts:
        raise SceneError("concat_paths needs at least one EchoPaths")
    head = parts[0].path_m.shape[:2]
    for i, part in enumerate(parts):
        if part.path_m.shape[:2] != head:
            raise SceneError(
                f"concat_paths part {i} has (n_f, n_rx) = {part.path_m.shape[:2]}, part 0 has {head}"
            )
    labels: tuple[str, ...] | None = None
    if all(part.labels is not None for part in parts):
        labels = tuple(label for part in parts for label in (part.labels or ()))
    return EchoPaths(
        path_m=np.concatenate([p.path_m for p in parts], axis=2),
        first_leg_m=np.concatenate([p.first_leg_m for p in parts], axis=2),
        last_leg_m=np.concatenate([p.last_leg_m for p in parts], axis=2),
        gain=np.concatenate([p.gain for p in parts], axis=2),
        departure=np.concatenate([p.departure for p in parts], axis=2),
        arrival=np.concatenate([p.arrival for p in parts], axis=2),
        order=np.concatenate([p.order for p in parts]),
        labels=labels,
    )


def _dot(a: FloatArray, b: FloatArray) -> FloatArray:
    return np.asarray(np.sum(a * b, axis=-1), dtype=float)


def _norm(a: FloatArray) -> FloatArray:
    return np.asarray(np.sqrt(np.sum(a * a, axis=-1)), dtype=float)


def _mirror(point: FloatArray, centre: FloatArray, normal: FloatArray) -> FloatArray:
    """``point`` mirrored in the plane through ``centre`` with unit ``normal``."""
    return point - 2.0 * _dot(point - centre, normal)[..., None] * normal


def _crossing(
    start: FloatArray, end: FloatArray, centre: FloatArray, normal: FloatArray, *, touching: bool = False
) -> tuple[FloatArray, BoolArray]:
    """Where the segment start -> end meets the plane, and whether it does.

    It does if its ends are on opposite sides, both more than 1 nm off the plane (so
    an edge lying in a face, as in :func:`corner`, makes no path with that face: its
    face reflections belong to the wedge's own diffraction); with ``touching`` also if
    one end (not both) is within 1 nm (a double reflection through the line where two
    faces meet). Symmetric in the ends.
    """
    d_start = _dot(start - centre, normal)
    d_end = _dot(end - centre, normal)
    off_start = np.abs(d_start) > _BOUNDARY_TOLERANCE_M
    off_end = np.abs(d_end) > _BOUNDARY_TOLERANCE_M
    ok = (d_start * d_end < 0) & off_start & off_end
    if touching:
        ok = ok | (off_start != off_end)
    fraction = d_start / np.where(ok, d_start - d_end, 1.0)
    return start + fraction[..., None] * (end - start), ok


def _inside(
    point: FloatArray, centre: FloatArray, normal: FloatArray, width_axis: FloatArray, size_m: FloatArray
) -> BoolArray:
    """Whether ``point`` (on the plane) lies within the rectangle, edges included (within 1 nm)."""
    offset = point - centre
    along = np.abs(_dot(offset, width_axis)) - _BOUNDARY_TOLERANCE_M
    across = np.abs(_dot(offset, np.cross(normal, width_axis))) - _BOUNDARY_TOLERANCE_M
    return np.asarray((along <= 0.5 * size_m[..., 0]) & (across <= 0.5 * size_m[..., 1]))


def _perpendicular(unit: FloatArray) -> FloatArray:
    """Some unit vector perpendicular to each unit vector (..., 3)."""
    helper = np.where((np.abs(unit[..., :1]) < 0.9), [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    other = helper - _dot(helper, unit)[..., None] * unit
    return np.asarray(other / _norm(other)[..., None], dtype=float)


def sphere_specular_point(
    source_m: ArrayLike, receiver_m: ArrayLike, centre_m: ArrayLike, radius_m: ArrayLike
) -> tuple[FloatArray, BoolArray]:
    """The point of a sphere's surface with the shortest path source -> surface -> receiver.

    It lies in the plane of source, centre and receiver at angle ``phi`` from the
    source's direction (seen from the centre), between 0 and the angle ``gamma`` of
    the receiver's direction. The path ``L(phi)`` has ``L' = a (d_s sin phi / r_s -
    d_r sin(gamma - phi) / r_r)``, increasing on the arc seen from both points, where
    the root is found by Newton steps kept inside a bracket (bisection otherwise);
    there the normal bisects the angle between the two rays (law of reflection).
    Monostatic (source = receiver) it is ``centre + a * unit(source - centre)``.

    Arrays broadcast: points (..., 3), radius (...). Returns the point (..., 3) and
    whether it exists: both points outside the sphere and the sphere not in the way
    (``gamma < arccos(a / d_s) + arccos(a / d_r)``, else the shortest path is a
    forward grazing one, not an echo).
    """
    x = np.asarray(source_m, dtype=float)
    y = np.asarray(receiver_m, dtype=float)
    c = np.asarray(centre_m, dtype=float)
    a = np.asarray(radius_m, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        to_x = x - c
        to_y = y - c
        dx = _norm(to_x)
        dy = _norm(to_y)
        u = to_x / dx[..., None]
        w = to_y / dy[..., None]
        cos_g = _dot(u, w)
        gamma = np.arctan2(_norm(np.cross(u, w)), cos_g)
        v = w - cos_g[..., None] * u
        v_norm = _norm(v)
        v = np.where((v_norm > 1e-12)[..., None], v / v_norm[..., None], _perpendicular(u))
        vis_x = np.arccos(np.clip(a / dx, -1.0, 1.0))
        vis_y = np.arccos(np.clip(a / dy, -1.0, 1.0))
        ok = np.asarray((dx > a) & (dy > a) & (gamma < vis_x + vis_y))
        gamma = np.where(ok, gamma, 0.0)
        low = np.where(ok, np.maximum(0.0, gamma - vis_y), 0.0)
        high = np.where(ok, np.minimum(gamma, vis_x), 0.0)
        phi = np.clip(0.5 * gamma, low, high)
        for _ in range(_NEWTON_STEPS):
            cos_p, sin_p = np.cos(phi), np.sin(phi)
            cos_q, sin_q = np.cos(gamma - phi), np.sin(gamma - phi)
            r_x = np.sqrt(dx * dx + a * a - 2 * a * dx * cos_p)
            r_y = np.sqrt(dy * dy + a * a - 2 * a * dy * cos_q)
            slope = dx * sin_p / r_x - dy * sin_q / r_y
            curve = (
                dx * (dx * cos_p - a) * (dx - a * cos_p) / r_x**3
                + dy * (dy * cos_q - a) * (dy - a * cos_q) / r_y**3
            )
            low = np.where(slope < 0, phi, low)
            high = np.where(slope > 0, phi, high)
            newton = phi - slope / curve
            step_ok = (newton >= low) & (newton <= high)
            new = np.where(ok, np.where(step_ok, newton, 0.5 * (low + high)), 0.0)
            moved = np.abs(new - phi)
            phi = new
            if not np.any(moved[ok] > _ANGLE_TOLERANCE_RAD):
                break
        point = c + a[..., None] * (np.cos(phi)[..., None] * u + np.sin(phi)[..., None] * v)
    return np.asarray(point, dtype=float), ok


def edge_point(
    source_m: ArrayLike, receiver_m: ArrayLike, start_m: ArrayLike, end_m: ArrayLike
) -> FloatArray:
    """The point of the segment start -> end with the shortest path source -> point -> receiver.

    Unfold the receiver about the edge's line into the source's half-plane: the
    straight line crosses the edge line at ``t = (t_s rho_r + t_r rho_s) / (rho_s +
    rho_r)`` (t along the edge, rho the distance from its line); there the two rays
    make equal angles with the edge (Keller's cone). The path is convex in t, so the
    shortest point of the segment is t clipped to it. Arrays broadcast (..., 3).
    """
    x = np.asarray(source_m, dtype=float)
    y = np.asarray(receiver_m, dtype=float)
    a = np.asarray(start_m, dtype=float)
    b = np.asarray(end_m, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        length = _norm(b - a)
        along = (b - a) / length[..., None]
        t_x = _dot(x - a, along)
        t_y = _dot(y - a, along)
        rho_x = _norm(x - a - t_x[..., None] * along)
        rho_y = _norm(y - a - t_y[..., None] * along)
        total = rho_x + rho_y
        t = np.where(
            total > 0, (t_x * rho_y + t_y * rho_x) / np.where(total > 0, total, 1.0), 0.5 * (t_x + t_y)
        )
        t = np.clip(t, 0.0, length)
        return np.asarray(a + t[..., None] * along, dtype=float)


def _block(
    valid: BoolArray,
    path: FloatArray,
    gain: FloatArray,
    to_first: FloatArray,
    to_last: FloatArray,
    order: int,
    labels: list[str],
    shape: tuple[int, int, int],
) -> EchoPaths:
    """Paths (n_f, n_rx, k) from their validity, length, gain and the vectors to the first/last points."""
    with np.errstate(invalid="ignore", divide="ignore"):
        first = np.broadcast_to(_norm(to_first), shape)
        last = np.broadcast_to(_norm(to_last), shape)
        path = np.broadcast_to(path, shape)
        gain = np.broadcast_to(gain, shape)
        ok = np.broadcast_to(valid, shape) & (first > 0) & (last > 0) & np.isfinite(path) & np.isfinite(gain)
        departure = np.broadcast_to(to_first, (*shape, 3)) / first[..., None]
        arrival = np.broadcast_to(to_last, (*shape, 3)) / last[..., None]
    nan = np.nan
    return EchoPaths(
        path_m=np.where(ok, path, nan),
        first_leg_m=np.where(ok, first, nan),
        last_leg_m=np.where(ok, last, nan),
        gain=np.where(ok, gain, 0.0),
        departure=np.where(ok[..., None], departure, nan),
        arrival=np.where(ok[..., None], arrival, nan),
        order=np.full(shape[2], order, dtype=np.int64),
        labels=tuple(labels),
    )


def _pointlike(
    source: FloatArray, receiver: FloatArray, states: ReflectorStates, n_rx: int
) -> tuple[FloatArray, FloatArray, list[str]]:
    """The reflection point and strength of every point, sphere and edge for a source and receiver.

    ``source`` and ``receiver`` broadcast to (n_f, n_rx, 1, 3). Returns points
    (n_f, n_rx, K, 3) (NaN where there is none), strengths (n_f, n_rx, K) and labels,
    K = n_p + n_s + n_e in that order.
    """
    n_f = states.n_frames
    n_p = states.points_m.shape[1]
    n_s = len(states.sphere_radii_m)
    n_e = len(states.edge_strengths_m)
    points = np.broadcast_to(states.points_m[:, None], (n_f, n_rx, n_p, 3))
    point_strengths = np.broadcast_to(states.point_strengths_m[:, None], (n_f, n_rx, n_p))
    sphere_points, seen = sphere_specular_point(
        source, receiver, states.sphere_centres_m[:, None], states.sphere_radii_m
    )
    sphere_points = np.broadcast_to(np.where(seen[..., None], sphere_points, np.nan), (n_f, n_rx, n_s, 3))
    sphere_strengths = np.broadcast_to(states.sphere_strengths_m, (n_f, n_rx, n_s))
    edge_points = np.broadcast_to(
        edge_point(source, receiver, states.edge_starts_m[:, None], states.edge_ends_m[:, None]),
        (n_f, n_rx, n_e, 3),
    )
    edge_strengths = np.broadcast_to(states.edge_strengths_m, (n_f, n_rx, n_e))
    labels = [f"point {i}" for i in range(n_p)] + [f"sphere {i}" for i in range(n_s)]
    labels += [f"edge {i}" for i in range(n_e)]
    return (
        np.concatenate([points, sphere_points, edge_points], axis=2),
        np.concatenate([point_strengths, sphere_strengths, edge_strengths], axis=2),
        labels,
    )


def _check_transducers(transmitter_m: ArrayLike, receivers_m: ArrayLike) -> tuple[FloatArray, FloatArray]:
    tx = _vector(transmitter_m, "transmitter_m")
    rx = np.asarray(receivers_m, dtype=float)
    if rx.ndim != 2 or rx.shape[1] != 3:
        raise SceneError(f"receivers_m must have shape (n_rx, 3), got {rx.shape}")
    if not np.all(np.isfinite(rx)):
        raise SceneError("receivers_m must be finite")
    return tx, rx


def echo_paths(
    transmitter_m: ArrayLike,
    receivers_m: ArrayLike,
    states: ReflectorStates,
    *,
    max_order: int = 1,
    point_pairs: bool = True,
) -> EchoPaths:
    """Every echo path from one transmitter via the reflectors to each receiver.

    First order, in the order of :func:`truth_positions_m` (points, spheres, planes,
    edges; path k belongs to truth row k):

    - point: ``r_tx + r_rx``, gain ``s / (r_tx r_rx)``;
    - sphere: via the specular point (:func:`sphere_specular_point`), gain
      ``s / (r1 r2)``;
    - plane: image source, ``|image - receiver|``, only if transmitter and receiver
      are on the same side and the line from the image to the receiver crosses the
      rectangle; gain ``R / path``;
    - edge: via :func:`edge_point`, gain ``s / (r1 r2)``.

    With ``max_order = 2``, then: plane-plane for each ordered pair (image of the
    image, both reflection points inside their rectangles; gain ``R1 R2 / path``);
    for each plane, every point, sphere and edge after the plane (transmitter's
    image) and then before it (receiver's image), with the plane's reflection point
    inside the rectangle (gain ``s R / (leg_a leg_b)``, the unfolded legs before and
    after the reflector); point-point for each ordered pair of different points
    (gain ``s1 s2 / (r1 r12 r2)``) unless ``point_pairs`` is False. Spheres and edges
    take part in second order only together with a plane.

    Parameters
    ----------
    transmitter_m : array_like (3,)

    receivers_m : array_like (n_rx, 3)

    states : ReflectorStates
        In the same frame of reference as the transducers.
    max_order : int
        1 or 2.
    point_pairs : bool
        With ``max_order = 2``, include the point-point paths (n_p (n_p - 1) of them).

    Returns
    -------
    EchoPaths
        (n_f, n_rx, n_paths), labelled.
    """
    tx, rx = _check_transducers(transmitter_m, receivers_m)
    if max_order not in (1, 2):
        raise SceneError(f"max_order must be 1 or 2, got {max_order}")
    n_f, n_rx = states.n_frames, len(rx)
    n_p = states.points_m.shape[1]
    n_s = len(states.sphere_radii_m)
    n_pl = len(states.plane_reflections)
    source = tx[None, None, None, :]
    receiver = rx[None, :, None, :]
    centres = states.plane_centres_m[:, None]  # (n_f, 1, n_pl, 3)
    normals = states.plane_normals[:, None]
    widths = states.plane_width_axes[:, None]
    sizes = states.plane_sizes_m
    reflections = states.plane_reflections

    with np.errstate(invalid="ignore", divide="ignore"):
        # First order: points, spheres and edges.
        found, strength, found_labels = _pointlike(source, receiver, states, n_rx)
        leg_a = found - source
        leg_b = found - receiver
        r_a, r_b = _norm(leg_a), _norm(leg_b)
        single = _block(
            np.isfinite(r_a) & np.isfinite(strength),
            r_a + r_b,
            strength / (r_a * r_b),
            leg_a,
            leg_b,
            1,
            found_labels,
            (n_f, n_rx, found.shape[2]),
        )
        # First order: planes.
        image = _mirror(source, centres, normals)
        spot, crosses = _crossing(image, receiver, centres, normals)
        on = crosses & _inside(spot, centres, normals, widths, sizes)
        path = _norm(receiver - image)
        planes = _block(
            on,
            path,
            reflections / path,
            spot - source,
            spot - receiver,
            1,
            [f"plane {j}" for j in range(n_pl)],
            (n_f, n_rx, n_pl),
        )
    cut = n_p + n_s
    parts = [_take(single, slice(0, cut)), planes, _take(single, slice(cut, None))]
    if max_order >= 2:
        parts += _second_order(source, receiver, states, n_rx, point_pairs)
    return concat_paths(parts)


def _take(paths: EchoPaths, index: slice) -> EchoPaths:
    """Some of the paths (a slice along the paths axis)."""
    labels = paths.labels[index] if paths.labels is not None else None
    return EchoPaths(
        path_m=paths.path_m[:, :, index],
        first_leg_m=paths.first_leg_m[:, :, index],
        last_leg_m=paths.last_leg_m[:, :, index],
        gain=paths.gain[:, :, index],
        departure=paths.departure[:, :, index],
        arrival=paths.arrival[:, :, index],
        order=paths.order[index],
        labels=labels,
    )


def _plane_and_pointlike(
    source: FloatArray,
    receiver: FloatArray,
    states: ReflectorStates,
    n_rx: int,
    j: int,
    *,
    plane_first: bool,
) -> EchoPaths:
    """Second-order paths via plane ``j`` and every point, sphere and edge, in one order.

    Plane first (transmitter -> plane -> reflector -> receiver) the transmitter is
    mirrored in the plane, plane last (transmitter -> reflector -> plane -> receiver)
    the receiver: either way the path is the first-order one between the two ends,
    one of them an image, with gain ``s R / (leg_a leg_b)`` (the unfolded legs
    before and after the reflector). It is valid where the leg on the image's side
    crosses the plane inside the rectangle.
    """
    c = states.plane_centres_m[:, None, j : j + 1]
    n = states.plane_normals[:, None, j : j + 1]
    w = states.plane_width_axes[:, None, j : j + 1]
    tx, rx = (_mirror(source, c, n), receiver) if plane_first else (source, _mirror(receiver, c, n))
    found, strength, names = _pointlike(tx, rx, states, n_rx)
    leg_a, leg_b = _norm(found - tx), _norm(found - rx)
    # The leg on the image's side, in path order, meets the plane at the first or last point.
    if plane_first:
        spot, crosses = _crossing(tx, found, c, n)
        to_first, to_last = spot - source, found - receiver
        labels = [f"plane {j} > {name}" for name in names]
    else:
        spot, crosses = _crossing(found, rx, c, n)
        to_first, to_last = found - source, spot - receiver
        labels = [f"{name} > plane {j}" for name in names]
    valid = crosses & _inside(spot, c, n, w, states.plane_sizes_m[j])
    gain = strength * states.plane_reflections[j] / (leg_a * leg_b)
    shape = (states.n_frames, n_rx, found.shape[2])
    return _block(valid, leg_a + leg_b, gain, to_first, to_last, 2, labels, shape)


def _second_order(
    source: FloatArray, receiver: FloatArray, states: ReflectorStates, n_rx: int, point_pairs: bool
) -> list[EchoPaths]:
    """Plane-plane, plane with point/sphere/edge (both ways) and point-point paths."""
    n_f = states.n_frames
    n_pl = len(states.plane_reflections)
    parts: list[EchoPaths] = []
    with np.errstate(invalid="ignore", divide="ignore"):
        # Plane i, then plane j: image of the image, unfolded back to both reflection points.
        first_i, then_j = (np.asarray(k) for k in np.nonzero(~np.eye(n_pl, dtype=bool)))
        c = states.plane_centres_m[:, None]
        n = states.plane_normals[:, None]
        w = states.plane_width_axes[:, None]
        size = states.plane_sizes_m
        image_1 = _mirror(source, c[:, :, first_i], n[:, :, first_i])
        image_2 = _mirror(image_1, c[:, :, then_j], n[:, :, then_j])
        spot_2, ok_2 = _crossing(image_2, receiver, c[:, :, then_j], n[:, :, then_j])
        spot_1, ok_1 = _crossing(image_1, spot_2, c[:, :, first_i], n[:, :, first_i], touching=True)
        valid = ok_1 & ok_2
        valid &= _inside(spot_1, c[:, :, first_i], n[:, :, first_i], w[:, :, first_i], size[first_i])
        valid &= _inside(spot_2, c[:, :, then_j], n[:, :, then_j], w[:, :, then_j], size[then_j])
        path = _norm(receiver - image_2)
        # Through the line where the two faces meet (a 90° corner seen monostatically),
        # both orders are one ray on the boundary of both: half each, R1 R2 / path in all.
        share = np.where(_norm(spot_2 - spot_1) <= _BOUNDARY_TOLERANCE_M, 0.5, 1.0)
        gain = share * states.plane_reflections[first_i] * states.plane_reflections[then_j] / path
        labels = [f"plane {i} > plane {j}" for i, j in zip(first_i, then_j, strict=True)]
        parts.append(
            _block(valid, path, gain, spot_1 - source, spot_2 - receiver, 2, labels, (n_f, n_rx, len(labels)))
        )

        # A plane with a point, sphere or edge, both ways round.
        for j in range(n_pl):
            for plane_first in (True, False):
                parts.append(_plane_and_pointlike(source, receiver, states, n_rx, j, plane_first=plane_first))

        # Point -> other point.
        n_p = states.points_m.shape[1]
        if point_pairs and n_p > 1:
            one, two = (np.asarray(k) for k in np.nonzero(~np.eye(n_p, dtype=bool)))
            p1 = states.points_m[:, None, one]  # (n_f, 1, pairs, 3)
            p2 = states.points_m[:, None, two]
            r1, r12, r2 = _norm(p1 - source), _norm(p2 - p1), _norm(p2 - receiver)
            s = states.point_strengths_m[:, None, one] * states.point_strengths_m[:, None, two]
            valid = r12 > 0
            labels = [f"point {i} > point {k}" for i, k in zip(one, two, strict=True)]
            parts.append(
                _block(
                    valid,
                    r1 + r12 + r2,
                    s / (r1 * r12 * r2),
                    p1 - source,
                    p2 - receiver,
                    2,
                    labels,
                    (n_f, n_rx, len(labels)),
                )
            )
    return parts


def truth_positions_m(transmitter_m: ArrayLike, states: ReflectorStates) -> FloatArray:
    """Where each reflector is seen from the transmitter, (n_f, n_truth, 3), NaN if nowhere.

    Rows: points (as given, NaN kept), spheres (the surface point nearest the
    transmitter, ``centre - a unit(centre - tx)``), planes (the foot of the
    perpendicular from the transmitter if it falls inside the rectangle, else NaN),
    edges (the point of the segment nearest the transmitter). These are the
    monostatic reflection points of the first-order paths, in the same order;
    second-order paths are never truth (they are ghosts).
    """
    tx = _vector(transmitter_m, "transmitter_m")
    with np.errstate(invalid="ignore", divide="ignore"):
        centres = states.sphere_centres_m
        radii = states.sphere_radii_m
        offset = centres - tx
        distance = _norm(offset)
        spheres = centres - radii[:, None] * offset / distance[..., None]
        spheres = np.where((distance > radii)[..., None], spheres, np.nan)
        c, n = states.plane_centres_m, states.plane_normals
        height = _dot(tx - c, n)
        foot = tx - height[..., None] * n
        seen = (height != 0) & _inside(foot, c, n, states.plane_width_axes, states.plane_sizes_m)
        planes = np.where(seen[..., None], foot, np.nan)
        edges = edge_point(tx, tx, states.edge_starts_m, states.edge_ends_m)
    return np.concatenate([states.points_m, spheres, planes, edges], axis=1)


def truth_kinds(reflectors: Sequence[Reflector]) -> tuple[str, ...]:
    """The class of each row of :func:`truth_positions_m` for these reflectors (in the order
    :func:`states_at` takes them): points and spheres ``"point"``, planes ``"plane"``, a
    corner's edge ``"corner"`` (its double bounce locates it), any other edge ``"point"``
    (:data:`echoloc.io.recording.REFLECTOR_KINDS` are the classes)."""
    points = ["point" for r in reflectors if isinstance(r, PointReflector)]
    spheres = ["point" for r in reflectors if isinstance(r, Sphere)]
    planes = ["plane" for r in reflectors if isinstance(r, Plane)]
    edges = ["corner" if r.concave else "point" for r in reflectors if isinstance(r, Edge)]
    return tuple(points + spheres + planes + edges)


def surface_points_m(reflectors: Sequence[Reflector], spacing_m: float) -> FloatArray:
    """Points sampling every reflector's surface at time 0, no farther apart than ``spacing_m``.

    Points as themselves, spheres on a Fibonacci lattice of their surface, planes on a
    rectangular lattice including their rims, edges along their segment. The truth
    against which a map's occupied cells are scored (:func:`echoloc.maps.mapping.map_accuracy`).
    """
    if not (math.isfinite(spacing_m) and spacing_m > 0):
        raise ValueError(f"spacing_m must be > 0, got {spacing_m}")
    parts: list[FloatArray] = [np.zeros((0, 3))]
    for reflector in reflectors:
        if isinstance(reflector, PointReflector):
            parts.append(np.asarray(reflector.position_m, dtype=float).reshape(1, 3))
        elif isinstance(reflector, Sphere):
            area = 4 * math.pi * reflector.radius_m**2
            n = max(8, math.ceil(2 * area / spacing_m**2))
            k = np.arange(n) + 0.5
            polar = np.arccos(1 - 2 * k / n)
            azimuth = math.pi * (1 + math.sqrt(5)) * k
            unit = np.column_stack(
                [np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)]
            )
            parts.append(reflector.centre_m + reflector.radius_m * unit)
        elif isinstance(reflector, Plane):
            width = _resolved(reflector.width_axis)
            height = reflector.height_axis
            u = (
                np.linspace(-0.5, 0.5, max(2, math.ceil(reflector.width_m / spacing_m) + 1))
                * reflector.width_m
            )
            v = (
                np.linspace(-0.5, 0.5, max(2, math.ceil(reflector.height_m / spacing_m) + 1))
                * reflector.height_m
            )
            uu, vv = np.meshgrid(u, v, indexing="ij")
            parts.append(reflector.centre_m + uu.reshape(-1, 1) * width + vv.reshape(-1, 1) * height)
        elif isinstance(reflector, Edge):
            length = float(np.linalg.norm(reflector.end_m - reflector.start_m))
            t = np.linspace(0.0, 1.0, max(2, math.ceil(length / spacing_m) + 1))
            parts.append(reflector.start_m + t[:, None] * (reflector.end_m - reflector.start_m))
    return np.asarray(np.vstack(parts), dtype=float)
