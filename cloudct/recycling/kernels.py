"""Numba kernels of path recycling: recording paths, their correction factors, and the
re-evaluation of images and gradients from stored paths (seed paper Sec. 5, Eqs. 50-53).

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
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from cloudct.mc.accumulate import add_to
from cloudct.mc.cameras import project
from cloudct.mc.detector_sampling import aimed_weight
from cloudct.mc.forward import (
    CLOUD,
    COUNT,
    ESCAPE,
    GRADIENT,
    GROUND,
    RECORD,
    RENDER,
    SCATTER,
    connection_angular,
    local_estimate,
    trace_photon,
)
from cloudct.mc.traversal import INF, Trail, march
from cloudct.physics.mixing import (
    effective_albedo,
    mixture_phase_function,
    scattering_log_derivative,
    total_extinction,
)


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
        if gradient is None:
            for c in range(S.crossing_start[k], S.crossing_start[k + 1]):
                tau += beta[S.crossing_voxel[c]] * S.crossing_length[c]
        else:
            flat = gradient.reshape((1, 1, gradient.size))
            for c in range(S.crossing_start[k], S.crossing_start[k + 1]):
                v = S.crossing_voxel[c]
                length = S.crossing_length[c]
                tau += beta[v] * length
                add_to(flat, 0, 0, v, weight * length)
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


# ----------------------------------------------------------------------------------------
# Re-evaluation of one stored path
# ----------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def stored_local_estimate(
    grid, bank, cams, beta, S, k, ix, iy, iz, weight, event_albedo, mode, image, residual,
    gradient,
):
    """:func:`~cloudct.mc.forward.local_estimate` of event record k from its stored camera
    connections ("connections" storage): the pixels, angles and 1 / (r^2 Omega) were kept,
    and the optical depth to the camera is the stored frozen part plus beta x length over
    the stored crossings of variable voxels. Same modes, values and deposit order as
    ``local_estimate`` (bitwise equal when every voxel is variable)."""
    ncols = cams.ncols
    nrows = cams.nrows
    weighted_sum = 0.0
    for c in range(S.connection_start[k], S.connection_start[k + 1]):
        pixel = S.connection_pixel[c]
        col = pixel % ncols
        row = (pixel // ncols) % nrows
        view = pixel // (ncols * nrows)
        if mode != RENDER and residual[view, row, col] == 0.0:
            continue
        mu = S.connection_cosine[c]
        angular = connection_angular(grid, bank, ix, iy, iz, mu, event_albedo)
        tau = S.connection_tau[c]
        for q in range(S.connection_crossing_start[c], S.connection_crossing_start[c + 1]):
            tau += beta[S.connection_voxel[q]] * S.connection_length[q]
        value = weight * angular * math.exp(-tau) * S.connection_factor[c]
        if mode == RENDER:
            add_to(image, view, row, col, value)
            continue
        value *= residual[view, row, col]
        weighted_sum += value
        if mode == GRADIENT and value != 0.0:
            flat = gradient.reshape((1, 1, gradient.size))
            for q in range(S.connection_crossing_start[c], S.connection_crossing_start[c + 1]):
                add_to(flat, 0, 0, S.connection_voxel[q], -value * S.connection_length[q])
            if event_albedo < 0.0:
                add_to(
                    gradient, ix, iy, iz,
                    value * scattering_log_derivative(grid, bank, CLOUD, ix, iy, iz, mu),
                )
    return weighted_sum



@njit(cache=True)
def replay_path(
    grid, bank, cams, copies, periodic, ground_albedo, rr_depth, rr_survival, power, beta, S,
    p, use_crossings, mode, image, residual, gradient, trail, scratch,
):
    """Re-evaluate stored path ``p`` under ``grid`` (the current medium M_t).

    Event e (a SCATTER or GROUND record) sends local estimates with the weight
    r_e x (source power x effective albedos of M_t x ground albedos x roulette factors x
    the stored aiming weights f / q), r_e the prefix correction factor. RENDER adds them
    to ``image``. GRADIENT (Eq. 53) deposits each event's own score terms (connection
    segment, vertex at the camera angle) through :func:`local_estimate`, keeps S_e in
    ``scratch``, and after the path
    walks it backwards: segment k gets -W_k l with W_k = sum_{e >= k} S_e and the sampled
    vertex k the term of Eq. (49) weighted by sum_{e > k} S_e, as in
    :func:`cloudct.mc.forward.trace_photon`, in one pass over the camera connections.

    Returns ``(events, S, log r)``: local-estimation events, the residual-weighted sum of
    the path's estimates (GRADIENT) and the log correction factor of the whole path.
    """
    ny = grid.y_edges.size - 1
    nz = grid.z_edges.size - 1
    a = S.path_start[p]
    z = S.path_start[p + 1]
    weight = power
    log_r = 0.0
    depth = 0
    total = 0.0
    inv_survival = 1.0 / rr_survival
    for k in range(a + 1, z):
        kind = S.kind[k]
        log_r += segment_term(grid, beta, S, k, use_crossings, periodic) - S.seg_ref[k]
        if kind == ESCAPE:
            break
        ix, iy, iz = decode_voxel(S.voxel[k], ny, nz)
        if kind == GROUND:
            event_albedo = ground_albedo
        else:
            weight *= effective_albedo(grid, ix, iy, iz)
            event_albedo = -1.0
        s_event = 0.0
        w = weight * math.exp(log_r)
        if w != 0.0 and S.connection_start.size > 1:
            s_event = stored_local_estimate(
                grid, bank, cams, beta, S, k, ix, iy, iz, w, event_albedo, mode, image,
                residual, gradient,
            )
        elif w != 0.0:
            s_event = local_estimate(
                grid, bank, cams, copies, periodic, S.position[0, k], S.position[1, k],
                S.position[2, k], ix, iy, iz, S.direction[0, k], S.direction[1, k],
                S.direction[2, k], w, event_albedo, mode, image, residual, gradient, trail,
            )
        if kind == GROUND:
            weight *= ground_albedo
        scratch[k - a] = s_event
        total += s_event
        depth += 1
        if k + 1 < z:
            if kind == SCATTER:
                log_r += direction_term(grid, bank, S, k) - S.dir_ref[k]
                weight *= S.aim_weight[k]
            if depth >= rr_depth:
                weight *= inv_survival
    if mode == GRADIENT and total != 0.0:
        later = 0.0  # sum of S_e over the events after record k
        for k in range(z - 1, a, -1):
            kind = S.kind[k]
            if kind == ESCAPE:
                continue
            if kind == SCATTER and k + 1 < z and later != 0.0:
                ix, iy, iz = decode_voxel(S.voxel[k], ny, nz)
                add_to(
                    gradient, ix, iy, iz,
                    later * scattering_log_derivative(
                        grid, bank, CLOUD, ix, iy, iz, scattering_cosine(S, k)
                    ),
                )
            later += scratch[k - a]  # now W_k = sum over the events at or after k
            if later != 0.0:
                segment_optical_depth(grid, beta, S, k, use_crossings, periodic, gradient, -later)
    return depth, total, log_r


# ----------------------------------------------------------------------------------------
# Batch kernels (parallel over batches; batch b owns photon-order positions b * P + k)
# ----------------------------------------------------------------------------------------


@njit(cache=True)
def _replay_batch(
    b, grid, bank, cams, copies, periodic, ground_albedo, rr_depth, rr_survival, power, beta, S,
    use_crossings, per_batch, first, last, mode, image, residual, gradient, log_ratio,
    trail_capacity, max_records,
):
    scratch = np.zeros(max_records)
    trail = Trail(
        np.zeros(trail_capacity, np.int64), np.zeros(trail_capacity), np.zeros(1, np.int64),
        np.zeros(1),
    )
    n = 0
    for k in range(first, last):
        j = b * per_batch + k
        depth, _, log_r = replay_path(
            grid, bank, cams, copies, periodic, ground_albedo, rr_depth, rr_survival, power,
            beta, S, S.slot[j], use_crossings, mode, image, residual, gradient, trail, scratch,
        )
        log_ratio[j] = log_r
        n += depth
    return n


@njit(parallel=True, cache=True)
def replay_render_batches(
    grid, bank, cams, copies, periodic, ground_albedo, rr_depth, rr_survival, power, beta, S,
    use_crossings, per_batch, first, last, images, log_ratio, events, max_records,
):
    """Re-evaluate the stored paths at photon-order positions ``b * per_batch + k`` for k in
    ``first .. last - 1`` of every batch b, adding their local estimates to ``images[b]``;
    ``log_ratio[j]`` receives the whole-path log correction factor of the path at
    photon-order position j. Each batch visits its paths in photon order, whatever the
    storage order (sorted or not), so the sums are bitwise independent of the sorting.
    (One kernel per mode, so that the mode is a compile-time constant.)
    """
    no_residual = np.zeros((1, 1, 1))
    for b in prange(images.shape[0]):
        events[b] += _replay_batch(
            b, grid, bank, cams, copies, periodic, ground_albedo, rr_depth, rr_survival, power,
            beta, S, use_crossings, per_batch, first, last, RENDER, images[b], no_residual,
            no_residual, log_ratio, 0, max_records,
        )


@njit(parallel=True, cache=True)
def replay_gradient_batches(
    grid, bank, cams, copies, periodic, ground_albedo, rr_depth, rr_survival, power, beta, S,
    use_crossings, per_batch, first, last, residual, gradients, log_ratio, events,
    trail_capacity, max_records,
):
    """As :func:`replay_render_batches`, depositing the residual-weighted score-function
    gradient of batch b into ``gradients[b]``."""
    no_image = np.zeros((1, 1, 1))
    for b in prange(gradients.shape[0]):
        events[b] += _replay_batch(
            b, grid, bank, cams, copies, periodic, ground_albedo, rr_depth, rr_survival, power,
            beta, S, use_crossings, per_batch, first, last, GRADIENT, no_image, residual,
            gradients[b], log_ratio, trail_capacity, max_records,
        )


@njit(parallel=True, cache=True)
def log_ratio_batches(grid, bank, beta, S, use_crossings, periodic, per_batch, log_ratio):
    """Whole-path log correction factors of all stored paths, by photon-order position."""
    nbatch = S.slot.size // per_batch
    for b in prange(nbatch):
        for k in range(per_batch):
            j = b * per_batch + k
            log_ratio[j] = path_log_ratio(grid, bank, beta, S, S.slot[j], use_crossings, periodic)


@njit(parallel=True, cache=True)
def reference_terms(
    grid, bank, cams, beta, S, use_crossings, periodic, per_batch, seg_out, dir_out, aim_out
):
    """The segment and direction terms of every record under ``grid`` (the reference), and
    the weight f / q of each sampled direction (:func:`aimed_weight`, with ``cams``'s aim
    fraction: the one the paths were traced with)."""
    ny = grid.y_edges.size - 1
    nz = grid.z_edges.size - 1
    nbatch = S.slot.size // per_batch
    for b in prange(nbatch):
        for k in range(per_batch):
            p = S.slot[b * per_batch + k]
            a = S.path_start[p]
            z = S.path_start[p + 1]
            seg_out[a] = 0.0
            dir_out[a] = 0.0
            aim_out[a] = 1.0
            for r in range(a + 1, z):
                seg_out[r] = segment_term(grid, beta, S, r, use_crossings, periodic)
                dir_out[r] = 0.0
                aim_out[r] = 1.0
                if S.kind[r] == SCATTER and r + 1 < z:
                    dir_out[r] = direction_term(grid, bank, S, r)
                    ix, iy, iz = decode_voxel(S.voxel[r], ny, nz)
                    aim_out[r] = aimed_weight(
                        grid, bank, cams, ix, iy, iz, S.position[0, r], S.position[1, r],
                        S.position[2, r], S.direction[0, r], S.direction[1, r],
                        S.direction[2, r], S.direction[0, r + 1], S.direction[1, r + 1],
                        S.direction[2, r + 1],
                    )


# ----------------------------------------------------------------------------------------
# Recording
# ----------------------------------------------------------------------------------------


@njit(parallel=True, cache=True)
def count_records(
    grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival, seed,
    per_batch, first_photon, first, last, counts,
):
    """Records of photons ``first_photon + b * per_batch + k`` (k in first .. last - 1)
    into counts[b * per_batch + k]."""
    nbatch = counts.size // per_batch
    image = np.zeros((1, 1, 1))
    for b in prange(nbatch):
        for k in range(first, last):
            i = b * per_batch + k
            counts[i] = trace_photon(
                grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival,
                seed, first_photon + i, COUNT, image, image, image, 0.0,
            )[0]


@njit(parallel=True, cache=True)
def write_records(
    grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival, seed,
    per_batch, first_photon, first, last, path_start, record,
):
    """Trace the same photons again and write their records (rows from path_start)."""
    nbatch = (path_start.size - 1) // per_batch
    image = np.zeros((1, 1, 1))
    for b in prange(nbatch):
        for k in range(first, last):
            i = b * per_batch + k
            trace_photon(
                grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival,
                seed, first_photon + i, RECORD, image, image, image, 0.0, record, path_start[i],
            )


@njit(cache=True)
def _walk_segment(grid, S, k, periodic, tau_target, limit, trail):
    ny = grid.y_edges.size - 1
    nz = grid.z_edges.size - 1
    j = k - 1
    ix, iy, iz = decode_voxel(S.voxel[j], ny, nz)
    trail.count[0] = 0
    trail.distance[0] = 0.0
    march(
        grid, S.position[0, j], S.position[1, j], S.position[2, j], S.direction[0, k],
        S.direction[1, k], S.direction[2, k], ix, iy, iz, tau_target, periodic, None, 0.0, limit,
        trail,
    )


@njit(parallel=True, cache=True)
def measure_segments(grid, S, length, periodic, per_batch, count_crossings, crossings):
    """Turn the sampled optical depths in ``S.length`` into segment lengths (walking each
    segment again under the reference medium, which stops at the same point), and count
    the crossings of the length-limited walks the stores use (when ``count_crossings``).

    ``length`` is ``S.length`` itself, passed on its own: with numba 0.68, an assignment
    to an element of an array held in a NamedTuple, made directly in a ``prange`` body, is
    lost (writes from called functions are kept)."""
    nbatch = S.slot.size // per_batch
    for b in prange(nbatch):
        trail = Trail(np.zeros(0, np.int64), np.zeros(0), np.zeros(1, np.int64), np.zeros(1))
        for i in range(b * per_batch, (b + 1) * per_batch):
            a = S.path_start[i]
            z = S.path_start[i + 1]
            crossings[a] = 0
            for k in range(a + 1, z):
                _walk_segment(grid, S, k, periodic, length[k], INF, trail)
                length[k] = trail.distance[0]
                if count_crossings:
                    limit = length[k] if S.kind[k] == SCATTER else INF
                    _walk_segment(grid, S, k, periodic, INF, limit, trail)
                    crossings[k] = trail.count[0]
                else:
                    crossings[k] = 0


@njit(parallel=True, cache=True)
def write_crossings(grid, S, periodic, per_batch):
    """Record every segment's crossings (flat voxel, length) into the CSR arrays of S."""
    nbatch = S.slot.size // per_batch
    bad = 0
    for b in prange(nbatch):
        for i in range(b * per_batch, (b + 1) * per_batch):
            for k in range(S.path_start[i] + 1, S.path_start[i + 1]):
                c0 = S.crossing_start[k]
                c1 = S.crossing_start[k + 1]
                trail = Trail(
                    S.crossing_voxel[c0:c1], S.crossing_length[c0:c1], np.zeros(1, np.int64),
                    np.zeros(1),
                )
                limit = S.length[k] if S.kind[k] == SCATTER else INF
                _walk_segment(grid, S, k, periodic, INF, limit, trail)
                if trail.count[0] != c1 - c0:
                    bad += 1
    return bad


@njit(cache=True)
def record_connections(
    grid, cams, copies, periodic, beta, variable, S, k, trail, write, first_connection,
    first_crossing, connection_end, crossing_end,
):
    """The camera connections of event record k (the local estimates of
    :func:`~cloudct.mc.forward.local_estimate`, in its order and with its skips), each
    walked to the top of the medium under the reference: its crossings of ``variable``
    voxels are kept, the optical depth of the others (``beta`` of the reference) summed.

    With ``write``, connection rows are written from ``first_connection`` and their
    crossings from ``first_crossing``, as far as ``connection_end`` and ``crossing_end``
    allow; connection c's number of crossings goes to ``connection_crossing_start[c + 1]``
    (made offsets once all are written). Returns ``(connections, variable crossings)``,
    all of them, written or not.
    """
    ny = grid.y_edges.size - 1
    nz = grid.z_edges.size - 1
    lx = grid.x_edges[-1] - grid.x_edges[0]
    ly = grid.y_edges[-1] - grid.y_edges[0]
    px = S.position[0, k]
    py = S.position[1, k]
    pz = S.position[2, k]
    ix, iy, iz = decode_voxel(S.voxel[k], ny, nz)
    ground = S.kind[k] == GROUND
    n = 0
    q = first_crossing
    for view in range(cams.position.shape[0]):
        for i in range(copies[view, 0], copies[view, 1] + 1):
            for j in range(copies[view, 2], copies[view, 3] + 1):
                row, col, cx, cy, cz, inv_r2_omega = project(
                    cams, view, px + i * lx, py + j * ly, pz
                )
                if row < 0 or (ground and cz <= 0.0):
                    continue
                trail.count[0] = 0
                march(grid, px, py, pz, cx, cy, cz, ix, iy, iz, INF, periodic, None, 0.0, INF,
                      trail)
                if trail.count[0] > trail.voxel.size:  # a longer ray: walk it with more room
                    trail = Trail(
                        np.zeros(2 * trail.count[0], trail.voxel.dtype),
                        np.zeros(2 * trail.count[0]), trail.count, trail.distance,
                    )
                    trail.count[0] = 0
                    march(grid, px, py, pz, cx, cy, cz, ix, iy, iz, INF, periodic, None, 0.0,
                          INF, trail)
                frozen = 0.0
                c = first_connection + n
                q_first = q
                for m in range(trail.count[0]):
                    v = trail.voxel[m]
                    if variable[v]:
                        if write and q < crossing_end:
                            S.connection_voxel[q] = v
                            S.connection_length[q] = trail.length[m]
                        q += 1
                    else:
                        frozen += beta[v] * trail.length[m]
                if write and c < connection_end:
                    S.connection_pixel[c] = (view * cams.nrows + row) * cams.ncols + col
                    if ground:
                        S.connection_cosine[c] = cz
                    else:
                        S.connection_cosine[c] = (
                            S.direction[0, k] * cx + S.direction[1, k] * cy
                            + S.direction[2, k] * cz
                        )
                    S.connection_factor[c] = inv_r2_omega
                    S.connection_tau[c] = frozen
                    S.connection_crossing_start[c + 1] = q - q_first
                n += 1
    return n, q - first_crossing


@njit(parallel=True, cache=True)
def connection_batches(
    grid, cams, copies, periodic, beta, variable, S, per_batch, trail_capacity, write,
    connections, crossings, batch_connection, batch_crossing,
):
    """The camera connections of the event records of batches 0 .. B - 1
    (``batch_connection`` and ``batch_crossing`` hold B + 1 offsets): their number and
    their crossings of variable voxels per record into ``connections`` and ``crossings``
    (all of them, always) and, with ``write``, the connections themselves, those of batch b
    in rows ``batch_connection[b] ..`` and their crossings in rows ``batch_crossing[b] ..``,
    as far as the next batch's offsets (see :func:`record_connections`)."""
    for b in prange(batch_connection.size - 1):
        trail = Trail(
            np.zeros(trail_capacity, S.voxel.dtype), np.zeros(trail_capacity),
            np.zeros(1, np.int64), np.zeros(1),
        )
        c = batch_connection[b]
        q = batch_crossing[b]
        for i in range(b * per_batch, (b + 1) * per_batch):
            for k in range(S.path_start[i] + 1, S.path_start[i + 1]):
                if S.kind[k] != SCATTER and S.kind[k] != GROUND:
                    continue
                n, m = record_connections(
                    grid, cams, copies, periodic, beta, variable, S, k, trail, write, c, q,
                    batch_connection[b + 1], batch_crossing[b + 1],
                )
                connections[k] = n
                crossings[k] = m
                c += n
                q += m
