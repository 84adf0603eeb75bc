"""Mie tables for water droplets with a gamma size distribution (miepython).

Size distribution (Hansen & Travis 1974, Eq. 2.56), with r_eff and v_eff its effective radius
and effective variance:

    n(r) ∝ r^alpha exp(-r / (r_eff v_eff)),   alpha = (1 - 3 v_eff) / v_eff.

Bulk optics per r_eff, with <.> the mean over n(r), cross sections C = Q pi r^2,
r_eff = <r^3> / <r^2> and rho_w = 1 g cm-3:

    beta / LWC = <C_ext> / (rho_w <(4/3) pi r^3>) = (3/4) Q_eff / (rho_w r_eff)
               = 750 Q_eff / r_eff   [km-1 per g m-3, r_eff in micron],
    Q_eff = <Q_ext r^2> / <r^2>,

so that Q_eff = 2 gives the familiar 1500 LWC / r_eff. The albedo is <C_sca> / <C_ext>, the
asymmetry parameter and the phase function are C_sca-weighted means over the distribution.

Radius quadrature: trapezoidal rule on one radius grid shared by all r_eff of a table, with
steps in size parameter x = 2 pi r / lambda of dx = max(0.005, 0.015 sqrt(x)), half the step
of SHDOM's make_mie_table (F. Evans: dx = max(0.01, 0.03 sqrt(x))). Against a reference with
dx = 0.02, at r_eff = 2 and 10 micron, it gives Q_eff and g to 2e-4 and the phase function to
7e-4 (median over angles) and 1.3e-2 (worst, near the glory): the size average smooths the
Mie ripple, and the steps sample its resonances densely. The grid spans the 1e-7 and
1 - 1e-7 quantiles of the r^2 n(r) and r^3 n(r) weights of the smallest and largest r_eff.

The refractive index of water, unless one is passed, is interpolated in the table of Hale &
Querry (1973) (:mod:`cloudct.physics.water`), at every wavelength alike: at 0.672 micron,
m = 1.331 + 2.149e-8 i.

Tables are cached as netCDF with the parameters that made them as attributes; the default
table (0.672 micron, v_eff = 0.1, r_eff 1..25 micron) ships in ``cloudct/data``, made with
that interpolated index.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import warnings
from pathlib import Path

import numpy as np
import xarray as xr
from scipy.stats import gamma as gamma_dist

from cloudct.jit_cache import cache_root
from cloudct.output_files import written_whole
from cloudct.physics import water

DEFAULT_WAVELENGTH = 0.672  # micron
DEFAULT_VEFF = 0.1
TABLE_VERSION = 1  # bump when the computation changes, to invalidate caches

_PACKAGED = Path(__file__).resolve().parent.parent / "data" / "mie_water_0.672um_veff0.1.nc"
_TAIL = 1e-7  # distribution mass left out at each end of the radius grid
_DX_MIN, _DX_SQRT = 0.005, 0.015  # radius quadrature: dx = max(_DX_MIN, _DX_SQRT sqrt(x))


def default_reff() -> np.ndarray:
    """Default effective radii of a table: 1 to 25 micron in steps of 0.1 micron."""
    return np.round(np.linspace(1.0, 25.0, 241), 10)


def default_angles() -> np.ndarray:
    """Default scattering angles [deg]: 0.02 deg steps to 2 deg (diffraction peak), then
    0.1 to 10 deg, 0.25 to 30 deg and 0.5 deg to 180 deg (561 angles)."""
    pieces = [
        np.arange(0, 100) * 0.02,
        2.0 + np.arange(0, 80) * 0.1,
        10.0 + np.arange(0, 80) * 0.25,
        30.0 + np.arange(0, 301) * 0.5,
    ]
    return np.round(np.concatenate(pieces), 10)


def _miepython():
    """miepython with its numba backend, which is ~100x faster than its pure-Python one.

    The backend is chosen when miepython is first imported (environment variable
    MIEPYTHON_USE_JIT); an explicit user setting is respected.
    """
    os.environ.setdefault("MIEPYTHON_USE_JIT", "1")
    import miepython

    if not miepython.USE_JIT:
        warnings.warn(
            "miepython was imported without its numba backend; Mie tables will be slow. "
            "Set MIEPYTHON_USE_JIT=1 before importing miepython.",
            stacklevel=3,
        )
    return miepython


def mie_efficiencies(
    refractive_index: complex, x: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mie efficiencies of homogeneous spheres.

    Args:
        refractive_index: m = n + i k of the sphere relative to its surroundings (k >= 0).
        x: size parameters 2 pi r / lambda (1-D array).

    Returns:
        ``(q_ext, q_sca, g)``: extinction and scattering efficiencies and asymmetry parameter.
    """
    mp = _miepython()
    m_mie = complex(refractive_index).conjugate()  # miepython's convention is m = n - i k
    qext, qsca, _, g = mp.efficiencies_mx(m_mie, np.atleast_1d(np.asarray(x, dtype=np.float64)))
    return np.asarray(qext), np.asarray(qsca), np.asarray(g)


def gamma_log_density(r: np.ndarray, reff: float, veff: float) -> np.ndarray:
    """log n(r) + const of the gamma distribution n(r) ∝ r^((1-3v)/v) exp(-r/(r_eff v))."""
    alpha = (1.0 - 3.0 * veff) / veff
    return alpha * np.log(r) - r / (reff * veff)


def _radius_grid(wavelength: float, reff_min: float, reff_max: float, veff: float) -> np.ndarray:
    """Radii [micron] of the quadrature: steps dx = max(0.005, 0.015 sqrt(x)) in size parameter."""
    alpha = (1.0 - 3.0 * veff) / veff
    # r^2 n(r) and r^3 n(r) are gamma densities of shapes alpha + 3 and alpha + 4, scale r_eff v
    r_lo = gamma_dist.ppf(_TAIL, alpha + 3.0) * veff * reff_min
    r_hi = gamma_dist.ppf(1.0 - _TAIL, alpha + 4.0) * veff * reff_max
    k = 2.0 * np.pi / wavelength
    xs = [k * r_lo]
    while xs[-1] < k * r_hi:
        xs.append(xs[-1] + max(_DX_MIN, _DX_SQRT * np.sqrt(xs[-1])))
    return np.asarray(xs) / k


def _index_source(wavelength: float, m: complex) -> str:
    """Where the refractive index ``m`` of a table comes from: the built-in table of water
    when ``m`` is its value at ``wavelength``, else the user."""
    try:
        builtin = water.water_refractive_index(wavelength)
    except ValueError:
        return "user"
    if _close(m.real, builtin.real) and _close(m.imag, builtin.imag):
        return f"{water.SOURCE}, interpolated: n linear, ln k linear in wavelength"
    return "user"


def _close(a, b) -> bool:
    """Equal numbers, to the last bits that an interpolation may round differently."""
    return math.isclose(float(a), float(b), rel_tol=1e-12, abs_tol=0.0)


def _table_attrs(wavelength: float, m: complex, veff: float) -> dict:
    return {
        "title": "Mie table for water droplets, gamma size distribution",
        "wavelength": float(wavelength),
        "wavelength_units": "micron",
        "refractive_index_real": float(m.real),
        "refractive_index_imag": float(m.imag),
        "refractive_index_source": _index_source(wavelength, m),
        "veff": float(veff),
        "size_distribution": "gamma: n(r) ~ r^((1-3 veff)/veff) exp(-r/(reff veff))",
        "quadrature": (
            f"trapezoidal in r, steps dx = max({_DX_MIN}, {_DX_SQRT} sqrt(x)) in size "
            f"parameter x = 2 pi r / wavelength, tails {_TAIL:g} left out at each end"
        ),
        "mie_code": "miepython",
        "table_version": TABLE_VERSION,
        "Conventions": "CF-1.8",
    }


def compute_mie_table(
    wavelength: float = DEFAULT_WAVELENGTH,
    refractive_index: complex | None = None,
    veff: float = DEFAULT_VEFF,
    reff: np.ndarray | None = None,
    angles: np.ndarray | None = None,
) -> xr.Dataset:
    """Compute a Mie table (no cache); see :func:`mie_table` for the arguments and output."""
    m = _refractive_index(wavelength, refractive_index)
    if not 0.0 < veff < 1.0 / 3.0:
        raise ValueError(f"veff must lie in (0, 1/3), got {veff}")
    reff = default_reff() if reff is None else np.asarray(reff, dtype=np.float64)
    angles = default_angles() if angles is None else np.asarray(angles, dtype=np.float64)
    if np.any(np.diff(reff) <= 0.0) or reff[0] <= 0.0:
        raise ValueError("reff must be positive and strictly increasing")

    mp = _miepython()
    r = _radius_grid(wavelength, reff[0], reff[-1], veff)
    x = 2.0 * np.pi * r / wavelength
    qext, qsca, gr = mie_efficiencies(m, x)
    mu = np.cos(np.radians(angles))
    m_mie = m.conjugate()  # miepython's convention is m = n - i k
    p_r = np.empty((r.size, mu.size))
    for i, xi in enumerate(x):
        p_r[i] = mp.i_unpolarized(m_mie, xi, mu, norm="one")  # per sr, unit integral

    # trapezoid weights times n(r), one row per r_eff (rows scaled by their maximum)
    dr = np.diff(r)
    trap = np.zeros_like(r)
    trap[:-1] += 0.5 * dr
    trap[1:] += 0.5 * dr
    logn = gamma_log_density(r[None, :], reff[:, None], veff)
    w = trap * np.exp(logn - logn.max(axis=1, keepdims=True))

    area = w @ r**2
    c_ext = w @ (qext * r**2)
    c_sca_r = w * (qsca * r**2)
    c_sca = c_sca_r.sum(axis=1)
    q_eff = c_ext / area
    ext_per_lwc = 750.0 * c_ext / (w @ r**3)  # (3/4) Q / r_eff with unit factor 1e3 / rho_w
    albedo = c_sca / c_ext
    g = (c_sca_r @ gr) / c_sca
    phase = (c_sca_r @ p_r) / c_sca[:, None]

    coords = {
        "reff": ("reff", reff, {"units": "micron", "long_name": "effective radius"}),
        "scattering_angle": (
            "scattering_angle",
            angles,
            {"units": "degree", "long_name": "scattering angle"},
        ),
    }
    data = {
        "ext_per_lwc": (
            "reff",
            ext_per_lwc,
            {"units": "km-1 m3 g-1", "long_name": "extinction per unit liquid water content"},
        ),
        "q_ext": (
            "reff",
            q_eff,
            {"units": "1", "long_name": "size-averaged extinction efficiency"},
        ),
        "albedo": ("reff", albedo, {"units": "1", "long_name": "single-scattering albedo"}),
        "g": ("reff", g, {"units": "1", "long_name": "asymmetry parameter"}),
        "phase": (
            ("reff", "scattering_angle"),
            phase,
            {"units": "sr-1", "long_name": "phase function, unit integral over the sphere"},
        ),
    }
    ds = xr.Dataset(data, coords=coords, attrs=_table_attrs(wavelength, m, veff))
    ds.attrs["n_radii"] = int(r.size)
    return ds


def _refractive_index(wavelength: float, refractive_index: complex | None) -> complex:
    """``refractive_index``, or the built-in index of water at ``wavelength``
    (:func:`cloudct.physics.water.water_refractive_index`; a ValueError outside its range)."""
    if refractive_index is not None:
        return complex(refractive_index)
    return water.water_refractive_index(wavelength)


def _same(stored, value) -> bool:
    """An attribute read from a file equals the one asked for (numbers to 1e-12: the
    interpolated refractive index may differ in its last bit from one machine's exp/log to
    another's)."""
    if isinstance(value, float) and isinstance(stored, (float, np.floating)):
        return _close(stored, value)
    return stored == value


def _matches(ds: xr.Dataset, attrs: dict, reff: np.ndarray, angles: np.ndarray) -> bool:
    same_attrs = all(_same(ds.attrs.get(key), value) for key, value in attrs.items())
    return (
        same_attrs
        and np.array_equal(ds["reff"].values, reff)
        and np.array_equal(ds["scattering_angle"].values, angles)
    )


def mie_table(
    wavelength: float = DEFAULT_WAVELENGTH,
    refractive_index: complex | None = None,
    veff: float = DEFAULT_VEFF,
    reff: np.ndarray | None = None,
    angles: np.ndarray | None = None,
    cache_dir: str | os.PathLike | None = None,
) -> xr.Dataset:
    """Mie table of water droplets: bulk optics per effective radius.

    Looks first for the table shipped in ``cloudct/data``, then in ``cache_dir``, for a
    table made with exactly these parameters; otherwise computes it and writes it there.

    Args:
        wavelength: wavelength [micron].
        refractive_index: m = n + i k of water (k >= 0); ``None`` for the built-in value,
            interpolated in Hale & Querry (1973) (:mod:`cloudct.physics.water`), from 0.2
            to 2.6 micron.
        veff: effective variance of the gamma size distribution, in (0, 1/3).
        reff: effective radii [micron], strictly increasing (default :func:`default_reff`).
        angles: scattering angles [deg] from 0 to 180 (default :func:`default_angles`).
        cache_dir: cache directory (default ``$CLOUDCT_CACHE_DIR``, else
            ``$XDG_CACHE_HOME/cloudct`` or ``~/.cache/cloudct``).

    Returns:
        Dataset over ``reff`` (and ``scattering_angle``) with ``ext_per_lwc``
        [km-1 per g m-3], ``q_ext``, ``albedo``, ``g`` and ``phase`` [sr-1]; the
        parameters are in its attributes.
    """
    m = _refractive_index(wavelength, refractive_index)
    reff = default_reff() if reff is None else np.asarray(reff, dtype=np.float64)
    angles = default_angles() if angles is None else np.asarray(angles, dtype=np.float64)
    attrs = _table_attrs(wavelength, m, veff)

    if _PACKAGED.exists():
        with xr.open_dataset(_PACKAGED) as ds:
            if _matches(ds, attrs, reff, angles):
                return ds.load()

    key = json.dumps(attrs, sort_keys=True).encode() + reff.tobytes() + angles.tobytes()
    digest = hashlib.sha1(key).hexdigest()[:12]
    path = Path(cache_dir or cache_root()) / (
        f"mie_water_{wavelength:g}um_veff{veff:g}_{digest}.nc"
    )
    if path.exists():
        try:
            with xr.open_dataset(path) as ds:
                if _matches(ds, attrs, reff, angles):
                    return ds.load()
        except (OSError, RuntimeError, ValueError):
            pass  # a damaged cache file: the table is computed again and replaces it

    ds = compute_mie_table(wavelength, m, veff, reff, angles)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with written_whole(path) as partial:
            ds.to_netcdf(partial)
    except OSError as err:
        warnings.warn(f"could not cache the Mie table at {path}: {err}", stacklevel=2)
    return ds
