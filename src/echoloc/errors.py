"""The one error family of echoloc.

Every problem caused by the user's input (a file, a scene, an option) raises a
subclass of :class:`EchoLocError`, with a message that names the file, the field
and the offending value. The command line turns these into one line on stderr and
exit code 2 (``docs/FORMATS.md``, "Exit codes").
"""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO


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


def scene_error_from(source: str, error: EchoLocError) -> SceneError:
    """``error`` as a :class:`SceneError` whose message starts with the file it is about,
    ``source`` (once: a message that already names it keeps its own)."""
    message = str(error)
    return SceneError(message if message.startswith(source) else f"{source}: {message}")


def refuse_new_output(path: Path, *, force: bool) -> None:
    """Refuse, with one line, an output file that cannot be written where it is asked for (no
    such folder, a folder there) or that exists unless ``force``: a file is never replaced
    without asking."""
    if problem := missing_directory(path):
        raise EchoLocError(f"{path}: {problem}")
    if path.is_dir():
        raise EchoLocError(f"{path}: is a directory")
    if (path.exists() or path.is_symlink()) and not force:
        raise EchoLocError(f"{path}: already exists; give --force to replace it")


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


def open_input(
    path: str | os.PathLike[str], *, what: str, max_bytes: int, error: type[EchoLocError] = EchoLocError
) -> BinaryIO:
    """The regular file ``path`` opened for binary reading, or ``error`` naming the file.

    Only a regular file is opened: a device (``/dev/zero`` never ends), a FIFO (which would
    block) or a directory is refused before a byte is read, and so is a file of more than
    ``max_bytes``. ``what`` names the input in messages ("scene file"). The caller closes it.
    """
    source = Path(path)
    try:
        # O_NONBLOCK: opening a FIFO must not wait for a writer (it is refused just after).
        fd = os.open(source, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0))
    except FileNotFoundError:
        raise error(f"{source}: no such {what}") from None
    except OSError as failure:
        raise error(f"{source}: cannot read {what} ({failure.strerror})") from None
    try:
        info = os.fstat(fd)
        if stat.S_ISDIR(info.st_mode):
            raise error(f"{source}: is a directory, not a {what}")
        if not stat.S_ISREG(info.st_mode):
            raise error(f"{source}: not a regular file (a device, FIFO or socket), not a {what}")
        if info.st_size > max_bytes:
            raise error(f"{source}: {what} of {info.st_size} bytes, more than the {max_bytes} it may have")
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_text_input(
    path: str | os.PathLike[str], *, what: str, max_bytes: int, error: type[EchoLocError] = EchoLocError
) -> str:
    """The UTF-8 text of the regular file ``path``, refused as ``error`` naming the file.

    Opened by :func:`open_input` (a regular file of at most ``max_bytes``); a file that
    grows past ``max_bytes`` while it is read is refused too.
    """
    source = Path(path)
    with open_input(source, what=what, max_bytes=max_bytes, error=error) as fh:
        try:
            data = fh.read(max_bytes + 1)
        except OSError as failure:
            raise error(f"{source}: cannot read {what} ({failure.strerror})") from None
    if len(data) > max_bytes:
        raise error(f"{source}: {what} of more than {max_bytes} bytes")
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as failure:
        raise error(
            f"{source}: cannot read {what} (not UTF-8 text: {failure.reason} at byte {failure.start})"
        ) from None
