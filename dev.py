#!/usr/bin/env python3
"""Set up echoloc in ./.venv (when missing or stale) and run a job in it.

Needs only python3 (>= 3.10) on the machine:

    python3 dev.py demo     # install, then run `echoloc demo` on the default scene
    python3 dev.py test     # install, then ruff, mypy and pytest
    python3 dev.py bench    # install, then the speed benchmarks
    python3 dev.py docs     # install, then build the API reference (docs/api/_build/html), warnings as errors
    python3 dev.py shell    # print how to activate the environment
    python3 dev.py oldest   # the oldest supported Python and numpy: install, demo, quick tests

The environment is rebuilt when pyproject.toml changes.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")
PYTHON = BIN / ("python.exe" if os.name == "nt" else "python")
STAMP = VENV / ".echoloc-installed"
DOCS_SOURCE = Path("docs") / "api"
DOCS_OUTPUT = DOCS_SOURCE / "_build" / "html"


def _run(*args: str | Path) -> None:
    print("+", " ".join(str(a) for a in args), flush=True)
    completed = subprocess.run([str(a) for a in args], cwd=ROOT, check=False)
    if completed.returncode != 0:
        sys.exit(completed.returncode)


def ensure_environment() -> None:
    """Create .venv and install echoloc with its dev tools if not done for this pyproject."""
    wanted = hashlib.sha256((ROOT / "pyproject.toml").read_bytes()).hexdigest()
    if STAMP.exists() and STAMP.read_text() == wanted and PYTHON.exists():
        return
    if not PYTHON.exists():
        print(f"creating virtual environment in {VENV}", flush=True)
        venv.EnvBuilder(with_pip=True, clear=True).create(VENV)
    _run(PYTHON, "-m", "pip", "install", "--quiet", "--upgrade", "pip")
    _run(PYTHON, "-m", "pip", "install", "--quiet", "-e", ".[dev]")
    STAMP.write_text(wanted)


OLDEST_PYTHON = "3.10"
OLDEST_NUMPY = "numpy==1.26.*"
OLDEST_VENV = ROOT / ".venv-oldest"
QUICK_TESTS = (
    "tests/test_package.py",
    "tests/physics",
    "tests/sim/test_scene.py",
    "tests/io/test_recording.py",
    "tests/tof/test_echoes.py",
    "tests/localise/test_locate.py",
)


def _find_oldest_python() -> str | None:
    """A working python3.10: on PATH, else one of pyenv's (its shim may point nowhere)."""
    candidates = [shutil.which(f"python{OLDEST_PYTHON}")]
    pyenv = Path.home() / ".pyenv" / "versions"
    if pyenv.is_dir():
        candidates += [str(path) for path in sorted(pyenv.glob(f"{OLDEST_PYTHON}.*/bin/python"))]
    for candidate in candidates:
        if candidate is None:
            continue
        probe = [candidate, "-c", "import sys; print('%d.%d' % sys.version_info[:2])"]
        done = subprocess.run(probe, capture_output=True, text=True, check=False)
        if done.returncode == 0 and done.stdout.strip() == OLDEST_PYTHON:
            return candidate
    return None


def _site_packages_mib(venv: Path) -> float:
    """The size of a virtual environment's installed packages, MiB."""
    total = sum(f.stat().st_size for f in venv.glob("lib/python*/site-packages/**/*") if f.is_file())
    return total / 2**20


def oldest(rest: list[str]) -> None:
    """Install echoloc (not editable) with the oldest supported Python and numpy, then run
    the demo and a quick subset of the tests there: what a ROS 2 Humble user gets."""
    python = _find_oldest_python()
    if python is None:
        print(f"oldest: no python{OLDEST_PYTHON} on this machine; skipped", flush=True)
        return
    bin_dir = OLDEST_VENV / ("Scripts" if os.name == "nt" else "bin")
    _run(python, "-m", "venv", "--clear", OLDEST_VENV)  # afresh: the sizes below are a new user's
    _run(bin_dir / "python", "-m", "pip", "install", "--quiet", "--upgrade", "pip")
    # The core alone first: the demo needs no extra.
    _run(bin_dir / "python", "-m", "pip", "install", "--quiet", ".", OLDEST_NUMPY)
    print(f"oldest: installed, core only: {_site_packages_mib(OLDEST_VENV):.0f} MiB", flush=True)
    demo_dir = OLDEST_VENV / "demo"
    demo_dir.mkdir(exist_ok=True)
    # Without numba (the [fast] extra) the kernels run as plain Python: the demo still works.
    _run(bin_dir / "echoloc", "demo", "-o", demo_dir / "echoloc-demo.h5")
    # The scene presets are in the wheel, those in folders too.
    _run(bin_dir / "echoloc", "simulate", "report/ball-fixed", "-o", demo_dir / "ball.h5", "--frames", "2")
    _run(
        bin_dir / "python", "-m", "pip", "install", "--quiet", ".[all]", OLDEST_NUMPY, "pytest", "hypothesis"
    )
    print(f"oldest: installed, all extras and pytest: {_site_packages_mib(OLDEST_VENV):.0f} MiB", flush=True)
    # The tests import the installed package, not src/: run them from outside the tree.
    _run(
        bin_dir / "python",
        "-m",
        "pytest",
        "-p",
        "no:cacheprovider",
        "--rootdir",
        ROOT,
        "-c",
        ROOT / "pyproject.toml",
        *[ROOT / t for t in QUICK_TESTS],
        *rest,
    )


def main(argv: list[str]) -> None:
    job = argv[0] if argv else "help"
    rest = argv[1:]
    if job == "oldest":
        oldest(rest)
        return
    if job not in {"demo", "test", "bench", "docs", "shell"}:
        print(__doc__)
        sys.exit(0 if job in {"help", "-h", "--help"} else 2)
    ensure_environment()
    if job == "demo":
        _run(BIN / "echoloc", "demo", *rest)
    elif job == "test":
        _run(PYTHON, "-m", "ruff", "check", "src", "tests", "benchmarks", "fuzz", "dev.py")
        _run(PYTHON, "-m", "ruff", "format", "--check", "src", "tests", "benchmarks", "fuzz", "dev.py")
        _run(PYTHON, "-m", "mypy")
        _run(PYTHON, "-m", "pytest", *rest)
    elif job == "bench":
        for script in sorted((ROOT / "benchmarks").glob("bench_*.py")):
            _run(PYTHON, script, *rest)
    elif job == "docs":
        # -E: read every page afresh; an incremental build does not repeat the warnings of
        # pages it does not read again, so a second run would pass where the first failed.
        _run(BIN / "sphinx-build", "-W", "--keep-going", "-E", "-b", "html", *rest, DOCS_SOURCE, DOCS_OUTPUT)
    else:
        print(f"source {BIN / 'activate'}")


if __name__ == "__main__":
    main(sys.argv[1:])
