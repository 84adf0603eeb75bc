"""When a retrieval changes its own step or photons: the plateau test and its answers.

A first-order retrieval's loss falls until the medium's remaining error is hidden by the
Monte Carlo noise of the gradient; then a smaller step (or a less noisy gradient) is what
lets it fall further. The loss logged at each iteration is itself a Monte Carlo estimate
(images of independent photons), so "has it stopped falling?" is a statistical question.
Three schedules (``RetrievalConfig.schedule``):

- ``"noise"`` (the default): over the last ``saturation_window`` iterations since the last
  change, the least-squares slope b of the loss against the iteration and its standard error
  s_b (:func:`loss_slope`); the loss is on a **plateau** when the decrease is statistically
  indistinguishable from zero, ``b / s_b > -t_(1-alpha)`` with alpha = ``significance``
  (Student t with W - 2 degrees of freedom). On a flat loss the test sees a decrease that
  is not there with probability alpha (``tests/test_schedule.py`` measures it); on a loss
  that falls by more than its noise it waits. s_b is taken from the scatter of the losses
  about the line and, as a floor, from each iteration's own standard error
  (``loss_std_error``, from the images' batches: :func:`cloudct.retrieval.loss.
  loss_std_error`), so both the images' noise and the iterates' wander count.
- ``"threshold"`` (the earlier default): a plateau when the mean loss of the last window
  is less than ``saturation_tolerance`` below that of the window before. At a plateau the
  loss's noise meets that test about every other window, so the step keeps halving until
  the medium stops moving (docs/benchmarks.md).
- ``"fixed"``: no test; the step decays at fixed fractions of the run
  (:data:`FIXED_FRACTIONS` of the time limit, or of the iterations without one): the
  baseline.

The answer to a plateau (``plateau``): at a coarse stage, the next stage; at the last,
``"photons"`` grows the gradient paths (and the images' photons) by ``photon_growth`` up to
``photon_cap`` times the count the run settled at (Smith et al. 2018, "Don't decay the
learning rate, increase the batch size"; the path-recycling authors grow theirs 1.5x per
plateau), while an iteration of the grown count still fits :data:`ITERATIONS_LEFT` times
in the time left, and decays the step after that; ``"step"`` decays the step by
``step_decay``. The step never falls below ``step_floor`` of its start: at the cap and the
floor the run keeps iterating at its noise floor, and says so once in its decisions.
"""

from __future__ import annotations

import logging
import math
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from scipy import stats

from cloudct.retrieval.photon_budget import decision

if TYPE_CHECKING:
    from cloudct.retrieval.config import RetrievalConfig
    from cloudct.retrieval.state import ScheduleState

LOGGER = logging.getLogger(__name__)

SCHEDULES = ("noise", "threshold", "fixed")
PLATEAU_ANSWERS = ("photons", "step")
#: ``schedule = "fixed"``: the step decays when the run has used these fractions of its
#: time limit (or of its iterations, without one).
FIXED_FRACTIONS = (0.5, 0.75, 0.875)
#: Photons grow only while an iteration of the grown count fits this many times in the
#: time that is left.
ITERATIONS_LEFT = 10


class Slope(NamedTuple):
    """The loss's least-squares slope per iteration over a window, and its standard
    error."""

    slope: float
    std_error: float
    window: int

    @property
    def t(self) -> float:
        """The slope in standard errors (negative: falling)."""
        return self.slope / self.std_error if self.std_error > 0.0 else -math.inf

    def text(self) -> str:
        """How the evidence reads in a decision's reason."""
        return (f"loss slope {self.slope:.3g} +- {self.std_error:.2g} per iteration over the "
                f"last {self.window} (t = {self.t:.2f})")


def loss_slope(losses: np.ndarray, std_errors: np.ndarray) -> Slope:
    """Least-squares slope of ``losses`` (one per iteration, at least 3) against the
    iteration, and its standard error from the larger of the residuals' variance about the
    line and the losses' mean squared standard error (NaN errors are left out)."""
    losses = np.asarray(losses, dtype=float)
    n = losses.size
    t = np.arange(n) - (n - 1) / 2.0
    spread = float(np.sum(t**2))
    slope = float(np.sum(t * losses) / spread)
    residuals = losses - losses.mean() - slope * t
    variance = float(np.sum(residuals**2)) / (n - 2)
    errors = np.asarray(std_errors, dtype=float)
    errors = errors[np.isfinite(errors)]
    if errors.size:
        variance = max(variance, float(np.mean(errors**2)))
    return Slope(slope, math.sqrt(variance / spread), n)


def noise_plateau(losses: np.ndarray, std_errors: np.ndarray, significance: float
                  ) -> tuple[bool, Slope]:
    """Whether the loss's decrease over the window is indistinguishable from zero at level
    ``significance`` (one-sided), and the slope it was judged on.

    A loss falling by 0.1 per iteration with standard errors of 0.01 is no plateau; a
    flat one with that noise is:

    >>> import numpy as np
    >>> errors = np.full(20, 0.01)
    >>> noise_plateau(5.0 - 0.1 * np.arange(20), errors, 0.05)[0]
    False
    >>> flat = 5.0 + 0.01 * np.random.default_rng(0).standard_normal(20)
    >>> noise_plateau(flat, errors, 0.05)[0]
    True
    """
    slope = loss_slope(losses, std_errors)
    return bool(slope.t > -stats.t.isf(significance, slope.window - 2)), slope


def threshold_plateau(losses: np.ndarray, window: int, tolerance: float) -> bool:
    """The earlier rule: the last ``window`` losses' mean is less than ``tolerance``
    (relative) below the mean of the ``window`` before (``losses`` holds 2 windows)."""
    before = float(np.mean(losses[-2 * window:-window]))
    recent = float(np.mean(losses[-window:]))
    return before - recent < tolerance * before


def fixed_decays_due(elapsed: float, time_limit: float | None, iteration: int,
                     iterations: int) -> int:
    """How many of the fixed schedule's decays are due: the fractions of
    :data:`FIXED_FRACTIONS` of the time limit (else of the iterations) the run has used."""
    used = elapsed / time_limit if time_limit else iteration / max(iterations, 1)
    return sum(used >= f for f in FIXED_FRACTIONS)


def photons_fit(photons: int, growth: float, seconds: float, elapsed: float,
                time_limit: float | None) -> bool:
    """Whether an iteration of ``photons * growth`` paths, taking about ``seconds *
    growth``, fits :data:`ITERATIONS_LEFT` times in the time left (always, without a
    time limit)."""
    if time_limit is None:
        return True
    return ITERATIONS_LEFT * seconds * growth <= time_limit - elapsed


def noise_weight(gradient_std_error: np.ndarray, mask: np.ndarray, reference: float
                 ) -> tuple[float, float]:
    """``sparsity_schedule = "noise"``: the L1 prior's weight as a multiple of its setting,
    the gradient's root-mean-square standard error in the hull over ``reference`` (that of
    the stage's first iteration once ``photons = "auto"`` has settled; 0: this is the
    first). Returns (multiple, the rms error)."""
    rms = float(np.sqrt(np.mean(gradient_std_error[mask] ** 2))) if mask.any() else 0.0
    if reference <= 0.0 or rms <= 0.0:
        return 1.0, rms
    return rms / reference, rms


def advance(config: RetrievalConfig, state: ScheduleState, seconds: float
            ) -> list[tuple[str, str]]:
    """The schedule after an iteration that took ``seconds``: the stage, photons and step
    changed in ``state`` (and the window restarted) where the loss is on a plateau, or where
    the fixed schedule is due. Returns the changes made, as (what, why)."""
    s, cfg = state, config
    if cfg.schedule == "fixed":
        due = fixed_decays_due(s.elapsed, cfg.time_limit, s.iteration, cfg.iterations)
        changes = []
        while s.decays + s.stage < due and not s.at_floor:
            changes += _answer(cfg, s, seconds, f"fixed schedule: {due} of "
                               f"{len(FIXED_FRACTIONS)} changes due", plateau="step")
        return changes
    if not s.photons_settled or s.at_floor:
        return []
    window = cfg.saturation_window
    losses = s.log["loss"][s.decayed_at:]  # every change of stage restarts the window
    if cfg.schedule == "noise":
        if len(losses) < window:
            return []
        errors = s.log["loss_std_error"][-window:]
        plateau, slope = noise_plateau(np.array(losses[-window:]), np.array(errors),
                                       cfg.significance)
        why = f"plateau: {slope.text()}"
    else:
        if len(losses) < 2 * window:
            return []
        plateau = threshold_plateau(np.array(losses), window, cfg.saturation_tolerance)
        why = (f"plateau: the loss fell less than {cfg.saturation_tolerance:.0%} over "
               f"{window} iterations")
    return _answer(cfg, s, seconds, why, cfg.plateau) if plateau else []


def record_decisions(s: ScheduleState, changes: list[tuple[str, str]]) -> None:
    """Add the ``changes`` made after the state's last iteration, as (what, why), to its
    decisions, each said in one line of the log."""
    for what, why in changes:
        row = decision(s.iteration, what, why)
        s.decisions.append(row)
        LOGGER.info("after iteration %d: %s (%s)", row["iteration"], what, why)


def _answer(cfg: RetrievalConfig, s: ScheduleState, seconds: float, why: str,
            plateau: str) -> list[tuple[str, str]]:
    """The answer to a plateau (the module docstring); restarts the window."""
    s.decayed_at = len(s.log["loss"])
    if s.stage + 1 < len(cfg.stages):
        s.stage += 1
        return [(f"stage {s.stage - 1} -> {s.stage}", why)]
    grown = int(round(s.photons * cfg.photon_growth))
    if (plateau == "photons" and grown <= cfg.photon_cap * s.photons_base
            and photons_fit(s.photons, cfg.photon_growth, seconds, s.elapsed, cfg.time_limit)):
        s.photons, was = grown, s.photons
        return [(f"photons {was} -> {grown}", why)]
    if cfg.step_decay < 1.0 and s.step_scale * cfg.step_decay >= cfg.step_floor:
        s.step_scale *= cfg.step_decay
        s.decays += 1
        return [(f"step x {cfg.step_decay:g} (now {s.step_scale:.4g} of its start)", why)]
    s.at_floor = True
    return [("no further change: the loss is at its noise floor", f"{why}; the photons are "
             f"at {s.photons} (cap or time limit) and the step at {s.step_scale:.4g} of its "
             "start (floor)")]
