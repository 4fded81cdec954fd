"""A sensor head drawn: its transducers, their axes and beams, and its capture channels."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Wedge
from numpy.typing import NDArray

from echoloc.io.head import HeadCheck, SensorHead


def _unit_axes(axes: NDArray[np.float64] | None, n: int) -> NDArray[np.float64]:
    """Each transducer's unit axis (z ahead when the head gives none)."""
    if axes is None:
        return np.tile([0.0, 0.0, 1.0], (n, 1))
    rows = np.asarray(axes, dtype=float)
    units: NDArray[np.float64] = rows / np.linalg.norm(rows, axis=1, keepdims=True)
    return units


def _view(
    ax: Axes,
    head: SensorHead,
    check: HeadCheck,
    across: int,
    along: int,
    labels: tuple[str, str],
    beam_length_m: float,
) -> None:
    """One projection: coordinate ``across`` horizontally, ``along`` vertically."""
    header = head.header
    groups = (
        ("transmitter", np.asarray(header.transmitters_m), header.transmitter_axes, "tab:red", "^"),
        ("receiver", np.asarray(header.receivers_m), header.receiver_axes, "tab:blue", "o"),
    )
    labels_at: dict[tuple[float, float], list[str]] = {}
    reach: list[tuple[float, float]] = []
    for name, positions, axes, colour, marker in groups:
        units = _unit_axes(axes, len(positions))
        for i, (position, unit) in enumerate(zip(positions, units, strict=True)):
            u, v = position[across], position[along]
            du, dv = unit[across], unit[along]
            tip = (u + 0.6 * beam_length_m * du, v + 0.6 * beam_length_m * dv)
            reach += [(u, v), tip]
            if check.beam_half_angle_deg is not None and math.hypot(du, dv) > 1e-9:
                centre = math.degrees(math.atan2(dv, du))
                half = check.beam_half_angle_deg
                ax.add_patch(
                    Wedge((u, v), beam_length_m, centre - half, centre + half, color=colour, alpha=0.07, lw=0)
                )
                for side in (centre - half, centre + half):
                    angle = math.radians(side)
                    reach.append((u + beam_length_m * math.cos(angle), v + beam_length_m * math.sin(angle)))
            if math.hypot(du, dv) > 1e-9:
                ax.annotate("", xy=tip, xytext=(u, v), arrowprops={"arrowstyle": "->", "color": colour})
            on_top = 5 if name == "transmitter" else 4  # a transmitter among receivers stays visible
            ax.plot(u, v, marker, color=colour, markersize=9, label=name if i == 0 else None, zorder=on_top)
            text = f"tx {i}" if name == "transmitter" else f"rx {i} (ch {head.channel_order[i]})"
            labels_at.setdefault((round(u, 6), round(v, 6)), []).append(text)
    for (u, v), texts in labels_at.items():  # transducers one behind the other share a label
        ax.annotate(", ".join(texts), (u, v), xytext=(6, 6), textcoords="offset points", fontsize="small")
    points = np.array(reach)
    low, high = points.min(axis=0), points.max(axis=0)
    margin = 0.15 * float(max(high - low)) + 0.01
    ax.set_xlim(low[0] - margin, high[0] + margin)
    ax.set_ylim(low[1] - margin, high[1] + margin)
    ax.set_xlabel(labels[0])
    ax.set_ylabel(labels[1])
    ax.set_aspect("equal", adjustable="box")
    ax.grid(alpha=0.3)


def plot_head(head: SensorHead, check: HeadCheck, path: str | Path) -> Path:
    """Draw ``head``: from above (x-z) and from in front (x-y, y down), each transducer with its
    axis and its -3 dB beam (when the head names a transducer model), each receiver with the
    capture channel it arrives on."""
    positions = np.vstack([head.header.transmitters_m, head.header.receivers_m])
    size = float(np.ptp(positions, axis=0).max()) or 0.1
    beam_length = 1.5 * size
    figure = Figure(figsize=(11, 6.2), layout="constrained")
    above, front = figure.subplots(1, 2)
    _view(above, head, check, 0, 2, ("x, m (right)", "z, m (ahead)"), beam_length)
    above.set_title("from above")
    _view(front, head, check, 0, 1, ("x, m (right)", "y, m (down)"), beam_length)
    front.invert_yaxis()
    front.set_title("from in front (looking along z)")
    front.legend(loc="upper right", fontsize="small")
    beam = (
        "beam unknown (give [transducers] model)"
        if check.beam_half_angle_deg is None
        else f"-3 dB beam ±{check.beam_half_angle_deg:.0f}°"
    )
    figure.suptitle(
        f"{head.name}: {len(head.header.receivers_m)} receivers, "
        f"{head.header.sample_rate_hz / 1e3:g} kHz, range {check.max_range_m:.2f} m, {beam}"
    )
    out = Path(path)
    figure.savefig(out, dpi=110)
    return out
