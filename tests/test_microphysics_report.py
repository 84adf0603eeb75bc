"""``cloudct report`` of a retrieval of LWC and r_eff (cloudct.retrieval.microphysics_report):
its errors against the truth by hand and against the retrieval's own
(MicrophysicsRetrieval.errors), its loss table, its figures, each band's re-render, and its
one-line refusals.

The result is built directly, as MicrophysicsRetrieval.result() writes it, on the tiny
cloud of test_microphysics_retrieval.py (a 4 x 4 x 3-cell cloud in a 6 x 6 x 5 grid, three
8 x 8 cameras, coarse Mie tables at 0.672 and 2.13 micron)."""

from __future__ import annotations

import json
from dataclasses import asdict

import numpy as np
import pytest
import xarray as xr
from test_microphysics_retrieval import (
    ANGLES,
    CLOUD,
    TABLE_REFF,
    TRUE_REFF,
    WAVELENGTHS,
    cloud_of,
    config,
    measured,
    scene,
)

from cloudct.cli import main
from cloudct.mc.render import render
from cloudct.mc.scene import Scene
from cloudct.mc.visibility import boundary_optical_distance
from cloudct.measurements import band_measurements, save_measurements
from cloudct.medium import save_medium
from cloudct.netcdf import save_netcdf
from cloudct.optics import to_optical
from cloudct.physics.mie import compute_mie_table
from cloudct.retrieval.config_file import config_to_toml
from cloudct.retrieval.microphysics import MicrophysicsRetrieval
from cloudct.retrieval.microphysics_report import (
    microphysics_errors,
    write_microphysics_report,
)

ITERATIONS = 3


@pytest.fixture(scope="module")
def tables():
    return [compute_mie_table(w, reff=TABLE_REFF, angles=ANGLES) for w in WAVELENGTHS]


@pytest.fixture(scope="module")
def truth():
    return cloud_of(0.2, TRUE_REFF)


@pytest.fixture(scope="module")
def measurements(tables, truth):
    return measured(truth, tables, 20_000)


def retrieved_medium() -> xr.Dataset:
    """The tiny cloud with LWC off by level and a voxel of water outside it, r_eff off by
    +2, -1 and -3 micron by level and by 1 micron more in one column."""
    medium = cloud_of(0.2, (8.0, 9.0, 12.0))
    lwc, reff = medium["lwc"].values, medium["reff"].values
    lwc[CLOUD] *= np.array([0.8, 1.0, 1.3])
    lwc[0, 0, 0], reff[0, 0, 0] = 0.05, 10.0
    reff[1, 1, 1:4] += 1.0
    return medium


@pytest.fixture(scope="module")
def result():
    """A result as MicrophysicsRetrieval.result() writes it, with a made-up log."""
    medium = retrieved_medium()
    cfg = config(iterations=ITERATIONS)
    ds = medium.assign_attrs(phase_truncation=3.0).assign_coords(
        iteration=np.arange(1, ITERATIONS + 1),
        wavelength=("band", np.array(WAVELENGTHS), {"units": "micron"}))
    falling = np.array([1.0, 0.7, 0.5])
    band_loss = np.outer(falling, [0.01, 0.03])
    logs = {"loss": band_loss.sum(axis=1), "loss_std_error": 0.1 * falling,
            "prior": np.zeros(3), "lwc_epsilon": 0.4 * falling, "lwc_delta": -0.1 * falling,
            "reff_absolute_error": 3 * falling, "reff_relative_error": 0.3 * falling,
            "reff_absolute_error_near": 2 * falling, "reff_relative_error_near": 0.2 * falling,
            "photons": np.full(3, 8000.0), "seconds": np.array([1.0, 2.0, 3.0])}
    for key, values in logs.items():
        ds[f"log_{key}"] = ("iteration", values)
    ds["log_band_loss"] = (("iteration", "band"), band_loss)
    ds["lwc_average"], ds["reff_average"] = 0.9 * ds["lwc"], ds["reff"]
    ds["cloud_mask"] = (("x", "y", "z"), (medium["lwc"].values > 0).astype(np.int8))
    return ds.assign_attrs(title="cloudct retrieval of LWC and r_eff", unknowns="lwc reff",
                           config=json.dumps(asdict(cfg)), config_toml=config_to_toml(cfg),
                           iterations_done=ITERATIONS, elapsed_s=3.0, reff_range=[4.0, 20.0],
                           backend="cpu", device="the CPU")


def test_the_report_gives_the_errors_figures_and_images(tmp_path, tables, truth,
                                                        measurements, result):
    """The errors by hand, over the true cloud and within optical distance 5 of its lit and
    viewed boundary in the shortest band's scene; the same as the retrieval's log takes them
    (MicrophysicsRetrieval.errors of the retrieved fields); the loss table; each band's
    image difference against a render of that band with its table; the figures."""
    summary = write_microphysics_report(result, tmp_path, truth=truth,
                                        measurements=measurements, render_photons=2000,
                                        mie_tables=tables).read_text()
    true_lwc, true_reff = truth["lwc"].values, truth["reff"].values
    lwc, reff = result["lwc"].values, result["reff"].values
    cloud = true_lwc > 0
    distance = boundary_optical_distance(to_optical(truth, tables[0], optics="mie"), scene())
    near = cloud & (distance < 5.0)
    assert 0 < near.sum() < cloud.sum()  # the near voxels are some of the cloud's
    error = np.abs(true_reff - reff)
    hand = {"lwc_epsilon": np.abs(true_lwc - lwc).sum() / true_lwc.sum(),
            "lwc_delta": (true_lwc.sum() - lwc.sum()) / true_lwc.sum(),
            "reff_absolute_error": error[cloud].mean(),
            "reff_relative_error": (error / np.where(cloud, true_reff, 1.0))[cloud].mean(),
            "reff_absolute_error_near": error[near].mean(),
            "reff_relative_error_near": (error / np.where(cloud, true_reff, 1.0))[near].mean()}
    errors = microphysics_errors(result, truth, distance)
    run = MicrophysicsRetrieval(measurements, retrieved_medium(), config(), truth=truth,
                                mie_tables=tables)
    for key, value in hand.items():
        assert errors[key] == pytest.approx(value, rel=1e-12), key
        assert run.errors()[key] == pytest.approx(value, rel=1e-12), key
    assert (f"| last iterate (lwc, reff) | {hand['lwc_epsilon']:.1%} | "
            f"{hand['lwc_delta']:+.1%} | {hand['reff_absolute_error']:.2f} | "
            f"{hand['reff_relative_error']:.1%} | {hand['reff_absolute_error_near']:.2f} | "
            f"{hand['reff_relative_error_near']:.1%} |") in summary
    average = 0.9 * lwc  # the made-up average: LWC x 0.9, r_eff the last iterate's
    assert (f"| ema average of the iterates (lwc_average, reff_average) | "
            f"{np.abs(true_lwc - average).sum() / true_lwc.sum():.1%} | "
            f"{(true_lwc.sum() - average.sum()) / true_lwc.sum():+.1%} | "
            f"{hand['reff_absolute_error']:.2f} |") in summary
    band_loss = result["log_band_loss"].values
    assert f"| 2.13 | {band_loss[0, 1]:.4g} | {band_loss[-1, 1]:.4g} |" in summary
    medium = retrieved_medium().assign_attrs(phase_truncation=3.0)
    for w, table in zip(WAVELENGTHS, tables, strict=True):
        band = band_measurements(measurements, w)
        images = render(to_optical(medium, table, optics="mie"), Scene.from_dataset(band),
                        photons=2000, progress=False)["radiance"].values
        measured = band["radiance"].values
        difference = np.abs(images - measured).sum() / np.abs(measured).sum()
        assert f"| {w:g} | {difference:.1%} | 2000 |" in summary
    for name in ("loss", "errors", "slices_lwc", "slices_reff", "images_0.672um",
                 "images_2.13um"):
        assert (tmp_path / f"{name}.png").stat().st_size > 1000, name


def test_the_command_line_reports_and_refuses_in_one_line(tmp_path, capsys, tables, truth,
                                                          measurements, result):
    """cloudct report RESULT --truth (no measurements: no distance, no images; the r_eff
    near errors shown as '-'); an optical truth, measurements without one of the result's
    bands, and a microphysical truth of an extinction result are refused in one line."""
    save_netcdf(result, tmp_path / "result.nc")
    save_medium(truth, tmp_path / "truth.nc")
    out = tmp_path / "report"
    assert main(["report", str(tmp_path / "result.nc"), "--truth", str(tmp_path / "truth.nc"),
                 "-o", str(out)]) == 0
    summary = (out / "summary.md").read_text()
    errors = microphysics_errors(result, truth)
    assert (f"| {errors['reff_absolute_error']:.2f} | {errors['reff_relative_error']:.1%} "
            "| - | - |") in summary
    assert sorted(p.name for p in out.glob("*.png")) == [
        "errors.png", "loss.png", "slices_lwc.png", "slices_reff.png"]
    capsys.readouterr()
    save_medium(to_optical(truth, tables[0], optics="mie"), tmp_path / "optical.nc")
    save_measurements(band_measurements(measurements, 0.672), tmp_path / "red.nc")
    extinction = to_optical(truth, tables[0], optics="mie").assign(
        log_loss=("iteration", [1.0]), log_seconds=("iteration", [1.0]))
    save_netcdf(extinction, tmp_path / "extinction.nc")
    for argv, message in (
            ([str(tmp_path / "result.nc"), "--truth", str(tmp_path / "optical.nc")],
             "its true medium must be microphysical (lwc, reff)"),
            ([str(tmp_path / "result.nc"), "--measurements", str(tmp_path / "red.nc")],
             "no band at 2.13 micron"),
            ([str(tmp_path / "extinction.nc"), "--truth", str(tmp_path / "truth.nc")],
             "holds none (lwc and reff): give the optical medium")):
        assert main(["report", *argv, "-o", str(tmp_path / "refused")]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "refused").exists()
