"""The loss (seed paper Eq. 41) and its gradient (Eq. 48): zero at the truth, pointing
uphill away from it, weights and masks."""

from __future__ import annotations

import numpy as np
import pytest
from mcstats import assert_consistent
from test_score_gradient import gradient_medium, gradient_scene

from cloudct.mc.render import render
from cloudct.retrieval.loss import loss_and_gradient


@pytest.fixture(scope="module")
def truth_measurements():
    """Noise-free measurements of the true medium, with 40x the photons of one replicate."""
    return render(gradient_medium(), gradient_scene(), photons=8_000_000, seed=1000,
                  progress=False)


def test_gradient_of_loss_is_zero_at_the_truth(truth_measurements):
    """Replicates with independent seeds (each with its own residual images and gradient
    paths) give gradients whose mean is zero within its standard error, voxel by voxel.
    The replicates' spread includes the residual's own noise, which a single call's batch
    standard error does not."""
    medium = gradient_medium()
    reps = np.array([
        loss_and_gradient(medium, truth_measurements, photons=200_000, seed=s).gradient
        for s in range(8)
    ])
    mean = reps.mean(axis=0)
    se = reps.std(axis=0, ddof=1) / np.sqrt(len(reps))
    live = se > 0
    assert live.sum() > 150
    assert_consistent(mean[live], se[live], 0.0, len(reps), label="gradient at truth")


def test_gradient_points_uphill_from_a_perturbed_cloud(truth_measurements):
    """Away from the truth, the gradient has a clearly positive projection on the
    perturbation: a gradient step towards the truth lowers the loss."""
    truth = gradient_medium()
    perturbed = truth.copy(deep=True)
    perturbed["cloud_extinction"] = perturbed["cloud_extinction"] * 1.3
    result = loss_and_gradient(perturbed, truth_measurements, photons=400_000, seed=3)
    step = (perturbed["cloud_extinction"] - truth["cloud_extinction"]).values
    projection = float(np.sum(result.gradient * step))
    error = float(np.sqrt(np.sum((result.gradient_std_error * step) ** 2)))
    assert projection > 5 * error
    assert result.loss > 0


def test_weights_and_masks(truth_measurements):
    medium = gradient_medium()
    none = np.zeros(truth_measurements.radiance.shape, dtype=bool)
    masked = loss_and_gradient(medium, truth_measurements, photons=20_000, mask=none)
    assert masked.loss == 0.0
    assert np.all(masked.gradient == 0.0)
    weights = np.zeros(truth_measurements.radiance.shape)
    weights[0] = 2.0
    result = loss_and_gradient(medium, truth_measurements, photons=20_000, weights=weights)
    diff = result.images.radiance.values[0] - truth_measurements.radiance.values[0]
    np.testing.assert_allclose(result.loss, np.sum(diff**2), rtol=1e-12)
    np.testing.assert_allclose(result.residual[1], 0.0)
    with pytest.raises(ValueError, match="weights"):
        loss_and_gradient(medium, truth_measurements, photons=100, weights=-weights)


def test_nan_measurements_are_masked_with_a_warning(truth_measurements):
    bad = truth_measurements.copy(deep=True)
    bad["radiance"].values[1, 2, 3] = np.nan
    with pytest.warns(UserWarning, match="1 measured pixels"):
        result = loss_and_gradient(gradient_medium(), bad, photons=20_000)
    assert result.residual[1, 2, 3] == 0.0
    assert np.isfinite(result.loss) and np.all(np.isfinite(result.gradient))
