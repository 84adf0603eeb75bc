"""``cloudct render`` and ``cloudct scene``: images of a medium, and the scene that frames it."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from cloudct.cli.options import (
    add_bands_option,
    add_distributed_options,
    add_optics_option,
    add_phase_truncation_option,
    band_medium_from_options,
    chosen_backend,
    medium_from_options,
    say_memory,
    truncated_as_asked,
)
from cloudct.distributed import close_client, connect, executor
from cloudct.mc.render import METHODS, render, save_images, save_previews
from cloudct.mc.scene import (
    BOUNDARIES,
    PRESETS,
    build_scene,
    load_scene,
    single_cloud_scene_of,
)
from cloudct.mc.scene_figure import save_scene_figure
from cloudct.mc.sensors import domain_means
from cloudct.measurement_bands import stack_bands
from cloudct.measurements import band_measurements
from cloudct.medium import cell_edges
from cloudct.netcdf import save_netcdf
from cloudct.optics import band_optics


def _cli_render(args: argparse.Namespace) -> int:
    """``cloudct render``: images of a medium for a scene, to netCDF and PNG previews."""
    if args.bands and (args.fluxes or args.probe):
        raise ValueError("--bands renders images; --fluxes and --probe are one wavelength's")
    if args.bands:  # one optical medium per band, as cloudct synth --bands
        media = band_optics(band_medium_from_options(args.medium, args.optics), args.bands)
    else:
        media = [medium_from_options(args.medium, args.optics)]
    media = [truncated_as_asked(m, args.phase_truncation) for m in media]
    medium = media[0]
    scene = single_cloud_scene_of(medium) if args.scene is None else load_scene(args.scene)
    output = Path(args.output)
    if output.exists() and not args.overwrite:
        raise FileExistsError(f"{output} exists (use --overwrite)")
    if args.fluxes or args.probe:
        return _render_fluxes(args, medium, scene, output)
    backend = chosen_backend(args)  # this process's; a scheduler's workers resolve theirs
    client = connect(args.scheduler, args.workers, backend=backend)
    spread = None if client is None else executor(client)
    if args.scheduler:
        backend = args.backend
    say_memory("render", medium, scene, args.batches, gradient=False,
               way_out="fewer batches (--batches), fewer or smaller images, a coarser grid")
    try:
        # compile (or load from the numba cache) first, so that the reported rate is the
        # render's
        warm_up = {} if args.method != "combined" else {"pixel_samples": 2}
        render(medium, scene, photons=2, method=args.method, batches=2, progress=False,
               backend=backend, executor=spread, **warm_up)
        bands = [
            render(
                band, scene, photons=args.photons, method=args.method, seed=args.seed + i,
                batches=args.batches, aim_fraction=args.aim_fraction, progress=None,
                backend=backend, executor=spread, pixel_samples=args.pixel_samples,
            )
            for i, band in enumerate(media)
        ]
    finally:
        if client is not None:
            close_client(client)
    png = Path(args.png or output.with_suffix(""))
    if args.bands:
        images = stack_bands([b.assign_attrs(wavelength=float(m.attrs["wavelength"]))
                              for b, m in zip(bands, media, strict=True)])
        save_images(images, output, overwrite=args.overwrite)
        previews = [f for w in images["wavelength"].values
                    for f in save_previews(band_measurements(images, w), png / f"band_{w:g}um")]
    else:
        images = bands[0]
        save_images(images, output, overwrite=args.overwrite)
        previews = save_previews(images, png)
    photons = sum(b.attrs["photons"] for b in bands)
    seconds = sum(b.attrs["wall_time"] for b in bands)
    rate = photons / seconds
    where = ""
    if "workers" in images.attrs:
        where = (f", {images.attrs['workers']} workers, "
                 f"{sum(b.attrs['bytes_to_workers'] for b in bands) / 2**20:.3g} MiB out, "
                 f"{sum(b.attrs['bytes_from_workers'] for b in bands) / 2**20:.3g} MiB back")
    unit = "samples/px" if args.method == "backward" else "photons"
    count = f"{bands[0].attrs['photons']} {unit}"
    if args.method == "combined":
        count += (f" and {bands[0].attrs['pixel_samples']} samples/px, "
                  f"{100 * bands[0].attrs['backward_share']:.3g} % of the light by the backward")
    if args.bands:
        count = (f"{len(bands)} bands ({', '.join(f'{w:g}' for w in args.bands)} micron), "
                 f"{count} each")
    print(
        f"wrote {output} and {len(previews)} PNG previews in {png} "
        f"({count}, {seconds:.1f} s, {rate:.3g}/s{where})"
    )
    return 0


def _render_fluxes(args: argparse.Namespace, medium, scene, output: Path) -> int:
    """``cloudct render --fluxes``: the domain-mean fluxes and radiance probes
    (:func:`cloudct.mc.sensors.domain_means`) for the scene's sun, boundaries and ground."""
    if args.method != "forward" or args.workers or args.scheduler:
        raise ValueError("--fluxes and --probe run the forward method in this process "
                         "(no --method backward or combined, --workers or --scheduler)")
    means = domain_means(
        medium, directions=args.probe or [], sun=scene.sun, boundary=scene.boundary,
        ground_albedo=scene.ground_albedo, photons=args.photons, seed=args.seed,
        batches=args.batches, aim_fraction=args.aim_fraction, progress=None,
        backend=args.backend,
    )
    save_netcdf(means, output, overwrite=args.overwrite)
    shares = ", ".join(f"{name} {float(means[name]):.4g} +- {float(means[name + '_std_error']):.2g}"
                       for name in ("albedo", "transmittance", "absorptance", "side_escape",
                                    "ground_absorptance"))
    print(f"wrote {output} ({means.attrs['photons']} photons, "
          f"{means.attrs['wall_time']:.1f} s): {shares}")
    return 0


def _probe(text: str) -> tuple[float, float]:
    """``ZENITH:AZIMUTH`` (degrees) of ``--probe``."""
    zenith, _, azimuth = text.partition(":")
    try:
        return float(zenith), float(azimuth or 0.0)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"a probe is ZENITH:AZIMUTH in degrees, got {text!r}") from None


def _cli_scene(args: argparse.Namespace) -> int:
    """``cloudct scene``: write a nine-camera scene for a medium (preset and overrides)."""
    edges = cell_edges(medium_from_options(args.medium, None))
    scene = build_scene(
        np.array([e[0] for e in edges]), np.array([e[-1] for e in edges]),
        preset=args.preset, ring_zenith=args.ring_zenith, distance=args.distance,
        altitude=args.altitude, azimuths=args.azimuths, rings=args.ring,
        region=None if args.region is None else (args.region[::2], args.region[1::2]),
        npix=args.npix, fov=args.fov,
        sun_zenith=args.sun_zenith, sun_azimuth=args.sun_azimuth, boundary=args.boundary,
        ground_albedo=args.ground_albedo,
    )
    output = Path(args.output)
    save_netcdf(scene.to_dataset(), output, overwrite=args.overwrite)
    written = f"wrote {output} ({len(scene.cameras)} cameras)"
    if args.figure:
        figure = save_scene_figure(scene, [e[0] for e in edges], [e[-1] for e in edges],
                                   args.figure)
        written += f" and {figure}"
    print(written)
    return 0


def _ring(text: str) -> tuple[float, list[float] | None]:
    """``ZENITH`` or ``ZENITH:AZ,AZ,...`` (degrees) of ``--ring``."""
    zenith, _, azimuths = text.partition(":")
    try:
        return float(zenith), ([float(a) for a in azimuths.split(",")] if azimuths else None)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"a ring is ZENITH or ZENITH:AZ,AZ,... in degrees, got {text!r}") from None


def register_cli(subparsers: argparse._SubParsersAction) -> None:
    """Add ``cloudct render`` and ``cloudct scene``."""
    p = subparsers.add_parser(
        "render",
        help="render multi-view images of a medium (default: the bundled single cloud)",
        description="Render images of a medium netCDF for a scene netCDF (default: the seed "
        "paper's single-cloud scene) to a netCDF of images plus PNG previews.",
    )
    p.add_argument("medium", nargs="?", help="medium netCDF (default: bundled single cloud)")
    p.add_argument("--scene", help="scene netCDF from `cloudct scene` (default: nine cameras)")
    p.add_argument("-o", "--output", default="images.nc", help="output netCDF of images")
    p.add_argument("--png", help="directory for PNG previews (default: next to the output)")
    p.add_argument("--photons", type=int, default=1_000_000,
                   help="forward (and combined) photons, or backward samples per pixel")
    p.add_argument("--method", choices=METHODS, default="forward",
                   help="forward (local estimation), backward (next-event estimation to the "
                   "sun) or combined (both, weighted by multiple importance sampling: the "
                   "fewest fireflies with Mie optics)")
    p.add_argument("--pixel-samples", type=int, default=None, metavar="N",
                   help="combined: backward samples per pixel (default: 4 backward paths "
                   "per photon, over the pixels)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--batches", type=int, default=32)
    p.add_argument("--aim-fraction", type=float, default=None, metavar="A",
                   help="forward: share of scattering directions aimed at the cameras "
                   "(unbiased; tames Mie fireflies). 0 switches it off; default 0.1 with Mie "
                   "(tabulated) phase functions, else 0")
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.add_argument("--fluxes", action="store_true",
                   help="write the domain-mean fluxes (albedo, transmittance, absorptance, "
                   "side escape, ground absorption, with standard errors) for the scene's "
                   "sun, boundaries and ground instead of images (forward, CPU)")
    p.add_argument("--probe", type=_probe, action="append", metavar="ZENITH:AZIMUTH",
                   help="with --fluxes (implied): also the domain-mean radiance travelling "
                   "in this direction [deg]: zenith from +z (< 90 leaving the top, > 90 "
                   "arriving at the bottom), azimuth from +x toward +y; repeat for more")
    add_bands_option(p, "images")
    add_optics_option(p, "Default: a medium's recorded choice, else 'hg' ('mie' with --bands)")
    add_phase_truncation_option(p, "the medium", "as the medium records, else none")
    add_distributed_options(p)
    p.set_defaults(func=_cli_render)

    s = subparsers.add_parser(
        "scene", help="write a nine-camera scene for a medium (presets, sun, boundaries)",
        description="Write a scene netCDF: a zenith camera and a ring of eight aimed at the "
        "box centre (a ring at other azimuths or at an altitude on request). Presets: "
        "single-cloud (ring at 29 deg, 2 km, 76x76: the seed paper's single cloud), "
        "cloud-field (33 deg, 2.16 km, 86x86: its cloud field), nadir (10 deg, 1.2 x the "
        "box's horizontal diagonal, 128x128: wide domains); any number may be overridden. "
        "The field of view frames the box unless given.",
    )
    s.add_argument("medium", nargs="?", help="medium netCDF (default: bundled single cloud)")
    s.add_argument("--preset", choices=sorted(PRESETS), default="single-cloud")
    s.add_argument("--ring-zenith", type=float, metavar="DEG", help="ring cameras' zenith angle")
    where = s.add_mutually_exclusive_group()
    where.add_argument("--distance", type=float, metavar="KM",
                       help="cameras' distance from the box centre")
    where.add_argument("--altitude", type=float, metavar="KM",
                       help="every camera at this height instead (the ring farther away)")
    s.add_argument("--azimuths", type=float, nargs="+", metavar="DEG",
                   help="the ring cameras' azimuths (default: 0 45 ... 315)")
    s.add_argument("--ring", type=_ring, action="append", metavar="ZENITH[:AZ,AZ,...]",
                   help="a ring of cameras at this zenith angle [deg] (azimuths default 0 "
                   "45 ... 315); repeat for several rings (instead of --ring-zenith)")
    s.add_argument("--region", type=float, nargs=6,
                   metavar=("X0", "X1", "Y0", "Y1", "Z0", "Z1"),
                   help="aim the cameras at this box [km] and fit the field of view to it "
                   "(a part of a wide domain)")
    s.add_argument("--npix", type=int, metavar="N", help="image size, N x N pixels")
    s.add_argument("--fov", type=float, metavar="DEG", help="full field of view (default: "
                   "fitted to the box)")
    s.add_argument("--sun-zenith", type=float, default=0.0, metavar="DEG")
    s.add_argument("--sun-azimuth", type=float, default=0.0, metavar="DEG",
                   help="direction towards the sun, degrees from +x toward +y")
    s.add_argument("--boundary", choices=BOUNDARIES, default="open")
    s.add_argument("--ground-albedo", type=float, metavar="A",
                   help="Lambertian ground albedo (default: no ground)")
    s.add_argument("--figure", metavar="PNG", help="also draw the scene (from above and "
                   "from the side) to this PNG file")
    s.add_argument("-o", "--output", default="scene.nc")
    s.add_argument("--overwrite", action="store_true")
    s.set_defaults(func=_cli_scene)
