"""Pictures of a back-projected image: maximum-intensity projections and slices, saved as PNG.

The image (:class:`echoloc.localise.backprojection.Image`) holds per voxel the k-th largest
channel amplitude SNR; it is drawn in dB (``20 log10``) from 6 dB below the
detection threshold to its maximum, so everything that could be an object shows.
Axes follow the sensor frame (docs/FORMATS.md): z is range, x to the right, y down.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.image import AxesImage
from numpy.typing import NDArray

from echoloc.localise.backprojection import Image

_AXES = ("x", "y", "z")


def _extent(image: Image, first: int, second: int) -> tuple[float, float, float, float]:
    grid = image.grid
    return (
        float(grid.lower_m[first]),
        float(grid.lower_m[first] + grid.shape[first] * grid.voxel_m),
        float(grid.lower_m[second] + grid.shape[second] * grid.voxel_m),
        float(grid.lower_m[second]),
    )


def _panel(
    axes: Axes,
    plane: NDArray[np.float32],
    image: Image,
    first: int,
    second: int,
    levels_db: tuple[float, float],
    points: Sequence[tuple[NDArray[np.float64], str, str]],
) -> AxesImage:
    """Draw ``plane`` (first axis, second axis) with the first axis horizontal."""
    db = 20 * np.log10(np.maximum(plane, 1e-6))
    shown = axes.imshow(
        db.T,
        extent=_extent(image, first, second),
        vmin=levels_db[0],
        vmax=levels_db[1],
        cmap="magma",
        interpolation="nearest",
        aspect="equal",
    )
    for positions, marker, colour in points:
        if len(positions):
            if marker == "x":
                axes.scatter(positions[:, first], positions[:, second], marker=marker, s=40, c=colour)
            else:
                axes.scatter(
                    positions[:, first],
                    positions[:, second],
                    marker=marker,
                    s=70,
                    facecolors="none",
                    edgecolors=colour,
                )
    axes.set_xlabel(f"{_AXES[first]} (m)")
    axes.set_ylabel(f"{_AXES[second]} (m)")
    return shown


def save_image_png(
    image: Image,
    path: str | Path,
    *,
    objects_m: NDArray[np.float64] | None = None,
    truth_m: NDArray[np.float64] | None = None,
    slice_at_m: NDArray[np.float64] | None = None,
    title: str = "",
) -> Path:
    """Save maximum-intensity projections (top row) and slices (bottom row) of a 3-D image.

    Projections along z (x-y, the view from the sensor), y (x-z, from above) and x
    (z-y, from the side); slices through ``slice_at_m`` (default: the brightest
    voxel). Located objects are drawn as white crosses, true positions as cyan
    circles.
    """
    if image.grid.dim != 3:
        raise ValueError(f"save_image_png draws 3-D images, got a {image.grid.dim}-D grid")
    values = image.values
    peak = float(values.max())
    threshold_db = 20 * np.log10(image.threshold)
    levels = (threshold_db - 6.0, max(20 * np.log10(max(peak, 1e-6)), threshold_db))
    if slice_at_m is None:
        index = np.array(np.unravel_index(int(np.argmax(values)), values.shape))
    else:
        index = np.clip(
            np.floor((slice_at_m - image.grid.lower_m) / image.grid.voxel_m).astype(int),
            0,
            np.array(values.shape) - 1,
        )
    points: list[tuple[NDArray[np.float64], str, str]] = []
    if truth_m is not None:
        points.append((np.asarray(truth_m).reshape(-1, 3), "o", "cyan"))
    if objects_m is not None:
        points.append((np.asarray(objects_m).reshape(-1, 3), "x", "white"))
    figure = Figure(figsize=(13, 8.5), layout="constrained")
    grid = figure.add_gridspec(2, 3)
    views = ((0, 1, 2), (0, 2, 1), (2, 1, 0))  # (horizontal, vertical, projected) axes
    shown = None
    for column, (first, second, along) in enumerate(views):
        top = figure.add_subplot(grid[0, column])
        projection = values.max(axis=along)
        plane = projection if first < second else projection.T
        shown = _panel(top, plane, image, first, second, levels, points)
        top.set_title(f"max over {_AXES[along]}")
        bottom = figure.add_subplot(grid[1, column])
        cut = np.take(values, index[along], axis=along)
        plane = cut if first < second else cut.T
        at = image.grid.axis_m(along)[index[along]]
        _panel(bottom, plane, image, first, second, levels, points)
        bottom.set_title(f"slice {_AXES[along]} = {at:.3f} m")
    if shown is not None:
        figure.colorbar(
            shown, ax=figure.axes, shrink=0.6, label=f"{image.support}th-largest channel SNR (dB)"
        )
    figure.suptitle(title or f"Back-projection, {image.grid.voxel_m * 1e3:g} mm voxels")
    target = Path(path)
    figure.savefig(target, dpi=110)
    return target
