"""Reflector classes on simulated rooms: found with the right class, false objects, plane accuracy.

First the point scenes of the localisation issue (1-6 random points, the report's three
balls), with and without classes: the point figures must hold. Then for each scene,
with its own transmitter and again with a second one 17 cm away (fired in
turn), simulate frames, locate them with reflector classes (``--classes``) and score
them against the scene's truth (:func:`echoloc.localise.evaluation.evaluate_classes`):
the confusion matrix of classes, the share of true reflectors found with the right
class, the share of located objects that are false, and the median normal and distance
errors of the planes. ``rooms/alcove`` and ``rooms/bookcase`` are held out: no test reads
them and nothing was tuned on them. Writes ``benchmarks/results/reflector_classes.md``.

    .venv/bin/python benchmarks/reflector_classes.py [--frames 1000] [--scenes a,b,...] [--points a,b]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
from pathlib import Path

import numpy as np

from echoloc.localise.evaluation import ClassEvaluation, evaluate, evaluate_classes
from echoloc.pipeline import prepare, run
from echoloc.sim.scene import Scene
from echoloc.sim.scenefile import load_scene, preset_path
from echoloc.sim.simulation import simulate

SCENES = (
    "wall-and-corner",
    "rooms/corridor",
    "rooms/doorway",
    "rooms/desk",
    "rooms/alcove",
    "rooms/bookcase",
)
HELD_OUT = ("rooms/alcove", "rooms/bookcase")
"""Scenes no test reads and nothing was tuned on: the classes' figures on rooms they never saw."""
SECOND_TRANSMITTER_M = (0.12, 0.12, 0.0)
RESULTS = Path(__file__).parent / "results" / "reflector_classes.md"


def with_transmitters(scene: Scene, n_tx: int) -> Scene:
    """The scene with its first transmitter only, or with a second one at :data:`SECOND_TRANSMITTER_M`."""
    first = scene.array.transmitters_m[:1]
    transmitters = first if n_tx == 1 else np.vstack([first, SECOND_TRANSMITTER_M])
    axes = scene.array.transmitter_axes
    if axes is not None:
        axes = axes[:1] if n_tx == 1 else np.vstack([axes[:1], axes[:1]])
    array = dataclasses.replace(scene.array, transmitters_m=transmitters, transmitter_axes=axes)
    return dataclasses.replace(scene, array=array, transmitter_codes=None)


def score(scene: Scene, n_frames: int) -> tuple[ClassEvaluation, float, float]:
    """Simulate, locate with classes and score; also the seconds a frame took to locate with
    classes and, in the same run, without (the plain association on the same frames)."""
    recording = simulate(scene, n_frames)
    plain = prepare(recording)
    chain = dataclasses.replace(
        plain, locate_options=dataclasses.replace(plain.locate_options, reflector_classes=True)
    )
    list(run(chain, range(min(2, n_frames))))  # the kernels loaded (or compiled) before timing
    start = time.perf_counter()
    results = [objects for _, objects in run(chain)]
    seconds = (time.perf_counter() - start) / n_frames
    start = time.perf_counter()
    for _ in run(plain):
        pass
    plain_seconds = (time.perf_counter() - start) / n_frames
    fired = (
        np.zeros(n_frames, dtype=int) if recording.frame_transmitter is None else recording.frame_transmitter
    )
    assert recording.truth_positions_m is not None
    assert recording.truth_kinds is not None
    evaluation = evaluate_classes(
        results, recording.truth_positions_m, recording.truth_kinds, recording.transmitters_m[fired]
    )
    return evaluation, seconds, plain_seconds


POINT_SCENES = ("random-1m3-six", "report-three-balls")


def point_figures(name: str, n_frames: int) -> list[str]:
    """The point-reflector figures of the localisation issue, with and without classes."""
    recording = simulate(load_scene(preset_path(name)), n_frames)
    assert recording.truth_positions_m is not None
    lines = [f"### {name} (points), {n_frames} frames", ""]
    for classes in (False, True):
        chain = prepare(recording)
        chain = dataclasses.replace(
            chain, locate_options=dataclasses.replace(chain.locate_options, reflector_classes=classes)
        )
        results = [objects for _, objects in run(chain)]
        e = evaluate(results, recording.truth_positions_m)
        worst = float(np.max(np.linalg.norm(e.errors_m, axis=1))) if len(e.errors_m) else float("nan")
        kinds = [o.surface.kind for f in results for o in f.objects if o.surface is not None]
        pointed = kinds.count("point") / len(kinds) if kinds else float("nan")
        lines.append(
            f"- {'with' if classes else 'without'} classes: recall {e.recall:.4f}, false objects "
            f"{e.false_rate:.4f}, largest error {worst * 1e3:.2f} mm"
            + (f", classed as points {pointed:.4f}" if classes else "")
        )
    return [*lines, ""]


def table(name: str, n_tx: int, e: ClassEvaluation, seconds: float, plain_seconds: float) -> list[str]:
    """Markdown lines for one scene and transmitter count."""
    lines = [
        f"### {name}, {n_tx} transmitter{'s' if n_tx > 1 else ''}",
        "",
        f"right class {e.right_class_rate:.3f} of {e.n_truth} true reflectors; "
        f"false objects {e.false_rate:.4f} ({e.n_false} of {e.n_located}); "
        f"{seconds * 1e3:.2f} ms a frame with classes, {plain_seconds * 1e3:.2f} without "
        f"({seconds / plain_seconds:.1f} times, same run)",
        "",
    ]
    if len(e.normal_errors_deg):
        lines += [
            f"planes: median normal error {np.median(e.normal_errors_deg):.3f} deg, "
            f"median |distance error| {np.median(np.abs(e.distance_errors_m)) * 1e3:.3f} mm "
            f"({len(e.normal_errors_deg)} plane sightings)",
            "",
        ]
    lines += [
        "| truth \\ reported | " + " | ".join(e.kinds) + " | missed |",
        "|---" * (len(e.kinds) + 2) + "|",
    ]
    for kind, row in zip(e.kinds, e.confusion, strict=True):
        if row.sum():
            lines.append(f"| {kind} | " + " | ".join(str(v) for v in row) + " |")
    return [*lines, ""]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--scenes", default=",".join(SCENES))
    parser.add_argument("--points", default=",".join(POINT_SCENES), help="point scenes ('' for none)")
    parser.add_argument("--output", type=Path, default=RESULTS)
    args = parser.parse_args()
    lines = [
        "# Reflector classes on simulated rooms",
        "",
        f"`python benchmarks/reflector_classes.py --frames {args.frames}`; match radius 20 mm. Times are "
        "the whole chain a frame (echoes and objects), with and without classes on the same frames in the "
        "same run, on a shared machine: read the ratio.",
        "",
    ]
    for name in args.points.split(",") if args.points else ():
        part = point_figures(name, args.frames if name.startswith("random") else 50)
        print("\n".join(part), flush=True)
        lines += part
    for name in args.scenes.split(","):
        scene = load_scene(preset_path(name))
        for n_tx in (1, 2):
            evaluation, seconds, plain_seconds = score(with_transmitters(scene, n_tx), args.frames)
            part = table(
                name + (" (held out)" if name in HELD_OUT else ""), n_tx, evaluation, seconds, plain_seconds
            )
            print("\n".join(part), flush=True)
            lines += part
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text("\n".join(lines))


if __name__ == "__main__":
    main()
