"""The forward (local estimation) and backward (next-event) estimators against references
they share no code with: analytic single scattering in a thin box, clear sky over a
Lambertian ground, and each other on a heterogeneous LES cloud.

The references use their own pinhole model written from CONVENTIONS.md (not cloudct's
camera code), their own ray-box geometry and their own phase functions.
"""

from __future__ import annotations

import numpy as np
import pytest
from mcstats import assert_consistent

from cloudct.mc.cameras import Camera
from cloudct.mc.render import render
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.medium import optical_medium

# ----------------------------------------------------------------------------------------
# Independent reference geometry and optics
# ----------------------------------------------------------------------------------------


def pixel_directions(cam: Camera, sub: int) -> np.ndarray:
    """Unit directions from the pinhole through sub x sub points of every pixel, written
    from the conventions: fov across the columns, row 0 at the top, col 0 on the left.
    Shape (nrows, ncols, sub * sub, 3)."""
    f = np.subtract(cam.lookat, cam.position)
    f = f / np.linalg.norm(f)
    r = np.cross(f, cam.up)
    r = r / np.linalg.norm(r)
    u = np.cross(r, f)
    half = np.tan(np.radians(cam.fov) / 2)
    pix = 2 * half / cam.ncols
    offsets = (np.arange(sub) + 0.5) / sub
    cols = (np.arange(cam.ncols)[:, None] + offsets[None, :]).ravel()
    rows = (np.arange(cam.nrows)[:, None] + offsets[None, :]).ravel()
    a = -half + cols * pix  # right
    b = half * cam.nrows / cam.ncols - rows * pix  # up
    d = f + a[None, :, None] * r + b[:, None, None] * u
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    # regroup (rows*sub, cols*sub) into per-pixel sub-samples
    d = d.reshape(cam.nrows, sub, cam.ncols, sub, 3).transpose(0, 2, 1, 3, 4)
    return d.reshape(cam.nrows, cam.ncols, sub * sub, 3)


def box_chord(origin: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Entry and exit distances of rays from ``origin`` along d (..., 3) through a box."""
    with np.errstate(divide="ignore"):
        t0 = (lo - origin) / d
        t1 = (hi - origin) / d
    near = np.minimum(t0, t1).max(axis=-1)
    far = np.maximum(t0, t1).min(axis=-1)
    near = np.maximum(near, 0.0)
    return near, far, far > near


def exit_distance(points: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray):
    """Distance from points inside a box to its boundary along the unit vector d."""
    with np.errstate(divide="ignore"):
        t = np.where(d > 0, (hi - points) / d, np.where(d < 0, (lo - points) / d, np.inf))
    return t.min(axis=-1)


def rayleigh(mu):
    return 3 / (16 * np.pi) * (1 + mu**2)


def henyey_greenstein(mu, g):
    return (1 - g**2) / (4 * np.pi * (1 + g**2 - 2 * g * mu) ** 1.5)


def uniform_axis(lo: float, hi: float, n: int) -> np.ndarray:
    return lo + (np.arange(n) + 0.5) * (hi - lo) / n


# ----------------------------------------------------------------------------------------
# Optically thin homogeneous box: single scattering
# ----------------------------------------------------------------------------------------

THIN = dict(beta_air=0.15, beta_cloud=0.35, albedo=0.01, g=0.6)
BOX_LO = np.array([0.0, 0.0, 0.5])
BOX_HI = np.array([1.0, 0.8, 0.9])


def thin_box_medium():
    nx, ny, nz = 4, 3, 2
    x = uniform_axis(BOX_LO[0], BOX_HI[0], nx)
    y = uniform_axis(BOX_LO[1], BOX_HI[1], ny)
    z = uniform_axis(BOX_LO[2], BOX_HI[2], nz)
    return optical_medium(
        x, y, z, np.full((nx, ny, nz), THIN["beta_cloud"]),
        cloud_albedo=THIN["albedo"], cloud_g=THIN["g"],
        air_extinction=THIN["beta_air"], air_albedo=THIN["albedo"],
    )


def single_scattering_reference(cam: Camera, sun: Sun, sub: int = 12, nquad: int = 32):
    """Pixel-averaged single-scattering radiance of the homogeneous thin box.

    Along each sub-pixel ray, radiance = integral over the chord of
    beta_s p(mu) exp(-beta l_sun(x)) exp(-beta s) ds with mu the cosine between the sun's
    travel direction and the direction towards the camera. Returns (radiance, whole)
    where ``whole`` marks pixels whose sub-rays all hit (or all miss) the box.
    """
    beta = THIN["beta_air"] + THIN["beta_cloud"]
    bs_air = THIN["albedo"] * THIN["beta_air"]
    bs_cloud = THIN["albedo"] * THIN["beta_cloud"]
    th, ph = np.radians(sun.zenith), np.radians(sun.azimuth)
    to_sun = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
    origin = np.asarray(cam.position, float)
    d = pixel_directions(cam, sub)
    near, far, hit = box_chord(origin, d, BOX_LO, BOX_HI)
    xg, wg = np.polynomial.legendre.leggauss(nquad)
    s = near[..., None] + (far - near)[..., None] * (xg + 1) / 2  # (..., nquad)
    points = origin + s[..., None] * d[..., None, :]
    l_sun = exit_distance(points, to_sun, BOX_LO, BOX_HI)
    mu = (-to_sun * -d).sum(-1)[..., None]  # sun travel . towards camera
    phase = (bs_air * rayleigh(mu) + bs_cloud * henyey_greenstein(mu, THIN["g"])) / (
        bs_air + bs_cloud
    )
    integrand = (bs_air + bs_cloud) * phase * np.exp(-beta * (l_sun + (s - near[..., None])))
    radiance = np.where(hit, (far - near) / 2 * (integrand * wg).sum(-1), 0.0)
    whole = hit.all(-1) | ~hit.any(-1)
    return radiance.mean(-1), whole, ~hit.any(-1)


@pytest.fixture(scope="module")
def thin_box_scene():
    target = tuple((BOX_LO + BOX_HI) / 2)
    cams = [
        Camera((0.5, 0.4, 3.5), target, (0, 1, 0), fov=28.0, nrows=16, ncols=16),
        Camera((2.4, -0.9, 2.6), target, (0, 0, 1), fov=30.0, nrows=16, ncols=16),
    ]
    return Scene(cameras=cams, sun=Sun(zenith=40.0, azimuth=30.0), boundary="open")


def test_thin_box_single_scattering(thin_box_scene):
    """Every pixel agrees with the analytic single-scattering radiance (multiple scattering
    is O(albedo * tau) ~ 0.3% of it, far below the per-pixel errors)."""
    images = render(thin_box_medium(), thin_box_scene, photons=400_000, seed=1, progress=False)
    for view, cam in enumerate(thin_box_scene.cameras):
        ref, whole, miss = single_scattering_reference(cam, thin_box_scene.sun)
        est = images.radiance.values[view]
        se = images.radiance_std_error.values[view]
        assert np.all(est[miss] == 0.0), "light from outside the box"
        lit = whole & ~miss
        assert lit.sum() > 60
        batches = images.attrs["batches"]
        assert_consistent(est[lit], se[lit], ref[lit], batches, label=f"view {view}")


# ----------------------------------------------------------------------------------------
# Clear sky over a Lambertian ground
# ----------------------------------------------------------------------------------------

GROUND = dict(albedo=0.3, beta_air=0.12, z0=0.0, z1=1.2)


def clear_sky_medium():
    x = uniform_axis(0.0, 1.0, 2)
    y = uniform_axis(0.0, 1.0, 2)
    z = uniform_axis(GROUND["z0"], GROUND["z1"], 3)
    return optical_medium(
        x, y, z, np.zeros((2, 2, 3)), cloud_albedo=0.0, cloud_g=0.0,
        air_extinction=GROUND["beta_air"], air_albedo=0.0,
    )


@pytest.fixture(scope="module")
def clear_sky_scene():
    cams = [
        Camera((0.5, 0.5, 4.0), (0.5, 0.5, 0.0), (0, 1, 0), fov=20.0, nrows=6, ncols=6),
        Camera((-1.5, 0.8, 3.0), (0.7, 0.2, 0.0), (0, 0, 1), fov=16.0, nrows=6, ncols=6),
    ]
    return Scene(cams, Sun(zenith=35.0, azimuth=-60.0), "periodic", GROUND["albedo"])


def clear_sky_reference(cam: Camera, sun: Sun, sub: int = 8) -> np.ndarray:
    """A cos(theta0) / pi x T(sun -> ground) x T(ground -> camera), pixel-averaged."""
    tau = GROUND["beta_air"] * (GROUND["z1"] - GROUND["z0"])
    mu0 = np.cos(np.radians(sun.zenith))
    mu_view = -pixel_directions(cam, sub)[..., 2]
    return GROUND["albedo"] * mu0 / np.pi * np.exp(-tau / mu0) * np.exp(-tau / mu_view).mean(-1)


@pytest.mark.parametrize("method, photons", [("forward", 200_000), ("backward", 2048)])
def test_clear_sky_lambertian_ground(clear_sky_scene, method, photons):
    images = render(
        clear_sky_medium(), clear_sky_scene, photons=photons, method=method, seed=2,
        progress=False,
    )
    for view, cam in enumerate(clear_sky_scene.cameras):
        assert_consistent(
            images.radiance.values[view], images.radiance_std_error.values[view],
            clear_sky_reference(cam, clear_sky_scene.sun), images.attrs["batches"],
            label=f"{method} view {view}",
        )


# ----------------------------------------------------------------------------------------
# Forward vs backward on a heterogeneous LES cloud
# ----------------------------------------------------------------------------------------


def test_forward_backward_agree_on_les_cloud():
    """Pixel by pixel, the two estimators agree within their combined standard errors on
    a cropped piece of the bundled RICO cloud (thin and dense parts, air + Mie extinction,
    HG cloud, Rayleigh air), with an oblique sun and a grey ground."""
    from cloudct.mc.render import single_cloud_medium

    medium = single_cloud_medium().isel(x=slice(2, 14), y=slice(14, 30), z=slice(2, 16))
    lo = np.array([float(medium[c][0]) for c in "xyz"]) - 0.01 * np.array([1, 1, 2])
    hi = np.array([float(medium[c][-1]) for c in "xyz"]) + 0.01 * np.array([1, 1, 2])
    centre = tuple((lo + hi) / 2)
    cams = [
        Camera((centre[0], centre[1], 2.0), centre, (0, 1, 0), fov=30.0, nrows=10, ncols=10),
        Camera((centre[0] + 1.0, centre[1] - 0.6, 1.6), centre, fov=30.0, nrows=10, ncols=10),
    ]
    scene = Scene(cams, Sun(zenith=30.0, azimuth=120.0), "open", ground_albedo=0.2)
    fwd = render(medium, scene, photons=600_000, seed=3, progress=False)
    bwd = render(medium, scene, photons=4096, method="backward", seed=4, progress=False)
    bright = fwd.radiance.values > 0.02 * fwd.radiance.values.max()
    assert bright.sum() > 50
    assert_consistent(
        fwd.radiance.values[bright], fwd.radiance_std_error.values[bright],
        bwd.radiance.values[bright], fwd.attrs["batches"],
        reference_error=bwd.radiance_std_error.values[bright], label="forward vs backward",
    )


# ----------------------------------------------------------------------------------------
# Reproducibility
# ----------------------------------------------------------------------------------------


def test_images_do_not_depend_on_thread_count(thin_box_scene):
    import numba

    medium = thin_box_medium()
    saved = numba.get_num_threads()
    try:
        numba.set_num_threads(1)
        one = render(medium, thin_box_scene, photons=20_000, seed=5, progress=False)
        numba.set_num_threads(numba.config.NUMBA_NUM_THREADS)
        many = render(medium, thin_box_scene, photons=20_000, seed=5, progress=False)
    finally:
        numba.set_num_threads(saved)
    np.testing.assert_array_equal(one.radiance.values, many.radiance.values)
    np.testing.assert_array_equal(one.radiance_std_error.values, many.radiance_std_error.values)


def test_mean_radiance_does_not_depend_on_batching(thin_box_scene):
    """The same photons split into 8 or 32 batches give the same mean image (the photon
    indices, hence the random streams, are the same; only the summation order differs)."""
    medium = thin_box_medium()
    a = render(medium, thin_box_scene, photons=32_000, batches=8, seed=6, progress=False)
    b = render(medium, thin_box_scene, photons=32_000, batches=32, seed=6, progress=False)
    np.testing.assert_allclose(a.radiance.values, b.radiance.values, rtol=1e-12, atol=1e-15)
    c = render(medium, thin_box_scene, photons=32_000, batches=32, seed=7, progress=False)
    assert not np.array_equal(b.radiance.values, c.radiance.values)
