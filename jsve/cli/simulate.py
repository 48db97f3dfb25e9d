"""`jsve simulate -o OUT`: write simulated format-v1 tracking logs (the stand-in front-end).

    jsve simulate -o study/                                          11 procedural flights x 31 x 10
    jsve simulate -o study/ --sequences MH_01,V1_01 --euroc-gt ../shared/data/euroc/groundtruth_left_cam
    jsve simulate -o study/ --procedural 3 --disturbances blur=0,25,50,occlusion --runs 5 --parquet

A thin layer over jsve.sim._study.write_study: one log per sequence x setting x run under
OUT/<sequence>/<disturbance>-<level>/run_<k>.csv, in parallel processes (an embedded Dask cluster, a
process pool or a running Dask cluster: --scheduler, docs/scaling.md); a re-run skips logs that
are already complete and were simulated under the same seed, --imu, configuration and input files
(their `generator` metadata); a folder holding logs of another key stops the command (exit 2) unless
--force discards them. docs/simulator.md describes the model.
"""

from __future__ import annotations

import argparse
import math

from jsve.cli import _common as common
from jsve.cli._scheduler import add_scheduler_option

HELP = "write simulated tracking logs (sequences x disturbances x levels x runs)"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "simulate",
        help=HELP,
        description="Simulate ORB-SLAM3 + logger on EuRoC ground-truth trajectories or procedural flights, "
        "under the seed paper's disturbances (or more), and write one format-v1 log per run. Deterministic "
        "under --seed; resumable (complete logs of the same seed and configuration are skipped; logs of "
        "another stop the command unless --force). Says the estimated size of the logs before writing "
        "and stops when it exceeds the free disk space (unless --yes). See docs/simulator.md.",
    )
    common.add_output_option(p, metavar="OUTDIR", required=True, help="output folder")
    source = p.add_mutually_exclusive_group()
    source.add_argument(
        "--sequences",
        metavar="MH_01,...",
        help="comma-separated EuRoC sequence names (needs --euroc-gt; default: procedural flights)",
    )
    source.add_argument(
        "--procedural", type=int, metavar="N", help="N procedural flights (default: 11, without --sequences)"
    )
    p.add_argument(
        "--euroc-gt",
        metavar="DIR",
        help="ORB-SLAM3's EuRoC left-camera ground truth folder (MH01_GT.txt, ...); sibling "
        "timestamps/ and imu/ folders are used when present (default: none, needed by --sequences)",
    )
    p.add_argument(
        "--disturbances",
        default="seed",
        metavar="SPEC",
        help="seed (the seed paper's 31 settings), all, none, or comma-separated names each with optional "
        "levels: blur,occlusion (their default levels) or blur=0,25,50,occlusion=100,200 (the earlier "
        "blur:0:25:50 works too); see `jsve disturb --list` for names and units",
    )
    p.add_argument(
        "--duration",
        type=float,
        metavar="S",
        help="length of every procedural flight, s (at 20 frames/s: 180 s = 3,600 frames; default: each "
        "flight's drawn between 80 and 180 s)",
    )
    p.add_argument("--runs", type=int, default=10, metavar="N", help="runs per setting")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="study seed")
    common.add_workers_option(p, "processes simulating sequences")
    add_scheduler_option(p, "OUTDIR and --euroc-gt")
    p.add_argument(
        "--imu",
        choices=("synthetic", "real"),
        default="synthetic",
        help="synthetic IMU or the real EuRoC imu0 stream where --euroc-gt's sibling imu/ folder has one",
    )
    p.add_argument("--parquet", action="store_true", help="also consolidate the logs into OUT/study.parquet")
    common.add_progress_option(p)
    common.add_yes_option(p)
    common.add_force_option(p)
    p.set_defaults(func=run)


@common.guarded("simulate")
def run(args: argparse.Namespace) -> int:
    from jsve.io._scheduler import check_scheduler
    from jsve.sim._config import SimConfig
    from jsve.sim._simulate import settings
    from jsve.sim._study import LOG_BYTES_PER_FRAME, study_size, write_study
    from jsve.sim._trajectory import FlightProfile

    if args.sequences and not args.euroc_gt:
        return common.fail("simulate", "--sequences needs --euroc-gt DIR (or use --procedural N)")
    if args.runs < 1:
        return common.fail("simulate", "--runs must be >= 1")
    if args.duration is not None and args.sequences:
        return common.fail(
            "simulate", "--duration sets procedural flights' length; EuRoC sequences have their own"
        )
    if args.duration is not None and not (args.duration > 0 and math.isfinite(args.duration)):
        return common.fail(
            "simulate", f"--duration must be a positive number of seconds, got {args.duration}"
        )
    flight = FlightProfile() if args.duration is None else FlightProfile(duration_s=(args.duration,) * 2)
    try:
        check_scheduler(args.scheduler)  # before the size is announced: a wrong value writes nothing
        grid = settings(args.disturbances)
        logs, frames, total = study_size(
            args.sequences,
            procedural=args.procedural,
            euroc_gt=args.euroc_gt,
            disturbances=args.disturbances,
            runs=args.runs,
            flight=flight,
        )
        detail = f"{common.plural(logs, 'log')} x ~{frames:.0f} frames x ~{LOG_BYTES_PER_FRAME} B"
        stop = common.announce_size("simulate", args.output, total, detail, yes=args.yes)
        if stop is not None:
            return stop
        result = write_study(
            args.output,
            args.sequences,
            procedural=args.procedural,
            euroc_gt=args.euroc_gt,
            disturbances=args.disturbances,
            runs=args.runs,
            seed=args.seed,
            workers=args.workers,
            config=SimConfig(imu_source=args.imu, flight=flight),
            progress=not args.no_progress,
            parquet=args.parquet,
            force=args.force,
            scheduler=args.scheduler,
        )
    except (ValueError, FileNotFoundError) as err:
        return common.fail("simulate", err)
    print(
        f"{result.written} logs written, {result.skipped} already complete, to {args.output} "
        f"in {result.seconds:.1f} s"
        f" ({len(grid)} settings; simulation {result.simulate_s:.1f} s and writing {result.write_s:.1f} s"
        f" summed over workers)" + (f"; Parquet: {result.parquet}" if result.parquet else "")
    )
    return 0
