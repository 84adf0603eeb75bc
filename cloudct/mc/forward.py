"""Forward (sun -> medium) path tracing with local estimation to every camera.

Seed paper Sec. 3.4: a photon enters on a sunlit face (:mod:`cloudct.mc.sun`: uniformly, or
preferably where the clouds are) with the weight that makes the estimate absolute, flies a
distance sampled by exact inversion of the optical depth (Eq. 32), scatters with the mixture
phase function (Eq. 33 and :mod:`cloudct.mc.events`), a share of its directions aimed at the
cameras (:mod:`cloudct.mc.detector_sampling`), and carries the effective albedo as a weight.
At every scattering event, and at every reflection by the Lambertian ground, it sends a local
estimate to every camera (Eqs. 36-39):

    weight * albedo * f_p(x, cos theta_{b,d}) * T(x, x_d) / (r^2 Omega_pixel)

for scattering, and weight * A cos(theta_d) / pi * T / (r^2 Omega_pixel) for the ground.
One path serves all views. With periodic boundaries the camera sees every periodic image of
the event, so each image copy that falls in its field of view is estimated.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, prange

from cloudct.mc.accumulate import add_along, add_to
from cloudct.mc.cameras import project
from cloudct.mc.combined import forward_share
from cloudct.mc.detector_sampling import aim_factor, scatter_aimed
from cloudct.mc.events import lambertian_bounce, russian_roulette
from cloudct.mc.random import DOMAIN_FORWARD, stream_start, uniform
from cloudct.mc.sun import sample_entry_point
from cloudct.mc.traversal import (
    BOTTOM,
    INF,
    LEFT,
    STOPPED,
    Trail,
    locate_point,
    march,
    optical_depth_to_exit,
)
from cloudct.physics.mixing import (
    effective_albedo,
    mixture_phase_function,
    reff_log_derivative,
    scattering_log_derivative,
)
from cloudct.physics.transmittance import EXPONENTIAL

INV_PI = 1.0 / math.pi


#: What a forward pass does with its local estimates.
RENDER = 0  # add them to the images
RESIDUAL = 1  # sum them, weighted by the pixels' residuals (first gradient pass)
GRADIENT = 2  # deposit the residual-weighted score-function gradient (second pass)
# deposit the score's vertex terms in the cloud's r_eff alone (second pass, instead of
# GRADIENT; mixing.reff_log_derivative): d/d r_eff at fixed extinction
REFF_GRADIENT = 3
COUNT = 4  # no estimates: count the path's records (path recycling, first pass)
RECORD = 5  # no estimates: write the path's records into a PathRecord (second pass)

#: The particle type whose extinction the gradients are taken with respect to.
CLOUD = 1

#: Kinds of path records (path recycling, :mod:`cloudct.recycling`).
ENTRY = 0  # the start point on a sunlit face, travelling along the sun's rays
SCATTER = 1  # a scattering vertex (the last one of a path may have albedo 0: absorbed)
GROUND = 2  # a reflection by the Lambertian ground
ESCAPE = 3  # where the path left the medium (or was absorbed by a black / no ground)


#: Flux tallies of a forward path (``fluxes`` of :func:`trace_photon`), in photon weight.
FLUX_TOP = 0  # left through the top face
FLUX_SIDE = 1  # left through a side face (open boundaries)
FLUX_DIRECT = 2  # reached the bottom face unscattered (the direct beam)
FLUX_DIFFUSE = 3  # reached the bottom face after scattering or a ground reflection
FLUX_GROUND = 4  # absorbed by the ground (1 - A of what reaches it)
FLUX_MEDIUM = 5  # absorbed in the medium: weight x (1 - albedo) at each collision
NFLUX = 6


class PathRecord(NamedTuple):
    """Where RECORD mode writes a path: one row per record, CSR over photons (the caller
    gives each photon its first row). The direction is that of the segment arriving at the
    record (the sun's for ENTRY); ``voxel`` the flat index ``(ix * ny + iy) * nz + iz`` of
    the voxel the tracer is in there; ``optical_depth`` the optical depth sampled for the
    segment arriving at a SCATTER record, ``inf`` for a segment that ends on a face of the
    box (GROUND, ESCAPE), 0 for ENTRY."""

    position: np.ndarray  # float64[3, nrecords], km
    direction: np.ndarray  # float64[3, nrecords]
    optical_depth: np.ndarray  # float64[nrecords]
    kind: np.ndarray  # int8[nrecords]
    voxel: np.ndarray  # int32 or int64[nrecords]


@njit(cache=True)
def put_record(record, row, kind, grid, px, py, pz, ux, uy, uz, ix, iy, iz, optical_depth):
    """Write one row of a :class:`PathRecord` (nothing when ``record`` is None: counting)."""
    if record is not None:
        record.position[0, row] = px
        record.position[1, row] = py
        record.position[2, row] = pz
        record.direction[0, row] = ux
        record.direction[1, row] = uy
        record.direction[2, row] = uz
        record.optical_depth[row] = optical_depth
        record.kind[row] = kind
        ny = grid.y_edges.size - 1
        nz = grid.z_edges.size - 1
        record.voxel[row] = (ix * ny + iy) * nz + iz


@njit(cache=True, inline="always")
def connection_angular(grid, bank, ix, iy, iz, mu, ground_albedo):
    """Angular factor of a local estimate from voxel (ix, iy, iz): the mixture phase
    function at the scattering cosine ``mu`` (``ground_albedo < 0``: a scattering event),
    or A mu / pi for the Lambertian ground, ``mu`` the cosine of the direction to the
    camera with the vertical (Eqs. 36-39)."""
    if ground_albedo < 0.0:
        return mixture_phase_function(grid, bank, ix, iy, iz, mu)
    return ground_albedo * mu * INV_PI


@njit(cache=True, inline="always")
def combined_forward_weight(cams, angular, camera_end, sun_end, sun_turn, sun_aim, sun_lobe):
    """The weight w_f of a local estimate in the combined estimator (:mod:`cloudct.mc.
    combined`): ``angular`` its angular factor c_n, ``camera_end`` T(x_n -> camera) /
    (r^2 Omega_pixel); the path's sun end, turn at x_1, aim fraction and lobe about the sun
    as :func:`local_estimate` takes them."""
    sun_side = sun_end * (angular if sun_turn < 0.0 else sun_turn)
    if sun_lobe >= 0.0:
        sun_side *= aim_factor(angular, sun_lobe, 1, sun_aim)
    return forward_share(sun_side, camera_end * angular, cams.mis_ratio)


@njit(cache=True, inline="always")
def sun_lobe_at(grid, bank, sun, ix, iy, iz, ux, uy, uz, depth):
    """The lobe about the sun with which a backward path would draw its direction at a
    scattering vertex reached along (ux, uy, uz): f at the angle of -u with the sun's rays;
    -1 where it draws none aimed (the first vertex, or no aiming at the sun)."""
    if depth == 0 or sun.aim_fraction <= 0.0:
        return -1.0
    return mixture_phase_function(
        grid, bank, ix, iy, iz, sun.direction[0] * ux + sun.direction[1] * uy
        + sun.direction[2] * uz,
    )


@njit(cache=True, inline="always")
def sun_side_after_turn(
    grid, bank, sun, ix, iy, iz, vx, vy, vz, ux, uy, uz, depth, sun_turn, back_aims, sun_lobe
):
    """A forward path's sun-side terms of the combined estimator after it turns from v to u
    at a scattering vertex: at the first (``depth`` 0) the next-event estimate's angular
    factor c_1; further on a backward path's aim factor f / q_s for drawing -v there
    (``sun_lobe`` >= 0). Returns ``(sun_turn, back_aims)``."""
    if depth == 0:
        return mixture_phase_function(grid, bank, ix, iy, iz, vx * ux + vy * uy + vz * uz), \
            back_aims
    if sun_lobe >= 0.0:
        back_aims *= aim_factor(
            mixture_phase_function(grid, bank, ix, iy, iz, vx * ux + vy * uy + vz * uz),
            sun_lobe, 1, sun.aim_fraction,
        )
    return sun_turn, back_aims


@njit(cache=True)
def local_estimate(
    grid, bank, cams, copies, periodic, px, py, pz, ix, iy, iz, ux, uy, uz, weight, ground_albedo,
    mode, image, residual, gradient, trail=None, sun_end=0.0, sun_turn=-1.0, sun_aim=0.0,
    sun_lobe=-1.0,
):
    """Local estimates of one event at (px, py, pz) to every camera (Eqs. 36-39).

    A scattering event (``ground_albedo < 0``) uses the mixture phase function at the angle
    between the incoming direction (ux, uy, uz) and the direction to the camera; a ground
    event uses the Lambertian factor A cos(theta) / pi.

    ``mode`` RENDER adds each estimate to ``image``. RESIDUAL and GRADIENT return the sum S
    of the estimates weighted by their pixels' ``residual``; GRADIENT also deposits into
    ``gradient`` the terms of the score function (Eq. 49) that belong to this event alone:
    the connection segment to the camera (-ds/dbeta per voxel, -l for the exponential; see
    :func:`cloudct.mc.traversal.march`) and, for scattering, the vertex
    term at the angle towards the camera. With a scratch :class:`~cloudct.mc.traversal.Trail`
    (``trail``), GRADIENT deposits the connection segment from the crossings recorded while
    computing its transmittance instead of walking it a second time (same values, same
    order; a ray with more crossings than the trail holds is walked again). REFF_GRADIENT
    deposits, for scattering, the vertex term in the cloud's r_eff at that angle alone
    (:func:`cloudct.physics.mixing.reff_log_derivative`).

    With ``cams.mis_ratio`` > 0 each estimate is weighted by its share w_f of the combined
    estimator (:mod:`cloudct.mc.combined`): ``sun_end`` is the path's T(x_1 -> sun) / W
    times the backward aim factors f / q_s of its vertices x_2 .. x_{n-1} over its own aim
    factors, ``sun_turn`` the next-event estimate's angular factor c_1 at x_1 (< 0 when this
    event is x_1 scattering: the estimate's own angular factor); a backward path draws its
    direction at this event towards x_{n-1} with the weight f / q_s whose aimed lobe is
    ``sun_lobe`` (f at the incoming direction's angle with the sun's; < 0: no such draw, at
    x_1 or the ground) and aim fraction ``sun_aim``
    (:mod:`cloudct.mc.detector_sampling`).
    """
    lx = grid.x_edges[-1] - grid.x_edges[0]
    ly = grid.y_edges[-1] - grid.y_edges[0]
    model = grid.transmittance_family[0] != EXPONENTIAL
    weighted_sum = 0.0
    for view in range(cams.position.shape[0]):
        for i in range(copies[view, 0], copies[view, 1] + 1):
            for j in range(copies[view, 2], copies[view, 3] + 1):
                row, col, cx, cy, cz, inv_r2_omega = project(
                    cams, view, px + i * lx, py + j * ly, pz
                )
                if row < 0:
                    continue
                if ground_albedo < 0.0:
                    mu = ux * cx + uy * cy + uz * cz
                elif cz > 0.0:
                    mu = cz
                else:
                    continue
                angular = connection_angular(grid, bank, ix, iy, iz, mu, ground_albedo)
                if mode != RENDER and residual[view, row, col] == 0.0:
                    continue
                scale = 1.0  # of the connection's deposits (march; 1: exponential)
                if mode != GRADIENT:
                    tau = optical_depth_to_exit(
                        grid, px, py, pz, cx, cy, cz, ix, iy, iz, periodic
                    )
                elif trail is None or model:
                    walk = march(grid, px, py, pz, cx, cy, cz, ix, iy, iz, INF, periodic)
                    tau = walk[7]
                    scale = walk[9]
                else:
                    trail.count[0] = 0
                    tau = march(
                        grid, px, py, pz, cx, cy, cz, ix, iy, iz, INF, periodic, None, 0.0, INF,
                        trail,
                    )[7]
                value = weight * angular * math.exp(-tau) * inv_r2_omega
                if cams.mis_ratio > 0.0:
                    value *= combined_forward_weight(
                        cams, angular, math.exp(-tau) * inv_r2_omega, sun_end, sun_turn,
                        sun_aim, sun_lobe,
                    )
                if mode == RENDER:
                    add_to(image, view, row, col, value)
                    continue
                value *= residual[view, row, col]
                weighted_sum += value
                if mode == GRADIENT and value != 0.0:
                    if trail is not None and not model and trail.count[0] <= trail.voxel.size:
                        deposit_trail(trail, gradient, -value)
                    else:
                        march(
                            grid, px, py, pz, cx, cy, cz, ix, iy, iz, INF, periodic, gradient,
                            -value * scale,
                        )
                    if ground_albedo < 0.0:
                        add_to(
                            gradient, ix, iy, iz,
                            value * scattering_log_derivative(grid, bank, CLOUD, ix, iy, iz, mu),
                        )
                elif mode == REFF_GRADIENT and value != 0.0 and ground_albedo < 0.0:
                    add_to(gradient, ix, iy, iz,
                           value * reff_log_derivative(grid, bank, ix, iy, iz, mu))
    return weighted_sum


@njit(cache=True)
def deposit_trail(trail, gradient, weight):
    """gradient[voxel] += weight x length for the crossings of a :class:`Trail`, in order
    (``gradient`` C-contiguous over (x, y, z), addressed by flat voxel index)."""
    add_along(gradient, trail.voxel, trail.length, 0, trail.count[0], weight)


@njit(cache=True)
def trace_photon(
    grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival, seed, index,
    mode, image, residual, gradient, path_sum, record=None, first=0, trail=None, fluxes=None,
):
    """Trace forward photon ``index`` (``ground_albedo < 0``: no ground).

    RENDER adds the path's local estimates to ``image``. RESIDUAL returns the path's sum S
    of residual-weighted estimates, sum_e S_e over its events e. GRADIENT, given that sum
    as ``path_sum``, re-traces the same path (same random stream) and deposits the
    residual-weighted score-function gradient sum_e S_e score_e (Eqs. 46-49). The score of
    event e holds the segments and sampled vertices of the path up to e, so segment k is
    weighted by W_k = sum_{e >= k} S_e, obtained as ``path_sum`` minus the events already
    passed: the cost stays linear in the path length. REFF_GRADIENT re-traces it the same
    way but deposits only the vertex terms in the cloud's r_eff (the extinction's part of
    d/d r_eff is GRADIENT's through the chain rule, :mod:`cloudct.mc.microphysics_gradient`).

    A scratch :class:`~cloudct.mc.traversal.Trail` lets GRADIENT walk each camera
    connection once (see :func:`local_estimate`).

    COUNT and RECORD make no estimates (the same random stream gives the same path): they
    return the number of path records (:data:`ENTRY`, its vertices, and the :data:`ESCAPE`
    of a path that leaves or meets a non-reflecting ground), and RECORD writes them into
    ``record`` from row ``first`` (:class:`PathRecord`, for path recycling).

    With a float64[1, 1, NFLUX] array ``fluxes``, the path also adds where its weight goes
    (:data:`FLUX_TOP` ... :data:`FLUX_MEDIUM`): the domain-mean fluxes of
    :mod:`cloudct.mc.sensors`. The path itself does not change.

    With ``cams.mis_ratio`` > 0 (the combined estimator, :mod:`cloudct.mc.combined`) the
    path keeps its sun end from its first vertex on (the transmittance to the sun there and
    the next-event estimate's angular factor) and the product of its aim factors, which
    weight its local estimates.

    Returns ``(vertices, S)``; ``(records, 0)`` in COUNT and RECORD modes.
    """
    state = stream_start(seed, DOMAIN_FORWARD, index)
    u_face, state = uniform(state)
    u1, state = uniform(state)
    u2, state = uniform(state)
    px, py, pz, weight = sample_entry_point(grid, sun, u_face, u1, u2)
    ux, uy, uz = sun.direction[0], sun.direction[1], sun.direction[2]
    ix, iy, iz = locate_point(grid, px, py, pz, ux, uy, uz)
    depth = 0
    sun_end = 0.0  # T(x_1 -> sun) / W of the combined estimator
    sun_turn = -1.0  # its angular factor c_1 at x_1; < 0 at x_1 itself: the estimate's own
    aim_product = 1.0  # the aim factors f / q of the directions drawn so far
    back_aims = 1.0  # a backward path's aim factors f / q_s at the vertices x_2 .. passed
    total = 0.0
    remaining = path_sum  # W_k: the residual-weighted estimates of events not yet passed
    records = 0  # COUNT / RECORD modes
    if mode >= COUNT:
        put_record(record, first, ENTRY, grid, px, py, pz, ux, uy, uz, ix, iy, iz, 0.0)
        records = 1
    while True:
        u, state = uniform(state)
        if mode == GRADIENT and remaining != 0.0:
            scale = 1.0  # of the flight's deposits: walked first for it under the model
            if grid.transmittance_family[0] != EXPONENTIAL:
                scale = march(
                    grid, px, py, pz, ux, uy, uz, ix, iy, iz, -math.log(u), periodic
                )[9]
            status, px, py, pz, ix, iy, iz, _, _, _ = march(
                grid, px, py, pz, ux, uy, uz, ix, iy, iz, -math.log(u), periodic, gradient,
                -remaining * scale,
            )
        else:
            status, px, py, pz, ix, iy, iz, _, _, _ = march(
                grid, px, py, pz, ux, uy, uz, ix, iy, iz, -math.log(u), periodic
            )
        if mode >= COUNT:
            if status == STOPPED:
                kind, sampled = SCATTER, -math.log(u)
            elif status == BOTTOM and ground_albedo > 0.0:
                kind, sampled = GROUND, INF
            else:
                kind, sampled = ESCAPE, INF
            put_record(
                record, first + records, kind, grid, px, py, pz, ux, uy, uz, ix, iy, iz, sampled
            )
            records += 1
        if status == LEFT:
            if fluxes is not None:
                add_to(fluxes, 0, 0, FLUX_TOP if pz >= grid.z_edges[-1] else FLUX_SIDE, weight)
            return (depth if mode < COUNT else records), total
        if status == BOTTOM:
            if fluxes is not None:
                add_to(fluxes, 0, 0, FLUX_DIRECT if depth == 0 else FLUX_DIFFUSE, weight)
                if ground_albedo >= 0.0:
                    add_to(fluxes, 0, 0, FLUX_GROUND, weight * (1.0 - ground_albedo))
            if ground_albedo <= 0.0:
                return (depth if mode < COUNT else records), total
            if cams.mis_ratio > 0.0 and depth == 0:
                sun_end = sun_transmittance(grid, sun, periodic, px, py, pz, ix, iy, iz)
                sun_turn = ground_albedo * -sun.direction[2] * INV_PI
            s_event = 0.0
            if mode < COUNT:
                # sun_aim and sun_lobe at their defaults (no aimed draw at the ground), passed
                # so that this call shares the scattering event's compiled local_estimate
                s_event = local_estimate(
                    grid, bank, cams, copies, periodic, px, py, pz, ix, iy, iz, ux, uy, uz,
                    weight, ground_albedo, mode, image, residual, gradient, trail,
                    sun_end * back_aims / aim_product, sun_turn, 0.0, -1.0,
                )
            weight *= ground_albedo
            ux, uy, uz, state = lambertian_bounce(state)
        else:
            albedo = effective_albedo(grid, ix, iy, iz)
            if fluxes is not None:
                add_to(fluxes, 0, 0, FLUX_MEDIUM, weight * (1.0 - albedo))
            if albedo == 0.0:
                return (depth if mode < COUNT else records), total
            weight *= albedo
            sun_lobe = -1.0
            if cams.mis_ratio > 0.0:
                if depth == 0:
                    sun_end = sun_transmittance(grid, sun, periodic, px, py, pz, ix, iy, iz)
                sun_lobe = sun_lobe_at(grid, bank, sun, ix, iy, iz, ux, uy, uz, depth)
            s_event = 0.0
            if mode < COUNT:
                s_event = local_estimate(
                    grid, bank, cams, copies, periodic, px, py, pz, ix, iy, iz, ux, uy, uz,
                    weight, -1.0, mode, image, residual, gradient, trail,
                    sun_end * back_aims / aim_product, sun_turn, sun.aim_fraction, sun_lobe,
                )
            vx, vy, vz = ux, uy, uz
            ux, uy, uz, aimed, state = scatter_aimed(
                grid, bank, cams, ix, iy, iz, px, py, pz, ux, uy, uz, state
            )
            weight *= aimed
            aim_product *= aimed
            if cams.mis_ratio > 0.0:
                sun_turn, back_aims = sun_side_after_turn(
                    grid, bank, sun, ix, iy, iz, vx, vy, vz, ux, uy, uz, depth, sun_turn,
                    back_aims, sun_lobe,
                )
            if mode == GRADIENT or mode == REFF_GRADIENT:
                # the sampled vertex term belongs to the scores of all later events
                mu = vx * ux + vy * uy + vz * uz
                later = remaining - s_event
                if later != 0.0:
                    if mode == GRADIENT:
                        term = scattering_log_derivative(grid, bank, CLOUD, ix, iy, iz, mu)
                    else:
                        term = reff_log_derivative(grid, bank, ix, iy, iz, mu)
                    add_to(gradient, ix, iy, iz, later * term)
        total += s_event
        remaining -= s_event
        depth += 1
        factor, state = russian_roulette(depth, rr_depth, rr_survival, state)
        if factor == 0.0:
            return (depth if mode < COUNT else records), total
        weight *= factor


@njit(cache=True)
def sun_transmittance(grid, sun, periodic, px, py, pz, ix, iy, iz):
    """T(x -> sun) / W at a path's first vertex: the transmittance along the sun's rays out
    of the medium over the uniform entry's photon weight (the sun end D_b / c_1 of
    :mod:`cloudct.mc.combined`, computed as the backward estimator's next-event estimate
    does)."""
    tau = optical_depth_to_exit(
        grid, px, py, pz, -sun.direction[0], -sun.direction[1], -sun.direction[2], ix, iy, iz,
        periodic,
    )
    return math.exp(-tau) / sun.power


@njit(parallel=True, cache=True)
def forward_batches(
    grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival, seed,
    per_batch, first, last, mode, images, residual, gradients, events,
):
    """Trace photons ``first .. last - 1`` of every batch, in parallel over batches.

    Batch ``b`` owns photon indices ``b * per_batch + k``, so which photons a batch
    holds, and their random streams, do not depend on the thread count. RENDER accumulates
    batch b's local estimates (not yet divided by its photon count) in ``images[b]``;
    GRADIENT accumulates its residual-weighted score-function gradient in ``gradients[b]``
    (each photon first traced in RESIDUAL mode for its sum, then again in GRADIENT mode,
    with a scratch trail per batch so that each camera connection is walked once);
    REFF_GRADIENT the same way its vertex terms in the cloud's r_eff.
    ``events[b]`` counts the path vertices.
    """
    capacity = 4 * (grid.x_edges.size + grid.y_edges.size + grid.z_edges.size) + 16
    for b in prange(images.shape[0]):
        trail = Trail(np.zeros(capacity, np.int64), np.zeros(capacity), np.zeros(1, np.int64),
                      np.zeros(1))
        n = 0
        for k in range(first, last):
            index = b * per_batch + k
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
                        rr_survival, seed, index, mode, images[b], residual, gradients[b],
                        path_sum, None, 0, trail,
                    )
                n += vertices
        events[b] += n


@njit(parallel=True, cache=True)
def sensor_batches(
    grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival, seed,
    per_batch, first, last, images, fluxes, events,
):
    """Trace photons ``first .. last - 1`` of every batch (the photons of
    :func:`forward_batches` in RENDER mode), adding their local estimates
    to ``images[b]`` and their flux tallies to ``fluxes[b]`` (float64[batches, 1, 1,
    NFLUX]), in parallel over batches; ``events[b]`` counts the path vertices."""
    unused = np.zeros((1, 1, 1))  # residual and gradient: not read or written in RENDER
    for b in prange(images.shape[0]):
        n = 0
        for k in range(first, last):
            n += trace_photon(
                grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival,
                seed, b * per_batch + k, RENDER, images[b], unused, unused, 0.0, None,
                0, None, fluxes[b],
            )[0]
        events[b] += n
