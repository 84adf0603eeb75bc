"""The retrieval's loss and its gradient with respect to every voxel's cloud extinction.

Seed paper Eq. (41), with pixel weights w_d (e.g. inverse noise variances; 0 masks a pixel):

    L = 1/2 sum_d w_d (I_d - I_d^measured)^2,
    dL / d beta_v = sum_d w_d (I_d - I_d^measured) dI_d / d beta_v        (Eq. 43/48)

computed without forming the Jacobian: the residual-weighted derivative is one Monte Carlo
pass (:mod:`cloudct.mc.gradient`). The images I_d in the residual come from paths
independent of the gradient's paths (a different seed), so that the product of two
estimates is an unbiased estimate of the product of their means (the bias Gkioulekas et al.
and the DRT paper point out when the same paths serve both).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import xarray as xr

from cloudct.distributed.executor import executor
from cloudct.mc.gradient import gradient_estimate
from cloudct.mc.render import render
from cloudct.mc.scene import Scene


@dataclass
class LossGradient:
    """A loss evaluation: the loss, its gradient over (x, y, z) with standard errors, the
    images the residual was computed from, and the gradient estimator's info (estimator,
    paths, wall time)."""

    loss: float
    gradient: np.ndarray
    gradient_std_error: np.ndarray
    images: xr.Dataset
    residual: np.ndarray
    gradient_info: dict

    @property
    def loss_std_error(self) -> float:
        """The loss's Monte Carlo standard error (:func:`loss_std_error`)."""
        return loss_std_error(self.residual, self.images["radiance_std_error"].values)


def pixel_weights(
    measurements: xr.Dataset, weights: np.ndarray | None = None, mask: np.ndarray | None = None
) -> np.ndarray:
    """Per-pixel loss weights: ``weights`` (default 1) times ``mask`` (default all pixels),
    with NaN measured pixels masked out (a warning says how many)."""
    measured = measurements["radiance"].values
    w = np.ones(measured.shape) if weights is None else np.asarray(weights, dtype=float).copy()
    if w.shape != measured.shape:
        raise ValueError(f"weights have shape {w.shape}, the measurements {measured.shape}")
    if not np.all(np.isfinite(w)) or np.any(w < 0):
        raise ValueError("pixel weights must be finite and non-negative")
    if mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != measured.shape:
            raise ValueError(f"mask has shape {mask.shape}, the measurements {measured.shape}")
        w = np.where(mask, w, 0.0)
    bad = ~np.isfinite(measured)
    if bad.any():
        warnings.warn(
            f"{int(bad.sum())} measured pixels are NaN or infinite; they are masked out",
            stacklevel=2,
        )
        w = np.where(bad, 0.0, w)
    return w


def image_loss(
    radiance: np.ndarray, measured: np.ndarray, weights: np.ndarray | None = None
) -> tuple[float, np.ndarray]:
    """Eq. (41) for images against measured ones: ``(L, residual)`` with the residual
    r_d = w_d (I_d - I_d^measured) of Eq. (48) (weights default 1). NaN measured pixels
    count as 0: give them weight 0 (:func:`pixel_weights` does)."""
    difference = radiance - np.nan_to_num(measured)
    residual = difference if weights is None else weights * difference
    return 0.5 * float(np.sum(residual * difference)), residual


def loss_std_error(residual: np.ndarray, std_error: np.ndarray) -> float:
    """The Monte Carlo standard error of Eq. (41) computed from images with per-pixel
    standard errors s_d, to first order (the delta method): dL/dI_d = r_d, the residual,
    and the pixels' batch means are independent across pixels to that order, so

        sigma_L^2 = sum_d r_d^2 s_d^2.

    (The loss of noisy images is also biased upwards by 1/2 sum_d w_d s_d^2, about the
    same at every iteration of a run: it shifts the loss, not its slope.)"""
    return float(np.sqrt(np.sum((residual * std_error) ** 2)))


def cross_loss(
    image_a: np.ndarray, image_b: np.ndarray, measured: np.ndarray, weights: np.ndarray
) -> float:
    """1/2 sum_d w_d (I_A,d - m_d) (I_B,d - m_d): Eq. (41) from two independent image
    estimates A and B, unbiased where the squared residual of one adds its variance. NaN
    measured pixels count as 0 (give them weight 0)."""
    measured = np.nan_to_num(measured)
    return 0.5 * float(np.sum(weights * (image_a - measured) * (image_b - measured)))


#: Batches of every estimate of a retrieval's loss and gradient.
BATCHES = 32


def loss_and_gradient(
    medium: xr.Dataset,
    measurements: xr.Dataset,
    *,
    photons: int,
    gradient_photons: int | None = None,
    seed: int = 0,
    weights: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    estimator: str = "score",
    pixel_sampling: str = "uniform",
    batches: int = BATCHES,
    progress: bool | None = False,
    backend: str = "cpu",
    client=None,
    method: str = "forward",
) -> LossGradient:
    """The loss of ``medium`` against ``measurements`` (an images Dataset carrying its
    scene, as written by :func:`cloudct.mc.render.render`) and its gradient.

    ``photons`` render the images of the residual (seed ``2 seed``) by the estimator
    ``method`` (:func:`cloudct.mc.render.render`: forward or combined); ``gradient_photons``
    (default: ``photons``) paths estimate the gradient on independent paths (seed ``2 seed
    + 1``) by ``estimator`` with ``pixel_sampling``
    (:func:`cloudct.mc.gradient.gradient_estimate`). ``backend`` as for
    :func:`cloudct.mc.render.render`; ``client`` (a Dask client, scheduler address or
    :class:`cloudct.distributed.DaskExecutor`) traces both on its workers, with the medium
    scattered once for both.
    """
    spread = None if client is None else executor(client)
    scene = Scene.from_dataset(measurements)
    w = pixel_weights(measurements, weights, mask)
    images = render(
        medium, scene, photons=photons, method=method, seed=2 * seed, batches=batches,
        progress=progress, backend=backend, executor=spread,
    )
    loss, residual = image_loss(images["radiance"].values, measurements["radiance"].values, w)
    mean, std_error, info = gradient_estimate(
        medium, scene, residual, estimator=estimator, photons=gradient_photons or photons,
        seed=2 * seed + 1, batches=batches, pixel_sampling=pixel_sampling, progress=progress,
        backend=backend, executor=spread,
    )
    return LossGradient(loss, mean, std_error, images, residual, info)
