"""Gradient-based updates of the cloud extinction, projected onto the feasible set.

The feasible set is {beta >= 0, beta = 0 outside the mask} (the space-carved hull).
Optimisers are small state machines whose state is a dict of arrays, so that a retrieval
can checkpoint and resume them exactly.
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter


def project(beta: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
    """Euclidean projection onto {beta >= 0, beta = 0 outside ``mask``}."""
    beta = np.maximum(beta, 0.0)
    if mask is not None:
        beta = np.where(mask, beta, 0.0)
    return beta


def block_mean(field: np.ndarray, mask: np.ndarray, block: int) -> np.ndarray:
    """``field`` averaged over the masked voxels of each ``block`` x ``block`` x ``block``
    block of the grid (edge blocks may be smaller), back on the grid; 0 outside the mask.

    A retrieval stage that ties its voxels in blocks steps every voxel of a block along the
    block's mean gradient: the coarse grid's gradient, with the Monte Carlo noise of a
    voxel averaged over the block's voxels.
    """
    if block == 1:
        return np.where(mask, field, 0.0)
    shape = field.shape
    ids = [np.arange(n) // block for n in shape]
    nb = [int(i[-1]) + 1 for i in ids]
    flat = (ids[0][:, None, None] * nb[1] + ids[1][None, :, None]) * nb[2] + ids[2][None, None, :]
    flat = np.broadcast_to(flat, shape)[mask]
    sums = np.bincount(flat, weights=field[mask], minlength=int(np.prod(nb)))
    counts = np.bincount(flat, minlength=int(np.prod(nb)))
    out = np.zeros(shape)
    out[mask] = sums[flat] / counts[flat]
    return out


def smoothed_gradient(gradient: np.ndarray, mask: np.ndarray, sigma: float) -> np.ndarray:
    """``gradient`` restricted to the mask, convolved with a Gaussian of standard deviation
    ``sigma`` voxels and restricted to the mask again (``sigma`` = 0: only the restriction).

    This is M G M g with M the mask and G the Gaussian convolution: a symmetric
    preconditioner whose eigenvalues are positive (for sigma up to 1.5; beyond, the
    kernel's truncation at 4 sigma lets the highest spatial frequencies reach -2e-5 of the
    largest), so the smoothed gradient is a descent direction, g . M G M g > 0, and a
    stationary point of the loss stays one. Unlike voxel blocks it keeps the minimiser; it
    damps the voxel-scale components of a step, where a Monte Carlo gradient is mostly noise.
    """
    masked = np.where(mask, gradient, 0.0)
    if sigma == 0.0:
        return masked
    return np.where(mask, gaussian_filter(masked, sigma, mode="constant", truncate=4.0), 0.0)


class Adam:
    """Adam (Kingma & Ba 2014), as in the seed paper: first and second moment decays
    ``beta1`` = 0.9 and ``beta2`` = 0.999, step size ``step`` in 1/km per iteration.

        m <- b1 m + (1 - b1) g,  v <- b2 v + (1 - b2) g^2,
        x <- x - step * (m / (1 - b1^t)) / (sqrt(v / (1 - b2^t)) + eps)
    """

    name = "adam"

    def __init__(
        self, step: float = 2.0, beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-12
    ) -> None:
        if step <= 0 or not 0 <= beta1 < 1 or not 0 <= beta2 < 1:
            raise ValueError("Adam needs step > 0 and moment decays in [0, 1)")
        self.step, self.beta1, self.beta2, self.eps = step, beta1, beta2, eps
        self.state: dict[str, np.ndarray] = {}

    def update(self, x: np.ndarray, grad: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
        """One step from ``x`` along the gradient ``grad``, projected."""
        t = int(self.state.get("t", np.zeros(())) + 1)
        m = self.state.get("m", np.zeros_like(x))
        v = self.state.get("v", np.zeros_like(x))
        m = self.beta1 * m + (1 - self.beta1) * grad
        v = self.beta2 * v + (1 - self.beta2) * grad**2
        m_hat = m / (1 - self.beta1**t)
        v_hat = v / (1 - self.beta2**t)
        self.state = {"t": np.array(t), "m": m, "v": v}
        return project(x - self.step * m_hat / (np.sqrt(v_hat) + self.eps), mask)


class MomentumSGD:
    """Gradient descent with (heavy-ball) momentum: u <- mu u + g, x <- x - step u."""

    name = "sgd"

    def __init__(self, step: float, momentum: float = 0.9) -> None:
        if step <= 0 or not 0 <= momentum < 1:
            raise ValueError("SGD needs step > 0 and momentum in [0, 1)")
        self.step, self.momentum = step, momentum
        self.state: dict[str, np.ndarray] = {}

    def update(self, x: np.ndarray, grad: np.ndarray, mask: np.ndarray | None) -> np.ndarray:
        """One step from ``x`` along the gradient ``grad``, projected."""
        u = self.momentum * self.state.get("u", np.zeros_like(x)) + grad
        self.state = {"u": u}
        return project(x - self.step * u, mask)


def bounded_update(before: np.ndarray, after: np.ndarray, max_change: float, step: float
                   ) -> np.ndarray:
    """``after`` with each voxel's change from ``before`` bounded by ``max_change`` x
    (beta + ``step``): relative for a cloud voxel, and at least ``max_change`` x the step
    [1/km] for an empty one, so that one noisy gradient can neither empty nor flood a voxel
    (``RetrievalConfig.max_change``). The result stays non-negative where ``after`` is."""
    bound = max_change * (before + step)
    return np.clip(after, before - bound, before + bound)


def make_optimizer(name: str, step: float) -> Adam | MomentumSGD:
    """An optimiser by name ("adam" or "sgd")."""
    if name == "adam":
        return Adam(step=step)
    if name == "sgd":
        return MomentumSGD(step=step)
    raise ValueError(f"optimizer must be 'adam' or 'sgd', got {name!r}")


def add_to_average(total: np.ndarray | None, weight: float, iterate: np.ndarray,
                   decay: float) -> tuple[np.ndarray, float]:
    """The weighted sum and total weight of an iterate average with ``iterate`` added:
    sum_k d^(n-k) x_k and sum_k d^(n-k) over the iterates k = 1 .. n since the average's
    (re)start (``total`` None), whose ratio is the average: d = 1 the uniform
    (Polyak-Ruppert) average, d < 1 an exponential moving average with Adam's bias
    correction (which the normalisation is)."""
    return (iterate.copy() if total is None else decay * total + iterate), decay * weight + 1.0
