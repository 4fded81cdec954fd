"""Located objects for other programs: PLY point clouds and MCAP files of ROS 2 messages.

Positions are in the echoloc sensor frame, the ROS optical-frame convention of REP 103
(``x`` right, ``y`` down, ``z`` boresight, metres; ``docs/FORMATS.md``). Its ROS
frame id is :data:`SENSOR_FRAME_ID`, the child of the sensor's body frame
:data:`BODY_FRAME_ID` (REP 103 body axes: ``x`` forward along the boresight, ``y``
left, ``z`` up) by the fixed optical rotation :data:`OPTICAL_ROTATION_XYZW`. A robot
attaches the body frame with one static transform, for example ``ros2 run tf2_ros
static_transform_publisher --x 0.1 --z 0.3 --frame-id base_link --child-frame-id
echoloc_sensor_link`` for a sensor looking forward along the robot's ``x``
(``docs/ROS.md``).

MCAP files hold ROS 2 messages in CDR, written with the ``mcap`` and
``mcap-ros2-support`` libraries (no ROS installation), with the message definitions of
ROS 2 **Jazzy** embedded as schemas, and on every channel the QoS profile its
publisher offers in rosbag2's channel metadata (``offered_qos_profiles``), so that
``ros2 bag play`` latches ``/tf_static`` and maps (:func:`offered_qos_profiles`):

- ``/echoloc/objects``: one ``sensor_msgs/msg/PointCloud2`` per frame, fields
  :data:`POINT_FIELDS` (FLOAT32): ``x, y, z, intensity`` and the six values of the
  position covariance ``cov_xx, cov_yy, cov_zz, cov_xy, cov_xz, cov_yz``.
- ``/echoloc/range/rx{N}``: one ``sensor_msgs/msg/Range`` per receiver and frame, in
  the receiver's own frame ``echoloc_rx{N}`` (origin at the receiver, ``x`` along its
  boresight, as ``Range`` measures along ``x``).
- ``/tf_static``: one ``tf2_msgs/msg/TFMessage`` with the body-to-optical rotation,
  every ``echoloc_rx{N}`` placed in :data:`SENSOR_FRAME_ID` and, for a moving sensor,
  ``map`` -> ``odom`` (identity).
- ``/tf``, when the recording has ``sensor_poses``: per frame ``odom`` ->
  :data:`BODY_FRAME_ID`, the sensor's pose in the z-up ``map`` frame of REP 105
  (:func:`body_pose_in_map`).
- ``/echoloc/surfaces``, when objects carry reflector classes (``--classes``): one
  ``visualization_msgs/msg/MarkerArray`` per frame (:func:`surface_markers`): a
  DELETEALL, then each plane as a thin CUBE over the patch its echoes met and each
  corner as a LINE_LIST along its edge.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from mcap.records import Schema
from mcap.writer import CompressionType
from mcap_ros2.writer import Writer as Ros2Writer
from numpy.typing import ArrayLike, NDArray

from echoloc.errors import EchoLocError, missing_directory
from echoloc.io.recording import Recording
from echoloc.localise.locate import FrameObjects, LocatedObject
from echoloc.physics.transducer import PRESETS, piston_beam_angles
from echoloc.pipeline import recording_speed_of_sound_m_s
from echoloc.tof.echoes import frame_time_s

SENSOR_FRAME_ID = "echoloc_sensor_optical_frame"
"""ROS frame id of the sensor frame (REP 103 optical convention: x right, y down, z boresight)."""
BODY_FRAME_ID = "echoloc_sensor_link"
"""ROS frame id of the sensor's body frame (REP 103: x forward along the boresight, y left, z up),
the parent of :data:`SENSOR_FRAME_ID`; same origin."""
ROS_MAP_FRAME_ID = "map"
"""ROS frame id of the fixed world frame (REP 105 ``map``: z up) of moving sensors and maps."""
ODOM_FRAME_ID = "odom"
"""ROS frame id between ``map`` and the body (REP 105); echoloc publishes ``map`` -> ``odom`` as the
identity, so the body's pose in ``odom`` is its pose in ``map``."""

OPTICAL_TO_BODY = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""``p_body = OPTICAL_TO_BODY @ p_optical``: body x = optical z, body y = -optical x, body z =
-optical y. Its columns are the optical axes in the body frame. The same matrix takes echoloc's
world frame (the sensor frame of the identity pose: y down) to the z-up ``map``."""
OPTICAL_ROTATION_XYZW = (-0.5, 0.5, -0.5, 0.5)
"""The quaternion (x, y, z, w) of :data:`OPTICAL_TO_BODY`: the rotation of the ``/tf_static``
transform from the body frame (parent) to the optical frame (child), REP 103's
``roll = -pi/2, yaw = -pi/2``."""

OBJECTS_TOPIC = "/echoloc/objects"
SURFACES_TOPIC = "/echoloc/surfaces"
RANGE_TOPIC_PREFIX = "/echoloc/range/rx"
TF_STATIC_TOPIC = "/tf_static"
TF_TOPIC = "/tf"
ROS_DISTRIBUTION = "jazzy"
"""The ROS 2 distribution whose message definitions the MCAP schemas carry (``Range`` has ``variance``)."""

_SEPARATOR = "=" * 80

# Message definitions (ROS 2 Jazzy, common_interfaces / rcl_interfaces / geometry2);
# only the comments are left out, which do not change the type or its encoding.
_TIME_MSG = """int32 sec
uint32 nanosec
"""
_HEADER_MSG = """builtin_interfaces/Time stamp
string frame_id
"""
_POINT_FIELD_MSG = """uint8 INT8    = 1
uint8 UINT8   = 2
uint8 INT16   = 3
uint8 UINT16  = 4
uint8 INT32   = 5
uint8 UINT32  = 6
uint8 FLOAT32 = 7
uint8 FLOAT64 = 8

string name
uint32 offset
uint8  datatype
uint32 count
"""
_POINT_CLOUD2_MSG = """std_msgs/Header header

uint32 height
uint32 width

PointField[] fields

bool    is_bigendian
uint32  point_step
uint32  row_step
uint8[] data

bool is_dense
"""
_RANGE_MSG = """std_msgs/Header header

uint8 ULTRASOUND=0
uint8 INFRARED=1

uint8 radiation_type

float32 field_of_view

float32 min_range
float32 max_range

float32 range

float32 variance
"""
_VECTOR3_MSG = """float64 x
float64 y
float64 z
"""
_QUATERNION_MSG = """float64 x 0
float64 y 0
float64 z 0
float64 w 1
"""
_TRANSFORM_MSG = """Vector3 translation
Quaternion rotation
"""
_TRANSFORM_STAMPED_MSG = """std_msgs/Header header
string child_frame_id
Transform transform
"""
_TF_MESSAGE_MSG = """geometry_msgs/TransformStamped[] transforms
"""
_MARKER_ARRAY_MSG = """Marker[] markers
"""
_MARKER_MSG = """int32 ARROW=0
int32 CUBE=1
int32 SPHERE=2
int32 CYLINDER=3
int32 LINE_STRIP=4
int32 LINE_LIST=5
int32 CUBE_LIST=6
int32 SPHERE_LIST=7
int32 POINTS=8
int32 TEXT_VIEW_FACING=9
int32 MESH_RESOURCE=10
int32 TRIANGLE_LIST=11

int32 ADD=0
int32 MODIFY=0
int32 DELETE=2
int32 DELETEALL=3

std_msgs/Header header
string ns
int32 id
int32 type
int32 action
geometry_msgs/Pose pose
geometry_msgs/Vector3 scale
std_msgs/ColorRGBA color
builtin_interfaces/Duration lifetime
bool frame_locked

geometry_msgs/Point[] points
std_msgs/ColorRGBA[] colors

string texture_resource
sensor_msgs/CompressedImage texture
UVCoordinate[] uv_coordinates

string text

string mesh_resource
MeshFile mesh_file
bool mesh_use_embedded_materials
"""
_POSE_MSG = """Point position
Quaternion orientation
"""
_POINT_MSG = """float64 x
float64 y
float64 z
"""
_COLOR_RGBA_MSG = """float32 r
float32 g
float32 b
float32 a
"""
_DURATION_MSG = """int32 sec
uint32 nanosec
"""
_COMPRESSED_IMAGE_MSG = """std_msgs/Header header
string format
uint8[] data
"""
_UV_COORDINATE_MSG = """float32 u
float32 v
"""
_MESH_FILE_MSG = """string filename
uint8[] data
"""


def _schema_text(main: str, *dependencies: tuple[str, str]) -> str:
    """A ``ros2msg`` schema: the main definition, then each dependency after a separator line."""
    parts = [main]
    for name, text in dependencies:
        parts.append(f"{_SEPARATOR}\nMSG: {name}\n{text}")
    return "\n".join(parts)


POINT_CLOUD2_SCHEMA = _schema_text(
    _POINT_CLOUD2_MSG,
    ("std_msgs/Header", _HEADER_MSG),
    ("builtin_interfaces/Time", _TIME_MSG),
    ("sensor_msgs/PointField", _POINT_FIELD_MSG),
)
RANGE_SCHEMA = _schema_text(
    _RANGE_MSG, ("std_msgs/Header", _HEADER_MSG), ("builtin_interfaces/Time", _TIME_MSG)
)
TF_MESSAGE_SCHEMA = _schema_text(
    _TF_MESSAGE_MSG,
    ("geometry_msgs/TransformStamped", _TRANSFORM_STAMPED_MSG),
    ("std_msgs/Header", _HEADER_MSG),
    ("builtin_interfaces/Time", _TIME_MSG),
    ("geometry_msgs/Transform", _TRANSFORM_MSG),
    ("geometry_msgs/Vector3", _VECTOR3_MSG),
    ("geometry_msgs/Quaternion", _QUATERNION_MSG),
)

MARKER_ARRAY_SCHEMA = _schema_text(
    _MARKER_ARRAY_MSG,
    ("visualization_msgs/Marker", _MARKER_MSG),
    ("std_msgs/Header", _HEADER_MSG),
    ("builtin_interfaces/Time", _TIME_MSG),
    ("geometry_msgs/Pose", _POSE_MSG),
    ("geometry_msgs/Point", _POINT_MSG),
    ("geometry_msgs/Quaternion", _QUATERNION_MSG),
    ("geometry_msgs/Vector3", _VECTOR3_MSG),
    ("std_msgs/ColorRGBA", _COLOR_RGBA_MSG),
    ("builtin_interfaces/Duration", _DURATION_MSG),
    ("sensor_msgs/CompressedImage", _COMPRESSED_IMAGE_MSG),
    ("visualization_msgs/UVCoordinate", _UV_COORDINATE_MSG),
    ("visualization_msgs/MeshFile", _MESH_FILE_MSG),
)

COVARIANCE_FIELDS = ("cov_xx", "cov_yy", "cov_zz", "cov_xy", "cov_xz", "cov_yz")
"""The six values of a position's symmetric 3x3 covariance, m^2, in the frame of the points: the
diagonal first (the fields before the off-diagonal ones were added keep their offsets)."""
_COVARIANCE_INDEX = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))
POINT_FIELDS = ("x", "y", "z", "intensity", *COVARIANCE_FIELDS)
"""The PointCloud2 fields (and PLY properties), in order, each one FLOAT32 (``PointField.FLOAT32 = 7``)."""
_FLOAT32 = 7
RADIATION_ULTRASOUND = 0


def receiver_frame_id(receiver: int) -> str:
    """ROS frame id of receiver ``receiver``'s ``Range`` messages: origin at it, x along its axis."""
    return f"echoloc_rx{receiver}"


# --- the points -----------------------------------------------------------------------


ObjectsInput = FrameObjects | Sequence[FrameObjects] | Sequence[LocatedObject] | NDArray[np.float64]


def _as_frames(objects: ObjectsInput, source: str) -> list[FrameObjects]:
    """Normalise the accepted inputs to a list of frames.

    An (n, 3) array of positions becomes one frame with unknown (NaN) covariance and
    score 1; a sequence of :class:`LocatedObject` becomes frame 0.
    """
    if isinstance(objects, FrameObjects):
        return [objects]
    if isinstance(objects, np.ndarray):
        points = np.asarray(objects, dtype=float)
        if points.ndim != 2 or points.shape[1] != 3:
            raise EchoLocError(f"{source}: points must have shape (n, 3), got {points.shape}")
        nan_cov = np.full((3, 3), np.nan)
        located = tuple(LocatedObject(p, nan_cov, (), (), math.nan, 1.0) for p in points)
        return [FrameObjects(0, 0.0, located)]
    items = list(objects)
    if all(isinstance(item, FrameObjects) for item in items):
        return [item for item in items if isinstance(item, FrameObjects)]
    if all(isinstance(item, LocatedObject) for item in items):
        return [FrameObjects(0, 0.0, tuple(item for item in items if isinstance(item, LocatedObject)))]
    raise EchoLocError(f"{source}: expected FrameObjects, LocatedObject items or an (n, 3) array")


def covariance_values(covariance_m2: ArrayLike) -> NDArray[np.float64]:
    """The six :data:`COVARIANCE_FIELDS` of a 3x3 covariance (symmetrised: the mean of the two
    off-diagonal halves)."""
    c = np.asarray(covariance_m2, dtype=float).reshape(3, 3)
    c = 0.5 * (c + c.T)
    return np.array([c[i, j] for i, j in _COVARIANCE_INDEX])


def _point_table(
    frame: FrameObjects, intensity: ArrayLike | None, source: str
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]:
    """Positions (n, 3), intensities (n,), covariances (n, 6: :data:`COVARIANCE_FIELDS`) and
    receiver counts (n,)."""
    n = len(frame.objects)
    positions = np.array([o.position_m for o in frame.objects], dtype=float).reshape(n, 3)
    covariances = np.array([covariance_values(o.covariance_m2) for o in frame.objects], dtype=float).reshape(
        n, len(COVARIANCE_FIELDS)
    )
    support = np.array([len(o.receivers) for o in frame.objects], dtype=np.int64)
    if intensity is None:
        values = np.array([o.score for o in frame.objects], dtype=float)
    else:
        values = np.asarray(intensity, dtype=float).reshape(-1)
        if values.shape != (n,):
            raise EchoLocError(f"{source}: frame {frame.frame} has {n} objects but {values.size} intensities")
    return positions, values, covariances, support


def _intensity_for(intensities: Sequence[ArrayLike] | None, index: int, n_frames: int, source: str) -> Any:
    if intensities is None:
        return None
    if len(intensities) != n_frames:
        raise EchoLocError(f"{source}: {len(intensities)} intensity arrays for {n_frames} frames")
    return intensities[index]


def _check_path(path: str | Path, suffix: str) -> Path:
    target = Path(path)
    if target.suffix.lower() != suffix:
        raise EchoLocError(
            f"{target}: expected a {suffix} file name, got extension {target.suffix or '(none)'!r}"
        )
    if problem := missing_directory(target):
        raise EchoLocError(f"{target}: {problem}")
    if target.is_dir():
        raise EchoLocError(f"{target}: is a directory")
    return target


# --- PLY ----------------------------------------------------------------------------------


def write_ply(
    path: str | Path,
    objects: ObjectsInput,
    *,
    binary: bool = True,
    per_frame: bool = False,
    intensities: Sequence[ArrayLike] | None = None,
    double: bool = False,
    comments: Sequence[str] | None = None,
) -> list[Path]:
    """Write located objects as a PLY point cloud (Bourke's polygon file format, 1994).

    Vertex properties: ``x, y, z`` (m, sensor frame, float32 or with ``double`` float64),
    ``intensity`` (the object's localisation score, or the given per-frame
    ``intensities``, e.g. echo amplitudes), ``cov_xx, cov_yy, cov_zz, cov_xy, cov_xz,
    cov_yz`` (the position covariance, m^2: :data:`COVARIANCE_FIELDS`), ``receivers``
    (how many receivers support the object)
    and, when all frames share one file, ``frame`` (the frame index). ``binary``
    writes ``binary_little_endian``, else ``ascii``. With ``per_frame`` one file per
    frame is written next to ``path``, named ``{stem}_{frame:06d}.ply``. ``comments``
    replace the header's description of the points (what they are, their frame and
    what their intensity means) for other kinds of points.

    Returns the paths written. Raises :class:`EchoLocError` for a name not ending in
    ``.ply``, a missing directory or a file that cannot be written.
    """
    target = _check_path(path, ".ply")
    frames = _as_frames(objects, str(target))
    source = str(target)
    tables = [
        _point_table(frame, _intensity_for(intensities, i, len(frames), source), source)
        for i, frame in enumerate(frames)
    ]
    if per_frame:
        written = []
        for frame, table in zip(frames, tables, strict=True):
            out = target.with_name(f"{target.stem}_{frame.frame:06d}.ply")
            _write_ply_file(out, [table], None, binary=binary, double=double, comments=comments)
            written.append(out)
        return written
    frame_ids = [frame.frame for frame in frames]
    _write_ply_file(target, tables, frame_ids, binary=binary, double=double, comments=comments)
    return [target]


def _write_ply_file(
    path: Path,
    tables: list[tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.int64]]],
    frame_ids: list[int] | None,
    *,
    binary: bool,
    double: bool,
    comments: Sequence[str] | None = None,
) -> None:
    float_type, float_name = ("<f8", "double") if double else ("<f4", "float")
    columns: list[tuple[str, str, str]] = [(name, float_type, float_name) for name in POINT_FIELDS]
    columns.append(("receivers", "u1", "uchar"))
    if frame_ids is not None:
        columns.append(("frame", "<i4", "int"))
    n = sum(len(t[0]) for t in tables)
    vertices = np.zeros(n, dtype=[(name, dtype) for name, dtype, _ in columns])
    row = 0
    for index, (positions, values, covariances, support) in enumerate(tables):
        rows = slice(row, row + len(positions))
        for axis, name in enumerate(("x", "y", "z")):
            vertices[name][rows] = positions[:, axis]
        vertices["intensity"][rows] = values
        for axis, name in enumerate(COVARIANCE_FIELDS):
            vertices[name][rows] = covariances[:, axis]
        vertices["receivers"][rows] = np.clip(support, 0, 255)
        if frame_ids is not None:
            vertices["frame"][rows] = frame_ids[index]
        row += len(positions)
    described = comments or (
        "echoloc located objects",
        f"frame_id {SENSOR_FRAME_ID}: REP 103 optical frame, x right, y down, z boresight, metres",
        "intensity: localisation score of the object (or the echo amplitude if given)",
        "cov_xx cov_yy cov_zz cov_xy cov_xz cov_yz: the position covariance, m^2 (NaN: unknown)",
        "receivers: number of receivers whose echoes support the object",
    )
    header = [
        "ply",
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
        *(f"comment {line}" for line in described),
    ]
    if frame_ids is not None:
        header.append("comment frame: index of the recording frame the object was located in")
    header.append(f"element vertex {n}")
    header.extend(f"property {ply_name} {name}" for name, _, ply_name in columns)
    header.append("end_header")
    try:
        with path.open("wb") as stream:
            stream.write(("\n".join(header) + "\n").encode("ascii"))
            if binary:
                stream.write(vertices.tobytes())
            else:
                float_format = "%.17g" if double else "%.9g"
                formats = [float_format if name in POINT_FIELDS else "%d" for name, _, _ in columns]
                for vertex in vertices:
                    line = " ".join(fmt % value for fmt, value in zip(formats, vertex.tolist(), strict=True))
                    stream.write((line + "\n").encode("ascii"))
    except OSError as error:
        raise EchoLocError(f"{path}: cannot write: {error.strerror or error}") from error


# --- MCAP (ROS 2) -------------------------------------------------------------------------


def ros_time(time_s: float) -> dict[str, int]:
    """``builtin_interfaces/Time`` of ``time_s`` seconds: whole seconds and nanoseconds, nanosec < 1e9."""
    if not (math.isfinite(time_s) and time_s < 2**31):
        # Checked before the nanoseconds are rounded: 1e300 s has no integer count of them.
        raise EchoLocError(f"stamp {time_s} s does not fit a ROS time (int32 seconds)")
    total_ns = round(time_s * 1e9)
    if total_ns < 0:
        raise EchoLocError(f"stamp {time_s} s is before 1970 (ROS time must not be negative)")
    sec, nanosec = divmod(total_ns, 1_000_000_000)
    if sec > 2**31 - 1:
        raise EchoLocError(f"stamp {time_s} s does not fit a ROS time (int32 seconds)")
    return {"sec": int(sec), "nanosec": int(nanosec)}


def point_cloud2(
    frame: FrameObjects,
    stamp_s: float,
    *,
    intensity: ArrayLike | None = None,
    frame_id: str = SENSOR_FRAME_ID,
) -> dict[str, Any]:
    """A ``sensor_msgs/msg/PointCloud2`` (as a dict) of one frame's objects.

    An unordered cloud (height 1), little-endian, 10 FLOAT32 fields per point
    (:data:`POINT_FIELDS`: position, intensity and the full covariance of each point in
    ``frame_id``, m and m^2): point_step 40 bytes, row_step 40 * width; ``is_dense`` is
    true when no value is NaN or infinite.
    """
    positions, values, covariances, _ = _point_table(frame, intensity, f"frame {frame.frame}")
    n = len(positions)
    table = np.column_stack([positions, values, covariances]).astype("<f4").reshape(n, len(POINT_FIELDS))
    point_step = 4 * len(POINT_FIELDS)
    fields = [
        {"name": name, "offset": 4 * i, "datatype": _FLOAT32, "count": 1}
        for i, name in enumerate(POINT_FIELDS)
    ]
    return {
        "header": {"stamp": ros_time(stamp_s), "frame_id": frame_id},
        "height": 1,
        "width": n,
        "fields": fields,
        "is_bigendian": False,
        "point_step": point_step,
        "row_step": point_step * n,
        "data": table.tobytes(),
        "is_dense": bool(np.all(np.isfinite(table))),
    }


PLANE_THICKNESS_M = 0.005
"""How thick a plane's marker is drawn, m."""
CORNER_MARKER_LENGTH_M = 0.3
"""How long a corner's edge is drawn, centred on its foot, m (the echoes tell where the edge is,
not where it ends)."""
_PLANE_COLOUR = {"r": 0.2, "g": 0.6, "b": 1.0, "a": 0.7}
_CORNER_COLOUR = {"r": 1.0, "g": 0.5, "b": 0.1, "a": 1.0}
_MARKER_CUBE, _MARKER_LINE_LIST, _MARKER_DELETEALL = 1, 5, 3


def _marker(header: dict[str, Any], ns: str, marker_id: int, kind: int, action: int = 0) -> dict[str, Any]:
    """A ``visualization_msgs/msg/Marker`` with every field at its default."""
    return {
        "header": header,
        "ns": ns,
        "id": marker_id,
        "type": kind,
        "action": action,
        "pose": {
            "position": {"x": 0.0, "y": 0.0, "z": 0.0},
            "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
        },
        "scale": {"x": 1.0, "y": 1.0, "z": 1.0},
        "color": {"r": 0.0, "g": 0.0, "b": 0.0, "a": 0.0},
        "lifetime": {"sec": 0, "nanosec": 0},
        "frame_locked": False,
        "points": [],
        "colors": [],
        "texture_resource": "",
        "texture": {"header": header, "format": "", "data": b""},
        "uv_coordinates": [],
        "text": "",
        "mesh_resource": "",
        "mesh_file": {"filename": "", "data": b""},
        "mesh_use_embedded_materials": False,
    }


def surface_markers(
    frame: FrameObjects, stamp_s: float, *, frame_id: str = SENSOR_FRAME_ID
) -> dict[str, Any]:
    """A ``visualization_msgs/msg/MarkerArray`` (as a dict) of one frame's planes and corners.

    First a DELETEALL (the markers of the previous frame go), then per plane a CUBE
    (namespace ``planes``) centred on the patch its echoes met: its z axis along the
    normal, x and y spanning the specular points (at least 1 cm), :data:`PLANE_THICKNESS_M`
    thick; per corner a LINE_LIST (namespace ``corners``) of :data:`CORNER_MARKER_LENGTH_M`
    along the edge through its foot. The id is the object's index in the frame.
    """
    header = {"stamp": ros_time(stamp_s), "frame_id": frame_id}
    markers = [_marker(header, "", 0, _MARKER_CUBE, _MARKER_DELETEALL)]
    for index, obj in enumerate(frame.objects):
        surface = obj.surface
        if surface is None:
            continue
        if surface.kind == "plane" and surface.normal is not None and surface.specular_points_m is not None:
            normal = np.asarray(surface.normal, dtype=float)
            rotation = _plane_frame(normal)
            points = np.asarray(surface.specular_points_m, dtype=float)
            centre = points.mean(axis=0)
            span = (points - centre) @ rotation[:, :2]
            size = np.maximum(span.max(axis=0) - span.min(axis=0), 0.01)
            middle = centre + rotation[:, :2] @ (0.5 * (span.max(axis=0) + span.min(axis=0)))
            marker = _marker(header, "planes", index, _MARKER_CUBE)
            qx, qy, qz, qw = (float(v) for v in _matrix_quaternion(rotation))
            marker["pose"] = {
                "position": dict(zip("xyz", (float(v) for v in middle), strict=True)),
                "orientation": {"x": qx, "y": qy, "z": qz, "w": qw},
            }
            marker["scale"] = {"x": float(size[0]), "y": float(size[1]), "z": PLANE_THICKNESS_M}
            marker["color"] = _PLANE_COLOUR
            markers.append(marker)
        elif surface.kind == "corner" and surface.edge_direction is not None:
            along = 0.5 * CORNER_MARKER_LENGTH_M * np.asarray(surface.edge_direction, dtype=float)
            foot = np.asarray(obj.position_m, dtype=float)
            marker = _marker(header, "corners", index, _MARKER_LINE_LIST)
            marker["points"] = [
                dict(zip("xyz", (float(v) for v in end), strict=True)) for end in (foot - along, foot + along)
            ]
            marker["scale"] = {"x": 0.01, "y": 0.0, "z": 0.0}
            marker["color"] = _CORNER_COLOUR
            markers.append(marker)
    return {"markers": markers}


def _plane_frame(normal: NDArray[np.float64]) -> NDArray[np.float64]:
    """A rotation matrix whose third column is ``normal`` (a right-handed orthonormal basis)."""
    helper = np.array([0.0, 1.0, 0.0]) if abs(normal[1]) < 0.9 else np.array([1.0, 0.0, 0.0])
    x = np.cross(helper, normal)
    x /= np.linalg.norm(x)
    y = np.cross(normal, x)
    return np.column_stack([x, y, normal])


def receiver_ranges_m(
    frame: FrameObjects, receivers_m: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per receiver, distance to the nearest object its echoes support, and that distance's variance.

    The range is the Euclidean distance ``|p - r|`` from the receiver to the object,
    not half the echo's path (which equals it only for a transmitter at the receiver);
    its variance is ``u^T C u`` with ``u`` the unit vector from receiver to object and
    ``C`` the object's covariance (first-order propagation). A receiver that supports
    no object gets ``+inf`` (REP 117: no detection) and variance 0 (unknown).
    """
    n_rx = len(receivers_m)
    ranges = np.full(n_rx, np.inf)
    variances = np.zeros(n_rx)
    for obj in frame.objects:
        for rx in set(obj.receivers):
            if not 0 <= rx < n_rx:
                continue
            offset = np.asarray(obj.position_m, dtype=float) - receivers_m[rx]
            distance = float(np.linalg.norm(offset))
            if distance < ranges[rx]:
                ranges[rx] = distance
                u = offset / distance if distance > 0 else np.zeros(3)
                variance = float(u @ np.asarray(obj.covariance_m2, dtype=float) @ u)
                variances[rx] = variance if np.isfinite(variance) and variance > 0 else 0.0
    return ranges, variances


def _axis_quaternion(axis: NDArray[np.float64]) -> NDArray[np.float64]:
    """Quaternion (x, y, z, w) of a frame whose x is ``axis`` (in the optical frame) and z is up (-y).

    For ``axis`` = +z this is REP 103's optical-to-body rotation: body x = optical z,
    body y = -optical x, body z = -optical y.
    """
    x = np.asarray(axis, dtype=float)
    x = x / np.linalg.norm(x)
    up = np.array([0.0, -1.0, 0.0])
    if abs(float(x @ up)) > 0.999:
        up = np.array([0.0, 0.0, 1.0])
    y = np.cross(up, x)
    y /= np.linalg.norm(y)
    z = np.cross(x, y)
    return _matrix_quaternion(np.column_stack([x, y, z]))


def _matrix_quaternion(m: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit quaternion (x, y, z, w) of rotation matrix ``m`` (Shepperd 1978, largest-pivot branch)."""
    trace = float(np.trace(m))
    diagonal = np.diag(m)
    if trace >= diagonal.max():
        w = 0.5 * math.sqrt(1.0 + trace)
        q = np.array([m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1], 0.0]) / (4 * w)
        q[3] = w
    else:
        i = int(np.argmax(diagonal))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = np.zeros(4)
        q[i] = 0.25 * s
        q[j] = (m[j, i] + m[i, j]) / s
        q[k] = (m[k, i] + m[i, k]) / s
        q[3] = (m[k, j] - m[j, k]) / s
    return q / np.linalg.norm(q)


# --- frames (REP 103 / REP 105) ------------------------------------------------------------


def _quaternion_matrix(q: ArrayLike) -> NDArray[np.float64]:
    """Rotation matrix of the quaternion (x, y, z, w), normalised first."""
    x, y, z, w = np.asarray(q, dtype=float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def body_pose_in_map(pose: ArrayLike) -> NDArray[np.float64]:
    """The body frame's pose ``[x, y, z, qx, qy, qz, qw]`` in the z-up ``map`` frame (REP 105).

    ``pose`` is echoloc's sensor pose (a recording's ``sensor_poses`` row or a trajectory's):
    the optical sensor frame in echoloc's world frame, whose axes are those of the sensor at
    the identity pose (x right, y down, z ahead), ``p_world = R(q) p_sensor + t``. With
    ``C`` = :data:`OPTICAL_TO_BODY`, which takes that world frame to ``map`` (map x = world
    z, map y = -world x, map z = -world y) and the optical frame to the body frame, the
    body's pose is ``t_map = C t`` and ``R_map = C R(q) C^T``: a sensor at the identity
    pose has its body frame on ``map``'s axes, looking along ``map``'s x.
    """
    row = np.asarray(pose, dtype=float).reshape(7)
    translation = OPTICAL_TO_BODY @ row[:3]
    rotation = OPTICAL_TO_BODY @ _quaternion_matrix(row[3:]) @ OPTICAL_TO_BODY.T
    return np.concatenate([translation, _matrix_quaternion(rotation)])


def transform_stamped(
    parent: str, child: str, stamp_s: float, translation: ArrayLike, rotation_xyzw: ArrayLike
) -> dict[str, Any]:
    """A ``geometry_msgs/msg/TransformStamped`` (as a dict): ``child``'s pose in ``parent``, so that
    ``p_parent = R p_child + translation``."""
    tx, ty, tz = (float(v) for v in np.asarray(translation, dtype=float).reshape(3))
    qx, qy, qz, qw = (float(v) for v in np.asarray(rotation_xyzw, dtype=float).reshape(4))
    return {
        "header": {"stamp": ros_time(stamp_s), "frame_id": parent},
        "child_frame_id": child,
        "transform": {
            "translation": {"x": tx, "y": ty, "z": tz},
            "rotation": {"x": qx, "y": qy, "z": qz, "w": qw},
        },
    }


_IDENTITY_XYZW = (0.0, 0.0, 0.0, 1.0)


def optical_transform(stamp_s: float, body_frame_id: str, optical_frame_id: str) -> dict[str, Any]:
    """The static transform from the body frame to the optical sensor frame: same origin,
    rotation :data:`OPTICAL_ROTATION_XYZW`."""
    return transform_stamped(body_frame_id, optical_frame_id, stamp_s, (0.0, 0.0, 0.0), OPTICAL_ROTATION_XYZW)


def map_odom_transform(stamp_s: float, map_frame_id: str, odom_frame_id: str) -> dict[str, Any]:
    """``map`` -> ``odom`` as the identity: echoloc's poses are already in the fixed frame."""
    return transform_stamped(map_frame_id, odom_frame_id, stamp_s, (0.0, 0.0, 0.0), _IDENTITY_XYZW)


def pose_transform(
    pose: ArrayLike, stamp_s: float, parent_frame_id: str, body_frame_id: str
) -> dict[str, Any]:
    """The body's pose in ``parent_frame_id`` (``odom`` or ``map``) from an echoloc sensor pose
    (:func:`body_pose_in_map`)."""
    body = body_pose_in_map(pose)
    return transform_stamped(parent_frame_id, body_frame_id, stamp_s, body[:3], body[3:])


# --- QoS in MCAP (rosbag2's channel metadata) -------------------------------------------------

_QOS_INFINITE = ("    sec: 9223372036", "    nsec: 854775807")  # RMW_DURATION_INFINITE
_QOS_KEEP_LAST = 1  # rmw_qos_history_policy_e
_QOS_RELIABLE = 1  # rmw_qos_reliability_policy_e
_QOS_TRANSIENT_LOCAL, _QOS_VOLATILE = 1, 2  # rmw_qos_durability_policy_e
_QOS_LIVELINESS_AUTOMATIC = 1  # rmw_qos_liveliness_policy_e


def offered_qos_profiles(*, transient_local: bool, depth: int) -> str:
    """One publisher's QoS as rosbag2 stores it in an MCAP channel's ``offered_qos_profiles``.

    A YAML sequence of one profile in the layout ``ros2 bag record`` writes (yaml-cpp's
    block style, no trailing newline), with the numeric values of rmw's enums that rosbag2
    uses for metadata up to version 8: history 1 (keep last) with ``depth``, reliability 1
    (reliable), durability 1 (transient local) or 2 (volatile), liveliness 1 (automatic),
    deadline, lifespan and lease duration infinite (9223372036 s 854775807 ns). rosbag2
    reads the numbers when the file's ``rosbag2`` metadata has no ``serialized_metadata``
    (as the MCAP files of Humble and Iron), which :class:`QosWriter` writes; on replay it
    offers the recorded durability, so transient-local topics are latched again.
    """
    if int(depth) < 1:
        raise EchoLocError(f"a QoS depth is at least 1, got {depth}")
    lines = (
        f"- history: {_QOS_KEEP_LAST}",
        f"  depth: {int(depth)}",
        f"  reliability: {_QOS_RELIABLE}",
        f"  durability: {_QOS_TRANSIENT_LOCAL if transient_local else _QOS_VOLATILE}",
        "  deadline:",
        *_QOS_INFINITE,
        "  lifespan:",
        *_QOS_INFINITE,
        f"  liveliness: {_QOS_LIVELINESS_AUTOMATIC}",
        "  liveliness_lease_duration:",
        *_QOS_INFINITE,
        "  avoid_ros_namespace_conventions: false",
    )
    return "\n".join(lines)


LATCHED_QOS = offered_qos_profiles(transient_local=True, depth=1)
"""``/tf_static`` and maps: reliable, transient local, keep last 1 (tf2's static broadcaster)."""
TF_QOS = offered_qos_profiles(transient_local=False, depth=100)
"""``/tf``: reliable, volatile, keep last 100 (tf2's broadcaster)."""
STREAM_QOS = offered_qos_profiles(transient_local=False, depth=10)
"""Per-frame data (objects, ranges, markers): reliable, volatile, keep last 10 (rclcpp's default)."""


class QosWriter(Ros2Writer):
    """``mcap_ros2``'s writer whose channels carry their publisher's QoS (:func:`offered_qos_profiles`).

    It writes the ``rosbag2`` metadata record (``ROS_DISTRO``) that tells rosbag2 how the
    QoS values are written; :meth:`add_topic` registers a channel before its first message.
    """

    def __init__(self, stream: Any, *, compression: CompressionType = CompressionType.ZSTD) -> None:
        super().__init__(stream, compression=compression)
        self.add_metadata("rosbag2", {"ROS_DISTRO": ROS_DISTRIBUTION})

    def add_topic(self, topic: str, schema: Schema, qos: str) -> None:
        """Register ``topic`` (message encoding CDR, ``schema``) with ``offered_qos_profiles = qos``."""
        if topic in self._channel_ids:
            raise EchoLocError(f"topic {topic} is registered twice")
        self._channel_ids[topic] = self._writer.register_channel(
            topic=topic, message_encoding="cdr", schema_id=schema.id, metadata={"offered_qos_profiles": qos}
        )


# --- Range --------------------------------------------------------------------------------

DEFAULT_RANGE_TRANSDUCER = "electrostatic50"
"""The transducer model assumed for a recording without ``carrier_hz`` (the report's 50 kHz one)."""


def range_field_of_view_rad(recording: Recording, speed_of_sound_m_s: float) -> float:
    """``sensor_msgs/Range.field_of_view`` of the recording's receivers, rad (a full angle).

    Twice the recording's ``field_of_view_deg`` (the half-angle of the beam's first null)
    when it has one. Otherwise the full first-null angle of the piston of the transducer
    model in :data:`echoloc.physics.transducer.PRESETS` whose centre frequency is nearest
    the recording's ``carrier_hz`` (in ratio), at that carrier and ``speed_of_sound_m_s``
    (:func:`echoloc.physics.transducer.piston_beam_angles`): for a 50 kHz carrier the
    report's electrostatic transducer, 36.0° at 20 °C (15° at -3 dB); a recording without a carrier takes
    :data:`DEFAULT_RANGE_TRANSDUCER`. A piston too small to have a null in front (``ka <
    3.83``, the CH101 model) hears the whole half-space: pi. An echo can come from anywhere
    inside the main lobe, so the first null, not the -3 dB width, bounds where the object
    may be, as ``Range`` asks; set ``field_of_view_deg`` in the recording when the beam is known.
    """
    if recording.field_of_view_deg is not None:
        return 2.0 * math.radians(recording.field_of_view_deg)
    carrier = recording.carrier_hz
    if carrier is None or not (math.isfinite(carrier) and carrier > 0):
        carrier = PRESETS[DEFAULT_RANGE_TRANSDUCER].centre_frequency_hz
    model = min(PRESETS.values(), key=lambda t: abs(math.log(t.centre_frequency_hz / carrier)))
    full = piston_beam_angles(model.radius_m, carrier, speed_of_sound_m_s).full_angle_null_rad
    return full if math.isfinite(full) else math.pi


def _max_range_m(recording: Recording, speed_m_s: float, receiver: int) -> float:
    """Farthest reflector distance from receiver whose echo still falls inside the window.

    An echo of path ``L`` from transmitter ``t`` to receiver ``r`` via ``p`` has
    ``|p - r| <= (L + |t - r|) / 2`` (triangle inequality); ``L`` at most the window's
    ``n_samples / sample_rate_hz`` times the speed of sound. The largest over transmitters.
    """
    window_path_m = recording.n_samples / recording.sample_rate_hz * speed_m_s
    baselines = np.linalg.norm(recording.transmitters_m - recording.receivers_m[receiver], axis=1)
    return float((window_path_m + baselines.max()) / 2)


_COMPRESSIONS = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}


class RosObjectsWriter:
    """Located objects as ROS 2 (Jazzy) messages in an MCAP file, a frame at a time: what
    :func:`write_mcap` writes for a whole recording and ``echoloc stream --mcap`` as frames
    arrive (``ros2 bag play`` replays it; :meth:`close` finishes the file).

    Per frame (:meth:`add`) one ``sensor_msgs/msg/PointCloud2`` on ``/echoloc/objects`` in
    ``frame_id`` (:func:`point_cloud2`: position, intensity, full covariance); with a
    ``header`` and ``ranges``, one ``sensor_msgs/msg/Range`` per receiver on
    ``/echoloc/range/rx{N}`` (frame ``echoloc_rx{N}``; :func:`receiver_ranges_m`;
    ULTRASOUND; field of view :func:`range_field_of_view_rad`; ``min_range`` =
    ``min_range_m``, ``max_range`` from the recording window, :func:`_max_range_m`); from
    the first frame with a classified object on, a ``visualization_msgs/msg/MarkerArray``
    of its planes and corners on ``/echoloc/surfaces`` (:func:`surface_markers`); with a
    ``pose``, one ``/tf`` from ``odom_frame_id`` (or ``map_frame_id`` when it is None) to
    ``body_frame_id`` (:func:`body_pose_in_map`).

    With ``tf_static``, one ``/tf_static`` message at ``first_stamp_s`` holds the
    body-to-optical rotation (``body_frame_id`` -> ``frame_id``, unless ``body_frame_id``
    is None), the receiver frames in ``frame_id`` (with a header) and, when ``moving``,
    ``map_frame_id`` -> ``odom_frame_id`` (identity). Every channel carries its QoS
    (:class:`QosWriter`): ``/tf_static`` transient local, depth 1 (latched on replay);
    the rest volatile. ``count`` is the number of messages written.
    """

    def __init__(
        self,
        path: str | Path,
        header: Recording | None,
        *,
        first_stamp_s: float,
        frame_id: str = SENSOR_FRAME_ID,
        ranges: bool = True,
        tf_static: bool = True,
        moving: bool = False,
        min_range_m: float = 0.0,
        compression: str = "zstd",
        body_frame_id: str | None = BODY_FRAME_ID,
        map_frame_id: str = ROS_MAP_FRAME_ID,
        odom_frame_id: str | None = ODOM_FRAME_ID,
    ) -> None:
        target = _check_path(path, ".mcap")
        self.source = str(target)
        if compression not in _COMPRESSIONS:
            raise EchoLocError(f"{target}: compression must be zstd, lz4 or none, got {compression!r}")
        ros_time(first_stamp_s)  # raises for a stamp ROS cannot hold, before the file is created
        self.header = header
        self.frame_id = frame_id
        self.body_frame_id = body_frame_id
        self.pose_parent = map_frame_id if odom_frame_id is None else odom_frame_id
        self.min_range_m = float(min_range_m)
        self.count = 0
        self._index = 0
        try:
            self._stream = target.open("wb")
        except OSError as error:
            raise EchoLocError(f"{target}: cannot write: {error.strerror or error}") from error
        writer = QosWriter(self._stream, compression=_COMPRESSIONS[compression])
        self._writer = writer
        writer.add_metadata(
            "echoloc",
            {
                "ros_distribution": ROS_DISTRIBUTION,
                "frame_id": frame_id,
                "frame_convention": "REP 103 optical: x right, y down, z boresight",
                "body_frame_id": body_frame_id or "",
                "body_frame_convention": "REP 103 body: x forward (boresight), y left, z up",
            },
        )
        self._cloud_schema = writer.register_msgdef("sensor_msgs/msg/PointCloud2", POINT_CLOUD2_SCHEMA)
        writer.add_topic(OBJECTS_TOPIC, self._cloud_schema, STREAM_QOS)
        statics: list[dict[str, Any]] = []
        if tf_static and body_frame_id is not None:
            statics.append(optical_transform(first_stamp_s, body_frame_id, frame_id))
        if tf_static and header is not None:
            receiver_axes = (
                header.receiver_axes
                if header.receiver_axes is not None
                else np.tile([0.0, 0.0, 1.0], (header.n_receivers, 1))
            )
            for rx in range(header.n_receivers):
                statics.append(
                    transform_stamped(
                        frame_id,
                        receiver_frame_id(rx),
                        first_stamp_s,
                        header.receivers_m[rx],
                        _axis_quaternion(receiver_axes[rx]),
                    )
                )
        if tf_static and moving and odom_frame_id is not None:
            statics.append(map_odom_transform(first_stamp_s, map_frame_id, odom_frame_id))
        self._tf_schema = writer.register_msgdef("tf2_msgs/msg/TFMessage", TF_MESSAGE_SCHEMA)
        if statics:
            writer.add_topic(TF_STATIC_TOPIC, self._tf_schema, LATCHED_QOS)
            t_ns = round(first_stamp_s * 1e9)
            writer.write_message(
                TF_STATIC_TOPIC, self._tf_schema, {"transforms": statics}, log_time=t_ns, publish_time=t_ns
            )
            self.count += 1
        self._tf_topic = False
        self._ranges = header is not None and ranges
        if header is not None and self._ranges:
            self._range_schema = writer.register_msgdef("sensor_msgs/msg/Range", RANGE_SCHEMA)
            for rx in range(header.n_receivers):
                writer.add_topic(f"{RANGE_TOPIC_PREFIX}{rx}", self._range_schema, STREAM_QOS)
            speed = recording_speed_of_sound_m_s(header)
            self._fov_rad = range_field_of_view_rad(header, speed)
            self._max_ranges = [_max_range_m(header, speed, rx) for rx in range(header.n_receivers)]
        self._marker_schema: Schema | None = None

    def add(
        self,
        frame: FrameObjects,
        stamp_s: float,
        *,
        intensity: ArrayLike | None = None,
        pose: NDArray[np.float64] | None = None,
    ) -> None:
        """One frame's messages, stamped ``stamp_s`` (header and log time): the frame's time on
        the capture clock, plus any offset; ``pose`` ``[x, y, z, qx, qy, qz, qw]`` of the sensor
        frame in the map (echoloc's convention) adds its ``/tf``."""
        writer = self._writer
        ros_time(stamp_s)  # raises for a stamp ROS cannot hold
        t_ns = round(stamp_s * 1e9)
        index = self._index
        self._index += 1
        if pose is not None and self.body_frame_id is not None:
            if not self._tf_topic:
                writer.add_topic(TF_TOPIC, self._tf_schema, TF_QOS)
                self._tf_topic = True
            moved = pose_transform(pose, stamp_s, self.pose_parent, self.body_frame_id)
            writer.write_message(
                TF_TOPIC,
                self._tf_schema,
                {"transforms": [moved]},
                log_time=t_ns,
                publish_time=t_ns,
                sequence=index,
            )
            self.count += 1
        cloud = point_cloud2(frame, stamp_s, intensity=intensity, frame_id=self.frame_id)
        writer.write_message(
            OBJECTS_TOPIC, self._cloud_schema, cloud, log_time=t_ns, publish_time=t_ns, sequence=index
        )
        self.count += 1
        if self._marker_schema is None and any(obj.surface is not None for obj in frame.objects):
            self._marker_schema = writer.register_msgdef(
                "visualization_msgs/msg/MarkerArray", MARKER_ARRAY_SCHEMA
            )
            writer.add_topic(SURFACES_TOPIC, self._marker_schema, STREAM_QOS)
        if self._marker_schema is not None:
            markers = surface_markers(frame, stamp_s, frame_id=self.frame_id)
            writer.write_message(
                SURFACES_TOPIC, self._marker_schema, markers, log_time=t_ns, publish_time=t_ns, sequence=index
            )
            self.count += 1
        header = self.header
        if header is None or not self._ranges:
            return
        distances, variances = receiver_ranges_m(frame, header.receivers_m)
        for rx in range(header.n_receivers):
            message = {
                "header": {"stamp": ros_time(stamp_s), "frame_id": receiver_frame_id(rx)},
                "radiation_type": RADIATION_ULTRASOUND,
                "field_of_view": self._fov_rad,
                "min_range": self.min_range_m,
                "max_range": self._max_ranges[rx],
                "range": float(distances[rx]),
                "variance": float(variances[rx]),
            }
            writer.write_message(
                f"{RANGE_TOPIC_PREFIX}{rx}",
                self._range_schema,
                message,
                log_time=t_ns,
                publish_time=t_ns,
                sequence=index,
            )
            self.count += 1

    def close(self) -> int:
        """Finish the file (its summary and index); the number of messages written."""
        if not self._stream.closed:
            try:
                self._writer.finish()  # type: ignore[no-untyped-call]
            finally:
                self._stream.close()
        return self.count

    def __enter__(self) -> RosObjectsWriter:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()


def write_mcap(
    path: str | Path,
    recording: Recording | None,
    objects_per_frame: Sequence[FrameObjects],
    *,
    start_time_s: float = 0.0,
    frame_rate_hz: float | None = None,
    intensities: Sequence[ArrayLike] | None = None,
    frame_id: str = SENSOR_FRAME_ID,
    ranges: bool = True,
    tf_static: bool = True,
    min_range_m: float = 0.0,
    compression: str = "zstd",
    body_frame_id: str | None = BODY_FRAME_ID,
    map_frame_id: str = ROS_MAP_FRAME_ID,
    odom_frame_id: str | None = ODOM_FRAME_ID,
) -> int:
    """Write the objects of every frame as ROS 2 (Jazzy) messages in an MCAP file
    (:class:`RosObjectsWriter`: the topics, frames and QoS; ``docs/ROS.md``).

    A recording with ``sensor_poses`` adds one ``/tf`` per frame and ``map`` -> ``odom`` to
    ``/tf_static``. Stamps (header and MCAP log time) are ``start_time_s`` (e.g. the Unix
    time of the first emission) plus the frame's time on the capture clock: the
    recording's ``frame_times`` (or back-to-back frames) when ``recording`` is given, else
    ``frame / frame_rate_hz`` when given, else each frame's ``time_s``; ``/tf_static`` takes
    the first. Never the wall clock. Returns the number of messages written.
    """
    target = _check_path(path, ".mcap")
    source = str(target)
    frames = list(objects_per_frame)
    if not all(isinstance(frame, FrameObjects) for frame in frames):
        raise EchoLocError(f"{source}: objects_per_frame must hold FrameObjects")
    if frame_rate_hz is not None and not (math.isfinite(frame_rate_hz) and frame_rate_hz > 0):
        raise EchoLocError(f"{source}: frame rate must be positive, got {frame_rate_hz}")
    if not math.isfinite(start_time_s):
        raise EchoLocError(f"{source}: start time must be finite, got {start_time_s}")
    if recording is not None:
        for frame in frames:
            if not 0 <= frame.frame < recording.n_frames:
                raise EchoLocError(
                    f"{source}: frame {frame.frame} is not in {recording.source} "
                    f"({recording.n_frames} frames)"
                )

    def stamp_of(frame: FrameObjects) -> float:
        if recording is not None:
            return start_time_s + frame_time_s(recording, frame.frame)
        if frame_rate_hz is not None:
            return start_time_s + frame.frame / frame_rate_hz
        return start_time_s + frame.time_s

    stamps = [stamp_of(frame) for frame in frames]
    for stamp in stamps:
        ros_time(stamp)  # raises for stamps ROS cannot hold, before the file is created
    for index in range(len(frames)):
        _intensity_for(intensities, index, len(frames), source)  # a bad list: before the file too
    poses = None if recording is None or body_frame_id is None else recording.sensor_poses
    with RosObjectsWriter(
        target,
        recording,
        first_stamp_s=min(stamps) if stamps else start_time_s,
        frame_id=frame_id,
        ranges=ranges,
        tf_static=tf_static,
        moving=poses is not None,
        min_range_m=min_range_m,
        compression=compression,
        body_frame_id=body_frame_id,
        map_frame_id=map_frame_id,
        odom_frame_id=odom_frame_id,
    ) as writer:
        for index, (frame, stamp) in enumerate(zip(frames, stamps, strict=True)):
            writer.add(
                frame,
                stamp,
                intensity=_intensity_for(intensities, index, len(frames), source),
                pose=None if poses is None else poses[frame.frame],
            )
    return writer.count
