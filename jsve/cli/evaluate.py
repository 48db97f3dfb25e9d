"""`jsve evaluate LOGS --rule ...`: replay rules over many logs and score them against ground truth.

    jsve evaluate study.parquet --rule orbslam3 --rule sve-option2 --align se3 -o results/

LOGS is a folder of format-v1 logs, a single log, or a Parquet file from `jsve ingest`. Writes
runs.parquet / runs.csv (one row per run and rule) and summary.csv (aggregated by --by), and prints
the summary.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

from jsve.io import _atomic as atomic
from jsve.io._ingest import read_logs, read_parquet
from jsve.io._logs import LogFormatError


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "evaluate", help="replay switching rules over logs and measure their trajectory error",
        description="Replay each rule (a preset name or a JSON file, see docs/state-machine.md) over every "
        "run, align to ground truth and report APE statistics with coverage and failures.",
    )  # fmt: skip
    p.add_argument("logs", metavar="LOGS", help="folder of logs, a log, or a Parquet file from `jsve ingest`")
    p.add_argument("--rule", action="append", metavar="PRESET|params.json",
                   help="orbslam3, sve-eq1, sve-option1, sve-option2, or a rule JSON file; repeatable "
                   "(default: all presets)")  # fmt: skip
    p.add_argument("--align", default="se3", choices=("se3", "sim3", "posyaw", "origin", "none"))
    p.add_argument("--n-to-align", type=int, metavar="N", help="align on the first N evaluated frames only")
    p.add_argument("--segments", default="largest", choices=("largest", "first", "all"),
                   help="which map segment of a run is scored (default: largest)")  # fmt: skip
    p.add_argument("--min-coverage", type=float, default=0.0, help="runs below this coverage count as failed")
    p.add_argument("--by", default="sequence,disturbance,level,rule",
                   help="comma-separated metadata keys to aggregate by (default: %(default)s)")  # fmt: skip
    p.add_argument("--on-error", choices=("raise", "quarantine"), default="raise")
    p.add_argument("-o", "--output", metavar="DIR", help="write runs.parquet, runs.csv and summary.csv here")
    p.add_argument("--workers", type=int, metavar="N")
    p.add_argument("--no-progress", action="store_true")
    p.add_argument("--x64", action="store_true", help="evaluate in float64 (slower; default float32)")
    p.set_defaults(func=run)


def load_rules(names: list[str] | None):
    """(name, Rule) pairs from preset names and JSON files; errors name the file."""
    from jsve.core._rules import PRESETS, preset, rule_from_dict

    pairs = []
    for name in names or list(PRESETS):
        if name in PRESETS:
            pairs.append((name, preset(name)))
            continue
        path = Path(name)
        if not path.is_file():
            raise ValueError(f"--rule {name!r} is neither a preset ({', '.join(PRESETS)}) nor a file")
        try:
            spec = json.loads(path.read_text())
        except json.JSONDecodeError as err:
            raise ValueError(f"{path}:{err.lineno}: not valid JSON: {err.msg}") from None
        pairs.append((path.stem, rule_from_dict(spec, source=str(path))))
    return pairs


def load_runs(source: str, *, on_error: str, workers: int | None, progress: bool):
    """RunLogs from a Parquet file or from logs on disk (quarantined logs reported on stderr)."""
    if source.endswith(".parquet"):
        return read_parquet(source)
    result = read_logs(source, on_error=on_error, workers=workers, progress=progress)
    for q in result.quarantined:
        print(f"jsve evaluate: quarantined {q.message}", file=sys.stderr)
    return result.runs


def run(args) -> int:
    import jax

    if args.x64:
        jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import pandas as pd

    from jsve.evaluation._aggregate import aggregate
    from jsve.evaluation._evaluate import evaluate
    from jsve.io._batching import buckets

    try:
        rules = load_rules(args.rule)
        runs = load_runs(args.logs, on_error=args.on_error, workers=args.workers, progress=not args.no_progress)
    except (ValueError, LogFormatError, OSError) as err:
        print(f"jsve evaluate: {err}", file=sys.stderr)
        return 2
    if not runs:
        print(f"jsve evaluate: no valid logs in {args.logs}", file=sys.stderr)
        return 2
    missing_gt = [r.source for r in runs if not r.has_ground_truth]
    if missing_gt:
        print(f"jsve evaluate: {len(missing_gt)} logs have no ground truth (first: {missing_gt[0]}); "
              "associate it with `jsve ingest --gt`", file=sys.stderr)  # fmt: skip
        return 2
    groups = buckets(runs, dtype=jnp.float64 if args.x64 else jnp.float32)
    tables = [
        evaluate(groups, rule, rule_name=name, align=args.align, n_first=args.n_to_align, segments=args.segments,
                 min_coverage=args.min_coverage, progress=not args.no_progress)
        for name, rule in rules
    ]  # fmt: skip
    per_run = pd.concat(tables, ignore_index=True)
    by = [k for k in args.by.split(",") if k]
    unknown = [k for k in by if k not in per_run.columns]
    if unknown:
        print(f"jsve evaluate: --by keys {unknown} are not metadata of these logs; known: "
              f"{', '.join(map(str, per_run.columns))}", file=sys.stderr)  # fmt: skip
        return 2
    summary = aggregate(per_run, by)
    if args.output:
        out = Path(args.output)
        out.mkdir(parents=True, exist_ok=True)
        atomic.write_table(per_run, out / "runs.parquet")
        atomic.write_table(per_run, out / "runs.csv")
        atomic.write_table(summary, out / "summary.csv")
    shown = by + ["n_runs", "failure_rate", "mean_coverage", "rmse_mean_all", "rmse_median_all", "pooled_rmse_all"]
    with pd.option_context("display.width", 160, "display.max_columns", 20, "display.max_rows", 200):
        print(summary[shown].to_string(index=False, float_format=lambda x: f"{x:.4g}"))
    return 0

