"""What the renderer and the gradients need to trace their photon batches elsewhere.

A render or a gradient (path score function, DRT or sample matching) is a sum over
independent batches of paths, so its batches may be traced anywhere that returns them in
batch order. An object with the three methods of :class:`BatchExecutor` does that;
:class:`cloudct.distributed.DaskExecutor` is the one cloudct provides (Dask workers). The
engine never imports the scale-out layer: the executor is passed in (``executor=`` of
:func:`cloudct.mc.render.render`, :func:`cloudct.mc.gradient.score_function_gradient`,
:func:`~cloudct.mc.gradient.drt_gradient`,
:func:`~cloudct.mc.gradient.sample_matching_gradient` and
:func:`cloudct.mc.gradient.gradient_estimate`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from cloudct.mc.pixel_sampling import PixelTable


@runtime_checkable
class BatchExecutor(Protocol):
    """Traces the batches of a call on other processes and returns them in batch order.

    ``k`` is a :class:`cloudct.mc.render.KernelInputs`; the other arguments are those of
    the single-process call. Each returns the per-batch means (float64, batch first) and the
    call's ``info``, with the same values as :func:`cloudct.mc.render.render_batches`,
    :func:`cloudct.mc.gradient.score_function_gradient` and the camera-side gradients
    (:func:`cloudct.mc.gradient.drt_gradient`,
    :func:`~cloudct.mc.gradient.sample_matching_gradient`) compute in this process.
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

    def camera_gradient_batch_means(
        self, k, residual: np.ndarray, table: PixelTable, *, estimator_args: tuple, seed: int,
        per_batch: int, batches: int, rr_depth: int, rr_survival: float, backend: str,
        progress: bool | None,
    ) -> tuple[np.ndarray, dict]:
        """The DRT or sample-matching gradient of each batch, as
        :func:`cloudct.mc.camera_gradient.camera_gradient_batches` traces it with
        ``estimator_args`` = (estimator code, probes, quadratic, mis) and the pixels of the
        alias ``table`` (:func:`cloudct.mc.pixel_sampling.pixel_table`; empty: every pixel
        with a non-zero residual), divided by ``per_batch``; ``info`` holds at least the path
        vertices ("events"), the wall time and the back end."""


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
