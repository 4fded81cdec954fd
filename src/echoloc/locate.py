"""Localisation: from path lengths per receiver to 3-D reflector positions.

Geometry (report ch. 3.5 and appendix F, restated in NOTES.md): an echo's path
``l = |p - T| + |p - R|`` puts the reflector on an ellipsoid with foci at the
transmitter T and the receiver R. Intersecting the ellipsoids of three or more
receivers gives ``p``.

- :func:`paired_closed_form` is the report's exact solution for a transmitter at
  the origin between two receiver pairs on the x and y axes.
- :func:`solve_positions` is the general solver for any geometry: a linear start
  from the squared equations ``2 R_i.p - 2 l_i rho = |R_i|^2 - l_i^2`` (rho = |p|,
  coordinates relative to T), with the constraint ``rho = |p|`` closing a
  rank-deficient system (a flat array, or three receivers), then Gauss-Newton on
  the exact model. The covariance is ``(J^T W J)^-1`` with ``W = diag(1/sigma_i^2)``.
- :func:`associate` finds several objects ("peaks to points"): every combination of
  one echo per receiver that can meet in one point is solved, the consistent ones
  (chi-square gate) are taken best first, and each echo is used at most once.
  Ghosts, the crossings of echoes from different objects, do not meet in one point
  for a fourth receiver and are rejected.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import combinations

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from echoloc.echoes import FrameEchoes
from echoloc.errors import GeometryError

_GN_ITERATIONS = 10


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
        Echoes from at least this many receivers make an object (>= 3 in 3-D).
    resolution_m
        Two echoes closer in path than this merge into one detection (the pulse's
        resolution); an object seen by fewer receivers than the array has is kept
        only where each missing echo can be explained by such a merge or by falling
        outside the receiver's window. None: no object with missing receivers.
    carrier_hz
        Carrier frequency for the per-echo phase-noise bound; None skips that term.
    window_m
        (shortest, longest) path each receiver can observe, m.
    boresight
        Unit vector the transducers face; solutions behind the array are rejected.
    """

    path_sigma_m: float = 0.5e-3
    gate_probability: float = 0.999
    min_receivers: int = 3
    resolution_m: float | None = None
    carrier_hz: float | None = None
    window_m: tuple[float, float] = (0.0, np.inf)
    boresight: tuple[float, float, float] = (0.0, 0.0, 1.0)


@dataclass(frozen=True, eq=False)
class LocatedObject:
    """One reflector: position and covariance in the sensor frame, and its support."""

    position_m: NDArray[np.float64]
    covariance_m2: NDArray[np.float64]
    receivers: tuple[int, ...]
    echo_indices: tuple[int, ...]
    chi2: float
    score: float

    @property
    def std_m(self) -> NDArray[np.float64]:
        return np.sqrt(np.diag(self.covariance_m2))


@dataclass(frozen=True, eq=False)
class FrameObjects:
    frame: int
    time_s: float
    objects: tuple[LocatedObject, ...]


# --- closed form -------------------------------------------------------------------


def paired_closed_form(paths_m: NDArray[np.float64], spacing_m: float) -> NDArray[np.float64]:
    """Exact position for T at the origin and R1..R4 at (+d,0,0), (-d,0,0), (0,+d,0), (0,-d,0).

    ``paths_m`` (..., 4) holds l1..l4. From NOTES.md (report appendix F):
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


# --- general solver ----------------------------------------------------------------


def linear_start(
    transmitter_m: NDArray[np.float64],
    receivers_m: NDArray[np.float64],
    paths_m: NDArray[np.float64],
    boresight: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Closed-form start for paths (n, n_rx) -> positions (n, 3).

    Solves ``2 R_i.p - 2 l_i rho = |R_i|^2 - l_i^2`` (NOTES.md) by least squares. When
    the system is rank-deficient (three receivers, or a flat array where the normal
    column vanishes) the solution is a line ``x0 + s v`` and ``rho^2 = |p|^2`` picks
    the point on it in front of the array.
    """
    rel = receivers_m - transmitter_m
    paths = np.atleast_2d(paths_m)
    n, m = paths.shape
    A = np.empty((n, m, 4))
    A[:, :, :3] = 2 * rel
    A[:, :, 3] = -2 * paths
    b = np.sum(rel**2, axis=1) - paths**2
    u, s, vt = np.linalg.svd(A, full_matrices=True)
    k = min(m, 4)
    ub = np.zeros((n, 4))
    ub[:, :k] = np.einsum("nmk,nm->nk", u[:, :, :k], b)
    s = np.concatenate([s, np.zeros((n, 4 - k))], axis=1)
    safe = np.where(s > 0, s, 1.0)
    # Rank 4: the least-squares solution. Rank 3 (three receivers, a flat array, or
    # receivers that coincide): the particular solution plus s * the null vector.
    full = np.einsum("nkj,nk->nj", vt[:, :4, :], np.where(s > 0, ub / safe, 0.0))
    x0 = np.einsum("nkj,nk->nj", vt[:, :3, :], ub[:, :3] / safe[:, :3])
    v = vt[:, 3, :]
    # |p0 + s vp|^2 - (rho0 + s vr)^2 = 0
    p0, r0, vp, vr = x0[:, :3], x0[:, 3], v[:, :3], v[:, 3]
    qa = np.sum(vp**2, axis=1) - vr**2
    qb = 2 * (np.sum(p0 * vp, axis=1) - r0 * vr)
    qc = np.sum(p0**2, axis=1) - r0**2
    disc = np.sqrt(np.maximum(qb**2 - 4 * qa * qc, 0.0))
    safe_a = np.where(np.abs(qa) > 1e-15, qa, 1e-15)
    roots = np.stack([(-qb + disc) / (2 * safe_a), (-qb - disc) / (2 * safe_a)], axis=1)
    candidates = p0[:, None, :] + roots[..., None] * vp[:, None, :]
    ahead = candidates @ boresight
    constrained = candidates[np.arange(n), np.argmax(ahead, axis=1)]
    rank_four = (s[:, 3] > 1e-6 * s[:, 0]) if m >= 4 else np.zeros(n, dtype=bool)
    p = np.where(rank_four[:, None], full[:, :3], constrained)
    return np.asarray(p + transmitter_m)


def model_paths_m(
    transmitter_m: NDArray[np.float64], receivers_m: NDArray[np.float64], points_m: NDArray[np.float64]
) -> NDArray[np.float64]:
    """Paths T -> p -> R_i for points (n, 3): (n, n_rx)."""
    return np.asarray(
        np.linalg.norm(points_m - transmitter_m, axis=-1)[:, None]
        + np.linalg.norm(points_m[:, None, :] - receivers_m, axis=-1)
    )


@dataclass(frozen=True, eq=False)
class Solution:
    """Batch of solved positions with covariance and chi-square of the residual."""

    position_m: NDArray[np.float64]  # (n, 3)
    covariance_m2: NDArray[np.float64]  # (n, 3, 3)
    chi2: NDArray[np.float64]  # (n,)
    converged: NDArray[np.bool_]  # (n,)


def solve_positions(
    transmitter_m: NDArray[np.float64],
    receivers_m: NDArray[np.float64],
    paths_m: NDArray[np.float64],
    sigma_m: NDArray[np.float64] | float,
    boresight: NDArray[np.float64] | None = None,
) -> Solution:
    """Weighted least-squares positions for paths (n, n_rx), n_rx >= 3.

    Linear start, then Gauss-Newton on ``l_i = |p - T| + |p - R_i|`` with Jacobian rows
    ``(p - T)/|p - T| + (p - R_i)/|p - R_i|``.
    """
    transmitter = np.asarray(transmitter_m, dtype=float)
    receivers = np.asarray(receivers_m, dtype=float)
    paths = np.atleast_2d(np.asarray(paths_m, dtype=float))
    if receivers.shape[0] < 3 or paths.shape[1] != receivers.shape[0]:
        raise GeometryError(
            f"need paths from >= 3 receivers matching the receivers given, "
            f"got {paths.shape} for {receivers.shape}"
        )
    axis = np.array([0.0, 0.0, 1.0]) if boresight is None else np.asarray(boresight, float)
    sigma = np.broadcast_to(np.asarray(sigma_m, dtype=float), paths.shape)
    weights = 1.0 / sigma**2
    p = linear_start(transmitter, receivers, paths, axis)
    step = np.full(len(p), np.inf)
    for _ in range(_GN_ITERATIONS):
        jac, residual = _jacobian_residual(transmitter, receivers, paths, p)
        normal = np.einsum("nmi,nm,nmj->nij", jac, weights, jac)
        rhs = np.einsum("nmi,nm,nm->ni", jac, weights, residual)
        delta = _solve_3x3(normal, rhs)
        p = p + delta
        step = np.linalg.norm(delta, axis=1)
        if np.all(step < 1e-10):
            break
    jac, residual = _jacobian_residual(transmitter, receivers, paths, p)
    normal = np.einsum("nmi,nm,nmj->nij", jac, weights, jac)
    covariance = _invert_3x3(normal)
    chi2 = np.sum(residual**2 * weights, axis=1)
    converged = np.isfinite(chi2) & (step < 1e-6) & np.all(np.isfinite(covariance), axis=(1, 2))
    return Solution(p, covariance, chi2, converged)


def _jacobian_residual(
    transmitter: NDArray[np.float64],
    receivers: NDArray[np.float64],
    paths: NDArray[np.float64],
    p: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    to_p = p - transmitter
    r_tx = np.linalg.norm(to_p, axis=1)
    from_rx = p[:, None, :] - receivers
    r_rx = np.linalg.norm(from_rx, axis=2)
    with np.errstate(invalid="ignore", divide="ignore"):
        jac = to_p[:, None, :] / r_tx[:, None, None] + from_rx / r_rx[..., None]
    residual = paths - (r_tx[:, None] + r_rx)
    return jac, residual


def _invertible(a: NDArray[np.float64]) -> NDArray[np.bool_]:
    """Which of the (n, 3, 3) matrices are finite and well enough conditioned to solve."""
    ok = np.all(np.isfinite(a), axis=(1, 2))
    if np.any(ok):
        condition = np.full(len(a), np.inf)
        condition[ok] = np.linalg.cond(a[ok])
        ok &= condition < 1e12
    return np.asarray(ok, dtype=bool)


def _solve_3x3(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    out = np.full(b.shape, np.nan)
    ok = _invertible(a)
    if np.any(ok):
        out[ok] = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]
    return out


def _invert_3x3(a: NDArray[np.float64]) -> NDArray[np.float64]:
    out = np.full(a.shape, np.nan)
    ok = _invertible(a)
    if np.any(ok):
        out[ok] = np.linalg.inv(a[ok])
    return out


# --- association -------------------------------------------------------------------


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


def _enumerate_combinations(
    paths: list[NDArray[np.float64]],
    sigmas: list[NDArray[np.float64]],
    receivers_m: NDArray[np.float64],
    direct_m: NDArray[np.float64],
    max_missing: int,
) -> NDArray[np.int64]:
    """All choices of one echo index (or -1: none) per receiver that can meet in a point.

    A point's paths obey ``|l_i - l_j| <= |R_i - R_j|`` (triangle inequality) and
    ``l_i >= |R_i - T|``; pairs breaking these by more than 4 sigma are pruned.
    """
    n_rx = len(paths)
    combos = np.zeros((1, 0), dtype=np.int64)
    for i in range(n_rx):
        feasible = (
            np.flatnonzero(paths[i] >= direct_m[i] - 4 * sigmas[i]) if len(paths[i]) else np.zeros(0, int)
        )
        options = np.concatenate([feasible, [-1]])
        new = np.repeat(combos, len(options), axis=0)
        choice = np.tile(options, len(combos))
        keep = np.ones(len(new), dtype=bool)
        if i > 0:
            mine = choice >= 0
            for j in range(i):
                theirs = new[:, j] >= 0
                both = mine & theirs
                if not np.any(both):
                    continue
                li = paths[i][choice[both]]
                lj = paths[j][new[both, j]]
                tolerance = 4 * np.hypot(sigmas[i][choice[both]], sigmas[j][new[both, j]])
                span = np.linalg.norm(receivers_m[i] - receivers_m[j])
                ok = np.abs(li - lj) <= span + tolerance
                keep[np.flatnonzero(both)[~ok]] = False
        missing = np.sum(new < 0, axis=1) + (choice < 0)
        keep &= missing <= max_missing
        combos = np.column_stack([new[keep], choice[keep]])
    return combos


def associate(
    transmitter_m: NDArray[np.float64],
    receivers_m: NDArray[np.float64],
    paths: list[NDArray[np.float64]],
    sigmas: list[NDArray[np.float64]],
    options: LocateOptions,
    usable: NDArray[np.bool_] | None = None,
    amplitudes: list[NDArray[np.float64]] | None = None,
) -> list[LocatedObject]:
    """Objects from echo paths per receiver ("peaks to points"); each echo used once.

    Stage by stage, from full support down to ``min_receivers``: every combination
    of one echo per receiver of the stage's size that meets in one point (chi-square
    gate, in front of the array) is a candidate, and the set of candidates that
    share no echo with the largest total weight is kept. The weight is the number of
    objects first; the path residual and, when ``amplitudes`` are given, the
    consistency of the echo amplitudes with spherical spreading break ties (a
    "ghost" made of echoes from different reflectors rarely has amplitudes that
    agree). An object with fewer receivers must explain each missing echo: its
    predicted path lies within ``resolution_m`` of an echo already used by an
    object of an earlier stage (the two echoes merged), or outside the window.
    """
    n_rx = len(receivers_m)
    usable = np.ones(n_rx, dtype=bool) if usable is None else np.asarray(usable, dtype=bool)
    active = np.flatnonzero(usable)
    if len(active) < options.min_receivers:
        return []
    rx = receivers_m[active]
    act_paths = [np.asarray(paths[i], float) for i in active]
    act_sigmas = [np.asarray(sigmas[i], float) for i in active]
    act_amplitudes = None if amplitudes is None else [np.asarray(amplitudes[i], float) for i in active]
    direct = np.linalg.norm(rx - transmitter_m, axis=1)
    allow_missing = len(active) - options.min_receivers if options.resolution_m is not None else 0
    combos = _enumerate_combinations(act_paths, act_sigmas, rx, direct, allow_missing)
    boresight = np.asarray(options.boresight, dtype=float)
    objects: list[LocatedObject] = []
    used: set[tuple[int, int]] = set()
    for size in range(len(active), len(active) - allow_missing - 1, -1):
        candidates: list[_Candidate] = []
        for subset in combinations(range(len(active)), size):
            present = np.zeros(len(active), dtype=bool)
            present[list(subset)] = True
            rows = combos[np.all((combos >= 0) == present, axis=1)]
            cols = list(subset)
            if used:
                free = np.ones(len(rows), dtype=bool)
                for c in cols:
                    free &= ~np.isin(rows[:, c], [e for r, e in used if r == c])
                rows = rows[free]
            if len(rows) == 0:
                continue
            candidates.extend(
                _solve_candidates(
                    transmitter_m,
                    rx,
                    cols,
                    rows,
                    act_paths,
                    act_sigmas,
                    act_amplitudes,
                    used,
                    options,
                    boresight,
                    present,
                )
            )
        for index in _best_disjoint(candidates):
            candidate = candidates[index]
            used |= candidate.echoes
            obj = candidate.obj
            objects.append(
                LocatedObject(
                    position_m=obj.position_m,
                    covariance_m2=obj.covariance_m2,
                    receivers=tuple(int(active[c]) for c in obj.receivers),
                    echo_indices=obj.echo_indices,
                    chi2=obj.chi2,
                    score=len(obj.receivers) / n_rx * obj.score,
                )
            )
    objects.sort(key=lambda o: float(np.linalg.norm(o.position_m - transmitter_m)))
    return objects


AMPLITUDE_LOG_SIGMA = 0.1
"""Assumed spread of echo amplitudes about the spreading model, natural-log units (10 %)."""


def _solve_candidates(
    transmitter_m: NDArray[np.float64],
    rx: NDArray[np.float64],
    cols: list[int],
    rows: NDArray[np.int64],
    paths: list[NDArray[np.float64]],
    sigmas: list[NDArray[np.float64]],
    amplitudes: list[NDArray[np.float64]] | None,
    used: set[tuple[int, int]],
    options: LocateOptions,
    boresight: NDArray[np.float64],
    present: NDArray[np.bool_],
) -> list[_Candidate]:
    """Solve each combination of echoes (rows) for receivers ``cols``; keep the plausible ones."""
    path_matrix = np.stack([paths[c][rows[:, c]] for c in cols], axis=1)
    sigma_matrix = np.stack([sigmas[c][rows[:, c]] for c in cols], axis=1)
    solution = solve_positions(transmitter_m, rx[cols], path_matrix, sigma_matrix, boresight)
    dof = len(cols) - 3
    gate = float(stats.chi2.ppf(options.gate_probability, dof)) if dof > 0 else np.inf
    ahead = (solution.position_m - transmitter_m) @ boresight > 0
    ok = solution.converged & ahead & (solution.chi2 <= gate)
    penalty = np.zeros(len(rows))
    if len(cols) < len(rx):
        used_paths = [np.array([paths[r][e] for r, e in used if r == i]) for i in range(len(rx))]
        explained, penalty = _missing_explained(
            transmitter_m, rx, used_paths, solution.position_m, present, options
        )
        ok &= explained
    amplitude_chi2 = np.zeros(len(rows))
    if amplitudes is not None:
        measured = np.stack([amplitudes[c][rows[:, c]] for c in cols], axis=1)
        r_tx = np.linalg.norm(solution.position_m - transmitter_m, axis=1)
        r_rx = np.linalg.norm(solution.position_m[:, None, :] - rx[cols], axis=2)
        with np.errstate(divide="ignore", invalid="ignore"):
            log_strength = np.log(measured * r_tx[:, None] * r_rx)
        spread = log_strength - np.mean(log_strength, axis=1, keepdims=True)
        amplitude_chi2 = np.nan_to_num(np.sum(spread**2, axis=1) / AMPLITUDE_LOG_SIGMA**2, nan=1e3)
    p_value = stats.chi2.sf(solution.chi2, dof) if dof > 0 else np.ones(len(rows))
    candidates = []
    for k in np.flatnonzero(ok):
        # More objects wins; residuals only break ties (each term stays below 0.1).
        tie_break = 1e-3 * min(
            float(solution.chi2[k]) / max(gate if np.isfinite(gate) else 1.0, 1.0)
            + float(amplitude_chi2[k]) / len(cols)
            + float(penalty[k]),
            100.0,
        )
        candidates.append(
            _Candidate(
                echoes=frozenset((c, int(rows[k, c])) for c in cols),
                weight=1.0 - tie_break,
                obj=LocatedObject(
                    position_m=solution.position_m[k],
                    covariance_m2=solution.covariance_m2[k],
                    receivers=tuple(cols),
                    echo_indices=tuple(int(rows[k, c]) for c in cols),
                    chi2=float(solution.chi2[k]),
                    score=float(p_value[k]),
                ),
            )
        )
    return candidates


@dataclass(frozen=True, eq=False)
class _Candidate:
    echoes: frozenset[tuple[int, int]]  # (receiver, echo index) pairs it uses
    weight: float
    obj: LocatedObject


def _best_disjoint(candidates: list[_Candidate], node_limit: int = 50_000) -> list[int]:
    """Indices of the heaviest set of candidates that share no echo (weighted set packing).

    Solved exactly by branch and bound on each connected group of conflicting
    candidates. The bound is the best weight per echo times the echoes still free,
    which is tight because every candidate weighs about its number of echoes. Past
    ``node_limit`` steps in a group the best set found so far is kept (never worse
    than the greedy choice it starts from).
    """
    n = len(candidates)
    conflicts = [
        {j for j in range(n) if j != i and candidates[i].echoes & candidates[j].echoes} for i in range(n)
    ]
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
        chosen.extend(_pack_group(sorted(group, key=lambda i: -candidates[i].weight), candidates, node_limit))
    return chosen


def _pack_group(group: list[int], candidates: list[_Candidate], node_limit: int) -> list[int]:
    """Branch and bound over one group of candidates, heaviest first."""
    items = [candidates[i] for i in group]
    per_echo = max(max(c.weight / len(c.echoes) for c in items), 0.0)
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

    def branch(k: int, used: frozenset[tuple[int, int]], total: float) -> None:
        nonlocal best, best_weight, steps
        steps += 1
        if total > best_weight + 1e-12:
            best, best_weight = list(picked), total
        if k == len(items) or steps > node_limit:
            return
        if total + per_echo * len(reachable[k] - used) <= best_weight + 1e-12:
            return
        item = items[k]
        if item.weight > 0 and not (item.echoes & used):
            picked.append(k)
            branch(k + 1, used | item.echoes, total + item.weight)
            picked.pop()
        branch(k + 1, used, total)

    branch(0, frozenset(), 0.0)
    return [group[k] for k in best]


def _missing_explained(
    transmitter_m: NDArray[np.float64],
    receivers_m: NDArray[np.float64],
    paths: list[NDArray[np.float64]],
    points_m: NDArray[np.float64],
    present: NDArray[np.bool_],
    options: LocateOptions,
) -> tuple[NDArray[np.bool_], NDArray[np.float64]]:
    """For each point: does every receiver without an echo have a reason not to show one?

    The reason is an echo on that receiver (``paths``: the echoes already used by
    other objects) within ``resolution_m`` of the predicted path, so that the two
    echoes merged, or a predicted path outside the receiver's window.
    Also returns the summed gaps in units of the resolution (0 for outside), a
    measure of how well the merges explain the missing echoes.
    """
    assert options.resolution_m is not None
    predicted = model_paths_m(transmitter_m, receivers_m, points_m)
    explained = np.ones(len(points_m), dtype=bool)
    penalty = np.zeros(len(points_m))
    low, high = options.window_m
    for i in np.flatnonzero(~present):
        outside = (predicted[:, i] < low) | (predicted[:, i] > high)
        if len(paths[i]):
            gap = np.min(np.abs(predicted[:, i, None] - paths[i][None, :]), axis=1) / options.resolution_m
        else:
            gap = np.full(len(points_m), np.inf)
        merged = gap <= 1.0
        explained &= outside | merged
        penalty += np.where(outside, 0.0, np.minimum(gap, 1.0))
    return explained, penalty


def locate_frame(
    frame_echoes: FrameEchoes,
    transmitter_m: NDArray[np.float64],
    receivers_m: NDArray[np.float64],
    options: LocateOptions,
    usable: NDArray[np.bool_] | None = None,
) -> FrameObjects:
    """Objects of one frame from its echoes."""
    c = frame_echoes.speed_of_sound_m_s
    paths = [ch.tof_s * c for ch in frame_echoes.channels]
    sigmas = [path_sigmas_m(ch.snr_db, c, options) for ch in frame_echoes.channels]
    amplitudes = [ch.amplitude for ch in frame_echoes.channels]
    objects = associate(transmitter_m, receivers_m, paths, sigmas, options, usable, amplitudes)
    return FrameObjects(frame_echoes.frame, frame_echoes.time_s, tuple(objects))
