"""Units of the files cloudct reads: the spellings accepted for each of its units, and, for
a unit that is convertible but not cloudct's, the conversion to make.

cloudct refuses a convertible unit with the factor to apply rather than converting it: a
file is read as it is, nothing about a user's data changes without the user's say, and the
message says exactly what to do (for example LWC in kg m-3: multiply by 1000 and set the
units to g m-3). The conversions are the handful that occur in cloud fields and camera
files (lengths, inverse lengths, densities, angles); a units library would add a dependency
for no more than this table.
"""

from __future__ import annotations

import math

#: Spellings accepted in a ``units`` attribute, per unit (CONVENTIONS.md), lower case.
SPELLINGS = {
    "km": {"km", "kilometer", "kilometre", "kilometers", "kilometres"},
    "km-1": {"km-1", "1/km", "/km", "km^-1", "km**-1"},
    "g m-3": {"g m-3", "g/m3", "g/m^3", "g m^-3", "g m**-3", "g.m-3"},
    "micron": {"micron", "microns", "um", "µm", "micrometer", "micrometre", "micrometers"},
    "1": {"1", "", "dimensionless"},
    "sr-1": {"sr-1", "1/sr", "/sr", "sr^-1", "sr**-1"},
    "degree": {"degree", "degrees", "deg"},
}

_METRE = {"m", "meter", "metre", "meters", "metres"}
_PER_METRE = {"m-1", "1/m", "/m", "m^-1", "m**-1"}
_KG_PER_M3 = {"kg m-3", "kg/m3", "kg/m^3", "kg m^-3", "kg m**-3", "kg.m-3"}
_MG_PER_M3 = {"mg m-3", "mg/m3", "mg/m^3", "mg m^-3"}
_RADIAN = {"rad", "radian", "radians"}

#: Factors that turn a value in a convertible unit into cloudct's unit.
CONVERSIONS: dict[str, dict[str, float]] = {
    "km": {**dict.fromkeys(_METRE, 1e-3), "cm": 1e-5},
    "km-1": dict.fromkeys(_PER_METRE, 1e3),
    "g m-3": {**dict.fromkeys(_KG_PER_M3, 1e3), **dict.fromkeys(_MG_PER_M3, 1e-3)},
    "micron": {**dict.fromkeys(_METRE, 1e6), "mm": 1e3, "cm": 1e4, "nm": 1e-3},
    "degree": dict.fromkeys(_RADIAN, 180.0 / math.pi),
}


def units_problem(name: str, units: object, unit: str) -> str | None:
    """None if ``units`` (a ``units`` attribute) spells ``unit``, else what is wrong with it:
    the conversion to make where one is known."""
    spelled = units.strip().lower() if isinstance(units, str) else None
    if spelled in SPELLINGS[unit]:
        return None
    factor = CONVERSIONS.get(unit, {}).get(spelled)
    if factor is None:
        return f"{name} has units {units!r}; expected {unit!r}"
    return (f"{name} has units {units!r}; cloudct reads {unit!r}: multiply {name} by "
            f"{factor:.6g} and set its units to {unit!r}")
