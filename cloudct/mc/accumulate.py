"""Adding a contribution to a shared output array from inside a kernel.

Every kernel writes its images and gradients through :func:`add_to`. On the CPU each
batch owns its output array, so a plain addition is race-free; a GPU back end, where many
threads share one array, gives this function an atomic implementation for the CUDA target.
"""

from __future__ import annotations

from numba import njit


@njit(cache=True)
def add_to(array, i, j, k, value):
    """array[i, j, k] += value."""
    array[i, j, k] += value
