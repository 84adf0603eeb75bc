"""Measurements in several bands: the layout (band, view, row, col) with the coordinate
wavelength, its checks, taking one band out and stacking bands, ``cloudct synth --bands``
and ``cloudct render --bands``, and carve/retrieve reading the 0.672 micron band of such a
file (docs/measurements.md, "Bands")."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from cloudct.cli import main
from cloudct.mc.cameras import nine_camera_set
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.measurement_bands import stack_bands
from cloudct.measurements import (
    MeasurementError,
    band_measurements,
    coarse_measurements,
    load_measurements,
    save_measurements,
    synthesize_measurements,
    validate_measurements,
)
from cloudct.medium import cell_edges, microphysical_medium, save_medium
from cloudct.netcdf import save_netcdf
from data_synth.synthetic_cloud import blob_cloud


def scene_of(medium, npix: int = 8, ground_albedo=None) -> Scene:
    edges = cell_edges(medium)
    lo, hi = np.array([e[0] for e in edges]), np.array([e[-1] for e in edges])
    return Scene(nine_camera_set(lo, hi, npix=npix), Sun(20.0, 30.0),
                 ground_albedo=ground_albedo)


@pytest.fixture(scope="module")
def two_bands():
    """Two one-band sets of a blob (optical: the wavelength only labels them) with
    different seeds and ground albedos."""
    blob = blob_cloud(8, 8, 6, extinction=30.0)
    red = synthesize_measurements(blob, scene_of(blob), photons=2000, seed=1, wavelength=0.672)
    swir = synthesize_measurements(blob, scene_of(blob, ground_albedo=0.3), photons=2000,
                                   seed=2, wavelength=2.13)
    return red, swir


def test_stack_bands_and_band_measurements_are_inverse(two_bands):
    red, swir = two_bands
    both = stack_bands([swir, red])  # sorted by wavelength
    assert both["radiance"].dims == ("band", "view", "row", "col")
    np.testing.assert_array_equal(both["wavelength"].values, [0.672, 2.13])
    assert both["wavelength"].attrs["units"] == "micron" and "wavelength" not in both.attrs
    # what differs between the bands becomes a variable over band; the rest stays
    np.testing.assert_array_equal(both["ground_albedo"].values, [-1.0, 0.3])
    np.testing.assert_array_equal(both["seed"].values, [1, 2])
    assert both.attrs["sun_zenith"] == 20.0 and both.attrs["photons"] == red.attrs["photons"]
    xr.testing.assert_identical(band_measurements(both, 0.672), red)
    xr.testing.assert_identical(band_measurements(both, 2.125), swir)  # within 0.01 micron
    xr.testing.assert_identical(stack_bands([band_measurements(both, w) for w in (0.672, 2.13)]),
                                both)
    with pytest.raises(MeasurementError, match=r"no band at 1.65 micron .*0.672, 2.13 micron"):
        band_measurements(both, 1.65)
    assert band_measurements(red, 0.672) is red  # one band: itself
    with pytest.raises(MeasurementError, match="one band, 0.672 micron"):
        band_measurements(red, 2.13)


def test_a_file_with_two_bands_round_trips(two_bands, tmp_path):
    both = stack_bands(list(two_bands))
    save_measurements(both, tmp_path / "bands.nc")
    back = load_measurements(tmp_path / "bands.nc")
    assert back["radiance"].dims == ("band", "view", "row", "col")
    np.testing.assert_array_equal(back["wavelength"].values, [0.672, 2.13])
    for name in ("radiance", "radiance_std_error", "radiance_noise_std", "ground_albedo"):
        np.testing.assert_array_equal(back[name].values, both[name].values)
    for one, w in zip(two_bands, (0.672, 2.13), strict=True):
        xr.testing.assert_identical(band_measurements(back, w), one)


def test_readers_of_one_band_refuse_several(two_bands):
    both = stack_bands(list(two_bands))
    for reader in (validate_measurements, lambda m: coarse_measurements(m, 2)):
        with pytest.raises(MeasurementError, match=r"2 bands \(0.672, 2.13 micron\).*"
                           "band_measurements"):
            reader(both)


def bad(both: xr.Dataset, change) -> xr.Dataset:
    out = both.copy(deep=True)
    change(out)
    return out


@pytest.mark.parametrize("change, message", [
    (lambda d: d.__setitem__("wavelength", ("band", [2.13, 0.672])),
     "wavelengths must be distinct and increasing, got 2.13, 0.672"),
    (lambda d: d.__setitem__("wavelength", ("band", [0.672, 0.672])),
     "distinct and increasing"),
    (lambda d: d.__setitem__("wavelength", ("band", [-0.672, 2.13])),
     "wavelengths must be positive"),
    (lambda d: d.attrs.update(wavelength=0.672), "not the attribute wavelength"),
    (lambda d: d["wavelength"].attrs.update(units="nm"), "multiply wavelength by 0.001"),
    (lambda d: d.__setitem__("fov", (("band", "view"), np.stack([d["fov"].values] * 2))),
     "fov varies over band: every band must have the same cameras and sun"),
    (lambda d: d.__setitem__("sun_zenith", ("band", [20.0, 30.0])), "same cameras and sun"),
    (lambda d: d.__setitem__("radiance_noise_std", d["radiance_noise_std"].isel(band=0)),
     "radiance_noise_std must be over"),
    (lambda d: d["radiance"].values[1].fill(np.nan), r"band 2.13 micron: every radiance pixel"),
    (lambda d: d["ground_albedo"].values.__setitem__(1, 2.0), r"band 2.13 micron: .*ground"),
])
def test_validation_refuses_a_bad_band_layout_in_one_line(two_bands, change, message):
    broken = bad(stack_bands(list(two_bands)), change)
    with pytest.raises(MeasurementError, match=message) as err:
        validate_measurements(broken, bands=True)
    assert "\n" not in str(err.value)


def test_no_wavelength_coordinate_is_refused(two_bands):
    both = stack_bands(list(two_bands))
    with pytest.raises(MeasurementError, match="coordinate wavelength over band"):
        validate_measurements(both.drop_vars("wavelength"), bands=True)


def test_stack_bands_refuses_what_is_not_one_set_of_cameras_and_sun(two_bands):
    red, swir = two_bands
    with pytest.raises(MeasurementError, match="two bands at one wavelength"):
        stack_bands([red, red])
    moved = swir.copy(deep=True)
    moved["position"].values[0, 2] += 0.1
    with pytest.raises(MeasurementError, match="position differs .*same cameras"):
        stack_bands([red, moved])
    other_sun = swir.assign_attrs(sun_zenith=40.0)
    with pytest.raises(MeasurementError, match="sun_zenith differs .*same sun"):
        stack_bands([red, other_sun])
    unlabelled = red.copy()
    unlabelled.attrs = {k: v for k, v in red.attrs.items() if k != "wavelength"}
    with pytest.raises(MeasurementError, match="records no wavelength"):
        stack_bands([unlabelled, swir])


# --- cloudct synth --bands, render --bands, and the retrieval's band --------------------


def thick_cloud() -> xr.Dataset:
    """A 6 x 6 x 4-cell block of LWC 2 g m-3, r_eff 20 micron (extinction about 150 /km,
    vertical optical depth about 24) in an 8 x 8 x 6 box of 40 m cells."""
    c = 0.02 + 0.04 * np.arange(8)
    lwc = np.zeros((8, 8, 6))
    lwc[1:7, 1:7, 1:5] = 2.0
    return microphysical_medium(c, c, c[:6], lwc, np.full(lwc.shape, 20.0))


@pytest.fixture(scope="module")
def synth_files(tmp_path_factory):
    """``synth --bands 0.672 2.13`` and the one-band ``synth`` of 0.672 micron with the same
    seeds, of :func:`thick_cloud` seen by nine 4 x 4 cameras (Mie optics: the combined
    estimator; 100 000 photons, a few seconds a band)."""
    folder = tmp_path_factory.mktemp("bands")
    medium = thick_cloud()
    save_medium(medium, folder / "cloud.nc")
    save_netcdf(scene_of(medium, npix=4).to_dataset(), folder / "scene.nc")
    common = [str(folder / "cloud.nc"), "--scene", str(folder / "scene.nc"), "--photons",
              "100000", "--seed", "7", "--noise-electrons", "5000", "--backend", "cpu"]
    assert main(["synth", *common, "--bands", "0.672", "2.13", "--ground-albedo", "0.1",
                 "0.05", "-o", str(folder / "bands.nc")]) == 0
    assert main(["synth", *common, "--optics", "mie", "--ground-albedo", "0.1",
                 "-o", str(folder / "red.nc")]) == 0
    return folder


def test_synth_bands_writes_a_valid_file_whose_first_band_is_the_one_band_synth(synth_files):
    bands = load_measurements(synth_files / "bands.nc")
    red = load_measurements(synth_files / "red.nc")
    np.testing.assert_array_equal(bands["wavelength"].values, [0.672, 2.13])
    assert bands.attrs["optics"] == "mie"  # the default of --bands
    np.testing.assert_array_equal(bands["seed"].values, [7, 8])  # band i: seed + i
    np.testing.assert_array_equal(bands["noise_seed"].values, [7, 8])
    np.testing.assert_array_equal(bands["ground_albedo"].values, [0.1, 0.05])
    first = band_measurements(bands, 0.672)
    for name in ("radiance", "radiance_std_error", "radiance_noise_std"):
        np.testing.assert_array_equal(first[name].values, red[name].values)  # bitwise
    assert Scene.from_dataset(first) == Scene.from_dataset(red)


def test_synth_bands_2_13_is_darker_than_0_672_on_the_lit_cloud(synth_files):
    """Droplets absorb at 2.13 micron (1 - omega = 0.046 at r_eff 20): the thick cloud's
    lit pixels (the central 2 x 2 of every view, all on the cloud) are darker (about half
    as bright). The standard error of the pixels' mean is bounded by the mean of the
    pixels' standard errors (the pixels of one render are correlated, and sd(sum) <= sum
    of sd whatever the correlation); the bands are independent (seeds 7 and 8). z > 3 on
    that bound is a one-sided test at 0.13 % or better. (The bound is dominated by the
    0.672 micron band's few pixels with Mie fireflies; pixel by pixel, every lit pixel is
    darker at 2.13 micron.)"""
    bands = load_measurements(synth_files / "bands.nc")
    lit = bands["radiance"].values[:, :, 1:3, 1:3].reshape(2, -1)
    error = bands["radiance_noise_std"].values[:, :, 1:3, 1:3].reshape(2, -1)
    assert np.all(lit[0] > 0.0)
    mean, bound = lit.mean(axis=1), error.mean(axis=1)
    z = (mean[0] - mean[1]) / np.hypot(*bound)
    print(f"lit mean 0.672: {mean[0]:.4f} +- {bound[0]:.4f}, 2.13: {mean[1]:.4f} +- "
          f"{bound[1]:.4f}, z = {z:.1f}")
    assert z > 3.0


def test_synth_refuses_bad_bands_and_albedos(synth_files, capsys):
    cloud, out = str(synth_files / "cloud.nc"), str(synth_files / "x.nc")
    assert main(["synth", cloud, "--bands", "2.13", "0.672", "-o", out]) == 2
    assert "distinct and increasing" in capsys.readouterr().err
    assert main(["synth", cloud, "--bands", "0.672", "2.13", "--ground-albedo", "0.1", "0.2",
                 "0.3", "-o", out]) == 2
    assert "one per band" in capsys.readouterr().err
    assert main(["synth", cloud, "--ground-albedo", "0.1", "0.2", "-o", out]) == 2
    assert "one value" in capsys.readouterr().err
    with pytest.raises(SystemExit):  # argparse: not both
        main(["synth", cloud, "--bands", "0.672", "--wavelength", "0.672", "-o", out])
    blob = synth_files / "blob.nc"
    save_medium(blob_cloud(8, 8, 6), blob)
    assert main(["synth", str(blob), "--bands", "0.672", "2.13", "-o", out]) == 2
    assert "microphysical" in capsys.readouterr().err
    assert not Path(out).exists()


def test_render_bands_writes_one_file_and_previews_per_band(synth_files, capsys):
    out = synth_files / "images.nc"
    assert main(["render", str(synth_files / "cloud.nc"), "--scene",
                 str(synth_files / "scene.nc"), "--bands", "0.672", "1.65", "--photons",
                 "2000", "--seed", "3", "-o", str(out)]) == 0
    assert "2 bands (0.672, 1.65 micron)" in capsys.readouterr().out
    images = load_measurements(out)
    np.testing.assert_array_equal(images["wavelength"].values, [0.672, 1.65])
    np.testing.assert_array_equal(images["seed"].values, [3, 4])
    assert images.attrs["optics"] == "mie"
    for w in ("0.672", "1.65"):
        assert (synth_files / "images" / f"band_{w}um" / "views.png").exists()
    assert main(["render", str(synth_files / "cloud.nc"), "--bands", "0.672", "--fluxes",
                 "-o", str(synth_files / "f.nc")]) == 2
    assert "--fluxes" in capsys.readouterr().err


def test_carve_and_retrieve_read_the_0_672_band(synth_files, capsys):
    bands = str(synth_files / "bands.nc")
    template = synth_files / "template.nc"
    save_medium(thick_cloud(), template)
    init = str(synth_files / "init.nc")
    assert main(["carve", bands, "--medium", str(template), "--optics", "hg", "-o", init,
                 "--fit-photons", "4000", "--backend", "cpu"]) == 0
    err = capsys.readouterr().err
    assert "holds the bands 0.672, 2.13 micron; the extinction retrieval reads the 0.672 " \
        "micron band" in err
    assert main(["retrieve", bands, "--init", init, "--iterations", "1", "--photons", "2000",
                 "--backend", "cpu", "-o", str(synth_files / "result.nc")]) == 0
    assert "reads the 0.672 micron band" in capsys.readouterr().err
    # a file without a band near 0.672 micron is refused, naming its bands
    swir = stack_bands([band_measurements(load_measurements(bands), 2.13)])
    save_measurements(swir, synth_files / "swir.nc")
    assert main(["carve", str(synth_files / "swir.nc"), "--medium", str(template),
                 "-o", str(synth_files / "x.nc")]) == 2
    err = capsys.readouterr().err
    assert "no band at 0.672 micron" in err and "hold 2.13 micron" in err
    assert err.count("\n") == 1


def test_the_schema_page_example_builds_a_file_with_bands(two_bands, tmp_path):
    """docs/measurements.md's first Python block, as it stands, given radiances over
    (band, view, row, col) and one wavelength per band."""
    page = (Path(__file__).resolve().parents[1] / "docs" / "measurements.md").read_text()
    namespace: dict = {}
    exec(compile(page.split("```python\n", 1)[1].split("```", 1)[0], "docs/measurements.md",
                 "exec"), namespace)
    red, swir = two_bands
    arrays = {name: red[name].values for name in ("position", "lookat", "up", "fov")}
    stacked = [np.stack([red[name].values, swir[name].values])
               for name in ("radiance", "radiance_noise_std")]
    m = namespace["measurement_set"](*stacked, **arrays, sun_zenith=20.0, sun_azimuth=30.0,
                                     wavelength=[0.672, 2.13])
    m.to_netcdf(tmp_path / "bands.nc")  # as another tool would write it
    back = load_measurements(tmp_path / "bands.nc")
    np.testing.assert_array_equal(back["wavelength"].values, [0.672, 2.13])
    np.testing.assert_array_equal(band_measurements(back, 2.13)["radiance"].values,
                                  swir["radiance"].values)
    with pytest.raises(MeasurementError, match="distinct and increasing"):
        namespace["measurement_set"](*stacked, **arrays, sun_zenith=20.0, sun_azimuth=30.0,
                                     wavelength=[2.13, 0.672])
