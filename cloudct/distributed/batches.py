"""Photon batches on Dask workers, images and gradients reduced on the client in batch order.

A render or a gradient is a sum over independent photon batches (batch b owns photon indices
``b * per_batch + k``, see :func:`cloudct.mc.render.render_batches`), so the batches can be
traced anywhere. Given a :class:`~cloudct.distributed.executor.DaskExecutor`
(``executor=``), the engine's calls :func:`cloudct.mc.render.render` /
:func:`~cloudct.mc.render.render_batches` and the gradients of :mod:`cloudct.mc.gradient`
(path score function, DRT, sample matching), and given a Dask client, scheduler
address or executor (``client=``), :func:`cloudct.retrieval.loss.loss_and_gradient`,
:class:`cloudct.retrieval.loop.Retrieval` and
:class:`~cloudct.distributed.recycling.DistributedRecycler` (path recycling with the paths
kept on the workers), submit ranges of batches to the workers. Each task returns the
per-batch arrays of its range (not yet reduced), the client puts them back in batch order
and reduces them exactly as the single-process code does (mean and standard deviation over
batches), so the results are bitwise those of one process for the same seed, whatever the
number of workers or tasks.

Where a sample index depends on the batch count, the split changes. Backward renders and
the camera-side gradients (DRT, sample matching) with every pixel traced index sample k of
pixel p in batch b as ``(p * batches + b) * per_batch + k``: a range of batches is not a
shifted range of samples. Backward renders are split over views instead; each view of each
batch is still computed whole, and a pixel's value is its own sum. A camera-side gradient
adds the terms of every pixel into the same voxels, so a split over views would add them in
another order (equal to rounding only). It is split over batches, and a task traces its
batches one at a time, batch b as the only batch of a kernel call with ``batches *
per_batch`` samples per batch and the sample range shifted by ``b * per_batch``: the indices
``p * batches * per_batch + b * per_batch + k`` and the order of additions (in the rounds
of :func:`cloudct.mc.estimate.run_in_rounds`) are those of the whole run
(:func:`batch_task`); such a task runs on one numba thread. With pixels drawn from
the alias table (residual pixel sampling, the retrieval's default) the index is ``b *
per_batch + k``, and a task traces its range of batches at once, as a forward task does.

What moves: the kernel inputs (medium and cameras, :class:`~cloudct.mc.estimate.KernelInputs`)
are scattered once per call to every worker (``client.scatter(..., broadcast=True)``) and
re-used by every task of the call (a second call with the same medium re-uses them: the
scatter is cached by content); the gradient's residual (with the camera-side gradients'
alias table) is scattered the same way; the results come back as per-batch arrays. Each
call reports the bytes in ``info`` / ``attrs`` (``bytes_to_workers``,
``bytes_from_workers``).

Failures: a task whose worker dies is re-run elsewhere by the scheduler (Dask's
``distributed.scheduler.allowed-failures``); a task that keeps killing workers, or any other
task error, makes the call raise (:class:`DistributedError` for dead workers). A worker
that dies with the last copy of a call's scattered inputs (Dask's memory manager keeps one
copy of data no task waits for) makes the scheduler forget the call's tasks: the client
scatters the inputs again and submits the tasks once more
(:meth:`~cloudct.distributed.executor.DaskExecutor.gather_shared`). A result is
only reduced when every submitted batch came back exactly once (checked), never a partial
sum.

Dask is imported only in :mod:`cloudct.distributed`, and only when a client is given: the
single-machine path does not need it (``pip install 'cloudct[distributed]'``). See
docs/distributed.md.
"""

from __future__ import annotations

import math
import os
import socket
import time
import uuid
from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np

from cloudct.distributed.cluster import DistributedError
from cloudct.mc.backend import resolve_backend
from cloudct.mc.estimate import (
    BATCH_KERNELS,
    BY_BATCHES,
    BY_VIEWS,
    Sampling,
    batch_runner,
    run_in_rounds,
)

if TYPE_CHECKING:
    from cloudct.distributed.executor import DaskExecutor

#: Test-only fault injection: a callable run on the worker at the start of every task with
#: the task's kind and first batch (tests set it on the workers to kill them mid-call).
FAULT_HOOK: Callable[[str, int], None] | None = None


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


def run_range(run, offset: int, per_batch: int, *, in_rounds: bool = False) -> None:
    """Run photons ``offset .. offset + per_batch - 1`` of every batch of a runner of
    :func:`cloudct.mc.estimate.batch_runner` and leave the results in its host arrays.

    The forward runners index photon k of their batch b as ``b * per_batch + k``, so running
    ``k`` over ``first_batch * per_batch + (0 .. per_batch - 1)`` on arrays of ``count``
    batches traces exactly batches ``first_batch .. first_batch + count - 1`` (with the same
    per-batch order of additions). ``in_rounds``: in the rounds of
    :func:`cloudct.mc.estimate.run_in_rounds` over ``0 .. per_batch - 1``, as one process
    runs them (this matters to the order of additions of the kernels that loop over pixels
    outside their samples). The CUDA launchers copy their results to the host in the round
    that ends at their own ``per_batch``; in any other range that is done here.
    """
    if in_rounds:
        run_in_rounds(lambda first, last: run(offset + first, offset + last), per_batch, 1,
                      False, unit="sample", desc="", max_rounds=run.max_rounds)
    else:
        run(offset, offset + per_batch)
    if hasattr(run, "finish") and offset + per_batch != run.per_batch:
        run.finish()


def _fault(kind: str, start: int) -> None:
    if FAULT_HOOK is not None:
        FAULT_HOOK(kind, start)


def view_subset(k, start: int, count: int):
    """The kernel inputs of views ``start .. start + count - 1`` only."""
    cams = k.cams
    sl = slice(start, start + count)
    sub = cams._replace(**{
        f: np.ascontiguousarray(getattr(cams, f)[sl])
        for f in cams._fields if isinstance(getattr(cams, f), np.ndarray)
    })
    return k._replace(cams=sub, copies=np.ascontiguousarray(k.copies[sl]))


def batch_task(kernel: str, k, sampling: Sampling, per_batch: int, args: tuple, start: int,
               count: int) -> BatchPart:
    """Items ``start .. start + count - 1`` of a call of the batch kernel ``kernel``
    (:data:`cloudct.mc.estimate.BATCH_KERNELS`), as per-batch sums; the items are batches,
    or views of every batch, as the kernel's ``split(args)`` says:

    - :data:`~cloudct.mc.estimate.BY_BATCHES`: photon (or drawn sample) k of batch b has
      index ``b * per_batch + k``, so the range is traced at once on arrays of ``count``
      batches with the samples shifted by ``start * per_batch``.
    - :data:`~cloudct.mc.estimate.BY_VIEWS` (backward renders): sample k of pixel p in batch
      b is index ``(p * batches + b) * per_batch + k``; with the views before ``start`` left
      out, the local pixel p' = p - start * npix, so the samples are shifted by ``start *
      npix * batches * per_batch``.
    - :data:`~cloudct.mc.estimate.EACH_BATCH` (camera-side gradients of every pixel): the
      index ``(p * batches + b) * per_batch + k`` depends on the batch count, so each batch
      b is traced alone, as the one batch of a kernel call with ``batches * per_batch``
      samples per batch over samples ``b * per_batch + (0 .. per_batch - 1)`` (the index
      ``p * batches * per_batch + b * per_batch + k`` of the whole run), in the rounds of
      one process.
    """
    _fault(kernel, start)
    t0, c0 = time.perf_counter(), time.process_time()
    record = BATCH_KERNELS[kernel]
    backend = resolve_backend(sampling.backend)
    split = record.split(args)
    if split == BY_VIEWS:
        sub = view_subset(k, start, count)
        values = np.zeros((sampling.batches, *record.shape(sub, args)))
        events = np.zeros(sampling.batches, dtype=np.int64)
        run = batch_runner(kernel, backend, sub, sampling, per_batch, args, values, events)
        run_range(run, start * k.cams.nrows * k.cams.ncols * sampling.batches * per_batch,
                  per_batch)
    else:
        values = np.zeros((count, *record.shape(k, args)))
        events = np.zeros(count, dtype=np.int64)
        if split == BY_BATCHES:
            run = batch_runner(kernel, backend, k, sampling, per_batch, args, values, events)
            run_range(run, start * per_batch, per_batch)
        else:
            for i in range(count):
                run = batch_runner(kernel, backend, k, sampling, sampling.batches * per_batch,
                                   args, values[i:i + 1], events[i:i + 1])
                run_range(run, (start + i) * per_batch, per_batch, in_rounds=True)
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


def run_tasks(
    ex: DaskExecutor, task, inputs: Callable[[], tuple[tuple, int]],
    ranges: list[tuple[int, int]], *, total: int, axis: int, started: float, work: int,
    unit: str, desc: str, progress: bool | None,
) -> tuple[np.ndarray, list[BatchPart], CallStats]:
    """Submit ``task(*shared, start, count)`` for each of ``ranges``, where ``inputs()``
    scatters the shared arguments and returns ``(shared, bytes sent)`` (called again should
    a dying worker take them with it, :meth:`DaskExecutor.gather_shared`), gather the
    parts, check that they cover items 0 .. total - 1 exactly once and concatenate their
    values along ``axis`` in order (:func:`assemble`). ``work``: progress units per item
    (photons per batch, or samples per view); the call started at ``started``
    (``time.perf_counter()``). Returns the values, the parts in order and the call's
    bookkeeping (also appended to ``ex.calls``)."""
    counts = {}

    def submit(*shared) -> list:
        tag = uuid.uuid4().hex[:8]
        futures = [ex.submit(task, *shared, s, n,
                             key=f"cloudct-{desc.replace(' ', '-')}-{tag}-{s}")
                   for s, n in ranges]
        counts.update({f.key: n for f, (_, n) in zip(futures, ranges, strict=True)})
        return futures

    parts, sent = ex.gather_shared(
        inputs, submit, progress_total=work * total,
        progress_of=lambda f: counts[f.key] * work, progress=progress, unit=unit, desc=desc,
    )
    values, parts = assemble(parts, total, axis=axis)
    ex.last_parts = [p._replace(values=None) for p in parts]
    stats = CallStats(ex.workers, len(ranges), sent, sum(nbytes(p) for p in parts),
                      _backends(parts), time.perf_counter() - started)
    ex.calls.append(stats)
    return values, parts, stats


def _holds_arrays(obj: Any) -> bool:
    """Whether ``obj`` (nested tuples) holds an array: only then is it worth scattering
    once instead of sending it with every task (a render's arguments hold none)."""
    if isinstance(obj, np.ndarray):
        return True
    return isinstance(obj, tuple) and any(_holds_arrays(v) for v in obj)


def distributed_batch_sums(
    ex: DaskExecutor, kernel: str, k, args: tuple, *, per_batch: int, sampling: Sampling,
    progress: bool | None = False, desc: str = "",
) -> tuple[np.ndarray, np.ndarray, CallStats]:
    """Per-batch sums of a call of the batch kernel ``kernel`` traced on the workers, one
    range of batches (or of views, :func:`batch_task`) per task, with the per-batch path
    vertices and the call's bookkeeping. The kernel inputs are scattered once to every
    worker (cached by content for the next call), the kernel's ``args`` once per call where
    they hold arrays (a residual, an alias table)."""
    started = time.perf_counter()
    record = BATCH_KERNELS[kernel]

    def inputs() -> tuple[tuple, int]:
        k_future, sent = ex.share(k, cache=True)
        args_future, more = ex.share(args) if _holds_arrays(args) else (args, 0)
        return (kernel, k_future, sampling, per_batch, args_future), sent + more

    batches = sampling.batches
    if record.split(args) == BY_VIEWS:
        nview = k.cams.position.shape[0]
        per = max(1, math.ceil(nview / (ex.tasks_per_worker * ex.workers)))
        ranges = [(s, min(per, nview - s)) for s in range(0, nview, per)]
        values, parts, stats = run_tasks(
            ex, batch_task, inputs, ranges, total=nview, axis=1, started=started,
            work=per_batch * batches, unit=record.unit, desc=desc, progress=progress,
        )
        return values, np.sum([p.events for p in parts], axis=0), stats
    values, parts, stats = run_tasks(
        ex, batch_task, inputs, ex.ranges(batches), total=batches, axis=0, started=started,
        work=per_batch, unit=record.unit, desc=desc, progress=progress,
    )
    return values, np.concatenate([p.events for p in parts]), stats


def stats_info(stats: CallStats) -> dict:
    """The bookkeeping of a call as ``info`` / netCDF attributes."""
    return {
        "workers": stats.workers,
        "tasks": stats.tasks,
        "bytes_to_workers": stats.bytes_to_workers,
        "bytes_from_workers": stats.bytes_from_workers,
    }
