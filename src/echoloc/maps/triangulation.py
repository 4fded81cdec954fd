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

**Tracks.** Per transmitter-receiver channel, an unplaced echo joins the open track
whose predicted path (the last path plus the last rate times the frames since) is
nearest, if within ``gate_m`` per frame since; else it opens a track. A track that got no
echo for more than ``max_gap_frames`` frames ends.

**Fit.** A track of ``n`` arcs ``(T_k, R_k, L_k)`` (world frame) is fitted by the point
``p`` that minimises ``sum_k ((|p - T_k| + |p - R_k| - L_k) / sigma)^2`` (``sigma`` the
map's path uncertainty) plus a weak prior
that ``p`` lies within the beam (a Gaussian across the middle arc's transmitter axis,
``sigma = range * tan(beam half-angle)``): when every arc's foci lie in one plane the data
cannot tell the point from its mirror image in that plane, and the beam's gain says the
axis side is the likelier one. The start is the best of a grid of directions inside the
beam, each placed on the middle arc's ellipsoid; Levenberg-Marquardt (scipy) refines it.
The covariance is ``(J^T J)^-1`` of the whitened residuals, prior included.

**Acceptance.** A track becomes a point when it has ``min_arcs`` arcs or more, its
reduced chi-square is at most ``max_reduced_chi2`` (a specular wall's arcs touch the
wall at points that slide along it, so they fit no single point once the sensor has
moved far enough), and the data alone (prior left out) fix the point to within
``max_std_m`` in at least two directions. Which directions must be fixed is the map's
business (a floor plan needs the horizontal two): :class:`TriangulatedPoint` keeps the
covariance.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from echoloc.errors import EchoLocError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True)
class TrackOptions:
    """How unplaced echoes are tracked across frames and when a track becomes a point.

    gate_m
        Largest change of an echo's path from its track's prediction, per frame since
        the track's last echo, m.
    max_gap_frames
        A track with no echo for more frames than this ends.
    min_arcs
        Fewest arcs (frames) a track needs to be fitted.
    max_reduced_chi2
        Largest chi-square per degree of freedom of an accepted point.
    max_std_m
        Largest standard deviation, m, of the two best-fixed directions of the point,
        from the data alone.
    max_arcs
        A track this long is fitted and restarted (bounds the memory and the fit's cost).
    """

    gate_m: float = 0.006
    max_gap_frames: int = 3
    min_arcs: int = 12
    max_reduced_chi2: float = 4.0
    max_std_m: float = 0.05
    max_arcs: int = 400

    def __post_init__(self) -> None:
        if not (math.isfinite(self.gate_m) and self.gate_m > 0):
            raise EchoLocError(f"gate_m must be > 0, got {self.gate_m}")
        if self.max_gap_frames < 0:
            raise EchoLocError(f"max_gap_frames must be >= 0, got {self.max_gap_frames}")
        if not 4 <= self.min_arcs <= self.max_arcs:
            raise EchoLocError(
                f"min_arcs must be at least 4 and at most max_arcs, got {self.min_arcs} and {self.max_arcs}"
            )
        if not (math.isfinite(self.max_reduced_chi2) and self.max_reduced_chi2 > 0):
            raise EchoLocError(f"max_reduced_chi2 must be > 0, got {self.max_reduced_chi2}")
        if not (math.isfinite(self.max_std_m) and self.max_std_m > 0):
            raise EchoLocError(f"max_std_m must be > 0, got {self.max_std_m}")


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
    """A reflector placed by a track of arcs: world position and covariance (prior included),
    the data's information matrix ``J^T J`` (prior left out, 1/m^2) and its standard
    deviations along its principal directions (best fixed first), the fit's reduced
    chi-square and the frames and channel it came from."""

    def covariance_given_m2(self, axes: Sequence[int]) -> FloatArray | None:
        """The covariance of the coordinates ``axes`` from the data alone, the others held
        where the fit put them (the inverse of the information's block); None when the data
        leave a combination of them free."""
        block = self.information_per_m2[np.ix_(axes, axes)]
        eigenvalues = np.linalg.eigvalsh(block)
        if eigenvalues.min() <= 1e-12 * max(eigenvalues.max(), 1e-300):
            return None
        return np.asarray(np.linalg.inv(block), dtype=float)

    position_m: FloatArray
    covariance_m2: FloatArray
    information_per_m2: FloatArray
    data_std_m: FloatArray
    reduced_chi2: float
    n_arcs: int
    first_frame: int
    last_frame: int
    channel: tuple[int, int]


def _direction_grid(axis: FloatArray, half_angle_rad: float, steps: int) -> FloatArray:
    """Unit vectors filling the cone of ``half_angle_rad`` about ``axis``: a square grid of
    tangent-plane offsets, those inside the cone kept (axis first)."""
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
    ``rho = (L^2 - |d|^2) / (2 (L - u . d))`` with ``d = R - T`` (squaring ``|rho u - d| = L - rho``)."""
    d = receiver_m - transmitter_m
    rho = (path_m**2 - d @ d) / (2.0 * (path_m - directions @ d))
    return np.asarray(transmitter_m + rho[:, None] * directions, dtype=float)


def fit_track(
    arcs: Sequence[Arc],
    options: TrackOptions,
    *,
    half_angle_rad: float,
    path_sigma_m: float,
    channel: tuple[int, int] = (0, 0),
) -> TriangulatedPoint | None:
    """The point on all of ``arcs``' ellipsoids (module doc), or None when the track is too
    short, fits no point or does not fix one. ``half_angle_rad``: the beam's half-angle (the
    prior and the start's search); ``path_sigma_m``: an echo path's standard deviation, m."""
    n = len(arcs)
    if n < options.min_arcs:
        return None
    transmitters = np.array([a.transmitter_m for a in arcs])
    receivers = np.array([a.receiver_m for a in arcs])
    paths = np.array([a.path_m for a in arcs])
    sigma = path_sigma_m
    middle = arcs[n // 2]
    directions = _direction_grid(middle.axis, half_angle_rad, 25)
    candidates = on_ellipsoid_m(middle.transmitter_m, middle.receiver_m, middle.path_m, directions)

    def model(points: FloatArray) -> FloatArray:
        return np.asarray(
            np.linalg.norm(points[..., None, :] - transmitters, axis=-1)
            + np.linalg.norm(points[..., None, :] - receivers, axis=-1),
            dtype=float,
        )

    cost = np.sum((model(candidates) - paths) ** 2, axis=1)
    start = candidates[int(np.argmin(cost))]
    centre, axis = middle.transmitter_m, middle.axis
    prior_sigma = max(float(np.linalg.norm(start - centre)) * math.tan(half_angle_rad), 1e-3)

    def residuals(p: FloatArray) -> FloatArray:
        offset = p - centre
        across = offset - (offset @ axis) * axis
        return np.concatenate([(model(p) - paths) / sigma, across / prior_sigma])

    solution = least_squares(residuals, start, method="lm", x_scale="jac")
    p = solution.x
    jacobian = solution.jac
    data_chi2 = float(np.sum(solution.fun[:n] ** 2))
    reduced = data_chi2 / max(n - 3, 1)
    if not (np.all(np.isfinite(p)) and reduced <= options.max_reduced_chi2):
        return None
    information = jacobian[:n].T @ jacobian[:n]
    eigenvalues = np.linalg.eigvalsh(information)[::-1]
    data_std = 1.0 / np.sqrt(np.maximum(eigenvalues, 1e-300))
    if data_std[1] > options.max_std_m:
        return None
    covariance = np.linalg.inv(jacobian.T @ jacobian)
    return TriangulatedPoint(
        position_m=p,
        covariance_m2=covariance,
        information_per_m2=information,
        data_std_m=data_std,
        reduced_chi2=reduced,
        n_arcs=n,
        first_frame=arcs[0].frame,
        last_frame=arcs[-1].frame,
        channel=channel,
    )


@dataclass
class _Track:
    arcs: list[Arc] = field(default_factory=list)

    def predicted_m(self, frame: int) -> float:
        last = self.arcs[-1]
        if len(self.arcs) < 2:
            return last.path_m
        before = self.arcs[-2]
        rate = (last.path_m - before.path_m) / max(last.frame - before.frame, 1)
        return last.path_m + rate * (frame - last.frame)


class ArcTracker:
    """Unplaced echoes followed from frame to frame, per channel; tracks that end are fitted
    (module doc). The one mutable thing of this module."""

    def __init__(self, options: TrackOptions, *, half_angle_rad: float, path_sigma_m: float) -> None:
        self.options = options
        self.half_angle_rad = half_angle_rad
        self.path_sigma_m = path_sigma_m
        self._tracks: dict[tuple[int, int], list[_Track]] = {}

    def add(self, frame: int, arcs_by_channel: dict[tuple[int, int], list[Arc]]) -> list[TriangulatedPoint]:
        """Add one frame's unplaced arcs (keyed by (transmitter, receiver)); the points of the
        tracks that ended."""
        options = self.options
        placed: list[TriangulatedPoint] = []
        for channel in sorted(set(self._tracks) | set(arcs_by_channel)):
            tracks = self._tracks.setdefault(channel, [])
            arcs = sorted(arcs_by_channel.get(channel, []), key=lambda a: a.path_m)
            taken: set[int] = set()
            pairs = []
            for t, track in enumerate(tracks):
                gap = frame - track.arcs[-1].frame
                predicted = track.predicted_m(frame)
                for a, arc in enumerate(arcs):
                    miss = abs(arc.path_m - predicted)
                    if miss <= options.gate_m * gap:
                        pairs.append((miss, t, a))
            pairs.sort()
            used_tracks: set[int] = set()
            for _, t, a in pairs:
                if t in used_tracks or a in taken:
                    continue
                used_tracks.add(t)
                taken.add(a)
                tracks[t].arcs.append(arcs[a])
            kept: list[_Track] = []
            for track in tracks:
                ended = frame - track.arcs[-1].frame > options.max_gap_frames
                full = len(track.arcs) >= options.max_arcs
                if ended or full:
                    point = self._fit(track, channel)
                    if point is not None:
                        placed.append(point)
                    if full and not ended:
                        kept.append(_Track([track.arcs[-1]]))
                else:
                    kept.append(track)
            kept += [_Track([arc]) for a, arc in enumerate(arcs) if a not in taken]
            self._tracks[channel] = kept
        return placed

    def _fit(self, track: _Track, channel: tuple[int, int]) -> TriangulatedPoint | None:
        return fit_track(
            track.arcs,
            self.options,
            half_angle_rad=self.half_angle_rad,
            path_sigma_m=self.path_sigma_m,
            channel=channel,
        )

    def finish(self) -> list[TriangulatedPoint]:
        """Fit every open track and close it."""
        placed = []
        for channel, tracks in self._tracks.items():
            for track in tracks:
                point = self._fit(track, channel)
                if point is not None:
                    placed.append(point)
        self._tracks = {}
        return placed
