"""The seed paper's cloud-field scene end to end, through the command line.

The medium is the seed paper's cloud field (Table 1: 79 x 84 x 27 voxels of 20 x 20 x 40
m), the window of the bundled rico122x106x39 with the most cloudy cells
(`cloudct.les.seed_paper_cloud_field`), with the default optics; the scene is the
`cloud-field` preset
(nine 86 x 86 cameras, a ring at 33 degrees, 2.16 km from the box centre, sun at the
zenith, open boundaries: a window of an LES domain is not periodic). The commands run are
those a user types (printed, and stored in the results):

    cloudct scene truth.nc --preset cloud-field -o scene.nc --figure scene.png
    cloudct synth truth.nc --scene scene.nc --photons P -o measurements.nc
    cloudct carve measurements.nc --medium truth.nc -o init.nc --figure hull.png
    cloudct retrieve measurements.nc --init init.nc --truth truth.nc --time-limit S \
        [--workers 2] -o result.nc
    cloudct report result.nc --truth truth.nc --measurements measurements.nc -o report

    python benchmarks/cloud_field.py --minutes 60 [--workers 2] [--out DIR]

Epsilon and delta over time are in result.nc (log_seconds, log_epsilon, log_delta) and in
DIR/cloud_field.json.
"""

from __future__ import annotations

import argparse
import json
import shlex
import time
from pathlib import Path

import numpy as np
import xarray as xr

from cloudct.cli import main as cloudct
from cloudct.les import seed_paper_cloud_field
from cloudct.medium import save_medium
from cloudct.optics import to_optical

HERE = Path(__file__).resolve().parent


def run(argv: list[str], log: list[dict]) -> None:
    """Run one cloudct command, timing it; stop on failure."""
    print("$ cloudct " + shlex.join(argv), flush=True)
    start = time.perf_counter()
    status = cloudct(argv)
    log.append({"command": "cloudct " + shlex.join(argv), "seconds": time.perf_counter() - start})
    if status != 0:
        raise SystemExit(f"cloudct {argv[0]} failed with status {status}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=60.0, help="retrieval time limit")
    parser.add_argument("--measurement-photons", type=int, default=10_000_000)
    parser.add_argument("--workers", type=int, help="retrieve on a local Dask cluster")
    parser.add_argument("--out", type=Path, default=HERE / "results" / "cloud_field")
    args = parser.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    truth = to_optical(seed_paper_cloud_field())
    save_medium(truth, out / "truth.nc", overwrite=True)
    f = {name: str(out / name) for name in ("truth.nc", "scene.nc", "measurements.nc",
                                            "init.nc", "result.nc")}
    log: list[dict] = []
    if not (out / "measurements.nc").exists():
        run(["scene", f["truth.nc"], "--preset", "cloud-field", "-o", f["scene.nc"],
             "--figure", str(out / "scene.png"), "--overwrite"], log)
        run(["synth", f["truth.nc"], "--scene", f["scene.nc"], "--photons",
             str(args.measurement_photons), "-o", f["measurements.nc"]], log)
    if not (out / "init.nc").exists():
        run(["carve", f["measurements.nc"], "--medium", f["truth.nc"], "-o", f["init.nc"],
             "--figure", str(out / "hull.png")], log)
    retrieve = ["retrieve", f["measurements.nc"], "--init", f["init.nc"], "--truth",
                f["truth.nc"], "--time-limit", str(60 * args.minutes), "--iterations",
                "100000", "-o", f["result.nc"], "--overwrite"]
    if args.workers:
        retrieve += ["--workers", str(args.workers)]
    run(retrieve, log)
    run(["report", f["result.nc"], "--truth", f["truth.nc"], "--measurements",
         f["measurements.nc"], "-o", str(out / "report")], log)

    result = xr.load_dataset(out / "result.nc")
    seconds = result["log_seconds"].values
    marks = {}
    for minutes in (5, 15, 30, 60):
        done = np.flatnonzero(seconds <= 60 * minutes)
        if done.size:
            i = done[-1]
            marks[f"{minutes} min"] = {"iteration": int(i + 1),
                                       "epsilon": float(result["log_epsilon"].values[i]),
                                       "delta": float(result["log_delta"].values[i])}
    summary = {
        "grid": list(truth["cloud_extinction"].shape), "workers": args.workers or 0,
        "iterations": int(seconds.size), "seconds": float(seconds[-1]),
        "final": {"epsilon": float(result["log_epsilon"].values[-1]),
                  "delta": float(result["log_delta"].values[-1])},
        "over_time": marks, "commands": log,
    }
    name = f"cloud_field{'_workers' + str(args.workers) if args.workers else ''}.json"
    (out / name).write_text(json.dumps(summary, indent=1) + "\n")
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
