"""Choice of the compute back end: CPU kernels (numba, parallel over batches) or CUDA kernels.

``backend="cpu"`` runs :func:`cloudct.mc.forward.forward_batches` and
:func:`cloudct.mc.backward.backward_batches`; ``"cuda"`` the kernels of
:mod:`cloudct.mc.cuda_kernels` (imported only then; needs numba-cuda and a GPU, or the CUDA
simulator); ``"auto"`` CUDA where a GPU is available, else the CPU with a one-line warning.
Both run the same ``@njit`` per-photon routines with the same photon indexing and random
streams.

The runners returned here are what :func:`cloudct.mc.render.run_in_rounds` calls:
``run(first, last)`` traces photons (or pixel samples) ``first .. last - 1`` of every batch
and leaves the results in the host arrays given to the runner once the round that ends at
``per_batch`` has run; ``run.max_rounds`` is the most rounds it should be called in.
"""

from __future__ import annotations

import importlib.util
import warnings

import numpy as np

from cloudct.mc.backward import backward_batches
from cloudct.mc.forward import forward_batches

BACKENDS = ("cpu", "cuda", "auto")


def cuda_unavailable_reason() -> str | None:
    """Why the CUDA back end cannot run here, or None when it can (a GPU, or the simulator)."""
    if importlib.util.find_spec("numba_cuda") is None:
        return "numba-cuda is not installed (pip install 'cloudct[cuda]')"
    from numba import cuda

    try:
        available = cuda.is_available()
    except Exception as exc:  # a broken driver or toolkit install
        return f"CUDA is not usable ({exc})"
    if not available:
        return "no CUDA GPU is available"
    from numba import config

    if not config.ENABLE_CUDASIM:
        try:
            from numba.cuda.cudadrv.nvvm import NVVM

            NVVM()
        except Exception as exc:  # the GPU compiler of the CUDA toolkit
            return f"NVVM is not found ({exc}); pip install 'numba-cuda[cu12]'"
    return None


def resolve_backend(backend: str) -> str:
    """``"cpu"`` or ``"cuda"`` for a requested back end (see the module docstring)."""
    if backend not in BACKENDS:
        raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if backend == "cpu":
        return "cpu"
    reason = cuda_unavailable_reason()
    if reason is None:
        return "cuda"
    if backend == "cuda":
        raise RuntimeError(f"backend='cuda': {reason}")
    warnings.warn(f"backend='auto': {reason}; running on the CPU", RuntimeWarning, stacklevel=3)
    return "cpu"


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
    from cloudct.mc.camera_gradient import camera_gradient_batches

    head = (k.grid, k.bank, k.cams, k.sun, k.periodic, k.ground, rr_depth, rr_survival, seed,
            per_batch)
    return _CPURunner(camera_gradient_batches, head,
                      (*method, residual, table, gradients, events))


def sort_by_path_length(lengths: np.ndarray) -> np.ndarray:
    """Indices that order paths by length (vertex or record count), stable: paths of equal
    length keep their order. Re-tracing (or replaying) paths in this order gives the threads
    of a GPU warp paths of similar length, so fewer of them idle (seed paper Sec. 5.3)."""
    return np.argsort(np.asarray(lengths), kind="stable")
