"""The scaffold every Monte Carlo estimate of cloudct runs on, held once.

A render, a gradient or a set of domain-mean fluxes is a sum over ``sampling.batches``
independent batches of paths: the estimate is the mean of the batch means and its standard
error their standard deviation over sqrt(batches) (:func:`mean_and_std_error`). This module
holds what every estimator shares:

- the **kernel inputs**: a validated medium and scene as the kernels' arrays
  (:func:`kernel_inputs`);
- the **sampling**: batches, Russian roulette, seed and back end (:class:`Sampling`), with
  the checks of sample counts and of pixel weights (:func:`check_residual`);
- **batching and the photon-index rule**: ``ceil(samples / batches)`` samples per batch;
  photon (or drawn pixel sample) k of batch b has index ``b * per_batch + k``, sample k of
  pixel p in batch b ``(p * batches + b) * per_batch + k`` (each index owns its random
  streams, so an estimate does not depend on threads, rounds, devices or workers);
- **rounds**: a runner traces samples ``first .. last - 1`` of every batch, called in up to
  50 rounds with a progress bar (:func:`run_in_rounds`); on the CPU each thread takes the
  next batch as it frees (a dynamic schedule, which leaves every sum as it is);
- the **batch kernels**: :data:`BATCH_KERNELS` holds one :class:`BatchKernel` per kind of
  path the engine traces (forward photons for images or for the score-function gradient,
  forward photons with flux tallies, backward pixel samples, camera-side gradient samples;
  path recycling registers its replays of stored paths, :func:`register_batch_kernel`),
  with its CPU batch kernel, its CUDA launcher and how its batches may be split;
- **where batches run**: :func:`batch_means` runs a batch kernel in this process, on the CPU
  or a GPU, or hands it to a :class:`~cloudct.mc.executor.BatchExecutor` (Dask workers),
  whose one entry point takes the kernel's name.

The gradient estimators the retrieval chooses from by name, and what each supports, are
registered in :data:`cloudct.mc.gradient.ESTIMATORS`; each names its batch kernel here.
"""

from __future__ import annotations

import importlib
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import xarray as xr
from numba import parallel_chunksize
from tqdm.auto import tqdm

from cloudct.mc.backend import BACKENDS, resolve_backend
from cloudct.mc.backward import backward_batches
from cloudct.mc.camera_gradient import camera_gradient_batches
from cloudct.mc.cameras import CameraArrays, camera_arrays
from cloudct.mc.detector_sampling import DEFAULT_AIM_FRACTION
from cloudct.mc.executor import BatchExecutor, check_executor
from cloudct.mc.forward import RENDER, forward_batches, sensor_batches
from cloudct.mc.scene import Scene, check_scene, periodic_copy_ranges
from cloudct.mc.sun import SunArrays, sun_arrays
from cloudct.medium import cell_edges, is_optical, validate_medium
from cloudct.optics import kernel_arrays_and_scale, to_optical
from cloudct.physics.mixing import OpticalGrid
from cloudct.physics.phase import TABULATED, PhaseBank

# ------------------------------------------------------------------------------------------
# Kernel inputs
# ------------------------------------------------------------------------------------------


class KernelInputs(NamedTuple):
    """Everything the kernels need of a medium and a scene."""

    grid: OpticalGrid
    bank: PhaseBank
    cams: CameraArrays
    copies: np.ndarray
    sun: SunArrays
    periodic: bool
    ground: float  # ground albedo, -1 for no ground
    edges: tuple[np.ndarray, np.ndarray, np.ndarray]
    #: d beta' / d beta of a phase truncation (:func:`cloudct.optics.cloud_extinction_scale`;
    #: None: 1), float64[x, y, z]
    cloud_scale: np.ndarray | None = None


def kernel_inputs(
    medium: xr.Dataset, scene: Scene, aim_fraction: float | None = None,
    entry_cloud_share: float = 0.0,
) -> KernelInputs:
    """Validate a medium and a scene and gather them into kernel arrays (``aim_fraction``:
    the share of scattering directions aimed at the cameras by forward paths and at the sun
    by backward ones, see :mod:`cloudct.mc.detector_sampling`; 0 switches it off, None
    chooses it by the optics: :func:`default_aim_fraction`). ``entry_cloud_share``: the
    forward photons' share m in [0, 1) entering where the clouds are
    (:func:`cloudct.mc.sun.sun_arrays`; 0: uniform entry)."""
    grid, bank, edges, cloud_scale = medium_arrays(medium)
    check_scene(scene, edges)
    if aim_fraction is None:
        aim_fraction = default_aim_fraction(bank)
    return KernelInputs(
        grid=grid,
        bank=bank,
        cams=camera_arrays(scene.cameras, aim_fraction),
        copies=periodic_copy_ranges(scene, edges),
        sun=sun_arrays(scene.sun, edges, scene.periodic, grid, entry_cloud_share)._replace(
            aim_fraction=float(aim_fraction)),
        periodic=scene.periodic,
        ground=-1.0 if scene.ground_albedo is None else float(scene.ground_albedo),
        edges=edges,
        cloud_scale=cloud_scale,
    )


def medium_arrays(
    medium: xr.Dataset,
) -> tuple[OpticalGrid, PhaseBank, tuple[np.ndarray, np.ndarray, np.ndarray],
           np.ndarray | None]:
    """A validated medium's kernel arrays, cell edges and the chain-rule factor of its
    phase truncation (:func:`cloudct.optics.cloud_extinction_scale`; microphysical media
    converted with their optics)."""
    validate_medium(medium)
    optical = medium if is_optical(medium) else to_optical(medium)
    grid, bank, scale = kernel_arrays_and_scale(optical)
    return grid, bank, cell_edges(optical), scale


def per_cloud_extinction(k: KernelInputs, gradients: np.ndarray) -> np.ndarray:
    """Gradients (..., x, y, z) with respect to the cloud extinction the kernels traced
    turned into gradients with respect to the medium's: times d beta' / d beta where the
    medium's phase functions are truncated (:mod:`cloudct.optics`), else unchanged."""
    return gradients if k.cloud_scale is None else gradients * k.cloud_scale


def default_aim_fraction(bank: PhaseBank) -> float:
    """The aim fraction used when none is given: :data:`DEFAULT_AIM_FRACTION` when a phase
    function is tabulated (Mie optics, whose diffraction peak makes fireflies), else 0
    (Henyey-Greenstein and Rayleigh: measured in docs/benchmarks.md, "Mie optics")."""
    return DEFAULT_AIM_FRACTION if has_peak(bank) else 0.0


def has_peak(bank: PhaseBank) -> bool:
    """Whether a phase function of ``bank`` is tabulated (Mie optics, with a diffraction
    peak: what sets the aim fraction's and the synthetic images' estimator defaults)."""
    return bool(np.any(bank.kind == TABULATED))


# ------------------------------------------------------------------------------------------
# Sampling
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Sampling:
    """How an estimate's paths are sampled, whatever the estimator.

    ``batches``: independent batches (at least 2, for standard errors); ``seed``: of the
    counter-based random streams (same seed, same estimate); ``rr_depth``,
    ``rr_survival``: Russian roulette, from vertex ``rr_depth`` on a path survives each
    vertex with probability ``rr_survival`` (medium-independent, unbiased); ``backend``:
    ``"cpu"``, ``"cuda"`` or ``"auto"`` (:mod:`cloudct.mc.backend`). Checked when made.
    """

    batches: int = 32
    seed: int = 0
    rr_depth: int = 100
    rr_survival: float = 0.95
    backend: str = "cpu"

    def __post_init__(self) -> None:
        if int(self.batches) < 2:
            raise ValueError(f"batches must be at least 2 for standard errors, got "
                             f"{self.batches}")
        if not 0.0 < self.rr_survival <= 1.0 or self.rr_depth < 1:
            raise ValueError("rr_survival must be in (0, 1] and rr_depth >= 1")
        if self.backend not in BACKENDS:
            raise ValueError(f"backend must be one of {BACKENDS}, got {self.backend!r}")

    def per_batch(self, samples: int) -> int:
        """Samples per batch for ``samples`` in all (a positive count), rounded up."""
        if int(samples) < 1:
            raise ValueError(f"photons (samples) must be a positive count, got {samples}")
        return math.ceil(int(samples) / self.batches)


def check_residual(residual: np.ndarray, scene: Scene) -> np.ndarray:
    """The residual weights as a float64 (view, row, col) array matching the scene."""
    residual = np.ascontiguousarray(residual, dtype=np.float64)
    cam = scene.cameras[0]
    shape = (len(scene.cameras), cam.nrows, cam.ncols)
    if residual.shape != shape:
        raise ValueError(f"residual has shape {residual.shape}, the scene's images {shape}")
    if not np.all(np.isfinite(residual)):
        raise ValueError("residual has NaN or infinite pixels (mask them with weight 0)")
    return residual


# ------------------------------------------------------------------------------------------
# Rounds and reduction
# ------------------------------------------------------------------------------------------


def run_in_rounds(
    run: Callable[[int, int], None], per_batch: int, batches: int, progress: bool | None,
    unit: str, desc: str, max_rounds: int = 50,
) -> float:
    """Call ``run(first, last)`` over up to ``max_rounds`` rounds of the per-batch sample
    range, with a progress bar; returns the wall time in seconds."""
    rounds = np.unique(
        np.linspace(0, per_batch, min(per_batch, max_rounds) + 1).astype(np.int64)
    )
    disable = None if progress is None else not progress
    start = time.perf_counter()
    # the CPU's threads take the batches one at a time as each frees (numba's dynamic
    # schedule): a batch's paths take a random time, and the even split of the batches left
    # threads waiting at the end of every round; each batch is still traced in order by one
    # thread, so the sums are the same
    with tqdm(total=per_batch * batches, disable=disable, unit=unit, desc=desc) as bar, \
            parallel_chunksize(1):
        for first, last in zip(rounds[:-1], rounds[1:], strict=True):
            run(int(first), int(last))
            bar.update(int(last - first) * batches)
    return time.perf_counter() - start


def mean_and_std_error(batch_means: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mean over the batches (axis 0) and its standard error (std of the batch means
    over sqrt(batches))."""
    return (batch_means.mean(axis=0),
            batch_means.std(axis=0, ddof=1) / math.sqrt(batch_means.shape[0]))


# ------------------------------------------------------------------------------------------
# Batch kernels
# ------------------------------------------------------------------------------------------


class _CPURunner:
    """Calls a CPU batch kernel with fixed arguments around ``first, last``."""

    max_rounds = 50

    def __init__(self, kernel, head: tuple, tail: tuple):
        self.kernel = kernel
        self.head = head
        self.tail = tail

    def __call__(self, first: int, last: int) -> None:
        self.kernel(*self.head, first, last, *self.tail)


def _forward_head(k: KernelInputs, s: Sampling, per_batch: int, args: tuple) -> tuple:
    return (k.grid, k.bank, k.cams, k.copies, k.sun, k.periodic, k.ground, s.rr_depth,
            s.rr_survival, s.seed, per_batch)


def _camera_head(k: KernelInputs, s: Sampling, per_batch: int, args: tuple) -> tuple:
    return (k.grid, k.bank, k.cams, k.sun, k.periodic, k.ground, s.rr_depth, s.rr_survival,
            s.seed, per_batch)


def _forward_tail(args: tuple, values: np.ndarray, events: np.ndarray) -> tuple:
    mode, residual = args  # RENDER fills the images, GRADIENT the per-voxel gradients
    unused = np.zeros((values.shape[0], 1, 1, 1))
    if mode == RENDER:
        return mode, values, np.zeros((1, 1, 1)), unused, events
    return mode, unused, residual, values, events


def images_shape(k: KernelInputs, args: tuple) -> tuple[int, ...]:
    """(view, row, col) of the scene's images: the ``shape`` of an image-valued kernel."""
    return (k.cams.position.shape[0], k.cams.nrows, k.cams.ncols)


def voxels_shape(k: KernelInputs, args: tuple) -> tuple[int, ...]:
    """(x, y, z) of the grid: the ``shape`` of a gradient-valued kernel."""
    return tuple(k.grid.extinction.shape[1:])


#: How an executor may split a batch kernel's work (see :mod:`cloudct.distributed.batches`).
BY_BATCHES = "batches"  # ranges of batches, each a shifted range of sample indices
BY_VIEWS = "views"  # ranges of views of every batch (indices depend on the batch count)
EACH_BATCH = "each batch"  # one batch at a time, in the rounds of one process


@dataclass(frozen=True)
class BatchKernel:
    """One kind of path the engine traces, on both back ends.

    The CPU batch kernel ``cpu`` (numba, parallel over batches) is called as ``cpu(*head(k,
    sampling, per_batch, args), first, last, *tail(args, values, events))``, the CUDA
    launcher named ``cuda`` (a class of the module ``cuda_module``, imported only then) as
    ``Launcher(k, rr_depth, rr_survival, seed, per_batch, *cuda_tail(args, values,
    events))`` (``cuda_tail`` None: ``tail``); both add the batch sums to ``values``
    (``float64[batches, *shape(k, args)]``) and the path vertices to ``events``. ``args``
    are the kernel's own inputs (named in :data:`BATCH_KERNELS`). ``split(args)`` says how
    an executor may split the work (one of :data:`BY_BATCHES`, :data:`BY_VIEWS`,
    :data:`EACH_BATCH`; ``splits``: all it may say); ``executors``: whether it runs on one
    at all (``elsewhere``: where it runs instead); ``unit``: what one sample is, for
    progress bars; ``thread``: what one CUDA thread traces."""

    name: str
    unit: str
    cpu: Callable
    cuda: str
    thread: str
    head: Callable[[KernelInputs, Sampling, int, tuple], tuple]
    tail: Callable[[tuple, np.ndarray, np.ndarray], tuple]
    shape: Callable[[KernelInputs, tuple], tuple[int, ...]]
    splits: tuple[str, ...]
    split: Callable[[tuple], str] = lambda args: BY_BATCHES
    executors: bool = True
    elsewhere: str = "this process only"
    cuda_module: str = "cloudct.mc.cuda_kernels"
    cuda_tail: Callable[[tuple, np.ndarray, np.ndarray], tuple] | None = None


#: The batch kernels by name; their ``args``: forward (mode RENDER or GRADIENT, residual),
#: sensors (the flux tallies' array, float64[batches, 1, 1, NFLUX]), backward (),
#: camera-gradient (estimator code, probes, quadratic, mis, residual, alias table). A layer
#: above the engine adds its own with :func:`register_batch_kernel` (path recycling's
#: replays, :mod:`cloudct.recycling.replay`).
BATCH_KERNELS: dict[str, BatchKernel] = {
    r.name: r for r in (
        BatchKernel("forward", "photon", forward_batches, "ForwardLauncher",
                    "forward photon (GRADIENT: two passes, the second sorted by path length)",
                    _forward_head, _forward_tail,
                    lambda k, a: (images_shape if a[0] == RENDER else voxels_shape)(k, a),
                    (BY_BATCHES,)),
        BatchKernel("sensors", "photon", sensor_batches, "SensorLauncher",
                    "forward photon, with flux tallies", _forward_head,
                    lambda a, values, events: (values, a[0], events), images_shape,
                    (BY_BATCHES,), executors=False),
        BatchKernel("backward", "sample/px", backward_batches, "BackwardLauncher",
                    "backward pixel sample", _camera_head,
                    lambda a, values, events: (values, events), images_shape,
                    (BY_VIEWS,), lambda a: BY_VIEWS),
        BatchKernel("camera-gradient", "sample", camera_gradient_batches,
                    "CameraGradientLauncher", "DRT or sample-matching pixel sample",
                    _camera_head, lambda a, values, events: (*a, values, events),
                    voxels_shape, (BY_BATCHES, EACH_BATCH),
                    lambda a: BY_BATCHES if a[-1].pixel.size else EACH_BATCH),
    )
}


def register_batch_kernel(record: BatchKernel) -> BatchKernel:
    """Add ``record`` to :data:`BATCH_KERNELS` (a layer above the engine registers its
    kernels so, at its import); a name taken by another record is an error."""
    known = BATCH_KERNELS.setdefault(record.name, record)
    if known is not record:
        raise ValueError(f"a batch kernel named {record.name!r} is registered already")
    return record


def batch_runner(
    kernel: str, backend: str, k: KernelInputs, sampling: Sampling, per_batch: int,
    args: tuple, values: np.ndarray, events: np.ndarray,
):
    """What :func:`run_in_rounds` calls to trace batch kernel ``kernel`` on a resolved
    ``backend`` (see :class:`BatchKernel`)."""
    record = BATCH_KERNELS[kernel]
    if backend == "cuda":
        launcher = getattr(importlib.import_module(record.cuda_module), record.cuda)
        tail = (record.cuda_tail or record.tail)(args, values, events)
        return launcher(k, sampling.rr_depth, sampling.rr_survival, sampling.seed, per_batch,
                        *tail)
    return _CPURunner(record.cpu, record.head(k, sampling, per_batch, args),
                      record.tail(args, values, events))


def batch_kernel_table() -> str:
    """The batch kernels registered in :data:`BATCH_KERNELS` as the Markdown table of
    ``docs/architecture.md``, which shows them with :mod:`cloudct.recycling` imported (its
    replays registered; a test keeps the page equal to it)."""
    lines = ["| batch kernel | CPU (numba) | CUDA launcher | one CUDA thread per | executors "
             "split it by |", "|" + " --- |" * 5]
    for r in BATCH_KERNELS.values():
        split = " or ".join(r.splits)
        lines.append(f"| `{r.name}` | `{r.cpu.py_func.__name__}` | `{r.cuda}` | {r.thread} | "
                     f"{split if r.executors else r.elsewhere} |")
    return "\n".join(lines) + "\n"


def combined_inputs(
    k: KernelInputs, sampling: Sampling, per_batch: int, pixel_samples: int
) -> tuple[KernelInputs, int]:
    """The kernel inputs of the combined estimator with ``per_batch`` forward photons per
    batch and ``pixel_samples`` backward samples of each pixel in all (their ratio N_b / N_f
    per batch in ``cams.mis_ratio``), and the backward samples of each pixel per batch."""
    per_pixel = sampling.per_batch(pixel_samples)
    return k._replace(cams=k.cams._replace(mis_ratio=per_pixel / per_batch)), per_pixel


def batch_means(
    kernel: str, k: KernelInputs, args: tuple, *, per_batch: int, sampling: Sampling,
    progress: bool | None = None, executor: BatchExecutor | None = None, desc: str = "",
) -> tuple[np.ndarray, dict]:
    """The batch means of batch kernel ``kernel`` (float64[batches, ...]: each batch's sum
    over its ``per_batch`` samples, divided by ``per_batch``) and the run's ``info`` (path
    vertices "events", "wall_time", "backend"; an executor adds its bookkeeping), traced
    in this process on ``sampling.backend`` or by ``executor``: for the same seed, the same
    values wherever the batches run (bitwise on the CPU, here or on Dask workers; to
    rounding on a GPU, whose threads add into an element in another order)."""
    record = BATCH_KERNELS[kernel]
    if executor is not None:
        if not record.executors:
            raise ValueError(f"the {kernel} kernel runs in this process only (executor=None)")
        sums, events, info = check_executor(executor).batch_sums(
            kernel, k, args, per_batch=per_batch, sampling=sampling, progress=progress,
            desc=desc or kernel,
        )
    else:
        backend = resolve_backend(sampling.backend)
        sums = np.zeros((sampling.batches, *record.shape(k, args)))
        events = np.zeros(sampling.batches, dtype=np.int64)
        run = batch_runner(kernel, backend, k, sampling, per_batch, args, sums, events)
        wall = run_in_rounds(run, per_batch, sampling.batches, progress, unit=record.unit,
                             desc=desc or kernel, max_rounds=run.max_rounds)
        info = {"wall_time": wall, "backend": backend}
    return sums / per_batch, {"events": int(events.sum()), **info}
