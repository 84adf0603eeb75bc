"""Sensors beyond cameras: domain-mean fluxes and radiance probes (docs/sensors.md).

What a plane-parallel code or a satellite product reports, from one set of forward photons:

- **Fluxes**, as shares of the solar power entering the domain (the weight every photon
  starts with, :mod:`cloudct.mc.sun`): the albedo (leaving through the top), the
  transmittance (reaching the bottom face travelling down; direct: unscattered, diffuse:
  the rest, including light the ground reflected and the medium sent back down), the
  absorptance of the medium (weight x (1 - albedo) at every collision, an expected-value
  estimator), the share leaving through the side faces (open boundaries) and the share the
  ground absorbs (1 - A of all that reaches it). The forward tracer adds them as it goes
  (the ``fluxes`` tallies of :func:`cloudct.mc.forward.trace_photon`: same paths, same
  random streams as a render with the same seed).
- **Radiance probes**: the radiance travelling in a direction w, averaged over the domain's
  projected area perpendicular to w (the top face, or the bottom face for downward
  directions, with periodic boundaries; the box's silhouette with open ones). Local
  estimation along the fixed direction: every scattering or ground event adds

      weight x f_p(x, mu) x T(x -> out along w) / A_perp(w),

  mu the cosine between the incoming direction and w (ground: A w_z / pi instead of f_p),
  A_perp(w) = Lx Ly |w_z| (+ Ly Lz |w_x| + Lx Lz |w_y| for open boundaries). Each probe is
  a one-pixel view of kind :data:`cloudct.mc.cameras.DOMAIN`, so the engine's local
  estimate serves it unchanged; its variance has no 1 / r^2 of a near pinhole and does not
  depend on the domain's size.

Both back ends (the ``sensors`` batch kernel of :mod:`cloudct.mc.estimate`): the CPU's
:func:`cloudct.mc.forward.sensor_batches`, or on a GPU the forward render kernel's sibling
that tallies the fluxes too (:func:`cloudct.mc.cuda_kernels.forward_sensor_kernel`); the
same photons either way.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import xarray as xr

from cloudct.mc.cameras import DOMAIN, CameraArrays, travel_direction
from cloudct.mc.estimate import (
    KernelInputs,
    Sampling,
    batch_means,
    default_aim_fraction,
    mean_and_std_error,
    medium_arrays,
)
from cloudct.mc.forward import (
    FLUX_DIFFUSE,
    FLUX_DIRECT,
    FLUX_GROUND,
    FLUX_MEDIUM,
    FLUX_SIDE,
    FLUX_TOP,
    NFLUX,
)
from cloudct.mc.render import RADIANCE_UNITS
from cloudct.mc.scene import BOUNDARIES
from cloudct.mc.sun import Sun, sun_arrays
from cloudct.optics import optics_name


def probe_arrays(
    directions: np.ndarray, edges: tuple[np.ndarray, ...], periodic: bool, aim_fraction: float
) -> CameraArrays:
    """One :data:`~cloudct.mc.cameras.DOMAIN` view per unit propagation direction (rows of
    ``directions``): it sees every event, along that direction, and divides by the domain's
    area projected perpendicular to it."""
    lx, ly, lz = (e[-1] - e[0] for e in edges)
    w = np.abs(directions)
    area = lx * ly * w[:, 2]
    if not periodic:
        area = area + ly * lz * w[:, 0] + lx * lz * w[:, 1]
    n = len(directions)
    zeros = np.zeros((n, 3))
    return CameraArrays(
        position=zeros, forward=-np.asarray(directions, float), right=zeros, up=zeros,
        half_width=np.zeros(n), half_height=np.zeros(n), pixel_area=area,
        projection=np.full(n, DOMAIN, np.int64), nrows=1, ncols=1,
        aim_fraction=float(aim_fraction),
    )


def domain_means(
    medium: xr.Dataset,
    *,
    directions: Sequence[tuple[float, float]] = (),
    sun: Sun | None = None,
    boundary: str = "open",
    ground_albedo: float | None = None,
    photons: int = 1_000_000,
    seed: int = 0,
    batches: int = 32,
    rr_depth: int = 100,
    rr_survival: float = 0.95,
    aim_fraction: float | None = None,
    progress: bool | None = None,
    backend: str = "cpu",
    entry_cloud_share: float = 0.0,
) -> xr.Dataset:
    """Domain-mean fluxes and radiance probes of ``medium`` lit by ``sun``.

    Parameters
    ----------
    medium
        A medium Dataset (optical, or microphysical: converted with its optics).
    directions
        Probe directions (zenith, azimuth) in degrees of the light's *propagation*: zenith
        from +z, below 90 for light leaving the top (reflected; the direction towards a
        sensor above), above 90 for light arriving at the bottom (transmitted; 180 is
        straight down); azimuth from +x toward +y. A plane-parallel code's transmitted
        view angle theta_v (from the nadir) is zenith 180 - theta_v.
    sun, boundary, ground_albedo
        As in :class:`cloudct.mc.scene.Scene` (default sun overhead, open boundaries, no
        ground).
    photons, seed, batches, rr_depth, rr_survival, aim_fraction, progress
        As for :func:`cloudct.mc.render.render`; ``aim_fraction`` aims scattering
        directions at the probe directions.
    backend
        ``"cpu"``, ``"cuda"`` or ``"auto"`` (:mod:`cloudct.mc.backend`).
    entry_cloud_share
        The share m in [0, 1) of photons entering where the clouds are, as for
        :func:`cloudct.mc.render.render` (0: uniform entry). The shares stay those of the
        solar power entering the domain: each photon's weight, not its count, carries it.

    Returns
    -------
    A Dataset with ``radiance`` and ``radiance_std_error`` over ``direction`` (coordinates
    ``zenith`` and ``azimuth``), the shares ``albedo``, ``transmittance`` (with
    ``transmittance_direct`` and ``transmittance_diffuse``), ``absorptance``,
    ``side_escape``, ``ground_absorptance`` and their sum ``energy_balance`` (1 by energy
    conservation), each with a ``*_std_error`` over the independent batches, and
    ``incoming_power``.
    """
    if boundary not in BOUNDARIES:
        raise ValueError(f"boundary must be one of {BOUNDARIES}, got {boundary!r}")
    if ground_albedo is not None and not 0.0 <= ground_albedo <= 1.0:
        raise ValueError(f"ground_albedo must be in [0, 1], got {ground_albedo}")
    sampling = Sampling(batches, seed, rr_depth, rr_survival, backend)
    per_batch = sampling.per_batch(photons)
    sun = Sun() if sun is None else sun
    angles = np.array(directions, dtype=float).reshape(-1, 2)
    if not np.all(np.isfinite(angles)) or np.any(
            (angles[:, 0] < 0.0) | (angles[:, 0] > 180.0)
            | (np.abs(angles[:, 0] - 90.0) < 1e-6)):
        raise ValueError("probe zenith angles must be in [0, 90) (leaving the top) or "
                         f"(90, 180] (arriving at the bottom), got {angles[:, 0].tolist()}")
    grid, bank, edges, _ = medium_arrays(medium)  # radiances: no gradient to scale
    periodic = boundary == "periodic"
    if aim_fraction is None:
        aim_fraction = default_aim_fraction(bank)
    travel = np.array([travel_direction(z, a) for z, a in angles]).reshape(-1, 3)
    k = KernelInputs(
        grid=grid, bank=bank, cams=probe_arrays(travel, edges, periodic, aim_fraction),
        copies=np.zeros((len(angles), 4), np.int64),
        sun=sun_arrays(sun, edges, periodic, grid, entry_cloud_share),
        periodic=periodic, ground=-1.0 if ground_albedo is None else float(ground_albedo),
        edges=edges,
    )
    fluxes = np.zeros((batches, 1, 1, NFLUX))
    means, run = batch_means("sensors", k, (fluxes,), per_batch=per_batch, sampling=sampling,
                             progress=progress, desc="fluxes")
    shares = fluxes[:, 0, 0, :] / (per_batch * k.sun.power)
    info = dict(photons=per_batch * batches, seed=seed, batches=batches,
                events=run["events"], wall_time=run["wall_time"], rr_depth=rr_depth,
                rr_survival=rr_survival, aim_fraction=float(aim_fraction),
                entry_cloud_share=k.sun.cloud_share, backend=run["backend"],
                optics=optics_name(medium))
    return _sensors_dataset(means[:, :, 0, 0], shares, angles, k, sun, boundary,
                            ground_albedo, info)


#: The flux shares of :func:`domain_means`: name -> (tallies summed, long name).
FLUX_SHARES = {
    "albedo": ((FLUX_TOP,), "domain-mean albedo: power leaving through the top / power in"),
    "transmittance": ((FLUX_DIRECT, FLUX_DIFFUSE),
                      "domain-mean transmittance: downward power reaching the bottom face "
                      "(direct + diffuse) / power in"),
    "transmittance_direct": ((FLUX_DIRECT,), "unscattered power reaching the bottom face / "
                             "power in"),
    "transmittance_diffuse": ((FLUX_DIFFUSE,), "scattered (or ground-reflected) downward "
                              "power reaching the bottom face / power in"),
    "absorptance": ((FLUX_MEDIUM,), "power absorbed in the medium / power in"),
    "side_escape": ((FLUX_SIDE,), "power leaving through the side faces (open boundaries) "
                    "/ power in"),
    "ground_absorptance": ((FLUX_GROUND,), "power absorbed by the ground / power in"),
}


def _sensors_dataset(
    radiance: np.ndarray, shares: np.ndarray, angles: np.ndarray, k: KernelInputs, sun: Sun,
    boundary: str, ground_albedo: float | None, info: dict,
) -> xr.Dataset:
    """The Dataset of :func:`domain_means` from per-batch probe radiances (batches,
    direction) and flux shares (batches, NFLUX)."""
    ds = xr.Dataset(coords={"direction": np.arange(len(angles))})
    ds = ds.assign_coords(zenith=("direction", angles[:, 0]),
                          azimuth=("direction", angles[:, 1]))
    ds["direction"].attrs.update(long_name="probe index")
    ds["zenith"].attrs.update(units="degree", long_name="zenith angle of the light's "
                              "propagation direction (< 90: leaving the top, > 90: arriving "
                              "at the bottom)")
    ds["azimuth"].attrs.update(units="degree", long_name="azimuth of the light's propagation "
                               "direction, from +x toward +y")
    mean, se = mean_and_std_error(radiance)
    ds["radiance"] = ("direction", mean)
    ds["radiance"].attrs.update(
        units=RADIANCE_UNITS, long_name="domain-mean radiance in the probe direction",
        comment="average over the domain's area projected perpendicular to the direction "
                "(periodic: the top or bottom face); solar irradiance perpendicular to the "
                "rays is 1",
    )
    ds["radiance_std_error"] = ("direction", se)
    ds["radiance_std_error"].attrs.update(units=RADIANCE_UNITS,
                                          long_name="Monte Carlo standard error of radiance")
    lost_bottom = (FLUX_GROUND,) if ground_albedo is not None else (FLUX_DIRECT, FLUX_DIFFUSE)
    rows = dict(FLUX_SHARES)
    rows["energy_balance"] = (
        (FLUX_TOP, FLUX_MEDIUM, FLUX_SIDE, *lost_bottom),
        "albedo + absorptance + side_escape + ground_absorptance (no ground: + "
        "transmittance); 1 by energy conservation",
    )
    for name, (kinds, long_name) in rows.items():
        mean, se = mean_and_std_error(shares[:, list(kinds)].sum(axis=1))
        ds[name] = ((), mean)
        ds[name].attrs.update(units="1", long_name=long_name)
        ds[f"{name}_std_error"] = ((), se)
        ds[f"{name}_std_error"].attrs.update(units="1",
                                             long_name=f"Monte Carlo standard error of {name}")
    ds["incoming_power"] = ((), k.sun.power)
    ds["incoming_power"].attrs.update(
        units="km2", long_name="solar power entering the domain (irradiance 1 perpendicular "
                               "to the rays, times the sunlit faces' projected area)")
    ds.attrs.update(
        title="cloudct domain-mean fluxes and radiance probes", Conventions="CF-1.8",
        sun_zenith=sun.zenith, sun_azimuth=sun.azimuth,
        sun_azimuth_convention="direction towards the sun, degrees from +x toward +y",
        boundary=boundary, ground_albedo=-1.0 if ground_albedo is None else ground_albedo,
        ground_albedo_note="-1 means no ground", method="forward", **info,
    )
    return ds
