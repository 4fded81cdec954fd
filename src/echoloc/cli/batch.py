"""`echoloc batch`: many recordings through the chain on a Dask cluster."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import click
from rich.table import Table
from rich.text import Text

from echoloc.cli.app import (
    _CHAIN_FIELDS,
    _WORKERS_OPTION,
    ChainSettings,
    _chain_option_decorators,
    _finite,
    _path_option,
    _progress,
    _warn,
    cli,
    stdout,
)
from echoloc.errors import EchoLocError
from echoloc.scale.batch import (
    DEFAULT_CHUNK_FRAMES,
    JOBS,
    OUTPUTS,
    BatchJob,
    FileOutcome,
    MapSettings,
    find_inputs,
    run_batch,
)

_JOB_OPTIONS = {
    "match_radius_m": ("--match-radius-m", "evaluate"),
    "cell_m": ("--cell-m", "map"),
    "three_d": ("--3d", "map"),
    "height_m": ("--height-m", "map"),
    "extent_text": ("--extent-m", "map"),
    "with_objects": ("--objects/--no-objects", "map"),
    "with_tracks": ("--tracks/--no-tracks", "map"),
}
"""The options of one job only, and that job."""


def _batch_options(func: Any) -> Any:
    """The chain's options as `locate` takes them, less its --workers (threads of the matched
    filter: a batch's --workers are processes, each running one thread)."""
    for decorator in reversed(_chain_option_decorators(locating=True)):
        if decorator is not _WORKERS_OPTION:
            func = decorator(func)
    return func


@cli.command(name="batch")
@click.argument("job", type=click.Choice(JOBS))
@click.argument("inputs", nargs=-1, required=True, metavar="INPUTS...")
@_path_option(
    "-o",
    "--outdir",
    "outdir",
    help="Folder for the outputs (made if missing) [default: next to each input].",
)
@click.option(
    "--scheduler",
    default=None,
    metavar="ADDR",
    help="Run on the Dask cluster of this scheduler (tcp://HOST:8786) instead of a local one.",
)
@click.option(
    "--workers",
    "n_workers",
    type=int,
    default=None,
    help="Worker processes of the local cluster [default: one a core].",
)
@click.option(
    "--chunk-frames",
    type=int,
    default=DEFAULT_CHUNK_FRAMES,
    show_default=True,
    help="Most frames of samples a task reads at once (a file is split into chunks of them).",
)
@click.option("--force", is_flag=True, help="Redo the outputs that are complete already.")
@click.option(
    "--frames", "frames_text", default=None, help="Frames of each file to process: N or START:STOP."
)
@click.option(
    "--repair-nonfinite",
    is_flag=True,
    help="Replace NaN or infinite samples by 0 (with a warning) instead of refusing the file.",
)
@_batch_options
@click.option(
    "--match-radius-m",
    type=float,
    default=0.02,
    show_default=True,
    help="evaluate: largest distance of a located object from its true reflector, m.",
)
@click.option("--cell-m", type=float, default=0.02, show_default=True, help="map: cell edge, m.")
@click.option("--3d", "three_d", is_flag=True, help="map: a 3-D grid instead of the floor plan.")
@click.option("--height-m", type=float, default=None, help="map: height (y) of the floor plan, m.")
@click.option(
    "--extent-m",
    "extent_text",
    default=None,
    help="map: x0,x1,z0,z1 (floor plan) or x0,x1,y0,y1,z0,z1 (3-D), m [default: everywhere heard].",
)
@click.option(
    "--objects/--no-objects",
    "with_objects",
    default=True,
    show_default=True,
    help="map: also add the located objects with their covariance.",
)
@click.option(
    "--tracks/--no-tracks",
    "with_tracks",
    default=True,
    show_default=True,
    help="map: place the echoes one receiver heard alone by following them across poses.",
)
def batch_command(
    job: str,
    inputs: tuple[str, ...],
    outdir: Path | None,
    scheduler: str | None,
    n_workers: int | None,
    chunk_frames: int,
    force: bool,
    frames_text: str | None,
    repair_nonfinite: bool,
    match_radius_m: float,
    cell_m: float,
    three_d: bool,
    height_m: float | None,
    extent_text: str | None,
    with_objects: bool,
    with_tracks: bool,
    **chain_options: Any,
) -> None:
    """Run JOB (echoes, locate, evaluate or map) on many recordings, on a Dask cluster.

    INPUTS are recording files, folders (their .h5, .hdf5 and .npz files) or quoted glob
    patterns ("runs/**/*.h5"). Each file's output goes next to it, or to --outdir:
    NAME.echoes.jsonl and NAME.locate.jsonl (what `echoloc echoes FILE --json` and `echoloc
    locate FILE --json` print), NAME.evaluate.json (`echoloc evaluate FILE --json`) or
    NAME.map.npz (`echoloc map FILE -o NAME.map.npz`), the same whatever the workers and
    chunks. Files are split into chunks of --chunk-frames frames, spread over the workers.

    An output complete already is skipped (--force redoes it); one half-written when a run
    was stopped is made again. A file that cannot be read or processed fails alone: the
    summary names it, and the exit code is 2 once every other file is done. By default a
    local cluster of one single-threaded worker process a core runs on 127.0.0.1; see
    docs/SCALE.md for a cluster of several machines.
    """
    context = click.get_current_context()
    for name, (flag, owner) in _JOB_OPTIONS.items():
        if job != owner and context.get_parameter_source(name) is not click.core.ParameterSource.DEFAULT:
            raise EchoLocError(f"{flag} is an option of the {owner} job, not of {job}")
    settings = ChainSettings(**{k: chain_options.pop(k) for k in _CHAIN_FIELDS if k in chain_options})
    map_settings = MapSettings()
    if job == "map":
        map_settings = _map_settings(cell_m, three_d, height_m, extent_text, with_objects, with_tracks)
    if job == "evaluate":
        _finite("--match-radius-m", match_radius_m, positive=True)
    spec = BatchJob(
        job=job,
        settings=settings,
        frames_text=frames_text,
        repair_nonfinite=repair_nonfinite,
        match_radius_m=match_radius_m,
        map=map_settings,
        chunk_frames=chunk_frames,
    )
    spec.check()  # bad options before a cluster starts
    found, unmatched = find_inputs(inputs)
    if not found and not unmatched:
        raise EchoLocError(f"no recording (.h5, .hdf5, .npz) in {', '.join(inputs)}")
    from echoloc.scale.cluster import open_client

    started = time.perf_counter()
    outcomes: list[FileOutcome] = list(unmatched)
    if found:
        with (
            open_client(scheduler, n_workers) as client,
            _progress(len(found), f"batch {job}", True) as advance,
        ):
            outcomes += run_batch(
                client, spec, found, outdir=outdir, force=force, progress=advance, warn=_warn
            )
    _print_summary(job, outcomes, time.perf_counter() - started)
    failed = sum(outcome.status == "failed" for outcome in outcomes)
    if failed:
        raise EchoLocError(f"{failed} of {len(outcomes)} input(s) failed (see the summary)")


def _map_settings(
    cell_m: float,
    three_d: bool,
    height_m: float | None,
    extent_text: str | None,
    with_objects: bool,
    with_tracks: bool,
) -> MapSettings:
    """The map options, refused as `echoloc map` refuses them."""
    from echoloc.cli.processing import _extent_option, check_grid_options

    check_grid_options(cell_m, height_m, three_d)
    extent = _extent_option(extent_text, 3 if three_d else 2)
    return MapSettings(
        cell_m=cell_m,
        three_d=three_d,
        height_m=height_m,
        extent_m=None if extent is None else tuple(extent),
        with_objects=with_objects,
        with_tracks=with_tracks,
    )


def _print_summary(job: str, outcomes: list[FileOutcome], seconds: float) -> None:
    """One row a file: its status, frames and output, or why it failed; then the counts."""
    table = Table()
    table.add_column("input", no_wrap=True)
    table.add_column("status", no_wrap=True)
    table.add_column("frames", justify="right", no_wrap=True)
    table.add_column("output, or why it failed", overflow="fold")
    for outcome in outcomes:
        if outcome.status == "failed":
            what = outcome.detail
        else:
            what = str(outcome.output)
            if outcome.detail and outcome.status == "done":
                what += f" ({outcome.detail})"
        frames = str(outcome.frames) if outcome.status == "done" else ""
        table.add_row(Text(str(outcome.input)), outcome.status, frames, Text(what))
    stdout.print(table, highlight=False)
    counts = {status: sum(o.status == status for o in outcomes) for status in ("done", "skipped", "failed")}
    stdout.print(
        Text(
            f"batch {job} ({OUTPUTS[job]}): {counts['done']} done, {counts['skipped']} skipped "
            f"(complete already), {counts['failed']} failed, in {seconds:.1f} s"
        ),
        highlight=False,
    )
