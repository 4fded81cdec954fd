"""Pictures of an occupancy grid: a floor plan, or slices and a projection of a 3-D grid, as PNG.

Occupancy is drawn from white (free, p = 0) to black (occupied, p = 1); cells no
reading touched are drawn in a pale blue, so that unknown space is never mistaken for
free. The sensor's path is drawn in red and, where given, the true surfaces in green.
Axes are the map frame's (:mod:`echoloc.maps.mapping`): x to the right, z ahead, y down.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.colors import ListedColormap
from matplotlib.figure import Figure
from numpy.typing import NDArray

from echoloc.errors import EchoLocError
from echoloc.maps.mapping import OccupancyGrid

_UNKNOWN = "#cfe3f5"
_AXES = ("x", "y", "z")


def _shown(probability: NDArray[np.float64], known: NDArray[np.bool_]) -> NDArray[np.float64]:
    return np.where(known, probability, np.nan)


def _panel(
    axes: Axes,
    grid: OccupancyGrid,
    plane: NDArray[np.float64],
    first: int,
    second: int,
    path_m: NDArray[np.float64] | None,
    truth_m: NDArray[np.float64] | None,
    title: str,
) -> None:
    spec = grid.spec
    lower, upper = spec.origin_m, spec.upper_m
    cmap = ListedColormap(np.linspace([1.0, 1.0, 1.0, 1.0], [0.0, 0.0, 0.0, 1.0], 256)).with_extremes(
        bad=_UNKNOWN
    )
    shown = axes.imshow(
        plane.T,
        origin="lower",
        extent=(float(lower[first]), float(upper[first]), float(lower[second]), float(upper[second])),
        cmap=cmap,
        vmin=0.0,
        vmax=1.0,
        interpolation="nearest",
        aspect="equal",
    )
    if truth_m is not None and len(truth_m):
        axes.scatter(
            truth_m[:, first], truth_m[:, second], s=0.05, c="tab:green", alpha=0.5, label="true surfaces"
        )
    if path_m is not None and len(path_m):
        axes.plot(path_m[:, first], path_m[:, second], c="tab:red", lw=1.2, label="sensor path")
        axes.scatter(path_m[:1, first], path_m[:1, second], c="tab:red", s=18, marker="o")
    axes.set_xlim(float(lower[first]), float(upper[first]))
    axes.set_ylim(float(lower[second]), float(upper[second]))
    axes.set_xlabel(f"{_AXES[first]} (m)")
    axes.set_ylabel(f"{_AXES[second]} (m)")
    axes.set_title(title)
    if (truth_m is not None and len(truth_m)) or (path_m is not None and len(path_m)):
        axes.legend(loc="upper right", fontsize="small", markerscale=12)
    axes.figure.colorbar(shown, ax=axes, shrink=0.8, label="occupancy probability (blue: unknown)")


def draw_floor_plan(
    axes: Axes,
    grid: OccupancyGrid,
    *,
    sensor_path_m: NDArray[np.float64] | None = None,
    truth_m: NDArray[np.float64] | None = None,
    title: str | None = None,
) -> None:
    """Draw a floor plan's occupancy on ``axes`` (x across, z up the page)."""
    if not grid.spec.is_floor_plan:
        raise EchoLocError("draw_floor_plan draws a floor plan; this grid is 3-D")
    height = float(grid.spec.centres_m(1)[0])
    _panel(
        axes,
        grid,
        _shown(grid.probability()[:, 0, :], grid.known()[:, 0, :]),
        0,
        2,
        sensor_path_m,
        truth_m,
        title
        or (
            f"Occupancy floor plan at y = {height:.2f} m, {grid.spec.cell_m * 100:g} cm cells, "
            f"{grid.frames} frames"
        ),
    )


def plot_grid(
    grid: OccupancyGrid,
    path: str | Path,
    *,
    sensor_path_m: NDArray[np.float64] | None = None,
    truth_m: NDArray[np.float64] | None = None,
    slices: int = 3,
) -> Path:
    """Draw ``grid`` to a PNG: the floor plan, or for a 3-D grid ``slices`` horizontal
    slices (x-z at several heights y) and a projection over y in which a column shows
    its most occupied cell when any is occupied, else its freest."""
    target = Path(path)
    if target.suffix.lower() != ".png":
        raise EchoLocError(f"{target}: a grid picture must be a .png file")
    spec = grid.spec
    probability = grid.probability()
    known = grid.known()
    if spec.is_floor_plan:
        figure = Figure(figsize=(8, 7.5), layout="constrained")
        draw_floor_plan(figure.add_subplot(), grid, sensor_path_m=sensor_path_m, truth_m=truth_m)
    else:
        layers = np.unique(np.linspace(0, spec.shape[1] - 1, max(1, slices)).round().astype(int))
        figure = Figure(figsize=(6.5 * (len(layers) + 1), 6), layout="constrained")
        ys = spec.centres_m(1)
        for n, j in enumerate(layers):
            axes = figure.add_subplot(1, len(layers) + 1, n + 1)
            near = None
            if truth_m is not None:
                near = truth_m[np.abs(truth_m[:, 1] - ys[j]) <= spec.cell_m / 2]
            _panel(
                axes,
                grid,
                _shown(probability[:, j, :], known[:, j, :]),
                0,
                2,
                sensor_path_m,
                near,
                f"slice y = {ys[j]:.2f} m",
            )
        axes = figure.add_subplot(1, len(layers) + 1, len(layers) + 1)
        seen = np.asarray(known.any(axis=1))
        # A column is as occupied as its most occupied cell, else as free as its freest.
        highest = np.where(known, probability, 0.0).max(axis=1)
        lowest = np.where(known, probability, 1.0).min(axis=1)
        projection = np.where(highest > 0.5, highest, lowest)
        _panel(
            axes,
            grid,
            _shown(projection, seen),
            0,
            2,
            sensor_path_m,
            None,
            "all heights (occupied over free)",
        )
    try:
        figure.savefig(target, dpi=110)
    except OSError as error:
        raise EchoLocError(f"{target}: cannot write: {error.strerror or error}") from error
    return target
