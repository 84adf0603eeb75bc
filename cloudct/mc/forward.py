"""Forward (sun -> medium) path tracing with local estimation to every camera.

Seed paper Sec. 3.4: a photon enters on a sunlit face (:mod:`cloudct.mc.sun`) with the
weight that makes the estimate absolute, flies a distance sampled by exact inversion of the
optical depth (Eq. 32), scatters with the mixture phase function (Eq. 33 and
:mod:`cloudct.mc.events`) and carries the effective albedo as a weight. At every scattering
event, and at every reflection by the Lambertian ground, it sends a local estimate to every
camera (Eqs. 36-39):

    weight * albedo * f_p(x, cos theta_{b,d}) * T(x, x_d) / (r^2 Omega_pixel)

for scattering, and weight * A cos(theta_d) / pi * T / (r^2 Omega_pixel) for the ground.
One path serves all views. With periodic boundaries the camera sees every periodic image of
the event, so each image copy that falls in its field of view is estimated.
"""

from __future__ import annotations

import math

from numba import njit, prange

from cloudct.mc.accumulate import add_to
from cloudct.mc.cameras import project
from cloudct.mc.events import lambertian_bounce, russian_roulette, scatter
from cloudct.mc.random import DOMAIN_FORWARD, stream_start, uniform
from cloudct.mc.sun import sample_entry_point
from cloudct.mc.traversal import BOTTOM, INF, LEFT, locate_point, march, optical_depth_to_exit
from cloudct.physics.mixing import (
    effective_albedo,
    mixture_phase_function,
    scattering_log_derivative,
)

INV_PI = 1.0 / math.pi


#: What a forward pass does with its local estimates.
RENDER = 0  # add them to the images
RESIDUAL = 1  # sum them, weighted by the pixels' residuals (first gradient pass)
GRADIENT = 2  # deposit the residual-weighted score-function gradient (second pass)

#: The particle type whose extinction the gradients are taken with respect to.
CLOUD = 1


@njit(cache=True)
def local_estimate(
    grid, bank, cams, copies, periodic, px, py, pz, ix, iy, iz, ux, uy, uz, weight, ground_albedo,
    mode, image, residual, gradient,
):
    """Local estimates of one event at (px, py, pz) to every camera (Eqs. 36-39).

    A scattering event (``ground_albedo < 0``) uses the mixture phase function at the angle
    between the incoming direction (ux, uy, uz) and the direction to the camera; a ground
    event uses the Lambertian factor A cos(theta) / pi.

    ``mode`` RENDER adds each estimate to ``image``. RESIDUAL and GRADIENT return the sum S
    of the estimates weighted by their pixels' ``residual``; GRADIENT also deposits into
    ``gradient`` the terms of the score function (Eq. 49) that belong to this event alone:
    the connection segment to the camera (-l per voxel) and, for scattering, the vertex
    term at the angle towards the camera.
    """
    lx = grid.x_edges[-1] - grid.x_edges[0]
    ly = grid.y_edges[-1] - grid.y_edges[0]
    weighted_sum = 0.0
    for view in range(cams.position.shape[0]):
        for i in range(copies[view, 0], copies[view, 1] + 1):
            for j in range(copies[view, 2], copies[view, 3] + 1):
                row, col, cx, cy, cz, inv_r2_omega = project(
                    cams, view, px + i * lx, py + j * ly, pz
                )
                if row < 0:
                    continue
                mu = ux * cx + uy * cy + uz * cz
                if ground_albedo < 0.0:
                    angular = mixture_phase_function(grid, bank, ix, iy, iz, mu)
                elif cz > 0.0:
                    angular = ground_albedo * cz * INV_PI
                else:
                    continue
                if mode != RENDER and residual[view, row, col] == 0.0:
                    continue
                tau = optical_depth_to_exit(grid, px, py, pz, cx, cy, cz, ix, iy, iz, periodic)
                value = weight * angular * math.exp(-tau) * inv_r2_omega
                if mode == RENDER:
                    add_to(image, view, row, col, value)
                    continue
                value *= residual[view, row, col]
                weighted_sum += value
                if mode == GRADIENT and value != 0.0:
                    march(grid, px, py, pz, cx, cy, cz, ix, iy, iz, INF, periodic, gradient, -value)
                    if ground_albedo < 0.0:
                        add_to(
                            gradient, ix, iy, iz,
                            value * scattering_log_derivative(grid, bank, CLOUD, ix, iy, iz, mu),
                        )
    return weighted_sum


@njit(cache=True)
def trace_photon(
    grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival, seed, index,
    mode, image, residual, gradient, path_sum,
):
    """Trace forward photon ``index`` (``ground_albedo < 0``: no ground).

    RENDER adds the path's local estimates to ``image``. RESIDUAL returns the path's sum S
    of residual-weighted estimates, sum_e S_e over its events e. GRADIENT, given that sum
    as ``path_sum``, re-traces the same path (same random stream) and deposits the
    residual-weighted score-function gradient sum_e S_e score_e (Eqs. 46-49). The score of
    event e holds the segments and sampled vertices of the path up to e, so segment k is
    weighted by W_k = sum_{e >= k} S_e, obtained as ``path_sum`` minus the events already
    passed: the cost stays linear in the path length.

    Returns ``(vertices, S)``.
    """
    state = stream_start(seed, DOMAIN_FORWARD, index)
    u_face, state = uniform(state)
    u1, state = uniform(state)
    u2, state = uniform(state)
    px, py, pz = sample_entry_point(grid, sun, u_face, u1, u2)
    ux, uy, uz = sun.direction[0], sun.direction[1], sun.direction[2]
    ix, iy, iz = locate_point(grid, px, py, pz, ux, uy, uz)
    weight = sun.power
    depth = 0
    total = 0.0
    remaining = path_sum  # W_k: the residual-weighted estimates of events not yet passed
    while True:
        u, state = uniform(state)
        if mode == GRADIENT and remaining != 0.0:
            status, px, py, pz, ix, iy, iz, _ = march(
                grid, px, py, pz, ux, uy, uz, ix, iy, iz, -math.log(u), periodic, gradient,
                -remaining,
            )
        else:
            status, px, py, pz, ix, iy, iz, _ = march(
                grid, px, py, pz, ux, uy, uz, ix, iy, iz, -math.log(u), periodic
            )
        if status == LEFT:
            return depth, total
        if status == BOTTOM:
            if ground_albedo <= 0.0:
                return depth, total
            s_event = local_estimate(
                grid, bank, cams, copies, periodic, px, py, pz, ix, iy, iz, ux, uy, uz, weight,
                ground_albedo, mode, image, residual, gradient,
            )
            weight *= ground_albedo
            ux, uy, uz, state = lambertian_bounce(state)
        else:
            albedo = effective_albedo(grid, ix, iy, iz)
            if albedo == 0.0:
                return depth, total
            weight *= albedo
            s_event = local_estimate(
                grid, bank, cams, copies, periodic, px, py, pz, ix, iy, iz, ux, uy, uz, weight,
                -1.0, mode, image, residual, gradient,
            )
            vx, vy, vz = ux, uy, uz
            ux, uy, uz, state = scatter(grid, bank, ix, iy, iz, ux, uy, uz, state)
            if mode == GRADIENT:
                # the sampled vertex term belongs to the scores of all later events
                mu = vx * ux + vy * uy + vz * uz
                later = remaining - s_event
                if later != 0.0:
                    add_to(
                        gradient, ix, iy, iz,
                        later * scattering_log_derivative(grid, bank, CLOUD, ix, iy, iz, mu),
                    )
        total += s_event
        remaining -= s_event
        depth += 1
        factor, state = russian_roulette(depth, rr_depth, rr_survival, state)
        if factor == 0.0:
            return depth, total
        weight *= factor


@njit(parallel=True, cache=True)
def forward_batches(
    grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival, seed,
    photons_per_batch, first, last, mode, images, residual, gradients, events,
):
    """Trace photons ``first .. last - 1`` of every batch, in parallel over batches.

    Batch ``b`` owns photon indices ``b * photons_per_batch + k``, so which photons a batch
    holds, and their random streams, do not depend on the thread count. RENDER accumulates
    batch b's local estimates (not yet divided by its photon count) in ``images[b]``;
    GRADIENT accumulates its residual-weighted score-function gradient in ``gradients[b]``
    (each photon first traced in RESIDUAL mode for its sum, then again in GRADIENT mode).
    ``events[b]`` counts the path vertices.
    """
    for b in prange(images.shape[0]):
        n = 0
        for k in range(first, last):
            index = b * photons_per_batch + k
            if mode == RENDER:
                n += trace_photon(
                    grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth,
                    rr_survival, seed, index, RENDER, images[b], residual, gradients[b], 0.0,
                )[0]
            else:
                vertices, path_sum = trace_photon(
                    grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth,
                    rr_survival, seed, index, RESIDUAL, images[b], residual, gradients[b], 0.0,
                )
                if path_sum != 0.0:
                    trace_photon(
                        grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth,
                        rr_survival, seed, index, GRADIENT, images[b], residual, gradients[b],
                        path_sum,
                    )
                n += vertices
        events[b] += n
