"""``cloudct retrieve``, ``cloudct report`` and ``cloudct demo``: the retrieval, its report,
and the whole chain on a bundled cloud (the single cloud or the cloud field)."""

from __future__ import annotations

import argparse
import shlex
import sys
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
    chosen_backend,
    measured_optics,
    medium_from_options,
    retrieval_measurements,
    say_memory,
)
from cloudct.cli.run_options import (
    OPTION_NAMES,
    add_config_options,
    add_run_options,
    config_from_options,
    run_settings,
)
from cloudct.distributed import close_client, connect
from cloudct.les import bundled_single_cloud, seed_paper_cloud_field
from cloudct.mc.scene import Scene, build_scene
from cloudct.measurements import (
    band_measurements,
    load_measurements,
    save_measurements,
    synthesize_measurements,
)
from cloudct.medium import cell_edges, load_medium, save_medium
from cloudct.netcdf import load_netcdf, require_variables, save_netcdf
from cloudct.optics import DEFAULT_OPTICS, optics_name, phase_truncation, to_optical
from cloudct.output_files import exclusive
from cloudct.physics.mie import DEFAULT_WAVELENGTH, mie_table
from cloudct.retrieval.carving import carve, initial_medium
from cloudct.retrieval.config import (
    AUTO,
    RetrievalConfig,
    settings_for_optics,
)
from cloudct.retrieval.config_file import (
    DEPENDENT,
    STAGE_FIELDS,
    ResumeConflict,
    config_from_settings,
    config_to_toml,
    resume_message,
    toml_value,
)
from cloudct.retrieval.loop import Retrieval
from cloudct.retrieval.loss import BATCHES
from cloudct.retrieval.microphysics import MicrophysicsRetrieval, retrieval_bands
from cloudct.retrieval.microphysics_first_guess import first_guess, stage_attrs
from cloudct.retrieval.microphysics_report import (
    RESULT_VARIABLES,
    is_microphysical_result,
    result_bands,
    true_fields,
    write_microphysics_report,
)
from cloudct.retrieval.photon_budget import target_seconds
from cloudct.retrieval.priors import Prior, prior_text
from cloudct.retrieval.report import write_report
from cloudct.retrieval.stopping import RunStopped
from cloudct.retrieval.warm_up import BackgroundWarmUp, tasks_for


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


def _compile_ahead(config: RetrievalConfig, backend: str, optics: str | None,
                   carving: bool) -> BackgroundWarmUp:
    """The run's kernels that the cache lacks, compiling in other processes while this one
    loads and carves (the forward render's, which the carving needs, compiles here)."""
    ahead = BackgroundWarmUp(tasks_for(config, carving), backend=backend,
                             optics=optics or DEFAULT_OPTICS)
    if ahead.tasks:
        print(f"compiling ahead, in other processes: {', '.join(ahead.tasks)}")
    return ahead


def _wait_for(ahead: BackgroundWarmUp) -> float:
    """Wait for :func:`_compile_ahead`'s processes before the first iteration; returns the
    seconds since they started (0 when none ran)."""
    seconds = ahead.wait()
    if ahead.tasks:
        print(f"compiled ahead in {seconds:.0f} s")
    return seconds


def _with_ahead(result: xr.Dataset, seconds: float) -> xr.Dataset:
    """``result`` with the seconds its kernels compiled ahead (attribute
    ``compile_ahead_s``: wall time beside the loading and carving, not the iterations')."""
    result.attrs["compile_ahead_s"] = float(seconds)
    return result


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
        if isinstance(value, tuple) and value and isinstance(value[0], Prior):
            return " ".join(prior_text(p) for p in value)
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
        elif field == "priors":
            label = f"{origin}'s [[prior]] rows {shown(asked, origin)}"
        else:
            label = f"{origin}'s {field} = {toml_value(asked)}"
        lines[label] = shown(kept, origin)
    return resume_message(lines)


def _retrieve(
    args: argparse.Namespace, settings: dict, origins: dict, measurements: xr.Dataset,
    truth: xr.Dataset | None, checkpoint: Path, backend: str, ahead: BackgroundWarmUp | None,
) -> tuple[Retrieval, xr.Dataset]:
    """``cloudct retrieve``'s run from its start (carved or read) or its checkpoint."""
    initial = _initial_medium(measurements, args.init, args.medium, args.optics, backend)
    say_memory("retrieve", initial, Scene.from_dataset(measurements), BATCHES, gradient=True)
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
        ahead_seconds = 0.0 if ahead is None else _wait_for(ahead)
        return run, _with_ahead(run.run(checkpoint=checkpoint, progress=None), ahead_seconds)
    finally:
        if client is not None:
            close_client(client)


def _stopped(stop: RunStopped, command: str, resume: list[str]) -> int:
    """The line of a run stopped by a signal, with the command that continues it, and the
    exit status of a process ended by that signal (128 + its number)."""
    print(f"cloudct {command}: {stop}; to go on from there: cloudct {shlex.join(resume)}",
          file=sys.stderr)
    return 128 + stop.signum


def _cli_retrieve(args: argparse.Namespace) -> int:
    if args.write_config:
        return _write_config(args)
    if args.measurements is None:
        raise ValueError("the measurement file is missing: cloudct retrieve MEASUREMENTS "
                         "(or --write-config)")
    output = Path(args.output)
    checkpoint = Path(args.checkpoint or output.with_suffix(".checkpoint.nc"))
    with exclusive(output), exclusive(checkpoint):  # a second run on them is refused
        return _retrieve_into(args, output, checkpoint)


def _retrieve_into(args: argparse.Namespace, output: Path, checkpoint: Path) -> int:
    """``cloudct retrieve`` with its output and checkpoint held."""
    _refuse_overwrite(output, args.overwrite)
    settings, origins = run_settings(args)  # a bad --config file ends here, before any work
    if tuple(settings.get("unknowns", RetrievalConfig.unknowns)) != RetrievalConfig.unknowns:
        return _retrieve_microphysics(args, settings, output)
    asked = None if args.resume else config_from_settings(settings)
    measurements = retrieval_measurements(args.measurements, "retrieve")
    truth = load_medium(args.truth) if args.truth else None
    if not args.resume:
        _refuse_overwrite(checkpoint, args.overwrite)
    backend = chosen_backend(args)  # this process's; a scheduler's workers resolve theirs
    ahead = None if asked is None or args.scheduler else _compile_ahead(
        asked, backend, measured_optics(measurements, args.optics), args.init == "carve")
    try:
        run, result = _retrieve(args, settings, origins, measurements, truth, checkpoint,
                                backend, ahead)
    except RunStopped as stop:
        again = args.argv if args.resume else [*args.argv, "--resume"]
        return _stopped(stop, "retrieve", again)
    finally:
        if ahead is not None:
            ahead.stop()
    save_netcdf(result, output, overwrite=True)  # refused before the run if not --overwrite
    compiling = np.nansum(run.state.log["compile_seconds"])
    print(f"wrote {output} ({run.state.iteration} iterations, {run.state.elapsed:.0f} s, "
          f"{compiling:.0f} s of it compiling); checkpoint {checkpoint}")
    return 0


def _retrieve_microphysics(args: argparse.Namespace, settings: dict, output: Path) -> int:
    """``cloudct retrieve --unknowns lwc reff``: LWC and r_eff from every band of the file
    (:mod:`cloudct.retrieval.microphysics`). ``--init carve`` carves the band at 0.672
    micron and turns its extinction into LWC at the r_eff with which the longest band
    renders as bright as measured (``brightness_reff``); ``--init FILE`` reads a
    microphysical medium. Checkpoints, resuming and Dask workers are refused."""
    what = "--unknowns lwc reff"
    if args.resume or args.checkpoint:
        raise ValueError(f"{'--resume' if args.resume else '--checkpoint'}: the retrieval of "
                         f"{what} writes no checkpoint yet, so it cannot resume; run it "
                         "whole (its result is written at the end)")
    if args.workers or args.scheduler:
        raise ValueError(f"{'--workers' if args.workers else '--scheduler'}: {what} traces "
                         "in this process only for now")
    config = config_from_settings(settings)
    measurements = load_measurements(args.measurements)
    retrieval_bands(measurements)  # several bands, before any carving
    truth = load_medium(args.truth) if args.truth else None
    backend = chosen_backend(args)
    attrs, mask = {}, None
    if args.init == "carve":
        red = band_measurements(measurements, DEFAULT_WAVELENGTH)
        grid = medium_from_options(args.medium, "mie")
        carved = initial_medium(carve(red, grid, backend=backend), grid)
        if config.extinction_share > 0.0:
            print(f"retrieving the extinction at {DEFAULT_WAVELENGTH:g} micron first "
                  f"({config.extinction_share:.0%} of the run) ...")
        guess = first_guess(measurements, carved, config,
                            table=mie_table(wavelength=DEFAULT_WAVELENGTH), truth=truth,
                            backend=backend)
        print(f"first guess: the {'retrieved' if guess.extinction_result else 'carved'} "
              f"extinction as LWC at r_eff {guess.reff:.3g} micron (the "
              f"{max(retrieval_bands(measurements)):g} micron images' brightness)")
        initial, mask, config, attrs = guess.medium, guess.mask, guess.config, stage_attrs(guess)
    else:
        initial = load_medium(args.init)
    run = MicrophysicsRetrieval(measurements, initial, config, mask=mask, truth=truth,
                                backend=backend)
    result = run.run(progress=None).assign_attrs(attrs)
    save_netcdf(result, output, overwrite=True)  # refused before the run if not --overwrite
    print(f"wrote {output} (lwc and reff, {run.state.iteration} iterations, "
          f"{run.state.elapsed:.0f} s)")
    return 0


def _cli_report(args: argparse.Namespace) -> int:
    result = load_netcdf(args.result, "result")
    if is_microphysical_result(result):
        return _report_microphysics(args, result)
    require_variables(result, ("cloud_extinction", "log_loss", "log_seconds"), "result",
                      args.result)
    truth = load_medium(args.truth) if args.truth else None
    if truth is not None and "cloud_extinction" not in truth:
        raise ValueError(f"the result {args.result} is a cloud extinction; the true medium "
                         f"{args.truth} holds none (lwc and reff): give the optical medium")
    measurements = (retrieval_measurements(args.measurements, "report")
                    if args.measurements else None)
    backend = "cpu" if measurements is None else chosen_backend(args)  # the re-render's
    summary = write_report(result, args.output, truth=truth, measurements=measurements,
                           backend=backend)
    print(f"wrote {summary}")
    return 0


def _report_microphysics(args: argparse.Namespace, result: xr.Dataset) -> int:
    """``cloudct report`` of a result of LWC and r_eff (``--unknowns lwc reff``): its
    truth must be microphysical and its measurements hold the result's bands."""
    require_variables(result, RESULT_VARIABLES, "result", args.result)
    truth = measurements = None
    if args.truth:
        truth = load_medium(args.truth)
        try:
            true_fields(result, truth)
        except ValueError as err:
            raise ValueError(f"--truth {args.truth}: {err}") from None
    if args.measurements:
        measurements = load_measurements(args.measurements)
        try:
            result_bands(result, measurements)
        except ValueError as err:
            raise ValueError(f"measurement file {args.measurements}: {err}") from None
    backend = "cpu" if measurements is None else chosen_backend(args)  # the re-render's
    summary = write_microphysics_report(result, args.output, truth=truth,
                                        measurements=measurements, backend=backend)
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
    with exclusive(out / "result.nc"):  # a second demo into the same folder is refused
        return _demo_into(args, demo, config, out)


def _demo_into(args: argparse.Namespace, demo: DemoScene, config: RetrievalConfig,
               out: Path) -> int:
    """``cloudct demo`` with its output folder held."""
    backend = chosen_backend(args)
    start = time.perf_counter()
    ahead = _compile_ahead(config, backend, args.optics, carving=True)
    try:
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
        say_memory("retrieve", initial, scene, BATCHES, gradient=True)
        each = (f"photons fitted to {target_seconds(config.iteration_seconds, backend):g} s "
                "per iteration"
                if config.photons == AUTO else f"{config.photons} photons each")
        print(f"3/4 retrieving ({config.iterations} iterations, {each}) ...")
        run = Retrieval(measurements, initial, config, truth=truth, backend=backend)
        ahead_seconds = _wait_for(ahead)
        result = _with_ahead(run.run(checkpoint=out / "checkpoint.nc", progress=None),
                             ahead_seconds)
        save_netcdf(result, out / "result.nc", overwrite=True)
    except RunStopped as stop:  # the retrieval goes on as cloudct retrieve, then the report
        files = {name: str(out / name) for name in ("measurements.nc", "init.nc", "truth.nc",
                                                    "checkpoint.nc", "result.nc")}
        return _stopped(stop, "demo", [
            "retrieve", files["measurements.nc"], "--init", files["init.nc"], "--truth",
            files["truth.nc"], "--checkpoint", files["checkpoint.nc"], "-o",
            files["result.nc"], "--backend", backend, "--resume"])
    finally:
        ahead.stop()
    print("4/4 report ...")
    summary = write_report(result, out / "report", truth=truth, measurements=measurements,
                           backend=backend)
    eps = float(result["log_epsilon"].values[-1])
    delta = float(result["log_delta"].values[-1])
    print(f"done in {time.perf_counter() - start:.0f} s: epsilon {eps:.1%}, delta {delta:+.1%}; "
          f"report {summary}")
    return 0


def register_cli(subparsers: argparse._SubParsersAction) -> None:
    """Add ``retrieve``, ``report`` and ``demo``."""
    r = subparsers.add_parser(
        "retrieve", help="retrieve a cloud's 3D extinction from multi-view measurements",
        description="Retrieve the cloud extinction from a measurement netCDF (cloudct synth). "
        "The run's settings come from the options, a --config file (options given override "
        "it) and the defaults, in that order.",
    )
    r.add_argument("measurements", nargs="?", help="measurement netCDF; of a file with several "
                   "bands, its 0.672 micron band (--unknowns lwc reff: every band)")
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
    p.add_argument("result", help="result netCDF from cloudct retrieve (the extinction, or "
                   "LWC and r_eff of --unknowns lwc reff)")
    p.add_argument("--truth", help="true medium netCDF (of LWC and r_eff: a microphysical "
                   "one)")
    p.add_argument("--measurements", help="measurement netCDF (re-rendered images; of a file "
                   "with several bands, its 0.672 micron band; of LWC and r_eff: the "
                   "result's bands, each rendered with its Mie table)")
    p.add_argument("-o", "--output", default="report")
    add_backend_option(p)
    p.set_defaults(func=_cli_report)

    d = subparsers.add_parser(
        "demo", help="the whole chain on a bundled cloud (the single cloud: about 25 minutes on "
        "2 CPU cores)",
        description="Synthesise measurements of a bundled cloud (noise-free, sun at the "
        "zenith, the nine cameras of the scene's preset of cloudct scene, open boundaries), "
        "carve, retrieve and report. --scene single-cloud (the default) is the seed paper's "
        "single cloud, rico32x37x26; its run's settings are the bundled "
        "cloudct/data/demo.toml: cloudct retrieve's defaults (one stage at 2x2 pixel "
        "blocks, gradient smoothed over 1 voxel, 2x photons for the residual's images, step "
        "0.5 /km, the priors L1 and total variation falling with the gradient's noise, the "
        "gradient by sample matching from residual-drawn pixels, more photons and then a "
        "smaller step when the loss's decrease is within its noise, the iterates' moving "
        "average) for 120 iterations, 5 s each at first. --scene "
        "cloud-field is the seed paper's cloud field, the 79 x 84 x 27 window of the LES "
        "field rico122x106x39 holding the most cloudy cells, seen by nine 86 x 86 cameras; "
        "its settings are cloudct/data/demo_cloud_field.toml (the same defaults, 120 "
        "iterations). cloudct demo --scene S "
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
