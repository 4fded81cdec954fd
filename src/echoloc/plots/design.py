"""Pictures for choosing an array: the report's figures 4.12 and 4.13, and GDOP maps.

One function per picture, each writes one PNG and returns its path (``echoloc
design -o DIR`` draws all three). The object-oriented matplotlib API is used (no
pyplot state, no display needed).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.colors import LogNorm
from matplotlib.figure import Figure
from matplotlib.ticker import FormatStrFormatter

from echoloc.localise.uncertainty import (
    ErrorMap,
    SpacingRecommendation,
    SpacingStudy,
    UncertaintyArea,
    paired_paths,
)


def plot_uncertainty_area(area: UncertaintyArea, path: str | Path) -> Path:
    """Figure 4.12: the two ellipse bands ``l_i +- dl_i`` and the corners a-d of their crossing."""
    d1, d2 = area.spacings_m
    (l1, l2), (e1, e2) = area.paths_m, area.path_errors_m
    figure = Figure(figsize=(12, 5.5), layout="constrained")
    overview, zoom = figure.subplots(1, 2, gridspec_kw={"width_ratios": [1.1, 1]})
    x0, z0 = area.position_m
    # Overview: both ellipses through the point, the transducers.
    span = max(d1, d2, abs(x0)) * 1.6 + 0.05
    u = np.linspace(-span, span, 700)
    v = np.linspace(-0.05 * area.range_m, area.range_m * 1.75, 700)
    uu, vv = np.meshgrid(u, v)
    p1, p2 = paired_paths(np.stack([uu, vv], axis=-1), d1, d2)
    overview.contour(uu, vv, p1, levels=[l1], colors="tab:blue", linewidths=1.2)
    overview.contour(uu, vv, p2, levels=[l2], colors="tab:orange", linewidths=1.2)
    overview.plot([0], [0], "k^", ms=9, label="T (transmitter)")
    overview.plot([d1, -d2], [0, 0], "kv", ms=9, label="R1, R2 (receivers)")
    overview.annotate("R1", (d1, 0), textcoords="offset points", xytext=(6, 6))
    overview.annotate("R2", (-d2, 0), textcoords="offset points", xytext=(6, 6))
    overview.plot([x0], [z0], "r*", ms=12, label="reflector")
    overview.plot([], [], color="tab:blue", label=f"ellipse T-R1, l1 = {l1:.3f} m")
    overview.plot([], [], color="tab:orange", label=f"ellipse T-R2, l2 = {l2:.3f} m")
    overview.set_aspect("equal")
    overview.set_xlabel("x (m)")
    overview.set_ylabel("z, boresight (m)")
    overview.set_title(f"Receivers at +{d1:.3f} m and -{d2:.3f} m; reflector at r = {area.range_m:.3f} m")
    overview.set_ylim(-0.05 * area.range_m, 1.75 * area.range_m)
    overview.legend(loc="upper center", fontsize="small", ncols=2)
    overview.grid(alpha=0.3)

    # Zoom: the bands and corners, in mm about the exact point.
    corners_mm = (area.corners_m - area.position_m) * 1e3
    half_u = max(np.max(np.abs(corners_mm[:, 0])), 1e3 * max(e1, e2)) * 1.8
    half_v = max(np.max(np.abs(corners_mm[:, 1])), 1e3 * max(e1, e2)) * 1.8
    half = max(half_u, half_v)
    u = np.linspace(-half, half, 600)
    v = np.linspace(-half, half, 600)
    uu, vv = np.meshgrid(u, v)
    p1, p2 = paired_paths(np.stack([x0 + uu / 1e3, z0 + vv / 1e3], axis=-1), d1, d2)
    zoom.contourf(uu, vv, np.abs(p1 - l1), levels=[0, e1], colors=["tab:blue"], alpha=0.25)
    zoom.contourf(uu, vv, np.abs(p2 - l2), levels=[0, e2], colors=["tab:orange"], alpha=0.25)
    zoom.contourf(
        uu,
        vv,
        np.maximum(np.abs(p1 - l1) / e1, np.abs(p2 - l2) / e2),
        levels=[0, 1],
        colors="none",
        hatches=["xx"],
    )
    for values, level, colour in ((p1, l1, "tab:blue"), (p2, l2, "tab:orange")):
        zoom.contour(uu, vv, values, levels=[level], colors=colour, linewidths=1.0)
    order = [0, 1, 2, 3, 0]
    zoom.plot(corners_mm[order, 0], corners_mm[order, 1], "k-", lw=0.8)
    lines = []
    offsets = {"a": (-14, 4), "b": (4, -14), "c": (6, 4), "d": (4, 6)}
    for name, (cu, cv), r, theta in zip(
        "abcd", corners_mm, area.corner_range_m, area.corner_angle_rad, strict=True
    ):
        zoom.plot([cu], [cv], "ko", ms=4)
        zoom.annotate(name, (cu, cv), textcoords="offset points", xytext=offsets[name], weight="bold")
        lines.append(
            f"{name}: Δr {1e3 * (r - area.range_m):+.2f} mm, Δθ {np.degrees(theta - area.angle_rad):+.3f}°"
        )
    zoom.text(
        0.98,
        0.98,
        "\n".join(lines),
        transform=zoom.transAxes,
        ha="right",
        va="top",
        fontsize="small",
        family="monospace",
        bbox={"boxstyle": "round", "fc": "white", "alpha": 0.9},
    )
    zoom.plot([0], [0], "r*", ms=10)
    zoom.plot([], [], "s", color="tab:blue", alpha=0.4, label=f"band l1 ± {e1 * 1e3:g} mm")
    zoom.plot([], [], "s", color="tab:orange", alpha=0.4, label=f"band l2 ± {e2 * 1e3:g} mm")
    zoom.set_aspect("equal")
    zoom.set_xlim(-half, half)
    zoom.set_ylim(-half, half)
    zoom.set_xlabel("x - x₀ (mm)")
    zoom.set_ylabel("z - z₀ (mm)")
    zoom.set_title("Uncertainty area (hatched), corners a-d (report fig. 4.12)")
    zoom.legend(loc="lower left", fontsize="small")
    zoom.grid(alpha=0.3)
    output = Path(path)
    figure.savefig(output, dpi=110)
    return output


def plot_spacing_study(
    study: SpacingStudy, recommendation: SpacingRecommendation | None, path: str | Path
) -> Path:
    """Figure 4.13: (a) angle error and (b) range error against spacing, per path error dl1.

    One colour per ``|dl1|``, solid for +dl1 and dashed for -dl1; dotted black the
    first-order values. Panel (a) is ``|dtheta|`` on a log axis, with the criterion of
    :func:`~echoloc.localise.uncertainty.recommended_spacing` (``r |dtheta| = tolerance``) as a
    grey curve: the recommended spacing is where the largest error meets it.
    """
    figure = Figure(figsize=(13, 5.8), layout="constrained")
    angle_axis, range_axis = figure.subplots(1, 2)
    d = study.spacings_m
    errors = study.path_errors_m
    magnitudes = sorted({abs(float(e)) for e in errors if e != 0}, reverse=True)
    for i, e in enumerate(errors):
        if e == 0:
            continue
        colour = f"C{magnitudes.index(abs(float(e))) % 10}"
        style = "-" if e > 0 else "--"
        label = f"Δl1 = {e * 1e3:+g} mm"
        angle_axis.plot(d, np.degrees(np.abs(study.angle_error_rad[i])), style, color=colour, label=label)
        angle_axis.plot(d, np.degrees(np.abs(study.linear_angle_error_rad[i])), ":", color="k", lw=0.9)
        range_axis.plot(d, study.range_error_m[i] * 1e3, style, color=colour, label=label)
        range_axis.plot(d, study.linear_range_error_m[i] * 1e3, ":", color="k", lw=0.9)
    for axis in (angle_axis, range_axis):
        axis.plot([], [], ":", color="k", lw=0.9, label="first order (linearised)")
        axis.set_xlabel("spacing d between the transmitter and each receiver (m)")
        axis.grid(alpha=0.3, which="both")
        axis.set_xlim(0, float(d.max()))
    angle_axis.set_yscale("log")
    angle_axis.set_ylabel("azimuth error |Δθ| (degrees)")
    range_axis.set_ylabel("range error Δr (mm)")
    held = (
        f"path l = l1 = l2 = {study.path_m[0]:g} m"
        if np.all(study.path_m == study.path_m[0])
        else f"range r = {study.range_m[0]:g} m"
    )
    angle_axis.set_title(f"(a) angle error, {held}, Δl2 = 0")
    range_axis.set_title(f"(b) range error, {held}, Δl2 = 0")
    if recommendation is not None:
        rec = recommendation
        angle_axis.plot(
            d,
            np.degrees(rec.max_cross_range_error_m / study.range_m),
            color="0.45",
            lw=2.5,
            alpha=0.6,
            label=f"criterion: r·|Δθ| = {rec.max_cross_range_error_m * 1e3:g} mm",
        )
        for axis in (angle_axis, range_axis):
            axis.axvline(rec.spacing_m, color="k", lw=1.5, ls="--")
            axis.axvspan(0, rec.spacing_m, color="0.5", alpha=0.12, lw=0)
            if rec.largest_spacing_m is not None:
                axis.axvline(rec.largest_spacing_m, color="k", lw=1.0, ls="-.")
                axis.axvspan(rec.largest_spacing_m, float(d.max()), color="0.5", alpha=0.12, lw=0)
        if rec.max_range_error_m is not None:
            for sign in (1, -1):
                range_axis.axhline(
                    sign * rec.max_range_error_m * 1e3,
                    color="0.45",
                    lw=2.5,
                    alpha=0.6,
                    label=f"bound: |Δr| = {rec.max_range_error_m * 1e3:g} mm" if sign > 0 else None,
                )
        angle_axis.plot([rec.spacing_m], [np.degrees(rec.angle_error_rad)], "ko", ms=6)
        range_axis.plot([rec.spacing_m], [rec.range_error_m * 1e3], "ko", ms=6)
        angle_axis.annotate(
            f"recommended d = {rec.spacing_m:.3f} m\n"
            f"|Δθ| = {np.degrees(rec.angle_error_rad):.2f}°, "
            f"r·|Δθ| = {rec.cross_range_error_m * 1e3:.1f} mm",
            (rec.spacing_m, np.degrees(rec.angle_error_rad)),
            textcoords="offset points",
            xytext=(12, 40),
            fontsize="small",
            arrowprops={"arrowstyle": "->"},
            bbox={"boxstyle": "round", "fc": "white", "alpha": 0.9},
        )
        range_axis.annotate(
            f"recommended d = {rec.spacing_m:.3f} m\n|Δr| = {rec.range_error_m * 1e3:.2f} mm",
            (rec.spacing_m, rec.range_error_m * 1e3),
            textcoords="offset points",
            xytext=(12, -45),
            fontsize="small",
            arrowprops={"arrowstyle": "->"},
            bbox={"boxstyle": "round", "fc": "white", "alpha": 0.9},
        )
        angle_axis.text(
            rec.spacing_m / 2,
            0.03,
            "too small:\nangle error dominates",
            transform=angle_axis.get_xaxis_transform(),
            ha="center",
            fontsize="small",
            color="0.3",
        )
    angle_axis.legend(loc="upper right", fontsize="small")
    range_axis.legend(loc="center left", fontsize="small", ncols=2)
    figure.suptitle(
        "Receiver spacing: too small makes the angle uncertain, too large the range (report fig. 4.13)"
    )
    output = Path(path)
    figure.savefig(output, dpi=110)
    return output


def plot_error_map(errors: ErrorMap, path: str | Path, *, title: str = "") -> Path:
    """GDOP, range std and angle std over a slice of the workspace, transducers marked."""
    figure = Figure(figsize=(15, 5), layout="constrained")
    axes = figure.subplots(1, 3, sharey=True)
    uu, vv = np.meshgrid(errors.u_m, errors.v_m)
    e = errors.errors
    sigma_mm = errors.sigma_m * 1e3
    panels = (
        (e.gdop, "GDOP = position std / path std", ""),
        (e.range_std_m * 1e3, f"range std (mm), σ_path = {sigma_mm:g} mm", "mm"),
        (np.degrees(e.angle_std_rad), f"angle std (degrees), σ_path = {sigma_mm:g} mm", "°"),
    )
    names = errors.plane if errors.receivers_m.shape[1] == 3 else "xz"
    iu, iv = ("xyz".index(names[0]), "xyz".index(names[1]))
    for axis, (values, label, unit) in zip(axes, panels, strict=True):
        finite = values[np.isfinite(values) & (values > 0)]
        if finite.size == 0:
            continue
        low = float(np.percentile(finite, 1))
        high = float(min(np.percentile(finite, 99), low * 1e3))
        clipped = np.clip(np.where(np.isfinite(values), values, high), low, high)
        mesh = axis.pcolormesh(uu, vv, clipped, norm=LogNorm(low, high), cmap="viridis", shading="auto")
        levels = np.unique(np.round(np.geomspace(low, high, 6), 3))
        lines = axis.contour(uu, vv, clipped, levels=levels[1:-1], colors="w", linewidths=0.6)
        axis.clabel(lines, fontsize="x-small", fmt=f"%.3g{unit}")
        bar = figure.colorbar(mesh, ax=axis, label=unit or "ratio", shrink=0.8)
        bar.ax.yaxis.set_major_formatter(FormatStrFormatter("%.3g"))
        bar.ax.yaxis.set_minor_formatter(FormatStrFormatter("%.3g"))
        tx = errors.transmitters_m
        rx = errors.receivers_m
        if rx.shape[1] == 2:
            tx_uv, rx_uv = tx, rx
        else:
            tx_uv, rx_uv = tx[:, [iu, iv]], rx[:, [iu, iv]]
        axis.plot(rx_uv[:, 0], rx_uv[:, 1], "wv", ms=8, mec="k", label="receivers")
        axis.plot(tx_uv[:, 0], tx_uv[:, 1], "r^", ms=8, mec="k", label="transmitters")
        axis.set_xlabel(f"{names[0]} (m)")
        axis.set_title(label)
        axis.set_aspect("equal")
    axes[0].set_ylabel(f"{names[1]} (m)")
    axes[0].legend(loc="upper left", fontsize="small")
    where = f", {'xyz'[3 - iu - iv]} = {errors.offset_m:.3f} m" if errors.receivers_m.shape[1] == 3 else ""
    figure.suptitle(
        (title + ": " if title else "")
        + f"first-order position errors in the {names} plane{where}, every transmitter-receiver pair"
    )
    output = Path(path)
    figure.savefig(output, dpi=110)
    return output
