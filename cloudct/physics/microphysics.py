"""The cloud's optics as functions of its microphysics (LWC, r_eff), and their derivatives.

For one Mie table (:func:`cloudct.physics.mie.mie_table`, rows at r_eff nodes r_0 < ... <
r_{n-1}) and arrays of liquid water content LWC [g m-3] and effective radius r_eff [micron]:

- the cloud extinction beta = LWC e(r_eff) [km-1], e the table's ``ext_per_lwc``, with
  d beta / d LWC = e(r_eff) and d beta / d r_eff = LWC e'(r_eff) (at fixed LWC);
- the single-scattering albedo omega(r_eff) and d omega / d r_eff;
- the phase function p(theta; r_eff) and d log p / d r_eff at a scattering angle theta.

**Interpolation in r_eff: linear between the two bracketing rows**, for all three. With
r_i <= r_eff <= r_{i+1} and t = (r_eff - r_i) / (r_{i+1} - r_i),

    q(r_eff) = (1 - t) q_i + t q_{i+1},   dq / d r_eff = (q_{i+1} - q_i) / (r_{i+1} - r_i),

so the derivative is constant inside each interval of the table. For e and omega this is
what :func:`cloudct.optics.to_optical` does (``np.interp``), so these derivatives are the
exact derivatives of the forward model's optics. For the phase function it is the only
scheme of the usual ones that keeps p a density: a convex mixture of two normalised,
non-negative rows is normalised and non-negative (a cubic in r_eff can undershoot below
zero in the steep diffraction peak, and a mixture in log p is not normalised), its mean
cosine is the same mixture of the rows' (linear in r_eff), and the kernels can sample it
exactly by drawing row i with probability 1 - t and row i + 1 with probability t. Its
score d log p / d r_eff = (p_{i+1} - p_i) / ((r_{i+1} - r_i) p) integrates to zero against
p, as a score must (2 pi int dp / d r_eff dmu = 0). Each row is the density the kernels
trace: linear in mu = cos(theta) between the table's angles and renormalised so that this
interpolant integrates to 1 exactly (:func:`cloudct.physics.phase.tabulated_nodes`).

At an interior node r_i the derivative is discontinuous; these functions take the
interval above it (the right derivative), and at the last node r_{n-1} the interval below.

r_eff outside [r_0, r_{n-1}] is a ValueError, except in clear cells (LWC = 0) of the
functions that take LWC: there r_eff is ignored as in :func:`cloudct.optics.to_optical`
(clipped to the table), so that beta = 0 and d beta / d LWC = e(r_eff clipped), the
extinction a first drop of water would bring.

:func:`extinction_part_of_gradient` applies the chain rule through beta to a gradient with
respect to beta per voxel (what the estimators of :mod:`cloudct.mc.gradient` return). The
albedo and phase-function parts of d loss / d r_eff come from the Monte Carlo path score
function instead (see its documentation); they are not computed here.

:func:`delta_scaled_reff_slopes` carries the r_eff slopes through a phase truncation
(:func:`cloudct.physics.phase.truncated_peak`), whose cut share f moves with r_eff too.
"""

from __future__ import annotations

import numpy as np
import xarray as xr
from numpy.typing import ArrayLike

from cloudct.physics.phase import tabulated_nodes


def _table_reff(table: xr.Dataset) -> np.ndarray:
    reff = np.asarray(table["reff"].values, dtype=np.float64)
    if reff.size < 2 or np.any(np.diff(reff) <= 0.0):
        raise ValueError("the Mie table needs at least two strictly increasing r_eff rows")
    return reff


def _check_inside(reff: np.ndarray, table_reff: np.ndarray, where: np.ndarray | None = None):
    """ValueError where ``reff`` (only where ``where``, when given) is not finite or lies
    outside the table's r_eff range."""
    inside = (reff >= table_reff[0]) & (reff <= table_reff[-1])
    bad = ~inside if where is None else where & ~inside
    if np.any(bad):
        found = reff[bad]
        finite = found[np.isfinite(found)]
        values = [f"{finite.min():g}..{finite.max():g}"] if finite.size else []
        values += ["not finite"] if finite.size < found.size else []
        raise ValueError(
            f"{int(bad.sum())} r_eff values outside the Mie table's range "
            f"{table_reff[0]:g}..{table_reff[-1]:g} micron (found {', '.join(values)})"
        )


def _microphysics(lwc: ArrayLike, reff: ArrayLike, table: xr.Dataset):
    """LWC and r_eff broadcast together and checked, r_eff clipped to the table where
    LWC = 0; with the table's r_eff."""
    lwc, reff = np.broadcast_arrays(np.asarray(lwc, dtype=np.float64),
                                    np.asarray(reff, dtype=np.float64))
    if not np.all(np.isfinite(lwc)) or np.any(lwc < 0.0):
        raise ValueError("LWC must be finite and >= 0")
    table_reff = _table_reff(table)
    cloudy = lwc > 0.0
    _check_inside(reff, table_reff, cloudy)
    if not np.all(np.isfinite(reff)):
        raise ValueError("r_eff must be finite (in clear cells too)")
    return lwc, np.clip(reff, table_reff[0], table_reff[-1]), table_reff


def reff_interval(reff: ArrayLike, table: xr.Dataset) -> tuple[np.ndarray, np.ndarray]:
    """The table row i below each r_eff and its weight t in [0, 1]: r_eff = (1 - t) r_i +
    t r_{i+1}, i in [0, n - 2] (the interval above an interior node, the last interval at
    the last node).

    Raises:
        ValueError: an r_eff outside the table's range (or not finite).
    """
    reff = np.asarray(reff, dtype=np.float64)
    table_reff = _table_reff(table)
    _check_inside(reff, table_reff)
    i = np.clip(np.searchsorted(table_reff, reff, side="right") - 1, 0, table_reff.size - 2)
    t = (reff - table_reff[i]) / (table_reff[i + 1] - table_reff[i])
    return i, t


def _linear(reff: np.ndarray, table: xr.Dataset, name: str) -> tuple[np.ndarray, np.ndarray]:
    """The table's ``name`` interpolated linearly in r_eff, and its slope per micron."""
    i, t = reff_interval(reff, table)
    q = np.asarray(table[name].values, dtype=np.float64)
    table_reff = _table_reff(table)
    slope = (q[i + 1] - q[i]) / (table_reff[i + 1] - table_reff[i])
    return (1.0 - t) * q[i] + t * q[i + 1], slope


def cloud_extinction(lwc: ArrayLike, reff: ArrayLike, table: xr.Dataset) -> np.ndarray:
    """beta = LWC e(r_eff) [km-1], e the table's extinction per LWC (linear in r_eff)."""
    lwc, reff, _ = _microphysics(lwc, reff, table)
    return lwc * _linear(reff, table, "ext_per_lwc")[0]


def extinction_lwc_derivative(lwc: ArrayLike, reff: ArrayLike, table: xr.Dataset) -> np.ndarray:
    """d beta / d LWC = e(r_eff) [km-1 per g m-3], the extinction per LWC; in clear cells
    (LWC = 0) that of the r_eff clipped to the table."""
    lwc, reff, _ = _microphysics(lwc, reff, table)
    return _linear(reff, table, "ext_per_lwc")[0]


def extinction_reff_derivative(lwc: ArrayLike, reff: ArrayLike, table: xr.Dataset) -> np.ndarray:
    """d beta / d r_eff at fixed LWC = LWC e'(r_eff) [km-1 per micron] (0 in clear cells);
    e' constant inside each interval of the table (module documentation)."""
    lwc, reff, _ = _microphysics(lwc, reff, table)
    return lwc * _linear(reff, table, "ext_per_lwc")[1]


def single_scattering_albedo(reff: ArrayLike, table: xr.Dataset) -> np.ndarray:
    """omega(r_eff), the table's albedo linear in r_eff."""
    return _linear(np.asarray(reff, dtype=np.float64), table, "albedo")[0]


def albedo_reff_derivative(reff: ArrayLike, table: xr.Dataset) -> np.ndarray:
    """d omega / d r_eff [per micron], constant inside each interval of the table."""
    return _linear(np.asarray(reff, dtype=np.float64), table, "albedo")[1]


def _phase_rows(table: xr.Dataset, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Ascending mu nodes and the kernels' normalised densities of ``rows`` (one per row)."""
    angles = np.asarray(table["scattering_angle"].values, dtype=np.float64)
    phase = np.asarray(table["phase"].values, dtype=np.float64)
    mu = tabulated_nodes(angles, phase[0])[0]  # the same nodes for every row
    pdf = [tabulated_nodes(angles, phase[row])[1] for row in rows]
    return mu, np.array(pdf).reshape(len(rows), mu.size)


def _bracketing_phase(reff: ArrayLike, scattering_angle: ArrayLike, table: xr.Dataset):
    """p_i(mu), p_{i+1}(mu), t and r_{i+1} - r_i for each (r_eff, angle) pair."""
    reff, angle = np.broadcast_arrays(np.asarray(reff, dtype=np.float64),
                                      np.asarray(scattering_angle, dtype=np.float64))
    if not np.all((angle >= 0.0) & (angle <= 180.0)):
        raise ValueError("scattering angles must lie in [0, 180] degrees")
    i, t = reff_interval(reff, table)
    rows, where = np.unique(np.concatenate([i.ravel(), i.ravel() + 1]), return_inverse=True)
    lower, upper = where[: i.size].reshape(i.shape), where[i.size:].reshape(i.shape)
    nodes, pdf = _phase_rows(table, rows)
    mu = np.cos(np.radians(angle))
    k = np.clip(np.searchsorted(nodes, mu, side="right") - 1, 0, nodes.size - 2)
    s = np.clip((mu - nodes[k]) / (nodes[k + 1] - nodes[k]), 0.0, 1.0)

    def at(row):
        return pdf[row, k] + s * (pdf[row, k + 1] - pdf[row, k])

    table_reff = _table_reff(table)
    return at(lower), at(upper), t, table_reff[i + 1] - table_reff[i]


def mie_phase_function(reff: ArrayLike, scattering_angle: ArrayLike,
                       table: xr.Dataset) -> np.ndarray:
    """p(theta; r_eff) [sr-1] = (1 - t) p_i(theta) + t p_{i+1}(theta): the two bracketing
    rows mixed linearly in r_eff, each linear in cos(theta) between the table's angles and
    normalised as the kernels trace it (module documentation). ``reff`` [micron] and
    ``scattering_angle`` [degrees] broadcast together.

    Raises:
        ValueError: an r_eff outside the table's range, an angle outside [0, 180].
    """
    low, high, t, _ = _bracketing_phase(reff, scattering_angle, table)
    return (1.0 - t) * low + t * high


def phase_log_reff_derivative(reff: ArrayLike, scattering_angle: ArrayLike,
                              table: xr.Dataset) -> np.ndarray:
    """d log p(theta; r_eff) / d r_eff [per micron] of :func:`mie_phase_function`:
    (p_{i+1} - p_i) / ((r_{i+1} - r_i) p), the score of one scattering at theta; 0 where
    p = 0 (no path scatters there)."""
    low, high, t, width = _bracketing_phase(reff, scattering_angle, table)
    p = (1.0 - t) * low + t * high
    return np.divide(high - low, width * p, out=np.zeros_like(p), where=p > 0.0)


def extinction_part_of_gradient(
    d_loss_d_extinction: ArrayLike, lwc: ArrayLike, reff: ArrayLike, table: xr.Dataset
) -> tuple[np.ndarray, np.ndarray]:
    """The parts of d loss / d LWC and d loss / d r_eff per voxel that come through the
    cloud extinction, from d loss / d beta per voxel:

        d loss / d LWC   = d loss / d beta * e(r_eff),
        d loss / d r_eff = d loss / d beta * LWC e'(r_eff)   (extinction part only).

    ``d_loss_d_extinction`` is what the gradient estimators return (e.g.
    :func:`cloudct.mc.gradient.score_function_gradient`, [per km-1]), in the true cloud
    extinction beta (with a phase truncation, already multiplied by d beta' / d beta).
    d loss / d LWC is then complete: LWC changes only beta. d loss / d r_eff is NOT: r_eff
    also changes the albedo omega and the phase function p, which this function leaves out.

    Those parts come from the Monte Carlo path score function (path-recycling paper,
    Czerninski & Schechner 2021, Eqs. (44)-(46) and Appendix C, Eqs. (76)-(77)): with
    m_v = r_eff of voxel v, the scattering factor of a vertex x_b in voxel v is
    f_s = beta_s^c p^c(theta) + beta_s^a p^a(theta) (Eq. 88), whose log-derivative at
    fixed LWC is the extinction term (the beta score of Eq. 91, through this function)
    plus

        [beta^c omega^c p^c / f_s] * (d log omega / d r_eff + d log p(theta) / d r_eff),

    the bracket the cloud's share of the scattering at theta (1 where the voxel holds no
    air). Each scattering vertex in voxel v therefore adds that term, at the angle the path
    turns through there, times the residual-weighted contribution of the estimates whose
    path holds that turn (Eq. 46): for a local estimate made at the vertex, the angle
    towards the camera; for the direction sampled there, the estimates made after it.
    Transmittance segments add nothing at fixed beta. The forward kernels accumulate these
    terms in their REFF_GRADIENT pass (:mod:`cloudct.mc.microphysics_gradient`).

    Args:
        d_loss_d_extinction: d loss / d beta per voxel.
        lwc, reff: the microphysics [g m-3, micron], broadcast with it.
        table: the Mie table of the band.

    Returns:
        ``(d_loss_d_lwc, d_loss_d_reff_extinction_part)``.
    """
    grad = np.asarray(d_loss_d_extinction, dtype=np.float64)
    lwc, reff, _ = _microphysics(lwc, reff, table)
    e, slope = _linear(reff, table, "ext_per_lwc")
    return grad * e, grad * lwc * slope


def delta_scaled_reff_slopes(
    albedo: ArrayLike, weight: ArrayLike, d_albedo: ArrayLike, d_weight: ArrayLike,
    share: ArrayLike, share_next: ArrayLike,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The slopes in r_eff of the optics a phase truncation leaves, from the full optics'.

    A cell mixes the rows k and k + 1 with weight t (slope dt = ``d_weight``); their cuts
    remove the shares f_k = ``share`` and f_{k+1} = ``share_next`` of scattering, the
    cell's f = (1 - t) f_k + t f_{k+1}, so df = (f_{k+1} - f_k) dt. The delta-scaled optics
    (:func:`cloudct.optics.kernel_arrays_and_scale`, Wiscombe 1977) are

        beta' = beta s,  s = 1 - omega f,
        omega' = omega (1 - f) / s,
        t' = t (1 - f_{k+1}) / (1 - f),

    whence, with d = d / d r_eff,

        d omega' = [(1 - f) d omega - omega (1 - omega) df] / s^2,
        d t'     = (1 - f_k) (1 - f_{k+1}) dt / (1 - f)^2,
        d log s  = -(f d omega + omega df) / s.

    Returns ``(d_albedo', d_weight', d_log_scale)`` [per micron], broadcast together: the
    kernels' albedo and next-row weight slopes (the vertex terms of the score in r_eff at
    fixed beta') and the relative slope of beta' / beta (a part of the extinction's term).
    """
    omega, t, d_omega, dt, f_k, f_next = np.broadcast_arrays(
        *(np.asarray(a, dtype=np.float64) for a in (albedo, weight, d_albedo, d_weight,
                                                    share, share_next)))
    f = (1.0 - t) * f_k + t * f_next
    df = (f_next - f_k) * dt
    s = 1.0 - omega * f
    d_omega_cut = ((1.0 - f) * d_omega - omega * (1.0 - omega) * df) / s**2
    d_weight_cut = (1.0 - f_k) * (1.0 - f_next) * dt / (1.0 - f) ** 2
    return d_omega_cut, d_weight_cut, -(f * d_omega + omega * df) / s
