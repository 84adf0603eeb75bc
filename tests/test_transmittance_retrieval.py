"""Retrieving under either transmittance assumption from the same measurements
(``RetrievalConfig.transmittance``, ``cloudct retrieve --transmittance``): measurements
record the model they were made under, ``medium`` retrieves under it (the score function,
the one estimator that differentiates it), ``exponential`` under exp(-tau)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import xarray as xr
from test_retrieval import initial_guess
from test_score_gradient import gradient_medium, gradient_scene

from cloudct.cli import main
from cloudct.measurements import (
    MeasurementError,
    load_measurements,
    measured_transmittance,
    save_measurements,
    synthesize_measurements,
)
from cloudct.medium import MediumError, save_medium, transmittance_model, with_transmittance
from cloudct.retrieval.config import RetrievalConfig
from cloudct.retrieval.config_file import config_to_toml, parse_config
from cloudct.retrieval.loop import Retrieval, run_id
from cloudct.retrieval.metrics import epsilon_delta

A = 1.0  # the power law's shape: strongly non-exponential (relative variance 1)


def power_law_truth() -> xr.Dataset:
    return with_transmittance(gradient_medium(), "gamma", A)


@pytest.fixture(scope="module")
def power_law_measurements() -> xr.Dataset:
    return synthesize_measurements(power_law_truth(), gradient_scene(), photons=2_000_000,
                                   seed=77, progress=False)


def test_measurements_record_their_transmittance_model(tmp_path, power_law_measurements):
    ds = power_law_measurements
    assert ds.attrs["transmittance"] == "gamma" and float(ds["transmittance_mode"]) == A
    save_measurements(ds, tmp_path / "m.nc")
    family, mode = measured_transmittance(load_measurements(tmp_path / "m.nc"))
    assert family == "gamma" and float(mode) == A
    # a mode field comes with the medium's grid
    field = np.resize([0.5, 2.0, np.inf], gradient_medium()["cloud_extinction"].shape)
    truth = with_transmittance(gradient_medium(), "gamma", field)
    ds = synthesize_measurements(truth, gradient_scene(), photons=2000, batches=4,
                                 progress=False)
    save_measurements(ds, tmp_path / "field.nc")
    family, mode = measured_transmittance(load_measurements(tmp_path / "field.nc"))
    np.testing.assert_array_equal(mode.values, field)
    np.testing.assert_array_equal(mode["x"].values, truth["x"].values)
    # without a model: exponential, and nothing is written
    plain = synthesize_measurements(gradient_medium(), gradient_scene(), photons=2000,
                                    batches=4, progress=False)
    assert "transmittance" not in plain.attrs and "transmittance_mode" not in plain
    assert measured_transmittance(plain) == ("exponential", None)
    with pytest.raises(MeasurementError, match="transmittance must be one of"):
        save_measurements(ds.assign_attrs(transmittance="fractal"), tmp_path / "bad.nc")
    with pytest.raises(MeasurementError, match="must be > 0"):
        save_measurements(ds.assign(transmittance_mode=-ds["transmittance_mode"]),
                          tmp_path / "bad.nc")


def test_the_settings_of_the_assumption_are_checked():
    model = RetrievalConfig(transmittance="medium")
    assert model.estimator == ("score",) and model.pixel_sampling == "uniform"
    assert RetrievalConfig().estimator == ("sm",)
    assert RetrievalConfig(transmittance="medium", estimator=("drt",)).estimator == ("drt",)
    for bad in (dict(estimator=("sm",)), dict(recycling="fixed"), dict(optimizer="lbfgsb")):
        with pytest.raises(ValueError, match="differentiated by the estimators 'score' or "
                                             "'drt' alone"):
            RetrievalConfig(transmittance="medium", **bad)
    with pytest.raises(ValueError, match="transmittance must be one of"):
        RetrievalConfig(transmittance="gamma")
    # the key round-trips through the configuration file, and only fingerprints where it acts
    assert parse_config(config_to_toml(model), "f")["transmittance"] == "medium"
    measured = xr.Dataset({"radiance": (("view", "row", "col"), np.zeros((1, 2, 2)))})
    assert run_id(measured, RetrievalConfig(estimator=("score",))) != run_id(measured, model)
    assert run_id(measured, RetrievalConfig(estimator=("score",), transmittance="exponential")
                  ) == run_id(measured, RetrievalConfig(estimator=("score",)))


def test_the_retrieval_media_carry_the_assumed_model(power_law_measurements):
    under_model = Retrieval(power_law_measurements, initial_guess(),
                            RetrievalConfig(transmittance="medium", iterations=0))
    family, mode = transmittance_model(under_model.medium())
    assert family == "gamma" and float(mode) == A
    with pytest.warns(UserWarning, match="transmittance is dropped"):
        exponential = Retrieval(power_law_measurements,
                                with_transmittance(initial_guess(), "gamma", 3.0),
                                RetrievalConfig(estimator=("score",), iterations=0))
    assert transmittance_model(exponential.medium()) == ("exponential", None)
    # a mode field on another grid does not fit
    other = gradient_medium().isel(x=slice(0, 5))
    field = synthesize_measurements(
        with_transmittance(other, "gamma", np.full(other["cloud_extinction"].shape, 2.0)),
        gradient_scene(), photons=2000, batches=4, progress=False)
    with pytest.raises(ValueError, match="does not fit the initial medium"):
        Retrieval(field, initial_guess(), RetrievalConfig(transmittance="medium"))
    assert issubclass(MediumError, ValueError)


def test_a_tiny_retrieval_under_the_model_lowers_epsilon(tmp_path, power_law_measurements):
    """From the flat hull, a retrieval under the measurements' power law lowers epsilon and
    writes a result whose medium holds the model (so that the report re-renders under
    it); through the command line, --transmittance medium."""
    truth = power_law_truth()
    config = RetrievalConfig(transmittance="medium", iterations=30, photons=40_000, step=1.0,
                             stages=(2,), saturation_window=5, checkpoint_every=10)
    result = Retrieval(power_law_measurements, initial_guess(), config,
                       truth=truth).run(progress=False)
    eps0, _ = epsilon_delta(truth["cloud_extinction"].values,
                            initial_guess()["cloud_extinction"].values)
    eps = result["log_epsilon"].values
    assert eps[-5:].mean() < 0.7 * eps0, (eps0, eps)
    assert result.attrs["transmittance"] == "gamma"
    assert result.attrs["measurement_transmittance"] == "gamma"
    assert float(result["transmittance_mode"]) == A

    save_measurements(power_law_measurements, tmp_path / "m.nc")
    save_medium(initial_guess(), tmp_path / "init.nc")
    argv = ["retrieve", str(tmp_path / "m.nc"), "--init", str(tmp_path / "init.nc"),
            "--iterations", "1", "--photons", "2000", "--transmittance", "medium", "-o",
            str(tmp_path / "r.nc")]
    assert main(argv) == 0
    written = xr.load_dataset(tmp_path / "r.nc")
    assert json.loads(written.attrs["config"])["transmittance"] == "medium"
    assert written.attrs["transmittance"] == "gamma"
