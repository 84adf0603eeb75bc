"""The CUDA back end against the CPU path, on a machine without a GPU.

1. CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``, set in a subprocess before numba is imported
   so that the rest of the suite stays on the normal CPU path). The simulated kernels
   (:mod:`cloudct.mc.cuda_kernels`) run the same compiled ``@njit`` per-photon routines as
   the CPU kernels, with the CPU's photon indexing and random streams (renders and the
   score-function gradient also of a medium under the power-law transmittance, whose
   gradient walks each flight twice). Expected agreement:

   - per photon (RESIDUAL pass: path sum and vertex count; every pixel sample): **bitwise**,
     since each photon draws the same stream and runs the same code;
   - per-batch images and gradients with one thread per block, where the simulator runs the
     threads one after the other, so every output element receives its photons' terms in the
     CPU's order: **bitwise**;
   - with 32 threads per block and with the GRADIENT pass re-ordered by path length (seed
     paper Sec. 5.3), only the order of the additions into an element can differ: equal **to
     float64 rounding** (rtol 1e-12, atol 1e-12 x the largest element); vertex counts exact.

   Renders: forward (plain and aimed at the cameras), backward, and combined (both, weighted
   by multiple importance sampling). Orthographic cameras: renders and the three gradient
   estimators to float64 rounding.

   Path recycling (:mod:`cloudct.recycling.cuda_replay`, one thread per stored path; stores
   of pinhole and of orthographic cameras) against the CPU replay of the same store: log r
   per path **bitwise** in every thread order; images and gradients **bitwise** with one
   thread per block in photon order, **to float64 rounding** in the storage-slot order of a
   sorted store (path sorting) and with 32 threads per block; event counts exact.

   The simulator runs the ``@njit`` routines as CPU code: it checks the kernels' indexing,
   launches, passes and reductions, not the GPU compilation.
2. GPU compilation without a GPU: each kernel, with every ``@njit`` routine it calls and the
   atomic CUDA implementation of ``add_to``, is compiled to PTX for sm_90 by NVVM and
   assembled by ptxas (from the ``cu12`` toolkit wheels of the ``test`` extra): in
   ``test_cuda_ptx.py``, which shares this file's scenes and subprocess runner.
3. Back-end choice in this process (no GPU): ``auto`` falls back to the CPU with a warning,
   ``cuda`` raises (render and replay).

numba-cuda is part of the ``test`` extra: without it these tests fail rather than skip. On a
machine with a GPU, ``tests/test_cuda_gpu.py`` runs the kernels for real.
"""

from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from cloudct.mc.render import render_batches

ROOT = Path(__file__).resolve().parents[1]

SCENES = """
import numpy as np
from cloudct.mc.cameras import Camera, orthographic_camera
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.medium import optical_medium, with_transmittance

axis = 0.05 + 0.1 * np.arange(4)
ext = np.random.default_rng(1).uniform(2.0, 12.0, (4, 4, 4))
ext[0] = 0.0
medium = optical_medium(axis, axis, axis + 0.5, ext)
# the power law of unresolved variability, shapes a = 0.5, 2 and inf (docs/transmittance.md)
power_law = with_transmittance(medium, "gamma", np.resize([0.5, 2.0, np.inf], ext.shape))
cams = [Camera((0.2, 0.2, 3.0), (0.2, 0.2, 0.7), (0, 1, 0), fov=20.0, nrows=6, ncols=6),
        Camera((1.5, 0.2, 2.5), (0.2, 0.2, 0.7), (0, 0, 1), fov=20.0, nrows=6, ncols=6)]
scenes = {"open": Scene(cams, Sun(30.0, 20.0), "open", 0.3),
          "periodic": Scene(cams[:1], Sun(20.0, 60.0), "periodic", None)}
# orthographic cameras: beside a pinhole over the open box, alone over the periodic slab
ortho_scenes = {
    "open": Scene([orthographic_camera((0.2, 0.2, 0.7), 25.0, 120.0, width=0.3, nrows=6,
                                       distance=2.0), cams[0]], Sun(30.0, 20.0), "open", 0.3),
    "periodic": Scene([orthographic_camera((0.2, 0.2, 0.7), 20.0, 60.0, width=0.6, nrows=6,
                                           distance=3.0)], Sun(20.0, 60.0), "periodic", None),
}
"""

COMPARE = """
def compare(cpu, gpu):
    cpu, gpu = np.asarray(cpu), np.asarray(gpu)
    return {"bitwise": bool(np.array_equal(cpu, gpu)), "max_diff": float(np.abs(cpu - gpu).max()),
            "scale": float(np.abs(cpu).max()), "cpu": cpu.tolist(), "gpu": gpu.tolist()}


def on_both(call):
    # compare() of call(backend)[0] on the CPU and on CUDA (a render's images or a
    # gradient's mean), with both runs' path vertices and the back end CUDA's ran on
    runs = [call(b) for b in ("cpu", "cuda")]
    case = compare(runs[0][0], runs[1][0])
    case["events"] = [runs[0][-1]["events"], runs[1][-1]["events"]]
    case["backend"] = runs[1][-1]["backend"]
    return case
"""

SIMULATOR_SCRIPT = SCENES + COMPARE + """
import json
from numba import config
assert config.ENABLE_CUDASIM
import cloudct.mc.cuda_kernels as ck
from cloudct.mc.backend import resolve_backend
from cloudct.mc.forward import RESIDUAL, trace_photon
from cloudct.mc.backward import trace_pixel_sample
from cloudct.mc.gradient import score_function_gradient
from cloudct.mc.render import render_batches
from cloudct.mc.estimate import kernel_inputs

out = {"auto": resolve_backend("auto")}
# renders: label, method, photons (samples per pixel), aim fraction, further arguments;
# "combined": forward photons aimed at the cameras and backward samples, MIS-weighted
RENDERS = (("forward", "forward", 256, None, {}), ("aimed", "forward", 256, 0.3, {}),
           ("backward", "backward", 8, None, {}),
           ("combined", "combined", 256, 0.3, {"pixel_samples": 8}))
residual = np.random.default_rng(2).normal(size=(2, 6, 6))
for tpb in (1, 32):
    ck.THREADS_PER_BLOCK = tpb
    for name, scene in scenes.items():
        for label, method, n, aim, kw in RENDERS:
            out[f"{label}/{name}/tpb{tpb}"] = on_both(lambda b: render_batches(
                medium, scene, photons=n, batches=4, method=method, aim_fraction=aim,
                progress=False, backend=b, **kw))
    for label, method, n in (("powerlaw", "forward", 256), ("powerlaw-backward", "backward", 8)):
        out[f"{label}/open/tpb{tpb}"] = on_both(lambda b: render_batches(
            power_law, scenes["open"], photons=n, batches=4, method=method, progress=False,
            backend=b))
    for sort in (False, True):
        ck.SORT_PATHS = sort
        for label, aim, which in (("gradient", None, medium), ("gradient-aimed", 0.3, medium),
                                  ("gradient-powerlaw", None, power_law)):
            out[f"{label}/sort{int(sort)}/tpb{tpb}"] = on_both(
                lambda b: score_function_gradient(
                    which, scenes["open"], residual, photons=256, batches=4, aim_fraction=aim,
                    progress=False, backend=b))

from cloudct.mc.gradient import drt_gradient, sample_matching_gradient
camera_side = {
    "drt": (drt_gradient, {}),
    "drt-residual": (drt_gradient, {"pixel_sampling": "residual"}),
    "sm": (sample_matching_gradient, {"probes": 2}),
    "sm-quadratic": (sample_matching_gradient, {"quadratic": True}),
    "sm-dual-suffix": (sample_matching_gradient, {"mis": False}),
    "sm-residual": (sample_matching_gradient, {"pixel_sampling": "residual"}),
}
for tpb in (1, 32):
    ck.THREADS_PER_BLOCK = tpb
    for name, (estimate, kw) in camera_side.items():
        out[f"{name}/tpb{tpb}"] = on_both(lambda b: estimate(
            medium, scenes["open"], residual, samples_per_pixel=4, batches=4, backend=b, **kw))

# orthographic cameras: renders, the score-function gradient (aimed paths, re-traced by
# path length) and the camera-side gradients, blocks of 32 threads
ck.THREADS_PER_BLOCK, ck.SORT_PATHS = 32, True
for name, scene in ortho_scenes.items():
    res = residual[:len(scene.cameras)]
    for label, method, n, aim, kw in RENDERS:
        out[f"orthographic-{label}/{name}"] = on_both(lambda b: render_batches(
            medium, scene, photons=n, batches=4, method=method, aim_fraction=aim,
            progress=False, backend=b, **kw))
    for label, estimate, kw in (
        ("score", score_function_gradient, {"photons": 256, "aim_fraction": 0.3}),
        ("drt", drt_gradient, {"samples_per_pixel": 4}),
        ("sm", sample_matching_gradient, {"samples_per_pixel": 4}),
    ):
        out[f"orthographic-{label}/{name}"] = on_both(lambda b: estimate(
            medium, scene, res, batches=4, backend=b, progress=False, **kw))

# domain-mean fluxes and radiance probes: the render's photons with their flux tallies
from cloudct.mc.sensors import FLUX_SHARES, domain_means
from cloudct.mc.sun import Sun
for tpb in (1, 32):
    ck.THREADS_PER_BLOCK = tpb
    for name, ground in (("open", 0.3), ("periodic", None)):
        runs = [domain_means(medium, directions=[(20.0, 10.0), (140.0, 200.0)],
                             sun=Sun(30.0, 20.0), boundary=name, ground_albedo=ground,
                             photons=256, batches=4, progress=False, backend=b)
                for b in ("cpu", "cuda")]
        names = ["radiance", *FLUX_SHARES]
        values = [np.concatenate([np.ravel(r[n].values) for v in names
                                  for n in (v, v + "_std_error")]) for r in runs]
        out[f"fluxes/{name}/tpb{tpb}"] = case = compare(values[0], values[1])
        case["events"] = [runs[0].attrs["events"], runs[1].attrs["events"]]
        case["backend"] = runs[1].attrs["backend"]

# per photon: the RESIDUAL pass kernel against trace_photon called on the CPU
k = kernel_inputs(medium, scenes["open"])
nbatch, per_batch, first, count = 3, 40, 5, 30
path_sum = np.zeros(nbatch * count)
vertices = np.zeros(nbatch * count, np.int64)
dummy = np.zeros((1, 1, 1))
events = np.zeros(nbatch, np.int64)
ck.THREADS_PER_BLOCK = 32
ck.launch_kernel(ck.forward_residual_kernel, nbatch * count, 32, ck.device_scene(k), k.periodic,
                 k.ground, 100, 0.95, 7, per_batch, first, count, nbatch, (residual, events,
                 path_sum, vertices, dummy, dummy))
cpu_sum, cpu_vertices = [], []
for t in range(nbatch * count):
    index = (t // count) * per_batch + first + t % count
    v, s = trace_photon(k.grid, k.bank, k.cams, k.copies, k.sun, k.periodic, k.ground, 100,
                        0.95, 7, index, RESIDUAL, dummy, residual, dummy, 0.0)
    cpu_sum.append(s)
    cpu_vertices.append(v)
out["photon/path_sum"] = compare(cpu_sum, path_sum)
out["photon/vertices"] = compare(cpu_vertices, vertices)
print("RESULT " + json.dumps(out))
"""

RECYCLING_SCRIPT = SCENES + COMPARE + """
import gc, json
from numba import config
assert config.ENABLE_CUDASIM
import cloudct.mc.cuda_kernels as ck
import cloudct.recycling.cuda_replay as cr
from cloudct.recycling import (Recycler, correction_log_weights, record_paths,
                               replay_batch_gradients, replay_images)
from cloudct.recycling.store import STORAGE

current = medium.copy(deep=True)
current["cloud_extinction"] = medium["cloud_extinction"] * np.random.default_rng(3).uniform(
    0.8, 1.2, ext.shape)
residual = np.random.default_rng(2).normal(size=(2, 6, 6))
stores = [(name, storage, sort, {}) for name in scenes for storage in STORAGE
          if storage != "auto" for sort in (False, True)]
if "connections" in STORAGE:  # camera connections of the variable (cloud) voxels only
    stores.append(("open", "connections", True, {"variable": ext > 0}))
stores.append(("open", "crossings", True, {"aim_fraction": 0.3}))  # aimed paths
# orthographic cameras: stored camera connections, and connections recomputed
all_scenes = {**scenes, **{f"orthographic-{n}": s for n, s in ortho_scenes.items()}}
stores += [("orthographic-open", "connections", True, {}),
           ("orthographic-periodic", "crossings", True, {})]
out = {}
for name, storage, sort, extra in stores:
    scene = all_scenes[name]
    res = residual[:len(scene.cameras)]
    store = record_paths(medium, scene, photons=48, batches=3, seed=5, storage=storage,
                         sort=sort, **extra)
    suffix = {"variable": "-masked", "aim_fraction": "-aimed"}.get(next(iter(extra), ""), "")
    label = f"{name}/{storage}{suffix}/sort{int(sort)}"
    cpu_images, cpu_ii = replay_images(store, current)
    cpu_gradient, cpu_gi = replay_batch_gradients(store, current, res)
    cpu_log_w = correction_log_weights(store, current)
    # thread order: photon order (the CPU's) or consecutive storage slots (path sorting)
    for tpb, by_slot in ((1, False), (1, True), (32, True)):
        ck.THREADS_PER_BLOCK, ck.SORT_PATHS = tpb, by_slot
        images, ii = replay_images(store, current, backend="cuda")
        gradient, gi = replay_batch_gradients(store, current, res, backend="cuda")
        key = f"{label}/tpb{tpb}/{'slot' if by_slot else 'photon'}"
        for what, cpu, gpu, cpu_info, gpu_info in (("images", cpu_images, images, cpu_ii, ii),
                                                   ("gradient", cpu_gradient, gradient, cpu_gi,
                                                    gi)):
            case = compare(cpu, gpu)
            case["events"] = [cpu_info["events"], gpu_info["events"]]
            case["backend"] = gpu_info["backend"]
            out[f"{key}/{what}"] = case
            out[f"{key}/{what}/log_r"] = compare(cpu_info["log_r"], gpu_info["log_r"])
        out[f"{key}/log_weights"] = compare(cpu_log_w,
                                            correction_log_weights(store, current, "cuda"))
    # slot order: thread q of the launch takes the path in storage slot q
    order = np.asarray(cr.device_store(store).order(True))
    out[f"{label}/slot_order"] = bool(np.array_equal(store.arrays.slot[order],
                                                     np.arange(store.paths)))

# the recycler: two evaluations (record, then recycle under another medium) on each back
# end, with forward paths alone and with the combined estimator (replays weighted, camera
# paths fresh)
ck.THREADS_PER_BLOCK, ck.SORT_PATHS = 32, True
for name, methods in (("recycler", ("forward", "score")),
                      ("recycler-combined", ("combined", "combined"))):
    evaluations = []
    for backend in ("cpu", "cuda"):
        recycler = Recycler(scenes["open"], photons=48, batches=3, seed=9,
                            storage="crossings", backend=backend, image_method=methods[0],
                            gradient_estimator=methods[1])
        evaluations.append([recycler.evaluate(m, residual=residual) for m in (medium, current)])
    for t, (cpu, gpu) in enumerate(zip(*evaluations)):
        out[f"{name}/{t}/images"] = compare(cpu.images.radiance, gpu.images.radiance)
        out[f"{name}/{t}/gradient"] = compare(cpu.gradient, gpu.gradient)
        out[f"{name}/{t}/info"] = [[e.info[k] for k in ("reasons", "ess_images",
                                                          "ess_gradient")]
                                   for e in (cpu, gpu)]

# the device copy of a store is made once and freed with the store
def cached_then_freed():
    store = record_paths(medium, scenes["open"], photons=6, batches=2, seed=1)
    first = cr.device_store(store)
    key = id(store)
    same = cr.device_store(store) is first
    del store, first
    gc.collect()
    return same, key not in cr._resident
out["device_store"] = cached_then_freed()
print("RESULT " + json.dumps(out))
"""

def require_numba_cuda() -> None:
    if importlib.util.find_spec("numba_cuda") is None:
        pytest.fail(
            "numba-cuda is not installed; the CUDA back end cannot be tested. Install the test "
            "extra: pip install -e '.[test]'",
            pytrace=False,
        )


def run_script(script: str, simulator: bool, timeout: float = 600.0) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(ROOT), env.get("PYTHONPATH")]))
    env.pop("NUMBA_ENABLE_CUDASIM", None)
    if simulator:
        env["NUMBA_ENABLE_CUDASIM"] = "1"
    proc = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=timeout,
        cwd=ROOT,
    )
    lines = [line for line in proc.stdout.splitlines() if line.startswith("RESULT ")]
    assert proc.returncode == 0 and lines, (
        f"subprocess failed (rc {proc.returncode}):\n{proc.stdout[-3000:]}\n{proc.stderr[-6000:]}"
    )
    return json.loads(lines[-1][len("RESULT "):])


@pytest.fixture(scope="module")
def simulated() -> dict:
    require_numba_cuda()
    return run_script(SIMULATOR_SCRIPT, simulator=True)


def test_simulator_is_the_cuda_backend(simulated):
    assert simulated["auto"] == "cuda"
    renders = [v for key, v in simulated.items()
               if key.startswith(("forward/", "aimed/", "backward/", "combined/"))]
    assert renders and all(v["backend"] == "cuda" for v in renders)


@pytest.mark.parametrize("key", ["photon/path_sum", "photon/vertices"])
def test_same_photon_same_path(simulated, key):
    """Each photon index draws the same stream on both back ends: bitwise equal."""
    case = simulated[key]
    assert case["bitwise"], f"{key}: max difference {case['max_diff']:.3g}"
    assert case["scale"] > 0.0


@pytest.mark.parametrize(
    "key",
    [f"{m}/{s}/tpb1" for m in ("forward", "aimed", "backward", "combined")
     for s in ("open", "periodic")]
    + ["powerlaw/open/tpb1", "powerlaw-backward/open/tpb1"]
    + ["gradient/sort0/tpb1", "gradient-aimed/sort0/tpb1", "gradient-powerlaw/sort0/tpb1"],
)
def test_sequential_threads_match_cpu_bitwise(simulated, key):
    """One thread per block: the CPU's summation order, so bitwise equal batches."""
    case = simulated[key]
    assert case["bitwise"], f"{key}: max difference {case['max_diff']:.3g} of {case['scale']:.3g}"
    assert case["scale"] > 0.0
    assert case["events"][0] == case["events"][1] > 0


@pytest.mark.parametrize(
    "key",
    [f"{m}/{s}/tpb32" for m in ("forward", "aimed", "backward", "combined")
     for s in ("open", "periodic")]
    + ["powerlaw/open/tpb32", "powerlaw-backward/open/tpb32"]
    + [f"{g}/{c}" for g in ("gradient", "gradient-aimed", "gradient-powerlaw")
       for c in ("sort1/tpb1", "sort0/tpb32", "sort1/tpb32")],
)
def test_reordered_threads_match_cpu_to_rounding(simulated, key):
    """Blocks of 32 threads, path-length order: summation order only, float64 rounding."""
    case = simulated[key]
    cpu, gpu = np.array(case["cpu"]), np.array(case["gpu"])
    assert case["scale"] > 0.0
    np.testing.assert_allclose(gpu, cpu, rtol=1e-12, atol=1e-12 * case["scale"], err_msg=key)
    assert case["events"][0] == case["events"][1] > 0


@pytest.mark.parametrize(
    "key",
    [f"orthographic-{what}/{scene}" for what in ("forward", "aimed", "backward", "combined",
                                                 "score", "drt", "sm")
     for scene in ("open", "periodic")],
)
def test_orthographic_cameras_match_cpu_to_rounding(simulated, key):
    """Orthographic cameras (one beside a pinhole over the open box, one over the periodic
    slab): renders (forward, aimed at the cameras, backward, combined), the score-function
    gradient of aimed paths and the DRT and sample-matching gradients on the CUDA back end,
    blocks of 32 threads: the CPU's samples summed in another order, equal to float64 rounding,
    with the same path vertices. (Path recycling with them: the replay tests below.)"""
    case = simulated[key]
    assert case["backend"] == "cuda"
    assert case["scale"] > 0.0
    np.testing.assert_allclose(np.array(case["gpu"]), np.array(case["cpu"]), rtol=1e-12,
                               atol=1e-12 * case["scale"], err_msg=key)
    assert case["events"][0] == case["events"][1] > 0


@pytest.mark.parametrize("scene", ["open", "periodic"])
def test_fluxes_and_probes_match_cpu(simulated, scene):
    """Domain-mean fluxes and radiance probes (:func:`cloudct.mc.sensors.domain_means`) on
    the CUDA back end: each share, each probe and their standard errors equal the CPU's
    bitwise with one thread per block (the CPU's summation order), to float64 rounding in
    blocks of 32 threads; the same path vertices."""
    for tpb in (1, 32):
        case = simulated[f"fluxes/{scene}/tpb{tpb}"]
        assert case["backend"] == "cuda"
        assert case["scale"] > 0.0
        assert case["events"][0] == case["events"][1] > 0
        if tpb == 1:
            assert case["bitwise"], f"max difference {case['max_diff']:.3g}"
        np.testing.assert_allclose(np.array(case["gpu"]), np.array(case["cpu"]), rtol=1e-12,
                                   atol=1e-12 * case["scale"])


def test_auto_backend_falls_back_to_cpu_with_a_warning():
    """No GPU in this process: ``auto`` warns once and renders on the CPU; ``cuda`` raises."""
    require_numba_cuda()
    from numba import cuda

    if cuda.is_available():
        pytest.skip("a GPU (or the simulator) is available in this process")
    ns: dict = {}
    exec(SCENES, ns)
    kw = dict(photons=64, batches=2, progress=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        auto, info = render_batches(ns["medium"], ns["scenes"]["open"], backend="auto", **kw)
    assert info["backend"] == "cpu"
    warned = [w for w in caught if "backend='auto'" in str(w.message)]
    assert warned and warned[0].filename == __file__  # the caller's line, not the engine's
    cpu, _ = render_batches(ns["medium"], ns["scenes"]["open"], backend="cpu", **kw)
    assert np.array_equal(auto, cpu)
    with pytest.raises(RuntimeError, match="backend='cuda'"):
        render_batches(ns["medium"], ns["scenes"]["open"], backend="cuda", **kw)
    with pytest.raises(ValueError, match="backend must be one of"):
        render_batches(ns["medium"], ns["scenes"]["open"], backend="gpu", **kw)


def test_sort_by_path_length_is_stable():
    from cloudct.mc.backend import sort_by_path_length

    lengths = np.array([3, 1, 2, 1, 3, 0, 2])
    order = sort_by_path_length(lengths)
    assert order.tolist() == [5, 1, 3, 2, 6, 0, 4]
    assert np.all(np.diff(lengths[order]) >= 0)


@pytest.mark.parametrize("estimator", ["drt", "drt-residual", "sm", "sm-quadratic",
                                       "sm-dual-suffix", "sm-residual"])
@pytest.mark.parametrize("tpb", [1, 32])
def test_camera_gradient_kernels_match_cpu_to_rounding(simulated, estimator, tpb):
    """The camera-side gradient kernels (DRT, sample matching; every pixel, or pixels drawn
    from the residual's alias table): the same samples as the CPU (same streams), summed in
    another order (threads run pixel-major, the CPU sample-major per pixel): equal to
    float64 rounding, with the same path vertices."""
    key = f"{estimator}/tpb{tpb}"
    case = simulated[key]
    cpu, gpu = np.array(case["cpu"]), np.array(case["gpu"])
    assert case["scale"] > 0.0
    np.testing.assert_allclose(gpu, cpu, rtol=1e-12, atol=1e-12 * case["scale"], err_msg=key)
    assert case["events"][0] == case["events"][1] > 0


# --------------------------------------------------------------------------------------
# Path recycling: the replay kernels (cloudct.recycling.cuda_replay) against the CPU replay
# of the same store, for every storage mode, sorted and unsorted stores, both scenes.
# --------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def recycled() -> dict:
    require_numba_cuda()
    return run_script(RECYCLING_SCRIPT, simulator=True)


def replay_cases(recycled: dict, *parts: str) -> dict:
    """The image and gradient comparisons whose key holds every one of ``parts``."""
    cases = {
        key: case for key, case in recycled.items()
        if key.endswith(("/images", "/gradient")) and all(p in key for p in parts)
    }
    assert cases, parts
    return cases


def test_replay_ran_on_the_cuda_backend(recycled):
    cases = replay_cases(recycled, "/tpb")
    assert all(case["backend"] == "cuda" for case in cases.values())
    assert all(case["scale"] > 0.0 for case in cases.values())


@pytest.mark.parametrize("parts", [("/tpb1/photon/",), ("/sort0/tpb1/slot/",)])
def test_replay_in_photon_order_matches_cpu_bitwise(recycled, parts):
    """One thread per block in photon order (an unsorted store's slot order is its photon
    order): every image and gradient element receives its paths' terms in the CPU's order,
    so the per-batch images and gradients are bitwise those of the CPU replay."""
    for key, case in replay_cases(recycled, *parts).items():
        assert case["bitwise"], f"{key}: max difference {case['max_diff']:.3g}"
        assert case["events"][0] == case["events"][1] > 0, key


@pytest.mark.parametrize("parts", [("/sort1/tpb1/slot/",), ("/tpb32/",)])
def test_replay_in_slot_order_matches_cpu_to_rounding(recycled, parts):
    """Sorted stores replayed in storage-slot order (path sorting) and blocks of 32 threads:
    the same terms, added in another order: equal to float64 rounding; events exact."""
    for key, case in replay_cases(recycled, *parts).items():
        cpu, gpu = np.array(case["cpu"]), np.array(case["gpu"])
        np.testing.assert_allclose(gpu, cpu, rtol=1e-12, atol=1e-12 * case["scale"],
                                   err_msg=key)
        assert case["events"][0] == case["events"][1] > 0, key


def test_replay_log_r_is_bitwise_in_every_thread_order(recycled):
    """log r per path (from the replays and from the log-weight kernel): each path is
    evaluated by one thread with the CPU's operations: bitwise, whatever the order."""
    cases = {k: v for k, v in recycled.items() if k.endswith(("/log_r", "/log_weights"))}
    assert len(cases) == 3 * len(replay_cases(recycled, "/tpb")) // 2
    for key, case in cases.items():
        assert case["bitwise"], f"{key}: max difference {case['max_diff']:.3g}"
    assert any(case["scale"] > 0.0 for case in cases.values())


def test_replay_slot_order_takes_consecutive_slots(recycled):
    orders = {k: v for k, v in recycled.items() if k.endswith("/slot_order")}
    assert orders and all(orders.values()), orders


@pytest.mark.parametrize("name", ["recycler", "recycler-combined"])
def test_recycler_on_the_cuda_backend_matches_cpu(recycled, name):
    """Two evaluations (the first records the stores, the second recycles them under
    another medium): the same decisions and ESS, images and gradient to rounding; with
    forward paths alone, and with the combined estimator (the replays weighted, the fresh
    camera paths the same on both back ends for the same seed)."""
    for t in (0, 1):
        for what in ("images", "gradient"):
            case = recycled[f"{name}/{t}/{what}"]
            assert case["scale"] > 0.0
            np.testing.assert_allclose(np.array(case["gpu"]), np.array(case["cpu"]), rtol=1e-12,
                                       atol=1e-12 * case["scale"], err_msg=f"{t}/{what}")
        cpu_info, gpu_info = recycled[f"{name}/{t}/info"]
        assert cpu_info == gpu_info
    assert recycled[f"{name}/0/info"][0][0] == {"images": "initial", "gradient": "initial"}


def test_device_store_is_cached_and_freed_with_the_store(recycled):
    assert recycled["device_store"] == [True, True]


def test_replay_auto_backend_falls_back_to_cpu_with_a_warning():
    """No GPU in this process: the replay's ``auto`` warns and runs on the CPU (bitwise the
    CPU replay); ``cuda`` raises; so does a Recycler asked for ``cuda``."""
    require_numba_cuda()
    from numba import cuda

    from cloudct.recycling import Recycler, record_paths, replay_images

    if cuda.is_available():
        pytest.skip("a GPU (or the simulator) is available in this process")
    ns: dict = {}
    exec(SCENES, ns)
    store = record_paths(ns["medium"], ns["scenes"]["open"], photons=8, batches=2, seed=1)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        auto, info = replay_images(store, ns["medium"], backend="auto")
    assert info["backend"] == "cpu"
    assert [str(w.message) for w in caught if "backend='auto'" in str(w.message)]
    assert np.array_equal(auto, replay_images(store, ns["medium"])[0])
    with pytest.raises(RuntimeError, match="backend='cuda'"):
        replay_images(store, ns["medium"], backend="cuda")
    with pytest.raises(RuntimeError, match="backend='cuda'"):
        Recycler(ns["scenes"]["open"], photons=8, batches=2, backend="cuda")
