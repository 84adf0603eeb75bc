"""Runners of the estimators' batch kernels on a back end (:mod:`cloudct.mc.backend`).

A runner is what :func:`cloudct.mc.render.run_in_rounds` calls: ``run(first, last)`` traces
photons (or pixel samples) ``first .. last - 1`` of every batch and leaves the results in the
host arrays given to the runner once the round that ends at ``per_batch`` has run;
``run.max_rounds`` is the most rounds it should be called in. ``backend="cpu"`` runs
:func:`cloudct.mc.forward.forward_batches`, :func:`cloudct.mc.backward.backward_batches` and
:func:`cloudct.mc.camera_gradient.camera_gradient_batches`; ``"cuda"`` the launchers of
:mod:`cloudct.mc.cuda_kernels` (imported only then).
"""

from __future__ import annotations

import numpy as np

from cloudct.mc.backward import backward_batches
from cloudct.mc.camera_gradient import camera_gradient_batches
from cloudct.mc.forward import forward_batches


class _CPURunner:
    """Calls a CPU batch kernel with fixed arguments around ``first, last``."""

    max_rounds = 50

    def __init__(self, kernel, head: tuple, tail: tuple):
        self.kernel = kernel
        self.head = head
        self.tail = tail

    def __call__(self, first: int, last: int) -> None:
        self.kernel(*self.head, first, last, *self.tail)


def forward_runner(
    backend: str, k, rr_depth: int, rr_survival: float, seed: int, per_batch: int, mode: int,
    images: np.ndarray, residual: np.ndarray, gradients: np.ndarray, events: np.ndarray,
):
    """Runner of :func:`~cloudct.mc.forward.forward_batches` (RENDER or GRADIENT mode) on
    ``backend`` ("cpu" or "cuda"), ``k`` a :class:`~cloudct.mc.render.KernelInputs`."""
    if backend == "cuda":
        from cloudct.mc.cuda_kernels import ForwardLauncher

        return ForwardLauncher(
            k, rr_depth, rr_survival, seed, per_batch, mode, images, residual, gradients, events
        )
    head = (k.grid, k.bank, k.cams, k.copies, k.sun, k.periodic, k.ground, rr_depth,
            rr_survival, seed, per_batch)
    return _CPURunner(forward_batches, head, (mode, images, residual, gradients, events))


def backward_runner(
    backend: str, k, rr_depth: int, rr_survival: float, seed: int, per_batch: int,
    images: np.ndarray, events: np.ndarray,
):
    """Runner of :func:`~cloudct.mc.backward.backward_batches` on ``backend``."""
    if backend == "cuda":
        from cloudct.mc.cuda_kernels import BackwardLauncher

        return BackwardLauncher(k, rr_depth, rr_survival, seed, per_batch, images, events)
    head = (k.grid, k.bank, k.cams, k.sun, k.periodic, k.ground, rr_depth, rr_survival, seed,
            per_batch)
    return _CPURunner(backward_batches, head, (images, events))


def camera_gradient_runner(
    backend: str, k, rr_depth: int, rr_survival: float, seed: int, per_batch: int,
    method: tuple, residual: np.ndarray, table, gradients: np.ndarray, events: np.ndarray,
):
    """Runner of :func:`~cloudct.mc.camera_gradient.camera_gradient_batches` on ``backend``:
    ``method`` = (estimator code, probes, quadratic, mis) of DRT or sample matching, pixels
    uniform or from the alias ``table``."""
    if backend == "cuda":
        from cloudct.mc.cuda_kernels import CameraGradientLauncher

        return CameraGradientLauncher(
            k, rr_depth, rr_survival, seed, per_batch, method, residual, table, gradients,
            events,
        )
    head = (k.grid, k.bank, k.cams, k.sun, k.periodic, k.ground, rr_depth, rr_survival, seed,
            per_batch)
    return _CPURunner(camera_gradient_batches, head,
                      (*method, residual, table, gradients, events))
