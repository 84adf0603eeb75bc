"""DRT and sample matching against finite differences in the cloud-free holes of the single
cloud's dense core, where an earlier one-sided check (h = 0.5 and 1 /km, 32 batches) gave
z-scores down to -4.6 and left open whether the estimators or the finite differences err.

Medium and scene: :func:`data_synth.single_cloud_piece.dense_core_piece` (10 x 10 x 12
voxels of 0.02 x 0.02 x 0.04 km, tau up to 2.5 per voxel) and its two 6 x 6 cameras, with
positive random pixel weights r_d (uniform 0.5 to 1.5, seed 4), so that the gradient is that
of J(beta) = sum_d r_d I_d. The holes are the cloud-free voxels with the most cloudy
neighbours (ties: the densest neighbours).

Finite differences of the backward renderer, common random numbers (one seed for every
medium), the cloud extinction of a hole cannot go below 0, so the second-order one-sided
stencil dJ/dbeta ~ (-3 J(0) + 4 J(h) - J(2h)) / 2h, whose error is O(h^2): run at several
steps h, its agreement across h shows the truncation is below the noise. Per-batch
differences give the mean and standard error; the standard error is also taken over groups
of 8 batches (the group means are closer to normal if a few batches carry heavy tails): the
two must agree for the error bars to be trusted.

DRT and sample matching (the defaults: linear, one probe, free-flight share) on the same
pixel weights, ``--runs`` independent runs each, averaged, with their batch standard errors;
z = (estimate - FD) / sqrt(se_est^2 + se_FD^2) per hole and step. The runs also compare
the two estimators over whole classes of voxels (cloud, cloud-free, holes): the class's
summed gradient with its standard error over the runs, and the mean of the per-voxel z of
SM - DRT for every pairing of runs beside the same between two runs of one estimator as
controls (:func:`pooled_comparison`). Usage::

    python -m benchmarks gradients.holes [--holes 4] [--steps 2 4 8] \
        [--fd-samples 65536] [--batches 128] [--gradient-samples 131072] [--runs 4] \
        [--output benchmarks/results/gradient_holes]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from benchmarks.common import RESULTS, markdown_table, run_header, write_result
from cloudct.mc.gradient import drt_gradient, sample_matching_gradient
from cloudct.mc.render import render_batches
from data_synth.single_cloud_piece import dense_core_piece, scene_of_dense_core

GROUP = 8  # batches per group of the grouped standard error
GRADIENT_BATCHES = 32


def holes_of(cloud: np.ndarray, count: int) -> list[tuple[int, int, int]]:
    """The ``count`` interior cloud-free voxels with the most cloudy face neighbours (ties:
    the largest mean neighbour extinction)."""
    ranked = []
    nx, ny, nz = cloud.shape
    for v in np.ndindex(nx - 2, ny - 2, nz - 2):
        v = tuple(int(a) + 1 for a in v)
        if cloud[v] == 0.0:
            near = face_neighbours(cloud, v)
            ranked.append((sum(b > 0 for b in near), float(np.mean(near)), v))
    ranked.sort(reverse=True)
    return [v for _, _, v in ranked[:count]]


def face_neighbours(cloud: np.ndarray, v: tuple[int, int, int]) -> list[float]:
    """The cloud extinction of an interior voxel's six face neighbours, 1/km."""
    i, j, k = v
    return [float(cloud[i - 1, j, k]), float(cloud[i + 1, j, k]), float(cloud[i, j - 1, k]),
            float(cloud[i, j + 1, k]), float(cloud[i, j, k - 1]), float(cloud[i, j, k + 1])]


def with_cloud(medium, voxel, value):
    out = medium.copy(deep=True)
    out["cloud_extinction"].values[voxel] = value
    return out


def mean_and_errors(per_batch: np.ndarray) -> tuple[float, float, float]:
    """Mean, standard error over batches, standard error over groups of :data:`GROUP`."""
    n = per_batch.size
    groups = per_batch[: n - n % GROUP].reshape(-1, GROUP).mean(axis=1)
    return (float(per_batch.mean()), float(per_batch.std(ddof=1) / math.sqrt(n)),
            float(groups.std(ddof=1) / math.sqrt(groups.size)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--holes", type=int, default=4)
    parser.add_argument("--steps", type=float, nargs="+", default=[2.0, 4.0, 8.0],
                        help="finite-difference steps h of the cloud extinction, 1/km")
    parser.add_argument("--fd-samples", type=int, default=65536,
                        help="backward samples per pixel of every finite-difference render")
    parser.add_argument("--batches", type=int, default=128)
    parser.add_argument("--gradient-samples", type=int, default=131072,
                        help="DRT and sample-matching samples per pixel of each run")
    parser.add_argument("--runs", type=int, default=4,
                        help="independent runs of each estimator (at least 2: the pooled "
                        "comparison's controls compare runs of one estimator)")
    parser.add_argument("--output", default=str(RESULTS / "gradient_holes"))
    args = parser.parse_args()
    if args.batches % GROUP:
        parser.error(f"--batches must be a multiple of {GROUP}")
    if args.runs < 2:
        parser.error("--runs must be at least 2")

    medium = dense_core_piece()
    scene = scene_of_dense_core(medium)
    weights = np.random.default_rng(4).uniform(0.5, 1.5, size=(2, 6, 6))
    holes = holes_of(medium["cloud_extinction"].values, args.holes)

    def objective_batches(m) -> np.ndarray:
        images, _ = render_batches(m, scene, photons=args.fd_samples, method="backward",
                                   seed=11, batches=args.batches, progress=False)
        return np.einsum("bvrc,vrc->b", images, weights)

    start = time.perf_counter()
    base = objective_batches(medium)
    fd = {}
    for hole in holes:
        for h in args.steps:
            j1 = objective_batches(with_cloud(medium, hole, h))
            j2 = objective_batches(with_cloud(medium, hole, 2 * h))
            fd[hole, h] = mean_and_errors((-3 * base + 4 * j1 - j2) / (2 * h))  # O(h^2)
        print(f"finite differences at {hole}: "
              + ", ".join(f"h {h}: {fd[hole, h][0]:.4g} +- {fd[hole, h][1]:.2g}"
                          for h in args.steps), flush=True)
    fd_seconds = time.perf_counter() - start

    estimates, runs = {}, {}
    for name, estimator, seed in (("DRT", drt_gradient, 5),
                                  ("sample matching", sample_matching_gradient, 6)):
        start = time.perf_counter()
        runs[name] = [estimator(medium, scene, weights, samples_per_pixel=args.gradient_samples,
                                seed=seed + 10 * r, batches=GRADIENT_BATCHES)[:2]
                      for r in range(args.runs)]
        mean = sum(m for m, _ in runs[name]) / args.runs
        error = np.sqrt(sum(e**2 for _, e in runs[name])) / args.runs
        estimates[name] = {"seconds": time.perf_counter() - start,
                           "holes": {str(v): [float(mean[v]), float(error[v])] for v in holes}}
        print(f"{name}: {estimates[name]['seconds']:.0f} s", flush=True)

    rows = []
    for hole in holes:
        for h in args.steps:
            d, se, se_grouped = fd[hole, h]
            row = {"hole": str(hole), "step": h, "fd": d, "fd_se": se,
                   "fd_se_grouped": se_grouped}
            for name, est in estimates.items():
                value, error = est["holes"][str(hole)]
                row[name] = value
                row[f"{name} se"] = error
                row[f"{name} z"] = (value - d) / math.hypot(error, se)
            rows.append(row)
    result = {**run_header(args), "holes": [list(v) for v in holes],
              "cloud_neighbours": {str(v): face_neighbours(medium["cloud_extinction"].values, v)
                                   for v in holes},
              "fd_seconds": fd_seconds, "estimators": estimates, "rows": rows,
              "pooled": pooled_comparison(medium["cloud_extinction"].values, runs)}
    write_result(result, args.output, markdown)


def pooled_comparison(cloud: np.ndarray, runs: dict) -> list[dict]:
    """Sample matching against DRT over classes of voxels: the mean over the class of the
    per-voxel z = (SM - DRT) / sqrt(se_SM^2 + se_DRT^2), for every pairing of an SM run
    with a DRT run, and as controls the same between two runs of one estimator (which
    must be about 0: the runs' z are correlated across voxels, so the spread of the
    controls, not 1 / sqrt(voxels), says how far from 0 a mean z may wander)."""
    cloudy = np.zeros(cloud.shape, int)
    padded = np.pad(cloud > 0, 1)
    for axis in range(3):
        for shift in (1, -1):
            cloudy += np.roll(padded, shift, axis)[1:-1, 1:-1, 1:-1]
    classes = {"cloud": cloud > 0, "cloud-free": cloud == 0,
               "cloud-free, 3 or more cloudy neighbours": (cloud == 0) & (cloudy >= 3)}

    def mean_z(a, b, mask):
        both = mask & (a[1] > 0) & (b[1] > 0)
        return float(((a[0] - b[0]) / np.hypot(a[1], b[1]))[both].mean())

    drt, sm = runs["DRT"], runs["sample matching"]
    out = []
    for label, mask in classes.items():
        sums = {name: np.array([m[mask].sum() for m, _ in r]) for name, r in
                (("DRT", drt), ("SM", sm))}
        out.append({
            "voxels": label, "count": int(mask.sum()),
            # the class's summed gradient, mean and standard error over the runs: an
            # unbiased comparison even where skewed estimates make the mean z drift
            "sum DRT": [float(sums["DRT"].mean()),
                        float(sums["DRT"].std(ddof=1) / math.sqrt(len(drt)))],
            "sum SM": [float(sums["SM"].mean()),
                       float(sums["SM"].std(ddof=1) / math.sqrt(len(sm)))],
            "SM - DRT": [mean_z(a, b, mask) for a in sm for b in drt],
            "DRT - DRT": [mean_z(a, b, mask) for i, a in enumerate(drt) for b in drt[i + 1:]],
            "SM - SM": [mean_z(a, b, mask) for i, a in enumerate(sm) for b in sm[i + 1:]],
        })
    return out


def markdown(result: dict) -> str:
    header = ["hole", "h (1/km)", "FD", "FD se (batches / groups)", "DRT", "z", "SM", "z"]
    rows = [[r["hole"], f"{r['step']:g}", f"{r['fd']:.4g}",
             f"{r['fd_se']:.2g} / {r['fd_se_grouped']:.2g}",
             f"{r['DRT']:.4g} +- {r['DRT se']:.2g}", f"{r['DRT z']:+.2f}",
             f"{r['sample matching']:.4g} +- {r['sample matching se']:.2g}",
             f"{r['sample matching z']:+.2f}"] for r in result["rows"]]
    pooled = [[p["voxels"], str(p["count"]),
               *(f"{p[k][0]:.4g} +- {p[k][1]:.2g}" for k in ("sum DRT", "sum SM")),
               *(", ".join(f"{z:+.3f}" for z in p[k]) for k in ("SM - DRT", "DRT - DRT",
                                                                "SM - SM"))]
              for p in result["pooled"]]
    return "\n".join([
        *markdown_table(header, rows), "",
        "Classes of voxels: the summed gradient (mean and standard error over the runs), "
        "and the mean per-voxel z for every pairing of runs:", "",
        *markdown_table(["voxels", "count", "sum DRT", "sum SM", "mean z SM - DRT",
                         "controls: DRT - DRT", "SM - SM"], pooled)]) + "\n"


if __name__ == "__main__":
    main()
