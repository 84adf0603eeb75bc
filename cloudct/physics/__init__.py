"""Optics of air and droplets: phase functions, particle mixing, Mie tables."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike


def wavelengths_within(wavelength: ArrayLike, bounds: tuple[float, float],
                       refusal: str) -> np.ndarray:
    """``wavelength`` [micron] as a float64 array, checked to lie within ``bounds``; else a
    ValueError ``"no {refusal} at {w} micron: ..."`` naming the first one outside (or not
    finite)."""
    lam = np.asarray(wavelength, dtype=np.float64)
    lo, hi = bounds
    inside = (lam >= lo) & (lam <= hi)
    if not np.all(inside):
        bad = np.ravel(lam[~inside] if lam.ndim else lam)[0]
        raise ValueError(f"no {refusal.format(bad=bad, lo=lo, hi=hi)}")
    return lam
