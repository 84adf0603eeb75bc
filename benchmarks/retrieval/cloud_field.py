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
        [--workers 2] [OPTIONS] -o NAME.nc
    cloudct report NAME.nc --truth truth.nc --measurements measurements.nc -o NAME_report

    python -m benchmarks retrieval.cloud_field --minutes 60 [--workers 2] [--name NAME] [--out DIR]
        [-- OPTIONS of cloudct retrieve]

Epsilon and delta over time are in NAME.nc (log_seconds, log_epsilon, log_delta) and in
DIR/NAME.json (NAME: cloud_field by default). ``--figure NAME [NAME ...]`` runs nothing and
draws the named runs' epsilon and delta against time to docs/figures/cloud_field.png.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from benchmarks.common import (
    REPO,
    RESULTS,
    error_figure,
    error_over_time,
    over_time_markdown,
    run_command,
    run_header,
    write_result,
)
from cloudct.les import seed_paper_cloud_field
from cloudct.medium import save_medium
from cloudct.optics import to_optical

FIGURE = REPO / "docs" / "figures" / "cloud_field.png"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=60.0, help="retrieval time limit")
    parser.add_argument("--measurement-photons", type=int, default=10_000_000)
    parser.add_argument("--workers", type=int, help="retrieve on a local Dask cluster")
    parser.add_argument("--name", default="cloud_field", help="of the result files")
    parser.add_argument("--out", type=Path, default=RESULTS / "cloud_field")
    parser.add_argument("--figure", nargs="+", metavar="NAME",
                        help="only draw these runs' epsilon and delta against time")
    parser.add_argument("retrieve_options", nargs=argparse.REMAINDER,
                        help="after --: more options of cloudct retrieve (e.g. --config FILE)")
    args = parser.parse_args()
    out = args.out
    if args.figure:
        error_figure({name: out / f"{name}.nc" for name in args.figure}, FIGURE,
                     "the seed paper's cloud field (79 x 84 x 27), from the carved start")
        return
    out.mkdir(parents=True, exist_ok=True)
    truth = to_optical(seed_paper_cloud_field())
    save_medium(truth, out / "truth.nc", overwrite=True)
    f = {name: str(out / name) for name in ("truth.nc", "scene.nc", "measurements.nc",
                                            "init.nc")}
    result = str(out / f"{args.name}.nc")
    log: list[dict] = []
    if not (out / "measurements.nc").exists():
        run_command(["scene", f["truth.nc"], "--preset", "cloud-field", "-o", f["scene.nc"],
                     "--figure", str(out / "scene.png"), "--overwrite"], log)
        run_command(["synth", f["truth.nc"], "--scene", f["scene.nc"], "--photons",
                     str(args.measurement_photons), "-o", f["measurements.nc"]], log)
    if not (out / "init.nc").exists():
        run_command(["carve", f["measurements.nc"], "--medium", f["truth.nc"], "-o",
                     f["init.nc"], "--figure", str(out / "hull.png")], log)
    retrieve = ["retrieve", f["measurements.nc"], "--init", f["init.nc"], "--truth",
                f["truth.nc"], "--time-limit", str(60 * args.minutes), "--iterations",
                "100000", "-o", result, "--overwrite"]
    if args.workers:
        retrieve += ["--workers", str(args.workers)]
    retrieve += [a for a in args.retrieve_options if a != "--"]
    run_command(retrieve, log)
    run_command(["report", result, "--truth", f["truth.nc"], "--measurements",
                 f["measurements.nc"], "-o", str(out / f"{args.name}_report")], log)

    summary = {**run_header(args), "grid": list(truth["cloud_extinction"].shape),
               **error_over_time(result), "commands": log}
    write_result(summary, out / args.name, over_time_markdown)


if __name__ == "__main__":
    main()
