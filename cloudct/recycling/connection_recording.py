"""Recording the camera connections of a path store ("connections" storage) within a
memory budget: every event record's connections to the cameras and their crossings of
variable voxels, walked by :func:`cloudct.recycling.record_kernels.connection_batches`
into per-batch rooms that are then closed up.
"""

from __future__ import annotations

import numpy as np

from cloudct.recycling.path_terms import StoreArrays
from cloudct.recycling.record_kernels import connection_batches
from cloudct.recycling.store_memory import (
    CONNECTION_BYTES,
    MemoryBudgetError,
    budget_message,
    connections_bytes,
)


def record_connections_within_budget(
    k, arrays: StoreArrays, beta: np.ndarray, variable: np.ndarray, per_batch: int,
    storage: str, budget: float | None, store_bytes: int, voxel_size: int, batches: int,
) -> tuple[StoreArrays, str]:
    """Record the camera connections of every event record when the store with them fits
    ``budget``: ``(arrays, "connections")``; else ``(arrays, "crossings")``
    (``storage="auto"``) or :class:`MemoryBudgetError`.

    Each connection is walked once: the first two batches are counted, every batch gets
    room for 1.2 x the larger of their counts (within the budget), all are walked once
    writing into their rooms, and the rooms are closed up. The walk counts everything, so
    the budget is decided on exact sizes; where a batch overflowed its room (rare), or the
    rooms did not fit the budget, a second walk writes the connections at their exact
    places.
    """
    nrec = arrays.kind.size
    capacity = 4 * sum(e.size - 1 for e in k.edges) + 16
    connections = np.zeros(nrec, dtype=np.int64)
    crossings = np.zeros(nrec, dtype=np.int64)

    def walk(S: StoreArrays, write: bool, batch_connection, batch_crossing) -> None:
        connection_batches(
            k.grid, k.cams, k.copies, k.periodic, beta, variable, S, per_batch, capacity,
            write, connections, crossings, batch_connection, batch_crossing,
        )

    record_bounds = arrays.path_start[::per_batch]  # each batch's first record, and the end

    def batch_totals(counts: np.ndarray) -> np.ndarray:
        total = np.zeros(nrec + 1, dtype=np.int64)
        np.cumsum(counts, out=total[1:])
        return total[record_bounds[1:]] - total[record_bounds[:-1]]

    pilot = np.zeros(min(batches, 2) + 1, dtype=np.int64)
    walk(arrays, False, pilot, pilot)
    npilot = pilot.size - 1
    room = np.array([batch_totals(connections)[:npilot].max(),
                     batch_totals(crossings)[:npilot].max()]) * 1.2 + 16
    room_bytes = batches * (room[0] * CONNECTION_BYTES + room[1] * (voxel_size + 8))
    free = np.inf if budget is None else budget - store_bytes - 8 * (nrec + 1)
    room = np.floor(room * min(1.0, max(free, 0.0) / room_bytes)).astype(np.int64)
    written = _connection_arrays(arrays, batches * room[0], batches * room[1])
    batch_connection = np.arange(batches + 1, dtype=np.int64) * room[0]
    batch_crossing = np.arange(batches + 1, dtype=np.int64) * room[1]
    walk(written, True, batch_connection, batch_crossing)
    per_connection, per_crossing = batch_totals(connections), batch_totals(crossings)
    nconn, ncross = int(per_connection.sum()), int(per_crossing.sum())
    need = store_bytes + connections_bytes(nrec, nconn, ncross, voxel_size)
    if budget is not None and need > budget:
        if storage == "connections":
            raise MemoryBudgetError(budget_message(budget, need, "connections", batches))
        return arrays, "crossings"
    offsets = (np.zeros(batches + 1, dtype=np.int64), np.zeros(batches + 1, dtype=np.int64))
    np.cumsum(per_connection, out=offsets[0][1:])
    np.cumsum(per_crossing, out=offsets[1][1:])
    if per_connection.max() <= room[0] and per_crossing.max() <= room[1]:
        _close_up(written, batch_connection, batch_crossing, *offsets, nconn, ncross)
    else:  # a second walk, to the exact places
        del written
        written = _connection_arrays(arrays, nconn, ncross)
        walk(written, True, *offsets)
    np.cumsum(written.connection_crossing_start, out=written.connection_crossing_start)
    connection_start = np.zeros(nrec + 1, dtype=np.int64)
    np.cumsum(connections, out=connection_start[1:])
    return written._replace(connection_start=connection_start), "connections"


def _connection_arrays(arrays: StoreArrays, nconn: int, ncross: int) -> StoreArrays:
    """``arrays`` with room for ``nconn`` camera connections and ``ncross`` crossings."""
    return arrays._replace(
        connection_pixel=np.empty(nconn, dtype=np.int32),
        connection_cosine=np.empty(nconn),
        connection_factor=np.empty(nconn),
        connection_tau=np.empty(nconn),
        connection_crossing_start=np.zeros(nconn + 1, dtype=np.int64),
        connection_voxel=np.empty(ncross, dtype=arrays.voxel.dtype),
        connection_length=np.empty(ncross),
    )


def _close_up(
    a: StoreArrays, room_connection: np.ndarray, room_crossing: np.ndarray,
    connection: np.ndarray, crossing: np.ndarray, nconn: int, ncross: int,
) -> None:
    """Move each batch's connections and crossings from its room (``room_*[b]`` on) to its
    place (``connection[b]``, ``crossing[b]``; never later than the room) and shrink the
    arrays in place to ``nconn`` and ``ncross``."""
    per_connection = [
        (a.connection_pixel, 0), (a.connection_cosine, 0), (a.connection_factor, 0),
        (a.connection_tau, 0), (a.connection_crossing_start, 1),  # counts at c + 1
    ]
    for b in range(connection.size - 1):
        n = connection[b + 1] - connection[b]
        for array, shift in per_connection:
            src = room_connection[b] + shift
            array[connection[b] + shift : connection[b] + shift + n] = array[src : src + n]
        n = crossing[b + 1] - crossing[b]
        for array in (a.connection_voxel, a.connection_length):
            array[crossing[b] : crossing[b] + n] = array[room_crossing[b] : room_crossing[b] + n]
    for array, shift in per_connection:
        array.resize(nconn + shift, refcheck=False)
    for array in (a.connection_voxel, a.connection_length):
        array.resize(ncross, refcheck=False)
