"""The `jsve` command: a thin dispatcher over one module per subcommand.

Each module in this package named in SUBCOMMANDS defines `register(subparsers)`, which adds its
parser and sets `func=callable(args) -> int`. Modules are imported lazily by name so that a slow
import (JAX, OpenCV) only happens for the command that needs it.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys

SUBCOMMANDS: tuple[str, ...] = (
    "ingest",
    "sve",
    "evaluate",
    "ape",
    "frontend-include",
    "disturb",
    "measure",
    "table1",
    "masks",
    "simulate",
    "fit",
    "report",
    "demo",
)
"""Module names under jsve.cli, in the order `jsve --help` lists them."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jsve",
        description="Scene-visibility-based switching for VI-SLAM: replay, evaluate and fit switching rules.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details to stderr")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS:
        importlib.import_module(f"jsve.cli.{name.replace('-', '_')}").register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="jsve: %(levelname)s: %(message)s"
    )
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
