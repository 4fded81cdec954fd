"""The receiver-spacing study behind ``echoloc design``: how far apart to put the receivers.

It joins the pieces of :mod:`echoloc.localise.uncertainty` into the study of the report
(section 4.3, figures 4.12 and 4.13): for a reflector at a held path ``l`` (or range
``r``) and a path error ``Δl``, the range and angle errors against the spacing ``d``, the
recommended spacing, the uncertainty area of one spacing, and the geometric dilution of
precision (GDOP) of an array over a plane.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from echoloc.errors import EchoLocError
from echoloc.localise.uncertainty import (
    ErrorMap,
    PositionErrors,
    SpacingRecommendation,
    SpacingStudy,
    UncertaintyArea,
    array_channels,
    cross_array,
    error_map,
    position_errors,
    recommended_spacing,
    spacing_study,
    uncertainty_area,
)

ROUND_SPACINGS_M = (0.01, 0.02, 0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.4, 0.5)
"""The spacings of the study's table, m (the report's, figure 4.13), beside the
recommended and chosen ones."""

CURVE_POINTS = 300
"""Spacings of the study's curves, from 0.01 m to the largest of interest."""

MAP_POINTS = 161
"""Grid points along each axis of the GDOP map."""


@dataclass(frozen=True)
class DesignStudy:
    """What ``echoloc design`` reports. Lengths in m, angles in rad.

    ``curves``: the errors over :data:`CURVE_POINTS` spacings for path errors ``±Δl``
    and ``±Δl/2`` (figure 4.13); ``table``: at :data:`ROUND_SPACINGS_M` (and the
    recommended and chosen spacings) for ``+Δl`` and ``-Δl``; ``area``: the uncertainty
    area at ``spacing_m`` with both paths in error (figure 4.12); ``gdop_map``: position
    errors of the array over a plane for ``σ_path = Δl``; ``on_boresight``: the same at
    the area's range straight ahead.
    """

    path_m: float | None
    range_m: float | None
    path_error_m: float
    recommendation: SpacingRecommendation
    spacing_m: float
    curves: SpacingStudy
    table: SpacingStudy
    area_path_m: float
    area: UncertaintyArea
    array_name: str
    transmitters_m: NDArray[np.float64]
    receivers_m: NDArray[np.float64]
    gdop_map: ErrorMap
    probe_m: NDArray[np.float64]
    on_boresight: PositionErrors


def design_study(
    path_error_m: float,
    *,
    path_m: float | None = None,
    range_m: float | None = None,
    spacing_m: float | None = None,
    max_cross_range_error_m: float | None = None,
    max_range_error_m: float | None = None,
    array_m: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None,
    array_name: str | None = None,
    plane: Literal["xz", "yz", "xy"] = "xz",
    offset_m: float | None = None,
) -> DesignStudy:
    """The spacing study for a reflector at path ``path_m`` or range ``range_m`` (neither:
    the report's ``l = 1 m``) with path error ``path_error_m``.

    ``spacing_m``: the spacing to draw the uncertainty area and the cross array of the map
    at [default: the recommended one]; ``array_m``: (transmitters, receivers) to map
    instead of that cross; ``plane``/``offset_m``: the map's plane and its third
    coordinate [default: 0, or the area's range for ``xy``].
    """
    if path_m is not None and range_m is not None:
        raise EchoLocError("give a path or a range to hold, not both")
    if path_m is None and range_m is None:
        path_m = 1.0
    if path_m is not None and spacing_m is not None and spacing_m >= path_m:
        raise EchoLocError(f"the spacing {spacing_m:g} m must be below the path {path_m:g} m")
    recommendation = recommended_spacing(
        path_error_m,
        path_m=path_m,
        range_m=range_m,
        max_cross_range_error_m=max_cross_range_error_m,
        max_range_error_m=max_range_error_m,
    )
    spacing = spacing_m if spacing_m is not None else recommendation.spacing_m
    # The report's spacings 0.01-0.5 m, beyond the recommendation when it is larger.
    top = max(0.5, 1.5 * recommendation.spacing_m, 1.2 * (recommendation.largest_spacing_m or 0.0))
    if path_m is not None:
        top = min(top, 0.98 * path_m)
    errors = path_error_m * np.array([-1.0, -0.5, 0.5, 1.0])
    curves = spacing_study(np.linspace(0.01, top, CURVE_POINTS), errors, path_m=path_m, range_m=range_m)
    table_d = np.array(ROUND_SPACINGS_M)
    table_d = np.unique(np.append(table_d[table_d <= top], [recommendation.spacing_m, spacing]))
    table = spacing_study(table_d, [path_error_m, -path_error_m], path_m=path_m, range_m=range_m)
    # Figure 4.12: the broadside point of the study at spacing d, both paths in error.
    area_path = float(spacing_study([spacing], [0.0], path_m=path_m, range_m=range_m).path_m[0])
    area = uncertainty_area(area_path, area_path, path_error_m, path_error_m, spacing)
    if array_m is not None:
        transmitters, receivers = array_m
        name = array_name or "the given array"
    else:
        transmitters, receivers = cross_array(spacing)
        name = f"report cross, d = {spacing:.3f} m"
    if offset_m is None:
        offset_m = area.range_m if plane == "xy" else 0.0
    reach = max(0.6, 1.6 * area.range_m)
    grid_u = np.linspace(-reach, reach, MAP_POINTS)
    if plane == "xy":
        grid_v = np.linspace(-reach, reach, MAP_POINTS)
    else:
        grid_v = np.linspace(0.02, 1.5 * reach, MAP_POINTS)
    gdop_map = error_map(
        transmitters, receivers, grid_u, grid_v, plane=plane, offset_m=offset_m, sigma_m=path_error_m
    )
    probe = np.zeros(transmitters.shape[1])
    probe[-1] = area.range_m
    tx_ch, rx_ch = array_channels(transmitters, receivers)
    return DesignStudy(
        path_m=path_m,
        range_m=range_m,
        path_error_m=path_error_m,
        recommendation=recommendation,
        spacing_m=spacing,
        curves=curves,
        table=table,
        area_path_m=area_path,
        area=area,
        array_name=name,
        transmitters_m=transmitters,
        receivers_m=receivers,
        gdop_map=gdop_map,
        probe_m=probe,
        on_boresight=position_errors(probe, tx_ch, rx_ch, path_error_m),
    )


def design_record(study: DesignStudy) -> dict[str, Any]:
    """The study as ``echoloc design --json`` prints it (before any ``plots`` entry)."""
    rows, area, at_point = study.table, study.area, study.on_boresight
    return {
        "held": {"path_m": study.path_m} if study.path_m is not None else {"range_m": study.range_m},
        "path_error_m": study.path_error_m,
        "recommendation": asdict(study.recommendation),
        "spacing_m": study.spacing_m,
        "study": [
            {
                "spacing_m": float(d),
                "range_m": float(rows.range_m[j]),
                "path_m": float(rows.path_m[j]),
                "range_error_m": [float(v) for v in rows.range_error_m[:, j]],
                "angle_error_rad": [float(v) for v in rows.angle_error_rad[:, j]],
                "linear_range_error_m": [float(v) for v in rows.linear_range_error_m[:, j]],
                "linear_angle_error_rad": [float(v) for v in rows.linear_angle_error_rad[:, j]],
                "cross_range_error_m": float(np.max(rows.cross_range_error_m[:, j])),
            }
            for j, d in enumerate(rows.spacings_m)
        ],
        "study_path_errors_m": [study.path_error_m, -study.path_error_m],
        "uncertainty_area": {
            "spacing_m": study.spacing_m,
            "path_m": study.area_path_m,
            "range_m": area.range_m,
            "corners": {
                name: {
                    "position_m": [float(v) for v in area.corners_m[k]],
                    "range_m": float(area.corner_range_m[k]),
                    "angle_rad": float(area.corner_angle_rad[k]),
                }
                for k, name in enumerate("abcd")
            },
        },
        "array": {
            "name": study.array_name,
            "transmitters_m": study.transmitters_m.tolist(),
            "receivers_m": study.receivers_m.tolist(),
            "on_boresight": {
                "position_m": study.probe_m.tolist(),
                "gdop": float(at_point.gdop),
                "std_m": [float(v) for v in at_point.std_m],
                "range_std_m": float(at_point.range_std_m),
                "angle_std_rad": float(at_point.angle_std_rad),
            },
        },
    }
