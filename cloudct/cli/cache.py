"""``cloudct cache``: where the compiled kernels are cached, clearing them, and filling
them ahead of a run (``--warm``)."""

from __future__ import annotations

import argparse
import time

from cloudct.cli.options import add_backend_option, add_optics_option, chosen_backend
from cloudct.jit_cache import cache_root, clear_kernel_cache, folder_size, kernel_cache_dir
from cloudct.optics import DEFAULT_OPTICS
from cloudct.retrieval.warm_up import TASKS, warm_up


def _cli_cache(args: argparse.Namespace) -> int:
    """``cloudct cache [--clear | --warm [TASK ...]]``."""
    if args.clear:
        freed = clear_kernel_cache()
        print(f"cleared {cache_root() / 'kernels'} ({freed / 2**20:.1f} MiB)")
        return 0
    if args.warm is not None:
        backend = chosen_backend(args)
        start = time.perf_counter()
        seconds = warm_up(args.warm or TASKS, backend=backend,
                          optics=args.optics or DEFAULT_OPTICS, jobs=args.jobs)
        for name, s in seconds.items():
            print(f"{name}: {s:.1f} s compiling (or loading)")
        print(f"the kernels of {len(seconds)} tasks are in {kernel_cache_dir()} "
              f"({backend}, {time.perf_counter() - start:.0f} s)")
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
        help="show, fill (--warm) or --clear the on-disk cache of compiled CPU and GPU kernels",
        description="cloudct compiles its kernels once per machine and keeps them in "
        "$CLOUDCT_CACHE_DIR/kernels (default ~/.cache/cloudct/kernels). A change to the "
        "source of any routine a kernel calls recompiles it on its next use; --clear "
        "deletes every cached kernel (the next run compiles them again); --warm compiles "
        "them now, several at once, so that no run spends its first minutes compiling "
        "(cloudct retrieve and demo compile their own ahead, while they load and carve).",
    )
    mode = p.add_mutually_exclusive_group()
    mode.add_argument("--clear", action="store_true", help="delete the cached kernels")
    mode.add_argument("--warm", nargs="*", choices=TASKS, metavar="TASK",
                      help="compile the kernels of these tasks (default: all of "
                      f"{', '.join(TASKS)})")
    p.add_argument("--jobs", type=int,
                   help="processes compiling at once with --warm (default: one per task, at "
                   "most the CPUs available)")
    add_backend_option(p)
    add_optics_option(p)
    p.set_defaults(func=_cli_cache)
