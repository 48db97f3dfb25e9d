"""The `jsve` command: a thin dispatcher over one module per subcommand.

Each subcommand NAME lives in the module jsve.cli.<NAME with '_' for '-'>, which defines

    HELP                  its one-line summary, for `jsve --help` and its own parser
    register(subparsers)  adds its parser, with `func=callable(args) -> int` as a default
    run(args)             the command itself, a thin layer over jsve's public functions

Subcommand modules import only the standard library and jsve.cli._common at top level; library code
(JAX, pandas, OpenCV, matplotlib, evo) is imported inside `run`, never by `register`: an option whose
choices come from the library takes them as `_common.LibraryNames`, read when a value is checked or a
help printed. `main` builds the full parser of the chosen subcommand only, so `jsve --help` lists every
subcommand without importing any library, and a command pays for the imports it needs (timings:
docs/performance.md, "CLI start-up"; tests/test_cli.py checks that building every parser imports no
library).
Every parser is a `_common.ArgumentParser`, whose help shows each option's default.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Iterable, Sequence

from jsve.cli import _common as common
from jsve.cli._common import use_all_cores as use_all_cores

SUBCOMMANDS: tuple[str, ...] = (
    "ingest",
    "sve",
    "evaluate",
    "check",
    "ape",
    "rpe",
    "frontend",
    "frontend-include",
    "disturb",
    "measure",
    "table1",
    "mask-logs",
    "simulate",
    "render",
    "fit",
    "tune",
    "report",
    "demo",
)
"""The subcommands, in the order `jsve --help` lists them."""


def _module(name: str):
    return importlib.import_module(f"jsve.cli.{name.replace('-', '_')}")


def build_parser(full: Iterable[str] | None = None) -> argparse.ArgumentParser:
    """The `jsve` parser.

    Arguments:
        full: the subcommands whose parser is built in full (their `register` runs); the others are
            listed by their HELP only. None: every subcommand in full.
    """
    parser = common.ArgumentParser(
        prog="jsve",
        description="Scene-visibility-based switching for VI-SLAM: replay, evaluate and fit switching rules.",
    )
    parser.add_argument("-v", "--verbose", action="store_true", help="log progress details to stderr")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", parser_class=common.ArgumentParser)
    full = set(SUBCOMMANDS if full is None else full)
    for name in SUBCOMMANDS:
        module = _module(name)
        if name in full:
            module.register(sub)
        else:
            sub.add_parser(name, help=module.HELP)
    return parser


def _command(argv: Sequence[str]) -> str | None:
    """The subcommand named on the command line: its first argument that is not an option (`jsve` itself
    takes no option with a value)."""
    return next((arg for arg in argv if not arg.startswith("-")), None)


def main(argv: Sequence[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else list(argv)
    command = _command(argv)
    parser = build_parser(full=[command] if command in SUBCOMMANDS else [])
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
