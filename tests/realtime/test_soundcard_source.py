"""The sound-card source against a fake PortAudio (tests/realtime/fake_portaudio.py): the emission
instant, the frames cut and what is located from them, overflows, and what a user without
sounddevice or PortAudio is told. Nothing here has met real hardware."""

from __future__ import annotations

import dataclasses
import importlib.abc
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fake_portaudio import BASE_TIME_S, FakeCard

from echoloc._toml import tomllib
from echoloc.errors import EchoLocError
from echoloc.io.head import SensorHead, head_from_dict, load_head
from echoloc.pipeline import prepare, run
from echoloc.realtime.soundcard_source import START_DELAY_S, SoundCardSource
from echoloc.realtime.stream import FrameQueue, StreamFrame, StreamProcessor, StreamStats
from echoloc.sim.simulation import simulate
from repo_paths import REPO

HEAD_FILE = REPO / "examples" / "heads" / "bench-4mic.toml"
FS = 192_000.0
PERIOD = 3840  # 192 kHz / 50 Hz
LATENCY = 1200  # samples, DAC to ADC: 6.25 ms
N_FRAMES = 10
TRUTH = ([0.1, 0.05, 0.8], [-0.2, 0.0, 1.3])


def _head(loopback: bool = True, **adc: Any) -> SensorHead:
    data = tomllib.loads(HEAD_FILE.read_text())
    if not loopback:
        del data["channels"]["loopback"]
    if adc:
        data["adc"] = adc
    return head_from_dict(data, source=str(HEAD_FILE))


@pytest.fixture(scope="module")
def head() -> SensorHead:
    return load_head(HEAD_FILE)


@pytest.fixture(scope="module")
def simulated(head: SensorHead) -> Any:
    """The bench head before two points (echoes about 0.35 of full scale), 40 dB SNR."""
    reflectors = [{"position_m": p, "strength": 0.2} for p in TRUTH]
    scene = head.scene({"reflectors": reflectors, "noise": {"snr_db": 40.0}, "seed": 7})
    return simulate(scene, N_FRAMES + 4)


def _capture(source: SoundCardSource, n_frames: int, timeout_s: float = 20.0) -> list[StreamFrame]:
    """The first ``n_frames`` frames the source delivers (then it is stopped)."""
    frames: list[StreamFrame] = []
    began = time.monotonic()
    source.start()
    try:
        while len(frames) < n_frames and time.monotonic() - began < timeout_s:
            item = source.queue.get(0.05)
            if isinstance(item, StreamFrame):
                frames.append(item)
    finally:
        source.stop()
    assert len(frames) == n_frames, (list(source.errors()), source.counters())
    return frames


def _quantised(head: SensorHead, samples: Any) -> Any:
    """What the head's ADC makes of simulated receiver samples, as a frame carries them (one frame,
    or frames)."""
    if np.ndim(samples) == 3:
        return np.stack([head.samples(head.counts(frame)) for frame in samples])
    return head.samples(head.counts(samples))


def _located(head: SensorHead, frames: list[StreamFrame]) -> tuple[list[Any], list[Any], list[Any]]:
    """Objects from the frames as `echoloc stream` locates them (a chain on the head's session),
    objects and echoes of `echoloc.pipeline.run` on a recording of the same samples."""
    processor = StreamProcessor(prepare(head.header))
    streamed = [r.objects for r in processor.process_batch(frames)]
    recording = dataclasses.replace(
        head.header,
        frames=np.stack([f.samples for f in frames]),
        frame_times_s=np.array([f.time_s for f in frames]),
    )
    pairs = list(run(prepare(recording)))
    return streamed, [o for _, o in pairs], [e for e, _ in pairs]


def _first(recording: Any, frames: Any) -> Any:
    """``recording`` with ``frames`` instead of its own (its first ``len(frames)``)."""
    n = len(frames)
    return dataclasses.replace(
        recording,
        frames=frames,
        frame_times_s=recording.frame_times_s[:n],
        frame_transmitter=recording.frame_transmitter[:n],
        truth_positions_m=recording.truth_positions_m[:n],
    )


def _positions(objects: Any) -> Any:
    return np.array(sorted(tuple(o.position_m) for o in objects.objects))


def _tofs(echoes: Any) -> list[Any]:
    return [channel.tof_s for channel in echoes.channels]


# --------------------------------------------------------------------- with a loopback


def test_the_loopback_finds_the_emission_and_the_frames_are_the_simulated_ones(
    head: SensorHead, simulated: Any
) -> None:
    """The pulse is found on the loopback input at the card's latency (to far better than 0.05
    sample); the frames cut are the simulated frames sample for sample; what `stream` locates in
    them is what `echoloc.pipeline` locates in the same samples, within a few mm of the points."""
    card = FakeCard(head, simulated.frames, latency_samples=LATENCY)
    source = SoundCardSource(head, FrameQueue(100), backend=card, amplitude=1.0)
    frames = _capture(source, N_FRAMES)
    stream = card.streams[0]

    # The output: the pulse every period exactly, on the tweeter's output alone.
    first = round(START_DELAY_S * FS)
    assert stream.onsets[:N_FRAMES] == [first + k * PERIOD for k in range(N_FRAMES)]
    assert stream.other_outputs_peak == 0.0

    # The emission instant, frame by frame: the latency, to a tiny fraction of a sample.
    emissions = list(source.emissions)[:N_FRAMES]
    assert [e.frame for e in emissions] == list(range(N_FRAMES))
    assert max(abs(e.latency_samples - LATENCY) for e in emissions) < 0.05
    report = source.emission()
    assert report.method == "loopback"
    assert abs(report.latency_samples - LATENCY) < 1e-3
    assert report.jitter_samples < 1e-3
    assert report.correlation > 0.99
    assert report.loopback_gain == pytest.approx(0.5, rel=1e-3)  # the fake's divider
    assert abs(report.reported_error_samples) < 1e-3  # this fake's driver tells the truth

    # The frames: numbered by emission, stamped with the DAC time of their pulse, and exactly
    # the simulator's samples after the head's ADC.
    assert [f.index for f in frames] == list(range(N_FRAMES))
    for k, frame in enumerate(frames):
        assert frame.time_s == pytest.approx(BASE_TIME_S + (first + k * PERIOD + stream.l_out) / FS, abs=1e-9)
        np.testing.assert_array_equal(frame.samples, _quantised(head, simulated.frames[k]))
    assert source.counters()["lost"] == 0
    assert sum(source.xruns.values()) == 0

    streamed, batch, _ = _located(head, frames)
    for mine, theirs in zip(streamed, batch, strict=True):
        np.testing.assert_array_equal(_positions(mine), _positions(theirs))
    for objects in streamed:
        found = _positions(objects)
        assert found.shape == (2, 3)
        assert np.max(np.linalg.norm(found - np.array(sorted(map(tuple, TRUTH))), axis=1)) < 3e-3


@pytest.mark.parametrize(
    ("fraction", "gain", "noise", "within"),
    [
        (0.37, 0.5, 0.0, 1e-3),  # quantisation is all the loopback's noise
        (0.5, 0.5, 0.0, 1e-3),  # halfway: the carrier's lobes either side are as high
        (0.81, -0.1, 1e-3, 0.02),  # an inverting amplifier, the loopback 40 dB above its noise
    ],
)
def test_a_latency_between_samples_is_found_and_the_frames_moved_by_it(
    head: SensorHead, simulated: Any, fraction: float, gain: float, noise: float, within: float
) -> None:
    """A card whose delay is 1200 samples and a ``fraction``: the loopback finds it (to ``within``
    samples, each frame), whatever the loopback's polarity; and the frames, moved by the
    fraction, give the echoes of the simulated frames (cut at a whole sample they would be up to
    half a sample, 0.9 mm of path, off)."""
    card = FakeCard(
        head,
        simulated.frames,
        latency_samples=LATENCY,
        fraction=fraction,
        loopback_gain=gain,
        loopback_noise=noise,
    )
    source = SoundCardSource(head, FrameQueue(100), backend=card)  # the default amplitude, 0.7
    frames = _capture(source, N_FRAMES)
    latencies = [e.latency_samples for e in list(source.emissions)[:N_FRAMES]]
    assert max(abs(v - (LATENCY + fraction)) for v in latencies) < within
    report = source.emission()
    assert report.jitter_samples < within
    assert report.loopback_gain == pytest.approx(gain * 0.7, rel=0.01)  # the divider, the amplitude
    assert report.correlation > (0.99 if noise == 0 else 0.9)

    _, _, echoes = _located(head, frames)
    expected = [e for e, _ in run(prepare(_first(simulated, 0.7 * simulated.frames[:N_FRAMES])))]
    worst = 0.0
    for mine, theirs in zip(echoes, expected, strict=True):
        for a, b in zip(_tofs(mine), _tofs(theirs), strict=True):
            assert len(a) == len(b) == 2
            worst = max(worst, float(np.max(np.abs(a - b))) * FS)
    assert worst < 0.05  # samples
    streamed, _, _ = _located(head, frames)
    for objects in streamed:
        found = _positions(objects)
        assert np.max(np.linalg.norm(found - np.array(sorted(map(tuple, TRUTH))), axis=1)) < 3e-3


# --------------------------------------------------------------------- without a loopback


@pytest.mark.parametrize(("error", "callback_times"), [(0, True), (6, True), (-5, True), (4, False)])
def test_without_a_loopback_the_driver_latency_is_used_and_its_error_is_a_range_bias(
    simulated: Any, error: int, callback_times: bool
) -> None:
    """No loopback: the emission is where the driver's latency puts it (the callbacks' times, or
    ``stream.latency`` when they are 0). A driver ``error`` samples too long cuts every frame that
    much late: every echo comes ``error / fs`` early, every path ``c error / fs`` short, each
    point's range about half that."""
    head = _head(loopback=False)
    card = FakeCard(
        head,
        simulated.frames,
        latency_samples=LATENCY,
        reported_error_samples=error,
        callback_times=callback_times,
    )
    source = SoundCardSource(head, FrameQueue(100), backend=card, amplitude=1.0)
    frames = _capture(source, N_FRAMES)
    said = list(source.errors())
    assert len(said) == 1
    assert "no channels.loopback" in said[0]
    assert source.emission().method == "latency"
    assert all(abs(e.latency_samples - (LATENCY + error)) < 1e-6 for e in list(source.emissions)[:N_FRAMES])

    # The frames are the simulated ones, shifted by the error (the card's silence around them).
    for k, frame in enumerate(frames):
        truth = _quantised(head, simulated.frames[k])
        if error >= 0:
            np.testing.assert_array_equal(frame.samples[:, : truth.shape[1] - error], truth[:, error:])
        else:
            np.testing.assert_array_equal(frame.samples[:, -error:], truth[:, :error])
        # The stamp is the pulse's DAC time whatever the error (it cancels out).
        first = round(START_DELAY_S * FS) + k * PERIOD
        assert frame.time_s == pytest.approx(BASE_TIME_S + (first + card.streams[0].l_out) / FS, abs=1e-9)

    _, _, echoes = _located(head, frames)
    reference = list(run(prepare(_first(simulated, _quantised(head, simulated.frames[:N_FRAMES])))))
    c = prepare(head.header).speed_of_sound_m_s
    for mine, (theirs, _objects) in zip(echoes, reference, strict=True):
        for a, b in zip(_tofs(mine), _tofs(theirs), strict=True):
            np.testing.assert_allclose(a - b, -error / FS, atol=0.01 / FS)
    streamed, _, _ = _located(head, frames)
    for mine, (_, theirs) in zip(streamed, reference, strict=True):
        shift = np.linalg.norm(_positions(mine), axis=1) - np.linalg.norm(_positions(theirs), axis=1)
        # Half the path's shift, to within the geometry's few per cent (bistatic, off axis).
        np.testing.assert_allclose(shift, -c * error / FS / 2, rtol=0.05, atol=2e-5)


# --------------------------------------------------------------------- xruns


@pytest.mark.parametrize(
    ("kind", "loopback"),
    [
        ("input_overflow", True),
        ("input_overflow", False),
        ("output_underflow", True),
        ("output_underflow", False),
        ("silent_slip", True),
    ],
)
def test_a_break_drops_the_frames_in_flight_and_the_stream_goes_on(
    simulated: Any, kind: str, loopback: bool
) -> None:
    """300 samples slip at callback 100 (input index 25600, inside emission 4's frame): input lost
    (an overflow: later pulses are heard 300 samples sooner), or a gap in the output (an
    underflow: 300 later). The flag is counted and said, emission 4 is dropped and counted lost
    (its samples straddle the break), and every later frame is again exactly the simulated one,
    its emission found where it now is: by the loopback, or by the driver's callback times. A
    slip no flag tells of (and the driver does not know) costs no frame with a loopback: the
    pulse leaves the tracking window and is found again half a period around it."""
    head = _head(loopback=loopback)
    slip, at_block = 300, 100
    options = (
        {"overflow_at_block": at_block, "overflow_samples": slip}
        if kind == "input_overflow"
        else {"output_gap_at_block": at_block, "output_gap_samples": slip}
    )
    if kind == "silent_slip":
        options["output_gap_flagged"] = False
    card = FakeCard(head, simulated.frames, latency_samples=LATENCY, **options)
    source = SoundCardSource(head, FrameQueue(100), backend=card, amplitude=1.0)
    dropped = [] if kind == "silent_slip" else [4]
    frames = _capture(source, N_FRAMES - len(dropped))
    first = round(START_DELAY_S * FS)
    gap = at_block * card.block
    # Emission 4 is written before the break and heard after it; 3 is complete before it.
    assert first + 4 * PERIOD < gap < first + 4 * PERIOD + LATENCY
    assert first + 3 * PERIOD + LATENCY + 2304 < gap

    assert [f.index for f in frames] == [k for k in range(N_FRAMES) if k not in dropped]
    assert source.counters()["lost"] == len(dropped)
    # The stream's summary says the break, beside the frame it cost.
    summary = StreamStats(**source.counters()).summary()
    assert ("xruns" in summary) == (kind != "silent_slip")
    said = list(source.errors())
    if kind == "silent_slip":
        assert sum(source.xruns.values()) == 0
    else:
        assert source.xruns == {name: int(name == kind) for name in source.xruns}
        assert any(kind.replace("_", " ") in line and "in flight are dropped" in line for line in said)
    for frame in frames:
        np.testing.assert_array_equal(frame.samples, _quantised(head, simulated.frames[frame.index]))
    after = LATENCY - slip if kind == "input_overflow" else LATENCY + slip
    latency = {e.frame: e.latency_samples for e in source.emissions}
    assert all(abs(latency[k] - LATENCY) < 0.05 for k in range(4))
    assert all(abs(latency[k] - after) < 0.05 for k in range(5, N_FRAMES))


# --------------------------------------------------------------------- what a user is told


class _NoPortAudio(importlib.abc.MetaPathFinder):
    """``import sounddevice`` as on a machine without libportaudio2: sounddevice's own OSError."""

    def find_spec(self, name: str, path: Any, target: Any = None) -> Any:
        if name == "sounddevice":
            raise OSError("PortAudio library not found")
        return None


def test_without_sounddevice_or_portaudio_one_clear_error(
    head: SensorHead, monkeypatch: pytest.MonkeyPatch
) -> None:
    def one_line_saying(*needles: str) -> None:
        with pytest.raises(EchoLocError) as error:
            SoundCardSource(head, FrameQueue(10))
        message = str(error.value)
        assert all(needle in message for needle in needles), message
        assert error.value.__suppress_context__
        assert "\n" not in message

    monkeypatch.setitem(sys.modules, "sounddevice", None)  # not installed
    one_line_saying("pip install 'echoloc[soundcard]'", "libportaudio2")
    monkeypatch.delitem(sys.modules, "sounddevice")
    monkeypatch.setattr(sys, "meta_path", [_NoPortAudio(), *sys.meta_path])
    one_line_saying("PortAudio library", "libportaudio2")


def test_the_command_says_it_in_one_line_without_a_traceback(tmp_path: Path) -> None:
    """`echoloc stream --source soundcard` on a machine without PortAudio: exit 2, one line."""
    script = (
        "import sys, importlib.abc\n"
        "class NoPortAudio(importlib.abc.MetaPathFinder):\n"
        "    def find_spec(self, name, path, target=None):\n"
        "        if name == 'sounddevice':\n"
        "            raise OSError('PortAudio library not found')\n"
        "sys.meta_path.insert(0, NoPortAudio())\n"
        "from echoloc.cli.entry import main\n"
        "head = sys.argv[1]\n"
        "sys.argv = ['echoloc', 'stream', '--source', 'soundcard', '--head', head, '--max-frames', '1']\n"
        "main()\n"
    )
    completed = subprocess.run(
        [sys.executable, "-c", script, str(HEAD_FILE)],
        capture_output=True,
        text=True,
        cwd=tmp_path,
        timeout=120,
        check=False,
    )
    assert completed.returncode == 2, completed.stderr
    lines = completed.stderr.strip().splitlines()
    assert len(lines) == 1
    assert "Traceback" not in completed.stderr
    assert "PortAudio library" in lines[0]
    assert "libportaudio2" in lines[0]


@pytest.mark.parametrize(
    ("options", "device", "said"),
    [
        ({}, "Scarlett", "no input device matching 'scarlett'"),
        ({"max_inputs": 2}, None, "has 2 input channels, the head needs 5"),
        ({"rates": (44100.0, 48000.0)}, None, "invalid sample rate"),
        (
            {"open_error": "Device unavailable [PaErrorCode -9985]"},
            "Fake",
            "cannot open it: device unavailable",
        ),
    ],
)
def test_a_device_that_cannot_be_opened_is_one_line_naming_it(
    head: SensorHead, options: dict[str, Any], device: Any, said: str
) -> None:
    card = FakeCard(head, **options)
    with pytest.raises(EchoLocError) as error:
        SoundCardSource(head, FrameQueue(10), backend=card, device=device).start().stop()
    message = str(error.value)
    assert said in message.lower()
    assert message.startswith(f"sound card {'the default device' if device is None else repr(device)}: ")
    assert message.endswith("list the devices with: python -m sounddevice")
    assert "\n" not in message


def test_a_head_the_card_cannot_drive_is_refused(head: SensorHead) -> None:
    data = tomllib.loads(HEAD_FILE.read_text())
    del data["channels"]["output"]
    with pytest.raises(EchoLocError, match=r"needs channels\.output"):
        SoundCardSource(head_from_dict(data, str(HEAD_FILE)), FrameQueue(10), backend=FakeCard(head))
    with pytest.raises(EchoLocError, match="amplitude"):
        SoundCardSource(head, FrameQueue(10), backend=FakeCard(head), amplitude=1.5)


def test_a_float32_head_keeps_the_card_samples(simulated: Any) -> None:
    """``[adc] format = "float32"``, ``full_scale = 1.0``: a frame carries the card's floats as they are."""
    head = _head(format="float32", full_scale=1.0)
    card = FakeCard(head, simulated.frames, latency_samples=LATENCY)
    frames = _capture(SoundCardSource(head, FrameQueue(100), backend=card, amplitude=1.0), 3)
    for k, frame in enumerate(frames):
        np.testing.assert_array_equal(frame.samples, simulated.frames[k].astype(np.float32))
