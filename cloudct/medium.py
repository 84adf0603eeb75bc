"""The medium: cloud and air on a rectilinear voxel grid, held as an ``xarray.Dataset``.

The schema is fixed in ``docs/architecture.md`` and explained in ``docs/data_model.md``.
In short: dimensions ``x``, ``y``, ``z`` with cell-centre coordinates in km; values are
constant inside each cell. The cloud is described either microphysically (``lwc`` [g m-3],
``reff`` [micron], optional ``veff``) or optically (``cloud_extinction`` [km-1],
``cloud_albedo``, and ``cloud_g`` or a ``cloud_phase`` table with ``cloud_phase_index``).
Air is a second particle type with ``air_extinction`` [km-1] (scalar, z-profile or 3D field)
and ``air_albedo``, scattering with the Rayleigh phase function.

:func:`validate_medium` checks a Dataset against the schema and raises :class:`MediumError`
naming the offending variable. Nothing is clipped or repaired silently.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import NamedTuple

import netCDF4
import numpy as np
import xarray as xr
from numpy.typing import ArrayLike

from cloudct.netcdf import load_netcdf

#: The seed paper's defaults (CONVENTIONS.md) and the default droplet effective variance
#: used by the Mie optics when a microphysical medium has no ``veff``.
DEFAULT_AIR_EXTINCTION = 0.04
DEFAULT_AIR_ALBEDO = 0.912
DEFAULT_CLOUD_ALBEDO = 0.99
DEFAULT_CLOUD_G = 0.85
DEFAULT_VEFF = 0.1

GRID_DIMS = ("x", "y", "z")

#: Relative tolerance (of the local spacing) for "uniform spacing" and "matching edges".
SPACING_RTOL = 1e-6

_XYZ = GRID_DIMS
_SCALAR: tuple[str, ...] = ()


class MediumError(ValueError):
    """A medium Dataset (or constructor input) that does not follow the medium schema."""


class DomainBounds(NamedTuple):
    """Outer faces of the medium box, in km."""

    x_min: float
    x_max: float
    y_min: float
    y_max: float
    z_min: float
    z_max: float


class _Spec(NamedTuple):
    dims: tuple[tuple[str, ...], ...]  # the allowed dimension tuples
    units: str  # canonical CF units
    long_name: str


_VARIABLES: dict[str, _Spec] = {
    "lwc": _Spec((_XYZ,), "g m-3", "liquid water content"),
    "reff": _Spec((_XYZ,), "micron", "droplet effective radius"),
    "veff": _Spec((_SCALAR, _XYZ), "1", "droplet effective variance"),
    "cloud_extinction": _Spec((_XYZ,), "km-1", "cloud extinction coefficient"),
    "cloud_albedo": _Spec((_SCALAR, _XYZ), "1", "cloud single-scattering albedo"),
    "cloud_g": _Spec((_SCALAR, _XYZ), "1", "cloud Henyey-Greenstein asymmetry parameter"),
    "cloud_phase": _Spec(
        (("phase_table", "scattering_angle"),), "sr-1", "cloud phase function (tabulated)"
    ),
    "cloud_phase_index": _Spec((_XYZ,), "1", "row of cloud_phase used in each cell"),
    "air_extinction": _Spec((_SCALAR, ("z",), _XYZ), "km-1", "air extinction coefficient"),
    "air_albedo": _Spec((_SCALAR,), "1", "air single-scattering albedo"),
}

_COORDINATES: dict[str, _Spec] = {
    "x": _Spec((("x",),), "km", "x coordinate of cell centres (east)"),
    "y": _Spec((("y",),), "km", "y coordinate of cell centres (north)"),
    "z": _Spec((("z",),), "km", "altitude of cell centres"),
    "z_bounds": _Spec((("z", "nv"),), "km", "altitude of cell lower and upper edges"),
    "scattering_angle": _Spec((("scattering_angle",),), "degree", "scattering angle"),
}

_EXTRA_COORD_ATTRS = {
    "x": {"axis": "X"},
    "y": {"axis": "Y"},
    "z": {"axis": "Z", "positive": "up"},
}

#: Spellings accepted in a ``units`` attribute, per canonical unit.
_UNIT_SPELLINGS = {
    "km": {"km", "kilometer", "kilometre", "kilometers", "kilometres"},
    "km-1": {"km-1", "1/km", "/km", "km^-1", "km**-1"},
    "g m-3": {"g m-3", "g/m3", "g/m^3", "g m^-3", "g m**-3", "g.m-3"},
    "micron": {"micron", "microns", "um", "µm", "micrometer", "micrometre", "micrometers"},
    "1": {"1", "", "dimensionless"},
    "sr-1": {"sr-1", "1/sr", "/sr", "sr^-1", "sr**-1"},
    "degree": {"degree", "degrees", "deg"},
}

_MICROPHYSICAL = ("lwc", "reff", "veff")
_OPTICAL = ("cloud_extinction", "cloud_albedo", "cloud_g", "cloud_phase", "cloud_phase_index")


# ---------------------------------------------------------------------------------------
# Constructors
# ---------------------------------------------------------------------------------------


def microphysical_medium(
    x: ArrayLike,
    y: ArrayLike,
    z: ArrayLike,
    lwc: ArrayLike,
    reff: ArrayLike,
    *,
    veff: ArrayLike | None = None,
    z_bounds: ArrayLike | None = None,
    air_extinction: ArrayLike = DEFAULT_AIR_EXTINCTION,
    air_albedo: float = DEFAULT_AIR_ALBEDO,
    title: str = "cloudct medium",
    source: str = "cloudct.medium.microphysical_medium",
) -> xr.Dataset:
    """A medium whose cloud is described by its microphysics.

    Args:
        x, y: cell-centre coordinates [km], uniformly spaced, increasing (at least 2 each).
        z: cell-centre altitudes [km], increasing; uniformly spaced unless ``z_bounds``.
        lwc: liquid water content [g m-3], shape (nx, ny, nz), >= 0.
        reff: droplet effective radius [micron], shape (nx, ny, nz); > 0 where lwc > 0.
            Where lwc = 0 it is ignored (any finite value >= 0, e.g. 0, is accepted).
        veff: droplet effective variance [1], scalar or (nx, ny, nz); omitted by default,
            in which case the optics use :data:`DEFAULT_VEFF` (0.1).
        z_bounds: cell edges along z [km], shape (nz, 2) as (lower, upper) per cell, for
            non-uniform z; each z must be the midpoint of its bounds.
        air_extinction: air extinction [km-1]: scalar, z-profile (nz,) or (nx, ny, nz).
        air_albedo: air single-scattering albedo.
        title, source: Dataset attributes (``source`` is the attribution of the field).

    Any input may also be an ``xarray.DataArray`` on the medium's dimensions; its
    coordinates must then equal the medium grid.

    Returns:
        A validated medium Dataset.

    Raises:
        MediumError: an input has the wrong shape or values outside the schema's ranges.
    """
    coords, sizes = _grid_variables(x, y, z, z_bounds)
    data_vars = {
        "lwc": _variable("lwc", lwc, sizes, coords),
        "reff": _variable("reff", reff, sizes, coords),
    }
    if veff is not None:
        data_vars["veff"] = _variable("veff", veff, sizes, coords)
    data_vars |= _air_variables(air_extinction, air_albedo, sizes, coords)
    return _assemble(coords, data_vars, {"title": title, "source": source})


def optical_medium(
    x: ArrayLike,
    y: ArrayLike,
    z: ArrayLike,
    cloud_extinction: ArrayLike,
    *,
    cloud_albedo: ArrayLike = DEFAULT_CLOUD_ALBEDO,
    cloud_g: ArrayLike | None = None,
    cloud_phase: tuple[ArrayLike, ArrayLike] | None = None,
    cloud_phase_index: ArrayLike | None = None,
    air_extinction: ArrayLike = DEFAULT_AIR_EXTINCTION,
    air_albedo: float = DEFAULT_AIR_ALBEDO,
    z_bounds: ArrayLike | None = None,
    wavelength: float | None = None,
    title: str = "cloudct medium",
    source: str = "cloudct.medium.optical_medium",
) -> xr.Dataset:
    """A medium whose cloud is described by its optical properties (the seed paper's setting).

    Args:
        x, y, z, z_bounds: the grid, as in :func:`microphysical_medium`.
        cloud_extinction: cloud extinction [km-1], shape (nx, ny, nz), >= 0.
        cloud_albedo: cloud single-scattering albedo in [0, 1], scalar or (nx, ny, nz).
        cloud_g: Henyey-Greenstein asymmetry parameter, -1 < g < 1, scalar or (nx, ny, nz).
            Defaults to :data:`DEFAULT_CLOUD_G` (0.85) unless ``cloud_phase`` is given.
        cloud_phase: a tabulated phase function instead of HG: ``(table, angles)`` with
            ``table`` [sr-1] of shape (ntable, nangle) (or (nangle,) for a single row) and
            ``angles`` [degree] increasing from 0 to 180.
        cloud_phase_index: the table row used in each cell: an int or an (nx, ny, nz) int
            array; may be omitted when the table has a single row.
        air_extinction, air_albedo: air, as in :func:`microphysical_medium`.
        wavelength: [micron], stored as the ``wavelength`` attribute when given.
        title, source: Dataset attributes.

    Returns:
        A validated medium Dataset.

    Raises:
        MediumError: inconsistent or out-of-range inputs, or both ``cloud_g`` and
            ``cloud_phase`` given.
    """
    coords, sizes = _grid_variables(x, y, z, z_bounds)
    data_vars = {
        "cloud_extinction": _variable("cloud_extinction", cloud_extinction, sizes, coords),
        "cloud_albedo": _variable("cloud_albedo", cloud_albedo, sizes, coords),
    }
    if cloud_phase is None:
        if cloud_phase_index is not None:
            raise MediumError("cloud_phase_index given without cloud_phase")
        g = DEFAULT_CLOUD_G if cloud_g is None else cloud_g
        data_vars["cloud_g"] = _variable("cloud_g", g, sizes, coords)
    else:
        if cloud_g is not None:
            raise MediumError("give either cloud_g or cloud_phase, not both")
        angles, phase, index = _phase_table_variables(cloud_phase, cloud_phase_index, sizes)
        coords["scattering_angle"] = angles
        data_vars["cloud_phase"] = phase
        data_vars["cloud_phase_index"] = index
    data_vars |= _air_variables(air_extinction, air_albedo, sizes, coords)
    attrs = {"title": title, "source": source}
    if wavelength is not None:
        attrs["wavelength"] = float(wavelength)
    return _assemble(coords, data_vars, attrs)


def _grid_variables(
    x: ArrayLike, y: ArrayLike, z: ArrayLike, z_bounds: ArrayLike | None
) -> tuple[dict[str, xr.Variable], dict[str, int]]:
    """Coordinate variables (with CF attributes) and the grid sizes."""
    coords = {}
    for name, values in (("x", x), ("y", y), ("z", z)):
        data = _as_float(name, values)
        if data.ndim != 1:
            raise MediumError(f"{name} must be a 1-D array of cell centres, got shape {data.shape}")
        coords[name] = xr.Variable((name,), data, attrs=_attrs(name))
    sizes = {name: coords[name].size for name in GRID_DIMS}
    if z_bounds is not None:
        bounds = _as_float("z_bounds", z_bounds)
        if bounds.shape != (sizes["z"], 2):
            raise MediumError(
                f"z_bounds must have shape (nz, 2) = ({sizes['z']}, 2), got {bounds.shape}"
            )
        coords["z"].attrs["bounds"] = "z_bounds"
        coords["z_bounds"] = xr.Variable(("z", "nv"), bounds, attrs=_attrs("z_bounds"))
    return coords, sizes


def _variable(
    name: str, value: ArrayLike, sizes: dict[str, int], coords: dict[str, xr.Variable]
) -> xr.Variable:
    """One schema variable from an array, a scalar or a DataArray on the medium grid."""
    allowed = _VARIABLES[name].dims
    if isinstance(value, xr.DataArray):
        value = _on_medium_grid(name, value, allowed, coords)
    data = _as_float(name, value)
    for dims in allowed:
        if data.shape == tuple(sizes[d] for d in dims):
            return xr.Variable(dims, data, attrs=_attrs(name))
    expected = " or ".join(str(tuple(sizes[d] for d in dims)) for dims in allowed)
    raise MediumError(f"{name} has shape {data.shape}; expected {expected}")


def _on_medium_grid(
    name: str,
    array: xr.DataArray,
    allowed: tuple[tuple[str, ...], ...],
    coords: dict[str, xr.Variable],
) -> np.ndarray:
    """The values of a DataArray whose dimensions and coordinates match the medium grid."""
    for dims in allowed:
        if set(array.dims) == set(dims):
            array = array.transpose(*dims)
            break
    else:
        expected = " or ".join(str(d) for d in allowed)
        raise MediumError(f"{name} has dimensions {array.dims}; expected {expected}")
    for dim in array.dims:
        if dim in array.coords:
            mine, theirs = coords[dim].values, array[dim].values
            if mine.shape != theirs.shape or not np.allclose(mine, theirs, rtol=0, atol=1e-9):
                raise MediumError(
                    f"{name} is on other {dim} coordinates than the medium grid "
                    f"(its {dim} spans {theirs.min():g}..{theirs.max():g} km in {theirs.size} "
                    f"points; the medium's spans {mine.min():g}..{mine.max():g} km in "
                    f"{mine.size})"
                )
    return array.values


def _phase_table_variables(
    cloud_phase: tuple[ArrayLike, ArrayLike],
    cloud_phase_index: ArrayLike | None,
    sizes: dict[str, int],
) -> tuple[xr.Variable, xr.Variable, xr.Variable]:
    """The scattering-angle coordinate, the phase table and the per-cell row index."""
    try:
        table, angles = cloud_phase
    except (TypeError, ValueError) as err:
        raise MediumError("cloud_phase must be a pair (table, angles_deg)") from err
    table = np.atleast_2d(_as_float("cloud_phase", table))
    angles = _as_float("scattering_angle", angles)
    if table.ndim != 2 or angles.ndim != 1 or table.shape[1] != angles.size:
        raise MediumError(
            f"cloud_phase table has shape {table.shape} but there are {angles.size} "
            "scattering angles; expected (ntable, nangle) with nangle angles"
        )
    ntable = table.shape[0]
    if cloud_phase_index is None:
        if ntable != 1:
            raise MediumError(f"cloud_phase_index is required: cloud_phase has {ntable} rows")
        cloud_phase_index = 0
    index = np.asarray(cloud_phase_index)
    if not np.issubdtype(index.dtype, np.integer):
        raise MediumError(f"cloud_phase_index must be integers, got dtype {index.dtype}")
    grid_shape = tuple(sizes[d] for d in _XYZ)
    if index.ndim == 0:
        index = np.full(grid_shape, index)
    if index.shape != grid_shape:
        raise MediumError(f"cloud_phase_index has shape {index.shape}; expected {grid_shape}")
    _check_index_range(index, ntable)
    return (
        xr.Variable(("scattering_angle",), angles, attrs=_attrs("scattering_angle")),
        xr.Variable(("phase_table", "scattering_angle"), table, attrs=_attrs("cloud_phase")),
        xr.Variable(_XYZ, index.astype(np.int32), attrs=_attrs("cloud_phase_index")),
    )


def _air_variables(
    air_extinction: ArrayLike,
    air_albedo: float,
    sizes: dict[str, int],
    coords: dict[str, xr.Variable],
) -> dict[str, xr.Variable]:
    return {
        "air_extinction": _variable("air_extinction", air_extinction, sizes, coords),
        "air_albedo": _variable("air_albedo", air_albedo, sizes, coords),
    }


def _assemble(
    coords: dict[str, xr.Variable], data_vars: dict[str, xr.Variable], attrs: dict
) -> xr.Dataset:
    """The Dataset, with ``z_bounds`` as a data variable (CF bounds), validated."""
    coords = dict(coords)
    if "z_bounds" in coords:
        data_vars = {**data_vars, "z_bounds": coords.pop("z_bounds")}
    ds = xr.Dataset(data_vars, coords=coords, attrs={**attrs, "Conventions": "CF-1.8"})
    validate_medium(ds)
    return ds


def _attrs(name: str) -> dict[str, str]:
    spec = _VARIABLES.get(name) or _COORDINATES[name]
    return {"units": spec.units, "long_name": spec.long_name, **_EXTRA_COORD_ATTRS.get(name, {})}


def _as_float(name: str, value: ArrayLike) -> np.ndarray:
    try:
        return np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise MediumError(f"{name} must be numeric: {err}") from err


# ---------------------------------------------------------------------------------------
# Queries
# ---------------------------------------------------------------------------------------


def is_microphysical(ds: xr.Dataset) -> bool:
    """Whether ``ds`` holds a complete microphysical cloud description (lwc and reff).

    This only looks at which variables are present; :func:`validate_medium` checks them.
    """
    return "lwc" in ds and "reff" in ds


def is_optical(ds: xr.Dataset) -> bool:
    """Whether ``ds`` holds a complete optical cloud description.

    That is ``cloud_extinction``, ``cloud_albedo`` and a phase function (``cloud_g``, or
    ``cloud_phase`` with ``cloud_phase_index``). Presence only, like :func:`is_microphysical`.
    """
    has_phase = "cloud_g" in ds or ("cloud_phase" in ds and "cloud_phase_index" in ds)
    return "cloud_extinction" in ds and "cloud_albedo" in ds and has_phase


def cell_edges(ds: xr.Dataset) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cell edges along x, y and z [km], float64 arrays of length n + 1.

    Along z the edges come from ``z_bounds`` when present; otherwise (and always along x
    and y) they are the midpoints between centres, extended by half a spacing at each end.

    Raises:
        MediumError: the grid does not follow the schema.
    """
    _check_grid(ds)
    x_edges = _edges_from_centres(ds["x"].values)
    y_edges = _edges_from_centres(ds["y"].values)
    if "z_bounds" in ds:
        bounds = np.asarray(ds["z_bounds"].values, dtype=np.float64)
        z_edges = np.append(bounds[:, 0], bounds[-1, 1])
    else:
        z_edges = _edges_from_centres(ds["z"].values)
    return x_edges, y_edges, z_edges


def domain_bounds(ds: xr.Dataset) -> DomainBounds:
    """The outer faces of the medium box [km]."""
    x_edges, y_edges, z_edges = cell_edges(ds)
    return DomainBounds(
        float(x_edges[0]),
        float(x_edges[-1]),
        float(y_edges[0]),
        float(y_edges[-1]),
        float(z_edges[0]),
        float(z_edges[-1]),
    )


def _edges_from_centres(centres: np.ndarray) -> np.ndarray:
    c = np.asarray(centres, dtype=np.float64)
    middle = 0.5 * (c[:-1] + c[1:])
    return np.concatenate(([c[0] - (middle[0] - c[0])], middle, [c[-1] + (c[-1] - middle[-1])]))


# ---------------------------------------------------------------------------------------
# Validation
# ---------------------------------------------------------------------------------------


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
       integer ``cloud_phase_index`` within the table; ``wavelength`` attribute > 0.

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
        units = array.attrs["units"]
        if not isinstance(units, str) or units.strip().lower() not in _UNIT_SPELLINGS[spec.units]:
            raise MediumError(f"{name} has units {units!r}; expected {spec.units!r}")
    bad = ~np.isfinite(array.values)
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
    if "wavelength" in ds.attrs:
        wavelength = ds.attrs["wavelength"]
        number = isinstance(wavelength, (int, float, np.integer, np.floating))
        if not (number and np.isfinite(wavelength) and wavelength > 0):
            raise MediumError(f"attribute wavelength must be > 0 (micron), is {wavelength!r}")


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


# ---------------------------------------------------------------------------------------
# netCDF
# ---------------------------------------------------------------------------------------


def save_medium(ds: xr.Dataset, path: str | os.PathLike, overwrite: bool = False) -> None:
    """Validate ``ds`` and write it to a netCDF-4 file.

    The file is written next to its destination and moved into place, so a failed write
    never leaves a half-written medium. No ``_FillValue`` is added, dtypes are kept
    (``cloud_phase_index`` stays int32), and all attributes are written.

    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is False.
        MediumError: ``ds`` is not a valid medium.
    """
    validate_medium(ds)
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True (--overwrite) to replace it")
    ds = ds.copy()
    ds.encoding = {}
    for variable in ds.variables.values():
        variable.encoding = {}
    encoding = {name: {"_FillValue": None} for name in ds.variables}
    partial = path.with_name(f".{path.name}.partial")
    try:
        ds.to_netcdf(partial, engine="netcdf4", format="NETCDF4", encoding=encoding)
        if "z_bounds" in ds:
            # xarray strips the attributes a CF bounds variable shares with its coordinate
            # (units, long_name); put them back so that every variable carries its units.
            with netCDF4.Dataset(partial, "a") as nc:
                nc["z_bounds"].setncatts(ds["z_bounds"].attrs)
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)


def load_medium(path: str | os.PathLike) -> xr.Dataset:
    """Read a medium netCDF file fully into memory (the file is closed) and validate it.

    Raises:
        FileNotFoundError: no such file.
        InputFileError: the file cannot be read as netCDF (truncated, another format).
        MediumError: the file does not hold a valid medium (the message names the file).
    """
    ds = load_netcdf(path, "medium")
    try:
        validate_medium(ds)
    except MediumError as err:
        raise MediumError(f"medium file {path}: {err}") from None
    return ds
