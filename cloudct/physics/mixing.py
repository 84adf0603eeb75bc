"""Mixing of particle types in a voxel, seed paper Eqs. (2)-(5), as numba functions.

Each of the ``ntype`` particle types j has, per voxel, an extinction beta^(j) and a
single-scattering albedo w^(j); its scattering coefficient is beta_s^(j) = w^(j) beta^(j)
(Eq. 3). Type 0 is air (Rayleigh), type 1 cloud; nothing here assumes ntype = 2.

Where a voxel scatters nothing (beta_s = 0), :func:`mixture_phase_function` returns the
phase function of type 0 and :func:`choose_particle_type` returns 0. Any density would do
there, since it is always multiplied by beta_s = 0 (or by an effective albedo of 0), and
this choice keeps the mixture a normalised density that the type choice samples exactly.

**A type's phase function in a cell** may itself be a convex mixture of two consecutive
rows of the phase bank, (1 - t) f_k + t f_{k+1} with k = ``phase_index`` and t =
``phase_weight`` (:func:`cell_phase_function`): the Mie phase function linear in r_eff
between two table rows (:mod:`cloudct.physics.microphysics`). A mixture of normalised
densities is a normalised density, and :func:`sample_cell_phase_cosine` draws it exactly:
row k + 1 with probability t, then the cosine from that row with the same uniform number
rescaled to [0, 1). With t = 0 that is row k and the number unchanged, bit for bit.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from cloudct.physics.phase import PhaseBank, phase_function, sample_phase_cosine


class OpticalGrid(NamedTuple):
    """Piecewise-constant optical properties of every particle type on the voxel grid."""

    x_edges: np.ndarray  # float64[nx + 1], km
    y_edges: np.ndarray  # float64[ny + 1], km
    z_edges: np.ndarray  # float64[nz + 1], km
    extinction: np.ndarray  # float64[ntype, nx, ny, nz], 1/km; type 0 air, 1 cloud
    albedo: np.ndarray  # float64[ntype, nx, ny, nz]
    phase_index: np.ndarray  # int32[ntype, nx, ny, nz], row k of the PhaseBank
    phase_weight: np.ndarray  # float64[ntype, nx, ny, nz], weight t of row k + 1 (module doc)
    # the cloud's d omega / d r_eff and d t / d r_eff [1/micron], float64[2, nx, ny, nz], for
    # gradients in r_eff (reff_log_derivative); zeros of shape [2, 1, 1, 1] otherwise
    cloud_reff_slopes: np.ndarray
    # the transmittance family (cloudct.physics.transmittance: 0 exponential) and its mode
    # per voxel (float64[nx, ny, nz]; float64[1, 1, 1] for the exponential family)
    transmittance_family: np.ndarray  # int64[1]
    transmittance_mode: np.ndarray


@njit(cache=True, _nrt=False)
def cell_phase_function(
    grid: OpticalGrid, bank: PhaseBank, j: int, ix: int, iy: int, iz: int, mu: float
) -> float:
    """Phase function of type j in voxel (ix, iy, iz) at scattering cosine ``mu`` [1/sr]:
    (1 - t) f_k(mu) + t f_{k+1}(mu), k its bank row and t its weight (module docstring)."""
    k = grid.phase_index[j, ix, iy, iz]
    t = grid.phase_weight[j, ix, iy, iz]
    if t == 0.0:
        return phase_function(bank, k, mu)
    return (1.0 - t) * phase_function(bank, k, mu) + t * phase_function(bank, k + 1, mu)


@njit(cache=True, _nrt=False)
def sample_cell_phase_cosine(
    grid: OpticalGrid, bank: PhaseBank, j: int, ix: int, iy: int, iz: int, u: float
) -> float:
    """Scattering cosine drawn from :func:`cell_phase_function` of type j in the voxel, for
    u uniform in [0, 1): row k + 1 when u < t (then u / t), else row k ((u - t) / (1 - t))."""
    k = grid.phase_index[j, ix, iy, iz]
    t = grid.phase_weight[j, ix, iy, iz]
    if u < t:
        return sample_phase_cosine(bank, k + 1, min(u / t, 1.0))
    return sample_phase_cosine(bank, k, min((u - t) / (1.0 - t), 1.0) if t > 0.0 else u)


@njit(cache=True, inline="always")
def total_extinction(grid: OpticalGrid, ix: int, iy: int, iz: int) -> float:
    """beta = sum_j beta^(j), Eq. (2) [1/km]."""
    beta = 0.0
    for j in range(grid.extinction.shape[0]):
        beta += grid.extinction[j, ix, iy, iz]
    return beta


@njit(cache=True, inline="always")
def scattering_coefficient(grid: OpticalGrid, ix: int, iy: int, iz: int) -> float:
    """beta_s = sum_j w^(j) beta^(j), Eqs. (2)-(3) [1/km]."""
    beta_s = 0.0
    for j in range(grid.extinction.shape[0]):
        beta_s += grid.albedo[j, ix, iy, iz] * grid.extinction[j, ix, iy, iz]
    return beta_s


@njit(cache=True, inline="always")
def effective_albedo(grid: OpticalGrid, ix: int, iy: int, iz: int) -> float:
    """w = sum_j w^(j) beta^(j) / beta = beta_s / beta, Eq. (4); 0 where beta = 0."""
    beta = total_extinction(grid, ix, iy, iz)
    if beta <= 0.0:
        return 0.0
    return scattering_coefficient(grid, ix, iy, iz) / beta


@njit(cache=True, inline="always")
def mixture_phase_function(
    grid: OpticalGrid, bank: PhaseBank, ix: int, iy: int, iz: int, mu: float
) -> float:
    """f_p = sum_j beta_s^(j) f_p^(j)(mu) / beta_s, Eq. (5) [1/sr]; type 0's where beta_s = 0."""
    num = 0.0
    beta_s = 0.0
    for j in range(grid.extinction.shape[0]):
        bs = grid.albedo[j, ix, iy, iz] * grid.extinction[j, ix, iy, iz]
        if bs > 0.0:
            num += bs * cell_phase_function(grid, bank, j, ix, iy, iz, mu)
            beta_s += bs
    if beta_s <= 0.0:
        return cell_phase_function(grid, bank, 0, ix, iy, iz, mu)
    return num / beta_s


@njit(cache=True, _nrt=False)
def choose_particle_type(grid: OpticalGrid, ix: int, iy: int, iz: int, u: float) -> int:
    """Particle type that scatters, with probability beta_s^(j) / beta_s, for u in [0, 1).

    With the path weight multiplied by the effective albedo (Eq. 4), a direction drawn from
    the chosen type's phase function follows the mixture of Eq. (5) exactly. (The seed
    paper's Eq. (33), beta^(j) / beta, is the same choice only when all albedos are equal.)
    Returns 0 where beta_s = 0; never returns a type with beta_s^(j) = 0 otherwise.
    """
    target = u * scattering_coefficient(grid, ix, iy, iz)
    cumulative = 0.0
    last = 0
    for j in range(grid.extinction.shape[0]):
        bs = grid.albedo[j, ix, iy, iz] * grid.extinction[j, ix, iy, iz]
        if bs > 0.0:
            cumulative += bs
            last = j
            if target < cumulative:
                return j
    return last


@njit(cache=True, inline="always")
def scattering_log_derivative(
    grid: OpticalGrid, bank: PhaseBank, ptype: int, ix: int, iy: int, iz: int, mu: float
) -> float:
    """d log(beta_s f_p(mu)) / d beta^(ptype) at fixed albedos, seed paper Eq. (49):
    w^(ptype) f^(ptype)(mu) / sum_j beta_s^(j) f^(j)(mu) [km]; 0 where nothing scatters."""
    num = 0.0
    den = 0.0
    for j in range(grid.extinction.shape[0]):
        w = grid.albedo[j, ix, iy, iz]
        wf = w * cell_phase_function(grid, bank, j, ix, iy, iz, mu)
        if j == ptype:
            num = wf
        den += wf * grid.extinction[j, ix, iy, iz]
    if den <= 0.0:
        return 0.0
    return num / den


@njit(cache=True)
def reff_log_derivative(
    grid: OpticalGrid, bank: PhaseBank, ix: int, iy: int, iz: int, mu: float
) -> float:
    """d log(beta_s f_p(mu)) / d r_eff of the cloud (type 1) at fixed extinctions [1/micron],
    the vertex term of the path score function in r_eff (docs/optics.md, "Derivatives in
    LWC and r_eff"):

        beta_c [omega_c' f_c(mu) + omega_c t' (f_{k+1}(mu) - f_k(mu))] / sum_j beta_s^(j) f_j(mu),

    with f_c = (1 - t) f_k + t f_{k+1} the cloud's two-row phase function and omega_c', t'
    the slopes of ``grid.cloud_reff_slopes``; 0 where nothing scatters."""
    den = 0.0
    for j in range(grid.extinction.shape[0]):
        den += (grid.albedo[j, ix, iy, iz] * grid.extinction[j, ix, iy, iz]
                * cell_phase_function(grid, bank, j, ix, iy, iz, mu))
    if den <= 0.0:
        return 0.0
    num = grid.cloud_reff_slopes[0, ix, iy, iz] * cell_phase_function(grid, bank, 1, ix, iy, iz, mu)
    slope = grid.cloud_reff_slopes[1, ix, iy, iz]
    if slope != 0.0:
        k = grid.phase_index[1, ix, iy, iz]
        num += grid.albedo[1, ix, iy, iz] * slope * (
            phase_function(bank, k + 1, mu) - phase_function(bank, k, mu))
    return grid.extinction[1, ix, iy, iz] * num / den
