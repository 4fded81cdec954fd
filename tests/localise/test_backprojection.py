"""Back-projection ("points to peaks"): lookup table, coarse-to-fine search, support rule, round trips."""

from __future__ import annotations

from collections.abc import Sequence
from functools import cache

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from numpy.typing import NDArray

from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording
from echoloc.localise.backprojection import (
    QUANTUM,
    BackprojectionOptions,
    Components,
    EchoModel,
    Envelopes,
    Grid,
    PathTable,
    _bounds,
    backproject_frame,
    brute_force_image,
    channel_paths_m,
    envelopes,
    fine_scores,
    local_maxima,
    locate_channels,
    path_table,
    prepare_backprojection,
    run_backprojection,
    search,
)
from echoloc.localise.evaluation import evaluate
from echoloc.localise.locate import exact_solutions
from echoloc.physics.waveform import barker_waveform
from echoloc.sim.scenefile import scene_from_dict
from echoloc.sim.simulation import simulate
from echoloc.tof.echoes import MatchedFilter, noise_power

FS = 200e3
C = 343.0
N_SAMPLES = 2400
ARRAY_3D = np.array([[0.25, 0.0, 0.0], [-0.25, 0.0, 0.0], [0.0, 0.25, 0.0], [0.0, -0.25, 0.0]])


@cache
def _filter() -> MatchedFilter:
    return MatchedFilter(barker_waveform().samples, N_SAMPLES, FS)


def _signals(
    tx_m: NDArray[np.float64],
    rx_m: NDArray[np.float64],
    points_m: NDArray[np.float64],
    amplitudes: NDArray[np.float64],
    noise: float,
    seed: int,
) -> NDArray[np.complex128]:
    """Matched-filter outputs in noise units of echoes from points: exact fractional delays by FFT."""
    rng = np.random.default_rng(seed)
    template = barker_waveform().samples
    n_fft = 2 * N_SAMPLES
    spectrum = np.fft.rfft(template, n_fft)
    freqs = np.fft.rfftfreq(n_fft)
    paths = channel_paths_m(tx_m, rx_m, points_m)  # (n_points, n_ch)
    frames = np.zeros((len(rx_m), N_SAMPLES))
    for p, a in zip(paths, amplitudes, strict=True):
        for ch, path in enumerate(p):
            delay = path / C * FS
            frames[ch] += a * np.fft.irfft(spectrum * np.exp(-2j * np.pi * freqs * delay), n_fft)[:N_SAMPLES]
    frames += noise * rng.standard_normal(frames.shape)
    out = _filter().correlate(frames)
    return np.asarray(out / np.sqrt([[noise_power(row)] for row in out]))


# --- lookup table --------------------------------------------------------------------


def test_path_table_equals_closed_form_paths() -> None:
    grid = Grid(np.array([-0.2, -0.1, 0.3]), np.array([0.2, 0.15, 0.55]), 0.01)
    tx = np.zeros((4, 3))
    table = path_table(grid, tx, ARRAY_3D, FS, C)
    index = np.arange(grid.n_voxels)
    centres = grid.centres_m(index)
    exact = np.linalg.norm(centres[:, None] - tx, axis=2) + np.linalg.norm(
        centres[:, None] - ARRAY_3D, axis=2
    )
    # Fixed point of 1/16 sample: half a step of rounding at most.
    np.testing.assert_allclose(table.paths_m(index), exact, rtol=0, atol=0.5 / QUANTUM * C / FS + 1e-12)
    assert grid.shape == (40, 25, 25)
    # The centre voxel of a symmetric axis is where the formula puts it.
    assert grid.axis_m(0)[0] == pytest.approx(-0.195)


def test_pyramid_cells_hold_every_sample_their_voxels_read() -> None:
    grid = Grid(np.array([-0.1, -0.1, 0.2]), np.array([0.13, 0.1, 0.41]), 0.005)  # odd sizes on purpose
    table = path_table(grid, np.zeros((4, 3)), ARRAY_3D, FS, C, top_cell_m=0.04)
    assert len(table.levels) == 3
    fine = table.fine.reshape(*grid.shape, 4).astype(np.int64)
    for level, (cells, shape) in enumerate(zip(table.levels, table.level_shapes, strict=True), start=1):
        spans = cells.reshape(*shape, 4, 2).astype(np.int64)
        size = 1 << level
        coords = np.stack(np.meshgrid(*[np.arange(n) for n in grid.shape], indexing="ij"), axis=-1)
        cell = coords // size
        lo = spans[cell[..., 0], cell[..., 1], cell[..., 2], :, 0]
        hi = spans[cell[..., 0], cell[..., 1], cell[..., 2], :, 1]
        assert np.all(lo <= fine // QUANTUM)
        assert np.all(hi >= -(-fine // QUANTUM))


# --- coarse to fine = brute force ----------------------------------------------------


@cache
def _small_table() -> PathTable:
    grid = Grid(np.array([-0.15, -0.15, 0.3]), np.array([0.15, 0.15, 0.6]), 0.005)
    return path_table(grid, np.zeros((4, 3)), ARRAY_3D, FS, C, top_cell_m=0.04)


@settings(max_examples=12, deadline=None)
@given(
    seed=st.integers(0, 2**31 - 1),
    n_points=st.integers(1, 4),
    k=st.integers(2, 4),
    floor=st.floats(2.0, 20.0),
)
def test_coarse_to_fine_finds_exactly_the_brute_force_voxels_and_peaks(
    seed: int, n_points: int, k: int, floor: float
) -> None:
    table = _small_table()
    rng = np.random.default_rng(seed)
    points = np.column_stack(
        [
            rng.uniform(-0.15, 0.15, n_points),
            rng.uniform(-0.15, 0.15, n_points),
            rng.uniform(0.3, 0.6, n_points),
        ]
    )
    signals = _signals(np.zeros((4, 3)), ARRAY_3D, points, rng.uniform(0.02, 0.2, n_points), 0.05, seed)
    env = envelopes(np.arange(4), np.abs(signals), table)
    image = brute_force_image(table, env, k).ravel()
    flat, scores = search(table, env, k, floor)
    expected = np.flatnonzero(image >= floor)
    np.testing.assert_array_equal(np.sort(flat), expected)
    np.testing.assert_array_equal(scores[np.argsort(flat)], image[expected])
    # Local maxima over the refined voxels are those of the full image.
    peaks = np.sort(local_maxima(table.grid.shape, flat, scores))
    full = np.sort(local_maxima(table.grid.shape, np.arange(len(image)), image))
    np.testing.assert_array_equal(peaks, full[image[full] >= floor])
    # The brightest voxel, with the floor raised as it goes.
    if len(expected):
        best, best_score = search(table, env, k, floor, best_only=True)
        assert image[best[np.argmax(best_score)]] == image.max()


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(1, 4))
def test_coarse_cell_score_bounds_every_voxel_inside(seed: int, k: int) -> None:
    table = _small_table()
    rng = np.random.default_rng(seed)
    magnitudes = rng.exponential(1.0, (4, N_SAMPLES)) ** 2
    env = envelopes(np.arange(4), magnitudes, table)
    image = brute_force_image(table, env, k)
    for level, shape in enumerate(table.level_shapes, start=1):
        bounds = _bounds(table, env, level, np.arange(int(np.prod(shape))), k).reshape(shape)
        size = 1 << level
        coords = np.indices(table.grid.shape) // size
        assert np.all(bounds[coords[0], coords[1], coords[2]] >= image)


# --- objects -------------------------------------------------------------------------


def _restored(signals: NDArray[np.complex128], model: EchoModel) -> tuple[NDArray[np.complex128], Components]:
    """CLEAN-restored signals around the echoes the matched-filter CLEAN finds (as the pipeline does)."""
    rows, components = [], []
    for row in signals:
        found = _clean_delays(row)
        restored, amplitudes = model.restore(row, found)
        rows.append(restored)
        components.append((found, amplitudes))
    return np.array(rows), components


def _clean_delays(row: NDArray[np.complex128]) -> NDArray[np.float64]:
    """Delays (samples) of the echoes in one channel: fit, subtract, repeat while above 14 dB."""
    model = EchoModel(matched=_filter())
    work = row.copy()
    delays = []
    while np.max(np.abs(work)) >= 5.0 and len(delays) < 8:
        tau, amplitude = model.fit(work, float(np.argmax(np.abs(work))), 1.0)
        model.subtract(work, tau, amplitude)
        delays.append(tau)
    return np.sort(np.array(delays))


def _image_2d(
    receivers: NDArray[np.float64], points: NDArray[np.float64], k: int
) -> tuple[PathTable, Envelopes, NDArray[np.complex128]]:
    grid = Grid(np.array([-0.4, 0.2]), np.array([0.4, 1.0]), 0.002)
    tx = np.zeros((len(receivers), 2))
    table = path_table(grid, tx, receivers, FS, C)
    signals, _ = _restored(
        _signals(tx, receivers, points, np.ones(len(points)), 0.02, 1), EchoModel(matched=_filter())
    )
    return table, envelopes(np.arange(len(receivers)), np.abs(signals), table), signals


def _brightness_near(table: PathTable, env: Envelopes, k: int, point: NDArray[np.float64]) -> float:
    """Largest image value within 2 voxels of a point."""
    grid = table.grid
    centre = np.floor((point - grid.lower_m) / grid.voxel_m).astype(int)
    offsets = np.stack(np.meshgrid(*[np.arange(-2, 3)] * grid.dim, indexing="ij"), axis=-1).reshape(
        -1, grid.dim
    )
    flat = np.ravel_multi_index(tuple((centre + offsets).T), grid.shape)
    return float(fine_scores(table, env, flat, k).max())


def test_two_receivers_show_the_two_ghost_crossings_and_a_third_removes_them() -> None:
    points = np.array([[-0.05, 0.55], [0.15, 0.62]])
    pair = np.array([[0.25, 0.0], [-0.25, 0.0]])
    # The expected ghosts: A's ellipse on receiver 0 crossing B's on receiver 1, and back.
    paths = channel_paths_m(np.zeros((2, 2)), pair, points)
    crossed = np.array([[paths[0, 0], paths[1, 1]], [paths[1, 0], paths[0, 1]]])
    solutions, valid = exact_solutions(np.zeros(2), pair, crossed)
    ghosts = np.array([s[v][np.argmax(s[v][:, 1])] for s, v in zip(solutions, valid, strict=True)])
    assert np.all(
        np.linalg.norm(ghosts[:, None] - points, axis=2) > 0.1
    )  # ghosts near (0.26, 0.56), (-0.16, 0.55)
    table, env, _ = _image_2d(pair, points, 2)
    peak = float(brute_force_image(table, env, 2).max())
    for p in (*points, *ghosts):
        assert _brightness_near(table, env, 2, p) > 0.8 * peak  # ghosts as bright as the objects
    # A third receiver, and three channels required: the ghosts go dark.
    trio = np.array([[0.25, 0.0], [-0.25, 0.0], [0.08, 0.0]])
    table3, env3, signals3 = _image_2d(trio, points, 3)
    peak3 = float(brute_force_image(table3, env3, 3).max())
    for p in points:
        assert _brightness_near(table3, env3, 3, p) > 0.8 * peak3
    for g in ghosts:
        assert _brightness_near(table3, env3, 3, g) < 0.01 * peak3
    # ... and exactly the two objects are located, to a fraction of a millimetre.
    model = EchoModel(matched=_filter())
    _, components = _restored(_signals(np.zeros((3, 2)), trio, points, np.ones(2), 0.02, 1), model)
    objects = locate_channels(
        table3,
        signals3,
        np.arange(3),
        [model] * 3,
        BackprojectionOptions(min_support=3),
        components=components,
    )
    assert len(objects) == 2
    found = np.array([o.position_m for o in objects])
    for p in points:
        assert np.min(np.linalg.norm(found - p, axis=1)) < 0.5e-3


def test_mirrored_array_mirrors_image_and_objects() -> None:
    grid = Grid(np.array([-0.3, -0.2, 0.3]), np.array([0.3, 0.2, 0.7]), 0.005)
    points = np.array([[0.12, -0.05, 0.45], [-0.2, 0.1, 0.62]])
    amplitudes = np.array([0.1, 0.05])
    mirror = np.array([-1.0, 1.0, 1.0])
    tx = np.zeros((4, 3))
    table = path_table(grid, tx, ARRAY_3D, FS, C)
    table_m = path_table(grid, tx, ARRAY_3D * mirror, FS, C)
    signals = _signals(tx, ARRAY_3D, points, amplitudes, 0.02, 5)
    env = envelopes(np.arange(4), np.abs(signals), table)
    env_m = envelopes(np.arange(4), np.abs(signals), table_m)
    image = brute_force_image(table, env, 4)
    image_m = brute_force_image(table_m, env_m, 4)
    # Same signals, mirrored receivers: the image of the mirrored scene.
    np.testing.assert_allclose(image_m, image[::-1], rtol=0, atol=0.02 * float(image.max()))
    model = EchoModel(matched=_filter())
    restored, components = _restored(signals, model)
    options = BackprojectionOptions()
    found = locate_channels(table, restored.copy(), np.arange(4), [model] * 4, options, components=components)
    found_m = locate_channels(
        table_m, restored.copy(), np.arange(4), [model] * 4, options, components=components
    )
    a = np.array(sorted(tuple(o.position_m) for o in found))
    b = np.array(sorted(tuple(o.position_m * mirror) for o in found_m))
    assert len(a) == 2
    np.testing.assert_allclose(a, b, atol=1e-6)
    np.testing.assert_allclose(a, np.array(sorted(map(tuple, points))), atol=1e-3)


# Two point reflectors in front of ARRAY_3D, and the grid that holds them (the round trips below).
TWO_POINTS = (
    {"kind": "point", "position_m": [0.1, -0.05, 0.5]},
    {"kind": "point", "position_m": [-0.15, 0.12, 0.65]},
)
ROUND_TRIP_GRID = Grid(np.array([-0.3, -0.3, 0.3]), np.array([0.3, 0.3, 0.9]), 0.005)


def _simulated(
    transmitters_m: list[list[float]], reflectors: Sequence[dict[str, object]], n_frames: int
) -> Recording:
    """Frames of a Barker-13 scene on ARRAY_3D: SNR 20 dB, 0.5 mm path jitter, seed 3."""
    data = {
        "seed": 3,
        "array": {"transmitters_m": transmitters_m, "receivers_m": ARRAY_3D.tolist()},
        "pulse": {"code": "barker13", "carrier_hz": 50e3, "cycles_per_bit": 4},
        "acquisition": {"sample_rate_hz": FS, "n_samples": N_SAMPLES},
        "noise": {"snr_db": 20.0, "path_jitter_m": 0.0005},
        "reflectors": list(reflectors),
    }
    return simulate(scene_from_dict(data, "test"), n_frames)


def test_simulated_scene_round_trip_within_a_few_mm() -> None:
    third = {"kind": "point", "position_m": [0.05, 0.18, 0.8], "strength": 0.7}
    recording = _simulated([[0.0, 0.0, 0.0]], [*TWO_POINTS, third], 6)
    bp = prepare_backprojection(recording, ROUND_TRIP_GRID)
    results = [backproject_frame(bp, i) for i in range(recording.n_frames)]
    assert recording.truth_positions_m is not None
    report = evaluate(results, recording.truth_positions_m, match_radius_m=0.01)
    assert report.recall == 1.0
    assert report.n_false == 0
    assert np.all(report.rmse_m < 3e-3)
    for frame in results:
        for obj in frame.objects:
            assert obj.receivers == (0, 1, 2, 3)
            assert np.all(np.isfinite(obj.std_m))
            assert np.all(obj.std_m < 5e-3)


def test_bad_grid_and_support_are_refused() -> None:
    with pytest.raises(EchoLocError, match="upper_m > lower_m"):
        Grid(np.array([0.0, 0.0, 1.0]), np.array([1.0, 1.0, 0.5]), 0.01)
    with pytest.raises(EchoLocError, match="voxel_m"):
        Grid(np.array([0.0, 0.0, 0.0]), np.array([1.0, 1.0, 1.0]), 0.0)
    table = _small_table()
    signals = np.zeros((4, N_SAMPLES), dtype=complex)
    with pytest.raises(EchoLocError, match="min_support=5"):
        locate_channels(table, signals, np.arange(4), [EchoModel()] * 4, BackprojectionOptions(min_support=5))


def test_two_transmitters_fired_in_turn_are_located_together() -> None:
    recording = _simulated([[0.0, 0.0, 0.0], [0.0, 0.1, 0.0]], TWO_POINTS, 4)
    assert recording.frame_transmitter is not None
    assert list(recording.frame_transmitter) == [0, 1, 0, 1]
    results = list(run_backprojection(prepare_backprojection(recording, ROUND_TRIP_GRID)))
    assert recording.truth_positions_m is not None
    report = evaluate(results, recording.truth_positions_m, match_radius_m=0.01)
    assert report.recall == 1.0
    assert report.n_false == 0
    assert set(results[0].objects[0].transmitters) == {0}  # only transmitter 0 has fired yet
    for frame in results[1:]:
        for obj in frame.objects:
            assert set(obj.transmitters) == {0, 1}  # both transmitters' channels support it
            assert len(obj.receivers) >= 6


def test_the_working_receivers_check_refuses_warns_or_passes() -> None:
    """Fewer working receivers than the grid's dimensions: one error naming the file; exactly as
    many channels a frame: a LocateWarning (every crossing is kept); more: silence. `locate` and
    `batch` both ask this one check."""
    import warnings

    from echoloc.localise.backprojection import BackprojectionOptions, check_working_receivers
    from echoloc.localise.locate import LocateWarning
    from echoloc.sim.scene import default_scene

    recording = simulate(default_scene(), 1)
    options = BackprojectionOptions()
    with pytest.raises(
        EchoLocError, match=r"only 2 working receiver\(s\), back-projection in 3-D needs at least 3"
    ):
        check_working_receivers(recording, 2, 3, options)
    with pytest.warns(LocateWarning, match="3 working channels: back-projection keeps every crossing"):
        check_working_receivers(recording, 3, 3, options)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_working_receivers(recording, 4, 3, options)
