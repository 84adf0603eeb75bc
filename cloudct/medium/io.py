"""netCDF files of a medium: :func:`save_medium` writes a validated medium atomically,
:func:`load_medium` reads one into memory and validates it.
"""

from __future__ import annotations

import os
from pathlib import Path

import netCDF4
import xarray as xr

from cloudct.medium.validation import validate_medium
from cloudct.netcdf import load_netcdf, save_netcdf


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
    ds = ds.copy()
    ds.encoding = {}
    for variable in ds.variables.values():
        variable.encoding = {}

    def restore_bounds_attributes(partial: Path) -> None:
        # xarray strips the attributes a CF bounds variable shares with its coordinate
        # (units, long_name); put them back so that every variable carries its units.
        if "z_bounds" in ds:
            with netCDF4.Dataset(partial, "a") as nc:
                nc["z_bounds"].setncatts(ds["z_bounds"].attrs)

    save_netcdf(ds, path, overwrite=overwrite,
                encoding={name: {"_FillValue": None} for name in ds.variables},
                finish=restore_bounds_attributes)


def load_medium(path: str | os.PathLike) -> xr.Dataset:
    """Read a medium netCDF file fully into memory (the file is closed) and validate it.

    Raises:
        FileNotFoundError: no such file.
        InputFileError: the file cannot be read as netCDF (truncated, another format).
        MediumError: the file does not hold a valid medium (the message names the file).
    """
    return load_netcdf(path, "medium", validate_medium)
