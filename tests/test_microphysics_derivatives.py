"""Derivatives of the cloud optics in LWC and r_eff (cloudct.physics.microphysics).

The extinction and albedo derivatives are checked against central finite differences of
``cloudct.optics.to_optical``, which computes the optics with ``np.interp`` and shares no
code with the derivative formulas; d log p / d r_eff against finite differences of the
interpolated phase function; the chain rule against a finite difference of a quadratic loss
of the extinction, computed through ``to_optical``; the slopes of the optics a phase
truncation leaves (``delta_scaled_reff_slopes``) against finite differences of the kernel
arrays (``kernel_arrays_and_scale``), whose delta-scaling shares no code with them.

Error budget of a central difference (f(r + h) - f(r - h)) / (2h): truncation
h^2 f''' / 6 + O(h^4), and rounding at most 2 k eps max|f| / (2h) when each value of f
carries a relative rounding error of at most k eps (k = 4 here: np.interp's few
operations, or a sum of terms). Beta and omega are linear in r_eff inside a table
interval and beta is linear in LWC, so wherever [r - h, r + h] lies inside one interval
(the test points keep a margin of MARGIN = 0.2 micron > h from the nodes) their
truncation error is exactly zero and the tolerance is the rounding bound alone. The
finite differences divide by the difference of the arguments as floats, so that the
rounding of r +- h itself adds nothing.
"""

import numpy as np
import pytest

from cloudct.mc.microphysics_gradient import cloud_reff_slopes
from cloudct.medium import microphysical_medium
from cloudct.optics import kernel_arrays_and_scale, peak_shares, to_optical
from cloudct.physics.microphysics import (
    albedo_reff_derivative,
    cloud_extinction,
    extinction_lwc_derivative,
    extinction_part_of_gradient,
    extinction_reff_derivative,
    mie_phase_function,
    phase_log_reff_derivative,
    reff_interval,
    single_scattering_albedo,
)
from cloudct.physics.mie import compute_mie_table

EPS = np.finfo(np.float64).eps
K = 4  # relative rounding of one evaluation, in eps (module documentation)
TABLE_REFF = [4.0, 8.0, 12.0, 16.0]
ANGLES = [0.0, 0.5, 1.0, 2.0, 5.0, 10.0, 30.0, 60.0, 90.0, 120.0, 140.0, 160.0, 180.0]
MARGIN = 0.2  # micron, from the table's nodes
H = 0.01  # micron, the r_eff step (< MARGIN)
# eight r_eff inside the intervals, each at least MARGIN from a node
REFF = np.array([4.7, 6.3, 7.5, 9.1, 11.2, 12.8, 13.9, 15.4])
LWC = np.array([0.05, 0.3, 0.8, 1.2, 0.1, 0.6, 2.0, 0.45])


@pytest.fixture(scope="module", params=[0.672, 2.13])
def table(request):
    """A small Mie table (4 r_eff rows, 13 angles) at the band's wavelength."""
    return compute_mie_table(request.param, reff=TABLE_REFF, angles=ANGLES)


def grid(values):
    return np.asarray(values, dtype=np.float64).reshape(2, 2, 2)


def optics(lwc, reff, table):
    """(cloud extinction, cloud albedo) of ``to_optical`` on a 2x2x2 medium, flattened."""
    medium = microphysical_medium([0.01, 0.03], [0.01, 0.03], [0.01, 0.03], grid(lwc),
                                  grid(reff))
    optical = to_optical(medium, table, optics="mie")
    return (optical["cloud_extinction"].transpose("x", "y", "z").values.ravel(),
            optical["cloud_albedo"].transpose("x", "y", "z").values.ravel())


def central(f, x, h):
    """Central difference of the vector function ``f`` at ``x`` (elementwise), and the
    rounding bound of the module documentation."""
    plus, minus = x + h, x - h
    f_plus, f_minus = f(plus), f(minus)
    step = plus - minus
    bound = 2 * K * EPS * np.maximum(np.abs(f_plus), np.abs(f_minus)) / step
    return (f_plus - f_minus) / step, bound


def trapezoid(y, x):
    """The trapezoidal rule (numpy >= 1.24 has no np.trapezoid); the sign of x's order."""
    return -np.sum(0.5 * np.diff(x) * (y[1:] + y[:-1]))


def test_the_test_points_keep_their_margin_from_the_nodes():
    assert H < MARGIN
    assert np.min(np.abs(REFF[:, None] - np.array(TABLE_REFF)[None, :])) >= MARGIN - 1e-12


def test_extinction_derivative_in_lwc_against_to_optical(table):
    h = 1e-3 * LWC
    fd, bound = central(lambda w: optics(w, REFF, table)[0], LWC, h)
    exact = extinction_lwc_derivative(LWC, REFF, table)
    print("d beta / d LWC", exact, "errors", fd - exact, "bounds", bound)
    assert np.all(np.abs(fd - exact) <= bound)
    np.testing.assert_allclose(cloud_extinction(LWC, REFF, table), optics(LWC, REFF, table)[0],
                               rtol=2 * K * EPS)


def test_extinction_derivative_in_reff_against_to_optical(table):
    fd, bound = central(lambda r: optics(LWC, r, table)[0], REFF, H)
    exact = extinction_reff_derivative(LWC, REFF, table)
    print("d beta / d r_eff", exact, "errors", fd - exact, "bounds", bound)
    assert np.all(exact < 0.0)  # beta / LWC ~ 1 / r_eff
    assert np.all(np.abs(fd - exact) <= bound)


def test_albedo_derivative_against_to_optical(table):
    fd, bound = central(lambda r: optics(LWC, r, table)[1], REFF, H)
    exact = albedo_reff_derivative(REFF, table)
    print("d omega / d r_eff", exact, "errors", fd - exact, "bounds", bound)
    assert np.all(exact < 0.0)  # bigger droplets absorb more
    assert np.all(np.abs(fd - exact) <= bound)
    np.testing.assert_allclose(single_scattering_albedo(REFF, table), optics(LWC, REFF, table)[1],
                               rtol=2 * K * EPS)


def test_at_a_node_the_derivatives_are_those_of_the_interval_above(table):
    # one-sided differences through to_optical are exact for functions linear in the step
    # (truncation h f'' / 2 = 0); the last node takes the interval below
    reff = np.array([4.0, 8.0, 12.0, 16.0, 8.0, 12.0, 4.0, 16.0])
    side = np.where(reff == 16.0, -1.0, 1.0)
    f0 = optics(LWC, reff, table)
    f1 = optics(LWC, reff + side * H, table)
    step = (reff + side * H) - reff
    for k, exact in enumerate((extinction_reff_derivative(LWC, reff, table),
                               albedo_reff_derivative(reff, table))):
        bound = 2 * K * EPS * np.maximum(np.abs(f0[k]), np.abs(f1[k])) / np.abs(step)
        assert np.all(np.abs((f1[k] - f0[k]) / step - exact) <= bound)
    i, t = reff_interval(reff, table)
    assert list(i) == [0, 1, 2, 2, 1, 2, 0, 2] and list(t) == [0, 0, 0, 1, 0, 0, 0, 1]


def test_clear_cells_have_no_extinction_and_the_extinction_per_lwc_of_the_table(table):
    # r_eff in clear cells is ignored (clipped to the table), as to_optical does: 2 and 30
    # micron lie outside the table's 4..16
    lwc = np.array([0.0, 0.0, 0.0, 0.3, 0.0, 0.6, 2.0, 0.45])
    reff = np.array([2.0, 30.0, 9.1, 7.5, 0.0, 12.8, 13.9, 15.4])
    assert np.all(cloud_extinction(lwc, reff, table)[lwc == 0] == 0.0)
    slope = extinction_lwc_derivative(lwc, reff, table)
    per_lwc = table["ext_per_lwc"].values
    np.testing.assert_allclose(slope[[0, 1, 4]], per_lwc[[0, -1, 0]], rtol=2 * K * EPS)
    assert np.all(extinction_reff_derivative(lwc, reff, table)[lwc == 0] == 0.0)
    # a forward difference from LWC = 0 is exact for beta linear in LWC (to_optical takes
    # it only where r_eff lies in the table: the clear cell at 9.1 micron)
    h = 1e-3
    first_drop = np.where(lwc == 0, h, 0.0) * (reff == 9.1)
    fd = (optics(lwc + first_drop, reff, table)[0] - optics(lwc, reff, table)[0])[2] / h
    assert abs(fd - slope[2]) <= 2 * K * EPS * abs(optics(lwc + first_drop, reff, table)[0][2]) / h


def test_reff_outside_the_table_is_refused(table):
    for bad in (3.9, 16.1, np.nan):
        reff = REFF.copy()
        reff[3] = bad
        for call, args in ((cloud_extinction, (LWC, reff)),
                           (extinction_reff_derivative, (LWC, reff)),
                           (extinction_part_of_gradient, (LWC, LWC, reff)),
                           (albedo_reff_derivative, (reff,)),
                           (phase_log_reff_derivative, (reff, 30.0))):
            with pytest.raises(ValueError, match="outside the Mie table's range 4..16"):
                call(*args, table)
    with pytest.raises(ValueError, match="LWC"):
        cloud_extinction(-LWC, REFF, table)


def test_the_interpolated_phase_function_is_a_density_with_a_zero_mean_score(table):
    # p and dp / d r_eff are linear in mu between the table's angles, so the trapezoidal
    # rule on those nodes integrates them exactly (to rounding)
    mu = np.cos(np.radians(ANGLES))
    for r in REFF:
        p = mie_phase_function(r, ANGLES, table)
        score = phase_log_reff_derivative(r, ANGLES, table)
        norm = 2 * np.pi * trapezoid(p, mu)
        mean_score = 2 * np.pi * trapezoid(p * score, mu)
        assert norm == pytest.approx(1.0, abs=1e-13)
        assert abs(mean_score) < 1e-13 * np.max(np.abs(p * score))
    # at a node, p is that table row, renormalised by a constant
    row = table["phase"].values[1]
    ratio = mie_phase_function(8.0, ANGLES, table) / row
    np.testing.assert_allclose(ratio, ratio[0], rtol=1e-13)


def test_phase_score_against_finite_differences_of_the_phase_function(table):
    # log p(r) = log(a + b r) inside an interval: the central difference is
    # atanh(s h) / h = s + s^3 h^2 / 3 + s^5 h^4 / 5 + ..., s = d log p / d r_eff, so its
    # truncation error has the sign of s and is at most (s^3 h^2 / 3) / (1 - (s h)^2);
    # rounding: log p carries an absolute error of at most K eps (1 + |log p|)
    reff, angle = np.meshgrid(REFF, [0.0, 0.7, 3.0, 20.0, 75.0, 137.0, 180.0])
    s = phase_log_reff_derivative(reff, angle, table)
    plus, minus = reff + H, reff - H
    log_plus = np.log(mie_phase_function(plus, angle, table))
    log_minus = np.log(mie_phase_function(minus, angle, table))
    step = plus - minus
    fd = (log_plus - log_minus) / step
    truncation = np.abs(s) ** 3 * (step / 2) ** 2 / 3 / (1 - (s * step / 2) ** 2)
    rounding = 2 * K * EPS * (1 + np.maximum(np.abs(log_plus), np.abs(log_minus))) / step
    print("d log p / d r_eff", s[:, 0], "max error", np.max(np.abs(fd - s)))
    assert np.all(np.abs(fd - s) <= truncation + rounding)
    assert np.all((fd - s) * np.sign(s) >= -rounding)
    assert np.all(s[0] > 0.0)  # the diffraction peak grows with the droplets


def test_chain_rule_against_a_quadratic_loss_of_the_extinction(table):
    # L = 1/2 sum_v w_v (beta_v - b_v)^2 with beta from to_optical: quadratic in LWC_v and,
    # inside an interval, in r_eff_v, so its central differences have no truncation error
    # (f''' = 0); rounding: each beta carries K eps |beta|, so L carries at most
    # K eps (L + sum_v w_v |beta_v - b_v| |beta_v|)
    rng = np.random.default_rng(7)
    weight = rng.uniform(0.5, 2.0, REFF.size)
    target = optics(LWC, REFF, table)[0] * rng.uniform(0.5, 1.5, REFF.size)

    def loss(lwc, reff):
        beta = optics(lwc, reff, table)[0]
        value = 0.5 * np.sum(weight * (beta - target) ** 2)
        error = K * EPS * (value + np.sum(weight * np.abs(beta - target) * np.abs(beta)))
        return value, error

    beta = optics(LWC, REFF, table)[0]
    d_lwc, d_reff = extinction_part_of_gradient(weight * (beta - target), LWC, REFF, table)
    for v in range(REFF.size):
        for x, exact, h in ((LWC, d_lwc[v], 1e-3 * LWC[v]), (REFF, d_reff[v], H)):
            plus, minus = x.copy(), x.copy()
            plus[v] += h
            minus[v] -= h
            args = ((plus, REFF), (minus, REFF)) if x is LWC else ((LWC, plus), (LWC, minus))
            (l_plus, e_plus), (l_minus, e_minus) = loss(*args[0]), loss(*args[1])
            step = plus[v] - minus[v]
            assert abs((l_plus - l_minus) / step - exact) <= (e_plus + e_minus) / step


def cut_optics(reff, table):
    """The kernels' delta-scaled cloud albedo, next-row weight and log(beta' / beta) of a
    2x2x2 medium whose phase functions are cut at 5 degrees, flattened."""
    medium = microphysical_medium([0.01, 0.03], [0.01, 0.03], [0.01, 0.03], grid(LWC),
                                  grid(reff)).assign_attrs(phase_truncation=5.0)
    kernel_grid, _, scale = kernel_arrays_and_scale(to_optical(medium, table, optics="mie"))
    return np.stack([kernel_grid.albedo[1].ravel(), kernel_grid.phase_weight[1].ravel(),
                     np.log(scale).ravel()])


def test_slopes_of_the_cut_optics_against_kernel_arrays(table):
    # the delta-scaled omega', t' and beta' / beta are rational in r_eff inside an interval:
    # the central difference's truncation error c h^2 is bounded by |fd(2h) - fd(h)| =
    # 3 c h^2 + O(h^4), to which the rounding bound is added
    medium = microphysical_medium([0.01, 0.03], [0.01, 0.03], [0.01, 0.03], grid(LWC),
                                  grid(REFF)).assign_attrs(phase_truncation=5.0)
    optical = to_optical(medium, table, optics="mie")
    slopes, d_log_scale = cloud_reff_slopes(grid(LWC), grid(REFF), table, peak_shares(optical))
    exact = np.stack([slopes[0].ravel(), slopes[1].ravel(), d_log_scale.ravel()])
    fd, rounding = central(lambda r: cut_optics(r, table), REFF, H)
    fd_2h = central(lambda r: cut_optics(r, table), REFF, 2 * H)[0]
    error = np.abs(fd - exact)
    print("omega', t', log s slopes", exact, "errors", error)
    assert np.all(error <= np.abs(fd_2h - fd) + rounding)
    # the cut matters: the full optics' slopes differ by far more than that
    full = cloud_reff_slopes(grid(LWC), grid(REFF), table)[0]
    assert np.all(np.abs(full.reshape(2, -1) - exact[:2]) > 10 * (error[:2] + rounding[:2]))
    assert np.all(np.abs(exact[2]) > 10 * (error[2] + rounding[2]))
