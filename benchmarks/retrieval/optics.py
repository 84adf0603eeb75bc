"""What the Henyey-Greenstein assumption costs, and how well a Mie retrieval does: the single
cloud retrieved from Mie measurements (issue 38, step 1).

The true medium is the seed paper's single cloud with Mie optics (``--optics mie``: Mie
albedos and phase functions of its droplets, a diffraction peak of hundreds per sr). Its
measurements (nine 76 x 76 views, sun at the zenith) record the optics. From a soft-carved
start with each optics (``cloudct carve --optics mie`` or ``hg``: the same hull and
extinction, the template's cloud optics), the commands a user types retrieve the extinction

- with Mie optics and the full forward peak (``--phase-truncation 0``) and each gradient
  estimator (``mie_sm``: sample matching, the default before a Mie medium's retrieval took
  the score function; ``mie_drt``; ``mie_score``; ``mie_combined``, the score function of
  forward photons and camera paths weighted by multiple importance sampling;
  ``mie_combined_images``, also the residual's images by the combined estimator;
  ``mie_combined_recycled``, both with adaptive path recycling: forward paths replayed,
  camera paths fresh), and with
  the phase functions' forward peak cut flat at 3 degrees for the retrieval's paths
  (``--phase-truncation 3``, a Mie medium's default now; ``mie_cut3_sm`` with the default
  estimator, ``mie_cut3_score``; the measurements keep the full peak), and
- assuming Henyey-Greenstein optics (g 0.85, albedo 0.99; ``hg_sm``: sample matching, the
  default with HG optics),

each for the same wall time, and reports epsilon and delta over time; the references
(``reference_sm``, ``reference_score``, ``reference_drt``) retrieve HG measurements of the
same cloud with HG optics and the same settings: the issue's target is a Mie retrieval
within 0.05 in epsilon of its reference. It also renders the true extinction with each
optics against the Mie measurements: the loss that remains at the truth when the optics
are wrong.

    python -m benchmarks retrieval.optics [--minutes 15] [--runs mie_sm hg_sm ...]
        [--backend cpu|cuda|auto] [--out DIR] [--figure PNG] [--collect]

Writes DIR/optics_retrieval.json (``_cuda`` or ``_auto`` after the name with another back
end; the runs of earlier calls stay in it, each with its date and commit) and the figure
(default docs/figures/optics_retrieval.png, same suffix) of the runs whose result files are
in DIR. On a GPU each run is preceded by a two-iteration retrieval that compiles its
kernels, outside the timed run. ``--collect`` retrieves nothing: it adds the runs' existing
result files to the summary (a call that ended before writing it).
"""

from __future__ import annotations

import argparse
import json
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
from cloudct.medium import save_medium

FIGURE = REPO / "docs" / "figures" / "optics_retrieval.png"

#: name -> (the optics of its measurements, of its initial medium, options of cloudct retrieve
#: besides the files and the time limit)
RUNS = {
    "mie_sm": ("mie", "mie", ["--estimator", "sm", "--phase-truncation", "0"]),
    "mie_drt": ("mie", "mie", ["--estimator", "drt", "--phase-truncation", "0"]),
    "mie_score": ("mie", "mie", ["--estimator", "score", "--phase-truncation", "0"]),
    "mie_combined": ("mie", "mie", ["--estimator", "combined", "--phase-truncation", "0"]),
    "mie_combined_images": ("mie", "mie", ["--estimator", "combined", "--image-method",
                                           "combined", "--phase-truncation", "0"]),
    "mie_combined_recycled": ("mie", "mie", ["--estimator", "combined", "--image-method",
                                             "combined", "--phase-truncation", "0",
                                             "--recycling", "adaptive"]),
    "mie_cut3_score": ("mie", "mie", ["--estimator", "score", "--phase-truncation", "3"]),
    "mie_cut3_sm": ("mie", "mie", ["--estimator", "sm", "--phase-truncation", "3"]),
    "hg_sm": ("mie", "hg", ["--estimator", "sm"]),
    "reference_sm": ("hg", "hg", ["--estimator", "sm"]),
    "reference_score": ("hg", "hg", ["--estimator", "score"]),
    "reference_drt": ("hg", "hg", ["--estimator", "drt"]),
}
LABELS = {"mie_sm": "Mie optics, sample matching",
          "mie_drt": "Mie optics, DRT", "mie_score": "Mie optics, score function",
          "mie_combined": "Mie optics, combined score function",
          "mie_combined_images": "Mie optics, combined score function and images",
          "mie_combined_recycled": "Mie optics, combined, recycled (adaptive)",
          "mie_cut3_score": "Mie optics cut at 3 degrees, score function",
          "mie_cut3_sm": "Mie optics cut at 3 degrees, sample matching",
          "hg_sm": "assuming HG, sample matching",
          "reference_sm": "reference: HG images, HG optics, sample matching",
          "reference_score": "reference: HG images, HG optics, score function",
          "reference_drt": "reference: HG images, HG optics, DRT"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--minutes", type=float, default=15.0, help="per retrieval")
    parser.add_argument("--measurement-photons", type=int, default=10_000_000)
    parser.add_argument("--measurement-method", choices=("forward", "combined"), default=None,
                        help="the measurements' render (`cloudct synth --method`; default: "
                        "combined with Mie optics, else forward; runs before 2026-11-27 14:00 "
                        "rendered forward)")
    parser.add_argument("--runs", nargs="+", choices=list(RUNS), default=list(RUNS)[:4])
    parser.add_argument("--backend", choices=("cpu", "cuda", "auto"), default="cpu",
                        help="of every command (default cpu: the 2-core table)")
    parser.add_argument("--out", type=Path, default=RESULTS / "optics_retrieval")
    parser.add_argument("--figure", type=Path, help=f"default {FIGURE} (back-end suffix)")
    parser.add_argument("--collect", action="store_true",
                        help="summarise the runs' existing result files, retrieve nothing")
    args = parser.parse_args()
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    backend = ["--backend", args.backend]
    summary = {**run_header(args), "minutes": args.minutes, "runs": {}}
    log: list[dict] = []
    for optics in sorted({RUNS[name][0] for name in args.runs} if not args.collect else ()):
        if not _file(out, optics, "measurements.nc").exists():
            save_medium(single_cloud_medium(optics), str(_file(out, optics, "truth.nc")),
                        overwrite=True)
            method = [] if args.measurement_method is None else [
                "--method", args.measurement_method]
            run_command(["synth", "--optics", optics, "--photons",
                         str(args.measurement_photons), *method, *backend,
                         "-o", str(_file(out, optics, "measurements.nc"))], log)
    for measured, optics in sorted({RUNS[name][:2] for name in args.runs}
                                   if not args.collect else ()):
        init = _file(out, measured, f"init_{optics}.nc")
        if not init.exists():
            run_command(["carve", str(_file(out, measured, "measurements.nc")),
                         "--optics", optics, *backend, "-o", str(init)], log)
    if "mie" in {RUNS[name][0] for name in args.runs} and not args.collect:
        summary["loss_at_the_truth"] = loss_at_the_truth(
            {"mie": single_cloud_medium("mie"), "hg": single_cloud_medium("hg")},
            load_measurements(str(out / "measurements.nc")), 2_000_000)
    suffix = "" if args.backend == "cpu" else f"_{args.backend}"
    for name in args.runs:
        measured, optics, options = RUNS[name]
        files = _file(out, measured, "measurements.nc"), _file(out, measured, f"init_{optics}.nc")
        result = str(out / f"{name}{suffix}.nc")
        if args.collect:
            summary["runs"][name] = {**error_over_time(result, minutes=(1, 2, 5, 10, 15, 30, 60)),
                                     "collected": "from the result file by --collect"}
            continue
        if args.backend != "cpu":  # compile the kernels first, outside the timed run
            run_command(["retrieve", str(files[0]), "--init", str(files[1]), "--iterations",
                         "2", "--photons", "20000", *options, *backend,
                         "-o", str(out / "warm_up.nc"), "--overwrite"], log)
        run_command(["retrieve", str(files[0]), "--init", str(files[1]), "--truth",
                     str(_file(out, measured, "truth.nc")), "--time-limit",
                     str(60 * args.minutes), "--iterations", "100000", *options, *backend,
                     "-o", result, "--overwrite"], log)
        summary["runs"][name] = {**error_over_time(result, minutes=(1, 2, 5, 10, 15, 30, 60)),
                                 **{key: summary[key] for key in ("date", "commit", "command")}}
    summary["commands"] = log
    output = out / f"optics_retrieval{suffix}"
    if output.with_suffix(".json").exists():  # earlier calls' runs stay, each with its call
        earlier = json.loads(output.with_suffix(".json").read_text())
        summary["runs"] = {**earlier["runs"], **summary["runs"]}
        summary["commands"] = earlier["commands"] + log
    device = "2 CPU cores" if args.backend == "cpu" else f"one GPU ({args.backend})"
    present = {LABELS[name]: out / f"{name}{suffix}.nc" for name in summary["runs"]
               if (out / f"{name}{suffix}.nc").exists()}
    error_figure(present, args.figure or FIGURE.with_name(f"{FIGURE.stem}{suffix}.png"),
                 "single cloud: Mie measurements retrieved with Mie optics and assuming HG, "
                 "and HG measurements with HG optics", device)
    write_result(summary, output, error_markdown)


def _file(out: Path, measured: str, name: str) -> Path:
    """``out/name`` for the Mie measurements (the benchmark's subject) and what is made of
    them, ``out/MEASURED_name`` for those of other optics (truth, measurements and carved
    starts ``init_OPTICS.nc`` alike)."""
    return out / (name if measured == "mie" else f"{measured}_{name}")


if __name__ == "__main__":
    main()
