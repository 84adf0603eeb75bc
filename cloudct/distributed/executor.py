"""The Dask executor: runs the batch tasks of a call on a cluster's workers, keeps what it
scattered to them for the next call, and is what the engine's ``executor=`` takes
(:class:`cloudct.mc.executor.BatchExecutor`)."""

from __future__ import annotations

import math
import weakref
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np

from cloudct.distributed.batches import (
    BatchPart,
    CallStats,
    distributed_batch_sums,
    nbytes,
    stats_info,
)
from cloudct.distributed.cluster import DistributedError, _import_distributed
from cloudct.mc.estimate import Sampling


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
        return len(self.addresses())

    def addresses(self) -> list[str]:
        """Addresses of the workers connected now, sorted (at least 1: waits for one)."""
        found = self.client.scheduler_info(n_workers=-1)["workers"]
        if not found:
            self.client.wait_for_workers(1)
            found = self.client.scheduler_info(n_workers=-1)["workers"]
        return sorted(found)

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
        addresses = frozenset(self.addresses())
        if self._threads is None or self._threads[0] != addresses:
            try:
                threads = self.client.run(_numba_threads)
            except Exception:  # a worker going away while asked: assume one thread
                threads = {}
            self._threads = (addresses, max(1, min(threads.values(), default=1)))
        return self._threads[1]

    def share(self, obj: Any, *, cache: bool = False) -> tuple[Any, int]:
        """Scatter ``obj`` to every worker once; returns ``(future, bytes sent)``. With
        ``cache``, an object of the same content scattered before is re-used, copied to the
        workers that lack it (a worker that died took its copy; a new one has none): the
        object has no lineage, so it must outlive any one worker."""
        key = None
        if cache:
            from dask.base import tokenize

            key = tokenize(obj)
            if key in self._cache and self._cache[key][0].status == "finished":
                self._cache.move_to_end(key)
                future = self._cache[key][0]
                return future, self.everywhere(future, nbytes(obj))
        workers = self.workers
        [future] = self.client.scatter([obj], broadcast=True, hash=False)
        sent = nbytes(obj) * workers
        if cache:
            self._cache[key] = (future, sent)
            while len(self._cache) > self._cache_size:
                self._cache.popitem(last=False)
        return future, sent

    def everywhere(self, future, size: int) -> int:
        """Copy the data of ``future`` (shared, ``size`` bytes) to the workers connected now
        that lack it (one that died took its copy; its replacement has none); returns the
        bytes sent. Scattered data has no lineage: held by every worker, it outlives any one
        of them."""
        holders = set(self.client.who_has([future]).get(future.key, ()))
        lacking = set(self.addresses()) - holders
        if lacking:
            self.client.replicate([future])
        return size * len(lacking)

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

    def gather_shared(self, inputs: Callable[[], tuple[tuple, int]],
                      submit: Callable[..., list], **gather_kwargs) -> tuple[list, int]:
        """Results of the tasks ``submit(*shared)`` submits (in its order, as
        :meth:`gather` with ``gather_kwargs``), where ``inputs()`` scatters what they share
        and returns ``(shared, bytes sent)``; returns the results and the bytes sent.

        Scattered data has no lineage, and Dask's active memory manager drops the copies of
        it no waiting task needs: a worker that dies can take the last copy with it, and the
        scheduler then forgets the tasks that need it. Should a call end so, with one of its
        shared futures (nested tuples searched) lost, ``inputs()`` is called again (it
        scatters anew what was lost) and the tasks are submitted once more; they are seeded,
        so the result is the same."""
        shared, sent = inputs()
        try:
            return self.gather(submit(*shared), **gather_kwargs), sent
        except DistributedError:
            if not any(future.status != "finished" for future in _futures(shared)):
                raise
        shared, more = inputs()
        return self.gather(submit(*shared), **gather_kwargs), sent + more

    def close(self) -> None:
        """Release scattered data (the client stays open)."""
        self._cache.clear()

    def batch_sums(
        self, kernel: str, k, args: tuple, *, per_batch: int, sampling: Sampling,
        progress: bool | None = False, desc: str = "",
    ) -> tuple[np.ndarray, np.ndarray, dict]:
        """What :func:`cloudct.mc.estimate.batch_means` adds up in one process, traced on
        the workers (:class:`cloudct.mc.executor.BatchExecutor`): the per-batch sums of the
        batch kernel ``kernel``, the per-batch path vertices and the call's ``info`` (wall
        time, the back ends the workers ran, and the call's bookkeeping)."""
        values, events, stats = distributed_batch_sums(
            self, kernel, k, args, per_batch=per_batch, sampling=sampling, progress=progress,
            desc=desc or kernel,
        )
        info = {"wall_time": stats.wall_time, "backend": stats.backend, **stats_info(stats)}
        return values, events, info


def _futures(obj: Any) -> list:
    """The Dask futures in ``obj`` (nested tuples)."""
    if isinstance(obj, tuple):
        return [f for item in obj for f in _futures(item)]
    return [obj] if isinstance(obj, _import_distributed().Future) else []


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
