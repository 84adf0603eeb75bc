"""``cloudct carve``: the cloud's hull and an initial medium from measurements."""

from __future__ import annotations

import argparse
from pathlib import Path

from cloudct.cli.options import (
    add_backend_option,
    add_optics_option,
    chosen_backend,
    measured_optics,
    medium_from_options,
    retrieval_measurements,
)
from cloudct.medium import save_medium
from cloudct.retrieval.carving import (
    FIT_PHOTONS,
    PROFILES,
    carve,
    initial_medium,
)
from cloudct.retrieval.carving_figure import save_hull_figure


def _cli_carve(args: argparse.Namespace) -> int:
    """``cloudct carve``: hull and initial medium from measurements."""
    measurements = retrieval_measurements(args.measurements, "carve")
    template = medium_from_options(args.medium, measured_optics(measurements, args.optics))
    output = Path(args.output)
    if output.exists() and not args.overwrite:
        raise FileExistsError(f"{output} exists (use --overwrite)")
    carved = carve(
        measurements, template, k=args.k, threshold=args.threshold, profile=args.profile,
        fit_photons=args.fit_photons if args.extinction is None else None,
        backend=chosen_backend(args) if args.extinction is None else "cpu",
    )
    medium = initial_medium(carved, template, args.extinction)
    save_medium(medium, output, overwrite=args.overwrite)
    figure = "" if args.figure is None else (
        f" and {save_hull_figure(carved, measurements, args.figure)}"
    )
    print(
        f"wrote {output}{figure}: hull of {int(carved['hull'].sum())} of "
        f"{carved['hull'].size} voxels (k = {carved.attrs['k']} of {carved.attrs['views']} "
        f"views), {carved.attrs['profile']} profile, mean cloud extinction "
        f"{float(medium['cloud_extinction'].values[carved['hull'].values > 0].mean()):.4g} /km"
    )
    return 0


def register_cli(subparsers: argparse._SubParsersAction) -> None:
    """Add ``cloudct carve``."""
    p = subparsers.add_parser(
        "carve",
        help="space-carve the cloud's hull from measurements into an initial medium",
        description="Space carving (seed paper Sec. 6.1.1): voxels seen as cloudy by at "
        "least K views form the hull, filled in proportion to the faintest excess radiance "
        "in which the views see each voxel (or with a constant extinction) at the mean "
        "extinction whose rendered images match the measured brightness (or a given one), on "
        "a template medium's grid.",
    )
    p.add_argument("measurements", help="measurement netCDF (from `cloudct synth`); of a file "
                   "with several bands, its 0.672 micron band")
    p.add_argument("-o", "--output", default="init.nc", help="output medium netCDF")
    p.add_argument("--medium", help="template medium netCDF giving the grid and the air "
                   "(default: the bundled single cloud)")
    p.add_argument("--k", type=int,
                   help="views that must see a voxel as cloudy (default: all but one)")
    p.add_argument("--threshold", type=float, help="cloudy-pixel radiance above the "
                   "clear-sky background (default: per-view rule)")
    p.add_argument("--profile", choices=PROFILES, default="excess",
                   help="shape of the extinction in the hull: 'excess' (soft carving, the "
                   "default), 'adiabatic' (soft carving x (z - z_base)^(2/3) above the hull's "
                   "base) or 'constant' (the seed paper's)")
    p.add_argument("--extinction", type=float,
                   help="mean cloud extinction in the hull [1/km] (default: fitted)")
    p.add_argument("--fit-photons", type=int, default=FIT_PHOTONS,
                   help="photons per trial render of the extinction fit")
    p.add_argument("--figure", help="PNG of the views with the cloudy pixels and the hull")
    add_optics_option(p, "Default: the measurements' recorded optics, else 'hg'")
    add_backend_option(p)
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=_cli_carve)
