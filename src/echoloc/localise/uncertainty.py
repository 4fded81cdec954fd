"""How sure a position is, and how far apart to put the receivers.

Three tools, from the report's section 4.3 and the usual navigation practice:

- :func:`uncertainty_area`: the corners a-d of the report's figure 4.12, the area
  where the two ellipses of one transmitter between two receivers cross when each
  measured path carries an error (exact, from the closed forms (3.5)/(3.6) of
  appendix F).
- :func:`position_errors` and :func:`error_map`: first-order error propagation for
  any array, any number of transmitters and receivers, in 2-D or 3-D. The path of
  channel i is ``l_i = |p - T_i| + |p - R_i|``; its gradient is
  ``(p - T_i)/|p - T_i| + (p - R_i)/|p - R_i|``; with path standard deviations
  ``sigma_i`` the position covariance is ``(J^T W J)^-1``, ``W = diag(1/sigma_i^2)``,
  and the geometric dilution of precision ``GDOP = sqrt(trace(cov)) / sigma`` for
  equal sigmas (e.g. Kaplan & Hegarty, *Understanding GPS*, 2nd ed., sec. 7.2.2).
- :func:`spacing_study` and :func:`recommended_spacing`: the report's figure 4.13
  (range and angle error against receiver spacing and path error), computed exactly
  by re-solving with the perturbed paths, beside the linearised figures, and the
  spacing a designer should choose under a stated criterion.

Frame and units: sensor frame of docs/FORMATS.md (z is the boresight, x to the right),
metres and radians. Range and angle are taken from the frame's origin (the report's
transmitter): range ``r = |p|``; in 2-D the angle is the report's azimuth
``theta = atan2(x, z)`` (positive towards +x, towards receiver R1).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.optimize import brentq

from echoloc.errors import EchoLocError, GeometryError

Plane = Literal["xz", "yz", "xy"]

_CORNER_NAMES = ("a", "b", "c", "d")


# --- the report's paired geometry (figure 4.12) ------------------------------------


def paired_range_angle(
    path1_m: ArrayLike, path2_m: ArrayLike, spacing1_m: ArrayLike, spacing2_m: ArrayLike | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Range r (m) and azimuth theta (rad) of a reflector from two paths, exactly.

    Transmitter T at the origin, receiver R1 at ``(+d1, 0)``, R2 at ``(-d2, 0)``
    (``d2 = d1`` when not given), paths ``l_i = |p| + |p - R_i|``. Squaring
    ``|p - R_i| = l_i - r`` gives ``l1^2 - 2 l1 r = d1^2 - 2 x d1`` and
    ``l2^2 - 2 l2 r = d2^2 + 2 x d2``, hence (report appendix F, (F.6) and (F.9),
    (3.5) for ``d1 = d2 = d``: ``r = (l1^2 + l2^2 - 2 d^2) / (2 (l1 + l2))``)::

        r = (d2 l1^2 + d1 l2^2 - d1 d2 (d1 + d2)) / (2 (d2 l1 + d1 l2))
        x = (d1^2 - d2^2 - l1^2 + l2^2 + 2 r (l1 - l2)) / (2 (d1 + d2))
        theta = arcsin(x / r)                                     (3.6)

    Paths that no point in front of the array explains (``|x| > r``) give NaN.
    """
    l1 = np.asarray(path1_m, dtype=float)
    l2 = np.asarray(path2_m, dtype=float)
    d1 = np.asarray(spacing1_m, dtype=float)
    d2 = d1 if spacing2_m is None else np.asarray(spacing2_m, dtype=float)
    r = (d2 * l1**2 + d1 * l2**2 - d1 * d2 * (d1 + d2)) / (2 * (d2 * l1 + d1 * l2))
    x = (d1**2 - d2**2 - l1**2 + l2**2 + 2 * r * (l1 - l2)) / (2 * (d1 + d2))
    with np.errstate(invalid="ignore", divide="ignore"):
        sine = np.where((r > 0) & (np.abs(x) <= r), x / r, np.nan)
    return np.asarray(r, dtype=float), np.asarray(np.arcsin(sine), dtype=float)


def paired_paths(
    position_m: ArrayLike, spacing1_m: float, spacing2_m: float | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Paths ``l_i = |p| + |p - R_i|`` (m) of 2-D points ``(..., 2) = (x, z)``; R1 at +d1, R2 at -d2."""
    p = np.asarray(position_m, dtype=float)
    d2 = spacing1_m if spacing2_m is None else spacing2_m
    r = np.hypot(p[..., 0], p[..., 1])
    return r + np.hypot(p[..., 0] - spacing1_m, p[..., 1]), r + np.hypot(p[..., 0] + d2, p[..., 1])


@dataclass(frozen=True)
class UncertaintyArea:
    """The crossing of two ellipse bands, report figure 4.12.

    ``corners_m`` (4, 2) holds corners a, b, c, d as (x, z); ``corner_range_m`` and
    ``corner_angle_rad`` (4,) their range and azimuth. As the report defines them:
    a = (l1 + dl1, l2 - dl2), the largest negative error of theta; b = (l1 - dl1,
    l2 - dl2), the largest negative error of r; c = (l1 - dl1, l2 + dl2), the largest
    positive error of theta; d = (l1 + dl1, l2 + dl2), the largest positive error of r.
    """

    paths_m: tuple[float, float]
    path_errors_m: tuple[float, float]
    spacings_m: tuple[float, float]
    range_m: float
    angle_rad: float
    position_m: NDArray[np.float64]
    corner_range_m: NDArray[np.float64]
    corner_angle_rad: NDArray[np.float64]
    corners_m: NDArray[np.float64]

    @property
    def range_error_m(self) -> tuple[float, float]:
        """Largest negative and positive range errors (corners b and d), m."""
        return float(self.corner_range_m[1] - self.range_m), float(self.corner_range_m[3] - self.range_m)

    @property
    def angle_error_rad(self) -> tuple[float, float]:
        """Largest negative and positive azimuth errors (corners a and c), rad."""
        return float(self.corner_angle_rad[0] - self.angle_rad), float(
            self.corner_angle_rad[2] - self.angle_rad
        )


def uncertainty_area(
    path1_m: float,
    path2_m: float,
    path_error1_m: float,
    path_error2_m: float,
    spacing_m: float,
    spacing2_m: float | None = None,
) -> UncertaintyArea:
    """Corners a-d of the uncertainty area (report section 4.3, figure 4.12).

    The report fills ``l1 +- dl1`` and ``l2 +- dl2`` into (3.5) and (3.6); see
    :class:`UncertaintyArea` for which corner is which. Path errors are magnitudes
    (their sign is ignored); the receivers are at ``+spacing_m`` and ``-spacing2_m``.
    """
    d1 = float(spacing_m)
    d2 = d1 if spacing2_m is None else float(spacing2_m)
    values = {"path1_m": path1_m, "path2_m": path2_m, "spacing_m": d1, "spacing2_m": d2}
    for name, value in values.items():
        if not (math.isfinite(value) and value > 0):
            raise GeometryError(f"uncertainty area: {name} must be a finite number > 0, got {value}")
    for name, value in (("path_error1_m", path_error1_m), ("path_error2_m", path_error2_m)):
        if not math.isfinite(value):
            raise GeometryError(f"uncertainty area: {name} must be finite, got {value}")
    e1, e2 = abs(path_error1_m), abs(path_error2_m)
    signs = np.array([[1.0, -1.0], [-1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]])  # a, b, c, d
    l1 = np.concatenate([[path1_m], path1_m + signs[:, 0] * e1])
    l2 = np.concatenate([[path2_m], path2_m + signs[:, 1] * e2])
    r, theta = paired_range_angle(l1, l2, d1, d2)
    if not np.all(np.isfinite(theta)):
        raise GeometryError(
            f"uncertainty area: paths {path1_m:g} m and {path2_m:g} m (errors {e1:g}, {e2:g} m) with "
            f"receivers at +{d1:g} m and -{d2:g} m do not cross in front of the array"
        )
    points = np.stack([r * np.sin(theta), r * np.cos(theta)], axis=-1)
    return UncertaintyArea(
        paths_m=(float(path1_m), float(path2_m)),
        path_errors_m=(e1, e2),
        spacings_m=(d1, d2),
        range_m=float(r[0]),
        angle_rad=float(theta[0]),
        position_m=points[0],
        corner_range_m=r[1:],
        corner_angle_rad=theta[1:],
        corners_m=points[1:],
    )


# --- first-order error propagation for any array -----------------------------------


def array_channels(
    transmitters_m: ArrayLike, receivers_m: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Every (transmitter, receiver) pair as channels: (n_tx n_rx, D) each, transmitter-major.

    Transmitters fire in turn and every receiver records each one (docs/FORMATS.md,
    ``frame_transmitter``); a transducer that both sends and receives appears in both
    lists, and its own channel measures twice the distance.
    """
    tx = np.atleast_2d(np.asarray(transmitters_m, dtype=float))
    rx = np.atleast_2d(np.asarray(receivers_m, dtype=float))
    if tx.shape[1] != rx.shape[1] or tx.shape[1] not in (2, 3):
        raise GeometryError(
            f"transmitters {tx.shape} and receivers {rx.shape} must be (n, 2) or (n, 3) alike"
        )
    return np.repeat(tx, len(rx), axis=0), np.tile(rx, (len(tx), 1))


def path_jacobian(
    positions_m: ArrayLike, transmitters_m: ArrayLike, receivers_m: ArrayLike
) -> NDArray[np.float64]:
    """Gradient of each channel's path at each position: (..., n_ch, D), dimensionless.

    Row i is ``(p - T_i)/|p - T_i| + (p - R_i)/|p - R_i|`` (the sum of the unit
    vectors from transmitter and receiver to the point; docs/METHOD.md, Gauss-Newton).
    ``transmitters_m`` is one position (D,) or one per channel (n_ch, D). At a
    transducer the direction is undefined and the row is NaN.
    """
    p = np.asarray(positions_m, dtype=float)[..., None, :]
    rx = np.atleast_2d(np.asarray(receivers_m, dtype=float))
    tx = np.broadcast_to(np.asarray(transmitters_m, dtype=float), rx.shape)
    to_t = p - tx
    to_r = p - rx
    with np.errstate(invalid="ignore", divide="ignore"):
        rows = to_t / np.linalg.norm(to_t, axis=-1, keepdims=True) + to_r / np.linalg.norm(
            to_r, axis=-1, keepdims=True
        )
    return np.asarray(rows, dtype=float)


def _inverse_normal(normal: NDArray[np.float64], rcond: float = 1e-12) -> NDArray[np.float64]:
    """Inverse of symmetric normal matrices (..., D, D); singular or non-finite ones give inf."""
    finite = np.all(np.isfinite(normal), axis=(-2, -1))
    safe = np.where(finite[..., None, None], normal, np.eye(normal.shape[-1]))
    values, vectors = np.linalg.eigh(safe)
    top = np.max(np.abs(values), axis=-1, keepdims=True)
    ok = finite & np.all(values > rcond * top, axis=-1) & (top[..., 0] > 0)
    with np.errstate(divide="ignore"):
        inverse_values = np.where(ok[..., None], 1.0 / np.where(ok[..., None], values, 1.0), np.inf)
    inverse = np.einsum(
        "...ik,...k,...jk->...ij", vectors, np.where(ok[..., None], inverse_values, 0), vectors
    )
    return np.where(ok[..., None, None], inverse, np.inf)


@dataclass(frozen=True)
class PositionErrors:
    """First-order position uncertainty at points (...,): covariance and what follows from it.

    ``covariance_m2`` (..., D, D) = ``(J^T W J)^-1``; ``std_m`` (..., D) per axis;
    ``range_std_m`` along the line of sight from the origin; ``cross_range_std_m``
    across it (all transverse directions together); ``angle_std_rad`` =
    cross-range / range (in 2-D exactly the std of the azimuth theta);
    ``gdop`` = ``sqrt(trace((J^T J)^-1))``, position std per unit path std,
    whatever ``sigma_m`` is. Points where the geometry fixes no position (on the
    array's plane, at a transducer) get infinities.
    """

    positions_m: NDArray[np.float64]
    covariance_m2: NDArray[np.float64]
    std_m: NDArray[np.float64]
    range_std_m: NDArray[np.float64]
    cross_range_std_m: NDArray[np.float64]
    angle_std_rad: NDArray[np.float64]
    gdop: NDArray[np.float64]


def position_errors(
    positions_m: ArrayLike,
    transmitters_m: ArrayLike,
    receivers_m: ArrayLike,
    sigma_m: ArrayLike = 1.0,
) -> PositionErrors:
    """Propagate path standard deviations to position uncertainty at points (..., D).

    ``transmitters_m`` and ``receivers_m`` are the channels (see
    :func:`array_channels` for a whole array); ``sigma_m`` is one path std or one per
    channel, m. Covariance ``(J^T W J)^-1`` with ``W = diag(1/sigma_i^2)`` (weighted
    least squares, first order; Kaplan & Hegarty sec. 7.2.2 for GDOP).
    """
    p = np.asarray(positions_m, dtype=float)
    rx = np.atleast_2d(np.asarray(receivers_m, dtype=float))
    if p.shape[-1] != rx.shape[1]:
        raise GeometryError(f"positions {p.shape} and receivers {rx.shape} differ in dimension")
    sigma = np.broadcast_to(np.asarray(sigma_m, dtype=float), (len(rx),))
    if not (np.all(np.isfinite(sigma)) and np.all(sigma > 0)):
        raise GeometryError(f"path sigma must be finite and > 0, got {np.asarray(sigma_m)!r}")
    if len(rx) < p.shape[-1]:
        raise GeometryError(f"{len(rx)} channels cannot fix a {p.shape[-1]}-D position")
    jac = path_jacobian(p, transmitters_m, rx)
    unit = _inverse_normal(np.einsum("...ki,...kj->...ij", jac, jac))
    weighted = jac / sigma[:, None]
    cov = _inverse_normal(np.einsum("...ki,...kj->...ij", weighted, weighted))
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.linalg.norm(p, axis=-1)
        u = p / r[..., None]
        range_var = np.einsum("...i,...ij,...j->...", u, cov, u)
        total = np.trace(cov, axis1=-2, axis2=-1)
        cross = np.sqrt(np.maximum(total - range_var, 0.0))
        cross = np.where(np.isfinite(total), cross, np.inf)
        return PositionErrors(
            positions_m=p,
            covariance_m2=cov,
            std_m=np.sqrt(np.diagonal(cov, axis1=-2, axis2=-1)),
            range_std_m=np.sqrt(range_var),
            cross_range_std_m=cross,
            angle_std_rad=cross / r,
            gdop=np.sqrt(np.trace(unit, axis1=-2, axis2=-1)),
        )


@dataclass(frozen=True)
class ErrorMap:
    """:class:`PositionErrors` on a grid over a plane of the workspace.

    ``plane`` names the grid axes (``"xz"``: u = x, v = z); ``offset_m`` is the
    fixed third coordinate (3-D arrays). ``errors`` has shape (len(v_m), len(u_m), ...).
    """

    plane: Plane
    offset_m: float
    u_m: NDArray[np.float64]
    v_m: NDArray[np.float64]
    sigma_m: float
    transmitters_m: NDArray[np.float64]
    receivers_m: NDArray[np.float64]
    errors: PositionErrors


_PLANE_AXES: dict[str, tuple[int, int, int]] = {"xz": (0, 2, 1), "yz": (1, 2, 0), "xy": (0, 1, 2)}


def error_map(
    transmitters_m: ArrayLike,
    receivers_m: ArrayLike,
    u_m: ArrayLike,
    v_m: ArrayLike,
    *,
    plane: Plane = "xz",
    offset_m: float = 0.0,
    sigma_m: float = 1.0,
) -> ErrorMap:
    """GDOP, range and angle std over a slice of the workspace for a whole array.

    The array is given as its transmitters (n_tx, D) and receivers (n_rx, D); every
    transmitter-receiver pair is a channel (:func:`array_channels`) with path std
    ``sigma_m``. 3-D arrays: the grid spans ``plane`` at ``offset_m`` on the third
    axis. 2-D arrays: the grid is (x, z) itself and ``plane``/``offset_m`` are ignored.
    """
    tx_ch, rx_ch = array_channels(transmitters_m, receivers_m)
    u = np.asarray(u_m, dtype=float).ravel()
    v = np.asarray(v_m, dtype=float).ravel()
    if plane not in _PLANE_AXES:
        raise EchoLocError(f"plane must be one of {sorted(_PLANE_AXES)}, got {plane!r}")
    if not (np.all(np.isfinite(u)) and np.all(np.isfinite(v)) and u.size and v.size):
        raise EchoLocError("error map: the grid coordinates must be finite and non-empty")
    uu, vv = np.meshgrid(u, v)
    if tx_ch.shape[1] == 2:
        points = np.stack([uu, vv], axis=-1)
    else:
        iu, iv, iw = _PLANE_AXES[plane]
        points = np.empty((*uu.shape, 3))
        points[..., iu], points[..., iv], points[..., iw] = uu, vv, offset_m
    return ErrorMap(
        plane=plane,
        offset_m=float(offset_m),
        u_m=u,
        v_m=v,
        sigma_m=float(sigma_m),
        transmitters_m=np.atleast_2d(np.asarray(transmitters_m, dtype=float)),
        receivers_m=np.atleast_2d(np.asarray(receivers_m, dtype=float)),
        errors=position_errors(points, tx_ch, rx_ch, sigma_m),
    )


# --- the spacing study of figure 4.13 ----------------------------------------------


def _broadside(
    spacings_m: NDArray[np.float64], path_m: float | None, range_m: float | None
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Path l = l1 = l2 and range r of a broadside point for each spacing, holding one of them."""
    if (path_m is None) == (range_m is None):
        raise EchoLocError("give exactly one of path_m (the report's l = l1 = l2) and range_m")
    d = spacings_m
    if path_m is not None:
        if not (math.isfinite(path_m) and path_m > 0):
            raise EchoLocError(f"path_m must be a finite number > 0, got {path_m}")
        if np.any(d >= path_m):
            raise EchoLocError(f"spacing must stay below the path l = {path_m:g} m, got up to {d.max():g} m")
        # z + sqrt(z^2 + d^2) = l  =>  z = (l^2 - d^2) / (2 l)
        return np.full_like(d, path_m), (path_m**2 - d**2) / (2 * path_m)
    assert range_m is not None
    if not (math.isfinite(range_m) and range_m > 0):
        raise EchoLocError(f"range_m must be a finite number > 0, got {range_m}")
    return range_m + np.hypot(range_m, d), np.full_like(d, range_m)


@dataclass(frozen=True)
class SpacingStudy:
    """Range and angle errors against spacing and path error, report figure 4.13.

    The report's set-up: one transmitter between two receivers at ``+-d`` (d = d1 =
    d2), a point on the boresight with equal paths l = l1 = l2, an error dl on path 1
    only (dl2 = 0). Arrays are (n_errors, n_spacings): ``range_error_m`` and
    ``angle_error_rad`` exact (re-solved with (3.5)/(3.6)), ``linear_*`` from the
    first-order propagation ``dp = J^-1 (dl, 0)`` (the same as the covariance
    ``J^-1 diag(dl^2, 0) J^-T`` with a sign). ``range_m`` and ``path_m`` (n_spacings,)
    are the true range and the path at each spacing (one of them is held fixed).
    """

    spacings_m: NDArray[np.float64]
    path_errors_m: NDArray[np.float64]
    path_m: NDArray[np.float64]
    range_m: NDArray[np.float64]
    range_error_m: NDArray[np.float64]
    angle_error_rad: NDArray[np.float64]
    linear_range_error_m: NDArray[np.float64]
    linear_angle_error_rad: NDArray[np.float64]

    @property
    def cross_range_error_m(self) -> NDArray[np.float64]:
        """Across-beam error ``r |dtheta|`` (m), the angle error as a distance at the point."""
        return np.asarray(self.range_m * np.abs(self.angle_error_rad), dtype=float)


def spacing_study(
    spacings_m: ArrayLike,
    path_errors_m: ArrayLike,
    *,
    path_m: float | None = None,
    range_m: float | None = None,
) -> SpacingStudy:
    """The report's figure 4.13: errors of r and theta for each spacing d and path error dl1.

    Hold either the path ``path_m`` (the report: l = 1.0 m, so the point sits at
    ``(l^2 - d^2) / (2 l)``, 0.47-0.5 m) or the range ``range_m`` (a designer's
    question: a point at that range). Exact errors come from (3.5)/(3.6) with
    ``l1 = l + dl``, ``l2 = l``; linear ones from the path Jacobian.
    """
    d = np.atleast_1d(np.asarray(spacings_m, dtype=float))
    e = np.atleast_1d(np.asarray(path_errors_m, dtype=float))
    if d.ndim != 1 or not (np.all(np.isfinite(d)) and np.all(d > 0)):
        raise EchoLocError(f"spacings must be finite and > 0, got {np.asarray(spacings_m)!r}")
    if e.ndim != 1 or not np.all(np.isfinite(e)):
        raise EchoLocError(f"path errors must be finite, got {np.asarray(path_errors_m)!r}")
    paths, r = _broadside(d, path_m, range_m)
    r_hat, theta_hat = paired_range_angle(paths[None, :] + e[:, None], paths[None, :], d[None, :])
    # Linear: J rows at p = (0, r) for R1 = (+d, 0), R2 = (-d, 0).
    s = np.hypot(r, d)
    jac = np.empty((len(d), 2, 2))
    jac[:, 0, 0], jac[:, 0, 1] = -d / s, 1 + r / s
    jac[:, 1, 0], jac[:, 1, 1] = d / s, 1 + r / s
    column = np.linalg.inv(jac)[:, :, 0]  # dp/dl1, (n_d, 2) = (dx, dz)
    return SpacingStudy(
        spacings_m=d,
        path_errors_m=e,
        path_m=paths,
        range_m=r,
        range_error_m=r_hat - r[None, :],
        angle_error_rad=theta_hat,
        linear_range_error_m=e[:, None] * column[None, :, 1],
        linear_angle_error_rad=e[:, None] * column[None, :, 0] / r[None, :],
    )


@dataclass(frozen=True)
class SpacingRecommendation:
    """The spacing to build and the errors it gives, with the criterion that chose it.

    ``spacing_m`` is the smallest spacing meeting the across-beam criterion;
    ``largest_spacing_m`` the largest one the range criterion allows (None when
    no range bound was asked for). Errors are worst cases over ``+-path_error_m``
    on one path, the report's figure 4.13 perturbation.
    """

    spacing_m: float
    largest_spacing_m: float | None
    path_error_m: float
    range_m: float
    path_m: float
    max_cross_range_error_m: float
    max_range_error_m: float | None
    cross_range_error_m: float
    angle_error_rad: float
    range_error_m: float
    criterion: str


def _worst(study: SpacingStudy) -> tuple[float, float, float]:
    """Worst cross-range, angle and range errors over the study's path errors (one spacing)."""
    return (
        float(np.max(study.cross_range_error_m)),
        float(np.max(np.abs(study.angle_error_rad))),
        float(np.max(np.abs(study.range_error_m))),
    )


def recommended_spacing(
    path_error_m: float,
    *,
    path_m: float | None = None,
    range_m: float | None = None,
    max_cross_range_error_m: float | None = None,
    max_range_error_m: float | None = None,
) -> SpacingRecommendation:
    """The receiver spacing d (m) to choose for a point at a given path or range.

    Criterion (default): the smallest spacing at which the across-beam error
    ``r |dtheta|`` caused by a path error ``dl`` is no larger than ``dl`` itself,
    worst case over ``dl1 = +-path_error_m``, ``dl2 = 0`` (the report's figure 4.13
    set-up). Why: the angle error falls like 1/d (to first order ``r dtheta =
    dl sqrt(r^2 + d^2) / (2 d)``) while the range error rises slowly with d
    (``dr = dl (l^2 + d^2) / (4 l^2)``); below this spacing the position is known
    worse across the beam than the paths are measured, so the angle dominates and a
    wider array pays; above it more spacing buys little and costs range accuracy,
    beam overlap and size. To first order the criterion is ``sqrt(r^2 + d^2) = 2 d``,
    i.e. ``d = r / sqrt(3)``: at the report's l = 1 m (the point at about 0.47 m)
    ``d = l / (2 + sqrt(3)) = 0.27 m`` - the report's "0.25 m would suffice" - and it
    grows in proportion to range (0.58 m for a point 1 m away), as the report notes
    the optimal spacing depends on range.

    ``max_cross_range_error_m`` replaces the tolerance dl by an absolute one;
    ``max_range_error_m`` adds an upper limit (the report's "not too large"):
    the largest spacing whose range error stays below it. When no spacing meets
    both, :class:`~echoloc.errors.EchoLocError` says which bound to relax.
    Hold ``path_m`` (l = l1 = l2) or ``range_m``, as in :func:`spacing_study`.
    """
    if not (math.isfinite(path_error_m) and path_error_m > 0):
        raise EchoLocError(f"path_error_m must be a finite number > 0, got {path_error_m}")
    tolerance = path_error_m if max_cross_range_error_m is None else max_cross_range_error_m
    if not (math.isfinite(tolerance) and tolerance > 0):
        raise EchoLocError(f"max_cross_range_error_m must be a finite number > 0, got {tolerance}")
    if max_range_error_m is not None and not (math.isfinite(max_range_error_m) and max_range_error_m > 0):
        raise EchoLocError(f"max_range_error_m must be a finite number > 0, got {max_range_error_m}")
    scale = path_m if path_m is not None else range_m
    if scale is None or (path_m is not None and range_m is not None):
        raise EchoLocError("give exactly one of path_m (the report's l = l1 = l2) and range_m")
    if not (math.isfinite(scale) and scale > 0):
        raise EchoLocError(f"{'path_m' if path_m is not None else 'range_m'} must be > 0, got {scale}")
    errors = np.array([-path_error_m, path_error_m])
    hi = 0.999 * scale if path_m is not None else 20.0 * scale
    lo = 1e-4 * scale

    def worst(d: float) -> tuple[float, float, float]:
        return _worst(spacing_study([d], errors, path_m=path_m, range_m=range_m))

    grid = np.geomspace(lo, hi, 400)
    on_grid = spacing_study(grid, errors, path_m=path_m, range_m=range_m)
    cross = np.max(on_grid.cross_range_error_m, axis=0)
    ok = np.flatnonzero(np.isfinite(cross) & (cross <= tolerance))
    held = f"path {path_m:g} m" if path_m is not None else f"range {range_m:g} m"
    if ok.size == 0:
        raise EchoLocError(
            f"no spacing up to {hi:g} m brings the across-beam error at {held} below "
            f"{tolerance * 1e3:g} mm for a path error of {path_error_m * 1e3:g} mm (raise the tolerance)"
        )
    first = int(ok[0])
    spacing = float(grid[0])
    if first > 0:
        spacing = float(
            brentq(lambda d: worst(d)[0] - tolerance, grid[first - 1], grid[first], xtol=1e-9 * scale)
        )
    cross_m, angle_rad, range_err = worst(spacing)
    largest: float | None = None
    if max_range_error_m is not None:
        range_errors = np.max(np.abs(on_grid.range_error_m), axis=0)
        allowed = np.flatnonzero(range_errors <= max_range_error_m)
        if allowed.size == 0 or range_err > max_range_error_m:
            raise EchoLocError(
                f"at {held} with a {path_error_m * 1e3:g} mm path error the across-beam criterion needs "
                f"d >= {spacing:.3g} m, where the range error is {range_err * 1e3:.3g} mm > "
                f"max_range_error_m {max_range_error_m * 1e3:g} mm: relax one of the bounds"
            )
        last = int(allowed[-1])
        largest = float(grid[last])
        if last + 1 < len(grid):
            largest = float(
                brentq(
                    lambda d: worst(d)[2] - max_range_error_m,
                    grid[last],
                    grid[last + 1],
                    xtol=1e-9 * scale,
                )
            )
    criterion = (
        f"smallest d with across-beam error r·|Δθ| <= {tolerance * 1e3:g} mm "
        f"for Δl1 = ±{path_error_m * 1e3:g} mm"
        + (
            f", and largest d with range error <= {max_range_error_m * 1e3:g} mm"
            if max_range_error_m is not None
            else ""
        )
    )
    l_at, r_at = _broadside(np.array([spacing]), path_m, range_m)
    return SpacingRecommendation(
        spacing_m=spacing,
        largest_spacing_m=largest,
        path_error_m=float(path_error_m),
        range_m=float(r_at[0]),
        path_m=float(l_at[0]),
        max_cross_range_error_m=float(tolerance),
        max_range_error_m=max_range_error_m,
        cross_range_error_m=cross_m,
        angle_error_rad=angle_rad,
        range_error_m=range_err,
        criterion=criterion,
    )


def report_array_2d(spacing_m: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The report's 2-D head: transmitter at the origin, receivers at (+d, 0) and (-d, 0)."""
    return np.zeros((1, 2)), np.array([[spacing_m, 0.0], [-spacing_m, 0.0]])


def cross_array(spacing_m: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The report's 3-D head with spacing d: transmitter at the origin, receivers at +-d on x and y."""
    d = spacing_m
    return np.zeros((1, 3)), np.array([[d, 0, 0], [-d, 0, 0], [0, d, 0], [0, -d, 0]], dtype=float)
