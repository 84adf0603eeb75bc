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
from scipy.optimize import brentq
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
from cloudct.mc.traversal import INF, LEFT, STOPPED, locate_point, march
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


#: Walks along which the derivatives are checked: (start, direction, optical-depth target,
#: distance, periodic). A walk stopped at a distance (two points), a free flight that ends
#: in a collision, a ray that leaves through the top, and one that wraps across the side
#: faces (periodic) before it leaves.
WALKS = {
    "distance": ((0.07, 0.11, 1.0), (0.45, 0.3, -0.84), INF, 0.9, False),
    "collision": ((0.07, 0.11, 1.0), (0.45, 0.3, -0.84), 0.35, INF, False),
    "exit": ((0.5, 0.4, 0.02), (-0.3, 0.2, 0.93), INF, INF, False),
    "periodic exit": ((0.81, 0.52, 0.02), (0.8, 0.45, 0.6), INF, INF, True),
}
STATUS = {"distance": STOPPED, "collision": STOPPED, "exit": LEFT, "periodic exit": LEFT}


def walk(ext, family, which, deposits=None, distance=None):
    """The walk ``which`` through the 5 x 5 x 5 slab of extinction ``ext`` under
    ``family`` (:func:`mode_field`, or exponential for None); with ``deposits``, they are
    added there; ``distance`` replaces the walk's."""
    medium = slab(5, 5, 5, extinction=ext)
    if family is not None:
        medium = with_transmittance(medium, family, mode_field(family, ext.shape))
    grid, _ = kernel_arrays(medium)
    p, d, target, limit, periodic = WALKS[which]
    d = np.array(d) / np.linalg.norm(d)
    cell = locate_point(grid, *p, *d)
    return march(grid, *p, *d, *cell, target, periodic, deposits, 1.0,
                 limit if distance is None else distance)


def log_density_at(ext, family, distance, voxel):
    """log(beta_v phi_v(u)) of a collision at a fixed ``distance`` along the collision walk's
    ray, u the local optical depth of the walk's T there in the mode of the end voxel
    ``voxel``, phi = -f' from the closed forms (a root finder inverts f)."""
    s = walk(ext, family, "distance", None, distance)[7]  # the collision walk's ray
    mode = mode_field(family, ext.shape)[voxel]
    if mode == np.inf:  # the power law's exponential limit
        return math.log(ext[voxel]) - s
    u = brentq(lambda t: closed_form(family, np.array(t), mode) - math.exp(-s), 0.0, 50.0,
               xtol=1e-15, rtol=4 * np.finfo(float).eps)
    if family == "gamma":  # phi = -f' of the closed forms, differentiated by hand
        phi = (1 + u / mode) ** (-mode - 1)
    else:
        phi = mode * math.exp(-u) + (0.5 * (1 - mode) if u < 2 else 0.0)
    return math.log(ext[voxel] * phi)


@pytest.mark.parametrize("family", ["gamma", "linear-mix"])
@pytest.mark.parametrize("which", list(WALKS))
def test_the_walks_derivatives_match_central_differences(family, which):
    """The deposits times the walk's scale (Q ratios, hazards, the collision factor:
    cloudct.physics.transmittance) against central differences voxel by voxel: of the
    walk's own equivalent depth s for a walk stopped at a distance or leaving the medium,
    and of minus the log collision density (its 1 / beta_v aside) for a free flight's
    collision, at the collision's distance."""
    rng = np.random.default_rng(3)
    ext = rng.uniform(0.3, 1.2, size=(5, 5, 5))  # optical depths below the linear part's 2
    deposits = np.zeros(ext.shape)
    first = walk(ext, family, which)
    walk(ext, family, which, deposits)
    derivative = deposits * first[9]
    crossed = list(map(tuple, np.argwhere(derivative != 0.0)))
    assert first[0] == STATUS[which] and 0.1 < first[7] < 2.0, first
    assert len(crossed) >= 4, crossed
    end = tuple(first[4:7])
    if which == "collision":  # in a voxel of a non-exponential mode: c is not 1 there
        assert mode_field(family, ext.shape)[end] not in (1.0, np.inf)
    for v in crossed:
        h = 1e-6 * ext[v]
        up, down = ext.copy(), ext.copy()
        up[v] += h
        down[v] -= h
        if which == "collision":  # -d log T_pdf = c ds - delta / beta at the fixed end
            reference = -(log_density_at(up, family, first[8], end)
                          - log_density_at(down, family, first[8], end)) / (2 * h)
            reference += (1.0 / ext[v]) if v == end else 0.0
        else:
            reference = (walk(up, family, which)[7] - walk(down, family, which)[7]) / (2 * h)
        assert derivative[v] == pytest.approx(reference, rel=2e-6), (v, which)
    # the derivatives are not the exponential's lengths: the test tells the two apart
    lengths = np.zeros(ext.shape)
    walk(ext, None, which, lengths)
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
