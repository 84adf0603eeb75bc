"""CUDA kernels of path recycling: stored paths re-evaluated on the GPU, one thread per path.

Imported only when a replay asks for the CUDA back end (:mod:`cloudct.recycling.replay`);
it needs numba-cuda. As in :mod:`cloudct.mc.cuda_kernels`, the kernels hold no physics:
each thread calls :func:`cloudct.recycling.replay_kernels.replay_path` (images, or the
score-function gradient, of one stored path under the current medium) or
:func:`~cloudct.recycling.path_terms.path_log_ratio`, the ``@njit`` routines of the CPU
replay, which numba-cuda compiles for the GPU. Writes into the per-batch images and gradients go
through :func:`cloudct.mc.accumulate.add_to` (atomic on the GPU).

Thread order (seed paper Sec. 5.3, path sorting). A store keeps batch b's paths in storage
slots ``b * per_batch .. (b + 1) * per_batch - 1``, each batch sorted by record count in a
sorted store. A launch covers ranks ``first .. first + count - 1`` of every batch, thread t
taking rank ``q = first + t % count`` of batch ``b = t // count``: with ``sort_paths``
(default :data:`cloudct.mc.cuda_kernels.SORT_PATHS`) the path in slot ``b * per_batch + q``,
so that consecutive threads take consecutive slots and a warp replays paths of similar length
(in a sorted store); otherwise the path of photon-order position ``b * per_batch + q``
(``S.slot`` gives its slot), the CPU kernels' order. In an unsorted store both orders are
the same. Each thread writes the log correction factor of its path at its photon-order
position and adds its event count to its batch.

Per-path scratch: :func:`~cloudct.recycling.replay_kernels.replay_path` writes ``scratch[k - a]``
for its records k in ``a .. z - 1``; every thread gets the slice ``scratch[a:]`` of one
float64[records] device array, so the paths' scratch rooms do not overlap. The camera
connections are walked twice in GRADIENT mode (no :class:`~cloudct.mc.traversal.Trail`; the
same values, added in the same order).

The store's arrays are copied to the device on the first replay and kept there while the
store lives (:func:`device_store`), since a recycler replays the same store every iteration;
:func:`release_device_store` frees them earlier.
"""

from __future__ import annotations

import weakref

import numpy as np
from numba import cuda, njit

import cloudct.mc.cuda_kernels as ck
from cloudct.mc.cuda_kernels import (
    GRADIENT_MODE,
    RENDER_MODE,
    device_scene,
    device_zeros,
    to_device,
    to_host,
)
from cloudct.recycling.path_terms import path_log_ratio
from cloudct.recycling.replay_kernels import replay_path

# --------------------------------------------------------------------------------------
# Kernels
# --------------------------------------------------------------------------------------


@njit(cache=True)
def replay_thread_path(t, order, S, per_batch, first, count):
    """Batch b, photon-order position j and storage slot p of the path that thread ``t`` of
    a replay launch takes: rank ``first + t % count`` of batch ``t // count`` in the thread
    order ``order`` (photon-order positions; see the module docstring)."""
    b = t // count
    j = order[b * per_batch + first + t % count]
    return b, j, S.slot[j]


@cuda.jit(cache=True)
def replay_render_kernel(
    scene, periodic, ground, rr_depth, rr_survival, per_batch, use_crossings, S, first, count,
    out,
):
    """RENDER replay of ranks ``first .. first + count - 1`` of every batch: out = (beta,
    order, images[nbatch, view, row, col], log_ratio[npaths], events[nbatch],
    scratch[records], no_residual[1, 1, 1])."""
    beta, order, images, log_ratio, events, scratch, no_residual = out
    t = cuda.grid(1)
    if t >= images.shape[0] * count:
        return
    b, j, p = replay_thread_path(t, order, S, per_batch, first, count)
    depth, _, log_r = replay_path(
        scene.grid, scene.bank, scene.cams, scene.copies, scene.sun, periodic, ground,
        rr_depth, rr_survival, beta, S, p, use_crossings, RENDER_MODE, images[b],
        no_residual, no_residual, None, scratch[S.path_start[p]:],
    )
    log_ratio[j] = log_r
    cuda.atomic.add(events, b, depth)


@cuda.jit(cache=True)
def replay_gradient_kernel(
    scene, periodic, ground, rr_depth, rr_survival, per_batch, use_crossings, S, first, count,
    out,
):
    """GRADIENT replay (as :func:`replay_render_kernel`): out = (beta, order, residual[view,
    row, col], gradients[nbatch, x, y, z], log_ratio, events, scratch, no_image[1, 1, 1])."""
    beta, order, residual, gradients, log_ratio, events, scratch, no_image = out
    t = cuda.grid(1)
    if t >= gradients.shape[0] * count:
        return
    b, j, p = replay_thread_path(t, order, S, per_batch, first, count)
    depth, _, log_r = replay_path(
        scene.grid, scene.bank, scene.cams, scene.copies, scene.sun, periodic, ground,
        rr_depth, rr_survival, beta, S, p, use_crossings, GRADIENT_MODE, no_image,
        residual, gradients[b], None, scratch[S.path_start[p]:],
    )
    log_ratio[j] = log_r
    cuda.atomic.add(events, b, depth)


@cuda.jit(cache=True)
def log_ratio_kernel(scene, periodic, per_batch, use_crossings, S, first, count, out):
    """Whole-path log correction factors of ranks ``first .. first + count - 1`` of every
    batch: out = (beta, order, log_ratio[npaths])."""
    beta, order, log_ratio = out
    t = cuda.grid(1)
    if t >= (log_ratio.size // per_batch) * count:
        return
    _, j, p = replay_thread_path(t, order, S, per_batch, first, count)
    log_ratio[j] = path_log_ratio(scene.grid, scene.bank, beta, S, p, use_crossings, periodic)


# --------------------------------------------------------------------------------------
# The store on the device
# --------------------------------------------------------------------------------------


class DeviceStore:
    """A path store's arrays on the device (``arrays``, the same NamedTuple type, field by
    field), the per-record scratch of the replay, and the thread orders."""

    def __init__(self, store) -> None:
        self.source = store.arrays  # the host arrays this copy was made of
        self.arrays = type(store.arrays)(*[to_device(a) for a in store.arrays])
        self.scratch = device_zeros(store.records)
        self._orders: dict[bool, object] = {}

    def order(self, by_slot: bool):
        """Photon-order positions in thread order (device int64[npaths]): those of the paths
        in storage slots 0, 1, ... (``by_slot``), or 0, 1, ... (photon order)."""
        if by_slot not in self._orders:
            slot = np.asarray(self.source.slot)
            positions = np.arange(slot.size, dtype=np.int64)
            order = positions
            if by_slot:
                order = np.empty_like(positions)
                order[slot] = positions  # the position of the path in slot q, q = 0, 1, ...
            self._orders[by_slot] = to_device(order)
        return self._orders[by_slot]


_resident: dict[int, DeviceStore] = {}


def device_store(store) -> DeviceStore:
    """The device copy of ``store`` (a :class:`~cloudct.recycling.store.PathStore`): made on
    the first call (a ``MemoryError`` where it does not fit in 80% of the free device
    memory), then reused while the store lives and holds the same arrays."""
    key = id(store)
    resident = _resident.get(key)
    if resident is not None and resident.source is store.arrays:
        return resident
    release_device_store(store)
    ck.check_fits(
        sum(a.nbytes for a in store.arrays) + 8 * store.records + 16 * store.paths,
        "the path store and its replay scratch",
        "record fewer paths or replay with backend='cpu'",
    )
    resident = DeviceStore(store)
    _resident[key] = resident
    weakref.finalize(store, _resident.pop, key, None)
    return resident


def release_device_store(store) -> None:
    """Free the device copy of ``store`` now (it is freed with the store otherwise)."""
    _resident.pop(id(store), None)


# --------------------------------------------------------------------------------------
# Launchers
# --------------------------------------------------------------------------------------


def _thread_order(resident: DeviceStore, sort_paths: bool | None):
    return resident.order(ck.SORT_PATHS if sort_paths is None else sort_paths)


class ReplayLauncher(ck.Launcher):
    """The CUDA counterpart of :func:`~cloudct.recycling.replay_kernels.replay_render_batches`
    (``residual`` None: ``out`` the per-batch images) and
    :func:`~cloudct.recycling.replay_kernels.replay_gradient_batches` (``out`` the per-batch
    gradients, weighted by ``residual``), as ``run(first, last)``: the CUDA launcher of the
    batch kernels ``replay-render`` and ``replay-gradient`` (registered by
    :mod:`cloudct.recycling.replay`; called as every launcher of
    :func:`cloudct.mc.estimate.batch_runner`: ``k``, the roulette, ``seed`` (unused: a
    replay draws no random numbers) and the paths per batch, then its own inputs). ``beta``
    is the flat total extinction of the current medium. The outputs (sums over the paths,
    as on the CPU), ``log_ratio`` (by photon-order position) and ``events`` are filled once
    the last round has run."""

    def __init__(
        self, k, rr_depth: int, rr_survival: float, seed: int, per_batch: int, store,
        beta: np.ndarray, residual: np.ndarray | None, out: np.ndarray,
        log_ratio: np.ndarray, events: np.ndarray, *,
        sort_paths: bool | None = None, threads_per_block: int | None = None,
    ) -> None:
        if per_batch != store.per_batch:
            raise ValueError(f"the store holds {store.per_batch} paths per batch, not "
                             f"{per_batch}")
        resident = device_store(store)
        self.per_batch = store.per_batch
        self.nbatch = store.batches
        self.tpb = threads_per_block or ck.THREADS_PER_BLOCK
        self.host = (out, log_ratio, events)
        self.scene = device_scene(k)
        self.args = (
            k.periodic, k.ground, rr_depth, rr_survival, store.per_batch, store.has_crossings,
            resident.arrays,
        )
        what = "the per-batch images" if residual is None else "the per-batch gradients"
        ck.check_fits(out.nbytes + log_ratio.nbytes, what + " and log r per path")
        self.out = device_zeros(out.shape)
        self.log_ratio = device_zeros(log_ratio.shape)
        self.events = device_zeros(self.nbatch, np.int64)
        dummy = device_zeros((1, 1, 1))
        head = (to_device(beta), _thread_order(resident, sort_paths))
        tail = (self.log_ratio, self.events, resident.scratch, dummy)
        if residual is None:
            self.kernel = replay_render_kernel
            self.buffers = (*head, self.out, *tail)
        else:
            self.kernel = replay_gradient_kernel
            self.buffers = (*head, to_device(residual), self.out, *tail)
        self.chunk = ck.launch_count(self.nbatch)

    def launch(self, first: int, count: int) -> None:
        ck.launch_kernel(self.kernel, self.nbatch * count, self.tpb, self.scene, *self.args, first,
                         count, self.buffers)

    def finish(self) -> None:
        out, log_ratio, events = self.host
        out += to_host(self.out)
        log_ratio[:] = to_host(self.log_ratio)
        events += to_host(self.events)


def log_weights(
    store, k, beta: np.ndarray, use_crossings: bool, *, sort_paths: bool | None = None,
    threads_per_block: int | None = None,
) -> np.ndarray:
    """log r of every stored path (photon order) on the device: the CUDA counterpart of
    :func:`~cloudct.recycling.replay_kernels.log_ratio_batches`, same arguments as
    :class:`ReplayLauncher`."""
    resident = device_store(store)
    ck.check_fits(8 * store.paths, "log r per path")
    log_ratio = device_zeros(store.paths)
    buffers = (to_device(beta), _thread_order(resident, sort_paths), log_ratio)
    scene = device_scene(k)
    tpb = threads_per_block or ck.THREADS_PER_BLOCK
    chunk = ck.launch_count(store.batches)
    for first in range(0, store.per_batch, chunk):
        count = min(chunk, store.per_batch - first)
        ck.launch_kernel(log_ratio_kernel, store.batches * count, tpb, scene, k.periodic,
                         store.per_batch, bool(use_crossings), resident.arrays, first, count,
                         buffers)
    if not ck.SIMULATOR:
        cuda.synchronize()
    return to_host(log_ratio)
