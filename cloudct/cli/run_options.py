"""The options of a retrieval run on the command line (``cloudct retrieve`` and ``cloudct
demo``, and the retrieval benchmarks): their parser, and the settings they give, with a
``--config`` file and the command's defaults (:func:`run_settings`)."""

from __future__ import annotations

import argparse
from typing import Any

from cloudct.cli.options import add_phase_truncation_option
from cloudct.mc.gradient import ESTIMATORS
from cloudct.mc.pixel_sampling import PIXEL_SAMPLINGS
from cloudct.optics import DEFAULT_OPTICS
from cloudct.retrieval.config import (
    AUTO,
    AVERAGING,
    DEFAULT_MICROPHYSICS_PRIORS,
    DEFAULT_PRIORS,
    IMAGE_METHODS,
    LEGACY_SPARSITY,
    OPTIMIZERS,
    RECYCLING,
    TRANSMITTANCE,
    UNKNOWNS,
    RetrievalConfig,
    settings_for_optics,
)
from cloudct.retrieval.config_file import (
    STAGE_FIELDS,
    config_from_settings,
    legacy_priors,
    load_config,
)
from cloudct.retrieval.photon_budget import TARGET_SECONDS
from cloudct.retrieval.priors import (
    PRIOR_SCHEDULES,
    PRIORS,
    REFF_PRIORS,
    Prior,
    parse_prior,
    prior_text,
)
from cloudct.retrieval.schedule import PLATEAU_ANSWERS, SCHEDULES

#: Options of a run (argparse's dest) -> their :class:`RetrievalConfig` field.
OPTION_FIELDS = {dest: dest for dest in (
    "iterations", "photons", "optimizer", "step", "trust_region", "time_limit",
    "recycling", "period", "min_ess", "recycling_memory", "stages", "stage_photons",
    "voxel_blocks", "stage_steps", "gradient_smoothing", "image_photons", "saturation_window",
    "step_decay", "estimator", "pixel_sampling", "averaging", "averaging_decay", "seed",
    "checkpoint_every", "transmittance", "iteration_seconds", "schedule", "significance",
    "plateau", "photon_growth", "photon_cap", "step_floor", "max_change",
    "phase_truncation", "image_method", "unknowns", "lwc_step", "reff_step",
    "extinction_share", "hold_extinction",
)} | {"fresh_gradient": "recycle_gradient",  # --fresh-gradient: recycle_gradient = false
      "prior": "priors"}
OPTION_NAMES = {field: "--" + dest.replace("_", "-") for dest, field in OPTION_FIELDS.items()}


def given_options(args: argparse.Namespace) -> dict[str, Any]:
    """The :class:`RetrievalConfig` fields given on the command line (an option left out
    is None)."""
    given = {}
    for dest, field in OPTION_FIELDS.items():
        value = getattr(args, dest, None)
        if value is None:
            continue
        if dest == "fresh_gradient":
            value = not value
        if dest == "prior":  # "none" (None) gives no term
            value = [p for p in value if p is not None]
        given[field] = tuple(value) if isinstance(value, list) else value
    return given


def run_settings(args: argparse.Namespace) -> tuple[dict[str, Any], dict[str, str | None]]:
    """The settings of a run, later ones first: the options on the command line, the
    ``--config`` file, the command's defaults (its bundled configuration file, the
    iterations and photons of :func:`add_run_options`), RetrievalConfig's. Returns the
    settings and where those of the command line (None) and of --config (the file) came
    from."""
    settings: dict[str, Any] = {}
    if getattr(args, "defaults_file", None) is not None:
        settings.update(load_config(args.defaults_file))
    settings.update(getattr(args, "run_defaults", {}))
    origins: dict[str, str | None] = {}
    if getattr(args, "config", None) is not None:
        from_file = load_config(args.config, base=settings)
        settings.update(from_file)
        origins.update(dict.fromkeys(from_file, args.config))
    given = given_options(args)
    if "stages" in given:  # the file's other per-stage settings must fit the new stages
        misfits = [OPTION_NAMES[f] for f in STAGE_FIELDS if f not in given and origins.get(f)
                   and len(settings[f]) != len(given["stages"])]
        if misfits:
            raise ValueError(
                f"--stages gives {len(given['stages'])} stages and {args.config} "
                f"{len(settings['stages'])} [[stage]] rows: give {', '.join(misfits)} too, or "
                "edit the file's rows"
            )
    settings.update(given)
    origins.update(dict.fromkeys(given))
    weight, schedule = getattr(args, "sparsity", None), getattr(args, "sparsity_schedule", None)
    if (weight, schedule) != (None, None):  # the L1 term alone, as before the other terms
        if "priors" in given:
            raise ValueError("--sparsity and --sparsity-schedule give the L1 term alone (the "
                             "priors before the other terms): with --prior, write it there, "
                             "e.g. --prior l1=0.01")
        settings["priors"] = legacy_priors(
            LEGACY_SPARSITY if weight is None else weight, schedule or "noise")
        origins["priors"] = None
    return settings, origins


def config_from_options(args: argparse.Namespace, optics: str = DEFAULT_OPTICS,
                        **settings) -> RetrievalConfig:
    """The configuration of a run's options (:func:`add_run_options`, --config and the
    command's defaults, :func:`run_settings`) for a medium of cloud ``optics``
    (:func:`~cloudct.retrieval.config.settings_for_optics`); ``settings`` (other
    :class:`RetrievalConfig` fields) are added and take precedence."""
    return config_from_settings(settings_for_optics({**run_settings(args)[0], **settings},
                                                    optics))


def prior_option(text: str) -> Prior | None:
    """``--prior``: a term (:func:`~cloudct.retrieval.priors.parse_prior`), or ``none``."""
    if text == "none":
        return None
    try:
        return parse_prior(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(str(err)) from None


def photon_count(text: str) -> int | str:
    """``--photons``: a count, or ``auto``."""
    return AUTO if text == AUTO else int(text)


def add_run_options(p: argparse.ArgumentParser, iterations: int | None = None,
                    photons: int | str | None = None) -> None:
    """The options of a retrieval run (iterations, photons, optimiser, step, coarse-to-fine
    stages, recycling) with these defaults for ``--iterations`` and ``--photons`` (None:
    :class:`RetrievalConfig`'s, or the command's configuration file's); the others default
    to RetrievalConfig's. Every option defaults to None, so that :func:`given_options`
    tells those given on the command line."""
    c = RetrievalConfig
    p.set_defaults(run_defaults={k: v for k, v in (("iterations", iterations),
                                                   ("photons", photons)) if v is not None})
    p.add_argument("--iterations", type=int,
                   help=f"iterations in all (default {iterations or 'the configuration file'})")
    p.add_argument("--photons", type=photon_count,
                   help="gradient photons per iteration (the images': x --image-photons), or "
                        "auto: as many as fill --iteration-seconds on the device (default "
                        f"{photons or 'the configuration file'})")
    p.add_argument("--iteration-seconds", type=float,
                   help="--photons auto: the wall time an iteration aims at (default "
                        f"{TARGET_SECONDS['cpu']:g} on a CPU, {TARGET_SECONDS['cuda']:g} on a "
                        "GPU)")
    p.add_argument("--optimizer", choices=OPTIMIZERS,
                   help=f"adam, sgd, or lbfgsb (L-BFGS-B windows on recycled paths; default "
                        f"{c.optimizer})")
    p.add_argument("--step", type=float,
                   help=f"step size [1/km per iteration] (adam, sgd; default {c.step})")
    p.add_argument("--unknowns", nargs="+", choices=sorted({u for us in UNKNOWNS for u in us}),
                   help="what is retrieved: extinction (the default; one band, of a file with "
                        "several its 0.672 micron band), or lwc reff: liquid water content and "
                        "droplet effective radius from a file with several bands "
                        "(docs/retrieval_config.md, \"Liquid water and droplet size\")")
    p.add_argument("--lwc-step", type=float,
                   help="--unknowns lwc reff: the step in LWC [g m-3 per iteration] (default "
                        f"{c.lwc_step})")
    p.add_argument("--reff-step", type=float,
                   help="--unknowns lwc reff: the step in r_eff [micron per iteration] "
                        f"(default {c.reff_step})")
    p.add_argument("--extinction-share", type=float,
                   help="--unknowns lwc reff: the share of the run (its --time-limit, else "
                        "its iterations) first spent retrieving the extinction in the shortest "
                        f"band; 1: all of it, r_eff one fitted constant (default "
                        f"{c.extinction_share})")
    p.add_argument("--hold-extinction", action=argparse.BooleanOptionalAction, default=None,
                   help="--unknowns lwc reff: keep the first guess's extinction in the "
                        "shortest band and retrieve r_eff alone, LWC following it (default: "
                        "after an extinction stage, --extinction-share > 0)")
    p.add_argument("--trust-region", type=float,
                   help="lbfgsb: relative change of a voxel's extinction per window "
                        f"(default {c.trust_region})")
    p.add_argument("--prior", nargs="+", type=prior_option, metavar="TERM=WEIGHT[,...]",
                   help="the loss's prior terms, replacing the defaults: each "
                        "TERM=WEIGHT[,schedule=fixed|noise][,OPTION=VALUE...] with TERM one "
                        f"of {', '.join(PRIORS)} (in extinction; with --unknowns lwc reff in "
                        "e_0 LWC) or, with --unknowns lwc "
                        f"reff, {', '.join(REFF_PRIORS)} (in r_eff) (cloudct.retrieval.priors;"
                        " the loss gains WEIGHT x the loss of a dark medium x the term), or "
                        f"none (default {' '.join(prior_text(p) for p in DEFAULT_PRIORS)}; "
                        "none with lbfgsb; with --unknowns lwc reff "
                        f"{' '.join(prior_text(p) for p in DEFAULT_MICROPHYSICS_PRIORS)})")
    p.add_argument("--sparsity", type=float,
                   help="the L1 term alone at this weight [1/km^2] (0: no prior), as the runs "
                        "before the other terms had it; --prior l1=W,... combines terms")
    p.add_argument("--time-limit", type=float, help="stop after S seconds")
    p.add_argument("--recycling", choices=RECYCLING,
                   help=f"path recycling policy (seed paper Alg. 2; default {c.recycling})")
    p.add_argument("--period", type=int,
                   help="recycling period N_r (fixed) or maximum period (adaptive); lbfgsb: "
                        f"evaluations per window (default {c.period})")
    p.add_argument("--min-ess", type=float,
                   help="adaptive recycling: resample when the ESS fraction falls below this "
                        f"(default {c.min_ess})")
    p.add_argument("--recycling-memory", type=float, metavar="GIB",
                   help="memory for the two path stores [GiB] (default: camera connections "
                        "while a store fits 2 GiB, else voxel crossings); camera connections "
                        "replay fastest")
    p.add_argument("--fresh-gradient", action="store_true", default=None,
                   help="with --recycling: recycle only the residual's images and trace the "
                        "gradient's paths fresh every iteration")
    p.add_argument("--stages", type=int, nargs="+",
                   help="coarse-to-fine stages: pixel block sizes, coarse to fine (default "
                        f"{' '.join(map(str, c.stages))})")
    p.add_argument("--stage-photons", type=float, nargs="+",
                   help="per stage: photons per iteration as a multiple of --photons (default "
                        "1 at every stage)")
    p.add_argument("--voxel-blocks", type=int, nargs="+",
                   help="per stage: voxels tied in blocks of this size (default 1 at every "
                        "stage)")
    p.add_argument("--stage-steps", type=float, nargs="+",
                   help="per stage: the step as a multiple of --step (default 1 at every "
                        "stage)")
    p.add_argument("--gradient-smoothing", type=float, nargs="+",
                   help="per stage: Gaussian sigma [voxels] the gradient is smoothed with "
                        "inside the hull (default 1 at every stage, 0 with lbfgsb)")
    p.add_argument("--image-photons", type=float, nargs="+",
                   help="per stage: photons of the residual's images as a multiple of the "
                        "gradient's (default 2 at every stage, 1 with lbfgsb)")
    p.add_argument("--estimator", nargs="+", choices=tuple(ESTIMATORS),
                   help="per stage: the gradient estimator, "
                        + ", ".join(f"{e.name}: {e.title}" for e in ESTIMATORS.values())
                        + "; each traces --photons paths, on the workers of --workers or "
                        "--scheduler where given (default sm, or score with a recycled "
                        "gradient or lbfgsb)")
    p.add_argument("--pixel-sampling", choices=PIXEL_SAMPLINGS,
                   help="drt, sm: trace every pixel alike (uniform) or draw pixels in "
                        "proportion to |residual| (residual, the default)")
    p.add_argument("--averaging", choices=AVERAGING,
                   help="also keep an average of the iterates, restarted at every stage change "
                        "and step decay: uniform (Polyak-Ruppert) or ema (exponential moving "
                        "average); the result holds it as cloud_extinction_average and the log "
                        f"its epsilon and delta (default {c.averaging})")
    p.add_argument("--averaging-decay", type=float,
                   help="--averaging ema: weight of the average so far at each iterate "
                        f"(default {c.averaging_decay})")
    p.add_argument("--image-method", choices=IMAGE_METHODS,
                   help="the residual's images: forward photons, or combined: forward and "
                        "camera paths by multiple importance sampling, without the fireflies "
                        "of a full Mie peak (recycled: camera paths fresh; not with lbfgsb; "
                        "default forward)")
    add_phase_truncation_option(
        p, "the retrieval's medium",
        "as the initial medium records; a Mie medium that records none: 3 (said in the log)")
    p.add_argument("--transmittance", choices=TRANSMITTANCE,
                   help="the transmittance the retrieval assumes: exponential, or medium: the "
                        "model and mode field the measurements record (docs/transmittance.md;"
                        " differentiated by the score function or DRT, without recycling) "
                        f"(default {c.transmittance})")
    p.add_argument("--saturation-window", type=int,
                   help="iterations of the loss a plateau is judged on "
                        f"(default {c.saturation_window})")
    p.add_argument("--step-decay", type=float,
                   help="last stage: multiply the step by this at a plateau of the loss "
                        f"(default {c.step_decay})")
    p.add_argument("--schedule", choices=SCHEDULES,
                   help="how a plateau of the loss is found: noise (its decrease within its "
                        "Monte Carlo noise), threshold (less than 2 %% per window) or fixed "
                        f"(none: the step decays at fixed fractions of the run) (default "
                        f"{c.schedule})")
    p.add_argument("--significance", type=float,
                   help=f"--schedule noise: the test's false-alarm rate (default "
                        f"{c.significance})")
    p.add_argument("--plateau", choices=PLATEAU_ANSWERS,
                   help="the last stage's answer to a plateau: photons (x --photon-growth up "
                        "to --photon-cap, then the step) or step (default "
                        f"{c.plateau})")
    p.add_argument("--photon-growth", type=float,
                   help=f"--plateau photons: growth per plateau (default {c.photon_growth})")
    p.add_argument("--photon-cap", type=float,
                   help="--plateau photons: at most this x the count the run settled at "
                        f"(default {c.photon_cap})")
    p.add_argument("--step-floor", type=float,
                   help=f"the step never below this x its start (default {c.step_floor})")
    p.add_argument("--max-change", type=float,
                   help="per voxel and iteration, |change| <= this x (extinction + step) "
                        "(default: unbounded)")
    p.add_argument("--sparsity-schedule", choices=PRIOR_SCHEDULES,
                   help="the L1 term alone (at --sparsity, default "
                        f"{LEGACY_SPARSITY:g}) with its weight fixed, or noise: x the "
                        "gradient's noise over the stage's first iteration's")


def add_config_options(p: argparse.ArgumentParser) -> None:
    """``--config FILE`` and ``--write-config`` (docs/retrieval_config.md)."""
    p.add_argument("--config", metavar="FILE",
                   help="the run's settings from a TOML file (cloudct retrieve --write-config "
                        "writes one; a result or checkpoint netCDF gives its run's); options "
                        "given on the command line override it")
    p.add_argument("--write-config", action="store_true",
                   help="print the run's settings (the defaults, with --config and the "
                        "options given) as a commented TOML file and exit")
