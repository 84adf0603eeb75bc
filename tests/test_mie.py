"""Mie optics: single-sphere limits, the size-averaged table, its cache, and the conversion of
a microphysical medium into kernel arrays.

Limits checked against theory: Q_ext -> 2 with the Nussenzveig-Wiscombe edge term
~1.99 x^(-2/3) for large spheres; Q_ext = (8/3) x^4 |(m^2 - 1)/(m^2 + 2)|^2 (1 + O(x^2)) for
small ones. The table's extinction per LWC is checked against an independent size
average (a different radius quadrature, scipy's gamma density) and against 1500 / r_eff.
"""

import math

import numpy as np
import pytest
import xarray as xr
from scipy import stats

import cloudct.physics.mie as mie
from cloudct.medium import microphysical_medium
from cloudct.optics import kernel_arrays, to_optical
from cloudct.physics.mie import compute_mie_table, mie_efficiencies, mie_table
from cloudct.physics.phase import HENYEY_GREENSTEIN, RAYLEIGH, TABULATED
from cloudct.physics.water import water_refractive_index


@pytest.fixture(scope="module")
def table():
    return mie_table()


@pytest.mark.parametrize("x0", [1000.0, 10000.0])
def test_large_spheres_extinction_tends_to_two(x0):
    # mean over a range of x to average out the ripple; edge term (Q - 2) x^(2/3) -> 1.992
    x = np.linspace(x0, 1.05 * x0, 101)
    qext, qsca, _ = mie_efficiencies(1.33, x)
    edge = (qext.mean() - 2.0) * x0 ** (2.0 / 3.0)
    print(f"x = {x0:g}: <Q_ext> = {qext.mean():.5f}, (Q - 2) x^(2/3) = {edge:.3f}")
    assert 1.8 < edge < 2.1
    np.testing.assert_allclose(qsca, qext, rtol=1e-12)  # no absorption


@pytest.mark.parametrize("m", [1.33, 1.5, complex(1.331, 2.15e-8)])
def test_small_spheres_rayleigh_limit(m):
    x = np.array([1e-3, 2e-3, 1e-2])
    qext, qsca, g = mie_efficiencies(m, x)
    rayleigh = 8.0 / 3.0 * x**4 * abs((m * m - 1) / (m * m + 2)) ** 2
    # relative corrections are O(x^2) (and absorption O(k / x^3) is tiny for water here)
    assert np.all(np.abs(qsca / rayleigh - 1.0) < x**2)
    slope = np.log(qsca[1] / qsca[0]) / np.log(2.0)
    assert slope == pytest.approx(4.0, abs=1e-5)
    assert np.all(np.abs(g) < x**2)  # isotropic-ish: g = O(x^2)


def test_non_absorbing_albedo_is_one():
    ds = compute_mie_table(refractive_index=1.331, reff=[2.0, 3.0], angles=[0.0, 90.0, 180.0])
    np.testing.assert_allclose(ds["albedo"].values, 1.0, rtol=0, atol=1e-12)
    absorbing = compute_mie_table(
        refractive_index=complex(1.331, 1e-4), reff=[2.0, 3.0], angles=[0.0, 90.0, 180.0]
    )
    assert np.all(absorbing["albedo"].values < 1.0 - 1e-4)


def independent_q_eff(reff, veff=0.1, wavelength=0.672):
    """<Q_ext r^2> / <r^2> on a uniform dx = 0.05 grid with scipy's gamma density."""
    m = water_refractive_index(wavelength)
    alpha = (1 - 3 * veff) / veff
    dist = stats.gamma(alpha + 1, scale=reff * veff)  # n(r) ∝ r^alpha exp(-r / (reff veff))
    r_lo, r_hi = dist.ppf(1e-9), dist.ppf(1 - 1e-12)
    k = 2 * math.pi / wavelength
    x = np.arange(k * r_lo, k * r_hi, 0.05)
    r = x / k
    qext, _, _ = mie_efficiencies(m, x)
    w = dist.pdf(r) * r**2
    return np.trapezoid(w * qext, r) / np.trapezoid(w, r)


@pytest.mark.parametrize("reff", [5.0, 10.0])
def test_extinction_per_lwc(table, reff):
    q_eff = independent_q_eff(reff)
    ext = float(table["ext_per_lwc"].sel(reff=reff))
    # beta / LWC = (3/4) Q_eff / (rho_w r_eff) = 750 Q_eff / r_eff [km-1 / (g m-3)];
    # the two quadratures differ by ~2e-4 (module docstring of cloudct.physics.mie)
    assert ext == pytest.approx(750.0 * q_eff / reff, rel=1e-3)
    # ... which is 1500 / r_eff up to the deviation of Q_eff from 2
    deviation = abs(ext - 1500.0 / reff)
    print(f"reff {reff}: Q_eff = {q_eff:.4f}, ext/LWC = {ext:.3f}, 1500/reff = {1500 / reff:.3f}")
    assert deviation <= abs(q_eff - 2.0) * 750.0 / reff * (1 + 1e-2)


def test_table_phase_functions(table):
    angles = table["scattering_angle"].values
    mu = np.cos(np.radians(angles))[::-1]
    for reff in (2.0, 10.0, 25.0):
        p = table["phase"].sel(reff=reff).values[::-1]
        # the linear interpolant between the 561 angles keeps the Mie normalisation and
        # asymmetry parameter to the resolution of the angle grid
        norm = 2 * math.pi * np.trapezoid(p, mu)
        g = 2 * math.pi * np.trapezoid(p * mu, mu) / norm
        assert norm == pytest.approx(1.0, abs=1e-3)
        assert g == pytest.approx(float(table["g"].sel(reff=reff)), abs=1e-4)
        assert p[-1] == p.max()  # forward peak
    assert np.all(np.diff(table["g"].sel(reff=slice(5, 25)).values) > 0)


def test_table_attributes_and_units(table):
    assert table.attrs["wavelength"] == 0.672
    assert table.attrs["veff"] == 0.1
    # Hale & Querry (1973): n = 1.331 at 0.650 and 0.675 micron, k = 1.64e-8 and 2.23e-8,
    # ln k linear in between (0.672 is 22/25 of the way)
    assert table.attrs["refractive_index_real"] == 1.331
    assert table.attrs["refractive_index_imag"] == pytest.approx(
        1.64e-8 * (2.23 / 1.64) ** (22 / 25), rel=1e-12
    )
    assert table.attrs["refractive_index_source"].startswith("Hale and Querry (1973)")
    assert "quadrature" in table.attrs
    for name in ("ext_per_lwc", "q_ext", "albedo", "g", "phase", "reff", "scattering_angle"):
        assert "units" in table[name].attrs and "long_name" in table[name].attrs


def test_cache(tmp_path, monkeypatch):
    params = dict(veff=0.05, reff=[4.0, 6.0], angles=[0.0, 1.0, 10.0, 90.0, 180.0])
    first = mie_table(cache_dir=tmp_path, **params)
    assert len(list(tmp_path.glob("*.nc"))) == 1

    def refuse(*args, **kwargs):
        raise AssertionError("recomputed a cached table")

    monkeypatch.setattr(mie, "compute_mie_table", refuse)
    again = mie_table(cache_dir=tmp_path, **params)
    xr.testing.assert_identical(first, again)
    # the default table ships with the package: nothing is computed or written
    default = mie_table(cache_dir=tmp_path / "unused")
    assert default.sizes["reff"] == 241
    assert not (tmp_path / "unused").exists()
    # other parameters are another table
    with pytest.raises(AssertionError, match="recomputed"):
        mie_table(cache_dir=tmp_path, veff=0.06, reff=[4.0, 6.0], angles=params["angles"])


def tiny_medium(lwc, reff, **kwargs):
    x = y = np.array([0.025, 0.075])
    z = np.array([0.1, 0.3, 0.5])
    shape = (2, 2, 3)
    return microphysical_medium(
        x, y, z, np.broadcast_to(lwc, shape), np.broadcast_to(reff, shape), **kwargs
    )


def test_to_optical_extinction(table):
    optical = to_optical(tiny_medium(0.5, 10.0), optics="mie")
    q_eff = float(table["q_ext"].sel(reff=10.0))
    # 1500 * 0.5 / 10 = 75 / km for Q = 2 (the quadrature's r_eff is 10 to ~1e-11)
    np.testing.assert_allclose(optical["cloud_extinction"].values, 75.0 * q_eff / 2.0, rtol=1e-10)
    np.testing.assert_allclose(
        optical["cloud_albedo"].values, float(table["albedo"].sel(reff=10.0)), rtol=1e-15
    )
    assert optical.attrs["wavelength"] == 0.672
    # r_eff on a node: row 10.0 alone (t = 0), and the row above for the derivative
    assert optical["cloud_phase"].shape == (2, table.sizes["scattering_angle"])
    assert float(optical["cloud_phase_reff"][0]) == 10.0
    assert np.all(optical["cloud_phase_index"].values == 0)
    assert np.all(optical["cloud_phase_weight"].values == 0.0)


def test_to_optical_interpolation_and_two_row_phase(table):
    reff = np.zeros((2, 2, 3))
    reff[..., 0], reff[..., 1], reff[..., 2] = 10.02, 10.08, 10.05
    lwc = np.where(np.arange(3) == 2, 0.0, 1.0) * np.ones((2, 2, 3))  # top layer clear
    optical = to_optical(tiny_medium(lwc, reff), optics="mie")
    lo, hi = table["ext_per_lwc"].sel(reff=10.0).item(), table["ext_per_lwc"].sel(reff=10.1).item()
    ext = optical["cloud_extinction"].values
    assert ext[0, 0, 0] == pytest.approx(0.8 * lo + 0.2 * hi, rel=1e-12)
    assert ext[0, 0, 1] == pytest.approx(0.2 * lo + 0.8 * hi, rel=1e-12)
    assert np.all(ext[..., 2] == 0.0)
    # the phase function of rows 10.0 and 10.1 mixed with the extinction's weights
    rows = optical["cloud_phase_reff"].values[optical["cloud_phase_index"].values]
    weight = optical["cloud_phase_weight"].values
    assert np.all(rows[..., :2] == 10.0)
    assert np.all(optical["cloud_phase_reff"].values == [10.0, 10.1])
    np.testing.assert_allclose(weight[..., 0], 0.2, rtol=1e-9)
    np.testing.assert_allclose(weight[..., 1], 0.8, rtol=1e-9)
    assert np.all(weight[..., 2] == 0.0) and np.all(rows[..., 2] == 10.0)


def test_to_optical_hg_and_errors():
    optical = to_optical(tiny_medium(0.3, 8.0), optics="hg")
    assert float(optical["cloud_g"]) == 0.85 and "cloud_phase" not in optical
    assert np.all(optical["cloud_albedo"].values == 0.99)  # the seed paper's
    assert optical.attrs["optics"] == "hg"
    mie = to_optical(tiny_medium(0.3, 8.0), optics="mie")
    assert mie.attrs["optics"] == "mie" and 0.999 < float(mie["cloud_albedo"].max()) <= 1.0
    np.testing.assert_array_equal(mie["cloud_extinction"], optical["cloud_extinction"])
    with pytest.raises(ValueError, match="optics must be one of"):
        to_optical(tiny_medium(0.3, 8.0), optics="rayleigh")
    with pytest.raises(ValueError, match="already optical with optics 'hg'"):
        to_optical(optical, optics="mie")
    with pytest.raises(ValueError, match="outside the Mie table"):
        to_optical(tiny_medium(0.3, 30.0))
    to_optical(tiny_medium(0.0, 30.0))  # clear cells: reff is ignored


def test_kernel_arrays_mie():
    profile = np.array([0.05, 0.04, 0.03])
    optical = to_optical(tiny_medium(0.5, 10.0, air_extinction=profile), optics="mie")
    grid, bank = kernel_arrays(optical)
    for name in ("x_edges", "y_edges", "z_edges", "extinction", "albedo"):
        array = getattr(grid, name)
        assert array.dtype == np.float64 and array.flags.c_contiguous
    assert grid.phase_index.dtype == np.int32 and grid.phase_index.flags.c_contiguous
    assert grid.extinction.shape == grid.albedo.shape == grid.phase_index.shape == (2, 2, 2, 3)
    np.testing.assert_allclose(grid.z_edges, [0.0, 0.2, 0.4, 0.6])
    np.testing.assert_allclose(grid.x_edges, [0.0, 0.05, 0.1])
    np.testing.assert_array_equal(grid.extinction[0], np.broadcast_to(profile, (2, 2, 3)))
    assert np.all(grid.albedo[0] == 0.912)
    np.testing.assert_array_equal(grid.extinction[1], optical["cloud_extinction"].values)
    assert bank.kind.tolist() == [RAYLEIGH, TABULATED, TABULATED]  # rows 10.0 and 10.1
    assert np.all(grid.phase_index[0] == 0) and np.all(grid.phase_index[1] == 1)
    assert np.all(grid.phase_weight == 0.0) and grid.phase_weight.shape == (2, 2, 2, 3)
    assert bank.table_start.dtype == np.int64 and bank.g.dtype == np.float64


def test_kernel_arrays_hg_distinct_g():
    optical = to_optical(tiny_medium(0.5, 10.0), optics="hg")
    g = np.full((2, 2, 3), 0.85)
    g[0, 0, 0] = 0.7
    optical["cloud_g"] = xr.DataArray(g, dims=("x", "y", "z"), attrs={"units": "1"})
    grid, bank = kernel_arrays(optical)
    assert bank.kind.tolist() == [RAYLEIGH, HENYEY_GREENSTEIN, HENYEY_GREENSTEIN]
    np.testing.assert_array_equal(bank.g[grid.phase_index[1]], g)
    with pytest.raises(ValueError, match="optical"):
        kernel_arrays(tiny_medium(0.5, 10.0))
