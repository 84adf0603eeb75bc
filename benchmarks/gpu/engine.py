"""The GPU as the retrieval's engine (issue 34): a warm start, and each gradient's paths per
second on the GPU against the CPU, on the seed paper's single cloud.

Prepared to run in one short call on a GPU machine (first run on an H100 on 2026-11-26:
``benchmarks/results/gpu_engine.md``):

1. **Warm start.** ``cloudct retrieve`` of the single cloud (measurements and carved start
   made first, on the GPU) run twice in new processes with an empty kernel cache
   (``CLOUDCT_CACHE_DIR`` in a temporary folder): the first process compiles the kernels,
   the second loads them (``cloudct.jit_cache``). Reported: each process's wall time to the
   end of its first iteration (``--iterations 1``), and the first iteration's own time from
   the result's log. The goal: the second within 10 s.
2. **Paths per second** of the forward render and of each gradient (score function, DRT,
   sample matching from every pixel and from residual-drawn pixels) on ``cuda`` and on the
   CPU with ``--cpu-threads`` numba threads (2: this project's development machine's
   cores), a random residual, compilation excluded by a warm-up call; and the score
   gradient's cost in renders per photon (the goal: at most 2.5).

Usage::

    python -m benchmarks gpu.engine [--paths 2000000] [--cpu-threads 2]
        [--output benchmarks/results/gpu_engine]

Without a GPU, ``--backend cpu`` runs both parts on the CPU alone (the warm start with
100,000 paths; ``--cpu-threads`` applies to part 2 only); ``--backend cuda`` runs them on
the GPU alone; ``--no-warm-start`` skips part 1. The result file is written after each
part, so that a run stopped by a time limit keeps what it measured.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks.common import RESULTS, WORK, markdown_table, run_header, write_result

#: The ``cloudct`` command, also where cloudct is not installed (only on the path).
CLOUDCT = [sys.executable, "-c", "import sys; from cloudct.cli import main; "
           "sys.exit(main(sys.argv[1:]))"]
ESTIMATORS = (("render", None), ("score", "uniform"), ("drt", "uniform"),
              ("sm", "uniform"), ("sm", "residual"))


def warm_start(work: Path, backend: str, photons: int) -> dict:
    """Part 1: two new processes of ``cloudct retrieve --iterations 1`` on ``backend`` with
    a cache that starts empty."""
    cache = Path(tempfile.mkdtemp(prefix="cloudct-cache-"))
    env = dict(os.environ, CLOUDCT_CACHE_DIR=str(cache / "retrieve"))
    meas, init = work / "measurements.nc", work / "init.nc"
    setup = [["synth", "-o", str(meas), "--photons", "20000000", "--backend", backend,
              "--overwrite"],
             ["carve", str(meas), "-o", str(init), "--backend", backend, "--overwrite"]]
    for argv in setup:  # with the caller's cache: only the retrievals start from an empty one
        subprocess.run([*CLOUDCT, *argv], check=True)
    runs = []
    for attempt in ("compiling", "cached"):
        out = work / f"warm_{attempt}.nc"
        start = time.perf_counter()
        subprocess.run([*CLOUDCT, "retrieve", str(meas), "--init", str(init), "-o", str(out),
                        "--iterations", "1", "--photons", str(photons), "--backend", backend,
                        "--overwrite"], env=env, check=True)
        import xarray as xr

        first = float(xr.load_dataset(out)["log_seconds"].values[0])
        runs.append({"process": attempt, "wall_s": time.perf_counter() - start,
                     "first_iteration_s": first})
    return {"cache": str(cache), "runs": runs}


def paths_per_second(backend: str, paths: int) -> dict:
    """Part 2 on one back end: seconds and paths per second of each estimator."""
    from cloudct.mc.gradient import gradient_estimate
    from cloudct.mc.render import render, single_cloud_medium
    from cloudct.mc.scene import single_cloud_scene
    from cloudct.medium import cell_edges

    medium = single_cloud_medium()
    edges = cell_edges(medium)
    scene = single_cloud_scene(np.array([e[0] for e in edges]),
                               np.array([e[-1] for e in edges]))
    shape = (len(scene.cameras), scene.cameras[0].nrows, scene.cameras[0].ncols)
    residual = np.random.default_rng(1).normal(size=shape)
    out = {}
    for name, sampling in ESTIMATORS:
        def run(n: int, name=name, sampling=sampling) -> tuple[float, int]:
            """Seconds and paths traced (the camera-side estimators' uniform pixel sampling
            rounds each pixel's samples up to a multiple of the batches)."""
            start = time.perf_counter()
            if name == "render":
                traced = render(medium, scene, photons=n, backend=backend,
                                progress=False).attrs["photons"]
            else:
                traced = gradient_estimate(medium, scene, residual, estimator=name, photons=n,
                                           pixel_sampling=sampling, backend=backend)[2]["photons"]
            return time.perf_counter() - start, int(traced)

        run(64 * int(np.prod(shape)) if name in ("drt", "sm") else 64)  # compile or load
        seconds, traced = run(paths)
        key = name if sampling in (None, "uniform") else f"{name}_{sampling}"
        out[key] = {"paths": paths, "paths_traced": traced, "seconds": seconds,
                    "paths_per_s": traced / seconds}
    out["score_renders_per_photon"] = out["score"]["seconds"] / out["render"]["seconds"]
    return out


def markdown(result: dict) -> str:
    lines = [f"# GPU engine ({result['date']}, {result['machine']}, "
             f"{result.get('device', 'no GPU')})", ""]
    if "warm_start" in result:
        lines += markdown_table(
            ["process", "wall time to the first iteration's end [s]", "first iteration [s]"],
            [[r["process"], f"{r['wall_s']:.1f}", f"{r['first_iteration_s']:.2f}"]
             for r in result["warm_start"]["runs"]]) + [""]
    backends = [b for b in ("cuda", "cpu") if b in result]
    rows = []
    for key in result[backends[0]]:
        if key == "score_renders_per_photon":
            continue
        cells = [key] + [f"{result[b][key]['paths_per_s']:.3g}" for b in backends]
        if len(backends) == 2:
            gain = result["cuda"][key]["paths_per_s"] / result["cpu"][key]["paths_per_s"]
            cells.append(f"{gain:.1f}")
        rows.append(cells)
    lines += markdown_table(["estimator", *[f"{b} paths/s" for b in backends]]
                            + (["GPU / CPU"] if len(backends) == 2 else []), rows)
    lines += ["", "Score gradient, renders per photon: " + ", ".join(
        f"{b} {result[b]['score_renders_per_photon']:.2f}" for b in backends), ""]
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--paths", type=int, default=2_000_000)
    parser.add_argument("--cpu-paths", type=int, default=200_000)
    parser.add_argument("--cpu-threads", type=int, default=2)
    parser.add_argument("--backend", choices=("both", "cuda", "cpu"), default="both")
    parser.add_argument("--no-warm-start", action="store_true",
                        help="part 2 only (paths per second)")
    parser.add_argument("--work", type=Path, default=WORK / "gpu_engine")
    parser.add_argument("--output", default=str(RESULTS / "gpu_engine"))
    args = parser.parse_args()
    result = run_header(args)
    args.work.mkdir(parents=True, exist_ok=True)
    if args.backend != "cpu":
        from cloudct.mc.backend import device_description, resolve_backend

        result["device"] = device_description(resolve_backend("cuda"))
        result["cuda"] = paths_per_second("cuda", args.paths)
        write_result(result, args.output, markdown)
        if not args.no_warm_start:
            result["warm_start"] = warm_start(args.work, "cuda", 1_000_000)
            write_result(result, args.output, markdown)
        if args.backend == "cuda":
            return
    elif not args.no_warm_start:
        result["warm_start"] = warm_start(args.work, "cpu", 100_000)
    import numba

    numba.set_num_threads(min(args.cpu_threads, numba.config.NUMBA_NUM_THREADS))
    result["cpu_threads"] = numba.get_num_threads()
    result["cpu"] = paths_per_second("cpu", args.cpu_paths)
    write_result(result, args.output, markdown)


if __name__ == "__main__":
    main()
