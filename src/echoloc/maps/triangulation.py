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
in which its transmitter fired (counted from the recording's schedule, so firings the
input skipped count as missed). An unplaced echo joins the open track whose predicted
path is nearest (a straight line through the track's last five paths against the frame
number), if the miss is within ``gate_m`` per frame since the track's last echo plus four
path sigmas. A track that missed more than ``max_gap_frames`` of its channel's firings
ends; a firing seen again adds nothing, and an input that goes back ends every track.

**Fit.** A track of ``n`` arcs ``(T_k, R_k, L_k)`` (world frame) is fitted by the point
``p`` that minimises ``sum_k ((|p - T_k| + |p - R_k| - L_k) / sigma)^2`` (``sigma`` the
path's standard deviation), over the coordinates the caller leaves free: a floor plan is
a slice at one height, so there the height is held at the slice's and the question is
where the ellipsoids meet in it. The start is the best of a grid of directions inside
the beam, each placed on the middle arc's ellipsoid by ``rho = (L^2 - |d|^2) / (2 (L -
u . d))``; Levenberg-Marquardt (scipy) refines it. The covariance is ``s^2 (J^T J)^-1``
with ``s^2`` the reduced chi-square, as scipy's ``curve_fit`` gives it when the noise
level is not known absolutely: the scatter of the track's own paths sets it.

**Acceptance.** A track becomes a point when

- it has ``min_arcs`` arcs or more and at least 10 degrees of freedom (its residuals set
  the covariance's scale);
- its reduced chi-square against ``sigma`` is at most ``max_reduced_chi2`` (a specular
  wall's arcs touch the wall at points that slide along it, so they fit no single point
  once the sensor has moved far enough);
- every free coordinate is fixed within ``max_std_m`` (a sensor that moved too little
  fixes only the range; one whose foci stayed on a line leaves a circle of points in
  space);
- the point lies in the beam, and no second minimum elsewhere in the beam fits within a
  chi-square of 9: foci that keep a symmetry (a line, a plane) fit the reflector's
  mirror image as well as the reflector, and refits from the best starts away from the
  first solution find it;
- in a slice, refitted in space from the slice's point, it does not lie off the slice by
  more than ``fixed_within_m`` plus two standard deviations where the motion fixes the
  height (a reflector above the slice would be placed in it at its slant range).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
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
_DEFAULT_STD_M = 0.02
"""A point's largest standard deviation when nothing sets it: the map's default cell."""
_MIN_DEGREES = 10
"""Fewest degrees of freedom a fit needs: its residuals set the covariance's scale, and
with fewer their chi-square is too loose an estimate of it (sqrt(2/10) = 45 %)."""
_OTHER_STARTS = 4
"""Starts, away from the first solution, refitted to look for a second minimum."""
_RIVAL_CHI2 = 9.0
"""A second minimum within this chi-square of the best (three sigmas) makes the track ambiguous."""


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
        Largest standard deviation, m, of an accepted point along any free direction;
        None: the cell of the map it marks (:class:`echoloc.maps.mapping.MapAccumulator`),
        or 2 cm used alone.
    max_arcs
        A track this long is fitted and restarted from its last two arcs (bounds the
        memory and the fit's cost).
    """

    gate_m: float = 0.006
    max_gap_frames: int = 3
    min_arcs: int = 12
    max_reduced_chi2: float = 4.0
    max_std_m: float | None = None
    max_arcs: int = 400

    def __post_init__(self) -> None:
        _positive("gate_m", self.gate_m)
        _whole("max_gap_frames", self.max_gap_frames, 0)
        _whole("min_arcs", self.min_arcs, 4)
        _whole("max_arcs", self.max_arcs, 4)
        if self.min_arcs > self.max_arcs:
            raise EchoLocError(f"min_arcs ({self.min_arcs}) must be at most max_arcs ({self.max_arcs})")
        _positive("max_reduced_chi2", self.max_reduced_chi2)
        if self.max_std_m is not None:
            _positive("max_std_m", self.max_std_m)

    @property
    def std_limit_m(self) -> float:
        """``max_std_m``, or 2 cm (the map's default cell) when it is None."""
        return _DEFAULT_STD_M if self.max_std_m is None else float(self.max_std_m)


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


def _checked_fixed(fixed: Mapping[int, float] | None) -> dict[int, float]:
    held = dict(fixed or {})
    for axis, value in held.items():
        if axis not in (0, 1, 2) or not math.isfinite(value):
            raise EchoLocError(f"fixed: coordinates are 0, 1 or 2 and finite values, got {held!r}")
    return held


def fit_track(
    arcs: Sequence[Arc],
    options: TrackOptions,
    *,
    half_angle_rad: float,
    path_sigma_m: float,
    fixed: Mapping[int, float] | None = None,
    fixed_within_m: float = 0.0,
    channel: tuple[int, int] = (0, 0),
) -> TriangulatedPoint | None:
    """The point on all of ``arcs``' ellipsoids (module doc), or None when the track is too
    short, fits no point, does not fix one, fits two, or holds values no fit can use.

    ``half_angle_rad``: the beam's half-angle (where the point may lie); ``path_sigma_m``:
    an echo path's standard deviation, m; ``fixed``: coordinates (0 x, 1 y, 2 z) held at
    the given values, m (a floor plan's height), and ``fixed_within_m`` how far from them
    the reflector may lie (half a cell).
    """
    sigma = _positive("path_sigma_m", path_sigma_m)
    held = _checked_fixed(fixed)
    free = [a for a in range(3) if a not in held]
    n = len(arcs)
    if n < options.min_arcs or not free or n - len(free) < _MIN_DEGREES:
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
    axis = axis / np.linalg.norm(axis)
    # A sensor that did not move leaves every ellipsoid the same: nothing to intersect.
    if np.ptp(transmitters, axis=0).max() + np.ptp(receivers, axis=0).max() < 1e-4:
        return None
    baseline = float(np.linalg.norm(middle.receiver_m - middle.transmitter_m))
    if not middle.path_m > baseline:
        return None
    cos_beam = math.cos(min(half_angle_rad, math.radians(80.0)))

    def in_beam(point: FloatArray) -> bool:
        offset = point - middle.transmitter_m
        distance = float(np.linalg.norm(offset))
        return distance > 0 and float(offset @ axis) >= cos_beam * distance

    def solve(
        coordinates: Sequence[int], start: FloatArray, base: FloatArray
    ) -> tuple[FloatArray, float, FloatArray]:
        """Levenberg-Marquardt over ``coordinates`` from ``start``, the others as in ``base``:
        the point, its chi-square and the information matrix J^T J."""

        def residuals(values: FloatArray) -> FloatArray:
            point = base.copy()
            point[list(coordinates)] = values
            return np.asarray((_paths_m(point, transmitters, receivers) - paths) / sigma, dtype=float)

        with np.errstate(all="ignore"):
            solution = least_squares(residuals, start, method="lm", x_scale="jac")
        point = base.copy()
        point[list(coordinates)] = solution.x
        return point, float(np.sum(solution.fun**2)), solution.jac.T @ solution.jac

    base = np.zeros(3)
    for a, value in held.items():
        base[a] = value
    candidates = on_ellipsoid_m(
        middle.transmitter_m, middle.receiver_m, middle.path_m, _direction_grid(axis, half_angle_rad, 25)
    )
    for a, value in held.items():
        candidates[:, a] = value
    scored = np.unique(np.linspace(0, n - 1, min(n, _START_ARCS)).round().astype(int))
    cost = np.sum(
        (_paths_m(candidates, transmitters[scored], receivers[scored]) - paths[scored]) ** 2, axis=1
    )
    order = np.argsort(cost)
    degrees = n - len(free)

    def accepted(found: tuple[FloatArray, float, FloatArray]) -> FloatArray | None:
        """The covariance of the fitted coordinates if the solution passes the chi-square, the
        uncertainty and the beam; else None."""
        point, chi2, information = found
        if not (np.all(np.isfinite(point)) and chi2 / degrees <= options.max_reduced_chi2 and in_beam(point)):
            return None
        block = _scaled_covariance(chi2, degrees, information)
        if block is None or not np.sqrt(np.linalg.eigvalsh(block).max()) <= options.std_limit_m:
            return None
        return block

    best = solve(free, candidates[order[0]][free], base)
    block = accepted(best)
    if block is None:
        return None
    point, chi2, _ = best
    # Other minima: a channel whose foci keep a symmetry (a line, a plane) fits the mirror
    # image of the reflector as well as the reflector. Refit from the best starts elsewhere.
    apart = 2.0 * options.std_limit_m
    starts = [c for c in candidates[order[1:]] if np.linalg.norm(c - point) > apart][:_OTHER_STARTS]
    for start in starts:
        other, other_chi2, _ = solve(free, start[free], base)
        if (
            np.all(np.isfinite(other))
            and other_chi2 <= chi2 + _RIVAL_CHI2
            and in_beam(other)
            and np.linalg.norm(other - point) > apart
        ):
            return None
    if held and _off_the_slice(solve, point, held, degrees, options, fixed_within_m):
        return None
    reduced = chi2 / degrees
    covariance = np.zeros((3, 3))
    covariance[np.ix_(free, free)] = block
    return TriangulatedPoint(
        position_m=point,
        covariance_m2=covariance,
        reduced_chi2=reduced,
        n_arcs=n,
        first_frame=arcs[0].frame,
        last_frame=arcs[-1].frame,
        channel=channel,
    )


def _paths_m(points: FloatArray, transmitters: FloatArray, receivers: FloatArray) -> FloatArray:
    """``|p - T_k| + |p - R_k|`` for every point (leading axes) and arc (last axis)."""
    return np.asarray(
        np.linalg.norm(points[..., None, :] - transmitters, axis=-1)
        + np.linalg.norm(points[..., None, :] - receivers, axis=-1),
        dtype=float,
    )


def _scaled_covariance(chi2: float, degrees: int, information: FloatArray) -> FloatArray | None:
    """``s^2 (J^T J)^-1`` with ``s^2 = chi2 / degrees`` (scipy's ``curve_fit`` without
    ``absolute_sigma``: the residuals' own scale); None when ``J^T J`` is singular (the data
    leave a direction free)."""
    eigenvalues = np.linalg.eigvalsh(information)
    if not eigenvalues.min() > 1e-12 * max(eigenvalues.max(), 1e-300):
        return None
    return np.asarray(chi2 / max(degrees, 1) * np.linalg.inv(information), dtype=float)


def _off_the_slice(
    solve: Callable[[Sequence[int], FloatArray, FloatArray], tuple[FloatArray, float, FloatArray]],
    point: FloatArray,
    held: dict[int, float],
    degrees: int,
    options: TrackOptions,
    within_m: float,
) -> bool:
    """Whether the motion fixes the held coordinates too, and puts the reflector away from
    them: refitted in space from the slice's point, it lies more than ``within_m`` plus two
    standard deviations off (a reflector above or below a floor plan's slice, which the
    slice's fit would place at its slant range)."""
    free_point, chi2, information = solve([0, 1, 2], point, point)
    covariance = _scaled_covariance(chi2, degrees - len(held), information)
    if covariance is None or not np.all(np.isfinite(free_point)):
        return False
    for a, value in held.items():
        std = math.sqrt(max(covariance[a, a], 0.0))
        if std <= options.std_limit_m and abs(free_point[a] - value) > within_m + 2.0 * std:
            return True
    return False


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
        fixed_within_m: float = 0.0,
    ) -> None:
        self.options = options
        self.half_angle_rad = _positive("half_angle_rad", half_angle_rad)
        self.path_sigma_m = _positive("path_sigma_m", path_sigma_m)
        self.fixed = _checked_fixed(fixed)
        if not (math.isfinite(fixed_within_m) and fixed_within_m >= 0):
            raise EchoLocError(f"fixed_within_m must be a finite number >= 0, got {fixed_within_m!r}")
        self.fixed_within_m = float(fixed_within_m)
        self._tracks: dict[tuple[int, int], list[_Track]] = {}
        self._last_firing: dict[tuple[int, int], int] = {}

    def add(
        self,
        frame: int,
        arcs_by_channel: Mapping[tuple[int, int], Sequence[Arc]],
        *,
        firing: int | None = None,
    ) -> list[TriangulatedPoint]:
        """Add one frame: every channel (transmitter, receiver) that fired in it, with its
        unplaced arcs (possibly none), and the count of earlier firings of those channels
        (``firing``; default the frame number, for a transmitter that fires every frame).
        Returns the points of the tracks that ended."""
        placed: list[TriangulatedPoint] = []
        for channel in sorted(arcs_by_channel):
            placed += self._add_channel(
                frame, channel, arcs_by_channel[channel], frame if firing is None else firing
            )
        return placed

    def _add_channel(
        self, frame: int, channel: tuple[int, int], new: Sequence[Arc], firing: int
    ) -> list[TriangulatedPoint]:
        options = self.options
        placed: list[TriangulatedPoint] = []
        last = self._last_firing.get(channel)
        if last is not None and firing == last:
            return placed  # the same firing again: its echoes are in the tracks already
        if last is not None and firing < last:  # the input went back: what came before ends
            placed += self._close(channel)
            last = None
        self._last_firing[channel] = firing
        skipped = 0 if last is None else firing - last - 1
        open_tracks: list[_Track] = []
        for track in self._tracks.get(channel, []):
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

    def _fitted(self, track: _Track, channel: tuple[int, int]) -> list[TriangulatedPoint]:
        point = fit_track(
            track.arcs,
            self.options,
            half_angle_rad=self.half_angle_rad,
            path_sigma_m=self.path_sigma_m,
            fixed=self.fixed,
            fixed_within_m=self.fixed_within_m,
            channel=channel,
        )
        return [] if point is None else [point]

    def _close(self, channel: tuple[int, int]) -> list[TriangulatedPoint]:
        placed = []
        for track in self._tracks.pop(channel, []):
            placed += self._fitted(track, channel)
        return placed

    def finish(self) -> list[TriangulatedPoint]:
        """Fit every open track and close it."""
        placed = []
        for channel in sorted(self._tracks):
            placed += self._close(channel)
        self._last_firing = {}
        return placed
