"""Types of echoloc.maps's public names; lazy_loader reads its imports to load each on first use."""

from .map_export import (
    read_grid_npz,
    write_grid_npz,
    write_grid_ply,
    write_map_mcap,
    write_nav2_map,
    write_octomap,
)
from .mapping import (
    GridSpec,
    MapAccumulator,
    OccupancyGrid,
    SensorModel,
    build_map,
    choose_grid,
    map_accuracy,
    read_trajectory,
)
from .triangulation import TrackOptions, TriangulatedPoint

__all__ = [
    "GridSpec",
    "MapAccumulator",
    "OccupancyGrid",
    "SensorModel",
    "TrackOptions",
    "TriangulatedPoint",
    "build_map",
    "choose_grid",
    "map_accuracy",
    "read_grid_npz",
    "read_trajectory",
    "write_grid_npz",
    "write_grid_ply",
    "write_map_mcap",
    "write_nav2_map",
    "write_octomap",
]
