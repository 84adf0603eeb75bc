"""Path recycling (seed paper Sec. 5): stored paths re-evaluated under a new medium.

- Under the reference medium the correction factor is exactly 1 and the re-evaluated
  images are bitwise those of the forward renderer with the same seed (the gradient equal
  to rounding: its deposits are made in another order).
- Under a perturbed medium (cloud extinction scaled voxel by voxel by 0.9-1.1), recycled
  images and gradients agree with fresh estimates from independent paths within their
  combined standard errors over batches.
- Sorted and unsorted stores, and the three storage modes, give bitwise identical results;
  camera connections restricted to a mask of variable voxels agree to rounding.
- The effective sample size of the correction factors falls as the medium departs from
  the reference.

Two scenes: the 6x6x6 gradient test medium (open boundaries, no ground), and a periodic
medium over a Lambertian ground with an aggressive Russian roulette (from the second
vertex, survival 0.6), which exercises ground records, wrapped positions and the roulette.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from mcstats import assert_consistent
from test_score_gradient import gradient_medium, gradient_scene, pixel_weights

from cloudct.mc.cameras import Camera
from cloudct.mc.detector_sampling import DEFAULT_AIM_FRACTION
from cloudct.mc.estimate import kernel_inputs
from cloudct.mc.gradient import score_function_gradient
from cloudct.mc.render import render_batches
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.mc.traversal import INF, march, new_trail
from cloudct.medium import optical_medium
from cloudct.recycling import (
    AdaptiveESS,
    FixedPeriod,
    MemoryBudgetError,
    Recycler,
    correction_log_weights,
    effective_sample_size,
    record_paths,
    replay_gradient,
    replay_images,
    replay_render,
    sort_paths,
)
from cloudct.recycling.replay import summary_ess, weight_summary
from cloudct.recycling.store import connections_bytes, crossings_bytes, lean_bytes

BATCHES = 32
RR = {"rr_depth": 2, "rr_survival": 0.6}


def periodic_medium():
    n = 5
    axis = (np.arange(n) + 0.5) * 0.1
    ext = np.zeros((n, n, n))
    ext[1:4, 1:4, 1:4] = 6.0
    ext[2, 2, 2] = 30.0
    return optical_medium(
        axis, axis, axis + 0.3, ext, cloud_albedo=0.95, cloud_g=0.8, air_extinction=0.5,
        air_albedo=0.9,
    )


def periodic_scene():
    c = (0.25, 0.25, 0.55)
    return Scene(
        [
            Camera((0.25, 0.25, 2.0), c, (0, 1, 0), fov=20.0, nrows=5, ncols=5),
            Camera((0.9, 0.1, 1.6), c, (0, 0, 1), fov=24.0, nrows=5, ncols=5),
        ],
        Sun(zenith=40.0, azimuth=30.0),
        "periodic",
        ground_albedo=0.3,
    )


SCENES = {
    "open": (gradient_medium, gradient_scene, {}),
    "periodic-ground-rr": (periodic_medium, periodic_scene, RR),
}


def perturbed(medium, seed=7):
    """Cloud extinction scaled voxel by voxel by factors uniform in 0.9-1.1."""
    out = medium.copy(deep=True)
    factors = np.random.default_rng(seed).uniform(0.9, 1.1, out["cloud_extinction"].shape)
    out["cloud_extinction"] = out["cloud_extinction"] * factors
    return out


def scaled(medium, factor):
    out = medium.copy(deep=True)
    out["cloud_extinction"] = out["cloud_extinction"] * factor
    return out


def weights_for(scene):
    cam = scene.cameras[0]
    shape = (len(scene.cameras), cam.nrows, cam.ncols)
    return np.random.default_rng(11).uniform(0.5, 1.5, size=shape)


@pytest.fixture(scope="module", params=list(SCENES))
def case(request):
    make_medium, make_scene, rr = SCENES[request.param]
    return request.param, make_medium(), make_scene(), rr


# ----------------------------------------------------------------------------------------
# Exactness under the reference medium
# ----------------------------------------------------------------------------------------


def test_correction_factor_is_exactly_one_under_the_reference(case):
    _, medium, scene, rr = case
    store = record_paths(medium, scene, photons=20_000, seed=4, batches=BATCHES, **rr)
    log_r = correction_log_weights(store, medium)
    assert np.all(log_r == 0.0)
    assert effective_sample_size(log_r) == store.paths
    recycled, info = replay_images(store, medium)
    fresh, fresh_info = render_batches(
        medium, scene, photons=20_000, seed=4, batches=BATCHES, progress=False, **rr
    )
    assert np.array_equal(recycled, fresh), "same paths, same weights, same estimates"
    assert info["events"] == fresh_info["events"]
    assert info["ess_fraction"] == 1.0
    dataset = replay_render(store, medium)
    assert np.array_equal(dataset.radiance.values, recycled.mean(axis=0))
    assert dataset.attrs["method"] == "forward-recycled"
    weights = weights_for(scene)
    grad, _, _ = replay_gradient(store, medium, weights)
    fresh_grad, _, _ = score_function_gradient(
        medium, scene, weights, photons=20_000, seed=4, batches=BATCHES, progress=False, **rr
    )
    scale = np.abs(fresh_grad).max()
    assert scale > 0
    np.testing.assert_allclose(grad, fresh_grad, rtol=0, atol=1e-12 * scale)


# ----------------------------------------------------------------------------------------
# Unbiasedness under a perturbed medium
# ----------------------------------------------------------------------------------------


@pytest.fixture(scope="module", params=[0.0, DEFAULT_AIM_FRACTION])
def aimed_store(case, request):
    """``(aim, store)``: the reference paths of each scene recorded with aim fraction
    ``aim`` (400,000 photons), once for both changes of the medium that
    :func:`test_recycled_images_agree_with_fresh_images` replays them under (a replay only
    reads its store)."""
    _, medium, scene, rr = case
    aim = request.param
    return aim, record_paths(
        medium, scene, photons=400_000, seed=1, batches=BATCHES, aim_fraction=aim, **rr
    )


@pytest.mark.parametrize("change", ["voxelwise", "scaled"])
def test_recycled_images_agree_with_fresh_images(case, aimed_store, change):
    """Voxel-wise factors 0.9-1.1 (the images hardly move), and all cloud scaled by 1.25
    (they move by many standard errors, so the correction factor must do its work). Paths
    aimed at the cameras (``aim`` > 0) keep their reference weights f / q in the store and
    are compared with fresh aimed paths; the plain sampler also shows that the comparison
    has the power to see a store without its correction factors."""
    name, medium, scene, rr = case
    aim, store = aimed_store
    target = perturbed(medium) if change == "voxelwise" else scaled(medium, 1.25)
    recycled, info = replay_images(store, target)
    fresh, _ = render_batches(
        target, scene, photons=400_000, seed=2, batches=BATCHES, progress=False,
        aim_fraction=aim, **rr
    )
    assert 0.2 < info["ess_fraction"] < 1.0
    mean, fresh_mean = recycled.mean(axis=0), fresh.mean(axis=0)
    se = recycled.std(axis=0, ddof=1) / np.sqrt(BATCHES)
    fresh_se = fresh.std(axis=0, ddof=1) / np.sqrt(BATCHES)
    lit = (se > 0) & (fresh_se > 0)
    assert lit.sum() > 0.8 * lit.size
    sigma = np.hypot(se, fresh_se)[lit]
    if change == "voxelwise":
        # power: a common bias of 3% would show as a pooled z-score above 6
        assert 0.03 * fresh_mean[lit].sum() / np.sqrt(np.sum(sigma**2)) > 6.0
    elif aim == 0.0:
        # without its correction factors the store fails the same comparison
        at_reference = replay_images(store, medium)[0]
        se_ref = at_reference.std(axis=0, ddof=1) / np.sqrt(BATCHES)
        with pytest.raises(AssertionError):
            assert_consistent(
                at_reference.mean(axis=0)[lit], se_ref[lit], fresh_mean[lit], BATCHES,
                reference_error=fresh_se[lit], label=f"uncorrected ({name})",
            )
    assert_consistent(
        mean[lit], se[lit], fresh_mean[lit], BATCHES, reference_error=fresh_se[lit],
        label=f"recycled vs fresh images ({name}, {change}, aim {aim})",
    )


def test_recycled_gradient_agrees_with_fresh_gradient():
    medium, scene = gradient_medium(), gradient_scene()
    target = perturbed(medium)
    weights = pixel_weights()
    store = record_paths(medium, scene, photons=300_000, seed=3, batches=BATCHES)
    grad, se, info = replay_gradient(store, target, weights)
    fresh, fresh_se, _ = score_function_gradient(
        target, scene, weights, photons=300_000, seed=8, batches=BATCHES, progress=False
    )
    live = (se > 0) & (fresh_se > 0)
    assert live.sum() > 150
    assert 0.5 < info["ess_fraction"] < 1.0
    # power: the gradient is resolved, many voxels at several standard errors from zero
    assert np.sum(np.abs(fresh[live]) > 4 * fresh_se[live]) > 30
    assert_consistent(
        grad[live], se[live], fresh[live], BATCHES, reference_error=fresh_se[live],
        label="recycled vs fresh gradient",
    )


def test_recycled_gradient_is_the_derivative_of_the_recycled_images(case):
    """With the paths fixed, the recycled images are a smooth function of the extinction and
    the recycled gradient is its exact derivative: central finite differences of
    sum_d w_d I_d agree with it to 1e-6, voxel by voxel, away from the reference."""
    _, medium, scene, rr = case
    weights = weights_for(scene)
    store = record_paths(medium, scene, photons=20_000, seed=5, batches=BATCHES, **rr)
    target = perturbed(medium, seed=2)
    beta = target["cloud_extinction"].values
    grad, _, _ = replay_gradient(store, target, weights)

    def weighted_sum(b):
        m = target.copy(deep=True)
        m["cloud_extinction"].values = b
        return float(np.sum(weights * replay_images(store, m)[0].mean(axis=0)))

    cloudy = np.argwhere(beta > 0)
    picks = cloudy[np.random.default_rng(4).choice(len(cloudy), 8, replace=False)]
    for v in map(tuple, picks):
        h = 1e-4 * beta[v]
        up, down = beta.copy(), beta.copy()
        up[v] += h
        down[v] -= h
        fd = (weighted_sum(up) - weighted_sum(down)) / (2 * h)
        assert grad[v] == pytest.approx(fd, rel=1e-6, abs=1e-12 * np.abs(grad).max()), v


# ----------------------------------------------------------------------------------------
# Sorting and storage modes do not change the results
# ----------------------------------------------------------------------------------------


def _results(store, medium, weights):
    images, info = replay_images(store, medium)
    grad, grad_se, _ = replay_gradient(store, medium, weights)
    return images, info["log_r"], grad, grad_se


def test_sorted_unsorted_and_storage_modes_give_identical_results(case):
    _, medium, scene, rr = case
    target = perturbed(medium)
    weights = weights_for(scene)
    kw = dict(photons=4_000, seed=5, batches=BATCHES, **rr)
    crossings = record_paths(medium, scene, storage="crossings", sort=False, **kw)
    lean = record_paths(medium, scene, storage="lean", sort=False, **kw)
    connections = record_paths(medium, scene, storage="connections", sort=False, **kw)
    assert (crossings.storage, lean.storage) == ("crossings", "lean")
    assert connections.storage == "connections" and connections.connections > 0
    reference = _results(crossings, target, weights)
    for store in (sort_paths(crossings), lean, sort_paths(lean), connections,
                  sort_paths(connections)):
        for a, b in zip(reference, _results(store, target, weights), strict=True):
            assert np.array_equal(a, b)
    # sorting: within every batch, the stored paths have non-decreasing lengths
    store = sort_paths(crossings)
    lengths = np.diff(store.arrays.path_start).reshape(BATCHES, -1)
    assert np.all(np.diff(lengths, axis=1) >= 0)
    assert np.array_equal(np.sort(store.record_counts()), np.sort(crossings.record_counts()))
    # memory: the crossings cost extra bytes; both are reported per scattering event
    assert connections.nbytes > crossings.nbytes > lean.nbytes
    assert crossings.bytes_per_event > lean.bytes_per_event > 0


def test_connections_with_a_variable_mask_keep_only_its_crossings(case):
    """Connections that keep only the crossings of variable voxels (and the optical depth
    of the others) give the results of the full store to rounding, for media that change
    only inside the mask; a medium that changes outside it is refused."""
    _, medium, scene, rr = case
    variable = medium["cloud_extinction"].values > 0
    target = perturbed(medium)  # the cloud changes, the air does not
    weights = weights_for(scene)
    kw = dict(photons=4_000, seed=5, batches=BATCHES, **rr)
    full = record_paths(medium, scene, storage="connections", **kw)
    masked = record_paths(medium, scene, storage="connections", variable=variable, **kw)
    assert masked.storage == "connections"
    assert 0 < masked.arrays.connection_voxel.size < full.arrays.connection_voxel.size
    assert masked.nbytes < full.nbytes
    images, log_r, grad, grad_se = _results(full, target, weights)
    m_images, m_log_r, m_grad, m_grad_se = _results(masked, target, weights)
    assert np.array_equal(log_r, m_log_r)  # the segments do not use the mask
    np.testing.assert_allclose(m_images, images, rtol=1e-12, atol=1e-15 * images.max())
    # the gradient inside the mask; outside it is not computed (zero)
    scale = np.abs(grad).max()
    np.testing.assert_allclose(m_grad[variable], grad[variable], rtol=0, atol=1e-11 * scale)
    assert np.all(m_grad[~variable] == 0.0) and np.abs(grad[~variable]).max() > 0
    air = medium.copy(deep=True)
    air["air_extinction"] = air["air_extinction"] * 1.01
    with pytest.raises(ValueError, match="outside the store's variable mask"):
        replay_images(masked, air)
    with pytest.raises(ValueError, match="boolean mask"):
        record_paths(medium, scene, storage="connections", variable=variable[:-1], **kw)


def test_effective_sample_size_from_per_batch_summaries():
    """The ESS and largest ratio combined from per-batch summaries (what Dask workers send
    back) equal the direct formulas over all paths, also with batches whose r are all 0."""
    log_r = np.random.default_rng(2).normal(0.0, 2.0, size=(8, 50))
    log_r[3] = -np.inf  # a batch of paths that the new medium cannot produce
    r = np.exp(log_r)
    ess, top = summary_ess(weight_summary(log_r, 8))
    assert top == log_r.max()
    assert ess == pytest.approx(r.sum() ** 2 / np.sum(r * r), rel=1e-12)
    assert effective_sample_size(log_r.ravel(), 8) == ess
    assert summary_ess(weight_summary(np.full(10, -np.inf), 2))[0] == 0.0


def test_effective_sample_size_falls_as_the_medium_departs_from_the_reference():
    medium, scene = gradient_medium(), gradient_scene()
    store = record_paths(medium, scene, photons=20_000, seed=6, batches=BATCHES)
    fractions = [
        effective_sample_size(correction_log_weights(store, scaled(medium, f))) / store.paths
        for f in (1.0, 1.05, 1.1, 1.2, 1.4, 2.0)
    ]
    assert fractions[0] == 1.0
    assert np.all(np.diff(fractions) < 0), fractions
    assert fractions[-1] < 0.8


# ----------------------------------------------------------------------------------------
# Memory budget and bad input
# ----------------------------------------------------------------------------------------


def test_memory_budget_chooses_the_storage_and_rejects_too_small_budgets():
    medium, scene = gradient_medium(), gradient_scene()
    kw = dict(photons=3_200, seed=9, batches=BATCHES)
    full = record_paths(medium, scene, storage="crossings", **kw)
    lean = record_paths(medium, scene, storage="lean", **kw)
    vsize = full.arrays.voxel.itemsize
    assert lean.nbytes == lean_bytes(lean.records, lean.paths, vsize)
    assert full.nbytes == lean.nbytes + crossings_bytes(full.records, full.crossings, vsize)
    connections = record_paths(medium, scene, storage="connections", **kw)
    assert connections.nbytes == full.nbytes + connections_bytes(
        full.records, connections.connections, connections.arrays.connection_voxel.size, vsize
    )
    assert record_paths(medium, scene, **kw).storage == "connections"
    # the exact budget leaves the batches no spare room: a second walk writes the
    # connections at their places, the same arrays as closing up the rooms of one walk
    exact = record_paths(medium, scene, memory_budget=connections.nbytes, **kw)
    assert exact.storage == "connections" and exact.nbytes == connections.nbytes
    for name, a in connections.arrays._asdict().items():
        np.testing.assert_array_equal(getattr(exact.arrays, name), a, err_msg=name)
    with pytest.raises(MemoryBudgetError, match="connections storage needs"):
        record_paths(medium, scene, memory_budget=full.nbytes, storage="connections", **kw)
    assert record_paths(medium, scene, memory_budget=full.nbytes, **kw).storage == "crossings"
    assert record_paths(medium, scene, memory_budget=full.nbytes - 1, **kw).storage == "lean"
    with pytest.raises(MemoryBudgetError, match="crossings storage needs"):
        record_paths(medium, scene, memory_budget=lean.nbytes, storage="crossings", **kw)
    with pytest.raises(MemoryBudgetError, match="lean storage needs"):
        record_paths(medium, scene, memory_budget=lean.nbytes - 1, **kw)
    with pytest.raises(MemoryBudgetError, match="too small for even one batch"):
        record_paths(medium, scene, memory_budget=1000, **kw)


def test_bad_input_gives_clear_errors():
    medium, scene = gradient_medium(), gradient_scene()
    store = record_paths(medium, scene, photons=640, seed=1, batches=BATCHES)
    coarse = medium.isel(x=slice(0, 3))
    with pytest.raises(ValueError, match="differs from the grid"):
        replay_images(store, coarse)
    with pytest.raises(ValueError, match="differs from the grid"):
        correction_log_weights(store, coarse)
    shifted = medium.assign_coords(z=medium.z + 0.01)
    with pytest.raises(ValueError, match="differs from the grid"):
        replay_gradient(store, shifted, pixel_weights())
    empty = dataclasses.replace(
        store,
        arrays=store.arrays._replace(path_start=np.zeros(1, np.int64), slot=np.zeros(0, np.int64)),
        photon=np.zeros(0, np.int64),
    )
    with pytest.raises(ValueError, match="empty"):
        replay_images(empty, medium)
    with pytest.raises(ValueError, match="empty"):
        sort_paths(empty)
    with pytest.raises(ValueError, match="positive"):
        record_paths(medium, scene, photons=0)
    with pytest.raises(ValueError, match="residual has shape"):
        replay_gradient(store, medium, np.ones((1, 6, 6)))
    with pytest.raises(ValueError, match="storage"):
        record_paths(medium, scene, photons=64, storage="disk")
    recycler = Recycler(scene, photons=640, batches=BATCHES, policy=FixedPeriod(5))
    recycler.evaluate(medium)
    with pytest.raises(ValueError, match="differs from the grid"):
        recycler.evaluate(coarse)


def test_distance_limited_march_gives_the_optical_depth_between_two_points():
    medium, scene = gradient_medium(), gradient_scene()
    k = kernel_inputs(medium, scene)
    p, d = np.array([0.05, 0.12, 0.61]), np.array([0.6, 0.3, 0.2])
    d = d / np.linalg.norm(d)
    ix, iy, iz = 0, 1, 1
    trail = new_trail(64)
    status, *end, tau, distance, scale = march(
        k.grid, *p, *d, ix, iy, iz, INF, False, None, 0.0, 0.37, trail
    )
    assert status == 0
    assert scale == 1.0  # the exponential: the deposits are the derivatives
    np.testing.assert_allclose(end[:3], p + 0.37 * d, atol=1e-14)
    assert distance == pytest.approx(0.37, rel=1e-14)
    assert trail.count[0] > 3
    np.testing.assert_allclose(trail.distance[0], 0.37, rtol=1e-14)
    # the optical depth is the sum of beta x length over the recorded crossings
    beta = k.grid.extinction.sum(axis=0).ravel()
    n = trail.count[0]
    assert tau == pytest.approx(np.sum(beta[trail.voxel[:n]] * trail.length[:n]), rel=1e-14)
    # without a limit, the walk is unchanged
    a = march(k.grid, *p, *d, ix, iy, iz, INF, False)
    b = march(k.grid, *p, *d, ix, iy, iz, INF, False, None, 0.0, INF, new_trail(0))
    assert a == b


# ----------------------------------------------------------------------------------------
# The recycler and its policies
# ----------------------------------------------------------------------------------------


def test_recycler_fixed_period_resamples_every_period_and_logs():
    medium, scene = gradient_medium(), gradient_scene()
    weights = pixel_weights()
    recycler = Recycler(scene, photons=3_200, batches=BATCHES, policy=FixedPeriod(2), seed=3)
    resampled = []
    for t in range(5):
        ev = recycler.evaluate(scaled(medium, 1.0 + 0.02 * t), residual=lambda im: weights)
        resampled.append(ev.info["resampled"])
        assert ev.images.radiance.shape == (2, 6, 6)
        assert ev.gradient.shape == (6, 6, 6)
        assert np.all(ev.gradient_std_error >= 0)
        assert ev.info["iteration"] == t
    assert resampled == [True, False, True, False, True]
    assert [e["reasons"]["gradient"] for e in recycler.log] == [
        "initial", None, "period", None, "period"
    ]
    assert recycler.log[1]["ess_images"] < 1.0 and recycler.log[2]["ess_images"] == 1.0
    # the residual's images and the gradient come from independent paths
    assert recycler.image_store.seed != recycler.gradient_store.seed
    assert recycler.nbytes == recycler.image_store.nbytes + recycler.gradient_store.nbytes


def test_recycler_adaptive_policy_resamples_on_low_ess_or_max_period():
    medium, scene = gradient_medium(), gradient_scene()
    recycler = Recycler(
        scene, photons=3_200, batches=BATCHES, policy=AdaptiveESS(0.8, max_period=3), seed=1
    )
    reasons = []
    for factor in (1.0, 1.0, 1.6, 1.6, 1.6, 1.6):
        reasons.append(recycler.evaluate(scaled(medium, factor)).info["reasons"]["images"])
    assert reasons == ["initial", None, "ess", None, None, "max_period"]
    assert recycler.log[2]["checked"]["images"]["ess_fraction"] < 0.8
    assert recycler.log[1]["checked"]["images"] == {"ess_fraction": 1.0, "max_ratio": 1.0}
    # the residual function receives the recycled images
    seen = {}

    def residual(images):
        seen["radiance"] = images.radiance.values
        return np.ones(images.radiance.shape)

    ev = recycler.evaluate(scaled(medium, 1.6), residual=residual)
    assert np.array_equal(seen["radiance"], ev.images.radiance.values)
    assert ev.info["reasons"]["gradient"] == "initial"
    # a cap on the largest correction factor resamples before the ESS falls that low
    capped = Recycler(
        scene, photons=3_200, batches=BATCHES, seed=1,
        policy=AdaptiveESS(0.1, max_period=50, max_ratio=1.5),
    )
    reasons = [capped.evaluate(scaled(medium, f)).info["reasons"]["images"] for f in (1, 1.3)]
    assert reasons == ["initial", "max_ratio"]
    assert capped.log[1]["checked"]["images"]["ess_fraction"] > 0.1
    with pytest.raises(ValueError, match="max_ratio"):
        AdaptiveESS(max_ratio=0.5)
