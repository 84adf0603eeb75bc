"""How much host memory a render or a gradient needs at its peak, known before any work.

A Monte Carlo estimate keeps one sum per batch of every pixel (images) or of every voxel
(gradients), float64[batches, ...] (:func:`cloudct.mc.estimate.batch_means`), then the
batch means, then the deviations from their mean for the standard error, so that at the
peak :data:`PEAK_COPIES` arrays of that size are alive. On a large grid this is what fills the
memory: 32 batches of a 256 x 256 x 100 gradient are 1.7 GB per copy. The medium's kernel
arrays, the cameras' tables and the process itself come on top; :func:`peak_bytes` counts
those arrays and :func:`check_memory` compares the whole with what the machine has free
(``MemAvailable`` of ``/proc/meminfo``), refusing in one line where it cannot fit. Measured
against the peaks of real runs on three sizes: ``benchmarks/scale/memory.py``.
"""

from __future__ import annotations

import math
import os
from pathlib import Path

#: Arrays of the per-batch size alive at once: the batch sums and the batch means, or the
#: batch means and their deviations (the standard error squares them in place).
PEAK_COPIES = 2
#: float64 arrays of the grid's size held for the kernels (extinctions, albedos, phase
#: indices and weights, and the clouds' extinction, with copies for periodic boundaries).
GRID_ARRAYS = 10


def peak_bytes(voxels: int, pixels: int, batches: int, gradient: bool) -> int:
    """Bytes of the arrays of one estimate at its peak: per-batch images (``pixels`` in all
    views), or per-batch gradients (``voxels``) when ``gradient``, ``PEAK_COPIES`` times,
    and the grid's arrays; the process's own memory is not counted."""
    per_batch = voxels if gradient else pixels
    return 8 * (PEAK_COPIES * batches * per_batch + GRID_ARRAYS * voxels)


def resident_bytes() -> int:
    """This process's resident memory now (0 where ``/proc`` cannot tell)."""
    try:
        pages = int(Path("/proc/self/statm").read_text().split()[1])
    except (OSError, IndexError, ValueError):
        return 0
    return pages * os.sysconf("SC_PAGE_SIZE")


def available_bytes() -> int | None:
    """The memory the machine can give without swapping (``MemAvailable``), None if
    unknown."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError):
        return None
    return None


class NotEnoughMemory(ValueError):
    """An estimate whose arrays cannot fit in the memory free."""


def check_memory(what: str, need: int, way_out: str = "a coarser grid",
                 available: int | None = None) -> str:
    """The line that says ``what`` needs about ``need`` bytes beyond this process's memory
    and what is free; :class:`NotEnoughMemory` (with ``way_out``) where it does not fit."""
    free = available_bytes() if available is None else available
    line = (f"{what}: about {_gib(need)} of memory at its peak, beyond this process's "
            f"{_gib(resident_bytes())}")
    if free is None:
        return line + " (free memory unknown)"
    if need > free:
        raise NotEnoughMemory(
            f"{line}, but only {_gib(free)} is free: use {way_out}, or a machine with more "
            "memory")
    return f"{line}; {_gib(free)} free"


def _gib(n: float) -> str:
    if n >= 2**28:
        return f"{n / 2**30:.2f} GiB"
    return f"{math.ceil(n / 2**20)} MiB" if n >= 2**20 else f"{math.ceil(n / 2**10)} KiB"
