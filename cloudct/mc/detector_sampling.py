"""Directional importance sampling: forward scattering directions aimed at the cameras,
backward ones at the sun.

Why: a local estimate is proportional to the phase function at the angle between the
photon's incoming direction and the direction to the camera. A Mie phase function has a
diffraction peak of order 10^3 per sr, so the rare events whose incoming direction happens
to point at a camera carry a pixel (fireflies). This is the detector directional importance
sampling (DDIS) of MYSTIC's VROOM (Buras and Mayer 2011, JQSRT 112, Sec. 3.2).

What: at a forward scattering event in voxel x, the new direction w is drawn from the
mixture density

    q(w) = (1 - a) f(v . w) + a / M  sum_{c sees x} f(d_c . w),

f the voxel's mixture phase function (Eq. 5 of the seed paper), v the incoming direction,
d_c the unit vector from x towards camera c (:func:`~cloudct.mc.cameras.project`: towards
a pinhole, or minus an orthographic camera's view direction, the one direction in which it
sees every point), M the number of cameras whose image holds x and ``a`` the aim fraction
(``CameraArrays.aim_fraction``). The second term is the phase function turned to point at
a camera: it is sampled exactly by the usual sampler about d_c instead of v. It is a
density over directions for either projection, never a delta: an orthographic camera sees
only light along d_c, but the next event's local estimate, not this draw, makes that
connection; the lobe only makes the directions that give it a large phase function
likely. The path weight is multiplied by f(v . w) / q(w) <= 1 / (1 - a), so every
estimate stays unbiased: a direction that now points at a camera often carries a small
weight, and the next event's local estimate, f times that weight, is bounded by about
f(v . w) M / a instead of the peak of f. Where no camera sees x, q = f and nothing changes.

Gradients: the path-space integrand is unchanged, only the sampling density is new, so the
score function of a path (seed paper Eq. 49) keeps its terms and the weight f / q is a
constant factor of the estimate. Path recycling keeps the reference factor f / q of each
stored vertex (:mod:`cloudct.recycling.record_kernels`).

With ``aim_fraction = 0`` no random number is drawn beyond the plain sampler's, so the
paths, and the images for a seed, are exactly those of the plain forward estimator.

The backward estimator's mirror image (:mod:`cloudct.mc.backward`): its next-event estimate
at a vertex carries f(s . u), s the unit vector towards the sun and u the direction the
path arrived along, a diffraction peak where the path happened to travel towards the sun.
A backward scattering event draws its new direction w from

    q_s(w) = (1 - a_s) f(v . w) + a_s f(s . w),

one lobe about the sun (``SunArrays.aim_fraction`` a_s), with the weight f(v . w) / q_s(w)
<= 1 / (1 - a_s); the next vertex's next-event estimate is then bounded by about
f(v . w) / a_s. The combined estimator (:mod:`cloudct.mc.combined`) evaluates both
weights, f / q and f / q_s, along the paths of either estimator.
"""

from __future__ import annotations

from numba import njit

from cloudct.mc.cameras import project
from cloudct.mc.events import scatter
from cloudct.mc.random import uniform
from cloudct.physics.mixing import mixture_phase_function

#: Default share of forward scattering events that aim their new direction at a camera.
DEFAULT_AIM_FRACTION = 0.1


@njit(cache=True, inline="always")
def aim_factor(f, lobes, count, a):
    """f / q with q = (1 - a) f + a ``lobes`` / ``count`` (the aimed lobes' densities at the
    drawn direction, summed over ``count`` lobes); 1 without lobes or aiming, 0 where q is 0
    (a direction outside the support of every component: never drawn)."""
    if count == 0 or a <= 0.0:
        return 1.0
    q = (1.0 - a) * f + a * lobes / count
    return f / q if q > 0.0 else 0.0


@njit(cache=True)
def aimed_weight(grid, bank, cams, ix, iy, iz, px, py, pz, vx, vy, vz, wx, wy, wz):
    """f(v . w) / q(w) of a direction w leaving a scattering event at (px, py, pz) in voxel
    (ix, iy, iz) with incoming direction v (see the module documentation); 1 when aiming is
    off or no camera sees the point."""
    a = cams.aim_fraction
    if a <= 0.0:
        return 1.0
    f = mixture_phase_function(grid, bank, ix, iy, iz, vx * wx + vy * wy + vz * wz)
    aimed, seen = camera_lobes(grid, bank, cams, ix, iy, iz, px, py, pz, wx, wy, wz)
    return aim_factor(f, aimed, seen, a)


@njit(cache=True)
def camera_lobes(grid, bank, cams, ix, iy, iz, px, py, pz, wx, wy, wz):
    """The aimed lobes at direction w of a scattering event at (px, py, pz): sum_c f(d_c .
    w) over the M cameras whose image holds the point, and M (q's second term, module
    documentation; it does not depend on the incoming direction)."""
    aimed = 0.0
    seen = 0
    for view in range(cams.position.shape[0]):
        row, _, cx, cy, cz, _ = project(cams, view, px, py, pz)
        if row >= 0:
            aimed += mixture_phase_function(grid, bank, ix, iy, iz, cx * wx + cy * wy + cz * wz)
            seen += 1
    return aimed, seen


@njit(cache=True)
def scatter_aimed(grid, bank, cams, ix, iy, iz, px, py, pz, ux, uy, uz, state):
    """New direction after a forward scattering event, drawn from q (module documentation),
    and the weight factor f / q: ``(wx, wy, wz, factor, state)``."""
    if cams.aim_fraction <= 0.0:
        wx, wy, wz, state = scatter(grid, bank, ix, iy, iz, ux, uy, uz, state)
        return wx, wy, wz, 1.0, state
    u, state = uniform(state)
    cx, cy, cz = ux, uy, uz
    if u < cams.aim_fraction:
        seen = 0
        for view in range(cams.position.shape[0]):
            if project(cams, view, px, py, pz)[0] >= 0:
                seen += 1
        if seen > 0:
            pick = min(int(u / cams.aim_fraction * seen), seen - 1)
            for view in range(cams.position.shape[0]):
                row, _, dx, dy, dz, _ = project(cams, view, px, py, pz)
                if row >= 0:
                    if pick == 0:
                        cx, cy, cz = dx, dy, dz
                        break
                    pick -= 1
    wx, wy, wz, state = scatter(grid, bank, ix, iy, iz, cx, cy, cz, state)
    factor = aimed_weight(grid, bank, cams, ix, iy, iz, px, py, pz, ux, uy, uz, wx, wy, wz)
    return wx, wy, wz, factor, state


@njit(cache=True)
def sun_aimed_weight(grid, bank, sun, ix, iy, iz, vx, vy, vz, wx, wy, wz):
    """f(v . w) / q_s(w) of a backward direction w leaving a scattering event in voxel (ix,
    iy, iz) with incoming direction v (q_s: the module documentation's lobe about the sun);
    1 when ``sun.aim_fraction`` is 0."""
    a = sun.aim_fraction
    if a <= 0.0:
        return 1.0
    f = mixture_phase_function(grid, bank, ix, iy, iz, vx * wx + vy * wy + vz * wz)
    towards_sun = -(sun.direction[0] * wx + sun.direction[1] * wy + sun.direction[2] * wz)
    return aim_factor(f, mixture_phase_function(grid, bank, ix, iy, iz, towards_sun), 1, a)


@njit(cache=True)
def scatter_sun_aimed(grid, bank, sun, ix, iy, iz, ux, uy, uz, state):
    """New direction after a backward scattering event, drawn from q_s (module
    documentation), and the weight factor f / q_s: ``(wx, wy, wz, factor, state)``."""
    cx, cy, cz = ux, uy, uz  # the lobe's axis: the incoming direction, or the sun's
    if sun.aim_fraction > 0.0:  # (no draw at 0: the plain sampler's random stream)
        u, state = uniform(state)
        if u < sun.aim_fraction:
            cx, cy, cz = -sun.direction[0], -sun.direction[1], -sun.direction[2]
    wx, wy, wz, state = scatter(grid, bank, ix, iy, iz, cx, cy, cz, state)
    factor = sun_aimed_weight(grid, bank, sun, ix, iy, iz, ux, uy, uz, wx, wy, wz)
    return wx, wy, wz, factor, state
