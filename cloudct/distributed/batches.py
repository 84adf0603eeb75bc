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
of :func:`cloudct.mc.render.run_in_rounds`) are those of the whole run
(:func:`camera_gradient_task`); such a task runs on one numba thread. With pixels drawn from
the alias table (residual pixel sampling, the retrieval's default) the index is ``b *
per_batch + k``, and a task traces its range of batches at once, as a forward task does.

What moves: the kernel inputs (medium and cameras, :class:`~cloudct.mc.render.KernelInputs`)
are scattered once per call to every worker (``client.scatter(..., broadcast=True)``) and
re-used by every task of the call (a second call with the same medium re-uses them: the
scatter is cached by content); the gradient's residual (with the camera-side gradients'
alias table) is scattered the same way; the results come back as per-batch arrays. Each
call reports the bytes in ``info`` / ``attrs`` (``bytes_to_workers``,
``bytes_from_workers``).

Failures: a task whose worker dies is re-run elsewhere by the scheduler (Dask's
``distributed.scheduler.allowed-failures``); a task that keeps killing workers, or any other
task error, makes the call raise (:class:`DistributedError` for dead workers). A result is
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
from cloudct.mc.backend import BACKENDS, resolve_backend
from cloudct.mc.forward import GRADIENT, RENDER
from cloudct.mc.render import run_in_rounds
from cloudct.mc.runners import backward_runner, camera_gradient_runner, forward_runner

if TYPE_CHECKING:
    from cloudct.distributed.executor import DaskExecutor
    from cloudct.mc.pixel_sampling import PixelTable

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
    :mod:`cloudct.mc.runners` and leave the results in its host arrays.

    The forward runners index photon k of their batch b as ``b * per_batch + k``, so running
    ``k`` over ``first_batch * per_batch + (0 .. per_batch - 1)`` on arrays of ``count``
    batches traces exactly batches ``first_batch .. first_batch + count - 1`` (with the same
    per-batch order of additions). ``in_rounds``: in the rounds of
    :func:`cloudct.mc.render.run_in_rounds` over ``0 .. per_batch - 1``, as one process
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


def camera_gradient_task(k, backend: str, rr_depth: int, rr_survival: float, seed: int,
                         per_batch: int, batches: int, estimator_args: tuple,
                         pixels: tuple[np.ndarray, PixelTable], start: int,
                         count: int) -> BatchPart:
    """Batches ``start .. start + count - 1`` of a DRT or sample-matching gradient
    (``estimator_args`` of :func:`cloudct.mc.runners.camera_gradient_runner`;
    ``pixels`` = (residual, alias table)), as per-batch sums.

    With an alias table, sample k of batch b has index ``b * per_batch + k``: the range of
    batches is traced at once with the samples shifted by ``start * per_batch``. Without
    one (every pixel), sample k of pixel p in batch b has index ``(p * batches + b) *
    per_batch + k``, which depends on the batch count: each batch b is then traced alone,
    as the one batch of a kernel call with ``batches * per_batch`` samples per batch over
    samples ``b * per_batch + (0 .. per_batch - 1)`` (the index ``p * batches * per_batch +
    b * per_batch + k`` of the whole run), in the rounds of one process.
    """
    _fault("camera-gradient", start)
    t0, c0 = time.perf_counter(), time.process_time()
    backend = resolve_backend(backend)
    residual, table = pixels
    values = np.zeros((count, *k.grid.extinction.shape[1:]))
    events = np.zeros(count, dtype=np.int64)
    if table.pixel.size:
        run = camera_gradient_runner(backend, k, rr_depth, rr_survival, seed, per_batch,
                                     estimator_args, residual, table, values, events)
        run_range(run, start * per_batch, per_batch)
    else:
        for i in range(count):
            run = camera_gradient_runner(
                backend, k, rr_depth, rr_survival, seed, batches * per_batch, estimator_args,
                residual, table, values[i:i + 1], events[i:i + 1],
            )
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


def _check_backend(backend: str) -> None:
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")


def run_tasks(
    ex: DaskExecutor, task, args: tuple, ranges: list[tuple[int, int]], *, total: int,
    axis: int, sent: int, started: float, work: int, unit: str, desc: str,
    progress: bool | None,
) -> tuple[np.ndarray, list[BatchPart], CallStats]:
    """Submit ``task(*args, start, count)`` for each of ``ranges``, gather the parts, check
    that they cover items 0 .. total - 1 exactly once and concatenate their values along
    ``axis`` in order (:func:`assemble`). ``work``: progress units per item (photons per
    batch, or samples per view); ``sent``: bytes already scattered for the call, which
    started at ``started`` (``time.perf_counter()``). Returns the values, the parts in
    order and the call's bookkeeping (also appended to ``ex.calls``)."""
    tag = uuid.uuid4().hex[:8]
    futures = [ex.submit(task, *args, s, n, key=f"cloudct-{desc.replace(' ', '-')}-{tag}-{s}")
               for s, n in ranges]
    counts = {f.key: n for f, (_, n) in zip(futures, ranges, strict=True)}
    parts = ex.gather(futures, work * total, lambda f: counts[f.key] * work, progress,
                      unit=unit, desc=desc)
    values, parts = assemble(parts, total, axis=axis)
    ex.last_parts = [p._replace(values=None) for p in parts]
    stats = CallStats(ex.workers, len(futures), sent, sum(nbytes(p) for p in parts),
                      _backends(parts), time.perf_counter() - started)
    ex.calls.append(stats)
    return values, parts, stats


def distributed_forward(
    ex: DaskExecutor, k, *, mode: int, seed: int, per_batch: int, batches: int, rr_depth: int,
    rr_survival: float, residual: np.ndarray | None = None, backend: str = "cpu",
    progress: bool | None = False, desc: str = "render",
) -> tuple[np.ndarray, np.ndarray, CallStats]:
    """Per-batch sums of a forward render (RENDER: float64[batches, view, row, col]) or
    score-function gradient (GRADIENT: float64[batches, x, y, z]) traced on the workers,
    with the per-batch path vertices and the call's bookkeeping."""
    _check_backend(backend)
    started = time.perf_counter()
    k_future, sent = ex.share(k, cache=True)
    residual_future = None
    if mode == GRADIENT:
        residual_future, more = ex.share(np.ascontiguousarray(residual))
        sent += more
    args = (k_future, backend, rr_depth, rr_survival, seed, per_batch, mode, residual_future)
    values, parts, stats = run_tasks(
        ex, forward_task, args, ex.ranges(batches), total=batches, axis=0, sent=sent,
        started=started, work=per_batch, unit="photon", desc=desc, progress=progress,
    )
    return values, np.concatenate([p.events for p in parts]), stats


def distributed_backward(
    ex: DaskExecutor, k, *, seed: int, per_batch: int, batches: int, rr_depth: int,
    rr_survival: float, backend: str = "cpu", progress: bool | None = False,
) -> tuple[np.ndarray, np.ndarray, CallStats]:
    """Per-batch sums of a backward render, float64[batches, view, row, col], traced on the
    workers one range of views per task, with the per-batch path vertices."""
    _check_backend(backend)
    started = time.perf_counter()
    k_future, sent = ex.share(k, cache=True)
    nview = k.cams.position.shape[0]
    per = max(1, math.ceil(nview / (ex.tasks_per_worker * ex.workers)))
    ranges = [(s, min(per, nview - s)) for s in range(0, nview, per)]
    args = (k_future, backend, rr_depth, rr_survival, seed, per_batch, batches)
    values, parts, stats = run_tasks(
        ex, backward_task, args, ranges, total=nview, axis=1, sent=sent, started=started,
        work=per_batch * batches, unit="sample/px", desc="backward", progress=progress,
    )
    return values, np.sum([p.events for p in parts], axis=0), stats


def distributed_camera_gradient(
    ex: DaskExecutor, k, residual: np.ndarray, table: PixelTable, *, estimator_args: tuple,
    seed: int, per_batch: int, batches: int, rr_depth: int, rr_survival: float,
    backend: str = "cpu", progress: bool | None = False, desc: str = "camera gradient",
) -> tuple[np.ndarray, np.ndarray, CallStats]:
    """Per-batch sums of a DRT or sample-matching gradient, float64[batches, x, y, z],
    traced on the workers one range of batches per task (:func:`camera_gradient_task`),
    with the per-batch path vertices and the call's bookkeeping. The residual and the
    alias table are scattered once to every worker."""
    _check_backend(backend)
    started = time.perf_counter()
    k_future, sent = ex.share(k, cache=True)
    pixels_future, more = ex.share((np.ascontiguousarray(residual), table))
    args = (k_future, backend, rr_depth, rr_survival, seed, per_batch, batches,
            estimator_args, pixels_future)
    values, parts, stats = run_tasks(
        ex, camera_gradient_task, args, ex.ranges(batches), total=batches, axis=0,
        sent=sent + more, started=started, work=per_batch, unit="sample", desc=desc,
        progress=progress,
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
