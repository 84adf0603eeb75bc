"""The loss's prior terms (cloudct.retrieval.priors): every registered term's gradient
against central finite differences of its value, and each term's value against what it
must be on fields whose answer is known without the code."""

from __future__ import annotations

import numpy as np
import pytest

from cloudct.medium import optical_medium
from cloudct.retrieval.priors import (
    PRIORS,
    Prior,
    PriorGrid,
    adiabatic_fit,
    parse_prior,
    prior_text,
)

#: Option sets each term is checked with (its defaults, then others).
OPTIONS = {"l1": [{}], "monotonic": [{}], "adiabatic": [{}],
           "smoothness": [{}, {"huber": 30.0}, {"horizontal": 0.5, "vertical": 2.0,
                                                 "huber": 5.0}]}


def grid_of(nx: int, ny: int, z_edges: np.ndarray) -> PriorGrid:
    """A grid of 20 m columns over the given z edges (km)."""
    x = 0.02 * (np.arange(nx) + 0.5)
    y = 0.02 * (np.arange(ny) + 0.5)
    z = 0.5 * (z_edges[:-1] + z_edges[1:])
    bounds = np.stack([z_edges[:-1], z_edges[1:]], axis=1)
    medium = optical_medium(x, y, z, np.zeros((nx, ny, z.size)), z_bounds=bounds)
    return PriorGrid.of(medium)


#: A small grid with uneven levels (stretched, as the SHDOM stratocumulus file's).
STRETCHED = np.array([0.0, 0.03, 0.05, 0.08, 0.1, 0.14, 0.17, 0.2])


def random_cloud(shape: tuple[int, int, int], seed: int) -> np.ndarray:
    """Extinction [1/km] from 1 to 60, no two voxels equal (a tie, such as two empty
    neighbours, is a kink of the terms with differences: there the gradient is the
    subgradient 0, which finite differences straddle)."""
    return np.random.default_rng(seed).uniform(1.0, 60.0, shape)


def test_every_term_is_a_registered_record():
    assert set(OPTIONS) == set(PRIORS)
    for name, term in PRIORS.items():
        assert term.name == name and term.reference and term.penalises and term.weight_units


@pytest.mark.parametrize("name", sorted(PRIORS))
def test_each_terms_gradient_is_that_of_its_value(name):
    """Central differences of Phi along random directions, and along single voxels, against
    the gradient's inner product; h small enough that no kink (a sign of a difference, a
    column's maximum, a fitted base or top) lies within +-h of the random field."""
    grid = grid_of(4, 3, STRETCHED)
    rng = np.random.default_rng(7)
    for options in OPTIONS[name]:
        prior = Prior(name, 1.0, options=options)
        for seed in range(3):
            beta = random_cloud((4, 3, 7), seed)
            value, gradient = prior.value_and_gradient(beta, grid)
            assert np.isfinite(value) and gradient.shape == beta.shape
            h = 1e-5
            directions = [rng.standard_normal(beta.shape) for _ in range(3)]
            for k in rng.choice(beta.size, 6, replace=False):
                d = np.zeros(beta.size)
                d[k] = 1.0
                directions.append(d.reshape(beta.shape))
            for d in directions:
                up = prior.value_and_gradient(beta + h * d, grid)[0]
                down = prior.value_and_gradient(beta - h * d, grid)[0]
                fd = (up - down) / (2 * h)
                np.testing.assert_allclose(fd, np.sum(gradient * d), rtol=1e-6,
                                           atol=1e-9 * max(abs(value), 1.0),
                                           err_msg=f"{name} {options}")


def test_l1_is_the_extinction_cross_section():
    grid = grid_of(2, 2, np.array([0.0, 0.04, 0.1]))
    beta = np.zeros((2, 2, 2))
    beta[1, 0, 1] = 10.0  # 10 /km in a 20 x 20 x 60 m cell
    value, gradient = Prior("l1", 1.0).value_and_gradient(beta, grid)
    assert value == pytest.approx(10.0 * 0.02 * 0.02 * 0.06)
    assert gradient[0, 0, 0] == pytest.approx(0.02 * 0.02 * 0.04)


def test_total_variation_of_a_step_is_the_jump_times_the_face():
    """A block of 10 /km: its TV is 10 /km x its surface (each face counted where the
    block meets empty cells); a linear ramp has the TV of a step of the same rise, and with
    Huber a gentle ramp costs its gradient squared / (2 delta)."""
    grid = grid_of(6, 6, np.linspace(0.0, 0.12, 7))  # 20 m cubes
    beta = np.zeros((6, 6, 6))
    beta[2:4, 2:4, 2:4] = 10.0
    surface = 6 * 4 * 0.02**2  # a 2 x 2 x 2 block: 24 faces
    assert Prior("smoothness", 1.0).value_and_gradient(beta, grid)[0] == pytest.approx(
        10.0 * surface)
    only_vertical = Prior("smoothness", 1.0, options={"horizontal": 0.0})
    assert only_vertical.value_and_gradient(beta, grid)[0] == pytest.approx(
        10.0 * 8 * 0.02**2)
    ramp = np.broadcast_to(np.arange(6.0)[None, None, :] * 2.0, (6, 6, 6)).copy()
    area = 36 * 0.02**2
    assert Prior("smoothness", 1.0).value_and_gradient(ramp, grid)[0] == pytest.approx(
        10.0 * area)
    slope = 2.0 / 0.02  # 100 /km^2
    huber = Prior("smoothness", 1.0, options={"huber": 400.0})
    assert huber.value_and_gradient(ramp, grid)[0] == pytest.approx(
        area * 0.1 * slope**2 / (2 * 400.0))


def test_monotonic_costs_what_is_lost_going_up_below_the_maximum():
    grid = grid_of(2, 2, np.linspace(0.0, 0.4, 11))  # four equal columns
    area = 4 * 0.02 * 0.02
    growing = np.tile(np.array([0, 0, 2, 5, 9, 14, 20, 18, 6, 0], float), (2, 2, 1))
    prior = Prior("monotonic", 1.0)
    assert prior.value_and_gradient(growing, grid)[0] == 0.0  # falls only above the peak
    ghost = growing.copy()
    ghost[:, :, 0] = 3.0  # a layer under the base
    hollow = growing.copy()
    hollow[:, :, 4] = 4.0  # a hollow in the core: 5 -> 4 loses 1
    assert prior.value_and_gradient(ghost, grid)[0] == pytest.approx(3.0 * area)
    assert prior.value_and_gradient(hollow, grid)[0] == pytest.approx(1.0 * area)
    value, gradient = prior.value_and_gradient(ghost, grid)
    cell = area / 4
    assert gradient[0, 0, 0] == pytest.approx(cell) and gradient[0, 0, 1] == pytest.approx(-cell)


def test_an_adiabatic_column_is_its_own_fit():
    """A column a (z - z_base)^(2/3) from a cell edge up to a top and zero outside costs
    nothing; a ghost layer under its base costs its extinction squared x its volume, and
    the fit still finds the cloud."""
    edges = np.linspace(0.0, 0.5, 26)  # 20 m levels
    grid = grid_of(2, 2, edges)  # four equal columns
    z = 0.5 * (edges[:-1] + edges[1:])
    base, top = 6, 19  # cloud from the edge at 0.12 km to the level centred at 0.39 km
    column = np.zeros(25)
    column[base:top + 1] = 80.0 * (z[base:top + 1] - edges[base]) ** (2 / 3)
    beta = np.tile(column, (2, 2, 1))
    prior = Prior("adiabatic", 1.0)
    value, gradient = prior.value_and_gradient(beta, grid)
    assert value == pytest.approx(0.0, abs=1e-20)
    np.testing.assert_allclose(adiabatic_fit(beta, grid), beta, rtol=1e-12, atol=1e-12)
    ghost = beta.copy()
    ghost[:, :, 2] = 4.0
    volume = 4 * 0.02 * 0.02 * 0.02
    assert prior.value_and_gradient(ghost, grid)[0] == pytest.approx(16.0 * volume)
    np.testing.assert_allclose(adiabatic_fit(ghost, grid), beta, rtol=1e-12, atol=1e-12)


def test_a_prior_setting_is_checked_and_written_as_the_command_line_reads_it():
    prior = parse_prior("smoothness=0.1,vertical=0.5,schedule=fixed")
    assert prior == Prior("smoothness", 0.1, "fixed", {"vertical": 0.5})
    assert parse_prior(prior_text(prior)) == prior
    for text, message in (("tv=1", "prior term must be one of"),
                          ("l1=-1", "weight must be >= 0"),
                          ("l1=0.1,schedule=weekly", "schedule must be one of"),
                          ("monotonic=1,huber=2", "unknown option 'huber'"),
                          ("smoothness=1,huber=-2", "huber must be >= 0"),
                          ("l1", "write TERM=WEIGHT"),
                          ("l1=lots", "'lots' is not a number")):
        with pytest.raises(ValueError, match=message):
            parse_prior(text)


def test_the_grid_follows_the_mediums_cell_bounds():
    grid = grid_of(3, 2, STRETCHED)
    assert grid.volume.shape == (3, 2, 7)
    np.testing.assert_allclose(grid.widths[2], np.diff(STRETCHED))
    np.testing.assert_allclose(grid.volume[0, 0], 0.02 * 0.02 * np.diff(STRETCHED))
