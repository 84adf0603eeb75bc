"""Non-exponential transmittance (cloudct.physics.transmittance, Vicini et al. 2021) in the
engine's walk: the families against their closed forms, the exponential limit bitwise, the
direct transmittance of a homogeneous slab against f(tau), and an explicit ensemble of
sub-grid media (gamma-distributed column optical depths, rendered exponentially) against
the coarse medium under the power law."""

from __future__ import annotations

import math

import numpy as np
import pytest
from mcstats import assert_consistent
from numba import njit
from test_forward import uniform_axis

from cloudct.mc.cameras import Camera
from cloudct.mc.gradient import drt_gradient, sample_matching_gradient
from cloudct.mc.render import render
from cloudct.mc.scene import Scene
from cloudct.mc.sensors import domain_means
from cloudct.mc.sun import Sun
from cloudct.mc.traversal import BOTTOM, INF, locate_point, march
from cloudct.medium import MediumError, optical_medium, validate_medium
from cloudct.optics import kernel_arrays
from cloudct.physics.transmittance import (
    GAMMA,
    LINEAR_MIX,
    optical_depth_of,
    transmittance,
    transmittance_slope,
)
from cloudct.recycling import record_paths, replay_images


def closed_form(family: str, tau: np.ndarray, mode: float) -> np.ndarray:
    """f(tau) written from the definitions (Vicini et al. Eq. 6; the gamma mixture)."""
    if family == "linear-mix":
        return mode * np.exp(-tau) + (1 - mode) * np.maximum(0.0, 1 - tau / 2)
    return (1 + tau / mode) ** (-mode)


@pytest.mark.parametrize("family, code, mode, m", [
    ("linear-mix", LINEAR_MIX, 0.0, 0.0), ("linear-mix", LINEAR_MIX, 0.4, 0.4),
    ("gamma", GAMMA, 0.5, 2.0), ("gamma", GAMMA, 2.0, 0.5), ("gamma", GAMMA, 50.0, 0.02),
])
def test_the_families_against_their_closed_forms(family, code, mode, m):
    tau = np.linspace(0.0, 6.0, 241)
    f = np.array([transmittance(code, t, m) for t in tau])
    np.testing.assert_allclose(f, closed_form(family, tau, mode), rtol=1e-12, atol=1e-15)
    inside = f > 0
    back = np.array([optical_depth_of(code, v, m) for v in f[inside]])
    np.testing.assert_allclose(back, tau[inside], rtol=1e-10, atol=1e-12)
    h = 1e-6  # the slope is -df/dtau: central differences away from the linear part's kink
    smooth = np.abs(tau - 2.0) > 1e-3
    numeric = -(closed_form(family, tau + h, mode) - closed_form(family, tau - h, mode)) / (2 * h)
    slope = np.array([transmittance_slope(code, t, m) for t in tau])
    np.testing.assert_allclose(slope[smooth][1:], numeric[smooth][1:], rtol=1e-6, atol=1e-9)


def slab(nx=4, ny=4, nz=5, extinction=None, family=None, mode=None, air=0.0):
    """A 1 x 1 x 1 km box of uniform (or given) cloud extinction, no air by default."""
    shape = (nx, ny, nz)
    ext = np.full(shape, 2.0) if extinction is None else extinction
    medium = optical_medium(uniform_axis(0, 1, nx), uniform_axis(0, 1, ny),
                            uniform_axis(0, 1, nz), ext, cloud_albedo=0.9, cloud_g=0.7,
                            air_extinction=air)
    if family is not None:
        medium["transmittance_mode"] = (("x", "y", "z"), np.broadcast_to(mode, shape).copy(),
                                        {"units": "1"})
        medium.attrs["transmittance"] = family
    return medium


def test_the_exponential_limit_renders_bitwise_the_exponential_images():
    scene = Scene([Camera((0.5, 0.5, 3.0), (0.5, 0.5, 0.5), (0, 1, 0), fov=30, nrows=6,
                          ncols=6)], Sun(20.0, 30.0), "periodic")
    plain = slab()
    ref = render(plain, scene, photons=4000, seed=2, batches=4, progress=False)
    for family, mode in (("gamma", np.inf), ("linear-mix", 1.0)):
        out = render(slab(family=family, mode=mode), scene, photons=4000, seed=2, batches=4,
                     progress=False)
        np.testing.assert_array_equal(out.radiance.values, ref.radiance.values)
        back = render(slab(family=family, mode=mode), scene, photons=8, method="backward",
                      seed=2, batches=4, progress=False)
        ref_back = render(plain, scene, photons=8, method="backward", seed=2, batches=4,
                          progress=False)
        np.testing.assert_array_equal(back.radiance.values, ref_back.radiance.values)


@njit(cache=True)
def _first_flights(grid, uniforms, evaluate):
    """Vertical rays down from the top face at (x, y) = uniforms[k, :2] (scaled to the box):
    1 if the free flight of target -log(1 - uniforms[k, 2]) reaches the bottom, else 0; or
    (``evaluate``) exp(-tau) of the walk to the bottom."""
    out = np.empty(uniforms.shape[0])
    top = grid.z_edges[-1]
    for k in range(uniforms.shape[0]):
        x = grid.x_edges[0] + (grid.x_edges[-1] - grid.x_edges[0]) * uniforms[k, 0]
        y = grid.y_edges[0] + (grid.y_edges[-1] - grid.y_edges[0]) * uniforms[k, 1]
        ix, iy, iz = locate_point(grid, x, y, top, 0.0, 0.0, -1.0)
        target = INF if evaluate else -math.log(1.0 - uniforms[k, 2])
        status, _, _, _, _, _, _, tau, _, _ = march(grid, x, y, top, 0.0, 0.0, -1.0, ix, iy, iz,
                                                    target, False)
        if evaluate:
            out[k] = math.exp(-tau)
        else:
            out[k] = 1.0 if status == BOTTOM else 0.0
    return out


def direct_transmittance(grid, n: int, seed: int, evaluate: bool) -> np.ndarray:
    """Per vertical ray from a uniform point of the top: whether its free flight reaches
    the bottom (0/1), or (``evaluate``) the walk's transmittance to the bottom."""
    return _first_flights(grid, np.random.default_rng(seed).random((n, 3)), evaluate)


@pytest.mark.parametrize("family, mode", [("gamma", 2.0), ("gamma", 0.7), ("linear-mix", 0.3),
                                          ("linear-mix", 0.0)])
def test_a_slabs_direct_transmittance_is_f_of_its_optical_depth(family, mode):
    """tau = 2 through the slab: the walk's transmittance equals f(2) to rounding, and the
    free flights reach the bottom with probability f(2) (binomial standard error)."""
    grid, _ = kernel_arrays(slab(family=family, mode=mode))
    expected = closed_form(family, np.array(2.0), mode)
    evaluated = direct_transmittance(grid, 50, 1, True)
    np.testing.assert_allclose(evaluated, expected, rtol=1e-12, atol=1e-15)
    hits = direct_transmittance(grid, 40_000, 3, False)
    std_error = math.sqrt(max(expected * (1 - expected), 1e-12) / hits.size)
    assert abs(hits.mean() - expected) < 4 * std_error + 1e-12, (hits.mean(), expected)


def test_an_ensemble_of_sub_grid_columns_has_the_power_law_transmittance():
    """Columns whose optical depth is gamma distributed (shape a, mean tau), each uniform,
    rendered with the ordinary exponential walk: their mean direct transmittance is the
    power law (1 + tau / a)^-a of the coarse medium (Laplace transform of the gamma law);
    both estimated by free flights, compared within their standard errors."""
    a, tau = 2.0, 1.5
    rng = np.random.default_rng(11)
    n = 64  # 64 x 64 columns of 1 km height: extinction = the column's optical depth
    column_tau = rng.gamma(a, tau / a, size=(n, n))
    fine = slab(nx=n, ny=n, nz=2, extinction=np.repeat(column_tau[:, :, None], 2, axis=2))
    coarse = slab(nx=2, ny=2, nz=2, extinction=np.full((2, 2, 2), tau), family="gamma",
                  mode=a)
    fine_hits = direct_transmittance(kernel_arrays(fine)[0], 200_000, 5, False)
    coarse_hits = direct_transmittance(kernel_arrays(coarse)[0], 200_000, 6, False)
    # the fine medium's mean over its own columns, and the power law it samples
    exact_fine = float(np.exp(-column_tau).mean())
    power_law = (1 + tau / a) ** (-a)
    se = math.sqrt(fine_hits.var() / fine_hits.size + coarse_hits.var() / coarse_hits.size)
    assert abs(fine_hits.mean() - coarse_hits.mean()) < 4 * se, (fine_hits.mean(),
                                                                 coarse_hits.mean(), se)
    assert abs(coarse_hits.mean() - power_law) < 4 * math.sqrt(coarse_hits.var() / 200_000)
    # the finite ensemble of 4096 columns is itself within its sampling error of the law
    assert abs(exact_fine - power_law) < 4 * np.exp(-column_tau).std() / n


def test_bad_modes_and_unsupported_estimators_are_refused():
    with pytest.raises(MediumError, match="must be in \\[0, 1\\]"):
        validate_medium(slab(family="linear-mix", mode=1.5))
    with pytest.raises(MediumError, match="must be > 0"):
        validate_medium(slab(family="gamma", mode=0.0))
    with pytest.raises(MediumError, match="needs the variable transmittance_mode"):
        validate_medium(slab().assign_attrs(transmittance="gamma"))
    with pytest.raises(MediumError, match="transmittance must be one of"):
        validate_medium(slab(family="fractal", mode=1.0))
    scene = Scene([Camera((0.5, 0.5, 3.0), (0.5, 0.5, 0.5), (0, 1, 0), fov=30, nrows=4,
                          ncols=4)], Sun(0.0, 0.0), "periodic")
    with pytest.raises(ValueError, match="non-exponential transmittance.*use DRT"):
        sample_matching_gradient(slab(family="gamma", mode=2.0), scene, np.ones((1, 4, 4)),
                                 samples_per_pixel=2, batches=2, progress=False)
    with pytest.raises(ValueError, match="linear-mix transmittance are not implemented"):
        drt_gradient(slab(family="linear-mix", mode=0.5), scene, np.ones((1, 4, 4)),
                     samples_per_pixel=2, batches=2, progress=False)
    # path recycling records and replays exponential paths only
    with pytest.raises(ValueError, match="non-exponential transmittance"):
        record_paths(slab(family="gamma", mode=2.0), scene, photons=8, batches=2)
    store = record_paths(slab(), scene, photons=8, batches=2)
    with pytest.raises(ValueError, match="non-exponential transmittance"):
        replay_images(store, slab(family="gamma", mode=2.0))


def test_energy_is_conserved_and_the_direct_beam_is_f_under_the_model():
    """Domain-mean fluxes (cloudct.mc.sensors) of a power-law slab (a = 2): conservative
    over a white ground with periodic boundaries everything comes back out of the top
    (albedo 1); absorbing, the direct transmittance is f(tau / mu0) and the energy balance
    closes, within standard errors."""
    sun = Sun(30.0, 0.0)
    conservative = slab(family="gamma", mode=2.0).assign(cloud_albedo=1.0)
    means = domain_means(conservative, sun=sun, boundary="periodic", ground_albedo=1.0,
                         photons=32_000, seed=4, rr_depth=5, progress=False)
    assert float(means.albedo_std_error) > 1e-4  # the roulette's noise: a real test
    assert_consistent(float(means.albedo), float(means.albedo_std_error), 1.0,
                      means.attrs["batches"], label="power law, white ground")
    means = domain_means(slab(family="gamma", mode=2.0), sun=sun, boundary="periodic",
                         photons=32_000, seed=5, rr_depth=3, progress=False)
    direct = closed_form("gamma", np.array(2.0 / math.cos(math.radians(30.0))), 2.0)
    assert_consistent(float(means.transmittance_direct),
                      float(means.transmittance_direct_std_error), float(direct),
                      means.attrs["batches"], label="power-law direct beam")
    assert_consistent(float(means.energy_balance), float(means.energy_balance_std_error), 1.0,
                      means.attrs["batches"], label="power-law energy balance")
