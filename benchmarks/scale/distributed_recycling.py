"""Scale-out benchmark of recycled retrieval iterations: 2 local Dask workers (one process
and one numba thread each) against one process with one numba thread, at several path
counts.

Scene: bundled rico32x37x26, nine 76x76 cameras, 32 batches; the recycler stores camera
connections with the cloud's voxels variable (``storage="auto"``, ``variable`` = the
cloud's voxels, as a retrieval passes its mask). For each path count the same recycler
settings run in one process (:class:`cloudct.recycling.Recycler`) and on the workers
(:class:`cloudct.distributed.DistributedRecycler`): one evaluation records the two stores,
then ``--repeats`` recycled evaluations (images + gradient) follow under media scaled by
0.92, 0.94, ... The serial and distributed evaluations of the same medium alternate, so
other load on the machine hits both alike; the results are checked to be bitwise equal.

Reported (JSON at ``--output``): per path count the median wall time of a recycled
iteration in each setting and their ratio, and the bytes a recycled iteration moves to and
from the workers (the client's payload count), which must not grow with the path count: the
paths stay on the workers. Usage::

    python -m benchmarks scale.distributed_recycling [--paths 50000 100000 200000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

import numpy as np

from benchmarks.common import RESULTS, run_header, write_result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--paths", type=int, nargs="+", default=[50_000, 100_000, 200_000])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument(
        "--output", default=str(RESULTS / "distributed_recycling.json")
    )
    args = parser.parse_args()

    import numba

    from cloudct.distributed import DistributedRecycler, close_client, local_cluster
    from cloudct.mc.render import render, single_cloud_medium
    from cloudct.mc.scene import single_cloud_scene
    from cloudct.medium import cell_edges
    from cloudct.recycling import FixedPeriod, Recycler

    # one numba thread in this process (the serial reference), like each worker
    # (cloudct.distributed.local_cluster(threads=1)); set here, not on import, so that
    # importing the module (python -m benchmarks check) changes nothing
    numba.set_num_threads(1)
    medium = single_cloud_medium()
    edges = cell_edges(medium)
    scene = single_cloud_scene(np.array([e[0] for e in edges]), np.array([e[-1] for e in edges]))
    cloud = medium["cloud_extinction"].values
    mask = cloud > 0
    target = render(medium, scene, photons=400_000, seed=99, progress=False).radiance.values

    def scaled(factor: float):
        out = medium.copy(deep=True)
        out["cloud_extinction"] = out["cloud_extinction"] * factor
        return out

    def residual(images):
        return images.radiance.values - target

    load_before = os.getloadavg()
    client = local_cluster(args.workers, threads=1)
    rows = []
    try:
        # compile (or load from cache) everything once in this process and on the workers
        for make in (lambda **kw: Recycler(scene, **kw),
                     lambda **kw: DistributedRecycler(scene, client=client, **kw)):
            make(photons=640, policy=FixedPeriod(5), seed=0, variable=mask).evaluate(
                scaled(0.9), residual=residual
            )
        for paths in args.paths:
            kw = dict(photons=paths, policy=FixedPeriod(args.repeats + 1), seed=1,
                      variable=mask)
            serial = Recycler(scene, **kw)
            dist = DistributedRecycler(scene, client=client, **kw)
            record = {}
            for name, rec in (("serial", serial), ("distributed", dist)):
                t0 = time.perf_counter()
                ev = rec.evaluate(scaled(0.9), residual=residual)
                record[name] = time.perf_counter() - t0
                assert ev.info["resampled"]
            walls = {"serial": [], "distributed": []}
            moved = []
            for r in range(args.repeats):
                m = scaled(0.92 + 0.02 * r)
                t0 = time.perf_counter()
                a = serial.evaluate(m, residual=residual)
                walls["serial"].append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                b = dist.evaluate(m, residual=residual)
                walls["distributed"].append(time.perf_counter() - t0)
                assert not a.info["resampled"] and not b.info["resampled"]
                assert np.array_equal(a.images.radiance.values, b.images.radiance.values)
                assert np.array_equal(a.gradient, b.gradient)
                moved.append((b.info["bytes_to_workers"], b.info["bytes_from_workers"]))
            row = {
                "paths_per_store": paths,
                "storage": serial.image_store.storage,
                "store_bytes_both_stores": serial.nbytes,
                "record_seconds": record,
                "recycled_seconds": walls,
                "serial_median_s": statistics.median(walls["serial"]),
                "distributed_median_s": statistics.median(walls["distributed"]),
                "bytes_to_workers_per_recycled_iteration": [m[0] for m in moved],
                "bytes_from_workers_per_recycled_iteration": [m[1] for m in moved],
                "bitwise_equal": True,
            }
            row["speedup"] = row["serial_median_s"] / row["distributed_median_s"]
            rows.append(row)
            print(json.dumps(row), flush=True)
            for store in (dist.image_store, dist.gradient_store):
                store.release()  # free the workers' memory before the next path count
            del serial, dist
    finally:
        close_client(client)
    result = {
        **run_header(args),
        "load_average_before": load_before,
        "load_average_after": os.getloadavg(),
        "workers": args.workers,
        "batches": 32,
        "rows": rows,
    }
    write_result(result, args.output)


if __name__ == "__main__":
    main()
