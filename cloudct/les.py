"""Readers of LES cloud fields in text form, giving microphysical medium Datasets.

Two formats (examples in ``shared/data/les``; see ``docs/data_model.md``):

* the JPL-LES text format of pyshdom/AT3D (``rico32x37x26.txt``, ``rico122x106x39.txt``)::

      # comment
      32,37,26      # nx,ny,nz
      0.020,0.020   # dx,dy [km, km]
      0.440,0.480,...,1.44  # altitude levels [km]
      x,y,z,lwc,reff            (or i,j,k,lwc,reff; an extra ",veff" column is allowed)
      2,2,4,0.00675,12.52100    (sparse rows: 0-based indices, g m-3, micron)

* the SHDOM particle-file text format (``les_stcu.txt``)::

      # comment
      64 64 16            (nx ny nz)
      0.055 0.055 0.438 0.463 ...   (dx dy, then the nz z levels, km)
      0 0 12 0.04020 5.110          (rows i j k lwc reff, 0-based)

Grid, for both: cell (i, j, k) spans x in [i dx, (i + 1) dx], y in [j dy, (j + 1) dy] and z
between level k and level k + 1. The levels are the lower edges of the cell layers; the top
of the last layer is the last level plus the last level spacing. Cells absent from the
file are clear air (lwc = 0, reff = 0). When the levels are uniformly spaced the medium has
plain z centres; otherwise it carries ``z_bounds``. Air gets the default extinction and
albedo of :mod:`cloudct.medium`.

Malformed files raise :class:`LESFormatError` naming the file, the 1-based line and the
reason.
"""

from __future__ import annotations

import importlib.resources
import itertools
import os
from pathlib import Path

import numpy as np
import xarray as xr

from cloudct.medium import SPACING_RTOL, microphysical_medium

#: Attribution of the bundled single cloud (see cloudct/data/README.md).
BUNDLED_SOURCE = (
    "JPL LES of the RICO trade-wind cumulus case (rico.20.smagorinsky), isolated cloud "
    "rico32x37x26, from the public pyshdom/AT3D distributions (LES by the JPL group)"
)
#: Attribution of the bundled cloud field (see cloudct/data/README.md).
BUNDLED_FIELD_SOURCE = (
    "JPL LES of the RICO trade-wind cumulus case (rico.20.smagorinsky), cloud field "
    "rico122x106x39, from the public pyshdom/AT3D distributions (LES by the JPL group)"
)
#: The seed paper's cloud field (its Table 1): 79 x 84 x 27 cells of 20 m x 20 m x 40 m.
SEED_PAPER_FIELD_SHAPE = (79, 84, 27)

_INDEX_HEADERS = (("x", "y", "z"), ("i", "j", "k"))


class LESFormatError(ValueError):
    """A malformed LES text file; the message names the file, the line and the reason."""

    def __init__(self, path: str | os.PathLike, line: int, reason: str) -> None:
        self.path = str(path)
        self.line = line
        self.reason = reason
        super().__init__(f"{self.path}, line {line}: {reason}")


def read_jpl_les(path: str | os.PathLike, *, source: str | None = None) -> xr.Dataset:
    """Read a JPL-LES text file (pyshdom/AT3D format) into a microphysical medium.

    Args:
        path: the text file.
        source: the ``source`` attribute (attribution); by default the file name and format.

    Returns:
        A validated medium with ``lwc`` [g m-3], ``reff`` [micron] (and ``veff`` if the file
        has that column) on cell centres x = (i + 1/2) dx, y = (j + 1/2) dy, and z halfway
        between consecutive levels (levels are lower edges, see the module docstring).

    Raises:
        LESFormatError: the file is malformed.
        FileNotFoundError: no such file.
    """
    path = Path(path)
    lines = _read_lines(path)
    sizes = _numbers(path, lines, 2, ",", int, "nx,ny,nz")
    if len(sizes) != 3:
        raise LESFormatError(path, 2, f"expected nx,ny,nz (3 integers), found {len(sizes)} values")
    nx, ny, nz = _positive(path, 2, sizes, "nx,ny,nz")
    spacing = _numbers(path, lines, 3, ",", float, "dx,dy")
    if len(spacing) != 2:
        raise LESFormatError(path, 3, f"expected dx,dy (2 numbers), found {len(spacing)} values")
    dx, dy = _positive(path, 3, spacing, "dx,dy")
    levels = _levels(path, 4, _numbers(path, lines, 4, ",", float, "altitude levels"), nz)
    header = [name.strip().lower() for name in _content(path, lines, 5).split(",")]
    if tuple(header[:3]) not in _INDEX_HEADERS or header[3:] not in (
        ["lwc", "reff"],
        ["lwc", "reff", "veff"],
    ):
        raise LESFormatError(
            path,
            5,
            "bad header: expected 'x,y,z,lwc,reff' or 'i,j,k,lwc,reff' (optionally ',veff'), "
            f"found {','.join(header)!r}",
        )
    fields = _read_rows(path, lines, 6, ",", header[3:], (nx, ny, nz))
    return _medium(path, lines, (dx, dy), levels, fields, source or _default_source(path, "JPL"))


def read_shdom_particle_file(path: str | os.PathLike, *, source: str | None = None) -> xr.Dataset:
    """Read an SHDOM particle-file text (e.g. ``les_stcu.txt``) into a microphysical medium.

    The z levels on line 3 are read like the JPL format's altitude levels: the lower edges
    of the cell layers, the top being the last level plus the last spacing. (SHDOM itself
    treats them as grid points with values interpolated in between; cloudct's media are
    piecewise constant, and this choice keeps both LES formats on the same footing.)

    Args:
        path: the text file.
        source: the ``source`` attribute (attribution); by default the file name and format.

    Returns:
        A validated medium with ``lwc`` [g m-3] and ``reff`` [micron]; non-uniform levels
        give a ``z_bounds`` variable.

    Raises:
        LESFormatError: the file is malformed.
        FileNotFoundError: no such file.
    """
    path = Path(path)
    lines = _read_lines(path)
    sizes = _numbers(path, lines, 2, None, int, "nx ny nz")
    if len(sizes) != 3:
        raise LESFormatError(path, 2, f"expected nx ny nz (3 integers), found {len(sizes)} values")
    nx, ny, nz = _positive(path, 2, sizes, "nx ny nz")
    values = _numbers(path, lines, 3, None, float, "dx dy and z levels")
    if len(values) < 2:
        raise LESFormatError(path, 3, "expected dx dy followed by the z levels")
    dx, dy = _positive(path, 3, values[:2], "dx dy")
    levels = _levels(path, 3, values[2:], nz)
    fields = _read_rows(path, lines, 4, None, ["lwc", "reff"], (nx, ny, nz))
    return _medium(path, lines, (dx, dy), levels, fields, source or _default_source(path, "SHDOM"))


def read_les(path: str | os.PathLike, *, source: str | None = None) -> xr.Dataset:
    """Read an LES text file in either format, telling them apart by line 2.

    ``nx,ny,nz`` with commas is the JPL-LES format, ``nx ny nz`` with blanks the SHDOM
    particle file. See :func:`read_jpl_les` and :func:`read_shdom_particle_file`.
    """
    path = Path(path)
    if "," in _content(path, _read_lines(path), 2):
        return read_jpl_les(path, source=source)
    return read_shdom_particle_file(path, source=source)


def bundled_single_cloud() -> xr.Dataset:
    """The seed paper's "single cloud": JPL-LES rico32x37x26 shipped in ``cloudct/data``.

    32 x 37 x 26 cells of 20 m x 20 m x 40 m, z from 0.44 to 1.48 km.
    """
    return _bundled("rico32x37x26.txt", BUNDLED_SOURCE)


def bundled_cloud_field() -> xr.Dataset:
    """The whole JPL-LES cloud field rico122x106x39 shipped in ``cloudct/data``: shallow
    cumulus over 122 x 106 x 39 cells of 20 m x 20 m x 40 m (2.44 x 2.12 km, z from 0.44
    to 2.0 km). The LES domain is horizontally periodic, so this field may be rendered with
    periodic boundaries."""
    return _bundled("rico122x106x39.txt", BUNDLED_FIELD_SOURCE)


def seed_paper_cloud_field() -> xr.Dataset:
    """The seed paper's cloud field: the 79 x 84 x 27 window of :func:`bundled_cloud_field`
    (1.58 x 1.68 x 1.08 km) that holds the most cloudy cells (LWC > 0;
    :func:`densest_window`), i.e. that cuts the fewest away.

    That is cells x 39..117, y 14..97, z 3..29 of rico122x106x39 (x 0.78 .. 2.36 km,
    y 0.28 .. 1.96 km, z 0.56 .. 1.64 km): 85 % of the field's cloudy cells and 91 % of its
    water; it keeps the cloud base (layer 3) and cuts the tallest tops (layers 30..32,
    1.3 % of the cloudy cells). (The window of the most water instead, z 4..30, would cut
    the whole cloud-base layer, since LWC grows with height.) The coordinates stay those of
    the LES domain. A window of an LES domain is not periodic: clouds cut by its side faces
    do not continue on the opposite side.
    """
    field = bundled_cloud_field()
    corner = densest_window(field["lwc"].values > 0.0, SEED_PAPER_FIELD_SHAPE)
    window = {axis: slice(start, start + size) for axis, start, size
              in zip("xyz", corner, SEED_PAPER_FIELD_SHAPE, strict=True)}
    ranges = ", ".join(f"{axis} {s.start}..{s.stop - 1}" for axis, s in window.items())
    return field.isel(window).assign_attrs(
        title="seed paper cloud field (79 x 84 x 27 window of rico122x106x39)",
        source=f"{BUNDLED_FIELD_SOURCE}; the window of the most cloudy cells, cells {ranges}",
    )


def densest_window(field: np.ndarray, shape: tuple[int, int, int]) -> tuple[int, int, int]:
    """The lowest corner (i, j, k) of the window of ``shape`` cells over which ``field``
    (for instance a cloud mask) sums to the most, from summed volumes over every position
    of the window in the grid; the first in (i, j, k) order among equal sums.

    Raises:
        ValueError: a window larger than the grid.
    """
    if any(n > size for n, size in zip(shape, field.shape, strict=True)):
        raise ValueError(f"a window of {shape} cells does not fit a grid of {field.shape}")
    total = np.zeros(tuple(s + 1 for s in field.shape))
    total[1:, 1:, 1:] = np.asarray(field, dtype=float).cumsum(0).cumsum(1).cumsum(2)
    lo = tuple(slice(None, total.shape[d] - shape[d]) for d in range(3))
    hi = tuple(slice(shape[d], None) for d in range(3))
    sums = np.zeros(tuple(s - n + 1 for s, n in zip(field.shape, shape, strict=True)))
    for corner in itertools.product((0, 1), repeat=3):  # inclusion-exclusion
        sign = -1.0 if (3 - sum(corner)) % 2 else 1.0
        sums += sign * total[tuple(hi[d] if corner[d] else lo[d] for d in range(3))]
    return tuple(int(i) for i in np.unravel_index(np.argmax(sums), sums.shape))


def _bundled(name: str, source: str) -> xr.Dataset:
    """The JPL-LES file ``name`` shipped in ``cloudct/data``, with its attribution."""
    resource = importlib.resources.files("cloudct") / "data" / name
    with importlib.resources.as_file(resource) as path:
        return read_jpl_les(path, source=source)


# ---------------------------------------------------------------------------------------
# Parsing helpers; line numbers are 1-based.
# ---------------------------------------------------------------------------------------


def _read_lines(path: Path) -> list[str]:
    data = path.read_bytes()
    try:
        return data.decode("utf-8").splitlines()
    except UnicodeDecodeError as err:
        line = data[: err.start].count(b"\n") + 1
        raise LESFormatError(path, line, "not a text file (undecodable bytes)") from err


def _content(path: Path, lines: list[str], number: int) -> str:
    """Line ``number`` without its trailing ``# comment``."""
    if number > len(lines):
        raise LESFormatError(path, number, "the file ends before the header is complete")
    return lines[number - 1].split("#", 1)[0].strip()


def _numbers(
    path: Path, lines: list[str], number: int, sep: str | None, kind: type, what: str
) -> list:
    text = _content(path, lines, number)
    try:
        values = [kind(field) for field in text.split(sep)]
    except ValueError:
        raise LESFormatError(
            path, number, f"expected {what}, found non-numeric values in {text!r}"
        ) from None
    if not all(np.isfinite(values)):
        raise LESFormatError(path, number, f"non-finite value in {what}: {text!r}")
    return values


def _positive(path: Path, number: int, values: list, what: str) -> list:
    if any(v <= 0 for v in values):
        raise LESFormatError(path, number, f"{what} must be positive, found {values}")
    return values


def _levels(path: Path, number: int, levels: list[float], nz: int) -> np.ndarray:
    if len(levels) != nz:
        raise LESFormatError(path, number, f"expected nz = {nz} z levels, found {len(levels)}")
    if nz < 2:
        raise LESFormatError(path, number, "one z level does not give the layer thickness")
    levels = np.array(levels)
    if np.any(np.diff(levels) <= 0):
        raise LESFormatError(path, number, "z levels must be strictly increasing")
    return levels


def _read_rows(
    path: Path,
    lines: list[str],
    first: int,
    sep: str | None,
    columns: list[str],
    shape: tuple[int, int, int],
) -> dict[str, np.ndarray]:
    """Sparse rows ``i j k value...`` from line ``first`` on, as dense arrays (0 elsewhere)."""
    fields = {name: np.zeros(shape) for name in columns}
    seen = np.zeros(shape, dtype=np.int64)  # line number of each cell's row, 0 if absent
    ncol = 3 + len(columns)
    for number in range(first, len(lines) + 1):
        text = _content(path, lines, number)
        if not text:
            continue
        row = text.split(sep)
        if len(row) != ncol:
            raise LESFormatError(
                path,
                number,
                f"expected {ncol} fields (i j k {' '.join(columns)}), found {len(row)}",
            )
        cell = tuple(_integer(path, number, field) for field in row[:3])
        for axis, (index, size) in enumerate(zip(cell, shape, strict=True)):
            if not 0 <= index < size:
                raise LESFormatError(
                    path,
                    number,
                    f"index {'ijk'[axis]} = {index} out of range 0..{size - 1} (0-based indices)",
                )
        if seen[cell]:
            raise LESFormatError(
                path, number, f"duplicate cell {cell}, first given on line {seen[cell]}"
            )
        seen[cell] = number
        values = dict(zip(columns, (_value(path, number, f) for f in row[3:]), strict=True))
        _check_row(path, number, values)
        for name, value in values.items():
            fields[name][cell] = value
    return fields


def _integer(path: Path, number: int, field: str) -> int:
    try:
        return int(field)
    except ValueError:
        raise LESFormatError(path, number, f"index {field.strip()!r} is not an integer") from None


def _value(path: Path, number: int, field: str) -> float:
    try:
        value = float(field)
    except ValueError:
        raise LESFormatError(path, number, f"non-numeric value {field.strip()!r}") from None
    if not np.isfinite(value):
        raise LESFormatError(path, number, f"non-finite value {field.strip()!r}")
    return value


def _check_row(path: Path, number: int, values: dict[str, float]) -> None:
    if values["lwc"] < 0:
        raise LESFormatError(path, number, f"negative LWC {values['lwc']:g}")
    for name in ("reff", "veff"):
        if name not in values:
            continue
        if values[name] < 0:
            raise LESFormatError(path, number, f"negative {name} {values[name]:g}")
        if values["lwc"] > 0 and values[name] == 0:
            raise LESFormatError(path, number, f"{name} = 0 in a cell with LWC > 0")


def _medium(
    path: Path,
    lines: list[str],
    spacing: tuple[float, float],
    levels: np.ndarray,
    fields: dict[str, np.ndarray],
    source: str,
) -> xr.Dataset:
    """The medium Dataset on the LES grid (see the module docstring for the geometry)."""
    nx, ny, nz = fields["lwc"].shape
    dx, dy = spacing
    thickness = np.diff(levels)
    edges = np.append(levels, levels[-1] + thickness[-1])
    uniform = np.all(np.abs(thickness - thickness.mean()) <= SPACING_RTOL * thickness.mean())
    return microphysical_medium(
        (np.arange(nx) + 0.5) * dx,
        (np.arange(ny) + 0.5) * dy,
        0.5 * (edges[:-1] + edges[1:]),
        fields["lwc"],
        fields["reff"],
        veff=fields.get("veff"),
        z_bounds=None if uniform else np.stack([edges[:-1], edges[1:]], axis=1),
        title=lines[0].lstrip("#! \t").strip() or path.name,
        source=source,
    )


def _default_source(path: Path, fmt: str) -> str:
    names = {"JPL": "JPL-LES text format of pyshdom/AT3D", "SHDOM": "SHDOM particle file"}
    return f"LES field read from {path.name}, {names[fmt]}"
