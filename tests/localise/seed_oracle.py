"""The numpy statement of association's seed search: the compiled
``echoloc.localise._locate_kernels.seed_candidates`` (steps 1-2 of
``echoloc.localise.locate.associate``, docs/METHOD.md section 7), in 2-D or 3-D.

A test-only oracle: ``tests/localise/test_seed_candidates.py`` holds the compiled loop to
it. It is written from the statement, not from the loops, and solves the geometry its own
way: where the kernel intersects a line in (p, rho) with the cone ``rho = |p - T|`` in
closed form, the oracle walks the closed curve on which D - 1 of the seed's ellipsoids
meet and finds, by bracketing and bisection, where the last ellipsoid's *unsquared*
equation ``|p - T| + |p - R| = l`` changes sign along it; Newton's method on the D
unsquared equations then polishes each point. Positions are in metres throughout.

Rounding. The kernel and the oracle compute the same numbers by different operations,
so a decision whose margin is within rounding of its threshold (a point on the edge of a
beam, a gap equal to its gate, an ill-conditioned or nearly tangent crossing) may go
either way. The oracle decides in Kleene's three-valued logic: a comparison is *sure*
when its margin exceeds the point's tolerance (:func:`point_tolerance`), and a row whose
fate or content hangs on an unsure comparison is not a row but a *doubtful point*, where
the kernel may emit rows (with any echoes) or none. Random scenes make doubtful points
rare (a few in a thousand crossings); the tests count them.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np

OWN, SHARED, NONE = 0, 1, 2
"""How a row uses a channel (the kernel's codes): its own echo, an echo merged with
another object's (a shared peak), no echo."""

POINT_TOL_M = 1e-9
"""The tolerance of a well-conditioned crossing, m (see :func:`point_tolerance`)."""

WELL_CONDITIONED = 1e-4
"""Above this ratio ``det(J_s^T J_s) / prod(diag)`` a crossing is well conditioned (the
seed's ellipsoids cross at more than about half a degree)."""

CONDITIONING_LIMIT = 1e-12
"""The kernel keeps a crossing when ``det(J_s^T J_s) > 1e-12 prod(diag)`` (Hadamard's
bound; J_s the seed channels' Jacobian rows): the statement's test for a crossing whose
ellipsoids are not nearly tangent."""

SURE_CONDITIONING = 1e-8
"""Below this ratio a crossing is doubtful, whichever side of :data:`CONDITIONING_LIMIT`
it falls: its point is then uncertain by up to some 1e-7 m."""

TANGENT_TOL_M = 1e-4
"""A crossing where the last ellipsoid only grazes the curve (its residual's extremum
along the curve within this of zero, m) is doubtful: the kernel keeps a slightly missed
tangency as a tangent point (a negative discriminant down to 1e-6 of qb^2)."""

TANGENT_RADIUS_M = 1e-2
"""How far from the oracle's extremum a kernel's tangent point may lie, m: a tangency
missed by ``delta`` moves the touching point by about ``sqrt(delta * 1 m)``."""

DOUBT_RADIUS_M = 1e-5
"""How far from the oracle's point a kernel's point at any other doubtful crossing may
lie, m (measured: up to 7e-8 m at the conditioning limit)."""


def point_tolerance(ratio: np.ndarray) -> np.ndarray:
    """How far the kernel's point may lie from the oracle's, m, at crossings of conditioning
    ``ratio`` = ``det(J_s^T J_s) / prod(diag)``: ``1e-9 m * max(1, sqrt(1e-4 / ratio))``.

    The oracle's point is exact to a few ulps of its metres (Newton's method on the
    unsquared equations). The kernel's closed form squares the paths and takes a square
    root of a discriminant that vanishes with the angle between the ellipsoids, about
    ``sqrt(ratio)``: measured, the two differ by below 1e-12 m at well-conditioned
    crossings (ratio > 1e-4: every real reflector of the report's head) and by about
    ``2e-13 m / sqrt(ratio)`` on nearly tangent ones (2-D and 3-D, ratio 1e-4 to 1e-12).
    The tolerance keeps a factor of 50 over that; paths are a few metres, so 1e-9 m is
    3e-10 of a path. Every comparison of lengths (beams, window, gates) is sure beyond
    the same tolerance: its margin inherits the point's error (gains and variances add
    relative errors of ``1e-16 / ratio``, far below it).
    """
    with np.errstate(divide="ignore"):
        return POINT_TOL_M * np.maximum(1.0, np.sqrt(WELL_CONDITIONED / ratio))


_SAMPLES = 512  # points on each curve; its residual's extrema are refined, so none is missed
_GOLDEN_STEPS = 40  # an extremum's angle to 1e-10 rad, its value to far below TANGENT_TOL_M
_BISECTIONS = 40  # a root's angle to 1e-14 rad; Newton's method does the rest
_NEWTON_STEPS = 3
_EXTREMUM_SCAN_M = 1e-2  # sampled extrema this near zero are refined (sampling error ~1e-3 m)


@dataclass(frozen=True)
class SeedRows:
    """The rows of the seed search, in no particular order, and its doubtful points.

    ``echo`` (n, C): per channel the echo's index within the channel, -1 for none;
    ``use`` (n, C): :data:`OWN`, :data:`SHARED` or :data:`NONE`; ``points`` (n, D), m:
    the exact crossing of the seed's ellipsoids, and ``tolerance`` (n,), m, how far the
    kernel's may lie from it (:func:`point_tolerance`). ``doubtful`` (k, D), m, are
    crossings whose fate or row rounding decides, ``doubt_radius`` (k,), m, how far the
    kernel's point may lie from each; ``n_combinations`` counts the echo combinations
    solved, ``n_crossings`` the crossings found (and grazings), before the checks.
    """

    echo: np.ndarray
    use: np.ndarray
    points: np.ndarray
    tolerance: np.ndarray
    doubtful: np.ndarray
    doubt_radius: np.ndarray
    n_combinations: int
    n_crossings: int


@dataclass(frozen=True)
class _Maybe:
    """A boolean array in Kleene's three-valued logic: ``value`` where ``sure``, unknown elsewhere."""

    value: np.ndarray
    sure: np.ndarray

    def __and__(self, other: _Maybe) -> _Maybe:
        known_false = (self.sure & ~self.value) | (other.sure & ~other.value)
        return _Maybe(self.value & other.value, (self.sure & other.sure) | known_false)

    def __or__(self, other: _Maybe) -> _Maybe:
        known_true = (self.sure & self.value) | (other.sure & other.value)
        return _Maybe(self.value | other.value, (self.sure & other.sure) | known_true)

    def __invert__(self) -> _Maybe:
        return _Maybe(~self.value, self.sure)


def _constant(value: bool, n: int) -> _Maybe:
    return _Maybe(np.full(n, value), np.ones(n, dtype=bool))


def _at_least(margin: np.ndarray, tol: np.ndarray | float = POINT_TOL_M) -> _Maybe:
    """``margin >= 0`` (m), sure when the margin is beyond ``tol`` (m; an infinite bound is sure)."""
    with np.errstate(invalid="ignore"):
        return _Maybe(margin >= 0, ~(np.abs(margin) <= tol))


@dataclass(frozen=True)
class Crossings:
    """Points where D ellipsoids of one transmitter meet: ``combo`` (m,) the row of the
    paths each solves, ``points`` (m, D), m; ``tangent`` marks the extrema of a grazing
    last ellipsoid (doubtful, not crossings)."""

    combo: np.ndarray
    points: np.ndarray
    tangent: np.ndarray


@dataclass(frozen=True)
class _Curve:
    """The closed curves where the ellipsoids of D - 1 receivers of a transmitter at the
    origin meet, one per row of their paths (see :func:`_curve`): ``p(psi) = q0 + rho q1
    + h normal`` with ``rho = mid - half cos psi`` and ``h = width half sin psi``."""

    q0: np.ndarray  # (n, D), m
    q1: np.ndarray  # (n, D)
    mid: np.ndarray  # (n,), m
    half: np.ndarray  # (n,), m
    width: np.ndarray  # (n,)
    normal: np.ndarray  # (D,)
    exists: np.ndarray  # (n,) bool

    def at(self, rows: np.ndarray, psi: np.ndarray) -> np.ndarray:
        """Points (..., D), m, of the curves ``rows`` (k,) at angles ``psi`` (k,) or (k, K), rad."""
        expand = (slice(None),) + (None,) * (psi.ndim - 1)
        rho = self.mid[rows][expand] - self.half[rows][expand] * np.cos(psi)
        h = (self.width * self.half)[rows][expand] * np.sin(psi)
        return self.q0[rows][expand] + rho[..., None] * self.q1[rows][expand] + h[..., None] * self.normal


def _curve(rel: np.ndarray, paths: np.ndarray) -> _Curve:
    """The closed curves where the ellipsoids of D - 1 receivers meet.

    ``rel`` (D - 1, D): the receivers relative to the transmitter, m; ``paths`` (n, D - 1),
    m. A point p of the curve has range ``rho = |p|`` and ``|p - R_k| = l_k - rho``;
    subtracting the squares gives ``R_k . p = (|R_k|^2 - l_k^2)/2 + l_k rho``, so p's
    component in the receivers' span is affine in rho, ``q0 + rho q1``, and its distance h
    from that span obeys ``h^2 = rho^2 - |q0 + rho q1|^2 = a rho^2 + b rho + c``, which is
    non-negative between its roots ``mid -+ half`` (a < 0 when every path exceeds its
    receiver's distance). ``rho = mid - half cos psi``, ``h = sqrt(-a) half sin psi``
    go round the curve once, smoothly (in 2-D, an ellipse's parametrisation from its focus).
    """
    dim = rel.shape[1]
    normal = np.cross(rel[0], rel[1]) if dim == 3 else np.array([-rel[0, 1], rel[0, 0]])
    normal = normal / np.linalg.norm(normal)
    # Minimum-norm solution of R w = y: w = R^T (R R^T)^-1 y.
    project = rel.T @ np.linalg.inv(rel @ rel.T)  # (D, D - 1)
    q0 = (0.5 * (np.sum(rel**2, axis=1) - paths**2)) @ project.T  # (n, D)
    q1 = paths @ project.T
    a = 1.0 - np.sum(q1**2, axis=1)
    b = -2.0 * np.sum(q0 * q1, axis=1)
    c = -np.sum(q0**2, axis=1)
    disc = b**2 - 4.0 * a * c
    exists = (a < 0) & (disc > 0)
    safe_a = np.where(exists, a, -1.0)
    half = np.sqrt(np.where(exists, disc, 0.0)) / (2.0 * -safe_a)
    return _Curve(q0, q1, -b / (2.0 * safe_a), half, np.sqrt(-safe_a), normal, exists)


def _residual(points: np.ndarray, receiver: np.ndarray, path: np.ndarray) -> np.ndarray:
    """``|p| + |p - R| - l`` (m): how far outside the ellipsoid of (T = 0, R, l) each point lies."""
    return np.sqrt(np.sum(points**2, axis=-1)) + np.sqrt(np.sum((points - receiver) ** 2, axis=-1)) - path


def ellipsoid_crossings(transmitter: np.ndarray, receivers: np.ndarray, paths: np.ndarray) -> Crossings:
    """Every point p with ``|p - T| + |p - R_k| = l_k`` for the D receivers ``receivers``
    (D, D), m, of the transmitter ``transmitter`` (D,), for each row of ``paths`` (n, D), m.

    The D - 1 receivers spanning the widest triangle with T give a closed curve
    (:func:`_curve`); along it, the last receiver's residual (:func:`_residual`) is
    sampled, its sign changes are bracketed, its extrema near zero refined (a pair of
    close roots may hide between two samples; a grazing extremum is a near-tangency), the
    brackets bisected, and the roots polished by Newton's method on the D unsquared
    equations. Points whose residuals are not then zero are dropped: the squared
    equations also hold where ``|p - R_k| = rho - l_k``.
    """
    rel = receivers - transmitter
    dim = rel.shape[1]
    if dim == 3:
        pairs = list(combinations(range(3), 2))
        spans = [np.linalg.norm(np.cross(rel[i], rel[j])) for i, j in pairs]
        curve_rows = list(pairs[int(np.argmax(spans))])
    else:
        curve_rows = [int(np.argmax(np.linalg.norm(rel, axis=1)))]
    last = next(k for k in range(dim) if k not in curve_rows)
    curve = _curve(rel[curve_rows], paths[:, curve_rows])

    def along(rows: np.ndarray, psi: np.ndarray) -> np.ndarray:
        """The last ellipsoid's residual (m) on the curves ``rows`` at ``psi`` (rad)."""
        lengths = paths[rows, last] if psi.ndim == 1 else paths[rows, last, None]
        return _residual(curve.at(rows, psi), rel[last], lengths)

    step = 2 * np.pi / _SAMPLES
    every = np.flatnonzero(curve.exists)
    values = along(every, np.broadcast_to(np.arange(_SAMPLES) * step, (len(every), _SAMPLES)))
    positive = values > 0
    # Sign changes between neighbouring samples (round the curve).
    index, j = np.nonzero(positive != np.roll(positive, -1, axis=1))
    lows, highs, owners = [j * step], [(j + 1) * step], [every[index]]
    # Extrema of the residual nearer zero than the sampling can tell: refined by golden
    # section on their two neighbouring intervals.
    toward_zero = np.where(positive, 1.0, -1.0)
    extremum = (
        (toward_zero * values <= toward_zero * np.roll(values, 1, axis=1))
        & (toward_zero * values <= toward_zero * np.roll(values, -1, axis=1))
        & (positive == np.roll(positive, 1, axis=1))
        & (positive == np.roll(positive, -1, axis=1))
        & (np.abs(values) < _EXTREMUM_SCAN_M)
    )
    index, e_j = np.nonzero(extremum)
    e_row, sign = every[index], toward_zero[index, e_j]
    lo, hi = (e_j - 1) * step, (e_j + 1) * step
    golden = (np.sqrt(5.0) - 1) / 2
    for _ in range(_GOLDEN_STEPS):
        x1, x2 = hi - golden * (hi - lo), lo + golden * (hi - lo)
        smaller = sign * along(e_row, x1) < sign * along(e_row, x2)
        hi, lo = np.where(smaller, x2, hi), np.where(smaller, lo, x1)
    e_psi = 0.5 * (lo + hi)
    e_value = along(e_row, e_psi)
    splits = sign * e_value <= 0  # the extremum crosses zero: a root either side of it
    lows += [(e_j[splits] - 1) * step, e_psi[splits]]
    highs += [e_psi[splits], (e_j[splits] + 1) * step]
    owners += [e_row[splits], e_row[splits]]
    grazing = np.abs(e_value) < TANGENT_TOL_M
    lo, hi, rows = np.concatenate(lows), np.concatenate(highs), np.concatenate(owners)
    low_positive = along(rows, lo) > 0
    for _ in range(_BISECTIONS):
        middle = 0.5 * (lo + hi)
        same = (along(rows, middle) > 0) == low_positive
        lo, hi = np.where(same, middle, lo), np.where(same, hi, middle)
    points = curve.at(rows, 0.5 * (lo + hi))
    for _ in range(_NEWTON_STEPS):
        offset = points[:, None, :] - rel[None]  # (m, D, D): p - R_k
        to_t = np.linalg.norm(points, axis=1)
        to_r = np.linalg.norm(offset, axis=2)
        residual = to_t[:, None] + to_r - paths[rows]
        jac = points[:, None, :] / to_t[:, None, None] + offset / to_r[..., None]
        solvable = np.abs(np.linalg.det(jac)) > 1e-12
        safe = np.where(solvable[:, None, None], jac, np.eye(dim))
        points = points - np.where(solvable[:, None], np.linalg.solve(safe, residual[..., None])[..., 0], 0.0)
    offset = points[:, None, :] - rel[None]
    residual = np.linalg.norm(points, axis=1)[:, None] + np.linalg.norm(offset, axis=2) - paths[rows]
    real = np.all(np.abs(residual) <= 1e-9 * np.maximum(1.0, paths[rows].max(axis=1))[:, None], axis=1)
    return Crossings(
        np.concatenate([rows[real], e_row[grazing]]),
        np.concatenate([points[real], curve.at(e_row[grazing], e_psi[grazing])]) + transmitter,
        np.concatenate([np.zeros(int(real.sum()), dtype=bool), np.ones(int(grazing.sum()), dtype=bool)]),
    )


def _in_beam(
    points: np.ndarray, origin: np.ndarray, axis: np.ndarray, cos_fov: float, tol: np.ndarray
) -> _Maybe:
    """Whether points (m, D), m, lie in the cone of half-angle ``acos(cos_fov)`` about ``axis``
    from ``origin``: ``(p - o) . axis >= cos_fov |p - o|``, sure beyond ``tol`` (m,), m."""
    offset = points - origin
    return _at_least(offset @ axis - cos_fov * np.linalg.norm(offset, axis=1), tol)


def seed_candidates_reference(
    transmitters: np.ndarray,
    receivers: np.ndarray,
    transmitter_axes: np.ndarray,
    receiver_axes: np.ndarray,
    boresight: np.ndarray,
    required: np.ndarray,
    paths: np.ndarray,
    sigmas: np.ndarray,
    offset: np.ndarray,
    seeds: np.ndarray,
    window_low: float,
    window_high: float,
    cos_fov: float,
    k_gate: float,
    merge_reach: float,
    min_own: int,
) -> SeedRows:
    """The seed search's rows (the kernel's arguments, without the sorted copies and the capacity).

    Channels c = 0..C-1 have a transmitter and a receiver (``transmitters``,
    ``receivers`` (C, D), m) with beam axes (C, D) of half-angle ``acos(cos_fov)``;
    channel c's echoes are ``paths[offset[c]:offset[c+1]]`` (m) with standard deviations
    ``sigmas`` (m). For every seed (D channels of one transmitter, a row of ``seeds``):

    1. Every combination of one echo per seed channel with ``l_k >= |R_k - T_k| - 4 s_k``
       and ``|l_k - l_q| <= |R_k - R_q| + |T_k - T_q| + 4 sqrt(s_k^2 + s_q^2)`` (the
       triangle inequality, with slack) is solved exactly (:func:`ellipsoid_crossings`);
       an exact crossing meets the inequality without slack, so the admission saves work
       but decides no row.
       A crossing counts if it lies ahead (``(p - T_0) . boresight > 0``), inside the
       transmitter's and the receiver's beam of every seed channel, and the seed's
       ellipsoids are not nearly tangent there (``det(J_s^T J_s) > 1e-12 prod diag``,
       J_s the rows ``(p - T)/|p - T| + (p - R)/|p - R|`` of the seed channels).
    2. Every other channel that sees the point (inside both its beams, its predicted path
       ``|p - T_c| + |p - R_c|`` inside ``[window_low, window_high]``) looks at its echo
       nearest that path. The seed's paths give the point a covariance
       ``J_s^-1 diag(s^2) J_s^-T``, hence the prediction a variance ``var = J_c cov J_c^T``;
       with ``reach = k_gate sqrt(var + s_echo^2)`` the echo is the row's own when its gap
       is at most ``reach``, else shared when the channel is required and the gap is at
       most ``reach + merge_reach``. A required channel that sees the point and has
       neither rejects it; a channel that cannot see it stays empty.
    3. A point with at least ``min_own`` own echoes (the seed's count) is a row: the echo
       per channel (seed channels: the combination's), its use, the point.

    Rows repeat an object once per seed that finds it, as the kernel's do.
    """
    n_ch, dim = receivers.shape
    echo_rows: list[np.ndarray] = [np.zeros((0, n_ch), dtype=np.int64)]
    use_rows: list[np.ndarray] = [np.zeros((0, n_ch), dtype=np.int8)]
    point_rows: list[np.ndarray] = [np.zeros((0, dim))]
    tolerances: list[np.ndarray] = [np.zeros(0)]
    doubt_points: list[np.ndarray] = [np.zeros((0, dim))]
    doubt_radii: list[np.ndarray] = [np.zeros(0)]
    n_combinations = n_crossings = 0
    direct = np.linalg.norm(receivers - transmitters, axis=1)
    for seed in np.asarray(seeds).tolist():
        t = transmitters[seed[0]]
        if not np.all(transmitters[seed] == t):
            raise ValueError(f"seed {seed}: channels of several transmitters")
        counts = [offset[c + 1] - offset[c] for c in seed]
        if min(counts) == 0:
            continue
        choice = np.stack(np.meshgrid(*[np.arange(k) for k in counts], indexing="ij"), -1).reshape(-1, dim)
        flat = offset[seed] + choice
        lengths, s = paths[flat], sigmas[flat]
        # Step 1: the triangle inequality (with its slack) admits the combination.
        admit = _constant(True, len(lengths))
        for k, c in enumerate(seed):
            admit = admit & _at_least(lengths[:, k] - (direct[c] - 4 * s[:, k]))
        for k, q in combinations(range(dim), 2):
            a, b = seed[k], seed[q]
            span = np.linalg.norm(receivers[a] - receivers[b])
            span += np.linalg.norm(transmitters[a] - transmitters[b])
            slack = 4 * np.hypot(s[:, k], s[:, q])
            admit = admit & _at_least(span + slack - np.abs(lengths[:, k] - lengths[:, q]))
        tried = admit.value | ~admit.sure
        n_combinations += int(tried.sum())
        crossings = ellipsoid_crossings(t, receivers[seed], lengths[tried])
        combo = np.flatnonzero(tried)[crossings.combo]
        p = crossings.points
        m = len(p)
        n_crossings += m
        if m == 0:
            continue
        to_t = p[:, None, :] - transmitters[None]  # (m, C, D)
        to_r = p[:, None, :] - receivers[None]
        predicted = np.linalg.norm(to_t, axis=2) + np.linalg.norm(to_r, axis=2)  # (m, C)
        jac = to_t / np.linalg.norm(to_t, axis=2)[..., None] + to_r / np.linalg.norm(to_r, axis=2)[..., None]
        seed_jac = jac[:, seed]  # (m, D, D)
        normal = np.einsum("mki,mkj->mij", seed_jac, seed_jac)
        diagonal = np.einsum("mii->mi", normal)
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = np.linalg.det(normal) / np.prod(diagonal, axis=1)
        ratio = np.where(np.all(diagonal > 0, axis=1) & np.isfinite(ratio), np.maximum(ratio, 0.0), 0.0)
        tol = point_tolerance(ratio)
        keep = _Maybe(admit.value[combo], admit.sure[combo])
        keep = keep & _at_least((p - transmitters[0]) @ boresight, tol)
        for c in seed:
            keep = keep & _in_beam(p, transmitters[c], transmitter_axes[c], cos_fov, tol)
            keep = keep & _in_beam(p, receivers[c], receiver_axes[c], cos_fov, tol)
        keep = keep & _Maybe(ratio > CONDITIONING_LIMIT, ratio > SURE_CONDITIONING)
        # The seed's paths' covariance, carried to the point: J_s^-1 diag(s^2) J_s^-T.
        safe_jac = np.where((ratio > 0)[:, None, None], seed_jac, np.eye(dim))
        spread = np.linalg.solve(safe_jac, np.eye(dim)[None] * s[combo][:, None, :])  # J_s^-1 diag(s)
        echo = np.full((m, n_ch), -1, dtype=np.int64)
        use = np.full((m, n_ch), NONE, dtype=np.int8)
        use_sure = np.ones(m, dtype=bool)
        own_low = np.full(m, dim)  # own echoes for sure, and possibly
        own_high = np.full(m, dim)
        for k, c in enumerate(seed):
            echo[:, c] = choice[combo, k]
            use[:, c] = OWN
        for c in range(n_ch):
            if c in seed:
                continue
            sees = _in_beam(p, transmitters[c], transmitter_axes[c], cos_fov, tol)
            sees = sees & _in_beam(p, receivers[c], receiver_axes[c], cos_fov, tol)
            sees = sees & _at_least(predicted[:, c] - window_low, tol)
            sees = sees & _at_least(window_high - predicted[:, c], tol)
            lo, hi = offset[c], offset[c + 1]
            if hi == lo:
                own, shared = _constant(False, m), _constant(False, m)
                nearest = np.full(m, -1)
            else:
                gaps = np.abs(paths[lo:hi][None, :] - predicted[:, c, None])  # (m, echoes)
                nearest = np.argmin(gaps, axis=1)
                gap = gaps[np.arange(m), nearest]
                runner_up = np.sort(gaps, axis=1)[:, 1] if hi - lo > 1 else np.full(m, np.inf)
                variance = np.sum((jac[:, c, None, :] @ spread)[:, 0] ** 2, axis=1)
                reach = k_gate * np.sqrt(variance + sigmas[lo + nearest] ** 2)
                # A near tie between two echoes leaves the gated echo, hence the outcome, unsure.
                tie_sure = runner_up - gap > tol
                own = _at_least(reach - gap, tol)
                own = _Maybe(own.value, own.sure & tie_sure)
                shared = _constant(bool(required[c]), m) & _at_least(reach + merge_reach - gap, tol)
                shared = _Maybe(shared.value, shared.sure & tie_sure)
            if required[c]:
                keep = keep & (~sees | own | shared)
            # The channel's entry: sure when every comparison it rests on is sure.
            entry_sure = sees.sure & (~sees.value | (own.sure & (own.value | shared.sure)))
            as_own = sees.value & own.value
            as_shared = sees.value & ~own.value & shared.value
            echo[:, c] = np.where(as_own | as_shared, nearest, -1)
            use[:, c] = np.where(as_own, OWN, np.where(as_shared, SHARED, NONE))
            use_sure &= entry_sure
            own_low += as_own & entry_sure
            own_high += (sees.value | ~sees.sure) & (own.value | ~own.sure)
        keep = keep & _Maybe(own_low >= min_own, (own_low >= min_own) | (own_high < min_own))
        # Where the crossing itself is uncertain (grazing, or ill-conditioned), the kernel's
        # point may lie further off than any margin: nothing about it is sure.
        reliable = ~crossings.tangent & (ratio > SURE_CONDITIONING)
        row = reliable & keep.sure & keep.value & use_sure
        doubtful = ~reliable | ~(keep.sure & (~keep.value | use_sure))
        echo_rows.append(echo[row])
        use_rows.append(use[row])
        point_rows.append(p[row])
        tolerances.append(tol[row])
        doubt_points.append(p[doubtful])
        doubt_radii.append(np.where(crossings.tangent[doubtful], TANGENT_RADIUS_M, DOUBT_RADIUS_M))
    return SeedRows(
        np.concatenate(echo_rows),
        np.concatenate(use_rows),
        np.concatenate(point_rows),
        np.concatenate(tolerances),
        np.concatenate(doubt_points),
        np.concatenate(doubt_radii),
        n_combinations,
        n_crossings,
    )
