"""Scale-out over Dask: a local cluster of 2 single-threaded worker processes.

- Forward and backward images, score-function, DRT and sample-matching gradients (pixels
  uniform or drawn by residual), loss gradients, retrieval steps (score function, and the
  default sample matching) and recycled evaluations equal the single-process results for the
  same seeds BITWISE (np.array_equal), whatever the split into tasks.
- With recycling the paths stay on the workers: the parts do not move between recycled
  iterations and only media, residuals and results come back.
- A worker killed in the middle of a call (images, camera-side gradients, a recycled
  iteration, whose lost part of the paths is recorded again): the task is re-run elsewhere
  and the result is still bitwise the single-process one; a worker that dies with the last
  copy of a call's scattered inputs: they are scattered again and the tasks submitted once
  more, bitwise the same; a task that keeps killing workers
  makes the call raise DistributedError; the reduction refuses results that do not cover
  every submitted batch exactly once.
"""

from __future__ import annotations

import dataclasses
import json
import os
import sys

import numpy as np
import pytest

pytest.importorskip("distributed")

import cloudpickle  # noqa: E402
import dask  # noqa: E402
from distributed import WorkerPlugin  # noqa: E402
from test_recycling import scaled, weights_for  # noqa: E402
from test_score_gradient import gradient_medium, gradient_scene, pixel_weights  # noqa: E402

import cloudct.distributed.batches as batches  # noqa: E402
from cloudct.distributed import (  # noqa: E402
    DaskExecutor,
    DistributedError,
    DistributedRecycler,
    close_client,
    executor,
    local_cluster,
)
from cloudct.distributed.batches import BatchPart, assemble  # noqa: E402
from cloudct.distributed.recycling import record_part  # noqa: E402
from cloudct.mc.gradient import (  # noqa: E402
    drt_gradient,
    sample_matching_gradient,
    score_function_gradient,
)
from cloudct.mc.render import render  # noqa: E402
from cloudct.recycling import FixedPeriod, Recycler  # noqa: E402
from cloudct.retrieval.loop import Retrieval, RetrievalConfig  # noqa: E402
from cloudct.retrieval.loss import loss_and_gradient  # noqa: E402

# functions of this module run on the workers: pickle them by value
cloudpickle.register_pickle_by_value(sys.modules[__name__])


@pytest.fixture(scope="module")
def kernels_cached() -> None:
    # compile (or load from the numba cache) the worker-only kernels here, so that the two
    # workers load them from the cache instead of both compiling them
    record_part(gradient_medium(), gradient_scene(), seed=0, per_batch=1, start=1, count=2)


def _two_workers():
    with dask.config.set({"distributed.scheduler.allowed-failures": 1}):
        return local_cluster(2, threads=1)


@pytest.fixture(scope="module")
def client(kernels_cached):
    c = _two_workers()
    yield c
    close_client(c)


@pytest.fixture
def own_client(kernels_cached):
    """Two workers of its own for a test that kills one: the next test does not wait for
    its replacement (a nanny slow to restart a worker on busy cores once hung the module's
    cluster)."""
    c = _two_workers()
    yield c
    close_client(c)


def same(a, b) -> bool:
    return np.array_equal(a, b)


@pytest.mark.parametrize("method, photons", [("forward", 20_000), ("backward", 64)])
def test_images_equal_the_single_process_images_bitwise(client, method, photons):
    medium, scene = gradient_medium(), gradient_scene()
    ref = render(medium, scene, photons=photons, method=method, seed=3, progress=False)
    for where in (executor(client), DaskExecutor(client, batches_per_task=1),
                  DaskExecutor(client, batches_per_task=5)):
        out = render(medium, scene, photons=photons, method=method, seed=3, progress=False,
                     executor=where)
        assert same(out.radiance.values, ref.radiance.values)
        assert same(out.radiance_std_error.values, ref.radiance_std_error.values)
        assert out.attrs["events"] == ref.attrs["events"]
        assert out.attrs["workers"] == 2 and out.attrs["backend"] == "cpu"
        assert out.attrs["bytes_from_workers"] >= out.radiance.size * 8 * 32


def test_gradients_loss_and_retrieval_equal_the_single_process_ones_bitwise(client):
    medium, scene = gradient_medium(), gradient_scene()
    weights = pixel_weights()
    ref = score_function_gradient(medium, scene, weights, photons=20_000, seed=5,
                                  progress=False)
    out = score_function_gradient(medium, scene, weights, photons=20_000, seed=5,
                                  progress=False, executor=executor(client))
    assert same(out[0], ref[0]) and same(out[1], ref[1])
    assert out[2]["events"] == ref[2]["events"]

    measured = render(medium, scene, photons=40_000, seed=77, progress=False)
    guess = scaled(medium, 0.8)
    a = loss_and_gradient(guess, measured, photons=10_000, seed=2)
    b = loss_and_gradient(guess, measured, photons=10_000, seed=2, client=client)
    assert a.loss == b.loss and same(a.gradient, b.gradient)
    assert same(a.gradient_std_error, b.gradient_std_error)

    for estimator in (("score",), None):  # None: the default, sample matching
        config = RetrievalConfig(iterations=2, photons=8_000, stages=(1,),
                                 stage_photons=(1.0,), estimator=estimator)
        one = Retrieval(measured, guess, config)
        one.run(progress=False)
        many = Retrieval(measured, guess, config, client=client)
        many.run(progress=False)
        assert same(one.state.extinction, many.state.extinction)
        assert one.state.log["loss"] == many.state.log["loss"]
    assert config.estimator == ("sm",) and config.pixel_sampling == "residual"

    # with recycling the stores live on the workers (a DistributedRecycler), same iterates
    config = RetrievalConfig(iterations=3, photons=8_000, stages=(1,), stage_photons=(1.0,),
                             recycling="fixed", period=2)
    one = Retrieval(measured, guess, config)
    one.run(progress=False)
    many = Retrieval(measured, guess, config, client=client)
    many.run(progress=False)
    assert type(many._recycler).__name__ == "DistributedRecycler"
    assert same(one.state.extinction, many.state.extinction)
    assert one.state.log["loss"] == many.state.log["loss"]
    assert one.state.log["resampled"] == [1.0, 0.0, 1.0]


@pytest.mark.parametrize("estimate, sampling", [
    (drt_gradient, "uniform"), (drt_gradient, "residual"),
    (sample_matching_gradient, "uniform"), (sample_matching_gradient, "residual"),
])
def test_camera_side_gradients_equal_the_single_process_ones_bitwise(client, estimate,
                                                                      sampling):
    """16 samples per pixel and batch: uniform pixel sampling traces them in 16 rounds of
    every pixel, which the workers must repeat (one batch per kernel call) to be bitwise."""
    medium, scene = gradient_medium(), gradient_scene()
    weights = pixel_weights()
    run = dict(samples_per_pixel=128, seed=4, batches=8, pixel_sampling=sampling)
    ref = estimate(medium, scene, weights, **run)
    for where in (executor(client), DaskExecutor(client, batches_per_task=3)):
        out = estimate(medium, scene, weights, **run, executor=where)
        assert same(out[0], ref[0]) and same(out[1], ref[1])
        for key in ("photons", "events", "pixel_sampling", "backend"):
            assert out[2][key] == ref[2][key], key
        assert out[2]["workers"] == 2
        # back: a float64 gradient per batch and voxel, and a few bytes per batch and task
        extra = out[2]["bytes_from_workers"] - 8 * ref[0].size * 8
        assert 0 < extra < 100 * out[2]["tasks"]


@pytest.mark.parametrize("methods", [{}, {"image_method": "combined",
                                           "gradient_estimator": "combined"}],
                         ids=["forward", "combined"])
def test_recycled_evaluations_equal_the_single_process_ones_and_paths_stay(client, methods):
    """Also with the combined estimator: the workers replay the forward half with its
    weights, the camera paths are traced here, the same as the single process's."""
    medium, scene = gradient_medium(), gradient_scene()
    w = weights_for(scene)

    def residual(images):
        return w * images.radiance.values

    local = Recycler(scene, photons=3_200, policy=FixedPeriod(2), seed=3, **methods)
    remote = DistributedRecycler(scene, client=client, photons=3_200, policy=FixedPeriod(2),
                                 seed=3, **methods)
    placements = []
    for t in range(3):
        m = scaled(medium, 1.0 + 0.03 * t)
        a = local.evaluate(m, residual=residual)
        b = remote.evaluate(m, residual=residual)
        assert same(a.images.radiance.values, b.images.radiance.values)
        assert same(a.images.radiance_std_error.values, b.images.radiance_std_error.values)
        assert same(a.gradient, b.gradient) and same(a.gradient_std_error, b.gradient_std_error)
        for key in ("reasons", "resampled", "ess_images", "ess_gradient", "ess_fraction", "age"):
            assert a.info[key] == b.info[key], key
        placements.append(remote.image_store.placement())
        # a recycled iteration moves the medium and the results, not the paths
        if not b.info["resampled"]:
            assert b.info["bytes_from_workers"] < remote.nbytes / 4
    assert [e["resampled"] for e in remote.log] == [True, False, True]
    # the recycled iteration moved no part to a worker that did not hold it already (Dask
    # may drop a replica made while recording, which moves nothing)
    assert placements[0].keys() == placements[1].keys()
    assert all(set(placements[1][k]) <= set(placements[0][k]) for k in placements[0])
    assert len({w for p in placements[0].values() for w in p}) == 2  # on both workers


def test_partial_results_are_refused():
    part = BatchPart(0, 2, np.zeros((2, 3)), np.zeros(2, np.int64), "cpu", 0.0)
    later = BatchPart(2, 2, np.ones((2, 3)), np.zeros(2, np.int64), "cpu", 0.0)
    values, _ = assemble([later, part], 4)
    assert same(values[:, 0], [0, 0, 1, 1])
    with pytest.raises(DistributedError, match="partial"):
        assemble([part], 4)  # a task's batches missing
    with pytest.raises(DistributedError, match="partial"):
        assemble([part, part, later], 4)  # a range twice
    with pytest.raises(DistributedError, match="partial"):
        assemble([part, later._replace(values=np.ones((1, 3)))], 4)  # a short task


def _kill_once(marker: str, after_first: bool = True):
    def hook(kind, start):
        # not the first task (unless asked): the call is under way elsewhere
        if start > 0 or not after_first:
            try:
                os.close(os.open(marker, os.O_CREAT | os.O_EXCL))
            except FileExistsError:
                return
            os._exit(1)

    return hook


def _set_hook(hook):
    batches.FAULT_HOOK = hook


def test_a_worker_killed_mid_call_is_replaced_and_the_result_is_complete(own_client, tmp_path):
    medium, scene = gradient_medium(), gradient_scene()
    ref = render(medium, scene, photons=20_000, seed=9, progress=False)
    marker = str(tmp_path / "killed")
    own_client.run(_set_hook, _kill_once(marker))
    try:
        out = render(medium, scene, photons=20_000, seed=9, progress=False,
                     executor=DaskExecutor(own_client, batches_per_task=4))
    finally:
        own_client.run(_set_hook, None)
    assert os.path.exists(marker)  # a worker did die during the call
    assert out.attrs["tasks"] == 8 and out.attrs["batches"] == 32
    assert same(out.radiance.values, ref.radiance.values)
    assert same(out.radiance_std_error.values, ref.radiance_std_error.values)


def test_paths_lost_with_every_worker_are_recorded_again_bitwise(own_client):
    """Every worker restarted between a recording and a recycled iteration: the parts, and
    the medium and scene they were recorded from, are gone with them; the store records
    them again from the medium and scene it keeps (the same paths), and the iteration is
    the single-process one, bitwise."""
    medium, scene = gradient_medium(), gradient_scene()
    w = weights_for(scene)
    local = Recycler(scene, photons=3_200, policy=FixedPeriod(2), seed=5)
    remote = DistributedRecycler(scene, client=own_client, photons=3_200, policy=FixedPeriod(2),
                                 seed=5)
    outs = []
    for recycler in (local, remote):
        for t in (0, 1):
            if recycler is remote and t == 1:
                own_client.restart_workers(list(own_client.scheduler_info()["workers"]))
                own_client.wait_for_workers(2)
            outs.append(recycler.evaluate(scaled(medium, 1.0 + 0.03 * t),
                                          residual=lambda images: w * images.radiance.values))
    ref, out = outs[1], outs[3]
    assert not out.info["resampled"]
    assert same(out.images.radiance.values, ref.images.radiance.values)
    assert same(out.gradient, ref.gradient)


def _kill_in(kinds: tuple[str, ...], marker: str):
    """Kill the worker running the first task of one of ``kinds`` past the call's first."""
    once = _kill_once(marker)

    def hook(kind, start):
        if kind in kinds:
            once(kind, start if kind != "replay" else 1)

    return hook


def _recycled_with_a_death(own_client, remote_client, arm) -> tuple:
    """The recycled second evaluation of 3,200 paths here and on ``remote_client``'s
    workers, ``arm()`` called before the remote one (it sets the fault hook), the hook
    unset after: (reference, remote result)."""
    medium, scene = gradient_medium(), gradient_scene()
    w = weights_for(scene)
    local = Recycler(scene, photons=3_200, policy=FixedPeriod(2), seed=3)
    remote = DistributedRecycler(scene, client=remote_client, photons=3_200,
                                 policy=FixedPeriod(2), seed=3)

    def evaluate(recycler, t):
        return recycler.evaluate(scaled(medium, 1.0 + 0.03 * t),
                                 residual=lambda images: w * images.radiance.values)

    for recycler in (local, remote):
        evaluate(recycler, 0)  # records the paths
    ref = evaluate(local, 1)
    arm()
    try:
        return ref, evaluate(remote, 1)  # replays them: a worker dies in it
    finally:
        own_client.run(_set_hook, None)


def _gradient_with_a_death(own_client, estimate, ex, arm) -> tuple:
    """A camera-side gradient here and with the executor ``ex``, ``arm()`` called before
    the latter, the hook unset after: (reference, distributed result)."""
    medium, scene = gradient_medium(), gradient_scene()
    run = dict(samples_per_pixel=64, seed=4, batches=8)
    ref = estimate(medium, scene, pixel_weights(), **run)
    arm()
    try:
        return ref, estimate(medium, scene, pixel_weights(), **run, executor=ex)
    finally:
        own_client.run(_set_hook, None)


@pytest.mark.parametrize("call", ["sm", "drt", "replay"])
def test_a_worker_killed_in_a_gradient_or_a_recycled_iteration_is_replaced_bitwise(
        own_client, tmp_path, call):
    """Sample matching and DRT gradients (each batch traced again elsewhere), and a recycled
    iteration whose worker dies with its part of the stored paths (the part recorded again
    from its seeds on a live worker, then replayed): bitwise the single-process result."""
    marker = str(tmp_path / "killed")
    if call == "replay":
        ref, out = _recycled_with_a_death(
            own_client, own_client,
            lambda: own_client.run(_set_hook, _kill_in(("replay",), marker)))
        assert not out.info["resampled"]
        assert same(out.images.radiance.values, ref.images.radiance.values)
        assert same(out.gradient, ref.gradient)
    else:
        estimate = {"sm": sample_matching_gradient, "drt": drt_gradient}[call]
        ref, out = _gradient_with_a_death(
            own_client, estimate, DaskExecutor(own_client, batches_per_task=2),
            lambda: own_client.run(_set_hook, _kill_in(("camera-gradient",), marker)))
        assert same(out[0], ref[0]) and same(out[1], ref[1])
    assert os.path.exists(marker)  # a worker did die during the call


def _keep_one_copy(key, dask_scheduler=None) -> str:
    """Drop every copy of ``key`` but the one on the lowest worker address, as Dask's
    active memory manager drops the copies no waiting task needs; returns that address."""
    ts = dask_scheduler.tasks[key]
    keep = min(ws.address for ws in ts.who_has)
    for ws in list(ts.who_has):
        if ws.address != keep:
            dask_scheduler.request_remove_replicas(ws.address, [key],
                                                   stimulus_id=f"cloudct-test-{key}")
    return keep


class _OneCopy(DaskExecutor):
    """Keeps one copy of what it scatters, on the lowest worker address."""

    def share(self, obj, *, cache=False):
        future, sent = super().share(obj, cache=cache)
        self.client.run_on_scheduler(_keep_one_copy, future.key)
        return future, sent


@pytest.mark.parametrize("call", ["drt", "replay"])
def test_a_worker_dying_with_the_last_copy_of_a_scattered_input_is_survived_bitwise(
        own_client, tmp_path, call):
    """The worker holding the only copy of a call's scattered inputs (the kernel inputs of
    a DRT gradient; the media of a recycled iteration, and its part of the stored paths)
    dies in the call: the scheduler forgets the tasks that need them (scattered data has no
    lineage); the inputs are scattered again from the client and the tasks submitted once
    more: bitwise the single-process result."""
    marker = str(tmp_path / "killed")
    holder = min(own_client.scheduler_info(n_workers=-1)["workers"])
    kill = _kill_once(marker, after_first=False)
    if call == "replay":
        ref, out = _recycled_with_a_death(
            own_client, _OneCopy(own_client),
            lambda: own_client.run(_set_hook, lambda kind, start: kind in (
                "log_weights", "replay") and kill(kind, start), workers=[holder]))
        assert not out.info["resampled"]
        assert same(out.images.radiance.values, ref.images.radiance.values)
        assert same(out.gradient, ref.gradient)
    else:
        ref, out = _gradient_with_a_death(
            own_client, drt_gradient, _OneCopy(own_client, batches_per_task=2),
            lambda: own_client.run(_set_hook, kill, workers=[holder]))
        assert same(out[0], ref[0]) and same(out[1], ref[1])
    assert os.path.exists(marker)  # the holder did die during the call


class _KillAlways(WorkerPlugin):
    """Every worker (restarted ones too) dies in every forward task."""

    name = "cloudct-test-kill"

    def setup(self, worker):
        def hook(kind, start):
            os._exit(1)

        batches.FAULT_HOOK = hook

    def teardown(self, worker):
        batches.FAULT_HOOK = None


def test_a_task_that_keeps_killing_workers_fails_the_call_clearly(own_client):
    medium, scene = gradient_medium(), gradient_scene()
    own_client.register_plugin(_KillAlways())
    try:
        with pytest.raises(DistributedError, match="no partial result"):
            render(medium, scene, photons=2_000, seed=1, progress=False,
                   executor=DaskExecutor(own_client, batches_per_task=32))
    finally:
        own_client.unregister_worker_plugin(_KillAlways.name)
        own_client.run(_set_hook, None)


def _wait_a_moment():
    import time

    time.sleep(2.0)  # long enough to be cancelled first, short enough not to hold the worker


def test_a_cancelled_task_fails_the_call_clearly(client):
    """A worker that dies can take the call's scattered inputs with it; the scheduler then
    cancels the tasks that need them (a race with the retries of the test above). The call
    fails with the same DistributedError as when workers keep dying, not with Dask's
    cancellation."""
    ex = DaskExecutor(client)
    future = ex.submit(_wait_a_moment, key="cloudct-test-cancelled")
    client.cancel([future])
    with pytest.raises(DistributedError, match="cancelled a task of this call"):
        ex.gather([future])


CUDASIM_SCRIPT = """
import json
import numpy as np
from numba import config
assert config.ENABLE_CUDASIM
import cloudct.mc.cuda_kernels as ck
from cloudct.distributed.batches import assemble, batch_task
from cloudct.mc.estimate import Sampling
from cloudct.mc.forward import GRADIENT, RENDER
from cloudct.mc.gradient import drt_gradient, score_function_gradient
from cloudct.mc.pixel_sampling import pixel_table
from cloudct.mc.render import render_batches
from cloudct.mc.estimate import kernel_inputs
from test_score_gradient import gradient_medium, gradient_scene, pixel_weights

ck.THREADS_PER_BLOCK = 1  # the simulator then adds in the CPU's order: bitwise
medium, scene = gradient_medium(), gradient_scene()
k = kernel_inputs(medium, scene)
out = {}
batches, per_batch = 6, 16
ref, _ = render_batches(medium, scene, photons=batches * per_batch, batches=batches,
                        progress=False, backend="cpu")
on_gpu = Sampling(batches=batches, backend="cuda")
parts = [batch_task("forward", k, on_gpu, per_batch, (RENDER, None), s, n)
         for s, n in ((0, 2), (2, 3), (5, 1))]
values, _ = assemble(parts, batches)
out["forward"] = bool(np.array_equal(values / per_batch, ref))
out["backends"] = sorted({p.backend for p in parts})
ref, _ = render_batches(medium, scene, photons=2 * batches, batches=batches, method="backward",
                        progress=False, backend="cpu")
parts = [batch_task("backward", k, on_gpu, 2, (), s, 1) for s in (0, 1)]
values, _ = assemble(parts, 2, axis=1)
out["backward"] = bool(np.array_equal(values / 2, ref))
w = pixel_weights()
ck.SORT_PATHS = False
mean = score_function_gradient(medium, scene, w, photons=batches * per_batch, batches=batches,
                               progress=False)[0]
parts = [batch_task("forward", k, on_gpu, per_batch, (GRADIENT, w), s, 3) for s in (0, 3)]
values, _ = assemble(parts, batches)
out["gradient"] = float(np.abs((values / per_batch).mean(axis=0) - mean).max() /
                        np.abs(mean).max())
k0 = kernel_inputs(medium, scene, aim_fraction=0.0)
for sampling, per_batch in (("uniform", 2), ("residual", 2 * w.size)):  # 8 samples per pixel
    mean = drt_gradient(medium, scene, w, samples_per_pixel=8, batches=4,
                        pixel_sampling=sampling)[0]
    pixels = (w, pixel_table(w, sampling))
    parts = [batch_task("camera-gradient", k0, Sampling(batches=4, backend="cuda"), per_batch,
                        (0, 1, False, False, *pixels), s, n) for s, n in ((0, 1), (1, 3))]
    values, _ = assemble(parts, 4)
    out[f"drt-{sampling}"] = bool(np.array_equal((values / per_batch).mean(axis=0), mean))
print("RESULT " + json.dumps(out))
"""


def test_gpu_worker_tasks_under_the_cuda_simulator():
    """The tasks of a GPU worker (backend "cuda": the CUDA launchers run on a range of
    batches, or one batch at a time for DRT with every pixel, results copied back by
    ``run_range``) give the CPU's per-batch arrays, checked with numba-cuda's simulator (no
    GPU here)."""
    pytest.importorskip("numba_cuda")
    import subprocess
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    env = dict(os.environ, NUMBA_ENABLE_CUDASIM="1",
               PYTHONPATH=os.pathsep.join([str(root), str(root / "tests")]))
    run = subprocess.run([sys.executable, "-c", CUDASIM_SCRIPT], env=env, capture_output=True,
                         text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    import json

    out = json.loads(run.stdout.split("RESULT ", 1)[1])
    assert out["backends"] == ["cuda"]
    assert out["forward"] and out["backward"]
    assert out["drt-uniform"] and out["drt-residual"]
    assert out["gradient"] < 1e-12  # the simulator's gradient pass adds in another order


def test_cli_render_and_retrieve_on_workers(client, tmp_path):
    """``cloudct render --scheduler`` / ``--workers`` and ``cloudct retrieve --scheduler``
    give the files of the single-process commands."""
    import xarray as xr

    from cloudct.cli import main
    from cloudct.measurements import save_measurements, synthesize_measurements
    from cloudct.medium import save_medium

    medium, scene = gradient_medium(), gradient_scene()
    save_medium(medium, tmp_path / "m.nc")
    scene.to_dataset().to_netcdf(tmp_path / "s.nc")
    address = client.scheduler.address
    # a worker killed on purpose by an earlier test may still be restarting (slow on a
    # loaded machine): the files record the workers connected at the call
    client.wait_for_workers(2, timeout=300)
    common = ["render", str(tmp_path / "m.nc"), "--scene", str(tmp_path / "s.nc"),
              "--photons", "4000"]
    assert main([*common, "-o", str(tmp_path / "one.nc")]) == 0
    assert main([*common, "-o", str(tmp_path / "sch.nc"), "--scheduler", address]) == 0
    assert main([*common, "-o", str(tmp_path / "two.nc"), "--workers", "2"]) == 0
    one = xr.load_dataset(tmp_path / "one.nc")
    for name in ("sch.nc", "two.nc"):
        other = xr.load_dataset(tmp_path / name)
        assert same(one.radiance.values, other.radiance.values)
        assert other.attrs["workers"] == 2

    scene8 = dataclasses.replace(scene, cameras=[
        dataclasses.replace(c, nrows=8, ncols=8) for c in scene.cameras
    ])  # the retrieval's default stages need image sizes divisible by 4
    measured = synthesize_measurements(medium, scene8, photons=20_000, seed=4, progress=False)
    save_measurements(measured, tmp_path / "meas.nc")
    save_medium(scaled(medium, 0.8), tmp_path / "init.nc")
    common = ["retrieve", str(tmp_path / "meas.nc"), "--init", str(tmp_path / "init.nc"),
              "--iterations", "2", "--photons", "4000"]
    # the default estimator (sample matching) on the workers
    assert main([*common, "-o", str(tmp_path / "r1.nc")]) == 0
    assert main([*common, "-o", str(tmp_path / "r2.nc"), "--scheduler", address]) == 0
    r1, r2 = xr.load_dataset(tmp_path / "r1.nc"), xr.load_dataset(tmp_path / "r2.nc")
    assert same(r1.cloud_extinction.values, r2.cloud_extinction.values)
    assert set(json.loads(r2.attrs["config"])["estimator"]) == {"sm"}
    assert same(r1.log_loss.values, r2.log_loss.values)


def test_local_cluster_keeps_the_distributed_configuration_in_a_fresh_process():
    """Starting the first local cluster of a process (distributed not yet imported) keeps
    dask's "distributed" configuration section (a temporary setting once removed it, and
    the scheduler then failed on its own defaults)."""
    import subprocess

    code = (
        "import dask, dask.config\n"
        "from cloudct.distributed import close_client, local_cluster\n"
        "client = local_cluster(1, threads=1)\n"
        "print(dask.config.get('distributed.scheduler.events-cleanup-delay'))\n"
        "print(dask.config.get('distributed.scheduler.work-stealing'))\n"
        "close_client(client)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
        cwd=os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
    )
    assert out.returncode == 0, out.stderr
    assert "KeyError" not in out.stderr
    assert out.stdout.split()[-1] == "True"  # the temporary setting is undone
