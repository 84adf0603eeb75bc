"""Bands: the refractive index of water (Hale & Querry 1973), the droplets' absorption it
gives at 1.65 and 2.13 micron, and air scaled between wavelengths (Bodhaine et al. 1999).

The expected numbers are typed in from the publications (the table's rows, Eq. 30's
arithmetic done by hand) or derived in the comments, not computed with the code checked.
"""

import math

import numpy as np
import pytest

from cloudct.medium import microphysical_medium
from cloudct.optics import band_optics, to_optical
from cloudct.physics.air import air_extinction_at, rayleigh_optical_depth
from cloudct.physics.mie import compute_mie_table, mie_table
from cloudct.physics.water import water_refractive_index

REFF = [5.0, 10.0, 20.0]
FEW_ANGLES = [0.0, 1.0, 10.0, 90.0, 180.0]


@pytest.fixture(scope="module")
def tables():
    """Small Mie tables (3 r_eff, 5 angles) at the near-infrared bands, default index."""
    return {lam: compute_mie_table(lam, reff=REFF, angles=FEW_ANGLES) for lam in (1.65, 2.13)}


# Hale & Querry (1973), Appl. Opt. 12, 555, the table's rows (wavelength [micron], n, k)
@pytest.mark.parametrize(
    "lam, n, k",
    [(0.650, 1.331, 1.64e-8), (1.6, 1.317, 8.55e-5), (2.0, 1.306, 1.10e-3), (2.2, 1.296, 2.89e-4)],
)
def test_water_index_at_tabulated_wavelengths(lam, n, k):
    m = water_refractive_index(lam)
    assert m.real == pytest.approx(n, rel=1e-12)
    assert m.imag == pytest.approx(k, rel=1e-12)


def test_water_index_between_tabulated_wavelengths():
    m = water_refractive_index(np.array([1.65, 2.1, 2.13]))
    assert m.shape == (3,)
    # 1.65 lies between the rows 1.6 (1.317, 8.55e-5) and 1.8 (1.312, 1.15e-4)
    assert 1.312 < m[0].real < 1.317 and 8.55e-5 < m[0].imag < 1.15e-4
    # 2.1 is midway between 2.0 (1.306, 1.10e-3) and 2.2 (1.296, 2.89e-4): the mean of n,
    # the geometric mean of k (ln k linear in wavelength)
    assert m[1].real == pytest.approx(1.301, rel=1e-12)
    assert m[1].imag == pytest.approx(math.sqrt(1.10e-3 * 2.89e-4), rel=1e-12)
    assert 1.296 < m[2].real < 1.306 and 2.89e-4 < m[2].imag < 1.10e-3
    for outside in (0.19, 2.7, float("nan")):
        with pytest.raises(ValueError, match="Hale & Querry"):
            water_refractive_index(outside)
    with pytest.raises(ValueError, match="pass refractive_index"):
        mie_table(wavelength=3.0, reff=REFF, angles=FEW_ANGLES)


@pytest.mark.parametrize("lam", [1.65, 2.13])
def test_droplet_coalbedo_grows_with_reff_near_its_geometric_optics_limit(tables, lam):
    table = tables[lam]
    m = water_refractive_index(lam)
    n, k = m.real, m.imag
    assert table.attrs["refractive_index_imag"] == k
    reff = table["reff"].values
    coalbedo = 1.0 - table["albedo"].values
    print(f"{lam} micron, m = {n:.5f} + {k:.4g} i: 1 - omega at r_eff {reff} = {coalbedo}")
    assert np.all(np.diff(coalbedo) > 0.0)

    # Weakly absorbing large sphere in geometric optics (alpha = 4 pi k / lambda, alpha r
    # << 1): a ray entering at impact parameter b = r s is refracted to cos(theta_t) =
    # sqrt(1 - s^2 / n^2) and crosses the chord L = 2 r cos(theta_t); entering with
    # transmission 1 - R and reflected back with R at each exit, it crosses it
    # (1 - R) / (1 - R) = 1 time on average, for either polarisation. So C_abs =
    # alpha int L 2 pi b db = (4 pi / 3) alpha r^3 n^2 [1 - (1 - 1/n^2)^(3/2)], i.e.
    # Q_abs = (8/3) x k F, F = (n^3 - (n^2 - 1)^(3/2)) / n (van de Hulst's (8/3) x k as
    # n -> 1). Over the size distribution <r^3> / <r^2> = r_eff, hence
    #     1 - omega = <C_abs> / <C_ext> = (16 pi / 3) F k r_eff / (lambda Q_eff).
    f = (n**3 - (n * n - 1.0) ** 1.5) / n
    limit = 16.0 * math.pi / 3.0 * f * k * reff / (lam * table["q_ext"].values)
    ratio = coalbedo / limit
    # Corrections: (i) saturation, 1 - exp(-alpha L) < alpha L, lowers it by about
    # alpha r_eff (1.4 % at 1.65 micron, 5.4 % at 2.13 micron, r_eff = 20); (ii) finite
    # size: Q_abs nears its limit from above, slowly, with a relative excess of order
    # x^(-2/3) (edge rays and surface waves, as in Q_ext = 2 + ~2 x^(-2/3)) to which the
    # sphere's resonances add when k is small. Both make the ratio fall as r_eff grows.
    # The upper bound is no fit to these corrections (x_eff = 15..76 here): it catches an
    # index or unit error (k in the wrong convention, 4 pi lost, lambda in nm).
    alpha = 4.0 * math.pi * k / lam
    print(f"  (1 - omega) / limit = {ratio}")
    assert np.all(ratio > 1.0 - alpha * reff)
    assert np.all(np.diff(ratio) < 0.0)
    assert np.all(ratio < 1.5)
    # linear in r_eff: doubling it from 5 to 10 micron doubles the co-albedo, up to the
    # slow change of those corrections (measured: 2.006 at 1.65, 2.022 at 2.13 micron)
    assert coalbedo[1] / coalbedo[0] == pytest.approx(2.0, rel=0.05)


def test_rayleigh_scaling_follows_bodhaine_eq30():
    # Eq. (30) by hand: tau = 0.0021520 num / den, num = 1.0455996 - 341.29061 / l^2 -
    # 0.90230850 l^2, den = 1 + 0.0027059889 / l^2 - 85.968563 l^2.
    # l = 0.5: num = -1364.3424175, den = -20.4813168, tau = 0.14335333
    # l = 2.13: num = -78.2735924, den = -389.0301770, tau = 4.3298639e-4
    assert rayleigh_optical_depth(0.5) == pytest.approx(0.14335333, rel=1e-7)
    assert rayleigh_optical_depth(2.13) == pytest.approx(4.3298639e-4, rel=1e-7)
    # l = 0.672: tau = 0.042971965; l = 1.65: tau = 1.17061288e-3
    profile = np.array([0.05, 0.04, 0.03])
    np.testing.assert_allclose(
        air_extinction_at(profile, 1.65, 0.672), profile * 1.17061288e-3 / 0.042971965, rtol=1e-7
    )
    assert air_extinction_at(0.04, 0.5, 2.13) == pytest.approx(
        0.04 * 0.14335333 / 4.3298639e-4, rel=1e-7
    )
    assert air_extinction_at(0.04, 0.672, 0.672) == 0.04
    with pytest.raises(ValueError, match="Bodhaine"):
        air_extinction_at(0.04, 3.0, 0.672)


def tiny_medium(**kwargs):
    x = y = np.array([0.025, 0.075])
    z = np.array([0.1, 0.3, 0.5])
    lwc = np.full((2, 2, 3), 0.5)
    reff = np.full((2, 2, 3), 10.0)
    return microphysical_medium(x, y, z, lwc, reff, air_extinction=[0.05, 0.04, 0.03], **kwargs)


def test_band_optics_scale_the_air(tables):
    medium = tiny_medium()  # air given at 0.672 micron (no attribute: the default)
    visible = to_optical(medium, optics="mie")
    np.testing.assert_array_equal(visible["air_extinction"], medium["air_extinction"])
    assert visible.attrs["air_extinction_wavelength"] == 0.672
    assert visible.attrs["air_extinction_wavelength_units"] == "micron"

    bands = band_optics(medium, [1.65, 2.13], mie_tables=[tables[1.65], tables[2.13]],
                        optics="mie")
    for optical, lam, tau in zip(bands, (1.65, 2.13), (1.17061288e-3, 4.3298639e-4),
                                 strict=True):
        assert optical.attrs["wavelength"] == lam
        assert optical.attrs["air_extinction_wavelength"] == lam
        np.testing.assert_allclose(
            optical["air_extinction"], np.array([0.05, 0.04, 0.03]) * tau / 0.042971965,
            rtol=1e-7,
        )
        assert float(optical["air_albedo"]) == float(medium["air_albedo"])
        albedo = float(tables[lam]["albedo"].sel(reff=10.0))
        np.testing.assert_allclose(optical["cloud_albedo"], albedo, rtol=1e-14)

    # air given at another wavelength, recorded on the medium
    at_2_13 = tiny_medium(air_extinction_wavelength=2.13)
    assert at_2_13.attrs["air_extinction_wavelength"] == 2.13
    (optical,) = band_optics(at_2_13, [1.65], mie_tables=[tables[1.65]], optics="mie")
    np.testing.assert_allclose(
        optical["air_extinction"], np.array([0.05, 0.04, 0.03]) * 1.17061288e-3 / 4.3298639e-4,
        rtol=1e-7,
    )
    with pytest.raises(ValueError, match="microphysical"):
        band_optics(visible, [1.65])
    with pytest.raises(ValueError, match="1 Mie tables for 2 bands"):
        band_optics(medium, [1.65, 2.13], mie_tables=[tables[1.65]])
