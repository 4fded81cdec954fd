"""The compiled seed search (``_locate_kernels.seed_candidates``, steps 1-2 of association)
gives the rows of its numpy statement (``seed_oracle.seed_candidates_reference``).

Rows are compared as multisets: the same (echo, use) per channel, points within the
oracle's tolerance of each row (1e-9 m at well-conditioned crossings, see
``seed_oracle.point_tolerance``). A kernel row the oracle has no row for must lie at one
of the oracle's doubtful points (a decision within rounding of its threshold).
"""

from __future__ import annotations

from itertools import combinations
from typing import Any, NamedTuple

import numpy as np
import pytest
from hypothesis import event, given, settings
from hypothesis import strategies as st
from seed_oracle import NONE, OWN, SHARED, SeedRows, seed_candidates_reference

from echoloc.localise import _locate_kernels as kernels

CROSS = np.array([[0.25, 0, 0], [-0.25, 0, 0], [0, 0.25, 0], [0, -0.25, 0]], dtype=float)
"""The report's head: receivers 0.25 m from the transmitter (at the origin) on +-x, +-y, m."""

LINE = np.array([[0.25, 0], [-0.25, 0], [0.12, 0], [-0.1, 0]], dtype=float)
"""A 2-D head (x, z): four receivers on the x axis, m."""

K_GATE = 3.2905267314918945  # sqrt(chi2.ppf(0.999, 1)): association's default one-path gate
MERGE_REACH = 0.0275 / 4  # a quarter of a 27.5 mm resolution, m
CAPACITY = 1 << 16


class Scene(NamedTuple):
    """The kernel's arguments without the sorted copies and the capacity (the oracle's)."""

    transmitters: np.ndarray
    receivers: np.ndarray
    transmitter_axes: np.ndarray
    receiver_axes: np.ndarray
    boresight: np.ndarray
    required: np.ndarray
    paths: np.ndarray
    sigmas: np.ndarray
    offset: np.ndarray
    seeds: np.ndarray
    window_low: float
    window_high: float
    cos_fov: float
    k_gate: float
    merge_reach: float
    min_own: int


class KernelRows(NamedTuple):
    echo: np.ndarray  # (count, C)
    use: np.ndarray  # (count, C)
    points: np.ndarray  # (count, D), m
    overflow: bool


def _seeds(transmitter_index: np.ndarray, required: np.ndarray, dim: int) -> np.ndarray:
    """Every D required channels of one transmitter (as locate builds the seed sets)."""
    seeds = [
        seed
        for t in np.unique(transmitter_index[required])
        for seed in combinations(np.flatnonzero((transmitter_index == t) & required).tolist(), dim)
    ]
    return np.array(seeds, dtype=np.int64).reshape(-1, dim)


def _scene(
    transmitters: np.ndarray,
    receivers: np.ndarray,
    channel_paths: list[np.ndarray],
    channel_sigmas: list[np.ndarray] | None = None,
    *,
    transmitter_index: np.ndarray | None = None,
    required: np.ndarray | None = None,
    transmitter_axes: np.ndarray | None = None,
    receiver_axes: np.ndarray | None = None,
    window: tuple[float, float] = (0.0, np.inf),
    field_of_view_deg: float = 90.0,
    merge_reach: float = 0.0,
    min_own: int | None = None,
) -> Scene:
    """A scene of channels (transmitter, receiver) (C, D), m, and each channel's echo paths, m."""
    n_ch, dim = receivers.shape
    boresight = np.zeros(dim)
    boresight[-1] = 1.0
    index = np.zeros(n_ch, dtype=np.int64) if transmitter_index is None else transmitter_index
    must = np.ones(n_ch, dtype=bool) if required is None else required
    sigmas = [np.full(len(p), 5e-4) for p in channel_paths] if channel_sigmas is None else channel_sigmas
    axes = np.tile(boresight, (n_ch, 1))
    return Scene(
        np.ascontiguousarray(transmitters, dtype=float),
        np.ascontiguousarray(receivers, dtype=float),
        axes.copy() if transmitter_axes is None else transmitter_axes,
        axes.copy() if receiver_axes is None else receiver_axes,
        boresight,
        must,
        np.concatenate([np.asarray(p, dtype=float) for p in channel_paths]),
        np.concatenate([np.asarray(s, dtype=float) for s in sigmas]),
        np.array([0, *np.cumsum([len(p) for p in channel_paths])], dtype=np.int64),
        _seeds(index, must, dim),
        float(window[0]),
        float(window[1]),
        float(np.cos(np.radians(field_of_view_deg))),
        K_GATE,
        float(merge_reach),
        dim if min_own is None else min_own,
    )


def _paths(transmitters: np.ndarray, receivers: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Paths T_c -> p -> R_c, (n, C), m."""
    p = np.atleast_2d(points)[:, None, :]
    return np.asarray(np.linalg.norm(p - transmitters, axis=2) + np.linalg.norm(p - receivers, axis=2))


def _kernel(scene: Scene, capacity: int = CAPACITY) -> KernelRows:
    """The compiled seed search, with the sorted copies locate's reference builds (np.lexsort)."""
    channel = np.repeat(np.arange(len(scene.offset) - 1), np.diff(scene.offset))
    order = np.lexsort((scene.paths, channel))
    sorted_index = (order - scene.offset[channel[order]]).astype(np.int64)
    echo, use, points, count, overflow = kernels.seed_candidates(
        *scene[:9], scene.paths[order], sorted_index, *scene[9:], capacity
    )
    return KernelRows(echo[:count], use[:count], points[:count], bool(overflow))


def _oracle(scene: Scene) -> SeedRows:
    return seed_candidates_reference(*scene)


def _match(kernel: KernelRows, oracle: SeedRows) -> tuple[list[int], list[int]]:
    """Pair kernel rows with oracle rows (the same echoes and uses, points within the oracle
    row's tolerance); returns the oracle rows left unpaired and the kernel rows left unpaired
    that lie at no doubtful point."""
    free = list(range(len(kernel.echo)))
    missing = []
    for i in range(len(oracle.echo)):
        same = [
            k
            for k in free
            if np.array_equal(kernel.echo[k], oracle.echo[i]) and np.array_equal(kernel.use[k], oracle.use[i])
        ]
        distance = [np.max(np.abs(kernel.points[k] - oracle.points[i])) for k in same]
        if distance and min(distance) <= oracle.tolerance[i]:
            free.remove(same[int(np.argmin(distance))])
        else:
            missing.append(i)
    extra = [
        k
        for k in free
        if not np.any(np.max(np.abs(oracle.doubtful - kernel.points[k]), axis=1) <= oracle.doubt_radius)
    ]
    return missing, extra


def _describe(kernel: KernelRows, oracle: SeedRows, missing: list[int], extra: list[int]) -> str:
    lines = [f"{len(oracle.echo)} oracle rows, {len(kernel.echo)} kernel rows"]
    lines += [f"oracle only: {oracle.echo[i]} {oracle.use[i]} {oracle.points[i]}" for i in missing]
    lines += [f"kernel only: {kernel.echo[k]} {kernel.use[k]} {kernel.points[k]}" for k in extra]
    return "\n".join(lines)


def _assert_same_rows(kernel: KernelRows, oracle: SeedRows) -> None:
    assert not kernel.overflow
    missing, extra = _match(kernel, oracle)
    assert not missing, _describe(kernel, oracle, missing, extra)
    assert not extra, _describe(kernel, oracle, missing, extra)


def _keys(rows: KernelRows | SeedRows) -> list[tuple[int, ...]]:
    """Each row's echoes and uses, sorted."""
    return sorted(tuple(e) + tuple(u) for e, u in zip(rows.echo.tolist(), rows.use.tolist(), strict=True))


# --- random scenes -----------------------------------------------------------------


def _random_scene(
    rng: np.random.Generator,
    dim: int,
    *,
    n_reflectors: int,
    noise_m: float,
    spurious: int,
    second_transmitter: bool,
    perturbation_m: float,
    tilt: float,
    field_of_view_deg: float,
    window: tuple[float, float],
    merge_reach: float,
    extra_own: int,
) -> Scene:
    """The report's head (or a 2-D line of receivers) perturbed, reflectors 0.3-1.5 m ahead,
    their paths with noise, some lost, spurious echoes, shuffled within each channel."""
    head = CROSS if dim == 3 else LINE
    receivers = head + rng.normal(0.0, perturbation_m, head.shape)
    transmitters = np.tile(rng.normal(0.0, perturbation_m / 3, dim), (len(head), 1))
    index = np.zeros(len(head), dtype=np.int64)
    required = np.ones(len(head), dtype=bool)
    if second_transmitter:  # a second frame combined: its channels partly optional
        other = rng.normal(0.0, 0.05, dim)
        other[-1] = 0.0
        receivers = np.vstack([receivers, receivers])
        transmitters = np.vstack([transmitters, np.tile(other, (len(head), 1))])
        index = np.r_[index, np.ones(len(head), dtype=np.int64)]
        required = np.r_[required, rng.random(len(head)) < 0.5]
    n_ch = len(receivers)
    axis = np.zeros(dim)
    axis[-1] = 1.0
    axes = [axis + rng.normal(0.0, tilt, (n_ch, dim)) for _ in range(2)]
    axes = [a / np.linalg.norm(a, axis=1, keepdims=True) for a in axes]
    depth = rng.uniform(0.3, 1.5, n_reflectors)
    across = rng.uniform(-0.5, 0.5, (n_reflectors, dim - 1)) * depth[:, None]
    true_paths = _paths(transmitters, receivers, np.column_stack([across, depth]))
    channel_paths, channel_sigmas = [], []
    for c in range(n_ch):
        heard = true_paths[:, c] + rng.normal(0.0, noise_m, n_reflectors)
        heard = heard[rng.random(n_reflectors) > 0.1]
        heard = rng.permutation(np.r_[heard, rng.uniform(0.3, 3.2, rng.integers(0, spurious + 1))])
        channel_paths.append(heard)
        channel_sigmas.append(rng.uniform(3e-4, 1.5e-3, len(heard)))
    return _scene(
        transmitters,
        receivers,
        channel_paths,
        channel_sigmas,
        transmitter_index=index,
        required=required,
        transmitter_axes=np.ascontiguousarray(axes[0]),
        receiver_axes=np.ascontiguousarray(axes[1]),
        window=window,
        field_of_view_deg=field_of_view_deg,
        merge_reach=merge_reach,
        min_own=dim + extra_own,
    )


@st.composite
def _scenes(draw: Any) -> Scene:
    dim = draw(st.sampled_from([3, 2]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    return _random_scene(
        rng,
        dim,
        n_reflectors=draw(st.integers(1, 4)),
        noise_m=draw(st.sampled_from([0.0, 2e-4, 5e-4, 2e-3])),
        spurious=draw(st.integers(0, 4)),
        second_transmitter=draw(st.booleans()),
        perturbation_m=draw(st.sampled_from([0.0, 0.01])),
        tilt=draw(st.sampled_from([0.0, 0.05])),
        field_of_view_deg=draw(st.sampled_from([90.0, 60.0, 35.0])),
        window=draw(st.sampled_from([(0.0, np.inf), (0.5, 2.4)])),
        merge_reach=draw(st.sampled_from([0.0, MERGE_REACH])),
        extra_own=draw(st.integers(0, 2)),
    )


@settings(max_examples=150, deadline=None)
@given(_scenes())
def test_the_kernel_emits_the_oracle_s_rows(scene: Scene) -> None:
    oracle = _oracle(scene)
    event(f"rows: {'none' if len(oracle.echo) == 0 else 'some'}")
    event(f"doubtful points: {'none' if len(oracle.doubtful) == 0 else 'some'}")
    _assert_same_rows(_kernel(scene), oracle)


def test_the_random_scenes_reach_every_outcome() -> None:
    """The property test's scenes give rows of every kind, and few doubtful points."""
    rows, crossings, doubtful = 0, 0, 0
    uses: set[int] = set()
    for seed in range(12):
        rng = np.random.default_rng(seed)
        scene = _random_scene(
            rng,
            3 if seed % 2 else 2,
            n_reflectors=3,
            noise_m=2e-3,
            spurious=3,
            second_transmitter=seed % 3 == 0,
            perturbation_m=0.01,
            tilt=0.05,
            field_of_view_deg=60.0,
            window=(0.5, 2.4),
            merge_reach=MERGE_REACH,
            extra_own=seed % 2,
        )
        oracle = _oracle(scene)
        _assert_same_rows(_kernel(scene), oracle)
        rows += len(oracle.echo)
        uses |= set(oracle.use.ravel().tolist())
        crossings += oracle.n_crossings
        doubtful += len(oracle.doubtful)
    assert rows > 50
    assert uses == {OWN, SHARED, NONE}
    assert doubtful <= 0.02 * crossings


# --- closed forms ------------------------------------------------------------------


@pytest.mark.parametrize(
    "point",
    [(0.1, -0.05, 0.8), (-0.3, 0.2, 0.5), (0.0, 0.0, 1.4), (0.2, 0.9), (-0.6, 0.4)],
    ids=str,
)
def test_a_reflector_s_exact_paths_give_its_point(point: tuple[float, ...]) -> None:
    """Exact paths of one reflector: every seed gives one row, all echoes own, at the point."""
    p = np.array(point)
    receivers = CROSS if len(p) == 3 else LINE
    transmitters = np.zeros_like(receivers)
    scene = _scene(
        transmitters, receivers, list(_paths(transmitters, receivers, p).T), min_own=len(receivers)
    )
    kernel, oracle = _kernel(scene), _oracle(scene)
    n_seeds = len(scene.seeds)
    assert len(kernel.echo) == n_seeds
    assert np.all(kernel.echo == 0)
    assert np.all(kernel.use == OWN)
    np.testing.assert_allclose(kernel.points, np.tile(p, (n_seeds, 1)), rtol=0, atol=1e-9)
    np.testing.assert_allclose(oracle.points, np.tile(p, (n_seeds, 1)), rtol=0, atol=1e-12)
    _assert_same_rows(kernel, oracle)


def test_the_report_s_closed_form_is_the_kernel_s_point() -> None:
    """docs/METHOD.md 6.1: a transmitter between receivers at +-d gives r and x in closed form."""
    d, l1, l2 = 0.25, 1.62, 1.71
    r = (l1**2 + l2**2 - 2 * d**2) / (2 * (l1 + l2))
    x = (l2**2 - l1**2 - 2 * r * (l2 - l1)) / (4 * d)
    receivers = np.array([[d, 0.0], [-d, 0.0]])
    scene = _scene(np.zeros((2, 2)), receivers, [np.array([l1]), np.array([l2])])
    kernel = _kernel(scene)
    np.testing.assert_allclose(kernel.points, [[x, np.sqrt(r**2 - x**2)]], rtol=0, atol=1e-9)
    _assert_same_rows(kernel, _oracle(scene))


# --- edge cases --------------------------------------------------------------------


def test_a_channel_outside_the_window_needs_no_echo() -> None:
    """A reflector toward +y: receiver 3 (at -y) hears the longest path. With the window's
    end below it, the seed (0, 1, 2) leaves channel 3 empty; seeds with channel 3 attach
    their other channel as usual. Without the window, losing channel 3's echo loses them all."""
    p = np.array([0.0, 0.2, 0.8])
    transmitters = np.zeros_like(CROSS)
    paths = _paths(transmitters, CROSS, p)[0]
    assert np.argmax(paths) == 3
    high = 0.5 * (paths[3] + np.sort(paths)[-2])
    scene = _scene(transmitters, CROSS, [np.array([x]) for x in paths], window=(0.0, high))
    kernel = _kernel(scene)
    assert _keys(kernel) == sorted([(0, 0, 0, 0) + (OWN,) * 4] * 3 + [(0, 0, 0, -1, OWN, OWN, OWN, NONE)])
    np.testing.assert_allclose(kernel.points, np.tile(p, (4, 1)), rtol=0, atol=1e-9)
    _assert_same_rows(kernel, _oracle(scene))
    # Channels 0-2 below the window: only the seed (0, 1, 2) finds its fourth echo (the
    # window bounds predictions, not a seed's own paths).
    low = scene._replace(window_low=high, window_high=np.inf)
    kernel = _kernel(low)
    left_out = [(-1, 0, 0, 0, NONE, OWN, OWN, OWN), (0, -1, 0, 0, OWN, NONE, OWN, OWN)]
    left_out.append((0, 0, -1, 0, OWN, OWN, NONE, OWN))
    assert _keys(kernel) == sorted([(0, 0, 0, 0) + (OWN,) * 4, *left_out])
    _assert_same_rows(kernel, _oracle(low))
    lost = _scene(transmitters, CROSS, [np.array([x]) for x in paths[:3]] + [np.array([])])
    assert len(_kernel(lost).echo) == 0
    _assert_same_rows(_kernel(lost), _oracle(lost))
    excused = lost._replace(window_high=high)
    assert _keys(_kernel(excused)) == [(0, 0, 0, -1, OWN, OWN, OWN, NONE)]
    _assert_same_rows(_kernel(excused), _oracle(excused))


def test_a_reflector_behind_the_array_gives_no_row() -> None:
    """A flat head cannot tell z from -z: a reflector behind it shows at its mirror image in
    front. A head whose receivers stand out of its plane rejects the crossing behind it."""
    p = np.array([0.1, -0.2, -0.7])
    transmitters = np.zeros_like(CROSS)
    flat = _scene(transmitters, CROSS, list(_paths(transmitters, CROSS, p).T))
    kernel = _kernel(flat)
    np.testing.assert_allclose(kernel.points, np.tile(p * [1, 1, -1], (4, 1)), rtol=0, atol=1e-9)
    _assert_same_rows(kernel, _oracle(flat))
    raised = CROSS + np.array([[0, 0, 0.03], [0, 0, -0.02], [0, 0, 0.04], [0, 0, 0.01]])
    curved = _scene(transmitters, raised, list(_paths(transmitters, raised, p).T))
    kernel = _kernel(curved)
    assert len(kernel.echo) == 0
    assert len(_oracle(curved).echo) == 0
    _assert_same_rows(kernel, _oracle(curved))


def test_the_field_of_view_bounds_the_rows() -> None:
    """A reflector 45 degrees off the boresight: seen with a 60-degree field of view, not with
    a 35-degree one; a receiver turned away from it needs no echo."""
    p = np.array([0.6, 0.0, 0.6])
    transmitters = np.zeros_like(CROSS)
    wide = _scene(transmitters, CROSS, list(_paths(transmitters, CROSS, p).T), field_of_view_deg=60.0)
    assert _keys(_kernel(wide)) == [(0, 0, 0, 0) + (OWN,) * 4] * 4
    _assert_same_rows(_kernel(wide), _oracle(wide))
    narrow = wide._replace(cos_fov=float(np.cos(np.radians(35.0))))
    assert len(_kernel(narrow).echo) == 0
    _assert_same_rows(_kernel(narrow), _oracle(narrow))
    turned = wide.receiver_axes.copy()
    turned[3] = [-np.sin(np.radians(40.0)), 0.0, np.cos(np.radians(40.0))]  # 85 degrees from p
    away = wide._replace(receiver_axes=turned)
    # Seeds with channel 3 lose the point; seed (0, 1, 2) keeps it, channel 3 empty.
    assert _keys(_kernel(away)) == [(0, 0, 0, -1, OWN, OWN, OWN, NONE)]
    _assert_same_rows(_kernel(away), _oracle(away))


@pytest.mark.parametrize("required", [True, False])
def test_the_gate_and_the_merge_reach(required: bool) -> None:
    """Channel 3's echo moved off its prediction: own within the gate, shared beyond it within
    the merge reach (on a required channel only), else the seed (0, 1, 2) is lost (required)
    or keeps channel 3 empty (optional)."""
    p = np.array([0.1, -0.05, 0.8])
    transmitters = np.zeros_like(CROSS)
    paths = _paths(transmitters, CROSS, p)[0]
    must = np.array([True, True, True, required])
    base = _scene(transmitters, CROSS, [np.array([x]) for x in paths], required=must, merge_reach=MERGE_REACH)
    base = base._replace(seeds=np.array([[0, 1, 2]]))
    reach = []
    for shift in (0.0, 1e-3, 4e-3, 8e-3, 20e-3):
        moved = base.paths.copy()
        moved[3] += shift
        scene = base._replace(paths=moved)
        kernel = _kernel(scene)
        _assert_same_rows(kernel, _oracle(scene))
        reach.append(_keys(kernel))
    own = (0, 0, 0, 0, OWN, OWN, OWN, OWN)
    shared = (0, 0, 0, 0, OWN, OWN, OWN, SHARED)
    empty = (0, 0, 0, -1, OWN, OWN, OWN, NONE)
    # Gate: 3.29 sqrt(var + (0.5 mm)^2), 1.6 mm and more, under 4 mm here; merge reach 6.9 mm beyond.
    assert reach[0] == reach[1] == [own]
    assert reach[2] == reach[3] == ([shared] if required else [empty])
    assert reach[4] == ([] if required else [empty])


@pytest.mark.parametrize("miss", [-1e-4, -1e-7, -1e-10, -1e-13, 0.0, 1e-9, 1e-5])
def test_nearly_tangent_ellipses(miss: float) -> None:
    """2-D receivers whose ellipses touch on the line through them, ahead of a tilted head:
    paths short of the touching ones by ``-miss`` cross twice, ever closer and worse
    conditioned (two roots between two of the oracle's samples, found by its refinement of
    the extremum; the tolerance grows as the conditioning falls); at and beyond the touch,
    doubtful points or nothing."""
    receivers = np.array([[0.25, 0.03], [-0.25, 0.01]])  # their line misses the transmitter
    transmitters = np.zeros_like(receivers)
    p = receivers[0] + 1.25 * (receivers[0] - receivers[1])  # on the line, beyond receiver 0
    paths = _paths(transmitters, receivers, p)[0] + np.array([0.0, miss])
    scene = _scene(transmitters, receivers, [np.array([x]) for x in paths])
    kernel, oracle = _kernel(scene), _oracle(scene)
    _assert_same_rows(kernel, oracle)
    if miss <= -1e-7:  # conditioning ratio 1e-6 and more: certain rows
        assert len(oracle.echo) == len(kernel.echo) == 2
    if miss <= -1e-10:  # ratio 1e-9 and more: kept by the kernel (the oracle's doubtful points)
        assert len(kernel.echo) == 2
    if miss > 0:
        assert len(kernel.echo) == 0


def test_overflow_stops_at_the_capacity() -> None:
    """More rows than the capacity: the kernel says so and returns the capacity's worth,
    every one a row of the oracle's; exactly the capacity is no overflow."""
    transmitters = np.zeros_like(CROSS)
    points = np.array([[0.1, -0.05, 0.8], [-0.3, 0.2, 0.5], [0.0, 0.3, 1.2]])
    scene = _scene(transmitters, CROSS, list(_paths(transmitters, CROSS, points).T), min_own=4)
    oracle = _oracle(scene)
    n = len(oracle.echo)
    assert n >= 12
    full = _kernel(scene, capacity=n)
    assert not full.overflow
    _assert_same_rows(full, oracle)
    for capacity in (0, 1, n - 1):
        short = _kernel(scene, capacity=capacity)
        assert short.overflow
        assert len(short.echo) == capacity
        missing, extra = _match(short, oracle)
        assert not extra
        assert len(missing) == n - capacity
