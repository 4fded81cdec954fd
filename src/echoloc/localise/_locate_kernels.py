"""Compiled inner loops of :mod:`echoloc.localise.locate` (numba): the whole association.

Association touches hundreds of tiny systems per frame (3x3 solves, one per echo
combination) and then packs a few dozen candidates into objects. Numpy calls and
Python sets each cost microseconds of overhead, which dominated a frame even with only
the seeds and Gauss-Newton compiled, so :func:`associate` runs every step (seeds,
refinement, choice) in one call. The formulas are those documented in
:mod:`echoloc.localise.locate`, whose numpy and Python references
(``locate._COMPILED = False``; they share the seed search and Gauss-Newton kernels
with the compiled path) the tests hold these loops to; this module holds only the loops,
with the same arithmetic in the same order.
Every function works in D = 2 or 3 dimensions. Small helpers are inlined
(``inline="always"``): called, each passed its array views through reference
counting, which cost a sizeable share of the seed loop. Inlined, a helper with loops still
counts references to its array arguments and to the views it takes (atomic
operations, again a sizeable share of the seed loop): the larger helpers that allocate
nothing (:func:`_exact_work`, the Gauss-Newton row and fit, the prediction
variance's solve) are compiled without the runtime (:func:`_without_runtime`) and
called, at no count at all; hot loops read rows by index rather than through views.
In 3-D the hottest of them (the exact seed solve, the seed's conditioning and
prediction gain, the Gauss-Newton row) run on local scalars instead of scratch rows
(:func:`_solve3`, :func:`_det3`: the same operations in the same order, so the same
bits), and the distance to a transmitter every channel shares is computed once a
point, which makes the call faster than with scratch rows.

``cache=True`` keeps the machine code in ``__pycache__``: the first call in a fresh
environment compiles (about half a minute), later processes load it (about 1 s). The
entry points Python calls once a frame release the GIL (see :mod:`echoloc.tof._echoes_kernels`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar, cast

import numpy as np
from numpy.typing import NDArray

from echoloc._jit import njit
from echoloc._linear_kernels import solve_in_place

if TYPE_CHECKING:
    from echoloc.localise.locate import AssociationTail, KernelGeometry, LocateKernelArguments

OWN, SHARED, NONE = 0, 1, 2

_Function = TypeVar("_Function", bound=Callable[..., Any])


def _without_runtime(function: _Function) -> _Function:
    """``njit(cache=True)`` without numba's runtime (``_nrt=False``, as numba's own string
    helpers): no reference counts on arrays and views; allocating fails to compile."""
    options: dict[str, Any] = {"cache": True, "_nrt": False}
    return cast(_Function, njit(**options)(function))


@njit(cache=True, inline="always")
def _solve3(
    a00: float,
    a01: float,
    a02: float,
    a10: float,
    a11: float,
    a12: float,
    a20: float,
    a21: float,
    a22: float,
    r0: float,
    r1: float,
    r2: float,
) -> Any:  # pragma: no cover - compiled
    """:func:`~echoloc._linear_kernels.solve_in_place` for a 3x3 system in scalars (registers,
    not array rows): the same pivots and operations in the same order, so the same bits;
    (solved, x0, x1, x2)."""
    if abs(a10) > abs(a00):
        if abs(a20) > abs(a10):
            a00, a01, a02, a20, a21, a22 = a20, a21, a22, a00, a01, a02
            r0, r2 = r2, r0
        else:
            a00, a01, a02, a10, a11, a12 = a10, a11, a12, a00, a01, a02
            r0, r1 = r1, r0
    elif abs(a20) > abs(a00):
        a00, a01, a02, a20, a21, a22 = a20, a21, a22, a00, a01, a02
        r0, r2 = r2, r0
    if a00 == 0.0 or not np.isfinite(a00):
        return False, 0.0, 0.0, 0.0
    f = a10 / a00
    a11 -= f * a01
    a12 -= f * a02
    r1 -= f * r0
    f = a20 / a00
    a21 -= f * a01
    a22 -= f * a02
    r2 -= f * r0
    if abs(a21) > abs(a11):
        a11, a12, a21, a22 = a21, a22, a11, a12
        r1, r2 = r2, r1
    if a11 == 0.0 or not np.isfinite(a11):
        return False, 0.0, 0.0, 0.0
    f = a21 / a11
    a22 -= f * a12
    r2 -= f * r1
    if a22 == 0.0 or not np.isfinite(a22):
        return False, 0.0, 0.0, 0.0
    x2 = r2 / a22
    x1 = (r1 - a12 * x2) / a11
    s = r0
    s -= a01 * x1
    s -= a02 * x2
    return True, s / a00, x1, x2


@_without_runtime
def _solve(
    m: NDArray[np.float64], v: NDArray[np.float64], x: NDArray[np.float64]
) -> bool:  # pragma: no cover - compiled
    """:func:`~echoloc._linear_kernels.solve_in_place`, called: inlined in the seed loop it
    counted references to its three arrays (atomic operations), which cost more than the call."""
    return solve_in_place(m, v, x)


@njit(cache=True, inline="always")
def _copy(source: NDArray[np.float64], target: NDArray[np.float64]) -> None:  # pragma: no cover - compiled
    """``target[:, :] = source`` in loops: the slice assignment checks the two views for
    overlap, which needs the runtime (unavailable in the ``_nrt=False`` helpers)."""
    for i in range(source.shape[0]):
        for j in range(source.shape[1]):
            target[i, j] = source[i, j]


@njit(cache=True, inline="always")
def _det(a: NDArray[np.float64]) -> float:  # pragma: no cover - compiled
    """Determinant of a 1x1, 2x2 or 3x3 matrix."""
    n = a.shape[0]
    if n == 1:
        return float(a[0, 0])
    if n == 2:
        return float(a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0])
    return float(
        a[0, 0] * (a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1])
        - a[0, 1] * (a[1, 0] * a[2, 2] - a[1, 2] * a[2, 0])
        + a[0, 2] * (a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0])
    )


@njit(cache=True, inline="always")
def _det3(
    a00: float, a01: float, a02: float, a10: float, a11: float, a12: float, a20: float, a21: float, a22: float
) -> float:  # pragma: no cover - compiled
    """:func:`_det` of the 3x3 matrix of these entries (row by row), the same expansion."""
    return a00 * (a11 * a22 - a12 * a21) - a01 * (a10 * a22 - a12 * a20) + a02 * (a10 * a21 - a11 * a20)


@njit(cache=True, inline="always")
def _well_conditioned(normal: NDArray[np.float64]) -> bool:  # pragma: no cover - compiled
    """det > 1e-12 x product of the diagonal (Hadamard's bound): not near-singular."""
    bound = 1.0
    for i in range(normal.shape[0]):
        if not normal[i, i] > 0.0:
            return False
        bound *= normal[i, i]
    return bool(np.isfinite(bound) and _det(normal) > 1e-12 * bound)


@njit(cache=True)
def _exact(
    t: NDArray[np.float64],  # (D,), m
    receivers: NDArray[np.float64],  # (D, D), m
    paths: NDArray[np.float64],  # (D,), m
    points: NDArray[np.float64],  # (2, D) out
) -> int:  # pragma: no cover - compiled
    """Points meeting D paths exactly (locate.exact_solutions for one row); returns how many (0-2)."""
    d = paths.shape[0]
    work = np.empty((5 * d + 5, d + 1))
    _exact_prepare(t, receivers, work)
    return _exact_work(t, paths, points, work)


@_without_runtime
def _exact_prepare(
    t: NDArray[np.float64], receivers: NDArray[np.float64], work: NDArray[np.float64]
) -> None:  # pragma: no cover - compiled
    """What :func:`_exact_work` computes from ``t`` and the D ``receivers`` alone, into ``work``
    (5 D + 5, D + 1), once for all the combinations of their paths: the receivers' columns
    of M, their squared distances from ``t``, the last component of the null vector and
    the path-free part of each sum of M M^T (the same sums, from the same start)."""
    d = receivers.shape[0]
    m = work[:d, :]
    v = work[d + 1, :]
    minor = work[d + 2 : 2 * d + 2, :d]
    norm2 = work[4 * d + 4, :d]
    partial_gram = work[4 * d + 5 : 5 * d + 5, :d]
    for i in range(d):
        total = 0.0
        for j in range(d):
            r = receivers[i, j] - t[j]
            m[i, j] = 2.0 * r
            total += r * r
        norm2[i] = total
    for i in range(d):
        for j in range(d):
            minor[i, j] = m[i, j]
    v[d] = (1.0 if d % 2 == 0 else -1.0) * _det(minor)
    for i in range(d):
        for k in range(d):
            s = 0.0
            for j in range(d):
                s += m[i, j] * m[k, j]
            partial_gram[i, k] = s


@_without_runtime
def _exact_work(
    t: NDArray[np.float64], paths: NDArray[np.float64], points: NDArray[np.float64], work: NDArray[np.float64]
) -> int:  # pragma: no cover - compiled
    """:func:`_exact` in the scratch rows ``work`` (5 D + 5, D + 1) that :func:`_exact_prepare`
    filled for ``t`` and the receivers: no allocation per combination of paths."""
    if paths.shape[0] == 3:
        return _exact_work_3d(t, paths, points, work)
    return _exact_work_any(t, paths, points, work)


@_without_runtime
def _exact_work_3d(
    t: NDArray[np.float64], paths: NDArray[np.float64], points: NDArray[np.float64], work: NDArray[np.float64]
) -> int:  # pragma: no cover - compiled
    """:func:`_exact_work_any` for D = 3 in scalars (registers, not the scratch rows): the same
    operations in the same order, so the same bits."""
    d = paths.shape[0]
    # The prepared rows (see _exact_prepare): M's receiver columns, |R_i - T|^2, v_D, M M^T.
    m00, m01, m02 = work[0, 0], work[0, 1], work[0, 2]
    m10, m11, m12 = work[1, 0], work[1, 1], work[1, 2]
    m20, m21, m22 = work[2, 0], work[2, 1], work[2, 2]
    v3 = work[d + 1, d]
    n0, n1, n2 = work[4 * d + 4, 0], work[4 * d + 4, 1], work[4 * d + 4, 2]
    l0, l1, l2 = paths[0], paths[1], paths[2]
    m03 = -2.0 * l0
    m13 = -2.0 * l1
    m23 = -2.0 * l2
    b0 = n0 - l0 * l0
    b1 = n1 - l1 * l1
    b2 = n2 - l2 * l2
    # Null vector: v_j = (-1)^j det(M without column j), each det as _det expands it.
    v0 = 1.0 * _det3(m01, m02, m03, m11, m12, m13, m21, m22, m23)
    v1 = -1.0 * _det3(m00, m02, m03, m10, m12, m13, m20, m22, m23)
    v2 = 1.0 * _det3(m00, m01, m03, m10, m11, m13, m20, m21, m23)
    pg = 4 * d + 5
    g00 = work[pg, 0] + m03 * m03
    g01 = work[pg, 1] + m03 * m13
    g02 = work[pg, 2] + m03 * m23
    g10 = work[pg + 1, 0] + m13 * m03
    g11 = work[pg + 1, 1] + m13 * m13
    g12 = work[pg + 1, 2] + m13 * m23
    g20 = work[pg + 2, 0] + m23 * m03
    g21 = work[pg + 2, 1] + m23 * m13
    g22 = work[pg + 2, 2] + m23 * m23
    trace = 0.0
    trace += g00
    trace += g11
    trace += g22
    if not abs(_det3(g00, g01, g02, g10, g11, g12, g20, g21, g22)) > 1e-18 * max(trace, 1e-30) ** d:
        return 0
    # y = (M M^T)^-1 b, as solve_in_place solves it.
    solved, y0, y1, y2 = _solve3(g00, g01, g02, g10, g11, g12, g20, g21, g22, b0, b1, b2)
    if not solved:
        return 0
    u0 = 0.0 + m00 * y0 + m10 * y1 + m20 * y2
    u1 = 0.0 + m01 * y0 + m11 * y1 + m21 * y2
    u2 = 0.0 + m02 * y0 + m12 * y1 + m22 * y2
    u3 = 0.0 + m03 * y0 + m13 * y1 + m23 * y2
    qa = -v3 * v3 + v0 * v0 + v1 * v1 + v2 * v2
    qb = 2.0 * (-u3 * v3 + u0 * v0 + u1 * v1 + u2 * v2)
    qc = -u3 * u3 + u0 * u0 + u1 * u1 + u2 * u2
    disc = qb * qb - 4.0 * qa * qc
    if disc < 0.0:
        if abs(disc) > 1e-6 * qb * qb:
            return 0
        disc = 0.0
    root = np.sqrt(disc)
    safe_a = qa if abs(qa) > 1e-300 else 1e-300
    longest = max(max(max(0.0, l0), l1), l2)
    slack = 1e-9 + 1e-6 * longest
    found = 0
    for sign in (1.0, -1.0):
        s = (-qb + sign * root) / (2.0 * safe_a)
        rho = u3 + s * v3
        if not (rho >= -slack and l0 - rho >= -slack and l1 - rho >= -slack and l2 - rho >= -slack):
            continue
        x = u0 + s * v0 + t[0]
        y = u1 + s * v1 + t[1]
        z = u2 + s * v2 + t[2]
        if np.isfinite(x) and np.isfinite(y) and np.isfinite(z):
            points[found, 0] = x
            points[found, 1] = y
            points[found, 2] = z
            found += 1
    return found


@_without_runtime
def _exact_work_any(
    t: NDArray[np.float64], paths: NDArray[np.float64], points: NDArray[np.float64], work: NDArray[np.float64]
) -> int:  # pragma: no cover - compiled
    """:func:`_exact_work` in any dimension, through the scratch rows."""
    d: int = paths.shape[0]  # typed: an index of NDArray's Any shape types its items as arrays
    m = work[:d, :]
    b = work[d, :d]
    v = work[d + 1, :]
    minor = work[d + 2 : 2 * d + 2, :d]
    gram = work[2 * d + 2 : 3 * d + 2, :d]
    y = work[3 * d + 2, :d]
    u0 = work[3 * d + 3, :]
    scratch = work[3 * d + 4 : 4 * d + 4, :d]
    norm2 = work[4 * d + 4, :d]
    partial_gram = work[4 * d + 5 : 5 * d + 5, :d]
    for i in range(d):
        m[i, d] = -2.0 * paths[i]
        b[i] = norm2[i] - paths[i] * paths[i]
    # Null vector: v_j = (-1)^j det(M without column j) (v_D, without the paths, is prepared).
    for j in range(d):
        for i in range(d):
            k = 0
            for col in range(d + 1):
                if col != j:
                    minor[i, k] = m[i, col]
                    k += 1
        v[j] = (1.0 if j % 2 == 0 else -1.0) * _det(minor)
    # Particular solution u0 = M^T (M M^T)^-1 b.
    for i in range(d):
        for k in range(d):
            gram[i, k] = partial_gram[i, k] + m[i, d] * m[k, d]
    trace = 0.0
    for i in range(d):
        trace += gram[i, i]
    if not abs(_det(gram)) > 1e-18 * max(trace, 1e-30) ** d:
        return 0
    rhs = minor[0]  # the minors are done with: one row holds a copy of b
    for i in range(d):
        rhs[i] = b[i]
        for k in range(d):
            scratch[i, k] = gram[i, k]
    if not solve_in_place(scratch, rhs, y):
        return 0
    for j in range(d + 1):
        s = 0.0
        for i in range(d):
            s += m[i, j] * y[i]
        u0[j] = s
    qa = -v[d] * v[d]
    qb = -u0[d] * v[d]
    qc = -u0[d] * u0[d]
    for j in range(d):
        qa += v[j] * v[j]
        qb += u0[j] * v[j]
        qc += u0[j] * u0[j]
    qb *= 2.0
    disc = qb * qb - 4.0 * qa * qc
    if disc < 0.0:
        if abs(disc) > 1e-6 * qb * qb:
            return 0
        disc = 0.0
    root = np.sqrt(disc)
    safe_a = qa if abs(qa) > 1e-300 else 1e-300
    longest = 0.0
    for i in range(d):
        longest = max(longest, paths[i])
    slack = 1e-9 + 1e-6 * longest
    found = 0
    for sign in (1.0, -1.0):
        s = (-qb + sign * root) / (2.0 * safe_a)
        rho = u0[d] + s * v[d]
        ok = rho >= -slack
        for i in range(d):
            ok = ok and paths[i] - rho >= -slack
        if not ok:
            continue
        for j in range(d):
            points[found, j] = u0[j] + s * v[j] + t[j]
        finite = True
        for j in range(d):
            finite = finite and np.isfinite(points[found, j])
        if finite:
            found += 1
    return found


@njit(cache=True, inline="always")
def _one_transmitter(transmitters: NDArray[np.float64]) -> bool:  # pragma: no cover - compiled
    """Whether every channel's transmitter is the first's, bit for bit (zeros' signs too):
    then each distance to it, and its direction, is the same number for every channel."""
    for c in range(1, transmitters.shape[0]):
        for j in range(transmitters.shape[1]):
            a, b = transmitters[c, j], transmitters[0, j]
            if not (a == b and np.signbit(a) == np.signbit(b)):
                return False
    return True


@njit(cache=True, inline="always")
def _in_beam(
    point: NDArray[np.float64],  # (D,), m
    origins: NDArray[np.float64],  # (C, D), m
    axes: NDArray[np.float64],  # (C, D), unit
    c: int,
    cos_fov: float,
) -> bool:  # pragma: no cover
    """Whether ``point`` is inside the beam of channel c's ``origins``/``axes`` (rows, not row
    views: a view in the seed loop costs two atomic reference counts)."""
    along = 0.0
    dist2 = 0.0
    for j in range(point.shape[0]):
        o = point[j] - origins[c, j]
        along += o * axes[c, j]
        dist2 += o * o
    return bool(along >= cos_fov * np.sqrt(dist2))


@njit(cache=True, inline="always")
def _insertion(
    values: NDArray[np.float64], lo: int, hi: int, value: float
) -> int:  # pragma: no cover - compiled
    """``lo + np.searchsorted(values[lo:hi], value)`` (NaN last) without the slice's view."""
    while lo < hi:
        mid = lo + ((hi - lo) >> 1)
        if values[mid] < value or (np.isnan(value) and not np.isnan(values[mid])):
            lo = mid + 1
        else:
            hi = mid
    return lo


@njit(cache=True, inline="always")
def _seed_conditioned_3d(
    jac: NDArray[np.float64], seed: NDArray[np.int64]
) -> bool:  # pragma: no cover - compiled
    """For D = 3, whether the seed channels' Jacobian rows ``jac[seed]`` (J_s) give a
    well-conditioned J_s^T J_s: the seed loop's normal matrix and :func:`_well_conditioned`
    in scalars, the same sums in the same order."""
    a, b, c = seed[0], seed[1], seed[2]
    a0, a1, a2 = jac[a, 0], jac[a, 1], jac[a, 2]
    b0, b1, b2 = jac[b, 0], jac[b, 1], jac[b, 2]
    c0, c1, c2 = jac[c, 0], jac[c, 1], jac[c, 2]
    n00 = 0.0 + a0 * a0 + b0 * b0 + c0 * c0
    n01 = 0.0 + a0 * a1 + b0 * b1 + c0 * c1
    n02 = 0.0 + a0 * a2 + b0 * b2 + c0 * c2
    n10 = 0.0 + a1 * a0 + b1 * b0 + c1 * c0
    n11 = 0.0 + a1 * a1 + b1 * b1 + c1 * c1
    n12 = 0.0 + a1 * a2 + b1 * b2 + c1 * c2
    n20 = 0.0 + a2 * a0 + b2 * b0 + c2 * c0
    n21 = 0.0 + a2 * a1 + b2 * b1 + c2 * c1
    n22 = 0.0 + a2 * a2 + b2 * b2 + c2 * c2
    if not (n00 > 0.0 and n11 > 0.0 and n22 > 0.0):
        return False
    bound = 1.0
    bound *= n00
    bound *= n11
    bound *= n22
    return bool(np.isfinite(bound) and _det3(n00, n01, n02, n10, n11, n12, n20, n21, n22) > 1e-12 * bound)


@njit(cache=True, inline="always")
def _seed_gain_3d(
    jac: NDArray[np.float64], seed: NDArray[np.int64], channel: int
) -> Any:  # pragma: no cover - compiled
    """For D = 3, (solved, g) with J_s^T g = the Jacobian row of ``channel``: the seed loop's
    solve in scalars (:func:`_solve3`)."""
    a, b, c = seed[0], seed[1], seed[2]
    return _solve3(
        jac[a, 0],
        jac[b, 0],
        jac[c, 0],
        jac[a, 1],
        jac[b, 1],
        jac[c, 1],
        jac[a, 2],
        jac[b, 2],
        jac[c, 2],
        jac[channel, 0],
        jac[channel, 1],
        jac[channel, 2],
    )


@njit(cache=True)
def seed_candidates(
    transmitters: NDArray[np.float64],  # (C, D), m
    receivers: NDArray[np.float64],  # (C, D), m
    transmitter_axes: NDArray[np.float64],  # (C, D), unit
    receiver_axes: NDArray[np.float64],  # (C, D), unit
    boresight: NDArray[np.float64],  # (D,)
    required: NDArray[np.bool_],  # (C,)
    flat_paths: NDArray[np.float64],  # (E,) every channel's echoes, m
    flat_sigmas: NDArray[np.float64],  # (E,), m
    offset: NDArray[np.int64],  # (C + 1,) channel c's echoes at offset[c]:offset[c + 1]
    sorted_paths: NDArray[np.float64],  # (E,) sorted within each channel, m
    sorted_index: NDArray[np.int64],  # (E,) their echo indices within the channel
    seeds: NDArray[np.int64],  # (S, D) channel indices
    window_low: float,
    window_high: float,
    cos_fov: float,
    k_gate: float,
    merge_reach: float,
    min_own: int,
    capacity: int | np.int64,  # Python int (locate) or np.int64 (candidates): int64
) -> Any:  # pragma: no cover - compiled
    """Steps 1-2 of locate.associate for every seed: (echo, use, points, count, overflow).

    ``flat_paths``/``flat_sigmas`` hold every channel's echoes, channel c's at
    ``offset[c]:offset[c+1]``; ``sorted_paths`` the same sorted within each channel,
    ``sorted_index`` their echo indices. Only the first ``count`` rows are written;
    ``overflow``: more than ``capacity`` rows (the caller tries again with more).
    """
    n_ch, d = receivers.shape
    echo_out = np.empty((capacity, n_ch), dtype=np.int64)
    use_out = np.empty((capacity, n_ch), dtype=np.int8)
    points_out = np.empty((capacity, d))
    count = 0
    direct = np.empty(n_ch)
    for c in range(n_ch):
        s = 0.0
        for j in range(d):
            s += (receivers[c, j] - transmitters[c, j]) ** 2
        direct[c] = np.sqrt(s)
    choice = np.zeros(d, dtype=np.int64)
    seed_paths = np.empty(d)
    seed_sigmas = np.empty(d)
    seed_rx = np.empty((d, d))
    points = np.empty((2, d))
    p = np.empty(d)
    jac = np.empty((n_ch, d))
    seed_jac = np.empty((d, d))
    predicted = np.empty(n_ch)
    row_echo = np.empty(n_ch, dtype=np.int64)
    row_use = np.empty(n_ch, dtype=np.int8)
    gain = np.empty(d)
    normal = np.empty((d, d))
    lhs = np.empty((d, d))
    column = np.empty(d)
    work = np.empty((5 * d + 5, d + 1))
    sizes = np.empty(d, dtype=np.int64)
    pair_reach = np.zeros((d, d))
    toward_t = np.empty(d)
    one_transmitter = _one_transmitter(transmitters)
    for s_index in range(seeds.shape[0]):
        seed = seeds[s_index]
        empty = False
        for k in range(d):
            sizes[k] = offset[seed[k] + 1] - offset[seed[k]]
            empty = empty or sizes[k] == 0
        if empty:
            continue
        for k in range(d):
            choice[k] = 0
        t = transmitters[seed[0]]
        for k in range(d):
            for j in range(d):
                seed_rx[k, j] = receivers[seed[k], j]
        _exact_prepare(t, seed_rx, work)
        for k in range(d):
            for q in range(k):
                a, b = seed[k], seed[q]
                span = 0.0
                span_t = 0.0
                for j in range(d):
                    span += (receivers[a, j] - receivers[b, j]) ** 2
                    span_t += (transmitters[a, j] - transmitters[b, j]) ** 2
                pair_reach[k, q] = np.sqrt(span) + np.sqrt(span_t)
        # Combinations of one echo per seed channel, depth first (the last channel's echo
        # changing fastest); triangle-inequality pruning on each prefix skips every
        # combination that shares an infeasible one.
        level = 0
        while level >= 0:
            if choice[level] == sizes[level]:
                choice[level] = 0
                level -= 1
                if level >= 0:
                    choice[level] += 1
                continue
            c = seed[level]
            seed_paths[level] = flat_paths[offset[c] + choice[level]]
            seed_sigmas[level] = flat_sigmas[offset[c] + choice[level]]
            feasible = not seed_paths[level] < direct[c] - 4.0 * seed_sigmas[level]
            for q in range(level):
                tol = 4.0 * np.sqrt(seed_sigmas[level] ** 2 + seed_sigmas[q] ** 2)
                feasible = (
                    feasible and not abs(seed_paths[level] - seed_paths[q]) > pair_reach[level, q] + tol
                )
            if not feasible:
                choice[level] += 1
                continue
            if level < d - 1:
                level += 1
                continue
            n_points = _exact_work(t, seed_paths, points, work)
            for r in range(n_points):
                for j in range(d):
                    p[j] = points[r, j]
                ahead = 0.0
                for j in range(d):
                    ahead += (p[j] - transmitters[0, j]) * boresight[j]
                if not ahead > 0.0:
                    continue
                ok = True
                for k in range(d):
                    c = seed[k]
                    ok = ok and _in_beam(p, transmitters, transmitter_axes, c, cos_fov)
                    ok = ok and _in_beam(p, receivers, receiver_axes, c, cos_fov)
                if not ok:
                    continue
                r_t = 0.0
                for c in range(n_ch):
                    if c == 0 or not one_transmitter:
                        # The distance to the transmitter and its direction: once for all
                        # channels when they share one (the same inputs, the same bits).
                        r_t = 0.0
                        for j in range(d):
                            r_t += (p[j] - transmitters[c, j]) ** 2
                        r_t = np.sqrt(r_t)
                        for j in range(d):
                            toward_t[j] = (p[j] - transmitters[c, j]) / r_t
                    r_r = 0.0
                    for j in range(d):
                        r_r += (p[j] - receivers[c, j]) ** 2
                    r_r = np.sqrt(r_r)
                    predicted[c] = r_t + r_r
                    for j in range(d):
                        jac[c, j] = toward_t[j] + (p[j] - receivers[c, j]) / r_r
                if d == 3:
                    if not _seed_conditioned_3d(jac, seed):
                        continue
                else:
                    for k in range(d):
                        for j in range(d):
                            seed_jac[k, j] = jac[seed[k], j]
                    for i in range(d):
                        for j in range(d):
                            acc = 0.0
                            for k in range(d):
                                acc += seed_jac[k, i] * seed_jac[k, j]
                            normal[i, j] = acc
                    if not _well_conditioned(normal):
                        continue
                n_own = 0
                keep = True
                for c in range(n_ch):
                    in_seed = -1
                    for k in range(d):
                        if seed[k] == c:
                            in_seed = k
                    if in_seed >= 0:
                        row_echo[c] = choice[in_seed]
                        row_use[c] = OWN
                        n_own += 1
                        continue
                    row_echo[c] = -1
                    row_use[c] = NONE
                    visible = _in_beam(p, transmitters, transmitter_axes, c, cos_fov)
                    visible = visible and _in_beam(p, receivers, receiver_axes, c, cos_fov)
                    outside = predicted[c] < window_low or predicted[c] > window_high
                    if not visible or outside:
                        continue  # this channel cannot see the point: no echo, none needed
                    # Prediction variance from the seed: g_c J_s^-1, squared, times sigma^2.
                    if d == 3:
                        solved, gain[0], gain[1], gain[2] = _seed_gain_3d(jac, seed, c)
                    else:
                        for i in range(d):
                            column[i] = jac[c, i]
                            for j in range(d):
                                lhs[i, j] = seed_jac[j, i]
                        solved = _solve(lhs, column, gain)
                    if not solved:
                        keep = False
                        break
                    var = 0.0
                    for k in range(d):
                        var += gain[k] ** 2 * seed_sigmas[k] ** 2
                    lo, hi = offset[c], offset[c + 1]
                    if hi > lo:
                        pos = _insertion(sorted_paths, lo, hi, predicted[c])
                        best = -1
                        gap = np.inf
                        for cand in (pos - 1, pos):
                            if lo <= cand < hi and abs(sorted_paths[cand] - predicted[c]) < gap:
                                gap = abs(sorted_paths[cand] - predicted[c])
                                best = cand
                        echo_index = sorted_index[best]
                        reach = k_gate * np.sqrt(var + flat_sigmas[lo + echo_index] ** 2)
                        if gap <= reach:
                            row_echo[c] = echo_index
                            row_use[c] = OWN
                            n_own += 1
                        elif required[c] and gap <= merge_reach + reach:
                            # A merged peak; on an optional channel (an older frame) a
                            # larger gap means the reflector moved: no support there.
                            row_echo[c] = echo_index
                            row_use[c] = SHARED
                    if row_use[c] == NONE and required[c]:
                        # A required channel that can see the point must show its echo.
                        keep = False
                        break
                if keep and n_own >= min_own:
                    if count == capacity:
                        return echo_out, use_out, points_out, count, True
                    echo_out[count] = row_echo
                    use_out[count] = row_use
                    points_out[count] = p
                    count += 1
            choice[level] += 1
    return echo_out, use_out, points_out, count, False


@njit(cache=True)
def gauss_newton(
    transmitters: NDArray[np.float64],  # (C, D), m
    receivers: NDArray[np.float64],  # (C, D), m
    paths: NDArray[np.float64],  # (n, C), m
    weights: NDArray[np.float64],  # (n, C), 0: channel unused
    start: NDArray[np.float64],  # (n, D), m
    iterations: int,
) -> Any:  # pragma: no cover - compiled
    """Weighted Gauss-Newton per row on l_c = |p - T_c| + |p - R_c| (locate.solve_positions).

    Returns (positions, covariances, chi2, converged); a singular or non-finite
    system leaves NaN.
    """
    n = paths.shape[0]
    d = receivers.shape[1]
    positions = np.full((n, d), np.nan)
    covariances = np.full((n, d, d), np.nan)
    chi2 = np.full(n, np.nan)
    converged = np.zeros(n, dtype=np.bool_)
    work = np.empty((2 * d + 6, d))
    for row in range(n):
        chi2[row], converged[row] = _gauss_newton_row(
            transmitters,
            receivers,
            paths[row],
            weights[row],
            start[row],
            iterations,
            positions[row],
            covariances[row],
            work,
        )
    return positions, covariances, chi2, converged


@_without_runtime
def _gauss_newton_row(
    transmitters: NDArray[np.float64],  # (C, D), m
    receivers: NDArray[np.float64],  # (C, D), m
    paths: NDArray[np.float64],  # (C,), m
    weights: NDArray[np.float64],  # (C,)
    start: NDArray[np.float64],  # (D,), m
    iterations: int | np.int64,  # Python int (gauss_newton) or np.int64 (choose, refine): int64
    position: NDArray[np.float64],  # (D,) out
    covariance: NDArray[np.float64],  # (D, D) out
    work: NDArray[np.float64],  # (2 D + 6, D) scratch
) -> Any:  # pragma: no cover - compiled
    """One row of :func:`gauss_newton` into ``position`` (D,) and ``covariance`` (D, D), which
    stay as given (NaN) when the system is singular; returns (chi2, converged).
    ``work`` is scratch of (2 D + 6, D)."""
    if receivers.shape[1] == 3:
        return _gauss_newton_row_3d(
            transmitters, receivers, paths, weights, start, iterations, position, covariance
        )
    return _gauss_newton_row_any(
        transmitters, receivers, paths, weights, start, iterations, position, covariance, work
    )


@_without_runtime
def _gauss_newton_row_3d(
    transmitters: NDArray[np.float64],  # (C, D), m
    receivers: NDArray[np.float64],  # (C, D), m
    paths: NDArray[np.float64],  # (C,), m
    weights: NDArray[np.float64],  # (C,)
    start: NDArray[np.float64],  # (D,), m
    iterations: int | np.int64,  # Python int (gauss_newton) or np.int64 (choose, refine): int64
    position: NDArray[np.float64],  # (D,) out
    covariance: NDArray[np.float64],  # (D, D) out
) -> Any:  # pragma: no cover - compiled
    """:func:`_gauss_newton_row_any` for D = 3 in scalars (registers, not scratch rows): the same
    operations in the same order, so the same bits. A covariance column whose solve fails
    (which the conditioning test before it rules out) stays NaN."""
    n_ch = paths.shape[0]
    one_transmitter = _one_transmitter(transmitters)
    p0, p1, p2 = start[0], start[1], start[2]
    chi2 = np.nan
    step = np.inf
    for it in range(iterations + 1):
        n00 = n01 = n02 = n10 = n11 = n12 = n20 = n21 = n22 = 0.0
        h0 = h1 = h2 = 0.0
        total = 0.0
        r_t = u0 = u1 = u2 = 0.0
        toward_t_known = False
        for c in range(n_ch):
            w = weights[c]
            if w == 0.0:
                continue
            if not (toward_t_known and one_transmitter):
                toward_t_known = True
                # The distance to the transmitter and its direction: once an iteration when
                # every channel shares one (the same inputs, the same bits).
                t0, t1, t2 = p0 - transmitters[c, 0], p1 - transmitters[c, 1], p2 - transmitters[c, 2]
                r_t = 0.0
                r_t += t0**2
                r_t += t1**2
                r_t += t2**2
                r_t = np.sqrt(r_t)
                u0, u1, u2 = t0 / r_t, t1 / r_t, t2 / r_t
            q0, q1, q2 = p0 - receivers[c, 0], p1 - receivers[c, 1], p2 - receivers[c, 2]
            r_r = 0.0
            r_r += q0**2
            r_r += q1**2
            r_r += q2**2
            r_r = np.sqrt(r_r)
            j0 = u0 + q0 / r_r
            j1 = u1 + q1 / r_r
            j2 = u2 + q2 / r_r
            residual = paths[c] - r_t - r_r
            total += w * residual * residual
            h0 += w * j0 * residual
            h1 += w * j1 * residual
            h2 += w * j2 * residual
            n00 += w * j0 * j0
            n01 += w * j0 * j1
            n02 += w * j0 * j2
            n10 += w * j1 * j0
            n11 += w * j1 * j1
            n12 += w * j1 * j2
            n20 += w * j2 * j0
            n21 += w * j2 * j1
            n22 += w * j2 * j2
        # _well_conditioned, as it tests the normal matrix.
        if not (n00 > 0.0 and n11 > 0.0 and n22 > 0.0):
            return np.nan, False
        bound = 1.0
        bound *= n00
        bound *= n11
        bound *= n22
        if not (np.isfinite(bound) and _det3(n00, n01, n02, n10, n11, n12, n20, n21, n22) > 1e-12 * bound):
            return np.nan, False
        if it == iterations or step < 1e-9:
            # Converged (or out of iterations): covariance and chi-square at p.
            for j in range(3):
                e0 = 1.0 if j == 0 else 0.0
                e1 = 1.0 if j == 1 else 0.0
                e2 = 1.0 if j == 2 else 0.0
                solved, x0, x1, x2 = _solve3(n00, n01, n02, n10, n11, n12, n20, n21, n22, e0, e1, e2)
                if solved:
                    covariance[0, j] = x0
                    covariance[1, j] = x1
                    covariance[2, j] = x2
            chi2 = total
            break
        solved, d0, d1, d2 = _solve3(n00, n01, n02, n10, n11, n12, n20, n21, n22, h0, h1, h2)
        if not solved:
            return np.nan, False
        p0 += d0
        p1 += d1
        p2 += d2
        step = 0.0
        step += d0**2
        step += d1**2
        step += d2**2
        step = np.sqrt(step)
    position[0] = p0
    position[1] = p1
    position[2] = p2
    return chi2, bool(step < 1e-6 and np.isfinite(chi2))


@_without_runtime
def _gauss_newton_row_any(
    transmitters: NDArray[np.float64],  # (C, D), m
    receivers: NDArray[np.float64],  # (C, D), m
    paths: NDArray[np.float64],  # (C,), m
    weights: NDArray[np.float64],  # (C,)
    start: NDArray[np.float64],  # (D,), m
    iterations: int | np.int64,  # Python int (gauss_newton) or np.int64 (choose, refine): int64
    position: NDArray[np.float64],  # (D,) out
    covariance: NDArray[np.float64],  # (D, D) out
    work: NDArray[np.float64],  # (2 D + 6, D) scratch
) -> Any:  # pragma: no cover - compiled
    """:func:`_gauss_newton_row` in any dimension, through the scratch rows ``work``."""
    n_ch = paths.shape[0]
    d = receivers.shape[1]
    normal = work[:d]
    lhs = work[d : 2 * d]
    p = work[2 * d]
    rhs = work[2 * d + 1]
    delta = work[2 * d + 2]
    jac = work[2 * d + 3]
    column = work[2 * d + 4]
    unit = work[2 * d + 5]
    for j in range(d):
        p[j] = start[j]
    chi2 = np.nan
    step = np.inf
    for it in range(iterations + 1):
        normal[:] = 0.0
        rhs[:] = 0.0
        total = 0.0
        for c in range(n_ch):
            w = weights[c]
            if w == 0.0:
                continue
            r_t = 0.0
            r_r = 0.0
            for j in range(d):
                r_t += (p[j] - transmitters[c, j]) ** 2
                r_r += (p[j] - receivers[c, j]) ** 2
            r_t = np.sqrt(r_t)
            r_r = np.sqrt(r_r)
            for j in range(d):
                jac[j] = (p[j] - transmitters[c, j]) / r_t + (p[j] - receivers[c, j]) / r_r
            residual = paths[c] - r_t - r_r
            total += w * residual * residual
            for i in range(d):
                rhs[i] += w * jac[i] * residual
                for j in range(d):
                    normal[i, j] += w * jac[i] * jac[j]
        if not _well_conditioned(normal):
            return np.nan, False
        if it == iterations or step < 1e-9:
            # Converged (or out of iterations): covariance and chi-square at p.
            for j in range(d):
                for i in range(d):
                    unit[i] = 1.0 if i == j else 0.0
                _copy(normal, lhs)
                solve_in_place(lhs, unit, column)
                for i in range(d):
                    covariance[i, j] = column[i]
            chi2 = total
            break
        _copy(normal, lhs)
        if not solve_in_place(lhs, rhs, delta):
            return np.nan, False
        step = 0.0
        for j in range(d):
            p[j] += delta[j]
            step += delta[j] ** 2
        step = np.sqrt(step)
    for j in range(d):
        position[j] = p[j]
    return chi2, bool(step < 1e-6 and np.isfinite(chi2))


@_without_runtime
def _fit_row(
    transmitters: NDArray[np.float64],  # (C, D), m
    receivers: NDArray[np.float64],  # (C, D), m
    transmitter_axes: NDArray[np.float64],  # (C, D), unit
    receiver_axes: NDArray[np.float64],  # (C, D), unit
    boresight: NDArray[np.float64],  # (D,)
    paths: NDArray[np.float64],  # (E,) every channel's echoes, m
    sigmas: NDArray[np.float64],  # (E,), m
    offset: NDArray[np.int64],  # (C + 1,) channel c's echoes at offset[c]:offset[c + 1]
    echo: NDArray[np.int64],  # (C,) echo index per channel
    use: NDArray[np.int8],  # (C,) OWN, SHARED or NONE
    start: NDArray[np.float64],  # (D,), m
    merge_sigma: float,
    gates: NDArray[np.float64],  # (C + 1,) chi-square gate by echo count
    check_beams: bool,
    cos_fov: float,
    iterations: int | np.int64,  # as refine's: int64
    measured: NDArray[np.float64],  # (C,) scratch
    weights: NDArray[np.float64],  # (C,) scratch
    position: NDArray[np.float64],  # (D,) out
    covariance: NDArray[np.float64],  # (D, D) out
    work: NDArray[np.float64],  # (2 D + 6, D) scratch
) -> Any:  # pragma: no cover - compiled
    """locate._fit_and_gate for one candidate: (chi2, converged, passes the gate and is in view).

    ``merge_sigma`` < 0: no merged peaks (resolution None).
    """
    n_ch = echo.shape[0]
    n_used = _measure(paths, sigmas, offset, echo, use, merge_sigma, measured, weights)
    position[:] = np.nan
    covariance[:, :] = np.nan
    chi2, converged = _gauss_newton_row(
        transmitters, receivers, measured, weights, start, iterations, position, covariance, work
    )
    ok = converged and chi2 <= gates[n_used]
    if ok:
        ahead = 0.0
        for j in range(position.shape[0]):
            ahead += (position[j] - transmitters[0, j]) * boresight[j]
        ok = ahead > 0.0
    if ok and check_beams:
        for c in range(n_ch):
            if use[c] != NONE:
                ok = ok and _in_beam(position, transmitters, transmitter_axes, c, cos_fov)
                ok = ok and _in_beam(position, receivers, receiver_axes, c, cos_fov)
    return chi2, converged, ok


@njit(cache=True)
def refine(
    transmitters: NDArray[np.float64],  # (C, D), m
    receivers: NDArray[np.float64],  # (C, D), m
    transmitter_axes: NDArray[np.float64],  # (C, D), unit
    receiver_axes: NDArray[np.float64],  # (C, D), unit
    boresight: NDArray[np.float64],  # (D,)
    required: NDArray[np.bool_],  # (C,)
    paths: NDArray[np.float64],  # (E,) every channel's echoes, m
    sigmas: NDArray[np.float64],  # (E,), m
    amplitudes: NDArray[np.float64],  # (E,) or (0,): none
    offset: NDArray[np.int64],  # (C + 1,) channel c's echoes at offset[c]:offset[c + 1]
    echo: NDArray[np.int64],  # (n, C) echo index per channel, -1 none
    use: NDArray[np.int8],  # (n, C) OWN, SHARED or NONE
    start: NDArray[np.float64],  # (n, D), m
    merge_sigma: float,
    gates: NDArray[np.float64],  # (C + 1,) chi-square gate by echo count
    check_beams: bool,
    cos_fov: float,
    min_own: int,
    iterations: int | np.int64,  # Python int (locate) or np.int64 (candidates, choose): int64
    amplitude_log_sigma: float,
) -> Any:  # pragma: no cover - compiled
    """Step 3 of locate.associate (locate._refine_reference): every candidate fitted and gated,
    again without its optional channels when it fails with them; the amplitude chi-square
    of those kept (``amplitudes`` empty: none). Returns the kept rows:
    (echo, use, positions, covariances, chi2, converged, amplitude_chi2)."""
    n, n_ch = echo.shape
    d = receivers.shape[1]
    echo_out = np.empty((n, n_ch), dtype=np.int64)
    use_out = np.empty((n, n_ch), dtype=np.int8)
    positions = np.empty((n, d))
    covariances = np.empty((n, d, d))
    chi2_out = np.empty(n)
    converged_out = np.empty(n, dtype=np.bool_)
    amplitude_chi2 = np.zeros(n)
    measured = np.empty(n_ch)
    weights = np.empty(n_ch)
    row_echo = np.empty(n_ch, dtype=np.int64)
    row_use = np.empty(n_ch, dtype=np.int8)
    log_strength = np.empty(n_ch)
    work = np.empty((2 * d + 6, d))
    kept = 0
    for row in range(n):
        position = positions[kept]
        covariance = covariances[kept]
        optional = False
        for c in range(n_ch):
            row_echo[c] = echo[row, c]
            row_use[c] = use[row, c]
            optional = optional or (use[row, c] != NONE and not required[c])
        # Fitted with the optional channels and, failing that, once more without them (one
        # call with the arrays as they are: a tuple of them would count references per row).
        chi2, converged, ok = np.nan, False, False
        for attempt in range(2):
            if attempt == 1:
                if ok or not optional:
                    break
                own = 0
                for c in range(n_ch):
                    if not required[c]:
                        row_use[c] = NONE
                    if row_use[c] == NONE:
                        row_echo[c] = -1
                    own += row_use[c] == OWN
                if own < min_own:
                    break
            chi2, converged, ok = _fit_row(
                transmitters,
                receivers,
                transmitter_axes,
                receiver_axes,
                boresight,
                paths,
                sigmas,
                offset,
                row_echo,
                row_use,
                start[row],
                merge_sigma,
                gates,
                check_beams,
                cos_fov,
                iterations,
                measured,
                weights,
                position,
                covariance,
                work,
            )
        if not ok:
            continue
        echo_out[kept] = row_echo
        use_out[kept] = row_use
        chi2_out[kept] = chi2
        converged_out[kept] = converged
        if amplitudes.shape[0] > 0:
            count = 0
            total = 0.0
            for c in range(n_ch):
                log_strength[c] = 0.0
                if row_use[c] != OWN:
                    continue
                count += 1
                r_t = 0.0
                r_r = 0.0
                for j in range(d):
                    r_t += (position[j] - transmitters[c, j]) ** 2
                    r_r += (position[j] - receivers[c, j]) ** 2
                spread = np.sqrt(r_t) * np.sqrt(r_r)
                log_strength[c] = np.log(abs(amplitudes[offset[c] + row_echo[c]]) * spread)
                total += log_strength[c]
            count = max(count, 1)
            mean = total / count
            spread2 = 0.0
            for c in range(n_ch):
                if row_use[c] == OWN:
                    spread2 += (log_strength[c] - mean) ** 2
            value = spread2 / amplitude_log_sigma**2 / count
            amplitude_chi2[kept] = 1e3 if np.isnan(value) or value == np.inf else value
        kept += 1
    return (
        echo_out[:kept],
        use_out[:kept],
        positions[:kept],
        covariances[:kept],
        chi2_out[:kept],
        converged_out[:kept],
        amplitude_chi2[:kept],
    )


@njit(cache=True)
def _weights(
    use: NDArray[np.int8],  # (n, C)
    chi2: NDArray[np.float64],  # (n,)
    amplitude_chi2: NDArray[np.float64],  # (n,)
    gates: NDArray[np.float64],  # (C + 1,)
    out: NDArray[np.float64],  # (n,) out
) -> bool:  # pragma: no cover
    """locate._weights into ``out``; False when two weights tie or one is NaN (order undefined)."""
    n, n_ch = use.shape
    for row in range(n):
        n_used = 0
        n_shared = 0
        for c in range(n_ch):
            n_used += use[row, c] != NONE
            n_shared += use[row, c] == SHARED
        gate = gates[n_used]
        gate = max(gate, 1.0) if np.isfinite(gate) else 1.0
        tie = chi2[row] / gate + amplitude_chi2[row] / max(n_used, 1) + 0.5 * n_shared
        if np.isnan(tie):
            return False
        out[row] = 1.0 - 1e-3 * min(tie, 100.0)
    return True


@njit(cache=True)
def _has_tie(values: NDArray[np.float64], members: NDArray[np.int64]) -> bool:  # pragma: no cover - compiled
    for a in range(members.shape[0]):
        for b in range(a):
            if values[members[a]] == values[members[b]]:
                return True
    return False


@njit(cache=True)
def _order_by_weight(
    weights: NDArray[np.float64], members: NDArray[np.int64]
) -> None:  # pragma: no cover - compiled
    """Sort ``members`` heaviest first (insertion sort: equal weights keep their order, as a
    stable sort leaves them)."""
    for a in range(1, members.shape[0]):
        item = members[a]
        b = a - 1
        while b >= 0 and weights[members[b]] < weights[item]:
            members[b + 1] = members[b]
            b -= 1
        members[b + 1] = item


@njit(cache=True)
def _pack_group(
    group: NDArray[np.int64],  # (m,) rows
    ids: NDArray[np.int64],  # (n, C) flat echo ids, -1 none
    weights: NDArray[np.float64],  # (n,)
    n_echo: int,
    node_limit: int,
    out: NDArray[np.int64],  # (m,) out
) -> int:  # pragma: no cover
    """locate._pack_group: branch and bound over ``group`` (sorted heaviest first); the chosen
    members into ``out`` in group order, returns how many. ``ids`` (n, C): flat echo ids, -1 none."""
    m = group.shape[0]
    n_ch = ids.shape[1]
    # Local echo numbers within the group.
    local = np.full(n_echo, -1, dtype=np.int64)
    q = 0
    per_echo = -np.inf
    for k in range(m):
        size = 0
        for c in range(n_ch):
            e = ids[group[k], c]
            if e >= 0:
                size += 1
                if local[e] < 0:
                    local[e] = q
                    q += 1
        per_echo = max(per_echo, weights[group[k]] / max(size, 1))
    per_echo = max(per_echo, 0.0)
    reachable = np.zeros((m + 1, q), dtype=np.bool_)
    for k in range(m - 1, -1, -1):
        reachable[k] = reachable[k + 1]
        for c in range(n_ch):
            e = ids[group[k], c]
            if e >= 0:
                reachable[k, local[e]] = True
    used = np.zeros(q, dtype=np.bool_)
    best = np.empty(m, dtype=np.int64)
    n_best = 0
    best_weight = 0.0
    for k in range(m):  # the greedy incumbent
        if weights[group[k]] > 0 and _disjoint(ids[group[k]], local, used):
            best[n_best] = k
            n_best += 1
            _mark(ids[group[k]], local, used, True)
    for i in range(n_best):
        best_weight += weights[group[best[i]]]
    used[:] = False
    picked = np.empty(m, dtype=np.int64)
    n_picked = 0
    steps = 0
    # Depth-first, "take item k" before "leave it", as the recursion of the reference.
    stack_k = np.empty(m + 2, dtype=np.int64)
    stack_total = np.empty(m + 2)
    stack_state = np.empty(m + 2, dtype=np.int64)
    depth = 1
    stack_k[0] = 0
    stack_total[0] = 0.0
    stack_state[0] = 0
    while depth > 0:
        top = depth - 1
        k = stack_k[top]
        total = stack_total[top]
        if stack_state[top] == 0:
            steps += 1
            if total > best_weight + 1e-12:
                best[:n_picked] = picked[:n_picked]
                n_best = n_picked
                best_weight = total
            if k == m or steps > node_limit:
                depth -= 1
                continue
            free = 0
            for i in range(q):
                free += reachable[k, i] and not used[i]
            if total + per_echo * free <= best_weight + 1e-12:
                depth -= 1
                continue
            w = weights[group[k]]
            if w > 0 and _disjoint(ids[group[k]], local, used):
                stack_state[top] = 1
                picked[n_picked] = k
                n_picked += 1
                _mark(ids[group[k]], local, used, True)
                total += w
            else:
                stack_state[top] = 2
        elif stack_state[top] == 1:
            n_picked -= 1
            _mark(ids[group[k]], local, used, False)
            stack_state[top] = 2
        else:
            depth -= 1
            continue
        stack_k[depth] = k + 1
        stack_total[depth] = total
        stack_state[depth] = 0
        depth += 1
    for i in range(n_best):
        out[i] = group[best[i]]
    return n_best


@njit(cache=True, inline="always")
def _disjoint(
    ids: NDArray[np.int64], local: NDArray[np.int64], used: NDArray[np.bool_]
) -> bool:  # pragma: no cover - compiled
    """Whether no echo of a candidate (flat ids, -1 none) is marked in ``used`` (by ``local`` number)."""
    free = True
    for c in range(ids.shape[0]):
        free = free and not (ids[c] >= 0 and used[local[ids[c]]])
    return free


@njit(cache=True, inline="always")
def _mark(
    ids: NDArray[np.int64], local: NDArray[np.int64], used: NDArray[np.bool_], value: bool
) -> None:  # pragma: no cover - compiled
    for c in range(ids.shape[0]):
        if ids[c] >= 0:
            used[local[ids[c]]] = value


@njit(cache=True)
def best_disjoint(
    members: NDArray[np.int64],  # (m,) rows
    ids: NDArray[np.int64],  # (n, C) flat echo ids, -1 none
    weights: NDArray[np.float64],  # (n,)
    n_echo: int,
    node_limit: int,
    out: NDArray[np.int64],  # (m,) out
) -> Any:  # pragma: no cover - compiled
    """locate._best_disjoint over the candidates ``members`` (rows of ``ids``/``weights``):
    the chosen rows into ``out`` in the reference's order; returns (how many, True), or
    (0, False) when weights tie within a group (the reference's order is then undefined)."""
    n = members.shape[0]
    n_ch = ids.shape[1]
    # Which members hold each echo (CSR), for the connected groups of conflicting members.
    start = np.zeros(n_echo + 1, dtype=np.int64)
    for i in range(n):
        for c in range(n_ch):
            e = ids[members[i], c]
            if e >= 0:
                start[e + 1] += 1
    for e in range(n_echo):
        start[e + 1] += start[e]
    holder = np.empty(start[n_echo], dtype=np.int64)
    fill = start[:-1].copy()
    for i in range(n):
        for c in range(n_ch):
            e = ids[members[i], c]
            if e >= 0:
                holder[fill[e]] = i
                fill[e] += 1
    seen = np.zeros(n, dtype=np.bool_)
    queue = np.empty(n, dtype=np.int64)
    count = 0
    for root in range(n):
        if seen[root]:
            continue
        seen[root] = True
        queue[0] = root
        size = 1
        head = 0
        while head < size:
            node = queue[head]
            head += 1
            for c in range(n_ch):
                e = ids[members[node], c]
                if e < 0:
                    continue
                for h in range(start[e], start[e + 1]):
                    other = holder[h]
                    if not seen[other]:
                        seen[other] = True
                        queue[size] = other
                        size += 1
        if size == 1:
            out[count] = members[root]
            count += 1
            continue
        group = members[queue[:size]]
        if _has_tie(weights, group):
            return 0, False
        _order_by_weight(weights, group)
        count += _pack_group(group, ids, weights, n_echo, node_limit, out[count:])
    return count, True


@njit(cache=True)
def _attach_ids(
    echo: NDArray[np.int64], use: NDArray[np.int8], offset: NDArray[np.int64], ids: NDArray[np.int64]
) -> None:  # pragma: no cover - compiled
    """Flat echo id (offset[c] + echo) of every echo a candidate uses, -1 where none."""
    for row in range(echo.shape[0]):
        for c in range(echo.shape[1]):
            ids[row, c] = offset[c] + echo[row, c] if use[row, c] != NONE else -1


@njit(cache=True)
def choose(
    transmitters: NDArray[np.float64],  # (C, D), m
    receivers: NDArray[np.float64],  # (C, D), m
    transmitter_axes: NDArray[np.float64],  # (C, D), unit
    receiver_axes: NDArray[np.float64],  # (C, D), unit
    boresight: NDArray[np.float64],  # (D,)
    required: NDArray[np.bool_],  # (C,)
    paths: NDArray[np.float64],  # (E,) every channel's echoes, m
    sigmas: NDArray[np.float64],  # (E,), m
    amplitudes: NDArray[np.float64],  # (E,) or (0,): none
    offset: NDArray[np.int64],  # (C + 1,) channel c's echoes at offset[c]:offset[c + 1]
    echo: NDArray[np.int64],  # (n, C) echo index per channel
    use: NDArray[np.int8],  # (n, C) OWN, SHARED or NONE
    position: NDArray[np.float64],  # (n, D), m
    chi2: NDArray[np.float64],  # (n,)
    amplitude_chi2: NDArray[np.float64],  # (n,)
    merge_sigma: float,
    merge_reach: float,
    gates: NDArray[np.float64],  # (C + 1,) chi-square gate by echo count
    check_beams: bool,
    cos_fov: float,
    min_own: int,
    sharing_rounds: int,
    amplitude_log_sigma: float,
    node_limit: int,
) -> Any:  # pragma: no cover - compiled
    """Step 4 of locate.associate (locate._choose_reference) up to the scores.

    Returns (done, echo, use, positions, covariances, chi2, converged, good): the
    chosen objects' rows and which survive (converged, finite, no duplicate).
    ``done`` False: weights tie where the reference's order decides; nothing else
    is meaningful then and the caller runs the reference. ``merge_sigma`` < 0: no
    merged peaks (resolution None).
    """
    n_ch: int  # typed (no code): an index of NDArray's Any shape types its items as arrays
    n, n_ch = echo.shape
    d = receivers.shape[1]
    n_echo = offset[n_ch]
    min_own_sharing = min_own - 1
    cap = 2 * n + 1
    chosen_echo = np.empty((cap, n_ch), dtype=np.int64)
    chosen_use = np.empty((cap, n_ch), dtype=np.int8)
    starts = np.empty((cap, d))
    failed = (
        False,
        np.empty((0, n_ch), dtype=np.int64),
        np.empty((0, n_ch), dtype=np.int8),
        np.empty((0, d)),
        np.empty((0, d, d)),
        np.empty(0),
        np.empty(0, dtype=np.bool_),
        np.empty(0, dtype=np.bool_),
    )
    weights = np.empty(n)
    if not _weights(use, chi2, amplitude_chi2, gates, weights):
        return failed
    ids = np.empty((n, n_ch), dtype=np.int64)
    _attach_ids(echo, use, offset, ids)
    has_shared = np.zeros(n, dtype=np.bool_)
    for row in range(n):
        for c in range(n_ch):
            has_shared[row] = has_shared[row] or use[row, c] == SHARED
    # First pass: candidates whose echoes are all their own; each echo used once.
    picked = np.empty(n, dtype=np.int64)
    count, ok = best_disjoint(np.flatnonzero(~has_shared), ids, weights, n_echo, node_limit, picked)
    if not ok:
        return failed
    # Then candidates with a merged-looking echo no chosen object uses.
    taken = np.zeros(n_echo, dtype=np.bool_)
    for i in range(count):
        for c in range(n_ch):
            if ids[picked[i], c] >= 0:
                taken[ids[picked[i], c]] = True
    second_pass = np.empty(n, dtype=np.int64)
    n_second = 0
    identity = np.arange(n_echo)
    for row in range(n):
        if has_shared[row] and _disjoint(ids[row], identity, taken):
            second_pass[n_second] = row
            n_second += 1
    more, ok = best_disjoint(second_pass[:n_second], ids, weights, n_echo, node_limit, picked[count:])
    if not ok:
        return failed
    count += more
    n_chosen = count
    done = np.zeros(n, dtype=np.bool_)
    for i in range(count):
        chosen_echo[i] = echo[picked[i]]
        chosen_use[i] = use[picked[i]]
        starts[i] = position[picked[i]]
        done[picked[i]] = True
    # Sharing rounds: candidates that lost echoes to chosen objects, with enough left.
    claimed = np.zeros(n_echo, dtype=np.bool_)
    retry = np.empty(n, dtype=np.int64)
    row_ids = np.empty(n_ch, dtype=np.int64)
    for _ in range(sharing_rounds):
        claimed[:] = False
        for i in range(n_chosen):
            for c in range(n_ch):
                if chosen_use[i, c] != NONE:
                    claimed[offset[c] + chosen_echo[i, c]] = True
        n_retry = 0
        for row in range(n):
            if done[row]:
                continue
            shared_claimed = True
            any_shared = False
            own_claimed = False
            own_free = 0
            for c in range(n_ch):
                e = ids[row, c]
                if e < 0:
                    continue
                if use[row, c] == OWN:
                    own_claimed = own_claimed or claimed[e]
                    own_free += not claimed[e]
                else:
                    any_shared = True
                    shared_claimed = shared_claimed and claimed[e]
            if shared_claimed and (any_shared or own_claimed) and own_free >= min_own_sharing:
                retry[n_retry] = row
                n_retry += 1
        if n_retry == 0:
            break
        rows = retry[:n_retry]
        done[rows] = True
        new_use = use[rows].copy()
        for i in range(n_retry):
            for c in range(n_ch):
                e = ids[rows[i], c]
                if e >= 0 and claimed[e]:
                    new_use[i, c] = SHARED
        s_echo, s_use, s_position, _, s_chi2, _, s_amplitude = refine(
            transmitters,
            receivers,
            transmitter_axes,
            receiver_axes,
            boresight,
            required,
            paths,
            sigmas,
            amplitudes,
            offset,
            echo[rows],
            new_use,
            position[rows],
            merge_sigma,
            gates,
            check_beams,
            cos_fov,
            min_own,
            np.int64(6),
            amplitude_log_sigma,
        )
        m = s_echo.shape[0]
        s_weights = np.empty(m)
        order = np.arange(m)
        if not _weights(s_use, s_chi2, s_amplitude, gates, s_weights):
            return failed
        # Heaviest first, ties in candidate order (the reference's stable argsort).
        _order_by_weight(s_weights, order)
        taken[:] = False
        added = False
        for k in order:
            clash = False
            for c in range(n_ch):
                if s_use[k, c] == NONE:
                    row_ids[c] = -1
                    continue
                row_ids[c] = offset[c] + s_echo[k, c]
                if s_use[k, c] == SHARED:
                    clash = clash or not claimed[row_ids[c]]
                else:
                    clash = clash or claimed[row_ids[c]] or taken[row_ids[c]]
            if clash:
                continue
            for c in range(n_ch):
                if s_use[k, c] == OWN:
                    taken[row_ids[c]] = True
            chosen_echo[n_chosen] = s_echo[k]
            chosen_use[n_chosen] = s_use[k]
            starts[n_chosen] = s_position[k]
            n_chosen += 1
            added = True
        if not added:
            break
    # An object must keep echoes no other object explains (else a ghost): worst first.
    users = np.zeros(n_echo, dtype=np.int64)
    for i in range(n_chosen):
        for c in range(n_ch):
            if chosen_use[i, c] != NONE:
                users[offset[c] + chosen_echo[i, c]] += 1
    while n_chosen > 0:
        worst = -1
        fewest = n_ch + 1
        for i in range(n_chosen):
            exclusive = 0
            for c in range(n_ch):
                if chosen_use[i, c] != NONE:
                    exclusive += users[offset[c] + chosen_echo[i, c]] == 1
            if exclusive < fewest:
                fewest = exclusive
                worst = i
        if fewest >= min_own_sharing:
            break
        for c in range(n_ch):
            if chosen_use[worst, c] != NONE:
                users[offset[c] + chosen_echo[worst, c]] -= 1
        for i in range(worst, n_chosen - 1):
            chosen_echo[i] = chosen_echo[i + 1]
            chosen_use[i] = chosen_use[i + 1]
            starts[i] = starts[i + 1]
        n_chosen -= 1
    # Every echo that serves two objects is a merged peak for all of them: re-solve.
    f_echo = chosen_echo[:n_chosen].copy()
    f_use = chosen_use[:n_chosen].copy()
    for i in range(n_chosen):
        for c in range(n_ch):
            if f_use[i, c] != NONE and users[offset[c] + f_echo[i, c]] > 1:
                f_use[i, c] = SHARED
    f_position = np.full((n_chosen, d), np.nan)
    f_covariance = np.full((n_chosen, d, d), np.nan)
    f_chi2 = np.empty(n_chosen)
    f_converged = np.empty(n_chosen, dtype=np.bool_)
    good = np.empty(n_chosen, dtype=np.bool_)
    measured = np.empty(n_ch)
    row_weights = np.empty(n_ch)
    work = np.empty((2 * d + 6, d))
    for i in range(n_chosen):
        _measure(paths, sigmas, offset, f_echo[i], f_use[i], merge_sigma, measured, row_weights)
        f_chi2[i], f_converged[i] = _gauss_newton_row(
            transmitters,
            receivers,
            measured,
            row_weights,
            starts[i],
            np.int64(4),
            f_position[i],
            f_covariance[i],
            work,
        )
        good[i] = f_converged[i] and np.all(np.isfinite(f_covariance[i]))
    # Objects that repeat a better one (paths within a merge's reach everywhere) go.
    if merge_sigma >= 0.0 and n_chosen >= 2:
        model = np.empty((n_chosen, n_ch))
        rank = np.empty(n_chosen)
        for i in range(n_chosen):
            for c in range(n_ch):
                r_t = 0.0
                r_r = 0.0
                for j in range(d):
                    r_t += (f_position[i, j] - transmitters[c, j]) ** 2
                    r_r += (f_position[i, j] - receivers[c, j]) ** 2
                model[i, c] = np.sqrt(r_t) + np.sqrt(r_r)
            n_shared = 0
            for c in range(n_ch):
                n_shared += f_use[i, c] == SHARED
            value = f_chi2[i]
            if np.isnan(value):
                value = 1e6
            elif np.isinf(value):
                value = np.finfo(np.float64).max if value > 0 else -np.finfo(np.float64).max
            rank[i] = n_shared * 1e6 + value
        drop = np.zeros(n_chosen, dtype=np.bool_)
        for i in range(n_chosen):
            for j in range(i + 1, n_chosen):
                close = True
                for c in range(n_ch):
                    close = close and abs(model[i, c] - model[j, c]) <= merge_reach
                if close and not (drop[i] or drop[j]):
                    drop[i if rank[i] > rank[j] else j] = True
        good &= ~drop
    return True, f_echo, f_use, f_position, f_covariance, f_chi2, f_converged, good


@njit(cache=True, inline="always")
def _measure(
    paths: NDArray[np.float64],  # (E,), m
    sigmas: NDArray[np.float64],  # (E,), m
    offset: NDArray[np.int64],  # (C + 1,)
    echo: NDArray[np.int64],  # (C,)
    use: NDArray[np.int8],  # (C,)
    merge_sigma: float,
    measured: NDArray[np.float64],  # (C,) out, m
    weights: NDArray[np.float64],  # (C,) out
) -> int:  # pragma: no cover - compiled
    """locate._measurements for one candidate into ``measured``/``weights``; returns the channels used."""
    n_used = 0
    for c in range(echo.shape[0]):
        if use[c] == NONE:
            measured[c] = 0.0
            weights[c] = 0.0
            continue
        n_used += 1
        k = offset[c] + echo[c]
        sigma = sigmas[k]
        if merge_sigma >= 0.0 and use[c] == SHARED:
            sigma = np.hypot(sigma, merge_sigma)
        measured[c] = paths[k]
        weights[c] = 1.0 / sigma**2
    return n_used


@njit(cache=True, error_model="numpy")  # a zero SNR divides as numpy does (inf, no exception)
def path_sigmas(
    snr_db: NDArray[np.float64], speed: float, prior_variance: float, omega: float
) -> Any:  # pragma: no cover
    """locate.path_sigmas_m, m, from the SNRs (dB), the carrier's angular frequency ``omega``
    (rad/s) and the a-priori variance (m^2): the same operations in the same order, one loop
    instead of eight numpy calls. The linear SNR is libm's power, which differs from numpy's
    in the last bit for about one value in twenty: every compiled path takes it from here, so
    they agree with each other to the bit, and with the numpy reference to 4 ulps."""
    sigmas = np.empty(snr_db.shape[0])
    for i in range(snr_db.shape[0]):
        snr = 10.0 ** (snr_db[i] / 10.0)
        phase = speed / (omega * np.sqrt(2.0 * snr))
        sigmas[i] = np.sqrt(prior_variance + phase * phase)
    return sigmas


@njit(cache=True)
def sort_within_channels(
    paths: NDArray[np.float64], offset: NDArray[np.int64]
) -> Any:  # pragma: no cover - compiled
    """Each channel's paths sorted, and their echo indices: np.lexsort((paths, channel)) of
    locate._seed_candidates (stable insertion sort, NaN last)."""
    sorted_paths = paths.copy()
    sorted_index = np.empty(paths.shape[0], dtype=np.int64)
    for c in range(offset.shape[0] - 1):
        lo = offset[c]
        for i in range(lo, offset[c + 1]):
            value = paths[i]
            j = i - 1
            while j >= lo and (
                sorted_paths[j] > value or (np.isnan(sorted_paths[j]) and not np.isnan(value))
            ):
                sorted_paths[j + 1] = sorted_paths[j]
                sorted_index[j + 1] = sorted_index[j]
                j -= 1
            sorted_paths[j + 1] = value
            sorted_index[j + 1] = i - lo
    return sorted_paths, sorted_index


@njit(cache=True)
def first_of_each(
    echo: NDArray[np.int64], use: NDArray[np.int8], count: int
) -> Any:  # pragma: no cover - compiled
    """Indices (ascending) of the first of every distinct (echo, use) row among the first ``count``."""
    n_ch = echo.shape[1]
    size = 1
    while size < 2 * count + 1:
        size *= 2
    table = np.full(size, -1, dtype=np.int64)
    first = np.empty(count, dtype=np.int64)
    n_first = 0
    for row in range(count):
        # FNV-1a, 32-bit, masked every step: no product overflows int64 (numba wraps
        # silently; numpy scalars, when the kernel runs uncompiled, warn).
        h = 2166136261
        for c in range(n_ch):
            h = ((h ^ (echo[row, c] + 1)) * 16777619) & 0xFFFFFFFF
            h = ((h ^ use[row, c]) * 16777619) & 0xFFFFFFFF
        slot = h & (size - 1)
        while True:
            other = table[slot]
            if other < 0:
                table[slot] = row
                first[n_first] = row
                n_first += 1
                break
            same = True
            for c in range(n_ch):
                same = same and echo[other, c] == echo[row, c] and use[other, c] == use[row, c]
            if same:
                break
            slot = (slot + 1) & (size - 1)
    return first[:n_first]


@njit(cache=True)
def candidates(
    geometry: KernelGeometry,
    paths: NDArray[np.float64],  # (E,) every channel's echoes, m
    sigmas: NDArray[np.float64],  # (E,), m
    amplitudes: NDArray[np.float64],  # (E,) or (0,): none
    offset: NDArray[np.int64],  # (C + 1,) channel c's echoes at offset[c]:offset[c + 1]
    tail: AssociationTail,
    node_limit: int,
    max_rows: int,
) -> Any:  # pragma: no cover - compiled
    """Steps 1-3 of locate.associate (the arguments of :func:`associate`): seeds (sorted,
    deduplicated) and refined. Returns (overflow, candidates): ``overflow`` more seed rows
    than ``max_rows`` (rounded up to 4096 x 4^k; no candidates then), ``candidates`` =
    refined (echo, use, positions, covariances, chi2, converged, amplitude_chi2).
    ``geometry`` and ``tail`` (locate.KernelGeometry, locate.AssociationTail) are read by
    name into the flat parameters of the kernels below."""
    transmitters, receivers = geometry.transmitters, geometry.receivers
    transmitter_axes, receiver_axes = geometry.transmitter_axes, geometry.receiver_axes
    boresight, required = geometry.boresight, geometry.required
    seeds, window_low, window_high = tail.seeds, tail.window_low, tail.window_high
    cos_fov, k_gate, merge_reach, merge_sigma = tail.cos_fov, tail.k_gate, tail.merge_reach, tail.merge_sigma
    gates, check_beams, min_own = tail.gates, tail.check_beams, tail.min_own
    amplitude_log_sigma = tail.amplitude_log_sigma
    sorted_paths, sorted_index = sort_within_channels(paths, offset)
    limit = np.int64(4096)
    while limit < max_rows:
        limit *= 4
    # A few dozen rows are usual: start small, again with 4 times more when too small
    # (growing the outputs inside the seed loop slows the loop down).
    capacity = np.int64(256)
    while True:
        echo, use, points, count, overflow = seed_candidates(
            transmitters,
            receivers,
            transmitter_axes,
            receiver_axes,
            boresight,
            required,
            paths,
            sigmas,
            offset,
            sorted_paths,
            sorted_index,
            seeds,
            window_low,
            window_high,
            cos_fov,
            k_gate,
            merge_reach,
            min_own,
            capacity,
        )
        if not overflow or capacity >= limit:
            break
        capacity *= 4
    # The same object comes from several seeds: keep one of each echo set (none on overflow).
    first = first_of_each(echo, use, 0 if overflow else count)
    refined = refine(
        transmitters,
        receivers,
        transmitter_axes,
        receiver_axes,
        boresight,
        required,
        paths,
        sigmas,
        amplitudes,
        offset,
        echo[first],
        use[first],
        points[first],
        merge_sigma,
        gates,
        check_beams,
        cos_fov,
        min_own,
        np.int64(6),
        amplitude_log_sigma,
    )
    return overflow, refined


@njit(cache=True)
def _nearest_first(
    position: NDArray[np.float64], rows: NDArray[np.int64], origin: NDArray[np.float64]
) -> bool:  # pragma: no cover - compiled
    """Sort ``rows`` by the distance of their ``position`` from ``origin``, nearest first, when
    that order is beyond doubt: every distance squared finite and each more than 1e-9 of
    itself above the one before, far beyond the rounding of any sum of D squares (a few
    1e-16 relative), so that locate's order (numpy's dot, stable sort) is the same;
    False (``rows`` as given) otherwise."""
    n = rows.shape[0]
    d = position.shape[1]
    distance2 = np.empty(n)
    for i in range(n):
        s = 0.0
        for j in range(d):
            s += (position[rows[i], j] - origin[j]) ** 2
        if not np.isfinite(s):
            return False
        distance2[i] = s
    order = np.arange(n)
    for a in range(1, n):
        item = order[a]
        b = a - 1
        while b >= 0 and distance2[order[b]] > distance2[item]:
            order[b + 1] = order[b]
            b -= 1
        order[b + 1] = item
    for a in range(1, n):
        if not distance2[order[a]] - distance2[order[a - 1]] > 1e-9 * distance2[order[a]]:
            return False
    sorted_rows = rows[order]
    rows[:] = sorted_rows
    return True


@njit(cache=True, nogil=True)
def associate(
    geometry: KernelGeometry,
    paths: NDArray[np.float64],  # (E,) every channel's echoes, m
    sigmas: NDArray[np.float64],  # (E,), m
    amplitudes: NDArray[np.float64],  # (E,) or (0,): none
    offset: NDArray[np.int64],  # (C + 1,) channel c's echoes at offset[c]:offset[c + 1]
    tail: AssociationTail,
    node_limit: int,
    max_rows: int,
    origin: NDArray[np.float64],  # (D,), m
) -> Any:  # pragma: no cover - compiled
    """Steps 1-4 of locate.associate in one call: :func:`candidates`, then :func:`choose`.

    Returns (status, echo_use, positions, covariances, chi2) of the surviving objects
    only (few arrays: each returned array costs the caller), ``echo_use`` (n, 2 C) the
    rows' echo indices then their use. Status 0 done, the objects nearest ``origin``
    first (:func:`_nearest_first`); 3 done, in the choice's order, as distances too
    close to order here (the caller orders them); 1 more than ``max_rows`` seed rows,
    2 tied weights (the caller chooses from :func:`candidates` with the reference):
    no objects then.
    """
    overflow, refined = candidates(geometry, paths, sigmas, amplitudes, offset, tail, node_limit, max_rows)
    done, echo, use, position, covariance, chi2, _, good = choose(
        geometry.transmitters,
        geometry.receivers,
        geometry.transmitter_axes,
        geometry.receiver_axes,
        geometry.boresight,
        geometry.required,
        paths,
        sigmas,
        amplitudes,
        offset,
        refined[0],
        refined[1],
        refined[2],
        refined[4],
        refined[6],
        tail.merge_sigma,
        tail.merge_reach,
        tail.gates,
        tail.check_beams,
        tail.cos_fov,
        tail.min_own,
        tail.sharing_rounds,
        tail.amplitude_log_sigma,
        node_limit,
    )
    status = 1 if overflow else 0 if done else 2
    rows = np.flatnonzero(good) if status == 0 else np.empty(0, dtype=np.int64)
    if status == 0 and not _nearest_first(position, rows, origin):
        status = 3
    n_ch = offset.shape[0] - 1
    echo_use = np.empty((rows.shape[0], 2 * n_ch), dtype=np.int64)
    for i in range(rows.shape[0]):
        for c in range(n_ch):
            echo_use[i, c] = echo[rows[i], c]
            echo_use[i, n_ch + c] = use[rows[i], c]
    return status, echo_use, position[rows], covariance[rows], chi2[rows]


@njit(cache=True, nogil=True)
def associate_frame(
    arguments: LocateKernelArguments,
    tof: NDArray[np.float64],  # (E,) times of flight, s
    snr_db: NDArray[np.float64],  # (E,) SNRs, dB
    amplitudes: NDArray[np.float64],  # (E,) or (0,): none
    offset: NDArray[np.int64],  # (C + 1,) channel c's echoes at offset[c]:offset[c + 1]
) -> Any:  # pragma: no cover - compiled
    """:func:`associate` on one frame's flat echoes as locate.locate_frame has them: times of
    flight ``tof`` (s) times the speed of sound for the paths and :func:`path_sigmas` of their
    SNRs ``snr_db`` (dB) for their sigmas, in this call. ``arguments``
    (locate.FrameLocator.kernel_arguments) are read by name."""
    speed = arguments.speed_of_sound_m_s
    paths = tof * speed
    sigmas = path_sigmas(snr_db, speed, arguments.prior_variance_m2, arguments.omega_rad_s)
    return associate(
        arguments.geometry,
        paths,
        sigmas,
        amplitudes,
        offset,
        arguments.tail,
        arguments.node_limit,
        arguments.max_rows,
        arguments.origin,
    )
