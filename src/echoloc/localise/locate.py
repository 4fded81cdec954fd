"""Localisation: from path lengths per receiver to reflector positions in 3-D (or 2-D).

Geometry (report ch. 3.5 and appendix F, restated in docs/METHOD.md): an echo's path
``l = |p - T| + |p - R|`` puts the reflector on an ellipsoid (an ellipse in 2-D) with
foci at the transmitter T and the receiver R. Intersecting the ellipsoids of three or
more receivers gives ``p``. Every function here works in the dimension of the
coordinates it is given (3-D, or 2-D for the report's planar figures).

A *channel* is one transmitter-receiver pair. One frame of a recording gives one
channel per receiver; combining the frames fired by different transmitters gives
``n_tx * n_rx`` channels (:func:`combine_frames`). A receiver may sit at its
transmitter's place (a transducer that both sends and receives).

- :func:`paired_closed_form` and :func:`paired_closed_form_2d`: the report's exact
  solutions for a transmitter between receiver pairs.
- :func:`solve_positions`: weighted Gauss-Newton for any geometry from a linear start
  (squared equations ``2 R_i.p - 2 l_i rho = |R_i|^2 - l_i^2``, ``rho = |p - T|``),
  with the covariance ``(J^T W J)^-1`` and the chi-square of the residual.
- :func:`associate` ("peaks to points"): several objects from the echoes of every
  channel, ghosts rejected; an echo serves two objects only as the merged peak of
  both; see its docstring.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import lru_cache
from itertools import accumulate, combinations
from operator import itemgetter
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import NDArray
from scipy import special

from echoloc.errors import GeometryError
from echoloc.localise.surfaces import Surface
from echoloc.tof.echoes import FrameEchoes

_GN_ITERATIONS = 10
_DEFAULT_AXIS = (0.0, 0.0, 1.0)


@dataclass(frozen=True)
class LocateOptions:
    """Options of the association and solver.

    path_sigma_m
        A-priori standard deviation of every measured path (model error, air
        turbulence), m; added in quadrature to each echo's own phase-noise bound.
    gate_probability
        Chi-square gate: a combination of echoes is one object when its residual is
        below the gate's quantile (for 4 receivers: 1 degree of freedom).
    min_receivers
        Echoes of their own (not shared with another object) from at least this many
        channels make an object (>= 3 in 3-D, >= 2 in 2-D); one fewer when the object
        shares merged echoes with objects already found.
    resolution_m
        Two echoes closer in path than this merge into one detection (the pulse's
        resolution, m). A channel whose echo merged with another object's still
        supports the object, with the merged echo shared and weighted by
        ``sigma = resolution_m / (4 sqrt 3)`` (the merged peak lies between the
        two paths).
        None: no sharing, every object needs an echo of its own on every channel.
    carrier_hz
        Carrier frequency for the per-echo phase-noise bound; None skips that term.
    window_m
        (shortest, longest) path each receiver can observe, m; a channel whose
        predicted path is outside the window need not show an echo.
    boresight
        Unit vector the array faces; solutions behind the transmitter are rejected.
    field_of_view_deg
        Half-angle of the transducers' beams, degrees: a solution further than this
        from the transmitter's axis, or from the axis of a receiver that supports it,
        is rejected (nothing outside a beam can echo). 90: anything in front.
    transmitter_axes, receiver_axes
        Unit boresight vector per transmitter and per receiver (docs/FORMATS.md
        ``transmitter_axes``/``receiver_axes``); None: every one along ``boresight``.
    excuse_one_channel
        In a frame where no object has an echo on every channel, let objects lack one on
        any one channel (each channel excused in turn, the answer with the best-scoring
        object kept): a ToF chip's channel that misses a weak echo still leaves a 3-of-4
        object, with the larger covariance of fewer ellipsoids. False: never.
    reflector_classes
        Tell points, planes and corners apart (:mod:`echoloc.localise.reflector_kinds`):
        planes and corners are located as such, and every object carries its class.
    edge_axis
        With reflector classes: the direction of the straight edges looked for among the
        echoes no point, plane or corner explains (table legs, door jambs, posts), in the
        sensor frame; the default, y, is the vertical of a level head (REP 103 optical:
        y down). None: no edges.
    """

    path_sigma_m: float = 0.5e-3
    gate_probability: float = 0.999
    min_receivers: int = 3
    resolution_m: float | None = None
    carrier_hz: float | None = None
    window_m: tuple[float, float] = (0.0, np.inf)
    boresight: tuple[float, ...] = _DEFAULT_AXIS
    field_of_view_deg: float = 90.0
    transmitter_axes: NDArray[np.float64] | None = field(default=None, compare=False)
    receiver_axes: NDArray[np.float64] | None = field(default=None, compare=False)
    excuse_one_channel: bool = False
    reflector_classes: bool = False
    edge_axis: tuple[float, float, float] | None = (0.0, 1.0, 0.0)


class LocateWarning(UserWarning):
    """A frame could not be located as asked (it is skipped, the stream goes on)."""


@dataclass(frozen=True, eq=False)
class LocatedObject:
    """One reflector: position and covariance in the sensor frame, and its support.

    ``receivers`` and ``echo_indices`` name, per supporting channel, the receiver and
    the index of its echo in that channel; ``transmitters`` the channel's transmitter.
    ``shared`` counts the echoes this object shares with another (merged echoes).
    ``surface`` is its class and, for a plane or corner, its geometry, when classes
    were asked for (``LocateOptions.reflector_classes``); None otherwise.
    """

    position_m: NDArray[np.float64]
    covariance_m2: NDArray[np.float64]
    receivers: tuple[int, ...]
    echo_indices: tuple[int, ...]
    chi2: float
    score: float
    transmitters: tuple[int, ...] = ()
    shared: int = 0
    surface: Surface | None = None

    @property
    def std_m(self) -> NDArray[np.float64]:
        return np.sqrt(np.diag(self.covariance_m2))


@dataclass(frozen=True, eq=False)
class FrameObjects:
    frame: int
    time_s: float
    objects: tuple[LocatedObject, ...]


# --- closed forms ------------------------------------------------------------------


def paired_closed_form(paths_m: NDArray[np.float64], spacing_m: float) -> NDArray[np.float64]:
    """Exact position for T at the origin and R1..R4 at (+d,0,0), (-d,0,0), (0,+d,0), (0,-d,0).

    ``paths_m`` (..., 4) holds l1..l4. From docs/METHOD.md (report appendix F):
    ``r = (l1^2 + l2^2 - 2 d^2) / (2 (l1 + l2))``,
    ``x = (l2^2 - l1^2 - 2 r (l2 - l1)) / (4 d)``, y likewise from l3, l4, and
    ``z = sqrt(r^2 - x^2 - y^2)``. The range r is taken from the x pair; the y pair
    gives it too, and the mean of both is used.
    """
    l1, l2, l3, l4 = np.moveaxis(np.asarray(paths_m, dtype=float), -1, 0)
    d = spacing_m
    r_x = (l1**2 + l2**2 - 2 * d**2) / (2 * (l1 + l2))
    r_y = (l3**2 + l4**2 - 2 * d**2) / (2 * (l3 + l4))
    x = (l2**2 - l1**2 - 2 * r_x * (l2 - l1)) / (4 * d)
    y = (l4**2 - l3**2 - 2 * r_y * (l4 - l3)) / (4 * d)
    r = 0.5 * (r_x + r_y)
    z = np.sqrt(np.maximum(r**2 - x**2 - y**2, 0.0))
    return np.stack([x, y, z], axis=-1)


def paired_closed_form_2d(paths_m: NDArray[np.float64], spacing_m: float) -> NDArray[np.float64]:
    """Exact 2-D position (x, z) for T at the origin and R1, R2 at (+d, 0), (-d, 0).

    The report's one-transmitter, two-receiver geometry (section 4.3, formulas 3.5
    and 3.6 of appendix F): ``r = (l1^2 + l2^2 - 2 d^2) / (2 (l1 + l2))``,
    ``x = (l2^2 - l1^2 - 2 r (l2 - l1)) / (4 d)``, ``z = sqrt(r^2 - x^2)``;
    ``paths_m`` is (..., 2).
    """
    l1, l2 = np.moveaxis(np.asarray(paths_m, dtype=float), -1, 0)
    d = spacing_m
    r = (l1**2 + l2**2 - 2 * d**2) / (2 * (l1 + l2))
    x = (l2**2 - l1**2 - 2 * r * (l2 - l1)) / (4 * d)
    z = np.sqrt(np.maximum(r**2 - x**2, 0.0))
    return np.stack([x, z], axis=-1)


def exact_solutions(
    transmitter_m: NDArray[np.float64],
    receivers_m: NDArray[np.float64],
    paths_m: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Every point that meets D paths exactly, D = the dimension (3 receivers in 3-D).

    The squared equations ``2 R_i.p - 2 l_i rho = |R_i|^2 - l_i^2`` (coordinates
    relative to the common transmitter T, ``rho = |p|``; docs/METHOD.md) are D linear
    equations in D + 1 unknowns: a line ``u0 + s v`` (v spans the null space, its
    components the signed D x D minors). ``rho^2 = |p|^2`` gives a quadratic in s
    with up to two roots. Returns points (n, 2, D) and which of them are real
    solutions (rho >= 0 and every ``l_i - rho = |p - R_i| >= 0``).
    """
    t = np.asarray(transmitter_m, dtype=float)  # (D,) or one per row (n, D)
    paths = np.atleast_2d(paths_m)
    n, dim = paths.shape
    rel = np.broadcast_to(np.asarray(receivers_m, dtype=float) - t[..., None, :], (n, dim, dim))
    m = np.empty((n, dim, dim + 1))
    m[:, :, :dim] = 2 * rel
    m[:, :, dim] = -2 * paths
    b = np.sum(rel**2, axis=2) - paths**2
    # Null vector: v_j = (-1)^j det(M without column j).
    v = np.empty((n, dim + 1))
    for j in range(dim + 1):
        minor = np.delete(m, j, axis=2)
        v[:, j] = (-1) ** j * np.linalg.det(minor)
    gram = np.einsum("nij,nkj->nik", m, m)
    ok = np.abs(np.linalg.det(gram)) > 1e-18 * np.maximum(np.einsum("nii->n", gram), 1e-30) ** dim
    safe_gram = np.where(ok[:, None, None], gram, np.eye(dim))
    u0 = np.einsum("nji,nj->ni", m, np.linalg.solve(safe_gram, b[..., None])[..., 0])
    p0, r0, vp, vr = u0[:, :dim], u0[:, dim], v[:, :dim], v[:, dim]
    qa = np.sum(vp**2, axis=1) - vr**2
    qb = 2 * (np.sum(p0 * vp, axis=1) - r0 * vr)
    qc = np.sum(p0**2, axis=1) - r0**2
    disc = qb**2 - 4 * qa * qc
    # Noise can push a near-tangent crossing slightly complex: keep it as the tangent point.
    tangent = disc < 0
    root = np.sqrt(np.maximum(disc, 0.0))
    safe_a = np.where(np.abs(qa) > 1e-300, qa, 1e-300)
    s = np.stack([(-qb + root) / (2 * safe_a), (-qb - root) / (2 * safe_a)], axis=1)
    points = p0[:, None, :] + s[..., None] * vp[:, None, :]
    rho = r0[:, None] + s * vr[:, None]
    slack = 1e-9 + 1e-6 * np.max(paths, axis=1)
    valid = (
        ok[:, None]
        & (rho >= -slack[:, None])
        & np.all(paths[:, None, :] - rho[..., None] >= -slack[:, None, None], axis=2)
    )
    valid &= ~tangent[:, None] | (np.abs(disc) <= 1e-6 * qb**2)[:, None]
    valid &= np.all(np.isfinite(points), axis=2)
    return np.asarray(points + t[..., None, :]), np.asarray(valid)


# --- general solver ----------------------------------------------------------------


def linear_start(
    transmitter_m: NDArray[np.float64],
    receivers_m: NDArray[np.float64],
    paths_m: NDArray[np.float64],
    boresight: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Closed-form start for paths (n, n_rx) -> positions (n, D), one common transmitter.

    Solves ``2 R_i.p - 2 l_i rho = |R_i|^2 - l_i^2`` (docs/METHOD.md) by least squares. When
    the system is rank-deficient (D receivers, or a flat array where the normal
    column vanishes) the solution is a line ``x0 + s v`` and ``rho^2 = |p|^2`` picks
    the point on it in front of the array.
    """
    rel = receivers_m - transmitter_m
    paths = np.atleast_2d(paths_m)
    n, m = paths.shape
    dim = rel.shape[1]
    a = np.empty((n, m, dim + 1))
    a[:, :, :dim] = 2 * rel
    a[:, :, dim] = -2 * paths
    b = np.sum(rel**2, axis=1) - paths**2
    u, s, vt = np.linalg.svd(a, full_matrices=True)
    k = min(m, dim + 1)
    ub = np.zeros((n, dim + 1))
    ub[:, :k] = np.einsum("nmk,nm->nk", u[:, :, :k], b)
    s = np.concatenate([s, np.zeros((n, dim + 1 - k))], axis=1)
    safe = np.where(s > 0, s, 1.0)
    # Full rank: the least-squares solution. One short (D receivers, a flat array, or
    # receivers that coincide): the particular solution plus s * the null vector.
    full = np.einsum("nkj,nk->nj", vt[:, : dim + 1, :], np.where(s > 0, ub / safe, 0.0))
    x0 = np.einsum("nkj,nk->nj", vt[:, :dim, :], ub[:, :dim] / safe[:, :dim])
    v = vt[:, dim, :]
    p0, r0, vp, vr = x0[:, :dim], x0[:, dim], v[:, :dim], v[:, dim]
    qa = np.sum(vp**2, axis=1) - vr**2
    qb = 2 * (np.sum(p0 * vp, axis=1) - r0 * vr)
    qc = np.sum(p0**2, axis=1) - r0**2
    disc = np.sqrt(np.maximum(qb**2 - 4 * qa * qc, 0.0))
    safe_a = np.where(np.abs(qa) > 1e-15, qa, 1e-15)
    roots = np.stack([(-qb + disc) / (2 * safe_a), (-qb - disc) / (2 * safe_a)], axis=1)
    candidates = p0[:, None, :] + roots[..., None] * vp[:, None, :]
    ahead = candidates @ boresight
    constrained = candidates[np.arange(n), np.argmax(ahead, axis=1)]
    full_rank = (s[:, dim] > 1e-6 * s[:, 0]) if m > dim else np.zeros(n, dtype=bool)
    p = np.where(full_rank[:, None], full[:, :dim], constrained)
    return np.asarray(p + transmitter_m)


def model_paths_m(
    transmitter_m: NDArray[np.float64], receivers_m: NDArray[np.float64], points_m: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Paths T -> p -> R_i for points (n, D): (n, n_rx).

    ``transmitter_m`` is one position (D,) or one per channel (n_rx, D).
    """
    points = np.asarray(points_m, dtype=float)
    t = np.asarray(transmitter_m, dtype=float)
    to_tx = np.linalg.norm(points[:, None, :] - t, axis=-1)
    to_rx = np.linalg.norm(points[:, None, :] - receivers_m, axis=-1)
    return np.asarray(to_tx + to_rx)


@dataclass(frozen=True, eq=False)
class Solution:
    """Batch of solved positions with covariance and chi-square of the residual."""

    position_m: NDArray[np.float64]  # (n, D)
    covariance_m2: NDArray[np.float64]  # (n, D, D)
    chi2: NDArray[np.float64]  # (n,)
    converged: NDArray[np.bool_]  # (n,)


def solve_positions(
    transmitter_m: NDArray[np.float64],
    receivers_m: NDArray[np.float64],
    paths_m: NDArray[np.float64],
    sigma_m: NDArray[np.float64] | float,
    boresight: NDArray[np.float64] | None = None,
    *,
    start_m: NDArray[np.float64] | None = None,
) -> Solution:
    """Weighted least-squares positions for paths (n, n_ch), n_ch >= D.

    ``transmitter_m`` is one position (D,) or one per channel (n_ch, D). The start
    is the linear solution (one transmitter) or ``start_m``; then Gauss-Newton on
    ``l_i = |p - T_i| + |p - R_i|`` with Jacobian rows
    ``(p - T_i)/|p - T_i| + (p - R_i)/|p - R_i|``. A NaN path, or an infinite
    sigma, leaves that channel out of that row's fit.
    """
    receivers = np.asarray(receivers_m, dtype=float)
    transmitter = np.asarray(transmitter_m, dtype=float)
    paths = np.atleast_2d(np.asarray(paths_m, dtype=float))
    dim = receivers.shape[1]
    if receivers.shape[0] < dim or paths.shape[1] != receivers.shape[0]:
        raise GeometryError(
            f"need paths from >= {dim} receivers matching the receivers given, "
            f"got {paths.shape} for {receivers.shape}"
        )
    axis = np.asarray(boresight if boresight is not None else _DEFAULT_AXIS[-dim:], dtype=float)
    sigma = np.broadcast_to(np.asarray(sigma_m, dtype=float), paths.shape)
    weights = np.where(np.isfinite(paths) & np.isfinite(sigma), 1.0 / sigma**2, 0.0)
    paths = np.where(weights > 0, paths, 0.0)
    if start_m is not None:
        start = np.broadcast_to(np.asarray(start_m, dtype=float), (len(paths), dim)).copy()
    elif transmitter.ndim == 1:
        start = linear_start(transmitter, receivers, paths, axis)
    else:
        raise GeometryError("several transmitters: give start_m (see associate for a start)")
    transmitters = np.broadcast_to(transmitter, receivers.shape)
    return _gauss_newton(transmitters, receivers, paths, weights, start)


def _gauss_newton(
    transmitters: NDArray[np.float64],
    receivers: NDArray[np.float64],
    paths: NDArray[np.float64],
    weights: NDArray[np.float64],
    start: NDArray[np.float64],
    iterations: int = _GN_ITERATIONS,
) -> Solution:
    """Gauss-Newton on channels (T_i, R_i); zero weights leave channels out (compiled loop)."""
    from echoloc.localise import _locate_kernels as kernels  # numba: imported (and compiled) on first use

    # Fresh C-ordered float64 copies: one compiled signature (views may be read-only).
    position, covariance, chi2, converged = kernels.gauss_newton(
        np.array(transmitters, dtype=float, order="C"),
        np.array(receivers, dtype=float, order="C"),
        np.array(paths, dtype=float, order="C"),
        np.array(weights, dtype=float, order="C"),
        np.array(start, dtype=float, order="C"),
        iterations,
    )
    return Solution(position, covariance, chi2, converged)


def path_sigmas_m(
    snr_db: NDArray[np.float64], speed_of_sound_m_s: float, options: LocateOptions
) -> NDArray[np.float64]:
    """Standard deviation of each measured path, m.

    ``sigma^2 = path_sigma_m^2 + (c / (2 pi f_c sqrt(2 SNR)))^2``: the a-priori model
    error plus the carrier-phase noise of an echo whose matched-filter output SNR
    is ``SNR`` (phase noise 1/sqrt(2 SNR) rad, divided by the carrier's angular
    frequency).
    """
    sigma2 = np.full(np.shape(snr_db), options.path_sigma_m**2)
    if options.carrier_hz:
        snr = 10 ** (np.asarray(snr_db) / 10)
        sigma2 = sigma2 + (speed_of_sound_m_s / (2 * np.pi * options.carrier_hz * np.sqrt(2 * snr))) ** 2
    return np.asarray(np.sqrt(sigma2))


def _flat_path_sigmas(
    snr_db: NDArray[np.float64], speed_of_sound_m_s: float, options: LocateOptions
) -> NDArray[np.float64]:
    """:func:`path_sigmas_m` as float64, m; of float64 SNRs with a carrier in one compiled loop
    (:func:`echoloc.localise._locate_kernels.path_sigmas`: the bits of every compiled path, within 4
    ulps of numpy's)."""
    if not (options.carrier_hz and snr_db.dtype == np.float64):
        return path_sigmas_m(snr_db, speed_of_sound_m_s, options).astype(float, copy=False)
    from echoloc.localise import _locate_kernels as kernels  # numba: imported (and compiled) on first use

    sigmas: NDArray[np.float64] = kernels.path_sigmas(
        snr_db, speed_of_sound_m_s, options.path_sigma_m**2, 2 * np.pi * options.carrier_hz
    )
    return sigmas


AMPLITUDE_LOG_SIGMA = 0.1
"""Assumed spread of echo amplitudes about the spreading model, natural-log units (10 %)."""

_OWN, _SHARED, _NONE = 0, 1, 2
_SHARING_ROUNDS = 3
_MAX_SEED_ROWS = 262_144


@lru_cache(maxsize=64)
def _chi2_gate(probability: float, dof: int) -> float:
    """The chi-square quantile: ``2 P^-1(dof / 2, probability)`` with P the regularised lower
    incomplete gamma function, the very expression of ``scipy.stats.chi2.ppf``, without the
    0.8 s that importing scipy.stats adds to every command's start."""
    return float(2.0 * special.gammaincinv(dof / 2, probability)) if dof > 0 else np.inf


@lru_cache(maxsize=64)
def _gates(probability: float, dim: int, n_channels: int) -> NDArray[np.float64]:
    """Chi-square gate for an object fitted on k = 0..n_channels channels (k - dim degrees of freedom)."""
    return np.array([_chi2_gate(probability, k - dim) for k in range(n_channels + 1)])


class KernelGeometry(NamedTuple):
    """The array as the compiled association (:mod:`echoloc.localise._locate_kernels`) takes
    it: the channels' transmitters and receivers (C, D), m, their axes (C, D), the array's
    boresight (D,) and the channels where an object must show an echo (C,). ``candidates``
    and ``associate`` take it whole; the seed and refinement kernels take its fields first,
    one by one, as ``*geometry``. Tests hold the fields to the kernels' parameters and reads."""

    transmitters: NDArray[np.float64]
    receivers: NDArray[np.float64]
    transmitter_axes: NDArray[np.float64]
    receiver_axes: NDArray[np.float64]
    boresight: NDArray[np.float64]
    required: NDArray[np.bool_]


class AssociationTail(NamedTuple):
    """The seeds and options of the compiled association, which ``candidates`` and
    ``associate`` (:mod:`echoloc.localise._locate_kernels`) take whole and read by name: the
    seed sets (S, D) of channel indices, the path window (m), the field of view's cosine,
    the one-path gate (sigmas), the merge reach and sigma (m; sigma -1: no merging), the
    chi-square gates by count of echoes, whether beams are checked, the fewest own echoes,
    the rounds of echo sharing and the amplitude check's log sigma."""

    seeds: NDArray[np.int64]
    window_low: float
    window_high: float
    cos_fov: float
    k_gate: float
    merge_reach: float
    merge_sigma: float
    gates: NDArray[np.float64]
    check_beams: bool
    min_own: int
    sharing_rounds: int
    amplitude_log_sigma: float


class LocateKernelArguments(NamedTuple):
    """What the compiled association of one frame's flat echoes
    (:func:`echoloc.localise._locate_kernels.associate_frame`) takes besides the echoes: the
    geometry, the speed of sound (m/s), the prior path variance (m^2), the carrier (rad/s),
    the seeds and options, the search's node and row limits, and the origin of the objects'
    order (D,), m."""

    geometry: KernelGeometry
    speed_of_sound_m_s: float
    prior_variance_m2: float
    omega_rad_s: float
    tail: AssociationTail
    node_limit: int
    max_rows: int
    origin: NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class _Geometry:
    """The channels of one association: transmitter and receiver of each, and their axes."""

    transmitters_m: NDArray[np.float64]  # (C, D)
    receivers_m: NDArray[np.float64]  # (C, D)
    transmitter_index: NDArray[np.int64]  # (C,)
    receiver_index: NDArray[np.int64]  # (C,)
    required: NDArray[np.bool_]  # (C,) channels where an object must show an echo or explain why not
    transmitter_axes: NDArray[np.float64]  # (C, D)
    receiver_axes: NDArray[np.float64]  # (C, D)
    boresight: NDArray[np.float64]  # (D,)

    @property
    def n(self) -> int:
        return len(self.receivers_m)

    @property
    def dim(self) -> int:
        return int(self.receivers_m.shape[1])

    @property
    def kernel_arguments(self) -> KernelGeometry:
        """The first six arguments of every compiled association kernel
        (:mod:`echoloc.localise._locate_kernels`), in their order."""
        return KernelGeometry(
            self.transmitters_m,
            self.receivers_m,
            self.transmitter_axes,
            self.receiver_axes,
            self.boresight,
            self.required,
        )


@dataclass(frozen=True, eq=False)
class _Candidates:
    """Candidate objects: per channel an echo index and how it is used."""

    echo: NDArray[np.int64]  # (n, C), -1 where no echo
    use: NDArray[np.int8]  # (n, C): _OWN, _SHARED or _NONE
    solution: Solution
    amplitude_chi2: NDArray[np.float64]


def associate(
    transmitter_m: NDArray[np.float64],
    receivers_m: NDArray[np.float64],
    paths: list[NDArray[np.float64]],
    sigmas: list[NDArray[np.float64]],
    options: LocateOptions,
    usable: NDArray[np.bool_] | None = None,
    amplitudes: list[NDArray[np.float64]] | None = None,
    *,
    transmitter_index: NDArray[np.int64] | None = None,
    receiver_index: NDArray[np.int64] | None = None,
    required: NDArray[np.bool_] | None = None,
) -> list[LocatedObject]:
    """Objects from the echo paths of every channel ("peaks to points").

    ``transmitter_m`` is the one transmitter (D,) of every channel, or one per channel
    (C, D) when frames of several transmitters are combined (:func:`combine_frames`
    builds those arguments). ``paths[c]`` and ``sigmas[c]`` are channel c's echoes, m.
    ``required`` marks the channels on which every object must show an echo or have
    a reason not to (default: all); the others support an object when they agree.

    1. Seeds: for D required channels of one transmitter at a time, every choice of
       one echo per channel that the triangle inequality allows (``|l_i - l_j| <=
       |R_i - R_j| + |T_i - T_j|`` and ``l_i >= |R_i - T_i|``, with 4-sigma slack)
       is solved exactly (:func:`exact_solutions`); points behind the array or
       outside the seed channels' beams are dropped.
    2. Every other channel that can see the point (inside its window and beams) has
       its path predicted from the seed, with the variance propagated from the
       seed's paths; the nearest echo within the chi-square gate is the object's own,
       one up to a quarter resolution further is a merged peak (weighted with
       :func:`_merge_sigma`). A required channel with neither rejects the seed.
    3. Each candidate is refined by Gauss-Newton on all its echoes and kept when its
       chi-square passes the gate (failing that, again without optional channels).
    4. The heaviest set of candidates with no echo in common is chosen (exact
       weighted set packing), those with only own echoes first; weights count
       objects first, then the residual, merged echoes and, when ``amplitudes`` are
       given, the consistency of the echo amplitudes with spherical spreading (a
       ghost built from echoes of different reflectors rarely has amplitudes that
       agree). In rounds, candidates that lost echoes to chosen objects and keep
       enough of their own are tried again with those echoes shared. Objects whose
       echoes all but one serve others, and objects that repeat another, go.
    """
    receivers = np.asarray(receivers_m, dtype=float)
    n_ch, dim = receivers.shape
    setup = _setup(transmitter_m, receivers, usable, transmitter_index, receiver_index, required, options)
    active = setup.active
    if len(active) < max(options.min_receivers, dim):
        return []
    echoes = _flatten(
        [paths[c] for c in active],
        [sigmas[c] for c in active],
        None if amplitudes is None else [amplitudes[c] for c in active],
    )
    return _objects(setup, echoes, options, n_ch)


def _objects(setup: _Setup, echoes: _Echoes, options: LocateOptions, n_ch: int) -> list[LocatedObject]:
    """Steps 1-4 of :func:`associate` on the usable channels' echoes, as located objects."""
    geometry, receiver_of, transmitter_of = setup.geometry, setup.receiver_of, setup.transmitter_of
    if _COMPILED:
        compiled = _associate_compiled(setup, echoes, options)
        if not isinstance(compiled, list):
            return _located(setup, *compiled, n_ch)
        chosen = compiled
    else:
        candidates = _seed_candidates(geometry, echoes, options)
        if len(candidates.echo) == 0:
            return []
        candidates = _refine(geometry, candidates, echoes, options)
        chosen = _choose_reference(geometry, candidates, echoes, options)
    objects = [
        LocatedObject(
            position_m=obj.position_m,
            covariance_m2=obj.covariance_m2,
            receivers=tuple([receiver_of[c] for c in obj.receivers]),
            echo_indices=obj.echo_indices,
            chi2=obj.chi2,
            score=obj.score * len(obj.receivers) / n_ch,
            transmitters=tuple([transmitter_of[c] for c in obj.receivers]),
            shared=obj.shared,
        )
        for obj in chosen
    ]
    objects.sort(key=lambda o: _distance(o.position_m - setup.origin))
    return objects


def chi2_tail(dof: int, chi2: float) -> float:
    """P(X > ``chi2``) for X chi-square with ``dof`` >= 1 degrees of freedom: an object's score.

    One and two degrees (four receivers in 3-D, or five) have closed forms, erfc(sqrt(chi2 / 2))
    and exp(-chi2 / 2) (Abramowitz & Stegun 26.4.4 and 26.4.5 with their sums empty); beyond,
    scipy.special.chdtrc. The closed forms skip chdtrc's general algorithm, which for one
    degree took a noticeable share of a frame's localisation.
    """
    if dof in (1, 2) and chi2 < 0:
        return math.nan  # as chdtrc: no chi-square is negative
    if dof == 1:
        return math.erfc(math.sqrt(0.5 * chi2))
    if dof == 2:
        return math.exp(-0.5 * chi2)
    return float(special.chdtrc(max(dof, 1), chi2))


def _located(
    setup: _Setup,
    echo_use: NDArray[np.int64],
    position: NDArray[np.float64],
    covariance: NDArray[np.float64],
    chi2: NDArray[np.float64],
    nearest_first: bool,
    n_ch: int,
) -> list[LocatedObject]:
    """:func:`_objects` from the compiled choice's surviving rows (``echo_use``: each row's
    echo indices, then its use; ``nearest_first``: already in the objects' order), with the
    same scores and order as from ``_Chosen``."""
    if len(chi2) == 0:
        return []
    n_channels = len(setup.receiver_of)
    supports = setup.supports
    rows: list[list[int]] = echo_use.tolist()
    support = []
    for row in rows:
        use = tuple(row[n_channels:])
        found = supports.get(use)
        if found is None:
            found = supports[use] = _support(use, setup)
        support.append(found)
    chi2_rows: list[float] = chi2.tolist()
    order: Any = range(len(rows))
    if len(rows) > 1 and not nearest_first:
        distance = [math.sqrt(offset.dot(offset)) for offset in position - setup.origin]
        order = sorted(order, key=distance.__getitem__)  # stable, as objects.sort
    objects = []
    for k in order:
        s = support[k]
        score = (chi2_tail(s.tail_dof, chi2_rows[k]) if s.dof > 0 else 1.0) * len(s.channels) / n_ch
        objects.append(
            _located_object(
                position[k],
                covariance[k],
                s.receivers,
                s.pick(rows[k]),
                chi2_rows[k],
                score,
                s.transmitters,
                s.shared,
            )
        )
    return objects


_new = object.__new__


def _located_object(
    position_m: NDArray[np.float64],
    covariance_m2: NDArray[np.float64],
    receivers: tuple[int, ...],
    echo_indices: tuple[int, ...],
    chi2: float,
    score: float,
    transmitters: tuple[int, ...],
    shared: int,
) -> LocatedObject:
    """``LocatedObject(...)`` as its ``__init__`` builds it (every field given, no
    ``__post_init__``), in one dict update instead of the frozen class's nine
    ``object.__setattr__`` calls: cheaper, and it runs for every object of every frame."""
    obj: LocatedObject = _new(LocatedObject)
    obj.__dict__.update(
        position_m=position_m,
        covariance_m2=covariance_m2,
        receivers=receivers,
        echo_indices=echo_indices,
        chi2=chi2,
        score=score,
        transmitters=transmitters,
        shared=shared,
        surface=None,
    )
    return obj


class _Support(NamedTuple):
    """What an object's use of the channels gives: its channels, receivers and transmitters,
    how to pick its echo indices from its row, how many echoes it shares, its degrees of
    freedom (channels - D) and those its score's chi-square tail takes (at least 1)."""

    channels: list[int]
    receivers: tuple[int, ...]
    transmitters: tuple[int, ...]
    pick: Callable[[list[int]], tuple[int, ...]]
    shared: int
    dof: int
    tail_dof: int


def _support(use: tuple[int, ...], setup: _Setup) -> _Support:
    channels = [c for c, u in enumerate(use) if u != _NONE]
    get = itemgetter(*channels)
    dof = len(channels) - setup.geometry.dim
    return _Support(
        channels,
        tuple([setup.receiver_of[c] for c in channels]),
        tuple([setup.transmitter_of[c] for c in channels]),
        get if len(channels) > 1 else lambda row: (get(row),),
        use.count(_SHARED),
        dof,
        max(dof, 1),
    )


def _distance(offset: NDArray[np.float64]) -> float:
    """np.linalg.norm of a vector, as it computes it (sqrt of the dot product), without its overhead."""
    return math.sqrt(float(offset.dot(offset)))


class _Setup(NamedTuple):
    """What every frame of a stream shares (cached by :func:`_setup`)."""

    geometry: _Geometry  # of the usable channels
    active: list[int]  # the usable channels' indices
    origin: NDArray[np.float64]  # of the objects' order (the first transmitter)
    receiver_of: list[int]  # each usable channel's receiver
    transmitter_of: list[int]  # and transmitter
    # Memos, filled as frames come (the same key always gives the same value: no state
    # leaks from one frame to the next): _support per use of the channels, and the
    # compiled association's seeds and options per options (_kernel_tail).
    supports: dict[tuple[int, ...], _Support]
    kernel_tails: dict[LocateOptions, AssociationTail]


_SETUPS: dict[tuple[Any, ...], _Setup] = {}


def _key(a: Any) -> tuple[Any, ...] | None:
    """Hashable value of an array argument (None stays None; a hashable tuple, as options'
    boresight, is its own: equal tuples give equal arrays)."""
    if a is None:
        return None
    if type(a) is np.ndarray:
        return (a.shape, a.dtype, a.tobytes())
    if type(a) is tuple:
        try:
            hash(a)
        except TypeError:
            pass
        else:
            return a
    a = np.asarray(a)
    return (a.shape, a.dtype, a.tobytes())


def _setup(
    transmitter_m: NDArray[np.float64],
    receivers: NDArray[np.float64],
    usable: NDArray[np.bool_] | None,
    transmitter_index: NDArray[np.int64] | None,
    receiver_index: NDArray[np.int64] | None,
    required: NDArray[np.bool_] | None,
    options: LocateOptions,
) -> _Setup:
    """The geometry of the usable channels, their indices, the origin of the objects' order,
    and each channel's receiver and transmitter: the same for every frame of a stream (cached by
    the arguments' values, built here on a miss)."""
    key = (
        _key(transmitter_m),
        _key(receivers),
        _key(usable),
        _key(transmitter_index),
        _key(receiver_index),
        _key(required),
        _key(options.boresight),
        _key(options.transmitter_axes),
        _key(options.receiver_axes),
    )
    setup = _SETUPS.get(key)
    if setup is not None:
        return setup
    if len(_SETUPS) >= 64:
        _SETUPS.clear()
    n_ch, dim = receivers.shape
    usable_mask = np.ones(n_ch, dtype=bool) if usable is None else np.asarray(usable, dtype=bool)
    tx = np.broadcast_to(np.asarray(transmitter_m, dtype=float), (n_ch, dim))
    tx_index = (
        np.zeros(n_ch, np.int64) if transmitter_index is None else np.asarray(transmitter_index, np.int64)
    )
    rx_index = np.arange(n_ch) if receiver_index is None else np.asarray(receiver_index, np.int64)
    if transmitter_index is None and np.ndim(transmitter_m) == 2:
        _, tx_index = np.unique(tx, axis=0, return_inverse=True)
        tx_index = tx_index.reshape(-1)
    active = np.flatnonzero(usable_mask)
    must = np.ones(n_ch, dtype=bool) if required is None else np.asarray(required, dtype=bool)
    geometry = _geometry(
        tx[active], receivers[active], tx_index[active], rx_index[active], must[active], options, dim
    )
    setup = _SETUPS[key] = _Setup(
        geometry, active.tolist(), tx[0].copy(), rx_index[active].tolist(), tx_index[active].tolist(), {}, {}
    )
    return setup


def _geometry(
    tx: NDArray[np.float64],
    rx: NDArray[np.float64],
    tx_index: NDArray[np.int64],
    rx_index: NDArray[np.int64],
    required: NDArray[np.bool_],
    options: LocateOptions,
    dim: int,
) -> _Geometry:
    boresight = np.asarray(options.boresight, dtype=float)[-dim:]
    boresight = boresight / np.linalg.norm(boresight)

    def axes(given: NDArray[np.float64] | None, index: NDArray[np.int64]) -> NDArray[np.float64]:
        if given is None:
            return np.broadcast_to(boresight, (len(index), dim)).copy()
        a = np.asarray(given, dtype=float)[index][:, -dim:]
        return np.asarray(a / np.linalg.norm(a, axis=1, keepdims=True))

    # C-ordered, writeable arrays: what the compiled stages take as they are.
    return _Geometry(
        *(
            np.array(a, order="C")
            for a in (
                tx,
                rx,
                tx_index,
                rx_index,
                required,
                axes(options.transmitter_axes, tx_index),
                axes(options.receiver_axes, rx_index),
                boresight,
            )
        )
    )


def _seed_sets(geometry: _Geometry) -> list[tuple[int, ...]]:
    """Which D channels seed candidates: per transmitter, every D of its channels, so
    that an object whose echo on some channel merged with another's, or lies outside
    that channel's window or beam, still has a seed of its own echoes. Only required
    channels seed: objects are those of the newest frame (cached)."""
    return _seed_sets_cached(geometry.transmitter_index.tobytes(), geometry.required.tobytes(), geometry.dim)


@lru_cache(maxsize=32)
def _seed_sets_cached(tx_index: bytes, required: bytes, dim: int) -> list[tuple[int, ...]]:
    index = np.frombuffer(tx_index, dtype=np.int64)
    must = np.frombuffer(required, dtype=bool)
    return [
        seed
        for t in np.unique(index[must])
        for seed in combinations(np.flatnonzero((index == t) & must).tolist(), dim)
    ]


def _associate_compiled(
    setup: _Setup, echoes: _Echoes, options: LocateOptions
) -> (
    list[_Chosen]
    | tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], bool]
):
    """Steps 1-4 of :func:`associate` in one compiled call (:func:`_seed_candidates`,
    :func:`_refine` and :func:`_choose` in turn, without the calls between them): the
    kernel's surviving rows (echo_use, positions, covariances, chi2, and whether they are
    nearest first already), or, when it leaves the choice to the reference (tied
    weights), the reference's choice."""
    from echoloc.localise import _locate_kernels as kernels  # numba: imported (and compiled) on first use

    geometry = setup.geometry
    args = (
        geometry.kernel_arguments,
        echoes.paths,
        echoes.sigmas,
        _NO_AMPLITUDES if echoes.amplitudes is None else echoes.amplitudes,
        echoes.offset,
        _kernel_tail(setup, options),
        _NODE_LIMIT,
        _MAX_SEED_ROWS,
    )
    status, echo_use, position, covariance, chi2 = kernels.associate(*args, setup.origin)
    if status == 1:
        warnings.warn(
            f"frame skipped: more than {_MAX_SEED_ROWS} echo combinations to associate; "
            "raise the detection threshold",
            LocateWarning,
            stacklevel=4,
        )
        return []
    if status == 2:
        # The same seeds and refinement again (ties are rare).
        echo, use, position, covariance, chi2, converged, amplitude_chi2 = kernels.candidates(*args)[1]
        candidates = _Candidates(echo, use, Solution(position, covariance, chi2, converged), amplitude_chi2)
        return _choose_reference(geometry, candidates, echoes, options)
    return echo_use, position, covariance, chi2, status == 0


def _kernel_tail(setup: _Setup, options: LocateOptions) -> AssociationTail:
    """The compiled association's arguments between the echoes and the limits: the seeds and
    the options (memo per options)."""
    try:
        return setup.kernel_tails[options]
    except KeyError:
        pass
    except TypeError:  # options holding unhashable values (a list for a tuple): no memo
        return _make_kernel_tail(setup.geometry, options)
    if len(setup.kernel_tails) >= 16:
        setup.kernel_tails.clear()
    tail = setup.kernel_tails[options] = _make_kernel_tail(setup.geometry, options)
    return tail


def _make_kernel_tail(geometry: _Geometry, options: LocateOptions) -> AssociationTail:
    return AssociationTail(_seed_array(geometry), *_kernel_options(options, geometry.dim, geometry.n))


def _kernel_options(options: LocateOptions, dim: int, n_channels: int) -> tuple[Any, ...]:
    """The options as the compiled association takes them (window .. amplitude sigma)."""
    beams = _checks_beams(options)  # from the axes too, which the options' hash leaves out
    try:
        return _kernel_options_cached(options, dim, n_channels, beams)
    except TypeError:  # options holding unhashable values (a list for a tuple)
        return _kernel_options_cached.__wrapped__(options, dim, n_channels, beams)


@lru_cache(maxsize=64)
def _kernel_options_cached(options: LocateOptions, dim: int, n_channels: int, beams: bool) -> tuple[Any, ...]:
    low, high = options.window_m
    return (
        float(low),
        float(high),
        float(np.cos(np.radians(options.field_of_view_deg))),
        float(np.sqrt(_chi2_gate(options.gate_probability, 1))),
        _merge_reach(options),
        -1.0 if options.resolution_m is None else _merge_sigma(options.resolution_m),
        _gates(options.gate_probability, dim, n_channels),
        beams,
        max(options.min_receivers, dim),
        _SHARING_ROUNDS if options.resolution_m is not None else 0,
        AMPLITUDE_LOG_SIGMA,
    )


def _seed_array(geometry: _Geometry) -> NDArray[np.int64]:
    return _seed_array_cached(geometry.transmitter_index.tobytes(), geometry.required.tobytes(), geometry.dim)


@lru_cache(maxsize=32)
def _seed_array_cached(tx_index: bytes, required: bytes, dim: int) -> NDArray[np.int64]:
    return np.array(_seed_sets_cached(tx_index, required, dim), dtype=np.int64).reshape(-1, dim)


def _seed_candidates(geometry: _Geometry, echoes: _Echoes, options: LocateOptions) -> _Candidates:
    """Steps 1-2 of :func:`associate`: seeds solved exactly, the other channels attached.

    The loops run compiled (:func:`echoloc.localise._locate_kernels.seed_candidates`).
    """
    dim, n_ch = geometry.dim, geometry.n
    seeds = np.array(_seed_sets(geometry), dtype=np.int64).reshape(-1, dim)
    from echoloc.localise import _locate_kernels as kernels  # numba: imported (and compiled) on first use

    # Sorted within each channel: by channel first, then by path.
    if _COMPILED:
        sorted_paths, sorted_index = kernels.sort_within_channels(echoes.paths, echoes.offset)
    else:
        channel = np.repeat(np.arange(n_ch), np.diff(echoes.offset))
        order = np.lexsort((echoes.paths, channel))
        sorted_paths = echoes.paths[order]
        sorted_index = order - echoes.offset[channel[order]]
    low, high = options.window_m
    capacity = 4096

    while True:
        echo, use, points, count, overflow = kernels.seed_candidates(
            *geometry.kernel_arguments,
            echoes.paths,
            echoes.sigmas,
            echoes.offset,
            sorted_paths,
            sorted_index,
            seeds,
            float(low),
            float(high),
            float(np.cos(np.radians(options.field_of_view_deg))),
            float(np.sqrt(_chi2_gate(options.gate_probability, 1))),
            _merge_reach(options),
            max(options.min_receivers, dim),
            capacity,
        )
        if not overflow:
            break
        if capacity >= _MAX_SEED_ROWS:
            warnings.warn(
                f"frame skipped: more than {_MAX_SEED_ROWS} echo combinations to associate; "
                "raise the detection threshold",
                LocateWarning,
                stacklevel=4,
            )
            return _no_candidates(n_ch, dim)
        capacity *= 4
    # The same object comes from several seeds: keep one of each echo set.
    first = (
        kernels.first_of_each(echo, use, count) if _COMPILED else _first_of_each(echo[:count], use[:count])
    )
    return _Candidates(
        echo[first], use[first], _empty_solution(len(first), dim, points[first]), np.zeros(len(first))
    )


def _first_of_each(echo: NDArray[np.int64], use: NDArray[np.int8]) -> list[int]:
    """Rows that are the first of their (echo, use) (numpy reference of the compiled one)."""
    seen: set[tuple[int, ...]] = set()
    first = []
    for k, row in enumerate(np.concatenate([echo, use.astype(np.int64)], axis=1).tolist()):
        if tuple(row) not in seen:
            seen.add(tuple(row))
            first.append(k)
    return first


def _no_candidates(n_ch: int, dim: int) -> _Candidates:
    empty = np.zeros((0, n_ch), dtype=np.int64)
    return _Candidates(empty, empty.astype(np.int8), _empty_solution(0, dim), np.zeros(0))


def _merge_reach(options: LocateOptions) -> float:
    """How far a merged peak may sit from an echo's path, m: resolution / 4 (see _merge_sigma)."""
    return 0.0 if options.resolution_m is None else float(0.25 * options.resolution_m)


def _merge_sigma(resolution_m: float) -> float:
    """Standard deviation of a merged peak about either of its two paths, m.

    The estimator separates echoes further apart than about half the resolution, so
    merged echoes lie at most ``s = resolution / 2`` apart and their common peak
    sits between them: an offset up to ``s / 2`` either way, uniform, so
    ``sigma = s / sqrt(12) = resolution / (4 sqrt 3)``. Checked on 1000 simulated
    frames: objects with shared echoes then have normalised errors of 0.8-1.1.
    """
    return float(resolution_m / (4 * np.sqrt(3.0)))


def _empty_solution(n: int, dim: int, start: NDArray[np.float64] | None = None) -> Solution:
    position = np.zeros((n, dim)) if start is None else start
    return Solution(position, np.full((n, dim, dim), np.nan), np.full(n, np.nan), np.zeros(n, dtype=bool))


def _in_beams(geometry: _Geometry, points: NDArray[np.float64], cos_fov: float) -> NDArray[np.bool_]:
    """(n, C): is each point inside both the transmitter's and the receiver's beam of each channel?"""
    inside = np.ones((len(points), geometry.n), dtype=bool)
    for origins, axes in (
        (geometry.transmitters_m, geometry.transmitter_axes),
        (geometry.receivers_m, geometry.receiver_axes),
    ):
        offset = points[:, None, :] - origins
        along = np.einsum("ncd,cd->nc", offset, axes)
        inside &= along >= cos_fov * np.linalg.norm(offset, axis=2)
    return inside


def _ahead(geometry: _Geometry, points: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Points in front of the array (the half-space its boresight faces, from transmitter 0)."""
    return np.asarray((points - geometry.transmitters_m[0]) @ geometry.boresight > 0)


def _refine(
    geometry: _Geometry, candidates: _Candidates, echoes: _Echoes, options: LocateOptions
) -> _Candidates:
    """Step 3: Gauss-Newton on every candidate's echoes; keep those that pass the gate.

    A candidate that fails with echoes on optional channels (older frames of other
    transmitters, whose reflector may have moved since) is fitted again without them.
    Runs compiled (:func:`echoloc.localise._locate_kernels.refine`); :func:`_refine_reference`
    is the same in numpy.
    """
    if not _COMPILED:
        return _refine_reference(geometry, candidates, echoes, options)
    from echoloc.localise import _locate_kernels as kernels  # numba: imported (and compiled) on first use

    echo, use, position, covariance, chi2, converged, amplitude_chi2 = kernels.refine(
        *geometry.kernel_arguments,
        echoes.paths,
        echoes.sigmas,
        _NO_AMPLITUDES if echoes.amplitudes is None else echoes.amplitudes,
        echoes.offset,
        np.ascontiguousarray(candidates.echo, dtype=np.int64),
        np.ascontiguousarray(candidates.use, dtype=np.int8),
        np.ascontiguousarray(candidates.solution.position_m, dtype=float),
        -1.0 if options.resolution_m is None else _merge_sigma(options.resolution_m),
        _gates(options.gate_probability, geometry.dim, geometry.n),
        _checks_beams(options),
        float(np.cos(np.radians(options.field_of_view_deg))),
        max(options.min_receivers, geometry.dim),
        6,
        AMPLITUDE_LOG_SIGMA,
    )
    return _Candidates(echo, use, Solution(position, covariance, chi2, converged), amplitude_chi2)


_COMPILED = True
"""Whether association runs its compiled stages (False: the numpy references, for tests)."""
_NO_AMPLITUDES = np.zeros(0)


def _checks_beams(options: LocateOptions) -> bool:
    """Whether solutions are held to the beams (a narrower field of view, or axes of their own)."""
    return bool(
        options.field_of_view_deg < 90
        or options.transmitter_axes is not None
        or options.receiver_axes is not None
    )


def _refine_reference(
    geometry: _Geometry, candidates: _Candidates, echoes: _Echoes, options: LocateOptions
) -> _Candidates:
    """:func:`_refine` in numpy."""
    echo, use = candidates.echo, candidates.use
    solution, ok = _fit_and_gate(geometry, echo, use, candidates.solution.position_m, echoes, options)
    optional = (use != _NONE) & ~geometry.required
    retry = ~ok & np.any(optional, axis=1)
    if np.any(retry):
        rows = np.flatnonzero(retry)
        use = use.copy()
        echo = echo.copy()
        use[rows[:, None], np.flatnonzero(~geometry.required)[None, :]] = _NONE
        echo = np.where(use != _NONE, echo, -1)
        enough = np.sum(use[rows] == _OWN, axis=1) >= max(options.min_receivers, geometry.dim)
        rows = rows[enough]
        again, again_ok = _fit_and_gate(
            geometry, echo[rows], use[rows], candidates.solution.position_m[rows], echoes, options
        )
        for field_name in ("position_m", "covariance_m2", "chi2", "converged"):
            getattr(solution, field_name)[rows] = getattr(again, field_name)
        ok[rows] = again_ok
    keep = np.flatnonzero(ok)
    solution = _rows(solution, list(keep))
    amplitude_chi2 = _amplitude_chi2(geometry, solution.position_m, echo[keep], use[keep], echoes)
    return _Candidates(echo[keep], use[keep], solution, amplitude_chi2)


def _fit_and_gate(
    geometry: _Geometry,
    echo: NDArray[np.int64],
    use: NDArray[np.int8],
    start: NDArray[np.float64],
    echoes: _Echoes,
    options: LocateOptions,
) -> tuple[Solution, NDArray[np.bool_]]:
    """Gauss-Newton on the candidates' echoes; which pass the chi-square gate, in front and in view."""
    measured, weights = _measurements(echoes, echo, use, options)
    solution = _gauss_newton(geometry.transmitters_m, geometry.receivers_m, measured, weights, start, 6)
    n_used = np.sum(use != _NONE, axis=1)
    gate = _gates(options.gate_probability, geometry.dim, geometry.n)[n_used]
    ok = solution.converged & (solution.chi2 <= gate)
    if np.any(ok):
        points = solution.position_m[ok]
        inside = _ahead(geometry, points)
        if _checks_beams(options):
            supported = use[ok] != _NONE
            cos_fov = np.cos(np.radians(options.field_of_view_deg))
            inside &= np.all(_in_beams(geometry, points, cos_fov) | ~supported, axis=1)
        ok[ok] &= inside
    return solution, np.asarray(ok)


def _measurements(
    echoes: _Echoes, echo: NDArray[np.int64], use: NDArray[np.int8], options: LocateOptions
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Paths and weights (n, C) of candidates; shared echoes weigh as merged peaks."""
    has = use != _NONE
    index = np.where(has, echoes.offset[:-1] + echo, 0)
    measured = np.where(has, echoes.paths[index], 0.0)
    sigma = echoes.sigmas[index]
    if options.resolution_m is not None:
        sigma = np.where(use == _SHARED, np.hypot(sigma, _merge_sigma(options.resolution_m)), sigma)
    weights = np.where(has, 1.0 / sigma**2, 0.0)
    return measured, weights


@dataclass(frozen=True, eq=False)
class _Echoes:
    """Every channel's echoes in flat arrays: channel c's at ``offset[c]:offset[c + 1]``."""

    offset: NDArray[np.int64]  # (C + 1,)
    paths: NDArray[np.float64]
    sigmas: NDArray[np.float64]
    amplitudes: NDArray[np.float64] | None


def _flatten(
    paths: list[NDArray[np.float64]],
    sigmas: list[NDArray[np.float64]],
    amplitudes: list[NDArray[np.float64]] | None,
) -> _Echoes:
    offset = np.zeros(len(paths) + 1, dtype=np.int64)
    offset[1:] = np.cumsum([len(p) for p in paths])

    def flat(values: list[NDArray[np.float64]]) -> NDArray[np.float64]:
        return np.concatenate([np.zeros(0), *values]).astype(float)

    return _Echoes(offset, flat(paths), flat(sigmas), None if amplitudes is None else flat(amplitudes))


def _amplitude_chi2(
    geometry: _Geometry,
    points: NDArray[np.float64],
    echo: NDArray[np.int64],
    use: NDArray[np.int8],
    echoes: _Echoes,
) -> NDArray[np.float64]:
    """How far the own echoes' amplitudes times the spreading ``r_T r_R`` are from equal."""
    if echoes.amplitudes is None or len(points) == 0:
        return np.zeros(len(points))
    own = use == _OWN
    amplitude = np.where(own, np.abs(echoes.amplitudes[np.where(own, echoes.offset[:-1] + echo, 0)]), 1.0)
    spread = np.linalg.norm(points[:, None, :] - geometry.transmitters_m, axis=2) * np.linalg.norm(
        points[:, None, :] - geometry.receivers_m, axis=2
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        log_strength = np.where(own, np.log(amplitude * spread), 0.0)
    count = np.maximum(np.sum(own, axis=1), 1)
    mean = np.sum(log_strength, axis=1) / count
    spread2 = np.sum(np.where(own, (log_strength - mean[:, None]) ** 2, 0.0), axis=1)
    return np.asarray(np.nan_to_num(spread2 / AMPLITUDE_LOG_SIGMA**2 / count, nan=1e3, posinf=1e3))


class _Chosen(NamedTuple):
    """One chosen object (a named tuple: built per object and frame, so cheaply)."""

    position_m: NDArray[np.float64]
    covariance_m2: NDArray[np.float64]
    receivers: tuple[int, ...]  # channel indices (mapped to receivers by associate)
    echo_indices: tuple[int, ...]
    chi2: float
    score: float
    shared: int


@dataclass(frozen=True, eq=False)
class _Candidate:
    echoes: frozenset[tuple[int, int]]  # (channel, echo index) of every echo it uses
    weight: float
    row: int


def _weights(candidates: _Candidates, options: LocateOptions, dim: int) -> NDArray[np.float64]:
    """Packing weight: one per object, less a tie-break (< 0.1) for residual, merges, amplitudes."""
    n_used = np.sum(candidates.use != _NONE, axis=1)
    gate = _gates(options.gate_probability, dim, candidates.use.shape[1])[n_used]
    gate = np.where(np.isfinite(gate), np.maximum(gate, 1.0), 1.0)
    n_shared = np.sum(candidates.use == _SHARED, axis=1)
    tie = candidates.solution.chi2 / gate + candidates.amplitude_chi2 / np.maximum(n_used, 1) + 0.5 * n_shared
    return np.asarray(1.0 - 1e-3 * np.minimum(tie, 100.0))


_NODE_LIMIT = 50_000


def _choose_reference(
    geometry: _Geometry, candidates: _Candidates, echoes: _Echoes, options: LocateOptions
) -> list[_Chosen]:
    """:func:`_choose` in Python and numpy."""
    weights = _weights(candidates, options, geometry.dim).tolist()
    echo_rows: list[list[int]] = candidates.echo.tolist()
    use_rows: list[list[int]] = candidates.use.tolist()
    items = [
        _Candidate(frozenset(_attached(e, u)), w, k)
        for k, (e, u, w) in enumerate(zip(echo_rows, use_rows, weights, strict=True))
    ]
    # First pass: candidates whose echoes are all their own; each echo used once.
    first_pass = [item for item in items if _SHARED not in use_rows[item.row]]
    picked = [first_pass[i].row for i in _best_disjoint(first_pass)]
    # Then candidates with a merged-looking echo no chosen object uses (its partner may
    # be the next candidate, or an echo merely biased): still each echo used once.
    taken_echoes = {e for k in picked for e in items[k].echoes}
    second_pass = [
        item for item in items if _SHARED in use_rows[item.row] and not (item.echoes & taken_echoes)
    ]
    picked += [second_pass[i].row for i in _best_disjoint(second_pass)]
    chosen_echo = [echo_rows[k] for k in picked]
    chosen_use = [list(use_rows[k]) for k in picked]
    starts = [candidates.solution.position_m[k] for k in picked]
    # Sharing needs one own echo fewer: the shared ones still take part in the fit.
    min_own_sharing = max(options.min_receivers, geometry.dim) - 1
    done = set(picked)
    for _ in range(_SHARING_ROUNDS if options.resolution_m is not None else 0):
        # Merged peaks: a candidate may share echoes that chosen objects use (two
        # reflectors' echoes merged there) when enough echoes of its own remain.
        # Rounds, because an object found by sharing can explain the next one's merge.
        claimed = {e for er, ur in zip(chosen_echo, chosen_use, strict=True) for e in _attached(er, ur)}
        retry = []
        for item in items:
            own = {e for e in item.echoes if use_rows[item.row][e[0]] == _OWN}
            shared = item.echoes - own
            if item.row in done or not shared <= claimed:
                continue
            if (shared or own & claimed) and len(own - claimed) >= min_own_sharing:
                retry.append(item.row)
        if not retry:
            break
        done.update(retry)
        new_use = candidates.use[retry].copy()
        for i, row in enumerate(retry):
            for c, e in _attached(echo_rows[row], use_rows[row]):
                if (c, e) in claimed:
                    new_use[i, c] = _SHARED
        second = _refine(
            geometry,
            _Candidates(
                candidates.echo[retry], new_use, _rows(candidates.solution, retry), np.zeros(len(retry))
            ),
            echoes,
            options,
        )
        taken: set[tuple[int, int]] = set()
        added = False
        second_echo, second_use = second.echo.tolist(), second.use.tolist()
        # Heaviest first; ties in candidate order (a stable sort: the same on every platform).
        for k in np.argsort(-_weights(second, options, geometry.dim), kind="stable").tolist():
            attached = set(_attached(second_echo[k], second_use[k]))
            merged = {e for e in attached if second_use[k][e[0]] == _SHARED}
            if ((attached - merged) & (claimed | taken)) or not merged <= claimed:
                continue
            taken |= attached - merged
            chosen_echo.append(second_echo[k])
            chosen_use.append(second_use[k])
            starts.append(second.solution.position_m[k])
            added = True
        if not added:
            break
    # An object must keep echoes no other object explains: one whose echoes all (but
    # one) serve other objects too is a crossing of theirs, a ghost. Worst first.
    users = _users(chosen_echo, chosen_use)
    while chosen_echo:
        exclusive = [
            sum(users[e] == 1 for e in _attached(er, ur))
            for er, ur in zip(chosen_echo, chosen_use, strict=True)
        ]
        worst = int(np.argmin(exclusive))
        if exclusive[worst] >= min_own_sharing:
            break
        for pair in _attached(chosen_echo[worst], chosen_use[worst]):
            users[pair] -= 1
        del chosen_echo[worst], chosen_use[worst], starts[worst]
    if not chosen_echo:
        return []
    # Every echo that serves two objects is a merged peak for all of them: re-solve.
    for er, ur in zip(chosen_echo, chosen_use, strict=True):
        for c, e in _attached(er, ur):
            if users[(c, e)] > 1:
                ur[c] = _SHARED
    echo = np.array(chosen_echo, dtype=np.int64)
    use = np.array(chosen_use, dtype=np.int8)
    measured, weight = _measurements(echoes, echo, use, options)
    final = _gauss_newton(
        geometry.transmitters_m, geometry.receivers_m, measured, weight, np.array(starts), 4
    )
    n_used = np.sum(use != _NONE, axis=1)
    dof = n_used - geometry.dim
    score = [
        chi2_tail(d, value) if d > 0 else 1.0
        for d, value in zip(dof.tolist(), final.chi2.tolist(), strict=True)
    ]
    good = final.converged & np.all(np.isfinite(final.covariance_m2), axis=(1, 2))
    good &= ~_duplicates(geometry, final, use, options)
    result = []
    for k in np.flatnonzero(good).tolist():
        channels = [c for c, u in enumerate(chosen_use[k]) if u != _NONE]
        result.append(
            _Chosen(
                final.position_m[k],
                final.covariance_m2[k],
                tuple(channels),
                tuple(chosen_echo[k][c] for c in channels),
                float(final.chi2[k]),
                score[k],
                sum(1 for u in chosen_use[k] if u == _SHARED),
            )
        )
    return result


def _duplicates(
    geometry: _Geometry, solution: Solution, use: NDArray[np.int8], options: LocateOptions
) -> NDArray[np.bool_]:
    """Objects that repeat a better one: their paths on every channel within a merge's reach
    of its paths, so no echo could tell the two apart (an echo split in two makes them).
    The one with more shared echoes, then the larger chi-square, goes."""
    drop = np.zeros(len(use), dtype=bool)
    if options.resolution_m is None or len(use) < 2:
        return drop
    paths = model_paths_m(geometry.transmitters_m, geometry.receivers_m, solution.position_m)
    close = np.all(np.abs(paths[:, None, :] - paths[None, :, :]) <= _merge_reach(options), axis=2)
    rank = np.sum(use == _SHARED, axis=1) * 1e6 + np.nan_to_num(solution.chi2, nan=1e6)
    for i, j in zip(*np.nonzero(np.triu(close, 1)), strict=True):
        if not (drop[i] or drop[j]):
            drop[i if rank[i] > rank[j] else j] = True
    return drop


def _users(echo: list[list[int]], use: list[list[int]]) -> dict[tuple[int, int], int]:
    """How many objects use each (channel, echo index)."""
    users: dict[tuple[int, int], int] = {}
    for er, ur in zip(echo, use, strict=True):
        for pair in _attached(er, ur):
            users[pair] = users.get(pair, 0) + 1
    return users


def _attached(echo: list[int], use: list[int]) -> list[tuple[int, int]]:
    """(channel, echo index) of every echo a candidate uses."""
    return [(c, e) for c, (e, u) in enumerate(zip(echo, use, strict=True)) if u != _NONE]


def _rows(solution: Solution, rows: list[int]) -> Solution:
    return Solution(
        solution.position_m[rows], solution.covariance_m2[rows], solution.chi2[rows], solution.converged[rows]
    )


def _best_disjoint(candidates: list[_Candidate], node_limit: int = _NODE_LIMIT) -> list[int]:
    """Indices of the heaviest set of candidates that share no echo (weighted set packing).

    Solved exactly by branch and bound on each connected group of conflicting
    candidates. The bound is the best weight per echo times the echoes still free
    (an upper bound on what the remaining candidates can add). Past
    ``node_limit`` steps in a group the best set found so far is kept (never worse
    than the greedy choice it starts from).
    """
    n = len(candidates)
    owners: dict[tuple[int, int], list[int]] = {}
    for i, candidate in enumerate(candidates):
        for e in candidate.echoes:
            owners.setdefault(e, []).append(i)
    conflicts: list[set[int]] = [set() for _ in range(n)]
    for group_members in owners.values():
        for i in group_members:
            conflicts[i].update(group_members)
    chosen: list[int] = []
    seen: set[int] = set()
    for root in range(n):
        if root in seen:
            continue
        group, stack = [], [root]
        seen.add(root)
        while stack:
            node = stack.pop()
            group.append(node)
            for other in conflicts[node] - seen:
                seen.add(other)
                stack.append(other)
        if len(group) == 1:
            chosen.append(group[0])
            continue
        chosen.extend(_pack_group(sorted(group, key=lambda i: -candidates[i].weight), candidates, node_limit))
    return chosen


def _pack_group(group: list[int], candidates: list[_Candidate], node_limit: int) -> list[int]:
    """Branch and bound over one group of candidates, heaviest first."""
    items = [candidates[i] for i in group]
    per_echo = max(max(c.weight / max(len(c.echoes), 1) for c in items), 0.0)
    # Echoes still reachable from position k onwards.
    reachable: list[frozenset[tuple[int, int]]] = [frozenset()] * (len(items) + 1)
    for k in range(len(items) - 1, -1, -1):
        reachable[k] = reachable[k + 1] | items[k].echoes
    best: list[int] = []
    used: set[tuple[int, int]] = set()
    for k, item in enumerate(items):  # the greedy incumbent
        if item.weight > 0 and not (item.echoes & used):
            best.append(k)
            used |= item.echoes
    best_weight = sum(items[k].weight for k in best)
    steps = 0
    picked: list[int] = []
    # Depth first, "take item k" before "leave it", on an explicit stack: a group of
    # thousands of candidates (a corrupt frame full of echoes) must not exhaust Python's
    # recursion limit. None on the stack: the "take" subtree above it is done, untake k.
    stack: list[tuple[int, frozenset[tuple[int, int]], float] | None] = [(0, frozenset(), 0.0)]
    while stack:
        node = stack.pop()
        if node is None:
            picked.pop()
            continue
        k, taken, total = node
        steps += 1
        if total > best_weight + 1e-12:
            best, best_weight = list(picked), total
        if k == len(items) or steps > node_limit:
            continue
        if total + per_echo * len(reachable[k] - taken) <= best_weight + 1e-12:
            continue
        item = items[k]
        stack.append((k + 1, taken, total))  # leave it: after the "take" subtree
        if item.weight > 0 and not (item.echoes & taken):
            picked.append(k)
            stack.append(None)
            stack.append((k + 1, taken | item.echoes, total + item.weight))
    return [group[k] for k in best]


# --- frames --------------------------------------------------------------------------


_OFFSETS: dict[tuple[int, ...], NDArray[np.int64]] = {}


def _offset(counts: tuple[int, ...]) -> NDArray[np.int64]:
    """Where each channel's echoes start in the flat arrays, and the end: (C + 1,), by the
    echo counts (memo: frames repeat a few counts; no caller writes to it)."""
    offset = _OFFSETS.get(counts)
    if offset is None:
        if len(_OFFSETS) >= 4096:
            _OFFSETS.clear()
        offset = _OFFSETS[counts] = np.array([0, *accumulate(counts)], dtype=np.int64)
    return offset


def locate_frame(
    frame_echoes: FrameEchoes,
    transmitter_m: NDArray[np.float64],
    receivers_m: NDArray[np.float64],
    options: LocateOptions,
    usable: NDArray[np.bool_] | None = None,
) -> FrameObjects:
    """Objects of one frame from its echoes (one transmitter, one channel per receiver).

    For many frames of one geometry, :class:`FrameLocator` does the same with its set-up once."""
    return FrameLocator(transmitter_m, receivers_m, options, usable)(frame_echoes)


class FrameLocator:
    """:func:`locate_frame` for one transmitter, receivers and options: what every frame of a
    stream shares (the usable channels' geometry, the compiled association's seeds and
    options) is looked up once, here, and each call locates one frame's echoes.

    Parameters
    ----------
    transmitter_m
        (D,), m.
    receivers_m
        (n_rx, D), m; a frame's channels are its receivers, in order.
    options
        The association's options.
    usable
        (n_rx,) receivers to use (None: all).
    """

    def __init__(
        self,
        transmitter_m: NDArray[np.float64],
        receivers_m: NDArray[np.float64],
        options: LocateOptions,
        usable: NDArray[np.bool_] | None = None,
    ) -> None:
        self.transmitter_m = transmitter_m
        self.receivers_m = receivers_m
        self.options = options
        self.usable = usable
        self._setup: _Setup | None = None
        # The compiled path's arguments that stay from frame to frame (kernel_arguments adds the
        # rest): the prior path variance (m^2), the carrier (rad/s), the seeds and options.
        self._fixed_kernel_arguments: tuple[float, float, AssociationTail] | None = None
        receivers = np.asarray(receivers_m, dtype=float)
        n_ch, dim = receivers.shape
        # Every channel usable and enough of them: each frame goes straight to its flat echoes.
        if (usable is None or bool(np.all(usable))) and n_ch >= max(options.min_receivers, dim):
            self._setup = setup = _setup(transmitter_m, receivers, usable, None, None, None, options)
            if options.carrier_hz:
                self._fixed_kernel_arguments = (
                    options.path_sigma_m**2,
                    2 * np.pi * options.carrier_hz,
                    _kernel_tail(setup, options),
                )

    def __call__(self, frame_echoes: FrameEchoes) -> FrameObjects:
        """The objects of ``frame_echoes`` (its channels: the receivers, in order)."""
        channels = frame_echoes.channels
        setup = self._setup
        if setup is None or not _COMPILED or len(channels) != len(setup.active) or not channels:
            return self._general(frame_echoes)
        offset = _offset(tuple([len(ch.tof_s) for ch in channels]))
        tof = np.concatenate([ch.tof_s for ch in channels])
        snr_db = np.concatenate([ch.snr_db for ch in channels])
        flat_amplitudes = np.concatenate([ch.amplitude for ch in channels]).astype(float, copy=False)
        c = frame_echoes.speed_of_sound_m_s
        objects = None
        if self._fixed_kernel_arguments and tof.dtype == snr_db.dtype == np.float64:
            objects = self._compiled(offset, tof, c, snr_db, flat_amplitudes)
        if objects is None or (not objects and self.options.excuse_one_channel):
            echoes = _Echoes(
                offset,
                (tof * c).astype(float, copy=False),
                _flat_path_sigmas(snr_db, c, self.options),
                flat_amplitudes,
            )
            if objects is None:
                objects = _objects(setup, echoes, self.options, len(channels))
            if not objects and self.options.excuse_one_channel:
                objects = self._excusing_one(echoes, len(channels))
        return FrameObjects(frame_echoes.frame, frame_echoes.time_s, tuple(objects))

    def _excusing_one(self, echoes: _Echoes, n_channels: int) -> list[LocatedObject]:
        """Objects that need no echo on one channel (``excuse_one_channel``), trying each
        channel in turn; the answer whose best object scores highest. No objects where one channel
        fewer cannot fix a position (fewer than ``min_receivers`` or the dimension)."""
        dim = len(self.transmitter_m)
        if n_channels - 1 < max(self.options.min_receivers, dim):
            return []
        best: list[LocatedObject] = []
        for excused in range(n_channels):
            required = np.ones(n_channels, dtype=bool)
            required[excused] = False
            setup = _setup(
                self.transmitter_m, self.receivers_m, self.usable, None, None, required, self.options
            )
            found = _objects(setup, echoes, self.options, n_channels)
            if found and (not best or max(o.score for o in found) > max(o.score for o in best)):
                best = found
        return best

    def _compiled(
        self,
        offset: NDArray[np.int64],
        tof_s: NDArray[np.float64],
        speed_of_sound_m_s: float,
        snr_db: NDArray[np.float64],
        amplitudes: NDArray[np.float64],
    ) -> list[LocatedObject] | None:
        """:func:`_objects` of one frame's flat echoes in one compiled call that also makes the
        paths and sigmas from the times of flight (s) and SNRs (dB, float64) as
        :func:`_flat_path_sigmas` does; None when the kernel leaves the choice to the
        reference (tied weights: the caller runs :func:`_objects`)."""
        from echoloc.localise import _locate_kernels as kernels  # numba: imported (and compiled) on first use

        arguments = self.kernel_arguments(speed_of_sound_m_s)
        assert arguments is not None
        status, echo_use, position, covariance, chi2 = kernels.associate_frame(
            arguments, tof_s, snr_db, amplitudes, offset
        )
        return self.kernel_objects(
            status, echo_use, position, covariance, chi2, len(offset) - 1, stacklevel=4
        )

    def kernel_arguments(self, speed_of_sound_m_s: float) -> LocateKernelArguments | None:
        """What the compiled association (:func:`echoloc.localise._locate_kernels.associate_frame`)
        takes besides a frame's echoes. None when this locator has no compiled path (some
        receiver unusable, or no carrier): :meth:`__call__` then takes the reference."""
        setup = self._setup
        if setup is None or not _COMPILED or self._fixed_kernel_arguments is None:
            return None
        prior_variance, omega, tail = self._fixed_kernel_arguments
        return LocateKernelArguments(
            setup.geometry.kernel_arguments,
            float(speed_of_sound_m_s),
            prior_variance,
            omega,
            tail,
            _NODE_LIMIT,
            _MAX_SEED_ROWS,
            setup.origin,
        )

    def kernel_objects(
        self,
        status: int,
        echo_use: NDArray[np.int64],
        position: NDArray[np.float64],
        covariance: NDArray[np.float64],
        chi2: NDArray[np.float64],
        n_channels: int,
        *,
        stacklevel: int = 2,
    ) -> list[LocatedObject] | None:
        """The objects of the compiled association's output for a frame of ``n_channels``
        channels; None on tied weights, which it leaves to the reference (:func:`_objects`).
        More seed rows than it takes (status 1) skip the frame with a warning."""
        if status == 1:
            warnings.warn(
                f"frame skipped: more than {_MAX_SEED_ROWS} echo combinations to associate; "
                "raise the detection threshold",
                LocateWarning,
                stacklevel=stacklevel,
            )
            return []
        if status == 2:
            return None
        setup = self._setup
        assert setup is not None
        return _located(setup, echo_use, position, covariance, chi2, status == 0, n_channels)

    def _general(self, frame_echoes: FrameEchoes) -> FrameObjects:
        """The reference path: :func:`associate` on the frame's channels."""
        c = frame_echoes.speed_of_sound_m_s
        channels = frame_echoes.channels
        paths = [ch.tof_s * c for ch in channels]
        sigmas = [path_sigmas_m(ch.snr_db, c, self.options) for ch in channels]
        amplitudes = [ch.amplitude for ch in channels]
        objects = associate(
            self.transmitter_m, self.receivers_m, paths, sigmas, self.options, self.usable, amplitudes
        )
        return FrameObjects(frame_echoes.frame, frame_echoes.time_s, tuple(objects))


def combine_frames(
    frames: list[tuple[int, FrameEchoes]],
    transmitters_m: NDArray[np.float64],
    receivers_m: NDArray[np.float64],
    options: LocateOptions,
    usable: NDArray[np.bool_] | None = None,
) -> FrameObjects:
    """Objects from frames fired by different transmitters, located together.

    ``frames`` holds (transmitter index, echoes) of consecutive frames, one per
    transmitter. Every (transmitter, receiver) pair is a channel: with n_tx
    transmitters an object is seen on n_tx times as many ellipsoids, which tightens
    it and rejects more ghosts. Objects are those of the newest frame: its channels
    are required, the older frames' channels support an object where they agree
    with it (within the chi-square gate), so a reflector that moved or vanished
    since an older frame is neither lost nor duplicated. The result carries the
    newest frame's number and time.
    """
    n_rx = len(receivers_m)
    paths, sigmas, amplitudes = [], [], []
    tx_positions, rx_positions, tx_index, rx_index, use = [], [], [], [], []
    rx_usable = np.ones(n_rx, dtype=bool) if usable is None else np.asarray(usable, dtype=bool)
    for t, echoes in frames:
        c = echoes.speed_of_sound_m_s
        for r, ch in enumerate(echoes.channels):
            paths.append(ch.tof_s * c)
            sigmas.append(path_sigmas_m(ch.snr_db, c, options))
            amplitudes.append(ch.amplitude)
            tx_positions.append(transmitters_m[t])
            rx_positions.append(receivers_m[r])
            tx_index.append(t)
            rx_index.append(r)
            use.append(rx_usable[r])
    newest = max((e for _, e in frames), key=lambda e: e.frame)
    required = [e.frame == newest.frame for _, e in frames for _ in e.channels]
    objects = associate(
        np.array(tx_positions),
        np.array(rx_positions),
        paths,
        sigmas,
        options,
        np.array(use),
        amplitudes,
        transmitter_index=np.array(tx_index),
        receiver_index=np.array(rx_index),
        required=np.array(required),
    )
    return FrameObjects(newest.frame, newest.time_s, tuple(objects))
