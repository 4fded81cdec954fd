"""The compiled stages of association give what their numpy references give."""

from __future__ import annotations

import sys

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from echoloc.localise import locate
from echoloc.localise.locate import (
    FrameLocator,
    LocatedObject,
    LocateOptions,
    combine_frames,
    locate_frame,
    model_paths_m,
)
from echoloc.tof.echoes import ChannelEchoes, FrameEchoes

CROSS = np.array([[0.25, 0, 0], [-0.25, 0, 0], [0, 0.25, 0], [0, -0.25, 0]], dtype=float)
TRANSMITTERS = np.array([[0.0, 0.0, 0.0], [0.1, 0.1, 0.0]])
OPTIONS = [
    LocateOptions(resolution_m=0.0275, carrier_hz=40e3),
    LocateOptions(),
    LocateOptions(resolution_m=0.0275, field_of_view_deg=35.0),
]


def _frame(rng: np.random.Generator, index: int, transmitter: np.ndarray, points: np.ndarray) -> FrameEchoes:
    """Noisy echoes of ``points``: some lost, some merged, some spurious; c = 1 (tof = path)."""
    paths = model_paths_m(transmitter, CROSS, points) + rng.normal(0, 0.5e-3, (len(points), len(CROSS)))
    strength = rng.uniform(0.5, 2.0, len(points))
    channels = []
    for i, receiver in enumerate(CROSS):
        spread = np.linalg.norm(points - transmitter, axis=1) * np.linalg.norm(points - receiver, axis=1)
        path, amplitude = paths[:, i], strength / spread * rng.lognormal(0, 0.1, len(points))
        keep = rng.random(len(points)) > 0.05
        path, amplitude = path[keep], amplitude[keep]
        extra = rng.integers(0, 3)
        path = np.r_[path, rng.uniform(0.4, 2.5, extra)]
        amplitude = np.r_[amplitude, rng.uniform(0.1, 2.0, extra)]
        order = np.argsort(path)
        path, amplitude = path[order], amplitude[order]
        merged = np.diff(path, prepend=-np.inf) > 0.01  # echoes closer than 1 cm come out as one
        channels.append(
            ChannelEchoes(
                tof_s=path[merged], amplitude=amplitude[merged], snr_db=rng.uniform(10, 30, merged.sum())
            )
        )
    return FrameEchoes(index, 0.0, 1.0, tuple(channels))


def _scene(seed: int) -> tuple[np.random.Generator, np.ndarray]:
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 7))
    points = np.column_stack([rng.uniform(-0.5, 0.5, n), rng.uniform(-0.5, 0.5, n), rng.uniform(0.2, 1.2, n)])
    return rng, points


def _assert_same(expected: tuple[LocatedObject, ...], got: tuple[LocatedObject, ...]) -> None:
    assert len(got) == len(expected)
    for a, b in zip(expected, got, strict=True):
        assert (a.receivers, a.echo_indices, a.transmitters, a.shared) == (
            b.receivers,
            b.echo_indices,
            b.transmitters,
            b.shared,
        )
        assert b.position_m == pytest.approx(a.position_m, rel=1e-9, abs=1e-12)
        assert b.covariance_m2 == pytest.approx(a.covariance_m2, rel=1e-9, abs=1e-18)
        assert b.chi2 == pytest.approx(a.chi2, rel=1e-7, abs=1e-12)
        assert b.score == pytest.approx(a.score, rel=1e-7, abs=1e-12)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), which=st.sampled_from(range(len(OPTIONS))))
def test_locate_frame_matches_the_numpy_reference(seed: int, which: int) -> None:
    """On random noisy scenes of 1-6 reflectors the compiled association finds the same objects."""
    rng, points = _scene(seed)
    frame = _frame(rng, 0, TRANSMITTERS[0], points)
    compiled = locate_frame(frame, TRANSMITTERS[0], CROSS, OPTIONS[which])
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(locate, "_COMPILED", False)
        reference = locate_frame(frame, TRANSMITTERS[0], CROSS, OPTIONS[which])
    _assert_same(reference.objects, compiled.objects)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), moved=st.floats(0.0, 0.01))
def test_combined_frames_match_the_numpy_reference(seed: int, moved: float) -> None:
    """Two transmitters' frames (optional channels, fitted again without them) agree too."""
    rng, points = _scene(seed)
    frames = [
        (0, _frame(rng, 0, TRANSMITTERS[0], points)),
        (1, _frame(rng, 1, TRANSMITTERS[1], points + np.array([0.0, 0.0, moved]))),
    ]
    compiled = combine_frames(frames, TRANSMITTERS, CROSS, OPTIONS[0])
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(locate, "_COMPILED", False)
        reference = combine_frames(frames, TRANSMITTERS, CROSS, OPTIONS[0])
    _assert_same(reference.objects, compiled.objects)


candidate_sets = st.lists(
    st.tuples(
        st.lists(st.integers(-1, 3), min_size=4, max_size=4),
        st.floats(0.5, 1.0, allow_nan=False),
    ),
    min_size=1,
    max_size=24,
    unique_by=lambda item: item[1],
)


@settings(max_examples=300, deadline=None)
@given(items=candidate_sets, node_limit=st.sampled_from([1, 5, 40, 50_000]))
def test_the_compiled_set_packing_matches_the_reference(items: list, node_limit: int) -> None:
    """Weighted set packing: the same candidates, in the same order, as locate._best_disjoint,
    also when the node limit cuts the search short."""
    from echoloc.localise import _locate_kernels

    echo = np.array([e for e, _ in items], dtype=np.int64)
    weights = np.array([w for _, w in items])
    reference = [
        locate._Candidate(frozenset((c, int(e)) for c, e in enumerate(row) if e >= 0), float(w), k)
        for k, (row, w) in enumerate(zip(echo, weights, strict=True))
    ]
    expected = locate._best_disjoint(reference, node_limit)
    ids = np.where(echo >= 0, 4 * np.arange(4) + echo, -1)
    out = np.empty(len(items), dtype=np.int64)
    count, done = _locate_kernels.best_disjoint(np.arange(len(items)), ids, weights, 16, node_limit, out)
    assert done
    assert out[:count].tolist() == expected


def test_tied_weights_leave_the_packing_to_the_reference() -> None:
    """Equal weights in one group of conflicting candidates: the reference's order (set
    iteration) decides, so the compiled packing declines."""
    from echoloc.localise import _locate_kernels

    ids = np.array([[0, 4, -1, -1], [0, 5, -1, -1], [1, 6, -1, -1]])
    out = np.empty(3, dtype=np.int64)
    _, done = _locate_kernels.best_disjoint(np.arange(3), ids, np.array([0.9, 0.9, 0.95]), 8, 50_000, out)
    assert not done
    count, done = _locate_kernels.best_disjoint(
        np.arange(3), ids, np.array([0.9, 0.91, 0.95]), 8, 50_000, out
    )
    assert done
    assert out[:count].tolist() == [1, 2]


@settings(max_examples=200, deadline=None)
@given(
    channels=st.lists(
        st.lists(st.sampled_from([0.5, 0.7, 1.1, np.nan]) | st.floats(0.0, 3.0), max_size=8),
        min_size=1,
        max_size=6,
    )
)
def test_the_compiled_sort_within_channels_matches_lexsort(channels: list) -> None:
    """Each channel's paths sorted stably (ties keep their order, NaN last), as np.lexsort does."""
    from echoloc.localise import _locate_kernels

    paths = np.array([p for ch in channels for p in ch], dtype=float)
    offset = np.cumsum([0] + [len(ch) for ch in channels])
    channel = np.repeat(np.arange(len(channels)), np.diff(offset))
    order = np.lexsort((paths, channel))
    sorted_paths, sorted_index = _locate_kernels.sort_within_channels(paths, offset)
    np.testing.assert_array_equal(sorted_paths, paths[order])
    np.testing.assert_array_equal(sorted_index, order - offset[channel[order]])


@settings(max_examples=100, deadline=None)
@given(
    snr_db=st.lists(st.floats(-20.0, 80.0), max_size=12),
    speed=st.floats(300.0, 360.0),
    carrier=st.floats(20e3, 200e3),
    prior=st.floats(0.0, 2e-3),
)
def test_the_compiled_path_sigmas_match_path_sigmas_m(
    snr_db: list[float], speed: float, carrier: float, prior: float
) -> None:
    """locate_frame's compiled path sigmas are path_sigmas_m's to rounding: libm's power (the
    compiled paths') and numpy's differ in the last bit of some linear SNRs, which left the
    sigmas of 30 million random cases at most 4 ulps apart (below 1e-15 relative)."""
    options = LocateOptions(path_sigma_m=prior, carrier_hz=carrier)
    snr = np.array(snr_db, dtype=float)
    np.testing.assert_allclose(
        locate._flat_path_sigmas(snr, speed, options), locate.path_sigmas_m(snr, speed, options), rtol=1e-15
    )


@settings(max_examples=200, deadline=None)
@given(rows=st.lists(st.tuples(st.integers(-1, 2), st.integers(-1, 2), st.integers(0, 2)), max_size=40))
def test_the_compiled_first_of_each_matches_the_reference(rows: list) -> None:
    """The first row of every distinct (echo, use), in order, as locate._first_of_each."""
    from echoloc.localise import _locate_kernels

    echo = np.array([[a, b] for a, b, _ in rows], dtype=np.int64).reshape(-1, 2)
    use = np.array([[u, 2 - u] for _, _, u in rows], dtype=np.int8).reshape(-1, 2)
    padded_echo, padded_use = (
        np.vstack([echo, np.zeros((3, 2), np.int64)]),
        np.vstack([use, np.zeros((3, 2), np.int8)]),
    )
    expected = locate._first_of_each(echo, use)
    assert _locate_kernels.first_of_each(padded_echo, padded_use, len(rows)).tolist() == expected


def test_the_geometry_cache_tells_streams_apart() -> None:
    """The cached per-stream setup follows usable receivers and axes: a dead receiver or a
    narrower beam on a later call is not answered from an earlier call's geometry."""
    rng, points = _scene(7)
    frame = _frame(rng, 0, TRANSMITTERS[0], points)
    all_four = locate_frame(frame, TRANSMITTERS[0], CROSS, OPTIONS[0])
    dead = locate_frame(frame, TRANSMITTERS[0], CROSS, OPTIONS[0], np.array([True, False, True, True]))
    assert all(1 not in o.receivers for o in dead.objects)
    assert any(1 in o.receivers for o in all_four.objects)
    tilted = np.tile([0.0, 0.6, 0.8], (4, 1))
    options = LocateOptions(resolution_m=0.0275, field_of_view_deg=30.0, receiver_axes=tilted)
    again = locate_frame(frame, TRANSMITTERS[0], CROSS, options)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(locate, "_SETUPS", {})
        fresh = locate_frame(frame, TRANSMITTERS[0], CROSS, options)
    _assert_same(fresh.objects, again.objects)


def test_options_that_differ_only_in_their_axes_are_told_apart() -> None:
    """LocateOptions hash without their axes: the compiled path's cached options must still
    hold a solution to receivers' own axes when those are given, and not when not."""
    points = np.array([[0.1, -0.45, 0.4], [0.0, 0.3, 0.8]])  # the first behind the tilted receivers
    frame = _frame(np.random.default_rng(11), 0, TRANSMITTERS[0], points)
    tilted = np.tile([0.0, 0.8, 0.6], (4, 1))
    plain = LocateOptions(resolution_m=0.0275)
    with_axes = LocateOptions(resolution_m=0.0275, receiver_axes=tilted, boresight=[0.0, 0.0, 1.0])  # type: ignore[arg-type]
    for options in (plain, with_axes, plain):
        compiled = locate_frame(frame, TRANSMITTERS[0], CROSS, options)
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(locate, "_COMPILED", False)
            reference = locate_frame(frame, TRANSMITTERS[0], CROSS, options)
        _assert_same(reference.objects, compiled.objects)
    assert len(locate_frame(frame, TRANSMITTERS[0], CROSS, with_axes).objects) < len(
        locate_frame(frame, TRANSMITTERS[0], CROSS, plain).objects
    )


@pytest.mark.parametrize("compiled", [True, False])
def test_too_many_combinations_skip_the_frame_with_a_warning(compiled: bool) -> None:
    """Past the seed-row limit a frame is skipped with a LocateWarning, compiled or not."""
    paths = np.arange(0.5, 0.9, 0.01)
    channels = tuple(
        ChannelEchoes(tof_s=paths, amplitude=np.ones(len(paths)), snr_db=np.full(len(paths), 20.0))
        for _ in CROSS
    )
    frame = FrameEchoes(0, 0.0, 1.0, channels)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(locate, "_MAX_SEED_ROWS", 4096)
        patch.setattr(locate, "_COMPILED", compiled)
        with pytest.warns(locate.LocateWarning, match="frame skipped"):
            assert locate_frame(frame, TRANSMITTERS[0], CROSS, OPTIONS[0]).objects == ()


def _assert_identical(expected: tuple[LocatedObject, ...], got: tuple[LocatedObject, ...]) -> None:
    assert len(got) == len(expected)
    for a, b in zip(expected, got, strict=True):
        assert (a.receivers, a.echo_indices, a.transmitters, a.shared, a.chi2, a.score) == (
            b.receivers,
            b.echo_indices,
            b.transmitters,
            b.shared,
            b.chi2,
            b.score,
        )
        assert np.array_equal(a.position_m, b.position_m)
        assert np.array_equal(a.covariance_m2, b.covariance_m2)


def test_repeated_and_interleaved_geometries_give_the_same_objects() -> None:
    """The cached setup keeps a memo of each object's support: calls with two geometries in
    turn, again and again, give bit for bit what a fresh cache gives for each."""
    rng, points = _scene(3)
    frames = [_frame(rng, i, TRANSMITTERS[0], points) for i in range(3)]
    geometries = [
        (TRANSMITTERS[0], CROSS, OPTIONS[0], None),
        (TRANSMITTERS[0], CROSS, OPTIONS[0], np.array([True, True, False, True])),
        (TRANSMITTERS[1], CROSS, OPTIONS[1], None),
    ]
    expected = {}
    for g, call in enumerate(geometries):
        for f, frame in enumerate(frames):
            with pytest.MonkeyPatch.context() as patch:
                patch.setattr(locate, "_SETUPS", {})
                expected[g, f] = locate_frame(frame, *call).objects
    assert any(expected.values())
    for _ in range(2):
        for f, frame in enumerate(frames):
            for g, call in enumerate(geometries):
                _assert_identical(expected[g, f], locate_frame(frame, *call).objects)


@settings(max_examples=25, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), which=st.sampled_from(range(len(OPTIONS))), dead=st.integers(-1, 3))
def test_a_frame_locator_reused_over_a_stream_gives_locate_frames_objects(
    seed: int, which: int, dead: int
) -> None:
    """A FrameLocator set up once (as a stream's chain holds one a transmitter) gives, frame
    after frame, bit for bit what a fresh set-up gives each frame on its own (no memo shared),
    and the numpy reference's objects, whether its channels all take the flat compiled path
    or a dead receiver sends them to associate; with the compiled path switched off after it
    was set up, it runs the reference itself."""
    rng, points = _scene(seed)
    usable = None if dead < 0 else np.arange(len(CROSS)) != dead
    call = (TRANSMITTERS[0], CROSS, OPTIONS[which], usable)
    frames = [_frame(rng, i, TRANSMITTERS[0], points) for i in range(4)]
    fresh, reference = [], []
    for frame in frames:
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(locate, "_SETUPS", {})
            fresh.append(locate_frame(frame, *call).objects)
            patch.setattr(locate, "_COMPILED", False)
            reference.append(locate_frame(frame, *call).objects)
    locator = FrameLocator(*call)
    for frame, expected, numpy_objects in zip(frames, fresh, reference, strict=True):
        got = locator(frame).objects
        _assert_identical(expected, got)
        _assert_same(numpy_objects, got)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(locate, "_COMPILED", False)
        for frame, numpy_objects in zip(frames, reference, strict=True):
            _assert_identical(numpy_objects, locator(frame).objects)


def test_frames_with_more_seed_rows_than_the_first_capacity_are_associated() -> None:
    """More seed rows than the compiled seeds' first outputs hold (256; this frame has
    about 1500): the seeds run again with room for more, as the reference does."""
    paths = np.arange(0.5, 0.58, 0.01)
    channels = tuple(
        ChannelEchoes(tof_s=paths, amplitude=np.ones(len(paths)), snr_db=np.full(len(paths), 20.0))
        for _ in CROSS
    )
    frame = FrameEchoes(0, 0.0, 1.0, channels)
    compiled = locate_frame(frame, TRANSMITTERS[0], CROSS, OPTIONS[0])
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(locate, "_COMPILED", False)
        reference = locate_frame(frame, TRANSMITTERS[0], CROSS, OPTIONS[0])
    assert compiled.objects
    _assert_same(reference.objects, compiled.objects)


def test_the_fast_located_object_is_the_dataclass_value() -> None:
    """locate._located_object builds what LocatedObject(...) builds, field for field."""
    values = (np.ones(3), np.eye(3), (0, 2, 3), (1, 0, 4), 0.5, 0.9, (0, 0, 0), 1)
    fast, plain = locate._located_object(*values), LocatedObject(*values)
    assert type(fast) is LocatedObject
    assert vars(fast) == vars(plain)
    assert np.array_equal(fast.std_m, plain.std_m)


def test_the_kernel_orders_objects_only_beyond_doubt() -> None:
    """_nearest_first sorts the surviving rows nearest first, and leaves distances within
    1e-9 of each other (or not finite) to locate's own order."""
    from echoloc.localise import _locate_kernels

    origin = np.zeros(3)
    position = np.array([[0.0, 0.0, 2.0], [9.0, 9.0, 9.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.5]])
    rows = np.array([0, 2, 3])
    assert _locate_kernels._nearest_first(position, rows, origin)
    assert rows.tolist() == [2, 3, 0]
    for close in (1.0 + 1e-12, 1.0, np.nan, np.inf):
        position[3] = [0.0, 0.0, close]
        rows = np.array([0, 2, 3])
        assert not _locate_kernels._nearest_first(position, rows, origin)
        assert rows.tolist() == [0, 2, 3]


def test_objects_at_equal_distances_keep_locate_s_order() -> None:
    """Two reflectors mirrored about the array's axis (equal distances): the compiled path
    leaves their order to locate, which gives the reference's."""
    points = np.array([[0.2, 0.1, 0.6], [-0.1, 0.2, 0.6]])
    paths = model_paths_m(TRANSMITTERS[0], CROSS, points)
    # Amplitudes off the spreading law by different amounts: no tie between the weights.
    amplitudes = np.random.default_rng(0).lognormal(0.0, 0.1, paths.shape)
    channels = []
    for i in range(len(CROSS)):
        order = np.argsort(paths[:, i])
        channels.append(ChannelEchoes(paths[order, i], amplitudes[order, i], np.full(len(points), 20.0)))
    frame = FrameEchoes(0, 0.0, 1.0, tuple(channels))
    compiled = locate_frame(frame, TRANSMITTERS[0], CROSS, OPTIONS[1])
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(locate, "_COMPILED", False)
        reference = locate_frame(frame, TRANSMITTERS[0], CROSS, OPTIONS[1])
    assert len(compiled.objects) == 2
    _assert_same(reference.objects, compiled.objects)


def test_a_group_of_thousands_of_candidates_packs_without_recursion() -> None:
    """A corrupt frame full of echoes made one conflict group of thousands of candidates,
    and the branch and bound recursed once per candidate past Python's limit (a
    RecursionError, "internal error"). A chain where candidate k shares an echo with k+1:
    the best packing takes every other one, from the heaviest end."""
    n = 3 * sys.getrecursionlimit()
    chain = [
        locate._Candidate(
            frozenset({(0, k), (1, k + 1)} if k % 2 else {(1, k), (0, k + 1)}), 1.0 - k * 1e-6, k
        )
        for k in range(n)
    ]
    chosen = locate._best_disjoint(chain, 50_000)
    used = [echo for k in chosen for echo in chain[k].echoes]
    assert len(used) == len(set(used))  # a packing: no echo used twice
    assert sorted(chosen) == list(range(0, n, 2))
