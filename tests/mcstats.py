"""Statistical comparison of Monte Carlo estimates with references, for the tests.

Estimates come with standard errors from B independent batches, so each standardised
difference z = (estimate - reference) / std_error follows a Student t distribution with
B - 1 degrees of freedom when the estimator is unbiased. The checks are:

- the pooled z-score of the summed differences, sum(d) / sqrt(sum(se^2)), lies within
  +-4 (sensitive to a common bias of all pixels);
- the mean of z^2 lies within 4 standard deviations of its expectation under the t
  distribution (sensitive to pixel-wise errors larger than the noise);
- no single pixel is beyond the 1e-4 / n two-sided quantile of the t distribution.
"""

from __future__ import annotations

import numpy as np
from scipy import stats


def assert_consistent(
    estimate: np.ndarray,
    std_error: np.ndarray,
    reference: np.ndarray,
    batches: int,
    reference_error: np.ndarray | float = 0.0,
    label: str = "",
) -> dict[str, float]:
    """Assert that estimates agree with a reference within their standard errors.

    ``reference_error`` is the reference's own standard error (another Monte Carlo
    estimate), combined in quadrature. Returns the summary statistics.
    """
    shape = np.shape(estimate)
    estimate, std_error, reference, ref_err = (
        np.broadcast_to(a, shape).ravel() for a in (estimate, std_error, reference, reference_error)
    )
    sigma = np.sqrt(std_error**2 + ref_err**2)
    assert np.all(sigma > 0), f"{label}: zero standard error in a compared pixel"
    n = estimate.size
    d = estimate - reference
    z = d / sigma
    dof = batches - 1
    pooled = d.sum() / np.sqrt(np.sum(sigma**2))
    # Student t with dof degrees of freedom: E[z^2] = dof / (dof - 2),
    # Var[z^2] = 2 dof^2 (dof - 1) / ((dof - 2)^2 (dof - 4))
    mean_z2 = float(np.mean(z**2))
    e_z2 = dof / (dof - 2)
    sd_z2 = np.sqrt(2 * dof**2 * (dof - 1) / ((dof - 2) ** 2 * (dof - 4)) / n)
    z_max = float(np.max(np.abs(z)))
    z_limit = stats.t.isf(0.5e-4 / n, dof)
    summary = {"n": n, "pooled_z": float(pooled), "mean_z2": mean_z2, "max_abs_z": z_max}
    print(f"{label}: " + ", ".join(f"{k} {v:.3g}" for k, v in summary.items()))
    assert abs(pooled) < 4.0, f"{label}: pooled z-score {pooled:.2f} ({summary})"
    assert abs(mean_z2 - e_z2) < 4 * sd_z2, (
        f"{label}: mean z^2 {mean_z2:.3f}, expected {e_z2:.3f} +- {sd_z2:.3f} ({summary})"
    )
    assert z_max < z_limit, f"{label}: max |z| {z_max:.2f} > {z_limit:.2f} ({summary})"
    return summary
