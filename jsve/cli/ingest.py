"""`jsve ingest`: validate a folder of format-v1 tracking logs and consolidate them into one Parquet file.

    jsve ingest logs/ -o study.parquet --on-error quarantine --gt V101_GT.txt --gt-format euroc

A thin layer over jsve.io._parquet.ingest; docs/log-format.md describes the format, the errors and the output.
Exit status: 0 on success (quarantined logs are listed in the summary and the report), 2 when a log is
malformed with --on-error raise, or when there are no logs.
"""

from __future__ import annotations

import argparse
import os

from jsve.cli import _common as common

HELP = "validate tracking logs and consolidate them into one Parquet file"

PARQUET_PER_CSV_BYTE = 0.33
"""Bytes of the Parquet file per byte of plain-text log, on the generous side (simulated logs with
ground truth come to less), so that the size announced before writing is not too low; a .csv.gz log
counts one for one."""


def parquet_size(paths: list[str]) -> tuple[float, str]:
    """(estimated bytes of the Parquet file of these logs, how it was estimated)."""
    import os

    plain = gz = 0
    for path in paths:
        size = os.path.getsize(path)
        if path.lower().endswith((".gz", ".gz.partial")):
            gz += size
        else:
            plain += size
    total = PARQUET_PER_CSV_BYTE * plain + gz
    text = common.format_bytes(plain + gz)
    return total, f"{common.plural(len(paths), 'log')}, {text} of text x ~{PARQUET_PER_CSV_BYTE:g}"


def register(subparsers) -> None:
    """Add the `ingest` subcommand to the `jsve` parser."""
    p = subparsers.add_parser(
        "ingest",
        help=HELP,
        description=(
            "Read every format-v1 tracking log under LOGDIR (*.csv, recursively; *.csv.partial files are "
            "reported as incomplete), validate it strictly, optionally associate ground truth, and write "
            "one Parquet file with all frames and the per-run metadata. Says the estimated size of the "
            "file before writing it. See docs/log-format.md."
        ),
    )
    p.add_argument(
        "logdir", metavar="LOGDIR", help="folder of logs (recursive), a single log, or a glob pattern"
    )
    common.add_output_option(p, metavar="OUT.parquet", required=True, help="the Parquet file to write")
    common.add_on_error_option(p)
    p.add_argument(
        "--quarantine-report",
        metavar="PATH",
        help="CSV report of quarantined logs (default: OUT.quarantine.csv beside the output)",
    )
    common.add_workers_option(p, "threads reading the logs (processes where --gt associates ground truth)")
    common.add_progress_option(p)
    common.add_yes_option(p)
    gt = p.add_argument_group("ground truth (associated with logs that carry none)")
    gt.add_argument(
        "--gt",
        metavar="[SEQ=]FILE",
        action="append",
        help="ground-truth trajectory file for every log, or SEQ=FILE for the logs whose `sequence` is SEQ "
        "(repeatable: a study of several sequences) (default: none)",
    )
    gt.add_argument(
        "--gt-format",
        choices=common.LibraryNames("jsve.io._groundtruth", "GT_FORMATS"),
        default="euroc",
        metavar="FORMAT",
        help="format of --gt: %(choices)s",
    )
    gt.add_argument(
        "--kitti-times",
        metavar="FILE",
        help="KITTI times file (s) (default: none, associate by frame index)",
    )
    gap = gt.add_argument(
        "--gt-max-gap-ms",
        type=float,
        metavar="MS",
        help="largest ground-truth sample spacing to interpolate across, ms (default: %(gap)s)",
    )
    gap.gap = common.LibraryValue("jsve.io._groundtruth", "DEFAULT_MAX_GAP_NS", scale=1e-6)
    gt.add_argument(
        "--no-interpolate", action="store_true", help="take the nearer ground-truth sample, not interpolate"
    )
    p.set_defaults(func=run, _parser=p)


def ground_truth_files(values: list[str]) -> dict[str | None, str]:
    """--gt values as {sequence: file}; one plain FILE (for every log) is {None: FILE}.

    Raises:
        ValueError: a plain FILE beside others, or a sequence named twice.
    """
    files: dict[str | None, str] = {}
    for value in values:
        sequence, sep, path = value.partition("=")
        key = sequence if sep and sequence and os.sep not in sequence else None
        path = path if key is not None else value
        if key in files:
            raise ValueError(
                f"{value!r}: " + (f"sequence {key} given twice" if key else "more than one --gt FILE")
            )
        files[key] = path
    if None in files and len(files) > 1:
        raise ValueError("give either one --gt FILE for every log or --gt SEQ=FILE per sequence, not both")
    return files


@common.guarded("ingest")
def run(args: argparse.Namespace) -> int:
    """Run `jsve ingest`; returns the exit status."""
    from jsve.io import _atomic as atomic
    from jsve.io._groundtruth import DEFAULT_MAX_GAP_NS, GroundTruth
    from jsve.io._ingest import check_ground_truth, find_logs
    from jsve.io._parquet import ingest

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
            files = ground_truth_files(args.gt)
            max_gap_ns = DEFAULT_MAX_GAP_NS if args.gt_max_gap_ms is None else round(args.gt_max_gap_ms * 1e6)
            gt_of = {
                sequence: GroundTruth(
                    path,
                    args.gt_format,
                    kitti_times=args.kitti_times,
                    max_gap_ns=int(max_gap_ns),
                    interpolate=not args.no_interpolate,
                )
                for sequence, path in files.items()
            }
            ground_truth = gt_of[None] if None in gt_of else gt_of
            check_ground_truth(ground_truth)  # the --gt files' own errors, before any log is read
    except ValueError as e:  # LogFormatError, TrajectoryFileError: the file, its line
        return common.fail("ingest", f"--gt: {e}")
    try:
        paths = find_logs(args.logdir)
    except FileNotFoundError as e:
        return common.fail("ingest", e)
    if paths:  # none: ingest says so, naming LOGDIR
        total, detail = parquet_size(paths)
        stop = common.announce_size("ingest", args.output, total, detail, yes=args.yes)
        if stop is not None:
            return stop
    try:
        with atomic.all_or_nothing():  # the Parquet file and its quarantine report, or neither
            summary = ingest(
                paths or args.logdir,
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
