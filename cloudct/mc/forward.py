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

import numpy as np
from numba import njit, prange

from cloudct.mc.cameras import project
from cloudct.mc.events import lambertian_bounce, russian_roulette, scatter
from cloudct.mc.random import DOMAIN_FORWARD, stream_start, uniform
from cloudct.mc.sun import sample_entry_point
from cloudct.mc.traversal import BOTTOM, LEFT, locate_point, march, optical_depth_to_exit
from cloudct.physics.mixing import effective_albedo, mixture_phase_function

INV_PI = 1.0 / math.pi


@njit(cache=True)
def local_estimate(
    grid, bank, cams, copies, periodic, px, py, pz, ix, iy, iz, ux, uy, uz, weight, ground_albedo,
    image,
):
    """Add the local estimates of one event at (px, py, pz) to every camera's image.

    A scattering event (``ground_albedo < 0``) uses the mixture phase function at the angle
    between the incoming direction (ux, uy, uz) and the direction to the camera; a ground
    event uses the Lambertian factor A cos(theta) / pi.
    """
    lx = grid.x_edges[-1] - grid.x_edges[0]
    ly = grid.y_edges[-1] - grid.y_edges[0]
    for view in range(cams.position.shape[0]):
        for i in range(copies[view, 0], copies[view, 1] + 1):
            for j in range(copies[view, 2], copies[view, 3] + 1):
                row, col, cx, cy, cz, inv_r2_omega = project(
                    cams, view, px + i * lx, py + j * ly, pz
                )
                if row < 0:
                    continue
                if ground_albedo < 0.0:
                    angular = mixture_phase_function(
                        grid, bank, ix, iy, iz, ux * cx + uy * cy + uz * cz
                    )
                elif cz > 0.0:
                    angular = ground_albedo * cz * INV_PI
                else:
                    continue
                tau = optical_depth_to_exit(grid, px, py, pz, cx, cy, cz, ix, iy, iz, periodic)
                image[view, row, col] += weight * angular * math.exp(-tau) * inv_r2_omega


@njit(cache=True)
def trace_photon(
    grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival, seed, index,
    image,
):
    """Trace forward photon ``index`` and add its local estimates to ``image``.

    ``ground_albedo < 0`` means no ground (light leaving through the bottom is lost).
    Returns the number of scattering and ground events of the path.
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
    while True:
        u, state = uniform(state)
        status, px, py, pz, ix, iy, iz, _ = march(
            grid, px, py, pz, ux, uy, uz, ix, iy, iz, -math.log(u), periodic
        )
        if status == LEFT:
            return depth
        if status == BOTTOM:
            if ground_albedo <= 0.0:
                return depth
            local_estimate(
                grid, bank, cams, copies, periodic, px, py, pz, ix, iy, iz, ux, uy, uz, weight,
                ground_albedo, image,
            )
            weight *= ground_albedo
            ux, uy, uz, state = lambertian_bounce(state)
        else:
            albedo = effective_albedo(grid, ix, iy, iz)
            weight *= albedo
            local_estimate(
                grid, bank, cams, copies, periodic, px, py, pz, ix, iy, iz, ux, uy, uz, weight,
                -1.0, image,
            )
            ux, uy, uz, state = scatter(grid, bank, ix, iy, iz, ux, uy, uz, state)
        depth += 1
        factor, state = russian_roulette(depth, rr_depth, rr_survival, state)
        if factor == 0.0:
            return depth
        weight *= factor


@njit(parallel=True, cache=True)
def forward_batches(
    grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival, seed,
    photons_per_batch, first, last, images, events,
):
    """Trace photons ``first .. last - 1`` of every batch, in parallel over batches.

    Batch ``b`` owns photon indices ``b * photons_per_batch + k``, so which photons a batch
    holds, and their random streams, do not depend on the thread count. ``images[b]``
    accumulates the batch's local estimates (not yet divided by its photon count) and
    ``events[b]`` its number of path vertices.
    """
    for b in prange(images.shape[0]):
        n = 0
        for k in range(first, last):
            n += trace_photon(
                grid, bank, cams, copies, sun, periodic, ground_albedo, rr_depth, rr_survival,
                seed, b * photons_per_batch + k, images[b],
            )
        events[b] += n


def new_batch_images(nbatch: int, cams) -> tuple[np.ndarray, np.ndarray]:
    """Zeroed per-batch image accumulators and event counters."""
    images = np.zeros((nbatch, cams.position.shape[0], cams.nrows, cams.ncols))
    return images, np.zeros(nbatch, dtype=np.int64)
