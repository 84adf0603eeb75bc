"""Traversal of the rectilinear voxel grid (3D DDA) with exact optical depths.

The extinction is piecewise constant in each voxel, so the optical depth along a ray is
the sum over the crossed voxels of extinction x length inside the voxel, and the free-flight
distance of Eq. (32) is found exactly by inverting that sum inside the voxel where it
reaches the sampled optical depth.

One routine, :func:`march`, walks a ray voxel by voxel; free flights, transmittances to
cameras and to the sun all call it. Under a non-exponential transmittance
(:mod:`cloudct.physics.transmittance`) it carries the equivalent optical depth -log T of
the recursive form (Vicini et al. 2021, Eqs. 7-8), exact per voxel, and ends a free flight
where T = u inside the voxel; T restarts at 1 at every path vertex (the paper's model).

With ``periodic`` boundaries a ray that leaves through
a side face re-enters through the opposite face; it ends when it leaves through the top
or reaches the bottom. With ``open`` boundaries it ends when it leaves through any face.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from cloudct.mc.accumulate import add_to
from cloudct.physics.mixing import total_extinction
from cloudct.physics.transmittance import (
    EXPONENTIAL,
    LINEAR_MIX,
    collision_factor,
    depth_step,
    log_hazard,
    optical_depth_to_reach,
)

#: March outcomes.
STOPPED = 0  # the sampled optical depth was reached inside the medium
LEFT = 1  # left the box through the top (or, with open boundaries, any side face)
BOTTOM = 2  # reached the bottom face of the box (the ground, where there is one)

INF = math.inf


class Trail(NamedTuple):
    """A record of the voxels a :func:`march` crosses (path recycling, gradient deposits).

    The walk appends, for every voxel it crosses, the flat voxel index
    ``(ix * ny + iy) * nz + iz`` and the length inside the voxel, while there is room
    (``capacity = voxel.size``, 0 to only count), and always advances ``count[0]`` and adds
    the length to ``distance[0]``. The caller resets ``count`` and ``distance``.
    """

    voxel: np.ndarray  # int32 or int64[capacity]
    length: np.ndarray  # float64[capacity], km
    count: np.ndarray  # int64[1]: crossings walked (may exceed the capacity)
    distance: np.ndarray  # float64[1]: distance walked, km


def new_trail(capacity: int, voxel_dtype=np.int64) -> Trail:
    """An empty :class:`Trail` with room for ``capacity`` crossings."""
    return Trail(
        np.zeros(capacity, voxel_dtype), np.zeros(capacity), np.zeros(1, np.int64), np.zeros(1)
    )


@njit(cache=True, _nrt=False)
def locate(edges, p, d):
    """Index of the cell of ``edges`` holding coordinate ``p``, ties broken by direction ``d``.

    A point exactly on an inner edge belongs to the cell the ray is about to enter.
    The result is clamped to the valid range, so points on the outer faces of the box map to
    the boundary cells.
    """
    n = edges.size - 1
    lo = 0
    hi = n
    # binary search for the last edge <= p
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if edges[mid] <= p:
            lo = mid
        else:
            hi = mid
    i = lo
    if p == edges[i] and d < 0.0 and i > 0:
        i -= 1
    if i > n - 1:
        i = n - 1
    return i


@njit(cache=True, inline="always")
def _distance_to_face(edges, i, p, d):
    """Distance along a unit-direction component ``d`` from ``p`` to the next face of cell i."""
    if d > 0.0:
        return max((edges[i + 1] - p) / d, 0.0)
    if d < 0.0:
        return max((edges[i] - p) / d, 0.0)
    return INF


#: Outcome of crossing a voxel face: still inside the medium.
INSIDE = -1


@njit(cache=True, inline="always")
def next_face(xe, ye, ze, px, py, pz, ux, uy, uz, ix, iy, iz):
    """Distance along (ux, uy, uz) to the next face of voxel (ix, iy, iz) of the grid with
    cell edges ``xe``, ``ye``, ``ze``, and the axis (0, 1, 2 for x, y, z) of that face."""
    tx = _distance_to_face(xe, ix, px, ux)
    ty = _distance_to_face(ye, iy, py, uy)
    tz = _distance_to_face(ze, iz, pz, uz)
    t = min(tx, min(ty, tz))
    if t == tx:
        return t, 0
    if t == ty:
        return t, 1
    return t, 2


@njit(cache=True, inline="always")
def step_index(i, p, edges, d):
    """Cell index and coordinate after crossing the face of cell i ahead along the
    direction component ``d``: the coordinate is set exactly to the face. The index may
    leave 0 .. n - 1 (see :func:`cross_boundary`)."""
    if d > 0.0:
        return i + 1, edges[i + 1]
    return i - 1, edges[i]


@njit(cache=True, _nrt=False)
def cross_boundary(grid, px, py, pz, ix, iy, iz, periodic):
    """After a step out of the cell range (:func:`step_index`): re-enter through the
    opposite side face with periodic boundaries, or end the walk.

    Returns ``(status, px, py, pz, ix, iy, iz)``: status :data:`INSIDE` with the wrapped
    voxel, or :data:`LEFT` / :data:`BOTTOM` with the last voxel inside and the point on the
    face it left through.
    """
    xe = grid.x_edges
    ye = grid.y_edges
    nx = xe.size - 1
    ny = ye.size - 1
    nz = grid.z_edges.size - 1
    if iz < 0:
        return BOTTOM, px, py, pz, ix, iy, 0
    if iz == nz:
        return LEFT, px, py, pz, ix, iy, nz - 1
    if not periodic:
        return LEFT, px, py, pz, min(max(ix, 0), nx - 1), min(max(iy, 0), ny - 1), iz
    if ix == nx:
        ix = 0
        px = xe[0]
    elif ix < 0:
        ix = nx - 1
        px = xe[nx]
    if iy == ny:
        iy = 0
        py = ye[0]
    elif iy < 0:
        iy = ny - 1
        py = ye[ny]
    return INSIDE, px, py, pz, ix, iy, iz


@njit(cache=True, _nrt=False)
def march(
    grid, px, py, pz, ux, uy, uz, ix, iy, iz, tau_target, periodic, lengths=None,
    length_weight=0.0, max_distance=INF, trail=None,
):
    """Walk from (px, py, pz) in voxel (ix, iy, iz) along the unit vector (ux, uy, uz).

    The walk stops where the optical depth reaches ``tau_target`` (use ``inf`` for a
    transmittance), where the distance walked reaches ``max_distance`` (the optical depth
    between two points), whichever comes first, or where the ray leaves the medium. When an
    array ``lengths`` is given, ``length_weight`` x (length inside the voxel) is added to
    ``lengths[ix, iy, iz]`` for every voxel crossed: for the exponential, the derivative of
    ``length_weight`` x (-log transmittance) with respect to each voxel's extinction, which
    the gradient estimators need (under a non-exponential transmittance, see below). A
    :class:`Trail` records the crossings.

    Under a non-exponential transmittance ``tau`` is the equivalent depth s = -log T, and
    the derivative of s at the walk's end with respect to voxel k's extinction is l_k
    h_k(u_in) / Q_{k-1} x Q_n (:mod:`cloudct.physics.transmittance`): the walk adds
    ``length_weight`` x l_k h_k(u_in) / Q_{k-1} and returns the end's factor as ``scale``,
    so a caller that walks the ray once for ``scale`` and again with ``length_weight`` x
    ``scale`` deposits the derivatives. For a walk that ended by reaching ``tau_target`` (a
    free flight's collision), ``scale`` also holds the collision factor c, which turns them
    into those of -log T_pdf (Eq. 9; the vertex's 1 / beta aside). ``scale`` is 1 for the
    exponential, whose deposits are the derivatives themselves.

    Returns ``(status, px, py, pz, ix, iy, iz, tau, distance, scale)`` with status
    :data:`STOPPED`, :data:`LEFT` or :data:`BOTTOM`; the position and voxel are where the
    walk ended (for LEFT and BOTTOM, on the face it left through), ``tau`` the optical depth
    travelled and ``distance`` the length walked (with periodic boundaries, across the
    wrapped faces).
    """
    xe = grid.x_edges
    ye = grid.y_edges
    ze = grid.z_edges
    nx = xe.size - 1
    ny = ye.size - 1
    nz = ze.size - 1
    family = grid.transmittance_family[0]
    tau = 0.0
    walked = 0.0
    log_q = 0.0  # log Q: the hazard ratios of the voxels passed (non-exponential only)
    while True:
        t, axis = next_face(xe, ye, ze, px, py, pz, ux, uy, uz, ix, iy, iz)
        beta = total_extinction(grid, ix, iy, iz)
        if family == EXPONENTIAL:
            tau_next = tau + beta * t
        else:  # tau is the equivalent optical depth -log T (Eqs. 7-8)
            mode = grid.transmittance_mode[ix, iy, iz]
            tau_next, log_ratio = depth_step(family, tau, mode, beta * t)
        piece = t  # the length walked in this voxel
        stop = False
        collided = False
        if walked + t >= max_distance:
            s = max_distance - walked
            if family == EXPONENTIAL:
                tau_s = tau + beta * s
            else:
                tau_s, log_ratio_s = depth_step(family, tau, mode, beta * s)
            if tau_s < tau_target:
                piece = s
                stop = True
                tau_end = tau_s
                if family != EXPONENTIAL:
                    log_ratio = log_ratio_s
        if not stop and tau_next >= tau_target:
            if family == EXPONENTIAL:
                piece = (tau_target - tau) / beta
            else:  # the free flight ends where T = u inside this voxel
                piece = optical_depth_to_reach(family, tau, mode, tau_target) / beta
            stop = True
            collided = True
            tau_end = tau_target
        if lengths is not None:
            if family == EXPONENTIAL:
                add_to(lengths, ix, iy, iz, length_weight * piece)
            else:
                add_to(lengths, ix, iy, iz, length_weight * piece
                       * math.exp(log_hazard(family, tau, mode) - log_q))
        if trail is not None:
            n = trail.count[0]
            if n < trail.voxel.size:
                trail.voxel[n] = (ix * ny + iy) * nz + iz
                trail.length[n] = piece
            trail.count[0] = n + 1
            trail.distance[0] += piece
        if stop:
            scale = 1.0
            if family != EXPONENTIAL and tau_end < INF:  # (T = 0: nothing to differentiate)
                if collided:
                    log_ratio = log_hazard(family, tau_end, mode) - log_hazard(family, tau, mode)
                scale = math.exp(log_q + log_ratio)
                if collided:
                    scale *= collision_factor(family, tau_end, mode)
            return (
                STOPPED, px + piece * ux, py + piece * uy, pz + piece * uz, ix, iy, iz, tau_end,
                walked + piece, scale,
            )
        tau = tau_next
        walked += t
        if family != EXPONENTIAL:
            log_q += log_ratio
        # cross the face (spelled out here and in the DRT walk: this is the engine's
        # hottest loop, and an inlined function returning the 7-tuple ran 1.6x slower)
        px += t * ux
        py += t * uy
        pz += t * uz
        if axis == 0:
            ix, px = step_index(ix, px, xe, ux)
        elif axis == 1:
            iy, py = step_index(iy, py, ye, uy)
        else:
            iz, pz = step_index(iz, pz, ze, uz)
        if ix < 0 or ix == nx or iy < 0 or iy == ny or iz < 0 or iz == nz:
            status, px, py, pz, ix, iy, iz = cross_boundary(grid, px, py, pz, ix, iy, iz, periodic)
            if status != INSIDE:
                scale = 1.0 if family == EXPONENTIAL else math.exp(log_q)
                return status, px, py, pz, ix, iy, iz, tau, walked, scale


def require_exponential(
    grid, what: str,
    alternative: str = "use the path score function (estimator 'score', no path recycling)",
) -> None:
    """Refuse ``what`` (sample matching, path recycling) for a medium whose transmittance is
    not exponential: those take the derivatives and the replay of exponential paths; the
    path score function and DRT differentiate the power law. ``alternative`` says what
    to use instead."""
    if grid.transmittance_family[0] != EXPONENTIAL:
        raise ValueError(
            f"{what} under a non-exponential transmittance (the medium's transmittance "
            f"attribute) are not implemented: {alternative} for the power law, or retrieve "
            "under the exponential assumption"
        )


def require_smooth_flight_density(grid, what: str) -> None:
    """Refuse ``what`` (the path score function, DRT) under a linear-mix transmittance with a
    mode below 1: its collision density -f' jumps where the linear part ends (optical
    depth 2 inside a voxel), a point that moves with the extinction, and the score function
    misses the boundary term of that jump (docs/transmittance.md, "Gradients")."""
    if grid.transmittance_family[0] == LINEAR_MIX and np.any(grid.transmittance_mode < 1.0):
        raise ValueError(
            f"{what} under the linear-mix transmittance are not implemented: its collision "
            "density jumps where the linear part ends, and the gradient estimators miss that "
            "boundary's term (docs/transmittance.md); the power law (transmittance 'gamma') "
            "is differentiated"
        )


@njit(cache=True, _nrt=False)
def optical_depth_to_exit(grid, px, py, pz, ux, uy, uz, ix, iy, iz, periodic):
    """Optical depth from a point inside the medium along a direction until it leaves."""
    return march(grid, px, py, pz, ux, uy, uz, ix, iy, iz, INF, periodic)[7]


@njit(cache=True, _nrt=False)
def locate_point(grid, px, py, pz, ux, uy, uz):
    """Voxel of a point inside (or on the surface of) the box, for a ray along (ux, uy, uz)."""
    return (
        locate(grid.x_edges, px, ux),
        locate(grid.y_edges, py, uy),
        locate(grid.z_edges, pz, uz),
    )


@njit(cache=True, _nrt=False)
def wrap_into_box(grid, px, py):
    """Horizontal position folded into the box, for periodic boundaries."""
    x0 = grid.x_edges[0]
    lx = grid.x_edges[-1] - x0
    y0 = grid.y_edges[0]
    ly = grid.y_edges[-1] - y0
    px = x0 + (px - x0) % lx
    py = y0 + (py - y0) % ly
    return px, py


@njit(cache=True, _nrt=False)
def ray_box_entry(grid, ox, oy, oz, ux, uy, uz, periodic):
    """Distance along a ray from outside the medium to where it enters it, or -1 if never.

    With open boundaries the medium is the box; with periodic boundaries it is the
    horizontally infinite slab between the bottom and top of the box.
    """
    t_near = 0.0
    t_far = INF
    if periodic:
        naxes = 1
    else:
        naxes = 3
    for a in range(3 - naxes, 3):
        if a == 0:
            o, u, lo, hi = ox, ux, grid.x_edges[0], grid.x_edges[-1]
        elif a == 1:
            o, u, lo, hi = oy, uy, grid.y_edges[0], grid.y_edges[-1]
        else:
            o, u, lo, hi = oz, uz, grid.z_edges[0], grid.z_edges[-1]
        if u == 0.0:
            if o < lo or o > hi:
                return -1.0
        else:
            t0 = (lo - o) / u
            t1 = (hi - o) / u
            if t0 > t1:
                t0, t1 = t1, t0
            t_near = max(t_near, t0)
            t_far = min(t_far, t1)
    if t_near > t_far or t_far <= 0.0:
        return -1.0
    return t_near
