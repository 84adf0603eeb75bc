"""Is there a barrier between a retrieved cloud and the truth? The loss along the straight
line between them.

For points s in [0, 1] the medium beta(s) = (1 - s) beta_retrieved + s beta_true (the
truth inside the retrieval's hull, ``cloud_mask``; epsilon falls linearly, (1 - s) x the
retrieved medium's), and its loss (seed paper Eq. 41) against the measurements at
``--pixel-block``, unbiased: 1/2 sum w (I_A - m)(I_B - m) over two independent renders A and
B (:func:`retrieval_single_cloud.fresh_loss`). Every point uses the same ``--pairs`` pairs
of seeds (common random numbers), so the differences L(s) - L(0) are reported with the
standard error of the paired differences, which is much smaller than that of each loss.

A loss that falls all the way from s = 0 to 1 means the retrieval stopped in a valley that
slopes, however gently, towards the truth (the descent is slow, not trapped); a loss that
rises first means a local minimum. Usage::

    python -m benchmarks retrieval.loss_path --retrieved RESULT.nc [--truth TRUTH.nc] [--pairs 3]
        [--photons 1000000] [--points 0 0.1 0.25 0.5 0.75 1] [--output FILE_STEM]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import xarray as xr

from benchmarks.common import RESULTS, WORK, markdown_table, run_header, write_result
from benchmarks.retrieval.single_cloud import fresh_loss, truth_and_measurements
from cloudct.measurements import coarse_measurements
from cloudct.retrieval.metrics import epsilon_delta


def markdown(result: dict) -> str:
    lines = [f"{result['machine']}, {result['date']}: `{result['command']}`", ""]
    rows = [
        [f"{p['s']:g}", f"{p['epsilon']:.3f}", f"{p['delta']:+.3f}",
         f"{p['loss']:.5f} +- {p['loss_error']:.5f}",
         f"{p['loss_change']:+.5f} +- {p['loss_change_error']:.5f}"]
        for p in result["points"]
    ]
    header = ["s", "epsilon", "delta", "loss", "L(s) - L(0), paired"]
    return "\n".join(lines + markdown_table(header, rows)) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--retrieved", required=True,
                        help="a retrieved medium netCDF with its cloud_mask")
    parser.add_argument("--truth", default=None,
                        help="the true medium netCDF (default: the bundled single cloud)")
    parser.add_argument("--points", type=float, nargs="+",
                        default=[0.0, 0.1, 0.25, 0.5, 0.75, 1.0])
    parser.add_argument("--pairs", type=int, default=3)
    parser.add_argument("--photons", type=int, default=1_000_000,
                        help="photons of each render")
    parser.add_argument("--pixel-block", type=int, default=2)
    parser.add_argument("--measurement-photons", type=int, default=20_000_000)
    parser.add_argument("--work", default=str(WORK))
    parser.add_argument("--output", default=str(RESULTS / "loss_path"))
    args = parser.parse_args()
    if args.pairs < 2:
        parser.error("--pairs must be at least 2 for standard errors")

    truth, measurements = truth_and_measurements(
        args.truth, args.measurement_photons, Path(args.work)
    )
    data = coarse_measurements(measurements, args.pixel_block)
    retrieved = xr.load_dataset(args.retrieved)
    mask = retrieved["cloud_mask"].values.astype(bool)
    beta_true = truth["cloud_extinction"].values
    start = retrieved["cloud_extinction"].values
    end = np.where(mask, beta_true, 0.0)
    medium = retrieved[[v for v in retrieved.data_vars if not v.startswith("log_")]]

    losses = []  # [point][pair]
    points = []
    for s in args.points:
        beta = (1.0 - s) * start + s * end
        at_s = medium.copy(deep=True)
        at_s["cloud_extinction"].values = beta
        losses.append([
            fresh_loss(at_s, data, args.photons, seed=10**9 + 2 * pair)["loss"]
            for pair in range(args.pairs)
        ])
        eps, delta = epsilon_delta(beta_true, beta)
        points.append({"s": s, "epsilon": eps, "delta": delta})
        print(f"s = {s:g}: epsilon {eps:.3f}, loss {np.mean(losses[-1]):.5f}", flush=True)
    losses = np.asarray(losses)
    root_n = np.sqrt(args.pairs)
    for point, row in zip(points, losses, strict=True):
        change = row - losses[0]
        point.update(
            losses=row.tolist(), loss=float(row.mean()),
            loss_error=float(row.std(ddof=1) / root_n), loss_change=float(change.mean()),
            loss_change_error=float(change.std(ddof=1) / root_n),
        )
    result = {
        **run_header(args), "retrieved": args.retrieved, "truth": args.truth or "single cloud",
        "pixel_block": args.pixel_block, "photons": args.photons, "pairs": args.pairs,
        "points": points,
    }
    write_result(result, args.output, markdown)


if __name__ == "__main__":
    main()
