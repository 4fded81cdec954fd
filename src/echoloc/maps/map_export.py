"""Occupancy grids for other programs: NPZ, PLY, OctoMap (.bt, .ot) and MCAP with ROS 2 messages.

- **NPZ**: the grid's arrays (:func:`echoloc.maps.mapping.grid_arrays`), read back by
  :func:`read_grid_npz`.
- **PLY**: the occupied cells' centres with ``intensity`` = occupancy probability and
  the covariance diagonal of a uniform cell, ``h²/12`` (:func:`echoloc.io.export.write_ply`).
- **OctoMap** through pyoctomap (the OctoMap library's Python binding, wheels with
  the library bundled): every observed cell is set to its log-odds with the grid's
  clamping; ``.bt`` keeps the compact maximum-likelihood tree (free or occupied per
  leaf, OctoMap's ``writeBinary``), ``.ot`` the full probabilities (``write``).
  OctoMap's resolution is the cell size; its frame is the map frame.
- **MCAP** (ROS 2 Jazzy definitions, mcap + mcap-ros2-support): ``/tf`` per frame
  (``echoloc_map`` -> ``echoloc_sensor_optical_frame``, the sensor pose), the frame's
  located objects on ``/echoloc/objects`` (``sensor_msgs/msg/PointCloud2`` in the
  sensor frame), and the final map: a floor plan as ``nav_msgs/msg/OccupancyGrid`` on
  ``/echoloc/map`` (cells -1 unknown, 0-100 percent), a 3-D grid as a PointCloud2 of
  its occupied cells on ``/echoloc/map_cloud``, both in ``echoloc_map``.

The floor plan is the map frame's x-z plane (y points down, REP 103 optical). The
OccupancyGrid's own x-y plane is turned onto it by its origin pose: grid x = map x,
grid y = map z, grid z (its normal) = map -y, up.
"""

from __future__ import annotations

import math
import zipfile
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from mcap.records import Schema
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer as Ros2Writer
from numpy.typing import NDArray

from echoloc.errors import EchoLocError, open_input
from echoloc.extras import missing_extra
from echoloc.io.export import (
    _HEADER_MSG,
    _QUATERNION_MSG,
    _TIME_MSG,
    POINT_CLOUD2_SCHEMA,
    ROS_DISTRIBUTION,
    SENSOR_FRAME_ID,
    TF_MESSAGE_SCHEMA,
    _check_path,
    _matrix_quaternion,
    _schema_text,
    point_cloud2,
    ros_time,
    write_ply,
)
from echoloc.localise.locate import FrameObjects, LocatedObject
from echoloc.maps.mapping import MAP_FRAME_ID, GridSpec, OccupancyGrid, SensorModel, grid_arrays

MAP_TOPIC = "/echoloc/map"
MAP_CLOUD_TOPIC = "/echoloc/map_cloud"
OBJECTS_TOPIC = "/echoloc/objects"
TF_TOPIC = "/tf"

_POINT_MSG = """float64 x
float64 y
float64 z
"""
_POSE_MSG = """Point position
Quaternion orientation
"""
_MAP_META_DATA_MSG = """builtin_interfaces/Time map_load_time
float32 resolution
uint32 width
uint32 height
geometry_msgs/Pose origin
"""
_OCCUPANCY_GRID_MSG = """std_msgs/Header header

MapMetaData info

int8[] data
"""
OCCUPANCY_GRID_SCHEMA = _schema_text(
    _OCCUPANCY_GRID_MSG,
    ("std_msgs/Header", _HEADER_MSG),
    ("builtin_interfaces/Time", _TIME_MSG),
    ("nav_msgs/MapMetaData", _MAP_META_DATA_MSG),
    ("geometry_msgs/Pose", _POSE_MSG),
    ("geometry_msgs/Point", _POINT_MSG),
    ("geometry_msgs/Quaternion", _QUATERNION_MSG),
)

# Columns: where the OccupancyGrid's x, y and z axes point in the map frame.
_FLOOR_PLAN_AXES = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])


# --- NPZ ---------------------------------------------------------------------------------


def write_grid_npz(grid: OccupancyGrid, path: str | Path) -> Path:
    """Save the grid's arrays (``log_odds``, ``updates``, ``origin_m``, ``cell_m``, ...) as NPZ."""
    target = _check_path(path, ".npz")
    try:
        with target.open("wb") as stream:
            np.savez_compressed(stream, **grid_arrays(grid))
    except OSError as error:
        raise EchoLocError(f"{target}: cannot write: {error.strerror or error}") from error
    return target


MAX_GRID_BYTES = 4 << 30
"""The largest grid file read, on disk and unpacked: a 3-D grid of 10^8 cells at 6 bytes a cell
(log-odds and update counts) with room to spare."""


def read_grid_npz(path: str | Path, model: SensorModel | None = None) -> OccupancyGrid:
    """Read a grid written by :func:`write_grid_npz`."""
    source = str(path)
    with open_input(path, what="grid file", max_bytes=MAX_GRID_BYTES) as handle:
        try:
            unpacked = sum(info.file_size for info in zipfile.ZipFile(handle).infolist())
        except (zipfile.BadZipFile, OSError, ValueError) as error:
            raise EchoLocError(f"{source}: not an echoloc grid ({error})") from None
        if unpacked > MAX_GRID_BYTES:  # declared by the archive before anything is unpacked
            raise EchoLocError(f"{source}: unpacks to {unpacked} bytes, over the limit of {MAX_GRID_BYTES}")
        handle.seek(0)
        return _grid_from(source, handle, model)


def _grid_from(source: str, handle: BinaryIO, model: SensorModel | None) -> OccupancyGrid:
    try:
        with np.load(handle, allow_pickle=False) as data:
            log_odds = np.asarray(data["log_odds"], dtype=np.float32)
            updates = np.asarray(data["updates"], dtype=np.uint16)
            origin = np.asarray(data["origin_m"], dtype=float)
            cell = float(data["cell_m"])
            frames = int(data["frames"])
    except (OSError, ValueError, KeyError) as error:
        raise EchoLocError(f"{source}: not an echoloc grid ({error})") from None
    if log_odds.ndim != 3 or updates.shape != log_odds.shape:
        raise EchoLocError(f"{source}: log_odds and updates must be 3-D arrays of one shape")
    shape = (int(log_odds.shape[0]), int(log_odds.shape[1]), int(log_odds.shape[2]))
    return OccupancyGrid(GridSpec(origin, cell, shape), log_odds, updates, model or SensorModel(), frames)


# --- points ------------------------------------------------------------------------------


def occupied_points(grid: OccupancyGrid) -> FrameObjects:
    """The occupied cells as points: centre, covariance ``h²/12`` per axis, score = probability."""
    occupied = grid.occupied()
    centres = grid.occupied_centres_m()
    probability = grid.probability()[occupied]
    covariance = np.eye(3) * grid.spec.cell_m**2 / 12.0
    objects = tuple(
        LocatedObject(centre, covariance, (), (), math.nan, float(p))
        for centre, p in zip(centres, probability, strict=True)
    )
    return FrameObjects(grid.frames, 0.0, objects)


def write_grid_ply(grid: OccupancyGrid, path: str | Path, *, binary: bool = True) -> Path:
    """The occupied cells as a PLY point cloud (intensity = occupancy probability), in double precision."""
    comments = (
        "echoloc occupancy grid: the centres of its occupied cells",
        f"frame_id {MAP_FRAME_ID}: the frame of the sensor poses (REP 103 optical axes), metres",
        "intensity: occupancy probability of the cell",
        f"cov_xx cov_yy cov_zz: h^2/12 of a uniform cell of h = {grid.spec.cell_m:g} m, m^2",
        "receivers: 0 (a cell, not a located object)",
    )
    return write_ply(path, [occupied_points(grid)], binary=binary, double=True, comments=comments)[0]


# --- OctoMap -----------------------------------------------------------------------------


def voxel_centres_m(spec: GridSpec, cells: NDArray[np.int64]) -> NDArray[np.float64]:
    """Centres of the OctoMap voxels that hold ``cells`` (n, 3 indices) of ``spec``.

    OctoMap's voxels tile space from 0 in steps of the resolution; each cell goes to
    the voxel nearest its centre, ``(round(c / h - 1/2) + 1/2) h``, so that neighbouring
    cells land in neighbouring voxels. For a grid whose origin is a multiple of ``h``
    (``GridSpec.box`` and a floor plan's x and z) that is the cell itself; otherwise
    (a floor plan's layer, centred on its height) the map moves by less than half a
    cell along that axis.
    """
    h = spec.cell_m
    centres = spec.origin_m + (np.asarray(cells) + 0.5) * h
    return np.asarray((np.round(centres / h - 0.5) + 0.5) * h)


def octree(grid: OccupancyGrid) -> Any:
    """A ``pyoctomap.OcTree`` at the grid's resolution holding every observed cell's log-odds
    (pyoctomap is the ``octomap`` extra)."""
    try:
        import pyoctomap
    except ImportError:
        raise missing_extra("octomap", "an OctoMap file") from None

    tree = pyoctomap.OcTree(grid.spec.cell_m)
    low, high = grid.model.clamp_probability
    tree.setClampingThresMin(low)
    tree.setClampingThresMax(high)
    tree.setOccupancyThres(grid.model.occupied_probability)
    known = np.argwhere(grid.known())
    centres = voxel_centres_m(grid.spec, known)
    values = grid.log_odds[tuple(known.T)]
    for centre, value in zip(centres, values, strict=True):
        tree.updateNode(centre, float(value), True)
    tree.updateInnerOccupancy()
    return tree


def write_octomap(grid: OccupancyGrid, path: str | Path) -> Path:
    """Write an OctoMap file: ``.bt`` (binary, maximum likelihood) or ``.ot`` (full probabilities)."""
    target = Path(path)
    suffix = target.suffix.lower()
    if suffix not in (".bt", ".ot"):
        raise EchoLocError(f"{target}: an OctoMap file is .bt (binary) or .ot (full)")
    target = _check_path(target, suffix)
    tree = octree(grid)
    if suffix == ".bt":
        tree.toMaxLikelihood()
        written = tree.writeBinary(str(target))
    else:
        written = tree.write(str(target))
    if not written:
        raise EchoLocError(f"{target}: OctoMap could not write the file")
    return target


# --- MCAP ----------------------------------------------------------------------------------


def floor_plan_pose(spec: GridSpec) -> tuple[tuple[float, float, float], tuple[float, float, float, float]]:
    """Where a floor plan's plane lies in the map frame: cell (0, 0)'s corner and the rotation (x, y, z, w).

    Grid x = map x, grid y = map z, grid normal = map -y (up): the plane through the
    layer's centre height.
    """
    if not spec.is_floor_plan:
        raise EchoLocError("a floor plan's pose is asked of a 3-D grid")
    qx, qy, qz, qw = (float(v) for v in _matrix_quaternion(_FLOOR_PLAN_AXES))
    x0, y0, z0 = (float(v) for v in spec.origin_m)
    return (x0, y0 + spec.cell_m / 2, z0), (qx, qy, qz, qw)


def floor_plan_cells(grid: OccupancyGrid) -> NDArray[np.float64]:
    """A floor plan's occupancy as rows along map z and columns along map x; -1 where unknown."""
    probability = grid.probability()[:, 0, :]
    return np.asarray(np.where(grid.known()[:, 0, :], probability, -1.0).T)


def occupancy_grid_message(grid: OccupancyGrid, stamp_s: float) -> dict[str, Any]:
    """A ``nav_msgs/msg/OccupancyGrid`` (as a dict) of a floor plan, in ``echoloc_map``.

    ``data`` is row-major from the origin cell, grid x fastest (map x), rows along map
    z; -1 where no reading touched a cell, else round(100 p).
    """
    spec = grid.spec
    if not spec.is_floor_plan:
        raise EchoLocError("nav_msgs/OccupancyGrid holds a floor plan; this grid is 3-D")
    probability = grid.probability()[:, 0, :]
    cells = np.where(grid.known()[:, 0, :], np.rint(100 * probability), -1).astype(np.int8)
    (x0, y0, z0), (qx, qy, qz, qw) = floor_plan_pose(spec)
    return {
        "header": {"stamp": ros_time(stamp_s), "frame_id": MAP_FRAME_ID},
        "info": {
            "map_load_time": ros_time(stamp_s),
            "resolution": float(spec.cell_m),
            "width": int(spec.shape[0]),
            "height": int(spec.shape[2]),
            "origin": {
                "position": {"x": x0, "y": y0, "z": z0},
                "orientation": {"x": qx, "y": qy, "z": qz, "w": qw},
            },
        },
        "data": cells.T.reshape(-1).tolist(),
    }


def _tf_message(pose: NDArray[np.float64], stamp_s: float) -> dict[str, Any]:
    x, y, z, qx, qy, qz, qw = (float(v) for v in pose)
    return {
        "transforms": [
            {
                "header": {"stamp": ros_time(stamp_s), "frame_id": MAP_FRAME_ID},
                "child_frame_id": SENSOR_FRAME_ID,
                "transform": {
                    "translation": {"x": x, "y": y, "z": z},
                    "rotation": {"x": qx, "y": qy, "z": qz, "w": qw},
                },
            }
        ]
    }


def _write_stamped(
    writer: Ros2Writer,
    topic: str,
    schema: Schema,
    message_at: Callable[[float], dict[str, Any]],
    stamp_s: float,
    sequence: int,
) -> None:
    """Write the message ``message_at(stamp_s)`` on ``topic`` as message ``sequence``, logged and
    published at its header's time ``stamp_s`` (s; whole ns in MCAP): a frame's ``/tf`` or objects
    in :func:`write_map_mcap`. The time is converted to ns first, so a time without a count of ns
    (inf, nan) fails here before the message is built."""
    t_ns = round(stamp_s * 1e9)
    writer.write_message(
        topic, schema, message_at(stamp_s), log_time=t_ns, publish_time=t_ns, sequence=sequence
    )


def write_map_mcap(
    path: str | Path,
    grid: OccupancyGrid,
    *,
    poses: NDArray[np.float64] | None = None,
    frame_times_s: NDArray[np.float64] | None = None,
    frames: Sequence[int] | None = None,
    objects_per_frame: Sequence[FrameObjects] = (),
    start_time_s: float = 0.0,
) -> int:
    """Write the map (and the sensor's poses and objects per frame) as ROS 2 messages in MCAP.

    ``frame_times_s`` holds every frame's time, indexed by frame number, and
    ``poses`` (same length, rows ``[x, y, z, qx, qy, qz, qw]``) the sensor's pose:
    one ``/tf`` is written for each frame of ``frames`` (default: all). Each
    :class:`FrameObjects` goes on ``/echoloc/objects`` stamped with its frame's time;
    the map is stamped with the last frame written. Returns the number of messages.
    """
    target = _check_path(path, ".mcap")
    if not math.isfinite(start_time_s) or start_time_s < 0:
        raise EchoLocError(f"{target}: start time must be finite and >= 0, got {start_time_s}")
    times = np.zeros(0) if frame_times_s is None else np.asarray(frame_times_s, dtype=float)
    if poses is not None and len(poses) != len(times):
        raise EchoLocError(f"{target}: {len(poses)} poses for {len(times)} frame times")
    written = list(range(len(times))) if frames is None else [int(k) for k in frames]
    if any(not 0 <= k < len(times) for k in written):
        raise EchoLocError(f"{target}: a frame to write is not among the {len(times)} frame times")
    for frame in objects_per_frame:
        if not 0 <= frame.frame < len(times):
            raise EchoLocError(f"{target}: objects of frame {frame.frame}, which has no time")
    last = start_time_s + (float(times[written].max()) if written else 0.0)
    try:
        stream = target.open("wb")
    except OSError as error:
        raise EchoLocError(f"{target}: cannot write: {error.strerror or error}") from error
    count = 0
    with stream, Ros2Writer(stream, compression=CompressionType.ZSTD) as writer:
        writer.add_metadata(
            "echoloc",
            {
                "ros_distribution": ROS_DISTRIBUTION,
                "map_frame_id": MAP_FRAME_ID,
                "sensor_frame_id": SENSOR_FRAME_ID,
                "frame_convention": "REP 103 optical: x right, y down, z boresight",
            },
        )
        cloud_schema = writer.register_msgdef("sensor_msgs/msg/PointCloud2", POINT_CLOUD2_SCHEMA)
        if poses is not None:
            tf_schema = writer.register_msgdef("tf2_msgs/msg/TFMessage", TF_MESSAGE_SCHEMA)
            for index, k in enumerate(written):
                stamp = start_time_s + float(times[k])
                _write_stamped(writer, TF_TOPIC, tf_schema, partial(_tf_message, poses[k]), stamp, index)
                count += 1
        for index, frame in enumerate(objects_per_frame):
            stamp = start_time_s + float(times[frame.frame])
            _write_stamped(writer, OBJECTS_TOPIC, cloud_schema, partial(point_cloud2, frame), stamp, index)
            count += 1
        t_ns = round(last * 1e9)
        if grid.spec.is_floor_plan:
            map_schema = writer.register_msgdef("nav_msgs/msg/OccupancyGrid", OCCUPANCY_GRID_SCHEMA)
            writer.write_message(
                MAP_TOPIC, map_schema, occupancy_grid_message(grid, last), log_time=t_ns, publish_time=t_ns
            )
        else:
            cloud = point_cloud2(occupied_points(grid), last, frame_id=MAP_FRAME_ID)
            writer.write_message(MAP_CLOUD_TOPIC, cloud_schema, cloud, log_time=t_ns, publish_time=t_ns)
        count += 1
    return count
