"""The figure of a space carving: the views with their cloudy pixels and the hull's
silhouette, and the hull's extinction profile (:mod:`cloudct.retrieval.carving`)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import xarray as xr

from cloudct.output_files import save_figure

# ---------------------------------------------------------------------------------------
# The hull figure
# ---------------------------------------------------------------------------------------


def save_hull_figure(carved: xr.Dataset, measurements: xr.Dataset, path: str | Path) -> Path:
    """Every view's measured image with the outlines of its cloudy pixels (cyan) and of the
    hull's silhouette (red), and below them the hull's extinction profile summed along z, y
    and x (top and side views, km). Returns the path written."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    radiance = measurements["radiance"].values
    nview = radiance.shape[0]
    ncol = max(math.ceil(math.sqrt(nview)), 3)
    nrow = math.ceil(nview / ncol) + 1  # the last row: the profile
    vmax = float(np.nanmax(radiance)) or 1.0
    fig, axes = plt.subplots(nrow, ncol, figsize=(2.6 * ncol, 2.6 * nrow + 0.4), squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    _profile_projections(carved, axes[-1])
    for v, ax in enumerate(axes[:-1].flat):
        if v >= nview:
            continue
        ax.imshow(radiance[v], cmap="gray", vmin=0.0, vmax=vmax)
        for name, colour in (("cloud_mask", "cyan"), ("hull_silhouette", "red")):
            field = carved[name].values[v]
            if field.any() and not field.all():
                ax.contour(field, levels=[0.5], colors=colour, linewidths=0.8)
        ax.set_title(f"view {v}", fontsize=8)
    fig.suptitle(
        f"space carving: cloudy pixels (cyan), hull silhouette (red); k = {carved.attrs['k']} "
        f"of {nview} views, {int(carved['hull'].sum())} voxels; "
        f"{carved.attrs['profile']} profile (bottom row)",
        fontsize=9,
    )
    fig.tight_layout()
    path = Path(path)
    save_figure(fig, path, dpi=120)
    plt.close(fig)
    return path


def _profile_projections(carved: xr.Dataset, axes) -> None:
    """The extinction profile summed along z, y and x on the first three of ``axes``."""
    profile = carved["extinction_profile"].transpose("x", "y", "z")
    edges = {
        name: (float(profile[name][0]), float(profile[name][-1])) for name in ("x", "y", "z")
    }
    for ax, (along, across, up) in zip(axes, (("z", "x", "y"), ("y", "x", "z"),
                                               ("x", "y", "z")), strict=False):
        image = profile.sum(along).transpose(up, across).values
        ax.axis("on")
        ax.imshow(image, origin="lower", cmap="magma", aspect="auto",
                  extent=(*edges[across], *edges[up]))
        ax.set_xlabel(f"{across} [km]", fontsize=7)
        ax.set_ylabel(f"{up} [km]", fontsize=7)
        ax.tick_params(labelsize=6)
        ax.set_title(f"profile summed along {along}", fontsize=8)
