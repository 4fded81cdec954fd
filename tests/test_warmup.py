"""Compiling the kernels ahead (``echoloc warmup``) and the first-run notice."""

from __future__ import annotations

import io
import os
import subprocess
import sys
from pathlib import Path

import pytest
from click.testing import CliRunner
from rich.console import Console

from echoloc import warmup
from echoloc.cli import app, commands
from echoloc.io.recording import write_recording
from echoloc.sim.scene import default_scene
from echoloc.sim.simulation import simulate


def test_an_empty_kernel_cache_is_cold_and_a_run_chain_leaves_it_warm(tmp_path: Path) -> None:
    """With numba's cache pointed at an empty folder the entry kernels are cold; in the
    package's own cache, once a chain and its one-call kernel have run, they are not."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "empty-cache")}
    code = "from echoloc.warmup import kernels_cold; print(kernels_cold())"
    # NUMBA_CACHE_DIR comes first among numba's cache locations, before __pycache__.
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, check=True)
    assert done.stdout.strip() == "True"
    warmup.warm_up_steps(workers=1)[0].run()
    assert warmup.kernels_cold() is False


def test_warmup_names_every_step_with_its_time() -> None:
    result = CliRunner().invoke(commands.cli, ["warmup", "--workers", "1"])
    assert result.exit_code == 0, result.output
    lines = result.output.strip().splitlines()
    names = [step.name for step in warmup.warm_up_steps(workers=1)]
    assert [line.rsplit(":", 1)[0] for line in lines[:-1]] == names
    assert all(line.endswith(" s") for line in lines)
    assert lines[-1].startswith("kernels ")
    assert not any("threads" in name for name in names)
    assert any("2 threads" in step.name for step in warmup.warm_up_steps(workers=2))


@pytest.mark.parametrize("terminal", [True, False])
def test_a_cold_first_run_says_so_on_a_terminal_only(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, terminal: bool
) -> None:
    """The notice goes to stderr before the command runs, on a terminal; a script reading
    stderr for errors never sees it."""
    path = tmp_path / "rec.h5"
    write_recording(simulate(default_scene(), 1), path)
    text = io.StringIO()
    monkeypatch.setattr(app, "stderr", Console(file=text, force_terminal=terminal, width=400))
    monkeypatch.setattr(warmup, "kernels_cold", lambda: True)
    result = CliRunner().invoke(commands.cli, ["echoes", str(path)])
    assert result.exit_code == 0, result.output
    assert ("compiling the numba kernels on this first run" in text.getvalue()) is terminal
    monkeypatch.setattr(warmup, "kernels_cold", lambda: False)
    text.truncate(0)
    CliRunner().invoke(commands.cli, ["echoes", str(path)])
    assert "compiling" not in text.getvalue()
