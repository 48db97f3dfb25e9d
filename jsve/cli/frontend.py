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
import sys
from pathlib import Path

from jsve.cli import _common as common
from jsve.cli._scheduler import add_scheduler_option

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
        "--pangolin",
        metavar="PREFIX",
        help="an installed Pangolin (holds lib/cmake/Pangolin) (default: one built in BUILD/pangolin, "
        "else CMake's search)",
    )
    pango.add_argument(
        "--pangolin-src",
        metavar="DIR|TAR",
        help="Pangolin sources to build into BUILD/pangolin (default: none, build no Pangolin)",
    )
    common.add_output_option(b, metavar="BUILD", required=True, help="build folder")
    b.add_argument(
        "-j",
        "--jobs",
        type=int,
        default=os.cpu_count() or 1,
        metavar="N",
        help="parallel compile jobs (default: all cores)",
    )
    common.add_progress_option(b)
    b.set_defaults(func=run_build)
    r = sub.add_parser(
        "run",
        help="run the hooked ORB-SLAM3 over EuRoC-format datasets, N runs each, writing jsve logs",
        description="Run the driver of BUILD (IMU_MONOCULAR, or MONOCULAR with --sensor) over each DATASET "
        "(a EuRoC-format folder, e.g. from `jsve render` or `jsve disturb`) --runs times, writing "
        "OUT/<sequence>/<disturbance>-<level>/run_<k>.csv (format-v3 log), run_<k>.orbslam3.txt "
        "(ORB-SLAM3's saved trajectory), run_<k>.saved-from-log.txt (the same rebuilt from the log), "
        "run_<k>.summary.json (events, and the ATE of both trajectories against the dataset's ground "
        "truth: a mismatch shows there) and run_<k>.console.txt. Resumable after a kill at any moment: a "
        "run is done once its summary is written; runs that crashed, timed out or hit a closed lockstep "
        "gate are outcomes and kept (--retry-failed runs them again); logs of other inputs stop the "
        "command unless --force. A downsampled dataset gets ORB-SLAM3 settings scaled to its image size. "
        "--masks takes the keypoints on cars and pedestrians out of ORB-SLAM3's frames "
        "(DATASET/mav0/cam0/masks); --keypoints writes run_<k>.keypoints.csv for `jsve mask-logs`.",
    )
    r.add_argument("build", metavar="BUILD", help="folder of `jsve frontend build`")
    r.add_argument("datasets", nargs="+", metavar="DATASET", help="EuRoC-format dataset folders")
    r.add_argument(
        "--vocabulary", required=True, metavar="VOC.txt", help="ORBvoc.txt or `jsve frontend vocabulary`'s"
    )
    r.add_argument(
        "--settings",
        required=True,
        metavar="YAML",
        help="ORB-SLAM3 settings (EuRoC Monocular-Inertial.yaml; Monocular.yaml with --sensor monocular)",
    )
    r.add_argument(
        "--sensor",
        choices=("imu-monocular", "monocular"),
        default="imu-monocular",
        help="ORB-SLAM3's sensor: IMU_MONOCULAR (default; images and mav0/imu0) or MONOCULAR (images "
        "alone, ORB-SLAM3's own rule only; trajectories scored after a sim3 alignment)",
    )
    r.add_argument(
        "--masks",
        action="store_true",
        help="drop the keypoints on cars and pedestrians before ORB-SLAM3 tracks them: each image's "
        "16-bit instance map DATASET/mav0/cam0/masks/<image name>.png (pixel = class * 1000 + instance; "
        "classes 1 and 2); a missing mask stops the command (docs/masks.md, Masks in the loop)",
    )
    r.add_argument(
        "--keypoints",
        action="store_true",
        help="write every frame's keypoints to run_<k>.keypoints.csv (side file v1, what `jsve mask-logs` "
        "reads; about 60 bytes per keypoint)",
    )
    r.add_argument(
        "--rule",
        default="orbslam3",
        metavar="RULE",
        help="the success test in the loop: orbslam3 (ORB-SLAM3's own, default), record (fails "
        "only frames without an inlier: logs that support every stricter rule), another preset "
        "(sve-option1, sve-option2, ...), or a rule JSON file of either family (e.g. jsve fit's "
        "fitted_sve.json or fitted_inliers.json)",
    )
    r.add_argument(
        "--switch-model",
        choices=("orbslam3", "imu-coast"),
        default="orbslam3",
        help="what a failed frame keeps: its optimised pose (orbslam3, as v1.0) or the pose "
        "TrackLocalMap started from (imu-coast)",
    )
    r.add_argument("--runs", type=int, default=1, metavar="N", help="runs per dataset")
    common.add_output_option(r, metavar="LOGDIR", required=True, help="output folder")
    common.add_workers_option(r, "drivers at once (each runs 3 threads)", default=1)
    add_scheduler_option(
        r,
        "BUILD, --vocabulary, --settings, the DATASETs and LOGDIR",
        local="--workers drivers started from this process (each driver is its own process: a Dask "
        "cluster on this machine would add only idle processes)",
        processes="the same as local",
    )
    r.add_argument(
        "--timeout", type=float, metavar="S", help="seconds before a run is stopped (default: no limit)"
    )
    r.add_argument("--force", action="store_true", help="redo runs whose logs came from other inputs")
    r.add_argument(
        "--retry-failed",
        action="store_true",
        help="run again the runs whose attempt crashed or timed out (default: keep them: a crash is an "
        "outcome of a non-deterministic system, and re-running until success biases the failure rate)",
    )
    from jsve.frontend import DEFAULT_GATE_TIMEOUT_S

    pace = r.add_mutually_exclusive_group()
    pace.add_argument(
        "--no-wait",
        action="store_true",
        help="feed frames as fast as tracking takes them "
        "(default: at the camera's rate, as a live camera; local mapping then keeps up)",
    )
    pace.add_argument(
        "--lockstep",
        action="store_true",
        help="deterministic runs: after each frame local mapping, then loop closing, run alone until "
        "their queues are empty; never paced. Run k draws from seed --seed + k; repeats are "
        "byte-identical (docs/frontend.md, Lockstep runs)",
    )
    r.add_argument(
        "--seed",
        type=int,
        metavar="S",
        help="run k seeds ORB-SLAM3's random draws (RANSAC) with S + k (default with --lockstep: 0; "
        "else ORB-SLAM3's own seed, 0, for every run)",
    )
    r.add_argument(
        "--gate-timeout",
        type=float,
        default=DEFAULT_GATE_TIMEOUT_S,
        metavar="S",
        help="with --lockstep: seconds a frame waits for local mapping and loop closing before the run "
        f"ends as outcome gate_timeout (default: {DEFAULT_GATE_TIMEOUT_S:g})",
    )
    common.add_progress_option(r)
    r.set_defaults(func=run_runs)
    v = sub.add_parser(
        "vocabulary", help="train a DBoW2 text vocabulary from images (ORB-SLAM3's ORB settings)"
    )
    from jsve.frontend._vocabulary import add_vocabulary_arguments, run_vocabulary

    add_vocabulary_arguments(v)  # its options and description, defined once there
    v.set_defaults(func=run_vocabulary)


def run_build(args: argparse.Namespace) -> int:
    from jsve.frontend._build import BuildError, build

    for flag, value in (("--orbslam3", args.orbslam3), ("--pangolin-src", args.pangolin_src)):
        if value and not Path(value).exists():
            return common.fail("frontend build", f"{flag} {value}: no such file or folder")
    try:
        driver = build(
            Path(args.orbslam3),
            Path(args.output),
            pangolin=Path(args.pangolin) if args.pangolin else None,
            pangolin_src=Path(args.pangolin_src) if args.pangolin_src else None,
            jobs=args.jobs,
            progress=not args.no_progress,
        )
    except (BuildError, OSError) as err:
        return common.fail("frontend build", err)
    print(driver)
    return 0


def run_runs(args: argparse.Namespace) -> int:
    from jsve.frontend._run import plan, run_all
    from jsve.io._resume import StaleOutputError
    from jsve.io._scheduler import SchedulerError, check_scheduler

    build, out = Path(args.build), Path(args.output)
    for flag, value in (
        ("BUILD", build / "build.json"),
        ("--vocabulary", args.vocabulary),
        ("--settings", args.settings),
    ):
        if not Path(value).is_file():
            return common.fail("frontend run", f"{flag}: {value}: no such file")
    try:
        check_scheduler(args.scheduler)  # before planning: a wrong value starts nothing
        if args.rule == "record":
            from jsve.frontend._run import record_rule

            rule = ("record", record_rule())
        else:
            from jsve.io import load_rules

            rule = load_rules([args.rule])[0]
        todo, done = plan(
            build, [Path(d) for d in args.datasets], runs=args.runs, out=out,
            vocabulary=Path(args.vocabulary), settings=Path(args.settings), rule=rule,
            switch_model=args.switch_model, force=args.force, retry_failed=args.retry_failed,
            mode="lockstep" if args.lockstep else ("no-wait" if args.no_wait else "paced"), seed=args.seed,
            sensor=args.sensor, masks=args.masks, keypoints=args.keypoints,
        )  # fmt: skip
    except (ValueError, OSError) as err:
        return common.fail("frontend run", err)
    except StaleOutputError as err:
        return common.fail("frontend run", f"{err}; --force redoes them")
    kept_failed = sum(not log.is_file() for log in done)
    print(
        f"jsve frontend run: {len(done)} runs done already ({kept_failed} of them failed: kept, "
        f"--retry-failed runs them again), {len(todo)} to run",
        file=sys.stderr,
    )
    try:
        results = run_all(build, todo, Path(args.vocabulary), workers=args.workers, timeout_s=args.timeout,
                          progress=not args.no_progress, scheduler=args.scheduler,
                          gate_timeout_s=args.gate_timeout)  # fmt: skip
    except SchedulerError as err:
        return common.fail("frontend run", err)
    failed = [r for r in results if r.get("exit_code") != 0]
    for r in failed:
        print(f"{r['log']}: {r.get('outcome')} (driver exit {r.get('exit_code')}; see its .console.txt)",
              file=sys.stderr)  # fmt: skip
    print(f"jsve frontend run: {len(results) - len(failed)} runs done, {len(failed)} failed; logs in {out}")
    return 1 if failed else 0
