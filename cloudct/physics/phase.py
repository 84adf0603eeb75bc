"""Phase functions: evaluation and exact sampling, as plain numba functions.

A phase function p(mu) is a density per steradian over the scattering cosine mu,
normalised as 2 pi * integral_{-1}^{1} p(mu) dmu = 1 (seed paper Eq. 6).

Kinds (``PhaseBank.kind``):

- ``RAYLEIGH``: p = 3 / (16 pi) (1 + mu^2); sampled by solving the CDF cubic exactly.
- ``HENYEY_GREENSTEIN``: p = (1 - g^2) / (4 pi (1 + g^2 - 2 g mu)^(3/2)); sampled by the
  exact inverse CDF, written without a division by g so that g = 0 and g -> 0 are exact.
- ``TABULATED``: p given at nodes mu_k (ascending, from -1 to 1) and linear in mu between
  them. The CDF is then piecewise quadratic and is inverted exactly, so evaluation and
  sampling describe the same density.

The numba functions take no Python objects and allocate nothing, so that ``numba.cuda``
kernels can call them too. The Python-side builder :func:`phase_bank` assembles a
:class:`PhaseBank` from a list of specifications; :func:`truncated_peak` cuts the forward
peak of a tabulated phase function flat (delta-M-like truncation, see its documentation).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np
from numba import njit

RAYLEIGH = 0
HENYEY_GREENSTEIN = 1
TABULATED = 2

FOUR_PI = 4.0 * math.pi
TWO_PI = 2.0 * math.pi


class PhaseBank(NamedTuple):
    """All phase functions of a scene; entry ``ip`` is row ``ip`` of every array."""

    kind: np.ndarray  # int32[nphase]: 0 Rayleigh, 1 Henyey-Greenstein, 2 tabulated
    g: np.ndarray  # float64[nphase]: HG g (the exact mean cosine for the others)
    table_start: np.ndarray  # int64[nphase + 1]: CSR offsets into the table arrays
    table_mu: np.ndarray  # float64[ntab]: ascending cos(scattering angle) nodes, -1 .. 1
    table_pdf: np.ndarray  # float64[ntab]: phase function per sr at the nodes
    table_cdf: np.ndarray  # float64[ntab]: P(mu' <= mu) at the nodes


# --------------------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def rayleigh_phase(mu: float) -> float:
    """Rayleigh phase function per sr (unpolarised, no depolarisation)."""
    return 3.0 / (4.0 * FOUR_PI) * (1.0 + mu * mu)


@njit(cache=True, inline="always")
def henyey_greenstein_phase(mu: float, g: float) -> float:
    """Henyey-Greenstein phase function per sr, |g| < 1."""
    d = 1.0 + g * g - 2.0 * g * mu
    return (1.0 - g * g) / (FOUR_PI * d * math.sqrt(d))


@njit(cache=True, inline="always")
def _table_interval(x: np.ndarray, lo: int, hi: int, v: float) -> int:
    """Index i in [lo, hi - 2] with x[i] <= v < x[i + 1] (clamped), by binary search."""
    a = lo
    b = hi - 1
    while b - a > 1:
        mid = (a + b) // 2
        if x[mid] <= v:
            a = mid
        else:
            b = mid
    return a


@njit(cache=True, inline="always")
def tabulated_phase(bank: PhaseBank, ip: int, mu: float) -> float:
    """Tabulated phase function per sr: linear interpolation in mu between nodes."""
    lo = bank.table_start[ip]
    hi = bank.table_start[ip + 1]
    i = _table_interval(bank.table_mu, lo, hi, mu)
    m0 = bank.table_mu[i]
    m1 = bank.table_mu[i + 1]
    t = min(max((mu - m0) / (m1 - m0), 0.0), 1.0)
    return bank.table_pdf[i] + t * (bank.table_pdf[i + 1] - bank.table_pdf[i])


@njit(cache=True, inline="always")
def phase_function(bank: PhaseBank, ip: int, mu: float) -> float:
    """Phase function ``ip`` of the bank at scattering cosine ``mu``, per sr."""
    kind = bank.kind[ip]
    if kind == RAYLEIGH:
        return rayleigh_phase(mu)
    if kind == HENYEY_GREENSTEIN:
        return henyey_greenstein_phase(mu, bank.g[ip])
    return tabulated_phase(bank, ip, mu)


# --------------------------------------------------------------------------------------
# Sampling
# --------------------------------------------------------------------------------------


@njit(cache=True)
def sample_rayleigh_cosine(u: float) -> float:
    """Scattering cosine with the Rayleigh density, for u uniform in [0, 1).

    The CDF (3/8)(mu + mu^3/3 + 4/3) = u is the depressed cubic mu^3 + 3 mu = q with
    q = 8u - 4; its single real root (Cardano) is mu = A - 1/A, A = cbrt(q/2 + sqrt(q^2/4 + 1)).
    The root is odd in q; it is computed for |q|, where A >= 1, to absolute accuracy ~1e-16.
    """
    q = 8.0 * u - 4.0
    h = 0.5 * abs(q)
    a = (h + math.sqrt(h * h + 1.0)) ** (1.0 / 3.0)
    mu = a - 1.0 / a
    return min(mu, 1.0) if q >= 0.0 else -min(mu, 1.0)


@njit(cache=True)
def sample_henyey_greenstein_cosine(g: float, u: float) -> float:
    """Scattering cosine with the HG density, for u uniform in [0, 1).

    The textbook inverse mu = (1 + g^2 - t^2) / (2g), t = (1 - g^2) / (1 - g + 2gu), divides
    by g and cancels catastrophically as g -> 0. Factoring 2g (1 - mu) = (t - 1 + g)(t + 1 - g)
    cancels the g exactly and leaves a product of positive factors:

        1 - mu = 2 (1 - g)^2 (1 - u) (1 + g u) / (1 - g + 2 g u)^2,

    accurate to a few 1e-16 in mu for all -0.99 <= g < 1 (exact at g = 0: mu = 2u - 1), with
    mu(0) = -1 and mu(1) = 1 exactly.
    """
    d = 1.0 - g + 2.0 * g * u
    one_minus_mu = 2.0 * (1.0 - g) ** 2 * (1.0 - u) * (1.0 + g * u) / (d * d)
    return max(1.0 - one_minus_mu, -1.0)


@njit(cache=True, _nrt=False)
def sample_tabulated_cosine(bank: PhaseBank, ip: int, u: float) -> float:
    """Scattering cosine with a tabulated (piecewise linear in mu) density, exactly.

    In the node interval [mu_i, mu_i + h] the CDF is c_i + a t^2 + b t with t = mu - mu_i,
    b = 2 pi p_i and a = pi (p_{i+1} - p_i) / h. The root of a t^2 + b t = d (d = u - c_i)
    is taken in the form t = 2d / (b + sqrt(b^2 + 4 a d)), stable for either sign of a
    and for a = 0 or b = 0.
    """
    lo = bank.table_start[ip]
    hi = bank.table_start[ip + 1]
    i = _table_interval(bank.table_cdf, lo, hi, u)
    m0 = bank.table_mu[i]
    h = bank.table_mu[i + 1] - m0
    p0 = bank.table_pdf[i]
    a = math.pi * (bank.table_pdf[i + 1] - p0) / h
    b = TWO_PI * p0
    d = max(u - bank.table_cdf[i], 0.0)
    denom = b + math.sqrt(max(b * b + 4.0 * a * d, 0.0))
    t = 2.0 * d / denom if denom > 0.0 else 0.0
    return min(m0 + min(t, h), 1.0)


@njit(cache=True, _nrt=False)
def sample_phase_cosine(bank: PhaseBank, ip: int, u: float) -> float:
    """Scattering cosine drawn from phase function ``ip`` of the bank, u uniform in [0, 1)."""
    kind = bank.kind[ip]
    if kind == RAYLEIGH:
        return sample_rayleigh_cosine(u)
    if kind == HENYEY_GREENSTEIN:
        return sample_henyey_greenstein_cosine(bank.g[ip], u)
    return sample_tabulated_cosine(bank, ip, u)


@njit(cache=True)
def scatter_direction(
    ux: float, uy: float, uz: float, mu: float, phi: float
) -> tuple[float, float, float]:
    """Unit vector at scattering cosine ``mu`` and azimuth ``phi`` [rad] about (ux, uy, uz).

    The azimuth is measured in the orthonormal frame (e1, e2, u) of Duff et al. (2017,
    "Building an orthonormal basis, revisited", JCGT 6(1)), which has no singularity at
    the poles (uz = +-1), unlike the textbook formula with 1 / sqrt(1 - uz^2). The result is
    renormalised so that rounding does not accumulate along a path.
    """
    sign = 1.0 if uz >= 0.0 else -1.0
    a = -1.0 / (sign + uz)
    b = ux * uy * a
    e1x = 1.0 + sign * ux * ux * a
    e1y = sign * b
    e1z = -sign * ux
    e2x = b
    e2y = sign + uy * uy * a
    e2z = -uy
    sin_t = math.sqrt(max(1.0 - mu * mu, 0.0))
    c = sin_t * math.cos(phi)
    s = sin_t * math.sin(phi)
    vx = mu * ux + c * e1x + s * e2x
    vy = mu * uy + c * e1y + s * e2y
    vz = mu * uz + c * e1z + s * e2z
    norm = 1.0 / math.sqrt(vx * vx + vy * vy + vz * vz)
    return vx * norm, vy * norm, vz * norm


# --------------------------------------------------------------------------------------
# Python-side builder
# --------------------------------------------------------------------------------------


def tabulated_nodes(
    angles_deg: np.ndarray, values: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """Nodes, normalised density, CDF and mean cosine of a tabulated phase function.

    Args:
        angles_deg: scattering angles [deg], strictly increasing from 0 to 180.
        values: phase function at those angles (any positive scale; per sr after scaling).

    Returns:
        ``(mu, pdf, cdf, g)``: ascending cosines (exactly -1 and 1 at the ends), the density
        per sr scaled so that 2 pi * integral(p dmu) = 1 exactly for the piecewise-linear
        interpolant, its CDF at the nodes (0 ... 1) and its exact mean cosine.
    """
    angles = np.asarray(angles_deg, dtype=np.float64)
    p = np.asarray(values, dtype=np.float64)
    if angles.ndim != 1 or angles.shape != p.shape or angles.size < 2:
        raise ValueError("angles and values must be 1-D arrays of the same length >= 2")
    if angles[0] != 0.0 or angles[-1] != 180.0 or np.any(np.diff(angles) <= 0.0):
        raise ValueError("scattering angles must increase strictly from 0 to 180 degrees")
    if np.any(p < 0.0) or not np.all(np.isfinite(p)):
        raise ValueError("tabulated phase function values must be finite and >= 0")
    mu = np.cos(np.radians(angles))[::-1].copy()
    p = p[::-1].copy()
    mu[0], mu[-1] = -1.0, 1.0
    if np.any(np.diff(mu) <= 0.0):
        raise ValueError("scattering angles too close: cosines are not strictly increasing")
    h = np.diff(mu)
    mass = TWO_PI * 0.5 * h * (p[:-1] + p[1:])  # exact integral of each linear piece
    total = mass.sum()
    if total <= 0.0:
        raise ValueError("tabulated phase function has zero integral")
    p /= total
    cdf = np.concatenate(([0.0], np.cumsum(mass) / total))
    cdf[-1] = 1.0
    # exact mean cosine of the piecewise-linear density: h/6 [(2a + b) p_a + (a + 2b) p_b]
    a, b = mu[:-1], mu[1:]
    g = TWO_PI * np.sum(h / 6.0 * ((2.0 * a + b) * p[:-1] + (a + 2.0 * b) * p[1:]))
    return mu, p, cdf, float(g)


def truncated_peak(
    angles_deg: np.ndarray, values: np.ndarray, truncation_deg: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """A tabulated phase function with its forward peak cut flat at ``truncation_deg``.

    Within the truncation angle the phase function is replaced by its value there,
    p'(mu) = min(p(mu), p(mu_t)) for mu > mu_t (a node is added at theta_t), and the
    share f of scattering that this removes (of the piecewise-linear interpolant, as
    :func:`tabulated_nodes` integrates it) is treated as no scattering at all: with the
    extinction beta (1 - omega f) and the single-scattering albedo omega (1 - f) /
    (1 - omega f) the light scattered into the peak goes on unscattered (the delta-M
    similarity of Wiscombe 1977, J. Atmos. Sci. 34, 1408, with a flat cut instead of a
    Legendre fit). Directions within theta_t of the incoming one are then exchanged for
    no deflection: a bias of order theta_t in the angular detail of the radiance, for a
    phase function whose largest value drops from ~10^3 per sr to p(theta_t) / (1 - f).

    Returns ``(angles, values, f)``: the angles with theta_t added (degrees), the cut
    values (not renormalised: :func:`tabulated_nodes` does it) and f in [0, 1).
    """
    angles = np.asarray(angles_deg, dtype=np.float64)
    p = np.asarray(values, dtype=np.float64)
    if not 0.0 < truncation_deg < 90.0:
        raise ValueError(f"the truncation angle must be in (0, 90) degrees, got {truncation_deg}")
    mu = np.cos(np.radians(angles))
    mu_t = math.cos(math.radians(truncation_deg))
    at_t = float(np.interp(mu_t, mu[::-1], p[::-1]))  # linear in mu, as evaluated
    if truncation_deg not in angles:
        j = int(np.searchsorted(angles, truncation_deg))
        angles = np.insert(angles, j, truncation_deg)
        p = np.insert(p, j, at_t)
        mu = np.insert(mu, j, mu_t)
    cut = np.where(angles < truncation_deg, np.minimum(p, at_t), p)

    def mass(q: np.ndarray) -> float:
        return float(np.sum(0.5 * (mu[:-1] - mu[1:]) * (q[:-1] + q[1:])))

    return angles, cut, 1.0 - mass(cut) / mass(p)


def phase_bank(entries: Sequence[tuple]) -> PhaseBank:
    """Build a :class:`PhaseBank` from phase-function specifications.

    Args:
        entries: one tuple per bank row, in order:
            ``("rayleigh",)``, ``("hg", g)`` with -1 < g < 1, or
            ``("tabulated", angles_deg, values)`` (see :func:`tabulated_nodes`; the values
            are renormalised and ``g`` is set to the interpolant's exact mean cosine).

    Returns:
        The bank, with float64 / int32 / int64 C-contiguous arrays.
    """
    kinds, gs, starts = [], [], [0]
    mus, pdfs, cdfs = [], [], []
    for entry in entries:
        name = entry[0].lower()
        if name == "rayleigh":
            kinds.append(RAYLEIGH)
            gs.append(0.0)
        elif name in ("hg", "henyey_greenstein"):
            g = float(entry[1])
            if not -1.0 < g < 1.0:
                raise ValueError(f"Henyey-Greenstein g must lie in (-1, 1), got {g}")
            kinds.append(HENYEY_GREENSTEIN)
            gs.append(g)
        elif name == "tabulated":
            mu, pdf, cdf, g = tabulated_nodes(entry[1], entry[2])
            kinds.append(TABULATED)
            gs.append(g)
            mus.append(mu)
            pdfs.append(pdf)
            cdfs.append(cdf)
            starts.append(starts[-1] + mu.size)
            continue
        else:
            raise ValueError(f"unknown phase function kind {entry[0]!r}")
        starts.append(starts[-1])

    def _join(parts: list[np.ndarray]) -> np.ndarray:
        return np.ascontiguousarray(np.concatenate(parts) if parts else np.zeros(0))

    return PhaseBank(
        kind=np.asarray(kinds, dtype=np.int32),
        g=np.asarray(gs, dtype=np.float64),
        table_start=np.asarray(starts, dtype=np.int64),
        table_mu=_join(mus),
        table_pdf=_join(pdfs),
        table_cdf=_join(cdfs),
    )
