"""Multi-pose triangulation: ellipsoid geometry, fits that give the truth back, tracks that
follow their reflector, and what a track must not place (a stationary sensor, a wall)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording
from echoloc.localise.locate import FrameObjects, LocatedObject
from echoloc.maps.mapping import GridSpec, MapAccumulator, SensorModel
from echoloc.maps.triangulation import Arc, ArcTracker, TrackOptions, fit_track, on_ellipsoid_m
from echoloc.tof.echoes import ChannelEchoes, FrameEchoes

C = 343.0
AHEAD = np.array([0.0, 0.0, 1.0])
BEAM = math.radians(20.0)
RECEIVER_OFFSET_M = np.array([0.25, 0.0, 0.0])
IN_THE_SLICE = {1: 0.0}
"""A floor plan at the sensor's height: the fit holds y at 0."""


def _path_m(point: np.ndarray, transmitter: np.ndarray, receiver: np.ndarray) -> float:
    return float(np.linalg.norm(point - transmitter) + np.linalg.norm(point - receiver))


def _sliding_arcs(
    point: np.ndarray,
    n: int,
    step_m: float,
    sigma_m: float = 0.0,
    seed: int = 0,
    bob_m: float = 0.0,
    first_frame: int = 0,
    every: int = 1,
) -> list[Arc]:
    """A sensor (transmitter, and one receiver 25 cm to its right) sliding along x by
    ``step_m`` a frame, bobbing up and down by ``bob_m``, looking ahead; each of its ``n``
    firings (every ``every`` frames) the path to ``point`` plus noise."""
    rng = np.random.default_rng(seed)
    arcs = []
    for k in range(n):
        transmitter = np.array([step_m * (k - n / 2), bob_m * math.sin(k / 5), 0.0])
        receiver = transmitter + RECEIVER_OFFSET_M
        path = _path_m(point, transmitter, receiver) + sigma_m * rng.standard_normal()
        arcs.append(Arc(first_frame + every * k, transmitter, receiver, path, AHEAD))
    return arcs


def _fit(arcs: list[Arc], sigma: float = 0.001, fixed: dict[int, float] | None = None, **options: float):
    return fit_track(
        arcs,
        TrackOptions(**options),
        half_angle_rad=BEAM,
        path_sigma_m=sigma,
        fixed=fixed,  # type: ignore[arg-type]
    )


def _track(
    frames: list[tuple[int, list[Arc]]],
    sigma: float = 0.001,
    channel: tuple[int, int] = (0, 0),
    by_firing: bool = False,
    **options: float,
):
    tracker = ArcTracker(
        TrackOptions(**options),  # type: ignore[arg-type]
        half_angle_rad=BEAM,
        path_sigma_m=sigma,
        fixed=IN_THE_SLICE,
    )
    placed = []
    for n, (frame, arcs) in enumerate(frames):
        placed += tracker.add(frame, {channel: arcs}, firing=n if by_firing else None)
    return placed + tracker.finish()


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.floats(-1, 1), min_size=3, max_size=3),
    st.lists(st.floats(-1, 1), min_size=3, max_size=3),
    st.floats(0.05, 3.0),
    st.lists(st.floats(-1, 1), min_size=3, max_size=3),
)
def test_points_placed_on_an_ellipsoid_have_its_path(transmitter, receiver, excess_m, direction) -> None:
    """``rho = (L^2 - |d|^2) / (2 (L - u . d))`` puts ``T + rho u`` on ``|p - T| + |p - R| = L``
    whatever the foci and the direction."""
    transmitter, receiver, direction = map(np.asarray, (transmitter, receiver, direction))
    if np.linalg.norm(direction) < 1e-3:
        return
    path = float(np.linalg.norm(receiver - transmitter)) + excess_m
    unit = direction / np.linalg.norm(direction)
    point = on_ellipsoid_m(transmitter, receiver, path, unit[None, :])[0]
    assert _path_m(point, transmitter, receiver) == pytest.approx(path, rel=1e-9, abs=1e-9)
    assert (point - transmitter) @ unit > 0  # along u, not behind the transmitter


@pytest.mark.parametrize("seed", range(4))
def test_a_track_in_a_slice_gives_the_reflector_back_within_its_covariance(seed: int) -> None:
    """40 frames, 4 mm apart, of a reflector 1.2 m away heard by one receiver, fitted in the
    slice at its height: the truth within the stated uncertainty (Mahalanobis distance,
    chi-square with 2 degrees of freedom, 99.9 %: 13.8), residuals the noise's, the height
    held."""
    truth = np.array([0.3, 0.0, 1.2])
    point = _fit(_sliding_arcs(truth, 40, 0.004, 0.001, seed), fixed=IN_THE_SLICE, max_std_m=0.05)
    assert point is not None
    plan = [0, 2]
    offset = (point.position_m - truth)[plan]
    assert offset @ np.linalg.solve(point.covariance_m2[np.ix_(plan, plan)], offset) < 13.8
    assert 0.3 < point.reduced_chi2 < 2.0
    assert point.position_m[1] == 0.0
    assert np.all(point.covariance_m2[1] == 0.0)
    assert (point.n_arcs, point.first_frame, point.last_frame) == (40, 0, 39)


@pytest.mark.parametrize("seed", range(3))
def test_a_track_that_also_moved_up_and_down_fixes_the_reflector_in_space(seed: int) -> None:
    """Foci that leave a line (the sensor bobs 5 cm) fix all three coordinates: the truth
    within the 3-D covariance (chi-square with 3 degrees of freedom, 99.9 %: 16.3)."""
    truth = np.array([0.3, -0.1, 1.2])
    point = _fit(_sliding_arcs(truth, 60, 0.004, 0.0005, seed, bob_m=0.05), sigma=0.0005, max_std_m=0.05)
    assert point is not None
    offset = point.position_m - truth
    assert offset @ np.linalg.solve(point.covariance_m2, offset) < 16.3


def test_foci_on_one_line_leave_a_circle_and_place_nothing_in_space() -> None:
    """Sliding along the line through the transmitter and the receiver, every ellipsoid is
    symmetric about that line: the point could be anywhere on a circle about it. In space
    that is no point; in a slice it is (the slice cuts the circle)."""
    arcs = _sliding_arcs(np.array([0.3, 0.0, 1.2]), 40, 0.004)
    assert _fit(arcs, max_std_m=1.0) is None
    assert _fit(arcs, fixed=IN_THE_SLICE) is not None


def test_a_stationary_sensor_places_nothing() -> None:
    """The same ellipsoid every frame fixes one direction only: no point, however long."""
    arcs = _sliding_arcs(np.array([0.1, 0.0, 1.0]), 60, 0.0)
    assert _fit(arcs, fixed=IN_THE_SLICE, max_std_m=1.0) is None


def test_a_wall_parallel_to_the_motion_is_no_point() -> None:
    """A wall's echo comes from the transmitter's mirror image (path ``|T' - R|``): sliding along
    the wall, the paths stay the same and the ellipsoids, shifted, share no point (the
    chi-square rejects it, not the uncertainty)."""
    wall_z = 1.5
    arcs = []
    for k in range(40):
        transmitter = np.array([0.01 * k - 0.2, 0.0, 0.0])
        receiver = transmitter + RECEIVER_OFFSET_M
        image = transmitter * [1, 1, -1] + [0, 0, 2 * wall_z]
        arcs.append(Arc(k, transmitter, receiver, float(np.linalg.norm(image - receiver)), AHEAD))
    assert _fit(arcs, fixed=IN_THE_SLICE, max_std_m=1.0) is None
    assert _fit(arcs, fixed=IN_THE_SLICE, max_std_m=1.0, max_reduced_chi2=1e9) is not None


def test_values_no_fit_can_use_place_nothing_and_bad_options_are_refused() -> None:
    arcs = _sliding_arcs(np.array([0.3, 0.0, 1.2]), 40, 0.004)
    broken = [*arcs[:20], Arc(20, arcs[20].transmitter_m, arcs[20].receiver_m, math.nan, AHEAD), *arcs[21:]]
    assert _fit(broken, fixed=IN_THE_SLICE) is None
    assert fit_track(arcs, TrackOptions(), half_angle_rad=math.nan, path_sigma_m=0.001) is None
    for bad in (0.0, math.nan, -1.0):
        with pytest.raises(EchoLocError, match="path_sigma_m"):
            ArcTracker(TrackOptions(), half_angle_rad=BEAM, path_sigma_m=bad)
    for options, name in (
        ({"min_arcs": 3}, "min_arcs"),
        ({"min_arcs": 4.5}, "min_arcs"),
        ({"min_arcs": "12"}, "min_arcs"),
        ({"max_gap_frames": math.nan}, "max_gap_frames"),
        ({"max_arcs": math.inf}, "max_arcs"),
        ({"min_arcs": 50, "max_arcs": 40}, "min_arcs"),
        ({"gate_m": 0.0}, "gate_m"),
        ({"max_std_m": math.nan}, "max_std_m"),
        ({"max_reduced_chi2": True}, "max_reduced_chi2"),
    ):
        with pytest.raises(EchoLocError, match=name):
            TrackOptions(**options)  # type: ignore[arg-type]


def test_two_reflectors_on_one_channel_make_two_tracks_through_missed_frames() -> None:
    """Two reflectors on the same channel, one missed every third frame (within the gap the
    tracker bridges): two tracks, each fitted to its own reflector."""
    near, far = np.array([-0.2, 0.0, 0.9]), np.array([0.3, 0.0, 1.4])
    frames = [
        (n.frame, [f] if n.frame % 3 == 2 else [f, n])
        for n, f in zip(_sliding_arcs(near, 50, 0.005), _sliding_arcs(far, 50, 0.005), strict=True)
    ]
    placed = sorted(_track(frames), key=lambda p: p.position_m[2])
    assert len(placed) == 2
    np.testing.assert_allclose(placed[0].position_m, near, atol=1e-4)
    np.testing.assert_allclose(placed[1].position_m, far, atol=1e-4)
    assert sorted(p.n_arcs for p in placed) == [34, 50]


def test_a_track_does_not_resume_across_a_jump_in_the_frames() -> None:
    """Frames 0-39 hear one post, frames 1000-1039 (the input skipped the rest) another whose
    path starts where the first's ended: two tracks, two posts, not one track that fits
    neither."""
    first = np.array([0.3, 0.0, 1.2])
    arcs_a = _sliding_arcs(first, 40, 0.004)
    # A second post, at the first's last path from the sensor's first pose after the jump.
    arcs_b = _sliding_arcs(np.array([0.0, 0.0, 1.0]), 40, 0.004, first_frame=1000)
    scale = arcs_a[-1].path_m / arcs_b[0].path_m
    second = np.array([0.0, 0.0, 1.0]) * scale
    arcs_b = _sliding_arcs(second, 40, 0.004, first_frame=1000)
    assert abs(arcs_b[0].path_m - arcs_a[-1].path_m) < 0.01
    placed = sorted(_track([(a.frame, [a]) for a in arcs_a + arcs_b]), key=lambda p: p.first_frame)
    assert [p.first_frame for p in placed] == [0, 1000]
    np.testing.assert_allclose(placed[0].position_m, first, atol=1e-4)
    np.testing.assert_allclose(placed[1].position_m, second, atol=1e-4)


def test_a_channel_firing_every_fifth_frame_keeps_its_track() -> None:
    """Five transmitters fired in turn: a channel hears every fifth frame, and its track
    still gathers every arc (misses are counted in the channel's firings, not in frames);
    counted in frames, four of five would be missed and the track would end at once."""
    truth = np.array([0.3, 0.0, 1.2])
    arcs = _sliding_arcs(truth, 40, 0.02, first_frame=3, every=5)
    assert _track([(a.frame, [a]) for a in arcs], channel=(3, 0)) == []
    placed = _track([(a.frame, [a]) for a in arcs], channel=(3, 0), by_firing=True)
    assert len(placed) == 1
    assert (placed[0].n_arcs, placed[0].channel) == (40, (3, 0))
    np.testing.assert_allclose(placed[0].position_m, truth, atol=1e-4)


def test_noise_as_large_as_the_path_sigma_does_not_split_a_track() -> None:
    """2 mm of path noise with a 2 mm path sigma: one reflector, one track, every arc."""
    truth = np.array([0.3, 0.0, 1.2])
    placed = _track([(a.frame, [a]) for a in _sliding_arcs(truth, 80, 0.005, 0.002, 7)], sigma=0.002)
    assert [p.n_arcs for p in placed] == [80]
    assert np.linalg.norm(placed[0].position_m - truth) < 0.02


def test_a_track_longer_than_max_arcs_is_fitted_in_pieces() -> None:
    """max_arcs 20 on 45 arcs: 20 arcs, then 20 (the restart keeps the last two arcs, which
    keep the rate), then 9 left: too few."""
    truth = np.array([0.0, 0.0, 1.0])
    placed = _track([(a.frame, [a]) for a in _sliding_arcs(truth, 45, 0.005)], min_arcs=10, max_arcs=20)
    assert [p.n_arcs for p in placed] == [20, 20]
    for p in placed:
        np.testing.assert_allclose(p.position_m, truth, atol=1e-4)


# --- in the map --------------------------------------------------------------------------------

POST_M = np.array([0.21, 0.0, 1.21])
"""At a cell's centre in both grids below."""
RECEIVERS_M = np.array([[0.25, 0.0, 0.0], [-0.25, 0.0, 0.0]])


def _drive(
    spec: GridSpec, tracks: TrackOptions | None, *, bob_m: float = 0.0, claimed: bool = False
) -> MapAccumulator:
    """A sensor driving along x (and bobbing up and down by ``bob_m``) past a post 1.2 m ahead
    that only its right receiver hears (the left one hears nothing, so no frame can place
    it). ``claimed``: a located object uses that echo every frame."""
    recording = Recording(
        sample_rate_hz=200e3,
        transmitters_m=np.zeros((1, 3)),
        receivers_m=RECEIVERS_M,
        frames=np.zeros((1, 2, 2400)),
        speed_of_sound_m_s=C,
        field_of_view_deg=20.0,
    )
    accumulator = MapAccumulator(spec, recording, SensorModel(tracks=tracks))
    for k in range(60):
        where = np.array([0.005 * (k - 30), bob_m * math.sin(k / 5), 0.0])
        heard = _path_m(POST_M, where, RECEIVERS_M[0] + where)
        echoes = FrameEchoes(
            k,
            k / 100,
            C,
            (ChannelEchoes(np.array([heard / C]), np.ones(1), np.full(1, 30.0)), ChannelEchoes.empty()),
        )
        objects = None
        if claimed:
            somewhere = LocatedObject(POST_M - where, np.eye(3) * 1e-6, (0,), (0,), 0.0, 1.0)
            objects = FrameObjects(k, k / 100, (somewhere,))
        accumulator.add_frame(echoes, np.array([*where, 0.0, 0.0, 0.0, 1.0]), objects=objects)
    accumulator.finish_tracks()
    return accumulator


def _post_log_odds(accumulator: MapAccumulator) -> float:
    index, _ = accumulator.spec.cell_indices([POST_M])
    return float(accumulator.grid().log_odds[tuple(index[0])])


FLOOR = GridSpec.floor_plan((-1.0, 1.0), (0.0, 2.0), 0.02)
BOX = GridSpec.box([-1.0, -0.51, 0.0], [1.0, 0.51, 2.0], 0.02)


def test_the_map_marks_a_post_one_receiver_heard_only_when_tracks_place_it() -> None:
    placed = _drive(FLOOR, TrackOptions())
    assert placed.n_triangulated == 1
    assert _post_log_odds(placed) > 0
    assert _post_log_odds(_drive(FLOOR, None)) <= 0


def test_echoes_a_located_object_used_are_not_tracked() -> None:
    assert _drive(FLOOR, TrackOptions(), claimed=True).n_triangulated == 0


def test_a_3d_map_marks_a_post_only_when_the_motion_fixed_its_height() -> None:
    """Driving level, every focus lies on one line: the post's height is unknown and a 3-D
    grid is not marked (it would be a ring). Bobbing 5 cm up and down fixes it."""
    level = _drive(BOX, TrackOptions())
    assert level.n_triangulated == 0
    assert _post_log_odds(level) <= 0
    bobbing = _drive(BOX, TrackOptions(), bob_m=0.05)
    assert bobbing.n_triangulated == 1
    assert _post_log_odds(bobbing) > 0


def test_frames_after_the_tracks_are_finished_are_mapped_in_full() -> None:
    """finish_tracks marks cells in a step of its own: the next frame's evidence at those
    cells is added, not skipped as if already counted."""
    accumulator = _drive(FLOOR, TrackOptions())
    before = _post_log_odds(accumulator)
    assert before > 0
    # The sensor straight in front of the post, hearing only a wall far behind it: the
    # post's cell lies before every first echo, inside both beams, and is cleared.
    where = np.array([POST_M[0], 0.0, 0.0])
    wall = 2 * 1.9
    echoes = FrameEchoes(
        60, 0.6, C, tuple(ChannelEchoes(np.array([wall / C]), np.ones(1), np.full(1, 30.0)) for _ in range(2))
    )
    accumulator.add_frame(echoes, np.array([*where, 0.0, 0.0, 0.0, 1.0]))
    assert _post_log_odds(accumulator) < before - 0.1


def test_a_firing_seen_twice_adds_nothing_and_an_input_that_goes_back_ends_the_tracks() -> None:
    truth = np.array([0.3, 0.0, 1.2])
    arcs = _sliding_arcs(truth, 40, 0.004, 0.001, 3)
    doubled = [(a.frame, [a]) for a in arcs for _ in range(2)]
    assert [p.n_arcs for p in _track(doubled)] == [40]
    back = [(a.frame, [a]) for a in arcs[:20]] + [(a.frame, [a]) for a in arcs[:20]]
    assert [p.n_arcs for p in _track(back)] == [20, 20]


def test_a_mirror_image_as_good_as_the_reflector_places_nothing() -> None:
    """Driving straight ahead with the receiver 25 cm right of the transmitter, every
    ellipsoid is symmetric about the plane halfway between them (x = 12.5 cm): the post
    5 cm right of the transmitter and its mirror image at 20 cm fit the paths alike. The
    track is ambiguous and places nothing; the same post seen from a drive across the beam
    is placed."""
    post = np.array([0.05, 0.0, 1.2])
    ahead = []
    for k in range(40):
        transmitter = np.array([0.0, 0.0, 0.01 * k])
        receiver = transmitter + RECEIVER_OFFSET_M
        ahead.append(Arc(k, transmitter, receiver, _path_m(post, transmitter, receiver), AHEAD))
    mirror = np.array([0.2, 0.0, 1.2])
    assert [_path_m(mirror, a.transmitter_m, a.receiver_m) for a in ahead] == pytest.approx(
        [a.path_m for a in ahead]
    )
    assert _fit(ahead, fixed=IN_THE_SLICE) is None
    across = _fit(_sliding_arcs(post, 40, 0.004), fixed=IN_THE_SLICE)
    assert across is not None
    np.testing.assert_allclose(across.position_m, post, atol=1e-4)


def test_a_reflector_above_the_slice_is_not_placed_in_it_when_the_motion_fixes_its_height() -> None:
    """Bobbing 2 mm fixes the height: a post 30 cm above the slice still fits the slice (at its
    slant range, 3.7 cm too far), and only the refit in space shows it is not there. A
    post in the slice is placed."""
    above = np.array([0.3, -0.3, 1.2])
    arcs = _sliding_arcs(above, 60, 0.004, 0.0005, 2, bob_m=0.002)
    assert _fit(arcs, sigma=0.0005, fixed=IN_THE_SLICE, max_std_m=0.05) is None
    level = np.array([0.3, 0.0, 1.2])
    arcs = _sliding_arcs(level, 60, 0.004, 0.0005, 2, bob_m=0.002)
    placed = _fit(arcs, sigma=0.0005, fixed=IN_THE_SLICE, max_std_m=0.05)
    assert placed is not None
    np.testing.assert_allclose(placed.position_m, level, atol=0.005)
