"""The ``echoloc`` command's entry point: the command line, imported under a guard.

Importing the command line takes about a second (numba, scipy and every stage); Ctrl-C in
that second printed Python's traceback. Here it ends as a Ctrl-C does once a command runs
(:func:`echoloc.cli.commands.main`): one line on stderr, exit code 1. A SIGTERM then still ends
the process at once (Python's default), before anything is written.
"""

from __future__ import annotations

import sys


def main() -> None:
    """Import and run the command line (:func:`echoloc.cli.commands.main`)."""
    try:
        from echoloc.cli.commands import main as run
    except KeyboardInterrupt:
        sys.stderr.write("echoloc: aborted\n")
        sys.exit(1)
    run()
