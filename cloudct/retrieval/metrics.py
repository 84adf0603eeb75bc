"""Retrieval quality, seed paper Eq. (54), over the cloud extinction grid:

    epsilon = ||b* - b||_1 / ||b*||_1,   delta = (||b*||_1 - ||b||_1) / ||b*||_1.
"""

from __future__ import annotations

import numpy as np


def epsilon_delta(truth: np.ndarray, estimate: np.ndarray) -> tuple[float, float]:
    """(epsilon, delta) of an estimated extinction field against the true one."""
    truth = np.asarray(truth, dtype=float)
    estimate = np.asarray(estimate, dtype=float)
    if truth.shape != estimate.shape:
        raise ValueError(f"grids differ: truth {truth.shape}, estimate {estimate.shape}")
    norm = np.abs(truth).sum()
    if norm == 0:
        raise ValueError("the true extinction is zero everywhere: epsilon is undefined")
    return (
        float(np.abs(truth - estimate).sum() / norm),
        float((norm - np.abs(estimate).sum()) / norm),
    )
