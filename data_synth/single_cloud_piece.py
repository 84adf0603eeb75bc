"""Small pieces of the bundled single cloud with cameras around them, small enough to pool
tens of millions of paths: the microphysics piece of the detector-sampling tests
(``tests/test_detector_sampling.py``) and of the Mie piece check of
``benchmarks/forward/mie_variance.py``; the dense core with its cloud-free holes of the
sample-matching tests (``tests/test_sample_matching.py``) and of the finite-difference
check in those holes (``benchmarks/gradients/holes.py``)."""

from __future__ import annotations

import numpy as np
import xarray as xr

from cloudct.les import bundled_single_cloud
from cloudct.mc.cameras import Camera
from cloudct.mc.render import single_cloud_medium
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun


def piece_microphysics() -> xr.Dataset:
    """A 12 x 16 x 14 piece of the bundled single cloud (LWC and r_eff of the LES)."""
    return bundled_single_cloud().isel(x=slice(2, 14), y=slice(14, 30), z=slice(2, 16))


def scene_of_piece(medium: xr.Dataset) -> Scene:
    """Three 16 x 16 cameras around ``medium`` (the nadir one 24 degrees wide), sun at 20
    degrees zenith, open boundaries."""
    lo = np.array([float(medium[c][0]) for c in "xyz"]) - 0.01 * np.array([1, 1, 2])
    hi = np.array([float(medium[c][-1]) for c in "xyz"]) + 0.01 * np.array([1, 1, 2])
    centre = tuple((lo + hi) / 2)
    cams = [
        Camera((centre[0], centre[1], 2.0), centre, (0, 1, 0), fov=24.0, nrows=16, ncols=16),
        Camera((centre[0] + 0.8, centre[1] - 0.5, 1.8), centre, fov=30.0, nrows=16, ncols=16),
        Camera((centre[0] - 0.7, centre[1] + 0.4, 1.7), centre, fov=30.0, nrows=16, ncols=16),
    ]
    return Scene(cams, Sun(zenith=20.0, azimuth=60.0), "open")


def dense_core_piece() -> xr.Dataset:
    """A 10 x 10 x 12 piece of the single cloud's optical medium (HG): its dense core (tau
    up to 2.5 per voxel), the cloud-free holes inside it and its cloud-free margin."""
    return single_cloud_medium().isel(x=slice(4, 14), y=slice(18, 28), z=slice(12, 24))


def scene_of_dense_core(medium: xr.Dataset) -> Scene:
    """Two 6 x 6 cameras, 14 degrees wide, on ``medium``'s centre (one 2 km above it, one
    1 km aside and 1.7 km above), sun at 20 degrees zenith, open boundaries."""
    x, y, z = (float(medium[a].mean()) for a in ("x", "y", "z"))
    target = (x, y, z)
    cams = [
        Camera((x, y, z + 2.0), target, (0, 1, 0), fov=14.0, nrows=6, ncols=6),
        Camera((x + 1.0, y, z + 1.7), target, (0, 0, 1), fov=14.0, nrows=6, ncols=6),
    ]
    return Scene(cams, Sun(zenith=20.0, azimuth=30.0), "open", None)
