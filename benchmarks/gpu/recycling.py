"""GPU benchmark: the recycled re-evaluation of stored paths, sorted vs unsorted store.

Scene: bundled RICO cloud 32x37x26 (:func:`cloudct.mc.render.single_cloud_medium`), nine
76x76 cameras at 2 km, sun at zenith, open boundaries (:func:`cloudct.mc.scene.
single_cloud_scene`), as ``benchmarks/retrieval/recycling.py``. One store of ``--photons`` paths is
recorded (on the CPU) under the reference medium (the cloud x 0.7), unsorted, and a copy is
sorted by path length (:func:`cloudct.recycling.sort_paths`: the same paths, each batch's
in order of their record count). Both are replayed on the GPU under a medium perturbed by
0.98-1.02 voxel-wise (:mod:`cloudct.recycling.cuda_replay`, one thread per path, threads on
consecutive storage slots): images (RENDER) and the residual-weighted gradient (GRADIENT).
In the unsorted store a warp holds paths of any length; in the sorted one, paths of the same
length (seed paper Sec. 5.3, path sorting).

Reported per store: wall time of the images and of the gradient replay (minimum and median
over ``--repeats``; the kernels plus the copy of the per-batch outputs to the host, the store
already on the device), paths/s and local-estimation events/s, the time of the store's copy
to the device, and the speed-up from sorting (unsorted / sorted wall time). The first call
(JIT compilation) is timed separately and excluded. The sorted and unsorted stores give the
same images and gradients up to the order of the additions (checked).

Usage (one command on a GPU machine; writes JSON and a markdown summary)::

    python -m benchmarks gpu.recycling [--photons 1048576] [--batches 32]
        [--storage crossings] [--repeats 5] [--output benchmarks/results/gpu_recycling]

Exits with a message where there is no GPU.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np

from benchmarks.common import RESULTS, run_header, write_result
from benchmarks.gpu.forward import device_name


def with_cloud(medium, cloud):
    """``medium`` with its cloud extinction replaced."""
    out = medium.copy(deep=True)
    out["cloud_extinction"] = (out["cloud_extinction"].dims, cloud)
    out["cloud_extinction"].attrs.update(medium["cloud_extinction"].attrs)
    return out


def timings(samples: list[float], paths: int, events: int) -> dict:
    """Minimum and median wall time, and the rates at the minimum."""
    best = min(samples)
    return {
        "wall_min_s": best, "wall_median_s": statistics.median(samples),
        "paths_per_s": paths / best, "events_per_s": events / best,
    }


def replay_store(store, current, residual, repeats: int) -> tuple[dict, tuple]:
    """Copy ``store`` to the device, then time its image and gradient replays."""
    from cloudct.recycling import replay_batch_gradients, replay_images
    from cloudct.recycling.cuda_replay import device_store, release_device_store

    t0 = time.perf_counter()
    device_store(store)
    to_device = time.perf_counter() - t0
    images = gradient = None
    walls: dict[str, list[float]] = {"images": [], "gradient": []}
    events = {}
    for _ in range(repeats):
        images, info = replay_images(store, current, backend="cuda")
        walls["images"].append(info["wall_time"])
        events["images"] = info["events"]
        gradient, info = replay_batch_gradients(store, current, residual, backend="cuda")
        walls["gradient"].append(info["wall_time"])
        events["gradient"] = info["events"]
    release_device_store(store)
    totals = [a + b for a, b in zip(walls["images"], walls["gradient"], strict=True)]
    result = {
        "to_device_s": to_device,
        "images": timings(walls["images"], store.paths, events["images"]),
        "gradient": timings(walls["gradient"], store.paths, events["gradient"]),
        "images_and_gradient": timings(totals, store.paths,
                                       events["images"] + events["gradient"]),
        "events_per_path": events["images"] / store.paths,
    }
    return result, (images, gradient)


def markdown(result: dict) -> str:
    lines = [
        "# GPU path-recycling benchmark: single-cloud scene (9 views, 76x76)",
        "",
        f"{result['date']}, `{result['command']}`",
        "",
        f"{result['device']}; {result['store']['paths']:,} paths "
        f"({result['store']['records'] / result['store']['paths']:.2f} records per path), "
        f"{result['settings']['storage']} storage, {result['settings']['batches']} batches, "
        f"{result['threads_per_block']} threads per block.",
        "",
        "| replay | store | wall min (s) | wall median (s) | paths/s | events/s |",
        "| --- | --- | --- | --- | --- | --- |",
    ]
    for what in ("images", "gradient", "images_and_gradient"):
        for name in ("unsorted", "sorted"):
            t = result[name][what]
            lines.append(
                f"| {what} | {name} | {t['wall_min_s']:.4g} | {t['wall_median_s']:.4g} | "
                f"{t['paths_per_s']:.4g} | {t['events_per_s']:.4g} |"
            )
    s = result["speedup_from_sorting"]
    lines += [
        "",
        "Speed-up from sorting (unsorted / sorted minimum wall time): images "
        f"x{s['images']:.3g}, gradient x{s['gradient']:.3g}, both x"
        f"{s['images_and_gradient']:.3g}. Sorted vs unsorted results: largest difference "
        f"{result['agreement']['images']:.2g} (images) and {result['agreement']['gradient']:.2g}"
        " (gradient) of the largest element.",
        "",
        "Wall time: the replay kernels and the copy of the per-batch outputs to the host, "
        "with the store already on the device (its copy: `to_device_s`); JIT compilation "
        f"({result['compile_s']:.1f} s) excluded.",
    ]
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photons", type=int, default=1 << 20, help="paths in the store")
    parser.add_argument("--batches", type=int, default=32)
    parser.add_argument("--storage", default="crossings",
                        help="storage mode of the store (see cloudct.recycling.store)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--seed", type=int, default=20)
    parser.add_argument("--output", default=str(RESULTS / "gpu_recycling"),
                        help="output path without suffix (.json and .md are written)")
    args = parser.parse_args()

    from cloudct.mc.backend import cuda_unavailable_reason

    reason = cuda_unavailable_reason()
    if reason is not None:
        print(f"gpu_recycling: no GPU to benchmark: {reason}.", file=sys.stderr)
        return 2

    import cloudct.mc.cuda_kernels as ck
    from cloudct.mc.render import single_cloud_medium
    from cloudct.mc.scene import single_cloud_scene
    from cloudct.medium import cell_edges
    from cloudct.recycling import (
        record_paths,
        replay_batch_gradients,
        replay_images,
        sort_paths,
    )

    truth = single_cloud_medium()
    edges = cell_edges(truth)
    scene = single_cloud_scene(np.array([e[0] for e in edges]), np.array([e[-1] for e in edges]))
    cloud = truth["cloud_extinction"].values
    reference = with_cloud(truth, 0.7 * cloud)
    rng = np.random.default_rng(5)
    current = with_cloud(truth, 0.7 * cloud * rng.uniform(0.98, 1.02, cloud.shape))
    result = {
        **run_header(args),
        "scene": "single cloud 32x37x26, 9 cameras 76x76, sun at zenith, open",
        "device": device_name("cuda"),
        "threads_per_block": ck.THREADS_PER_BLOCK,
    }

    # JIT compilation: the first replays of a small store, minus identical second ones
    small = record_paths(reference, scene, photons=args.batches * 4, seed=1,
                         batches=args.batches, storage=args.storage)
    ones = np.ones((len(scene.cameras), 76, 76))

    def small_replays() -> float:
        t = time.perf_counter()
        replay_images(small, current, backend="cuda")
        replay_batch_gradients(small, current, ones, backend="cuda")
        return time.perf_counter() - t

    result["compile_s"] = small_replays() - small_replays()

    t0 = time.perf_counter()
    unsorted = record_paths(reference, scene, photons=args.photons, seed=args.seed,
                            batches=args.batches, storage=args.storage, sort=False)
    result["record_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    stores = {"unsorted": unsorted, "sorted": sort_paths(unsorted)}
    result["sort_s"] = time.perf_counter() - t0
    result["store"] = unsorted.summary()
    counts = unsorted.record_counts()
    result["records_per_path"] = {"mean": float(counts.mean()), "max": int(counts.max())}

    # residual weights: the recycled images of the current medium minus those of the truth
    measured, _ = replay_images(stores["sorted"], truth, backend="cuda")
    images, _ = replay_images(stores["sorted"], current, backend="cuda")
    residual = images.mean(axis=0) - measured.mean(axis=0)

    outputs = {}
    for name, store in stores.items():
        result[name], outputs[name] = replay_store(store, current, residual, args.repeats)
        print(json.dumps({name: result[name]}), flush=True)
    result["speedup_from_sorting"] = {
        what: result["unsorted"][what]["wall_min_s"] / result["sorted"][what]["wall_min_s"]
        for what in ("images", "gradient", "images_and_gradient")
    }
    result["agreement"] = {
        what: float(np.abs(outputs["sorted"][i] - outputs["unsorted"][i]).max()
                    / np.abs(outputs["unsorted"][i]).max())
        for i, what in enumerate(("images", "gradient"))
    }
    write_result(result, args.output, markdown)
    return 0


if __name__ == "__main__":
    sys.exit(main())
