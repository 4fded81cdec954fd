"""The streaming processor and its sockets: same results as the batch chain, and every frame accounted for."""

from __future__ import annotations

import itertools
import socket
import sys
import threading
import time
from dataclasses import replace
from typing import Any

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from echoloc.errors import EchoLocError
from echoloc.io.output import echoes_record, objects_record
from echoloc.pipeline import prepare, run
from echoloc.realtime.protocol import encode_frame, encode_session
from echoloc.realtime.stream import (
    FrameQueue,
    LatencyHistogram,
    SequenceTracker,
    StreamFrame,
    StreamProcessor,
    recording_frames,
    stream_recording,
)
from echoloc.realtime.transport import (
    EndEvent,
    Endpoint,
    Listener,
    SessionEvent,
    parse_endpoint,
    send_recording,
)
from echoloc.sim.scene import default_scene
from echoloc.sim.scenefile import load_scene
from echoloc.sim.simulation import recording_header, simulate
from repo_paths import REPO

SCENES = REPO / "src" / "echoloc" / "scenes"


@pytest.fixture(scope="module")
def recording():
    return simulate(default_scene(), 12)


@pytest.fixture(scope="module")
def two_tx():
    return simulate(load_scene(SCENES / "two-transmitters.toml"), 6)


def _records(pairs):
    return [(echoes_record(e), objects_record(o)) for e, o in pairs]


@pytest.mark.parametrize("batch_frames", [1, 5])
def test_streaming_equals_batch_processing(recording, batch_frames):
    chain = prepare(recording)
    batch = _records(run(chain))
    streamed = _records((r.echoes, r.objects) for r in stream_recording(chain, batch_frames=batch_frames))
    assert streamed == batch
    # Not vacuous: the three balls are found in every frame.
    assert all(len(o["objects"]) == 3 for _, o in batch)


def test_batches_of_frames_give_the_echoes_and_objects_of_one_at_a_time(recording, two_tx):
    """run() hands the estimator 32 frames a call by default; 1 or 5 a call change nothing, with
    transmitters fired in turn too (objects combine the latest frame of each)."""
    for rec in (recording, two_tx):
        chain = prepare(rec)
        one = _records(run(chain, batch_frames=1))
        assert _records(run(chain, batch_frames=5)) == one
        assert _records(run(chain)) == one


def test_a_refused_frame_in_a_batch_keeps_the_frames_before_it(recording):
    """An estimator error at frame 3 of a batch: frames 0-2 still come out, then the error."""
    chain = prepare(recording)
    calls = []

    class Refusing:
        def __call__(self, frame):
            calls.append(1)
            if len(calls) == 4:
                raise EchoLocError("frame refused")
            return chain.estimator(frame)

        def batch(self, frames):
            raise EchoLocError("frame refused")

    refusing = replace(chain, estimator=Refusing())
    done: list[int] = []

    def take_all() -> None:
        for echoes, _ in run(refusing, batch_frames=8):
            done.append(echoes.frame)

    with pytest.raises(EchoLocError, match="frame refused"):
        take_all()
    assert done == [0, 1, 2]


def test_a_batch_through_the_processor_times_each_frame_from_the_batch_s_start(recording):
    """Frames without an arrival time count from the batch's start, to when their result is
    made (after the batch's one call, in frame order); the objects are those of one frame a
    call."""
    chain = prepare(recording)
    processor = StreamProcessor(chain)
    frames = [replace(f, arrival_s=float("nan")) for f in list(recording_frames(recording))[:6]]
    results = processor.process_batch(frames)
    assert [r.echoes.frame for r in results] == list(range(6))
    assert processor.processed == 6
    latencies = [r.latency_s for r in results]
    assert latencies[0] > 0
    assert all(a <= b for a, b in itertools.pairwise(latencies))  # made in order, one clock
    alone = StreamProcessor(chain)
    assert _records((r.echoes, r.objects) for r in results) == _records(
        (r.echoes, r.objects) for r in map(alone.process, frames)
    )
    assert processor.process_batch([]) == []


def test_streaming_equals_batch_with_transmitters_fired_in_turn(two_tx):
    assert two_tx.frame_transmitter is not None
    assert len(set(two_tx.frame_transmitter.tolist())) == 2
    chain = prepare(two_tx)
    assert _records((r.echoes, r.objects) for r in stream_recording(chain)) == _records(run(chain))


def test_a_session_header_streams_what_the_recording_gives(recording):
    """The network path: a chain prepared from the session (no frames) gives the same objects."""
    from echoloc.realtime.protocol import decode_header, decode_session

    message = encode_session(recording)
    header = decode_session(decode_header(message), message[52:], "test")
    processor = StreamProcessor(prepare(header))
    streamed = [objects_record(processor.process(f).objects) for f in recording_frames(recording)]
    assert streamed == [objects_record(o) for _, o in run(prepare(recording))]


def test_latency_histogram_quantiles_within_half_a_percent():
    rng = np.random.default_rng(3)
    values = rng.lognormal(mean=np.log(2e-3), sigma=0.6, size=20_000)
    hist = LatencyHistogram()
    for v in values:
        hist.add(float(v))
    for q in (0.5, 0.9, 0.99):
        exact = np.quantile(values, q, method="inverted_cdf")
        assert hist.quantile(q) == pytest.approx(exact, rel=0.006)
    assert hist.max_s == values.max()
    assert hist.count == len(values)
    # Constant memory: the counters do not grow with the number of values.
    assert len(hist._counts) < 2500
    hist.reset()
    assert np.isnan(hist.quantile(0.5))


@given(
    st.lists(st.floats(min_value=1e-6, max_value=10.0), min_size=1, max_size=60),
    st.sampled_from([0.0, 0.01, 0.5, 0.9, 0.99, 1.0]),
)
def test_latency_quantile_within_half_a_percent_and_never_beyond_the_values(values, q):
    # A quantile is its bin's centre: 20 latencies once gave a p99 above their maximum.
    hist = LatencyHistogram()
    for v in values:
        hist.add(v)
    exact = float(np.quantile(values, q, method="inverted_cdf"))
    assert min(values) <= hist.quantile(q) <= max(values)
    assert hist.quantile(q) == pytest.approx(exact, rel=0.006)
    assert (hist.min_s, hist.max_s) == (min(values), max(values))


def test_sequence_tracker_counts_gaps_wraps_and_disorder():
    tracker = SequenceTracker()
    numbers = [tracker.observe(s) for s in (2**32 - 2, 2**32 - 1, 0, 3, 2, 4)]
    # Wrapping 2**32-1 -> 0 is not a gap; 0 -> 3 loses 1 and 2; 2 then arrives late.
    assert numbers == [2**32 - 2, 2**32 - 1, 2**32, 2**32 + 3, None, 2**32 + 4]
    assert tracker.lost == 2
    assert tracker.out_of_order == 1


def test_queue_drops_oldest_frames_counts_them_and_keeps_sessions():
    queue = FrameQueue(3)
    frames = [StreamFrame(k, np.zeros((1, 1)), 0.0) for k in range(5)]
    queue.put(frames[0])
    queue.put(SessionEvent(None))  # type: ignore[arg-type]
    for f in frames[1:]:
        queue.put(f)
    assert queue.dropped == 2
    assert len(queue) == 3
    items = [queue.get(0.01) for _ in range(4)]
    assert isinstance(items[0], SessionEvent)
    assert [i.index for i in items[1:]] == [2, 3, 4]
    assert queue.get(0.01) is None


def test_a_batch_off_the_queue_is_the_frames_waiting_up_to_a_control_item():
    queue = FrameQueue(16)
    frames = [StreamFrame(k, np.zeros((1, 1)), 0.0) for k in range(6)]
    for f in frames[:4]:
        queue.put(f)
    queue.put(SessionEvent(None))  # type: ignore[arg-type]
    for f in frames[4:]:
        queue.put(f)
    assert [f.index for f in queue.get_batch(0.01, 3)] == [0, 1, 2]  # at most 3
    assert [f.index for f in queue.get_batch(0.01, 8)] == [3]  # never past the session
    assert isinstance(queue.get_batch(0.01, 8)[0], SessionEvent)
    assert [f.index for f in queue.get_batch(0.01, 8)] == [4, 5]
    assert len(queue) == 0
    assert queue.get_batch(0.01, 8) == []


def test_blocking_queue_waits_instead_of_dropping():
    queue = FrameQueue(1, block=True)
    queue.put(StreamFrame(0, np.zeros((1, 1)), 0.0))
    done = threading.Event()

    def producer():
        queue.put(StreamFrame(1, np.zeros((1, 1)), 0.0))
        done.set()

    thread = threading.Thread(target=producer)
    thread.start()
    assert not done.wait(0.2)
    # A put that did not wait would have finished by now, the oldest frame dropped for it.
    assert thread.is_alive()
    assert (len(queue._items), queue.dropped) == (1, 0)
    assert queue.get(0.1).index == 0
    assert done.wait(2.0)
    thread.join()
    assert queue.dropped == 0


def test_parse_endpoint_defaults_to_loopback():
    assert parse_endpoint("7447") == Endpoint("127.0.0.1", 7447, "tcp")
    assert parse_endpoint("udp://0.0.0.0:9") == Endpoint("0.0.0.0", 9, "udp")
    with pytest.raises(EchoLocError, match="not a number"):
        parse_endpoint("host:abc")


def _drain(listener, n_frames, timeout_s=20.0):
    """Items off the listener's queue until n_frames frames or an end arrived."""
    items = []
    deadline = time.monotonic() + timeout_s
    frames = 0
    while time.monotonic() < deadline and frames < n_frames:
        item = listener.queue.get(0.1)
        if item is None:
            continue
        if isinstance(item, EndEvent):
            break
        items.append(item)
        frames += isinstance(item, StreamFrame)
    return items


@pytest.mark.parametrize("transport", ["tcp", "udp"])
def test_loopback_stream_gives_the_batch_results(recording, transport):
    with Listener(Endpoint("127.0.0.1", 0, transport), FrameQueue(64, block=True)) as listener:
        sender = threading.Thread(
            target=send_recording,
            args=(recording, listener.address),
            kwargs={"speed": 0, "sample_format": "float64" if transport == "tcp" else "float32"},
        )
        sender.start()
        items = _drain(listener, recording.n_frames)
        sender.join(10)
        counters = listener.counters()
    assert isinstance(items[0], SessionEvent)
    processor = StreamProcessor(prepare(items[0].header))
    got = [objects_record(processor.process(f).objects) for f in items[1:]]
    assert counters["received"] == recording.n_frames
    assert counters["lost"] == counters["malformed"] == counters["dropped"] == 0
    want = [objects_record(o) for _, o in run(prepare(recording))]
    if transport == "tcp":  # float64 on the wire: bit for bit
        assert got == want
    else:  # float32 on the wire (one datagram a frame): the same objects within 10 µm
        for g, w in zip(got, want, strict=True):
            assert len(g["objects"]) == len(w["objects"]) == 3
            for a, b in zip(g["objects"], w["objects"], strict=True):
                np.testing.assert_allclose(a["position_m"], b["position_m"], atol=1e-5)


def test_udp_losses_garbage_and_misfits_are_counted_never_silent(recording):
    with Listener(Endpoint("127.0.0.1", 0, "udp"), FrameQueue(64)) as listener:
        out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        address = ("127.0.0.1", listener.address.port)
        frame = recording.frames[0]
        send = lambda data: out.sendto(data, address)  # noqa: E731
        send(encode_frame(frame, sequence=0, sample_rate_hz=2e5))  # before any session: rejected
        send(encode_session(recording))
        for seq in (0, 1, 4, 5):  # 2 and 3 lost on the way
            send(encode_frame(frame, sequence=seq, sample_rate_hz=2e5))
        send(b"not a message at all, only noise on the port")
        send(encode_frame(frame[:3], sequence=6, sample_rate_hz=2e5))  # 3 channels: rejected
        send(encode_frame(frame, sequence=3, sample_rate_hz=2e5))  # late: out of order
        truncated = encode_frame(frame, sequence=7, sample_rate_hz=2e5)[:-10]
        send(truncated)
        out.close()
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and listener.malformed < 2:
            time.sleep(0.02)
        time.sleep(0.1)
        counters = listener.counters()
        messages = list(listener.errors())
    assert counters == {
        "received": 4,
        "lost": 2,
        "dropped": 0,
        "out_of_order": 1,
        "malformed": 2,
        "rejected": 2,
        "refused": 0,
        "restarts": 0,
    }
    assert any("before any session" in m for m in messages)
    assert any("3 channels" in m for m in messages)
    assert all("\n" not in m for m in messages)


def test_processor_counts_late_frames_and_refuses_misfits(recording):
    processor = StreamProcessor(prepare(recording), deadline_s=0.5)
    old = StreamFrame(0, recording.frames[0], 0.0, 0, time.monotonic() - 1.0)
    result = processor.process(old)
    assert result.late
    assert result.latency_s >= 1.0
    # A frame that just arrived, and one without an arrival time, are on time.
    fresh = processor.process(StreamFrame(1, recording.frames[1], 0.01, 0, time.monotonic()))
    assert not fresh.late
    assert fresh.latency_s < 0.5
    assert not processor.process(StreamFrame(2, recording.frames[2], 0.02)).late
    assert (processor.stats().late, processor.stats().processed) == (1, 3)
    with pytest.raises(EchoLocError, match="3 channels"):
        processor.process(StreamFrame(1, recording.frames[0][:3], 0.0))


def test_a_new_session_takes_its_chain_and_keeps_the_streams_counters(recording, two_tx):
    """start_session: the new chain's frames come out as a fresh processor's would (no echoes of
    the old session combined into them), while processed, late and the latencies go on."""
    processor = StreamProcessor(prepare(recording), deadline_s=0.5)
    processor.process(StreamFrame(0, recording.frames[0], 0.0, 0, time.monotonic() - 1.0))  # late
    processor.process(StreamFrame(1, recording.frames[1], 0.01))
    chain = prepare(two_tx)
    processor.start_session(chain)
    assert processor.chain is chain
    got = [processor.process(f) for f in recording_frames(two_tx)]
    fresh = StreamProcessor(chain)
    expected = [fresh.process(f) for f in recording_frames(two_tx)]
    assert [objects_record(r.objects) for r in got] == [objects_record(r.objects) for r in expected]
    stats = processor.stats()
    assert (stats.processed, stats.late) == (2 + two_tx.n_frames, 1)
    assert processor.latency.count == 2 + two_tx.n_frames


def test_a_sender_written_from_the_protocol_page_alone_is_located_right():
    """examples/minimal_sender.py uses only the standard library and docs/STREAM_PROTOCOL.md."""
    import subprocess
    import sys

    script = REPO / "examples" / "minimal_sender.py"
    assert "echoloc" not in {
        line.split()[1].split(".")[0]
        for line in script.read_text().splitlines()
        if line.startswith("import ")
    }
    reflector = (0.05, -0.03, 0.6)
    with Listener(Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(16)) as listener:
        subprocess.run(
            [
                sys.executable,
                str(script),
                *("--to", f"127.0.0.1:{listener.address.port}", "--frames", "3", "--rate", "200"),
                *("--reflector", *map(str, reflector)),
            ],
            check=True,
            timeout=60,
        )
        items = _drain(listener, 3)
        counters = listener.counters()
    assert counters["malformed"] == counters["rejected"] == 0
    session, *frames = items
    assert isinstance(session, SessionEvent)
    assert len(frames) == 3
    processor = StreamProcessor(prepare(session.header))
    for frame in frames:
        (obj,) = processor.process(frame).objects.objects
        # int16 samples, noise 1 % of full scale: within a millimetre.
        np.testing.assert_allclose(obj.position_m, reflector, atol=1e-3)


def test_session_of_two_transmitters_combines_frames_as_the_batch_chain(two_tx):
    """Over the wire the frames name their transmitter; the header alone must combine them."""
    from echoloc.realtime.protocol import decode_header, decode_session

    message = encode_session(two_tx)
    header = decode_session(decode_header(message), message[52:], "test")
    assert header.frame_transmitter is None
    processor = StreamProcessor(prepare(header))
    streamed = [objects_record(processor.process(f).objects) for f in recording_frames(two_tx)]
    batch = [objects_record(o) for _, o in run(prepare(two_tx))]
    assert streamed == batch
    # Combined: after the first frame, objects are supported by both transmitters' channels.
    assert all(o["channels"] == 8 for line in batch[1:] for o in line["objects"])


def test_geometry_file_replaces_the_session_message(recording):
    with Listener(Endpoint("127.0.0.1", 0, "udp"), FrameQueue(8), geometry=recording) as listener:
        out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        for seq in range(3):  # frames only, as a firmware without a session would send
            out.sendto(
                encode_frame(
                    recording.frames[seq], sequence=seq, sample_rate_hz=2e5, frame_time_s=seq * 0.01
                ),
                ("127.0.0.1", listener.address.port),
            )
        out.close()
        items = _drain(listener, 3, timeout_s=5)
    assert isinstance(items[0], SessionEvent)
    assert items[0].header.n_frames == 0
    assert [f.index for f in items[1:]] == [0, 1, 2]
    assert listener.counters()["rejected"] == 0


def test_garbage_bytes_on_tcp_are_counted_as_malformed_not_dropped_silently():
    from echoloc.realtime.protocol import MAGIC

    garbage = b"not a message at all " * 11
    with Listener(Endpoint("127.0.0.1", 0, "tcp"), FrameQueue(16)) as listener:
        with socket.create_connection(("127.0.0.1", listener.address.port), timeout=5) as client:
            client.sendall(garbage)
        # The listener closes the connection once it has read it to its close; a connection that
        # never sent a session queues no end (`stream --once` must not stop for garbage).
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and (listener.malformed == 0 or listener.connections):
            time.sleep(0.01)
        assert listener.queue.get(0.1) is None
        counters = listener.counters()
    # Every byte skipped but the last len(MAGIC) - 1, which could have begun a message when the
    # sender hung up; one complaint per read that skipped bytes (one, unless TCP split them).
    assert listener.bytes_skipped == len(garbage) - (len(MAGIC) - 1)
    assert counters["malformed"] >= 1
    assert counters["received"] == 0


def test_the_listeners_address_outlives_its_socket():
    listener = Listener(Endpoint("127.0.0.1", 0, "udp"), FrameQueue(4)).start()
    port = listener.address.port
    listener.stop()
    assert listener.address.port == port > 0


def test_warm_up_frame_takes_clean_and_locates_its_reflector(recording):
    """The warm-up frame reaches every kernel a crowded frame does: its overlapping echoes go to
    CLEAN on every channel, and the reflector on the transmitter's axis is located there."""
    from echoloc.pipeline import samples_echoes, transmitter_objects
    from echoloc.tof.echoes import MatchedFilter, _compiled_batch

    chain = prepare(recording)
    processor = StreamProcessor(chain)
    frame = processor.warm_up_frame()
    matched = MatchedFilter(
        np.asarray(recording.waveform, float), recording.n_samples, recording.sample_rate_hz
    )
    handed = _compiled_batch(
        matched.correlate_single(frame[None]).reshape(len(frame), -1), matched, chain.echo_options
    )
    assert not handed.ok.any()
    objects = transmitter_objects(chain, samples_echoes(chain, frame, 0, 0.0), 0).objects
    assert len(objects) >= 1
    axis = np.asarray(chain.locate_options.boresight, dtype=float)
    nearest = min(
        objects,
        key=lambda o: float(np.linalg.norm(np.cross(o.position_m - recording.transmitters_m[0], axis))),
    )
    offset = nearest.position_m - recording.transmitters_m[0]
    assert np.linalg.norm(np.cross(offset, axis)) < 5e-3  # on the axis, within 5 mm
    before = processor.stats()
    processor.warm_up()
    assert processor.stats() == before  # counters untouched


# The kernels a stream calls from Python once a frame, by module. Written out by hand: a new
# per-frame kernel must be added here to be held to ``nogil``.
_FRAME_KERNELS = {
    "echoloc._chain_kernels": ("echoes_and_objects",),
    "echoloc.tof._echoes_kernels": (
        "weigh_and_fold",
        "correlate_and_fit",
        "batch_channels",
        "clean_run",
        "clean_run_rows",
    ),
    "echoloc.localise._locate_kernels": ("associate", "associate_frame"),
    "echoloc.maps._mapping_kernels": ("channel_update", "add_supported_evidence", "apply_frame"),
}


@pytest.mark.parametrize(
    ("module", "name"), [(module, name) for module, names in _FRAME_KERNELS.items() for name in names]
)
def test_frame_kernels_are_compiled_to_release_the_gil(module: str, name: str) -> None:
    """Every kernel a frame calls runs without the GIL, so the receiving thread of
    `echoloc stream` (and the live view's and recorder's) can work meanwhile."""
    kernel = getattr(__import__(module, fromlist=[name]), name)
    assert kernel.targetoptions.get("nogil") is True


def _share_of_call_with_python_running(kernel: Any, *args: Any) -> float:
    """``kernel(*args)`` in a thread while this one runs Python in a loop: the span of this
    thread's steps inside the call, as a share of the call's duration."""
    call: list[float] = []

    def run() -> None:
        started = time.perf_counter()
        kernel(*args)
        call.extend([started, time.perf_counter()])

    steps: list[float] = []
    previous = sys.getswitchinterval()
    sys.setswitchinterval(1e-4)
    try:
        worker = threading.Thread(target=run)
        worker.start()
        while worker.is_alive():
            steps.append(time.perf_counter())
        worker.join()
    finally:
        sys.setswitchinterval(previous)
    started, ended = call
    inside = [t for t in steps if started < t < ended]
    return (inside[-1] - inside[0]) / (ended - started) if len(inside) > 1 else 0.0


def test_a_frame_kernel_lets_another_thread_run_during_its_call() -> None:
    """What ``nogil`` buys, checked on one kernel: while a thread is inside the fold (tens of
    milliseconds here, many scheduler slices), the main thread keeps running Python. A kernel
    that held the GIL would let it run only around the call's ends (the switch interval is 0.1
    ms here): under a tenth of the call on a quiet machine, under half on a loaded one. Three
    tries, as other jobs may hold the cores for a while."""
    from echoloc.tof import _echoes_kernels as kernels

    rows, bins, folded = 1000, 40_000, 1000
    spectrum = np.broadcast_to(np.ones(bins, np.complex64), (rows, bins))  # read-only, no memory
    weights = np.ones(bins, np.complex64)
    out = np.zeros((rows, folded), np.complex64)
    kernels.weigh_and_fold(spectrum[:2], weights, out[:2])  # compiled (or loaded) for these types first
    shares = []
    for _ in range(3):
        shares.append(_share_of_call_with_python_running(kernels.weigh_and_fold, spectrum, weights, out))
        if shares[-1] > 0.5:
            break
    assert np.array_equal(out, np.full((rows, folded), bins // folded, np.complex64))  # 40 bins a lag
    assert max(shares) > 0.5, shares


def test_warm_up_is_not_taken_for_a_frame_by_the_channel_check(recording):
    """The made-up warm-up frame went through the live chain: its channel check counted it as the
    session's first frame (frames_seen 0 -> 1), judging the sensor on noise it never sent."""
    chain = prepare(recording_header(default_scene()))
    watch = chain.channel_watch
    assert watch is not None
    processor = StreamProcessor(chain)
    processor.warm_up()
    assert watch.frames_seen == 0
    processor.process(StreamFrame(0, recording.frames[0], 0.0))  # a real frame is checked
    assert watch.frames_seen == 1


def test_a_frame_that_does_not_fit_is_rejected_not_also_lost(recording):
    """Frames 0, 1 (3 channels: a misfit), 2: one rejected, none lost (the misfit's sequence
    number still belongs to the numbering)."""
    with Listener(Endpoint("127.0.0.1", 0, "udp"), FrameQueue(64)) as listener:
        out = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        address = ("127.0.0.1", listener.address.port)
        frame = recording.frames[0]
        out.sendto(encode_session(recording), address)
        out.sendto(encode_frame(frame, sequence=0, sample_rate_hz=2e5), address)
        out.sendto(encode_frame(frame[:3], sequence=1, sample_rate_hz=2e5), address)
        out.sendto(encode_frame(frame, sequence=2, sample_rate_hz=2e5), address)
        out.close()
        deadline = time.monotonic() + 5
        while time.monotonic() < deadline and listener.received + listener.rejected < 3:
            time.sleep(0.02)
        counters = listener.counters()
    assert (counters["received"], counters["rejected"], counters["lost"]) == (2, 1, 0)
