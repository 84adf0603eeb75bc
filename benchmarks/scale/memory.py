"""The memory estimate of a gradient (``cloudct.mc.memory.peak_bytes``) against the
measured peak, on three grid sizes.

Media and scene as ``scale.cost_tables`` (the LES piece tiled to 10^5 and 10^6 voxels, and
256 x 256 x 100). Each size runs in its own process: the kernels are loaded on a small
piece first (so that the loading is not counted), then the resident memory is read, a
score-function gradient of a random residual runs with 32 batches and 2,000 photons, and
the peak resident memory (``ru_maxrss``) minus the memory before is the measured peak of
the call, against ``peak_bytes``. Usage::

    python -m benchmarks scale.memory [--sizes 1e5 1e6 256x256x100]
        [--output benchmarks/results/memory]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys

import numpy as np

from benchmarks.common import REPO, RESULTS, markdown_table, run_header, write_result

BATCHES = 32


def run_case(size: str) -> dict:
    """One size, in this process."""
    from benchmarks.scale.cost_tables import field_piece, scene_for
    from cloudct.mc.gradient import score_function_gradient
    from cloudct.mc.memory import peak_bytes, resident_bytes

    small = field_piece("1e4")
    residual = np.random.default_rng(0).normal(size=(9, 76, 76))
    score_function_gradient(small, scene_for(small), residual, photons=64, progress=False)
    medium = field_piece(size)
    scene = scene_for(medium)
    voxels = int(medium["cloud_extinction"].size)
    before = resident_bytes()
    score_function_gradient(medium, scene, residual, photons=2000, batches=BATCHES,
                            progress=False)
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
    estimate = peak_bytes(voxels, residual.size, BATCHES, gradient=True)
    return {"size": size, "voxels": voxels, "before_mib": before / 2**20,
            "measured_mib": (peak - before) / 2**20, "estimate_mib": estimate / 2**20,
            "estimate_over_measured": estimate / (peak - before)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", nargs="+", default=["1e5", "1e6", "256x256x100"])
    parser.add_argument("--output", default=str(RESULTS / "memory"))
    args = parser.parse_args()
    rows = []
    for size in args.sizes:
        code = ("import json; from benchmarks.scale.memory import run_case; "
                f"print('RESULT ' + json.dumps(run_case({size!r})))")
        proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                              cwd=REPO, check=True)
        line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")][-1]
        rows.append(json.loads(line[len("RESULT "):]))
        print(rows[-1], flush=True)
    result = {**run_header(args), "batches": BATCHES, "rows": rows}
    write_result(result, args.output, lambda r: "\n".join(markdown_table(
        ["size", "voxels", "before (MiB)", "measured peak (MiB)", "estimate (MiB)",
         "estimate / measured"],
        [[x["size"], str(x["voxels"]), f"{x['before_mib']:.0f}", f"{x['measured_mib']:.0f}",
          f"{x['estimate_mib']:.0f}", f"{x['estimate_over_measured']:.2f}"]
         for x in r["rows"]])))


if __name__ == "__main__":
    main()
