"""`jsve sve LOG`: per-frame S_a, S_b, S_c and the seed's combinations of one log, as CSV.

    jsve sve logs/MH_04-blur-15-7.csv -o sve.csv

Columns: t_ns, then jsve.core._sve.sve_table's columns (docs/sve.md defines each one).
"""

from __future__ import annotations

import sys

from jsve.cli import _common as common

HELP = "per-frame SVE metrics and combinations of one log (CSV)"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "sve",
        help=HELP,
        description="Compute S_a (original and ORB-SLAM3 variants), S_b and S_c (clamped and unclamped) and "
        "the Eq.1 / Option 1 / Option 2 combinations for every frame of a format-v1 log.",
    )
    p.add_argument("log", metavar="LOG", help="a format-v1 tracking log")
    common.add_output_option(p, metavar="OUT.csv", help="write here (default: standard output)")
    p.set_defaults(func=run)


def run(args) -> int:
    import numpy as np
    import pandas as pd

    from jsve.core._sve import sve_table
    from jsve.io import _atomic as atomic
    from jsve.io._errors import LogFormatError
    from jsve.io._logs import read_log
    from jsve.io._schema import BIN_COLUMNS

    try:
        log = read_log(args.log)
    except (LogFormatError, OSError) as err:
        return common.fail("sve", err)
    f = log.frames
    columns = sve_table(
        f["n_extracted"].to_numpy(),
        f["n_inliers"].to_numpy(),
        f["n_frustum"].to_numpy(),
        f[list(BIN_COLUMNS)].to_numpy(),
        n_features=log.meta.get("n_features", 1000),
    )
    table = pd.DataFrame({"t_ns": f["t_ns"].to_numpy()} | {k: np.asarray(v) for k, v in columns.items()})
    if args.output:
        atomic.write_table(table, args.output, float_format="%.9g")
    else:
        try:
            table.to_csv(sys.stdout, index=False, float_format="%.9g")
        except BrokenPipeError:  # `jsve sve LOG | head` closes the pipe early: not an error
            sys.stderr.close()
    return 0
