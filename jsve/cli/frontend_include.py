"""`jsve frontend-include`: print the directory of jsve_log.hpp, for a C++ compiler's `-I`."""

from __future__ import annotations

import argparse
import sys

HELP = "print the directory of the C++ log writer jsve_log.hpp (for -I)"


def register(subparsers: argparse._SubParsersAction) -> None:
    parser = subparsers.add_parser(
        "frontend-include",
        help=HELP,
        description="Print the directory holding jsve_log.hpp, the header-only C++17 writer of tracking "
        'log format v1, e.g. g++ -std=c++17 -I"$(jsve frontend-include)" ... (see docs/frontend.md).',
    )
    parser.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from jsve.frontend import get_include

    sys.stdout.write(get_include() + "\n")
    return 0
