"""Connecting to Dask: clients, local clusters of CPU or GPU worker processes, and the
error a distributed call raises. Dask is imported only when a client is made."""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from typing import Any


class DistributedError(RuntimeError):
    """A distributed call could not complete (a worker died too often, or results are
    missing); no partial result is returned."""


def _import_distributed():
    try:
        import distributed
    except ImportError as err:  # pragma: no cover - depends on the installation
        raise ImportError(
            "a Dask client or scheduler needs dask.distributed: pip install 'cloudct[distributed]'"
        ) from err
    return distributed


def worker_environment(threads: int = 1, gpu: int | str | None = None) -> dict[str, str]:
    """Environment of a cloudct worker process: ``threads`` numba threads (the worker runs
    one task at a time; its numba kernels are parallel over the batches of the task) and,
    for a GPU worker, ``CUDA_VISIBLE_DEVICES`` = that one GPU."""
    env = {
        "NUMBA_NUM_THREADS": str(int(threads)),
        "OMP_NUM_THREADS": str(int(threads)),
        "MKL_NUM_THREADS": "1",
        "OPENBLAS_NUM_THREADS": "1",
    }
    if gpu is not None:
        env["CUDA_VISIBLE_DEVICES"] = str(gpu)
    return env


def local_cluster(
    workers: int | None = None,
    *,
    threads: int | None = None,
    gpus: Sequence[int | str] | None = None,
    dashboard_address: str = ":0",
    **cluster_kwargs: Any,
):
    """A :class:`distributed.Client` on a new cluster of worker processes on this machine.

    CPU: ``workers`` processes (default: one per core), each with one Dask thread (one task
    at a time) and ``threads`` numba threads (default: cores // workers, at least 1).
    GPU: with ``gpus`` (device ids, e.g. ``range(4)``), one single-threaded worker per GPU
    with ``CUDA_VISIBLE_DEVICES`` set to that GPU alone (no dask-cuda needed); run the calls
    with ``backend="cuda"``. The scheduler's web server (dashboard where bokeh is installed)
    listens on ``dashboard_address`` (default: a free port; ``client.dashboard_link``).
    ``client.close(); client.cluster.close()`` (or :func:`close_client`) stops it.

    The scheduler runs without work stealing, so that a task replaying a recycled path-store
    part runs on the worker that holds the part (stealing would copy the part to the
    thief); a part lost with its worker is still recomputed elsewhere. Use the same setting
    (``distributed.scheduler.work-stealing: false``) for clusters started by other means.
    """
    import dask

    # distributed registers its configuration defaults on import: import it before the
    # temporary setting, whose exit would otherwise remove the whole "distributed" section
    _import_distributed()
    with dask.config.set({"distributed.scheduler.work-stealing": False}):
        return _start_local_cluster(workers, threads, gpus, dashboard_address, cluster_kwargs)


def _start_local_cluster(workers, threads, gpus, dashboard_address, cluster_kwargs):
    distributed = _import_distributed()
    cores = os.cpu_count() or 1
    kwargs = {"dashboard_address": dashboard_address, "silence_logs": logging.WARNING}
    kwargs.update(cluster_kwargs)
    if gpus is not None:
        gpus = list(gpus)
        if not gpus:
            raise ValueError("gpus must name at least one device")
        host_threads = threads or 1
        specs = {
            f"gpu-{g}": {
                "cls": distributed.Nanny,
                "options": {"nthreads": 1, "env": worker_environment(host_threads, g)},
            }
            for g in gpus
        }
        scheduler = {
            "cls": distributed.Scheduler,
            "options": {"dashboard_address": kwargs.pop("dashboard_address")},
        }
        kwargs.pop("silence_logs", None)
        cluster = distributed.SpecCluster(workers=specs, scheduler=scheduler, **kwargs)
        client = distributed.Client(cluster, direct_to_workers=True)
        client.wait_for_workers(len(gpus))
        return client
    workers = int(workers or cores)
    if workers < 1:
        raise ValueError(f"workers must be positive, got {workers}")
    threads = int(threads or max(1, cores // workers))
    cluster = distributed.LocalCluster(
        n_workers=workers, threads_per_worker=1, processes=True,
        env=worker_environment(threads), **kwargs,
    )
    # results come straight from the workers, not through the scheduler
    client = distributed.Client(cluster, direct_to_workers=True)
    client.wait_for_workers(workers)
    return client


def close_client(client) -> None:
    """Close a client and, when it started its own cluster, the cluster."""
    cluster = getattr(client, "cluster", None)
    client.close()
    if cluster is not None:
        cluster.close()


def connect(scheduler=None, workers: int | None = None, *, backend: str = "cpu"):
    """A client for the command line: ``scheduler`` (an address or a scheduler file path) or
    a new local cluster of ``workers`` processes (GPU workers 0 .. workers - 1 with
    ``backend="cuda"``); None when neither is given (single process)."""
    if scheduler is not None and workers is not None:
        raise ValueError("give either a scheduler address or a number of workers, not both")
    if scheduler is not None:
        distributed = _import_distributed()
        if os.path.isfile(str(scheduler)):
            return distributed.Client(scheduler_file=str(scheduler))
        return distributed.Client(scheduler)
    if workers is not None:
        if backend == "cuda":
            return local_cluster(gpus=range(int(workers)))
        return local_cluster(int(workers))
    return None
