"""Many recordings through the chain on a Dask cluster: ``echoloc batch`` (issue 35).

Each input file gets one output, written next to it or in an output folder, with exactly
what the serial command gives for it with the same options (:data:`OUTPUTS`):
``NAME.echoes.jsonl`` and ``NAME.locate.jsonl`` byte for byte the stdout of ``echoloc
echoes FILE --json`` and ``echoloc locate FILE --json``, ``NAME.evaluate.json`` that of
``echoloc evaluate FILE --json``, and ``NAME.map.npz`` the arrays of ``echoloc map FILE -o
NAME.map.npz``, whatever the number of workers and the size of the chunks.

How a file is cut up without changing a frame's result:

- **Plan** (one task a file, :func:`_plan_task`): the file is opened
  (:class:`echoloc.io.recording.RecordingParts`: the header and the per-frame datasets, no
  samples yet) and the chain prepared from exactly the frames the serial chain reads to
  prepare itself: the up to :data:`~echoloc.tof.channel_health.ASSESS_FRAMES` frames spread
  over the file its channel check assesses (so the same channels are corrected, re-read or
  left out), and for the envelope-peak estimator the first
  :data:`~echoloc.tof.envelope_peaks.RING_DOWN_FRAMES` frames its ring-down is measured on.
  What that gives (the channel check, the receivers used, the ring-down) travels to the
  chunk tasks in a :class:`FilePlan`.
- **Chunks** (:func:`_chunk_task`): the file's frames are cut into ranges; a task reads
  its range (and only that: a worker holds at most ``chunk_frames`` frames of samples,
  beside the plan's up to 64) and runs the chain on it, prepared from the header with the
  plan's channel check. Where a frame's result depends on the frames before it (several
  transmitters fired in turn are located together: the association takes the latest frame
  of every other transmitter among the last n_tx - 1, back-projection the latest of each,
  however old), the task also runs the frames before its range that the serial run would
  hold at its first frame, and drops their results. A compressed NPZ archive can only be
  read from its start: its chunks run one after the other in one task.
- **Map**: occupancy accumulates with clamping, so frame order matters: one task a file
  reads its frames chunk by chunk, in order, into one grid.

Outputs are written by this process (the client), never by a worker: each to a temporary
name beside it (``.NAME.JOB.partial.EXT``), renamed once complete (:func:`_commit`). A
complete output is skipped on the next run (``force`` redoes it); a temporary left by a
run that was killed is removed and its output made again. Tasks only read, so a task
Dask runs again after its worker died gives the same result, and each output is written
once. A file that cannot be read or processed fails alone (:class:`FileOutcome`).
"""

from __future__ import annotations

import atexit
import collections
import contextlib
import functools
import glob
import json
import os
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from echoloc.errors import EchoLocError
from echoloc.io.output import echoes_record, json_line, objects_record
from echoloc.io.recording import Recording, RecordingParts, constant_receivers

if TYPE_CHECKING:
    from echoloc.cli.app import ChainSettings
    from echoloc.localise.backprojection import Backprojector
    from echoloc.localise.locate import FrameObjects
    from echoloc.maps.mapping import OccupancyGrid
    from echoloc.pipeline import Chain
    from echoloc.tof.channel_health import ChannelWatch
    from echoloc.tof.templates import Template

JOBS = ("echoes", "locate", "evaluate", "map")
"""What a batch runs on every file: the serial command of that name."""

OUTPUTS = {
    "echoes": ".echoes.jsonl",
    "locate": ".locate.jsonl",
    "evaluate": ".evaluate.json",
    "map": ".map.npz",
}
"""The output of each job, appended to the input's name less its extension."""

RECORDING_SUFFIXES = (".h5", ".hdf5", ".npz")
"""The files a folder given as input contributes (outputs of ``map``, ``*.map.npz``, excepted)."""

DEFAULT_CHUNK_FRAMES = 256
"""Frames a task reads at once by default: 20 MB of samples at 4 x 2400 (float64), enough
that a task's fixed costs (preparing the chain, a reader process) stay small beside it."""

MAX_OPEN_FILES = 4
"""Recordings a worker keeps open between tasks (each HDF5 file with its reader process)."""

_GLOB_CHARACTERS = frozenset("*?[")


# --- what to run ----------------------------------------------------------------------------


@dataclass(frozen=True)
class MapSettings:
    """The options of ``echoloc map`` a batch takes (a file's own ``--trajectory`` excepted)."""

    cell_m: float = 0.02
    three_d: bool = False
    height_m: float | None = None
    extent_m: tuple[tuple[float, float], ...] | None = None
    with_objects: bool = True
    with_tracks: bool = True


@dataclass(frozen=True, kw_only=True)
class BatchJob:
    """What a batch runs on every file: the job (:data:`JOBS`), the chain's settings (those of
    ``echoloc locate``), the frames, and the options of ``evaluate`` and ``map``."""

    job: str
    settings: ChainSettings
    frames_text: str | None = None
    repair_nonfinite: bool = False
    match_radius_m: float = 0.02
    map: MapSettings = field(default_factory=MapSettings)
    chunk_frames: int = DEFAULT_CHUNK_FRAMES

    def check(self) -> Template | None:
        """Refuse bad values before any file is read; the template (None: not given)."""
        if self.job not in JOBS:
            raise EchoLocError(f"unknown job {self.job!r}: choose from {', '.join(JOBS)}")
        if self.chunk_frames < 1:
            raise EchoLocError(f"--chunk-frames must be >= 1, got {self.chunk_frames}")
        if self.job == "map" and self.settings.method != "association":
            raise EchoLocError(
                "map reads every receiver's echoes and the association's objects; "
                "--method backprojection is for locate and evaluate"
            )
        return self.settings.check()


@dataclass(frozen=True, eq=False)
class FilePlan:
    """What the chunk tasks of one file share, found once by :func:`_plan_task`.

    ``frames``: the frames processed. ``context``: how many frames before a chunk the
    association needs (n_tx - 1 with transmitters combined, else 0). ``watch`` and
    ``usable``: the chain's channel check and the receivers it uses, as the serial chain
    has them. ``ring_down``: envelope-peak's blind samples per receiver (None: another
    estimator). ``backprojection``: for ``--method backprojection``, the receivers it uses
    (every one not dead over the whole file) and its echo finder's channel check.
    """

    source: str
    n_frames: int
    frames: range
    context: int
    random_access: bool
    watch: ChannelWatch | None
    usable: NDArray[np.bool_]
    ring_down: NDArray[np.int64] | None = None
    backprojection: tuple[NDArray[np.bool_], ChannelWatch | None, NDArray[np.bool_] | None] | None = None


@dataclass(frozen=True)
class _Reported:
    """A task's value and the warnings it raised (said once per file by the client), or why the
    file failed."""

    value: Any
    warnings: tuple[str, ...] = ()
    error: str | None = None


@dataclass(frozen=True)
class FileOutcome:
    """What became of one input: ``status`` is ``done``, ``skipped`` (its output was complete
    already) or ``failed`` (``detail`` says why, in one line); ``detail`` also says when a
    half-written output of an earlier run was removed."""

    input: Path
    output: Path | None
    status: str
    detail: str = ""
    frames: int = 0
    seconds: float = 0.0


# --- inputs and outputs -----------------------------------------------------------------------


def _is_output(path: Path) -> bool:
    """A batch's own output or temporary, which a folder or glob never feeds back in."""
    name = path.name
    return name.startswith(".") or any(name.endswith(suffix) for suffix in OUTPUTS.values())


def find_inputs(items: Sequence[str | os.PathLike[str]]) -> tuple[list[Path], list[FileOutcome]]:
    """The recordings ``items`` name: files as given, folders' ``*.h5``, ``*.hdf5`` and ``*.npz``
    (sorted, not recursive), and glob patterns' matches (sorted; ``**`` recurses), each once.
    Also an outcome ``failed`` for each pattern that matches nothing (a file that does not
    exist is kept: reading it fails with its own line)."""
    found: list[Path] = []
    failed: list[FileOutcome] = []
    seen: set[Path] = set()

    def add(path: Path) -> None:
        key = Path(os.path.abspath(path))
        if key not in seen:
            seen.add(key)
            found.append(path)

    for item in items:
        text = os.fspath(item)
        path = Path(text)
        if path.is_dir():
            for child in sorted(path.iterdir()):
                if child.suffix.lower() in RECORDING_SUFFIXES and child.is_file() and not _is_output(child):
                    add(child)
        elif path.exists() or not _GLOB_CHARACTERS & set(text):
            add(path)
        else:
            matches = [
                Path(match)
                for match in sorted(glob.glob(text, recursive=True))
                if Path(match).is_file() and not _is_output(Path(match))
            ]
            if not matches:
                failed.append(FileOutcome(path, None, "failed", f"{text}: matches no file"))
            for match in matches:
                add(match)
    return found, failed


def output_path(recording: Path, job: str, outdir: Path | None = None) -> Path:
    """Where the output of ``job`` for ``recording`` goes: ``NAME`` + :data:`OUTPUTS` [job], next
    to it or in ``outdir``; ``NAME`` is its file name less its extension."""
    name = recording.name[: -len(recording.suffix)] if recording.suffix else recording.name
    return (outdir if outdir is not None else recording.parent) / f"{name}{OUTPUTS[job]}"


def temporary_path(output: Path) -> Path:
    """The name an output is written under until it is complete (hidden, same extension)."""
    return output.with_name(f".{output.name[: -len(output.suffix)]}.partial{output.suffix}")


def _commit(temporary: Path, output: Path) -> None:
    """Make a complete temporary the output: on disk, then renamed in one step."""
    with open(temporary, "rb") as handle:
        os.fsync(handle.fileno())
    os.replace(temporary, output)
    with contextlib.suppress(OSError):
        directory = os.open(output.parent, os.O_RDONLY)
        try:
            os.fsync(directory)
        finally:
            os.close(directory)


# --- the workers' side --------------------------------------------------------------------------

_open_files: collections.OrderedDict[tuple[str, bool], tuple[tuple[int, int, int], RecordingParts]] = (
    collections.OrderedDict()
)
_open_lock = threading.Lock()


def close_open_files() -> None:
    """Close the files this process keeps open for tasks (their HDF5 reader processes too):
    at exit, and for a cluster run inside this process when it is done."""
    with _open_lock:
        while _open_files:
            _open_files.popitem()[1][1].close()


atexit.register(close_open_files)


def _parts(path: str, repair_nonfinite: bool) -> RecordingParts:
    """The file opened for reading in parts, kept open for the next task on it in this worker
    (the last :data:`MAX_OPEN_FILES`), opened again when it changed since."""
    key = (path, repair_nonfinite)
    try:
        info = os.stat(path)
        identity = (info.st_ino, info.st_size, info.st_mtime_ns)
    except OSError:
        identity = (0, 0, 0)  # opening says what is wrong
    with _open_lock:
        held = _open_files.pop(key, None)
        if held is not None:
            if held[0] == identity:
                _open_files[key] = held
                return held[1]
            held[1].close()
        parts = RecordingParts(path, repair_nonfinite=repair_nonfinite)
        _open_files[key] = (identity, parts)
        while len(_open_files) > MAX_OPEN_FILES:
            _open_files.popitem(last=False)[1][1].close()
        return parts


@contextlib.contextmanager
def _recorded(lines: list[str]) -> Iterator[None]:
    """The warnings raised inside, added to ``lines`` (one line each, once) instead of shown."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            yield
        finally:
            for item in caught:
                text = " ".join(str(item.message).split())
                if text not in lines:
                    lines.append(text)


def _reporting(function: Callable[..., Any]) -> Callable[..., _Reported]:
    """A task: its value with the warnings it raised; a file it cannot read or process gives the
    reason (one line) instead of an error, which Dask would log as a task that failed."""

    @functools.wraps(function)
    def task(*args: Any) -> _Reported:
        said: list[str] = []
        try:
            with _recorded(said):
                value = function(*args)
        except (EchoLocError, OSError, MemoryError) as error:
            return _Reported(None, tuple(said), _failure(error))
        return _Reported(value, tuple(said))

    return task


@_reporting
def _plan_task(path: str, job: BatchJob, template: Template | None) -> FilePlan:
    """Open the file, check it as the serial command would, and find what its chunks share."""
    from echoloc.cli.app import _frames_option
    from echoloc.pipeline import check_locatable, recording_combines_transmitters
    from echoloc.tof.channel_health import assessed_frames
    from echoloc.tof.envelope_peaks import RING_DOWN_FRAMES, ring_down_samples

    parts = _parts(path, job.repair_nonfinite)
    header = parts.header
    n_frames = parts.n_frames
    frames = _frames_option(job.frames_text, n_frames)
    assessed = replace(header, frames=parts.frames_at(assessed_frames(n_frames).tolist()))
    _warn_dead(assessed)
    chain = job.settings.chain(assessed, template)
    if job.job == "evaluate" and parts.per_frame["truth_positions_m"] is None:
        raise EchoLocError(f"{path}: has no truth_positions to evaluate against")
    if job.job in ("locate", "evaluate"):
        check_locatable(chain)
    ring_down = None
    if job.settings.estimator_name(header) == "envelope-peak":
        count = min(n_frames, RING_DOWN_FRAMES)
        first = (
            replace(header, background=parts.background(0, count))
            if parts.per_frame_background
            else replace(header, frames=parts.frames(0, count))
        )
        ring_down = ring_down_samples(first)
    backprojection = None
    if job.job != "echoes" and job.settings.method == "backprojection":
        backprojection = _plan_backprojection(parts, assessed, chain, job.chunk_frames)
    fired = parts.per_frame["frame_transmitter"]
    combined = job.job != "echoes" and recording_combines_transmitters(header, fired)
    context = len(header.transmitters_m) - 1 if combined else 0
    plan = FilePlan(
        source=path,
        n_frames=n_frames,
        frames=frames,
        context=context,
        random_access=parts.random_access,
        watch=chain.channel_watch,
        usable=chain.usable_receivers,
        ring_down=ring_down,
        backprojection=backprojection,
    )
    return plan


def _warn_dead(assessed: Recording) -> None:
    """Warn about the receivers whose samples are all equal on the frames the channel check reads:
    :func:`~echoloc.io.recording.read_recording` warns about those of the whole file (which takes
    every sample), and the channel check leaves both out without a word of its own."""
    from echoloc.io.recording import RecordingWarning, dead_receivers

    dead = dead_receivers(assessed)
    if dead:
        which = (
            f"receiver {dead[0]} looks" if len(dead) == 1 else f"receivers {', '.join(map(str, dead))} look"
        )
        warnings.warn(
            f"{assessed.source}: {which} dead: every sample equal on the {assessed.n_frames} frames "
            "its channels were checked on",
            RecordingWarning,
            stacklevel=2,
        )


def _plan_backprojection(
    parts: RecordingParts, assessed: Recording, chain: Chain, chunk_frames: int
) -> tuple[NDArray[np.bool_], ChannelWatch | None, NDArray[np.bool_] | None]:
    """What back-projection takes from the whole file, as
    :func:`~echoloc.localise.backprojection.prepare_backprojection` finds it: the receivers
    not dead over all of it (read chunk by chunk), refused or warned about as it does; and,
    where it finds echoes to restore, its echo finder's channel check and receivers."""
    from echoloc.localise.backprojection import BackprojectionOptions, check_working_receivers, default_grid
    from echoloc.pipeline import prepare

    header = parts.header
    blocks = (
        parts.frames(start, min(start + chunk_frames, parts.n_frames))
        for start in range(0, parts.n_frames, chunk_frames)
    )
    usable = np.ones(header.n_receivers, dtype=bool)
    usable[constant_receivers(blocks)] = False
    options = BackprojectionOptions()
    check_working_receivers(header, int(usable.sum()), default_grid().dim, options)
    if not (options.restore and header.signal_kind == "rf" and header.firing != "simultaneous"):
        return usable, None, None
    finder = prepare(assessed, speed_of_sound_m_s=chain.speed_of_sound_m_s, conditioning=chain.conditioning)
    return usable, finder.channel_watch, finder.usable_receivers


def _peak_estimator(header: Recording, chain: Chain, ring_down: NDArray[np.int64]) -> Any:
    """The chain's envelope-peak estimator with the file's ring-down (``prepare`` measures it on
    the first frames of the recording it is given, here a header without any)."""
    from echoloc.tof.conditioning import blinded
    from echoloc.tof.envelope_peaks import peak_echoes, prepare_peak_detector
    from echoloc.tof.estimators import Estimator

    detector = replace(prepare_peak_detector(header, chain.echo_options.template), blind_samples=ring_down)

    def prepared(options: Any) -> Estimator:
        return lambda frame: peak_echoes(frame, detector, options)

    return blinded(prepared, header, chain.conditioning, chain.echo_options)


def _file_chain(job: BatchJob, template: Template | None, plan: FilePlan, header: Recording) -> Chain:
    """The file's chain, as the serial command prepares it, on ``header`` (no frames), with the
    plan's channel check: the chunk tasks then give it their frames (:func:`_on`)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the plan said them once
        chain = job.settings.chain(header, template)
    chain = replace(chain, channel_watch=plan.watch, usable_receivers=plan.usable)
    if plan.ring_down is not None:
        chain = replace(chain, estimator=_peak_estimator(header, chain, plan.ring_down))
    return chain


def _on(chain: Chain, recording: Recording) -> Chain:
    """``chain`` running on ``recording``'s frames, sharing its locators (the same geometry)."""
    moved = replace(chain, recording=recording)
    vars(moved)["_by_receivers"] = chain._by_receivers
    return moved


_backprojectors: dict[tuple[Any, ...], tuple[RecordingParts, Backprojector]] = {}
_backprojectors_lock = threading.Lock()


def _backprojector(
    chain: Chain, plan: FilePlan, parts: RecordingParts, key: tuple[Any, ...]
) -> Backprojector:
    """Back-projection as the serial command prepares it, on ``chain``'s header: with the
    receivers and the echo finder's channel check of the plan. Its path table takes seconds
    to build: a worker keeps the last one for the next task on the same file (opened as
    ``parts``: a file changed since is opened again)."""
    from echoloc.localise.backprojection import prepare_backprojection

    with _backprojectors_lock:
        found = _backprojectors.get(key)
        if found is not None and found[0] is parts:
            return found[1]
        assert plan.backprojection is not None
        usable, watch, finder_usable = plan.backprojection
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the plan said them once
            bp = prepare_backprojection(
                chain.recording, speed_of_sound_m_s=chain.speed_of_sound_m_s, conditioning=chain.conditioning
            )
        finder = bp.chain
        if finder is not None and finder_usable is not None:
            finder = replace(finder, channel_watch=watch, usable_receivers=finder_usable)
        bp = replace(bp, usable_receivers=usable, chain=finder)
        _backprojectors.clear()
        _backprojectors[key] = (parts, bp)
        return bp


def _times(header: Recording, frame_times_s: NDArray[np.float64] | None, indices: Sequence[int]) -> Any:
    """Start times of frames ``indices``, as :func:`echoloc.tof.echoes.frame_time_s` gives them."""
    if frame_times_s is not None:
        return frame_times_s[list(indices)]
    return np.array([index * header.n_samples / header.sample_rate_hz for index in indices], dtype=float)


class _Rows:
    """The frames of a file for chunks taken in order, each chunk a recording of its own: the
    frames before a chunk it needs (its context) are those the chunk before kept, else read."""

    def __init__(self, parts: RecordingParts) -> None:
        self.parts = parts
        self.kept: dict[int, tuple[NDArray[Any], NDArray[Any] | None]] = {}

    def recording(self, indices: Sequence[int], keep: Iterable[int] = ()) -> Recording:
        """Frames ``indices`` (ascending) of the file as a recording (its frame k is the file's
        ``indices[k]``); the rows of ``keep`` (among ``indices``) are kept for the next chunk."""
        parts = self.parts
        header = parts.header
        missing = [i for i in indices if i not in self.kept]
        fresh = dict(zip(missing, parts.frames_at(missing), strict=True))
        frames = np.stack([self.kept[i][0] if i in self.kept else fresh[i] for i in indices])
        backgrounds: NDArray[Any] | None = None
        if parts.per_frame_background:
            rows = dict(zip(missing, parts.samples_at("background", missing), strict=True))
            backgrounds = np.stack([rows[i] if i in rows else self.kept[i][1] for i in indices])  # type: ignore[misc]
        wanted = set(keep)
        self.kept = {
            i: (frames[k], None if backgrounds is None else backgrounds[k])
            for k, i in enumerate(indices)
            if i in wanted
        }
        per_frame = parts.per_frame
        rows_of = list(indices)

        def pick(name: str) -> Any:
            values = per_frame[name]
            return None if values is None else values[rows_of]

        return replace(
            header,
            frames=frames,
            frame_times_s=_times(header, per_frame["frame_times_s"], rows_of),
            frame_transmitter=pick("frame_transmitter"),
            truth_positions_m=pick("truth_positions_m"),
            sensor_poses=pick("sensor_poses"),
            background=header.background if backgrounds is None else backgrounds,
        )


def _context(plan: FilePlan, fired: NDArray[np.int64] | None, start: int, backprojection: bool) -> list[int]:
    """The frames before ``start`` whose results the serial run still holds at frame ``start``:
    :func:`echoloc.pipeline.combine_latest` those of the last n_tx - 1 frames,
    :func:`echoloc.localise.backprojection.run_backprojection` the latest of every other
    transmitter, however old."""
    first = plan.frames.start
    if plan.context == 0 or start <= first:
        return []
    if not backprojection or fired is None:
        return list(range(max(first, start - plan.context), start))
    before = fired[first:start]
    latest = [
        first + int(hits[-1])
        for transmitter in range(plan.context + 1)
        if transmitter != fired[start] and len(hits := np.flatnonzero(before == transmitter))
    ]
    return sorted(latest)


def _chunk_recordings(
    parts: RecordingParts, plan: FilePlan, ranges: Sequence[tuple[int, int]], backprojection: bool
) -> Iterator[tuple[Recording, list[int], int]]:
    """Each range of frames as a recording with its context frames first; the file's indices of
    its frames, and how many of them are context."""
    rows = _Rows(parts)
    fired = parts.per_frame["frame_transmitter"]
    for n, (start, stop) in enumerate(ranges):
        context = _context(plan, fired, start, backprojection)
        keep = _context(plan, fired, ranges[n + 1][0], backprojection) if n + 1 < len(ranges) else []
        indices = [*context, *range(start, stop)]
        yield rows.recording(indices, keep), indices, len(context)


@_reporting
def _chunk_task(
    path: str, job: BatchJob, template: Template | None, plan: FilePlan, ranges: list[tuple[int, int]]
) -> Any:
    """The results of frames ``ranges`` (in order) of a file: the JSON lines of ``echoes`` or
    ``locate``, or the located objects for ``evaluate``."""
    from echoloc.localise.backprojection import run_backprojection
    from echoloc.pipeline import frame_echoes, run

    parts = _parts(path, job.repair_nonfinite)
    chain = _file_chain(job, template, plan, parts.header)
    backprojection = job.job != "echoes" and job.settings.method == "backprojection"
    lines: list[str] = []
    located: list[FrameObjects] = []
    for recording, indices, n_context in _chunk_recordings(parts, plan, ranges, backprojection):
        if job.job == "echoes":
            on = _on(chain, recording)
            for k, index in enumerate(indices):
                lines.append(json_line(echoes_record(replace(frame_echoes(on, k), frame=index))))
            continue
        found: Iterable[FrameObjects]
        if backprojection:
            bp = _backprojector(chain, plan, parts, (path, job.settings, job.repair_nonfinite))
            finder = bp.chain
            bp = replace(bp, recording=recording, chain=None if finder is None else _on(finder, recording))
            found = run_backprojection(bp)
        else:
            found = (objects for _, objects in run(_on(chain, recording)))
        for k, objects in enumerate(found):
            if k < n_context:
                continue
            renumbered = replace(objects, frame=indices[k])
            if job.job == "evaluate":
                located.append(renumbered)
            else:
                lines.append(json_line(objects_record(renumbered)))
    return located if job.job == "evaluate" else "".join(f"{line}\n" for line in lines)


@_reporting
def _evaluate_task(path: str, job: BatchJob, plan: FilePlan, *chunks: _Reported) -> str:
    """``echoloc evaluate FILE --json``'s line from the objects its chunks located."""
    from echoloc.cli.app import _json_safe
    from echoloc.cli.processing import _classes_record, _evaluation_record
    from echoloc.localise.evaluation import evaluate, evaluate_classes

    del plan
    parts = _parts(path, job.repair_nonfinite)
    header = parts.header
    truth = parts.per_frame["truth_positions_m"]
    if truth is None:  # the plan refused such a file; the file changed since
        raise EchoLocError(f"{path}: has no truth_positions to evaluate against")
    results = [objects for chunk in chunks for objects in chunk.value]
    report = evaluate(results, truth, job.match_radius_m)
    record = _evaluation_record(report, job.settings.estimator_name(header))
    if job.settings.classes and header.truth_kinds is not None:
        fired = parts.per_frame["frame_transmitter"]
        if fired is None:
            fired = np.zeros(parts.n_frames, dtype=int)
        classes = evaluate_classes(
            results,
            truth,
            header.truth_kinds,
            header.transmitters_m[fired],
            match_radius_m=job.match_radius_m,
        )
        record["classes"] = _classes_record(classes)
    return json.dumps(_json_safe(record), allow_nan=False) + "\n"


@_reporting
def _map_task(path: str, job: BatchJob, template: Template | None, plan: FilePlan) -> OccupancyGrid:
    """The occupancy grid of ``echoloc map``: the file's frames read chunk by chunk, in order,
    into one grid (it clamps as it accumulates, so the order is the serial one)."""
    from echoloc.maps.mapping import chain_accumulator, choose_grid, frame_poses, integrate
    from echoloc.pipeline import run

    settings = job.map
    parts = _parts(path, job.repair_nonfinite)
    header = parts.header
    per_frame = parts.per_frame
    # The whole recording as the accumulator sees it: every per-frame field, and frames
    # of the right shape that take no memory (NaN, should anything read them).
    everything = replace(
        header,
        frames=np.broadcast_to(
            np.array(np.nan, dtype=header.frames.dtype), (parts.n_frames, *header.frames.shape[1:])
        ),
        frame_times_s=per_frame["frame_times_s"],
        frame_transmitter=per_frame["frame_transmitter"],
        truth_positions_m=per_frame["truth_positions_m"],
        sensor_poses=per_frame["sensor_poses"],
    )
    chain = _file_chain(job, template, plan, header)
    poses = frame_poses(everything, None)
    spec = choose_grid(
        everything,
        poses[list(plan.frames)],
        settings.cell_m,
        chain.speed_of_sound_m_s,
        three_d=settings.three_d,
        extent_m=None if settings.extent_m is None else list(settings.extent_m),
        height_m=settings.height_m,
    )
    accumulator = chain_accumulator(
        _on(chain, everything), spec, path_sigma_m=job.settings.path_sigma_m, tracks=settings.with_tracks
    )

    def results() -> Iterator[tuple[Any, FrameObjects | None]]:
        for recording, indices, n_context in _chunk_recordings(parts, plan, _ranges(plan, job), False):
            for k, (echoes, objects) in enumerate(run(_on(chain, recording))):
                if k >= n_context:
                    located = replace(objects, frame=indices[k]) if settings.with_objects else None
                    yield replace(echoes, frame=indices[k]), located

    return integrate(accumulator, results(), poses)


def _ranges(plan: FilePlan, job: BatchJob) -> list[tuple[int, int]]:
    """The file's frames cut into ranges of at most ``chunk_frames`` less the context."""
    step = job.chunk_frames - plan.context
    if step < 1:
        raise EchoLocError(
            f"{plan.source}: --chunk-frames {job.chunk_frames} leaves no room for frames of its own: "
            f"each chunk also runs the {plan.context} frame(s) before it "
            f"(its {plan.context + 1} transmitters are located together)"
        )
    frames = plan.frames
    return [(start, min(start + step, frames.stop)) for start in range(frames.start, frames.stop, step)]


# --- the client's side ----------------------------------------------------------------------------


@dataclass(eq=False)
class _File:
    """The state of one file in a running batch."""

    input: Path
    output: Path
    detail: str = ""
    plan: FilePlan | None = None
    futures: list[Any] = field(default_factory=list)  # its chunk tasks, in frame order
    arrived: int = 0  # chunk results in
    texts: dict[int, str] = field(default_factory=dict)  # chunk lines not yet written
    written: int = 0  # chunks written to the temporary
    handle: Any = None  # the temporary, open for writing
    warnings: list[str] = field(default_factory=list)
    started: float = field(default_factory=time.perf_counter)
    over: bool = False

    def warn(self, lines: Iterable[str]) -> None:
        for line in lines:
            if line not in self.warnings:
                self.warnings.append(line)

    def close(self) -> None:
        """Drop what is half-written: the temporary, and the tasks still to run."""
        if self.handle is not None:
            self.handle.close()
            self.handle = None
        with contextlib.suppress(OSError):
            temporary_path(self.output).unlink(missing_ok=True)
        for future in self.futures:
            future.cancel()
        self.futures = []


def _failure(error: BaseException) -> str:
    """One line for a task's error."""
    text = " ".join(str(error).split())
    if isinstance(error, EchoLocError):
        return text
    if isinstance(error, MemoryError):
        return "not enough memory for this file (a smaller --chunk-frames?)"
    if isinstance(error, OSError):
        where = f"{error.filename}: " if error.filename else ""
        return f"{where}{error.strerror or error}"
    name = type(error).__name__
    if name == "KilledWorker":
        return f"its task ended every worker it ran on ({text})"
    return f"internal error: {name}: {text} (please report this)"


def _prepared_outputs(
    job: str, inputs: Sequence[Path], outdir: Path | None, force: bool
) -> tuple[list[_File], dict[Path, FileOutcome]]:
    """The files to run, and the outcomes of those not to: complete (skipped) or clashing."""
    outcomes: dict[Path, FileOutcome] = {}
    files: list[_File] = []
    claimed: dict[Path, Path] = {}
    for path in inputs:
        output = output_path(path, job, outdir)
        key = Path(os.path.abspath(output))
        if key in claimed:
            message = f"{path}: its output {output} would be that of {claimed[key]} too"
            outcomes[path] = FileOutcome(path, output, "failed", message)
            continue
        claimed[key] = path
        temporary = temporary_path(output)
        leftover = temporary.exists()
        if output.exists() and not force:
            with contextlib.suppress(OSError):
                temporary.unlink(missing_ok=True)
            outcomes[path] = FileOutcome(path, output, "skipped", "complete already")
            continue
        detail = ""
        if leftover:
            try:
                temporary.unlink()
            except OSError as error:
                outcomes[path] = FileOutcome(
                    path, output, "failed", f"{temporary}: {error.strerror or error}"
                )
                continue
            detail = "a half-written output of an earlier run was removed"
        files.append(_File(path, output, detail))
    return files, outcomes


def run_batch(
    client: Any,
    job: BatchJob,
    inputs: Sequence[Path],
    *,
    outdir: Path | None = None,
    force: bool = False,
    progress: Callable[[int], None] | None = None,
    warn: Callable[[str], None] | None = None,
    on_result: Callable[[str], None] | None = None,
) -> list[FileOutcome]:
    """Run ``job`` on every file of ``inputs`` on the Dask ``client``; an outcome per input, in order.

    ``outdir``: where outputs go (made if missing; default: next to each input). ``force``:
    redo outputs that are complete. ``progress(1)`` is called as each file is done,
    skipped or failed; ``warn(line)`` with each warning a file's tasks raised, once, after
    the file is done; ``on_result(kind)`` as each task's result arrives (``plan``,
    ``chunk``, ``evaluate`` or ``map``).
    """
    from distributed import as_completed

    template = job.check()
    if outdir is not None:
        try:
            outdir.mkdir(parents=True, exist_ok=True)
        except OSError as error:
            raise EchoLocError(
                f"{outdir}: cannot make the output folder: {error.strerror or error}"
            ) from None
    files, outcomes = _prepared_outputs(job.job, inputs, outdir, force)
    advance = progress or (lambda n: None)
    advance(len(outcomes))
    tasks: dict[str, tuple[_File, str, int]] = {}
    pending = as_completed()  # type: ignore[no-untyped-call]

    def submit(state: _File, kind: str, index: int, function: Callable[..., Any], *args: Any) -> Any:
        future = client.submit(function, *args, pure=False, key=f"echoloc-batch-{kind}-{os.urandom(8).hex()}")
        tasks[future.key] = (state, kind, index)
        pending.add(future)  # type: ignore[no-untyped-call]
        return future

    def end(state: _File, outcome: FileOutcome) -> None:
        state.over = True
        outcomes[state.input] = outcome
        if warn is not None and outcome.status == "done":
            for line in state.warnings:
                warn(line if str(state.input) in line else f"{state.input}: {line}")
        advance(1)

    def fail(state: _File, message: str) -> None:
        state.close()
        end(state, FileOutcome(state.input, state.output, "failed", message))

    def finish(state: _File) -> None:
        if state.handle is not None:
            state.handle.close()
            state.handle = None
        _commit(temporary_path(state.output), state.output)
        state.futures = []
        assert state.plan is not None
        seconds = time.perf_counter() - state.started
        end(
            state,
            FileOutcome(state.input, state.output, "done", state.detail, len(state.plan.frames), seconds),
        )

    for state in files:
        submit(state, "plan", 0, _plan_task, str(state.input), job, template)
    try:
        for future in pending:
            state, kind, index = tasks.pop(future.key)
            if state.over:
                continue
            if on_result is not None:
                on_result(kind)
            try:
                reported: _Reported = future.result()
            except Exception as error:
                fail(state, _failure(error))
                continue
            state.warn(reported.warnings)
            if reported.error is not None:
                fail(state, reported.error)
                continue
            try:
                if kind == "plan":
                    _planned(state, reported.value, job, template, submit)
                elif kind == "chunk":
                    state.arrived += 1
                    if job.job == "evaluate":
                        if state.arrived == len(state.futures):
                            assert state.plan is not None
                            chunks = state.futures
                            state.futures = [
                                submit(
                                    state,
                                    "evaluate",
                                    0,
                                    _evaluate_task,
                                    str(state.input),
                                    job,
                                    state.plan,
                                    *chunks,
                                )
                            ]
                        continue
                    _write_chunk(state, index, reported.value)
                    if state.written == len(state.futures):
                        finish(state)
                elif kind == "evaluate":
                    temporary_path(state.output).write_bytes(reported.value.encode())
                    finish(state)
                elif kind == "map":
                    from echoloc.maps.map_export import write_grid_npz

                    write_grid_npz(reported.value, temporary_path(state.output))
                    finish(state)
            except EchoLocError as error:
                fail(state, _failure(error))
            except OSError as error:
                fail(state, f"{state.output}: cannot write: {error.strerror or error}")
    finally:
        for state in files:
            if not state.over:
                state.close()
    return [outcomes[path] for path in inputs if path in outcomes]


def _planned(
    state: _File, plan: FilePlan, job: BatchJob, template: Template | None, submit: Callable[..., Any]
) -> None:
    """A file's plan came back: submit its chunk tasks (or its map task)."""
    state.plan = plan
    path = str(state.input)
    ranges = _ranges(plan, job)  # refuses chunks too small, here
    if job.job == "map":
        state.futures = [submit(state, "map", 0, _map_task, path, job, template, plan)]
        return
    groups = [[piece] for piece in ranges] if plan.random_access else [ranges]
    state.futures = [
        submit(state, "chunk", index, _chunk_task, path, job, template, plan, group)
        for index, group in enumerate(groups)
    ]


def _write_chunk(state: _File, index: int, text: str) -> None:
    """Write a chunk's lines to the temporary once those before it are written."""
    state.texts[index] = text
    if state.handle is None:
        state.handle = open(temporary_path(state.output), "wb")  # noqa: SIM115 -- closed by finish or close
    while state.written in state.texts:
        state.handle.write(state.texts.pop(state.written).encode())
        state.written += 1
