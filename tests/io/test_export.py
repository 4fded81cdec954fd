"""Exports: every file is read back with an independent reader (plyfile, mcap + mcap_ros2)."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from plyfile import PlyData

from echoloc import pipeline
from echoloc.errors import EchoLocError
from echoloc.io.export import (
    OBJECTS_TOPIC,
    POINT_FIELDS,
    SENSOR_FRAME_ID,
    SURFACES_TOPIC,
    TF_STATIC_TOPIC,
    receiver_frame_id,
    ros_time,
    write_mcap,
    write_ply,
)
from echoloc.io.recording import Recording
from echoloc.localise.locate import FrameObjects, LocatedObject
from echoloc.physics.transducer import PRESETS, piston_beam_angles
from echoloc.sim.scene import default_scene
from echoloc.sim.simulation import simulate
from ros_messages import cloud_points


@pytest.fixture(scope="module")
def located() -> tuple[Recording, list[FrameObjects]]:
    """Real echoloc output: the default scene, simulated and located."""
    rec = simulate(default_scene(), 4)
    chain = pipeline.prepare(rec)
    return rec, [objects for _, objects in pipeline.run(chain)]


def _object(
    position: list[float], cov_diag: list[float], score: float, receivers: tuple[int, ...]
) -> LocatedObject:
    return LocatedObject(
        np.array(position), np.diag(cov_diag), receivers, tuple(0 for _ in receivers), 0.0, score
    )


def _synthetic() -> list[FrameObjects]:
    return [
        FrameObjects(0, 0.0, (_object([0.1, -0.2, 1.5], [1e-4, 2e-4, 3e-5], 0.9, (0, 1, 2)),)),
        FrameObjects(1, 0.05, ()),
        FrameObjects(
            2,
            0.1,
            (
                _object([0.0, 0.0, 0.5], [1e-6, 1e-6, 1e-7], 0.5, (0, 1)),
                _object([-0.3, 0.25, 2.0], [4e-4, 5e-4, 6e-5], 0.7, (1, 2, 3)),
            ),
        ),
    ]


def _read_mcap(path: Path) -> list[tuple[str, str, int, Any]]:
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        return [
            (channel.topic, schema.name, message.log_time, decoded)
            for schema, channel, message, decoded in reader.iter_decoded_messages()
        ]


def _cloud_points(msg: Any) -> np.ndarray:
    """The objects' cloud decoded from its own field list, which is the documented one."""
    assert [f.name for f in msg.fields] == list(POINT_FIELDS)
    return cloud_points(msg)


def _expected(frame: FrameObjects) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Positions, scores and covariances (n, 3, 3) of a frame's objects."""
    n = len(frame.objects)
    pos = np.array([o.position_m for o in frame.objects]).reshape(n, 3)
    score = np.array([o.score for o in frame.objects])
    cov = np.array([o.covariance_m2 for o in frame.objects]).reshape(n, 3, 3)
    return pos, score, cov


def _assert_cloud_matches(msg: Any, frame: FrameObjects) -> None:
    points = _cloud_points(msg)
    pos, score, cov = _expected(frame)
    assert msg.width == len(frame.objects)
    got_pos = np.column_stack([points["x"], points["y"], points["z"]]) if len(points) else np.zeros((0, 3))
    np.testing.assert_allclose(got_pos, pos, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(points["intensity"], score, rtol=1e-6)
    got_cov = np.array(
        [
            [
                [p["cov_xx"], p["cov_xy"], p["cov_xz"]],
                [p["cov_xy"], p["cov_yy"], p["cov_yz"]],
                [p["cov_xz"], p["cov_yz"], p["cov_zz"]],
            ]
            for p in points
        ]
    ).reshape(-1, 3, 3)
    np.testing.assert_allclose(got_cov, cov, rtol=1e-6, atol=1e-6 * np.abs(cov).max(initial=0.0))
    assert msg.is_dense is True


# --- MCAP ---------------------------------------------------------------------------------


def test_mcap_of_real_pipeline_output_decodes_to_the_objects(
    located: tuple[Recording, list[FrameObjects]], tmp_path: Path
) -> None:
    rec, frames = located
    assert sum(len(f.objects) for f in frames) > 0
    start = 1_700_000_000.25
    out = tmp_path / "run.mcap"
    count = write_mcap(out, rec, frames, start_time_s=start)
    messages = _read_mcap(out)
    assert count == len(messages) == 1 + len(frames) * (1 + rec.n_receivers)

    clouds = [m for m in messages if m[0] == OBJECTS_TOPIC]
    assert {m[1] for m in clouds} == {"sensor_msgs/msg/PointCloud2"}
    assert len(clouds) == len(frames)
    assert rec.frame_times_s is not None
    stamps = []
    for (_, _, log_time, msg), frame in zip(clouds, frames, strict=True):
        _assert_cloud_matches(msg, frame)
        assert msg.header.frame_id == SENSOR_FRAME_ID
        stamp_ns = msg.header.stamp.sec * 1_000_000_000 + msg.header.stamp.nanosec
        assert 0 <= msg.header.stamp.nanosec < 1_000_000_000
        assert stamp_ns == log_time == round((start + rec.frame_times_s[frame.frame]) * 1e9)
        stamps.append(stamp_ns)
    assert np.all(np.diff(stamps) > 0)

    ranges = [m for m in messages if m[0].startswith("/echoloc/range/rx")]
    assert {m[1] for m in ranges} == {"sensor_msgs/msg/Range"}
    assert {m[0] for m in ranges} == {f"/echoloc/range/rx{n}" for n in range(rec.n_receivers)}
    c = pipeline.recording_speed_of_sound_m_s(rec)
    window_m = rec.n_samples / rec.sample_rate_hz * c
    for topic, _, log_time, msg in ranges:
        rx = int(topic.removeprefix("/echoloc/range/rx"))
        assert msg.header.frame_id == receiver_frame_id(rx)
        assert msg.radiation_type == 0  # ULTRASOUND
        frame = next(f for f, s in zip(frames, stamps, strict=True) if s == log_time)
        supported = [o for o in frame.objects if rx in o.receivers]
        nearest = min(float(np.linalg.norm(o.position_m - rec.receivers_m[rx])) for o in supported)
        assert msg.range == pytest.approx(nearest, rel=1e-6)
        assert msg.variance > 0
        assert msg.min_range == 0.0
        # Co-located transmitter at the origin, receivers 0.25 m off: (L + 0.25) / 2.
        assert msg.max_range == pytest.approx((window_m + 0.25) / 2, rel=1e-6)
        assert msg.min_range <= msg.range <= msg.max_range
        # The recording gives no field of view: the first-null beam of the 50 kHz transducer model.
        assert rec.field_of_view_deg is None
        model = PRESETS["electrostatic50"]
        beam = piston_beam_angles(model.radius_m, rec.carrier_hz, c)
        assert msg.field_of_view == pytest.approx(beam.full_angle_null_rad, rel=1e-6)
        assert math.radians(30) < msg.field_of_view < math.radians(40)


def test_mcap_tf_static_puts_each_receiver_frame_at_its_position(
    located: tuple[Recording, list[FrameObjects]], tmp_path: Path
) -> None:
    rec, frames = located
    out = tmp_path / "tf.mcap"
    write_mcap(out, rec, frames[:1])
    (tf,) = [m for m in _read_mcap(out) if m[0] == TF_STATIC_TOPIC]
    assert tf[1] == "tf2_msgs/msg/TFMessage"
    assert [t.child_frame_id for t in tf[3].transforms] == [
        SENSOR_FRAME_ID,
        *(receiver_frame_id(n) for n in range(rec.n_receivers)),
    ]
    for t, position in zip(tf[3].transforms[1:], rec.receivers_m, strict=True):
        assert t.header.frame_id == SENSOR_FRAME_ID
        tr = t.transform.translation
        np.testing.assert_allclose([tr.x, tr.y, tr.z], position)
        q = t.transform.rotation
        x, y, z, w = q.x, q.y, q.z, q.w
        # The child's x axis (first column of R(q)) is the receiver's boresight +z.
        x_axis = [1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)]
        np.testing.assert_allclose(x_axis, [0.0, 0.0, 1.0], atol=1e-12)
        # ... and its z axis points up, -y in the optical frame (REP 103).
        z_axis = [2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)]
        np.testing.assert_allclose(z_axis, [0.0, -1.0, 0.0], atol=1e-12)


def test_mcap_field_of_view_and_tilted_receiver(
    located: tuple[Recording, list[FrameObjects]], tmp_path: Path
) -> None:
    rec, frames = located
    axes = np.tile([0.0, 0.0, 1.0], (rec.n_receivers, 1))
    axes[1] = [math.sin(0.3), 0.0, math.cos(0.3)]
    tilted = replace(rec, field_of_view_deg=20.0, receiver_axes=axes)
    out = tmp_path / "fov.mcap"
    write_mcap(out, tilted, frames[:2], ranges=True)
    messages = _read_mcap(out)
    for _, _, _, msg in (m for m in messages if m[1] == "sensor_msgs/msg/Range"):
        assert msg.field_of_view == pytest.approx(math.radians(40.0), rel=1e-6)
    (tf,) = [m for m in messages if m[0] == TF_STATIC_TOPIC]
    (receiver_1,) = [t for t in tf[3].transforms if t.child_frame_id == receiver_frame_id(1)]
    q = receiver_1.transform.rotation
    x, y, z, w = q.x, q.y, q.z, q.w
    x_axis = [1 - 2 * (y * y + z * z), 2 * (x * y + w * z), 2 * (x * z - w * y)]
    np.testing.assert_allclose(x_axis, axes[1], atol=1e-12)


def test_mcap_without_recording_uses_frame_rate_and_empty_frames_are_valid(tmp_path: Path) -> None:
    frames = _synthetic()
    out = tmp_path / "synthetic.mcap"
    count = write_mcap(out, None, frames, frame_rate_hz=20.0, start_time_s=10.0)
    messages = _read_mcap(out)
    assert count == len(messages) == len(frames) + 1
    # Without a recording, /tf_static holds only the body-to-optical rotation.
    assert messages[0][0] == TF_STATIC_TOPIC
    assert [t.child_frame_id for t in messages[0][3].transforms] == [SENSOR_FRAME_ID]
    messages = messages[1:]
    assert {m[0] for m in messages} == {OBJECTS_TOPIC}
    for (_, schema, log_time, msg), frame in zip(messages, frames, strict=True):
        assert schema == "sensor_msgs/msg/PointCloud2"
        _assert_cloud_matches(msg, frame)
        assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (10, frame.frame * 50_000_000)
        assert log_time == 10_000_000_000 + frame.frame * 50_000_000
    empty = messages[1][3]
    assert (empty.width, empty.row_step, len(empty.data), empty.point_step) == (0, 0, 0, 40)


def test_mcap_intensities_replace_scores_and_default_stamps_are_frame_times(tmp_path: Path) -> None:
    frames = _synthetic()
    amplitudes = [np.array([0.25]), np.array([]), np.array([0.5, 0.75])]
    out = tmp_path / "amp.mcap"
    write_mcap(out, None, frames, intensities=amplitudes)
    messages = [m for m in _read_mcap(out) if m[0] == OBJECTS_TOPIC]
    for (_, _, log_time, msg), frame, amp in zip(messages, frames, amplitudes, strict=True):
        np.testing.assert_allclose(_cloud_points(msg)["intensity"], amp)
        assert log_time == round(frame.time_s * 1e9)


def test_ros_time_splits_seconds_and_nanoseconds() -> None:
    assert ros_time(1.5) == {"sec": 1, "nanosec": 500_000_000}
    assert ros_time(1_700_000_000.000000001) == {"sec": 1_700_000_000, "nanosec": 0}
    assert ros_time(2.999999999999) == {"sec": 3, "nanosec": 0}
    with pytest.raises(EchoLocError, match="negative"):
        ros_time(-0.1)


# --- PLY ----------------------------------------------------------------------------------


@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("double", [False, True])
def test_ply_round_trip_all_frames(
    located: tuple[Recording, list[FrameObjects]], tmp_path: Path, binary: bool, double: bool
) -> None:
    _, frames = located
    out = tmp_path / "objects.ply"
    assert write_ply(out, frames, binary=binary, double=double) == [out]
    ply = PlyData.read(str(out))
    assert ply.text is (not binary)
    if binary:
        assert ply.byte_order == "<"
    vertex = ply["vertex"]
    names = [p.name for p in vertex.properties]
    assert names == [*POINT_FIELDS, "receivers", "frame"]
    assert vertex["x"].dtype == np.dtype("f8" if double else "f4")
    assert any("cov_xx cov_yy cov_zz" in c and "covariance" in c for c in ply.comments)
    assert any(SENSOR_FRAME_ID in c for c in ply.comments)
    expected = [
        (f.frame, o.position_m, o.score, np.diag(o.covariance_m2), len(o.receivers))
        for f in frames
        for o in f.objects
    ]
    assert len(vertex.data) == len(expected)
    rtol = 1e-15 if double else 1e-6
    for row, (frame, pos, score, cov, support) in zip(vertex.data, expected, strict=True):
        assert row["frame"] == frame
        np.testing.assert_allclose([row["x"], row["y"], row["z"]], pos, rtol=rtol, atol=1e-7)
        assert row["intensity"] == pytest.approx(score, rel=rtol)
        np.testing.assert_allclose([row["cov_xx"], row["cov_yy"], row["cov_zz"]], cov, rtol=rtol)
        assert row["receivers"] == support


def test_ply_per_frame_and_empty_frame(tmp_path: Path) -> None:
    frames = _synthetic()
    out = tmp_path / "cloud.ply"
    written = write_ply(out, frames, per_frame=True, binary=False)
    assert written == [tmp_path / f"cloud_{n:06d}.ply" for n in (0, 1, 2)]
    for path, frame in zip(written, frames, strict=True):
        vertex = PlyData.read(str(path))["vertex"]
        assert "frame" not in [p.name for p in vertex.properties]
        assert vertex.count == len(frame.objects)
        pos, score, _ = _expected(frame)
        np.testing.assert_allclose(
            np.column_stack([vertex["x"], vertex["y"], vertex["z"]]).reshape(-1, 3), pos, rtol=1e-6
        )
        np.testing.assert_allclose(vertex["intensity"], score, rtol=1e-6)
    empty = tmp_path / "empty.ply"
    write_ply(empty, FrameObjects(7, 0.0, ()))
    assert PlyData.read(str(empty))["vertex"].count == 0


def test_ply_points_array_and_amplitudes(tmp_path: Path) -> None:
    points = np.array([[0.0, 0.1, 1.0], [0.2, -0.1, 2.0]])
    out = tmp_path / "points.ply"
    write_ply(out, points, intensities=[np.array([3.0, 4.0])])
    vertex = PlyData.read(str(out))["vertex"]
    np.testing.assert_allclose(np.column_stack([vertex["x"], vertex["y"], vertex["z"]]), points, rtol=1e-6)
    np.testing.assert_allclose(vertex["intensity"], [3.0, 4.0])
    assert np.all(np.isnan(vertex["cov_xx"]))


# --- errors -------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "match"),
    [
        ("out.txt", "expected a .ply file name"),
        ("out", "extension '\\(none\\)'"),
        ("missing/out.ply", "does not exist"),
    ],
)
def test_ply_bad_paths_raise_one_line(tmp_path: Path, name: str, match: str) -> None:
    with pytest.raises(EchoLocError, match=match) as info:
        write_ply(tmp_path / name, _synthetic())
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    ("name", "match"),
    [("out.ply", "expected a .mcap file name"), ("missing/out.mcap", "does not exist")],
)
def test_mcap_bad_paths_raise_one_line(tmp_path: Path, name: str, match: str) -> None:
    with pytest.raises(EchoLocError, match=match) as info:
        write_mcap(tmp_path / name, None, _synthetic())
    assert "\n" not in str(info.value)


def test_mcap_bad_inputs_raise(located: tuple[Recording, list[FrameObjects]], tmp_path: Path) -> None:
    rec, _ = located
    out = tmp_path / "bad.mcap"
    with pytest.raises(EchoLocError, match="frame 9 is not in"):
        write_mcap(out, rec, [FrameObjects(9, 0.0, ())])
    with pytest.raises(EchoLocError, match="frame rate must be positive"):
        write_mcap(out, None, _synthetic(), frame_rate_hz=0.0)
    with pytest.raises(EchoLocError, match="frame 2 has 2 objects but 1 intensities"):
        write_mcap(out, None, _synthetic(), intensities=[np.ones(1), np.ones(0), np.ones(1)])
    with pytest.raises(EchoLocError, match="before 1970"):
        write_mcap(out, None, _synthetic(), start_time_s=-5.0)
    (tmp_path / "dir.mcap").mkdir()
    with pytest.raises(EchoLocError, match="is a directory"):
        write_mcap(tmp_path / "dir.mcap", None, _synthetic())


# --- reflector classes: planes and corners as markers ---------------------------------------


def _quaternion_matrix(q: Any) -> np.ndarray:
    """Rotation matrix of a decoded geometry_msgs/Quaternion (x, y, z, w)."""
    x, y, z, w = q.x, q.y, q.z, q.w
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_mcap_draws_planes_and_corners_as_markers(tmp_path: Path) -> None:
    """The corridor with two transmitters, located with classes: each frame's MarkerArray decodes
    with mcap_ros2, clears the last frame's markers, lays a thin box in the plane over the patch its
    echoes met, and draws the corner's edge along its direction through its foot."""
    from echoloc.sim.scenefile import load_scene, preset_path

    rec = simulate(load_scene(preset_path("rooms/corridor")), 3)
    chain = pipeline.prepare(rec)
    chain = replace(chain, locate_options=replace(chain.locate_options, reflector_classes=True))
    frames = [objects for _, objects in pipeline.run(chain)]
    out = tmp_path / "classes.mcap"
    write_mcap(out, rec, frames)
    markers = [m for m in _read_mcap(out) if m[0] == SURFACES_TOPIC]
    assert {m[1] for m in markers} == {"visualization_msgs/msg/MarkerArray"}
    assert len(markers) == len(frames)
    planes = corners = 0
    for (_, _, _, message), frame in zip(markers, frames, strict=True):
        assert message.markers[0].action == 3  # DELETEALL
        for marker in message.markers[1:]:
            obj = frame.objects[marker.id]
            assert obj.surface is not None
            if marker.ns == "planes":
                planes += 1
                rotation = _quaternion_matrix(marker.pose.orientation)
                np.testing.assert_allclose(rotation[:, 2], obj.surface.normal, atol=1e-9)
                centre = np.array([marker.pose.position.x, marker.pose.position.y, marker.pose.position.z])
                assert obj.surface.normal @ (centre - obj.position_m) == pytest.approx(0.0, abs=1e-6)
                assert obj.surface.specular_points_m is not None
                span = (obj.surface.specular_points_m - centre) @ rotation[:, :2]
                np.testing.assert_allclose(np.abs(span).max(axis=0), [marker.scale.x / 2, marker.scale.y / 2])
            else:
                corners += 1
                ends = np.array([[p.x, p.y, p.z] for p in marker.points])
                np.testing.assert_allclose(ends.mean(axis=0), obj.position_m, atol=1e-9)
                direction = (ends[1] - ends[0]) / np.linalg.norm(ends[1] - ends[0])
                assert abs(direction @ obj.surface.edge_direction) == pytest.approx(1.0)
    assert planes >= 2
    assert corners >= 2


def test_mcap_without_classes_has_no_marker_channel(
    located: tuple[Recording, list[FrameObjects]], tmp_path: Path
) -> None:
    rec, frames = located
    out = tmp_path / "plain.mcap"
    write_mcap(out, rec, frames)
    assert SURFACES_TOPIC not in {m[0] for m in _read_mcap(out)}
