"""CUDA kernels for the forward and backward estimators, from the same physics source.

Imported only when the CUDA back end is used (:mod:`cloudct.mc.backend`); it needs
numba-cuda. The kernels hold no physics: each thread calls the ``@njit`` per-photon routines
of the CPU engine (:func:`cloudct.mc.forward.trace_photon`,
:func:`cloudct.mc.backward.trace_pixel_sample`), which numba-cuda compiles for the GPU when
a kernel calls them. Their writes into shared images and gradients go through
:func:`cloudct.mc.accumulate.add_to`, whose CUDA implementation (an atomic addition) is
registered when this module is imported.

Indexing is that of the CPU kernels, so the same seed draws the same random streams: forward
photon k of batch b is photon index ``b * per_batch + k`` and backward sample k of pixel p
in batch b is index ``(p * nbatch + b) * per_batch + k``. A launch covers the photons
``first .. first + count - 1`` of every batch; thread t handles photon ``k = first + t %
count`` of batch ``b = t // count`` (forward), or pixel ``t % npix`` of batch
``(t // npix) % nbatch`` (backward, neighbouring threads trace neighbouring pixels).

Kernel arguments: every array reaches a kernel inside a (named) tuple. On a GPU numba-cuda
flattens tuples of device arrays into kernel parameters without copying them; the CUDA
simulator (``NUMBA_ENABLE_CUDASIM=1``) passes tuples through unchanged, so the ``@njit``
routines receive numpy arrays there (the simulator would wrap top-level arrays in objects
compiled code cannot take). Under the simulator the "device" arrays are host arrays.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from typing import NamedTuple

import numpy as np
from numba import config, cuda, njit

from cloudct.jit_cache import install_cuda_locator
from cloudct.mc.accumulate import add_to, register_cuda_implementation
from cloudct.mc.backend import sort_by_path_length
from cloudct.mc.backward import trace_pixel_sample
from cloudct.mc.camera_gradient import (
    DRT,
    SAMPLE_MATCHING,
    SCORE,
    drawn_pixel,
    gradient_sample,
)
from cloudct.mc.forward import GRADIENT, REFF_GRADIENT, RENDER, RESIDUAL, trace_photon

register_cuda_implementation()
# kernels compiled once per machine, not per process (cloudct.jit_cache: where, and when stale)
install_cuda_locator()

SIMULATOR = bool(config.ENABLE_CUDASIM)

#: Threads per block (the per-photon routines are register-heavy; 128 keeps occupancy).
THREADS_PER_BLOCK = 128
#: Re-trace the photons of the GRADIENT pass ordered by path length (seed paper Sec. 5.3).
SORT_PATHS = True
#: Most threads (photons or pixel samples) per launch.
MAX_LAUNCH = 1 << 22
#: Device memory per forward-gradient photon and launch: path sum, vertices, order.
BYTES_PER_GRADIENT_PHOTON = 24
#: The modes the kernels pass, as int64 values: numba types an int constant as a literal and
#: compiles a routine once per literal it is given, so each forward kernel would compile its
#: own ``trace_photon``; NVVM, which inlines it into the kernel, folds the value all the same.
RENDER_MODE = np.int64(RENDER)
RESIDUAL_MODE = np.int64(RESIDUAL)
GRADIENT_MODE = np.int64(GRADIENT)


class DeviceScene(NamedTuple):
    """The kernel inputs of :class:`cloudct.mc.estimate.KernelInputs` that are arrays."""

    grid: tuple  # OpticalGrid of device arrays
    bank: tuple  # PhaseBank
    cams: tuple  # CameraArrays
    copies: object  # int64[nview, 4]
    sun: tuple  # SunArrays


# --------------------------------------------------------------------------------------
# Kernels
# --------------------------------------------------------------------------------------


@njit(cache=True)
def thread_photon(t, per_batch, first, count):
    """Batch b and photon index of thread ``t`` of a forward launch that covers photons
    ``first .. first + count - 1`` of every batch (the module docstring's thread map)."""
    b = t // count
    return b, b * per_batch + first + t % count


@cuda.jit(cache=True)
def forward_render_kernel(
    scene, periodic, ground, rr_depth, rr_survival, seed, per_batch, first, count, out
):
    """RENDER: out = (images[nbatch, view, row, col], events[nbatch], no_residual[1, 1, 1],
    no_gradient[1, 1, 1])."""
    images, events, no_residual, no_gradient = out
    t = cuda.grid(1)
    if t >= images.shape[0] * count:
        return
    b, index = thread_photon(t, per_batch, first, count)
    vertices, _ = trace_photon(
        scene.grid, scene.bank, scene.cams, scene.copies, scene.sun, periodic, ground,
        rr_depth, rr_survival, seed, index, RENDER_MODE, images[b], no_residual, no_gradient,
        0.0,
    )
    cuda.atomic.add(events, b, vertices)


@cuda.jit(cache=True)
def forward_sensor_kernel(
    scene, periodic, ground, rr_depth, rr_survival, seed, per_batch, first, count, out
):
    """RENDER with the flux tallies of :mod:`cloudct.mc.sensors` (the photons of
    :func:`forward_render_kernel`): out = (images[nbatch, view, row, col], events[nbatch],
    fluxes[nbatch, 1, 1, NFLUX], no_residual[1, 1, 1])."""
    images, events, fluxes, unused = out
    t = cuda.grid(1)
    if t >= images.shape[0] * count:
        return
    b, index = thread_photon(t, per_batch, first, count)
    vertices, _ = trace_photon(
        scene.grid, scene.bank, scene.cams, scene.copies, scene.sun, periodic, ground,
        rr_depth, rr_survival, seed, index, RENDER_MODE, images[b], unused, unused, 0.0, None, 0,
        None, fluxes[b],
    )
    cuda.atomic.add(events, b, vertices)


@cuda.jit(cache=True)
def forward_residual_kernel(
    scene, periodic, ground, rr_depth, rr_survival, seed, per_batch, first, count, nbatch, out
):
    """First gradient pass (RESIDUAL) of every photon of the launch: out = (residual, events,
    path_sum[nbatch * count], vertices[nbatch * count], no_image[1, 1, 1],
    no_gradient[1, 1, 1]); thread t writes path_sum[t] and vertices[t]."""
    residual, events, path_sum, vertices, no_image, no_gradient = out
    t = cuda.grid(1)
    if t >= nbatch * count:
        return
    b, index = thread_photon(t, per_batch, first, count)
    n, s = trace_photon(
        scene.grid, scene.bank, scene.cams, scene.copies, scene.sun, periodic, ground,
        rr_depth, rr_survival, seed, index, RESIDUAL_MODE, no_image, residual, no_gradient, 0.0,
    )
    path_sum[t] = s
    vertices[t] = n
    cuda.atomic.add(events, b, n)


@cuda.jit(cache=True)
def forward_gradient_kernel(
    scene, periodic, ground, rr_depth, rr_survival, seed, per_batch, first, count, mode, out
):
    """Second gradient pass (``mode`` GRADIENT or REFF_GRADIENT) in an explicit photon
    order: out = (residual,
    gradients[nbatch, x, y, z], path_sum, order[n], no_image[1, 1, 1]); thread t re-traces
    launch photon p = order[t] (the layout of :func:`forward_residual_kernel`) with its
    path sum. The order lets warps hold photons of similar path length."""
    residual, gradients, path_sum, order, no_image = out
    t = cuda.grid(1)
    if t >= order.shape[0]:
        return
    p = order[t]
    b = p // count
    index = b * per_batch + first + p % count
    trace_photon(
        scene.grid, scene.bank, scene.cams, scene.copies, scene.sun, periodic, ground,
        rr_depth, rr_survival, seed, index, mode, no_image, residual, gradients[b],
        path_sum[p],
    )


@njit(cache=True)
def pixel_sample_of_thread(t, nbatch, nview, nrows, ncols, per_batch, first):
    """Batch, pixel and sample index of thread ``t`` of a pixel-sample kernel: threads run
    pixel-fastest, then batch, then sample ``first + k``; the sample index is the CPU's
    (:func:`cloudct.mc.backward.backward_batches`)."""
    npix = nview * nrows * ncols
    pixel = t % npix
    rest = t // npix
    b = rest % nbatch
    k = first + rest // nbatch
    view = pixel // (nrows * ncols)
    row = (pixel // ncols) % nrows
    col = pixel % ncols
    return b, view, row, col, (pixel * nbatch + b) * per_batch + k


@cuda.jit(cache=True)
def backward_kernel(
    scene, periodic, ground, rr_depth, rr_survival, seed, per_batch, first, count, out
):
    """Backward samples ``first .. first + count - 1`` of every pixel and batch: out =
    (images[nbatch, view, row, col], events[nbatch])."""
    images, events = out
    nbatch = images.shape[0]
    t = cuda.grid(1)
    if t >= images.size * count:
        return
    b, view, row, col, index = pixel_sample_of_thread(
        t, nbatch, images.shape[1], images.shape[2], images.shape[3], per_batch, first
    )
    value, vertices = trace_pixel_sample(
        scene.grid, scene.bank, scene.cams, scene.sun, periodic, ground, rr_depth,
        rr_survival, seed, index, view, row, col,
    )
    add_to(images[b], view, row, col, value)
    cuda.atomic.add(events, b, vertices)


@cuda.jit(device=True)
def camera_gradient_thread(
    t, estimator, scene, periodic, ground, rr_depth, rr_survival, seed, per_batch, first,
    count, probes, quadratic, mis, out,
):
    """Thread ``t``'s DRT, sample-matching or backward score-function sample (``estimator``,
    a code of :mod:`cloudct.mc.camera_gradient`) among the samples ``first .. first + count
    - 1`` of every batch (and of every pixel, when the alias table is empty), with the
    sample indices of :func:`cloudct.mc.camera_gradient.camera_gradient_batches`: out =
    (residual[view, row, col], table, gradients[nbatch, nx, ny, nz], events[nbatch])."""
    residual, table, gradients, events = out
    nbatch = gradients.shape[0]
    nrows, ncols = residual.shape[1], residual.shape[2]
    if table.pixel.size == 0:
        if t >= residual.size * nbatch * count:
            return
        b, view, row, col, index = pixel_sample_of_thread(
            t, nbatch, residual.shape[0], nrows, ncols, per_batch, first
        )
        weight = residual[view, row, col]
        if weight == 0.0:
            return
    else:
        if t >= nbatch * count:
            return
        b = t % nbatch
        index = b * per_batch + first + t // nbatch
        view, row, col, weight = drawn_pixel(table, seed, index, nrows, ncols)
    vertices = gradient_sample(
        estimator, scene.grid, scene.bank, scene.cams, scene.sun, periodic, ground, rr_depth,
        rr_survival, seed, index, view, row, col, weight, gradients[b], probes, quadratic,
        mis,
    )
    cuda.atomic.add(events, b, vertices)


# One kernel per camera-side estimator, given as an int64 constant that NVVM folds: a run
# compiles only its estimator's code (all three in one kernel: 225,000 lines of PTX and 107 s
# of NVVM and ptxas on 2 cores; each alone 66,000-83,000 lines and 25-45 s).
DRT_CODE, SAMPLE_MATCHING_CODE, SCORE_CODE = (np.int64(e) for e in (DRT, SAMPLE_MATCHING, SCORE))


@cuda.jit(cache=True)
def drt_gradient_kernel(
    scene, periodic, ground, rr_depth, rr_survival, seed, per_batch, first, count, probes,
    quadratic, mis, out,
):
    """DRT samples: :func:`camera_gradient_thread` (``probes``, ``quadratic`` and ``mis``
    unused)."""
    camera_gradient_thread(cuda.grid(1), DRT_CODE, scene, periodic, ground, rr_depth,
                           rr_survival, seed, per_batch, first, count, probes, quadratic,
                           mis, out)


@cuda.jit(cache=True)
def sample_matching_gradient_kernel(
    scene, periodic, ground, rr_depth, rr_survival, seed, per_batch, first, count, probes,
    quadratic, mis, out,
):
    """Sample-matching samples: :func:`camera_gradient_thread`."""
    camera_gradient_thread(cuda.grid(1), SAMPLE_MATCHING_CODE, scene, periodic, ground,
                           rr_depth, rr_survival, seed, per_batch, first, count, probes,
                           quadratic, mis, out)


@cuda.jit(cache=True)
def backward_score_gradient_kernel(
    scene, periodic, ground, rr_depth, rr_survival, seed, per_batch, first, count, probes,
    quadratic, mis, out,
):
    """Backward score-function samples: :func:`camera_gradient_thread` (``probes``,
    ``quadratic`` and ``mis`` unused)."""
    camera_gradient_thread(cuda.grid(1), SCORE_CODE, scene, periodic, ground, rr_depth,
                           rr_survival, seed, per_batch, first, count, probes, quadratic,
                           mis, out)


#: The camera-side gradient kernel of each estimator code.
CAMERA_GRADIENT_KERNELS = {DRT: drt_gradient_kernel,
                           SAMPLE_MATCHING: sample_matching_gradient_kernel,
                           SCORE: backward_score_gradient_kernel}


# --------------------------------------------------------------------------------------
# Host side
# --------------------------------------------------------------------------------------


def to_device(value):
    """Arrays (also inside tuples and NamedTuples) copied to the device; scalars as they
    are. Under the simulator arrays stay numpy arrays (see the module docstring)."""
    if isinstance(value, np.ndarray):
        value = np.ascontiguousarray(value)
        return value.copy() if SIMULATOR else cuda.to_device(value)
    if isinstance(value, tuple):
        items = [to_device(v) for v in value]
        return type(value)(*items) if hasattr(value, "_fields") else tuple(items)
    return value


def to_host(array) -> np.ndarray:
    """A device array's contents as a numpy array."""
    return np.array(array) if SIMULATOR else array.copy_to_host()


def device_scene(k) -> DeviceScene:
    """The arrays of :class:`cloudct.mc.estimate.KernelInputs` on the device."""
    return DeviceScene(*to_device((k.grid, k.bank, k.cams, k.copies, k.sun)))


def device_zeros(shape, dtype=np.float64):
    """A zero-filled device array."""
    return to_device(np.zeros(shape, dtype))


def free_memory() -> int:
    """Free device memory in bytes (a large number under the simulator)."""
    if SIMULATOR:
        return 1 << 40
    return int(cuda.current_context().get_memory_info()[0])


def launch_count(nbatch: int, per_photon_bytes: int = 0, fraction: float = 0.5) -> int:
    """Photons of each batch per launch: at most :data:`MAX_LAUNCH` threads, and the
    per-photon device buffers within ``fraction`` of the free device memory."""
    limit = MAX_LAUNCH
    if per_photon_bytes:
        limit = min(limit, int(fraction * free_memory()) // per_photon_bytes)
    return max(1, limit // nbatch)


def check_fits(nbytes: int, what: str, advice: str = "use fewer batches") -> None:
    """Refuse, before any launch, device buffers (``what``, ``nbytes``) that would take more
    than 80 % of the free device memory, with ``advice`` on what to change."""
    free = free_memory()
    if nbytes > 0.8 * free:
        raise MemoryError(
            f"{what} need {nbytes / 2**30:.2f} GiB of device memory, {free / 2**30:.2f} GiB "
            f"free: {advice}"
        )


def launch_kernel(kernel, nthreads: int, threads_per_block: int, *args) -> None:
    """Launch a CUDA ``kernel`` on at least ``nthreads`` threads in blocks of
    ``threads_per_block`` (the kernels return early past their last photon)."""
    blocks = (nthreads + threads_per_block - 1) // threads_per_block
    kernel[blocks, threads_per_block](*args)


class Launcher(ABC):
    """Calls ``run(first, last)`` of :func:`cloudct.mc.estimate.run_in_rounds`: photons
    ``first .. last - 1`` of every batch, in launches of at most ``chunk`` per batch. The
    outputs stay on the device until the round that ends at ``per_batch``, which copies
    them into the caller's host arrays."""

    chunk: int
    per_batch: int
    nbatch: int

    @property
    def max_rounds(self) -> int:
        """Rounds for :func:`~cloudct.mc.estimate.run_in_rounds`: at least one launch each."""
        return max(1, min(50, math.ceil(self.per_batch / self.chunk)))

    def __call__(self, first: int, last: int) -> None:
        for start in range(first, last, self.chunk):
            self.launch(start, min(self.chunk, last - start))
        if not SIMULATOR:
            cuda.synchronize()
        if last == self.per_batch:
            self.finish()

    def _pixel_sample_setup(self, k, rr_depth, rr_survival, seed, per_batch, host, tpb):
        """Common state of the pixel-sample launchers (backward, DRT, sample matching): the
        device scene, the kernels' scalar arguments, and the host outputs (per-batch array
        first)."""
        self.scene = device_scene(k)
        self.scalars = (k.periodic, k.ground, rr_depth, rr_survival, seed, per_batch)
        self.per_batch = per_batch
        self.host = host
        self.tpb = tpb or THREADS_PER_BLOCK
        self.nbatch = host[0].shape[0]

    @abstractmethod
    def launch(self, first: int, count: int) -> None:
        """Launch the kernel for samples ``first .. first + count - 1`` of every batch."""

    @abstractmethod
    def finish(self) -> None:
        """Copy the device outputs into the caller's host arrays."""


class ForwardLauncher(Launcher):
    """The CUDA counterpart of :func:`cloudct.mc.forward.forward_batches`, same arguments:
    RENDER fills ``images``, GRADIENT ``gradients`` (RESIDUAL then GRADIENT pass for every
    launch, the second in the order of :func:`sort_by_path_length` when ``sort_paths``).
    With a float64[nbatch, 1, 1, NFLUX] array ``fluxes`` (RENDER only), the photons also add
    their flux tallies to it, as :func:`cloudct.mc.forward.sensor_batches` does."""

    def __init__(
        self, k, rr_depth, rr_survival, seed, per_batch, mode, images, residual, gradients,
        events, *, fluxes: np.ndarray | None = None, sort_paths: bool | None = None,
        threads_per_block: int | None = None,
    ):
        if mode not in (RENDER, GRADIENT, REFF_GRADIENT):
            raise ValueError(f"mode must be RENDER, GRADIENT or REFF_GRADIENT, got {mode}")
        if fluxes is not None and mode != RENDER:
            raise ValueError("flux tallies are made by RENDER launches only")
        self.scene = device_scene(k)
        self.scalars = (k.periodic, k.ground, rr_depth, rr_survival, seed, per_batch)
        self.per_batch = per_batch
        self.mode = mode
        self.host = (images, gradients, events, fluxes)
        self.fluxes = None if fluxes is None else device_zeros(fluxes.shape)
        self.sort_paths = SORT_PATHS if sort_paths is None else sort_paths
        self.tpb = threads_per_block or THREADS_PER_BLOCK
        self.nbatch = images.shape[0] if mode == RENDER else gradients.shape[0]
        self.events = device_zeros(self.nbatch, np.int64)
        self.dummy = device_zeros((1, 1, 1))
        if mode == RENDER:
            check_fits(images.nbytes, "the per-batch images")
            self.images = device_zeros(images.shape)
            self.chunk = launch_count(self.nbatch)
        else:
            check_fits(gradients.nbytes, "the per-batch gradients")
            self.gradients = device_zeros(gradients.shape)
            self.residual = to_device(residual)
            self.chunk = launch_count(self.nbatch, BYTES_PER_GRADIENT_PHOTON)
            self.path_sum = device_zeros(self.nbatch * self.chunk)
            self.vertices = device_zeros(self.nbatch * self.chunk, np.int64)

    def launch(self, first: int, count: int) -> None:
        n = self.nbatch * count
        if self.mode == RENDER:
            if self.fluxes is None:
                kernel, out = forward_render_kernel, (self.images, self.events, self.dummy,
                                                      self.dummy)
            else:
                kernel, out = forward_sensor_kernel, (self.images, self.events, self.fluxes,
                                                      self.dummy)
            launch_kernel(kernel, n, self.tpb, self.scene, *self.scalars, first, count, out)
            return
        path_sum, vertices = self.path_sum, self.vertices
        out = (self.residual, self.events, path_sum, vertices, self.dummy, self.dummy)
        launch_kernel(forward_residual_kernel, n, self.tpb, self.scene, *self.scalars, first, count,
                      self.nbatch, out)
        sums = to_host(path_sum[:n])
        if self.sort_paths:
            order = sort_by_path_length(to_host(vertices[:n]))
            order = order[sums[order] != 0.0]
        else:
            order = np.flatnonzero(sums)
        if order.size == 0:
            return
        out = (self.residual, self.gradients, path_sum, to_device(order.astype(np.int64)),
               self.dummy)
        launch_kernel(forward_gradient_kernel, order.size, self.tpb, self.scene, *self.scalars,
                      first, count, self.mode, out)

    def finish(self) -> None:
        images, gradients, events, fluxes = self.host
        if self.mode == RENDER:
            images += to_host(self.images)
            if fluxes is not None:
                fluxes += to_host(self.fluxes)
        else:
            gradients += to_host(self.gradients)
        events += to_host(self.events)


class SensorLauncher(ForwardLauncher):
    """The CUDA counterpart of :func:`cloudct.mc.forward.sensor_batches`, same arguments: a
    RENDER launch that also adds the photons' flux tallies to ``fluxes``."""

    def __init__(self, k, rr_depth, rr_survival, seed, per_batch, images, fluxes, events,
                 **options):
        super().__init__(k, rr_depth, rr_survival, seed, per_batch, RENDER, images, None, None,
                         events, fluxes=fluxes, **options)


class BackwardLauncher(Launcher):
    """The CUDA counterpart of :func:`cloudct.mc.backward.backward_batches`."""

    def __init__(
        self, k, rr_depth, rr_survival, seed, per_batch, images, events, *,
        threads_per_block: int | None = None,
    ):
        self._pixel_sample_setup(k, rr_depth, rr_survival, seed, per_batch, (images, events),
                                 threads_per_block)
        check_fits(images.nbytes, "the per-batch images")
        self.images = device_zeros(images.shape)
        self.events = device_zeros(self.nbatch, np.int64)
        npix = int(np.prod(images.shape[1:]))
        self.chunk = max(1, MAX_LAUNCH // (npix * self.nbatch))

    def launch(self, first: int, count: int) -> None:
        n = int(np.prod(self.images.shape)) * count
        launch_kernel(backward_kernel, n, self.tpb, self.scene, *self.scalars, first, count,
                      (self.images, self.events))

    def finish(self) -> None:
        images, events = self.host
        images += to_host(self.images)
        events += to_host(self.events)



class CameraGradientLauncher(Launcher):
    """The CUDA counterpart of :func:`cloudct.mc.camera_gradient.camera_gradient_batches`,
    same arguments."""

    def __init__(
        self, k, rr_depth, rr_survival, seed, per_batch, estimator, probes, quadratic, mis,
        residual, table, gradients, events, *, threads_per_block: int | None = None,
    ):
        self._pixel_sample_setup(k, rr_depth, rr_survival, seed, per_batch,
                                 (gradients, events), threads_per_block)
        check_fits(gradients.nbytes, "the per-batch gradients")
        self.kernel = CAMERA_GRADIENT_KERNELS[int(estimator)]
        self.options = (probes, quadratic, mis)
        self.residual = to_device(residual)
        self.table = to_device(table)
        self.gradients = device_zeros(gradients.shape)
        self.events = device_zeros(self.nbatch, np.int64)
        # threads per sample index k: every pixel of every batch, or every batch (table)
        self.width = self.nbatch * (1 if table.pixel.size else int(residual.size))
        self.chunk = max(1, MAX_LAUNCH // self.width)

    def launch(self, first: int, count: int) -> None:
        launch_kernel(self.kernel, self.width * count, self.tpb, self.scene, *self.scalars,
                      first, count, *self.options, (self.residual, self.table, self.gradients,
                                                    self.events))

    def finish(self) -> None:
        gradients, events = self.host
        gradients += to_host(self.gradients)
        events += to_host(self.events)
