"""Sample matching (cloudct.mc.sample_matching) and residual-driven pixel sampling
(cloudct.mc.pixel_sampling) against references they share no code with.

- Sample matching against central finite differences of the backward renderer on the DRT
  test medium (tests/test_drt.py: dense and thin cloud, cloud-free air, voxels with no
  extinction at all, a Lambertian ground), for the linear variant with one and four probes
  per segment and for the quadratic variant: pooled z and mean z^2 over the compared voxels
  (``mcstats.assert_consistent``), fixed seeds.
- Sample matching against DRT (which shares the path tracer but none of the derivative
  terms' sampling) on a piece of the LES single cloud, voxel by voxel, and on a periodic
  scene without ground.
- Residual-driven pixel sampling: the alias table draws pixels with probability |r| / sum |r|
  (frequencies against the exact probabilities); each estimator's mean is unchanged
  (z-test against uniform pixel sampling); with a sparse residual the variance falls.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from mcstats import assert_consistent
from numba import njit
from test_drt import (
    AIR_VOXELS,
    CLOUD_VOXELS,
    EMPTY_VOXELS,
    compare,
    drt_medium,
    drt_scene,
    pixel_weights,
)

from cloudct.mc.gradient import (
    drt_gradient,
    gradient_estimate,
    sample_matching_gradient,
)
from cloudct.mc.pixel_sampling import draw_pixel, pixel_table, residual_table
from cloudct.mc.random import stream_start
from data_synth.single_cloud_piece import dense_core_piece, scene_of_dense_core

BATCHES = 32
ALL_VOXELS = CLOUD_VOXELS + AIR_VOXELS + EMPTY_VOXELS


# ----------------------------------------------------------------------------------------
# Against finite differences
# ----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "probes, quadratic, mis, samples",
    [(1, False, True, 4096), (4, False, True, 2048), (1, True, True, 2048),
     (1, False, False, 4096)],
    ids=["linear-1-probe", "linear-4-probes", "quadratic-1-probe", "dual-suffix-no-mis"],
)
def test_sample_matching_matches_finite_differences(finite_differences, probes, quadratic,
                                                    mis, samples):
    """Every kind of voxel at once: dense cloud, thin cloud, cloud-free air, and voxels with
    no extinction at all, where only an estimator that samples the in-scattering along the
    whole segment sees the (positive, > 20 standard errors in total) derivative."""
    sm = sample_matching_gradient(
        drt_medium(), drt_scene(), pixel_weights(), samples_per_pixel=samples, probes=probes,
        quadratic=quadratic, mis=mis, seed=17, batches=BATCHES,
    )
    stats = compare(ALL_VOXELS, sm, finite_differences,
                    f"sample matching {probes} {quadratic} {mis}")
    assert stats["n"] == 8
    # the voxels without extinction alone: the in-scattering term is there
    compare(EMPTY_VOXELS, sm, finite_differences, "sample matching, empty voxels")


# ----------------------------------------------------------------------------------------
# Against DRT
# ----------------------------------------------------------------------------------------


def assert_same_mean(a, b, label, min_voxels):
    """Two estimates of the same gradient agree voxel by voxel where both have spread."""
    both = (a[1] > 0) & (b[1] > 0)
    assert both.sum() >= min_voxels, both.sum()
    return assert_consistent(a[0][both], a[1][both], b[0][both], BATCHES,
                             reference_error=b[1][both], label=label)


def test_sample_matching_has_the_mean_of_drt_on_an_les_piece():
    medium = dense_core_piece()
    scene = scene_of_dense_core(medium)
    residual = np.random.default_rng(4).uniform(0.5, 1.5, size=(2, 6, 6))
    sm = sample_matching_gradient(medium, scene, residual, samples_per_pixel=2048, seed=3,
                                  batches=BATCHES)
    drt = drt_gradient(medium, scene, residual, samples_per_pixel=2048, seed=4,
                       batches=BATCHES)
    stats = assert_same_mean(sm, drt, "LES piece: SM vs DRT", min_voxels=500)
    # the comparison has power: many voxels' derivatives are resolved
    resolved = np.abs(drt[0]) > 3 * drt[1]
    print("voxels resolved by DRT at 3 standard errors:", resolved.sum())
    assert resolved.sum() >= 50
    assert stats["n"] >= 500


def test_sample_matching_has_the_mean_of_drt_with_periodic_boundaries():
    medium, scene = drt_medium(), drt_scene(periodic=True, ground=None)
    r = pixel_weights()
    sm = sample_matching_gradient(medium, scene, r, samples_per_pixel=2048, probes=2, seed=8,
                                  batches=BATCHES)
    drt = drt_gradient(medium, scene, r, samples_per_pixel=2048, seed=9, batches=BATCHES)
    assert_same_mean(sm, drt, "periodic: SM vs DRT", min_voxels=100)


def test_sample_matching_is_linear_in_the_residual_and_checks_its_input():
    medium, scene = drt_medium(), drt_scene(periodic=True, ground=None)
    r = pixel_weights()
    g1, s1, info = sample_matching_gradient(medium, scene, r, samples_per_pixel=64, seed=2,
                                            batches=4)
    g2, s2, _ = sample_matching_gradient(medium, scene, 2.0 * r, samples_per_pixel=64,
                                         seed=2, batches=4)
    assert np.any(g1 != 0.0) and info["events"] > 0
    np.testing.assert_array_equal(g2, 2.0 * g1)
    np.testing.assert_array_equal(s2, 2.0 * s1)
    with pytest.raises(ValueError, match="probes"):
        sample_matching_gradient(medium, scene, r, samples_per_pixel=8, batches=2, probes=0)
    with pytest.raises(ValueError, match="residual"):
        sample_matching_gradient(medium, scene, r[:1], samples_per_pixel=8, batches=2)
    with pytest.raises(ValueError, match="pixel_sampling"):
        sample_matching_gradient(medium, scene, r, samples_per_pixel=8, batches=2,
                                 pixel_sampling="importance")


def test_gradient_estimate_chooses_the_estimator_by_name():
    medium, scene = drt_medium(), drt_scene()
    r = pixel_weights()
    g, _, info = gradient_estimate(medium, scene, r, estimator="sm", photons=32 * 64, seed=2,
                                   batches=4)
    ref, _, _ = sample_matching_gradient(medium, scene, r, samples_per_pixel=64, seed=2,
                                         batches=4)
    np.testing.assert_array_equal(g, ref)
    assert info["estimator"] == "sm" and info["photons"] == 32 * 64
    # residual-drawn pixels: as many samples as asked for, to whole samples per pixel (4 of
    # each of the 32 pixels), not one sample of each pixel in each of the 32 batches
    _, _, drawn = gradient_estimate(medium, scene, r, estimator="sm", photons=100, seed=2,
                                    batches=32, pixel_sampling="residual")
    assert np.count_nonzero(r) == 32 and drawn["photons"] == 4 * 32
    with pytest.raises(ValueError, match="estimator must be one of"):
        gradient_estimate(medium, scene, r, estimator="mis", photons=64)
    with pytest.raises(ValueError, match="camera-side"):
        gradient_estimate(medium, scene, r, estimator="score", photons=64,
                          pixel_sampling="residual")
    with pytest.raises(TypeError, match="BatchExecutor"):
        gradient_estimate(medium, scene, r, estimator="drt", photons=64, executor=object())


# ----------------------------------------------------------------------------------------
# Residual-driven pixel sampling
# ----------------------------------------------------------------------------------------


@njit(cache=True)
def _draw_many(table, npix, n, seed):
    counts = np.zeros(npix)
    for k in range(n):
        pixel, _, _ = draw_pixel(table, stream_start(seed, 77, k))
        counts[pixel] += 1.0
    return counts


def test_alias_table_draws_pixels_in_proportion_to_the_residual():
    rng = np.random.default_rng(5)
    residual = rng.normal(size=(3, 5, 7)) * rng.uniform(0, 1, (3, 5, 7)) ** 3
    residual[0, 0, :4] = 0.0
    table = residual_table(residual)
    flat = residual.ravel()
    assert table.pixel.size == np.count_nonzero(flat)
    np.testing.assert_allclose(table.weight, np.sign(flat[table.pixel]) * np.abs(flat).sum())
    n_per_batch = 20_000
    counts = np.stack([_draw_many(table, flat.size, n_per_batch, b) for b in range(BATCHES)])
    freq = counts / n_per_batch
    p = np.abs(flat) / np.abs(flat).sum()
    assert not counts[:, flat == 0.0].any(), "a pixel with zero residual was drawn"
    seen = p > 1e-3
    assert seen.sum() >= 50
    assert_consistent(freq.mean(axis=0)[seen],
                      freq.std(axis=0, ddof=1)[seen] / math.sqrt(BATCHES), p[seen], BATCHES,
                      label="alias table frequencies")
    with pytest.raises(ValueError, match="every residual is zero"):
        residual_table(np.zeros(4))
    assert pixel_table(np.zeros(4), "residual").pixel.size == 0  # nothing to trace


@pytest.mark.parametrize("estimator", [drt_gradient, sample_matching_gradient],
                         ids=["drt", "sm"])
def test_residual_sampling_keeps_the_mean_and_lowers_the_variance_of_a_sparse_residual(
    estimator,
):
    """A residual that is large on 4 pixels and small on the other 28: uniform sampling
    spends 7/8 of its samples where the residual is small. Drawing pixels in proportion to
    |r| keeps the mean (z-test, voxel by voxel) and, with as many samples in all, lowers
    the summed variance."""
    medium, scene = drt_medium(), drt_scene()
    residual = pixel_weights() * 0.02
    residual[0, 1, 1] = residual[1, 2, 2] = 1.0
    residual[0, 2, 3] = residual[1, 0, 1] = -0.8
    uniform = estimator(medium, scene, residual, samples_per_pixel=2048, seed=6,
                        batches=BATCHES)
    drawn = estimator(medium, scene, residual, samples_per_pixel=2048, seed=7,
                      batches=BATCHES, pixel_sampling="residual")
    assert drawn[2]["photons"] == uniform[2]["photons"]  # as many samples in all
    assert_same_mean(drawn, uniform, "residual vs uniform pixel sampling", min_voxels=80)
    variance_ratio = np.sum(drawn[1] ** 2) / np.sum(uniform[1] ** 2)
    print("summed variance, residual / uniform pixel sampling:", variance_ratio)
    assert variance_ratio < 0.7
