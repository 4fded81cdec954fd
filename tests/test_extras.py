"""The optional parts (echoloc.extras): without their package, one line that names it and
the extra to install, exit code 2; the core never needs them."""

from __future__ import annotations

import importlib
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from echoloc.errors import EchoLocError
from echoloc.io.recording import write_recording
from echoloc.sim.scene import default_scene
from echoloc.sim.simulation import simulate


def _hide(monkeypatch: pytest.MonkeyPatch, package: str, *importers: str) -> None:
    """Make ``import package`` fail as if it were not installed, and forget the modules
    that imported it so that they import it again."""
    for name in [m for m in sys.modules if m == package or m.startswith(package + ".")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, package, None)
    for importer in importers:
        for name in [m for m in sys.modules if m == importer or m.startswith(importer + ".")]:
            monkeypatch.delitem(sys.modules, name)


def test_without_matplotlib_the_plots_name_the_plot_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    _hide(monkeypatch, "matplotlib", "echoloc.plots")
    with pytest.raises(
        EchoLocError, match=r"needs matplotlib, which is not installed: pip install 'echoloc\[plot\]'"
    ):
        importlib.import_module("echoloc.plots.frame")


def test_without_foxglove_the_live_view_names_the_live_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    _hide(monkeypatch, "foxglove", "echoloc.realtime.liveview")
    with pytest.raises(EchoLocError, match=r"pip install 'echoloc\[live\]'"):
        importlib.import_module("echoloc.realtime.liveview")


def test_without_pyoctomap_an_octomap_names_the_octomap_extra(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    from echoloc.maps.map_export import write_octomap
    from echoloc.maps.mapping import GridSpec, MapAccumulator

    recording = simulate(default_scene(), 1)
    grid = MapAccumulator(GridSpec(np.zeros(3), 0.1, (2, 2, 2)), recording).grid()
    _hide(monkeypatch, "pyoctomap")
    with pytest.raises(EchoLocError, match=r"pip install 'echoloc\[octomap\]'"):
        write_octomap(grid, tmp_path / "map.bt")


def test_the_command_says_it_in_one_line_and_the_core_still_runs(tmp_path: Path) -> None:
    """`echoloc image` without matplotlib: exit 2, one line; `echoloc locate` on the same
    recording, in the same interpreter without matplotlib, runs."""
    path = tmp_path / "rec.h5"
    write_recording(simulate(default_scene(), 1), path)
    code = (
        "import sys\n"
        "sys.modules['matplotlib'] = None\n"
        "from echoloc.cli.commands import main\n"
        "try:\n"
        "    main(sys.argv[1:])\n"
        "except SystemExit as done:\n"
        "    print('exit', done.code)\n"
    )
    image = subprocess.run(
        [sys.executable, "-c", code, "image", str(path), "-o", str(tmp_path / "x.png")],
        capture_output=True,
        text=True,
        check=False,
    )
    assert "exit 2" in image.stdout
    lines = image.stderr.strip().splitlines()
    assert len(lines) == 1, image.stderr
    assert lines[0].startswith("echoloc: error:")
    assert "pip install 'echoloc[plot]'" in lines[0]
    located = subprocess.run(
        [sys.executable, "-c", code, "locate", str(path), "--json"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert "exit 0" in located.stdout, located.stderr
    assert '"objects"' in located.stdout
