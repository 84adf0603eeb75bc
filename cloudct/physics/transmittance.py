"""Transmittance families: exponential, and non-exponential for unresolved sub-grid
variability (Vicini, Jakob and Kaplanyan 2021, "A non-exponential transmittance model for
volumetric scene representations"; its Eqs. 6-9).

A family is a transmittance function f(tau, m) of the optical depth tau, non-increasing,
f(0, m) = 1, with a per-voxel *transmittance mode* m:

- :data:`EXPONENTIAL`: f = exp(-tau); the mode is ignored.
- :data:`LINEAR_MIX` (the paper's Eq. 6): f = m exp(-tau) + (1 - m) max(0, 1 - tau / 2),
  m = gamma in [0, 1] (1: exponential; 0: linear, with the same mean free path).
- :data:`GAMMA` (power law): f = (1 + tau / a)^-a, the mean of exp(-tau') over a gamma
  distribution of optical depths tau' with mean tau and shape a (relative variance 1 / a):
  the transmittance of a voxel whose optical depth varies below the grid's resolution (Davis
  and Marshak's generalized radiative transfer). The kernels take m = 1 / a >= 0, so that
  m = 0 (a = infinity) is exponential: f = (1 + m tau)^(-1/m) = exp(-log1p(m tau) / m),
  written so that it tends to exp(-tau) without rounding trouble as m -> 0.

Along a ray through piecewise-constant voxels, the transmittance follows the paper's
recursive form (Eq. 7), exact per voxel (the mode is constant inside it):

    T <- f(f^-1(T, m_v) + beta_v l_v, m_v),                                    (Eqs. 7-8)

and a free flight is sampled by inverting T = u inside the voxel where T falls below u:
l = (f^-1(u, m_v) - f^-1(T_in, m_v)) / beta_v. The collision density is T_pdf = -df/dtau
(f^-1(T, m), m) beta (Eq. 9), not beta T. All functions are ``@njit`` and work on the
*equivalent optical depth* s = -log T, in which the exponential family is the identity
(s_out = s_in + beta l), so that a walk can carry one number for every family.

Derivatives with respect to the extinctions (the score function, mode field fixed). Write
u_j for the local optical depth f_j^-1(T) inside voxel j of a ray, h_j(u) = -f_j'(u) /
f_j(u) for the family's *hazard* (1 for the exponential) and tau_j = beta_j l_j. The
recursion gives ds_j / ds_{j-1} = h_j(u_out) / h_j(u_in) and ds_j / dtau_j = h_j(u_out),
so the equivalent depth s at the end of a walk through voxels 1 .. n changes with voxel k's
extinction as

    ds / dbeta_k = l_k h_k(u_in,k) / Q_{k-1} x Q_n,   Q_k = prod_{j<=k} h_j(u_out,j) / h_j(u_in,j),

(for the exponential l_k; for the power law with one mode, l_k / (1 + m U), U the ray's
optical depth). The log of a free flight's collision density beta_v phi_v(u) (phi = -f',
Eq. 9) changes as d log T_pdf / dbeta_k = delta_kv / beta_v - c ds / dbeta_k with the
*collision factor* c = -phi' f / phi^2 at the collision (1 for the exponential, 1 + m for
the power law, :func:`collision_factor`).
"""

from __future__ import annotations

import math

from numba import njit

#: Family codes (the medium's ``transmittance`` attribute names them, see FAMILIES).
EXPONENTIAL = 0
LINEAR_MIX = 1
GAMMA = 2
#: The names of the families in files and the API, by code.
FAMILIES = {"exponential": EXPONENTIAL, "linear-mix": LINEAR_MIX, "gamma": GAMMA}

_NEWTON_STEPS = 60


@njit(cache=True, inline="always")
def transmittance(family: int, tau: float, m: float) -> float:
    """f(tau, m): the transmittance after optical depth ``tau`` with mode ``m`` (Eq. 6 and
    the power law; see the module docstring for the modes)."""
    if family == LINEAR_MIX:
        return m * math.exp(-tau) + (1.0 - m) * max(0.0, 1.0 - 0.5 * tau)
    if family == GAMMA and m > 0.0:
        return math.exp(-math.log1p(m * tau) / m)
    return math.exp(-tau)


@njit(cache=True, inline="always")
def transmittance_slope(family: int, tau: float, m: float) -> float:
    """-df/dtau (tau, m) >= 0: the free-flight density per unit optical depth (Eq. 9)."""
    if family == LINEAR_MIX:
        return m * math.exp(-tau) + ((1.0 - m) * 0.5 if tau < 2.0 else 0.0)
    if family == GAMMA and m > 0.0:
        return math.exp(-(1.0 / m + 1.0) * math.log1p(m * tau))
    return math.exp(-tau)


@njit(cache=True)
def optical_depth_of(family: int, t: float, m: float) -> float:
    """f^-1(t, m): the optical depth after which the transmittance is ``t`` in (0, 1]
    (``inf`` for t = 0 where f never reaches 0; 2 for the linear family's t = 0)."""
    if t >= 1.0:
        return 0.0
    if family == GAMMA and m > 0.0:
        return math.expm1(-m * math.log(t)) / m if t > 0.0 else math.inf
    if family != LINEAR_MIX or m >= 1.0:
        return -math.log(t) if t > 0.0 else math.inf
    if m <= 0.0:
        return 2.0 * (1.0 - t)
    if t <= m * math.exp(-2.0):  # beyond the linear part's end: f = m exp(-tau)
        return -math.log(t / m) if t > 0.0 else math.inf
    # 0 < tau < 2: f is convex and decreasing there, so Newton's method from tau = 0 rises
    # monotonically to the root without overshooting it (to rounding)
    tau = 0.0
    for _ in range(_NEWTON_STEPS):
        step = (transmittance(family, tau, m) - t) / transmittance_slope(family, tau, m)
        tau += step
        if step <= 1e-15 * max(tau, 1.0):
            break
    return min(tau, 2.0)


@njit(cache=True, inline="always")
def is_exponential(family: int, m: float) -> bool:
    """Whether the family is exponential at mode ``m`` (its limit a = inf, gamma = 1)."""
    return family == EXPONENTIAL or (family == GAMMA and m <= 0.0) or (
        family == LINEAR_MIX and m >= 1.0
    )


@njit(cache=True, inline="always")
def depth_step(family: int, s: float, m: float, dtau: float) -> tuple[float, float]:
    """A voxel of optical depth ``dtau`` and mode ``m`` entered at equivalent depth ``s``:
    the equivalent depth -log T after it (Eqs. 7-8, exact for a constant mode) and log
    h(u_out) / h(u_in), the log of its hazard ratio (the module docstring's Q factor)."""
    if is_exponential(family, m):
        return s + dtau, 0.0
    if family == GAMMA:  # u = f^-1(e^-s) = expm1(m s) / m, s = log1p(m u) / m, h = e^(-m s):
        # s_out = log1p(m (u + dtau)) / m, written without e^(m s), which overflows for small a
        growth = math.log1p(m * dtau * math.exp(-m * s))
        return s + growth / m, -growth
    t_in = math.exp(-s)
    u = optical_depth_of(family, t_in, m)
    t = transmittance(family, u + dtau, m)
    if t <= 0.0:  # the linear family's end: nothing passes, no derivative is taken
        return math.inf, 0.0
    ratio = (transmittance_slope(family, u + dtau, m) * t_in
             / (transmittance_slope(family, u, m) * t))
    return -math.log(t), math.log(ratio)


@njit(cache=True, inline="always")
def optical_depth_to_reach(family: int, s: float, m: float, s_target: float) -> float:
    """The optical depth of a voxel of mode ``m`` entered at equivalent depth ``s`` after
    which the equivalent depth reaches ``s_target`` >= s: the free flight's end inside the
    voxel (divide by the voxel's extinction for the length)."""
    if is_exponential(family, m):
        return s_target - s
    if family == GAMMA:  # (expm1(m s_target) - expm1(m s)) / m, without overflow
        if s_target <= s:
            return 0.0
        return math.exp(m * s + math.log(math.expm1(m * (s_target - s)))) / m
    return (optical_depth_of(family, math.exp(-s_target), m)
            - optical_depth_of(family, math.exp(-s), m))


@njit(cache=True, inline="always")
def log_hazard(family: int, s: float, m: float) -> float:
    """log h, h = -f'(u) / f(u) = ds / du, at the equivalent depth ``s`` (T = e^-s, u =
    f^-1(T, m)) in a voxel of mode ``m`` (h = 1 for the exponential, e^(-m s) = 1 / (1 + m
    u) for the power law)."""
    if is_exponential(family, m):
        return 0.0
    if family == GAMMA:
        return -m * s
    t = math.exp(-s)
    return math.log(transmittance_slope(family, optical_depth_of(family, t, m), m) / t)


@njit(cache=True, inline="always")
def collision_factor(family: int, s: float, m: float) -> float:
    """c = -phi'(u) f(u) / phi(u)^2 (phi = -f') at the end of a free flight at equivalent
    depth ``s`` in a voxel of mode ``m``: the collision density's log derivative per unit
    of the flight's equivalent depth (module docstring; 1 for the exponential, 1 + m for
    the power law)."""
    if is_exponential(family, m):
        return 1.0
    if family == GAMMA:
        return 1.0 + m
    u = optical_depth_of(family, math.exp(-s), m)
    if u >= 2.0:  # the linear mix's exponential tail
        return 1.0
    decay = m * math.exp(-u)  # -phi' on the linear part, where phi = decay + (1 - m) / 2
    phi = decay + 0.5 * (1.0 - m)
    return decay * transmittance(family, u, m) / (phi * phi)
