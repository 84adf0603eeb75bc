"""``cloudct info``: what this installation runs on, for a bug report or a first check.

It prints the versions of cloudct and of the libraries it computes with, the CPU threads
numba uses, whether the CUDA back end can run here (the GPU's name, or the reason it
cannot), and where the compiled kernels are cached.
"""

from __future__ import annotations

import argparse
import platform
import sys
from importlib import metadata

from cloudct.jit_cache import cache_root, folder_size, kernel_cache_dir
from cloudct.mc.backend import cuda_unavailable_reason, device_description

#: Distributions whose versions ``cloudct info`` reports, in this order.
LIBRARIES = ("numpy", "numba", "numba-cuda", "scipy", "xarray", "netCDF4", "matplotlib",
             "miepython", "dask", "distributed")


def library_versions() -> dict[str, str]:
    """The installed version of each of :data:`LIBRARIES`, or ``"not installed"``."""
    versions = {}
    for name in LIBRARIES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions


def installation_report() -> list[tuple[str, str]]:
    """(label, value) lines describing this installation: versions, devices, caches."""
    from cloudct import __version__

    gpu_reason = cuda_unavailable_reason()
    kernels = kernel_cache_dir()
    return [
        ("cloudct", __version__),
        ("python", f"{platform.python_version()} ({sys.executable})"),
        *library_versions().items(),
        ("cpu back end", device_description("cpu")),
        ("cuda back end", device_description("cuda") if gpu_reason is None
         else f"unavailable: {gpu_reason}"),
        ("backend 'auto' runs on", "cuda" if gpu_reason is None else "cpu"),
        ("kernel cache", f"{kernels} ({folder_size(kernels) / 2**20:.1f} MiB; all copies "
                         f"under {cache_root() / 'kernels'})"),
    ]


def _cli_info(args: argparse.Namespace) -> int:
    """``cloudct info``."""
    lines = installation_report()
    width = max(len(label) for label, _ in lines)
    for label, value in lines:
        print(f"{label:<{width}}  {value}")
    return 0


def register_cli(subparsers: argparse._SubParsersAction) -> None:
    """Add ``cloudct info``."""
    p = subparsers.add_parser(
        "info",
        help="versions, the CPU and GPU back ends found here, and the kernel cache",
        description="Print what this cloudct installation runs on: the versions of cloudct "
        "and its libraries, the CPU threads, whether the CUDA back end can run (the GPU, or "
        "why not) and where the compiled kernels are cached. Paste it into bug reports.",
    )
    p.set_defaults(func=_cli_info)
