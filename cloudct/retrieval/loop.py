"""The retrieval loop (seed paper Alg. 1/2): gradient steps on the cloud extinction, with
coarse-to-fine stages, checkpoints and a per-iteration log.

Each iteration t evaluates the loss and its gradient at the current medium with photons
seeded by (seed, t) — so that a resumed run repeats exactly what an uninterrupted run does —
and takes one projected optimiser step (non-negative extinction, zero outside the carved
mask). The coarse-to-fine schedule starts from images averaged over blocks of pixels
(exactly the box-filtered radiance of a coarser camera) and fewer photons, and moves to the
next stage when the loss stops decreasing. The run's settings, :class:`RetrievalConfig`, and
their TOML file are :mod:`cloudct.retrieval.config`'s and
:mod:`cloudct.retrieval.config_file`'s.
"""

from __future__ import annotations

import json
import logging
import math
import time
import warnings
from dataclasses import asdict
from pathlib import Path

import numpy as np
import xarray as xr
from tqdm.auto import tqdm

from cloudct.distributed.executor import executor
from cloudct.jit_cache import compile_clock
from cloudct.mc.backend import device_description, resolve_backend
from cloudct.mc.gradient import gradient_estimate
from cloudct.mc.scene import Scene
from cloudct.mc.traversal import require_smooth_flight_density
from cloudct.mc.visibility import boundary_optical_distance
from cloudct.measurements import (
    assumed_transmittance,
    coarse_measurements,
    measured_transmittance,
)
from cloudct.medium import transmittance_model, validate_medium
from cloudct.netcdf import InputFileError, load_netcdf, require_variables, save_netcdf
from cloudct.optics import kernel_arrays, optics_name, phase_truncation, with_phase_truncation
from cloudct.retrieval.config import (
    AUTO,
    OPTICS_TRUNCATION,
    RetrievalConfig,
    settings_for_optics,
)
from cloudct.retrieval.config_file import check_resume, config_from_json, config_to_toml
from cloudct.retrieval.fingerprint import run_id
from cloudct.retrieval.loss import (
    image_loss,
    loss_and_gradient,
    loss_std_error,
    pixel_weights,
)
from cloudct.retrieval.metrics import epsilon_by_shell, epsilon_delta
from cloudct.retrieval.optimizers import (
    add_to_average,
    block_mean,
    bounded_update,
    make_optimizer,
    project,
    smoothed_gradient,
)
from cloudct.retrieval.photon_budget import (
    fit_auto_photons,
    start_count,
    target_seconds,
)
from cloudct.retrieval.priors import PriorGrid
from cloudct.retrieval.sample_average import lbfgsb_window
from cloudct.retrieval.schedule import advance, noise_weight, record_decisions
from cloudct.retrieval.state import LOG_FIELDS, SHELL_PARTS, RetrievalState, state_from_file
from cloudct.retrieval.stopping import RunStopped, stop_requests

LOGGER = logging.getLogger(__name__)

class Retrieval:
    """A cloud tomography retrieval of the cloud extinction from multi-view measurements.

    ``initial`` is an optical medium (e.g. from space carving) whose grid, air and cloud
    albedo/phase are kept; ``mask`` (x, y, z booleans, default: where the initial cloud
    extinction is positive) bounds the cloud; ``truth`` (optional) gives epsilon and delta.
    ``backend`` and ``client`` (a Dask client, scheduler address or
    :class:`cloudct.distributed.DaskExecutor`) choose where the photons are traced; they do
    not change the results (see :mod:`cloudct.distributed`).
    """

    def __init__(
        self,
        measurements: xr.Dataset,
        initial: xr.Dataset,
        config: RetrievalConfig | None = None,
        *,
        mask: np.ndarray | None = None,
        truth: xr.Dataset | None = None,
        backend: str = "cpu",
        client=None,
    ) -> None:
        if config is not None and config.microphysical:
            raise ValueError("Retrieval retrieves the cloud extinction; the unknowns lwc reff "
                             "are cloudct.retrieval.microphysics.MicrophysicsRetrieval's")
        validate_medium(initial)
        # resolved once, here (on the workers with a client)
        self.backend = backend if client is not None else resolve_backend(backend)
        self.client = client
        self.config = config or RetrievalConfig(
            **settings_for_optics({}, optics_name(initial), phase_truncation(initial)))
        if config is not None and config.phase_truncation is None \
                and optics_name(initial) in OPTICS_TRUNCATION and phase_truncation(initial) == 0:
            warnings.warn(
                f"the initial medium has {optics_name(initial)} optics with the full forward "
                "peak and the config names no phase_truncation: the retrieval traces the full "
                "peak with the config's estimators, not the defaults cloudct retrieve takes "
                "for these optics (RetrievalConfig(**settings_for_optics(settings, optics, "
                "truncation)) gives those; phase_truncation=0 keeps the full peak)",
                UserWarning, stacklevel=2,
            )
        self.measurements = measurements
        self.template = assumed_transmittance(initial, measurements, self.config.transmittance)
        if self.config.phase_truncation is not None:
            self.template = with_phase_truncation(self.template, self.config.phase_truncation)
        # before any work: the score function does not differentiate the linear mix
        require_smooth_flight_density(kernel_arrays(self.template)[0], "score-function gradients")
        self.mask = (
            initial["cloud_extinction"].values > 0 if mask is None else np.asarray(mask, bool)
        )
        if self.mask.shape != initial["cloud_extinction"].shape:
            raise ValueError("the mask's grid differs from the initial medium's")
        self.truth = None if truth is None else truth["cloud_extinction"].values
        if self.truth is not None and self.truth.shape != self.mask.shape:
            raise ValueError("the true medium's grid differs from the initial medium's")
        # each true voxel's optical distance from the lit and viewed boundary: the log
        # splits epsilon by it (where the images speak, where the priors do)
        self._distance = None if truth is None else boundary_optical_distance(
            truth, Scene.from_dataset(measurements))
        quasi_newton = self.config.optimizer == "lbfgsb"
        if quasi_newton and client is not None:
            raise ValueError("optimizer 'lbfgsb' records its paths on this machine: no client")
        self.optimizer = None if quasi_newton else make_optimizer(
            self.config.optimizer, self.config.step
        )
        self.id = run_id(measurements, self.config)
        self._recycler = None
        self._recycler_key = None  # (stage, photons) of the recycler's stores
        self.clock = time.perf_counter  # the wall clock iterations are timed by
        self._times_at_base: list[float] = []  # settled photons "auto": the iterations' times
        # since the last change, scaled to the settled count (photon_budget.refit_to_device)
        self._empty_losses: dict[int, float] = {}
        self._prior_grid = PriorGrid.of(self.template)
        self._stage_data = [coarse_measurements(measurements, b) for b in self.config.stages]
        self.state = RetrievalState(
            iteration=0, stage=0,
            extinction=project(initial["cloud_extinction"].values.astype(float), self.mask),
            optimizer_state={},
        )
        auto = self.config.photons == AUTO
        self.state.photons = start_count(self.backend) if auto else self.config.photons
        self.state.photons_settled = not auto
        self.state.photons_base = self.state.photons

    def medium(self, extinction: np.ndarray | None = None) -> xr.Dataset:
        """The current medium (the initial one with the current cloud extinction)."""
        out = self.template.copy(deep=True)
        out["cloud_extinction"].values = (
            self.state.extinction if extinction is None else extinction
        ).copy()
        return out

    def step(self) -> dict[str, float]:
        """One iteration: loss and gradient, optimiser step (or an L-BFGS-B window), log
        row."""
        s = self.state
        start = self.clock()
        photons, gradient_photons = self.config.photons_at(s.stage, s.photons)
        with compile_clock() as compiling:
            if self.optimizer is None:
                row = {"loss": self._lbfgsb_window(photons, gradient_photons),
                       "resampled": 1.0, "ess": math.nan, "loss_std_error": math.nan,
                       "gradient_seconds": math.nan, "prior": math.nan}
            else:
                row = self._first_order_step(photons, gradient_photons)
        eps, delta = eps_average, delta_average = (math.nan, math.nan)
        average = self._add_to_average()
        parts = dict.fromkeys(SHELL_PARTS, math.nan)
        if self.truth is not None:
            eps, delta = epsilon_delta(self.truth, s.extinction)
            parts = epsilon_by_shell(self.truth, s.extinction, self._distance)
            if average is not None:
                eps_average, delta_average = epsilon_delta(self.truth, average)
        seconds = self.clock() - start
        compiled = min(compiling.seconds, seconds)
        s.elapsed += seconds
        row.update({
            "epsilon": eps, "delta": delta, "seconds": s.elapsed, "compile_seconds": compiled,
            "photons": photons + gradient_photons, "step": self.config.step * self._stage_step(),
            "stage": s.stage, "iteration_seconds": seconds, "epsilon_average": eps_average,
            "delta_average": delta_average,
            **{f"epsilon_{name.replace(' ', '_')}": parts[name] for name in SHELL_PARTS},
        })
        for key in LOG_FIELDS:
            s.log[key].append(float(row[key]))
        s.iteration += 1
        self._schedule(seconds - compiled)
        return row

    def _schedule(self, seconds: float) -> None:
        """After an iteration that traced for ``seconds`` (its compiling left out): fit
        ``photons = "auto"`` to the device (:mod:`cloudct.retrieval.photon_budget`), then
        the plateau schedule (:mod:`cloudct.retrieval.schedule`); each change is a decision
        of the log, and a change of stage or step restarts the iterate average."""
        s = self.state
        changes = []
        if self.config.photons == AUTO:
            cfg = self.config
            share = (sum(cfg.photons_at(s.stage, s.photons_base))  # of the settled count
                     / sum(cfg.photons_at(s.stage, s.photons)))
            changes += fit_auto_photons(s, self._times_at_base, seconds, share,
                                        target_seconds(cfg.iteration_seconds, self.backend))
        stage, step_scale = s.stage, s.step_scale
        changes += advance(self.config, s, seconds)
        record_decisions(s, changes)
        if (s.stage, s.step_scale) != (stage, step_scale):  # another optimisation: restart
            s.average_sum, s.average_weight = None, 0.0
        if s.stage != stage:  # other pixels: the prior's noise reference too
            s.noise_reference = 0.0

    def _add_to_average(self) -> np.ndarray | None:
        """Add the current iterate to the iterate average and return the average (None
        without averaging): sum_k d^(n-k) beta_k / sum_k d^(n-k) over the iterates k = 1 ..
        n since the last restart (:func:`~cloudct.retrieval.optimizers.add_to_average`)."""
        s, cfg = self.state, self.config
        if cfg.averaging == "none":
            return None
        s.average_sum, s.average_weight = add_to_average(
            s.average_sum, s.average_weight, s.extinction, cfg.averaging_decay_factor)
        return self.average()

    def average(self) -> np.ndarray | None:
        """The iterate average (``config.averaging``; None without one or before the first
        iterate of the current stage)."""
        s = self.state
        if s.average_sum is None:
            return None
        return s.average_sum / s.average_weight

    def empty_loss(self, stage: int) -> float:
        """L_empty = 1/2 sum_d w_d m_d^2, the loss (Eq. 41) of a medium that sends no light
        to the cameras, at the stage's pixels: the unit of the priors' weights
        (:mod:`cloudct.retrieval.priors`)."""
        if stage not in self._empty_losses:  # once per stage (pixel_weights warns of NaNs)
            data = self._stage_data[stage]
            measured = data["radiance"].values
            self._empty_losses[stage] = image_loss(np.zeros_like(measured), measured,
                                                   pixel_weights(data))[0]
        return self._empty_losses[stage]

    def prior(self, stage: int, extinction: np.ndarray, multiple: float = 1.0
              ) -> tuple[float, np.ndarray | float]:
        """The priors' part of the loss at ``stage`` and its gradient (0.0 without priors):

            P(beta) = L_empty sum_j w_j m_j Phi_j(beta)

        with m_j = ``multiple`` for a term whose schedule is ``noise`` and 1 for a fixed
        one (:mod:`cloudct.retrieval.priors`). With the L1 term, Phi = sum_v beta_v V_v:
        among media that fit the images about equally well (many, at Monte Carlo noise
        levels) the prior prefers the one with the least extinction, emptying the hull's
        cloud-free voxels, whose gradient is mostly noise."""
        value, gradient = 0.0, 0.0
        for p in self.config.priors:
            if p.weight == 0.0:
                continue
            phi, d_phi = p.value_and_gradient(extinction, self._prior_grid)
            scale = p.weight * self.empty_loss(stage)
            term = scale * d_phi
            if p.schedule == "noise":
                term, scale = term * multiple, scale * multiple
            value += scale * phi
            gradient = term if isinstance(gradient, float) else gradient + term
        return value, gradient

    def _seed(self, stream: int) -> int:
        """The seed of one of the run's random streams (an iteration's photons, a stage's
        recycler): fixed by the run's seed, so that a resumed run repeats them."""
        return self.config.seed * 1_000_003 + stream

    def _stage_step(self) -> float:
        """The step multiple of this iteration: the stage's, times the step decay."""
        return self.config.stage_steps[self.state.stage] * self.state.step_scale

    def _lbfgsb_window(self, photons: int, gradient_photons: int) -> float:
        """An L-BFGS-B window from the current extinction; returns its reference loss."""
        s = self.state
        window = lbfgsb_window(
            self.medium(), self._stage_data[s.stage], self.mask, photons=photons,
            photons_b=gradient_photons, seed=self._seed(s.iteration),
            trust_region=min(self.config.trust_region * self._stage_step(), 1.0),
            evaluations=self.config.period, backend=self.backend,
            memory_budget=self.config.recycling_bytes(),
        )
        s.extinction = window.extinction
        return window.loss

    def _first_order_step(self, photons: int, gradient_photons: int) -> dict[str, float]:
        """Loss and gradient (fresh or recycled) with the priors', preconditioned, and the
        optimiser's step, bounded per voxel by ``max_change``; returns the log's loss, its
        standard error, resampled, ESS fraction, the gradient's seconds and the prior."""
        s, cfg = self.state, self.config
        multiple = 1.0
        if cfg.recycling == "none":
            result = loss_and_gradient(
                self.medium(), self._stage_data[s.stage], photons=photons,
                gradient_photons=gradient_photons, seed=self._seed(s.iteration),
                estimator=cfg.estimator[s.stage], pixel_sampling=cfg.pixel_sampling,
                backend=self.backend, client=self.client, method=cfg.image_method,
            )
            loss, gradient, resampled, ess = result.loss, result.gradient, 1.0, math.nan
            loss_error = result.loss_std_error
            gradient_seconds = result.gradient_info["wall_time"]
            noisy = any(p.schedule == "noise" for p in cfg.priors)
            if noisy and s.photons_settled:  # x noise / first
                multiple, rms = noise_weight(result.gradient_std_error, self.mask,
                                             s.noise_reference)
                s.noise_reference = s.noise_reference or rms
        else:
            loss, loss_error, gradient, resampled, ess, gradient_seconds = (
                self._recycled_loss_and_gradient(photons, gradient_photons)
            )
        prior, prior_gradient = self.prior(s.stage, s.extinction, multiple)
        gradient = smoothed_gradient(
            block_mean(gradient + prior_gradient, self.mask, cfg.voxel_blocks[s.stage]),
            self.mask, cfg.gradient_smoothing[s.stage],
        )
        self.optimizer.state = s.optimizer_state
        self.optimizer.step = cfg.step * self._stage_step()
        stepped = self.optimizer.update(s.extinction, gradient, self.mask)
        if cfg.max_change is not None:
            stepped = bounded_update(s.extinction, stepped, cfg.max_change,
                                     self.optimizer.step)
        s.extinction = stepped
        s.optimizer_state = self.optimizer.state
        return {"loss": loss, "loss_std_error": loss_error, "resampled": resampled, "ess": ess,
                "gradient_seconds": gradient_seconds, "prior": prior}

    def _recycled_loss_and_gradient(
        self, photons: int, gradient_photons: int
    ) -> tuple[float, float, np.ndarray, float, float, float]:
        """Loss, its standard error and gradient from the stage's recycler (seed paper
        Alg. 2): stored paths re-evaluated under the current medium, resampled when the
        policy says so.

        With ``recycle_gradient`` False only the residual's images are recycled, and the
        gradient's paths are traced fresh (with the seed of a fresh iteration's): the
        gradient's noise then changes every iteration, as without recycling, instead of
        repeating for a whole period, which Adam turns into steps as large as a signal's
        (docs/recycling.md). The images store then has the whole memory budget.
        """
        s = self.state
        config = self.config
        data = self._stage_data[s.stage]
        if self._recycler is None or self._recycler_key != (s.stage, s.photons):
            budget = config.recycling_bytes()
            if budget is not None and not config.recycle_gradient:  # the images' share: all
                budget *= (photons + gradient_photons) / photons
            settings = dict(
                photons=photons, gradient_photons=gradient_photons,
                policy=config.policy(), variable=self.mask, memory_budget=budget,
                seed=self._seed(7919 * (s.stage + 1)), image_method=config.image_method,
                gradient_estimator="combined" if config.estimator[s.stage] == "combined"
                else "score",
            )
            if self.client is None:
                from cloudct.recycling.recycler import Recycler

                self._recycler = Recycler(
                    Scene.from_dataset(data), backend=self.backend, **settings
                )
            else:  # the stores live on the workers
                from cloudct.distributed.recycling import DistributedRecycler

                self._recycler = DistributedRecycler(
                    Scene.from_dataset(data), client=self.client, **settings
                )
            self._recycler_key = (s.stage, s.photons)
        w = pixel_weights(data)
        measured = data["radiance"].values

        def residual(images: xr.Dataset) -> np.ndarray:
            return image_loss(images["radiance"].values, measured, w)[1]

        medium = self.medium()
        ev = self._recycler.evaluate(
            medium, residual=residual if config.recycle_gradient else None
        )
        loss, recycled_residual = image_loss(ev.images["radiance"].values, measured, w)
        loss_error = loss_std_error(recycled_residual, ev.images["radiance_std_error"].values)
        gradient, gradient_seconds = ev.gradient, math.nan  # replayed with the images
        if not config.recycle_gradient:
            gradient, _, info = gradient_estimate(
                medium, Scene.from_dataset(data), residual(ev.images),
                estimator=config.estimator[s.stage], photons=gradient_photons,
                seed=2 * self._seed(s.iteration) + 1, pixel_sampling=config.pixel_sampling,
                backend=self.backend,
                executor=None if self.client is None else executor(self.client),
            )
            gradient_seconds = info["wall_time"]
        return (loss, loss_error, gradient, float(ev.info["resampled"]),
                float(ev.info["ess_fraction"]), gradient_seconds)

    def run(
        self, *, checkpoint: str | Path | None = None, progress: bool | None = None
    ) -> xr.Dataset:
        """Iterate until ``config.iterations`` (or the time limit); checkpoint every
        ``checkpoint_every`` iterations and on interrupt; return the result Dataset.
        SIGTERM or Ctrl-C ends the run at the end of the current iteration: the checkpoint
        is written and :class:`~cloudct.retrieval.stopping.RunStopped` raised
        (:mod:`cloudct.retrieval.stopping`)."""
        cfg = self.config
        disable = None if progress is None else not progress
        bar = tqdm(total=cfg.iterations, initial=self.state.iteration, disable=disable,
                   desc="retrieve", unit="it")
        with stop_requests() as stop:
            try:
                while self.state.iteration < cfg.iterations and stop.signum is None:
                    if cfg.time_limit is not None and self.state.elapsed >= cfg.time_limit:
                        break
                    row = self.step()
                    bar.update(1)
                    postfix = {"loss": f"{row['loss']:.3g}", "stage": row["stage"],
                               "photons/s": f"{row['photons'] / row['iteration_seconds']:.3g}"}
                    if not math.isnan(row["epsilon"]):
                        postfix.update(eps=f"{row['epsilon']:.3f}",
                                       delta=f"{row['delta']:+.3f}")
                    bar.set_postfix(postfix)
                    if checkpoint is not None and \
                            self.state.iteration % cfg.checkpoint_every == 0:
                        self.save_checkpoint(checkpoint)
            except KeyboardInterrupt:
                if checkpoint is not None:
                    self.save_checkpoint(checkpoint)
                raise
            finally:
                bar.close()
        if checkpoint is not None:
            self.save_checkpoint(checkpoint)
        if stop.signum is not None:
            raise RunStopped(stop.signum, self.state.iteration,
                             None if checkpoint is None else Path(checkpoint))
        return self.result()

    def result(self) -> xr.Dataset:
        """The retrieved medium with the run's log over ``iteration`` and its settings."""
        s = self.state
        ds = s.add_log_to(self.medium())
        ds["cloud_mask"] = (("x", "y", "z"), self.mask.astype(np.int8))
        ds["cloud_mask"].attrs.update(units="1", long_name="carved cloud hull (1 = inside)")
        average = self.average()
        if average is not None:
            ds["cloud_extinction_average"] = (("x", "y", "z"), average)
            ds["cloud_extinction_average"].attrs.update(
                units="km-1", long_name=f"{self.config.averaging} average of the iterates of "
                "the last stage (and step) of cloud extinction",
            )
        ds.attrs.update(
            title="cloudct retrieval", run_id=self.id, config=json.dumps(asdict(self.config)),
            config_toml=config_to_toml(self.config, header="cloudct retrieve --config FILE "
                                       "re-runs this retrieval (docs/retrieval_config.md)"),
            **s.attrs(),
            optics=optics_name(self.template),
            measurement_optics=str(self.measurements.attrs.get("optics", "unrecorded")),
            transmittance=transmittance_model(self.template)[0],
            measurement_transmittance=measured_transmittance(self.measurements)[0],
            backend=self.backend,
            device=device_description(self.backend) if self.client is None
            else f"Dask workers ({self.backend} back end)",
        )
        return ds

    def save_checkpoint(self, path: str | Path) -> None:
        """Write the state (extinction, optimiser moments, iterate average, log, stage)
        atomically."""
        ds = self.result()
        for key, value in self.state.optimizer_state.items():
            ds[f"optimizer_{key}"] = (("x", "y", "z") if np.ndim(value) == 3 else (), value)
        if self.state.average_sum is not None:
            ds["average_sum"] = (("x", "y", "z"), self.state.average_sum)
        save_netcdf(ds, path, overwrite=True)

    @classmethod
    def resume(
        cls,
        path: str | Path,
        measurements: xr.Dataset,
        initial: xr.Dataset,
        *,
        truth: xr.Dataset | None = None,
        iterations: int | None = None,
        settings: dict | None = None,
        backend: str = "cpu",
        client=None,
    ) -> Retrieval:
        """Continue the run stored in checkpoint ``path``; it must belong to these
        measurements and settings (same run id). Without recycling the resumed run repeats
        exactly what the uninterrupted run does; with recycling the path stores are not in
        the checkpoint, so the resumed run first records new paths under the current medium.

        ``settings`` (:class:`RetrievalConfig` fields) are those asked of the resumed run:
        ``iterations`` and ``time_limit`` replace the checkpoint's, and any other that
        differs from the checkpoint's raises
        :class:`~cloudct.retrieval.config.ResumeConflict` (a ValueError)."""
        ck = load_netcdf(path, "checkpoint")
        require_variables(ck, ("cloud_mask",), "checkpoint", path)
        if not {"config", "run_id"} <= set(ck.attrs):
            raise InputFileError(f"checkpoint file {path} lacks its run's settings (attributes "
                                 "config and run_id); is it a cloudct checkpoint?")
        asked = dict(settings or {})
        if iterations is not None:
            asked["iterations"] = iterations
        config = check_resume(config_from_json(ck.attrs["config"]), asked)
        run = cls(measurements, initial, config, mask=ck["cloud_mask"].values.astype(bool),
                  truth=truth, backend=backend, client=client)
        if ck.attrs["run_id"] != run.id:
            raise ValueError(
                f"checkpoint {path} belongs to another run (id {ck.attrs['run_id']}, these "
                f"measurements and settings give {run.id})"
            )
        run.state = state_from_file(ck, run.state)
        traced = ck.attrs.get("backend", run.backend)
        if traced != run.backend:
            LOGGER.info(
                "resumed on the %s back end from a checkpoint traced on %s: the iterations "
                "from here on trace the same estimators with the same seeds, equal in "
                "distribution, not bitwise, to those the %s run would have traced",
                run.backend, traced, traced)
        return run
