"""Design studies: a scene and its processing, varied over a grid or at random, on a Dask cluster.

A sweep file (TOML, ``echoloc sweep SWEEP.toml``) names a base scene (a preset, a scene
file, or an inline ``[scene]`` table), the frames to simulate per point, the processing
options (those of :class:`echoloc.cli.app.ChainSettings`), the metrics, and the parameters
to vary: ``[grid]``, the product of value lists, or ``[random]``, points drawn from ranges.
A parameter is a scene key by its dotted path (``noise.snr_db``, ``pulse.code``,
``reflectors[0].position_m``), a processing option by its name (``threshold_db``), or the
receivers' geometry, ``array.spacing_m`` and ``array.n_receivers``, laid out by
``[array_layout]`` around the first transmitter (:func:`layout_receivers`).

:func:`load_sweep` checks the whole file before anything runs: every key, every parameter
path, and every point's scene and processing options (a value the scene refuses is one
line naming the point). :func:`run_sweep` then runs the points as tasks of a
``dask.distributed`` client (:func:`echoloc.scale.cluster.open_client`), small points
several to a task (:func:`points_per_task`); :func:`run_point` is one point anywhere:
simulate its frames a chunk at a time (flat memory whatever the frames), run the chain on
each chunk, and score the objects against the truth (:data:`METRICS`). Each point's
noise is fixed by its seed (:func:`point_seed`), drawn from the sweep's seed and the
point's own parameter values: the table is the same whatever the workers and the order
the tasks run, and a point keeps its results when other values join the grid. Only
``time_per_frame_s`` depends on the machine.
"""

from __future__ import annotations

import copy
import csv
import hashlib
import io
import itertools
import json
import math
import re
import time
import warnings
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

import numpy as np
from numpy.typing import NDArray

from echoloc._toml import tomllib
from echoloc.errors import EchoLocError, read_text_input
from echoloc.sim.scene import Scene
from echoloc.sim.scenefile import (
    _GAIN_KEYS,
    _REFLECTOR_KEYS,
    _SECTIONS,
    MAX_SCENE_FILE_BYTES,
    preset_names,
    preset_path,
    scene_from_dict,
)

if TYPE_CHECKING:
    from echoloc.cli.app import ChainSettings
    from echoloc.io.recording import FrameBatch, Recording
    from echoloc.localise.locate import FrameObjects
    from echoloc.tof.templates import Template


class SweepError(EchoLocError):
    """A sweep file, or one of its points, that cannot run (one line naming the file and key)."""


MAX_SWEEP_FILE_BYTES = MAX_SCENE_FILE_BYTES
"""The largest sweep file read, bytes (an inline scene counts)."""

MAX_POINTS = 100_000
"""The most points a sweep may have (a grid's product or ``[random] points``)."""

MAX_FRAMES_PER_POINT = 10_000_000
"""The most frames a point may simulate (they are made and scored batch by batch)."""

METRICS: dict[str, str] = {
    "median_error_m": "median distance of a located object from its true reflector, m",
    "p90_error_m": "90th percentile of that distance, m",
    "rms_error_m": "root mean square of that distance, m",
    "spread_m": "spread of the error about each reflector's mean error (3-D standard deviation, "
    "pooled over the truth's reflectors), m",
    "rms_range_error_m": "RMS error of the range from the sensor frame's origin, m",
    "rms_angle_error_deg": "RMS angle between located and true directions from the origin, degrees",
    "reported_sigma_m": "RMS of the 3-D standard deviation the chain reports for its objects, m",
    "sigma_ratio": "spread_m / reported_sigma_m: 1 when the reported uncertainty is honest",
    "recall": "true reflectors located (within match_radius_m) / all true reflectors",
    "false_rate": "located objects matching no reflector / all located objects",
    "located_per_frame": "objects located per frame",
    "time_per_frame_s": "wall-clock seconds of the chain (preparation included) per frame on the "
    "worker that ran the point: the one column that depends on the machine",
}
"""Every metric a sweep computes, in the table's order, with what it means."""

PROCESSING_KEYS: dict[str, str] = {
    "estimator": "estimator",
    "threshold_db": "threshold_db",
    "blanking_s": "blanking_s",
    "speed_of_sound_m_s": "speed_of_sound_m_s",
    "calibration": "calibration_path",
    "path_sigma_m": "path_sigma_m",
    "template": "template_path",
    "background": "background",
    "tvg": "tvg",
    "blind_zone": "blind_zone_text",
    "field_of_view_deg": "field_of_view_deg",
    "method": "method",
    "classes": "classes",
}
"""The keys of ``[processing]`` (the options of `echoloc locate`, without the dashes) and the
:class:`~echoloc.cli.app.ChainSettings` field each sets."""

LAYOUT_KINDS = ("cross", "ring")
"""Receiver layouts of ``[array_layout]``."""

LAYOUT_PARAMETERS = ("array.spacing_m", "array.n_receivers")
"""The parameters of the receivers' geometry, laid out by ``[array_layout]``."""

DISTRIBUTIONS = ("uniform", "log_uniform", "integers", "choice")
"""How ``[random]`` draws a parameter: ``{uniform = [lo, hi]}`` and the like."""

CHUNK_FRAMES = 256
"""Frames of a point simulated and run through the chain at a time (the chain is prepared
once a chunk): 20 MB of the report's frames."""

CHUNK_BYTES = 64 << 20
"""The most samples a chunk may hold, bytes (complex128 counted): long frames go fewer at a time."""

TASK_FRAMES = 256
"""Frames one task of :func:`run_sweep` runs at least, when its points are small: several
points go to one task (:func:`points_per_task`)."""

TASKS_PER_WORKER = 4
"""Tasks a worker gets at least, however small the points (for the work to share out)."""

RANDOM_DIGITS = 4
"""Significant digits a drawn number is rounded to, so that the table shows what ran."""

_TOP_LEVEL = {
    "scene",
    "frames",
    "seed",
    "metrics",
    "match_radius_m",
    "processing",
    "array_layout",
    "grid",
    "random",
    "plot",
}
_PLOT_KEYS = {"x", "y", "lines", "log_x", "log_y"}
_LAYOUT_KEYS = {"kind", "spacing_m", "n_receivers"}
_REFLECTOR_PATH = re.compile(r"^reflectors\[(\d+)\]\.([a-z_]+)$")
_ALL_REFLECTOR_KEYS = set().union(*_REFLECTOR_KEYS.values()) | {"kind"}


# --- the sweep file ------------------------------------------------------------------


@dataclass(frozen=True)
class ArrayLayout:
    """Receivers laid out around the first transmitter, in its z plane (:func:`layout_receivers`).

    ``cross``: on the x and y axes at ``±spacing_m``, then ``±2 spacing_m``, ... (the
    report's head for 4); ``n_receivers`` a multiple of 4. ``ring``: ``n_receivers`` (>= 3)
    evenly on a circle of radius ``spacing_m``, the first on +x.
    """

    kind: Literal["cross", "ring"] = "cross"
    spacing_m: float | None = None
    n_receivers: int = 4


@dataclass(frozen=True)
class PlotSpec:
    """What ``--plot`` draws: ``y`` (a metric) against parameter ``x``, one line per value of
    ``lines``; None: the first metric, the first and second parameters."""

    x: str | None = None
    y: str | None = None
    lines: str | None = None
    log_x: bool = False
    log_y: bool | None = None  # None: when the values span more than a factor of 30


@dataclass(frozen=True, eq=False)
class Study:
    """What every point of a sweep shares; a point adds its parameter values and seed.

    ``scene`` is the base scene's TOML table; ``processing`` the ``[processing]`` table
    with its file paths resolved.
    """

    source: str
    scene: Mapping[str, Any]
    frames: int
    processing: Mapping[str, Any]
    layout: ArrayLayout | None
    metrics: tuple[str, ...]
    match_radius_m: float


@dataclass(frozen=True)
class SweepPoint:
    """One point: its number in the sweep, its parameter values (in the sweep's parameter
    order) and the seed of its frames' noise (:func:`point_seed`)."""

    index: int
    values: tuple[tuple[str, Any], ...]
    seed: int

    def describe(self) -> str:
        """``noise.snr_db = 20, pulse.code = 'barker13'``."""
        return ", ".join(f"{path} = {_shown(value)}" for path, value in self.values)


@dataclass(frozen=True, eq=False)
class Sweep:
    """A checked sweep file: the study, its parameters and every point."""

    study: Study
    kind: Literal["grid", "random"]
    seed: int
    parameters: tuple[str, ...]
    points: tuple[SweepPoint, ...]
    plot: PlotSpec = field(default_factory=PlotSpec)

    @property
    def source(self) -> str:
        return self.study.source

    @property
    def columns(self) -> tuple[str, ...]:
        """The table's columns: the point, its parameters, its seed and frames, the metrics."""
        return ("point", *self.parameters, "seed", "frames", *self.study.metrics)

    def with_frames(self, frames: int) -> Sweep:
        """The same sweep with ``frames`` frames per point (a quick trial: ``--frames``)."""
        _check_frames(self.source, frames, "--frames")
        return replace(self, study=replace(self.study, frames=frames))


def _shown(value: Any) -> str:
    if isinstance(value, str):
        return repr(value)
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return f"{value:g}"
    return json.dumps(value)


def _fail(source: str, message: str) -> SweepError:
    return SweepError(f"{source}: {message}")


def _check_keys(source: str, where: str, data: Mapping[str, Any], allowed: set[str]) -> None:
    unknown = sorted(set(data) - allowed)
    if unknown:
        raise _fail(source, f"{where}: unknown key {unknown[0]!r} (allowed: {', '.join(sorted(allowed))})")


def _table(source: str, data: Mapping[str, Any], name: str) -> dict[str, Any]:
    value = data.get(name, {})
    if not isinstance(value, dict):
        raise _fail(source, f"[{name}] must be a table")
    return value


def _whole(source: str, key: str, value: Any, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise _fail(source, f"{key} must be a whole number >= {minimum}, got {value!r}")
    return value


def _number(source: str, key: str, value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise _fail(source, f"{key} must be a finite number, got {value!r}")
    return float(value)


def _check_frames(source: str, frames: Any, key: str) -> int:
    frames = _whole(source, key, frames, 1)
    if frames > MAX_FRAMES_PER_POINT:
        raise _fail(source, f"{key} must be at most {MAX_FRAMES_PER_POINT}, got {frames}")
    return int(frames)


def load_sweep(path: str | Path) -> Sweep:
    """Read and check a sweep file: its keys, its parameters, and every point's scene and
    processing options. Relative paths in it (the base scene, a calibration or template
    file) are taken from the sweep file's directory."""
    path = Path(path)
    text = read_text_input(path, what="sweep file", max_bytes=MAX_SWEEP_FILE_BYTES, error=SweepError)
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise SweepError(f"{path}: not valid TOML ({error})") from None
    except (ValueError, RecursionError) as error:
        reason = "nested too deeply" if isinstance(error, RecursionError) else str(error)
        raise SweepError(f"{path}: not valid TOML ({reason})") from None
    return sweep_from_dict(data, source=str(path), base_dir=path.parent)


def sweep_from_dict(data: Mapping[str, Any], source: str = "<sweep>", base_dir: Path | None = None) -> Sweep:
    """:func:`load_sweep` of a parsed TOML table; relative paths are taken from ``base_dir``
    (default: the current directory)."""
    base_dir = Path(".") if base_dir is None else base_dir
    _check_keys(source, "top level", data, _TOP_LEVEL)
    scene = _base_scene(source, data.get("scene"), base_dir)
    frames = _check_frames(source, data.get("frames", 100), "frames")
    seed = _whole(source, "seed", data.get("seed", 0), 0)
    metrics = _metrics(source, data.get("metrics", list(METRICS)))
    match_radius_m = _number(source, "match_radius_m", data.get("match_radius_m", 0.02))
    if not match_radius_m > 0:
        raise _fail(source, f"match_radius_m must be > 0, got {match_radius_m:g}")
    processing = _processing(source, _table(source, data, "processing"), base_dir)
    if ("grid" in data) == ("random" in data):
        raise _fail(source, "give the parameters to vary as [grid] or as [random], one of the two")
    kind: Literal["grid", "random"] = "grid" if "grid" in data else "random"
    varied = _table(source, data, kind)
    if kind == "grid":
        parameters, rows = _grid(source, varied)
    else:
        parameters, rows = _random(source, varied, seed)
    for path in parameters:
        _check_parameter(source, path, scene)
    layout = _layout(source, data, parameters)
    study = Study(source, scene, frames, processing, layout, metrics, match_radius_m)
    points = tuple(
        SweepPoint(index, tuple(zip(parameters, values, strict=True)), point_seed(seed, parameters, values))
        for index, values in enumerate(rows)
    )
    plot = _plot_spec(source, _table(source, data, "plot"), parameters, metrics)
    sweep = Sweep(study, kind, seed, parameters, points, plot)
    check_points(sweep)
    return sweep


def _base_scene(source: str, value: Any, base_dir: Path) -> dict[str, Any]:
    """The base scene's TOML table: ``scene = "NAME"`` (a scene file beside the sweep file, or
    a preset) or an inline ``[scene]`` table; checked as a scene."""
    if value is None:
        raise _fail(source, "scene is required: a preset name, a scene file, or a [scene] table")
    if isinstance(value, dict):
        table, where = copy.deepcopy(value), f"{source} [scene]"
    elif isinstance(value, str):
        path = base_dir / value
        if not path.exists() and value.removesuffix(".toml") in preset_names():
            path = preset_path(value)
        elif not path.exists():
            presets = ", ".join(preset_names())
            raise _fail(
                source, f"scene {value!r}: no such scene file (beside the sweep file) or preset ({presets})"
            )
        text = read_text_input(path, what="scene file", max_bytes=MAX_SCENE_FILE_BYTES, error=SweepError)
        try:
            table = tomllib.loads(text)
        except (tomllib.TOMLDecodeError, ValueError, RecursionError) as error:
            raise _fail(source, f"scene {path}: not valid TOML ({error})") from None
        where = f"{source} scene {path}"
    else:
        raise _fail(source, f"scene must be a preset name, a scene file or a [scene] table, got {value!r}")
    try:
        scene_from_dict(table, source=where)
    except EchoLocError as error:
        raise SweepError(str(error)) from None
    return table


def _metrics(source: str, value: Any) -> tuple[str, ...]:
    if not (isinstance(value, list) and value and all(isinstance(v, str) for v in value)):
        raise _fail(source, f"metrics must be a list of metric names, got {value!r}")
    for name in value:
        if name not in METRICS:
            raise _fail(source, f"metrics: unknown metric {name!r} (known: {', '.join(METRICS)})")
    if len(set(value)) != len(value):
        raise _fail(source, f"metrics: a metric is named twice in {value!r}")
    return tuple(value)


def _processing(source: str, table: Mapping[str, Any], base_dir: Path) -> dict[str, Any]:
    _check_keys(source, "[processing]", table, set(PROCESSING_KEYS))
    resolved = dict(table)
    for key in ("calibration", "template"):
        if key in resolved:
            if not isinstance(resolved[key], str):
                raise _fail(source, f"processing.{key} must be a file path, got {resolved[key]!r}")
            resolved[key] = str(base_dir / resolved[key])
    return resolved


def _flatten(
    source: str, where: str, table: Mapping[str, Any], leaf: Callable[[Any], bool]
) -> dict[str, Any]:
    """``{"noise": {"snr_db": [...]}}`` (TOML's ``noise.snr_db = [...]``) as
    ``{"noise.snr_db": [...]}``; a quoted ``"noise.snr_db"`` key is the same parameter."""
    flat: dict[str, Any] = {}

    def walk(prefix: str, value: Any) -> None:
        if isinstance(value, dict) and not leaf(value):
            if not value:
                raise _fail(source, f"{where} {prefix}: an empty table")
            for key, item in value.items():
                walk(f"{prefix}.{key}" if prefix else key, item)
            return
        if prefix in flat:
            raise _fail(source, f"{where}: parameter {prefix!r} is given twice")
        flat[prefix] = value

    walk("", dict(table))
    return flat


def _grid(source: str, table: Mapping[str, Any]) -> tuple[tuple[str, ...], list[tuple[Any, ...]]]:
    flat = _flatten(source, "[grid]", table, lambda value: False)
    if not flat:
        raise _fail(source, "[grid] names no parameter to vary")
    size = 1
    for path, values in flat.items():
        if not isinstance(values, list) or not values:
            raise _fail(source, f"grid {path} must be a non-empty list of values, got {values!r}")
        size *= len(values)
        if size > MAX_POINTS:
            raise _fail(source, f"[grid] has more than {MAX_POINTS} points")
    parameters = tuple(flat)
    return parameters, list(itertools.product(*(flat[p] for p in parameters)))


def _random(
    source: str, table: Mapping[str, Any], seed: int
) -> tuple[tuple[str, ...], list[tuple[Any, ...]]]:
    table = dict(table)
    if "points" not in table:
        raise _fail(source, "[random] needs points, the number of points to draw")
    n_points = _whole(source, "random.points", table.pop("points"), 1)
    if n_points > MAX_POINTS:
        raise _fail(source, f"random.points must be at most {MAX_POINTS}, got {n_points}")
    flat = _flatten(
        source, "[random]", table, lambda value: len(value) == 1 and next(iter(value)) in DISTRIBUTIONS
    )
    if not flat:
        raise _fail(source, "[random] names no parameter to vary")
    draws = {path: _distribution(source, path, spec) for path, spec in flat.items()}
    rng = np.random.default_rng(seed)
    rows = [tuple(draws[path](rng) for path in flat) for _ in range(n_points)]
    return tuple(flat), rows


def _distribution(source: str, path: str, spec: Any) -> Callable[[np.random.Generator], Any]:
    """How ``[random]`` draws ``path``: one of :data:`DISTRIBUTIONS`."""
    shapes = "{uniform = [lo, hi]}, {log_uniform = [lo, hi]}, {integers = [lo, hi]} or {choice = [...]}"
    if not (isinstance(spec, dict) and len(spec) == 1 and next(iter(spec)) in DISTRIBUTIONS):
        raise _fail(source, f"random {path} must be {shapes}, got {spec!r}")
    (name, values), key = next(iter(spec.items())), f"random {path}.{next(iter(spec))}"
    if name == "choice":
        if not isinstance(values, list) or not values:
            raise _fail(source, f"{key} must be a non-empty list of values, got {values!r}")
        choices = list(values)
        return lambda rng: copy.deepcopy(choices[int(rng.integers(len(choices)))])
    if not (isinstance(values, list) and len(values) == 2):
        raise _fail(source, f"{key} must be [lo, hi], got {values!r}")
    if name == "integers":
        first, last = (_whole(source, key, v, -(2**62)) for v in values)
        if first > last:
            raise _fail(source, f"{key} must be [lo, hi] with lo <= hi, got {values!r}")
        return lambda rng: int(rng.integers(first, last, endpoint=True))
    low, high = (_number(source, key, v) for v in values)
    if low > high:
        raise _fail(source, f"{key} must be [lo, hi] with lo <= hi, got {values!r}")
    if name == "log_uniform":
        if not low > 0:
            raise _fail(source, f"{key} must be above 0 (a log scale), got {values!r}")
        return lambda rng: _rounded(math.exp(rng.uniform(math.log(low), math.log(high))))
    return lambda rng: _rounded(float(rng.uniform(low, high)))


def _rounded(value: float) -> float:
    return float(f"{value:.{RANDOM_DIGITS}g}")


def _check_parameter(source: str, path: str, scene: Mapping[str, Any]) -> None:
    """Refuse a parameter no scene key, processing option or layout names."""
    if path in LAYOUT_PARAMETERS or path in PROCESSING_KEYS or path == "max_order":
        return
    if path == "seed":
        raise _fail(
            source,
            "seed cannot vary: the sweep sets each point's seed (the sweep's own seed is top-level seed)",
        )
    if (found := _REFLECTOR_PATH.match(path)) is not None:
        index, key = int(found.group(1)), found.group(2)
        reflectors = scene.get("reflectors", [])
        count = len(reflectors) if isinstance(reflectors, list) else 0
        if index >= count:
            raise _fail(source, f"parameter {path!r}: the base scene has {count} [[reflectors]]")
        if key not in _ALL_REFLECTOR_KEYS:
            raise _fail(
                source,
                f"parameter {path!r}: unknown reflector key {key!r} "
                f"(keys: {', '.join(sorted(_ALL_REFLECTOR_KEYS))})",
            )
        return
    parts = path.split(".")
    if len(parts) == 2 and parts[0] in _SECTIONS and parts[1] in _SECTIONS[parts[0]]:
        return
    if len(parts) == 3 and parts[:2] == ["receiver", "gain"] and parts[2] in _GAIN_KEYS:
        return
    if len(parts) == 2 and parts[0] in _SECTIONS:
        allowed = sorted(
            _SECTIONS[parts[0]] | ({"spacing_m", "n_receivers"} if parts[0] == "array" else set())
        )
        raise _fail(
            source, f"parameter {path!r}: [{parts[0]}] has no key {parts[1]!r} (keys: {', '.join(allowed)})"
        )
    raise _fail(
        source,
        f"unknown parameter {path!r}: a scene key by its path (noise.snr_db, pulse.code, "
        f"reflectors[0].position_m, ...), a processing option ({', '.join(PROCESSING_KEYS)}), "
        "or array.spacing_m / array.n_receivers",
    )


def _layout(source: str, data: Mapping[str, Any], parameters: Sequence[str]) -> ArrayLayout | None:
    swept = [p for p in parameters if p in LAYOUT_PARAMETERS]
    if "array_layout" not in data and not swept:
        return None
    table = _table(source, data, "array_layout")
    _check_keys(source, "[array_layout]", table, _LAYOUT_KEYS)
    kind = table.get("kind", "cross")
    if kind not in LAYOUT_KINDS:
        raise _fail(source, f"array_layout.kind must be one of {', '.join(LAYOUT_KINDS)}; got {kind!r}")
    spacing = table.get("spacing_m")
    if spacing is not None:
        spacing = _number(source, "array_layout.spacing_m", spacing)
    elif "array.spacing_m" not in parameters:
        raise _fail(source, "array_layout.spacing_m is required unless array.spacing_m is a parameter")
    n_receivers = _whole(source, "array_layout.n_receivers", table.get("n_receivers", 4), 1)
    for path in ("array.receivers_m", "array.receiver_axes"):
        if path in parameters:
            raise _fail(source, f"{path} cannot vary with [array_layout]: the layout places the receivers")
    layout = ArrayLayout(kind=kind, spacing_m=spacing, n_receivers=n_receivers)
    if spacing is not None:
        try:
            layout_receivers(layout, np.zeros(3))  # a bad fixed value now, not at each point
        except SweepError as error:
            raise _fail(source, f"[array_layout] {error}") from None
    return layout


def _plot_spec(
    source: str, table: Mapping[str, Any], parameters: Sequence[str], metrics: Sequence[str]
) -> PlotSpec:
    _check_keys(source, "[plot]", table, _PLOT_KEYS)
    for key in ("x", "lines"):
        if key in table and table[key] not in parameters:
            raise _fail(
                source,
                f"plot.{key} must be one of the parameters ({', '.join(parameters)}), got {table[key]!r}",
            )
    if "y" in table and table["y"] not in metrics:
        raise _fail(source, f"plot.y must be one of the metrics ({', '.join(metrics)}), got {table['y']!r}")
    for key in ("log_x", "log_y"):
        if key in table and not isinstance(table[key], bool):
            raise _fail(source, f"plot.{key} must be true or false, got {table[key]!r}")
    return PlotSpec(
        x=table.get("x"),
        y=table.get("y"),
        lines=table.get("lines"),
        log_x=table.get("log_x", False),
        log_y=table.get("log_y"),
    )


def point_seed(seed: int, parameters: Sequence[str], values: Sequence[Any]) -> int:
    """The seed of a point's frames: a hash of the sweep's ``seed`` and the point's parameter
    values (by name, whatever their order in the file; 20 and 20.0 alike), 63 bits."""

    def plain(value: Any) -> Any:
        if isinstance(value, bool) or not isinstance(value, int | float):
            return [plain(v) for v in value] if isinstance(value, list) else value
        return float(value)

    named = sorted((path, plain(value)) for path, value in zip(parameters, values, strict=True))
    text = json.dumps([seed, named], separators=(",", ":"))
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:8], "big") >> 1


# --- a point's scene and processing ------------------------------------------------------


def layout_receivers(layout: ArrayLayout, centre_m: NDArray[np.float64]) -> list[list[float]]:
    """The receivers of ``layout`` around ``centre_m`` (the first transmitter), in its z plane."""
    d, n = layout.spacing_m, layout.n_receivers
    if d is None or not (math.isfinite(d) and d > 0):
        raise SweepError(f"array.spacing_m must be > 0, got {d!r}")
    if layout.kind == "cross":
        if n % 4 or n < 4:
            raise SweepError(f"array.n_receivers of a cross must be a multiple of 4, got {n}")
        offsets = [
            (k * d * sx, k * d * sy)
            for k in range(1, n // 4 + 1)
            for sx, sy in ((1, 0), (-1, 0), (0, 1), (0, -1))
        ]
    else:
        if n < 3:
            raise SweepError(f"array.n_receivers of a ring must be >= 3, got {n}")
        offsets = [(d * math.cos(2 * math.pi * i / n), d * math.sin(2 * math.pi * i / n)) for i in range(n)]
    cx, cy, cz = (float(v) for v in centre_m)
    return [[round(cx + u, 12), round(cy + v, 12), cz] for u, v in offsets]


def point_scene_table(study: Study, point: SweepPoint) -> dict[str, Any]:
    """The scene table of ``point``: the base scene with the point's scene values set, its
    receivers laid out, and its seed (unchecked: :func:`point_scene` checks it)."""
    table = copy.deepcopy(dict(study.scene))
    layout = study.layout
    for path, value in point.values:
        if path in PROCESSING_KEYS:
            continue
        if path == "array.spacing_m":
            layout = replace(layout or ArrayLayout(), spacing_m=value)
            continue
        if path == "array.n_receivers":
            layout = replace(layout or ArrayLayout(), n_receivers=value)
            continue
        value = copy.deepcopy(value)
        if (found := _REFLECTOR_PATH.match(path)) is not None:
            table["reflectors"][int(found.group(1))][found.group(2)] = value
            continue
        *tables, key = path.split(".")
        where = table
        for name in tables:
            where = where.setdefault(name, {})
            if not isinstance(where, dict):
                raise SweepError(f"parameter {path!r}: [{name}] of the base scene is not a table")
        where[key] = value
    if layout is not None:
        if isinstance(layout.n_receivers, bool) or not isinstance(layout.n_receivers, int):
            raise SweepError(f"array.n_receivers must be a whole number, got {layout.n_receivers!r}")
        if isinstance(layout.spacing_m, bool) or not isinstance(layout.spacing_m, int | float):
            raise SweepError(f"array.spacing_m must be a number, got {layout.spacing_m!r}")
        array = table.setdefault("array", {})
        transmitters = array.get("transmitters_m", [[0.0, 0.0, 0.0]])
        centre = np.asarray(transmitters[0], dtype=float)
        array["receivers_m"] = layout_receivers(replace(layout, spacing_m=float(layout.spacing_m)), centre)
    table["seed"] = point.seed
    return table


def point_scene(study: Study, point: SweepPoint) -> Scene:
    """``point``'s scene, checked (a refused value names the point)."""
    where = f"{study.source} point {point.index} ({point.describe()})"
    try:
        return scene_from_dict(point_scene_table(study, point), source=where)
    except EchoLocError as error:
        message = str(error)
        raise SweepError(message if message.startswith(where) else f"{where}: {message}") from None


def point_settings(study: Study, point: SweepPoint) -> ChainSettings:
    """``point``'s processing options as :class:`echoloc.cli.app.ChainSettings`."""
    from echoloc.cli.app import ChainSettings  # the options every command that locates shares
    from echoloc.tof.estimators import AUTO, ESTIMATORS

    options = dict(study.processing)
    options.update((path, value) for path, value in point.values if path in PROCESSING_KEYS)
    where = f"{study.source}" + (
        f" point {point.index} ({point.describe()})"
        if any(path in PROCESSING_KEYS for path, _ in point.values)
        else ""
    )
    kwargs: dict[str, Any] = {}
    for key, value in options.items():
        name = f"processing.{key}" if key in study.processing else key
        if key in ("estimator", "method"):
            choices = (AUTO, *sorted(ESTIMATORS)) if key == "estimator" else ("association", "backprojection")
            if value not in choices:
                raise _fail(where, f"{name} must be one of {', '.join(choices)}; got {value!r}")
        elif key in ("background", "tvg", "classes"):
            if not isinstance(value, bool):
                raise _fail(where, f"{name} must be true or false, got {value!r}")
        elif key == "blind_zone":
            if value != "auto":
                value = str(_number(where, name, value))
        elif key in ("calibration", "template"):
            if not isinstance(value, str):
                raise _fail(where, f"{name} must be a file path, got {value!r}")
            value = Path(value)
        else:
            value = _number(where, name, value)
        kwargs[PROCESSING_KEYS[key]] = value
    settings = ChainSettings(**kwargs)
    try:
        settings.check()
    except EchoLocError as error:
        raise _fail(where, f"[processing] {error}") from None
    return settings


def check_points(sweep: Sweep) -> None:
    """Build every point's scene and processing options: the first one refused is a
    :class:`SweepError` naming the point, before anything runs."""
    checked: set[str] = set()
    for point in sweep.points:
        point_scene(sweep.study, point)
        key = json.dumps([v for v in point.values if v[0] in PROCESSING_KEYS], default=str)
        if key not in checked:
            point_settings(sweep.study, point)
            checked.add(key)


# --- one point -----------------------------------------------------------------------


@dataclass
class _Tally:
    """Running scores of a point's frames, batch by batch: every metric of :data:`METRICS`
    in flat memory but for one error distance (8 bytes) per matched object."""

    frames: int = 0
    truth: int = 0
    located: int = 0
    distances: list[NDArray[np.float64]] = field(default_factory=list)
    sum_sq: float = 0.0
    range_sq: float = 0.0
    angle_sq: float = 0.0
    sigma_sq: float = 0.0
    # Per truth column: count, mean error and summed squared deviations (Welford).
    groups: dict[int, tuple[int, NDArray[np.float64], float]] = field(default_factory=dict)

    @property
    def matched(self) -> int:
        return sum(len(d) for d in self.distances)

    def add(self, results: Iterable[Any], truth_positions_m: NDArray[np.float64], radius_m: float) -> None:
        from echoloc.localise.evaluation import match

        for frame in results:
            truth_all = truth_positions_m[frame.frame]
            columns = np.flatnonzero(np.all(np.isfinite(truth_all), axis=1))
            truth = truth_all[columns]
            estimated = np.array([o.position_m for o in frame.objects], dtype=float).reshape(-1, 3)
            pairs = match(estimated, truth, radius_m)
            self.frames += 1
            self.truth += len(truth)
            self.located += len(estimated)
            if not pairs:
                continue
            rows = np.array([e for e, _ in pairs])
            cols = np.array([t for _, t in pairs])
            found, real = estimated[rows], truth[cols]
            errors = found - real
            distance = np.linalg.norm(errors, axis=1)
            self.distances.append(distance)
            self.sum_sq += float(np.sum(distance**2))
            self.range_sq += float(
                np.sum((np.linalg.norm(found, axis=1) - np.linalg.norm(real, axis=1)) ** 2)
            )
            cosine = np.sum(found * real, axis=1) / (
                np.linalg.norm(found, axis=1) * np.linalg.norm(real, axis=1)
            )
            self.angle_sq += float(np.sum(np.degrees(np.arccos(np.clip(cosine, -1.0, 1.0))) ** 2))
            for e in rows:
                self.sigma_sq += float(np.sum(np.asarray(frame.objects[e].std_m, dtype=float) ** 2))
            for column, error in zip(columns[cols], errors, strict=True):
                count, mean, m2 = self.groups.get(int(column), (0, np.zeros(3), 0.0))
                count += 1
                delta = error - mean
                mean = mean + delta / count
                m2 += float(delta @ (error - mean))
                self.groups[int(column)] = (count, mean, m2)

    def scores(self, seconds: float) -> dict[str, float]:
        """Every metric of :data:`METRICS`."""
        matched = self.matched
        nan = float("nan")
        distances = np.concatenate(self.distances) if self.distances else np.zeros(0)
        pooled = sum(m2 for _, _, m2 in self.groups.values())
        dof = matched - len(self.groups)
        spread = math.sqrt(pooled / dof) if dof > 0 else nan
        sigma = math.sqrt(self.sigma_sq / matched) if matched else nan
        return {
            "median_error_m": float(np.median(distances)) if matched else nan,
            "p90_error_m": float(np.percentile(distances, 90)) if matched else nan,
            "rms_error_m": math.sqrt(self.sum_sq / matched) if matched else nan,
            "spread_m": spread,
            "rms_range_error_m": math.sqrt(self.range_sq / matched) if matched else nan,
            "rms_angle_error_deg": math.sqrt(self.angle_sq / matched) if matched else nan,
            "reported_sigma_m": sigma,
            "sigma_ratio": spread / sigma if matched and sigma > 0 else nan,
            "recall": matched / self.truth if self.truth else nan,
            "false_rate": (self.located - matched) / self.located if self.located else 0.0,
            "located_per_frame": self.located / self.frames if self.frames else nan,
            "time_per_frame_s": seconds / self.frames if self.frames else nan,
        }


def _objects(settings: ChainSettings, recording: Recording, template: Template | None) -> list[FrameObjects]:
    """Objects of every frame of ``recording`` by the settings' method."""
    from echoloc.pipeline import check_locatable, run

    if settings.method == "backprojection":
        from echoloc.localise.backprojection import prepare_backprojection, run_backprojection

        chain = settings.chain(recording, template)
        bp = prepare_backprojection(
            recording, speed_of_sound_m_s=chain.speed_of_sound_m_s, conditioning=chain.conditioning
        )
        return list(run_backprojection(bp))
    chain = settings.chain(recording, template)
    check_locatable(chain)
    return [objects for _, objects in run(chain)]


def _chunks(scene: Scene, frames: int) -> Iterator[Recording]:
    """``frames`` frames of ``scene`` as recordings of up to :data:`CHUNK_FRAMES` frames (fewer
    when frames are large: at most :data:`CHUNK_BYTES` of samples), one simulation from the
    scene's seed cut into pieces: the chain is prepared once a chunk."""
    from echoloc.sim.simulation import recording_header, simulate_batches

    header = recording_header(scene)
    frame_bytes = 16 * max(1, int(np.prod(header.frames.shape[1:])))
    limit = max(1, min(CHUNK_FRAMES, CHUNK_BYTES // frame_bytes))
    pending: list[FrameBatch] = []
    for batch in simulate_batches(scene, frames):
        pending.append(batch)
        if sum(b.n_frames for b in pending) >= limit:
            yield _joined(header, pending)
            pending = []
    if pending:
        yield _joined(header, pending)


def _joined(header: Recording, batches: Sequence[FrameBatch]) -> Recording:
    """The recording ``header`` with the frames of ``batches`` (numbered from 0)."""

    def join(name: str) -> Any:
        parts = [getattr(batch, name) for batch in batches]
        return None if parts[0] is None else np.concatenate(parts, axis=0)

    return replace(
        header,
        frames=join("frames"),
        frame_times_s=join("frame_times_s"),
        frame_transmitter=join("frame_transmitter"),
        truth_positions_m=join("truth_positions_m"),
        sensor_poses=join("sensor_poses"),
    )


def run_point(study: Study, point: SweepPoint) -> dict[str, Any]:
    """One row of the table: ``point``'s frames simulated and run through the chain a chunk
    at a time (:func:`_chunks`: flat memory whatever the frames), the objects scored against
    the truth. Warnings are collected, not shown, as ``_warnings``."""

    scene = point_scene(study, point)
    settings = point_settings(study, point)
    tally = _Tally()
    seconds = 0.0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        template = settings.check()
        try:
            for recording in _chunks(scene, study.frames):
                start = time.perf_counter()
                results = _objects(settings, recording, template)
                seconds += time.perf_counter() - start
                truth = np.asarray(recording.truth_positions_m, dtype=float)
                tally.add(results, truth, study.match_radius_m)
        except EchoLocError as error:
            raise SweepError(f"{study.source} point {point.index} ({point.describe()}): {error}") from None
    scores = tally.scores(seconds)
    row: dict[str, Any] = {
        "point": point.index,
        **dict(point.values),
        "seed": point.seed,
        "frames": tally.frames,
    }
    row.update((name, scores[name]) for name in study.metrics)
    row["_warnings"] = sorted({str(w.message) for w in caught})
    return row


# --- the whole sweep ---------------------------------------------------------------------


def run_sweep_serial(sweep: Sweep, progress: Callable[[int], None] | None = None) -> list[dict[str, Any]]:
    """Every point in this process, one after the other (no cluster): the rows by point."""
    rows = []
    for point in sweep.points:
        rows.append(run_point(sweep.study, point))
        if progress is not None:
            progress(1)
    return rows


def run_points(study: Study, points: Sequence[SweepPoint]) -> list[dict[str, Any]]:
    """:func:`run_point` of each of ``points``, in turn: one task of :func:`run_sweep`."""
    return [run_point(study, point) for point in points]


def points_per_task(frames: int, n_points: int, n_workers: int) -> int:
    """How many points one task runs: points of fewer than :data:`TASK_FRAMES` frames go
    together up to about that many frames (a task costs the cluster a few milliseconds),
    leaving at least :data:`TASKS_PER_WORKER` tasks a worker to share the work out."""
    together = max(1, TASK_FRAMES // max(1, frames))
    return max(1, min(together, n_points // (TASKS_PER_WORKER * max(1, n_workers))))


def run_sweep(
    sweep: Sweep,
    client: Any,
    *,
    progress: Callable[[int], None] | None = None,
    order: Sequence[int] | None = None,
    workers: Sequence[str] | None = None,
    group: int | None = None,
) -> list[dict[str, Any]]:
    """Every point on the ``dask.distributed`` ``client``, ``group`` points a task (default:
    :func:`points_per_task`): the rows by point, the same whatever the workers, the
    grouping and the order the tasks run.

    ``order``: the points' indices in the order to submit them (default: as numbered);
    ``workers``: the worker addresses that may run them (default: any). The first point
    that fails raises its error (naming it), the rest are cancelled.
    """
    from distributed import as_completed

    n_points = len(sweep.points)
    indices = list(range(n_points)) if order is None else list(order)
    if sorted(indices) != list(range(n_points)):
        raise SweepError("the order to submit the points in must name each point once")
    if group is None:
        n_workers = len(workers) if workers is not None else len(client.scheduler_info().get("workers", {}))
        group = points_per_task(sweep.study.frames, n_points, n_workers)
    if group < 1:
        raise SweepError(f"points a task must be >= 1, got {group}")
    token = hashlib.sha256(f"{sweep.source}{time.time_ns()}".encode()).hexdigest()[:12]
    [study] = client.scatter([sweep.study], broadcast=True, hash=False)
    futures = [
        client.submit(
            run_points,
            study,
            [sweep.points[i] for i in indices[start : start + group]],
            key=f"echoloc-sweep-{token}-{start}",
            pure=False,
            workers=None if workers is None else list(workers),
        )
        for start in range(0, n_points, group)
    ]
    rows: dict[int, dict[str, Any]] = {}
    try:
        for future in as_completed(futures):  # type: ignore[no-untyped-call]
            done = future.result()
            rows.update((int(row["point"]), row) for row in done)
            if progress is not None:
                progress(len(done))
    finally:
        client.cancel(futures)
        client.cancel([study])
    return [rows[i] for i in range(n_points)]


# --- the table ---------------------------------------------------------------------------


def cell(value: Any) -> str:
    """A value as the CSV writes it: whole numbers as they are, other numbers to 10
    significant digits (``nan`` when undefined), booleans as ``true``/``false``, lists as JSON."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | np.integer):
        return str(int(value))
    if isinstance(value, float | np.floating):
        return "nan" if math.isnan(value) else format(float(value), ".10g")
    if isinstance(value, str):
        return value
    return json.dumps(value, separators=(", ", ": "))


def csv_text(sweep: Sweep, rows: Sequence[Mapping[str, Any]]) -> str:
    """The table as CSV text: a header of :attr:`Sweep.columns`, one line a point, ``\\n`` ends."""
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(sweep.columns)
    for row in rows:
        writer.writerow([cell(row[name]) for name in sweep.columns])
    return out.getvalue()


def parquet_available() -> bool:
    """Whether pyarrow, which writes Parquet, is installed."""
    try:
        import pyarrow.parquet  # type: ignore[import-not-found]  # noqa: F401
    except ImportError:
        return False
    return True


def write_table(sweep: Sweep, rows: Sequence[Mapping[str, Any]], path: str | Path) -> Path:
    """Write the table: Parquet when ``path`` ends ``.parquet`` (needs pyarrow), else CSV."""
    path = Path(path)
    if path.suffix.lower() == ".parquet":
        if not parquet_available():
            raise SweepError("needs pyarrow: pip install pyarrow")
        import pyarrow as pa
        import pyarrow.parquet as pq

        columns = {
            name: [json.dumps(row[name]) if isinstance(row[name], list | dict) else row[name] for row in rows]
            for name in sweep.columns
        }
        pq.write_table(pa.table(columns), str(path))
        return path
    path.write_text(csv_text(sweep, rows), encoding="utf-8", newline="")
    return path
