"""Command-line options shared by several commands."""

from __future__ import annotations

import argparse

import xarray as xr

from cloudct.mc.render import single_cloud_medium
from cloudct.medium import load_medium
from cloudct.optics import DEFAULT_OPTICS, OPTICS, with_optics


def add_distributed_options(p: argparse.ArgumentParser) -> None:
    """``--backend``, ``--workers`` and ``--scheduler`` (see docs/distributed.md)."""
    p.add_argument("--backend", choices=("cpu", "cuda", "auto"), default="cpu",
                   help="compute back end (on the workers, with --workers/--scheduler)")
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
