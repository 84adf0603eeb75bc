"""Measurements in several bands: one-band sets stacked into one, and synthetic ones.

The layout (docs/measurements.md, "Bands"): ``radiance`` and its error variables over
(band, view, row, col), the coordinate ``wavelength`` over ``band`` [micron], positive and
increasing, instead of the attribute; one set of cameras, sun and boundaries for all
bands; every attribute that differs between the bands (the ground albedo, the seeds, the
wall time) a variable over ``band`` of the same name. :mod:`cloudct.measurements` checks
it (``validate_measurements(ds, bands=True)``), reads and writes it, and takes one band
out (:func:`~cloudct.measurements.band_measurements`); this module builds it:
:func:`stack_bands` from one-band sets (the inverse of ``band_measurements``), and
:func:`synthesize_bands` by rendering a microphysical medium in each band.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import xarray as xr

from cloudct.mc.scene import Scene, single_cloud_scene_of
from cloudct.measurements import (
    BAND,
    CAMERA_VARIABLES,
    DEFAULT_BATCHES,
    DEFAULT_PHOTONS,
    IMAGE_DIMS,
    SCENE_ATTRS,
    MeasurementError,
    NoiseModel,
    _listing,
    synthesize_measurements,
    validate_measurements,
)
from cloudct.optics import band_optics


def synthesize_bands(
    medium: xr.Dataset,
    wavelengths: Sequence[float],
    scene: Scene | None = None,
    *,
    photons: int = DEFAULT_PHOTONS,
    seed: int = 0,
    noise: NoiseModel | None = None,
    noise_seed: int | None = None,
    ground_albedo: float | Sequence[float] | None = None,
    optics: str | None = None,
    batches: int = DEFAULT_BATCHES,
    progress: bool | None = None,
    backend: str = "cpu",
    method: str | None = None,
) -> xr.Dataset:
    """Synthetic measurements of a microphysical ``medium`` in several bands: one set with
    bands (module documentation), each band
    :func:`~cloudct.measurements.synthesize_measurements` of the medium's optics at its
    wavelength (:func:`cloudct.optics.band_optics`: its Mie table, the air
    scaled to it), all with the same cameras and sun.

    Band ``i`` (counted from the shortest wavelength) is rendered with seed ``seed + i``
    and its noise drawn with ``noise_seed + i`` (``noise_seed`` default ``seed``), so that
    the bands' errors are independent and the first band is bitwise the one-band set of
    :func:`~cloudct.measurements.synthesize_measurements` with the same seeds. The noise
    model is the same in every band.

    Args:
        medium: a microphysical medium (``lwc``, ``reff``).
        wavelengths: the bands [micron], distinct and increasing.
        scene: as in :func:`~cloudct.measurements.synthesize_measurements`.
        ground_albedo: the ground's albedo in every band (one value) or in each (one per
            band), in [0, 1]; None: the scene's. The set records one attribute where all
            bands have the same, else a variable ``ground_albedo`` over ``band``.
        optics: the cloud optics (:func:`cloudct.optics.band_optics`; None: the medium's
            recorded choice, else the default). HG optics have no droplet absorption: the
            bands then differ only in extinction and air.
        photons, noise, batches, progress, backend, method: as in
            :func:`~cloudct.measurements.synthesize_measurements`, for each band.

    Raises:
        ValueError: an optical medium, wavelengths that are not distinct and increasing,
            a number of ground albedos that is neither 1 nor the number of bands, or what
            :func:`~cloudct.measurements.synthesize_measurements` raises.
    """
    wavelengths = [float(w) for w in wavelengths]
    if not wavelengths:
        raise ValueError("no bands: give at least one wavelength")
    if any(b <= a for a, b in zip(wavelengths, wavelengths[1:], strict=False)):
        raise ValueError("the bands' wavelengths must be distinct and increasing, got "
                         f"{_listing(wavelengths)}")
    if ground_albedo is None or np.ndim(ground_albedo) == 0:
        albedos = [ground_albedo] * len(wavelengths)
    else:
        albedos = [float(a) for a in ground_albedo]
        if len(albedos) == 1:
            albedos = albedos * len(wavelengths)
        if len(albedos) != len(wavelengths):
            raise ValueError(f"{len(albedos)} ground albedos for {len(wavelengths)} bands: "
                             "give one, or one per band")
    optical = band_optics(medium, wavelengths, optics=optics)
    if scene is None:
        scene = single_cloud_scene_of(medium)
    noise_seed = seed if noise_seed is None else int(noise_seed)
    bands = [
        synthesize_measurements(
            band_medium, scene if albedo is None else replace(scene, ground_albedo=float(albedo)),
            photons=photons, seed=seed + i, noise=noise, noise_seed=noise_seed + i,
            wavelength=wavelength, batches=batches, progress=progress, backend=backend,
            method=method,
        )
        for i, (band_medium, wavelength, albedo) in enumerate(
            zip(optical, wavelengths, albedos, strict=True))
    ]
    return stack_bands(bands)



def _same(a, b) -> bool:
    """Two attribute values are equal (arrays element-wise, NaN equal to NaN)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        if a.shape != b.shape:
            return False
        try:
            return bool(np.array_equal(a, b, equal_nan=True))
        except TypeError:  # strings
            return bool(np.array_equal(a, b))
    return bool(a == b) or (isinstance(a, float) and isinstance(b, float)
                            and math.isnan(a) and math.isnan(b))


def stack_bands(measurements: Sequence[xr.Dataset]) -> xr.Dataset:
    """One measurement set with bands from one-band sets of the same cameras and sun, each
    with its ``wavelength`` attribute: the images stacked over ``band`` in increasing
    wavelength, the coordinate ``wavelength``, the attributes that are the same for all
    bands kept and those that differ (numbers or strings: the ground albedo, the seeds,
    the wall time) made variables over ``band``. The inverse of
    :func:`~cloudct.measurements.band_measurements`.

    Raises:
        MeasurementError: a set that is not a valid one-band set or records no wavelength,
            two bands at one wavelength, different cameras, sun or variables, or an array
            attribute that differs between the bands.
    """
    sets = list(measurements)
    if not sets:
        raise MeasurementError("no bands to stack")
    for i, ds in enumerate(sets):
        try:
            validate_measurements(ds)
        except MeasurementError as err:
            raise MeasurementError(f"set {i} of the bands: {err}") from None
        if "wavelength" not in ds.attrs:
            raise MeasurementError(f"set {i} of the bands records no wavelength attribute")
    sets.sort(key=lambda ds: float(ds.attrs["wavelength"]))
    wavelengths = np.array([float(ds.attrs["wavelength"]) for ds in sets])
    if np.any(np.diff(wavelengths) <= 0.0):
        raise MeasurementError(f"two bands at one wavelength: {_listing(wavelengths)} micron")
    first = sets[0]
    images = [name for name, v in first.data_vars.items() if v.dims == IMAGE_DIMS]
    for ds in sets[1:]:
        if set(ds.variables) != set(first.variables):
            raise MeasurementError("the bands hold different variables: "
                                   f"{sorted(set(ds.variables) ^ set(first.variables))}")
        for name, variable in first.variables.items():
            if name not in images and not variable.equals(ds[name].variable):
                what = ("; every band must have the same cameras"
                        if name in CAMERA_VARIABLES else "")
                raise MeasurementError(f"{name} differs between the bands{what}")
    out = first.drop_vars(images)
    for name in images:
        stacked = xr.concat([ds[name] for ds in sets], dim=BAND)
        out[name] = stacked.assign_attrs(first[name].attrs)
    keys = set(first.attrs)
    for ds in sets[1:]:
        if set(ds.attrs) != keys:
            raise MeasurementError("the bands record different attributes: "
                                   f"{sorted(set(ds.attrs) ^ keys)}")
    attrs = {}
    for key, value in first.attrs.items():
        values = [ds.attrs[key] for ds in sets]
        if key == "wavelength":
            continue
        if all(_same(value, v) for v in values[1:]):
            attrs[key] = value
        elif key in SCENE_ATTRS:
            raise MeasurementError(f"{key} differs between the bands; every band must have "
                                   "the same sun and boundaries")
        elif all(np.ndim(v) == 0 for v in values):
            out[key] = (BAND, np.array(values))
            out[key].attrs["long_name"] = f"{key} of each band"
            if key == "ground_albedo":
                out[key].attrs.update(units="1", comment="-1 means no ground")
        else:
            raise MeasurementError(f"the attribute {key} differs between the bands")
    out = out.assign_coords(wavelength=(BAND, wavelengths, {
        "units": "micron", "long_name": "wavelength of the band"}))
    out.attrs = attrs
    validate_measurements(out, bands=True)
    return out
