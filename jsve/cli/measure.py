"""`jsve measure DATASET... -o OUT`: per-frame visibility counts and SVE metrics measured on real frames.

A thin layer over jsve.image._measure.measure_datasets: every EuRoC dataset at or below each DATASET is
measured (ORB-SLAM3-style ORB, frame-to-frame verified inliers, frustum stand-in, SVE bins) in
parallel with a progress bar, and one table per dataset is written with its key (the dataset's path and
camera content, camera, stride and settings) beside it. A rerun keeps tables of an equal key; a table of
another key stops the command (one line, exit 2) unless --force, which measures it again.
"""

from __future__ import annotations

import argparse

from jsve.cli import _common as common

HELP = "measure per-frame visibility (ORB counts, inliers, SVE metrics) on EuRoC image folders"


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "measure",
        help=HELP,
        description=(
            "Measure every EuRoC dataset at or below each DATASET (e.g. the output of `jsve disturb`) and "
            "write one table per dataset to OUT/<DATASET name>/<relative path>.<format>: t_ns, n_extracted, "
            "n_inliers, n_frustum, bin_0..bin_63 and the SVE metrics of `jsve sve`. See docs/disturbances.md "
            "for what each count stands in for."
        ),
    )
    parser.add_argument(
        "datasets", metavar="DATASET", nargs="+", help="dataset folder(s) or folders of datasets"
    )
    common.add_output_option(parser, metavar="OUT", required=True, help="output folder for the tables")
    parser.add_argument("--format", choices=("csv", "parquet"), default="csv", help="table format")
    parser.add_argument("--camera", default="cam0", metavar="CAM", help="camera folder under mav0")
    parser.add_argument("--stride", type=int, default=1, metavar="N", help="measure every N-th frame")
    parser.add_argument(
        "--extractor",
        choices=("orbslam3", "opencv"),
        default="orbslam3",
        help="orbslam3: ORB-SLAM3's per-cell FAST 20/7 and quadtree; opencv: cv2.ORB_create plus a FAST-7 "
        "pass in empty cells",
    )
    parser.add_argument("--no-fallback", action="store_true", help="no FAST-7 retry (minThFAST)")
    parser.add_argument("--n-features", type=int, default=1000, metavar="N", help="ORB nFeatures")
    common.add_workers_option(parser, "worker processes")
    parser.add_argument(
        "--overwrite",
        action="store_true",
        help="re-measure every dataset, even those with a table of its key",
    )
    common.add_progress_option(parser)
    common.add_force_option(parser)
    parser.set_defaults(func=run)


@common.guarded("measure")
def run(args: argparse.Namespace) -> int:
    from jsve.image._datasets import DatasetError
    from jsve.image._measure import measure_datasets
    from jsve.image._orb import OrbSettings

    try:
        orb = OrbSettings(extractor=args.extractor, fallback=not args.no_fallback, n_features=args.n_features)
        tables = measure_datasets(
            args.datasets,
            args.output,
            table_format=args.format,
            camera=args.camera,
            stride=args.stride,
            orb=orb,
            workers=args.workers,
            overwrite=args.overwrite,
            force=args.force,
            progress=not args.no_progress,
        )
    except (ValueError, DatasetError) as error:
        return common.fail("measure", error)
    print(f"{len(tables)} tables in {args.output}")
    return 0
