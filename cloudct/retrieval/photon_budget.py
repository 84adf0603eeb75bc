"""Photons that fit the device: the count of ``photons = "auto"``.

A retrieval's precision per iteration is set by its photons, and what a device can trace in
the same time differs a hundredfold between two CPU cores and a GPU. With ``photons =
"auto"`` (:class:`~cloudct.retrieval.config.RetrievalConfig`) a run therefore traces as
many gradient paths per iteration (and images' photons in proportion) as fill
``iteration_seconds`` of wall time on the device it runs on, so that one configuration file
serves a laptop and a GPU:

- the count starts at :data:`START` for the back end, and the time aimed at is
  ``iteration_seconds`` or, by default, :data:`TARGET_SECONDS` for the back end;
- an iteration's time is its tracing time: the wall time less what it spent compiling
  kernels or loading them from the cache (the log's ``compile_seconds``,
  :func:`cloudct.jit_cache.compile_clock`), so a cold first iteration sizes the count as a
  warm one does;
- after each iteration the count is rescaled by the ratio of the target time to the
  iteration's time (at most :data:`MOST_UP` times up and :data:`MOST_DOWN` times down at
  once, rounded to two significant digits), until an iteration takes between
  :data:`SETTLED` times the target: the count settles (a resumed run keeps it);
- settled, it is fitted again when the median time of the last :data:`DRIFT_WINDOW`
  iterations, scaled to the settled count (the noise schedule's growth taken out), leaves
  that band: whatever slowed or sped the iterations that sized it (another process, a
  first iteration's one-off costs) does not size the whole run. The photons grown by the
  schedule keep their multiple of the settled count.

On 2 CPU cores the default of 5 s starts a run where many iterations fit: about 200,000
gradient paths on the single cloud and 650,000 on the two cumuli (2026-11-28). The noise
schedule (:mod:`cloudct.retrieval.schedule`) then grows the photons 1.5x at each plateau of
the loss, up to 16x, while ten iterations of the grown count fit in the time left, so the
same defaults serve a 10-minute run and an hour: the 20 s of the defaults before
2026-11-28 gave a 10-minute run 35-40 iterations, and the first ten minutes lost against
fixed 400,000-path iterations of about 6-8 s (issue 51; docs/benchmarks.md, "Defaults for
every run length"). On a GPU the default of 2 s is that of the GPU retrieval the project
measured (4 x 10^6 paths, about 1.2 s an iteration on an H200), not a measured optimum.
Each change is a decision of the run's log
(:func:`decision`), and the count of every iteration is in its ``photons`` column. The count
depends on the measured times, so two runs with ``"auto"`` may trace different photons;
give a number for iterates that repeat bitwise.
"""

from __future__ import annotations

import math
from statistics import median
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from cloudct.retrieval.state import RetrievalState

#: Gradient paths of the first iteration, per back end.
START = {"cpu": 50_000, "cuda": 1_000_000}
#: The wall time [s] an iteration aims at, per back end, where ``iteration_seconds`` is
#: not given.
TARGET_SECONDS = {"cpu": 5.0, "cuda": 2.0}
#: The band of iteration times, as multiples of the target, in which the count settles.
SETTLED = (2.0 / 3.0, 1.5)
#: The most the count grows, or shrinks, at one rescaling.
MOST_UP = 16.0
MOST_DOWN = 4.0
#: Settled iterations whose median time is compared with the target.
DRIFT_WINDOW = 3


def start_count(backend: str) -> int:
    """Gradient paths of a run's first iteration on ``backend`` (the CPU's where the
    back end is not known here: Dask workers)."""
    return START.get(backend, START["cpu"])


def target_seconds(iteration_seconds: float | None, backend: str) -> float:
    """The wall time an iteration of ``photons = "auto"`` aims at on ``backend``."""
    if iteration_seconds is not None:
        return float(iteration_seconds)
    return TARGET_SECONDS.get(backend, TARGET_SECONDS["cpu"])


def rescaled_count(photons: int, seconds: float, target: float) -> int | None:
    """The count that an iteration of ``photons`` paths taking ``seconds`` calls for to
    take ``target`` seconds, or None when it is within the settled band already.

    >>> rescaled_count(50_000, 2.0, 20.0)  # ten times too fast: ten times the paths
    500000
    >>> rescaled_count(50_000, 18.0, 20.0) is None  # close enough to the target
    True
    """
    ratio = target / seconds if seconds > 0.0 else MOST_UP
    if SETTLED[0] <= 1.0 / ratio <= SETTLED[1]:
        return None
    wanted = photons * min(max(ratio, 1.0 / MOST_DOWN), MOST_UP)
    digits = 10.0 ** (math.floor(math.log10(wanted)) - 1)  # two significant digits
    return max(int(round(wanted / digits) * digits), 1)


def fit_to_device(state: RetrievalState, seconds: float, target: float
                  ) -> list[tuple[str, str]]:
    """Rescale ``state.photons`` after an iteration of ``seconds`` towards ``target``
    seconds, or settle it (then it is also ``state.photons_base``); returns the change as
    (what, why)."""
    count = rescaled_count(state.photons, seconds, target)
    why = f"photons auto: an iteration took {seconds:.3g} s, the target {target:g} s"
    if count is None:
        state.photons_settled, state.photons_base = True, state.photons
        return [(f"photons settled at {state.photons}", why)]
    was, state.photons = state.photons, count
    return [(f"photons {was} -> {count}", why)]


def refit_to_device(state: RetrievalState, seconds_at_base: float, target: float
                    ) -> list[tuple[str, str]]:
    """Fit a settled count again when iterations take ``seconds_at_base`` (their median
    time scaled to ``state.photons_base``) outside the settled band around ``target``:
    the settled count is rescaled, and ``state.photons`` with it (keeping the schedule's
    multiple of it); returns the change as (what, why), none within the band."""
    count = rescaled_count(state.photons_base, seconds_at_base, target)
    if count is None:
        return []
    was = state.photons
    state.photons = max(int(round(state.photons * count / state.photons_base)), 1)
    state.photons_base = count
    why = (f"photons auto: iterations took {seconds_at_base:.3g} s at the settled count, "
           f"the target {target:g} s")
    return [(f"photons {was} -> {state.photons} (settled at {count})", why)]


def fit_auto_photons(state: RetrievalState, times_at_base: list[float], seconds: float,
                     share: float, target: float) -> list[tuple[str, str]]:
    """``photons = "auto"`` after an iteration that traced for ``seconds``: the count
    rescaled until it settles (:func:`fit_to_device`), then fitted again when the median
    of the last :data:`DRIFT_WINDOW` iterations' times scaled to the settled count (x
    ``share``, the photons at that count over those traced) leaves the settled band
    (:func:`refit_to_device`). ``times_at_base`` holds those times since the last change
    (the run's, emptied at a change); returns the changes as (what, why)."""
    if not state.photons_settled:
        return fit_to_device(state, seconds, target)
    times_at_base.append(seconds * share)
    if len(times_at_base) < DRIFT_WINDOW:
        return []
    changes = refit_to_device(state, median(times_at_base[-DRIFT_WINDOW:]), target)
    if changes:
        times_at_base.clear()
    return changes


def decision(iteration: int, what: str, why: str) -> dict[str, int | str]:
    """A row of a run's decisions log: after which iteration, what changed, and why."""
    return {"iteration": int(iteration), "what": what, "why": why}
