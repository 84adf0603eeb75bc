"""The README's main job as a user meets it: ``cloudct demo`` run twice into a fresh folder,
first with an empty kernel cache (the first run after an install compiles every kernel),
then again with the cache it filled; the wall time of each (measurements, carving, the
retrieval, the report) and the error of the result against the truth.

Each run is the ``cloudct`` command next to this Python (a separate process, as a user
types it) with ``CLOUDCT_CACHE_DIR`` set to a fresh folder for the pair. The result's
epsilon and delta (Eq. 54) are those of the last iterate and of the iterates' average
(``cloud_extinction_average``), read from ``result.nc`` against ``truth.nc``. Usage::

    python -m benchmarks retrieval.demo [--scene single-cloud] \
        [--output benchmarks/results/demo]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from benchmarks.common import RESULTS, WORK, markdown_table, run_header, write_result


def demo_run(scene: str, folder: Path, cache: Path) -> dict:
    """One ``cloudct demo --overwrite`` into ``folder`` with the kernel cache at ``cache``:
    its wall time and its result's epsilon and delta."""
    import xarray as xr

    from cloudct.retrieval.metrics import epsilon_delta

    command = [str(Path(sys.executable).with_name("cloudct")), "demo", "--scene", scene,
               "-o", str(folder), "--overwrite"]
    env = {**os.environ, "CLOUDCT_CACHE_DIR": str(cache)}
    start = time.perf_counter()
    subprocess.run(command, env=env, check=True)
    seconds = time.perf_counter() - start
    truth = xr.load_dataset(folder / "truth.nc")["cloud_extinction"].values
    result = xr.load_dataset(folder / "result.nc")
    eps, delta = epsilon_delta(truth, result["cloud_extinction"].values)
    eps_a, delta_a = epsilon_delta(truth, result["cloud_extinction_average"].values)
    return {"seconds": seconds, "iterations": int(result.sizes["iteration"]),
            "epsilon": eps, "delta": delta, "epsilon_average": eps_a, "delta_average": delta_a}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--scene", choices=("single-cloud", "cloud-field"),
                        default="single-cloud")
    parser.add_argument("--output", default=str(RESULTS / "demo"))
    args = parser.parse_args()

    header = run_header(args)
    folder = WORK / f"demo_{args.scene}"
    runs = {}
    with tempfile.TemporaryDirectory(prefix="cloudct_cache_") as cache:
        for name in ("empty kernel cache", "cache filled by the first run"):
            runs[name] = demo_run(args.scene, folder, Path(cache))
            print(name, runs[name], flush=True)
    shutil.rmtree(folder, ignore_errors=True)
    write_result({**header, "runs": runs}, args.output, markdown)


def markdown(result: dict) -> str:
    rows = [[name, f"{r['seconds'] / 60:.1f} min", str(r["iterations"]),
             f"{r['epsilon']:.1%} / {r['delta']:+.1%}",
             f"{r['epsilon_average']:.1%} / {r['delta_average']:+.1%}"]
            for name, r in result["runs"].items()]
    return "\n".join(markdown_table(
        ["run", "wall time", "iterations", "last iterate: epsilon / delta",
         "average of the iterates: epsilon / delta"], rows)) + "\n"


if __name__ == "__main__":
    main()
