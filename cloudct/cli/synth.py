"""``cloudct synth``: noisy synthetic measurements of a medium."""

from __future__ import annotations

import argparse
from pathlib import Path

from cloudct.cli.options import (
    add_backend_option,
    add_optics_option,
    chosen_backend,
    medium_from_options,
    say_memory,
)
from cloudct.mc.scene import load_scene, single_cloud_scene_of
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
    medium = medium_from_options(args.medium, args.optics)
    scene = single_cloud_scene_of(medium) if args.scene is None else load_scene(args.scene)
    noise = None
    if args.noise_electrons is not None:
        noise = NoiseModel(args.noise_electrons, read_noise=args.read_noise or 0.0)
    output = Path(args.output)
    if output.exists() and not args.overwrite:
        raise FileExistsError(f"{output} exists (use --overwrite)")
    say_memory("synth", medium, scene, DEFAULT_BATCHES, gradient=False)
    ds = synthesize_measurements(
        medium, scene, photons=args.photons, seed=args.seed, noise=noise,
        wavelength=args.wavelength, optics=args.optics, progress=None,
        backend=chosen_backend(args), method=args.method,
    )
    save_measurements(ds, output, overwrite=args.overwrite)
    noise_text = "no camera noise" if noise is None else (
        f"{noise.electrons:g} e- at radiance 1/pi, read noise {noise.read_noise:g} e-"
    )
    print(
        f"wrote {output}: {ds.sizes['view']} views of {ds.sizes['row']}x{ds.sizes['col']}, "
        f"{ds.attrs['photons']} photons ({ds.attrs['method']}) on the {ds.attrs['backend']} "
        f"back end, {noise_text}"
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
    p.add_argument("--seed", type=int, default=0, help="seed of the render and the noise")
    p.add_argument(
        "--noise-electrons", type=float, metavar="E",
        help="mean photo-electrons at radiance 1/pi (white plate facing the sun); "
        "default: no camera noise",
    )
    p.add_argument("--read-noise", type=float, metavar="R", help="read noise [electrons rms]")
    p.add_argument("--wavelength", type=float, default=DEFAULT_WAVELENGTH,
                   help="wavelength [micron] (default %(default)s)")
    add_optics_option(p)
    add_backend_option(p)
    p.add_argument("--overwrite", action="store_true", help="replace an existing output")
    p.set_defaults(func=_cli_synth)
