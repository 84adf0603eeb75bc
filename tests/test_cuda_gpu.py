"""The CUDA back end on a real GPU (skipped where there is none; see test_cuda_sim.py).

On a GPU the per-photon routines are compiled by NVVM, whose exp/log (libdevice) and
fused multiply-adds may differ from the CPU's in the last bit, so a photon's path can
occasionally take a different branch. Hence:

- same seed, per photon (RESIDUAL pass): nearly all vertex counts identical, and the path
  sums of those photons equal to 1e-9 relative;
- different seeds: GPU and CPU images and gradients agree within their standard errors
  (independent estimates of the same expectation, :func:`mcstats.assert_consistent`);
- path recycling: the GPU replay of a store and the CPU replay of the same store (the same
  paths, no branching on random numbers) agree to 1e-9 relative;
- same seed, every gradient estimator (score, DRT, sample matching, the backward score
  function, the combined one) with pinholes, and the first three with an orthographic
  camera: the same gradient to rounding, but for the rare paths that branch otherwise
  (:func:`assert_same_to_rounding`);
- a second process loads the kernels that the first compiled from the on-disk cache.

Run on a GPU machine with ``python -m pytest tests/test_cuda_gpu.py tests/test_cuda_sim.py``.
"""

from __future__ import annotations

import importlib.util
import json
import math
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest
from mcstats import assert_consistent

if importlib.util.find_spec("numba_cuda") is None:
    pytest.fail("numba-cuda is not installed: pip install -e '.[test]'", pytrace=False)

from numba import config, cuda  # noqa: E402

from cloudct.mc.cameras import Camera, orthographic_camera  # noqa: E402
from cloudct.mc.estimate import kernel_inputs  # noqa: E402
from cloudct.mc.forward import RESIDUAL, trace_photon  # noqa: E402
from cloudct.mc.gradient import gradient_estimate, score_function_gradient  # noqa: E402
from cloudct.mc.render import render_batches  # noqa: E402
from cloudct.mc.scene import Scene  # noqa: E402
from cloudct.mc.sun import Sun  # noqa: E402
from cloudct.medium import optical_medium, with_transmittance  # noqa: E402
from cloudct.recycling import (  # noqa: E402
    correction_log_weights,
    record_paths,
    replay_batch_gradients,
    replay_images,
    sort_paths,
)
from cloudct.recycling.store import STORAGE  # noqa: E402

pytestmark = pytest.mark.skipif(
    config.ENABLE_CUDASIM or not cuda.is_available(), reason="no CUDA GPU on this machine"
)

BATCHES = 32


def std_error(batches: np.ndarray) -> np.ndarray:
    return batches.std(axis=0, ddof=1) / math.sqrt(len(batches))


def medium_and_scene():
    axis = 0.05 + 0.1 * np.arange(6)
    ext = np.random.default_rng(1).uniform(2.0, 20.0, (6, 6, 6))
    medium = optical_medium(axis, axis, axis + 0.5, ext)
    cams = [
        Camera((0.3, 0.3, 3.0), (0.3, 0.3, 0.8), (0, 1, 0), fov=25.0, nrows=8, ncols=8),
        Camera((1.6, 0.3, 2.5), (0.3, 0.3, 0.8), (0, 0, 1), fov=25.0, nrows=8, ncols=8),
    ]
    return medium, Scene(cams, Sun(30.0, 20.0), "open", 0.3)


def test_same_photon_same_path_on_the_gpu():
    import cloudct.mc.cuda_kernels as ck

    medium, scene = medium_and_scene()
    k = kernel_inputs(medium, scene)
    residual = np.random.default_rng(2).normal(size=(2, 8, 8))
    nbatch, per_batch, first, count = 4, 5000, 0, 5000
    n = nbatch * count
    path_sum, vertices = ck.device_zeros(n), ck.device_zeros(n, np.int64)
    dummy, events = ck.device_zeros((1, 1, 1)), ck.device_zeros(nbatch, np.int64)
    ck.launch_kernel(
        ck.forward_residual_kernel, n, ck.THREADS_PER_BLOCK, ck.device_scene(k), k.periodic,
        k.ground, 100, 0.95, 3, per_batch, first, count, nbatch,
        (ck.to_device(residual), events, path_sum, vertices, dummy, dummy),
    )
    gpu_sum, gpu_vertices = ck.to_host(path_sum), ck.to_host(vertices)
    host_dummy = np.zeros((1, 1, 1))
    cpu = np.array([
        trace_photon(
            k.grid, k.bank, k.cams, k.copies, k.sun, k.periodic, k.ground, 100, 0.95, 3,
            (t // count) * per_batch + first + t % count, RESIDUAL, host_dummy, residual,
            host_dummy, 0.0,
        )
        for t in range(n)
    ])
    same = cpu[:, 0] == gpu_vertices
    assert same.mean() > 0.99, f"only {same.mean():.4f} of the paths have the same length"
    np.testing.assert_allclose(
        gpu_sum[same], cpu[same, 1], rtol=1e-9, atol=1e-12 * np.abs(cpu[:, 1]).max()
    )


def power_law(medium):
    """The medium under the power-law transmittance, shapes a = 0.5, 2 and inf."""
    shape = medium["cloud_extinction"].shape
    return with_transmittance(medium, "gamma", np.resize([0.5, 2.0, np.inf], shape))


@pytest.mark.parametrize("method, photons, transmittance", [
    ("forward", 400_000, "exponential"), ("backward", 256, "exponential"),
    ("forward", 400_000, "gamma"), ("backward", 256, "gamma"),
    ("combined", 100_000, "exponential"),
])
def test_gpu_images_agree_with_cpu(method, photons, transmittance):
    medium, scene = medium_and_scene()
    if transmittance == "gamma":
        medium = power_law(medium)
    kw = dict(photons=photons, batches=BATCHES, method=method, progress=False)
    cpu, _ = render_batches(medium, scene, seed=1, backend="cpu", **kw)
    gpu, info = render_batches(medium, scene, seed=2, backend="cuda", **kw)
    assert info["backend"] == "cuda"
    lit = cpu.mean(axis=0) > 0
    assert_consistent(
        gpu.mean(axis=0)[lit], std_error(gpu)[lit], cpu.mean(axis=0)[lit], BATCHES,
        std_error(cpu)[lit],
        label=f"{method} GPU vs CPU",
    )


@pytest.mark.parametrize("transmittance", ["exponential", "gamma"])
def test_gpu_gradient_agrees_with_cpu(transmittance):
    medium, scene = medium_and_scene()
    if transmittance == "gamma":
        medium = power_law(medium)
    residual = np.random.default_rng(2).normal(size=(2, 8, 8))
    kw = dict(photons=400_000, batches=BATCHES, progress=False)
    cpu = score_function_gradient(medium, scene, residual, seed=1, backend="cpu", **kw)
    gpu = score_function_gradient(medium, scene, residual, seed=2, backend="cuda", **kw)
    assert gpu[2]["backend"] == "cuda"
    assert_consistent(gpu[0], gpu[1], cpu[0], BATCHES, cpu[1],
                      label=f"gradient GPU vs CPU ({transmittance})")


@pytest.mark.parametrize("estimator, pixel_sampling", [
    ("drt", "uniform"), ("sm", "uniform"), ("sm", "residual"),
])
def test_gpu_camera_gradient_agrees_with_cpu(estimator, pixel_sampling):
    """The camera-side estimators (DRT, sample matching; pixels per pixel or drawn from the
    residual) on the GPU against the CPU, independent seeds."""
    medium, scene = medium_and_scene()
    residual = np.random.default_rng(2).normal(size=(2, 8, 8))
    kw = dict(estimator=estimator, photons=128 * 2 * 8 * 8, batches=BATCHES,
              pixel_sampling=pixel_sampling)
    cpu = gradient_estimate(medium, scene, residual, seed=1, backend="cpu", **kw)
    gpu = gradient_estimate(medium, scene, residual, seed=2, backend="cuda", **kw)
    assert gpu[2]["backend"] == "cuda"
    seen = np.hypot(gpu[1], cpu[1]) > 0  # voxels that some path of either run reached
    assert seen.mean() > 0.9
    assert_consistent(gpu[0][seen], gpu[1][seen], cpu[0][seen], BATCHES, cpu[1][seen],
                      label=f"{estimator} ({pixel_sampling}) GPU vs CPU")


@pytest.mark.parametrize("storage", [s for s in STORAGE if s != "auto"])
def test_gpu_replay_agrees_with_cpu_replay(storage):
    """Path recycling: the GPU replay of a store against the CPU replay of the same store
    (same paths, so no statistical test): NVVM's exp/log may differ in the last bit, and the
    atomic additions come in another order, so log r, images and gradient agree to 1e-9
    relative (and the event counts exactly), for sorted and unsorted stores."""
    medium, scene = medium_and_scene()
    current = medium.copy(deep=True)
    current["cloud_extinction"] = medium["cloud_extinction"] * np.random.default_rng(4).uniform(
        0.9, 1.1, medium["cloud_extinction"].shape
    )
    residual = np.random.default_rng(2).normal(size=(2, 8, 8))
    unsorted = record_paths(medium, scene, photons=20_000, batches=8, seed=5, storage=storage,
                            sort=False)
    for store in (unsorted, sort_paths(unsorted)):
        runs = {
            backend: (
                replay_images(store, current, backend=backend),
                replay_batch_gradients(store, current, residual, backend=backend),
                correction_log_weights(store, current, backend=backend),
            )
            for backend in ("cpu", "cuda")
        }
        (cpu_images, cpu_ii), (cpu_gradient, cpu_gi), cpu_log_w = runs["cpu"]
        (gpu_images, gpu_ii), (gpu_gradient, gpu_gi), gpu_log_w = runs["cuda"]
        assert gpu_ii["backend"] == gpu_gi["backend"] == "cuda"
        assert gpu_ii["events"] == cpu_ii["events"] > 0
        assert gpu_gi["events"] == cpu_gi["events"]
        for cpu, gpu in ((cpu_ii["log_r"], gpu_ii["log_r"]), (cpu_gi["log_r"], gpu_gi["log_r"]),
                         (cpu_log_w, gpu_log_w)):
            np.testing.assert_allclose(gpu, cpu, rtol=1e-9, atol=1e-12)
        for cpu, gpu in ((cpu_images, gpu_images), (cpu_gradient, gpu_gradient)):
            np.testing.assert_allclose(gpu, cpu, rtol=1e-9, atol=1e-12 * np.abs(cpu).max())


def assert_same_to_rounding(gpu: np.ndarray, cpu: np.ndarray, label: str) -> None:
    """Same-seed estimates on both targets: equal to rounding except where NVVM's last-bit
    differences make a rare path branch otherwise (see the module docstring): at least
    99.9 % of the entries equal to 1e-9 relative, and all of them together within 1e-4 of
    the estimate's total magnitude."""
    scale = np.abs(cpu).max()
    close = np.isclose(gpu, cpu, rtol=1e-9, atol=1e-12 * scale)
    spread = np.abs(gpu - cpu).sum() / np.abs(cpu).sum()
    print(f"{label}: {close.mean():.6f} of entries equal to 1e-9, summed difference "
          f"{spread:.3g} of the total, largest {np.abs(gpu - cpu).max() / scale:.3g} of the "
          "largest entry")
    assert close.mean() >= 0.999, f"{label}: only {close.mean():.5f} equal to rounding"
    assert spread < 1e-4, f"{label}: summed difference {spread:.3g} of the total"


@pytest.mark.parametrize("estimator, pixel_sampling", [
    ("score", "uniform"), ("drt", "uniform"), ("sm", "uniform"), ("sm", "residual"),
    ("backward-score", "uniform"), ("combined", "uniform"),
])
def test_same_seed_gradients_equal_the_cpus(estimator, pixel_sampling):
    """Every gradient estimator, same seed on both back ends: the same random streams, so
    the same paths and the same gradient to rounding (the render's property, issue 34)."""
    medium, scene = medium_and_scene()
    residual = np.random.default_rng(2).normal(size=(2, 8, 8))
    paths = {"score": 400_000, "combined": 100_000}.get(estimator, 64 * 2 * 8 * 8)
    kw = dict(estimator=estimator, photons=paths, batches=BATCHES, seed=3,
              pixel_sampling=pixel_sampling)
    cpu = gradient_estimate(medium, scene, residual, backend="cpu", **kw)
    gpu = gradient_estimate(medium, scene, residual, backend="cuda", **kw)
    assert (cpu[2]["backend"], gpu[2]["backend"]) == ("cpu", "cuda")
    assert_same_to_rounding(gpu[0], cpu[0], f"{estimator} ({pixel_sampling}) same seed")


@pytest.mark.parametrize("estimator", ["score", "drt", "sm"])
def test_same_seed_gradients_of_orthographic_cameras_equal_the_cpus(estimator):
    """An orthographic camera beside a pinhole: every gradient estimator, same seed on both
    back ends, the same gradient to rounding (as for pinholes above)."""
    medium, scene = medium_and_scene()
    ortho = orthographic_camera((0.3, 0.3, 0.8), 30.0, 200.0, width=0.6, nrows=8,
                                distance=2.0)
    scene = Scene([ortho, scene.cameras[0]], scene.sun, scene.boundary, scene.ground_albedo)
    residual = np.random.default_rng(2).normal(size=(2, 8, 8))
    paths = 400_000 if estimator == "score" else 64 * 2 * 8 * 8
    kw = dict(estimator=estimator, photons=paths, batches=BATCHES, seed=3)
    cpu = gradient_estimate(medium, scene, residual, backend="cpu", **kw)
    gpu = gradient_estimate(medium, scene, residual, backend="cuda", **kw)
    assert (cpu[2]["backend"], gpu[2]["backend"]) == ("cpu", "cuda")
    assert_same_to_rounding(gpu[0], cpu[0], f"{estimator}, orthographic camera, same seed")


def test_same_seed_fluxes_and_probes_equal_the_cpus():
    """Domain-mean fluxes and radiance probes, same seed on both back ends: the same photons,
    so the same shares and probe radiances, within 1e-4 relative (as the same-seed gradients:
    atomic additions in another order, and NVVM's exp/log may end a rare path elsewhere)."""
    from cloudct.mc.sensors import FLUX_SHARES, domain_means

    medium, scene = medium_and_scene()
    kw = dict(directions=[(20.0, 10.0), (140.0, 200.0)], sun=scene.sun, boundary="open",
              ground_albedo=0.3, photons=400_000, batches=BATCHES, seed=3, progress=False)
    cpu = domain_means(medium, backend="cpu", **kw)
    gpu = domain_means(medium, backend="cuda", **kw)
    assert gpu.attrs["backend"] == "cuda"
    assert abs(gpu.attrs["events"] - cpu.attrs["events"]) <= 1e-4 * cpu.attrs["events"]
    for name in ("radiance", *FLUX_SHARES):
        np.testing.assert_allclose(gpu[name].values, cpu[name].values, rtol=1e-4,
                                   atol=1e-9, err_msg=name)


def test_a_second_process_loads_the_kernels_from_the_cache(tmp_path):
    """Issue 34's warm start: the kernels compiled by one process are loaded, not compiled,
    by the next (cloudct.jit_cache)."""
    code = textwrap.dedent("""
        import json, time
        from test_cuda_gpu import medium_and_scene
        from cloudct.mc.render import render
        import cloudct.mc.cuda_kernels as ck
        medium, scene = medium_and_scene()
        start = time.perf_counter()
        render(medium, scene, photons=64, batches=2, backend="cuda", progress=False)
        stats = ck.forward_render_kernel.stats
        print(json.dumps([sum(stats.cache_hits.values()), sum(stats.cache_misses.values()),
                          time.perf_counter() - start]))
    """)
    env = dict(os.environ, CLOUDCT_CACHE_DIR=str(tmp_path),
               PYTHONPATH=os.pathsep.join([os.path.dirname(__file__),
                                           os.environ.get("PYTHONPATH", "")]))
    runs = [json.loads(subprocess.run([sys.executable, "-c", code], env=env, text=True,
                                      capture_output=True, check=True).stdout.splitlines()[-1])
            for _ in range(2)]
    print(f"first render: {runs[0][2]:.1f} s (compiling), second process: {runs[1][2]:.1f} s")
    assert runs[0][:2] == [0, 1] and runs[1][:2] == [1, 0]
