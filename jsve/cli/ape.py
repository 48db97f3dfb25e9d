"""`jsve ape REF EST [EST ...]`: absolute pose error of many estimates against one reference, in one call.

An evo_ape-like command that scores every estimate in a single batched JAX computation (float64, equal to
evo to 1e-6): files are read with evo's file_interface and associated by timestamps with evo's
associate_trajectories (tum, euroc) or by index (kitti), padded to the longest (jsve.io._trajectories),
aligned and scored by jsve.core._pose_error.batched_pose_error, as Table I does.
Prints one row per estimate (APE translation part, metres, with failed and failure_reason) or JSON; exit
code 2 when a file cannot be used.
"""

from __future__ import annotations

import argparse
import json

from jsve.cli import _common as common

HELP = "absolute pose error of many estimates against one reference (evo_ape-like, batched)"

TABLE_COLUMNS = ("rmse", "mean", "median", "std", "min", "max", "sse", "count", "failed", "failure_reason")
"""The columns printed after `estimate` (a failed run's statistics are NaN; failure_reason says why)."""


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "ape",
        help=HELP,
        description=(
            "Absolute pose error (translation part, metres) of each EST against REF, aligned with --align "
            "and scored in one batched computation. Statistics as evo defines them: rmse, mean, median, std "
            "(population), min, max, sse, count."
        ),
    )
    parser.add_argument("ref", metavar="REF", help="reference (ground-truth) trajectory file")
    parser.add_argument("est", metavar="EST", nargs="+", help="estimated trajectory file(s)")
    common.add_align_option(
        parser,
        help="alignment: se3, sim3 (with scale), posyaw (yaw + translation), origin (first pose), none "
        "(default: se3)",
    )
    common.add_trajectory_options(parser, default_format="tum")
    parser.add_argument(
        "--json", action="store_true", help="print JSON (a list of objects) instead of a table"
    )
    parser.add_argument(
        "-o", "--output", metavar="TABLE.csv", help="also write the per-estimate table as CSV"
    )
    parser.set_defaults(func=run)


@common.guarded("ape")
def run(args: argparse.Namespace) -> int:
    import jax
    import pandas as pd

    from jsve.core._pose_error import batched_pose_error
    from jsve.evaluation._aggregate import per_run_table
    from jsve.io import _atomic as atomic
    from jsve.io._trajectories import read_pose_pairs, stack_pose_pairs

    try:
        n_first = common.n_first(args.n_to_align)
        pairs = read_pose_pairs(args.ref, args.est, args.format, t_max_diff=args.t_max_diff)
    except ValueError as error:  # TrajectoryFileError is a ValueError: a file that cannot be used
        return common.fail("ape", error)

    previous = jax.config.jax_enable_x64
    jax.config.update("jax_enable_x64", True)  # evo computes in float64; so do we, to match it to 1e-6
    try:
        errors, _ = batched_pose_error(*stack_pose_pairs(pairs), align=args.align, n_first=n_first)
        table = per_run_table(errors, pd.DataFrame({"estimate": list(args.est)}))
    finally:
        jax.config.update("jax_enable_x64", previous)

    if args.output:
        atomic.write_text(args.output, table.to_csv(index=False))  # CSV whatever the suffix
    shown = table[["estimate", *TABLE_COLUMNS]]
    if args.json:
        records = shown.to_dict(orient="records")
        print(json.dumps([{k: _plain(v) for k, v in r.items()} for r in records], indent=2))
    else:
        print(shown.to_string(index=False, float_format=lambda v: f"{v:.6f}"))
    return 0


def _plain(value):
    """A JSON-ready Python scalar (NaN becomes null)."""
    if hasattr(value, "item"):
        value = value.item()
    if isinstance(value, float) and value != value:
        return None
    return value
