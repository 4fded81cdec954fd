"""Scoring against truth: one-to-one matching, recall, false objects, RMSE."""

from __future__ import annotations

import numpy as np
import pytest

from echoloc.errors import EchoLocError
from echoloc.localise.evaluation import evaluate, frames_at_positions, match, target_positions
from echoloc.localise.locate import FrameObjects, LocatedObject


def _objects(frame: int, positions: list[list[float]], std: float = 1e-3) -> FrameObjects:
    return FrameObjects(
        frame,
        0.0,
        tuple(
            LocatedObject(np.array(p, float), np.eye(3) * std**2, (0, 1, 2, 3), (0, 0, 0, 0), 0.0, 1.0)
            for p in positions
        ),
    )


def test_matching_is_one_to_one_and_order_free() -> None:
    """The minimum-total-distance assignment pairs each estimate with its own truth."""
    truth = np.array([[0, 0, 1.0], [0.1, 0, 1.0], [0.2, 0, 1.0]])
    estimated = truth[[2, 0, 1]] + 0.001
    assert sorted(match(estimated, truth, 0.01)) == [(0, 2), (1, 0), (2, 1)]


def test_matching_respects_the_radius() -> None:
    """An estimate farther than the radius from every truth is a false object."""
    truth = np.array([[0, 0, 1.0]])
    assert match(np.array([[0, 0, 1.03]]), truth, 0.02) == []
    assert match(np.array([[0, 0, 1.01]]), truth, 0.02) == [(0, 0)]


def test_figures() -> None:
    """Two frames, three true reflectors, one missed, one false: recall 2/3, false 1/3."""
    truth = np.full((2, 2, 3), np.nan)
    truth[0, 0] = [0, 0, 1.0]
    truth[0, 1] = [0.2, 0, 1.0]
    truth[1, 0] = [0, 0.1, 0.5]
    results = [
        _objects(0, [[0.002, 0, 1.0]]),
        _objects(1, [[0, 0.1, 0.497], [0.5, 0.5, 0.5]]),
    ]
    report = evaluate(results, truth, 0.02)
    assert (report.n_truth, report.n_located, report.n_matched, report.n_false) == (3, 3, 2, 1)
    assert report.recall == pytest.approx(2 / 3)
    assert report.false_rate == pytest.approx(1 / 3)
    assert report.rmse_m == pytest.approx([np.sqrt(0.002**2 / 2), 0.0, np.sqrt(0.003**2 / 2)])
    assert report.mean_std_m == pytest.approx([1e-3] * 3)


# --- target positions: calibrate on some, test on the others ----------------------------

# Frames 0-1 at a far point, 2-4 at a near one, 5 with no known target, 6 back at the far one.
FAR, NEAR, NEAR_AGAIN, NONE = [0.0, 0.0, 0.3], [0.05, 0.0, 0.1], [0.05, 0.00004, 0.1], [np.nan] * 3
TRUTH_M = np.array([[FAR], [FAR], [NEAR], [NEAR], [NEAR_AGAIN], [NONE], [FAR]])


def test_target_positions_are_numbered_by_depth_and_share_frames() -> None:
    """Positions within 0.1 mm are one set-up; set-ups are numbered by z first, so the near
    point is 0 though it appears second; a frame with no truth has none."""
    positions, which = target_positions(TRUTH_M)
    np.testing.assert_allclose(positions, [[0.05, 0.0, 0.1], [0.0, 0.0, 0.3]])
    np.testing.assert_array_equal(which, [1, 1, 0, 0, 0, -1, 1])


@pytest.mark.parametrize(
    ("spec", "frames"),
    [
        ("0::2", [2, 3, 4]),
        ("1::2", [0, 1, 6]),
        ("1", [0, 1, 6]),
        ("-1", [0, 1, 6]),
        (":", [0, 1, 2, 3, 4, 6]),
    ],
)
def test_positions_pick_every_frame_of_their_set_ups(spec: str, frames: list[int]) -> None:
    assert frames_at_positions(TRUTH_M, spec, range(7)) == frames


@pytest.mark.parametrize(
    ("spec", "message"),
    [
        ("a::2", "must be a slice"),
        ("0:1:2:3", "must be a slice"),
        ("::0", "must not be 0"),
        ("5:", "picks no frame"),
    ],
)
def test_bad_position_slices_are_one_clear_error(spec: str, message: str) -> None:
    with pytest.raises(EchoLocError, match=message):
        frames_at_positions(TRUTH_M, spec, range(7))
