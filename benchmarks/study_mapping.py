"""Mapping study: a simulated room mapped by a moving, spinning sensor, and what a pan scan adds.

1. **Room** (mapping/room): four walls, a box and a pole, double
   reflections on; the head drives diagonally and spins at 30 deg/s for one turn
   (1200 frames). The floor plan at 2 cm (and 1 cm) is scored against the true
   surfaces (:func:`echoloc.maps.mapping.map_accuracy`):

   - *coverage*: of the surface the sensor saw, the fraction with an occupied cell
     within one cell. "Seen" = within a cell of a true reflection point (the
     recording's ``truth_positions``) inside the beam that at least two receivers
     heard within 2 cm of its path (the map's ``min_support``); the figure for
     "heard by at least one receiver" is given beside it;
   - *precision*: occupied cells within one cell of any true surface;
   - *ghosts in free space*: occupied cells in the room's interior, farther than 1.5
     cells from every surface, as a fraction of the observed interior and as area.

   Each run maps with the default sensor model, which places the echoes one receiver
   heard alone by tracking them across poses (:mod:`echoloc.maps.triangulation`); the
   rows marked "no tracks (before)" map without it, as before that stage existed.

2. **Mechanical scanning** (mapping/pan-scan): the head standing still
   with a fixed boresight, then panning +-45 degrees (period 4 s), 400 frames each:
   the area it observes and the poles and wall it hears.

    python benchmarks/study_mapping.py

Writes benchmarks/results/mapping.md, map_room.png and map_scan.png.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import time
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from scipy.spatial import cKDTree

from echoloc import pipeline
from echoloc.io.recording import Recording
from echoloc.maps.mapping import (
    GridSpec,
    MapAccumulator,
    OccupancyGrid,
    SensorModel,
    build_map,
    frame_poses,
    integrate,
    map_accuracy,
    seen_surface_points_m,
    seen_truth_points_m,
)
from echoloc.maps.triangulation import TriangulatedPoint
from echoloc.plots.maps import draw_floor_plan, plot_grid
from echoloc.sim.reflectors import Edge, Plane, surface_points_m
from echoloc.sim.scene import Scene, SensorMotion
from echoloc.sim.scenefile import load_scene
from echoloc.sim.simulation import simulate
from reflector_classes import with_transmitters

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "benchmarks" / "results"
ROOM = ROOT / "src" / "echoloc" / "scenes" / "mapping" / "room.toml"
SCAN = ROOT / "src" / "echoloc" / "scenes" / "mapping" / "pan-scan.toml"
# The room's interior and the box, from room.toml.
ROOM_X, ROOM_Z = (-1.4, 1.6), (-1.0, 2.0)
BOX_X, BOX_Z = (0.2, 0.6), (1.1, 1.5)
POLE_XZ = (-0.7, 0.9)
EXTENT = ((-1.6, 1.8), (-1.2, 2.2))


def _free_space(spec: GridSpec) -> np.ndarray:
    margin = 1.5 * spec.cell_m
    x, z = np.meshgrid(spec.centres_m(0), spec.centres_m(2), indexing="ij")
    inside = (
        (x > ROOM_X[0] + margin)
        & (x < ROOM_X[1] - margin)
        & (z > ROOM_Z[0] + margin)
        & (z < ROOM_Z[1] - margin)
    )
    in_box = (
        (x > BOX_X[0] - margin) & (x < BOX_X[1] + margin) & (z > BOX_Z[0] - margin) & (z < BOX_Z[1] + margin)
    )
    near_pole = np.hypot(x - POLE_XZ[0], z - POLE_XZ[1]) < margin + 0.02
    return np.asarray((inside & ~in_box & ~near_pole)[:, None, :])


def _plan_length_m(points_m: np.ndarray, spec: GridSpec) -> float:
    """How much of the floor plan the surface samples cover: their distinct cells times the cell
    size, m (the samples are a quarter cell apart and fill the layer's height several times over,
    so their count is no length)."""
    index, inside = spec.cell_indices(points_m)
    return len(np.unique(index[inside], axis=0)) * spec.cell_m


def _score(scene: Scene, recording: Recording, results: list, grid: OccupancyGrid) -> dict[str, float]:
    spec = grid.spec
    surface = surface_points_m(scene.objects, spec.cell_m / 4)
    echoes = [e for e, _ in results]
    row: dict[str, float] = {}
    for channels in (2, 1):
        heard = seen_truth_points_m(recording, echoes, tolerance_m=0.02, min_channels=channels)
        seen = seen_surface_points_m(surface, heard, spec)
        accuracy = map_accuracy(grid, surface, seen, free_space=_free_space(spec))
        row[f"coverage_{channels}"] = accuracy.coverage
        row[f"seen_m_{channels}"] = _plan_length_m(seen, spec)
    row.update(
        precision=accuracy.precision,
        occupied=accuracy.occupied_cells,
        ghost_fraction=accuracy.ghost_fraction,
        ghost_area_m2=accuracy.ghost_area_m2,
        free_m2=accuracy.free_cells * spec.cell_m**2,
    )
    return row


def _label(reflector: object) -> str:
    """A reflector named by its kind and where it is on the floor plan (x, z), m."""
    if isinstance(reflector, Plane):
        x, _, z = reflector.centre_m
        nx, _, nz = reflector.normal
        return f"plane at ({x:.2f}, {z:.2f}) facing ({nx:+.2f}, {nz:+.2f})"
    if isinstance(reflector, Edge):
        x, _, z = 0.5 * (np.asarray(reflector.start_m) + np.asarray(reflector.end_m))
        return f"edge at ({x:.2f}, {z:.2f})"
    position = getattr(reflector, "position_m", getattr(reflector, "centre_m", None))
    where = "" if position is None else f" at ({position[0]:.2f}, {position[2]:.2f})"
    return f"{type(reflector).__name__.lower()}{where}"


def by_reflector(scene: Scene, recording: Recording, results: list, grid: OccupancyGrid) -> list[str]:
    """Table rows: for each reflector, the surface one receiver or more heard of it, two or more,
    and the share of the first the map marks (within a cell), the coverage's make-up."""
    spec = grid.spec
    everything = surface_points_m(scene.objects, spec.cell_m / 4)
    echoes = [e for e, _ in results]
    heard = {n: seen_truth_points_m(recording, echoes, tolerance_m=0.02, min_channels=n) for n in (1, 2)}
    rows = []
    for reflector in scene.objects:
        own = surface_points_m([reflector], spec.cell_m / 4)
        seen = {n: seen_surface_points_m(own, heard[n], spec) for n in (1, 2)}
        if not len(seen[1]):
            continue
        covered = map_accuracy(grid, everything, seen[1]).coverage
        rows.append(
            f"| {_label(reflector)} | {_plan_length_m(seen[1], spec):.2f} m | "
            f"{_plan_length_m(seen[2], spec):.2f} m | {covered:.3f} |"
        )
    return rows


def _counted(kinds: list[str], kind: str) -> str:
    """``"3 planes"``, ``"1 point"``: how many of ``kinds`` are ``kind``."""
    n = kinds.count(kind)
    return f"{n} {kind}{'' if n == 1 else 's'}"


def room(n_frames: int) -> list[str]:
    scene = load_scene(ROOM)
    recording = simulate(scene, n_frames)
    results = list(pipeline.run(pipeline.prepare(recording)))
    poses = frame_poses(recording)
    lines = [
        "## 1. The room: a moving, spinning sensor",
        "",
        f"`{ROOM.relative_to(ROOT)}`, {n_frames} frames: floor plan at the head's height, scored against the "
        "true surfaces (module doc).",
        "",
        "| cells | seen by >= 2 receivers | coverage | seen by >= 1 | coverage | precision | "
        "ghosts in free space | ghost area | free area observed |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    chain = pipeline.prepare(recording)
    classed = list(
        pipeline.run(
            dataclasses.replace(
                chain, locate_options=dataclasses.replace(chain.locate_options, reflector_classes=True)
            )
        )
    )
    kinds = [o.surface.kind for _, f in classed for o in f.objects if o.surface is not None]
    # The same drive with a second transmitter fired in turn, which tells walls from points.
    two = simulate(with_transmitters(scene, 2), n_frames)
    two_chain = pipeline.prepare(two)
    two_plain = list(pipeline.run(two_chain))
    with_classes = dataclasses.replace(two_chain.locate_options, reflector_classes=True)
    two_classed = list(pipeline.run(dataclasses.replace(two_chain, locate_options=with_classes)))
    two_kinds = [o.surface.kind for _, f in two_classed for o in f.objects if o.surface is not None]
    breakdown: list[str] = []
    placed: list[str] = []
    untracked = SensorModel(tracks=None)
    for cell, rec, runs, name, model in (
        (0.02, recording, results, "2 cm, no tracks (before)", untracked),
        (0.02, recording, results, "2 cm", SensorModel()),
        (0.01, recording, results, "1 cm", SensorModel()),
        (0.02, recording, classed, "2 cm, --classes", SensorModel()),
        (0.02, two, two_plain, "2 cm, two transmitters", SensorModel()),
        (0.02, two, two_classed, "2 cm, two transmitters, --classes, no tracks (before)", untracked),
        (0.02, two, two_classed, "2 cm, two transmitters, --classes", SensorModel()),
    ):
        spec = GridSpec.floor_plan(EXTENT[0], EXTENT[1], cell)
        accumulator = MapAccumulator(spec, rec, model)
        grid = integrate(accumulator, runs, frame_poses(rec))
        r = _score(scene, rec, runs, grid)
        if accumulator.triangulated and cell == 0.02:
            placed.append(_placed_row(name, accumulator.triangulated, scene))
        lines.append(
            f"| {name} | {r['seen_m_2']:.2f} m | **{r['coverage_2']:.3f}** | "
            f"{r['seen_m_1']:.2f} m | "
            f"{r['coverage_1']:.3f} | {r['precision']:.3f} | **{100 * r['ghost_fraction']:.2f} %** | "
            f"{r['ghost_area_m2'] * 1e4:.0f} cm² | {r['free_m2']:.2f} m² |"
        )
        truth = surface_points_m(scene.objects, cell / 4)
        truth = truth[np.abs(truth[:, 1]) < cell / 2]
        if name == "2 cm":
            for target in (RESULTS / "map_room.png", ROOT / "docs" / "map_room.png"):
                plot_grid(grid, target, sensor_path_m=poses[:, :3], truth_m=truth)
        if name == "2 cm, two transmitters, --classes":
            plot_grid(grid, RESULTS / "map_room_classes.png", sensor_path_m=poses[:, :3], truth_m=truth)
            breakdown = by_reflector(scene, rec, runs, grid)
    lines += [
        "",
        f"With `--classes` the {len(kinds)} objects are {kinds.count('point')} points, "
        f"{kinds.count('plane')} planes and {kinds.count('corner')} corners: one transmitter hears these "
        "walls near normal incidence, where it cannot tell a wall from a point (docs/METHOD.md 10.10).",
        f"With a second transmitter 17 cm away (at (0.12, 0.12, 0) m, fired in turn) the {len(two_kinds)} "
        f"objects are {_counted(two_kinds, 'point')}, {_counted(two_kinds, 'plane')} and "
        f"{_counted(two_kinds, 'corner')}; each plane is drawn as the segment its echoes met.",
        "",
        "![room](map_room.png)",
        "",
        "Two transmitters, `--classes`:",
        "",
        "![room, two transmitters, classes](map_room_classes.png)",
        "",
        "What the coverage of the surface heard by one receiver or more is made of (two transmitters, "
        "`--classes`, 2 cm): per reflector, the surface heard by one receiver or more and by two or more "
        "(within a cell of a reflection point heard within 2 cm), and the share of the first the map marks. "
        "Where faces meet at an edge, the edge's neighbourhood counts for each of them. "
        "A reflector one receiver at a time heard leaves one ellipsoid a frame, which places it nowhere "
        "in that frame; a track of such echoes places it once the sensor has moved enough (below).",
        "",
        "| reflector | heard by >= 1 | by >= 2 | marked |",
        "|---|---|---|---|",
        *breakdown,
        "",
        "Reflectors placed by tracks across poses (echoes no frame's objects used, followed from frame to "
        "frame on one channel and fitted to one point: `echoloc.maps.triangulation`), and how far each lies "
        "from the nearest true surface:",
        "",
        "| run | points | median distance | 90th percentile | farthest |",
        "|---|---|---|---|---|",
        *placed,
        "",
        _tracking_cost(two, two_classed),
        "",
    ]
    return lines


def _tracking_cost(recording: Recording, results: list, rounds: int = 5) -> str:
    """What the tracks add to building the map: the two ways timed in turn, best of ``rounds``."""
    spec = GridSpec.floor_plan(EXTENT[0], EXTENT[1], 0.02)
    poses = frame_poses(recording)
    best = {True: math.inf, False: math.inf}
    for _ in range(rounds):
        for tracked in (False, True):
            model = SensorModel() if tracked else SensorModel(tracks=None)
            start = time.perf_counter()
            build_map(recording, results, spec, model=model, poses=poses)
            best[tracked] = min(best[tracked], time.perf_counter() - start)
    return (
        f"Building this map from the {recording.n_frames} frames' echoes and objects (two transmitters, "
        f"`--classes`, best of {rounds}, timed in turn): {best[False]:.2f} s without tracks, "
        f"{best[True]:.2f} s with them ({best[True] / best[False]:.2f} times)."
    )


def _placed_row(name: str, points: list[TriangulatedPoint], scene: Scene) -> str:
    """A table row: how many points the tracks placed and their distances to the true surfaces."""
    surface = cKDTree(surface_points_m(scene.objects, 0.005))
    distance_mm = 1000 * surface.query(np.array([p.position_m for p in points]))[0]
    return (
        f"| {name} | {len(points)} | {np.median(distance_mm):.0f} mm | "
        f"{np.percentile(distance_mm, 90):.0f} mm | {distance_mm.max():.0f} mm |"
    )


def scan(n_frames: int) -> list[str]:
    panned = load_scene(SCAN)
    still = dataclasses.replace(panned, motion=SensorMotion())
    spec = GridSpec.floor_plan((-1.8, 1.8), (-0.2, 2.2), 0.02)
    figure = Figure(figsize=(14, 5.5), layout="constrained")
    lines = [
        "## 2. Mechanical scanning: a narrow beam standing still, then panning +-45 degrees",
        "",
        f"`{SCAN.relative_to(ROOT)}`: five poles 1.3 m away at -40 ... 40 degrees and a wall 1.8 m ahead; "
        f"{n_frames} frames ({n_frames / 100:g} s) each, floor plan at 2 cm. A reflector counts as heard "
        "when at least two receivers heard it within 2 cm of its path in some frame.",
        "",
        "| head | area observed | free area | poles heard | wall heard | occupied cells |",
        "|---|---|---|---|---|---|",
    ]
    for k, (name, scene) in enumerate((("fixed boresight", still), ("pan +-45 deg, period 4 s", panned))):
        recording = simulate(scene, n_frames)
        results = list(pipeline.run(pipeline.prepare(recording)))
        grid = build_map(recording, results, spec)
        heard = seen_truth_points_m(recording, [e for e, _ in results], tolerance_m=0.02, min_channels=2)
        poles = [obj for obj in scene.objects if isinstance(obj, Edge)]
        poles_heard = sum(
            bool(len(heard))
            and bool(np.min(np.hypot(heard[:, 0] - pole.start_m[0], heard[:, 2] - pole.start_m[2])) < 0.03)
            for pole in poles
        )
        wall = seen_surface_points_m(surface_points_m(scene.objects[:1], 0.005), heard, spec)
        lines.append(
            f"| {name} | {grid.known().sum() * spec.cell_m**2:.2f} m² | "
            f"{grid.free().sum() * spec.cell_m**2:.2f} m² | "
            f"{poles_heard} of {len(poles)} | {len(wall) * 0.005:.2f} m | {int(grid.occupied().sum())} |"
        )
        truth = surface_points_m(scene.objects, 0.005)
        draw_floor_plan(
            figure.add_subplot(1, 2, k + 1),
            grid,
            sensor_path_m=np.zeros((1, 3)),
            truth_m=truth[np.abs(truth[:, 1]) < 0.01],
            title=name,
        )
    figure.savefig(RESULTS / "map_scan.png", dpi=110)
    lines += [
        "",
        "![scan](map_scan.png)",
        "",
        "The pan widens what the 18-degree beam covers; the poles' arcs still run together, because a "
        "pole 1.3 m away is heard mostly by the vertical receiver pair, whose ellipses coincide in the "
        "horizontal plane: angle within the beam is known only where the horizontal pair hears too.",
        "",
    ]
    return lines


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1200)
    parser.add_argument("--scan-frames", type=int, default=400)
    args = parser.parse_args()
    lines = [
        "# study_mapping.py — last run",
        "",
        f"`python benchmarks/study_mapping.py --frames {args.frames}`",
        "",
    ]
    lines += room(args.frames)
    lines += scan(args.scan_frames)
    text = "\n".join(lines)
    (RESULTS / "mapping.md").write_text(text)
    print(text)


if __name__ == "__main__":
    main()
