"""`jsve disturb DATASET... -o OUT`: write disturbed copies of EuRoC datasets, one per (disturbance, level).

A thin layer over jsve.image._datasets.disturb_datasets: parallel (--scheduler: an embedded Dask cluster,
a process pool or a running Dask cluster, docs/scaling.md), with a progress bar, resumable (finished
datasets made from the same source content, parameters and seed are skipped, stale `.partial` folders
redone; a finished dataset of another seed, source or parameters stops the command, exit 2, unless
--force rewrites it). `--list` shows the registered disturbances. `--disturbances blur=5,15,occlusion`
chooses disturbances and levels (the earlier `--disturbance NAMES --levels ...` still works). Before
writing, the estimated size is printed; above the free disk space the command stops unless --yes.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from jsve.cli import _common as common
from jsve.cli._scheduler import add_scheduler_option

HELP = "write disturbed copies of EuRoC datasets (blur, downsample, occlusion, noise, ...)"


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "disturb",
        help=HELP,
        description=(
            "Write one disturbed copy of each EuRoC DATASET (a folder holding mav0/) per disturbance and "
            "level, as OUT/<dataset>/<disturbance>-<level>/ with a manifest. Camera images (cam0, cam1) are "
            "disturbed; IMU, ground truth and everything else is hard-linked (or copied) untouched. "
            "Re-running skips finished datasets made from the same source content, parameters and seed; "
            "one made otherwise stops the command unless --force."
        ),
    )
    parser.add_argument("datasets", metavar="DATASET", nargs="*", help="EuRoC dataset folder(s)")
    common.add_output_option(parser, metavar="OUT", help="output root folder (required unless --list)")
    parser.add_argument(
        "--disturbances",
        metavar="SPEC",
        help="comma-separated names each with optional levels: blur,noise (their default levels) or "
        "blur=5,15,25,occlusion=100,200 (default: every disturbance at its default levels; see --list)",
    )
    parser.add_argument(
        "--disturbance",
        metavar="NAMES",
        help="the earlier spelling: comma-separated names, levels from --levels (default: none; use "
        "--disturbances)",
    )
    parser.add_argument(
        "--levels",
        metavar="LEVELS",
        action="append",
        help="the earlier spelling of levels, with --disturbance: `5,15,25` (one disturbance selected) or "
        "`NAME=5,15,25` (repeatable) (default: the registry's grid; use --disturbances NAME=5,15,25)",
    )
    parser.add_argument(
        "--downsample-mode",
        choices=("rescale", "calibration"),
        default="rescale",
        help="rescale: scale back to the original size (calibration unchanged); calibration: keep the "
        "small image and write scaled intrinsics to sensor.yaml",
    )
    parser.add_argument(
        "--param",
        metavar="NAME.KEY=VALUE",
        action="append",
        default=[],
        help="a disturbance parameter, e.g. motion_blur.angle=45 or haze.patchiness=0.5; repeatable "
        "(default: the registry's parameters)",
    )
    parser.add_argument(
        "--seed", type=int, default=0, metavar="N", help="base seed of the random disturbances"
    )
    common.add_workers_option(parser, "processes writing datasets")
    add_scheduler_option(parser, "the DATASETs and OUT")
    common.add_progress_option(parser)
    parser.add_argument(
        "--list", action="store_true", help="list the disturbances and their levels, and exit"
    )
    common.add_yes_option(parser)
    common.add_force_option(parser)
    parser.set_defaults(func=run)


def _value(text: str):
    lowered = text.lower()
    if lowered in ("true", "false"):
        return lowered == "true"
    for kind in (int, float):
        try:
            return kind(text)
        except ValueError:
            pass
    return text


def _parse_levels(items: list[str] | None, names: list[str]) -> dict[str, list[float]]:
    levels: dict[str, list[float]] = {}
    for item in items or []:
        if "=" in item:
            name, values = item.split("=", 1)
        elif len(names) == 1:
            name, values = names[0], item
        else:
            raise ValueError(f"--levels {item!r}: with several disturbances write NAME=LEVELS")
        levels[name.strip()] = [_value(v.strip()) for v in values.split(",") if v.strip()]
    return levels


def _disturbances(args: argparse.Namespace, known: list[str]) -> tuple[list[str], dict[str, list[float]]]:
    """(names, levels) from --disturbances, or from the earlier --disturbance and --levels."""
    if args.disturbances is not None:
        if args.disturbance is not None or args.levels:
            raise ValueError("--disturbances replaces --disturbance and --levels: give one or the other")
        from jsve.core._levels import parse_disturbances

        parsed = parse_disturbances(args.disturbances, known)
        names = list(dict.fromkeys(name for name, _ in parsed))
        levels: dict[str, list[float]] = {}
        for name, values in parsed:
            if values is not None:
                levels.setdefault(name, []).extend(v for v in values if v not in levels.get(name, []))
        return names, levels
    names = [n.strip() for n in args.disturbance.split(",")] if args.disturbance else known
    return names, _parse_levels(args.levels, names)


def _size(jobs) -> tuple[float, str]:
    """(estimated bytes, how) of the datasets `jobs` write: each the size of its source's camera images
    (the rest of a dataset is hard-linked, or copied where links fail)."""
    from jsve.image._datasets import camera_dirs

    images: dict[Path, int] = {}
    for job in jobs:
        if job.source not in images:
            files = (f for cam in camera_dirs(job.source) for f in (cam / "data").iterdir())
            images[job.source] = sum(f.stat().st_size for f in files if f.is_file())
    total = sum(images[job.source] for job in jobs)
    mean = total / max(len(jobs), 1)
    return total, f"{common.plural(len(jobs), 'dataset')} x ~{common.format_bytes(mean)} of camera images"


def _parse_params(items: list[str]) -> dict[str, dict[str, object]]:
    params: dict[str, dict[str, object]] = {}
    for item in items:
        key, sep, value = item.partition("=")
        name, dot, field = key.partition(".")
        if not sep or not dot:
            raise ValueError(f"--param {item!r}: expected NAME.KEY=VALUE")
        params.setdefault(name.strip(), {})[field.strip()] = _value(value.strip())
    return params


@common.guarded("disturb")
def run(args: argparse.Namespace) -> int:
    from jsve.image._datasets import DatasetError, disturb_datasets, format_level, make_jobs
    from jsve.image._disturb import DISTURBANCES
    from jsve.io._scheduler import check_scheduler

    if args.list:
        for name, (_, levels, unit, doc) in DISTURBANCES.items():
            print(f"{name:12s} [{unit}] {', '.join(format_level(v) for v in levels)}\n{'':12s} {doc}")
        return 0
    if not args.datasets or not args.output:
        return common.fail("disturb", "need DATASET(s) and -o OUT (or --list)")
    try:
        check_scheduler(args.scheduler)  # before the size is announced: a wrong value writes nothing
        names, levels = _disturbances(args, list(DISTURBANCES))
        params = _parse_params(args.param)
        if args.downsample_mode != "rescale" and "downsample" in names:
            params.setdefault("downsample", {})["mode"] = args.downsample_mode
        jobs = make_jobs(args.datasets, args.output, names, levels, params, args.seed)
        total, detail = _size(jobs)
        stop = common.announce_size("disturb", args.output, total, detail, yes=args.yes)
        if stop is not None:
            return stop
        results = disturb_datasets(
            args.datasets,
            args.output,
            names,
            levels,
            params,
            seed=args.seed,
            workers=args.workers,
            progress=not args.no_progress,
            force=args.force,
            scheduler=args.scheduler,
        )
    except (ValueError, DatasetError) as error:
        return common.fail("disturb", error)
    counts = {s: sum(r.status == s for r in results) for s in ("written", "redone", "skipped")}
    print(
        f"{len(results)} datasets in {args.output}: {counts['written']} written, {counts['redone']} redone "
        f"(stale partial), {counts['skipped']} already finished"
    )
    return 0
