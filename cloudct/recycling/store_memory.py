"""Memory of a path store: bytes per record, path and camera connection, the size of each
storage mode (:mod:`cloudct.recycling.store`), and the error raised when a memory budget
cannot hold them.
"""

from __future__ import annotations

#: Bytes of one record besides the voxel index: position and direction (6 float64),
#: length, the two reference terms, the aiming weight (4 float64) and the kind (int8).
RECORD_BYTES = 6 * 8 + 4 * 8 + 1
#: Bytes of one stored path: CSR offset, storage slot and photon index (int64 each).
PATH_BYTES = 3 * 8
#: Bytes of one camera connection besides its crossings: pixel (int32), cosine,
#: 1 / (r^2 Omega), frozen optical depth (float64) and its CSR offset (int64).
CONNECTION_BYTES = 4 + 3 * 8 + 8


class MemoryBudgetError(ValueError):
    """The memory budget cannot hold the paths in the requested storage mode."""


def lean_bytes(records: int, paths: int, voxel_size: int) -> int:
    """Bytes of a lean store with ``records`` records of ``paths`` paths."""
    return records * (RECORD_BYTES + voxel_size) + paths * PATH_BYTES + 4 * 8  # + 4 CSR ends


def crossings_bytes(records: int, crossings: int, voxel_size: int) -> int:
    """Bytes that the crossings add to a lean store (CSR offsets and the crossings)."""
    return records * 8 + crossings * (voxel_size + 8)


def connections_bytes(records: int, connections: int, crossings: int, voxel_size: int) -> int:
    """Bytes that camera connections add to a crossings store: CSR offsets, pixel (int32),
    cosine, 1 / (r^2 Omega) and frozen optical depth (float64) per connection, and the
    crossings of variable voxels."""
    return records * 8 + connections * CONNECTION_BYTES + crossings * (voxel_size + 8)


def budget_message(budget: float, need: int, what: str, batches: int) -> str:
    """The :class:`MemoryBudgetError` message: what ``what`` storage needs, against the
    budget."""
    per_batch = need / batches
    text = (
        f"memory_budget of {budget / 2**20:.3g} MiB cannot hold the paths: {what} storage "
        f"needs {need / 2**20:.3g} MiB ({per_batch / 2**20:.3g} MiB per batch of photons)"
    )
    if budget < per_batch:
        text += "; the budget is too small for even one batch"
    return text + ". Raise memory_budget, use fewer photons, or storage='lean'/'auto'."
