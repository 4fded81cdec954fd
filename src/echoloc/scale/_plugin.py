"""The worker plugin of :mod:`echoloc.scale.cluster` (imported only where dask.distributed is)."""

from __future__ import annotations

from typing import Any

from distributed import WorkerPlugin


class KernelWarmup(WorkerPlugin):
    """Load echoloc's compiled kernels as a worker starts, once.

    Loading them from numba's cache takes about a second a process; done here, the first
    task on each worker does not pay it and the timings of tasks stay comparable.
    """

    name = "echoloc-kernels"

    def setup(self, worker: Any) -> None:
        del worker
        from echoloc.realtime.stream import warm_kernels

        warm_kernels()
