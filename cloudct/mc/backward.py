"""Backward (camera -> sun) path tracing with next-event estimation towards the sun.

A pixel's value is the average radiance over its area on the image plane, so each sample
starts at the pinhole through a uniform point of the pixel (an orthographic camera: at a
uniform point of the pixel on its image rectangle, along the view direction;
:func:`cloudct.mc.cameras.pixel_ray`). The ray enters the medium, flies a distance sampled
by exact inversion of the optical depth (Eq. 32), and at every scattering vertex collects
the single-scattered sunlight

    throughput * albedo * f_p(x, cos angle(sun travel, -ray)) * T(x -> sun) * F0,  F0 = 1,

then continues in a direction drawn from the mixture phase function (a share of them about
the direction to the sun, weighted so that the images stay unbiased:
:mod:`cloudct.mc.detector_sampling`); at the Lambertian ground it collects throughput *
A cos(theta0) / pi * T(ground -> sun) and bounces cosine-weighted. The same vertex routines
as the forward estimator are used (:mod:`cloudct.mc.events`), with the same
medium-independent Russian roulette. The direct view of the sun's disc is not part of the
images (a delta the pixels never contain).

The same paths give a residual-weighted gradient by the path score function (Eqs. 44-49 of
the seed paper, the path read from the camera's end): :func:`score_pixel_sample` traces a
sample twice (the same random stream), the first time for its estimate, the second to
deposit each estimate's score. Every next-event estimate holds the flights and the sampled
vertices before it and its own connection to the sun and turn there, so a flight is
weighted by the estimates at its end and beyond, as in
:func:`cloudct.mc.forward.trace_photon`.
"""

from __future__ import annotations

import math

from numba import njit, prange

from cloudct.mc.accumulate import add_to
from cloudct.mc.cameras import inverse_r2_omega, pixel_ray
from cloudct.mc.combined import backward_share
from cloudct.mc.detector_sampling import aim_factor, camera_lobes, scatter_sun_aimed
from cloudct.mc.events import lambertian_bounce, russian_roulette
from cloudct.mc.forward import CLOUD
from cloudct.mc.random import DOMAIN_BACKWARD, stream_start, uniform
from cloudct.mc.traversal import (
    BOTTOM,
    INF,
    LEFT,
    locate_point,
    march,
    optical_depth_to_exit,
    ray_box_entry,
    wrap_into_box,
)
from cloudct.physics.mixing import (
    effective_albedo,
    mixture_phase_function,
    scattering_log_derivative,
)

INV_PI = 1.0 / math.pi


@njit(cache=True, _nrt=False)
def camera_ray_entry(grid, cams, periodic, view, row, col, state):
    """Start of a backward path: the ray from the pinhole through a uniform point of pixel
    (view, row, col) (orthographic: from that point along the view direction), taken to
    where it enters the medium (with periodic boundaries, folded into the box).

    Returns ``(hit, t, px, py, pz, ux, uy, uz, ix, iy, iz, state)``, ``t`` the distance
    from the ray's origin to the entry; ``hit`` is False when the ray misses the medium.
    """
    xi_u, state = uniform(state)
    xi_v, state = uniform(state)
    ox, oy, oz, ux, uy, uz = pixel_ray(cams, view, row, col, xi_u, xi_v)
    t = ray_box_entry(grid, ox, oy, oz, ux, uy, uz, periodic)
    if t < 0.0:
        return False, t, ox, oy, oz, ux, uy, uz, 0, 0, 0, state
    px, py, pz = ox + t * ux, oy + t * uy, oz + t * uz
    if periodic:
        px, py = wrap_into_box(grid, px, py)
    ix, iy, iz = locate_point(grid, px, py, pz, ux, uy, uz)
    return True, t, px, py, pz, ux, uy, uz, ix, iy, iz, state


@njit(cache=True)
def trace_pixel_sample(
    grid, bank, cams, sun, periodic, ground_albedo, rr_depth, rr_survival, seed, index, view,
    row, col, gradient=None, weight=0.0, path_sum=0.0,
):
    """Radiance estimate of one backward sample of pixel (view, row, col).

    With a ``gradient`` array (over (x, y, z)), the sample is traced again for its score
    (Eq. 49): given ``path_sum``, ``weight`` times the radiance the same sample returned
    without it, each estimate e, weighted by ``weight`` (S_e), deposits its connection to the
    sun (-S_e x the length in each voxel) and, scattered, its turn from the sun's rays
    towards the camera side (S_e d log(beta_s f) / dbeta); each flight deposits -W_k x length,
    W_k = sum_{e >= k} S_e the estimates at its end and beyond, and each scattering vertex
    its sampled turn with the estimates after it (``path_sum`` minus those passed: linear in
    the path length). Exponential transmittance only (the callers refuse others).

    With ``cams.mis_ratio`` > 0 each next-event estimate is weighted by its share of the
    combined estimator, w_b of :mod:`cloudct.mc.combined`: the path's camera end D_f (the
    first vertex's transmittance to the camera, 1 / (r^2 Omega_pixel) and the local
    estimate's angular factor there) is kept from the first vertex on, and the product of
    the aim factors f / q (:func:`~cloudct.mc.detector_sampling.aimed_weight`) with which a
    forward photon would have drawn the directions of the vertices passed, and of its own
    (f / q_s: directions aimed at the sun).

    Returns ``(radiance, vertices)``; ``ground_albedo < 0`` means no ground.
    """
    state = stream_start(seed, DOMAIN_BACKWARD, index)
    hit, t_entry, px, py, pz, ux, uy, uz, ix, iy, iz, state = camera_ray_entry(
        grid, cams, periodic, view, row, col, state
    )
    if not hit:
        return 0.0, 0
    sx, sy, sz = -sun.direction[0], -sun.direction[1], -sun.direction[2]  # towards the sun
    ratio = cams.mis_ratio
    camera_end = 0.0  # W T(x_n -> camera) / (r^2 Omega_pixel) of the combined estimator
    camera_turn = -1.0  # its angular factor c_n at x_n; < 0 at x_n itself: the NEE's own
    aim_product = 1.0  # the forward photon's aim factors f / q at x_{n-1} .. (passed)
    sun_aims = 1.0  # this path's own aim factors f / q_s (in its throughput)
    lobes, seen = 0.0, 0  # the forward aim's camera lobes at the current vertex
    radiance = 0.0
    throughput = 1.0
    depth = 0
    remaining = path_sum  # W_k: the weighted estimates of the vertices not yet passed
    while True:
        u, state = uniform(state)
        if gradient is not None and remaining != 0.0:
            status, px, py, pz, ix, iy, iz, _, walked, _ = march(
                grid, px, py, pz, ux, uy, uz, ix, iy, iz, -math.log(u), periodic, gradient,
                -remaining,
            )
        else:
            status, px, py, pz, ix, iy, iz, _, walked, _ = march(
                grid, px, py, pz, ux, uy, uz, ix, iy, iz, -math.log(u), periodic
            )
        if status == LEFT:
            return radiance, depth
        if status == BOTTOM and ground_albedo <= 0.0:
            return radiance, depth
        if ratio > 0.0 and depth == 0:
            tau_camera = optical_depth_to_exit(
                grid, px, py, pz, -ux, -uy, -uz, ix, iy, iz, periodic
            )
            camera_end = (sun.power * math.exp(-tau_camera)
                          * inverse_r2_omega(cams, view, ux, uy, uz, t_entry + walked))
            if status == BOTTOM:  # the local estimate's Lambertian factor, towards the camera
                camera_turn = ground_albedo * -uz * INV_PI
        tau_sun = optical_depth_to_exit(grid, px, py, pz, sx, sy, sz, ix, iy, iz, periodic)
        vx, vy, vz = ux, uy, uz
        if status == BOTTOM:
            angular = ground_albedo * sz * INV_PI
            # (the product in its original order: the plain images stay bitwise)
            contribution = throughput * ground_albedo * sz * INV_PI * math.exp(-tau_sun)
            throughput *= ground_albedo
            ux, uy, uz, state = lambertian_bounce(state)
        else:
            throughput *= effective_albedo(grid, ix, iy, iz)
            # sunlight travels along -s and leaves towards the camera along -u:
            # the scattering cosine is (-s).(-u) = s.u
            angular = mixture_phase_function(grid, bank, ix, iy, iz, sx * vx + sy * vy + sz * vz)
            contribution = throughput * angular * math.exp(-tau_sun)
            ux, uy, uz, aimed, state = scatter_sun_aimed(
                grid, bank, sun, ix, iy, iz, ux, uy, uz, state
            )
            throughput *= aimed
        if ratio > 0.0:
            turn = angular if camera_turn < 0.0 else camera_turn
            aims = aim_product
            if depth > 0 and status != BOTTOM:
                # the forward photon's draws here, towards x_{i+1} along -u: their aimed
                # lobes, then as x_1 (from the sun, f = the estimate's own angular factor)
                lobes, seen = camera_lobes(grid, bank, cams, ix, iy, iz, px, py, pz,
                                           -vx, -vy, -vz)
                aims *= aim_factor(angular, lobes, seen, cams.aim_fraction)
            contribution *= backward_share(
                math.exp(-tau_sun) * angular * sun_aims, camera_end * turn * aims, ratio
            )
            if status != BOTTOM:
                sun_aims *= aimed
                # the photon arrives here along -u' and leaves towards the camera side along -u
                if depth == 0:
                    camera_turn = mixture_phase_function(
                        grid, bank, ix, iy, iz, vx * ux + vy * uy + vz * uz
                    )
                else:  # and as an interior vertex, arriving along -u', for the paths on
                    turn_here = mixture_phase_function(
                        grid, bank, ix, iy, iz, vx * ux + vy * uy + vz * uz
                    )
                    aim_product *= aim_factor(turn_here, lobes, seen, cams.aim_fraction)
        radiance += contribution
        if gradient is not None:
            value = weight * contribution  # S_e
            if value != 0.0:
                march(grid, px, py, pz, sx, sy, sz, ix, iy, iz, INF, periodic, gradient, -value)
                if status != BOTTOM:
                    add_to(gradient, ix, iy, iz, value * scattering_log_derivative(
                        grid, bank, CLOUD, ix, iy, iz, sx * vx + sy * vy + sz * vz))
            later = remaining - value
            if status != BOTTOM and later != 0.0:  # the sampled turn, for the later estimates
                add_to(gradient, ix, iy, iz, later * scattering_log_derivative(
                    grid, bank, CLOUD, ix, iy, iz, vx * ux + vy * uy + vz * uz))
            remaining = later
        depth += 1
        factor, state = russian_roulette(depth, rr_depth, rr_survival, state)
        if factor == 0.0:
            return radiance, depth
        throughput *= factor


@njit(cache=True)
def score_pixel_sample(
    grid, bank, cams, sun, periodic, ground_albedo, rr_depth, rr_survival, seed, index, view,
    row, col, weight, gradient,
):
    """Adds to ``gradient`` ``weight`` (the pixel's residual) times the path score
    function's estimate of dI / dbeta_cloud from backward sample ``index`` of pixel (view,
    row, col) (:func:`trace_pixel_sample`, two passes); returns its path vertices. With
    ``cams.mis_ratio`` > 0, the estimates carry their combined estimator's weights w_b."""
    radiance, vertices = trace_pixel_sample(
        grid, bank, cams, sun, periodic, ground_albedo, rr_depth, rr_survival, seed, index,
        view, row, col,
    )
    if weight * radiance != 0.0:
        trace_pixel_sample(
            grid, bank, cams, sun, periodic, ground_albedo, rr_depth, rr_survival, seed, index,
            view, row, col, gradient, weight, weight * radiance,
        )
    return vertices


@njit(parallel=True, cache=True)
def backward_batches(
    grid, bank, cams, sun, periodic, ground_albedo, rr_depth, rr_survival, seed,
    per_batch, first, last, images, events,
):
    """Samples ``first .. last - 1`` of every pixel in every batch, parallel over batches.

    ``images[b]`` accumulates batch ``b``'s sum of sample radiances per pixel (not yet
    divided by its sample count) and ``events[b]`` its number of path vertices.
    """
    nbatch, nview, nrows, ncols = images.shape
    for b in prange(nbatch):
        n = 0
        for view in range(nview):
            for row in range(nrows):
                for col in range(ncols):
                    pixel = (view * nrows + row) * ncols + col
                    for k in range(first, last):
                        index = (pixel * nbatch + b) * per_batch + k
                        value, vertices = trace_pixel_sample(
                            grid, bank, cams, sun, periodic, ground_albedo, rr_depth,
                            rr_survival, seed, index, view, row, col,
                        )
                        add_to(images[b], view, row, col, value)
                        n += vertices
        events[b] += n
