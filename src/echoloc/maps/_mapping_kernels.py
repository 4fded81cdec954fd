"""Compiled inner loops of :mod:`echoloc.maps.mapping` (numba, compiled on first use and cached).

One frame's updates are gathered in scratch arrays the size of the grid (allocated
once per map): ``occupied`` sums the positive log-odds of every channel's echo arcs,
``free`` keeps the strongest (most negative) clearing of any channel, and ``stamp``
marks the cells touched in the current frame so that :func:`apply_frame` visits only
those. That order is what keeps one sensor's clearing from erasing another's
obstacle within a frame: a cell that any channel marks occupied takes no free update.

Across frames, every cell keeps the evidence-weighted sum of the beam axes it was
heard along (``hit_axes``). Specular surfaces (walls, boards, box faces: most of what
a robot meets) return an echo only while the beam's axis is within about its
half-power angle of their normal; a reading whose axis is farther than
``acos(clear_cos)`` from the axes a cell was heard along clears it by only
``silent_clear`` of the usual amount, since silence from there is expected (after
Konolige's MURIEL, *Improved occupancy grids for map building*, Autonomous Robots
4, 1997, which keeps the directions each cell was seen from).

The entry points Python calls once a frame release the GIL (see :mod:`echoloc.tof._echoes_kernels`).
"""

from __future__ import annotations

import math

import numpy as np

from echoloc._jit import njit


@njit(cache=True)
def _touch(cell: int, stamp: np.ndarray, frame_id: int, touched: np.ndarray, n_touched: int) -> int:
    if stamp[cell] != frame_id:
        stamp[cell] = frame_id
        touched[n_touched] = cell
        n_touched += 1
    return n_touched


@njit(cache=True)
def _beam_gain(cos_angle: float, cos_null: float, table: np.ndarray) -> float:
    """One-way main-lobe directivity from ``table`` (sampled uniformly in cos from cos_null to 1)."""
    if cos_angle <= cos_null:
        return 0.0
    n = table.shape[0]
    position = (cos_angle - cos_null) / (1.0 - cos_null) * (n - 1)
    k = int(position)
    if k >= n - 1:
        return float(table[n - 1])
    frac = position - k
    return float(table[k] * (1.0 - frac) + table[k + 1] * frac)


@njit(cache=True)
def _column_range(
    alpha: float, rho2: float, az: float, cos_null: float, radius2: float
) -> tuple[float, float]:
    """A range of ``u`` holding every point of a column inside the cone and the ball.

    The column is the line ``d(u) = (dx, dy, u)`` from the apex (``alpha = dx ax + dy
    ay``, ``rho2 = dx² + dy²``); the cone is ``d·a >= cos_null |d|`` (one nappe: convex,
    so the line meets it in one interval); the ball ``|d|² <= radius2``. Returns
    (lo, hi), empty when lo > hi; a superset is fine, the caller tests every cell.
    """
    if rho2 > radius2:
        return 1.0, -1.0
    half = math.sqrt(radius2 - rho2)
    lo, hi = -half, half
    # The half-space alpha + az u >= 0.
    if az > 0.0:
        lo = max(lo, -alpha / az)
    elif az < 0.0:
        hi = min(hi, -alpha / az)
    elif alpha < 0.0:
        return 1.0, -1.0
    if lo > hi:
        return lo, hi
    # (alpha + az u)² - c² (rho2 + u²) >= 0: a u² + b u + c0 >= 0.
    c2 = cos_null * cos_null
    a = az * az - c2
    b = 2.0 * alpha * az
    c0 = alpha * alpha - c2 * rho2
    if abs(a) < 1e-12:
        if abs(b) < 1e-12:
            return (lo, hi) if c0 >= 0.0 else (1.0, -1.0)
        root = -c0 / b
        return (max(lo, root), hi) if b > 0.0 else (lo, min(hi, root))
    disc = b * b - 4.0 * a * c0
    if disc < 0.0:
        return (lo, hi) if a > 0.0 else (1.0, -1.0)
    sq = math.sqrt(disc)
    r1 = (-b - sq) / (2.0 * a)
    r2 = (-b + sq) / (2.0 * a)
    if r1 > r2:
        r1, r2 = r2, r1
    if a < 0.0:
        return max(lo, r1), min(hi, r2)
    # Two rays (-inf, r1] and [r2, inf); the half-space keeps the nappe's, take the hull.
    left_lo, left_hi = lo, min(hi, r1)
    right_lo, right_hi = max(lo, r2), hi
    left = left_lo <= left_hi
    right = right_lo <= right_hi
    if left and right:
        return lo, hi
    if left:
        return left_lo, left_hi
    if right:
        return right_lo, right_hi
    return 1.0, -1.0


@njit(cache=True, nogil=True)
def channel_update(
    origin: np.ndarray,
    cell_m: float,
    shape: np.ndarray,
    lower: np.ndarray,
    upper: np.ndarray,
    transmitter: np.ndarray,
    receiver: np.ndarray,
    tx_axis: np.ndarray,
    rx_axis: np.ndarray,
    cos_null: float,
    beam_table: np.ndarray,
    min_gain: float,
    free_below_m: float,
    free_margin_sigmas: float,
    blind_m: float,
    echo_paths_m: np.ndarray,
    path_sigma_m: float,
    arc_sigmas: float,
    reach_m: float,
    hit_gain: float,
    free_gain: float,
    occupied: np.ndarray,
    free: np.ndarray,
    support: np.ndarray,
    central: np.ndarray,
    hit_axes: np.ndarray,
    clear_cos: float,
    silent_clear: float,
    stamp: np.ndarray,
    frame_id: int,
    touched: np.ndarray,
    n_touched: int,
) -> int:
    """Inverse sensor model of one transmitter-receiver channel over the cells in [lower, upper).

    A cell at ``p`` with path ``L = |p - T| + |p - R|`` inside both beams (two-way
    gain ``w = D_T D_R >= min_gain``) and beyond the blind zone gets

    - log-odds ``free_gain * w`` (``free_gain`` = logit of the free probability, < 0)
      when ``L`` is shorter than ``free_below_m - free_margin_sigmas * s`` (the first
      echo less ``arc_sigmas`` of the cell's own ``s`` below, or the clearing range of
      a channel with no echo and no margin): nothing detectable lies there;
    - ``log(p / (1 - p))`` with ``p = 0.5 + hit_gain * w * exp(-(L - L_k)^2 / 2 s^2)``
      for each echo ``L_k`` within ``arc_sigmas`` s, where ``s^2 = path_sigma_m^2 + (|grad L| h / 2)^2``
      widens the arc by the cell's own spread of paths (h the cell size), so that
      the arc cannot fall between cell centres;
    - nothing beyond ``reach_m`` (the last echo plus its uncertainty).

    A clearing of a cell heard before along axes more than ``acos(clear_cos)`` from
    ``tx_axis`` is scaled by ``silent_clear``. ``support`` counts the channels whose
    arcs pass through each cell in this frame; ``central`` marks the arc cells within
    ``acos(clear_cos)`` of the beam's axis (where a wall's echo could have come from).
    Returns the new count of touched cells.
    """
    ny, nz = shape[1], shape[2]
    n_echoes = echo_paths_m.shape[0]
    bx = transmitter[0] - receiver[0]
    by = transmitter[1] - receiver[1]
    bz = transmitter[2] - receiver[2]
    # path <= reach bounds |p - T| by (reach + |T - R|) / 2 (triangle inequality).
    radius = 0.5 * (reach_m + math.sqrt(bx * bx + by * by + bz * bz)) + cell_m
    pad = math.sqrt(3.0) * cell_m
    for i in range(lower[0], upper[0]):
        px = origin[0] + (i + 0.5) * cell_m
        for j in range(lower[1], upper[1]):
            py = origin[1] + (j + 0.5) * cell_m
            # Only the part of the column inside the cone and the ball (a superset).
            cx = px - transmitter[0]
            cy = py - transmitter[1]
            u_lo, u_hi = _column_range(
                cx * tx_axis[0] + cy * tx_axis[1],
                cx * cx + cy * cy,
                tx_axis[2],
                max(0.0, cos_null - 1e-9),
                radius * radius,
            )
            if u_lo > u_hi:
                continue
            k_lo = max(lower[2], math.floor((transmitter[2] + u_lo - pad - origin[2]) / cell_m - 0.5))
            k_hi = min(upper[2], math.ceil((transmitter[2] + u_hi + pad - origin[2]) / cell_m - 0.5) + 1)
            for k in range(k_lo, k_hi):
                pz = origin[2] + (k + 0.5) * cell_m
                dtx = px - transmitter[0]
                dty = py - transmitter[1]
                dtz = pz - transmitter[2]
                r_t = math.sqrt(dtx * dtx + dty * dty + dtz * dtz)
                if r_t <= 0.0:
                    continue
                cos_t = (dtx * tx_axis[0] + dty * tx_axis[1] + dtz * tx_axis[2]) / r_t
                if cos_t <= cos_null:
                    continue
                drx = px - receiver[0]
                dry = py - receiver[1]
                drz = pz - receiver[2]
                r_r = math.sqrt(drx * drx + dry * dry + drz * drz)
                if r_r <= 0.0:
                    continue
                path = r_t + r_r
                if path > reach_m or path < blind_m:
                    continue
                cos_r = (drx * rx_axis[0] + dry * rx_axis[1] + drz * rx_axis[2]) / r_r
                gain = _beam_gain(cos_t, cos_null, beam_table) * _beam_gain(cos_r, cos_null, beam_table)
                if gain < min_gain:
                    continue
                cell = (i * ny + j) * nz + k
                gx = dtx / r_t + drx / r_r
                gy = dty / r_t + dry / r_r
                gz = dtz / r_t + drz / r_r
                spread = 0.5 * cell_m * math.sqrt(gx * gx + gy * gy + gz * gz)
                sigma2 = path_sigma_m * path_sigma_m + spread * spread
                sigma = math.sqrt(sigma2)
                if path < free_below_m - free_margin_sigmas * sigma:
                    value = free_gain * gain
                    hx = hit_axes[cell, 0]
                    hy = hit_axes[cell, 1]
                    hz = hit_axes[cell, 2]
                    norm = math.sqrt(hx * hx + hy * hy + hz * hz)
                    if norm > 0.0 and hx * tx_axis[0] + hy * tx_axis[1] + hz * tx_axis[2] < clear_cos * norm:
                        value *= silent_clear
                    if value < 0.0:
                        n_touched = _touch(cell, stamp, frame_id, touched, n_touched)
                        if value < free[cell]:
                            free[cell] = value
                    continue
                supported = False
                for e in range(n_echoes):
                    offset = path - echo_paths_m[e]
                    if abs(offset) > arc_sigmas * sigma:
                        continue
                    p = 0.5 + hit_gain * gain * math.exp(-0.5 * offset * offset / sigma2)
                    n_touched = _touch(cell, stamp, frame_id, touched, n_touched)
                    occupied[cell] += math.log(p / (1.0 - p))
                    if not supported:
                        supported = True
                        support[cell] += 1
                        if cos_t >= clear_cos:
                            central[cell] = 1
    return n_touched


@njit(cache=True, nogil=True)
def add_supported_evidence(
    cells: np.ndarray,
    evidence: np.ndarray,
    occupied: np.ndarray,
    support: np.ndarray,
    stamp: np.ndarray,
    frame_id: int,
    touched: np.ndarray,
    n_touched: int,
) -> int:
    """Add occupied evidence that needs no arcs to meet (a located object: several channels
    already agree on it) to ``cells``; values of 1e-6 or less are skipped. Returns the new
    count of touched cells."""
    for n in range(cells.shape[0]):
        if evidence[n] <= 1e-6:
            continue
        cell = cells[n]
        n_touched = _touch(cell, stamp, frame_id, touched, n_touched)
        occupied[cell] += evidence[n]
        support[cell] = 255
    return n_touched


@njit(cache=True, nogil=True)
def apply_frame(
    log_odds: np.ndarray,
    updates: np.ndarray,
    occupied: np.ndarray,
    free: np.ndarray,
    support: np.ndarray,
    central: np.ndarray,
    min_support: int,
    hit_axes: np.ndarray,
    tx_axis: np.ndarray,
    touched: np.ndarray,
    n_touched: int,
    clamp_low: float,
    clamp_high: float,
) -> None:
    """Add one frame's updates to the touched cells and reset the scratch arrays.

    A cell on the arcs of at least ``min_support`` channels takes the sum of their
    occupied evidence (and, when it lay near the beam's axis, ``central``, adds
    ``tx_axis`` times it to its ``hit_axes``: an arc's far side says nothing about
    where a wall faces); a cell on
    fewer arcs is left alone (an arc's tail, where the other receivers' ellipsoids
    have parted: not there, but not known free either); the others take the
    strongest clearing. Log-odds are clamped to [clamp_low, clamp_high] (OctoMap's
    clamping, so that a cell can change its mind after a bounded number of contrary
    readings).
    """
    for n in range(n_touched):
        cell = touched[n]
        evidence = occupied[cell]
        enough = support[cell] >= min_support
        near_axis = central[cell] != 0
        support[cell] = 0
        central[cell] = 0
        if evidence > 0.0:
            occupied[cell] = 0.0
            free[cell] = 0.0
            if not enough:
                continue
            delta = evidence
            if near_axis:
                hit_axes[cell, 0] += evidence * tx_axis[0]
                hit_axes[cell, 1] += evidence * tx_axis[1]
                hit_axes[cell, 2] += evidence * tx_axis[2]
        else:
            delta = free[cell]
        value = log_odds[cell] + delta
        if value < clamp_low:
            value = clamp_low
        elif value > clamp_high:
            value = clamp_high
        log_odds[cell] = value
        if updates[cell] < 65535:
            updates[cell] += 1
        occupied[cell] = 0.0
        free[cell] = 0.0
