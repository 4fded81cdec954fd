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

STUB = Path(echoloc.__file__).with_suffix(".pyi")


def _stub_names() -> tuple[list[str], dict[str, str]]:
    """The stub's literal ``__all__`` and, for every name it imports, the module it comes from."""
    tree = ast.parse(STUB.read_text())
    listed: list[str] = []
    origin: dict[str, str] = {}
    for node in tree.body:
        if isinstance(node, ast.ImportFrom):
            for alias in node.names:
                origin[alias.name] = f"echoloc.{node.module}"
        elif isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets
        ):
            listed = list(ast.literal_eval(node.value))
    return listed, origin


def test_every_public_name_is_its_module_s_object_and_listed_once() -> None:
    """``echoloc.X`` is ``X`` of the module the stub imports it from, for every name of the
    stub's ``__all__``; the runtime ``__all__`` (lazy_loader's) is that list, nothing more."""
    listed, origin = _stub_names()
    assert len(listed) > 100
    assert sorted(echoloc.__all__) == sorted(listed)
    assert len(set(listed)) == len(listed)
    assert set(origin) | {"__version__"} == set(listed)
    for name, module in origin.items():
        assert getattr(echoloc, name) is getattr(importlib.import_module(module), name), name
    assert set(listed) <= set(dir(echoloc))
    with pytest.raises(AttributeError, match="no_such_name"):
        echoloc.no_such_name  # noqa: B018


def test_importing_the_package_loads_no_stage() -> None:
    """``import echoloc`` (or its wire protocol alone) costs no numba or scipy.fft: the
    stages load when a name of theirs is first used."""
    code = (
        "import sys, echoloc, echoloc.realtime.protocol\n"
        "print(sorted(m for m in ('numba', 'scipy.fft', 'echoloc.tof.echoes') if m in sys.modules))\n"
        "echoloc.MatchedFilter\n"
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
