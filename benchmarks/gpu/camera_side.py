"""GPU benchmark: the camera-side gradient kernels against the render, by occupancy, and a
target for Nsight Compute (issue 52, item 3).

Scene: the seed paper's single cloud (bundled 32x37x26, nine 76x76 views, sun at zenith),
a random normal residual on every pixel, as ``gpu.engine``. Kernels: the forward render
(``forward_render_kernel``) and the camera-side gradients at the retrieval's settings:
DRT, sample matching (one probe per segment, linear variant, free-flight MIS) and the
backward score function, each sample of each pixel of each batch on its own thread
(pixel-fastest, uniform pixel sampling). Each launch traces ``--batches`` x pixels paths
(the render as many photons).

For each kernel, each register cap in ``--max-registers`` (0: the compiler's own choice,
the kernel as cloudct runs it, loaded from the kernel cache; a cap recompiles it with
``maxrregcount``) and each block size in ``--threads-per-block``: registers and local
memory (spills) per thread, the resident warps per multiprocessor that the registers allow
(the occupancy bound), the compile time of a capped variant, and paths per second (the
minimum over ``--repeats`` of ``--launches`` launches, synchronised; outputs stay on the
device). The GPU-to-render ratio of each kernel's paths/s is the figure issue 52 asks
about: on 2 cores sample matching traces 6x the render's paths/s, on an H100 1x.

Static, without a GPU (``--static``): the same kernels compiled to PTX for sm_90 and
assembled by ptxas (``-v``): registers (and the resident warps per multiprocessor they
allow in blocks of 128 threads), stack frame, spills; with ``--nvdisasm PATH`` also the SASS
instructions and their atomic and local-memory instructions. These say what a profile
cannot be blamed on, not how fast a kernel runs.

Per-path work on the CPU (``--warp-work``, no GPU): every path of ``--warps`` warps of 32
consecutive threads (render: photons; camera-side: 32 neighbouring pixels, in the kernels'
pixel-fastest order, warps at random places in the images) timed alone on one CPU thread
(the least of 3 runs). A warp runs until its longest lane ends: sum of lane times / (32 x
sum of warps' longest) is the share of lanes a kernel keeps busy if nothing else diverged
(an upper bound of its SIMT efficiency); also the mean time per path and the share of
paths with a scattering vertex (most camera paths of the single cloud's views see no
cloud).

``--ncu-target``: run each kernel once (after a warm-up launch), for Nsight Compute to
profile; ``--lineinfo`` compiles them with line information, so that ncu's source page maps
stalls to the Python lines of ``cloudct.mc``. docs/gpu.md, "Issue 52 on a lent GPU", has the
whole session's commands.

Usage::

    python -m benchmarks gpu.camera_side [--max-registers 0 168 128]
        [--threads-per-block 64 128 256] [--output benchmarks/results/gpu_camera_side]
    python -m benchmarks gpu.camera_side --static [--nvdisasm PATH]
    python -m benchmarks gpu.camera_side --ncu-target [--lineinfo]
    python -m benchmarks gpu.camera_side --warp-work [--warps 200]

Exits with a message (status 2) where there is no GPU, but for ``--static`` and
``--warp-work``.
"""

from __future__ import annotations

import argparse
import math
import os
import re
import subprocess
import sys
import tempfile
import time
from types import SimpleNamespace

import numpy as np
from numba import njit, objmode

from benchmarks.common import RESULTS, markdown_table, run_header, write_result
from cloudct.mc.camera_gradient import DRT, SAMPLE_MATCHING, SCORE, gradient_sample
from cloudct.mc.forward import RENDER, trace_photon

#: The kernels, by the name of the estimator they serve.
KERNELS = {"render": "forward_render_kernel", "drt": "drt_gradient_kernel",
           "sm": "sample_matching_gradient_kernel", "score": "backward_score_gradient_kernel"}
#: Each camera-side kernel's estimator code and (probes, quadratic, mis): sample matching's
#: as the retrieval runs it (cloudct.mc.gradient.sample_matching_gradient), the others unused.
CAMERA_SIDE = {"drt": (DRT, (1, False, False)), "sm": (SAMPLE_MATCHING, (1, False, True)),
               "score": (SCORE, (1, False, False))}
#: Russian roulette as in every estimator's default.
RR_DEPTH, RR_SURVIVAL = 100, 0.95
#: The compute capability the static part compiles for (H100, H200).
STATIC_CC = (9, 0)


def single_cloud() -> tuple:
    """The single-cloud medium and scene, and a random residual on every pixel."""
    from cloudct.mc.render import single_cloud_medium
    from cloudct.mc.scene import single_cloud_scene_of

    medium = single_cloud_medium()
    scene = single_cloud_scene_of(medium)
    shape = (len(scene.cameras), scene.cameras[0].nrows, scene.cameras[0].ncols)
    return medium, scene, np.random.default_rng(1).normal(size=shape)


def launchers(name: str, nbatch: int, seed: int = 0):
    """``(launcher, threads, launch(kernel, tpb))`` for kernel ``name``: a cloudct launcher on
    the single cloud and a function that launches one batch-wide round of ``kernel`` (the
    named kernel or a variant of it) with its arguments."""
    import cloudct.mc.cuda_kernels as ck
    from cloudct.mc.estimate import kernel_inputs
    from cloudct.mc.pixel_sampling import pixel_table

    medium, scene, residual = single_cloud()
    npix = residual.size
    if name == "render":
        k = kernel_inputs(medium, scene)
        images = np.zeros((nbatch, *residual.shape))
        launcher = ck.ForwardLauncher(k, RR_DEPTH, RR_SURVIVAL, seed, npix, RENDER, images,
                                      None, None, np.zeros(nbatch, np.int64))

        def launch(kernel, tpb: int) -> None:
            ck.launch_kernel(kernel, nbatch * npix, tpb, launcher.scene, *launcher.scalars,
                             0, npix, (launcher.images, launcher.events, launcher.dummy,
                                       launcher.dummy))

        return launcher, nbatch * npix, launch
    estimator, options = CAMERA_SIDE[name]
    k = kernel_inputs(medium, scene, aim_fraction=0.0)  # as the camera-side estimators
    launcher = ck.CameraGradientLauncher(
        k, RR_DEPTH, RR_SURVIVAL, seed, 1, estimator, *options, residual,
        pixel_table(residual, "uniform"), np.zeros((nbatch, *k.grid.albedo.shape[1:])),
        np.zeros(nbatch, np.int64))

    def launch(kernel, tpb: int) -> None:
        launcher.kernel, launcher.tpb = kernel, tpb
        launcher.launch(0, 1)

    return launcher, launcher.width, launch


def variant(name: str, max_registers: int, lineinfo: bool = False):
    """Kernel ``name`` as cloudct compiles it (``max_registers`` 0, no line information), or
    a new dispatcher of the same function with a register cap and/or line information."""
    from numba import cuda

    import cloudct.mc.cuda_kernels as ck

    kernel = getattr(ck, KERNELS[name])
    options = {key: value for key, value in (("max_registers", max_registers),
                                             ("lineinfo", lineinfo)) if value}
    return cuda.jit(**options)(kernel.py_func) if options else kernel


def occupancy_warps(registers: int, tpb: int, register_file: int = 65536,
                    max_threads: int = 2048) -> int:
    """Resident warps per multiprocessor that ``registers`` per thread allow in blocks of
    ``tpb`` threads (registers allocated per warp in units of 256), on a multiprocessor of
    ``register_file`` registers and ``max_threads`` threads (the defaults: sm_90's)."""
    per_warp = math.ceil(registers * 32 / 256) * 256
    warps_per_block = math.ceil(tpb / 32)
    blocks = register_file // (per_warp * warps_per_block)
    return min(blocks * warps_per_block, max_threads // 32)


def measure(name: str, args: argparse.Namespace) -> list[dict]:
    """Rows of the table of kernel ``name``: every register cap and block size."""
    from numba import cuda

    device = cuda.get_current_device()
    limits = (device.MAX_REGISTERS_PER_MULTIPROCESSOR, device.MAX_THREADS_PER_MULTIPROCESSOR)
    launcher, threads, launch = launchers(name, args.batches)
    rows = []
    for cap in args.max_registers:
        kernel = variant(name, cap)
        start = time.perf_counter()
        launch(kernel, args.threads_per_block[0])  # compiles (or loads) the kernel
        cuda.synchronize()
        first = time.perf_counter() - start
        # per signature (one, after the launch), unless the dispatcher is specialised
        registers, local = (next(iter(v.values())) if isinstance(v, dict) else v
                            for v in (kernel.get_regs_per_thread(),
                                      kernel.get_local_mem_per_thread()))
        for tpb in args.threads_per_block:
            seconds = []
            for _ in range(args.repeats):
                start = time.perf_counter()
                for _ in range(args.launches):
                    launch(kernel, tpb)
                cuda.synchronize()
                seconds.append(time.perf_counter() - start)
            best = min(seconds)
            rows.append({
                "kernel": name, "max_registers": cap, "threads_per_block": tpb,
                "registers": registers, "local_bytes": local,
                "warps_per_sm": occupancy_warps(registers, tpb, *limits), "first_launch_s": first,
                "seconds": best, "paths_per_s": threads * args.launches / best,
            })
            print(rows[-1], flush=True)
    launcher.finish()  # the outputs back to the host, as a run ends
    return rows


def ncu_target(args: argparse.Namespace) -> None:
    """One launch of each kernel after a warm-up launch (``--lineinfo``: recompiled with
    line information), for ``ncu --launch-skip`` to pick the second."""
    from numba import cuda

    for name in args.kernels:
        _, _, launch = launchers(name, args.batches)
        kernel = variant(name, 0, args.lineinfo)
        for _ in range(2):
            launch(kernel, args.threads_per_block[0])
            cuda.synchronize()


#: The SASS instruction classes counted by ``--static --nvdisasm``.
SASS_CLASSES = {"atomic (RED)": r"\bREDG?\.", "atomic with return (ATOM)": r"\bATOMG?\.",
                "local memory (LDL/STL)": r"\b(LDL|STL)\b", "calls": r"\bCALL\.",
                "f64 divisions (subroutine calls)": r"div_rn_f64"}


def static_resources(args: argparse.Namespace) -> list[dict]:
    """Registers, stack and spills (ptxas -v) of each kernel compiled for sm_90 without a
    GPU; SASS instruction counts with ``--nvdisasm``."""
    import numba.cuda.dispatcher as dispatcher
    from numba import cuda
    from numba.cuda.typing.typeof import typeof

    # numba-cuda compiles the routines a kernel calls for the current device: name one
    dispatcher.get_current_device = lambda: SimpleNamespace(compute_capability=STATIC_CC)
    import nvidia.cuda_nvcc

    ptxas = os.path.join(list(nvidia.cuda_nvcc.__path__)[0], "bin", "ptxas")
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.kernels:
            arguments = static_arguments(name, args.batches)
            ptx, _ = cuda.compile_ptx(variant(name, 0).py_func,
                                      tuple(typeof(a) for a in arguments),
                                      cc=STATIC_CC)
            path = os.path.join(tmp, name)
            with open(path + ".ptx", "w") as f:
                f.write(ptx)
            log = subprocess.run([ptxas, f"-arch=sm_{STATIC_CC[0]}{STATIC_CC[1]}", "-v",
                                  path + ".ptx", "-o", path + ".cubin"], capture_output=True,
                                 text=True, check=True).stderr
            usage = re.search(r"Used (\d+) registers", log)
            frame = re.search(r"(\d+) bytes stack frame, (\d+) bytes spill stores, "
                              r"(\d+) bytes spill loads", log)
            registers = int(usage.group(1))
            row = {"kernel": name, "ptx_lines": ptx.count("\n"), "registers": registers,
                   "warps_per_sm_at_128": occupancy_warps(registers, 128),
                   "stack_frame_bytes": int(frame.group(1)),
                   "spill_store_bytes": int(frame.group(2)),
                   "spill_load_bytes": int(frame.group(3))}
            if args.nvdisasm:
                sass = subprocess.run([args.nvdisasm, "-c", path + ".cubin"],
                                      capture_output=True, text=True, check=True).stdout
                row["sass_instructions"] = len(re.findall(r"/\*[0-9a-f]{4,}\*/\s+\S", sass))
                for label, pattern in SASS_CLASSES.items():
                    row[label] = len(re.findall(pattern, sass))
            rows.append(row)
            print(row, flush=True)
    return rows


def static_arguments(name: str, nbatch: int) -> tuple:
    """The arguments of kernel ``name`` on the single cloud as host arrays (of the types a
    run passes)."""
    from cloudct.mc.cuda_kernels import DeviceScene
    from cloudct.mc.estimate import kernel_inputs
    from cloudct.mc.pixel_sampling import pixel_table

    medium, scene, residual = single_cloud()
    k = kernel_inputs(medium, scene, aim_fraction=None if name == "render" else 0.0)
    device = DeviceScene(k.grid, k.bank, k.cams, k.copies, k.sun)
    scalars = (k.periodic, k.ground, RR_DEPTH, RR_SURVIVAL, 0, 1, 0, 1)
    if name == "render":
        d = np.zeros((1, 1, 1))
        return (device, *scalars, (np.zeros((nbatch, *residual.shape)),
                                   np.zeros(nbatch, np.int64), d, d))
    out = (residual, pixel_table(residual, "uniform"),
           np.zeros((nbatch, *k.grid.albedo.shape[1:])), np.zeros(nbatch, np.int64))
    return (device, *scalars, *CAMERA_SIDE[name][1], out)


@njit
def _clock() -> float:
    with objmode(t="float64"):
        t = time.perf_counter()
    return t


@njit
def _timer_overhead(count, repeats):
    """Median over ``count`` of the least of ``repeats`` timings of nothing: what each
    path's time below includes."""
    out = np.empty(count)
    for i in range(count):
        best = np.inf
        for _ in range(repeats):
            start = _clock()
            best = min(best, _clock() - start)
        out[i] = best
    return np.median(out)


@njit
def _photon_times(k, seed, indices, image, repeats):
    """Seconds (least of ``repeats``) and vertices of each forward photon of ``indices``
    (RENDER)."""
    out = np.empty(indices.size)
    vertices = np.zeros(indices.size, np.int64)
    unused = np.zeros((1, 1, 1))
    for i in range(indices.size):
        best = np.inf
        for _ in range(repeats):
            start = _clock()
            vertices[i] = trace_photon(
                k.grid, k.bank, k.cams, k.copies, k.sun, k.periodic, k.ground, RR_DEPTH,
                RR_SURVIVAL, seed, indices[i], RENDER, image, unused, unused, 0.0)[0]
            best = min(best, _clock() - start)
        out[i] = best
    return out, vertices


@njit
def _sample_times(estimator, k, seed, indices, views, rows, cols, gradient, options, repeats):
    """Seconds (least of ``repeats``) and vertices of each camera-side sample."""
    out = np.empty(indices.size)
    vertices = np.zeros(indices.size, np.int64)
    probes, quadratic, mis = options
    for i in range(indices.size):
        best = np.inf
        for _ in range(repeats):
            start = _clock()
            vertices[i] = gradient_sample(
                estimator, k.grid, k.bank, k.cams, k.sun, k.periodic, k.ground, RR_DEPTH,
                RR_SURVIVAL, seed, indices[i], views[i], rows[i], cols[i], 1.0, gradient,
                probes, quadratic, mis)
            best = min(best, _clock() - start)
        out[i] = best
    return out, vertices


def busy_share(seconds: np.ndarray) -> float:
    """Sum of lane times over 32 x the sum of each warp's longest lane."""
    warps = seconds.reshape(-1, 32)
    return float(warps.sum() / (32 * warps.max(axis=1).sum()))


def warp_work(args: argparse.Namespace) -> list[dict]:
    """The ``--warp-work`` rows: each kernel's time per path, busy share and share of paths
    that scatter."""
    from cloudct.mc.estimate import kernel_inputs

    medium, scene, residual = single_cloud()
    _, nrows, ncols = residual.shape
    repeats = 3
    overhead = _timer_overhead(1000, repeats)
    table = []

    def add_row(name: str, seconds: np.ndarray, vertices: np.ndarray) -> None:
        seconds = np.maximum(seconds - overhead, 0.0)
        table.append({"kernel": name, "us_per_path": float(1e6 * seconds.mean()),
                      "busy_share": busy_share(seconds),
                      "scattering_share": float(np.mean(vertices > 0))})
        print(table[-1], flush=True)

    k = kernel_inputs(medium, scene)
    add_row("render", *_photon_times(k, 0, np.arange(32 * args.warps, dtype=np.int64),
                                     np.zeros(residual.shape), repeats))
    k = kernel_inputs(medium, scene, aim_fraction=0.0)
    start = np.random.default_rng(0).integers(0, residual.size // 32, args.warps) * 32
    pixels = (start[:, None] + np.arange(32)).ravel()
    nbatch = args.batches
    indices = pixels * nbatch  # sample 0 of batch 0 of each pixel (the kernels' index)
    views, rows, cols = pixels // (nrows * ncols), (pixels // ncols) % nrows, pixels % ncols
    gradient = np.zeros(k.grid.albedo.shape[1:])
    for name, (estimator, options) in CAMERA_SIDE.items():
        add_row(name, *_sample_times(estimator, k, 0, indices, views, rows, cols, gradient,
                                     options, repeats))
    return table


def markdown(result: dict) -> str:
    lines = [f"# Camera-side kernels ({result['date']}, {result.get('device', 'no GPU')})", ""]
    for part in ("static", "warp_work"):
        if result.get(part):
            keys = list(result[part][0])
            lines += markdown_table(keys, [[f"{r[k]:.3g}" if isinstance(r[k], float)
                                            else f"{r[k]}" for k in keys]
                                           for r in result[part]])
            lines.append("")
    rows = result.get("rows", [])
    if rows:
        render = {(r["max_registers"], r["threads_per_block"]): r["paths_per_s"]
                  for r in rows if r["kernel"] == "render"}
        lines += markdown_table(
            ["kernel", "register cap", "threads/block", "registers", "local B", "warps/SM",
             "first launch [s]", "paths/s", "/ render (same settings)"],
            [[r["kernel"], f"{r['max_registers'] or '-'}", f"{r['threads_per_block']}",
              f"{r['registers']}", f"{r['local_bytes']}", f"{r['warps_per_sm']}",
              f"{r['first_launch_s']:.1f}", f"{r['paths_per_s']:.3g}",
              (f"{r['paths_per_s'] / render[key]:.2f}"
               if (key := (r["max_registers"], r["threads_per_block"])) in render else "")]
             for r in rows])
    return "\n".join(lines) + "\n"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--kernels", nargs="+", choices=list(KERNELS), default=list(KERNELS))
    parser.add_argument("--max-registers", type=int, nargs="+", default=[0, 168, 128],
                        help="register caps (0: the compiler's choice, cloudct's kernel)")
    parser.add_argument("--threads-per-block", type=int, nargs="+", default=[128, 64, 256])
    parser.add_argument("--batches", type=int, default=8,
                        help="batches per launch: each launch traces batches x pixels paths")
    parser.add_argument("--launches", type=int, default=4)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--static", action="store_true",
                        help="registers, stack, spills (and SASS) for sm_90, without a GPU")
    parser.add_argument("--nvdisasm", help="nvdisasm executable, for --static's SASS counts")
    parser.add_argument("--warp-work", action="store_true",
                        help="each path's time on one CPU thread, by warp (no GPU)")
    parser.add_argument("--warps", type=int, default=200, help="--warp-work: warps timed")
    parser.add_argument("--ncu-target", action="store_true",
                        help="launch each kernel twice and stop, for Nsight Compute")
    parser.add_argument("--lineinfo", action="store_true",
                        help="--ncu-target: compile with line information")
    parser.add_argument("--output", default=str(RESULTS / "gpu_camera_side"),
                        help="output path without suffix (.json and .md are written)")
    args = parser.parse_args()
    result = {**run_header(args)}
    if args.static or args.warp_work:
        if args.static:
            result["static"] = static_resources(args)
        if args.warp_work:
            result["warp_work"] = warp_work(args)
        write_result(result, args.output, markdown)
        return 0

    from cloudct.mc.backend import cuda_unavailable_reason

    reason = cuda_unavailable_reason()
    if reason is not None:
        print(f"gpu.camera_side: no GPU to benchmark: {reason}.", file=sys.stderr)
        return 2
    if args.ncu_target:
        ncu_target(args)
        return 0
    from benchmarks.gpu.forward import device_name

    result["device"] = device_name("cuda")
    result["rows"] = []
    for name in args.kernels:
        result["rows"] += measure(name, args)
        write_result(result, args.output, markdown)  # kept if a time limit stops the run
    return 0


if __name__ == "__main__":
    sys.exit(main())
