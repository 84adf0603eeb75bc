"""Questions asked of a medium Dataset: which cloud description it holds, and the cell
edges and outer faces of its grid.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from cloudct.medium.schema import DomainBounds
from cloudct.medium.validation import _check_grid


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
