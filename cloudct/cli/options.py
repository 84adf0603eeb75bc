"""Command-line options shared by several commands."""

from __future__ import annotations

import argparse
import sys

import xarray as xr

from cloudct.les import bundled_single_cloud
from cloudct.mc.backend import (
    BACKENDS,
    cuda_unavailable_reason,
    device_description,
    resolve_backend,
)
from cloudct.mc.memory import check_memory, peak_bytes
from cloudct.mc.render import single_cloud_medium
from cloudct.mc.scene import Scene
from cloudct.measurements import BAND, band_measurements, band_wavelengths, load_measurements
from cloudct.medium import is_microphysical, is_optical, load_medium
from cloudct.optics import DEFAULT_OPTICS, OPTICS, with_optics, with_phase_truncation
from cloudct.physics.mie import DEFAULT_WAVELENGTH

#: The cloud optics of ``--bands`` where neither the option nor the medium chooses: HG
#: optics have no droplet absorption, so their bands would differ only in extinction and air.
BAND_OPTICS = "mie"


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


def band_medium_from_options(path: str | None, optics: str | None) -> xr.Dataset:
    """The microphysical medium of ``--bands``: the file at ``path`` (None: the bundled
    single cloud's LWC and r_eff) with the cloud ``optics`` chosen: ``optics`` if given, else
    the medium's recorded choice, else :data:`BAND_OPTICS`. An optical medium is refused:
    its optics are one wavelength's."""
    medium = bundled_single_cloud() if path is None else load_medium(path)
    if is_optical(medium) or not is_microphysical(medium):
        raise ValueError(f"--bands needs a microphysical medium (lwc, reff); {path} is "
                         "optical, its optics are one wavelength's")
    return with_optics(medium, optics or medium.attrs.get("optics", BAND_OPTICS))


def add_bands_option(p: argparse.ArgumentParser, what: str) -> None:
    """``--bands W [W ...]``: ``what`` at several wavelengths [micron]."""
    p.add_argument(
        "--bands", type=float, nargs="+", metavar="MICRON",
        help=f"{what} in several bands (wavelengths in micron, increasing, e.g. 0.672 1.65 "
        "2.13), of a microphysical medium (default: the bundled single cloud's LWC and "
        "r_eff), into one file with a band dimension; band i (from the shortest) has seed "
        f"SEED + i. Cloud optics default to a medium's recorded choice, else {BAND_OPTICS!r}",
    )


def retrieval_measurements(path: str, command: str) -> xr.Dataset:
    """The measurement file at ``path`` as the extinction retrieval reads it (``cloudct
    carve``, ``retrieve``, ``report``): a file with several bands gives its band at 0.672
    micron (:data:`~cloudct.physics.mie.DEFAULT_WAVELENGTH`, the wavelength of the
    retrieval's optics; :func:`cloudct.measurements.band_measurements`), which is said in
    one line on stderr; a file without one is refused, naming its bands."""
    measurements = load_measurements(path)
    if BAND not in measurements.dims:
        return measurements
    held = ", ".join(f"{w:g}" for w in band_wavelengths(measurements))
    try:
        one = band_measurements(measurements, DEFAULT_WAVELENGTH)
    except ValueError as err:
        raise ValueError(f"measurement file {path}: {err}; the extinction retrieval works at "
                         f"{DEFAULT_WAVELENGTH:g} micron") from None
    print(f"cloudct {command}: {path} holds the bands {held} micron; the extinction retrieval "
          f"reads the {float(one.attrs['wavelength']):g} micron band", file=sys.stderr)
    return one


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

