"""The report of a `jsve evaluate -o` folder: every rule replayed on every run, nothing fitted.

    Headline             what was evaluated, the rule with the lowest objective and its paired difference
                         to orbslam3 and sve-option2 (bootstrap over runs), how often it switches, caveats
    Figures              per level (objective, ATE of the runs that kept tracking, failures)
    All runs, per rule   objective with intervals and differences, failures, coverage, switching
    Why runs failed      failure reasons per rule
    Per level            compact tables, details collapsed

The folder records neither a failure penalty nor a support policy, so the objective is the fit's default
(jsve.core._objective: 1 m, penalise) and the run weighting `jsve fit`'s default.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from jsve.core._objective import DEFAULT_FAILURE_PENALTY_M
from jsve.core._rules import BASELINES
from jsve.evaluation import failure_counts
from jsve.fitting import compare
from jsve.report import _derive as derive
from jsve.report._document import Bullets, Section, Table
from jsve.report._format import cm_ci, count, metres, percent, words_list
from jsve.report._tables import OVERVIEW_TEXT, has_levels, level_sections, overview_table, read_table

GROUP_COLUMNS = ("sequence", "disturbance", "level")
"""`jsve fit`'s default run weighting (jsve.fitting._study.StudyConfig.balance_by)."""


def _paired(scored: pd.DataFrame, n_boot: int = 1000) -> pd.DataFrame:
    """Every rule's objective on all runs with a bootstrap interval and its paired difference to each
    baseline present, by jsve.fitting.compare over one "fold kind" holding every run."""
    table = scored.assign(
        run_index=pd.factorize(scored["run_id"])[0]
        if "run_id" in scored
        else scored.groupby("rule").cumcount(),
        fold_kind="all runs",
        failed=scored["objective_failed"],
        unsupported=scored["unsupported_fraction"] > 0 if "unsupported_fraction" in scored else False,
        loss=scored["loss"].where(scored["included"]),
    )
    return compare(table, n_boot=n_boot, seed=0)


def evaluation_sections(out: Path, fig_dir: Path) -> list[Section]:
    """The evaluation's report as sections; the figures are written to `fig_dir`."""
    runs = read_table(out, "runs")
    if runs is None:
        raise FileNotFoundError(f"{out}: no runs.parquet (from `jsve evaluate -o`)")
    scoring = derive.Scoring(
        penalty=DEFAULT_FAILURE_PENALTY_M,
        support="penalise",
        balance_by=tuple(c for c in GROUP_COLUMNS if c in runs.columns),
    )
    scored = derive.scored_runs(runs, scoring)
    overview = derive.rule_overview(scored)
    diffs = _paired(scored)
    rules = list(overview["rule"])
    models = sorted(set(runs["switch_model"].astype(str))) if "switch_model" in runs else []
    best = diffs.sort_values(["mean_loss", "rule"]).iloc[0]
    n_runs = int(runs["run_id"].nunique()) if "run_id" in runs else len(runs) // len(rules)
    listed = words_list(f"`{r}`" for r in rules)
    weighting = (
        f", every ({', '.join(scoring.balance_by)}) group weighted equally" if scoring.balance_by else ""
    )
    head = [
        f"**What was evaluated.** {count(len(rules), 'rule')} ({listed}) replayed by `jsve evaluate` on "
        f"{count(n_runs, 'run')}"
        + (f" under the switch model {words_list(f'`{m}`' for m in models)}" if models else "")
        + "; nothing was fitted. Each rule is scored as `jsve fit` scores it: the mean per-run ATE RMSE, "
        f"a failed run (or one out of the log's support) charged {metres(scoring.penalty)} (jsve's "
        f"default penalty){weighting}."
    ]
    sentences = []
    for base in BASELINES.values():
        key = f"diff_vs_{base}"
        if best["rule"] != base and key in best and pd.notna(best[key]):
            low, high = best[f"{key}_ci_low"], best[f"{key}_ci_high"]
            gap = cm_ci(best[key], low, high, sign=True)
            word = derive.verdict(low, high)
            phrase = {"better": "better than", "worse": "worse than"}.get(word, f"{word} from")
            sentences.append(f"{phrase} `{base}` ({gap} cm)")
    objective = cm_ci(best["mean_loss"], best["ci_low"], best["ci_high"])
    head.append(
        f"**Lowest objective: `{best['rule']}`**, {objective} cm"
        + (f"; {words_list(sentences)}" if sentences else "")
        + ". 95 % paired bootstrap intervals over runs; negative differences are better. The runs are not "
        "held out: a rule fitted on them looks better here than it is."
    )
    o = overview.set_index("rule").loc[best["rule"]]
    if {"rejected", "reached_lost"} <= set(o.index):
        head.append(
            f"**How often it switches.** `{best['rule']}` rejects {percent(o['rejected'])} of frames and "
            f"{percent(o['reached_lost'])} of runs reach LOST; every rule below."
        )
    caveats = [
        "Replayed, not re-run: the replay keeps each frame's logged pose and features; what a rule would "
        "have changed in the front-end itself is for a re-run to say (docs/validation.md).",
        f"The failure penalty ({metres(scoring.penalty)}) sets the exchange rate between failures and error; "
        "`jsve fit --failure-penalty` uses another.",
    ]
    if "unsupported_runs" in o and (o["unsupported_runs"] > 0).any():
        worst = o["unsupported_runs"].idxmax()
        caveats.append(
            f"Support: up to {percent(o.loc[worst, 'unsupported_runs'])} of runs (`{worst}`) leave the logs' "
            "support and count as failed: record with a permissive rule for full support (docs/frontend.md)."
        )
    head += ["**Caveats.**", Bullets(tuple(caveats))]
    sections = [Section("Headline", head)]
    sections.append(
        Section(
            "All runs, per rule",
            [
                OVERVIEW_TEXT,
                Table(overview_table(overview, diffs)),
            ],
        )
    )
    levels = derive.level_table(scored) if has_levels(runs) else None
    level_figure, level_section = level_sections(levels, fig_dir)
    if level_figure:
        sections.insert(1, Section("Figures", level_figure))
    failures = failure_counts(runs, ["rule"]) if "failure_reason" in runs else pd.DataFrame()
    if not failures.empty:
        sections.append(
            Section(
                "Why runs failed",
                [Table(failures.rename(columns={"n_runs": "runs", "failure_reason": "reason"}))],
            )
        )
    if level_section is not None:
        sections.append(level_section)
    return sections
