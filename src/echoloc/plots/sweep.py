"""The picture of a sweep (``echoloc sweep --plot``): a metric against a swept parameter.

A grid draws one line per value of a second parameter (per combination of the others, when
there are more); a random sweep draws its points, coloured by the second parameter. Lengths
are drawn in mm, times in ms; the y axis is logarithmic when the values span more than a
factor of 30 (or as the sweep file's ``[plot]`` says).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import FuncFormatter

from echoloc.scale.sweep import Sweep

_LABELS = {
    "median_error_m": "median position error",
    "p90_error_m": "90th percentile of the position error",
    "rms_error_m": "RMS position error",
    "spread_m": "spread of the position error (3-D std)",
    "rms_range_error_m": "RMS range error",
    "rms_angle_error_deg": "RMS angle error",
    "reported_sigma_m": "reported 3-D σ",
    "sigma_ratio": "real spread / reported σ",
    "recall": "recall",
    "false_rate": "false objects / located objects",
    "located_per_frame": "objects located per frame",
    "time_per_frame_s": "chain time per frame",
}

LOG_SPAN = 30.0
"""The y axis is logarithmic (unless the sweep file says) when the values span more than this."""

MAX_LEGEND = 12
"""Lines named in the legend at most (the rest are drawn, not named)."""


def _scale(metric: str) -> tuple[float, str]:
    """Factor and unit a metric is drawn in."""
    if metric.endswith("_m"):
        return 1e3, "mm"
    if metric.endswith("_s"):
        return 1e3, "ms"
    if metric.endswith("_deg"):
        return 1.0, "°"
    return 1.0, ""


def _numeric(values: Sequence[Any]) -> bool:
    return all(isinstance(v, int | float) and not isinstance(v, bool) for v in values)


def _text(value: Any) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


def plot_sweep(
    sweep: Sweep,
    rows: Sequence[Mapping[str, Any]],
    path: str | Path,
    *,
    metric: str | None = None,
) -> Path:
    """Draw ``metric`` (default: the sweep's ``[plot] y``, else its first metric) against the
    sweep's ``[plot] x`` (default: its first parameter) into ``path``; returns the path."""
    spec = sweep.plot
    y_name = metric or spec.y or sweep.study.metrics[0]
    x_name = spec.x or sweep.parameters[0]
    others = [p for p in sweep.parameters if p != x_name]
    if spec.lines is not None and spec.lines != x_name:
        others.remove(spec.lines)
        others.insert(0, spec.lines)
    factor, unit = _scale(y_name)
    x_values = [row[x_name] for row in rows]
    numeric_x = _numeric(x_values)
    categories = [] if numeric_x else list(dict.fromkeys(_text(v) for v in x_values))

    def x_of(value: Any) -> float:
        return float(value) if numeric_x else float(categories.index(_text(value)))

    y_all = np.array([float(row[y_name]) * factor for row in rows])
    figure = Figure(figsize=(9, 5.6), layout="constrained")
    axis = figure.subplots()
    if sweep.kind == "grid":
        groups: dict[tuple[Any, ...], list[Mapping[str, Any]]] = {}
        for row in rows:
            groups.setdefault(tuple(_text(row[p]) for p in others), []).append(row)
        colours = [f"C{i % 10}" for i in range(len(groups))]
        markers = "osD^v<>ph*"
        for i, (key, members) in enumerate(groups.items()):
            members = sorted(members, key=lambda r: x_of(r[x_name]))
            if len(others) == 1:
                label: str | None = key[0]
            else:
                label = ", ".join(f"{p} = {v}" for p, v in zip(others, key, strict=True)) or None
            axis.plot(
                [x_of(r[x_name]) for r in members],
                [float(r[y_name]) * factor for r in members],
                marker=markers[(i // 10) % len(markers)],
                ms=5,
                lw=1.6,
                color=colours[i],
                label=label if i < MAX_LEGEND else None,
            )
        if others:
            hidden = max(0, len(groups) - MAX_LEGEND)
            title = others[0] if len(others) == 1 else "parameters"
            legend = axis.legend(title=title, fontsize="small", title_fontsize="small", loc="best")
            if hidden:
                legend.set_title(f"{title}; {hidden} more lines not named")
    else:
        xs = [x_of(v) for v in x_values]
        colour_by = others[0] if others else None
        if colour_by is None:
            axis.scatter(xs, y_all, s=22, color="C0")
        else:
            values = [row[colour_by] for row in rows]
            if _numeric(values):
                points = axis.scatter(xs, y_all, s=22, c=[float(v) for v in values], cmap="viridis")
                figure.colorbar(points, ax=axis, label=colour_by)
            else:
                names = list(dict.fromkeys(_text(v) for v in values))
                for i, name in enumerate(names):
                    picked = [k for k, v in enumerate(values) if _text(v) == name]
                    axis.scatter([xs[k] for k in picked], y_all[picked], s=22, color=f"C{i % 10}", label=name)
                axis.legend(title=colour_by, fontsize="small", title_fontsize="small")
    if not numeric_x:
        axis.set_xticks(range(len(categories)), categories, rotation=20 if len(categories) > 4 else 0)
    finite = y_all[np.isfinite(y_all)]
    log_y = spec.log_y
    if log_y is None:
        log_y = (
            bool(len(finite)) and bool(np.all(finite > 0)) and float(finite.max() / finite.min()) > LOG_SPAN
        )
    if log_y and len(finite) and np.all(finite > 0):
        axis.set_yscale("log")
    if spec.log_x and numeric_x and all(x_of(v) > 0 for v in x_values):
        axis.set_xscale("log")
        plain = FuncFormatter(lambda value, _: f"{value:g}")
        axis.xaxis.set_major_formatter(plain)
        axis.xaxis.set_minor_formatter(plain)
        axis.tick_params(axis="x", which="both", labelsize="small")
    label = _LABELS.get(y_name, y_name)
    axis.set_ylabel(f"{label} ({unit})" if unit else label)
    axis.set_xlabel(x_name)
    axis.grid(alpha=0.3, which="both" if log_y else "major")
    frames = sweep.study.frames
    missing = int(np.sum(~np.isfinite(y_all)))
    note = f"; {missing} point{'s' if missing != 1 else ''} without a value" if missing else ""
    axis.set_title(
        f"{label} against {x_name}\n{Path(sweep.source).name}: {len(rows)} points "
        f"({sweep.kind}), {frames} frame{'s' if frames != 1 else ''} each{note}",
        fontsize="medium",
    )
    output = Path(path)
    figure.savefig(output, dpi=110)
    return output
