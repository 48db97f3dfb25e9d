"""`jsve table1 --ref REF --original EST... --masked EST... -o DIR`: the seed's Table I, masked vs original.

Reads and associates the trajectories as `jsve ape` does (evo's file_interface; by index for kitti, by
timestamps for tum / euroc), scores them with jsve.masks._table_one in float64 (equal to evo_ape to 1e-6) and
writes table1.md, table1.csv, per_run.csv, the APE-over-time, histogram and density plots, and the
aligned estimates as KITTI pose files into DIR. Prints the Markdown table; exit code 2 when a file
cannot be used.
"""

from __future__ import annotations

import argparse
import sys

from .ape import ALIGN_CHOICES, FORMATS, InputError, _associate, _read


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "table1",
        help="Table I: APE statistics of masked vs original estimates, with plots and aligned poses",
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
    parser.add_argument("--format", choices=FORMATS, default="kitti", help="file format (default: kitti)")
    parser.add_argument(
        "--align",
        choices=ALIGN_CHOICES,
        default="se3",
        help="se3 (evo_ape --align), sim3 (--align --correct_scale), posyaw, origin, none (default: se3)",
    )
    parser.add_argument(
        "--n-to-align", type=int, default=-1, metavar="N", help="align on the first N poses (default -1: all)"
    )
    parser.add_argument(
        "--t-max-diff",
        type=float,
        default=0.01,
        metavar="S",
        help="largest time difference in seconds for associating poses (tum, euroc; default 0.01)",
    )
    parser.add_argument(
        "--times",
        metavar="FILE",
        help="kitti: frame times in seconds, one per reference pose (KITTI's times.txt), for the time axis",
    )
    parser.add_argument("-o", "--output", required=True, metavar="DIR", help="folder for the report")
    parser.add_argument(
        "--plot-formats", default="png,svg", metavar="LIST", help="comma-separated: png, svg (default both)"
    )
    parser.add_argument("--no-plots", action="store_true", help="write the tables and poses only")
    parser.set_defaults(func=run)


def _times(path: str, n_poses: int):
    import numpy as np

    try:
        times = np.loadtxt(path, dtype=np.float64, ndmin=1)
    except (OSError, ValueError) as error:
        raise InputError(f"cannot read {path} as KITTI times (seconds, one per line): {error}") from error
    if times.shape != (n_poses,):
        raise InputError(f"{path} has {times.size} times but the reference has {n_poses} poses")
    return times - times[0]


def _pairs(args, paths: list[str], ref, times):
    import numpy as np

    from jsve.masks._table_one import PosePair

    pairs = []
    for path in paths:
        ref_i, est_i = _associate(ref, _read(path, args.format), args.ref, path, args.format, args.t_max_diff)
        if args.format == "kitti":
            t = times
        else:
            t = np.asarray(ref_i.timestamps, np.float64) - float(ref.timestamps[0])
        pairs.append(PosePair(path, np.stack(ref_i.poses_se3), np.stack(est_i.poses_se3), t))
    return pairs


def run(args: argparse.Namespace) -> int:
    import jax

    from jsve.masks import _table_one as tablei

    formats = tuple(f.strip() for f in args.plot_formats.split(",") if f.strip())
    bad = [f for f in formats if f not in tablei.PLOT_FORMATS]
    if bad or not formats:
        print(
            f"jsve table1: --plot-formats must list png and/or svg, got {args.plot_formats!r}",
            file=sys.stderr,
        )
        return 2
    if args.n_to_align == 0 or args.n_to_align < -1:
        print(
            f"jsve table1: --n-to-align must be positive or -1 (all), got {args.n_to_align}", file=sys.stderr
        )
        return 2
    if args.times and args.format != "kitti":
        print("jsve table1: --times applies to --format kitti (tum and euroc carry stamps)", file=sys.stderr)
        return 2
    n_first = None if args.n_to_align == -1 else args.n_to_align
    try:
        ref = _read(args.ref, args.format)
        times = _times(args.times, ref.num_poses) if args.times else None
        groups = {
            "original": _pairs(args, args.original, ref, times),
            "masked": _pairs(args, args.masked, ref, times),
        }
    except InputError as error:
        print(f"jsve table1: {error}", file=sys.stderr)
        return 2

    with jax.enable_x64(True):  # evo computes in float64; so do we, to match it to 1e-6
        table = tablei.table_one(groups, align=args.align, n_first=n_first)
    tablei.write_report(table, args.output, formats=formats, plots=not args.no_plots)
    print(tablei.to_markdown(table), end="")
    return 0
