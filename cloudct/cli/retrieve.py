"""``cloudct retrieve``, ``cloudct report`` and ``cloudct demo``: the retrieval, its report,
and the whole chain on a bundled cloud (the single cloud or the cloud field)."""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import xarray as xr

from cloudct.cli.options import (
    add_backend_option,
    add_distributed_options,
    add_optics_option,
    add_phase_truncation_option,
    chosen_backend,
    measured_optics,
    medium_from_options,
)
from cloudct.distributed import close_client, connect
from cloudct.les import bundled_single_cloud, seed_paper_cloud_field
from cloudct.mc.gradient import ESTIMATORS
from cloudct.mc.pixel_sampling import PIXEL_SAMPLINGS
from cloudct.mc.scene import build_scene
from cloudct.measurements import load_measurements, save_measurements, synthesize_measurements
from cloudct.medium import cell_edges, load_medium, save_medium
from cloudct.netcdf import load_netcdf, require_variables
from cloudct.optics import DEFAULT_OPTICS, optics_name, phase_truncation, to_optical
from cloudct.retrieval.carving import carve, initial_medium
from cloudct.retrieval.config import (
    AUTO,
    AVERAGING,
    IMAGE_METHODS,
    OPTIMIZERS,
    RECYCLING,
    SPARSITY,
    SPARSITY_SCHEDULES,
    TRANSMITTANCE,
    RetrievalConfig,
    settings_for_optics,
)
from cloudct.retrieval.config_file import (
    DEPENDENT,
    STAGE_FIELDS,
    ResumeConflict,
    config_from_settings,
    config_to_toml,
    load_config,
    resume_message,
    toml_value,
)
from cloudct.retrieval.loop import Retrieval
from cloudct.retrieval.photon_budget import TARGET_SECONDS, target_seconds
from cloudct.retrieval.report import write_report
from cloudct.retrieval.schedule import PLATEAU_ANSWERS, SCHEDULES


def _refuse_overwrite(path: Path, overwrite: bool) -> None:
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists (use --overwrite)")


def _initial_medium(
    measurements: xr.Dataset, init: str, template: str | None, optics: str | None,
    backend: str,
) -> xr.Dataset:
    """The starting medium: space carving of the measurements on the template's grid (with
    the measurements' optics unless ``optics`` is given; its fit renders on ``backend``), or
    a medium file."""
    if init != "carve":
        return load_medium(init)
    grid = medium_from_options(template, measured_optics(measurements, optics))
    return initial_medium(carve(measurements, grid, backend=backend), grid)


#: The demo's run settings (``cloudct demo``; ``cloudct retrieve --config`` reads it too).
DEMO_CONFIG = Path(__file__).resolve().parents[1] / "data" / "demo.toml"


class DemoScene(NamedTuple):
    """A scene of ``cloudct demo --scene``: its true medium (microphysical) and its run
    settings; the cameras are :func:`build_scene`'s preset of the same name."""

    medium: Callable[[], xr.Dataset]
    config: Path


#: ``cloudct demo --scene`` choices. The cloud field is a window of an LES domain, not the
#: periodic domain itself: it is rendered with open boundaries (the presets'), as the seed
#: paper's isolated cloud is.
DEMO_SCENES = {
    "single-cloud": DemoScene(bundled_single_cloud, DEMO_CONFIG),
    "cloud-field": DemoScene(seed_paper_cloud_field,
                             DEMO_CONFIG.with_name("demo_cloud_field.toml")),
}

#: Options of a run (argparse's dest) -> their :class:`RetrievalConfig` field.
OPTION_FIELDS = {dest: dest for dest in (
    "iterations", "photons", "optimizer", "step", "trust_region", "sparsity", "time_limit",
    "recycling", "period", "min_ess", "recycling_memory", "stages", "stage_photons",
    "voxel_blocks", "stage_steps", "gradient_smoothing", "image_photons", "saturation_window",
    "step_decay", "estimator", "pixel_sampling", "averaging", "averaging_decay", "seed",
    "checkpoint_every", "transmittance", "iteration_seconds", "schedule", "significance",
    "plateau", "photon_growth", "photon_cap", "step_floor", "max_change", "sparsity_schedule",
    "phase_truncation", "image_method",
)} | {"fresh_gradient": "recycle_gradient"}  # --fresh-gradient: recycle_gradient = false
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
    return settings, origins


def config_from_options(args: argparse.Namespace, optics: str = DEFAULT_OPTICS,
                        **settings) -> RetrievalConfig:
    """The configuration of a run's options (:func:`add_run_options`, --config and the
    command's defaults, :func:`run_settings`) for a medium of cloud ``optics``
    (:func:`~cloudct.retrieval.config.settings_for_optics`); ``settings`` (other
    :class:`RetrievalConfig` fields) are added and take precedence."""
    return config_from_settings(settings_for_optics({**run_settings(args)[0], **settings},
                                                    optics))


def _write_config(args: argparse.Namespace) -> int:
    """``--write-config``: the run's settings as a commented TOML file on stdout."""
    settings, _ = run_settings(args)
    config = config_from_settings(settings)
    unset = tuple(f for f in DEPENDENT if f not in settings)
    print(config_to_toml(
        config, comments=True, unset=unset,
        header=f"cloudct {args.command} --config FILE: the settings of a retrieval run; "
        "options given on the\ncommand line override the file's (docs/retrieval_config.md)",
    ), end="")
    return 0


def _resume_conflict(conflicts: dict, origins: dict[str, str | None]) -> str:
    """The message of settings asked of a resumed run that differ from the checkpoint's,
    each as the command line or the --config file gave it."""

    def shown(value: Any, origin: str | None) -> str:  # as the command line or a file has it
        if origin is not None:
            return toml_value(value)
        return " ".join(str(v) for v in value) if isinstance(value, tuple) else str(value)

    lines = {}
    for field, (asked, kept) in conflicts.items():
        origin = origins[field]
        if origin is None and field == "recycle_gradient":
            lines["--fresh-gradient"] = f"recycle_gradient = {toml_value(kept)}"
            continue
        if origin is None:
            label = f"{OPTION_NAMES[field]} {shown(asked, None)}"
        elif field in STAGE_FIELDS:
            label = f"{origin}'s [[stage]] {STAGE_FIELDS[field]} values {toml_value(asked)}"
        else:
            label = f"{origin}'s {field} = {toml_value(asked)}"
        lines[label] = shown(kept, origin)
    return resume_message(lines)


def _cli_retrieve(args: argparse.Namespace) -> int:
    if args.write_config:
        return _write_config(args)
    if args.measurements is None:
        raise ValueError("the measurement file is missing: cloudct retrieve MEASUREMENTS "
                         "(or --write-config)")
    output = Path(args.output)
    _refuse_overwrite(output, args.overwrite)
    settings, origins = run_settings(args)  # a bad --config file ends here, before any work
    if not args.resume:
        config_from_settings(settings)
    measurements = load_measurements(args.measurements)
    truth = load_medium(args.truth) if args.truth else None
    checkpoint = Path(args.checkpoint or output.with_suffix(".checkpoint.nc"))
    if not args.resume:
        _refuse_overwrite(checkpoint, args.overwrite)
    backend = chosen_backend(args)  # this process's; a scheduler's workers resolve theirs
    initial = _initial_medium(measurements, args.init, args.medium, args.optics, backend)
    client = connect(args.scheduler, args.workers, backend=backend)
    if client is not None:
        print(f"tracing on {client}")
    try:
        where = {"backend": args.backend if args.scheduler else backend, "client": client}
        if args.resume:
            asked = {field: settings[field] for field in origins}
            try:
                run = Retrieval.resume(checkpoint, measurements, initial, truth=truth,
                                       settings=asked, **where)
            except ResumeConflict as err:
                raise ValueError(_resume_conflict(err.conflicts, origins)) from None
        else:
            settings = settings_for_optics(settings, optics_name(initial),
                                           phase_truncation(initial))
            run = Retrieval(measurements, initial, config_from_settings(settings), truth=truth,
                            **where)
        result = run.run(checkpoint=checkpoint, progress=None)
    finally:
        if client is not None:
            close_client(client)
    result.to_netcdf(output)
    print(f"wrote {output} ({run.state.iteration} iterations, {run.state.elapsed:.0f} s); "
          f"checkpoint {checkpoint}")
    return 0


def _cli_report(args: argparse.Namespace) -> int:
    result = load_netcdf(args.result, "result")
    require_variables(result, ("cloud_extinction", "log_loss", "log_seconds"), "result",
                      args.result)
    truth = load_medium(args.truth) if args.truth else None
    measurements = load_measurements(args.measurements) if args.measurements else None
    backend = "cpu" if measurements is None else chosen_backend(args)  # the re-render's
    summary = write_report(result, args.output, truth=truth, measurements=measurements,
                           backend=backend)
    print(f"wrote {summary}")
    return 0


def _cli_demo(args: argparse.Namespace) -> int:
    """The whole chain on a bundled cloud: measurements, carving, retrieval, report."""
    demo = DEMO_SCENES[args.scene]
    args.defaults_file = demo.config
    if args.write_config:
        return _write_config(args)
    config = config_from_options(args, optics=args.optics or DEFAULT_OPTICS)
    out = Path(args.output)
    _refuse_overwrite(out / "result.nc", args.overwrite)
    out.mkdir(parents=True, exist_ok=True)
    backend = chosen_backend(args)
    start = time.perf_counter()
    truth = to_optical(demo.medium(), optics=args.optics or DEFAULT_OPTICS)
    lo, hi = (np.array([e[i] for e in cell_edges(truth)]) for i in (0, -1))
    scene = build_scene(lo, hi, preset=args.scene)
    print(f"{args.scene}: {' x '.join(map(str, truth['cloud_extinction'].shape))} voxels, "
          f"{len(scene.cameras)} views of {scene.cameras[0].nrows} x {scene.cameras[0].ncols}, "
          f"{scene.boundary} boundaries")
    print(f"1/4 synthesising measurements ({args.measurement_photons} photons) ...")
    measurements = synthesize_measurements(truth, scene, photons=args.measurement_photons,
                                           seed=1, backend=backend)
    save_measurements(measurements, out / "measurements.nc", overwrite=True)
    save_medium(truth, out / "truth.nc", overwrite=True)
    print("2/4 space carving ...")
    initial = initial_medium(carve(measurements, truth, backend=backend), truth)
    save_medium(initial, out / "init.nc", overwrite=True)
    each = (f"photons fitted to {target_seconds(config.iteration_seconds, backend):g} s "
            "per iteration"
            if config.photons == AUTO else f"{config.photons} photons each")
    print(f"3/4 retrieving ({config.iterations} iterations, {each}) ...")
    run = Retrieval(measurements, initial, config, truth=truth, backend=backend)
    result = run.run(checkpoint=out / "checkpoint.nc", progress=None)
    result.to_netcdf(out / "result.nc")
    print("4/4 report ...")
    summary = write_report(result, out / "report", truth=truth, measurements=measurements,
                           backend=backend)
    eps = float(result["log_epsilon"].values[-1])
    delta = float(result["log_delta"].values[-1])
    print(f"done in {time.perf_counter() - start:.0f} s: epsilon {eps:.1%}, delta {delta:+.1%}; "
          f"report {summary}")
    return 0


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
    p.add_argument("--trust-region", type=float,
                   help="lbfgsb: relative change of a voxel's extinction per window "
                        f"(default {c.trust_region})")
    p.add_argument("--sparsity", type=float,
                   help="weight of an L1 prior on the cloud extinction [1/km^2]: the loss "
                        "gains this x the loss of a dark medium x the cloud's extinction "
                        f"cross-section [km^2] (default {SPARSITY}, 0 with lbfgsb; 0: none)")
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
    p.add_argument("--sparsity-schedule", choices=SPARSITY_SCHEDULES,
                   help="the L1 prior's weight: fixed, or noise: x the gradient's noise "
                        f"over the stage's first iteration's (default {c.sparsity_schedule})")


def add_config_options(p: argparse.ArgumentParser) -> None:
    """``--config FILE`` and ``--write-config`` (docs/retrieval_config.md)."""
    p.add_argument("--config", metavar="FILE",
                   help="the run's settings from a TOML file (cloudct retrieve --write-config "
                        "writes one; a result or checkpoint netCDF gives its run's); options "
                        "given on the command line override it")
    p.add_argument("--write-config", action="store_true",
                   help="print the run's settings (the defaults, with --config and the "
                        "options given) as a commented TOML file and exit")


def register_cli(subparsers: argparse._SubParsersAction) -> None:
    """Add ``retrieve``, ``report`` and ``demo``."""
    r = subparsers.add_parser(
        "retrieve", help="retrieve a cloud's 3D extinction from multi-view measurements",
        description="Retrieve the cloud extinction from a measurement netCDF (cloudct synth). "
        "The run's settings come from the options, a --config file (options given override "
        "it) and the defaults, in that order.",
    )
    r.add_argument("measurements", nargs="?", help="measurement netCDF")
    r.add_argument("--init", default="carve", help="'carve' or an initial medium netCDF")
    r.add_argument("--medium", help="template medium for the grid and air (with --init carve)")
    r.add_argument("--truth", help="true medium netCDF: epsilon and delta are logged")
    r.add_argument("-o", "--output", default="result.nc")
    r.add_argument("--checkpoint", help="checkpoint file (default: OUTPUT.checkpoint.nc)")
    r.add_argument("--checkpoint-every", type=int,
                   help=f"iterations between checkpoints (default "
                        f"{RetrievalConfig.checkpoint_every})")
    r.add_argument("--resume", action="store_true",
                   help="continue from the checkpoint with its settings (--iterations and "
                        "--time-limit may change them; other settings given must equal them)")
    r.add_argument("--seed", type=int, help=f"default {RetrievalConfig.seed}")
    r.add_argument("--overwrite", action="store_true")
    add_config_options(r)
    add_run_options(r)
    add_optics_option(r, "With --init carve, the cloud optics of the template (default: the "
                      "measurements' recorded optics, else 'hg')")
    add_distributed_options(r)
    r.set_defaults(func=_cli_retrieve)

    p = subparsers.add_parser("report", help="figures and a summary of a retrieval result")
    p.add_argument("result", help="result netCDF from cloudct retrieve")
    p.add_argument("--truth", help="true medium netCDF")
    p.add_argument("--measurements", help="measurement netCDF (re-rendered images)")
    p.add_argument("-o", "--output", default="report")
    add_backend_option(p)
    p.set_defaults(func=_cli_report)

    d = subparsers.add_parser(
        "demo", help="the whole chain on a bundled cloud (the single cloud: about 10 minutes on "
        "2 CPU cores)",
        description="Synthesise measurements of a bundled cloud (noise-free, sun at the "
        "zenith, the nine cameras of the scene's preset of cloudct scene, open boundaries), "
        "carve, retrieve and report. --scene single-cloud (the default) is the seed paper's "
        "single cloud, rico32x37x26; its run's settings are the bundled "
        "cloudct/data/demo.toml: cloudct retrieve's defaults (one stage at 2x2 pixel "
        "blocks, gradient smoothed over 1 voxel, 2x photons for the residual's images, step "
        "0.5 /km, the L1 prior 0.01 falling with the gradient's noise, the gradient by sample "
        "matching from residual-drawn pixels, more photons and then a smaller step when the "
        "loss's decrease is within its noise, the iterates' moving average) for 60 "
        "iterations of about 5 s. --scene "
        "cloud-field is the seed paper's cloud field, the 79 x 84 x 27 window of the LES "
        "field rico122x106x39 holding the most cloudy cells, seen by nine 86 x 86 cameras; "
        "its settings are cloudct/data/demo_cloud_field.toml (the same defaults, 60 "
        "iterations of about 20 s on a CPU). cloudct demo --scene S "
        "--write-config prints a scene's settings.",
    )
    d.add_argument("-o", "--output", default="cloudct_demo", help="output directory")
    d.add_argument("--overwrite", action="store_true",
                   help="replace the results of an earlier demo in the output directory")
    d.add_argument("--scene", choices=DEMO_SCENES, default="single-cloud",
                   help="the cloud and its cameras: single-cloud (default) or cloud-field")
    d.add_argument("--measurement-photons", type=int, default=10_000_000,
                   help="photons of the synthetic measurements (default %(default)s)")
    add_optics_option(d, "Default: 'hg'")
    add_backend_option(d)
    add_config_options(d)
    add_run_options(d)
    d.set_defaults(func=_cli_demo)
