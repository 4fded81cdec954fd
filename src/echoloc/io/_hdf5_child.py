"""The child process that reads an HDF5 recording for :func:`echoloc.io.recording.read_recording`.

Why a child: a corrupt HDF5 file can make libhdf5 loop forever (one byte of a global
heap's size can do it) or allocate without end, inside C code where Python's signal
handlers never run, so neither a deadline nor Ctrl-C nor SIGTERM could end it. Here
the libhdf5 calls run in a process the reader can abandon: it kills the child when
no bytes come for a while (:func:`echoloc.io.recording.hdf5_stall_timeout_s`, set by
``ECHOLOC_HDF5_STALL_S``), and the parent itself only ever waits in Python, where
signals are honoured. The parent starts it isolated (``python -I``) with its own import
path minus the current directory, so no module lying in that directory is imported.

Protocol on stdout, each message ``kind (1 byte) + length (8 bytes, little-endian) +
payload``: ``R`` (ready: imports done), ``H`` (the header: JSON of the root
attributes and each dataset's shape, dtype and storage), then, after the parent
sends on stdin the JSON list of datasets it wants, ``D`` blocks with their raw
C-order bytes in the file's dtype, in that order, and ``Z`` (done). ``E`` carries a
one-line message at any point and ends the child. Only metadata is read before the
parent has checked the declared shapes against each other and a size limit.
"""

from __future__ import annotations

import json
import os
import struct
import sys
from typing import Any, BinaryIO

SLICE_BYTES = 4 << 20
"""The most bytes of a dataset read from libhdf5 at once (rows along axis 0)."""

MEMORY_HEADROOM_BYTES = 768 << 20
"""Address space the child may add past what its imports took: a corrupt file that
makes libhdf5 allocate without end fails here instead of taking the machine."""

ATTRIBUTES = (
    "format",
    "version",
    "sample_rate_hz",
    "signal_kind",
    "firing",
    "truth_kinds",
    "carrier_hz",
    "speed_of_sound_m_s",
    "temperature_c",
    "relative_humidity",
    "field_of_view_deg",
)


def send(out: BinaryIO, kind: bytes, payload: bytes | memoryview = b"") -> None:
    """One message to the parent."""
    out.write(kind + struct.pack("<Q", len(payload)))
    out.write(payload)
    out.flush()


def _limit_memory() -> None:
    """Cap the address space at what the imports took plus :data:`MEMORY_HEADROOM_BYTES` (Linux)."""
    try:
        import resource

        with open("/proc/self/statm", encoding="ascii") as fh:
            pages = int(fh.read().split()[0])
        used = pages * os.sysconf("SC_PAGE_SIZE")
        limit = used + MEMORY_HEADROOM_BYTES
        _, hard = resource.getrlimit(resource.RLIMIT_AS)
        if hard != resource.RLIM_INFINITY:
            limit = min(limit, hard)
        resource.setrlimit(resource.RLIMIT_AS, (limit, hard))
    except (ImportError, OSError, ValueError):  # not Linux: no cap, the deadline still holds
        pass


def _die_with_parent(parent_pid: int) -> None:
    """Have the kernel kill this process when its parent dies (Linux): a parent killed
    by SIGKILL must not leave a child looping in libhdf5 for ever."""
    try:
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        pr_set_pdeathsig = 1
        libc.prctl(pr_set_pdeathsig, signal.SIGKILL)
    except (OSError, AttributeError):  # not Linux: the parent's kill on exit is all there is
        pass
    if os.getppid() != parent_pid:  # the parent died before prctl took effect
        os._exit(1)


def _attribute(value: Any) -> dict[str, Any]:
    """An attribute as JSON: a plain value, bytes as hex, anything else as its repr."""
    import numpy as np

    if isinstance(value, np.ndarray) and value.size == 1:
        value = value.reshape(()).item()
    elif isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, bytes):
        try:
            value = value.decode("utf-8")
        except UnicodeDecodeError:
            return {"bytes": value[:200].hex()}
    if isinstance(value, bool | int | float | str):
        return {"value": value}
    return {"repr": repr(value)[:200]}


def _describe(item: Any) -> dict[str, Any]:
    """A dataset's shape, dtype and storage: metadata only, no data read."""
    import h5py
    import numpy as np

    if not isinstance(item, h5py.Dataset):
        return {"kind": type(item).__name__}
    dtype = item.dtype
    plain = dtype.kind in "biufc" and dtype.fields is None and dtype.subdtype is None
    plist = item.id.get_create_plist()
    return {
        "kind": "Dataset",
        "shape": None if item.shape is None else [int(n) for n in item.shape],
        "dtype": str(dtype),
        "descr": np.lib.format.dtype_to_descr(dtype) if plain else None,
        "stored": int(item.id.get_storage_size()),
        "filtered": plist.get_nfilters() > 0,
        "external": plist.get_external_count() > 0,
        "virtual": bool(item.is_virtual),
    }


def _stream(out: BinaryIO, dataset: Any) -> None:
    """The dataset's bytes in C order, in slices of at most :data:`SLICE_BYTES` along axis 0."""
    import numpy as np

    shape = dataset.shape
    if len(shape) == 0 or 0 in shape:
        arr = np.ascontiguousarray(dataset[()])
        if arr.nbytes:
            send(out, b"D", arr.reshape(-1).view(np.uint8).data)
        return
    row_bytes = max(1, dataset.dtype.itemsize * int(np.prod(shape[1:])))
    rows = max(1, SLICE_BYTES // row_bytes)
    for start in range(0, shape[0], rows):
        arr = np.ascontiguousarray(dataset[start : start + rows])
        send(out, b"D", arr.reshape(-1).view(np.uint8).data)


def main() -> None:
    """Read ``sys.argv[1]`` (datasets named in the JSON list ``sys.argv[2]``; the parent's
    pid in ``sys.argv[3]``) as the module docstring says."""
    out = sys.stdout.buffer
    _die_with_parent(int(sys.argv[3]))
    import h5py
    import numpy as np

    del np
    _limit_memory()
    send(out, b"R")
    path = sys.argv[1]
    try:
        if not h5py.is_hdf5(path):
            send(out, b"E", b"not an HDF5 file (no HDF5 signature)")
            return
        with h5py.File(path, "r") as f:
            attrs = {name: _attribute(f.attrs[name]) for name in ATTRIBUTES if name in f.attrs}
            names = json.loads(sys.argv[2])
            datasets = {name: _describe(f[name]) for name in names if name in f}
            header = json.dumps({"attrs": attrs, "datasets": datasets}).encode()
            send(out, b"H", header)
            wanted = json.loads(sys.stdin.readline() or "[]")
            for name in wanted:
                _stream(out, f[name])
            send(out, b"Z")
    except BrokenPipeError:  # the parent refused the file and went away
        return
    except (OSError, ValueError, KeyError, TypeError, RuntimeError, MemoryError) as exc:
        message = " ".join(f"cannot read as HDF5: {exc}".split())
        send(out, b"E", message.encode("utf-8", "replace"))


if __name__ == "__main__":
    main()
