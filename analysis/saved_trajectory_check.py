"""Real ORB-SLAM3 logs scored three ways: `jsve ape` of ORB-SLAM3's own saved file, jsve's score of
the log under its own rule (the saved trajectory rebuilt from the log, failures by coverage, bounded
loss), and the score jsve gave before it read the saved trajectory (the logged online poses, a run failed
at its first loss of tracking, raw loss).

    python analysis/saved_trajectory_check.py LOGDIR --gt SEQUENCE=GT.csv [--gt ...] [-o table.csv]

LOGDIR is `jsve frontend run`'s output (format-v3 logs beside their `*.orbslam3-euroc.txt`); each GT is a
EuRoC ground truth (state_groundtruth_estimate0/data.csv) of the sequence the logs' metadata names. One
row per log: its events, the saved trajectory's coverage, failed, the three ATEs (m) and the largest
difference between the first two (docs/state-machine.md, "Scoring a run").
"""

from __future__ import annotations

import argparse
from pathlib import Path

import jax
import numpy as np
import pandas as pd

import jsve
from jsve.evaluation import own_rule_table
from jsve.io import euroc_ate, event_counts


def online_only(run: jsve.RunLog) -> jsve.RunLog:
    """The log without what format v3 adds (keyframe columns, trailer): its online poses only."""
    frames = run.frames.drop(columns=[c for c in jsve.io.schema.KEYFRAME_COLUMNS if c in run.frames])
    return jsve.RunLog(meta=run.meta, frames=frames, source=run.source)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("logdir", type=Path)
    parser.add_argument("--gt", action="append", required=True, metavar="SEQUENCE=FILE")
    parser.add_argument("-o", "--output", type=Path)
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    gts = dict(item.split("=", 1) for item in args.gt)
    paths = sorted(p for p in args.logdir.rglob("run_*.csv"))
    runs = [jsve.io.read_log(p) for p in paths]
    runs = [jsve.associate_ground_truth(r, gts[r.meta["sequence"]]) for r in runs]
    new = own_rule_table(runs)
    old = own_rule_table([online_only(r) for r in runs], failure="strict", min_coverage=0.0)
    old_loss = np.where(old["failed"], np.nan, old["rmse"])
    rows = []
    for path, run, n, o in zip(paths, runs, new.itertuples(), old_loss, strict=True):
        saved_file = Path(f"{path.with_suffix('')}.orbslam3-euroc.txt")
        gt = gts[run.meta["sequence"]]
        file_ate = euroc_ate(gt, saved_file)[0] if saved_file.is_file() else np.nan
        events = {k: v for k, v in event_counts(run).items() if k in ("reset", "new_map", "merge", "loop")}
        rows.append(
            {
                "log": str(path.relative_to(args.logdir)),
                **events,
                "coverage": n.coverage,
                "failed": n.failed,
                "ate_saved_file_m": file_ate,
                "ate_jsve_m": n.rmse,
                "difference_m": abs(file_ate - n.rmse) if np.isfinite(file_ate) else np.nan,
                "ate_online_strict_m": o,  # NaN: failed under the earlier scoring
            }
        )
    table = pd.DataFrame(rows)
    with pd.option_context("display.width", 200, "display.max_columns", 20):
        print(table.to_string(index=False, float_format=lambda x: f"{x:.6g}"))
    finite = table["difference_m"].dropna()
    print(
        f"\nlargest |ATE jsve - ATE saved file|: {finite.max():.3g} m over {len(finite)} logs with a saved"
        " file"
    )
    if args.output:
        table.to_csv(args.output, index=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
