"""The package itself: its public names, loaded on first use, and the command's entry point."""

from __future__ import annotations

import ast
import importlib
import os
import subprocess
import sys
from pathlib import Path

import pytest

import echoloc
from echoloc.cli import entry

PACKAGE = Path(echoloc.__file__).parent
SUBPACKAGES = ("physics", "sim", "tof", "localise", "maps", "io", "realtime", "plots")


def _stub_names(package: str) -> tuple[list[str], dict[str, tuple[str, bool]]]:
    """A stub's literal ``__all__`` and, for every name it imports, the module it comes from
    and whether the name is that module itself (``from . import x``: the subpackage ``x``)."""
    folder = PACKAGE if package == "echoloc" else PACKAGE / package.split(".")[-1]
    tree = ast.parse((folder / "__init__.pyi").read_text())
    listed: list[str] = []
    origin: dict[str, tuple[str, bool]] = {}
    for node in tree.body:
        if isinstance(node, ast.ImportFrom):
            assert node.level == 1, "lazy_loader reads only imports from within the package"
            for alias in node.names:
                if node.module:
                    origin[alias.name] = (f"{package}.{node.module}", False)
                else:
                    origin[alias.name] = (f"{package}.{alias.name}", True)
        elif isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets
        ):
            listed = list(ast.literal_eval(node.value))
    return listed, origin


@pytest.mark.parametrize("package", ["echoloc", *(f"echoloc.{name}" for name in SUBPACKAGES)])
def test_every_public_name_is_its_module_s_object_and_listed_once(package: str) -> None:
    """``package.X`` is ``X`` of the module the stub imports it from (or the subpackage ``X``),
    for every name of the stub's ``__all__``; the runtime ``__all__`` is that list, nothing more."""
    module = importlib.import_module(package)
    listed, origin = _stub_names(package)
    assert sorted(module.__all__) == sorted(listed)
    assert len(set(listed)) == len(listed)
    assert set(origin) | ({"__version__"} if package == "echoloc" else set()) == set(listed)
    for name, (source, is_module) in origin.items():
        expected = importlib.import_module(source)
        assert getattr(module, name) is (expected if is_module else getattr(expected, name)), name
    assert set(listed) <= set(dir(module))
    with pytest.raises(AttributeError, match="no_such_name"):
        module.no_such_name  # noqa: B018


def test_the_stable_api_is_small_and_every_stage_is_reachable() -> None:
    """About twenty names at the top (the stable API) beside the subpackages; every subpackage
    public name is reachable from ``echoloc`` in one attribute step."""
    top = [name for name in echoloc.__all__ if name not in SUBPACKAGES and name != "__version__"]
    assert 15 <= len(top) <= 25, top
    for name in SUBPACKAGES:
        assert getattr(echoloc, name).__name__ == f"echoloc.{name}"
    # The verbs of the stable API are functions, their modules nouns: importing the module
    # (which sets it as an attribute of its subpackage) leaves the function in place.
    simulation = importlib.import_module("echoloc.sim.simulation")
    evaluation = importlib.import_module("echoloc.localise.evaluation")
    assert echoloc.simulate is echoloc.sim.simulate is simulation.simulate
    assert echoloc.evaluate is echoloc.localise.evaluate is evaluation.evaluate


def test_importing_the_package_loads_no_stage() -> None:
    """``import echoloc`` (or its wire protocol alone) costs no numba or scipy.fft: the
    stages load when a name of theirs is first used."""
    code = (
        "import sys, echoloc, echoloc.realtime.protocol\n"
        "print(sorted(m for m in ('numba', 'scipy.fft', 'echoloc.tof.echoes') if m in sys.modules))\n"
        "echoloc.tof.MatchedFilter\n"
        "print('echoloc.tof.echoes' in sys.modules)\n"
    )
    env = {k: v for k, v in os.environ.items() if k != "EAGER_IMPORT"}
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, env=env
    ).stdout
    assert out.split("\n")[:2] == ["[]", "True"], out


class _InterruptedImport:
    """A meta path finder that raises KeyboardInterrupt for one module, as Ctrl-C during it would."""

    def __init__(self, name: str) -> None:
        self.name = name

    def find_spec(self, name: str, path: object = None, target: object = None) -> None:
        if name == self.name:
            raise KeyboardInterrupt


def test_ctrl_c_while_the_command_line_loads_is_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Ctrl-C in the second the command line takes to import: "echoloc: aborted", exit 1,
    as once a command runs, not Python's traceback."""
    monkeypatch.delitem(sys.modules, "echoloc.cli.commands", raising=False)
    monkeypatch.setattr(sys, "meta_path", [_InterruptedImport("echoloc.cli.commands"), *sys.meta_path])
    try:
        with pytest.raises(SystemExit) as stopped:
            entry.main()
    except KeyboardInterrupt:
        pytest.fail("the interrupt got through entry.main() (it would print a traceback)")
    assert stopped.value.code == 1
    assert capsys.readouterr().err == "echoloc: aborted\n"
