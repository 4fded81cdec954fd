"""Occupancy grids: the inverse sensor model's geometry, its rules across channels and frames,
the beam against the piston's closed form, trajectories, and a simulated room mapped back."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from echoloc import pipeline
from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording
from echoloc.localise.locate import FrameObjects, LocatedObject
from echoloc.localise.surfaces import Surface
from echoloc.maps.mapping import (
    GridSpec,
    MapAccumulator,
    SensorModel,
    Trajectory,
    beam_table,
    build_map,
    frame_poses,
    half_power_angle_deg,
    map_accuracy,
    read_trajectory,
    seen_surface_points_m,
    seen_truth_points_m,
)
from echoloc.physics.transducer import piston_directivity, piston_half_angle_rad
from echoloc.sim.reflectors import Edge, Plane, surface_points_m
from echoloc.sim.scene import Array, Scene, SensorMotion
from echoloc.sim.simulation import simulate
from echoloc.tof.echoes import ChannelEchoes, FrameEchoes
from mapping_oracle import channel_update_reference

C = 343.0
FS = 200e3
N_SAMPLES = 2400
IDENTITY = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])


def _recording(receivers: list[list[float]], fov_deg: float | None = None) -> Recording:
    """A header-like recording: geometry and window only (the map never reads samples)."""
    n_rx = len(receivers)
    return Recording(
        sample_rate_hz=FS,
        transmitters_m=np.zeros((1, 3)),
        receivers_m=np.array(receivers, dtype=float),
        frames=np.zeros((1, n_rx, N_SAMPLES)),
        speed_of_sound_m_s=C,
        field_of_view_deg=fov_deg,
    )


def _echoes(paths_per_channel: list[list[float]], frame: int = 0) -> FrameEchoes:
    channels = tuple(
        ChannelEchoes(np.array(paths) / C, np.ones(len(paths)), np.full(len(paths), 30.0))
        for paths in paths_per_channel
    )
    return FrameEchoes(frame, 0.0, C, channels)


def _floor(cell: float = 0.01) -> GridSpec:
    return GridSpec.floor_plan((-1.0, 1.0), (0.0, 2.0), cell)


def _cell_value(grid_values: np.ndarray, spec: GridSpec, point: list[float]) -> float:
    index, inside = spec.cell_indices([point])
    assert inside[0]
    return float(grid_values[tuple(index[0])])


# --- beams ------------------------------------------------------------------------------


@pytest.mark.parametrize("fov_deg", [5.0, 18.06, 40.0])
def test_beam_table_is_the_piston_directivity_with_that_first_null(fov_deg: float) -> None:
    cos_null, table = beam_table(fov_deg)
    assert cos_null == pytest.approx(math.cos(math.radians(fov_deg)))
    # The piston of radius a at 50 kHz whose first null is at fov_deg.
    k = 2 * math.pi * 50e3 / C
    radius = 3.8317059702075125 / (k * math.sin(math.radians(fov_deg)))
    cos_t = np.linspace(cos_null, 1.0, len(table))
    expected = piston_directivity(np.arccos(cos_t), radius, 50e3, C)
    np.testing.assert_allclose(table, np.clip(expected, 0, 1), atol=1e-9)
    assert table[-1] == pytest.approx(1.0)
    assert table[0] == pytest.approx(0.0, abs=1e-9)


def test_half_power_angle_matches_the_transducer_module() -> None:
    k = 2 * math.pi * 50e3 / C
    radius = 3.8317059702075125 / (k * math.sin(math.radians(18.0)))
    expected = math.degrees(piston_half_angle_rad(radius, 50e3, C))
    assert half_power_angle_deg(18.0) == pytest.approx(expected, rel=1e-9)
    assert half_power_angle_deg(90.0) == 90.0


# --- grids --------------------------------------------------------------------------------


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(-0.999, 0.999), min_size=1, max_size=20),
    st.lists(st.floats(0.001, 1.999), min_size=1, max_size=20),
    st.sampled_from([0.005, 0.01, 0.037]),
)
def test_a_point_lies_in_the_cell_whose_centre_is_within_half_a_cell(
    xs: list[float], zs: list[float], cell: float
) -> None:
    spec = GridSpec.floor_plan((-1.0, 1.0), (0.0, 2.0), cell, height_m=0.3)
    n = min(len(xs), len(zs))
    points = np.column_stack([xs[:n], np.full(n, 0.3), zs[:n]])
    index, inside = spec.cell_indices(points)
    assert np.all(inside[:n])
    centres = spec.origin_m + (index + 0.5) * cell
    assert np.all(np.abs(centres - points) <= cell / 2 + 1e-12)
    assert spec.is_floor_plan
    assert spec.shape[1] == 1


def test_grid_refuses_impossible_specs() -> None:
    with pytest.raises(EchoLocError, match="cell size"):
        GridSpec(np.zeros(3), 0.0, (2, 2, 2))
    with pytest.raises(EchoLocError, match="too large"):
        GridSpec.box([0, 0, 0], [100, 100, 100], 0.001)
    with pytest.raises(EchoLocError, match="low < high"):
        GridSpec.floor_plan((1.0, 0.0), (0.0, 1.0), 0.01)


# --- the inverse sensor model ----------------------------------------------------------


def _monostatic_map(
    paths: list[list[float]], model: SensorModel | None = None
) -> tuple[GridSpec, np.ndarray, np.ndarray]:
    rec = _recording([[0.0, 0.0, 0.0]], fov_deg=20.0)
    spec = _floor()
    acc = MapAccumulator(spec, rec, model or SensorModel(min_support=1))
    acc.add_frame(_echoes(paths), IDENTITY)
    grid = acc.grid()
    return spec, grid.log_odds, grid.updates


def test_one_echo_clears_before_marks_the_arc_and_leaves_the_rest() -> None:
    # Transmitter and receiver at the origin: the echo of path 2 m is the circle r = 1 m.
    spec, log_odds, updates = _monostatic_map([[2.0]])
    assert _cell_value(log_odds, spec, [0.0, 0.0, 0.5]) < 0  # before the echo: free
    assert _cell_value(log_odds, spec, [0.0, 0.0, 1.0]) > 0  # on the arc: occupied
    tilted = [math.sin(math.radians(5)), 0.0, math.cos(math.radians(5))]
    assert _cell_value(log_odds, spec, tilted) > 0  # the arc, 5 degrees off the axis
    assert _cell_value(updates, spec, [0.0, 0.0, 1.3]) == 0  # beyond: unknown
    assert _cell_value(updates, spec, [0.6, 0.0, 0.6]) == 0  # outside the 20-degree beam: unknown
    # The arc is where the path is 2 m: occupied cells lie within the widened Gaussian of it.
    index = np.argwhere(log_odds > 0)
    centres = spec.origin_m + (index + 0.5) * spec.cell_m
    radius = np.linalg.norm(centres, axis=1)
    assert np.all(np.abs(radius - 1.0) <= 2 * math.hypot(0.002, spec.cell_m) / 2 + spec.cell_m)
    # Every arc cell holds the closed form p = 0.5 + 0.2 D(θ)² exp(-(L - 2)² / 2σ²), with
    # σ² = σ_path² + (|∇L| h / 2)² and |∇L| = 2 for a transducer that sends and receives.
    theta = np.arccos(centres[:, 2] / radius)
    cos_null, table = beam_table(20.0)
    gain = np.interp(np.cos(theta), np.linspace(cos_null, 1, len(table)), table) ** 2
    sigma2 = 0.002**2 + (2 * spec.cell_m / 2) ** 2
    expected = 0.5 + 0.2 * gain * np.exp(-0.5 * (2 * radius - 2.0) ** 2 / sigma2)
    measured = 1 / (1 + np.exp(-log_odds[tuple(index.T)].astype(float)))
    np.testing.assert_allclose(measured, expected, atol=2e-3)
    assert measured.max() > 0.6  # the cell nearest the arc on the axis


def test_no_echo_clears_to_the_clearing_range_and_marks_nothing() -> None:
    model = SensorModel(min_support=1, clear_fraction=0.5)
    spec, log_odds, updates = _monostatic_map([[]], model)
    window = N_SAMPLES / FS * C
    clear_range = 0.5 * window / 2
    assert not np.any(log_odds > 0)
    assert _cell_value(log_odds, spec, [0.0, 0.0, clear_range - 0.05]) < 0
    assert _cell_value(updates, spec, [0.0, 0.0, clear_range + 0.05]) == 0


def test_one_channels_clearing_does_not_erase_another_channels_echo_in_the_same_frame() -> None:
    # A ring of two sensors side by side, both looking ahead: rx 0 hears a reflector at
    # 0.8 m, rx 1 (4 cm to the side, same transmitter) hears nothing and clears its beam.
    rec = _recording([[0.0, 0.0, 0.0], [0.04, 0.0, 0.0]], fov_deg=20.0)
    spec = _floor()
    acc = MapAccumulator(spec, rec, SensorModel(min_support=1))
    acc.add_frame(_echoes([[1.6], []]), IDENTITY)
    grid = acc.grid()
    assert _cell_value(grid.log_odds, spec, [0.0, 0.0, 0.8]) > 0
    # Without the first channel the second one clears that cell.
    alone = MapAccumulator(spec, rec, SensorModel(min_support=1))
    alone.add_frame(_echoes([[], []]), IDENTITY)
    assert _cell_value(alone.grid().log_odds, spec, [0.0, 0.0, 0.8]) < 0


def test_an_arc_heard_by_one_receiver_only_is_not_marked_with_min_support_two() -> None:
    rec = _recording([[0.0, 0.0, 0.0], [0.25, 0.0, 0.0]], fov_deg=40.0)
    spec = _floor()
    acc = MapAccumulator(spec, rec, SensorModel(min_support=2))
    acc.add_frame(_echoes([[1.6], []]), IDENTITY)
    assert not np.any(acc.grid().log_odds > 0)
    # Both receivers hearing a reflector at (0, 0, 0.8) mark it.
    both = MapAccumulator(spec, rec, SensorModel(min_support=2))
    reflector = np.array([0.0, 0.0, 0.8])
    path_1 = float(np.linalg.norm(reflector) + np.linalg.norm(reflector - rec.receivers_m[1]))
    both.add_frame(_echoes([[1.6], [path_1]]), IDENTITY)
    grid = both.grid()
    assert _cell_value(grid.log_odds, spec, [0.0, 0.0, 0.8]) > 0
    # Along the arc of rx 0, where the two ellipses have parted by more than the arcs'
    # width (0.25 sin 15° = 6.5 cm of path against 3 σ = 3 cm), nothing is marked.
    for angle in (-15.0, 15.0):
        side = [0.8 * math.sin(math.radians(angle)), 0.0, 0.8 * math.cos(math.radians(angle))]
        assert _cell_value(grid.log_odds, spec, side) <= 0


def test_the_cell_holding_a_wall_is_the_one_marked_wherever_the_wall_lies_in_it() -> None:
    # One transducer, 5 cm cells: a wall anywhere inside the cell from z = 1.00 to 1.05
    # must mark that cell and clear the one before it, not the one behind.
    rec = _recording([[0.0, 0.0, 0.0]], fov_deg=20.0)
    spec = GridSpec.floor_plan((-0.5, 0.5), (0.0, 2.0), 0.05)
    for distance in np.linspace(1.0005, 1.0495, 9):
        acc = MapAccumulator(spec, rec, SensorModel(min_support=1))
        for _ in range(3):
            acc.add_frame(_echoes([[2 * distance]]), IDENTITY)
        grid = acc.grid()
        assert _cell_value(grid.log_odds, spec, [0.0, 0.0, distance]) > 0, distance
        assert _cell_value(grid.log_odds, spec, [0.0, 0.0, 0.9]) < 0, distance
        assert _cell_value(grid.updates, spec, [0.0, 0.0, 1.22]) == 0, distance


def test_scratch_counts_do_not_leak_into_the_next_frame() -> None:
    # With no beam-gain floor, far beam edges add arcs of zero evidence; a single
    # channel in the next frame must still not pass min_support = 2.
    rec = _recording([[0.0, 0.0, 0.0], [0.25, 0.0, 0.0]], fov_deg=40.0)
    spec = _floor()
    acc = MapAccumulator(spec, rec, SensorModel(min_support=2, min_beam_gain=0.0))
    acc.add_frame(_echoes([[1.6], [1.6]]), IDENTITY)
    acc.add_frame(_echoes([[1.2], []]), IDENTITY)
    lone = acc.grid().log_odds
    fresh = MapAccumulator(spec, rec, SensorModel(min_support=2, min_beam_gain=0.0))
    fresh.add_frame(_echoes([[1.6], [1.6]]), IDENTITY)
    # The second frame's lone arc at r = 0.6 m marks nothing.
    assert _cell_value(lone, spec, [0.0, 0.0, 0.6]) <= 0
    assert np.count_nonzero(lone > 0) <= np.count_nonzero(fresh.grid().log_odds > 0)


def _pose_yaw(deg: float) -> np.ndarray:
    q = Rotation.from_euler("y", deg, degrees=True).as_quat()
    return np.concatenate([[0.0, 0.0, 0.0], q])


def test_a_specular_wall_is_not_erased_by_oblique_silence_but_is_by_silence_along_its_normal() -> None:
    rec = _recording([[0.0, 0.0, 0.0]], fov_deg=18.0)
    spec = _floor()
    model = SensorModel(min_support=1)
    wall = [0.0, 0.0, 1.0]
    # Heard along the normal, then 30 frames of silence with the beam turned 10 degrees
    # (beyond the 7.4-degree half-power angle: a wall is silent there).
    oblique = MapAccumulator(spec, rec, model)
    for _ in range(5):
        oblique.add_frame(_echoes([[2.0]]), IDENTITY)
    for _ in range(30):
        oblique.add_frame(_echoes([[]]), _pose_yaw(10.0))
    assert _cell_value(oblique.grid().log_odds, spec, wall) > 0
    # The same silence along the normal (a reflector that went away) clears it.
    gone = MapAccumulator(spec, rec, model)
    for _ in range(5):
        gone.add_frame(_echoes([[2.0]]), IDENTITY)
    for _ in range(30):
        gone.add_frame(_echoes([[]]), _pose_yaw(2.0))
    assert _cell_value(gone.grid().log_odds, spec, wall) < 0


def test_log_odds_are_clamped() -> None:
    rec = _recording([[0.0, 0.0, 0.0]], fov_deg=20.0)
    spec = _floor()
    model = SensorModel(min_support=1)
    acc = MapAccumulator(spec, rec, model)
    for _ in range(60):
        acc.add_frame(_echoes([[2.0]]), IDENTITY)
    grid = acc.grid()
    low, high = model.clamp_probability
    assert float(grid.log_odds.max()) == pytest.approx(math.log(high / (1 - high)), rel=1e-6)
    assert float(grid.log_odds.min()) == pytest.approx(math.log(low / (1 - low)), rel=1e-6)


def test_a_pose_moves_the_arc_with_the_sensor() -> None:
    rec = _recording([[0.0, 0.0, 0.0]], fov_deg=20.0)
    spec = _floor()
    acc = MapAccumulator(spec, rec, SensorModel(min_support=1))
    # Turned 30 degrees about y (y down): the boresight points to +x, +z.
    pose = _pose_yaw(30.0)
    pose[:3] = [0.1, 0.0, 0.2]
    acc.add_frame(_echoes([[2.0]]), pose)
    grid = acc.grid()
    expected = np.array([0.1, 0.0, 0.2]) + np.array(
        [math.sin(math.radians(30)), 0.0, math.cos(math.radians(30))]
    )
    assert _cell_value(grid.log_odds, spec, list(expected)) > 0
    assert _cell_value(grid.updates, spec, [0.0, 0.0, 1.0]) == 0


def test_a_located_object_adds_a_blob_at_its_position() -> None:
    rec = _recording([[0.0, 0.0, 0.0]], fov_deg=20.0)
    spec = _floor()
    acc = MapAccumulator(spec, rec, SensorModel(min_support=1))
    point = np.array([0.303, 0.0, 1.507])
    obj = LocatedObject(point, np.diag([1e-6, 1e-6, 1e-6]), (0,), (0,), 0.0, 1.0)
    acc.add_frame(_echoes([[]]), IDENTITY, objects=FrameObjects(0, 0.0, (obj,)))
    grid = acc.grid()
    peak = np.unravel_index(int(np.argmax(grid.log_odds)), spec.shape)
    index, _ = spec.cell_indices([point])
    assert tuple(int(i) for i in peak) == tuple(int(i) for i in index[0])


def test_a_located_plane_adds_the_segment_its_echoes_met() -> None:
    """A plane (reflector classes) marks the cells of the rectangle spanned by its specular
    points, a segment across the floor plan along the wall, not a blob at its foot: every
    marked cell's centre lies within a cell of the plane, and the segment is as long as the
    points' spread."""
    rec = _recording([[0.0, 0.0, 0.0]], fov_deg=20.0)
    spec = _floor()
    acc = MapAccumulator(spec, rec, SensorModel(min_support=1))
    turn = math.radians(30.0)
    normal = np.array([-math.sin(turn), 0.0, -math.cos(turn)])  # towards the sensor
    foot = -1.2 * normal
    along = np.array([math.cos(turn), 0.0, -math.sin(turn)])  # in the plane, horizontal
    specular = foot + np.outer([-0.1, -0.03, 0.05, 0.1], along) + np.outer([0, 0.004, -0.004, 0], [0, 1, 0])
    surface = Surface(
        "plane",
        1.0,
        {"plane": 1.0},
        normal=normal,
        normal_covariance=np.zeros((3, 3)),
        distance_m=1.2,
        distance_std_m=1e-4,
        specular_points_m=specular,
        extent_m=0.2,
    )
    obj = LocatedObject(foot, np.diag([1e-6] * 3), (0,), (0,), 0.0, 1.0, surface=surface)
    acc.add_frame(_echoes([[]]), IDENTITY, objects=FrameObjects(0, 0.0, (obj,)))
    grid = acc.grid()
    marked = np.argwhere(grid.log_odds > 0)
    centres = spec.origin_m + (marked + 0.5) * spec.cell_m
    assert np.all(np.abs((centres - foot) @ normal) < spec.cell_m)
    spread = (centres - foot) @ along
    assert spread.min() == pytest.approx(-0.1, abs=spec.cell_m)
    assert spread.max() == pytest.approx(0.1, abs=spec.cell_m)
    assert 20 <= len(marked) <= 40  # 0.2 m of wall at 1 cm, a staircase of cells


# --- trajectories ------------------------------------------------------------------------


def test_trajectory_interpolates_position_linearly_and_rotation_by_slerp(tmp_path: Path) -> None:
    q1 = Rotation.from_euler("y", 60, degrees=True).as_quat()
    path = tmp_path / "traj.txt"
    path.write_text(
        f"# t x y z qx qy qz qw\n0 0 0 0 0 0 0 1\n2.0, 1, 0, 2, {q1[0]}, {q1[1]}, {q1[2]}, {q1[3]}\n"
    )
    trajectory = read_trajectory(path)
    pose = trajectory.at([1.0, 5.0])
    np.testing.assert_allclose(pose[0, :3], [0.5, 0.0, 1.0])
    angle = Rotation.from_quat(pose[0, 3:]).magnitude()
    assert math.degrees(angle) == pytest.approx(30.0)
    np.testing.assert_allclose(pose[1, :3], [1.0, 0.0, 2.0])  # held after the end


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("0 0 0 0 0 0 0\n", "expected 8 values"),
        ("0 0 0 0 0 0 0 x\n", "not a number"),
        ("0 0 0 0 0 0 0 2\n", "unit length"),
        ("1 0 0 0 0 0 0 1\n0 0 0 0 0 0 0 1\n", "increase"),
        ("# nothing\n", "no poses"),
    ],
)
def test_bad_trajectories_are_refused_in_one_line(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(EchoLocError, match=message):
        read_trajectory(path)


def test_frame_poses_prefer_the_trajectory_then_the_recording() -> None:
    rec = _recording([[0.0, 0.0, 0.0]])
    np.testing.assert_array_equal(frame_poses(rec), IDENTITY[None, :])
    trajectory = Trajectory(
        np.array([0.0, 1.0]), np.array([[1, 2, 3, 0, 0, 0, 1.0], [1, 2, 3, 0, 0, 0, 1.0]])
    )
    np.testing.assert_allclose(frame_poses(rec, trajectory)[0, :3], [1, 2, 3])


# --- scanning and a simulated room ---------------------------------------------------------


def _wall_scene(motion: SensorMotion) -> Scene:
    array = Array(
        transmitters_m=np.zeros((1, 3)),
        receivers_m=np.array([[0.25, 0, 0], [-0.25, 0, 0], [0, 0.25, 0], [0, -0.25, 0.0]]),
    )
    wall = Plane(
        centre_m=np.array([0.0, -0.25, 1.2]),
        normal=np.array([0.0, 0.0, -1.0]),
        width_m=2.4,
        height_m=1.5,
        width_axis=np.array([1.0, 0.0, 0.0]),
        reflection=0.95,
    )
    pole = Edge(np.array([-0.35, -1.0, 0.8]), np.array([-0.35, 0.5, 0.8]), 0.2)
    return Scene(
        array=array,
        objects=(wall, pole),
        transducer="electrostatic50",
        snr_db=20.0,
        seed=5,
        motion=motion,
    )


@pytest.fixture(scope="module")
def scanned_wall() -> tuple[Scene, Recording]:
    # The head slides 0.5 m to the right while panning +-30 degrees every 2 s.
    scene = _wall_scene(SensorMotion(velocity_m_s=np.array([0.1, 0.0, 0.0]), pan_deg=30.0, scan_period_s=2.0))
    return scene, simulate(scene, 500)


def test_simulated_scan_maps_the_wall_within_a_cell_and_no_ghosts_in_free_space(
    scanned_wall: tuple[Scene, Recording],
) -> None:
    scene, rec = scanned_wall
    chain = pipeline.prepare(rec)
    results = list(pipeline.run(chain))
    cell = 0.02
    spec = GridSpec.floor_plan((-1.0, 1.5), (0.0, 1.6), cell)
    grid = build_map(rec, results, spec)
    surface = surface_points_m(scene.objects, cell / 4)
    heard = seen_truth_points_m(rec, [e for e, _ in results], tolerance_m=0.02)
    seen = seen_surface_points_m(surface, heard, spec)
    assert len(seen) > 100  # at least half a metre of wall
    xs, zs = spec.centres_m(0), spec.centres_m(2)
    x, z = np.meshgrid(xs, zs, indexing="ij")
    free = (z < 1.2 - 2 * cell) & (np.hypot(x + 0.35, z - 0.8) > 2 * cell)
    accuracy = map_accuracy(grid, surface, seen, free_space=free[:, None, :])
    assert accuracy.coverage >= 0.9
    assert accuracy.ghost_fraction <= 0.01
    assert accuracy.free_cells > 1000


def test_a_pan_scan_widens_what_a_narrow_beam_sees(scanned_wall: tuple[Scene, Recording]) -> None:
    _scene, _ = scanned_wall
    fixed = simulate(_wall_scene(SensorMotion(velocity_m_s=np.array([1e-9, 0.0, 0.0]))), 100)
    panned = simulate(
        _wall_scene(SensorMotion(velocity_m_s=np.array([1e-9, 0.0, 0.0]), pan_deg=40.0, scan_period_s=1.0)),
        100,
    )
    spec = GridSpec.floor_plan((-1.5, 1.5), (0.0, 2.0), 0.02)
    areas = []
    for rec in (fixed, panned):
        chain = pipeline.prepare(rec)
        grid = build_map(rec, list(pipeline.run(chain)), spec)
        areas.append(grid.known().sum() * 0.02**2)
    # An 18-degree beam sweeps (18 + 40) / 18 ~ 3 times the angle.
    assert areas[1] > 2.0 * areas[0]


@settings(max_examples=40, deadline=None)
@given(
    st.floats(-180, 180),
    st.floats(-0.3, 0.3),
    st.lists(st.floats(0.6, 3.5), min_size=0, max_size=3),
    st.booleans(),
    st.sampled_from([8.0, 25.0, 90.0]),
)
def test_compiled_channel_update_equals_its_numpy_statement(
    yaw_deg: float, rx_x: float, paths: list[float], heard_before: bool, fov_deg: float
) -> None:
    """The kernel, on the float32/int32 scratch the accumulator uses and inside the bounds
    the accumulator gives it, touches exactly the cells the numpy statement does on the
    whole grid, with the same evidence, clearing, support and near-axis marks."""
    from echoloc.maps import _mapping_kernels as kernels
    from echoloc.maps.mapping import _cone_bounds, channel_window

    spec = GridSpec.box([-1.0, -0.3, 0.0], [1.0, 0.3, 2.0], 0.05)
    shape = np.array(spec.shape, dtype=np.int64)
    n = spec.n_cells
    rotation = Rotation.from_euler("yx", [yaw_deg, 0.3 * yaw_deg], degrees=True).as_matrix()
    tx, rx = np.array([0.0, 0.0, 1.0]), np.array([rx_x, 0.0, 1.0])
    tx_axis = rotation @ [0.0, 0.0, 1.0]
    rx_axis = rotation @ [0.0, 0.1, 1.0]
    rx_axis /= np.linalg.norm(rx_axis)
    cos_null, table = beam_table(fov_deg)
    echo_paths = np.sort(np.array(paths))
    free_below, margin, reach = channel_window(echo_paths, 2.5, 0.002, spec.cell_m, 2.0)
    bounds = _cone_bounds(spec, tx, tx_axis, math.radians(fov_deg), (reach + abs(rx_x)) / 2)
    hit_axes = np.zeros((n, 3), np.float32)
    if heard_before:
        hit_axes[:] = [1.0, 0.0, 0.0]
    model = (
        cos_null,
        table,
        0.1,
        free_below,
        margin,
        0.2,
        echo_paths,
        0.002,
        2.0,
        reach,
        0.2,
        math.log(0.4 / 0.6),
    )
    head = (spec.origin_m, spec.cell_m, shape)
    geometry = (tx, rx, tx_axis, rx_axis)
    clear_cos = math.cos(math.radians(7.4))
    cells, ref_occupied, ref_free, ref_arc, ref_central = channel_update_reference(
        *head, np.zeros(3, np.int64), shape, *geometry, *model, hit_axes, clear_cos, 0.05
    )
    if bounds is None:
        assert len(cells) == 0
        return
    occupied, free = np.zeros(n, np.float32), np.zeros(n, np.float32)
    support, central = np.zeros(n, np.uint8), np.zeros(n, np.uint8)
    stamp = np.full(n, -1, np.int32)
    touched = np.zeros(n, np.int32)
    count = kernels.channel_update(
        *head,
        *bounds,
        *geometry,
        *model,
        occupied,
        free,
        support,
        central,
        hit_axes,
        clear_cos,
        0.05,
        stamp,
        0,
        touched,
        0,
    )
    assert sorted(touched[:count].tolist()) == sorted(cells.tolist())
    np.testing.assert_allclose(occupied[cells], ref_occupied, rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(free[cells], ref_free, rtol=1e-5, atol=1e-6)
    np.testing.assert_array_equal(support[cells], ref_arc.astype(np.uint8))
    np.testing.assert_array_equal(central[cells], ref_central.astype(np.uint8))


# --- the grid echoloc map fills ------------------------------------------------------------


def test_the_chosen_grid_covers_what_the_sensor_can_hear_and_obeys_extent_and_height() -> None:
    """Without an extent, a floor plan reaches (path + baseline)/2 + head size beyond every
    pose, at the poses' mean height; an extent and a height are taken as given; a 3-D box
    takes a height for no axis."""
    from echoloc.maps.mapping import choose_grid
    from echoloc.sim.scene import default_scene

    recording = simulate(default_scene(), 1)
    c = 343.0
    poses = np.array([[0.0, 0.1, 0.0, 0, 0, 0, 1], [0.4, 0.3, 0.2, 0, 0, 0, 1]])
    heard = recording.n_samples / recording.sample_rate_hz * c
    baseline = np.max(np.linalg.norm(recording.transmitters_m[:, None] - recording.receivers_m[None], axis=2))
    size = np.max(np.linalg.norm(np.vstack([recording.transmitters_m, recording.receivers_m]), axis=1))
    reach = (heard + baseline) / 2 + size
    plan = choose_grid(recording, poses, 0.05, c)
    assert plan.shape[1] == 1
    assert plan.origin_m[0] <= -reach + 1e-9
    assert plan.upper_m[0] >= 0.4 + reach - 0.05 - 1e-9
    assert plan.origin_m[2] <= -reach + 1e-9
    assert plan.upper_m[2] >= 0.2 + reach - 0.05 - 1e-9
    assert plan.origin_m[1] + plan.cell_m / 2 == pytest.approx(0.2)  # the mean height, y
    given_plan = choose_grid(recording, poses, 0.1, c, extent_m=[(-1.0, 1.0), (0.0, 2.0)], height_m=0.5)
    assert given_plan.shape == (20, 1, 20)
    assert given_plan.origin_m[1] + given_plan.cell_m / 2 == pytest.approx(0.5)
    box = choose_grid(recording, poses, 0.1, c, three_d=True, extent_m=[(-1, 1), (-0.5, 0.5), (0, 2)])
    assert box.shape == (20, 10, 20)
    with pytest.raises(EchoLocError, match="3-D grid"):
        choose_grid(recording, poses, 0.1, c, three_d=True, height_m=0.5)
