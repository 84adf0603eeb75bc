"""What the engine needs to trace its photon batches elsewhere.

A render, a gradient (path score function, DRT or sample matching) or any other estimate
of :mod:`cloudct.mc.estimate` is a sum over independent batches of paths, so its batches may
be traced anywhere that returns them in batch order. An object with the one method of
:class:`BatchExecutor` does that for every batch kernel of
:data:`cloudct.mc.estimate.BATCH_KERNELS`; :class:`cloudct.distributed.DaskExecutor` is the
one cloudct provides (Dask workers). The engine never imports the scale-out layer: the
executor is passed in (``executor=`` of :func:`cloudct.mc.render.render`,
:func:`cloudct.mc.gradient.score_function_gradient`,
:func:`~cloudct.mc.gradient.drt_gradient`,
:func:`~cloudct.mc.gradient.sample_matching_gradient` and
:func:`cloudct.mc.gradient.gradient_estimate`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from cloudct.mc.estimate import KernelInputs, Sampling


@runtime_checkable
class BatchExecutor(Protocol):
    """Traces the batches of a call on other processes and returns them in batch order."""

    def batch_sums(
        self, kernel: str, k: KernelInputs, args: tuple, *, per_batch: int,
        sampling: Sampling, progress: bool | None, desc: str,
    ) -> tuple[np.ndarray, np.ndarray, dict]:
        """The per-batch sums of the batch kernel named ``kernel`` (float64[batches, ...],
        not divided by ``per_batch``), its per-batch path vertices (int64[batches]) and the
        call's ``info`` (at least "wall_time" and "backend"), bitwise what
        :func:`cloudct.mc.estimate.batch_means` adds up in this process for the same
        ``k``, ``args``, ``per_batch`` and ``sampling``."""


def check_executor(executor: object) -> BatchExecutor:
    """``executor`` if it is a :class:`BatchExecutor`, else a TypeError that says how to
    get one from a Dask client or a scheduler address."""
    if not isinstance(executor, BatchExecutor):
        raise TypeError(
            f"executor must be a BatchExecutor such as cloudct.distributed.DaskExecutor, got "
            f"{type(executor).__name__}; cloudct.distributed.executor(client) makes one of "
            "a Dask client or a scheduler address"
        )
    return executor
