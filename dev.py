#!/usr/bin/env python3
"""Set up echoloc in ./.venv (when missing or stale) and run a job in it.

Needs only python3 (>= 3.11) on the machine:

    python3 dev.py demo     # install, then run `echoloc demo` on the default scene
    python3 dev.py test     # install, then ruff, mypy and pytest
    python3 dev.py bench    # install, then the speed benchmarks
    python3 dev.py shell    # print how to activate the environment

The environment is rebuilt when pyproject.toml changes.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import venv
from pathlib import Path

ROOT = Path(__file__).resolve().parent
VENV = ROOT / ".venv"
BIN = VENV / ("Scripts" if os.name == "nt" else "bin")
PYTHON = BIN / ("python.exe" if os.name == "nt" else "python")
STAMP = VENV / ".echoloc-installed"


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


def main(argv: list[str]) -> None:
    job = argv[0] if argv else "help"
    rest = argv[1:]
    if job not in {"demo", "test", "bench", "shell"}:
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
    else:
        print(f"source {BIN / 'activate'}")


if __name__ == "__main__":
    main(sys.argv[1:])
