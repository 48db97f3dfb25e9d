"""`jsve evaluate LOGS --rule ...`: replay rules over many logs and score them against ground truth.

    jsve evaluate study.parquet --rule orbslam3 --rule sve-option2 --align se3 -o results/

LOGS is a folder of format-v1 logs, a single log, or a Parquet file from `jsve ingest`. Writes
runs.parquet / runs.csv (one row per run and rule) and summary.csv (aggregated by --by), and prints
the summary and, per rule, how many runs failed for each failure_reason.
"""

from __future__ import annotations

from pathlib import Path

from jsve.cli import _common as common

HELP = "replay switching rules over logs and measure their trajectory error"


def register(subparsers) -> None:
    from jsve.core._rules import PRESETS

    p = subparsers.add_parser(
        "evaluate",
        help=HELP,
        description="Replay each rule (a preset name or a JSON file, see docs/state-machine.md) over every "
        "run, align to ground truth and report APE statistics with coverage and failures.",
    )
    p.add_argument("logs", metavar="LOGS", help="folder of logs, a log, or a Parquet file from `jsve ingest`")
    p.add_argument(
        "--rule",
        action="append",
        metavar="PRESET|params.json",
        help=f"{', '.join(PRESETS)}, or a rule JSON file; repeatable (default: all presets)",
    )
    common.add_align_option(p)
    p.add_argument("--n-to-align", type=int, metavar="N", help="align on the first N evaluated frames only")
    common.add_segments_option(p)
    p.add_argument("--min-coverage", type=float, default=0.0, help="runs below this coverage count as failed")
    p.add_argument(
        "--by",
        default="sequence,disturbance,level,rule",
        help="comma-separated metadata keys to aggregate by (default: %(default)s)",
    )
    common.add_switch_model_option(p)
    p.add_argument("--on-error", choices=common.on_error_choices(), default="raise")
    p.add_argument("-o", "--output", metavar="DIR", help="write runs.parquet, runs.csv and summary.csv here")
    p.add_argument("--workers", type=int, metavar="N")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--x64", action="store_true", help="evaluate in float64 (slower; default float32)")
    p.set_defaults(func=run)


@common.guarded("evaluate")
def run(args) -> int:
    import jax

    if args.x64:
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import pandas as pd

    from jsve.evaluation._aggregate import aggregate, failure_counts
    from jsve.evaluation._evaluate import evaluate
    from jsve.io import _atomic as atomic
    from jsve.io._batching import buckets

    progress = not args.no_progress
    if args.output:
        atomic.check_writable(args.output)  # before the replay: an unwritable folder fails at once
    try:
        from jsve.io import load_rules

        rules = load_rules(args.rule)
        runs = common.load_runs(
            "evaluate", args.logs, on_error=args.on_error, workers=args.workers, progress=progress
        )
    except (ValueError, OSError) as err:  # LogFormatError is a ValueError
        return common.fail("evaluate", err)
    if not runs:
        return common.fail("evaluate", f"no valid logs in {args.logs}")
    missing_gt = [r.source for r in runs if not r.has_ground_truth]
    if missing_gt:
        return common.fail(
            "evaluate",
            f"{len(missing_gt)} logs have no ground truth (first: {missing_gt[0]}); "
            "associate it with `jsve ingest --gt`",
        )
    groups = buckets(runs, dtype=jnp.float64 if args.x64 else jnp.float32)
    options = dict(
        align=args.align,
        n_first=args.n_to_align,
        segments=args.segments,
        switch_model=args.switch_model or "orbslam3",
    )
    tables = [
        evaluate(groups, rule, rule_name=name, min_coverage=args.min_coverage, progress=progress, **options)
        for name, rule in rules
    ]
    per_run = pd.concat(tables, ignore_index=True)
    by = [k for k in args.by.split(",") if k]
    unknown = [k for k in by if k not in per_run.columns]
    if unknown:
        known = ", ".join(map(str, per_run.columns))
        return common.fail("evaluate", f"--by keys {unknown} are not metadata of these logs; known: {known}")
    summary = aggregate(per_run, by)
    if args.output:
        out = Path(args.output)
        with atomic.all_or_nothing():  # the three tables, or none
            atomic.write_table(per_run, out / "runs.parquet")
            atomic.write_table(per_run, out / "runs.csv")
            atomic.write_table(summary, out / "summary.csv")
    shown = [
        *by,
        "n_runs",
        "failure_rate",
        "mean_coverage",
        "mean_changed",
        "mean_unsupported",
        "rmse_mean_all",
        "rmse_median_all",
        "pooled_rmse_all",
    ]
    failures = failure_counts(per_run, ["rule"])
    with pd.option_context("display.width", 160, "display.max_columns", 20, "display.max_rows", 200):
        print(summary[shown].to_string(index=False, float_format=lambda x: f"{x:.4g}"))
        print()
        if failures.empty:
            print("failed runs: none")
        else:
            print("failed runs by failure_reason:")
            # One line per (rule, reason): the count before the reason, whose length varies.
            width = max(len("rule"), *(len(str(r)) for r in failures["rule"]))
            print(f"{'rule':<{width}}  {'n_runs':>6}  failure_reason")
            for rule, n_runs, reason in failures[["rule", "n_runs", "failure_reason"]].to_numpy():
                print(f"{rule!s:<{width}}  {n_runs:>6}  {reason}")
    return 0
