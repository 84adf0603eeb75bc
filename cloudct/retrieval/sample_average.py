"""L-BFGS-B on the sample-average loss of fixed paths: the deterministic end of a retrieval.

Between two recordings, path recycling makes the Monte Carlo images a deterministic, smooth
function of the cloud extinction: the stored paths re-weighted by their correction factors
(seed paper Eqs. 50-53). Their replayed gradient is the exact derivative of that function
(tests/test_recycling.py checks it against central finite differences), so a quasi-Newton
method with a line search, which a fresh-photon gradient would defeat, can be run on it.

A window records two stores, A and B, independently under the current medium (the
reference) and minimises over the masked voxels

    L_AB(beta) = 1/2 sum_d w_d (I_A,d(beta) - m_d) (I_B,d(beta) - m_d),

    dL_AB/dbeta = 1/2 sum_d [w_d (I_B,d - m_d) dI_A,d/dbeta + w_d (I_A,d - m_d) dI_B,d/dbeta]

(Eq. 41 with the images of two independent stores; the gradient is two replays in GRADIENT
mode, each with the other store's residual). As the product of independent unbiased
estimates, L_AB estimates the noise-free loss without bias at every beta, unlike
1/2 sum_d w_d (I_A,d - m_d)^2, which adds the images' variance, itself a function of beta.
L_AB is not bounded below: far from the reference, where the correction factors of a few
paths dominate, the minimiser fits the paths' noise rather than the images. Each voxel is
therefore held in a trust region [(1 - rho) beta_ref, (1 + rho) beta_ref] and a window
takes a bounded number of evaluations; the next window records new paths under its result.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import xarray as xr
from scipy.optimize import minimize

from cloudct.mc.scene import Scene
from cloudct.recycling.replay import replay_gradient, replay_images
from cloudct.recycling.store import PathStore, record_paths
from cloudct.retrieval.loss import cross_loss, image_loss, pixel_weights


@dataclass
class Window:
    """One L-BFGS-B window: the extinction it ends at and what it saw on the way."""

    extinction: np.ndarray  # float[x, y, z], 0 outside the mask
    loss: float  # Eq. (41) of store A's images at the reference (comparable to a fresh loss)
    start: float  # L_AB at the reference
    end: float  # L_AB at the result
    evaluations: int
    message: str


class SampleAverageLoss:
    """L_AB and its gradient over the masked voxels of ``template``, from two stores of
    ``photons`` and ``photons_b`` paths recorded under ``template`` with seeds ``2 seed`` and
    ``2 seed + 1`` (see the module documentation), sharing ``memory_budget`` (bytes, None:
    :func:`~cloudct.recycling.store.record_paths`'s default) in proportion to their paths."""

    def __init__(
        self,
        template: xr.Dataset,
        measurements: xr.Dataset,
        mask: np.ndarray,
        *,
        photons: int,
        photons_b: int,
        seed: int,
        weights: np.ndarray | None = None,
        backend: str = "cpu",
        memory_budget: float | None = None,
    ) -> None:
        self.template = template.copy(deep=True)
        self.mask = np.asarray(mask, bool)
        self.weights = pixel_weights(measurements, weights)
        self.measured = np.nan_to_num(measurements["radiance"].values)
        self.backend = backend
        scene = Scene.from_dataset(measurements)
        self.stores: tuple[PathStore, PathStore] = tuple(
            record_paths(
                template, scene, photons=n, seed=2 * seed + i, variable=self.mask,
                memory_budget=None if memory_budget is None
                else memory_budget * n / (photons + photons_b),
            )
            for i, n in enumerate((photons, photons_b))
        )
        self.values: list[float] = []  # L_AB at every evaluation
        self.reference_loss = float("nan")  # Eq. (41) of store A's images, first evaluation

    def medium(self, x: np.ndarray) -> xr.Dataset:
        """The template with cloud extinction ``x`` in the masked voxels and 0 elsewhere."""
        beta = np.zeros(self.mask.shape)
        beta[self.mask] = x
        self.template["cloud_extinction"].values = beta
        return self.template

    def __call__(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        """(L_AB, dL_AB/dx) at extinction ``x`` of the masked voxels."""
        medium = self.medium(x)
        image_a, image_b = (
            replay_images(store, medium, backend=self.backend)[0].mean(axis=0)
            for store in self.stores
        )
        if not self.values:
            self.reference_loss = image_loss(image_a, self.measured, self.weights)[0]
        residual_a = self.weights * (image_a - self.measured)
        residual_b = self.weights * (image_b - self.measured)
        value = cross_loss(image_a, image_b, self.measured, self.weights)
        self.values.append(value)
        gradient = 0.5 * (
            replay_gradient(self.stores[0], medium, residual_b, backend=self.backend)[0]
            + replay_gradient(self.stores[1], medium, residual_a, backend=self.backend)[0]
        )
        return value, gradient[self.mask]


def lbfgsb_window(
    medium: xr.Dataset,
    measurements: xr.Dataset,
    mask: np.ndarray,
    *,
    photons: int,
    photons_b: int | None = None,
    seed: int = 0,
    trust_region: float = 0.3,
    evaluations: int = 30,
    backend: str = "cpu",
    memory_budget: float | None = None,
) -> Window:
    """One window: record stores A (``photons``) and B (``photons_b``, default ``photons``)
    under ``medium`` and run scipy's L-BFGS-B on L_AB for up to ``evaluations`` evaluations,
    each masked voxel bounded to ``(1 -+ trust_region)`` times its extinction in ``medium``
    (so a voxel at 0 stays 0: paths cannot scatter where the reference has no extinction).
    ``memory_budget`` bounds the two stores together (bytes; see :class:`SampleAverageLoss`).
    """
    if not 0.0 < trust_region <= 1.0:
        raise ValueError(f"trust_region must be in (0, 1], got {trust_region}")
    if evaluations < 1:
        raise ValueError(f"evaluations must be >= 1, got {evaluations}")
    mask = np.asarray(mask, bool)
    loss = SampleAverageLoss(
        medium, measurements, mask, photons=photons, photons_b=photons_b or photons,
        seed=seed, backend=backend, memory_budget=memory_budget,
    )
    x0 = medium["cloud_extinction"].values[mask].astype(float)
    scale = 0.0  # store A's loss at x0, set by the first evaluation (L-BFGS-B's, at x0)

    def relative(u: np.ndarray) -> tuple[float, np.ndarray]:
        """L_AB over extinctions relative to x0, in units of the loss at x0: L-BFGS-B's
        first step and its stopping rules then work on the scale of the problem."""
        nonlocal scale
        value, gradient = loss(u * x0)
        scale = scale or max(loss.reference_loss, np.finfo(float).tiny)
        return value / scale, gradient * x0 / scale

    result = minimize(  # the window's budget of evaluations is its stopping rule
        relative, np.ones_like(x0), jac=True, method="L-BFGS-B",
        bounds=[(1.0 - trust_region, 1.0 + trust_region)] * x0.size,
        options={"maxfun": evaluations, "maxiter": evaluations, "ftol": 0.0, "gtol": 0.0},
    )
    extinction = np.zeros(mask.shape)
    extinction[mask] = result.x * x0
    return Window(extinction, loss.reference_loss, loss.values[0], float(result.fun) * scale,
                  len(loss.values), str(result.message))
