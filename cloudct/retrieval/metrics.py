"""Retrieval quality, seed paper Eq. (54), over the cloud extinction grid:

    epsilon = ||b* - b||_1 / ||b*||_1,   delta = (||b*||_1 - ||b||_1) / ||b*||_1.

:func:`epsilon_split` tells where epsilon comes from: extinction retrieved where the true
cloud has none (e.g. the empty part of a space-carved hull) and errors inside the cloud.
"""

from __future__ import annotations

import numpy as np


def _fields(truth: np.ndarray, estimate: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    truth = np.asarray(truth, dtype=float)
    estimate = np.asarray(estimate, dtype=float)
    if truth.shape != estimate.shape:
        raise ValueError(f"grids differ: truth {truth.shape}, estimate {estimate.shape}")
    norm = np.abs(truth).sum()
    if norm == 0:
        raise ValueError("the true extinction is zero everywhere: epsilon is undefined")
    return truth, estimate, float(norm)


def epsilon_delta(truth: np.ndarray, estimate: np.ndarray) -> tuple[float, float]:
    """(epsilon, delta) of an estimated extinction field against the true one.

    A retrieval that put 12 and 15 /km where the truth holds 10 and 20 /km is off by 7 of
    the true 30 /km, and holds a tenth too little:

    >>> import numpy as np
    >>> epsilon_delta(np.array([0.0, 10.0, 20.0]), np.array([0.0, 12.0, 15.0]))
    (0.23333333333333334, 0.1)
    """
    truth, estimate, norm = _fields(truth, estimate)
    return (
        float(np.abs(truth - estimate).sum() / norm),
        float((norm - np.abs(estimate).sum()) / norm),
    )


def epsilon_split(truth: np.ndarray, estimate: np.ndarray) -> dict[str, float]:
    """Epsilon as the sum of its parts, each relative to ||b*||_1:

    - ``outside``: ||b||_1 over the voxels where the truth is zero (extinction put where
      there is no cloud);
    - ``inside``: ||b* - b||_1 over the cloud's voxels;
    - ``cloud_mass``: ||b||_1 over the cloud's voxels (1: the cloud holds the true mass).

    ``outside + inside`` is epsilon.
    """
    truth, estimate, norm = _fields(truth, estimate)
    cloud = truth != 0
    return {
        "outside": float(np.abs(estimate[~cloud]).sum() / norm),
        "inside": float(np.abs(truth - estimate)[cloud].sum() / norm),
        "cloud_mass": float(np.abs(estimate[cloud]).sum() / norm),
    }
