"""`echoloc send`, `stream` and `record` as a user runs them: separate processes on loopback."""

from __future__ import annotations

import contextlib
import json
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import replace
from pathlib import Path

import h5py
import numpy as np
import pytest

from echoloc.io.recording import read_recording, write_recording
from echoloc.realtime.transport import Endpoint, send_recording
from echoloc.sim.scene import default_scene
from echoloc.sim.simulation import simulate
from interactive import with_sigint

ECHOLOC = [str(Path(sys.executable).with_name("echoloc"))]
TIMEOUT_S = 60


@pytest.fixture(scope="module")
def recording_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("stream") / "demo.h5"
    write_recording(simulate(default_scene(), 15), path)
    return path


def echoloc(*args: object, check: bool = False) -> subprocess.CompletedProcess[str]:
    """Run ``echoloc ARGS`` to its end, its output captured as text."""
    return subprocess.run(
        [*ECHOLOC, *map(str, args)], capture_output=True, text=True, timeout=TIMEOUT_S, check=check
    )


class Proc:
    """A command running in the background whose stderr lines are collected as they come."""

    def __init__(self, *args: object) -> None:
        self.popen = subprocess.Popen(
            with_sigint([*ECHOLOC, *map(str, args)]),
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            env={**os.environ, "PYTHONFAULTHANDLER": "1"},  # SIGABRT on a hang prints every thread
        )
        self.lines: list[str] = []
        self._stdout: list[str] = []
        self._reader = threading.Thread(target=self._read, daemon=True)
        self._reader.start()
        self._out_reader = threading.Thread(target=self._read_stdout, daemon=True)
        self._out_reader.start()

    def _read(self) -> None:
        assert self.popen.stderr is not None
        for line in self.popen.stderr:
            self.lines.append(line.rstrip("\n"))

    def _read_stdout(self) -> None:
        assert self.popen.stdout is not None
        self._stdout.append(self.popen.stdout.read())

    def wait_for(self, pattern: str, timeout_s: float = TIMEOUT_S) -> re.Match[str]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for line in list(self.lines):
                found = re.search(pattern, line)
                if found:
                    return found
            if self.popen.poll() is not None and not self._reader.is_alive():
                break
            time.sleep(0.02)
        self.kill()
        raise AssertionError(f"no line matching {pattern!r} in {self.lines}")

    def port(self) -> int:
        return int(self.wait_for(r"listening on \w+://127\.0\.0\.1:(\d+)").group(1))

    def finish(self, timeout_s: float = TIMEOUT_S) -> tuple[int, str]:
        try:
            self.popen.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired as hung:
            self.popen.send_signal(signal.SIGABRT)  # faulthandler: where every thread is
            with contextlib.suppress(subprocess.TimeoutExpired):
                self.popen.wait(timeout=5)
            self.kill()
            raise AssertionError("\n".join(["still running; its stderr:", *self.lines[-80:]])) from hung
        self.kill()  # waits for the readers, closes the pipes
        return self.popen.returncode, "".join(self._stdout)

    def kill(self) -> None:
        """Kill it if still running, and close its pipes."""
        if self.popen.poll() is None:
            self.popen.kill()
        self.popen.wait(10)
        self._reader.join(5)
        self._out_reader.join(5)
        for pipe in (self.popen.stdout, self.popen.stderr):
            if pipe is not None:
                pipe.close()


def test_stream_prints_what_locate_prints_and_counts_nothing_lost(recording_path):
    stream = Proc("stream", "--listen", "127.0.0.1:0", "--once", "--json")
    port = stream.port()
    sent = echoloc("send", recording_path, "--to", f"127.0.0.1:{port}", "--speed", "0")
    assert sent.returncode == 0, sent.stderr
    assert "sent 15 frames" in sent.stderr
    code, stdout = stream.finish()
    assert code == 0, stream.lines
    located = echoloc("locate", recording_path, "--json", check=True)
    assert stdout == located.stdout
    assert len(stdout.splitlines()) == 15
    summary = stream.lines[-1]
    assert "received 15, processed 15, lost 0, dropped 0, late 0, out of order 0" in summary
    assert "malformed 0, rejected 0" in summary


def test_a_second_session_keeps_the_counts_of_the_first(tmp_path, recording_path):
    """Two senders in turn, the second's head at another temperature (a new session, a new
    chain): every frame is located as `locate` locates its file, and the counters are the
    stream's, not the last session's (they once said processed 15 of 30)."""
    warmer = tmp_path / "warmer.h5"
    write_recording(simulate(replace(default_scene(), temperature_c=30.0, seed=1), 15), warmer)
    stream = Proc("stream", "--listen", "127.0.0.1:0", "--json", "--max-frames", "30")
    port = stream.port()
    for path in (recording_path, warmer):
        sent = echoloc("send", path, "--to", f"127.0.0.1:{port}", "--speed", "0")
        assert sent.returncode == 0, sent.stderr
    code, stdout = stream.finish()
    assert code == 0, stream.lines
    located = [echoloc("locate", path, "--json", check=True).stdout for path in (recording_path, warmer)]
    assert stdout == "".join(located)
    assert sum("session: 4 receivers" in line for line in stream.lines) == 2
    assert "received 30, processed 30, lost 0, dropped 0, late 0" in stream.lines[-1]


def test_stream_with_the_live_view_and_its_map_changes_nothing_it_prints(recording_path):
    stream = Proc("stream", "--listen", "127.0.0.1:0", "--once", "--json", "--view", "--view-port", "0")
    port = stream.port()
    stream.wait_for(r"live view on ws://127\.0\.0\.1:\d+")
    sent = echoloc("send", recording_path, "--to", f"127.0.0.1:{port}", "--speed", "1")
    assert sent.returncode == 0, sent.stderr
    code, stdout = stream.finish()
    assert code == 0, stream.lines
    located = echoloc("locate", recording_path, "--json", check=True)
    assert stdout == located.stdout
    assert "received 15, processed 15, lost 0, dropped 0" in stream.lines[-1]


def test_stream_reports_counts_on_sigint(recording_path):
    stream = Proc("stream", "--listen", "127.0.0.1:0", "--udp")
    port = stream.port()
    send_recording(read_recording(recording_path), Endpoint("127.0.0.1", port, "udp"), speed=0, end=False)
    stream.wait_for(r"session: 4 receivers")
    time.sleep(0.5)
    stream.popen.send_signal(signal.SIGINT)
    code, _ = stream.finish()
    assert code == 0
    found = re.search(r"received (\d+), processed (\d+), lost (\d+), dropped (\d+)", stream.lines[-1])
    assert found is not None, stream.lines
    received, processed, lost, dropped = map(int, found.groups())
    left = re.search(r"dropped \d+, unprocessed (\d+)", stream.lines[-1])
    unprocessed = 0 if left is None else int(left.group(1))
    # Every one of the 15 frames sent is accounted for: processed, lost, dropped, or left
    # unprocessed by the interrupt (still queued, or in the batch it cut short).
    assert received + lost == 15
    assert processed + dropped + unprocessed == received
    assert stream.lines[-1].endswith("(interrupted)")


def test_frames_left_when_the_stream_stops_are_counted_unprocessed(recording_path):
    """Stopped after 5 frames while the sender's 15 came in: those received and neither
    processed nor dropped are reported as left unprocessed, never silently."""
    stream = Proc("stream", "--listen", "127.0.0.1:0", "--max-frames", "5")
    port = stream.port()
    echoloc("send", recording_path, "--to", f"127.0.0.1:{port}", "--speed", "0")  # may be cut off
    code, _ = stream.finish()
    assert code == 0, stream.lines
    found = re.search(r"received (\d+), processed (\d+), lost 0, dropped (\d+)", stream.lines[-1])
    assert found is not None, stream.lines
    received, processed, dropped = map(int, found.groups())
    assert processed == 5
    left = re.search(r"dropped \d+, unprocessed (\d+)", stream.lines[-1])
    assert (0 if left is None else int(left.group(1))) == received - processed - dropped


def test_frames_left_when_recording_stops_are_counted_unrecorded(tmp_path, recording_path):
    """`record` stopped after 5 frames while 15 came in: every frame received is recorded,
    dropped, or reported as unrecorded, and the file holds the 5."""
    out = tmp_path / "five.h5"
    record = Proc("record", out, "--listen", "127.0.0.1:0", "--max-frames", "5")
    port = record.port()
    echoloc("send", recording_path, "--to", f"127.0.0.1:{port}", "--speed", "0")  # may be cut off
    code, _ = record.finish()
    assert code == 0, record.lines
    found = re.search(
        r"(\d+) frames in \d+ batch(?:es)? .* received (\d+), lost 0, dropped (\d+)", record.lines[-1]
    )
    assert found is not None, record.lines
    recorded, received, dropped = map(int, found.groups())
    assert recorded == 5
    left = re.search(r"dropped \d+, unrecorded (\d+)", record.lines[-1])
    assert (0 if left is None else int(left.group(1))) == received - recorded - dropped
    assert read_recording(out).n_frames == 5


def test_send_to_nothing_is_one_line_and_exit_2(recording_path):
    sent = echoloc("send", recording_path, "--to", "127.0.0.1:9", "--connect-timeout", "0.2")
    assert sent.returncode == 2
    assert len(sent.stderr.strip().splitlines()) == 1
    assert "cannot connect" in sent.stderr


def test_record_then_read_back_equals_what_was_sent(tmp_path, recording_path):
    out = tmp_path / "rec.h5"
    record = Proc("record", out, "--listen", "127.0.0.1:0", "--once", "--batch-frames", "4")
    port = record.port()
    source = read_recording(recording_path)
    send_recording(source, Endpoint("127.0.0.1", port), speed=0, sample_format="float32")
    code, _ = record.finish()
    assert code == 0, record.lines
    assert "15 frames in 4 batches to" in record.lines[-1]
    assert "received 15, lost 0, dropped 0, malformed 0" in record.lines[-1]
    back = read_recording(out)
    np.testing.assert_array_equal(back.frames, source.frames.astype(np.float32))
    with h5py.File(out, "r") as f:  # float32 on the wire: float32 on disk, nothing rounded
        assert f["frames"].dtype == np.float32
    np.testing.assert_array_equal(back.receivers_m, source.receivers_m)
    np.testing.assert_array_equal(back.waveform, source.waveform)
    np.testing.assert_allclose(back.frame_times_s, np.arange(15) * 0.01)


def test_record_killed_with_sigkill_keeps_every_flushed_batch(tmp_path, recording_path):
    out = tmp_path / "killed.h5"
    record = Proc("record", out, "--listen", "127.0.0.1:0", "--batch-frames", "5", "--verbose")
    port = record.port()
    source = read_recording(recording_path)
    stop = threading.Event()
    sender = threading.Thread(
        target=lambda: _send_until_stopped(source, port, stop),
        daemon=True,
    )
    sender.start()
    try:
        # Wait for a few batches on disk, then kill mid-stream: no chance to close the file.
        record.wait_for(r"(\d+) frames written")
        written = int(record.wait_for(r"(?:[3-9]\d|\d{3,}) frames written").group(0).split()[0])
        time.sleep(0.05)  # inside the next batch
        os.kill(record.popen.pid, signal.SIGKILL)
        record.popen.wait(10)
    finally:
        stop.set()
        sender.join(10)
        record.kill()
    assert record.popen.returncode == -signal.SIGKILL
    with h5py.File(out, "r") as f:  # the file opens ...
        assert f["frames"].shape[0] >= written
        assert f["frames"].dtype == np.float64  # as sent: float32 would round these samples
    back = read_recording(out)  # ... and passes the contract's every check
    reported = [int(m.group(1)) for line in record.lines if (m := re.search(r"(\d+) frames written", line))]
    # At most the batch being written is lost: everything reported flushed is there.
    assert back.n_frames >= reported[-1]
    assert back.n_frames % 5 == 0
    n = source.n_frames
    # Sent as float64 (float32 would round these samples), recorded as float64.
    expected = np.stack([source.frames[k % n] for k in range(back.n_frames)])
    np.testing.assert_array_equal(back.frames, expected)
    # Frame times run on across the loops at the recording's own step (10 ms).
    np.testing.assert_allclose(np.diff(back.frame_times_s), 0.01, atol=1e-9)


def _send_until_stopped(source, port: int, stop: threading.Event) -> None:
    from echoloc.errors import EchoLocError

    with contextlib.suppress(EchoLocError):  # the recorder was killed: the connection breaks
        send_recording(source, Endpoint("127.0.0.1", port), rate_hz=400.0, loops=0, stop=stop, end=False)


def test_stream_record_writes_the_processed_frames(tmp_path, recording_path):
    out = tmp_path / "both.h5"
    stream = Proc("stream", "--listen", "127.0.0.1:0", "--once", "--json", "--record", out)
    port = stream.port()
    source = read_recording(recording_path)
    send_recording(source, Endpoint("127.0.0.1", port), speed=0)
    code, stdout = stream.finish()
    assert code == 0, stream.lines
    assert [json.loads(line)["frame"] for line in stdout.splitlines()] == list(range(15))
    back = read_recording(out)
    # The samples as sent: float32 on the wire only where it holds them exactly ("auto").
    np.testing.assert_array_equal(back.frames, source.frames)
    np.testing.assert_array_equal(back.receivers_m, source.receivers_m)
    assert any("recorded 15 frames" in line for line in stream.lines)


@pytest.mark.parametrize("command", ["send", "stream", "record", "bench"])
def test_help_of_the_real_time_commands(command):
    from click.testing import CliRunner

    from echoloc.cli.commands import cli

    result = CliRunner().invoke(cli, [command, "--help"])
    assert result.exit_code == 0
    assert f"Usage: cli {command}" in result.output or f"Usage: echoloc {command}" in result.output
    if command in ("stream", "record", "send"):
        assert "127.0.0.1:7447" in result.output  # loopback unless told otherwise
    if command == "bench":
        assert all(option in result.output for option in ("--rounds", "--workers", "--reflectors"))


def test_bench_reports_both_chains_and_the_physics():
    done = echoloc("bench", "--reflectors", "0", "--frames", "4", "--baseline-frames", "1", "--json")
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["objects"] == 3
    assert report["echoloc"]["recall"] == 1.0
    assert report["speedup"] > 1  # the brute-force locate of the scipy chain takes seconds
    assert report["physics_frames_per_s"] == pytest.approx(85.8, abs=0.1)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["record", "x.npz"], "recorded to HDF5"),
        (["record", "/no/such/dir/x.h5"], "does not exist"),
        (["stream", "--record", "x.npz"], "recorded to HDF5"),
        (["stream", "--listen", "127.0.0.1:abc"], "port 'abc' is not a number"),
        (["record", "x.h5", "--udp", "--listen", "127.0.0.1:99999"], "outside 0..65535"),
        (["send", "/no/such.h5"], "no such file"),
        (["send", "x.h5", "--rate", "0"], "--rate must be > 0"),
        (["stream", "--listen", "127.0.0.1:0", "--duration", "-1"], "--duration"),
        (["record", "x.h5", "--listen", "127.0.0.1:0", "--batch-seconds", "0"], "--batch-seconds"),
    ],
)
def test_bad_input_is_one_line_and_exit_2(capsys, tmp_path, recording_path, args, message):
    from echoloc.cli import commands as cli

    args = [str(recording_path) if a == "x.h5" and args[0] == "send" else a for a in args]
    with pytest.raises(SystemExit) as info:
        cli.main(args)
    _, err = capsys.readouterr()
    assert info.value.code == 2
    assert len(err.strip().splitlines()) == 1
    assert err.startswith("echoloc: error: ")
    if message is not None:
        assert message in err


def test_record_with_no_sender_says_so_and_writes_nothing(capsys, tmp_path):
    from echoloc.cli import commands as cli

    out = tmp_path / "nothing.h5"
    with pytest.raises(SystemExit) as info:
        cli.main(["record", str(out), "--listen", "127.0.0.1:0", "--duration", "0.3"])
    _, err = capsys.readouterr()
    assert info.value.code == 2
    assert re.search(r"echoloc: error: .*nothing\.h5: no session arrived on tcp://127\.0\.0\.1:\d+", err)
    assert "Traceback" not in err
    assert not out.exists()


def test_a_busy_port_is_one_line_and_exit_2(capsys):
    import socket

    from echoloc.cli import commands as cli

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        with pytest.raises(SystemExit) as info:
            cli.main(["record", "out.h5", "--listen", f"127.0.0.1:{port}"])
    _, err = capsys.readouterr()
    assert info.value.code == 2
    assert f"cannot listen on tcp://127.0.0.1:{port}" in err


def test_stream_records_a_batch_before_processing_it(tmp_path, recording_path):
    """`stream --record`: frames are written before the chain runs on them, so a batch whose
    processing fails is still in the recording, sample for sample."""
    from echoloc.pipeline import prepare
    from echoloc.realtime.session import LiveSession
    from echoloc.realtime.stream import StreamProcessor, recording_frames
    from echoloc.realtime.transport import SessionEvent

    class Failing(StreamProcessor):
        def process_batch(self, frames):
            raise RuntimeError("the chain failed")

    class Counters:
        def counters(self):
            return {}

    source = read_recording(recording_path)
    out = tmp_path / "kept.h5"
    session = LiveSession(Counters(), prepare, 0.1, record_path=out)
    session.handle(SessionEvent(source))
    session.processor = Failing(session.processor.chain)
    frames = list(recording_frames(source, range(3)))
    with pytest.raises(RuntimeError, match="the chain failed"):
        session.handle(frames)
    session.close(interrupted=True)
    assert session.record_error is None
    kept = read_recording(out)
    assert kept.n_frames == 3
    # The recorder stores the samples as they came: float64 here, which float32 would round.
    np.testing.assert_array_equal(np.asarray(kept.frames), np.asarray(source.frames[:3]))


def test_stream_detects_envelope_echoes_with_the_threshold_locate_takes(tmp_path):
    """An envelope head streamed with a calibration and no estimator named: stream picks what
    locate picks for envelope data (envelope-peak) and prints what `locate --calibration`
    prints, both detecting with the calibration's threshold, not the matched filter's 14 dB
    (which finds other echoes on this head)."""
    recording = tmp_path / "ch101.h5"
    calibration = tmp_path / "calibration.json"
    echoloc("simulate", "ch101", "-o", recording, "--frames", "12", check=True)
    echoloc("calibrate", recording, "-o", calibration, check=True)
    record = json.loads(calibration.read_text())
    calibration.write_text(json.dumps({**record, "threshold_db": 1.25}))
    stream = Proc("stream", "--listen", "127.0.0.1:0", "--once", "--json", "--calibration", calibration)
    port = stream.port()
    echoloc("send", recording, "--to", f"127.0.0.1:{port}", "--speed", "0", check=True)
    code, stdout = stream.finish()
    assert code == 0, stream.lines
    located = echoloc("locate", recording, "--json", "--calibration", calibration, check=True).stdout
    at_14_db = echoloc(
        "locate", recording, "--json", "--calibration", calibration, "--threshold-db", "14", check=True
    ).stdout
    assert stdout == located
    assert located != at_14_db


def test_stream_takes_every_processing_option_locate_takes():
    """One definition (echoloc.cli.app.ChainSettings) gives both commands their options: what
    locate takes to process frames, stream takes too; only the choice of a file's frames and
    locate's output differ."""
    from echoloc.cli.commands import cli

    def names(command: str) -> set[str]:
        return {name for param in cli.commands[command].params for name in param.opts}

    of_a_file = {"recording_path", "--frames", "--positions", "--repair-nonfinite", "--json"}
    assert names("locate") - of_a_file <= names("stream")
    for option in ("--blind-zone", "--template", "--tvg", "--background", "--method", "--classes"):
        assert option in names("stream")


@pytest.fixture(scope="module")
def ringing_head(tmp_path_factory):
    """A head file, and a recording of it (two points, the transmitter ringing for 1.2 ms)."""
    folder = tmp_path_factory.mktemp("head")
    head_path = folder / "head.toml"
    head_path.write_text(
        "[array]\n"
        "transmitters_m = [[0.0, 0.0, 0.0]]\n"
        "receivers_m = [[0.25, 0.0, 0.0], [-0.25, 0.0, 0.0], [0.0, 0.25, 0.0], [0.0, -0.25, 0.0]]\n"
        "[acquisition]\nsample_rate_hz = 200e3\nn_samples = 1800\nframe_rate_hz = 100\n"
        "[channels]\norder = [1, 0, 3, 2]\n"
    )
    from echoloc.io.head import load_head

    scene = load_head(head_path).scene(
        {
            "reflectors": [{"position_m": [0.1, 0.05, 0.7]}, {"position_m": [-0.2, 0.0, 1.1]}],
            "ring_down": {"level": 3.0, "decay_s": 3e-4, "direct_path": True},
            "noise": {"snr_db": 25.0},
            "seed": 5,
        }
    )
    recording = folder / "ringing.h5"
    write_recording(simulate(scene, 12), recording)
    return head_path, recording


def test_stream_with_a_head_file_prints_what_locate_prints_with_every_option(ringing_head):
    """--head HEAD.toml gives the session; --blind-zone auto, --classes and the rest act on the
    stream exactly as on the file (the head's header carries what the recording's does)."""
    head_path, recording = ringing_head
    options = ["--blind-zone", "auto", "--classes", "--no-background", "--path-sigma-m", "0.002"]
    stream = Proc("stream", "--listen", "127.0.0.1:0", "--once", "--json", "--head", head_path, *options)
    port = stream.port()
    echoloc("send", recording, "--to", f"127.0.0.1:{port}", "--speed", "0", check=True)
    code, stdout = stream.finish()
    assert code == 0, stream.lines
    located = echoloc("locate", recording, "--json", *options, check=True).stdout
    assert stdout == located
    records = [json.loads(line) for line in stdout.splitlines()]
    assert len(records) == 12
    # The ring-down is not an object: both points, and only they, in every frame.
    for record in records:
        positions = sorted(o["position_m"] for o in record["objects"])
        assert np.allclose(positions, [[-0.2, 0.0, 1.1], [0.1, 0.05, 0.7]], atol=0.005)
        assert {o["kind"] for o in record["objects"]} == {"point"}


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["stream", "--source", "serial:loop://"], "needs --head HEAD.toml"),
        (["stream", "--source", "radio"], "--source must be net, serial:PORT[@BAUD] or soundcard"),
        (["stream", "--source", "net:7447"], "--source net takes no address"),
        (["stream", "--method", "backprojection"], "--method backprojection is for recordings"),
        (["stream", "--blind-zone", "soon"], "--blind-zone must be SECONDS or auto"),
        (["stream", "--classes", "--method", "backprojection"], "backprojection"),
        (["record", "x.h5", "--source", "soundcard", "--head", "x.h5"], "needs --head HEAD.toml"),
    ],
)
def test_bad_source_or_option_is_one_line_and_exit_2(capsys, tmp_path, args, message):
    from echoloc.cli import commands as cli

    args = [str(tmp_path / a) if a == "x.h5" else a for a in args]
    with pytest.raises(SystemExit) as info:
        cli.main(args)
    _, err = capsys.readouterr()
    assert info.value.code == 2
    assert len(err.strip().splitlines()) == 1, err
    assert message in err


def test_a_board_on_a_serial_port_streams_what_locate_finds_in_the_same_samples(tmp_path):
    """`stream --source serial:socket://...` (pyserial's TCP port, a board behind a serial-to-
    network bridge): the frames in the serial framing, the head from its file, and the JSON
    is `locate --json` of a recording of the same samples at the same capture times. When the
    board goes away the stream ends by itself: nothing can come after."""
    import socket

    from echoloc.io.head import load_head
    from echoloc.realtime.serial_source import encode_serial_frame

    head_path = Path(__file__).resolve().parents[2] / "examples" / "heads" / "mcu-4ch.toml"
    head = load_head(head_path)
    scene = head.scene({"reflectors": [{"position_m": [0.1, 0.05, 0.8]}], "seed": 4})
    simulated = simulate(scene, 8)
    counts = [head.counts(frame) for frame in simulated.frames]
    stamps_us = [5_000_000 + 10_000 * k for k in range(8)]
    as_read = replace(
        simulated,
        frames=np.stack([head.samples(c) for c in counts]),
        frame_times_s=np.array(stamps_us) / 1e6,
        truth_positions_m=None,
        truth_kinds=None,
    )
    recording = tmp_path / "as-read.h5"
    write_recording(as_read, recording)
    server = socket.create_server(("127.0.0.1", 0))
    port = server.getsockname()[1]

    def board() -> None:
        connection, _ = server.accept()
        with connection:
            # pyserial's socket:// empties its input as it opens: a board streaming all along
            # loses only what came before; this one waits until the port is surely open.
            time.sleep(2.0)
            for k, frame in enumerate(counts):
                connection.sendall(encode_serial_frame(frame, sequence=k, timestamp_us=stamps_us[k]))
            time.sleep(1.0)

    sender = threading.Thread(target=board, daemon=True)
    sender.start()
    streamed = echoloc(
        "stream", "--source", f"serial:socket://127.0.0.1:{port}", "--head", head_path,
        "--json",
    )  # fmt: skip
    server.close()
    assert streamed.returncode == 0, streamed.stderr
    assert "capturing from serial:socket://127.0.0.1" in streamed.stderr
    assert "received 8, processed 8, lost 0" in streamed.stderr
    assert "the port went away" in streamed.stderr
    located = echoloc("locate", recording, "--json", check=True).stdout
    assert streamed.stdout == located
    assert len(located.splitlines()) == 8


def test_a_head_the_chain_cannot_use_ends_a_capture_at_once_in_one_line(tmp_path):
    """Two receivers cannot locate: the capture source's session is refused, and since no other
    session can come, `stream` says so and exits 2 instead of waiting for frames."""
    head = tmp_path / "two.toml"
    head.write_text(
        "[array]\ntransmitters_m = [[0.0, 0.0, 0.0]]\nreceivers_m = [[0.2, 0.0, 0.0], [-0.2, 0.0, 0.0]]\n"
        "[acquisition]\nsample_rate_hz = 200e3\nn_samples = 1600\nframe_rate_hz = 100\n"
    )
    start = time.monotonic()
    result = echoloc("stream", "--source", "serial:loop://", "--head", head, "--json")
    assert result.returncode == 2
    assert time.monotonic() - start < 30
    lines = result.stderr.strip().splitlines()
    assert lines[-1].startswith("echoloc: error: serial:loop://: the head cannot be used:")
    assert "at least 3 are needed" in lines[-1]


def test_stream_writes_ros_messages_live_that_read_back_as_locate_found_them(tmp_path, recording_path):
    """--mcap: the objects of every frame as ROS 2 PointCloud2 (and Range, /tf_static with
    QoS), written as they come, stamped with the frames' capture times; read back with the
    MCAP libraries they are `locate --json`'s objects."""
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    from ros_messages import cloud_points

    out = tmp_path / "live.mcap"
    stream = Proc("stream", "--listen", "127.0.0.1:0", "--once", "--mcap", out)
    port = stream.port()
    echoloc("send", recording_path, "--to", f"127.0.0.1:{port}", "--speed", "0", check=True)
    code, _ = stream.finish()
    assert code == 0, stream.lines
    assert any(f"ROS 2 messages to {out}" in line for line in stream.lines)
    located = [
        json.loads(line)
        for line in echoloc("locate", recording_path, "--json", check=True).stdout.splitlines()
    ]
    clouds, statics = [], []
    with out.open("rb") as handle:
        reader = make_reader(handle, decoder_factories=[DecoderFactory()])
        qos = {c.topic: c.metadata["offered_qos_profiles"] for c in reader.get_summary().channels.values()}
        for _, channel, _, message in reader.iter_decoded_messages():
            if channel.topic == "/echoloc/objects":
                clouds.append(message)
            elif channel.topic == "/tf_static":
                statics.append(message)
    assert "durability: 1" in qos["/tf_static"]  # transient local: latched on replay
    assert len(statics) == 1
    assert len(clouds) == len(located) == 15
    for cloud, record in zip(clouds, located, strict=True):
        stamp = cloud.header.stamp.sec + cloud.header.stamp.nanosec * 1e-9
        assert stamp == pytest.approx(record["time_s"], abs=1e-9)
        points = cloud_points(cloud)
        got = sorted(np.column_stack([points["x"], points["y"], points["z"]]).tolist())
        want = sorted(o["position_m"] for o in record["objects"])
        np.testing.assert_allclose(got, want, atol=1e-6)  # float32 in the cloud


def test_an_mcap_target_is_checked_before_anything_arrives(capsys, tmp_path):
    from echoloc.cli import commands as cli

    existing = tmp_path / "old.mcap"
    existing.write_bytes(b"")
    for target, message in ((tmp_path / "x.bag", "writes an .mcap file"), (existing, "already exists")):
        with pytest.raises(SystemExit) as info:
            cli.main(["stream", "--mcap", str(target)])
        assert info.value.code == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1
        assert message in err
