"""``echoloc import``: write a contract recording from the layouts users already have.

``echoloc import spiel FOLDER -o OUT.h5`` reads the CSV layout of the SPiEL/PaCE CH101
data set; ``echoloc import samples FILE --head head.toml -o OUT.h5`` reads plain
samples described by a sensor-head TOML. The reading lives in
:mod:`echoloc.io.importers`; ``docs/IMPORT.md`` is the user's page. Bad input raises
:class:`~echoloc.errors.EchoLocError`, which ``echoloc.cli.commands.main`` turns into one line
on stderr and exit code 2.
"""

from __future__ import annotations

from pathlib import Path

import click
import numpy as np

from echoloc.cli.app import _path_option
from echoloc.errors import EchoLocError, unwritable
from echoloc.io.head import is_sectioned_head, load_head
from echoloc.io.importers import read_head, read_samples, read_samples_with_head, read_spiel
from echoloc.io.recording import Recording, write_recording

_OUTPUT_SUFFIXES = (".h5", ".hdf5", ".npz")


def _check_output(output: Path, force: bool) -> None:
    """Refuse, before reading anything, an output that cannot or must not be written."""
    if output.suffix.lower() not in _OUTPUT_SUFFIXES:
        raise EchoLocError(f"{output}: unknown extension {output.suffix!r}, expected .h5, .hdf5 or .npz")
    if problem := unwritable(output):
        raise EchoLocError(f"{output}: {problem}")
    if output.exists() and not force:
        raise EchoLocError(f"{output}: already exists (pass --force to replace it)")


def _write(recording: Recording, output: Path, what: str) -> None:
    written = write_recording(recording, output)
    parts = [
        f"{recording.n_frames} frame(s) × {recording.n_receivers} receivers × "
        f"{recording.n_samples} {recording.signal_kind} samples at {recording.sample_rate_hz:g} Hz"
    ]
    if recording.background is not None:
        parts.append("background per frame" if recording.background.ndim == 3 else "one background")
    if recording.truth_positions_m is not None:
        known = int((~np.isnan(recording.truth_positions_m).all(axis=(1, 2))).sum())
        parts.append(f"truth for {known} frame(s)")
    click.echo(f"echoloc: import: wrote {written} from {what}: {'; '.join(parts)}", err=True)


_output_option = _path_option(
    "-o",
    "--output",
    required=True,
    help="Recording to write (.h5, or .npz).",
)
_force_option = click.option("--force", is_flag=True, help="Replace OUT if it exists.")


@click.group(name="import", context_settings={"help_option_names": ["-h", "--help"]})
def import_group() -> None:
    """Write a contract recording (docs/FORMATS.md) from another layout (docs/IMPORT.md)."""


@import_group.command(name="spiel")
@click.argument("folder", metavar="FOLDER", type=click.Path(path_type=Path))
@_output_option
@_path_option(
    "--head",
    "head_path",
    help="Sensor-head TOML overriding the CH101 head (positions, rate, air).",
)
@click.option(
    "--samples",
    "n_samples",
    type=click.IntRange(min=1),
    default=None,
    help="Keep the first N samples of every channel [default: drop the last 2, as the published loader].",
)
@_force_option
def spiel_command(
    folder: Path, output: Path, head_path: Path | None, n_samples: int | None, force: bool
) -> None:
    """Import the SPiEL/PaCE CH101 CSV layout: FOLDER of *_frames.csv/*_labels.csv pairs.

    Backgrounds come from the sibling folder FOLDER_bg when it exists.
    """
    _check_output(output, force)
    head = None if head_path is None else read_head(head_path)
    recording = read_spiel(folder, head, n_samples)
    _write(recording, output, f"{folder} ({recording.n_frames} file pairs)")


@import_group.command(name="samples")
@click.argument("samples_path", metavar="FILE", type=click.Path(path_type=Path))
@_path_option(
    "--head",
    "head_path",
    required=True,
    help="Sensor-head TOML: an import head (docs/IMPORT.md: sample rate, signal kind, positions, "
    "files, truth) or a live head's file (docs/HEAD.md).",
)
@_output_option
@_force_option
def samples_command(samples_path: Path, head_path: Path, output: Path, force: bool) -> None:
    """Import plain samples described by a sensor-head TOML.

    FILE is a .npy of shape (n_frames, n_rx, n_samples), or a text table (.csv, comma
    or whitespace separated) of one row per frame and receiver: row r is frame
    r // n_rx, receiver r % n_rx.
    """
    _check_output(output, force)
    if is_sectioned_head(head_path):  # a live head's file (docs/HEAD.md) serves too
        recording = read_samples_with_head(samples_path, load_head(head_path))
    else:
        recording = read_samples(samples_path, read_head(head_path))
    _write(recording, output, str(samples_path))
