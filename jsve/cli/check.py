"""`jsve check LOGS`: identity replay: replay the rule each log's front-end ran and compare states.

Prints one line per flagged log and a summary; with -o writes the per-log table (CSV). Exit status 1
when any log is flagged (its replayed states agree with the logged ones on fewer than 99 % of frames).
"""

from __future__ import annotations

import sys
from pathlib import Path

from jsve.cli import _common as common

HELP = "identity replay: does replaying each log's own rule give back its logged states?"


def register(sub) -> None:
    p = sub.add_parser("check", help=HELP, description=HELP)
    p.add_argument("logs", metavar="LOGS", help="folder of logs, a log, or a Parquet file from `jsve ingest`")
    rule = p.add_argument(
        "--rule",
        metavar="PRESET",
        help="the rule (%(presets)s) of logs whose metadata names none (default: such a log is an error)",
    )
    rule.presets = common.LibraryNames("jsve.core._rules", "PRESETS")
    common.add_on_error_option(p)
    common.add_output_option(
        p, metavar="CSV", help="write the per-log table here (default: print the flagged logs only)"
    )
    common.add_workers_option(p)
    common.add_progress_option(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from jsve._jax_cache import enable_compilation_cache
    from jsve.evaluation._identity import IDENTITY_THRESHOLD, identity_table
    from jsve.io import _atomic as atomic

    enable_compilation_cache()  # a second run compiles nothing

    try:
        runs = common.load_runs(
            "check", args.logs, on_error=args.on_error, workers=args.workers, progress=not args.no_progress
        )
        if not runs:
            return common.fail("check", f"no valid logs in {args.logs}")
        table = identity_table(runs, rule=args.rule)
    except (ValueError, OSError) as err:
        return common.fail("check", err)
    if args.output:
        atomic.write_table(table, Path(args.output))
    flagged = table[table["flagged"]]
    for row in flagged.itertuples():
        print(
            f"{row.source}: replayed states agree on {100 * row.agreement:.2f} % of frames "
            f"(first mismatch at frame {row.first_mismatch}; rule {row.rule}, {row.switch_model})"
        )
    print(
        f"jsve check: {len(table)} logs, {len(flagged)} flagged (below {100 * IDENTITY_THRESHOLD:g} %); "
        f"agreement min {100 * table['agreement'].min():.2f} %, mean {100 * table['agreement'].mean():.2f} %",
        file=sys.stderr if flagged.empty else sys.stdout,
    )
    return 1 if len(flagged) else 0
