"""What the exponential assumption costs: the single cloud retrieved from power-law
measurements under each transmittance assumption (docs/transmittance.md).

The true medium is the seed paper's single cloud with the power-law transmittance of
shape a (default 2) in every voxel, the unresolved sub-grid variability of a cloud whose
optical depth varies inside a voxel with relative variance 1 / a. Its measurements (nine
76 x 76 views, sun at the zenith) record the model. From the same soft-carved start, the
commands a user types retrieve the extinction

- under the exponential assumption, with the path score function (the estimator that can
  also differentiate the model, so that the two runs differ in the assumption only), and
- under the measurements' model (``--transmittance medium``, the score function),
- and, as the best exponential retrieval cloudct has, under the exponential assumption with
  its defaults (sample matching from residual-drawn pixels),

each for the same wall time, and reports epsilon and delta over time. It also renders the
true extinction under each assumption against the measurements: the loss that remains at
the truth when the assumption is wrong.

    python -m benchmarks retrieval.transmittance [--minutes 15] [--shape 2] [--out DIR]

Writes DIR/transmittance_retrieval.json and the figure docs/figures/transmittance_retrieval.png.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from benchmarks.common import (
    REPO,
    RESULTS,
    error_figure,
    error_markdown,
    error_over_time,
    loss_at_the_truth,
    run_command,
    run_header,
    write_result,
)
from cloudct.mc.render import single_cloud_medium
from cloudct.measurements import load_measurements
from cloudct.medium import save_medium, with_transmittance

FIGURE = REPO / "docs" / "figures" / "transmittance_retrieval.png"

#: name -> options of cloudct retrieve (besides the files and the time limit)
RUNS = {
    "exponential_score": ["--estimator", "score", "--photons", "200000"],
    "medium_score": ["--transmittance", "medium", "--photons", "200000"],
    "exponential_defaults": [],
}


LABELS = {"exponential_score": "exponential (score function)",
          "medium_score": "power law, --transmittance medium (score function)",
          "exponential_defaults": "exponential (defaults: sample matching)"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=15.0, help="per retrieval")
    parser.add_argument("--shape", type=float, default=2.0, help="the power law's a")
    parser.add_argument("--measurement-photons", type=int, default=10_000_000)
    parser.add_argument("--runs", nargs="+", choices=list(RUNS), default=list(RUNS))
    parser.add_argument("--out", type=Path,
                        default=RESULTS / "transmittance_retrieval")
    args = parser.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    summary = {**run_header(args), "shape": args.shape, "minutes": args.minutes, "runs": {}}
    truth = with_transmittance(single_cloud_medium(), "gamma", args.shape)
    f = {name: str(out / name) for name in ("truth.nc", "measurements.nc", "init.nc")}
    log: list[dict] = []
    if not (out / "measurements.nc").exists():
        save_medium(truth, f["truth.nc"], overwrite=True)
        run_command(["synth", f["truth.nc"], "--photons", str(args.measurement_photons), "-o",
                     f["measurements.nc"]], log)
    if not (out / "init.nc").exists():
        run_command(["carve", f["measurements.nc"], "--medium", f["truth.nc"], "-o",
                     f["init.nc"]], log)
    summary["loss_at_the_truth"] = loss_at_the_truth(
        {"exponential": with_transmittance(truth, "exponential"), "medium": truth},
        load_measurements(f["measurements.nc"]), 2_000_000)
    for name in args.runs:
        result = str(out / f"{name}.nc")
        run_command(["retrieve", f["measurements.nc"], "--init", f["init.nc"], "--truth",
                     f["truth.nc"], "--time-limit", str(60 * args.minutes), "--iterations",
                     "100000", *RUNS[name], "-o", result, "--overwrite"], log)
        summary["runs"][name] = error_over_time(result, minutes=(5, 10, 15, 30, 60))
    summary["commands"] = log
    error_figure({LABELS[name]: out / f"{name}.nc" for name in args.runs}, FIGURE,
                 "single cloud, power-law measurements (a = 2), retrieved under each "
                 "assumption")
    write_result(summary, out / "transmittance_retrieval", error_markdown)


if __name__ == "__main__":
    main()
