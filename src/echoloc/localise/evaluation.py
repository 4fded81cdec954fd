"""Scoring located objects against known reflector positions (``truth_positions``).

Located objects are matched one-to-one to true reflectors by the assignment that
minimises the total distance (Hungarian method, ``scipy.optimize.linear_sum_assignment``),
and a pair counts only when closer than ``match_radius_m``.

- recall: matched true reflectors / all true reflectors;
- false objects: unmatched located objects / all located objects;
- RMSE per axis over the matched pairs, beside the mean reported ``std_m``, so
  that the reported uncertainty can be checked against the real spread.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import linear_sum_assignment

from echoloc.errors import EchoLocError
from echoloc.localise.locate import FrameObjects


def match(
    estimated_m: NDArray[np.float64], truth_m: NDArray[np.float64], match_radius_m: float
) -> list[tuple[int, int]]:
    """Pairs (estimated index, truth index) of the minimum-distance one-to-one matching within the radius."""
    if len(estimated_m) == 0 or len(truth_m) == 0:
        return []
    distance = np.linalg.norm(estimated_m[:, None, :] - truth_m[None, :, :], axis=2)
    # Pairs beyond the radius are made too costly to be worth taking.
    cost = np.where(distance <= match_radius_m, distance, 1e6)
    rows, cols = linear_sum_assignment(cost)
    return [(int(r), int(c)) for r, c in zip(rows, cols, strict=True) if distance[r, c] <= match_radius_m]


@dataclass(frozen=True, eq=False)
class Evaluation:
    """Detection and accuracy figures over a recording."""

    n_frames: int
    n_truth: int
    n_located: int
    n_matched: int
    errors_m: NDArray[np.float64]  # (n_matched, 3): estimate - truth
    reported_std_m: NDArray[np.float64]  # (n_matched, 3)
    match_radius_m: float

    @property
    def recall(self) -> float:
        return self.n_matched / self.n_truth if self.n_truth else float("nan")

    @property
    def n_false(self) -> int:
        return self.n_located - self.n_matched

    @property
    def false_rate(self) -> float:
        return self.n_false / self.n_located if self.n_located else 0.0

    @property
    def rmse_m(self) -> NDArray[np.float64]:
        if len(self.errors_m) == 0:
            return np.full(3, np.nan)
        return np.asarray(np.sqrt(np.mean(self.errors_m**2, axis=0)))

    @property
    def bias_m(self) -> NDArray[np.float64]:
        if len(self.errors_m) == 0:
            return np.full(3, np.nan)
        return np.asarray(np.mean(self.errors_m, axis=0))

    @property
    def mean_std_m(self) -> NDArray[np.float64]:
        if len(self.reported_std_m) == 0:
            return np.full(3, np.nan)
        return np.asarray(np.sqrt(np.mean(self.reported_std_m**2, axis=0)))


def evaluate(
    results: Iterable[FrameObjects], truth_positions_m: NDArray[np.float64], match_radius_m: float = 0.02
) -> Evaluation:
    """Compare located objects per frame with ``truth_positions_m`` (n_frames, n_max, 3), NaN-padded."""
    n_frames = n_truth = n_located = 0
    errors, stds = [], []
    for frame in results:
        truth = truth_positions_m[frame.frame]
        truth = truth[np.all(np.isfinite(truth), axis=1)]
        estimated = np.array([o.position_m for o in frame.objects]).reshape(-1, 3)
        pairs = match(estimated, truth, match_radius_m)
        n_frames += 1
        n_truth += len(truth)
        n_located += len(estimated)
        for e, t in pairs:
            errors.append(estimated[e] - truth[t])
            stds.append(frame.objects[e].std_m)
    return Evaluation(
        n_frames=n_frames,
        n_truth=n_truth,
        n_located=n_located,
        n_matched=len(errors),
        errors_m=np.array(errors).reshape(-1, 3),
        reported_std_m=np.array(stds).reshape(-1, 3),
        match_radius_m=match_radius_m,
    )


def target_positions(truth_positions_m: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """The distinct target set-ups of a recording, ordered by their first position's z, y and
    x, and each frame's set-up (-1: no known target). Frames whose known positions agree to 0.1 mm share
    a set-up (a rig that holds a target still for several frames)."""
    n_frames = len(truth_positions_m)
    keys: dict[bytes, int] = {}
    positions: list[NDArray[np.float64]] = []
    which = np.full(n_frames, -1, dtype=np.int64)
    for index in range(n_frames):
        points = truth_positions_m[index]
        points = points[np.all(np.isfinite(points), axis=1)]
        if len(points) == 0:
            continue
        key = np.round(points / 1e-4).astype(np.int64).tobytes()
        if key not in keys:
            keys[key] = len(positions)
            positions.append(points)
        which[index] = keys[key]
    first = np.array([p[0] for p in positions]).reshape(-1, 3)
    # Numbered along the boresight first (z, then y, then x): every other set-up then
    # samples every depth of a grid, so a calibration on half of them sees the whole range.
    order = np.lexsort((first[:, 0], first[:, 1], first[:, 2])) if len(first) else np.zeros(0, dtype=np.int64)
    rank = np.empty(len(order), dtype=np.int64)
    rank[order] = np.arange(len(order))
    which = np.where(which >= 0, rank[np.maximum(which, 0)], -1)
    return first[order], which


def frames_at_positions(
    truth_positions_m: NDArray[np.float64], spec: str, frames: Sequence[int]
) -> list[int]:
    """The frames among ``frames`` whose target set-up (:func:`target_positions`) is picked by
    ``spec``, a Python slice over the set-ups: ``0::2`` every other from the first, ``1::2``
    the rest, ``:10`` the first ten. For calibrating on some positions and testing on others."""
    parts = spec.split(":")
    try:
        if len(parts) > 3:
            raise ValueError
        numbers = [int(p) if p.strip() else None for p in parts]
    except ValueError:
        raise EchoLocError(f"--positions must be a slice START:STOP:STEP, got {spec!r}") from None
    if len(numbers) == 1:
        index = numbers[0]
        numbers = [index, None if index is None or index == -1 else index + 1, None]
    if len(numbers) == 3 and numbers[2] == 0:
        raise EchoLocError(f"--positions: the step of {spec!r} must not be 0")
    _, which = target_positions(truth_positions_m)
    n_positions = int(which.max()) + 1 if len(which) else 0
    chosen = set(range(n_positions)[slice(*numbers)])
    picked = [int(f) for f in frames if int(which[f]) in chosen]
    if not picked:
        raise EchoLocError(f"--positions {spec} picks no frame ({n_positions} target positions known)")
    return picked


@dataclass(frozen=True, eq=False)
class ClassEvaluation:
    """Reflector classes against the truth's (:func:`evaluate_classes`).

    ``confusion[i, j]`` counts true reflectors of class ``kinds[i]`` located (within the
    match radius) and reported as ``kinds[j]``; its last column counts those not located.
    ``normal_errors_deg`` and ``distance_errors_m`` hold, for each true plane located and
    reported as a plane, the angle between the reported and true normals and the difference
    of the distances from the frame's transmitter.
    """

    kinds: tuple[str, ...]
    confusion: NDArray[np.int64]
    n_located: int
    n_false: int
    normal_errors_deg: NDArray[np.float64]
    distance_errors_m: NDArray[np.float64]

    @property
    def n_truth(self) -> int:
        return int(self.confusion.sum())

    @property
    def right_class_rate(self) -> float:
        """True reflectors located with the right class / all true reflectors."""
        n = len(self.kinds)
        return float(np.trace(self.confusion[:, :n]) / self.n_truth) if self.n_truth else float("nan")

    @property
    def false_rate(self) -> float:
        return self.n_false / self.n_located if self.n_located else 0.0


def evaluate_classes(
    results: Iterable[FrameObjects],
    truth_positions_m: NDArray[np.float64],
    truth_kinds: Sequence[str],
    frame_transmitters_m: NDArray[np.float64],
    kinds: tuple[str, ...] = ("point", "plane", "corner"),
    match_radius_m: float = 0.02,
) -> ClassEvaluation:
    """Score located objects and their classes against truth rows of known class.

    ``truth_kinds`` gives the class of each truth row (the columns of
    ``truth_positions_m``, NaN rows skipped); ``frame_transmitters_m`` (n_frames, 3) the
    transmitter each frame fired, from which a true plane's foot gives its normal and
    distance. Objects without a class count as points. Matching is :func:`match`'s.
    """
    confusion = np.zeros((len(kinds), len(kinds) + 1), dtype=np.int64)
    n_located = n_matched = 0
    normal_errors: list[float] = []
    distance_errors: list[float] = []
    for frame in results:
        truth = truth_positions_m[frame.frame]
        rows = np.flatnonzero(np.all(np.isfinite(truth), axis=1))
        estimated = np.array([o.position_m for o in frame.objects]).reshape(-1, 3)
        pairs = match(estimated, truth[rows], match_radius_m)
        n_located += len(estimated)
        n_matched += len(pairs)
        found = {t: e for e, t in pairs}
        tx = frame_transmitters_m[frame.frame]
        for k, row in enumerate(rows):
            truth_kind = kinds.index(truth_kinds[int(row)])
            if k not in found:
                confusion[truth_kind, -1] += 1
                continue
            obj = frame.objects[found[k]]
            surface = obj.surface
            reported = kinds.index(surface.kind) if surface is not None else 0
            confusion[truth_kind, reported] += 1
            if kinds[truth_kind] == kinds[reported] == "plane" and surface is not None:
                assert surface.normal is not None
                assert surface.distance_m is not None
                offset = tx - truth[row]
                distance = float(np.linalg.norm(offset))
                cosine = float(np.clip(surface.normal @ (offset / distance), -1.0, 1.0))
                normal_errors.append(math.degrees(math.acos(cosine)))
                distance_errors.append(surface.distance_m - distance)
    return ClassEvaluation(
        kinds=kinds,
        confusion=confusion,
        n_located=n_located,
        n_false=n_located - n_matched,
        normal_errors_deg=np.array(normal_errors),
        distance_errors_m=np.array(distance_errors),
    )
