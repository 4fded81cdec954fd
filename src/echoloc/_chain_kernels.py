"""The per-frame chain in one compiled call: frames' echoes, then each frame's objects.

:func:`echoes_and_objects` runs the matched filter's compiled batch path
(:func:`echoloc.tof._echoes_kernels.correlate_and_fit`) on every channel of a batch of frames, then
the association (:func:`echoloc.localise._locate_kernels.associate_frame`) on each frame whose channels
it could all vouch for. Called from Python, the two stages made the echoes Python objects and
flattened them again for a second call; here the one call hands the association the echoes'
own arrays, which saves that round trip (`benchmarks/bench_chain_kernel.py` measures it). Frames
with a channel left to CLEAN come back unassociated: the caller runs CLEAN and the
association as before.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from echoloc._jit import launch_threading_layer, njit
from echoloc.localise._locate_kernels import associate_frame
from echoloc.tof._echoes_kernels import correlate_and_fit

if TYPE_CHECKING:
    from echoloc.localise.locate import LocateKernelArguments
    from echoloc.tof.echoes import EchoKernelArguments

_Rows = NDArray[np.int64] | NDArray[np.float64]
"""What :func:`_with_room` grows, and returns grown or as it was: the objects' echo use (int64,
2-D), positions (float64, 2-D), covariances (3-D) and chi-square (1-D); numba compiles it for
each (a TypeVar would say that it returns the type it takes, but numba's Dispatcher stub drops
a generic function's type variables)."""

# The kernel's cached machine code holds batch_echoes_parallel's, which calls numba's threading
# layer. Loaded from the cache before that layer was launched it crashed the process (numba
# 0.68: nothing launches it for a caller of a parallel kernel); this launches it.
launch_threading_layer()

LEFT_TO_CLEAN = -1
"""A frame's status when some channel of it is left to CLEAN (no association run)."""


@njit(cache=True, inline="always")
def _with_room(rows: _Rows, used: int, needed: int) -> _Rows:  # pragma: no cover - compiled
    """``rows`` (n, ...), or a copy of its first ``used`` rows with room for ``needed`` more."""
    if used + needed <= rows.shape[0]:
        return rows
    grown = np.empty((max(2 * rows.shape[0], used + needed), *rows.shape[1:]), rows.dtype)
    grown[:used] = rows[:used]
    return grown


@njit(cache=True, nogil=True)
def echoes_and_objects(
    echo_arguments: EchoKernelArguments, n_rx: int, locate_arguments: LocateKernelArguments
) -> tuple[
    NDArray[np.int64],  # status (n_frames,)
    NDArray[np.int64],  # found (n_frames + 1,)
    NDArray[np.int64],  # echo_use (n_objects, 2 n_rx)
    NDArray[np.float64],  # positions (n_objects, D), m
    NDArray[np.float64],  # covariances (n_objects, D, D)
    NDArray[np.float64],  # chi2 (n_objects,)
]:  # pragma: no cover
    """Echoes of every channel of a batch of frames and the objects of each frame, in one call.

    ``echo_arguments`` are :func:`correlate_and_fit`'s (echoes.EchoKernelArguments): the
    rows of samples (n_frames * ``n_rx``, a frame's receivers in order) and the outputs
    ``out``, ``kept`` and ``ok``, which hold the echoes after the call.
    ``locate_arguments`` are :func:`associate_frame`'s besides a frame's echoes
    (locate.LocateKernelArguments), read by name.

    Returns (status, found, echo_use, positions, covariances, chi2): ``status`` (n_frames,)
    is associate_frame's for each frame, or :data:`LEFT_TO_CLEAN`; frame f's objects are the
    rows ``found[f]:found[f + 1]`` of the other four.
    """
    correlate_and_fit(echo_arguments)
    out, kept, ok = echo_arguments.out, echo_arguments.kept, echo_arguments.ok
    receivers = locate_arguments.geometry.receivers
    n_frames = kept.shape[0] // n_rx
    dim = receivers.shape[1]
    status = np.full(n_frames, LEFT_TO_CLEAN, dtype=np.int64)
    found = np.zeros(n_frames + 1, dtype=np.int64)
    capacity = 8 * n_frames
    echo_use = np.empty((capacity, 2 * n_rx), dtype=np.int64)
    positions = np.empty((capacity, dim))
    covariances = np.empty((capacity, dim, dim))
    chi2 = np.empty(capacity)
    offset = np.zeros(n_rx + 1, dtype=np.int64)
    for f in range(n_frames):
        found[f + 1] = found[f]
        first = f * n_rx
        vouched = True
        for c in range(n_rx):
            vouched = vouched and ok[first + c]
            offset[c + 1] = offset[c] + kept[first + c]
        if not vouched:
            continue
        # The frame's echoes flat, channel after channel, as locate.FrameLocator passes them.
        tof = np.empty(offset[n_rx])
        amplitude = np.empty(offset[n_rx])
        snr_db = np.empty(offset[n_rx])
        for c in range(n_rx):
            for e in range(kept[first + c]):
                tof[offset[c] + e] = out[0, first + c, e]
                amplitude[offset[c] + e] = out[1, first + c, e]
                snr_db[offset[c] + e] = out[2, first + c, e]
        frame_status, frame_use, frame_positions, frame_covariances, frame_chi2 = associate_frame(
            locate_arguments, tof, snr_db, amplitude, offset
        )
        status[f] = frame_status
        n = frame_chi2.shape[0]
        used = found[f]
        echo_use = _with_room(echo_use, used, n)
        positions = _with_room(positions, used, n)
        covariances = _with_room(covariances, used, n)
        chi2 = _with_room(chi2, used, n)
        echo_use[used : used + n] = frame_use
        positions[used : used + n] = frame_positions
        covariances[used : used + n] = frame_covariances
        chi2[used : used + n] = frame_chi2
        found[f + 1] = used + n
    n = found[n_frames]
    return status, found, echo_use[:n], positions[:n], covariances[:n], chi2[:n]
