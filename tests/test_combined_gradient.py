"""The path score function on backward paths, and the combined estimator's gradient
(:func:`cloudct.mc.gradient.combined_gradient`): forward photons and backward pixel
samples, each path's score weighted by its share under multiple importance sampling.

- The backward paths' score function (:func:`cloudct.mc.backward.score_pixel_sample`)
  agrees per voxel with the forward score function (:func:`cloudct.mc.forward.
  trace_photon`; independent paths, the two ends of each path sampled the other way round)
  wherever the total extinction is not zero (where it is, both miss the same
  in-scattering).
- The combined gradient agrees with the forward score function on the HG box, with the
  backward paths carrying a sizeable share of it (so that a wrong weight shows; checked by
  hand: with the backward kernel's weights left out the pooled z-score is far beyond 4),
  and on a piece of the single cloud with Mie optics over a Lambertian ground, both
  estimators aiming.
- What it refuses: a non-exponential transmittance, pixels drawn by residual.
"""

from __future__ import annotations

import numpy as np
import pytest
from mcstats import assert_consistent
from test_score_gradient import gradient_medium, gradient_scene, pixel_weights

from cloudct.mc.gradient import (
    backward_score_gradient,
    combined_gradient,
    gradient_estimate,
    score_function_gradient,
)
from cloudct.mc.scene import Scene
from cloudct.medium import with_transmittance
from cloudct.optics import to_optical
from data_synth.single_cloud_piece import piece_microphysics, scene_of_piece

BATCHES = 32


@pytest.fixture(scope="module")
def forward_reference():
    """The forward score function's gradient of the HG box, and where it can be compared
    (a non-zero total extinction)."""
    medium = gradient_medium()
    mean, error, _ = score_function_gradient(medium, gradient_scene(), pixel_weights(),
                                             photons=800_000, seed=1, progress=False)
    scattering = (medium["cloud_extinction"].values + medium["air_extinction"].values) > 0.0
    return mean, error, scattering


def test_backward_score_function_agrees_with_the_forward_one(forward_reference):
    f, fe, where = forward_reference
    b, be, info = backward_score_gradient(gradient_medium(), gradient_scene(), pixel_weights(),
                                          samples_per_pixel=2048, seed=2)
    assert info["photons"] == 2048 * 72
    assert where.sum() >= 150
    assert_consistent(b[where], be[where], f[where], BATCHES, reference_error=fe[where],
                      label="backward vs forward score function")


def test_combined_gradient_agrees_with_the_forward_score_function(forward_reference):
    f, fe, where = forward_reference
    c, ce, info = combined_gradient(gradient_medium(), gradient_scene(), pixel_weights(),
                                    photons=400_000, pixel_samples=4096, seed=3,
                                    progress=False)
    assert info["pixel_samples"] == 4096
    assert info["mis_ratio"] == pytest.approx(4096 / 400_000)
    assert 0.2 < info["backward_share"] < 0.8, info["backward_share"]
    assert info["events"] > info["backward_events"] > 0
    assert_consistent(c[where], ce[where], f[where], BATCHES, reference_error=fe[where],
                      label="combined vs forward score function, HG")


def test_combined_gradient_with_mie_optics_agrees_with_the_forward_one():
    micro = piece_microphysics()
    micro["reff"] = micro["reff"].where(micro["lwc"] <= 0.0, 4.0)  # a peak of ~90 per sr
    medium = to_optical(micro, optics="mie")
    piece = scene_of_piece(medium)
    scene = Scene(piece.cameras, piece.sun, "open", 0.3)
    cam = scene.cameras[0]
    residual = np.random.default_rng(5).uniform(0.5, 1.5, (len(scene.cameras), cam.nrows,
                                                           cam.ncols))
    f, fe, info_f = score_function_gradient(medium, scene, residual, photons=200_000, seed=1,
                                            progress=False)
    c, ce, info = combined_gradient(medium, scene, residual, photons=100_000,
                                    pixel_samples=256, seed=11, progress=False)
    assert info["aim_fraction"] == info_f["aim_fraction"] == 0.1  # Mie: both aim
    assert 0.1 < info["backward_share"] < 0.9, info["backward_share"]
    cloud = medium["cloud_extinction"].values > 0.0
    assert_consistent(c[cloud], ce[cloud], f[cloud], BATCHES, reference_error=fe[cloud],
                      label="combined vs forward score function, Mie")


def test_combined_gradient_defaults_and_refusals():
    medium, scene, residual = gradient_medium(), gradient_scene(), pixel_weights()
    residual[0] = 0.0  # the second view's 36 pixels alone
    _, _, info = gradient_estimate(medium, scene, residual, estimator="combined",
                                   photons=3_200, seed=1)
    # 4 backward paths per photon over the pixels traced, rounded up to whole batches
    assert info["estimator"] == "combined" and info["photons"] == 3_200
    assert info["pixel_samples"] == 384  # 4 x 3200 / 36 = 356 -> 12 per batch
    with pytest.raises(ValueError, match="camera-side estimators.*backward-score"):
        gradient_estimate(medium, scene, residual, estimator="combined", photons=3_200,
                          pixel_sampling="residual")
    power_law = with_transmittance(medium, "gamma", 2.0)
    for run in (lambda: combined_gradient(power_law, scene, residual, photons=640),
                lambda: backward_score_gradient(power_law, scene, residual,
                                                samples_per_pixel=32)):
        with pytest.raises(ValueError, match="non-exponential.*not implemented"):
            run()
