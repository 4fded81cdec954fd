"""A frame's echoes and objects in one compiled call (echoloc._chain_kernels) give what the two
stages give one after the other, to the bit."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import numpy as np
import pytest

from echoloc.benchmark import bench_scene
from echoloc.io.output import echoes_record, objects_record
from echoloc.pipeline import Chain, prepare, run, samples_results_batch
from echoloc.sim.simulation import simulate
from echoloc.tof.echoes import _correlated_channels


def _staged(chain: Chain) -> Chain:
    """``chain`` without the one-call path: its stages one after the other."""
    staged = prepare(chain.recording)
    staged.__dict__["one_call"] = None
    return staged


def _records(pairs):
    return [(echoes_record(e), objects_record(o)) for e, o in pairs]


@pytest.fixture(scope="module")
def crowded():
    """Frames of 5 random reflectors (some channels left to CLEAN) and of 10 (more objects in
    a frame than the kernel's first room for them)."""
    return [simulate(bench_scene(5), 64), simulate(bench_scene(10), 4)]


@pytest.mark.parametrize("batch_frames", [1, 16])
def test_one_call_gives_the_stages_answers_to_the_bit(crowded, batch_frames):
    for recording in crowded:
        chain = prepare(recording)
        assert chain.one_call is not None
        staged = _staged(chain)
        got = _records(run(chain, batch_frames=batch_frames))
        assert got == _records(run(staged, batch_frames=batch_frames))
        for (_, one_call), (_, stages) in zip(
            run(chain, batch_frames=batch_frames), run(staged, batch_frames=batch_frames), strict=True
        ):
            for a, b in zip(one_call.objects, stages.objects, strict=True):
                np.testing.assert_array_equal(a.position_m, b.position_m)
                np.testing.assert_array_equal(a.covariance_m2, b.covariance_m2)
    # Not vacuous: CLEAN had channels of the five-reflector frames, and a ten-reflector frame
    # had more objects than the kernel's first room (8 a frame).
    five, ten = crowded
    estimator = prepare(five).one_call
    assert estimator is not None
    mf, options = estimator[0].mf, estimator[0].options
    assert any(c is None for c in _correlated_channels(np.asarray(five.frames), mf, options))
    assert max(len(o.objects) for _, o in run(prepare(ten), batch_frames=1)) > 8


def test_one_call_frames_left_to_clean_come_out_in_order_with_the_stages_answers(crowded):
    """A batch with frames the kernel leaves to CLEAN (LEFT_TO_CLEAN: CLEAN and the association
    run after it) keeps the frame order and gives the stages' answers, frame by frame."""
    from echoloc import _chain_kernels
    from echoloc.tof.echoes import echo_kernel_arguments

    recording = crowded[0]
    chain = prepare(recording)
    assert chain.one_call is not None
    estimator, _, locate_arguments = chain.one_call
    frames = np.asarray(recording.frames, dtype=float)
    arguments = echo_kernel_arguments(frames, estimator.mf, estimator.options)
    status = _chain_kernels.echoes_and_objects(arguments, recording.n_receivers, locate_arguments)[0]
    assert (status == _chain_kernels.LEFT_TO_CLEAN).sum() >= 2  # not vacuous
    indices = list(range(recording.n_frames))
    found = samples_results_batch(
        chain, list(recording.frames), indices, [0.0] * len(indices), [0] * len(indices)
    )
    assert [e.frame for e, _ in found] == [o.frame for _, o in found] == indices
    staged = _staged(chain)
    one_at_a_time = [
        samples_results_batch(staged, [recording.frames[i]], [i], [0.0], [0])[0] for i in indices
    ]
    assert _records(found) == _records(one_at_a_time)


@pytest.mark.parametrize("status", [1, 2])
def test_the_kernel_s_overflow_and_tie_statuses_finish_as_the_stages_do(crowded, monkeypatch, status):
    """Status 1 (more seed rows than the association takes): the frame is skipped with one
    warning, no objects. Status 2 (tied weights): the frame goes to the locator, which chooses
    as the stages do (with the reference on a real tie). Both are rare on real frames, so the
    kernel's status is forced."""
    from echoloc import _chain_kernels
    from echoloc.localise.locate import LocateWarning

    recording = crowded[0]
    chain = prepare(recording)
    kernel = _chain_kernels.echoes_and_objects

    def forced(*arguments):
        found = kernel(*arguments)
        found[0][:] = status
        return found

    monkeypatch.setattr(_chain_kernels, "echoes_and_objects", forced)
    if status == 1:
        with pytest.warns(LocateWarning, match="frame skipped"):
            found = samples_results_batch(chain, [recording.frames[1]], [1], [0.0], [0])
        assert found[0][1].objects == ()
        return
    found = samples_results_batch(chain, [recording.frames[1]], [1], [0.0], [0])
    staged = samples_results_batch(_staged(chain), [recording.frames[1]], [1], [0.0], [0])
    assert len(found[0][1].objects) >= 3
    assert _records(found) == _records(staged)


def test_the_one_call_kernel_loads_from_the_cache_in_a_fresh_process(crowded):
    """Its cached code holds a parallel kernel's: loaded before numba's threading layer was
    launched, it crashed the process (echoloc._chain_kernels launches the layer on import)."""
    list(run(prepare(crowded[0]), frames=[0]))  # compiled here, so the child loads it cached
    from pathlib import Path

    from echoloc import _chain_kernels

    cache = Path(_chain_kernels.__file__).parent / "__pycache__"
    assert list(cache.glob("_chain_kernels.echoes_and_objects-*.nbi")), "numba did not cache the kernel"
    child = textwrap.dedent(
        """
        from echoloc import _chain_kernels
        from echoloc.benchmark import bench_scene
        from echoloc.pipeline import prepare, samples_results_batch
        from echoloc.sim.simulation import simulate

        recording = simulate(bench_scene(5), 1)
        found = samples_results_batch(prepare(recording), [recording.frames[0]], [0], [0.0], [0])
        print(len(found[0][1].objects))
        """
    )
    done = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-2000:]
    assert int(done.stdout.split()[-1]) >= 3


def test_frames_of_another_channel_count_are_refused_in_one_line(crowded):
    """The kernel reads as many channels as the chain has receivers: a frame of fewer is an
    EchoLocError naming both counts, before the kernel runs."""
    from echoloc.errors import EchoLocError

    recording = crowded[0]
    chain = prepare(recording)
    assert chain.one_call is not None
    with pytest.raises(EchoLocError, match="frames of 3 channels for a chain of 4 receivers"):
        samples_results_batch(chain, [recording.frames[0][:3]], [0], [0.0], [0])
