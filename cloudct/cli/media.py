"""``cloudct les2nc``: an LES text file to a medium netCDF file."""

from __future__ import annotations

import argparse
from pathlib import Path

from cloudct.les import read_les
from cloudct.medium import save_medium
from cloudct.optics import DEFAULT_OPTICS, OPTICS, with_optics


def register_cli(subparsers: argparse._SubParsersAction) -> None:
    """Add ``cloudct les2nc FILE -o OUT [--optics hg|mie] [--overwrite] [--source TEXT]``."""
    parser = subparsers.add_parser(
        "les2nc",
        help="convert an LES text file to a medium netCDF file",
        description=(
            "Read an LES text file (JPL-LES/pyshdom format or SHDOM particle file, "
            "detected automatically) and write it as a cloudct medium netCDF file: the "
            "microphysics (lwc, reff) with the cloud optics chosen for it, which every "
            "command that renders it uses."
        ),
    )
    parser.add_argument("file", type=Path, help="LES text file")
    parser.add_argument(
        "-o", "--output", type=Path, required=True, help="medium netCDF file to write"
    )
    parser.add_argument("--overwrite", action="store_true", help="replace an existing output")
    parser.add_argument("--source", help="attribution stored in the 'source' attribute")
    parser.add_argument(
        "--optics", choices=OPTICS, default=DEFAULT_OPTICS,
        help="cloud optics, recorded in the file: 'hg' (the seed paper's: Mie extinction, "
        "Henyey-Greenstein g 0.85, cloud albedo 0.99; the default) or 'mie' (Mie albedos "
        "and phase functions)",
    )
    parser.set_defaults(func=_les2nc)


def _les2nc(args: argparse.Namespace) -> int:
    ds = with_optics(read_les(args.file, source=args.source), args.optics)
    save_medium(ds, args.output, overwrite=args.overwrite)
    sizes = " x ".join(str(ds.sizes[d]) for d in ("x", "y", "z"))
    cloudy = int((ds["lwc"] > 0).sum())
    print(
        f"wrote {args.output}: {sizes} cells, {cloudy} cloudy, "
        f"max LWC {float(ds['lwc'].max()):.4g} g m-3, optics {args.optics!r}"
    )
    return 0
