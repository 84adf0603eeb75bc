"""Path-recycling benchmark on the seed paper's single-cloud scene.

Scene: bundled RICO cloud 32x37x26 (Mie extinction at 0.672 micron, cloud albedo 0.99, HG
g = 0.85; air 0.04 /km), open boundaries, sun at zenith, nine 76x76 cameras at 2 km.

Reported (JSON, printed and written to ``--output``):

- ``iteration``: wall (and CPU) time of one retrieval iteration, images + gradient, fresh
  (``render`` + ``score_function_gradient`` on independent paths, as ``loss_and_gradient``)
  and recycled (replay of an images store and a gradient store under a medium perturbed by
  0.98-1.02 voxel-wise), for the storage modes (camera connections with the cloud's voxels
  variable or all voxels, crossings, lean) and sorted/unsorted stores; the time to record
  the two stores, and the recycled cost per iteration amortised over N_r = 30.
  Minimum and median over ``--repeats``; JIT compilation excluded.
- ``memory``: bytes per stored scattering event and per path in each mode, and the
  projected size of 10^6 paths (``--million`` records 10^6 paths in crossings mode and
  measures it).
- ``ess``: the ESS fraction of both stores along retrievals that start from the cloud
  scaled by 0.7 and never resample: the retrieval's Adam (step 2.0 /km per iteration as in
  the seed paper, and 0.5) on the cloud's voxels, driven by the recycled gradients.

Other processes may share the machine; the load average is recorded. Usage::

    python -m benchmarks retrieval.recycling [--photons 200000] [--iterations 30]
        [--repeats 3] [--million] [--adam-steps 2.0 0.5]
        [--output benchmarks/results/recycling_single_cloud.json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np

from benchmarks.common import RESULTS, run_header, write_result
from cloudct.mc.gradient import score_function_gradient
from cloudct.mc.render import render, single_cloud_medium
from cloudct.mc.scene import single_cloud_scene
from cloudct.medium import cell_edges
from cloudct.recycling import (
    AdaptiveESS,
    FixedPeriod,
    Recycler,
    record_paths,
    replay_gradient,
    replay_images,
)
from cloudct.retrieval.loss import image_loss
from cloudct.retrieval.optimizers import Adam


def timed(fn):
    """(result, wall seconds, CPU seconds of all threads)."""
    w, c = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - w, time.process_time() - c


def summary(samples: list[tuple[float, float]]) -> dict:
    walls = [s[0] for s in samples]
    cpus = [s[1] for s in samples]
    return {
        "wall_min_s": min(walls), "wall_median_s": statistics.median(walls),
        "cpu_min_s": min(cpus), "cpu_median_s": statistics.median(cpus),
    }


def with_cloud(medium, cloud):
    out = medium.copy(deep=True)
    out["cloud_extinction"] = (out["cloud_extinction"].dims, cloud)
    out["cloud_extinction"].attrs.update(medium["cloud_extinction"].attrs)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photons", type=int, default=200_000, help="paths per store")
    parser.add_argument("--batches", type=int, default=32)
    parser.add_argument("--iterations", type=int, default=30, help="ESS trajectory length")
    parser.add_argument("--adam-steps", type=float, nargs="+", default=[2.0, 0.5],
                        help="Adam step sizes (1/km per iteration) of the ESS trajectories")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--million", action="store_true", help="record 10^6 paths")
    parser.add_argument("--skip-ess", action="store_true",
                        help="keep the ESS trajectories of an earlier run in --output")
    parser.add_argument(
        "--output", default=str(RESULTS / "recycling_single_cloud.json")
    )
    args = parser.parse_args()
    n, nb = args.photons, args.batches
    earlier = json.loads(Path(args.output).read_text()) if Path(args.output).exists() else {}

    truth = single_cloud_medium()
    edges = cell_edges(truth)
    scene = single_cloud_scene(np.array([e[0] for e in edges]), np.array([e[-1] for e in edges]))
    cloud = truth["cloud_extinction"].values
    mask = cloud > 0
    result = {
        **run_header(args),
        "photons_per_store": n,
        "batches": nb,
    }
    measured = render(truth, scene, photons=4 * n, seed=999, batches=nb, progress=False)
    target = measured["radiance"].values

    # JIT warm-up of every kernel used below
    small = record_paths(truth, scene, photons=nb * 4, seed=1, batches=nb)
    ones = np.ones(target.shape)
    replay_images(small, truth)
    replay_gradient(small, truth, ones)
    record_paths(truth, scene, photons=nb * 4, seed=1, batches=nb, storage="lean")
    render(truth, scene, photons=nb * 4, batches=nb, progress=False)
    score_function_gradient(truth, scene, ones, photons=nb * 4, batches=nb, progress=False)

    # -- one iteration: fresh vs recycled ------------------------------------------------
    reference = with_cloud(truth, 0.7 * cloud)
    rng = np.random.default_rng(5)
    current = with_cloud(truth, 0.7 * cloud * rng.uniform(0.98, 1.02, cloud.shape))

    def fresh_iteration():
        images = render(current, scene, photons=n, seed=10, batches=nb, progress=False)
        residual = images["radiance"].values - target
        return score_function_gradient(
            current, scene, residual, photons=n, seed=11, batches=nb, progress=False
        )

    fresh = []
    for _ in range(args.repeats):
        _, wall, cpu = timed(fresh_iteration)
        fresh.append((wall, cpu))
    iteration = {"fresh": summary(fresh)}

    stores = {}
    # "connections" with the cloud's voxels variable (the mask an ideal space carving
    # gives, as in a retrieval), "connections_all" with every voxel variable
    modes = {
        "connections": ("connections", mask),
        "connections_all": ("connections", None),
        "crossings": ("crossings", None),
        "lean": ("lean", None),
    }
    for name, (storage, variable) in modes.items():
        def record_two(storage=storage, variable=variable):
            return tuple(
                record_paths(reference, scene, photons=n, seed=s, batches=nb, storage=storage,
                             variable=variable)
                for s in (20, 21)
            )

        (a, b), wall, cpu = timed(record_two)
        stores[name] = (a, b)
        iteration[f"record_two_stores_{name}"] = {"wall_s": wall, "cpu_s": cpu}
    stores["crossings_unsorted"] = tuple(
        record_paths(reference, scene, photons=n, seed=s, batches=nb, storage="crossings",
                     sort=False)
        for s in (20, 21)
    )
    assert all(s.sorted for s in stores["crossings"])

    for name, (image_store, gradient_store) in stores.items():
        def recycled_iteration(image_store=image_store, gradient_store=gradient_store):
            batch_images, info = replay_images(image_store, current)
            residual = batch_images.mean(axis=0) - target
            return replay_gradient(gradient_store, current, residual), info

        samples = []
        for _ in range(args.repeats):
            (_, info), wall, cpu = timed(recycled_iteration)
            samples.append((wall, cpu))
        iteration[f"recycled_{name}"] = summary(samples)
        iteration[f"recycled_{name}"]["ess_fraction_images"] = info["ess_fraction"]
    f = iteration["fresh"]["wall_min_s"]
    for name in stores:
        r = iteration[f"recycled_{name}"]
        r["ratio_to_fresh_wall"] = r["wall_min_s"] / f
        r["ratio_to_fresh_cpu"] = r["cpu_min_s"] / iteration["fresh"]["cpu_min_s"]
    for name in ("connections", "crossings"):
        rec = iteration[f"record_two_stores_{name}"]["wall_s"]
        amortised = (rec + 30 * iteration[f"recycled_{name}"]["wall_min_s"]) / 30
        iteration[f"recycled_{name}_amortised_30_wall_s"] = amortised
        iteration[f"amortised_{name}_ratio_to_fresh_wall"] = amortised / f
    result["iteration"] = iteration
    write_result(result, args.output)  # each section as soon as it is done

    # -- memory (stores recorded under the true cloud) ---------------------------------
    memory = {}
    for name, (storage, variable) in modes.items():
        s = record_paths(truth, scene, photons=n, seed=25, batches=nb, storage=storage,
                         variable=variable)
        memory[name] = {
            "bytes_per_event": s.bytes_per_event,
            "bytes_per_path": s.nbytes / s.paths,
            "bytes_per_record": s.nbytes / s.records,
            "events_per_path": s.events / s.paths,
            "records_per_path": s.records / s.paths,
            "crossings_per_segment": s.crossings / max(s.records - s.paths, 1),
            "connections_per_path": s.connections / s.paths,
            "crossings_per_connection": s.arrays.connection_voxel.size / max(s.connections, 1),
            "projected_bytes_1e6_paths": s.nbytes / s.paths * 1e6,
        }
    if args.million:
        store, wall, cpu = timed(
            lambda: record_paths(truth, scene, photons=1_000_000, seed=30, batches=nb,
                                 storage="crossings")
        )
        memory["crossings_1e6_measured"] = {
            "bytes": store.nbytes, "gib": store.nbytes / 2**30, "record_wall_s": wall,
            "bytes_per_event": store.bytes_per_event,
        }
        del store
    result["memory"] = memory
    write_result(result, args.output)  # each section as soon as it is done

    if args.skip_ess:
        if "ess" in earlier:
            result["ess"] = {**earlier["ess"], "from_run_of": earlier.get("date")}
        result["load_average_end"] = os.getloadavg()
        write_result(result, args.output)  # each section as soon as it is done
        return

    # -- ESS along a retrieval that never resamples --------------------------------------
    # the retrieval's Adam (cloudct.retrieval.optimizers, step in 1/km per iteration; the
    # seed paper's 2.0 and a smaller one) on the cloud's voxels (the mask an ideal space
    # carving gives), from 0.7 x the true cloud, driven by the recycled gradients
    start = 0.7 * cloud
    result["ess"] = {"start": "0.7 x truth", "optimizer": "adam", "trajectories": {}}
    policies = {
        "fixed": FixedPeriod(args.iterations + 1),
        "adaptive_ess_0.5": AdaptiveESS(min_fraction=0.5, max_period=50),
        "adaptive_ess_0.5_max_ratio_20": AdaptiveESS(0.5, max_period=50, max_ratio=20.0),
    }
    runs = [(step, "fixed") for step in args.adam_steps] + [
        (args.adam_steps[0], kind) for kind in policies if kind != "fixed"
    ]
    for step, kind in runs:
        policy = policies[kind]
        recycler = Recycler(scene, photons=n, batches=nb, policy=policy, seed=40, variable=mask)
        optimizer = Adam(step=step)
        beta = start.copy()
        trajectory = []
        for t in range(args.iterations):
            ev = recycler.evaluate(
                with_cloud(truth, beta), residual=lambda im: im["radiance"].values - target
            )
            loss = image_loss(ev.images["radiance"].values, target)[0]
            trajectory.append({
                "iteration": t, "loss": loss, "ess_images": ev.info["ess_images"],
                "ess_gradient": ev.info["ess_gradient"], "resampled": ev.info["resampled"],
                "mean_relative_change_from_reference": float(
                    np.mean(np.abs(beta[mask] - start[mask]) / start[mask])
                ),
                "wall_s": ev.info["wall_time"], "checked": ev.info["checked"],
            })
            print(json.dumps({"adam_step": step, "policy": kind, **trajectory[-1]}), flush=True)
            beta = optimizer.update(beta, ev.gradient, mask)
        key = f"adam_{step}_{kind}"
        result["ess"]["trajectories"][key] = trajectory
        if kind != "fixed":
            total = sum(row["wall_s"] for row in trajectory)
            result["ess"][f"summary_{key}"] = {
                "resampled_at": [row["iteration"] for row in trajectory if row["resampled"]],
                "total_wall_s": total,
                "fresh_equivalent_wall_s": args.iterations * iteration["fresh"]["wall_min_s"],
                "ratio_to_fresh": total / (args.iterations * iteration["fresh"]["wall_min_s"]),
            }
        write_result(result, args.output)  # each section as soon as it is done
    result["load_average_end"] = os.getloadavg()
    write_result(result, args.output)  # each section as soon as it is done
    print(json.dumps({k: v for k, v in result.items() if k != "ess"}, indent=2))


if __name__ == "__main__":
    main()
