"""A small piece of the bundled single cloud and three cameras around it: the scene of the
detector-sampling tests (``tests/test_detector_sampling.py``) and of the Mie piece check of
``benchmarks/forward/mie_variance.py``, small enough to pool tens of millions of photons."""

from __future__ import annotations

import numpy as np
import xarray as xr

from cloudct.les import bundled_single_cloud
from cloudct.mc.cameras import Camera
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
