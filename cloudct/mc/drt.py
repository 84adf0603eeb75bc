"""Differential ratio tracking (DRT) gradients of the backward estimator w.r.t. cloud extinction.

For per-pixel residual weights r_d (= w_d (I_d - I_d^measured)) this module estimates

    g_v = sum_d r_d dI_d / d beta_v,

where beta_v is the CLOUD extinction (particle type 1) of voxel v, with the cloud albedo
alpha_c and phase function f_c held fixed (so the cloud scattering coefficient alpha_c beta_v
moves with it) and air (type 0) fixed. I_d is the backward estimator of
:mod:`cloudct.mc.backward`: pixel ray, free flights by exact inversion of the optical depth,
next-event estimation (NEE) to the sun at every vertex, optional Lambertian ground,
medium-independent Russian roulette. The estimator follows Nimier-David et al. (2022),
"Unbiased inverse volumetric rendering with differential trackers" (DRT), Secs. 4.1-4.7,
adapted to this engine as below. It is unbiased for every voxel, including voxels where the
cloud extinction, or even the total extinction, is zero, where a score-function (free-flight)
estimator misses the in-scattering term altogether (DRT Sec. 4.2, "Bias").

Radiance along a ray (DRT Eq. 4 in this engine's terms)
------------------------------------------------------
A ray from x along the unit vector u (backward direction: light travels along -u) meets the
box boundary or the ground at t_s. With T(t) = exp(-int_0^t beta) the transmittance,

    L(x, u) = int_0^t_s T(t) J(x_t, u) dt + T(t_s) L_g,

    J(x, u) = sum_j alpha_j beta_j [ f_j(s.u) T_sun(x) + int f_j(u.w) L(x, w) dw ],

the in-scattered radiance per unit length: the mixture of seed-paper Eqs. (2)-(5) written as
sum_j beta_s^(j) f_j = beta_s f_mix, the collimated sun (irradiance 1 across its rays,
towards-sun unit vector s, T_sun(x) the transmittance from x along s out of the medium) and
the diffuse radiance L (the sun's own disc is never seen, as in the images).
L_g = A cos(theta0)/pi T_sun + A int cos/pi L is the Lambertian ground. A pixel's value is
the pixel-area average of L over its rays. (DRT's sigma_t alpha L_s is J; its L_e is 0.)

Derivative w.r.t. beta_v (DRT Eqs. 5-7)
---------------------------------------
With 1_v(x) the indicator of voxel v and len_v(a, b) the length of the chord a-b inside v,
and the albedos and phase functions fixed, d(sum_j alpha_j beta_j f_j)/dbeta_v =
alpha_c f_c 1_v (dbeta/dbeta_v = 1_v), so dL/dbeta_v has three kinds of terms:

(1a) in-scattering, Eq. (5): int_0^t_s T(t) 1_v(x_t) K(x_t, u) dt with

         K(x, u) = alpha_c [ f_c(s.u) T_sun(x) + int f_c(u.w) L(x, w) dw ]

     over the WHOLE ray to t_s, also where beta = 0: the term a score function (a
     free-flight estimator) cannot sample there;
(a)  attenuation, Eq. (6): -len_v(0, t) T(t) J(t) along the ray, -len_v(0, t_s) T(t_s) L_g
     for the ground (second row of Eq. 6), and inside J the NEE's own attenuation
     -len_v(x, sun) alpha_j beta_j f_j(s.u) T_sun(x);
(1b) recursion, Eq. (7): T sum_j alpha_j beta_j int f_j dL/dbeta_v and the ground's
     A int cos/pi dL/dbeta_v (the ground itself does not depend on beta: Eq. (9) with
     L_e = 0), i.e. the same three kinds of terms further along the path.

Estimators
----------
A sample traces one backward path (vertices k = 1..n; segment j runs from vertex j-1, or the
box entry point for j = 1, to vertex j or out of the medium) with throughput Theta_j on
segment j (product of the effective albedos, ground albedos and roulette factors before it)
and NEE contributions E_k. I_hat = sum_k E_k. The path is traced twice with the same random
stream, like path replay backpropagation (DRT Sec. 3.2, steps II and III): pass 1 gives
R = sum_k E_k, pass 2 replays the identical path and, knowing every suffix
S_j = sum_{k >= j} E_k = R - (prefix sum), deposits in linear time and constant memory:

(a)  segment j: -r S_j len_v(segment j) (free-flight estimator of the transmittance
     gradients, DRT Eq. 10; for a segment ending on the ground or leaving the medium this is
     the second row of Eq. 6), and at every vertex k: -r E_k len_v(NEE ray to the sun).
     Both through :func:`~cloudct.mc.traversal.march` with its ``lengths`` deposit.
(1a) free-flight (DT) part, DRT Eq. (8) first summand, at each scattering vertex x_k in
     voxel v_k, sampled with density beta T by the free flight, MIS-weighted by w_DT(x_k):

         r w_DT alpha_c [ Theta_k f_c(s.u) T_sun / beta
                          + f_c(mu_k) S_{k+1} / (sum_j alpha_j beta_j f_j(mu_k)) ]

     where mu_k is the sampled scattering cosine (density f_mix(mu_k)) and S_{k+1}, the
     suffix after vertex k, equals Theta_k alpha_eff RR_k L_hat(x_k, u_k); the division by
     alpha_eff cancels into the mixture kernel, so no 0 * inf appears.
(1a) DRT part, Eqs. (13), (16): the in-scattering integral of one ray sampled with density
     T(t) / C, C = int_0^t_s T dt (Eq. 15), with the sample weight C (Eqs. 19-20):

         r (W / Theta_j) Theta_j C w_DRT(x') alpha_c(x')
             [ f_c(s.u) T_sun(x') + L_hat(x', w') ],   w' ~ f_c(u . w'),

     deposited into the voxel of x'. The diffuse part is estimated by a new backward path
     from x' in a direction w' drawn from the CLOUD phase function of that voxel (it exists
     on every voxel, whatever its cloud extinction); it needs only the radiance, not its
     derivative. Linear time (Sec. 4.7): one segment j per path is chosen by weighted
     reservoir sampling with weights Theta_j; W = sum_j Theta_j over the path's segments
     is the inverse selection probability times Theta_j. The reservoir, the transmittance
     sample and the recursive path draw from a second stream, so given the path they are
     independent of it and the selection is unbiased.
(1b) recursion: nothing to add; the terms above at later vertices carry Theta.

Transmittance sampling: exact "ratio tracking" voxel by voxel
-------------------------------------------------------------
The paper's ratio tracker builds a stochastic piecewise-constant approximation f_RT of T
from majorant steps (Eq. 19) because its media are arbitrary functions of position. Here
the extinction is piecewise constant, so along a ray the exact transmittance is piecewise
exponential and every voxel piece i (entry T_i, length d_i, extinction beta_i) has the exact
area a_i = T_i (1 - exp(-beta_i d_i)) / beta_i (a_i = T_i d_i where beta_i = 0). The walk
proposes each piece to a weighted reservoir with weight a_i (Listing 1 with the exact area
instead of Tr * dt) and then samples the distance inside the chosen piece exactly
proportional to exp(-beta_i t). This is DRT's residual ratio tracking (Sec. 4.5 and its
Appendix B) with the control extinction equal to the true piecewise-constant extinction:
the tracking is T itself, the weight sum_i a_i = C is exact (zero variance), t' has density
exactly T / C, the cost is one walk to the exit (the price of one NEE transmittance, with no
majorant to choose), and empty voxels are sampled like any other.

Under the power law (:mod:`cloudct.physics.transmittance`)
----------------------------------------------------------
The free flights sample the collision density T_pdf = beta phi(u) = beta h T (h the hazard)
instead of beta T, and its derivative w.r.t. beta_v is 1_v phi(u) - c ds/dbeta_v T_pdf:

(a)  the attenuation deposits of a segment and of an NEE ray are ``march``'s with the
     walk's ``scale`` (c Q_n for a flight ending in a collision, Q_n otherwise), each
     walked first for it, as in the score function (1 for the exponential: unchanged);
(1a) free-flight part: phi K / (beta phi) = K / beta, unchanged;
(1a) DRT part: the in-scattering integrand is phi K = h T K, so the point drawn with
     density T / C carries the weight C h(x'). Inside a voxel of mode m entered at
     equivalent depth s, T(t) / T_in = (1 + kappa t)^(-1/m), kappa = m beta e^(-m s), whose
     integral and its inverse are closed forms (:func:`power_law_piece`): C stays exact.

Multiple importance sampling (Sec. 4.6, Eqs. 21-22)
---------------------------------------------------
Power heuristic of p_DT = beta T against p_DRT = T / C with C replaced by a fixed length
ell (the height of the box, the order of C where the weights matter, i.e. in thin media;
using the exact C_j would need a walk per segment, and the selection-dependent factor
W / Theta_j cannot be used, since W depends on the sampled vertex):

    w_DT(x) = (beta ell)^2 / ((beta ell)^2 + 1),   w_DRT(x) = 1 - w_DT(x),

and w_DT = 0 where nothing scatters (beta_s = 0 < beta, a purely absorbing voxel), where the
free-flight estimate would need 0 * inf: the weights only need to sum to one at every point,
and there the DRT sample carries the whole in-scattering term. Where beta = 0, w_DRT = 1.

Random streams: domain :data:`~cloudct.mc.random.DOMAIN_DRT`; pixel sample ``index`` uses
stream 2 * index for the path (passes 1 and 2) and 2 * index + 1 for the reservoir, the
transmittance sample and the recursive path. The paths are therefore uncorrelated with the
images of :mod:`cloudct.mc.backward` for the same seed, as an unbiased loss gradient needs
(DRT footnote 1).
"""

from __future__ import annotations

import math

from numba import njit

from cloudct.mc.accumulate import add_to, inline_on_cpu
from cloudct.mc.backward import camera_ray_entry
from cloudct.mc.events import lambertian_bounce, russian_roulette, scatter
from cloudct.mc.random import DOMAIN_DRT, stream_start, uniform
from cloudct.mc.traversal import (
    BOTTOM,
    INF,
    INSIDE,
    LEFT,
    cross_boundary,
    march,
    next_face,
    optical_depth_to_exit,
    step_index,
)
from cloudct.physics.mixing import (
    cell_phase_function,
    effective_albedo,
    mixture_phase_function,
    sample_cell_phase_cosine,
    scattering_coefficient,
    total_extinction,
)
from cloudct.physics.phase import scatter_direction
from cloudct.physics.transmittance import EXPONENTIAL, GAMMA

INV_PI = 1.0 / math.pi
TWO_PI = 2.0 * math.pi
CLOUD = 1  # particle type whose extinction is differentiated


@njit(cache=True, inline="always")
def power_law_piece(kappa, mode, length):
    """int_0^d (1 + kappa t)^(-1/m) dt / d and log1p(kappa d): the mean relative
    transmittance T(t) / T_in over a voxel piece of length d = ``length`` under the power law
    of mode m (kappa = m beta h_in, module docstring), written with expm1 and log1p so that
    it stays exact as m -> 1 (the integral's logarithm) and as kappa d -> 0."""
    y = math.log1p(kappa * length)
    x = (1.0 - 1.0 / mode) * y
    mean = (math.expm1(x) / x if x != 0.0 else 1.0) * y / (kappa * length)
    return mean, y


@njit(cache=True, _nrt=False)
def sample_transmittance(grid, px, py, pz, ux, uy, uz, ix, iy, iz, periodic, state):
    """A point on the ray from (px, py, pz) along (ux, uy, uz), drawn with density T(t) / C.

    The ray runs to where it leaves the medium (or reaches the bottom); C = int T dt over it.
    Each voxel piece is proposed to a weighted reservoir with its exact area int T dt
    (T_in (1 - exp(-beta d)) / beta for the exponential), then the distance inside the chosen
    piece is drawn proportional to T (exact ratio tracking, see the module docstring; under
    the power law, the section on it).

    Returns ``(C, h, qx, qy, qz, qix, qiy, qiz, state)``; h is the transmittance's hazard
    -f'(u) / f(u) at the point (1 for the exponential), C = 0 (no point) for an empty chord.
    """
    family = grid.transmittance_family[0]
    trans = 1.0
    depth = 0.0  # the equivalent optical depth -log T (non-exponential only)
    total = 0.0
    rx = ry = rz = 0.0
    rix = riy = riz = -1
    rbeta = 0.0
    rlen = 0.0
    rkappa = 0.0  # the chosen piece's kappa (power law), 0 where it is exponential
    rmode = 0.0
    rhazard = 1.0
    xe = grid.x_edges
    ye = grid.y_edges
    ze = grid.z_edges
    nx = xe.size - 1
    ny = ye.size - 1
    nz = ze.size - 1
    while True:
        t, axis = next_face(xe, ye, ze, px, py, pz, ux, uy, uz, ix, iy, iz)
        beta = total_extinction(grid, ix, iy, iz)
        x = beta * t
        kappa = 0.0
        mode = 0.0
        hazard = 1.0  # h at the piece's entry, e^(-m s) under the power law
        if family != EXPONENTIAL:
            mode = grid.transmittance_mode[ix, iy, iz]
            if family == GAMMA and mode > 0.0:
                hazard = math.exp(-mode * depth)
                kappa = mode * beta * hazard
        growth = x  # of the equivalent depth across the piece (Eqs. 7-8)
        if kappa > 0.0:
            mean, y = power_law_piece(kappa, mode, t)
            area = trans * t * mean
            growth = y / mode  # depth_step's, from the same log1p(kappa t)
        else:
            area = trans * t * (-math.expm1(-x) / x) if x > 0.0 else trans * t
        if area > 0.0:
            total += area
            u, state = uniform(state)
            if u * total < area:
                rx, ry, rz = px, py, pz
                rix, riy, riz = ix, iy, iz
                rbeta = beta
                rlen = t
                rkappa = kappa
                rmode = mode
                rhazard = hazard
        if family == EXPONENTIAL:
            trans *= math.exp(-x)
        else:  # (the linear mix reaches here only at gamma = 1, the exponential)
            depth += growth
            trans = math.exp(-depth)
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
                break
    if rix < 0:
        return 0.0, 1.0, 0.0, 0.0, 0.0, 0, 0, 0, state
    u, state = uniform(state)
    hazard = rhazard  # constant along a piece without extinction
    if rkappa > 0.0:  # invert int_0^s (1 + kappa t)^(-1/m) dt = u x the piece's area
        a = 1.0 - 1.0 / rmode
        _, y = power_law_piece(rkappa, rmode, rlen)
        y = math.log1p(u * math.expm1(a * y)) / a if a != 0.0 else u * y
        s = math.expm1(y) / rkappa
        hazard = rhazard / (1.0 + rkappa * min(s, rlen))
    else:
        x = rbeta * rlen
        if x > 0.0:
            s = -math.log1p(u * math.expm1(-x)) / rbeta
        else:
            s = u * rlen
    s = min(s, rlen)
    return total, hazard, rx + s * ux, ry + s * uy, rz + s * uz, rix, riy, riz, state


@njit(cache=True, _nrt=False)
def free_flight_mis_weight(grid, ix, iy, iz, length):
    """w_DT of the module docstring: (beta ell)^2 / ((beta ell)^2 + 1), 0 where beta_s = 0."""
    if scattering_coefficient(grid, ix, iy, iz) <= 0.0:
        return 0.0
    x = total_extinction(grid, ix, iy, iz) * length
    x *= x
    return x / (x + 1.0)


@njit(cache=True, _nrt=False)
def scattering_kernel(grid, bank, ix, iy, iz, mu):
    """sum_j alpha_j beta_j f_j(mu) = beta_s f_mix(mu) [1/(km sr)]."""
    value = 0.0
    for j in range(grid.extinction.shape[0]):
        bs = grid.albedo[j, ix, iy, iz] * grid.extinction[j, ix, iy, iz]
        if bs > 0.0:
            value += bs * cell_phase_function(grid, bank, j, ix, iy, iz, mu)
    return value


@njit(cache=True, _nrt=False)
def trace_path(
    grid, bank, sun, periodic, ground_albedo, rr_depth, rr_survival, px, py, pz, ix, iy, iz,
    ux, uy, uz, state, replay, total, residual, gradient, side, mis_length,
):
    """A backward path from (px, py, pz) in voxel (ix, iy, iz) along (ux, uy, uz).

    Pass 1 (``replay`` False) returns its radiance estimate R = sum_k E_k (also used for the
    recursive paths of the DRT samples). Pass 2 (``replay`` True, same ``state``, ``total``
    = R of pass 1) replays the identical path and adds to ``gradient`` the attenuation terms
    and the MIS-weighted free-flight in-scattering terms, all times ``residual``, and runs the
    segment reservoir on the ``side`` stream.

    Returns ``(radiance, vertices, state, side, W, found, rx, ry, rz, rix, riy, riz, rux,
    ruy, ruz)``: the reservoir's weight sum W = sum_j Theta_j and the chosen segment's start
    point, voxel and direction (``found`` False when no segment had throughput).
    """
    sx, sy, sz = -sun.direction[0], -sun.direction[1], -sun.direction[2]  # towards the sun
    family = grid.transmittance_family[0]
    radiance = 0.0  # prefix sum of the E_k
    throughput = 1.0
    depth = 0
    res_w = 0.0
    found = False
    rx = ry = rz = 0.0
    rix = riy = riz = 0
    rux = ruy = ruz = 0.0
    while True:
        u, state = uniform(state)
        if replay:
            # Sec. 4.7: one segment per path, reservoir proportional to the throughput
            res_w += throughput
            v, side = uniform(side)
            if v * res_w < throughput:
                found = True
                rx, ry, rz, rix, riy, riz, rux, ruy, ruz = px, py, pz, ix, iy, iz, ux, uy, uz
            # Eq. (10) / Eq. (6): every later contribution is attenuated by this segment;
            # under the power law the segment is walked first for its deposits' scale
            weight = -residual * (total - radiance)
            if family != EXPONENTIAL and weight != 0.0:
                weight *= march(
                    grid, px, py, pz, ux, uy, uz, ix, iy, iz, -math.log(u), periodic
                )[9]
            status, px, py, pz, ix, iy, iz, _, _, _ = march(
                grid, px, py, pz, ux, uy, uz, ix, iy, iz, -math.log(u), periodic, gradient,
                weight,
            )
        else:
            status, px, py, pz, ix, iy, iz, _, _, _ = march(
                grid, px, py, pz, ux, uy, uz, ix, iy, iz, -math.log(u), periodic
            )
        if status == LEFT:
            break
        if status == BOTTOM and ground_albedo <= 0.0:
            break
        sun_walk = march(grid, px, py, pz, sx, sy, sz, ix, iy, iz, INF, periodic)
        t_sun = math.exp(-sun_walk[7])
        sun_scale = sun_walk[9]  # of the NEE attenuation's deposits (1: exponential)
        if status == BOTTOM:
            e = throughput * ground_albedo * sz * INV_PI * t_sun
            radiance += e
            if replay and e != 0.0:
                march(
                    grid, px, py, pz, sx, sy, sz, ix, iy, iz, INF, periodic, gradient,
                    -residual * e * sun_scale,
                )
            throughput *= ground_albedo
            ux, uy, uz, state = lambertian_bounce(state)
        else:
            albedo = effective_albedo(grid, ix, iy, iz)
            mu_sun = sx * ux + sy * uy + sz * uz
            e = throughput * albedo * mixture_phase_function(grid, bank, ix, iy, iz, mu_sun) * t_sun
            radiance += e
            theta = throughput
            throughput *= albedo
            nux, nuy, nuz, state = scatter(grid, bank, ix, iy, iz, ux, uy, uz, state)
            if replay:
                if e != 0.0:  # NEE attenuation
                    march(
                        grid, px, py, pz, sx, sy, sz, ix, iy, iz, INF, periodic, gradient,
                        -residual * e * sun_scale,
                    )
                w_dt = free_flight_mis_weight(grid, ix, iy, iz, mis_length)
                alpha_c = grid.albedo[CLOUD, ix, iy, iz]
                if w_dt > 0.0 and alpha_c > 0.0:
                    # Eq. (8), first summand, MIS-weighted: sun part + diffuse part, whose
                    # continuation estimate is the suffix after this vertex
                    beta = total_extinction(grid, ix, iy, iz)
                    value = (theta * cell_phase_function(grid, bank, CLOUD, ix, iy, iz, mu_sun)
                             * t_sun / beta)
                    suffix = total - radiance
                    if suffix != 0.0:
                        mu = min(max(ux * nux + uy * nuy + uz * nuz, -1.0), 1.0)
                        kernel = scattering_kernel(grid, bank, ix, iy, iz, mu)
                        if kernel > 0.0:
                            value += (cell_phase_function(grid, bank, CLOUD, ix, iy, iz, mu)
                                      * suffix / kernel)
                    add_to(gradient, ix, iy, iz, residual * w_dt * alpha_c * value)
            ux, uy, uz = nux, nuy, nuz
        depth += 1
        factor, state = russian_roulette(depth, rr_depth, rr_survival, state)
        if factor == 0.0:
            break
        throughput *= factor
        if throughput == 0.0:
            break
    return (
        radiance, depth, state, side, res_w, found, rx, ry, rz, rix, riy, riz, rux, ruy, ruz,
    )


@njit(cache=True, _nrt=False)
def cloud_sun_term(grid, bank, sun, periodic, px, py, pz, ix, iy, iz, ux, uy, uz):
    """f_c(s.u) T_sun(x): the sunlight a unit of cloud scattering coefficient at x (voxel
    (ix, iy, iz)) sends back along -u, per unit albedo (the sun part of K in the module
    docstring)."""
    sx, sy, sz = -sun.direction[0], -sun.direction[1], -sun.direction[2]
    tau_sun = optical_depth_to_exit(grid, px, py, pz, sx, sy, sz, ix, iy, iz, periodic)
    return (cell_phase_function(grid, bank, CLOUD, ix, iy, iz, sx * ux + sy * uy + sz * uz)
            * math.exp(-tau_sun))


@njit(cache=True, _nrt=False)
def cloud_diffuse_term(
    grid, bank, sun, periodic, ground_albedo, rr_depth, rr_survival, px, py, pz, ix, iy, iz,
    ux, uy, uz, state, gradient, mis_length,
):
    """One-sample estimate of int f_c(u.w) L(x, w) dw (the diffuse part of K in the module
    docstring): a new backward path from x in a direction w drawn from the cloud phase
    function of voxel (ix, iy, iz), which exists on every voxel whatever its cloud
    extinction. Only the radiance is needed, not its derivative (``gradient`` and
    ``mis_length`` are not written).

    Returns ``(radiance, vertices, state)``.
    """
    u, state = uniform(state)
    mu = sample_cell_phase_cosine(grid, bank, CLOUD, ix, iy, iz, u)
    u, state = uniform(state)
    wx, wy, wz = scatter_direction(ux, uy, uz, mu, TWO_PI * u)
    radiance, vertices, state, _, _, _, _, _, _, _, _, _, _, _, _ = trace_path(
        grid, bank, sun, periodic, ground_albedo, rr_depth, rr_survival, px, py, pz, ix, iy,
        iz, wx, wy, wz, state, False, 0.0, 0.0, gradient, state, mis_length,
    )
    return radiance, vertices, state


@njit(cache=True, _nrt=False, inline=inline_on_cpu)
def primal_pass(
    grid, bank, cams, sun, periodic, ground_albedo, rr_depth, rr_survival, seed, domain, index,
    view, row, col, gradient, mis_length,
):
    """The start of a camera-side gradient sample (DRT, sample matching): the streams of
    sample ``index`` in ``domain`` (2 index: the path, 2 index + 1: the side draws), the
    pixel ray's entry into the medium and pass 1, the path's radiance estimate R = sum_k E_k.

    Returns ``(hit, R, vertices, state, side, px, py, pz, ix, iy, iz, ux, uy, uz)`` with
    ``state`` at the path's start, for pass 2 to replay it.
    """
    state = stream_start(seed, domain, 2 * index)
    side = stream_start(seed, domain, 2 * index + 1)
    hit, _, px, py, pz, ux, uy, uz, ix, iy, iz, state = camera_ray_entry(
        grid, cams, periodic, view, row, col, state
    )
    total = 0.0
    vertices = 0
    if hit:
        total, vertices, _, _, _, _, _, _, _, _, _, _, _, _, _ = trace_path(
            grid, bank, sun, periodic, ground_albedo, rr_depth, rr_survival, px, py, pz, ix,
            iy, iz, ux, uy, uz, state, False, 0.0, 0.0, gradient, side, mis_length,
        )
    return hit, total, vertices, state, side, px, py, pz, ix, iy, iz, ux, uy, uz


@njit(cache=True, _nrt=False)
def drt_pixel_sample(
    grid, bank, cams, sun, periodic, ground_albedo, rr_depth, rr_survival, seed, index, view,
    row, col, residual, gradient, mis_length,
):
    """Add one pixel sample's residual-weighted gradient estimate to ``gradient``.

    Returns the number of path vertices traced (the primal path once, the DRT path).
    """
    hit, total, vertices, state, side, px, py, pz, ix, iy, iz, ux, uy, uz = primal_pass(
        grid, bank, cams, sun, periodic, ground_albedo, rr_depth, rr_survival, seed,
        DOMAIN_DRT, index, view, row, col, gradient, mis_length,
    )
    if not hit:
        return 0
    # pass 2: replay with deposits, segment reservoir on the side stream
    (_, _, _, side, res_w, found, rx, ry, rz, rix, riy, riz, rux, ruy, ruz) = trace_path(
        grid, bank, sun, periodic, ground_albedo, rr_depth, rr_survival, px, py, pz, ix, iy,
        iz, ux, uy, uz, state, True, total, residual, gradient, side, mis_length,
    )
    if not found:
        return vertices
    # DRT in-scattering sample on the chosen segment, Eqs. (13), (16), (19)
    c, hazard, qx, qy, qz, qix, qiy, qiz, side = sample_transmittance(
        grid, rx, ry, rz, rux, ruy, ruz, rix, riy, riz, periodic, side
    )
    if c <= 0.0:
        return vertices
    w_drt = 1.0 - free_flight_mis_weight(grid, qix, qiy, qiz, mis_length)
    alpha_c = grid.albedo[CLOUD, qix, qiy, qiz]
    if w_drt <= 0.0 or alpha_c <= 0.0:
        return vertices
    value = cloud_sun_term(grid, bank, sun, periodic, qx, qy, qz, qix, qiy, qiz, rux, ruy, ruz)
    diffuse, more, side = cloud_diffuse_term(
        grid, bank, sun, periodic, ground_albedo, rr_depth, rr_survival, qx, qy, qz, qix, qiy,
        qiz, rux, ruy, ruz, side, gradient, mis_length,
    )
    value += diffuse
    # the in-scattering's density along the ray is the collision density per unit
    # extinction, T h (power law section of the module docstring; h = 1: exponential)
    add_to(gradient, qix, qiy, qiz, residual * res_w * c * hazard * w_drt * alpha_c * value)
    return vertices + more
