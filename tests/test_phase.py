"""Phase functions: normalisation, exact inverse CDFs, and sampled statistics.

Reference values come from scipy quadrature of the evaluated densities and from closed-form
CDFs, not from the builder's own normalisation. Statistical checks use fixed seeds, z-scores
with the sample standard error (|z| < 4) and chi-square p-values (> 1e-3).
"""

import math
from fractions import Fraction

import numpy as np
import pytest
from numba import njit
from scipy import integrate, stats

from cloudct.physics.mie import mie_table
from cloudct.physics.phase import (
    HENYEY_GREENSTEIN,
    RAYLEIGH,
    TABULATED,
    phase_bank,
    phase_function,
    sample_henyey_greenstein_cosine,
    sample_phase_cosine,
    sample_rayleigh_cosine,
    scatter_direction,
)

N_SAMPLES = 200_000
HG_G = (0.0, 0.5, 0.85, -0.3)


@pytest.fixture(scope="module")
def bank():
    """Rayleigh, four HG and the Mie phase function of r_eff = 10 micron (default table)."""
    table = mie_table().sel(reff=10.0)
    entries = [("rayleigh",)] + [("hg", g) for g in HG_G]
    entries.append(("tabulated", table["scattering_angle"].values, table["phase"].values))
    return phase_bank(entries)


CASES = [(0, "rayleigh")] + [(1 + i, f"hg g={g}") for i, g in enumerate(HG_G)] + [(5, "mie")]


def breakpoints(bank, ip):
    """Nodes of a tabulated phase function (where its derivative jumps), for quad."""
    lo, hi = bank.table_start[ip], bank.table_start[ip + 1]
    return bank.table_mu[lo + 1 : hi - 1]


def sphere_integral(bank, ip, lo, hi, weight=None):
    """2 pi * integral_lo^hi p(mu) [weight(mu)] dmu by adaptive quadrature."""
    pts = [m for m in breakpoints(bank, ip) if lo < m < hi]
    if weight is None:
        weight = _one

    def f(mu):
        return phase_function(bank, ip, mu) * weight(mu)

    # quad's breakpoints are needed where the tabulated density has kinks or a narrow peak
    value, _ = integrate.quad(f, lo, hi, points=pts or None, limit=4 * len(pts) + 200)
    return 2.0 * math.pi * value


def _one(mu):
    return 1.0


@njit(cache=True)
def _draw(bank, ip, n, rng):
    out = np.empty(n)
    for i in range(n):
        out[i] = sample_phase_cosine(bank, ip, rng.random())
    return out


def draw(bank, ip, n, seed):
    """n scattering cosines from bank row ip, drawn in a numba loop with a seeded generator."""
    return _draw(bank, ip, n, np.random.default_rng(seed))


@pytest.mark.parametrize("ip,name", CASES)
def test_normalised_over_sphere(bank, ip, name):
    # the piecewise-linear Mie interpolant: normalised exactly by construction; the
    # analytic ones: exactly. quad's own accuracy here is ~1e-12.
    assert sphere_integral(bank, ip, -1.0, 1.0) == pytest.approx(1.0, abs=1e-9)


def test_analytic_values():
    b = phase_bank([("rayleigh",), ("hg", 0.85)])
    assert phase_function(b, 0, 0.0) == 3.0 / (16.0 * math.pi)
    assert phase_function(b, 0, -1.0) == 6.0 / (16.0 * math.pi)
    # HG forward value (1 + g) / (4 pi (1 - g)^2)
    assert phase_function(b, 1, 1.0) == pytest.approx(1.85 / (4 * math.pi * 0.15**2), rel=1e-14)
    assert list(b.kind) == [RAYLEIGH, HENYEY_GREENSTEIN]


@pytest.mark.parametrize("ip,name", CASES)
def test_bank_g_is_mean_cosine(bank, ip, name):
    g = sphere_integral(bank, ip, -1.0, 1.0, weight=lambda mu: mu)
    assert bank.g[ip] == pytest.approx(g, abs=1e-9)


@pytest.mark.parametrize("ip,name", CASES)
def test_sampled_mean_cosine(bank, ip, name):
    mu = draw(bank, ip, N_SAMPLES, 1234 + ip)
    g = sphere_integral(bank, ip, -1.0, 1.0, weight=lambda m: m)
    z = (mu.mean() - g) / (mu.std(ddof=1) / math.sqrt(mu.size))
    print(f"{name}: mean cosine {mu.mean():.5f} vs {g:.5f}, z = {z:+.2f}")
    assert abs(z) < 4.0


def chi_square_bins(bank, ip):
    """Bin edges in mu, fine near the forward direction, and the bin probabilities."""
    theta = np.concatenate(
        [np.arange(0.0, 2.0, 0.1), np.arange(2.0, 10.0, 0.5), np.arange(10.0, 180.0, 2.0), [180]]
    )
    edges = np.cos(np.radians(theta))[::-1]
    edges[0], edges[-1] = -1.0, 1.0
    prob = np.array(
        [sphere_integral(bank, ip, a, b) for a, b in zip(edges[:-1], edges[1:], strict=True)]
    )
    return edges, prob


def merge_small_bins(counts, expected, minimum=5.0):
    """Merge neighbouring bins until each expects at least ``minimum`` counts."""
    obs, exp = [], []
    o_acc = e_acc = 0.0
    for o, e in zip(counts, expected, strict=True):
        o_acc += o
        e_acc += e
        if e_acc >= minimum:
            obs.append(o_acc)
            exp.append(e_acc)
            o_acc = e_acc = 0.0
    obs[-1] += o_acc
    exp[-1] += e_acc
    return np.array(obs), np.array(exp)


@pytest.mark.parametrize("ip,name", CASES)
def test_sampled_histogram_chi_square(bank, ip, name):
    edges, prob = chi_square_bins(bank, ip)
    mu = draw(bank, ip, N_SAMPLES, 99 + ip)
    counts, _ = np.histogram(mu, bins=edges)
    obs, exp = merge_small_bins(counts, prob * N_SAMPLES / prob.sum())
    result = stats.chisquare(obs, exp)
    print(f"{name}: chi2 = {result.statistic:.1f} on {obs.size - 1} dof, p = {result.pvalue:.3f}")
    if name == "mie":
        assert np.sum(edges > math.cos(math.radians(2.0))) >= 20  # the peak is resolved
    assert result.pvalue > 1e-3


@pytest.mark.parametrize("u", np.linspace(0.0, 1.0, 41))
def test_rayleigh_inverse_cdf(u):
    mu = sample_rayleigh_cosine(u)
    assert 3.0 / 8.0 * (mu + mu**3 / 3.0 + 4.0 / 3.0) == pytest.approx(u, abs=1e-14)


@pytest.mark.parametrize("g", [0.0, 1e-12, 1e-6, 0.5, 0.85, -0.3, 0.99])
def test_hg_inverse_cdf(g):
    # the textbook inverse in exact rational arithmetic, where its 1/g is harmless
    for u in np.linspace(0.0, 1.0, 101):
        mu = sample_henyey_greenstein_cosine(g, u)
        gq, uq = Fraction(g), Fraction(u)
        if g == 0.0:
            exact = 2 * uq - 1
        else:
            t = (1 - gq**2) / (1 - gq + 2 * gq * uq)
            exact = (1 + gq**2 - t**2) / (2 * gq)
        assert mu == pytest.approx(float(exact), abs=1e-15)


@pytest.mark.parametrize(
    "values,inverse",
    [
        ([1.0, 0.0], lambda u: 2.0 * np.sqrt(u) - 1.0),  # p ∝ 1 + mu
        ([0.0, 1.0], lambda u: 1.0 - 2.0 * np.sqrt(1.0 - u)),  # p ∝ 1 - mu
        ([2.0, 2.0], lambda u: 2.0 * u - 1.0),  # isotropic
    ],
)
def test_tabulated_inverse_cdf_exact(values, inverse):
    b = phase_bank([("tabulated", [0.0, 180.0], values)])
    assert b.kind[0] == TABULATED
    u = np.linspace(0.0, 1.0, 101)
    mu = np.array([sample_phase_cosine(b, 0, x) for x in u])
    np.testing.assert_allclose(mu, inverse(u), rtol=0, atol=1e-14)


def test_tabulated_cdf_piecewise_quadratic(bank):
    # CDF of the linear interpolant at a sampled mu, written out independently
    ip = 5
    lo, hi = bank.table_start[ip], bank.table_start[ip + 1]
    nodes, pdf = bank.table_mu[lo:hi], bank.table_pdf[lo:hi]
    piece = 2 * math.pi * np.diff(nodes) * 0.5 * (pdf[:-1] + pdf[1:])
    for u in np.linspace(0.0, 0.999999, 57):
        mu = sample_phase_cosine(bank, ip, u)
        i = min(np.searchsorted(nodes, mu, side="right") - 1, nodes.size - 2)
        t = mu - nodes[i]
        slope = (pdf[i + 1] - pdf[i]) / (nodes[i + 1] - nodes[i])
        cdf = piece[:i].sum() + 2 * math.pi * (pdf[i] * t + 0.5 * slope * t * t)
        assert cdf == pytest.approx(u, abs=1e-12)


def test_tabulated_evaluation_is_linear_in_mu():
    b = phase_bank([("hg", 0.3), ("tabulated", [0.0, 90.0, 180.0], [3.0, 1.0, 2.0])])
    assert b.table_start.tolist() == [0, 0, 3]
    p_back, p_side, p_fwd = b.table_pdf
    assert p_fwd / p_back == pytest.approx(1.5, rel=1e-15)
    assert phase_function(b, 1, 0.5) == pytest.approx(0.5 * (p_side + p_fwd), rel=1e-15)
    assert phase_function(b, 1, -0.25) == pytest.approx(0.75 * p_side + 0.25 * p_back, rel=1e-15)


def test_builder_rejects_bad_specs():
    with pytest.raises(ValueError):
        phase_bank([("hg", 1.0)])
    with pytest.raises(ValueError):
        phase_bank([("tabulated", [0.0, 90.0], [1.0, 1.0])])  # does not reach 180
    with pytest.raises(ValueError):
        phase_bank([("mie",)])


DIRECTIONS = [
    (0.0, 0.0, 1.0),
    (0.0, 0.0, -1.0),
    (1e-9, -2e-9, 1.0),
    (3e-9, 1e-9, -1.0),
    (1.0, 0.0, 0.0),
    (0.3, -0.4, -math.sqrt(0.75)),
]


@pytest.mark.parametrize("u", DIRECTIONS)
def test_scatter_direction_geometry(u):
    u = np.array(u) / np.linalg.norm(u)
    for mu in (-1.0, -0.3, 0.0, 0.7, 0.999999, 1.0):
        for phi in np.linspace(0.0, 2.0 * math.pi, 7):
            v = np.array(scatter_direction(*u, mu, phi))
            assert np.linalg.norm(v) == pytest.approx(1.0, abs=1e-15)
            assert v @ u == pytest.approx(mu, abs=1e-14)
    # azimuths a quarter turn apart span a right-handed frame about u
    a = np.array(scatter_direction(*u, 0.0, 0.0))
    b = np.array(scatter_direction(*u, 0.0, 0.5 * math.pi))
    np.testing.assert_allclose(np.cross(a, b), u, atol=1e-14)
