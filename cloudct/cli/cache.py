"""``cloudct cache``: where the compiled kernels are cached, and clearing them."""

from __future__ import annotations

import argparse

from cloudct.jit_cache import cache_root, clear_kernel_cache, folder_size, kernel_cache_dir


def _cli_cache(args: argparse.Namespace) -> int:
    """``cloudct cache [--clear]``."""
    if args.clear:
        freed = clear_kernel_cache()
        print(f"cleared {cache_root() / 'kernels'} ({freed / 2**20:.1f} MiB)")
        return 0
    folder = kernel_cache_dir()
    print(f"compiled kernels of this cloudct: {folder} "
          f"({folder_size(folder) / 2**20:.1f} MiB; all copies: "
          f"{folder_size(cache_root() / 'kernels') / 2**20:.1f} MiB)")
    return 0


def register_cli(subparsers: argparse._SubParsersAction) -> None:
    """Add ``cloudct cache``."""
    p = subparsers.add_parser(
        "cache",
        help="show (or --clear) the on-disk cache of compiled CPU and GPU kernels",
        description="cloudct compiles its kernels once per machine and keeps them in "
        "$CLOUDCT_CACHE_DIR/kernels (default ~/.cache/cloudct/kernels). A change to the "
        "source of any routine a kernel calls recompiles it on its next use; --clear "
        "deletes every cached kernel (the next run compiles them again).",
    )
    p.add_argument("--clear", action="store_true", help="delete the cached kernels")
    p.set_defaults(func=_cli_cache)
