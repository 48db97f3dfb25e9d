"""`jsve table1 --ref REF --original EST... --masked EST... -o DIR`: the seed's Table I, masked vs original.

Reads and associates the trajectories as `jsve ape` does (jsve.io._trajectories: evo's file_interface; by
index for kitti, by timestamps for tum / euroc), scores them with jsve.masks._table_one in float64 (equal to
evo_ape to 1e-6) and writes table1.md, table1.csv, per_run.csv, the APE-over-time, histogram and density
plots, and the aligned estimates as KITTI pose files into DIR. Prints the Markdown table; exit code 2 when
a file cannot be used.
"""

from __future__ import annotations

import argparse

from jsve.cli import _common as common

HELP = "Table I: APE statistics of masked vs original estimates, with plots and aligned poses"


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "table1",
        help=HELP,
        description=(
            "APE (translation part, metres) of two sets of estimates against one reference, side by side: "
            "rmse, mean, median, std, min, max, sse (mean over each set's runs), as Markdown and CSV, with "
            "the APE over time, its histogram and its density (KDE), and the aligned estimates as KITTI "
            "pose files."
        ),
    )
    parser.add_argument("--ref", required=True, metavar="REF", help="reference (ground-truth) trajectory")
    parser.add_argument(
        "--original", required=True, nargs="+", metavar="EST", help="estimates of the original system"
    )
    parser.add_argument("--masked", required=True, nargs="+", metavar="EST", help="estimates with masks")
    common.add_align_option(
        parser,
        help="se3 (evo_ape --align), sim3 (--align --correct_scale), posyaw, origin, none (default: se3)",
    )
    common.add_trajectory_options(parser, default_format="kitti")
    parser.add_argument(
        "--times",
        metavar="FILE",
        help="kitti: frame times in seconds, one per reference pose (KITTI's times.txt), for the time axis "
        "(default: none, the pose index)",
    )
    common.add_output_option(parser, metavar="DIR", required=True, help="folder for the report")
    parser.add_argument(
        "--plot-formats", default="png,svg", metavar="LIST", help="comma-separated: png, svg (default both)"
    )
    parser.add_argument("--no-plots", action="store_true", help="write the tables and poses only")
    parser.set_defaults(func=run)


@common.guarded("table1")
def run(args: argparse.Namespace) -> int:
    import jax

    from jsve.io._trajectories import read_pose_pairs
    from jsve.masks import _table_one as table_one

    formats = tuple(f.strip() for f in args.plot_formats.split(",") if f.strip())
    bad = [f for f in formats if f not in table_one.PLOT_FORMATS]
    if bad or not formats:
        return common.fail("table1", f"--plot-formats must list png and/or svg, got {args.plot_formats!r}")
    try:
        n_first = common.n_first(args.n_to_align)
    except ValueError as error:
        return common.fail("table1", error)
    if args.times and args.format != "kitti":
        return common.fail("table1", "--times applies to --format kitti (tum and euroc carry stamps)")
    try:
        pairs = read_pose_pairs(
            args.ref,
            args.original + args.masked,
            args.format,
            t_max_diff=args.t_max_diff,
            kitti_times=args.times,
        )
    except ValueError as error:  # TrajectoryFileError is a ValueError: a file that cannot be used
        return common.fail("table1", error)
    n_original = len(args.original)
    groups = {"original": pairs[:n_original], "masked": pairs[n_original:]}

    with jax.enable_x64(True):  # evo computes in float64; so do we, to match it to 1e-6
        table = table_one.table_one(groups, align=args.align, n_first=n_first)
    from jsve.io import _atomic as atomic

    with atomic.all_or_nothing():  # every table, figure and pose file, or none
        table_one.write_report(table, args.output, formats=formats, plots=not args.no_plots)
    print(table_one.to_markdown(table), end="")
    return 0
