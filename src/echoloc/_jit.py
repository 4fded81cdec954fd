"""numba when it is installed, plain Python when it is not: the one place kernels import it from.

numba is the ``[fast]`` extra. The kernel modules (``*_kernels.py``) are written in the
subset of Python and numpy that numba compiles, so without it the same functions run as
they are, interpreted: the same answers (to rounding: numba's ``fastmath`` and scipy.fft
against rocket-fft's FFT may differ in the last bits), 7-50 times slower a frame
(``benchmarks/results/uncompiled.md``: 40 ms instead of 1 ms on a 4-channel rf frame).
:func:`njit` says so once, as a warning, the first time a kernel module is imported
without numba.

Setting ``ECHOLOC_DISABLE_NUMBA=1`` takes the plain-Python path even where numba is
installed (for the tests that hold the two to each other, and to compare speeds).
"""

from __future__ import annotations

import contextlib
import os
import warnings
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, TypeVar

_Function = TypeVar("_Function", bound=Callable[..., Any])

_TURNED_OFF = os.environ.get("ECHOLOC_DISABLE_NUMBA", "") not in ("", "0")

_numba: Any = None
if not _TURNED_OFF:
    with contextlib.suppress(ImportError):
        import numba as _numba

HAVE_NUMBA = _numba is not None
"""Whether the kernels are compiled (numba imported) or run as plain Python."""

NO_NUMBA_NOTICE = (
    ("ECHOLOC_DISABLE_NUMBA is set" if _TURNED_OFF else "numba is not installed")
    + ": echoloc's kernels run as plain Python, the same answers 7-50 times slower a "
    "frame; `pip install 'echoloc[fast]'` compiles them"
)


class UncompiledWarning(UserWarning):
    """The kernels run as plain Python: numba is not installed (or is turned off)."""


_told = False


def _tell_once() -> None:
    """Warn, once a process, that the kernels run uncompiled."""
    global _told
    if not _told:
        _told = True
        warnings.warn(NO_NUMBA_NOTICE, UncompiledWarning, stacklevel=4)


def _njit(*args: Any, **options: Any) -> Any:
    """numba's ``njit`` (both ``@njit`` and ``@njit(...)``); without numba, the function itself."""
    if _numba is not None:
        return _numba.njit(*args, **options)
    _tell_once()
    if len(args) == 1 and callable(args[0]) and not options:
        return args[0]

    def unchanged(function: _Function) -> _Function:
        return function

    return unchanged


if TYPE_CHECKING:  # mypy reads the kernels as decorated by numba's own (untyped) njit
    from numba import njit as njit
else:
    njit = _njit


prange: Any = _numba.prange if _numba is not None else range
"""numba's parallel range; ``range`` without numba."""


def set_threads(threads: int, tasks: int) -> int:
    """Threads for a compiled parallel loop over ``tasks``, set as numba's count for the next
    call: ``threads`` capped by ``tasks`` and numba's pool (1 without numba)."""
    if _numba is None or threads <= 1 or tasks <= 1:
        return 1
    count = max(1, min(threads, tasks, int(_numba.config.NUMBA_NUM_THREADS)))
    if count > 1:
        _numba.set_num_threads(count)
    return count


def launch_threading_layer() -> None:
    """Start numba's threading layer now (nothing without numba); see ``_chain_kernels``."""
    if _numba is not None:
        _numba.get_num_threads()
