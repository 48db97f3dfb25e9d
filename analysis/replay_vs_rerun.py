"""Does the replay predict the re-run? Replay every recording under every rule and compare with the
rules' own runs of the real front-end (issue 11; jsve.evaluation._agreement has the statistics).

    python analysis/replay_vs_rerun.py LOGDIR --ground-truth V101=GT.csv [--rules orbslam3,sve-option2,...]
        [--penalty 1.0] [-o OUTDIR]

LOGDIR is `jsve frontend run`'s output over one or more rules and switch models
(LOGDIR/<sequence>/<disturbance>-<level>[/<rule>-<model>]/run_<k>.csv). Every finished log is a
recording: it is replayed under each rule of --rules (default: every rule that has runs of its own in
LOGDIR) and each switch model that has runs. A rule's own runs are its re-runs, scored by replaying
them under their own rule (jsve check shows that this reproduces the logged states). A run that
ORB-SLAM3 crashed in (its summary's exit code is not 0; the log stays `.partial`) is a failed re-run,
counted. Writes OUTDIR/agreement.csv (per setting, rule, switch model and recording kind),
OUTDIR/ranking.csv (per level: Kendall tau, regret@1), OUTDIR/unmatched.csv, and prints them.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import pandas as pd

from jsve.evaluation import SETTING, agreement_table, evaluate, ranking_table, unmatched
from jsve.io import GroundTruth, buckets, load_rules, read_logs, recorded_rule_label

KEYS = [*SETTING, "rule", "switch_model"]


def recording_label(meta: dict) -> str:
    """The rule and switch model a run ran under, e.g. `orbslam3-orbslam3`, `record-imu-coast`."""
    return recorded_rule_label(meta) or "orbslam3-orbslam3"


def crashed_runs(logdir: Path) -> pd.DataFrame:
    """Re-runs ORB-SLAM3 crashed in: failed, no error, no coverage (from the runs' summaries)."""
    rows = []
    for summary in sorted(logdir.rglob("*.summary.json")):
        info = json.loads(summary.read_text())
        if info.get("exit_code", 0) == 0:
            continue
        # the summary's folder, not its `log` (a path relative to where the run was started)
        parts = summary.parent.relative_to(logdir).parts
        disturbance, _, level = parts[1].rpartition("-")
        label = parts[2] if len(parts) > 2 else "orbslam3-orbslam3"
        rows.append({"sequence": parts[0], "disturbance": disturbance, "level": float(level), "label": label,
                     "rmse": float("nan"), "failed": True, "coverage": 0.0})  # fmt: skip
    return pd.DataFrame(rows)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("logs", metavar="LOGDIR", type=Path)
    parser.add_argument("--ground-truth", action="append", required=True, metavar="SEQUENCE=FILE",
                        help="EuRoC ground truth of a sequence (repeatable)")  # fmt: skip
    parser.add_argument("--rules", help="comma-separated presets or rule JSON files (default: the rules run)")
    parser.add_argument("--penalty", type=float, default=1.0, help="loss of a failed run, m (default 1)")
    parser.add_argument("-o", "--output", type=Path, default=Path("replay_vs_rerun"), help="output folder")
    args = parser.parse_args(argv)
    gt = {k: GroundTruth(v, fmt="euroc") for k, v in (s.split("=", 1) for s in args.ground_truth)}
    runs = read_logs(args.logs, ground_truth=gt, on_error="quarantine", progress=False).runs
    labels = [recording_label(r.meta) for r in runs]
    names = (
        args.rules.split(",") if args.rules else sorted({r.meta.get("rule_name", "orbslam3") for r in runs})
    )
    rules = load_rules([n for n in names if n != "record"])
    models = sorted({r.meta.get("switch_model", "orbslam3") for r in runs})
    bucketed = buckets(runs)
    replayed, reruns = [], []
    for model in models:
        for name, rule in rules:
            table = evaluate(bucketed, rule, rule_name=name, switch_model=model, progress=False)
            table["recording"] = labels_in(table, runs, labels)
            own = table["recording"] == f"{name}-{model}"
            reruns.append(table[own])
            replayed.append(
                table.assign(
                    kind=table["recording"].where(table["recording"].str.startswith("record"), "rule")
                )
            )
    replayed_t, reruns_t = pd.concat(replayed), pd.concat(reruns)
    crashed = crashed_runs(args.logs)
    if len(crashed):
        split = crashed["label"].str.rpartition("-")
        crashed = crashed.assign(rule=split[0], switch_model=split[2])
        reruns_t = pd.concat([reruns_t, crashed[crashed["rule"].isin([n for n, _ in rules])]])
    args.output.mkdir(parents=True, exist_ok=True)
    tables = {}
    for kind, part in replayed_t.groupby("kind"):
        tables[kind] = agreement_table(part, reruns_t, KEYS, args.penalty).assign(recording=kind)
    agreement = pd.concat(tables.values(), ignore_index=True)
    ranking = pd.concat(
        [ranking_table(t, [*SETTING, "switch_model"]).assign(recording=k) for k, t in tables.items()],
        ignore_index=True,
    )
    missing = unmatched(replayed_t, reruns_t, KEYS)
    agreement.to_csv(args.output / "agreement.csv", index=False)
    ranking.to_csv(args.output / "ranking.csv", index=False)
    missing.to_csv(args.output / "unmatched.csv", index=False)
    with pd.option_context("display.width", 200, "display.max_columns", 30):
        print(agreement.round(4).to_string(index=False))
        print(ranking.round(4).to_string(index=False))
        if len(missing):
            print(f"{len(missing)} settings without the other side (unmatched.csv):")
            print(missing.to_string(index=False))
    return 0


def labels_in(table: pd.DataFrame, runs, labels) -> list[str]:
    """The recording label of each row of an evaluate table (rows follow the runs' `source`)."""
    by_source = {r.source: label for r, label in zip(runs, labels, strict=True)}
    return [by_source[s] for s in table["source"]]


if __name__ == "__main__":
    sys.exit(main())
