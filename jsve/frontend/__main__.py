"""`python -m jsve.frontend --include`: print the header's directory for `-I`."""

from __future__ import annotations

import argparse
import sys

from . import get_include, header_path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m jsve.frontend", description="Locate jsve_log.hpp, the C++ writer of log format v3."
    )
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--include", action="store_true", help="print the directory to pass to -I")
    group.add_argument("--header", action="store_true", help="print the path of jsve_log.hpp")
    args = parser.parse_args(argv)
    sys.stdout.write((get_include() if args.include else header_path()) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
