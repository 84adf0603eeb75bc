"""More test clouds for the retrieval, from the bundled LES fields.

The seed paper's single cloud was the only scene the retrieval's defaults and the L1
prior's weight were measured on. These scenes check whether they carry over; all get the
single cloud's optics (Mie extinction at 0.672 micron, HG g = 0.85, cloud albedo 0.99,
the file's air), or with ``--optics mie`` Mie phase functions and albedos of their
droplets (the measurements of a Mie retrieval, issue 38):

- ``two_cumuli``: the two largest isolated cumuli of ``rico122x106x39`` after its
  stratocumulus (connected components of 851 and 817 cloudy voxels, 10-12 levels deep,
  against the single cloud's 3,943 voxels over 26 levels), every other cloud removed,
  cropped with a margin of two voxels, from the field's bottom.
- ``stratocumulus``: a 32 x 32 column patch of the broken stratocumulus deck of
  ``les_stcu`` (SHDOM's; 55 m columns, 16 levels of 25 m), x and y from 16 to 47: a
  layer cloud that fills most of its box, unlike the cumuli, whose carved hull is about
  twice the cloud.

Usage::

    python -m benchmarks scenes two_cumuli [--optics hg|mie] [--output FILE]  (default
        benchmarks/work/two_cumuli.nc, two_cumuli_mie.nc with Mie optics)
    python -m benchmarks scenes stratocumulus [--output benchmarks/work/stratocumulus.nc]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import xarray as xr
from scipy import ndimage

from benchmarks.common import REPO, WORK
from cloudct.les import read_les
from cloudct.medium import save_medium
from cloudct.optics import OPTICS, to_optical

LES = REPO.parent / "shared" / "data" / "les"
#: two_cumuli: how many of the largest clouds to skip (the stratocumulus) and to keep, and
#: the margin of clear voxels around them.
SKIP, KEEP, MARGIN = 1, 2, 2
#: stratocumulus: the patch's first column and its width, in columns.
PATCH_START, PATCH_SIZE = 16, 32


def cloud_optics(microphysics: xr.Dataset, title: str, optics: str = "hg") -> xr.Dataset:
    """The optical medium of a microphysical one: with the single cloud's optics (``hg``),
    or with Mie phase functions and albedos (``mie``)."""
    optical = to_optical(microphysics, optics=optics)
    optical.attrs["title"] = title
    return optical


def two_cumuli(les: xr.Dataset, optics: str = "hg") -> xr.Dataset:
    """The two cumuli scene (see the module documentation) of ``rico122x106x39``."""
    label, n = ndimage.label(les["lwc"].values > 0)
    sizes = ndimage.sum_labels(np.ones(label.shape), label, np.arange(1, n + 1))
    keep = 1 + np.argsort(sizes)[::-1][SKIP : SKIP + KEEP]
    inside = np.isin(label, keep)
    microphysics = les.copy()
    for name in ("lwc", "reff"):
        microphysics[name] = les[name].where(inside, 0.0)
    box = [np.flatnonzero(inside.any(axis=tuple(a for a in range(3) if a != axis)))
           for axis in range(3)]
    crop = {
        dim: slice(max(b[0] - MARGIN, 0), min(b[-1] + 1 + MARGIN, les.sizes[dim]))
        for dim, b in zip(("x", "y", "z"), box, strict=True)
    }
    crop["z"] = slice(0, crop["z"].stop)  # from the field's bottom, as the single cloud
    return cloud_optics(
        microphysics.isel(crop), "two cumuli of rico122x106x39 (components 2 and 3 by size)",
        optics,
    )


def stratocumulus(les: xr.Dataset, optics: str = "hg") -> xr.Dataset:
    """The stratocumulus patch (see the module documentation) of ``les_stcu``."""
    patch = slice(PATCH_START, PATCH_START + PATCH_SIZE)
    return cloud_optics(
        les.isel(x=patch, y=patch),
        f"les_stcu columns {PATCH_START}-{PATCH_START + PATCH_SIZE - 1} in x and y", optics,
    )


SCENES = {"two_cumuli": (two_cumuli, "rico122x106x39.txt"),
          "stratocumulus": (stratocumulus, "les_stcu.txt")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("scene", choices=sorted(SCENES))
    parser.add_argument("--les", default=None,
                        help="the LES file (default: the scene's, in ../shared/data/les)")
    parser.add_argument("--optics", choices=OPTICS, default="hg",
                        help="the single cloud's HG optics (default) or Mie optics")
    parser.add_argument("--output", default=None,
                        help="medium netCDF (default: benchmarks/work/SCENE.nc, "
                             "SCENE_mie.nc with Mie optics)")
    args = parser.parse_args()
    build, les_file = SCENES[args.scene]
    medium = build(read_les(args.les or LES / les_file), args.optics)
    suffix = "" if args.optics == "hg" else f"_{args.optics}"
    output = Path(args.output or WORK / f"{args.scene}{suffix}.nc")
    output.parent.mkdir(parents=True, exist_ok=True)
    save_medium(medium, output, overwrite=True)
    cloud = medium["cloud_extinction"].values
    print(f"{output}: grid {cloud.shape}, {int((cloud > 0).sum())} cloudy voxels, "
          f"extinction up to {cloud.max():.1f} /km")


if __name__ == "__main__":
    main()
