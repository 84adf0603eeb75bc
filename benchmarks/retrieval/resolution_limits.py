"""How fine a retrieval must resolve the single cloud to reach a given epsilon.

Epsilon and delta (seed paper Eq. 54), split into extinction outside the true cloud and
the error inside it, of the true extinction blurred in two ways, without any Monte Carlo:

- convolved with a Gaussian of standard deviation ``--sigmas`` voxels (the scales the
  retrieval's gradient smoothing damps);
- averaged over ``--blocks`` x ``--blocks`` x ``--blocks`` voxel blocks, over the whole
  block ("grid") or over the block's cloudy voxels only ("support": a coarse field that
  knows the cloud's exact boundary);

and of the retrieved media given with ``--retrieved`` (medium netCDFs of
``benchmarks/retrieval/single_cloud.py --medium-output``). Usage::

    python -m benchmarks retrieval.resolution_limits [--retrieved A.nc B.nc]
        [--output benchmarks/results/resolution_limits]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import xarray as xr
from scipy.ndimage import gaussian_filter

from benchmarks.common import RESULTS, markdown_table, run_header, write_result
from cloudct.mc.render import single_cloud_medium
from cloudct.retrieval.metrics import epsilon_delta, epsilon_split
from cloudct.retrieval.optimizers import block_mean


def quality(truth: np.ndarray, beta: np.ndarray) -> dict:
    eps, delta = epsilon_delta(truth, beta)
    return {"epsilon": eps, "delta": delta, **epsilon_split(truth, beta)}


def markdown(result: dict) -> str:
    rows = [
        [row["field"], *(f"{row[k]:.3f}" for k in ("epsilon", "delta", "outside", "inside"))]
        for row in result["fields"]
    ]
    return "\n".join([
        f"{result['machine']}, {result['date']}: `{result['command']}`", "",
        *markdown_table(["field", "epsilon", "delta", "outside", "inside"], rows), "",
    ])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sigmas", type=float, nargs="+", default=[0.5, 1.0, 1.5, 2.0])
    parser.add_argument("--blocks", type=int, nargs="+", default=[2, 3, 4])
    parser.add_argument("--retrieved", nargs="*", default=[])
    parser.add_argument("--output", default=str(RESULTS / "resolution_limits"))
    args = parser.parse_args()

    truth = single_cloud_medium()["cloud_extinction"].values
    cloud = truth > 0
    fields = []
    for sigma in args.sigmas:
        blurred = gaussian_filter(truth, sigma, mode="constant", truncate=4.0)
        fields.append({"field": f"truth, Gaussian sigma {sigma:g} voxel",
                       **quality(truth, blurred)})
    for block in args.blocks:
        for name, where in (("grid", np.ones_like(cloud)), ("support", cloud)):
            fields.append({"field": f"truth, {block}x{block}x{block} blocks ({name})",
                           **quality(truth, block_mean(truth, where, block))})
    for path in args.retrieved:
        retrieved = xr.load_dataset(path)["cloud_extinction"].values
        fields.append({"field": f"retrieved: {Path(path).name}", **quality(truth, retrieved)})
    write_result({**run_header(args), "fields": fields}, args.output, markdown)


if __name__ == "__main__":
    main()
