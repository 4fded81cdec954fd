"""Multi-pose triangulation: ellipsoid geometry, fits that give the truth back, and what a
track must not place (a stationary sensor, a wall)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from echoloc.errors import EchoLocError
from echoloc.io.recording import Recording
from echoloc.maps.mapping import GridSpec, MapAccumulator, SensorModel
from echoloc.maps.triangulation import Arc, ArcTracker, TrackOptions, fit_track, on_ellipsoid_m
from echoloc.tof.echoes import ChannelEchoes, FrameEchoes

C = 343.0
AHEAD = np.array([0.0, 0.0, 1.0])
BEAM = math.radians(20.0)
RECEIVER_OFFSET_M = np.array([0.25, 0.0, 0.0])


def _path_m(point: np.ndarray, transmitter: np.ndarray, receiver: np.ndarray) -> float:
    return float(np.linalg.norm(point - transmitter) + np.linalg.norm(point - receiver))


def _sliding_arcs(point: np.ndarray, n: int, step_m: float, sigma_m: float = 0.0, seed: int = 0) -> list[Arc]:
    """A sensor (transmitter, and one receiver 25 cm to its right) sliding along x by
    ``step_m`` a frame, looking ahead; each frame's path to ``point`` plus noise."""
    rng = np.random.default_rng(seed)
    arcs = []
    for k in range(n):
        transmitter = np.array([step_m * (k - n / 2), 0.0, 0.0])
        receiver = transmitter + RECEIVER_OFFSET_M
        path = _path_m(point, transmitter, receiver) + sigma_m * rng.standard_normal()
        arcs.append(Arc(k, transmitter, receiver, path, AHEAD))
    return arcs


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
def test_a_track_from_a_sliding_sensor_gives_the_reflector_back_within_its_covariance(seed: int) -> None:
    """40 frames, 4 mm apart, of a reflector 1.2 m away heard by one receiver: the fit is the
    truth within its stated uncertainty (Mahalanobis distance in the plane the motion fixes,
    chi-square with 2 degrees of freedom, 99.9 %: 13.8), and the residuals are the noise's."""
    truth = np.array([0.3, 0.0, 1.2])
    sigma = 0.001
    arcs = _sliding_arcs(truth, 40, 0.004, sigma, seed)
    point = fit_track(arcs, TrackOptions(), half_angle_rad=BEAM, path_sigma_m=sigma)
    assert point is not None
    plan = [0, 2]
    offset = (point.position_m - truth)[plan]
    covariance = point.covariance_m2[np.ix_(plan, plan)]
    assert offset @ np.linalg.solve(covariance, offset) < 13.8
    assert 0.3 < point.reduced_chi2 < 2.0
    # All foci lie in the plane y = 0: the data cannot tell the point from its mirror image,
    # the beam's axis (in that plane) decides, and the height's uncertainty says so.
    assert abs(point.position_m[1]) < 1e-3
    assert point.data_std_m[2] > 100 * point.data_std_m[1]
    assert (point.n_arcs, point.first_frame, point.last_frame) == (40, 0, 39)


def test_a_stationary_sensor_places_nothing() -> None:
    """The same ellipsoid every frame fixes one direction only: no point, however long."""
    arcs = _sliding_arcs(np.array([0.1, 0.0, 1.0]), 60, 0.0)
    assert fit_track(arcs, TrackOptions(), half_angle_rad=BEAM, path_sigma_m=0.001) is None


def test_a_wall_parallel_to_the_motion_is_no_point() -> None:
    """A wall's echo comes from the transmitter's mirror image (path ``|T' - R|``): sliding along
    the wall, the paths stay the same and the ellipsoids, shifted, share no point."""
    wall_z = 1.5
    arcs = []
    for k in range(40):
        transmitter = np.array([0.01 * k - 0.2, 0.0, 0.0])
        receiver = transmitter + RECEIVER_OFFSET_M
        image = transmitter * [1, 1, -1] + [0, 0, 2 * wall_z]
        arcs.append(Arc(k, transmitter, receiver, float(np.linalg.norm(image - receiver)), AHEAD))
    assert fit_track(arcs, TrackOptions(), half_angle_rad=BEAM, path_sigma_m=0.001) is None


def test_two_reflectors_on_one_channel_make_two_tracks_through_missed_frames() -> None:
    """Two reflectors on the same channel, one missed every third frame (within the gap the
    tracker bridges): two tracks, each fitted to its own reflector."""
    near, far = np.array([-0.2, 0.0, 0.9]), np.array([0.3, 0.0, 1.4])
    tracker = ArcTracker(TrackOptions(), half_angle_rad=BEAM, path_sigma_m=0.001)
    placed = []
    for near_arc, far_arc in zip(_sliding_arcs(near, 50, 0.005), _sliding_arcs(far, 50, 0.005), strict=True):
        frame_arcs = [far_arc] if near_arc.frame % 3 == 2 else [far_arc, near_arc]
        placed += tracker.add(near_arc.frame, {(0, 0): frame_arcs})
    placed += tracker.finish()
    assert len(placed) == 2
    found = sorted((p.position_m for p in placed), key=lambda p: p[2])
    np.testing.assert_allclose(found[0], near, atol=1e-4)
    np.testing.assert_allclose(found[1], far, atol=1e-4)
    assert sorted(p.n_arcs for p in placed) == [34, 50]


def test_a_track_longer_than_max_arcs_is_fitted_in_pieces() -> None:
    truth = np.array([0.0, 0.0, 1.0])
    tracker = ArcTracker(TrackOptions(min_arcs=10, max_arcs=20), half_angle_rad=BEAM, path_sigma_m=0.001)
    placed = []
    for arc in _sliding_arcs(truth, 45, 0.005):
        placed += tracker.add(arc.frame, {(0, 0): [arc]})
    placed += tracker.finish()
    # 20 arcs, then 20 more (the restart keeps the last arc), then the 7 left: too few.
    assert [p.n_arcs for p in placed] == [20, 20]
    for p in placed:
        np.testing.assert_allclose(p.position_m, truth, atol=1e-4)


def test_track_options_refuse_what_cannot_work() -> None:
    with pytest.raises(EchoLocError, match="min_arcs"):
        TrackOptions(min_arcs=3)
    with pytest.raises(EchoLocError, match="gate_m"):
        TrackOptions(gate_m=0.0)
    with pytest.raises(EchoLocError, match="max_std_m"):
        TrackOptions(max_std_m=float("nan"))


def _one_receiver_drive(tracks: TrackOptions | None, spec: GridSpec | None = None) -> float:
    """A sensor driving along x past a post 1.2 m ahead that only its right receiver hears
    (the left one hears nothing, so no frame can place it): the log-odds of the post's cell."""
    post = np.array([0.2, 0.0, 1.2])
    receivers = np.array([[0.25, 0.0, 0.0], [-0.25, 0.0, 0.0]])
    recording = Recording(
        sample_rate_hz=200e3,
        transmitters_m=np.zeros((1, 3)),
        receivers_m=receivers,
        frames=np.zeros((1, 2, 2400)),
        speed_of_sound_m_s=C,
        field_of_view_deg=20.0,
    )
    spec = spec or GridSpec.floor_plan((-1.0, 1.0), (0.0, 2.0), 0.02)
    accumulator = MapAccumulator(spec, recording, SensorModel(tracks=tracks))
    for k in range(60):
        x = 0.005 * (k - 30)
        heard = _path_m(post, np.array([x, 0.0, 0.0]), receivers[0] + [x, 0.0, 0.0])
        echoes = FrameEchoes(
            k,
            k / 100,
            C,
            (ChannelEchoes(np.array([heard / C]), np.ones(1), np.full(1, 30.0)), ChannelEchoes.empty()),
        )
        accumulator.add_frame(echoes, np.array([x, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))
    accumulator.finish_tracks()
    index, _ = spec.cell_indices([post])
    return float(accumulator.grid().log_odds[tuple(index[0])])


def test_the_map_marks_a_post_one_receiver_heard_only_when_tracks_place_it() -> None:
    assert _one_receiver_drive(TrackOptions()) > 0
    assert _one_receiver_drive(None) <= 0


def test_a_3d_map_leaves_a_post_whose_height_the_motion_did_not_fix() -> None:
    """Every focus of that drive lies at one height, so the data fix the post in the floor
    plan but not in height: a 3-D grid does not mark it (it would mark a column)."""
    box = GridSpec.box([-1.0, -0.5, 0.0], [1.0, 0.5, 2.0], 0.02)
    assert _one_receiver_drive(TrackOptions(), box) <= 0


def test_the_covariance_given_the_other_axes_is_the_inverse_of_the_informations_block() -> None:
    arcs = _sliding_arcs(np.array([0.3, 0.0, 1.2]), 40, 0.004)
    point = fit_track(arcs, TrackOptions(), half_angle_rad=BEAM, path_sigma_m=0.001)
    assert point is not None
    plan = point.covariance_given_m2([0, 2])
    assert plan is not None
    np.testing.assert_allclose(plan, np.linalg.inv(point.information_per_m2[np.ix_([0, 2], [0, 2])]))
    # The foci all lie in the plane y = 0: the height is free, so no 3-D covariance.
    assert point.covariance_given_m2([0, 1, 2]) is None
