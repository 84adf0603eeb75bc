"""When to resample the stored paths: re-use policies for path recycling.

- :class:`FixedPeriod`: the seed paper's Alg. 2, new paths every ``period`` (N_r)
  iterations.
- :class:`AdaptiveESS`: new paths when the effective sample size of the correction factors,
  ESS = (sum_i r_i)^2 / sum_i r_i^2 over the stored paths, falls below ``min_fraction`` of
  the number of paths, and at the latest after ``max_period`` iterations; optionally also
  when the largest correction factor exceeds ``max_ratio``.

A policy is asked before every evaluation of a store with the number of evaluations the
store has served (``age``) and, for policies with ``uses_ess``, the store's ESS fraction
and largest log correction factor under the new medium; it answers with a reason to
resample (a short string, logged) or None.

Why ``max_ratio``: the ESS over all paths counts the many paths that never meet the voxels
that changed (r = 1). One path with r = R among N gives ESS ~ N^2 / (N + R^2), so the ESS
fraction stays above 0.5 up to R ~ sqrt(N) (about 450 for 2 x 10^5 paths), while a single
path with r in the hundreds already dominates the pixels it reaches (a pixel receives a few
hundred estimates or fewer). On the single-cloud benchmark with the seed paper's Adam step,
recycled losses jump while the ESS fraction is still about 0.5
(docs/recycling.md); ``max_ratio`` of a few tens catches that.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Protocol


class Policy(Protocol):
    """What :class:`cloudct.recycling.Recycler` asks of a re-use policy."""

    uses_ess: ClassVar[bool]

    def resample_reason(
        self, age: int, ess_fraction: float | None, max_log_ratio: float | None = None
    ) -> str | None:
        """Why to resample before this evaluation, or None to recycle."""


@dataclass(frozen=True)
class FixedPeriod:
    """Resample every ``period`` evaluations (period 1: fresh paths every iteration)."""

    period: int = 30
    uses_ess: ClassVar[bool] = False

    def __post_init__(self) -> None:
        if int(self.period) != self.period or self.period < 1:
            raise ValueError(f"period must be a positive integer, got {self.period}")

    def resample_reason(
        self, age: int, ess_fraction: float | None, max_log_ratio: float | None = None
    ) -> str | None:
        return "period" if age >= self.period else None


@dataclass(frozen=True)
class AdaptiveESS:
    """Resample when the ESS fraction of the correction factors drops below
    ``min_fraction``, when the paths have served ``max_period`` evaluations, or (if given)
    when a path's correction factor exceeds ``max_ratio``."""

    min_fraction: float = 0.5
    max_period: int = 50
    max_ratio: float | None = None
    uses_ess: ClassVar[bool] = True

    def __post_init__(self) -> None:
        if not 0.0 < self.min_fraction <= 1.0:
            raise ValueError(f"min_fraction must be in (0, 1], got {self.min_fraction}")
        if int(self.max_period) != self.max_period or self.max_period < 1:
            raise ValueError(f"max_period must be a positive integer, got {self.max_period}")
        if self.max_ratio is not None and not self.max_ratio > 1.0:
            raise ValueError(f"max_ratio must be above 1 (or None), got {self.max_ratio}")

    def resample_reason(
        self, age: int, ess_fraction: float | None, max_log_ratio: float | None = None
    ) -> str | None:
        if age >= self.max_period:
            return "max_period"
        if ess_fraction is not None and ess_fraction < self.min_fraction:
            return "ess"
        if (
            self.max_ratio is not None and max_log_ratio is not None
            and max_log_ratio > math.log(self.max_ratio)
        ):
            return "max_ratio"
        return None
