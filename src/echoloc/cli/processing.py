"""`echoloc echoes`, `locate`, `image`, `export`, `map`, `evaluate` and `calibrate`: recordings
through the chain."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import click
import numpy as np
from numpy.typing import NDArray
from rich.table import Table

from echoloc.cli.app import (
    Processing,
    _check_writable,
    _Decorated,
    _finite,
    _json_safe,
    _located,
    _path_option,
    _processing_options,
    _progress,
    _warn,
    cli,
    stdout,
)
from echoloc.cli.basics import _class_cells, _object_cells
from echoloc.errors import EchoLocError
from echoloc.io.output import echoes_record, json_line, objects_record
from echoloc.localise.calibrate import (
    DETECTION_KEEP,
    SEARCH_THRESHOLD_DB,
    detection_threshold_db,
    fit_calibration,
    write_calibration,
)
from echoloc.localise.evaluation import ClassEvaluation, Evaluation, evaluate, evaluate_classes
from echoloc.localise.locate import FrameObjects
from echoloc.pipeline import (
    check_locatable,
    frame_echoes,
    learn_chain_echo_shape,
    run,
)
from echoloc.tof.echoes import FrameEchoes, frame_time_s
from echoloc.tof.estimators import default_threshold_db
from echoloc.tof.templates import read_template

# --- echoes, locate, evaluate ------------------------------------------------------


@cli.command()
@_processing_options(locating=False)
@click.option("--json", "as_json", is_flag=True, help="JSON Lines per docs/FORMATS.md instead of a table.")
def echoes(processing: Processing, as_json: bool) -> None:
    """Times of flight of the echoes in every frame of RECORDING, per receiver."""
    recording, chain, frames = processing.open()
    if as_json:
        for index in frames:
            click.echo(json_line(echoes_record(frame_echoes(chain, index))))
        return
    table = Table(
        title=f"Echoes in {processing.recording_path} ({processing.estimator_name(recording)}, "
        f"c = {chain.speed_of_sound_m_s:.2f} m/s)"
    )
    for column in ("frame", "receiver", "tof µs", "path m", "amplitude", "SNR dB"):
        table.add_column(column, justify="right")
    for index in frames:
        _echo_rows(table, frame_echoes(chain, index))
    stdout.print(table)


def _echo_rows(table: Table, result: FrameEchoes) -> None:
    for receiver, channel in enumerate(result.channels):
        if len(channel.tof_s) == 0:
            table.add_row(str(result.frame), str(receiver), "-", "-", "-", "-")
        for tof, amplitude, snr in zip(channel.tof_s, channel.amplitude, channel.snr_db, strict=True):
            table.add_row(
                str(result.frame),
                str(receiver),
                f"{tof * 1e6:.3f}",
                f"{tof * result.speed_of_sound_m_s:.5f}",
                f"{amplitude:.4g}",
                f"{snr:.1f}",
            )


@cli.command()
@_processing_options(locating=True)
@click.option("--json", "as_json", is_flag=True, help="JSON Lines per docs/FORMATS.md instead of a table.")
def locate(processing: Processing, as_json: bool) -> None:
    """3-D positions of the reflectors in every frame of RECORDING."""
    recording, chain, frames = processing.open()
    check_locatable(chain)
    if as_json:
        for objects in _located(processing, recording, chain, frames):
            click.echo(json_line(objects_record(objects)))
        return
    table = Table(title=f"Objects in {processing.recording_path} ({processing.estimator_name(recording)})")
    columns = ["frame", "x mm", "y mm", "z mm", "±σ x, y, z mm", "range mm", "rx", "score"]
    for column in columns + (["kind", "normal or edge"] if processing.classes else []):
        table.add_column(column, justify="right")
    for objects in _located(processing, recording, chain, frames):
        _object_rows(table, objects, processing.classes)
    stdout.print(table)


def _output_option(help_text: str) -> Callable[[_Decorated], _Decorated]:
    """``-o/--output OUT``, required: the file a command writes, its format by extension."""
    return _path_option("-o", "--output", "output_path", required=True, help=help_text)


def _object_rows(table: Table, result: FrameObjects, classes: bool = False) -> None:
    if not result.objects:
        table.add_row(str(result.frame), *["-"] * (9 if classes else 7))
    for obj in result.objects:
        table.add_row(str(result.frame), *_object_cells(obj), *(_class_cells(obj) if classes else []))


@cli.command(name="image")
@_processing_options(locating=True)
@click.option("--frame", "frame_index", type=int, default=0, show_default=True, help="Frame to image.")
@click.option("--voxel-m", type=float, default=0.005, show_default=True, help="Voxel edge of the grid, m.")
@_path_option("-o", "--output", "output_path", required=True, help="PNG.")
def image_command(processing: Processing, frame_index: int, voxel_m: float, output_path: Path) -> None:
    """Back-project one frame of RECORDING onto the cubic metre in front and save the image.

    Maximum-intensity projections and slices through the brightest voxel, with the
    objects back-projection locates (crosses) and the recording's truth (circles).
    """
    from echoloc.localise.backprojection import (
        backproject_frame,
        default_grid,
        frame_image,
        prepare_backprojection,
    )
    from echoloc.plots.imaging import save_image_png

    _finite("--voxel-m", voxel_m, positive=True)
    if not 0.001 <= voxel_m <= 0.1:
        raise EchoLocError(f"--voxel-m must be between 0.001 and 0.1 m, got {voxel_m:g}")
    if output_path.suffix.lower() != ".png":
        raise EchoLocError(f"{output_path}: the image is written as PNG (.png)")
    if processing.classes:
        raise EchoLocError("image back-projects a frame: --classes applies to the association (locate)")
    recording, chain, _ = processing.open()
    if not 0 <= frame_index < recording.n_frames:
        raise EchoLocError(f"--frame {frame_index} is outside the recording's {recording.n_frames} frames")
    if recording.transmitters_m.shape[1] != 3:
        raise EchoLocError(f"{processing.recording_path}: images are drawn for 3-D recordings")
    bp = prepare_backprojection(
        recording,
        default_grid(voxel_m),
        speed_of_sound_m_s=chain.speed_of_sound_m_s,
        conditioning=chain.conditioning,
    )
    objects = backproject_frame(bp, frame_index)
    truth = None
    if recording.truth_positions_m is not None:
        rows = recording.truth_positions_m[frame_index]
        truth = rows[np.all(np.isfinite(rows), axis=1)]
    located = np.array([o.position_m for o in objects.objects]).reshape(-1, 3)
    written = save_image_png(
        frame_image(bp, frame_index),
        output_path,
        objects_m=located,
        truth_m=truth,
        title=f"{processing.recording_path.name}, frame {frame_index}: {len(located)} objects",
    )
    stdout.print(f"{len(located)} objects in frame {frame_index}; image written to {written}")


@cli.command(name="export")
@_processing_options(locating=True)
@_output_option("OUT.mcap (ROS 2 Jazzy PointCloud2 + Range per receiver) or OUT.ply (points).")
@click.option("--start-time-s", type=float, default=0.0, show_default=True, help="ROS time of frame 0, s.")
@click.option("--ascii", "ascii_ply", is_flag=True, help="PLY as text instead of binary.")
@click.option("--per-frame", is_flag=True, help="PLY: one file per frame (OUT_000000.ply, ...).")
def export_command(
    processing: Processing, output_path: Path, start_time_s: float, ascii_ply: bool, per_frame: bool
) -> None:
    """Locate every frame of RECORDING and write the objects for robots: MCAP or PLY.

    MCAP: sensor_msgs/msg/PointCloud2 on /echoloc/objects (x, y, z, intensity and the
    full covariance) and sensor_msgs/msg/Range on /echoloc/range/rx{N}, in the frame
    echoloc_sensor_optical_frame (REP 103), with /tf_static from echoloc_sensor_link
    (x forward, z up) to it and to the receivers, and /tf when the sensor moves
    (docs/ROS.md).
    """
    from echoloc.io.export import write_mcap, write_ply

    suffix = output_path.suffix.lower()
    if suffix not in (".mcap", ".ply"):
        raise EchoLocError(f"{output_path}: choose the format by extension, .mcap or .ply")
    given = click.get_current_context().get_parameter_source
    if suffix == ".mcap":
        _finite("--start-time-s", start_time_s, minimum=0.0, maximum=2**31 - 1)  # ROS time: int32 seconds
        if ply_only := [name for name, on in (("--ascii", ascii_ply), ("--per-frame", per_frame)) if on]:
            verb = "is" if len(ply_only) == 1 else "are"
            _warn(f"{' and '.join(ply_only)} {verb} for PLY; MCAP is binary, one file: ignored")
    elif given("start_time_s") is not click.core.ParameterSource.DEFAULT:
        _warn("--start-time-s sets MCAP's ROS times; PLY has no time stamps: ignored")
    recording, chain, frames = processing.open()
    check_locatable(chain)
    results = []
    with _progress(len(frames), "locating", True) as advance:
        for objects in _located(processing, recording, chain, frames):
            results.append(objects)
            advance(1)
    if suffix == ".mcap":
        count = write_mcap(output_path, recording, results, start_time_s=start_time_s)
        stdout.print(f"wrote {count} messages ({len(results)} frames) to {output_path}")
    else:
        written = write_ply(output_path, results, binary=not ascii_ply, per_frame=per_frame)
        points = sum(len(r.objects) for r in results)
        where = written[0] if len(written) == 1 else f"{len(written)} files like {written[0]}"
        stdout.print(f"wrote {points} points ({len(results)} frames) to {where}")


_MAP_FORMATS = (".png", ".npz", ".ply", ".bt", ".ot", ".mcap", ".yaml")


_MAX_SAMPLE_RATE_HZ = 100e6
"""The highest sample rate `waveform` takes: 100 MHz, far above any ultrasonic ADC's, where a
millisecond's pulse is already 100 000 samples (at 1 THz it would be 10^9)."""


def check_grid_options(cell_m: float, height_m: float | None, three_d: bool) -> None:
    """Refuse a map's cell size outside 1 mm - 1 m and a floor plan's height given to a 3-D grid
    (`map` and `batch map` alike), in one line."""
    _finite("--cell-m", cell_m, positive=True)
    if not 0.001 <= cell_m <= 1.0:
        raise EchoLocError(f"--cell-m must be between 0.001 and 1 m, got {cell_m:g}")
    if height_m is not None:
        _finite("--height-m", height_m)
        if three_d:
            raise EchoLocError(
                "--height-m sets the floor plan's height; a --3d grid takes --extent-m instead"
            )


def _extent_option(text: str | None, dims: int) -> list[tuple[float, float]] | None:
    """``--extent-m``: "x0,x1,z0,z1" for a floor plan, "x0,x1,y0,y1,z0,z1" in 3-D."""
    if text is None:
        return None
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise EchoLocError(
            f"--extent-m: expected {2 * dims} numbers separated by commas, got {text!r}"
        ) from None
    if len(values) != 2 * dims or not all(math.isfinite(v) for v in values):
        raise EchoLocError(f"--extent-m: expected {2 * dims} finite numbers, got {text!r}")
    pairs = [(values[2 * i], values[2 * i + 1]) for i in range(dims)]
    if any(high <= low for low, high in pairs):
        raise EchoLocError(f"--extent-m: every range must go from low to high, got {text!r}")
    return pairs


@cli.command(name="map")
@_processing_options(locating=True)
@_output_option(
    "OUT.png (picture), .npz (arrays), .ply (occupied cells), .bt/.ot (OctoMap), "
    ".mcap (ROS 2: nav_msgs/OccupancyGrid or a cloud, /tf, objects) "
    "or .yaml (nav2 map_server: OUT.yaml + OUT.pgm, floor plan).",
)
@click.option("--cell-m", type=float, default=0.02, show_default=True, help="Cell edge, m.")
@click.option(
    "--3d", "three_d", is_flag=True, help="A 3-D grid instead of the floor plan (x-z at one height)."
)
@click.option(
    "--height-m",
    type=float,
    default=None,
    help="Height (y) of the floor plan, m [default: the sensor's mean].",
)
@click.option(
    "--extent-m",
    "extent_text",
    default=None,
    help="Grid extent: x0,x1,z0,z1 (floor plan) or x0,x1,y0,y1,z0,z1 (3-D), m "
    "[default: everywhere the sensor could hear].",
)
@_path_option(
    "--trajectory",
    "trajectory_path",
    help="Sensor poses, TUM format (time x y z qx qy qz qw per line) "
    "[default: the recording's sensor_poses].",
)
@click.option(
    "--objects/--no-objects",
    "with_objects",
    default=True,
    show_default=True,
    help="Also add the located objects with their covariance.",
)
@click.option(
    "--tracks/--no-tracks",
    "with_tracks",
    default=True,
    show_default=True,
    help="Place the echoes one receiver heard alone by following them across poses as the sensor "
    "moves (docs/METHOD.md §8).",
)
def map_command(
    processing: Processing,
    output_path: Path,
    cell_m: float,
    three_d: bool,
    height_m: float | None,
    extent_text: str | None,
    trajectory_path: Path | None,
    with_objects: bool,
    with_tracks: bool,
) -> None:
    """Build an occupancy grid from every frame of RECORDING and write it; the format by extension.

    Each receiver's echoes clear the beam before the first echo and mark the echo's
    arc (ellipse with the transmitter and receiver as foci) occupied; located objects
    add their covariance. The map frame is the frame of the sensor poses (the
    recording's sensor_poses or --trajectory); without poses, the sensor frame. MCAP
    and nav2 files give it as ROS's z-up map frame (REP 103/105, docs/ROS.md).
    """
    from echoloc.maps.map_export import (
        write_grid_npz,
        write_grid_ply,
        write_map_mcap,
        write_nav2_map,
        write_octomap,
    )
    from echoloc.maps.mapping import chain_accumulator, choose_grid, frame_poses, integrate, read_trajectory
    from echoloc.plots.maps import plot_grid

    suffix = output_path.suffix.lower()
    if suffix not in _MAP_FORMATS:
        raise EchoLocError(f"{output_path}: choose the format by extension: {', '.join(_MAP_FORMATS)}")
    check_grid_options(cell_m, height_m, three_d)
    if suffix == ".yaml" and three_d:
        raise EchoLocError(f"{output_path}: a nav2 map (.yaml + .pgm) is a floor plan; drop --3d")
    _check_writable(output_path)
    if suffix == ".yaml":
        _check_writable(output_path.with_suffix(".pgm"))
    if processing.method != "association":
        raise EchoLocError(
            "map reads every receiver's echoes and the association's objects; "
            "--method backprojection is for locate, evaluate, export and image"
        )
    extent = _extent_option(extent_text, 3 if three_d else 2)
    trajectory = read_trajectory(trajectory_path) if trajectory_path is not None else None
    recording, chain, frames = processing.open()
    poses = frame_poses(recording, trajectory)
    spec = choose_grid(
        recording,
        poses[list(frames)],
        cell_m,
        chain.speed_of_sound_m_s,
        three_d=three_d,
        extent_m=extent,
        height_m=height_m,
    )
    accumulator = chain_accumulator(chain, spec, path_sigma_m=processing.path_sigma_m, tracks=with_tracks)
    located: list[FrameObjects] = []

    def results() -> Iterator[tuple[FrameEchoes, FrameObjects | None]]:
        for echoes, objects in run(chain, frames):
            located.append(objects)
            yield echoes, objects if with_objects else None

    started = time.perf_counter()
    with _progress(len(frames), "mapping", True) as advance:
        grid = integrate(accumulator, results(), poses, progress=advance)
    elapsed = time.perf_counter() - started
    written: Path | str
    if suffix == ".png":
        written = plot_grid(grid, output_path, sensor_path_m=poses[list(frames), :3])
    elif suffix == ".npz":
        written = write_grid_npz(grid, output_path)
    elif suffix == ".ply":
        written = write_grid_ply(grid, output_path)
    elif suffix in (".bt", ".ot"):
        written = write_octomap(grid, output_path)
    elif suffix == ".yaml":
        yaml_path, pgm_path = write_nav2_map(grid, output_path)
        written = f"{yaml_path} and {pgm_path}"
    else:
        times = np.array([frame_time_s(recording, i) for i in range(recording.n_frames)])
        write_map_mcap(
            output_path,
            grid,
            poses=poses,
            frame_times_s=times,
            frames=list(frames),
            objects_per_frame=located,
        )
        written = output_path
    n_cells = spec.n_cells
    occupied = int(grid.occupied().sum())
    free = int(grid.free().sum())
    known = int(grid.known().sum())
    shape = " x ".join(str(n) for n in spec.shape)
    stdout.print(
        f"{len(frames)} frames mapped in {elapsed:.1f} s "
        f"({len(frames) / max(elapsed, 1e-9):.0f} frames/s, echoes and objects included) onto "
        f"{shape} cells of {cell_m * 100:g} cm: {occupied} occupied, {free} free, "
        f"{n_cells - known} unknown{_placed_by_tracks(accumulator.n_triangulated)}; written to {written}"
    )


def _placed_by_tracks(n_points: int) -> str:
    """What the map's tracks across poses placed (echoes one receiver heard alone), if any."""
    if not n_points:
        return ""
    return f", {n_points} reflector{'' if n_points == 1 else 's'} placed by tracks across poses"


@cli.command(name="evaluate")
@_processing_options(locating=True)
@click.option(
    "--match-radius-m",
    type=float,
    default=0.02,
    show_default=True,
    help="Largest distance of a located object from its true reflector, m.",
)
@click.option("--json", "as_json", is_flag=True, help="One JSON object with the figures.")
def evaluate_command(processing: Processing, match_radius_m: float, as_json: bool) -> None:
    """Compare located objects with the recording's truth_positions: recall, false objects, RMSE."""
    _finite("--match-radius-m", match_radius_m, positive=True)
    recording, chain, frames = processing.open()
    if recording.truth_positions_m is None:
        raise EchoLocError(f"{processing.recording_path}: has no truth_positions to evaluate against")
    check_locatable(chain)
    results = []
    with _progress(len(frames), "locating", not as_json) as advance:
        for objects in _located(processing, recording, chain, frames):
            results.append(objects)
            advance(1)
    report = evaluate(results, recording.truth_positions_m, match_radius_m)
    classes = None
    if processing.classes and recording.truth_kinds is not None:
        fired = (
            np.zeros(recording.n_frames, dtype=int)
            if recording.frame_transmitter is None
            else recording.frame_transmitter
        )
        classes = evaluate_classes(
            results,
            recording.truth_positions_m,
            recording.truth_kinds,
            recording.transmitters_m[fired],
            match_radius_m=match_radius_m,
        )
    if as_json:
        record = _evaluation_record(report, processing.estimator_name(recording))
        if classes is not None:
            record["classes"] = _classes_record(classes)
        click.echo(json.dumps(_json_safe(record), allow_nan=False))
        return
    _print_evaluation(report, processing.recording_path, processing.estimator_name(recording))
    if classes is not None:
        _print_classes(classes)
    elif processing.classes:
        stdout.print("(no truth_kinds in the recording: the classes are not scored)")


def _classes_record(scored: ClassEvaluation) -> dict[str, Any]:
    """The class figures of ``evaluate --classes --json``."""
    return {
        "kinds": list(scored.kinds),
        "confusion": scored.confusion.tolist(),
        "right_class_rate": scored.right_class_rate,
        "false_rate": scored.false_rate,
        "median_normal_error_deg": _median(scored.normal_errors_deg),
        "median_abs_distance_error_m": _median(np.abs(scored.distance_errors_m)),
    }


def _median(values: NDArray[np.float64]) -> float:
    return float(np.median(values)) if len(values) else float("nan")


def _print_classes(scored: ClassEvaluation) -> None:
    """The confusion matrix of classes, and the planes' normal and distance errors."""
    table = Table(title=f"classes: right for {scored.right_class_rate:.4f} of the true reflectors")
    table.add_column("truth \\ reported")
    for kind in (*scored.kinds, "missed"):
        table.add_column(kind, justify="right")
    for kind, row in zip(scored.kinds, scored.confusion, strict=True):
        if row.sum():
            table.add_row(kind, *(str(int(v)) for v in row))
    stdout.print(table)
    if len(scored.normal_errors_deg):
        normal = _median(scored.normal_errors_deg)
        distance_mm = _median(np.abs(scored.distance_errors_m)) * 1e3
        stdout.print(
            f"planes: median normal error {normal:.3f}°, median |distance error| {distance_mm:.3f} mm "
            f"({len(scored.normal_errors_deg)} sightings)"
        )


def _evaluation_record(report: Evaluation, estimator: str) -> dict[str, Any]:
    return {
        "estimator": estimator,
        "frames": report.n_frames,
        "truth_objects": report.n_truth,
        "located_objects": report.n_located,
        "matched": report.n_matched,
        "recall": report.recall,
        "false_objects": report.n_false,
        "false_rate": report.false_rate,
        "rmse_m": [float(v) for v in report.rmse_m],
        "bias_m": [float(v) for v in report.bias_m],
        "mean_reported_std_m": [float(v) for v in report.mean_std_m],
        "match_radius_m": report.match_radius_m,
    }


def _print_evaluation(report: Evaluation, path: Path, estimator: str) -> None:
    table = Table(title=f"{path}: {report.n_frames} frames, {report.n_truth} true reflectors ({estimator})")
    table.add_column("figure")
    table.add_column("value", justify="right")
    table.add_row("recall", f"{report.recall:.4f} ({report.n_matched}/{report.n_truth})")
    table.add_row("false objects", f"{report.false_rate:.4f} ({report.n_false}/{report.n_located})")
    for axis, rmse, bias, std in zip("xyz", report.rmse_m, report.bias_m, report.mean_std_m, strict=True):
        table.add_row(
            f"{axis}: RMSE / bias / reported σ (mm)",
            f"{rmse * 1e3:.3f} / {bias * 1e3:+.3f} / {std * 1e3:.3f}",
        )
    table.add_row("match radius", f"{report.match_radius_m * 1e3:g} mm")
    stdout.print(table)


@cli.command(name="calibrate")
@_processing_options(locating=False, calibrated=False)
@_path_option("-o", "--output", required=True, help="Calibration JSON to write.")
def calibrate_command(processing: Processing, output: Path) -> None:
    """Fit the speed of sound and a delay per receiver from frames with known targets (truth_positions).

    The file also holds the path error measured from the fit's residuals, which `locate
    --calibration` assumes; for envelope-peak without --threshold-db, the detection threshold
    that 99 % of the targets reach on three receivers (at most the default), which it then
    detects with; and, for envelope-peak (envelope or iq data without a
    waveform), the echo shape learnt from these targets.
    """
    recording, chain, frames = processing.open()
    if recording.truth_positions_m is None:
        raise EchoLocError(f"{processing.recording_path}: has no truth_positions to calibrate against")
    shape = None
    peaks = processing.estimator_name(recording) == "envelope-peak"
    if peaks and processing.template_path is None:
        # No pulse is known: learn the echo's shape from these frames' known targets (the
        # report's BALL template), then time the echoes with it.
        shape = learn_chain_echo_shape(chain, frames, "truth", "learnt")
        chain = processing.chain(recording, shape)
    measure_threshold = peaks and processing.threshold_db is None
    echoes = []
    with _progress(len(frames), "finding echoes", True) as advance:
        for index in frames:
            echoes.append(frame_echoes(chain, index))
            advance(1)
    calibration = fit_calibration(
        recording, echoes, speed_of_sound_m_s=chain.speed_of_sound_m_s, echo_shape=shape
    )
    threshold = ""
    if measure_threshold:
        # With the rig calibrated, look for the targets' echoes again down to the noise and
        # measure the threshold that they need (the fit above keeps the default's echoes).
        template = shape
        if template is None and processing.template_path is not None:
            template = read_template(processing.template_path)
        search = replace(processing, threshold_db=SEARCH_THRESHOLD_DB).chain(recording, template)
        min_receivers = search.locate_options.min_receivers
        measured = detection_threshold_db(
            recording,
            [frame_echoes(search, index) for index in frames],
            calibration,
            ceiling_db=default_threshold_db("envelope-peak"),
            min_receivers=min_receivers,
        )
        calibration = replace(calibration, threshold_db=measured)
        if measured is None:
            threshold = f"; no target heard on {min_receivers} receivers, so no detection threshold measured"
        else:
            threshold = (
                f"; detection threshold {measured:.2f} dB "
                f"({DETECTION_KEEP:.0%} of the targets keep echoes on {min_receivers} receivers)"
            )
    written = write_calibration(calibration, output)
    delays = ", ".join(f"{d * 1e6:+.3f}" for d in calibration.receiver_delays_s)
    sigma = calibration.path_sigma_m or 0.0
    learnt = "" if shape is None else "; the echo shape learnt from them"
    how = "fitted; assumed" if calibration.speed_fitted else "kept: the targets do not determine it; assumed"
    stdout.print(
        f"speed of sound {calibration.speed_of_sound_m_s:.3f} m/s ({how} "
        f"{chain.speed_of_sound_m_s:.3f}); "
        f"receiver delays {delays} µs; {calibration.echoes_used} echoes from {len(frames)} frames, "
        f"residual {calibration.residual_rms_s * 1e9:.1f} ns rms, path σ {sigma * 1e3:.2f} mm{learnt}"
        f"{threshold}. "
        f"Written to {written}."
    )
