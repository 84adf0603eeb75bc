"""Command-line options shared by several commands."""

from __future__ import annotations

import argparse


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
