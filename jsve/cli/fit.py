"""`jsve fit LOGS -o OUT`: fit switching rules to minimise position error, cross-validate, and report.

    jsve fit study.parquet -o results/ --config sweeps/fit.toml

LOGS is a folder of format-v1 logs, a log, or a Parquet file from `jsve ingest`; the logs need ground
truth. Runs every stage of jsve.fitting._study (presets, fits, k-fold cross-validation, parameter
bootstrap, heat map, SVE per level; --thorough adds leave-one-group-out folds and the bootstrap's local
design) into OUT, resumably, then writes OUT/report.md and OUT/report.html (`jsve report OUT` re-renders).
A study folder is resumed only for the same data content and configuration; another stops the command
(exit 2, one line naming the folder and what differs) unless --force deletes the old study's files.
"""

from __future__ import annotations

import logging
import sys
from pathlib import Path

from jsve.cli import _common as common

HELP = "fit SVE weights and thresholds (and ORB-SLAM3's) to minimise position error"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "fit",
        help=HELP,
        description="Search, Nelder-Mead and (optionally) relaxed BFGS fits of each rule family, with "
        "k-fold cross-validation against the presets, bootstrap intervals of the fitted parameters "
        "(--thorough: also leave-one-group-out folds, and finer intervals) and a report.",
    )
    p.add_argument("logs", metavar="LOGS", help="folder of logs, a log, or a Parquet file from `jsve ingest`")
    p.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="DIR",
        help="study folder (resumed if it holds a study of the same data and configuration)",
    )
    p.add_argument(
        "--config",
        metavar="TOML",
        help="study settings (see sweeps/fit.toml; default: jsve.fitting's StudyConfig defaults)",
    )
    p.add_argument(
        "--family",
        action="append",
        choices=("sve", "inliers"),
        help="rule family to fit; repeatable (default: both)",
    )
    penalty = p.add_argument(
        "--failure-penalty",
        type=float,
        metavar="M",
        help="metres charged for a failed run (default: --config's, else %(penalty)s m)",
    )
    penalty.penalty = common.LibraryValue("jsve.core._objective", "DEFAULT_FAILURE_PENALTY_M")
    common.add_switch_model_option(p)
    common.add_support_option(p)
    p.add_argument(
        "--thorough",
        action="store_true",
        help="also leave out each sequence and each disturbance in turn, and refit each bootstrap "
        "resample among 1,024 settings around the fit too, for finer parameter intervals "
        "(jsve.fitting._config.THOROUGH; about twice the time, docs/fitting.md); "
        "--config's settings override it (default: 5-fold only, and intervals from refits among the "
        "search's settings and the fit)",
    )
    p.add_argument("--relaxed", action="store_true", help="also run the relaxed (annealed BFGS) fit")
    p.add_argument(
        "--search",
        choices=("auto", "halving", "exhaustive"),
        help="how the design is searched: 'halving' screens every setting on a stratified share of the "
        "runs and re-scores the best on more (about a third of the cost), 'exhaustive' scores every "
        "setting on every run, 'auto' is exhaustive below 300 runs and halving above, its first rung "
        "on at least 40 runs (default: --config's [fit] search, else auto)",
    )
    p.add_argument(
        "--eta",
        type=float,
        metavar="X",
        help="halving: keep the best 1/X of the settings and score them on X times as many runs at each "
        "rung (default: --config's, else 3)",
    )
    p.add_argument(
        "--initial-fraction",
        type=float,
        metavar="F",
        help="halving: share of the runs the first rung screens every setting on, in (0, 1] "
        "(default: --config's, else 1/9; 1 is the exhaustive search; --search auto sets its own)",
    )
    p.add_argument(
        "--seed",
        type=int,
        metavar="N",
        help="seed of designs, folds and bootstraps (default: --config's, else 0)",
    )
    common.add_on_error_option(p)
    common.add_workers_option(p, "processes reading the logs, and Dask workers of --scheduler local")
    p.add_argument(
        "--scheduler",
        default=None,
        metavar="local|processes|ADDRESS",
        help="run the searches over rule settings as Dask tasks, settings sharded across workers that each "
        "stream the Parquet study (LOGS must be a .parquet file): local, an embedded Dask cluster of "
        "--workers processes; processes, a process pool; or a running Dask cluster's scheduler address "
        "(tcp://host:8786) or scheduler file, whose workers must have the same jsve and see LOGS under the "
        "same absolute path (docs/scaling.md). Each worker holds the study's search layout (about 70 bytes "
        "a frame, docs/performance.md). Default: in this process, on every core",
    )
    common.add_progress_option(p)
    p.add_argument(
        "--no-estimate",
        action="store_true",
        help="skip the timing probe and the expected wall time printed before the fit (without it "
        "`jsve fit` times a few settings of each stage's computation on the data, after compiling them, "
        "and states on stderr how long the study should take, then the actual time beside it; "
        "see docs/fitting.md) (default: off)",
    )
    p.add_argument(
        "--estimate-only",
        action="store_true",
        help="state the expected wall time (the timing probe and the cost model) and stop: nothing is "
        "written to DIR (default: off)",
    )
    p.add_argument("--no-report", action="store_true", help="write the tables only, not the report")
    common.add_force_option(p)
    p.set_defaults(func=run)


@common.guarded("fit")
def run(args) -> int:
    from jsve._jax_cache import enable_compilation_cache
    from jsve.cli._common import use_all_cores
    from jsve.fitting._config import StudyConfig
    from jsve.io._atomic import check_writable

    check_writable(args.output)  # before reading the logs: an unwritable folder fails at once
    if args.scheduler is not None:  # a wrong value fails before the logs are read
        from jsve.io._scheduler import SchedulerError, check_scheduler

        try:
            check_scheduler(args.scheduler)
        except SchedulerError as err:
            return common.fail("fit", err)
    use_all_cores()  # one XLA CPU device per core: the batched search runs on all of them
    enable_compilation_cache()  # a second run compiles nothing
    try:
        config = StudyConfig.from_toml(
            args.config,
            thorough=args.thorough,
            families=tuple(args.family) if args.family else None,
            failure_penalty=args.failure_penalty,
            switch_model=args.switch_model,
            support=args.support,
            relaxed=args.relaxed or None,
            seed=args.seed,
            search=args.search,
            eta=args.eta,
            initial_fraction=args.initial_fraction,
        )
        # A Parquet study is streamed into FitData (jsve.fitting._data.FitData.from_parquet): no parsed
        # runs are held; logs on disk are parsed first.
        streamed = Path(args.logs).name.endswith(".parquet")
        runs = [] if streamed else common.load_runs(
            "fit", args.logs, on_error=args.on_error, workers=args.workers, progress=not args.no_progress
        )  # fmt: skip
    except (ValueError, OSError) as err:  # LogFormatError is a ValueError
        return common.fail("fit", err)
    if not streamed and not runs:
        return common.fail("fit", f"no valid logs in {args.logs}")
    import time

    from jsve.fitting._data import FitData
    from jsve.fitting._study import run_study
    from jsve.report._report import trust_warnings, write_report

    started = time.perf_counter()
    try:
        if streamed:
            data = FitData.from_parquet(args.logs, config.objective())
        else:
            data = FitData.from_runs(runs, config.objective())
    except (ValueError, OSError) as err:  # LogFormatError is a ValueError
        return common.fail("fit", err)
    if args.scheduler is not None:
        from jsve.fitting._distributed import ShardedSearch

        if not streamed:
            return common.fail("fit", "--scheduler needs a Parquet study (`jsve ingest` the logs first)")
        data.searcher = ShardedSearch.of(data, args.scheduler, args.workers)
    from jsve._memory import release_memory

    release_memory()  # loading leaves each bucket shape's executables and freed heap behind (jsve._memory)
    logging.getLogger(__name__).info("fitting over %d runs, %d frames", data.n_runs, data.n_frames)
    description = {"source": str(args.logs)}
    expected = None
    if args.estimate_only and args.no_estimate:
        return common.fail("fit", "--estimate-only and --no-estimate exclude each other")
    if not args.no_estimate:
        expected = _estimate(data, config, args, description)
    if args.estimate_only:
        if expected is None:
            print("jsve fit: every stage is done already: nothing to estimate", file=sys.stderr)
        return 0
    from_estimate = time.perf_counter()
    try:
        run_study(
            data,
            args.output,
            config,
            progress=not args.no_progress,
            data_description=description,
            force=args.force,
        )
    finally:
        close = getattr(data.searcher, "close", None)
        if close is not None:
            close()  # a local cluster's or pool's workers
    if not args.no_report:
        write_report(args.output)
    for line in trust_warnings(args.output):  # beyond what the replay-vs-re-run validation supports
        print(f"jsve fit: warning: {line}", file=sys.stderr)
    if expected is not None:
        _report_timing(args.output, expected, time.perf_counter() - from_estimate)
    # The demo's closing lines (the headline in words), timed from the logs read to the report written.
    done = "fitted" if args.no_report else "fitted and reported"
    seconds = time.perf_counter() - started
    common.print_study_summary(f"jsve fit: {done} in {seconds:.0f} s", args.output, report=not args.no_report)
    return 0


def _estimate(data, config, args, description: dict):
    """The expected wall time of the study (jsve.fitting._estimate), stated on stderr in one line before
    the study starts; None where every stage is done already (nothing to time), or where the count's
    scratch files cannot be written (said on stderr; the study then meets the same disk itself). A
    folder of another study stops here (StaleOutputError), before the probe, as run_study would."""
    from jsve.fitting._estimate import estimate
    from jsve.fitting._study import finished_stages

    done = finished_stages(args.output, config, data, data_description=description, force=args.force)
    try:  # the count runs the stages on scratch files of a temporary folder
        expected = estimate(data, config, done=done, progress=not args.no_progress)
    except OSError as err:
        if args.estimate_only:
            raise
        print(f"jsve fit: no estimate of the wall time ({err})", file=sys.stderr, flush=True)
        return None
    if expected is None:
        return None
    resumed = f" ({len(done)} stages done already)" if done else ""
    print(f"jsve fit: {expected.line()}{resumed}", file=sys.stderr, flush=True)
    return expected


def _report_timing(out, expected, actual: float) -> None:
    """The estimate against the measured wall time, on stderr and in study.json's "timing"."""
    from jsve.fitting._estimate import duration
    from jsve.fitting._study import record_timing

    ratio = actual / expected.total if expected.total > 0 else float("inf")
    print(
        f"jsve fit: took {duration(actual)}, expected {duration(expected.total)} "
        f"(actual / expected {ratio:.2f})",
        file=sys.stderr,
    )
    record_timing(out, {**expected.as_dict(), "actual_s": actual, "actual_over_expected": ratio})
