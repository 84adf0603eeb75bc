"""Validation of benchmarks/forward/mitsuba_peer.py (not part of the pytest suite).

Run: ``python -m benchmarks forward.check_mitsuba_peer [--quick] [--timing-only]``.

(a) Radiometry: homogeneous boxes against an analytic single-scattering model (our own pinhole
    camera in cloudct's convention, box-filtered pixels, exact attenuation in the homogeneous box,
    the sun lighting whichever faces it sees): exact single scattering (max_depth=2) for air only,
    cloud (HG) only with an oblique sun, and an air+cloud mixture (tests the blendphase weight);
    then the full volpath (max_depth=-1) on an optically thin box (tau ~ 0.01), where multiple
    scattering adds O(tau).
(b) Orientation: a dense white blob in the north-east top corner of an off-centre, non-cubic box,
    seen from the zenith, the south and the east; its brightness centroid is compared with the
    projection of its centre in cloudct's [row, col] convention.
(c) Absolute multiple scattering: a thick conservative isotropic slab (tau = 100) seen at nadir
    with the sun at the zenith, against Chandrasekhar's H-function result corrected for finite
    tau by van de Hulst's asymptotic formula (a white Lambertian plate would read 1/pi).
(d) Timing: a 32x37x26 random-blob cloud scene, 9 cameras 76x76 at 2 km (seed-paper layout).
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time

import numpy as np

from benchmarks.common import REPO
from benchmarks.forward import mitsuba_peer as mp

# ----------------------------------------------------------------------------- analytic model


def camera_rays(cam, nsub=6):
    """Unit ray directions [nrows, ncols, nsub*nsub, 3] in cloudct's convention."""
    pos = np.asarray(cam["position"], float)
    f = np.asarray(cam["lookat"], float) - pos
    f /= np.linalg.norm(f)
    r = np.cross(f, np.asarray(cam["up"], float))
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    nr, nc = cam["nrows"], cam["ncols"]
    th = np.tan(np.deg2rad(cam["fov_deg"]) / 2)
    tv = th * nr / nc
    s = (np.arange(nsub) + 0.5) / nsub
    a, b = np.meshgrid(s, s, indexing="ij")
    cols = np.arange(nc)[None, :, None] + a.ravel()[None, None, :]
    rows = np.arange(nr)[:, None, None] + b.ravel()[None, None, :]
    xs = -th + cols * 2 * th / nc
    ys = tv - rows * 2 * tv / nr
    xs, ys = np.broadcast_arrays(xs, ys)
    d = f + xs[..., None] * r + ys[..., None] * u
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def project(cam, p):
    """(row, col) in fractional pixels of world point p (cloudct's convention)."""
    pos = np.asarray(cam["position"], float)
    f = np.asarray(cam["lookat"], float) - pos
    f /= np.linalg.norm(f)
    r = np.cross(f, np.asarray(cam["up"], float))
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    v = np.asarray(p, float) - pos
    x, y = v @ r / (v @ f), v @ u / (v @ f)
    th = np.tan(np.deg2rad(cam["fov_deg"]) / 2)
    tv = th * cam["nrows"] / cam["ncols"]
    return (tv - y) / (2 * tv) * cam["nrows"], (x + th) / (2 * th) * cam["ncols"]


def slab(o, d, lo, hi):
    """Entry and exit distances of rays o + t d through the box (t_in > t_out: miss)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1 = (lo - o) / d
        t2 = (hi - o) / d
    tmin = np.where(np.isnan(t1), -np.inf, np.minimum(t1, t2)).max(axis=-1)
    tmax = np.where(np.isnan(t1), np.inf, np.maximum(t1, t2)).min(axis=-1)
    return np.maximum(tmin, 0.0), tmax


def phase_mix(mu, w_cloud, g):
    ray = 3.0 / (16 * np.pi) * (1 + mu**2)
    hg = (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * mu) ** 1.5)
    return (1 - w_cloud) * ray + w_cloud * hg


def single_scatter_image(cam, lo, hi, beta, omega, w_cloud, g, sun, nsub=6, nt=64):
    """Box-filtered single-scattering radiance of a homogeneous box, irradiance 1."""
    d = camera_rays(cam, nsub)
    o = np.asarray(cam["position"], float)
    t_in, t_out = slab(o, d, lo, hi)
    hit = t_out > t_in
    mu = d @ sun  # cos(scattering angle) = (-sun).(-d)
    p = phase_mix(mu, w_cloud, g)
    x = (np.arange(nt) + 0.5) / nt
    length = np.where(hit, t_out - t_in, 0.0)
    t = t_in[..., None] + length[..., None] * x  # [..., nt]
    pts = o + t[..., None] * d[..., None, :]
    # distance to the box exit along the sun direction
    with np.errstate(divide="ignore"):
        ds = np.where(sun > 0, (hi - pts) / sun, np.where(sun < 0, (lo - pts) / sun, np.inf))
    l_sun = ds.min(axis=-1)
    integrand = np.exp(-beta * (t - t_in[..., None])) * np.exp(-beta * l_sun)
    rad = omega * beta * p * length * integrand.mean(axis=-1)
    return np.where(hit, rad, 0.0).mean(axis=-1)


# ----------------------------------------------------------------------------------- checks


def homogeneous_case(name, beta_air, beta_cloud, w_air, w_cloud, g, sun_zen, sun_az, max_depth,
                     cam, n_batches, spp, lo=(-1.0, -1.0, 0.0), hi=(1.0, 1.0, 1.0)):
    lo, hi = np.array(lo), np.array(hi)
    n = (4, 4, 2)
    edges = [np.linspace(lo[i], hi[i], n[i] + 1) for i in range(3)]
    air = np.full(n, beta_air)
    cld = np.full(n, beta_cloud)
    out = mp.render_batches(*edges, air, cld, w_air, w_cloud, g, sun_zen, sun_az, [cam],
                            n_batches=n_batches, spp_per_batch=spp, seed=7, max_depth=max_depth)
    beta = beta_air + beta_cloud
    omega = (w_air * beta_air + w_cloud * beta_cloud) / beta
    wc = w_cloud * beta_cloud / (omega * beta)
    ref = single_scatter_image(cam, lo, hi, beta, omega, wc, g, mp.sun_direction(sun_zen, sun_az))
    img, var = out["images"][0], out["var_mean"][0]
    m_mc, m_an = img.mean(), ref.mean()
    se = np.sqrt(out["batches"][:, 0].mean(axis=(1, 2)).var(ddof=1) / n_batches)
    # pooled variance model var_i = c * ref_i (per-pixel batch variances from few batches
    # are too noisy to divide by)
    ok = ref > 0
    c = var[ok].sum() / ref[ok].sum()
    chi2 = np.mean((img[ok] - ref[ok]) ** 2 / (c * ref[ok]))
    # the same comparison with the blend weight swapped (wrong convention)
    ref_sw = single_scatter_image(cam, lo, hi, beta, omega, 1 - wc, g,
                                  mp.sun_direction(sun_zen, sun_az))
    # and with the image mirrored left-right (wrong orientation)
    chi2_flip = np.mean((img[ok] - ref[:, ::-1][ok]) ** 2 / (c * ref[ok]))
    # and with the sun azimuth mirrored (phi0 -> -phi0: wrong handedness)
    ref_az = single_scatter_image(cam, lo, hi, beta, omega, wc, g,
                                  mp.sun_direction(sun_zen, -sun_az))
    chi2_az = np.mean((img[ok] - ref_az[ok]) ** 2 / (c * ref[ok]))
    print(f"  {name}: mean MC {m_mc:.6e} +- {se:.1e}, analytic SS {m_an:.6e}, "
          f"rel diff {(m_mc / m_an - 1) * 100:+.2f}% ({(m_mc - m_an) / se:+.1f} sigma); "
          f"pixel chi2/dof {chi2:.2f} (vs mirrored image {chi2_flip:.1f}, vs mirrored sun "
          f"azimuth {chi2_az:.1f}); "
          f"swapped-blend mean {ref_sw.mean():.4e}; {out['render_s']:.1f}s")
    return m_mc / m_an - 1, chi2


def check_radiometry(quick):
    nb, spp = (4, 256) if quick else (8, 1024)
    nadir = {"position": [0.0, 0.0, 3.0], "lookat": [0.0, 0.0, 0.5], "up": [0.0, 1.0, 0.0],
             "fov_deg": 70.0, "nrows": 24, "ncols": 32}
    print("(a) radiometry vs analytic single scattering, nadir camera, fov 70 (pixels see top "
          "and side faces)")
    homogeneous_case("air only (Rayleigh, w=0.9, tau_z=0.1), sun zenith, SS only",
                     0.1, 0.0, 0.9, 0.99, 0.85, 0.0, 0.0, 2, nadir, nb, spp)
    homogeneous_case("cloud only (HG g=0.5, w=1, tau_z=0.1), sun 50/30, SS only",
                     0.0, 0.1, 0.912, 1.0, 0.5, 50.0, 30.0, 2, nadir, nb, spp)
    homogeneous_case("mix air 0.08 + cloud 0.02 (g=0.85), sun 30/120, SS only",
                     0.08, 0.02, 0.912, 0.99, 0.85, 30.0, 120.0, 2, nadir, nb, spp)
    nadir40 = dict(nadir, fov_deg=40.0)
    homogeneous_case("thin air (tau_z=0.01, w=0.912), sun zenith, full volpath, fov 40",
                     0.01, 0.0, 0.912, 0.99, 0.85, 0.0, 0.0, -1, nadir40, nb, 4 * spp)
    homogeneous_case("thin cloud HG g=0.85 (tau_z=0.01, w=0.99), sun zenith, full volpath",
                     0.0, 0.01, 0.912, 0.99, 0.85, 0.0, 0.0, -1, nadir40, nb, 4 * spp)


def check_orientation(quick):
    print("(b) orientation: dense white blob in the NE top corner of box x[0,1.6] y[0,1.2] "
          "z[0,0.8]")
    lo, hi, n = np.array([0.0, 0.0, 0.0]), np.array([1.6, 1.2, 0.8]), (16, 12, 8)
    edges = [np.linspace(lo[i], hi[i], n[i] + 1) for i in range(3)]
    air = np.full(n, 0.04)
    cld = np.zeros(n)
    cld[11:14, 8:11, 5:7] = 60.0
    blob = np.array([12.5 * 0.1, 9.5 * 0.1, 6.0 * 0.1])
    c = (lo + hi) / 2
    cams = [
        {"position": c + [0, 0, 3], "lookat": c, "up": [0, 1, 0], "name": "zenith, up=N"},
        {"position": c + [0, -3, 0], "lookat": c, "up": [0, 0, 1], "name": "south, look N"},
        {"position": c + [3, 0, 0], "lookat": c, "up": [0, 0, 1], "name": "east, look W"},
    ]
    for cam in cams:
        cam.update(fov_deg=45.0, nrows=40, ncols=50)
    out = mp.render_mitsuba(*edges, air, cld, 0.912, 1.0, 0.85, 0.0, 0.0, cams,
                            spp=64 if quick else 256)
    for cam, img in zip(cams, out["images"], strict=True):
        bg = np.median(img)
        w = np.clip(img - bg, 0, None)
        w = np.where(w > 0.3 * w.max(), w, 0.0)
        rr, cc = np.indices(img.shape) + 0.5
        r_mc, c_mc = (w * rr).sum() / w.sum(), (w * cc).sum() / w.sum()
        r_ex, c_ex = project(cam, blob)
        print(f"  {cam['name']:15s}: blob centroid (row, col) = ({r_mc:5.1f}, {c_mc:5.1f}), "
              f"expected ({r_ex:5.1f}, {c_ex:5.1f}); mirrored would be col "
              f"{cam['ncols'] - c_ex:5.1f} / row {cam['nrows'] - r_ex:5.1f}; blob radiance "
              f"{img[w > 0].mean():.3f} (white plate 1/pi = {1 / np.pi:.3f})")
    return out


def chandrasekhar_h(mu, omega=1.0):
    """Chandrasekhar's H(mu) for isotropic scattering (integral representation)."""
    from scipy.integrate import quad

    def f(t):
        return np.log(1 - omega * np.arctan(t) / t) / (1 + (mu * t) ** 2)

    v = quad(f, 0, 1, limit=200)[0] + quad(f, 1, np.inf, limit=200)[0]
    return np.exp(-mu / np.pi * v)


def check_thick_slab(quick):
    h1 = chandrasekhar_h(1.0)
    r_inf = h1**2 / 8.0  # reflection function R(1,1) of the half space, I = R mu0 E / pi
    k1 = np.sqrt(3.0) / 4.0 * h1  # escape function K(1), normalised 2 int K mu dmu = 1
    q0 = 0.7104
    cam = {"position": [0, 0, 3.0], "lookat": [0, 0, 0], "up": [0, 1, 0], "fov_deg": 2.0,
           "nrows": 8, "ncols": 8}
    nb, spp = (4, 256) if quick else (8, 1024)
    print(f"(c) thick conservative isotropic slab (HG g=0), sun zenith, nadir view; half-space "
          f"H(1)^2/(8 pi) = {r_inf / np.pi:.4f} (white plate 1/pi = {1 / np.pi:.4f})")
    for tau, rr in ((30.0, None), (100.0, None), (100.0, 1000)):
        r_tau = r_inf - 4 * k1**2 / (3 * (tau + 2 * q0))  # van de Hulst, thick-slab asymptote
        lo, hi = np.array([-3.0, -3.0, 0.0]), np.array([3.0, 3.0, 1.0])
        edges = [np.linspace(lo[i], hi[i], 2) for i in range(3)]
        kw = {} if rr is None else {"rr_depth": rr}
        out = mp.render_batches(*edges, np.zeros((1, 1, 1)), np.full((1, 1, 1), tau), 0.912,
                                1.0, 0.0, 0.0, 0.0, [cam], n_batches=nb,
                                spp_per_batch=spp if tau < 50 else spp // 4, seed=3, **kw)
        m = out["images"].mean()
        se = np.sqrt(out["batches"].mean(axis=(1, 2, 3)).var(ddof=1) / nb)
        ref = r_tau / np.pi
        print(f"  tau={tau:5.0f} rr_depth={'off' if rr is None else rr}: MC {m:.4f} +- {se:.4f}, "
              f"theory {ref:.4f}, rel diff {(m / ref - 1) * 100:+.2f}% "
              f"({(m - ref) / se:+.1f} sigma) [{out['render_s']:.1f}s]")


def timing_scene(seed=1):
    rng = np.random.default_rng(seed)
    n = (32, 37, 26)
    dx, dz = 0.02, 0.025
    xe, ye, ze = (np.arange(n[0] + 1) * dx, np.arange(n[1] + 1) * dx, np.arange(n[2] + 1) * dz)
    xc, yc, zc = np.meshgrid((xe[1:] + xe[:-1]) / 2, (ye[1:] + ye[:-1]) / 2,
                             (ze[1:] + ze[:-1]) / 2, indexing="ij")
    cld = np.zeros(n)
    for _ in range(6):
        c = rng.uniform([0.15, 0.15, 0.15], [xe[-1] - 0.15, ye[-1] - 0.15, ze[-1] - 0.15])
        r = rng.uniform(0.06, 0.15)
        d2 = ((xc - c[0]) ** 2 + (yc - c[1]) ** 2 + (zc - c[2]) ** 2) / r**2
        cld = np.maximum(cld, rng.uniform(40, 100) * np.exp(-d2) * (d2 < 4))
    cld[cld < 1.0] = 0.0
    air = np.full(n, 0.04)
    centre = np.array([xe[-1], ye[-1], ze[-1]]) / 2
    cams = [{"position": centre + [0, 0, 2.0], "lookat": centre, "up": [0, 1, 0]}]
    for az in range(0, 360, 45):
        t, p = np.deg2rad(29.0), np.deg2rad(az)
        cams.append({"position": centre + 2.0 * np.array([np.sin(t) * np.cos(p),
                                                          np.sin(t) * np.sin(p), np.cos(t)]),
                     "lookat": centre, "up": [0, 0, 1]})
    for cam in cams:
        cam.update(fov_deg=30.0, nrows=76, ncols=76)
    return (xe, ye, ze, air, cld), cams


def check_timing(spp, threads):
    (xe, ye, ze, air, cld), cams = timing_scene()
    print(f"(d) timing: grid {air.shape}, max cloud ext {cld.max():.1f}/km, cloudy cells "
          f"{(cld > 0).sum()}, 9 cameras 76x76 at 2 km, threads={threads}")
    out = mp.render_mitsuba(xe, ye, ze, air, cld, 0.912, 0.99, 0.85, 0.0, 0.0, cams, spp=spp,
                            threads=threads)
    im = out["images"]
    print(f"  build {out['build_s']:.2f}s, first render (JIT + 4 spp view 0) "
          f"{out['first_render_s']:.2f}s, second {out['second_render_s']:.2f}s -> JIT "
          f"{out['compile_s']:.2f}s; render 9 views x {spp} spp: {out['render_s']:.2f}s = "
          f"{out['render_s'] / spp * 1e3:.1f} ms per spp (all 9 views), "
          f"{out['render_s'] / (spp * im.size) * 1e9:.0f} ns per path; CPU time "
          f"{out['render_cpu_s']:.1f}s = {out['render_cpu_s'] / spp * 1e3:.0f} CPU-ms per spp "
          f"(wall/CPU ratio shows contention: ideal {1 / threads:.2f}, seen "
          f"{out['render_s'] / out['render_cpu_s']:.2f})")
    print("  view means:", np.array2string(im.mean(axis=(1, 2)), precision=4))
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--timing-only", action="store_true")
    ap.add_argument("--cold-jit", action="store_true",
                    help="(internal) timing run in a process with an empty Dr.Jit kernel cache")
    ap.add_argument("--spp", type=int, default=64)
    ap.add_argument("--threads", type=int, default=2)
    a = ap.parse_args()
    if a.cold_jit:
        check_timing(a.spp, a.threads)
        return
    t0 = time.time()
    if not a.timing_only:
        check_radiometry(a.quick)
        check_orientation(a.quick)
        check_thick_slab(a.quick)
    print("(d) cold Dr.Jit kernel cache (fresh HOME):")
    with tempfile.TemporaryDirectory() as home:
        subprocess.run([sys.executable, "-m", "benchmarks.forward.check_mitsuba_peer",
                        "--cold-jit", "--spp", str(a.spp), "--threads", str(a.threads)],
                       check=True, cwd=REPO, env=dict(os.environ, HOME=home))
    print("(d) warm kernel cache (this process / ~/.drjit):")
    check_timing(a.spp, a.threads)
    print(f"total {time.time() - t0:.0f}s")


if __name__ == "__main__":
    main()
