"""The sample-average loss of fixed paths and the L-BFGS-B window on it
(:mod:`cloudct.retrieval.sample_average`).

- L_AB's gradient is the exact derivative of L_AB (central finite differences, 1e-6).
- L_AB, the product of two independent stores' residuals, estimates the noise-free loss
  without bias away from the reference medium (mean over 40 seeds against a 4M-photon
  render, within 4 standard errors), while one store's squared residual is biased upwards
  by the images' variance (more than 4 standard errors above it): the bias L_AB avoids.
- A window lowers L_AB and stays in its trust region, inside the mask.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_recycling import perturbed, scaled, weights_for
from test_score_gradient import gradient_medium, gradient_scene

from cloudct.mc.render import render
from cloudct.retrieval.loss import image_loss
from cloudct.retrieval.sample_average import SampleAverageLoss, lbfgsb_window


@pytest.fixture(scope="module")
def problem():
    """Measurements of the gradient test medium, a guess (0.8 x the truth), its hull."""
    truth = gradient_medium()
    measured = render(truth, gradient_scene(), photons=400_000, seed=77, progress=False)
    guess = scaled(truth, 0.8)
    return measured, guess, truth["cloud_extinction"].values > 0


def test_gradient_is_the_derivative_of_the_sample_average_loss(problem):
    measured, guess, mask = problem
    loss = SampleAverageLoss(guess, measured, mask, photons=20_000, photons_b=10_000, seed=3)
    x = perturbed(guess, seed=5)["cloud_extinction"].values[mask]
    value, gradient = loss(x)
    assert gradient.shape == x.shape and np.all(np.isfinite(gradient))
    for i in np.random.default_rng(1).choice(x.size, 6, replace=False):
        h = 1e-4 * x[i]
        up, down = x.copy(), x.copy()
        up[i] += h
        down[i] -= h
        fd = (loss(up)[0] - loss(down)[0]) / (2 * h)
        assert gradient[i] == pytest.approx(fd, rel=1e-6, abs=1e-12 * np.abs(gradient).max())
    assert loss.values[0] == value  # every evaluation is recorded, the first one first
    # a memory budget is shared by the two stores in proportion to their paths: halfway
    # between what they take with and without camera connections, A (2/3 of the paths)
    # cannot keep its connections
    assert [store.storage for store in loss.stores] == ["connections", "connections"]
    connections = sum(store.connection_nbytes for store in loss.stores)
    budget = sum(store.nbytes for store in loss.stores) - connections / 2
    small = SampleAverageLoss(guess, measured, mask, photons=20_000, photons_b=10_000, seed=3,
                              memory_budget=budget)
    assert small.stores[0].storage != "connections"
    assert sum(store.nbytes for store in small.stores) <= budget
    assert small(x)[0] == pytest.approx(value, rel=1e-12)  # the same paths, stored otherwise


def test_sample_average_loss_is_unbiased_where_the_squared_residual_is_not(problem):
    measured, guess, mask = problem
    weights = weights_for(gradient_scene())
    target = perturbed(guess, seed=9)  # away from the reference the stores were recorded at
    x = target["cloud_extinction"].values[mask]
    cross, squared = [], []
    for seed in range(40):
        loss = SampleAverageLoss(guess, measured, mask, photons=4_000, photons_b=4_000,
                                 seed=seed, weights=weights)
        cross.append(loss(x)[0])
        squared.append(loss.reference_loss)  # Eq. (41) of store A's images, the same paths
    reference = render(target, gradient_scene(), photons=4_000_000, seed=5, progress=False)
    noise_free = image_loss(reference["radiance"].values, measured["radiance"].values,
                            weights)[0]
    cross, squared = np.array(cross), np.array(squared)
    se_cross = cross.std(ddof=1) / np.sqrt(cross.size)
    se_squared = squared.std(ddof=1) / np.sqrt(squared.size)
    assert abs(cross.mean() - noise_free) < 4 * se_cross, (cross.mean(), noise_free, se_cross)
    assert squared.mean() - noise_free > 4 * se_squared, (squared.mean(), noise_free)


def test_a_window_lowers_the_loss_within_its_trust_region(problem):
    measured, guess, mask = problem
    window = lbfgsb_window(guess, measured, mask, photons=20_000, seed=2, trust_region=0.3,
                           evaluations=8)
    x0 = guess["cloud_extinction"].values
    assert window.end < window.start and window.evaluations >= 3
    assert np.all(window.extinction[~mask] == 0.0)
    inside = window.extinction[mask]
    assert np.all(inside >= 0.7 * x0[mask] - 1e-12) and np.all(inside <= 1.3 * x0[mask] + 1e-12)
    assert not np.allclose(inside, x0[mask])
    assert window.loss > 0.0 and np.isfinite(window.loss)
    with pytest.raises(ValueError, match="trust_region"):
        lbfgsb_window(guess, measured, mask, photons=100, trust_region=0.0)
    with pytest.raises(ValueError, match="evaluations"):
        lbfgsb_window(guess, measured, mask, photons=100, evaluations=0)
