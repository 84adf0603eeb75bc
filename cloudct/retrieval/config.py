"""The settings of a retrieval run: :class:`RetrievalConfig`.

Every setting has a default, checked with the others when a configuration is made; their
TOML file (``cloudct retrieve --config run.toml``) is :mod:`cloudct.retrieval.config_file`'s.
The resolved configuration is stored with every result and checkpoint (attribute
``config_toml``), and that text re-runs the same retrieval (docs/retrieval_config.md).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

from cloudct.mc.gradient import ESTIMATORS, camera_side_names, gradient_estimator
from cloudct.mc.pixel_sampling import PIXEL_SAMPLINGS
from cloudct.retrieval.priors import PRIORS, REFF_PRIORS, Prior, as_prior
from cloudct.retrieval.schedule import PLATEAU_ANSWERS, SCHEDULES

RECYCLING = ("none", "fixed", "adaptive")
OPTIMIZERS = ("adam", "sgd", "lbfgsb")
# per-stage settings that may be given as None: (field, type, value at every stage with Adam
# or SGD, with L-BFGS-B); the first-order values are the measured defaults (docs/benchmarks.md)
PER_STAGE_DEFAULTS = (
    ("stage_photons", float, 1.0, 1.0), ("voxel_blocks", int, 1, 1),
    ("stage_steps", float, 1.0, 1.0),
    ("gradient_smoothing", float, 1.0, 0.0), ("image_photons", float, 2.0, 1.0),
)
AVERAGING = ("none", "uniform", "ema")
#: The transmittance a retrieval assumes: exponential or the measurements' model.
TRANSMITTANCE = ("exponential", "medium")
#: The estimators of the residual's images (cloudct.mc.render.METHODS but the backward one).
IMAGE_METHODS = ("forward", "combined")
#: The loss's prior terms by default with Adam or SGD (:mod:`cloudct.retrieval.priors`;
#: none with L-BFGS-B).
DEFAULT_PRIORS = (Prior("l1", 0.01, "noise"), Prior("smoothness", 1e-4, "noise"))
#: What a retrieval retrieves: the cloud extinction (the seed paper's unknown) from one band,
#: or the liquid water content and droplet effective radius from several bands
#: (:mod:`cloudct.retrieval.microphysics`).
UNKNOWNS = (("extinction",), ("lwc", "reff"))
#: The loss's prior terms by default for the unknowns LWC and r_eff: the extinction's L1
#: and smoothness on the reference extinction e_0 LWC (:mod:`cloudct.retrieval.
#: microphysics`), at fixed weights (L1 a third of the extinction's: with its 0.01 and the
#: noise schedule the single cloud lost 39 % of its water in 15 minutes, with 0.003 fixed
#: 8 %; docs/benchmarks.md, "LWC and r_eff from several bands"), and r_eff smooth inside
#: the cloud (:data:`cloudct.retrieval.priors.REFF_PRIORS`).
DEFAULT_MICROPHYSICS_PRIORS = (Prior("l1", 0.003, "fixed"), Prior("smoothness", 1e-4, "fixed"),
                               Prior("reff_smoothness", 1e-3, "noise"))
#: The L1 term's weight [1/km^2] where a setting of the runs before the other terms
#: (``sparsity_schedule`` without ``sparsity``) leaves it unset: their default.
LEGACY_SPARSITY = 0.01
#: ``photons`` chosen by the device's speed (:mod:`cloudct.retrieval.photon_budget`).
AUTO = "auto"


@dataclass
class RetrievalConfig:
    """Settings of a retrieval run (all stored in checkpoints and results).

    One set of defaults for every scene, chosen by 2-core trials on two cumuli and the seed
    paper's cloud field (docs/benchmarks.md, "A step schedule that reads the Monte Carlo
    noise"): one stage at 2 x 2 pixel blocks, the gradient smoothed
    over 1 voxel, 2x photons for the residual's images, Adam with a step of 0.5 /km, the
    gradient by sample matching from pixels drawn in proportion to |residual|
    (``estimator``, ``pixel_sampling``: 100-400 times the score function's precision per
    second near the plateau; the score function where stored paths are replayed, which
    only it and the combined estimator can), two prior terms (``priors``,
    :mod:`cloudct.retrieval.priors`; chosen by an ablation at equal compute on the single
    cloud and two cumuli, docs/benchmarks.md, "Priors"): L1 at 0.01 /km^2 and total
    variation at 1e-4 /km, their weights falling with the gradient's noise (none with
    L-BFGS-B), the noise schedule (:mod:`cloudct.retrieval.schedule`): when
    the loss's decrease is within its Monte Carlo noise, 1.5x the photons up to 16x, then
    the step halved down to 1/16; and the iterates' exponential moving average kept beside
    the last (``averaging``). The seed paper's step of 2 /km with coarse-to-fine stages 4,
    2, 1 walks away from the carved start; a step of 1 /km makes the cloud field worse than
    its carved start.

    ``photons="auto"`` (the default) traces as many gradient paths per iteration as fill
    ``iteration_seconds`` on the device the run is on (:mod:`cloudct.retrieval.
    photon_budget`); a number fixes them, and with them the iterates, bitwise.

    ``transmittance="medium"`` retrieves under the measurements' (non-exponential) model,
    differentiated by the score function (its default estimator there) or DRT (recycling,
    L-BFGS-B and sample matching refused); ``"exponential"`` assumes exp(-tau)
    (docs/transmittance.md).

    ``optimizer="lbfgsb"`` makes every iteration a window of L-BFGS-B on the sample-average
    loss of fixed paths (:mod:`cloudct.retrieval.sample_average`): up to ``period``
    evaluations within a trust region of ``trust_region`` (x the stage's step multiple and
    the step decay) relative to each voxel's extinction; ``step`` does not apply, and the
    gradient preconditioners (voxel blocks, smoothing) and the recycling policies are
    refused.
    """

    iterations: int = 300
    photons: int | str = "auto"  # gradient's per iteration at the finest stage (see
    # image_photons), or "auto": as many as fill iteration_seconds on the device
    # (cloudct.retrieval.photon_budget)
    iteration_seconds: float | None = None  # photons "auto": the wall time an iteration aims
    # at (None: the back end's, cloudct.retrieval.photon_budget.TARGET_SECONDS)
    optimizer: str = "adam"  # "adam", "sgd" or "lbfgsb"
    step: float = 0.5  # 1/km per iteration for Adam
    seed: int = 0
    stages: tuple[int, ...] = (2,)  # pixel block sizes, coarse to fine
    stage_photons: tuple[float, ...] | None = None  # per stage: photon fraction (None: 1)
    voxel_blocks: tuple[int, ...] | None = None  # per stage: voxels tied in blocks (None: 1)
    stage_steps: tuple[float, ...] | None = None  # per stage: step as a multiple of `step`
    gradient_smoothing: tuple[float, ...] | None = None  # per stage: Gaussian sigma, voxels
    # (None: 1; 0 with lbfgsb)
    image_photons: tuple[float, ...] | None = None  # per stage: residual images' photons as a
    # multiple of the gradient's (None: 2; 1 with lbfgsb)
    schedule: str = "noise"  # how a plateau of the loss is found: "noise" (its decrease is
    # within its noise), "threshold" (below saturation_tolerance) or "fixed" (none: the
    # step decays at fixed fractions of the run) (cloudct.retrieval.schedule)
    saturation_window: int = 20  # iterations of the loss a plateau is judged on
    saturation_tolerance: float = 0.02  # "threshold": the relative decrease of a plateau
    significance: float = 0.05  # "noise": the test's false-alarm rate (one-sided)
    plateau: str = "photons"  # the last stage's answer: "photons" (grow them, then decay
    # the step) or "step" (decay it)
    photon_growth: float = 1.5  # "photons": x this per plateau
    photon_cap: float = 16.0  # ... up to this x the count the run settled at
    step_decay: float = 0.5  # the step x this at a plateau of the last stage (1: never)
    step_floor: float = 0.0625  # the step never below this x its start (0: no floor)
    max_change: float | None = None  # per voxel and iteration, |change| <= this x (beta +
    # the step) (Retrieval._first_order_step; None: unbounded)
    checkpoint_every: int = 20
    time_limit: float | None = None  # seconds; stop after this much wall time
    recycling: str = "none"  # "none", "fixed" (every `period` iterations) or "adaptive" (ESS)
    period: int = 30  # fixed period N_r, the adaptive policy's maximum period, or lbfgsb's
    # evaluations per window
    min_ess: float = 0.5  # adaptive: resample when ESS / paths falls below this
    recycling_memory: float | None = None  # GiB for the two path stores of the recycling
    # or of an lbfgsb window (None: camera connections while a store fits 2 GiB)
    recycle_gradient: bool = True  # False: recycle only the residual's images and trace the
    # gradient's paths fresh every iteration (Retrieval._recycled_loss_and_gradient)
    trust_region: float = 0.3  # lbfgsb: relative change of a voxel's extinction per window
    priors: tuple[Prior, ...] | None = None  # the loss's prior terms, each with its weight
    # and schedule (cloudct.retrieval.priors; None: DEFAULT_PRIORS, none with lbfgsb)
    estimator: tuple[str, ...] | None = None  # per stage: gradient estimator, one of
    # cloudct.mc.gradient.ESTIMATORS (None: "sm", or "score" where the gradient is replayed;
    # a Mie medium with its full peak fills it first: settings_for_optics)
    pixel_sampling: str | None = None  # camera-side estimators: pixels "uniform" or
    # drawn in proportion to |residual| (cloudct.mc.pixel_sampling; None: "residual")
    averaging: str = "ema"  # iterate average (Retrieval.average): "none", "uniform"
    # (Polyak-Ruppert) or "ema" (exponential moving average), restarted at every stage
    # change and step decay
    averaging_decay: float = 0.9  # "ema": weight of the average so far at each iterate
    transmittance: str = "exponential"  # or "medium": the measurements' transmittance model
    # and mode field (differentiated by the score function or DRT)
    image_method: str = "forward"  # the residual's images: "forward", or "combined" (forward
    # and camera paths weighted by multiple importance sampling, cloudct.mc.combined: without
    # the fireflies of a full Mie peak; recycled: forward paths replayed, camera paths fresh;
    # not with lbfgsb)
    phase_truncation: float | None = None  # degrees: the Mie phase functions' forward peak
    # cut flat for the retrieval's paths (cloudct.optics; 0: the full peak; None: as the
    # initial medium records)
    unknowns: tuple[str, ...] = ("extinction",)  # or ("lwc", "reff"): liquid water content
    # and droplet effective radius from several bands (cloudct.retrieval.microphysics)
    lwc_step: float = 0.02  # unknowns lwc reff: the step in LWC [g m-3 per iteration]
    reff_step: float = 0.5  # unknowns lwc reff: the step in r_eff [micron per iteration]
    extinction_share: float = 0.0  # unknowns lwc reff: the share of the run (its time limit,
    # else its iterations) first spent retrieving the extinction in the shortest band
    # (cloudct.retrieval.microphysics_first_guess.extinction_stage; 0: none; 1: all of it,
    # r_eff the brightness-fitted constant)
    hold_extinction: bool | None = None  # unknowns lwc reff: keep the first guess's
    # extinction in the shortest band and retrieve r_eff alone, LWC = beta / e(r_eff)
    # following it (None: after an extinction stage, cloudct.retrieval.microphysics_first_
    # guess.first_guess; else not)

    def __post_init__(self) -> None:
        if self.optimizer not in OPTIMIZERS:
            raise ValueError(f"optimizer must be one of {OPTIMIZERS}, got {self.optimizer!r}")
        self.stages = tuple(int(s) for s in self.stages)
        self.unknowns = tuple(str(name) for name in self.unknowns)
        if self.unknowns not in UNKNOWNS:
            raise ValueError("unknowns must be one of "
                             f"{' or '.join(' '.join(u) for u in UNKNOWNS)}, got "
                             f"{' '.join(self.unknowns)}")
        if self.microphysical:  # sample matching for d/d beta, the r_eff vertex terms the
            # score function's (docs/benchmarks.md, "Sample matching for the extinction's
            # terms"): pixels drawn by residual
            self.estimator = self.estimator or ("sm",) * len(self.stages)
            if self.priors is None:
                self.priors = DEFAULT_MICROPHYSICS_PRIORS
        quasi_newton = self.optimizer == "lbfgsb"
        for name, kind, first_order, lbfgsb in PER_STAGE_DEFAULTS:  # None: the default
            default = lbfgsb if quasi_newton else first_order
            values = getattr(self, name)
            values = (default,) * len(self.stages) if values is None else values
            setattr(self, name, tuple(kind(v) for v in values))
        if self.priors is None:
            self.priors = () if quasi_newton else DEFAULT_PRIORS
        self.priors = tuple(as_prior(p) for p in self.priors)
        terms = [p.term for p in self.priors]
        if len(set(terms)) < len(terms):
            raise ValueError(f"priors name a term twice: {terms}")
        self._check_priors()
        if self.phase_truncation is not None and not 0.0 <= self.phase_truncation < 90.0:
            raise ValueError(f"phase_truncation must be in [0, 90) degrees, got "
                             f"{self.phase_truncation}")
        if self.image_method not in IMAGE_METHODS:
            raise ValueError(f"image_method must be one of {IMAGE_METHODS}, got "
                             f"{self.image_method!r}")
        if self.image_method != "forward" and quasi_newton:
            raise ValueError("image_method 'combined' is not lbfgsb's: its windows replay "
                             "stored forward paths alone (use adam or sgd, or image_method "
                             "'forward')")
        if self.transmittance not in TRANSMITTANCE:
            raise ValueError(f"transmittance must be one of {TRANSMITTANCE}, got "
                             f"{self.transmittance!r}")
        model = self.transmittance == "medium"
        if self.estimator is None:  # the best measured, where stored paths are not replayed
            replayed = quasi_newton or (self.recycling != "none" and self.recycle_gradient)
            self.estimator = ("score" if replayed or model else "sm",) * len(self.stages)
        self.estimator = tuple(str(name) for name in self.estimator)
        records = [gradient_estimator(name) for name in self.estimator]
        camera_side = any(e.camera_side for e in records)
        if self.pixel_sampling is None:
            self.pixel_sampling = "residual" if camera_side else "uniform"
        per_stage = (self.stage_photons, self.voxel_blocks, self.stage_steps,
                     self.gradient_smoothing, self.image_photons, self.estimator)
        if not self.stages or any(len(v) != len(self.stages) for v in per_stage):
            raise ValueError(
                "stages, stage_photons, voxel_blocks, stage_steps, gradient_smoothing, "
                "image_photons and estimator must have the same, non-zero length"
            )
        if self.pixel_sampling not in PIXEL_SAMPLINGS:
            raise ValueError(
                f"pixel_sampling must be one of {PIXEL_SAMPLINGS}, got {self.pixel_sampling!r}"
            )
        if self.pixel_sampling != "uniform" and not camera_side:
            raise ValueError(f"pixel_sampling applies to the camera-side estimators "
                             f"({camera_side_names()}); no stage uses one")
        if self.microphysical:  # their own refusals first (recycling, lbfgsb: in their words)
            self._check_microphysics()
        replay = [e.name for e in records if not e.replayable]
        if replay and self.recycling != "none" and self.recycle_gradient:
            raise ValueError(
                "recycled gradients (a recycling policy without recycle_gradient=False) "
                f"replay stored forward paths, which the estimator {replay[0]!r} does not "
                "record: use "
                f"{' or '.join(repr(e.name) for e in ESTIMATORS.values() if e.replayable)} "
                "at every stage"
            )
        if quasi_newton and set(self.estimator) != {"score"}:
            raise ValueError("optimizer 'lbfgsb' replays stored forward paths by the path "
                             "score function: use the estimator 'score' at every stage")
        if model and (any("gamma" not in e.transmittances for e in records) or quasi_newton
                      or self.recycling != "none"):
            able = " or ".join(repr(e.name) for e in ESTIMATORS.values()
                               if "gamma" in e.transmittances)
            raise ValueError(
                "transmittance 'medium' (a non-exponential model) is differentiated by the "
                f"estimators {able} alone, without stored paths: use one of them at every "
                "stage, recycling 'none' and the optimizer adam or sgd"
            )
        if min(self.stages) < 1:
            raise ValueError(f"stages (pixel blocks) must be >= 1, got {self.stages}")
        if min(self.gradient_smoothing) < 0.0:
            raise ValueError(f"gradient_smoothing must be >= 0, got {self.gradient_smoothing}")
        if min(self.stage_steps) <= 0.0:
            raise ValueError(f"stage_steps must be > 0, got {self.stage_steps}")
        if not 0.0 < self.step_decay <= 1.0:
            raise ValueError(f"step_decay must be in (0, 1], got {self.step_decay}")
        self._check_schedule()
        if min(self.voxel_blocks) < 1:
            raise ValueError(f"voxel_blocks must be >= 1, got {self.voxel_blocks}")
        if self.photons != AUTO and not (isinstance(self.photons, int) and self.photons >= 1):
            raise ValueError(f"photons must be a count >= 1 or {AUTO!r}, got {self.photons!r}")
        if self.iteration_seconds is not None and not self.iteration_seconds > 0.0:
            raise ValueError(f"iteration_seconds must be > 0, got {self.iteration_seconds}")
        if self.iterations < 0 or self.checkpoint_every < 1:
            raise ValueError("iterations >= 0 and checkpoint_every >= 1 needed")
        if min(self.stage_photons) <= 0.0:
            raise ValueError(f"stage_photons must be > 0, got {self.stage_photons}")
        if min(self.image_photons) <= 0.0:
            raise ValueError(f"image_photons must be > 0, got {self.image_photons}")
        if self.recycling not in RECYCLING:
            raise ValueError(f"recycling must be one of {RECYCLING}, got {self.recycling!r}")
        if not 0.0 < self.trust_region <= 1.0:
            raise ValueError(f"trust_region must be in (0, 1], got {self.trust_region}")
        if not self.recycle_gradient and self.recycling == "none":
            raise ValueError("recycle_gradient=False needs a recycling policy (it recycles "
                             "the residual's images only)")
        if self.recycling_memory is not None and not self.recycling_memory > 0.0:
            raise ValueError(
                f"recycling_memory must be a positive number of GiB, got {self.recycling_memory}"
            )
        if self.averaging not in AVERAGING:
            raise ValueError(f"averaging must be one of {AVERAGING}, got {self.averaging!r}")
        if not 0.0 < self.averaging_decay < 1.0:
            raise ValueError(f"averaging_decay must be in (0, 1), got {self.averaging_decay}")
        if quasi_newton and (
            self.recycling != "none" or max(self.voxel_blocks) > 1
            or max(self.gradient_smoothing) > 0.0 or self.priors
        ):
            raise ValueError(
                "optimizer 'lbfgsb' recycles its own paths (period evaluations per window) "
                "and minimises the sample-average loss alone: leave recycling at 'none', "
                "voxel_blocks at 1, gradient_smoothing at 0 and no priors"
            )

    @property
    def averaging_decay_factor(self) -> float:
        """The iterate average's weight of the average so far at each iterate
        (:func:`~cloudct.retrieval.optimizers.add_to_average`): 1 for ``"uniform"``."""
        return 1.0 if self.averaging == "uniform" else self.averaging_decay

    @property
    def microphysical(self) -> bool:
        """Whether the unknowns are LWC and r_eff (:mod:`cloudct.retrieval.microphysics`)."""
        return self.unknowns == ("lwc", "reff")

    def _check_priors(self) -> None:
        """The prior terms act on the unknowns: extinction terms or r_eff terms."""
        terms = {**PRIORS, **REFF_PRIORS} if self.microphysical else PRIORS
        for p in self.priors:
            if p.term not in terms:
                raise ValueError(
                    f"prior {p.term} is a term in "
                    f"{'extinction' if p.term in PRIORS else 'r_eff'}; the unknowns "
                    f"{' '.join(self.unknowns)} take the terms {', '.join(terms)}")

    def _check_microphysics(self) -> None:
        """The settings the retrieval of LWC and r_eff supports (one line per refusal)."""
        what = "unknowns lwc reff"
        if not (self.lwc_step > 0.0 and self.reff_step > 0.0):
            raise ValueError(f"lwc_step and reff_step must be > 0, got {self.lwc_step} and "
                             f"{self.reff_step}")
        if not 0.0 <= self.extinction_share <= 1.0:
            raise ValueError(f"extinction_share must be in [0, 1], got {self.extinction_share}")
        refusals = (
            (self.recycling != "none", f"recycling {self.recycling!r}: path recycling is not "
             f"supported for the {what} yet; leave recycling at 'none'"),
            (self.optimizer == "lbfgsb", f"optimizer 'lbfgsb' is not supported for the {what};"
             " use adam or sgd"),
            (self.transmittance != "exponential", f"transmittance {self.transmittance!r} is not"
             f" supported for the {what}; leave it at 'exponential'"),
            (len(self.stages) > 1, f"{len(self.stages)} stages: the {what} are retrieved in "
             "one stage (one [[stage]] row) for now"),
            (self.photons == AUTO, f"photons 'auto' is not fitted to the device for the "
             f"{what} yet: give a count (--photons N)"),
            (self.max_change is not None, f"max_change bounds the extinction's step; the {what}"
             " have lwc_step and reff_step"),
        )
        for refused, why in refusals:
            if refused:
                raise ValueError(why)

    def _check_schedule(self) -> None:
        """The settings of :mod:`cloudct.retrieval.schedule`, each with its one-line error."""
        for name, choices in (("schedule", SCHEDULES), ("plateau", PLATEAU_ANSWERS)):
            if getattr(self, name) not in choices:
                raise ValueError(f"{name} must be one of {choices}, got "
                                 f"{getattr(self, name)!r}")
        if self.saturation_window < (5 if self.schedule == "noise" else 1):
            raise ValueError("saturation_window must be >= 1 (>= 5 for the noise test: a "
                             f"slope's t-test on fewer is powerless), got "
                             f"{self.saturation_window}")
        if not 0.0 < self.significance < 0.5:
            raise ValueError(f"significance must be in (0, 0.5), got {self.significance}")
        if not self.photon_growth > 1.0 or not self.photon_cap >= 1.0:
            raise ValueError(f"photon_growth must be > 1 and photon_cap >= 1, got "
                             f"{self.photon_growth} and {self.photon_cap}")
        if not 0.0 <= self.step_floor <= 1.0:
            raise ValueError(f"step_floor must be in [0, 1], got {self.step_floor}")
        if self.max_change is not None and not self.max_change > 0.0:
            raise ValueError(f"max_change must be > 0 (or unset), got {self.max_change}")

    def photons_at(self, stage: int, photons: int | None = None) -> tuple[int, int]:
        """Photons of an iteration at ``stage``: (images of the residual, gradient), for
        ``photons`` gradient paths at the finest stage (None: the configured count)."""
        photons = self.photons if photons is None else photons
        if photons == AUTO:
            raise ValueError("photons 'auto': the count is the run's (Retrieval.state.photons)")
        gradient = max(int(photons * self.stage_photons[stage]), 1)
        return max(int(round(gradient * self.image_photons[stage])), 1), gradient

    def recycling_bytes(self) -> float | None:
        """The path stores' memory budget in bytes (None: the recycler's default)."""
        return None if self.recycling_memory is None else self.recycling_memory * 2**30

    def policy(self):
        """The recycling policy of these settings (None without recycling)."""
        from cloudct.recycling.policy import AdaptiveESS, FixedPeriod

        if self.recycling == "fixed":
            return FixedPeriod(self.period)
        if self.recycling == "adaptive":
            return AdaptiveESS(min_fraction=self.min_ess, max_period=self.period)
        return None


#: The cut (degrees) of the phase functions' forward peak that a retrieval of a medium of
#: these cloud optics takes, where its settings name none and the medium records none: on
#: 2 cores the single cloud's Mie measurements are retrieved in 15 minutes to epsilon 0.56
#: with the peak cut at 3 degrees, 0.66-0.69 with the full peak (docs/benchmarks.md, "Mie
#: optics"; docs/optics.md, "Cutting the peak").
OPTICS_TRUNCATION = {"mie": 3.0}
#: The gradient estimator and the residual's images a retrieval takes, where its settings
#: name none, for a medium of these cloud optics traced with the full peak: with Mie optics
#: the combined estimator (forward photons and camera paths by multiple importance
#: sampling) has 5.9x the score function's gradient precision per second (sample matching's
#: gradient is mostly noise), and with its images too the single cloud's 15-minute retrieval
#: reaches epsilon 0.588 against 0.656 with the score function and forward images
#: (docs/benchmarks.md, "Mie optics"); path recycling replays its forward half. Where
#: lbfgsb replays stored paths, or a non-exponential transmittance is differentiated, the
#: score function and forward images, which those take. With the peak cut the defaults of
#: HG optics hold.
OPTICS_ESTIMATOR = {"mie": "combined"}
OPTICS_IMAGE_METHOD = {"mie": "combined"}


def settings_for_optics(settings: dict, optics: str, recorded_truncation: float = 0.0) -> dict:
    """``settings`` (:class:`RetrievalConfig`'s keyword arguments) for a medium of cloud
    ``optics`` whose phase functions are cut at ``recorded_truncation`` degrees (0: the
    full peak): with :data:`OPTICS_TRUNCATION`'s cut where they name no ``phase_truncation``
    and the medium records none, then, where the peak stays full, with
    :data:`OPTICS_ESTIMATOR`'s estimator at every stage where they name neither an
    estimator nor a pixel sampling (the score function where lbfgsb replays stored paths or
    the transmittance is the medium's), and :data:`OPTICS_IMAGE_METHOD`'s images where
    they name none and the optimizer is not lbfgsb; each default taken is said in one line
    of the ``cloudct`` log."""
    log = logging.getLogger("cloudct")
    out = dict(settings)
    cut = out.get("phase_truncation")
    if cut is None:
        cut = recorded_truncation
        if cut == 0.0 and optics in OPTICS_TRUNCATION:
            cut = out["phase_truncation"] = OPTICS_TRUNCATION[optics]
            log.info("phase truncation %g degrees: the medium has %s optics, whose forward "
                     "peak makes the gradient mostly noise; the retrieval's paths see it cut "
                     "(phase_truncation = 0 keeps it; docs/optics.md)", cut, optics)
    if cut > 0.0:
        return out
    quasi_newton = out.get("optimizer") == "lbfgsb"
    name = OPTICS_ESTIMATOR.get(optics)
    model = out.get("transmittance") == "medium"
    if name is not None and out.get("estimator") is None and out.get("pixel_sampling") is None:
        if quasi_newton or model:
            name = "score"
        stages = len(out.get("stages", RetrievalConfig.stages))
        out["estimator"] = (name,) * stages
        log.info("estimator %s: the medium has %s optics with the full forward peak, with "
                 "which sample matching's gradient is mostly noise (docs/benchmarks.md, "
                 "\"Mie optics\")", name, optics)
    method = OPTICS_IMAGE_METHOD.get(optics)
    if method is not None and out.get("image_method") is None and not quasi_newton:
        out["image_method"] = method
        log.info("image method %s: the medium has %s optics with the full forward peak, whose "
                 "forward images have fireflies (docs/benchmarks.md, \"Mie optics\")", method,
                 optics)
    return out
