"""What the renderer and the gradients need to trace their photon batches elsewhere.

A render or a score-function gradient is a sum over independent photon batches, so its
batches may be traced anywhere that returns them in batch order. An object with the two
methods of :class:`BatchExecutor` does that; :class:`cloudct.distributed.DaskExecutor` is
the one cloudct provides (Dask workers). The engine never imports the scale-out layer: the
executor is passed in (``executor=`` of :func:`cloudct.mc.render.render`,
:func:`cloudct.mc.gradient.score_function_gradient` and
:func:`cloudct.mc.gradient.gradient_estimate`).
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class BatchExecutor(Protocol):
    """Traces the batches of a call on other processes and returns them in batch order.

    ``k`` is a :class:`cloudct.mc.render.KernelInputs`; the other arguments are those of
    the single-process call. Both return the per-batch means (float64, batch first) and the
    call's ``info``, with the same values as :func:`cloudct.mc.render.render_batches` and
    :func:`cloudct.mc.gradient.score_function_gradient` compute in this process.
    """

    def render_batch_means(
        self, k, *, method: str, seed: int, per_batch: int, batches: int, rr_depth: int,
        rr_survival: float, backend: str, progress: bool | None,
    ) -> tuple[np.ndarray, dict]:
        """The images of each batch and the run's attributes."""

    def gradient_batch_means(
        self, k, residual: np.ndarray, *, seed: int, per_batch: int, batches: int,
        rr_depth: int, rr_survival: float, backend: str, progress: bool | None,
    ) -> tuple[np.ndarray, dict]:
        """The score-function gradient of each batch and the run's ``info``."""


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
