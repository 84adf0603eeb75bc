"""Numba kernels of path recycling: the arrays of a path store as the kernels see them,
and the medium-dependent terms of each stored record (seed paper Sec. 5, Eq. 51).

A stored path is a run of records (:class:`cloudct.mc.forward.PathRecord` kinds): ENTRY,
its vertices (SCATTER, GROUND) and, for a path that leaves the medium, ESCAPE. Segment k
runs from record k - 1 to record k along ``direction[:, k]``; it is ``length[k]`` long
when it ends at a SCATTER vertex and otherwise ends on a face of the box. Everything that
depends on the medium is computed by the functions below, for the reference medium when
the store is made and for the current medium at every re-evaluation, with the same
floating-point operations in the same order: the correction factor is exactly 1 when the
two media are the same, and both storage modes give identical results.

Per record, under a medium M (``segment_term``, ``direction_term``):

    segment term   log beta(x_k) - tau(segment k)        (SCATTER: free-flight pdf beta T)
                   - tau(segment k)                      (GROUND, ESCAPE: probability T)
    direction term log f_p,mixture(x_k, d_k . d_{k+1})   (SCATTER followed by a record)

The source, the Lambertian bounce and the Russian roulette do not depend on the medium,
so log r = sum over records of (term under M_t - term under M_ref). Directions aimed at
the cameras (:mod:`cloudct.mc.detector_sampling`) were drawn from q, not f: each SCATTER
record keeps its reference weight f / q, a factor of the path's weight like an albedo.
The local estimate at event e uses the prefix ratio r_e: the segment terms up to e and
the direction terms of the vertices before e.

The kernels that replay stored paths are in :mod:`cloudct.recycling.replay_kernels`, those
that record them in :mod:`cloudct.recycling.record_kernels`.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from cloudct.mc.accumulate import add_along
from cloudct.mc.forward import SCATTER
from cloudct.mc.traversal import INF, march
from cloudct.physics.mixing import mixture_phase_function, total_extinction


class StoreArrays(NamedTuple):
    """The arrays of a path store as the kernels see them (see :class:`PathStore`)."""

    path_start: np.ndarray  # int64[npaths + 1]: CSR offsets of each stored path's records
    slot: np.ndarray  # int64[npaths]: storage slot of the path of photon-order position j
    position: np.ndarray  # float64[3, nrec], km (wrapped into the box if periodic)
    direction: np.ndarray  # float64[3, nrec]: direction of the segment arriving at the record
    length: np.ndarray  # float64[nrec]: length of that segment, km
    kind: np.ndarray  # int8[nrec]: ENTRY, SCATTER, GROUND, ESCAPE
    voxel: np.ndarray  # int32/int64[nrec]: flat voxel index (ix * ny + iy) * nz + iz
    seg_ref: np.ndarray  # float64[nrec]: segment term under the reference medium
    dir_ref: np.ndarray  # float64[nrec]: direction term under the reference medium
    aim_weight: np.ndarray  # float64[nrec]: f / q of the direction sampled at a SCATTER
    # record under the reference (detector directional importance sampling; else 1)
    crossing_start: np.ndarray  # int64[nrec + 1] ("crossings" storage; else int64[1])
    crossing_voxel: np.ndarray  # int32/int64[ncross]: flat voxel of each crossing
    crossing_length: np.ndarray  # float64[ncross]: length inside it, km
    # "connections" storage (else connection_start = int64[1], the rest empty): per event
    # record its camera connections, per connection its crossings of variable voxels
    connection_start: np.ndarray  # int64[nrec + 1]: CSR offsets of each record's connections
    connection_pixel: np.ndarray  # int32[nconn]: (view * nrows + row) * ncols + col
    connection_cosine: np.ndarray  # float64[nconn]: mu of :func:`connection_angular`
    connection_factor: np.ndarray  # float64[nconn]: 1 / (r^2 Omega_pixel), 1/km^2
    connection_tau: np.ndarray  # float64[nconn]: optical depth of its frozen voxels
    connection_crossing_start: np.ndarray  # int64[nconn + 1]
    connection_voxel: np.ndarray  # int32/int64[ncc]: flat voxel of each variable crossing
    connection_length: np.ndarray  # float64[ncc]: length inside it, km


@njit(cache=True, inline="always")
def decode_voxel(v, ny, nz):
    """(ix, iy, iz) of the flat voxel index (ix * ny + iy) * nz + iz."""
    iz = v % nz
    rest = v // nz
    return rest // ny, rest % ny, iz


@njit(parallel=True, cache=True)
def flat_total_extinction(grid):
    """Total extinction of every voxel by flat index, computed as the traversal does."""
    nx, ny, nz = grid.extinction.shape[1:]
    beta = np.empty(nx * ny * nz)
    for ix in prange(nx):
        for iy in range(ny):
            for iz in range(nz):
                beta[(ix * ny + iy) * nz + iz] = total_extinction(grid, ix, iy, iz)
    return beta


# ----------------------------------------------------------------------------------------
# Medium-dependent terms of one record
# ----------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def segment_optical_depth(grid, beta, S, k, use_crossings, periodic, gradient, weight):
    """Optical depth of segment k (record k - 1 to record k) under ``grid``.

    With ``use_crossings`` it sums beta[voxel] x length over the stored crossings; otherwise
    it walks the segment again (:func:`march` limited to ``length[k]``). Both add the same
    products in the same order. With an array ``gradient``, ``weight`` x length is added to
    every crossed voxel (the segment's part of the score function, for weight = -W_k).
    """
    if use_crossings:
        tau = 0.0
        for c in range(S.crossing_start[k], S.crossing_start[k + 1]):
            tau += beta[S.crossing_voxel[c]] * S.crossing_length[c]
        if gradient is not None:
            add_along(gradient, S.crossing_voxel, S.crossing_length, S.crossing_start[k],
                      S.crossing_start[k + 1], weight)
        return tau
    ny = grid.y_edges.size - 1
    nz = grid.z_edges.size - 1
    j = k - 1
    ix, iy, iz = decode_voxel(S.voxel[j], ny, nz)
    limit = S.length[k] if S.kind[k] == SCATTER else INF
    return march(
        grid, S.position[0, j], S.position[1, j], S.position[2, j], S.direction[0, k],
        S.direction[1, k], S.direction[2, k], ix, iy, iz, INF, periodic, gradient, weight, limit,
    )[7]


@njit(cache=True, inline="always")
def segment_term(grid, beta, S, k, use_crossings, periodic):
    """log of the medium-dependent sampling probability of segment k: log beta(x_k) - tau
    for a segment ending in a scattering vertex, -tau for one ending on a face."""
    tau = segment_optical_depth(grid, beta, S, k, use_crossings, periodic, None, 0.0)
    if S.kind[k] == SCATTER:
        b = beta[S.voxel[k]]
        if b > 0.0:
            return math.log(b) - tau
        return -INF
    return -tau


@njit(cache=True, inline="always")
def scattering_cosine(S, k):
    """Cosine of the scattering angle at record k (between segments k and k + 1)."""
    return (
        S.direction[0, k] * S.direction[0, k + 1]
        + S.direction[1, k] * S.direction[1, k + 1]
        + S.direction[2, k] * S.direction[2, k + 1]
    )


@njit(cache=True, inline="always")
def direction_term(grid, bank, S, k):
    """log f_p,mixture at SCATTER record k for the direction the path took from it (Eq. 5:
    the type choice by beta_s^(j) and that type's phase function sample the mixture)."""
    ny = grid.y_edges.size - 1
    nz = grid.z_edges.size - 1
    ix, iy, iz = decode_voxel(S.voxel[k], ny, nz)
    f = mixture_phase_function(grid, bank, ix, iy, iz, scattering_cosine(S, k))
    if f > 0.0:
        return math.log(f)
    return -INF


@njit(cache=True)
def path_log_ratio(grid, bank, beta, S, p, use_crossings, periodic):
    """log r of the whole stored path in slot p: mu(path | grid) / mu(path | reference)."""
    a = S.path_start[p]
    z = S.path_start[p + 1]
    log_r = 0.0
    for k in range(a + 1, z):
        log_r += segment_term(grid, beta, S, k, use_crossings, periodic) - S.seg_ref[k]
        if S.kind[k] == SCATTER and k + 1 < z:
            log_r += direction_term(grid, bank, S, k) - S.dir_ref[k]
    return log_r
