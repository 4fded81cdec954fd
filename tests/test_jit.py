"""Without numba the kernels run as plain Python: the same objects, and one notice saying so."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from echoloc._jit import NO_NUMBA_NOTICE
from repo_paths import REPO

CROWDED_SCENE = """
seed = 3
[array]
transmitters_m = [[0.0, 0.0, 0.0]]
receivers_m = [[0.05, 0.0, 0.0], [-0.05, 0.0, 0.0], [0.0, 0.05, 0.0], [0.0, -0.05, 0.0]]
[acquisition]
sample_rate_hz = 200e3
n_samples = 2400
[random_reflectors]
count = [4, 6]
x_m = [-0.3, 0.3]
y_m = [-0.3, 0.3]
z_m = [0.5, 0.6]
"""
"""Reflectors close in range: echoes overlap, so pair splitting and CLEAN run."""


def _echoloc(*args: str | Path, uncompiled: bool) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ)
    env.pop("ECHOLOC_DISABLE_NUMBA", None)
    if uncompiled:
        env["ECHOLOC_DISABLE_NUMBA"] = "1"
    command = [sys.executable, "-m", "echoloc", *map(str, args)]
    return subprocess.run(command, capture_output=True, text=True, env=env, check=False, timeout=600)


def _objects(stdout: str) -> list[np.ndarray]:
    """Each frame's object positions (n, 3), m, sorted by x then y then z."""
    frames = []
    for line in stdout.splitlines():
        positions = np.array([o["position_m"] for o in json.loads(line)["objects"]]).reshape(-1, 3)
        frames.append(positions[np.lexsort(positions.T[::-1])])
    return frames


@pytest.mark.parametrize("scene", ["report-three-balls", "crowded", "ch101"])
def test_uncompiled_kernels_find_what_the_compiled_ones_find(scene: str, tmp_path: Path) -> None:
    """The same scene through both paths: the same objects in every frame, within 1 nm (the
    only differences are rounding: numba's fastmath sums, rocket-fft against scipy.fft), and
    on the plain path one warning line that says why it is slower."""
    if scene == "report-three-balls":
        scene_file = REPO / "src" / "echoloc" / "scenes" / "report-three-balls.toml"
    elif scene == "crowded":
        scene_file = tmp_path / "crowded.toml"
        scene_file.write_text(CROWDED_SCENE)
    else:
        scene_file = REPO / "src" / "echoloc" / "scenes" / "ch101.toml"
    recording = tmp_path / "recording.h5"
    made = _echoloc("simulate", scene_file, "--frames", "4", "-o", recording, uncompiled=False)
    assert made.returncode == 0, made.stderr

    compiled = _echoloc("locate", recording, "--json", uncompiled=False)
    plain = _echoloc("locate", recording, "--json", uncompiled=True)
    assert compiled.returncode == 0, compiled.stderr
    assert plain.returncode == 0, plain.stderr
    assert compiled.stderr == ""
    (notice,) = plain.stderr.splitlines()
    assert notice.startswith("echoloc: warning: ECHOLOC_DISABLE_NUMBA is set: ")
    assert notice.endswith(NO_NUMBA_NOTICE.split(": ", 1)[1])

    compiled_frames, plain_frames = _objects(compiled.stdout), _objects(plain.stdout)
    assert len(compiled_frames) == len(plain_frames) == 4
    assert sum(len(f) for f in compiled_frames) >= 4  # objects are found, so they are compared
    for a, b in zip(compiled_frames, plain_frames, strict=True):
        assert a.shape == b.shape
        np.testing.assert_allclose(b, a, rtol=0, atol=1e-9)
