"""The Dask cluster echoloc's scale-out runs on: a LocalCluster on 127.0.0.1, or one you name.

``echoloc batch`` and ``echoloc sweep`` submit their tasks to a ``dask.distributed``
client (:func:`open_client`): by default a LocalCluster of as many single-threaded worker
processes as the machine has cores (numba's kernels and numpy's FFTs use one thread each,
so processes, not threads, share the cores out), its scheduler, workers and dashboard
bound to 127.0.0.1; with ``--scheduler tcp://HOST:8786``, an existing cluster. Each
worker loads echoloc's compiled kernels once, as it starts
(:class:`echoloc.scale._plugin.KernelWarmup`), from
numba's cache on disk (compiled once per machine, ``echoloc warmup``), so no task pays
for it. dask is the ``cluster`` extra (``pip install 'echoloc[cluster]'``).
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from echoloc.errors import EchoLocError

LOCAL_HOST = "127.0.0.1"
"""Where a LocalCluster listens: this machine only."""


def _distributed() -> Any:
    try:
        import distributed
    except ImportError:
        raise EchoLocError(
            "running on Dask needs dask.distributed, which is not installed: pip install 'echoloc[cluster]'"
        ) from None
    return distributed


def _kernel_warmup() -> Any:
    from echoloc.scale._plugin import KernelWarmup

    return KernelWarmup()


def default_workers() -> int:
    """Worker processes of a LocalCluster: the cores this process may use."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)


@contextmanager
def open_client(scheduler: str | None = None, workers: int | None = None) -> Iterator[Any]:
    """A ``distributed.Client``: on the cluster at ``scheduler`` (``tcp://HOST:PORT``), or on a
    LocalCluster of ``workers`` single-threaded processes (default :func:`default_workers`),
    every part of it bound to 127.0.0.1. Closed (and a LocalCluster shut down) on exit."""
    distributed = _distributed()
    if workers is not None and workers < 1:
        raise EchoLocError(f"--workers must be >= 1, got {workers}")
    if scheduler is not None:
        if workers is not None:
            raise EchoLocError("--workers sizes a local cluster; an existing one (--scheduler) has its own")
        try:
            client = distributed.Client(scheduler, timeout="10s")
        except (OSError, TimeoutError) as error:
            raise EchoLocError(f"cannot reach the Dask scheduler at {scheduler}: {error}") from None
        try:
            client.register_plugin(_kernel_warmup())
            yield client
        finally:
            client.close()
        return
    from echoloc.warmup import kernels_cold

    if kernels_cold():
        # Compiled here once, before the workers start: several processes compiling the same
        # kernels into one cache at once would each do the whole work (and race on its files).
        from echoloc.realtime.stream import warm_kernels

        warm_kernels()
    import dask

    # dask's nanny gives its workers MALLOC_TRIM_THRESHOLD_=65536, which makes glibc map every
    # array over 128 kB afresh: the chain then runs 1.3-1.6 times slower in a worker than in
    # this process (benchmarks/results/sweep.md). echoloc's tasks hold no long-lived memory to
    # trim, so the workers keep glibc's defaults (and so does a cluster started after this one).
    os.environ.pop("MALLOC_TRIM_THRESHOLD_", None)
    with dask.config.set({"distributed.nanny.pre-spawn-environ.MALLOC_TRIM_THRESHOLD_": None}):
        cluster = distributed.LocalCluster(
            n_workers=workers or default_workers(),
            threads_per_worker=1,
            processes=True,
            host=LOCAL_HOST,
            dashboard_address=f"{LOCAL_HOST}:0",
            scheduler_port=0,
            silence_logs=40,  # errors only: a worker's own log lines are not the user's business
        )
    try:
        client = distributed.Client(cluster)
        try:
            client.register_plugin(_kernel_warmup())
            yield client
        finally:
            client.close()
    finally:
        cluster.close()
