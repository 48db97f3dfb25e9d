"""`jsve mask-logs LOG... --mots FILE | --png DIR -o OUT`: tracking logs without their dynamic keypoints.

For each LOG, reads its keypoint side file (`<log>.keypoints.csv`, docs/masks.md), removes the keypoints
that Algorithm 1 puts on a dynamic object of the masks, and writes the log with n_extracted, n_inliers
and bin_0..bin_63 recomputed to OUT/<log name>, so that SVE and replay can be evaluated with and without
dynamic features. A thin layer over jsve.masks._masks.apply_masks. Exit code 2 when a file cannot be used
or written (then no masked log is written), or when two LOGs share a file name.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from jsve.cli import _common as common

HELP = "remove keypoints on dynamic objects (KITTI MOTS / PNG masks) from logs with keypoint files"


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "mask-logs",
        help=HELP,
        description=(
            "Apply dynamic-object masks to tracking logs through their keypoint side files "
            "(<log>.keypoints.csv): a keypoint is removed when the mask is set at any of its four integer "
            "neighbours (Masked ORB-SLAM3, Algorithm 1); the counts and SVE bins are recomputed over the "
            "rest and the masked logs written to OUT."
        ),
    )
    parser.add_argument("logs", metavar="LOG", nargs="+", help="format-v1 tracking logs")
    source = parser.add_mutually_exclusive_group(required=True)
    source.add_argument(
        "--mots",
        metavar="FILE",
        help="KITTI MOTS instances_txt file of the sequence (this or --png required)",
    )
    source.add_argument(
        "--png",
        metavar="DIR",
        help="folder of one mask PNG per frame, frame number in the name (this or --mots required)",
    )
    parser.add_argument(
        "--classes",
        default=None,
        metavar="LIST",
        help="class ids to mask, comma-separated; add 10 for MOTS ignore regions. With --png, LIST reads "
        "the PNGs as MOTS instance maps (default: --mots 1,2 = car, pedestrian; --png any non-zero pixel)",
    )
    parser.add_argument(
        "--key",
        choices=("frame", "t_ns"),
        default="frame",
        help="how a frame finds its mask: frame index (KITTI) or image stamp (EuRoC file names); "
        "default frame",
    )
    parser.add_argument(
        "--missing-empty", action="store_true", help="--png: a frame without a PNG has no mask"
    )
    common.add_output_option(parser, metavar="OUT", required=True, help="folder for the masked logs")
    parser.add_argument(
        "--no-verify", action="store_true", help="do not check that the keypoints reproduce the log's counts"
    )
    parser.add_argument(
        "--no-verify-bins", action="store_true", help="check n_extracted and n_inliers but not the bins"
    )
    parser.set_defaults(func=run)


@common.guarded("mask-logs")
def run(args: argparse.Namespace) -> int:
    from jsve.io import _atomic as atomic
    from jsve.io._keypoints import keypoints_path, read_keypoints
    from jsve.io._logs import LogFormatError, read_log, write_log
    from jsve.masks import _masks as masks

    try:
        classes = None if args.classes is None else [int(c) for c in args.classes.split(",") if c.strip()]
        if args.mots:
            source = masks.MotsMasks(args.mots, classes or masks.DYNAMIC_CLASSES)
        else:
            source = masks.PngMasks(args.png, classes, missing="empty" if args.missing_empty else "error")
    except ValueError as error:  # LogFormatError is a ValueError too
        return common.fail("mask-logs", error)
    except OSError as error:
        return common.fail("mask-logs", f"cannot read the masks: {error}")

    out = Path(args.output)
    # Each log is written to OUT/<its file name>: two inputs of one name would overwrite each other.
    targets: dict[str, str] = {}
    for path in args.logs:
        name = Path(path).name
        if name in targets:
            return common.fail(
                "mask-logs",
                f"{targets[name]} and {path} would both be written to {out / name}; "
                "mask logs of the same file name into different folders (one run each)",
            )
        targets[name] = path
    lines = []
    try:
        # Every masked log, or none: the error leaves the block (a return inside it would end the
        # block normally and commit the logs written before the bad one).
        with atomic.all_or_nothing():
            for path in args.logs:
                run_log = read_log(path)
                keypoints = read_keypoints(keypoints_path(path))
                result = masks.apply_masks(
                    run_log,
                    keypoints,
                    source,
                    key=args.key,
                    verify=not args.no_verify,
                    verify_bins=not args.no_verify_bins,
                )
                target = write_log(result.log, out / Path(path).name)
                n_kp = len(keypoints.keypoints)
                share = result.removed.sum() / n_kp if n_kp else 0.0
                lines.append(
                    f"{path} -> {target}: removed {int(result.removed.sum())} of {n_kp} keypoints "
                    f"({share:.1%}) over {len(run_log.frames)} frames"
                )
    except (LogFormatError, ValueError, OSError) as error:
        return common.fail("mask-logs", error)
    print("\n".join(lines))
    return 0
