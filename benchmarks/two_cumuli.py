"""A second test cloud for the retrieval: two small cumuli of the RICO field.

The seed paper's single cloud was the only scene the retrieval's defaults and the L1
prior's weight were measured on. This writes another one, to see whether they carry over:
the two largest isolated cumuli of ``rico122x106x39`` after its stratocumulus
(connected components of 851 and 817 cloudy voxels, 10-12 levels deep, against the single
cloud's 3,943 voxels over 26 levels), every other cloud removed, cropped with a margin of
two voxels, with the single cloud's optics (Mie extinction at 0.672 micron, HG g = 0.85,
cloud albedo 0.99, the file's air). Usage::

    python benchmarks/two_cumuli.py [--les ../shared/data/les/rico122x106x39.txt]
        [--output benchmarks/work/two_cumuli.nc]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import xarray as xr
from scipy import ndimage

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))

from cloudct.medium import save_medium  # noqa: E402
from cloudct.physics.optics import to_optical  # noqa: E402
from data_synth.les import read_les  # noqa: E402

#: How many of the largest clouds to skip (the stratocumulus) and to keep.
SKIP, KEEP, MARGIN = 1, 2, 2


def two_cumuli(les: xr.Dataset) -> xr.Dataset:
    """The optical medium of the two cumuli (see the module documentation)."""
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
    optical = to_optical(microphysics.isel(crop), phase="hg", g=0.85)
    optical["cloud_albedo"] = xr.full_like(optical["cloud_extinction"], 0.99).assign_attrs(
        units="1", long_name="cloud single-scattering albedo"
    )
    optical.attrs["title"] = "two cumuli of rico122x106x39 (components 2 and 3 by size)"
    return optical


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--les", default=str(HERE.parent.parent / "shared" / "data" / "les"
                                             / "rico122x106x39.txt"))
    parser.add_argument("--output", default=str(HERE / "work" / "two_cumuli.nc"))
    args = parser.parse_args()
    medium = two_cumuli(read_les(args.les))
    Path(args.output).parent.mkdir(parents=True, exist_ok=True)
    save_medium(medium, args.output, overwrite=True)
    cloud = medium["cloud_extinction"].values
    print(f"{args.output}: grid {cloud.shape}, {int((cloud > 0).sum())} cloudy voxels, "
          f"extinction up to {cloud.max():.1f} /km")


if __name__ == "__main__":
    main()
