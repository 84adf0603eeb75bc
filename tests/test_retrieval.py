"""The retrieval loop: optimiser formulas, epsilon/delta, checkpoint-resume, and a tiny
end-to-end retrieval that lowers epsilon."""

from __future__ import annotations

import numpy as np
import pytest
from test_score_gradient import gradient_medium, gradient_scene

from cloudct.mc.render import render
from cloudct.measurements import coarse_measurements
from cloudct.retrieval.loop import (
    Retrieval,
    RetrievalConfig,
    run_id,
)
from cloudct.retrieval.metrics import epsilon_delta, epsilon_split
from cloudct.retrieval.optimizers import (
    Adam,
    MomentumSGD,
    block_mean,
    project,
    smoothed_gradient,
)
from cloudct.retrieval.priors import PRIORS, Prior, PriorGrid
from cloudct.retrieval.report import write_report
from cloudct.retrieval.schedule import advance
from cloudct.retrieval.state import LOG_FIELDS


def test_adam_follows_its_formula():
    x = np.array([1.0, 2.0, 3.0])
    g1, g2 = np.array([0.5, -1.0, 2.0]), np.array([0.1, 0.3, -0.2])
    opt = Adam(step=0.1)
    x1 = opt.update(x, g1, None)
    # first step: m_hat = g, v_hat = g^2 -> step * sign(g)
    np.testing.assert_allclose(x1, x - 0.1 * np.sign(g1), rtol=1e-9)
    x2 = opt.update(x1, g2, None)
    m = 0.9 * 0.1 * g1 + 0.1 * g2
    v = 0.999 * 0.001 * g1**2 + 0.001 * g2**2
    expected = x1 - 0.1 * (m / (1 - 0.9**2)) / (np.sqrt(v / (1 - 0.999**2)) + 1e-12)
    np.testing.assert_allclose(x2, expected, rtol=1e-12)


def test_sgd_momentum_and_projection():
    opt = MomentumSGD(step=0.5, momentum=0.9)
    x = np.array([3.0, 1.0, 1.0])
    mask = np.array([True, True, False])
    x1 = opt.update(x, np.array([1.0, 4.0, 0.0]), mask)
    np.testing.assert_allclose(x1, [2.5, 0.0, 0.0])  # -1.0 projected to 0, masked to 0
    x2 = opt.update(x1, np.array([1.0, 0.0, 0.0]), mask)
    # u = 0.9 * (1, 4, 0) + (1, 0, 0) = (1.9, 3.6, 0); x1 - 0.5 u = (1.55, -1.8, 0)
    np.testing.assert_allclose(x2, [1.55, 0.0, 0.0])
    assert np.array_equal(project(np.array([-1.0, 2.0]), None), [0.0, 2.0])


def test_block_mean_ties_the_masked_voxels_of_each_block():
    rng = np.random.default_rng(3)
    field = rng.normal(size=(5, 4, 3))
    mask = rng.uniform(size=field.shape) < 0.7
    assert np.array_equal(block_mean(field, mask, 1), np.where(mask, field, 0.0))
    tied = block_mean(field, mask, 2)
    assert np.all(tied[~mask] == 0.0)
    for bx in range(3):  # blocks 2 x 2 x 2, smaller at the edges (5 = 2 + 2 + 1, 3 = 2 + 1)
        for by in range(2):
            for bz in range(2):
                sl = (slice(2 * bx, 2 * bx + 2), slice(2 * by, 2 * by + 2),
                      slice(2 * bz, 2 * bz + 2))
                inside = mask[sl]
                if inside.any():
                    np.testing.assert_allclose(tied[sl][inside], field[sl][inside].mean())
    # the sum over the mask is kept: a tied step moves the block's total like the field
    np.testing.assert_allclose(tied[mask].sum(), field[mask].sum())
    with pytest.raises(ValueError, match="voxel_blocks"):
        RetrievalConfig(voxel_blocks=(2, 1))


def test_defaults_and_per_stage_settings_left_at_none():
    """The defaults are the settings measured on three scenes (docs/benchmarks.md), and a
    per-stage setting left at None takes its default at every stage (L-BFGS-B's own: no
    smoothing, two equal path stores)."""
    default = RetrievalConfig()
    assert (default.optimizer, default.step, default.stages, default.step_decay) == (
        "adam", 0.5, (2,), 0.5)
    assert (default.stage_photons, default.gradient_smoothing, default.image_photons) == (
        (1.0,), (1.0,), (2.0,))
    assert default.priors == (Prior("l1", 0.01, "noise"), Prior("smoothness", 1e-4, "noise"))
    assert default.averaging == "ema"
    assert (default.schedule, default.plateau, default.photons) == ("noise", "photons", "auto")
    three = RetrievalConfig(stages=(4, 2, 1))
    assert three.stage_photons == three.stage_steps == (1.0, 1.0, 1.0)
    assert three.gradient_smoothing == (1.0,) * 3 and three.image_photons == (2.0,) * 3
    assert three.voxel_blocks == (1, 1, 1)
    quasi_newton = RetrievalConfig(optimizer="lbfgsb", stages=(2, 1))
    assert quasi_newton.gradient_smoothing == (0.0, 0.0)
    assert quasi_newton.image_photons == (1.0, 1.0) and quasi_newton.priors == ()


def test_smoothed_gradient_is_a_symmetric_positive_preconditioner():
    rng = np.random.default_rng(4)
    shape = (9, 8, 7)
    mask = rng.uniform(size=shape) < 0.6
    u, v = rng.normal(size=shape), rng.normal(size=shape)
    assert np.array_equal(smoothed_gradient(u, mask, 0.0), np.where(mask, u, 0.0))
    su, sv = smoothed_gradient(u, mask, 1.5), smoothed_gradient(v, mask, 1.5)
    assert np.all(su[~mask] == 0.0)
    # u . S v = v . S u, and g . S g > 0: a descent direction with the same stationary points
    assert np.vdot(u, sv) == pytest.approx(np.vdot(v, su), rel=1e-12)
    for g in (u, v, rng.normal(size=shape)):
        assert np.vdot(g, smoothed_gradient(g, mask, 1.5)) > 0.0
    # a single voxel's gradient spreads over its neighbours as the Gaussian's weights
    one = np.zeros(shape)
    one[4, 4, 3] = 1.0
    spread = smoothed_gradient(one, np.ones(shape, bool), 1.0)
    g1 = np.exp(-0.5) / np.exp(0.0)  # a neighbour one voxel away, relative to the centre
    assert spread[5, 4, 3] / spread[4, 4, 3] == pytest.approx(g1, rel=1e-6)
    assert spread[5, 5, 3] / spread[4, 4, 3] == pytest.approx(g1**2, rel=1e-6)
    # the noise of independent voxels is averaged down, a smooth field is kept
    noise = rng.normal(size=(40, 40, 40))
    full = np.ones(noise.shape, bool)
    assert smoothed_gradient(noise, full, 2.0)[8:-8, 8:-8, 8:-8].std() < 0.1
    ramp = np.broadcast_to(np.linspace(0.0, 1.0, 40), noise.shape)
    np.testing.assert_allclose(smoothed_gradient(ramp, full, 2.0)[8:-8, 8:-8, 8:-8],
                               ramp[8:-8, 8:-8, 8:-8], atol=1e-9)
    with pytest.raises(ValueError, match="gradient_smoothing"):
        RetrievalConfig(stages=(2, 1), stage_photons=(1.0, 1.0), gradient_smoothing=(1.0,))
    with pytest.raises(ValueError, match="gradient_smoothing must be >= 0"):
        RetrievalConfig(stages=(1,), stage_photons=(1.0,), gradient_smoothing=(-1.0,))


def test_epsilon_delta():
    truth = np.array([1.0, 2.0, 3.0, 0.0])
    assert epsilon_delta(truth, truth) == (0.0, 0.0)
    eps, delta = epsilon_delta(truth, np.array([2.0, 2.0, 3.0, 1.0]))
    assert eps == pytest.approx(2.0 / 6.0) and delta == pytest.approx(-2.0 / 6.0)
    with pytest.raises(ValueError, match="grids"):
        epsilon_delta(truth, truth[:3])


def test_epsilon_split_adds_up_to_epsilon():
    truth = np.array([1.0, 2.0, 3.0, 0.0, 0.0])
    estimate = np.array([2.0, 0.5, 3.0, 1.0, 0.5])
    split = epsilon_split(truth, estimate)
    # outside the cloud: 1 + 0.5; inside: |1 - 2| + |2 - 0.5|; the cloud holds 5.5
    assert split == pytest.approx({"outside": 1.5 / 6, "inside": 2.5 / 6, "cloud_mass": 5.5 / 6})
    assert split["outside"] + split["inside"] == pytest.approx(epsilon_delta(truth, estimate)[0])
    with pytest.raises(ValueError, match="zero everywhere"):
        epsilon_split(np.zeros(3), np.ones(3))


def test_coarse_measurements_are_block_means():
    images = render(gradient_medium(), gradient_scene(), photons=20_000, progress=False)
    coarse = coarse_measurements(images, 2)
    assert coarse.radiance.shape == (2, 3, 3)
    np.testing.assert_allclose(
        coarse.radiance.values[1, 2, 0], images.radiance.values[1, 4:6, 0:2].mean()
    )
    assert coarse.attrs["optics"] == images.attrs["optics"]  # the attributes stay


@pytest.fixture(scope="module")
def measurements():
    return render(gradient_medium(), gradient_scene(), photons=4_000_000, seed=77,
                  progress=False)


def initial_guess():
    init = gradient_medium()
    truth = init["cloud_extinction"].values
    init["cloud_extinction"].values = np.where(truth > 0, 8.0, 0.0)  # the carved hull, flat
    return init


# the tiny retrievals' settings: those the tests were calibrated on (no prior, 4x image
# photons, the step halved at a 2 % plateau), not today's defaults
CONFIG = dict(photons=40_000, step=1.0, stages=(2, 1), stage_photons=(0.5, 1.0),
              image_photons=(4.0, 4.0), priors=(), schedule="threshold",
              saturation_window=3, plateau="step", checkpoint_every=3)


LBFGSB = dict(CONFIG, optimizer="lbfgsb", trust_region=0.3, image_photons=None)


@pytest.mark.parametrize("settings", [CONFIG, dict(LBFGSB, period=3)], ids=["adam", "lbfgsb"])
def test_checkpoint_resume_continues_exactly(tmp_path, measurements, settings):
    straight = Retrieval(measurements, initial_guess(), RetrievalConfig(iterations=6, **settings))
    straight.run(progress=False)
    first = Retrieval(measurements, initial_guess(), RetrievalConfig(iterations=3, **settings))
    first.run(checkpoint=tmp_path / "ck.nc", progress=False)
    resumed = Retrieval.resume(tmp_path / "ck.nc", measurements, initial_guess(), iterations=6)
    resumed.run(progress=False)
    np.testing.assert_array_equal(resumed.state.extinction, straight.state.extinction)
    np.testing.assert_array_equal(resumed.state.log["loss"], straight.state.log["loss"])


def test_step_decays_when_the_loss_saturates_at_the_last_stage(tmp_path, measurements):
    """The threshold schedule (the earlier default): a decay when the loss falls less than
    2 % from one window to the next."""
    config = RetrievalConfig(iterations=0, photons=1_000, stages=(1,), stage_photons=(1.0,),
                             schedule="threshold", plateau="step", saturation_window=2,
                             step_decay=0.5)
    run = Retrieval(measurements, initial_guess(), config)
    s = run.state
    s.log["loss"], s.log["stage"] = [1.0, 1.0, 1.0, 1.0], [0.0] * 4
    assert advance(config, s, 1.0) == [("step x 0.5 (now 0.5 of its start)", "plateau: the "
                                        "loss fell less than 2% over 2 iterations")]
    assert (s.step_scale, s.decayed_at, s.stage) == (0.5, 4, 0)
    assert advance(config, s, 1.0) == []  # the window restarts after a decay
    assert s.step_scale == 0.5
    s.log["loss"] += [2.0, 1.0, 0.5, 0.25]  # decreasing: no decay
    s.log["stage"] += [0.0] * 4
    assert advance(config, s, 1.0) == []
    assert s.step_scale == 0.5
    for key in LOG_FIELDS:
        if key not in ("loss", "stage"):
            s.log[key] = [0.0] * 8
    run.save_checkpoint(tmp_path / "ck.nc")
    resumed = Retrieval.resume(tmp_path / "ck.nc", measurements, initial_guess())
    assert (resumed.state.step_scale, resumed.state.decayed_at) == (0.5, 4)
    with pytest.raises(ValueError, match="step_decay"):
        RetrievalConfig(step_decay=0.0)


def test_each_stage_steps_with_its_own_step(measurements):
    config = RetrievalConfig(iterations=0, photons=1_000, step=2.0, stages=(2, 1),
                             stage_photons=(1.0, 1.0), stage_steps=(1.0, 0.25), step_decay=0.5,
                             image_photons=(1.0, 1.0))
    run = Retrieval(measurements, initial_guess(), config)
    assert run.step()["photons"] == 2_000  # images and gradient, 1,000 each
    assert run.optimizer.step == 2.0
    run.state.stage, run.state.step_scale = 1, 0.5  # the last stage, its step decayed once
    run.step()
    assert run.optimizer.step == 2.0 * 0.25 * 0.5
    with pytest.raises(ValueError, match="stage_steps"):
        RetrievalConfig(stages=(2, 1), stage_photons=(1.0, 1.0), stage_steps=(1.0,))
    with pytest.raises(ValueError, match="stage_steps must be > 0"):
        RetrievalConfig(stages=(1,), stage_photons=(1.0,), stage_steps=(0.0,))


def test_residual_images_take_their_own_photon_count(measurements, monkeypatch):
    import cloudct.retrieval.loop as loop

    seen = {}
    real = loop.loss_and_gradient

    def spy(*args, **kwargs):
        seen.update(photons=kwargs["photons"], gradient_photons=kwargs["gradient_photons"])
        return real(*args, **kwargs)

    monkeypatch.setattr(loop, "loss_and_gradient", spy)
    config = RetrievalConfig(iterations=0, photons=1_000, image_photons=(3.0, 1.0),
                             stages=(2, 1), stage_photons=(0.5, 1.0))
    run = Retrieval(measurements, initial_guess(), config)
    assert run.step()["photons"] == 1_500 + 500
    assert seen == {"photons": 1_500, "gradient_photons": 500}
    run.state.stage = 1
    assert run.step()["photons"] == 1_000 + 1_000
    with pytest.raises(ValueError, match="image_photons must be > 0"):
        RetrievalConfig(stages=(1,), stage_photons=(1.0,), image_photons=(0.0,))
    with pytest.raises(ValueError, match="image_photons and estimator must have the same"):
        RetrievalConfig(stages=(2, 1), stage_photons=(1.0, 1.0), image_photons=(1.0,))


@pytest.mark.parametrize("term", sorted(PRIORS))
def test_each_prior_term_enters_the_step_with_its_weight(measurements, monkeypatch, term):
    """With the data gradient set to zero, one SGD step moves every masked voxel by -step x
    weight x L_empty x dPhi/dbeta (L_empty the loss of a dark medium at the stage's pixels),
    projected onto beta >= 0, leaves the rest at zero, and logs weight x L_empty x Phi; for
    the L1 term dPhi/dbeta is the voxel volume."""
    import cloudct.retrieval.loop as loop

    real = loop.loss_and_gradient

    def data_gradient_zero(*args, **kwargs):
        result = real(*args, **kwargs)
        result.gradient = np.zeros_like(result.gradient)
        return result

    monkeypatch.setattr(loop, "loss_and_gradient", data_gradient_zero)
    prior = Prior(term, 0.2)
    config = RetrievalConfig(iterations=0, photons=1_000, optimizer="sgd", step=50.0,
                             stages=(2,), gradient_smoothing=(0.0,), image_photons=(1.0,),
                             priors=(prior,))
    start = initial_guess()
    beta = start["cloud_extinction"].values
    beta = np.where(beta > 0, beta * np.linspace(0.5, 1.5, beta.size).reshape(beta.shape), 0.0)
    start["cloud_extinction"].values = beta
    run = Retrieval(measurements, start, config)
    row = run.step()
    coarse = coarse_measurements(measurements, 2)["radiance"].values
    dark_loss = 0.5 * np.sum(coarse**2)
    phi, d_phi = prior.value_and_gradient(beta, PriorGrid.of(start))
    hull = beta > 0
    expected = np.where(hull, np.maximum(beta - 50.0 * 0.2 * dark_loss * d_phi, 0.0), 0.0)
    np.testing.assert_allclose(run.state.extinction, expected, rtol=1e-9, atol=1e-12)
    assert row["prior"] == pytest.approx(0.2 * dark_loss * phi, rel=1e-12)
    if term == "l1":
        x = start["x"].values
        np.testing.assert_allclose(d_phi, (x[1] - x[0]) ** 3)  # the test grid is cubic
    with pytest.raises(ValueError, match="weight must be >= 0"):
        RetrievalConfig(priors=(Prior(term, -1.0),))


def test_checkpoint_from_another_run_is_refused(tmp_path, measurements):
    run = Retrieval(measurements, initial_guess(), RetrievalConfig(iterations=1, **CONFIG))
    run.run(checkpoint=tmp_path / "ck.nc", progress=False)
    other = measurements.copy(deep=True)
    other["radiance"] = other["radiance"] * 1.01
    with pytest.raises(ValueError, match="another run"):
        Retrieval.resume(tmp_path / "ck.nc", other, initial_guess())


def test_tiny_retrieval_lowers_epsilon(measurements):
    truth = gradient_medium()
    run = Retrieval(measurements, initial_guess(), RetrievalConfig(iterations=40, **CONFIG),
                    truth=truth)
    result = run.run(progress=False)
    eps0, _ = epsilon_delta(truth["cloud_extinction"].values,
                            initial_guess()["cloud_extinction"].values)
    eps = result["log_epsilon"].values
    assert eps[-5:].mean() < 0.6 * eps0, (eps0, eps)
    # losses of different stages differ in pixel count: compare within the last stage
    stage = result["log_stage"].values
    last = result["log_loss"].values[stage == stage.max()]
    assert len(last) >= 10 and last[-5:].mean() < 0.8 * last[:3].mean(), last


def test_tiny_retrieval_with_recycling(measurements):
    """Alg. 2: paths recycled for 5 iterations at a time; epsilon still falls, and the log
    records the resampling decisions and the correction factors' ESS."""
    truth = gradient_medium()
    config = RetrievalConfig(iterations=40, recycling="fixed", period=5, **CONFIG)
    result = Retrieval(measurements, initial_guess(), config, truth=truth).run(progress=False)
    resampled = result["log_resampled"].values
    assert 8 <= resampled.sum() <= 10  # every 5th iteration, and at each new stage
    assert np.all(result["log_ess"].values[resampled == 0] < 1.0)
    eps0, _ = epsilon_delta(truth["cloud_extinction"].values,
                            initial_guess()["cloud_extinction"].values)
    assert result["log_epsilon"].values[-5:].mean() < 0.75 * eps0


def test_tiny_retrieval_recycling_the_combined_estimator(measurements, monkeypatch):
    """Recycling with the combined estimator's images and gradient: the recycler replays
    the forward half and traces the backward half fresh (a Recycler told the method and
    the estimator); resampled every 5th iteration, epsilon falls. (The estimator's
    agreement with fresh paths: tests/test_combined_recycling.py.)"""
    import cloudct.recycling.recycler as recycler

    made = []

    class Noted(recycler.Recycler):
        def __init__(self, *args, **kw):
            made.append((kw["image_method"], kw["gradient_estimator"]))
            super().__init__(*args, **kw)

    monkeypatch.setattr(recycler, "Recycler", Noted)
    truth = gradient_medium()
    config = RetrievalConfig(iterations=12, recycling="fixed", period=5, **CONFIG,
                             estimator=("combined", "combined"), image_method="combined")
    result = Retrieval(measurements, initial_guess(), config, truth=truth).run(progress=False)
    assert made and set(made) == {("combined", "combined")}
    resampled = result["log_resampled"].values
    assert 3 <= resampled.sum() <= 4  # every 5th iteration, and at a new stage
    eps0, _ = epsilon_delta(truth["cloud_extinction"].values,
                            initial_guess()["cloud_extinction"].values)
    assert result["log_epsilon"].values[-3:].mean() < 0.9 * eps0


def test_tiny_retrieval_recycling_only_the_images(measurements):
    """``recycle_gradient=False``: the residual's images come from the recycled store
    (resampled every 5th iteration), the gradient from fresh paths every iteration; epsilon
    falls as with both stores recycled, and no gradient store is ever recorded."""
    truth = gradient_medium()
    config = RetrievalConfig(iterations=40, recycling="fixed", period=5,
                             recycle_gradient=False, **CONFIG)
    run = Retrieval(measurements, initial_guess(), config, truth=truth)
    result = run.run(progress=False)
    assert run._recycler.gradient_store is None
    assert 8 <= result["log_resampled"].values.sum() <= 10
    eps0, _ = epsilon_delta(truth["cloud_extinction"].values,
                            initial_guess()["cloud_extinction"].values)
    assert result["log_epsilon"].values[-5:].mean() < 0.75 * eps0
    both = RetrievalConfig(recycling="fixed", period=5, **CONFIG)
    assert run.id != Retrieval(measurements, initial_guess(), both).id
    with pytest.raises(ValueError, match="needs a recycling policy"):
        RetrievalConfig(recycle_gradient=False)


def test_recycling_memory_chooses_how_the_paths_are_stored(measurements):
    """``recycling_memory`` is the recycler's budget: a budget that cannot hold the camera
    connections stores voxel crossings, a larger one connections (which replay faster);
    it does not enter the run id (storage modes differ in rounding only)."""
    from cloudct.recycling.store import MemoryBudgetError

    def stores(memory):
        config = RetrievalConfig(iterations=1, recycling="fixed", period=5,
                                 recycling_memory=memory, **CONFIG)
        run = Retrieval(measurements, initial_guess(), config)
        run.run(progress=False)
        return run, run._recycler.image_store

    run, store = stores(1.0)
    assert store.storage == run._recycler.gradient_store.storage == "connections"
    both = (store, run._recycler.gradient_store)
    crossings = sum(s.nbytes - s.connection_nbytes for s in both)  # without connections
    small, store = stores((crossings + run._recycler.nbytes) / 2 / 2**30)  # halfway
    assert store.storage == small._recycler.gradient_store.storage == "crossings"
    assert run.id == small.id == Retrieval(measurements, initial_guess(),
                                           RetrievalConfig(recycling="fixed", period=5,
                                                           **CONFIG)).id
    with pytest.raises(MemoryBudgetError):
        stores(1e-6)
    with pytest.raises(ValueError, match="recycling_memory"):
        RetrievalConfig(recycling_memory=0.0)


def test_tiny_retrieval_with_lbfgsb_windows(measurements):
    """Every iteration an L-BFGS-B window of 8 evaluations on fixed paths: the fresh loss
    at the windows' starts falls by more than two thirds (about tenfold, seed 0) and
    epsilon by 30 % or more."""
    truth = gradient_medium()
    config = RetrievalConfig(iterations=8, period=8, **LBFGSB)
    run = Retrieval(measurements, initial_guess(), config, truth=truth)
    result = run.run(progress=False)
    assert run.optimizer is None and config.gradient_smoothing == (0.0, 0.0)
    assert config.image_photons == (1.0, 1.0)  # the L-BFGS-B defaults: two equal stores
    eps0, _ = epsilon_delta(truth["cloud_extinction"].values,
                            initial_guess()["cloud_extinction"].values)
    loss = result["log_loss"].values
    assert loss[-3:].mean() < 0.3 * loss[0], loss
    assert result["log_epsilon"].values[-3:].mean() < 0.7 * eps0, result["log_epsilon"].values
    assert np.all(result["log_resampled"].values == 1.0)  # new paths every window


def test_lbfgsb_refuses_what_it_does_not_use(measurements):
    for settings in (dict(recycling="fixed"), dict(voxel_blocks=(2,)),
                     dict(gradient_smoothing=(1.0,)),
                     dict(priors=(Prior("l1", 0.1),))):
        with pytest.raises(ValueError, match="lbfgsb"):
            RetrievalConfig(optimizer="lbfgsb", **settings)
    with pytest.raises(ValueError, match="trust_region"):
        RetrievalConfig(optimizer="lbfgsb", trust_region=1.5)
    with pytest.raises(ValueError, match="optimizer must be one of"):
        RetrievalConfig(optimizer="newton")
    with pytest.raises(ValueError, match="no client"):
        Retrieval(measurements, initial_guess(), RetrievalConfig(optimizer="lbfgsb"),
                  client="tcp://127.0.0.1:1")
    # the trust region and the sparsity fingerprint only the runs they act on
    def run_id(**settings):
        return Retrieval(measurements, initial_guess(), RetrievalConfig(**settings)).id

    assert run_id(trust_region=0.3) == run_id(trust_region=0.5)
    l1 = Prior("l1", 0.1)
    assert run_id(priors=(l1,)) != run_id() != run_id(priors=())
    assert run_id(priors=()) == run_id(priors=(Prior("l1", 0.0),))
    assert run_id(optimizer="lbfgsb", trust_region=0.3) != run_id(optimizer="lbfgsb",
                                                                  trust_region=0.5)


def test_cli_retrieve_passes_the_coarse_to_fine_options(tmp_path, measurements, capsys):
    """``cloudct retrieve`` sets stages, photons per stage, voxel blocks, saturation window,
    step decay, steps per stage and sparsity, and records them in the result's settings."""
    import json

    import xarray as xr

    from cloudct.cli import main
    from cloudct.measurements import save_measurements
    from cloudct.medium import save_medium

    save_measurements(measurements, tmp_path / "meas.nc")
    save_medium(initial_guess(), tmp_path / "init.nc")
    out = tmp_path / "r.nc"
    argv = ["retrieve", str(tmp_path / "meas.nc"), "--init", str(tmp_path / "init.nc"),
            "--iterations", "2", "--photons", "2000", "--stages", "2", "1",
            "--stage-photons", "0.5", "2", "--voxel-blocks", "2", "1",
            "--saturation-window", "6", "--step-decay", "0.5", "--stage-steps", "1", "0.25",
            "--gradient-smoothing", "1.5", "0", "--image-photons", "1", "3", "--sparsity",
            "0.05", "--min-ess", "0.4", "--recycling-memory", "0.5", "--fresh-gradient",
            "--recycling", "fixed", "-o", str(out)]
    assert main(argv) == 0
    config = json.loads(xr.load_dataset(out).attrs["config"])
    assert config["stages"] == [2, 1] and config["stage_photons"] == [0.5, 2.0]
    assert config["voxel_blocks"] == [2, 1] and config["stage_steps"] == [1.0, 0.25]
    assert config["gradient_smoothing"] == [1.5, 0.0] and config["image_photons"] == [1.0, 3.0]
    assert (config["saturation_window"], config["step_decay"]) == (6, 0.5)
    assert {"term": "l1", "weight": 0.05, "schedule": "noise", "options": {}} in config["priors"]
    assert (config["min_ess"], config["recycling_memory"]) == (0.4, 0.5)
    assert (config["recycling"], config["recycle_gradient"]) == ("fixed", False)
    assert main(argv) != 0  # the result exists
    assert "exists (use --overwrite)" in capsys.readouterr().err
    quasi_newton = [*argv[:4], "--iterations", "1", "--photons", "2000", "--optimizer",
                    "lbfgsb", "--trust-region", "0.2", "--period", "3", "-o",
                    str(tmp_path / "lbfgsb.nc")]
    assert main(quasi_newton) == 0
    config = json.loads(xr.load_dataset(tmp_path / "lbfgsb.nc").attrs["config"])
    assert (config["optimizer"], config["trust_region"], config["period"]) == ("lbfgsb", 0.2, 3)
    assert config["stages"] == [2] and config["gradient_smoothing"] == [0.0]
    assert main([*argv[:-2], "--voxel-blocks", "2", "-o", str(tmp_path / "other.nc")]) != 0
    assert "same, non-zero length" in capsys.readouterr().err


def test_cli_demo_runs_the_whole_chain_with_the_retrieve_defaults(tmp_path, capsys):
    """``cloudct demo`` (the README's main job) at a tiny photon count: measurements, truth,
    carved start, result, checkpoint and report are written, the run uses ``cloudct
    retrieve``'s defaults but for the iterations' time, and a second demo into the same
    directory is refused."""
    import json

    import xarray as xr

    from cloudct.cli import main

    out = tmp_path / "demo"
    argv = ["demo", "-o", str(out), "--measurement-photons", "100000", "--iterations", "2",
            "--photons", "2000"]
    assert main(argv) == 0
    assert "epsilon" in capsys.readouterr().out
    for name in ("measurements.nc", "truth.nc", "init.nc", "result.nc", "checkpoint.nc",
                 "report/summary.md"):
        assert (out / name).is_file(), name
    result = xr.load_dataset(out / "result.nc")
    assert RetrievalConfig(**json.loads(result.attrs["config"])) == RetrievalConfig(
        iterations=2, photons=2_000)
    assert np.isfinite(result["log_epsilon"].values).all() and result.sizes["iteration"] == 2
    assert main(argv) != 0
    assert "exists (use --overwrite)" in capsys.readouterr().err


def test_cli_report_writes_figures_and_the_error_split(tmp_path, measurements):
    """``cloudct report RESULT --truth --measurements``: the figures and a summary whose
    epsilon, delta and epsilon split are those of the result against the truth."""
    from cloudct.cli import main
    from cloudct.measurements import save_measurements
    from cloudct.medium import save_medium

    truth = gradient_medium()
    result = Retrieval(measurements, initial_guess(), RetrievalConfig(iterations=3, **CONFIG),
                       truth=truth).run(progress=False)
    result.to_netcdf(tmp_path / "r.nc")
    save_medium(truth, tmp_path / "truth.nc")
    save_measurements(measurements, tmp_path / "meas.nc")
    out = tmp_path / "report"
    assert main(["report", str(tmp_path / "r.nc"), "--truth", str(tmp_path / "truth.nc"),
                 "--measurements", str(tmp_path / "meas.nc"), "-o", str(out)]) == 0
    for name in ("loss", "epsilon_delta", "slices", "scatter", "images"):
        assert (out / f"{name}.png").stat().st_size > 1000, name
    summary = (out / "summary.md").read_text()
    beta, true_beta = result["cloud_extinction"].values, truth["cloud_extinction"].values
    eps, delta = epsilon_delta(true_beta, beta)
    split = epsilon_split(true_beta, beta)
    assert f"| {eps:.1%} | {delta:+.1%} |" in summary
    assert f"| {split['outside']:.1%} | {split['inside']:.1%} | {split['cloud_mass']:.1%} |" \
        in summary
    # a masked (NaN) pixel is left out of the image difference, not turned into a NaN
    masked = measurements.copy(deep=True)
    masked["radiance"][0, 0, 0] = np.nan
    summary = write_report(result, tmp_path / "masked", measurements=masked,
                           render_photons=2000).read_text()
    difference = summary.split("Relative L1 image difference: ")[1].split("%")[0]
    assert np.isfinite(float(difference)), difference


# ----------------------------------------------------------------------------------------
# The gradient estimator of each stage, and iterate averaging
# ----------------------------------------------------------------------------------------


def test_estimator_settings_are_checked_and_fingerprinted_only_where_they_act(measurements):
    default = RetrievalConfig()
    assert default.estimator == ("sm",) and default.pixel_sampling == "residual"
    # where stored forward paths are replayed, the score function
    assert RetrievalConfig(recycling="fixed").estimator == ("score",)
    assert RetrievalConfig(optimizer="lbfgsb", stages=(4, 2)).estimator == ("score", "score")
    assert RetrievalConfig(estimator=("score",)).pixel_sampling == "uniform"
    score = RetrievalConfig(estimator=("score",))
    assert run_id(measurements, score) == run_id(  # checkpoints of earlier runs resume
        measurements, RetrievalConfig(estimator=("score",), pixel_sampling="uniform"))
    assert run_id(measurements, score) != run_id(measurements, default)
    assert run_id(measurements, RetrievalConfig(averaging="ema")) == run_id(
        measurements, default)  # the average does not change the iterates
    with pytest.raises(ValueError, match="estimator must be one of"):
        RetrievalConfig(estimator=("mis",))
    with pytest.raises(ValueError, match="same, non-zero length"):
        RetrievalConfig(stages=(2, 1), estimator=("sm",))
    with pytest.raises(ValueError, match="camera-side"):
        RetrievalConfig(estimator=("score",), pixel_sampling="residual")
    with pytest.raises(ValueError, match="pixel_sampling must be one of"):
        RetrievalConfig(estimator=("drt",), pixel_sampling="bright")
    with pytest.raises(ValueError, match="replay stored forward paths"):
        RetrievalConfig(estimator=("sm",), recycling="adaptive")
    with pytest.raises(ValueError, match="lbfgsb.*score"):
        RetrievalConfig(estimator=("drt",), optimizer="lbfgsb")
    RetrievalConfig(estimator=("sm",), recycling="adaptive", recycle_gradient=False)
    with pytest.raises(ValueError, match="averaging must be one of"):
        RetrievalConfig(averaging="median")
    with pytest.raises(ValueError, match="averaging_decay"):
        RetrievalConfig(averaging="ema", averaging_decay=1.0)


@pytest.mark.parametrize("estimator, sampling", [(("drt", "sm"), "residual"),
                                                 (("sm", "sm"), "uniform")])
def test_tiny_retrieval_with_camera_side_gradients(measurements, estimator, sampling):
    truth = gradient_medium()
    config = RetrievalConfig(iterations=30, **{**CONFIG, "photons": 20_000},
                             estimator=estimator, pixel_sampling=sampling)
    run = Retrieval(measurements, initial_guess(), config, truth=truth)
    result = run.run(progress=False)
    eps0, _ = epsilon_delta(truth["cloud_extinction"].values,
                            initial_guess()["cloud_extinction"].values)
    eps = result["log_epsilon"].values
    assert eps[-5:].mean() < 0.6 * eps0, (eps0, eps)
    seconds = result["log_gradient_seconds"].values
    assert np.all(np.isfinite(seconds)) and np.all(seconds > 0)


def test_tiny_retrieval_with_the_combined_estimator(measurements, monkeypatch):
    """The combined gradient and the residual's images by the combined estimator
    (``image_method``) lower epsilon as the others do; lbfgsb, which replays forward paths
    by the score function, refuses both."""
    import cloudct.retrieval.loss as loss

    methods = []

    def render_and_note(*args, method="forward", **kw):
        methods.append(method)
        return render(*args, method=method, **kw)

    monkeypatch.setattr(loss, "render", render_and_note)
    truth = gradient_medium()
    config = RetrievalConfig(iterations=30, **{**CONFIG, "photons": 20_000},
                             estimator=("combined", "combined"), image_method="combined")
    result = Retrieval(measurements, initial_guess(), config, truth=truth).run(progress=False)
    assert methods == ["combined"] * 30
    eps0, _ = epsilon_delta(truth["cloud_extinction"].values,
                            initial_guess()["cloud_extinction"].values)
    eps = result["log_epsilon"].values
    assert eps[-5:].mean() < 0.6 * eps0, (eps0, eps)
    with pytest.raises(ValueError, match="image_method 'combined' is not lbfgsb's"):
        RetrievalConfig(image_method="combined", optimizer="lbfgsb")
    with pytest.raises(ValueError, match="lbfgsb.*score"):
        RetrievalConfig(estimator=("combined",), optimizer="lbfgsb")
    with pytest.raises(ValueError, match="image_method must be one of"):
        RetrievalConfig(image_method="backward")
    # fingerprinted where it acts (forward: as before the setting, old checkpoints resume)
    assert run_id(measurements, RetrievalConfig(image_method="combined")) != run_id(
        measurements, RetrievalConfig())


def test_iterate_averages_and_their_restarts(measurements, monkeypatch):
    """The uniform average is the mean of the iterates since the last stage change; the
    moving average is the decay-weighted mean (Adam's bias correction), the first iterate
    itself after a restart."""
    import cloudct.retrieval.loop as loop

    truth = gradient_medium()
    settings = dict(CONFIG, photons=5_000)
    runs = {kind: Retrieval(measurements, initial_guess(),
                            RetrievalConfig(iterations=0, averaging=kind, **settings),
                            truth=truth) for kind in ("uniform", "ema")}
    iterates = []
    for _ in range(4):
        for run in runs.values():
            run.step()
        np.testing.assert_array_equal(runs["uniform"].state.extinction,
                                      runs["ema"].state.extinction)
        iterates.append(runs["uniform"].state.extinction.copy())
    np.testing.assert_allclose(runs["uniform"].average(), np.mean(iterates, axis=0),
                               rtol=1e-12)
    weights = 0.9 ** np.arange(3, -1, -1)
    np.testing.assert_allclose(
        runs["ema"].average(), np.tensordot(weights, iterates, axes=1) / weights.sum(),
        rtol=1e-12,
    )
    eps, delta = epsilon_delta(truth["cloud_extinction"].values, runs["ema"].average())
    assert runs["ema"].state.log["epsilon_average"][-1] == eps
    assert runs["ema"].state.log["delta_average"][-1] == delta
    result = runs["ema"].result()
    np.testing.assert_array_equal(result["cloud_extinction_average"].values,
                                  runs["ema"].average())
    np.testing.assert_array_equal(result["cloud_extinction"].values, iterates[-1])
    # a new stage restarts the average at its first iterate
    run = runs["uniform"]
    stage = run.state.stage

    def next_stage(config, state, seconds) -> list:
        state.stage += 1
        return []

    monkeypatch.setattr(loop, "advance", next_stage)  # the loss saturates
    run.step()
    assert run.state.stage == stage + 1 and run.average() is None
    monkeypatch.setattr(loop, "advance", lambda config, state, seconds: [])
    run.step()
    np.testing.assert_array_equal(run.average(), run.state.extinction)
    # without averaging: no average, NaN in the log
    plain = Retrieval(measurements, initial_guess(),
                      RetrievalConfig(iterations=1, averaging="none", **settings), truth=truth)
    out = plain.run(progress=False)
    assert "cloud_extinction_average" not in out
    assert np.isnan(out["log_epsilon_average"].values).all()


def test_checkpoint_resume_with_averaging_continues_exactly(tmp_path, measurements):
    settings = dict(CONFIG, photons=5_000, averaging="ema")
    straight = Retrieval(measurements, initial_guess(), RetrievalConfig(iterations=5, **settings))
    straight.run(progress=False)
    first = Retrieval(measurements, initial_guess(), RetrievalConfig(iterations=2, **settings))
    first.run(checkpoint=tmp_path / "ck.nc", progress=False)
    resumed = Retrieval.resume(tmp_path / "ck.nc", measurements, initial_guess(), iterations=5)
    resumed.run(progress=False)
    np.testing.assert_array_equal(resumed.average(), straight.average())
    assert resumed.state.average_weight == straight.state.average_weight
