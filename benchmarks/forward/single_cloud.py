"""Forward-model benchmark on the seed paper's single-cloud scene, with Mitsuba 3 as the peer.

Scene: bundled RICO cloud 32x37x26 (Mie extinction at 0.672 micron, cloud albedo 0.99, HG
g = 0.85; air 0.04 /km, albedo 0.912, Rayleigh), open boundaries, sun at zenith, nine 76x76
cameras at 2 km (zenith + ring at 29 degrees).

Reported for each renderer: samples per second, path vertices per second (cloudct), the Monte
Carlo efficiency 1 / (relative variance x wall time) where the relative variance is the mean,
over bright pixels (radiance above 10% of the view's maximum), of each pixel's variance of the
mean divided by its squared mean, estimated from independent batches; and the JIT compilation
time, excluded from the efficiency. The two renderers' view-mean radiances are compared as
z-scores. Usage::

    python -m benchmarks forward.single_cloud [--photons 4000000] [--mitsuba-spp 256]
        [--no-mitsuba] [--output benchmarks/results/forward_single_cloud.json]

Mitsuba needs ``pip install mitsuba`` and Debian's ``libllvm19`` (see
benchmarks/forward/mitsuba_peer.py).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

import numpy as np

from benchmarks.common import RESULTS, run_header, write_result

COLD_JIT = """
import time, numpy as np
t = time.perf_counter()
from cloudct.mc.render import render, single_cloud_medium
from cloudct.mc.scene import single_cloud_scene
from cloudct.medium import cell_edges
m = single_cloud_medium()
e = cell_edges(m)
scene = single_cloud_scene(np.array([x[0] for x in e]), np.array([x[-1] for x in e]))
t0 = time.perf_counter()
render(m, scene, photons=64, progress=False)
t1 = time.perf_counter()
render(m, scene, photons=64, progress=False)
t2 = time.perf_counter()
print((t1 - t0) - (t2 - t1))
"""


def jit_seconds(cache_dir: str) -> float:
    """Compile (or cache-load) time of the forward kernels in a fresh process."""
    env = dict(os.environ, NUMBA_CACHE_DIR=cache_dir, CLOUDCT_CACHE_DIR=cache_dir)
    out = subprocess.run(
        [sys.executable, "-c", COLD_JIT], env=env, capture_output=True, text=True, check=True
    )
    return float(out.stdout.strip().splitlines()[-1])


def relative_variance(mean: np.ndarray, var_of_mean: np.ndarray) -> float:
    """Mean over bright pixels (above 10% of the view's maximum) of var / mean^2."""
    bright = mean > 0.1 * mean.max(axis=(1, 2), keepdims=True)
    return float(np.mean(var_of_mean[bright] / mean[bright] ** 2))


def view_means(batches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """View-mean radiance and its standard error from per-batch images."""
    per_batch = batches.mean(axis=(2, 3))
    return per_batch.mean(axis=0), per_batch.std(axis=0, ddof=1) / np.sqrt(len(per_batch))


def run_cloudct(photons: int, batches: int) -> dict:
    from cloudct.mc.render import render_batches, single_cloud_medium
    from cloudct.mc.scene import single_cloud_scene
    from cloudct.medium import cell_edges

    medium = single_cloud_medium()
    edges = cell_edges(medium)
    scene = single_cloud_scene(np.array([e[0] for e in edges]), np.array([e[-1] for e in edges]))
    render_batches(medium, scene, photons=64, progress=False)  # JIT warm-up
    b, info = render_batches(medium, scene, photons=photons, batches=batches, progress=False)
    mean = b.mean(axis=0)
    var = b.var(axis=0, ddof=1) / batches
    rv = relative_variance(mean, var)
    wall = info["wall_time"]
    vm, vse = view_means(b)
    return {
        "photons": info["photons"], "wall_s": wall, "photons_per_s": info["photons"] / wall,
        "vertices_per_s": info["events"] / wall, "relative_variance": rv,
        "relative_error_bright": float(np.sqrt(rv)), "efficiency": 1.0 / (rv * wall),
        "view_mean": vm.tolist(), "view_mean_se": vse.tolist(), "scene": scene, "medium": medium,
    }


def run_mitsuba(medium, scene, spp_per_batch: int, batches: int) -> dict:
    from benchmarks.forward.mitsuba_peer import render_batches
    from cloudct.medium import cell_edges

    xe, ye, ze = cell_edges(medium)
    cloud = medium["cloud_extinction"].values
    air = np.broadcast_to(medium["air_extinction"].values, cloud.shape)
    cams = [
        {"position": c.position, "lookat": c.lookat, "up": c.up, "fov_deg": c.fov,
         "nrows": c.nrows, "ncols": c.ncols}
        for c in scene.cameras
    ]
    out = render_batches(
        xe, ye, ze, np.ascontiguousarray(air), cloud, float(medium["air_albedo"]),
        float(np.unique(medium["cloud_albedo"].values)[0]), float(medium["cloud_g"]),
        scene.sun.zenith, scene.sun.azimuth, cams, n_batches=batches,
        spp_per_batch=spp_per_batch, threads=2,
    )
    rv = relative_variance(out["images"], out["var_mean"])
    vm, vse = view_means(out["batches"])
    return {
        "spp": out["spp"], "wall_s": out["render_s"], "compile_s": out["compile_s"],
        "samples_per_s": out["spp"] * 9 * 76 * 76 / out["render_s"],
        "relative_variance": rv, "relative_error_bright": float(np.sqrt(rv)),
        "efficiency": 1.0 / (rv * out["render_s"]),
        "view_mean": vm.tolist(), "view_mean_se": vse.tolist(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photons", type=int, default=4_000_000)
    parser.add_argument("--batches", type=int, default=32)
    parser.add_argument("--mitsuba-spp", type=int, default=256, help="total Mitsuba spp")
    parser.add_argument("--no-mitsuba", action="store_true")
    parser.add_argument("--output", default=str(RESULTS / "forward_single_cloud.json"))
    args = parser.parse_args()

    result = run_header(args)
    with tempfile.TemporaryDirectory() as cache:
        result["cloudct_jit_cold_s"] = jit_seconds(cache)
        result["cloudct_jit_cached_s"] = jit_seconds(cache)
    cc = run_cloudct(args.photons, args.batches)
    scene, medium = cc.pop("scene"), cc.pop("medium")
    result["cloudct"] = cc
    if not args.no_mitsuba:
        mi = run_mitsuba(medium, scene, max(args.mitsuba_spp // args.batches, 1), args.batches)
        result["mitsuba"] = mi
        result["efficiency_ratio"] = cc["efficiency"] / mi["efficiency"]
        z = (np.array(cc["view_mean"]) - mi["view_mean"]) / np.hypot(
            cc["view_mean_se"], mi["view_mean_se"]
        )
        result["view_mean_z"] = z.tolist()
    write_result(result, args.output)


if __name__ == "__main__":
    main()
