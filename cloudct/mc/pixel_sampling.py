"""Residual-driven pixel sampling for the camera-side gradient estimators (DRT, sample
matching).

The loss gradient is g_v = sum_d r_d dI_d / d beta_v (seed paper Eq. 48). A camera-side
estimator traces paths from pixels; tracing every pixel equally spends as much on a pixel
whose residual r_d is nearly zero as on one whose residual dominates the sum. Drawing the
pixel of each sample with probability

    p_d = |r_d| / R,    R = sum_d |r_d|,

and weighting the sample's estimate of dI_d / d beta by r_d / p_d = sign(r_d) R keeps the
estimator unbiased (E[r_d / p_d dI_d] = sum_d r_d dI_d) and puts the samples where the
residual is. The draw uses Walker's alias table (Vose's construction): one uniform number
picks a column, a second chooses between the column's pixel and its alias, in constant time.
The table is rebuilt from each iteration's residual on the host; only its arrays reach the
kernels.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from cloudct.mc.random import uniform

#: Pixel samplings of :func:`cloudct.mc.gradient.gradient_estimate`: every pixel the same
#: samples, or samples in proportion to |residual|.
PIXEL_SAMPLINGS = ("uniform", "residual")


class PixelTable(NamedTuple):
    """An alias table over the pixels with a non-zero residual (empty: uniform sampling)."""

    pixel: np.ndarray  # int64[n]: flat (view, row, col) index of column i's pixel
    threshold: np.ndarray  # float64[n]: keep column i's pixel when u < threshold[i]
    alias: np.ndarray  # int64[n]: the column whose pixel is taken otherwise
    weight: np.ndarray  # float64[n]: r_d / p_d = sign(r_d) R of column i's pixel


def uniform_table() -> PixelTable:
    """The empty table: the kernels then trace every pixel with a non-zero residual."""
    return PixelTable(np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64), np.zeros(0))


def residual_table(residual: np.ndarray) -> PixelTable:
    """The alias table of p_d = |r_d| / sum |r| over ``residual`` (any shape; flat indices).

    Raises ValueError when every residual is zero (there is nothing to sample).
    """
    flat = np.ascontiguousarray(residual, dtype=np.float64).ravel()
    pixel = np.flatnonzero(flat)
    if pixel.size == 0:
        raise ValueError("every residual is zero: there is no pixel to sample")
    magnitude = np.abs(flat[pixel])
    total = float(magnitude.sum())
    n = pixel.size
    scaled = magnitude * (n / total)  # mean 1
    threshold = np.ones(n)
    alias = np.arange(n, dtype=np.int64)
    small = [i for i in range(n) if scaled[i] < 1.0]
    large = [i for i in range(n) if scaled[i] >= 1.0]
    while small and large:  # Vose: fill each small column up to 1 from a large one
        s = small.pop()
        g = large.pop()
        threshold[s] = scaled[s]
        alias[s] = g
        scaled[g] -= 1.0 - scaled[s]
        (small if scaled[g] < 1.0 else large).append(g)
    # what is left is 1 up to rounding: those columns keep their own pixel (threshold 1)
    weight = np.sign(flat[pixel]) * total
    return PixelTable(pixel.astype(np.int64), threshold, alias, weight)


def pixel_table(residual: np.ndarray, pixel_sampling: str) -> PixelTable:
    """The table of ``pixel_sampling`` (one of :data:`PIXEL_SAMPLINGS`) for ``residual``
    (uniform where every residual is zero: then no pixel is traced either way)."""
    if pixel_sampling not in PIXEL_SAMPLINGS:
        raise ValueError(
            f"pixel_sampling must be one of {PIXEL_SAMPLINGS}, got {pixel_sampling!r}"
        )
    if pixel_sampling == "uniform" or not np.any(residual):
        return uniform_table()
    return residual_table(residual)


@njit(cache=True, inline="always")
def draw_pixel(table, state):
    """A pixel drawn from the alias table: ``(flat pixel index, r_d / p_d, state)``."""
    n = table.pixel.size
    u, state = uniform(state)
    i = min(int(u * n), n - 1)
    v, state = uniform(state)
    if v >= table.threshold[i]:
        i = table.alias[i]
    return table.pixel[i], table.weight[i], state
