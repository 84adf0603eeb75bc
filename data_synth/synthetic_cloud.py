"""Synthetic clouds for tests and tutorials: an LES-style cumulus field and a convex blob.

:func:`synthetic_cloud` gives a *microphysical* medium (``lwc``, ``reff``) that looks like a
field of shallow cumulus from a large-eddy simulation, without running one:

1. **Where the cloud is.** White noise on the grid is smoothed by a Gaussian filter
   (``scipy.ndimage.gaussian_filter``, periodic in x and y so that the field can be used with
   periodic boundaries) with standard deviations ``correlation_length`` horizontally and
   ``vertical_correlation_length`` vertically, and normalised to zero mean and unit variance:
   a smooth Gaussian random field f. A cell is cloudy where

       f(x, y, z) - narrowing * s**2 > t,      s = (z - z_base) / (z_top - z_base),

   between cloud base ``z_base`` and the highest top ``z_top``. The threshold t is the
   (1 - ``cloud_fraction``) quantile of f in the lowest cloudy layer, so ``cloud_fraction``
   is the cloudy fraction at cloud base; the term in s**2 makes the clouds narrower towards
   their tops (cumulus towers), so that cloud tops vary from column to column.
2. **How much water.** Inside the cloud the liquid water content grows linearly with the
   height above cloud base, as in an adiabatic parcel, times a taper that brings it smoothly
   to zero at the cloud's edges (entrainment):

       LWC = lwc_gradient * (z - z_base) * smoothstep(excess / edge_width),

   where excess = f - t (in units of the field's standard deviation) and
   smoothstep(u) = 3 u^2 - 2 u^3 for u in [0, 1], 1 beyond. The clouds' upper surfaces,
   where the narrowing term cuts them, keep their LWC up to the top cell, as cumulus tops
   do.
3. **Droplet size.** The effective radius follows the adiabatic LWC of the cell's height
   for a constant droplet number concentration N (extreme inhomogeneous mixing: entrainment
   dilutes the number of droplets, not their size):

       r_eff = (3 LWC_ad / (4 pi rho_w k N))^(1/3),   LWC_ad = lwc_gradient * (z - z_base),

   with rho_w = 10^6 g m-3 and k = 0.8 (the ratio (r_v / r_eff)^3 of maritime cumulus,
   Martin et al. 1994), clipped to :data:`REFF_RANGE` (the bundled Mie table's range).
   So r_eff grows as the cube root of the LWC: for the defaults about 4.5 micron in the
   lowest cloudy layer and 13 micron half a kilometre higher.

:func:`blob_cloud` gives an *optical* medium with one ellipsoid of constant extinction, the
simplest convex cloud, for space-carving tests.

Both return media validated by :func:`cloudct.medium.validate_medium`.
"""

from __future__ import annotations

import numpy as np
import xarray as xr
from scipy.ndimage import gaussian_filter

from cloudct.medium import (
    DEFAULT_AIR_ALBEDO,
    DEFAULT_AIR_EXTINCTION,
    DEFAULT_CLOUD_ALBEDO,
    DEFAULT_CLOUD_G,
    microphysical_medium,
    optical_medium,
)

#: Effective radii [micron] the synthetic cloud is clipped to (the bundled Mie table's range).
REFF_RANGE = (1.0, 25.0)
#: Density of liquid water [g m-3].
WATER_DENSITY = 1.0e6
#: (r_v / r_eff)^3 of maritime cumulus droplet spectra (Martin et al. 1994).
SPECTRAL_SHAPE_K = 0.8


def synthetic_cloud(
    nx: int,
    ny: int,
    nz: int,
    *,
    dx: float = 0.02,
    dy: float | None = None,
    dz: float = 0.04,
    z_bottom: float = 0.0,
    z_base: float | None = None,
    z_top: float | None = None,
    cloud_fraction: float = 0.3,
    correlation_length: float = 0.08,
    vertical_correlation_length: float = 0.25,
    narrowing: float = 2.0,
    edge_width: float = 0.5,
    lwc_gradient: float = 1.5,
    droplet_concentration: float = 100.0,
    air_extinction: float = DEFAULT_AIR_EXTINCTION,
    air_albedo: float = DEFAULT_AIR_ALBEDO,
    seed: int = 0,
) -> xr.Dataset:
    """An LES-style field of cumulus clouds as a microphysical medium (see the module doc).

    Args:
        nx, ny, nz: number of cells along x, y, z (at least 2 each).
        dx, dy, dz: cell sizes [km] (``dy`` defaults to ``dx``); the defaults are those of
            the RICO LES (20 m x 20 m x 40 m).
        z_bottom: altitude of the grid's bottom face [km]; x and y start at 0.
        z_base: cloud base altitude [km]; default two layers above the grid's bottom.
        z_top: altitude above which no cell is cloudy [km]; default one layer below the
            grid's top.
        cloud_fraction: fraction of cloudy cells in the lowest cloudy layer, in (0, 1).
        correlation_length: horizontal standard deviation of the Gaussian filter [km]
            (about the radius of a cloud).
        vertical_correlation_length: vertical standard deviation of the filter [km].
        narrowing: how much the clouds narrow with height: the threshold rises by this many
            standard deviations of the field from base to ``z_top`` (0: straight columns).
        edge_width: width of the LWC taper at cloud edges, in standard deviations of the
            field (> 0).
        lwc_gradient: rate of increase of the LWC with height above cloud base
            [g m-3 per km]; the adiabatic rate is about 2 near a warm cloud base, and 1.5 is
            typical of the sub-adiabatic cores of trade cumulus.
        droplet_concentration: droplet number concentration N [cm-3], which sets r_eff.
        air_extinction, air_albedo: the air [km-1, 1].
        seed: seed of the noise; the same arguments and seed give the same cloud.

    Returns:
        A validated microphysical medium (``lwc``, ``reff``; air), uniformly spaced.

    Raises:
        ValueError: an argument out of range, or a grid and parameters giving no cloud.
    """
    dy = dx if dy is None else dy
    _check_grid(nx, ny, nz, dx, dy, dz)
    x, y, z = _centres(nx, ny, nz, dx, dy, dz, z_bottom)
    z_base = z_bottom + 2.0 * dz if z_base is None else float(z_base)
    z_top = z_bottom + (nz - 1) * dz if z_top is None else float(z_top)
    if not z_base < z_top:
        raise ValueError(f"z_base ({z_base} km) must be below z_top ({z_top} km)")
    if not 0.0 < cloud_fraction < 1.0:
        raise ValueError(f"cloud_fraction must be in (0, 1), got {cloud_fraction}")
    for name, value in (
        ("correlation_length", correlation_length),
        ("vertical_correlation_length", vertical_correlation_length),
        ("edge_width", edge_width),
        ("lwc_gradient", lwc_gradient),
        ("droplet_concentration", droplet_concentration),
    ):
        if not value > 0.0:
            raise ValueError(f"{name} must be positive, got {value}")

    field = _gaussian_random_field(
        (nx, ny, nz),
        (correlation_length / dx, correlation_length / dy, vertical_correlation_length / dz),
        seed,
    )
    height = np.broadcast_to(z - z_base, field.shape)  # km above cloud base
    in_layer = (height >= 0.0) & (z <= z_top)
    if not in_layer.any():
        raise ValueError(f"no cell centre between z_base ({z_base}) and z_top ({z_top}) km")
    base_layer = int(np.argmax(in_layer[0, 0, :]))
    threshold = np.quantile(field[:, :, base_layer], 1.0 - cloud_fraction)
    excess = field - threshold
    cloudy = (excess > narrowing * (height / (z_top - z_base)) ** 2) & in_layer
    adiabatic_lwc = lwc_gradient * np.maximum(height, 0.0)
    lwc = np.where(cloudy, adiabatic_lwc * _smoothstep(excess / edge_width), 0.0)
    reff = np.where(lwc > 0.0, adiabatic_reff(adiabatic_lwc, droplet_concentration), 0.0)
    return microphysical_medium(
        x.ravel(), y.ravel(), z.ravel(), lwc, reff,
        air_extinction=air_extinction,
        air_albedo=air_albedo,
        title="cloudct synthetic cumulus field",
        source=(
            f"data_synth.synthetic_cloud.synthetic_cloud(seed={seed}, cloud_fraction="
            f"{cloud_fraction}, correlation_length={correlation_length} km, "
            f"lwc_gradient={lwc_gradient} g m-3 km-1, N={droplet_concentration} cm-3)"
        ),
    )


def adiabatic_reff(lwc: np.ndarray, droplet_concentration: float) -> np.ndarray:
    """Effective radius [micron] of droplets holding ``lwc`` [g m-3] at a number
    concentration [cm-3]: (3 LWC / (4 pi rho_w k N))^(1/3), clipped to :data:`REFF_RANGE`."""
    number_per_m3 = droplet_concentration * 1.0e6
    volume_radius_cubed = 3.0 * np.asarray(lwc) / (4.0 * np.pi * WATER_DENSITY * number_per_m3)
    reff_m = np.cbrt(volume_radius_cubed / SPECTRAL_SHAPE_K)
    return np.clip(reff_m * 1.0e6, *REFF_RANGE)


def blob_cloud(
    nx: int,
    ny: int,
    nz: int,
    *,
    dx: float = 0.02,
    dy: float | None = None,
    dz: float = 0.04,
    z_bottom: float = 0.0,
    centre: tuple[float, float, float] | None = None,
    semi_axes: tuple[float, float, float] | None = None,
    extinction: float = 20.0,
    cloud_albedo: float = DEFAULT_CLOUD_ALBEDO,
    cloud_g: float = DEFAULT_CLOUD_G,
    air_extinction: float = DEFAULT_AIR_EXTINCTION,
    air_albedo: float = DEFAULT_AIR_ALBEDO,
) -> xr.Dataset:
    """A convex ellipsoidal cloud of constant extinction, as an optical medium.

    A cell belongs to the blob when its centre lies inside the ellipsoid
    ((x - cx) / ax)^2 + ((y - cy) / ay)^2 + ((z - cz) / az)^2 <= 1.

    Args:
        nx, ny, nz, dx, dy, dz, z_bottom: the grid, as in :func:`synthetic_cloud`.
        centre: centre of the ellipsoid [km]; default the centre of the box.
        semi_axes: semi-axes (ax, ay, az) [km]; default 0.35 of the box's extent along
            each axis (the blob spans 70 % of the box).
        extinction: cloud extinction inside the blob [km-1].
        cloud_albedo, cloud_g: cloud single-scattering albedo and HG asymmetry parameter.
        air_extinction, air_albedo: the air [km-1, 1].

    Returns:
        A validated optical medium.

    Raises:
        ValueError: a bad grid, non-positive semi-axes, negative extinction, or an
            ellipsoid that contains no cell centre.
    """
    dy = dx if dy is None else dy
    _check_grid(nx, ny, nz, dx, dy, dz)
    x, y, z = _centres(nx, ny, nz, dx, dy, dz, z_bottom)
    extent = np.array([nx * dx, ny * dy, nz * dz])
    lower = np.array([0.0, 0.0, z_bottom])
    centre_ = lower + 0.5 * extent if centre is None else np.asarray(centre, dtype=float)
    axes = 0.35 * extent if semi_axes is None else np.asarray(semi_axes, dtype=float)
    if axes.shape != (3,) or not np.all(axes > 0.0):
        raise ValueError(f"semi_axes must be three positive lengths, got {semi_axes}")
    if not extinction >= 0.0:
        raise ValueError(f"extinction must be >= 0, got {extinction}")
    r2 = (
        ((x - centre_[0]) / axes[0]) ** 2
        + ((y - centre_[1]) / axes[1]) ** 2
        + ((z - centre_[2]) / axes[2]) ** 2
    )
    inside = r2 <= 1.0
    if not inside.any():
        raise ValueError("the ellipsoid contains no cell centre of the grid")
    return optical_medium(
        x.ravel(), y.ravel(), z.ravel(), np.where(inside, extinction, 0.0),
        cloud_albedo=cloud_albedo,
        cloud_g=cloud_g,
        air_extinction=air_extinction,
        air_albedo=air_albedo,
        title="cloudct ellipsoidal blob",
        source=(
            f"data_synth.synthetic_cloud.blob_cloud(centre={_km(centre_)}, "
            f"semi_axes={_km(axes)}, extinction={extinction:g} km-1)"
        ),
    )


def _km(values: np.ndarray) -> str:
    return "(" + ", ".join(f"{v:.6g}" for v in values) + ") km"


def _check_grid(nx: int, ny: int, nz: int, dx: float, dy: float, dz: float) -> None:
    if min(nx, ny, nz) < 2:
        raise ValueError(f"the grid needs at least 2 cells along each axis, got {(nx, ny, nz)}")
    if not min(dx, dy, dz) > 0.0:
        raise ValueError(f"cell sizes must be positive, got {(dx, dy, dz)}")


def _centres(
    nx: int, ny: int, nz: int, dx: float, dy: float, dz: float, z_bottom: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cell centres shaped (nx, 1, 1), (1, ny, 1), (1, 1, nz) for broadcasting."""
    x = (np.arange(nx) + 0.5) * dx
    y = (np.arange(ny) + 0.5) * dy
    z = z_bottom + (np.arange(nz) + 0.5) * dz
    return x[:, None, None], y[None, :, None], z[None, None, :]


def _gaussian_random_field(
    shape: tuple[int, int, int], sigma_cells: tuple[float, float, float], seed: int
) -> np.ndarray:
    """White noise smoothed by a Gaussian filter (periodic in x and y, reflected in z),
    normalised to zero mean and unit variance."""
    noise = np.random.default_rng(seed).standard_normal(shape)
    field = gaussian_filter(noise, sigma_cells, mode=("wrap", "wrap", "reflect"))
    return (field - field.mean()) / field.std()


def _smoothstep(u: np.ndarray) -> np.ndarray:
    """3 u^2 - 2 u^3 on [0, 1], 0 below and 1 above."""
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)
