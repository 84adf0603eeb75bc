"""netCDF files in and out: inputs read with one clear line when a file cannot be read, and
outputs written whole or not at all.

Every command reads its inputs (media, scenes, measurements, results, checkpoints) through
:func:`load_netcdf`, so that a missing, truncated, empty or non-netCDF file ends in one
line naming the file and what is wrong, not in a traceback from the HDF5 library.
:func:`save_netcdf` writes next to the destination and moves the file into place
(:func:`cloudct.output_files.written_whole`), so a failed write never leaves a half-written
file.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from pathlib import Path

import xarray as xr

from cloudct.output_files import written_whole


class InputFileError(ValueError):
    """An input file that cannot be read as netCDF, or lacks what it must hold."""


def load_netcdf(
    path: str | os.PathLike, what: str, validate: Callable[[xr.Dataset], None] | None = None
) -> xr.Dataset:
    """The whole netCDF file at ``path``, read into memory (the file is closed).

    Args:
        path: the file.
        what: what the file should hold ("medium", "scene", ...), for the messages.
        validate: a check of the contents; the error it raises (a ValueError) is raised
            again, of the same type, with the file named.

    Raises:
        FileNotFoundError: no such file.
        InputFileError: a directory, or a file that the netCDF library cannot read
            (truncated, empty, or of another format).
    """
    ds = _read(Path(path), what)
    if validate is not None:
        try:
            validate(ds)
        except ValueError as err:
            raise type(err)(f"{what} file {path}: {err}") from None
    return ds


def _read(path: Path, what: str) -> xr.Dataset:
    """The file's contents, or one line saying why it cannot be read as netCDF."""
    if not path.exists():
        raise FileNotFoundError(f"{what} file {path} does not exist")
    if path.is_dir():
        raise InputFileError(f"{what} file {path} is a directory, not a netCDF file")
    try:
        with xr.open_dataset(path, engine="netcdf4") as stored:
            return stored.load()
    except Exception as err:  # whatever the library raises on a damaged file
        # (OSError, RuntimeError, ValueError; AttributeError on a damaged attribute, ...)
        reason = str(err).splitlines()[0] if str(err) else type(err).__name__
        size = path.stat().st_size
        raise InputFileError(
            f"{what} file {path} ({size} bytes) cannot be read as netCDF: it may be truncated, "
            f"empty or of another format ({reason})"
        ) from None


def require_variables(ds: xr.Dataset, names: list[str] | tuple[str, ...], what: str,
                      path: str | os.PathLike) -> None:
    """Raise :class:`InputFileError` naming the variables of ``names`` that ``ds`` (read
    from ``path``) lacks."""
    missing = [n for n in names if n not in ds.variables]
    if missing:
        raise InputFileError(
            f"{what} file {path} lacks {', '.join(missing)}; is it a cloudct {what} file?"
        )


def save_netcdf(
    ds: xr.Dataset,
    path: str | os.PathLike,
    *,
    overwrite: bool = False,
    encoding: dict | None = None,
    finish: Callable[[Path], None] | None = None,
) -> None:
    """Write ``ds`` to a netCDF-4 file at ``path`` atomically; ``finish(partial)`` may amend
    the written file before it is moved into place.

    Raises:
        FileExistsError: ``path`` exists and ``overwrite`` is False.
    """
    path = Path(path)
    if path.exists() and not overwrite:
        raise FileExistsError(f"{path} exists; pass overwrite=True (--overwrite) to replace it")
    with written_whole(path, ds.nbytes) as partial:
        ds.to_netcdf(partial, engine="netcdf4", format="NETCDF4", encoding=encoding)
        if finish is not None:
            finish(partial)
