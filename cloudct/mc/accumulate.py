"""Adding a contribution to a shared output array from inside a kernel.

Every kernel writes its images and gradients through :func:`add_to`, the one operation of the
engine that differs between targets. It is a plain Python function with one numba
implementation per target (``numba.extending.overload``):

- ``cpu``: ``array[i, j, k] += value``. Each CPU batch owns its output array, so a plain
  addition is race-free (and compiles to exactly what an ``@njit`` function did).
- ``cuda``: ``cuda.atomic.add``, since many GPU threads share one array. It is registered by
  :func:`register_cuda_implementation`, which the CUDA back end
  (:mod:`cloudct.mc.cuda_kernels`) calls on import, so that importing cloudct never needs
  numba-cuda.

The ``@njit`` routines of the engine call ``add_to``; numba-cuda compiles those routines for
the GPU when a CUDA kernel calls them, and resolves ``add_to`` to the CUDA implementation
there.

:func:`inline_on_cpu` is the other difference: an ``inline=`` choice for ``@njit`` routines
that are inlined into the CPU kernels but stay calls on the GPU, whose code they leave as it
was.
"""

from __future__ import annotations

from numba import njit
from numba.core.target_extension import current_target
from numba.extending import overload


def add_to(array, i, j, k, value):
    """array[i, j, k] += value.

    Called from Python (not from compiled code: the CUDA simulator runs kernels as Python
    threads), it runs the compiled CPU addition, a single call under the GIL and so atomic
    with respect to other Python threads.
    """
    _add_to_cpu(array, i, j, k, value)


def inline_on_cpu(expr, caller_ir, callee_ir) -> bool:
    """``@njit(inline=inline_on_cpu)``: numba's cost model for inlining at its IR level, asked
    at every call site. Inline where a CPU kernel is compiled; where numba-cuda compiles a
    CUDA kernel (under the target ``"cuda"``) the routine stays a device function call."""
    return current_target() == "cpu"


def _add(array, i, j, k, value):
    array[i, j, k] += value


_add_to_cpu = njit(cache=True)(_add)


def add_along(gradient, voxels, lengths, start, stop, weight):
    """gradient[voxel] += weight x length for the crossings ``start .. stop - 1`` of a ray
    (``voxels[c]``: flat C-order index into the (x, y, z) array ``gradient``, ``lengths[c]``
    the length inside it), in order.

    Called from Python, the compiled CPU version runs. The CPU addresses a flat view of
    ``gradient``; the CUDA version (:func:`register_cuda_implementation`) turns each index
    into (x, y, z) by arithmetic instead, since ``reshape`` inside a CUDA kernel makes
    numba-cuda link a helper, and numba-cuda cannot cache a kernel with linked files.
    """
    _add_along_cpu(gradient, voxels, lengths, start, stop, weight)


def _add_along_flat(gradient, voxels, lengths, start, stop, weight):
    flat = gradient.reshape((1, 1, gradient.size))
    for c in range(start, stop):
        flat[0, 0, voxels[c]] += weight * lengths[c]


_add_along_cpu = njit(cache=True)(_add_along_flat)


@overload(add_along, target="cpu")
def _add_along_cpu_overload(gradient, voxels, lengths, start, stop, weight):
    return _add_along_flat


@overload(add_to, target="cpu")
def _add_to_cpu_overload(array, i, j, k, value):
    return _add


_cuda_registered = False


def register_cuda_implementation() -> None:
    """Give :func:`add_to` its atomic CUDA implementation (needs numba-cuda; idempotent)."""
    global _cuda_registered
    if _cuda_registered:
        return
    from numba import cuda
    from numba.cuda.extending import overload as cuda_overload

    def _atomic_add(array, i, j, k, value):
        cuda.atomic.add(array, (i, j, k), value)

    @cuda_overload(add_to, target="cuda")
    def _add_to_cuda_overload(array, i, j, k, value):
        return _atomic_add

    def _atomic_add_along(gradient, voxels, lengths, start, stop, weight):
        ny, nz = gradient.shape[1], gradient.shape[2]
        for c in range(start, stop):
            v = voxels[c]
            cuda.atomic.add(gradient, (v // (ny * nz), (v // nz) % ny, v % nz),
                            weight * lengths[c])

    @cuda_overload(add_along, target="cuda")
    def _add_along_cuda_overload(gradient, voxels, lengths, start, stop, weight):
        return _atomic_add_along

    _cuda_registered = True
