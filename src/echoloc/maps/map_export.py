"""Occupancy grids for other programs: NPZ, PLY, OctoMap (.bt, .ot), MCAP with ROS 2 messages and
nav2's map files (YAML + PGM).

- **NPZ**: the grid's arrays (:func:`echoloc.maps.mapping.grid_arrays`), read back by
  :func:`read_grid_npz`.
- **PLY**: the occupied cells' centres with ``intensity`` = occupancy probability and
  the covariance of a uniform cell, ``h²/12`` on the diagonal (:func:`echoloc.io.export.write_ply`).
- **OctoMap** through pyoctomap (the OctoMap library's Python binding, wheels with
  the library bundled): every observed cell is set to its log-odds with the grid's
  clamping; ``.bt`` keeps the compact maximum-likelihood tree (free or occupied per
  leaf, OctoMap's ``writeBinary``), ``.ot`` the full probabilities (``write``).
  OctoMap's resolution is the cell size; its frame is the map frame.
- **MCAP** (ROS 2 Jazzy definitions, mcap + mcap-ros2-support), frames by REP 103/105
  (``docs/ROS.md``): ``/tf_static`` (``map`` -> ``odom`` identity, ``echoloc_sensor_link``
  -> ``echoloc_sensor_optical_frame``), ``/tf`` per frame (``odom`` ->
  ``echoloc_sensor_link``, the sensor's pose), the frame's located objects on
  ``/echoloc/objects`` (``sensor_msgs/msg/PointCloud2`` in the optical frame), and the
  final map in ``map`` (z up): a floor plan as ``nav_msgs/msg/OccupancyGrid`` on
  ``/echoloc/map`` (cells -1 unknown, 0-100 percent; rows along map y, columns along map
  x, origin orientation the identity), a 3-D grid as a PointCloud2 of its occupied cells
  on ``/echoloc/map_cloud``; both latched (transient local) on replay.
- **nav2 map files** (:func:`write_nav2_map`): ``NAME.yaml`` and ``NAME.pgm`` as nav2's
  ``map_saver`` writes them for that OccupancyGrid (trinary).

echoloc builds maps in its own world frame, the frame of the sensor poses, whose axes
are the sensor's at the identity pose (x right, y down, z ahead; REP 103 optical); a
floor plan is its x-z plane. The ROS exports turn it into the z-up ``map`` frame with
:data:`echoloc.io.export.OPTICAL_TO_BODY` (map x = world z, map y = -world x, map z =
-world y), which is exact: cells are only renumbered, never resampled.
"""

from __future__ import annotations

import math
import zipfile
from collections.abc import Callable, Sequence
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from mcap.records import Schema
from numpy.typing import NDArray

from echoloc.errors import EchoLocError, open_input
from echoloc.extras import missing_extra
from echoloc.io.export import (
    _HEADER_MSG,
    _QUATERNION_MSG,
    _TIME_MSG,
    BODY_FRAME_ID,
    LATCHED_QOS,
    ODOM_FRAME_ID,
    OPTICAL_TO_BODY,
    POINT_CLOUD2_SCHEMA,
    ROS_DISTRIBUTION,
    ROS_MAP_FRAME_ID,
    SENSOR_FRAME_ID,
    STREAM_QOS,
    TF_MESSAGE_SCHEMA,
    TF_QOS,
    QosWriter,
    _check_path,
    _schema_text,
    map_odom_transform,
    optical_transform,
    point_cloud2,
    pose_transform,
    ros_time,
    write_ply,
)
from echoloc.localise.locate import FrameObjects, LocatedObject
from echoloc.maps.mapping import MAP_FRAME_ID, GridSpec, OccupancyGrid, SensorModel, grid_arrays

MAP_TOPIC = "/echoloc/map"
MAP_CLOUD_TOPIC = "/echoloc/map_cloud"
OBJECTS_TOPIC = "/echoloc/objects"
TF_TOPIC = "/tf"
TF_STATIC_TOPIC = "/tf_static"

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
        f"cov_xx cov_yy cov_zz: h^2/12 of a uniform cell of h = {grid.spec.cell_m:g} m, m^2; "
        "cov_xy cov_xz cov_yz: 0",
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


def map_floor_plan(grid: OccupancyGrid) -> tuple[NDArray[np.float64], tuple[float, float, float]]:
    """A floor plan in the z-up ``map`` frame: occupancy (rows along map y, columns along map x,
    row 0 the smallest y; -1 where unknown) and the corner of cell (0, 0) in ``map``, m.

    World x runs along map -y and world z along map x (:data:`OPTICAL_TO_BODY`), so the
    rows are the grid's x cells in reverse and the columns its z cells: cell ``(r, c)``
    is the grid's cell ``(nx - 1 - r, 0, c)``. The corner is ``(z0, -(x0 + nx h),
    -height)`` with ``height`` the layer's centre (world y, down).
    """
    spec = grid.spec
    if not spec.is_floor_plan:
        raise EchoLocError("a floor plan is asked of a 3-D grid")
    probability = np.where(grid.known()[:, 0, :], grid.probability()[:, 0, :], -1.0)
    cells = np.ascontiguousarray(probability[::-1, :], dtype=float)
    x0, y0, z0 = (float(v) for v in spec.origin_m)
    h = float(spec.cell_m)
    return cells, (z0, -(x0 + spec.shape[0] * h), -(y0 + h / 2))


def occupancy_percent(cells: NDArray[np.float64]) -> NDArray[np.int8]:
    """OccupancyGrid values of probabilities: round(100 p), -1 where unknown (negative)."""
    values = np.where(cells < 0, -1.0, np.rint(100.0 * np.clip(cells, 0.0, 1.0)))
    return np.asarray(values, dtype=np.int8)


def occupancy_grid_message(
    grid: OccupancyGrid, stamp_s: float, *, frame_id: str = ROS_MAP_FRAME_ID
) -> dict[str, Any]:
    """A ``nav_msgs/msg/OccupancyGrid`` (as a dict) of a floor plan in the z-up ``map`` frame.

    The layout of :func:`map_floor_plan`: ``data`` row-major from the origin cell, map x
    fastest, rows along map y; -1 where no reading touched a cell, else round(100 p). The
    origin pose is cell (0, 0)'s corner with the identity orientation, as nav2 expects;
    its z is the floor plan's height. ``map_load_time`` and the header stamp are ``stamp_s``.
    """
    cells, (x0, y0, z0) = map_floor_plan(grid)
    return {
        "header": {"stamp": ros_time(stamp_s), "frame_id": frame_id},
        "info": {
            "map_load_time": ros_time(stamp_s),
            "resolution": float(grid.spec.cell_m),
            "width": int(cells.shape[1]),
            "height": int(cells.shape[0]),
            "origin": {
                "position": {"x": x0, "y": y0, "z": z0},
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
            },
        },
        "data": occupancy_percent(cells).reshape(-1).tolist(),
    }


def points_in_map(frame: FrameObjects) -> FrameObjects:
    """Points of echoloc's world frame (y down) in the z-up ``map``: positions ``C p`` and
    covariances ``C Σ C^T`` with ``C`` = :data:`OPTICAL_TO_BODY` (exact: a permutation with signs)."""
    c = OPTICAL_TO_BODY
    moved = tuple(
        replace(
            obj,
            position_m=c @ np.asarray(obj.position_m, dtype=float),
            covariance_m2=c @ np.asarray(obj.covariance_m2, dtype=float) @ c.T,
        )
        for obj in frame.objects
    )
    return replace(frame, objects=moved)


def _write_stamped(
    writer: QosWriter,
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


def _pose_message(pose: NDArray[np.float64], parent: str, body: str, stamp_s: float) -> dict[str, Any]:
    return {"transforms": [pose_transform(pose, stamp_s, parent, body)]}


def write_map_mcap(
    path: str | Path,
    grid: OccupancyGrid,
    *,
    poses: NDArray[np.float64] | None = None,
    frame_times_s: NDArray[np.float64] | None = None,
    frames: Sequence[int] | None = None,
    objects_per_frame: Sequence[FrameObjects] = (),
    start_time_s: float = 0.0,
    map_frame_id: str = ROS_MAP_FRAME_ID,
    odom_frame_id: str | None = ODOM_FRAME_ID,
) -> int:
    """Write the map (and the sensor's poses and objects per frame) as ROS 2 messages in MCAP.

    ``frame_times_s`` holds every frame's time on the capture clock, indexed by frame
    number, and ``poses`` (same length, rows ``[x, y, z, qx, qy, qz, qw]``) the sensor's
    pose in echoloc's world frame. ``/tf_static`` (one message, transient local) holds
    ``map_frame_id`` -> ``odom_frame_id`` (identity; left out when ``odom_frame_id`` is
    None) and the body-to-optical rotation; one ``/tf`` is written for each frame of
    ``frames`` (default: all): ``odom_frame_id`` (or ``map_frame_id``) ->
    ``echoloc_sensor_link`` (:func:`echoloc.io.export.body_pose_in_map`). Each
    :class:`FrameObjects` goes on ``/echoloc/objects`` in the optical frame, stamped with
    its frame's time; the map (:func:`occupancy_grid_message`, or the occupied cells
    of a 3-D grid in ``map_frame_id``) is stamped with the last frame written and
    latched. Returns the number of messages.
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
    first = start_time_s + (float(times[written].min()) if written else 0.0)
    last = start_time_s + (float(times[written].max()) if written else 0.0)
    ros_time(first)
    ros_time(last)
    parent = map_frame_id if odom_frame_id is None else odom_frame_id
    try:
        stream = target.open("wb")
    except OSError as error:
        raise EchoLocError(f"{target}: cannot write: {error.strerror or error}") from error
    count = 0
    with stream, QosWriter(stream) as writer:
        writer.add_metadata(
            "echoloc",
            {
                "ros_distribution": ROS_DISTRIBUTION,
                "map_frame_id": map_frame_id,
                "body_frame_id": BODY_FRAME_ID,
                "sensor_frame_id": SENSOR_FRAME_ID,
                "frame_convention": "REP 103/105: map and body z up, x forward; "
                "sensor frame optical: x right, y down, z boresight",
            },
        )
        tf_schema = writer.register_msgdef("tf2_msgs/msg/TFMessage", TF_MESSAGE_SCHEMA)
        writer.add_topic(TF_STATIC_TOPIC, tf_schema, LATCHED_QOS)
        statics = [optical_transform(first, BODY_FRAME_ID, SENSOR_FRAME_ID)]
        if odom_frame_id is not None:
            statics.insert(0, map_odom_transform(first, map_frame_id, odom_frame_id))
        t_ns = round(first * 1e9)
        writer.write_message(
            TF_STATIC_TOPIC, tf_schema, {"transforms": statics}, log_time=t_ns, publish_time=t_ns
        )
        count += 1
        cloud_schema = writer.register_msgdef("sensor_msgs/msg/PointCloud2", POINT_CLOUD2_SCHEMA)
        if poses is not None:
            writer.add_topic(TF_TOPIC, tf_schema, TF_QOS)
            for index, k in enumerate(written):
                stamp = start_time_s + float(times[k])
                moved = partial(_pose_message, np.asarray(poses[k], dtype=float), parent, BODY_FRAME_ID)
                _write_stamped(writer, TF_TOPIC, tf_schema, moved, stamp, index)
                count += 1
        if objects_per_frame:
            writer.add_topic(OBJECTS_TOPIC, cloud_schema, STREAM_QOS)
        for index, frame in enumerate(objects_per_frame):
            stamp = start_time_s + float(times[frame.frame])
            _write_stamped(writer, OBJECTS_TOPIC, cloud_schema, partial(point_cloud2, frame), stamp, index)
            count += 1
        t_ns = round(last * 1e9)
        if grid.spec.is_floor_plan:
            map_schema = writer.register_msgdef("nav_msgs/msg/OccupancyGrid", OCCUPANCY_GRID_SCHEMA)
            writer.add_topic(MAP_TOPIC, map_schema, LATCHED_QOS)
            occupancy = occupancy_grid_message(grid, last, frame_id=map_frame_id)
            writer.write_message(MAP_TOPIC, map_schema, occupancy, log_time=t_ns, publish_time=t_ns)
        else:
            writer.add_topic(MAP_CLOUD_TOPIC, cloud_schema, LATCHED_QOS)
            cloud = point_cloud2(points_in_map(occupied_points(grid)), last, frame_id=map_frame_id)
            writer.write_message(MAP_CLOUD_TOPIC, cloud_schema, cloud, log_time=t_ns, publish_time=t_ns)
        count += 1
    return count


# --- nav2 map files ------------------------------------------------------------------------

NAV2_FREE_THRESH = 0.25
"""nav2 ``map_saver``'s default: cells of at most 25 % are written free (254)."""
NAV2_OCCUPIED_THRESH = 0.65
"""nav2 ``map_saver``'s default: cells of at least 65 % are written occupied (0)."""
NAV2_YAML_FREE_THRESH = 0.196
"""The ``free_thresh`` written into the YAML. nav2's ``map_server`` reads a pixel's occupancy as
``1 - shade/255``: 254 gives 0.004, 0 gives 1, and the unknown grey 205 gives 50/255 = 0.19608, which
map_saver's own 0.25 would read as *free*. 0.196 (ROS 1 map_saver's value) keeps 205 unknown, so the
map reads back as the three classes it was written with."""
_PGM_FREE, _PGM_OCCUPIED, _PGM_UNKNOWN = 254, 0, 205


def nav2_pixels(
    grid: OccupancyGrid,
    *,
    free_thresh: float = NAV2_FREE_THRESH,
    occupied_thresh: float = NAV2_OCCUPIED_THRESH,
) -> NDArray[np.uint8]:
    """The trinary PGM image of a floor plan as nav2's ``map_saver`` writes it, (height, width).

    From the OccupancyGrid values ``v`` (:func:`occupancy_grid_message`): unknown (-1) ->
    205; ``v <= round(100 free_thresh)`` -> 254 (free); ``v >= round(100
    occupied_thresh)`` -> 0 (occupied); in between -> 205. Image row 0 is the top of the
    map, its largest y: the grid's rows in reverse.
    """
    if not 0.0 <= free_thresh < occupied_thresh <= 1.0:
        raise EchoLocError(
            f"nav2 thresholds need 0 <= free < occupied <= 1, got {free_thresh} and {occupied_thresh}"
        )
    cells, _ = map_floor_plan(grid)
    values = occupancy_percent(cells).astype(np.int16)
    free_percent = int(np.rint(free_thresh * 100.0))
    occupied_percent = int(np.rint(occupied_thresh * 100.0))
    pixels = np.full(values.shape, _PGM_UNKNOWN, dtype=np.uint8)
    known = values >= 0
    pixels[known & (values <= free_percent)] = _PGM_FREE
    pixels[known & (values >= occupied_percent)] = _PGM_OCCUPIED
    return np.ascontiguousarray(pixels[::-1, :])


def _yaml_number(value: float) -> str:
    """A number for the YAML, to the nanometre: fixed point, no exponent (every YAML reader takes
    it as a float), no trailing zeros, "0" for zero of either sign."""
    text = f"{float(value):.9f}".rstrip("0").rstrip(".")
    return "0" if text in ("", "-0") else text


def write_nav2_map(
    grid: OccupancyGrid,
    path: str | Path,
    *,
    free_thresh: float = NAV2_FREE_THRESH,
    occupied_thresh: float = NAV2_OCCUPIED_THRESH,
) -> tuple[Path, Path]:
    """Write a floor plan as nav2 map files: ``NAME.yaml`` and the image ``NAME.pgm`` beside it.

    The image is binary PGM (P5, 8 bits) from :func:`nav2_pixels`: 254 free, 0 occupied,
    205 unknown, row 0 the map's top (largest y). The YAML has nav2's keys, written in
    this order: ``image`` (the PGM's file name, relative to the YAML), ``mode: trinary``,
    ``resolution`` (the cell, m), ``origin: [x, y, yaw]`` (the lower-left corner of the
    bottom-left cell in ``map``, yaw 0: :func:`map_floor_plan`), ``negate: 0``,
    ``occupied_thresh`` and ``free_thresh`` (:data:`NAV2_YAML_FREE_THRESH`, so that
    ``map_server`` reads the three shades back as written). ``nav2_map_server`` (and
    ROS 1's ``map_server``) loads it as the OccupancyGrid of :func:`occupancy_grid_message`
    reduced to free (0), occupied (100) and unknown (-1), at z = 0.

    Returns the YAML's and the PGM's paths. Raises :class:`EchoLocError` for a 3-D grid,
    a name not ending in ``.yaml`` or a file that cannot be written.
    """
    target = Path(path)
    if target.suffix.lower() not in (".yaml", ".yml"):
        raise EchoLocError(f"{target}: a nav2 map is NAME.yaml (with NAME.pgm beside it)")
    target = _check_path(target, target.suffix.lower())
    if not grid.spec.is_floor_plan:
        raise EchoLocError(f"{target}: a nav2 map is a floor plan; this grid is 3-D (drop --3d)")
    image = target.with_suffix(".pgm")
    pixels = nav2_pixels(grid, free_thresh=free_thresh, occupied_thresh=occupied_thresh)
    _, (x0, y0, _) = map_floor_plan(grid)
    height, width = pixels.shape
    lines = (
        f"image: {image.name}",
        "mode: trinary",
        f"resolution: {_yaml_number(grid.spec.cell_m)}",
        f"origin: [{_yaml_number(x0)}, {_yaml_number(y0)}, 0]",
        "negate: 0",
        f"occupied_thresh: {_yaml_number(occupied_thresh)}",
        f"free_thresh: {_yaml_number(min(NAV2_YAML_FREE_THRESH, free_thresh))}",
    )
    try:
        image.write_bytes(f"P5\n{width} {height}\n255\n".encode("ascii") + pixels.tobytes())
        target.write_text("\n".join(lines) + "\n", encoding="utf-8")
    except OSError as error:
        raise EchoLocError(f"{target}: cannot write: {error.strerror or error}") from error
    return target, image
