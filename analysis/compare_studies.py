"""Held-out comparison of the fitted rules of two `jsve fit` studies of the same data.

Two studies of one Parquet study that differ in how they fit (e.g. `--search halving` against
`--search exhaustive`) cross-validate on the same folds (the folds follow the runs' metadata and the
seed), so every held-out run is scored by both studies' fold fits. This script pools their held-out
tables, names each study's fitted rules after the study (`fitted-sve@halving`), and compares them with
jsve.fitting.compare: per fold kind and family, each study's weighted mean held-out loss with a
bootstrap CI over runs, and the paired difference of the second study from the first (negative: the
second is better), plus each study's wall time per stage from its stages.json.

    python analysis/compare_studies.py FIT_A FIT_B --names halving exhaustive [--csv OUT.csv]

Both studies must hold the same runs (their study.json data fingerprints are equal) and have
finished their cross-validation stage.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import pandas as pd

from jsve.fitting import compare


def _study(path: Path) -> dict:
    study = json.loads((path / "study.json").read_text())
    stages = json.loads((path / "stages.json").read_text()).get("done", {})
    if "cross_validation" not in stages:
        raise SystemExit(f"{path}: the cross-validation stage has not finished")
    return {"study": study, "stages": stages}


def pooled_heldout(folders: list[Path], names: list[str]) -> pd.DataFrame:
    """Both studies' held-out rows of their fitted rules, each rule named `<rule>@<study name>`."""
    tables = []
    for folder, name in zip(folders, names, strict=True):
        held = pd.read_parquet(folder / "heldout.parquet")
        fitted = held[held["rule"].str.startswith("fitted-")].copy()
        fitted["rule"] = fitted["rule"] + "@" + name
        tables.append(fitted)
    return pd.concat(tables, ignore_index=True)


def comparison(folders: list[Path], names: list[str], *, n_boot: int = 2000, seed: int = 0) -> pd.DataFrame:
    """Per fold kind and fitted rule of either study: mean held-out loss [CI], and for the second study's
    rules the paired difference from the first study's rule of the same family [CI]."""
    held = pooled_heldout(folders, names)
    families = sorted({r.split("@")[0] for r in held["rule"]})
    rows = []
    for family in families:
        part = held[held["rule"].str.split("@").str[0] == family]
        base = f"{family}@{names[0]}"
        table = compare(part, baselines=[base], n_boot=n_boot, seed=seed)
        renamed = {c: c.replace(base, names[0]) for c in table.columns if c.startswith(f"diff_vs_{base}")}
        rows.append(table.rename(columns=renamed))
    return pd.concat(rows, ignore_index=True)


def main(argv=None) -> int:
    raw = argparse.RawDescriptionHelpFormatter
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=raw)
    parser.add_argument("folders", nargs=2, type=Path, help="two `jsve fit` output folders")
    parser.add_argument("--names", nargs=2, default=["a", "b"], help="a short name for each study")
    parser.add_argument("--csv", type=Path, help="also write the comparison table here")
    parser.add_argument("--n-boot", type=int, default=2000)
    args = parser.parse_args(argv)
    studies = [_study(f) for f in args.folders]
    prints = {s["study"].get("data_fingerprint") for s in studies}
    if len(prints) != 1:
        raise SystemExit(f"the studies hold different data (fingerprints {sorted(map(str, prints))})")
    table = comparison(list(args.folders), list(args.names), n_boot=args.n_boot)
    pd.set_option("display.width", 200)
    pd.set_option("display.max_columns", 20)
    first = ("fold_kind", "rule", "n_runs", "mean_loss", "ci_low", "ci_high")
    cols = [c for c in table.columns if c in first]
    cols += [c for c in table.columns if c.startswith("diff_vs_")]
    print(table[cols].to_string(index=False, float_format=lambda x: f"{x:.4f}"))
    print()
    for name, s in zip(args.names, studies, strict=True):
        stages = s["stages"]
        total = sum(v.get("seconds", 0.0) for v in stages.values())
        parts = ", ".join(f"{k} {v.get('seconds', 0.0):.0f} s" for k, v in stages.items())
        peak = max((v.get("peak_rss_gb") or 0.0) for v in stages.values())
        print(f"{name}: {total / 60:.1f} min of stages ({parts}); peak RSS {peak:.2f} GB" if peak else
              f"{name}: {total / 60:.1f} min of stages ({parts})")  # fmt: skip
    if args.csv:
        table.to_csv(args.csv, index=False)
    return 0


if __name__ == "__main__":
    sys.exit(main())
