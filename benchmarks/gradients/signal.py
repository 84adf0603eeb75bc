"""How much of a retrieval gradient is signal, per second of tracing: independent estimates
of each gradient estimator compared, per voxel block size, on the single-cloud scene at the
space-carved start of a retrieval (or at another medium, ``--start``, e.g. a retrieved one).

Every estimator estimates the same gradient g (they are all unbiased), so what tells them
apart is the noise n of one estimate and its cost. Two estimates g1, g2 of one estimator,
from independent paths, give the noise without g: E|g1 - g2|^2 = 2 E|n|^2, a sum of many
squares and so a precise number even where the noise swamps the signal. The precision per
second of an estimator is 1 / (E|n|^2 x seconds per estimate); divided by the score
function's it is the equal-time efficiency. The signal |g|^2 is the mean of g_i . g_j over
all pairs of independent estimates of all estimators (all runs pool into it), so the
signal-to-noise ratio per second is |g|^2 / (E|n|^2 s), and its inverse the time an even
signal-to-noise ratio takes. The gradients are taken over the carved hull, averaged over
voxel blocks as a retrieval stage that ties its voxels does
(:func:`cloudct.retrieval.optimizers.block_mean`), and compared with the direction towards
the truth, d = beta_true - beta: the pooled g . d gives the mean gradient's cosine with -d,
and an estimate of T seconds points towards the truth with the expected cosine about
-(g . d) / (|d| sqrt(|g|^2 + E|n|^2 s / T)) (reported at 10 s). cos(g1, g2), the signal
fraction of one pair, is kept for comparison with earlier runs. The residual is common to
all estimates (images of the medium rendered once with ``--residual-photons``), so only the
gradient's own noise is measured.

Runs are ``ESTIMATOR:PATHS[:residual]`` with ESTIMATOR one of :data:`VARIANTS` (score: the
path score function, PATHS forward photons; combined: the score function of forward photons
and 4 camera paths per photon, MIS-weighted, PATHS forward photons; drt, sm, sm4, smq,
smdual: DRT and sample matching with 1 or 4 probes per segment, quadratic, or without the
free-flight share, and bscore, the score function of camera paths, PATHS camera paths in
all) and ``residual`` for pixels drawn in proportion to |residual|
(:mod:`cloudct.mc.pixel_sampling`). Usage::

    python -m benchmarks gradients.signal [--pixel-blocks 2] \
        [--runs score:200000 drt:200000 sm:200000 sm:200000:residual] [--start MEDIUM.nc] \
        [--optics hg|mie] [--truncation DEG] [--output benchmarks/results/gradient_signal]

``--truncation DEG`` (with ``--optics mie``): the start's phase functions cut flat at DEG
degrees for every estimate and the residual's images (``phase_truncation``,
:mod:`cloudct.optics`), as a retrieval with that setting traces them; the measurements keep
the full peak.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from benchmarks.common import RESULTS, WORK, markdown_table, run_header, write_result
from benchmarks.retrieval.single_cloud import measurements_for
from cloudct.mc.gradient import (
    backward_score_gradient,
    combined_gradient,
    drt_gradient,
    sample_matching_gradient,
    score_function_gradient,
)
from cloudct.mc.render import render, single_cloud_medium
from cloudct.mc.scene import Scene
from cloudct.measurements import coarse_measurements
from cloudct.medium import load_medium
from cloudct.optics import with_phase_truncation
from cloudct.retrieval.carving import carve, initial_medium
from cloudct.retrieval.optimizers import block_mean

VOXEL_BLOCKS = (1, 2, 4)
BATCHES = 32  # camera-side samples per pixel are rounded up to a multiple of this
EQUAL_TIME = 10.0  # seconds at which the expected cosine towards the truth is reported
#: estimator variants: (function, keyword arguments); score and combined take photons, the
#: others samples per pixel
VARIANTS = {
    "score": (score_function_gradient, {}),
    "combined": (combined_gradient, {}),
    "bscore": (backward_score_gradient, {}),
    "drt": (drt_gradient, {}),
    "sm": (sample_matching_gradient, {"probes": 1}),
    "sm4": (sample_matching_gradient, {"probes": 4}),
    "smq": (sample_matching_gradient, {"probes": 1, "quadratic": True}),
    "smdual": (sample_matching_gradient, {"probes": 1, "mis": False}),
}


def cosine(a: np.ndarray, b: np.ndarray) -> float:
    return float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b)))


def pooled_signal(estimates: list[tuple[np.ndarray, np.ndarray]], target: np.ndarray):
    """|g|^2 and g . d from all pairs of independent estimates (each run's two and across
    runs), and their spread over the pairs."""
    flat = [g for pair in estimates for g in pair]
    dots = [flat[i] @ flat[j] for i in range(len(flat)) for j in range(i + 1, len(flat))]
    towards = [g @ target for g in flat]
    return float(np.mean(dots)), float(np.mean(towards)), float(np.std(dots) / np.sqrt(len(dots)))


def markdown(result: dict) -> str:
    lines = [
        f"{result['machine']}, {result['date']}: `{result['command']}`", "",
        f"{result.get('optics', 'hg')} optics"
        + (f" cut at {result['truncation']} degrees" if result.get("truncation") else "")
        + "; start: "
        f"{result['start'] or 'constant carved hull'}, {result['pixel_blocks']}x"
        f"{result['pixel_blocks']} pixel blocks; pooled signal |g|^2 per voxel block size: "
        + ", ".join(f"{vb}: {s['signal']:.3g} +- {s['signal_spread']:.2g}"
                    for vb, s in result["pooled"].items()), "",
        *markdown_table(
            ["estimator", "pixels", "paths per estimate", "s per estimate", "voxel blocks",
             "noise E|n|^2", "efficiency vs score", "SNR per s", "s for SNR 1",
             f"cos towards truth at {EQUAL_TIME:g} s", "cos(g1, g2)"],
            [[row["estimator"], row["pixel_sampling"], f"{row['paths']:,}",
              f"{row['seconds']:.2f}", str(row["voxel_blocks"]), f"{row['noise']:.3g}",
              f"{row['efficiency_vs_score']:.2f}", f"{row['snr_per_second']:.4f}",
              f"{row['seconds_for_snr_1']:.0f}", f"{row['cos_truth_equal_time']:.3f}",
              f"{row['cos_independent']:.3f}"]
             for row in result["rows"]],
        ),
    ]
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pixel-blocks", type=int, default=4)
    parser.add_argument("--runs", nargs="+", default=["score:200000", "drt:200000"],
                        help="ESTIMATOR:PATHS[:residual] (module docstring)")
    parser.add_argument("--residual-photons", type=int, default=1_000_000)
    parser.add_argument("--measurement-photons", type=int, default=20_000_000)
    parser.add_argument("--measurement-method", choices=("forward", "combined"), default=None,
                        help="the measurements' render (default: combined with Mie optics, "
                        "else forward; runs before 2026-11-27 14:00 rendered forward)")
    parser.add_argument("--work", default=str(WORK))
    parser.add_argument("--start", default=None,
                        help="evaluate at this medium netCDF (its cloud_mask, where present, "
                             "is the hull) instead of the constant carved start")
    parser.add_argument("--optics", choices=("hg", "mie"), default="hg",
                        help="the single cloud's optics, of the truth and the start alike")
    parser.add_argument("--truncation", type=float, default=0.0,
                        help="Mie: cut the start's forward peak at this many degrees")
    parser.add_argument("--output", default=str(RESULTS / "gradient_signal"))
    args = parser.parse_args()

    truth = single_cloud_medium(args.optics)
    name = "single_cloud" if args.optics == "hg" else f"single_cloud_{args.optics}"
    measurements = measurements_for(truth, args.measurement_photons, Path(args.work), name,
                                    args.measurement_method)
    if args.start is None:  # the seed paper's constant start, that of the first runs
        initial = initial_medium(carve(measurements, truth, profile="constant"), truth)
    else:
        initial = load_medium(args.start)
    if args.truncation:
        initial = with_phase_truncation(initial, args.truncation)
    data = coarse_measurements(measurements, args.pixel_blocks)
    scene = Scene.from_dataset(data)
    images = render(initial, scene, photons=args.residual_photons, seed=11)
    residual = images["radiance"].values - data["radiance"].values
    beta = initial["cloud_extinction"].values
    hull = initial["cloud_mask"].values > 0 if "cloud_mask" in initial else beta > 0
    towards_truth = truth["cloud_extinction"].values - beta
    pixels = int(np.count_nonzero(residual))

    def estimate(name: str, paths: int, sampling: str, seed: int):
        function, kw = VARIANTS[name]
        if name in ("score", "combined"):
            return function(initial, scene, residual, photons=paths, seed=seed,
                            batches=BATCHES, progress=False)
        return function(initial, scene, residual, samples_per_pixel=-(-paths // pixels),
                        seed=seed, batches=BATCHES, pixel_sampling=sampling, **kw)

    runs = []
    for spec in args.runs:
        name, paths, *rest = spec.split(":")
        paths, sampling = int(paths), (rest[0] if rest else "uniform")
        estimate(name, min(paths, 20 * pixels), sampling, 0)  # compile outside the timing
        start = time.perf_counter()
        pair = [estimate(name, paths, sampling, seed) for seed in (1, 2)]
        seconds = (time.perf_counter() - start) / 2
        runs.append((name, sampling, pair[0][2]["photons"], seconds, [p[0] for p in pair]))
        print(f"{spec}: {seconds:.2f} s per estimate", flush=True)

    result = {**run_header(args), "pixel_blocks": args.pixel_blocks, "start": args.start,
              "optics": args.optics, "truncation": args.truncation, "pooled": {}, "rows": []}
    for vb in VOXEL_BLOCKS:
        target = block_mean(towards_truth, hull, vb)[hull]
        blocked = [tuple(block_mean(g, hull, vb)[hull] for g in run[4]) for run in runs]
        signal, g_dot_d, spread = pooled_signal(blocked, target)
        result["pooled"][vb] = {"signal": signal, "signal_spread": spread,
                                "g_dot_truth_direction": g_dot_d}
        score_cost = None
        for (name, sampling, paths, seconds, _), (g1, g2) in zip(runs, blocked, strict=True):
            noise = float(np.sum((g1 - g2) ** 2) / 2)
            if name == "score" and score_cost is None:
                score_cost = noise * seconds
            snr = signal / (noise * seconds) if signal > 0 else 0.0
            at_t = np.sqrt(max(signal, 0.0) + noise * seconds / EQUAL_TIME)
            result["rows"].append({
                "estimator": name, "pixel_sampling": sampling, "paths": paths,
                "seconds": seconds, "voxel_blocks": vb, "noise": noise,
                "efficiency_vs_score": (score_cost / (noise * seconds)
                                        if score_cost else float("nan")),
                "snr_per_second": snr,
                "seconds_for_snr_1": 1.0 / snr if snr > 0 else float("inf"),
                "cos_truth_equal_time": -g_dot_d / (np.linalg.norm(target) * at_t),
                "cos_independent": cosine(g1, g2),
                "cos_truth": [cosine(-g1, target), cosine(-g2, target)],
            })
    result["rows"].sort(key=lambda row: row["voxel_blocks"])
    write_result(result, args.output, markdown)


if __name__ == "__main__":
    main()
