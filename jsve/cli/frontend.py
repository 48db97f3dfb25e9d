"""`jsve frontend build|vocabulary|run`: the real front-end, ORB-SLAM3 v1.0 with jsve's hook.

    jsve frontend build --orbslam3 ORB_SLAM3-v1.0.tar.gz --pangolin-src Pangolin-v0.9.5.tar.gz -o BUILD
    jsve frontend build --orbslam3 ~/ORB_SLAM3 --pangolin /usr/local -o BUILD     # an installed Pangolin

`build` copies ORB-SLAM3 (a clone or the v1.0 archive; never modified) into BUILD, applies jsve's hook
by anchored edits and builds Pangolin (when not installed), DBoW2, g2o, the library and jsve's driver
BUILD/bin/jsve_orbslam3 (jsve.frontend._build; docs/frontend.md). A re-run rebuilds only what changed.
`vocabulary` trains a DBoW2 text vocabulary from images (jsve.frontend._vocabulary), for machines
without ORB-SLAM3's ORBvoc.txt.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from jsve.cli import _common as common

HELP = "build and run ORB-SLAM3 v1.0 with jsve's logging hook"


def register(subparsers) -> None:
    p = subparsers.add_parser("frontend", help=HELP, description=HELP + " (docs/frontend.md).")
    sub = p.add_subparsers(dest="frontend_command", metavar="STEP", required=True)
    b = sub.add_parser(
        "build",
        help="copy ORB-SLAM3, apply jsve's hook, build it and jsve's driver",
        description="Copy ORB-SLAM3 v1.0 (a source tree or its .tar.gz; never modified) into BUILD, apply "
        "jsve's hook by anchored edits, build Pangolin when none is installed, DBoW2, g2o, the library "
        "and jsve's driver BUILD/bin/jsve_orbslam3. Idempotent: a re-run rebuilds only what changed. "
        "The first build takes 20-35 min at -j2 and up to ~8 GB of memory; compiler output goes to "
        "BUILD/build.log.",
    )
    b.add_argument("--orbslam3", required=True, metavar="DIR|TAR", help="ORB-SLAM3 v1.0 sources")
    pango = b.add_mutually_exclusive_group()
    pango.add_argument(
        "--pangolin", metavar="PREFIX", help="an installed Pangolin (holds lib/cmake/Pangolin)"
    )
    pango.add_argument(
        "--pangolin-src", metavar="DIR|TAR", help="Pangolin sources to build into BUILD/pangolin"
    )
    b.add_argument("-o", "--out", required=True, metavar="BUILD", help="build folder")
    b.add_argument("-j", "--jobs", type=int, default=os.cpu_count() or 1, help="parallel compile jobs")
    b.add_argument("--no-progress", action="store_true")
    b.set_defaults(func=run_build)
    v = sub.add_parser(
        "vocabulary",
        help="train a DBoW2 text vocabulary from images (ORB-SLAM3's ORB settings)",
        description="Train a deterministic DBoW2 text-format vocabulary (TF-IDF, L1) from ORB features of "
        "IMAGES (files or folders) with ORB-SLAM3's settings, for runs without ORB-SLAM3's ORBvoc.txt.",
    )
    from jsve.frontend._vocabulary import add_vocabulary_arguments, run_vocabulary

    add_vocabulary_arguments(v)
    v.set_defaults(func=run_vocabulary)


def run_build(args: argparse.Namespace) -> int:
    from jsve.frontend._build import BuildError, build

    for flag, value in (("--orbslam3", args.orbslam3), ("--pangolin-src", args.pangolin_src)):
        if value and not Path(value).exists():
            return common.fail("frontend build", f"{flag} {value}: no such file or folder")
    try:
        driver = build(
            Path(args.orbslam3),
            Path(args.out),
            pangolin=Path(args.pangolin) if args.pangolin else None,
            pangolin_src=Path(args.pangolin_src) if args.pangolin_src else None,
            jobs=args.jobs,
            progress=not args.no_progress,
        )
    except (BuildError, OSError) as err:
        return common.fail("frontend build", err)
    print(driver)
    return 0
