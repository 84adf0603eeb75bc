"""Particle mixing, seed paper Eqs. (2)-(5), and the particle-type choice.

Hand computations check the formulas; sampled type frequencies are compared with
beta_s^(j) / beta_s through binomial z-scores (|z| < 4) and a chi-square test, and the
two-stage sampling (type, then that type's phase function) with the mixture density of
Eq. (5) by a chi-square test (p > 1e-3). Seeds are fixed.
"""

import math

import numpy as np
import pytest
from numba import njit
from scipy import integrate, stats

from cloudct.physics.mixing import (
    OpticalGrid,
    cell_phase_function,
    choose_particle_type,
    effective_albedo,
    mixture_phase_function,
    sample_cell_phase_cosine,
    scattering_coefficient,
    total_extinction,
)
from cloudct.physics.phase import (
    henyey_greenstein_phase,
    phase_bank,
    phase_function,
    rayleigh_phase,
    sample_phase_cosine,
)

# bank rows: 0 Rayleigh, 1 HG g = 0.85, 2 HG g = -0.5
BANK = phase_bank([("rayleigh",), ("hg", 0.85), ("hg", -0.5)])


def make_grid(extinction, albedo, phase_index, phase_weight=None):
    """A 1 x 1 x 1 grid with one value per particle type (``phase_weight``: each type's
    weight of the bank row after its ``phase_index``; None: 0)."""
    shape = (len(extinction), 1, 1, 1)
    weight = np.zeros(shape) if phase_weight is None else phase_weight
    return OpticalGrid(
        x_edges=np.array([0.0, 1.0]),
        y_edges=np.array([0.0, 1.0]),
        z_edges=np.array([0.0, 1.0]),
        extinction=np.asarray(extinction, dtype=np.float64).reshape(shape),
        albedo=np.asarray(albedo, dtype=np.float64).reshape(shape),
        phase_index=np.asarray(phase_index, dtype=np.int32).reshape(shape),
        phase_weight=np.asarray(weight, dtype=np.float64).reshape(shape),
        cloud_reff_slopes=np.zeros((2, 1, 1, 1)),
        transmittance_family=np.zeros(1, dtype=np.int64),
        transmittance_mode=np.zeros((1, 1, 1)),
    )


# air 0.04 / km with albedo 0.912 and cloud 10 / km with albedo 0.99 (the seed paper's)
AIR_CLOUD = make_grid([0.04, 10.0], [0.912, 0.99], [0, 1])


def test_eqs_2_to_4_by_hand():
    assert total_extinction(AIR_CLOUD, 0, 0, 0) == pytest.approx(10.04, rel=1e-15)
    beta_s = 0.912 * 0.04 + 0.99 * 10.0
    assert scattering_coefficient(AIR_CLOUD, 0, 0, 0) == pytest.approx(beta_s, rel=1e-15)
    assert effective_albedo(AIR_CLOUD, 0, 0, 0) == pytest.approx(beta_s / 10.04, rel=1e-15)


@pytest.mark.parametrize("mu", [-1.0, -0.4, 0.0, 0.3, 0.95, 1.0])
def test_eq_5_by_hand(mu):
    bs_air, bs_cloud = 0.912 * 0.04, 0.99 * 10.0
    p_air = 3.0 / (16.0 * math.pi) * (1.0 + mu * mu)
    p_cloud = (1 - 0.85**2) / (4 * math.pi * (1 + 0.85**2 - 2 * 0.85 * mu) ** 1.5)
    expected = (bs_air * p_air + bs_cloud * p_cloud) / (bs_air + bs_cloud)
    got = mixture_phase_function(AIR_CLOUD, BANK, 0, 0, 0, mu)
    assert got == pytest.approx(expected, rel=1e-13)


@pytest.mark.parametrize("row", [0, 1, 2])
def test_one_type_mixture_is_that_type(row):
    grid = make_grid([3.0], [0.7], [row])
    assert effective_albedo(grid, 0, 0, 0) == pytest.approx(0.7, rel=1e-15)
    for mu in np.linspace(-1.0, 1.0, 9):
        assert mixture_phase_function(grid, BANK, 0, 0, 0, mu) == phase_function(BANK, row, mu)
    assert choose_particle_type(grid, 0, 0, 0, 0.999999) == 0


def test_mixture_normalised():
    value, _ = integrate.quad(
        lambda mu: mixture_phase_function(AIR_CLOUD, BANK, 0, 0, 0, mu), -1.0, 1.0, limit=200
    )
    assert 2.0 * math.pi * value == pytest.approx(1.0, abs=1e-10)


def test_no_scattering_voxel():
    # beta_s = 0: type 0's phase function and type 0; beta = 0: albedo 0
    absorbing = make_grid([0.0, 5.0], [0.9, 0.0], [0, 1])
    assert effective_albedo(absorbing, 0, 0, 0) == 0.0
    assert choose_particle_type(absorbing, 0, 0, 0, 0.5) == 0
    assert mixture_phase_function(absorbing, BANK, 0, 0, 0, 0.2) == rayleigh_phase(0.2)
    empty = make_grid([0.0, 0.0], [0.9, 0.99], [0, 1])
    assert effective_albedo(empty, 0, 0, 0) == 0.0


def test_never_chooses_a_non_scattering_type():
    grid = make_grid([1.0, 2.0, 0.0], [0.5, 0.0, 1.0], [0, 1, 2])
    for u in (0.0, 0.5, 1.0 - 1e-16, np.nextafter(1.0, 0.0)):
        assert choose_particle_type(grid, 0, 0, 0, u) == 0


@njit(cache=True)
def _choose_many(grid, n, rng):
    counts = np.zeros(grid.extinction.shape[0], dtype=np.int64)
    for _ in range(n):
        counts[choose_particle_type(grid, 0, 0, 0, rng.random())] += 1
    return counts


@njit(cache=True)
def _scatter_many(grid, bank, n, rng):
    out = np.empty(n)
    for i in range(n):
        j = choose_particle_type(grid, 0, 0, 0, rng.random())
        out[i] = sample_cell_phase_cosine(grid, bank, j, 0, 0, 0, rng.random())
    return out


def test_choice_frequencies_two_types():
    # very different albedos, so that beta_s^(j)/beta_s and Eq. (33)'s beta^(j)/beta differ
    grid = make_grid([1.0, 2.0], [0.9, 0.2], [0, 1])
    n = 400_000
    counts = _choose_many(grid, n, np.random.default_rng(7))
    p = 0.9 / (0.9 + 0.4)  # beta_s^(0) / beta_s (Eq. 33 would give 1/3)
    z = (counts[0] - n * p) / math.sqrt(n * p * (1 - p))
    print(f"type 0 chosen {counts[0] / n:.5f} vs {p:.5f}: z = {z:+.2f}")
    assert abs(z) < 4.0


def test_choice_frequencies_three_types():
    grid = make_grid([0.04, 10.0, 3.0], [0.912, 0.99, 0.5], [0, 1, 2])
    beta_s = grid.albedo[:, 0, 0, 0] * grid.extinction[:, 0, 0, 0]
    n = 400_000
    counts = _choose_many(grid, n, np.random.default_rng(11))
    p = beta_s / beta_s.sum()
    z = (counts - n * p) / np.sqrt(n * p * (1 - p))
    result = stats.chisquare(counts, n * p)
    print(f"z = {np.array2string(z, precision=2)}, chi2 p = {result.pvalue:.3f}")
    assert np.all(np.abs(z) < 4.0)
    assert result.pvalue > 1e-3


def chi_square_of_directions(mu, density):
    """Chi-square p-value of sampled cosines against a density per sr, in 90 bins of equal
    scattering angle."""
    n = mu.size
    edges = np.cos(np.radians(np.linspace(180.0, 0.0, 91)))
    edges[0], edges[-1] = -1.0, 1.0
    prob = np.array(
        [
            2.0 * math.pi * integrate.quad(density, a, b)[0]
            for a, b in zip(edges[:-1], edges[1:], strict=True)
        ]
    )
    counts, _ = np.histogram(mu, bins=edges)
    assert np.all(n * prob >= 5.0)
    result = stats.chisquare(counts, n * prob / prob.sum())
    print(f"chi2 = {result.statistic:.1f} on {counts.size - 1} dof, p = {result.pvalue:.3f}")
    return result.pvalue


def test_two_stage_sampling_follows_eq_5():
    # air + cloud (HG 0.85) + a back-scattering type: direction histogram vs Eq. (5)
    grid = make_grid([0.5, 2.0, 1.0], [0.912, 0.99, 0.6], [0, 1, 2])
    mu = _scatter_many(grid, BANK, 300_000, np.random.default_rng(2021))
    assert chi_square_of_directions(
        mu, lambda m: mixture_phase_function(grid, BANK, 0, 0, 0, m)) > 1e-3
    # and the HG rows of the bank are the HG formula
    assert phase_function(BANK, 2, 0.1) == henyey_greenstein_phase(0.1, -0.5)


# a cloud whose phase function mixes bank rows 1 and 2 (HG 0.85 and -0.5) with weight 0.3
T = 0.3
AIR_MIXED_CLOUD = make_grid([0.5, 2.0], [0.912, 0.99], [0, 1], [0.0, T])


def mixed_cloud_by_hand(mu):
    """Eq. (5) for AIR_MIXED_CLOUD, written out with the closed forms."""
    bs_air, bs_cloud = 0.912 * 0.5, 0.99 * 2.0
    cloud = (1.0 - T) * henyey_greenstein_phase(mu, 0.85) + T * henyey_greenstein_phase(mu, -0.5)
    return (bs_air * rayleigh_phase(mu) + bs_cloud * cloud) / (bs_air + bs_cloud)


@pytest.mark.parametrize("mu", [-1.0, -0.4, 0.0, 0.3, 0.95, 1.0])
def test_a_cells_two_row_phase_function_by_hand(mu):
    expected = (1.0 - T) * henyey_greenstein_phase(mu, 0.85) + T * henyey_greenstein_phase(mu, -0.5)
    assert cell_phase_function(AIR_MIXED_CLOUD, BANK, 1, 0, 0, 0, mu) == pytest.approx(
        expected, rel=1e-14)
    assert mixture_phase_function(AIR_MIXED_CLOUD, BANK, 0, 0, 0, mu) == pytest.approx(
        mixed_cloud_by_hand(mu), rel=1e-13)


def test_two_row_sampling_follows_the_mixture():
    """Type, then row (k + 1 with probability t), then the cosine: the histogram of the
    directions follows the by-hand mixture; with t = 0 the draw is row k's, bit for bit."""
    mu = _scatter_many(AIR_MIXED_CLOUD, BANK, 300_000, np.random.default_rng(53))
    assert chi_square_of_directions(mu, mixed_cloud_by_hand) > 1e-3
    single = make_grid([0.5, 2.0], [0.912, 0.99], [0, 1])
    for u in (0.0, 0.1, 0.5, 0.93, np.nextafter(1.0, 0.0)):
        assert sample_cell_phase_cosine(single, BANK, 1, 0, 0, 0, u) == \
            sample_phase_cosine(BANK, 1, u)
