"""A plane-parallel homogeneous slab with periodic boundaries against an independent
adding-doubling solver (tests/reference/plane_parallel.py, which shares no code with
cloudct): reflected and transmitted radiance at several view directions.

Each camera sees the slab through a narrow field of view; the reference is averaged over
sub-directions of every pixel, as the pixel's value is the average over its area.
"""

from __future__ import annotations

import numpy as np
import pytest
from mcstats import assert_consistent
from reference.plane_parallel import rayleigh_hg_mixture, slab_radiances
from test_forward import pixel_directions, uniform_axis

from cloudct.mc.cameras import Camera
from cloudct.mc.render import render
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.medium import optical_medium

SLAB = dict(beta_air=0.3, albedo_air=0.95, beta_cloud=1.7, albedo_cloud=0.99, g=0.85, top=1.0)
SUN = Sun(zenith=30.0, azimuth=0.0)
# (zenith, azimuth) of the light's propagation direction; reflected goes up, transmitted
# down (zenith from the nadir)
REFLECTED = [(0.0, 0.0), (35.0, 0.0), (35.0, 180.0), (60.0, 90.0)]
TRANSMITTED = [(0.0, 0.0), (40.0, 180.0)]
DISTANCE = 3.0
TARGET = (0.5, 0.5, 0.5)


def slab_medium():
    return optical_medium(
        uniform_axis(0.0, 1.0, 2), uniform_axis(0.0, 1.0, 2), uniform_axis(0.0, SLAB["top"], 4),
        np.full((2, 2, 4), SLAB["beta_cloud"]), cloud_albedo=SLAB["albedo_cloud"],
        cloud_g=SLAB["g"], air_extinction=SLAB["beta_air"], air_albedo=SLAB["albedo_air"],
    )


def camera_for(zenith: float, azimuth: float, upward: bool) -> Camera:
    th, ph = np.radians(zenith), np.radians(azimuth)
    travel = np.array([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph),
                       np.cos(th) if upward else -np.cos(th)])
    position = np.asarray(TARGET) + DISTANCE * travel
    up = (0.0, 1.0, 0.0) if zenith == 0.0 else (0.0, 0.0, 1.0)
    return Camera(tuple(position), TARGET, up, fov=8.0, nrows=3, ncols=3)


def reference_image(cam: Camera, upward: bool) -> np.ndarray:
    travel = -pixel_directions(cam, 4)  # light travels from the slab to the pinhole
    zenith = np.degrees(np.arccos(travel[..., 2] if upward else -travel[..., 2]))
    azimuth = np.degrees(np.arctan2(travel[..., 1], travel[..., 0]))
    beta = SLAB["beta_air"] + SLAB["beta_cloud"]
    bs_air = SLAB["albedo_air"] * SLAB["beta_air"]
    bs_cloud = SLAB["albedo_cloud"] * SLAB["beta_cloud"]
    reflected, transmitted = slab_radiances(
        beta * SLAB["top"], (bs_air + bs_cloud) / beta,
        rayleigh_hg_mixture(bs_air, bs_cloud, SLAB["g"]), np.cos(np.radians(SUN.zenith)),
        SUN.azimuth, zenith.ravel(), azimuth.ravel(),
    )
    values = reflected if upward else transmitted
    return values.reshape(zenith.shape).mean(-1)


@pytest.mark.parametrize("method, photons", [("forward", 1_500_000), ("backward", 12_000)])
def test_slab_reflection_and_transmission(method, photons):
    cams = [camera_for(z, a, True) for z, a in REFLECTED]
    cams += [camera_for(z, a, False) for z, a in TRANSMITTED]
    scene = Scene(cams, SUN, "periodic", ground_albedo=None)
    images = render(slab_medium(), scene, photons=photons, method=method, seed=9, progress=False)
    upward = [True] * len(REFLECTED) + [False] * len(TRANSMITTED)
    ref = np.array([reference_image(c, u) for c, u in zip(cams, upward, strict=True)])
    assert_consistent(
        images.radiance.values, images.radiance_std_error.values, ref,
        images.attrs["batches"], label=f"{method} slab",
    )
    # the comparison has power: each pixel is resolved to better than 5%
    rel = images.radiance_std_error.values.mean(axis=(1, 2)) / ref.mean(axis=(1, 2))
    assert np.all(rel < 0.05), rel
