"""Occupancy grids: echoes and located objects -> a 2-D or 3-D log-odds map of the workspace.

The report proposes a grid of the workspace in which every cell is unknown, empty or
occupied, filled with a sonar beam's probability profiles (§2.4.5, figure 2.18:
"probably empty" inside the beam before the echo, "somewhere occupied" on the echo's
arc). This module
is that grid, as log-odds (Moravec & Elfes 1985; Thrun, Burgard & Fox, *Probabilistic
Robotics*, 2005, ch. 9) with OctoMap's clamping (Hornung et al. 2013).

**Inverse sensor model.** Each transmitter-receiver channel of a frame is one reading.
A cell at ``p`` with path ``L = |p - T| + |p - R|`` (the echo's ellipsoid, foci at the
transmitter and the receiver) and two-way beam gain ``w = D_T(θ_T) D_R(θ_R)`` (piston
main lobe, :func:`beam_table`) is

- *free* with log-odds ``w logit(free_probability)`` when ``L`` is shorter than the
  first echo less three of the cell's own standard deviations (those of the arc,
  below): nothing detectable lies there;
- *occupied* with ``p = 0.5 + (hit_probability - 0.5) w g`` on each echo's arc, ``g`` a
  Gaussian in ``L - L_k`` whose width is the path uncertainty and the cell's own
  spread of paths;
- left alone beyond the last echo (shadowed or out of reach), inside the blind zone,
  and outside the main lobe or where ``w < min_beam_gain``.

A channel with no echo clears up to ``no_echo_clear_m`` of path (default: 0.8 of the
window) and marks nothing. Three rules keep one reading from undoing another's
(:class:`SensorModel`, and the compiled loops in ``_mapping_kernels.py``):

- *marking wins within a frame*: a cell that any channel marks occupied takes no
  clearing from the others, so that with several receivers (or a ring of sensors)
  one channel's clearing cannot erase another's obstacle;
- *arcs need support*: a cell is marked only where the arcs of ``min_support``
  channels of the frame meet (the receivers' ellipsoids cross at the reflector and
  part along the arc), and an arc's unsupported tails are left alone;
- *silence is no evidence where a wall would be silent*: a cell heard near the
  beam's axis keeps the axes it was heard along, and a reading whose axis is more
  than the half-power angle away clears it by only ``silent_clear`` (a specular
  surface returns nothing at oblique incidence; after Konolige's MURIEL, 1997).

Located objects (:mod:`echoloc.localise.locate`) with their covariance are added as Gaussian
blobs of ``object_probability``; a plane (``--classes``) as the segment of it its echoes
met (the rectangle in the plane spanned by its specular points), not as an arc.

**Frames.** The map lives in the fixed frame of the sensor poses (``sensor_poses`` in
the recording, ``p_world = R(q) p_sensor + t``, or a trajectory file,
:func:`read_trajectory`); without poses it is the sensor frame itself (REP 103
optical: x right, y down, z ahead). A 2-D map (:meth:`GridSpec.floor_plan`) is the
horizontal x-z plane of that frame at one height: one layer of cells.
"""

from __future__ import annotations

import math
import warnings
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation, Slerp

from echoloc.errors import EchoLocError, read_text_input
from echoloc.io.recording import Recording
from echoloc.localise.locate import FrameObjects, LocatedObject
from echoloc.maps.triangulation import Arc, ArcTracker, TrackOptions, TriangulatedPoint
from echoloc.physics.transducer import X_FIRST_NULL, X_MINUS_3DB
from echoloc.pipeline import Chain
from echoloc.tof.echoes import FrameEchoes, frame_time_s

FloatArray = NDArray[np.float64]

MAP_FRAME_ID = "echoloc_map"
"""ROS frame id of the map: the fixed frame the sensor poses are given in."""

_MAX_CELLS = 60_000_000
"""A map holds about 36 bytes a cell while it is built (:class:`MapAccumulator`) and the
pictures and exports take copies: 60 M cells is about 2 GiB of scratch."""


_KEPT_POINTS = 10_000
"""Points placed by tracks that a map keeps a list of (a live map runs for hours)."""

_MIN_TRACK_SIGMA_M = 1e-4
"""A track's fit needs a path uncertainty above zero (``path_sigma_m`` may be 0): 0.1 mm,
below any echo estimator's."""


class MapWarning(UserWarning):
    """A map was built, but from less than was asked (frames outside a trajectory, nothing in reach)."""


def _check_cell(cell_m: float) -> None:
    if not (math.isfinite(cell_m) and cell_m > 0):
        raise EchoLocError(f"grid cell size must be > 0 m, got {cell_m}")


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


@dataclass(frozen=True, eq=False)
class GridSpec:
    """A regular grid of cubic cells: ``origin_m`` is the outer corner of cell (0, 0, 0).

    Cell ``(i, j, k)`` spans ``origin_m + [i, j, k] * cell_m`` to ``+ cell_m`` on each
    axis of the map frame; its centre is half a cell further. A 2-D grid is a grid
    with one layer (``shape[1] == 1`` for :meth:`floor_plan`).
    """

    origin_m: FloatArray
    cell_m: float
    shape: tuple[int, int, int]

    def __post_init__(self) -> None:
        origin = np.asarray(self.origin_m, dtype=float).reshape(-1)
        if origin.shape != (3,) or not np.all(np.isfinite(origin)):
            raise EchoLocError(f"grid origin must be a finite [x, y, z], got {origin.tolist()}")
        if not (math.isfinite(self.cell_m) and self.cell_m > 0):
            raise EchoLocError(f"grid cell size must be > 0 m, got {self.cell_m}")
        shape = tuple(int(n) for n in self.shape)
        if len(shape) != 3 or min(shape) < 1:
            raise EchoLocError(f"grid shape must be three counts >= 1, got {self.shape}")
        if math.prod(shape) > _MAX_CELLS:
            raise EchoLocError(
                f"a grid of {shape[0]} x {shape[1]} x {shape[2]} cells is too large "
                f"(at most {_MAX_CELLS:,}, about 36 bytes each while mapping); "
                "use larger cells or a smaller extent"
            )
        object.__setattr__(self, "origin_m", origin)
        object.__setattr__(self, "shape", shape)

    @classmethod
    def box(cls, lower_m: ArrayLike, upper_m: ArrayLike, cell_m: float) -> GridSpec:
        """A 3-D grid covering the box from ``lower_m`` to ``upper_m``.

        The box is rounded out to cell boundaries at whole multiples of ``cell_m``, the
        lattice OctoMap uses, so that every cell is one OctoMap voxel.
        """
        _check_cell(cell_m)
        lower = np.asarray(lower_m, dtype=float)
        upper = np.asarray(upper_m, dtype=float)
        if lower.shape != (3,) or upper.shape != (3,) or not np.all(upper > lower):
            raise EchoLocError(f"grid box needs lower < upper on every axis, got {lower} and {upper}")
        first = np.floor(lower / cell_m + 1e-9)
        last = np.ceil(upper / cell_m - 1e-9)
        counts = np.maximum(1, last - first).astype(int)
        return cls(first * cell_m, cell_m, (int(counts[0]), int(counts[1]), int(counts[2])))

    @classmethod
    def floor_plan(
        cls, x_m: tuple[float, float], z_m: tuple[float, float], cell_m: float, height_m: float = 0.0
    ) -> GridSpec:
        """A 2-D grid: the horizontal x-z plane of the map frame at ``y = height_m`` (y points down).

        Its one layer is centred on ``height_m``; x and z are rounded out to whole
        multiples of ``cell_m``.
        """
        _check_cell(cell_m)
        if not (x_m[1] > x_m[0] and z_m[1] > z_m[0]):
            raise EchoLocError(f"floor plan needs x and z ranges low < high, got x {x_m}, z {z_m}")
        x0 = math.floor(x_m[0] / cell_m + 1e-9)
        z0 = math.floor(z_m[0] / cell_m + 1e-9)
        nx = max(1, math.ceil(x_m[1] / cell_m - 1e-9) - x0)
        nz = max(1, math.ceil(z_m[1] / cell_m - 1e-9) - z0)
        return cls(np.array([x0 * cell_m, height_m - cell_m / 2, z0 * cell_m]), cell_m, (nx, 1, nz))

    @property
    def is_floor_plan(self) -> bool:
        """Whether the grid is one layer in y (a 2-D map of the x-z plane)."""
        return self.shape[1] == 1

    @property
    def n_cells(self) -> int:
        return math.prod(self.shape)

    @property
    def upper_m(self) -> FloatArray:
        return np.asarray(self.origin_m + np.array(self.shape) * self.cell_m, dtype=float)

    def centres_m(self, axis: int) -> FloatArray:
        """Cell centres along ``axis`` (0, 1, 2 = x, y, z), m."""
        return np.asarray(self.origin_m[axis] + (np.arange(self.shape[axis]) + 0.5) * self.cell_m)

    def cell_indices(self, points_m: ArrayLike) -> tuple[NDArray[np.int64], NDArray[np.bool_]]:
        """Integer cell indices (n, 3) of points, and whether each point is inside the grid."""
        points = np.asarray(points_m, dtype=float).reshape(-1, 3)
        index = np.floor((points - self.origin_m) / self.cell_m).astype(np.int64)
        inside = np.all((index >= 0) & (index < np.array(self.shape)), axis=1) & np.all(
            np.isfinite(points), axis=1
        )
        return index, inside


@dataclass(frozen=True)
class SensorModel:
    """Probabilities of the inverse sensor model (module doc) and the map's clamping.

    hit_probability
        Occupancy of a cell on an echo's arc at the beam's centre.
    free_probability
        Occupancy of a cell before the first echo at the beam's centre.
    object_probability
        Occupancy at the centre of a located object's covariance ellipsoid.
    clamp_probability
        Log-odds are kept between the logits of these two (OctoMap's defaults 0.12, 0.97).
    occupied_probability
        Observed cells above it are occupied; observed cells below the smaller of 0.5
        and ``1 - occupied_probability`` are free (:meth:`OccupancyGrid.occupied`,
        :meth:`OccupancyGrid.free`).
    min_beam_gain
        Cells where the two-way beam gain is below this are left alone.
    path_sigma_m
        Standard deviation of an echo's path (the estimator's and the model's error).
    no_echo_clear_m, clear_fraction
        Path up to which a channel without echoes clears; None: ``clear_fraction`` of
        the recording's window (the faintest echoes come from its far end, where
        silence says least).
    field_of_view_deg
        Half-angle of the beams' main lobe (the piston's first null); None: the
        recording's ``field_of_view_deg``, else 90 (the half-space, flat gain).
    silent_clear, clear_angle_deg
        A cell heard before is cleared by a reading whose beam axis is more than
        ``clear_angle_deg`` (default: the beam's one-way half-power angle,
        :func:`half_power_angle_deg`) from the axes it was heard along by only
        ``silent_clear`` of the usual amount: specular walls are silent at oblique
        incidence, so silence from there is no evidence (module doc).
    arc_sigmas
        Half-width of an echo's arc, in the cell's own sigma (``sqrt(σ_path² + (|∇L|
        h / 2)²)``): a cell holding the reflector is within about one of it, so two
        mark it and clear nothing of it.
    min_support
        A cell on an echo arc is marked occupied only when the arcs of at least this
        many channels of the frame pass through it (fewer where fewer receivers work):
        the receivers' ellipsoids meet at the reflector and part along the arc, so an
        arc's tails are left alone instead of marked.
    tracks
        How the echoes no located object used are followed across frames and placed
        by the sensor's motion (:mod:`echoloc.maps.triangulation`); None: they are not.
    """

    hit_probability: float = 0.7
    free_probability: float = 0.4
    object_probability: float = 0.9
    clamp_probability: tuple[float, float] = (0.12, 0.97)
    occupied_probability: float = 0.5
    min_beam_gain: float = 0.1
    path_sigma_m: float = 0.002
    no_echo_clear_m: float | None = None
    field_of_view_deg: float | None = None
    silent_clear: float = 0.05
    clear_angle_deg: float | None = None
    min_support: int = 2
    clear_fraction: float = 0.8
    arc_sigmas: float = 2.0
    tracks: TrackOptions | None = field(default_factory=TrackOptions)

    def __post_init__(self) -> None:
        for name in ("hit_probability", "object_probability"):
            value = getattr(self, name)
            if not 0.5 < value < 1.0:
                raise EchoLocError(f"{name} must be between 0.5 and 1 (exclusive), got {value}")
        if not 0.0 < self.free_probability < 0.5:
            raise EchoLocError(f"free_probability must be between 0 and 0.5, got {self.free_probability}")
        low, high = self.clamp_probability
        if not 0.0 < low < 0.5 < high < 1.0:
            raise EchoLocError(f"clamp_probability must satisfy 0 < low < 0.5 < high < 1, got {low, high}")
        if not low < self.occupied_probability < high:
            raise EchoLocError(
                f"occupied_probability must lie between the clamps, got {self.occupied_probability}"
            )
        if not 0.0 <= self.min_beam_gain < 1.0:
            raise EchoLocError(f"min_beam_gain must be in [0, 1), got {self.min_beam_gain}")
        if not (math.isfinite(self.path_sigma_m) and self.path_sigma_m >= 0):
            raise EchoLocError(f"path_sigma_m must be >= 0, got {self.path_sigma_m}")
        for name in ("field_of_view_deg", "clear_angle_deg"):
            angle = getattr(self, name)
            if angle is not None and not (math.isfinite(angle) and 0 < angle <= 90):
                raise EchoLocError(f"{name} must be in (0, 90] degrees, got {angle}")
        if not (math.isfinite(self.arc_sigmas) and 1.0 <= self.arc_sigmas <= 5.0):
            raise EchoLocError(f"arc_sigmas must be between 1 and 5, got {self.arc_sigmas}")
        if not 0.0 < self.clear_fraction <= 1.0:
            raise EchoLocError(f"clear_fraction must be in (0, 1], got {self.clear_fraction}")
        if not 1 <= self.min_support <= 254:
            raise EchoLocError(f"min_support must be between 1 and 254 channels, got {self.min_support}")
        if not 0.0 <= self.silent_clear <= 1.0:
            raise EchoLocError(f"silent_clear must be in [0, 1], got {self.silent_clear}")
        if self.tracks is not None and not isinstance(self.tracks, TrackOptions):
            raise EchoLocError(f"tracks must be TrackOptions or None, got {self.tracks!r}")


@dataclass(frozen=True, eq=False)
class OccupancyGrid:
    """Log-odds per cell (float32, ``spec.shape``) and how many readings touched each cell.

    A cell no reading touched is unknown (``updates == 0``); log-odds 0 is p = 0.5.
    """

    spec: GridSpec
    log_odds: NDArray[np.float32]
    updates: NDArray[np.uint16]
    model: SensorModel = field(default_factory=SensorModel)
    frames: int = 0

    def probability(self) -> NDArray[np.float64]:
        """Occupancy probability per cell, ``1 / (1 + exp(-log_odds))``."""
        return np.asarray(1.0 / (1.0 + np.exp(-self.log_odds.astype(float))))

    def occupied(self) -> NDArray[np.bool_]:
        """Cells whose occupancy is above ``model.occupied_probability``."""
        return np.asarray((self.updates > 0) & (self.log_odds > _logit(self.model.occupied_probability)))

    def free(self) -> NDArray[np.bool_]:
        """Observed cells whose occupancy is below 0.5 and ``1 - model.occupied_probability``."""
        limit = min(0.0, -_logit(self.model.occupied_probability))
        return np.asarray((self.updates > 0) & (self.log_odds < limit))

    def known(self) -> NDArray[np.bool_]:
        return np.asarray(self.updates > 0)

    def occupied_centres_m(self) -> FloatArray:
        """Centres (n, 3) of the occupied cells, m, in the map frame."""
        index = np.argwhere(self.occupied())
        return np.asarray(self.spec.origin_m + (index + 0.5) * self.spec.cell_m)


# --- beams ---------------------------------------------------------------------------


def beam_table(field_of_view_deg: float, n: int = 1024) -> tuple[float, NDArray[np.float64]]:
    """One-way piston directivity over the main lobe, sampled uniformly in cos θ.

    ``D(θ) = 2 J1(x) / x``, ``x = k a sin θ`` with ``k a = j_1,1 / sin θ_null``
    (the piston whose first null is at ``field_of_view_deg``; Kinsler et al. §7.4).
    At 90 degrees the beam is taken flat (gain 1 over the front half-space: no
    transducer model). Returns ``cos θ_null`` and the table from there to the axis.
    """
    from scipy.special import j1

    if not 0 < field_of_view_deg <= 90:
        raise EchoLocError(f"field of view must be in (0, 90] degrees, got {field_of_view_deg}")
    cos_null = math.cos(math.radians(field_of_view_deg))
    if field_of_view_deg >= 90:
        return 0.0, np.ones(n)
    ka = X_FIRST_NULL / math.sin(math.radians(field_of_view_deg))
    cos_t = np.linspace(cos_null, 1.0, n)
    x = ka * np.sqrt(np.clip(1.0 - cos_t**2, 0.0, None))
    safe = np.where(x < 1e-8, 1.0, x)
    table = np.where(x < 1e-8, 1.0, 2.0 * j1(safe) / safe)
    return cos_null, np.clip(table, 0.0, 1.0)


def half_power_angle_deg(field_of_view_deg: float) -> float:
    """One-way half-power (-3 dB) half-angle of the piston whose first null is at ``field_of_view_deg``.

    ``sin θ_3dB = x_3dB / (k a)`` with ``2 J1(x_3dB) / x_3dB = 1/√2`` (x_3dB = 1.6163)
    and ``k a = j_1,1 / sin θ_null`` (Kinsler et al. §7.4). A flat wall's echo fades
    out once its normal is about this far off the axis (two-way gain one half).
    """
    if field_of_view_deg >= 90:
        return 90.0
    ka = X_FIRST_NULL / math.sin(math.radians(field_of_view_deg))
    return math.degrees(math.asin(min(1.0, X_MINUS_3DB / ka)))


# --- poses ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Timed poses of the sensor frame in the map frame: ``[x, y, z, qx, qy, qz, qw]`` per row."""

    times_s: FloatArray
    poses: FloatArray
    source: str = "<trajectory>"

    def __post_init__(self) -> None:
        times = np.asarray(self.times_s, dtype=float).reshape(-1)
        poses = np.asarray(self.poses, dtype=float)
        if poses.shape != (len(times), 7):
            raise EchoLocError(f"{self.source}: poses must be (n, 7) rows, got {poses.shape}")
        if len(times) == 0:
            raise EchoLocError(f"{self.source}: the trajectory has no poses")
        if not (np.all(np.isfinite(times)) and np.all(np.isfinite(poses))):
            raise EchoLocError(f"{self.source}: the trajectory has a NaN or infinite value")
        if np.any(np.diff(times) <= 0):
            raise EchoLocError(f"{self.source}: trajectory times must increase strictly")
        norms = np.linalg.norm(poses[:, 3:], axis=1)
        if np.any(np.abs(norms - 1) > 1e-3):
            k = int(np.argmax(np.abs(norms - 1)))
            raise EchoLocError(
                f"{self.source}: the quaternion of pose {k} is not of unit length ({norms[k]:.4f})"
            )
        object.__setattr__(self, "times_s", times)
        object.__setattr__(self, "poses", poses)

    def at(self, times_s: ArrayLike) -> FloatArray:
        """Poses at ``times_s``: positions interpolated linearly, rotations by slerp.

        Times outside the trajectory take its first or last pose.
        """
        times = np.clip(np.asarray(times_s, dtype=float).reshape(-1), self.times_s[0], self.times_s[-1])
        if len(self.times_s) == 1:
            return np.tile(self.poses[0], (len(times), 1))
        position = np.column_stack([np.interp(times, self.times_s, self.poses[:, i]) for i in range(3)])
        rotation = Slerp(self.times_s, Rotation.from_quat(self.poses[:, 3:]))(times).as_quat()
        return np.asarray(np.hstack([position, rotation.reshape(-1, 4)]))


MAX_TRAJECTORY_BYTES = 256 << 20
"""The largest trajectory file read, bytes: at about 100 bytes a pose, an hour of poses at
700 Hz; its rows take a few times the text's size in memory while they are parsed."""


def read_trajectory(path: str | Path) -> Trajectory:
    """Read a trajectory in the TUM RGB-D format: ``time x y z qx qy qz qw`` per line.

    Whitespace or commas separate the values; ``#`` starts a comment. Times are in
    seconds on the recording's clock (``frame_times``); poses are the sensor frame's
    in the map frame (Sturm et al. 2012, the TUM benchmark's ground-truth format).
    """
    source = str(path)
    text = read_text_input(path, what="trajectory", max_bytes=MAX_TRAJECTORY_BYTES)
    rows: list[list[float]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        content = line.split("#", 1)[0].replace(",", " ").split()
        if not content:
            continue
        if len(content) != 8:
            raise EchoLocError(
                f"{source}:{number}: expected 8 values (time x y z qx qy qz qw), got {len(content)}"
            )
        try:
            rows.append([float(v) for v in content])
        except ValueError:
            raise EchoLocError(f"{source}:{number}: not a number in {line.strip()!r}") from None
    if not rows:
        raise EchoLocError(f"{source}: the trajectory has no poses")
    table = np.array(rows)
    return Trajectory(table[:, 0], table[:, 1:], source)


def frame_poses(recording: Recording, trajectory: Trajectory | None = None) -> FloatArray:
    """The sensor's pose at every frame (n_frames, 7): the trajectory's, the recording's, or identity.

    A trajectory must span at least one frame's time; frames outside its span take
    its first or last pose, with a :class:`MapWarning`.
    """
    if trajectory is not None:
        times = np.array([frame_time_s(recording, k) for k in range(recording.n_frames)])
        start, end = trajectory.times_s[0], trajectory.times_s[-1]
        outside = (times < start - 1e-9) | (times > end + 1e-9)
        if np.all(outside):
            raise EchoLocError(
                f"{trajectory.source}: its times {start:g} .. {end:g} s cover none of the frames of "
                f"{recording.source} ({times[0]:g} .. {times[-1]:g} s)"
            )
        if np.any(outside):
            warnings.warn(
                f"{trajectory.source}: {int(outside.sum())} of {len(times)} frames fall outside its "
                f"times {start:g} .. {end:g} s and take its first or last pose",
                MapWarning,
                stacklevel=2,
            )
        return trajectory.at(times)
    if recording.sensor_poses is not None:
        return np.asarray(recording.sensor_poses, dtype=float)
    identity = np.zeros((recording.n_frames, 7))
    identity[:, 6] = 1.0
    return identity


def default_floor_plan(
    recording: Recording, poses: FloatArray, cell_m: float, speed_of_sound_m_s: float
) -> GridSpec:
    """A floor plan covering every place the sensor could have heard, at the sensor's mean height."""
    reach = _window_range_m(recording, speed_of_sound_m_s)
    positions = poses[:, :3]
    low = positions.min(axis=0) - reach
    high = positions.max(axis=0) + reach
    return GridSpec.floor_plan((low[0], high[0]), (low[2], high[2]), cell_m, float(positions[:, 1].mean()))


def default_box(
    recording: Recording, poses: FloatArray, cell_m: float, speed_of_sound_m_s: float
) -> GridSpec:
    """A 3-D grid covering every place the sensor could have heard."""
    reach = _window_range_m(recording, speed_of_sound_m_s)
    positions = poses[:, :3]
    return GridSpec.box(positions.min(axis=0) - reach, positions.max(axis=0) + reach, cell_m)


def choose_grid(
    recording: Recording,
    poses: FloatArray,
    cell_m: float,
    speed_of_sound_m_s: float,
    *,
    three_d: bool = False,
    extent_m: Sequence[tuple[float, float]] | None = None,
    height_m: float | None = None,
) -> GridSpec:
    """The grid ``echoloc map`` fills: a floor plan (x, z at one height), or with
    ``three_d`` a box, over ``extent_m`` ((low, high) per axis, m: x, z for a floor plan,
    x, y, z for a box) or, without it, over every place the sensor at ``poses`` could have
    heard. A floor plan lies at ``height_m`` [default: the sensor's mean height, y]."""
    if three_d:
        if height_m is not None:
            raise EchoLocError("a floor plan's height has no meaning for a 3-D grid; give its extent")
        if extent_m is not None:
            return GridSpec.box([e[0] for e in extent_m], [e[1] for e in extent_m], cell_m)
        return default_box(recording, poses, cell_m, speed_of_sound_m_s)
    if extent_m is not None:
        height = float(poses[:, 1].mean()) if height_m is None else height_m
        return GridSpec.floor_plan(extent_m[0], extent_m[1], cell_m, height)
    spec = default_floor_plan(recording, poses, cell_m, speed_of_sound_m_s)
    if height_m is None:
        return spec
    return GridSpec.floor_plan(
        (spec.origin_m[0], spec.upper_m[0]), (spec.origin_m[2], spec.upper_m[2]), cell_m, height_m
    )


def _window_range_m(recording: Recording, speed_of_sound_m_s: float) -> float:
    """Farthest distance from the head an echo inside the window can come from, m."""
    path = recording.n_samples / recording.sample_rate_hz * speed_of_sound_m_s
    baseline = float(
        np.max(np.linalg.norm(recording.transmitters_m[:, None, :] - recording.receivers_m[None], axis=2))
    )
    extent = float(
        np.max(np.linalg.norm(np.vstack([recording.transmitters_m, recording.receivers_m]), axis=1))
    )
    return (path + baseline) / 2 + extent


# --- building the map ----------------------------------------------------------------


def _unit(vectors: FloatArray) -> FloatArray:
    return np.asarray(vectors / np.linalg.norm(vectors, axis=-1, keepdims=True))


def channel_window(
    paths_m: FloatArray, clear_m: float, path_sigma_m: float, cell_m: float, arc_sigmas: float = 2.0
) -> tuple[float, float, float]:
    """Where one channel's reading acts: (clear below this path, less so many sigmas; reach).

    With echoes, cells are cleared below the first echo less ``arc_sigmas`` of the
    cell's own sigma (its path's and its spread of paths', the arc's half-width), and
    nothing is touched beyond the last echo plus that many of the largest such sigma,
    ``sqrt(σ² + h²)`` (``|∇L| <= 2``). Without echoes, cells are cleared up to
    ``clear_m`` and nothing beyond.
    """
    if len(paths_m) == 0:
        return clear_m, 0.0, clear_m
    widest = math.hypot(path_sigma_m, cell_m)
    return float(paths_m[0]), arc_sigmas, float(paths_m[-1]) + arc_sigmas * widest + cell_m


def _cone_bounds(
    spec: GridSpec, apex: FloatArray, axis: FloatArray, half_angle_rad: float, reach_m: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]] | None:
    """Cell index range [lower, upper) holding the spherical sector of ``reach_m`` about ``axis``."""
    extent = np.zeros((2, 3))
    for i in range(3):
        for sign_index, sign in enumerate((1.0, -1.0)):
            angle = math.acos(max(-1.0, min(1.0, sign * float(axis[i]))))
            reach_along = 1.0 if angle <= half_angle_rad else math.cos(min(math.pi, angle - half_angle_rad))
            extent[sign_index, i] = sign * max(0.0, reach_along) * reach_m
    high = apex + extent[0]
    low = apex + extent[1]
    lower = np.floor((low - spec.origin_m) / spec.cell_m).astype(np.int64) - 1
    upper = np.floor((high - spec.origin_m) / spec.cell_m).astype(np.int64) + 2
    lower = np.maximum(lower, 0)
    upper = np.minimum(upper, np.array(spec.shape))
    if np.any(upper <= lower):
        return None
    return lower, upper


class MapAccumulator:
    """A map being built, frame by frame (the one mutable thing of this module).

    ``add_frame`` integrates one frame's echoes (and, if given, its located objects) at
    one pose; ``grid()`` returns a frozen :class:`OccupancyGrid` snapshot. Scratch
    arrays for a frame's updates are allocated once, so memory stays at about 36
    bytes per cell whatever the number of frames.
    """

    def __init__(
        self,
        spec: GridSpec,
        recording: Recording,
        model: SensorModel | None = None,
        *,
        blind_path_m: float = 0.0,
        usable_receivers: NDArray[np.bool_] | None = None,
    ) -> None:
        from echoloc.maps import _mapping_kernels

        self._kernels = _mapping_kernels
        self.spec = spec
        self.model = model or SensorModel()
        self.recording = recording
        fov = self.model.field_of_view_deg or recording.field_of_view_deg or 90.0
        self._cos_null, self._beam = beam_table(min(90.0, fov))
        self._half_angle = math.radians(min(90.0, fov))
        n = spec.n_cells
        self._log_odds = np.zeros(n, dtype=np.float32)
        self._updates = np.zeros(n, dtype=np.uint16)
        self._occupied = np.zeros(n, dtype=np.float32)
        self._free = np.zeros(n, dtype=np.float32)
        self._hit_axes = np.zeros((n, 3), dtype=np.float32)
        self._support = np.zeros(n, dtype=np.uint8)
        self._central = np.zeros(n, dtype=np.uint8)
        clear_angle = self.model.clear_angle_deg or half_power_angle_deg(min(90.0, fov))
        self._clear_cos = math.cos(math.radians(clear_angle))
        self._stamp = np.full(n, -1, dtype=np.int32)
        self._touched = np.zeros(n, dtype=np.int32)
        self._frames = 0
        self._stamp_id = 0
        self._blind_m = float(blind_path_m)
        self._usable = None if usable_receivers is None else np.asarray(usable_receivers, dtype=bool)
        self._tx_axes = (
            _unit(np.asarray(recording.transmitter_axes, dtype=float))
            if recording.transmitter_axes is not None
            else np.tile([0.0, 0.0, 1.0], (len(recording.transmitters_m), 1))
        )
        self._rx_axes = (
            _unit(np.asarray(recording.receiver_axes, dtype=float))
            if recording.receiver_axes is not None
            else np.tile([0.0, 0.0, 1.0], (recording.n_receivers, 1))
        )
        low, high = self.model.clamp_probability
        self._clamp = (_logit(low), _logit(high))
        self._hit_gain = self.model.hit_probability - 0.5
        self._free_gain = _logit(self.model.free_probability)
        # A floor plan is a slice at one height: tracks are fitted in it, the height held.
        slice_m = {a: float(spec.centres_m(a)[0]) for a in range(3) if spec.shape[a] == 1}
        self._tracker = (
            None
            if self.model.tracks is None
            else ArcTracker(
                self.model.tracks
                if self.model.tracks.max_std_m is not None
                else replace(self.model.tracks, max_std_m=spec.cell_m),
                half_angle_rad=self._half_angle,
                path_sigma_m=max(self.model.path_sigma_m, _MIN_TRACK_SIGMA_M),
                fixed=slice_m,
                fixed_within_m=spec.cell_m / 2,
            )
        )
        # Each frame's count of earlier frames its transmitter fired (tracks count their
        # channel's missed firings); without a schedule, one transmitter fires every frame.
        self._firings: NDArray[np.int64] | None = None
        if recording.frame_transmitter is not None:
            schedule = np.asarray(recording.frame_transmitter, dtype=np.int64)
            self._firings = np.zeros(len(schedule), dtype=np.int64)
            for t in np.unique(schedule):
                mine = schedule == t
                self._firings[mine] = np.arange(int(mine.sum()))
        self.triangulated: deque[TriangulatedPoint] = deque(maxlen=_KEPT_POINTS)
        """The last points the tracks placed (and the map marked), oldest first."""
        self.n_triangulated = 0
        """How many points the tracks placed in the grid, in all."""

    @property
    def memory_bytes(self) -> int:
        """Bytes held by the grid and its scratch arrays."""
        arrays = (
            self._log_odds,
            self._updates,
            self._occupied,
            self._free,
            self._hit_axes,
            self._support,
            self._central,
            self._stamp,
            self._touched,
        )
        return sum(a.nbytes for a in arrays)

    def add_frame(
        self,
        echoes: FrameEchoes,
        pose: ArrayLike,
        *,
        transmitter: int = 0,
        objects: FrameObjects | None = None,
    ) -> None:
        """Integrate one frame: every usable channel's reading, then the located objects, at ``pose``."""
        usable_receivers = self._usable
        pose_row = np.asarray(pose, dtype=float).reshape(7)
        rotation = Rotation.from_quat(pose_row[3:]).as_matrix()
        translation = pose_row[:3]
        tx_world = rotation @ self.recording.transmitters_m[transmitter] + translation
        tx_axis = rotation @ self._tx_axes[transmitter]
        c = echoes.speed_of_sound_m_s
        window = self.recording.n_samples / self.recording.sample_rate_hz * c
        clear_m = (
            self.model.no_echo_clear_m
            if self.model.no_echo_clear_m is not None
            else self.model.clear_fraction * window
        )
        sigma = self.model.path_sigma_m
        spec = self.spec
        origin = spec.origin_m
        shape = np.array(spec.shape, dtype=np.int64)
        frame_id = self._stamp_id
        n_touched = 0
        for rx, channel in enumerate(echoes.channels):
            if usable_receivers is not None and not usable_receivers[rx]:
                continue
            paths = np.sort(np.asarray(channel.tof_s, dtype=float) * c)
            paths = paths[paths <= window]
            rx_world = rotation @ self.recording.receivers_m[rx] + translation
            rx_axis = rotation @ self._rx_axes[rx]
            free_below, margin, reach = channel_window(
                paths, float(clear_m), sigma, spec.cell_m, self.model.arc_sigmas
            )
            baseline = float(np.linalg.norm(tx_world - rx_world))
            bounds = _cone_bounds(spec, tx_world, tx_axis, self._half_angle, (reach + baseline) / 2)
            if bounds is None:
                continue
            n_touched = self._kernels.channel_update(
                origin,
                spec.cell_m,
                shape,
                bounds[0],
                bounds[1],
                tx_world,
                rx_world,
                tx_axis,
                rx_axis,
                self._cos_null,
                self._beam,
                self.model.min_beam_gain,
                free_below,
                margin,
                self._blind_m,
                paths,
                sigma,
                self.model.arc_sigmas,
                reach,
                self._hit_gain,
                self._free_gain,
                self._occupied,
                self._free,
                self._support,
                self._central,
                self._hit_axes,
                self._clear_cos,
                self.model.silent_clear,
                self._stamp,
                frame_id,
                self._touched,
                n_touched,
            )
        if objects is not None:
            n_touched = self._add_objects(objects, rotation, translation, frame_id, n_touched)
        if self._tracker is not None:
            arcs = self._unplaced_arcs(echoes, objects, rotation, translation, transmitter, tx_world, tx_axis)
            firings = self._firings
            firing = (
                int(firings[echoes.frame])
                if firings is not None and 0 <= echoes.frame < len(firings)
                else None
            )
            for point in self._tracker.add(echoes.frame, arcs, firing=firing):
                n_touched = self._add_triangulated(point, frame_id, n_touched)
        usable = len(echoes.channels) if usable_receivers is None else int(np.sum(usable_receivers))
        self._apply(n_touched, max(1, min(self.model.min_support, usable)), tx_axis)
        self._frames += 1

    def _apply(self, n_touched: int, min_support: int, tx_axis: FloatArray) -> None:
        """Add the touched cells' evidence to the map (``apply_frame``), then move the stamp on."""
        self._kernels.apply_frame(
            self._log_odds,
            self._updates,
            self._occupied,
            self._free,
            self._support,
            self._central,
            min_support,
            self._hit_axes,
            tx_axis,
            self._touched,
            n_touched,
            self._clamp[0],
            self._clamp[1],
        )
        self._stamp_id += 1

    def _add_objects(
        self,
        objects: FrameObjects,
        rotation: FloatArray,
        translation: FloatArray,
        frame_id: int,
        n_touched: int,
    ) -> int:
        """Each located object as a Gaussian blob of its covariance (plus the cell's own spread);
        a plane (reflector classes) as the patch of it that was heard (:meth:`_add_plane`)."""
        for obj in objects.objects:
            surface = obj.surface
            if surface is not None and surface.kind == "plane" and surface.specular_points_m is not None:
                n_touched = self._add_plane(obj, rotation, translation, frame_id, n_touched)
                continue
            mean = rotation @ np.asarray(obj.position_m, dtype=float) + translation
            covariance = rotation @ np.asarray(obj.covariance_m2, dtype=float) @ rotation.T
            n_touched = self._add_gaussian(
                mean, covariance, frame_id, n_touched, peak_probability=self.model.object_probability
            )
        return n_touched

    def _unplaced_arcs(
        self,
        echoes: FrameEchoes,
        objects: FrameObjects | None,
        rotation: FloatArray,
        translation: FloatArray,
        transmitter: int,
        tx_world: FloatArray,
        tx_axis: FloatArray,
    ) -> dict[tuple[int, int], list[Arc]]:
        """The frame's echoes that no located object used, as world-frame arcs, for every usable
        channel of the transmitter that fired (those without such echoes too: the tracker
        counts the firings a track missed)."""
        used: set[tuple[int, int]] = set()
        if objects is not None:
            for obj in objects.objects:
                sources = obj.transmitters or (transmitter,) * len(obj.receivers)
                used.update(
                    (rx, index)
                    for rx, index, source in zip(obj.receivers, obj.echo_indices, sources, strict=True)
                    if source == transmitter
                )
        c = echoes.speed_of_sound_m_s
        arcs: dict[tuple[int, int], list[Arc]] = {}
        for rx, channel in enumerate(echoes.channels):
            if self._usable is not None and not self._usable[rx]:
                continue
            rx_world = rotation @ self.recording.receivers_m[rx] + translation
            paths = np.asarray(channel.tof_s, dtype=float) * c
            arcs[transmitter, rx] = [
                Arc(echoes.frame, tx_world, rx_world, float(path), tx_axis)
                for index, path in enumerate(paths)
                if (rx, index) not in used and path >= self._blind_m
            ]
        return arcs

    def _add_triangulated(self, point: TriangulatedPoint, frame_id: int, n_touched: int) -> int:
        """A track's point (:mod:`echoloc.maps.triangulation`), fitted in the grid's slice (a
        floor plan) or in space (a 3-D grid): each of its arcs, now placed, adds the evidence
        of an arc (``hit_probability``) at the point, spread by its covariance out to two
        standard deviations."""
        if not self.spec.cell_indices(point.position_m[None, :])[1][0]:
            return n_touched  # outside the grid: nothing to mark
        self.triangulated.append(point)
        self.n_triangulated += 1
        return self._add_gaussian(
            point.position_m,
            point.covariance_m2,
            frame_id,
            n_touched,
            peak_probability=self.model.hit_probability,
            weight=point.n_arcs,
            cutoff_sigmas=2.0,
        )

    def _add_gaussian(
        self,
        mean: FloatArray,
        covariance: FloatArray,
        frame_id: int,
        n_touched: int,
        *,
        peak_probability: float,
        weight: float = 1.0,
        cutoff_sigmas: float = math.inf,
    ) -> int:
        """``weight`` times the log-odds of a Gaussian blob of ``peak_probability`` at its centre
        (world frame), spread by the covariance plus the cell's own spread, over its 3-sigma
        box and within ``cutoff_sigmas`` (Mahalanobis) of the centre or in the centre's cell."""
        spec = self.spec
        h = spec.cell_m
        ny, nz = spec.shape[1], spec.shape[2]
        covariance = covariance + np.eye(3) * (h * h / 12.0)
        if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(covariance))):
            return n_touched
        half = 3.0 * np.sqrt(np.diag(covariance))
        lower = np.maximum(np.floor((mean - half - spec.origin_m) / h).astype(int), 0)
        upper = np.minimum(np.floor((mean + half - spec.origin_m) / h).astype(int) + 1, spec.shape)
        if np.any(upper <= lower):
            return n_touched
        grids = np.meshgrid(*(np.arange(lower[a], upper[a]) for a in range(3)), indexing="ij")
        index = np.stack([g.reshape(-1) for g in grids], axis=1)
        offset = spec.origin_m + (index + 0.5) * h - mean
        d2 = np.einsum("ni,ij,nj->n", offset, np.linalg.inv(covariance), offset)
        # Within the cutoff, and always the cell that holds the centre.
        within = (d2 <= cutoff_sigmas**2) | np.all(index == np.floor((mean - spec.origin_m) / h), axis=1)
        index, d2 = index[within], d2[within]
        p = 0.5 + (peak_probability - 0.5) * np.exp(-0.5 * d2)
        cells = (index[:, 0] * ny + index[:, 1]) * nz + index[:, 2]
        return int(
            self._kernels.add_supported_evidence(
                cells,
                weight * np.log(p / (1 - p)),
                self._occupied,
                self._support,
                self._stamp,
                frame_id,
                self._touched,
                n_touched,
            )
        )

    def finish_tracks(self) -> None:
        """Fit the tracks still open (the end of a recording) and mark their points."""
        if self._tracker is None:
            return
        n_touched = 0
        for point in self._tracker.finish():
            n_touched = self._add_triangulated(point, self._stamp_id, n_touched)
        self._apply(n_touched, 1, np.zeros(3))

    def _add_plane(
        self, obj: LocatedObject, rotation: FloatArray, translation: FloatArray, frame_id: int, n_touched: int
    ) -> int:
        """A plane as a surface segment: the rectangle in the plane spanned by the points where the
        channels' echoes met it (their specular points), sampled every half cell, each cell it
        crosses marked with ``object_probability``; a single specular point marks its cell."""
        surface = obj.surface
        assert surface is not None
        assert surface.specular_points_m is not None
        assert surface.normal is not None
        spec = self.spec
        h = spec.cell_m
        ny, nz = spec.shape[1], spec.shape[2]
        points = np.asarray(surface.specular_points_m, dtype=float) @ rotation.T + translation
        normal = rotation @ np.asarray(surface.normal, dtype=float)
        helper = np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
        u = np.cross(normal, helper)
        u /= np.linalg.norm(u)
        v = np.cross(normal, u)
        centre = points.mean(axis=0)
        along_u, along_v = (points - centre) @ u, (points - centre) @ v
        steps_u = np.arange(along_u.min(), along_u.max() + h / 4, h / 2)
        steps_v = np.arange(along_v.min(), along_v.max() + h / 4, h / 2)
        grid_u, grid_v = np.meshgrid(steps_u, steps_v, indexing="ij")
        samples = centre + grid_u.reshape(-1, 1) * u + grid_v.reshape(-1, 1) * v
        index = np.floor((samples - spec.origin_m) / h).astype(np.int64)
        inside = np.all((index >= 0) & (index < np.array(spec.shape)), axis=1)
        index = np.unique(index[inside], axis=0)
        if not len(index):
            return n_touched
        cells = (index[:, 0] * ny + index[:, 1]) * nz + index[:, 2]
        p = self.model.object_probability
        return int(
            self._kernels.add_supported_evidence(
                cells,
                np.full(len(cells), math.log(p / (1 - p))),
                self._occupied,
                self._support,
                self._stamp,
                frame_id,
                self._touched,
                n_touched,
            )
        )

    def grid(self) -> OccupancyGrid:
        """A frozen snapshot of the map as it is now."""
        return OccupancyGrid(
            self.spec,
            self._log_odds.reshape(self.spec.shape).copy(),
            self._updates.reshape(self.spec.shape).copy(),
            self.model,
            self._frames,
        )


def build_map(
    recording: Recording,
    results: Iterable[tuple[FrameEchoes, FrameObjects | None]],
    spec: GridSpec,
    *,
    model: SensorModel | None = None,
    poses: FloatArray | None = None,
    blind_path_m: float = 0.0,
    usable_receivers: NDArray[np.bool_] | None = None,
    progress: Callable[[int], None] | None = None,
) -> OccupancyGrid:
    """Integrate every frame's echoes (and objects, where not None) into a grid.

    ``results`` is what :func:`echoloc.pipeline.run` yields (objects may be None to
    map from echoes alone); ``poses`` (n_frames, 7), by default :func:`frame_poses`.
    """
    accumulator = MapAccumulator(
        spec, recording, model, blind_path_m=blind_path_m, usable_receivers=usable_receivers
    )
    return integrate(accumulator, results, poses, progress=progress)


def chain_accumulator(
    chain: Chain, spec: GridSpec, *, path_sigma_m: float | None = None, tracks: bool = True
) -> MapAccumulator:
    """A :class:`MapAccumulator` for the frames a chain processes.

    Its beam is the chain's field of view (the recording's ``field_of_view_deg`` or
    the user's, at most the half-space), its blind zone the chain's blanking, and it
    leaves out the receivers the chain leaves out. ``tracks``: place the echoes one
    receiver heard alone by following them across poses (:class:`SensorModel`).
    """
    fov = min(90.0, float(chain.locate_options.field_of_view_deg))
    model = SensorModel(field_of_view_deg=fov, tracks=TrackOptions() if tracks else None)
    if path_sigma_m is not None:
        model = replace(model, path_sigma_m=path_sigma_m)
    return MapAccumulator(
        spec,
        chain.recording,
        model,
        blind_path_m=chain.echo_options.blanking_s * chain.speed_of_sound_m_s,
        usable_receivers=chain.usable_receivers,
    )


def integrate(
    accumulator: MapAccumulator,
    results: Iterable[tuple[FrameEchoes, FrameObjects | None]],
    poses: FloatArray | None = None,
    *,
    progress: Callable[[int], None] | None = None,
) -> OccupancyGrid:
    """Add every frame of ``results`` to ``accumulator`` at its pose; the grid it then holds.

    Frames fired by transmitter ``frame_transmitter[k]`` use that transmitter.
    """
    recording = accumulator.recording
    poses = frame_poses(recording) if poses is None else np.asarray(poses, dtype=float)
    if poses.shape != (recording.n_frames, 7):
        raise EchoLocError(
            f"{recording.source}: {poses.shape[0]} poses for {recording.n_frames} frames (need one per frame)"
        )
    for echoes, objects in results:
        transmitter = (
            0 if recording.frame_transmitter is None else int(recording.frame_transmitter[echoes.frame])
        )
        accumulator.add_frame(echoes, poses[echoes.frame], transmitter=transmitter, objects=objects)
        if progress is not None:
            progress(1)
    accumulator.finish_tracks()
    grid = accumulator.grid()
    if grid.frames and not grid.known().any():
        warnings.warn(
            f"{recording.source}: no cell of the {' x '.join(map(str, grid.spec.shape))} grid was within "
            "reach of the sensor; the map is all unknown (check its extent and height)",
            MapWarning,
            stacklevel=2,
        )
    return grid


# --- accuracy against known surfaces ---------------------------------------------------


@dataclass(frozen=True)
class MapAccuracy:
    """How a map's occupied cells compare with the true surfaces (within ``tolerance_cells``).

    coverage
        Fraction of the seen surface samples with an occupied cell within tolerance.
    precision
        Fraction of occupied cells within tolerance of any true surface sample.
    false_cells, false_area_m2
        Occupied cells farther than that from every surface ("ghosts"), and their
        area (2-D) or volume (3-D, then m^3).
    free_cells
        Observed cells whose occupancy is below 0.5: free space.
    ghost_fraction, ghost_area_m2
        With a mask of the truly free space: the fraction of its observed cells that
        are occupied, and their area (volume in 3-D); NaN without a mask.
    """

    coverage: float
    precision: float
    occupied_cells: int
    false_cells: int
    false_area_m2: float
    free_cells: int
    seen_samples: int
    ghost_fraction: float = float("nan")
    ghost_area_m2: float = float("nan")


def _dilated(mask: NDArray[np.bool_], cells: int) -> NDArray[np.bool_]:
    from scipy.ndimage import binary_dilation

    if cells <= 0:
        return mask
    return np.asarray(binary_dilation(mask, structure=np.ones((3, 3, 3), bool), iterations=cells))


def map_accuracy(
    grid: OccupancyGrid,
    surface_points_m: ArrayLike,
    seen_points_m: ArrayLike | None = None,
    *,
    tolerance_cells: int = 1,
    free_space: NDArray[np.bool_] | None = None,
) -> MapAccuracy:
    """Coverage and precision of ``grid`` against sampled true surfaces (module :class:`MapAccuracy`).

    ``surface_points_m`` samples every true surface densely (spacing below a cell);
    ``seen_points_m`` the part of them the sensor saw (default: all); ``free_space``
    (``spec.shape``) marks the cells known to be empty (e.g. a room's interior farther
    than the tolerance from every surface), where an occupied cell is a ghost.
    """
    spec = grid.spec
    occupied = grid.occupied()
    surface = np.zeros(spec.shape, dtype=bool)
    index, inside = spec.cell_indices(surface_points_m)
    surface[tuple(index[inside].T)] = True
    near_surface = _dilated(surface, tolerance_cells)
    seen = np.asarray(surface_points_m if seen_points_m is None else seen_points_m, dtype=float).reshape(
        -1, 3
    )
    seen_index, seen_inside = spec.cell_indices(seen)
    near_occupied = _dilated(occupied, tolerance_cells)
    seen_hit = near_occupied[tuple(seen_index[seen_inside].T)]
    n_occupied = int(occupied.sum())
    false = occupied & ~near_surface
    cell_measure = spec.cell_m ** (2 if spec.is_floor_plan else 3)
    ghost_fraction = ghost_area = float("nan")
    if free_space is not None:
        if free_space.shape != spec.shape:
            raise EchoLocError(f"free_space has shape {free_space.shape}, the grid {spec.shape}")
        truly_free = free_space & grid.known()
        ghosts = int((occupied & truly_free).sum())
        ghost_fraction = ghosts / max(1, int(truly_free.sum()))
        ghost_area = ghosts * cell_measure
    return MapAccuracy(
        coverage=float(seen_hit.mean()) if len(seen_hit) else float("nan"),
        precision=float((occupied & near_surface).sum() / n_occupied) if n_occupied else float("nan"),
        occupied_cells=n_occupied,
        false_cells=int(false.sum()),
        false_area_m2=float(false.sum() * cell_measure),
        free_cells=int(grid.free().sum()),
        seen_samples=len(seen_hit),
        ghost_fraction=ghost_fraction,
        ghost_area_m2=ghost_area,
    )


def grid_arrays(grid: OccupancyGrid) -> dict[str, Any]:
    """The grid as plain arrays and attributes (what
    :func:`echoloc.maps.map_export.write_grid_npz` stores)."""
    return {
        "log_odds": grid.log_odds,
        "updates": grid.updates,
        "origin_m": grid.spec.origin_m,
        "cell_m": np.float64(grid.spec.cell_m),
        "frames": np.int64(grid.frames),
        "frame_id": np.str_(MAP_FRAME_ID),
    }


def seen_truth_points_m(
    recording: Recording,
    echoes_per_frame: Iterable[FrameEchoes],
    poses: FloatArray | None = None,
    *,
    tolerance_m: float = 0.01,
    field_of_view_deg: float | None = None,
    min_channels: int = 2,
) -> FloatArray:
    """The recording's ``truth_positions`` that some channel heard, in the map frame (n, 3).

    A true reflection point ``p`` of frame ``k`` counts as heard when it lies inside
    the transmitter's beam (within ``field_of_view_deg``, default the recording's,
    of its axis) and at least ``min_channels`` channels of that frame have an echo
    within ``tolerance_m`` of their path ``|p - T| + |p - R|`` (the map's
    ``min_support``: one receiver alone cannot place a reflector): the part of the
    scene that the sensor actually saw, against which a map is scored.
    """
    if recording.truth_positions_m is None:
        raise EchoLocError(f"{recording.source}: has no truth_positions to score a map against")
    poses = frame_poses(recording) if poses is None else poses
    fov = field_of_view_deg or recording.field_of_view_deg or 90.0
    cos_beam = math.cos(math.radians(fov))
    heard: list[FloatArray] = [np.zeros((0, 3))]
    for echoes in echoes_per_frame:
        truth = recording.truth_positions_m[echoes.frame]
        truth = truth[np.all(np.isfinite(truth), axis=1)]
        if not len(truth):
            continue
        tx_index = (
            0 if recording.frame_transmitter is None else int(recording.frame_transmitter[echoes.frame])
        )
        tx = recording.transmitters_m[tx_index]
        axis = (
            np.array([0.0, 0.0, 1.0])
            if recording.transmitter_axes is None
            else recording.transmitter_axes[tx_index]
        )
        offset = truth - tx
        cos_angle = offset @ axis / np.maximum(np.linalg.norm(offset, axis=1) * np.linalg.norm(axis), 1e-12)
        count = np.zeros(len(truth), dtype=int)
        for rx, channel in enumerate(echoes.channels):
            if not len(channel.tof_s):
                continue
            model = np.linalg.norm(truth - tx, axis=1) + np.linalg.norm(
                truth - recording.receivers_m[rx], axis=1
            )
            measured = np.asarray(channel.tof_s) * echoes.speed_of_sound_m_s
            count += np.min(np.abs(model[:, None] - measured[None, :]), axis=1) <= tolerance_m
        found = (count >= min_channels) & (cos_angle >= cos_beam)
        if np.any(found):
            pose = poses[echoes.frame]
            rotation = Rotation.from_quat(pose[3:]).as_matrix()
            heard.append(truth[found] @ rotation.T + pose[:3])
    return np.asarray(np.vstack(heard), dtype=float)


def seen_surface_points_m(
    surface_points_m: ArrayLike, heard_points_m: ArrayLike, spec: GridSpec, *, within_cells: float = 1.0
) -> FloatArray:
    """The surface samples within ``within_cells`` cells of a heard reflection point (and in the grid)."""
    from scipy.spatial import cKDTree

    surface = np.asarray(surface_points_m, dtype=float).reshape(-1, 3)
    heard = np.asarray(heard_points_m, dtype=float).reshape(-1, 3)
    _, inside = spec.cell_indices(surface)
    surface = surface[inside]
    if not len(heard) or not len(surface):
        return np.zeros((0, 3))
    distance, _ = cKDTree(heard).query(surface, k=1)
    return np.asarray(surface[distance <= within_cells * spec.cell_m])
