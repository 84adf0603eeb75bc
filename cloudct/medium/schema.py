"""The medium schema: the variables and coordinates a medium Dataset may hold (their
dimensions, units, spelled as :mod:`cloudct.units` accepts, and long names), the defaults,
and the error raised for a Dataset or constructor input that does not follow the schema.
"""

from __future__ import annotations

from typing import NamedTuple

#: The seed paper's defaults (CONVENTIONS.md) and the default droplet effective variance
#: used by the Mie optics when a microphysical medium has no ``veff``.
DEFAULT_AIR_EXTINCTION = 0.04
DEFAULT_AIR_ALBEDO = 0.912
DEFAULT_CLOUD_ALBEDO = 0.99
DEFAULT_CLOUD_G = 0.85
DEFAULT_VEFF = 0.1

#: The medium attribute that records the wavelength [micron] at which ``air_extinction`` is
#: given (with ``air_extinction_wavelength_units = "micron"``); a medium without it has its
#: air at 0.672 micron, the default wavelength (the seed paper's 0.04 km-1).
AIR_EXTINCTION_WAVELENGTH = "air_extinction_wavelength"

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
    "cloud_phase_weight": _Spec(
        (_XYZ,), "1", "weight of the row after cloud_phase_index in each cell's phase function"
    ),
    "air_extinction": _Spec((_SCALAR, ("z",), _XYZ), "km-1", "air extinction coefficient"),
    "air_albedo": _Spec((_SCALAR,), "1", "air single-scattering albedo"),
    "transmittance_mode": _Spec(
        (_SCALAR, _XYZ), "1", "transmittance mode of the unresolved sub-grid variability"
    ),
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

_MICROPHYSICAL = ("lwc", "reff", "veff")
_OPTICAL = ("cloud_extinction", "cloud_albedo", "cloud_g", "cloud_phase", "cloud_phase_index",
            "cloud_phase_weight")
