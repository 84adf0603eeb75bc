"""Validation of a medium Dataset against the schema (:mod:`cloudct.medium.schema`):
:func:`validate_medium` raises :class:`~cloudct.medium.schema.MediumError` naming the
offending variable, and where its first offending value is. Nothing is clipped or
repaired silently.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from cloudct.medium.schema import (
    _COORDINATES,
    _MICROPHYSICAL,
    _OPTICAL,
    _VARIABLES,
    AIR_EXTINCTION_WAVELENGTH,
    GRID_DIMS,
    SPACING_RTOL,
    MediumError,
)
from cloudct.physics.transmittance import FAMILIES as TRANSMITTANCE_FAMILIES
from cloudct.units import units_problem


def validate_medium(ds: xr.Dataset) -> None:
    """Check that ``ds`` follows the medium schema; raise :class:`MediumError` if not.

    Checked, in this order:

    1. a complete cloud description (microphysical: ``lwc`` + ``reff`` [+ ``veff``];
       optical: ``cloud_extinction`` + ``cloud_albedo`` + exactly one of ``cloud_g`` or
       ``cloud_phase`` + ``cloud_phase_index``), no partial description, and air
       (``air_extinction``, ``air_albedo``). A Dataset may carry both complete cloud
       descriptions (e.g. an optical medium that keeps the microphysics it came from).
    2. the grid: coordinates ``x``, ``y``, ``z`` present, 1-D, finite, strictly increasing,
       in km; ``x`` and ``y`` uniform with at least 2 cells; ``z`` uniform with at least
       2 cells, or described by ``z_bounds`` (contiguous cells, each ``z`` at the midpoint
       of its bounds, ``z.attrs["bounds"] == "z_bounds"``).
    3. every schema variable: allowed dimensions, numeric dtype, ``units`` (where the
       attribute is present), no NaN or infinity.
    4. ranges: lwc, extinctions >= 0; reff and veff > 0 where lwc > 0 and >= 0 elsewhere
       (their value is ignored where lwc = 0); albedos in [0, 1]; |g| < 1; phase table
       rows >= 0 and not all zero on scattering angles rising from 0 to 180 degrees;
       integer ``cloud_phase_index`` within the table; ``wavelength`` and
       ``air_extinction_wavelength`` attributes > 0.

    Variables outside the schema are allowed and ignored.
    """
    if not isinstance(ds, xr.Dataset):
        raise MediumError(f"a medium must be an xarray.Dataset, got {type(ds).__name__}")
    _check_descriptions(ds)
    _check_grid(ds)
    for name in _VARIABLES:
        if name in ds:
            _check_form(ds, name)
    _check_values(ds)


def _check_descriptions(ds: xr.Dataset) -> None:
    micro = [v for v in _MICROPHYSICAL if v in ds]
    optical = [v for v in _OPTICAL if v in ds]
    if not micro and not optical:
        raise MediumError(
            "no cloud description: a medium needs lwc and reff (microphysical) or "
            "cloud_extinction, cloud_albedo and cloud_g or cloud_phase + cloud_phase_index "
            "(optical)"
        )
    if micro:
        for name in ("lwc", "reff"):
            if name not in ds:
                raise MediumError(
                    f"incomplete microphysical description: {name} is missing "
                    f"(found {', '.join(micro)}; lwc and reff are both required)"
                )
    if optical:
        for name in ("cloud_extinction", "cloud_albedo"):
            if name not in ds:
                raise MediumError(
                    f"incomplete optical description: {name} is missing "
                    f"(found {', '.join(optical)})"
                )
        if "cloud_g" in ds and "cloud_phase" in ds:
            raise MediumError("both cloud_g and cloud_phase are present: keep one phase function")
        if "cloud_phase" in ds and "cloud_phase_index" not in ds:
            raise MediumError("cloud_phase is present but cloud_phase_index is missing")
        if "cloud_phase_index" in ds and "cloud_phase" not in ds:
            raise MediumError("cloud_phase_index is present but cloud_phase is missing")
        if "cloud_phase_weight" in ds and "cloud_phase" not in ds:
            raise MediumError("cloud_phase_weight is present but cloud_phase is missing")
        if "cloud_g" not in ds and "cloud_phase" not in ds:
            raise MediumError(
                "incomplete optical description: no phase function "
                "(cloud_g, or cloud_phase + cloud_phase_index)"
            )
    if "air_extinction" not in ds:
        raise MediumError("air_extinction is missing (use 0 for a medium without air)")
    if "air_albedo" not in ds:
        raise MediumError("air_albedo is missing")


def _check_grid(ds: xr.Dataset) -> None:
    for name in GRID_DIMS:
        if name not in ds.coords:
            raise MediumError(f"coordinate {name} is missing")
        coordinate = ds.coords[name]
        if coordinate.dims != (name,):
            raise MediumError(f"coordinate {name} must be 1-D along {name}, has {coordinate.dims}")
        _check_form(ds, name)
        _check_increasing(name, coordinate.values)
    for name in ("x", "y"):
        _check_uniform(name, ds[name].values, "x and y must be uniformly spaced")
    bounds_name = ds["z"].attrs.get("bounds")
    if "z_bounds" in ds and bounds_name != "z_bounds":
        raise MediumError(
            f'z_bounds is present but z.attrs["bounds"] is {bounds_name!r}; expected "z_bounds"'
        )
    if bounds_name is not None and bounds_name != "z_bounds":
        raise MediumError(f'z.attrs["bounds"] is {bounds_name!r}; the schema uses "z_bounds"')
    if bounds_name is None:
        _check_uniform("z", ds["z"].values, "non-uniform z needs a z_bounds variable")
    else:
        _check_z_bounds(ds)


def _check_increasing(name: str, values: np.ndarray) -> None:
    steps = np.diff(values)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0))
        raise MediumError(
            f"coordinate {name} must be strictly increasing, but {name}[{k}] = "
            f"{values[k]:g} and {name}[{k + 1}] = {values[k + 1]:g}"
        )


def _check_uniform(name: str, values: np.ndarray, hint: str) -> None:
    if values.size < 2:
        raise MediumError(
            f"coordinate {name} has {values.size} cell; at least 2 are needed to know its "
            f"spacing ({hint})"
        )
    steps = np.diff(values.astype(np.float64))
    mean = steps.mean()
    worst = np.max(np.abs(steps - mean))
    if worst > SPACING_RTOL * mean:
        raise MediumError(
            f"coordinate {name} is not uniformly spaced (spacings from {steps.min():g} to "
            f"{steps.max():g} km); {hint}"
        )


def _check_z_bounds(ds: xr.Dataset) -> None:
    if "z_bounds" not in ds:
        raise MediumError('z.attrs["bounds"] names z_bounds but there is no z_bounds variable')
    bounds = ds["z_bounds"]
    if bounds.dims != ("z", "nv") or bounds.shape[1] != 2:
        raise MediumError(
            f"z_bounds must have dimensions ('z', 'nv') with nv = 2, has {bounds.dims} "
            f"of shape {bounds.shape}"
        )
    _check_form(ds, "z_bounds")
    lower, upper = bounds.values[:, 0], bounds.values[:, 1]
    thickness = upper - lower
    if np.any(thickness <= 0):
        k = int(np.argmax(thickness <= 0))
        raise MediumError(f"z_bounds[{k}] = ({lower[k]:g}, {upper[k]:g}): lower must be < upper")
    gaps = np.abs(lower[1:] - upper[:-1])
    if np.any(gaps > SPACING_RTOL * thickness[1:]):
        k = int(np.argmax(gaps > SPACING_RTOL * thickness[1:]))
        raise MediumError(
            f"z_bounds cells are not contiguous: cell {k} ends at {upper[k]:g} km but cell "
            f"{k + 1} starts at {lower[k + 1]:g} km"
        )
    z = ds["z"].values
    off = np.abs(z - 0.5 * (lower + upper))
    if np.any(off > SPACING_RTOL * thickness):
        k = int(np.argmax(off > SPACING_RTOL * thickness))
        raise MediumError(
            f"z_bounds is inconsistent with z: z[{k}] = {z[k]:g} km is not the midpoint of "
            f"its bounds ({lower[k]:g}, {upper[k]:g}) km"
        )


def _check_form(ds: xr.Dataset, name: str) -> None:
    """Dimensions, dtype, units and finiteness of one variable or coordinate."""
    spec = _VARIABLES.get(name) or _COORDINATES[name]
    array = ds[name]
    if array.dims not in spec.dims:
        expected = " or ".join(str(d) for d in spec.dims)
        raise MediumError(f"{name} has dimensions {array.dims}; expected {expected}")
    kind = array.dtype.kind
    if name == "cloud_phase_index":
        if kind not in "iu":
            raise MediumError(f"cloud_phase_index must have an integer dtype, has {array.dtype}")
    elif kind not in "iuf":
        raise MediumError(f"{name} must be a real number array, has dtype {array.dtype}")
    if "units" in array.attrs:
        problem = units_problem(name, array.attrs["units"], spec.units)
        if problem is not None:
            raise MediumError(problem)
    bad = ~np.isfinite(array.values)
    if name == "transmittance_mode":  # the power law's a may be +inf: exponential there
        bad &= array.values != np.inf
    if np.any(bad):
        raise MediumError(
            f"{name} has {int(bad.sum())} NaN or infinite values{_first(array, bad)}; note "
            "that assigning a DataArray on other coordinates than the medium grid fills the "
            "mismatch with NaN"
        )


def _check_values(ds: xr.Dataset) -> None:
    for name in ("lwc", "cloud_extinction", "air_extinction"):
        if name in ds:
            _require(ds[name], ds[name].values >= 0, "must be >= 0")
    if "lwc" in ds:
        cloudy = ds["lwc"].values > 0
        for name in ("reff", "veff"):
            if name in ds:
                _require(ds[name], ds[name].values >= 0, "must be >= 0")
                on_grid = ds[name].broadcast_like(ds["lwc"])
                _require(on_grid, ~cloudy | (on_grid.values > 0), "must be > 0 where lwc > 0")
    for name in ("cloud_albedo", "air_albedo"):
        if name in ds:
            values = ds[name].values
            _require(ds[name], (values >= 0) & (values <= 1), "must be in [0, 1]")
    if "cloud_g" in ds:
        _require(ds["cloud_g"], np.abs(ds["cloud_g"].values) < 1, "must satisfy -1 < g < 1")
    if "cloud_phase" in ds:
        _check_phase_table(ds)
    check_transmittance(ds)
    for name in ("wavelength", AIR_EXTINCTION_WAVELENGTH):
        if name in ds.attrs:
            wavelength = ds.attrs[name]
            number = isinstance(wavelength, (int, float, np.integer, np.floating))
            if not (number and np.isfinite(wavelength) and wavelength > 0):
                raise MediumError(f"attribute {name} must be > 0 (micron), is {wavelength!r}")


def check_transmittance(ds: xr.Dataset) -> None:
    """The transmittance family (attribute ``transmittance``) and its mode (variable
    ``transmittance_mode``) of a medium, or of measurements that record them; raises
    :class:`MediumError`."""
    family = ds.attrs.get("transmittance", "exponential")
    if family not in TRANSMITTANCE_FAMILIES:
        raise MediumError(f"attribute transmittance must be one of "
                          f"{sorted(TRANSMITTANCE_FAMILIES)}, is {family!r}")
    if family != "exponential" and "transmittance_mode" not in ds:
        raise MediumError(f"transmittance {family!r} needs the variable transmittance_mode")
    if "transmittance_mode" not in ds or family == "exponential":
        return
    mode = ds["transmittance_mode"]
    if family == "linear-mix":
        _require(mode, (mode.values >= 0) & (mode.values <= 1),
                 "(gamma of Vicini et al.'s Eq. 6) must be in [0, 1]")
    else:
        _require(mode, mode.values > 0, "(the power law's a) must be > 0 (inf: exponential)")


def _check_phase_table(ds: xr.Dataset) -> None:
    if "scattering_angle" not in ds.coords:
        raise MediumError("cloud_phase has no scattering_angle coordinate")
    _check_form(ds, "scattering_angle")
    angles = ds["scattering_angle"].values
    _check_increasing("scattering_angle", angles)
    if angles.size < 2 or not (np.isclose(angles[0], 0) and np.isclose(angles[-1], 180)):
        raise MediumError(
            "coordinate scattering_angle must run from 0 to 180 degrees, runs from "
            f"{angles[0]:g} to {angles[-1]:g}"
        )
    table = ds["cloud_phase"].values
    negative = np.any(table < 0, axis=1)
    if np.any(negative):
        raise MediumError(
            f"cloud_phase row {int(np.argmax(negative))} has negative values; "
            "a phase function must be >= 0"
        )
    empty = ~np.any(table > 0, axis=1)
    if np.any(empty):
        raise MediumError(f"cloud_phase row {int(np.argmax(empty))} is zero at every angle")
    _check_index_range(ds["cloud_phase_index"].values, table.shape[0])
    if "cloud_phase_weight" in ds:
        _check_phase_weight(ds["cloud_phase_weight"], ds["cloud_phase_index"].values,
                            table.shape[0])


def _check_phase_weight(weight: xr.DataArray, index: np.ndarray, ntable: int) -> None:
    """A cell's phase function is (1 - t) row k + t row k + 1: t in [0, 1], and t = 0 on
    the table's last row."""
    values = weight.values
    _require(weight, (values >= 0) & (values <= 1), "must be in [0, 1]")
    _require(weight, (values == 0) | (index < ntable - 1),
             f"must be 0 where cloud_phase_index is the table's last row ({ntable - 1})")


def _check_index_range(index: np.ndarray, ntable: int) -> None:
    outside = (index < 0) | (index >= ntable)
    if np.any(outside):
        raise MediumError(
            f"cloud_phase_index has {int(outside.sum())} values outside 0..{ntable - 1} "
            f"(cloud_phase has {ntable} rows; values span {index.min()}..{index.max()})"
        )


def _require(array: xr.DataArray, ok: np.ndarray, rule: str) -> None:
    """Raise a MediumError naming ``array`` where ``ok`` is False."""
    bad = ~np.broadcast_to(ok, array.shape)
    if np.any(bad):
        values = array.values[bad]
        units = f" {array.attrs['units']}" if array.attrs.get("units", "1") != "1" else ""
        if values.size == 1:
            found = f"{values[0]:g}{units}"
        else:
            found = f"{values.size} values from {values.min():g} to {values.max():g}{units}"
        raise MediumError(f"{array.name} {rule}; found {found}{_first(array, bad)}")


def _first(array: xr.DataArray, bad: np.ndarray) -> str:
    """Where the first offending element is, for error messages."""
    if array.ndim == 0:
        return ""
    index = np.argwhere(bad)[0]
    where = []
    for dim, i in zip(array.dims, index, strict=True):
        if dim in array.coords:
            coordinate = array[dim]
            units = coordinate.attrs.get("units", "")
            where.append(f"{dim}={float(coordinate.values[i]):g} {units}".rstrip())
        else:
            where.append(f"{dim} index {i}")
    return f" (first at {', '.join(where)})"
