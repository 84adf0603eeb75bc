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

The package's modules: :mod:`~cloudct.medium.schema` (the variables, units, defaults and
:class:`MediumError`), :mod:`~cloudct.medium.constructors`,
:mod:`~cloudct.medium.validation`, :mod:`~cloudct.medium.queries` (cloud description,
cell edges, domain bounds) and :mod:`~cloudct.medium.io` (netCDF files); everything
public is imported from ``cloudct.medium``.
"""

from cloudct.medium.constructors import (
    microphysical_medium,
    optical_medium,
    transmittance_model,
    with_transmittance,
)
from cloudct.medium.io import load_medium, save_medium
from cloudct.medium.queries import cell_edges, domain_bounds, is_microphysical, is_optical
from cloudct.medium.schema import (
    AIR_EXTINCTION_WAVELENGTH,
    DEFAULT_AIR_ALBEDO,
    DEFAULT_AIR_EXTINCTION,
    DEFAULT_CLOUD_ALBEDO,
    DEFAULT_CLOUD_G,
    DEFAULT_VEFF,
    GRID_DIMS,
    SPACING_RTOL,
    DomainBounds,
    MediumError,
)
from cloudct.medium.validation import check_transmittance, validate_medium

__all__ = [
    "AIR_EXTINCTION_WAVELENGTH",
    "DEFAULT_AIR_ALBEDO",
    "DEFAULT_AIR_EXTINCTION",
    "DEFAULT_CLOUD_ALBEDO",
    "DEFAULT_CLOUD_G",
    "DEFAULT_VEFF",
    "GRID_DIMS",
    "SPACING_RTOL",
    "DomainBounds",
    "MediumError",
    "cell_edges",
    "check_transmittance",
    "domain_bounds",
    "is_microphysical",
    "is_optical",
    "load_medium",
    "microphysical_medium",
    "optical_medium",
    "save_medium",
    "transmittance_model",
    "validate_medium",
    "with_transmittance",
]
