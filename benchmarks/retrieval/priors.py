"""The ablation of the loss's prior terms (issue 51): each term alone beside the L1 term and
the best combinations, at equal compute, on the single cloud and the two cumuli; the seed
paper's cloud field is judged with the winners, not tuned on.

Each run is ``retrieval.single_cloud`` (measurements and carved start cached as there) with
a fixed photon count and a photon budget (``--photon-budget``): runs stop after the same
number of traced photons, so they are compared at equal compute whatever else the machine
runs, and several run at once (``--jobs``, each with ``--threads`` numba threads). A scene's
count and budget are those of a 15-minute run on 2 cores with iterations of about 5 s at
the start (:data:`SCENES`; ``--minutes`` scales the budget). The result table gives, per
variant and scene, epsilon and delta (Eq. 54) at the photons of 10, 15 and 60 minutes
(:data:`MARKS`, those within the run's budget) and at the end, and epsilon's parts outside the
true cloud and in each optical-distance shell of the true cloud
(:func:`cloudct.retrieval.metrics.epsilon_by_shell`). Usage::

    python -m benchmarks retrieval.priors --scenes single_cloud two_cumuli \\
        --variants l1 l1+monotonic [--minutes 15] [--jobs 2 --threads 1] \\
        [--out benchmarks/results/priors]
    python -m benchmarks retrieval.priors --collect [--out ...]   (the table of the runs done)
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

from benchmarks.common import RESULTS, SHELL_LOG, WORK, markdown_table, run_header, write_result
from cloudct.retrieval.state import SHELL_PARTS

#: Per scene: the truth (None: the bundled single cloud), the gradient paths per iteration
#: (what photons "auto" settles at for 5-s iterations on the 2 cores of 2026-11-28) and the
#: iterations of 15 minutes at that rate (the budget: their photons, images' included).
SCENES = {
    "single_cloud": (None, 200_000, 180),
    "two_cumuli": (str(WORK / "two_cumuli.nc"), 650_000, 180),
}
#: The variants: their options of cloudct retrieve (the run's defaults otherwise).
VARIANTS = {
    "none": ["--prior", "none"],
    "l1": ["--prior", "l1=0.01"],
    "l1+smoothness": ["--prior", "l1=0.01", "smoothness=1e-4"],
    "l1+smoothness,seed1": ["--prior", "l1=0.01", "smoothness=1e-4", "--seed", "1"],
    "l1+smoothness4": ["--prior", "l1=0.01", "smoothness=4e-4"],
    "l1+smoothness16": ["--prior", "l1=0.01", "smoothness=1.6e-3"],
    "l1+huber": ["--prior", "l1=0.01", "smoothness=1e-4,huber=200"],
    "l1+monotonic": ["--prior", "l1=0.01", "monotonic=1e-3"],
    "l1+monotonic4": ["--prior", "l1=0.01", "monotonic=4e-3"],
    "l1+adiabatic": ["--prior", "l1=0.01", "adiabatic=4e-4"],
    "l1+adiabatic4": ["--prior", "l1=0.01", "adiabatic=1.6e-3"],
    "l1+adiabatic16": ["--prior", "l1=0.01", "adiabatic=6.4e-3"],
    "l1+adiabatic64": ["--prior", "l1=0.01", "adiabatic=2.56e-2"],
    "l1+adiabatic16-fixed": ["--prior", "l1=0.01", "adiabatic=6.4e-3,schedule=fixed"],
    "adiabatic4": ["--prior", "adiabatic=1.6e-3"],
    "l1,adiabatic-start": ["--prior", "l1=0.01", "--profile", "adiabatic"],
    "l1+smoothness+adiabatic": ["--prior", "l1=0.01", "smoothness=1e-4", "adiabatic=4e-4"],
    "l1+smoothness+adiabatic,adiabatic-start": ["--prior", "l1=0.01", "smoothness=1e-4",
                                                "adiabatic=4e-4", "--profile", "adiabatic"],
    # the README's command before issue 51: 400,000 sample-matching paths, step 1 on the
    # threshold schedule, a fixed L1 weight of 0.005, no averaging
    "previous-readme": ["--photons", "400000", "--image-photons", "2", "--step", "1",
                        "--schedule", "threshold", "--plateau", "step", "--step-floor", "0",
                        "--saturation-window", "10", "--prior", "l1=0.005,schedule=fixed",
                        "--averaging", "none"],
}
PARTS = SHELL_LOG


#: The marks of the table: epsilon / delta once the photons of this many 2-core minutes are
#: traced (a longer budget's run read at a shorter one's).
MARKS = (10.0, 15.0, 60.0)


def photons_per_minute(scene: str) -> float:
    """The photons a minute of 2 cores traces on the scene (the gradient's and 2x the
    images'), at the count of :data:`SCENES`."""
    _, photons, iterations = SCENES[scene]
    return 3 * photons * iterations / 15.0


def at_budget(log: dict, photons: float) -> int | None:
    """The index of the iteration at which the photons traced reach ``photons`` (as the run
    stops at its budget), None where the run stopped before."""
    traced = np.cumsum(log["photons"])
    reached = np.nonzero(traced >= photons * (1.0 - 1e-9))[0]
    return int(reached[0]) if reached.size else None


def run_path(out: Path, scene: str, variant: str) -> Path:
    return out / f"{scene}__{variant}.json"


def run_variant(scene: str, variant: str, minutes: float, threads: int, out: Path) -> int:
    """One run of ``retrieval.single_cloud`` for the variant on the scene."""
    truth, photons, iterations = SCENES[scene]
    budget = photons_per_minute(scene) * minutes
    command = [sys.executable, "-m", "benchmarks", "retrieval.single_cloud",
               "--photons", str(photons), "--photon-budget", f"{budget:.0f}",
               "--minutes", "100000", "--final-loss-photons", "0",
               "--output", str(run_path(out, scene, variant)),
               "--medium-output", str(WORK / "priors" / f"{scene}__{variant}.nc"),
               *VARIANTS[variant]]
    if truth is not None:
        command += ["--truth", truth]
    env = {**os.environ, "NUMBA_NUM_THREADS": str(threads)}
    print(" ".join(command[1:]), flush=True)
    with open(run_path(out, scene, variant).with_suffix(".log"), "w") as log:
        return subprocess.run(command, env=env, stdout=log, stderr=subprocess.STDOUT).returncode


def collect(out: Path) -> dict:
    """The runs in ``out``: per scene and variant, the final epsilon, delta and parts."""
    rows = {}
    for path in sorted(out.glob("*__*.json")):
        scene, variant = path.stem.split("__")
        run = json.loads(path.read_text())
        log = run["log"]
        marks = {}
        for minutes in MARKS:
            i = at_budget(log, photons_per_minute(scene) * minutes)
            if i is not None:
                marks[f"{minutes:g} min"] = [log["epsilon"][i], log["delta"][i]]
        rows.setdefault(scene, {})[variant] = {"marks": marks,
            "iterations": run["iterations"], "photons": sum(log["photons"]),
            "epsilon": log["epsilon"][-1], "delta": log["delta"][-1],
            "start": run["initial"], "options": VARIANTS.get(variant),
            **{part: log[part][-1] for part in PARTS},
        }
    return rows


def markdown(result: dict) -> str:
    lines = []
    for scene, variants in result["runs"].items():
        marks = [f"{m:g} min" for m in MARKS
                 if any(f"{m:g} min" in r["marks"] for r in variants.values())]
        rows = [[v, str(r["iterations"]),
                 *(" / ".join(f"{x:+.3f}" if j else f"{x:.3f}"
                              for j, x in enumerate(r["marks"][m])) if m in r["marks"] else ""
                   for m in marks),
                 f"{r['epsilon']:.3f} / {r['delta']:+.3f}",
                 *(f"{r[p]:.3f}" for p in PARTS)] for v, r in variants.items()]
        lines += [f"### {scene}", "", *markdown_table(
            ["variant", "iterations", *(f"{m}: epsilon / delta" for m in marks),
             "end: epsilon / delta", "outside",
             *(f"in the cloud, {part}" for part in SHELL_PARTS[1:])], rows), ""]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenes", nargs="+", choices=tuple(SCENES), default=list(SCENES))
    parser.add_argument("--variants", nargs="+", choices=tuple(VARIANTS), default=[])
    parser.add_argument("--minutes", type=float, default=15.0,
                        help="the budget as minutes of 2 cores (default %(default)s)")
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--out", type=Path, default=RESULTS / "priors")
    parser.add_argument("--collect", action="store_true", help="only tabulate the runs done")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    if not args.collect:
        todo = [(s, v) for v in args.variants for s in args.scenes]
        with ThreadPoolExecutor(args.jobs) as pool:
            codes = list(pool.map(lambda sv: run_variant(*sv, args.minutes, args.threads,
                                                         args.out), todo))
        failed = [sv for sv, code in zip(todo, codes, strict=True) if code]
        if failed:
            print(f"failed: {failed} (their .log files in {args.out})", file=sys.stderr)
    write_result({**run_header(args), "runs": collect(args.out)}, args.out / "summary",
                 markdown)


if __name__ == "__main__":
    main()
