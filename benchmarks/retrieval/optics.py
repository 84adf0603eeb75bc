"""What the Henyey-Greenstein assumption costs, and how well a Mie retrieval does: the single
cloud retrieved from Mie measurements (issue 38, step 1).

The true medium is the seed paper's single cloud with Mie optics (``--optics mie``: Mie
albedos and phase functions of its droplets, a diffraction peak of hundreds per sr). Its
measurements (nine 76 x 76 views, sun at the zenith) record the optics. From a soft-carved
start with each optics (``cloudct carve --optics mie`` or ``hg``: the same hull and
extinction, the template's cloud optics), the commands a user types retrieve the extinction

- with Mie optics and each gradient estimator (``mie_sm``, the defaults; ``mie_drt``,
  ``mie_score``), and
- assuming Henyey-Greenstein optics (g 0.85, albedo 0.99; ``hg_sm``, the defaults),

each for the same wall time, and reports epsilon and delta over time. It also renders the
true extinction with each optics against the measurements: the loss that remains at the
truth when the optics are wrong.

    python -m benchmarks retrieval.optics [--minutes 15] [--runs mie_sm hg_sm ...] [--out DIR]

Writes DIR/optics_retrieval.json and the figure docs/figures/optics_retrieval.png (of the
runs made in this call).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from benchmarks.common import (
    REPO,
    RESULTS,
    error_figure,
    error_over_time,
    loss_at_the_truth,
    run_command,
    run_header,
    write_result,
)
from cloudct.mc.render import single_cloud_medium
from cloudct.measurements import load_measurements
from cloudct.medium import save_medium

FIGURE = REPO / "docs" / "figures" / "optics_retrieval.png"

#: name -> (the optics of its initial medium, options of cloudct retrieve besides the files
#: and the time limit)
RUNS = {
    "mie_sm": ("mie", []),
    "mie_drt": ("mie", ["--estimator", "drt"]),
    "mie_score": ("mie", ["--estimator", "score"]),
    "hg_sm": ("hg", []),
}
LABELS = {"mie_sm": "Mie optics (defaults: sample matching)",
          "mie_drt": "Mie optics, DRT", "mie_score": "Mie optics, score function",
          "hg_sm": "assuming HG (defaults: sample matching)"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=15.0, help="per retrieval")
    parser.add_argument("--measurement-photons", type=int, default=10_000_000)
    parser.add_argument("--runs", nargs="+", choices=list(RUNS), default=list(RUNS))
    parser.add_argument("--out", type=Path, default=RESULTS / "optics_retrieval")
    args = parser.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    summary = {**run_header(args), "minutes": args.minutes, "runs": {}}
    truth = single_cloud_medium("mie")
    f = {name: str(out / name) for name in ("truth.nc", "measurements.nc")}
    log: list[dict] = []
    if not (out / "measurements.nc").exists():
        save_medium(truth, f["truth.nc"], overwrite=True)
        run_command(["synth", "--optics", "mie", "--photons", str(args.measurement_photons),
                     "-o", f["measurements.nc"]], log)
    for optics in sorted({RUNS[name][0] for name in args.runs}):
        init = out / f"init_{optics}.nc"
        if not init.exists():
            run_command(["carve", f["measurements.nc"], "--optics", optics, "-o", str(init)],
                        log)
    summary["loss_at_the_truth"] = loss_at_the_truth(
        {"mie": truth, "hg": single_cloud_medium("hg")},
        load_measurements(f["measurements.nc"]), 2_000_000)
    for name in args.runs:
        optics, options = RUNS[name]
        result = str(out / f"{name}.nc")
        run_command(["retrieve", f["measurements.nc"], "--init", str(out / f"init_{optics}.nc"),
                     "--truth", f["truth.nc"], "--time-limit", str(60 * args.minutes),
                     "--iterations", "100000", *options, "-o", result, "--overwrite"], log)
        summary["runs"][name] = error_over_time(result, minutes=(5, 10, 15, 30, 60))
    summary["commands"] = log
    error_figure({LABELS[name]: out / f"{name}.nc" for name in args.runs}, FIGURE,
                 "single cloud, Mie measurements, retrieved with Mie optics and assuming HG")
    write_result(summary, out / "optics_retrieval")


if __name__ == "__main__":
    main()
