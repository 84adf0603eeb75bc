"""The score-function gradient under a non-exponential transmittance (Vicini et al. 2021),
mode field fixed, against finite differences.

Two levels, each against a reference that shares no code with what it checks:
- the walk's derivatives, deterministically: along a ray through voxels of different modes,
  the deposits of :func:`cloudct.mc.traversal.march` times its ``scale`` equal central
  differences of the equivalent depth -log T that the walk itself returns, and the
  collision density's log derivative (the factor c) equals differences of log(beta phi(u))
  written from the families' closed forms;
- the whole estimator: ``score_function_gradient`` of a medium of varying power-law
  shapes against central finite differences of forward renders with common random numbers
  (as tests/test_score_gradient.py does for the exponential). The linear mix is refused.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from mcstats import assert_consistent
from test_score_gradient import (
    BATCHES,
    SCATTERING_VOXELS,
    finite_difference,
    gradient_medium,
    gradient_scene,
    pixel_weights,
)
from test_transmittance import closed_form, slab

from cloudct.mc.gradient import score_function_gradient
from cloudct.mc.traversal import INF, locate_point, march
from cloudct.medium import with_transmittance
from cloudct.optics import kernel_arrays
from cloudct.physics.transmittance import GAMMA, LINEAR_MIX, collision_factor

# modes per voxel: strongly non-exponential in one part, mildly in another, exponential in
# a third, so that the walks cross mode boundaries (the hazard ratios Q of the derivation)
MODES = {"gamma": (0.5, 2.0, np.inf), "linear-mix": (0.2, 0.6, 1.0)}


def mode_field(family: str, shape: tuple[int, int, int]) -> np.ndarray:
    """Three modes of ``family`` in bands along x and a checkerboard along z."""
    strong, mild, limit = MODES[family]
    x = np.arange(shape[0])[:, None, None]
    z = np.arange(shape[2])[None, None, :]
    field = np.where((x + z) % 2 == 0, strong, mild) * np.ones(shape)
    field[x[:, 0, 0] % 3 == 2] = limit
    return field


def ray(grid):
    """A slanted ray from a point on the top face, through many voxels."""
    d = np.array([0.45, 0.3, -0.84])
    d /= np.linalg.norm(d)
    p = (0.07, 0.11, float(grid.z_edges[-1]))
    return p, d, locate_point(grid, *p, *d)


def depth_and_derivative(medium, max_distance):
    """The walk's equivalent depth over ``max_distance`` and its derivative per voxel
    (deposits x scale), and the walk's scale."""
    grid, _ = kernel_arrays(medium)
    p, d, cell = ray(grid)
    deposits = np.zeros(grid.extinction.shape[1:])
    first = march(grid, *p, *d, *cell, INF, False, None, 0.0, max_distance)
    march(grid, *p, *d, *cell, INF, False, deposits, 1.0, max_distance)
    return first[7], deposits * first[9], first


@pytest.mark.parametrize("family", ["gamma", "linear-mix"])
def test_the_walks_depth_derivatives_match_central_differences(family):
    """ds / dbeta_k (Q ratios and hazards, cloudct.physics.transmittance) equals central
    differences of the walk's own s, voxel by voxel, to the differences' truncation."""
    rng = np.random.default_rng(3)
    ext = rng.uniform(0.3, 1.2, size=(5, 5, 5))  # optical depths below the linear part's 2
    medium = with_transmittance(slab(5, 5, 5, extinction=ext), family,
                                mode_field(family, ext.shape))
    s, derivative, first = depth_and_derivative(medium, 0.9)
    assert first[0] == 0 and 0.3 < s < 1.5  # stopped at the distance, T well inside (0, 1)
    crossed = np.argwhere(derivative != 0.0)
    assert len(crossed) >= 5
    for v in map(tuple, crossed):
        h = 1e-6 * ext[v]
        up, down = ext.copy(), ext.copy()
        up[v] += h
        down[v] -= h
        s_up = depth_and_derivative(with_transmittance(slab(5, 5, 5, extinction=up), family,
                                                       mode_field(family, ext.shape)), 0.9)[0]
        s_down = depth_and_derivative(with_transmittance(slab(5, 5, 5, extinction=down),
                                                         family, mode_field(family, ext.shape)),
                                      0.9)[0]
        assert derivative[v] == pytest.approx((s_up - s_down) / (2 * h), rel=1e-6), v
    # the derivatives are not the exponential's lengths: the test tells the two apart
    _, lengths, _ = depth_and_derivative(with_transmittance(medium, "exponential"), 0.9)
    assert np.max(np.abs(derivative - lengths)) > 0.05 * np.max(lengths)


@pytest.mark.parametrize("family, mode", [("gamma", 0.5), ("gamma", 3.0),
                                          ("linear-mix", 0.3), ("linear-mix", 0.0)])
def test_the_collision_factor_is_the_log_density_derivative(family, mode):
    """c = -phi' f / phi^2 against differences of log phi(u) over s(u) = -log f(u) from
    the closed form: d log T_pdf = -c ds at a fixed extinction of the collision voxel."""
    code = GAMMA if family == "gamma" else LINEAR_MIX
    m = 1.0 / mode if family == "gamma" else mode
    h = 1e-6

    def log_phi_and_s(t):
        slope = -(closed_form(family, np.array(t + h), mode)
                  - closed_form(family, np.array(t - h), mode)) / (2 * h)
        return math.log(slope), -math.log(closed_form(family, np.array(t), mode))

    for u in (0.1, 0.7, 1.6, 3.0):
        if family == "linear-mix" and mode == 0.0 and u >= 2.0:
            continue  # the pure linear law ends at 2
        (lp1, s1), (lp0, s0) = log_phi_and_s(u + 1e-3), log_phi_and_s(u - 1e-3)
        expected = -(lp1 - lp0) / (s1 - s0)
        got = collision_factor(code, -math.log(closed_form(family, np.array(u), mode)), m)
        assert got == pytest.approx(expected, rel=1e-4, abs=1e-6), (u, got, expected)


def power_law_medium():
    base = gradient_medium()
    return with_transmittance(base, "gamma", mode_field("gamma", base["cloud_extinction"].shape))


def test_the_score_function_under_the_power_law_matches_finite_differences():
    """Voxel by voxel, the score-function gradient of a medium whose power-law shapes vary
    (a = 0.5, 2 and inf) agrees with central finite differences of its forward renders
    (common random numbers), in the dense core (optical depth 2.5 per voxel) and the thin
    shell around it."""
    medium = power_law_medium()
    mean, se, _ = score_function_gradient(
        medium, gradient_scene(), pixel_weights(), photons=2_000_000, seed=5,
        batches=BATCHES, progress=False,
    )
    voxels = [v for v in SCATTERING_VOXELS if v != (1, 2, 3) and v != (0, 0, 3)]
    fd = np.array([finite_difference(medium, v) for v in voxels])
    sf = np.array([mean[v] for v in voxels])
    sf_se = np.array([se[v] for v in voxels])
    assert fd[:, 0].sum() / np.sqrt(np.sum(fd[:, 1] ** 2)) > 5.0  # the comparison has power
    assert_consistent(sf, sf_se, fd[:, 0], BATCHES, reference_error=fd[:, 1],
                      label="SF vs FD, power law")


def test_the_linear_mix_gradient_is_refused():
    """Eq. 6's collision density jumps where its linear part ends; the score function would
    miss that moving boundary's term (measured: 7x the finite difference in the dense core,
    docs/transmittance.md), so it refuses rather than returning a biased gradient. The
    exponential limit (gamma = 1 everywhere) is differentiated as the exponential."""
    base = gradient_medium()
    mixed = with_transmittance(base, "linear-mix",
                               mode_field("linear-mix", base["cloud_extinction"].shape))
    with pytest.raises(ValueError, match="linear-mix transmittance are not implemented"):
        score_function_gradient(mixed, gradient_scene(), pixel_weights(), photons=64,
                                batches=2, progress=False)
    limit = with_transmittance(base, "linear-mix", 1.0)
    args = dict(photons=2000, seed=1, batches=4, progress=False)
    np.testing.assert_array_equal(
        score_function_gradient(limit, gradient_scene(), pixel_weights(), **args)[0],
        score_function_gradient(base, gradient_scene(), pixel_weights(), **args)[0])
