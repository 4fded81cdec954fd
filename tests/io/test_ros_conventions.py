"""Robot-facing outputs by ROS 2 conventions (REP 103 / REP 105, nav2, rosbag2), read back with
independent readers: mcap + mcap_ros2 for MCAP, PIL for the nav2 PGM, a small YAML reader here."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from PIL import Image
from scipy.spatial.transform import Rotation

from echoloc.io.export import (
    BODY_FRAME_ID,
    COVARIANCE_FIELDS,
    OBJECTS_TOPIC,
    ODOM_FRAME_ID,
    ROS_MAP_FRAME_ID,
    SENSOR_FRAME_ID,
    TF_STATIC_TOPIC,
    TF_TOPIC,
    range_field_of_view_rad,
    write_mcap,
)
from echoloc.io.recording import Recording
from echoloc.localise.locate import FrameObjects, LocatedObject
from echoloc.maps.map_export import MAP_TOPIC, write_map_mcap, write_nav2_map
from echoloc.maps.mapping import GridSpec, OccupancyGrid, SensorModel
from echoloc.physics.transducer import PRESETS, piston_beam_angles
from echoloc.sim.scene import default_scene
from echoloc.sim.simulation import simulate
from ros_messages import cloud_points


@pytest.fixture(scope="module")
def recording() -> Recording:
    return simulate(default_scene(), 3)


def _read(path: Path) -> tuple[list[tuple[str, Any]], dict[str, dict[str, str]], dict[str, dict[str, str]]]:
    """Decoded messages (topic, message), each channel's metadata by topic, and the file's metadata."""
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        messages = [(channel.topic, decoded) for _, channel, _, decoded in reader.iter_decoded_messages()]
        summary = reader.get_summary()
        assert summary is not None
        channels = {c.topic: dict(c.metadata) for c in summary.channels.values()}
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return messages, channels, metadata


def _matrix(transform: Any) -> np.ndarray:
    """4x4 homogeneous matrix of a decoded geometry_msgs/Transform: p_parent = M p_child."""
    q = transform.rotation
    t = transform.translation
    m = np.eye(4)
    m[:3, :3] = Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix()
    m[:3, 3] = [t.x, t.y, t.z]
    return m


def _edges(messages: list[tuple[str, Any]], topic: str) -> dict[tuple[str, str], list[np.ndarray]]:
    edges: dict[tuple[str, str], list[np.ndarray]] = {}
    for name, message in messages:
        if name == topic:
            for t in message.transforms:
                edges.setdefault((t.header.frame_id, t.child_frame_id), []).append(_matrix(t.transform))
    return edges


def _one_object(position: list[float], covariance: np.ndarray, frame: int = 0) -> FrameObjects:
    obj = LocatedObject(np.array(position), covariance, (0, 1, 2), (0, 0, 0), 0.0, 0.8)
    return FrameObjects(frame, 0.0, (obj,))


# --- frames ----------------------------------------------------------------------------------


def test_a_point_in_the_optical_frame_lands_in_the_body_frame_by_tf_static(
    recording: Recording, tmp_path: Path
) -> None:
    """Optical (x right, y down, z ahead) (0.1, 0.2, 1.0) is body (x ahead, y left, z up)
    (1.0, -0.1, -0.2)."""
    out = tmp_path / "frames.mcap"
    write_mcap(out, recording, [_one_object([0.1, 0.2, 1.0], np.eye(3) * 1e-6)])
    messages, _, _ = _read(out)
    assert [name for name, _ in messages].count(TF_STATIC_TOPIC) == 1
    statics = _edges(messages, TF_STATIC_TOPIC)
    (body_to_optical,) = statics[(BODY_FRAME_ID, SENSOR_FRAME_ID)]
    np.testing.assert_allclose(body_to_optical[:3, 3], 0.0)
    np.testing.assert_allclose(body_to_optical @ [0.1, 0.2, 1.0, 1.0], [1.0, -0.1, -0.2, 1.0], atol=1e-12)
    # REP 103's optical rotation, quaternion (x, y, z, w) = (-0.5, 0.5, -0.5, 0.5).
    ((_, tf),) = [m for m in messages if m[0] == TF_STATIC_TOPIC]
    (t,) = [t for t in tf.transforms if t.child_frame_id == SENSOR_FRAME_ID]
    q = t.transform.rotation
    assert (q.x, q.y, q.z, q.w) == (-0.5, 0.5, -0.5, 0.5)
    # The cloud itself stays in the optical frame, exactly as located.
    ((_, cloud),) = [m for m in messages if m[0] == OBJECTS_TOPIC]
    assert cloud.header.frame_id == SENSOR_FRAME_ID
    xyz = np.frombuffer(bytes(cloud.data), "<f4")[:3]
    np.testing.assert_allclose(xyz, [0.1, 0.2, 1.0], rtol=1e-6)


def test_a_moving_sensor_chains_map_odom_body_optical(recording: Recording, tmp_path: Path) -> None:
    """With sensor poses, map -> odom (static) -> body (/tf per frame) -> optical (static) takes an
    object to where the pose puts it in echoloc's world frame, turned to the z-up map."""
    angles_deg = [0.0, 30.0, -45.0]
    turns = Rotation.from_euler("y", np.reshape(angles_deg, (3, 1)), degrees=True)  # about y: down
    positions = np.array([[0.0, 0.0, 0.0], [0.5, -0.1, 0.2], [-0.3, 0.05, 1.0]])
    poses = np.column_stack([positions, turns.as_quat()])
    moving = replace(recording, sensor_poses=poses)
    objects = [_one_object([0.1, 0.2, 1.0], np.eye(3) * 1e-6, frame=k) for k in range(3)]
    out = tmp_path / "moving.mcap"
    write_mcap(out, moving, objects, start_time_s=100.0)
    messages, _, _ = _read(out)
    statics = _edges(messages, TF_STATIC_TOPIC)
    dynamic = _edges(messages, TF_TOPIC)
    (map_to_odom,) = statics[(ROS_MAP_FRAME_ID, ODOM_FRAME_ID)]
    np.testing.assert_allclose(map_to_odom, np.eye(4))
    (body_to_optical,) = statics[(BODY_FRAME_ID, SENSOR_FRAME_ID)]
    assert set(dynamic) == {(ODOM_FRAME_ID, BODY_FRAME_ID)}
    odom_to_body = dynamic[(ODOM_FRAME_ID, BODY_FRAME_ID)]
    assert len(odom_to_body) == 3
    optical = np.array([0.1, 0.2, 1.0, 1.0])
    for k in range(3):
        world = turns[k].apply(optical[:3]) + positions[k]  # p_world = R(q) p_sensor + t
        expected = [world[2], -world[0], -world[1]]  # map x = ahead, y = left, z = up
        got = map_to_odom @ odom_to_body[k] @ body_to_optical @ optical
        np.testing.assert_allclose(got[:3], expected, atol=1e-12)
        # A turn about the downward y is a pure yaw of the opposite sign in the z-up map.
        yaw, pitch, roll = Rotation.from_matrix(odom_to_body[k][:3, :3]).as_euler("zyx", degrees=True)
        assert (yaw, pitch, roll) == pytest.approx((-angles_deg[k], 0.0, 0.0), abs=1e-9)
    # Stamps come from the capture clock (the recording's frame times), not the wall clock.
    assert recording.frame_times_s is not None
    stamps = [
        m.transforms[0].header.stamp.sec + m.transforms[0].header.stamp.nanosec * 1e-9
        for name, m in messages
        if name == TF_TOPIC
    ]
    np.testing.assert_allclose(stamps, 100.0 + recording.frame_times_s[:3], atol=1e-9)


# --- the floor plan: OccupancyGrid and nav2 files ------------------------------------------------

CELL = 0.02
WALL_Z = (1.00, 1.02)  # a wall 1 m ahead (echoloc's world z) ...
WALL_X = (-0.30, 0.10)  # ... from 0.3 m left to 0.1 m right of the sensor (world x points right)


def _wall_grid() -> OccupancyGrid:
    """A floor plan 0.1 m below the sensor: the wall occupied, the space before it free, the rest unknown."""
    spec = GridSpec.floor_plan((-0.5, 0.5), (0.0, 1.2), CELL, height_m=0.1)
    x = spec.centres_m(0)[:, None]
    z = spec.centres_m(2)[None, :]
    wall = (x > WALL_X[0]) & (x < WALL_X[1]) & (z > WALL_Z[0]) & (z < WALL_Z[1])
    seen = (np.abs(x) < 0.35) & (z < WALL_Z[0])
    log_odds = np.where(wall, 3.0, -2.0).astype(np.float32)[:, None, :]
    updates = np.where(seen | wall, 5, 0).astype(np.uint16)[:, None, :]
    return OccupancyGrid(spec, log_odds, updates, SensorModel(), frames=1)


def _wall_in_map() -> tuple[tuple[float, float], tuple[float, float]]:
    """The wall's extent in the z-up map: x = world z, y = -world x."""
    return WALL_Z, (-WALL_X[1], -WALL_X[0])


def test_occupancy_grid_lies_in_the_maps_x_y_plane_with_the_wall_at_its_place(tmp_path: Path) -> None:
    grid = _wall_grid()
    out = tmp_path / "map.mcap"
    write_map_mcap(out, grid, poses=np.array([[0, 0, 0, 0, 0, 0, 1.0]]), frame_times_s=np.array([2.5]))
    messages, channels, _ = _read(out)
    ((_, msg),) = [m for m in messages if m[0] == MAP_TOPIC]
    assert msg.header.frame_id == ROS_MAP_FRAME_ID
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (2, 500_000_000)  # the frame's time
    o = msg.info.origin
    assert (o.orientation.x, o.orientation.y, o.orientation.z, o.orientation.w) == (0.0, 0.0, 0.0, 1.0)
    assert msg.info.resolution == pytest.approx(CELL)
    cells = np.array(msg.data, dtype=np.int8).reshape(msg.info.height, msg.info.width)
    rows, columns = np.nonzero(cells > 50)
    x = o.position.x + (columns + 0.5) * CELL
    y = o.position.y + (rows + 0.5) * CELL
    (x_low, x_high), (y_low, y_high) = _wall_in_map()
    assert len(x) == round((x_high - x_low) / CELL) * round((y_high - y_low) / CELL)
    assert np.all((x > x_low) & (x < x_high))
    assert np.all((y > y_low) & (y < y_high))
    assert y.min() == pytest.approx(y_low + CELL / 2)  # the wall's right end, 0.1 m to the right
    assert y.max() == pytest.approx(y_high - CELL / 2)  # its left end, 0.3 m to the left
    assert o.position.z == pytest.approx(-0.1)  # the plan's height: 0.1 m below the sensor
    # Latched on replay: the map and /tf_static are transient local, keep last 1.
    for topic in (MAP_TOPIC, TF_STATIC_TOPIC):
        (profile,) = _qos(channels[topic])
        assert profile["durability"] == "1"
        assert profile["depth"] == "1"


def _yaml(text: str) -> dict[str, str]:
    """The flat ``key: value`` YAML of a nav2 map file."""
    pairs = [line.split(":", 1) for line in text.splitlines() if line.strip()]
    return {key.strip(): value.strip() for key, value in pairs}


def test_nav2_map_files_put_the_wall_where_map_server_reads_it(tmp_path: Path) -> None:
    grid = _wall_grid()
    yaml_path, pgm_path = write_nav2_map(grid, tmp_path / "room.yaml")
    assert (yaml_path, pgm_path) == (tmp_path / "room.yaml", tmp_path / "room.pgm")
    meta = _yaml(yaml_path.read_text())
    assert list(meta) == [
        "image",
        "mode",
        "resolution",
        "origin",
        "negate",
        "occupied_thresh",
        "free_thresh",
    ]
    assert meta["image"] == "room.pgm"
    assert meta["mode"] == "trinary"
    assert meta["negate"] == "0"
    resolution = float(meta["resolution"])
    assert resolution == CELL
    origin_x, origin_y, yaw = (float(v) for v in meta["origin"].strip("[]").split(","))
    assert yaw == 0.0
    assert pgm_path.read_bytes().startswith(b"P5\n")
    with Image.open(pgm_path) as image:
        assert image.format == "PPM"
        assert image.mode == "L"
        pixels = np.asarray(image)
    assert set(np.unique(pixels)) == {0, 205, 254}
    height, width = pixels.shape
    # nav2's map_server: occupancy 1 - shade; occupied above occupied_thresh, free below free_thresh.
    occupancy = 1.0 - pixels / 255.0
    occupied = occupancy > float(meta["occupied_thresh"])
    free = occupancy < float(meta["free_thresh"])
    assert not np.any(free & (pixels == 205))  # the unknown grey reads back unknown, not free
    # Image row 0 is the top of the map (largest y): row r is map row height - 1 - r.
    rows, columns = np.nonzero(occupied)
    x = origin_x + (columns + 0.5) * resolution
    y = origin_y + (height - 1 - rows + 0.5) * resolution
    (x_low, x_high), (y_low, y_high) = _wall_in_map()
    assert np.all((x > x_low) & (x < x_high))
    assert y.min() == pytest.approx(y_low + CELL / 2)
    assert y.max() == pytest.approx(y_high - CELL / 2)
    # The cells between the sensor and the wall are free, those beyond unknown.
    rows, columns = np.nonzero(free)
    assert np.all(origin_x + (columns + 0.5) * resolution < x_low)
    assert width == grid.spec.shape[2]
    assert height == grid.spec.shape[0]


def test_nav2_map_is_the_occupancy_grid_message_through_map_saver_rules(tmp_path: Path) -> None:
    """Cells of 25 % or less are free, 65 % or more occupied, in between and unknown grey."""
    spec = GridSpec.floor_plan((0.0, 0.1), (0.0, 0.1), 0.02)
    probability = np.linspace(0.0, 1.0, 25).reshape(5, 1, 5)
    log_odds = np.log(np.clip(probability, 1e-6, 1 - 1e-6) / np.clip(1 - probability, 1e-6, 1)).astype(
        np.float32
    )
    updates = np.ones(spec.shape, dtype=np.uint16)
    updates[0, 0, 0] = 0  # unknown
    grid = OccupancyGrid(spec, log_odds, updates, SensorModel())
    _, pgm = write_nav2_map(grid, tmp_path / "levels.yaml")
    with Image.open(pgm) as image:
        pixels = np.asarray(image)[::-1, :]  # map rows, y up
    percent = np.rint(100 * probability[::-1, 0, :])  # map rows are world x reversed
    known = updates[::-1, 0, :] > 0
    expected = np.where(percent <= 25, 254, np.where(percent >= 65, 0, 205))
    np.testing.assert_array_equal(pixels, np.where(known, expected, 205))


def test_nav2_map_refuses_a_3d_grid_and_other_names(tmp_path: Path) -> None:
    from echoloc.errors import EchoLocError

    box = GridSpec.box([0, 0, 0], [0.1, 0.1, 0.1], 0.05)
    grid = OccupancyGrid(box, np.zeros(box.shape, np.float32), np.zeros(box.shape, np.uint16))
    with pytest.raises(EchoLocError, match="floor plan"):
        write_nav2_map(grid, tmp_path / "m.yaml")
    with pytest.raises(EchoLocError, match=r"NAME\.yaml"):
        write_nav2_map(_wall_grid(), tmp_path / "m.pgm")


# --- QoS ------------------------------------------------------------------------------------


def _qos(text: str | dict[str, str]) -> list[dict[str, str]]:
    """rosbag2's ``offered_qos_profiles``: a YAML sequence of maps, durations as nested sec/nsec."""
    if isinstance(text, dict):
        text = text["offered_qos_profiles"]
    profiles: list[dict[str, str]] = []
    parent = ""
    for line in text.splitlines():
        indent = len(line) - len(line.lstrip(" -"))
        key, _, value = line.strip(" -").partition(":")
        if line.startswith("- "):
            profiles.append({})
        if indent == 2 and not value.strip():
            parent = key
        elif indent == 4:
            profiles[-1][f"{parent}.{key}"] = value.strip()
        else:
            profiles[-1][key] = value.strip()
    return profiles


def test_every_channel_offers_its_qos_as_rosbag2_records_it(recording: Recording, tmp_path: Path) -> None:
    moving = replace(recording, sensor_poses=np.tile([0, 0, 0, 0, 0, 0, 1.0], (recording.n_frames, 1)))
    out = tmp_path / "qos.mcap"
    write_mcap(out, moving, [_one_object([0.0, 0.0, 1.0], np.eye(3) * 1e-6)])
    _, channels, metadata = _read(out)
    # The rosbag2 record without serialized metadata: rosbag2 reads the numeric QoS (version <= 8).
    assert metadata["rosbag2"] == {"ROS_DISTRO": "jazzy"}
    keys = [
        "history",
        "depth",
        "reliability",
        "durability",
        "deadline.sec",
        "deadline.nsec",
        "lifespan.sec",
        "lifespan.nsec",
        "liveliness",
        "liveliness_lease_duration.sec",
        "liveliness_lease_duration.nsec",
        "avoid_ros_namespace_conventions",
    ]
    for topic, meta in channels.items():
        (profile,) = _qos(meta)
        assert list(profile) == keys, topic
        assert profile["history"] == "1"  # keep last
        assert profile["reliability"] == "1"  # reliable
        assert profile["liveliness"] == "1"  # automatic
        assert profile["deadline.sec"] == "9223372036"
        assert profile["deadline.nsec"] == "854775807"
        assert profile["avoid_ros_namespace_conventions"] == "false"
        latched = topic == TF_STATIC_TOPIC
        assert profile["durability"] == ("1" if latched else "2"), topic  # transient local / volatile
        assert profile["depth"] == ("1" if latched else "100" if topic == TF_TOPIC else "10"), topic
    assert {TF_STATIC_TOPIC, TF_TOPIC, OBJECTS_TOPIC, "/echoloc/range/rx0"} <= set(channels)


# --- covariance -----------------------------------------------------------------------------


def test_the_full_covariance_round_trips_through_point_cloud2(tmp_path: Path) -> None:
    rng = np.random.default_rng(5)
    frames = []
    truth = []
    for k in range(3):
        objects = []
        for _ in range(4):
            a = rng.normal(size=(3, 3)) * 1e-2
            covariance = a @ a.T  # symmetric positive semidefinite, correlated axes
            truth.append(covariance)
            objects.append(LocatedObject(rng.normal(size=3), covariance, (0, 1), (0, 0), 0.0, 0.5))
        frames.append(FrameObjects(k, 0.1 * k, tuple(objects)))
    out = tmp_path / "cov.mcap"
    write_mcap(out, None, frames)
    messages, _, _ = _read(out)
    clouds = [m for name, m in messages if name == OBJECTS_TOPIC]
    got = []
    for cloud in clouds:
        points = cloud_points(cloud)  # decoded from the message's own field list
        assert set(COVARIANCE_FIELDS) <= set(points.dtype.names)
        for p in points:
            xx, yy, zz = float(p["cov_xx"]), float(p["cov_yy"]), float(p["cov_zz"])
            xy, xz, yz = float(p["cov_xy"]), float(p["cov_xz"]), float(p["cov_yz"])
            got.append(np.array([[xx, xy, xz], [xy, yy, yz], [xz, yz, zz]]))
    assert len(got) == len(truth) == 12
    for back, covariance in zip(got, truth, strict=True):
        np.testing.assert_allclose(back, covariance, rtol=1e-6, atol=1e-6 * np.abs(covariance).max())
        assert np.linalg.eigvalsh(back).min() >= -1e-6 * np.abs(covariance).max()
        assert abs(back[0, 1]) > 0  # the off-diagonal is there, not just the diagonal


# --- Range ---------------------------------------------------------------------------------------


def test_range_field_of_view_comes_from_the_recording_or_the_transducer(recording: Recording) -> None:
    c = 343.0
    assert range_field_of_view_rad(replace(recording, field_of_view_deg=12.5), c) == pytest.approx(
        math.radians(25.0)
    )
    unknown = replace(recording, field_of_view_deg=None)
    for carrier, name in [(50_000.0, "electrostatic50"), (40_000.0, "piezo40")]:
        fov = range_field_of_view_rad(replace(unknown, carrier_hz=carrier), c)
        beam = piston_beam_angles(PRESETS[name].radius_m, carrier, c)
        assert fov == pytest.approx(2 * beam.half_angle_null_rad)
        assert fov < math.pi / 2
    # The CH101 model's port is far smaller than the wavelength: no null, the half-space.
    assert range_field_of_view_rad(replace(unknown, carrier_hz=175_000.0), c) == pytest.approx(math.pi)
