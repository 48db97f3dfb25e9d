"""The report of a `jsve evaluate -o` folder: every rule replayed on every run, nothing fitted.

    Headline             what was evaluated, the rule with the lowest objective and its paired difference
                         to orbslam3 and sve-option2 (bootstrap over runs), how often it switches, caveats
    Figures              per level (objective, ATE of the runs that kept tracking, failures)
    All runs, per rule   objective with intervals and differences, failures, coverage, switching
    Why runs failed      failure reasons per rule
    Per level            compact tables, details collapsed

    Method               how the runs were scored (alignment, penalty, switch model, support) and the
                         rules with their parameters, from the folder's evaluation.json

The objective uses the failure penalty and support policy `jsve evaluate` recorded in evaluation.json
(jsve.evaluation.EvaluationRecord); a folder written before the record existed is scored with the fit's
defaults (jsve.core._objective: 1 m, penalise) and says so. Runs are weighted as `jsve fit` weighs them.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from jsve.core._objective import DEFAULT_FAILURE_PENALTY_M
from jsve.core._rules import BASELINES, RULE_KINDS, param_names
from jsve.evaluation import failure_counts
from jsve.evaluation._record import EvaluationRecord, read_evaluation_record
from jsve.fitting import compare
from jsve.report import _derive as derive
from jsve.report._document import Bullets, Section, Sub, Table
from jsve.report._format import cm_ci, count, metres, number, percent, words_list
from jsve.report._tables import (
    ALIGN_TEXT,
    OVERVIEW_TEXT,
    has_levels,
    level_sections,
    overview_table,
    read_table,
    scoring_bullets,
)

GROUP_COLUMNS = ("sequence", "disturbance", "level")
"""`jsve fit`'s default run weighting (jsve.fitting._config.StudyConfig.balance_by)."""


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


def _scoring(record: EvaluationRecord | None, runs: pd.DataFrame) -> derive.Scoring:
    """The penalty and support policy `jsve evaluate` recorded (jsve's defaults for a folder without a
    record), runs weighted as `jsve fit` weighs them."""
    return derive.Scoring(
        penalty=record.failure_penalty if record else DEFAULT_FAILURE_PENALTY_M,
        support=record.support if record else "penalise",
        balance_by=tuple(c for c in GROUP_COLUMNS if c in runs.columns),
        loss=record.loss if record else "bounded",
        failure=record.failure if record else "coverage",
    )


def _scored_as(scoring: derive.Scoring, recorded: bool) -> str:
    """How a run's loss is counted, in words, and where the settings come from."""
    if scoring.support == "exclude":
        loss = (
            f"the mean per-run ATE RMSE, a failed run charged {metres(scoring.penalty)}, a run out of the "
            "log's support left out of its rule's mean"
        )
    else:
        loss = (
            "the mean per-run ATE RMSE, a failed run (or one out of the log's support) charged "
            f"{metres(scoring.penalty)}"
        )
    lead = "Each rule is scored as `jsve fit` scores it"
    if recorded:
        return f"{lead}, with the settings `jsve evaluate` recorded: {loss}"
    return f"{lead}: {loss} (jsve's default penalty: the folder records none)"


def _parameters(table: dict, kind: str) -> str:
    """A rule part's parameters as "imu_init 15, not_init 50, ..." (4 significant digits), in the rule's
    parameter order (jsve.core.param_names), static fields such as `inputs` last."""
    order = param_names(kind) if kind in RULE_KINDS else ()
    keys = sorted(table, key=lambda k: order.index(k) if k in order else len(order))
    return ", ".join(f"{k} {number(table[k]) if isinstance(table[k], float) else table[k]}" for k in keys)


def rules_table(record: EvaluationRecord) -> pd.DataFrame:
    """Every rule evaluated: its name, where it came from (a preset or the rule file), its family and its
    parameters, one column per part of the rule (jsve.core.rule_to_dict: thresholds, combination)."""
    rows = []
    for r in record.rules:
        row = {"rule": r.name, "from": r.file or "preset", "kind": r.rule.get("kind", "-")}
        for part, table in r.rule.items():
            if isinstance(table, dict):
                row[part] = _parameters(table, row["kind"])
        rows.append(row)
    return pd.DataFrame(rows).fillna("-")


RULES_TEXT = (
    "Thresholds are in the rule's score units: tracked inliers for `inliers` rules, the SVE score (0 to 1) "
    "for `sve` rules (docs/sve.md); a rule file's name is its stem."
)


def _method(record: EvaluationRecord | None, scoring: derive.Scoring, models: list[str]) -> Section:
    """How the runs were scored and which rules, from evaluation.json; without it, what is assumed."""
    if record is None:
        items = scoring_bullets(
            scoring,
            align="se3",
            min_coverage=0.0,
            switch_model=models[0] if len(models) == 1 else None,
            support=scoring.support,
        )
        note = (
            "This folder has no evaluation.json (written before `jsve evaluate -o` recorded its settings): "
            f"the runs are scored with jsve's defaults ({metres(scoring.penalty)}, `{scoring.support}`), and "
            "the alignment, coverage floor and rules are not known beyond the tables."
        )
        return Section("Method", [note, Bullets(tuple(items))])
    items = scoring_bullets(
        scoring,
        align=record.align,
        min_coverage=record.min_coverage,
        switch_model=record.switch_model,
        support=record.support,
    )
    if record.n_to_align:
        items.append(f"Alignment on the first {count(record.n_to_align, 'evaluated frame')} of each segment.")
    items.append(f"Segments scored: {SEGMENTS_TEXT.get(record.segments, record.segments)}.")
    items.append(
        f"Replayed in {'float64' if record.float64 else 'float32'} by `jsve evaluate` on {record.logs or '-'}"
        + (f"; summary.csv aggregated by {', '.join(record.by)}." if record.by else ".")
    )
    blocks: list = [Bullets(tuple(items))]
    if record.rules:
        blocks += [Sub("Rules"), RULES_TEXT, Table(rules_table(record))]
    return Section("Method", blocks)


SEGMENTS_TEXT = {
    "saved": "the trajectory the front-end saves: its saved map's frames (docs/state-machine.md)",
    "largest": "each run's largest map segment (the one with most evaluable frames)",
    "first": "each run's first map segment",
    "all": "every map segment of a run, each aligned on its own, errors pooled",
}
"""jsve.core._trajectory.SEGMENT_MODES in words."""


def evaluation_sections(out: Path, fig_dir: Path) -> list[Section]:
    """The evaluation's report as sections; the figures are written to `fig_dir`.

    Raises:
        FileNotFoundError: no runs.parquet. ValueError: an evaluation.json that is not a record.
    """
    runs = read_table(out, "runs")
    if runs is None:
        raise FileNotFoundError(f"{out}: no runs.parquet (from `jsve evaluate -o`)")
    record = read_evaluation_record(out)
    scoring = _scoring(record, runs)
    scored = derive.scored_runs(runs, scoring)
    overview = derive.rule_overview(scored)
    diffs = _paired(scored)
    rules = list(overview["rule"])
    if record is not None:
        models = [record.switch_model]
    else:
        models = sorted(set(runs["switch_model"].astype(str))) if "switch_model" in runs else []
    best = diffs.sort_values(["mean_loss", "rule"]).iloc[0]
    n_runs = int(runs["run_id"].nunique()) if "run_id" in runs else len(runs) // len(rules)
    listed = words_list(f"`{r}`" for r in rules)
    weighting = (
        f", every ({', '.join(scoring.balance_by)}) group weighted equally" if scoring.balance_by else ""
    )
    aligned = f" and {ALIGN_TEXT.get(record.align, record.align)} alignment" if record else ""
    head = [
        f"**What was evaluated.** {count(len(rules), 'rule')} ({listed}) replayed by `jsve evaluate` on "
        f"{count(n_runs, 'run')}"
        + (f" under the switch model {words_list(f'`{m}`' for m in models)}{aligned}" if models else "")
        + "; nothing was fitted. "
        f"{_scored_as(scoring, record is not None)}{weighting}."
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
        "`jsve evaluate --failure-penalty` and `jsve fit --failure-penalty` set another.",
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
    sections.append(_method(record, scoring, models))
    return sections
