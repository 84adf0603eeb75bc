"""The retrieval of LWC and r_eff from several bands (cloudct.retrieval.microphysics,
``cloudct retrieve --unknowns lwc reff``): its loss and gradient over bands against the
per-band pieces it sums, a tiny retrieval that lowers the loss and the r_eff error, its
bounds, its refusals, the command line, and the r_eff terms and error metrics it uses.

The scene is tiny (a 4 x 4 x 3-cell cloud in a 6 x 6 x 5 grid of 50 m cells, three 8 x 8
cameras, coarse Mie tables at 0.672 and 2.13 micron) so that each test runs in seconds."""

from __future__ import annotations

import json

import numpy as np
import pytest
import xarray as xr

from cloudct.cli import main
from cloudct.mc.cameras import Camera
from cloudct.mc.microphysics_gradient import microphysics_gradient
from cloudct.mc.render import render
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.measurement_bands import stack_bands
from cloudct.measurements import band_measurements, synthesize_measurements
from cloudct.medium import microphysical_medium, optical_medium, save_medium
from cloudct.netcdf import save_netcdf
from cloudct.optics import to_optical
from cloudct.physics.microphysics import cloud_extinction
from cloudct.physics.mie import compute_mie_table
from cloudct.retrieval.config import RetrievalConfig
from cloudct.retrieval.loop import Retrieval
from cloudct.retrieval.loss import image_loss, pixel_weights
from cloudct.retrieval.metrics import reff_absolute_error, reff_relative_error
from cloudct.retrieval.microphysics import (
    BandsLossGradient,
    MicrophysicsRetrieval,
    loss_and_gradient_over_bands,
)
from cloudct.retrieval.microphysics_first_guess import (
    brightness_reff,
    first_guess,
    microphysical_first_guess,
    stage_attrs,
)
from cloudct.retrieval.priors import Prior, PriorGrid, reff_growth, reff_smoothness

WAVELENGTHS = (0.672, 2.13)
TABLE_REFF = [4.0, 7.0, 10.0, 13.0, 16.0, 20.0]
ANGLES = [0.0, 1.0, 2.0, 4.0, 8.0, 15.0, 30.0, 60.0, 90.0, 120.0, 140.0, 160.0, 175.0, 180.0]
CLOUD = (slice(1, 5), slice(1, 5), slice(1, 4))
#: r_eff of the true cloud's three levels [micron]: droplets grow with height
TRUE_REFF = (6.0, 10.0, 15.0)


@pytest.fixture(scope="module")
def tables():
    """Coarse Mie tables of the two bands (r_eff 4-20 micron)."""
    return [compute_mie_table(w, reff=TABLE_REFF, angles=ANGLES) for w in WAVELENGTHS]


def cloud_of(lwc: float, reff) -> xr.Dataset:
    """A 4 x 4 x 3-cell cloud of ``lwc`` [g m-3] and r_eff per level ``reff`` [micron]."""
    axis = (np.arange(6) + 0.5) * 0.05
    lwc_field = np.zeros((6, 6, 5))
    lwc_field[CLOUD] = lwc
    reff_field = np.zeros_like(lwc_field)
    reff_field[CLOUD] = np.asarray(reff, dtype=float)[None, None, :]
    return microphysical_medium(axis, axis, axis[:5] + 0.5, lwc_field, reff_field,
                                air_extinction=0.04).assign_attrs(optics="mie")


def scene() -> Scene:
    c = (0.15, 0.15, 0.65)
    return Scene([Camera((0.15, 0.15, 1.6), c, (0, 1, 0), fov=25.0, nrows=8, ncols=8),
                  Camera((0.9, 0.15, 1.3), c, (0, 0, 1), fov=30.0, nrows=8, ncols=8),
                  Camera((0.15, -0.6, 1.3), c, (0, 0, 1), fov=30.0, nrows=8, ncols=8)],
                 Sun(zenith=20.0, azimuth=30.0), "open")


@pytest.fixture(scope="module")
def truth():
    return cloud_of(0.2, TRUE_REFF)


def measured(cloud: xr.Dataset, tables, photons: int) -> xr.Dataset:
    """``cloud``'s images in both bands, ``photons`` forward photons each (band i: seed i)."""
    return stack_bands([
        synthesize_measurements(to_optical(cloud, table, optics="mie"), scene(),
                                photons=photons, seed=i, method="forward", wavelength=w)
        for i, (table, w) in enumerate(zip(tables, WAVELENGTHS, strict=True))])


@pytest.fixture(scope="module")
def measurements(tables, truth):
    """The true cloud's images in both bands, 200 000 forward photons each."""
    return measured(truth, tables, 200_000)


def config(**settings) -> RetrievalConfig:
    """The tests' settings: the score function (its tiny retrieval lowers r_eff's error
    within 10 iterations; sample matching, the default, is set where a test names it)."""
    base = dict(unknowns=("lwc", "reff"), photons=3000, stages=(1,), image_photons=(1.0,),
                lwc_step=0.005, reff_step=1.0, priors=(), estimator=("score",))
    return RetrievalConfig(**{**base, **settings})


@pytest.mark.parametrize(("estimator", "pixel_sampling"),
                         [("score", "uniform"), ("sm", "residual")])
def test_the_loss_and_gradient_over_bands_are_the_sums_of_each_bands(
        tables, truth, measurements, estimator, pixel_sampling):
    """Each band: its images (seed 2 (seed + b)), its weighted loss and residual
    (image_loss) and microphysics_gradient (seed 2 (seed + b) + 1, the estimator asked) with
    its table: the function's loss, gradients and standard errors are their sums (in
    quadrature)."""
    start = cloud_of(0.3, (10.0, 10.0, 10.0))
    bands = [band_measurements(measurements, w) for w in WAVELENGTHS]
    asked = dict(estimator=estimator, pixel_sampling=pixel_sampling)
    ev = loss_and_gradient_over_bands(start, bands, tables, photons=2000,
                                      gradient_photons=1000, seed=4, **asked)
    loss, gradient, variance = 0.0, {"lwc": 0.0, "reff": 0.0}, {"lwc": 0.0, "reff": 0.0}
    for b, (band, table) in enumerate(zip(bands, tables, strict=True)):
        images = render(to_optical(start, table, optics="mie"), scene(), photons=2000,
                        seed=2 * (4 + b), progress=False)
        band_loss, residual = image_loss(images["radiance"].values, band["radiance"].values,
                                         pixel_weights(band))
        assert ev.band_losses[b] == band_loss
        loss += band_loss
        mean, std_error, _ = microphysics_gradient(start, scene(), residual, photons=1000,
                                                   mie_table=table, seed=2 * (4 + b) + 1,
                                                   progress=False, **asked)
        for name in gradient:
            gradient[name] = gradient[name] + mean[name]
            variance[name] = variance[name] + std_error[name] ** 2
    assert ev.loss == pytest.approx(loss, rel=1e-14)
    for name in gradient:
        np.testing.assert_allclose(ev.gradient[name], gradient[name], rtol=1e-13, atol=0.0)
        np.testing.assert_allclose(ev.std_error[name], np.sqrt(variance[name]), rtol=1e-13)


@pytest.fixture(scope="module")
def retrieval(tables, truth, measurements):
    """Ten iterations from 1.5 x the true LWC with r_eff 10 micron everywhere in the
    cloud, 6000 gradient photons each."""
    start = cloud_of(0.3, (10.0, 10.0, 10.0))
    run = MicrophysicsRetrieval(measurements, start,
                                config(iterations=10, photons=6000, lwc_step=0.01),
                                truth=truth, mie_tables=tables)
    start_error = run.errors()["reff_absolute_error"]
    return start, start_error, run, run.run(progress=False)


def test_a_retrieval_lowers_the_loss_and_the_reff_error(retrieval, tables, truth):
    """The r_eff error's mean over the last three iterations is below 0.9 x the start's
    (3 micron), and the loss, evaluated with the combined estimator's images (no fireflies)
    at three seeds, common to the start and the end, falls by more than three standard
    errors of the seeds' differences."""
    start, start_error, run, result = retrieval
    assert start_error == pytest.approx(3.0)
    assert np.mean(result["log_reff_absolute_error"].values[-3:]) < 0.9 * start_error
    differences = []
    for seed in range(3):
        first, last = (loss_and_gradient_over_bands(m, run.bands, tables, photons=4000,
                                                    gradient_photons=32, seed=100 + 10 * seed,
                                                    method="combined").loss
                       for m in (start, run.medium()))
        differences.append(first - last)
    mean = np.mean(differences)
    assert mean > 3.0 * np.std(differences, ddof=1) / np.sqrt(3), differences


def test_the_result_holds_lwc_reff_and_the_log(retrieval):
    _, _, run, result = retrieval
    assert result["lwc"].attrs["units"] == "g m-3" and result["reff"].attrs["units"] == "micron"
    assert result.sizes["iteration"] == 10 and result["log_band_loss"].shape == (10, 2)
    np.testing.assert_allclose(result["log_band_loss"].sum("band"), result["log_loss"])
    np.testing.assert_array_equal(result["wavelength"].values, WAVELENGTHS)
    for name in ("lwc_epsilon", "lwc_delta", "reff_relative_error",
                 "reff_absolute_error_near", "reff_relative_error_near"):
        assert np.all(np.isfinite(result[f"log_{name}"].values)), name
    for name in ("lwc", "reff"):  # the default: an exponential moving average
        average = result[f"{name}_average"].values
        assert np.all(average[~run.mask] == 0.0) and np.all(average[run.mask] > 0.0)
    assert result.attrs["unknowns"] == "lwc reff"
    assert RetrievalConfig(**json.loads(result.attrs["config"])) == run.config


def constant_gradient(lwc_slope: float, reff_slope: float, traced: list | None = None):
    """A stand-in for loss_and_gradient_over_bands: loss 1 +- 0.01 and the gradients
    ``lwc_slope`` and ``reff_slope`` everywhere, without noise; each call's photons are
    appended to ``traced``."""

    def evaluate(medium, bands, tables, *, photons, gradient_photons, **_):
        if traced is not None:
            traced.append((photons, gradient_photons))
        ones = np.ones(medium["lwc"].shape)
        return BandsLossGradient(1.0, np.array([0.5, 0.5]), 0.01,
                                 {"lwc": lwc_slope * ones, "reff": reff_slope * ones},
                                 {"lwc": 0.0 * ones, "reff": 0.0 * ones},
                                 {"wall_time": 0.0, "photons": 0})

    return evaluate


def test_the_schedule_grows_the_photons_then_decays_both_steps(monkeypatch, tables,
                                                               measurements):
    """A loss flat at its noise (1 +- 0.01) and a constant gradient (-1 in LWC, +1 in
    r_eff): after each window of 5 iterations the noise schedule finds a plateau; the
    photons of both evaluations double to their cap (4x), then both fields' steps halve to
    their floor (0.25), then the run says it is at its floor. Adam moves each voxel by its
    step when the gradient is constant, so the fields move by exactly the logged steps,
    and the uniform iterate average restarts at each change of step."""
    traced = []
    monkeypatch.setattr("cloudct.retrieval.microphysics.loss_and_gradient_over_bands",
                        constant_gradient(-1.0, 1.0, traced))
    start = cloud_of(0.2, (12.0, 12.0, 12.0))
    run = MicrophysicsRetrieval(
        measurements, start,
        config(iterations=26, photons=1000, saturation_window=5, photon_growth=2.0,
               photon_cap=4.0, step_decay=0.5, step_floor=0.25, averaging="uniform",
               lwc_step=0.01, reff_step=0.1), mie_tables=tables)
    result = run.run(progress=False)
    photons = [1000] * 5 + [2000] * 5 + [4000] * 16
    assert traced == [(p, p) for p in photons]
    steps = np.array([1.0] * 15 + [0.5] * 5 + [0.25] * 6)
    np.testing.assert_array_equal(result["log_step"].values, steps)
    np.testing.assert_array_equal(result["log_photons"].values, 2 * 2 * np.array(photons))
    what = [d["what"] for d in json.loads(result.attrs["decisions"])]
    assert what == ["photons 1000 -> 2000", "photons 2000 -> 4000",
                    "step x 0.5 (now 0.5 of its start)", "step x 0.5 (now 0.25 of its start)",
                    "no further change: the loss is at its noise floor"]
    mask = run.mask
    moved = 0.01 * steps.sum()
    np.testing.assert_allclose(result["lwc"].values[mask], 0.2 + moved, rtol=1e-6)
    np.testing.assert_allclose(result["reff"].values[mask], 12.0 - 10 * moved, rtol=1e-6)
    # the average of the six iterates at step 0.25: 2.5 of those steps behind the last
    np.testing.assert_allclose(result["lwc_average"].values[mask],
                               0.2 + moved - 2.5 * 0.0025, rtol=1e-6)
    assert np.all(result["lwc_average"].values[~mask] == 0.0)


def test_holding_the_extinction_moves_reff_alone_and_lwc_along_it(monkeypatch, tables,
                                                                  measurements):
    """hold_extinction: one SGD step on the constant gradients a = dL/dLWC = 0.3 and b =
    dL/dr_eff = 0.02 (with a heavy L1 term on the extinction, which has nothing to move
    while it is held) moves r_eff by -step (b + a dLWC/dr_eff), the derivative at fixed
    0.672 micron extinction taken here by central differences of LWC = beta / e(r_eff);
    LWC follows, so that the extinction stays the first guess's to rounding."""
    monkeypatch.setattr("cloudct.retrieval.microphysics.loss_and_gradient_over_bands",
                        constant_gradient(0.3, 0.02))
    start = cloud_of(0.2, (12.0, 12.0, 12.0))
    held = config(iterations=1, optimizer="sgd", reff_step=2.0, hold_extinction=True,
                  gradient_smoothing=(0.0,),
                  priors=(Prior("l1", 1e3, "fixed"),))
    result = MicrophysicsRetrieval(measurements, start, held, mie_tables=tables).run(
        progress=False)
    beta = cloud_extinction(start["lwc"].values, start["reff"].values, tables[0])[CLOUD]

    def lwc_at(reff: float) -> np.ndarray:
        return beta / cloud_extinction(1.0, reff, tables[0])

    slope = (lwc_at(12.001) - lwc_at(11.999)) / 0.002  # e(r_eff): linear on 10-13 micron
    np.testing.assert_allclose(result["reff"].values[CLOUD], 12.0 - 2.0 * (0.02 + 0.3 * slope),
                               rtol=1e-9)
    np.testing.assert_allclose(cloud_extinction(result["lwc"].values, result["reff"].values,
                                                tables[0])[CLOUD], beta, rtol=1e-12)
    assert np.all(result["lwc"].values[CLOUD] < 0.2)  # less water (dL/dLWC > 0): smaller r_eff
    # an extinction stage that took the whole time limit leaves no iteration: the start
    none = MicrophysicsRetrieval(measurements, start, config(time_limit=0.0),
                                 mie_tables=tables).run(progress=False)
    assert none.sizes["iteration"] == 0 and none["log_band_loss"].shape == (0, 2)
    np.testing.assert_array_equal(none["lwc"].values, start["lwc"].values)


def test_the_extinction_stage_starts_lwc_and_reff(tables, truth, measurements):
    """extinction_share 0.5 of 4 iterations: the extinction at 0.672 micron is retrieved
    for 2 iterations from a stand-in for the carving (the true extinction x 0.7); the
    first guess holds its iterate average as LWC at one fitted r_eff, its mask is that
    run's, and the retrieval of LWC and r_eff gets the 2 iterations left."""
    optical = to_optical(truth, tables[0], optics="mie")
    carved = optical.assign(cloud_extinction=0.7 * optical["cloud_extinction"])
    guess = first_guess(measurements, carved,
                        config(iterations=4, extinction_share=0.5, iteration_seconds=0.2),
                        table=tables[0], band_table=tables[1])
    stage = guess.extinction_result
    assert stage.sizes["iteration"] == 2 and guess.config.iterations == 2
    assert stage["log_epsilon"].isnull().all()  # no truth given
    extinction = stage["cloud_extinction_average"].transpose("x", "y", "z").values
    lwc, reff = (guess.medium[name].transpose("x", "y", "z").values for name in ("lwc", "reff"))
    np.testing.assert_allclose(cloud_extinction(lwc, reff, tables[0]), extinction, rtol=1e-12)
    assert np.all(reff[extinction > 0] == guess.reff) and tables[0]["reff"][0] <= guess.reff
    np.testing.assert_array_equal(guess.mask, stage["cloud_mask"].values.astype(bool))
    assert stage_attrs(guess)["extinction_stage_iterations"] == 2
    # a share of 1: the extinction takes every iteration, none is left to LWC and r_eff
    whole = first_guess(measurements, carved,
                        config(iterations=2, extinction_share=1.0, iteration_seconds=0.2),
                        table=tables[0], band_table=tables[1])
    assert whole.extinction_result.sizes["iteration"] == 2 and whole.config.iterations == 0


def test_the_steps_keep_the_bounds(tables, truth, measurements):
    """Large steps from a start that fills more than the mask: r_eff stays within the
    tables' range (and reaches its ends), LWC >= 0 (and reaches 0), both 0 outside the
    mask."""
    start = cloud_of(0.2, (10.0, 10.0, 10.0))
    start["lwc"].values[0, :, :] = 0.3  # outside the mask below
    start["reff"].values[0, :, :] = 12.0
    mask = truth["lwc"].values > 0
    run = MicrophysicsRetrieval(measurements, start, config(iterations=3, lwc_step=0.3,
                                                            reff_step=8.0),
                                mask=mask, mie_tables=tables)
    result = run.run(progress=False)
    lwc, reff = result["lwc"].values, result["reff"].values
    assert np.all(lwc[~mask] == 0.0) and np.all(reff[~mask] == 0.0)
    assert lwc.min() == 0.0 and np.any(lwc[mask] == 0.0)
    assert reff[mask].min() >= 4.0 and reff[mask].max() <= 20.0
    assert np.any(np.isin(reff[mask], (4.0, 20.0)))


def test_bad_inputs_are_refused_in_one_line(tables, truth, measurements):
    one_band = band_measurements(measurements, 0.672)
    with pytest.raises(ValueError, match=r"several bands.*one band \(0.672 micron\)"):
        MicrophysicsRetrieval(one_band, truth, config(), mie_tables=tables[:1])
    optical = to_optical(truth, tables[0], optics="mie")
    bare = optical_medium(optical["x"].values, optical["y"].values, optical["z"].values,
                          optical["cloud_extinction"].values)
    with pytest.raises(ValueError, match="start from a microphysical medium"):
        MicrophysicsRetrieval(measurements, bare, config(), mie_tables=tables)
    with pytest.raises(ValueError, match="recycling 'fixed': path recycling is not supported"):
        config(recycling="fixed")
    with pytest.raises(ValueError, match="photons 'auto'"):
        config(photons="auto")
    with pytest.raises(ValueError, match="prior reff_smoothness is a term in r_eff"):
        RetrievalConfig(priors=({"term": "reff_smoothness", "weight": 0.01},))
    with pytest.raises(ValueError, match="unknowns must be one of"):
        RetrievalConfig(unknowns=("lwc",))
    with pytest.raises(ValueError, match="MicrophysicsRetrieval's"):
        Retrieval(one_band, optical, config())


def test_the_configured_estimator_differentiates_the_extinction(monkeypatch, tables,
                                                                measurements):
    """The configured estimator reaches every band's gradient, with the pixels drawn by
    residual (a camera-side estimator's default); sample matching is the default."""
    default = RetrievalConfig(unknowns=("lwc", "reff"), photons=3000)
    assert default.estimator == ("sm",) and default.pixel_sampling == "residual"
    assert config().pixel_sampling == "uniform"
    asked = []

    def spy(*args, **kwargs):
        asked.append((kwargs["estimator"], kwargs["pixel_sampling"]))
        return loss_and_gradient_over_bands(*args, **kwargs)

    monkeypatch.setattr("cloudct.retrieval.microphysics.loss_and_gradient_over_bands", spy)
    run = MicrophysicsRetrieval(measurements, cloud_of(0.3, (10.0, 10.0, 10.0)),
                                config(iterations=2, estimator=("sm",)), mie_tables=tables)
    result = run.run(progress=False)
    assert asked == [("sm", "residual")] * 2
    assert np.isfinite(result["lwc"].values).all() and np.isfinite(result["reff"].values).all()


def test_the_first_guess_holds_the_extinction_as_lwc(tables, truth):
    optical = to_optical(truth, tables[0], optics="mie")
    guess = microphysical_first_guess(optical, tables[0], reff=10.0)
    cloudy = truth["lwc"].values > 0
    np.testing.assert_array_equal(guess["reff"].values, np.where(cloudy, 10.0, 0.0))
    back = to_optical(guess, tables[0], optics="mie")["cloud_extinction"].values
    np.testing.assert_allclose(back, optical["cloud_extinction"].values, rtol=1e-12)
    assert float(guess["air_extinction"]) == pytest.approx(0.04)  # given at 0.672 micron
    with pytest.raises(ValueError, match="the Mie table at 2.13"):
        microphysical_first_guess(optical, tables[1])


def test_the_command_line_retrieves_lwc_and_reff(tmp_path, capsys, truth):
    """cloudct synth --bands 0.672 1.65 2.13 of the tiny cloud, then cloudct retrieve
    --unknowns lwc reff from its carved start: lwc and reff written; its refusals."""
    save_medium(truth, tmp_path / "cloud.nc")
    save_netcdf(scene().to_dataset(), tmp_path / "scene.nc")
    bands = str(tmp_path / "bands.nc")
    assert main(["synth", str(tmp_path / "cloud.nc"), "--scene", str(tmp_path / "scene.nc"),
                 "--bands", "0.672", "1.65", "2.13", "--photons", "20000", "--backend",
                 "cpu", "-o", bands]) == 0
    common = [bands, "--unknowns", "lwc", "reff", "--medium", str(tmp_path / "cloud.nc"),
              "--photons", "1000", "--backend", "cpu"]
    out = tmp_path / "result.nc"
    assert main(["retrieve", *common, "--iterations", "2", "--truth",
                 str(tmp_path / "cloud.nc"), "-o", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    result = xr.load_dataset(out)
    assert result["lwc"].attrs["units"] == "g m-3" and result["reff"].attrs["units"] == "micron"
    assert result.sizes["iteration"] == 2 and result.sizes["band"] == 3
    assert result.attrs["extinction_stage_iterations"] == 0
    # the extinction first: 2 of 4 iterations, then r_eff at that extinction
    assert main(["retrieve", *common, "--iterations", "4", "--extinction-share", "0.5",
                 "--iteration-seconds", "0.2", "-o", str(tmp_path / "staged.nc")]) == 0
    assert "retrieving the extinction at 0.672 micron first" in capsys.readouterr().out
    staged = xr.load_dataset(tmp_path / "staged.nc")
    assert staged.attrs["extinction_stage_iterations"] == 2 and staged.sizes["iteration"] == 2
    assert json.loads(staged.attrs["config"])["hold_extinction"] is True
    assert np.all(np.isfinite(result["log_reff_absolute_error"].values))
    for extra, message in ((["--recycling", "fixed"], "path recycling is not supported"),
                           (["--resume"], "--resume: the retrieval of --unknowns lwc reff "
                            "writes no checkpoint"),
                           (["--photons", "auto"], "photons 'auto'")):
        assert main(["retrieve", *common, *extra, "-o", str(tmp_path / "x.nc")]) == 2
        err = capsys.readouterr().err
        assert message in err and err.count("\n") == 1, err
    one = tmp_path / "red.nc"
    assert main(["synth", str(tmp_path / "cloud.nc"), "--scene", str(tmp_path / "scene.nc"),
                 "--optics", "mie", "--photons", "2000", "--backend", "cpu", "-o",
                 str(one)]) == 0
    capsys.readouterr()
    assert main(["retrieve", str(one), *common[1:], "-o", str(tmp_path / "x.nc")]) == 2
    err = capsys.readouterr().err
    assert "need measurements in several bands" in err and err.count("\n") == 1, err
    assert not (tmp_path / "x.nc").exists()


# --- the r_eff terms and the r_eff errors, by hand -----------------------------------------


def test_the_reff_terms_by_hand():
    """Two columns of 20 m x 20 m cells 40 m apart vertically: the r_eff terms count only
    neighbours that both hold droplets, with their hand-computed values and gradients."""
    x = np.array([0.01, 0.03])
    medium = optical_medium(x, np.array([0.01, 0.03]), np.array([0.02, 0.06, 0.10]),
                            np.zeros((2, 2, 3)))
    grid = PriorGrid.of(medium)
    reff = np.zeros((2, 2, 3))
    reff[0, 0, :] = [12.0, 10.0, 0.0]  # falls by 2 going up, then a clear cell
    reff[1, 0, :] = [9.0, 10.0, 11.0]  # beside the first column at the two lower levels
    area_z, area_x = 0.02 * 0.02, 0.02 * 0.04
    # pairs: vertical (12, 10) and (9, 10), (10, 11); horizontal (12, 9), (10, 10)
    expected = (area_z * (4 + 1 + 1) / (2 * 0.04) + area_x * 9 / (2 * 0.02))
    value, gradient = reff_smoothness(reff, grid)
    assert value == pytest.approx(expected, rel=1e-12)
    assert gradient[0, 0, 0] == pytest.approx(area_z * 2 / 0.04 + area_x * 3 / 0.02)
    assert gradient[0, 0, 2] == 0.0 and gradient[0, 1, 0] == 0.0  # clear cells
    value, gradient = reff_growth(reff, grid)
    assert value == pytest.approx(area_z * 4 / (2 * 0.04), rel=1e-12)
    np.testing.assert_allclose(gradient[0, 0], [area_z * 2 / 0.04, -area_z * 2 / 0.04, 0.0])
    assert not gradient[1].any()
    for term in (reff_smoothness, reff_growth):  # the gradient is that of the value
        h, direction = 1e-6, np.where(reff > 0, np.random.default_rng(1).normal(size=reff.shape),
                                      0.0)
        fd = (term(reff + h * direction, grid)[0] - term(reff - h * direction, grid)[0]) / (2 * h)
        assert fd == pytest.approx(np.sum(term(reff, grid)[1] * direction), rel=1e-6)


def test_the_extinction_terms_act_on_the_reference_extinction_of_lwc(tables, truth,
                                                                      measurements):
    """The extinction's terms (l1, Huber smoothness) of the unknowns LWC and r_eff: Phi of
    e_0 LWC, e_0 the shortest band's extinction per unit LWC at 10 micron; its gradient in
    LWC against central differences of its value (Huber's rho is quadratic near each
    point, so the difference's error is rounding alone), none in r_eff."""
    terms = ({"term": "l1", "weight": 0.01, "schedule": "fixed"},
             {"term": "smoothness", "weight": 1e-3, "schedule": "fixed",
              "options": {"huber": 50.0}})
    run = MicrophysicsRetrieval(measurements, truth, config(priors=terms), mie_tables=tables)
    e_0 = float(tables[0]["ext_per_lwc"].interp(reff=10.0))
    assert run.reference_extinction == pytest.approx(e_0, rel=1e-12)
    run.lwc = run.lwc * np.random.default_rng(2).uniform(0.5, 1.5, run.lwc.shape)
    value, gradient = run.prior()
    assert np.all(gradient["reff"] == 0.0)
    lwc = run.lwc.copy()
    for voxel in ((2, 2, 1), (1, 3, 2), (4, 1, 3)):
        sides = []
        for sign in (1.0, -1.0):
            run.lwc = lwc.copy()
            run.lwc[voxel] += sign * 1e-4
            sides.append(run.prior()[0])
        fd = (sides[0] - sides[1]) / 2e-4
        assert fd == pytest.approx(gradient["lwc"][voxel], rel=1e-6, abs=1e-9 * abs(value))


def test_the_reff_errors_by_hand():
    truth_lwc = np.array([0.0, 0.2, 0.4, 0.1])
    truth_reff = np.array([5.0, 8.0, 12.0, 16.0])
    reff = np.array([20.0, 10.0, 9.0, 16.0])  # the clear voxel does not count
    assert reff_absolute_error(truth_lwc, truth_reff, reff) == pytest.approx(5.0 / 3.0)
    assert reff_relative_error(truth_lwc, truth_reff, reff) == pytest.approx(
        (2 / 8 + 3 / 12 + 0) / 3)
    near = np.array([True, True, False, False])
    assert reff_absolute_error(truth_lwc, truth_reff, reff, near) == pytest.approx(2.0)
    assert np.isnan(reff_relative_error(truth_lwc, truth_reff, reff, np.zeros(4, bool)))
    with pytest.raises(ValueError, match="true LWC is zero everywhere"):
        reff_absolute_error(np.zeros(4), truth_reff, reff)


def test_the_first_guess_r_eff_renders_the_longest_band_as_bright_as_measured(tables):
    """A thick cloud of one r_eff (12 micron) seen in both bands, its visible extinction
    known: the fitted constant is that r_eff within 3 sigma, sigma = the standard error of
    the log of the measured and of the fit's summed 2.13 micron radiance (independent
    photons) over |d log B / d log r_eff| (a central difference of the fit's renders at
    10.5 and 13.5 micron, common random numbers), plus the bisection's resolution."""
    reff, fit = 12.0, dict(photons=20_000, seed=3)
    truth = cloud_of(1.0, (reff,) * 3)
    bands = measured(truth, tables, 100_000)
    visible = to_optical(truth, tables[0], optics="mie")
    fitted = brightness_reff(visible, bands, tables[0], band_table=tables[1],
                             phase_truncation=0.0, scan=5, steps=6, **fit)

    def summed(r):
        images = render(to_optical(microphysical_first_guess(visible, tables[0], r),
                                   tables[1], optics="mie"), scene(), progress=False, **fit)
        return (images["radiance"].values.sum(),
                np.sqrt(np.sum(images["radiance_std_error"].values ** 2)))

    longest = band_measurements(bands, WAVELENGTHS[1])
    log_errors = [np.sqrt(np.sum(longest["radiance_std_error"].values ** 2))
                  / longest["radiance"].values.sum()]
    value, error = summed(reff)
    log_errors.append(error / value)
    slope = np.log(summed(13.5)[0] / summed(10.5)[0]) / np.log(13.5 / 10.5)
    assert slope < -0.1, slope  # the band darkens as r_eff grows: the fit has a signal
    sigma = np.hypot(*log_errors) / abs(slope)
    resolution = np.log(20.0 / 4.0) / 4 / 2**6  # the last bracket's half width
    print(f"fitted {fitted:.3f} micron, sigma {sigma * reff:.3f} micron, slope {slope:.3f}")
    assert abs(np.log(fitted / reff)) < 3.0 * sigma + resolution
