"""Compiled Gauss-Newton of :mod:`echoloc.localise.surfaces` (numba): point, plane, image and edge fits.

Classifying a frame's echoes fits a handful of hypotheses to a few hundred groups of
four to eight paths; in numpy each step of each fit is a dozen calls on tiny arrays,
whose overhead was the whole cost. Here one call fits every row: per row the
Gauss-Newton of :func:`echoloc.localise.surfaces.fit` (the same step halving and
stopping rule, the same closed-form Jacobians), the chi-square and the covariance
``(J^T W J)^-1``. The formulas are those of :mod:`echoloc.localise.surfaces`, whose numpy
fits the tests hold this module to (``surfaces._COMPILED = False``).
Models: :data:`POINT` ``|P - T| + |P - R|``; :data:`PLANE` ``|V - R|`` with V the
transmitter mirrored in the plane of foot offset F from the reference; :data:`IMAGE`
``|V - R|``; :data:`EDGE` ``sqrt((d_T + d_R)^2 + (e.(R - T))^2)`` for a line along e;
:data:`CORNER` ``|V - R|`` with V the transmitter turned half a turn about the edge through G
with direction ``cos psi a + sin psi b`` ((a, b) across ``G - T_ref``, built from the row's
helper vector), whose Jacobian is a forward difference as in numpy.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from echoloc._jit import njit
from echoloc._linear_kernels import solve_in_place

POINT, PLANE, IMAGE, EDGE, CORNER = 0, 1, 2, 3, 4

_STEP = 1e-6
"""Forward-difference step of the corner's Jacobian (m; rad for the edge angle), as numpy's."""


@njit(cache=True)
def _corner_paths(
    p: NDArray[np.float64],
    tx: NDArray[np.float64],
    rx: NDArray[np.float64],
    reference: NDArray[np.float64],
    helper: NDArray[np.float64],
    paths: NDArray[np.float64],
) -> None:  # pragma: no cover - compiled
    """The corner's paths (m,) for parameters ``(G, psi)``."""
    w = p[:3] - reference
    w = w / np.sqrt(w[0] ** 2 + w[1] ** 2 + w[2] ** 2)
    a = helper - (helper[0] * w[0] + helper[1] * w[1] + helper[2] * w[2]) * w
    a = a / np.sqrt(a[0] ** 2 + a[1] ** 2 + a[2] ** 2)
    b = np.array([w[1] * a[2] - w[2] * a[1], w[2] * a[0] - w[0] * a[2], w[0] * a[1] - w[1] * a[0]])
    e = np.cos(p[3]) * a + np.sin(p[3]) * b
    for i in range(tx.shape[0]):
        along = (tx[i, 0] - p[0]) * e[0] + (tx[i, 1] - p[1]) * e[1] + (tx[i, 2] - p[2]) * e[2]
        total = 0.0
        for k in range(3):
            image = 2.0 * (p[k] + along * e[k]) - tx[i, k]
            total += (image - rx[i, k]) ** 2
        paths[i] = np.sqrt(total)


@njit(cache=True)
def _model(
    model: int,
    p: NDArray[np.float64],
    tx: NDArray[np.float64],
    rx: NDArray[np.float64],
    reference: NDArray[np.float64],
    basis: NDArray[np.float64],
    paths: NDArray[np.float64],
    jacobian: NDArray[np.float64],
) -> None:  # pragma: no cover - compiled
    """Paths (m,) and their Jacobian (m, k) of one parameter vector ``p`` on channels ``tx``, ``rx``.

    ``basis`` holds the edge's axis e and the two directions a, b across it as rows; for the
    corner, its first row is the row's helper vector.
    """
    m = tx.shape[0]
    if model == CORNER:
        _corner_paths(p, tx, rx, reference, basis[0], paths)
        shifted = p.copy()
        moved = np.empty(m)
        for k in range(4):
            shifted[k] = p[k] + _STEP
            _corner_paths(shifted, tx, rx, reference, basis[0], moved)
            for i in range(m):
                jacobian[i, k] = (moved[i] - paths[i]) / _STEP
            shifted[k] = p[k]
        return
    if model == POINT:
        for i in range(m):
            dt = np.sqrt((p[0] - tx[i, 0]) ** 2 + (p[1] - tx[i, 1]) ** 2 + (p[2] - tx[i, 2]) ** 2)
            dr = np.sqrt((p[0] - rx[i, 0]) ** 2 + (p[1] - rx[i, 1]) ** 2 + (p[2] - rx[i, 2]) ** 2)
            paths[i] = dt + dr
            for k in range(3):
                jacobian[i, k] = (p[k] - tx[i, k]) / dt + (p[k] - rx[i, k]) / dr
    elif model == IMAGE:
        for i in range(m):
            d = np.sqrt((p[0] - rx[i, 0]) ** 2 + (p[1] - rx[i, 1]) ** 2 + (p[2] - rx[i, 2]) ** 2)
            paths[i] = d
            for k in range(3):
                jacobian[i, k] = (p[k] - rx[i, k]) / d
    elif model == PLANE:
        h = np.sqrt(p[0] ** 2 + p[1] ** 2 + p[2] ** 2)
        u = p / h
        for i in range(m):
            d = tx[i] - reference
            ud = u[0] * d[0] + u[1] * d[1] + u[2] * d[2]
            height = h - ud
            image = tx[i] + 2.0 * height * u
            offset = image - rx[i]
            length = np.sqrt(offset[0] ** 2 + offset[1] ** 2 + offset[2] ** 2)
            paths[i] = length
            g = offset / length
            gu = g[0] * u[0] + g[1] * u[1] + g[2] * u[2]
            # g . dV/dF = 2 [ (g.u) u^T - (g.u) d^T P / h + (h - u.d) g^T P / h ], P = I - u u^T
            for k in range(3):
                d_projected = (d[k] - ud * u[k]) / h
                g_projected = (g[k] - gu * u[k]) / h
                jacobian[i, k] = 2.0 * (gu * u[k] - gu * d_projected + height * g_projected)
    else:  # EDGE
        for i in range(m):
            ta = tx[i, 0] * basis[1, 0] + tx[i, 1] * basis[1, 1] + tx[i, 2] * basis[1, 2]
            tb = tx[i, 0] * basis[2, 0] + tx[i, 1] * basis[2, 1] + tx[i, 2] * basis[2, 2]
            ra = rx[i, 0] * basis[1, 0] + rx[i, 1] * basis[1, 1] + rx[i, 2] * basis[1, 2]
            rb = rx[i, 0] * basis[2, 0] + rx[i, 1] * basis[2, 1] + rx[i, 2] * basis[2, 2]
            along = (
                (rx[i, 0] - tx[i, 0]) * basis[0, 0]
                + (rx[i, 1] - tx[i, 1]) * basis[0, 1]
                + (rx[i, 2] - tx[i, 2]) * basis[0, 2]
            )
            d_t = np.sqrt((p[0] - ta) ** 2 + (p[1] - tb) ** 2)
            d_r = np.sqrt((p[0] - ra) ** 2 + (p[1] - rb) ** 2)
            total = d_t + d_r
            length = np.sqrt(total**2 + along**2)
            paths[i] = length
            jacobian[i, 0] = total / length * ((p[0] - ta) / d_t + (p[0] - ra) / d_r)
            jacobian[i, 1] = total / length * ((p[1] - tb) / d_t + (p[1] - rb) / d_r)


@njit(cache=True)
def _chi2(
    paths: NDArray[np.float64], measured: NDArray[np.float64], weights: NDArray[np.float64]
) -> float:  # pragma: no cover - compiled
    total = 0.0
    for i in range(paths.shape[0]):
        if weights[i] > 0:
            r = measured[i] - paths[i]
            total += weights[i] * r * r
    return total if np.isfinite(total) else np.inf


@njit(cache=True, nogil=True)
def fit(
    model: int,
    start: NDArray[np.float64],
    measured: NDArray[np.float64],
    weights: NDArray[np.float64],
    tx: NDArray[np.float64],
    rx: NDArray[np.float64],
    reference: NDArray[np.float64],
    bases: NDArray[np.float64],
    iterations: int,
    halvings: int,
    converged: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:  # pragma: no cover - compiled
    """Gauss-Newton of every row: parameters (n, k), covariance (n, k, k) and chi-square (n,).

    ``bases`` (n, 3, 3) is each row's ``basis`` of :func:`_model`.

    ``measured`` and ``weights`` are (n, m), a zero weight leaving a channel out. A step
    that raises the chi-square is halved up to ``halvings`` times; the rows stop together
    when none moved a parameter by more than ``converged`` (as the numpy fit).
    """
    n, k = start.shape
    m = tx.shape[0]
    parameters = start.copy()
    chi2 = np.empty(n)
    covariance = np.full((n, k, k), np.nan)
    paths = np.empty(m)
    jacobian = np.empty((m, k))
    trial_paths = np.empty(m)
    trial_jacobian = np.empty((m, k))
    normal = np.empty((k, k))
    gradient = np.empty(k)
    step = np.empty(k)
    trial = np.empty(k)
    for row in range(n):
        _model(model, parameters[row], tx, rx, reference, bases[row], paths, jacobian)
        chi2[row] = _chi2(paths, measured[row], weights[row])
    active = np.ones(n, dtype=np.bool_)
    for _ in range(iterations):
        largest = 0.0
        for row in range(n):
            if not active[row]:
                continue
            p = parameters[row]
            _model(model, p, tx, rx, reference, bases[row], paths, jacobian)
            for a in range(k):
                gradient[a] = 0.0
                for b in range(k):
                    normal[a, b] = 0.0
            trace = 0.0
            for i in range(m):
                w = weights[row, i]
                if w <= 0:
                    continue
                r = measured[row, i] - paths[i]
                if not np.isfinite(r):
                    continue
                for a in range(k):
                    ja = jacobian[i, a] if np.isfinite(jacobian[i, a]) else 0.0
                    gradient[a] += w * ja * r
                    for b in range(k):
                        jb = jacobian[i, b] if np.isfinite(jacobian[i, b]) else 0.0
                        normal[a, b] += w * ja * jb
            for a in range(k):
                trace += normal[a, a]
            for a in range(k):
                normal[a, a] += trace * 1e-12 + 1e-300
            if not solve_in_place(normal, gradient, step):
                active[row] = False
                continue
            factor = 1.0
            moved = False
            for _ in range(halvings):
                for a in range(k):
                    trial[a] = p[a] + factor * step[a]
                _model(model, trial, tx, rx, reference, bases[row], trial_paths, trial_jacobian)
                trial_chi2 = _chi2(trial_paths, measured[row], weights[row])
                if trial_chi2 <= chi2[row]:
                    size = 0.0
                    for a in range(k):
                        size = max(size, abs(factor * step[a]))
                        p[a] = trial[a]
                    chi2[row] = trial_chi2
                    largest = max(largest, size)
                    moved = True
                    break
                factor *= 0.5
            if not moved:
                active[row] = False
        if largest < converged:
            break
    for row in range(n):
        _model(model, parameters[row], tx, rx, reference, bases[row], paths, jacobian)
        for a in range(k):
            for b in range(k):
                total = 0.0
                for i in range(m):
                    w = weights[row, i]
                    ja = jacobian[i, a] if np.isfinite(jacobian[i, a]) else 0.0
                    jb = jacobian[i, b] if np.isfinite(jacobian[i, b]) else 0.0
                    if w > 0:
                        total += w * ja * jb
                normal[a, b] = total
        if np.all(np.isfinite(normal)):
            covariance[row] = np.linalg.pinv(normal)
    return parameters, covariance, chi2
