"""Locating with reflector classes: planes and corners found as such, points as before.

A frame's echoes are explained in six steps (docs/METHOD.md 10.10):

1. **Points, then classes.** The point association (:mod:`echoloc.localise.locate`) runs as
   without classes, and each object is classified by the hypotheses of
   :mod:`echoloc.localise.surfaces`. It becomes a plane or corner only when that fits within
   the chi-square gate and explains its echoes decisively better (a likelihood ratio of
   exp(:data:`DECISIVE_CHI2` / 2));
   one a plane explains about as well (on the boresight or the diagonals of a symmetric
   array with one transmitter) stays a point and says so through its ``kind_confidence``.
2. **Ghosts.** An object whose echoes two others with shorter paths explain as double
   reflections goes (:func:`_explained_away`). With several transmitters, each point is then
   cross-checked against what the others would hear from a plane, a corner or a point there
   (:func:`_cross_check`).
3. **Mirror groups** among the echoes no object took (:func:`mirror_groups`): every choice
   of one echo per receiver that one image fits, with amplitudes that agree, and that a
   point fits decisively worse. With several transmitters, a group of the newest frame,
   or an object step 1 could not tell from a plane, is paired with another transmitter's
   group that one plane or corner fits (:func:`_paired`).
4. **Edges** along ``LocateOptions.edge_axis`` among what is left (:func:`edge_groups`).
5. **Ghosts again**, and, with several transmitters, a point that only the newest frame
   supports must echo to the other transmitters too (:func:`_seen_by_others`), and a point or
   corner that is a nearer point's reflection in a wall never heard goes
   (:func:`_without_unheard_mirrors`).
6. **One plane a wall** (:func:`_one_plane_a_wall`).

Everything here is in the sensor frame, m.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from echoloc.localise import surfaces
from echoloc.localise.locate import (
    FrameObjects,
    LocatedObject,
    LocateOptions,
    _chi2_gate,
    _merge_sigma,
    chi2_tail,
    linear_start,
    path_sigmas_m,
)
from echoloc.tof.echoes import ChannelEchoes, FrameEchoes

FloatArray = NDArray[np.float64]

DECISIVE_CHI2 = 9.0
"""How much worse (in chi-square) a point must fit an echo group than a mirror for the group to be
taken as a mirror before the point association sees it: a likelihood ratio of exp(4.5), 90 to 1."""

MIRROR_AMPLITUDE_LOG_SIGMA = 0.25
"""Spread allowed to a mirror group's amplitudes times paths about their mean, natural-log units
(28 %): wider than the point association's 10 % because a corner's double bounce shares some
receivers' echoes with its edge's own, which adds to them."""

MOVED_M = 0.03
"""How far (in path, m) a point may have moved between the frames of two transmitters and still
count as seen by both (:func:`_seen_by_others`): 1.5 m/s at 100 frames a second."""

PAIRING_MARGIN_M = 0.05
"""Slack on the distance of two transmitters' mirror midpoints before their pairing is fitted, m."""

CORNER_COSINE = math.sin(math.radians(10.0))
"""Two planes whose normals' cosine is below this (within 10 degrees of a right angle) make a
corner: their plane-plane double reflection is that corner's echo, not a ghost."""

_UNTESTED = surfaces.Surface("point", 1.0, {"point": 1.0})
"""The class of an object no hypothesis beside the association's point could be fitted to."""

MIRROR_CANDIDATE = 0.05
"""A point found on one transmitter's echoes whose plane probability is at least this is tried
as a mirror with the other transmitters' echoes (where one transmitter cannot tell them apart)."""

CROSS_CHECK_SIGMAS = 3.0
"""How far (in merged-peak sigmas, :func:`echoloc.localise.locate._merge_sigma`) another
transmitter's echo may lie from where a plane, corner or point predicts it and still confirm it."""

MERGED_PRIOR = 0.1
"""Prior probability that an echo is a merged peak, for :func:`_robust_object`'s mixture."""

_ROBUST_ROUNDS = 2
"""Refits of :func:`_robust_hypotheses` after the first that may call more echoes merged."""

MISSED_PRICE = CROSS_CHECK_SIGMAS**2 + 2 * math.log(9.0 * (1 - MERGED_PRIOR) / MERGED_PRIOR)
"""What a channel of another transmitter costs a hypothesis when it holds no echo within reach of
its prediction: as much as an echo at the edge of the reach that was called merged, with a merged
peak's sigma taken as 9 times a clean echo's (it is 7 times for the 0.5 mm model error and the
29 mm resolution of the test scenes; a fixed price keeps the choice the same on every frame)."""

MAX_COMBINATIONS = 200_000
"""Most echo combinations one transmitter's mirror search weighs; beyond, the frame's mirror
search stops at this many (the point association still runs)."""

SAME_WALL_DEG = 5.0
"""Two planes of one frame whose normals are within this angle, and whose distances differ by less
than the pulse's resolution, are one wall: two walls that close along their normal would make
one merged echo on every channel, so no frame hears them apart."""


@dataclass(frozen=True, eq=False)
class MirrorGroup:
    """One echo per channel of one transmitter that a virtual source explains.

    ``channels`` are receiver indices, ``echoes`` the echo index on each; ``image_m`` the
    fitted virtual source.
    """

    transmitter: int
    channels: tuple[int, ...]
    echoes: tuple[int, ...]
    paths_m: FloatArray
    sigmas_m: FloatArray
    image_m: FloatArray


def _combinations(
    paths: list[FloatArray], receivers_m: FloatArray, slack: list[FloatArray]
) -> NDArray[np.int64]:
    """Echo indices (k, n_ch), one per channel, whose paths two by two differ by no more than
    the receivers' distance plus the slack (a sphere about one source cannot reach further)."""
    rows = np.arange(len(paths[0]), dtype=np.int64)[:, None]
    for c in range(1, len(paths)):
        n = len(paths[c])
        if n == 0 or len(rows) == 0:
            return np.zeros((0, len(paths)), dtype=np.int64)
        grown = np.concatenate(
            [np.repeat(rows, n, axis=0), np.tile(np.arange(n, dtype=np.int64), len(rows))[:, None]], axis=1
        )
        keep = np.ones(len(grown), dtype=bool)
        for b in range(c):
            reach = np.linalg.norm(receivers_m[c] - receivers_m[b])
            gap = np.abs(paths[c][grown[:, c]] - paths[b][grown[:, b]])
            keep &= gap <= reach + slack[c][grown[:, c]] + slack[b][grown[:, b]]
        rows = grown[keep][:MAX_COMBINATIONS]
    return rows


class _Combinations(NamedTuple):
    """One transmitter's usable channels (receiver indices), their receivers (m, 3), and every
    combination of one echo per channel that one reflection can make: echo indices (k, m), paths
    and sigmas (k, m), m."""

    channels: list[int]
    receivers_m: FloatArray
    rows: NDArray[np.int64]
    paths_m: FloatArray
    sigmas_m: FloatArray


def _echo_combinations(
    echoes: FrameEchoes,
    receivers_m: FloatArray,
    options: LocateOptions,
    usable: NDArray[np.bool_] | None,
    widened: set[tuple[int, int]] | None = None,
) -> _Combinations | None:
    """:class:`_Combinations` of a frame, None with fewer than four usable channels or none at all.
    The echoes in ``widened`` (channel, echo) get the association's merged-peak sigma added."""
    n_rx = len(receivers_m)
    use = np.ones(n_rx, dtype=bool) if usable is None else np.asarray(usable, dtype=bool)
    channels = [c for c in range(n_rx) if use[c]]
    if len(channels) < 4:
        return None
    c_m_s = echoes.speed_of_sound_m_s
    paths = [echoes.channels[c].tof_s * c_m_s for c in channels]
    sigmas = [path_sigmas_m(echoes.channels[c].snr_db, c_m_s, options) for c in channels]
    if widened:
        merge = 0.0 if options.resolution_m is None else _merge_sigma(options.resolution_m)
        for k, c in enumerate(channels):
            merged = np.array([(c, e) in widened for e in range(len(paths[k]))], dtype=bool)
            sigmas[k] = np.where(merged, np.sqrt(sigmas[k] ** 2 + merge**2), sigmas[k])
    rx = receivers_m[channels]
    rows = _combinations(paths, rx, [4 * s for s in sigmas])
    if widened and len(rows):
        borrowed = sum(
            np.array([(c, int(e)) in widened for e in rows[:, k]], dtype=np.int64)
            for k, c in enumerate(channels)
        )
        rows = rows[np.asarray(borrowed) <= 1]
    if len(rows) == 0:
        return None
    measured = np.stack([paths[k][rows[:, k]] for k in range(len(channels))], axis=1)
    s = np.stack([sigmas[k][rows[:, k]] for k in range(len(channels))], axis=1)
    return _Combinations(channels, rx, rows, measured, s)


def _amplitudes_agree(
    echoes: FrameEchoes, found: _Combinations, rows: NDArray[np.int64], power: int, options: LocateOptions
) -> NDArray[np.bool_]:
    """Whether each combination's amplitudes times its paths to ``power`` are the same on every
    channel within :data:`MIRROR_AMPLITUDE_LOG_SIGMA` (the chi-square gate): spherical spreading
    from one image (power 1) or from a point-like reflector (power 2). Echoes of different
    reflectors that happen to fit one geometry rarely agree in it."""
    amplitudes = np.stack(
        [np.abs(echoes.channels[c].amplitude)[found.rows[rows, k]] for k, c in enumerate(found.channels)],
        axis=1,
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        strength = np.log(amplitudes * found.paths_m[rows] ** power)
    spread = (
        np.sum((strength - strength.mean(axis=1, keepdims=True)) ** 2, axis=1) / MIRROR_AMPLITUDE_LOG_SIGMA**2
    )
    return np.asarray(
        np.nan_to_num(spread, nan=np.inf) <= _chi2_gate(options.gate_probability, len(found.channels) - 1)
    )


def _disjoint(
    found: _Combinations, order: Sequence[int], exempt: set[tuple[int, int]] | None = None
) -> list[int]:
    """The combinations (rows of ``found``), in ``order``, that share no echo with one taken before;
    echoes in ``exempt`` (merged peaks borrowed from other objects) may repeat."""
    taken: set[tuple[int, int]] = set()
    chosen = []
    for r in order:
        picks = [(c, int(found.rows[r, k])) for k, c in enumerate(found.channels)]
        own = [p for p in picks if exempt is None or p not in exempt]
        if any(p in taken for p in own):
            continue
        taken.update(own)
        chosen.append(int(r))
    return chosen


def mirror_groups(
    transmitter: int,
    transmitter_m: FloatArray,
    receivers_m: FloatArray,
    echoes: FrameEchoes,
    options: LocateOptions,
    usable: NDArray[np.bool_] | None = None,
    *,
    decisive: bool = True,
) -> list[MirrorGroup]:
    """The disjoint mirror groups of one transmitter's frame, best fit first.

    Every usable channel must hold an echo of the group, and there must be one more
    channel than a virtual source has coordinates (a degree of freedom to test it).
    ``decisive``: only groups a point fits :data:`DECISIVE_CHI2` worse (False: also those
    a point fits as well, to be told apart with another transmitter's echoes).
    """
    found = _echo_combinations(echoes, receivers_m, options, usable)
    if found is None:
        return []
    channels, rx, measured, s = found.channels, found.receivers_m, found.paths_m, found.sigmas_m
    boresight = np.asarray(options.boresight, dtype=float)
    boresight = boresight / np.linalg.norm(boresight)
    start = surfaces.image_start_m(rx, measured, boresight)
    gate = _chi2_gate(options.gate_probability, len(channels) - 3)
    # A cheap first cut: the closed form's own chi-square, with a wide margin.
    with np.errstate(invalid="ignore"):
        first = np.sum(((surfaces.mirror_paths_m(start, rx) - measured) / s) ** 2, axis=1)
    near = np.flatnonzero(np.isfinite(first) & (first <= 100 * gate + 100))
    if len(near) == 0:
        return []
    image = surfaces.fit(
        lambda v: surfaces.mirror_paths_m(v, rx),
        start[near],
        measured[near],
        s[near],
        jacobian=surfaces.mirror_jacobian(rx),
        kernel=surfaces.CompiledModel(surfaces.IMAGE_MODEL, rx, rx),  # an image needs no transmitter
    )
    ahead = (image.parameters - transmitter_m) @ boresight > 0
    agree = _amplitudes_agree(echoes, found, near, 1, options)
    passed = (image.chi2 <= gate) & ahead & agree
    if not np.any(passed):
        return []
    tx = np.broadcast_to(transmitter_m, rx.shape)
    point = surfaces.fit(
        lambda p: surfaces.point_paths_m(p, tx, rx),
        0.5 * (image.parameters[passed] + transmitter_m),
        measured[near[passed]],
        s[near[passed]],
        jacobian=lambda p: surfaces.point_jacobian(p, tx, rx),
        kernel=surfaces.CompiledModel(surfaces.POINT_MODEL, tx, rx),
    )
    margin = point.chi2 - image.chi2[passed]
    keep = margin >= DECISIVE_CHI2 if decisive else np.ones(len(margin), dtype=bool)
    candidates = np.flatnonzero(passed)[keep]  # indices into near
    order = sorted(candidates.tolist(), key=lambda k: image.chi2[k])
    chosen = _disjoint(found, [int(near[k]) for k in order])
    at = {int(near[k]): k for k in order}
    return [
        MirrorGroup(
            transmitter=transmitter,
            channels=tuple(channels),
            echoes=tuple(int(found.rows[r, c]) for c in range(len(channels))),
            paths_m=measured[r],
            sigmas_m=s[r],
            image_m=image.parameters[at[r]],
        )
        for r in chosen
    ]


@dataclass(frozen=True, eq=False)
class EdgeGroup:
    """One echo per channel of one transmitter that a straight edge along the edge axis explains.

    ``line`` holds the edge's two coordinates across the axis (:func:`echoloc.localise.surfaces.edge_paths_m`)
    with their covariance; ``chi2`` the edge's fit, ``mirror_chi2`` an image's on the same paths
    (for the class probabilities).
    """

    transmitter: int
    channels: tuple[int, ...]
    echoes: tuple[int, ...]
    line: FloatArray
    covariance: FloatArray
    chi2: float
    mirror_chi2: float


def edge_groups(
    transmitter: int,
    transmitter_m: FloatArray,
    receivers_m: FloatArray,
    echoes: FrameEchoes,
    options: LocateOptions,
    usable: NDArray[np.bool_] | None = None,
    shared: set[tuple[int, int]] | None = None,
) -> list[EdgeGroup]:
    """The disjoint edge groups of one transmitter's frame, best fit first.

    ``shared`` names (channel, echo) pairs other objects took: a group may use one of them as
    a merged peak (its sigma widened as the association widens a shared echo's), not more.

    An edge along ``options.edge_axis`` has two free coordinates, so four channels leave two
    degrees of freedom to test it. A group counts when the edge fits within the gate, its
    amplitudes agree with point-like spreading (amplitude x path^2 the same on every channel,
    within :data:`MIRROR_AMPLITUDE_LOG_SIGMA`), and both a point and a mirror fit it
    :data:`DECISIVE_CHI2` worse: a post, a table leg or a door jamb whose echo slides along it
    from receiver to receiver, which no single point explains.
    """
    if options.edge_axis is None:
        return []
    found = _echo_combinations(echoes, receivers_m, options, usable, shared or set())
    if found is None:
        return []
    channels, rx, measured, s = found.channels, found.receivers_m, found.paths_m, found.sigmas_m
    axis = np.asarray(options.edge_axis, dtype=float)
    e, a, b = surfaces.axis_basis(axis)
    plane = np.stack([a, b])
    tx = np.broadcast_to(transmitter_m, rx.shape)
    # The start: the 2-D point problem across the axis, |Q - T'| + |Q - R'| = sqrt(l^2 - (e.(R - T))^2).
    across = np.sqrt(np.maximum(measured**2 - ((rx - transmitter_m) @ e)[None] ** 2, 0.0))
    boresight = np.asarray(options.boresight, dtype=float) @ plane.T
    if not np.linalg.norm(boresight) > 1e-9:
        return []
    start = linear_start(transmitter_m @ plane.T, rx @ plane.T, across, boresight / np.linalg.norm(boresight))
    gate = _chi2_gate(options.gate_probability, len(channels) - 2)
    # A cheap first cut: the 2-D closed form's own chi-square, with a wide margin.
    with np.errstate(invalid="ignore"):
        first = np.sum(((surfaces.edge_paths_m(start, axis, tx, rx) - measured) / s) ** 2, axis=1)
    near = np.flatnonzero(np.isfinite(first) & (first <= 100 * gate + 100))
    if len(near) == 0:
        return []
    edge = surfaces.fit(
        lambda q: surfaces.edge_paths_m(q, axis, tx, rx),
        start[near],
        measured[near],
        s[near],
        jacobian=lambda q: surfaces.edge_jacobian(q, axis, tx, rx),
        kernel=surfaces.CompiledModel(surfaces.EDGE_MODEL, tx, rx, axis=axis),
    )
    agree = _amplitudes_agree(echoes, found, near, 2, options)
    feet = surfaces.edge_foot_m(edge.parameters, axis, transmitter_m)
    ahead = (feet - transmitter_m) @ np.asarray(options.boresight, dtype=float) > 0
    passed = np.flatnonzero((edge.chi2 <= gate) & agree & ahead)  # indices into near
    if len(passed) == 0:
        return []
    rows = near[passed]
    point = surfaces.fit(
        lambda p: surfaces.point_paths_m(p, tx, rx),
        feet[passed],
        measured[rows],
        s[rows],
        jacobian=lambda p: surfaces.point_jacobian(p, tx, rx),
        kernel=surfaces.CompiledModel(surfaces.POINT_MODEL, tx, rx),
    )
    mirror_start = surfaces.image_start_m(rx, measured[rows], np.asarray(options.boresight, dtype=float))
    mirror = surfaces.fit(
        lambda v: surfaces.mirror_paths_m(v, rx),
        mirror_start,
        measured[rows],
        s[rows],
        jacobian=surfaces.mirror_jacobian(rx),
        kernel=surfaces.CompiledModel(surfaces.IMAGE_MODEL, tx, rx),
    )
    keep = np.minimum(point.chi2, mirror.chi2) - edge.chi2[passed] >= DECISIVE_CHI2
    order = sorted(np.flatnonzero(keep).tolist(), key=lambda k: edge.chi2[passed[k]])
    at = {int(rows[k]): k for k in order}
    chosen = _disjoint(found, [int(rows[k]) for k in order], shared)
    return [
        EdgeGroup(
            transmitter=transmitter,
            channels=tuple(channels),
            echoes=tuple(int(found.rows[r, c]) for c in range(len(channels))),
            line=edge.parameters[passed[at[r]]],
            covariance=edge.covariance[passed[at[r]]],
            chi2=float(edge.chi2[passed[at[r]]]),
            mirror_chi2=float(mirror.chi2[at[r]]),
        )
        for r in chosen
    ]


def _edge_object(group: EdgeGroup, transmitters_m: FloatArray, options: LocateOptions) -> LocatedObject:
    """An edge group as a located point-like object: the edge's point nearest the transmitter, with
    the edge's direction and the class probabilities of edge (a point-like class) against mirror."""
    assert options.edge_axis is not None
    axis = np.asarray(options.edge_axis, dtype=float)
    e, a, b = surfaces.axis_basis(axis)
    across = np.stack([a, b], axis=1)  # (3, 2)
    n = len(group.channels)
    evidence = np.array([-0.5 * group.chi2 - np.log(n), -0.5 * group.mirror_chi2 - 1.5 * np.log(n)])
    weight = np.exp(evidence - evidence.max())
    probability = weight / weight.sum()
    surface = surfaces.Surface(
        "point",
        float(probability[0]),
        {"point": float(probability[0]), "plane": float(probability[1])},
        edge_direction=e,
        edge_covariance=np.zeros((3, 3)),
    )
    dof = n - 2
    return LocatedObject(
        position_m=surfaces.edge_foot_m(group.line[None], axis, transmitters_m[group.transmitter])[0],
        covariance_m2=across @ group.covariance @ across.T,
        receivers=group.channels,
        echo_indices=group.echoes,
        chi2=group.chi2,
        score=chi2_tail(dof, group.chi2),
        transmitters=(group.transmitter,) * n,
        surface=surface,
    )


def _without(
    echoes: FrameEchoes, removed: set[tuple[int, int]]
) -> tuple[FrameEchoes, list[NDArray[np.int64]]]:
    """``echoes`` less the (channel, echo) pairs in ``removed``, and per channel the original index
    of each echo kept."""
    channels, kept_at = [], []
    for c, ch in enumerate(echoes.channels):
        keep = np.array([k for k in range(len(ch.tof_s)) if (c, k) not in removed], dtype=np.int64)
        kept_at.append(keep)
        channels.append(ChannelEchoes(ch.tof_s[keep], ch.amplitude[keep], ch.snr_db[keep]))
    return replace(echoes, channels=tuple(channels)), kept_at


@dataclass(frozen=True, eq=False)
class _Channels:
    """Channel geometry and paths of one echo group: transmitter positions, receivers, paths, sigmas."""

    transmitters_m: FloatArray
    receivers_m: FloatArray
    paths_m: FloatArray
    sigmas_m: FloatArray
    transmitters: tuple[int, ...]
    receivers: tuple[int, ...]
    echoes: tuple[int, ...]


def _group_channels(
    groups: Sequence[MirrorGroup], transmitters_m: FloatArray, receivers_m: FloatArray
) -> _Channels:
    tx_of = [g.transmitter for g in groups for _ in g.channels]
    return _Channels(
        transmitters_m[tx_of],
        receivers_m[[c for g in groups for c in g.channels]],
        np.concatenate([g.paths_m for g in groups]),
        np.concatenate([g.sigmas_m for g in groups]),
        tuple(tx_of),
        tuple(c for g in groups for c in g.channels),
        tuple(e for g in groups for e in g.echoes),
    )


def _objects_of(
    groups: Sequence[_Channels],
    reference: int,
    transmitters_m: FloatArray,
    starts_m: FloatArray,
    options: LocateOptions,
    shared: Sequence[int] | None = None,
) -> list[LocatedObject | None]:
    """A located object of the hypotheses' best class for each echo group (None where none fits).

    Groups on the same channels are fitted together, in one call of
    :func:`echoloc.localise.surfaces.hypotheses`."""
    found: list[LocatedObject | None] = [None] * len(groups)
    by_channels: dict[tuple[tuple[int, ...], tuple[int, ...]], list[int]] = {}
    for k, g in enumerate(groups):
        by_channels.setdefault((g.transmitters, g.receivers), []).append(k)
    reference_m = transmitters_m[reference]
    for members in by_channels.values():
        first = groups[members[0]]
        fitted = surfaces.hypotheses(
            first.transmitters_m,
            first.receivers_m,
            np.stack([groups[k].paths_m for k in members]),
            np.stack([groups[k].sigmas_m for k in members]),
            reference_m,
            starts_m[members],
            options.gate_probability,
        )
        for row, k in enumerate(members):
            if not np.any(np.isfinite(fitted.chi2[row])) or not np.any(fitted.probability[row] > 0):
                continue
            surface, position, covariance = surfaces.describe(
                fitted, row, first.transmitters_m, first.receivers_m, reference_m
            )
            kind = surfaces.KINDS.index(surface.kind)
            chi2 = float(fitted.chi2[row, kind])
            dof = int(fitted.n_paths[row]) - surfaces.PARAMETERS[surface.kind]
            found[k] = LocatedObject(
                position_m=np.asarray(position, dtype=float),
                covariance_m2=np.asarray(covariance, dtype=float),
                receivers=groups[k].receivers,
                echo_indices=groups[k].echoes,
                chi2=chi2,
                score=chi2_tail(dof, chi2) if dof > 0 else 1.0,
                transmitters=groups[k].transmitters,
                shared=0 if shared is None else shared[k],
                surface=surface,
            )
    return found


def _paired(
    newest: MirrorGroup,
    others: list[MirrorGroup],
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    options: LocateOptions,
) -> tuple[LocatedObject | None, MirrorGroup | None]:
    """The newest frame's group with the other transmitter's group that one plane or corner fits
    best (within the gate), or alone."""
    start = 0.5 * (newest.image_m + transmitters_m[newest.transmitter])
    # A plane's or a corner's images lie across it from their transmitters: the midpoints of
    # image and transmitter are on the plane, or on the edge, so two transmitters' midpoints
    # are no farther apart than the transmitters (plus a margin for the fits' errors).
    t_newest = transmitters_m[newest.transmitter]
    near = [
        other
        for other in others
        if np.linalg.norm(0.5 * (other.image_m + transmitters_m[other.transmitter]) - start)
        <= np.linalg.norm(transmitters_m[other.transmitter] - t_newest) + PAIRING_MARGIN_M
    ]
    groups = [_group_channels([newest], transmitters_m, receivers_m)]
    groups += [_group_channels([newest, other], transmitters_m, receivers_m) for other in near]
    found = _objects_of(groups, newest.transmitter, transmitters_m, np.tile(start, (len(groups), 1)), options)
    best: tuple[float, LocatedObject, MirrorGroup] | None = None
    for other, channels, candidate in zip(near, groups[1:], found[1:], strict=True):
        if candidate is None or candidate.surface is None or candidate.surface.kind == "point":
            continue
        dof = len(channels.paths_m) - surfaces.PARAMETERS[candidate.surface.kind]
        if candidate.chi2 <= _chi2_gate(options.gate_probability, dof) and (
            best is None or candidate.chi2 < best[0]
        ):
            best = (candidate.chi2, candidate, other)
    if best is None:
        return found[0], None
    return best[1], best[2]


def locate_with_classes(
    frames: Sequence[tuple[int, FrameEchoes]],
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    options: LocateOptions,
    usable: NDArray[np.bool_] | None,
    locate_points: Callable[[list[tuple[int, FrameEchoes]]], FrameObjects],
) -> FrameObjects:
    """The objects of the newest of ``frames`` ((transmitter, echoes), one per transmitter), each
    with its class (:class:`echoloc.localise.surfaces.Surface`).

    ``locate_points`` is the point association for the same frames (one frame: its transmitter's
    :class:`~echoloc.localise.locate.FrameLocator`; several: :func:`~echoloc.localise.locate.combine_frames`).
    """
    newest_t = max(frames, key=lambda f: f[1].frame)[0]
    points = locate_points(list(frames))
    alternatives: list[tuple[LocatedObject, LocatedObject]] = []
    objects = _classified(
        points.objects, frames, newest_t, transmitters_m, receivers_m, options, alternatives
    )
    objects = _explained_away(objects, frames, transmitters_m, receivers_m, options, alternatives)
    # Two transmitter positions tell what one image cannot (Kleeman and Kuc): cross-check points.
    fired = transmitters_m[[t for t, _ in frames]]
    told_apart = surfaces.distinct_transmitters(fired) >= 2 and options.resolution_m is not None
    if told_apart:
        objects = _cross_checked(objects, frames, newest_t, transmitters_m, receivers_m, options)

    # The echoes no object took may still hold planes and corners the point association cannot fit.
    # With several transmitters, the other frames' mirror groups may also be the other half of
    # a plane or corner the association found on the newest frame alone.
    used = _used_echoes(objects, frames)
    # An older frame's echoes only lend points optional support: its mirror groups may take them
    # (a wall the association built from the newest frame and stray older echoes pairs with them).
    settled = _used_echoes(
        [o for o in objects if o.surface is not None and o.surface.kind != "point"], frames
    )
    groups: dict[int, list[MirrorGroup]] = {}
    for t, echoes in frames:
        rest, kept_at = _without(echoes, used[t] if t == newest_t else settled[t])
        found = mirror_groups(
            t, transmitters_m[t], receivers_m, rest, options, usable, decisive=t == newest_t
        )
        groups[t] = [
            replace(g, echoes=tuple(int(kept_at[c][e]) for c, e in zip(g.channels, g.echoes, strict=True)))
            for g in found
        ]
    others = [g for t, gs in groups.items() if t != newest_t for g in gs]
    if others:
        for k, o in enumerate(objects):
            group = _as_mirror_group(o, frames, newest_t, transmitters_m, options)
            if group is None:
                continue
            paired, partner = _paired(group, others, transmitters_m, receivers_m, options)
            if partner is not None and paired is not None:
                objects[k] = paired
                others.remove(partner)
    for group in groups[newest_t]:
        found_object, partner = _paired(group, others, transmitters_m, receivers_m, options)
        if found_object is None:
            continue
        objects.append(found_object)
        if partner is not None:
            others.remove(partner)
    # Then edges, on the newest frame's echoes: those no object took, and one merged peak at most.
    newest_echoes = dict(frames)[newest_t]
    taken = _used_echoes(objects, frames)[newest_t]
    for edge in edge_groups(
        newest_t, transmitters_m[newest_t], receivers_m, newest_echoes, options, usable, taken
    ):
        shares = sum((c, e) in taken for c, e in zip(edge.channels, edge.echoes, strict=True))
        objects.append(replace(_edge_object(edge, transmitters_m, options), shared=shares))
    real = _explained_away(objects, frames, transmitters_m, receivers_m, options, alternatives)
    if len(frames) > 1:
        real = [o for o in real if _seen_by_others(o, frames, newest_t, transmitters_m, receivers_m)]
    if told_apart:
        real = _without_unheard_mirrors(real, frames, newest_t, transmitters_m, receivers_m, options)
    return FrameObjects(points.frame, points.time_s, tuple(_one_plane_a_wall(real, options)))


def _one_plane_a_wall(objects: list[LocatedObject], options: LocateOptions) -> list[LocatedObject]:
    """``objects`` with one plane a wall: of the planes :data:`SAME_WALL_DEG` and the resolution
    apart (the same wall, found from two echo groups), the one with the most echoes, then the
    best fit (its chi-square tail), stays. Without a known resolution, nothing goes."""
    if options.resolution_m is None:
        return objects
    planes = [
        (k, o.surface.normal, o.surface.distance_m, (-len(o.receivers), -o.score))
        for k, o in enumerate(objects)
        if o.surface is not None
        and o.surface.kind == "plane"
        and o.surface.normal is not None
        and o.surface.distance_m is not None
    ]
    cos_same = math.cos(math.radians(SAME_WALL_DEG))
    kept: list[tuple[FloatArray, float]] = []
    dropped: set[int] = set()
    for k, normal, distance, _ in sorted(planes, key=lambda plane: plane[3]):
        if any(float(normal @ n) >= cos_same and abs(distance - d) < options.resolution_m for n, d in kept):
            dropped.add(k)
        else:
            kept.append((normal, distance))
    return [o for k, o in enumerate(objects) if k not in dropped]


def _predicted_elsewhere(
    image_m: FloatArray,
    point_m: FloatArray,
    newest_m: FloatArray,
    transmitter_m: FloatArray,
    receivers_m: FloatArray,
    edge_axis: tuple[float, float, float] | None,
) -> dict[str, FloatArray]:
    """The paths (m) another transmitter at ``transmitter_m`` would hear on ``receivers_m`` (m, 3)
    from what one transmitter at ``newest_m`` heard as the image ``image_m`` or the point
    ``point_m``: as that point, as the plane that makes the image (the bisector of transmitter and
    image), and as a corner whose edge crosses the image's midpoint along ``edge_axis`` (made
    perpendicular to the image's direction; no corner without an axis). Kleeman and Kuc's test:
    one image fixes a plane, and, with the edge's direction, a corner; a point stays put."""
    tx = np.broadcast_to(transmitter_m, receivers_m.shape)
    feet = (0.5 * (image_m - newest_m))[None]
    predicted = {
        "point": surfaces.point_paths_m(point_m[None], tx, receivers_m)[0],
        "plane": surfaces.plane_paths_m(feet, tx, receivers_m, newest_m)[0],
    }
    if edge_axis is not None:
        u = feet[0] / np.linalg.norm(feet[0])
        e = np.asarray(edge_axis, dtype=float)
        e = e - (e @ u) * u
        if np.linalg.norm(e) > 1e-6:
            e = e / np.linalg.norm(e)
            image = surfaces.half_turned_m(transmitter_m, newest_m + feet[0], e)
            predicted["corner"] = np.linalg.norm(image - receivers_m, axis=1)
    return predicted


def _cross_checked(
    objects: list[LocatedObject],
    frames: Sequence[tuple[int, FrameEchoes]],
    newest_t: int,
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    options: LocateOptions,
) -> list[LocatedObject]:
    """``objects``, each point the other transmitters hear as a plane or corner refitted as such
    (:func:`_cross_check`); for two or more transmitter positions and a known resolution."""
    return [
        o
        if o.surface is not None and o.surface.kind != "point"
        else _cross_check(o, frames, newest_t, transmitters_m, receivers_m, options)
        for o in objects
    ]


def _cross_check(
    o: LocatedObject,
    frames: Sequence[tuple[int, FrameEchoes]],
    newest_t: int,
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    options: LocateOptions,
) -> LocatedObject:
    """A point of the newest frame, or the plane or corner the other transmitters' echoes say it is.

    Its newest-frame echoes (four or more) fix an image and a point; where the other
    transmitters hear a point, a plane or a corner follows from them (:func:`_predicted_elsewhere`).
    Each hypothesis takes, on every other channel, the echo nearest its prediction within
    :data:`CROSS_CHECK_SIGMAS` merged-peak sigmas (a wall's echo merges with its own double
    reflections, which moves the peak by millimetres); a channel with none costs it
    :data:`MISSED_PRICE`. Each is then fitted on its own echoes, merged peaks allowed
    (:func:`_robust_hypotheses`), with Schwarz's penalty. A plane or corner (confirmed by three
    or more echoes) replaces the point when it scores :data:`DECISIVE_CHI2` better and its fit
    passes the chi-square gate.
    """
    base = _channels_of(o, frames, newest_t, transmitters_m, receivers_m, options)
    if base is None:
        return o
    assert options.resolution_m is not None
    merge = _merge_sigma(options.resolution_m)
    newest_m = transmitters_m[newest_t]
    sources = _image_and_point(base, o.position_m, np.sqrt(base.sigmas_m**2 + merge**2), options)
    if sources is None:
        return o
    image, point = sources
    hits = _nearest_echoes(image, point, frames, newest_t, transmitters_m, receivers_m, options, merge)
    if all(len(hits.get(kind, [])) < 3 for kind in ("plane", "corner")):
        return o
    n_other = sum(len(echoes.channels) for t, echoes in frames if t != newest_t)
    start_m = newest_m + 0.5 * (image - newest_m)
    scores = np.full(len(surfaces.KINDS), np.inf)
    fits: list[tuple[_Channels, _RobustFit] | None] = [None] * len(surfaces.KINDS)
    for k, kind in enumerate(surfaces.KINDS):
        extra = hits.get(kind, [])
        if kind != "point" and len(extra) < 3:
            continue
        group = _with_echoes(base, extra, dict(frames), transmitters_m, receivers_m, options)
        robust = _robust_hypotheses(group, newest_m, start_m, merge, options, (kind,))
        penalty = surfaces.PARAMETERS[kind] * math.log(len(base.paths_m) + n_other)
        scores[k] = robust.priced[k] + MISSED_PRICE * (n_other - len(extra)) + penalty
        fits[k] = (group, robust)
    best = int(np.argmin(scores))
    entry = fits[best]
    if best == 0 or entry is None or scores[0] - scores[best] < DECISIVE_CHI2:
        return o
    group, robust = entry
    dof = len(group.paths_m) - surfaces.PARAMETERS[surfaces.KINDS[best]]
    if robust.chi2[best] > _chi2_gate(options.gate_probability, dof):
        return o
    return _robust_object(group, robust, best, scores, newest_m)


def _channels_of(
    o: LocatedObject,
    frames: Sequence[tuple[int, FrameEchoes]],
    transmitter: int,
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    options: LocateOptions,
) -> _Channels | None:
    """An object's echoes on one transmitter's frame, as a channel group; None with under four."""
    tx_of = _channel_transmitters(o, frames)
    own = [k for k, t in enumerate(tx_of) if t == transmitter]
    if len(own) < 4:
        return None
    paths, sigmas = _group_paths(o, tx_of, frames, options)
    return _Channels(
        transmitters_m[[transmitter] * len(own)],
        receivers_m[[o.receivers[k] for k in own]],
        paths[own],
        sigmas[own],
        (transmitter,) * len(own),
        tuple(o.receivers[k] for k in own),
        tuple(o.echo_indices[k] for k in own),
    )


def _image_and_point(
    group: _Channels, near_m: FloatArray, sigmas_m: FloatArray, options: LocateOptions
) -> tuple[FloatArray, FloatArray] | None:
    """The image and the point (m) that fit one transmitter's echo group (sigmas ``sigmas_m``), the
    point started at ``near_m``; None when the image is not ahead of the transmitter."""
    tx, rx = group.transmitters_m, group.receivers_m
    image = _fit_image(rx, group.paths_m, sigmas_m, options.boresight).parameters[0]
    if not (np.all(np.isfinite(image)) and (image - tx[0]) @ np.asarray(options.boresight) > 0):
        return None
    return image, _point_fit(near_m, group.paths_m, sigmas_m, tx, rx).parameters[0]


def _nearest_echoes(
    image_m: FloatArray,
    point_m: FloatArray,
    frames: Sequence[tuple[int, FrameEchoes]],
    newest_t: int,
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    options: LocateOptions,
    merge: float,
) -> dict[str, list[tuple[int, int, int]]]:
    """For each hypothesis, the (transmitter, receiver, echo) of the other frames' echoes nearest
    its prediction (:func:`_predicted_elsewhere`), where within :data:`CROSS_CHECK_SIGMAS` ``merge``."""
    newest_m = transmitters_m[newest_t]
    nowhere = np.full(len(receivers_m), np.nan)  # a hypothesis this geometry cannot make

    def prediction(kind: str) -> Callable[[FloatArray], FloatArray]:
        def paths(tx: FloatArray) -> FloatArray:
            found = _predicted_elsewhere(image_m, point_m, newest_m, tx[0], receivers_m, options.edge_axis)
            return found.get(kind, nowhere)

        return paths

    reach = CROSS_CHECK_SIGMAS * merge
    return {
        kind: _echoes_near(prediction(kind), frames, newest_t, transmitters_m, receivers_m, reach)
        for kind in surfaces.KINDS
    }


def _hypothesis_paths(
    found: surfaces.Hypotheses, kind: str, group: _Channels, reference_m: FloatArray
) -> FloatArray:
    """The paths (m) the fit of ``kind`` in ``found`` (one row) predicts on the group's channels."""
    tx, rx = group.transmitters_m, group.receivers_m
    if kind == "point":
        paths = surfaces.point_paths_m(found.point.parameters, tx, rx)
    elif kind == "plane":
        paths = surfaces.plane_paths_m(found.plane.parameters, tx, rx, reference_m)
    else:
        assert found.corner is not None
        assert found.corner_helper is not None
        images = surfaces.corner_images_m(found.corner.parameters, tx, reference_m, found.corner_helper)
        paths = surfaces.mirror_paths_images(images, rx)
    return np.asarray(paths[0], dtype=float)


class _RobustFit(NamedTuple):
    """The three hypotheses of one echo group under :func:`_robust_hypotheses`: chi-squares with the
    price of the echoes called merged (for the class), without it (for the gate), and each
    hypothesis's refit (None where not fitted)."""

    priced: FloatArray
    chi2: FloatArray
    refits: list[surfaces.Hypotheses | None]


def _robust_hypotheses(
    group: _Channels,
    reference_m: FloatArray,
    start_m: FloatArray,
    merge: float,
    options: LocateOptions,
    kinds: Sequence[str] = surfaces.KINDS,
) -> _RobustFit:
    """Fit the point, plane and corner to an echo group some of whose echoes may be merged peaks.

    Each echo is either clean (its own sigma) or merged with another (its sigma widened by a
    merged peak's ``merge``): a two-component mixture. Every hypothesis is fitted first with all
    sigmas widened, then again with only the echoes it misses by more than three plain sigmas
    widened (again while the refit misses more, :data:`_ROBUST_ROUNDS` times at most); each
    widened echo costs ``2 ln((sigma_merged / sigma) (1 - p) / p)``, the mixture's
    price of calling it merged (p = :data:`MERGED_PRIOR`). Only ``kinds`` are scored (the corner,
    the costliest fit, only when asked).
    """
    plain = group.sigmas_m
    widened = np.sqrt(plain**2 + merge**2)
    price = 2 * np.log(widened / plain * (1 - MERGED_PRIOR) / MERGED_PRIOR)

    def fitted(sigmas: FloatArray) -> surfaces.Hypotheses:
        return surfaces.hypotheses(
            group.transmitters_m,
            group.receivers_m,
            group.paths_m[None],
            sigmas[None],
            reference_m,
            start_m[None],
            options.gate_probability,
            corner_mode="always" if "corner" in kinds else "never",
        )

    first = fitted(widened)
    priced = np.full(len(surfaces.KINDS), np.inf)
    chi2 = np.full(len(surfaces.KINDS), np.inf)
    refits: list[surfaces.Hypotheses | None] = [None] * len(surfaces.KINDS)
    for k, kind in enumerate(surfaces.KINDS):
        if kind not in kinds or not np.isfinite(first.chi2[0, k]):
            continue
        loose = np.abs(group.paths_m - _hypothesis_paths(first, kind, group, reference_m)) > 3 * plain
        again = fitted(np.where(loose, widened, plain))
        for _ in range(_ROBUST_ROUNDS):
            if not np.isfinite(again.chi2[0, k]):
                break
            missed = np.abs(group.paths_m - _hypothesis_paths(again, kind, group, reference_m)) > 3 * plain
            if not np.any(missed & ~loose):
                break
            loose |= missed
            again = fitted(np.where(loose, widened, plain))
        if not np.isfinite(again.chi2[0, k]):
            continue
        chi2[k] = float(again.chi2[0, k])
        priced[k] = chi2[k] + float(np.sum(price[loose]))
        refits[k] = again
    return _RobustFit(priced, chi2, refits)


def _with_echoes(
    group: _Channels,
    extra: Sequence[tuple[int, int, int]],
    by_tx: dict[int, FrameEchoes],
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    options: LocateOptions,
) -> _Channels:
    """``group`` with the echoes ``extra`` (transmitter, receiver, echo index) added."""
    if not extra:
        return group
    paths, sigmas = [], []
    for t, r, e in extra:
        ch, c = by_tx[t].channels[r], by_tx[t].speed_of_sound_m_s
        paths.append(ch.tof_s[e] * c)
        sigmas.append(float(path_sigmas_m(ch.snr_db[e : e + 1], c, options)[0]))
    return _Channels(
        np.vstack([group.transmitters_m, transmitters_m[[t for t, _, _ in extra]]]),
        np.vstack([group.receivers_m, receivers_m[[r for _, r, _ in extra]]]),
        np.concatenate([group.paths_m, paths]),
        np.concatenate([group.sigmas_m, sigmas]),
        group.transmitters + tuple(t for t, _, _ in extra),
        group.receivers + tuple(r for _, r, _ in extra),
        group.echoes + tuple(e for _, _, e in extra),
    )


def _robust_object(
    group: _Channels, robust: _RobustFit, kind: int, scores: FloatArray, reference_m: FloatArray
) -> LocatedObject:
    """The object hypothesis ``kind`` (an index into :data:`echoloc.localise.surfaces.KINDS`) makes of
    ``group``, with class probabilities from the hypotheses' ``scores`` (chi-squares with their
    prices and Schwarz's penalties, each on its own echoes)."""
    refit = robust.refits[kind]
    assert refit is not None
    finite = np.isfinite(scores)
    weights = np.where(finite, np.exp(-0.5 * (scores - scores[kind])), 0.0)
    probability = (weights / weights.sum())[None]
    # describe() reports the likeliest class of its Hypotheses: this one, with these probabilities.
    chi2 = np.where(finite, scores, np.inf)[None]
    found = replace(refit, chi2=chi2, probability=probability)
    surface, position, covariance = surfaces.describe(
        found, 0, group.transmitters_m, group.receivers_m, reference_m
    )
    dof = len(group.paths_m) - surfaces.PARAMETERS[surface.kind]
    fit_chi2 = float(robust.chi2[kind])
    return LocatedObject(
        position_m=np.asarray(position, dtype=float),
        covariance_m2=np.asarray(covariance, dtype=float),
        receivers=group.receivers,
        echo_indices=group.echoes,
        chi2=fit_chi2,
        score=chi2_tail(dof, fit_chi2) if dof > 0 else 1.0,
        transmitters=group.transmitters,
        surface=surface,
    )


def _fit_image(
    receivers_m: FloatArray,
    ranges_m: FloatArray,
    sigmas_m: FloatArray,
    boresight: tuple[float, ...],
    start_m: FloatArray | None = None,
) -> surfaces.Fit:
    """The virtual source at ``ranges_m`` (m,) from ``receivers_m`` (m, 3), fitted compiled from
    ``start_m`` or, without it, from the closed form on the ``boresight``'s side."""
    paths = ranges_m[None]
    if start_m is None:
        ahead = np.asarray(boresight, dtype=float)
        start = surfaces.image_start_m(receivers_m, paths, ahead / np.linalg.norm(ahead))
    else:
        start = start_m[None]
    return surfaces.fit(
        surfaces.mirror_model(receivers_m),
        start,
        paths,
        sigmas_m[None],
        jacobian=surfaces.mirror_jacobian(receivers_m),
        kernel=surfaces.CompiledModel(surfaces.IMAGE_MODEL, receivers_m, receivers_m),
    )


def mirrored_paths_m(
    planes_m: FloatArray,
    point_m: FloatArray,
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    *,
    plane_first: bool,
) -> FloatArray:
    """The double reflections of a point ``point_m`` via planes (n, 3), on channels (m, 3): (n, m), m.

    A plane is ``{x: u.x = h}`` given as ``h u`` (its foot from the origin). Plane first
    (transmitter -> plane -> point -> receiver) the path is ``|P - T'| + |P - R|`` with T' the
    transmitter's image; plane last, ``|P - T| + |P - R'|`` (the image-source method, Allen and
    Berkley 1979).
    """
    normals = planes_m / np.linalg.norm(planes_m, axis=1, keepdims=True)
    tx = _mirror_points(transmitters_m, planes_m, normals) if plane_first else transmitters_m[None]
    rx = receivers_m[None] if plane_first else _mirror_points(receivers_m, planes_m, normals)
    return np.asarray(np.linalg.norm(point_m - tx, axis=-1) + np.linalg.norm(point_m - rx, axis=-1))


def _without_unheard_mirrors(
    objects: list[LocatedObject],
    frames: Sequence[tuple[int, FrameEchoes]],
    newest_t: int,
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    options: LocateOptions,
) -> list[LocatedObject]:
    """``objects`` less the points and corners that are a point's double reflection via a wall
    never heard itself (:func:`_unheard_mirror`); for two or more transmitter positions only (with
    one, a point at the same range as another is such a reflection of it for some plane). Corners
    are tested too: four parameters fit a ghost's echoes better than a point's three, so a ghost
    can come out classed as a corner. Objects are tested nearest first, and only the points
    kept may explain the farther ones: a ghost is never the reflector of another ghost (nor of a
    real corner behind it)."""
    newest_m = transmitters_m[newest_t]
    ranges = np.nan_to_num([float(np.linalg.norm(o.position_m - newest_m)) for o in objects], nan=np.inf)
    order = sorted(range(len(objects)), key=lambda k: float(ranges[k]))
    kept_points: list[LocatedObject] = []
    ghosts: set[int] = set()
    for k in order:
        o = objects[k]
        kind = "point" if o.surface is None else o.surface.kind
        if kind != "plane" and _unheard_mirror(
            o, kept_points, frames, newest_t, transmitters_m, receivers_m, options
        ):
            ghosts.add(k)
        elif kind == "point":
            kept_points.append(o)
    return [o for k, o in enumerate(objects) if k not in ghosts]


def _unheard_mirror(
    o: LocatedObject,
    points: Sequence[LocatedObject],
    frames: Sequence[tuple[int, FrameEchoes]],
    newest_t: int,
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    options: LocateOptions,
) -> bool:
    """Whether an object is a nearer point's double reflection via a plane that made no echo of its own.

    A wall whose foot lies outside it (or beyond the beam) is never heard, but the sound of a
    ball beside it still reaches the receivers via the wall, as if from the ball's mirror image:
    a point (or, its two orders' peaks merged, a corner) that fits no other reflector. Each
    nearer point V is tried as the reflector and the object as its double reflection via a wall,
    first or last (:func:`_mirror_explains`), on the echoes of one transmitter that gave the
    object four or more (the newest frame's if it did) and on the other transmitters' echoes
    where it predicts them.
    """
    newest_first = [newest_t] + [t for t, _ in frames if t != newest_t]
    groups = (_channels_of(o, frames, t, transmitters_m, receivers_m, options) for t in newest_first)
    base = next((g for g in groups if g is not None), None)
    if base is None:
        return False
    base_t = base.transmitters[0]
    kind = "point" if o.surface is None else o.surface.kind
    assert options.resolution_m is not None
    merge = _merge_sigma(options.resolution_m)
    mean_path = float(np.mean(base.paths_m))
    for v in points:
        if v is o:
            continue
        if (
            np.mean(surfaces.point_paths_m(v.position_m[None], base.transmitters_m, base.receivers_m))
            >= mean_path
        ):
            continue
        if np.allclose(o.position_m, v.position_m):
            continue
        if _mirror_explains(
            base,
            o.position_m,
            v.position_m,
            frames,
            base_t,
            transmitters_m,
            receivers_m,
            options,
            merge,
            kind,
        ):
            return True
    return False


def _point_fit(
    near_m: FloatArray, paths_m: FloatArray, sigmas_m: FloatArray, tx: FloatArray, rx: FloatArray
) -> surfaces.Fit:
    """The point that best fits ``paths_m`` on channels (tx, rx), started at ``near_m``."""
    return surfaces.fit(
        lambda p: surfaces.point_paths_m(p, tx, rx),
        near_m[None],
        paths_m[None],
        sigmas_m[None],
        jacobian=lambda p: surfaces.point_jacobian(p, tx, rx),
        kernel=surfaces.CompiledModel(surfaces.POINT_MODEL, tx, rx),
    )


def _echoes_near(
    predict: Callable[[FloatArray], FloatArray],
    frames: Sequence[tuple[int, FrameEchoes]],
    newest_t: int,
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    reach_m: float,
) -> list[tuple[int, int, int]]:
    """The (transmitter, receiver, echo) of the other frames' echoes (all but ``newest_t``'s)
    nearest any of the paths ``predict(transmitters (m, 3))`` gives each receiver ((k, m): k
    alternatives), where within ``reach_m``."""
    found: list[tuple[int, int, int]] = []
    for t, echoes in frames:
        if t == newest_t:
            continue
        c = echoes.speed_of_sound_m_s
        predicted = np.atleast_2d(predict(np.broadcast_to(transmitters_m[t], receivers_m.shape)))
        for r, ch in enumerate(echoes.channels):
            if len(ch.tof_s) == 0 or not np.any(np.isfinite(predicted[:, r])):
                continue
            gap = np.nanmin(np.abs(ch.tof_s[:, None] * c - predicted[None, :, r]), axis=1)
            e = int(np.argmin(gap))
            if gap[e] <= reach_m:
                found.append((t, r, e))
    return found


def _mirror_explains(
    base: _Channels,
    ghost_m: FloatArray,
    point_m: FloatArray,
    frames: Sequence[tuple[int, FrameEchoes]],
    base_t: int,
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    options: LocateOptions,
    merge: float,
    kind: str = "point",
) -> bool:
    """Whether one frame's echoes ``base`` (transmitter ``base_t``) of an object of class ``kind``
    located at ``ghost_m`` are the double reflection of the point ``point_m`` (V) via one plane, wall
    first or last, and the other frames hold its echoes too (:func:`_unheard_mirror`). Both orders
    have closed forms.

    - Wall last (T -> V -> wall -> R): ``l_i - |V - T|`` is the distance from the receiver to V's
      mirror image V', which trilaterates from four receivers; V' does not depend on the
      transmitter, so every frame's echoes must lie at ``|V - T_t| + |V' - R_i|``.
    - Wall first (T -> wall -> V -> R): ``l_i - |V - R_i|`` is ``|V - T'|``, one number per
      transmitter, the same on every receiver: each frame's echoes must give one value on three or
      more receivers.

    Sigmas are widened by a merged peak's; the fit must pass the chi-square gate and beat a point,
    and the object's own class, on the same echoes by :data:`DECISIVE_CHI2`.
    """
    sigma = np.sqrt(base.sigmas_m**2 + merge**2)
    reach = CROSS_CHECK_SIGMAS * merge
    to_receivers = np.linalg.norm(point_m - receivers_m, axis=1)
    others = [(t, echoes) for t, echoes in frames if t != base_t]
    tx_base = base.transmitters_m[0]
    candidates: list[tuple[list[tuple[int, int, int]], bool]] = []  # (echoes, wall last)

    # Wall last: V' from the base frame's echoes, then the other frames' echoes where it puts them.
    ranges = base.paths_m - np.linalg.norm(point_m - tx_base)
    image = _fit_image(base.receivers_m, ranges, sigma, options.boresight)
    v_image = image.parameters[0]
    if np.all(np.isfinite(v_image)) and image.chi2[0] <= _chi2_gate(
        options.gate_probability, len(ranges) - 3
    ):
        extra = _echoes_near(
            lambda tx: np.linalg.norm(point_m - tx[0]) + np.linalg.norm(v_image - receivers_m, axis=1),
            frames,
            base_t,
            transmitters_m,
            receivers_m,
            reach,
        )
        if len(extra) >= 3 and np.linalg.norm(v_image - point_m) > 0:
            candidates.append((extra, True))

    # Wall first: one |V - T'| per frame, shared by the receivers.
    first = base.paths_m - to_receivers[list(base.receivers)]
    weights = 1 / sigma**2
    d_base = float(np.sum(weights * first) / np.sum(weights))
    if d_base > np.linalg.norm(point_m - tx_base) + reach and np.sum(
        weights * (first - d_base) ** 2
    ) <= _chi2_gate(options.gate_probability, len(first) - 1):
        extra = []
        for t, echoes in others:
            c = echoes.speed_of_sound_m_s
            # Longer than V's own echo, |V - T|: sound that went to the wall first.
            direct = float(np.linalg.norm(point_m - transmitters_m[t]))
            values = [
                (r, e, float(ch.tof_s[e] * c - to_receivers[r]))
                for r, ch in enumerate(echoes.channels)
                for e in range(len(ch.tof_s))
            ]
            best: list[tuple[int, int, int]] = []
            values = [(r, e, d) for r, e, d in values if d > direct + reach]
            for _, _, d in values:
                near: dict[int, tuple[int, float]] = {}
                for r, e, other in values:
                    if abs(other - d) <= reach and (r not in near or abs(other - d) < near[r][1]):
                        near[r] = (e, abs(other - d))
                if len(near) > len(best):
                    best = [(t, r, e) for r, (e, _) in sorted(near.items())]
            extra += best
        if len(extra) >= 3:
            candidates.append((extra, False))

    by_tx = dict(frames)
    for extra, wall_last in candidates:
        group = _with_echoes(base, extra, by_tx, transmitters_m, receivers_m, options)
        widened = np.sqrt(group.sigmas_m**2 + merge**2)
        tx, rx = group.transmitters_m, group.receivers_m
        to_tx = np.linalg.norm(point_m - tx, axis=1)
        if wall_last:
            # V' refitted on every channel; the wall (V and V''s bisector) must have the
            # transducers on V's side.
            ranges = group.paths_m - to_tx
            refit = _fit_image(rx, ranges, widened, options.boresight, start_m=v_image)
            ghost_chi2, dof = float(refit.chi2[0]), len(ranges) - 3
            normal = refit.parameters[0] - point_m
            u = normal / np.linalg.norm(normal)
            h = float(u @ (0.5 * (refit.parameters[0] + point_m)))
            if not np.all(np.vstack([transmitters_m, receivers_m]) @ u < h):
                continue
        else:
            values = group.paths_m - np.linalg.norm(point_m - rx, axis=1)
            ghost_chi2, dof = 0.0, len(values)
            for t in set(group.transmitters):
                mine = np.array([k == t for k in group.transmitters])
                w = 1 / widened[mine] ** 2
                d = float(np.sum(w * values[mine]) / np.sum(w))
                ghost_chi2 += float(np.sum(w * (values[mine] - d) ** 2))
                dof -= 1
        if not ghost_chi2 <= _chi2_gate(options.gate_probability, dof):
            continue
        if _rival_chi2(kind, ghost_m, group, widened, tx_base, options) - ghost_chi2 >= DECISIVE_CHI2:
            return True
    return False


def _rival_chi2(
    kind: str,
    near_m: FloatArray,
    group: _Channels,
    sigmas_m: FloatArray,
    reference_m: FloatArray,
    options: LocateOptions,
) -> float:
    """The best chi-square of a point, or for a corner of a point, a plane or a corner (a corner
    whose edge runs along the transmitters' baseline is the plane's twin), on the group's echoes
    (sigmas ``sigmas_m``): what a ghost explanation of them must beat."""
    tx, rx = group.transmitters_m, group.receivers_m
    if kind != "corner":
        return float(_point_fit(near_m, group.paths_m, sigmas_m, tx, rx).chi2[0])
    fitted = surfaces.hypotheses(
        tx,
        rx,
        group.paths_m[None],
        sigmas_m[None],
        reference_m,
        near_m[None],
        options.gate_probability,
        corner_mode="always",
    )
    return float(np.min(fitted.chi2[0]))  # the point's, the plane's and the corner's


def _seen_by_others(
    o: LocatedObject,
    frames: Sequence[tuple[int, FrameEchoes]],
    newest_t: int,
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
) -> bool:
    """Whether a point echoes to every other transmitter: three or more of its channels come
    from that transmitter's frame, or that frame has echoes within :data:`MOVED_M` of its
    paths on three channels.

    A real reflector echoes to every transmitter; if it moved between the frames the
    association leaves the older frame out (or takes a channel or two of it by chance), but
    its echoes are still near. A point seen through an unheard wall (the receivers' mirror
    images) lies elsewhere for another transmitter, and its older echoes are not there.
    Planes and corners pass.
    """
    if o.surface is not None and o.surface.kind != "point":
        return True
    own = _channel_transmitters(o, frames)
    for t, echoes in frames:
        if t == newest_t or sum(k == t for k in own) >= 3:
            continue
        predicted = surfaces.point_paths_m(
            o.position_m[None], np.broadcast_to(transmitters_m[t], receivers_m.shape), receivers_m
        )[0]
        c = echoes.speed_of_sound_m_s
        near = sum(
            bool(np.any(np.abs(ch.tof_s * c - predicted[r]) <= MOVED_M))
            for r, ch in enumerate(echoes.channels)
        )
        if near < 3:
            return False
    return True


def _used_echoes(
    objects: Sequence[LocatedObject], frames: Sequence[tuple[int, FrameEchoes]]
) -> dict[int, set[tuple[int, int]]]:
    """The (receiver, echo) pairs each transmitter's frame lends to ``objects``."""
    used: dict[int, set[tuple[int, int]]] = {t: set() for t, _ in frames}
    for o in objects:
        for t, r, e in zip(_channel_transmitters(o, frames), o.receivers, o.echo_indices, strict=True):
            used[t].add((r, e))
    return used


def _as_mirror_group(
    o: LocatedObject,
    frames: Sequence[tuple[int, FrameEchoes]],
    newest_t: int,
    transmitters_m: FloatArray,
    options: LocateOptions,
) -> MirrorGroup | None:
    """A point the association found that may be a mirror, as a mirror group of its newest-frame
    channels to pair with the other transmitters' (None for anything else): one found on the
    newest frame alone that a plane fits nearly as well, or one whose older-frame support may be
    stray echoes that made a plane look like a point."""
    if len(frames) == 1 or o.surface is None or o.surface.kind != "point":
        return None
    tx_of = _channel_transmitters(o, frames)
    own = [k for k, t in enumerate(tx_of) if t == newest_t]
    if len(own) < 4 or (
        len(own) == len(tx_of) and o.surface.probabilities.get("plane", 0.0) < MIRROR_CANDIDATE
    ):
        return None
    paths, sigmas = _group_paths(o, tx_of, frames, options)
    image = 2 * o.position_m - transmitters_m[newest_t]  # a point's position is near the foot
    receivers = tuple(o.receivers[k] for k in own)
    echoes = tuple(o.echo_indices[k] for k in own)
    return MirrorGroup(newest_t, receivers, echoes, paths[own], sigmas[own], image)


def _channel_transmitters(o: LocatedObject, frames: Sequence[tuple[int, FrameEchoes]]) -> list[int]:
    """The transmitter of each of an object's channels: its own record when several frames were
    combined, else the one frame's transmitter (a single frame's locator numbers it 0)."""
    if len(frames) == 1:
        return [frames[0][0]] * len(o.receivers)
    return list(o.transmitters)


def _classified(
    objects: Sequence[LocatedObject],
    frames: Sequence[tuple[int, FrameEchoes]],
    newest_t: int,
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    options: LocateOptions,
    alternatives: list[tuple[LocatedObject, LocatedObject]],
) -> list[LocatedObject]:
    """Point objects with their classes: each as located when a point is likeliest, else as the
    plane or corner its echoes fit decisively better. A point kept as such although a plane or
    corner fits it best is appended to ``alternatives`` with that fit, (object, fit): a double
    reflection off it may take that shape (:func:`_explained_away`). The list holds the objects
    themselves, so an entry can never name another object later."""
    if not objects:
        return []
    groups = []
    transmitters_of = []
    for o in objects:
        tx_of = _channel_transmitters(o, frames)
        transmitters_of.append(tuple(tx_of))
        paths, sigmas = _group_paths(o, tx_of, frames, options)
        groups.append(
            _Channels(
                transmitters_m[tx_of],
                receivers_m[list(o.receivers)],
                paths,
                sigmas,
                tuple(tx_of),
                o.receivers,
                o.echo_indices,
            )
        )
    starts = np.array([o.position_m for o in objects])
    fitted = _objects_of(groups, newest_t, transmitters_m, starts, options, [o.shared for o in objects])
    classified = []
    for o, f, channel_transmitters in zip(objects, fitted, transmitters_of, strict=True):
        if f is None or f.surface is None:
            # No hypothesis could be fitted beside the association's point.
            classified.append(replace(o, transmitters=channel_transmitters, surface=_UNTESTED))
        elif f.surface.kind == "point" or not _decisive(f.surface) or not _fits(f, options):
            # A point, or a mirror that does not explain the echoes decisively better: the
            # association's own fit stays the answer (shared echoes weighted as it weighs them).
            surface = f.surface
            if surface.kind != "point":
                surface = replace(surface, kind="point", confidence=surface.probabilities["point"])
                surface = replace(surface, normal=None, normal_covariance=None, distance_m=None)
                surface = replace(surface, distance_std_m=None, specular_points_m=None, extent_m=None)
                surface = replace(surface, edge_direction=None, edge_covariance=None)
            kept = replace(o, transmitters=channel_transmitters, surface=surface)
            if f.surface.kind != "point":
                alternatives.append((kept, f))
            classified.append(kept)
        else:
            classified.append(replace(f, score=o.score))
    return classified


def _fits(o: LocatedObject, options: LocateOptions) -> bool:
    """Whether an object's fit passes the chi-square gate for its degrees of freedom."""
    assert o.surface is not None
    dof = len(o.receivers) - surfaces.PARAMETERS[o.surface.kind]
    return dof <= 0 or o.chi2 <= _chi2_gate(options.gate_probability, dof)


def classify_points(
    objects: Sequence[LocatedObject],
    frames: Sequence[tuple[int, FrameEchoes]],
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    options: LocateOptions,
) -> list[LocatedObject]:
    """Objects the point association found outside :func:`locate_with_classes` (a clipped
    channel's re-read), classified as it classifies its own."""
    newest_t = max(frames, key=lambda f: f[1].frame)[0]
    return _classified(objects, frames, newest_t, transmitters_m, receivers_m, options, [])


def _decisive(surface: surfaces.Surface) -> bool:
    """Whether a plane or corner explains a point association's echoes decisively better than the
    point: by a likelihood ratio of at least exp(DECISIVE_CHI2 / 2), with Schwarz's penalty."""
    point = surface.probabilities.get("point", 0.0)
    return surface.confidence >= point * math.exp(0.5 * DECISIVE_CHI2)


def _group_paths(
    o: LocatedObject, tx_of: list[int], frames: Sequence[tuple[int, FrameEchoes]], options: LocateOptions
) -> tuple[FloatArray, FloatArray]:
    """The paths and sigmas (m) of an object's echoes."""
    by_tx = dict(frames)
    paths, sigmas = [], []
    for t, r, e in zip(tx_of, o.receivers, o.echo_indices, strict=True):
        ch = by_tx[t].channels[r]
        c = by_tx[t].speed_of_sound_m_s
        paths.append(ch.tof_s[e] * c)
        sigmas.append(float(path_sigmas_m(ch.snr_db[e : e + 1], c, options)[0]))
    return np.array(paths), np.array(sigmas)


def _mirror_points(points_m: FloatArray, feet_m: FloatArray, normals: FloatArray) -> FloatArray:
    """``points_m`` (m, 3) mirrored in each plane (feet and normals (L, 3)): (L, m, 3)."""
    height = np.einsum("lmk,lk->lm", points_m[None] - feet_m[:, None], normals)
    return np.asarray(points_m[None] - 2 * height[..., None] * normals[:, None])


def _double_reflections(
    points_m: FloatArray, feet_m: FloatArray, normals: FloatArray, tx: FloatArray, rx: FloatArray
) -> FloatArray:
    """Every double reflection's path on the channels (tx, rx) (m, 3): (N, m).

    Between two different points A, B: ``|A - T| + |B - A| + |B - R|``; a plane then a point
    B: ``|B - T'| + |B - R|`` (T' the transmitter's image); a point A then a plane:
    ``|A - T| + |A - R'|`` (the receiver's image); a plane then another: ``|T'' - R|``
    (the image of the image), except for two planes within 10 degrees of a right angle,
    whose double bounce is the corner they make (reported as such, not a ghost). Points
    (K, 3); planes by their feet and normals (L, 3). Corners make none of their own: their
    double bounce is their echo.
    """
    m = len(tx)
    parts = [np.zeros((0, m))]
    if len(points_m) >= 2:
        to_tx = np.linalg.norm(points_m[:, None] - tx[None], axis=-1)  # (K, m)
        to_rx = np.linalg.norm(points_m[:, None] - rx[None], axis=-1)
        between = np.linalg.norm(points_m[:, None] - points_m[None], axis=-1)  # (K, K)
        first, second = np.nonzero(~np.eye(len(points_m), dtype=bool))
        parts.append(to_tx[first] + between[first, second][:, None] + to_rx[second])
    if len(feet_m) and len(points_m):
        tx_images = _mirror_points(tx, feet_m, normals)  # (L, m, 3)
        rx_images = _mirror_points(rx, feet_m, normals)
        to_rx = np.linalg.norm(points_m[:, None] - rx[None], axis=-1)  # (K, m)
        to_tx = np.linalg.norm(points_m[:, None] - tx[None], axis=-1)
        plane_first = np.linalg.norm(points_m[None, :, None] - tx_images[:, None], axis=-1) + to_rx[None]
        plane_last = to_tx[None] + np.linalg.norm(points_m[None, :, None] - rx_images[:, None], axis=-1)
        parts += [plane_first.reshape(-1, m), plane_last.reshape(-1, m)]
    if len(feet_m) >= 2:
        tx_images = _mirror_points(tx, feet_m, normals)  # (L, m, 3)
        for i, j in zip(*np.nonzero(~np.eye(len(feet_m), dtype=bool)), strict=True):
            if abs(float(normals[i] @ normals[j])) < CORNER_COSINE:
                continue  # two walls at a right angle: their double bounce is the corner's own echo
            twice = _mirror_points(tx_images[i], feet_m[j : j + 1], normals[j : j + 1])[0]
            parts.append(np.linalg.norm(twice - rx, axis=-1)[None])
    return np.asarray(np.concatenate(parts))


def _versions(
    o: LocatedObject, alternatives: Sequence[tuple[LocatedObject, LocatedObject]]
) -> list[LocatedObject]:
    """The object, and the plane or corner it could also be."""
    return [o, *(other for kept, other in alternatives if kept is o)]


def _primitives(
    kept: Sequence[LocatedObject], alternatives: Sequence[tuple[LocatedObject, LocatedObject]]
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The points (K, 3) and the planes' feet and normals (L, 3) of settled objects, with the
    plane each point might also be."""
    points, feet, normals = [], [], []
    for o in kept:
        for version in _versions(o, alternatives):
            surface = version.surface
            if surface is None or surface.kind == "point":
                points.append(version.position_m)
            elif surface.kind == "plane" and surface.normal is not None:
                feet.append(version.position_m)
                normals.append(surface.normal)
    return (
        np.array(points, dtype=float).reshape(-1, 3),
        np.array(feet, dtype=float).reshape(-1, 3),
        np.array(normals, dtype=float).reshape(-1, 3),
    )


def _explained_away(
    objects: list[LocatedObject],
    frames: Sequence[tuple[int, FrameEchoes]],
    transmitters_m: FloatArray,
    receivers_m: FloatArray,
    options: LocateOptions,
    alternatives: Sequence[tuple[LocatedObject, LocatedObject]],
) -> list[LocatedObject]:
    """``objects`` less those whose echoes others with shorter paths explain as double
    reflections: ghosts, not reflectors. The objects come back shortest mean path first. An
    object with an alternative (a plane it was not decisively told from) explains as either.

    Each channel's echo is compared with the nearest of every double reflection between the
    settled objects, in either order (:func:`_double_reflections`; a ghost's echoes may mix
    several, since each receiver hears the nearest), within the chi-square gate over the
    object's channels. A double reflection overlaps other echoes
    often, so each channel's sigma includes that of a merged peak (the association's
    ``resolution_m / (4 sqrt 3)``). A double reflection is longer than either reflector's own
    echo, so the objects are settled in order of their mean path, and only those settled can
    explain a later one.
    """
    merge = 0.0 if options.resolution_m is None else _merge_sigma(options.resolution_m)
    measured = []
    for o in objects:
        tx_of = _channel_transmitters(o, frames)
        measured.append((o, tx_of, *_group_paths(o, tx_of, frames, options)))
    newest_t = max(frames, key=lambda f: f[1].frame)[0]
    measured.sort(key=lambda m: float(np.mean(m[2])))
    kept: list[LocatedObject] = []
    for o, tx_of, observed, sigma in measured:
        # The newest frame's channels: older frames only lend support, and may hold other echoes there.
        own = (
            np.array([t == newest_t for t in tx_of])
            if sum(t == newest_t for t in tx_of) >= 3
            else np.ones(len(tx_of), bool)
        )
        # An echo a settled object took too (a merged peak the association shared) is that
        # object's; the rest must be double reflections for this one to be a ghost.
        settled = {
            (t, r, e)
            for k in kept
            for t, r, e in zip(_channel_transmitters(k, frames), k.receivers, k.echo_indices, strict=True)
        }
        borrowed = np.array(
            [(t, r, e) in settled for t, r, e in zip(tx_of, o.receivers, o.echo_indices, strict=True)]
        )
        rest = own & ~borrowed
        if rest.sum() < 2:
            rest = own  # too little of its own to judge on: as before, on all its channels
        observed, sigma = observed[rest], sigma[rest]
        tx, rx = transmitters_m[np.array(tx_of)[rest]], receivers_m[np.array(o.receivers)[rest]]
        if not _double_reflection(observed, sigma, merge, kept, alternatives, tx, rx, options):
            kept.append(o)
    return kept


def _double_reflection(
    observed: FloatArray,
    sigma: FloatArray,
    merge: float,
    kept: Sequence[LocatedObject],
    alternatives: Sequence[tuple[LocatedObject, LocatedObject]],
    tx: FloatArray,
    rx: FloatArray,
    options: LocateOptions,
) -> bool:
    """Whether the double reflections between ``kept`` explain the paths ``observed`` (sigma ``sigma``):
    one pair's, in either order per channel, with every sigma widened by a merged peak's
    ``merge``; or the nearest of all of them per channel (a ghost may mix several pairs), within
    the plain sigmas but for the worst channel, which is widened. With many objects many double
    reflections lie about, so the mixture must fit tighter than one pair."""
    gate = _chi2_gate(options.gate_probability, len(observed))
    widened = np.sqrt(sigma**2 + merge**2)
    points, feet, normals = _primitives(kept, alternatives)
    predicted = _double_reflections(points, feet, normals, tx, rx)
    if not len(predicted):
        return False
    nearest = np.min(np.abs(predicted - observed), axis=0)
    mixed = (nearest / sigma) ** 2
    worst = int(np.argmax(mixed))
    mixed[worst] = (nearest[worst] / widened[worst]) ** 2
    if np.sum(mixed) <= gate:
        return True
    for i, first in enumerate(kept):
        for second in kept[i + 1 :]:
            for a in _versions(first, alternatives):
                for b in _versions(second, alternatives):
                    p_a, f_a, n_a = _primitives([a], ())
                    p_b, f_b, n_b = _primitives([b], ())
                    pair = _double_reflections(
                        np.vstack([p_a, p_b]), np.vstack([f_a, f_b]), np.vstack([n_a, n_b]), tx, rx
                    )
                    if len(pair) and np.sum((np.min(np.abs(pair - observed), axis=0) / widened) ** 2) <= gate:
                        return True
    return False
