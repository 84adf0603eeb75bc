"""Mitsuba 3 peer renderer for cloudct's forward-model benchmark.

Renders exactly cloudct's scene (open box, vacuum outside, black background, sun as a directional
source of irradiance 1, piecewise-constant voxel medium of air + cloud) with Mitsuba 3's ``volpath``
integrator, so that efficiencies and view-mean radiances can be compared. No dependency on cloudct.

Install (Debian 12, CPU/LLVM backend; verified with mitsuba 3.9.1 / drjit 1.5.0, Python 3.11)::

    pip install mitsuba                  # wheel ships llvm_ad_mono, llvm_ad_rgb, ... (no llvm_mono)
    apt-get update && apt-get install -y libllvm19
    python -c "import mitsuba as mi; mi.set_variant('llvm_ad_mono')"

Dr.Jit finds ``/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1`` by itself. Do not use LLVM 15 (Debian's
``libllvm15``): kernels then abort with ``LLVM ERROR: Cannot select: ... fminimum``. If several
LLVMs are installed and the wrong one is picked, set
``DRJIT_LIBLLVM_PATH=/usr/lib/x86_64-linux-gnu/libLLVM-19.so``. Dr.Jit caches compiled kernels in
``~/.drjit``; with a warm cache the first render of a new process skips most of the compilation
(``compile_s`` then measures tracing + cache load only).

Scene mapping (units: km and 1/km throughout, Mitsuba ``scale`` = 1):

* ``cube`` shape, ``to_world`` = translate(box centre) @ scale(half extents), ``null`` BSDF, the
  medium as its ``interior``. No other shape: the open box, rays leaving it are lost.
* ``heterogeneous`` medium: ``sigma_t`` = gridvolume of air + cloud extinction; ``albedo`` =
  gridvolume of (w_a b_a + w_c b_c) / (b_a + b_c); phase = ``blendphase`` with ``phase_0`` =
  ``rayleigh`` and ``phase_1`` = ``hg`` (g = cloud_g), ``weight`` = gridvolume of the cloud's share
  of the scattering coefficient w_c b_c / (w_a b_a + w_c b_c). Mitsuba's convention: weight 0
  selects the first nested phase (names sorted: ``phase_0``), weight 1 the second (``phase_1``).
  All grid volumes use ``filter_type`` 'nearest' (piecewise constant per cell: Dr.Jit's nearest
  texture lookup gives cell i on [i/n, (i+1)/n) of the unit cube) and ``to_world`` =
  translate(box min) @ scale(box extent). Mitsuba's grid data is laid out [z, y, x, channel]; the
  [x, y, z] arrays are transposed accordingly. Edges must be uniform in each axis.
* ``directional`` emitter, ``irradiance`` 1, ``direction`` = -(sin t0 cos p0, sin t0 sin p0,
  cos t0) (p0 = azimuth towards the sun from +x toward +y). Mitsuba's radiance is then in
  cloudct's units (a white Lambertian plate facing the sun reads 1/pi).
* ``volpath``, ``max_depth`` -1 (unlimited), ``rr_depth`` 2**30, i.e. no Russian roulette: paths
  end only by leaving the box (their weight decays as albedo**n). Mitsuba's roulette survives with
  q = min(max(throughput), 0.95) and is applied on every loop iteration (null collisions too):
  unbiased in expectation, but for albedo ~1 it reweights by 0.95**-k, a heavy-tailed estimator
  that in practice truncates long paths. With rr_depth=1000 a tau=100 conservative slab read
  3-4 % low (0.316-0.319; theory 0.330, no roulette 0.332 +- 0.001). Shadow rays use ratio
  tracking against the medium's single global majorant max(sigma_t) (Mitsuba 3 has no majorant
  grid), so the cost grows with the densest voxel, not the mean extinction.
* ``perspective`` sensor, ``fov_axis`` 'x' (fov = full angle across the columns), ``to_world`` =
  look_at(position, lookat, up), ``hdrfilm`` (luminance) with a ``box`` reconstruction filter of
  radius 0.5 px: every sample lands in its own pixel, so a pixel is the area average over the
  pixel on the image plane (cloudct's convention). ``independent`` sampler.

Orientation: Mitsuba's look_at builds the camera frame (left = up x dir, up, dir) and its
perspective camera maps camera-space +x (left) to column 0 and +y (up) to row 0. The Mitsuba
image array [row, col] is therefore already cloudct's [row, col] (row 0 = camera's up side,
col 0 = left when looking along the view direction): no flip is applied. This was verified with
an offset dense blob seen from the zenith, the south and the east
(benchmarks/forward/check_mitsuba_peer.py).

Cameras must lie outside the box (a camera inside would need the sensor's ``medium``).
"""

from __future__ import annotations

import time

import numpy as np

__all__ = ["build_scene", "render_mitsuba", "render_batches", "sun_direction"]

_WARMUP_SPP = 4
_NO_RR = 1 << 30  # rr_depth that in practice disables Russian roulette


def _mitsuba(variant: str, threads: int):
    import drjit as dr
    import mitsuba as mi

    if mi.variant() != variant:
        mi.set_variant(variant)
    dr.set_thread_count(int(threads))
    return mi, dr


def sun_direction(sun_zenith_deg: float, sun_azimuth_deg: float) -> np.ndarray:
    """Unit vector TOWARDS the sun (photons travel along its negative)."""
    t0, p0 = np.deg2rad(sun_zenith_deg), np.deg2rad(sun_azimuth_deg)
    return np.array([np.sin(t0) * np.cos(p0), np.sin(t0) * np.sin(p0), np.cos(t0)])


def _uniform_bounds(edges) -> tuple[float, float, int]:
    e = np.asarray(edges, dtype=np.float64)
    d = np.diff(e)
    if e.ndim != 1 or e.size < 2 or np.any(d <= 0):
        raise ValueError("cell edges must be a strictly increasing 1-D array")
    if not np.allclose(d, d.mean(), rtol=1e-6, atol=0.0):
        raise ValueError("Mitsuba grid volumes need uniform cell spacing")
    return float(e[0]), float(e[-1]), e.size - 1


def _medium_fields(air_ext, cloud_ext, air_albedo, cloud_albedo):
    """Total extinction, effective albedo and the cloud's share of scattering, [nx, ny, nz]."""
    air = np.asarray(air_ext, dtype=np.float64)
    cld = np.asarray(cloud_ext, dtype=np.float64)
    if air.shape != cld.shape or air.ndim != 3:
        raise ValueError("air_extinction and cloud_extinction must both be [nx, ny, nz]")
    if np.any(air < 0) or np.any(cld < 0):
        raise ValueError("extinctions must be non-negative")
    ext = air + cld
    sca_a, sca_c = air_albedo * air, cloud_albedo * cld
    sca = sca_a + sca_c
    albedo = np.divide(sca, ext, out=np.zeros_like(ext), where=ext > 0)
    weight = np.divide(sca_c, sca, out=np.zeros_like(ext), where=sca > 0)
    return ext, albedo, weight


def build_scene(x_edges, y_edges, z_edges, air_extinction, cloud_extinction,
                air_albedo: float, cloud_albedo: float, cloud_g: float,
                sun_zenith_deg: float, sun_azimuth_deg: float, cameras: list[dict],
                max_depth: int = -1, rr_depth: int = _NO_RR, variant: str = "llvm_ad_mono",
                threads: int = 2):
    """Build the Mitsuba scene (one sensor per camera). Returns ``mi.Scene``."""
    mi, _ = _mitsuba(variant, threads)
    x0, x1, nx = _uniform_bounds(x_edges)
    y0, y1, ny = _uniform_bounds(y_edges)
    z0, z1, nz = _uniform_bounds(z_edges)
    ext, albedo, weight = _medium_fields(air_extinction, cloud_extinction, air_albedo,
                                         cloud_albedo)
    if ext.shape != (nx, ny, nz):
        raise ValueError(f"field shape {ext.shape} does not match the edges {(nx, ny, nz)}")
    if not -1.0 < cloud_g < 1.0:
        raise ValueError("cloud_g must lie in (-1, 1)")

    lo = np.array([x0, y0, z0])
    hi = np.array([x1, y1, z1])
    T = mi.ScalarTransform4f
    grid_to_world = T().translate(lo.tolist()) @ T().scale((hi - lo).tolist())

    def gridvolume(a):
        # Mitsuba's VolumeGrid data is [z, y, x, channel].
        data = np.ascontiguousarray(np.transpose(a, (2, 1, 0))[..., None], dtype=np.float32)
        return {"type": "gridvolume", "grid": mi.VolumeGrid(data), "filter_type": "nearest",
                "to_world": grid_to_world}

    medium = {
        "type": "heterogeneous",
        "sigma_t": gridvolume(ext),
        "albedo": gridvolume(albedo),
        "scale": 1.0,
        "phase": {
            "type": "blendphase",
            "weight": gridvolume(weight),  # 0 -> phase_0 (air), 1 -> phase_1 (cloud)
            "phase_0": {"type": "rayleigh"},
            "phase_1": {"type": "hg", "g": float(cloud_g)},
        },
    }
    scene = {
        "type": "scene",
        "integrator": {"type": "volpath", "max_depth": int(max_depth), "rr_depth": int(rr_depth)},
        "sun": {"type": "directional", "irradiance": 1.0,
                "direction": (-sun_direction(sun_zenith_deg, sun_azimuth_deg)).tolist()},
        "box": {"type": "cube",
                "to_world": T().translate(((lo + hi) / 2).tolist()) @ T().scale(((hi - lo) / 2)
                                                                                 .tolist()),
                "bsdf": {"type": "null"}, "interior": medium},
    }
    for i, cam in enumerate(cameras):
        scene[f"cam{i:04d}"] = {
            "type": "perspective",
            "fov_axis": "x",
            "fov": float(cam["fov_deg"]),
            "to_world": T().look_at(origin=np.asarray(cam["position"], float).tolist(),
                                    target=np.asarray(cam["lookat"], float).tolist(),
                                    up=np.asarray(cam["up"], float).tolist()),
            "sampler": {"type": "independent", "sample_count": 1},
            "film": {"type": "hdrfilm", "width": int(cam["ncols"]), "height": int(cam["nrows"]),
                     "rfilter": {"type": "box"}, "pixel_format": "luminance",
                     "sample_border": False},
        }
    return mi.load_dict(scene)


def _pass_spp(spp: int, npix: int, max_lanes: int) -> int:
    """Largest divisor of spp with npix * pass_spp <= max_lanes (at least 1)."""
    best = 1
    for d in range(1, spp + 1):
        if spp % d == 0 and d * npix <= max_lanes:
            best = d
    return best


class _Renderer:
    """Renders views of a built scene; seeds are drawn from one counter (independent streams)."""

    def __init__(self, scene, cameras, seed, mi, max_lanes):
        self.scene, self.cameras, self.mi, self.max_lanes = scene, cameras, mi, max_lanes
        self.base = (int(seed) * 1_000_003) & 0xFFFFFFFF
        self.counter = 0

    def _next_seed(self) -> int:
        self.counter += 1
        return (self.base + self.counter) & 0xFFFFFFFF

    def render_view(self, view: int, spp: int) -> np.ndarray:
        cam = self.cameras[view]
        pspp = _pass_spp(spp, int(cam["nrows"]) * int(cam["ncols"]), self.max_lanes)
        acc = np.zeros((int(cam["nrows"]), int(cam["ncols"])))
        for _ in range(spp // pspp):
            img = self.mi.render(self.scene, sensor=view, spp=pspp, seed=self._next_seed())
            acc += np.asarray(img, dtype=np.float64).reshape(acc.shape)
        return acc / (spp // pspp)

    def render_all(self, spp: int):
        imgs = [self.render_view(v, spp) for v in range(len(self.cameras))]
        return _stack(imgs)

    def warmup(self) -> tuple[float, float]:
        """Time the first render (JIT + render) and an identical second one (render only)."""
        t = []
        for _ in range(2):
            t0 = time.perf_counter()
            self.render_view(0, _WARMUP_SPP)
            t.append(time.perf_counter() - t0)
        return t[0], t[1]


def _stack(imgs):
    shapes = {im.shape for im in imgs}
    return np.stack(imgs) if len(shapes) == 1 else imgs


def render_mitsuba(x_edges, y_edges, z_edges, air_extinction, cloud_extinction,
                   air_albedo: float, cloud_albedo: float, cloud_g: float,
                   sun_zenith_deg: float, sun_azimuth_deg: float, cameras: list[dict],
                   spp: int, seed: int = 0, threads: int = 2, variant: str = "llvm_ad_mono",
                   max_depth: int = -1, rr_depth: int = _NO_RR, max_lanes: int = 1 << 22) -> dict:
    """Render every camera with ``spp`` samples per pixel.

    Returns a dict:

    * ``images``: float64[nview, nrows, ncols] (a list if the views differ in size);
    * ``spp``, ``threads``, ``variant``; ``build_s``: scene construction;
    * ``first_render_s``: first render of the scene (a 4-spp render of view 0, plus the JIT
      compilation if this process has not compiled the kernel yet); ``second_render_s``: the same
      render again; ``compile_s`` = first - second, the JIT overhead;
    * ``render_s``: all views at ``spp`` (pure render, wall clock); ``render_cpu_s``: process CPU
      time of the same (all threads).

    The warm-up renders are not part of the images. ``max_lanes`` bounds the wavefront (pixels x
    spp per ``mi.render`` call); larger spp is split into passes with independent seeds.
    """
    mi, _ = _mitsuba(variant, threads)
    t0 = time.perf_counter()
    scene = build_scene(x_edges, y_edges, z_edges, air_extinction, cloud_extinction, air_albedo,
                        cloud_albedo, cloud_g, sun_zenith_deg, sun_azimuth_deg, cameras,
                        max_depth=max_depth, rr_depth=rr_depth, variant=variant, threads=threads)
    build_s = time.perf_counter() - t0
    r = _Renderer(scene, cameras, seed, mi, max_lanes)
    first, second = r.warmup()
    t0, c0 = time.perf_counter(), time.process_time()
    images = r.render_all(int(spp))
    render_s, render_cpu_s = time.perf_counter() - t0, time.process_time() - c0
    return {"images": images, "spp": int(spp), "build_s": build_s, "first_render_s": first,
            "second_render_s": second, "compile_s": max(first - second, 0.0),
            "render_s": render_s, "render_cpu_s": render_cpu_s, "threads": int(threads),
            "variant": variant}


def render_batches(x_edges, y_edges, z_edges, air_extinction, cloud_extinction,
                   air_albedo: float, cloud_albedo: float, cloud_g: float,
                   sun_zenith_deg: float, sun_azimuth_deg: float, cameras: list[dict],
                   n_batches: int, spp_per_batch: int, seed: int = 0, threads: int = 2,
                   variant: str = "llvm_ad_mono", max_depth: int = -1, rr_depth: int = _NO_RR,
                   max_lanes: int = 1 << 22) -> dict:
    """Render ``n_batches`` statistically independent batches of ``spp_per_batch`` each.

    Returns ``{"batches": float64[n_batches, nview, nrows, ncols], "images": batch mean,
    "var_mean": per-pixel variance of that mean (sample variance over batches / n_batches),
    "spp": n_batches * spp_per_batch, "batch_s": float64[n_batches] render seconds per batch,
    "render_s": their sum, "render_cpu_s", "build_s", "first_render_s", "second_render_s",
    "compile_s", "threads", "variant"}``. All views must share one image size.
    """
    mi, _ = _mitsuba(variant, threads)
    t0 = time.perf_counter()
    scene = build_scene(x_edges, y_edges, z_edges, air_extinction, cloud_extinction, air_albedo,
                        cloud_albedo, cloud_g, sun_zenith_deg, sun_azimuth_deg, cameras,
                        max_depth=max_depth, rr_depth=rr_depth, variant=variant, threads=threads)
    build_s = time.perf_counter() - t0
    r = _Renderer(scene, cameras, seed, mi, max_lanes)
    first, second = r.warmup()
    batches, batch_s = [], []
    c0 = time.process_time()
    for _ in range(int(n_batches)):
        t0 = time.perf_counter()
        imgs = r.render_all(int(spp_per_batch))
        batch_s.append(time.perf_counter() - t0)
        if isinstance(imgs, list):
            raise ValueError("render_batches needs all cameras to share one image size")
        batches.append(imgs)
    render_cpu_s = time.process_time() - c0
    b = np.stack(batches)
    var_mean = (b.var(axis=0, ddof=1) / b.shape[0]) if b.shape[0] > 1 else np.full(b.shape[1:],
                                                                                    np.nan)
    return {"batches": b, "images": b.mean(axis=0), "var_mean": var_mean,
            "spp": int(n_batches) * int(spp_per_batch), "batch_s": np.array(batch_s),
            "render_s": float(np.sum(batch_s)), "render_cpu_s": render_cpu_s,
            "build_s": build_s, "first_render_s": first,
            "second_render_s": second, "compile_s": max(first - second, 0.0),
            "threads": int(threads), "variant": variant}
