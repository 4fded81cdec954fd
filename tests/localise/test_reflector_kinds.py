"""Locating with reflector classes (``--classes``) on simulated rooms: walls as planes, corners
at their edges, posts as edges, double reflections explained away."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from echoloc.cli.commands import main
from echoloc.io.output import objects_record
from echoloc.io.recording import Recording, write_recording
from echoloc.localise.evaluation import evaluate_classes
from echoloc.localise.locate import FrameObjects, LocatedObject
from echoloc.localise.surfaces import Surface
from echoloc.pipeline import prepare, run
from echoloc.sim.reflectors import Edge, Plane, PointReflector, corner, truth_kinds
from echoloc.sim.scene import Scene
from echoloc.sim.scenefile import load_scene, preset_path
from echoloc.sim.simulation import _objects, simulate
from echoloc.tof.echoes import ChannelEchoes, FrameEchoes

SECOND_TRANSMITTER_M = (0.12, 0.12, 0.0)


def _with_transmitters(scene: Scene, n_tx: int) -> Scene:
    first = scene.array.transmitters_m[:1]
    transmitters = first if n_tx == 1 else np.vstack([first, SECOND_TRANSMITTER_M])
    return dataclasses.replace(scene, array=dataclasses.replace(scene.array, transmitters_m=transmitters))


def _located(recording: Recording, classes: bool = True) -> list[FrameObjects]:
    chain = prepare(recording)
    options = dataclasses.replace(chain.locate_options, reflector_classes=classes)
    return [objects for _, objects in run(dataclasses.replace(chain, locate_options=options))]


def _nearest(frame: FrameObjects, position: np.ndarray) -> tuple[float, LocatedObject]:
    distances = [float(np.linalg.norm(o.position_m - position)) for o in frame.objects]
    k = int(np.argmin(distances))
    return distances[k], frame.objects[k]


@pytest.fixture(scope="module")
def corridor() -> Scene:
    return load_scene(preset_path("rooms/corridor"))


def test_the_corridor_with_one_transmitter(corridor: Scene) -> None:
    """15 degrees off the boresight one transmitter cannot tell the end wall or the corner
    decisively from a point: both stay points within 1 cm of their feet, with a point
    probability below one half; the post is a point; nothing else is reported."""
    recording = simulate(_with_transmitters(corridor, 1), 6)
    assert recording.truth_positions_m is not None
    truth = recording.truth_positions_m[0]
    for frame in _located(recording):
        for row in (1, 3):  # the end wall's foot, the corner's edge
            distance, found = _nearest(frame, truth[row])
            assert distance < 0.01
            assert found.surface is not None
            assert found.surface.kind == "point"
            assert found.surface.confidence < 0.5
        distance, post = _nearest(frame, truth[0])
        assert distance < 3e-3
        assert post.surface is not None
        assert post.surface.kind == "point"
        assert post.surface.confidence > 0.9
        assert len(frame.objects) == 3


def test_a_wall_far_off_the_boresight_is_a_plane_with_one_transmitter() -> None:
    """40 degrees off the boresight the wavefront's curvature tells: a plane, its normal within
    0.1 degree and its distance within 1 mm."""
    turn = math.radians(40.0)
    normal = np.array([-math.sin(turn), 0.0, -math.cos(turn)])
    wall = Plane(centre_m=-1.2 * normal, normal=normal, width_m=3.0, height_m=2.0)
    scene = dataclasses.replace(
        _with_transmitters(load_scene(preset_path("rooms/corridor")), 1),
        objects=(wall,),
        reflector_positions_m=np.zeros((0, 3)),
        reflector_strengths=np.zeros(0),
    )
    for frame in _located(simulate(scene, 4)):
        distance, found = _nearest(frame, -1.2 * normal)
        assert distance < 1e-3
        assert found.surface is not None
        assert found.surface.kind == "plane"
        assert found.surface.normal is not None
        assert math.degrees(math.acos(min(1.0, found.surface.normal @ normal))) < 0.1
        assert found.surface.distance_m == pytest.approx(1.2, abs=1e-3)


def test_the_corridor_with_two_transmitters_finds_the_corner(corridor: Scene) -> None:
    """Once both transmitters have fired, the corner is a corner with a vertical edge."""
    recording = simulate(_with_transmitters(corridor, 2), 6)
    assert recording.truth_positions_m is not None
    for frame in _located(recording)[1:]:
        truth = recording.truth_positions_m[frame.frame]
        distance, found = _nearest(frame, truth[3])
        assert distance < 3e-3
        assert found.surface is not None
        assert found.surface.kind == "corner"
        assert found.surface.edge_direction is not None
        assert abs(found.surface.edge_direction[1]) > math.cos(math.radians(2.0))
        assert len(set(found.transmitters)) == 2
        # Nothing else: the post's and the wall's double reflections, some of them built on an echo
        # the wall took too, are explained away.
        rows = truth[np.all(np.isfinite(truth), axis=1)]
        assert all(np.min(np.linalg.norm(rows - o.position_m, axis=1)) < 0.01 for o in frame.objects)


def test_double_scattering_between_two_balls_is_explained_away() -> None:
    """Two balls 0.35 m apart: the echo that goes from one to the other locates as a third ball
    without classes; with them, the two nearer balls explain it and it goes."""
    scene = load_scene(preset_path("wall-and-corner"))
    scene = dataclasses.replace(scene, objects=())  # its two balls alone, with max_order = 2
    recording = simulate(scene, 4)
    truth = recording.truth_positions_m
    assert truth is not None
    plain = _located(recording, classes=False)
    classes = _located(recording)
    for without, with_classes in zip(plain, classes, strict=True):
        assert len(without.objects) > 2  # the ghosts of the double scattering
        assert len(with_classes.objects) == 2
        for row in truth[with_classes.frame]:
            assert _nearest(with_classes, row)[0] < 2e-3


def test_a_vertical_post_is_located_as_an_edge() -> None:
    """A pole through the head's height across the cross: no point fits its echoes (they slide
    along it), so it is lost without classes and found, as an edge, with them."""
    scene = _with_transmitters(load_scene(preset_path("rooms/corridor")), 1)
    pole = Edge([0.2, -1.0, 1.0], [0.2, 1.0, 1.0], strength_m=0.3)
    scene = dataclasses.replace(
        scene,
        objects=(pole,),
        reflector_positions_m=np.zeros((0, 3)),
        reflector_strengths=np.zeros(0),
        max_order=1,
    )
    recording = simulate(scene, 3)
    foot = np.array([0.2, 0.0, 1.0])
    for frame in _located(recording, classes=False):
        assert all(np.linalg.norm(o.position_m - foot) > 0.01 for o in frame.objects)
    for frame in _located(recording):
        distance, found = _nearest(frame, foot)
        assert distance < 2e-3
        assert found.surface is not None
        assert found.surface.kind == "point"
        assert found.surface.edge_direction is not None
        np.testing.assert_allclose(abs(found.surface.edge_direction @ [0.0, 1.0, 0.0]), 1.0)


def test_truth_kinds_name_a_corners_edge_a_corner() -> None:
    faces_and_edge = corner([0, -1, 1.5], [0, 1, 1.5], [0, 0, -1], [1, 0, 0], 1.0)
    post = Edge([0.5, -1, 1], [0.5, 1, 1])
    assert truth_kinds([PointReflector([0, 0, 1]), *faces_and_edge, post]) == (
        "point",
        "plane",
        "plane",
        "corner",
        "point",
    )
    assert truth_kinds(_objects(load_scene(preset_path("rooms/corridor")))) == (
        "point",
        "plane",
        "plane",
        "corner",
    )


def _object(position: list[float], kind: str | None) -> LocatedObject:
    surface = (
        None
        if kind is None
        else Surface(
            kind,
            0.9,
            {kind: 0.9},
            normal=np.array([0.0, 0.0, -1.0]),
            normal_covariance=np.eye(3) * 1e-6,
            distance_m=1.0,
            distance_std_m=1e-4,
            extent_m=0.2,
        )
    )
    return LocatedObject(
        np.array(position), np.eye(3) * 1e-6, (0, 1, 2, 3), (0, 0, 0, 0), 0.0, 1.0, surface=surface
    )


def test_evaluate_classes_counts_the_confusion_matrix() -> None:
    """Truth: a point and a plane; located: the plane right, the point as a plane, and a stray."""
    truth = np.array([[[0.0, 0.0, 1.0], [0.3, 0.0, 1.0]]])
    frame = FrameObjects(
        0,
        0.0,
        (
            _object([0.0, 0.0, 1.0], "plane"),
            _object([0.3, 0.0, 1.001], "plane"),
            _object([1.0, 1.0, 1.0], None),
        ),
    )
    scored = evaluate_classes([frame], truth, ("plane", "point"), np.zeros((1, 3)))
    np.testing.assert_array_equal(scored.confusion, [[0, 1, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0]])
    assert scored.right_class_rate == 0.5
    assert scored.n_false == 1
    np.testing.assert_allclose(scored.normal_errors_deg, [0.0], atol=1e-6)
    np.testing.assert_allclose(scored.distance_errors_m, [0.0], atol=1e-12)


def test_the_json_gains_the_class_fields_only_when_asked() -> None:
    """docs/FORMATS.md 4: the contract's fields as before; kind and the rest added."""
    plain = objects_record(FrameObjects(0, 0.0, (_object([0.0, 0.0, 1.0], None),)))["objects"][0]
    assert set(plain) == {"position_m", "std_m", "receivers", "score", "channels", "shared_echoes"}
    classed = objects_record(FrameObjects(0, 0.0, (_object([0.0, 0.0, 1.0], "plane"),)))["objects"][0]
    assert {k: classed[k] for k in plain} == plain
    assert classed["kind"] == "plane"
    assert classed["normal"] == [0.0, 0.0, -1.0]
    assert classed["normal_std_deg"] == pytest.approx(math.degrees(math.sqrt(3e-6)))
    assert classed["distance_m"] == 1.0
    assert classed["extent_m"] == 0.2


def test_locate_classes_on_the_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    recording = simulate(load_scene(preset_path("rooms/corridor")), 2)  # two transmitters
    path = tmp_path / "corridor.h5"
    write_recording(recording, path)
    with pytest.raises(SystemExit) as exit_info:
        main(["locate", str(path), "--classes", "--json"])
    assert exit_info.value.code in (0, None)
    lines = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
    kinds = sorted(o["kind"] for o in lines[1]["objects"])  # once both transmitters have fired
    assert kinds == ["corner", "plane", "point"]
    plane = next(o for o in lines[1]["objects"] if o["kind"] == "plane")
    assert np.linalg.norm(plane["normal"]) == pytest.approx(1.0)
    assert plane["extent_m"] > 0
    corner_edge = next(o for o in lines[1]["objects"] if o["kind"] == "corner")["edge_direction"]
    assert abs(corner_edge[1]) > math.cos(math.radians(2.0))


def test_evaluate_classes_on_the_command_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The simulator writes truth_kinds; `evaluate --classes --json` scores them: every true
    reflector of the corridor is counted once in the confusion matrix."""
    path = tmp_path / "corridor.h5"
    write_recording(simulate(load_scene(preset_path("rooms/corridor")), 4), path)
    with pytest.raises(SystemExit) as exit_info:
        main(["evaluate", str(path), "--classes", "--json"])
    assert exit_info.value.code in (0, None)
    record = json.loads(capsys.readouterr().out)
    classes = record["classes"]
    assert classes["kinds"] == ["point", "plane", "corner"]
    assert int(np.sum(classes["confusion"])) == record["truth_objects"] == 12
    assert classes["confusion"][2][2] >= 2  # the corner, once both transmitters fired
    assert classes["median_normal_error_deg"] < 0.1


def test_a_door_jamb_merged_with_the_wall_on_one_receiver_is_found() -> None:
    """The doorway's left jamb echoes within 7 mm of the wall's echo on one receiver, where the two
    merge into one peak that the wall takes: the edge search borrows that peak (one at most) and
    finds the jamb, vertical, at its foot."""
    scene = _with_transmitters(load_scene(preset_path("rooms/doorway")), 1)
    recording = simulate(scene, 4)
    assert recording.truth_positions_m is not None
    assert recording.truth_kinds is not None
    jamb = next(k for k, kind in enumerate(recording.truth_kinds) if kind == "point")
    for frame in _located(recording):
        distance, found = _nearest(frame, recording.truth_positions_m[frame.frame, jamb])
        assert distance < 5e-3
        assert found.surface is not None
        assert found.surface.edge_direction is not None
        assert abs(found.surface.edge_direction[1]) == pytest.approx(1.0)
        assert found.shared == 1


def test_two_walls_at_a_right_angle_make_a_corner_not_a_ghost() -> None:
    """The double bounce between two planes is the image of the image; between two walls at a right
    angle it is their corner's own echo, which must not explain the corner away. At 60 degrees it
    is a ghost's path, the transmitter mirrored in one wall, then in the other."""
    from echoloc.localise import reflector_kinds

    tx = np.zeros((4, 3))
    rx = np.array([[0.25, 0, 0], [-0.25, 0, 0], [0, 0.25, 0], [0, -0.25, 0]])
    feet = np.array([[0.0, 0.0, 1.5], [-0.6, 0.0, 0.0]])
    for angle, expected in ((90.0, 0), (60.0, 2)):
        turn = math.radians(angle)
        normals = np.array([[0.0, 0.0, -1.0], [math.sin(turn), 0.0, -math.cos(turn)]])
        paths = reflector_kinds._double_reflections(np.zeros((0, 3)), feet, normals, tx, rx)
        assert len(paths) == expected
        if expected:
            image = tx[0] - 2 * ((tx[0] - feet[0]) @ normals[0]) * normals[0]
            image = image - 2 * ((image - feet[1]) @ normals[1]) * normals[1]
            np.testing.assert_allclose(paths[0], np.linalg.norm(image - rx, axis=1))


def test_classes_refuse_back_projection(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "corridor.h5"
    write_recording(simulate(load_scene(preset_path("rooms/corridor")), 1), path)
    for argv in (
        ["locate", str(path), "--classes", "--method", "backprojection"],
        ["image", str(path), "--classes", "-o", str(tmp_path / "i.png")],
    ):
        with pytest.raises(SystemExit) as exit_info:
            main(argv)
        assert exit_info.value.code == 2
        assert "--classes" in capsys.readouterr().err


def test_a_ghost_built_on_an_echo_a_real_object_took_is_explained_away() -> None:
    """Balls A and C, and an object B the association built from A's echo on one receiver (a
    shared, merged peak) and the double reflection A -> C on the others: B is a ghost and goes.
    The same B with an echo of its own on that receiver, which nothing explains, stays."""
    from echoloc.localise import reflector_kinds
    from echoloc.localise.locate import LocateOptions
    from echoloc.localise.surfaces import point_paths_m
    from echoloc.tof.echoes import ChannelEchoes, FrameEchoes

    c = 343.0
    rx = np.array([[0.25, 0, 0], [-0.25, 0, 0], [0, 0.25, 0], [0, -0.25, 0]], dtype=float)
    tx = np.zeros((4, 3))
    a, b = np.array([0.3, 0.0, 1.0]), np.array([-0.2, 0.1, 0.8])
    direct_a, direct_b = point_paths_m(a[None], tx, rx)[0], point_paths_m(b[None], tx, rx)[0]
    double = np.linalg.norm(a) + np.linalg.norm(b - a) + np.linalg.norm(b - rx, axis=1)
    stray = direct_a[0] + 0.05
    channels = tuple(
        ChannelEchoes(
            np.array([direct_a[r], direct_b[r], double[r], stray]) / c, np.ones(4), np.full(4, 30.0)
        )
        for r in range(4)
    )
    frames = [(0, FrameEchoes(0, 0.0, c, channels))]
    point = Surface("point", 1.0, {"point": 1.0})

    def located(position: np.ndarray, echoes: tuple[int, ...]) -> LocatedObject:
        return LocatedObject(
            position, np.eye(3) * 1e-8, (0, 1, 2, 3), echoes, 0.0, 1.0, (0,) * 4, surface=point
        )

    options = LocateOptions(resolution_m=0.027)
    ball_a, ball_b = located(a, (0, 0, 0, 0)), located(b, (1, 1, 1, 1))
    for first_echo, stays in ((0, False), (3, True)):
        ghost = located(np.array([0.1, 0.2, 1.2]), (first_echo, 2, 2, 2))
        kept = reflector_kinds._explained_away(
            [ball_a, ball_b, ghost], frames, np.zeros((1, 3)), rx, options, []
        )
        assert (ghost in kept) is stays
        assert ball_a in kept
        assert ball_b in kept


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


def _mirrored(point: np.ndarray, foot: np.ndarray, normal: np.ndarray) -> np.ndarray:
    return point - 2 * ((point - foot) @ normal) * normal


@settings(max_examples=60, deadline=None)
@given(
    st.floats(-50.0, 50.0),
    st.floats(-20.0, 20.0),
    st.floats(0.6, 3.0),
    st.tuples(st.floats(-0.2, 0.2), st.floats(-0.2, 0.2), st.floats(-0.05, 0.05)),
)
def test_one_image_fixes_what_another_transmitter_hears(
    azimuth_deg: float, elevation_deg: float, distance_m: float, second: tuple[float, float, float]
) -> None:
    """Kleeman and Kuc's test in closed form. A plane's image of one transmitter makes the plane
    (the bisector of transmitter and image), so another transmitter hears its own mirror image.
    A vertical corner's image is where its two walls' mirrors put the transmitter, one after
    the other; another transmitter hears the same two mirrors' image of itself. A point stays
    put."""
    from echoloc.localise import reflector_kinds

    az, el = math.radians(azimuth_deg), math.radians(elevation_deg)
    toward = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
    t0, t1 = np.zeros(3), np.array(second)
    rx = np.array([[0.25, 0, 0], [-0.25, 0, 0], [0, 0.25, 0], [0, -0.25, 0]])
    vertical = (0.0, 1.0, 0.0)

    # A plane with its foot at distance_m along `toward`, normal towards the sensor.
    foot = distance_m * toward
    image = _mirrored(t0, foot, -toward)
    point = np.array([0.1, -0.2, 1.0])
    predicted = reflector_kinds._predicted_elsewhere(image, point, t0, t1, rx, vertical)
    np.testing.assert_allclose(predicted["plane"], np.linalg.norm(_mirrored(t1, foot, -toward) - rx, axis=1))
    np.testing.assert_allclose(
        predicted["point"], np.linalg.norm(point - t1) + np.linalg.norm(point - rx, axis=1)
    )

    # A vertical corner whose edge passes through the foot of the horizontal direction: walls at
    # +-45 degrees to the line of sight, both through the edge.
    flat = _unit(np.array([toward[0], 0.0, toward[2]]))
    edge = distance_m * flat
    across = np.cross([0.0, 1.0, 0.0], flat)
    normal_a, normal_b = _unit(-flat + across), _unit(-flat - across)
    twice = _mirrored(_mirrored(t0, edge, normal_a), edge, normal_b)
    predicted = reflector_kinds._predicted_elsewhere(twice, point, t0, t1, rx, vertical)
    expected = _mirrored(_mirrored(t1, edge, normal_a), edge, normal_b)
    np.testing.assert_allclose(predicted["corner"], np.linalg.norm(expected - rx, axis=1), atol=1e-12)


def test_walls_whose_echoes_merge_with_double_reflections_are_planes() -> None:
    """The doorway with two transmitters: the wall beside the door and the far wall echo within
    millimetres of their double reflections via the jambs, whose peaks merge with theirs. Once
    both transmitters have fired, each wall heard is a plane whichever fired last (the class does
    not depend on the order), its normal within 0.5 degree and its distance within 2 mm of the
    newest transmitter's; the jambs are points. Without the robust cross-check of the other
    transmitter's echoes the walls stay points on the newest frame's echoes in most frames."""
    recording = simulate(_with_transmitters(load_scene(preset_path("rooms/doorway")), 2), 7)
    assert recording.truth_positions_m is not None
    assert recording.truth_kinds is not None
    assert recording.frame_transmitter is not None
    fired = recording.transmitters_m[recording.frame_transmitter]
    normal = np.array([-0.342, 0.0, 0.9397])  # the doorway's walls, towards the sensor
    normal /= -np.linalg.norm(normal)
    planes = 0
    for frame in _located(recording)[1:]:
        truth = recording.truth_positions_m[frame.frame]
        for row, kind in enumerate(recording.truth_kinds):
            if not np.all(np.isfinite(truth[row])):
                continue
            distance, found = _nearest(frame, truth[row])
            assert distance < 5e-3
            assert found.surface is not None
            assert found.surface.kind == kind
            if kind == "plane":
                planes += 1
                assert found.surface.normal is not None
                assert found.surface.distance_m is not None
                cosine = min(1.0, float(found.surface.normal @ normal))
                assert math.degrees(math.acos(cosine)) < 0.5
                expected = float(np.linalg.norm(truth[row] - fired[frame.frame]))
                assert found.surface.distance_m == pytest.approx(expected, abs=2e-3)
    assert planes == 12  # two walls heard in each of six frames


@pytest.mark.parametrize("kind", ["point", "plane"])
def test_a_merged_peak_costs_its_price_not_the_class(kind: str) -> None:
    """Eight exact paths of a point or a plane (two transmitters, four receivers), one of them moved
    4 mm as a merged peak moves it: the robust fit calls that echo merged, and only that one,
    keeps the true class decisively, and fits the other seven to within 0.1 mm."""
    from echoloc.localise import reflector_kinds, surfaces

    tx = np.array([[0.0, 0.0, 0.0]] * 4 + [[0.12, 0.12, 0.0]] * 4)
    rx = np.array([[0.25, 0, 0], [-0.25, 0, 0], [0, 0.25, 0], [0, -0.25, 0]] * 2)
    reference = tx[0]
    where = np.array([0.3, 0.05, 1.6])
    if kind == "point":
        paths = surfaces.point_paths_m(where[None], tx, rx)[0]
    else:
        paths = surfaces.plane_paths_m(where[None], tx, rx, reference)[0]
    moved = paths.copy()
    moved[5] += 0.004
    sigmas = np.full(8, 6e-4)
    group = reflector_kinds._Channels(tx, rx, moved, sigmas, (0,) * 4 + (1,) * 4, (0, 1, 2, 3) * 2, (0,) * 8)
    options = prepare(simulate(load_scene(preset_path("rooms/corridor")), 1)).locate_options
    merge = reflector_kinds._merge_sigma(0.029)
    robust = reflector_kinds._robust_hypotheses(group, reference, where, merge, options)
    k = surfaces.KINDS.index(kind)
    widened = math.sqrt(6e-4**2 + merge**2)
    price = 2 * math.log(widened / 6e-4 * (1 - reflector_kinds.MERGED_PRIOR) / reflector_kinds.MERGED_PRIOR)
    assert robust.priced[k] - robust.chi2[k] == pytest.approx(price)  # one echo called merged
    others = [j for j in range(len(surfaces.KINDS)) if j != k and np.isfinite(robust.priced[j])]
    assert others
    assert all(robust.priced[j] - robust.priced[k] > reflector_kinds.DECISIVE_CHI2 for j in others)
    refit = robust.refits[k]
    assert refit is not None
    residual = reflector_kinds._hypothesis_paths(refit, kind, group, reference) - paths
    assert np.max(np.abs(np.delete(residual, 5))) < 1e-4  # it still weighs 1/50 of a clean echo


def _frames_of(paths_by_tx: list[np.ndarray], c: float) -> list[tuple[int, FrameEchoes]]:
    """Two frames (transmitter t fired frame t) whose channels hold the given paths (k, 4) sorted."""
    frames = []
    for t, paths in enumerate(paths_by_tx):
        channels = []
        for r in range(paths.shape[1]):
            tof = np.sort(paths[:, r]) / c
            channels.append(ChannelEchoes(tof, np.ones_like(tof), np.full_like(tof, 30.0)))
        frames.append((t, FrameEchoes(t, 0.01 * t, c, tuple(channels))))
    return frames


_TWO_TRANSMITTERS_M = np.array([[0.0, 0.0, 0.0], [0.12, 0.12, 0.0]])
_CROSS_RECEIVERS_M = np.array([[0.25, 0, 0], [-0.25, 0, 0], [0, 0.25, 0], [0, -0.25, 0]])


def _direct_and_mirrored_paths(
    ball: np.ndarray, plane: np.ndarray, plane_first: bool
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per transmitter of :data:`_TWO_TRANSMITTERS_M`, the cross's paths (4,) to a ball and back,
    and via the plane (foot ``plane`` from the origin) wall first or last, m."""
    from echoloc.localise import reflector_kinds, surfaces

    direct, mirrored = [], []
    for transmitter_m in _TWO_TRANSMITTERS_M:
        channel_tx = np.broadcast_to(transmitter_m, _CROSS_RECEIVERS_M.shape)
        direct.append(surfaces.point_paths_m(ball[None], channel_tx, _CROSS_RECEIVERS_M)[0])
        mirrored.append(
            reflector_kinds.mirrored_paths_m(
                plane[None], ball, channel_tx, _CROSS_RECEIVERS_M, plane_first=plane_first
            )[0]
        )
    return direct, mirrored


@pytest.mark.parametrize("plane_first", [True, False])
@pytest.mark.parametrize("ball", [(-0.2, 0.1, 0.9), (0.15, -0.05, 1.2), (-0.15, 0.2, 0.7)])
def test_a_ball_seen_in_a_wall_never_heard_is_explained_by_that_wall(
    ball: tuple[float, float, float], plane_first: bool
) -> None:
    """A ball 15 cm from a wall the array never hears itself (its foot lies off the wall): the
    receivers hear the ball via the wall (wall first, or last) as if from the ball's mirror
    image, which the point association takes for a point. Fitted as the ball's double reflection
    via an unknown plane (both transmitters' echoes) it is explained away. A real point with the
    same echoes on the newest frame, but its own on the other, is not."""
    from echoloc.localise import reflector_kinds, surfaces

    c = 343.0
    tx, rx = _TWO_TRANSMITTERS_M, _CROSS_RECEIVERS_M
    v = np.array(ball)
    u = _unit(np.array([math.copysign(1.0, v[0]), 0.0, 0.0]))  # the wall beside the ball, beyond it
    plane = (u @ v + 0.15) * u
    point_paths, ghost_paths = _direct_and_mirrored_paths(v, plane, plane_first)
    channel_tx = np.broadcast_to(tx[1], rx.shape)
    start = 0.5 * (tx[1] + (v + 2 * (u @ plane / np.linalg.norm(plane) - u @ v) * u))
    apparent = surfaces.fit(
        lambda p: surfaces.point_paths_m(p, channel_tx, rx),
        start[None],
        ghost_paths[1][None],
        np.full((1, 4), 1e-4),
    ).parameters[0]
    options = prepare(simulate(load_scene(preset_path("rooms/corridor")), 1)).locate_options

    def located(position: np.ndarray, ghost: bool) -> LocatedObject:
        # Each channel's echoes are sorted: the ghost is the later one unless it is shorter there.
        later = ghost_paths[1] > point_paths[1]
        index = tuple(int(k) for k in np.where(later == ghost, 1, 0))
        return LocatedObject(position, np.eye(3) * 1e-6, (0, 1, 2, 3), index, 0.0, 1.0, (1, 1, 1, 1))

    ball_object = located(v, False)
    # The ghost's echoes on both frames, beside the ball's own.
    frames = _frames_of([np.vstack([point_paths[t], ghost_paths[t]]) for t in range(2)], c)
    ghost_object = located(apparent, True)
    points = [ball_object, ghost_object]
    assert reflector_kinds._unheard_mirror(ghost_object, points, frames, 1, tx, rx, options)
    # A real point where the ghost seemed to be: its echoes on the older frame are its own.
    real = surfaces.point_paths_m(apparent[None], np.broadcast_to(tx[0], rx.shape), rx)[0]
    frames = _frames_of([np.vstack([point_paths[0], real]), np.vstack([point_paths[1], ghost_paths[1]])], c)
    assert not reflector_kinds._unheard_mirror(ghost_object, points, frames, 1, tx, rx, options)


@pytest.mark.parametrize("plane_first", [True, False])
@pytest.mark.parametrize("ball", [(-0.2, 0.1, 0.9), (0.15, -0.05, 1.2)])
def test_a_ghost_taken_for_a_corner_is_explained_by_the_wall_never_heard(
    ball: tuple[float, float, float], plane_first: bool
) -> None:
    """The ghost test covers an object classed as a corner too (four parameters fit a ghost's
    echoes that a point's three cannot), on the echoes of the transmitter that gave the object
    four (here the older one: the newest gave three). A real corner, its edge where the ghost
    seemed to be, beside the same ball, keeps its own echoes and is not explained away."""
    from echoloc.localise import reflector_kinds, surfaces

    c = 343.0
    tx, rx = _TWO_TRANSMITTERS_M, _CROSS_RECEIVERS_M
    v = np.array(ball)
    u = _unit(np.array([math.copysign(1.0, v[0]), 0.0, 0.0]))
    plane = (u @ v + 0.15) * u
    point_paths, ghost_paths = _direct_and_mirrored_paths(v, plane, plane_first)
    mirror_v = v + 2 * (np.linalg.norm(plane) - u @ v) * u
    edge_foot = 0.5 * (v + mirror_v)  # on the wall, level with the ball
    options = prepare(simulate(load_scene(preset_path("rooms/corridor")), 1)).locate_options
    corner_surface = Surface(
        "corner", 0.9, {"point": 0.1, "corner": 0.9}, edge_direction=np.array([0.0, 1.0, 0])
    )

    def located(echo_paths: list[np.ndarray]) -> LocatedObject:
        # Four echoes of transmitter 0 and three of transmitter 1 (receiver 0 missed it).
        index = [int(echo_paths[t][r] > point_paths[t][r]) for t in (0, 1) for r in range(4)]
        return LocatedObject(
            edge_foot,
            np.eye(3) * 1e-6,
            (0, 1, 2, 3, 1, 2, 3),
            tuple(index[:4] + index[5:]),
            0.0,
            1.0,
            (0, 0, 0, 0, 1, 1, 1),
            surface=corner_surface,
        )

    ball_object = dataclasses.replace(located(point_paths), position_m=v, surface=None)
    frames = _frames_of([np.vstack([point_paths[t], ghost_paths[t]]) for t in range(2)], c)
    ghost = located(ghost_paths)
    kept = reflector_kinds._without_unheard_mirrors([ghost, ball_object], frames, 1, tx, rx, options)
    assert kept == [ball_object]
    # A real corner: its edge vertical through the ghost's foot; its echoes come from its images.
    real = [
        np.linalg.norm(surfaces.half_turned_m(tx[t], edge_foot, np.array([0.0, 1.0, 0.0])) - rx, axis=1)
        for t in range(2)
    ]
    frames = _frames_of([np.vstack([point_paths[t], real[t]]) for t in range(2)], c)
    corner_object = located(real)
    kept = reflector_kinds._without_unheard_mirrors([corner_object, ball_object], frames, 1, tx, rx, options)
    assert kept == [corner_object, ball_object]


def test_a_ghost_must_beat_the_fit_of_the_class_it_was_given(monkeypatch: pytest.MonkeyPatch) -> None:
    """The same ghost echoes, reported once as a point and once as a corner, against a stand-in
    for the rivals' fits: a point's fit it beats, a corner's that fits them perfectly it does not.
    The class reaches the comparison (the rivals' own fits are tested below)."""
    from echoloc.localise import reflector_kinds

    c = 343.0
    tx, rx = _TWO_TRANSMITTERS_M, _CROSS_RECEIVERS_M
    v = np.array([0.15, -0.05, 1.2])
    plane = np.array([0.30, 0.0, 0.0])
    point_paths, ghost_paths = _direct_and_mirrored_paths(v, plane, plane_first=False)
    frames = _frames_of([np.vstack([point_paths[t], ghost_paths[t]]) for t in range(2)], c)
    index = tuple(int(ghost_paths[t][r] > point_paths[t][r]) for t in (0, 1) for r in range(4))
    ghost_at = np.array([0.3, -0.05, 1.2])
    ghost = LocatedObject(ghost_at, np.eye(3) * 1e-6, (0, 1, 2, 3) * 2, index, 0.0, 1.0, (0,) * 4 + (1,) * 4)
    ball = LocatedObject(
        v, np.eye(3) * 1e-6, (0, 1, 2, 3) * 2, tuple(1 - i for i in index), 0.0, 1.0, ghost.transmitters
    )
    options = prepare(simulate(load_scene(preset_path("rooms/corridor")), 1)).locate_options
    monkeypatch.setattr(reflector_kinds, "_rival_chi2", lambda kind, *rest: 0.0 if kind == "corner" else 1e9)
    as_corner = dataclasses.replace(ghost, surface=Surface("corner", 0.9, {"point": 0.1, "corner": 0.9}))
    assert reflector_kinds._unheard_mirror(ghost, [ball], frames, 1, tx, rx, options)
    assert not reflector_kinds._unheard_mirror(as_corner, [ball], frames, 1, tx, rx, options)


def test_what_a_ghost_must_beat_is_the_objects_own_class() -> None:
    """A real corner's echoes (two transmitters, its images half-turned about the edge) fit a
    corner exactly and a point badly: a ghost explanation of a corner must beat the corner's
    chi-square (about 0), of a point the point's."""
    from echoloc.localise import reflector_kinds, surfaces

    tx, rx = _TWO_TRANSMITTERS_M, _CROSS_RECEIVERS_M
    edge_foot, up = np.array([-0.3, 0.0, 1.1]), np.array([0.0, 1.0, 0.0])
    paths = np.concatenate(
        [np.linalg.norm(surfaces.half_turned_m(tx[t], edge_foot, up) - rx, axis=1) for t in range(2)]
    )
    group = reflector_kinds._Channels(
        tx[[0, 0, 0, 0, 1, 1, 1, 1]],
        np.vstack([rx, rx]),
        paths,
        np.full(8, 1e-3),
        (0, 0, 0, 0, 1, 1, 1, 1),
        (0, 1, 2, 3, 0, 1, 2, 3),
        (0,) * 8,
    )
    options = prepare(simulate(load_scene(preset_path("rooms/corridor")), 1)).locate_options
    as_corner = reflector_kinds._rival_chi2("corner", edge_foot, group, group.sigmas_m, tx[0], options)
    as_point = reflector_kinds._rival_chi2("point", edge_foot, group, group.sigmas_m, tx[0], options)
    assert as_corner < 1e-3
    assert as_point > 10 * reflector_kinds.DECISIVE_CHI2


def test_only_points_kept_explain_farther_objects_as_their_ghosts() -> None:
    """A ball, its ghost via a wall never heard (G), and an object X whose echoes are exactly G's
    double reflection via a second such wall. G is the ball's ghost and goes; X, which only G
    explains, stays: a ghost is no reflector, so it explains nothing (a real corner behind a
    ghost would otherwise go with it). The objects are given farthest first: the order is the
    test's own, nearest first."""
    from echoloc.localise import reflector_kinds, surfaces

    c = 343.0
    tx, rx = _TWO_TRANSMITTERS_M, _CROSS_RECEIVERS_M
    ball = np.array([0.15, -0.05, 1.2])
    first_wall = np.array([0.30, 0.0, 0.0])  # x = 0.30, beyond the ball
    second_wall = np.array([0.0, 0.0, 1.6])  # z = 1.6, beyond the ghost

    def apparent(paths: np.ndarray, start: np.ndarray) -> np.ndarray:
        channel_tx = np.broadcast_to(tx[1], rx.shape)
        return surfaces.fit(
            lambda p: surfaces.point_paths_m(p, channel_tx, rx),
            start[None],
            paths[None],
            np.full((1, 4), 1e-4),
        ).parameters[0]

    ball_paths, ghost_paths = _direct_and_mirrored_paths(ball, first_wall, plane_first=False)
    ghost_at = apparent(ghost_paths[1], np.array([0.45, -0.05, 1.2]))
    _, far_paths = _direct_and_mirrored_paths(ghost_at, second_wall, plane_first=False)
    far_at = apparent(far_paths[1], np.array([0.45, -0.05, 2.0]))
    stacks = [np.vstack([ball_paths[t], ghost_paths[t], far_paths[t]]) for t in range(2)]
    frames = _frames_of(stacks, c)

    def located(position: np.ndarray, row: int) -> LocatedObject:
        # The echo index on each channel is the path's rank among that channel's sorted paths.
        index = tuple(int(np.sum(stacks[t][:, r] < stacks[t][row, r])) for t in range(2) for r in range(4))
        return LocatedObject(
            position, np.eye(3) * 1e-6, (0, 1, 2, 3) * 2, index, 0.0, 1.0, (0, 0, 0, 0, 1, 1, 1, 1)
        )

    objects = [located(far_at, 2), located(ghost_at, 1), located(ball, 0)]
    options = prepare(simulate(load_scene(preset_path("rooms/corridor")), 1)).locate_options
    # X is G's double reflection: with G taken for real, G would explain it.
    assert reflector_kinds._unheard_mirror(objects[0], [objects[1]], frames, 1, tx, rx, options)
    kept = reflector_kinds._without_unheard_mirrors(objects, frames, 1, tx, rx, options)
    assert [o.position_m.tolist() for o in kept] == [far_at.tolist(), ball.tolist()]


def test_one_wall_found_twice_in_a_frame_is_reported_once() -> None:
    """Two planes 2 degrees and 1 cm apart are one wall (walls that close along their normal make
    one merged echo on every channel): the one with more echoes stays. A wall parallel to it but
    10 cm farther (beyond the 29 mm resolution), and one turned 10 degrees, are walls of their own;
    without a known resolution nothing is merged."""
    from echoloc.localise import reflector_kinds

    options = prepare(simulate(load_scene(preset_path("rooms/corridor")), 1)).locate_options
    assert options.resolution_m is not None
    assert options.resolution_m < 0.05  # 1 cm apart is within it, 10 cm beyond

    def wall(angle_deg: float, distance_m: float, n_echoes: int) -> LocatedObject:
        a = math.radians(angle_deg)
        normal = np.array([math.sin(a), 0.0, -math.cos(a)])
        surface = Surface("plane", 1.0, {"plane": 1.0}, normal=normal, distance_m=distance_m)
        return LocatedObject(
            -distance_m * normal,
            np.eye(3) * 1e-6,
            tuple(range(n_echoes)),
            (0,) * n_echoes,
            1.0,
            0.9,
            surface=surface,
        )

    best, twin = wall(0.0, 1.20, 8), wall(2.0, 1.21, 6)
    farther, turned = wall(0.0, 1.30, 6), wall(10.0, 1.20, 6)
    ball = dataclasses.replace(best, surface=None, position_m=np.array([0.2, 0.0, 0.8]))
    objects = [twin, ball, best, farther, turned]
    assert reflector_kinds._one_plane_a_wall(objects, options) == [ball, best, farther, turned]
    unknown = dataclasses.replace(options, resolution_m=None)
    assert reflector_kinds._one_plane_a_wall(objects, unknown) == objects
