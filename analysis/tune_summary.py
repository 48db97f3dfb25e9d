"""The tunings of docs/tuning.md side by side: every finished `jsve tune` folder under OUT, its held-out
check, and the replay's prediction against the front-end per raced candidate, pooled over the tunings.

    python analysis/tune_summary.py OUT [--csv-prefix docs/data/tune]

Prints the tables; with --csv-prefix writes <prefix>_check.csv, <prefix>_agreement.csv and
<prefix>_runs.csv (every run of every tuning, one row each, the tuning named).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pandas as pd
from scipy import stats

FAILURES_APART = (
    "rule_only_lost",
    "baseline_only_lost",
    "lost_p",
    "tracked_pairs",
    "tracked_mean_diff_m",
    "tracked_bca_low_m",
    "tracked_bca_high_m",
)
"""check.csv's columns that test the failures apart and score the pairs both rules tracked."""


def finished(out: Path) -> list[Path]:
    """The folders under OUT holding a finished tuning."""
    found = []
    for path in sorted(out.glob("*/tune.json")):
        if json.loads(path.read_text()).get("status") == "done":
            found.append(path.parent)
    return found


def stacked(folders: list[Path], name: str) -> pd.DataFrame:
    """File `name` of every folder, with the tuning's folder name first."""
    tables = []
    for folder in folders:
        try:
            table = pd.read_csv(folder / name)
        except pd.errors.EmptyDataError:
            continue
        table.insert(0, "tuning", folder.name)
        tables.append(table)
    return pd.concat(tables, ignore_index=True) if tables else pd.DataFrame()


def _spearman(x: pd.Series, y: pd.Series) -> tuple[float, float]:
    """Spearman's rho and its p; NaN for both where either side is constant or there are under 3 pairs
    (the rank correlation is undefined, not 0)."""
    if len(x) < 3 or x.nunique() < 2 or y.nunique() < 2:
        return float("nan"), float("nan")
    result = stats.spearmanr(x, y)
    return float(result.statistic), float(result.pvalue)


def pooled_agreement(agreement: pd.DataFrame) -> dict:
    """Over every raced candidate of every tuning: the predicted - measured difference to the incumbent
    (its mean and spread, metres), Spearman's rho of the two, and on the halves: the prediction made on
    the even seeds against the measurement on the odd ones."""
    if agreement.empty:
        return {"candidates": 0}
    bias = agreement["predicted_diff_m"] - agreement["measured_diff_m"]
    rho, p = _spearman(agreement["predicted_diff_m"], agreement["measured_diff_m"])
    halves, halves_p = _spearman(agreement["predicted_diff_even_m"], agreement["measured_diff_odd_m"])
    return {
        "candidates": len(agreement),
        "bias_mean_m": bias.mean(),
        "bias_sd_m": bias.std(ddof=1),
        "spearman": rho,
        "spearman_p": p,
        "halves_spearman": halves,
        "halves_spearman_p": halves_p,
    }


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out", type=Path)
    parser.add_argument("--csv-prefix", type=Path)
    args = parser.parse_args(argv)
    folders = finished(args.out)
    if not folders:
        print(f"{args.out}: no finished tuning")
        return 1
    check, agreement, runs = (stacked(folders, n) for n in ("check.csv", "agreement.csv", "runs.csv"))
    with pd.option_context("display.width", 220, "display.max_columns", 30):
        keep = ["tuning", "scope", "rule", "baseline", "pairs", "mean_diff_m", "bca_low_m", "bca_high_m"]
        keep += ["t_low_m", "t_high_m", "wilcoxon_p", "better", "worse", "rule_failed", "baseline_failed"]
        keep += [c for c in FAILURES_APART if c in check]
        print(check[keep].to_string(index=False, float_format=lambda x: f"{x:.4g}"))
        print()
        print(agreement.to_string(index=False, float_format=lambda x: f"{x:.4g}"))
    print("\npooled:", json.dumps(pooled_agreement(agreement), default=float))
    print("\nruns per tuning:", runs.groupby("tuning", sort=False).size().to_dict())
    # Tunings share a pool: a run one tuning made, another finds. The machine's cost counts each once.
    # A run is the same run where its log and its recorded wall time are (tunings of other machines'
    # builds write logs of the same paths, with other contents).
    distinct = runs.drop_duplicates(["log", "wall_s"])
    wall, cpu = distinct["wall_s"].dropna(), distinct["cpu_s"].dropna()
    print(f"runs: {len(distinct)} distinct over {len(folders)} tunings ({len(runs)} uses), "
          f"{wall.sum() / 3600:.2f} h of run wall time, {wall.mean():.1f} s wall and {cpu.mean():.1f} s CPU "
          "a run")  # fmt: skip
    if args.csv_prefix:
        args.csv_prefix.parent.mkdir(parents=True, exist_ok=True)
        check.to_csv(f"{args.csv_prefix}_check.csv", index=False)
        agreement.to_csv(f"{args.csv_prefix}_agreement.csv", index=False)
        runs.drop(columns="log").to_csv(f"{args.csv_prefix}_runs.csv", index=False)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
