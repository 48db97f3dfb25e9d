"""`jsve evaluate LOGS --rule ...`: replay rules over many logs and score them against ground truth.

    jsve evaluate study.parquet --rule orbslam3 --rule sve-option2 --align se3 -o results/

LOGS is a folder of format-v1 logs, a single log, or a Parquet file from `jsve ingest`. Writes
runs.parquet / runs.csv (one row per run and rule), summary.csv (aggregated by --by) and
evaluation.json (the settings and rules it scored with, jsve.evaluation.EvaluationRecord, which
`jsve report` reads), and prints the summary and, per rule, how many runs failed for each failure_reason.
"""

from __future__ import annotations

from pathlib import Path

from jsve.cli import _common as common

HELP = "replay switching rules over logs and measure their trajectory error"


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "evaluate",
        help=HELP,
        description="Replay each rule (a preset name or a JSON file, see docs/state-machine.md) over every "
        "run, align to ground truth and report, per group, the objective the fit minimises (failed runs "
        "charged the failure penalty) beside the failure rate, coverage and the APE of the runs that "
        "did not fail.",
    )
    p.add_argument("logs", metavar="LOGS", help="folder of logs, a log, or a Parquet file from `jsve ingest`")
    rule = p.add_argument(
        "--rule",
        action="append",
        metavar="PRESET|params.json",
        help="a preset (%(presets)s) or a rule JSON file (e.g. jsve fit's fitted_sve.json); repeatable "
        "(default: every preset)",
    )
    rule.presets = common.LibraryNames("jsve.core._rules", "PRESETS")
    common.add_align_option(p)
    p.add_argument(
        "--n-to-align",
        type=int,
        metavar="N",
        help="align on the first N evaluated frames only (default: all)",
    )
    common.add_scoring_options(p)
    penalty = p.add_argument(
        "--failure-penalty",
        type=float,
        metavar="M",
        help="metres charged for a failed run in the objective shown (default: the fit's, %(penalty)s m)",
    )
    penalty.penalty = common.LibraryValue("jsve.core._objective", "DEFAULT_FAILURE_PENALTY_M")
    p.add_argument(
        "--by",
        default="sequence,disturbance,level,rule",
        metavar="KEYS",
        help="comma-separated metadata keys to aggregate by",
    )
    common.add_switch_model_option(p)
    common.add_support_option(p)
    common.add_on_error_option(p)
    common.add_output_option(
        p,
        metavar="DIR",
        help="write runs.parquet, runs.csv, summary.csv and evaluation.json (the settings and rules, for "
        "`jsve report DIR`) to this folder (default: print the summary only)",
    )
    common.add_workers_option(p)
    common.add_progress_option(p)
    p.add_argument("--x64", action="store_true", help="evaluate in float64 (slower; float32 otherwise)")
    p.set_defaults(func=run)


@common.guarded("evaluate")
def run(args) -> int:
    import jax

    from jsve._jax_cache import enable_compilation_cache

    enable_compilation_cache()  # before the first compilation: a second run compiles nothing

    if args.x64:
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp

    from jsve.core._objective import DEFAULT_FAILURE_PENALTY_M, DEFAULT_MIN_COVERAGE
    from jsve.evaluation._aggregate import aggregate, failure_counts
    from jsve.evaluation._evaluate import TABLE_COLUMNS, evaluate_rules, in_run_order
    from jsve.evaluation._record import write_evaluation_record
    from jsve.io import _atomic as atomic
    from jsve.io._batching import buckets, meta_columns

    progress = not args.no_progress
    if args.min_coverage is None:
        args.min_coverage = DEFAULT_MIN_COVERAGE
    if args.output:
        atomic.check_writable(args.output)  # before the replay: an unwritable folder fails at once
    dtype = jnp.float64 if args.x64 else jnp.float32
    options = dict(
        align=args.align,
        n_first=args.n_to_align,
        failure=args.failure,
        min_coverage=args.min_coverage,
        switch_model=args.switch_model or "orbslam3",
        progress=progress,
    )
    by = [k for k in args.by.split(",") if k]
    try:
        from jsve.io import load_rules

        rules = load_rules(args.rule)
        if Path(args.logs).name.endswith(".parquet"):
            # Streamed: Arrow record batches become chunks of padded arrays, scored under every rule
            # while in memory, so the peak follows the chunk size, not the study (jsve.io._stream).
            from jsve.io._stream import iter_buckets, open_study

            study, runs = open_study(args.logs), None
            n_runs, metas = study.n_runs, [e["meta"] for e in study.entries]
            missing_gt = [e["source"] for e in study.entries if not e["has_ground_truth"]]
        else:
            runs = common.load_runs(
                "evaluate", args.logs, on_error=args.on_error, workers=args.workers, progress=progress
            )
            study, n_runs, metas = None, len(runs), [r.meta for r in runs]
            missing_gt = [r.source for r in runs if not r.has_ground_truth]
        if n_runs == 0:
            return common.fail("evaluate", f"no valid logs in {args.logs}")
        if missing_gt:
            return common.fail(
                "evaluate",
                f"{len(missing_gt)} logs have no ground truth (first: {missing_gt[0]}); "
                "associate it with `jsve ingest --gt`",
            )
        known = [*meta_columns(metas), *TABLE_COLUMNS]
        unknown = [k for k in by if k not in known]
        if unknown:  # before the replay: a typo costs no evaluation
            return common.fail(
                "evaluate", f"--by keys {unknown} are not metadata of these logs; known: {', '.join(known)}"
            )
        if study is not None:
            per_run = evaluate_rules(iter_buckets(study, dtype=dtype), rules, n_runs=n_runs, **options)
            per_run = in_run_order(per_run, study.file_order(per_run["run_id"]))
        else:
            per_run = evaluate_rules(buckets(runs, dtype=dtype), rules, **options)
    except (ValueError, OSError) as err:  # LogFormatError is a ValueError
        return common.fail("evaluate", err)
    penalty = DEFAULT_FAILURE_PENALTY_M if args.failure_penalty is None else args.failure_penalty
    try:
        summary = aggregate(
            per_run, by, failure_penalty=penalty, support=args.support or "penalise", loss=args.loss
        )
    except ValueError as err:
        return common.fail("evaluate", err)
    if args.output:
        out = Path(args.output)
        with atomic.all_or_nothing():  # the three tables and the record, or none
            atomic.write_table(per_run, out / "runs.parquet")
            atomic.write_table(per_run, out / "runs.csv")
            atomic.write_table(summary, out / "summary.csv")
            write_evaluation_record(_record(args, rules, by, penalty), out)
    print(screen_summary(summary, by, penalty))
    failures = failure_counts(per_run, ["rule"])
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


def _record(args, rules, by: list[str], penalty: float):
    """What the folder records beside its tables (jsve.evaluation.EvaluationRecord): every setting the
    runs were scored with, resolved to its value, and every rule, so that `jsve report DIR` scores and
    describes them as this command did."""
    from jsve.evaluation._record import EvaluationRecord, rule_records

    return EvaluationRecord(
        align=args.align,
        n_to_align=args.n_to_align,
        segments="saved",
        min_coverage=args.min_coverage,
        failure=args.failure,
        loss=args.loss,
        switch_model=args.switch_model or "orbslam3",
        failure_penalty=penalty,
        support=args.support or "penalise",
        by=tuple(by),
        float64=bool(args.x64),
        logs=str(args.logs),
        rules=rule_records(rules, args.rule),
    )


def screen_summary(summary, by: list[str], penalty: float) -> str:
    """The summary as `jsve evaluate` prints it: per group the objective the fit minimises first, then
    what it is made of (failures, runs out of support, coverage, the ATE of the runs that did not fail).
    Never a mean ATE over all runs, which averages a failed run over the part it tracked and can rank
    a rule that fails every run first. Text columns left-aligned, numbers right-aligned.

    Arguments:
        summary: jsve.evaluation.aggregate's table. by: its group columns. penalty: metres per failed run.
    """
    import math

    def pct(x) -> str:
        return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.0f} %"

    def metres(x) -> str:
        return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.4f}"

    def count(x) -> str:
        return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.2g}"

    columns = [
        ("runs", lambda r: str(int(r["n_runs"]))),
        ("objective m", lambda r: metres(r["objective"])),
        ("failed", lambda r: pct(r["failure_rate"])),
        ("unsupported", lambda r: pct(r.get("share_unsupported_runs"))),
        ("coverage", lambda r: pct(r["mean_coverage"])),
        ("ATE ok m", lambda r: metres(r["rmse_mean_nonfailed"])),
        ("n ok", lambda r: str(int(r["n_runs"] - r["n_failed"]))),
        ("resets", lambda r: count(r.get("mean_resets"))),
        ("new maps", lambda r: count(r.get("mean_new_maps"))),
        ("changed", lambda r: pct(r.get("mean_changed"))),
    ]
    rows = [[str(r[k]) for k in by] + [cell(r) for _, cell in columns] for r in summary.to_dict("records")]
    header = [*by, *(name for name, _ in columns)]
    widths = [max(len(h), *(len(row[i]) for row in rows)) if rows else len(h) for i, h in enumerate(header)]
    left = len(by)  # the group keys are text: left-aligned

    def line(cells) -> str:
        return "  ".join(
            c.ljust(w) if i < left else c.rjust(w) for i, (c, w) in enumerate(zip(cells, widths, strict=True))
        ).rstrip()

    legend = (
        f"objective: the mean run loss the fit minimises, m (a run's ATE RMSE on its saved trajectory, "
        f"capped at {penalty:g} m unless --loss raw; {penalty:g} m for a run that failed or left the log's "
        "support); failed, unsupported: share of runs; coverage: mean share of frames in the saved "
        "trajectory; ATE ok: mean ATE RMSE of the n ok runs that did not fail; resets, new maps: per run "
        "(events, not failures); changed: mean share of frames whose replayed state differs from the "
        "logged one"
    )
    return "\n".join([line(header), *(line(row) for row in rows), "", legend])
