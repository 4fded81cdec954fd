"""The ``echoloc`` command line, assembled: the group and its entry point (``app``) with the
commands of each module registered on it. A thin edge over the library: each command parses
its options, calls the library, and prints.

Exit codes (docs/FORMATS.md): 0 success, 2 bad input or usage (one line on stderr), 1 an
internal error.
"""

from echoloc.cli import basics, batch, hardware, physics, processing, realtime, sweep  # noqa: F401  (register their commands)
from echoloc.cli.app import cli, main
from echoloc.cli.importing import import_group

cli.add_command(import_group, name="import")

__all__ = ["cli", "main"]
