"""The Mie phase function linear in r_eff between table rows (issue 53): each cloudy cell's
phase function is (1 - t) row k + t row k + 1 (``cloud_phase_index`` k, ``cloud_phase_weight``
t), and the kernels evaluate and sample that mixture.

References that share no code with the mixture in the kernels: the rows' weights against
t = (r_eff - r_k) / (r_{k+1} - r_k) by hand; and a medium whose single phase-table row is the
mixture, made beforehand from the two normalised rows (``tabulated_nodes``), which the
kernels trace as one row. Its kernel arrays, phase truncation included, equal the mixed
Mie medium's to rounding; and for two very different rows (forward and backward HG,
tabulated; two Mie rows a few microns apart differ too little for images of a few 10^5
photons to tell) its images agree with the mixed medium's within their standard errors
(independent seeds), while the images of row k alone do not (the test can fail).
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from cloudct.mc.cameras import Camera
from cloudct.mc.render import render_batches
from cloudct.mc.scene import Scene
from cloudct.mc.sun import Sun
from cloudct.medium import MediumError, microphysical_medium, optical_medium, validate_medium
from cloudct.optics import kernel_arrays_and_scale, to_optical, with_phase_truncation
from cloudct.physics.mie import compute_mie_table
from cloudct.physics.mixing import cell_phase_function
from cloudct.physics.phase import tabulated_nodes

TABLE_REFF = [4.0, 10.0, 16.0]
ANGLES = [0.0, 0.5, 1.0, 2.0, 3.0, 5.0, 10.0, 20.0, 30.0, 60.0, 90.0, 120.0, 140.0, 160.0,
          180.0]
AXIS = 0.05 + 0.1 * np.arange(4)
BATCHES = 20


@pytest.fixture(scope="module")
def table():
    return compute_mie_table(0.672, reff=TABLE_REFF, angles=ANGLES)


def mie_medium(table, reff):
    """A 4 x 4 x 4 cloud (LWC 0.5 g/m^3) of one r_eff, Mie optics."""
    lwc = np.full((4, 4, 4), 0.5)
    lwc[0, 0, :] = 0.0  # clear cells keep row 0 and weight 0
    medium = microphysical_medium(AXIS, AXIS, AXIS + 0.5, lwc, np.full((4, 4, 4), reff))
    return to_optical(medium, table, optics="mie")


def single_row_medium(mixed):
    """``mixed`` with its two-row phase functions replaced by one row holding the mixture of
    the two normalised rows (every cloudy cell has the same k and t)."""
    cloudy = mixed["cloud_extinction"].values > 0
    k = int(mixed["cloud_phase_index"].values[cloudy][0])
    t = float(mixed["cloud_phase_weight"].values[cloudy][0])
    angles = mixed["scattering_angle"].values
    rows = mixed["cloud_phase"].values

    def normalised(row):  # per sr, at the angles (tabulated_nodes orders by cosine)
        return tabulated_nodes(angles, row)[1][::-1]

    row = (1.0 - t) * normalised(rows[k]) + t * normalised(rows[k + 1])
    return optical_medium(
        AXIS, AXIS, AXIS + 0.5, mixed["cloud_extinction"].values,
        cloud_albedo=mixed["cloud_albedo"].values, cloud_phase=(row, angles),
        air_extinction=mixed["air_extinction"], air_albedo=float(mixed["air_albedo"]),
        wavelength=mixed.attrs.get("wavelength"),
    )


@pytest.mark.parametrize(("reff", "k", "t"), [(7.0, 0, 0.5), (10.0, 1, 0.0), (14.5, 1, 0.75),
                                              (16.0, 1, 1.0), (4.0, 0, 0.0)])
def test_each_cell_takes_the_two_rows_about_its_reff(table, reff, k, t):
    """Rows k, k + 1 of the table about r_eff with t = (r_eff - r_k) / (r_{k+1} - r_k) (the
    interval above a node, the last one at the last node); the medium keeps the consecutive
    rows of its cloudy cells' intervals."""
    medium = mie_medium(table, reff)
    cloudy = medium["lwc"].values > 0
    first = float(medium["cloud_phase_reff"].values[0])
    index = medium["cloud_phase_index"].values
    weight = medium["cloud_phase_weight"].values
    assert np.all(weight[cloudy] == pytest.approx(t, abs=1e-15))
    assert np.all(index[~cloudy] == 0) and np.all(weight[~cloudy] == 0.0)
    assert TABLE_REFF.index(first) + index[cloudy][0] == k
    assert medium["cloud_phase"].shape[0] == 2  # rows k and k + 1, whatever t
    np.testing.assert_array_equal(medium["cloud_phase"].values[index[cloudy][0]],
                                  table["phase"].values[k])


def test_a_weight_must_name_a_row_after_its_own(table):
    medium = mie_medium(table, 7.0)
    bad = medium.copy(deep=True)
    bad["cloud_phase_weight"].values[1, 1, 1] = 1.5
    with pytest.raises(MediumError, match="cloud_phase_weight must be in"):
        validate_medium(bad)
    bad = medium.copy(deep=True)
    bad["cloud_phase_index"].values[1, 1, 1] = 1  # the last of its two rows, with t = 0.5
    with pytest.raises(MediumError, match="last row"):
        validate_medium(bad)
    with pytest.raises(MediumError, match="without cloud_phase"):
        optical_medium(AXIS, AXIS, AXIS, np.ones((4, 4, 4)), cloud_phase_weight=np.zeros((4,) * 3))


@pytest.mark.parametrize("truncation", [0.0, 4.0])
def test_the_kernels_see_the_mixture_as_one_mixed_row(table, truncation):
    """Extinction, albedo and the cell's phase function at every node angle: the two-row
    medium's kernel arrays equal those of the medium whose one row is the mixture; with a
    phase truncation too, where the mixture's weight becomes t (1 - f_{k+1}) / (1 - f)
    (the flat cut of the mixture is the mixture of the rows' cuts where both peaks fall
    monotonically, as these do)."""
    mixed = mie_medium(table, 14.5)
    single = single_row_medium(mixed)
    if truncation:
        mixed, single = (with_phase_truncation(m, truncation) for m in (mixed, single))
    (grid_m, bank_m, scale_m), (grid_s, bank_s, scale_s) = (
        kernel_arrays_and_scale(m) for m in (mixed, single))
    cloudy = mixed["cloud_extinction"].values > 0  # clear cells: any phase function
    np.testing.assert_allclose(grid_m.extinction, grid_s.extinction, rtol=1e-13, atol=0)
    np.testing.assert_allclose(grid_m.albedo[:, cloudy], grid_s.albedo[:, cloudy], rtol=1e-13)
    if truncation:
        np.testing.assert_allclose(scale_m[cloudy], scale_s[cloudy], rtol=1e-13)
        assert np.all(scale_m[cloudy] < 1.0)
    for mu in np.cos(np.radians([0.0, 1.0, 2.5, 4.0, 7.0, 45.0, 100.0, 179.0])):
        for cell in ((1, 2, 3), (2, 2, 0)):
            assert cell_phase_function(grid_m, bank_m, 1, *cell, mu) == pytest.approx(
                cell_phase_function(grid_s, bank_s, 1, *cell, mu), rel=1e-12)


def mean_and_error(batches):
    """Mean over the first axis (independent batches) and its standard error."""
    return batches.mean(axis=0), batches.std(axis=0, ddof=1) / np.sqrt(batches.shape[0])


def z_scores(medium_a, medium_b, scene, seeds):
    """Per-pixel z-scores of the difference of two media's images, and that of the sum of
    all pixels (taken per batch: the pixels of one batch share its photons)."""
    (a, b) = (render_batches(m, scene, photons=400_000, seed=s, batches=BATCHES,
                             progress=False)[0]
              for m, s in zip((medium_a, medium_b), seeds, strict=True))
    (ma, sa), (mb, sb) = mean_and_error(a), mean_and_error(b)
    lit = (sa > 0) & (sb > 0)
    per_pixel = (ma - mb)[lit] / np.hypot(sa, sb)[lit]
    (ta, sta), (tb, stb) = (mean_and_error(x.sum(axis=(1, 2, 3))) for x in (a, b))
    return per_pixel, (ta - tb) / np.hypot(sta, stb)


def test_the_mixed_medium_renders_as_the_one_mixed_row():
    """Images of a medium whose cells mix two tabulated rows (forward HG g = 0.85 and
    backward HG g = -0.5, t = 0.4) and of the one-row medium of their mixture, independent
    seeds: every pixel and their sum agree within their standard errors; row k alone (t =
    0) differs from the mixture, so the comparison sees a wrong mixture."""
    angles = np.concatenate([np.linspace(0.0, 10.0, 21), np.linspace(12.0, 180.0, 85)])
    mu = np.cos(np.radians(angles))
    rows = np.array([henyey_greenstein(mu, g) for g in (0.85, -0.5)])
    extinction = np.full((4, 4, 4), 8.0)
    mixed = optical_medium(AXIS, AXIS, AXIS + 0.5, extinction, cloud_albedo=0.99,
                           cloud_phase=(rows, angles),
                           cloud_phase_index=np.zeros((4, 4, 4), dtype=np.int32),
                           cloud_phase_weight=np.full((4, 4, 4), 0.4))
    cams = [Camera((0.2, 0.2, 3.0), (0.2, 0.2, 0.7), (0, 1, 0), fov=25.0, nrows=6, ncols=6),
            Camera((1.6, 0.2, 1.2), (0.2, 0.2, 0.7), (0, 0, 1), fov=40.0, nrows=6, ncols=6)]
    scene = Scene(cams, Sun(30.0, 200.0), "open", 0.0)
    single = single_row_medium(mixed)
    per_pixel, total = z_scores(mixed, single, scene, (1, 2))
    # each z is Student's t with (about) 2 (BATCHES - 1) degrees of freedom: a max over the
    # pixels at a family-wise level of 1e-4, and the sum's at 4 sigma
    limit = stats.t.isf(0.5e-4 / per_pixel.size, 2 * (BATCHES - 1))
    print(f"mixture vs mixed row: max |z| {np.abs(per_pixel).max():.2f} (limit {limit:.2f}), "
          f"sum z {total:+.2f}")
    assert np.abs(per_pixel).max() < limit and abs(total) < 4.0
    row_k = mixed.copy(deep=True)
    row_k["cloud_phase_weight"].values[:] = 0.0
    per_pixel, wrong = z_scores(row_k, single, scene, (3, 2))
    print(f"row k alone vs mixed row: max |z| {np.abs(per_pixel).max():.2f}, sum z {wrong:+.2f}")
    assert np.abs(per_pixel).max() > 2.0 * limit


def henyey_greenstein(mu, g):
    return (1.0 - g * g) / (4.0 * np.pi * (1.0 + g * g - 2.0 * g * mu) ** 1.5)
