"""The combined estimator in path recycling: stored forward paths replayed with each local
estimate weighted by its share w_f under the current medium, and backward paths traced
fresh with their next-event estimates weighted by w_b (:class:`cloudct.recycling.Recycler`
with ``image_method="combined"`` and ``gradient_estimator="combined"``).

- Under the reference medium the replayed forward half is the fresh forward half of the
  same photons (:func:`cloudct.mc.forward.trace_photon` with ``cams.mis_ratio`` > 0), images
  and gradient, to rounding, in every storage mode, with and without aiming, over an open
  box and over a periodic scene with a Lambertian ground: the replay recomputes every
  weight (the sun end at the first vertex or the ground, the turns, both directions' aim
  factors) as the tracer does.
- Under a perturbed medium the recycler's combined images and gradient agree with the
  fresh combined estimator's (independent paths) within standard errors; its forward half
  replayed without the weights w_f, plus the backward half, fails the same comparison
  (the test's power).
"""

from __future__ import annotations

import numpy as np
import pytest
from mcstats import assert_consistent
from test_recycling import SCENES, perturbed, weights_for

from cloudct.mc.detector_sampling import DEFAULT_AIM_FRACTION
from cloudct.mc.estimate import (
    Sampling,
    batch_means,
    combined_inputs,
    kernel_inputs,
    per_cloud_extinction,
)
from cloudct.mc.forward import GRADIENT, RENDER
from cloudct.mc.gradient import combined_gradient
from cloudct.mc.render import backward_images, render_batches
from cloudct.recycling import FixedPeriod, Recycler, record_paths, replay_images
from cloudct.recycling.replay import replay_batch_gradients

BATCHES = 32


@pytest.mark.parametrize("aim", [0.0, DEFAULT_AIM_FRACTION])
@pytest.mark.parametrize("name", list(SCENES))
def test_replayed_forward_half_is_the_fresh_one_under_the_reference(name, aim):
    make_medium, make_scene, rr = SCENES[name]
    medium, scene = make_medium(), make_scene()
    weights = weights_for(scene)
    photons, pixel_samples = 8_000, 64
    sampling = Sampling(BATCHES, 4, rr.get("rr_depth", 100), rr.get("rr_survival", 0.95))
    k, _ = combined_inputs(kernel_inputs(medium, scene, aim), sampling,
                           sampling.per_batch(photons), pixel_samples)
    ratio = k.cams.mis_ratio
    per_batch = sampling.per_batch(photons)
    fresh_images = batch_means("forward", k, (RENDER, None), per_batch=per_batch,
                               sampling=sampling)[0]
    fresh_gradient = per_cloud_extinction(k, batch_means(
        "forward", k, (GRADIENT, weights), per_batch=per_batch, sampling=sampling)[0])
    plain = batch_means("forward", k._replace(cams=k.cams._replace(mis_ratio=0.0)),
                        (RENDER, None), per_batch=per_batch, sampling=sampling)[0]
    assert 0.05 < fresh_images.sum() / plain.sum() < 0.95  # the weights do act
    for storage in ("crossings", "lean", "connections"):
        store = record_paths(medium, scene, photons=photons, seed=4, batches=BATCHES,
                             storage=storage, aim_fraction=aim, **rr)
        images, info = replay_images(store, medium, mis_ratio=ratio)
        assert info["mis_ratio"] == ratio
        np.testing.assert_allclose(images, fresh_images, rtol=1e-12,
                                   atol=1e-14 * fresh_images.max(), err_msg=storage)
        gradient = replay_batch_gradients(store, medium, weights, mis_ratio=ratio)[0]
        np.testing.assert_allclose(gradient, fresh_gradient, rtol=1e-10,
                                   atol=1e-12 * np.abs(fresh_gradient).max(), err_msg=storage)


def test_combined_recycler_agrees_with_the_fresh_combined_estimator():
    make_medium, make_scene, rr = SCENES["periodic-ground-rr"]
    medium, scene = make_medium(), make_scene()
    target = perturbed(medium)
    weights = weights_for(scene)
    recycler = Recycler(scene, photons=120_000, batches=BATCHES, policy=FixedPeriod(100),
                        seed=3, image_method="combined", gradient_estimator="combined", **rr)
    recycler.resample(medium)
    ev = recycler.evaluate(target, residual=weights)
    assert ev.images.attrs["method"] == "combined-recycled"
    assert 0.2 < ev.info["ess_images"] < 1.0
    fresh, _ = render_batches(target, scene, photons=120_000, method="combined", seed=9,
                              batches=BATCHES, progress=False, **rr)
    fresh_se = fresh.std(axis=0, ddof=1) / np.sqrt(BATCHES)
    recycled, se = ev.images["radiance"].values, ev.images["radiance_std_error"].values
    lit = (se > 0) & (fresh_se > 0)
    assert lit.sum() > 0.8 * lit.size
    assert_consistent(recycled[lit], se[lit], fresh.mean(axis=0)[lit], BATCHES,
                      reference_error=fresh_se[lit], label="recycled vs fresh combined images")

    # power: the replay without its weights w_f, plus the backward half, counts the
    # forward share of every path twice
    store = recycler.image_store
    unweighted = replay_images(store, target)[0]
    k, per_pixel, sampling = recycler._backward_half(
        target, store, ev.images.attrs["pixel_samples"] // BATCHES, 2)
    wrong = unweighted + backward_images(k, per_pixel, sampling=sampling)[0]
    with pytest.raises(AssertionError):
        assert_consistent(wrong.mean(axis=0)[lit], (wrong.std(axis=0, ddof=1)
                                                    / np.sqrt(BATCHES))[lit],
                          fresh.mean(axis=0)[lit], BATCHES, reference_error=fresh_se[lit],
                          label="unweighted replay + backward half")

    g, ge, _ = combined_gradient(target, scene, weights, photons=120_000, seed=10,
                                 batches=BATCHES, progress=False, **rr)
    live = (ev.gradient_std_error > 0) & (ge > 0)
    assert live.sum() > 20
    assert ev.info["gradient_time"] > 0.0
    assert_consistent(ev.gradient[live], ev.gradient_std_error[live], g[live], BATCHES,
                      reference_error=ge[live], label="recycled vs fresh combined gradient")


def test_combined_recycling_refusals():
    scene = SCENES["open"][1]()
    with pytest.raises(ValueError, match="image_method"):
        Recycler(scene, photons=100, image_method="backward")
    with pytest.raises(ValueError, match="gradient_estimator"):
        Recycler(scene, photons=100, gradient_estimator="sm")
