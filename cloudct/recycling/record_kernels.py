"""Numba kernels of path recycling that make a path store (seed paper Sec. 5):
trace the photons and write their records, measure their segments and voxel crossings,
record the camera connections of their events, and compute the reference medium's
terms of every record (:mod:`cloudct.recycling.path_terms`).

The Python side, which sizes the arrays and chooses the storage mode, is
:mod:`cloudct.recycling.store`.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from cloudct.mc.cameras import project
from cloudct.mc.detector_sampling import aimed_weight
from cloudct.mc.forward import COUNT, GROUND, RECORD, SCATTER, trace_photon
from cloudct.mc.traversal import INF, Trail, march
from cloudct.recycling.path_terms import decode_voxel, direction_term, segment_term

# ----------------------------------------------------------------------------------------
# Reference terms
# ----------------------------------------------------------------------------------------


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
