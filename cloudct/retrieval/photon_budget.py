"""Photons that fit the device: the count of ``photons = "auto"``.

A retrieval's precision per iteration is set by its photons, and what a device can trace in
the same time differs a hundredfold between two CPU cores and a GPU. With ``photons =
"auto"`` (:class:`~cloudct.retrieval.config.RetrievalConfig`) a run therefore traces as
many gradient paths per iteration (and images' photons in proportion) as fill
``iteration_seconds`` of wall time on the device it runs on, so that one configuration file
serves a laptop and a GPU:

- the count starts at :data:`START` for the back end, and the time aimed at is
  ``iteration_seconds`` or, by default, :data:`TARGET_SECONDS` for the back end;
- after each iteration it is rescaled by the ratio of the target time to the iteration's
  measured time (at most :data:`MOST_UP` times up and :data:`MOST_DOWN` times down at once,
  rounded to two significant digits), until an iteration takes between :data:`SETTLED`
  times the target; from then on it stays (a resumed run keeps it);
- the first iteration a run traces in a process is not used (its time includes compiling
  the kernels, or loading them from the cache).

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


def decision(iteration: int, what: str, why: str) -> dict[str, int | str]:
    """A row of a run's decisions log: after which iteration, what changed, and why."""
    return {"iteration": int(iteration), "what": what, "why": why}
