"""Validation of the independent plane-parallel reference solver (tests/reference).

The checks here do not use cloudct at all.  They establish that the adding–doubling
reference converges to the exact radiance so that it can be used to judge the Monte Carlo
engine:

* single-scattering limit (closed form written here with explicit 3-D direction vectors,
  which also pins down the azimuth convention);
* energy conservation for conservative scattering;
* fluxes obtained by integrating the user-facing radiances over the hemisphere;
* a semi-infinite isotropically scattering medium against Chandrasekhar's H-function,
  computed here from its explicit integral representation, which itself is checked
  against Chandrasekhar's (1950) tabulated conservative values;
* reciprocity of the reflection and transmission functions;
* a Lambertian surface under a vanishingly thin slab and the analytic surface-coupling
  formula for a thick slab;
* convergence with the number of streams.
"""

from __future__ import annotations

import numpy as np
import pytest
from reference.plane_parallel import (
    henyey_greenstein,
    isotropic,
    rayleigh,
    rayleigh_hg_mixture,
    slab_fluxes,
    slab_radiances,
)
from scipy.integrate import quad

MIX_085 = rayleigh_hg_mixture(0.3, 0.7, 0.85)  # bs_Rayleigh = 0.3, bs_HG = 0.7, g = 0.85


def _direction(zenith_deg: np.ndarray, azimuth_deg: np.ndarray, upward: bool) -> np.ndarray:
    """Unit propagation vector; zenith measured from +z (upward) or from -z (downward)."""
    th, ph = np.deg2rad(zenith_deg), np.deg2rad(azimuth_deg)
    vz = np.cos(th) if upward else -np.cos(th)
    return np.stack(np.broadcast_arrays(np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), vz))


def _single_scattering(tau, omega, phase, mu0, phi0_deg, theta_v, phi_v):
    """Closed-form single-scattering radiances for unit solar irradiance."""
    theta0 = np.rad2deg(np.arccos(mu0))
    sun_travel = _direction(theta0, phi0_deg + 180.0, upward=False)
    up = _direction(theta_v, phi_v, upward=True)
    down = _direction(theta_v, phi_v, upward=False)
    mu = np.cos(np.deg2rad(theta_v))
    cos_r = np.einsum("i,i...->...", sun_travel, up)
    cos_t = np.einsum("i,i...->...", sun_travel, down)
    refl = omega * phase(cos_r) * mu0 / (mu0 + mu) * (1.0 - np.exp(-tau * (1 / mu0 + 1 / mu)))
    equal = np.isclose(mu, mu0, rtol=0.0, atol=1e-12)
    mu_safe = np.where(equal, 0.5, mu)
    geom_t = np.where(
        equal,
        tau / mu * np.exp(-tau / mu),  # limit mu -> mu0
        mu0 / (mu0 - mu_safe) * (np.exp(-tau / mu0) - np.exp(-tau / mu_safe)),
    )
    return refl, omega * phase(cos_t) * geom_t


# ---------------------------------------------------------------------------------------


@pytest.mark.parametrize("omega", [1.0, 0.6])
def test_single_scattering_limit(omega: float) -> None:
    mu0, phi0 = np.cos(np.deg2rad(35.0)), 40.0
    # Includes exact backscatter (35, 40) and exact forward scattering (35, 220).
    theta_v = np.array([0.0, 20.0, 35.0, 35.0, 50.0, 65.0, 75.0, 10.0])
    phi_v = np.array([0.0, 100.0, 40.0, 220.0, 300.0, 180.0, 15.0, 250.0])

    def excess(tau: float) -> np.ndarray:
        """Relative excess of the full solution over single scattering (refl, trans)."""
        refl, trans = slab_radiances(tau, omega, MIX_085, mu0, phi0, theta_v, phi_v)
        refl_ss, trans_ss = _single_scattering(tau, omega, MIX_085, mu0, phi0, theta_v, phi_v)
        return np.concatenate([refl / refl_ss - 1.0, trans / trans_ss - 1.0])

    # Multiple scattering adds a positive O(tau) fraction (about 6 tau for this forward-peaked
    # mixture, the reflection in particular being fed by forward-scattered light).
    e3, e4, e5 = excess(1e-3), excess(1e-4), excess(1e-5)
    assert np.all(e3 > 0) and np.all(e3 < 1e-2)
    assert np.all(e5 > 0) and np.all(e5 < 1e-4)
    # The excess is proportional to tau (up to tau*ln(tau) corrections), so the single-
    # scattering part itself is exact: any error in it would not scale away like this.
    np.testing.assert_allclose(e4 / e5, 10.0, rtol=0.07)


@pytest.mark.parametrize("tau", [0.1, 1.0, 10.0])
@pytest.mark.parametrize("phase", [MIX_085, rayleigh(), henyey_greenstein(0.5)])
def test_energy_conservation(tau: float, phase) -> None:
    mu0 = np.cos(np.deg2rad(50.0))
    fluxes = slab_fluxes(tau, 1.0, phase, mu0)
    total = fluxes.reflected + fluxes.transmitted_diffuse + fluxes.transmitted_direct
    assert abs(total - mu0) < 1e-4 * mu0
    assert fluxes.reflected > 0 and fluxes.transmitted_diffuse > 0


def test_hemispheric_integral_of_radiance_matches_flux() -> None:
    """Integrate the user-facing radiance (incl. exact single scattering) over 2π."""
    tau, omega, mu0, phi0 = 2.0, 0.95, np.cos(np.deg2rad(30.0)), 0.0
    phase = rayleigh_hg_mixture(0.2, 0.8, 0.7)
    x, w = np.polynomial.legendre.leggauss(48)
    mu, w_mu = 0.5 * (x + 1.0), 0.5 * w
    n_phi = 180
    phi = np.arange(n_phi) * 360.0 / n_phi
    theta_grid = np.rad2deg(np.arccos(mu))[:, None] + 0 * phi[None, :]
    refl, trans = slab_radiances(tau, omega, phase, mu0, phi0, theta_grid, phi[None, :])
    d_phi = 2.0 * np.pi / n_phi
    flux_r = np.sum(w_mu[:, None] * mu[:, None] * refl) * d_phi
    flux_t = np.sum(w_mu[:, None] * mu[:, None] * trans) * d_phi
    fluxes = slab_fluxes(tau, omega, phase, mu0)
    assert flux_r == pytest.approx(fluxes.reflected, rel=1e-7)
    assert flux_t == pytest.approx(fluxes.transmitted_diffuse, rel=1e-7)


def _chandrasekhar_h(mu: float, omega: float) -> float:
    """Isotropic-scattering H-function from its explicit integral representation.

    ln H(mu) = -(mu/pi) ∫_0^{pi/2} ln(1 - omega θ cot θ) / (cos²θ + mu² sin²θ) dθ
    (Chandrasekhar 1950, Radiative Transfer, ch. V).
    """

    def integrand(theta: float) -> float:
        if theta == 0.0:
            return np.log(1.0 - omega) if omega < 1.0 else 0.0
        char = 1.0 - omega * theta / np.tan(theta)
        return np.log(char) / (np.cos(theta) ** 2 + mu**2 * np.sin(theta) ** 2)

    value, _ = quad(integrand, 0.0, np.pi / 2, limit=200, epsabs=1e-12, epsrel=1e-10)
    return float(np.exp(-mu / np.pi * value))


def test_h_function_reproduces_published_table() -> None:
    # Chandrasekhar (1950), table of H(mu) for conservative isotropic scattering.
    assert _chandrasekhar_h(0.5, 1.0) == pytest.approx(2.01278, abs=1e-5)
    assert _chandrasekhar_h(1.0, 1.0) == pytest.approx(2.90781, abs=1e-5)
    # Exact moment identity: ∫_0^1 H dmu = 2 (1 - sqrt(1 - omega)) / omega.
    omega = 0.9
    x, w = np.polynomial.legendre.leggauss(40)
    alpha0 = sum(
        0.5 * wi * _chandrasekhar_h(0.5 * (xi + 1), omega) for xi, wi in zip(x, w, strict=True)
    )
    assert alpha0 == pytest.approx(2 * (1 - np.sqrt(1 - omega)) / omega, rel=1e-6)


@pytest.mark.parametrize(("omega", "tau"), [(0.5, 10.0), (0.9, 40.0)])
def test_semi_infinite_isotropic_matches_h_function(omega: float, tau: float) -> None:
    """I_r = omega/(4 pi) * mu0/(mu + mu0) * H(mu) H(mu0) for a semi-infinite medium."""
    mu0 = 0.6
    theta_v = np.array([0.0, 30.0, 60.0, 80.0])
    refl, _ = slab_radiances(tau, omega, isotropic(), mu0, 0.0, theta_v, [0.0, 45.0, 90.0, 270.0])
    mu = np.cos(np.deg2rad(theta_v))
    h0 = _chandrasekhar_h(mu0, omega)
    expected = [omega / (4 * np.pi) * mu0 / (m + mu0) * _chandrasekhar_h(m, omega) * h0 for m in mu]
    np.testing.assert_allclose(refl, expected, rtol=1e-6)


@pytest.mark.parametrize("surface_albedo", [0.0, 0.4])
def test_reciprocity(surface_albedo: float) -> None:
    """rho(mu, mu0, dphi) = pi I_r / mu0 is symmetric under mu <-> mu0 at fixed
    dphi = phi_v - phi0; for the (up-down symmetric) bare slab likewise pi I_t / mu0."""
    tau, omega = 1.5, 0.9

    def rho(sun_zenith: float, view_zenith: float, phi0: float, dphi: float):
        mu0 = np.cos(np.deg2rad(sun_zenith))
        refl, trans = slab_radiances(
            tau, omega, MIX_085, mu0, phi0, view_zenith, phi0 + dphi, surface_albedo
        )
        return np.pi * refl / mu0, np.pi * trans / mu0

    for dphi in (0.0, 70.0, 180.0):
        r_ab, t_ab = rho(25.0, 62.0, 10.0, dphi)
        r_ba, t_ba = rho(62.0, 25.0, 123.0, dphi)
        assert r_ab == pytest.approx(r_ba, rel=1e-10)
        if surface_albedo == 0.0:
            assert t_ab == pytest.approx(t_ba, rel=1e-10)


@pytest.mark.parametrize("tau", [0.0, 1e-9])
def test_lambertian_surface_under_vanishing_slab(tau: float) -> None:
    albedo, mu0 = 0.37, np.cos(np.deg2rad(42.0))
    theta_v = np.array([0.0, 30.0, 60.0, 85.0])
    refl, trans = slab_radiances(
        tau, 0.9, MIX_085, mu0, 15.0, theta_v, [0.0, 90.0, 195.0, 15.0], albedo
    )
    np.testing.assert_allclose(refl, albedo * mu0 / np.pi, rtol=1e-6)
    assert np.all(np.abs(trans) < 1e-6)


def test_lambertian_coupling_formula() -> None:
    """Surface contribution from the bare-slab solutions (van de Hulst / Chandrasekhar):

    I_r(A) = I_r(0) + A E / pi * [exp(-tau/mu) + F_t(mu)/mu]
    I_t(A) = I_t(0) + A E / pi * F_r(mu)/mu
    E = [mu0 exp(-tau/mu0) + F_t(mu0)] / (1 - A S),   S = 2 ∫_0^1 F_r(mu) dmu,

    F_r, F_t = reflected / diffusely transmitted flux for a unit beam at mu (reciprocity
    turns them into the response to isotropic illumination).
    """
    tau, omega, albedo, n = 1.0, 0.9, 0.3, 16
    phase = rayleigh_hg_mixture(0.3, 0.7, 0.6)
    mu0, phi0 = np.cos(np.deg2rad(30.0)), 0.0
    theta_v = np.array([0.0, 40.0, 70.0])
    phi_v = np.array([0.0, 120.0, 200.0])
    mu = np.cos(np.deg2rad(theta_v))

    def fluxes(m: float) -> tuple[float, float]:
        f = slab_fluxes(tau, omega, phase, m, n_streams=n)
        return f.reflected, f.transmitted_diffuse

    # S by Gauss quadrature in t with mu = t^2 (clusters nodes near the horizon).
    x, w = np.polynomial.legendre.leggauss(40)
    t, w_t = 0.5 * (x + 1.0), 0.5 * w
    spherical_albedo = 2.0 * sum(
        2 * ti * wi * fluxes(ti**2)[0] for ti, wi in zip(t, w_t, strict=True)
    )
    e_surf = (mu0 * np.exp(-tau / mu0) + fluxes(mu0)[1]) / (1.0 - albedo * spherical_albedo)
    f_view = np.array([fluxes(m) for m in mu])

    r0, t0 = slab_radiances(tau, omega, phase, mu0, phi0, theta_v, phi_v, n_streams=n)
    r_a, t_a = slab_radiances(tau, omega, phase, mu0, phi0, theta_v, phi_v, albedo, n_streams=n)
    expected_r = r0 + albedo * e_surf / np.pi * (np.exp(-tau / mu) + f_view[:, 1] / mu)
    expected_t = t0 + albedo * e_surf / np.pi * f_view[:, 0] / mu
    np.testing.assert_allclose(r_a, expected_r, rtol=1e-7)
    np.testing.assert_allclose(t_a, expected_t, rtol=1e-7)


@pytest.mark.parametrize(("tau", "omega"), [(0.1, 0.5), (1.0, 0.9), (10.0, 1.0)])
def test_stream_convergence(tau: float, omega: float) -> None:
    mu0, phi0 = np.cos(np.deg2rad(60.0)), 0.0
    # Includes the forward-scattering peak of transmission (60, 180).
    theta_v = np.array([0.0, 30.0, 60.0, 60.0, 75.0])
    phi_v = np.array([0.0, 90.0, 180.0, 0.0, 160.0])
    results = {
        n: slab_radiances(tau, omega, MIX_085, mu0, phi0, theta_v, phi_v, n_streams=n)
        for n in (8, 16, 32, 48)
    }
    ref = np.concatenate(results[48])

    def err(n: int) -> float:
        return float(np.max(np.abs(np.concatenate(results[n]) / ref - 1.0)))

    assert err(8) > err(16) > err(32)
    assert err(16) < 2e-3
    assert err(32) < 5e-6


def test_callable_phase_function_matches_helper() -> None:
    """A plain callable (numerical Legendre moments) gives the same answer as the helper."""
    g = 0.7

    def hg(x: np.ndarray) -> np.ndarray:
        return (1 - g * g) / (4 * np.pi * (1 + g * g - 2 * g * x) ** 1.5)

    views = ([10.0, 50.0], [0.0, 200.0])
    helper = slab_radiances(1.0, 0.8, henyey_greenstein(g), 0.7, 20.0, *views, n_streams=16)
    plain = slab_radiances(1.0, 0.8, hg, 0.7, 20.0, *views, n_streams=16)
    np.testing.assert_allclose(plain, helper, rtol=1e-9)


def test_shapes_and_input_validation() -> None:
    refl, trans = slab_radiances(
        1.0, 0.9, rayleigh(), 0.5, 0.0, [[0.0], [45.0]], [0.0, 90.0, 180.0]
    )
    assert refl.shape == trans.shape == (2, 3)
    # Azimuth is irrelevant at nadir/zenith view.
    np.testing.assert_allclose(refl[0], refl[0, 0], rtol=1e-12)
    with pytest.raises(ValueError):
        slab_radiances(1.0, 0.9, rayleigh(), 0.5, 0.0, 90.0, 0.0)
    with pytest.raises(ValueError):
        slab_radiances(1.0, 1.1, rayleigh(), 0.5, 0.0, 10.0, 0.0)
    with pytest.raises(ValueError):
        slab_radiances(-1.0, 0.9, rayleigh(), 0.5, 0.0, 10.0, 0.0)


def test_view_chunking_is_transparent(monkeypatch: pytest.MonkeyPatch) -> None:
    """Many distinct view angles are processed in chunks; results must not depend on it."""
    import reference.plane_parallel as module

    views = ([0.0, 10.0, 20.0, 35.0, 50.0, 70.0, 10.0], [0.0, 30, 60, 90, 120, 150, 300])
    whole = slab_radiances(1.0, 0.9, MIX_085, 0.7, 0.0, *views, 0.2)
    monkeypatch.setattr(module, "_VIEW_CHUNK", 2)
    chunked = slab_radiances(1.0, 0.9, MIX_085, 0.7, 0.0, *views, 0.2)
    np.testing.assert_allclose(chunked, whole, rtol=1e-12)
