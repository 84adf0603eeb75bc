"""The retrieval of liquid water content (LWC) and droplet effective radius (r_eff) from
measurements in several bands (issue 53): ``RetrievalConfig(unknowns=("lwc", "reff"))``,
``cloudct retrieve --unknowns lwc reff``.

Droplets absorb in the shortwave infrared (1.65, 2.13 micron) in proportion to their size,
and the extinction per unit of water falls as 1 / r_eff, so the images of several bands
tell LWC and r_eff apart where one band sees only the extinction. The loss is the sum of
every band's (seed paper Eq. 41) plus prior terms in LWC and r_eff::

    L(LWC, r_eff) = sum_b 1/2 sum_d w_bd (I_bd - m_bd)^2
                    + L_empty sum_j w_j m_j Phi_j(e_0 LWC) + L_empty sum_k w_k m_k Psi_k(r_eff),
    dL / dLWC_v = sum_b sum_d r_bd dI_bd / dLWC_v + L_empty sum_j w_j m_j e_0 dPhi_j / d beta_v,
    dL / dr_eff_v = sum_b sum_d r_bd dI_bd / dr_eff_v + L_empty sum_k w_k m_k dPsi_k / dr_eff_v,

with r_bd = w_bd (I_bd - m_bd) the residual of band b, I_bd rendered through the band's
Mie table (:func:`cloudct.optics.band_optics`), its derivatives by
:func:`cloudct.mc.microphysics_gradient.microphysics_gradient` (the extinction's terms by
the configured ``estimator``, sample matching by default; the albedo's and the phase
function's terms in r_eff by the path score function of forward photons), L_empty the
loss of a dark medium summed over the bands, Phi_j the extinction's terms of
:data:`cloudct.retrieval.priors.PRIORS` on the reference extinction e_0 LWC (e_0 the
shortest band's extinction per unit LWC at
:data:`~cloudct.retrieval.microphysics_first_guess.FIRST_GUESS_REFF`: a fixed multiple of LWC,
so that the terms and their weights keep the extinction's units and meaning, and
exact functions of LWC alone) and Psi_k the r_eff terms of
:data:`cloudct.retrieval.priors.REFF_PRIORS` (weights and schedules as for the extinction's
terms, a ``noise`` schedule following the noise of the gradient in its own field). Each
iteration takes one projected step on both fields, each with its own
optimiser (:func:`cloudct.retrieval.optimizers.make_optimizer`): LWC's step
``lwc_step`` [g m-3] and r_eff's ``reff_step`` [micron]. With Adam (the default) every
voxel moves by about its step per iteration whatever the scale of its gradient (Adam
divides by the root mean square of the gradient), which is what puts two fields of other
units and gradients of other scales on one footing. The feasible set: LWC >= 0 in the mask
(the carved hull) and 0 outside; r_eff within the range of r_eff that every band's Mie table
covers, in the mask, and 0 outside (clear cells: r_eff means nothing there, and the r_eff
terms count only cells with droplets).

The first guess (:mod:`cloudct.retrieval.microphysics_first_guess`) is the carved
extinction, or the extinction retrieved from the shortest band for ``extinction_share`` of
the run, as LWC at one r_eff fitted to the longest band's brightness. With
``hold_extinction`` the shortest band's extinction beta = e(r_eff) LWC stays the first
guess's: r_eff alone is stepped, along dL/dr_eff at fixed beta = dL/dr_eff + dL/dLWC dLWC /
dr_eff with dLWC / dr_eff = -LWC e'(r_eff) / e(r_eff), LWC = beta / e(r_eff) follows, and
the extinction's prior terms, with nothing to move, are left out.

The paths see the Mie phase functions' forward peak cut at ``phase_truncation`` degrees
(unset: as the initial medium records, else :data:`~cloudct.retrieval.config.
OPTICS_TRUNCATION`'s 3 degrees, as the extinction's retrieval of Mie media), with the
extinction and albedo delta-scaled; the gradients stay in the true LWC and r_eff, the cut's
own dependence on r_eff included (:mod:`cloudct.mc.microphysics_gradient`). A full peak
(``phase_truncation = 0``) makes the 0.672 micron gradient heavy-tailed
(docs/benchmarks.md, "LWC and r_eff from several bands").

The steps and photons follow the extinction's plateau schedule
(:func:`cloudct.retrieval.schedule.advance`, ``schedule``, ``plateau`` and their settings):
where the loss summed over the bands stops falling beyond its Monte Carlo noise, the
photons of every band grow by ``photon_growth`` (to ``photon_cap`` times the configured
count, while an iteration of the grown count fits the time left), then both fields' steps
decay together by ``step_decay`` (to ``step_floor``). Both fields are averaged over the
iterates since the last change of step (``averaging``: by default an exponential moving
average, :func:`~cloudct.retrieval.optimizers.add_to_average`): the result holds the last
iterate (``lwc``, ``reff``) and the average (``lwc_average``, ``reff_average``), whose
errors the log keeps too (``*_average``). One stage; path recycling, checkpoints and
resuming, L-BFGS-B, a non-exponential transmittance and Dask workers are refused by the
configuration or here.
"""

from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace

import numpy as np
import xarray as xr
from tqdm.auto import tqdm

from cloudct.mc.backend import device_description, resolve_backend
from cloudct.mc.microphysics_gradient import microphysics_gradient
from cloudct.mc.render import render
from cloudct.mc.scene import Scene
from cloudct.mc.visibility import boundary_optical_distance
from cloudct.measurements import (
    BAND,
    band_measurements,
    band_wavelengths,
    coarse_measurements,
)
from cloudct.medium import is_microphysical, is_optical, validate_medium
from cloudct.optics import GRID, PHASE_TRUNCATION, band_optics, to_optical
from cloudct.physics.microphysics import (
    cloud_extinction,
    extinction_lwc_derivative,
    extinction_reff_derivative,
)
from cloudct.physics.mie import DEFAULT_VEFF, mie_table
from cloudct.retrieval.config import OPTICS_TRUNCATION, RetrievalConfig
from cloudct.retrieval.config_file import config_to_toml
from cloudct.retrieval.loss import BATCHES, image_loss, loss_std_error, pixel_weights
from cloudct.retrieval.metrics import (
    SHELLS,
    epsilon_delta,
    reff_absolute_error,
    reff_relative_error,
)
from cloudct.retrieval.microphysics_first_guess import FIRST_GUESS_REFF
from cloudct.retrieval.optimizers import (
    add_to_average,
    block_mean,
    make_optimizer,
    smoothed_gradient,
)
from cloudct.retrieval.priors import REFF_PRIORS, PriorGrid
from cloudct.retrieval.schedule import advance, noise_weight, record_decisions
from cloudct.retrieval.state import ScheduleState

LOGGER = logging.getLogger(__name__)

#: The optical distance from the cloud's lit and viewed boundary within which the log's
#: ``_near`` errors are taken: the images' reach (the veiled core lies beyond).
NEAR = SHELLS[-1]
#: The errors against a truth of an iterate (:meth:`MicrophysicsRetrieval.errors`): units,
#: long name.
ERROR_COLUMNS = {
    "lwc_epsilon": ("1", "epsilon of LWC, seed paper Eq. (54)"),
    "lwc_delta": ("1", "delta of LWC, seed paper Eq. (54)"),
    "reff_absolute_error": ("micron", "mean |r_eff error| over the true cloud"),
    "reff_relative_error": ("1", "mean |r_eff error| / r_eff over the true cloud"),
    "reff_absolute_error_near": ("micron", f"mean |r_eff error| over the true cloud within "
                                 f"optical distance {NEAR:g} of its lit and viewed boundary"),
    "reff_relative_error_near": ("1", f"mean |r_eff error| / r_eff over the true cloud "
                                 f"within optical distance {NEAR:g} of its boundary"),
}
#: The log's columns that need a truth: the iterate's errors and the iterate average's.
ERROR_FIELDS = (*ERROR_COLUMNS, *(f"{key}_average" for key in ERROR_COLUMNS))
#: The columns of the per-iteration log (``log_*`` over ``iteration``): units, long name.
LOG_FIELDS = {
    "loss": ("1", "loss summed over the bands, seed paper Eq. (41)"),
    "loss_std_error": ("1", "Monte Carlo standard error of the loss"),
    "prior": ("1", "the prior terms' part of the loss at the iterate the step started from"),
    **ERROR_COLUMNS,
    **{f"{key}_average": (units, f"{name}, of the iterate average")
       for key, (units, name) in ERROR_COLUMNS.items()},
    "photons": ("1", "photons of the iteration, all bands: images' and gradients'"),
    "step": ("1", "the steps' multiple of lwc_step and reff_step (step decays)"),
    "seconds": ("s", "cumulative wall time"),
}


@dataclass
class BandsLossGradient:
    """A loss evaluation over bands: the loss and each band's, its standard error, and its
    gradients in ``"lwc"`` [per g m-3] and ``"reff"`` [per micron] over (x, y, z) with
    their standard errors; ``info``: the gradients' wall time and photons."""

    loss: float
    band_losses: np.ndarray
    loss_std_error: float
    gradient: dict[str, np.ndarray]
    std_error: dict[str, np.ndarray]
    info: dict


def loss_and_gradient_over_bands(
    medium: xr.Dataset,
    bands: Sequence[xr.Dataset],
    tables: Sequence[xr.Dataset],
    *,
    photons: int,
    gradient_photons: int | None = None,
    seed: int = 0,
    weights: Sequence[np.ndarray] | None = None,
    method: str = "forward",
    estimator: str = "score",
    pixel_sampling: str = "uniform",
    batches: int = BATCHES,
    backend: str = "cpu",
) -> BandsLossGradient:
    """The loss of the microphysical ``medium`` against one-band measurement sets
    ``bands``, summed over the bands, and its gradients in LWC and r_eff (module
    documentation).

    Band b is rendered with its Mie table ``tables[b]`` (its wavelength the band's) by
    ``photons`` of ``method`` (:func:`cloudct.mc.render.render`) with seed ``2 (seed + b)``,
    its residual taken with ``weights[b]`` (default :func:`~cloudct.retrieval.loss.
    pixel_weights`) by :func:`~cloudct.retrieval.loss.image_loss`, and its gradients
    estimated by :func:`~cloudct.mc.microphysics_gradient.microphysics_gradient` with
    ``gradient_photons`` (default ``photons``) of ``estimator`` (its ``pixel_sampling``) on
    independent paths, seed ``2 (seed + b) + 1``. The bands' gradients and losses add up;
    their standard errors add in quadrature (independent paths)."""
    wavelengths = [float(band.attrs["wavelength"]) for band in bands]
    weights = [pixel_weights(band) for band in bands] if weights is None else weights
    optical = band_optics(medium, wavelengths, mie_tables=tables, optics="mie")
    losses, variance = [], 0.0
    gradient = {name: 0.0 for name in ("lwc", "reff")}
    error = {name: 0.0 for name in ("lwc", "reff")}
    info = {"wall_time": 0.0, "photons": 0}
    for b, (band, table, w, optics) in enumerate(zip(bands, tables, weights, optical,
                                                      strict=True)):
        scene = Scene.from_dataset(band)
        images = render(optics, scene, photons=photons, method=method, seed=2 * (seed + b),
                        batches=batches, progress=False, backend=backend)
        loss, residual = image_loss(images["radiance"].values, band["radiance"].values, w)
        losses.append(loss)
        variance += loss_std_error(residual, images["radiance_std_error"].values) ** 2
        mean, std_error, band_info = microphysics_gradient(
            medium, scene, residual, photons=gradient_photons or photons, mie_table=table,
            estimator=estimator, pixel_sampling=pixel_sampling, seed=2 * (seed + b) + 1,
            batches=batches, progress=False, backend=backend)
        for name in gradient:
            gradient[name] = gradient[name] + mean[name]
            error[name] = error[name] + std_error[name] ** 2
        info["wall_time"] += band_info["wall_time"]
        info["photons"] += band_info["photons"]
    return BandsLossGradient(float(sum(losses)), np.array(losses), math.sqrt(variance),
                             gradient, {k: np.sqrt(v) for k, v in error.items()}, info)


def retrieval_bands(measurements: xr.Dataset) -> np.ndarray:
    """The wavelengths [micron] of a measurement set with several bands; a ValueError in
    one line for a set of one band."""
    wavelengths = band_wavelengths(measurements)
    if BAND not in measurements.dims or wavelengths.size < 2:
        held = ", ".join(f"{w:g}" for w in wavelengths) or "an unrecorded wavelength"
        raise ValueError(f"the unknowns lwc reff need measurements in several bands (e.g. "
                         f"cloudct synth --bands 0.672 1.65 2.13); these hold one band "
                         f"({held} micron)")
    return wavelengths


class MicrophysicsRetrieval:
    """A retrieval of LWC and r_eff from measurements in several bands (module
    documentation).

    ``measurements`` hold two bands or more (docs/measurements.md, "Bands"); ``initial`` is
    a microphysical medium (:func:`microphysical_first_guess` makes one from a carved
    extinction) whose grid, air and v_eff are kept; ``mask`` (x, y, z booleans, default:
    where the initial LWC is positive) bounds the cloud; ``truth`` (optional, microphysical)
    gives the log's errors; ``mie_tables`` one table per band (default: each band's
    :func:`~cloudct.physics.mie.mie_table` at the initial medium's v_eff).
    """

    def __init__(
        self,
        measurements: xr.Dataset,
        initial: xr.Dataset,
        config: RetrievalConfig,
        *,
        mask: np.ndarray | None = None,
        truth: xr.Dataset | None = None,
        mie_tables: Sequence[xr.Dataset] | None = None,
        backend: str = "cpu",
    ) -> None:
        if not config.microphysical:
            raise ValueError("MicrophysicsRetrieval retrieves the unknowns lwc reff; the "
                             "extinction is cloudct.retrieval.loop.Retrieval's")
        wavelengths = retrieval_bands(measurements)
        if is_optical(initial) or not is_microphysical(initial):
            raise ValueError("the unknowns lwc reff start from a microphysical medium (lwc, "
                             "reff); the initial medium is optical (cloud extinction): "
                             "microphysical_first_guess turns it into one (cloudct retrieve "
                             "--unknowns lwc reff --init carve does)")
        validate_medium(initial)
        cut = config.phase_truncation
        if cut is None:
            cut = float(initial.attrs.get(PHASE_TRUNCATION, 0.0)) or OPTICS_TRUNCATION["mie"]
            LOGGER.info("phase truncation %g degrees: the paths see the Mie peak cut "
                        "(phase_truncation = 0 keeps it)", cut)
        self.config = config = replace(config, phase_truncation=float(cut))
        initial = initial.assign_attrs({PHASE_TRUNCATION: float(cut)})
        self.backend = resolve_backend(backend)
        veff = float(initial["veff"].max()) if "veff" in initial else DEFAULT_VEFF
        self.tables = ([mie_table(wavelength=float(w), veff=veff) for w in wavelengths]
                       if mie_tables is None else list(mie_tables))
        if len(self.tables) != wavelengths.size:
            raise ValueError(f"{len(self.tables)} Mie tables for {wavelengths.size} bands")
        self.wavelengths = wavelengths
        self.bands = [coarse_measurements(band_measurements(measurements, w), config.stages[0])
                      for w in wavelengths]
        self.weights = [pixel_weights(band) for band in self.bands]
        self.empty_loss = sum(image_loss(np.zeros_like(band["radiance"].values),
                                         band["radiance"].values, w)[0]
                              for band, w in zip(self.bands, self.weights, strict=True))
        self.template = initial
        lwc = initial["lwc"].transpose(*GRID).values.astype(float)
        self.mask = lwc > 0.0 if mask is None else np.asarray(mask, dtype=bool)
        if self.mask.shape != lwc.shape:
            raise ValueError("the mask's grid differs from the initial medium's")
        self.reff_range = (max(float(t["reff"].values[0]) for t in self.tables),
                           min(float(t["reff"].values[-1]) for t in self.tables))
        self.lwc = np.where(self.mask, lwc, 0.0)
        self.reff = self._bounded(initial["reff"].transpose(*GRID).values.astype(float))
        self.optimizers = {"lwc": make_optimizer(config.optimizer, config.lwc_step),
                           "reff": make_optimizer(config.optimizer, config.reff_step)}
        self._prior_grid = PriorGrid.of(initial)
        self.truth = None if truth is None else self._true_fields(truth)
        self.state = ScheduleState(log={key: [] for key in LOG_FIELDS},
                                   photons=config.photons, photons_base=config.photons)
        # the iterate average of each field: its weighted sum and total weight
        self.averages: dict[str, tuple[np.ndarray | None, float]] = {}
        self.noise_reference: dict[str, float] = {}
        # e_0: the extinction per unit LWC of the shortest band at FIRST_GUESS_REFF
        self.shortest_table = self.tables[int(np.argmin(self.wavelengths))]
        self.reference_extinction = float(extinction_lwc_derivative(
            0.0, FIRST_GUESS_REFF, self.shortest_table))
        # hold_extinction: the shortest band's cloud extinction that LWC follows
        self.held_extinction = (cloud_extinction(self.lwc, self.reff, self.shortest_table)
                                if config.hold_extinction else None)
        self.band_losses: list[np.ndarray] = []

    def _bounded(self, reff: np.ndarray) -> np.ndarray:
        """r_eff clipped to the tables' range in the mask, 0 outside."""
        return np.where(self.mask, np.clip(reff, *self.reff_range), 0.0)

    def _true_fields(self, truth: xr.Dataset) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The true LWC and r_eff, and each voxel's optical distance from the cloud's lit
        and viewed boundary in the shortest band."""
        if is_optical(truth) or not is_microphysical(truth):
            raise ValueError("the true medium of the unknowns lwc reff must be microphysical "
                             "(lwc, reff)")
        lwc = truth["lwc"].transpose(*GRID).values.astype(float)
        if lwc.shape != self.mask.shape:
            raise ValueError("the true medium's grid differs from the initial medium's")
        distance = boundary_optical_distance(to_optical(truth, self.tables[0], optics="mie"),
                                             Scene.from_dataset(self.bands[0]))
        return lwc, truth["reff"].transpose(*GRID).values.astype(float), distance

    def medium(self) -> xr.Dataset:
        """The current medium: the initial one with the current LWC and r_eff."""
        out = self.template.copy(deep=True)
        out["lwc"] = out["lwc"].transpose(*GRID).copy(data=self.lwc.copy())
        out["reff"] = out["reff"].transpose(*GRID).copy(data=self.reff.copy())
        return out

    def prior(self, multiples: dict[str, float] | None = None
              ) -> tuple[float, dict[str, np.ndarray | float]]:
        """The prior terms' part of the loss at the current iterate and its gradients in
        ``"lwc"`` and ``"reff"``: L_empty sum_j w_j m_j Phi_j, m_j = ``multiples[field]`` for
        a term whose schedule is ``noise`` (as :meth:`cloudct.retrieval.loop.Retrieval.
        prior`), the field the term acts on: r_eff for the terms of :data:`~cloudct.
        retrieval.priors.REFF_PRIORS`, the extinction's terms on the reference extinction
        e_0 LWC (module documentation)."""
        multiples = multiples or {}
        value, gradient = 0.0, {"lwc": 0.0, "reff": 0.0}
        for p in self.config.priors:
            name = "reff" if p.term in REFF_PRIORS else "lwc"
            if name == "lwc" and self.held_extinction is not None:
                continue  # the extinction is held: its terms have nothing to move
            field = self.reff if name == "reff" else self.reference_extinction * self.lwc
            phi, d_phi = p.value_and_gradient(field, self._prior_grid)
            scale = p.weight * self.empty_loss * (
                multiples.get(name, 1.0) if p.schedule == "noise" else 1.0)
            value += scale * phi
            chain = 1.0 if name == "reff" else self.reference_extinction
            gradient[name] = gradient[name] + scale * chain * d_phi
        return value, gradient

    def errors(self, fields: dict[str, np.ndarray] | None = None) -> dict[str, float]:
        """The errors against the truth (:data:`ERROR_COLUMNS`; NaN without a truth) of
        ``fields`` (``"lwc"`` and ``"reff"``; default: the current iterate)."""
        if self.truth is None:
            return dict.fromkeys(ERROR_COLUMNS, math.nan)
        fields = fields or {"lwc": self.lwc, "reff": self.reff}
        lwc, reff, distance = self.truth
        epsilon, delta = epsilon_delta(lwc, fields["lwc"])
        near = distance < NEAR
        r = fields["reff"]
        return {"lwc_epsilon": epsilon, "lwc_delta": delta,
                "reff_absolute_error": reff_absolute_error(lwc, reff, r),
                "reff_relative_error": reff_relative_error(lwc, reff, r),
                "reff_absolute_error_near": reff_absolute_error(lwc, reff, r, near),
                "reff_relative_error_near": reff_relative_error(lwc, reff, r, near)}

    def average(self) -> dict[str, np.ndarray] | None:
        """The iterate average of both fields since the last change of step (None without
        averaging or before the first iterate)."""
        if not self.averages:
            return None
        return {name: total / weight for name, (total, weight) in self.averages.items()}

    def step(self) -> dict[str, float]:
        """One iteration: the loss and gradients over the bands, the prior terms, one
        projected step on each field, the iterate average and the schedule; returns the
        log's row."""
        cfg, s = self.config, self.state
        start = time.perf_counter()
        photons, gradient_photons = cfg.photons_at(0, s.photons)
        ev = loss_and_gradient_over_bands(
            self.medium(), self.bands, self.tables, photons=photons,
            gradient_photons=gradient_photons,
            seed=cfg.seed * 1_000_003 + s.iteration * len(self.bands),
            weights=self.weights, method=cfg.image_method, estimator=cfg.estimator[0],
            pixel_sampling=cfg.pixel_sampling, backend=self.backend)
        multiples = {}
        for name in ("lwc", "reff"):
            multiples[name], rms = noise_weight(ev.std_error[name], self.mask,
                                                self.noise_reference.get(name, 0.0))
            self.noise_reference.setdefault(name, rms)
        prior, prior_gradient = self.prior(multiples)
        gradients = {name: ev.gradient[name] + prior_gradient[name] for name in ("lwc", "reff")}
        fields = (("lwc", self.lwc), ("reff", self.reff))
        if self.held_extinction is not None:  # dL/dr at fixed beta: + dL/dLWC dLWC/dr
            gradients["reff"] = gradients["reff"] - gradients["lwc"] * extinction_reff_derivative(
                self.lwc, self.reff, self.shortest_table) / extinction_lwc_derivative(
                self.lwc, self.reff, self.shortest_table)
            fields = fields[1:]
        stepped = {"lwc": self.lwc}
        for name, now in fields:
            gradient = smoothed_gradient(block_mean(gradients[name], self.mask,
                                                    cfg.voxel_blocks[0]),
                                         self.mask, cfg.gradient_smoothing[0])
            self.optimizers[name].step = getattr(cfg, f"{name}_step") * s.step_scale
            stepped[name] = self.optimizers[name].update(now, gradient, self.mask)
        self.lwc, self.reff = stepped["lwc"], self._bounded(stepped["reff"])
        if self.held_extinction is not None:
            self.lwc = np.where(self.mask, self.held_extinction / extinction_lwc_derivative(
                self.lwc, self.reff, self.shortest_table), 0.0)
        if cfg.averaging != "none":
            for name, now in (("lwc", self.lwc), ("reff", self.reff)):
                self.averages[name] = add_to_average(*self.averages.get(name, (None, 0.0)),
                                                     now, cfg.averaging_decay_factor)
        average = self.average()
        average_errors = (self.errors(average) if average is not None
                          else dict.fromkeys(ERROR_COLUMNS, math.nan))
        seconds = time.perf_counter() - start
        s.elapsed += seconds
        row = {"loss": ev.loss, "loss_std_error": ev.loss_std_error, "prior": prior,
               **self.errors(), **{f"{k}_average": v for k, v in average_errors.items()},
               "photons": (photons + gradient_photons) * len(self.bands),
               "step": s.step_scale, "seconds": s.elapsed}
        for key in LOG_FIELDS:
            s.log[key].append(float(row[key]))
        self.band_losses.append(ev.band_losses)
        s.iteration += 1
        step_scale = s.step_scale
        record_decisions(s, advance(cfg, s, seconds))
        if s.step_scale != step_scale:  # another optimisation: restart the average
            self.averages = {}
        return row

    def run(self, *, progress: bool | None = None) -> xr.Dataset:
        """Iterate until ``config.iterations`` (or its time limit); return the result."""
        cfg = self.config
        s = self.state
        bar = tqdm(total=cfg.iterations, initial=s.iteration,
                   disable=None if progress is None else not progress, desc="retrieve",
                   unit="it")
        try:
            while s.iteration < cfg.iterations:
                if cfg.time_limit is not None and s.elapsed >= cfg.time_limit:
                    break
                row = self.step()
                bar.update(1)
                bar.set_postfix(loss=f"{row['loss']:.3g}")
        finally:
            bar.close()
        return self.result()

    def result(self) -> xr.Dataset:
        """The retrieved medium (``lwc``, ``reff``; ``lwc_average`` and ``reff_average``
        with averaging) with the carved mask, the log over ``iteration`` (``log_band_loss``
        over (iteration, band) too), the schedule's decisions and the run's settings."""
        s = self.state
        ds = self.medium().assign_coords(
            iteration=np.arange(1, s.iteration + 1),
            wavelength=(BAND, self.wavelengths, {"units": "micron",
                                                 "long_name": "band wavelength"}))
        for key, (units, name) in LOG_FIELDS.items():
            ds[f"log_{key}"] = ("iteration", np.array(s.log[key], dtype=float),
                                {"units": units, "long_name": name})
        ds["log_band_loss"] = (("iteration", BAND),
                               np.reshape(self.band_losses, (s.iteration, len(self.wavelengths))),
                               {"units": "1", "long_name": "each band's loss, Eq. (41)"})
        ds["cloud_mask"] = (GRID, self.mask.astype(np.int8),
                            {"units": "1", "long_name": "carved cloud hull (1 = inside)"})
        average = self.average()
        for name in () if average is None else ("lwc", "reff"):
            ds[f"{name}_average"] = ds[name].transpose(*GRID).copy(data=average[name])
            ds[f"{name}_average"].attrs["long_name"] = (
                f"{self.config.averaging} average of the iterates of {name} since the last "
                "change of step")
        ds.attrs.update(
            title="cloudct retrieval of LWC and r_eff", unknowns="lwc reff",
            config=json.dumps(asdict(self.config)),
            config_toml=config_to_toml(self.config, header="cloudct retrieve --config FILE "
                                       "re-runs this retrieval (docs/retrieval_config.md)"),
            **s.attrs(), reff_range=list(self.reff_range), reff_range_units="micron",
            backend=self.backend, device=device_description(self.backend),
        )
        return ds
