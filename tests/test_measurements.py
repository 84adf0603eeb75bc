"""Synthetic measurements (render + camera noise, netCDF round trip, CLI) and the synthetic
cloud generators."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from cloudct.cli import main
from cloudct.mc.cameras import nine_camera_set
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.measurements import (
    MeasurementError,
    NoiseModel,
    load_measurements,
    noise_model_from_attrs,
    save_measurements,
    synthesize_measurements,
    validate_measurements,
)
from cloudct.medium import cell_edges, is_microphysical, save_medium, validate_medium
from cloudct.optics import to_optical
from data_synth.synthetic_cloud import blob_cloud, synthetic_cloud


def small_blob():
    return blob_cloud(8, 8, 6, extinction=30.0)


def small_scene(medium, npix: int = 12) -> Scene:
    edges = cell_edges(medium)
    lo, hi = np.array([e[0] for e in edges]), np.array([e[-1] for e in edges])
    return Scene(nine_camera_set(lo, hi, npix=npix), Sun(20.0, 30.0))


@pytest.fixture(scope="module")
def noisy():
    medium = small_blob()
    noise = NoiseModel(electrons=2000.0, read_noise=8.0)
    return synthesize_measurements(
        medium, small_scene(medium), photons=20_000, seed=5, noise=noise, noise_seed=9
    )


def test_measurements_round_trip_through_netcdf(noisy, tmp_path):
    path = tmp_path / "m.nc"
    save_measurements(noisy, path)
    back = load_measurements(path)
    assert Scene.from_dataset(back) == Scene.from_dataset(noisy)
    assert back.attrs["sun_zenith"] == 20.0 and back.attrs["sun_azimuth"] == 30.0
    assert noise_model_from_attrs(back) == NoiseModel(2000.0, read_noise=8.0)
    for name in ("wavelength", "photons", "seed", "noise_seed", "noise_model", "method"):
        assert back.attrs[name] == noisy.attrs[name], name
    assert noisy.attrs["method"] == "forward"  # HG optics: the forward estimator by default
    np.testing.assert_array_equal(back.attrs["medium_box"], noisy.attrs["medium_box"])
    np.testing.assert_array_equal(back.attrs["medium_shape"], [8, 8, 6])
    for name in ("radiance", "radiance_std_error", "radiance_noise_std"):
        np.testing.assert_array_equal(back[name].values, noisy[name].values)
        assert back[name].attrs["units"] == "1"
    with pytest.raises(FileExistsError):
        save_measurements(noisy, path)


def test_noise_is_reproducible_and_stated():
    medium = small_blob()
    scene = small_scene(medium)
    noise = NoiseModel(electrons=500.0, read_noise=4.0)
    a, b, c = (
        synthesize_measurements(medium, scene, photons=4000, seed=1, noise=noise, noise_seed=s)
        for s in (3, 3, 4)
    )
    clean = synthesize_measurements(medium, scene, photons=4000, seed=1)
    np.testing.assert_array_equal(a.radiance.values, b.radiance.values)
    assert not np.array_equal(a.radiance.values, c.radiance.values)
    assert clean.attrs["noise_model"] == "none" and noise_model_from_attrs(clean) is None
    np.testing.assert_array_equal(clean.radiance_noise_std.values,
                                  clean.radiance_std_error.values)
    expected = np.sqrt(noise.variance(clean.radiance.values) + clean.radiance_std_error**2)
    np.testing.assert_allclose(a.radiance_noise_std.values, expected, rtol=1e-12)


@pytest.mark.parametrize("radiance, seed", [(0.0, 1), (0.002, 2), (0.05, 3), (0.3, 4)])
def test_noise_model_mean_and_variance(radiance, seed):
    """z-tests on 200 000 pixels of one radiance: the sample mean against the radiance, and
    the sample variance against the stated variance, with the variance's standard error
    from the sample's fourth central moment."""
    noise = NoiseModel(electrons=400.0, read_noise=3.0)
    n = 200_000
    draws = noise.apply(np.full(n, radiance), np.random.default_rng(seed))
    variance = float(noise.variance(radiance))
    z_mean = (draws.mean() - radiance) / np.sqrt(variance / n)
    centred = draws - draws.mean()
    m4 = np.mean(centred**4)
    z_var = (draws.var(ddof=1) - variance) / np.sqrt((m4 - variance**2) / n)
    print(f"radiance {radiance}: z(mean) {z_mean:.2f}, z(variance) {z_var:.2f}")
    assert abs(z_mean) < 4.0
    assert abs(z_var) < 4.0


def test_noise_model_refuses_bad_input():
    with pytest.raises(ValueError, match="electrons"):
        NoiseModel(electrons=0.0)
    with pytest.raises(ValueError, match="read noise"):
        NoiseModel(electrons=10.0, read_noise=-1.0)
    with pytest.raises(ValueError, match="non-negative"):
        NoiseModel(10.0).apply(np.array([-0.1]), np.random.default_rng(0))


def test_validation_of_measurements(noisy):
    masked = noisy.copy(deep=True)
    masked["radiance"][0, 0, 0] = np.nan
    validate_measurements(masked)  # NaN marks a masked pixel
    bad = noisy.copy(deep=True)
    bad["radiance"][0, 0, 0] = np.inf
    with pytest.raises(MeasurementError, match="infinite"):
        validate_measurements(bad)
    with pytest.raises(MeasurementError, match="radiance"):
        validate_measurements(noisy.drop_vars("radiance"))
    with pytest.raises(MeasurementError, match="fov"):
        validate_measurements(noisy.drop_vars("fov"))
    no_sun = noisy.copy()
    no_sun.attrs = {k: v for k, v in noisy.attrs.items() if k != "sun_zenith"}
    with pytest.raises(MeasurementError, match="sun_zenith"):
        validate_measurements(no_sun)


def test_wavelength_must_match_optical_medium():
    optical = to_optical(synthetic_cloud(8, 8, 8, seed=1), wavelength=0.672, optics="mie")
    with pytest.raises(ValueError, match="0.672"):
        synthesize_measurements(optical, photons=100, wavelength=0.55)


def test_cli_synth(tmp_path, capsys):
    save_medium(small_blob(), tmp_path / "blob.nc")
    out = tmp_path / "m.nc"
    argv = ["synth", str(tmp_path / "blob.nc"), "-o", str(out), "--photons", "3000",
            "--noise-electrons", "1000", "--read-noise", "5", "--seed", "3"]
    assert main(argv) == 0
    ds = load_measurements(out)
    assert ds.sizes["view"] == 9 and ds.attrs["photons"] == 3008  # 32 batches
    assert noise_model_from_attrs(ds) == NoiseModel(1000.0, read_noise=5.0)
    assert ds.attrs["seed"] == 3 and ds.attrs["noise_seed"] == 3
    assert main(argv) == 2  # refuses to overwrite
    assert main(["synth", "-o", str(tmp_path / "x.nc"), "--read-noise", "5"]) == 2
    assert "needs --noise-electrons" in capsys.readouterr().err


# --- synthetic clouds ------------------------------------------------------------------


def test_synthetic_cloud_is_reproducible_and_valid():
    a = synthetic_cloud(24, 20, 16, seed=7)
    b = synthetic_cloud(24, 20, 16, seed=7)
    c = synthetic_cloud(24, 20, 16, seed=8)
    validate_medium(a)
    assert is_microphysical(a)
    xr.testing.assert_identical(a, b)
    assert not np.array_equal(a.lwc.values, c.lwc.values)
    assert a.lwc.shape == (24, 20, 16)
    np.testing.assert_allclose(np.diff(a.x.values), 0.02)
    np.testing.assert_allclose(np.diff(a.z.values), 0.04)
    to_optical(a)  # r_eff within the Mie table


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_synthetic_cloud_is_adiabatic_like(seed):
    """Inside the cloud the LWC and r_eff grow with height (least-squares slope over the
    cloudy cells), the lowest cloudy layer holds the requested cloud fraction, and the
    clouds narrow upwards."""
    m = synthetic_cloud(32, 32, 20, seed=seed, cloud_fraction=0.3)
    lwc, reff = m.lwc.values, m.reff.values
    cloudy = lwc > 0
    z = np.broadcast_to(m.z.values, lwc.shape)[cloudy]
    assert np.polyfit(z, lwc[cloudy], 1)[0] > 0.5  # g m-3 per km
    assert np.polyfit(z, reff[cloudy], 1)[0] > 0.0
    fraction = cloudy.mean(axis=(0, 1))
    base = int(np.argmax(fraction > 0))
    assert base == 2  # default cloud base: two layers above the bottom
    assert abs(fraction[base] - 0.3) < 0.01
    assert fraction[base:].max() == fraction[base]
    assert np.all(reff[cloudy] >= 1.0) and np.all(reff[cloudy] <= 25.0)


def test_blob_cloud_is_an_ellipsoid_of_constant_extinction():
    m = blob_cloud(20, 20, 16, extinction=12.0)
    validate_medium(m)
    ext = m.cloud_extinction.values
    assert set(np.unique(ext)) == {0.0, 12.0}
    # volume: 4/3 pi of the semi-axes (0.35 of the box: 0.14, 0.14, 0.224 km)
    volume = (ext > 0).sum() * 0.02 * 0.02 * 0.04
    assert volume == pytest.approx(4.0 / 3.0 * np.pi * 0.14 * 0.14 * 0.224, rel=0.05)
    with pytest.raises(ValueError, match="no cell centre"):
        blob_cloud(8, 8, 8, centre=(5.0, 5.0, 5.0))


# ---------------------------------------------------------------------------------------
# The schema page's example (docs/measurements.md), as it stands on the page
# ---------------------------------------------------------------------------------------


def schema_page_example() -> dict:
    """The namespace of the first Python block of docs/measurements.md, executed."""
    page = (Path(__file__).resolve().parents[1] / "docs" / "measurements.md").read_text()
    code = page.split("```python\n", 1)[1].split("```", 1)[0]
    namespace: dict = {}
    exec(compile(code, "docs/measurements.md", "exec"), namespace)
    return namespace


def test_a_file_built_from_arrays_as_the_schema_page_shows_runs_through_carve_and_retrieve(
    tmp_path, capsys
):
    example = schema_page_example()
    cloud = small_blob()
    rendered = synthesize_measurements(cloud, small_scene(cloud, npix=16), photons=100_000,
                                       seed=3, progress=False)
    arrays = {name: rendered[name].values for name in ("position", "lookat", "up", "fov")}
    m = example["measurement_set"](
        rendered["radiance"].values, rendered["radiance_noise_std"].values, **arrays,
        sun_zenith=20.0, sun_azimuth=30.0,
    )
    m.to_netcdf(tmp_path / "measurements.nc")  # as another tool would write it
    assert validate_measurements(load_measurements(tmp_path / "measurements.nc")) is None
    edges = cell_edges(cloud)
    save_medium(example["template_medium"](*edges), tmp_path / "template.nc")
    assert main(["carve", str(tmp_path / "measurements.nc"), "--medium",
                 str(tmp_path / "template.nc"), "-o", str(tmp_path / "init.nc"),
                 "--fit-photons", "20000"]) == 0
    assert main(["retrieve", str(tmp_path / "measurements.nc"), "--init",
                 str(tmp_path / "init.nc"), "--iterations", "2", "--photons", "4000",
                 "-o", str(tmp_path / "result.nc")]) == 0
    result = xr.load_dataset(tmp_path / "result.nc")
    assert result["log_loss"].size == 2 and np.all(np.isfinite(result["log_loss"].values))
    with pytest.raises(MeasurementError, match="fov"):  # the page's validation is live
        example["measurement_set"](
            rendered["radiance"].values, rendered["radiance_noise_std"].values,
            **{**arrays, "fov": np.full(9, np.inf)}, sun_zenith=20.0, sun_azimuth=30.0,
        )
