"""A bounded fuzz run (the long one is ``fuzz/run.py``): hostile recordings, scenes and
calibration files through the CLI, each judged by the harness (``fuzz/harness.py``):
exit 0 or a clean exit 2, no traceback, within 10 s and under 1 GiB."""

from __future__ import annotations

import random
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from repo_paths import REPO

sys.path.insert(0, str(REPO / "fuzz"))

import harness  # fuzz/ ships with the repository, not the wheel: found through sys.path


def fuzz_settings(max_examples: int) -> settings:
    return settings(
        max_examples=max_examples,
        deadline=None,
        derandomize=True,  # CI sees the same cases every run; fuzz/run.py explores
        suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
        database=None,
    )


@pytest.fixture(scope="module")
def worker() -> Iterator[harness.Worker]:
    with harness.Worker() as running:
        yield running


@pytest.fixture(scope="module")
def seeds(worker: harness.Worker, tmp_path_factory: pytest.TempPathFactory) -> harness.Seeds:
    return harness.make_seeds(worker, tmp_path_factory.mktemp("fuzz-seeds"))


def _judge(
    worker: harness.Worker, seeds: harness.Seeds, name: str, rng: random.Random, folder: Path
) -> tuple[harness.Outcome, str]:
    tally = harness.Tally()
    outcome = harness.run_family(worker, seeds, harness.FAMILIES[name], rng, tally, folder)
    return outcome, next(iter(tally.examples.values()), "")


@pytest.mark.parametrize(
    ("family", "max_examples"), [("recordings", 60), ("scenes", 25), ("calibrations", 25)]
)
def test_mutated_files_end_cleanly(
    worker: harness.Worker, seeds: harness.Seeds, tmp_path: Path, family: str, max_examples: int
) -> None:
    """``max_examples`` mutations of the family's seed files, each judged by the harness."""

    @fuzz_settings(max_examples)
    @given(rng=st.randoms(use_true_random=False))
    def mutated_file_ends_cleanly(rng: random.Random) -> None:
        outcome, finding = _judge(worker, seeds, family, rng, tmp_path / "case")
        assert outcome.problems == [], finding

    mutated_file_ends_cleanly()


def test_hostile_sessions_leave_the_stream_serving(seeds: harness.Seeds, tmp_path: Path) -> None:
    """Over TCP and UDP: after each hostile session, a valid sender is fully processed (and, on
    TCP, confirmed), the stream never prints a traceback and ends with exit 0 on SIGTERM."""
    import sessions  # starts `echoloc stream` processes: only here

    tally = harness.Tally()
    sessions.run_sessions(seeds, random.Random(31), tally, 30, tmp_path)
    assert sum(tally.cases.values()) == 30
    assert tally.clean, tally.examples
    assert tally.notes["stream (tcp) exit code on SIGTERM"] == 0
    assert tally.notes["stream (udp) exit code on SIGTERM"] == 0


def test_the_judge_catches_what_it_must(worker: harness.Worker, tmp_path: Path) -> None:
    """The harness itself: an internal error is exit 1, a usage error is a clean exit 2."""
    usage = worker.run(["locate", "--no-such-option"], tmp_path)
    assert usage.exit == 2
    assert usage.problems == []
    broken = harness.Outcome(1, "echoloc: internal error: ZeroDivisionError", 0.1, 1 << 20)
    assert broken.problems == ["exit 1"]
    assert harness.Outcome(None, "", 10.0, 0, hung=True).problems == ["hang"]
    assert harness.Outcome(2, "echoloc: error: x", 0.1, (1 << 30) + 1).problems == ["memory"]
    assert harness.Outcome(2, "Traceback (most recent call last):\n", 0.1, 1).problems == [
        "traceback",
        "exit 2 without an error line",
    ]
