"""`jsve ingest`: validate a folder of format-v1 tracking logs and consolidate them into one Parquet file.

    jsve ingest logs/ -o study.parquet --on-error quarantine --gt V101_GT.txt --gt-format euroc

A thin layer over jsve.io._ingest.ingest; docs/log-format.md describes the format, the errors and the output.
Exit status: 0 on success (quarantined logs are listed in the summary and the report), 2 when a log is
malformed with --on-error raise, or when there are no logs.
"""

from __future__ import annotations

import argparse

from jsve.cli import _common as common

HELP = "validate tracking logs and consolidate them into one Parquet file"


def register(subparsers) -> None:
    """Add the `ingest` subcommand to the `jsve` parser."""
    from jsve.io._groundtruth import DEFAULT_MAX_GAP_NS, GT_FORMATS

    p = subparsers.add_parser(
        "ingest",
        help=HELP,
        description=(
            "Read every format-v1 tracking log under LOGDIR (*.csv, recursively; *.csv.partial files are "
            "reported as incomplete), validate it strictly, optionally associate ground truth, and write "
            "one Parquet file with all frames and the per-run metadata. See docs/log-format.md."
        ),
    )
    p.add_argument(
        "logdir", metavar="LOGDIR", help="folder of logs (recursive), a single log, or a glob pattern"
    )
    p.add_argument("-o", "--output", required=True, metavar="OUT.parquet", help="the Parquet file to write")
    p.add_argument(
        "--on-error",
        choices=common.on_error_choices(),
        default="raise",
        help="raise: stop at the first bad log (exit 2); quarantine: set bad logs aside and report them "
        "(default: raise)",
    )
    p.add_argument(
        "--quarantine-report",
        metavar="PATH",
        help="CSV report of quarantined logs (default: OUT.quarantine.csv beside the output)",
    )
    p.add_argument("--workers", type=int, metavar="N", help="worker processes (default: all CPUs)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    gt = p.add_argument_group("ground truth (associated with logs that carry none)")
    gt.add_argument("--gt", metavar="FILE", help="ground-truth trajectory file")
    gt.add_argument(
        "--gt-format", choices=GT_FORMATS, default="euroc", help="format of --gt (default: euroc)"
    )
    gt.add_argument(
        "--kitti-times", metavar="FILE", help="KITTI times file (s); without it, associate by frame index"
    )
    gt.add_argument(
        "--gt-max-gap-ms",
        type=float,
        default=DEFAULT_MAX_GAP_NS / 1e6,
        metavar="MS",
        help="largest ground-truth sample spacing to interpolate across, ms (default: %(default)g)",
    )
    gt.add_argument("--no-interpolate", action="store_true", help="take the nearer ground-truth sample")
    p.set_defaults(func=run, _parser=p)


@common.guarded("ingest")
def run(args: argparse.Namespace) -> int:
    """Run `jsve ingest`; returns the exit status."""
    from jsve.io import _atomic as atomic
    from jsve.io._groundtruth import GroundTruth
    from jsve.io._ingest import check_ground_truth, ingest

    parser = args._parser
    if args.quarantine_report and args.on_error != "quarantine":
        parser.error("--quarantine-report needs --on-error quarantine")
    if args.gt is None and (args.kitti_times or args.no_interpolate):
        parser.error("--kitti-times and --no-interpolate need --gt")
    if args.kitti_times and args.gt_format != "kitti":
        parser.error("--kitti-times needs --gt-format kitti")
    if args.workers is not None and args.workers < 1:
        parser.error("--workers must be >= 1")
    ground_truth = None
    try:
        if args.gt is not None:
            ground_truth = GroundTruth(
                args.gt,
                args.gt_format,
                kitti_times=args.kitti_times,
                max_gap_ns=int(round(args.gt_max_gap_ms * 1e6)),
                interpolate=not args.no_interpolate,
            )
            check_ground_truth(ground_truth)  # the --gt file's own error, before any log is read
    except ValueError as e:  # LogFormatError, TrajectoryFileError: the file, its line
        return common.fail("ingest", f"--gt: {e}")
    try:
        with atomic.all_or_nothing():  # the Parquet file and its quarantine report, or neither
            summary = ingest(
                args.logdir,
                args.output,
                on_error=args.on_error,
                workers=args.workers,
                progress=not args.no_progress,
                ground_truth=ground_truth,
                quarantine_report=args.quarantine_report,
            )
    except (ValueError, FileNotFoundError) as e:  # LogFormatError is a ValueError
        return common.fail("ingest", e)
    print(summary.line())
    return 0
