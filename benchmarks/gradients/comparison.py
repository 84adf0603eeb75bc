"""Score function vs differential ratio tracking on the single-cloud LES scene.

The residual weights are those of a retrieval's first iteration: images of the space-carved
initial medium minus the measurements of the true cloud (three of the nine views, pixels
averaged 4x4, to keep finite differences affordable). For each estimator, independent
seeds give per-voxel means and standard deviations (cloudct.retrieval.diagnostics), which
are compared at equal time; a handful of voxels (cloudy, clear air inside and outside the
hull) are checked against central finite differences with common random numbers. Usage::

    python -m benchmarks gradients.comparison [--seeds 4] [--output benchmarks/results]
"""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path

import numpy as np

from benchmarks.common import RESULTS, run_header, write_result


def main() -> None:
    from cloudct.mc.render import render, render_batches, single_cloud_medium
    from cloudct.mc.scene import Scene, single_cloud_scene
    from cloudct.measurements import coarse_measurements
    from cloudct.medium import cell_edges
    from cloudct.retrieval.carving import carve, initial_medium
    from cloudct.retrieval.diagnostics import gradient_statistics, plot_gradient_slices

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--photons", type=int, default=400_000, help="score-function photons")
    parser.add_argument("--spp", type=int, default=64, help="DRT samples per pixel")
    parser.add_argument("--fd-photons", type=int, default=2_000_000)
    parser.add_argument("--output", default=str(RESULTS))
    args = parser.parse_args()
    out = Path(args.output)
    out.mkdir(parents=True, exist_ok=True)

    truth = single_cloud_medium()
    edges = cell_edges(truth)
    full = single_cloud_scene(np.array([e[0] for e in edges]), np.array([e[-1] for e in edges]))
    measured = render(truth, full, photons=4_000_000, seed=1, progress=False)
    initial = initial_medium(carve(measured, truth), truth)
    views = [0, 2, 6]
    coarse = coarse_measurements(measured.isel(view=views), 4)
    scene = Scene.from_dataset(coarse)
    images = render(initial, scene, photons=2_000_000, seed=2, progress=False)
    residual = images.radiance.values - coarse.radiance.values

    stats = gradient_statistics(
        initial, scene, residual, {"score": args.photons, "drt": args.spp}, seeds=args.seeds
    )
    stats.to_netcdf(out / "gradient_statistics.nc")

    beta = initial["cloud_extinction"].values
    hull = beta > 0
    air_in_box = ~hull
    t = stats["seconds_per_estimate"].values
    std = stats["std"].values
    # standard deviation of an estimate that took the score function's time
    equal_time = std * np.sqrt(t / t[0])[:, None, None, None]
    summary = {
        **run_header(args),
        "seconds_per_estimate": dict(zip(stats.estimator.values.tolist(), t.tolist(),
                                         strict=True)),
        "median_std_ratio_drt_over_score_equal_time": {
            "hull": float(np.median(equal_time[1][hull] / equal_time[0][hull])),
            "outside_hull": float(np.median(equal_time[1][air_in_box]
                                            / np.maximum(equal_time[0][air_in_box], 1e-300))),
        },
    }

    # finite differences on a few voxels
    rng = np.random.default_rng(0)
    cloudy = np.argwhere(hull & (truth["cloud_extinction"].values > 0))
    clear = np.argwhere(air_in_box)
    picks = [tuple(v) for v in cloudy[rng.choice(len(cloudy), 4, replace=False)]]
    picks += [tuple(v) for v in clear[rng.choice(len(clear), 2, replace=False)]]

    def weighted(medium, seed=7):
        b, _ = render_batches(medium, scene, photons=args.fd_photons, seed=seed, progress=False)
        return np.einsum("bvrc,vrc->b", b, residual)

    fd_rows = []
    base = None
    for voxel in picks:
        value = beta[voxel]
        start = time.perf_counter()
        if value > 0:
            h = 0.2 * value
            plus, minus = initial.copy(deep=True), initial.copy(deep=True)
            plus["cloud_extinction"].values[voxel] += h
            minus["cloud_extinction"].values[voxel] -= h
            per_batch = (weighted(plus) - weighted(minus)) / (2 * h)
        else:
            h = 2.0
            base = weighted(initial) if base is None else base
            one, two = initial.copy(deep=True), initial.copy(deep=True)
            one["cloud_extinction"].values[voxel] = h
            two["cloud_extinction"].values[voxel] = 2 * h
            per_batch = (-3 * base + 4 * weighted(one) - weighted(two)) / (2 * h)
        fd, fd_se = per_batch.mean(), per_batch.std(ddof=1) / math.sqrt(len(per_batch))
        row = {"voxel": [int(i) for i in voxel], "beta": float(value), "fd": float(fd),
               "fd_se": float(fd_se), "seconds": time.perf_counter() - start}
        for k, name in enumerate(stats.estimator.values):
            m = float(stats["mean"].values[k][voxel])
            se = float(stats["std"].values[k][voxel]) / math.sqrt(args.seeds)
            row[f"{name}"] = m
            row[f"{name}_se"] = se
            row[f"{name}_z"] = (m - fd) / math.hypot(se, fd_se)
        fd_rows.append(row)
        print(row, flush=True)
    summary["finite_differences"] = fd_rows
    plot_gradient_slices(stats, out / "gradient_slices.png")
    write_result(summary, out / "gradient_comparison")


if __name__ == "__main__":
    main()
