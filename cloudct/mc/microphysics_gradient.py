"""Residual-weighted gradients of the images with respect to every voxel's liquid water
content and droplet effective radius, by the path score function of forward photons.

For per-pixel weights r_d and a microphysical medium (LWC, r_eff) with Mie optics of one
table (one band), g_v = sum_d r_d dI_d / d m_v for m = LWC and m = r_eff at fixed LWC:

- d/d LWC = e(r_eff) d/d beta: LWC changes the cloud extinction beta = LWC e(r_eff) alone
  (:func:`cloudct.physics.microphysics.extinction_part_of_gradient`), so the score-function
  gradient in beta (:func:`cloudct.mc.gradient.score_function_gradient`'s, the GRADIENT pass)
  gives it whole;
- d/d r_eff = LWC e'(r_eff) d/d beta + the vertex terms of the score in r_eff at fixed beta:
  every scattering vertex in voxel v adds d log(beta_s f_p(theta)) / d r_eff (the albedo's
  and the two-row phase function's slopes, :func:`cloudct.physics.mixing.
  reff_log_derivative`) at the angle the path turns through there, weighted as the vertex
  term in beta is (path-recycling paper, Eqs. 44-46 and 76-77). A second pass of the same
  photons (same seeds) deposits them (:data:`cloudct.mc.forward.REFF_GRADIENT`).

With a phase truncation (the medium's ``phase_truncation``, :mod:`cloudct.optics`) the
kernels trace delta-scaled optics beta' = beta (1 - omega f), omega' and t', whose cut share
f moves with r_eff: the grid then carries d omega' / d r_eff and d t' / d r_eff, and the
extinction's part gains beta d log(1 - omega f) / d r_eff
(:func:`cloudct.physics.microphysics.delta_scaled_reff_slopes`).

With the score function (``estimator="score"``) both derivatives come from the same
photons, so each batch gives one sample of each, and the standard errors are those of the
batch means. Unbiased where the score function is: wherever paths can scatter (it misses
the in-scattering a first drop of water would bring where nothing scatters, as
:func:`~cloudct.mc.gradient.score_function_gradient` does).

Any other estimator of :data:`cloudct.mc.gradient.ESTIMATORS` gives d/d beta, hence d/d LWC
whole and the extinction's part of d/d r_eff, by the same chain rule; the albedo's and the
phase function's terms in r_eff are the score function's vertex terms alone (no other
estimator carries them), from their own pass of forward photons. The two parts are then
independent estimates, their standard errors added in quadrature.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from cloudct.mc.estimate import (
    Sampling,
    batch_means,
    check_residual,
    kernel_inputs,
    mean_and_std_error,
    per_cloud_extinction,
)
from cloudct.mc.executor import BatchExecutor
from cloudct.mc.forward import GRADIENT, REFF_GRADIENT
from cloudct.mc.gradient import gradient_estimate, gradient_estimator
from cloudct.mc.scene import Scene
from cloudct.medium import is_microphysical, is_optical
from cloudct.optics import GRID, peak_shares, to_optical
from cloudct.physics.microphysics import (
    albedo_reff_derivative,
    delta_scaled_reff_slopes,
    extinction_part_of_gradient,
    reff_interval,
    single_scattering_albedo,
)
from cloudct.physics.mie import mie_table as load_mie_table


def cloud_reff_slopes(
    lwc: np.ndarray, reff: np.ndarray, table: xr.Dataset,
    shares: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray | float]:
    """float64[2, x, y, z]: d omega / d r_eff and d t / d r_eff = 1 / (r_{k+1} - r_k) of the
    cloud in each voxel [1/micron] (0 where LWC = 0), the grid's ``cloud_reff_slopes``, and
    d log(beta' / beta) / d r_eff (0 without a truncation). With the cut shares f_k,
    f_{k+1} of a phase truncation (:func:`cloudct.optics.peak_shares`), the slopes of the
    delta-scaled omega' and t' the kernels trace."""
    cloudy = lwc > 0.0
    table_reff = np.asarray(table["reff"].values, dtype=np.float64)
    r = np.clip(reff, table_reff[0], table_reff[-1])
    k, t = reff_interval(r, table)
    slopes = [albedo_reff_derivative(r, table), 1.0 / (table_reff[k + 1] - table_reff[k])]
    d_log_scale = 0.0
    if shares is not None:
        *slopes, d_log_scale = delta_scaled_reff_slopes(
            single_scattering_albedo(r, table), t, *slopes, *shares)
        d_log_scale = np.where(cloudy, d_log_scale, 0.0)
    return np.ascontiguousarray(np.where(cloudy, np.stack(slopes), 0.0)), d_log_scale


def microphysics_gradient(
    medium: xr.Dataset,
    scene: Scene,
    residual: np.ndarray,
    *,
    photons: int,
    mie_table: xr.Dataset | None = None,
    estimator: str = "score",
    pixel_sampling: str = "uniform",
    seed: int = 0,
    batches: int = 32,
    rr_depth: int = 100,
    rr_survival: float = 0.95,
    aim_fraction: float | None = None,
    progress: bool | None = None,
    backend: str = "cpu",
    executor: BatchExecutor | None = None,
) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict]:
    """sum_d residual_d dI_d / d LWC and / d r_eff per voxel by the path score function of
    ``photons`` forward photons (module documentation).

    Args:
        medium: a microphysical medium (``lwc`` [g m-3], ``reff`` [micron]); its optics are
            the Mie optics of ``mie_table`` (None: the default table of the medium's
            ``wavelength`` attribute, else 0.672 micron), their peak cut where it has a
            ``phase_truncation``.
        scene, residual: the cameras and sun, and the per-pixel weights (view, row, col).
        photons: forward photons in all; seed, batches, rr_depth, rr_survival,
            aim_fraction, progress, backend and executor as for
            :func:`cloudct.mc.gradient.score_function_gradient`.
        estimator: the estimator of d/d beta (:func:`cloudct.mc.gradient.gradient_estimate`,
            with ``photons`` paths and ``pixel_sampling``); the r_eff vertex terms are the
            score function's, from ``photons`` forward photons more unless it is
            ``"score"`` (module documentation).

    Returns:
        ``(mean, std_error, info)``: ``mean`` and ``std_error`` map ``"lwc"`` [per g m-3]
        and ``"reff"`` [per micron] to arrays over (x, y, z); ``info`` the photons and the
        wall time of the two passes.

    Raises:
        ValueError: a medium that is not microphysical.
    """
    if is_optical(medium) or not is_microphysical(medium):
        raise ValueError("gradients in LWC and r_eff need a microphysical medium (lwc, reff) "
                         "without an optical cloud description")
    if mie_table is None:
        mie_table = load_mie_table(wavelength=float(medium.attrs.get("wavelength", 0.672)),
                                   veff=float(medium["veff"].max()) if "veff" in medium
                                   else 0.1)
    optical = to_optical(medium, mie_table, optics="mie")
    lwc = medium["lwc"].transpose(*GRID).values.astype(np.float64)
    reff = medium["reff"].transpose(*GRID).values.astype(np.float64)
    sampling = Sampling(batches, seed, rr_depth, rr_survival, backend)
    per_batch = sampling.per_batch(photons)
    residual = check_residual(residual, scene)
    gradient_estimator(estimator)  # a known name, before any work
    k = kernel_inputs(optical, scene, aim_fraction)
    run = dict(per_batch=per_batch, sampling=sampling, progress=progress, executor=executor)
    # d/d LWC = e(r) d/d beta; the extinction's part of d/d r_eff: (LWC e'(r) + beta d log(1 -
    # omega f) / d r) d/d beta
    lwc_per_beta, reff_per_beta = extinction_part_of_gradient(np.ones_like(lwc), lwc, reff,
                                                              mie_table)
    slopes, d_log_scale = cloud_reff_slopes(lwc, reff, mie_table, peak_shares(optical))
    beta = optical["cloud_extinction"].transpose(*GRID).values
    reff_per_beta = reff_per_beta + beta * d_log_scale
    if estimator == "score":
        in_beta, first = batch_means("forward", k, (GRADIENT, residual), desc="gradient", **run)
        in_beta = per_cloud_extinction(k, in_beta)  # d/d beta' -> d/d beta
    k_reff = k._replace(grid=k.grid._replace(cloud_reff_slopes=slopes))
    vertex, second = batch_means("forward", k_reff, (REFF_GRADIENT, residual),
                                 desc="gradient in r_eff", **run)
    mean, std_error = {}, {}
    if estimator == "score":  # the same photons: per-batch samples of both
        for name, per_batch_values in (("lwc", lwc_per_beta * in_beta),
                                       ("reff", reff_per_beta * in_beta + vertex)):
            mean[name], std_error[name] = mean_and_std_error(per_batch_values)
    else:
        in_beta, in_beta_error, first = gradient_estimate(
            optical, scene, residual, estimator=estimator, photons=photons, seed=seed,
            batches=batches, pixel_sampling=pixel_sampling, progress=progress,
            backend=backend, executor=executor)
        vertex, vertex_error = mean_and_std_error(vertex)
        mean["lwc"], std_error["lwc"] = lwc_per_beta * in_beta, lwc_per_beta * in_beta_error
        mean["reff"] = reff_per_beta * in_beta + vertex
        std_error["reff"] = np.hypot(reff_per_beta * in_beta_error, vertex_error)
    traced = per_batch * batches  # the forward photons of the vertex terms' pass
    info = {"photons": traced if estimator == "score" else first["photons"] + traced,
            "estimator": estimator, "aim_fraction": k.cams.aim_fraction,
            "wall_time": first["wall_time"] + second["wall_time"],
            "events": first["events"] + second["events"], "backend": first["backend"]}
    return mean, std_error, info
