"""`echoloc sweep`: a design study over scene and processing parameters on a Dask cluster."""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import click
from rich.table import Table

from echoloc.cli.app import (
    _check_plot,
    _check_writable,
    _path_option,
    _progress,
    _warn,
    cli,
    stderr,
    stdout,
)
from echoloc.errors import EchoLocError
from echoloc.scale.sweep import Sweep, cell, load_sweep, parquet_available, run_sweep, write_table

SHOWN_ROWS = 40
"""Points printed as a table at most; a larger sweep prints its first and last ones."""

SHOWN_WARNINGS = 5
"""Distinct warnings of the points shown at most."""


@cli.command(name="sweep")
@click.argument("sweep_path", metavar="SWEEP.toml", type=click.Path(path_type=Path))
@_path_option(
    "-o",
    "--output",
    required=True,
    help="The table, one row a point: CSV, or Parquet when the name ends .parquet (needs pyarrow).",
)
@_path_option(
    "--plot",
    "plot_path",
    default=None,
    help="Draw a metric against the swept parameter(s) into this PNG (one line per value of a "
    "second parameter).",
)
@click.option(
    "--metric",
    default=None,
    help="The metric --plot draws [default: the sweep file's [plot] y, else its first metric].",
)
@click.option(
    "--frames",
    type=int,
    default=None,
    help="Frames per point instead of the sweep file's (a quick trial run; seeds stay the same).",
)
@click.option(
    "--workers",
    type=int,
    default=None,
    help="Worker processes of the local cluster [default: one a core].",
)
@click.option(
    "--scheduler",
    metavar="tcp://HOST:PORT",
    default=None,
    help="Run on this Dask scheduler's cluster instead of a local one (its workers must see "
    "the files the sweep names).",
)
def sweep_command(
    sweep_path: Path,
    output: Path,
    plot_path: Path | None,
    metric: str | None,
    frames: int | None,
    workers: int | None,
    scheduler: str | None,
) -> None:
    """Simulate, locate and score every point of a sweep file: a grid or random draws of scene
    keys (noise.snr_db, pulse.code, ...), processing options and the receivers' spacing.

    The whole file and every point's scene are checked before the cluster starts. Each
    point's noise is seeded from the sweep's seed and the point's values, so the table is
    the same whatever the workers (all but time_per_frame_s). See docs/SCALE.md.
    """
    sweep = load_sweep(sweep_path)
    if frames is not None:
        sweep = sweep.with_frames(frames)
    if metric is not None and metric not in sweep.study.metrics:
        raise EchoLocError(
            f"--metric must be one of the sweep's metrics ({', '.join(sweep.study.metrics)}), got {metric!r}"
        )
    if output.suffix.lower() == ".parquet" and not parquet_available():
        raise EchoLocError(f"{output}: needs pyarrow: pip install pyarrow")
    _check_writable(output)
    _check_plot(plot_path)
    if plot_path is not None:
        import echoloc.plots  # noqa: F401  (matplotlib missing: one line now, not after the sweep)

    from echoloc.scale.cluster import open_client

    n_points = len(sweep.points)
    start = time.perf_counter()
    with open_client(scheduler, workers) as client:
        n_workers = len(client.scheduler_info().get("workers", {}))
        with _progress(n_points, "sweeping", True) as advance:
            rows = run_sweep(sweep, client, progress=advance)
    elapsed = time.perf_counter() - start
    written = write_table(sweep, rows, output)
    _print_rows(sweep, rows)
    _print_warnings(rows)
    stdout.print(
        f"{n_points} points x {sweep.study.frames} frames in {elapsed:.1f} s on {n_workers} "
        f"worker{'s' if n_workers != 1 else ''}; table written to {written}",
        highlight=False,
    )
    if plot_path is not None:
        from echoloc.plots.sweep import plot_sweep

        stderr.print(f"plot written to {plot_sweep(sweep, rows, plot_path, metric=metric)}", highlight=False)


def _print_rows(sweep: Sweep, rows: Sequence[Mapping[str, Any]]) -> None:
    """The table on stdout: every point of a small sweep, the first and last of a large one;
    the metrics that fit the terminal's width (the table file holds them all)."""
    half = SHOWN_ROWS // 2
    shown = list(rows) if len(rows) <= SHOWN_ROWS else [*rows[:half], None, *rows[-half:]]
    cells = {
        name: [
            "..." if row is None else cell(row[name]) if name in sweep.parameters else _shown(row[name])
            for row in shown
        ]
        for name in ("point", *sweep.parameters, *sweep.study.metrics)
    }
    room = stdout.width - 4
    columns: list[str] = []
    for name, texts in cells.items():
        width = max(len(name), *(len(t) for t in texts)) + 3
        first_metric = name == sweep.study.metrics[0]
        if name in sweep.study.metrics and room - width < 0 and not first_metric:
            break
        columns.append(name)
        room -= width
    left = [m for m in sweep.study.metrics if m not in columns]
    frames = f"{sweep.study.frames} frame{'s' if sweep.study.frames != 1 else ''}"
    table = Table(
        title=f"{sweep.source}: {sweep.kind} of {len(rows)} points, {frames} each",
        caption=f"not shown (in the table file): {', '.join(left)}" if left else None,
    )
    for name in columns:
        table.add_column(name, justify="left" if name in sweep.parameters else "right", no_wrap=True)
    for k in range(len(shown)):
        table.add_row(*(cells[name][k] for name in columns))
    stdout.print(table)


def _shown(value: Any) -> str:
    if isinstance(value, float) and math.isfinite(value):
        return f"{value:.4g}"
    return cell(value)


def _print_warnings(rows: Sequence[Mapping[str, Any]]) -> None:
    """Distinct warnings the points raised, with how many points raised each."""
    counts: dict[str, int] = {}
    for row in rows:
        for message in row.get("_warnings", ()):
            counts[message] = counts.get(message, 0) + 1
    for message, count in list(counts.items())[:SHOWN_WARNINGS]:
        _warn(f"{count} point{'s' if count != 1 else ''}: {message}")
    if len(counts) > SHOWN_WARNINGS:
        _warn(f"and {len(counts) - SHOWN_WARNINGS} more kinds of warning")
