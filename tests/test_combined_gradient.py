"""The path score function on backward paths, and the combined estimator's gradient
(:func:`cloudct.mc.gradient.combined_gradient`): forward photons and backward pixel
samples, each path's score weighted by its share under multiple importance sampling.

- The backward paths' score function (:func:`cloudct.mc.backward.score_pixel_sample`)
  agrees per voxel with DRT wherever the total extinction is not zero (where it is, a score
  function misses the in-scattering).
- The combined gradient agrees with the forward score function (:func:`cloudct.mc.forward.
  trace_photon`: independent paths, each path's ends sampled the other way round) and with
  DRT on the HG box, the backward paths carrying a sizeable share of it, so that a wrong
  weight shows (checked by hand: with either kernel's weights set to 1 the pooled z-score
  against the forward score function is 12 or 8.6; without the backward estimates' turn
  towards the sun, their sampled turns or their connections to the sun, the backward
  score function's is -39, -48 or +20). On a piece of the single cloud with Mie optics over
  a Lambertian ground, both estimators aiming, it agrees with the forward score function;
  there the per-voxel noise (about 110 % of the gradient) leaves the comparison blind to
  errors of the weights, which the HG box catches.
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
    drt_gradient,
    gradient_estimate,
    score_function_gradient,
)
from cloudct.mc.scene import Scene
from cloudct.medium import with_transmittance
from cloudct.optics import to_optical
from data_synth.single_cloud_piece import piece_microphysics, scene_of_piece

BATCHES = 32


@pytest.fixture(scope="module")
def references():
    """The HG box's gradient by the forward score function and by DRT (unbiased
    everywhere; camera paths whose transmittances are differentiated by ratio tracking, no
    score), and where the score functions can be compared (a non-zero total extinction)."""
    medium, scene, residual = gradient_medium(), gradient_scene(), pixel_weights()
    forward = score_function_gradient(medium, scene, residual, photons=800_000, seed=1,
                                      progress=False)
    drt = drt_gradient(medium, scene, residual, samples_per_pixel=4096, seed=4)
    scattering = (medium["cloud_extinction"].values + medium["air_extinction"].values) > 0.0
    return {"forward score function": forward[:2], "DRT": drt[:2]}, scattering


def test_backward_score_function_agrees_with_drt(references):
    """Against DRT: the forward score function's per-voxel errors have heavier tails than
    Student's t (two forward estimates of 4 x 10^5 photons each: mean z^2 1.36 over the
    box's voxels, 1.07 expected)."""
    (reference, error), where = references[0]["DRT"], references[1]
    b, be, info = backward_score_gradient(gradient_medium(), gradient_scene(), pixel_weights(),
                                          samples_per_pixel=2048, seed=2)
    assert info["photons"] == 2048 * 72
    assert where.sum() >= 150
    assert_consistent(b[where], be[where], reference[where], BATCHES, reference_error=error[where],
                      label="backward score function vs DRT")


def test_combined_gradient_agrees_with_the_forward_score_function_and_drt(references):
    c, ce, info = combined_gradient(gradient_medium(), gradient_scene(), pixel_weights(),
                                    photons=400_000, pixel_samples=4096, seed=3,
                                    progress=False)
    assert info["pixel_samples"] == 4096
    assert info["mis_ratio"] == pytest.approx(4096 / 400_000)
    assert 0.2 < info["backward_share"] < 0.8, info["backward_share"]
    assert info["events"] > info["backward_events"] > 0
    where = references[1]
    for name, (reference, error) in references[0].items():
        assert_consistent(c[where], ce[where], reference[where], BATCHES,
                          reference_error=error[where], label=f"combined vs {name}, HG")


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
