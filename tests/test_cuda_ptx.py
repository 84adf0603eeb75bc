"""Every CUDA kernel compiled for a real GPU without one: numba-cuda's PTX for sm_90,
assembled by ptxas (or linked by nvJitLink), in a subprocess that names the device.

Its own file, apart from the simulator's tests of ``test_cuda_sim.py``, so that the test
runner gives this long compilation (minutes on 2 cores) a worker of its own."""

from __future__ import annotations

import importlib.util

import pytest
from test_cuda_sim import SCENES, require_numba_cuda, run_script

PTX_SCRIPT = SCENES + """
import json, os, re, subprocess, tempfile
from types import SimpleNamespace
import numba.cuda.dispatcher as dispatcher
from numba import cuda
from numba.cuda.typing.typeof import typeof

CC = (9, 0)
# numba-cuda compiles the @njit routines a kernel calls for the current device's compute
# capability; there is no device here, so name one.
assert hasattr(dispatcher, "get_current_device"), "numba-cuda internals changed"
dispatcher.get_current_device = lambda: SimpleNamespace(compute_capability=CC)
import cloudct.mc.cuda_kernels as ck
from cloudct.mc.forward import NFLUX
from cloudct.mc.pixel_sampling import residual_table
from cloudct.mc.estimate import kernel_inputs

k = kernel_inputs(medium, scenes["open"])
scene = ck.DeviceScene(k.grid, k.bank, k.cams, k.copies, k.sun)
scalars = (k.periodic, k.ground, 100, 0.95, 0, 10)
images, events, d = np.zeros((4, 2, 6, 6)), np.zeros(4, np.int64), np.zeros((1, 1, 1))
gradients, residual = np.zeros((4, 4, 4, 4)), np.zeros((2, 6, 6))
path_sum, vertices = np.zeros(8), np.zeros(8, np.int64)
cases = {
    "forward_render_kernel": (scene, *scalars, 0, 2, (images, events, d, d)),
    "forward_residual_kernel": (scene, *scalars, 0, 2, 4,
                                (residual, events, path_sum, vertices, d, d)),
    "forward_gradient_kernel": (scene, *scalars, 0, 2, 2, (residual, gradients, path_sum,
                                                        vertices, d)),
    "forward_sensor_kernel": (scene, *scalars, 0, 2, (images, events, np.zeros((4, 1, 1, NFLUX)),
                                                      d)),
    "backward_kernel": (scene, *scalars, 0, 2, (images, events)),
}
# the camera-side gradients, one kernel per estimator (pixels drawn from an alias table)
camera_side = (scene, *scalars, 0, 2, 2, False, True,
               (residual, residual_table(residual + 1.0), gradients, events))
for name in ("drt_gradient_kernel", "sample_matching_gradient_kernel",
             "backward_score_gradient_kernel"):
    cases[name] = camera_side
kernels = dict.fromkeys(cases, ck)

# the replay kernels of path recycling, on a store's arrays
import cloudct.recycling.cuda_replay as cr
from cloudct.recycling import record_paths

store = record_paths(medium, scenes["open"], photons=8, batches=2, seed=3)
beta, order, log_r = np.zeros(64), np.zeros(8, np.int64), np.zeros(8)
scratch = np.zeros(store.records)
replay = (scene, k.periodic, k.ground, 100, 0.95, 4, True, store.arrays, 0, 4)
cases["replay_render_kernel"] = (*replay, (beta, order, images, log_r, events, scratch, d))
cases["replay_gradient_kernel"] = (*replay, (beta, order, residual, gradients, log_r, events,
                                             scratch, d))
cases["log_ratio_kernel"] = (scene, k.periodic, 4, True, store.arrays, 0, 4,
                             (beta, order, log_r))
kernels.update(dict.fromkeys(["replay_render_kernel", "replay_gradient_kernel",
                              "log_ratio_kernel"], cr))


EXTERN_FUNCTION = r"\\.extern\\s+\\.func\\s+(?:\\([^)]*\\)\\s*)?(\\w+)"
import nvidia.cuda_nvcc
ptxas = os.path.join(list(nvidia.cuda_nvcc.__path__)[0], "bin", "ptxas")
out = {}
with tempfile.TemporaryDirectory() as tmp:
    for name, args in cases.items():
        ptx, _ = cuda.compile_ptx(getattr(kernels[name], name).py_func,
                                  tuple(typeof(a) for a in args), cc=CC)
        path = os.path.join(tmp, name + ".ptx")
        with open(path, "w") as f:
            f.write(ptx)
        asm = subprocess.run([ptxas, "-arch=sm_90", "-v", path, "-o", path + ".cubin"],
                             capture_output=True, text=True)
        rc, log = asm.returncode, asm.stderr
        out[name] = {
            # functions declared but not defined: numba-cuda would link a helper for them
            # (e.g. numba_attempt_nocopy_reshape for array.reshape), and cannot cache such a
            # kernel on disk ("Cannot pickle CUDACodeLibrary with linking files")
            "extern_functions": re.findall(EXTERN_FUNCTION, ptx),
            "atomics": sorted({w for w in ptx.split() if w.startswith("atom.")}),
            "ptxas_rc": rc,
            "ptxas": [l for l in log.splitlines() if "registers" in l or "rror" in l
                      or "spill" in l],
        }
print("RESULT " + json.dumps(out))
"""


def test_kernels_compile_for_a_gpu():
    """Every kernel, the replay kernels of path recycling included, compiles to PTX (sm_90)
    and assembles, with atomic float64 additions where it writes shared images or gradients
    (``add_to``'s CUDA implementation), and calls no function that numba-cuda would link at
    launch: a kernel with linked files cannot be cached on disk (found on an H100,
    2026-11-26: the recycled gradient's reshape made every replay fail to save)."""
    require_numba_cuda()
    if importlib.util.find_spec("nvidia.cuda_nvcc") is None:
        pytest.fail("NVVM/ptxas not found: install numba-cuda[cu12] (the test extra)",
                    pytrace=False)
    result = run_script(PTX_SCRIPT, simulator=False, timeout=1800.0)
    for name, info in result.items():
        assert not info["extern_functions"], (
            f"{name} calls {info['extern_functions']}, which numba-cuda links at launch: such a "
            "kernel cannot be cached on disk (use index arithmetic, as add_along does, not "
            "array.reshape)")
        assert info["ptxas_rc"] == 0, f"{name}: ptxas failed: {info['ptxas']}"
    for name in ("forward_render_kernel", "forward_gradient_kernel", "backward_kernel",
                 "drt_gradient_kernel", "sample_matching_gradient_kernel",
                 "backward_score_gradient_kernel", "replay_render_kernel",
                 "replay_gradient_kernel"):
        assert "atom.global.add.f64" in result[name]["atomics"], result[name]
    assert "atom.global.add.f64" not in result["forward_residual_kernel"]["atomics"]
    assert not result["log_ratio_kernel"]["atomics"]
