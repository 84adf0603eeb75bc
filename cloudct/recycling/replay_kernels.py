"""Numba kernels of path recycling that re-evaluate stored paths under a new medium:
the images and the score-function gradient of each stored path with its correction
factors (seed paper Eqs. 50-53), and the batch kernels over a store.

The records' medium-dependent terms are those of :mod:`cloudct.recycling.path_terms`;
:func:`replay_path` and :func:`~cloudct.recycling.path_terms.path_log_ratio` are also
compiled for the GPU (:mod:`cloudct.recycling.cuda_replay`).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from cloudct.mc.accumulate import add_along, add_to
from cloudct.mc.detector_sampling import aimed_weight
from cloudct.mc.forward import (
    CLOUD,
    ESCAPE,
    GRADIENT,
    GROUND,
    INV_PI,
    RENDER,
    SCATTER,
    combined_forward_weight,
    connection_angular,
    local_estimate,
    sun_lobe_at,
    sun_side_after_turn,
    sun_transmittance,
)
from cloudct.mc.traversal import Trail
from cloudct.physics.mixing import effective_albedo, scattering_log_derivative
from cloudct.recycling.path_terms import (
    decode_voxel,
    direction_term,
    path_log_ratio,
    scattering_cosine,
    segment_optical_depth,
    segment_term,
)

# ----------------------------------------------------------------------------------------
# Re-evaluation of one stored path
# ----------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def stored_local_estimate(
    grid, bank, cams, beta, S, k, ix, iy, iz, weight, event_albedo, mode, image, residual,
    gradient, sun_end, sun_turn, sun_aim, sun_lobe,
):
    """:func:`~cloudct.mc.forward.local_estimate` of event record k from its stored camera
    connections ("connections" storage): the pixels, angles and 1 / (r^2 Omega) were kept,
    and the optical depth to the camera is the stored frozen part plus beta x length over
    the stored crossings of variable voxels. Same modes, values, combined estimator's
    weights and deposit order as ``local_estimate`` (bitwise equal when every voxel is
    variable)."""
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
        if cams.mis_ratio > 0.0:
            value *= combined_forward_weight(
                cams, angular, math.exp(-tau) * S.connection_factor[c], sun_end, sun_turn,
                sun_aim, sun_lobe,
            )
        if mode == RENDER:
            add_to(image, view, row, col, value)
            continue
        value *= residual[view, row, col]
        weighted_sum += value
        if mode == GRADIENT and value != 0.0:
            add_along(gradient, S.connection_voxel, S.connection_length,
                      S.connection_crossing_start[c], S.connection_crossing_start[c + 1], -value)
            if event_albedo < 0.0:
                add_to(
                    gradient, ix, iy, iz,
                    value * scattering_log_derivative(grid, bank, CLOUD, ix, iy, iz, mu),
                )
    return weighted_sum


@njit(cache=True)
def replay_path(
    grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival, beta, S,
    p, use_crossings, mode, image, residual, gradient, trail, scratch,
):
    """Re-evaluate stored path ``p`` under ``grid`` (the current medium M_t).

    Event e (a SCATTER or GROUND record) sends local estimates with the weight
    r_e x (source power x effective albedos of M_t x ground albedos x roulette factors x
    the stored aiming weights f / q), r_e the prefix correction factor, and with
    ``cams.mis_ratio`` > 0 each estimate's weight w_f of the combined estimator
    (:mod:`cloudct.mc.combined`), computed from the path under M_t as
    :func:`~cloudct.mc.forward.trace_photon` computes it (the sun end at the first vertex,
    the aim factors f / q of the stored directions under M_t), so that it and a backward
    path traced under M_t split each path's estimate into w_f + w_b = 1. RENDER adds them
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
    weight = sun.power
    log_r = 0.0
    depth = 0
    total = 0.0
    inv_survival = 1.0 / rr_survival
    combined = cams.mis_ratio > 0.0
    sun_end = 0.0  # the combined estimator's path terms, as in trace_photon
    sun_turn = -1.0
    aim_product = 1.0
    back_aims = 1.0
    for k in range(a + 1, z):
        kind = S.kind[k]
        log_r += segment_term(grid, beta, S, k, use_crossings, periodic) - S.seg_ref[k]
        if kind == ESCAPE:
            break
        ix, iy, iz = decode_voxel(S.voxel[k], ny, nz)
        px, py, pz = S.position[0, k], S.position[1, k], S.position[2, k]
        vx, vy, vz = S.direction[0, k], S.direction[1, k], S.direction[2, k]
        sun_lobe = -1.0
        if combined and depth == 0:
            sun_end = sun_transmittance(grid, sun, periodic, px, py, pz, ix, iy, iz)
        if kind == GROUND:
            event_albedo = ground_albedo
            if combined and depth == 0:
                sun_turn = ground_albedo * -sun.direction[2] * INV_PI
        else:
            weight *= effective_albedo(grid, ix, iy, iz)
            event_albedo = -1.0
            if combined:
                sun_lobe = sun_lobe_at(grid, bank, sun, ix, iy, iz, vx, vy, vz, depth)
        sun_aim = sun.aim_fraction if sun_lobe >= 0.0 else 0.0
        s_event = 0.0
        w = weight * math.exp(log_r)
        if w != 0.0 and S.connection_start.size > 1:
            s_event = stored_local_estimate(
                grid, bank, cams, beta, S, k, ix, iy, iz, w, event_albedo, mode, image,
                residual, gradient, sun_end * back_aims / aim_product, sun_turn, sun_aim,
                sun_lobe,
            )
        elif w != 0.0:
            s_event = local_estimate(
                grid, bank, cams, copies, periodic, px, py, pz, ix, iy, iz, vx, vy, vz, w,
                event_albedo, mode, image, residual, gradient, trail,
                sun_end * back_aims / aim_product, sun_turn, sun_aim, sun_lobe,
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
                if combined:
                    ux, uy, uz = S.direction[0, k + 1], S.direction[1, k + 1], \
                        S.direction[2, k + 1]
                    aim_product *= aimed_weight(grid, bank, cams, ix, iy, iz, px, py, pz, vx,
                                                vy, vz, ux, uy, uz)
                    sun_turn, back_aims = sun_side_after_turn(
                        grid, bank, sun, ix, iy, iz, vx, vy, vz, ux, uy, uz, depth - 1,
                        sun_turn, back_aims, sun_lobe,
                    )
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
    b, grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival, beta, S,
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
            grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival,
            beta, S, S.slot[j], use_crossings, mode, image, residual, gradient, trail, scratch,
        )
        log_ratio[j] = log_r
        n += depth
    return n


@njit(parallel=True, cache=True)
def replay_render_batches(
    grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival, beta, S,
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
            b, grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival,
            beta, S, use_crossings, per_batch, first, last, RENDER, images[b], no_residual,
            no_residual, log_ratio, 0, max_records,
        )


@njit(parallel=True, cache=True)
def replay_gradient_batches(
    grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival, beta, S,
    use_crossings, per_batch, first, last, residual, gradients, log_ratio, events,
    trail_capacity, max_records,
):
    """As :func:`replay_render_batches`, depositing the residual-weighted score-function
    gradient of batch b into ``gradients[b]``."""
    no_image = np.zeros((1, 1, 1))
    for b in prange(gradients.shape[0]):
        events[b] += _replay_batch(
            b, grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival,
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
