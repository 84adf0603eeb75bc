"""``cloudct retrieve``, ``cloudct report`` and ``cloudct demo``: the retrieval, its report,
and the whole chain on the bundled cloud."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import xarray as xr

from cloudct.cli.options import add_distributed_options
from cloudct.distributed import close_client, connect
from cloudct.mc.gradient import ESTIMATORS
from cloudct.mc.pixel_sampling import PIXEL_SAMPLINGS
from cloudct.mc.render import single_cloud_medium
from cloudct.measurements import load_measurements, save_measurements, synthesize_measurements
from cloudct.medium import load_medium, save_medium
from cloudct.netcdf import load_netcdf, require_variables
from cloudct.retrieval.carving import carve, initial_medium
from cloudct.retrieval.loop import (
    AVERAGING,
    OPTIMIZERS,
    RECYCLING,
    Retrieval,
    RetrievalConfig,
)
from cloudct.retrieval.report import write_report


def _refuse_overwrite(path: Path, overwrite: bool) -> None:
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists (use --overwrite)")


def _initial_medium(measurements: xr.Dataset, init: str, template: str | None) -> xr.Dataset:
    """The starting medium: space carving of the measurements, or a medium file."""
    if init != "carve":
        return load_medium(init)
    from cloudct.mc.render import single_cloud_medium
    from cloudct.retrieval.carving import carve, initial_medium

    grid = single_cloud_medium() if template is None else load_medium(template)
    return initial_medium(carve(measurements, grid), grid)


def config_from_options(args: argparse.Namespace, **settings) -> RetrievalConfig:
    """The run options of :func:`add_run_options` as a configuration; ``settings``
    (other :class:`RetrievalConfig` fields) are added and take precedence."""
    options = dict(
        iterations=args.iterations, photons=args.photons, optimizer=args.optimizer,
        step=args.step, trust_region=args.trust_region, sparsity=args.sparsity,
        time_limit=args.time_limit, recycling=args.recycling, period=args.period,
        min_ess=args.min_ess, recycling_memory=args.recycling_memory,
        recycle_gradient=not args.fresh_gradient,
        stages=args.stages, stage_photons=args.stage_photons, voxel_blocks=args.voxel_blocks,
        stage_steps=args.stage_steps, gradient_smoothing=args.gradient_smoothing,
        image_photons=args.image_photons,
        saturation_window=args.saturation_window, step_decay=args.step_decay,
        estimator=args.estimator, pixel_sampling=args.pixel_sampling,
        averaging=args.averaging, averaging_decay=args.averaging_decay,
    )
    return RetrievalConfig(**{**options, **settings})


def _cli_retrieve(args: argparse.Namespace) -> int:
    output = Path(args.output)
    _refuse_overwrite(output, args.overwrite)
    measurements = load_measurements(args.measurements)
    truth = load_medium(args.truth) if args.truth else None
    initial = _initial_medium(measurements, args.init, args.medium)
    checkpoint = Path(args.checkpoint or output.with_suffix(".checkpoint.nc"))
    if not args.resume:
        _refuse_overwrite(checkpoint, args.overwrite)
    client = connect(args.scheduler, args.workers, backend=args.backend)
    if client is not None:
        print(f"tracing on {client}")
    try:
        where = {"backend": args.backend, "client": client}
        if args.resume:
            run = Retrieval.resume(checkpoint, measurements, initial, truth=truth,
                                   iterations=args.iterations, **where)
        else:
            settings = dict(seed=args.seed, checkpoint_every=args.checkpoint_every)
            if client is not None and args.estimator is None:  # what the workers trace
                settings["estimator"] = ["score"] * len(args.stages)
            config = config_from_options(args, **settings)
            run = Retrieval(measurements, initial, config, truth=truth, **where)
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
    summary = write_report(result, args.output, truth=truth, measurements=measurements)
    print(f"wrote {summary}")
    return 0


def _cli_demo(args: argparse.Namespace) -> int:
    """The whole chain on the bundled single cloud: measurements, carving, retrieval, report."""
    out = Path(args.output)
    _refuse_overwrite(out / "result.nc", args.overwrite)
    out.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    truth = single_cloud_medium()
    print(f"1/4 synthesising measurements ({args.measurement_photons} photons) ...")
    measurements = synthesize_measurements(truth, photons=args.measurement_photons, seed=1)
    save_measurements(measurements, out / "measurements.nc", overwrite=True)
    save_medium(truth, out / "truth.nc", overwrite=True)
    print("2/4 space carving ...")
    initial = initial_medium(carve(measurements, truth), truth)
    save_medium(initial, out / "init.nc", overwrite=True)
    print(f"3/4 retrieving ({args.iterations} iterations, {args.photons} photons each) ...")
    run = Retrieval(measurements, initial, config_from_options(args), truth=truth)
    result = run.run(checkpoint=out / "checkpoint.nc", progress=None)
    result.to_netcdf(out / "result.nc")
    print("4/4 report ...")
    summary = write_report(result, out / "report", truth=truth, measurements=measurements)
    eps = float(result["log_epsilon"].values[-1])
    delta = float(result["log_delta"].values[-1])
    print(f"done in {time.perf_counter() - start:.0f} s: epsilon {eps:.1%}, delta {delta:+.1%}; "
          f"report {summary}")
    return 0


def add_run_options(p: argparse.ArgumentParser, iterations: int, photons: int) -> None:
    """The options of a retrieval run (iterations, photons, optimiser, step, coarse-to-fine
    stages, recycling) with these defaults for ``--iterations`` and ``--photons``; the others
    default to :class:`RetrievalConfig`'s."""
    p.add_argument("--iterations", type=int, default=iterations)
    p.add_argument("--photons", type=int, default=photons,
                   help="gradient photons per iteration (the images': x --image-photons)")
    p.add_argument("--optimizer", choices=OPTIMIZERS, default=RetrievalConfig.optimizer,
                   help="adam, sgd, or lbfgsb (L-BFGS-B windows on recycled paths)")
    p.add_argument("--step", type=float, default=RetrievalConfig.step,
                   help="step size [1/km per iteration] (adam, sgd)")
    p.add_argument("--trust-region", type=float, default=RetrievalConfig.trust_region,
                   help="lbfgsb: relative change of a voxel's extinction per window")
    p.add_argument("--sparsity", type=float, default=RetrievalConfig.sparsity,
                   help="weight of an L1 prior on the cloud extinction [1/km^2]: the loss "
                        "gains this x the loss of a dark medium x the cloud's extinction "
                        "cross-section [km^2] (0: none)")
    p.add_argument("--time-limit", type=float, default=None, help="stop after S seconds")
    p.add_argument("--recycling", choices=RECYCLING, default=RetrievalConfig.recycling,
                   help="path recycling policy (seed paper Alg. 2)")
    p.add_argument("--period", type=int, default=RetrievalConfig.period,
                   help="recycling period N_r (fixed) or maximum period (adaptive); lbfgsb: "
                        "evaluations per window")
    p.add_argument("--min-ess", type=float, default=RetrievalConfig.min_ess,
                   help="adaptive recycling: resample when the ESS fraction falls below this")
    p.add_argument("--recycling-memory", type=float, default=None, metavar="GIB",
                   help="memory for the two path stores [GiB] (default: camera connections "
                        "while a store fits 2 GiB, else voxel crossings); camera connections "
                        "replay fastest")
    p.add_argument("--fresh-gradient", action="store_true",
                   help="with --recycling: recycle only the residual's images and trace the "
                        "gradient's paths fresh every iteration")
    p.add_argument("--stages", type=int, nargs="+", default=list(RetrievalConfig.stages),
                   help="coarse-to-fine stages: pixel block sizes, coarse to fine")
    p.add_argument("--stage-photons", type=float, nargs="+", default=None,
                   help="per stage: photons per iteration as a multiple of --photons (default "
                        "%(default)s; None: 1 at every stage)")
    p.add_argument("--voxel-blocks", type=int, nargs="+", default=None,
                   help="per stage: voxels tied in blocks of this size (default %(default)s; "
                        "None: 1 at every stage)")
    p.add_argument("--stage-steps", type=float, nargs="+", default=None,
                   help="per stage: the step as a multiple of --step (default %(default)s; None: 1 "
                        "at every stage)")
    p.add_argument("--gradient-smoothing", type=float, nargs="+", default=None,
                   help="per stage: Gaussian sigma [voxels] the gradient is smoothed with "
                        "inside the hull (default %(default)s; None: 1 at every stage, 0 "
                        "with lbfgsb)")
    p.add_argument("--image-photons", type=float, nargs="+", default=None,
                   help="per stage: photons of the residual's images as a multiple of the "
                        "gradient's (default %(default)s; None: 4 at every stage, 1 with "
                        "lbfgsb)")
    p.add_argument("--estimator", nargs="+", choices=ESTIMATORS, default=None,
                   help="per stage: the gradient estimator, score (path score function, "
                        "forward photons), drt (differential ratio tracking) or sm (sample "
                        "matching), the last two tracing --photons camera paths on this "
                        "machine (default %(default)s: sm, or score with --workers or "
                        "--scheduler, a recycled gradient or lbfgsb)")
    p.add_argument("--pixel-sampling", choices=PIXEL_SAMPLINGS, default=None,
                   help="drt, sm: trace every pixel alike (uniform) or draw pixels in "
                        "proportion to |residual| (residual, the default)")
    p.add_argument("--averaging", choices=AVERAGING, default=RetrievalConfig.averaging,
                   help="also keep an average of the iterates, restarted at every stage change "
                        "and step decay: uniform (Polyak-Ruppert) or ema (exponential moving "
                        "average); the result holds it as cloud_extinction_average and the log "
                        "its epsilon and delta")
    p.add_argument("--averaging-decay", type=float, default=RetrievalConfig.averaging_decay,
                   help="--averaging ema: weight of the average so far at each iterate")
    p.add_argument("--saturation-window", type=int, default=RetrievalConfig.saturation_window,
                   help="iterations over which the loss must keep falling to stay in a stage")
    p.add_argument("--step-decay", type=float, default=RetrievalConfig.step_decay,
                   help="last stage: multiply the step by this when the loss saturates")


def register_cli(subparsers: argparse._SubParsersAction) -> None:
    """Add ``retrieve``, ``report`` and ``demo``."""
    r = subparsers.add_parser(
        "retrieve", help="retrieve a cloud's 3D extinction from multi-view measurements",
        description="Retrieve the cloud extinction from a measurement netCDF (cloudct synth).",
    )
    r.add_argument("measurements", help="measurement netCDF")
    r.add_argument("--init", default="carve", help="'carve' or an initial medium netCDF")
    r.add_argument("--medium", help="template medium for the grid and air (with --init carve)")
    r.add_argument("--truth", help="true medium netCDF: epsilon and delta are logged")
    r.add_argument("-o", "--output", default="result.nc")
    r.add_argument("--checkpoint", help="checkpoint file (default: OUTPUT.checkpoint.nc)")
    r.add_argument("--checkpoint-every", type=int, default=20)
    r.add_argument("--resume", action="store_true", help="continue from the checkpoint")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--overwrite", action="store_true")
    add_run_options(r, iterations=300, photons=100_000)
    add_distributed_options(r)
    r.set_defaults(func=_cli_retrieve)

    p = subparsers.add_parser("report", help="figures and a summary of a retrieval result")
    p.add_argument("result", help="result netCDF from cloudct retrieve")
    p.add_argument("--truth", help="true medium netCDF")
    p.add_argument("--measurements", help="measurement netCDF (re-rendered images)")
    p.add_argument("-o", "--output", default="report")
    p.set_defaults(func=_cli_report)

    d = subparsers.add_parser(
        "demo", help="the whole chain on the bundled single cloud (a few minutes)",
        description="Synthesise measurements of the bundled single cloud, carve, retrieve and "
        "report. The run's settings are those of the best measured single-cloud retrieval: "
        "cloudct retrieve's defaults (one stage at 2x2 pixel blocks, gradient smoothed over "
        "1 voxel, 4x photons for the residual's images, step 1 /km halved when the loss "
        "saturates, the gradient by sample matching from residual-drawn pixels) with the L1 "
        "prior --sparsity 0.01, and 60 iterations of 50,000 gradient paths.",
    )
    d.add_argument("-o", "--output", default="cloudct_demo", help="output directory")
    d.add_argument("--overwrite", action="store_true",
                   help="replace the results of an earlier demo in the output directory")
    d.add_argument("--measurement-photons", type=int, default=10_000_000)
    add_run_options(d, iterations=60, photons=50_000)
    d.set_defaults(func=_cli_demo, sparsity=0.01)  # measured on this cloud (benchmarks.md)
