"""The live view: a real WebSocket client speaking the Foxglove protocol gets and decodes our messages."""

from __future__ import annotations

import asyncio
import base64
import json
import struct
import time

import numpy as np
import pytest
import websockets
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory

from echoloc.pipeline import prepare
from echoloc.realtime.liveview import LiveView, envelope_trace
from echoloc.realtime.stream import StreamProcessor, recording_frames
from echoloc.sim.scene import default_scene
from echoloc.sim.simulation import simulate

SUBPROTOCOL = "foxglove.sdk.v1"  # the SDK server's name; test_liveview_subprotocols.py tries both


@pytest.fixture(scope="module")
def results():
    recording = simulate(default_scene(), 4)
    processor = StreamProcessor(prepare(recording))
    return recording, [(processor.process(f), f.samples) for f in recording_frames(recording)]


def _protobuf_class(channel):
    """The message class of a channel advertised with a protobuf FileDescriptorSet."""
    files = descriptor_pb2.FileDescriptorSet.FromString(base64.b64decode(channel["schema"]))
    pool = descriptor_pool.DescriptorPool()
    for file in files.file:
        pool.Add(file)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(channel["schemaName"]))


async def _client(port, publish, wanted):
    """Subscribe to every advertised channel, have ``publish`` run, collect one message per topic."""
    async with websockets.connect(
        f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], close_timeout=1
    ) as ws:
        assert ws.subprotocol == SUBPROTOCOL
        channels = {}
        server_info = None
        while not wanted <= {c["topic"] for c in channels.values()}:
            message = json.loads(await asyncio.wait_for(ws.recv(), 10))
            if message["op"] == "serverInfo":
                server_info = message
            elif message["op"] == "advertise":
                channels.update({c["id"]: c for c in message["channels"]})
        assert server_info is not None
        assert server_info["name"] == "echoloc"
        subscriptions = {k: c for k, c in enumerate(channels.values(), start=1)}
        await ws.send(
            json.dumps(
                {
                    "op": "subscribe",
                    "subscriptions": [{"id": k, "channelId": c["id"]} for k, c in subscriptions.items()],
                }
            )
        )
        await asyncio.sleep(0.3)  # the server registers the subscriptions
        publisher = asyncio.get_running_loop().run_in_executor(None, publish)
        got = {}
        deadline = time.monotonic() + 15
        while not wanted <= set(got) and time.monotonic() < deadline:
            data = await asyncio.wait_for(ws.recv(), 10)
            if isinstance(data, str):
                continue
            assert data[0] == 0x01  # message data
            subscription, log_time_ns = struct.unpack_from("<IQ", data, 1)
            channel = subscriptions[subscription]
            got.setdefault(channel["topic"], (channel, log_time_ns, data[13:]))
        await publisher
        return got


def test_foxglove_client_receives_and_decodes_objects_traces_and_stats(results):
    recording, frames = results
    wanted = {
        "/echoloc/objects",
        "/echoloc/points",
        "/echoloc/locate",
        "/echoloc/echo_traces",
        "/echoloc/stats",
    }
    with LiveView(port=0, max_rate_hz=50.0) as view:
        assert view.url.startswith("ws://127.0.0.1:")
        view.set_session(recording)

        def publish():
            from echoloc.realtime.stream import StreamStats

            for _ in range(20):  # again and again, in case the first went out before the subscription
                for result, samples in frames:
                    view.publish(result, samples, StreamStats(processed=7))
                    time.sleep(0.025)

        got = asyncio.run(_client(view.port, publish, wanted))
    assert wanted <= set(got)
    truth = recording.truth_positions_m[0]

    # The locate line is docs/FORMATS.md's, and its objects are the three balls.
    channel, log_time_ns, payload = got["/echoloc/locate"]
    assert channel["encoding"] == "json"
    located = json.loads(payload)
    assert len(located["objects"]) == 3
    assert abs(log_time_ns / 1e9 - time.time()) < 60

    # SceneUpdate, protobuf: one sphere per ball, at its true position within 2 mm.
    channel, _, payload = got["/echoloc/objects"]
    assert channel["schemaName"] == "foxglove.SceneUpdate"
    scene = _protobuf_class(channel).FromString(payload)
    (entity,) = scene.entities
    assert entity.frame_id == "echoloc_sensor_optical_frame"
    centres = np.array([[s.pose.position.x, s.pose.position.y, s.pose.position.z] for s in entity.spheres])
    assert len(centres) == 3
    for ball in truth:
        assert np.min(np.linalg.norm(centres - ball, axis=1)) < 2e-3
    assert all(t.text.endswith(" mm") for t in entity.texts)

    # PointCloud, protobuf: x, y, z, score as float32, one point per object of the frame
    # published (whichever of the four it was: matched on all four columns).
    channel, _, payload = got["/echoloc/points"]
    cloud = _protobuf_class(channel).FromString(payload)
    assert cloud.point_stride == 16
    points = np.frombuffer(cloud.data, "<f4").reshape(-1, 4)
    points = points[np.argsort(points[:, 2])]
    expected = [
        np.array([[*o.position_m, o.score] for o in sorted(r.objects.objects, key=lambda o: o.position_m[2])])
        for r, _ in frames
    ]
    assert any(
        e.shape == points.shape and np.allclose(points, e.astype(np.float32), rtol=0, atol=1e-7)
        for e in expected
    )
    np.testing.assert_allclose(np.sort(points[:, 2]), np.sort(centres[:, 2]), atol=1e-6)

    # Echo traces: the matched filter's envelope per receiver, peaking at one of its echoes.
    channel, _, payload = got["/echoloc/echo_traces"]
    traces = json.loads(payload)
    assert len(traces["channels"]) == 4
    for trace in traces["channels"]:
        envelope = np.array(trace["envelope"])
        peak_path = np.argmax(envelope) * traces["path_step_m"]
        assert min(abs(peak_path - p) for p in trace["echo_paths_m"]) < 2 * traces["path_step_m"]

    assert json.loads(got["/echoloc/stats"][2])["processed"] == 7


def test_map_hook_publishes_an_occupancy_grid():
    grid = np.zeros((3, 5))
    grid[1, 2] = 1.0

    with LiveView(port=0) as view:

        def publish():
            for _ in range(40):
                view.publish_map(grid, 0.05, (-0.1, -0.05, 0.5))
                time.sleep(0.05)

        got = asyncio.run(_client(view.port, publish, {"/echoloc/map"}))
    channel, _, payload = got["/echoloc/map"]
    assert channel["schemaName"] == "foxglove.Grid"
    message = _protobuf_class(channel).FromString(payload)
    assert message.column_count == 5
    assert message.cell_size.x == pytest.approx(0.05)
    cells = np.frombuffer(message.data, "<f4").reshape(3, 5)
    np.testing.assert_array_equal(cells, grid)


def test_envelope_trace_pools_the_analytic_magnitude():
    t = np.arange(1000)
    window = np.zeros(1000)
    window[300:500] = np.hanning(200)  # smooth edges: the analytic magnitude is the window
    burst = window * np.sin(2 * np.pi * 0.25 * t)
    pooled, factor = envelope_trace(np.stack([burst, 2 * burst]), 100)
    assert factor == 10
    assert pooled.shape == (2, 100)
    assert np.argmax(pooled[0]) in (39, 40)  # the window's peak, sample 400
    np.testing.assert_allclose(pooled[0], window.reshape(100, 10).max(axis=1), atol=0.02)
    np.testing.assert_allclose(pooled[1], 2 * pooled[0])


def test_a_live_floor_plan_lies_flat_in_the_body_frame_under_the_located_objects(results):
    """The live floor plan is published in the body frame (x forward, y left, z up), flat, with
    its cells where the objects are: an object at optical (x, y, z) lies over body (z, -x)."""
    from echoloc.io.export import BODY_FRAME_ID, OPTICAL_TO_BODY
    from echoloc.maps.map_export import map_floor_plan
    from echoloc.maps.mapping import GridSpec, MapAccumulator

    recording, processed = results
    spec = GridSpec.floor_plan((-0.5, 0.5), (0.2, 1.0), 0.02)
    mapper = MapAccumulator(spec, recording)
    for result, _ in processed:
        mapper.add_frame(result.echoes, [0, 0, 0, 0, 0, 0, 1.0], objects=result.objects)
    cells, corner = map_floor_plan(mapper.grid())

    with LiveView(port=0) as view:

        def publish():
            for _ in range(40):
                view.publish_map(cells, spec.cell_m, corner, stamp_s=12.5)
                time.sleep(0.05)

        got = asyncio.run(_client(view.port, publish, {"/echoloc/map"}))
    channel, _, payload = got["/echoloc/map"]
    message = _protobuf_class(channel).FromString(payload)
    assert message.frame_id == BODY_FRAME_ID
    assert (message.timestamp.seconds, message.timestamp.nanos) == (12, 500_000_000)
    q = message.pose.orientation
    assert (q.x, q.y, q.z, q.w) == (0.0, 0.0, 0.0, 1.0)  # flat: x-y is the floor
    decoded = np.frombuffer(message.data, "<f4").reshape(-1, message.column_count)
    np.testing.assert_allclose(decoded, cells, atol=1e-6)
    h = spec.cell_m
    origin = np.array([message.pose.position.x, message.pose.position.y])
    for obj in processed[0][0].objects.objects:
        body = OPTICAL_TO_BODY @ obj.position_m
        column, row = np.floor((body[:2] - origin) / h).astype(int)
        neighbourhood = decoded[max(row - 1, 0) : row + 2, max(column - 1, 0) : column + 2]
        assert neighbourhood.max() > 0.5, (obj.position_m, body)


def test_the_optical_frame_hangs_under_the_body_frame_with_capture_clock_stamps(results):
    """/tf carries REP-103's optical rotation; messages carry the frame's capture time."""
    from scipy.spatial.transform import Rotation

    from echoloc.io.export import BODY_FRAME_ID, SENSOR_FRAME_ID

    recording, frames = results
    with LiveView(port=0, max_rate_hz=50.0) as view:
        view.set_session(recording)

        def publish():
            for _ in range(20):
                for result, samples in frames:
                    view.publish(result, samples)
                    time.sleep(0.025)

        got = asyncio.run(_client(view.port, publish, {"/tf", "/echoloc/points"}))
    channel, _, payload = got["/tf"]
    transform = _protobuf_class(channel).FromString(payload).transforms[0]
    assert (transform.parent_frame_id, transform.child_frame_id) == (BODY_FRAME_ID, SENSOR_FRAME_ID)
    r = transform.rotation
    body = Rotation.from_quat([r.x, r.y, r.z, r.w]).apply([0.1, 0.2, 1.0])
    np.testing.assert_allclose(body, [1.0, -0.1, -0.2], atol=1e-12)
    channel, _, payload = got["/echoloc/points"]
    stamp = _protobuf_class(channel).FromString(payload).timestamp
    times = {round(result.objects.time_s * 1e9) for result, _ in frames}
    assert stamp.seconds * 1_000_000_000 + stamp.nanos in times
