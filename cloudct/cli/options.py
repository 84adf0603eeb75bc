"""Command-line options shared by several commands."""

from __future__ import annotations

import argparse
import sys

import xarray as xr

from cloudct.mc.backend import (
    BACKENDS,
    cuda_unavailable_reason,
    device_description,
    resolve_backend,
)
from cloudct.mc.memory import check_memory, peak_bytes
from cloudct.mc.render import single_cloud_medium
from cloudct.mc.scene import Scene
from cloudct.medium import load_medium
from cloudct.optics import DEFAULT_OPTICS, OPTICS, with_optics, with_phase_truncation


def add_backend_option(p: argparse.ArgumentParser, workers: bool = False) -> None:
    """``--backend cpu|cuda|auto`` (default auto: the GPU where one is found)."""
    p.add_argument("--backend", choices=BACKENDS, default="auto",
                   help="where the photons are traced: cuda (a GPU), cpu, or auto (the "
                   "default: the GPU where numba-cuda finds one, else the CPU)"
                   + ("; with --workers/--scheduler, on the workers" if workers else ""))


def chosen_backend(args: argparse.Namespace) -> str:
    """``"cpu"`` or ``"cuda"`` for ``--backend`` (:func:`cloudct.mc.backend.resolve_backend`):
    with ``auto``, the GPU where one is found, saying so in one line on stderr, else the CPU
    (silently: the usual case, whose messages stay one line); a back end asked for that
    cannot run is a one-line error."""
    if args.backend == "auto":
        if cuda_unavailable_reason() is not None:
            return "cpu"
        print(f"cloudct {args.command}: running on {device_description('cuda')}",
              file=sys.stderr)
        return "cuda"
    try:
        return resolve_backend(args.backend)
    except RuntimeError as err:
        raise ValueError(str(err)) from None


def add_distributed_options(p: argparse.ArgumentParser) -> None:
    """``--backend``, ``--workers`` and ``--scheduler`` (see docs/distributed.md)."""
    add_backend_option(p, workers=True)
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, metavar="N",
                       help="trace on a local Dask cluster of N worker processes (one per "
                       "GPU with --backend cuda); needs cloudct[distributed]")
    where.add_argument("--scheduler", metavar="ADDRESS",
                       help="trace on the Dask cluster of this scheduler (tcp://host:port or "
                       "a scheduler file)")


def add_optics_option(p: argparse.ArgumentParser, default: str = "") -> None:
    """``--optics hg|mie``: the cloud optics of the bundled cloud or a microphysical medium
    (``default``: what the help says None means, when it is not the documented default)."""
    p.add_argument(
        "--optics", choices=OPTICS, default=None,
        help="cloud optics of the bundled cloud or of a microphysical medium (lwc, reff): "
        "'hg' (the seed paper's: Mie extinction, Henyey-Greenstein g 0.85, cloud albedo "
        "0.99) or 'mie' (Mie albedos and phase functions); an optical medium keeps its own. "
        + (default or f"Default: a medium's recorded choice, else {DEFAULT_OPTICS!r}"),
    )


def add_phase_truncation_option(p: argparse.ArgumentParser, what: str, default: str) -> None:
    """``--phase-truncation DEGREES``: Mie phase functions cut flat within that angle of the
    forward direction for the kernels; ``what`` says of which medium, ``default`` what
    happens without the option (cloudct.optics)."""
    p.add_argument(
        "--phase-truncation", type=float, metavar="DEGREES",
        help=f"cut the forward diffraction peak of {what}'s Mie phase functions flat at this "
        "angle, the extinction and albedo delta-scaled (faster, HG-like noise; a bias of the "
        "order of the angle in the images' detail: docs/benchmarks.md, 'Mie optics'); 0 "
        f"keeps the full peak. Default: {default}",
    )


def truncated_as_asked(medium: xr.Dataset, degrees: float | None) -> xr.Dataset:
    """``medium`` with ``--phase-truncation`` applied (None: as it is)."""
    return medium if degrees is None else with_phase_truncation(medium, degrees)


def medium_from_options(path: str | None, optics: str | None) -> xr.Dataset:
    """The medium file at ``path`` (None: the bundled single cloud) with the cloud
    ``optics`` chosen (:func:`cloudct.optics.with_optics`)."""
    if path is None:
        return single_cloud_medium(optics or DEFAULT_OPTICS)
    return with_optics(load_medium(path), optics)


def measured_optics(measurements: xr.Dataset, optics: str | None) -> str | None:
    """``optics`` if given, else the optics the measurements record (None if none known)."""
    recorded = measurements.attrs.get("optics")
    return optics if optics is not None else (recorded if recorded in OPTICS else None)


def say_memory(what: str, medium: xr.Dataset, scene: Scene, batches: int,
               gradient: bool, way_out: str = "a coarser grid") -> None:
    """Print the memory ``what`` needs at its peak (:mod:`cloudct.mc.memory`: its per-batch
    images, or gradients where ``gradient``), or refuse in one line, with ``way_out``,
    where it cannot fit."""
    pixels = sum(c.nrows * c.ncols for c in scene.cameras)
    voxels = medium.sizes["x"] * medium.sizes["y"] * medium.sizes["z"]
    need = peak_bytes(voxels, pixels, batches, gradient)
    print(check_memory(what, need, way_out))

