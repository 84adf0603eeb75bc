"""Choice of the compute back end: CPU kernels (numba, parallel over batches) or CUDA kernels.

``backend="cpu"`` runs the ``@njit`` batch kernels; ``"cuda"`` the kernels of
:mod:`cloudct.mc.cuda_kernels` (needs numba-cuda and a GPU, or the CUDA simulator);
``"auto"`` CUDA where a GPU is available, else the CPU with a one-line warning. Both run the
same ``@njit`` per-photon routines with the same photon indexing and random streams.
:data:`cloudct.mc.estimate.BATCH_KERNELS` builds the runner of a batch kernel on the chosen
back end; this module imports no estimator.
"""

from __future__ import annotations

import importlib.util
import sys
import warnings
from pathlib import Path

import numpy as np

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
    warnings.warn(f"backend='auto': {reason}; running on the CPU", RuntimeWarning,
                  stacklevel=_level_outside_cloudct())
    return "cpu"


def _level_outside_cloudct() -> int:
    """The ``stacklevel`` of a warning issued by this module's caller that points at the
    first frame outside the cloudct package: the user's line, however deep in the engine
    the back end was resolved."""
    package = str(Path(__file__).resolve().parents[1])
    frame, level = sys._getframe(2), 2
    while frame is not None and str(Path(frame.f_code.co_filename).resolve()).startswith(package):
        frame, level = frame.f_back, level + 1
    return level


def device_description(backend: str) -> str:
    """The device a resolved back end runs on, in words: ``"the GPU NVIDIA H100 80GB HBM3"``
    or ``"the CPU (16 threads)"``."""
    if backend == "cuda":
        from numba import cuda

        name = cuda.get_current_device().name
        return f"the GPU {name.decode() if isinstance(name, bytes) else name}"
    from numba import config

    return f"the CPU ({config.NUMBA_NUM_THREADS} threads)"


def sort_by_path_length(lengths: np.ndarray) -> np.ndarray:
    """Indices that order paths by length (vertex or record count), stable: paths of equal
    length keep their order. Re-tracing (or replaying) paths in this order gives the threads
    of a GPU warp paths of similar length, so fewer of them idle (seed paper Sec. 5.3)."""
    return np.argsort(np.asarray(lengths), kind="stable")
