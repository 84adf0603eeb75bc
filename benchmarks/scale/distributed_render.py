"""Scale-out benchmark: a forward render of the single-cloud scene on 2 local Dask workers
(one process each, one numba thread each) against one process with one numba thread.

Scene: bundled rico32x37x26 (``single_cloud_medium()``), nine 76x76 cameras at 2 km
(``single_cloud_scene`` on the medium's box), 32 batches. Serial and distributed renders
are interleaved (serial, distributed, serial, ...) so that other load on the machine hits
both alike; each reported time is the median over ``--repeats``. Checks that the images
are bitwise equal, and reports the bytes moved per call: the payload the client counts
(``bytes_to_workers``, ``bytes_from_workers``) and, as a cross-check, the loopback
interface's byte counters over the call (all Dask traffic of the call, heartbeats
included). Also reports the bytes of one retrieval iteration (images + gradient) and of one
recycled iteration (paths kept on the workers). Usage::

    python -m benchmarks scale.distributed_render [--photons 400000] [--repeats 3]
        [--output benchmarks/results/distributed_render.json]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

import numpy as np

from benchmarks.common import RESULTS, run_header, write_result


def loopback_bytes() -> int | None:
    """Bytes sent over the loopback interface so far (None where not readable)."""
    try:
        import psutil

        counters = psutil.net_io_counters(pernic=True)
        lo = counters.get("lo")
        return None if lo is None else int(lo.bytes_sent)
    except Exception:  # pragma: no cover - platform dependent
        return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--photons", type=int, default=400_000)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--output", default=str(RESULTS / "distributed_render.json"))
    args = parser.parse_args()

    import numba

    from cloudct.distributed import (
        DaskExecutor,
        DistributedRecycler,
        close_client,
        executor,
        local_cluster,
    )
    from cloudct.mc.render import render, single_cloud_medium
    from cloudct.mc.scene import single_cloud_scene
    from cloudct.medium import cell_edges
    from cloudct.recycling import FixedPeriod
    from cloudct.retrieval.loss import loss_and_gradient

    # one numba thread in this process (the serial reference), like each worker
    # (cloudct.distributed.local_cluster(threads=1)); set here, not on import, so that
    # importing the module (python -m benchmarks check) changes nothing
    numba.set_num_threads(1)
    medium = single_cloud_medium()
    edges = cell_edges(medium)
    scene = single_cloud_scene(np.array([e[0] for e in edges]), np.array([e[-1] for e in edges]))
    kw = dict(photons=args.photons, seed=0, batches=32, progress=False)

    load_before = os.getloadavg()
    render(medium, scene, photons=64, progress=False)  # JIT / cache load
    client = local_cluster(args.workers, threads=1)
    try:
        render(medium, scene, photons=64, progress=False,
               executor=executor(client))  # workers' cache load
        serial, dist, lo_bytes, payload, loads = [], [], [], [], []
        serial_cpu, worker_cpu, overhead = [], [], []
        for _ in range(args.repeats):
            loads.append(os.getloadavg()[0])
            t0, c0 = time.perf_counter(), time.process_time()
            ref = render(medium, scene, **kw)
            serial.append(time.perf_counter() - t0)
            serial_cpu.append(time.process_time() - c0)
            lo0 = loopback_bytes()
            t0 = time.perf_counter()
            out = render(medium, scene, **kw, executor=executor(client))
            dist.append(time.perf_counter() - t0)
            lo1 = loopback_bytes()
            per_worker: dict[str, float] = {}
            per_worker_wall: dict[str, float] = {}
            for part in executor(client).last_parts:
                per_worker[part.where] = per_worker.get(part.where, 0.0) + part.cpu_seconds
                per_worker_wall[part.where] = per_worker_wall.get(part.where, 0.0) + part.seconds
            worker_cpu.append(per_worker)
            # wall time of the call beyond the busiest worker's task time: submission,
            # scheduling, transfers, reduction
            overhead.append(dist[-1] - max(per_worker_wall.values()))
            lo_bytes.append(None if lo0 is None else lo1 - lo0)
            payload.append((out.attrs["bytes_to_workers"], out.attrs["bytes_from_workers"]))
            assert np.array_equal(out.radiance.values, ref.radiance.values)
            assert np.array_equal(out.radiance_std_error.values, ref.radiance_std_error.values)
        # the first call with a medium scatters it; later calls re-use it: report both
        first_call = render(medium, scene, photons=64, progress=False,
                            executor=DaskExecutor(client))  # an executor with an empty cache

        # one retrieval iteration: images + gradient of a perturbed medium
        guess = medium.copy(deep=True)
        guess["cloud_extinction"] = guess["cloud_extinction"] * 0.9
        ex = executor(client)
        before = len(ex.calls)
        loss_and_gradient(guess, ref, photons=args.photons // 4, seed=1, client=ex)
        iteration_calls = ex.calls[before:]

        # recycled iterations: paths recorded once on the workers, then re-evaluated
        recycler = DistributedRecycler(scene, client=client, photons=args.photons // 4,
                                       policy=FixedPeriod(10), seed=0)
        weights = np.ones(ref.radiance.shape)
        recycled = []
        for factor in (0.9, 0.92, 0.94):
            g = medium.copy(deep=True)
            g["cloud_extinction"] = g["cloud_extinction"] * factor
            ev = recycler.evaluate(g, residual=lambda im: weights * im.radiance.values)
            recycled.append({k: ev.info[k] for k in
                             ("resampled", "bytes", "bytes_to_workers", "bytes_from_workers",
                              "wall_time")})
        placement = {str(k): list(v) for k, v in recycler.image_store.placement().items()}
    finally:
        close_client(client)
    load_after = os.getloadavg()

    t_serial = statistics.median(serial)
    t_dist = statistics.median(dist)
    result = {
        **run_header(args),
        "load_average_before": load_before,
        "load_average_after": load_after,
        "load_average_1min_at_each_repeat": loads,
        "photons": ref.attrs["photons"],
        "batches": 32,
        "workers": args.workers,
        "serial_seconds": serial,
        "distributed_seconds": dist,
        "serial_median_s": t_serial,
        "distributed_median_s": t_dist,
        "speedup": t_serial / t_dist,
        "serial_cpu_seconds": serial_cpu,
        "worker_cpu_seconds": worker_cpu,
        # what the speed-up would be with a free core per process: the serial CPU time over
        # the busiest worker's CPU time (contention-free estimate, excludes the client's and
        # the communication's wall time)
        "cpu_bound_speedup": statistics.median(
            sc / max(wc.values()) for sc, wc in zip(serial_cpu, worker_cpu, strict=True)
        ),
        "call_overhead_seconds": overhead,
        # the same, charging the call's overhead too
        "cpu_bound_speedup_with_overhead": statistics.median(
            sc / (max(wc.values()) + oh)
            for sc, wc, oh in zip(serial_cpu, worker_cpu, overhead, strict=True)
        ),
        "bitwise_equal": True,
        "bytes_per_render_call": {
            "to_workers_first_call_medium_scatter": first_call.attrs["bytes_to_workers"],
            "to_workers_repeat_call": payload[-1][0],
            "from_workers": payload[-1][1],
            "loopback_bytes_per_call": lo_bytes,
        },
        "retrieval_iteration_calls": [
            {"tasks": c.tasks, "bytes_to_workers": c.bytes_to_workers,
             "bytes_from_workers": c.bytes_from_workers, "wall_time": c.wall_time}
            for c in iteration_calls
        ],
        "recycled_iterations": recycled,
        "recycled_store_placement": placement,
    }
    write_result(result, args.output)


if __name__ == "__main__":
    main()
