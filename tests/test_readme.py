"""The README's Python examples run as written and find the default scene's balls.

A reader copies these blocks first; if an API they use is renamed, or the chain stops
finding the report's three balls, this fails instead of the reader.
"""

from __future__ import annotations

import ast
import contextlib
import io
import re
import socket
import threading

import numpy as np

import echoloc
from repo_paths import REPO

README = REPO / "README.md"
USING_THE_LIBRARY = "## Using the library"
LIVE_PORT = "port=7447"


def _python_blocks(after: str = "") -> list[str]:
    """The README's ```python blocks after its text ``after`` (all of them: "")."""
    text = README.read_text(encoding="utf-8")
    return re.findall(r"```python\n(.*?)```", text[text.index(after) :], flags=re.DOTALL)


def _library_example() -> str:
    """The block under the 'Using the library' heading."""
    blocks = _python_blocks(USING_THE_LIBRARY)
    assert blocks, "README: no python block under 'Using the library'"
    return blocks[0]


def _live_example() -> str:
    """The README's first python block: a listener and a StreamProcessor on live frames."""
    blocks = _python_blocks()
    assert blocks, "README: no python block"
    return blocks[0]


def _free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


def _balls_found(positions: list[np.ndarray], frames: int) -> None:
    """Each default-scene ball within 2 mm in all but one of ``frames``; nothing else printed."""
    truth = echoloc.default_scene().reflector_positions_m
    assert len(positions) >= frames * len(truth) * 0.9, f"only {len(positions)} objects in {frames} frames"
    # Every ball is found within 2 mm in most frames (its reported std is ~1 mm), and nothing
    # is printed away from the balls (a ghost, or a position in the wrong units).
    nearest_mm = np.array([np.min(np.linalg.norm(truth - p, axis=1)) * 1e3 for p in positions])
    assert np.all(nearest_mm < 5.0), f"objects {nearest_mm.max():.1f} mm from any ball"
    for ball in truth:
        hits = sum(np.linalg.norm(p - ball) < 2e-3 for p in positions)
        assert hits >= frames - 1, f"ball at {ball} found within 2 mm in {hits} of {frames} frames"


def test_the_readme_library_example_prints_the_default_scenes_balls() -> None:
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        exec(compile(_library_example(), str(README), "exec"), {"__name__": "readme"})
    # Each line: "[x y z] [sx sy sz] (receivers...)" as numpy prints a position and its std.
    positions = [
        np.array([float(v) for v in line[line.index("[") + 1 : line.index("]")].split()])
        for line in printed.getvalue().splitlines()
    ]
    _balls_found(positions, 10)


def test_the_readme_live_example_locates_frames_a_sender_streams_to_it() -> None:
    """The listener block, its port swapped for a free one, fed 10 frames over loopback TCP."""
    code = _live_example()
    assert LIVE_PORT in code, f"README's live example no longer listens with {LIVE_PORT}"
    port = _free_tcp_port()
    recording = echoloc.simulate(echoloc.default_scene(), n_frames=10)
    endpoint = echoloc.realtime.Endpoint("127.0.0.1", port)
    sender = threading.Thread(
        target=echoloc.realtime.send_recording, args=(recording, endpoint), kwargs={"speed": 0}, daemon=True
    )
    printed = io.StringIO()
    code = code.replace(LIVE_PORT, f"port={port}")
    # The block runs until the sender's end message: in a thread, so a sender that never
    # gets through fails the test instead of hanging it.
    block = threading.Thread(
        target=exec, args=(compile(code, str(README), "exec"), {"__name__": "readme"}), daemon=True
    )
    with contextlib.redirect_stdout(printed):
        block.start()
        sender.start()  # it retries until the block's listener is up
        sender.join(30)
        block.join(30)
    assert not block.is_alive(), f"README's live example still waiting; it printed {printed.getvalue()!r}"
    *frames, summary = printed.getvalue().splitlines()
    # Each frame's line: "N [[x, y, z], ...]"; then the stats line, every frame counted.
    assert [int(line.split(" ", 1)[0]) for line in frames] == list(range(10))
    positions = [np.array(p) for line in frames for p in ast.literal_eval(line.split(" ", 1)[1])]
    _balls_found(positions, 10)
    assert "received 10," in summary, summary
    assert "lost 0, dropped 0," in summary, summary
