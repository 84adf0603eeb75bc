"""What happens at a path vertex, shared by the forward and backward estimators.

- :func:`scatter`: the particle type by its share of the scattering coefficient, then
  the new direction from that type's phase function (seed paper Sec. 3.4.2). Together they
  sample the mixture phase function of Eq. (5) exactly.
- :func:`lambertian_bounce`: a cosine-weighted direction into the upper hemisphere.
- :func:`russian_roulette`: after ``rr_depth`` vertices a path survives each further vertex
  with the fixed probability ``rr_survival`` and its weight is divided by it. The probability
  does not depend on the medium, so re-weighting a stored path under another medium (path
  recycling) stays exact.
"""

from __future__ import annotations

import math

from numba import njit

from cloudct.mc.random import uniform
from cloudct.physics.mixing import choose_particle_type, sample_cell_phase_cosine
from cloudct.physics.phase import scatter_direction

TWO_PI = 2.0 * math.pi


@njit(cache=True, _nrt=False)
def scatter(grid, bank, ix, iy, iz, ux, uy, uz, state):
    """New direction after a scattering event in voxel (ix, iy, iz)."""
    u, state = uniform(state)
    ptype = choose_particle_type(grid, ix, iy, iz, u)
    u, state = uniform(state)
    mu = sample_cell_phase_cosine(grid, bank, ptype, ix, iy, iz, u)
    u, state = uniform(state)
    ux, uy, uz = scatter_direction(ux, uy, uz, mu, TWO_PI * u)
    return ux, uy, uz, state


@njit(cache=True)
def lambertian_bounce(state):
    """A direction into the upper hemisphere with density cos(theta) / pi."""
    u, state = uniform(state)
    cos_t = math.sqrt(u)
    sin_t = math.sqrt(1.0 - u)
    u, state = uniform(state)
    phi = TWO_PI * u
    return sin_t * math.cos(phi), sin_t * math.sin(phi), cos_t, state


@njit(cache=True)
def russian_roulette(depth, rr_depth, rr_survival, state):
    """Weight factor after the roulette at vertex ``depth``: 0 (path ends) or 1 / survival."""
    if depth < rr_depth:
        return 1.0, state
    u, state = uniform(state)
    if u < rr_survival:
        return 1.0 / rr_survival, state
    return 0.0, state
