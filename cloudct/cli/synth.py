"""``cloudct synth``: noisy synthetic measurements of a medium."""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

from cloudct.cli.options import (
    add_backend_option,
    add_bands_option,
    add_optics_option,
    band_medium_from_options,
    chosen_backend,
    medium_from_options,
    say_memory,
)
from cloudct.mc.scene import load_scene, single_cloud_scene_of
from cloudct.measurement_bands import synthesize_bands
from cloudct.measurements import (
    DEFAULT_BATCHES,
    DEFAULT_PHOTONS,
    NoiseModel,
    save_measurements,
    synthesize_measurements,
)
from cloudct.physics.mie import DEFAULT_WAVELENGTH


def _cli_synth(args: argparse.Namespace) -> int:
    """``cloudct synth``: synthetic measurements of a medium, to netCDF."""
    if args.read_noise is not None and args.noise_electrons is None:
        raise ValueError("--read-noise needs --noise-electrons (the signal level)")
    albedo = args.ground_albedo
    if albedo is not None and len(albedo) > 1 and len(albedo) != len(args.bands or [None]):
        raise ValueError(f"--ground-albedo takes one value, or one per band of --bands; got "
                         f"{len(albedo)}")
    if args.bands:
        medium = band_medium_from_options(args.medium, args.optics)
    else:
        medium = medium_from_options(args.medium, args.optics)
    scene = single_cloud_scene_of(medium) if args.scene is None else load_scene(args.scene)
    noise = None
    if args.noise_electrons is not None:
        noise = NoiseModel(args.noise_electrons, read_noise=args.read_noise or 0.0)
    output = Path(args.output)
    if output.exists() and not args.overwrite:
        raise FileExistsError(f"{output} exists (use --overwrite)")
    say_memory("synth", medium, scene, DEFAULT_BATCHES, gradient=False)
    run = dict(photons=args.photons, seed=args.seed, noise=noise, progress=None,
               backend=chosen_backend(args), method=args.method)
    if args.bands:
        ds = synthesize_bands(medium, args.bands, scene, ground_albedo=albedo, **run)
    else:
        if albedo is not None:
            scene = replace(scene, ground_albedo=albedo[0])
        ds = synthesize_measurements(medium, scene, wavelength=args.wavelength,
                                     optics=args.optics, **run)
    save_measurements(ds, output, overwrite=args.overwrite)
    noise_text = "no camera noise" if noise is None else (
        f"{noise.electrons:g} e- at radiance 1/pi, read noise {noise.read_noise:g} e-"
    )
    bands = "" if not args.bands else (
        f"{ds.sizes['band']} bands ({', '.join(f'{w:g}' for w in ds['wavelength'].values)} "
        f"micron, {ds.attrs['optics']} optics) x "
    )
    print(
        f"wrote {output}: {bands}{ds.sizes['view']} views of {ds.sizes['row']}x"
        f"{ds.sizes['col']}, {ds.attrs['photons']} photons{' per band' if bands else ''} "
        f"({ds.attrs['method']}) on the {ds.attrs['backend']} back end, {noise_text}"
    )
    return 0


def register_cli(subparsers: argparse._SubParsersAction) -> None:
    """Add ``cloudct synth``."""
    p = subparsers.add_parser(
        "synth",
        help="synthesize noisy multi-view measurements of a medium",
        description="Render a medium (default: the bundled single cloud) for a scene "
        "(default: the seed paper's nine cameras) with many photons, add camera noise "
        "(Poisson photo-electrons at the stated signal level plus Gaussian read noise), and "
        "write a measurement netCDF.",
    )
    p.add_argument("medium", nargs="?", help="medium netCDF (default: bundled single cloud)")
    p.add_argument("-o", "--output", default="measurements.nc", help="output netCDF")
    p.add_argument("--scene", help="scene netCDF from `cloudct scene` (default: nine cameras)")
    p.add_argument("--photons", type=int, default=DEFAULT_PHOTONS, help="forward photons")
    p.add_argument("--method", choices=("forward", "combined"), default=None,
                   help="the render's estimator: forward, or combined (the forward photons "
                   "and 4 backward paths per photon, weighted by multiple importance sampling: "
                   "no fireflies with Mie optics); default: combined with Mie optics, else "
                   "forward")
    p.add_argument("--seed", type=int, default=0, help="seed of the render and the noise "
                   "(band i of --bands: SEED + i)")
    p.add_argument(
        "--noise-electrons", type=float, metavar="E",
        help="mean photo-electrons at radiance 1/pi (white plate facing the sun); "
        "default: no camera noise",
    )
    p.add_argument("--read-noise", type=float, metavar="R", help="read noise [electrons rms]")
    wavelength = p.add_mutually_exclusive_group()
    wavelength.add_argument("--wavelength", type=float, default=DEFAULT_WAVELENGTH,
                            help="wavelength [micron] (default %(default)s)")
    add_bands_option(wavelength, "measurements")
    p.add_argument("--ground-albedo", type=float, nargs="+", metavar="A",
                   help="a Lambertian ground's albedo in [0, 1]: one value, or with --bands "
                   "one per band (default: the scene's; without --scene, no ground)")
    add_optics_option(p, "Default: a medium's recorded choice, else 'hg' ('mie' with --bands)")
    add_backend_option(p)
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=_cli_synth)
