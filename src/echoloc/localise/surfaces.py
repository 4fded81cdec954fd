"""Reflector hypotheses: was an echo group a point, a plane or a concave corner?

Geometry (docs/METHOD.md, "Walls and corners"). A *channel* is a transmitter T and a
receiver R; an echo group holds one path ``l`` per channel.

- **Point** P (a ball, a pole, an edge seen end-on): ``l = |P - T| + |P - R|``, an
  ellipsoid per channel.
- **Plane** (a wall): a mirror. The echo is the direct sound of the transmitter's
  image, ``l = |V - R|`` with ``V = T + 2 (h - u.(T - T_ref)) u``: ``u`` the unit
  normal from the reference transmitter T_ref towards the plane and ``h`` the plane's
  distance from T_ref (the image-source method: J. B. Allen and D. A. Berkley, J.
  Acoust. Soc. Am. 65 (1979) 943-950). Each channel's echo comes from its own
  *specular point*, where the line from V to R crosses the plane (the mirror law).
- **Concave right-angle corner** (where two walls meet): two mirrors at 90 degrees
  compose to a half turn about their common edge, so the double bounce is the direct
  sound of ``V = 2 (G + e e.(T - G)) - T``: T turned 180 degrees about the edge line
  through G with direction e (G the edge's foot from T_ref). The corner's echo seems to
  come from a point *behind* the walls; the corner itself is at G.

What one transmitter can tell apart: a point from a mirror, through the curvature of
the wavefront (the ellipsoids of a point against the spheres about one image). For a
transmitter at the centre of a cross of receivers the difference between its two
receiver pairs is about ``a^2 (u_x^2 - u_y^2) / (4 r)`` (a the cross's radius, u the
direction, r the range; docs/METHOD.md 10.10): nothing on the boresight and on the
diagonals, 0.8 mm a path 20 degrees off them at 1 m for a = 0.25 m. A plane and a
corner make the *same* image for one transmitter (``V = 2 G - T`` either way), so one
transmitter cannot tell them apart; a mirror-like group is then reported as a plane.
Two transmitters can: a plane's images are related by a reflection, a corner's by a
half turn, which differ unless the transmitters' baseline runs along the edge (R.
Kleeman and R. Kuc, "Mobile robot sonar for target localization and classification",
Int. J. Robotics Research 14 (1995) 295-318). One transmitter with three receivers
tells walls from edges, but not walls from corners, from one snapshot (H. Peremans, K.
Audenaert and J. M. Van Campenhout, "A high-resolution sensor based on tri-aural
perception", IEEE Trans. Robotics and Automation 9 (1993) 36-48).

The choice between hypotheses is by Schwarz's Bayesian information criterion: each
fitted hypothesis k with chi-square ``chi2_k`` and ``p_k`` parameters on ``n`` paths has
the weight ``exp(-chi2_k / 2) n^(-p_k / 2)``; the weights, normalised over the
hypotheses the geometry can test, are the class probabilities (G. Schwarz, "Estimating
the dimension of a model", Ann. Statist. 6 (1978) 461-464).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import special

from echoloc._jit import HAVE_NUMBA

FloatArray = NDArray[np.float64]

KINDS = ("point", "plane", "corner")
"""The reflector classes, in the order of :attr:`Hypotheses.chi2`."""

PARAMETERS = {"point": 3, "plane": 3, "corner": 4}
"""Free parameters of each hypothesis: a point; a plane's foot; an edge's foot and direction."""

_ITERATIONS = 12
_HALVINGS = 8
_STEP_M = 1e-6
"""Forward-difference step of the Jacobian, in the parameters' units (m; rad for the edge angle)."""

POINT_MODEL, PLANE_MODEL, IMAGE_MODEL, EDGE_MODEL, CORNER_MODEL = 0, 1, 2, 3, 4
"""The models of :mod:`echoloc.localise._surface_kernels`, by number (as there)."""

_CONVERGED = 1e-8
"""Gauss-Newton stops when no row moved a parameter by more than this (m, or rad)."""

_CORNER_STARTS = 6
"""Edge directions tried as starts of the corner fit, evenly over half a turn."""


# ---------------------------------------------------------------------------------------
# Models: parameters (n, k) -> predicted paths (n, m) for one channel geometry.


def point_paths_m(points_m: FloatArray, transmitters_m: FloatArray, receivers_m: FloatArray) -> FloatArray:
    """``|P - T| + |P - R|`` for points (n, 3) and channels (m, 3), (m, 3): (n, m)."""
    p = points_m[:, None, :]
    return np.asarray(np.linalg.norm(p - transmitters_m, axis=-1) + np.linalg.norm(p - receivers_m, axis=-1))


def mirror_paths_images(images_m: FloatArray, receivers_m: FloatArray) -> FloatArray:
    """``|V_i - R_i|`` for one image per channel, images (n, m, 3), receivers (m, 3): (n, m)."""
    return np.asarray(np.linalg.norm(images_m - receivers_m[None], axis=-1))


def _plane_heights(feet_m: FloatArray, transmitters_m: FloatArray, reference_m: FloatArray) -> FloatArray:
    """Distance of each channel's transmitter from the plane, (n, m), m."""
    h = np.linalg.norm(feet_m, axis=-1)
    u = feet_m / h[:, None]
    return np.asarray(h[:, None] - np.einsum("nk,mk->nm", u, transmitters_m - reference_m))


def plane_images_m(feet_m: FloatArray, transmitters_m: FloatArray, reference_m: FloatArray) -> FloatArray:
    """Each channel's transmitter (m, 3) mirrored in the plane of foot offset ``feet_m`` (n, 3): (n, m, 3).

    ``feet_m`` runs from ``reference_m`` to the plane's foot of the perpendicular: its
    length is the plane's distance, its direction the normal away from the sensor.
    """
    u = feet_m / np.linalg.norm(feet_m, axis=-1, keepdims=True)
    height = _plane_heights(feet_m, transmitters_m, reference_m)
    return np.asarray(transmitters_m[None] + 2 * height[..., None] * u[:, None, :])


def plane_paths_m(
    feet_m: FloatArray, transmitters_m: FloatArray, receivers_m: FloatArray, reference_m: FloatArray
) -> FloatArray:
    """``|V - R|`` with V the transmitter's mirror image in the plane of foot offset ``feet_m`` (n, 3)."""
    return mirror_paths_images(plane_images_m(feet_m, transmitters_m, reference_m), receivers_m)


def _edge_directions(corners: FloatArray, reference_m: FloatArray, helper: FloatArray) -> FloatArray:
    """Unit edge directions (n, 3) of corner parameters ``(G, psi)`` (n, 4): ``cos psi a + sin psi b``
    with (a, b) an orthonormal basis of the plane perpendicular to ``G - T_ref`` built from
    ``helper`` (n, 3), a fixed vector per row not along ``G - T_ref``."""
    w = corners[:, :3] - reference_m
    w = w / np.linalg.norm(w, axis=-1, keepdims=True)
    a = helper - np.sum(helper * w, axis=-1, keepdims=True) * w
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = np.cross(w, a)
    psi = corners[:, 3:4]
    return np.asarray(np.cos(psi) * a + np.sin(psi) * b)


def corner_images_m(
    corners: FloatArray, transmitters_m: FloatArray, reference_m: FloatArray, helper: FloatArray
) -> FloatArray:
    """Each channel's transmitter turned half a turn about the corner's edge, (n, m, 3)."""
    return half_turned_m(
        transmitters_m[None], corners[:, None, :3], _edge_directions(corners, reference_m, helper)[:, None, :]
    )


def half_turned_m(points_m: FloatArray, through_m: FloatArray, direction: FloatArray) -> FloatArray:
    """``points_m`` turned half a turn about the line through ``through_m`` along the unit
    ``direction`` (broadcast over the leading axes): ``2 (G + e e.(P - G)) - P``, what two
    mirrors at a right angle, meeting on that line, make of a point."""
    along = np.sum((points_m - through_m) * direction, axis=-1, keepdims=True)
    return np.asarray(2 * (through_m + along * direction) - points_m)


def mirror_paths_m(images_m: FloatArray, receivers_m: FloatArray) -> FloatArray:
    """``|V - R|`` for one image per row (n, 3) heard by receivers (m, 3): (n, m)."""
    return np.asarray(np.linalg.norm(images_m[:, None, :] - receivers_m, axis=-1))


def axis_basis(axis: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The unit ``axis`` and two unit vectors (a, b) completing a right-handed orthonormal basis."""
    return _axis_basis(tuple(float(v) for v in np.asarray(axis, dtype=float).reshape(3)))


@functools.lru_cache(maxsize=16)
def _axis_basis(axis: tuple[float, float, float]) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`axis_basis`, once per axis (a frame asks for it at every step of every fit)."""
    e = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    helper = np.array([1.0, 0.0, 0.0]) if abs(e[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    a = helper - (helper @ e) * e
    a = a / np.linalg.norm(a)
    return e, a, np.cross(e, a)


def _edge_terms(
    lines: FloatArray, axis: FloatArray, transmitters_m: FloatArray, receivers_m: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """The channels across the axis (t2, r2 (m, 2)), their distances from each line (n, m) and
    the offsets along the axis (m,)."""
    e, a, b = axis_basis(axis)
    plane = np.stack([a, b])  # (2, 3)
    t2 = transmitters_m @ plane.T  # (m, 2)
    r2 = receivers_m @ plane.T
    d_t = np.linalg.norm(t2[None] - lines[:, None, :], axis=-1)
    d_r = np.linalg.norm(r2[None] - lines[:, None, :], axis=-1)
    return t2, r2, d_t, d_r, (receivers_m - transmitters_m) @ e


def edge_paths_m(
    lines: FloatArray, axis: FloatArray, transmitters_m: FloatArray, receivers_m: FloatArray
) -> FloatArray:
    """Shortest paths T -> line -> R via straight lines along ``axis`` (n, m).

    ``lines`` (n, 2) are the coordinates, in the basis (a, b) of :func:`axis_basis`, of where
    each line crosses the plane through the origin perpendicular to the axis. Unfolding the
    path about the line (Keller's law of edge diffraction: the rays make equal angles with the
    edge) gives ``l = sqrt((d_T + d_R)^2 + (e.(R - T))^2)``, d the distances from the line.
    """
    _, _, d_t, d_r, along = _edge_terms(lines, axis, transmitters_m, receivers_m)
    return np.asarray(np.sqrt((d_t + d_r) ** 2 + along[None] ** 2))


def edge_jacobian(
    lines: FloatArray, axis: FloatArray, transmitters_m: FloatArray, receivers_m: FloatArray
) -> FloatArray:
    """d l / d line (n, m, 2) of :func:`edge_paths_m`: ``(S / l) ((q - t)/d_T + (q - r)/d_R)``,
    S = d_T + d_R, q the line's crossing and t, r the channel's ends across the axis."""
    t2, r2, d_t, d_r, along = _edge_terms(lines, axis, transmitters_m, receivers_m)
    total = d_t + d_r
    length = np.sqrt(total**2 + along[None] ** 2)
    q = lines[:, None, :]
    gradient = (q - t2[None]) / d_t[..., None] + (q - r2[None]) / d_r[..., None]
    return np.asarray((total / length)[..., None] * gradient)


def edge_foot_m(lines: FloatArray, axis: FloatArray, point_m: FloatArray) -> FloatArray:
    """The point of each line (n, 2) nearest ``point_m`` (3,): (n, 3)."""
    e, a, b = axis_basis(axis)
    return np.asarray(lines[:, :1] * a + lines[:, 1:2] * b + (point_m @ e) * e)


# ---------------------------------------------------------------------------------------
# Fitting: weighted Gauss-Newton with step halving, many rows at once.


_COMPILED = HAVE_NUMBA
"""Whether :func:`fit` runs the compiled kernels (:mod:`echoloc.localise._surface_kernels`) for
the models they hold; the tests set it False to hold the kernels to the numpy fit."""


class CompiledModel(NamedTuple):
    """A model :mod:`echoloc.localise._surface_kernels` fits: its number (:data:`POINT_MODEL`,
    :data:`PLANE_MODEL`, :data:`IMAGE_MODEL`, :data:`EDGE_MODEL`, :data:`CORNER_MODEL`) and
    what it needs: the channels, the reference transmitter (plane, corner), the edge's axis
    (edge) and each row's helper vector of :func:`_edge_directions` (corner)."""

    model: int
    transmitters_m: FloatArray
    receivers_m: FloatArray
    reference_m: FloatArray | None = None
    axis: FloatArray | None = None
    helpers: FloatArray | None = None


def _kernel_fit(
    kernel: CompiledModel, start: FloatArray, paths: FloatArray, weights: FloatArray, iterations: int
) -> Fit:
    """:func:`fit` by the compiled kernel."""
    from echoloc.localise import _surface_kernels  # numba: imported (and compiled) on first use

    n = len(start)
    bases = np.zeros((n, 3, 3))
    if kernel.axis is not None:
        bases[:] = np.stack(axis_basis(kernel.axis))
    if kernel.helpers is not None:
        bases[:, 0] = kernel.helpers
    reference = np.zeros(3) if kernel.reference_m is None else np.asarray(kernel.reference_m, dtype=float)
    parameters, covariance, chi2 = _surface_kernels.fit(
        kernel.model,
        np.array(start, dtype=float, order="C"),
        np.array(paths, dtype=float, order="C"),
        np.array(weights, dtype=float, order="C"),
        np.array(kernel.transmitters_m, dtype=float, order="C"),
        np.array(kernel.receivers_m, dtype=float, order="C"),
        reference,
        bases,
        iterations,
        _HALVINGS,
        _CONVERGED,
    )
    return Fit(parameters, covariance, chi2)


@dataclass(frozen=True, eq=False)
class Fit:
    """Fitted parameters (n, k), their covariance (n, k, k) and the chi-square (n,)."""

    parameters: FloatArray
    covariance: FloatArray
    chi2: FloatArray


def _weighted_chi2(residual: FloatArray, w: FloatArray) -> FloatArray:
    """``sum w r^2`` per row over the weighted channels; inf where it is not finite."""
    chi2 = np.sum(np.where(w > 0, w * residual * residual, 0.0), axis=1)
    return np.asarray(np.where(np.isfinite(chi2), chi2, np.inf))


def _jacobian(model: Callable[[FloatArray], FloatArray], p: FloatArray, at_p: FloatArray) -> FloatArray:
    """d model / d p by forward differences from ``at_p = model(p)``: (n, m, k)."""
    columns = []
    for k in range(p.shape[1]):
        step = np.zeros_like(p)
        step[:, k] = _STEP_M
        with np.errstate(invalid="ignore", divide="ignore"):
            columns.append((model(p + step) - at_p) / _STEP_M)
    jac = np.stack(columns, axis=-1)
    return np.asarray(np.where(np.isfinite(jac), jac, 0.0))


def fit(
    model: Callable[[FloatArray], FloatArray],
    start: FloatArray,
    paths_m: FloatArray,
    sigmas_m: FloatArray,
    iterations: int = _ITERATIONS,
    jacobian: Callable[[FloatArray], FloatArray] | None = None,
    kernel: CompiledModel | None = None,
) -> Fit:
    """Weighted least squares of ``paths_m`` (n, m) against ``model(parameters)`` from ``start`` (n, k).

    ``jacobian(parameters)`` gives d model / d parameters (n, m, k); without it, forward
    differences. ``kernel`` names the same model in :mod:`echoloc.localise._surface_kernels`,
    which then fits it, compiled (when numba is installed). Gauss-Newton; a step that
    raises the chi-square is halved up to 8 times, then the row stays where it is.
    Weights ``1 / sigma^2``; a NaN path or an infinite sigma
    leaves the channel out. The covariance is ``(J^T W J)^-1`` at the solution
    (a pseudo-inverse where a parameter is not determined).
    """
    w = np.where(np.isfinite(paths_m) & np.isfinite(sigmas_m), 1.0 / np.asarray(sigmas_m) ** 2, 0.0)
    paths = np.where(w > 0, paths_m, 0.0)
    if kernel is not None and _COMPILED:
        return _kernel_fit(kernel, np.atleast_2d(start), paths, w, iterations)
    p = np.array(start, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        predicted = model(p)
    chi2 = _weighted_chi2(paths - predicted, w)

    def derivative(q: FloatArray, at_q: FloatArray) -> FloatArray:
        if jacobian is None:
            return _jacobian(model, q, at_q)
        with np.errstate(invalid="ignore", divide="ignore"):
            exact = jacobian(q)
        return np.asarray(np.where(np.isfinite(exact), exact, 0.0))

    for _ in range(iterations):
        jac = derivative(p, predicted)
        r = np.where(w > 0, paths - predicted, 0.0)
        r = np.where(np.isfinite(r), r, 0.0)
        jtw = np.swapaxes(jac, 1, 2) * w[:, None, :]
        normal = jtw @ jac
        gradient = np.einsum("nkm,nm->nk", jtw, r)
        scale = np.trace(normal, axis1=1, axis2=2)[:, None, None] * 1e-12 + 1e-300
        step = np.linalg.solve(normal + scale * np.eye(p.shape[1]), gradient[..., None])[..., 0]
        factor = np.ones(len(p))
        done = ~np.all(np.isfinite(step), axis=1)
        largest = 0.0
        for _ in range(_HALVINGS):
            trial = p + factor[:, None] * step
            with np.errstate(invalid="ignore", divide="ignore"):
                trial_predicted = model(trial)
            trial_chi2 = _weighted_chi2(paths - trial_predicted, w)
            better = ~done & (trial_chi2 <= chi2)
            p = np.where(better[:, None], trial, p)
            predicted = np.where(better[:, None], trial_predicted, predicted)
            chi2 = np.where(better, trial_chi2, chi2)
            if np.any(better):
                largest = max(largest, float(np.max(factor[better] * np.max(np.abs(step[better]), axis=1))))
            done |= better
            if np.all(done):
                break
            factor = np.where(done, factor, 0.5 * factor)
        if largest < _CONVERGED:
            break
    jac = derivative(p, predicted)
    normal = np.swapaxes(jac, 1, 2) * w[:, None, :] @ jac
    covariance = np.asarray(np.linalg.pinv(normal, hermitian=True), dtype=float)
    return Fit(p, covariance, chi2)


# ---------------------------------------------------------------------------------------
# Closed form: a virtual source from its one-way paths.


def image_start_m(receivers_m: FloatArray, paths_m: FloatArray, boresight: FloatArray) -> FloatArray:
    """The point V with ``|V - R_i| = l_i`` by linear least squares, for paths (n, m): (n, 3).

    Relative to the receivers' centroid c, ``|V - c|^2 - 2 R'_i.(V - c) + |R'_i|^2 = l_i^2``;
    subtracting the mean over i leaves ``-2 R'_i.(V - c)`` linear. Receivers in a plane
    leave V's component along the plane's normal free; ``|V - c|^2 = mean(l^2) -
    mean(|R'|^2)`` then gives it, on the ``boresight`` side.
    """
    c = receivers_m.mean(axis=0)
    rel = receivers_m - c
    sq = np.sum(rel**2, axis=1)
    paths2 = paths_m**2
    rhs = -0.5 * ((paths2 - paths2.mean(axis=1, keepdims=True)) - (sq - sq.mean()))
    u, s, vt = np.linalg.svd(rel, full_matrices=True)
    rank = int(np.sum(s > 1e-9 * max(s[0], 1e-300)))
    inverse = vt[:rank].T @ np.diag(1.0 / s[:rank]) @ u[:, :rank].T  # (3, m)
    v = rhs @ inverse.T  # (n, 3): the component in the receivers' span
    if rank < 3:
        normal = vt[2]
        if normal @ boresight < 0:
            normal = -normal
        radius2 = paths2.mean(axis=1) - sq.mean()
        along = np.sqrt(np.maximum(radius2 - np.sum(v**2, axis=1), 0.0))
        v = v + along[:, None] * normal
    return np.asarray(v + c)


# ---------------------------------------------------------------------------------------
# The three hypotheses for echo groups that share one channel geometry.


@dataclass(frozen=True, eq=False)
class Hypotheses:
    """The point, plane and corner fits of n echo groups on one channel geometry.

    ``chi2`` is (n, 3) in the order of :data:`KINDS` (inf where a hypothesis was not
    fitted: the corner with one transmitter); ``probability`` (n, 3) the class
    probabilities (BIC weights over the hypotheses fitted). The fits' parameters: the
    point; the plane's foot offset from the reference transmitter (its length the
    distance, its direction the normal, pointing away from the sensor); the corner's
    edge foot G and edge angle (with ``helper``, see :func:`_edge_directions`).
    """

    point: Fit
    plane: Fit
    corner: Fit | None
    corner_helper: FloatArray | None
    chi2: FloatArray
    probability: FloatArray
    n_paths: NDArray[np.int64]

    @property
    def kind(self) -> NDArray[np.int64]:
        """Index into :data:`KINDS` of the likeliest class per group (the simplest on a tie)."""
        return np.asarray(np.argmax(self.probability, axis=1))


def class_probabilities(chi2: FloatArray, n_paths: NDArray[np.int64]) -> FloatArray:
    """BIC weights ``exp(-chi2/2) n^(-p/2)`` normalised per row; chi2 (n, 3) in :data:`KINDS` order."""
    penalty = np.array([PARAMETERS[k] for k in KINDS], dtype=float)
    log_n = np.log(np.maximum(n_paths, 1)).astype(float)[:, None]
    evidence = -0.5 * chi2 - 0.5 * penalty[None, :] * log_n
    evidence = np.where(np.isfinite(chi2), evidence, -np.inf)
    top = np.max(evidence, axis=1, keepdims=True)
    top = np.where(np.isfinite(top), top, 0.0)
    weight = np.exp(evidence - top)
    total = np.sum(weight, axis=1, keepdims=True)
    return np.asarray(np.where(total > 0, weight / np.where(total > 0, total, 1.0), 0.0))


def distinct_transmitters(transmitters_m: FloatArray, tolerance_m: float = 1e-6) -> int:
    """How many different transmitter positions the channels hold."""
    kept: list[FloatArray] = []
    for t in transmitters_m:
        if not any(np.linalg.norm(t - k) <= tolerance_m for k in kept):
            kept.append(t)
    return len(kept)


def _helper(feet_m: FloatArray) -> FloatArray:
    """A vector per row well away from ``feet_m``'s direction (x, or y when the foot lies along x)."""
    unit = feet_m / np.linalg.norm(feet_m, axis=1, keepdims=True)
    helper = np.zeros_like(feet_m)
    along_x = np.abs(unit[:, 0]) > 0.9
    helper[~along_x, 0] = 1.0
    helper[along_x, 1] = 1.0
    return helper


def hypotheses(
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    paths_m: FloatArray,
    sigmas_m: FloatArray,
    reference_m: FloatArray,
    start_m: FloatArray,
    gate_probability: float = 0.999,
    *,
    corner_mode: Literal["auto", "always", "never"] = "auto",
) -> Hypotheses:
    """Fit the three hypotheses to echo groups (n, m) on channels ``transmitters_m``,
    ``receivers_m`` (m, 3), m.

    ``start_m`` (n, 3) is a rough position of each reflector (a located point, or half
    way to a virtual source); ``reference_m`` (3,) the transmitter whose foot of the
    perpendicular reports a plane or corner. The corner is fitted only when the
    channels hold two or more transmitters (with one it is the plane's twin) and
    neither the point nor the plane fits within the chi-square gate of
    ``gate_probability`` (a corner is the hypothesis of last resort: it has the most
    parameters); ``corner_mode="always"`` fits it whenever two or more transmitters can tell it,
    ``"never"`` not at all.
    """
    tx = np.asarray(transmitters_m, dtype=float)
    rx = np.asarray(receivers_m, dtype=float)
    ref = np.asarray(reference_m, dtype=float)
    paths = np.atleast_2d(np.asarray(paths_m, dtype=float))
    sigmas = np.broadcast_to(np.asarray(sigmas_m, dtype=float), paths.shape)
    start = np.atleast_2d(np.asarray(start_m, dtype=float))
    n_paths = np.sum(np.isfinite(paths) & np.isfinite(sigmas), axis=1)

    point = fit(
        lambda p: point_paths_m(p, tx, rx),
        start,
        paths,
        sigmas,
        jacobian=lambda p: point_jacobian(p, tx, rx),
        kernel=CompiledModel(POINT_MODEL, tx, rx),
    )
    feet = start - ref
    plane = fit(
        lambda f: plane_paths_m(f, tx, rx, ref),
        feet,
        paths,
        sigmas,
        jacobian=lambda f: plane_jacobian(f, tx, rx, ref),
        kernel=CompiledModel(PLANE_MODEL, tx, rx, ref),
    )
    chi2 = np.full((len(paths), 3), np.inf)
    chi2[:, 0] = point.chi2
    chi2[:, 1] = plane.chi2
    corner: Fit | None = None
    helper: FloatArray | None = None
    # The corner, where two or more transmitters can tell it from a plane and neither simpler
    # hypothesis fits within the gate (its edge direction takes a search over starts).
    simple = np.minimum(point.chi2, plane.chi2) <= 2.0 * special.gammaincinv(
        np.maximum(n_paths - 3, 1) / 2, gate_probability
    )
    if corner_mode == "always":
        simple = np.zeros_like(simple)
    if corner_mode != "never" and distinct_transmitters(tx) >= 2 and not np.all(simple):
        corner, helper = _fit_corner(tx, rx, ref, paths, sigmas, plane.parameters + ref)
        # A corner whose edge runs along the transmitters' baseline (projected on the plane)
        # makes the very images of a plane: where the two fits predict the same paths (within
        # one sigma in all) the corner is the plane's twin, not a hypothesis of its own.
        with np.errstate(invalid="ignore"):
            apart = (
                mirror_paths_images(corner_images_m(corner.parameters, tx, ref, helper), rx)
                - plane_paths_m(plane.parameters, tx, rx, ref)
            ) / sigmas
        distinct = np.nansum(apart**2, axis=1) >= 1.0
        chi2[:, 2] = np.where(distinct & ~simple, corner.chi2, np.inf)
    return Hypotheses(point, plane, corner, helper, chi2, class_probabilities(chi2, n_paths), n_paths)


def _fit_corner(
    tx: FloatArray,
    rx: FloatArray,
    ref: FloatArray,
    paths: FloatArray,
    sigmas: FloatArray,
    feet_at: FloatArray,
) -> tuple[Fit, FloatArray]:
    """The corner fit through the plane fit's foot, the best per row.

    The edge's direction starts from each transmitter's own image (fitted on its channels
    alone): the edge is perpendicular to every ``V_k - T_k``, so it lies along their cross
    product. Rows where that start does not reach the chi-square of a good fit (under
    ``2 n`` for n paths), or where no two transmitters have four channels each, try
    :data:`_CORNER_STARTS` directions spread over half a turn.
    """
    n = len(paths)
    helper = _helper(feet_at - ref)

    def fitted(start: FloatArray, rows: NDArray[np.int64], helpers: FloatArray) -> Fit:
        def model(q: FloatArray) -> FloatArray:
            return mirror_paths_images(corner_images_m(q, tx, ref, helpers), rx)

        kernel = CompiledModel(CORNER_MODEL, tx, rx, ref, helpers=helpers)
        return fit(model, start, paths[rows], sigmas[rows], kernel=kernel)

    front = np.mean(feet_at - ref, axis=0)
    size = float(np.linalg.norm(front))
    guessed = _edge_guess(tx, rx, paths, sigmas, front / size) if size > 0 else None
    result = Fit(np.full((n, 4), np.nan), np.full((n, 4, 4), np.nan), np.full(n, np.inf))
    if guessed is not None:
        angle = _edge_angle(feet_at, ref, helper, guessed)
        first = fitted(np.concatenate([feet_at, angle[:, None]], axis=1), np.arange(n), helper)
        result = first
    retry = np.flatnonzero(~(result.chi2 <= 2.0 * paths.shape[1]))
    if len(retry):
        # Evenly spread edge angles over half a turn (e and -e are one line) cover every direction.
        k = _CORNER_STARTS
        angles = np.tile(np.arange(k) * math.pi / k, len(retry))
        start = np.concatenate([np.repeat(feet_at[retry], k, axis=0), angles[:, None]], axis=1)
        tried = fitted(start, np.repeat(retry, k), np.repeat(helper[retry], k, axis=0))
        best = np.argmin(tried.chi2.reshape(len(retry), k), axis=1) + np.arange(len(retry)) * k
        parameters, covariance, chi2 = result.parameters.copy(), result.covariance.copy(), result.chi2.copy()
        better = tried.chi2[best] < chi2[retry]
        parameters[retry[better]] = tried.parameters[best[better]]
        covariance[retry[better]] = tried.covariance[best[better]]
        chi2[retry[better]] = tried.chi2[best[better]]
        result = Fit(parameters, covariance, chi2)
    return result, helper


def _edge_guess(
    tx: FloatArray, rx: FloatArray, paths: FloatArray, sigmas: FloatArray, front: FloatArray
) -> FloatArray | None:
    """The edge direction (n, 3) across the images of the first two transmitters with four or more
    channels each (``(V_0 - T_0) x (V_1 - T_1)``), or None when there are no two such. ``front``
    is the side of a flat array the images lie on (where the plane fit put the surface)."""
    groups: list[NDArray[np.int64]] = []
    for t in np.unique(tx, axis=0):
        channels = np.flatnonzero(np.all(np.abs(tx - t) <= 1e-9, axis=1))
        if len(channels) >= 4:
            groups.append(channels)
    if len(groups) < 2:
        return None
    offsets = []
    for channels in groups[:2]:
        receivers = rx[channels]
        start = image_start_m(receivers, paths[:, channels], front)
        image = fit(
            mirror_model(receivers),
            start,
            paths[:, channels],
            sigmas[:, channels],
            4,
            mirror_jacobian(receivers),
            CompiledModel(IMAGE_MODEL, receivers, receivers),
        )
        offsets.append(image.parameters - tx[channels[0]])
    across = np.cross(offsets[0], offsets[1])
    size = np.linalg.norm(across, axis=1, keepdims=True)
    return np.asarray(np.where(size > 0, across / np.where(size > 0, size, 1.0), np.nan))


def mirror_model(receivers: FloatArray) -> Callable[[FloatArray], FloatArray]:
    """The one-way paths from images (n, 3) to ``receivers``, as a model for :func:`fit`."""

    def model(images: FloatArray) -> FloatArray:
        return mirror_paths_m(images, receivers)

    return model


def mirror_jacobian(receivers: FloatArray) -> Callable[[FloatArray], FloatArray]:
    """d|V - R| / dV = (V - R) / |V - R| for images (n, 3): (n, m, 3)."""

    def jacobian(images: FloatArray) -> FloatArray:
        offset = images[:, None, :] - receivers[None]
        return np.asarray(offset / np.linalg.norm(offset, axis=-1, keepdims=True))

    return jacobian


def point_jacobian(points_m: FloatArray, transmitters_m: FloatArray, receivers_m: FloatArray) -> FloatArray:
    """d(|P - T| + |P - R|) / dP = (P - T)/|P - T| + (P - R)/|P - R|: (n, m, 3)."""
    to_t = points_m[:, None, :] - transmitters_m[None]
    to_r = points_m[:, None, :] - receivers_m[None]
    return np.asarray(
        to_t / np.linalg.norm(to_t, axis=-1, keepdims=True)
        + to_r / np.linalg.norm(to_r, axis=-1, keepdims=True)
    )


def plane_jacobian(
    feet_m: FloatArray, transmitters_m: FloatArray, receivers_m: FloatArray, reference_m: FloatArray
) -> FloatArray:
    """d|V - R| / dF for the plane of foot offset F (n, 3): (n, m, 3).

    With ``h = |F|``, ``u = F / h``, ``d = T - T_ref`` and ``V = T + 2 (h - u.d) u``:
    ``dV/dF = 2 [u u^T - u d^T P / h + (h - u.d) P / h]``, ``P = I - u u^T``, and the
    path's gradient is the unit vector ``(V - R) / |V - R|`` times that.
    """
    h = np.linalg.norm(feet_m, axis=-1)
    u = feet_m / h[:, None]
    d = transmitters_m - reference_m  # (m, 3)
    projector = np.eye(3)[None] - u[:, :, None] * u[:, None, :]  # (n, 3, 3)
    height = h[:, None] - np.einsum("nk,mk->nm", u, d)  # (n, m)
    d_projected = np.einsum("mk,nkj->nmj", d, projector) / h[:, None, None]  # (n, m, 3): d^T P / h
    images = transmitters_m[None] + 2 * height[..., None] * u[:, None, :]
    offset = images - receivers_m[None]
    g = offset / np.linalg.norm(offset, axis=-1, keepdims=True)  # (n, m, 3)
    g_u = np.einsum("nmk,nk->nm", g, u)
    # g . dV/dF = 2 [ (g.u) u^T - (g.u) d^T P / h + (h - u.d) g^T P / h ]
    g_projected = np.einsum("nmk,nkj->nmj", g, projector) / h[:, None, None]
    return np.asarray(
        2 * (g_u[..., None] * u[:, None, :] - g_u[..., None] * d_projected + height[..., None] * g_projected)
    )


def _edge_angle(
    feet_at: FloatArray, ref: FloatArray, helper: FloatArray, direction: FloatArray
) -> FloatArray:
    """The corner parameter psi (n,) of an edge direction, in the basis :func:`_edge_directions` uses."""
    w = feet_at - ref
    w = w / np.linalg.norm(w, axis=-1, keepdims=True)
    a = helper - np.sum(helper * w, axis=-1, keepdims=True) * w
    a = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b = np.cross(w, a)
    angle = np.arctan2(np.sum(direction * b, axis=1), np.sum(direction * a, axis=1))
    return np.asarray(np.where(np.isfinite(angle), angle, 0.0))


# ---------------------------------------------------------------------------------------
# What a classified group reports.


@dataclass(frozen=True, eq=False)
class Surface:
    """The class of a located reflector and, for a plane or corner, its geometry.

    ``kind`` is one of :data:`KINDS`; ``confidence`` its probability among the classes
    the geometry could test (``probabilities`` maps each tested class to its own).

    Plane: ``normal`` the unit normal pointing from the plane towards the sensor,
    ``distance_m`` the plane's distance from the reference transmitter, with
    ``normal_covariance`` (3, 3) (small-angle: its trace is the squared angular error,
    rad^2) and ``distance_std_m``; ``specular_points_m`` (m, 3) where each channel's
    echo met the plane, and ``extent_m`` the largest distance between two of them (how
    much of the plane was heard: a lower bound on its size).

    Corner: ``edge_direction`` the unit direction of the edge (sign arbitrary) with
    ``edge_covariance`` (3, 3). The located position is the edge's foot of the
    perpendicular from the reference transmitter; for a plane, the plane's foot.
    """

    kind: str
    confidence: float
    probabilities: dict[str, float]
    normal: FloatArray | None = None
    normal_covariance: FloatArray | None = None
    distance_m: float | None = None
    distance_std_m: float | None = None
    specular_points_m: FloatArray | None = None
    extent_m: float | None = None
    edge_direction: FloatArray | None = None
    edge_covariance: FloatArray | None = None


def specular_points_m(
    foot_offset_m: FloatArray, transmitters_m: FloatArray, receivers_m: FloatArray, reference_m: FloatArray
) -> FloatArray:
    """Where each channel's echo meets the plane of foot offset ``foot_offset_m`` (3,): (m, 3).

    The line from the transmitter's image V to the receiver R crosses the plane at
    ``R + t (V - R)``, ``t = (h - u.(R - T_ref)) / (u.(V - R))``: by construction the
    angle of incidence there equals the angle of reflection.
    """
    h = float(np.linalg.norm(foot_offset_m))
    u = foot_offset_m / h
    images = plane_images_m(foot_offset_m[None], transmitters_m, reference_m)[0]
    t = (h - (receivers_m - reference_m) @ u) / ((images - receivers_m) @ u)
    return np.asarray(receivers_m + t[:, None] * (images - receivers_m))


def describe(
    found: Hypotheses, row: int, transmitters_m: FloatArray, receivers_m: FloatArray, reference_m: FloatArray
) -> tuple[Surface, FloatArray, FloatArray]:
    """The :class:`Surface` of group ``row`` and the position and covariance (m, m^2) to report."""
    kind_index = int(found.kind[row])
    kind = KINDS[kind_index]
    tested = [k for k, c in zip(KINDS, found.chi2[row], strict=True) if np.isfinite(c)]
    probabilities = {k: float(found.probability[row, KINDS.index(k)]) for k in tested}
    confidence = probabilities[kind]
    if kind == "point":
        return (
            Surface(kind, confidence, probabilities),
            found.point.parameters[row],
            found.point.covariance[row],
        )
    if kind == "plane":
        offset = found.plane.parameters[row]
        covariance = found.plane.covariance[row]
        h = float(np.linalg.norm(offset))
        u = offset / h
        tangent = (np.eye(3) - np.outer(u, u)) / h
        specular = specular_points_m(offset, transmitters_m, receivers_m, reference_m)
        spread = np.linalg.norm(specular[:, None] - specular[None], axis=-1)
        surface = Surface(
            kind,
            confidence,
            probabilities,
            normal=-u,
            normal_covariance=tangent @ covariance @ tangent.T,
            distance_m=h,
            distance_std_m=float(math.sqrt(max(u @ covariance @ u, 0.0))),
            specular_points_m=specular,
            extent_m=float(spread.max()),
        )
        return surface, reference_m + offset, covariance
    assert found.corner is not None
    assert found.corner_helper is not None
    parameters = found.corner.parameters[row : row + 1]
    helper = found.corner_helper[row : row + 1]
    direction = _edge_directions(parameters, reference_m, helper)[0]
    jac = np.empty((3, 4))
    for k in range(4):
        step = np.zeros((1, 4))
        step[0, k] = _STEP_M
        jac[:, k] = (
            _edge_directions(parameters + step, reference_m, helper)[0]
            - _edge_directions(parameters - step, reference_m, helper)[0]
        ) / (2 * _STEP_M)
    covariance = found.corner.covariance[row]
    surface = Surface(
        kind,
        confidence,
        probabilities,
        edge_direction=direction,
        edge_covariance=jac @ covariance @ jac.T,
    )
    return surface, parameters[0, :3], covariance[:3, :3]
