"""echoloc.benchmark: the scipy chain it compares with is a fair one, and the figures add up."""

from __future__ import annotations

import numpy as np
import pytest

from echoloc.benchmark import baseline_echoes, baseline_locate, bench_chains, bench_scene, format_bench
from echoloc.errors import EchoLocError
from echoloc.localise.locate import model_paths_m
from echoloc.pipeline import prepare
from echoloc.sim.scene import default_scene
from echoloc.sim.simulation import simulate


@pytest.fixture(scope="module")
def recording():
    return simulate(default_scene(), 6)


def test_scipy_chain_finds_the_true_paths_and_positions(recording):
    chain = prepare(recording)
    truth = recording.truth_positions_m[0]
    expected = model_paths_m(recording.transmitters_m[0], recording.receivers_m, truth)  # (3 balls, 4 rx)
    paths = baseline_echoes(chain, recording.frames[0])
    assert len(paths) == 4
    far = np.argmax(np.linalg.norm(truth, axis=1))  # the ball at 665 mm, clear of the other two
    for receiver, found in enumerate(paths):
        assert np.min(np.abs(found - expected[far, receiver])) < 2e-3
    # What the straightforward chain gets wrong, and echoloc does not: the two balls 16 mm
    # apart merge on some receivers, and code sidelobes pass the 5-sigma height as echoes.
    assert any(len(found) > 3 for found in paths)
    objects = baseline_locate(chain, 0, paths).objects
    assert np.min([np.linalg.norm(o.position_m - truth[far]) for o in objects]) < 5e-3


def test_bench_figures_are_consistent(recording):
    report = bench_chains(recording, baseline_frames=1, warmup_frames=1, rounds=3, backlog_frames=4)
    ours, backlog, theirs = report["echoloc"], report["echoloc_backlog"], report["scipy"]
    assert ours["frames"] == backlog["frames"] == 6
    assert ours["rounds"] == backlog["rounds"] == 3
    assert backlog["batch_frames"] == 4
    assert theirs["frames"] == 1
    assert ours["recall"] == backlog["recall"] == 1.0
    for figures in (ours, backlog, theirs):
        assert 0 < figures["latency_p50_ms"] <= figures["latency_p99_ms"]
        assert figures["frames_per_s"] == pytest.approx(1e3 / figures["ms_per_frame"])
    for figures in (ours, backlog):  # the median pass lies within the passes' range
        low, high = figures["ms_per_frame_range"]
        assert low <= figures["ms_per_frame"] <= high
    assert ours["peak_mib"] > 0
    assert theirs["peak_mib"] > 0
    assert report["backlog_times_physics"] == pytest.approx(
        backlog["frames_per_s"] / report["physics_frames_per_s"]
    )
    assert report["speedup"] == pytest.approx(theirs["ms_per_frame"] / ours["ms_per_frame"])
    # Sound: 2 m of range is 4 m of path, 11.7 ms at 343 m/s: 85.8 frames/s.
    assert report["physics_frames_per_s"] == pytest.approx(report["speed_of_sound_m_s"] / 4.0)
    assert report["physics_frames_per_s"] == pytest.approx(85.8, abs=0.1)
    assert report["recording_frames_per_s"] == pytest.approx(100.0)
    assert report["times_physics"] == pytest.approx(ours["frames_per_s"] / report["physics_frames_per_s"])
    text = format_bench(report)
    assert "x the scipy chain" in text
    assert "| echoloc (stream, a frame a call) | 6 |" in text
    assert "| echoloc (stream, a backlog 4 frames a call) | 6 |" in text
    assert "median of 3 passes" in text
    assert report["workers"] == 1
    if report["cpus"] is not None:
        assert len(report["cpus"]) == 1
        assert f"one core (CPU {report['cpus'][0]})" in text


@pytest.mark.parametrize(
    ("rounds", "backlog_frames", "message"), [(0, 16, "rounds"), (1, 1, "backlog_frames")]
)
def test_bench_refuses_no_rounds_and_a_backlog_of_one(recording, rounds, backlog_frames, message):
    """A backlog of one frame a call would be the other row measured twice."""
    with pytest.raises(EchoLocError, match=f"{message} must be >= "):
        bench_chains(
            recording, baseline_frames=1, warmup_frames=1, rounds=rounds, backlog_frames=backlog_frames
        )


def test_bench_on_two_cores_pins_two_and_finds_the_same_objects(recording):
    report = bench_chains(recording, baseline_frames=1, warmup_frames=1, workers=2)
    assert report["workers"] == 2
    assert report["echoloc"]["recall"] == 1.0
    if report["cpus"] is not None:
        assert 1 <= len(report["cpus"]) <= 2
        assert report["cpus"] == sorted(report["cpus"])
        assert "echoes on 2 threads" in format_bench(report)


def test_bench_scene_has_the_asked_number_of_objects():
    recording = simulate(bench_scene(5), 2)
    assert np.isfinite(recording.truth_positions_m[:, :, 0]).sum(axis=1).tolist() == [5, 5]
    assert (
        np.isfinite(simulate(bench_scene(0), 1).truth_positions_m[0, :, 0]).sum() == 3
    )  # the report's balls
