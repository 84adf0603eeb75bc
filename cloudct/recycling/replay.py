"""Re-evaluation of stored paths under a new medium M_t (seed paper Eqs. 50-53).

- :func:`correction_log_weights`: log r of every stored path, r = mu(path | M_t) /
  mu(path | M_ref) (Eq. 51), the whole path including its escape segment.
- :func:`effective_sample_size`: (sum r)^2 / sum r^2 over the paths, from per-batch
  summaries (:func:`weight_summary`, :func:`summary_ess`).
- :func:`replay_images`: the images of M_t (Eq. 52), per batch, from the stored paths.
- :func:`replay_gradient`: the residual-weighted score-function gradient of M_t (Eq. 53),
  with respect to the cloud extinction of every voxel (albedo and phase fixed);
  :func:`replay_batch_gradients`: the same per batch.

Every function takes ``backend="cpu" | "cuda" | "auto"`` (default ``"cpu"``), as
:func:`cloudct.mc.render.render` does: ``"cuda"`` re-evaluates the paths on the GPU, one
thread per path (:mod:`cloudct.recycling.cuda_replay`), ``"auto"`` there where a GPU is
available, else on the CPU with a one-line warning.

Each local estimate uses the correction factor of its path's prefix (the segments up to
the event and the directions sampled before it), unbiased like the whole-path factor and
with a smaller variance. The estimates are unbiased for any M_t on the store's grid whose
extinction is positive wherever the reference's is and whose scattering is positive
wherever the reference's is (paths cannot visit where M_ref has no extinction).
"""

from __future__ import annotations

import math

import numpy as np
import xarray as xr

from cloudct.mc.backend import resolve_backend
from cloudct.mc.estimate import (
    BATCH_KERNELS,
    BatchKernel,
    KernelInputs,
    Sampling,
    batch_runner,
    check_residual,
    images_shape,
    kernel_inputs,
    per_cloud_extinction,
    register_batch_kernel,
    voxels_shape,
)
from cloudct.mc.render import images_dataset
from cloudct.mc.traversal import require_exponential
from cloudct.medium import cell_edges
from cloudct.recycling.path_terms import flat_total_extinction
from cloudct.recycling.replay_kernels import (
    log_ratio_batches,
    replay_gradient_batches,
    replay_render_batches,
)
from cloudct.recycling.store import PathStore, check_not_empty, check_same_grid, run_batches


def _inputs(
    store: PathStore, medium: xr.Dataset, mis_ratio: float = 0.0
) -> tuple[KernelInputs, np.ndarray]:
    check_not_empty(store)
    check_same_grid(store, cell_edges(medium))
    if not mis_ratio >= 0.0:
        raise ValueError(f"mis_ratio must be >= 0, got {mis_ratio}")
    # the recording's aim: the combined estimator's weights take the paths' aim factors
    k = kernel_inputs(medium, store.scene, store.info.get("aim_fraction"))
    k = k._replace(cams=k.cams._replace(mis_ratio=float(mis_ratio)))
    require_exponential(k.grid, "recycled paths")  # the store was recorded exponentially
    beta = flat_total_extinction(k.grid)
    if store.variable is not None:
        changed = beta[~store.variable.ravel()] != store.frozen_extinction
        if changed.any():
            raise ValueError(
                f"the medium's extinction differs from the reference's in {changed.sum()} "
                "voxels outside the store's variable mask; record the paths with a mask "
                "holding every voxel that may change"
            )
    return k, beta


def weight_summary(log_r: np.ndarray, batches: int = 1) -> np.ndarray:
    """Per batch of the paths (photon order, ``batches`` equal batches): the largest log r,
    and sum r and sum r^2 in units of that largest r: float64[batches, 3]. The ESS and the
    largest ratio of all paths follow from these (:func:`summary_ess`), so that stores kept
    elsewhere (Dask workers) need return 24 bytes per batch, not 8 per path."""
    log_r = np.asarray(log_r, dtype=float).reshape(int(batches), -1)
    out = np.zeros((log_r.shape[0], 3))
    out[:, 0] = -np.inf
    for b, row in enumerate(log_r):
        top = np.max(row) if row.size else -np.inf
        if np.isfinite(top):
            r = np.exp(row - top)
            out[b] = top, r.sum(), np.sum(r * r)
    return out


def summary_ess(summary: np.ndarray) -> tuple[float, float]:
    """(ESS, largest log r) of all paths from the per-batch :func:`weight_summary` rows,
    combined in batch order: ESS = (sum r)^2 / sum r^2 (0 if all r = 0)."""
    top = float(np.max(summary[:, 0])) if summary.size else -np.inf
    if not np.isfinite(top):
        return 0.0, top
    s1 = s2 = 0.0
    for m, a, b in summary:
        if np.isfinite(m):
            scale = math.exp(m - top)
            s1 += scale * a
            s2 += scale * scale * b
    return float(s1 * s1 / s2), top


def effective_sample_size(log_r: np.ndarray, batches: int = 1) -> float:
    """(sum r)^2 / sum r^2 for correction factors given by their logs (0 if all r = 0),
    summed by batches as :func:`weight_summary` does."""
    return summary_ess(weight_summary(log_r, batches))[0]


def correction_log_weights(
    store: PathStore, medium: xr.Dataset, backend: str = "cpu"
) -> np.ndarray:
    """log r of every stored path under ``medium``, in photon order (exactly 0 under the
    reference medium). Cheap: no local estimates, only the segments' optical depths."""
    backend = resolve_backend(backend)
    k, beta = _inputs(store, medium)
    if backend == "cuda":
        from cloudct.recycling.cuda_replay import log_weights

        return log_weights(store, k, beta, store.has_crossings)
    log_r = np.empty(store.paths)
    log_ratio_batches(
        k.grid, k.bank, beta, store.arrays, store.has_crossings, k.periodic,
        store.per_batch, log_r,
    )
    return log_r


def _replay_head(k: KernelInputs, s: Sampling, per_batch: int, args: tuple) -> tuple:
    store, beta = args[:2]
    return (k.grid, k.bank, k.cams, k.copies, k.sun, k.periodic, k.ground, s.rr_depth,
            s.rr_survival, beta, store.arrays, store.has_crossings, per_batch)


#: The replays as batch kernels of the engine's registry. Their ``args``: (store, beta, log r
#: per path) for the images; (store, beta, log r, residual, trail capacity) for the gradient.
#: On Dask they run where each part of a store is kept (:mod:`cloudct.distributed.recycling`).
_KEPT = "where its store is kept (Dask: `cloudct.distributed.recycling`)"
REPLAY_KERNELS = tuple(register_batch_kernel(record) for record in (
    BatchKernel("replay-render", "path", replay_render_batches, "ReplayLauncher",
                "stored path (local estimates), in the store's thread order", _replay_head,
                lambda a, values, events: (values, a[2], events, a[0].max_records),
                images_shape, (), executors=False, elsewhere=_KEPT,
                cuda_module="cloudct.recycling.cuda_replay",
                cuda_tail=lambda a, values, events: (a[0], a[1], None, values, a[2], events)),
    BatchKernel("replay-gradient", "path", replay_gradient_batches, "ReplayLauncher",
                "stored path (score-function gradient), in the store's thread order",
                _replay_head, lambda a, values, events: (a[3], values, a[2], events, a[4],
                                                         a[0].max_records),
                voxels_shape, (), executors=False, elsewhere=_KEPT,
                cuda_module="cloudct.recycling.cuda_replay",
                cuda_tail=lambda a, values, events: (a[0], a[1], a[3], values, a[2], events)),
))


def _replay(
    store: PathStore, medium: xr.Dataset, residual: np.ndarray | None,
    progress: bool | None, desc: str, backend: str, mis_ratio: float,
) -> tuple[np.ndarray, dict]:
    backend = resolve_backend(backend)
    k, beta = _inputs(store, medium, mis_ratio)
    b = store.batches
    log_r = np.empty(store.paths)
    events = np.zeros(b, dtype=np.int64)
    # the store's roulette and seed; its batches (a part of a store may hold one) size `out`
    sampling = Sampling(seed=store.seed, rr_depth=store.rr_depth,
                        rr_survival=store.rr_survival, backend=backend)
    if residual is None:
        kernel, args = "replay-render", (store, beta, log_r)
    else:
        # scratch room for the crossings of a camera connection (longer ones: walked twice)
        trail_capacity = 4 * sum(e.size - 1 for e in k.edges) + 16
        kernel, args = "replay-gradient", (store, beta, log_r, residual, trail_capacity)
    out = np.zeros((b, *BATCH_KERNELS[kernel].shape(k, args)))
    run = batch_runner(kernel, backend, k, sampling, store.per_batch, args, out, events)
    wall = run_batches(run, store.per_batch, b, progress, unit="path", desc=desc)
    if residual is not None:
        out = per_cloud_extinction(k, out)
        if store.variable is not None:
            out[:, ~store.variable] = 0.0  # connections hold no crossings of frozen voxels
    summary = weight_summary(log_r, store.batches)
    ess = summary_ess(summary)[0]
    info = {
        "photons": store.paths,
        "events": int(events.sum()),
        "wall_time": wall,
        "ess": ess,
        "ess_fraction": ess / store.paths,
        "storage": store.storage,
        "sorted": store.sorted,
        "seed": store.seed,
        "backend": backend,
        "mis_ratio": k.cams.mis_ratio,
        "weight_summary": summary,
        "log_r": log_r,
    }
    return out / store.per_batch, info


def replay_images(
    store: PathStore, medium: xr.Dataset, progress: bool | None = False, backend: str = "cpu",
    mis_ratio: float = 0.0,
) -> tuple[np.ndarray, dict]:
    """Images of ``medium`` from the stored paths, per batch: float64[batches, view, row,
    col] (batch means, like :func:`cloudct.mc.render.render_batches`) and run information
    (``ess``, ``ess_fraction`` of the whole-path correction factors, ``log_r`` per path,
    ``backend`` run on).

    ``mis_ratio`` > 0 makes them the forward half of the combined estimator
    (:mod:`cloudct.mc.combined`): each local estimate weighted by w_f under ``medium``, with
    ``mis_ratio`` backward samples of each pixel per stored path (N_b / N_f, per batch);
    backward samples traced under ``medium`` with the same ratio add the other half
    (:class:`~cloudct.recycling.recycler.Recycler` with ``image_method="combined"``)."""
    return _replay(store, medium, None, progress, "recycled images", backend, mis_ratio)


def replay_render(
    store: PathStore, medium: xr.Dataset, progress: bool | None = False, backend: str = "cpu"
) -> xr.Dataset:
    """Images of ``medium`` from the stored paths as an images Dataset (radiance and its
    standard error over batches), like :func:`cloudct.mc.render.render`."""
    return recycled_images(store, *replay_images(store, medium, progress, backend))


def recycled_images(store, batch_images: np.ndarray, info: dict) -> xr.Dataset:
    """The images Dataset of per-batch images and the info of :func:`replay_images` (or of
    a store with the same attributes and method)."""
    return images_dataset(
        batch_images.mean(axis=0),
        batch_images.std(axis=0, ddof=1) / math.sqrt(store.batches),
        store.scene,
        method="forward-recycled",
        photons=store.paths,
        seed=store.seed,
        batches=store.batches,
        events=info["events"],
        wall_time=info["wall_time"],
        rr_depth=store.rr_depth,
        rr_survival=store.rr_survival,
        storage=store.storage,
        ess_fraction=info["ess_fraction"],
        backend=info.get("backend", "cpu"),
    )


def replay_batch_gradients(
    store: PathStore,
    medium: xr.Dataset,
    residual: np.ndarray,
    progress: bool | None = False,
    backend: str = "cpu",
    mis_ratio: float = 0.0,
) -> tuple[np.ndarray, dict]:
    """The gradient of :func:`replay_gradient` per batch: float64[batches, x, y, z] (batch
    means) and run information with ``log_r`` per path, like :func:`replay_images` (and
    its ``mis_ratio``: the forward half of the combined gradient)."""
    residual = check_residual(residual, store.scene)
    return _replay(store, medium, residual, progress, "recycled gradient", backend, mis_ratio)


def replay_gradient(
    store: PathStore,
    medium: xr.Dataset,
    residual: np.ndarray,
    progress: bool | None = False,
    backend: str = "cpu",
    mis_ratio: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """sum_d residual_d dI_d / d beta_cloud per voxel under ``medium`` from the stored paths
    (Eq. 53 with the path score function of Eqs. 44-49). Returns ``(mean, std_error,
    info)`` like :func:`cloudct.mc.gradient.score_function_gradient`; ``mis_ratio`` as for
    :func:`replay_images`."""
    batch_means, info = replay_batch_gradients(store, medium, residual, progress, backend,
                                               mis_ratio)
    return (
        batch_means.mean(axis=0),
        batch_means.std(axis=0, ddof=1) / math.sqrt(store.batches),
        info,
    )
