"""The ``cloudct`` command line: one subcommand per everyday job.

The command line is the top layer (docs/architecture.md): each module of this package holds
the subcommands of one job and registers them with a ``register_cli(subparsers)`` function;
the library below never imports it.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

from cloudct.output_files import WriteError

#: Modules that contribute subcommands, in the order ``--help`` lists them.
COMMAND_MODULES = (
    "cloudct.cli.media",
    "cloudct.cli.render",
    "cloudct.cli.synth",
    "cloudct.cli.carve",
    "cloudct.cli.retrieve",
    "cloudct.cli.cache",
    "cloudct.cli.info",
)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the ``cloudct`` command with every subcommand."""
    from cloudct import __version__

    parser = argparse.ArgumentParser(
        prog="cloudct",
        description="3D cloud tomography by differentiable Monte Carlo radiative transfer.",
    )
    parser.add_argument("--version", action="version", version=f"cloudct {__version__}")
    subparsers = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMAND_MODULES:
        importlib.import_module(name).register_cli(subparsers)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``cloudct`` console command."""
    log = logging.getLogger("cloudct")  # what a run decides on its own, one line each
    if not log.handlers:
        log.addHandler(logging.StreamHandler(sys.stderr))
        log.setLevel(logging.INFO)
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)  # for a command to repeat
    if args.command is None:
        parser.print_help()
        return 0
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError, FileExistsError, WriteError) as err:
        print(f"cloudct {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
