"""GPU benchmark: the forward render of the seed paper's single-cloud scene, GPU and CPU.

Scene: bundled RICO cloud 32x37x26 (:func:`cloudct.mc.render.single_cloud_medium`), nine
76x76 cameras at 2 km, sun at zenith, open boundaries
(:func:`cloudct.mc.scene.single_cloud_scene`). For each back end: photons per second,
scattering events (path vertices) per second, and the Monte Carlo efficiency 1 / (relative
variance x wall time), where the relative variance is the mean over bright pixels (radiance
above 10% of the view's maximum) of (standard error / radiance)^2, from independent batches
(the definition of ``benchmarks/forward/single_cloud.py``). The first call of each back end
(JIT compilation, or loading the CPU's on-disk cache) is timed separately and excluded:
``compile_s`` is its time minus that of an identical second call. GPU and CPU view-mean
radiances are compared as z-scores.

Usage (one command on a GPU machine; writes JSON and a markdown summary)::

    python -m benchmarks gpu.forward [--backend both|cuda|cpu] [--gpu-photons 16777216]
        [--cpu-photons 1000000] [--batches 32] [--output benchmarks/results/gpu_forward]

``--backend cuda`` or ``both`` (the default) exits with a message where there is no GPU.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

import numpy as np

from benchmarks.common import RESULTS, run_header, write_result
from benchmarks.forward.single_cloud import relative_variance, view_means


def device_name(backend: str) -> str:
    if backend == "cuda":
        from numba import config, cuda

        if config.ENABLE_CUDASIM:
            return "CUDA simulator"
        dev = cuda.get_current_device()
        name = dev.name.decode() if isinstance(dev.name, bytes) else str(dev.name)
        major, minor = dev.compute_capability
        return f"{name} (compute capability {major}.{minor})"
    return f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores"


def run(backend: str, photons: int, batches: int, seed: int, medium, scene) -> dict:
    """Warm-up (compile) calls, then one timed render on ``backend``."""
    from cloudct.mc.render import render_batches

    warm = dict(photons=batches * 8, batches=batches, seed=seed, progress=False,
                backend=backend)
    t0 = time.perf_counter()
    render_batches(medium, scene, **warm)
    t1 = time.perf_counter()
    render_batches(medium, scene, **warm)
    t2 = time.perf_counter()
    b, info = render_batches(
        medium, scene, photons=photons, batches=batches, seed=seed, progress=False,
        backend=backend,
    )
    call = time.perf_counter() - t2
    wall = info["wall_time"]
    mean = b.mean(axis=0)
    rv = relative_variance(mean, b.var(axis=0, ddof=1) / batches)
    vm, vse = view_means(b)
    return {
        "backend": info["backend"], "device": device_name(backend),
        "photons": info["photons"], "batches": batches, "events": info["events"],
        "compile_s": (t1 - t0) - (t2 - t1), "first_call_s": t1 - t0,
        "wall_s": wall, "call_s": call,
        "photons_per_s": info["photons"] / wall, "events_per_s": info["events"] / wall,
        "relative_variance": rv, "relative_error_bright": float(np.sqrt(rv)),
        "efficiency": 1.0 / (rv * wall), "view_mean": vm.tolist(), "view_mean_se": vse.tolist(),
    }


def markdown(result: dict) -> str:
    rows = [("device", "{}"), ("photons", "{:,}"), ("events", "{:,}"), ("compile_s", "{:.2f}"),
            ("wall_s", "{:.3f}"), ("photons_per_s", "{:.4g}"), ("events_per_s", "{:.4g}"),
            ("relative_error_bright", "{:.4g}"), ("efficiency", "{:.4g}")]
    names = [b for b in ("cuda", "cpu") if b in result]
    lines = [
        "# GPU forward benchmark: single-cloud scene (9 views, 76x76)",
        "",
        f"{result['date']}, `{result['command']}`",
        "",
        "| quantity | " + " | ".join(names) + " |",
        "| --- | " + " | ".join("---" for _ in names) + " |",
    ]
    for key, fmt in rows:
        lines.append(f"| {key} | " + " | ".join(fmt.format(result[n][key]) for n in names) + " |")
    if "speedup_photons_per_s" in result:
        lines += [
            "",
            f"GPU / CPU: photons per second x{result['speedup_photons_per_s']:.3g}, "
            f"efficiency x{result['efficiency_ratio']:.3g}; view-mean z-scores "
            + ", ".join(f"{z:+.2f}" for z in result["view_mean_z"]) + ".",
        ]
    lines += [
        "",
        "efficiency = 1 / (relative variance x wall time); relative variance = mean over "
        "bright pixels (above 10% of the view's maximum) of (standard error / radiance)^2. "
        "compile_s (JIT, or CPU cache load) is excluded from wall_s.",
    ]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--backend", choices=("both", "cuda", "cpu"), default="both")
    parser.add_argument("--gpu-photons", type=int, default=1 << 24)
    parser.add_argument("--cpu-photons", type=int, default=1_000_000)
    parser.add_argument("--batches", type=int, default=32)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", default=str(RESULTS / "gpu_forward"),
                        help="output path without suffix (.json and .md are written)")
    args = parser.parse_args()

    from cloudct.mc.backend import cuda_unavailable_reason

    if args.backend in ("both", "cuda"):
        reason = cuda_unavailable_reason()
        if reason is not None:
            print(f"gpu_forward: no GPU to benchmark: {reason}. "
                  "Run with --backend cpu for the CPU figures alone.", file=sys.stderr)
            return 2

    from cloudct.mc.render import single_cloud_medium
    from cloudct.mc.scene import single_cloud_scene
    from cloudct.medium import cell_edges

    medium = single_cloud_medium()
    edges = cell_edges(medium)
    scene = single_cloud_scene(np.array([e[0] for e in edges]), np.array([e[-1] for e in edges]))
    result = {**run_header(args),
              "scene": "single cloud 32x37x26, 9 cameras 76x76, sun at zenith, open"}
    if args.backend in ("both", "cuda"):
        result["cuda"] = run("cuda", args.gpu_photons, args.batches, args.seed, medium, scene)
    if args.backend in ("both", "cpu"):
        result["cpu"] = run("cpu", args.cpu_photons, args.batches, args.seed + 1, medium, scene)
    if "cuda" in result and "cpu" in result:
        g, c = result["cuda"], result["cpu"]
        result["speedup_photons_per_s"] = g["photons_per_s"] / c["photons_per_s"]
        result["efficiency_ratio"] = g["efficiency"] / c["efficiency"]
        result["view_mean_z"] = (
            (np.array(g["view_mean"]) - c["view_mean"])
            / np.hypot(g["view_mean_se"], c["view_mean_se"])
        ).tolist()
    write_result(result, args.output, markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
