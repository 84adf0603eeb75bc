"""The step schedule that reads the Monte Carlo noise (cloudct.retrieval.schedule): the
plateau test's false-alarm rate on synthetic losses of known noise, its power on a real
slowdown, the answers to a plateau (photons within their cap and the time limit, then the
step down to its floor), the fixed baseline, bounded updates, and a resumed run that
continues the schedule bitwise."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats
from test_retrieval import initial_guess
from test_score_gradient import gradient_medium, gradient_scene

from cloudct.mc.render import render
from cloudct.retrieval.config import RetrievalConfig
from cloudct.retrieval.loop import Retrieval
from cloudct.retrieval.optimizers import bounded_update
from cloudct.retrieval.priors import Prior
from cloudct.retrieval.schedule import (
    FIXED_FRACTIONS,
    ITERATIONS_LEFT,
    advance,
    loss_slope,
    noise_plateau,
    noise_weight,
)
from cloudct.retrieval.state import LOG_FIELDS, RetrievalState

WINDOW, ALPHA, TRIALS = 10, 0.05, 4000


def _binomial_bounds(p: float, n: int) -> tuple[float, float]:
    """Where n Bernoulli(p) trials' rate lies but with probability 1e-4."""
    lo, hi = stats.binom.interval(1 - 1e-4, n, p)
    return lo / n, hi / n


def test_the_slope_is_the_least_squares_slope():
    t = np.arange(7.0)
    slope = loss_slope(3.0 - 0.5 * t, np.full(7, np.nan))
    assert slope.slope == pytest.approx(-0.5) and slope.std_error == pytest.approx(0.0)
    assert slope.window == 7 and slope.t == -np.inf
    noisy = loss_slope(3.0 - 0.5 * t + np.array([0.1, -0.1, 0, 0.1, -0.1, 0, 0.05]),
                       np.full(7, 10.0))  # the losses' own errors dominate the scatter
    assert noisy.std_error == pytest.approx(10.0 / np.sqrt(np.sum((t - 3) ** 2)))


def test_on_a_flat_loss_a_decrease_is_seen_at_the_false_alarm_rate():
    """Flat plus Gaussian noise: the test claims a decrease (no plateau) in a fraction
    alpha of the windows when the noise is unknown (the t-test is exact), and in at most
    alpha when each loss's standard error is given (its floor makes it conservative)."""
    rng = np.random.default_rng(11)
    sigma = 0.03
    losses = 1.0 + sigma * rng.normal(size=(TRIALS, WINDOW))
    unknown = np.mean([not noise_plateau(row, np.full(WINDOW, np.nan), ALPHA)[0]
                       for row in losses])
    lo, hi = _binomial_bounds(ALPHA, TRIALS)
    assert lo <= unknown <= hi, unknown
    known = np.mean([not noise_plateau(row, np.full(WINDOW, sigma), ALPHA)[0]
                     for row in losses])
    assert known <= hi, known


def test_a_loss_that_falls_well_above_its_noise_is_not_a_plateau():
    rng = np.random.default_rng(12)
    sigma = 0.03
    t = np.arange(WINDOW) - (WINDOW - 1) / 2
    slope = -6.0 * sigma / np.sqrt(np.sum(t**2))  # six standard errors per window
    losses = 1.0 + slope * np.arange(WINDOW) + sigma * rng.normal(size=(TRIALS, WINDOW))
    plateaus = np.mean([noise_plateau(row, np.full(WINDOW, sigma), ALPHA)[0]
                        for row in losses])
    assert plateaus < 0.01, plateaus


def _state(losses, errors, photons=1000) -> RetrievalState:
    s = RetrievalState(iteration=len(losses), stage=0, extinction=np.zeros(1),
                       optimizer_state={}, photons=photons, photons_base=photons)
    s.log = {k: [0.0] * len(losses) for k in LOG_FIELDS}
    s.log["loss"], s.log["loss_std_error"] = list(losses), list(errors)
    return s


def test_a_real_slowdown_is_found_within_a_window():
    """A loss that falls fast, then levels off at its noise: no plateau while it falls,
    and one within a window of the levelling."""
    rng = np.random.default_rng(13)
    sigma = 0.002
    knee = 30
    t = np.arange(60)
    truth = np.where(t < knee, 1.0 - 0.02 * t, 1.0 - 0.02 * knee)
    config = RetrievalConfig(photons=1000, stages=(1,), saturation_window=WINDOW)
    found = []
    for _ in range(50):
        losses = truth + sigma * rng.normal(size=t.size)
        for n in range(1, t.size + 1):
            s = _state(losses[:n], np.full(n, sigma))
            if advance(config, s, 1.0):
                found.append(n)
                break
    found = np.array(found)
    assert found.size == 50 and found.min() > knee
    assert np.all(found <= knee + WINDOW + 2), found


def test_photons_grow_within_their_cap_and_the_time_limit_then_the_step_to_its_floor():
    config = RetrievalConfig(photons=1000, stages=(1,), saturation_window=WINDOW,
                             photon_growth=2.0, photon_cap=4.0, step_decay=0.5,
                             step_floor=0.25)
    flat = np.ones(WINDOW)
    s = _state(flat, np.full(WINDOW, 0.1))
    changes = []
    for _ in range(6):
        changes += [what for what, _ in advance(config, s, 1.0)]
        s.log = {k: v + v[:WINDOW] for k, v in s.log.items()}  # another flat window
    assert changes == ["photons 1000 -> 2000", "photons 2000 -> 4000",
                       "step x 0.5 (now 0.5 of its start)", "step x 0.5 (now 0.25 of its start)",
                       "no further change: the loss is at its noise floor"]
    assert (s.photons, s.step_scale, s.at_floor) == (4000, 0.25, True)
    # the time limit: a grown iteration must fit ITERATIONS_LEFT times in the time left
    timed = RetrievalConfig(photons=1000, stages=(1,), saturation_window=WINDOW,
                            time_limit=100.0)
    s = _state(flat, np.full(WINDOW, 0.1))
    s.elapsed = 100.0 - ITERATIONS_LEFT * 1.5 * 2.0 + 1.0  # just too little for 3 s each
    assert [w for w, _ in advance(timed, s, 2.0)] == ["step x 0.5 (now 0.5 of its start)"]
    s = _state(flat, np.full(WINDOW, 0.1))
    s.elapsed = 100.0 - ITERATIONS_LEFT * 1.5 * 2.0 - 1.0
    assert [w for w, _ in advance(timed, s, 2.0)] == ["photons 1000 -> 1500"]


def test_the_fixed_schedule_decays_at_its_fractions_of_the_run():
    config = RetrievalConfig(photons=1000, stages=(1,), schedule="fixed", time_limit=80.0,
                             step_floor=0.0)
    s = _state([1.0], [0.1])
    decays = []
    for elapsed in np.arange(0.0, 81.0, 5.0):
        s.elapsed = elapsed
        decays += [(elapsed, what) for what, _ in advance(config, s, 1.0)]
    assert [e for e, _ in decays] == [f * 80.0 for f in FIXED_FRACTIONS]
    assert s.step_scale == 0.5 ** len(FIXED_FRACTIONS)


def test_bounded_updates_neither_empty_nor_flood_a_voxel():
    before = np.array([10.0, 10.0, 0.0, 0.0])
    after = np.array([0.0, 100.0, 50.0, 0.0])
    bounded = bounded_update(before, after, 0.5, step=1.0)
    np.testing.assert_allclose(bounded, [4.5, 15.5, 0.5, 0.0])
    assert np.all(bounded >= 0.0)


def test_the_prior_weight_follows_the_gradients_noise():
    mask = np.array([True, True, False])
    multiple, rms = noise_weight(np.array([3.0, 4.0, 100.0]), mask, 0.0)
    assert (multiple, rms) == (1.0, pytest.approx(np.sqrt(12.5)))
    multiple, _ = noise_weight(np.array([1.5, 2.0, 100.0]), mask, rms)
    assert multiple == pytest.approx(0.5)


@pytest.fixture(scope="module")
def measurements():
    return render(gradient_medium(), gradient_scene(), photons=1_000_000, seed=77,
                  progress=False)


SETTINGS = dict(photons=4000, stages=(1,), saturation_window=5, significance=0.2,
                photon_growth=1.5, photon_cap=2.0, step_floor=0.25, max_change=0.5,
                priors=(Prior("l1", 0.01, "noise"),), checkpoint_every=1)


def test_a_resumed_run_continues_the_schedule_bitwise(tmp_path, measurements):
    straight = Retrieval(measurements, initial_guess(), RetrievalConfig(iterations=24,
                                                                        **SETTINGS))
    straight.run(progress=False)
    assert len(straight.state.decisions) >= 2, straight.state.decisions  # it did decide
    first = Retrieval(measurements, initial_guess(), RetrievalConfig(iterations=13, **SETTINGS))
    first.run(checkpoint=tmp_path / "ck.nc", progress=False)
    resumed = Retrieval.resume(tmp_path / "ck.nc", measurements, initial_guess(), iterations=24)
    resumed.run(progress=False)
    np.testing.assert_array_equal(resumed.state.extinction, straight.state.extinction)
    assert resumed.state.decisions == straight.state.decisions
    for key in ("loss", "loss_std_error", "photons", "step"):
        np.testing.assert_array_equal(resumed.state.log[key], straight.state.log[key])
    assert np.all(np.isfinite(straight.state.log["loss_std_error"]))
    assert (resumed.state.photons, resumed.state.step_scale) == (
        straight.state.photons, straight.state.step_scale)
