"""Map exports, each read back with an independent reader: numpy, plyfile, pyoctomap, mcap_ros2."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pyoctomap
import pytest
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from plyfile import PlyData
from scipy.spatial.transform import Rotation

from echoloc.cli import commands as cli
from echoloc.errors import EchoLocError
from echoloc.io.export import BODY_FRAME_ID, ODOM_FRAME_ID, ROS_MAP_FRAME_ID
from echoloc.io.recording import write_recording
from echoloc.maps.map_export import (
    MAP_CLOUD_TOPIC,
    MAP_TOPIC,
    TF_TOPIC,
    read_grid_npz,
    write_grid_npz,
    write_grid_ply,
    write_map_mcap,
    write_octomap,
)
from echoloc.maps.mapping import GridSpec, OccupancyGrid, SensorModel
from echoloc.sim.reflectors import Plane
from echoloc.sim.scene import Array, Scene, SensorMotion
from echoloc.sim.simulation import simulate


def _grid(spec: GridSpec, seed: int = 1) -> OccupancyGrid:
    """A grid with free, occupied and unknown cells at random."""
    rng = np.random.default_rng(seed)
    log_odds = rng.uniform(-1.9, 3.4, spec.shape).astype(np.float32)
    updates = rng.integers(0, 3, spec.shape).astype(np.uint16)
    return OccupancyGrid(spec, log_odds, updates, SensorModel(), frames=7)


FLOOR = GridSpec.floor_plan((-0.5, 0.5), (0.0, 0.8), 0.05, height_m=0.1)
BOX = GridSpec.box([-0.2, -0.1, 0.3], [0.2, 0.1, 0.6], 0.05)


def _read_mcap(path: Path) -> list[tuple[str, str, Any]]:
    with path.open("rb") as stream:
        reader = make_reader(stream, decoder_factories=[DecoderFactory()])
        return [(c.topic, s.name, m) for s, c, _, m in reader.iter_decoded_messages()]


def test_npz_round_trip_is_exact(tmp_path: Path) -> None:
    grid = _grid(BOX)
    back = read_grid_npz(write_grid_npz(grid, tmp_path / "g.npz"))
    np.testing.assert_array_equal(back.log_odds, grid.log_odds)
    np.testing.assert_array_equal(back.updates, grid.updates)
    np.testing.assert_array_equal(back.spec.origin_m, grid.spec.origin_m)
    assert back.spec.shape == grid.spec.shape
    assert back.frames == 7


def test_ply_holds_the_occupied_cells_with_their_probability(tmp_path: Path) -> None:
    grid = _grid(BOX)
    ply = PlyData.read(str(write_grid_ply(grid, tmp_path / "g.ply")))
    vertex = ply["vertex"]
    points = np.column_stack([vertex["x"], vertex["y"], vertex["z"]])
    np.testing.assert_allclose(points, grid.occupied_centres_m(), atol=1e-6)
    np.testing.assert_allclose(vertex["intensity"], grid.probability()[grid.occupied()], atol=1e-6)
    np.testing.assert_allclose(vertex["cov_xx"], 0.05**2 / 12, rtol=1e-5)


@pytest.mark.parametrize("suffix", [".bt", ".ot"])
def test_octomap_leaves_are_the_grids_cells(tmp_path: Path, suffix: str) -> None:
    grid = _grid(BOX)
    path = write_octomap(grid, tmp_path / f"g{suffix}")
    tree = pyoctomap.OcTree(0.1)
    if suffix == ".bt":
        assert tree.readBinary(str(path))
    else:
        tree = tree.read(str(path))
    assert tree.getResolution() == pytest.approx(0.05)
    known = np.argwhere(grid.known())
    centres = grid.spec.origin_m + (known + 0.5) * grid.spec.cell_m
    for cell, centre in zip(known[::7], centres[::7], strict=True):
        node = tree.search(centre)
        assert node is not None
        occupied = bool(grid.log_odds[tuple(cell)] > 0)
        assert tree.isNodeOccupied(node) == occupied
        if suffix == ".ot":  # full probabilities kept
            assert node.getLogOdds() == pytest.approx(float(grid.log_odds[tuple(cell)]), abs=1e-5)
    unknown = np.argwhere(~grid.known())[0]
    assert tree.search(grid.spec.origin_m + (unknown + 0.5) * grid.spec.cell_m) is None


def test_mcap_floor_plan_decodes_to_the_grid(tmp_path: Path) -> None:
    grid = _grid(FLOOR)
    q = Rotation.from_euler("y", 20, degrees=True).as_quat()  # a turn about echoloc's world y (down)
    poses = np.array([[0.0, 0.0, 0.0, 0, 0, 0, 1], [0.1, 0.0, 0.05, *q]])
    count = write_map_mcap(tmp_path / "m.mcap", grid, poses=poses, frame_times_s=np.array([0.0, 0.01]))
    messages = _read_mcap(tmp_path / "m.mcap")
    assert count == len(messages) == 4  # /tf_static, two /tf, the map
    tfs = [m for topic, _, m in messages if topic == TF_TOPIC]
    assert [t.transforms[0].header.frame_id for t in tfs] == [ODOM_FRAME_ID] * 2
    assert tfs[1].transforms[0].child_frame_id == BODY_FRAME_ID
    moved = tfs[1].transforms[0].transform
    # The body moved 0.1 m to the sensor's right (map -y) and 0.05 m ahead (map +x) ...
    tr = moved.translation
    np.testing.assert_allclose([tr.x, tr.y, tr.z], [0.05, -0.1, 0.0], atol=1e-12)
    # ... and turned 20 degrees about the downward y: clockwise seen from above, a yaw of -20 degrees.
    r = moved.rotation
    np.testing.assert_allclose(
        Rotation.from_quat([r.x, r.y, r.z, r.w]).as_euler("zyx", degrees=True), [-20, 0, 0], atol=1e-9
    )
    ((_topic, schema, msg),) = [m for m in messages if m[0] == MAP_TOPIC]
    assert schema == "nav_msgs/msg/OccupancyGrid"
    assert msg.header.frame_id == ROS_MAP_FRAME_ID
    nx, _, nz = FLOOR.shape
    assert (msg.info.width, msg.info.height) == (nz, nx)  # columns along map x (ahead), rows along map y
    o = msg.info.origin
    assert (o.orientation.x, o.orientation.y, o.orientation.z, o.orientation.w) == (0, 0, 0, 1)
    cells = np.array(msg.data, dtype=np.int8).reshape(msg.info.height, msg.info.width)
    expected = np.where(grid.known()[:, 0, :], np.rint(100 * grid.probability()[:, 0, :]), -1)
    # Row r, column c is the grid's cell (nx - 1 - r, 0, c): its centre lies where that cell's does.
    np.testing.assert_array_equal(cells, expected[::-1, :])
    for r, c in [(0, 0), (3, 5), (nx - 1, nz - 1)]:
        offset = np.array([(c + 0.5) * 0.05, (r + 0.5) * 0.05, 0.0])
        centre_map = np.array([o.position.x, o.position.y, o.position.z]) + offset
        centre_world = FLOOR.origin_m + (np.array([nx - 1 - r, 0, c]) + 0.5) * 0.05
        # map x = world z (ahead), map y = -world x (left), map z = -world y (up)
        np.testing.assert_allclose(
            centre_map, [centre_world[2], -centre_world[0], -centre_world[1]], atol=1e-9
        )
    assert o.position.z == pytest.approx(-0.1)  # the floor plan's height, 0.1 m below (y down)


def test_mcap_of_a_3d_grid_is_a_cloud_of_its_occupied_cells(tmp_path: Path) -> None:
    grid = _grid(BOX)
    write_map_mcap(tmp_path / "m.mcap", grid)
    ((_, schema, msg),) = [m for m in _read_mcap(tmp_path / "m.mcap") if m[0] == MAP_CLOUD_TOPIC]
    assert schema == "sensor_msgs/msg/PointCloud2"
    assert msg.header.frame_id == ROS_MAP_FRAME_ID
    table = np.frombuffer(bytes(msg.data), dtype="<f4").reshape(msg.width, len(msg.fields))
    world = grid.occupied_centres_m()
    np.testing.assert_allclose(
        table[:, :3], np.column_stack([world[:, 2], -world[:, 0], -world[:, 1]]), atol=1e-6
    )


# --- the command ------------------------------------------------------------------------


def _run(capsys: pytest.CaptureFixture[str], *args: object) -> tuple[int, str, str]:
    """``echoloc ARGS`` in-process: exit code, stdout, stderr."""
    capsys.readouterr()
    with pytest.raises(SystemExit) as info:
        cli.main([str(a) for a in args])
    out, err = capsys.readouterr()
    assert isinstance(info.value.code, int)
    return info.value.code, out, err


@pytest.fixture(scope="module")
def panned_wall(tmp_path_factory: pytest.TempPathFactory) -> Path:
    array = Array(
        transmitters_m=np.zeros((1, 3)),
        receivers_m=np.array([[0.25, 0, 0], [-0.25, 0, 0], [0, 0.25, 0], [0, -0.25, 0.0]]),
    )
    wall = Plane(
        centre_m=np.array([0.0, -0.25, 1.0]),
        normal=np.array([0.0, 0.0, -1.0]),
        width_m=2.0,
        height_m=1.5,
        width_axis=np.array([1.0, 0.0, 0.0]),
    )
    scene = Scene(
        array=array,
        objects=(wall,),
        transducer="electrostatic50",
        snr_db=20.0,
        seed=3,
        motion=SensorMotion(velocity_m_s=np.array([0.1, 0.0, 0.0]), pan_deg=20.0, scan_period_s=1.0),
    )
    path = tmp_path_factory.mktemp("map") / "wall.h5"
    write_recording(simulate(scene, 120), path)
    return path


@pytest.mark.parametrize("suffix", [".png", ".npz", ".ply", ".bt", ".ot", ".mcap", ".yaml"])
def test_map_command_writes_each_format(
    capsys: pytest.CaptureFixture[str], panned_wall: Path, tmp_path: Path, suffix: str
) -> None:
    out = tmp_path / f"map{suffix}"
    code, stdout, stderr = _run(capsys, "map", panned_wall, "-o", out, "--extent-m=-1,1,0,1.5")
    assert code == 0, stderr
    assert "120 frames mapped" in " ".join(stdout.split())
    assert out.stat().st_size > 0
    if suffix == ".npz":
        grid = read_grid_npz(out)
        assert grid.frames == 120
        # The wall at z = 1.0 is occupied, the space before it free.
        occupied = grid.occupied_centres_m()
        assert len(occupied) > 10
        assert np.median(np.abs(occupied[:, 2] - 1.0)) <= grid.spec.cell_m
    if suffix == ".png":
        assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    if suffix == ".ply":
        vertex = PlyData.read(str(out))["vertex"]
        assert len(vertex["z"]) > 10
        assert np.median(np.abs(np.asarray(vertex["z"]) - 1.0)) <= 0.02
        assert np.all(np.asarray(vertex["intensity"]) > 0.5)
    if suffix in (".bt", ".ot"):
        tree = pyoctomap.OcTree(0.1)
        if suffix == ".bt":
            assert tree.readBinary(str(out))
        else:
            tree = tree.read(str(out))
        node = tree.search(np.array([0.0, 0.0, 1.0]))
        assert node is not None
        assert tree.isNodeOccupied(node)  # the wall straight ahead
        assert not tree.isNodeOccupied(tree.search(np.array([0.0, 0.0, 0.8])))  # free before it
    if suffix == ".mcap":
        messages = _read_mcap(out)
        assert sum(topic == TF_TOPIC for topic, _, _ in messages) == 120
        ((_, _, grid_msg),) = [m for m in messages if m[0] == MAP_TOPIC]
        assert max(grid_msg.data) > 50
    if suffix == ".yaml":
        # nav2's map files: the wall 1 m ahead of the sensor is at map x = 1 m (x forward).
        from PIL import Image

        assert "map.pgm" in " ".join(stdout.split())
        meta = dict(line.split(": ", 1) for line in out.read_text().splitlines())
        assert meta["image"] == "map.pgm"
        resolution = float(meta["resolution"])
        origin_x, origin_y, _ = (float(v) for v in meta["origin"].strip("[]").split(","))
        with Image.open(tmp_path / "map.pgm") as image:
            pixels = np.asarray(image)
        rows, columns = np.nonzero(pixels == 0)
        assert len(rows) > 10
        x = origin_x + (columns + 0.5) * resolution
        y = origin_y + (pixels.shape[0] - 1 - rows + 0.5) * resolution
        assert np.median(np.abs(x - 1.0)) <= resolution
        assert np.all(np.abs(y) < 1.0)  # within the 2 m wide wall, across the map's y
        # Free space (254) was heard between the sensor and the wall.
        _, free_columns = np.nonzero(pixels == 254)
        assert np.sum(origin_x + (free_columns + 0.5) * resolution < 0.9) > 100


def test_map_command_3d_and_trajectory(
    capsys: pytest.CaptureFixture[str], panned_wall: Path, tmp_path: Path
) -> None:
    trajectory = tmp_path / "traj.txt"
    trajectory.write_text("0 0 0 0 0 0 0 1\n10 0 0 0 0 0 0 1\n")
    out = tmp_path / "map.npz"
    code, _, stderr = _run(
        capsys, "map", panned_wall, "-o", out, "--3d", "--cell-m", "0.05", "--trajectory", trajectory
    )
    assert code == 0, stderr
    grid = read_grid_npz(out)
    assert grid.spec.shape[1] > 1
    # Identity poses: the beam never left the boresight, so nothing far to the side was heard.
    centres = grid.spec.origin_m + (np.argwhere(grid.known()) + 0.5) * grid.spec.cell_m
    angle = np.degrees(np.arctan2(np.hypot(centres[:, 0], centres[:, 1]), centres[:, 2]))
    assert angle.max() < 25


def test_map_command_stamps_objects_with_their_own_frames_time(
    capsys: pytest.CaptureFixture[str], panned_wall: Path, tmp_path: Path
) -> None:
    out = tmp_path / "sub.mcap"
    code, _, stderr = _run(capsys, "map", panned_wall, "-o", out, "--frames", "40:60")
    assert code == 0, stderr
    messages = _read_mcap(out)
    stamps = [
        m.header.stamp.sec + m.header.stamp.nanosec * 1e-9 for t, _, m in messages if t == "/echoloc/objects"
    ]
    tfs = [m.transforms[0].header.stamp for t, _, m in messages if t == TF_TOPIC]
    # 100 frames a second: frame k at k / 100 s.
    np.testing.assert_allclose(stamps, np.arange(40, 60) / 100, atol=1e-9)
    assert len(tfs) == 20


@pytest.mark.filterwarnings("always::echoloc.maps.mapping.MapWarning")
def test_a_trajectory_that_misses_every_frame_is_refused_and_a_partial_one_warned(
    capsys: pytest.CaptureFixture[str], panned_wall: Path, tmp_path: Path
) -> None:
    late = tmp_path / "late.txt"
    late.write_text("100 0 0 0 0 0 0 1\n101 0.5 0 0 0 0 0 1\n")
    code, _, stderr = _run(capsys, "map", panned_wall, "-o", tmp_path / "a.npz", "--trajectory", late)
    assert code == 2
    assert "cover none of the frames" in stderr
    part = tmp_path / "part.txt"
    part.write_text("0 0 0 0 0 0 0 1\n0.5 0 0 0 0 0 0 1\n")
    code, _, stderr = _run(capsys, "map", panned_wall, "-o", tmp_path / "b.npz", "--trajectory", part)
    assert code == 0
    assert "69 of 120 frames fall outside" in stderr


@pytest.mark.filterwarnings("always::echoloc.maps.mapping.MapWarning")
def test_a_map_with_nothing_in_reach_says_so(
    capsys: pytest.CaptureFixture[str], panned_wall: Path, tmp_path: Path
) -> None:
    code, _, stderr = _run(
        capsys, "map", panned_wall, "-o", tmp_path / "far.npz", "--extent-m", "100,101,100,101"
    )
    assert code == 0
    assert "within reach of the sensor" in stderr


def test_an_unaligned_floor_plan_still_gives_one_octomap_voxel_per_cell(tmp_path: Path) -> None:
    from echoloc.maps.map_export import voxel_centres_m

    # The layer is centred on y = 0 with 2 cm cells: its centre sits on an OctoMap voxel
    # edge, where writing cell centres could send two cells to one voxel and add their
    # log-odds.
    spec = GridSpec.floor_plan((-0.99, 0.99), (0.01, 0.99), 0.02, height_m=0.0)
    grid = _grid(spec, seed=4)
    tree = pyoctomap.OcTree(0.1).read(str(write_octomap(grid, tmp_path / "g.ot")))
    known = np.argwhere(grid.known())
    centres = voxel_centres_m(spec, known)
    assert len(np.unique(np.floor(centres / 0.02).astype(int), axis=0)) == len(known)
    for cell, centre in zip(known[::5], centres[::5], strict=True):
        node = tree.search(centre)
        assert node.getLogOdds() == pytest.approx(float(grid.log_odds[tuple(cell)]), abs=1e-5)
    # Each voxel centre is within half a cell of its cell's centre.
    own = spec.origin_m + (known + 0.5) * spec.cell_m
    assert np.max(np.abs(centres - own)) <= spec.cell_m / 2 + 1e-12


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["-o", "map.txt"], "choose the format by extension"),
        (["-o", "map.png", "--3d", "--height-m", "0.1"], "--height-m"),
        (["-o", "map.yaml", "--3d"], "drop --3d"),
        (["-o", "map.png", "--method", "backprojection"], "--method backprojection"),
        (["-o", "nowhere/map.png"], "does not exist"),
        (["-o", "map.png", "--cell-m", "0"], "--cell-m"),
        (["-o", "map.png", "--extent-m", "1,2,3"], "--extent-m"),
        (["-o", "map.png", "--extent-m", "1,0,0,1"], "low to high"),
        (["-o", "map.png", "--trajectory", "missing.txt"], "no such trajectory"),
    ],
)
def test_map_command_refuses_bad_input_in_one_line(
    capsys: pytest.CaptureFixture[str], panned_wall: Path, tmp_path: Path, args: list[str], message: str
) -> None:
    args = [a if not a.startswith("map.") else str(tmp_path / a) for a in args]
    code, _, stderr = _run(capsys, "map", panned_wall, *args)
    assert code == 2
    assert message in stderr
    assert "Traceback" not in stderr
    assert len([line for line in stderr.splitlines() if line.strip()]) == 1


def test_a_grid_file_that_is_no_grid_or_a_device_is_one_error(tmp_path: Path) -> None:
    """Only a regular file is read as a grid (a device never ends), and a zip archive that
    declares more than the limit unpacked is refused from its directory, before unpacking."""
    import zipfile

    from echoloc.maps import map_export

    with pytest.raises(EchoLocError, match="not a regular file"):
        read_grid_npz("/dev/zero")
    junk = tmp_path / "junk.npz"
    junk.write_bytes(b"not a zip archive")
    with pytest.raises(EchoLocError, match=r"junk\.npz: not an echoloc grid"):
        read_grid_npz(junk)
    bomb = tmp_path / "bomb.npz"
    with zipfile.ZipFile(bomb, "w", compression=zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("log_odds.npy", bytes(map_export.MAX_GRID_BYTES // 1024 + 1))
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(map_export, "MAX_GRID_BYTES", 100_000)  # the file itself is about 4 kB
        with pytest.raises(EchoLocError, match=r"bomb\.npz: unpacks to .* over the limit"):
            read_grid_npz(bomb)


def test_map_and_batch_map_place_single_receiver_echoes_unless_told_not_to(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    """The room's first 130 frames: the box's near-left edge is heard by one receiver at a time
    while the robot drives and the head turns, and the tracks place it (docs/METHOD.md §8).
    --no-tracks maps as before them; `batch map` takes the same switch and writes the same
    grid as `map`."""
    from echoloc.maps.map_export import read_grid_npz
    from echoloc.sim.scenefile import load_scene, preset_path

    room = tmp_path / "room.h5"
    write_recording(simulate(load_scene(preset_path("mapping/room")), 130), room)
    grids = {}
    for switch in ("--tracks", "--no-tracks"):
        out = tmp_path / f"serial{switch}.npz"
        code, stdout, stderr = _run(capsys, "map", room, "-o", out, switch)
        assert code == 0, stderr
        assert ("placed by tracks across poses" in " ".join(stdout.split())) == (switch == "--tracks")
        grids[switch] = read_grid_npz(out)
        code, _, stderr = _run(capsys, "batch", "map", room, "--workers", 1, "-o", tmp_path / switch, switch)
        assert code == 0, stderr
        batch = read_grid_npz(tmp_path / switch / "room.map.npz")
        np.testing.assert_array_equal(batch.log_odds, grids[switch].log_odds)
    # The edge at (0.2, 1.1) m of the floor plan: marked with tracks only.
    spec = grids["--tracks"].spec
    index, inside = spec.cell_indices([[0.2, 0.0, 1.1]])
    assert inside[0]
    near = tuple(slice(max(i - 1, 0), i + 2) for i in index[0])
    assert grids["--tracks"].occupied()[near].any()
    assert not grids["--no-tracks"].occupied()[near].any()
