"""The README's library example runs as written and finds the default scene's balls.

A reader copies this block first; if an API it uses is renamed, or the chain stops
finding the report's three balls, this fails instead of the reader.
"""

from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import numpy as np

import echoloc

README = Path(__file__).resolve().parents[1] / "README.md"
USING_THE_LIBRARY = "## Using the library"


def _library_example() -> str:
    """The first ```python block after the README's 'Using the library' heading."""
    text = README.read_text(encoding="utf-8")
    start = text.index(USING_THE_LIBRARY)
    block = re.search(r"```python\n(.*?)```", text[start:], flags=re.DOTALL)
    assert block is not None, "README: no python block under 'Using the library'"
    return block.group(1)


def test_the_readme_library_example_prints_the_default_scenes_balls() -> None:
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        exec(compile(_library_example(), str(README), "exec"), {"__name__": "readme"})
    # Each line: "[x y z] [sx sy sz] (receivers...)" as numpy prints a position and its std.
    positions = [
        np.array([float(v) for v in line[line.index("[") + 1 : line.index("]")].split()])
        for line in printed.getvalue().splitlines()
    ]
    truth = echoloc.default_scene().reflector_positions_m
    assert len(positions) >= 10 * len(truth) * 0.9, f"only {len(positions)} objects in 10 frames"
    # Every ball is found within 2 mm in most frames (its reported std is ~1 mm), and nothing
    # is printed away from the balls (a ghost, or a position in the wrong units).
    nearest_mm = np.array([np.min(np.linalg.norm(truth - p, axis=1)) * 1e3 for p in positions])
    assert np.all(nearest_mm < 5.0), f"objects {nearest_mm.max():.1f} mm from any ball"
    for ball in truth:
        hits = sum(np.linalg.norm(p - ball) < 2e-3 for p in positions)
        assert hits >= 9, f"ball at {ball} found within 2 mm in {hits} of 10 frames"
