"""What a render, a gradient and a path store cost against the voxel count and the photons.

Media: from the LES cloud field ``rico122x106x39`` (20 m x 20 m x 40 m cells, all 39
levels) with the single cloud's optics (HG g = 0.85, cloud albedo 0.99, the file's air):

- 10^4 voxels: the 16 x 16 columns around the field's column of largest liquid water path;
- 10^5 and 10^6 voxels: that piece tiled 3 x 3 and 10 x 10 times (48 x 48 and 160 x 160
  columns), so that the cloud fraction, and the paths, stay those of the 10^4 piece and
  the cost per photon shows what grows with the grid alone;
- the whole field (122 x 106 columns, 5 x 10^5 voxels, 3% cloudy): a real field's mix;
- ``256x256x100`` (6.6 x 10^6 voxels, a research LES domain's size): the piece tiled
  16 x 16 and **upsampled** in z from 39 levels of 40 m to 100 of 15.6 m (each new level
  takes the nearest LES level: the same cloud, column optical depths within a few percent,
  the largest 22.8 -> 22.3).

Scene: nine 76 x 76 cameras (zenith and a ring at 29 degrees) aimed at the box centre from
max(2 km, 1.5 x the box's horizontal diagonal), the field of view fitted to the box, sun at
the zenith, open boundaries. Each case runs in its own process, so that its peak resident
memory (``ru_maxrss``) is its own; the JIT compilation (or the cache load) is excluded from
the times by a warm-up call. Reported per case: the forward render's wall time, photons and
path vertices per second; the score-function gradient's wall time (random residual, every
pixel non-zero); the bytes of a path store (``record_paths``, default storage) per path and
per event; the peak memory. ``--photon-scan``: the render's time against the photons on the
10^5-voxel piece. ``--backend cuda``: render and gradients on the GPU (no path store, which
is recorded on the CPU; the GPU's peak memory is read outside, e.g. by nvidia-smi).
``--sample-matching``: also the sample-matching gradient (the retrieval's default estimator;
as many paths as the score function's photons, pixels drawn from the residual). Usage::

    python -m benchmarks scale.cost_tables [--photons 200000] [--photon-scan] [--backend cuda]
        [--sizes 1e4 1e5 1e6 field 256x256x100] [--sample-matching]
        [--output benchmarks/results/cost_tables]
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import numpy as np

from benchmarks.common import (
    REPO,
    RESULTS,
    markdown_table,
    run_header,
    write_result,
)

#: case: (tiles of the 16 x 16-column piece per side, levels or None for the LES's) or
#: None for the whole field
SIZES = {"1e4": (1, None), "1e5": (3, None), "1e6": (10, None), "field": None,
         "256x256x100": (16, 100)}
#: the cases of the table by default
DEFAULT_SIZES = ("1e4", "1e5", "1e6", "field")
PIECE = 16


def field_piece(size: str):
    """The medium of one case (module documentation)."""
    import xarray as xr

    from benchmarks.scenes import cloud_optics
    from cloudct.les import bundled_cloud_field

    les = bundled_cloud_field()  # the bundled copy of rico122x106x39
    if SIZES[size] is not None:
        tiles, levels = SIZES[size]
        lwp = les["lwc"].sum("z").values
        i, j = np.unravel_index(int(np.argmax(lwp)), lwp.shape)
        i0 = int(np.clip(i - PIECE // 2, 0, les.sizes["x"] - PIECE))
        j0 = int(np.clip(j - PIECE // 2, 0, les.sizes["y"] - PIECE))
        piece = les.isel(x=slice(i0, i0 + PIECE), y=slice(j0, j0 + PIECE))
        dx = float(les.x[1] - les.x[0])
        dy = float(les.y[1] - les.y[0])
        n = PIECE * tiles
        les = xr.Dataset(
            {name: (piece[name].dims, np.tile(piece[name].values, (tiles, tiles, 1)),
                    piece[name].attrs)
             for name in piece.data_vars if piece[name].dims == ("x", "y", "z")},
            coords={"x": ("x", float(piece.x[0]) + dx * np.arange(n), piece.x.attrs),
                    "y": ("y", float(piece.y[0]) + dy * np.arange(n), piece.y.attrs),
                    "z": piece.z},
            attrs=piece.attrs,
        )
        for name in piece.data_vars:
            if name not in les:
                les[name] = piece[name]
        if levels is not None:  # the same bottom and top, thinner levels
            z = les.z.values
            dz = (z[-1] - z[0]) / (len(z) - 1)
            centres = z[0] - dz / 2 + (np.arange(levels) + 0.5) * dz * len(z) / levels
            les = les.sel(z=centres, method="nearest").assign_coords(
                z=("z", centres, piece.z.attrs))
    return cloud_optics(les, f"rico122x106x39 piece {size}")


def scene_for(medium):
    from cloudct.mc.cameras import nine_camera_set
    from cloudct.mc.scene import Scene
    from cloudct.mc.sun import Sun
    from cloudct.medium import cell_edges

    edges = cell_edges(medium)
    lo = np.array([e[0] for e in edges])
    hi = np.array([e[-1] for e in edges])
    distance = max(2.0, 1.5 * float(np.hypot(*(hi - lo)[:2])))
    return Scene(nine_camera_set(lo, hi, distance=distance), Sun(0.0, 0.0), "open")


def run_case(size: str, photons: int, gradient: bool, store: bool, backend: str = "cpu",
             sample_matching: bool = False) -> dict:
    """One case, in this process."""
    from cloudct.mc.gradient import gradient_estimate, score_function_gradient
    from cloudct.mc.render import render_batches
    from cloudct.recycling import record_paths

    medium = field_piece(size)
    scene = scene_for(medium)
    shape = medium["cloud_extinction"].shape
    out = {"size": size, "shape": list(shape), "voxels": int(np.prod(shape)),
           "cloudy_voxels": int((medium["cloud_extinction"].values > 0).sum()),
           "photons": photons, "backend": backend}
    render_batches(medium, scene, photons=64, progress=False, backend=backend)  # JIT warm-up
    _, info = render_batches(medium, scene, photons=photons, progress=False, backend=backend)
    out.update(render_s=info["wall_time"], photons_per_s=info["photons"] / info["wall_time"],
               vertices_per_photon=info["events"] / info["photons"],
               vertices_per_s=info["events"] / info["wall_time"])
    residual = np.random.default_rng(0).normal(size=(9, 76, 76))
    if gradient:
        kw = dict(progress=False, backend=backend)
        score_function_gradient(medium, scene, residual, photons=64, **kw)
        t = time.perf_counter()
        score_function_gradient(medium, scene, residual, photons=photons // 2, **kw)
        out["gradient_s_per_photon"] = (time.perf_counter() - t) / (photons // 2)
    if sample_matching:
        kw = dict(estimator="sm", pixel_sampling="residual", progress=False, backend=backend)
        # JIT warm-up: one pixel, since every drawn pixel gets a path per batch at least
        one_pixel = np.zeros_like(residual)
        one_pixel[0, 38, 38] = 1.0
        gradient_estimate(medium, scene, one_pixel, photons=64, **kw)
        t = time.perf_counter()
        _, _, sm = gradient_estimate(medium, scene, residual, photons=photons // 2, **kw)
        out["sm_gradient_s_per_path"] = (time.perf_counter() - t) / sm["photons"]
    if store:
        paths = max(photons // 10, 320)
        s = record_paths(medium, scene, photons=paths)
        out.update(store_bytes=s.nbytes, store_storage=s.storage,
                   store_bytes_per_path=s.nbytes / s.paths, store_bytes_per_event=s.bytes_per_event)
    out["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    return out


def in_subprocess(size: str, photons: int, gradient: bool, store: bool, backend: str = "cpu",
                  sample_matching: bool = False) -> dict:
    call = f"{size!r}, {photons}, {gradient}, {store}, {backend!r}, {sample_matching}"
    code = ("import json; import benchmarks.scale.cost_tables as c; "
            f"print('RESULT', json.dumps(c.run_case({call})))")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          cwd=REPO)
    if proc.returncode != 0:
        raise RuntimeError(f"case {size} failed:\n{proc.stderr}")
    line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")][-1]
    return json.loads(line[len("RESULT "):])


def markdown(result: dict) -> str:
    cases = result["voxels"]
    columns = {
        "voxels": lambda c: c["size"],
        "grid": lambda c: "x".join(map(str, c["shape"])),
        "cloudy": lambda c: str(c["cloudy_voxels"]),
        "render s": lambda c: f"{c['render_s']:.1f}",
        "photons/s": lambda c: f"{c['photons_per_s']:.3g}",
        "vertices/photon": lambda c: f"{c['vertices_per_photon']:.1f}",
        "vertices/s": lambda c: f"{c['vertices_per_s']:.3g}",
        "gradient us/photon": lambda c: f"{1e6 * c['gradient_s_per_photon']:.2f}",
    }
    if all("sm_gradient_s_per_path" in c for c in cases):
        columns["sm gradient us/path"] = lambda c: f"{1e6 * c['sm_gradient_s_per_path']:.2f}"
    if all("store_bytes" in c for c in cases):
        columns["store MiB"] = lambda c: f"{c['store_bytes'] / 2**20:.1f} ({c['store_storage']})"
        columns["store B/event"] = lambda c: f"{c['store_bytes_per_event']:.0f}"
    columns["peak RSS MiB"] = lambda c: f"{c['peak_rss_mib']:.0f}"
    stored = ", a tenth recorded in the path store" if "store MiB" in columns else ""
    lines = [f"{result['photons']} photons per render (32 batches), half as many per "
             f"gradient{stored}; back end {result.get('device', result.get('backend', 'cpu'))}.",
             ""]
    lines += markdown_table(list(columns), [[f(c) for f in columns.values()] for c in cases])
    if result.get("photon_scan"):
        lines += ["", "Render time against photons (10^5 voxels):", ""]
        lines += markdown_table(["photons", "render s", "photons/s"],
                                [[str(c["photons"]), f"{c['render_s']:.2f}",
                                  f"{c['photons_per_s']:.3g}"] for c in result["photon_scan"]])
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--photons", type=int, default=200_000)
    parser.add_argument("--photon-scan", action="store_true")
    parser.add_argument("--backend", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--sizes", nargs="+", choices=list(SIZES), default=list(DEFAULT_SIZES))
    parser.add_argument("--sample-matching", action="store_true")
    parser.add_argument("--output", default=str(RESULTS / "cost_tables"))
    args = parser.parse_args()
    store = args.backend == "cpu"
    result = {**run_header(args), "photons": args.photons, "backend": args.backend, "voxels": []}
    if args.backend == "cuda":
        from benchmarks.gpu.forward import device_name

        result["device"] = device_name("cuda")
    for size in args.sizes:
        case = in_subprocess(size, args.photons, True, store, args.backend, args.sample_matching)
        print(case, flush=True)
        result["voxels"].append(case)
        write_result(result, args.output, markdown)  # what is done, if cut off
    if args.photon_scan:
        result["photon_scan"] = [in_subprocess("1e5", p, False, False, args.backend)
                                 for p in (50_000, 200_000, 800_000)]
    write_result(result, args.output, markdown)


if __name__ == "__main__":
    main()
