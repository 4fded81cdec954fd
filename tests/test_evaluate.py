"""Scoring against truth: one-to-one matching, recall, false objects, RMSE."""

from __future__ import annotations

import numpy as np
import pytest

from echoloc.evaluate import evaluate, match
from echoloc.locate import FrameObjects, LocatedObject


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
