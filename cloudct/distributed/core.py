"""Scale-out over Dask: photon batches on workers, images and gradients reduced on the client.

A render or a gradient is a sum over independent photon batches (batch b owns photon indices
``b * per_batch + k``, see :func:`cloudct.mc.render.render_batches`), so the batches can be
traced anywhere. With a Dask client (or a scheduler address) the API calls

- :func:`cloudct.mc.render.render` / :func:`~cloudct.mc.render.render_batches`,
- :func:`cloudct.mc.gradient.score_function_gradient`,
- :func:`cloudct.retrieval.loss.loss_and_gradient` and :class:`cloudct.retrieval.loop.Retrieval`,
- :class:`DistributedRecycler` (path recycling with the paths kept on the workers),

submit ranges of batches to the workers. Each task returns the per-batch arrays of its
range (not yet reduced), the client puts them back in batch order and reduces them exactly
as the single-process code does (mean and standard deviation over batches), so the results
are bitwise those of one process for the same seed, whatever the number of workers or tasks.
(Backward renders are split over views instead of batches: their sample indices depend on
the batch count; each view of each batch is still computed whole, so the same holds.)

What moves: the kernel inputs (medium and cameras, :class:`~cloudct.mc.render.KernelInputs`)
are scattered once per call to every worker (``client.scatter(..., broadcast=True)``) and
re-used by every task of the call (a second call with the same medium re-uses them: the
scatter is cached by content); the gradient's residual is scattered the same way; the
results come back as per-batch arrays. Each call reports the bytes in ``info`` /
``attrs`` (``bytes_to_workers``, ``bytes_from_workers``).

Failures: a task whose worker dies is re-run elsewhere by the scheduler (Dask's
``distributed.scheduler.allowed-failures``); a task that keeps killing workers, or any other
task error, makes the call raise (:class:`DistributedError` for dead workers). A result is
only reduced when every submitted batch came back exactly once (checked), never a partial
sum.

Dask is imported only here, and only when a client is given: the single-machine path does
not need it (``pip install 'cloudct[distributed]'``). See docs/distributed.md.
"""

from __future__ import annotations

import logging
import math
import os
import socket
import time
import uuid
import weakref
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

import numpy as np

from cloudct.mc.backend import BACKENDS, backward_runner, forward_runner, resolve_backend
from cloudct.mc.forward import GRADIENT, RENDER

logger = logging.getLogger(__name__)

#: Test-only fault injection: a callable run on the worker at the start of every task with
#: the task's kind and first batch (tests set it on the workers to kill them mid-call).
FAULT_HOOK: Callable[[str, int], None] | None = None


class DistributedError(RuntimeError):
    """A distributed call could not complete (a worker died too often, or results are
    missing); no partial result is returned."""


# ------------------------------------------------------------------------------------------
# Connecting: clients, local clusters, executors
# ------------------------------------------------------------------------------------------


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


class CallStats(NamedTuple):
    """Bookkeeping of one distributed call (also merged into the call's ``info``)."""

    workers: int
    tasks: int
    bytes_to_workers: int
    bytes_from_workers: int
    backend: str
    wall_time: float


def nbytes(obj: Any) -> int:
    """Bytes of the arrays in ``obj`` (nested tuples, lists, dicts, NamedTuples, xarray
    objects), plus 8 per scalar: what serialising it moves, to within headers."""
    if isinstance(obj, np.ndarray):
        return int(obj.nbytes)
    if hasattr(obj, "variables") and hasattr(obj, "attrs"):  # xarray Dataset
        return int(sum(v.values.nbytes for v in obj.variables.values()))
    if isinstance(obj, dict):
        return sum(nbytes(v) for v in obj.values())
    if isinstance(obj, (tuple, list)):
        return sum(nbytes(v) for v in obj)
    if hasattr(obj, "__dict__") and not isinstance(obj, type):
        return nbytes(vars(obj))
    return 8


class DaskExecutor:
    """Runs batch tasks on a Dask cluster for the cloudct API calls.

    ``client`` is a :class:`distributed.Client`, a scheduler address, or None for the
    current default client. A call is split into about ``tasks_per_worker`` tasks per
    worker (several, so that a slow or busy worker takes fewer), but never into tasks of
    fewer batches than a worker has numba threads (its kernels are parallel over the
    batches of a task); ``batches_per_task`` overrides both (e.g. one task per GPU worker
    and call). None of this changes any result.
    Every API call that takes ``client=`` also takes a ``DaskExecutor``.
    """

    def __init__(self, client=None, *, tasks_per_worker: int = 4,
                 batches_per_task: int | None = None, cache_size: int = 2):
        distributed = _import_distributed()
        if client is None:
            client = distributed.default_client()
        elif isinstance(client, str):
            client = distributed.Client(client)
        self.client = client
        self.tasks_per_worker = int(tasks_per_worker)
        self.batches_per_task = batches_per_task
        self._cache: OrderedDict[str, tuple[Any, int]] = OrderedDict()
        self._cache_size = int(cache_size)
        #: Bookkeeping of every call (CallStats), in order.
        self.calls: list[CallStats] = []
        self._threads: tuple[frozenset, int] | None = None
        #: The last call's task results without their arrays (timings, worker processes).
        self.last_parts: list[BatchPart] = []

    @property
    def workers(self) -> int:
        """Number of workers connected now (at least 1: waits for one)."""
        n = len(self.client.scheduler_info(n_workers=-1)["workers"])
        if n == 0:
            self.client.wait_for_workers(1)
            n = len(self.client.scheduler_info(n_workers=-1)["workers"])
        return n

    def ranges(self, total: int) -> list[tuple[int, int]]:
        """Split items 0 .. total - 1 into contiguous (start, count) task ranges."""
        if self.batches_per_task is not None:
            per = max(1, int(self.batches_per_task))
        else:
            per = max(self.worker_threads(),
                      math.ceil(total / (self.tasks_per_worker * self.workers)))
        return [(s, min(per, total - s)) for s in range(0, total, per)]

    def worker_threads(self) -> int:
        """The smallest number of numba threads of the workers (asked once per set of
        workers)."""
        addresses = frozenset(self.client.scheduler_info(n_workers=-1)["workers"])
        if self._threads is None or self._threads[0] != addresses:
            try:
                threads = self.client.run(_numba_threads)
            except Exception:  # a worker going away while asked: assume one thread
                threads = {}
            self._threads = (addresses, max(1, min(threads.values(), default=1)))
        return self._threads[1]

    def share(self, obj: Any, *, cache: bool = False) -> tuple[Any, int]:
        """Scatter ``obj`` to every worker once; returns ``(future, bytes sent)``. With
        ``cache``, an object of the same content scattered before is re-used (0 bytes)."""
        key = None
        if cache:
            from dask.base import tokenize

            key = tokenize(obj)
            if key in self._cache and self._cache[key][0].status == "finished":
                self._cache.move_to_end(key)
                return self._cache[key][0], 0
        workers = self.workers
        [future] = self.client.scatter([obj], broadcast=True, hash=False)
        sent = nbytes(obj) * workers
        if cache:
            self._cache[key] = (future, sent)
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return future, sent

    def submit(self, func, *args, key: str, **kwargs):
        """Submit one task (impure: it always runs)."""
        return self.client.submit(func, *args, key=key, pure=False, **kwargs)

    def gather(self, futures: list, progress_total: int = 0, progress_of=None,
               progress: bool | None = False, unit: str = "photon", desc: str = "") -> list:
        """Results of ``futures`` in their order, with a progress bar as they complete.
        Raises :class:`DistributedError` when workers died too often or a task was
        cancelled (a dying worker can take the call's scattered inputs with it, and the
        scheduler then cancels the tasks that need them), and re-raises the error of a task
        that failed; cancels the other tasks then."""
        distributed = _import_distributed()
        from distributed.client import FutureCancelledError
        from tqdm.auto import tqdm

        disable = None if progress is None else not progress
        try:
            with tqdm(total=progress_total, disable=disable, unit=unit, desc=desc) as bar:
                for future in distributed.as_completed(futures):
                    if future.status == "error":
                        future.result()  # raises the task's error
                    if progress_of is not None:
                        bar.update(progress_of(future))
            return self.client.gather(futures)
        except distributed.KilledWorker as err:
            task = getattr(err, "task", err.args[0] if err.args else "a task")
            raise DistributedError(
                f"a Dask worker died while running {task!r} (more often than "
                "distributed.scheduler.allowed-failures allows); the call was abandoned and "
                "no partial result is returned"
            ) from err
        except FutureCancelledError as err:
            raise DistributedError(
                f"the Dask scheduler cancelled a task of this call ({err}); when a worker "
                "dies, the data scattered to it can be lost with it. The call was abandoned "
                "and no partial result is returned"
            ) from err
        finally:
            self.client.cancel([f for f in futures if not f.done()])

    def close(self) -> None:
        """Release scattered data (the client stays open)."""
        self._cache.clear()


def _numba_threads() -> int:
    import numba

    return int(numba.config.NUMBA_NUM_THREADS)


_EXECUTORS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_BY_ADDRESS: dict[str, DaskExecutor] = {}


def executor(client) -> DaskExecutor:
    """A :class:`DaskExecutor` for ``client`` (a client, an address or an executor); the
    same one for every call with the same client, so that a medium scattered by one call is
    re-used by the next (e.g. the images and the gradient of one iteration)."""
    if isinstance(client, DaskExecutor):
        return client
    if client is None:
        return DaskExecutor(None)
    if isinstance(client, str):
        if client not in _BY_ADDRESS:
            _BY_ADDRESS[client] = DaskExecutor(client)
        return _BY_ADDRESS[client]
    ex = _EXECUTORS.get(client)
    if ex is None:
        ex = _EXECUTORS[client] = DaskExecutor(client)
    return ex


# ------------------------------------------------------------------------------------------
# Worker side
# ------------------------------------------------------------------------------------------


class BatchPart(NamedTuple):
    """What a task returns: per-batch sums of a range of batches (or, for backward renders,
    of a range of views of every batch)."""

    start: int  # first batch (forward) or first view (backward)
    count: int  # batches (forward) or views (backward) in ``values``
    values: np.ndarray  # per-batch sums (not divided by the photons per batch)
    events: np.ndarray  # int64[batches of the part]: path vertices
    backend: str
    seconds: float  # wall time of the task on the worker
    cpu_seconds: float = 0.0  # CPU time of the worker process during the task
    where: str = ""  # host:pid of the worker process


def _where() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def run_range(run, offset: int, per_batch: int) -> None:
    """Run photons ``offset .. offset + per_batch - 1`` of every batch of a runner of
    :mod:`cloudct.mc.backend` and leave the results in its host arrays.

    The runners index photon k of their batch b as ``b * per_batch + k``, so running
    ``k`` over ``first_batch * per_batch + (0 .. per_batch - 1)`` on arrays of ``count``
    batches traces exactly batches ``first_batch .. first_batch + count - 1`` (with the same
    per-batch order of additions). The CUDA launchers copy their results to the host in the
    round that ends at ``per_batch``; with an offset that is done here.
    """
    run(offset, offset + per_batch)
    if offset and hasattr(run, "finish"):
        run.finish()


def _fault(kind: str, start: int) -> None:
    if FAULT_HOOK is not None:
        FAULT_HOOK(kind, start)


def forward_task(k, backend: str, rr_depth: int, rr_survival: float, seed: int,
                 per_batch: int, mode: int, residual, start: int, count: int) -> BatchPart:
    """Batches ``start .. start + count - 1`` of a forward render (``mode`` RENDER: images)
    or score-function gradient (GRADIENT: per-voxel gradients), as per-batch sums."""
    _fault("forward", start)
    t0, c0 = time.perf_counter(), time.process_time()
    backend = resolve_backend(backend)
    events = np.zeros(count, dtype=np.int64)
    if mode == RENDER:
        values = np.zeros((count, k.cams.position.shape[0], k.cams.nrows, k.cams.ncols))
        other = np.zeros((count, 1, 1, 1))
        run = forward_runner(backend, k, rr_depth, rr_survival, seed, per_batch, RENDER,
                             values, np.zeros((1, 1, 1)), other, events)
    else:
        values = np.zeros((count, *k.grid.extinction.shape[1:]))
        other = np.zeros((count, 1, 1, 1))
        run = forward_runner(backend, k, rr_depth, rr_survival, seed, per_batch, GRADIENT,
                             other, residual, values, events)
    run_range(run, start * per_batch, per_batch)
    return BatchPart(start, count, values, events, backend, time.perf_counter() - t0,
                     time.process_time() - c0, _where())


def view_subset(k, start: int, count: int):
    """The kernel inputs of views ``start .. start + count - 1`` only."""
    cams = k.cams
    sl = slice(start, start + count)
    sub = cams._replace(**{
        f: np.ascontiguousarray(getattr(cams, f)[sl])
        for f in cams._fields if isinstance(getattr(cams, f), np.ndarray)
    })
    return k._replace(cams=sub, copies=np.ascontiguousarray(k.copies[sl]))


def backward_task(k, backend: str, rr_depth: int, rr_survival: float, seed: int,
                  per_batch: int, batches: int, start: int, count: int) -> BatchPart:
    """Views ``start .. start + count - 1`` of every batch of a backward render.

    Backward sample k of pixel p in batch b is index ``(p * batches + b) * per_batch + k``;
    with the views before ``start`` left out, the local pixel p' = p - start * npix, so the
    sample range is shifted by ``start * npix * batches * per_batch``.
    """
    _fault("backward", start)
    t0, c0 = time.perf_counter(), time.process_time()
    backend = resolve_backend(backend)
    sub = view_subset(k, start, count)
    values = np.zeros((batches, count, k.cams.nrows, k.cams.ncols))
    events = np.zeros(batches, dtype=np.int64)
    run = backward_runner(backend, sub, rr_depth, rr_survival, seed, per_batch, values, events)
    offset = start * k.cams.nrows * k.cams.ncols * batches * per_batch
    run_range(run, offset, per_batch)
    return BatchPart(start, count, values, events, backend, time.perf_counter() - t0,
                     time.process_time() - c0, _where())


# ------------------------------------------------------------------------------------------
# Client side: submission and ordered reduction
# ------------------------------------------------------------------------------------------


def assemble(parts: Sequence[BatchPart], total: int, axis: int = 0) -> tuple[np.ndarray, list]:
    """Concatenate parts along ``axis`` in order, after checking that they cover items
    0 .. total - 1 exactly once (no partial sums). Returns the array and the parts sorted."""
    parts = sorted(parts, key=lambda p: p.start)
    expected = 0
    for p in parts:
        if p.start != expected or p.count < 1 or p.values.shape[axis] != p.count:
            raise DistributedError(
                f"distributed results do not cover items 0..{total - 1} exactly once "
                f"(part at {p.start} of {p.count}, expected one at {expected}); refusing to "
                "reduce a partial sum"
            )
        expected += p.count
    if expected != total:
        raise DistributedError(
            f"distributed results cover {expected} of {total} items; refusing to reduce a "
            "partial sum"
        )
    return np.concatenate([p.values for p in parts], axis=axis), parts


def _backends(parts: Sequence[BatchPart]) -> str:
    return ",".join(sorted({p.backend for p in parts}))


def _check_backend(backend: str) -> None:
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")


def distributed_forward(
    client, k, *, mode: int, seed: int, per_batch: int, batches: int, rr_depth: int,
    rr_survival: float, residual: np.ndarray | None = None, backend: str = "cpu",
    progress: bool | None = False, desc: str = "render",
) -> tuple[np.ndarray, np.ndarray, CallStats]:
    """Per-batch sums of a forward render (RENDER: float64[batches, view, row, col]) or
    score-function gradient (GRADIENT: float64[batches, x, y, z]) traced on the workers,
    with the per-batch path vertices and the call's bookkeeping."""
    _check_backend(backend)
    ex = executor(client)
    start = time.perf_counter()
    k_future, sent = ex.share(k, cache=True)
    residual_future = None
    if mode == GRADIENT:
        residual_future, more = ex.share(np.ascontiguousarray(residual))
        sent += more
    tag = uuid.uuid4().hex[:8]
    ranges = ex.ranges(batches)
    futures = [
        ex.submit(forward_task, k_future, backend, rr_depth, rr_survival, seed, per_batch,
                  mode, residual_future, s, n, key=f"cloudct-{desc}-{tag}-{s}")
        for s, n in ranges
    ]
    counts = {f.key: n for f, (_, n) in zip(futures, ranges, strict=True)}
    parts = ex.gather(
        futures, per_batch * batches, lambda f: counts[f.key] * per_batch, progress,
        unit="photon", desc=desc,
    )
    values, parts = assemble(parts, batches)
    ex.last_parts = [p._replace(values=None) for p in parts]
    events = np.concatenate([p.events for p in parts])
    stats = CallStats(ex.workers, len(futures), sent, sum(nbytes(p) for p in parts),
                      _backends(parts), time.perf_counter() - start)
    ex.calls.append(stats)
    return values, events, stats


def distributed_backward(
    client, k, *, seed: int, per_batch: int, batches: int, rr_depth: int, rr_survival: float,
    backend: str = "cpu", progress: bool | None = False,
) -> tuple[np.ndarray, np.ndarray, CallStats]:
    """Per-batch sums of a backward render, float64[batches, view, row, col], traced on the
    workers one range of views per task, with the per-batch path vertices."""
    _check_backend(backend)
    ex = executor(client)
    start = time.perf_counter()
    k_future, sent = ex.share(k, cache=True)
    nview = k.cams.position.shape[0]
    per = max(1, math.ceil(nview / (ex.tasks_per_worker * ex.workers)))
    ranges = [(s, min(per, nview - s)) for s in range(0, nview, per)]
    tag = uuid.uuid4().hex[:8]
    futures = [
        ex.submit(backward_task, k_future, backend, rr_depth, rr_survival, seed, per_batch,
                  batches, s, n, key=f"cloudct-backward-{tag}-{s}")
        for s, n in ranges
    ]
    counts = {f.key: n for f, (_, n) in zip(futures, ranges, strict=True)}
    parts = ex.gather(
        futures, per_batch * batches * nview, lambda f: counts[f.key] * per_batch * batches,
        progress, unit="sample/px", desc="backward",
    )
    values, parts = assemble(parts, nview, axis=1)
    ex.last_parts = [p._replace(values=None) for p in parts]
    events = np.sum([p.events for p in parts], axis=0)
    stats = CallStats(ex.workers, len(futures), sent, sum(nbytes(p) for p in parts),
                      _backends(parts), time.perf_counter() - start)
    ex.calls.append(stats)
    return values, events, stats


def stats_info(stats: CallStats) -> dict:
    """The bookkeeping of a call as ``info`` / netCDF attributes."""
    return {
        "workers": stats.workers,
        "tasks": stats.tasks,
        "bytes_to_workers": stats.bytes_to_workers,
        "bytes_from_workers": stats.bytes_from_workers,
    }


def render_batch_means(
    client, k, *, method: str, seed: int, per_batch: int, batches: int, rr_depth: int,
    rr_survival: float, backend: str, progress: bool | None,
) -> tuple[np.ndarray, dict]:
    """What :func:`cloudct.mc.render.render_batches` returns, traced on the workers: the
    images of each batch and the run's attributes (plus the call's bookkeeping)."""
    if method == "forward":
        values, events, stats = distributed_forward(
            client, k, mode=RENDER, seed=seed, per_batch=per_batch, batches=batches,
            rr_depth=rr_depth, rr_survival=rr_survival, backend=backend, progress=progress,
        )
    else:
        values, events, stats = distributed_backward(
            client, k, seed=seed, per_batch=per_batch, batches=batches, rr_depth=rr_depth,
            rr_survival=rr_survival, backend=backend, progress=progress,
        )
    info = dict(
        method=method, photons=per_batch * batches, seed=seed, batches=batches,
        events=int(events.sum()), wall_time=stats.wall_time, rr_depth=rr_depth,
        rr_survival=rr_survival, aim_fraction=k.cams.aim_fraction, backend=stats.backend,
        **stats_info(stats),
    )
    return values / per_batch, info


def gradient_batch_means(
    client, k, residual: np.ndarray, *, seed: int, per_batch: int, batches: int,
    rr_depth: int, rr_survival: float, backend: str, progress: bool | None,
) -> tuple[np.ndarray, dict]:
    """The per-batch score-function gradients of
    :func:`cloudct.mc.gradient.score_function_gradient`, traced on the workers, and its
    ``info`` (plus the call's bookkeeping)."""
    values, events, stats = distributed_forward(
        client, k, mode=GRADIENT, seed=seed, per_batch=per_batch, batches=batches,
        rr_depth=rr_depth, rr_survival=rr_survival, residual=residual, backend=backend,
        progress=progress, desc="gradient",
    )
    info = {"photons": per_batch * batches, "events": int(events.sum()),
            "wall_time": stats.wall_time, "backend": stats.backend,
            "aim_fraction": k.cams.aim_fraction, **stats_info(stats)}
    return values / per_batch, info


__all__ = [
    "BatchPart",
    "CallStats",
    "DaskExecutor",
    "DistributedError",
    "assemble",
    "close_client",
    "connect",
    "distributed_backward",
    "distributed_forward",
    "executor",
    "gradient_batch_means",
    "local_cluster",
    "nbytes",
    "render_batch_means",
    "stats_info",
    "worker_environment",
]
