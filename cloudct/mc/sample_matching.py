"""Sample-matching gradients of the backward estimator w.r.t. cloud extinction.

Yu et al. (2025), "Sample matching" (``shared/papers/sample_matching_yu_2025.txt``), Secs.
4-5, in this engine's terms. It estimates the same quantity as :mod:`cloudct.mc.drt`,

    g_v = sum_d r_d dI_d / d beta_v    (beta_v: cloud extinction of voxel v),

with the backward estimator of :mod:`cloudct.mc.backward` (pixel ray, exact free flights,
next-event estimation (NEE) to the sun, optional Lambertian ground), and the notation of the
DRT module's docstring: a ray from x along u (light travels along -u) meets the boundary or
the ground at t_s, T(t) is its transmittance, J the in-scattered radiance per unit length,
K(x, u) = alpha_c [f_c(s.u) T_sun(x) + int f_c(u.w) L(x, w) dw] the in-scattering that a
unit of cloud extinction at x adds, and L_g the ground's radiance.

One ray segment, matched (paper Eqs. 21-22)
-------------------------------------------
The derivative of L(x, u) through this ray's own extinction has a scattering part (DRT's
Eq. 5) and a transmittance part (Eq. 6):

    int_0^t_s T(s) 1_v(s) K(s) ds  -  int_0^t_s 1_v(s) [int_s^t_s T J dt + T(t_s) L_g] ds.

The two evaluate d beta / d beta_v = 1_v at different points (the scattering part at s, the
transmittance part at every point before the vertex t). With int_s^t_s T J dt + T(t_s) L_g
= T(s) L(x_s, u), both become one integral over the segment,

    int_0^t_s 1_v(s) T(s) [K(x_s, u) - L(x_s, u)] ds,

and with T(s) = int_s^t_s beta T dt + T(t_s) (Fubini, the paper's Eq. 22) it is the
expectation over the free flight t (density beta T, or t = t_s with probability T(t_s)) of

    int_0^t 1_v(y) [K(y) - X(t)] dy,   X(t) = J(t) / beta(t) at a scattering vertex,
                                               L_g at the ground, 0 where the ray leaves,

which is estimated at probe points y on the sampled segment: the scattering and the
transmittance parts of d beta at y enter with opposite signs at the SAME point, so their
noise cancels where K and X are alike (paper Sec. 4; its "light component", Eq. 36, is the
segment that leaves the medium or ends on the ground). Given the path, X(t) is the suffix
S_j / Theta_{j-1} that the primal path already estimates (the NEE at the vertex plus the
rest of the path, as in DRT's path replay), so no transmittance ratio is needed: both
parts use their own suffix paths (the paper's dual-suffix-path variant, Eq. 35).

Probes and the direct/indirect split (paper Sec. 5.3)
-----------------------------------------------------
Segment j of the path (from vertex j-1, or the box entry, along u; throughput Theta_{j-1};
length t_j) gets Lambda stratified probes y_i = (i + xi_i) / Lambda x t_j, i = 0 .. Lambda-1.
K and X split into a direct (sun) and an indirect part:

- direct, at every probe: r (t_j / Lambda) [Theta_{j-1} alpha_c(y_i) f_c(s.u) T_sun(y_i)
  - E_j] into the voxel of y_i, where E_j is the NEE contribution of vertex j (0 where the
  ray leaves). One sun connection per probe.
- indirect, at one probe y* drawn uniformly among the Lambda (so uniform on the segment):
  the attenuation partner -r t_j (S_j - E_j) into the voxel of y*, S_j - E_j being the
  primal path's estimate of everything after vertex j's NEE; and the in-scattering
  r t_j Theta_{j-1} alpha_c(y*) L_hat(y*, w'), with w' drawn from the cloud phase function at
  y* and L_hat a new backward path's radiance (:func:`cloudct.mc.drt.cloud_diffuse_term`).
  - quadratic variant: a new path on every segment;
  - linear variant (default): the attenuation partner on every segment (it costs
    nothing), the new path on one segment per path, chosen by weighted reservoir sampling
    with weights w_j = Theta_{j-1} t_j alpha_c(y*_j) (the in-scattering's share of the
    integral) and divided by its selection probability w_j / W, W = sum_j w_j:
    r W L_hat(y*, w'). (The paper's linear variant puts the whole pair on the chosen
    segment.)

Free-flight share of the indirect in-scattering (``mis``, default)
-----------------------------------------------------------------
A new path from y* is independent of the primal path's suffix S_j - E_j, so the indirect
pair's two terms do not cancel, they add their variances: in a dense cloud, where many short
segments cross a voxel, this is most of the gradient's noise (measured on the single cloud:
docs/validation.md). There the free-flight vertices estimate the same in-scattering better,
from the primal path's own continuation (DRT's Eq. 8, diffuse part): at scattering vertex
x_j, r w_ff alpha_c f_c(mu_j) (S_j - E_j) / (sum_i alpha_i beta_i f_i(mu_j)), mu_j the sampled
scattering cosine, which correlates with the attenuation partners of the segments around
it. With ``mis`` the two share the in-scattering through DRT's MIS weight w_ff(x) =
(beta ell)^2 / ((beta ell)^2 + 1) (:func:`cloudct.mc.drt.free_flight_mis_weight`; 0 where
nothing scatters): the vertices take w_ff of it, the probes 1 - w_ff (their weight w_j and
deposit carry the factor). Both are unbiased for the in-scattering, and weights that sum to
one at every point keep the sum unbiased; without ``mis`` the probes take it all (the
paper's dual suffix paths).

The remaining derivative terms are those of DRT and are deposited the same way: the
attenuation of each NEE connection to the sun, -r E_j len_v(x_j -> sun) (no matching partner:
the collimated sun scatters out of its beam, never back into it), and the recursion, which
the later segments carry through their throughput. Sample matching needs no MIS: its probes
cover every point of every segment, voxels without extinction included, so it is unbiased
everywhere, like DRT.

Random streams: domain :data:`~cloudct.mc.random.DOMAIN_SAMPLE_MATCHING`; pixel sample
``index`` uses stream 2 * index for the path (both passes) and 2 * index + 1 for the probes,
the reservoir and the indirect paths, independent of the path given the path.
"""

from __future__ import annotations

import math

from numba import njit

from cloudct.mc.accumulate import add_to
from cloudct.mc.drt import (
    CLOUD,
    INV_PI,
    cloud_diffuse_term,
    cloud_sun_term,
    free_flight_mis_weight,
    primal_pass,
    scattering_kernel,
)
from cloudct.mc.events import lambertian_bounce, russian_roulette, scatter
from cloudct.mc.random import DOMAIN_SAMPLE_MATCHING, uniform
from cloudct.mc.traversal import BOTTOM, INF, LEFT, march, optical_depth_to_exit
from cloudct.physics.mixing import cell_phase_function, effective_albedo, mixture_phase_function


@njit(cache=True, _nrt=False)
def match_segments(
    grid, bank, sun, periodic, ground_albedo, rr_depth, rr_survival, px, py, pz, ix, iy, iz,
    ux, uy, uz, state, side, total, residual, gradient, probes, quadratic, mis, mis_length,
):
    """Pass 2 of a sample: replay the backward path of ``state`` (pass 1's radiance
    ``total``) and add the matched probe terms and the NEE attenuation terms (module
    docstring), times ``residual``, to ``gradient``.

    Returns ``(vertices, side, W, found, yx, yy, yz, yix, yiy, yiz, yux, yuy, yuz)``: the
    vertices of the indirect paths traced (quadratic), and for the linear variant the
    reservoir's weight sum W, whether a segment was chosen, and its probe y*, voxel and
    direction.
    """
    sx, sy, sz = -sun.direction[0], -sun.direction[1], -sun.direction[2]  # towards the sun
    radiance = 0.0  # prefix sum of the NEE contributions E_k
    throughput = 1.0
    depth = 0
    traced = 0
    res_w = 0.0
    found = False
    cx = cy = cz = 0.0
    cix = ciy = ciz = 0
    cux = cuy = cuz = 0.0
    while True:
        u, state = uniform(state)
        status, qx, qy, qz, qix, qiy, qiz, _, length, _ = march(
            grid, px, py, pz, ux, uy, uz, ix, iy, iz, -math.log(u), periodic
        )
        leaves = status == LEFT or (status == BOTTOM and ground_albedo <= 0.0)
        e = 0.0  # E_j, the NEE at the segment's vertex
        albedo = 0.0
        if not leaves:
            tau_sun = optical_depth_to_exit(grid, qx, qy, qz, sx, sy, sz, qix, qiy, qiz, periodic)
            t_sun = math.exp(-tau_sun)
            if status == BOTTOM:
                e = throughput * ground_albedo * sz * INV_PI * t_sun
            else:
                albedo = effective_albedo(grid, qix, qiy, qiz)
                mu_sun = sx * ux + sy * uy + sz * uz
                e = throughput * albedo * mixture_phase_function(
                    grid, bank, qix, qiy, qiz, mu_sun
                ) * t_sun
        indirect = total - radiance - e  # S_j - E_j
        # Lambda stratified probes along the segment, walked in order
        v, side = uniform(side)
        pick = min(int(v * probes), probes - 1)
        yx, yy, yz, yix, yiy, yiz = px, py, pz, ix, iy, iz
        walked = 0.0
        bx, by, bz = px, py, pz
        bix, biy, biz = ix, iy, iz
        for i in range(probes):
            v, side = uniform(side)
            target = (i + v) / probes * length
            _, yx, yy, yz, yix, yiy, yiz, _, _, _ = march(
                grid, yx, yy, yz, ux, uy, uz, yix, yiy, yiz, INF, periodic, None, 0.0,
                target - walked,
            )
            walked = target
            alpha_c = grid.albedo[CLOUD, yix, yiy, yiz]
            direct = 0.0
            if alpha_c > 0.0:
                direct = throughput * alpha_c * cloud_sun_term(
                    grid, bank, sun, periodic, yx, yy, yz, yix, yiy, yiz, ux, uy, uz
                )
            add_to(gradient, yix, yiy, yiz, residual * length / probes * (direct - e))
            if i == pick:
                bx, by, bz, bix, biy, biz = yx, yy, yz, yix, yiy, yiz
        # the indirect pair at probe y*: the attenuation partner on every segment (it costs
        # nothing), the in-scattering by a new path, weighted by 1 - w_ff where the
        # free-flight vertices take a share w_ff of it (``mis``)
        add_to(gradient, bix, biy, biz, -residual * length * indirect)
        alpha_c = grid.albedo[CLOUD, bix, biy, biz]
        if mis:
            alpha_c *= 1.0 - free_flight_mis_weight(grid, bix, biy, biz, mis_length)
        if quadratic:
            if alpha_c > 0.0:
                diffuse, more, side = cloud_diffuse_term(
                    grid, bank, sun, periodic, ground_albedo, rr_depth, rr_survival, bx, by,
                    bz, bix, biy, biz, ux, uy, uz, side, gradient, mis_length,
                )
                traced += more
                add_to(gradient, bix, biy, biz,
                       residual * length * throughput * alpha_c * diffuse)
        else:
            w = throughput * length * alpha_c
            if w > 0.0:
                res_w += w
                v, side = uniform(side)
                if v * res_w < w:
                    found = True
                    cx, cy, cz, cix, ciy, ciz = bx, by, bz, bix, biy, biz
                    cux, cuy, cuz = ux, uy, uz
        if leaves:
            break
        radiance += e
        if e != 0.0:  # the NEE connection's attenuation (DRT Eq. 6, in J)
            march(
                grid, qx, qy, qz, sx, sy, sz, qix, qiy, qiz, INF, periodic, gradient,
                -residual * e,
            )
        px, py, pz, ix, iy, iz = qx, qy, qz, qix, qiy, qiz
        if status == BOTTOM:
            throughput *= ground_albedo
            ux, uy, uz, state = lambertian_bounce(state)
        else:
            throughput *= albedo
            nux, nuy, nuz, state = scatter(grid, bank, ix, iy, iz, ux, uy, uz, state)
            if mis and indirect != 0.0:
                # the free-flight share of the indirect in-scattering (DRT Eq. 8, diffuse
                # part): the primal path's own continuation, the suffix after this NEE
                w_ff = free_flight_mis_weight(grid, ix, iy, iz, mis_length)
                alpha_c = grid.albedo[CLOUD, ix, iy, iz]
                if w_ff > 0.0 and alpha_c > 0.0:
                    mu = min(max(ux * nux + uy * nuy + uz * nuz, -1.0), 1.0)
                    kernel = scattering_kernel(grid, bank, ix, iy, iz, mu)
                    if kernel > 0.0:
                        add_to(gradient, ix, iy, iz, residual * w_ff * alpha_c
                               * cell_phase_function(grid, bank, CLOUD, ix, iy, iz, mu)
                               * indirect / kernel)
            ux, uy, uz = nux, nuy, nuz
        depth += 1
        factor, state = russian_roulette(depth, rr_depth, rr_survival, state)
        if factor == 0.0:
            break
        throughput *= factor
        if throughput == 0.0:
            break
    return traced, side, res_w, found, cx, cy, cz, cix, ciy, ciz, cux, cuy, cuz


@njit(cache=True, _nrt=False)
def sample_matching_pixel_sample(
    grid, bank, cams, sun, periodic, ground_albedo, rr_depth, rr_survival, seed, index, view,
    row, col, residual, gradient, probes, quadratic, mis, mis_length,
):
    """Add one pixel sample's residual-weighted sample-matching estimate to ``gradient``.

    Returns the number of path vertices traced (the primal path once, the indirect paths).
    """
    hit, total, vertices, state, side, px, py, pz, ix, iy, iz, ux, uy, uz = primal_pass(
        grid, bank, cams, sun, periodic, ground_albedo, rr_depth, rr_survival, seed,
        DOMAIN_SAMPLE_MATCHING, index, view, row, col, gradient, mis_length,
    )
    if not hit:
        return 0
    traced, side, res_w, found, cx, cy, cz, cix, ciy, ciz, cux, cuy, cuz = match_segments(
        grid, bank, sun, periodic, ground_albedo, rr_depth, rr_survival, px, py, pz, ix, iy,
        iz, ux, uy, uz, state, side, total, residual, gradient, probes, quadratic, mis,
        mis_length,
    )
    vertices += traced
    if not found:
        return vertices
    # linear variant: the chosen segment's in-scattering, divided by w_j / W
    diffuse, more, side = cloud_diffuse_term(
        grid, bank, sun, periodic, ground_albedo, rr_depth, rr_survival, cx, cy, cz, cix, ciy,
        ciz, cux, cuy, cuz, side, gradient, mis_length,
    )
    add_to(gradient, cix, ciy, ciz, residual * res_w * diffuse)
    return vertices + more
