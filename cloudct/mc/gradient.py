"""Residual-weighted gradients of the images with respect to every voxel's cloud extinction.

For per-pixel weights r_d (in a retrieval, r_d = w_d (I_d - I_d^measured), seed paper
Eq. 48) these functions estimate g_v = sum_d r_d dI_d / d beta_v without forming the
Jacobian. The cloud albedo and phase function stay fixed, so the cloud's scattering
coefficient changes with its extinction; air is not differentiated.

- :func:`score_function_gradient`: forward paths with local estimation and the path score
  function of Eqs. (44)-(49) (see :func:`cloudct.mc.forward.trace_photon`). It is unbiased
  wherever paths can scatter; where the total extinction is zero no vertex can land, so it
  misses the in-scattering a small increase of the cloud there would create.
- DRT on the backward estimator (:mod:`cloudct.mc.drt`), unbiased everywhere.

Both return the mean over independent batches and its standard error per voxel.
"""

from __future__ import annotations

import math

import numpy as np
import xarray as xr

from cloudct.mc.backend import forward_runner, resolve_backend
from cloudct.mc.forward import GRADIENT
from cloudct.mc.render import check_sampling, kernel_inputs, run_in_rounds
from cloudct.mc.scene import Scene


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


def score_function_gradient(
    medium: xr.Dataset,
    scene: Scene,
    residual: np.ndarray,
    *,
    photons: int,
    seed: int = 0,
    batches: int = 32,
    rr_depth: int = 100,
    rr_survival: float = 0.95,
    progress: bool | None = None,
    backend: str = "cpu",
    client=None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """sum_d residual_d dI_d / d beta_cloud per voxel by the path score function.

    ``backend``: ``"cpu"``, ``"cuda"`` or ``"auto"`` (:mod:`cloudct.mc.backend`).
    ``client``: a Dask client, address or executor to trace the batches on its workers
    (bitwise the same result, see :mod:`cloudct.distributed`); None: this process.

    Returns ``(mean, std_error, info)`` with arrays over (x, y, z) and ``info`` holding the
    photon count, path vertices and wall time.
    """
    check_sampling(photons, batches, rr_depth, rr_survival)
    residual = check_residual(residual, scene)
    k = kernel_inputs(medium, scene)
    per_batch = math.ceil(int(photons) / batches)
    if client is not None:
        from cloudct.distributed.core import gradient_batch_means

        batch_means, info = gradient_batch_means(
            client, k, residual, seed=seed, per_batch=per_batch, batches=batches,
            rr_depth=rr_depth, rr_survival=rr_survival, backend=backend, progress=progress,
        )
        return (
            batch_means.mean(axis=0),
            batch_means.std(axis=0, ddof=1) / math.sqrt(batches),
            info,
        )
    gradients = np.zeros((batches, *k.grid.extinction.shape[1:]))
    no_images = np.zeros((batches, 1, 1, 1))
    events = np.zeros(batches, dtype=np.int64)

    backend = resolve_backend(backend)
    run = forward_runner(
        backend, k, rr_depth, rr_survival, seed, per_batch, GRADIENT, no_images, residual,
        gradients, events,
    )
    wall = run_in_rounds(
        run, per_batch, batches, progress, unit="photon", desc="gradient",
        max_rounds=run.max_rounds,
    )
    batch_means = gradients / per_batch
    info = {"photons": per_batch * batches, "events": int(events.sum()), "wall_time": wall,
            "backend": backend}
    return (
        batch_means.mean(axis=0),
        batch_means.std(axis=0, ddof=1) / math.sqrt(batches),
        info,
    )
