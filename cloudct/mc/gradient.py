"""Residual-weighted gradients of the images with respect to every voxel's cloud extinction.

For per-pixel weights r_d (in a retrieval, r_d = w_d (I_d - I_d^measured), seed paper
Eq. 48) these functions estimate g_v = sum_d r_d dI_d / d beta_v without forming the
Jacobian. The cloud albedo and phase function stay fixed, so the cloud's scattering
coefficient changes with its extinction; air is not differentiated.

- :func:`score_function_gradient`: forward paths with local estimation and the path score
  function of Eqs. (44)-(49) (see :func:`cloudct.mc.forward.trace_photon`). It is unbiased
  wherever paths can scatter; where the total extinction is zero no vertex can land, so it
  misses the in-scattering a small increase of the cloud there would create. It is the
  one estimator that also differentiates a non-exponential transmittance, the power law
  (the score of T_pdf and T, :mod:`cloudct.physics.transmittance`; the mode field fixed).
- DRT on the backward estimator (:mod:`cloudct.mc.drt`), unbiased everywhere.
- Sample matching on the backward estimator (:mod:`cloudct.mc.sample_matching`), unbiased
  everywhere, with the scattering and attenuation terms evaluated at shared probe points.
- :func:`backward_score_gradient`: the path score function of backward paths (Eq. 49 with
  the path read from the camera), unbiased where the score function is.
- :func:`combined_gradient`: the path score function of the combined estimator's paths
  (:mod:`cloudct.mc.combined`): forward photons and backward pixel samples, each path's
  score weighted by its share, so that a peaked (Mie) phase function's fireflies leave
  the gradient as they leave the images.

All return the mean over independent batches and its standard error per voxel.
:data:`ESTIMATORS` holds one record per estimator (:class:`GradientEstimator`: its name,
what it traces and what it supports); :func:`gradient_estimate` runs one by name, as the
retrieval, the command line and the diagnostics do.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import xarray as xr

from cloudct.mc.camera_gradient import DRT, SAMPLE_MATCHING, SCORE, TITLES
from cloudct.mc.cameras import PROJECTIONS
from cloudct.mc.combined import samples_per_pixel
from cloudct.mc.estimate import (
    KernelInputs,
    Sampling,
    batch_means,
    check_residual,
    combined_inputs,
    kernel_inputs,
    mean_and_std_error,
    per_cloud_extinction,
)
from cloudct.mc.executor import BatchExecutor
from cloudct.mc.forward import GRADIENT
from cloudct.mc.pixel_sampling import PIXEL_SAMPLINGS, pixel_table
from cloudct.mc.scene import Scene
from cloudct.mc.sun import check_cloud_share
from cloudct.mc.traversal import require_exponential, require_smooth_flight_density
from cloudct.physics.transmittance import FAMILIES

#: Sample matching's probes per segment by default (measured: docs/validation.md).
SAMPLE_MATCHING_PROBES = 1


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
    aim_fraction: float | None = None,
    progress: bool | None = None,
    backend: str = "cpu",
    executor: BatchExecutor | None = None,
    entry_cloud_share: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """sum_d residual_d dI_d / d beta_cloud per voxel by the path score function.

    ``aim_fraction``: the forward paths' detector directional importance sampling, as for
    :func:`cloudct.mc.render.render` (0: off); the score terms are the same, the weights
    f / q make the estimate unbiased (:mod:`cloudct.mc.detector_sampling`).

    ``entry_cloud_share``: the share m in [0, 1) of photons entering where the clouds are,
    as for :func:`cloudct.mc.render.render` (0: uniform entry). The entry density is fixed
    for the whole estimate (it is built from the medium before any path is traced), so
    the score terms are the same and only each path's weight changes.

    ``backend``: ``"cpu"``, ``"cuda"`` or ``"auto"`` (:mod:`cloudct.mc.backend`).
    ``executor``: traces the batches elsewhere, e.g. a
    :class:`cloudct.distributed.DaskExecutor` on Dask workers (bitwise the same result,
    :mod:`cloudct.mc.executor`); None: this process.

    Returns ``(mean, std_error, info)`` with arrays over (x, y, z) and ``info`` holding the
    photon count, path vertices and wall time.
    """
    sampling = Sampling(batches, seed, rr_depth, rr_survival, backend)
    per_batch = sampling.per_batch(photons)
    residual = check_residual(residual, scene)
    k = kernel_inputs(medium, scene, aim_fraction, entry_cloud_share=entry_cloud_share)
    require_smooth_flight_density(k.grid, "score-function gradients")
    gradients, run = batch_means("forward", k, (GRADIENT, residual), per_batch=per_batch,
                                 sampling=sampling, progress=progress, executor=executor,
                                 desc="gradient")
    info = {"photons": per_batch * batches, **run, "aim_fraction": k.cams.aim_fraction,
            "entry_cloud_share": k.sun.cloud_share}
    return (*mean_and_std_error(per_cloud_extinction(k, gradients)), info)


def combined_gradient(
    medium: xr.Dataset,
    scene: Scene,
    residual: np.ndarray,
    *,
    photons: int,
    pixel_samples: int | None = None,
    seed: int = 0,
    batches: int = 32,
    rr_depth: int = 100,
    rr_survival: float = 0.95,
    aim_fraction: float | None = None,
    progress: bool | None = None,
    backend: str = "cpu",
    executor: BatchExecutor | None = None,
    entry_cloud_share: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """sum_d residual_d dI_d / d beta_cloud per voxel by the path score function of the
    combined estimator's paths (:mod:`cloudct.mc.combined`).

    dI/dbeta = integral of df/dbeta over the paths, and the combined estimator's weights
    are a partition of unity of each path, so the score-function gradient of ``photons``
    forward photons, each local estimate's score weighted by w_f
    (:func:`score_function_gradient`), plus that of ``pixel_samples`` backward samples of
    every pixel with a non-zero residual, each next-event estimate's score weighted by w_b
    (:func:`cloudct.mc.backward.score_pixel_sample`), is unbiased; the weights are taken at
    the current medium and not differentiated. None: :data:`~cloudct.mc.combined.
    BACKWARD_PATHS_PER_PHOTON` backward paths per photon, spread over those pixels. Batch b
    of the result is the sum of the two estimators' batch b.

    Exponential transmittance only (the backward paths' score of the power law is not
    written). Other parameters as for :func:`score_function_gradient`; ``info`` adds
    ``pixel_samples``, ``mis_ratio``, the backward paths' ``backward_events`` and
    ``backward_share``, their part of the gradient's sum of |g| over the voxels.
    """
    sampling = Sampling(batches, seed, rr_depth, rr_survival, backend)
    per_batch = sampling.per_batch(photons)
    residual = check_residual(residual, scene)
    k = kernel_inputs(medium, scene, aim_fraction, entry_cloud_share=entry_cloud_share)
    require_exponential(k.grid, "combined gradients",
                        "use the path score function (estimator 'score')")
    require_smooth_flight_density(k.grid, "combined gradients")
    if pixel_samples is None:
        pixel_samples = samples_per_pixel(per_batch * batches, np.count_nonzero(residual))
    k, per_pixel = combined_inputs(k, sampling, per_batch, pixel_samples)
    run_of = dict(sampling=sampling, progress=progress, executor=executor)
    forward, run = batch_means("forward", k, (GRADIENT, residual), per_batch=per_batch,
                               desc="combined gradient, forward", **run_of)
    backward, run_backward = backward_score_batches(k, residual, per_pixel, **run_of)
    share = float(np.abs(backward.mean(axis=0)).sum())
    share /= max(share + float(np.abs(forward.mean(axis=0)).sum()), np.finfo(float).tiny)
    info = {"photons": per_batch * batches, "pixel_samples": per_pixel * batches,
            "mis_ratio": k.cams.mis_ratio, "backward_share": share, **run_backward, **run,
            "events": run["events"] + run_backward["events"],
            "backward_events": run_backward["events"],
            "wall_time": run["wall_time"] + run_backward["wall_time"],
            "aim_fraction": k.cams.aim_fraction, "entry_cloud_share": k.sun.cloud_share}
    return (*mean_and_std_error(per_cloud_extinction(k, forward + backward)), info)


def backward_score_batches(
    k: KernelInputs, residual: np.ndarray, per_pixel: int, **run_of
) -> tuple[np.ndarray, dict]:
    """The combined gradient's backward half, per batch: the backward score function of
    ``per_pixel`` samples in each batch of every pixel with a non-zero ``residual``, each
    next-event estimate's score weighted by w_b (``k.cams.mis_ratio`` > 0;
    :func:`~cloudct.mc.estimate.combined_inputs`); in the kernels' extinction (apply
    :func:`~cloudct.mc.estimate.per_cloud_extinction`). ``run_of`` as for
    :func:`~cloudct.mc.estimate.batch_means`."""
    return batch_means(
        "camera-gradient", k, (SCORE, 1, False, False, residual, pixel_table(residual, "uniform")),
        per_batch=per_pixel, desc="combined gradient, backward", **run_of,
    )


def _camera_gradient(
    estimator: int, medium: xr.Dataset, scene: Scene, residual: np.ndarray, *,
    samples_per_pixel: int, seed: int, batches: int, rr_depth: int, rr_survival: float,
    progress: bool | None, backend: str, pixel_sampling: str, probes: int = 1,
    quadratic: bool = False, mis: bool = False, executor: BatchExecutor | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """The camera-side estimators' common host side (see :func:`drt_gradient`)."""
    sampling = Sampling(batches, seed, rr_depth, rr_survival, backend)
    sampling.per_batch(samples_per_pixel)  # a positive count
    residual = check_residual(residual, scene)
    k = kernel_inputs(medium, scene, aim_fraction=0.0)  # camera paths aim at no camera
    if estimator != DRT:
        require_exponential(k.grid, f"{TITLES[estimator]} gradients",
                            "use DRT (estimator 'drt') or the path score function")
    require_smooth_flight_density(k.grid, f"{TITLES[estimator]} gradients")
    pixels = int(np.count_nonzero(residual))
    table = pixel_table(residual, pixel_sampling)
    # per batch: samples of each pixel (uniform), or as many samples in all as
    # samples_per_pixel x pixels (table), not rounded up to whole samples of each pixel in
    # each batch (that rounding would trace pixels x batches samples at the least)
    per_batch = sampling.per_batch(int(samples_per_pixel) * (pixels if table.pixel.size else 1))
    args = (estimator, int(probes), bool(quadratic), bool(mis), residual, table)
    gradients, run = batch_means(
        "camera-gradient", k, args, per_batch=per_batch, sampling=sampling, progress=progress,
        executor=executor, desc=TITLES[estimator],
    )
    samples = per_batch * batches * (1 if table.pixel.size else pixels)
    info = {"photons": samples, **run, "pixel_sampling": pixel_sampling}
    return (*mean_and_std_error(per_cloud_extinction(k, gradients)), info)


def drt_gradient(
    medium: xr.Dataset,
    scene: Scene,
    residual: np.ndarray,
    *,
    samples_per_pixel: int,
    seed: int = 0,
    batches: int = 32,
    rr_depth: int = 100,
    rr_survival: float = 0.95,
    pixel_sampling: str = "uniform",
    progress: bool | None = False,
    backend: str = "cpu",
    executor: BatchExecutor | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """sum_d residual_d dI_d / d(cloud extinction) per voxel, by differential ratio
    tracking (:mod:`cloudct.mc.drt`).

    Parameters
    ----------
    medium
        A medium Dataset (optical, or microphysical: converted with the default optics).
    scene
        Cameras, sun, boundary conditions and ground.
    residual
        Per-pixel weights, shape (view, row, col), e.g. w_d (I_d - I_d^measured).
    samples_per_pixel
        Backward samples per pixel with a non-zero residual, rounded up to a multiple of
        ``batches``.
    pixel_sampling
        ``"uniform"``: that many samples of every such pixel; ``"residual"``: as many
        samples in all, each of a pixel drawn with probability |r_d| / sum |r|
        (:mod:`cloudct.mc.pixel_sampling`).
    seed, batches, rr_depth, rr_survival, progress, backend
        As for :func:`cloudct.mc.render.render`.
    executor
        Traces the batches elsewhere, e.g. a :class:`cloudct.distributed.DaskExecutor` on
        Dask workers (bitwise the same result, :mod:`cloudct.mc.executor`); None: this
        process.

    Returns
    -------
    ``(mean, std_error, info)``: float64[nx, ny, nz] each, in km x (residual units x
    radiance units), the mean over the batches and its standard error (std of the batch
    means over sqrt(batches)); ``info`` holds the samples traced ("photons"), the path
    vertices and the wall time.
    """
    return _camera_gradient(
        DRT, medium, scene, residual, samples_per_pixel=samples_per_pixel, seed=seed,
        batches=batches, rr_depth=rr_depth, rr_survival=rr_survival, progress=progress,
        backend=backend, pixel_sampling=pixel_sampling, executor=executor,
    )


def backward_score_gradient(
    medium: xr.Dataset,
    scene: Scene,
    residual: np.ndarray,
    *,
    samples_per_pixel: int,
    seed: int = 0,
    batches: int = 32,
    rr_depth: int = 100,
    rr_survival: float = 0.95,
    pixel_sampling: str = "uniform",
    progress: bool | None = False,
    backend: str = "cpu",
    executor: BatchExecutor | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """sum_d residual_d dI_d / d(cloud extinction) per voxel by the path score function of
    backward paths (:func:`cloudct.mc.backward.score_pixel_sample`): the score of Eq. (49)
    with the path read from the camera, each next-event estimate towards the sun holding
    its path's flights and turns. Like the forward score function it misses the
    in-scattering where the total extinction is zero; exponential transmittance only.
    Parameters and the result as for :func:`drt_gradient`."""
    return _camera_gradient(
        SCORE, medium, scene, residual, samples_per_pixel=samples_per_pixel, seed=seed,
        batches=batches, rr_depth=rr_depth, rr_survival=rr_survival, progress=progress,
        backend=backend, pixel_sampling=pixel_sampling, executor=executor,
    )


def sample_matching_gradient(
    medium: xr.Dataset,
    scene: Scene,
    residual: np.ndarray,
    *,
    samples_per_pixel: int,
    probes: int = SAMPLE_MATCHING_PROBES,
    quadratic: bool = False,
    mis: bool = True,
    seed: int = 0,
    batches: int = 32,
    rr_depth: int = 100,
    rr_survival: float = 0.95,
    pixel_sampling: str = "uniform",
    progress: bool | None = False,
    backend: str = "cpu",
    executor: BatchExecutor | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """sum_d residual_d dI_d / d(cloud extinction) per voxel, by sample matching
    (:mod:`cloudct.mc.sample_matching`): ``probes`` stratified probes per path segment
    share the sun (direct) terms; the indirect in-scattering is traced from one probe of
    one segment per path chosen by reservoir sampling (``quadratic=False``) or of every
    segment (``quadratic=True``); with ``mis`` the free-flight vertices take a share of it
    where the medium is dense (the primal path's own continuation, as in DRT), without it
    the probes take it all (the paper's dual suffix paths). Other parameters and the result
    as for :func:`drt_gradient`."""
    if int(probes) < 1:
        raise ValueError(f"probes must be a positive count, got {probes}")
    return _camera_gradient(
        SAMPLE_MATCHING, medium, scene, residual, samples_per_pixel=samples_per_pixel,
        seed=seed, batches=batches, rr_depth=rr_depth, rr_survival=rr_survival,
        progress=progress, backend=backend, pixel_sampling=pixel_sampling, probes=probes,
        quadratic=quadratic, mis=mis, executor=executor,
    )


@dataclass(frozen=True)
class GradientEstimator:
    """What the retrieval, the command line and the diagnostics need to know of a gradient
    estimator: its name and title, whether it traces camera paths (``photons`` are then
    spread over the pixels with a non-zero residual, uniformly or in proportion to
    |residual|) or forward photons (each serves every pixel), whether path recycling and
    L-BFGS-B windows can replay its stored paths, the transmittance families it
    differentiates, and ``run(medium, scene, residual, *, photons, seed, batches,
    pixel_sampling, progress, backend, executor, entry_cloud_share)``."""

    name: str
    title: str
    camera_side: bool
    replayable: bool
    transmittances: tuple[str, ...]
    run: Callable[..., tuple[np.ndarray, np.ndarray, dict]]
    #: the back ends (:mod:`cloudct.mc.backend`) and camera projections it runs on
    backends: tuple[str, ...] = ("cpu", "cuda")
    projections: tuple[str, ...] = PROJECTIONS
    #: what path recycling does with its paths, where it is replayable
    recycled: str = "recorded and replayed"


def camera_side_names() -> str:
    """The camera-side estimators of :data:`ESTIMATORS`, for messages."""
    return ", ".join(e.name for e in ESTIMATORS.values() if e.camera_side)


def _uniform_pixels_only(pixel_sampling: str, why: str) -> None:
    if pixel_sampling != "uniform":
        raise ValueError(f"pixel_sampling applies to the camera-side estimators "
                         f"({camera_side_names()}): {why}")


def _score_run(medium, scene, residual, *, photons, seed, batches, pixel_sampling, progress,
               backend, executor, entry_cloud_share):
    _uniform_pixels_only(pixel_sampling, "one forward photon serves every pixel")
    return score_function_gradient(
        medium, scene, residual, photons=photons, seed=seed, batches=batches,
        progress=progress, backend=backend, executor=executor,
        entry_cloud_share=entry_cloud_share,
    )


def _combined_run(medium, scene, residual, *, photons, seed, batches, pixel_sampling, progress,
                  backend, executor, entry_cloud_share):
    _uniform_pixels_only(pixel_sampling, "the combined estimator's weights take the same "
                         "number of camera paths for every pixel")
    return combined_gradient(
        medium, scene, residual, photons=photons, seed=seed, batches=batches,
        progress=progress, backend=backend, executor=executor,
        entry_cloud_share=entry_cloud_share,
    )


def _camera_side_run(estimator: Callable) -> Callable:
    """``run`` of a camera-side estimator: ``photons`` paths in all over the residual's
    pixels."""

    def run(medium, scene, residual, *, photons, seed, batches, pixel_sampling, progress,
            backend, executor, entry_cloud_share):
        residual = check_residual(residual, scene)
        pixels = max(int(np.count_nonzero(residual)), 1)
        return estimator(
            medium, scene, residual, samples_per_pixel=max(math.ceil(int(photons) / pixels), 1),
            seed=seed, batches=batches, pixel_sampling=pixel_sampling, progress=progress,
            backend=backend, executor=executor,
        )

    return run


#: The gradient estimators by name.
ESTIMATORS: dict[str, GradientEstimator] = {
    e.name: e for e in (
        GradientEstimator("score", "path score function (forward photons)", camera_side=False,
                          replayable=True, transmittances=("exponential", "gamma"),
                          run=_score_run),
        GradientEstimator("drt", "differential ratio tracking (camera paths)",
                          camera_side=True, replayable=False,
                          transmittances=("exponential", "gamma"),
                          run=_camera_side_run(drt_gradient)),
        GradientEstimator("sm", "sample matching (camera paths)", camera_side=True,
                          replayable=False, transmittances=("exponential",),
                          run=_camera_side_run(sample_matching_gradient)),
        GradientEstimator("backward-score", "path score function (camera paths)",
                          camera_side=True, replayable=False, transmittances=("exponential",),
                          run=_camera_side_run(backward_score_gradient)),
        GradientEstimator("combined", "path score function (forward photons and camera "
                          "paths, MIS-weighted)", camera_side=False, replayable=True,
                          transmittances=("exponential",), run=_combined_run,
                          recycled="forward photons replayed, camera paths fresh"),
    )
}


def support_table() -> str:
    """What each gradient estimator of :data:`ESTIMATORS` supports, as the Markdown table of
    ``docs/architecture.md`` (a test keeps the page equal to it); where a cell says
    "refused", the call stops before any work with the reason and the alternative."""

    def family(record: GradientEstimator, name: str) -> str:
        return "yes" if name in record.transmittances else "refused"

    header = ["estimator", "traces", "back ends", "executors", "cameras", "pixels drawn",
              *(f"transmittance: {f}" for f in FAMILIES), "path recycling"]
    lines = ["| " + " | ".join(header) + " |", "|" + " --- |" * len(header)]
    for r in ESTIMATORS.values():
        cells = [
            f"`{r.name}`: {r.title}",
            "camera paths" if r.camera_side else "forward photons",
            ", ".join(r.backends),
            "this process, Dask (any BatchExecutor)",
            ", ".join(r.projections),
            ", ".join(PIXEL_SAMPLINGS) if r.camera_side else "(each photon serves every pixel)",
            *(family(r, f) for f in FAMILIES),
            r.recycled if r.replayable else "refused (fresh paths each iteration)",
        ]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def gradient_estimator(name: str) -> GradientEstimator:
    """The record of the estimator ``name``, or a ValueError that lists the names."""
    if name not in ESTIMATORS:
        raise ValueError(f"estimator must be one of {tuple(ESTIMATORS)}, got {name!r}")
    return ESTIMATORS[name]


def gradient_estimate(
    medium: xr.Dataset,
    scene: Scene,
    residual: np.ndarray,
    *,
    estimator: str = "score",
    photons: int,
    seed: int = 0,
    batches: int = 32,
    pixel_sampling: str = "uniform",
    progress: bool | None = False,
    backend: str = "cpu",
    executor: BatchExecutor | None = None,
    entry_cloud_share: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """sum_d residual_d dI_d / d beta_cloud per voxel by the estimator named ``estimator``
    (one of :data:`ESTIMATORS`), with ``photons`` paths in all (the count the retrieval's
    ``--photons`` sets, the same name from the command line to here).

    ``"score"`` traces ``photons`` forward photons (each serves every pixel), a share
    ``entry_cloud_share`` of them entering where the clouds are
    (:func:`score_function_gradient`; the camera-side estimators ignore it). ``"drt"`` and
    ``"sm"`` trace camera paths: ``ceil(photons / n)`` samples per pixel for the n pixels
    whose residual is not zero, drawn per pixel (``pixel_sampling="uniform"``) or, as many
    in all, in proportion to |residual| (``"residual"``; :mod:`cloudct.mc.pixel_sampling`).
    Uniform pixel sampling rounds each pixel's samples up to a multiple of ``batches``, so
    with fewer than ``batches`` samples per pixel it traces up to ``batches`` times more
    paths than asked (``info["photons"]`` says how many); residual-drawn pixels round the
    total only. An ``executor`` traces the batches of any of them elsewhere (bitwise the
    same result).

    Returns ``(mean, std_error, info)``; ``info`` holds the estimator, the paths traced
    and the wall time in seconds.
    """
    record = gradient_estimator(estimator)
    check_cloud_share(entry_cloud_share)
    mean, std_error, info = record.run(
        medium, scene, residual, photons=photons, seed=seed, batches=batches,
        pixel_sampling=pixel_sampling, progress=progress, backend=backend,
        executor=executor, entry_cloud_share=entry_cloud_share,
    )
    info["estimator"] = estimator
    return mean, std_error, info
