"""Multi-pose triangulation: reflectors one receiver heard alone, placed by the sensor's motion.

An echo that no located object explains puts its reflector somewhere on one ellipsoid
(foci the transmitter and the receiver, path ``L``): within one frame, nowhere. As the
sensor moves, the same static reflector keeps returning an echo on the same channel
whose path changes smoothly from frame to frame, and every one of those ellipsoids
passes through it. Following such an echo from frame to frame (a *track*) and finding
the point on all of its ellipsoids places the reflector. This is the sonar practice of
grouping returns across poses before placing them: Leonard & Durrant-Whyte's regions of
constant depth (*Directed Sonar Sensing for Mobile Robot Navigation*, 1992) and Wijk &
Christensen's triangulation-based fusion (IEEE T-RA 16(6), 2000).

**Tracks.** Each transmitter-receiver channel is followed separately, over the frames
in which its transmitter fired. An unplaced echo joins the open track whose predicted
path is nearest (a straight line through the track's last five paths against the frame
number), if the miss is within ``gate_m`` per frame since the track's last echo plus four
path sigmas. A track that missed more than ``max_gap_frames`` of its channel's firings
(frames skipped in the input count as missed) ends.

**Fit.** A track of ``n`` arcs ``(T_k, R_k, L_k)`` (world frame) is fitted by the point
``p`` that minimises ``sum_k ((|p - T_k| + |p - R_k| - L_k) / sigma)^2`` (``sigma`` the
path's standard deviation), over the coordinates the caller leaves free: a floor plan is
a slice at one height, so there the height is held at the slice's and the question is
where the ellipsoids meet in it. The start is the best of a grid of directions inside
the beam, each placed on the middle arc's ellipsoid by ``rho = (L^2 - |d|^2) / (2 (L -
u . d))``; Levenberg-Marquardt (scipy) refines it. The covariance is ``s^2 (J^T J)^-1``
with ``s^2`` the reduced chi-square, as scipy's ``curve_fit`` gives it when the noise
level is not known absolutely: the scatter of the track's own paths sets it.

**Acceptance.** A track becomes a point when it has ``min_arcs`` arcs or more, its
reduced chi-square against ``sigma`` is at most ``max_reduced_chi2`` (a specular wall's
arcs touch the wall at points that slide along it, so they fit no single point once the
sensor has moved far enough), and every free coordinate is fixed within ``max_std_m``
(a sensor that stood still, or drove straight at the reflector, fixes only its range).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from echoloc.errors import EchoLocError

FloatArray = NDArray[np.float64]

_RATE_ARCS = 5
"""Arcs a track's predicted path is fitted through (a straight line in the frame number)."""
_START_ARCS = 40
"""Arcs, evenly spread over the track, on which the start's grid of directions is scored."""
_NOISE_GATE_SIGMAS = 4.0
"""Path sigmas a track's gate allows beyond its motion allowance."""


def _whole(name: str, value: object, low: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < low:
        raise EchoLocError(f"{name} must be a whole number >= {low}, got {value!r}")
    return int(value)


def _positive(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise EchoLocError(f"{name} must be a number > 0, got {value!r}")
    if not (math.isfinite(value) and value > 0):
        raise EchoLocError(f"{name} must be a finite number > 0, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class TrackOptions:
    """How unplaced echoes are tracked across frames and when a track becomes a point.

    gate_m
        Largest change of an echo's path from its track's prediction, per frame since
        the track's last echo, m (four path sigmas are allowed on top).
    max_gap_frames
        A track that missed more of its channel's firings than this ends.
    min_arcs
        Fewest arcs (frames) a track needs to be fitted.
    max_reduced_chi2
        Largest chi-square per degree of freedom, against the path sigma, of an accepted
        point.
    max_std_m
        Largest standard deviation, m, of an accepted point along any free direction.
    max_arcs
        A track this long is fitted and restarted from its last two arcs (bounds the
        memory and the fit's cost).
    """

    gate_m: float = 0.006
    max_gap_frames: int = 3
    min_arcs: int = 12
    max_reduced_chi2: float = 4.0
    max_std_m: float = 0.03
    max_arcs: int = 400

    def __post_init__(self) -> None:
        _positive("gate_m", self.gate_m)
        _whole("max_gap_frames", self.max_gap_frames, 0)
        _whole("min_arcs", self.min_arcs, 4)
        _whole("max_arcs", self.max_arcs, 4)
        if self.min_arcs > self.max_arcs:
            raise EchoLocError(f"min_arcs ({self.min_arcs}) must be at most max_arcs ({self.max_arcs})")
        _positive("max_reduced_chi2", self.max_reduced_chi2)
        _positive("max_std_m", self.max_std_m)


@dataclass(frozen=True)
class Arc:
    """One unplaced echo in the world frame: its ellipsoid's foci and path, and the beam's axis."""

    frame: int
    transmitter_m: FloatArray
    receiver_m: FloatArray
    path_m: float
    axis: FloatArray


@dataclass(frozen=True)
class TriangulatedPoint:
    """A reflector placed by a track of arcs: world position and covariance (zero along the
    coordinates held fixed), the fit's reduced chi-square against the path sigma, and the
    frames and channel (transmitter, receiver) it came from."""

    position_m: FloatArray
    covariance_m2: FloatArray
    reduced_chi2: float
    n_arcs: int
    first_frame: int
    last_frame: int
    channel: tuple[int, int]


def _direction_grid(axis: FloatArray, half_angle_rad: float, steps: int) -> FloatArray:
    """Unit vectors filling the cone of ``half_angle_rad`` (at most 80 degrees) about ``axis``:
    a square grid of tangent-plane offsets, those inside the cone kept."""
    helper = np.array([1.0, 0.0, 0.0]) if abs(axis[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    reach = math.tan(min(half_angle_rad, math.radians(80.0)))
    offsets = np.linspace(-reach, reach, steps)
    grid_a, grid_b = np.meshgrid(offsets, offsets, indexing="ij")
    a, b = grid_a.reshape(-1), grid_b.reshape(-1)
    keep = a * a + b * b <= reach * reach + 1e-12
    directions = axis + a[keep, None] * u + b[keep, None] * v
    return np.asarray(directions / np.linalg.norm(directions, axis=1, keepdims=True), dtype=float)


def on_ellipsoid_m(
    transmitter_m: FloatArray, receiver_m: FloatArray, path_m: float, directions: FloatArray
) -> FloatArray:
    """Points ``T + rho u`` on the ellipsoid ``|p - T| + |p - R| = L`` along unit directions ``u``:
    ``rho = (L^2 - |d|^2) / (2 (L - u . d))`` with ``d = R - T`` (squaring ``|rho u - d| = L - rho``).
    Needs ``L > |d|``."""
    d = receiver_m - transmitter_m
    rho = (path_m**2 - d @ d) / (2.0 * (path_m - directions @ d))
    return np.asarray(transmitter_m + rho[:, None] * directions, dtype=float)


def fit_track(
    arcs: Sequence[Arc],
    options: TrackOptions,
    *,
    half_angle_rad: float,
    path_sigma_m: float,
    fixed: Mapping[int, float] | None = None,
    channel: tuple[int, int] = (0, 0),
) -> TriangulatedPoint | None:
    """The point on all of ``arcs``' ellipsoids (module doc), or None when the track is too
    short, fits no point, does not fix one, or holds values no fit can use.

    ``half_angle_rad``: the beam's half-angle (where the start is looked for);
    ``path_sigma_m``: an echo path's standard deviation, m; ``fixed``: coordinates (0 x,
    1 y, 2 z) held at the given values, m (a floor plan's height).
    """
    n = len(arcs)
    if n < options.min_arcs:
        return None
    fixed = dict(fixed or {})
    free = [a for a in range(3) if a not in fixed]
    if not free or n <= len(free):
        return None
    transmitters = np.array([a.transmitter_m for a in arcs], dtype=float)
    receivers = np.array([a.receiver_m for a in arcs], dtype=float)
    paths = np.array([a.path_m for a in arcs], dtype=float)
    middle = arcs[n // 2]
    axis = np.asarray(middle.axis, dtype=float)
    if not (
        np.all(np.isfinite(transmitters))
        and np.all(np.isfinite(receivers))
        and np.all(np.isfinite(paths))
        and np.all(np.isfinite(axis))
        and np.linalg.norm(axis) > 0
        and math.isfinite(half_angle_rad)
        and half_angle_rad > 0
    ):
        return None
    # A sensor that did not move leaves every ellipsoid the same: nothing to intersect.
    if np.ptp(transmitters, axis=0).max() + np.ptp(receivers, axis=0).max() < 1e-4:
        return None
    baseline = float(np.linalg.norm(middle.receiver_m - middle.transmitter_m))
    if not middle.path_m > baseline:
        return None
    sigma = path_sigma_m

    def paths_at(points: FloatArray, t: FloatArray, r: FloatArray) -> FloatArray:
        return np.asarray(
            np.linalg.norm(points[..., None, :] - t, axis=-1)
            + np.linalg.norm(points[..., None, :] - r, axis=-1),
            dtype=float,
        )

    def full(coordinates: FloatArray) -> FloatArray:
        point = np.empty(3)
        point[free] = coordinates
        for a, value in fixed.items():
            point[a] = value
        return point

    candidates = on_ellipsoid_m(
        middle.transmitter_m,
        middle.receiver_m,
        middle.path_m,
        _direction_grid(axis / np.linalg.norm(axis), half_angle_rad, 25),
    )
    for a, value in fixed.items():
        candidates[:, a] = value
    scored = np.unique(np.linspace(0, n - 1, min(n, _START_ARCS)).round().astype(int))
    cost = np.sum(
        (paths_at(candidates, transmitters[scored], receivers[scored]) - paths[scored]) ** 2, axis=1
    )
    start = candidates[int(np.argmin(cost))][free]

    def residuals(coordinates: FloatArray) -> FloatArray:
        return np.asarray((paths_at(full(coordinates), transmitters, receivers) - paths) / sigma, dtype=float)

    solution = least_squares(residuals, start, method="lm", x_scale="jac")
    if not np.all(np.isfinite(solution.x)):
        return None
    degrees = n - len(free)
    reduced = float(np.sum(solution.fun**2)) / degrees
    if not reduced <= options.max_reduced_chi2:
        return None
    information = solution.jac.T @ solution.jac
    eigenvalues = np.linalg.eigvalsh(information)
    if not eigenvalues.min() > 1e-12 * max(eigenvalues.max(), 1e-300):
        return None
    # scipy's curve_fit without absolute_sigma: the residuals' own scale.
    block = reduced * np.linalg.inv(information)
    if not np.sqrt(np.linalg.eigvalsh(block).max()) <= options.max_std_m:
        return None
    covariance = np.zeros((3, 3))
    covariance[np.ix_(free, free)] = block
    return TriangulatedPoint(
        position_m=full(solution.x),
        covariance_m2=covariance,
        reduced_chi2=reduced,
        n_arcs=n,
        first_frame=arcs[0].frame,
        last_frame=arcs[-1].frame,
        channel=channel,
    )


@dataclass
class _Track:
    arcs: list[Arc] = field(default_factory=list)
    missed: int = 0

    def predicted_m(self, frame: int) -> float:
        """The path a straight line through the last few arcs' paths (against the frame) predicts."""
        recent = self.arcs[-_RATE_ARCS:]
        if len(recent) < 2:
            return recent[-1].path_m
        frames = np.array([a.frame for a in recent], dtype=float)
        paths = np.array([a.path_m for a in recent])
        spread = frames - frames.mean()
        if not np.any(spread):  # every arc from one frame number: no rate to be had
            return recent[-1].path_m
        slope = float(spread @ (paths - paths.mean()) / (spread @ spread))
        return float(paths.mean() + slope * (frame - frames.mean()))


class ArcTracker:
    """Unplaced echoes followed from frame to frame, per channel; tracks that end are fitted
    (module doc). The one mutable thing of this module."""

    def __init__(
        self,
        options: TrackOptions,
        *,
        half_angle_rad: float,
        path_sigma_m: float,
        fixed: Mapping[int, float] | None = None,
    ) -> None:
        self.options = options
        self.half_angle_rad = _positive("half_angle_rad", half_angle_rad)
        self.path_sigma_m = _positive("path_sigma_m", path_sigma_m)
        self.fixed = dict(fixed or {})
        self._tracks: dict[tuple[int, int], list[_Track]] = {}
        self._last_fired: dict[tuple[int, int], int] = {}
        self._period: dict[tuple[int, int], int] = {}

    def add(
        self, frame: int, arcs_by_channel: Mapping[tuple[int, int], Sequence[Arc]]
    ) -> list[TriangulatedPoint]:
        """Add one frame: every channel (transmitter, receiver) that fired in it, with its
        unplaced arcs (possibly none). Returns the points of the tracks that ended."""
        placed: list[TriangulatedPoint] = []
        for channel in sorted(arcs_by_channel):
            placed += self._add_channel(frame, channel, arcs_by_channel[channel])
        return placed

    def _add_channel(
        self, frame: int, channel: tuple[int, int], new: Sequence[Arc]
    ) -> list[TriangulatedPoint]:
        options = self.options
        skipped = self._skipped_firings(frame, channel)
        tracks = self._tracks.get(channel, [])
        placed: list[TriangulatedPoint] = []
        open_tracks: list[_Track] = []
        for track in tracks:
            track.missed += skipped
            if track.missed > options.max_gap_frames:
                placed += self._fitted(track, channel)
            else:
                open_tracks.append(track)
        arcs = sorted(new, key=lambda a: a.path_m)
        pairs = []
        noise = _NOISE_GATE_SIGMAS * self.path_sigma_m
        for t, track in enumerate(open_tracks):
            since = frame - track.arcs[-1].frame
            predicted = track.predicted_m(frame)
            for a, arc in enumerate(arcs):
                miss = abs(arc.path_m - predicted)
                if miss <= options.gate_m * since + noise:
                    pairs.append((miss, t, a))
        pairs.sort()
        joined: set[int] = set()
        taken: set[int] = set()
        for _, t, a in pairs:
            if t in joined or a in taken:
                continue
            joined.add(t)
            taken.add(a)
            open_tracks[t].arcs.append(arcs[a])
            open_tracks[t].missed = 0
        kept: list[_Track] = []
        for t, track in enumerate(open_tracks):
            if t not in joined:
                track.missed += 1
            if track.missed > options.max_gap_frames:
                placed += self._fitted(track, channel)
            elif len(track.arcs) >= options.max_arcs:
                placed += self._fitted(track, channel)
                kept.append(_Track(track.arcs[-2:]))
            else:
                kept.append(track)
        kept += [_Track([arc]) for a, arc in enumerate(arcs) if a not in taken]
        self._tracks[channel] = kept
        return placed

    def _skipped_firings(self, frame: int, channel: tuple[int, int]) -> int:
        """Firings of ``channel`` the input skipped since its last one (frames missing from a
        stream or a range): the frames since, over the channel's period, less one."""
        last = self._last_fired.get(channel)
        self._last_fired[channel] = frame
        if last is None or frame <= last:
            return 0
        elapsed = frame - last
        period = self._period.setdefault(channel, elapsed)
        skipped = max(0, round(elapsed / period) - 1)
        if not skipped:
            self._period[channel] = elapsed
        return skipped

    def _fitted(self, track: _Track, channel: tuple[int, int]) -> list[TriangulatedPoint]:
        point = fit_track(
            track.arcs,
            self.options,
            half_angle_rad=self.half_angle_rad,
            path_sigma_m=self.path_sigma_m,
            fixed=self.fixed,
            channel=channel,
        )
        return [] if point is None else [point]

    def finish(self) -> list[TriangulatedPoint]:
        """Fit every open track and close it."""
        placed = []
        for channel in sorted(self._tracks):
            for track in self._tracks[channel]:
                placed += self._fitted(track, channel)
        self._tracks = {}
        return placed
