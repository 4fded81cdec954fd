"""Compiled inner loops of :mod:`echoloc.locate` (numba): seeds, attachment and Gauss-Newton.

Association touches hundreds of tiny systems per frame (3x3 solves, one per echo
combination). As numpy calls each costs microseconds of overhead, which kept a
frame of five objects at ~2.5 ms; compiled, the same arithmetic takes tens of
microseconds. The formulas are those documented in :mod:`echoloc.locate`; this
module holds only their loops. Every function works in D = 2 or 3 dimensions.

``cache=True`` keeps the machine code in ``__pycache__``: the first call in a fresh
environment compiles (a few seconds), later processes load it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numba import njit

OWN, SHARED, NONE = 0, 1, 2


@njit(cache=True)
def _solve(a: Any, b: Any, x: Any) -> bool:  # pragma: no cover - compiled
    """Solve the small system a x = b by Gaussian elimination with partial pivoting; False if singular."""
    return _solve_in_place(a.copy(), b.copy(), x)


@njit(cache=True)
def _solve_in_place(m: Any, v: Any, x: Any) -> bool:  # pragma: no cover - compiled
    """:func:`_solve` overwriting ``m`` and ``v`` (no allocation: called per echo combination)."""
    n = m.shape[0]
    for col in range(n):
        pivot = col
        for row in range(col + 1, n):
            if abs(m[row, col]) > abs(m[pivot, col]):
                pivot = row
        if m[pivot, col] == 0.0 or not np.isfinite(m[pivot, col]):
            return False
        if pivot != col:
            for k in range(n):
                m[col, k], m[pivot, k] = m[pivot, k], m[col, k]
            v[col], v[pivot] = v[pivot], v[col]
        for row in range(col + 1, n):
            f = m[row, col] / m[col, col]
            for k in range(col, n):
                m[row, k] -= f * m[col, k]
            v[row] -= f * v[col]
    for row in range(n - 1, -1, -1):
        s = v[row]
        for k in range(row + 1, n):
            s -= m[row, k] * x[k]
        x[row] = s / m[row, row]
    return True


@njit(cache=True)
def _det(a: Any) -> float:  # pragma: no cover - compiled
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


@njit(cache=True)
def _well_conditioned(normal: Any) -> bool:  # pragma: no cover - compiled
    """det > 1e-12 x product of the diagonal (Hadamard's bound): not near-singular."""
    bound = 1.0
    for i in range(normal.shape[0]):
        if not normal[i, i] > 0.0:
            return False
        bound *= normal[i, i]
    return bool(np.isfinite(bound) and _det(normal) > 1e-12 * bound)


@njit(cache=True)
def _exact(t: Any, receivers: Any, paths: Any, points: Any) -> int:  # pragma: no cover - compiled
    """Points meeting D paths exactly (locate.exact_solutions for one row); returns how many (0-2)."""
    d = paths.shape[0]
    return _exact_work(t, receivers, paths, points, np.empty((4 * d + 4, d + 1)))


@njit(cache=True)
def _exact_work(t: Any, receivers: Any, paths: Any, points: Any, work: Any) -> int:  # pragma: no cover
    """:func:`_exact` in the scratch rows ``work`` (4 D + 4, D + 1): no allocation per combination."""
    d = paths.shape[0]
    m = work[:d, :]
    b = work[d, :d]
    v = work[d + 1, :]
    minor = work[d + 2 : 2 * d + 2, :d]
    gram = work[2 * d + 2 : 3 * d + 2, :d]
    y = work[3 * d + 2, :d]
    u0 = work[3 * d + 3, :]
    scratch = work[3 * d + 4 : 4 * d + 4, :d]
    for i in range(d):
        norm2 = 0.0
        for j in range(d):
            r = receivers[i, j] - t[j]
            m[i, j] = 2.0 * r
            norm2 += r * r
        m[i, d] = -2.0 * paths[i]
        b[i] = norm2 - paths[i] * paths[i]
    # Null vector: v_j = (-1)^j det(M without column j).
    for j in range(d + 1):
        for i in range(d):
            k = 0
            for col in range(d + 1):
                if col != j:
                    minor[i, k] = m[i, col]
                    k += 1
        v[j] = (-1.0) ** j * _det(minor)
    # Particular solution u0 = M^T (M M^T)^-1 b.
    for i in range(d):
        for k in range(d):
            s = 0.0
            for j in range(d + 1):
                s += m[i, j] * m[k, j]
            gram[i, k] = s
    trace = 0.0
    for i in range(d):
        trace += gram[i, i]
    if not abs(_det(gram)) > 1e-18 * max(trace, 1e-30) ** d:
        return 0
    scratch[:, :] = gram
    rhs = minor[0]  # the minors are done with: one row holds a copy of b
    rhs[:] = b
    if not _solve_in_place(scratch, rhs, y):
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


@njit(cache=True)
def _in_beam(point: Any, origin: Any, axis: Any, cos_fov: float) -> bool:  # pragma: no cover - compiled
    along = 0.0
    dist2 = 0.0
    for j in range(point.shape[0]):
        o = point[j] - origin[j]
        along += o * axis[j]
        dist2 += o * o
    return bool(along >= cos_fov * np.sqrt(dist2))


@njit(cache=True)
def seed_candidates(
    transmitters: Any,
    receivers: Any,
    transmitter_axes: Any,
    receiver_axes: Any,
    boresight: Any,
    required: Any,
    flat_paths: Any,
    flat_sigmas: Any,
    offset: Any,
    sorted_paths: Any,
    sorted_index: Any,
    seeds: Any,
    window_low: float,
    window_high: float,
    cos_fov: float,
    k_gate: float,
    merge_reach: float,
    min_own: int,
    capacity: int,
) -> Any:  # pragma: no cover - compiled
    """Steps 1-2 of locate.associate for every seed: (echo, use, points, count, overflow).

    ``flat_paths``/``flat_sigmas`` hold every channel's echoes, channel c's at
    ``offset[c]:offset[c+1]``; ``sorted_paths`` the same sorted within each channel,
    ``sorted_index`` their echo indices.
    """
    n_ch, d = receivers.shape
    echo_out = np.full((capacity, n_ch), -1, dtype=np.int64)
    use_out = np.full((capacity, n_ch), NONE, dtype=np.int8)
    points_out = np.zeros((capacity, d))
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
    jac = np.empty((n_ch, d))
    seed_jac = np.empty((d, d))
    predicted = np.empty(n_ch)
    row_echo = np.empty(n_ch, dtype=np.int64)
    row_use = np.empty(n_ch, dtype=np.int8)
    gain = np.empty(d)
    normal = np.empty((d, d))
    lhs = np.empty((d, d))
    column = np.empty(d)
    work = np.empty((4 * d + 4, d + 1))
    sizes = np.empty(d, dtype=np.int64)
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
        while True:
            # One combination of echoes on the seed channels: triangle-inequality pruning.
            feasible = True
            for k in range(d):
                c = seed[k]
                seed_paths[k] = flat_paths[offset[c] + choice[k]]
                seed_sigmas[k] = flat_sigmas[offset[c] + choice[k]]
                if seed_paths[k] < direct[c] - 4.0 * seed_sigmas[k]:
                    feasible = False
            if feasible:
                for k in range(d):
                    for q in range(k):
                        a, b = seed[k], seed[q]
                        span = 0.0
                        span_t = 0.0
                        for j in range(d):
                            span += (receivers[a, j] - receivers[b, j]) ** 2
                            span_t += (transmitters[a, j] - transmitters[b, j]) ** 2
                        tol = 4.0 * np.sqrt(seed_sigmas[k] ** 2 + seed_sigmas[q] ** 2)
                        if abs(seed_paths[k] - seed_paths[q]) > np.sqrt(span) + np.sqrt(span_t) + tol:
                            feasible = False
            if feasible:
                n_points = _exact_work(t, seed_rx, seed_paths, points, work)
                for r in range(n_points):
                    p = points[r]
                    ahead = 0.0
                    for j in range(d):
                        ahead += (p[j] - transmitters[0, j]) * boresight[j]
                    if not ahead > 0.0:
                        continue
                    ok = True
                    for k in range(d):
                        c = seed[k]
                        ok = ok and _in_beam(p, transmitters[c], transmitter_axes[c], cos_fov)
                        ok = ok and _in_beam(p, receivers[c], receiver_axes[c], cos_fov)
                    if not ok:
                        continue
                    for c in range(n_ch):
                        r_t = 0.0
                        r_r = 0.0
                        for j in range(d):
                            r_t += (p[j] - transmitters[c, j]) ** 2
                            r_r += (p[j] - receivers[c, j]) ** 2
                        r_t = np.sqrt(r_t)
                        r_r = np.sqrt(r_r)
                        predicted[c] = r_t + r_r
                        for j in range(d):
                            jac[c, j] = (p[j] - transmitters[c, j]) / r_t + (p[j] - receivers[c, j]) / r_r
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
                        visible = _in_beam(p, transmitters[c], transmitter_axes[c], cos_fov)
                        visible = visible and _in_beam(p, receivers[c], receiver_axes[c], cos_fov)
                        outside = predicted[c] < window_low or predicted[c] > window_high
                        if not visible or outside:
                            continue  # this channel cannot see the point: no echo, none needed
                        # Prediction variance from the seed: g_c J_s^-1, squared, times sigma^2.
                        for i in range(d):
                            column[i] = jac[c, i]
                            for j in range(d):
                                lhs[i, j] = seed_jac[j, i]
                        if not _solve_in_place(lhs, column, gain):
                            keep = False
                            break
                        var = 0.0
                        for k in range(d):
                            var += gain[k] ** 2 * seed_sigmas[k] ** 2
                        lo, hi = offset[c], offset[c + 1]
                        if hi > lo:
                            pos = lo + np.searchsorted(sorted_paths[lo:hi], predicted[c])
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
            # Next combination (odometer over the seed channels).
            k = d - 1
            while k >= 0:
                choice[k] += 1
                if choice[k] < sizes[k]:
                    break
                choice[k] = 0
                k -= 1
            if k < 0:
                break
    return echo_out, use_out, points_out, count, False


@njit(cache=True)
def gauss_newton(
    transmitters: Any, receivers: Any, paths: Any, weights: Any, start: Any, iterations: int
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


@njit(cache=True)
def _gauss_newton_row(
    transmitters: Any,
    receivers: Any,
    paths: Any,
    weights: Any,
    start: Any,
    iterations: int,
    position: Any,
    covariance: Any,
    work: Any,
) -> Any:  # pragma: no cover - compiled
    """One row of :func:`gauss_newton` into ``position`` (D,) and ``covariance`` (D, D), which
    stay as given (NaN) when the system is singular; returns (chi2, converged).
    ``work`` is scratch of (2 D + 6, D)."""
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
                lhs[:, :] = normal
                _solve_in_place(lhs, unit, column)
                for i in range(d):
                    covariance[i, j] = column[i]
            chi2 = total
            break
        lhs[:, :] = normal
        if not _solve_in_place(lhs, rhs, delta):
            return np.nan, False
        step = 0.0
        for j in range(d):
            p[j] += delta[j]
            step += delta[j] ** 2
        step = np.sqrt(step)
    for j in range(d):
        position[j] = p[j]
    return chi2, bool(step < 1e-6 and np.isfinite(chi2))


@njit(cache=True)
def _fit_row(
    transmitters: Any,
    receivers: Any,
    transmitter_axes: Any,
    receiver_axes: Any,
    boresight: Any,
    paths: Any,
    sigmas: Any,
    offset: Any,
    echo: Any,
    use: Any,
    start: Any,
    merge_sigma: float,
    gates: Any,
    check_beams: bool,
    cos_fov: float,
    iterations: int,
    measured: Any,
    weights: Any,
    position: Any,
    covariance: Any,
    work: Any,
) -> Any:  # pragma: no cover - compiled
    """locate._fit_and_gate for one candidate: (chi2, converged, passes the gate and is in view).

    ``merge_sigma`` < 0: no merged peaks (resolution None).
    """
    n_ch = echo.shape[0]
    n_used = 0
    for c in range(n_ch):
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
                ok = ok and _in_beam(position, transmitters[c], transmitter_axes[c], cos_fov)
                ok = ok and _in_beam(position, receivers[c], receiver_axes[c], cos_fov)
    return chi2, converged, ok


@njit(cache=True)
def refine(
    transmitters: Any,
    receivers: Any,
    transmitter_axes: Any,
    receiver_axes: Any,
    boresight: Any,
    required: Any,
    paths: Any,
    sigmas: Any,
    amplitudes: Any,
    offset: Any,
    echo: Any,
    use: Any,
    start: Any,
    merge_sigma: float,
    gates: Any,
    check_beams: bool,
    cos_fov: float,
    min_own: int,
    iterations: int,
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
        args = (transmitters, receivers, transmitter_axes, receiver_axes, boresight, paths, sigmas, offset)
        fit = (start[row], merge_sigma, gates, check_beams, cos_fov, iterations)
        scratch = (measured, weights, position, covariance, work)
        chi2, converged, ok = _fit_row(*args, row_echo, row_use, *fit, *scratch)
        if not ok and optional:
            own = 0
            for c in range(n_ch):
                if not required[c]:
                    row_use[c] = NONE
                if row_use[c] == NONE:
                    row_echo[c] = -1
                own += row_use[c] == OWN
            if own >= min_own:
                chi2, converged, ok = _fit_row(*args, row_echo, row_use, *fit, *scratch)
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
