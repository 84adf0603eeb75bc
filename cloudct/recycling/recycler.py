"""The recycler: what a retrieval loop calls every iteration (seed paper Alg. 2).

::

    recycler = Recycler(scene, photons=10**6, policy=AdaptiveESS(0.5, 50),
                        memory_budget=4 * 2**30, seed=0)
    for t in range(iterations):
        ev = recycler.evaluate(medium, residual=lambda images: w * (images.radiance.values
                                                                    - measured))
        medium = step(medium, ev.gradient)          # ev.images, ev.info["ess_fraction"], ...

Every call re-evaluates stored paths under the current medium, after resampling them (under
the current medium, which becomes the reference) when the policy says so. The images that
form the residual and the gradient come from two independent stores (independent random
streams), so that their product is an unbiased estimate of the product of their means
(see :mod:`cloudct.retrieval.loss`): the images store is replayed in RENDER mode, the
residual computed from those images, and the gradient store replayed in GRADIENT mode with
that residual. Keeping two stores costs twice the memory of one; rendering the residual
images fresh instead would cost about as much time as replaying them (both are dominated by
the local estimates), so both are stored and recycled. Each store has its own age and is
resampled on its own; every decision is logged in :attr:`Recycler.log` and through the
``logging`` module.

With ``image_method="combined"`` or ``gradient_estimator="combined"`` the images or the
gradient are the combined estimator's (:mod:`cloudct.mc.combined`; a Mie medium's full
forward peak): the stored forward paths are replayed with each local estimate weighted by
its share w_f under the current medium, and the other half, backward paths with their
next-event estimates weighted by w_b, is traced fresh under the current medium every
evaluation (:func:`~cloudct.mc.render.backward_images`,
:func:`~cloudct.mc.gradient.backward_score_batches`), with independent random streams per
evaluation. The two halves are independent, each unbiased for its share of every path
(w_f + w_b = 1 per path under the same medium), so their sum is unbiased; only the forward
half is recycled.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import xarray as xr

from cloudct.mc.backend import resolve_backend
from cloudct.mc.combined import samples_per_pixel
from cloudct.mc.estimate import (
    KernelInputs,
    Sampling,
    check_residual,
    combined_inputs,
    kernel_inputs,
    per_cloud_extinction,
)
from cloudct.mc.gradient import backward_score_batches
from cloudct.mc.render import backward_images, default_pixel_samples
from cloudct.mc.scene import Scene
from cloudct.medium import cell_edges
from cloudct.recycling.policy import AdaptiveESS, Policy
from cloudct.recycling.replay import (
    correction_log_weights,
    recycled_images,
    replay_gradient,
    replay_images,
    summary_ess,
    weight_summary,
)
from cloudct.recycling.store import PathStore, check_same_grid, record_paths

logger = logging.getLogger(__name__)

STORES = ("images", "gradient")
#: The recycler's images: forward paths replayed, or the combined estimator's
IMAGE_METHODS = ("forward", "combined")
#: The recycler's gradient: the path score function of replayed forward paths, or the
#: combined estimator's
GRADIENT_ESTIMATORS = ("score", "combined")


class Evaluation(NamedTuple):
    """One evaluation of the recycler under a medium."""

    images: xr.Dataset  # radiance and radiance_std_error over (view, row, col)
    residual: np.ndarray | None  # the pixel weights the gradient used (None: no gradient)
    gradient: np.ndarray | None  # sum_d residual_d dI_d / d beta_cloud over (x, y, z)
    gradient_std_error: np.ndarray | None
    info: dict  # iteration, resampled, reasons, ESS fractions, ages, times, memory


@dataclass
class _Slot:
    photons: int
    store: PathStore | None = None
    age: int = 0  # evaluations served by the current store
    generation: int = 0  # stores recorded so far


def store_seed(seed: int, generation: int, which: int) -> int:
    """Seed of the random streams of store ``which`` (0 images, 1 gradient) of a given
    generation: independent streams for every store the recycler ever records."""
    state = np.random.SeedSequence([int(seed), int(generation), int(which)]).generate_state(
        1, np.uint64
    )
    return int(state[0] >> np.uint64(1))


class Recycler:
    """Path recycling for a retrieval loop (see the module documentation).

    Parameters
    ----------
    scene
        Cameras, sun, boundaries and ground (fixed for the recycler's life).
    photons
        Paths in the images store (rounded up to a multiple of ``batches``).
    gradient_photons
        Paths in the gradient store (default: ``photons``).
    batches
        Independent batches for standard errors.
    policy
        :class:`~cloudct.recycling.policy.FixedPeriod` or
        :class:`~cloudct.recycling.policy.AdaptiveESS` (the default, 0.5 and 50).
    memory_budget
        Bytes for both stores together (None: no limit), shared in proportion to their
        photons; ``storage="auto"`` stores what fits (see
        :data:`~cloudct.recycling.store.AUTO_CONNECTIONS_BUDGET`).
    storage
        ``"auto"``, ``"connections"``, ``"crossings"`` or ``"lean"`` (see
        :mod:`cloudct.recycling.store`).
    variable
        bool[x, y, z]: the voxels whose extinction the evaluated media may change (default:
        all), e.g. a retrieval's mask; camera connections keep only their crossings.
    seed
        Seed of all the recycler's random streams.
    rr_depth, rr_survival
        Russian roulette, as for :func:`cloudct.mc.render.render`.
    sort
        Sort each store's paths by length (path sorting); default: on the GPU only (on the
        CPU sorting does not speed the replay up, and it costs a copy of the store).
    backend
        ``"cpu"``, ``"cuda"`` or ``"auto"``: where the stored paths are re-evaluated (and
        their correction factors computed) as for :func:`cloudct.mc.render.render`; resolved
        once, here (``"auto"`` warns once where it falls back to the CPU). With ``"cuda"``
        each store is copied to the GPU on its first replay and kept there while it is in
        use. Paths are recorded on the CPU.
    image_method, gradient_estimator
        ``"combined"``: the images, or the gradient, of the combined estimator (module
        documentation), with :data:`~cloudct.mc.combined.BACKWARD_PATHS_PER_PHOTON`
        backward paths per stored path, traced fresh every evaluation over every pixel
        (images) or those with a non-zero residual (gradient); ``"forward"`` and
        ``"score"`` (the defaults) replay the forward paths alone.
    """

    def __init__(
        self,
        scene: Scene,
        *,
        photons: int,
        gradient_photons: int | None = None,
        batches: int = 32,
        policy: Policy | None = None,
        memory_budget: float | None = None,
        storage: str = "auto",
        seed: int = 0,
        rr_depth: int = 100,
        rr_survival: float = 0.95,
        sort: bool | None = None,
        progress: bool | None = False,
        variable: np.ndarray | None = None,
        backend: str = "cpu",
        image_method: str = "forward",
        gradient_estimator: str = "score",
    ) -> None:
        if image_method not in IMAGE_METHODS:
            raise ValueError(f"image_method must be one of {IMAGE_METHODS}, got "
                             f"{image_method!r}")
        if gradient_estimator not in GRADIENT_ESTIMATORS:
            raise ValueError(f"gradient_estimator must be one of {GRADIENT_ESTIMATORS}, got "
                             f"{gradient_estimator!r}")
        self.image_method = image_method
        self.gradient_estimator = gradient_estimator
        gradient_photons = photons if gradient_photons is None else gradient_photons
        if int(photons) < 1 or int(gradient_photons) < 1:
            raise ValueError("photons and gradient_photons must be positive counts")
        if int(batches) < 2:
            raise ValueError(f"batches must be at least 2 for standard errors, got {batches}")
        self.scene = scene
        self.batches = int(batches)
        self.policy = AdaptiveESS() if policy is None else policy
        self.memory_budget = memory_budget
        self.storage = storage
        self.variable = variable
        self.seed = int(seed)
        self.rr_depth = int(rr_depth)
        self.rr_survival = float(rr_survival)
        self.progress = progress
        self.backend = resolve_backend(backend)
        self.sort = self.backend == "cuda" if sort is None else bool(sort)
        self._slots = {
            "images": _Slot(int(photons)),
            "gradient": _Slot(int(gradient_photons)),
        }
        self.iteration = 0
        #: One dict per evaluation: iteration, reasons, ESS fractions, ages, times.
        self.log: list[dict] = []

    # -- stores ---------------------------------------------------------------------------

    @property
    def image_store(self) -> PathStore | None:
        """The store the images (and so the residual) are replayed from."""
        return self._slots["images"].store

    @property
    def gradient_store(self) -> PathStore | None:
        """The store the gradient is replayed from."""
        return self._slots["gradient"].store

    @property
    def nbytes(self) -> int:
        """Memory held by the stores."""
        return sum(s.store.nbytes for s in self._slots.values() if s.store is not None)

    def _budget(self, name: str) -> float | None:
        if self.memory_budget is None:
            return None
        total = sum(s.photons for s in self._slots.values())
        return self.memory_budget * self._slots[name].photons / total

    def resample(self, medium: xr.Dataset, which: tuple[str, ...] = STORES) -> None:
        """Record new paths under ``medium`` (the new reference) for the named stores."""
        for name in which:
            slot = self._slots[name]
            self._release_store(slot.store)  # release the old paths before recording new ones
            slot.store = None
            slot.store = self._record_store(
                medium, photons=slot.photons,
                seed=store_seed(self.seed, slot.generation, STORES.index(name)),
                memory_budget=self._budget(name),
            )
            slot.generation += 1
            slot.age = 0

    # -- the store operations (overridden where the stores live elsewhere) -----------------

    def _record_store(
        self, medium: xr.Dataset, *, photons: int, seed: int, memory_budget: float | None
    ) -> PathStore:
        return record_paths(
            medium, self.scene, photons=photons, seed=seed, batches=self.batches,
            storage=self.storage, memory_budget=memory_budget, sort=self.sort,
            rr_depth=self.rr_depth, rr_survival=self.rr_survival, progress=self.progress,
            variable=self.variable,
        )

    def _release_store(self, store) -> None:
        """Free a store about to be replaced (None: none yet; here dropping it is enough)."""

    def _log_weights(self, store, medium: xr.Dataset) -> np.ndarray:
        """The :func:`~cloudct.recycling.replay.weight_summary` of the store's paths."""
        return weight_summary(correction_log_weights(store, medium, self.backend), store.batches)

    def _replay_images(
        self, store, medium: xr.Dataset, mis_ratio: float = 0.0
    ) -> tuple[np.ndarray, dict]:
        return replay_images(store, medium, self.progress, self.backend, mis_ratio)

    def _replay_gradient(
        self, store, medium: xr.Dataset, residual: np.ndarray, mis_ratio: float = 0.0
    ) -> tuple:
        return replay_gradient(store, medium, residual, self.progress, self.backend, mis_ratio)

    # -- the combined estimator: replayed forward half, fresh backward half ---------------

    def _backward_half(
        self, medium: xr.Dataset, store, pixel_samples: int, stream: int
    ) -> tuple[KernelInputs, int, Sampling]:
        """Kernel inputs of ``medium`` with the combined estimator's ratio for ``store``'s
        paths and ``pixel_samples`` backward samples of each pixel, those samples per batch,
        and the sampling of this evaluation's backward paths (stream 2: the images', 3: the
        gradient's; independent of the stores' and of every other evaluation's)."""
        sampling = Sampling(self.batches, store_seed(self.seed, self.iteration, stream),
                            self.rr_depth, self.rr_survival, self.backend)
        k = kernel_inputs(medium, self.scene, store.info.get("aim_fraction"))  # the paths' aim
        k, per_pixel = combined_inputs(k, sampling, store.per_batch, pixel_samples)
        return k, per_pixel, sampling

    def _images(self, store, medium: xr.Dataset) -> tuple[np.ndarray, dict]:
        """Per-batch images of ``medium`` by the recycler's image method, and run info."""
        if self.image_method == "forward":
            return self._replay_images(store, medium)
        k, per_pixel, sampling = self._backward_half(
            medium, store, default_pixel_samples(store.paths, self.scene), 2
        )
        forward, info = self._replay_images(store, medium, k.cams.mis_ratio)
        backward, run = backward_images(k, per_pixel, sampling=sampling, progress=self.progress)
        return forward + backward, {
            **info, "pixel_samples": per_pixel * self.batches,
            "backward_events": run["events"], "backward_time": run["wall_time"],
            "wall_time": info["wall_time"] + run["wall_time"],
        }

    def _gradient(self, store, medium: xr.Dataset, residual: np.ndarray) -> tuple:
        """(mean, std_error, info) of the gradient by the recycler's estimator."""
        if self.gradient_estimator == "score":
            return self._replay_gradient(store, medium, residual)
        residual = check_residual(residual, self.scene)
        k, per_pixel, sampling = self._backward_half(
            medium, store, samples_per_pixel(store.paths, np.count_nonzero(residual)), 3
        )
        mean, std_error, info = self._replay_gradient(store, medium, residual,
                                                      k.cams.mis_ratio)
        batches, run = backward_score_batches(k, residual, per_pixel, sampling=sampling,
                                              progress=self.progress)
        batches = per_cloud_extinction(k, batches)
        if self.variable is not None:
            batches[:, ~self.variable] = 0.0  # the voxels that may change, as the stores
        # independent halves: their variances add
        return mean + batches.mean(axis=0), np.hypot(
            std_error, batches.std(axis=0, ddof=1) / math.sqrt(self.batches)
        ), {**info, "pixel_samples": per_pixel * self.batches,
            "backward_events": run["events"], "backward_time": run["wall_time"],
            "wall_time": info["wall_time"] + run["wall_time"]}

    def _extra_info(self) -> dict:
        """Entries that an evaluation's info adds (none here)."""
        return {}

    # -- the call of every iteration ----------------------------------------------------

    def evaluate(
        self,
        medium: xr.Dataset,
        residual: Callable[[xr.Dataset], np.ndarray] | np.ndarray | None = None,
    ) -> Evaluation:
        """Images of ``medium`` and, given a ``residual``, the residual-weighted gradient.

        ``residual`` is either a function of the images Dataset returning the pixel weights
        r_d (e.g. w_d (I_d - I_d^measured), seed paper Eq. 48), or fixed weights over
        (view, row, col), or None for images only. Stores are resampled first where the
        policy says so (or where none exists yet). The medium must be on the grid of the
        stores (call :meth:`resample` after changing the grid).
        """
        start = time.perf_counter()
        edges = cell_edges(medium)
        for slot in self._slots.values():
            if slot.store is not None:
                check_same_grid(slot.store, edges)
        needed = ("images",) if residual is None else STORES
        reasons: dict[str, str | None] = {}
        checked: dict[str, dict] = {}
        record_time = 0.0
        for name in needed:
            slot = self._slots[name]
            if slot.store is None:
                reason = "initial"
            else:
                ess = max_log_r = None
                if self.policy.uses_ess:
                    ess, max_log_r = summary_ess(self._log_weights(slot.store, medium))
                    ess /= slot.store.paths
                    checked[name] = {"ess_fraction": ess, "max_ratio": math.exp(max_log_r)}
                reason = self.policy.resample_reason(slot.age, ess, max_log_r)
            if reason is not None:
                t0 = time.perf_counter()
                self.resample(medium, (name,))
                record_time += time.perf_counter() - t0
            reasons[name] = reason

        store = self._slots["images"].store
        batch_images, image_info = self._images(store, medium)
        images = recycled_images(store, batch_images, image_info)
        if self.image_method == "combined":
            images.attrs.update(method="combined-recycled",
                                pixel_samples=image_info["pixel_samples"],
                                mis_ratio=image_info["mis_ratio"])
        weights = gradient = gradient_se = None
        gradient_info: dict = {}
        if residual is not None:
            weights = residual(images) if callable(residual) else residual
            gradient, gradient_se, gradient_info = self._gradient(
                self._slots["gradient"].store, medium, weights
            )
        for name in needed:
            self._slots[name].age += 1
        info = {
            "iteration": self.iteration,
            "resampled": any(r is not None for r in reasons.values()),
            "reasons": reasons,
            "ess_images": image_info["ess_fraction"],
            "ess_gradient": gradient_info.get("ess_fraction"),
            "checked": checked,
            "age": {name: self._slots[name].age for name in needed},
            "record_time": record_time,
            "images_time": image_info["wall_time"],
            "gradient_time": gradient_info.get("wall_time", 0.0),
            "bytes": self.nbytes,
            **self._extra_info(),
        }
        fractions = [f for f in (info["ess_images"], info["ess_gradient"]) if f is not None]
        info["ess_fraction"] = min(fractions)
        info["wall_time"] = time.perf_counter() - start
        self.log.append(info)
        logger.info(
            "recycling iteration %d: %s, ESS fraction %.3f, ages %s, %.2f s",
            self.iteration,
            "resampled (" + ", ".join(f"{k}: {v}" for k, v in reasons.items() if v) + ")"
            if info["resampled"] else "recycled",
            info["ess_fraction"], info["age"], info["wall_time"],
        )
        self.iteration += 1
        return Evaluation(images, weights, gradient, gradient_se, info)
