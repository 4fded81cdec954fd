"""Commands started as from an interactive shell, whatever started the tests.

A shell without job control starts background jobs with SIGINT ignored (POSIX), and an
ignored signal stays ignored across ``exec``: tests run by ``cmd &`` (or a CI runner that
does so) would start every child with Ctrl-C ignored, and echoloc, which leaves an ignored
SIGINT ignored as it should (``nohup``, background jobs), would then not stop on the
SIGINT a test sends. Tests that send SIGINT start their command through :func:`with_sigint`.
"""

from __future__ import annotations

import sys

_RESET_AND_EXEC = (
    "import os, signal, sys; "
    "signal.signal(signal.SIGINT, signal.SIG_DFL); "
    "os.execvp(sys.argv[1], sys.argv[1:])"
)


def with_sigint(command: list[str]) -> list[str]:
    """``command`` run with SIGINT at its default disposition (then exec'd, so its pid is the
    command's own)."""
    return [sys.executable, "-c", _RESET_AND_EXEC, *command]
