"""Retrieval benchmark of liquid water content and droplet effective radius from several
bands (issue 53 item 4).

The retrieval is :class:`cloudct.retrieval.microphysics.MicrophysicsRetrieval`. Scenes
(``--scene``): ``single_cloud``, the bundled RICO cloud 32x37x26
(:func:`cloudct.les.bundled_single_cloud`, its LWC and r_eff); ``two_cumuli``, the two
cumuli of ``benchmarks/scenes.py`` (the same LES fields, clouds and cropping: the LWC and
r_eff that its optical medium keeps, made a microphysical medium again with the file's air;
the LES file is read from ``--les``). Both are seen by the single-cloud preset's nine 76x76
cameras around the medium's box (:func:`cloudct.mc.scene.single_cloud_scene_of`), sun at
the zenith, no ground (the scene's default, as ``cloudct synth``), open boundaries.

Measurements: each band of ``--bands`` (microns; 0.672 must be among them) is rendered
once with Mie optics (:func:`cloudct.measurement_bands.synthesize_bands`, each band's
:func:`cloudct.physics.mie.mie_table`) by ``--measurement-photons`` of the Mie optics'
default estimator (combined), noise-free, with a seed of its own (0.672: 1, 1.65: 2,
2.13: 3: band for band ``cloudct synth --bands 0.672 1.65 2.13 --seed 1``), and cached per
band in ``--work``; a band set is the stack of its cached bands
(:func:`cloudct.measurement_bands.stack_bands`), so the runs of the ablation fit the same
images of a band. The retrieval needs two bands or more (one band sees the extinction
alone and cannot tell LWC from r_eff: ``MicrophysicsRetrieval`` refuses it, and so does
this benchmark), so the ablation of the bands is ``--bands 0.672 1.65``, ``--bands 0.672
2.13`` and ``--bands 0.672 1.65 2.13``.

First guess: as ``cloudct retrieve --unknowns lwc reff --init carve``: the 0.672 micron
band carved (:func:`cloudct.retrieval.carving.carve`, then ``initial_medium``) on the grid
of the truth with Mie optics (for the single cloud the command's default template), its
extinction made LWC at the constant r_eff with which the longest band renders as bright as
measured (:func:`cloudct.retrieval.microphysics_first_guess.brightness_reff` and
``microphysical_first_guess``); the mask is where that LWC is positive (the retrieval's
default: the hull less its voxels of zero carved extinction). With ``--extinction-share``
the extinction is first retrieved from the 0.672 micron band for that share of
``--minutes`` (the carved hull the mask), and the marks count from the run's start, the
extinction stage included (its extinction epsilon is in ``carving.extinction_stage_log``).
The retrieval then runs with ``--photons`` gradient photons per band and iteration (2x as
many for each band's images, by ``--image-method``: the retrieval's default, forward, or
combined; 20,000 photons: about 14 s per iteration with three bands on the single cloud on
2 busy CPU cores), Adam steps ``--lwc-step`` [g m-3] and ``--reff-step`` [micron] and the
default r_eff prior for ``--minutes`` of iteration wall time (the first iteration's
compilation included; the synthesis and the carving are not counted and their wall times
are reported), the truth given so that every iteration logs LWC's epsilon and delta and
r_eff's mean absolute and relative errors over the true cloud and over its voxels within
optical distance 5 of the lit and viewed boundary (``_near``).

Reported (JSON at ``--output``, Markdown beside it): the run header and settings, the
retrieval's configuration, the first guess's errors, the whole per-iteration log (with
each band's loss) and the errors of the last iteration finished by each of ``--marks``
minutes. Usage::

    python -m benchmarks retrieval.microphysics --scene single_cloud|two_cumuli
        --bands 0.672 1.65 2.13 [--minutes 15] [--photons 20000] [--lwc-step 0.02]
        [--reff-step 0.5] [--prior TERM=WEIGHT[,...] ...] [--image-method forward|combined]
        [--extinction-share 0.75] [--hold-extinction]
        [--measurement-photons 2000000] [--threads N]
        [--output FILE.json] [--medium-output FILE.nc] [--work DIR]

(default output ``benchmarks/results/microphysics/SCENE_BANDS.json``, BANDS e.g.
``0.672+1.65+2.13``).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import xarray as xr

from benchmarks.common import RESULTS, WORK, markdown_table, run_header, write_result
from benchmarks.scenes import LES, two_cumuli
from cloudct.les import bundled_single_cloud, read_les
from cloudct.mc.gradient import ESTIMATORS
from cloudct.mc.render import default_method
from cloudct.mc.scene import single_cloud_scene_of
from cloudct.measurement_bands import stack_bands, synthesize_bands
from cloudct.measurements import band_measurements, load_measurements, save_measurements
from cloudct.medium import microphysical_medium
from cloudct.optics import to_optical
from cloudct.physics.mie import DEFAULT_WAVELENGTH, mie_table
from cloudct.retrieval.carving import carve, initial_medium
from cloudct.retrieval.config import RetrievalConfig
from cloudct.retrieval.microphysics import ERROR_FIELDS, MicrophysicsRetrieval
from cloudct.retrieval.microphysics_first_guess import FirstGuess, first_guess, stage_attrs
from cloudct.retrieval.priors import parse_prior
from cloudct.retrieval.schedule import SCHEDULES

#: The bands the benchmark knows [micron], each with its measurement seed.
BAND_SEEDS = {0.672: 1, 1.65: 2, 2.13: 3}
SCENES = ("single_cloud", "two_cumuli")
#: What each time mark and the start report: the log's errors against the truth.
ERRORS = ERROR_FIELDS


def two_cumuli_microphysics(les_file: Path) -> xr.Dataset:
    """The two cumuli of ``benchmarks/scenes.py`` as a microphysical medium: the LWC and
    r_eff its optical medium keeps (the LES's, the other clouds removed, cropped), with
    the LES file's air; checked to give the scene's extinction back."""
    optical = two_cumuli(read_les(les_file))
    medium = microphysical_medium(
        optical["x"].values, optical["y"].values, optical["z"].values,
        optical["lwc"].transpose("x", "y", "z").values,
        optical["reff"].transpose("x", "y", "z").values,
        z_bounds=optical["z_bounds"].values if "z_bounds" in optical else None,
        air_extinction=optical["air_extinction"], air_albedo=float(optical["air_albedo"]),
        air_extinction_wavelength=float(optical.attrs["air_extinction_wavelength"]),
        title=optical.attrs["title"],
        source=f"{optical.attrs['source']}; benchmarks/scenes.py two_cumuli, microphysical",
    )
    again = to_optical(medium, optics="hg")["cloud_extinction"].transpose("x", "y", "z")
    if not np.allclose(again.values, optical["cloud_extinction"].transpose("x", "y", "z")
                       .values, rtol=1e-12, atol=0.0):
        raise RuntimeError("the microphysical two cumuli do not give the scene's extinction")
    return medium


def truth_of(scene: str, les_file: Path) -> xr.Dataset:
    """The scene's true microphysical medium (module documentation)."""
    return bundled_single_cloud() if scene == "single_cloud" else two_cumuli_microphysics(
        les_file)


def band_name(bands: list[float]) -> str:
    """A band set as file names show it: ``0.672+1.65+2.13``."""
    return "+".join(f"{w:g}" for w in bands)


def measurements_for(truth: xr.Dataset, scene: str, bands: list[float], photons: int,
                     work: Path) -> tuple[xr.Dataset, float]:
    """The noise-free measurements of ``truth`` in ``bands`` (Mie optics, the nine
    cameras), each band rendered once and cached in ``work``, stacked into one set; and the
    seconds spent rendering the bands that were not cached."""
    scene_cameras = single_cloud_scene_of(truth)
    method = default_method(to_optical(truth, optics="mie"))
    seconds, sets = 0.0, []
    for w in bands:
        path = work / f"microphysics_{scene}_band{w:g}_{method}_{photons}.nc"
        if not path.exists():
            print(f"synthesising the {w:g} micron band ({photons} photons, {method}) ...",
                  flush=True)
            t0 = time.perf_counter()
            ds = synthesize_bands(truth, [w], scene_cameras, photons=photons,
                                  seed=BAND_SEEDS[w], optics="mie", method=method,
                                  progress=False)
            seconds += time.perf_counter() - t0
            work.mkdir(parents=True, exist_ok=True)
            save_measurements(band_measurements(ds, w), path, overwrite=True)
        sets.append(load_measurements(path))
    return stack_bands(sets), seconds


def carved_first_guess(measurements: xr.Dataset, truth: xr.Dataset, config: RetrievalConfig
                       ) -> tuple[FirstGuess, dict]:
    """``cloudct retrieve --unknowns lwc reff --init carve``'s first guess: the 0.672
    micron band carved on the truth's grid with Mie optics, with ``config.extinction_share``
    > 0 its extinction retrieved for that share of the run, the extinction made LWC at the
    r_eff with which the longest band renders as bright as measured
    (:func:`cloudct.retrieval.microphysics_first_guess.first_guess`); and what the carving,
    the extinction stage and the fit found (hull voxels, mean extinction, the stage's
    iterations, seconds and epsilon of the extinction, r_eff, seconds)."""
    t0 = time.perf_counter()
    red = band_measurements(measurements, DEFAULT_WAVELENGTH)
    grid = to_optical(truth, optics="mie")
    carved = carve(red, grid)
    initial = initial_medium(carved, grid)
    carving_seconds = time.perf_counter() - t0
    guess = first_guess(measurements, initial, config,
                        table=mie_table(wavelength=DEFAULT_WAVELENGTH), truth=truth,
                        progress=True)
    found = {"seconds": time.perf_counter() - t0, "carving_seconds": carving_seconds,
             "hull_voxels": int(carved["hull"].values.sum()),
             "extinction_estimate": float(carved.attrs["extinction_estimate"]),
             **stage_attrs(guess)}
    stage = guess.extinction_result
    if stage is not None:
        found["extinction_stage_log"] = {
            key: [float(x) for x in stage[f"log_{key}"].values]
            for key in ("seconds", "epsilon", "delta", "epsilon_average", "delta_average")}
    return guess, found


def run_config(args: argparse.Namespace) -> RetrievalConfig:
    """The retrieval settings of a run with these options (recorded as its ``config``)."""
    priors = None if args.prior is None else tuple(parse_prior(p) for p in args.prior)
    return RetrievalConfig(unknowns=("lwc", "reff"), photons=args.photons, priors=priors,
                           lwc_step=args.lwc_step, reff_step=args.reff_step,
                           iterations=args.iterations, time_limit=60.0 * args.minutes,
                           image_method=args.image_method, seed=args.seed,
                           schedule=args.schedule, extinction_share=args.extinction_share,
                           hold_extinction=args.hold_extinction, checkpoint_every=10**9,
                           estimator=args.estimator and (args.estimator,))


def at_marks(log: dict, marks_s: list[float], offset: float = 0.0) -> dict:
    """The errors and loss of the last iteration finished by each time mark (None where
    the run did not last that long or had not begun: its log's seconds start ``offset``
    seconds into the run, after the extinction stage)."""
    seconds = np.asarray(log["seconds"]) + offset
    out = {}
    for mark in marks_s:
        key = f"{mark / 60:g}_min"
        done = np.flatnonzero(seconds <= mark)
        if seconds.size == 0 or mark > seconds[-1] * 1.001 + 1.0 or done.size == 0:
            out[key] = None
            continue
        i = int(done[-1])
        out[key] = {"iteration": i + 1, "seconds": float(seconds[i]),
                    "loss": log["loss"][i], **{name: log[name][i] for name in ERRORS}}
    return out


def final_row(log: dict, initial: dict, offset: float) -> dict:
    """The errors and loss of the last iteration, ``offset`` seconds of extinction stage
    added to its time; without an iteration (``extinction_share`` 1) the start's errors,
    the iterate average's the same."""
    if not log["seconds"]:
        return {"iteration": 0, "seconds": offset, "loss": float("nan"), **initial,
                **{f"{k}_average": v for k, v in initial.items()}}
    return {"iteration": len(log["seconds"]), "seconds": log["seconds"][-1] + offset,
            "loss": log["loss"][-1], **{name: log[name][-1] for name in ERRORS}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scene", choices=SCENES, default="single_cloud")
    parser.add_argument("--bands", type=float, nargs="+", default=sorted(BAND_SEEDS),
                        help="wavelengths [micron], two or more of "
                             f"{' '.join(f'{w:g}' for w in BAND_SEEDS)}, 0.672 among them")
    parser.add_argument("--minutes", type=float, default=15.0,
                        help="iteration wall time (the retrieval's time_limit)")
    parser.add_argument("--iterations", type=int, default=1_000_000)
    parser.add_argument("--marks", type=float, nargs="+", default=[5.0, 10.0, 15.0, 30.0, 60.0],
                        help="minutes at which the errors are reported")
    parser.add_argument("--photons", type=int, default=20_000,
                        help="gradient photons per band and iteration (the images': 2x)")
    parser.add_argument("--lwc-step", type=float, default=RetrievalConfig.lwc_step,
                        help="Adam's step in LWC [g m-3 per iteration]")
    parser.add_argument("--reff-step", type=float, default=RetrievalConfig.reff_step,
                        help="Adam's step in r_eff [micron per iteration]")
    parser.add_argument("--prior", nargs="+", default=None,
                        help="prior terms as cloudct retrieve --prior writes them (default: "
                        "the retrieval's)")
    parser.add_argument("--image-method", choices=("forward", "combined"),
                        default=RetrievalConfig.image_method,
                        help="the estimator of each band's residual images (combined: no "
                             "fireflies of the Mie peak, more time per photon)")
    parser.add_argument("--estimator", choices=tuple(ESTIMATORS), default=None,
                        help="the estimator of the extinction's terms of the gradients (the "
                             "r_eff vertex terms stay the score function's; default: the "
                             "retrieval's, score)")
    parser.add_argument("--schedule", choices=SCHEDULES, default=RetrievalConfig.schedule,
                        help="the step and photon schedule (cloudct.retrieval.schedule)")
    parser.add_argument("--extinction-share", type=float,
                        default=RetrievalConfig.extinction_share,
                        help="the share of --minutes first spent retrieving the extinction "
                             "at 0.672 micron")
    parser.add_argument("--hold-extinction", action=argparse.BooleanOptionalAction,
                        default=RetrievalConfig.hold_extinction,
                        help="keep the first guess's extinction and retrieve r_eff alone")
    parser.add_argument("--measurement-photons", type=int, default=2_000_000,
                        help="photons of each band's measurements")
    parser.add_argument("--threads", type=int, default=None,
                        help="numba threads (default: numba's, one per core)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--les", default=str(LES / "rico122x106x39.txt"),
                        help="the LES file of --scene two_cumuli")
    parser.add_argument("--work", default=str(WORK),
                        help="where the measurements are cached")
    parser.add_argument("--output", "--out", default=None,
                        help="result JSON (Markdown beside it; default benchmarks/results/"
                             "microphysics/SCENE_BANDS.json)")
    parser.add_argument("--medium-output", default=None,
                        help="also write the retrieved medium with its log (netCDF)")
    args = parser.parse_args()
    args.bands = sorted(args.bands)
    unknown = [w for w in args.bands if w not in BAND_SEEDS]
    if unknown or len(set(args.bands)) < len(args.bands):
        parser.error(f"--bands: distinct values of {' '.join(f'{w:g}' for w in BAND_SEEDS)}")
    if len(args.bands) < 2 or DEFAULT_WAVELENGTH not in args.bands:
        parser.error("--bands: 0.672 and at least one more band (one band cannot tell LWC "
                     "from r_eff; the first guess carves the 0.672 band)")
    if args.output is None:
        args.output = str(RESULTS / "microphysics" / f"{args.scene}_{band_name(args.bands)}"
                          ".json")
    if args.threads is not None:
        import numba

        numba.set_num_threads(args.threads)

    truth = truth_of(args.scene, Path(args.les))
    measurements, synth_s = measurements_for(truth, args.scene, args.bands,
                                             args.measurement_photons, Path(args.work))
    asked = run_config(args)
    guess, carving = carved_first_guess(measurements, truth, asked)
    config = guess.config  # less the extinction stage's time
    t0 = time.perf_counter()
    tables = [mie_table(wavelength=w) for w in args.bands]
    tables_s = time.perf_counter() - t0
    result = {
        **run_header(args),
        "scene": args.scene,
        "bands": args.bands,
        "measurement_photons": args.measurement_photons,
        "measurement_method": str(measurements.attrs.get("method")),
        "measurement_seconds": synth_s,
        "mie_table_seconds": tables_s,
        "carving": carving,
        "start": "the 0.672 micron band's extinction (carved, or retrieved for "
                 "extinction_share of the run) as LWC at the brightness-fitted r_eff",
        "config": dict(vars(asked)),
        "config_after_extinction_stage": dict(vars(config)),
    }
    run = MicrophysicsRetrieval(measurements, guess.medium, config, mask=guess.mask,
                                truth=truth, mie_tables=tables)
    result["reff_range"] = list(run.reff_range)
    result["mask_voxels"] = int(run.mask.sum())
    result["true_cloud_voxels"] = int((run.truth[0] > 0).sum())
    result["initial"] = run.errors()
    retrieved = run.run(progress=True)
    if args.medium_output is not None:
        Path(args.medium_output).parent.mkdir(parents=True, exist_ok=True)
        retrieved.to_netcdf(args.medium_output)
    log = {k: [float(x) for x in v] for k, v in run.state.log.items()}
    log["band_loss"] = [[float(x) for x in losses] for losses in run.band_losses]
    seconds = np.diff(log["seconds"], prepend=0.0)
    result.update(
        log=log,
        iterations=run.state.iteration,
        decisions=run.state.decisions,
        first_iteration_seconds=float(seconds[0]) if seconds.size else None,
        median_iteration_seconds=float(np.median(seconds[1:])) if seconds.size > 1 else None,
        final=final_row(log, result["initial"], carving["extinction_stage_seconds"]),
        marks=at_marks(log, [60.0 * m for m in args.marks],
                       carving["extinction_stage_seconds"]),
        load_average_end=os.getloadavg(),
    )
    write_result(result, args.output, marks_markdown)


def marks_markdown(result: dict) -> str:
    """LWC's epsilon and delta and r_eff's errors (all and near the boundary) at the
    start, each time mark and the end, as a table."""
    start = {"iteration": 0, "seconds": 0.0, "loss": float("nan"), **result["initial"]}
    rows = []
    for name, v in [("start", start), *result["marks"].items(), ("end", result["final"])]:
        if v is None:
            continue
        for of in ("", "_average") if name != "start" else ("",):
            rows.append([name.replace("_", " ") + (" (average)" if of else ""),
                         str(v["iteration"]), f"{v['seconds']:.0f}",
                         f"{v['lwc_epsilon' + of]:.3f}", f"{v['lwc_delta' + of]:+.3f}",
                         f"{v['reff_absolute_error' + of]:.2f}",
                         f"{v['reff_relative_error' + of]:.3f}",
                         f"{v['reff_absolute_error_near' + of]:.2f}",
                         f"{v['reff_relative_error_near' + of]:.3f}", f"{v['loss']:.3g}"])
    table = markdown_table(["time", "iteration", "seconds", "LWC epsilon", "LWC delta",
                            "r_eff error [um]", "r_eff rel. error", "near: r_eff error [um]",
                            "near: rel. error", "loss"], rows)
    bands = ", ".join(f"{w:g}" for w in result["bands"])
    lines = [f"{result['scene']}, bands {bands} micron: {result['iterations']} iterations "
             f"(first {result['first_iteration_seconds'] or float('nan'):.1f} s, then median "
             f"{result['median_iteration_seconds'] or float('nan'):.1f} s each); carved hull "
             f"{result['carving']['hull_voxels']} voxels, first guess r_eff "
             f"{result['carving']['first_guess_reff']:.2f} micron, true cloud "
             f"{result['true_cloud_voxels']}.", *_stage_line(result["carving"]), "",
             *table]
    return "\n".join(lines) + "\n"


def _stage_line(carving: dict) -> list[str]:
    """A line on the extinction stage (none without one)."""
    stage = carving.get("extinction_stage_log")
    if not stage:
        return []
    return ["", f"Extinction stage (0.672 micron): {carving['extinction_stage_iterations']} "
            f"iterations in {carving['extinction_stage_seconds']:.0f} s, epsilon of the "
            f"extinction {stage['epsilon'][0]:.3f} -> {stage['epsilon'][-1]:.3f} (iterate "
            f"average {stage['epsilon_average'][-1]:.3f}, delta "
            f"{stage['delta_average'][-1]:+.3f}); the table's start is the retrieval of LWC "
            "and r_eff's, after it."]


if __name__ == "__main__":
    main()
