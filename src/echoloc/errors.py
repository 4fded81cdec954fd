"""The one error family of echoloc.

Every problem caused by the user's input (a file, a scene, an option) raises a
subclass of :class:`EchoLocError`, with a message that names the file, the field
and the offending value. The command line turns these into one line on stderr and
exit code 2 (``../shared/FORMATS.md``, "Exit codes").
"""

from __future__ import annotations

import os
from pathlib import Path


class EchoLocError(ValueError):
    """Bad input: the message is meant for the user, as one line."""


class RecordingError(EchoLocError):
    """A recording file (HDF5 or NPZ) breaks the interchange contract."""


class SceneError(EchoLocError):
    """A scene description (TOML or in code) is invalid."""


class WaveformError(EchoLocError):
    """A code or waveform cannot be built as asked."""


class GeometryError(EchoLocError):
    """Transducer positions or measured paths that no reflector can explain."""


def missing_directory(path: Path) -> str | None:
    """Why ``path``'s directory cannot take a new file ("directory 'd' does not exist", or
    "'d' is not a directory" where a file stands), for an output's message; None when it can."""
    parent = path.parent  # Path("name").parent is Path(".")
    if parent.is_dir():
        return None
    if parent.exists():
        return f"{str(parent)!r} is not a directory"
    return f"directory {str(parent)!r} does not exist"


def unwritable(path: Path) -> str | None:
    """Why no file can be written at ``path`` (a directory stands there, its directory is
    missing, or permission is denied), for an output's message; None when it can."""
    if path.is_dir():
        return "is a directory"
    if problem := missing_directory(path):
        return problem
    if not os.access(path if path.exists() else path.parent, os.W_OK):
        return "cannot write here (permission denied)"
    return None
