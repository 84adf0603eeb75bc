"""The medium constructors: :func:`microphysical_medium` and :func:`optical_medium` build
a medium Dataset with CF attributes from arrays, scalars or DataArrays on the medium
grid, and validate it.
"""

from __future__ import annotations

import numpy as np
import xarray as xr
from numpy.typing import ArrayLike

from cloudct.medium.schema import (
    _COORDINATES,
    _EXTRA_COORD_ATTRS,
    _VARIABLES,
    _XYZ,
    AIR_EXTINCTION_WAVELENGTH,
    DEFAULT_AIR_ALBEDO,
    DEFAULT_AIR_EXTINCTION,
    DEFAULT_CLOUD_ALBEDO,
    DEFAULT_CLOUD_G,
    GRID_DIMS,
    MediumError,
)
from cloudct.medium.validation import _check_index_range, validate_medium


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
    air_extinction_wavelength: float | None = None,
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
        air_extinction_wavelength: the wavelength [micron] at which ``air_extinction`` is
            given, stored as the attribute :data:`AIR_EXTINCTION_WAVELENGTH` when given
            (absent: 0.672 micron); the optics at another wavelength scale the air to it
            (:func:`cloudct.optics.to_optical`).
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
    attrs = {"title": title, "source": source}
    return _assemble(coords, data_vars, attrs | _air_wavelength_attrs(air_extinction_wavelength))


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
    cloud_phase_weight: ArrayLike | None = None,
    air_extinction: ArrayLike = DEFAULT_AIR_EXTINCTION,
    air_albedo: float = DEFAULT_AIR_ALBEDO,
    air_extinction_wavelength: float | None = None,
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
        cloud_phase_weight: each cell's weight t in [0, 1] of the row after its
            ``cloud_phase_index`` k: its phase function is (1 - t) row k + t row k + 1 (the
            Mie phase function linear in r_eff between table rows), shape (nx, ny, nz);
            None: row k alone.
        air_extinction, air_albedo, air_extinction_wavelength: air, as in
            :func:`microphysical_medium`.
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
        if cloud_phase_index is not None or cloud_phase_weight is not None:
            raise MediumError("cloud_phase_index or cloud_phase_weight given without cloud_phase")
        g = DEFAULT_CLOUD_G if cloud_g is None else cloud_g
        data_vars["cloud_g"] = _variable("cloud_g", g, sizes, coords)
    else:
        if cloud_g is not None:
            raise MediumError("give either cloud_g or cloud_phase, not both")
        angles, phase, index = _phase_table_variables(cloud_phase, cloud_phase_index, sizes)
        coords["scattering_angle"] = angles
        data_vars["cloud_phase"] = phase
        data_vars["cloud_phase_index"] = index
        if cloud_phase_weight is not None:
            data_vars["cloud_phase_weight"] = _variable("cloud_phase_weight", cloud_phase_weight,
                                                        sizes, coords)
    data_vars |= _air_variables(air_extinction, air_albedo, sizes, coords)
    attrs = {"title": title, "source": source}
    if wavelength is not None:
        attrs["wavelength"] = float(wavelength)
    return _assemble(coords, data_vars, attrs | _air_wavelength_attrs(air_extinction_wavelength))


def with_transmittance(medium: xr.Dataset, family: str, mode: ArrayLike | None = None
                       ) -> xr.Dataset:
    """A copy of ``medium`` with the transmittance ``family`` (the attribute
    ``transmittance``: ``"exponential"``, ``"linear-mix"`` or ``"gamma"``,
    docs/transmittance.md) and its ``mode`` (the variable ``transmittance_mode``: a scalar,
    an (nx, ny, nz) array or a DataArray on the medium grid; the power law's a, which may be
    ``inf``, or Eq. 6's gamma). ``"exponential"`` removes both.

    Raises:
        MediumError: an unknown family, a missing mode, or modes out of the family's range.
    """
    out = medium.copy()
    out.attrs.pop("transmittance", None)
    if "transmittance_mode" in out:
        out = out.drop_vars("transmittance_mode")
    if family == "exponential":
        return out
    if mode is None:
        raise MediumError(f"transmittance {family!r} needs a mode")
    sizes = {d: out.sizes[d] for d in GRID_DIMS}
    coords = {d: out[d].variable for d in GRID_DIMS}
    out["transmittance_mode"] = _variable("transmittance_mode", mode, sizes, coords)
    out.attrs["transmittance"] = family
    validate_medium(out)
    return out


def transmittance_model(medium: xr.Dataset) -> tuple[str, xr.DataArray | None]:
    """The medium's transmittance family and its mode (None for the exponential)."""
    family = str(medium.attrs.get("transmittance", "exponential"))
    if family == "exponential":
        return family, None
    return family, medium["transmittance_mode"]


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


def _air_wavelength_attrs(wavelength: float | None) -> dict:
    """The attributes that record the wavelength [micron] of the air extinction, if given."""
    if wavelength is None:
        return {}
    return {AIR_EXTINCTION_WAVELENGTH: float(wavelength),
            AIR_EXTINCTION_WAVELENGTH + "_units": "micron"}


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
