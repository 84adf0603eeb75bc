"""Entry where the clouds are: the forward render's efficiency against the cloud share m.

Forward photons enter the box through the sunlit faces' grid cells with probability
p_c = (1 - m) a_c + m a_c g_c / sum a g (g_c = 1 - exp(-tau_c) of the sun's ray from the
cell; :mod:`cloudct.mc.sun`), weighted by P a_c / p_c. This script renders, forward on the
CPU, at m = 0, 0.5 and 0.8 (``--shares``):

- ``single_cloud``: the seed paper's single cloud (:func:`cloudct.mc.render.
  single_cloud_medium`), nine 76 x 76 cameras (:func:`cloudct.mc.scene.single_cloud_scene`),
  sun at zenith, open boundaries;
- ``seed_field``: the seed paper's cloud field (:func:`cloudct.les.seed_paper_cloud_field`,
  79 x 84 x 27) with the ``cloud-field`` preset (nine 86 x 86 cameras), open boundaries,
  as ``cloudct retrieve demo --scene cloud-field``;
- ``whole_field``: the whole bundled field rico122x106x39 (:func:`cloudct.les.
  bundled_cloud_field`), periodic, the ``nadir`` preset (nine 128 x 128 cameras);

all with the single cloud's optics (Mie extinction at 0.672 micron, HG g = 0.85). For each
render: wall time, path vertices per photon, and the Monte Carlo efficiency 1 / (relative
variance x wall time) (``benchmarks/forward/single_cloud.py``'s definition), and the same with the
process's CPU time instead of the wall time (less sensitive to other work on a shared
machine). The relative variance is (standard error / radiance)^2 averaged over three pixel
sets: ``bright`` (radiance above 10% of the view's maximum: the project's efficiency),
``all`` (every pixel with radiance > 0) and ``cloudy`` (bright pixels whose central ray
crosses a cloud optical depth of at least 1). The radiance there, and in the pixel sets, is
the reference image: the average of the renders at all shares, which estimate the same
image (a render's own mean would put its noise in the denominator, and a pixel it missed
would divide by 0). Ratios are against m = 0; view-mean z-scores against m = 0 check that
the images agree (independent seeds).

The photon count is the same for every m of a scene: ``--seconds`` of tracing at the middle
share, from the photons per second of a short calibration render (``--photons`` fixes it).

Usage::

    python -m benchmarks forward.entry_sampling [--scenes single_cloud seed_field whole_field]
        [--shares 0 0.5 0.8] [--seconds 35] [--batches 32]
        [--output benchmarks/results/entry_sampling]
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np

from benchmarks.common import RESULTS, markdown_table, run_header, write_result
from benchmarks.forward.single_cloud import view_means
from cloudct.les import bundled_cloud_field, seed_paper_cloud_field
from cloudct.mc.cameras import camera_arrays
from cloudct.mc.render import render_batches, single_cloud_medium
from cloudct.mc.scene import build_scene, single_cloud_scene
from cloudct.medium import cell_edges
from cloudct.optics import to_optical
from cloudct.retrieval.cloudy_pixels import (
    cell_index,
    medium_bounds,
    pixel_rays,
    ray_box,
    ray_steps,
    wrapped_index,
)

#: Cloud optical depth along a pixel's central ray from which a bright pixel is cloudy.
CLOUDY_DEPTH = 1.0
#: Share at which the photon count is calibrated to ``--seconds``.
CALIBRATION_SHARE = 0.5


def scenes() -> dict:
    """name -> (medium, scene, description) of the three benchmark scenes."""
    out = {}
    single = single_cloud_medium()
    lo, hi = (np.array([e[i] for e in cell_edges(single)]) for i in (0, -1))
    out["single_cloud"] = (single, single_cloud_scene(lo, hi),
                           "single cloud 32x37x26, 9 cameras 76x76, sun at zenith, open")
    field = to_optical(seed_paper_cloud_field(), optics="hg")
    lo, hi = (np.array([e[i] for e in cell_edges(field)]) for i in (0, -1))
    out["seed_field"] = (field, build_scene(lo, hi, preset="cloud-field"),
                         "seed paper cloud field 79x84x27, preset cloud-field (9 x 86x86), "
                         "sun at zenith, open")
    whole = to_optical(bundled_cloud_field(), optics="hg")
    lo, hi = (np.array([e[i] for e in cell_edges(whole)]) for i in (0, -1))
    out["whole_field"] = (whole, build_scene(lo, hi, preset="nadir", boundary="periodic"),
                          "whole field rico122x106x39, preset nadir (9 x 128x128), sun at "
                          "zenith, periodic")
    return out


def cloud_depth_of_pixels(medium, scene) -> np.ndarray:
    """Cloud optical depth along each pixel's central ray through the medium (with periodic
    boundaries, through the slab, the field repeated), float64[view, row, col]."""
    edges = cell_edges(medium)
    cloud = medium["cloud_extinction"].values
    cams = camera_arrays(scene.cameras, 0.0)
    lo, hi = medium_bounds(scene, edges)
    step = 0.25 * min(float(np.diff(e).min()) for e in edges)
    depth = np.zeros((len(scene.cameras), cams.nrows, cams.ncols))
    for view in range(len(scene.cameras)):
        origin = cams.position[view]
        rays = pixel_rays(cams, view)[:, :, 0, :]
        t_in, t_out = ray_box(origin, rays, lo, hi)
        tau = np.zeros(t_in.shape)
        for live, t, length in ray_steps(t_in, t_out, step):
            point = origin + t[:, None] * rays[live]
            index = [wrapped_index(edges[a], point[:, a]) if scene.periodic and a < 2
                     else cell_index(edges[a], point[:, a]) for a in range(3)]
            tau[live] += cloud[index[0], index[1], index[2]] * length
        depth[view] = tau
    return depth


def pixel_sets(mean: np.ndarray, cloud_depth: np.ndarray) -> dict[str, np.ndarray]:
    """The pixel masks over which the relative variance is averaged."""
    bright = mean > 0.1 * mean.max(axis=(1, 2), keepdims=True)
    return {"bright": bright, "all": mean > 0.0,
            "cloudy": bright & (cloud_depth >= CLOUDY_DEPTH)}


def measure(medium, scene, share: float, photons: int, batches: int,
            seed: int) -> tuple[dict, np.ndarray, np.ndarray]:
    """One timed render at cloud share ``share``: its numbers, mean image and variance of
    the mean."""
    load = os.getloadavg()
    cpu = time.process_time()
    b, info = render_batches(medium, scene, photons=photons, batches=batches, seed=seed,
                             progress=False, entry_cloud_share=share)
    vm, vse = view_means(b)
    result = {"entry_cloud_share": share, "applied_share": info["entry_cloud_share"],
              "photons": info["photons"], "seed": seed, "wall_s": info["wall_time"],
              "cpu_s": time.process_time() - cpu,
              "vertices_per_photon": info["events"] / info["photons"],
              "load_average_before": load, "view_mean": vm.tolist(),
              "view_mean_se": vse.tolist()}
    return result, b.mean(axis=0), b.var(axis=0, ddof=1) / batches


def run_scene(name: str, medium, scene, args) -> dict:
    """The renders of one scene at every share, with their efficiencies over the pixel sets
    of the reference image (the average of the renders) and ratios against m = 0."""
    render_batches(medium, scene, photons=args.batches * 4, batches=args.batches,
                   progress=False, entry_cloud_share=CALIBRATION_SHARE)  # JIT warm-up
    photons = args.photons
    if photons is None:
        probe = args.batches * 2000
        _, info = render_batches(medium, scene, photons=probe, batches=args.batches,
                                 progress=False, entry_cloud_share=CALIBRATION_SHARE)
        photons = args.batches * max(1, round(args.seconds * probe / info["wall_time"]
                                              / args.batches))
    runs = []
    for i, share in enumerate(args.shares):
        print(f"{name}: m = {share}, {photons:,} photons ...", flush=True)
        runs.append(measure(medium, scene, share, photons, args.batches, args.seed + i))
    # every share estimates the same image: their average is the reference radiance
    reference = np.mean([mean for _, mean, _ in runs], axis=0)
    masks = pixel_sets(reference, cloud_depth_of_pixels(medium, scene))
    for result, _, var in runs:
        for key, mask in masks.items():
            rv = float(np.mean(var[mask] / reference[mask] ** 2))
            result[f"pixels_{key}"] = int(mask.sum())
            result[f"relative_variance_{key}"] = rv
            result[f"efficiency_{key}"] = 1.0 / (rv * result["wall_s"])
            result[f"efficiency_cpu_{key}"] = 1.0 / (rv * result["cpu_s"])
    base = runs[0][0]
    for result, _, _ in runs:
        for key in masks:
            result[f"efficiency_ratio_{key}"] = (result[f"efficiency_{key}"]
                                                 / base[f"efficiency_{key}"])
            result[f"efficiency_ratio_cpu_{key}"] = (result[f"efficiency_cpu_{key}"]
                                                     / base[f"efficiency_cpu_{key}"])
            result[f"variance_ratio_{key}"] = (base[f"relative_variance_{key}"]
                                               / result[f"relative_variance_{key}"])
        result["wall_ratio"] = result["wall_s"] / base["wall_s"]
        result["view_mean_z"] = ((np.array(result["view_mean"]) - base["view_mean"])
                                 / np.hypot(result["view_mean_se"], base["view_mean_se"])
                                 ).tolist()
    return {"photons": photons, "cloudy_depth": CLOUDY_DEPTH,
            "runs": [result for result, _, _ in runs]}


def ratios(run: dict, key: str) -> str:
    """The efficiency ratios of a pixel set by wall time and by CPU time, as a cell."""
    return f"{run[f'efficiency_ratio_{key}']:.2f}, {run[f'efficiency_ratio_cpu_{key}']:.2f}"


def markdown(result: dict) -> str:
    lines = ["# Entry where the clouds are: forward efficiency against the cloud share m", "",
             f"{result['date']}, {result['machine']}, numba threads {result['numba_threads']}, "
             f"load average {', '.join(f'{x:.2f}' for x in result['load_average_start'])} "
             f"(start), {', '.join(f'{x:.2f}' for x in result['load_average_end'])} (end)",
             "", f"`{result['command']}`", ""]
    header = ["m", "photons", "wall s", "CPU s", "vertices / photon", "rel. error (bright)",
              "variance ratio bright", "eff. ratio bright (wall, CPU)",
              "variance ratio cloudy", "eff. ratio cloudy (wall, CPU)",
              "eff. ratio all (wall, CPU)", "max abs view-mean z"]
    for name, scene in result["scenes"].items():
        rows = [[f"{r['entry_cloud_share']:g}", f"{r['photons']:,}", f"{r['wall_s']:.1f}",
                 f"{r['cpu_s']:.1f}", f"{r['vertices_per_photon']:.2f}",
                 f"{math.sqrt(r['relative_variance_bright']):.4f}",
                 f"{r['variance_ratio_bright']:.2f}", ratios(r, "bright"),
                 f"{r['variance_ratio_cloudy']:.2f}", ratios(r, "cloudy"), ratios(r, "all"),
                 f"{np.max(np.abs(r['view_mean_z'])):.2f}"] for r in scene["runs"]]
        pixels = scene["runs"][0]
        lines += [f"## {name}: {scene['description']}", "",
                  f"pixels: bright {pixels['pixels_bright']:,}, all {pixels['pixels_all']:,}, "
                  f"cloudy {pixels['pixels_cloudy']:,}", "",
                  *markdown_table(header, rows), ""]
    lines += ["efficiency = 1 / (relative variance x wall time), the relative variance "
              "(standard error / radiance)^2 averaged over the pixels of a set, radiance and "
              "sets from the reference image (the average of the renders at all m): bright "
              "(above 10% of the view's maximum), all (radiance > 0), "
              f"cloudy (bright, cloud optical depth >= {CLOUDY_DEPTH:g} along the central "
              "ray). Ratios against m = 0: variance ratio = relative variance at m = 0 / at m "
              "(same photons: independent of the machine's load), efficiency ratio = variance "
              "ratio x time at m = 0 / at m, by wall time (the project's definition) and by "
              "the process's CPU time (less sensitive to other work on the cores). View-mean "
              "z-scores against m = 0 "
              "(independent seeds). Wall times on a shared 2-core machine: see the load "
              "averages."]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", default=["single_cloud", "seed_field",
                                                        "whole_field"])
    parser.add_argument("--shares", nargs="+", type=float, default=[0.0, 0.5, 0.8])
    parser.add_argument("--seconds", type=float, default=35.0,
                        help="tracing time per render at m = 0.5 that sets the photon count")
    parser.add_argument("--photons", type=int, default=None, help="fixed photon count")
    parser.add_argument("--batches", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", default=str(RESULTS / "entry_sampling"),
                        help="output path without suffix (.json and .md are written)")
    args = parser.parse_args()
    if args.shares[0] != 0.0:
        parser.error("the first share must be 0 (the reference of the ratios)")
    result = {**run_header(args), "calibration_share": CALIBRATION_SHARE, "backend": "cpu",
              "method": "forward", "scenes": {}}
    available = scenes()
    start = time.perf_counter()
    for name in args.scenes:
        medium, scene, description = available[name]
        result["scenes"][name] = {"description": description,
                                  **run_scene(name, medium, scene, args)}
    result["total_s"] = time.perf_counter() - start
    result["load_average_end"] = os.getloadavg()
    write_result(result, args.output, markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
