"""Retrieval benchmark on the seed paper's single-cloud scene.

Scene: the bundled RICO cloud 32x37x26 (the ``cloudct render`` default: Mie extinction at
0.672 micron, air, open boundaries), or another medium given with ``--truth`` (e.g.
``benchmarks/scenes.py``'s), sun at zenith, the nine 76x76 cameras. Noise-free
measurements are rendered with ``--measurement-photons`` (cached in ``--work``), the
initial medium is the space-carved hull filled in the excess profile (``--profile
constant``: the seed paper's constant) at the fitted mean extinction
(:func:`cloudct.retrieval.carving.carve`), and the retrieval runs for ``--minutes`` of
iteration wall time (measurement synthesis and carving are not counted; the carving's wall
time is reported).

Reported (JSON at ``--output``): the settings, the machine and load average, the whole
per-iteration log (loss, epsilon, delta, cumulative seconds, compile seconds, stage,
resampling), and epsilon/delta at the time marks ``--marks`` (minutes of iteration wall time,
compiling included; the last iteration finished by then, with the seconds it spent compiling),
and the final medium's loss from fresh paths (``--final-loss-photons``, not timed): the
logged losses of recycled runs come from the stored paths the steps were fitted to, and a
single render's squared residual is biased by its variance, so runs are compared on
``final_loss_fresh``, 1/2 sum w (I_A - m)(I_B - m) over two independent renders A and B.
With ``--photon-budget`` (and a fixed ``--photons``) the run stops after the photons traced
reach the budget instead of after ``--minutes``: settings compared at equal compute, whatever
else the machine runs (the ablation of the priors, ``retrieval.priors``). ``--backend cuda``
runs everything on a GPU (with ``--photons auto``, the retrieval's default, the photons
follow the device). Usage::

    python -m benchmarks retrieval.single_cloud --minutes 60 [--recycling none|fixed|adaptive]
        [--photons 100000] [--step 2.0] [--voxel-blocks 4 2 1] [--output FILE.json]
        [--medium-output FILE.nc] [--start FILE.nc] [--truth FILE.nc] [--assume FILE.nc]
        [--backend cpu|cuda|auto]
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import numpy as np
import xarray as xr

from benchmarks.common import (
    RESULTS,
    SHELL_LOG,
    WORK,
    markdown_table,
    run_header,
    write_result,
)
from cloudct.cli.run_options import add_run_options, config_from_options
from cloudct.mc.backend import device_description
from cloudct.mc.render import default_method, render, single_cloud_medium
from cloudct.mc.scene import Scene
from cloudct.measurements import (
    coarse_measurements,
    load_measurements,
    save_measurements,
    synthesize_measurements,
)
from cloudct.medium import load_medium
from cloudct.optics import DEFAULT_OPTICS, optics_name
from cloudct.retrieval.carving import PROFILES, carve, initial_medium
from cloudct.retrieval.config import RetrievalConfig
from cloudct.retrieval.loop import Retrieval
from cloudct.retrieval.loss import cross_loss, pixel_weights


def measurements_for(truth, photons: int, work: Path, name: str = "single_cloud",
                     method: str | None = None, backend: str = "cpu"):
    """Noise-free measurements of the truth, rendered once (on ``backend``) and cached under
    ``name`` (and the render's ``method`` where it is not the forward estimator; None: the
    optics' default, :func:`cloudct.mc.render.default_method`: combined for Mie optics)."""
    method = method or default_method(truth)
    tag = "" if method == "forward" else f"{method}_"
    path = work / f"{name}_measurements_{tag}{photons}.nc"
    if path.exists():
        return load_measurements(path)
    work.mkdir(parents=True, exist_ok=True)
    measurements = synthesize_measurements(truth, photons=photons, seed=1, method=method,
                                           backend=backend)
    save_measurements(measurements, path, overwrite=True)
    return measurements


def truth_and_measurements(truth_file: str | None, photons: int, work: Path,
                           method: str | None = None, backend: str = "cpu"):
    """The true medium (``truth_file``, default the bundled single cloud) and its cached
    noise-free measurements (:func:`measurements_for`, named after the file)."""
    if truth_file is None:
        truth, name = single_cloud_medium(), "single_cloud"
    else:
        truth, name = load_medium(truth_file), Path(truth_file).stem
    return truth, measurements_for(truth, photons, work, name, method, backend)


def compiled_by(log: dict, iteration: int | None = None) -> float:
    """Seconds the run spent compiling kernels up to and including ``iteration`` (0-based;
    None: the whole run), from the log's ``compile_seconds`` (0 in logs without it)."""
    per_iteration = log.get("compile_seconds", [0.0])
    return float(np.sum(per_iteration if iteration is None else per_iteration[:iteration + 1]))


def at_marks(log: dict, marks_s: list[float]) -> dict:
    """epsilon, delta and loss of the last iteration finished by each time mark (and the
    epsilon and delta of the iterate average, where the run averages)."""
    seconds = np.asarray(log["seconds"])
    out = {}
    for mark in marks_s:
        done = np.nonzero(seconds <= mark)[0]
        key = f"{mark / 60:g}_min"
        if mark > seconds[-1] * 1.001 + 1.0 or done.size == 0:
            out[key] = None  # the run did not last that long
            continue
        i = int(done[-1])
        out[key] = {
            "iteration": i + 1, "seconds": float(seconds[i]),
            "compile_seconds": compiled_by(log, i),
            "epsilon": log["epsilon"][i],
            "delta": log["delta"][i], "loss": log["loss"][i],
            "epsilon_average": log["epsilon_average"][i],
            "delta_average": log["delta_average"][i],
            **{name: log[name][i] for name in SHELL_LOG if name in log},
        }
    return out


def fresh_loss(medium: xr.Dataset, data: xr.Dataset, photons: int, seed: int = 10**9,
               backend: str = "cpu") -> dict:
    """The loss of ``medium`` against the measurements ``data`` from two independent fresh
    renders A and B (seeds ``seed`` + 1 and + 2; paths no iteration used): the unbiased
    1/2 sum w (I_A - m)(I_B - m), and A's squared residual (what a fresh iteration logs)
    for comparison."""
    w = pixel_weights(data)
    m = data["radiance"].values
    a, b = (
        render(medium, Scene.from_dataset(data), photons=photons, seed=seed + k,
               backend=backend)["radiance"].values
        for k in (1, 2)
    )
    return {"photons": photons, "loss": cross_loss(a, b, m, w),
            "squared_residual": cross_loss(a, a, m, w)}


def run_config(args: argparse.Namespace, optics: str = DEFAULT_OPTICS) -> RetrievalConfig:
    """The retrieval settings a run with these options uses for a truth of cloud ``optics``
    (recorded as its ``config``): those of ``cloudct retrieve``, the optics' defaults
    included (:func:`~cloudct.retrieval.config.settings_for_optics`; until 2026-11-27 17:30
    the HG defaults whatever the optics: the Mie runs before then traced the full peak)."""
    return config_from_options(args, optics, seed=args.seed, time_limit=60.0 * args.minutes,
                               checkpoint_every=10**9)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--minutes", type=float, default=60.0)
    parser.add_argument("--marks", type=float, nargs="+", default=[15.0, 60.0])
    parser.add_argument("--measurement-photons", type=int, default=20_000_000)
    parser.add_argument("--measurement-method", choices=("forward", "combined"), default=None,
                        help="the measurements' render (default: combined with Mie optics, "
                        "else forward; runs before 2026-11-27 14:00 rendered forward)")
    parser.add_argument("--final-loss-photons", type=int, default=1_000_000,
                        help="photons of each of the two fresh renders of the final loss "
                             "(0: none)")
    add_run_options(parser, iterations=1_000_000, photons=100_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--backend", choices=("cpu", "cuda", "auto"), default="cpu",
                        help="where the measurements, the carving, the retrieval and the final "
                             "loss run (a new process compiles the kernels within its first "
                             "iterations: the log and the marks give that time apart)")
    parser.add_argument("--work", default=str(WORK))
    parser.add_argument("--output", default=str(RESULTS / "retrieval_single_cloud.json"))
    parser.add_argument("--medium-output", default=None,
                        help="also write the retrieved medium with its log (netCDF)")
    parser.add_argument("--profile", default="excess", choices=PROFILES,
                        help="shape of the carved start's extinction (cloudct.retrieval."
                             "carving.carve); the runs before 2026-11-22 05:00 used 'constant'")
    parser.add_argument("--truth", default=None,
                        help="the true medium (netCDF, e.g. from benchmarks/scenes.py; "
                             "default: the bundled single cloud), seen by the nine cameras "
                             "around its box")
    parser.add_argument("--assume", default=None,
                        help="a medium netCDF whose cloud optics the retrieval assumes (e.g. "
                             "the truth with HG optics, benchmarks/scenes.py): the carved "
                             "start takes its optics, the settings its defaults; default: the "
                             "truth's optics")
    parser.add_argument("--photon-budget", type=float, default=None,
                        help="stop after the iteration at which the photons traced (the "
                             "images' and the gradient's, as the log counts them) reach this "
                             "many: runs compared at equal compute whatever else the machine "
                             "runs (give --photons a count: auto follows the machine)")
    parser.add_argument("--start", default=None,
                        help="start from this medium netCDF (e.g. a --medium-output; its "
                             "cloud_mask is the hull) instead of the carved hull")
    args = parser.parse_args()
    if args.time_limit is not None:
        parser.error("the run's length is --minutes")

    t0 = time.perf_counter()
    truth, measurements = truth_and_measurements(
        args.truth, args.measurement_photons, Path(args.work), args.measurement_method,
        args.backend,
    )
    synth_s = time.perf_counter() - t0
    carving_s = None
    assumed = truth if args.assume is None else load_medium(args.assume)
    if args.start is None:
        t0 = time.perf_counter()
        initial = initial_medium(carve(measurements, assumed, profile=args.profile,
                                       backend=args.backend), assumed)
        mask, carving_s = None, time.perf_counter() - t0
    else:
        start = xr.load_dataset(args.start)
        initial = assumed.copy(deep=True)
        initial["cloud_extinction"].values = start["cloud_extinction"].values.copy()
        mask = start["cloud_mask"].values.astype(bool)
    config = run_config(args, optics_name(assumed))
    result = {
        **run_header(args),
        "measurement_photons": args.measurement_photons,
        "measurement_method": measurements.attrs.get("method", "forward"),
        "measurement_seconds": synth_s,
        "carving_seconds": carving_s,
        "start": args.start or f"carved hull, {args.profile} profile",
        "assumed_optics": optics_name(assumed),
        "config": {k: v for k, v in vars(config).items()},
    }
    run = Retrieval(measurements, initial, config, mask=mask, truth=truth,
                    backend=args.backend)
    result["device"] = device_description(run.backend)
    eps0 = run.state.extinction
    from cloudct.retrieval.metrics import epsilon_delta

    result["initial"] = dict(zip(("epsilon", "delta"), epsilon_delta(run.truth, eps0),
                                 strict=True))
    if args.photon_budget is None:
        retrieved = run.run(progress=True)
    else:  # as Retrieval.run, stopping at the budget
        while sum(run.state.log["photons"]) < args.photon_budget:
            run.step()
        retrieved = run.result()
    result["photon_budget"] = args.photon_budget
    if args.medium_output is not None:
        Path(args.medium_output).parent.mkdir(parents=True, exist_ok=True)
        retrieved.to_netcdf(args.medium_output)
    if args.final_loss_photons > 0:
        stage_data = coarse_measurements(measurements, run.config.stages[run.state.stage])
        result["final_loss_fresh"] = fresh_loss(run.medium(), stage_data,
                                                args.final_loss_photons, backend=run.backend)
    log = {k: [float(x) for x in v] for k, v in run.state.log.items()}
    result["log"] = log
    result["iterations"] = run.state.iteration
    result["decisions"] = run.state.decisions
    result["final"] = {"epsilon": log["epsilon"][-1], "delta": log["delta"][-1],
                       "loss": log["loss"][-1], "seconds": log["seconds"][-1],
                       "stage": log["stage"][-1]}
    result["marks"] = at_marks(log, [60.0 * m for m in args.marks])
    result["load_average_end"] = os.getloadavg()
    write_result(result, args.output, marks_markdown)


def marks_markdown(result: dict) -> str:
    """Epsilon, delta and the loss at the start, each time mark and the end, with epsilon's
    parts outside the true cloud and by optical distance from its lit and viewed boundary,
    as a table."""
    log = result["log"]
    shells = [name for name in SHELL_LOG if name in log]
    rows = [["start", "0", "", f"{result['initial']['epsilon']:.3f}",
             f"{result['initial']['delta']:+.3f}", "", "", *([""] * len(shells))]]
    final = {**result["final"], "iteration": result["iterations"],
             **{name: log[name][-1] for name in shells}, "epsilon_average": math.nan,
             "compile_seconds": compiled_by(log)}
    for mark, v in [*result["marks"].items(), ("end", final)]:
        if v is not None:
            rows.append([mark.replace("_", " "), str(v["iteration"]),
                         f"{v.get('compile_seconds', math.nan):.0f}", f"{v['epsilon']:.3f}",
                         f"{v['delta']:+.3f}", f"{v['loss']:.3g}",
                         f"{v['epsilon_average']:.3f}", *(f"{v[n]:.3f}" for n in shells)])
    fresh = result.get("final_loss_fresh")
    lines = markdown_table(["time", "iteration", "compiling so far [s]", "epsilon", "delta",
                            "loss",
                            "epsilon of the average",
                            *(n.removeprefix("epsilon_").replace("_", " ") for n in shells)],
                           rows)
    if fresh:
        lines += ["", f"Final loss from fresh paths: {fresh['loss']:.3g} "
                      f"({fresh['photons']} photons per render)."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
