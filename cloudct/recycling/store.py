"""The path store: sampled forward paths kept for re-evaluation under other media.

A store is a structure of arrays in CSR form (:class:`~cloudct.recycling.path_terms.StoreArrays`):
per path the offset of its records; per record (ENTRY, each SCATTER or GROUND vertex, and
the ESCAPE of a path that leaves the medium) the position, the direction of the segment
arriving there, that segment's length, the kind, the flat voxel index, and the reference
medium's segment and direction terms of the sampling pdf, so that the reference medium
itself need not be kept. Two storage modes:

- ``"crossings"``: every segment's voxel crossings (flat voxel, length) are stored too, so a
  segment's optical depth under a new medium is a sum over them (fast, memory-hungry);
- ``"lean"``: segments are walked again through the grid when needed (less memory);
- ``"connections"``: the crossings, and also every event's camera connections (the local
  estimates' pixels, angles, 1 / (r^2 Omega) and the connection's voxel crossings), so that
  a re-evaluation walks no ray at all (fastest, most memory). With a ``variable`` mask
  (the voxels whose extinction may change, e.g. a retrieval's cloud hull) a connection keeps
  only its crossings of variable voxels and the optical depth of the others, which the
  re-evaluations then require to be unchanged.

All modes give bitwise identical results (``"connections"`` with a mask: to rounding, the
frozen part of each optical depth being summed first). ``"auto"`` picks the first of
``"connections"`` (within :data:`AUTO_CONNECTIONS_BUDGET` when no budget is given),
``"crossings"`` and ``"lean"`` that fits the memory budget.

Recording traces every photon twice with the same counter-based random streams (same
photon index and seed, same path): a first pass counts each path's records, a cumulative
sum gives the CSR offsets, the second pass writes them (:data:`cloudct.mc.forward.COUNT`,
:data:`~cloudct.mc.forward.RECORD`). Photons are split into batches as in
:func:`cloudct.mc.render.render_batches` (batch b owns photons b * P .. (b + 1) * P - 1), so
the re-evaluated images and gradients come with standard errors over batches.

Path sorting (seed paper Sec. 5.3): :func:`sort_paths` reorders each batch's paths by their
number of records, so that paths of the same length lie together (what GPU threads in a
group need). The CPU kernels visit each batch's paths in photon order through ``slot``, so
sorted and unsorted stores give bitwise identical results.

The recording kernels are in :mod:`cloudct.recycling.record_kernels`, the recording of
camera connections within a memory budget in :mod:`cloudct.recycling.connection_recording`,
and the stores' sizes in bytes in :mod:`cloudct.recycling.store_memory`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
import xarray as xr

from cloudct.mc.estimate import kernel_inputs, run_in_rounds
from cloudct.mc.forward import ENTRY, ESCAPE, GROUND, SCATTER, PathRecord
from cloudct.mc.scene import Scene
from cloudct.mc.traversal import require_exponential
from cloudct.recycling.connection_recording import record_connections_within_budget
from cloudct.recycling.path_terms import StoreArrays, flat_total_extinction
from cloudct.recycling.record_kernels import (
    count_records,
    measure_segments,
    reference_terms,
    write_crossings,
    write_records,
)
from cloudct.recycling.store_memory import (
    MemoryBudgetError,
    budget_message,
    connections_bytes,
    crossings_bytes,
    lean_bytes,
)

STORAGE = ("auto", "connections", "crossings", "lean")

#: Memory that ``storage="auto"`` lets camera connections take when no budget is given.
AUTO_CONNECTIONS_BUDGET = 2 * 2**30


def voxel_dtype(shape: tuple[int, int, int]) -> type:
    """int32 voxel indices where they fit, else int64."""
    return np.int32 if int(np.prod(shape)) < 2**31 else np.int64


@dataclass
class PathStore:
    """Stored forward paths of one scene, sampled under a reference medium.

    ``arrays`` holds the paths (storage order); ``photon[p]`` is the photon index of the path
    in slot p, and ``arrays.slot[j]`` the slot of photon j. Batch b holds photons
    ``b * per_batch .. (b + 1) * per_batch - 1``.
    """

    arrays: StoreArrays
    photon: np.ndarray
    scene: Scene
    edges: tuple[np.ndarray, np.ndarray, np.ndarray]
    seed: int
    batches: int
    per_batch: int
    rr_depth: int
    rr_survival: float
    storage: str
    sorted: bool = False
    info: dict = field(default_factory=dict)
    #: "connections" storage with a mask: the variable voxels (bool[x, y, z]) and the
    #: reference's total extinction of the frozen ones (flat, in voxel order)
    variable: np.ndarray | None = None
    frozen_extinction: np.ndarray | None = None

    @property
    def paths(self) -> int:
        """Number of stored paths (photons)."""
        return int(self.photon.size)

    @property
    def records(self) -> int:
        """Number of records (entries, vertices, escapes)."""
        return int(self.arrays.kind.size)

    @property
    def events(self) -> int:
        """Number of stored scattering and ground events (the local-estimation events)."""
        kind = self.arrays.kind
        return int(np.count_nonzero((kind == SCATTER) | (kind == GROUND)))

    @property
    def crossings(self) -> int:
        """Number of stored voxel crossings (0 for lean storage)."""
        return int(self.arrays.crossing_voxel.size)

    @property
    def has_crossings(self) -> bool:
        """Whether segment crossings are stored ("crossings" and "connections" storage)."""
        return self.storage in ("crossings", "connections")

    @property
    def connections(self) -> int:
        """Number of stored camera connections (0 unless "connections" storage)."""
        return int(self.arrays.connection_pixel.size)

    @property
    def nbytes(self) -> int:
        """Memory held by the store's arrays."""
        return int(sum(a.nbytes for a in self.arrays) + self.photon.nbytes)

    @property
    def connection_nbytes(self) -> int:
        """Memory held by the camera connections (0 unless "connections" storage)."""
        return int(sum(a.nbytes for name, a in self.arrays._asdict().items()
                       if name.startswith("connection_")))

    @property
    def bytes_per_event(self) -> float:
        """Store bytes per stored scattering (or ground) event."""
        return self.nbytes / max(self.events, 1)

    @cached_property
    def max_records(self) -> int:
        """Records of the longest path."""
        return int(np.max(np.diff(self.arrays.path_start))) if self.paths else 0

    def record_counts(self) -> np.ndarray:
        """Records per path, in photon order."""
        return np.diff(self.arrays.path_start)[self.arrays.slot]

    def summary(self) -> dict:
        """Sizes and memory of the store, for logs and benchmarks."""
        return {
            "storage": self.storage,
            "sorted": self.sorted,
            "paths": self.paths,
            "records": self.records,
            "events": self.events,
            "crossings": self.crossings,
            "connections": self.connections,
            "connection_crossings": int(self.arrays.connection_voxel.size),
            "bytes": self.nbytes,
            "bytes_per_event": self.bytes_per_event,
            "bytes_per_path": self.nbytes / max(self.paths, 1),
            "seed": self.seed,
            **self.info,
        }


def record_paths(
    medium: xr.Dataset,
    scene: Scene,
    *,
    photons: int,
    seed: int = 0,
    batches: int = 32,
    storage: str = "auto",
    memory_budget: float | None = None,
    sort: bool = True,
    rr_depth: int = 100,
    rr_survival: float = 0.95,
    progress: bool | None = False,
    first_batch: int = 0,
    nbatch: int | None = None,
    variable: np.ndarray | None = None,
    aim_fraction: float | None = None,
) -> PathStore:
    """Sample ``photons`` forward paths under ``medium`` (the reference) and store them.

    ``photons`` is rounded up to a multiple of ``batches``; photon i follows the same path
    as photon i of :func:`cloudct.mc.render.render` with the same seed. ``memory_budget``
    (bytes, None for no limit) bounds the store; ``storage`` is ``"auto"``,
    ``"connections"``, ``"crossings"`` or ``"lean"``. A budget that cannot hold the paths raises
    :class:`MemoryBudgetError`.

    ``first_batch`` and ``nbatch`` (default: all) record only batches ``first_batch ..
    first_batch + nbatch - 1`` of the ``batches``: the same paths, as a store of ``nbatch``
    batches (photon ``first_batch * per_batch + j`` at storage index j). With ``nbatch``
    given, the store is a part of a larger recording and may be a single batch.

    ``variable`` (bool[x, y, z], default: every voxel) marks the voxels whose extinction
    the re-evaluations may change; "connections" storage keeps only their crossings.

    ``aim_fraction``: the paths' detector directional importance sampling, as for
    :func:`cloudct.mc.render.render`; each scattering record keeps its weight f / q under
    the reference (``StoreArrays.aim_weight``).

    The paths always enter uniformly on the sunlit faces (``entry_cloud_share`` 0 of
    :func:`cloudct.mc.render.render`, :mod:`cloudct.mc.sun`): a replay starts every path
    with the weight ``k.sun.power``, which entry where the clouds are would not match.
    """
    whole = nbatch is None
    nbatch = int(batches) - int(first_batch) if whole else int(nbatch)
    if storage not in STORAGE:
        raise ValueError(f"storage must be one of {STORAGE}, got {storage!r}")
    if int(photons) < 1:
        raise ValueError(f"photons must be a positive count, got {photons}")
    if whole and int(batches) < 2:
        raise ValueError(f"batches must be at least 2 for standard errors, got {batches}")
    if not (0 <= int(first_batch) and 1 <= nbatch and int(first_batch) + nbatch <= batches):
        raise ValueError(
            f"batches {first_batch}..{first_batch + nbatch - 1} are not among the {batches}"
        )
    if not 0.0 < rr_survival <= 1.0 or rr_depth < 1:
        raise ValueError("rr_survival must be in (0, 1] and rr_depth >= 1")
    if memory_budget is not None and not memory_budget > 0:
        raise ValueError(f"memory_budget must be a positive number of bytes, got {memory_budget}")
    start_time = time.perf_counter()
    k = kernel_inputs(medium, scene, aim_fraction)
    require_exponential(k.grid, "recycled paths")
    shape = k.grid.extinction.shape[1:]
    if variable is not None:
        variable = np.asarray(variable)
        if variable.shape != shape or variable.dtype != bool:
            raise ValueError(
                f"variable must be a boolean mask of the grid's shape {shape}, got "
                f"{variable.dtype} {variable.shape}"
            )
    vdtype = voxel_dtype(shape)
    vsize = np.dtype(vdtype).itemsize
    per_batch = math.ceil(int(photons) / batches)
    batches = nbatch  # from here on, the batches of this store
    npaths = per_batch * batches
    run_args = (
        k.grid, k.bank, k.cams, k.copies, k.sun, k.periodic, k.ground, rr_depth, rr_survival,
        int(seed), per_batch, int(first_batch) * per_batch,
    )

    # pass 1: records per path, CSR offsets
    counts = np.zeros(npaths, dtype=np.int64)
    run_batches(
        lambda first, last: count_records(*run_args, first, last, counts),
        per_batch, batches, progress, unit="photon", desc="count paths",
    )
    path_start = np.zeros(npaths + 1, dtype=np.int64)
    np.cumsum(counts, out=path_start[1:])
    nrec = int(path_start[-1])
    lean = lean_bytes(nrec, npaths, vsize)
    if memory_budget is not None and lean > memory_budget:
        raise MemoryBudgetError(budget_message(memory_budget, lean, "lean", batches))

    # pass 2: the records themselves
    record = PathRecord(
        position=np.empty((3, nrec)),
        direction=np.empty((3, nrec)),
        optical_depth=np.empty(nrec),
        kind=np.empty(nrec, dtype=np.int8),
        voxel=np.empty(nrec, dtype=vdtype),
    )
    run_batches(
        lambda first, last: write_records(*run_args, first, last, path_start, record),
        per_batch, batches, progress, unit="photon", desc="record paths",
    )
    slot = np.arange(npaths, dtype=np.int64)
    empty_cross = (np.zeros(1, np.int64), np.zeros(0, vdtype), np.zeros(0))
    empty_connections = (
        np.zeros(1, np.int64), np.zeros(0, np.int32), np.zeros(0), np.zeros(0), np.zeros(0),
        np.zeros(1, np.int64), np.zeros(0, vdtype), np.zeros(0),
    )
    arrays = StoreArrays(
        path_start, slot, record.position, record.direction, record.optical_depth, record.kind,
        record.voxel, np.empty(nrec), np.empty(nrec), np.empty(nrec), *empty_cross,
        *empty_connections,
    )

    # segment lengths (from the sampled optical depths) and crossing counts
    count_crossings = storage != "lean"
    crossings_per_record = np.zeros(nrec, dtype=np.int64)
    measure_segments(
        k.grid, arrays, arrays.length, k.periodic, per_batch, count_crossings,
        crossings_per_record,
    )
    chosen = "lean"
    if count_crossings:
        ncross = int(crossings_per_record.sum())
        full = lean + crossings_bytes(nrec, ncross, vsize)
        fits = memory_budget is None or full <= memory_budget
        if storage == "crossings" and not fits:
            raise MemoryBudgetError(budget_message(memory_budget, full, "crossings", batches))
        if fits:
            chosen = "crossings"
            crossing_start = np.zeros(nrec + 1, dtype=np.int64)
            np.cumsum(crossings_per_record, out=crossing_start[1:])
            del crossings_per_record
            arrays = arrays._replace(
                crossing_start=crossing_start,
                crossing_voxel=np.empty(ncross, dtype=vdtype),
                crossing_length=np.empty(ncross),
            )
            bad = write_crossings(k.grid, arrays, k.periodic, per_batch)
            if bad:
                raise RuntimeError(f"{bad} segments crossed a different number of voxels")
    beta = flat_total_extinction(k.grid)
    frozen = None
    if storage == "connections" and chosen != "crossings":
        raise MemoryBudgetError(budget_message(memory_budget, full, "crossings", batches))
    if storage in ("auto", "connections") and chosen == "crossings":
        flat_variable = (
            np.ones(beta.size, dtype=bool) if variable is None else variable.ravel()
        )
        budget = memory_budget
        if budget is None and storage == "auto":
            budget = AUTO_CONNECTIONS_BUDGET
        arrays, chosen = record_connections_within_budget(
            k, arrays, beta, flat_variable, per_batch, storage, budget, full, vsize, batches
        )
        if chosen == "connections" and not flat_variable.all():
            frozen = beta[~flat_variable]
    # the reference medium's terms, computed as every re-evaluation computes them
    reference_terms(
        k.grid, k.bank, k.cams, beta, arrays, chosen != "lean", k.periodic, per_batch,
        arrays.seg_ref, arrays.dir_ref, arrays.aim_weight,
    )
    store = PathStore(
        arrays=arrays,
        photon=np.arange(npaths, dtype=np.int64),
        scene=scene,
        edges=tuple(np.array(e, dtype=float) for e in k.edges),
        seed=int(seed),
        batches=int(batches),
        per_batch=per_batch,
        rr_depth=int(rr_depth),
        rr_survival=float(rr_survival),
        storage=chosen,
        info={
            "record_time": 0.0, "memory_budget": memory_budget, "first_batch": int(first_batch),
            "aim_fraction": k.cams.aim_fraction,
        },
        variable=None if frozen is None else variable.copy(),
        frozen_extinction=frozen,
    )
    if sort:
        store = sort_paths(store)
    store.info["record_time"] = time.perf_counter() - start_time
    return store


def run_batches(
    run: Callable[[int, int], None], per_batch: int, batches: int, progress: bool | None,
    unit: str, desc: str,
) -> float:
    """``run(0, per_batch)`` in one call, or in rounds with a progress bar when ``progress``
    (each call of a parallel kernel has a fixed cost, large on a loaded machine); returns
    the wall time."""
    if progress:
        return run_in_rounds(run, per_batch, batches, progress, unit=unit, desc=desc)
    start = time.perf_counter()
    run(0, per_batch)
    return time.perf_counter() - start


def _gather_ranges(starts: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Concatenated ranges starts[i] .. ends[i] - 1 and their new CSR offsets."""
    lengths = ends - starts
    offsets = np.zeros(lengths.size + 1, dtype=np.int64)
    np.cumsum(lengths, out=offsets[1:])
    index = np.repeat(starts - offsets[:-1], lengths) + np.arange(offsets[-1], dtype=np.int64)
    return index, offsets


def sort_paths(store: PathStore) -> PathStore:
    """A copy of ``store`` with each batch's paths stored in order of their number of
    records (stable, so equal lengths keep photon order). Batches keep their paths, and the
    kernels visit them in photon order: results are bitwise those of the unsorted store."""
    check_not_empty(store)
    a = store.arrays
    lengths = np.diff(a.path_start)
    order = np.empty(store.paths, dtype=np.int64)  # new slot -> old slot
    for b in range(store.batches):
        photons = np.arange(b * store.per_batch, (b + 1) * store.per_batch)
        old_slots = a.slot[photons]
        order[photons] = old_slots[np.argsort(lengths[old_slots], kind="stable")]
    rec, path_start = _gather_ranges(a.path_start[order], a.path_start[order + 1])
    photon = store.photon[order]
    slot = np.empty_like(a.slot)
    slot[photon] = np.arange(store.paths, dtype=np.int64)
    if store.has_crossings:
        cross, crossing_start = _gather_ranges(a.crossing_start[rec], a.crossing_start[rec + 1])
        crossing_voxel = a.crossing_voxel[cross]
        crossing_length = a.crossing_length[cross]
    else:
        crossing_start, crossing_voxel, crossing_length = (
            a.crossing_start, a.crossing_voxel, a.crossing_length,
        )
    connection = {}
    if store.storage == "connections":
        conn, connection_start = _gather_ranges(
            a.connection_start[rec], a.connection_start[rec + 1]
        )
        cc, connection_crossing_start = _gather_ranges(
            a.connection_crossing_start[conn], a.connection_crossing_start[conn + 1]
        )
        connection = {
            "connection_start": connection_start,
            "connection_pixel": a.connection_pixel[conn],
            "connection_cosine": a.connection_cosine[conn],
            "connection_factor": a.connection_factor[conn],
            "connection_tau": a.connection_tau[conn],
            "connection_crossing_start": connection_crossing_start,
            "connection_voxel": a.connection_voxel[cc],
            "connection_length": a.connection_length[cc],
        }
    arrays = a._replace(
        path_start=path_start,
        slot=slot,
        position=np.ascontiguousarray(a.position[:, rec]),
        direction=np.ascontiguousarray(a.direction[:, rec]),
        length=a.length[rec],
        kind=a.kind[rec],
        voxel=a.voxel[rec],
        seg_ref=a.seg_ref[rec],
        dir_ref=a.dir_ref[rec],
        aim_weight=a.aim_weight[rec],
        crossing_start=crossing_start,
        crossing_voxel=crossing_voxel,
        crossing_length=crossing_length,
        **connection,
    )
    return replace(store, arrays=arrays, photon=photon, sorted=True, info=dict(store.info))


def check_not_empty(store: PathStore) -> None:
    """Raise ValueError for a store without paths."""
    if store.paths == 0 or store.records == 0:
        raise ValueError("the path store is empty: record paths (photons > 0) first")


def check_same_grid(store: PathStore, edges: tuple[np.ndarray, ...]) -> None:
    """Raise ValueError when a medium's grid (cell edges) is not the store's."""
    shape = tuple(e.size - 1 for e in store.edges)
    other = tuple(np.asarray(e).size - 1 for e in edges)
    if shape != other or not all(
        np.array_equal(np.asarray(e), f) for e, f in zip(edges, store.edges, strict=True)
    ):
        raise ValueError(
            f"the medium's grid {other} (cell edges) differs from the grid {shape} the paths "
            "were recorded on; path recycling needs the same grid (resample the paths)"
        )


__all__ = [
    "ENTRY",
    "ESCAPE",
    "GROUND",
    "SCATTER",
    "STORAGE",
    "MemoryBudgetError",
    "AUTO_CONNECTIONS_BUDGET",
    "PathStore",
    "connections_bytes",
    "crossings_bytes",
    "lean_bytes",
    "record_paths",
    "sort_paths",
]
