"""How much of a retrieval gradient is signal: independent estimates compared, per voxel
block size, on the single-cloud scene at the space-carved start of a retrieval (or at
another medium, ``--start``, e.g. a retrieved one).

Two gradient estimates g1, g2 from independent paths share their mean g; with noise n_i,
E[g1 . g2] = |g|^2 while |g_i|^2 = |g|^2 + |n_i|^2, so cos(g1, g2) estimates the signal
fraction |g|^2 / (|g|^2 + |n|^2) of one estimate's squared norm. The gradients are taken
over the carved hull, averaged over voxel blocks as a retrieval stage that ties its voxels
does (:func:`cloudct.retrieval.optimizers.block_mean`), and compared with the direction
towards the truth (cos(-g, beta_true - beta)); the noise is orthogonal to that direction on
average, so the mean gradient's cosine with it is about cos(-g, truth - beta) /
sqrt(cos(g1, g2)). The residual is common to all estimates
(images of the initial medium rendered once with ``--residual-photons``), so only the
gradient's own noise is measured. Usage::

    python benchmarks/gradient_signal.py [--pixel-blocks 4] [--score-photons 200000]
        [--drt-samples 32 64] [--start MEDIUM.nc] [--output benchmarks/results/gradient_signal]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from common import markdown_table, run_header, write_json_and_markdown  # noqa: E402
from retrieval_single_cloud import measurements_for  # noqa: E402

from cloudct.mc.drt import drt_gradient  # noqa: E402
from cloudct.mc.gradient import score_function_gradient  # noqa: E402
from cloudct.mc.render import render, single_cloud_medium  # noqa: E402
from cloudct.mc.scene import Scene  # noqa: E402
from cloudct.medium import load_medium  # noqa: E402
from cloudct.retrieval.carving import carve, initial_medium  # noqa: E402
from cloudct.retrieval.loop import coarse_measurements  # noqa: E402
from cloudct.retrieval.optimizers import block_mean  # noqa: E402

VOXEL_BLOCKS = (1, 2, 4)
BATCHES = 32  # DRT's samples per pixel are rounded up to a multiple of this


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


def markdown(result: dict) -> str:
    lines = [
        f"{result['machine']}, {result['date']}: `{result['command']}`", "",
        *markdown_table(
            ["estimator", "paths per estimate", "s per estimate", "voxel blocks",
             "cos(g1, g2)", "cos(-g, truth - beta)"],
            [[row["estimator"], f"{row['paths']:,}", f"{row['seconds']:.2f}",
              str(row["voxel_blocks"]), f"{row['cos_independent']:.3f}",
              f"{row['cos_truth'][0]:.3f}, {row['cos_truth'][1]:.3f}"]
             for row in result["rows"]],
        ),
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pixel-blocks", type=int, default=4)
    parser.add_argument("--score-photons", type=int, nargs="+", default=[200_000])
    parser.add_argument("--drt-samples", type=int, nargs="*", default=[32, 64],
                        help="DRT backward samples per pixel (rounded up to a multiple of 32)")
    parser.add_argument("--residual-photons", type=int, default=1_000_000)
    parser.add_argument("--measurement-photons", type=int, default=20_000_000)
    parser.add_argument("--work", default=str(HERE / "work"))
    parser.add_argument("--start", default=None,
                        help="evaluate at this medium netCDF (its cloud_mask, where present, "
                             "is the hull) instead of the constant carved start")
    parser.add_argument("--output", default=str(HERE / "results" / "gradient_signal"))
    args = parser.parse_args()

    truth = single_cloud_medium()
    measurements = measurements_for(truth, args.measurement_photons, Path(args.work))
    if args.start is None:  # the seed paper's constant start, that of the first runs
        initial = initial_medium(carve(measurements, truth, profile="constant"), truth)
    else:
        initial = load_medium(args.start)
    data = coarse_measurements(measurements, args.pixel_blocks)
    scene = Scene.from_dataset(data)
    images = render(initial, scene, photons=args.residual_photons, seed=11)
    residual = images["radiance"].values - data["radiance"].values
    beta = initial["cloud_extinction"].values
    hull = initial["cloud_mask"].values > 0 if "cloud_mask" in initial else beta > 0
    towards_truth = truth["cloud_extinction"].values - beta

    def score(paths: int, seed: int) -> np.ndarray:
        return score_function_gradient(initial, scene, residual, photons=paths, seed=seed,
                                      batches=BATCHES)[0]

    def drt(paths: int, seed: int) -> np.ndarray:
        return drt_gradient(initial, scene, residual, samples_per_pixel=paths, seed=seed,
                            batches=BATCHES)[0]

    runs = [("score", score, p) for p in args.score_photons]
    runs += [("drt", drt, s) for s in args.drt_samples]
    result = {**run_header(), "pixel_blocks": args.pixel_blocks, "start": args.start,
              "rows": []}
    for name, estimate, paths in runs:
        estimate(min(paths, 1000), 0)  # compile outside the timing
        start = time.perf_counter()
        g = [estimate(paths, seed) for seed in (1, 2)]
        seconds = (time.perf_counter() - start) / 2
        total = paths if name == "score" else -(-paths // BATCHES) * BATCHES * residual.size
        for vb in VOXEL_BLOCKS:
            g1, g2 = (block_mean(x, hull, vb)[hull] for x in g)
            target = block_mean(towards_truth, hull, vb)[hull]
            result["rows"].append({
                "estimator": name, "paths": total, "seconds": seconds, "voxel_blocks": vb,
                "cos_independent": cosine(g1, g2),
                "cos_truth": [cosine(-g1, target), cosine(-g2, target)],
            })
            print(result["rows"][-1], flush=True)
    write_json_and_markdown(result, args.output, markdown)


if __name__ == "__main__":
    main()
