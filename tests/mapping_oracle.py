"""The numpy statement of the occupancy map's compiled channel update
(``echoloc.maps._mapping_kernels.channel_update``), for one channel on a fresh frame.

A test-only oracle: ``tests/maps/test_mapping.py`` holds the compiled loop to it, and
``benchmarks/bench_mapping.py`` times the two side by side. It lives with the tests, out
of the installed package.
"""

from __future__ import annotations

import numpy as np


def channel_update_reference(
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
    hit_axes: np.ndarray,
    clear_cos: float,
    silent_clear: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The numpy statement of ``channel_update`` for one channel on a fresh frame.

    Returns the flat indices of the touched cells, their occupied evidence (sum over
    echoes), their clearing (0 where none), whether the channel's arc passes through
    them and whether they lie near the beam's axis (``central``); the tests hold the
    compiled loop to it and the benchmark compares their speed.
    """
    axes = [origin[a] + (np.arange(lower[a], upper[a]) + 0.5) * cell_m for a in range(3)]
    px, py, pz = np.meshgrid(*axes, indexing="ij")
    index = np.stack(np.meshgrid(*(np.arange(lower[a], upper[a]) for a in range(3)), indexing="ij"), -1)
    p = np.stack([px, py, pz], -1).reshape(-1, 3)
    index = index.reshape(-1, 3)
    dt = p - transmitter
    dr = p - receiver
    r_t = np.linalg.norm(dt, axis=1)
    r_r = np.linalg.norm(dr, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_t = dt @ tx_axis / r_t
        cos_r = dr @ rx_axis / r_r
    path = r_t + r_r
    grid = np.linspace(cos_null, 1.0, len(beam_table))

    def lobe(c: np.ndarray) -> np.ndarray:
        return np.where(c > cos_null, np.interp(np.clip(c, cos_null, 1.0), grid, beam_table), 0.0)

    gain = lobe(cos_t) * lobe(cos_r)
    ok = (
        (r_t > 0)
        & (r_r > 0)
        & (cos_t > cos_null)
        & (path <= reach_m)
        & (path >= blind_m)
        & (gain >= min_gain)
    )
    cells = (index[:, 0] * shape[1] + index[:, 1]) * shape[2] + index[:, 2]
    g = (dt / r_t[:, None]) + (dr / r_r[:, None])
    sigma2 = path_sigma_m**2 + (0.5 * cell_m * np.linalg.norm(g, axis=1)) ** 2
    clear = ok & (path < free_below_m - free_margin_sigmas * np.sqrt(sigma2))
    free = np.where(clear, free_gain * gain, 0.0)
    heard = hit_axes[cells]
    norm = np.linalg.norm(heard, axis=1)
    oblique = (norm > 0) & (heard @ tx_axis < clear_cos * norm)
    free = np.where(oblique, free * silent_clear, free)
    offset = path[:, None] - echo_paths_m[None, :]
    near = (np.abs(offset) <= arc_sigmas * np.sqrt(sigma2)[:, None]) & (ok & ~clear)[:, None]
    prob = 0.5 + hit_gain * gain[:, None] * np.exp(-0.5 * offset**2 / sigma2[:, None])
    occupied = np.where(near, np.log(prob / (1.0 - prob)), 0.0).sum(axis=1)
    on_arc = near.any(axis=1)
    touched = (free < 0) | on_arc
    central = on_arc & (cos_t >= clear_cos)
    return cells[touched], occupied[touched], free[touched], on_arc[touched], central[touched]
