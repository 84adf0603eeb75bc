"""The render API and CLI: datasets, netCDF round trips, bad input."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from cloudct.cli import main
from cloudct.mc.cameras import Camera, nine_camera_set
from cloudct.mc.render import render
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.medium import MediumError, optical_medium, save_medium


def small_medium(extinction: float = 5.0):
    axis = 0.05 + 0.1 * np.arange(4)
    return optical_medium(axis, axis, axis + 0.5, np.full((4, 4, 4), extinction))


def looking_down(**kw) -> Camera:
    return Camera((0.2, 0.2, 3.0), (0.2, 0.2, 0.7), (0, 1, 0), fov=20.0, nrows=8, ncols=8, **kw)


def test_render_dataset_has_units_and_scene():
    images = render(small_medium(), Scene([looking_down()]), photons=2000, progress=False)
    assert images.radiance.dims == ("view", "row", "col")
    assert images.radiance.shape == (1, 8, 8)
    assert images.radiance.attrs["units"] == "1"
    assert np.all(np.isfinite(images.radiance.values))
    assert np.all(images.radiance_std_error.values >= 0)
    assert images.position.dims == ("view", "xyz")
    assert images.attrs["photons"] == 2016  # rounded up to a multiple of 32 batches
    assert Scene.from_dataset(images) == Scene([looking_down()])


def test_scene_netcdf_round_trip(tmp_path):
    cams = nine_camera_set(np.zeros(3), np.ones(3))
    scene = Scene(cams, Sun(20.0, 45.0), "periodic", 0.3)
    scene.to_dataset().to_netcdf(tmp_path / "scene.nc")
    assert Scene.from_dataset(xr.load_dataset(tmp_path / "scene.nc")) == scene


def test_nine_camera_set_geometry():
    cams = nine_camera_set(np.zeros(3), np.array([0.64, 0.74, 1.04]))
    centre = np.array([0.32, 0.37, 0.52])
    assert len(cams) == 9
    for cam in cams:
        offset = np.subtract(cam.position, centre)
        assert np.isclose(np.linalg.norm(offset), 2.0)
        assert (cam.nrows, cam.ncols) == (76, 76)
    zeniths = [np.degrees(np.arccos(np.subtract(c.position, centre)[2] / 2.0)) for c in cams]
    np.testing.assert_allclose(zeniths, [0.0] + [29.0] * 8, atol=1e-9)


@pytest.mark.parametrize(
    "scene, message",
    [
        (Scene([Camera((0.2, 0.2, 0.9), (0.2, 0.2, 0.0), (0, 1, 0))]), "inside the medium"),
        (Scene([Camera((0.2, 0.2, 3.0), (0.2, 0.2, 5.0), (0, 1, 0))]), "does not see"),
        (Scene([Camera((5.0, 5.0, 3.0), (9.0, 9.0, 0.0), (0, 0, 1), fov=5.0)]), "does not see"),
        (Scene([Camera((0.2, 0.2, 0.1), (0.2, 0.2, 1.0), (0, 1, 0))], ground_albedo=0.1),
         "below the ground"),
        (Scene([Camera((0.2, 0.2, 0.8), (0.2, 0.2, 0.0), (0, 1, 0))], boundary="periodic"),
         "inside the periodic medium"),
        (Scene([Camera((0.2, 0.2, 3.0), (3.0, 0.2, 2.5), (0, 0, 1), fov=60.0)],
               boundary="periodic"), "horizon"),
    ],
)
def test_bad_scenes_are_refused(scene, message):
    with pytest.raises(ValueError, match=message):
        render(small_medium(), scene, photons=100, progress=False)


@pytest.mark.parametrize("zenith", [90.0, 120.0, float("nan")])
def test_sun_below_horizon_is_refused(zenith):
    with pytest.raises(ValueError, match="sun"):
        Sun(zenith=zenith)


@pytest.mark.parametrize("kwargs, message", [
    ({"photons": 0}, "photons"), ({"batches": 1}, "batches"), ({"method": "both"}, "method"),
])
def test_bad_render_arguments_are_refused(kwargs, message):
    with pytest.raises(ValueError, match=message):
        render(small_medium(), Scene([looking_down()]), progress=False, **kwargs)


def test_medium_with_nan_is_refused():
    medium = small_medium()
    medium["cloud_extinction"][1, 1, 1] = np.nan
    with pytest.raises(MediumError, match="cloud_extinction"):
        render(medium, Scene([looking_down()]), photons=100, progress=False)


def test_empty_medium_gives_black_images():
    """A medium with no extinction scatters nothing: exactly zero, not NaN."""
    medium = small_medium(0.0)
    medium["air_extinction"] = medium["air_extinction"] * 0.0
    images = render(medium, Scene([looking_down()]), photons=1000, progress=False)
    assert np.all(images.radiance.values == 0.0)
    assert np.all(images.radiance_std_error.values == 0.0)


def test_cli_render_writes_netcdf_and_previews(tmp_path):
    save_medium(small_medium(), tmp_path / "medium.nc")
    Scene([looking_down()]).to_dataset().to_netcdf(tmp_path / "scene.nc")
    out = tmp_path / "images.nc"
    argv = [
        "render", str(tmp_path / "medium.nc"), "--scene", str(tmp_path / "scene.nc"),
        "-o", str(out), "--photons", "3200", "--png", str(tmp_path / "png"),
    ]
    assert main(argv) == 0
    images = xr.load_dataset(out)
    assert images.radiance.shape == (1, 8, 8)
    assert (tmp_path / "png" / "views.png").exists()
    assert main(argv) == 2  # refuses to overwrite
    assert main([*argv, "--overwrite"]) == 0
