"""The first guess of a retrieval of LWC and r_eff (issue 53,
:mod:`cloudct.retrieval.microphysics`).

The first guess (:func:`microphysical_first_guess`) is the carved extinction turned into
LWC at a constant r_eff: LWC = beta / e(r_eff), e the table's extinction per unit LWC
(:mod:`cloudct.physics.microphysics`). The constant is the one with which the first
guess's images in the longest band are as bright as the measured ones
(:func:`brightness_reff`: the bispectral idea of Nakajima & King 1990, J. Atmos. Sci. 47,
1878, for the whole cloud at once: at a fixed extinction in the visible, larger droplets
hold more water and absorb more in the shortwave infrared); without a fit,
:data:`FIRST_GUESS_REFF` = 10 micron. A constant leaves the images to tell the r_eff
profile (the r_eff gradient can move it either way) and does not presume a cloud base that
the carving knows only to a voxel or two.

With ``extinction_share`` > 0 (:func:`first_guess`) the extinction comes not from the
carving but from a retrieval of the extinction in the shortest band
(:class:`cloudct.retrieval.loop.Retrieval` from the carved start, with the defaults of its
optics) that takes that share of the run: the images of the visible band alone tell the
extinction, and its retrieval's estimators and schedule are the product's best; r_eff and
LWC then start from its iterate average. With ``hold_extinction`` the retrieval of LWC and
r_eff keeps that extinction and moves r_eff alone (:mod:`cloudct.retrieval.microphysics`).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace

import numpy as np
import xarray as xr

from cloudct.mc.render import render
from cloudct.mc.scene import Scene
from cloudct.measurements import BAND_TOLERANCE, band_measurements, band_wavelengths
from cloudct.medium import is_optical, microphysical_medium
from cloudct.optics import GRID, PHASE_TRUNCATION, optics_name, phase_truncation, to_optical
from cloudct.physics.microphysics import extinction_lwc_derivative
from cloudct.physics.mie import mie_table
from cloudct.retrieval.carving import FIT_PHOTONS
from cloudct.retrieval.config import OPTICS_TRUNCATION, RetrievalConfig, settings_for_optics
from cloudct.retrieval.loop import Retrieval

LOGGER = logging.getLogger(__name__)

#: The first guess's effective radius [micron] (module documentation).
FIRST_GUESS_REFF = 10.0


def microphysical_first_guess(initial: xr.Dataset, table: xr.Dataset,
                              reff: float = FIRST_GUESS_REFF) -> xr.Dataset:
    """The microphysical medium of an optical one (e.g. the carved start,
    :func:`cloudct.retrieval.carving.initial_medium`): LWC = beta / e(``reff``) [g m-3]
    and r_eff = ``reff`` [micron] where the cloud extinction beta > 0 (0 elsewhere), e the
    extinction per unit LWC of ``table``, whose wavelength must be the extinction's; the
    grid and the air (at the wavelength it was given at) are kept."""
    if not is_optical(initial):
        raise ValueError("the first guess of LWC and r_eff is made from a cloud extinction "
                         "(an optical medium, e.g. the carved start)")
    at = float(initial.attrs.get("wavelength", table.attrs["wavelength"]))
    if abs(at - float(table.attrs["wavelength"])) > BAND_TOLERANCE:
        raise ValueError(f"the extinction is at {at:g} micron, the Mie table at "
                         f"{float(table.attrs['wavelength']):g}: give that band's table")
    beta = initial["cloud_extinction"].transpose(*GRID).values.astype(float)
    cloudy = beta > 0.0
    per_lwc = extinction_lwc_derivative(np.zeros_like(beta), np.full(beta.shape, reff), table)
    air_at = initial.attrs.get("air_extinction_wavelength", initial.attrs.get("wavelength"))
    return microphysical_medium(
        initial["x"].values, initial["y"].values, initial["z"].values,
        np.where(cloudy, beta / per_lwc, 0.0), np.where(cloudy, reff, 0.0),
        z_bounds=initial["z_bounds"].values if "z_bounds" in initial else None,
        air_extinction=initial["air_extinction"], air_albedo=float(initial["air_albedo"]),
        air_extinction_wavelength=None if air_at is None else float(air_at),
        title="cloudct first guess of LWC and r_eff",
        source=f"cloudct.retrieval.microphysics_first_guess.microphysical_first_guess: the cloud "
        f"extinction at {at:g} micron as LWC at r_eff {reff:g} micron",
    ).assign_attrs(optics="mie")


def brightness_reff(
    initial: xr.Dataset,
    measurements: xr.Dataset,
    table: xr.Dataset,
    *,
    band_table: xr.Dataset | None = None,
    photons: int = FIT_PHOTONS,
    seed: int = 0,
    phase_truncation: float = OPTICS_TRUNCATION["mie"],
    scan: int = 9,
    steps: int = 8,
    backend: str = "cpu",
) -> float:
    """The constant r_eff [micron] with which :func:`microphysical_first_guess` of the
    optical medium ``initial`` (its extinction in the band of ``table``) renders the
    longest band of ``measurements`` as bright as measured (module documentation), with
    that band's Mie table ``band_table`` (default: :func:`~cloudct.physics.mie.mie_table`
    at the v_eff of ``table``).

    The summed radiance of the band's measured pixels, B*, is matched by that of renders
    B(r_eff) (forward, ``photons`` photons, the same ``seed`` every time so that B varies
    smoothly with r_eff; the peak cut at ``phase_truncation`` degrees as the retrieval's
    paths see it). B rises with r_eff while the droplets are small against the wavelength
    (the band's extinction grows towards the visible one's) and then falls (more water,
    more absorption): B is rendered at ``scan`` r_eff spaced evenly in log r over the range
    both tables cover, and the root of log B(r) = log B* on the falling side of the
    brightest is found by bisection in log r, ``steps`` renders more (8: to 0.2 % in r).
    Where B* lies beyond that side's B, its nearer end is returned and a line logged."""
    longest = float(band_wavelengths(measurements).max())
    band = band_measurements(measurements, longest)
    measured = band["radiance"].values
    observed = np.isfinite(measured)
    target = float(measured[observed].sum())
    scene = Scene.from_dataset(band)
    if band_table is None:
        band_table = mie_table(wavelength=longest, veff=float(table.attrs["veff"]))
    low = max(float(table["reff"].values[0]), float(band_table["reff"].values[0]))
    high = min(float(table["reff"].values[-1]), float(band_table["reff"].values[-1]))

    def log_ratio(log_reff: float) -> float:
        medium = microphysical_first_guess(initial, table, math.exp(log_reff))
        optical = to_optical(medium.assign_attrs({PHASE_TRUNCATION: phase_truncation}),
                             band_table, optics="mie")
        images = render(optical, scene, photons=photons, seed=seed, progress=False,
                        backend=backend)
        return math.log(float(images["radiance"].values[observed].sum()) / target)

    grid = np.linspace(math.log(low), math.log(high), scan)
    ratios = np.array([log_ratio(x) for x in grid])
    brightest = int(np.argmax(ratios))
    darker = np.flatnonzero(ratios[brightest:] <= 0.0)
    if ratios[brightest] <= 0.0 or darker.size == 0:
        end = math.exp(grid[brightest] if ratios[brightest] <= 0.0 else grid[-1])
        LOGGER.info("first guess r_eff %.3g micron: the %g micron images are %s than any "
                    "r_eff in %g..%g micron renders them", end, longest,
                    "brighter" if ratios[brightest] <= 0.0 else "darker", low, high)
        return end
    lo, hi = grid[brightest + darker[0] - 1], grid[brightest + darker[0]]
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        if log_ratio(mid) > 0.0:
            lo = mid
        else:
            hi = mid
    return math.exp(0.5 * (lo + hi))


@dataclass
class FirstGuess:
    """The start of a retrieval of LWC and r_eff (:func:`first_guess`): the microphysical
    ``medium``, the cloud ``mask`` (x, y, z), the first guess's constant ``reff``
    [micron], the ``config`` of the retrieval of LWC and r_eff (its time limit or
    iterations less the extinction stage's) and the extinction stage's result (None
    without one)."""

    medium: xr.Dataset
    mask: np.ndarray
    reff: float
    config: RetrievalConfig
    extinction_result: xr.Dataset | None = None


def extinction_stage(measurements: xr.Dataset, carved: xr.Dataset, config: RetrievalConfig,
                     *, truth: xr.Dataset | None = None, backend: str = "cpu",
                     progress: bool | None = None) -> xr.Dataset:
    """The result of the retrieval of the extinction in the shortest band of
    ``measurements`` from the optical medium ``carved`` (:class:`~cloudct.retrieval.loop.
    Retrieval` with the defaults of its optics) for ``config.extinction_share`` of
    ``config.time_limit`` (without one: of ``config.iterations``), with ``config``'s seed,
    phase truncation and ``iteration_seconds`` (its photons fitted to them); ``truth``
    (microphysical, optional) gives its log's epsilon of the extinction."""
    shortest = float(band_wavelengths(measurements).min())
    settings = {"seed": config.seed, "phase_truncation": config.phase_truncation,
                "iteration_seconds": config.iteration_seconds, "iterations": config.iterations}
    if config.time_limit is None:
        settings["iterations"] = _stage_iterations(config)
    else:
        settings["time_limit"] = config.extinction_share * config.time_limit
    settings = settings_for_optics({k: v for k, v in settings.items() if v is not None},
                                   optics_name(carved), phase_truncation(carved))
    veff = float(truth["veff"].max()) if truth is not None and "veff" in truth else None
    optical_truth = None if truth is None else to_optical(
        truth, mie_table(wavelength=shortest, **({} if veff is None else {"veff": veff})),
        optics="mie")
    run = Retrieval(band_measurements(measurements, shortest), carved,
                    RetrievalConfig(**settings), truth=optical_truth, backend=backend)
    return run.run(progress=progress)


def first_guess(measurements: xr.Dataset, carved: xr.Dataset, config: RetrievalConfig, *,
                table: xr.Dataset, band_table: xr.Dataset | None = None,
                truth: xr.Dataset | None = None, backend: str = "cpu",
                progress: bool | None = None) -> FirstGuess:
    """The start of a retrieval of LWC and r_eff from the optical medium ``carved`` (the
    carved hull's extinction in the band of the Mie ``table``, the shortest band): with
    ``config.extinction_share`` > 0 the extinction of :func:`extinction_stage` (its iterate
    average where it keeps one), else the carved one, made LWC at :func:`brightness_reff`
    (module documentation; ``band_table``: the longest band's table, as there); the mask is
    the carved hull, and the returned config has the extinction stage's time (or
    iterations) taken off and ``hold_extinction`` unset made true after an extinction
    stage (false without one)."""
    rest, result, mask = replace(config, hold_extinction=bool(config.hold_extinction)), None, None
    start = carved
    if config.extinction_share > 0.0 and (config.time_limit is not None
                                          or _stage_iterations(config) > 0):
        result = extinction_stage(measurements, carved, config, truth=truth, backend=backend,
                                  progress=progress)
        extinction = result.get("cloud_extinction_average", result["cloud_extinction"])
        start = carved.copy()
        start["cloud_extinction"] = carved["cloud_extinction"].copy(
            data=extinction.transpose(*carved["cloud_extinction"].dims).values)
        mask = result["cloud_mask"].transpose(*GRID).values.astype(bool)
        rest = replace(config, hold_extinction=config.hold_extinction is not False)
        if config.time_limit is None:
            rest.iterations -= int(result.attrs["iterations_done"])
        else:
            rest.time_limit = max(config.time_limit - float(result.attrs["elapsed_s"]), 0.0)
    reff = brightness_reff(start, measurements, table, band_table=band_table,
                           backend=backend, phase_truncation=_truncation(config))
    medium = microphysical_first_guess(start, table, reff)
    if mask is None:  # the carved start: where it holds water
        mask = medium["lwc"].transpose(*GRID).values > 0.0
    return FirstGuess(medium, mask, reff, rest, result)


def stage_attrs(guess: FirstGuess) -> dict:
    """The first guess's record for a result's attributes: its r_eff and the extinction
    stage's iterations and seconds (0 without one)."""
    result = guess.extinction_result
    return {"first_guess_reff": guess.reff, "first_guess_reff_units": "micron",
            "extinction_stage_iterations": 0 if result is None
            else int(result.attrs["iterations_done"]),
            "extinction_stage_seconds": 0.0 if result is None
            else float(result.attrs["elapsed_s"])}


def _stage_iterations(config: RetrievalConfig) -> int:
    """The extinction stage's iterations in a run without a time limit: its share of the
    run's, rounded down (below a share of 1, at least one is left to LWC and r_eff)."""
    return int(config.extinction_share * config.iterations)


def _truncation(config: RetrievalConfig) -> float:
    """The phase truncation [degrees] the retrieval's paths see (config's, else the Mie
    default)."""
    return (OPTICS_TRUNCATION["mie"] if config.phase_truncation is None
            else config.phase_truncation)
